//! Oren-Nayar (1994): rough diffuse surfaces made of Lambertian V-cavities with a Gaussian
//! slope-angle distribution of standard deviation σ (shadowing, masking, interreflection).
//! α = max(θ_l, θ_v), β = min(θ_l, θ_v), Δφ = φ_v − φ_l.
//!
//! - `qualitative` (Oren & Nayar's simplified model):
//!   `f = ρ/π (A + B max(0, cos Δφ) sin α tan β)`, `A = 1 − 0.5 σ²/(σ² + 0.33)`,
//!   `B = 0.45 σ²/(σ² + 0.09)`.
//! - `full` (their eq. with interreflection):
//!   `f = ρ/π [C1 + cos Δφ C2 tan β + (1 − |cos Δφ|) C3 tan((α+β)/2)]
//!      + 0.17 ρ²/π σ²/(σ² + 0.13) [1 − cos Δφ (2β/π)²]`,
//!   `C1 = A`, `C2 = 0.45 σ²/(σ²+0.09) sin α` if cos Δφ ≥ 0 else
//!   `0.45 σ²/(σ²+0.09) (sin α − (2β/π)³)`, `C3 = 0.125 σ²/(σ²+0.09) (4αβ/π²)²`.
//!
//!   The published fit can turn negative for back-scattering at grazing angles with large σ;
//!   the value is clamped at 0.
//!
//! Normalization: ρ is the facet albedo; at σ = 0 both reduce to Lambert `ρ/π`. The
//! published fits are **not strictly energy conserving**: at normal incidence the albedo is
//! below ρ, but towards grazing incidence it rises above it, up to ≈ 1.015 ρ (qualitative,
//! σ ≈ 12.5°) and ≈ 1.051 (full, ρ = 1, σ ≈ 17.5°) at θ = 89.99° (measured numerically,
//! tests `oren_nayar_grazing_overshoot`, `oren_nayar_albedo_bounded`). No rescaling is
//! applied: the formulas are the published ones (as in Mitsuba 0.6's `roughdiffuse`, whose
//! σ = α/√2 in radians), except that the full model is clamped at 0. Reciprocal. θ = 0 is handled without an azimuth (`cos Δφ sin θ_l sin θ_v = l_xy · v_xy`,
//! and every term with cos Δφ carries a factor that vanishes at β = 0).

use gonio_devices::Vec3;
use serde::{Deserialize, Serialize};
use std::f64::consts::{FRAC_1_PI, PI};

use super::Rgb;

/// Which Oren-Nayar formulation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum OrenNayarVariant {
    /// `A + B max(0, cos Δφ) sin α tan β`.
    #[default]
    Qualitative,
    /// With the C1..C3 terms and the interreflection term.
    Full,
}

#[inline]
pub(crate) fn eval(albedo: &Rgb, sigma: f64, variant: OrenNayarVariant, l: Vec3, v: Vec3) -> Rgb {
    let s2 = sigma * sigma;
    let a = 1.0 - 0.5 * s2 / (s2 + 0.33);
    let b = 0.45 * s2 / (s2 + 0.09);
    let (ci, co) = (l.z.min(1.0), v.z.min(1.0));
    let (si, so) = ((1.0 - ci * ci).max(0.0).sqrt(), (1.0 - co * co).max(0.0).sqrt());
    // α = larger polar angle (smaller cosine), β = smaller one.
    let (cos_a, sin_a, cos_b, sin_b) = if ci > co { (co, so, ci, si) } else { (ci, si, co, so) };
    let tan_b = sin_b / cos_b;
    let pxy = l.x * v.x + l.y * v.y; // = cos Δφ sin θ_l sin θ_v
    let sisj = si * so;
    let cos_dphi = if sisj > 1e-12 {
        (pxy / sisj).clamp(-1.0, 1.0)
    } else {
        0.0
    };
    match variant {
        OrenNayarVariant::Qualitative => {
            // B max(0,cos Δφ) sin α tan β = B max(0, l_xy·v_xy) / cos β: no azimuth needed.
            let val = FRAC_1_PI * (a + b * pxy.max(0.0) / cos_b);
            albedo.map(|r| r * val)
        }
        OrenNayarVariant::Full => {
            let alpha = cos_a.clamp(-1.0, 1.0).acos();
            let beta = cos_b.clamp(-1.0, 1.0).acos();
            let t3 = 2.0 * beta / PI;
            let c2 = if cos_dphi >= 0.0 {
                b * sin_a
            } else {
                b * (sin_a - t3 * t3 * t3)
            };
            let tmp2 = 4.0 * alpha * beta / (PI * PI);
            let c3 = 0.125 * s2 / (s2 + 0.09) * tmp2 * tmp2;
            let tan_half = (sin_a + sin_b) / (cos_a + cos_b);
            let single = a + cos_dphi * c2 * tan_b + (1.0 - cos_dphi.abs()) * c3 * tan_half;
            let inter = 0.17 * s2 / (s2 + 0.13) * (1.0 - cos_dphi * t3 * t3);
            albedo.map(|r| (FRAC_1_PI * (r * single + r * r * inter)).max(0.0))
        }
    }
}
