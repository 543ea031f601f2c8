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

pub use devices::{build_sim_rig, lamp_radius_mm, SimOptions, SimRig, SimWorld};
pub use render::{PointLight, RawView, RenderQuality, Renderer, TruthView, ViewCache};
pub use sample::{Sample, SampleSpec};
