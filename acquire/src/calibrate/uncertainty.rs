//! What an intrinsics run adds around the fit so its result can be trusted across the
//! whole image: the plan check before the rig moves, the projection-uncertainty report
//! after the fit (with, on the simulator, the true projection error next to it), and the
//! heat-map picture `gonio calibrate` writes.
//!
//! The numerics live in `gonio_calibration::uncertainty` and
//! `gonio_calibration::intrinsics::check_plan`; this module supplies what only the rig
//! knows: the nominal board poses of the planned views, and where the sample appears.

use super::*;
use gonio_calibration::intrinsics::{check_plan, PlanCheck, PlannedView, ViewPose};
use gonio_calibration::uncertainty::{
    projection_error, projection_uncertainty, ImageDisc, ProjectionUncertainty, UncertaintyOptions,
};

/// The true projection error over the same grid as the reported uncertainty (simulator).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ProjectionTruth {
    /// True projection error (px) at each grid node, row-major like `sigma_px` (`null`
    /// where the estimate defines no ray).
    pub error_px: Vec<Option<f64>>,
    pub max_error_px: f64,
    /// Where the largest error is (px).
    pub max_error_at_px: [f64; 2],
    pub sample_max_error_px: Option<f64>,
    /// Largest error / reported sigma over the grid; the report is consistent when this
    /// stays within about 3.
    pub max_error_over_sigma: f64,
    /// Fraction of grid nodes (with a ray) where the error exceeds three sigma.
    pub beyond_3_sigma_fraction: f64,
}

/// The nominal camera (rig file) as a [`CameraModel`] without distortion.
fn nominal_camera(rig: &Rig) -> CameraModel {
    let k = rig.spec.camera.intrinsics();
    CameraModel {
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        distortion: [0.0; 5],
    }
}

/// Board → camera pose of axis configuration `q` from the rig's nominal kinematics.
pub(super) fn nominal_board_pose(rig: &Rig, q: &[f64]) -> ViewPose {
    let pose = rig.kinematics.camera_pose(q);
    let o = pose.to_camera(gonio_devices::Vec3::new(0.0, 0.0, 0.0));
    // column k of R is the camera-frame image of the sample frame's unit vector k
    let col = |e: gonio_devices::Vec3| {
        let c = pose.to_camera(e);
        [c.x - o.x, c.y - o.y, c.z - o.z]
    };
    let cols = [
        col(gonio_devices::Vec3::new(1.0, 0.0, 0.0)),
        col(gonio_devices::Vec3::new(0.0, 1.0, 0.0)),
        col(gonio_devices::Vec3::new(0.0, 0.0, 1.0)),
    ];
    ViewPose::from_matrix(
        std::array::from_fn(|i| std::array::from_fn(|j| cols[j][i])),
        [o.x, o.y, o.z],
    )
}

/// Check the recipe's poses before the rig moves: every pose through the inverse
/// kinematics (nothing moves), the whole board predicted through the nominal camera, and
/// the fit's Jacobian there ([`check_plan`]). A plan that cannot determine the camera is
/// refused naming the parameters. Boards on a wedge are not planar in the sample frame's
/// z = 0 plane, so their plans are not checked (`None`).
// Called once per recipe; the error's size costs nothing next to a capture.
#[allow(clippy::result_large_err)]
pub(super) fn check_intrinsics_plan(
    recipe: &Recipe,
    rig: &Rig,
    board: &gonio_calibration::board::Board,
) -> Result<Option<PlanCheck>, CalibrateError> {
    if recipe.wedge.is_some() {
        return Ok(None);
    }
    let object = board.all_corners();
    let mut plan = Vec::with_capacity(recipe.poses.len());
    let mut prev: Option<Vec<f64>> = None;
    for (index, pose) in recipe.poses.iter().enumerate() {
        let light = pose.light.unwrap_or(recipe.light);
        let q = rig
            .kinematics
            .inverse(
                Direction::from_degrees(light[0], light[1]),
                Direction::from_degrees(pose.view[0], pose.view[1]),
                prev.as_deref(),
            )
            .ok()
            .and_then(|s| s.into_iter().next())
            .ok_or_else(|| CalibrateError::Unreachable {
                recipe: recipe.name.clone(),
                index,
                view: pose.view,
                light,
                rig: rig.spec.name.clone(),
                reason: "no axis configuration reaches it (checked before the rig moved)".into(),
            })?;
        plan.push(PlannedView {
            label: format!("pose {index} view θ={} φ={}", pose.view[0], pose.view[1]),
            object: object.clone(),
            pose: nominal_board_pose(rig, &q),
        });
        prev = Some(q);
    }
    let size = (rig.spec.camera.width, rig.spec.camera.height);
    check_plan(&nominal_camera(rig), &plan, size, &recipe.estimate)
        .map(Some)
        .map_err(|cause| CalibrateError::Intrinsics {
            recipe: recipe.name.clone(),
            cause,
        })
}

/// Where the sample appears in acquisitions: the camera aims at the sample's centre, so a
/// disc about the principal point whose radius is the sample's half-diagonal (the square
/// turns on the turntable) seen from the camera distance; tilted views only foreshorten it.
pub(super) fn sample_region(rig: &Rig, cam: &CameraModel) -> ImageDisc {
    let g = &rig.spec.geometry;
    let half_diag = 0.5 * g.sample_size_mm * std::f64::consts::SQRT_2;
    ImageDisc {
        centre_px: [cam.cx, cam.cy],
        radius_px: cam.fx.max(cam.fy) * half_diag / g.camera_distance_mm,
    }
}

/// The projection-uncertainty report of a fit.
pub(super) fn report(rig: &Rig, fit: &IntrinsicsCalibration, views: &[TargetView]) -> ProjectionUncertainty {
    let size = (rig.spec.camera.width, rig.spec.camera.height);
    projection_uncertainty(
        &fit.camera,
        &fit.covariance,
        views,
        size,
        Some(sample_region(rig, &fit.camera)),
        &UncertaintyOptions::default(),
    )
}

/// The true projection error on the report's grid (simulator).
pub(super) fn truth_check(estimate: &CameraModel, truth: &CameraModel, r: &ProjectionUncertainty) -> ProjectionTruth {
    let mut error_px = Vec::with_capacity(r.sigma_px.len());
    let (mut max_e, mut at, mut ratio, mut beyond) = (0.0f64, [0.0; 2], 0.0f64, 0usize);
    let mut sample_max: Option<f64> = None;
    for (j, &y) in r.grid_y.iter().enumerate() {
        for (i, &x) in r.grid_x.iter().enumerate() {
            let (Some(e), Some(s)) = (projection_error(estimate, truth, x, y), r.sigma_px[j * r.nx() + i]) else {
                error_px.push(None);
                continue;
            };
            if e > max_e {
                max_e = e;
                at = [x, y];
            }
            ratio = ratio.max(e / s);
            if e.is_nan() || e > 3.0 * s {
                beyond += 1;
            }
            if let Some(d) = r.sample_region {
                if (x - d.centre_px[0]).hypot(y - d.centre_px[1]) <= d.radius_px {
                    sample_max = Some(sample_max.map_or(e, |m: f64| m.max(e)));
                }
            }
            error_px.push(Some(e));
        }
    }
    let n = error_px.iter().flatten().count().max(1);
    ProjectionTruth {
        error_px,
        max_error_px: max_e,
        max_error_at_px: at,
        sample_max_error_px: sample_max,
        max_error_over_sigma: ratio,
        beyond_3_sigma_fraction: beyond as f64 / n as f64,
    }
}

/// The heat map `gonio calibrate` writes (`uncertainty.png`): the one-sigma projection
/// uncertainty on a log colour scale from 0.01 px (dark blue) through the threshold
/// (green) to 10 px and above (red), the sample's region as a white circle, the observed
/// corners as black dots, nodes above the threshold hatched by a darker tone.
pub fn heat_map(r: &ProjectionUncertainty, views: &[TargetView]) -> image::RgbImage {
    let [w, h] = r.image_size;
    let (nx, ny) = (r.nx(), r.ny());
    // bilinear interpolation of log10(sigma) between nodes
    // no ray: drawn as the top of the scale
    let log_sigma: Vec<f64> = r
        .sigma_px
        .iter()
        .map(|s| s.map_or(3.0, |s| s.max(1e-6).log10()))
        .collect();
    let node = |gx: &[f64], x: f64| -> (usize, f64) {
        let step = gx[1] - gx[0];
        let k = ((x / step).floor() as usize).min(gx.len() - 2);
        (k, ((x - gx[k]) / step).clamp(0.0, 1.0))
    };
    let colour = |t: f64| -> [u8; 3] {
        // t in [0, 1]: blue → cyan → green → yellow → red
        let stops: [[f64; 3]; 5] = [
            [20.0, 30.0, 140.0],
            [0.0, 170.0, 220.0],
            [40.0, 190.0, 60.0],
            [240.0, 220.0, 0.0],
            [220.0, 30.0, 20.0],
        ];
        let x = t.clamp(0.0, 1.0) * 4.0;
        let k = (x.floor() as usize).min(3);
        let f = x - k as f64;
        std::array::from_fn(|c| (stops[k][c] * (1.0 - f) + stops[k + 1][c] * f).round() as u8)
    };
    let (lo, hi) = (-2.0f64, 1.0f64); // 0.01 px .. 10 px
    let mut img = image::RgbImage::new(w as u32, h as u32);
    if nx < 2 || ny < 2 {
        return img;
    }
    for py in 0..h {
        let (j, fy) = node(&r.grid_y, py as f64 + 0.5);
        for px in 0..w {
            let (i, fx) = node(&r.grid_x, px as f64 + 0.5);
            let at = |a: usize, b: usize| log_sigma[b * nx + a];
            let v = (1.0 - fy) * ((1.0 - fx) * at(i, j) + fx * at(i + 1, j))
                + fy * ((1.0 - fx) * at(i, j + 1) + fx * at(i + 1, j + 1));
            let mut c = colour((v - lo) / (hi - lo));
            if v > r.threshold_px.log10() && (px + py) % 8 < 2 {
                c = c.map(|x| x / 2);
            }
            img.put_pixel(px as u32, py as u32, image::Rgb(c));
        }
    }
    if let Some(d) = r.sample_region {
        let n = (2.0 * std::f64::consts::PI * d.radius_px).ceil() as usize * 2;
        for k in 0..n.max(8) {
            let a = 2.0 * std::f64::consts::PI * k as f64 / n.max(8) as f64;
            let (x, y) = (
                d.centre_px[0] + d.radius_px * a.cos(),
                d.centre_px[1] + d.radius_px * a.sin(),
            );
            if x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h {
                img.put_pixel(x as u32, y as u32, image::Rgb([255, 255, 255]));
            }
        }
    }
    for v in views {
        for p in &v.image {
            let (cx, cy) = (p[0].floor() as i64, p[1].floor() as i64);
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (x, y) = (cx + dx, cy + dy);
                    if x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h {
                        img.put_pixel(x as u32, y as u32, image::Rgb([0, 0, 0]));
                    }
                }
            }
        }
    }
    img
}
