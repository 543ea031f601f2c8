//! Sub-pixel X-corner location by fitting a model of the corner to the raw pixels.
//!
//! Why not only the gradient-orthogonality estimate (`cornerSubPix`)? Its answer depends on
//! where the corner sits within a pixel and on how perspective foreshortens the squares
//! around it: on rendered boards it scatters by 0.02–0.07 px. That is harmless for a wide
//! lens, but a telephoto camera (±5° field) sees so little perspective that the principal
//! point is amplified from these hundredths of a pixel into tens of pixels. A model fit
//! uses every pixel's value, not only its gradient direction.
//!
//! The model of the pixel whose square is `P` (unit area, centre `c`), with `d = c − q`:
//!
//! ```text
//! M(P) = (a + b · B₁(n₁·d) · B₂(n₂·d)) · (1 + g·d)
//! B(u) = mean over the pixel square of erf((u + n·t) / (√2 s)),  t ∈ P − c
//! ```
//!
//! two straight edges through the corner `q` with unit normals `n₁, n₂` (any angle between
//! them: perspective makes them non-orthogonal), each an `erf` step blurred by the optics'
//! `s` and **integrated over the pixel's area in closed form**, the mean level `a` and
//! half-contrast `b`, and a linear illumination gradient `g` (a point lamp lights one side of
//! a square more than the other). Why the area integral: a sensor pixel averages the light
//! over its square, and a sharp edge's pixel values are then a ramp whose exact shape
//! depends on where the edge crosses the pixel; a model sampled at pixel centres cannot
//! follow that and errs by a few hundredths of a pixel, periodically in the sub-pixel phase.
//! The square's projection onto the normal is a trapezoid (a box of width |n_x| convolved
//! with one of width |n_y|), so `B` is a second difference of erf's second antiderivative.
//!
//! Near the junction the product of the two edge profiles is not the exact image of a blurred
//! corner, but both are point-symmetric about `q`, so the mismatch does not move the fitted
//! `q` to first order; far from the junction, along the edges, the model is exact. Residuals
//! are weighted by `(1 − r²/R²)²` around the current estimate (re-centred until it stays):
//! a hard window edge would cut the edge lines unevenly on the two sides of the corner.
//! Levenberg-Marquardt over nine parameters and the ~50–200 pixels of the window.

use nalgebra::{SMatrix, SVector};

type Mat9 = SMatrix<f64, 9, 9>;
type Vec9 = SVector<f64, 9>;

/// A fitted corner.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CornerFit {
    /// Corner position (pixel coordinates, centres at half-integers).
    pub q: [f64; 2],
    /// Fitted optical blur σ (pixels), beyond the pixel's own area.
    pub blur_px: f64,
    /// RMS of the weighted residuals over the contrast (|dark − bright|): ≈ noise/contrast
    /// for a clean corner, much more when something else (an occluder's rim, a mark)
    /// lies in the window.
    pub relative_residual: f64,
}

const SQRT_PI: f64 = 1.772_453_850_905_516;

/// erf's first antiderivative `∫ erf = z erf z + e^{−z²}/√π`.
#[inline]
fn erf_int1(z: f64) -> f64 {
    z * libm::erf(z) + (-z * z).exp() / SQRT_PI
}

/// erf's second antiderivative `(z²/2 + 1/4) erf z + z e^{−z²} / (2√π)`.
#[inline]
fn erf_int2(z: f64) -> f64 {
    (0.5 * z * z + 0.25) * libm::erf(z) + z * (-z * z).exp() / (2.0 * SQRT_PI)
}

/// Radius (pixels) of the junction core that the weights fade out: within about a pixel of
/// the corner the product of two edge profiles differs most from the image of a sharp
/// corner (most for skewed corners); the edges around it determine `q` as well.
const JUNCTION_CORE_PX: f64 = 1.0;

/// Smallest blur the model uses (pixels): below it the pixel's own area dominates anyway,
/// and the closed form's scaling by `1/s` stays well conditioned.
const MIN_BLUR: f64 = 0.02;

/// One pixel-integrated edge: `B(u)` and `dB/du` for unit normal `n` and blur `s`.
#[inline]
fn edge(u: f64, n: [f64; 2], s: f64) -> (f64, f64) {
    let k = std::f64::consts::SQRT_2 * s; // erf((u + t)/k)
    let (w1, w2) = (n[0].abs().max(n[1].abs()), n[0].abs().min(n[1].abs()));
    if w2 < 1e-3 {
        // One box of width w1: (k/w1) [I1((u + w1/2)/k) − I1((u − w1/2)/k)].
        let (zp, zm) = ((u + 0.5 * w1) / k, (u - 0.5 * w1) / k);
        let v = k / w1 * (erf_int1(zp) - erf_int1(zm));
        let dv = (libm::erf(zp) - libm::erf(zm)) / w1;
        return (v, dv);
    }
    // Trapezoid: (k²/(w1 w2)) Σ ± I2((u ± w1/2 ± w2/2)/k); the derivative uses I1.
    let (a, b) = (0.5 * (w1 + w2), 0.5 * (w1 - w2));
    let z = [(u + a) / k, (u + b) / k, (u - b) / k, (u - a) / k];
    let v = k * k / (w1 * w2) * (erf_int2(z[0]) - erf_int2(z[1]) - erf_int2(z[2]) + erf_int2(z[3]));
    let dv = k / (w1 * w2) * (erf_int1(z[0]) - erf_int1(z[1]) - erf_int1(z[2]) + erf_int1(z[3]));
    (v, dv)
}

/// Nodes and weights of 10-point Gauss-Legendre quadrature on [−1, 1] (positive half).
const GL_X: [f64; 5] = [
    0.148_874_338_981_631_2,
    0.433_395_394_129_247_2,
    0.679_409_568_299_024_4,
    0.865_063_366_688_984_5,
    0.973_906_528_517_171_7,
];
const GL_W: [f64; 5] = [
    0.295_524_224_714_752_9,
    0.269_266_719_309_996_3,
    0.219_086_362_515_982,
    0.149_451_349_150_580_6,
    0.066_671_344_308_688_1,
];

/// The corner surface `S ∈ [−1, 1]` at offset `d` from the corner, with its derivatives by
/// the two signed edge distances `u₁ = n₁·d`, `u₂ = n₂·d`.
///
/// `S = B₁(u₁) B₂(u₂) + C`: the product of the pixel-integrated edges, exact away from the
/// junction, plus the junction term `C` that turns the product into the blurred image of a
/// sharp corner with non-orthogonal edges. For Gaussian blur `σ`, `E[sign U₁ · sign U₂]` of
/// the bivariate normal `(U₁, U₂)` (means `u₁, u₂`, correlation `ρ = n₁·n₂`) is
/// `erf(a/√2) erf(b/√2) + (2/π) ∫₀^{asin ρ} exp(−(a² − 2ab sin θ + b²) / (2 cos² θ)) dθ`
/// with `a = u₁/σ, b = u₂/σ` (Drezner and Wesolowsky's form of the orthant probability);
/// the integral is `C`, 0 for orthogonal edges. It is evaluated with the pixel's area as
/// extra Gaussian variance (1/12 along any direction): `C` only matters within a pixel or
/// two of the junction, where that approximation's error is second order.
/// The quadrature nodes of the junction term for one pair of normals: `sin θ`, `1/cos² θ`
/// and the weight at each node, and the term's scale `(2/π) · asin(ρ)/2` (0 = orthogonal
/// edges, no term). Computed once per parameter vector, not per pixel.
#[derive(Clone, Copy)]
struct Junction {
    rho: f64,
    st: [f64; 10],
    ic2: [f64; 10],
    w: [f64; 10],
    scale: f64,
}

impl Junction {
    fn new(n1: [f64; 2], n2: [f64; 2]) -> Junction {
        let rho = (n1[0] * n2[0] + n1[1] * n2[1]).clamp(-0.995, 0.995);
        let half = 0.5 * rho.asin();
        let (mut st, mut ic2, mut w) = ([0.0; 10], [0.0; 10], [0.0; 10]);
        for k in 0..5 {
            for (m, sign) in [(0, -1.0), (1, 1.0)] {
                let t = half * (1.0 + sign * GL_X[k]);
                st[2 * k + m] = t.sin();
                ic2[2 * k + m] = 1.0 / t.cos().powi(2);
                w[2 * k + m] = GL_W[k];
            }
        }
        Junction {
            rho,
            st,
            ic2,
            w,
            scale: if rho.abs() > 1e-9 {
                2.0 / std::f64::consts::PI * half
            } else {
                0.0
            },
        }
    }
}

#[inline]
fn corner_surface(d: [f64; 2], n1: [f64; 2], n2: [f64; 2], s: f64, jn: &Junction) -> (f64, f64, f64) {
    let u1 = n1[0] * d[0] + n1[1] * d[1];
    let u2 = n2[0] * d[0] + n2[1] * d[1];
    let ((e1, de1), (e2, de2)) = (edge(u1, n1, s), edge(u2, n2, s));
    let (mut v, mut d1, mut d2) = (e1 * e2, de1 * e2, e1 * de2);
    let se = (s * s + 1.0 / 12.0).sqrt();
    let (a, b) = (u1 / se, u2 / se);
    // The integrand is at most exp(−(a² + b²)(1 − |ρ|) / 2): beyond e⁻⁴⁰ the term is zero
    // in double precision, which is every pixel more than a few blur widths from the corner.
    if jn.scale != 0.0 && (a * a + b * b) * (1.0 - jn.rho.abs()) < 80.0 {
        let (mut c, mut ca, mut cb) = (0.0, 0.0, 0.0);
        for k in 0..10 {
            let (st, ic2) = (jn.st[k], jn.ic2[k]);
            let ex = jn.w[k] * (-(a * a - 2.0 * a * b * st + b * b) * 0.5 * ic2).exp();
            c += ex;
            ca -= ex * (a - b * st) * ic2;
            cb -= ex * (b - a * st) * ic2;
        }
        v += jn.scale * c;
        d1 += jn.scale * ca / se;
        d2 += jn.scale * cb / se;
    }
    (v, d1, d2)
}

/// Fit the corner model to `pixel(x, y)` (the raw value of pixel (x, y), whose square is
/// `[x, x+1) × [y, y+1)`) of a `w × h` image, starting at `start` with edge direction angles
/// `dirs` (radians: the image directions of the two board axes through the corner), weights
/// out to `radius` pixels. `None` when the window leaves the image, the window has too
/// little contrast, the fit does not converge, or it ends more than `radius / 2` from the
/// start (that is another feature, not this corner). Pixels at or above `saturation` are
/// fitted with the model clipped at that level (a clipped bright square would otherwise
/// shift every edge toward it).
pub fn fit_corner(
    pixel: &dyn Fn(usize, usize) -> f64,
    (w, h): (usize, usize),
    start: [f64; 2],
    dirs: [f64; 2],
    radius: f64,
    saturation: f64,
) -> Option<CornerFit> {
    // Every pixel the window can reach while its centre stays within radius / 2 of the start.
    let reach = (1.5 * radius).ceil() as isize + 1;
    let (ci, cj) = ((start[0] - 0.5).round() as isize, (start[1] - 0.5).round() as isize);
    if ci - reach < 0 || cj - reach < 0 || ci + reach >= w as isize || cj + reach >= h as isize {
        return None;
    }
    let mut px: Vec<([f64; 2], f64)> = Vec::new();
    for y in cj - reach..=cj + reach {
        for x in ci - reach..=ci + reach {
            px.push(([x as f64 + 0.5, y as f64 + 0.5], pixel(x as usize, y as usize)));
        }
    }
    let near: Vec<f64> = px
        .iter()
        .filter(|(c, _)| (c[0] - start[0]).hypot(c[1] - start[1]) <= radius)
        .map(|p| p.1)
        .collect();
    if near.len() < 20 {
        return None;
    }
    let (lo, hi) = near
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
    if hi.partial_cmp(&lo) != Some(std::cmp::Ordering::Greater) || !(hi - lo).is_finite() {
        return None;
    }
    // Parameters: qx, qy, α₁, α₂ (normal angles), ln s, a, b, gx, gy. The sign of b (which
    // pair of quadrants is bright) is read off the image: the model's product is positive
    // in the quadrant both normals point into.
    let n_of = |alpha: f64| [alpha.cos(), alpha.sin()];
    let alpha0 = [
        dirs[0] + std::f64::consts::FRAC_PI_2,
        dirs[1] + std::f64::consts::FRAC_PI_2,
    ];
    let probe = {
        let (n1, n2) = (n_of(alpha0[0]), n_of(alpha0[1]));
        let d = [n1[0] + n2[0], n1[1] + n2[1]];
        let len = d[0].hypot(d[1]).max(1e-9);
        let r = 0.5 * radius;
        let p = [start[0] + r * d[0] / len, start[1] + r * d[1] / len];
        let (x, y) = ((p[0] - 0.5).round() as usize, (p[1] - 0.5).round() as usize);
        pixel(x.min(w - 1), y.min(h - 1))
    };
    let mid = 0.5 * (lo + hi);
    let b0 = if probe >= mid {
        0.5 * (hi - lo)
    } else {
        -0.5 * (hi - lo)
    };
    let mut p = Vec9::from_column_slice(&[start[0], start[1], alpha0[0], alpha0[1], 0.5f64.ln(), mid, b0, 0.0, 0.0]);

    // Weighted residuals √w (v − M). With `jac`, also the rows √w ∂M/∂p: analytic for the
    // position, levels and gradient; by central differences for the angles and the blur,
    // which enter the pixel-area integral through the trapezoid's widths too.
    let r2max = radius * radius;
    let eval = |p: &Vec9, centre: [f64; 2], jac: Option<&mut Vec<Vec9>>| -> (f64, Vec<f64>, usize) {
        let (q, s) = ([p[0], p[1]], p[4].exp().max(MIN_BLUR));
        let (n1, n2) = (n_of(p[2]), n_of(p[3]));
        let mut r = Vec::with_capacity(px.len());
        let (mut sum, mut used) = (0.0, 0usize);
        let mut jrows = jac;
        let want_jac = jrows.is_some();
        if let Some(j) = jrows.as_deref_mut() {
            j.clear();
        }
        // numeric derivative steps for α₁, α₂, ln s
        const H: f64 = 1e-6;
        let jn = Junction::new(n1, n2);
        let (jd1p, jd1m, jd2p, jd2m) = if want_jac {
            (
                Junction::new(n_of(p[2] + H), n2),
                Junction::new(n_of(p[2] - H), n2),
                Junction::new(n1, n_of(p[3] + H)),
                Junction::new(n1, n_of(p[3] - H)),
            )
        } else {
            (jn, jn, jn, jn)
        };
        for &(c, v) in &px {
            let rc2 = (c[0] - centre[0]).powi(2) + (c[1] - centre[1]).powi(2);
            if rc2 >= r2max {
                continue;
            }
            let d = [c[0] - q[0], c[1] - q[1]];
            let core = 1.0 - (-rc2 / (2.0 * JUNCTION_CORE_PX * JUNCTION_CORE_PX)).exp();
            used += 1;
            let sw = (1.0 - rc2 / r2max) * core; // √ of the weight
            let (s12, ds1, ds2) = corner_surface(d, n1, n2, s, &jn);
            let lin = 1.0 + p[7] * d[0] + p[8] * d[1];
            let base = p[5] + p[6] * s12;
            // The sensor clips: a pixel that reads the saturation level and that the model
            // puts above it agrees with the model and carries no information on where the
            // edge is. (Only pixels that read the level: a model above the level at a pixel
            // below it is simply wrong, and must keep its gradient.)
            let clipped = v >= saturation && base * lin >= saturation;
            let res = if clipped { 0.0 } else { sw * (v - base * lin) };
            sum += res * res;
            r.push(res);
            if clipped {
                if let Some(j) = jrows.as_deref_mut() {
                    j.push(Vec9::zeros());
                }
            } else if want_jac {
                let bl = p[6] * lin;
                let ds_dq = [-(ds1 * n1[0] + ds2 * n2[0]), -(ds1 * n1[1] + ds2 * n2[1])];
                let surf = |a1: f64, a2: f64, s: f64, jn: &Junction| corner_surface(d, n_of(a1), n_of(a2), s, jn).0;
                let ds_da1 = (surf(p[2] + H, p[3], s, &jd1p) - surf(p[2] - H, p[3], s, &jd1m)) / (2.0 * H);
                let ds_da2 = (surf(p[2], p[3] + H, s, &jd2p) - surf(p[2], p[3] - H, s, &jd2m)) / (2.0 * H);
                let (sp, sm) = ((p[4] + H).exp().max(MIN_BLUR), (p[4] - H).exp().max(MIN_BLUR));
                let ds_dls = (surf(p[2], p[3], sp, &jn) - surf(p[2], p[3], sm, &jn)) / (2.0 * H);
                if let Some(j) = jrows.as_deref_mut() {
                    j.push(
                        Vec9::from_column_slice(&[
                            bl * ds_dq[0] - base * p[7],
                            bl * ds_dq[1] - base * p[8],
                            bl * ds_da1,
                            bl * ds_da2,
                            bl * ds_dls,
                            lin,
                            s12 * lin,
                            base * d[0],
                            base * d[1],
                        ]) * sw,
                    );
                }
            }
        }
        (sum, r, used)
    };

    let mut jrows = Vec::with_capacity(px.len());
    let mut centre = start;
    let mut used = 0;
    let mut final_cost = f64::NAN;
    // Outer loop: re-centre the weights on the estimate until it stays put.
    for _ in 0..6 {
        let (mut cost, mut r, u) = eval(&p, centre, Some(&mut jrows));
        used = u;
        let mut lambda = 1e-3;
        for _ in 0..60 {
            let mut jtj = Mat9::zeros();
            let mut jtr = Vec9::zeros();
            for (row, &res) in jrows.iter().zip(&r) {
                jtj += row * row.transpose();
                jtr += row * res;
            }
            let mut step_taken = None;
            for _ in 0..12 {
                let mut a = jtj;
                for k in 0..9 {
                    a[(k, k)] += lambda * jtj[(k, k)].max(1e-12);
                }
                let Some(step) = a.cholesky().map(|c| c.solve(&jtr)) else {
                    lambda *= 10.0;
                    continue;
                };
                let trial = p + step;
                let (c2, _, _) = eval(&trial, centre, None);
                if c2.is_finite() && c2 <= cost {
                    p = trial;
                    lambda = (lambda * 0.3).max(1e-12);
                    step_taken = Some(step);
                    break;
                }
                lambda *= 10.0;
            }
            let Some(step) = step_taken else { break };
            let (c3, r3, _) = eval(&p, centre, Some(&mut jrows));
            let rel = (cost - c3) / cost.max(1e-300);
            (cost, r) = (c3, r3);
            if step[0].abs().max(step[1].abs()) < 1e-6 && rel < 1e-8 {
                break;
            }
        }
        if !p.iter().all(|v| v.is_finite()) || (p[0] - start[0]).hypot(p[1] - start[1]) > 0.5 * radius {
            return None;
        }
        final_cost = cost;
        let moved = (p[0] - centre[0]).hypot(p[1] - centre[1]);
        centre = [p[0], p[1]];
        if moved < 1e-4 {
            break;
        }
    }
    let s = p[4].exp().max(MIN_BLUR);
    if s > radius || used < 20 || p[6].abs() < 1e-12 {
        return None;
    }
    Some(CornerFit {
        q: [p[0], p[1]],
        blur_px: s,
        relative_residual: (final_cost / used as f64).sqrt() / (2.0 * p[6].abs()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Separable Gaussian blur (σ in pixels), edges clamped: a lens that does not focus
    /// to a point.
    fn blur(img: &[f64], n: usize, sigma: f64) -> Vec<f64> {
        let r = (4.0 * sigma).ceil() as isize;
        let k: Vec<f64> = (-r..=r)
            .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp())
            .collect();
        let ks: f64 = k.iter().sum();
        let pass = |src: &[f64], horizontal: bool| -> Vec<f64> {
            let mut out = vec![0.0; n * n];
            for y in 0..n as isize {
                for x in 0..n as isize {
                    let mut acc = 0.0;
                    for (t, kv) in k.iter().enumerate() {
                        let o = t as isize - r;
                        let (xx, yy) = if horizontal { (x + o, y) } else { (x, y + o) };
                        let (xx, yy) = (xx.clamp(0, n as isize - 1), yy.clamp(0, n as isize - 1));
                        acc += kv * src[(yy * n as isize + xx) as usize];
                    }
                    out[(y * n as isize + x) as usize] = acc / ks;
                }
            }
            out
        };
        pass(&pass(img, true), false)
    }

    /// [`corner_image`] seen through a lens with Gaussian blur `sigma` (pixels): the exact
    /// image at 8× resolution, blurred there (where the Gaussian is sampled finely enough to
    /// act as the continuous one), then each pixel the mean of its 8 × 8 sub-pixels. (Blurring
    /// the pixel image itself would blur its aliasing too, and the test would measure that.)
    fn blurred_corner_image(n: usize, q: [f64; 2], a1: f64, a2: f64, sigma: f64) -> Vec<f64> {
        const M: usize = 8;
        let fine = blur(
            &corner_image(n * M, [q[0] * M as f64, q[1] * M as f64], a1, a2),
            n * M,
            sigma * M as f64,
        );
        let mut out = vec![0.0; n * n];
        for y in 0..n * M {
            for x in 0..n * M {
                out[(y / M) * n + x / M] += fine[y * n * M + x] / (M * M) as f64;
            }
        }
        out
    }

    /// The part of polygon `poly` where `n·(x − q) ≥ 0` (Sutherland–Hodgman, one plane).
    fn clip(poly: &[[f64; 2]], n: [f64; 2], q: [f64; 2]) -> Vec<[f64; 2]> {
        let side = |p: [f64; 2]| n[0] * (p[0] - q[0]) + n[1] * (p[1] - q[1]);
        let mut out = Vec::new();
        for k in 0..poly.len() {
            let (a, b) = (poly[k], poly[(k + 1) % poly.len()]);
            let (sa, sb) = (side(a), side(b));
            if sa >= 0.0 {
                out.push(a);
            }
            if (sa >= 0.0) != (sb >= 0.0) {
                let t = sa / (sa - sb);
                out.push([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])]);
            }
        }
        out
    }

    fn area(poly: &[[f64; 2]]) -> f64 {
        let mut s = 0.0;
        for k in 0..poly.len() {
            let (a, b) = (poly[k], poly[(k + 1) % poly.len()]);
            s += a[0] * b[1] - a[1] * b[0];
        }
        0.5 * s.abs()
    }

    /// An X-corner with edges at angles `a1`, `a2` through `q`, levels 0.1 / 0.9, each
    /// pixel the exact area average over its square (polygon clipping): what an ideal
    /// sensor without optical blur records, with no sampling error of its own.
    fn corner_image(n: usize, q: [f64; 2], a1: f64, a2: f64) -> Vec<f64> {
        let (n1, n2) = ([-a1.sin(), a1.cos()], [-a2.sin(), a2.cos()]);
        let neg = |v: [f64; 2]| [-v[0], -v[1]];
        let mut img = vec![0.0; n * n];
        for y in 0..n {
            for x in 0..n {
                let (x0, y0) = (x as f64, y as f64);
                let sq = [[x0, y0], [x0 + 1.0, y0], [x0 + 1.0, y0 + 1.0], [x0, y0 + 1.0]];
                let bright = area(&clip(&clip(&sq, n1, q), n2, q)) + area(&clip(&clip(&sq, neg(n1), q), neg(n2), q));
                img[y * n + x] = 0.1 + 0.8 * bright;
            }
        }
        img
    }

    #[test]
    fn sharp_and_skewed_corners_are_located_to_a_thousandth_of_a_pixel() {
        let n = 30;
        let mut worst: f64 = 0.0;
        for (k, &(a1, a2)) in [(0.0, 90.0), (10.0, 95.0), (-20.0, 45.0), (30.0, 150.0)]
            .iter()
            .enumerate()
        {
            for phase in 0..5 {
                let q = [15.0 + 0.17 * phase as f64 + 0.03 * k as f64, 14.6 + 0.23 * phase as f64];
                let (a1, a2) = (f64::to_radians(a1), f64::to_radians(a2));
                let img = corner_image(n, q, a1, a2);
                let at = |x: usize, y: usize| img[y * n + x];
                let start = [q[0] + 0.3, q[1] - 0.25];
                let fit = fit_corner(&at, (n, n), start, [a1 + 0.05, a2 - 0.04], 6.0, f64::INFINITY).expect("fit");
                let e = (fit.q[0] - q[0]).hypot(fit.q[1] - q[1]);
                worst = worst.max(e);
            }
        }
        println!("sharp corners: worst error {worst:.5} px");
        assert!(worst < 2e-3, "worst {worst} px");
    }

    #[test]
    fn an_illumination_gradient_does_not_pull_the_corner() {
        let n = 24;
        let q = [12.3, 11.8];
        let img = corner_image(n, q, 0.2, 1.9);
        // 4 % brighter per 10 px to the right and down
        let lit: Vec<f64> = (0..n * n)
            .map(|k| img[k] * (1.0 + 0.004 * ((k % n) as f64 - q[0]) + 0.002 * ((k / n) as f64 - q[1])))
            .collect();
        let at = |x: usize, y: usize| lit[y * n + x];
        let fit = fit_corner(&at, (n, n), [12.0, 12.0], [0.2, 1.9], 6.0, f64::INFINITY).expect("fit");
        let e = (fit.q[0] - q[0]).hypot(fit.q[1] - q[1]);
        assert!(e < 2e-3, "error {e} px");
    }

    #[test]
    fn a_blurred_corner_is_located_and_its_blur_measured() {
        let n = 30;
        let mut worst: f64 = 0.0;
        for (k, &(a1, a2)) in [(5.0f64, 92.0f64), (-20.0, 45.0)].iter().enumerate() {
            let q = [15.21 + 0.1 * k as f64, 14.67];
            let (a1, a2) = (a1.to_radians(), a2.to_radians());
            let img = blurred_corner_image(n, q, a1, a2, 1.0);
            let at = |x: usize, y: usize| img[y * n + x];
            let fit = fit_corner(&at, (n, n), [q[0] - 0.3, q[1] + 0.2], [a1, a2], 7.0, f64::INFINITY).expect("fit");
            println!(
                "case {k}: {:+.5} {:+.5} blur {:.4}",
                fit.q[0] - q[0],
                fit.q[1] - q[1],
                fit.blur_px
            );
            worst = worst.max((fit.q[0] - q[0]).hypot(fit.q[1] - q[1]));
            assert!((fit.blur_px - 1.0).abs() < 0.1, "blur {}", fit.blur_px);
        }
        println!("blurred corners: worst error {worst:.5} px");
        assert!(worst < 3e-3, "worst {worst} px");
    }

    #[test]
    fn saturated_bright_squares_do_not_pull_the_corner() {
        let n = 30;
        let q = [15.37, 14.81];
        let (a1, a2) = (0.3f64, 1.75f64);
        // 0.1 / 0.9 levels scaled so the bright squares read 1.4 before the sensor clips at 1
        let img: Vec<f64> = corner_image(n, q, a1, a2).iter().map(|v| (v * 1.6).min(1.0)).collect();
        let at = |x: usize, y: usize| img[y * n + x];
        let fit = fit_corner(&at, (n, n), [15.0, 15.0], [a1, a2], 6.0, 1.0).expect("fit");
        let e = (fit.q[0] - q[0]).hypot(fit.q[1] - q[1]);
        println!("clipped corner: error {e:.5} px");
        assert!(e < 3e-3, "error {e} px");
    }

    #[test]
    fn windows_without_a_corner_are_refused() {
        let n = 30;
        // a flat window: no contrast
        let flat = vec![0.5; n * n];
        let at = |x: usize, y: usize| flat[y * n + x];
        assert!(fit_corner(&at, (n, n), [15.0, 15.0], [0.0, 1.5], 6.0, f64::INFINITY).is_none());
        // a window partly outside the image
        let img = corner_image(n, [3.2, 15.0], 0.0, 1.5);
        let at = |x: usize, y: usize| img[y * n + x];
        assert!(fit_corner(&at, (n, n), [3.2, 15.0], [0.0, 1.5], 6.0, f64::INFINITY).is_none());
    }
}
