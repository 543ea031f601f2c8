//! gonio-dataset: the on-disk contract of a gonio acquisition, the floor every other gonio
//! crate stands on.
//!
//! * [`sweep`]: which (light, view) directions a dataset holds, and their grid.
//! * [`shard`]: which part of a job a process runs (`--shard I/N`), a value every heavy job reads.
//! * [`store`]: the dataset directory and its one writer ([`store::Dataset`]): manifest,
//!   journal, images, durability; the exports (UBO2003, npy, Zarr) and the UBO2003 import.
//!
//! Nothing here knows how a dataset was acquired or how it will be compressed: acquisition
//! (`gonio-acquire`) and processing (`gonio-btf`) both read and write through this crate.

pub mod shard;
pub mod store;
pub mod sweep;
