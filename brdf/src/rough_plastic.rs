//! Rough plastic: a rough dielectric coating (specular microfacet reflection) over a
//! Lambertian base, evaluated **exactly as Mitsuba 3's `roughplastic` BSDF** (`eval()` of
//! `src/bsdfs/roughplastic.cpp`, Mitsuba 3.x), so values can be compared with Mitsuba's
//! `scalar_rgb` variant (which returns `f · cos θ_o`; this module returns `f`).
//!
//! With `l`, `v` the two directions, `h = (l+v)/|l+v|`, `η = int_ior/ext_ior`:
//!
//! ```text
//! f = ρ_s · F(l·h, η) D(h) G1(l,h) G1(v,h) / (4 cos θ_l cos θ_v)
//!   + ρ_d' · t(cos θ_l) t(cos θ_v) / (π η²),
//! ρ_d' = ρ_d / (1 − R_i)          (nonlinear = false, Mitsuba's default)
//! ρ_d' = ρ_d / (1 − ρ_d R_i)      (nonlinear = true)
//! ```
//!
//! - `F` is the unpolarized dielectric Fresnel term, `D` Beckmann or GGX (isotropic),
//!   `G1` Mitsuba's Smith masking: exact for GGX, Walter's rational approximation for
//!   Beckmann (`a ≥ 1.6 → 1`, else `(3.535a + 2.181a²)/(1 + 2.276a + 2.577a²)`,
//!   `a = cot θ / α`, < 0.35 % error); separable `G2 = G1 G1`.
//! - `t(μ)` is the transmittance of the rough interface from outside,
//!   `1 − (directional albedo of the rough dielectric reflection)`, which Mitsuba
//!   precomputes for 64 values `μ_j = max(10⁻⁶, j/63)` by integrating `(1 − F) G1(refracted)`
//!   over the distribution of visible normals with a 32×32 (η > 1) or 128×128 (η ≤ 1)
//!   Gauss-Legendre rule in the sample space of Mitsuba's visible-normal sampling routine,
//!   and interpolates linearly in μ. The same procedure, the same sampling routine
//!   (Heitz 2018 for GGX, Jakob 2014 with three Newton steps for Beckmann) and the same
//!   grids are used here, in f64.
//! - `R_i = 2 · mean_j(μ_j · R(μ_j; 1/η))` is the internal diffuse reflectance of the
//!   interface seen from inside (the mean over the same 64 μ_j, as Mitsuba does).
//! - α is clamped to ≥ 10⁻⁴ (Mitsuba's clamp).
//!
//! The tables depend only on (distribution, α, η); they are computed on first use
//! (≈ 1 M quadrature points, ~0.1 s in release) and cached per process and per thread,
//! so `eval` itself does not allocate after the first call for a material.
//!
//! Reciprocal. Energy: `t(μ)` already discounts the coating's reflection, so the albedo is
//! ≤ 1 up to the quadrature approximations of the tables (see the tests).

use gonio_devices::Vec3;
use std::cell::RefCell;
use std::f64::consts::PI;
use std::sync::{Arc, Mutex};

use super::math::{erf, erfinv, gauss_legendre, INV_SQRT_PI};
use super::microfacet::Distribution;
use super::Rgb;

/// Number of μ samples of Mitsuba's transmittance table (`MI_ROUGH_TRANSMITTANCE_RES`).
const RES: usize = 64;

/// Mitsuba's lower clamp of the roughness.
pub(crate) const MIN_ALPHA: f64 = 1e-4;

/// Precomputed per-material tables.
#[derive(Debug, Clone)]
pub(crate) struct Tables {
    /// `t(μ_j)`, transmittance into the coating from outside.
    pub ext_t: [f64; RES],
    /// Internal diffuse reflectance `R_i`.
    pub internal_r: f64,
}

#[derive(Clone, Copy, PartialEq, Debug)]
struct Key {
    dist: Distribution,
    alpha: u64,
    eta: u64,
}

type Cache = Vec<(Key, Arc<Tables>)>;

static GLOBAL: Mutex<Cache> = Mutex::new(Vec::new());
const LOCAL_CAP: usize = 64;
const GLOBAL_CAP: usize = 256;

thread_local! {
    static LOCAL: RefCell<Cache> = const { RefCell::new(Vec::new()) };
}

/// Run `f` with the tables of (dist, alpha, eta), computing them on first use.
fn with_tables<R>(dist: Distribution, alpha: f64, eta: f64, f: impl FnOnce(&Tables) -> R) -> R {
    let key = Key {
        dist,
        alpha: alpha.to_bits(),
        eta: eta.to_bits(),
    };
    let hit = LOCAL.with(|c| c.borrow().iter().find(|(k, _)| *k == key).map(|(_, t)| Arc::clone(t)));
    let tables = match hit {
        Some(t) => t,
        None => {
            let global = {
                let g = GLOBAL.lock().unwrap_or_else(|e| e.into_inner());
                g.iter().find(|(k, _)| *k == key).map(|(_, t)| Arc::clone(t))
            };
            let t = match global {
                Some(t) => t,
                None => {
                    let t = Arc::new(compute_tables(dist, alpha, eta));
                    let mut g = GLOBAL.lock().unwrap_or_else(|e| e.into_inner());
                    if !g.iter().any(|(k, _)| *k == key) {
                        if g.len() >= GLOBAL_CAP {
                            g.remove(0);
                        }
                        g.push((key, Arc::clone(&t)));
                    }
                    t
                }
            };
            LOCAL.with(|c| {
                let mut c = c.borrow_mut();
                if c.len() >= LOCAL_CAP {
                    c.remove(0);
                }
                c.push((key, Arc::clone(&t)));
            });
            t
        }
    };
    f(&tables)
}

/// Tables of a material (for tests).
#[cfg(test)]
pub(crate) fn tables(dist: Distribution, alpha: f64, eta: f64) -> Tables {
    with_tables(dist, alpha.max(MIN_ALPHA), eta, |t| t.clone())
}

/// The rough plastic BRDF (1/sr). `l`, `v` unit, local frame.
#[allow(clippy::too_many_arguments)]
#[inline]
pub(crate) fn eval(
    dist: Distribution,
    alpha: f64,
    eta: f64,
    diffuse: &Rgb,
    specular: &Rgb,
    nonlinear: bool,
    l: Vec3,
    v: Vec3,
) -> Rgb {
    let (ci, co) = (l.z, v.z);
    if ci <= 0.0 || co <= 0.0 {
        return [0.0; 3];
    }
    let alpha = alpha.max(MIN_ALPHA);
    // Specular layer.
    let spec = match super::math::half_vector(l, v) {
        Some(h) => {
            let d = mitsuba_d(dist, h, alpha);
            if d == 0.0 {
                0.0
            } else {
                let f = fresnel_mitsuba(l.dot(h), eta).0;
                let g = smith_g1_mitsuba(dist, l, h, alpha) * smith_g1_mitsuba(dist, v, h, alpha);
                let s = f * d * g / (4.0 * ci * co);
                if s.is_finite() {
                    s
                } else {
                    0.0
                }
            }
        }
        None => 0.0,
    };
    // Diffuse base.
    with_tables(dist, alpha, eta, |t| {
        let ti = lerp_gather(&t.ext_t, ci);
        let to = lerp_gather(&t.ext_t, co);
        let k = ti * to / (PI * eta * eta);
        [0, 1, 2].map(|c| {
            let rd = diffuse[c];
            let denom = 1.0 - if nonlinear { rd * t.internal_r } else { t.internal_r };
            let diff = if denom > 0.0 { rd / denom } else { 0.0 };
            specular[c] * spec + diff * k
        })
    })
}

/// Mitsuba's `lerp_gather` over the μ table.
#[inline]
fn lerp_gather(data: &[f64; RES], x: f64) -> f64 {
    let x = x.clamp(0.0, 1.0) * (RES - 1) as f64;
    let index = (x as usize).min(RES - 2);
    let w = x - index as f64;
    data[index] * (1.0 - w) + data[index + 1] * w
}

/// Mitsuba's microfacet `eval(m)` (isotropic), including its `D cos θ > 1e-20` cut.
#[inline]
fn mitsuba_d(dist: Distribution, m: Vec3, alpha: f64) -> f64 {
    let d = super::microfacet::d(dist, m, alpha, alpha);
    if d * m.z > 1e-20 {
        d
    } else {
        0.0
    }
}

/// Mitsuba's `smith_g1(v, m)`.
#[inline]
fn smith_g1_mitsuba(dist: Distribution, v: Vec3, m: Vec3, alpha: f64) -> f64 {
    let xy_alpha_2 = (alpha * v.x).powi(2) + (alpha * v.y).powi(2);
    if v.dot(m) * v.z <= 0.0 {
        return 0.0;
    }
    if xy_alpha_2 == 0.0 {
        return 1.0;
    }
    let tan_theta_alpha_2 = xy_alpha_2 / (v.z * v.z);
    match dist {
        Distribution::Beckmann => {
            let a = 1.0 / tan_theta_alpha_2.sqrt();
            if a >= 1.6 {
                1.0
            } else {
                let a2 = a * a;
                (3.535 * a + 2.181 * a2) / (1.0 + 2.276 * a + 2.577 * a2)
            }
        }
        Distribution::Ggx => 2.0 / (1.0 + (1.0 + tan_theta_alpha_2).sqrt()),
    }
}

/// Mitsuba's `fresnel(cos_theta_i, eta)`: (F, cos θ_t signed, η_it, η_ti).
#[inline]
fn fresnel_mitsuba(cos_theta_i: f64, eta: f64) -> (f64, f64, f64, f64) {
    let outside = cos_theta_i >= 0.0;
    let rcp_eta = 1.0 / eta;
    let (eta_it, eta_ti) = if outside { (eta, rcp_eta) } else { (rcp_eta, eta) };
    let cos_t_sqr = 1.0 - (1.0 - cos_theta_i * cos_theta_i) * eta_ti * eta_ti;
    let ci = cos_theta_i.abs();
    let ct = cos_t_sqr.max(0.0).sqrt();
    let r = if eta == 1.0 {
        0.0
    } else if ci == 0.0 {
        1.0
    } else {
        let a_s = (ci - eta_it * ct) / (ci + eta_it * ct);
        let a_p = (eta_it * ci - ct) / (eta_it * ci + ct);
        0.5 * (a_s * a_s + a_p * a_p)
    };
    let cos_t = if cos_theta_i >= 0.0 { -ct } else { ct };
    (r, cos_t, eta_it, eta_ti)
}

/// Mitsuba's `square_to_uniform_disk_concentric`.
fn concentric(u: (f64, f64)) -> (f64, f64) {
    let x = 2.0 * u.0 - 1.0;
    let y = 2.0 * u.1 - 1.0;
    if x == 0.0 && y == 0.0 {
        return (0.0, 0.0);
    }
    let q13 = x.abs() < y.abs();
    let (r, rp) = if q13 { (y, x) } else { (x, y) };
    let mut phi = 0.25 * PI * rp / r;
    if q13 {
        phi = 0.5 * PI - phi;
    }
    (r * phi.cos(), r * phi.sin())
}

/// GGX visible slopes for α = 1 (Mitsuba's `sample_visible_11`, Heitz 2018).
fn ggx_visible_11(cos_theta_i: f64, u: (f64, f64)) -> (f64, f64) {
    let (px, mut py) = concentric(u);
    let s = 0.5 * (1.0 + cos_theta_i);
    let a = (1.0 - px * px).max(0.0).sqrt();
    py = a * (1.0 - s) + py * s;
    let (x, y) = (px, py);
    let z = (1.0 - x * x - y * y).max(0.0).sqrt();
    let sin_theta_i = (1.0 - cos_theta_i * cos_theta_i).max(0.0).sqrt();
    let norm = 1.0 / (sin_theta_i * y + cos_theta_i * z);
    ((cos_theta_i * y - sin_theta_i * z) * norm, x * norm)
}

/// Beckmann visible slope along the incidence plane for α = 1 (Mitsuba's
/// `sample_visible_11`: initial guess plus three Newton steps in the erf domain).
fn beckmann_visible_11_x(cos_theta_i: f64, u1: f64) -> f64 {
    let tan_theta_i = (1.0 - cos_theta_i * cos_theta_i).max(0.0).sqrt() / cos_theta_i;
    let cot_theta_i = 1.0 / tan_theta_i;
    let maxval = erf(cot_theta_i);
    let mut sx = u1.clamp(1e-6, 1.0 - 1e-6);
    let mut x = maxval - (maxval + 1.0) * erf((-sx.ln()).sqrt());
    sx *= 1.0 + maxval + INV_SQRT_PI * tan_theta_i * (-cot_theta_i * cot_theta_i).exp();
    for _ in 0..3 {
        let slope = erfinv(x);
        let value = 1.0 + x + INV_SQRT_PI * tan_theta_i * (-slope * slope).exp() - sx;
        let derivative = 1.0 - slope * tan_theta_i;
        x -= value / derivative;
    }
    erfinv(x)
}

/// Beckmann visible slope across the incidence plane for α = 1.
fn beckmann_visible_11_y(u2: f64) -> f64 {
    erfinv(2.0 * u2.clamp(1e-6, 1.0 - 1e-6) - 1.0)
}

/// Mitsuba's `sincos_phi` of the stretched direction.
fn sincos_phi(v: Vec3) -> (f64, f64) {
    let s2 = v.x * v.x + v.y * v.y;
    if s2 <= 4.0 * f32::EPSILON as f64 {
        return (0.0, 1.0);
    }
    let inv = 1.0 / s2.sqrt();
    ((v.y * inv).clamp(-1.0, 1.0), (v.x * inv).clamp(-1.0, 1.0))
}

/// Integrates `g(m)` over the visible normals of `wi` with Mitsuba's `res × res`
/// Gauss-Legendre grid in the sample space of its visible-normal sampling.
fn integrate_visible(dist: Distribution, alpha: f64, wi: Vec3, res: usize, mut g: impl FnMut(Vec3) -> f64) -> f64 {
    let (nodes, weights) = gauss_legendre(res);
    let u: Vec<f64> = nodes.iter().map(|x| 0.5 * x + 0.5).collect();
    let wi_p = Vec3::new(alpha * wi.x, alpha * wi.y, wi.z).normalized();
    let (sin_phi, cos_phi) = sincos_phi(wi_p);
    let cos_theta = wi_p.z;
    // Beckmann slopes separate into a function of u1 and one of u2.
    let (bx, by): (Vec<f64>, Vec<f64>) = match dist {
        Distribution::Beckmann => (
            u.iter().map(|&a| beckmann_visible_11_x(cos_theta, a)).collect(),
            u.iter().map(|&b| beckmann_visible_11_y(b)).collect(),
        ),
        Distribution::Ggx => (Vec::new(), Vec::new()),
    };
    let mut sum = 0.0;
    for i in 0..res {
        for j in 0..res {
            let (sx, sy) = match dist {
                Distribution::Beckmann => (bx[i], by[j]),
                Distribution::Ggx => ggx_visible_11(cos_theta, (u[i], u[j])),
            };
            let slope_x = (cos_phi * sx - sin_phi * sy) * alpha;
            let slope_y = (sin_phi * sx + cos_phi * sy) * alpha;
            let m = Vec3::new(-slope_x, -slope_y, 1.0).normalized();
            let val = g(m);
            sum += val * weights[i] * weights[j] * 0.25;
        }
    }
    sum
}

/// Mitsuba's `eval_reflectance`: directional albedo of the rough dielectric reflection.
fn eval_reflectance(dist: Distribution, alpha: f64, wi: Vec3, eta: f64) -> f64 {
    let res = if eta > 1.0 { 32 } else { 128 };
    integrate_visible(dist, alpha, wi, res, |m| {
        let wim = wi.dot(m);
        let wo = m * (2.0 * wim) - wi;
        let f = fresnel_mitsuba(wim, eta).0;
        if wo.z <= 0.0 || wi.z <= 0.0 {
            return 0.0;
        }
        smith_g1_mitsuba(dist, wo, m, alpha) * f
    })
}

/// Mitsuba's `eval_transmittance`: directional transmittance through the rough interface.
fn eval_transmittance(dist: Distribution, alpha: f64, wi: Vec3, eta: f64) -> f64 {
    let res = if eta > 1.0 { 32 } else { 128 };
    integrate_visible(dist, alpha, wi, res, |m| {
        let wim = wi.dot(m);
        let (f, cos_t, _eta_it, eta_ti) = fresnel_mitsuba(wim, eta);
        let wo = m * (wim * eta_ti + cos_t) - wi * eta_ti;
        if wo.z * wi.z >= 0.0 {
            return 0.0;
        }
        smith_g1_mitsuba(dist, wo, m, alpha) * (1.0 - f)
    })
}

fn compute_tables(dist: Distribution, alpha: f64, eta: f64) -> Tables {
    let mut ext_t = [0.0; RES];
    let mut mean = 0.0;
    for (j, t) in ext_t.iter_mut().enumerate() {
        let mu = (j as f64 / (RES - 1) as f64).max(1e-6);
        let wi = Vec3::new((1.0 - mu * mu).sqrt(), 0.0, mu);
        let v = eval_transmittance(dist, alpha, wi, eta);
        *t = if v.is_finite() { v } else { 0.0 };
        let r = eval_reflectance(dist, alpha, wi, 1.0 / eta);
        mean += if r.is_finite() { r * mu } else { 0.0 };
    }
    Tables {
        ext_t,
        internal_r: 2.0 * mean / RES as f64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn beckmann_rational_g1_close_to_exact() {
        // Walter's rational fit vs the exact erf form (independent implementation).
        for &th in &[10.0f64, 45.0, 70.0, 80.0, 85.0, 89.0, 89.99] {
            for &a in &[0.05, 0.3, 1.0] {
                let t = th.to_radians();
                let w = Vec3::new(t.sin(), 0.0, t.cos());
                let n = Vec3::new(0.0, 0.0, 1.0);
                let approx = smith_g1_mitsuba(Distribution::Beckmann, w, n, a);
                let exact = super::super::microfacet::g1(Distribution::Beckmann, w, n, a, a);
                assert!(
                    (approx - exact).abs() <= 0.0036 * exact + 1e-12,
                    "θ={th} α={a}: {approx} vs {exact}"
                );
            }
        }
    }

    #[test]
    fn transmittance_table_is_physical() {
        for dist in [Distribution::Beckmann, Distribution::Ggx] {
            for &(alpha, eta) in &[(1e-4, 1.5), (0.1, 1.49), (0.6, 1.33), (1.0, 2.0)] {
                let t = tables(dist, alpha, eta);
                for (j, &v) in t.ext_t.iter().enumerate() {
                    assert!(
                        v.is_finite() && (0.0..=1.0 + 1e-9).contains(&v),
                        "{dist:?} α={alpha} j={j}: {v}"
                    );
                }
                // At normal incidence a smooth interface transmits 1 − ((η−1)/(η+1))².
                if alpha < 0.01 {
                    let f0 = ((eta - 1.0) / (eta + 1.0)).powi(2);
                    assert!(
                        (t.ext_t[RES - 1] - (1.0 - f0)).abs() < 1e-3,
                        "{dist:?}: {}",
                        t.ext_t[RES - 1]
                    );
                }
                assert!(
                    t.internal_r > 0.0 && t.internal_r < 1.0,
                    "{dist:?} α={alpha}: R_i={}",
                    t.internal_r
                );
            }
        }
    }
}
