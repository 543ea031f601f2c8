//! Plane-to-image homographies: the exact map from the sample plane (z = 0, millimetres)
//! to a pinhole camera's pixels.
//!
//! A homography is built either from the rig's known camera pose ([`Homography::from_pose`])
//! or fitted to detected marker centres ([`Homography::fit`]). The sign of the third
//! homogeneous coordinate is kept meaningful: for a homography from a pose it is the depth
//! of the point in front of the camera, and a fit is oriented so that it is positive at the
//! fitted points. [`Homography::apply`] uses it to refuse points behind the camera, which a
//! sign-blind projective division would silently map onto the image.

use crate::CalibError;
use gonio_devices::camera::Intrinsics;
use gonio_devices::kinematics::CameraPose;
use gonio_devices::Vec3;
use nalgebra::{DMatrix, Matrix3, SMatrix, SVector};
use serde::{Deserialize, Serialize};

/// Row-major 3 × 3 matrix mapping sample-plane `(x_mm, y_mm, 1)` to homogeneous pixel
/// coordinates `(u·w, v·w, w)` (pixel (i, j) has its centre at (i + ½, j + ½)).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Homography(pub [[f64; 3]; 3]);

/// A point correspondence: plane `(x, y)` in mm and its pixel `(u, v)`.
pub type Correspondence = ((f64, f64), (f64, f64));

/// Gauss-Newton / Levenberg-Marquardt iterations after the DLT. The DLT minimizes an
/// algebraic error; a handful of iterations reach the reprojection-error minimum from it.
const LM_ITERATIONS: usize = 30;

/// Below this ratio of the two smallest-but-one to the largest singular value of the
/// normalized DLT system the null space is more than one-dimensional: the points do not
/// determine a homography.
const DEGENERATE_SV_RATIO: f64 = 1e-7;

/// Smallest allowed ratio of the minor to the major eigenvalue of the normalized point
/// scatter: below it the points are (numerically) on a line.
const COLLINEAR_RATIO: f64 = 1e-5;

impl Homography {
    /// The exact homography of the z = 0 plane for a pinhole camera at `pose`.
    ///
    /// With `R` the rows (right, down, forward) and `c` the centre of projection, a plane
    /// point maps to camera coordinates `x·R e_x + y·R e_y − R c`; multiplying by `K` gives
    /// `H = K [r₁ r₂ t]`, whose third output is the point's depth along `forward`.
    pub fn from_pose(intr: &Intrinsics, pose: &CameraPose) -> Homography {
        let o = pose.to_camera(Vec3::ZERO);
        let ex = pose.to_camera(Vec3::new(1.0, 0.0, 0.0)) - o;
        let ey = pose.to_camera(Vec3::new(0.0, 1.0, 0.0)) - o;
        let k = |c: Vec3| [intr.fx * c.x + intr.cx * c.z, intr.fy * c.y + intr.cy * c.z, c.z];
        let (a, b, t) = (k(ex), k(ey), k(o));
        Homography([[a[0], b[0], t[0]], [a[1], b[1], t[1]], [a[2], b[2], t[2]]])
    }

    /// Homogeneous image of a plane point: `(u·w, v·w, w)`.
    #[inline]
    pub fn apply_homogeneous(&self, x: f64, y: f64) -> [f64; 3] {
        let h = &self.0;
        [
            h[0][0] * x + h[0][1] * y + h[0][2],
            h[1][0] * x + h[1][1] * y + h[1][2],
            h[2][0] * x + h[2][1] * y + h[2][2],
        ]
    }

    /// Pixel coordinates of a plane point, or `None` when it lies behind the camera
    /// (w ≤ 0) or the result is not finite.
    #[inline]
    pub fn apply(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        let [u, v, w] = self.apply_homogeneous(x, y);
        if w > 0.0 && w.is_finite() {
            let (u, v) = (u / w, v / w);
            (u.is_finite() && v.is_finite()).then_some((u, v))
        } else {
            None
        }
    }

    /// The inverse map (pixel → plane), or `None` for a singular matrix.
    ///
    /// Computed as adj(H)/det(H), so the sign convention carries over: a pixel whose ray
    /// meets the plane in front of the camera maps with w > 0 (w = 1/depth for a pose
    /// homography), one above the horizon with w < 0 and is refused by [`apply`](Self::apply).
    pub fn inverse(&self) -> Option<Homography> {
        let m = self.matrix();
        let scale = m.abs().max();
        if !(scale > 0.0 && scale.is_finite()) {
            return None;
        }
        // Scale first so the determinant test is relative.
        let ms = m / scale;
        let det = ms.determinant();
        if det.abs() < 1e-14 {
            return None;
        }
        let inv = ms.try_inverse()? / scale;
        Some(Homography::from_matrix(&inv))
    }

    /// d(u, v)/d(x, y) at a plane point, in pixels per millimetre: `[[du/dx, du/dy],
    /// [dv/dx, dv/dy]]`. Meaningless behind the camera (the caller checks `apply` first).
    #[inline]
    pub fn jacobian(&self, x: f64, y: f64) -> [[f64; 2]; 2] {
        let h = &self.0;
        let [uw, vw, w] = self.apply_homogeneous(x, y);
        let (u, v) = (uw / w, vw / w);
        [
            [(h[0][0] - u * h[2][0]) / w, (h[0][1] - u * h[2][1]) / w],
            [(h[1][0] - v * h[2][0]) / w, (h[1][1] - v * h[2][1]) / w],
        ]
    }

    /// Root-mean-square reprojection distance (pixels) of `(plane, pixel)` pairs; infinite
    /// if a plane point maps behind the camera, NaN for no pairs.
    pub fn rms_error(&self, pairs: &[Correspondence]) -> f64 {
        let mut sum = 0.0;
        for &((x, y), (u, v)) in pairs {
            match self.apply(x, y) {
                Some((pu, pv)) => sum += (pu - u).powi(2) + (pv - v).powi(2),
                None => return f64::INFINITY,
            }
        }
        (sum / pairs.len() as f64).sqrt()
    }

    /// Fit the homography to `(plane (x, y) mm, pixel (u, v))` correspondences.
    ///
    /// Normalized DLT (Hartley: each point set translated to its centroid and scaled to a
    /// mean distance of √2, which makes the linear system well conditioned), solved by SVD,
    /// then Levenberg-Marquardt on the reprojection error in pixels, which is the error the
    /// marker detector actually makes. Errors instead of garbage for fewer than 4 points,
    /// non-finite input, (near-)collinear points or any configuration whose null space is
    /// not one-dimensional (e.g. three of four points on a line).
    pub fn fit(pairs: &[Correspondence]) -> Result<Homography, CalibError> {
        if pairs.len() < 4 {
            return Err(CalibError::TooFewPoints {
                needed: 4,
                got: pairs.len(),
            });
        }
        for (index, &((x, y), (u, v))) in pairs.iter().enumerate() {
            if ![x, y, u, v].iter().all(|c| c.is_finite()) {
                return Err(CalibError::NonFinite { index });
            }
        }
        let plane: Vec<(f64, f64)> = pairs.iter().map(|p| p.0).collect();
        let pix: Vec<(f64, f64)> = pairs.iter().map(|p| p.1).collect();
        let t_plane = normalization(&plane, "plane points")?;
        let t_pix = normalization(&pix, "pixel points")?;
        let np: Vec<(f64, f64)> = plane.iter().map(|&p| t_plane.map(p)).collect();
        let nq: Vec<(f64, f64)> = pix.iter().map(|&p| t_pix.map(p)).collect();

        // DLT: each pair gives two rows of A h = 0. Pad to at least 9 rows so the SVD's V
        // contains the whole 9-dimensional space (nalgebra returns min(rows, 9) vectors).
        let rows = (2 * pairs.len()).max(9);
        let mut a = DMatrix::<f64>::zeros(rows, 9);
        for (k, (&(x, y), &(u, v))) in np.iter().zip(&nq).enumerate() {
            let r = 2 * k;
            let row0 = [x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y, -u];
            let row1 = [0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y, -v];
            for c in 0..9 {
                a[(r, c)] = row0[c];
                a[(r + 1, c)] = row1[c];
            }
        }
        let svd = a.svd(false, true);
        let v_t = svd
            .v_t
            .as_ref()
            .ok_or_else(|| CalibError::Degenerate("SVD did not converge".into()))?;
        let s = &svd.singular_values; // sorted descending, length 9
        if s[0].is_nan() || s[0] <= 0.0 || s[7] / s[0] < DEGENERATE_SV_RATIO {
            return Err(CalibError::Degenerate(format!(
                "the points do not determine a homography (singular values {:.3e} … {:.3e}; \
                 are three or more of four points collinear?)",
                s[0], s[7]
            )));
        }
        let mut h = SVector::<f64, 9>::from_iterator(v_t.row(8).iter().copied());
        let mut cost = sq_cost(&h, &np, &nq);
        // Levenberg-Marquardt in normalized coordinates: the pixel normalization is a
        // similarity, so its residuals are the pixel residuals times one constant.
        let mut lambda = 1e-3;
        for _ in 0..LM_ITERATIONS {
            let (jtj, jtr) = normal_equations(&h, &np, &nq);
            let mut improved = false;
            for _ in 0..10 {
                let mut m = jtj;
                for d in 0..9 {
                    m[(d, d)] += lambda * (jtj[(d, d)] + 1e-12);
                }
                let Some(chol) = m.cholesky() else {
                    lambda *= 10.0;
                    continue;
                };
                let step = chol.solve(&(-jtr));
                let mut cand = h + step;
                cand /= cand.norm();
                let c = sq_cost(&cand, &np, &nq);
                if c < cost {
                    let rel = (cost - c) / cost.max(1e-300);
                    h = cand;
                    cost = c;
                    lambda = (lambda * 0.3).max(1e-12);
                    improved = rel > 1e-14;
                    break;
                }
                lambda *= 10.0;
            }
            if !improved {
                break;
            }
        }
        let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
        let det_rel = hn.determinant() / hn.norm().powi(3);
        if det_rel.is_nan() || det_rel.abs() <= 1e-9 {
            return Err(CalibError::Degenerate(format!(
                "the fitted homography is singular (relative determinant {det_rel:.2e})"
            )));
        }
        let full = t_pix.inverse_matrix() * hn * t_plane.matrix();
        let mut full = full / full.norm();
        // Orient so points in front of the camera have w > 0; all of them must agree.
        let ws: Vec<f64> = plane
            .iter()
            .map(|&(x, y)| full[(2, 0)] * x + full[(2, 1)] * y + full[(2, 2)])
            .collect();
        let positive = ws.iter().filter(|&&w| w > 0.0).count();
        if positive * 2 < ws.len() {
            full = -full;
        }
        if positive != ws.len() && positive != 0 {
            return Err(CalibError::Degenerate(
                "the fitted plane crosses the camera's horizon between the points".into(),
            ));
        }
        Ok(Homography::from_matrix(&full))
    }

    /// The matrix as nalgebra's type.
    pub fn matrix(&self) -> Matrix3<f64> {
        let h = &self.0;
        Matrix3::new(
            h[0][0], h[0][1], h[0][2], h[1][0], h[1][1], h[1][2], h[2][0], h[2][1], h[2][2],
        )
    }

    /// From nalgebra's type.
    pub fn from_matrix(m: &Matrix3<f64>) -> Homography {
        Homography([
            [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
            [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
            [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
        ])
    }
}

/// Hartley normalization: `p ↦ s·(p − c)` with mean distance √2 from the origin.
#[derive(Clone, Copy, Debug)]
struct Similarity {
    cx: f64,
    cy: f64,
    s: f64,
}

impl Similarity {
    fn map(&self, (x, y): (f64, f64)) -> (f64, f64) {
        (self.s * (x - self.cx), self.s * (y - self.cy))
    }
    fn matrix(&self) -> Matrix3<f64> {
        Matrix3::new(
            self.s,
            0.0,
            -self.s * self.cx,
            0.0,
            self.s,
            -self.s * self.cy,
            0.0,
            0.0,
            1.0,
        )
    }
    fn inverse_matrix(&self) -> Matrix3<f64> {
        Matrix3::new(1.0 / self.s, 0.0, self.cx, 0.0, 1.0 / self.s, self.cy, 0.0, 0.0, 1.0)
    }
}

/// The normalizing similarity of a point set; fails for coincident or collinear points,
/// which no homography fit can use.
fn normalization(pts: &[(f64, f64)], what: &str) -> Result<Similarity, CalibError> {
    let n = pts.len() as f64;
    let cx = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let cy = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let mean_d = pts.iter().map(|p| (p.0 - cx).hypot(p.1 - cy)).sum::<f64>() / n;
    if !(mean_d > 0.0 && mean_d.is_finite()) {
        return Err(CalibError::Degenerate(format!("all {what} coincide")));
    }
    let s = std::f64::consts::SQRT_2 / mean_d;
    // Scatter matrix of the normalized points: its eigenvalue ratio measures how far the
    // set is from a line.
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for p in pts {
        let (x, y) = (s * (p.0 - cx), s * (p.1 - cy));
        sxx += x * x;
        sxy += x * y;
        syy += y * y;
    }
    let tr = sxx + syy;
    let disc = ((sxx - syy).powi(2) + 4.0 * sxy * sxy).sqrt();
    let (major, minor) = ((tr + disc) / 2.0, (tr - disc) / 2.0);
    if minor / major < COLLINEAR_RATIO {
        return Err(CalibError::Degenerate(format!(
            "the {what} are collinear (scatter eigenvalue ratio {:.1e})",
            minor / major
        )));
    }
    Ok(Similarity { cx, cy, s })
}

/// Sum of squared reprojection residuals for `h` (row-major 9-vector).
fn sq_cost(h: &SVector<f64, 9>, p: &[(f64, f64)], q: &[(f64, f64)]) -> f64 {
    p.iter()
        .zip(q)
        .map(|(&(x, y), &(u, v))| {
            let w = h[6] * x + h[7] * y + h[8];
            let pu = (h[0] * x + h[1] * y + h[2]) / w;
            let pv = (h[3] * x + h[4] * y + h[5]) / w;
            let c = (pu - u).powi(2) + (pv - v).powi(2);
            if c.is_finite() {
                c
            } else {
                f64::INFINITY
            }
        })
        .sum()
}

/// `JᵀJ` and `Jᵀr` of the reprojection residuals with respect to the 9 entries of `h`.
fn normal_equations(h: &SVector<f64, 9>, p: &[(f64, f64)], q: &[(f64, f64)]) -> (SMatrix<f64, 9, 9>, SVector<f64, 9>) {
    let mut jtj = SMatrix::<f64, 9, 9>::zeros();
    let mut jtr = SVector::<f64, 9>::zeros();
    for (&(x, y), &(u, v)) in p.iter().zip(q) {
        let w = h[6] * x + h[7] * y + h[8];
        let pu = (h[0] * x + h[1] * y + h[2]) / w;
        let pv = (h[3] * x + h[4] * y + h[5]) / w;
        let ju = SVector::<f64, 9>::from([x / w, y / w, 1.0 / w, 0.0, 0.0, 0.0, -pu * x / w, -pu * y / w, -pu / w]);
        let jv = SVector::<f64, 9>::from([0.0, 0.0, 0.0, x / w, y / w, 1.0 / w, -pv * x / w, -pv * y / w, -pv / w]);
        jtj += ju * ju.transpose() + jv * jv.transpose();
        jtr += ju * (pu - u) + jv * (pv - v);
    }
    (jtj, jtr)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::{pose, rig_intrinsics, Rng};

    fn grid_points() -> Vec<(f64, f64)> {
        let mut v = Vec::new();
        for i in 0..5 {
            for j in 0..5 {
                v.push((-35.0 + 17.5 * i as f64, -35.0 + 17.5 * j as f64));
            }
        }
        v
    }

    #[test]
    fn from_pose_matches_direct_projection() {
        let intr = rig_intrinsics();
        for (theta, phi) in [(0.0, 0.0), (45.0, 30.0), (75.0, 200.0)] {
            let p = pose(theta, phi);
            let h = Homography::from_pose(&intr, &p);
            for (x, y) in grid_points() {
                let c = p.to_camera(Vec3::new(x, y, 0.0));
                let (u, v) = intr.project(c.x, c.y, c.z);
                let (hu, hv) = h.apply(x, y).unwrap();
                assert!(
                    (u - hu).abs() < 1e-9 && (v - hv).abs() < 1e-9,
                    "θ={theta}: {u},{v} vs {hu},{hv}"
                );
            }
        }
    }

    #[test]
    fn apply_refuses_points_behind_the_camera() {
        let intr = rig_intrinsics();
        let h = Homography::from_pose(&intr, &pose(75.0, 0.0));
        // The camera sits at x ≈ 966 mm: plane points beyond it are behind it.
        assert!(h.apply(2000.0, 0.0).is_none());
        assert!(h.apply(0.0, 0.0).is_some());
        // The inverse refuses pixels above the horizon the same way.
        let inv = h.inverse().unwrap();
        let (u, v) = h.apply(10.0, -5.0).unwrap();
        let (x, y) = inv.apply(u, v).unwrap();
        assert!((x - 10.0).abs() < 1e-9 && (y + 5.0).abs() < 1e-9);
        // At θ = 75° the camera looks 15° below the horizontal, so the horizon is
        // 5000·tan 15° ≈ 1340 px above the principal point (image "down" is world −z).
        let d = 5000.0 * 15f64.to_radians().tan();
        assert!(inv.apply(384.0, 320.0 - (d - 1.0)).is_some());
        assert!(inv.apply(384.0, 320.0 - (d + 1.0)).is_none());
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let h = Homography::from_pose(&rig_intrinsics(), &pose(60.0, 40.0));
        for (x, y) in grid_points() {
            let j = h.jacobian(x, y);
            let e = 1e-5;
            let (u1, v1) = h.apply(x + e, y).unwrap();
            let (u0, v0) = h.apply(x - e, y).unwrap();
            let (u3, v3) = h.apply(x, y + e).unwrap();
            let (u2, v2) = h.apply(x, y - e).unwrap();
            let fd = [
                [(u1 - u0) / (2.0 * e), (u3 - u2) / (2.0 * e)],
                [(v1 - v0) / (2.0 * e), (v3 - v2) / (2.0 * e)],
            ];
            for r in 0..2 {
                for c in 0..2 {
                    assert!((j[r][c] - fd[r][c]).abs() < 1e-5, "{j:?} vs {fd:?}");
                }
            }
        }
    }

    /// Max pixel distance between two homographies over the holder's area.
    fn max_dist(a: &Homography, b: &Homography) -> f64 {
        let mut worst: f64 = 0.0;
        for i in 0..=16 {
            for j in 0..=16 {
                let (x, y) = (-40.0 + 5.0 * i as f64, -40.0 + 5.0 * j as f64);
                let (u, v) = a.apply(x, y).unwrap();
                let (p, q) = b.apply(x, y).unwrap();
                worst = worst.max((u - p).hypot(v - q));
            }
        }
        worst
    }

    #[test]
    fn fit_recovers_exact_homography() {
        let intr = rig_intrinsics();
        for (theta, phi) in [(0.0, 0.0), (60.0, 18.0), (75.0, 345.0)] {
            let truth = Homography::from_pose(&intr, &pose(theta, phi));
            let pairs: Vec<_> = grid_points()
                .into_iter()
                .map(|p| (p, truth.apply(p.0, p.1).unwrap()))
                .collect();
            let fit = Homography::fit(&pairs).unwrap();
            let d = max_dist(&fit, &truth);
            assert!(d < 1e-6, "θ={theta}: {d}");
            // Minimal case: 4 points in general position.
            let fit4 = Homography::fit(&[pairs[0], pairs[4], pairs[20], pairs[24]]).unwrap();
            assert!(max_dist(&fit4, &truth) < 1e-6);
        }
    }

    #[test]
    fn fit_with_noise_is_within_a_tenth_of_a_pixel() {
        // 16 marker-like points (the holder's border) with 0.05 px detection noise (what the
        // marker detector achieves on noisy frames): the least-squares fit averages it and
        // stays within 0.1 px of the truth over the whole holder, corners included.
        let intr = rig_intrinsics();
        let border = gonio_devices::target::MarkerBorder::default();
        let mut rng = Rng::new(7);
        let mut worst: f64 = 0.0;
        for (theta, phi) in [(0.0, 0.0), (30.0, 60.0), (60.0, 18.0), (75.0, 90.0)] {
            let truth = Homography::from_pose(&intr, &pose(theta, phi));
            let pairs: Vec<_> = border
                .markers(60.0)
                .iter()
                .map(|m| {
                    let (u, v) = truth.apply(m.x, m.y).unwrap();
                    ((m.x, m.y), (u + 0.05 * rng.normal(), v + 0.05 * rng.normal()))
                })
                .collect();
            let fit = Homography::fit(&pairs).unwrap();
            let d = max_dist(&fit, &truth);
            eprintln!("θ={theta}: fitted H max error {d:.4} px over the holder (0.05 px marker noise)");
            worst = worst.max(d);
        }
        assert!(worst < 0.1, "{worst}");
    }

    #[test]
    fn levenberg_marquardt_improves_on_dlt() {
        // With one gross error the reprojection optimum differs from the algebraic one;
        // the final RMS must not be worse than the DLT starting point would give.
        let truth = Homography::from_pose(&rig_intrinsics(), &pose(60.0, 0.0));
        let mut rng = Rng::new(3);
        let pairs: Vec<_> = grid_points()
            .into_iter()
            .map(|p| {
                let (u, v) = truth.apply(p.0, p.1).unwrap();
                (p, (u + 0.5 * rng.normal(), v + 0.5 * rng.normal()))
            })
            .collect();
        let fit = Homography::fit(&pairs).unwrap();
        let rms_fit = fit.rms_error(&pairs);
        let rms_truth = truth.rms_error(&pairs);
        assert!(
            rms_fit <= rms_truth,
            "fit {rms_fit} must beat the generating H {rms_truth}"
        );
    }

    #[test]
    fn degenerate_inputs_are_errors() {
        let truth = Homography::from_pose(&rig_intrinsics(), &pose(30.0, 0.0));
        let pair = |x: f64, y: f64| ((x, y), truth.apply(x, y).unwrap());
        assert_eq!(
            Homography::fit(&[pair(0.0, 0.0), pair(1.0, 0.0), pair(0.0, 1.0)]),
            Err(CalibError::TooFewPoints { needed: 4, got: 3 })
        );
        let collinear: Vec<_> = (0..8).map(|k| pair(k as f64 * 3.0, k as f64 * 2.0 - 5.0)).collect();
        assert!(matches!(Homography::fit(&collinear), Err(CalibError::Degenerate(_))));
        let three_on_a_line = [pair(0.0, 0.0), pair(10.0, 0.0), pair(20.0, 0.0), pair(5.0, 10.0)];
        assert!(
            matches!(Homography::fit(&three_on_a_line), Err(CalibError::Degenerate(_))),
            "{:?}",
            Homography::fit(&three_on_a_line)
        );
        let same = [pair(1.0, 1.0); 5];
        assert!(matches!(Homography::fit(&same), Err(CalibError::Degenerate(_))));
        let mut nan = collinear.clone();
        nan[3].1 .0 = f64::NAN;
        assert_eq!(Homography::fit(&nan), Err(CalibError::NonFinite { index: 3 }));
        // Collinear image points (the plane seen edge-on) are degenerate too.
        let edge_on: Vec<_> = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)]
            .iter()
            .map(|&(x, y)| ((x, y), (100.0 + 5.0 * x + 3.0 * y, 200.0)))
            .collect();
        assert!(matches!(Homography::fit(&edge_on), Err(CalibError::Degenerate(_))));
    }

    #[test]
    fn inverse_round_trips_and_refuses_singular() {
        let h = Homography::from_pose(&rig_intrinsics(), &pose(45.0, 123.0));
        let inv = h.inverse().unwrap();
        for (x, y) in grid_points() {
            let (u, v) = h.apply(x, y).unwrap();
            let (bx, by) = inv.apply(u, v).unwrap();
            assert!((bx - x).abs() < 1e-9 && (by - y).abs() < 1e-9);
        }
        assert!(Homography([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 0.0, 1.0]])
            .inverse()
            .is_none());
        assert!(Homography([[0.0; 3]; 3]).inverse().is_none());
    }
}
