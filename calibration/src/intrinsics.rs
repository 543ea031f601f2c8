//! Camera intrinsics and lens distortion from views of a planar target (Zhang's method).
//!
//! 1. One homography per view ([`Homography::fit`]: normalized DLT + LM).
//! 2. Closed-form intrinsics from the homographies: every view gives two linear
//!    constraints on `B = K⁻ᵀK⁻¹` (its first two columns are images of orthonormal
//!    vectors); with zero skew as a third constraint the stacked system `V b = 0` is solved
//!    by SVD and `K` recovered from the Cholesky factor of `B`. The condition number of `V`
//!    is the degeneracy diagnostic: views whose target planes are (nearly) parallel give
//!    the same two rows, so `V` loses rank and the fit is refused instead of returned.
//! 3. Per-view poses from `K⁻¹H`, then Levenberg-Marquardt over all corners of all views
//!    on the reprojection error in pixels: `fx, fy, cx, cy`, the OpenCV distortion model
//!    (`k1, k2, p1, p2[, k3]`) and six pose parameters per view (Rodrigues vector and
//!    translation, the OpenCV convention, so results compare directly with
//!    `cv2.calibrateCamera`).
//!
//! Pixel convention: gonio's (pixel (i, j) has its centre at (i + ½, j + ½)). OpenCV puts
//! pixel centres at integers, so its `cx, cy` are ours minus ½.

use crate::{CalibError, Homography};
use nalgebra::{DMatrix, DVector, Matrix3, Rotation3, Vector3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// One view of the planar target: target points (mm, on z = 0) and their pixels.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TargetView {
    /// A name for messages (e.g. the pose it was captured at).
    pub label: String,
    pub object: Vec<[f64; 2]>,
    pub image: Vec<[f64; 2]>,
}

/// Which distortion coefficients are estimated (the others stay 0).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum DistortionModel {
    /// Pinhole only.
    None,
    /// `k1, k2`.
    Radial,
    /// `k1, k2, p1, p2` (OpenCV with `CALIB_FIX_K3`).
    #[default]
    Opencv4,
    /// `k1, k2, p1, p2, k3` (OpenCV's default).
    Opencv5,
}

impl DistortionModel {
    /// Indices into `[k1, k2, p1, p2, k3]` of the estimated coefficients.
    fn free(self) -> &'static [usize] {
        match self {
            DistortionModel::None => &[],
            DistortionModel::Radial => &[0, 1],
            DistortionModel::Opencv4 => &[0, 1, 2, 3],
            DistortionModel::Opencv5 => &[0, 1, 2, 3, 4],
        }
    }
}

/// A pinhole camera with OpenCV's radial-tangential distortion.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraModel {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// `[k1, k2, p1, p2, k3]`.
    pub distortion: [f64; 5],
}

impl CameraModel {
    /// Apply the distortion to normalized coordinates `(x, y) = (X/Z, Y/Z)`.
    #[inline]
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.distortion;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// Pixel of a camera-frame point (z > 0).
    #[inline]
    pub fn project(&self, p: &Vector3<f64>) -> (f64, f64) {
        let (x, y) = self.distort(p.x / p.z, p.y / p.z);
        (self.fx * x + self.cx, self.fy * y + self.cy)
    }

    /// [`project`](Self::project) for a plain `[x, y, z]` camera-frame point.
    pub fn project_point(&self, p: [f64; 3]) -> (f64, f64) {
        self.project(&Vector3::from(p))
    }

    /// [`undistort`](Self::undistort) where the model is invertible: `None` where the
    /// iteration does not reproduce the pixel or the radial map folds over (its derivative
    /// `1 + 3k1 r² + 5k2 r⁴ + 7k3 r⁶` not positive), as a fitted polynomial can beyond the
    /// field its corners covered. No ray is defined there.
    pub fn try_undistort(&self, u: f64, v: f64) -> Option<(f64, f64)> {
        let (x, y) = self.undistort(u, v);
        let (xd, yd) = ((u - self.cx) / self.fx, (v - self.cy) / self.fy);
        let (dx, dy) = self.distort(x, y);
        let [k1, k2, _, _, k3] = self.distortion;
        let r2 = x * x + y * y;
        let slope = 1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + 7.0 * k3 * r2));
        let ok = x.is_finite() && y.is_finite() && (dx - xd).hypot(dy - yd) < 1e-9 && slope > 0.0;
        ok.then_some((x, y))
    }

    /// Normalized undistorted coordinates of a pixel (the inverse of [`project`](Self::project)
    /// up to depth), by fixed-point iteration, which converges for the moderate distortion
    /// of measurement lenses (|distortion displacement| ≪ r).
    pub fn undistort(&self, u: f64, v: f64) -> (f64, f64) {
        let (xd, yd) = ((u - self.cx) / self.fx, (v - self.cy) / self.fy);
        if self.distortion.iter().all(|&c| c == 0.0) {
            return (xd, yd);
        }
        let (mut x, mut y) = (xd, yd);
        for _ in 0..50 {
            let (dx, dy) = self.distort(x, y);
            let (ex, ey) = (dx - xd, dy - yd);
            x -= ex;
            y -= ey;
            if ex.abs().max(ey.abs()) < 1e-15 {
                break;
            }
        }
        (x, y)
    }
}

/// A view's pose: target frame → camera frame, `X_c = R X + t` (OpenCV's rvec, tvec; mm).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewPose {
    /// Rodrigues vector (axis × angle, radians).
    pub rvec: [f64; 3],
    pub tvec: [f64; 3],
}

impl ViewPose {
    /// A pose from a rotation matrix (rows, orthonormal) and a translation. Converted
    /// without re-orthonormalizing: `Rotation3::from_matrix` iterates from the identity and
    /// can miss a half-turn, which is what a board facing the camera is.
    pub fn from_matrix(r: [[f64; 3]; 3], tvec: [f64; 3]) -> Self {
        let m = Matrix3::from_fn(|i, j| r[i][j]);
        let rv = Rotation3::from_matrix_unchecked(m).scaled_axis();
        ViewPose {
            rvec: [rv.x, rv.y, rv.z],
            tvec,
        }
    }

    fn rotation(&self) -> Rotation3<f64> {
        Rotation3::from_scaled_axis(Vector3::from(self.rvec))
    }

    /// Angle (degrees) between the camera's optical axis and the target normal: 0 = the
    /// target faces the camera, 90 = seen edge-on.
    pub fn tilt_deg(&self) -> f64 {
        let n = self.rotation() * Vector3::z();
        n.z.abs().clamp(0.0, 1.0).acos().to_degrees()
    }
}

/// What to estimate and when to refuse.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IntrinsicsOptions {
    pub distortion: DistortionModel,
    pub min_views: usize,
    pub min_points_per_view: usize,
    /// Refuse when the condition number of Zhang's constraint matrix (normalized) exceeds
    /// this: the views do not determine the intrinsics (nearly parallel target planes).
    pub max_condition: f64,
    /// Refuse views whose target is tilted more than this from facing the camera: corner
    /// localisation degrades as the squares foreshorten, biasing the whole fit.
    pub max_tilt_deg: f64,
    pub max_iterations: usize,
    /// Hold `fy / fx` at this value instead of estimating `fy` (OpenCV's
    /// `CALIB_FIX_ASPECT_RATIO`; 1.0 = square pixels, true of practically every sensor).
    /// Why it matters: a rig that can only tilt the target about one camera axis (a
    /// two-arm goniometer: the camera arc tilts, the turntable only turns the target in its
    /// plane) puts every target plane parallel to that axis, and then `fy` and the principal
    /// point across that axis trade against each other; with little perspective (a long
    /// lens) the data hardly separate them. `None`: `fy` is estimated.
    #[serde(default)]
    pub aspect_ratio: Option<f64>,
    /// Refuse the result when a focal length or principal point coordinate has a one-sigma
    /// uncertainty above this fraction of the focal length: the data do not determine it
    /// (too few or too similar views), and a fit that reprojects well can still be far off.
    pub max_relative_sigma: f64,
    /// Corner noise (px, one sigma per coordinate) assumed when a recipe's planned poses
    /// are checked before the rig moves ([`check_plan`]); the detector reaches 0.01–0.03 px
    /// on the simulator, so 0.05 px is a conservative planning value.
    pub planning_noise_px: f64,
}

impl Default for IntrinsicsOptions {
    fn default() -> Self {
        IntrinsicsOptions {
            distortion: DistortionModel::Opencv4,
            min_views: 3,
            min_points_per_view: 8,
            max_condition: 1e7,
            max_tilt_deg: 75.0,
            max_iterations: 100,
            aspect_ratio: None,
            max_relative_sigma: 0.005,
            planning_noise_px: 0.05,
        }
    }
}

/// One-sigma uncertainties of the camera parameters (from the LM covariance with the
/// residual variance as the noise estimate).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraSigma {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub distortion: [f64; 5],
}

/// The result of [`calibrate_intrinsics`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct IntrinsicsCalibration {
    pub camera: CameraModel,
    pub sigma: CameraSigma,
    /// The closed-form (Zhang) estimate the refinement started from (no distortion).
    pub initial: CameraModel,
    pub poses: Vec<ViewPose>,
    /// RMS reprojection error over all corners (pixels).
    pub rms_px: f64,
    pub view_rms_px: Vec<f64>,
    pub view_tilt_deg: Vec<f64>,
    /// Condition number of the normalized Zhang constraint matrix (largest over
    /// second-smallest singular value): large = the views barely determine the intrinsics.
    pub condition: f64,
    pub iterations: usize,
    pub points: usize,
    /// Covariance of the camera parameters, marginal over the poses: what the projection
    /// uncertainty ([`crate::uncertainty`]) is propagated from.
    pub covariance: CameraCovariance,
}

/// Covariance of `[fx, fy, cx, cy, k1, k2, p1, p2, k3]` from the fit: `σ² (JᵀJ)⁻¹` over all
/// parameters (camera and every pose), its camera block kept. `σ²` is the observed corner
/// noise: the residual variance per coordinate (sum of squares over degrees of freedom).
/// Fixed parameters have zero rows; with a fixed aspect ratio fy's row is the ratio times
/// fx's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraCovariance {
    pub params: [[f64; NCAM]; NCAM],
    /// One-sigma corner noise per coordinate (px) the covariance is scaled by.
    pub noise_sigma_px: f64,
    /// Condition number (largest over smallest singular value) of `JᵀJ` scaled to unit
    /// diagonal: the numerical health of the inverse; above ~1e12 the covariance means
    /// little and some combination of parameters is not determined.
    pub condition: f64,
}

#[derive(Debug, Error, Clone, PartialEq)]
pub enum IntrinsicsError {
    #[error("intrinsics: need at least {needed} views of the target, got {got}")]
    TooFewViews { needed: usize, got: usize },
    #[error("intrinsics: view `{view}`: {got} corners, need at least {needed}")]
    TooFewPoints { view: String, needed: usize, got: usize },
    #[error("intrinsics: view `{view}`: object and image point counts differ ({object} vs {image})")]
    Mismatch { view: String, object: usize, image: usize },
    #[error("intrinsics: view `{view}`: non-finite coordinate at point {index}")]
    NonFinite { view: String, index: usize },
    #[error("intrinsics: view `{view}`: homography: {source}")]
    Homography { view: String, source: CalibError },
    #[error(
        "intrinsics: the views do not determine the camera (condition number {condition:.3e} > {max:.1e}): \
         the target planes are nearly parallel; add views with the target tilted in different directions"
    )]
    Degenerate { condition: f64, max: f64 },
    #[error("intrinsics: closed-form estimate failed: {0}")]
    ClosedForm(String),
    #[error(
        "intrinsics: view `{view}` is grazing: target tilted {tilt_deg:.1}° from the optical axis \
         (limit {max_deg:.1}°); corners there are unreliable — drop the view or raise max_tilt_deg"
    )]
    Grazing { view: String, tilt_deg: f64, max_deg: f64 },
    #[error(
        "intrinsics: {param} = {value:.3} is not determined by these views (one sigma {sigma:.3} px, \
         limit {max_fraction} of the focal length): add views tilted in more directions"
    )]
    Undetermined {
        param: String,
        value: f64,
        sigma: f64,
        max_fraction: f64,
    },
    #[error("intrinsics: refinement diverged ({0})")]
    Diverged(String),
    /// The planned poses cannot determine some parameters (checked before the rig moves,
    /// from the predicted Jacobian at the planned poses: [`check_plan`]).
    #[error(
        "intrinsics: the planned poses cannot determine {} ({detail}); add views with the target \
         tilted in other directions (different φ as well as θ) and at least {min_views} views",
        params.join(", ")
    )]
    PlanUndetermined {
        params: Vec<String>,
        detail: String,
        min_views: usize,
    },
}

/// Number of camera parameters in the LM vector: fx, fy, cx, cy, k1, k2, p1, p2, k3.
pub const NCAM: usize = 9;

/// Names of the camera parameters, in [`CameraCovariance`]'s order.
pub const CAMERA_PARAMS: [&str; NCAM] = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"];

/// Calibrate a camera from views of a planar target.
///
/// `image_size` (width, height in pixels) only normalizes the closed-form system.
pub fn calibrate_intrinsics(
    views: &[TargetView],
    image_size: (usize, usize),
    opts: &IntrinsicsOptions,
) -> Result<IntrinsicsCalibration, IntrinsicsError> {
    let min_views = opts.min_views.max(2);
    if views.len() < min_views {
        return Err(IntrinsicsError::TooFewViews {
            needed: min_views,
            got: views.len(),
        });
    }
    if let Some(a) = opts.aspect_ratio {
        if !(a.is_finite() && a > 0.0) {
            return Err(IntrinsicsError::ClosedForm(format!(
                "aspect_ratio = {a}: must be a positive number (fy / fx; 1.0 for square pixels)"
            )));
        }
    }
    let min_points = opts.min_points_per_view.max(4);
    for v in views {
        if v.object.len() != v.image.len() {
            return Err(IntrinsicsError::Mismatch {
                view: v.label.clone(),
                object: v.object.len(),
                image: v.image.len(),
            });
        }
        if v.object.len() < min_points {
            return Err(IntrinsicsError::TooFewPoints {
                view: v.label.clone(),
                needed: min_points,
                got: v.object.len(),
            });
        }
        for (index, (o, i)) in v.object.iter().zip(&v.image).enumerate() {
            if !(o.iter().chain(i).all(|c| c.is_finite())) {
                return Err(IntrinsicsError::NonFinite {
                    view: v.label.clone(),
                    index,
                });
            }
        }
    }
    let homographies = views
        .iter()
        .map(|v| {
            let pairs: Vec<_> = v
                .object
                .iter()
                .zip(&v.image)
                .map(|(o, i)| ((o[0], o[1]), (i[0], i[1])))
                .collect();
            Homography::fit(&pairs).map_err(|source| IntrinsicsError::Homography {
                view: v.label.clone(),
                source,
            })
        })
        .collect::<Result<Vec<_>, _>>()?;

    let (k, condition) = closed_form(&homographies, image_size)?;
    if condition > opts.max_condition {
        return Err(IntrinsicsError::Degenerate {
            condition,
            max: opts.max_condition,
        });
    }
    let initial = CameraModel {
        fx: k[(0, 0)],
        fy: k[(1, 1)],
        cx: k[(0, 2)],
        cy: k[(1, 2)],
        distortion: [0.0; 5],
    };
    let mut poses: Vec<ViewPose> = homographies.iter().map(|h| pose_from_homography(&k, h)).collect();
    for (v, p) in views.iter().zip(&poses) {
        let tilt = p.tilt_deg();
        if tilt > opts.max_tilt_deg {
            return Err(IntrinsicsError::Grazing {
                view: v.label.clone(),
                tilt_deg: tilt,
                max_deg: opts.max_tilt_deg,
            });
        }
    }

    let mut cam = initial;
    if let Some(a) = opts.aspect_ratio {
        // start from the closed form's mean focal length with the fixed ratio
        let f = 0.5 * (cam.fx + cam.fy / a);
        cam.fx = f;
        cam.fy = a * f;
    }
    let free = opts.distortion.free();
    let (iterations, jtj) = refine(
        views,
        &mut cam,
        &mut poses,
        free,
        opts.aspect_ratio,
        opts.max_iterations,
    )?;

    let mut view_rms_px = Vec::with_capacity(views.len());
    let mut sum = 0.0;
    let mut points = 0;
    for (v, p) in views.iter().zip(&poses) {
        let r = residuals(v, &cam, p);
        let s: f64 = r.iter().map(|e| e * e).sum();
        view_rms_px.push((s / v.object.len() as f64).sqrt());
        sum += s;
        points += v.object.len();
    }
    let rms_px = (sum / points as f64).sqrt();
    let nparams = 4 + free.len() + 6 * views.len() - usize::from(opts.aspect_ratio.is_some());
    let dof = (2 * points).saturating_sub(nparams).max(1);
    let variance = sum / dof as f64;
    let sigma = sigma_from(&jtj, variance, free, opts.aspect_ratio);
    let covariance = camera_covariance(&jtj, variance, free, opts.aspect_ratio);
    let f = cam.fx.min(cam.fy);
    for (param, value, sig) in [
        ("fx", cam.fx, sigma.fx),
        ("fy", cam.fy, sigma.fy),
        ("cx", cam.cx, sigma.cx),
        ("cy", cam.cy, sigma.cy),
    ] {
        // NaN-safe: an undefined sigma is refused too.
        if sig.is_nan() || sig > opts.max_relative_sigma * f {
            return Err(IntrinsicsError::Undetermined {
                param: param.into(),
                value,
                sigma: sig,
                max_fraction: opts.max_relative_sigma,
            });
        }
    }
    let view_tilt_deg = poses.iter().map(|p| p.tilt_deg()).collect();
    Ok(IntrinsicsCalibration {
        camera: cam,
        sigma,
        initial,
        poses,
        rms_px,
        view_rms_px,
        view_tilt_deg,
        condition,
        iterations,
        points,
        covariance,
    })
}

/// One planned view for [`check_plan`]: the board points (mm, z = 0) and the pose the rig
/// is expected to hold the board at (nominal kinematics).
#[derive(Clone, Debug, PartialEq)]
pub struct PlannedView {
    pub label: String,
    pub object: Vec<[f64; 2]>,
    pub pose: ViewPose,
}

/// What [`check_plan`] found for a plan it accepts.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlanCheck {
    /// Condition number of the predicted normal matrix (scaled to unit diagonal).
    pub condition: f64,
    /// Predicted one-sigma camera parameters at [`IntrinsicsOptions::planning_noise_px`].
    pub predicted_sigma: [f64; NCAM],
    /// Corners predicted inside the image, per view.
    pub points_per_view: Vec<usize>,
}

/// Check before the rig moves that the planned views can determine the camera: predict
/// the corners through the nominal camera `cam` at the planned poses (points outside the
/// image are dropped), build the fit's Jacobian there, and look at its rank and
/// conditioning. Refuses, naming the parameters, when a combination of parameters has no
/// curvature (a null direction of the scaled normal matrix: all boards tilted about one
/// axis, too few views) or when a focal length or principal point would have a predicted
/// one sigma above [`IntrinsicsOptions::max_relative_sigma`] of the focal length.
pub fn check_plan(
    cam: &CameraModel,
    plan: &[PlannedView],
    image_size: (usize, usize),
    opts: &IntrinsicsOptions,
) -> Result<PlanCheck, IntrinsicsError> {
    let min_views = opts.min_views.max(2);
    let (w, h) = (image_size.0 as f64, image_size.1 as f64);
    let mut views = Vec::new();
    let mut poses = Vec::new();
    let mut points_per_view = Vec::new();
    for pv in plan {
        let r = pv.pose.rotation();
        let t = Vector3::from(pv.pose.tvec);
        let (mut object, mut image) = (Vec::new(), Vec::new());
        for o in &pv.object {
            let pc = r * Vector3::new(o[0], o[1], 0.0) + t;
            if pc.z <= 1e-9 {
                continue;
            }
            let (u, v) = cam.project(&pc);
            if (0.0..w).contains(&u) && (0.0..h).contains(&v) {
                object.push(*o);
                image.push([u, v]);
            }
        }
        points_per_view.push(object.len());
        if object.len() >= opts.min_points_per_view.max(4) {
            views.push(TargetView {
                label: pv.label.clone(),
                object,
                image,
            });
            poses.push(pv.pose);
        }
    }
    let free = opts.distortion.free();
    let free_cam = free_camera_params(free, opts.aspect_ratio);
    if views.len() < min_views {
        return Err(IntrinsicsError::PlanUndetermined {
            params: free_cam.iter().map(|&c| CAMERA_PARAMS[c].to_string()).collect(),
            detail: format!(
                "{} of {} planned views show the board, at least {min_views} are needed",
                views.len(),
                plan.len()
            ),
            min_views,
        });
    }
    // Twice: the pinhole parameters alone first (the closed-form start has no distortion,
    // and a focal length that only the distortion's curvature pins down is not trusted),
    // then the full model.
    let pinhole = free_camera_params(&[], opts.aspect_ratio);
    let pin_cam = CameraModel {
        distortion: [0.0; 5],
        ..*cam
    };
    let (jtj, _) = normal_equations(&views, &pin_cam, &poses, &pinhole, opts.aspect_ratio);
    let (inv, condition, vecs, vals) = scaled_inverse(&jtj);
    let Some(inv) = inv else {
        return Err(undetermined_plan(
            &views, &jtj, &pinhole, condition, &vecs, &vals, min_views,
        ));
    };
    weak_parameters(&inv, &pinhole, cam, opts, condition, "pinhole model", min_views)?;
    let (jtj, _) = normal_equations(&views, cam, &poses, &free_cam, opts.aspect_ratio);
    let (inv, condition, vecs, vals) = scaled_inverse(&jtj);
    let Some(inv) = inv else {
        return Err(undetermined_plan(
            &views, &jtj, &free_cam, condition, &vecs, &vals, min_views,
        ));
    };
    let predicted_sigma = weak_parameters(&inv, &free_cam, cam, opts, condition, "full model", min_views)?;
    Ok(PlanCheck {
        condition,
        predicted_sigma,
        points_per_view,
    })
}

/// Predicted one sigma of the nine camera parameters from the inverse normal matrix over
/// `free_cam` at the planning noise; refuses when a focal length or principal point
/// coordinate exceeds [`IntrinsicsOptions::max_relative_sigma`] of the focal length.
fn weak_parameters(
    inv: &DMatrix<f64>,
    free_cam: &[usize],
    cam: &CameraModel,
    opts: &IntrinsicsOptions,
    condition: f64,
    model: &str,
    min_views: usize,
) -> Result<[f64; NCAM], IntrinsicsError> {
    let var = opts.planning_noise_px.powi(2);
    let mut predicted_sigma = [0.0; NCAM];
    for (col, &ci) in free_cam.iter().enumerate() {
        predicted_sigma[ci] = (inv[(col, col)] * var).max(0.0).sqrt();
    }
    if let Some(a) = opts.aspect_ratio {
        predicted_sigma[1] = a * predicted_sigma[0];
    }
    let f = cam.fx.min(cam.fy);
    let weak: Vec<String> = (0..4)
        .filter(|&i| predicted_sigma[i].is_nan() || predicted_sigma[i] > opts.max_relative_sigma * f)
        .map(|i| {
            format!(
                "{} (predicted one sigma {:.3} px)",
                CAMERA_PARAMS[i], predicted_sigma[i]
            )
        })
        .collect();
    if weak.is_empty() {
        return Ok(predicted_sigma);
    }
    Err(IntrinsicsError::PlanUndetermined {
        params: weak,
        detail: format!(
            "{model}: limit {} of the focal length at {} px corner noise; condition number {condition:.2e}",
            opts.max_relative_sigma, opts.planning_noise_px
        ),
        min_views,
    })
}

/// The refusal of a plan whose predicted normal matrix is singular: the parameters with
/// weight in its null directions, camera parameters by name and poses by their view.
fn undetermined_plan(
    views: &[TargetView],
    jtj: &DMatrix<f64>,
    free_cam: &[usize],
    condition: f64,
    vecs: &DMatrix<f64>,
    vals: &DVector<f64>,
    min_views: usize,
) -> IntrinsicsError {
    let nc = free_cam.len();
    let lmax = vals.iter().cloned().fold(0.0, f64::max);
    let mut weight = vec![0.0; jtj.nrows()];
    for (k, &l) in vals.iter().enumerate() {
        if l <= 1e-14 * lmax {
            for (i, wgt) in weight.iter_mut().enumerate() {
                *wgt += vecs[(i, k)].powi(2);
            }
        }
    }
    for (i, wgt) in weight.iter_mut().enumerate() {
        if jtj[(i, i)] <= 0.0 {
            *wgt += 1.0;
        }
    }
    let mut params: Vec<String> = (0..nc)
        .filter(|&i| weight[i] > 0.01)
        .map(|i| CAMERA_PARAMS[free_cam[i]].to_string())
        .collect();
    let poses: Vec<&str> = views
        .iter()
        .enumerate()
        .filter(|(vi, _)| (0..6).any(|k| weight[nc + 6 * vi + k] > 0.01))
        .map(|(_, v)| v.label.as_str())
        .collect();
    if !poses.is_empty() {
        params.push(format!("the board pose of {} view(s)", poses.len()));
    }
    if params.is_empty() {
        params.push("a combination of all parameters".into());
    }
    IntrinsicsError::PlanUndetermined {
        params,
        detail: format!(
            "the predicted normal matrix over {} views is singular, condition number {condition:.2e}",
            views.len()
        ),
        min_views,
    }
}

/// Reprojection residuals (pixels) of one view, `[du0, dv0, du1, dv1, …]`.
fn residuals(v: &TargetView, cam: &CameraModel, p: &ViewPose) -> Vec<f64> {
    let r = p.rotation();
    let t = Vector3::from(p.tvec);
    let mut out = Vec::with_capacity(2 * v.object.len());
    for (o, i) in v.object.iter().zip(&v.image) {
        let pc = r * Vector3::new(o[0], o[1], 0.0) + t;
        let (u, w) = if pc.z > 1e-9 {
            cam.project(&pc)
        } else {
            (f64::INFINITY, f64::INFINITY)
        };
        out.push(u - i[0]);
        out.push(w - i[1]);
    }
    out
}

/// Zhang's closed form with zero skew. Returns K (pixels) and the condition number.
fn closed_form(hs: &[Homography], (w, h): (usize, usize)) -> Result<(Matrix3<f64>, f64), IntrinsicsError> {
    // Normalize pixels: centre of the image at 0, image half-size ≈ 1, so the entries of
    // B are of comparable size and the condition number means something.
    let s = (w.max(h) as f64 / 2.0).max(1.0);
    let t = Matrix3::new(
        1.0 / s,
        0.0,
        -(w as f64) / 2.0 / s,
        0.0,
        1.0 / s,
        -(h as f64) / 2.0 / s,
        0.0,
        0.0,
        1.0,
    );
    let mut rows: Vec<[f64; 6]> = Vec::with_capacity(2 * hs.len() + 1);
    let vij = |hm: &Matrix3<f64>, i: usize, j: usize| -> [f64; 6] {
        let (a, b) = (hm.column(i), hm.column(j));
        [
            a[0] * b[0],
            a[0] * b[1] + a[1] * b[0],
            a[1] * b[1],
            a[2] * b[0] + a[0] * b[2],
            a[2] * b[1] + a[1] * b[2],
            a[2] * b[2],
        ]
    };
    for hom in hs {
        let hm = t * hom.matrix();
        let hm = hm / hm.column(0).norm().max(hm.column(1).norm());
        let v12 = vij(&hm, 0, 1);
        let v11 = vij(&hm, 0, 0);
        let v22 = vij(&hm, 1, 1);
        rows.push(v12);
        rows.push(std::array::from_fn(|k| v11[k] - v22[k]));
    }
    // Zero skew: B12 = 0.
    rows.push([0.0, 1.0, 0.0, 0.0, 0.0, 0.0]);
    let n = rows.len();
    let mut v = DMatrix::<f64>::zeros(n.max(6), 6);
    for (r, row) in rows.iter().enumerate() {
        let norm = row.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-300);
        for c in 0..6 {
            v[(r, c)] = row[c] / norm;
        }
    }
    let svd = v.svd(false, true);
    let v_t = svd
        .v_t
        .as_ref()
        .ok_or_else(|| IntrinsicsError::ClosedForm("SVD did not converge".into()))?;
    // nalgebra does not sort singular values: sort indices by value.
    let sv = &svd.singular_values;
    let mut idx: Vec<usize> = (0..sv.len()).collect();
    idx.sort_by(|&a, &b| sv[b].total_cmp(&sv[a]));
    let smallest = idx[5];
    let condition = sv[idx[0]] / sv[idx[4]].max(1e-300);
    let b = v_t.row(smallest);
    let mut bm = Matrix3::new(b[0], b[1], b[3], b[1], b[2], b[4], b[3], b[4], b[5]);
    if bm[(0, 0)] < 0.0 {
        bm = -bm;
    }
    // B = K⁻ᵀK⁻¹ = L Lᵀ with L = K⁻ᵀ lower triangular: K = (Lᵀ)⁻¹, scaled to K33 = 1.
    let chol = bm.cholesky().ok_or_else(|| {
        IntrinsicsError::ClosedForm(format!(
            "the constraint solution is not positive definite (condition number {condition:.3e}); \
             the views are degenerate or the corners wrong"
        ))
    })?;
    let lt = chol.l().transpose();
    let kn = lt
        .try_inverse()
        .ok_or_else(|| IntrinsicsError::ClosedForm("singular K".into()))?;
    let kn = kn / kn[(2, 2)];
    let k = t.try_inverse().expect("normalization is invertible") * kn;
    if !(k[(0, 0)] > 0.0 && k[(1, 1)] > 0.0 && k.iter().all(|x| x.is_finite())) {
        return Err(IntrinsicsError::ClosedForm(format!(
            "non-physical focal lengths fx={:.4e} fy={:.4e}",
            k[(0, 0)],
            k[(1, 1)]
        )));
    }
    Ok((k, condition))
}

/// Extrinsics from `H ∝ K [r1 r2 t]`, with the rotation projected onto SO(3).
fn pose_from_homography(k: &Matrix3<f64>, h: &Homography) -> ViewPose {
    let kinv = k.try_inverse().unwrap_or_else(Matrix3::identity);
    let m = kinv * h.matrix();
    let lambda = 1.0 / m.column(0).norm().max(1e-300);
    let mut r1 = m.column(0) * lambda;
    let mut r2 = m.column(1) * lambda;
    let mut t = m.column(2) * lambda;
    if t[2] < 0.0 {
        r1 = -r1;
        r2 = -r2;
        t = -t;
    }
    let r3 = r1.cross(&r2);
    let r = Matrix3::from_columns(&[r1.into_owned(), r2.into_owned(), r3]);
    let rot = Rotation3::from_matrix(&r);
    let rv = rot.scaled_axis();
    ViewPose {
        rvec: [rv.x, rv.y, rv.z],
        tvec: [t[0], t[1], t[2]],
    }
}

fn cam_to_vec(c: &CameraModel) -> [f64; NCAM] {
    let d = c.distortion;
    [c.fx, c.fy, c.cx, c.cy, d[0], d[1], d[2], d[3], d[4]]
}

fn vec_to_cam(p: &[f64]) -> CameraModel {
    CameraModel {
        fx: p[0],
        fy: p[1],
        cx: p[2],
        cy: p[3],
        distortion: [p[4], p[5], p[6], p[7], p[8]],
    }
}

fn pose_to_vec(p: &ViewPose) -> [f64; 6] {
    [p.rvec[0], p.rvec[1], p.rvec[2], p.tvec[0], p.tvec[1], p.tvec[2]]
}

fn vec_to_pose(p: &[f64]) -> ViewPose {
    ViewPose {
        rvec: [p[0], p[1], p[2]],
        tvec: [p[3], p[4], p[5]],
    }
}

/// The camera parameters (indices into [`cam_to_vec`]) the LM estimates: fx, fy unless the
/// aspect ratio is fixed, cx, cy, then the free distortion coefficients.
fn free_camera_params(free_dist: &[usize], aspect: Option<f64>) -> Vec<usize> {
    [0, 1, 2, 3]
        .into_iter()
        .filter(|&c| c != 1 || aspect.is_none())
        .chain(free_dist.iter().map(|&d| 4 + d))
        .collect()
}

/// `JᵀJ` and `Jᵀr` of the reprojection residuals over the free camera parameters
/// (`free_cam`, [`free_camera_params`]) and six pose parameters per view, in that order.
///
/// The Jacobian is by central differences, block by block (a pose only moves its own
/// view's residuals).
fn normal_equations(
    views: &[TargetView],
    cam: &CameraModel,
    poses: &[ViewPose],
    free_cam: &[usize],
    aspect: Option<f64>,
) -> (DMatrix<f64>, DVector<f64>) {
    let tie = |cv: &mut [f64; NCAM]| {
        if let Some(a) = aspect {
            cv[1] = a * cv[0];
        }
    };
    let nc = free_cam.len();
    let n = nc + 6 * views.len();
    let mut jtj = DMatrix::<f64>::zeros(n, n);
    let mut jtr = DVector::<f64>::zeros(n);
    let cvec = cam_to_vec(cam);
    for (vi, (v, p)) in views.iter().zip(poses).enumerate() {
        let r0 = residuals(v, cam, p);
        let m = r0.len();
        let mut jc = DMatrix::<f64>::zeros(m, nc);
        for (col, &ci) in free_cam.iter().enumerate() {
            let h = 1e-6 * cvec[ci].abs().max(if ci < 4 { 1.0 } else { 1e-2 });
            let mut a = cvec;
            let mut b = cvec;
            a[ci] += h;
            b[ci] -= h;
            tie(&mut a);
            tie(&mut b);
            let (ra, rb) = (residuals(v, &vec_to_cam(&a), p), residuals(v, &vec_to_cam(&b), p));
            for row in 0..m {
                jc[(row, col)] = (ra[row] - rb[row]) / (2.0 * h);
            }
        }
        let pvec = pose_to_vec(p);
        let mut jp = DMatrix::<f64>::zeros(m, 6);
        for k in 0..6 {
            let h = if k < 3 { 1e-7 } else { 1e-6 * pvec[k].abs().max(1.0) };
            let mut a = pvec;
            let mut b = pvec;
            a[k] += h;
            b[k] -= h;
            let (ra, rb) = (residuals(v, cam, &vec_to_pose(&a)), residuals(v, cam, &vec_to_pose(&b)));
            for row in 0..m {
                jp[(row, k)] = (ra[row] - rb[row]) / (2.0 * h);
            }
        }
        let r = DVector::from_vec(r0);
        let o = nc + 6 * vi;
        let cc = jc.transpose() * &jc;
        let cp = jc.transpose() * &jp;
        let pp = jp.transpose() * &jp;
        let mut block = jtj.view_mut((0, 0), (nc, nc));
        block += &cc;
        let mut block = jtj.view_mut((0, o), (nc, 6));
        block += &cp;
        let mut block = jtj.view_mut((o, 0), (6, nc));
        block += cp.transpose();
        let mut block = jtj.view_mut((o, o), (6, 6));
        block += &pp;
        let gc = jc.transpose() * &r;
        let gp = jp.transpose() * &r;
        let mut seg = jtr.rows_mut(0, nc);
        seg += &gc;
        let mut seg = jtr.rows_mut(o, 6);
        seg += &gp;
    }
    (jtj, jtr)
}

/// Levenberg-Marquardt over the free camera parameters and all poses. Returns the
/// iterations used and `JᵀJ` at the solution (for the covariance).
///
/// The Jacobian ([`normal_equations`]) is by central differences, which is exact enough
/// for convergence: the minimum is set by the residuals, not by the Jacobian.
fn refine(
    views: &[TargetView],
    cam: &mut CameraModel,
    poses: &mut [ViewPose],
    free_dist: &[usize],
    aspect: Option<f64>,
    max_iter: usize,
) -> Result<(usize, DMatrix<f64>), IntrinsicsError> {
    // With a fixed aspect ratio fy is not a parameter: it follows fx.
    let free_cam = free_camera_params(free_dist, aspect);
    let tie = |cv: &mut [f64; NCAM]| {
        if let Some(a) = aspect {
            cv[1] = a * cv[0];
        }
    };
    let nc = free_cam.len();
    let n = nc + 6 * views.len();
    let cost_of = |cam: &CameraModel, poses: &[ViewPose]| -> f64 {
        views
            .iter()
            .zip(poses)
            .map(|(v, p)| residuals(v, cam, p).iter().map(|e| e * e).sum::<f64>())
            .sum()
    };
    let normal_equations =
        |cam: &CameraModel, poses: &[ViewPose]| normal_equations(views, cam, poses, &free_cam, aspect);
    let apply = |cam: &CameraModel, poses: &[ViewPose], step: &DVector<f64>| -> (CameraModel, Vec<ViewPose>) {
        let mut cv = cam_to_vec(cam);
        for (col, &ci) in free_cam.iter().enumerate() {
            cv[ci] += step[col];
        }
        tie(&mut cv);
        let ps = poses
            .iter()
            .enumerate()
            .map(|(vi, p)| {
                let mut pv = pose_to_vec(p);
                for (k, x) in pv.iter_mut().enumerate() {
                    *x += step[nc + 6 * vi + k];
                }
                vec_to_pose(&pv)
            })
            .collect();
        (vec_to_cam(&cv), ps)
    };

    let mut cost = cost_of(cam, poses);
    if !cost.is_finite() {
        return Err(IntrinsicsError::Diverged(
            "the initial estimate puts target points behind the camera".into(),
        ));
    }
    let mut lambda = 1e-3;
    let mut iterations = 0;
    let (mut jtj, mut jtr) = normal_equations(cam, poses);
    for it in 0..max_iter {
        iterations = it + 1;
        let mut accepted = false;
        for _ in 0..12 {
            let mut m = jtj.clone();
            for d in 0..n {
                m[(d, d)] += lambda * jtj[(d, d)].max(1e-12);
            }
            let Some(ch) = m.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let step = ch.solve(&(-&jtr));
            let (c2, p2) = apply(cam, poses, &step);
            let new_cost = cost_of(&c2, &p2);
            if new_cost.is_finite() && new_cost < cost {
                let rel = (cost - new_cost) / cost.max(1e-300);
                *cam = c2;
                poses.copy_from_slice(&p2);
                cost = new_cost;
                lambda = (lambda * 0.3).max(1e-12);
                accepted = true;
                if rel < 1e-14 {
                    let ne = normal_equations(cam, poses);
                    return Ok((iterations, ne.0));
                }
                break;
            }
            lambda *= 10.0;
        }
        if !accepted {
            break;
        }
        (jtj, jtr) = normal_equations(cam, poses);
        if jtr.amax() < 1e-12 * cost.max(1e-30).sqrt() {
            break;
        }
    }
    if !(cam.fx > 0.0 && cam.fy > 0.0 && cost.is_finite()) {
        return Err(IntrinsicsError::Diverged(format!(
            "fx={} fy={} cost={cost}",
            cam.fx, cam.fy
        )));
    }
    let (jtj, _) = normal_equations(cam, poses);
    Ok((iterations, jtj))
}

/// The inverse of a symmetric positive semi-definite normal matrix, scaled to unit diagonal
/// first (`A = D JᵀJ D`, `D = diag(JᵀJ)^-½`) so parameters of different units (pixels,
/// distortion coefficients, radians, mm) do not set the condition number, then inverted by
/// symmetric eigendecomposition. Returns the inverse (or `None` when a direction is not
/// determined: an eigenvalue below `1e-14` of the largest, or a parameter the residuals do
/// not depend on) and the condition number of `A`.
pub(crate) fn scaled_inverse(jtj: &DMatrix<f64>) -> (Option<DMatrix<f64>>, f64, DMatrix<f64>, DVector<f64>) {
    let n = jtj.nrows();
    let d = DVector::from_iterator(
        n,
        (0..n).map(|i| {
            let v = jtj[(i, i)];
            if v > 0.0 {
                1.0 / v.sqrt()
            } else {
                0.0
            }
        }),
    );
    let mut a = jtj.clone();
    for i in 0..n {
        for j in 0..n {
            a[(i, j)] *= d[i] * d[j];
        }
    }
    let eig = a.clone().symmetric_eigen();
    let (lmax, lmin) = eig
        .eigenvalues
        .iter()
        .fold((0.0f64, f64::INFINITY), |(hi, lo), &l| (hi.max(l), lo.min(l)));
    let condition = if lmin > 0.0 { lmax / lmin } else { f64::INFINITY };
    let unobserved = d.iter().any(|&x| x == 0.0);
    if unobserved || lmin.is_nan() || lmin <= 1e-14 * lmax {
        return (None, condition, eig.eigenvectors, eig.eigenvalues);
    }
    let mut inv = DMatrix::<f64>::zeros(n, n);
    for k in 0..n {
        let v = eig.eigenvectors.column(k);
        inv += (v * v.transpose()) / eig.eigenvalues[k];
    }
    for i in 0..n {
        for j in 0..n {
            inv[(i, j)] *= d[i] * d[j];
        }
    }
    (Some(inv), condition, eig.eigenvectors, eig.eigenvalues)
}

/// [`CameraCovariance`] from `JᵀJ` (parameter order of [`refine`]) and the corner noise
/// variance. An undetermined fit gives infinite variances.
fn camera_covariance(jtj: &DMatrix<f64>, variance: f64, free_dist: &[usize], aspect: Option<f64>) -> CameraCovariance {
    let free_cam = free_camera_params(free_dist, aspect);
    let nc = free_cam.len();
    // map from the free parameters to the nine: t[full][free]
    let mut t = [[0.0; NCAM]; NCAM];
    for (col, &ci) in free_cam.iter().enumerate() {
        t[ci][col] = 1.0;
    }
    if let Some(a) = aspect {
        t[1][0] = a;
    }
    let (inv, condition, _, _) = scaled_inverse(jtj);
    let mut params = [[0.0; NCAM]; NCAM];
    for (i, row) in params.iter_mut().enumerate() {
        for (j, out) in row.iter_mut().enumerate() {
            let mut acc = 0.0;
            for a in 0..nc {
                for b in 0..nc {
                    let tab = t[i][a] * t[j][b];
                    if tab != 0.0 {
                        acc += tab * inv.as_ref().map_or(f64::INFINITY, |m| m[(a, b)]);
                    }
                }
            }
            *out = acc * variance;
        }
    }
    CameraCovariance {
        params,
        noise_sigma_px: variance.sqrt(),
        condition,
    }
}

/// One-sigma parameter errors from `σ² (JᵀJ)⁻¹`. The parameter order is [`refine`]'s: fx,
/// fy (unless the aspect ratio is fixed, when its sigma is the ratio times fx's), cx, cy,
/// then the free distortion coefficients.
fn sigma_from(jtj: &DMatrix<f64>, variance: f64, free_dist: &[usize], aspect: Option<f64>) -> CameraSigma {
    let nc = 4 + free_dist.len() - usize::from(aspect.is_some());
    let diag: Vec<f64> = match jtj.clone().cholesky() {
        Some(ch) => {
            let inv = ch.inverse();
            (0..nc).map(|i| (inv[(i, i)] * variance).max(0.0).sqrt()).collect()
        }
        None => vec![f64::INFINITY; nc],
    };
    let (fx, fy, rest) = match aspect {
        Some(a) => (diag[0], a * diag[0], &diag[1..]),
        None => (diag[0], diag[1], &diag[2..]),
    };
    let mut distortion = [0.0; 5];
    for (k, &d) in free_dist.iter().enumerate() {
        distortion[d] = rest[2 + k];
    }
    CameraSigma {
        fx,
        fy,
        cx: rest[0],
        cy: rest[1],
        distortion,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::Rng;

    /// A board of `n × n` corners, `pitch` mm apart, centred on the origin.
    fn board(n: usize, pitch: f64) -> Vec<[f64; 2]> {
        let h = (n - 1) as f64 / 2.0;
        (0..n * n)
            .map(|k| [((k % n) as f64 - h) * pitch, ((k / n) as f64 - h) * pitch])
            .collect()
    }

    /// A camera at distance `d` looking at the origin from (tilt θ, azimuth φ), with roll.
    fn look_pose(theta: f64, phi: f64, roll: f64, d: f64, offset: [f64; 2]) -> ViewPose {
        let (th, ph) = (theta.to_radians(), phi.to_radians());
        let c = Vector3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()) * d;
        let target = Vector3::new(offset[0], offset[1], 0.0);
        let fwd = (target - c).normalize();
        let up = if fwd.cross(&Vector3::y()).norm() > 1e-6 {
            Vector3::y()
        } else {
            Vector3::x()
        };
        let right = fwd.cross(&up).normalize();
        let down = fwd.cross(&right);
        let r0 = Matrix3::from_rows(&[right.transpose(), down.transpose(), fwd.transpose()]);
        let r = Rotation3::from_axis_angle(&Vector3::z_axis(), roll.to_radians()).matrix() * r0;
        let t = -(r * c);
        // (`from_matrix` iterates from the identity and can miss a half-turn such as a
        // board facing the camera: the matrix is already orthonormal)
        let rv = Rotation3::from_matrix_unchecked(r).scaled_axis();
        ViewPose {
            rvec: [rv.x, rv.y, rv.z],
            tvec: [t.x, t.y, t.z],
        }
    }

    fn synth(cam: &CameraModel, poses: &[ViewPose], obj: &[[f64; 2]], noise: f64, seed: u64) -> Vec<TargetView> {
        let mut rng = Rng::new(seed);
        poses
            .iter()
            .enumerate()
            .map(|(k, p)| {
                let r = p.rotation();
                let image = obj
                    .iter()
                    .map(|o| {
                        let (u, v) = cam.project(&(r * Vector3::new(o[0], o[1], 0.0) + Vector3::from(p.tvec)));
                        [u + noise * rng.normal(), v + noise * rng.normal()]
                    })
                    .collect();
                TargetView {
                    label: format!("view {k}"),
                    object: obj.to_vec(),
                    image,
                }
            })
            .collect()
    }

    fn truth() -> CameraModel {
        CameraModel {
            fx: 1500.0,
            fy: 1502.0,
            cx: 400.0,
            cy: 310.0,
            distortion: [-0.12, 0.05, 0.0008, -0.0005, 0.0],
        }
    }

    fn orbit() -> Vec<ViewPose> {
        let mut poses = Vec::new();
        for (k, &(th, ph)) in [
            (30.0, 0.0),
            (30.0, 90.0),
            (35.0, 180.0),
            (40.0, 270.0),
            (20.0, 45.0),
            (45.0, 135.0),
            (10.0, 225.0),
            (50.0, 315.0),
        ]
        .iter()
        .enumerate()
        {
            let off = [(k as f64 - 3.5) * 8.0, ((k * 3) % 5) as f64 * 6.0 - 12.0];
            poses.push(look_pose(th, ph, 10.0 * k as f64, 400.0, off));
        }
        poses
    }

    #[test]
    fn recovers_camera_exactly_without_noise() {
        let cam = truth();
        let views = synth(&cam, &orbit(), &board(9, 10.0), 0.0, 1);
        let c = calibrate_intrinsics(&views, (800, 600), &IntrinsicsOptions::default()).unwrap();
        assert!(c.rms_px < 1e-6, "rms {}", c.rms_px);
        assert!((c.camera.fx - cam.fx).abs() < 1e-4, "{:?}", c.camera);
        assert!((c.camera.cy - cam.cy).abs() < 1e-4, "{:?}", c.camera);
        for k in 0..4 {
            assert!(
                (c.camera.distortion[k] - cam.distortion[k]).abs() < 1e-7,
                "{:?}",
                c.camera
            );
        }
        // the closed form (no distortion model) is already close
        assert!((c.initial.fx - cam.fx).abs() / cam.fx < 0.05, "{:?}", c.initial);
    }

    #[test]
    fn noisy_corners_give_consistent_uncertainty() {
        let cam = truth();
        let views = synth(&cam, &orbit(), &board(9, 10.0), 0.05, 7);
        let c = calibrate_intrinsics(&views, (800, 600), &IntrinsicsOptions::default()).unwrap();
        // RMS point distance of 2-D noise with σ = 0.05 per coordinate: 0.05·√2.
        assert!((c.rms_px - 0.05 * 2f64.sqrt()).abs() < 0.008, "rms {}", c.rms_px);
        for (est, tru, sig) in [
            (c.camera.fx, cam.fx, c.sigma.fx),
            (c.camera.fy, cam.fy, c.sigma.fy),
            (c.camera.cx, cam.cx, c.sigma.cx),
            (c.camera.cy, cam.cy, c.sigma.cy),
        ] {
            assert!(sig > 0.0 && sig < 2.0, "sigma {sig}");
            assert!((est - tru).abs() < 4.0 * sig, "{est} vs {tru} ± {sig}");
        }
    }

    /// The reported projection uncertainty bounds the true error over the whole image,
    /// including the corners where no target corner was seen: over a dozen noise draws the
    /// worst ratio (true error / reported sigma, over every grid node) stays within 4 and is
    /// typically 1–2, i.e. the sigma is neither optimistic nor inflated.
    #[test]
    fn projection_uncertainty_bounds_the_true_error() {
        use crate::uncertainty::{projection_error, projection_uncertainty, UncertaintyOptions};
        let cam = truth();
        let mut worst = Vec::new();
        for seed in 1..=12 {
            let views = synth(&cam, &orbit(), &board(9, 10.0), 0.05, seed);
            let c = calibrate_intrinsics(&views, (800, 600), &IntrinsicsOptions::default()).unwrap();
            assert!(c.covariance.condition.is_finite() && c.covariance.condition > 1.0);
            let r = projection_uncertainty(
                &c.camera,
                &c.covariance,
                &views,
                (800, 600),
                None,
                &UncertaintyOptions::default(),
            );
            assert!(
                r.coverage_fraction > 0.0 && r.coverage_fraction < 1.0,
                "{}",
                r.coverage_fraction
            );
            let mut w: f64 = 0.0;
            for (j, &y) in r.grid_y.iter().enumerate() {
                for (i, &x) in r.grid_x.iter().enumerate() {
                    let s = r.sigma_px[j * r.nx() + i].unwrap();
                    assert!(s > 0.0 && s.is_finite());
                    w = w.max(projection_error(&c.camera, &cam, x, y).unwrap() / s);
                }
            }
            worst.push(w);
        }
        worst.sort_by(f64::total_cmp);
        assert!(worst[11] < 4.0, "{worst:?}");
        let median = 0.5 * (worst[5] + worst[6]);
        assert!((0.7..2.0).contains(&median), "{worst:?}");
    }

    #[test]
    fn plans_that_cannot_determine_the_camera_are_refused() {
        let cam = truth();
        let plan = |poses: &[ViewPose]| -> Vec<PlannedView> {
            poses
                .iter()
                .enumerate()
                .map(|(k, p)| PlannedView {
                    label: format!("view {k}"),
                    object: board(9, 10.0),
                    pose: *p,
                })
                .collect()
        };
        let opts = IntrinsicsOptions::default();
        let ok = check_plan(&cam, &plan(&orbit()), (800, 600), &opts).unwrap();
        assert!(ok.predicted_sigma[0] > 0.0 && ok.predicted_sigma[0] < 1.0, "{ok:?}");
        // too few views
        let e = check_plan(&cam, &plan(&orbit()[..2]), (800, 600), &opts).unwrap_err();
        assert!(e.to_string().contains("2 of 2 planned views"), "{e}");
        // the board only turned about the optical axis: every plane parallel
        let flat: Vec<ViewPose> = (0..6)
            .map(|k| look_pose(0.0, 0.0, 30.0 * k as f64, 400.0, [0.0, 0.0]))
            .collect();
        let e = check_plan(&cam, &plan(&flat), (800, 600), &opts).unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("fx") && msg.contains("cx"), "{msg}");
    }

    #[test]
    fn parallel_views_are_refused() {
        let cam = CameraModel {
            distortion: [0.0; 5],
            ..truth()
        };
        // All views with the same tilt direction, only translated and rolled about the
        // target normal: Zhang's constraints repeat.
        let poses: Vec<ViewPose> = (0..6)
            .map(|k| {
                let mut p = look_pose(25.0, 30.0, 0.0, 400.0 + 20.0 * k as f64, [0.0, 0.0]);
                p.tvec[0] += 5.0 * k as f64;
                p
            })
            .collect();
        let views = synth(&cam, &poses, &board(9, 10.0), 0.01, 3);
        let e = calibrate_intrinsics(&views, (800, 600), &IntrinsicsOptions::default()).unwrap_err();
        assert!(
            matches!(e, IntrinsicsError::Degenerate { .. } | IntrinsicsError::ClosedForm(_)),
            "{e}"
        );
    }

    #[test]
    fn grazing_view_is_refused_and_named() {
        let cam = truth();
        let mut poses = orbit();
        poses.push(look_pose(82.0, 10.0, 0.0, 400.0, [0.0, 0.0]));
        let views = synth(&cam, &poses, &board(9, 10.0), 0.0, 1);
        match calibrate_intrinsics(&views, (800, 600), &IntrinsicsOptions::default()) {
            Err(IntrinsicsError::Grazing { view, tilt_deg, .. }) => {
                assert_eq!(view, "view 8");
                assert!((tilt_deg - 82.0).abs() < 2.0, "{tilt_deg}");
            }
            other => panic!("expected a grazing-view error, got {other:?}"),
        }
    }

    #[test]
    fn too_few_views_or_points_and_bad_input_are_errors() {
        let cam = truth();
        let views = synth(&cam, &orbit()[..2], &board(9, 10.0), 0.0, 1);
        assert!(matches!(
            calibrate_intrinsics(&views, (800, 600), &IntrinsicsOptions::default()),
            Err(IntrinsicsError::TooFewViews { needed: 3, got: 2 })
        ));
        let mut views = synth(&cam, &orbit(), &board(9, 10.0), 0.0, 1);
        views[2].image.truncate(5);
        views[2].object.truncate(5);
        assert!(matches!(
            calibrate_intrinsics(&views, (800, 600), &IntrinsicsOptions::default()),
            Err(IntrinsicsError::TooFewPoints { .. })
        ));
        let mut views = synth(&cam, &orbit(), &board(9, 10.0), 0.0, 1);
        views[1].image[3][0] = f64::NAN;
        assert!(matches!(
            calibrate_intrinsics(&views, (800, 600), &IntrinsicsOptions::default()),
            Err(IntrinsicsError::NonFinite { index: 3, .. })
        ));
    }

    #[test]
    fn undistort_inverts_distort() {
        let cam = truth();
        for &(x, y) in &[(0.1, -0.2), (0.3, 0.25), (-0.35, 0.05)] {
            let (xd, yd) = cam.distort(x, y);
            let (u, v) = (cam.fx * xd + cam.cx, cam.fy * yd + cam.cy);
            let (xu, yu) = cam.undistort(u, v);
            assert!((xu - x).abs() < 1e-12 && (yu - y).abs() < 1e-12);
        }
    }
}
