//! The rectifying warp: resample a raw frame onto the sample's texel grid without
//! aliasing at any view direction.
//!
//! Output texel (i, j) of a W × H image covers, on the sample plane (edge `s` mm),
//! `x ∈ [i/W·s − s/2, (i+1)/W·s − s/2]` and `y` from `s/2 − j/H·s` down to
//! `s/2 − (j+1)/H·s`: columns grow with +x and rows with −y, row 0 is the +y edge, as
//! `shared/docs/conventions.md` fixes for rectified images.
//!
//! Each texel is a box prefilter over its own footprint: the homography's Jacobian at the
//! texel centre gives how many camera pixels each texel edge spans, and the texel averages
//! `n_u × n_v` bilinear samples spread uniformly over it with
//! `n = clamp(⌈pixels spanned⌉, 1, max_supersample)` per axis. So the sample spacing never
//! exceeds one camera pixel (minified views are filtered, not point-sampled, which would
//! alias fine texture into moiré), while magnified directions (grazing views, where a texel
//! is a fraction of a pixel) cost a single bilinear lookup. The axes are counted separately
//! because oblique views minify one axis and magnify the other.
//!
//! Samples that fall outside the frame or behind the camera contribute black: a texel the
//! camera did not see reads dark rather than repeating the frame's edge.

use crate::Homography;
use gonio_devices::image::RgbImage;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Size of the rectified image and of the sample it covers.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RectifyParams {
    /// Output width in texels (along +x).
    pub width: usize,
    /// Output height in texels (along −y).
    pub height: usize,
    /// Edge length of the square sample (mm); the output covers `[−s/2, s/2]²`.
    pub sample_mm: f64,
    /// Upper bound of the per-axis supersampling count; bounds the cost per texel at
    /// extreme minification (the filter then under-samples gracefully instead of stalling).
    pub max_supersample: usize,
}

impl RectifyParams {
    /// Why these parameters cannot be used, if they cannot.
    pub fn validate(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!(
                "output size {}×{} must be at least 1×1",
                self.width, self.height
            ));
        }
        if !(self.sample_mm > 0.0 && self.sample_mm.is_finite()) {
            return Err(format!("sample_mm = {} must be a finite number > 0", self.sample_mm));
        }
        if self.max_supersample == 0 {
            return Err("max_supersample must be ≥ 1".into());
        }
        Ok(())
    }

    /// Texel edge lengths (mm) along x and y.
    fn texel_mm(&self) -> (f64, f64) {
        (self.sample_mm / self.width as f64, self.sample_mm / self.height as f64)
    }

    /// Plane coordinates (mm) of texel (i, j)'s centre.
    pub fn texel_centre(&self, i: usize, j: usize) -> (f64, f64) {
        let (dx, dy) = self.texel_mm();
        let s2 = self.sample_mm / 2.0;
        ((i as f64 + 0.5) * dx - s2, s2 - (j as f64 + 0.5) * dy)
    }
}

/// Per-axis sample counts `(n_u, n_v)` for a texel whose centre is at plane `(x, y)`:
/// the camera pixels its x and y edges span, rounded up and clamped to
/// `1 ..= max_supersample`. A texel centre behind the camera gets `(1, 1)`.
pub fn texel_samples(h: &Homography, params: &RectifyParams, x: f64, y: f64) -> (usize, usize) {
    let (dx, dy) = params.texel_mm();
    match texel_map(&h.0, x, y) {
        Some((_, jac)) => counts(&jac, dx, dy, params.max_supersample.max(1)),
        None => (1, 1),
    }
}

/// Pixel position of a texel centre and the Jacobian d(u, v)/d(x, y) there (px per mm).
type TexelMap = ((f64, f64), [[f64; 2]; 2]);

/// The image of a texel centre, or `None` behind the camera.
#[inline(always)]
fn texel_map(m: &[[f64; 3]; 3], x: f64, y: f64) -> Option<TexelMap> {
    let w = m[2][0] * x + m[2][1] * y + m[2][2];
    if w.is_nan() || w <= 0.0 {
        return None;
    }
    let inv_w = 1.0 / w;
    let u = (m[0][0] * x + m[0][1] * y + m[0][2]) * inv_w;
    let v = (m[1][0] * x + m[1][1] * y + m[1][2]) * inv_w;
    let jac = [
        [(m[0][0] - u * m[2][0]) * inv_w, (m[0][1] - u * m[2][1]) * inv_w],
        [(m[1][0] - v * m[2][0]) * inv_w, (m[1][1] - v * m[2][1]) * inv_w],
    ];
    Some(((u, v), jac))
}

/// Per-axis counts from the Jacobian: ⌈pixels spanned by each texel edge⌉ in
/// `1 ..= max` (NaN → 1).
#[inline(always)]
fn counts(jac: &[[f64; 2]; 2], dx: f64, dy: f64, max: usize) -> (usize, usize) {
    let len_x = (jac[0][0] * jac[0][0] + jac[1][0] * jac[1][0]).sqrt() * dx;
    let len_y = (jac[0][1] * jac[0][1] + jac[1][1] * jac[1][1]).sqrt() * dy;
    let count = |len: f64| {
        if len > 1.0 {
            // ⌈len⌉ without a libm call, a hair low so that exactly one pixel stays one
            // sample.
            ((len - 1e-9) as usize + 1).min(max)
        } else {
            1
        }
    };
    (count(len_x), count(len_y))
}

/// Edge of the output tiles (texels) the warp walks, see [`warp`].
const TILE: usize = 16;

/// Bilinear reads from a raw frame of at least 2 × 2 pixels, with the per-frame constants
/// hoisted out of the per-sample path.
struct Source<'a> {
    data: &'a [f32],
    width: usize,
    stride: usize,
    /// Frame size in pixels (the valid range of continuous coordinates).
    wf: f64,
    hf: f64,
    height: usize,
}

impl<'a> Source<'a> {
    fn new(raw: &'a RgbImage) -> Self {
        assert!(
            raw.width >= 2 && raw.height >= 2,
            "raw frame must be at least 2 × 2 pixels"
        );
        Source {
            data: &raw.data,
            width: raw.width,
            stride: raw.width * 3,
            wf: raw.width as f64,
            hf: raw.height as f64,
            height: raw.height,
        }
    }

    /// Bilinear sample at continuous pixel coordinates (pixel (i, j) centred at
    /// (i + ½, j + ½)), clamped to the edge pixels within half a pixel of the frame edge,
    /// black outside `[0, W] × [0, H]`.
    #[inline(always)]
    fn sample(&self, u: f64, v: f64) -> [f32; 3] {
        if !(u >= 0.0 && v >= 0.0 && u <= self.wf && v <= self.hf) {
            return [0.0; 3];
        }
        // u + ½ ≥ ½ > 0, so the truncating cast is a floor: x0 = ⌊u − ½⌋ + 1 ∈ [0, W].
        // The top-left index of the 2 × 2 neighbourhood is then kept in [0, W − 2] with
        // the fraction clamped to [0, 1], which clamps to the edge pixels within half a
        // pixel of the frame edge.
        let xs = (u + 0.5) as usize;
        let ys = (v + 0.5) as usize;
        let x0 = xs.saturating_sub(1).min(self.width - 2);
        let y0 = ys.saturating_sub(1).min(self.height - 2);
        let fx = ((u - 0.5 - x0 as f64) as f32).clamp(0.0, 1.0);
        let fy = ((v - 0.5 - y0 as f64) as f32).clamp(0.0, 1.0);
        let i = (y0 * self.width + x0) * 3;
        let top: &[f32; 6] = self.data[i..i + 6].try_into().expect("6 values");
        let j = i + self.stride;
        let bottom: &[f32; 6] = self.data[j..j + 6].try_into().expect("6 values");
        let mut out = [0.0f32; 3];
        for c in 0..3 {
            let t = top[c] + fx * (top[c + 3] - top[c]);
            let b = bottom[c] + fx * (bottom[c + 3] - bottom[c]);
            out[c] = t + fy * (b - t);
        }
        out
    }
}

/// Rectify `raw` through `h` (sample plane mm → raw pixels) onto the texel grid of
/// `params`, box-filtering each texel's footprint (see the module documentation).
/// Parallel over output rows.
///
/// # Panics
/// If `raw`'s buffer does not match its size, `raw` is smaller than 2 × 2 pixels or
/// `params` fails [`RectifyParams::validate`] ([`crate::rectify::rectify_frame`] checks all
/// three and returns errors instead).
pub fn warp(raw: &RgbImage, h: &Homography, params: &RectifyParams) -> RgbImage {
    assert_eq!(
        raw.data.len(),
        raw.width * raw.height * 3,
        "raw image buffer does not match its size"
    );
    let src = Source::new(raw);
    if let Err(e) = params.validate() {
        panic!("invalid rectify parameters: {e}");
    }
    let (w_out, h_out) = (params.width, params.height);
    let (dx, dy) = params.texel_mm();
    let s2 = params.sample_mm / 2.0;
    let m = &h.0;
    let max = params.max_supersample;
    let recip: Vec<f64> = (0..=max).map(|n| 1.0 / n.max(1) as f64).collect();
    let mut out = RgbImage::new(w_out, h_out);
    // Bands of TILE rows in parallel, each walked in TILE × TILE tiles: the raw pixels a
    // tile reads stay in L1 whatever the camera's orientation (a rectified row can run
    // down a raw column, which row-by-row order would turn into one cache miss per sample).
    out.data
        .par_chunks_mut(w_out * 3 * TILE)
        .enumerate()
        .for_each(|(band, rows)| {
            let band_rows = rows.len() / (w_out * 3);
            for i0 in (0..w_out).step_by(TILE) {
                for jj in 0..band_rows {
                    let j = band * TILE + jj;
                    let row = &mut rows[jj * w_out * 3..(jj + 1) * w_out * 3];
                    let y_top = s2 - j as f64 * dy;
                    for i in i0..(i0 + TILE).min(w_out) {
                        let x_left = i as f64 * dx - s2;
                        let Some(((uc, vc), jac)) = texel_map(m, x_left + 0.5 * dx, y_top - 0.5 * dy) else {
                            continue; // behind the camera: stays black
                        };
                        let (nu, nv) = counts(&jac, dx, dy, max);
                        // Within one texel the homography is affine to ~1e-4 of the footprint (the
                        // depth changes by a texel's extent over a distance of ~1000 mm), so samples
                        // step along the Jacobian from the centre: no division per sample.
                        let (sx, sy) = (dx * recip[nu], dy * recip[nv]);
                        let (ux, vx) = (jac[0][0] * sx, jac[1][0] * sx); // one step along +x
                        let (uy, vy) = (-jac[0][1] * sy, -jac[1][1] * sy); // one step down a row (−y)
                        let (ox, oy) = (0.5 * (nu as f64 - 1.0), 0.5 * (nv as f64 - 1.0));
                        let mut acc = [0.0f32; 3];
                        for b in 0..nv {
                            let fb = b as f64 - oy;
                            let (u_row, v_row) = (uc + fb * uy, vc + fb * vy);
                            for a in 0..nu {
                                let fa = a as f64 - ox;
                                let c = src.sample(u_row + fa * ux, v_row + fa * vx);
                                acc[0] += c[0];
                                acc[1] += c[1];
                                acc[2] += c[2];
                            }
                        }
                        let norm = (recip[nu] * recip[nv]) as f32;
                        row[i * 3..i * 3 + 3].copy_from_slice(&[acc[0] * norm, acc[1] * norm, acc[2] * norm]);
                    }
                }
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::*;
    use std::time::Instant;

    /// A smooth, asymmetric colour texture (periods ≥ 5 mm, resolvable even at θ = 75°),
    /// defined on the whole plane so texel rings at the sample edge are not mixed with the
    /// border.
    fn smooth(x: f64, y: f64) -> [f32; 3] {
        use std::f64::consts::TAU;
        let a =
            0.5 + 0.25 * (TAU * x / 7.0 + 0.3).sin() * (TAU * y / 5.0).cos() + 0.1 * (TAU * (x + 2.0 * y) / 11.0).sin();
        let b = 0.4 + 0.2 * (TAU * (x - y) / 9.0).cos() + 0.05 * x / 30.0;
        let c = 0.3 + 0.15 * (TAU * y / 6.0 + 1.0).sin() + 0.1 * y / 30.0;
        [a as f32, b as f32, c as f32]
    }

    /// A checker of `cell` mm squares, 0.1 / 0.9.
    fn checker(cell: f64) -> impl Fn(f64, f64) -> [f32; 3] + Sync {
        move |x, y| {
            let k = (x / cell).floor() as i64 + (y / cell).floor() as i64;
            if k.rem_euclid(2) == 0 {
                [0.1; 3]
            } else {
                [0.9; 3]
            }
        }
    }

    /// The texture box-filtered over each texel (n × n point samples per texel).
    fn box_truth(f: &dyn Fn(f64, f64) -> [f32; 3], p: &RectifyParams, n: usize) -> RgbImage {
        let mut img = RgbImage::new(p.width, p.height);
        let (dx, dy) = (p.sample_mm / p.width as f64, p.sample_mm / p.height as f64);
        for j in 0..p.height {
            for i in 0..p.width {
                let mut acc = [0.0f64; 3];
                for a in 0..n {
                    for b in 0..n {
                        let x = i as f64 * dx - p.sample_mm / 2.0 + (a as f64 + 0.5) * dx / n as f64;
                        let y = p.sample_mm / 2.0 - j as f64 * dy - (b as f64 + 0.5) * dy / n as f64;
                        let c = f(x, y);
                        for k in 0..3 {
                            acc[k] += c[k] as f64 / (n * n) as f64;
                        }
                    }
                }
                img.set(i, j, [acc[0] as f32, acc[1] as f32, acc[2] as f32]);
            }
        }
        img
    }

    fn rmse(a: &RgbImage, b: &RgbImage) -> f64 {
        let s: f64 = a.data.iter().zip(&b.data).map(|(x, y)| ((x - y) as f64).powi(2)).sum();
        (s / a.data.len() as f64).sqrt()
    }

    fn params(w: usize, max_supersample: usize) -> RectifyParams {
        RectifyParams {
            width: w,
            height: w,
            sample_mm: SAMPLE_MM,
            max_supersample,
        }
    }

    #[test]
    fn texel_grid_follows_the_convention() {
        let p = RectifyParams {
            width: 4,
            height: 2,
            sample_mm: 8.0,
            max_supersample: 4,
        };
        assert_eq!(p.texel_centre(0, 0), (-3.0, 2.0));
        assert_eq!(p.texel_centre(3, 1), (3.0, -2.0));
        // A dark dot at (+20, +20) mm lands top-right in the rectified image.
        let intr = rig_intrinsics();
        let pose0 = pose(30.0, 120.0);
        let dot = |x: f64, y: f64| {
            if (x - 20.0).hypot(y - 20.0) < 2.0 {
                [0.0; 3]
            } else {
                [1.0; 3]
            }
        };
        let img = render(&intr, &pose0, &dot, 0.0, 0.0, 0);
        let out = warp(&img, &crate::Homography::from_pose(&intr, &pose0), &params(60, 8));
        let (mut sw, mut si, mut sj) = (0.0, 0.0, 0.0);
        for j in 0..60 {
            for i in 0..60 {
                let w = 1.0 - out.get(i, j)[0] as f64;
                sw += w;
                si += w * (i as f64 + 0.5);
                sj += w * (j as f64 + 0.5);
            }
        }
        // x = +20 → column (20 + 30)/60·60 = 50; y = +20 → row (30 − 20)/60·60 = 10.
        assert!(
            (si / sw - 50.0).abs() < 0.05 && (sj / sw - 10.0).abs() < 0.05,
            "{} {}",
            si / sw,
            sj / sw
        );
    }

    #[test]
    fn supersampling_counts_follow_the_footprint() {
        let intr = rig_intrinsics();
        let p = RectifyParams {
            width: 256,
            height: 256,
            sample_mm: 60.0,
            max_supersample: 8,
        };
        // Frontal: 60 mm = 300 px over 256 texels → 1.17 px per texel → 2 × 2.
        let front = crate::Homography::from_pose(&intr, &pose(0.0, 0.0));
        assert_eq!(texel_samples(&front, &p, 0.0, 0.0), (2, 2));
        // θ = 75° at φ = 0: x is foreshortened to 0.3 px per texel (magnified, bilinear),
        // y still spans 1.17 px.
        let graze = crate::Homography::from_pose(&intr, &pose(75.0, 0.0));
        assert_eq!(texel_samples(&graze, &p, 0.0, 0.0), (1, 2));
        // 16 × 16 output: 18.75 px per texel, clamped to 8.
        let coarse = RectifyParams {
            width: 16,
            height: 16,
            ..p.clone()
        };
        assert_eq!(texel_samples(&front, &coarse, 0.0, 0.0), (8, 8));
        // Frontal at 300 × 300 texels: exactly one pixel per texel (to rounding) → 1 × 1.
        let exact = RectifyParams {
            width: 300,
            height: 300,
            ..p
        };
        assert_eq!(texel_samples(&front, &exact, 0.1, 0.1), (1, 1));
    }

    fn round_trip(theta: f64, phi: f64) -> (f64, f64) {
        let intr = rig_intrinsics();
        let pose0 = pose(theta, phi);
        let img = render(&intr, &pose0, &smooth, 0.0, 0.0, 0);
        let p = params(256, 8);
        let out = warp(&img, &crate::Homography::from_pose(&intr, &pose0), &p);
        let truth = box_truth(&smooth, &p, 4);
        let mean: f64 = truth.data.iter().map(|&v| v as f64).sum::<f64>() / truth.data.len() as f64;
        let spread =
            (truth.data.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / truth.data.len() as f64).sqrt();
        (rmse(&out, &truth), spread)
    }

    #[test]
    fn warp_returns_the_texture_frontal_and_at_75_degrees() {
        for (theta, phi, bound) in [(0.0, 0.0, 0.005), (75.0, 0.0, 0.01), (75.0, 345.0, 0.01)] {
            let (e, spread) = round_trip(theta, phi);
            eprintln!("warp round trip θ={theta} φ={phi}: RMSE {e:.5} (texture std {spread:.3})");
            assert!(e < bound, "θ={theta} φ={phi}: RMSE {e}");
        }
    }

    /// RMSE of the rectified checker against its box-filtered truth, at a given
    /// `max_supersample`.
    fn checker_error(theta: f64, phi: f64, out_size: usize, max_supersample: usize) -> f64 {
        let intr = rig_intrinsics();
        let pose0 = pose(theta, phi);
        // 0.53 mm cells: 2.65 camera pixels per cell frontally, 1.3 at θ = 60° (a period
        // above two pixels, so the frame itself still resolves the checker), 3.54 cells
        // per 1.875 mm texel of a 32² output (non-integer, so point samples drift through
        // the checker's phase as aliasing does).
        let tex = checker(0.53);
        let img = render(&intr, &pose0, &tex, 0.0, 0.0, 0);
        let p = params(out_size, max_supersample);
        let out = warp(&img, &crate::Homography::from_pose(&intr, &pose0), &p);
        rmse(&out, &box_truth(&tex, &p, 32))
    }

    #[test]
    fn minified_checker_does_not_alias() {
        for (theta, phi) in [(0.0, 0.0), (45.0, 30.0), (60.0, 0.0)] {
            let filtered = checker_error(theta, phi, 32, 16);
            let point_sampled = checker_error(theta, phi, 32, 1);
            eprintln!(
                "checker 0.53 mm → 32² texels, θ={theta} φ={phi}: RMSE vs box truth {filtered:.4} \
                 (point-sampled bilinear: {point_sampled:.4})"
            );
            assert!(filtered < 0.02, "θ={theta}: {filtered}");
            assert!(
                point_sampled > 0.1,
                "the test must be able to see aliasing: {point_sampled}"
            );
        }
    }

    #[test]
    fn texels_the_camera_did_not_see_are_black() {
        // Camera moved 66.8 mm along the sample's +y (its image right), so the frame's
        // left edge u = 0 falls on y = 66.8 − 384/5 = −10 mm.
        let intr = rig_intrinsics();
        let moved = perturb(&pose(0.0, 0.0), 0.0, 0.0, 0.0, gonio_devices::Vec3::new(0.0, 66.8, 0.0));
        let img = render(&intr, &moved, &smooth, 0.0, 0.0, 0);
        let p = params(60, 8);
        let out = warp(&img, &crate::Homography::from_pose(&intr, &moved), &p);
        let truth = box_truth(&smooth, &p, 4);
        let (mut black, mut seen) = (0, 0);
        for j in 0..60 {
            let y = p.texel_centre(0, j).1;
            for i in 0..60 {
                let (a, b) = (out.get(i, j), truth.get(i, j));
                if y < -11.0 {
                    assert_eq!(a, [0.0; 3], "({i}, {j})");
                    black += 1;
                } else if y > -9.0 {
                    assert!((a[0] - b[0]).abs() < 0.01, "({i}, {j}): {a:?} vs {b:?}");
                    seen += 1;
                }
            }
        }
        assert!(black > 1000 && seen > 1000, "{black} {seen}");
    }

    #[test]
    fn warp_is_fast() {
        let intr = rig_intrinsics();
        let pose0 = pose(0.0, 0.0);
        let img = render(&intr, &pose0, &smooth, 0.0, 0.0, 0);
        let h = crate::Homography::from_pose(&intr, &pose0);
        let p = params(256, 8);
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let mut best = f64::INFINITY;
        for _ in 0..5 {
            let t = Instant::now();
            let out = pool.install(|| warp(&img, &h, &p));
            best = best.min(t.elapsed().as_secs_f64());
            assert_eq!(out.data.len(), 256 * 256 * 3);
        }
        eprintln!("warp 768×640 → 256×256 frontal, one thread: {:.2} ms", best * 1e3);
        // Generous (test builds are unoptimized and the machine is shared): this only
        // catches gross regressions; release timing is measured separately.
        assert!(best < 0.25, "{best} s");
    }
}
