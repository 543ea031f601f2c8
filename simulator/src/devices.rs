//! Simulated devices implementing the `gonio-devices` traits: axes with trapezoidal
//! motion on the [`SimClock`], a lamp, and a camera that renders the sample at the pose
//! the axes are actually in.

use crate::clock::SimClock;
use crate::render::{PointLight, Renderer};
use crate::sensor::SensorModel;
use async_trait::async_trait;
use gonio_devices::axis::check_limits;
use gonio_devices::image::RgbImage;
use gonio_devices::kinematics::{self, Kinematics};
use gonio_devices::rig::RigSpec;
use gonio_devices::{
    Axis, AxisStatus, Camera, CameraConfig, DeviceError, Frame, FrameMeta, Intrinsics, Light, MotionModel, SoftLimits,
};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

struct AxisState {
    homed: bool,
    start: f64,
    target: f64,
    t_start: f64,
    t_end: f64,
}

/// A simulated motor stage.
pub struct SimAxis {
    name: String,
    limits: SoftLimits,
    motion: MotionModel,
    clock: Arc<SimClock>,
    state: Mutex<AxisState>,
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
            }),
        }
    }

    /// Position now (interpolated along the profile while moving).
    pub fn position_now(&self) -> f64 {
        let s = self.state.lock().expect("axis state poisoned");
        let t = self.clock.now() - s.t_start;
        s.start + self.motion.position_at(s.target - s.start, t)
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
        };
        Ok(())
    }
    async fn start_move(&self, target: f64) -> Result<(), DeviceError> {
        check_limits(&self.name, self.limits, target, "move_abs")?;
        let from = self.position_now();
        let now = self.clock.now();
        let mut s = self.state.lock().expect("axis state poisoned");
        if !s.homed {
            return Err(DeviceError::NotHomed {
                device: self.name.clone(),
                command: "move_abs".into(),
            });
        }
        let dt = self.motion.move_time(target - from);
        *s = AxisState {
            homed: true,
            start: from,
            target,
            t_start: now,
            t_end: now + dt,
        };
        Ok(())
    }
    async fn wait_idle(&self) -> Result<f64, DeviceError> {
        let end = self.state.lock().expect("axis state poisoned").t_end;
        self.clock.wait_until(end).await;
        Ok(self.position_now())
    }
    async fn stop(&self) -> Result<(), DeviceError> {
        let p = self.position_now();
        let now = self.clock.now();
        let mut s = self.state.lock().expect("axis state poisoned");
        s.start = p;
        s.target = p;
        s.t_start = now;
        s.t_end = now;
        Ok(())
    }
    async fn position(&self) -> Result<f64, DeviceError> {
        Ok(self.position_now())
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
    pub width: usize,
    pub height: usize,
    pub roi: Roi,
    /// Lens distortion of the simulated camera (zero = ideal pinhole).
    pub lens: crate::render::LensDistortion,
}

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
    fn point_light(&self, q: &[f64]) -> PointLight {
        let (on, k) = *self.light.state.lock().expect("light poisoned");
        PointLight {
            position: self.kinematics.light_position(q),
            intensity: if on { k * self.light_intensity_w_sr } else { 0.0 },
            radius: self.lamp_radius_mm,
        }
    }

    /// Current axis positions.
    pub fn configuration(&self) -> Vec<f64> {
        self.axes.iter().map(|a| a.position_now()).collect()
    }

    /// Ground truth for configuration `q` in normalised sensor units (DN / max DN, not
    /// clipped, no noise, no vignetting), rectified to `width × height` texels.
    pub fn truth(&self, q: &[f64], width: usize, height: usize) -> RgbImage {
        let pose = self.kinematics.camera_pose(q);
        let light = self.point_light(q);
        let rad = self.renderer.render_truth(pose.position, width, height, &light);
        self.sensor.lock().expect("sensor poisoned").normalize_truth(&rad)
    }

    /// Render the raw frame the camera sees in configuration `q`.
    pub fn raw_radiance(&self, q: &[f64]) -> RgbImage {
        let pose = self.kinematics.camera_pose(q);
        let light = self.point_light(q);
        self.renderer
            .render_raw_distorted(&self.intrinsics, &self.lens, &pose, self.width, self.height, &light)
    }
}

/// The simulated camera.
pub struct SimCamera {
    world: Arc<SimWorld>,
    sequence: AtomicU64,
}

#[async_trait]
impl Camera for SimCamera {
    fn name(&self) -> &str {
        "sim-camera"
    }
    async fn configure(&self, config: &CameraConfig) -> Result<CameraConfig, DeviceError> {
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
        s.exposure_s = config.exposure;
        s.gain = config.gain;
        s.bit_depth = config.bit_depth.clamp(8, 16);
        Ok(CameraConfig {
            bit_depth: s.bit_depth,
            ..config.clone()
        })
    }

    async fn capture(&self) -> Result<Frame, DeviceError> {
        let world = self.world.clone();
        let seq = self.sequence.fetch_add(1, Ordering::SeqCst);
        let q = world.configuration();
        let (exposure, gain, bits) = {
            let s = world.sensor.lock().expect("sensor poisoned");
            (s.exposure_s, s.gain, s.bit_depth)
        };
        let timestamp = world.clock.now();
        // Noise is seeded by the pose, not the frame counter: the same measurement gets the
        // same noise whether the run was interrupted and resumed or not.
        let noise_key = q.iter().fold(0u64, |h, x| crate::noise::mix64(h ^ x.to_bits()));
        let w2 = world.clone();
        let data = tokio::task::spawn_blocking(move || {
            let rad = w2.raw_radiance(&q);
            let sensor = w2.sensor.lock().expect("sensor poisoned").clone();
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
        world.clock.wait(exposure + world.readout_s).await;
        Ok(Frame {
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
        })
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

/// The lamp's disc radius from the rig file (`light.options.radius_mm`, default 0 = a
/// point lamp); at most half the lamp's distance from the sample, so the disc stays a lamp.
pub fn lamp_radius_mm(spec: &RigSpec) -> Result<f64, SimRigError> {
    let Some(v) = spec.light.options.get("radius_mm") else {
        return Ok(0.0);
    };
    let max = spec.geometry.light_distance_mm / 2.0;
    v.as_float()
        .or_else(|| v.as_integer().map(|i| i as f64))
        .filter(|r| r.is_finite() && *r >= 0.0 && *r <= max)
        .ok_or(SimRigError {
            rig: spec.name.clone(),
            key: "light.options.radius_mm".into(),
            message: format!("{v}: must be a number of millimetres in [0, {max}] (half the lamp distance)"),
        })
}

pub fn build_sim_rig(spec: &RigSpec, renderer: Arc<Renderer>, opts: &SimOptions) -> Result<SimRig, SimRigError> {
    let clock = Arc::new(SimClock::new(opts.realtime));
    let axes: Vec<Arc<SimAxis>> = spec
        .axes
        .iter()
        .map(|a| Arc::new(SimAxis::new(&a.name, a.limits(), a.motion(), clock.clone())))
        .collect();
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
        seed: opts.seed.unwrap_or(opt("seed", 1.0)? as u64),
    };
    let light = Arc::new(SimLight {
        state: Mutex::new((false, 0.0)),
    });
    let world = Arc::new(SimWorld {
        axes: axes.clone(),
        kinematics: kinematics::for_rig(spec),
        renderer,
        light: light.clone(),
        light_intensity_w_sr: spec.light.intensity_w_sr,
        lamp_radius_mm: lamp_radius_mm(spec)?,
        intrinsics: spec.camera.intrinsics(),
        sensor: Mutex::new(sensor),
        clock: clock.clone(),
        readout_s: spec.camera.readout_s,
        width: spec.camera.width,
        height: spec.camera.height,
        lens: {
            // Distortion coefficients may be negative: read them without `opt`'s ≥ 0 rule.
            let mut c = [0.0; 5];
            for (k, key) in ["k1", "k2", "p1", "p2", "k3"].iter().enumerate() {
                if let Some(v) = spec.camera.options.get(*key) {
                    c[k] = v
                        .as_float()
                        .or_else(|| v.as_integer().map(|i| i as f64))
                        .filter(|x| x.is_finite() && x.abs() < 10.0)
                        .ok_or(SimRigError {
                            rig: spec.name.clone(),
                            key: format!("camera.options.{key}"),
                            message: format!("{v}: must be a number with |value| < 10"),
                        })?;
                }
            }
            crate::render::LensDistortion(c)
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
    let camera = Arc::new(SimCamera {
        world: world.clone(),
        sequence: AtomicU64::new(0),
    });
    Ok(SimRig {
        axes: axes.into_iter().map(|a| a as Arc<dyn Axis>).collect(),
        camera,
        light,
        world,
        clock,
    })
}
