//! gonio-btf: processing measured BTFs once they are stored.
//!
//! * [`compress`]: the field's compression methods, the `.gbtf` container and the UBO2014
//!   `.btf`, their readers (`compress::interp::BtfModel`) and the sharded passes.
//! * [`fit`]: analytic BRDF models (the `gonio-brdf` library) fitted to measured data,
//!   averaged or per texel.
//! * [`synthesize`]: growing a compressed BTF to any size.
//! * [`export`]: a fitted glTF SVBRDF written for renderers (glTF, MaterialX, USD, Mitsuba).
//!
//! Reads datasets through `gonio-dataset`; knows nothing of rigs or acquisition.

pub mod compress;
pub mod export;
pub mod fit;
pub mod synthesize;
