//! gonio: plan, drive, rectify, store and compress gonioreflectometer acquisitions.
//!
//! See ARCHITECTURE.md for the map. Data flows sweep → [`plan`] → engine (drives the
//! hardware traits of `gonio-devices`) → [`rectify`] → [`store`].

pub mod calibrate;
pub mod cli;
pub mod compress;
pub mod engine;
pub mod merge;
pub mod plan;
pub mod rectify;
pub mod shard;
pub mod slurm;
pub mod store;
pub mod sweep;
pub mod synth;
