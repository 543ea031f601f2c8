//! What the two offset fits ([`crate::rig_geometry`]: camera axes and mount from target
//! corners, [`crate::light_geometry`]: lamp axes from a mirror's highlight) share: the check
//! of each view's axis positions and the parameter table they report.

use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};

/// One estimated parameter.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ParameterEstimate {
    /// `zero_offset.<axis name>` or `camera_rotation.<x|y|z>`.
    pub name: String,
    pub value_deg: f64,
    /// One-sigma uncertainty (LM covariance, residual variance as the noise estimate).
    pub sigma_deg: f64,
}

/// Why the axis positions `q` of one view cannot belong to a rig with `axes` axes (one
/// position per axis), or `None` when they can. The caller wraps the reason in its own
/// error with the view's label.
pub(crate) fn axis_count_problem(q: &[f64], axes: usize) -> Option<String> {
    (q.len() != axes).then(|| format!("{} axis positions for a rig with {axes} axes", q.len()))
}

/// One-sigma uncertainties (square roots of the diagonal, negative variances read as 0) and
/// the correlation matrix of a covariance. A zero σ has correlation 1 with itself and 0
/// with the others.
pub(crate) fn sigmas_and_correlation(cov: &DMatrix<f64>) -> (Vec<f64>, Vec<Vec<f64>>) {
    let n = cov.nrows();
    let sig: Vec<f64> = (0..n).map(|i| cov[(i, i)].max(0.0).sqrt()).collect();
    let correlation = (0..n)
        .map(|a| {
            (0..n)
                .map(|b| {
                    let d = sig[a] * sig[b];
                    if d > 0.0 {
                        cov[(a, b)] / d
                    } else if a == b {
                        1.0
                    } else {
                        0.0
                    }
                })
                .collect()
        })
        .collect();
    (sig, correlation)
}

/// The parameter table of a fit: each name with its value and σ, given in radians and
/// reported in degrees.
pub(crate) fn parameter_table(names: &[String], values_rad: &[f64], sigmas_rad: &[f64]) -> Vec<ParameterEstimate> {
    names
        .iter()
        .zip(values_rad.iter().zip(sigmas_rad))
        .map(|(name, (v, s))| ParameterEstimate {
            name: name.clone(),
            value_deg: v.to_degrees(),
            sigma_deg: s.to_degrees(),
        })
        .collect()
}
