//! The simulated gonioreflectometer.
//!
//! - [`brdf`]: the material library (analytic BRDF models).
//!
//! The simulator implements the hardware traits of `gonio-devices`, so the acquisition
//! engine cannot tell it from a real rig.

pub mod brdf;
