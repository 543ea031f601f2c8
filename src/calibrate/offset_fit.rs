//! What the two offset-fit recipes ([`super::rig_geometry`]: camera axes and mount,
//! [`super::light_geometry`]: lamp axes) share around their fits: the planner's rig, the
//! rig with a fit applied, each parameter's error against the simulator's truth and the
//! figures of an error-versus-effort row.

use super::rig_geometry::ParameterError;
use gonio_calibration::rig_geometry::ParameterEstimate;
use gonio_devices::rig::RigSpec;

/// The rig as the planner knows it: the rig file without its simulator-only truth
/// (`[sim_misalignment]`).
pub(super) fn nominal_rig(spec: &RigSpec) -> RigSpec {
    let mut r = spec.clone();
    r.sim_misalignment = None;
    r
}

/// A copy of `nominal` with a fit written into its `[alignment]` by `apply` (the fit's own
/// `apply`).
pub(super) fn corrected(nominal: &RigSpec, apply: impl FnOnce(&mut RigSpec)) -> RigSpec {
    let mut r = nominal.clone();
    apply(&mut r);
    r
}

impl ParameterError {
    /// `p` against its true value `truth_deg`.
    pub(super) fn new(p: &ParameterEstimate, truth_deg: f64) -> ParameterError {
        ParameterError {
            name: p.name.clone(),
            estimate_deg: p.value_deg,
            truth_deg,
            error_deg: p.value_deg - truth_deg,
            sigma_deg: p.sigma_deg,
        }
    }
}

/// The figures of one error-versus-effort row (the fit on the first k views or poses);
/// each recipe's row type adds its count and says which direction error it reports.
pub(super) struct EffortFigures {
    pub rms_px: Option<f64>,
    pub max_parameter_error_deg: Option<f64>,
    /// Largest direction error over the Bonn pairs after applying the fit (simulator).
    pub max_direction_error_deg: Option<f64>,
    pub failure: Option<String>,
}

impl EffortFigures {
    /// A fit with `parameters` and `rms_px`. Its largest parameter error is taken against
    /// the truth where there is one (`truth_errors`, simulator), else against `reference`
    /// (the fit with all views: on a real rig, how far fewer views move the estimate).
    pub(super) fn of_fit(
        parameters: &[ParameterEstimate],
        rms_px: f64,
        truth_errors: Option<Vec<ParameterError>>,
        reference: &[ParameterEstimate],
        max_direction_error_deg: Option<f64>,
    ) -> EffortFigures {
        let max_parameter_error_deg = match truth_errors {
            Some(e) => e.iter().map(|p| p.error_deg.abs()).fold(0.0, f64::max),
            None => parameters
                .iter()
                .zip(reference)
                .map(|(a, b)| (a.value_deg - b.value_deg).abs())
                .fold(0.0, f64::max),
        };
        EffortFigures {
            rms_px: Some(rms_px),
            max_parameter_error_deg: Some(max_parameter_error_deg),
            max_direction_error_deg,
            failure: None,
        }
    }

    /// A fit that was refused, and why.
    pub(super) fn refused(why: impl ToString) -> EffortFigures {
        EffortFigures {
            rms_px: None,
            max_parameter_error_deg: None,
            max_direction_error_deg: None,
            failure: Some(why.to_string()),
        }
    }
}
