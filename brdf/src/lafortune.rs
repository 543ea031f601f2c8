//! Lafortune et al. 1997, generalized cosine lobes:
//! `f = kd/π + Σ_j ks_j (n_j+2)/(2π) max(0, C_x l_x v_x + C_y l_y v_y + C_z l_z v_z)^{n_j}`.
//!
//! Normalization: the factor `(n+2)/(2π)` makes a lobe with `|C_x| = |C_y| = |C_z| = 1`
//! have specular albedo exactly `ks` at normal incidence (`C = (−1, −1, 1)` is the modified
//! Phong mirror lobe, `C = (1, 1, 1)` retro-reflection, `C = (0, 0, 1)`-like lobes are
//! off-specular/forward). For general `C` the lobe value is `|C⊙l|^n (u·v)^n` with
//! `u = C⊙l/|C⊙l|`, and since a cosine lobe about any axis `u` collects at most as much
//! cosine-weighted energy as one about the normal, the directional albedo of a lobe is
//! ≤ `ks · max_i |C_i|^n`. `validate` therefore requires
//! `kd + Σ_j ks_j max_i|C_{j,i}|^{n_j} ≤ 1` per channel (sufficient for energy
//! conservation). Reciprocal (the dot form is symmetric in l and v).

use gonio_devices::Vec3;
use serde::{Deserialize, Serialize};
use std::f64::consts::{FRAC_1_PI, PI};

use super::math::pow_pos;
use super::Rgb;

/// One generalized cosine lobe.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LafortuneLobe {
    /// `[C_x, C_y, C_z]`.
    pub c: [f64; 3],
    /// Lobe exponent `n ≥ 0`.
    pub exponent: f64,
    /// Lobe weight per RGB channel (its albedo at normal incidence when `|C_i| = 1`).
    pub ks: Rgb,
}

impl LafortuneLobe {
    /// Upper bound of this lobe's directional albedo per unit `ks`: `max_i |C_i|^n`.
    pub fn albedo_bound(&self) -> f64 {
        let cmax = self.c.iter().fold(0.0f64, |a, c| a.max(c.abs()));
        if cmax == 0.0 {
            return 0.0; // the lobe vanishes identically
        }
        (self.exponent * cmax.ln()).exp()
    }
}

/// One lobe's value per unit `ks` at unit `l`, `v`: `(n+2)/(2π) · max(0, C_x l_x v_x +
/// C_y l_y v_y + C_z l_z v_z)^n`. The one home of the formula: the model's [`eval`] and the
/// per-texel SVBRDF decoder (`gonio_btf::compress::svbrdf`) both call it.
#[inline]
pub fn lobe_value(c: [f64; 3], exponent: f64, l: Vec3, v: Vec3) -> f64 {
    let s = c[0] * l.x * v.x + c[1] * l.y * v.y + c[2] * l.z * v.z;
    (exponent + 2.0) / (2.0 * PI) * pow_pos(s, exponent)
}

#[inline]
pub(crate) fn eval(kd: &Rgb, lobes: &[LafortuneLobe], l: Vec3, v: Vec3) -> Rgb {
    let mut out = kd.map(|k| k * FRAC_1_PI);
    for lobe in lobes {
        if lobe.ks.iter().all(|k| *k == 0.0) {
            continue; // switched off (its power may overflow when |C| > 1: no 0·∞)
        }
        let val = lobe_value(lobe.c, lobe.exponent, l, v);
        for (o, k) in out.iter_mut().zip(&lobe.ks) {
            if *k != 0.0 {
                *o += k * val;
            }
        }
    }
    out
}
