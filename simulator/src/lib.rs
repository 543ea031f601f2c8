//! The simulated gonioreflectometer.
//!
//! - [`brdf`]: the material library (analytic BRDF models).
//! - [`sample`]: synthetic samples (height field, material maps, marker border) from TOML.
//! - [`render`]: the physically based renderer (raw frames and ground truth).
//! - [`sensor`]: radiance → digital numbers (noise, saturation, vignetting).
//! - [`clock`], [`devices`]: simulated axes, lamp and camera on a virtual clock.
//! - [`emulate`] (feature `emulate`): Zaber / Newport ESP300 controller emulators on ptys.
//!
//! The simulator implements the hardware traits of `gonio-devices`, so the acquisition
//! engine cannot tell it from a real rig.

/// The material library lives in its own crate (`gonio-brdf`), shared with fitting and
/// compression; re-exported here under its old path.
pub use gonio_brdf as brdf;
pub mod camera_faults;
pub mod clock;
pub mod devices;
#[cfg(feature = "emulate")]
pub mod emulate;
pub mod mechanics;
pub mod noise;
pub mod render;
pub mod sample;
pub mod sensor;

/// How many simulated worlds this process has constructed (renderers and simulated rigs;
/// each [`Renderer::new`] and [`build_sim_rig`] counts one).
///
/// Why: a rig whose camera, light and axes are all real must not build the simulator at
/// all (it would render frames nobody looks at, for hours); a test asserts that this
/// counter does not move while such a rig is built.
pub fn constructions() -> usize {
    CONSTRUCTIONS.load(std::sync::atomic::Ordering::Relaxed)
}

static CONSTRUCTIONS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// Count one construction (see [`constructions`]).
pub(crate) fn count_construction() {
    CONSTRUCTIONS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
}

pub use devices::{build_sim_rig, lamp_radius_mm, SimOptions, SimRig, SimWorld};
pub use render::{PointLight, RawView, RenderQuality, Renderer, TruthView, ViewCache};
pub use sample::{Sample, SampleSpec};
