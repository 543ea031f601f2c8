//! Errors of the calibration crate.

use thiserror::Error;

/// Why a calibration step could not produce a trustworthy result.
///
/// Every fitting routine returns one of these instead of a numerically meaningless answer,
/// so callers (the rectifier) can fall back to another source of geometry.
#[derive(Clone, Debug, PartialEq, Error)]
pub enum CalibError {
    /// Fewer correspondences than the model has degrees of freedom allow.
    #[error("need at least {needed} point correspondences, got {got}")]
    TooFewPoints { needed: usize, got: usize },
    /// The correspondences do not determine the model (e.g. collinear points).
    #[error("degenerate point configuration: {0}")]
    Degenerate(String),
    /// An input coordinate is NaN or infinite.
    #[error("non-finite input coordinate at correspondence {index}")]
    NonFinite { index: usize },
}
