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
    let dirs = gonio_dataset::sweep::bonn81();
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
pub(super) fn camera_model(spec: &RigSpec) -> Result<CameraModel, gonio_devices::rig::OptionError> {
    let k = spec.camera.intrinsics();
    Ok(CameraModel {
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        distortion: spec.camera.distortion()?,
    })
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

/// The one-sigma direction uncertainty of an offset fit over the Bonn pairs, propagated
/// from the fit's parameter covariance, and on the simulator the true direction error next
/// to it.
///
/// For each reachable pair, the axes are those the corrected rig's inverse kinematics
/// commands; the reached light and view directions are differentiated with respect to each
/// fitted parameter by central differences (± 1e-3°) of the forward kinematics, `J` (3 × n);
/// the direction's covariance is `J Σ Jᵀ` with `Σ` the fit's covariance (sigmas and
/// correlation). The sigma reported is the square root of its largest eigenvalue: the
/// worst direction, as an angle.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct DirectionUncertainty {
    pub pairs: usize,
    pub view_sigma_max_deg: f64,
    pub view_sigma_mean_deg: f64,
    pub light_sigma_max_deg: f64,
    pub light_sigma_mean_deg: f64,
    /// Simulator only: the largest true error over the pairs in units of that pair's
    /// sigma (view, light); `None` where the fit does not move that direction (sigma 0).
    pub view_max_error_over_sigma: Option<f64>,
    pub light_max_error_over_sigma: Option<f64>,
    /// Simulator only: fraction of pairs whose true error exceeds 3 sigma (view, light).
    pub view_beyond_3_sigma_fraction: Option<f64>,
    pub light_beyond_3_sigma_fraction: Option<f64>,
}

/// A copy of `spec` with fitted parameter `name` (`zero_offset.AXIS` or
/// `camera_rotation.x|y|z`, degrees) moved by `delta_deg`.
fn nudged(spec: &RigSpec, name: &str, delta_deg: f64) -> RigSpec {
    let mut r = spec.clone();
    let mut a = r.alignment.clone().unwrap_or_default();
    if let Some(axis) = name.strip_prefix("zero_offset.") {
        *a.axis_zero_offset_deg.entry(axis.to_string()).or_insert(0.0) += delta_deg;
    } else if let Some(c) = name.strip_prefix("camera_rotation.") {
        let k = match c {
            "x" => 0,
            "y" => 1,
            _ => 2,
        };
        a.camera_rotation_deg[k] += delta_deg;
    }
    r.alignment = Some(a);
    r
}

/// [`DirectionUncertainty`] of a fit (`parameters`, `correlation`) already applied to
/// `corrected`; `truth` is the simulated mechanism.
pub fn direction_uncertainty(
    corrected: &RigSpec,
    parameters: &[ParameterEstimate],
    correlation: &[Vec<f64>],
    truth: Option<&RigSpec>,
) -> DirectionUncertainty {
    use nalgebra::{DMatrix, Matrix3, SymmetricEigen, Vector3};
    const H_DEG: f64 = 1e-3;
    let n = parameters.len();
    let cov = DMatrix::from_fn(n, n, |i, j| {
        let c = correlation.get(i).and_then(|r| r.get(j).copied()).unwrap_or(0.0);
        let c = if c.is_finite() { c } else { 0.0 };
        parameters[i].sigma_deg * parameters[j].sigma_deg * c
    });
    let k0 = kinematics::for_rig(corrected);
    let nudges: Vec<_> = parameters
        .iter()
        .map(|p| {
            (
                kinematics::for_rig(&nudged(corrected, &p.name, H_DEG)),
                kinematics::for_rig(&nudged(corrected, &p.name, -H_DEG)),
            )
        })
        .collect();
    let kt = truth.map(kinematics::for_rig);
    let v3 = |d: gonio_devices::Direction| {
        let v = d.vector();
        Vector3::new(v.x, v.y, v.z)
    };
    let sigma = |jac: &DMatrix<f64>| -> f64 {
        let c = jac * &cov * jac.transpose();
        let m = Matrix3::from_fn(|i, j| c[(i, j)]);
        let e = SymmetricEigen::new(m).eigenvalues.max().max(0.0);
        e.sqrt().to_degrees() // unit vector per degree × degree → radians
    };
    let dirs = gonio_dataset::sweep::bonn81();
    let mut out = DirectionUncertainty {
        pairs: 0,
        view_sigma_max_deg: 0.0,
        view_sigma_mean_deg: 0.0,
        light_sigma_max_deg: 0.0,
        light_sigma_mean_deg: 0.0,
        view_max_error_over_sigma: None,
        light_max_error_over_sigma: None,
        view_beyond_3_sigma_fraction: None,
        light_beyond_3_sigma_fraction: None,
    };
    // (max ratio, beyond count) for view and light; a zero sigma with an error counts as beyond
    let mut stats = [(0.0f64, 0usize, false); 2];
    for v in &dirs {
        for l in &dirs {
            let Ok(sols) = k0.inverse(*l, *v, None) else { continue };
            let Some(q) = sols.first() else { continue };
            let (mut jl, mut jv) = (DMatrix::zeros(3, n), DMatrix::zeros(3, n));
            for (k, (kp, km)) in nudges.iter().enumerate() {
                let ((lp, vp), (lm, vm)) = (kp.forward(q), km.forward(q));
                let dl = (v3(lp) - v3(lm)) / (2.0 * H_DEG);
                let dv = (v3(vp) - v3(vm)) / (2.0 * H_DEG);
                jl.set_column(k, &dl);
                jv.set_column(k, &dv);
            }
            let (sl, sv) = (sigma(&jl), sigma(&jv));
            out.pairs += 1;
            out.view_sigma_max_deg = out.view_sigma_max_deg.max(sv);
            out.light_sigma_max_deg = out.light_sigma_max_deg.max(sl);
            out.view_sigma_mean_deg += sv;
            out.light_sigma_mean_deg += sl;
            if let Some(kt) = &kt {
                let (lt, vt) = kt.forward(q);
                let errors = [vt.angle_to(*v).to_degrees(), lt.angle_to(*l).to_degrees()];
                for (s, (e, sg)) in stats.iter_mut().zip(errors.into_iter().zip([sv, sl])) {
                    // errors far below the kinematics' numerical floor are no errors
                    if e < 1e-9 {
                        continue;
                    }
                    if sg > 0.0 {
                        s.0 = s.0.max(e / sg);
                        s.2 = true;
                    }
                    if e > 3.0 * sg {
                        s.1 += 1;
                    }
                }
            }
        }
    }
    let d = out.pairs.max(1) as f64;
    out.view_sigma_mean_deg /= d;
    out.light_sigma_mean_deg /= d;
    if kt.is_some() {
        out.view_max_error_over_sigma = stats[0].2.then_some(stats[0].0);
        out.light_max_error_over_sigma = stats[1].2.then_some(stats[1].0);
        out.view_beyond_3_sigma_fraction = Some(stats[0].1 as f64 / d);
        out.light_beyond_3_sigma_fraction = Some(stats[1].1 as f64 / d);
    }
    out
}
