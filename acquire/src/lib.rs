//! gonio-acquire: everything between a sweep and a stored dataset.
//!
//! Data flows sweep → [`plan`] → [`session`] → [`engine`] (steps the [`rig`]) →
//! [`develop`] → `gonio_dataset::store`; [`calibrate`] steps the same rig through recipes.
//!
//! * [`rig`]: the one step every plan shares (`Rig::reach`, `Rig::capture` under the
//!   capture policy) over the device traits of `gonio-devices`.
//! * [`develop`]: the per-frame chain, raw corrections → exposure scale or HDR merge →
//!   lens → rectification → BRDF.
//! * [`plan`]: inverse kinematics, infeasible pairs, the order and its duration.
//! * [`engine`]: runs a plan on a rig, frames to the store thread, events to observers.
//! * [`calibrate`]: the calibration recipes, run through the same rig step.
//! * [`session`]: an acquisition as a library (create, resume, run), shared by the CLI,
//!   the tests and the live monitor.
//!
//! This crate compiles no dense-factorization library (faer) and no HTTP server: a lab
//! build that only acquires links it alone (ARCHITECTURE.md, "Crates").

pub mod calibrate;
pub mod develop;
pub mod engine;
pub mod plan;
pub mod rig;
pub mod session;
