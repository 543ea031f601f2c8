//! Building a [`Rig`] from a rig file: which implementation stands behind each axis,
//! the camera and the light (the rig file's `backend` keys), and the adapters a *mixed*
//! rig (serial axes, simulated camera) needs.

use super::{GroundTruth, Rig};
use async_trait::async_trait;
use gonio_devices::kinematics;
use gonio_devices::rig::RigSpec;
use gonio_devices::{Axis, AxisStatus, Camera, DeviceError, LampReading, Light, MotionModel, SoftLimits};
use gonio_simulator::devices::{SimAxis, SimLight};
use gonio_simulator::{build_sim_rig, Renderer, SampleSpec, SimOptions};
use std::sync::Arc;

#[derive(Debug, thiserror::Error)]
pub enum RigBuildError {
    #[error("rig {rig}: {part} uses backend `{backend}`, which this build does not provide (available: {available})")]
    UnknownBackend {
        rig: String,
        part: String,
        backend: String,
        available: String,
    },
    /// (`error` is not a `source`: its text is already in the message, and anyhow's chain
    /// would print it twice.)
    #[error("rig {rig}: {error}")]
    Serial {
        rig: String,
        error: gonio_devices::serial::SerialConfigError,
    },
    /// The rig names a real backend that this build leaves out (a cargo feature).
    #[error(
        "rig {rig}: {part} uses backend `{backend}`, which this build leaves out: rebuild gonio with \
         `--features {feature}` (needs {needs})"
    )]
    MissingFeature {
        rig: String,
        part: String,
        backend: String,
        feature: &'static str,
        needs: &'static str,
    },
    #[cfg(any(feature = "v4l2", feature = "genicam"))]
    #[error("rig {rig}: {source}")]
    Camera { rig: String, source: DeviceError },
    /// A rig-file option that is present but wrong (its key names it).
    #[error("rig {rig}: {error}")]
    Option {
        rig: String,
        error: gonio_devices::rig::OptionError,
    },
    #[error(transparent)]
    Sim(#[from] gonio_simulator::devices::SimRigError),
    #[error(transparent)]
    Sample(#[from] gonio_simulator::sample::SampleError),
}

impl Rig {
    /// Build the rig from the rig file's backends.
    ///
    /// The camera is simulated (`sim`, or `v4l2` with that feature); the light is `sim` or
    /// `hmp` (a lamp on a Rohde & Schwarz HMP supply, options in `[light] options`, see
    /// `gonio_devices::serial::hmp`; the simulated camera still renders with a shadow
    /// simulated lamp switched alongside, [`MirroredLight`]). Axes are `sim` or a serial controller
    /// (`zaber`, `esp300`; options in the axis' `options` table, see
    /// `gonio_devices::serial`). A rig with serial axes is a *mixed* rig: the serial axes
    /// move in wall time, and the simulated camera renders the pose they actually reached
    /// (each serial axis drives a shadow simulated axis to its read-back, see
    /// [`MirroredAxis`]), so the images and the ground truth stay consistent.
    pub fn build(spec: &RigSpec, sample: &SampleSpec, opts: &SimOptions) -> Result<Rig, RigBuildError> {
        let unknown = |part: String, backend: &str, available: &str| RigBuildError::UnknownBackend {
            rig: spec.name.clone(),
            part,
            backend: backend.to_string(),
            available: available.to_string(),
        };
        for (part, backend) in [("camera", &spec.camera.backend), ("light", &spec.light.backend)] {
            #[cfg(feature = "v4l2")]
            if part == "camera" && backend == "v4l2" {
                continue;
            }
            #[cfg(feature = "genicam")]
            if part == "camera" && backend == "genicam" {
                continue;
            }
            if let Some(&(_, feature, needs)) = CAMERA_FEATURES.iter().find(|(b, ..)| part == "camera" && b == backend)
            {
                return Err(RigBuildError::MissingFeature {
                    rig: spec.name.clone(),
                    part: part.to_string(),
                    backend: backend.to_string(),
                    feature,
                    needs,
                });
            }
            if part == "light" && backend == "hmp" {
                continue;
            }
            if backend != "sim" {
                let available = if part == "light" {
                    "sim, hmp"
                } else {
                    "sim; with cargo features: v4l2, genicam"
                };
                return Err(unknown(part.to_string(), backend, available));
            }
        }
        let lamp_monitor = spec.lamp_monitor().map_err(|error| RigBuildError::Option {
            rig: spec.name.clone(),
            error,
        })?;
        let axis_backends = std::iter::once("sim")
            .chain(gonio_devices::serial::BACKENDS.iter().copied())
            .collect::<Vec<_>>()
            .join(", ");
        let mut mixed = false;
        for a in &spec.axes {
            if gonio_devices::serial::BACKENDS.contains(&a.backend.as_str()) {
                mixed = true;
            } else if a.backend != "sim" {
                return Err(unknown(format!("axis {}", a.name), &a.backend, &axis_backends));
            }
        }
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
        if mixed {
            let mut ports = gonio_devices::serial::PortRegistry::new();
            for (i, a) in spec.axes.iter().enumerate() {
                if a.backend == "sim" {
                    continue;
                }
                let real = ports.build_axis(a).map_err(|error| RigBuildError::Serial {
                    rig: spec.name.clone(),
                    error,
                })?;
                shadows[i] = Some(sim.world.axes[i].clone());
                axes[i] = Arc::new(MirroredAxis {
                    real,
                    shadow: sim.world.axes[i].clone(),
                });
            }
        }
        let shadow_light = sim.world.light.clone();
        #[allow(unused_mut)]
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
        #[cfg(feature = "v4l2")]
        if let Some(real) = v4l2_camera(spec)? {
            // A real camera sees the real scene: the simulator's ground truth does not apply.
            camera = real;
            truth = None;
        }
        #[cfg(feature = "genicam")]
        if let Some(real) = genicam_camera(spec)? {
            camera = real;
            truth = None;
        }
        let light: Arc<dyn Light> = if spec.light.backend == "hmp" {
            let serial = |error| RigBuildError::Serial {
                rig: spec.name.clone(),
                error,
            };
            let opts = gonio_devices::serial::Options::for_light(&spec.light.options);
            let config = gonio_devices::serial::hmp::HmpConfig::from_options(&opts).map_err(serial)?;
            let real = gonio_devices::serial::hmp::HmpLight::open(config).map_err(serial)?;
            Arc::new(MirroredLight {
                real: Arc::new(real),
                shadow: shadow_light,
            })
        } else {
            sim.light
        };
        Ok(Rig {
            spec: spec.clone(),
            kinematics: kinematics::for_rig(spec),
            axes,
            camera,
            light,
            lamp_monitor,
            truth,
            clock: if mixed { None } else { Some(sim.clock) },
            border: sample.border.clone(),
            sample_mm: sample.size_mm,
            started: std::time::Instant::now(),
            shadows,
            still_at: std::sync::Mutex::new(None),
        })
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

// ---- V4L2 camera backend (feature `v4l2`, devices/src/v4l2) ---------------------------

/// The rig's camera when its backend is `v4l2` (`None` for other backends): opened and
/// checked here so that a missing or wrong device fails the rig build, not step one.
#[cfg(feature = "v4l2")]
fn v4l2_camera(spec: &RigSpec) -> Result<Option<Arc<dyn Camera>>, RigBuildError> {
    use gonio_devices::v4l2::{V4l2Camera, V4l2Options};
    if spec.camera.backend != "v4l2" {
        return Ok(None);
    }
    let err = |source| RigBuildError::Camera {
        rig: spec.name.clone(),
        source,
    };
    let opts = V4l2Options::from_rig(&spec.camera).map_err(err)?;
    let camera = V4l2Camera::open(opts).map_err(err)?;
    Ok(Some(Arc::new(camera)))
}

// ---- GenICam camera backend (feature `genicam`, devices/src/genicam) --------------------

/// The rig's camera when its backend is `genicam` (`None` for other backends): opened here
/// so that a missing camera or a wrong option fails the rig build, not step one.
#[cfg(feature = "genicam")]
fn genicam_camera(spec: &RigSpec) -> Result<Option<Arc<dyn Camera>>, RigBuildError> {
    use gonio_devices::genicam::camera::{FromRigError, GenicamCamera};
    if spec.camera.backend != "genicam" {
        return Ok(None);
    }
    let camera = GenicamCamera::from_rig(&spec.camera).map_err(|e| match e {
        FromRigError::Option(error) => RigBuildError::Option {
            rig: spec.name.clone(),
            error,
        },
        FromRigError::Device(source) => RigBuildError::Camera {
            rig: spec.name.clone(),
            source,
        },
    })?;
    Ok(Some(Arc::new(camera)))
}

/// Camera backends behind cargo features: (backend, feature, what building it needs). A rig
/// naming one that this build leaves out is told which feature to enable.
const CAMERA_FEATURES: [(&str, &str, &str); 2] =
    [("v4l2", "v4l2", "libclang"), ("genicam", "genicam", "libaravis-dev")];

#[cfg(test)]
mod tests {
    use super::*;

    /// A rig naming a real camera backend that this build leaves out says which cargo
    /// feature to enable (and what building it needs), before anything is opened.
    #[test]
    fn a_camera_backend_left_out_of_the_build_names_its_feature() {
        for (backend, feature, needs) in CAMERA_FEATURES {
            let compiled =
                (backend == "v4l2" && cfg!(feature = "v4l2")) || (backend == "genicam" && cfg!(feature = "genicam"));
            if compiled {
                continue;
            }
            let mut spec = RigSpec::default_rig();
            spec.camera.backend = backend.to_string();
            let sample = SampleSpec::resolve("white-standard").unwrap();
            let e = Rig::build(&spec, &sample, &SimOptions::default()).err().unwrap();
            let msg = e.to_string();
            assert!(matches!(e, RigBuildError::MissingFeature { .. }), "{msg}");
            assert!(
                msg.contains(&format!("--features {feature}")) && msg.contains(needs),
                "{msg}"
            );
        }
    }
}
