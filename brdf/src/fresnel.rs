//! Fresnel reflectance: dielectric (real η), conductor (complex n + ik, per RGB channel) and
//! Schlick's approximation. All are unpolarized (mean of the s and p parts, thesis eq. (22)
//! with s = t = ½).

use super::{BrdfError, Rgb};
use serde::{Deserialize, Serialize};

/// The Fresnel term of a microfacet model, as written in material files:
/// `fresnel = { type = "conductor", eta = [0.2, 0.92, 1.1], k = [3.9, 2.45, 2.14] }`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "kebab-case", deny_unknown_fields)]
pub enum Fresnel {
    /// `F ≡ 1` (an ideal reflector; useful to inspect `D·G` alone).
    None,
    /// Dielectric interface with relative index `eta = n₂/n₁` (> 1: the light arrives from
    /// the less dense side). `eta < 1` produces total internal reflection beyond the
    /// critical angle.
    Dielectric { eta: f64 },
    /// Conductor with complex relative index `eta + i k`, per RGB channel.
    Conductor { eta: Rgb, k: Rgb },
    /// Schlick: `F = F₀ + (1 − F₀)(1 − cos θ)⁵`.
    Schlick { f0: Rgb },
}

impl Fresnel {
    /// Reflectance for the cosine between the light and the (micro)facet normal.
    #[inline]
    pub fn eval(&self, cos_i: f64) -> Rgb {
        match self {
            Fresnel::None => [1.0; 3],
            Fresnel::Dielectric { eta } => [dielectric(cos_i, *eta); 3],
            Fresnel::Conductor { eta, k } => [0, 1, 2].map(|c| conductor(cos_i, eta[c], k[c])),
            Fresnel::Schlick { f0 } => {
                let m = (1.0 - cos_i.abs().min(1.0)).max(0.0);
                let m5 = m * m * m * m * m;
                f0.map(|f| f + (1.0 - f) * m5)
            }
        }
    }

    pub(crate) fn validate(&self, model: &'static str) -> Result<(), BrdfError> {
        let bad = |param: &str, value: String, message: &str| {
            Err(BrdfError::BadParameter {
                model: model.into(),
                param: param.into(),
                value,
                message: message.into(),
            })
        };
        match self {
            Fresnel::None => Ok(()),
            Fresnel::Dielectric { eta } => {
                if eta.is_finite() && *eta > 0.0 && *eta <= 100.0 {
                    Ok(())
                } else {
                    bad("fresnel.eta", eta.to_string(), "valid range is 0 < eta ≤ 100")
                }
            }
            Fresnel::Conductor { eta, k } => {
                if !eta.iter().all(|e| e.is_finite() && *e > 0.0 && *e <= 100.0) {
                    return bad("fresnel.eta", format!("{eta:?}"), "each channel must be in (0, 100]");
                }
                if !k.iter().all(|e| e.is_finite() && *e >= 0.0 && *e <= 100.0) {
                    return bad("fresnel.k", format!("{k:?}"), "each channel must be in [0, 100]");
                }
                Ok(())
            }
            Fresnel::Schlick { f0 } => {
                if f0.iter().all(|e| e.is_finite() && (0.0..=1.0).contains(e)) {
                    Ok(())
                } else {
                    bad("fresnel.f0", format!("{f0:?}"), "each channel must be in [0, 1]")
                }
            }
        }
    }
}

/// Unpolarized dielectric Fresnel reflectance (Cook-Torrance form):
/// `c = cos θ_i`, `g = √(η² + c² − 1)`,
/// `F = ½ ((g−c)/(g+c))² (1 + ((c(g+c)−1)/(c(g−c)+1))²)`.
///
/// `eta` = n₂/n₁ (transmitted over incident side). `cos_i < 0` means the light arrives from
/// the other side: η is inverted. `g² < 0` is total internal reflection: `F = 1`.
/// `eta = 1` (index matched) gives 0.
#[inline]
pub fn dielectric(cos_i: f64, eta: f64) -> f64 {
    let (c, eta) = if cos_i < 0.0 {
        ((-cos_i).min(1.0), 1.0 / eta)
    } else {
        (cos_i.min(1.0), eta)
    };
    if eta == 1.0 {
        return 0.0;
    }
    let g2 = eta * eta + c * c - 1.0;
    if g2 <= 0.0 {
        // Total internal reflection (and the degenerate grazing limit for η < 1).
        return 1.0;
    }
    let g = g2.sqrt();
    let a = (g - c) / (g + c);
    let b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0);
    (0.5 * a * a * (1.0 + b * b)).clamp(0.0, 1.0)
}

/// Unpolarized conductor Fresnel reflectance for the complex relative index `eta + i k`
/// (thesis eqs. (20)–(22) with s = t = ½; written with `a² + b² = |ñ² − sin²θ|`,
/// `a = Re √(ñ² − sin²θ)`, as in Moeller, *Optics*):
/// `R_s = (a²+b² − 2a cos θ + cos²θ)/(a²+b² + 2a cos θ + cos²θ)`,
/// `R_p = R_s (a²+b² cos²θ − 2a cos θ sin²θ + sin⁴θ)/(a²+b² cos²θ + 2a cos θ sin²θ + sin⁴θ)`.
/// With `k = 0` this equals [`dielectric`]. Stable for `k` up to 100 and θ → 90°.
#[inline]
pub fn conductor(cos_i: f64, eta: f64, k: f64) -> f64 {
    let c = cos_i.abs().min(1.0);
    let c2 = c * c;
    let s2 = 1.0 - c2;
    let s4 = s2 * s2;
    let t1 = eta * eta - k * k - s2;
    let a2pb2 = (t1 * t1 + 4.0 * eta * eta * k * k).sqrt();
    let a = (0.5 * (a2pb2 + t1)).max(0.0).sqrt();
    let term1 = a2pb2 + c2;
    let term2 = 2.0 * c * a;
    if term1 + term2 <= 0.0 {
        // ñ = 1 at exactly grazing incidence: index matched.
        return 0.0;
    }
    let rs = (term1 - term2) / (term1 + term2);
    let term3 = a2pb2 * c2 + s4;
    let term4 = term2 * s2;
    let rp = rs * (term3 - term4) / (term3 + term4);
    (0.5 * (rs + rp)).clamp(0.0, 1.0)
}

/// Normal-incidence reflectance `((n−1)² + k²)/((n+1)² + k²)`.
pub fn normal_incidence(eta: f64, k: f64) -> f64 {
    ((eta - 1.0).powi(2) + k * k) / ((eta + 1.0).powi(2) + k * k)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Independent reference: Fresnel amplitudes with complex arithmetic,
    /// `r_s = (cos θ − √(ñ² − sin²θ))/(cos θ + √(ñ² − sin²θ))`,
    /// `r_p = (ñ² cos θ − √(ñ² − sin²θ))/(ñ² cos θ + √(ñ² − sin²θ))`.
    fn complex_reference(c: f64, n: f64, k: f64) -> f64 {
        #[derive(Clone, Copy)]
        struct C(f64, f64);
        let add = |a: C, b: C| C(a.0 + b.0, a.1 + b.1);
        let sub = |a: C, b: C| C(a.0 - b.0, a.1 - b.1);
        let mul = |a: C, b: C| C(a.0 * b.0 - a.1 * b.1, a.0 * b.1 + a.1 * b.0);
        let abs2 = |a: C| a.0 * a.0 + a.1 * a.1;
        let sqrt = |a: C| {
            let r = abs2(a).sqrt();
            let re = (0.5 * (r + a.0)).max(0.0).sqrt();
            let im = (0.5 * (r - a.0)).max(0.0).sqrt().copysign(a.1);
            C(re, im)
        };
        let nn = C(n, k);
        let n2 = mul(nn, nn);
        let s2 = 1.0 - c * c;
        let root = sqrt(sub(n2, C(s2, 0.0)));
        let cc = C(c, 0.0);
        let rs = abs2(sub(cc, root)) / abs2(add(cc, root));
        let n2c = mul(n2, cc);
        let rp = abs2(sub(n2c, root)) / abs2(add(n2c, root));
        0.5 * (rs + rp)
    }

    #[test]
    fn normal_incidence_closed_form() {
        for &(n, k) in &[(1.5, 0.0), (0.2, 3.9), (1.1, 2.14), (2.5, 10.0), (0.05, 10.0)] {
            let f = conductor(1.0, n, k);
            let e = normal_incidence(n, k);
            assert!((f - e).abs() < 1e-14, "n={n} k={k}: {f} vs {e}");
        }
        for &n in &[1.01f64, 1.33, 1.5, 2.4, 0.7] {
            let e = ((n - 1.0) / (n + 1.0)).powi(2);
            assert!((dielectric(1.0, n) - e).abs() < 1e-14);
        }
        let s = Fresnel::Schlick { f0: [0.04, 0.5, 1.0] };
        assert_eq!(s.eval(1.0), [0.04, 0.5, 1.0]);
        assert_eq!(s.eval(0.0), [1.0, 1.0, 1.0]);
    }

    #[test]
    fn dielectric_grazing_tends_to_one() {
        for &n in &[1.01, 1.5, 3.0] {
            assert!((dielectric(0.0, n) - 1.0).abs() < 1e-12);
            let f = dielectric((89.99f64).to_radians().cos(), n);
            assert!(f > 0.99 && f <= 1.0, "eta={n}: F(89.99°)={f}");
        }
        for &(n, k) in &[(1.5, 0.0), (0.2, 3.9), (0.05, 10.0)] {
            assert!((conductor(0.0, n, k) - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn total_internal_reflection_gives_one() {
        // From glass (n = 1.5) into air: η = 1/1.5, critical angle asin(1/1.5) = 41.8°.
        let eta: f64 = 1.0 / 1.5;
        let crit = eta.asin();
        for &deg in &[42.0f64, 60.0, 89.99] {
            assert_eq!(dielectric(deg.to_radians().cos(), eta), 1.0, "θ={deg}");
        }
        assert!(dielectric((crit - 0.01).cos(), eta) < 1.0);
        // Light arriving from the back side (cos < 0) of an η = 1.5 interface is the same case.
        assert_eq!(dielectric(-(60.0f64).to_radians().cos(), 1.5), 1.0);
        // The conductor formula with k = 0 handles TIR too.
        assert!((conductor((60.0f64).to_radians().cos(), eta, 0.0) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn index_matched_is_zero() {
        assert_eq!(dielectric(0.3, 1.0), 0.0);
        assert_eq!(dielectric(0.0, 1.0), 0.0);
        assert_eq!(conductor(0.0, 1.0, 0.0), 0.0);
    }

    proptest! {
        #[test]
        fn conductor_matches_complex_reference(c in 0.0f64..=1.0, n in 0.01f64..10.0, k in 0.0f64..10.0) {
            let f = conductor(c, n, k);
            let r = complex_reference(c, n, k);
            prop_assert!((f - r).abs() < 1e-10, "c={} n={} k={}: {} vs {}", c, n, k, f, r);
            prop_assert!((0.0..=1.0).contains(&f));
        }

        #[test]
        fn dielectric_matches_conductor_with_k0(c in 0.0f64..=1.0, n in 0.2f64..5.0) {
            prop_assume!((n - 1.0f64).abs() > 1e-6);
            let d = dielectric(c, n);
            let r = conductor(c, n, 0.0);
            prop_assert!((d - r).abs() < 1e-10, "c={} n={}: {} vs {}", c, n, d, r);
            prop_assert!((0.0..=1.0).contains(&d));
        }

        #[test]
        fn schlick_bounded_and_monotone(c in 0.0f64..=1.0, f0 in 0.0f64..=1.0) {
            let s = Fresnel::Schlick { f0: [f0; 3] };
            let a = s.eval(c)[0];
            let b = s.eval((c - 0.01).max(0.0))[0];
            prop_assert!((f0..=1.0).contains(&a));
            prop_assert!(b >= a);
        }
    }
}
