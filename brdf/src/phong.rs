//! Phong-family lobes: original Phong, modified (energy-normalized) Phong, normalized
//! Blinn-Phong. `r = 2(n·l)n − l` is the mirror direction of `l`, `h` the half vector.
//! Powers are computed as `exp(n ln c)`: exponents up to 10⁷ neither overflow nor lose the
//! lobe.

use gonio_devices::Vec3;
use std::f64::consts::{FRAC_1_PI, PI};

use super::math::{half_vector, pow_pos, reflect_z};
use super::Rgb;

/// Original Phong (1975) as a BRDF: `f = kd/π + ks (r·v)^n / (n·l)`.
///
/// **Not reciprocal** (the `1/(n·l)` makes `f(l,v) ≠ f(v,l)`) and **not energy conserving**
/// (the lobe is not normalized and grows without bound as `n·l → 0`). Kept for comparison
/// with the lecture notes; use `modified-phong` for physically plausible work.
#[inline]
pub fn phong(kd: &Rgb, ks: &Rgb, n: f64, l: Vec3, v: Vec3) -> Rgb {
    let c = reflect_z(l).dot(v);
    let s = pow_pos(c, n) / l.z;
    [0, 1, 2].map(|i| kd[i] * FRAC_1_PI + ks[i] * s)
}

/// Modified Phong (Lewis 1994): `f = kd/π + ks (n+2)/(2π) max(0, r·v)^n`.
///
/// Normalization: `∫ (n+2)/(2π) cos^n θ cos θ dω = 1`, so at normal incidence the specular
/// albedo is exactly `ks`, and it only decreases with the angle of incidence (lobe cut by
/// the horizon). Reciprocal; energy conserving when `kd + ks ≤ 1` per channel.
#[inline]
pub fn modified_phong(kd: &Rgb, ks: &Rgb, n: f64, l: Vec3, v: Vec3) -> Rgb {
    let c = reflect_z(l).dot(v);
    let s = (n + 2.0) / (2.0 * PI) * pow_pos(c, n);
    [0, 1, 2].map(|i| kd[i] * FRAC_1_PI + ks[i] * s)
}

/// Normalized Blinn-Phong: `f = kd/π + ks (m+8)/(8π) (n·h)^m`.
///
/// Normalization: the common `(m+8)/(8π)` (Akenine-Möller et al.), an approximation. Its
/// specular albedo at normal incidence is exactly
/// `A(m) = (m+8)(m + 2^{−m/2}) / ((m+2)(m+4))` ([`blinn_phong_normal_albedo`]): 1 at m = 0,
/// up to 1.0752 near m ≈ 8.8, → 1 for m → ∞. Normal incidence is the maximum over incidence
/// angles, so energy is conserved when `kd + A(m) ks ≤ 1` — which `validate` enforces.
/// `(r·v)^n ≈ (n·h)^{4n}` relates the exponent to Phong's. Reciprocal.
#[inline]
pub fn blinn_phong(kd: &Rgb, ks: &Rgb, m: f64, l: Vec3, v: Vec3) -> Rgb {
    let s = match half_vector(l, v) {
        Some(h) => (m + 8.0) / (8.0 * PI) * pow_pos(h.z, m),
        None => 0.0,
    };
    [0, 1, 2].map(|i| kd[i] * FRAC_1_PI + ks[i] * s)
}

/// Specular albedo of the normalized Blinn-Phong lobe (ks = 1) at normal incidence:
/// `A(m) = (m+8)(m + 2^{−m/2}) / ((m+2)(m+4))`.
///
/// Derivation: with `u = cos(θ/2) = n·h`, `cos θ = 2u² − 1`, `sin θ dθ = −4u du`,
/// `∫₀^{π/2} u^m cos θ sin θ dθ = 4 ∫_{1/√2}^1 u^{m+1}(2u² − 1) du
///  = 4 (m + 2^{−m/2}) / ((m+2)(m+4))`, times `2π (m+8)/(8π)`.
pub fn blinn_phong_normal_albedo(m: f64) -> f64 {
    let tail = (-0.5 * m * std::f64::consts::LN_2).exp();
    (m + 8.0) * (m + tail) / ((m + 2.0) * (m + 4.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blinn_phong_albedo_closed_form_values() {
        assert!((blinn_phong_normal_albedo(0.0) - 1.0).abs() < 1e-15);
        // maximum ≈ 1.0752 near m = 8.8
        let max = (0..200)
            .map(|i| blinn_phong_normal_albedo(i as f64 * 0.5))
            .fold(0.0, f64::max);
        assert!(max > 1.075 && max < 1.0753, "{max}");
        assert!((blinn_phong_normal_albedo(1e6) - 1.0).abs() < 1e-5);
    }

    #[test]
    fn phong_is_not_reciprocal() {
        let l = Vec3::new(0.5, 0.0, 0.75f64.sqrt());
        let v = Vec3::new(-0.8, 0.0, 0.6);
        let a = phong(&[0.0; 3], &[0.5; 3], 10.0, l, v)[0];
        let b = phong(&[0.0; 3], &[0.5; 3], 10.0, v, l)[0];
        assert!((a / b - 0.6 / 0.75f64.sqrt()).abs() < 1e-12, "{a} {b}");
    }
}
