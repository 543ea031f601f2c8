//! gonio: plan, drive, develop, store and compress gonioreflectometer acquisitions.
//!
//! See ARCHITECTURE.md for the map and its invariants. Data flows sweep → [`plan`] →
//! [`session`] → [`engine`] (steps the [`rig`]) → [`develop`] → [`store`]; [`calibrate`]
//! steps the same rig through recipes, [`compress`] reads the stored datasets and
//! [`synthesize`] grows compressed ones.

pub mod calibrate;
pub mod cli;
pub mod compress;
pub mod develop;
pub mod engine;
pub mod fit;
pub mod merge;
pub mod plan;
pub mod rig;
pub mod session;
pub mod shard;
pub mod slurm;
pub mod store;
pub mod sweep;
pub mod synth;
pub mod synthesize;
pub mod view;

#[cfg(test)]
mod layering;
