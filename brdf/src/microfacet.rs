//! Microfacet normal distributions (Beckmann, GGX/Trowbridge-Reitz; isotropic and
//! anisotropic) and Smith masking-shadowing (separable or height-correlated), after Walter
//! et al. 2007 and Heitz 2014. Everything is in the local frame (normal +z, tangent +x);
//! `alpha_u` is the roughness along +x, `alpha_v` along +y.
//!
//! Normalization: `∫ D(h) (n·h) dω_h = 1` over the hemisphere (projected microfacet area
//! equals the macro-surface area). For Beckmann `alpha = √2 · σ_slope`, i.e. it is the `m`
//! (RMS slope) of Cook-Torrance.

use gonio_devices::Vec3;
use serde::{Deserialize, Serialize};

use super::math::{erfc_fast, INV_SQRT_PI};
use std::f64::consts::PI;

/// The microfacet normal distribution.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Distribution {
    /// `D = exp(−(h_x²/α_u² + h_y²/α_v²)/h_z²) / (π α_u α_v h_z⁴)`.
    Beckmann,
    /// `D = 1 / (π α_u α_v (h_x²/α_u² + h_y²/α_v² + h_z²)²)`.
    Ggx,
}

/// How the Smith masking `G1` of light and view are combined into `G2`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Masking {
    /// `G2 = G1(l) G1(v)` (Walter 2007; Mitsuba 3).
    #[default]
    Separable,
    /// `G2 = 1 / (1 + Λ(l) + Λ(v))` (Heitz 2014; pbrt-v4).
    HeightCorrelated,
}

/// Normal distribution `D(h)` for a unit `h`; 0 for `h_z ≤ 0`.
#[inline]
pub fn d(dist: Distribution, h: Vec3, au: f64, av: f64) -> f64 {
    let hz = h.z;
    if hz <= 0.0 {
        return 0.0;
    }
    let hz2 = hz * hz;
    let sx = h.x / au;
    let sy = h.y / av;
    match dist {
        Distribution::Beckmann => {
            let t = (sx * sx + sy * sy) / hz2;
            if t > 740.0 {
                return 0.0;
            }
            (-t).exp() / (PI * au * av * hz2 * hz2)
        }
        Distribution::Ggx => {
            let q = sx * sx + sy * sy + hz2;
            1.0 / (PI * au * av * q * q)
        }
    }
}

/// Smith's auxiliary function `Λ(w)` (w unit, `w_z > 0`). No azimuth is needed: the
/// projected roughness enters as `α_u² w_x² + α_v² w_y²`, so θ = 0 is not special.
#[inline]
pub fn lambda(dist: Distribution, w: Vec3, au: f64, av: f64) -> f64 {
    let wz2 = w.z * w.z;
    let xy = (au * w.x).powi(2) + (av * w.y).powi(2);
    if xy <= 0.0 {
        return 0.0;
    }
    if wz2 <= 0.0 {
        return f64::INFINITY;
    }
    match dist {
        Distribution::Ggx => {
            // (−1 + √(1 + ε))/2 written without cancellation for small ε = α² tan²θ.
            let e = xy / wz2;
            e / (2.0 * (1.0 + (1.0 + e).sqrt()))
        }
        Distribution::Beckmann => {
            // a = cot θ / α; Λ = (erf(a) − 1)/2 + e^{−a²}/(2a√π), erfc to 1.2e-7 relative
            // (G1 to ~1e-7 absolute).
            let a = w.z.abs() / xy.sqrt();
            if a > 26.0 {
                return 0.0;
            }
            (0.5 * (INV_SQRT_PI * (-a * a).exp() / a - erfc_fast(a))).max(0.0)
        }
    }
}

/// Smith masking `G1(w, h) = χ⁺(w·h / w·n) / (1 + Λ(w))`.
#[inline]
pub fn g1(dist: Distribution, w: Vec3, h: Vec3, au: f64, av: f64) -> f64 {
    if w.dot(h) * w.z <= 0.0 {
        return 0.0;
    }
    1.0 / (1.0 + lambda(dist, w, au, av))
}

/// Masking-shadowing `G2(l, v, h)`.
#[inline]
pub fn g2(dist: Distribution, masking: Masking, l: Vec3, v: Vec3, h: Vec3, au: f64, av: f64) -> f64 {
    if l.dot(h) * l.z <= 0.0 || v.dot(h) * v.z <= 0.0 {
        return 0.0;
    }
    let ll = lambda(dist, l, au, av);
    let lv = lambda(dist, v, au, av);
    match masking {
        Masking::Separable => 1.0 / ((1.0 + ll) * (1.0 + lv)),
        Masking::HeightCorrelated => 1.0 / (1.0 + ll + lv),
    }
}

/// The single-scattering microfacet reflection `D G2 / (4 |n·l| |n·v|)` without Fresnel,
/// with its half vector; `None` when the half vector is undefined (`l + v ≈ 0`) or a
/// direction is below the horizon.
#[inline]
pub fn dg_over_4(dist: Distribution, masking: Masking, l: Vec3, v: Vec3, au: f64, av: f64) -> Option<(f64, Vec3)> {
    if l.z <= 0.0 || v.z <= 0.0 {
        return None;
    }
    let h = super::math::half_vector(l, v)?;
    let dd = d(dist, h, au, av);
    if dd == 0.0 {
        return Some((0.0, h));
    }
    let g = g2(dist, masking, l, v, h, au, av);
    let val = dd * g / (4.0 * l.z * v.z);
    Some((if val.is_finite() { val } else { 0.0 }, h))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::gauss_legendre;

    /// `∫ D(h)(n·h) dω_h` in slope space: `h = normalize(−α_u q_x, −α_v q_y, 1)`,
    /// `dω_h = cos³θ_h d²p`, `p = (α_u q_x, α_v q_y)`, so the integral is
    /// `∫ D(h(q)) cos⁴θ_h α_u α_v d²q`. Polar `q = r(cos φ, sin φ)` with `r = tan t`,
    /// t ∈ [0, π/2): smooth for both distributions at any roughness.
    fn projected_area_slope_space(dist: Distribution, au: f64, av: f64) -> f64 {
        let (xt, wt) = gauss_legendre(96);
        let nphi = 64;
        let mut sum = 0.0;
        for (xi, wi) in xt.iter().zip(&wt) {
            let t = (xi + 1.0) * 0.25 * PI; // [0, π/2]
            let dt = 0.25 * PI * wi;
            let r = t.tan();
            let dr = dt / (t.cos() * t.cos());
            for k in 0..nphi {
                let phi = (k as f64 + 0.5) * 2.0 * PI / nphi as f64;
                let (qx, qy) = (r * phi.cos(), r * phi.sin());
                let h = Vec3::new(-au * qx, -av * qy, 1.0).normalized();
                let c4 = h.z.powi(4);
                sum += d(dist, h, au, av) * c4 * au * av * r * dr * 2.0 * PI / nphi as f64;
            }
        }
        sum
    }

    /// The same integral directly over the hemisphere of h (θ_h by Gauss-Legendre): only
    /// accurate for moderate roughness, but independent of the slope-space mapping.
    fn projected_area_direct(dist: Distribution, au: f64, av: f64) -> f64 {
        let (x, w) = gauss_legendre(400);
        let nphi = 128;
        let mut sum = 0.0;
        for (xi, wi) in x.iter().zip(&w) {
            let th = (xi + 1.0) * 0.25 * PI;
            let dth = 0.25 * PI * wi;
            for k in 0..nphi {
                let phi = (k as f64 + 0.5) * 2.0 * PI / nphi as f64;
                let h = Vec3::new(th.sin() * phi.cos(), th.sin() * phi.sin(), th.cos());
                sum += d(dist, h, au, av) * h.z * th.sin() * dth * 2.0 * PI / nphi as f64;
            }
        }
        sum
    }

    #[test]
    fn ndf_projected_area_is_one_slope_space() {
        for dist in [Distribution::Beckmann, Distribution::Ggx] {
            for &(au, av) in &[
                (1e-4, 1e-4),
                (1e-3, 0.5),
                (0.05, 0.05),
                (0.3, 0.1),
                (1.0, 1.0),
                (0.7, 0.02),
            ] {
                let s = projected_area_slope_space(dist, au, av);
                assert!((s - 1.0).abs() < 1e-6, "{dist:?} au={au} av={av}: {s}");
            }
        }
    }

    #[test]
    fn ndf_projected_area_is_one_direct() {
        // GGX's long tail is cut only by the hemisphere; ∫ is exactly 1 for both.
        for dist in [Distribution::Beckmann, Distribution::Ggx] {
            for &(au, av) in &[(0.3, 0.3), (1.0, 1.0), (0.5, 0.2)] {
                let s = projected_area_direct(dist, au, av);
                assert!((s - 1.0).abs() < 2e-4, "{dist:?} au={au} av={av}: {s}");
            }
        }
    }

    #[test]
    fn smith_g1_projected_area_constraint() {
        // ∫ G1(w,h) max(0, w·h) D(h) dω_h = w·n (Heitz 2014, eq. 5): Smith's Λ is the one
        // consistent with D. Checked for both distributions, isotropic and anisotropic.
        let (x, w) = gauss_legendre(200);
        let nphi = 200;
        for dist in [Distribution::Beckmann, Distribution::Ggx] {
            for &(au, av, th_deg, ph_deg) in &[
                (0.3, 0.3, 60.0f64, 0.0f64),
                (0.5, 0.1, 75.0, 30.0),
                (0.8, 0.8, 85.0, 0.0),
                (0.2, 0.6, 40.0, 100.0),
            ] {
                let (th, ph) = (th_deg.to_radians(), ph_deg.to_radians());
                let wv = Vec3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos());
                let mut sum = 0.0;
                for (xi, wi) in x.iter().zip(&w) {
                    let t = (xi + 1.0) * 0.25 * PI;
                    let dt = 0.25 * PI * wi;
                    for k in 0..nphi {
                        let phi = (k as f64 + 0.5) * 2.0 * PI / nphi as f64;
                        let h = Vec3::new(t.sin() * phi.cos(), t.sin() * phi.sin(), t.cos());
                        let wh = wv.dot(h);
                        if wh > 0.0 {
                            sum += g1(dist, wv, h, au, av) * wh * d(dist, h, au, av) * t.sin() * dt * 2.0 * PI
                                / nphi as f64;
                        }
                    }
                }
                assert!(
                    (sum - wv.z).abs() < 2e-3 * wv.z.max(0.1),
                    "{dist:?} {au} {av} θ={th_deg}: {sum} vs {}",
                    wv.z
                );
            }
        }
    }

    #[test]
    fn g2_bounds_and_order() {
        let l = Vec3::new(0.6, 0.1, 0.7937253933193772);
        let v = Vec3::new(-0.5, 0.3, 0.8124038404635961);
        let h = (l + v).normalized();
        for dist in [Distribution::Beckmann, Distribution::Ggx] {
            for &a in &[1e-4, 0.1, 0.5, 1.0] {
                let s = g2(dist, Masking::Separable, l, v, h, a, a);
                let c = g2(dist, Masking::HeightCorrelated, l, v, h, a, a);
                assert!(
                    s > 0.0 && s <= 1.0 && c <= 1.0 && c >= s,
                    "{dist:?} a={a}: sep {s} hc {c}"
                );
            }
        }
    }

    #[test]
    fn normal_direction_has_no_masking_and_no_nan() {
        // θ = 0: azimuth undefined; anisotropic Λ must not NaN.
        let n = Vec3::new(0.0, 0.0, 1.0);
        for dist in [Distribution::Beckmann, Distribution::Ggx] {
            assert_eq!(lambda(dist, n, 0.01, 0.9), 0.0);
            assert_eq!(g1(dist, n, n, 0.01, 0.9), 1.0);
            let dn = d(dist, n, 0.01, 0.9);
            assert!((dn - 1.0 / (PI * 0.01 * 0.9)).abs() < 1e-9 * dn);
        }
    }
}
