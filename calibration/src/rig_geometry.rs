//! Rig geometry: axis zero offsets and the camera's mounting rotation, estimated from
//! images of a planar target over many axis positions (a bundle adjustment over all views
//! at once).
//!
//! Model: a target corner `X` (board frame = sample frame, z = 0) is seen at pixel
//! `π(K, pose(q + δ; R_m) · X)`, where `q` are the commanded axis positions, `δ` the axis
//! zero offsets, `R_m` the camera's mounting rotation, `pose` the rig kind's camera pose
//! (the kinematics of `gonio-devices` with an [`AlignmentSpec`]) and `π` the calibrated
//! camera (intrinsics and distortion, held fixed). Levenberg-Marquardt minimises the
//! reprojection error in pixels over every corner of every view.
//!
//! Why not per-view poses first (as Zhang does) and a fit to them after: the views share
//! the offsets, so fitting all corners at once weighs each view by what it actually
//! constrains and gives one covariance for the parameters that matter.
//!
//! What images cannot tell: axes that move only the lamp do not change the camera's view
//! of the target; they are reported as unobserved, not estimated. Parameters whose effects
//! on the images are (nearly) the same for the given views — the turntable's offset and
//! the camera's roll when every view looks straight down — make the normal equations
//! singular; the fit is then refused with the parameters named, never returned.
//!
//! The checkerboard is 4-fold symmetric, so its detected grid can be any quarter turn of
//! the true one: each view is relabelled to the quarter turn the nominal model (zero
//! offsets) predicts best. That is unambiguous while the misalignment is far below 45°.

use crate::intrinsics::CameraModel;
pub use crate::offset_fit::ParameterEstimate;
use crate::offset_fit::{axis_count_problem, parameter_table, sigmas_and_correlation};
use gonio_devices::kinematics;
use gonio_devices::rig::{AlignmentSpec, RigKind, RigSpec};
use gonio_devices::Vec3;
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// One view: commanded axis positions and the target corners seen there.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RigView {
    /// A name for messages (e.g. the recipe pose it was captured at).
    pub label: String,
    /// Commanded axis positions (radians, the rig file's axis order).
    pub q: Vec<f64>,
    /// Board points (mm, board frame, up to the board's 4-fold symmetry).
    pub object: Vec<[f64; 2]>,
    /// Their pixels (gonio's convention: pixel centres at half-integers).
    pub image: Vec<[f64; 2]>,
}

/// When to stop and when to refuse.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RigGeometryOptions {
    pub min_views: usize,
    pub min_points_per_view: usize,
    pub max_iterations: usize,
    /// Largest accepted condition number of the column-normalised Jacobian. Separable
    /// parameters give tens to thousands; an exactly confounded pair gives > 1e8.
    pub max_condition: f64,
    /// A fit whose reprojection RMS (px) is above this does not describe the rig (wrong
    /// intrinsics, wrong target, a misalignment the model has no parameter for).
    pub max_rms_px: f64,
}

impl Default for RigGeometryOptions {
    fn default() -> Self {
        RigGeometryOptions {
            min_views: 3,
            min_points_per_view: 8,
            max_iterations: 100,
            max_condition: 1e5,
            max_rms_px: 2.0,
        }
    }
}

/// The result of [`estimate_rig_geometry`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RigGeometryFit {
    /// The estimate as the kinematics take it (degrees): offsets of the observed axes and
    /// the camera mounting rotation.
    pub alignment: AlignmentSpec,
    pub parameters: Vec<ParameterEstimate>,
    /// Correlation matrix of `parameters` (same order).
    pub correlation: Vec<Vec<f64>>,
    /// Axes that do not move the camera relative to the target (the lamp's): not estimated.
    pub unobserved_axes: Vec<String>,
    /// Condition number of the column-normalised Jacobian at the solution.
    pub condition: f64,
    pub rms_px: f64,
    /// Reprojection RMS with the nominal (ideal) kinematics, before the fit.
    pub initial_rms_px: f64,
    pub view_rms_px: Vec<f64>,
    /// Quarter turns applied to each view's board labels (see the module doc).
    pub grid_quarter_turns: Vec<u8>,
    pub iterations: usize,
    pub points: usize,
}

impl RigGeometryFit {
    /// Feed the estimate into a rig description, so its kinematics (planner, IK,
    /// rectification by pose) use the true geometry: commanded directions become true
    /// directions. Offsets of unobserved axes already in `rig.alignment` are kept.
    pub fn apply(&self, rig: &mut RigSpec) {
        let mut a = rig.alignment.clone().unwrap_or_default();
        for (k, v) in &self.alignment.axis_zero_offset_deg {
            a.axis_zero_offset_deg.insert(k.clone(), *v);
        }
        a.camera_rotation_deg = self.alignment.camera_rotation_deg;
        rig.alignment = Some(a);
    }
}

#[derive(Clone, Debug, PartialEq, Error)]
pub enum RigGeometryError {
    #[error("rig geometry: rig `{rig}` is of kind {kind:?}; only `two-arm` rigs have an alignment model")]
    Unsupported { rig: String, kind: RigKind },
    #[error("rig geometry: {got} views, need at least {needed}")]
    TooFewViews { needed: usize, got: usize },
    #[error("rig geometry: view `{view}`: {reason}")]
    BadView { view: String, reason: String },
    #[error(
        "rig geometry: these views do not determine {parameters:?} (condition {condition:.3e} > {max:.0e}): {hint}"
    )]
    Undetermined {
        parameters: Vec<String>,
        condition: f64,
        max: f64,
        hint: String,
    },
    #[error("rig geometry: no axis moves the camera relative to the target; nothing to estimate")]
    NothingObservable,
    #[error("rig geometry: reprojection RMS {rms_px:.3} px after the fit (limit {max_px} px): the model does not describe these images (wrong intrinsics or target, or a misalignment it has no parameter for)")]
    PoorFit { rms_px: f64, max_px: f64 },
}

/// The parameter vector's meaning: which axes' offsets, then the 3 mount angles.
struct Model<'a> {
    rig: &'a RigSpec,
    camera: &'a CameraModel,
    axes: Vec<usize>,
}

impl Model<'_> {
    fn n(&self) -> usize {
        self.axes.len() + 3
    }

    fn alignment(&self, p: &[f64]) -> AlignmentSpec {
        let mut a = AlignmentSpec::default();
        for (k, &i) in self.axes.iter().enumerate() {
            a.axis_zero_offset_deg
                .insert(self.rig.axes[i].name.clone(), p[k].to_degrees());
        }
        let m = self.axes.len();
        a.camera_rotation_deg = [p[m].to_degrees(), p[m + 1].to_degrees(), p[m + 2].to_degrees()];
        a
    }

    fn names(&self) -> Vec<String> {
        let mut v: Vec<String> = self
            .axes
            .iter()
            .map(|&i| format!("zero_offset.{}", self.rig.axes[i].name))
            .collect();
        v.extend(["x", "y", "z"].iter().map(|c| format!("camera_rotation.{c}")));
        v
    }

    /// Residuals (pixels) of every corner of every view, `[du, dv, …]`.
    fn residuals(&self, p: &[f64], views: &[RigView], turns: &[u8]) -> Vec<f64> {
        let mut spec = self.rig.clone();
        spec.alignment = Some(self.alignment(p));
        spec.sim_misalignment = None;
        let k = kinematics::for_rig(&spec);
        let mut out = Vec::new();
        for (v, &t) in views.iter().zip(turns) {
            let pose = k.camera_pose(&v.q);
            for (o, i) in v.object.iter().zip(&v.image) {
                let [x, y] = quarter_turn(*o, t);
                let c = pose.to_camera(Vec3::new(x, y, 0.0));
                let (u, w) = if c.z > 1e-9 {
                    self.camera.project_point([c.x, c.y, c.z])
                } else {
                    // behind the camera: a large, smooth penalty instead of a NaN
                    (1e6, 1e6)
                };
                out.push(u - i[0]);
                out.push(w - i[1]);
            }
        }
        out
    }

    /// Central-difference Jacobian (the kinematics are not differentiated symbolically: the
    /// same code serves every rig kind that gets an alignment model).
    fn jacobian(&self, p: &[f64], views: &[RigView], turns: &[u8], m: usize) -> DMatrix<f64> {
        let h = 1e-6;
        let mut j = DMatrix::zeros(m, self.n());
        for c in 0..self.n() {
            let mut a = p.to_vec();
            let mut b = p.to_vec();
            a[c] += h;
            b[c] -= h;
            let (ra, rb) = (self.residuals(&a, views, turns), self.residuals(&b, views, turns));
            for r in 0..m {
                j[(r, c)] = (ra[r] - rb[r]) / (2.0 * h);
            }
        }
        j
    }
}

/// Board point turned by `t` quarter turns about the board's centre.
fn quarter_turn(o: [f64; 2], t: u8) -> [f64; 2] {
    match t % 4 {
        0 => o,
        1 => [-o[1], o[0]],
        2 => [-o[0], -o[1]],
        _ => [o[1], -o[0]],
    }
}

fn sum_sq(r: &[f64]) -> f64 {
    r.iter().map(|x| x * x).sum()
}

/// Condition number and the right singular vector of the smallest singular value of the
/// column-normalised Jacobian (zero columns count as infinitely ill-conditioned).
fn conditioning(j: &DMatrix<f64>) -> (f64, DVector<f64>) {
    let mut jn = j.clone();
    for mut col in jn.column_iter_mut() {
        let n = col.norm();
        if n > 0.0 {
            col /= n;
        }
    }
    let svd = jn.svd(false, true);
    let s = &svd.singular_values;
    let (imin, smin) = s
        .iter()
        .enumerate()
        .fold((0, f64::INFINITY), |b, (i, &x)| if x < b.1 { (i, x) } else { b });
    let smax = s.iter().cloned().fold(0.0, f64::max);
    let vt = svd.v_t.expect("requested");
    let cond = if smin > 0.0 { smax / smin } else { f64::INFINITY };
    (cond, vt.row(imin).transpose())
}

/// Estimate the axis zero offsets and the camera mounting rotation of `rig` from target
/// views. `rig` gives the ideal kinematics (any `alignment` in it is ignored: the estimate
/// is absolute); `camera` the calibrated intrinsics, held fixed.
pub fn estimate_rig_geometry(
    rig: &RigSpec,
    camera: &CameraModel,
    views: &[RigView],
    opts: &RigGeometryOptions,
) -> Result<RigGeometryFit, RigGeometryError> {
    if rig.kind != RigKind::TwoArm {
        return Err(RigGeometryError::Unsupported {
            rig: rig.name.clone(),
            kind: rig.kind,
        });
    }
    let needed = opts.min_views.max(1);
    if views.len() < needed {
        return Err(RigGeometryError::TooFewViews {
            needed,
            got: views.len(),
        });
    }
    for v in views {
        let bad = |reason: String| RigGeometryError::BadView {
            view: v.label.clone(),
            reason,
        };
        if let Some(reason) = axis_count_problem(&v.q, rig.axes.len()) {
            return Err(bad(reason));
        }
        if v.object.len() != v.image.len() {
            return Err(bad(format!(
                "{} board points but {} image points",
                v.object.len(),
                v.image.len()
            )));
        }
        if v.object.len() < opts.min_points_per_view {
            return Err(bad(format!(
                "{} points, need at least {}",
                v.object.len(),
                opts.min_points_per_view
            )));
        }
        let finite = v.q.iter().all(|x| x.is_finite())
            && v.object.iter().chain(&v.image).all(|p| p.iter().all(|x| x.is_finite()));
        if !finite {
            return Err(bad("non-finite axis position or point".into()));
        }
    }
    let all_axes = Model {
        rig,
        camera,
        axes: (0..rig.axes.len()).collect(),
    };
    let p0 = vec![0.0; all_axes.n()];
    // Board labels: the quarter turn the nominal model predicts best, per view.
    let turns: Vec<u8> = views
        .iter()
        .map(|v| {
            (0..4u8)
                .min_by(|&a, &b| {
                    let ra = sum_sq(&all_axes.residuals(&p0, std::slice::from_ref(v), &[a]));
                    let rb = sum_sq(&all_axes.residuals(&p0, std::slice::from_ref(v), &[b]));
                    ra.total_cmp(&rb)
                })
                .unwrap_or(0)
        })
        .collect();
    let r0 = all_axes.residuals(&p0, views, &turns);
    let m = r0.len();
    let points = m / 2;
    let initial_rms_px = (sum_sq(&r0) / points.max(1) as f64).sqrt();
    // Observability: an axis whose offset does not change any residual moves only the lamp.
    let j_all = all_axes.jacobian(&p0, views, &turns, m);
    let scale = j_all.column_iter().map(|c| c.norm()).fold(0.0, f64::max);
    let mut observed = Vec::new();
    let mut unobserved_axes = Vec::new();
    for (i, a) in rig.axes.iter().enumerate() {
        if j_all.column(i).norm() > 1e-9 * scale.max(1e-300) {
            observed.push(i);
        } else {
            unobserved_axes.push(a.name.clone());
        }
    }
    if observed.is_empty() {
        return Err(RigGeometryError::NothingObservable);
    }
    let model = Model {
        rig,
        camera,
        axes: observed,
    };
    let n = model.n();
    let names = model.names();
    let check = |j: &DMatrix<f64>| -> Result<f64, RigGeometryError> {
        let (cond, null) = conditioning(j);
        if cond.is_finite() && cond <= opts.max_condition {
            return Ok(cond);
        }
        let parameters: Vec<String> = null
            .iter()
            .zip(&names)
            .filter(|(x, _)| x.abs() >= 0.25)
            .map(|(_, n)| n.clone())
            .collect();
        Err(RigGeometryError::Undetermined {
            hint: hint(rig, views, &parameters),
            parameters,
            condition: cond,
            max: opts.max_condition,
        })
    };
    // Levenberg-Marquardt (Marquardt's diagonal scaling).
    let mut p = vec![0.0; n];
    let mut r = model.residuals(&p, views, &turns);
    let mut cost = sum_sq(&r);
    let mut lambda = 1e-3;
    let mut iterations = 0;
    let mut j = model.jacobian(&p, views, &turns, m);
    check(&j)?;
    for it in 0..opts.max_iterations {
        iterations = it + 1;
        let jtj = j.transpose() * &j;
        let g = j.transpose() * DVector::from_vec(r.clone());
        let mut improved = false;
        for _ in 0..30 {
            let mut a = jtj.clone();
            for d in 0..n {
                a[(d, d)] += lambda * jtj[(d, d)].max(1e-12);
            }
            let Some(step) = a.cholesky().map(|c| c.solve(&(-&g))) else {
                lambda *= 10.0;
                continue;
            };
            let cand: Vec<f64> = p.iter().zip(step.iter()).map(|(x, s)| x + s).collect();
            let rc = model.residuals(&cand, views, &turns);
            let cc = sum_sq(&rc);
            if cc < cost {
                let small = step.norm() < 1e-12 * (1.0 + p.iter().map(|x| x * x).sum::<f64>().sqrt());
                let rel = (cost - cc) / cost.max(1e-300);
                p = cand;
                r = rc;
                cost = cc;
                lambda = (lambda / 10.0).max(1e-12);
                improved = !(small || rel < 1e-14);
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
        j = model.jacobian(&p, views, &turns, m);
    }
    let condition = check(&j)?;
    let rms_px = (cost / points.max(1) as f64).sqrt();
    if rms_px.is_nan() || rms_px > opts.max_rms_px {
        return Err(RigGeometryError::PoorFit {
            rms_px,
            max_px: opts.max_rms_px,
        });
    }
    // Covariance: σ² (JᵀJ)⁻¹ with σ² the residual variance per coordinate.
    let dof = m.saturating_sub(n).max(1);
    let s2 = cost / dof as f64;
    let jtj = j.transpose() * &j;
    let cov = jtj
        .clone()
        .pseudo_inverse(1e-300)
        .unwrap_or_else(|_| DMatrix::from_element(n, n, f64::NAN))
        * s2;
    let (sig, correlation) = sigmas_and_correlation(&cov);
    let mut view_rms_px = Vec::with_capacity(views.len());
    let mut off = 0;
    for v in views {
        let k = 2 * v.object.len();
        view_rms_px.push((sum_sq(&r[off..off + k]) / v.object.len() as f64).sqrt());
        off += k;
    }
    let parameters = parameter_table(&names, &p, &sig);
    Ok(RigGeometryFit {
        alignment: model.alignment(&p),
        parameters,
        correlation,
        unobserved_axes,
        condition,
        rms_px,
        initial_rms_px,
        view_rms_px,
        grid_quarter_turns: turns,
        iterations,
        points,
    })
}

/// What to add to the pose set, for the parameters a degenerate fit could not separate.
fn hint(rig: &RigSpec, views: &[RigView], parameters: &[String]) -> String {
    let arc = rig.axis_by_role("camera_elevation");
    let turn = rig.axis_by_role("sample_rotation");
    if let (Some((ia, arc)), Some((it, turn))) = (arc, turn) {
        let all_pole = views.iter().all(|v| v.q[ia].abs() < 1e-3);
        if all_pole && parameters.iter().any(|p| p.ends_with(&turn.name)) {
            return format!(
                "every view has `{}` at 0° (camera straight above the sample), where turning `{}` looks exactly like rolling the camera about its optical axis; add views with the camera tilted (θ ≠ 0)",
                arc.name, turn.name
            );
        }
        let span = |i: usize| {
            let (lo, hi) = views.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
                (l.min(v.q[i]), h.max(v.q[i]))
            });
            (hi - lo).to_degrees()
        };
        return format!(
            "add views that spread the camera more widely (`{}` spans {:.1}°, `{}` spans {:.1}° in these views)",
            arc.name,
            span(ia),
            turn.name,
            span(it)
        );
    }
    "add views at more varied axis positions".into()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> CameraModel {
        CameraModel {
            fx: 1100.0,
            fy: 1100.0,
            cx: 391.5,
            cy: 313.25,
            distortion: [0.0; 5],
        }
    }

    fn rig() -> RigSpec {
        let mut r = RigSpec::default_rig();
        r.geometry.camera_distance_mm = 300.0;
        r.geometry.light_distance_mm = 600.0;
        r.geometry.camera_body_radius_mm = 30.0;
        r
    }

    fn truth() -> AlignmentSpec {
        AlignmentSpec {
            axis_zero_offset_deg: [("turntable".to_string(), 0.8), ("camera_arc".to_string(), -0.5)]
                .into_iter()
                .collect(),
            camera_rotation_deg: [0.3, -0.4, 0.6],
        }
    }

    /// Exact projections of an 11 × 11 board (5 mm) through the true rig, labels turned by
    /// `turn` quarter turns as a symmetric board's detector may report them.
    fn views(qs: &[[f64; 2]], turn: u8) -> Vec<RigView> {
        let mut t = rig();
        t.alignment = Some(truth());
        let k = kinematics::for_rig(&t);
        let cam = camera();
        qs.iter()
            .enumerate()
            .map(|(n, [a, e])| {
                let q = vec![a.to_radians(), e.to_radians(), 0.0, 0.0];
                let pose = k.camera_pose(&q);
                let mut object = Vec::new();
                let mut image = Vec::new();
                for j in 0..11 {
                    for i in 0..11 {
                        let o = [(i as f64 - 5.0) * 5.0, (j as f64 - 5.0) * 5.0];
                        let c = pose.to_camera(Vec3::new(o[0], o[1], 0.0));
                        let (u, v) = cam.project_point([c.x, c.y, c.z]);
                        // label as the detector might: the board point turned back
                        object.push(quarter_turn(o, (4 - turn % 4) % 4));
                        image.push([u, v]);
                    }
                }
                RigView {
                    label: format!("v{n}"),
                    q,
                    object,
                    image,
                }
            })
            .collect()
    }

    #[test]
    fn recovers_the_truth_from_exact_corners() {
        let qs = [
            [0.0, 0.0],
            [30.0, 25.0],
            [120.0, 40.0],
            [-60.0, -35.0],
            [200.0 - 20.0, 55.0],
        ];
        let fit = estimate_rig_geometry(&rig(), &camera(), &views(&qs, 1), &Default::default()).unwrap();
        assert_eq!(fit.unobserved_axes, vec!["light_base", "light_arc"]);
        assert!(
            fit.grid_quarter_turns.iter().all(|&t| t == 1),
            "{:?}",
            fit.grid_quarter_turns
        );
        let t = truth();
        for (k, v) in &t.axis_zero_offset_deg {
            let e = fit.alignment.axis_zero_offset_deg[k];
            assert!((e - v).abs() < 1e-6, "{k}: {e} vs {v}");
        }
        for c in 0..3 {
            assert!((fit.alignment.camera_rotation_deg[c] - t.camera_rotation_deg[c]).abs() < 1e-6);
        }
        assert!(fit.rms_px < 1e-6 && fit.initial_rms_px > 1.0, "{fit:?}");
        let mut r = rig();
        fit.apply(&mut r);
        assert_eq!(r.alignment.as_ref().unwrap().axis_zero_offset_deg.len(), 2);
    }

    #[test]
    fn straight_down_views_leave_the_turntable_undetermined() {
        let qs = [[0.0, 0.0], [60.0, 0.0], [150.0, 0.0], [-90.0, 0.0]];
        let e = estimate_rig_geometry(&rig(), &camera(), &views(&qs, 0), &Default::default()).unwrap_err();
        match &e {
            RigGeometryError::Undetermined { parameters, hint, .. } => {
                assert!(parameters.iter().any(|p| p == "zero_offset.turntable"), "{e}");
                assert!(parameters.iter().any(|p| p == "camera_rotation.z"), "{e}");
                assert!(hint.contains("θ ≠ 0"), "{e}");
            }
            _ => panic!("{e}"),
        }
    }

    #[test]
    fn bad_inputs_are_named() {
        let mut v = views(&[[0.0, 20.0], [90.0, 30.0], [180.0, 40.0]], 0);
        v[1].image.pop();
        let e = estimate_rig_geometry(&rig(), &camera(), &v, &Default::default()).unwrap_err();
        assert!(
            matches!(&e, RigGeometryError::BadView { view, .. } if view == "v1"),
            "{e}"
        );
        let e = estimate_rig_geometry(&rig(), &camera(), &v[..2], &Default::default()).unwrap_err();
        assert!(matches!(e, RigGeometryError::TooFewViews { .. }), "{e}");
    }
}
