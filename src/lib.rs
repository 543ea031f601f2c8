//! gonio: the command line, the browser viewer, synthetic dataset families, shard merges and
//! the Slurm front end, on top of the library crates (ARCHITECTURE.md, "Crates"):
//!
//! * `gonio-dataset`: sweeps, shards and the dataset's one writer (`store`);
//! * `gonio-acquire`: plan, rig, develop, engine, calibrate, session;
//! * `gonio-btf`: compress, fit, synthesize;
//! * `gonio-brdf`, `gonio-devices`, `gonio-simulator`, `gonio-calibration` below them.
//!
//! The library crates' modules are re-exported under their old paths (`gonio::store`,
//! `gonio::session`, …) so that scripts and tests written against the single crate keep
//! compiling; new code names the crate that owns the module.

pub use gonio_acquire::{calibrate, develop, engine, plan, rig, session};
#[cfg(feature = "btf")]
pub use gonio_btf::{compress, fit, synthesize};
pub use gonio_dataset::{shard, store, sweep};

pub mod cli;
#[cfg(feature = "btf")]
pub mod merge;
pub mod slurm;
pub mod synth;
#[cfg(feature = "monitor")]
pub mod view;

#[cfg(test)]
mod layering;
