//! Cook-Torrance (1982) as in the thesis (eqs. 19–27): Beckmann distribution with several
//! roughness lobes, V-cavity geometry term, selectable Fresnel term.
//!
//! `f = kd/π + ks ⊙ F(l·h) · D(h) · G / (4 (n·l)(n·v))`, with
//! - `D = Σ_j w_j exp(−tan²γ/m_j²) / (π m_j² cos⁴γ)`, `Σ w_j = 1`, γ = ∠(n, h);
//! - `G = min{1, 2(n·h)(n·v)/(v·h), 2(n·h)(n·l)/(v·h)}`;
//! - `F` dielectric (η), conductor (n + ik per channel), Schlick or none ([`Fresnel`]).
//!
//! Normalization: each `D_j` satisfies `∫ D_j (n·h) dω_h = 1` and the denominator is
//! `4 (n·l)(n·v)` (the Jacobian of the half-vector map), so as `m → 0` with `F = 1` the
//! specular albedo tends to 1 (exactly a mirror). Cook & Torrance's paper and the lecture
//! write `F D G / (π (n·l)(n·v))` resp. `F D G / ((n·l)(n·v))` with D scaled differently;
//! those are `4/π` resp. 4 times brighter than this energy-consistent form. With the
//! V-cavity `G` and `F ≤ 1` the specular albedo is ≤ 1 (checked numerically in the tests),
//! so `kd + ks ≤ 1` conserves energy. Reciprocal.

use gonio_devices::Vec3;
use serde::{Deserialize, Serialize};
use std::f64::consts::FRAC_1_PI;

use super::fresnel::Fresnel;
use super::math::half_vector;
use super::microfacet::{d, Distribution};
use super::Rgb;

/// One Beckmann roughness lobe of the Cook-Torrance distribution.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BeckmannLobe {
    /// Weight `w_j ≥ 0`; the weights of a model sum to 1.
    pub weight: f64,
    /// RMS slope `m_j` (Beckmann roughness).
    pub m: f64,
}

/// V-cavity geometry term (Torrance-Sparrow / Blinn).
#[inline]
pub(crate) fn vcavity_g(l: Vec3, v: Vec3, h: Vec3) -> f64 {
    let vh = v.dot(h);
    if vh <= 0.0 || l.dot(h) <= 0.0 {
        return 0.0;
    }
    let k = 2.0 * h.z / vh;
    1.0f64.min(k * v.z).min(k * l.z).max(0.0)
}

#[inline]
pub(crate) fn eval(kd: &Rgb, ks: &Rgb, lobes: &[BeckmannLobe], fresnel: &Fresnel, l: Vec3, v: Vec3) -> Rgb {
    let mut spec = [0.0; 3];
    if let Some(h) = half_vector(l, v) {
        let dd: f64 = lobes
            .iter()
            .map(|lb| lb.weight * d(Distribution::Beckmann, h, lb.m, lb.m))
            .sum();
        if dd > 0.0 {
            let g = vcavity_g(l, v, h);
            let s = dd * g / (4.0 * l.z * v.z);
            if s.is_finite() && s > 0.0 {
                let f = fresnel.eval(l.dot(h));
                spec = [0, 1, 2].map(|i| ks[i] * f[i] * s);
            }
        }
    }
    [0, 1, 2].map(|i| kd[i] * FRAC_1_PI + spec[i])
}
