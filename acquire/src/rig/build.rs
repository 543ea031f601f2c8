//! Building a [`Rig`] from a rig file: which implementation stands behind each axis,
//! the camera and the light (the rig file's `backend` keys), and the adapters a *mixed*
//! rig (serial axes, simulated camera) needs.

use super::backends::{AxisCtor, Backends, Make, Ports, RigBuildError};
use super::{GroundTruth, Rig};
use async_trait::async_trait;
use gonio_devices::kinematics;
use gonio_devices::rig::RigSpec;
use gonio_devices::{Axis, AxisStatus, Camera, DeviceError, LampReading, Light, MotionModel, SoftLimits};
use gonio_simulator::devices::{SimAxis, SimLight};
use gonio_simulator::{build_sim_rig, Renderer, SampleSpec, SimOptions};
use std::sync::Arc;

impl Rig {
    /// Build the rig from the rig file's backends, with this build's backend tables
    /// ([`Backends::builtin`]).
    ///
    /// The camera is simulated (`sim`, or `v4l2` with that feature); the light is `sim` or
    /// `hmp` (a lamp on a Rohde & Schwarz HMP supply, options in `[light] options`, see
    /// `gonio_devices::serial::hmp`; the simulated camera still renders with a shadow
    /// simulated lamp switched alongside, [`MirroredLight`]). Axes are `sim` or a serial controller
    /// (`zaber`, `esp300`; options in the axis' `options` table, see
    /// `gonio_devices::serial`). A rig with serial axes is a *mixed* rig: the serial axes
    /// move in wall time, and the simulated camera renders the pose they actually reached
    /// (each serial axis drives a shadow simulated axis to its read-back, see
    /// [`MirroredAxis`]), so the images and the ground truth stay consistent. A rig with
    /// no simulated part at all builds no simulator (see [`Rig::build_with`]).
    pub fn build(spec: &RigSpec, sample: &SampleSpec, opts: &SimOptions) -> Result<Rig, RigBuildError> {
        Self::build_with(spec, sample, opts, &Backends::builtin())
    }

    /// [`Rig::build`] with the caller's backend tables: a library user adds its own rows
    /// (a lab's camera crate) with [`Backends::with_camera`] and the like.
    ///
    /// A rig whose camera, light and every axis are real builds no simulator at all (no
    /// sample, renderer or simulated world: `sample` and `opts` are not used), has no
    /// ground truth and runs on the wall clock. Whenever the camera is real, the sample
    /// holder (marker border, sample size) comes from the rig file
    /// ([`RigSpec::holder_geometry`]); a simulated camera takes it from the sample it
    /// renders.
    pub fn build_with(
        spec: &RigSpec,
        sample: &SampleSpec,
        opts: &SimOptions,
        backends: &Backends,
    ) -> Result<Rig, RigBuildError> {
        // Every backend is resolved before anything is opened or built, so a misspelt or
        // compiled-out backend fails at once, whichever part names it.
        let camera_make = backends.camera(spec)?;
        let light_make = backends.light(spec)?;
        let axis_makes = spec
            .axes
            .iter()
            .map(|a| backends.axis(spec, a))
            .collect::<Result<Vec<_>, _>>()?;
        let lamp_monitor = spec.lamp_monitor().map_err(|error| RigBuildError::Option {
            rig: spec.name.clone(),
            error,
        })?;
        // A real lamp warms up before the first frame; a simulated one is warm at once.
        let lamp_warmup = match light_make {
            Make::Real(_) => Some(spec.lamp_warmup().map_err(|error| RigBuildError::Option {
                rig: spec.name.clone(),
                error,
            })?),
            _ => None,
        };
        let open_camera = real(&camera_make);
        let (border, sample_mm) = if open_camera.is_some() {
            spec.holder_geometry().map_err(|error| RigBuildError::Option {
                rig: spec.name.clone(),
                error,
            })?
        } else {
            (sample.border.clone(), sample.size_mm)
        };
        let open_axes: Option<Vec<AxisCtor>> = axis_makes.iter().map(real).collect();
        if let (Some(open_camera), Some(open_light), Some(open_axes)) = (open_camera, real(&light_make), open_axes) {
            let mut ports = Ports::default();
            let axes = spec
                .axes
                .iter()
                .zip(open_axes)
                .map(|(a, open)| open(spec, a, &mut ports))
                .collect::<Result<Vec<_>, _>>()?;
            let camera = open_camera(spec)?;
            let light = open_light(spec)?;
            return Ok(Rig {
                spec: spec.clone(),
                kinematics: kinematics::for_rig(spec),
                shadows: vec![None; axes.len()],
                axes,
                camera,
                light,
                lamp_monitor,
                lamp_warmup,
                truth: None,
                clock: None,
                border,
                sample_mm,
                started: std::time::Instant::now(),
                still_at: std::sync::Mutex::new(None),
            });
        }
        let mixed = axis_makes.iter().any(|m| matches!(m, Make::Real(_)));
        let built = Arc::new(sample.clone().build()?);
        let renderer = Arc::new(Renderer::new(built, opts.quality));
        // The shadow world of a mixed rig runs on a virtual clock: the serial axes already
        // take real time, the shadow axes only have to end up where the real ones are.
        let sim_opts = SimOptions {
            realtime: opts.realtime && !mixed,
            ..opts.clone()
        };
        let sim = build_sim_rig(spec, renderer, &sim_opts)?;
        let mut axes = sim.axes;
        let mut shadows = vec![None; axes.len()];
        let mut ports = Ports::default();
        for (i, (a, make)) in spec.axes.iter().zip(&axis_makes).enumerate() {
            let Make::Real(open) = make else { continue };
            let real = open(spec, a, &mut ports)?;
            shadows[i] = Some(sim.world.axes[i].clone());
            axes[i] = Arc::new(MirroredAxis {
                real,
                shadow: sim.world.axes[i].clone(),
            });
        }
        let shadow_light = sim.world.light.clone();
        let (mut camera, mut truth): (Arc<dyn Camera>, Option<Arc<dyn GroundTruth>>) =
            (sim.camera, Some(sim.world as Arc<dyn GroundTruth>));
        if mixed && opts.realtime {
            // The shadow world's clock is virtual (see above), so its camera would expose
            // and read out instantly; with `--realtime` the rig must take its real time.
            // (`overlapped_readout_s` was validated when the simulated rig above was built.)
            let readout = spec.camera.overlapped_readout_s().unwrap_or(0.0);
            camera = Arc::new(WallPacedCamera {
                inner: camera,
                seconds: spec.camera.capture_time() - readout,
                readout,
                free_at: std::sync::Mutex::new(None),
            });
        }
        if let Make::Real(open) = camera_make {
            // A real camera sees the real scene: the simulator's ground truth does not apply.
            camera = open(spec)?;
            truth = None;
        }
        let light: Arc<dyn Light> = match light_make {
            Make::Real(open) => Arc::new(MirroredLight {
                real: open(spec)?,
                shadow: shadow_light,
            }),
            _ => sim.light,
        };
        Ok(Rig {
            spec: spec.clone(),
            kinematics: kinematics::for_rig(spec),
            axes,
            camera,
            light,
            lamp_monitor,
            lamp_warmup,
            truth,
            clock: if mixed { None } else { Some(sim.clock) },
            border,
            sample_mm,
            started: std::time::Instant::now(),
            shadows,
            still_at: std::sync::Mutex::new(None),
        })
    }
}

/// The constructor behind a real backend's row (`None` for a simulated one).
fn real<C: Copy>(make: &Make<C>) -> Option<C> {
    match make {
        Make::Real(open) => Some(*open),
        _ => None,
    }
}

/// A simulated camera that takes its exposure and readout time on the wall clock (a mixed
/// rig in `--realtime` mode: the serial axes move in real time, so must the captures).
/// As the simulated camera does on its own clock, `capture` returns after `seconds` (the
/// exposure) and the overlapped `readout` runs on while the axes move: the next capture
/// starts no earlier than `free_at`.
struct WallPacedCamera {
    inner: Arc<dyn Camera>,
    seconds: f64,
    readout: f64,
    free_at: std::sync::Mutex<Option<std::time::Instant>>,
}

impl WallPacedCamera {
    async fn wait_free(&self) {
        let free_at = *self.free_at.lock().expect("free_at poisoned");
        if let Some(t) = free_at {
            tokio::time::sleep_until(tokio::time::Instant::from_std(t)).await;
        }
    }
}

#[async_trait]
impl Camera for WallPacedCamera {
    fn name(&self) -> &str {
        self.inner.name()
    }
    async fn configure(
        &self,
        config: &gonio_devices::CameraConfig,
    ) -> Result<gonio_devices::CameraConfig, DeviceError> {
        self.inner.configure(config).await
    }
    async fn capture(&self) -> Result<gonio_devices::Frame, DeviceError> {
        self.wait_free().await;
        let start = std::time::Instant::now();
        let frame = self.inner.capture().await?;
        let left = self.seconds - start.elapsed().as_secs_f64();
        if left > 0.0 {
            tokio::time::sleep(std::time::Duration::from_secs_f64(left)).await;
        }
        *self.free_at.lock().expect("free_at poisoned") =
            Some(std::time::Instant::now() + std::time::Duration::from_secs_f64(self.readout));
        Ok(frame)
    }
    async fn readout_done(&self) {
        self.wait_free().await;
    }
    fn rig_still(&self) {
        self.inner.rig_still()
    }
    fn begin_measurement(&self, index: u64) {
        self.inner.begin_measurement(index)
    }
    async fn identity(&self) -> Result<String, DeviceError> {
        self.inner.identity().await
    }
    async fn temperature_c(&self) -> Result<Option<f64>, DeviceError> {
        self.inner.temperature_c().await
    }
}

/// A real axis whose settled read-back is copied to a simulated axis, so the simulated
/// camera of a mixed rig renders the pose the hardware reached (including its deadband
/// error), not the pose that was asked for.
pub struct MirroredAxis {
    pub real: Arc<dyn Axis>,
    pub shadow: Arc<SimAxis>,
}

impl MirroredAxis {
    async fn mirror(&self, read_back: f64) -> Result<(), DeviceError> {
        mirror(&self.shadow, read_back).await
    }
}

/// Move a shadow axis to a real axis' read-back.
pub(super) async fn mirror(shadow: &SimAxis, read_back: f64) -> Result<(), DeviceError> {
    let lim = shadow.limits();
    // A read-back a microstep outside the soft limits must not fail the shadow move.
    let x = read_back.clamp(lim.min, lim.max);
    if let Err(DeviceError::NotHomed { .. }) = shadow.start_move(x).await {
        shadow.home().await?;
        shadow.start_move(x).await?;
    }
    shadow.wait_idle().await.map(|_| ())
}

#[async_trait]
impl Axis for MirroredAxis {
    fn name(&self) -> &str {
        self.real.name()
    }
    fn limits(&self) -> SoftLimits {
        self.real.limits()
    }
    fn motion(&self) -> MotionModel {
        self.real.motion()
    }
    async fn identity(&self) -> Result<String, DeviceError> {
        self.real.identity().await
    }
    async fn home(&self) -> Result<(), DeviceError> {
        self.real.home().await?;
        self.shadow.home().await?;
        let p = self.real.position().await?;
        self.mirror(p).await
    }
    async fn start_move(&self, target: f64) -> Result<(), DeviceError> {
        self.real.start_move(target).await
    }
    async fn start_move_at(&self, target: f64, velocity: f64) -> Result<(), DeviceError> {
        self.real.start_move_at(target, velocity).await
    }
    async fn start_trajectory(&self, trajectory: &gonio_devices::Trajectory) -> Result<(), DeviceError> {
        self.real.start_trajectory(trajectory).await
    }
    async fn wait_idle(&self) -> Result<f64, DeviceError> {
        let p = self.real.wait_idle().await?;
        self.mirror(p).await?;
        Ok(p)
    }
    async fn stop(&self) -> Result<(), DeviceError> {
        self.real.stop().await
    }
    async fn position(&self) -> Result<f64, DeviceError> {
        self.real.position().await
    }
    async fn reference_position(&self) -> Result<Option<f64>, DeviceError> {
        self.real.reference_position().await
    }
    async fn status(&self) -> Result<AxisStatus, DeviceError> {
        self.real.status().await
    }
}

/// A real lamp whose switching is copied to the simulated lamp, so the simulated camera of
/// a mixed rig renders with the lamp on when the real one is on. Identity and read-back
/// are the real lamp's.
pub struct MirroredLight {
    pub real: Arc<dyn Light>,
    pub shadow: Arc<SimLight>,
}

#[async_trait]
impl Light for MirroredLight {
    fn name(&self) -> &str {
        self.real.name()
    }
    async fn set(&self, on: bool, intensity: f64) -> Result<(), DeviceError> {
        self.real.set(on, intensity).await?;
        self.shadow.set(on, intensity).await
    }
    async fn identity(&self) -> Result<String, DeviceError> {
        self.real.identity().await
    }
    async fn read_back(&self) -> Result<Option<LampReading>, DeviceError> {
        self.real.read_back().await
    }
}
