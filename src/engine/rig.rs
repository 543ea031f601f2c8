//! Building a rig (hardware trait objects + kinematics) from a rig file.
//!
//! The engine sees only [`Rig`]: axes, camera and light as trait objects. Which
//! implementation stands behind each is the rig file's `backend` key; a simulated rig also
//! offers the ground truth of every measurement ([`GroundTruth`]).

use gonio_devices::image::RgbImage;
use gonio_devices::kinematics::{self, Kinematics};
use gonio_devices::rig::RigSpec;
use gonio_devices::target::MarkerBorder;
use gonio_devices::{Axis, Camera, Light};
use gonio_simulator::clock::SimClock;
use gonio_simulator::{build_sim_rig, Renderer, SampleSpec, SimOptions, SimWorld};
use std::sync::Arc;

/// What the simulator knows that a real rig does not: the exact rectified image.
pub trait GroundTruth: Send + Sync {
    /// Ground truth for axis configuration `q` (radians) in the units of the rectified
    /// images (normalised sensor signal, not clipped).
    fn truth(&self, q: &[f64], width: usize, height: usize) -> RgbImage;
}

impl GroundTruth for SimWorld {
    fn truth(&self, q: &[f64], width: usize, height: usize) -> RgbImage {
        SimWorld::truth(self, q, width, height)
    }
}

pub struct Rig {
    pub spec: RigSpec,
    pub kinematics: Box<dyn Kinematics>,
    pub axes: Vec<Arc<dyn Axis>>,
    pub camera: Arc<dyn Camera>,
    pub light: Arc<dyn Light>,
    pub truth: Option<Arc<dyn GroundTruth>>,
    /// The simulated rig's clock (virtual time); `None` on real hardware (wall time).
    pub clock: Option<Arc<SimClock>>,
    /// The holder's marker border and the sample edge length (mm), for rectification.
    pub border: MarkerBorder,
    pub sample_mm: f64,
    started: std::time::Instant,
}

#[derive(Debug, thiserror::Error)]
pub enum RigBuildError {
    #[error("rig {rig}: {part} uses backend `{backend}`, which this build does not provide (available: sim)")]
    UnknownBackend { rig: String, part: String, backend: String },
    #[error(transparent)]
    Sim(#[from] gonio_simulator::devices::SimRigError),
    #[error(transparent)]
    Sample(#[from] gonio_simulator::sample::SampleError),
}

impl Rig {
    /// Seconds on the rig's clock: virtual for a simulated rig, wall time otherwise.
    pub fn time(&self) -> f64 {
        match &self.clock {
            Some(c) => c.now(),
            None => self.started.elapsed().as_secs_f64(),
        }
    }

    /// Build the rig. Every part must currently be `sim` (real backends plug in here).
    pub fn build(spec: &RigSpec, sample: &SampleSpec, opts: &SimOptions) -> Result<Rig, RigBuildError> {
        let parts = std::iter::once(("camera".to_string(), spec.camera.backend.clone()))
            .chain(std::iter::once(("light".to_string(), spec.light.backend.clone())))
            .chain(
                spec.axes
                    .iter()
                    .map(|a| (format!("axis {}", a.name), a.backend.clone())),
            );
        for (part, backend) in parts {
            if backend != "sim" {
                return Err(RigBuildError::UnknownBackend {
                    rig: spec.name.clone(),
                    part,
                    backend,
                });
            }
        }
        let built = Arc::new(sample.clone().build()?);
        let renderer = Arc::new(Renderer::new(built, opts.quality));
        let sim = build_sim_rig(spec, renderer, opts)?;
        Ok(Rig {
            spec: spec.clone(),
            kinematics: kinematics::for_rig(spec),
            axes: sim.axes,
            camera: sim.camera,
            light: sim.light,
            truth: Some(sim.world as Arc<dyn GroundTruth>),
            clock: Some(sim.clock),
            border: sample.border.clone(),
            sample_mm: sample.size_mm,
            started: std::time::Instant::now(),
        })
    }
}
