//! Projection uncertainty of an intrinsics fit over the whole image, and how much of the
//! image the observed corners covered.
//!
//! A fit that reprojects its corners to 0.01 px can still be pixels off where no corner
//! was seen: the distortion polynomial is extrapolating there. What tells the two apart is
//! the fit's own covariance propagated to the image: `Σ_θ` (the camera parameters'
//! covariance, marginal over the board poses, scaled by the observed corner noise;
//! [`CameraCovariance`]) through the projection of a fixed set of points.
//!
//! The points: one per grid node over the whole image, the node's pixel unprojected
//! through the *estimated* camera to a ray and a point on it held fixed in the camera
//! frame. Held fixed in the camera frame, its projection depends only on its direction, so
//! the distance does not matter (unlike mrcal, which holds the point fixed in the boards'
//! frame and so also propagates the pose uncertainty; here the principal point's
//! uncertainty therefore shows in full, including the part a rotation of the camera would
//! absorb, which makes the report conservative near the centre). At each node the 2 × 2
//! covariance `J Σ_θ Jᵀ` (`J`: the projection's derivatives with respect to the nine camera
//! parameters) gives the reported one sigma: the square root of its larger eigenvalue, the
//! worst direction (mrcal's convention).
//!
//! The true error it is checked against on the simulator ([`projection_error`]) is the
//! same construction with the true camera: the node's ray through the estimate, projected
//! by the truth, distance to the node.

use crate::intrinsics::{CameraCovariance, CameraModel, TargetView, NCAM};
use serde::{Deserialize, Serialize};

/// Where and how finely to evaluate, and what counts as too uncertain.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct UncertaintyOptions {
    /// Grid node spacing (px); nodes also lie on the image border and its corners.
    pub grid_step_px: f64,
    /// One-sigma projection uncertainty (px) above which a region is flagged. 0.1 px: the
    /// intrinsics recipes' own reprojection target, and at the wide-lens rig's 1100 px
    /// focal length ≈ 0.09 mrad, an order below a texel of the rectified BTF
    /// (`docs/guide/calibration-uncertainty.md`).
    pub threshold_px: f64,
    /// Side of the cells (px) the coverage is counted in.
    pub coverage_cell_px: f64,
}

impl Default for UncertaintyOptions {
    fn default() -> Self {
        UncertaintyOptions {
            grid_step_px: 16.0,
            threshold_px: 0.1,
            coverage_cell_px: 8.0,
        }
    }
}

/// A disc in the image (px): where the sample appears in acquisitions.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ImageDisc {
    pub centre_px: [f64; 2],
    pub radius_px: f64,
}

impl ImageDisc {
    fn contains(&self, x: f64, y: f64) -> bool {
        (x - self.centre_px[0]).hypot(y - self.centre_px[1]) <= self.radius_px
    }
}

/// The projection-uncertainty report of one intrinsics fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProjectionUncertainty {
    /// How the points were chosen and what the sigma means (for readers of the JSON).
    pub method: String,
    pub image_size: [usize; 2],
    /// Grid node coordinates (px, gonio's convention).
    pub grid_x: Vec<f64>,
    pub grid_y: Vec<f64>,
    /// One-sigma projection uncertainty (px) at each node, row-major (`grid_y` rows);
    /// `null` where the estimated model folds over and defines no ray (counted as
    /// exceeding the threshold).
    pub sigma_px: Vec<Option<f64>>,
    /// Fraction of grid nodes where the estimated model defines no ray.
    pub undefined_fraction: f64,
    pub noise_sigma_px: f64,
    pub covariance_condition: f64,
    pub max_px: f64,
    pub median_px: f64,
    /// Where the sample appears in acquisitions, and the largest sigma inside it.
    pub sample_region: Option<ImageDisc>,
    pub sample_max_px: Option<f64>,
    /// Fraction of the image inside the convex hull of some view's corners.
    pub coverage_fraction: f64,
    /// Pixel bounding box of all observed corners `[x0, y0, x1, y1]`.
    pub corner_bbox_px: [f64; 4],
    pub threshold_px: f64,
    /// Fraction of grid nodes above the threshold.
    pub exceeding_fraction: f64,
    /// The image sectors (of a 3 × 3 split: "top-left" … "centre" … "bottom-right") with a
    /// node above the threshold.
    pub exceeding_sectors: Vec<String>,
    /// A sentence for the user when any node exceeds the threshold.
    pub warning: Option<String>,
}

impl ProjectionUncertainty {
    pub fn nx(&self) -> usize {
        self.grid_x.len()
    }

    pub fn ny(&self) -> usize {
        self.grid_y.len()
    }
}

/// Grid nodes over `[0, n]` at about `step` apart, both ends included.
fn axis_nodes(n: usize, step: f64) -> Vec<f64> {
    let cells = ((n as f64 / step.max(1.0)).ceil() as usize).max(1);
    (0..=cells).map(|i| n as f64 * i as f64 / cells as f64).collect()
}

/// Derivatives of the pixel `(u, v)` of normalized point `(x, y)` with respect to
/// `[fx, fy, cx, cy, k1, k2, p1, p2, k3]`.
fn projection_jacobian(cam: &CameraModel, x: f64, y: f64) -> [[f64; NCAM]; 2] {
    let (xd, yd) = cam.distort(x, y);
    let r2 = x * x + y * y;
    let (r4, r6) = (r2 * r2, r2 * r2 * r2);
    let (fx, fy) = (cam.fx, cam.fy);
    [
        [
            xd,
            0.0,
            1.0,
            0.0,
            fx * x * r2,
            fx * x * r4,
            fx * 2.0 * x * y,
            fx * (r2 + 2.0 * x * x),
            fx * x * r6,
        ],
        [
            0.0,
            yd,
            0.0,
            1.0,
            fy * y * r2,
            fy * y * r4,
            fy * (r2 + 2.0 * y * y),
            fy * 2.0 * x * y,
            fy * y * r6,
        ],
    ]
}

/// One sigma (px, worst direction) of the projection of the ray through pixel `(u, v)`;
/// `None` where the estimated model defines no ray ([`CameraModel::try_undistort`]).
pub fn sigma_at(cam: &CameraModel, cov: &CameraCovariance, u: f64, v: f64) -> Option<f64> {
    let (x, y) = cam.try_undistort(u, v)?;
    let j = projection_jacobian(cam, x, y);
    let mut c = [[0.0; 2]; 2];
    for a in 0..2 {
        for b in 0..2 {
            let mut acc = 0.0;
            for i in 0..NCAM {
                if j[a][i] == 0.0 {
                    continue;
                }
                for k in 0..NCAM {
                    if j[b][k] != 0.0 {
                        acc += j[a][i] * cov.params[i][k] * j[b][k];
                    }
                }
            }
            c[a][b] = acc;
        }
    }
    let tr = c[0][0] + c[1][1];
    let det = c[0][0] * c[1][1] - c[0][1] * c[1][0];
    let disc = (0.25 * tr * tr - det).max(0.0).sqrt();
    Some((0.5 * tr + disc).max(0.0).sqrt())
}

/// The true projection error at pixel `(u, v)` (simulator): the estimate's ray through it,
/// projected by the true camera, distance to `(u, v)` in pixels.
/// `None` where the estimate defines no ray.
pub fn projection_error(estimate: &CameraModel, truth: &CameraModel, u: f64, v: f64) -> Option<f64> {
    let (x, y) = estimate.try_undistort(u, v)?;
    let (ut, vt) = truth.project_point([x, y, 1.0]);
    Some((ut - u).hypot(vt - v))
}

/// Twice the signed area of triangle `o a b`.
fn cross(o: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
}

/// Convex hull (counter-clockwise in the `cross` sense), monotone chain.
fn convex_hull(points: &[[f64; 2]]) -> Vec<[f64; 2]> {
    let mut p = points.to_vec();
    p.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    p.dedup();
    if p.len() < 3 {
        return p;
    }
    let mut lower: Vec<[f64; 2]> = Vec::new();
    for &q in &p {
        while lower.len() >= 2 && cross(lower[lower.len() - 2], lower[lower.len() - 1], q) <= 0.0 {
            lower.pop();
        }
        lower.push(q);
    }
    let mut upper: Vec<[f64; 2]> = Vec::new();
    for &q in p.iter().rev() {
        while upper.len() >= 2 && cross(upper[upper.len() - 2], upper[upper.len() - 1], q) <= 0.0 {
            upper.pop();
        }
        upper.push(q);
    }
    lower.pop();
    upper.pop();
    lower.extend(upper);
    lower
}

fn inside_hull(hull: &[[f64; 2]], q: [f64; 2]) -> bool {
    hull.len() >= 3 && (0..hull.len()).all(|i| cross(hull[i], hull[(i + 1) % hull.len()], q) >= 0.0)
}

/// Fraction of the image (counted in cells of `cell` px, by their centres) inside the
/// convex hull of at least one view's corners.
pub fn coverage_fraction(views: &[TargetView], image_size: (usize, usize), cell: f64) -> f64 {
    let hulls: Vec<Vec<[f64; 2]>> = views.iter().map(|v| convex_hull(&v.image)).collect();
    let nx = ((image_size.0 as f64 / cell).ceil() as usize).max(1);
    let ny = ((image_size.1 as f64 / cell).ceil() as usize).max(1);
    let (sx, sy) = (image_size.0 as f64 / nx as f64, image_size.1 as f64 / ny as f64);
    let mut covered = 0usize;
    for j in 0..ny {
        for i in 0..nx {
            let q = [(i as f64 + 0.5) * sx, (j as f64 + 0.5) * sy];
            if hulls.iter().any(|h| inside_hull(h, q)) {
                covered += 1;
            }
        }
    }
    covered as f64 / (nx * ny) as f64
}

/// Name of the 3 × 3 image sector a pixel falls in.
fn sector(x: f64, y: f64, (w, h): (usize, usize)) -> &'static str {
    const NAMES: [[&str; 3]; 3] = [
        ["top-left", "top", "top-right"],
        ["left", "centre", "right"],
        ["bottom-left", "bottom", "bottom-right"],
    ];
    let col = ((3.0 * x / w as f64) as usize).min(2);
    let row = ((3.0 * y / h as f64) as usize).min(2);
    NAMES[row][col]
}

/// The report for a fit: the sigma grid over the whole image, its worst value inside the
/// sample's region, the corners' coverage, and a warning naming where the sigma exceeds
/// the threshold.
pub fn projection_uncertainty(
    cam: &CameraModel,
    cov: &CameraCovariance,
    views: &[TargetView],
    image_size: (usize, usize),
    sample_region: Option<ImageDisc>,
    opts: &UncertaintyOptions,
) -> ProjectionUncertainty {
    let grid_x = axis_nodes(image_size.0, opts.grid_step_px);
    let grid_y = axis_nodes(image_size.1, opts.grid_step_px);
    let mut sigma_px = Vec::with_capacity(grid_x.len() * grid_y.len());
    let mut sample_max: Option<f64> = None;
    let mut exceeding = 0usize;
    let mut sectors: Vec<&'static str> = Vec::new();
    for &y in &grid_y {
        for &x in &grid_x {
            let s = sigma_at(cam, cov, x, y);
            // no ray, or NaN (an undetermined fit): counts as exceeding
            let over = !s.is_some_and(|s| s <= opts.threshold_px);
            if over {
                exceeding += 1;
                let name = sector(x, y, image_size);
                if !sectors.contains(&name) {
                    sectors.push(name);
                }
            }
            if sample_region.is_some_and(|r| r.contains(x, y)) {
                let v = s.unwrap_or(f64::INFINITY);
                sample_max = Some(sample_max.map_or(v, |m: f64| m.max(v)));
            }
            sigma_px.push(s);
        }
    }
    // fixed order for the output: reading order of the 3 × 3 split
    const ORDER: [&str; 9] = [
        "top-left",
        "top",
        "top-right",
        "left",
        "centre",
        "right",
        "bottom-left",
        "bottom",
        "bottom-right",
    ];
    let exceeding_sectors: Vec<String> = ORDER
        .iter()
        .filter(|n| sectors.contains(n))
        .map(|n| n.to_string())
        .collect();
    // over the nodes with a ray
    let mut sorted: Vec<f64> = sigma_px.iter().flatten().copied().collect();
    sorted.sort_by(|a, b| a.total_cmp(b));
    let max_px = sorted.last().copied().unwrap_or(f64::NAN);
    let median_px = sorted.get(sorted.len() / 2).copied().unwrap_or(f64::NAN);
    let undefined_fraction = 1.0 - sorted.len() as f64 / sigma_px.len().max(1) as f64;
    let all: Vec<[f64; 2]> = views.iter().flat_map(|v| v.image.iter().copied()).collect();
    let corner_bbox_px = all.iter().fold(
        [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY],
        |b, p| [b[0].min(p[0]), b[1].min(p[1]), b[2].max(p[0]), b[3].max(p[1])],
    );
    let coverage = coverage_fraction(views, image_size, opts.coverage_cell_px);
    let n = sigma_px.len();
    let exceeding_fraction = exceeding as f64 / n as f64;
    let warning =
        (exceeding > 0).then(|| {
            let inside = match (sample_region, sample_max) {
                (Some(_), Some(m)) if m.is_nan() || m > opts.threshold_px => {
                    format!(" INCLUDING the sample's region (up to {m:.3} px there)")
                }
                (Some(_), Some(m)) => format!(" (inside the sample's region at most {m:.3} px)"),
                _ => String::new(),
            };
            let undefined = if undefined_fraction > 0.0 {
            format!(
                "; over {:.0} % of the image the fitted distortion folds over and defines no ray at all",
                100.0 * undefined_fraction
            )
        } else {
            String::new()
        };
        format!(
            "projection uncertainty above {:.2} px over {:.0} % of the image, in the {} ({} up to {:.3} px){inside}{undefined}; \
             the corners covered {:.0} % of the image: the model extrapolates there — add views that put the board \
             into those parts of the image",
            opts.threshold_px,
            100.0 * exceeding_fraction,
            exceeding_sectors.join(", "),
            if exceeding_sectors.len() == 1 { "sector" } else { "sectors" },
            max_px,
            100.0 * coverage
        )
        });
    ProjectionUncertainty {
        method: "1-sigma (worst direction) of the projection of the estimated camera's ray through each grid node, \
                 held fixed in the camera frame, from the camera parameters' covariance marginal over the board poses \
                 scaled by the residual corner variance"
            .into(),
        image_size: [image_size.0, image_size.1],
        grid_x,
        grid_y,
        sigma_px,
        undefined_fraction,
        noise_sigma_px: cov.noise_sigma_px,
        covariance_condition: cov.condition,
        max_px,
        median_px,
        sample_region,
        sample_max_px: sample_max,
        coverage_fraction: coverage,
        corner_bbox_px,
        threshold_px: opts.threshold_px,
        exceeding_fraction,
        exceeding_sectors,
        warning,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hull_and_coverage() {
        let sq = [[10.0, 10.0], [30.0, 10.0], [30.0, 30.0], [10.0, 30.0], [20.0, 20.0]];
        let h = convex_hull(&sq);
        assert_eq!(h.len(), 4);
        assert!(inside_hull(&h, [15.0, 25.0]));
        assert!(!inside_hull(&h, [35.0, 25.0]));
        let v = TargetView {
            label: "a".into(),
            object: vec![[0.0; 2]; 4],
            image: vec![[0.0, 0.0], [50.0, 0.0], [50.0, 50.0], [0.0, 50.0]],
        };
        let f = coverage_fraction(&[v], (100, 100), 10.0);
        assert!((f - 0.25).abs() < 1e-12, "{f}");
    }

    #[test]
    fn sigma_of_a_principal_point_only_covariance_is_its_sigma() {
        let cam = CameraModel {
            fx: 1000.0,
            fy: 1000.0,
            cx: 400.0,
            cy: 300.0,
            distortion: [-0.1, 0.02, 0.0, 0.0, 0.0],
        };
        let mut params = [[0.0; NCAM]; NCAM];
        params[2][2] = 0.04; // cx: 0.2 px
        params[3][3] = 0.01; // cy: 0.1 px
        let cov = CameraCovariance {
            params,
            noise_sigma_px: 0.01,
            condition: 1.0,
        };
        for (u, v) in [(0.0, 0.0), (400.0, 300.0), (700.0, 100.0)] {
            assert!((sigma_at(&cam, &cov, u, v).unwrap() - 0.2).abs() < 1e-12);
        }
        // a k1 variance grows with the radius, zero at the principal point
        let mut params = [[0.0; NCAM]; NCAM];
        params[4][4] = 1e-4;
        let cov = CameraCovariance { params, ..cov };
        let at = |u, v| sigma_at(&cam, &cov, u, v).unwrap();
        assert!(at(400.0, 300.0) < 1e-12);
        assert!(at(0.0, 0.0) > at(200.0, 150.0));
        // a polynomial that folds over inside the image defines no ray there
        let folded = CameraModel {
            distortion: [-0.1, 1.5, 0.0, 0.0, -90.0],
            ..cam
        };
        assert!(folded.try_undistort(400.0, 300.0).is_some());
        assert!(sigma_at(&folded, &cov, 0.0, 0.0).is_none());
        let r = projection_uncertainty(&cam, &cov, &[], (800, 600), None, &UncertaintyOptions::default());
        assert_eq!(r.sigma_px.len(), r.nx() * r.ny());
        assert_eq!(r.nx(), 51);
        assert!(r.warning.is_some());
        assert!(r.exceeding_sectors.contains(&"top-left".to_string()));
        assert!(!r.exceeding_sectors.contains(&"centre".to_string()));
    }
}
