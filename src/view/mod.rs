//! Looking at the data: the CPU reference renderer (`gonio render`) and the browser
//! viewer's server (`gonio view`).
//!
//! * [`render`]: a BTF on a plane, sphere or cylinder under a directional light, seen by an
//!   orthographic camera (thesis ch. 7); the page's WebGL2 shader draws the same scene.
//! * [`params`]: parsing of the scene parameters, one parser for the CLI and the HTTP API.
//! * [`source`]: what is shown (a dataset, a `.gbtf`, a UBO2014 `.btf`).
//! * [`server`]: the HTTP server (axum) with its token, path and parameter checks.
//! * [`gpu`]: the factor blocks of the DFMF, median-cut and homomorphic GPU decoders.
//! * [`monitor`]: progress of a dataset being written, read from its journal.
//! * [`abrdf_cache`]: the texel-major cache of a raw dataset behind the inspect page's ABRDF.

pub mod abrdf_cache;
pub mod gpu;
pub mod monitor;
pub mod params;
pub mod render;
pub mod server;
pub mod source;
