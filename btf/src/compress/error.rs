//! [`CompressError`], the one error type of the compression pipeline (its own file so
//! that every method file can name it without importing the module root).

use gonio_dataset::store::StoreError;
use std::path::PathBuf;

/// Errors of the compression pipeline.
#[derive(Debug, thiserror::Error)]
pub enum CompressError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("dataset {dir}: {reason}")]
    Dataset { dir: PathBuf, reason: String },
    #[error(
        "{path}: measurement {index} (light {light_deg:?}°, view {view_deg:?}°) has a non-finite value {value} \
         at texel {texel}"
    )]
    NonFinite {
        path: PathBuf,
        index: usize,
        light_deg: [f64; 2],
        view_deg: [f64; 2],
        texel: usize,
        value: f32,
    },
    #[error("{path}: corrupt .gbtf file: {reason}")]
    Corrupt { path: PathBuf, reason: String },
    #[error("invalid input: {0}")]
    Invalid(String),
    #[error("SVD failed: {0}")]
    Svd(String),
    /// An exact lookup (`CompressedBtf::reconstruct_deg`) of a direction that is not on the
    /// grid; `interp::reconstruct_at` interpolates instead.
    #[error("{which} direction {deg:?}° is not one of the measured directions (use interpolation)")]
    NotMeasured { which: &'static str, deg: [f64; 2] },
    /// Interpolation refuses to extrapolate far from every measurement.
    #[error(
        "{which} direction {deg:?}° is {gap_deg:.1}° from the nearest measured direction; \
         interpolation uses measurements within {limit_deg}°"
    )]
    TooFar {
        which: &'static str,
        deg: [f64; 2],
        gap_deg: f64,
        limit_deg: f64,
    },
}
