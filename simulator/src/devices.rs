//! Simulated devices implementing the `gonio-devices` traits: axes with trapezoidal
//! motion on the [`SimClock`], a lamp, and a camera that renders the sample at the pose
//! the axes are actually in.

use crate::clock::SimClock;
use crate::render::{key_bits, PointLight, RawView, Renderer, TruthView, ViewCache};
use crate::sensor::SensorModel;
use async_trait::async_trait;
use gonio_devices::axis::check_limits;
use gonio_devices::image::RgbImage;
use gonio_devices::kinematics::{self, Kinematics};
use gonio_devices::rig::RigSpec;
use gonio_devices::{
    Axis, AxisStatus, Camera, CameraConfig, DeviceError, Frame, FrameMeta, Intrinsics, Light, MotionModel, SoftLimits,
    Vec3,
};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

struct AxisState {
    homed: bool,
    start: f64,
    target: f64,
    t_start: f64,
    t_end: f64,
    /// Cruise velocity of the current move: the axis' maximum, or what a fly-scan asked for
    /// (`start_move_at`).
    velocity: f64,
    /// How late the stage follows the current move's profile (s): the injected lag of a
    /// velocity-commanded move ([`SimAxis::with_flight_lag`]), 0 otherwise.
    lag: f64,
    /// The phases of a profiled move (`start_trajectory`): the position follows them
    /// instead of the trapezoid.
    trajectory: Option<Arc<gonio_devices::Trajectory>>,
}

/// A simulated motor stage.
pub struct SimAxis {
    name: String,
    limits: SoftLimits,
    motion: MotionModel,
    clock: Arc<SimClock>,
    state: Mutex<AxisState>,
    /// Opt-in mechanical error model (rig file `options.mechanical`): the load side then
    /// differs from the read-back. `None`: the load is exactly where the motor is.
    mech: Option<Mutex<crate::mechanics::MechanicalState>>,
    /// Injected fault (rig file axis `options.flight_lag_s`): a velocity-commanded move
    /// trails its profile by this many seconds, as a stage with a following error does, so
    /// a flown frame is exposed behind its planned pose. Stop-and-go moves are unaffected.
    flight_lag: f64,
}

impl SimAxis {
    pub fn new(name: &str, limits: SoftLimits, motion: MotionModel, clock: Arc<SimClock>) -> Self {
        SimAxis {
            name: name.into(),
            limits,
            motion,
            clock,
            state: Mutex::new(AxisState {
                homed: false,
                start: 0.0,
                target: 0.0,
                t_start: 0.0,
                t_end: 0.0,
                velocity: motion.max_velocity,
                lag: 0.0,
                trajectory: None,
            }),
            mech: None,
            flight_lag: 0.0,
        }
    }

    /// Give the axis a mechanical error model (see [`crate::mechanics`]); `None` keeps it ideal.
    pub fn with_mechanics(mut self, model: Option<crate::mechanics::MechanicalErrors>) -> Self {
        self.mech = model.map(|m| Mutex::new(crate::mechanics::MechanicalState::new(m)));
        self
    }

    /// Give velocity-commanded moves a lag (see the field); 0 keeps the stage on its profile.
    pub fn with_flight_lag(mut self, lag_s: f64) -> Self {
        self.flight_lag = lag_s.max(0.0);
        self
    }

    /// The mechanical error model, if the axis has one.
    pub fn mechanics(&self) -> Option<crate::mechanics::MechanicalErrors> {
        self.mech
            .as_ref()
            .map(|m| m.lock().expect("axis mechanics poisoned").model)
    }

    /// Zero offsets (degrees) drawn at every homing so far: the truth for homing repeatability.
    pub fn home_offsets_deg(&self) -> Vec<f64> {
        self.mech
            .as_ref()
            .map(|m| m.lock().expect("axis mechanics poisoned").home_offsets().to_vec())
            .unwrap_or_default()
    }

    /// Where the load really is now (radians): the read-back plus backlash, homing offset
    /// and positioning error. What the simulated camera sees and a load-side encoder reads.
    pub fn load_position_now(&self) -> f64 {
        self.load_position_at(self.clock.now())
    }

    /// Where the load is at rig time `t` along the current move (the moment of a sub-frame
    /// of a flown exposure); [`SimAxis::load_position_now`] at `t = now`.
    pub fn load_position_at(&self, t: f64) -> f64 {
        let p = self.position_at(t);
        match &self.mech {
            None => p,
            Some(m) => {
                let m = m.lock().expect("axis mechanics poisoned");
                if m.model.is_zero() {
                    p
                } else {
                    m.true_deg(p.to_degrees()).to_radians()
                }
            }
        }
    }

    fn mech_fold(&self, motor: f64) {
        if let Some(m) = &self.mech {
            m.lock().expect("axis mechanics poisoned").fold(motor.to_degrees());
        }
    }

    /// Start a move along a trapezoid cruising at `velocity` (capped at the axis' maximum),
    /// trailing it by `lag` seconds.
    fn start_profile(&self, target: f64, velocity: f64, lag: f64) -> Result<(), DeviceError> {
        check_limits(&self.name, self.limits, target, "move_abs")?;
        if !(velocity.is_finite() && velocity > 0.0) {
            return Err(DeviceError::Rejected {
                device: self.name.clone(),
                command: format!("start_move_at {target} {velocity}"),
                reason: "the velocity must be > 0".into(),
            });
        }
        let velocity = velocity.min(self.motion.max_velocity);
        let motion = MotionModel {
            max_velocity: velocity,
            ..self.motion
        };
        self.begin_move("move_abs", |from, now| AxisState {
            homed: true,
            start: from,
            target,
            t_start: now,
            t_end: now + motion.move_time(target - from) + lag,
            velocity,
            lag,
            trajectory: None,
        })
    }

    /// The start every move shares: fold the mechanics at the current position, refuse an
    /// axis that is not homed (naming `command`), then set the move `state(from, now)`.
    fn begin_move(&self, command: &str, state: impl FnOnce(f64, f64) -> AxisState) -> Result<(), DeviceError> {
        let from = self.position_now();
        self.mech_fold(from);
        let now = self.clock.now();
        let mut s = self.state.lock().expect("axis state poisoned");
        if !s.homed {
            return Err(DeviceError::NotHomed {
                device: self.name.clone(),
                command: command.into(),
            });
        }
        *s = state(from, now);
        Ok(())
    }

    /// Position now (interpolated along the profile while moving). A finished move is at
    /// its target exactly: `start + (target − start)` can miss it in the last bit, and
    /// then where an axis ends would depend on where it came from, so the same pose
    /// reached from two directions (a resumed run, a shard) would read back, and render,
    /// differently.
    pub fn position_now(&self) -> f64 {
        self.position_at(self.clock.now())
    }

    /// The read-back at rig time `t` along the current move.
    pub fn position_at(&self, t: f64) -> f64 {
        let s = self.state.lock().expect("axis state poisoned");
        let t = t - s.t_start - s.lag;
        if let Some(tr) = &s.trajectory {
            // Past its last knot the trajectory is at its target exactly.
            return tr.position_at(t);
        }
        let d = s.target - s.start;
        let motion = MotionModel {
            max_velocity: s.velocity,
            ..self.motion
        };
        let p = motion.position_at(d, t);
        if p == d {
            s.target
        } else {
            s.start + p
        }
    }
}

#[async_trait]
impl Axis for SimAxis {
    fn name(&self) -> &str {
        &self.name
    }
    fn limits(&self) -> SoftLimits {
        self.limits
    }
    fn motion(&self) -> MotionModel {
        self.motion
    }
    async fn home(&self) -> Result<(), DeviceError> {
        let from = self.position_now();
        let dt = self.motion.move_time(from);
        let end = self.clock.now() + dt;
        self.clock.wait_until(end).await;
        let mut s = self.state.lock().expect("axis state poisoned");
        *s = AxisState {
            homed: true,
            start: 0.0,
            target: 0.0,
            t_start: end,
            t_end: end,
            velocity: self.motion.max_velocity,
            lag: 0.0,
            trajectory: None,
        };
        drop(s);
        if let Some(m) = &self.mech {
            m.lock().expect("axis mechanics poisoned").home();
        }
        Ok(())
    }
    async fn start_move(&self, target: f64) -> Result<(), DeviceError> {
        self.start_profile(target, self.motion.max_velocity, 0.0)
    }
    async fn start_move_at(&self, target: f64, velocity: f64) -> Result<(), DeviceError> {
        self.start_profile(target, velocity, self.flight_lag)
    }
    async fn start_trajectory(&self, trajectory: &gonio_devices::Trajectory) -> Result<(), DeviceError> {
        for k in &trajectory.knots {
            check_limits(&self.name, self.limits, k.x, "start_trajectory")?;
        }
        let m = self.motion;
        let fast = trajectory
            .knots
            .iter()
            .any(|k| k.v.abs() > m.max_velocity * (1.0 + 1e-9) || k.a.abs() > m.acceleration * (1.0 + 1e-9));
        if fast || !(trajectory.end.is_finite() && trajectory.end >= 0.0) {
            return Err(DeviceError::Rejected {
                device: self.name.clone(),
                command: "start_trajectory".into(),
                reason: "the profile exceeds the axis' velocity or acceleration".into(),
            });
        }
        self.begin_move("start_trajectory", |from, now| AxisState {
            homed: true,
            start: from,
            target: trajectory.target(),
            t_start: now,
            t_end: now + trajectory.end + self.flight_lag,
            velocity: m.max_velocity,
            lag: self.flight_lag,
            trajectory: Some(Arc::new(trajectory.clone())),
        })
    }
    async fn wait_idle(&self) -> Result<f64, DeviceError> {
        let end = self.state.lock().expect("axis state poisoned").t_end;
        self.clock.wait_until(end).await;
        Ok(self.position_now())
    }
    async fn stop(&self) -> Result<(), DeviceError> {
        let p = self.position_now();
        self.mech_fold(p);
        let now = self.clock.now();
        let mut s = self.state.lock().expect("axis state poisoned");
        s.start = p;
        s.target = p;
        s.t_start = now;
        s.t_end = now;
        s.velocity = self.motion.max_velocity;
        s.lag = 0.0;
        s.trajectory = None;
        Ok(())
    }
    async fn position(&self) -> Result<f64, DeviceError> {
        Ok(self.position_now())
    }
    async fn reference_position(&self) -> Result<Option<f64>, DeviceError> {
        let encoder = self
            .mech
            .as_ref()
            .is_some_and(|m| m.lock().expect("axis mechanics poisoned").model.encoder);
        Ok(encoder.then(|| self.load_position_now()))
    }
    async fn status(&self) -> Result<AxisStatus, DeviceError> {
        let homed = self.state.lock().expect("axis state poisoned").homed;
        let t_end = self.state.lock().expect("axis state poisoned").t_end;
        Ok(AxisStatus {
            homed,
            moving: self.clock.now() < t_end,
            position: self.position_now(),
        })
    }
}

/// A simulated lamp.
pub struct SimLight {
    state: Mutex<(bool, f64)>,
    /// Nominal voltage and current at full intensity, reported as the read-back when the
    /// rig file gives them (`light.options.voltage`, `current`); `None`: measures nothing.
    nominal: Option<gonio_devices::LampReading>,
    /// Output drift per hour of rig time (`light.options.drift_per_hour`; 0: none): the
    /// radiant intensity is multiplied by 1 + drift × hours. The read-back does not follow.
    drift_per_hour: f64,
}

#[async_trait]
impl Light for SimLight {
    fn name(&self) -> &str {
        "sim-light"
    }
    async fn set(&self, on: bool, intensity: f64) -> Result<(), DeviceError> {
        if !(0.0..=1.0).contains(&intensity) {
            return Err(DeviceError::Rejected {
                device: "sim-light".into(),
                command: format!("set intensity {intensity}"),
                reason: "intensity must be in [0, 1]".into(),
            });
        }
        *self.state.lock().expect("light poisoned") = (on, intensity);
        Ok(())
    }
    /// The nominal values scaled by the intensity (0 when off), if the rig file gave them.
    async fn read_back(&self) -> Result<Option<gonio_devices::LampReading>, DeviceError> {
        let (on, k) = *self.state.lock().expect("light poisoned");
        let k = if on { k } else { 0.0 };
        Ok(self.nominal.map(|n| gonio_devices::LampReading {
            voltage_v: n.voltage_v * k,
            current_a: n.current_a * k,
        }))
    }
}

/// Everything the simulated camera needs to know about the world.
pub struct SimWorld {
    pub axes: Vec<Arc<SimAxis>>,
    pub kinematics: Box<dyn Kinematics>,
    pub renderer: Arc<Renderer>,
    pub light: Arc<SimLight>,
    pub light_intensity_w_sr: f64,
    /// Radius of the lamp's disc (rig file `light.options.radius_mm`; 0 = point lamp).
    pub lamp_radius_mm: f64,
    pub intrinsics: Intrinsics,
    pub sensor: Mutex<SensorModel>,
    pub clock: Arc<SimClock>,
    pub readout_s: f64,
    /// The readout overlaps what follows (rig file `camera.options.overlap_readout`, on by
    /// default; [`gonio_devices::rig::CameraSpec::readout_overlaps_motion`]): `capture`
    /// returns when the exposure ends, so the axes may move on, and the sensor stays busy
    /// until [`SimWorld::sensor_free_at`].
    pub overlap_readout: bool,
    /// Rig-clock time the sensor finishes reading out the last frame: the next exposure
    /// starts no earlier.
    pub sensor_free_at: Mutex<f64>,
    pub width: usize,
    pub height: usize,
    pub roi: Roi,
    /// Lens distortion of the simulated camera (zero = ideal pinhole).
    pub lens: crate::render::LensDistortion,
    /// Non-linear response and colour crosstalk (rig file `camera.options`
    /// `response_compression`, `crosstalk`); `None` = the linear colour-clean default.
    pub response: Option<crate::sensor::SensorResponse>,
    /// Independent noise in every frame (`camera.options.frame_noise = true`), as a real
    /// camera has; default: noise seeded by the measurement's identity (see
    /// [`noise_key`]), so a resumed acquisition is reproducible — but then repeated frames
    /// of one pose outside a measurement (dark and flat frames) are equal.
    pub frame_noise: bool,
    /// Traced truth views of recent camera positions ([`SimWorld::truth`] shades them).
    pub truth_views: ViewCache<TruthView>,
    /// Traced raw frames of recent camera poses ([`SimWorld::raw_radiance`] shades them).
    pub raw_views: ViewCache<RawView>,
}

/// Camera positions whose traced truth view [`SimWorld::truth`] keeps (see
/// [`ViewCache`]): ≈ 6 MiB each at 256² texels with one ray per texel. On the default
/// rig's Bonn tour (183 distinct camera poses, revisited along the tour) 8 views answer
/// 94 % of the pairs from the cache.
pub const TRUTH_VIEW_CACHE: usize = 8;
/// Bytes the cached truth views may hold together (the newest is always kept): 8 views of
/// 256² texels with one ray per texel fit; a sample whose truth takes 16 rays per texel
/// (`truth_rays_per_cell = 4`, ≈ 80 MiB per view) keeps one.
pub const TRUTH_VIEW_BUDGET: usize = 64 << 20;
/// Camera poses whose traced raw frame [`SimWorld::raw_radiance`] keeps (see
/// [`ViewCache`]): about 100 bytes per traced ray, 30–40 MiB per pose of the default rig
/// (the marker border's edge pixels take 16 rays each). One pose answers 79 % of the
/// default Bonn tour's frames from the cache (2 would answer 87 %, 8 would answer 94 %),
/// and keeps the footprint flat from the first frame on: a second pose would fill only
/// when the tour first changes pose, which a memory soak reads as growth.
pub const RAW_VIEW_CACHE: usize = 1;

/// Largest axis travel between two sub-frames of a moving exposure (0.05°): far below any
/// lobe the sample library renders, and the sweep of a default fly-scan exposure (0.5°)
/// takes 10.
pub const MOTION_STEP_RAD: f64 = 0.05 * std::f64::consts::PI / 180.0;
/// At most this many sub-frames per exposure (a sweep beyond 3.2° is sampled coarser).
pub const MAX_MOTION_SUBFRAMES: usize = 64;

/// Which part of the sensor the simulated camera reads out.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Roi {
    /// The whole sensor.
    Full,
    /// The bounding box of the sample holder (plus a margin): the rest of the frame only
    /// sees the dark background, so reading it costs time and tells nothing.
    Holder,
}

impl SimWorld {
    /// The lamp as the camera sees it now: switched as set, with its output drift at the
    /// rig clock's time (`light.options.drift_per_hour`).
    fn point_light(&self, q: &[f64]) -> PointLight {
        let (on, k) = *self.light.state.lock().expect("light poisoned");
        let d = self.light.drift_per_hour;
        let drift = if d == 0.0 {
            1.0
        } else {
            1.0 + d * self.clock.now() / 3600.0
        };
        PointLight {
            position: self.kinematics.light_position(q),
            intensity: if on { k * drift * self.light_intensity_w_sr } else { 0.0 },
            radius: self.lamp_radius_mm,
        }
    }

    /// The lamp of the ground truth: on at full intensity, without drift, whatever the
    /// light is doing right now (the store thread renders a measurement's truth while the
    /// drive loop may already have switched the light off for a dark frame). The truth is
    /// what the sample is under the nominal lamp; a drift is an error against it.
    fn truth_light(&self, q: &[f64]) -> PointLight {
        PointLight {
            position: self.kinematics.light_position(q),
            intensity: self.light_intensity_w_sr,
            radius: self.lamp_radius_mm,
        }
    }

    /// Axis positions (load side) at rig time `t`.
    pub fn configuration_at(&self, t: f64) -> Vec<f64> {
        self.axes.iter().map(|a| a.load_position_at(t)).collect()
    }

    /// The raw radiance of one exposure from `t0` to `t1`: the frame at `q0` when the rig
    /// stands still, else the mean over sub-frames spaced at most [`MOTION_STEP_RAD`] of
    /// axis travel apart (midpoint rule), so motion blur is rendered, not assumed away.
    pub fn exposure_radiance(&self, t0: f64, t1: f64) -> (Vec<f64>, RgbImage) {
        let q0 = self.configuration_at(t0);
        let q1 = self.configuration_at(t1);
        let travel = q0.iter().zip(&q1).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        let qm = self.configuration_at(0.5 * (t0 + t1));
        if travel == 0.0 && qm == q0 {
            let rad = self.raw_radiance(&q0);
            return (q0, rad);
        }
        let k = ((travel / MOTION_STEP_RAD).ceil() as usize).clamp(2, MAX_MOTION_SUBFRAMES);
        let mut acc: Option<RgbImage> = None;
        for i in 0..k {
            let t = t0 + (t1 - t0) * (i as f64 + 0.5) / k as f64;
            let img = self.raw_radiance(&self.configuration_at(t));
            match acc.as_mut() {
                None => acc = Some(img),
                Some(a) => a.data.iter_mut().zip(&img.data).for_each(|(x, y)| *x += y),
            }
        }
        let mut img = acc.expect("k >= 2 sub-frames");
        let inv = 1.0 / k as f32;
        img.data.iter_mut().for_each(|x| *x *= inv);
        (qm, img)
    }

    /// Current axis positions.
    pub fn configuration(&self) -> Vec<f64> {
        // The load side: with a mechanical error model the camera sees where the sample and
        // arms really are, not where the controller thinks they are.
        self.axes.iter().map(|a| a.load_position_now()).collect()
    }

    /// Ground truth for configuration `q` in normalised sensor units (DN / max DN, not
    /// clipped, no noise, no vignetting), rectified to `width × height` texels.
    pub fn truth(&self, q: &[f64], width: usize, height: usize) -> RgbImage {
        let pose = self.kinematics.camera_pose(q);
        let light = self.truth_light(q);
        // Traced once per camera position, shaded per light: the same bytes as
        // `render_truth`, which traces every time.
        let rad = self.truth_radiance(pose.position, width, height, &light);
        self.sensor.lock().expect("sensor poisoned").normalize_truth(&rad)
    }

    /// The truth's radiance: the camera position's traced view (cached, see
    /// [`TRUTH_VIEW_CACHE`]) shaded for `light`.
    fn truth_radiance(&self, camera: Vec3, width: usize, height: usize, light: &PointLight) -> RgbImage {
        let key = key_bits(&[camera.x, camera.y, camera.z, width as f64, height as f64]);
        let bytes = self.renderer.truth_view_bytes(width, height);
        let view = self
            .truth_views
            .get_sized(key, bytes, || self.renderer.truth_view(camera, width, height));
        self.renderer.shade_truth(&view, light)
    }

    /// [`SimWorld::truth`] normalised at `exposure_s` and `gain` instead of the sensor's
    /// current setting (an HDR bracket changes that setting while earlier measurements'
    /// truths are still being rendered).
    pub fn truth_at(&self, q: &[f64], width: usize, height: usize, exposure_s: f64, gain: f64) -> RgbImage {
        let pose = self.kinematics.camera_pose(q);
        let light = self.truth_light(q);
        let rad = self.truth_radiance(pose.position, width, height, &light);
        let mut sensor = self.sensor.lock().expect("sensor poisoned").clone();
        sensor.exposure_s = exposure_s;
        sensor.gain = gain;
        sensor.normalize_truth(&rad)
    }

    /// Render the raw frame the camera sees in configuration `q`.
    pub fn raw_radiance(&self, q: &[f64]) -> RgbImage {
        let pose = self.kinematics.camera_pose(q);
        let light = self.point_light(q);
        // Traced once per camera pose, shaded per light: the same bytes as
        // `render_raw_distorted`, which traces every time. Intrinsics, lens and size are
        // fixed for the world; the pose is the key.
        let (p, r, d, f) = (pose.position, pose.right, pose.down, pose.forward);
        let key = key_bits(&[p.x, p.y, p.z, r.x, r.y, r.z, d.x, d.y, d.z, f.x, f.y, f.z]);
        let view = self.raw_views.get(key, || {
            self.renderer
                .raw_view(&self.intrinsics, &self.lens, &pose, self.width, self.height)
        });
        self.renderer.shade_raw(&view, &light)
    }
}

/// Which measurement a capture belongs to: canonical pair index and exposure index within
/// the measurement (see `Camera::begin_measurement`). The exposure index starts at 0 and
/// advances with every `configure` inside the measurement (a re-exposure at another
/// exposure time); retries of the same exposure keep it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CaptureIdentity {
    pub index: u64,
    pub exposure: u64,
}

/// Domain tag of measurement keys, so that no measurement key equals a pose key.
const MEASUREMENT_KEY: u64 = 0x6D65_6173_7572_656D;

/// The noise key of one capture (the sensor mixes it with its seed and the row).
///
/// * Inside a measurement: (canonical pair index, exposure index) only. The pose is left
///   out on purpose: read-backs of the same commanded pose can differ in the last bit
///   between runs that took different paths to it, and noise must not change with them.
/// * Outside a measurement (calibration recipes, `gonio sim` captures): the pose bits, as
///   before. Those poses come from a recipe in a fixed order, never from the order
///   optimiser, so they repeat exactly; repeated frames of one pose share their noise
///   unless `frame_noise` is set.
/// * `frame_noise` mixes in the camera's frame counter (independent noise per frame).
pub fn noise_key(identity: Option<CaptureIdentity>, q: &[f64], frame_noise: bool, sequence: u64) -> u64 {
    use crate::noise::mix64;
    let mut key = match identity {
        Some(id) => mix64(mix64(MEASUREMENT_KEY ^ id.index) ^ id.exposure),
        None => q.iter().fold(0u64, |h, x| mix64(h ^ x.to_bits())),
    };
    if frame_noise {
        key = mix64(key ^ sequence.wrapping_add(1));
    }
    key
}

/// The simulated camera.
pub struct SimCamera {
    world: Arc<SimWorld>,
    sequence: AtomicU64,
    /// The measurement being captured and the exposures taken of it so far
    /// (`Camera::begin_measurement`); `None` outside measurements.
    measurement: Mutex<Option<CaptureIdentity>>,
    /// Opt-in injected fault (rig file `camera.options.fault`, see [`crate::camera_faults`]).
    fault: Option<crate::camera_faults::CameraFault>,
    /// The last frame handed out, kept only with a `stale` fault (to hand it out again).
    last_frame: Mutex<Option<Frame>>,
}

impl SimCamera {
    /// The injected fault, if the rig file configured one.
    pub fn fault(&self) -> Option<&crate::camera_faults::CameraFault> {
        self.fault.as_ref()
    }

    /// Apply a fault that replaces the whole capture: `timeout` never returns, `drop`
    /// fails, `stale` hands out the previous frame. `None`: capture normally.
    async fn injected(&self, kind: crate::camera_faults::CameraFaultKind) -> Option<Result<Frame, DeviceError>> {
        use crate::camera_faults::CameraFaultKind as K;
        match kind {
            K::Timeout => {
                tracing::warn!("sim-camera: injected fault `timeout`: the capture hangs");
                std::future::pending::<()>().await;
                None
            }
            K::Drop => Some(Err(DeviceError::Other {
                device: "sim-camera".into(),
                command: "capture".into(),
                reason: "frame dropped (injected fault `drop`)".into(),
            })),
            K::Stale => self.last_frame.lock().expect("last frame poisoned").clone().map(Ok),
            K::Saturate | K::Exposure => None,
        }
    }

    /// Apply a fault that alters a rendered frame, and keep the frame if a later `stale`
    /// fault needs it. Without a fault this is a no-op.
    fn after_capture(&self, kind: Option<crate::camera_faults::CameraFaultKind>, mut frame: Frame) -> Frame {
        use crate::camera_faults::CameraFaultKind as K;
        match kind {
            Some(K::Saturate) => {
                let max = frame.max_dn();
                frame.data.fill(max);
            }
            Some(K::Stale) => {
                // No previous frame to repeat (first capture): a frame from before the rig
                // started, which every freshness rule must refuse.
                frame.meta.timestamp = -1.0;
            }
            _ => {}
        }
        if self.fault.as_ref().is_some_and(|f| f.kind == K::Stale) {
            *self.last_frame.lock().expect("last frame poisoned") = Some(frame.clone());
        }
        frame
    }
}

#[async_trait]
impl Camera for SimCamera {
    fn name(&self) -> &str {
        "sim-camera"
    }
    async fn configure(&self, config: &CameraConfig) -> Result<CameraConfig, DeviceError> {
        // A new setting inside a measurement (a re-exposure at another exposure time) is
        // the measurement's next exposure: it gets its own noise.
        if let Some(id) = self.measurement.lock().expect("measurement poisoned").as_mut() {
            id.exposure += 1;
        }
        let mut s = self.world.sensor.lock().expect("sensor poisoned");
        if config.width != self.world.width || config.height != self.world.height {
            return Err(DeviceError::Rejected {
                device: "sim-camera".into(),
                command: format!("configure {}x{}", config.width, config.height),
                reason: format!("the simulated sensor is {}x{}", self.world.width, self.world.height),
            });
        }
        if !(config.exposure > 0.0 && config.gain > 0.0) {
            return Err(DeviceError::Rejected {
                device: "sim-camera".into(),
                command: "configure".into(),
                reason: "exposure and gain must be > 0".into(),
            });
        }
        // An injected `exposure` fault: the camera keeps its exposure and says so.
        let ignored = config.exposure != s.exposure_s && self.fault.as_ref().is_some_and(|f| f.next_exposure_change());
        if ignored {
            tracing::warn!(
                requested = config.exposure,
                kept = s.exposure_s,
                "sim-camera: injected fault `exposure`: the exposure is not applied"
            );
        } else {
            s.exposure_s = config.exposure;
        }
        s.gain = config.gain;
        s.bit_depth = config.bit_depth.clamp(8, 16);
        Ok(CameraConfig {
            bit_depth: s.bit_depth,
            exposure: s.exposure_s,
            ..config.clone()
        })
    }

    fn exposes_in_motion(&self) -> bool {
        true
    }

    async fn readout_done(&self) {
        let free_at = *self.world.sensor_free_at.lock().expect("sensor_free_at poisoned");
        self.world.clock.wait_until(free_at).await;
    }

    fn begin_measurement(&self, index: u64) {
        *self.measurement.lock().expect("measurement poisoned") = Some(CaptureIdentity { index, exposure: 0 });
    }

    async fn capture(&self) -> Result<Frame, DeviceError> {
        // A retry (after a dropped, timed-out or stale frame) is the same exposure again,
        // so it gets the same noise: a run with a transient fault stores the same bytes as
        // one without.
        let identity = *self.measurement.lock().expect("measurement poisoned");
        let fault = self.fault.as_ref().and_then(|f| f.next_capture());
        if let Some(kind) = fault {
            if let Some(result) = self.injected(kind).await {
                return result;
            }
        }
        let world = self.world.clone();
        // The sensor may still be reading out the previous frame (its readout overlapped the
        // move that brought the rig here): the exposure starts once it is free.
        let free_at = *world.sensor_free_at.lock().expect("sensor_free_at poisoned");
        world.clock.wait_until(free_at).await;
        let seq = self.sequence.fetch_add(1, Ordering::SeqCst);
        let q = world.configuration();
        let (exposure, gain, bits) = {
            let s = world.sensor.lock().expect("sensor poisoned");
            (s.exposure_s, s.gain, s.bit_depth)
        };
        let timestamp = world.clock.now();
        // Noise is seeded by the measurement's identity, not the frame counter: the same
        // measurement gets the same noise whether the run was interrupted and resumed or not.
        let noise_key = noise_key(identity, &q, world.frame_noise, seq);
        let w2 = world.clone();
        let data = tokio::task::spawn_blocking(move || {
            // Still rig: the frame at `q`. Moving rig (a fly-scan): the exposure's motion,
            // integrated, and the mid-exposure pose for the read-out window.
            let (q, rad) = w2.exposure_radiance(timestamp, timestamp + exposure);
            let sensor = w2.sensor.lock().expect("sensor poisoned").clone();
            if let Some(r) = &w2.response {
                let roi = match w2.roi {
                    Roi::Holder if w2.lens.is_zero() => {
                        let pose = w2.kinematics.camera_pose(&q);
                        w2.renderer.pixel_bounds(&w2.intrinsics, &pose, w2.width, w2.height)
                    }
                    _ => (0, 0, w2.width, w2.height),
                };
                return sensor.expose_roi_response(&rad, noise_key, roi, r);
            }
            match w2.roi {
                Roi::Full => sensor.expose(&rad, noise_key),
                Roi::Holder if !w2.lens.is_zero() => sensor.expose(&rad, noise_key),
                Roi::Holder => {
                    let pose = w2.kinematics.camera_pose(&q);
                    let roi = w2.renderer.pixel_bounds(&w2.intrinsics, &pose, w2.width, w2.height);
                    sensor.expose_roi(&rad, noise_key, roi)
                }
            }
        })
        .await
        .map_err(|e| DeviceError::Other {
            device: "sim-camera".into(),
            command: "capture".into(),
            reason: e.to_string(),
        })?;
        if world.overlap_readout {
            world.clock.wait(exposure).await;
            *world.sensor_free_at.lock().expect("sensor_free_at poisoned") = world.clock.now() + world.readout_s;
        } else {
            world.clock.wait(exposure + world.readout_s).await;
        }
        let frame = Frame {
            width: world.width,
            height: world.height,
            data,
            meta: FrameMeta {
                timestamp,
                exposure,
                gain,
                sequence: seq,
                bit_depth: bits,
            },
        };
        Ok(self.after_capture(fault, frame))
    }
}

/// A whole simulated rig built from a rig file and a sample.
pub struct SimRig {
    pub axes: Vec<Arc<dyn Axis>>,
    pub camera: Arc<dyn Camera>,
    pub light: Arc<dyn Light>,
    pub world: Arc<SimWorld>,
    pub clock: Arc<SimClock>,
}

/// Options of the simulated rig that are not in the rig file.
#[derive(Clone, Debug, Default)]
pub struct SimOptions {
    pub realtime: bool,
    /// Override the sensor noise switch (None: noise on).
    pub noise: Option<bool>,
    pub seed: Option<u64>,
    pub quality: crate::render::RenderQuality,
}

/// Errors building a simulated rig (bad sensor options).
#[derive(Debug, thiserror::Error)]
#[error("rig {rig}: {key}: {message}")]
pub struct SimRigError {
    pub rig: String,
    pub key: String,
    pub message: String,
}

/// The simulated camera's response and crosstalk from the rig file: `camera.options`
/// `response_compression = a` (0 ..= 8; 0 = linear) and `crosstalk = [[…], […], […]]`
/// (3 × 3, entries in −1 ..= 2, invertible). `None` when neither is given. Also what a
/// calibration run on the simulator compares its estimates with.
pub fn sensor_response(spec: &RigSpec) -> Result<Option<crate::sensor::SensorResponse>, SimRigError> {
    let err = |key: &str, message: String| SimRigError {
        rig: spec.name.clone(),
        key: format!("camera.options.{key}"),
        message,
    };
    let num = |v: &toml::Value| v.as_float().or_else(|| v.as_integer().map(|i| i as f64));
    let o = &spec.camera.options;
    let compression = match o.get("response_compression") {
        None => None,
        Some(v) => Some(
            num(v)
                .filter(|a| a.is_finite() && (0.0..=8.0).contains(a))
                .ok_or_else(|| {
                    err(
                        "response_compression",
                        format!("{v}: must be a number in 0 ..= 8 (0 = linear)"),
                    )
                })?,
        ),
    };
    let crosstalk = match o.get("crosstalk") {
        None => None,
        Some(v) => {
            let bad = || {
                err(
                    "crosstalk",
                    format!("{v}: must be 3 rows of 3 numbers in −1 ..= 2 forming an invertible matrix"),
                )
            };
            let rows = v.as_array().filter(|r| r.len() == 3).ok_or_else(bad)?;
            let mut m = [[0.0; 3]; 3];
            for (i, row) in rows.iter().enumerate() {
                let row = row.as_array().filter(|r| r.len() == 3).ok_or_else(bad)?;
                for (j, x) in row.iter().enumerate() {
                    m[i][j] = num(x)
                        .filter(|x| x.is_finite() && (-1.0..=2.0).contains(x))
                        .ok_or_else(bad)?;
                }
            }
            let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
                - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
                + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
            if det.abs() < 1e-3 {
                return Err(bad());
            }
            Some(m)
        }
    };
    Ok(
        (compression.is_some() || crosstalk.is_some()).then(|| crate::sensor::SensorResponse {
            compression: compression.unwrap_or(0.0),
            crosstalk,
        }),
    )
}

/// The lamp's disc radius from the rig file ([`RigSpec::lamp_radius_mm`]), as a
/// simulator error.
pub fn lamp_radius_mm(spec: &RigSpec) -> Result<f64, SimRigError> {
    spec.lamp_radius_mm().map_err(|e| option_error(spec, e))
}

fn option_error(spec: &RigSpec, e: gonio_devices::rig::OptionError) -> SimRigError {
    SimRigError {
        rig: spec.name.clone(),
        key: e.key,
        message: format!("{}: {}", e.value, e.message),
    }
}

pub fn build_sim_rig(spec: &RigSpec, renderer: Arc<Renderer>, opts: &SimOptions) -> Result<SimRig, SimRigError> {
    crate::count_construction();
    let clock = Arc::new(SimClock::new(opts.realtime));
    let axes: Vec<Arc<SimAxis>> = spec
        .axes
        .iter()
        .map(|a| {
            let mech = crate::mechanics::MechanicalErrors::from_options(&a.options).map_err(|e| SimRigError {
                rig: spec.name.clone(),
                key: format!("axis {}: {}", a.name, e.key),
                message: e.message,
            })?;
            let lag = match a.options.get("flight_lag_s") {
                None => 0.0,
                Some(v) => v
                    .as_float()
                    .or_else(|| v.as_integer().map(|i| i as f64))
                    .filter(|x| x.is_finite() && (0.0..=10.0).contains(x))
                    .ok_or_else(|| SimRigError {
                        rig: spec.name.clone(),
                        key: format!("axis {}: options.flight_lag_s", a.name),
                        message: format!("{v}: must be seconds in [0, 10]"),
                    })?,
            };
            Ok(Arc::new(
                SimAxis::new(&a.name, a.limits(), a.motion(), clock.clone())
                    .with_mechanics(mech)
                    .with_flight_lag(lag),
            ))
        })
        .collect::<Result<_, SimRigError>>()?;
    let opt = |key: &str, default: f64| -> Result<f64, SimRigError> {
        match spec.camera.options.get(key) {
            None => Ok(default),
            Some(v) => v
                .as_float()
                .or_else(|| v.as_integer().map(|i| i as f64))
                .filter(|x| x.is_finite() && *x >= 0.0)
                .ok_or(SimRigError {
                    rig: spec.name.clone(),
                    key: format!("camera.options.{key}"),
                    message: format!("{v}: must be a number ≥ 0"),
                }),
        }
    };
    let sensor = SensorModel {
        full_well_e: opt("full_well_e", 20000.0)?.max(1.0),
        read_noise_e: opt("read_noise_e", 4.0)?,
        dark_current_e_s: opt("dark_current_e_s", 5.0)?,
        sensitivity_e_per_radiance_s: opt("sensitivity_e_per_radiance_s", 14000.0)?,
        vignetting: opt("vignetting", 0.0)?.min(0.9),
        bit_depth: spec.camera.bit_depth,
        gain: spec.camera.gain,
        exposure_s: spec.camera.exposure_s,
        noise: opts.noise.unwrap_or(true),
        seed: match opts.seed {
            Some(seed) => seed,
            None => spec
                .camera
                .noise_seed()
                .map_err(|e| option_error(spec, e))?
                .unwrap_or(1),
        },
    };
    let nominal = if spec.light.backend == "sim" {
        spec.sim_lamp_nominal().map_err(|e| option_error(spec, e))?
    } else {
        None
    };
    let drift_per_hour = spec.sim_light_drift_per_hour().map_err(|e| option_error(spec, e))?;
    let light = Arc::new(SimLight {
        state: Mutex::new((false, 0.0)),
        nominal,
        drift_per_hour,
    });
    let world = Arc::new(SimWorld {
        axes: axes.clone(),
        // The simulator places the camera and lamp where they really are: with the rig's
        // true misalignment (`sim_misalignment`), which the planner's kinematics do not know.
        kinematics: kinematics::for_rig(&spec.simulated_truth()),
        renderer,
        light: light.clone(),
        light_intensity_w_sr: spec.light.intensity_w_sr,
        lamp_radius_mm: lamp_radius_mm(spec)?,
        intrinsics: spec.camera.intrinsics(),
        sensor: Mutex::new(sensor),
        clock: clock.clone(),
        readout_s: spec.camera.readout_s,
        overlap_readout: spec
            .camera
            .readout_overlaps_motion()
            .map_err(|e| option_error(spec, e))?,
        sensor_free_at: Mutex::new(0.0),
        width: spec.camera.width,
        height: spec.camera.height,
        lens: crate::render::LensDistortion(spec.camera.distortion().map_err(|e| option_error(spec, e))?),
        response: sensor_response(spec)?,
        truth_views: ViewCache::with_budget(TRUTH_VIEW_CACHE, TRUTH_VIEW_BUDGET),
        raw_views: ViewCache::new(RAW_VIEW_CACHE),
        frame_noise: match spec.camera.options.get("frame_noise") {
            None => false,
            Some(v) => v.as_bool().ok_or(SimRigError {
                rig: spec.name.clone(),
                key: "camera.options.frame_noise".into(),
                message: format!("{v}: must be true or false"),
            })?,
        },
        roi: match spec.camera.options.get("roi").and_then(|v| v.as_str()) {
            None | Some("holder") => Roi::Holder,
            Some("full") => Roi::Full,
            Some(other) => {
                return Err(SimRigError {
                    rig: spec.name.clone(),
                    key: "camera.options.roi".into(),
                    message: format!("`{other}`: use \"holder\" (default) or \"full\""),
                })
            }
        },
    });
    let fault = match spec.camera.options.get("fault") {
        None => None,
        Some(v) => Some(
            v.as_str()
                .ok_or_else(|| format!("{v}: must be a string like \"drop:at=3\""))
                .and_then(|s| crate::camera_faults::CameraFault::parse(s).map_err(|e| e.to_string()))
                .map_err(|message| SimRigError {
                    rig: spec.name.clone(),
                    key: "camera.options.fault".into(),
                    message,
                })?,
        ),
    };
    let camera = Arc::new(SimCamera {
        world: world.clone(),
        sequence: AtomicU64::new(0),
        measurement: Mutex::new(None),
        fault,
        last_frame: Mutex::new(None),
    });
    Ok(SimRig {
        axes: axes.into_iter().map(|a| a as Arc<dyn Axis>).collect(),
        camera,
        light,
        world,
        clock,
    })
}

#[cfg(test)]
mod tests {
    use super::{noise_key, CaptureIdentity};

    #[test]
    fn measurement_noise_depends_on_identity_not_pose() {
        let id = |index, exposure| Some(CaptureIdentity { index, exposure });
        // Read-backs one ulp apart (what different paths to one pose gave): same key.
        let a = [0.1f64, 0.7, -1.2];
        let b = [f64::from_bits(0.1f64.to_bits() + 1), 0.7, -1.2];
        assert_eq!(noise_key(id(42, 0), &a, false, 3), noise_key(id(42, 0), &b, false, 9));
        // Another measurement, another exposure of the same one: other keys.
        assert_ne!(noise_key(id(42, 0), &a, false, 0), noise_key(id(43, 0), &a, false, 0));
        assert_ne!(noise_key(id(42, 0), &a, false, 0), noise_key(id(42, 1), &a, false, 0));
        // Outside a measurement the pose decides (calibration recipes), bit for bit.
        assert_ne!(noise_key(None, &a, false, 0), noise_key(None, &b, false, 0));
        assert_eq!(noise_key(None, &a, false, 0), noise_key(None, &a, false, 5));
        // frame_noise: the frame counter makes every frame independent.
        assert_ne!(noise_key(id(42, 0), &a, true, 0), noise_key(id(42, 0), &a, true, 1));
    }

    /// A sim light measures nothing unless the rig file gives nominal values; then it
    /// reports them times its intensity, and 0 when off.
    #[tokio::test]
    async fn sim_light_reports_nominal_values_only_when_asked() {
        use gonio_devices::{LampReading, Light};
        let light = |nominal| super::SimLight {
            state: std::sync::Mutex::new((false, 0.0)),
            nominal,
            drift_per_hour: 0.0,
        };
        let plain = light(None);
        plain.set(true, 1.0).await.unwrap();
        assert_eq!(plain.read_back().await.unwrap(), None);
        assert_eq!(plain.identity().await.unwrap(), "sim-light");
        let n = light(Some(LampReading {
            voltage_v: 12.0,
            current_a: 8.0,
        }));
        n.set(true, 0.5).await.unwrap();
        assert_eq!(
            n.read_back().await.unwrap(),
            Some(LampReading {
                voltage_v: 6.0,
                current_a: 4.0
            })
        );
        n.set(false, 0.5).await.unwrap();
        assert_eq!(n.read_back().await.unwrap().unwrap().current_a, 0.0);
    }

    /// The world's traced-view caches give the bytes of a fresh trace for every pair, in a
    /// tour order that revisits poses, and keep no more views than their capacity.
    #[test]
    fn cached_views_render_the_same_bytes_as_fresh_traces() {
        use crate::render::{PointLight, RenderQuality, Renderer};
        use crate::SampleSpec;
        use gonio_devices::rig::RigSpec;
        use std::sync::Arc;
        let mut spec = RigSpec::default_rig();
        // A small frame keeps the test fast; the relief sample exercises shadows and parallax.
        spec.camera.width = 160;
        spec.camera.height = 128;
        spec.camera.focal_length_px = 900.0;
        let sample = Arc::new(SampleSpec::resolve("corduroy").unwrap().build().unwrap());
        let renderer = Arc::new(Renderer::new(sample.clone(), RenderQuality::default()));
        let rig = super::build_sim_rig(&spec, renderer, &super::SimOptions::default()).unwrap();
        let world = &rig.world;
        *world.light.state.lock().unwrap() = (true, 1.0);
        let fresh = Renderer::new(sample, RenderQuality::default());
        let deg = |v: [f64; 4]| v.map(f64::to_radians).to_vec();
        // Three camera poses (turntable, camera arc), lights moving: poses A B A C B A.
        let poses = [
            [0.0, 30.0],
            [45.0, -50.0],
            [0.0, 30.0],
            [120.0, 65.0],
            [45.0, -50.0],
            [0.0, 30.0],
        ];
        for (k, p) in poses.iter().enumerate() {
            let q = deg([p[0], p[1], 20.0 * k as f64, 40.0 + 5.0 * k as f64]);
            let pose = world.kinematics.camera_pose(&q);
            let light = PointLight::point(world.kinematics.light_position(&q), world.light_intensity_w_sr);
            let raw = fresh.render_raw(&world.intrinsics, &pose, world.width, world.height, &light);
            assert_eq!(world.raw_radiance(&q).data, raw.data, "raw frame {k}");
            let truth = fresh.render_truth(pose.position, 48, 48, &light);
            let want = world.sensor.lock().unwrap().normalize_truth(&truth);
            assert_eq!(world.truth(&q, 48, 48).data, want.data, "truth {k}");
        }
        // Truth: A B C fit (capacity 8), so only the first visit of each pose traced.
        assert_eq!(world.truth_views.stats(), (3, 3));
        // Raw: capacity 1, so only a repeated pose hits; here every pose differs from
        // the one before.
        assert_eq!(world.raw_views.stats(), (0, 6));
        assert!(world.raw_views.len() <= super::RAW_VIEW_CACHE);
    }
}
