//! Rough conductor: the modern single-scattering microfacet BRDF (Walter et al. 2007; as
//! Mitsuba 3's `roughconductor` and pbrt-v4's `ConductorBxDF`):
//!
//! `f = tint ⊙ F(l·h; η + ik) · D(h) · G2(l, v, h) / (4 |n·l| |n·v|)`
//!
//! - `D`: Beckmann or GGX, isotropic or anisotropic (`α_u` along +x, `α_v` along +y),
//!   normalized so that `∫ D (n·h) dω_h = 1`;
//! - `G2`: Smith, separable (`G1 G1`, Mitsuba's choice, the default) or height-correlated
//!   (`1/(1 + Λ_l + Λ_v)`, pbrt-v4's choice), with the exact Λ for both distributions
//!   (Mitsuba uses a rational approximation of the Beckmann G1, < 0.35 % off);
//! - `F`: unpolarized conductor Fresnel with complex index per RGB channel.
//!
//! Reciprocal; energy conserving (single scattering only, so the albedo is < 1 and falls
//! off for large α because multiple scattering is not modelled).

use gonio_devices::Vec3;

use super::fresnel::conductor;
use super::microfacet::{dg_over_4, Distribution, Masking};
use super::Rgb;

#[allow(clippy::too_many_arguments)]
#[inline]
pub(crate) fn eval(
    dist: Distribution,
    masking: Masking,
    au: f64,
    av: f64,
    eta: &Rgb,
    k: &Rgb,
    tint: &Rgb,
    l: Vec3,
    v: Vec3,
) -> Rgb {
    match dg_over_4(dist, masking, l, v, au, av) {
        Some((s, h)) if s > 0.0 => {
            let c = l.dot(h);
            [0, 1, 2].map(|i| tint[i] * conductor(c, eta[i], k[i]) * s)
        }
        _ => [0.0; 3],
    }
}
