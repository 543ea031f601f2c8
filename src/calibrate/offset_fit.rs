//! What the two offset-fit recipes ([`super::rig_geometry`]: camera axes and mount,
//! [`super::light_geometry`]: lamp axes) share around their fits: the planner's rig, the
//! rig with a fit applied, each parameter's error against the simulator's truth, the
//! direction errors over the Bonn pairs, the rig file's camera model and the figures of an
//! error-versus-effort row.

use gonio_calibration::intrinsics::CameraModel;
use gonio_calibration::rig_geometry::ParameterEstimate;
use gonio_devices::kinematics;
use gonio_devices::rig::RigSpec;
use serde::{Deserialize, Serialize};

/// Estimate against the simulator's truth, one parameter.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ParameterError {
    pub name: String,
    pub estimate_deg: f64,
    pub truth_deg: f64,
    pub error_deg: f64,
    pub sigma_deg: f64,
}

/// Angular errors (degrees) between the directions asked for and the directions the rig
/// really reaches, over every (light, view) pair of the Bonn set the planner can reach.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DirectionErrors {
    pub pairs: usize,
    pub view_max_deg: f64,
    pub view_mean_deg: f64,
    pub light_max_deg: f64,
    pub light_mean_deg: f64,
}

/// Direction errors when the planner uses `nominal` and the mechanism is `truth`: each Bonn
/// pair is solved by `nominal`'s IK (first solution) and evaluated by `truth`'s FK.
pub fn direction_errors(nominal: &RigSpec, truth: &RigSpec) -> DirectionErrors {
    let (kn, kt) = (kinematics::for_rig(nominal), kinematics::for_rig(truth));
    let dirs = crate::sweep::bonn81();
    let (mut n, mut vmax, mut vsum, mut lmax, mut lsum) = (0usize, 0.0f64, 0.0, 0.0f64, 0.0);
    for v in &dirs {
        for l in &dirs {
            let Ok(sols) = kn.inverse(*l, *v, None) else { continue };
            let Some(q) = sols.first() else { continue };
            let (lt, vt) = kt.forward(q);
            let (ev, el) = (vt.angle_to(*v).to_degrees(), lt.angle_to(*l).to_degrees());
            n += 1;
            vmax = vmax.max(ev);
            lmax = lmax.max(el);
            vsum += ev;
            lsum += el;
        }
    }
    let d = n.max(1) as f64;
    DirectionErrors {
        pairs: n,
        view_max_deg: vmax,
        view_mean_deg: vsum / d,
        light_max_deg: lmax,
        light_mean_deg: lsum / d,
    }
}

/// The rig file's camera as a calibrated camera model (intrinsics + distortion options).
pub(super) fn camera_model(spec: &RigSpec) -> CameraModel {
    let k = spec.camera.intrinsics();
    let mut distortion = [0.0; 5];
    for (i, key) in ["k1", "k2", "p1", "p2", "k3"].iter().enumerate() {
        if let Some(v) = spec.camera.options.get(*key) {
            distortion[i] = v.as_float().or_else(|| v.as_integer().map(|x| x as f64)).unwrap_or(0.0);
        }
    }
    CameraModel {
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        distortion,
    }
}

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
