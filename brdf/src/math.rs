//! Numerical helpers shared by the BRDF models: overflow-free powers, the error function and
//! its inverse (f64 accurate), Gauss-Legendre nodes, and small vector helpers.

use gonio_devices::Vec3;

/// `1/√π`.
pub(crate) const INV_SQRT_PI: f64 = 0.564_189_583_547_756_3;

/// `max(0, c)^n` computed as `exp(n ln c)`: no overflow or `powf` trouble for exponents up to
/// 1e7 and more. `0^0` is taken as 0 (a lobe with exponent 0 is still cut at `c ≤ 0`).
#[inline]
pub(crate) fn pow_pos(c: f64, n: f64) -> f64 {
    if c > 0.0 {
        (n * c.ln()).exp()
    } else {
        0.0
    }
}

/// Mirror direction of `w` about the normal +z.
#[inline]
pub(crate) fn reflect_z(w: Vec3) -> Vec3 {
    Vec3::new(-w.x, -w.y, w.z)
}

/// Unit half vector `(l+v)/|l+v|`, or `None` when `l + v` (numerically) vanishes.
#[inline]
pub(crate) fn half_vector(l: Vec3, v: Vec3) -> Option<Vec3> {
    let s = l + v;
    let n2 = s.dot(s);
    if n2 > 1e-300 && n2.is_finite() {
        Some(s * (1.0 / n2.sqrt()))
    } else {
        None
    }
}

/// Error function, absolute error ≲ 1e-15 everywhere.
pub(crate) fn erf(x: f64) -> f64 {
    if x.is_nan() {
        return x;
    }
    let a = x.abs();
    let r = if a < 3.0 { erf_series(a) } else { 1.0 - erfc_cf(a) };
    r.copysign(x)
}

/// Complementary error function, relative accuracy ~1e-14 for x ≥ 3 (continued fraction),
/// absolute ≲ 1e-15 below.
pub(crate) fn erfc(x: f64) -> f64 {
    if x.is_nan() {
        return x;
    }
    if x < 0.0 {
        return 2.0 - erfc(-x);
    }
    if x < 3.0 {
        1.0 - erf_series(x)
    } else {
        erfc_cf(x)
    }
}

/// `2/(2k+1)` for the series below (multiplications instead of divisions).
const TWO_OVER_ODD: [f64; 96] = {
    let mut t = [0.0; 96];
    let mut k = 0;
    while k < 96 {
        t[k] = 2.0 / (2 * k + 1) as f64;
        k += 1;
    }
    t
};

/// Fast complementary error function for x ≥ 0 (Chebyshev fit, Numerical Recipes
/// `erfcc`): relative error < 1.2e-7 everywhere (tested against [`erfc`]). Used for the
/// Beckmann Smith Λ, where it bounds the error of `G1` to ~1e-7 at a fraction of the cost.
#[inline]
pub(crate) fn erfc_fast(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let p = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98 + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let r = t * p.exp();
    if x >= 0.0 {
        r
    } else {
        2.0 - r
    }
}

/// `erf(x) = 2x e^{-x²}/√π Σ (2x²)^k / (2k+1)!!` for 0 ≤ x < 3: all terms positive, no
/// cancellation; at most ~70 terms.
fn erf_series(x: f64) -> f64 {
    let x2 = x * x;
    let mut term = x;
    let mut sum = x;
    for c in &TWO_OVER_ODD[1..] {
        term *= x2 * c;
        sum += term;
        if term < sum * 1e-17 {
            break;
        }
    }
    2.0 * INV_SQRT_PI * (-x2).exp() * sum
}

/// `erfc(x)` for x ≥ 3 by the Laplace continued fraction
/// `erfc(x) = e^{-x²}/√π · 1/(x + (1/2)/(x + 1/(x + (3/2)/(x + …))))`, evaluated bottom-up.
fn erfc_cf(x: f64) -> f64 {
    if x > 27.3 {
        return 0.0;
    }
    let mut t = x;
    for k in (1..=60).rev() {
        t = x + (k as f64 * 0.5) / t;
    }
    INV_SQRT_PI * (-x * x).exp() / t
}

/// Inverse error function on (-1, 1): Giles' approximation refined by two Newton steps on
/// `erf` (or on `erfc` near ±1). Returns ±∞ at ±1 and NaN outside.
pub(crate) fn erfinv(y: f64) -> f64 {
    if !(-1.0..=1.0).contains(&y) {
        return f64::NAN;
    }
    if y == 1.0 {
        return f64::INFINITY;
    }
    if y == -1.0 {
        return f64::NEG_INFINITY;
    }
    let mut w = -((1.0 - y) * (1.0 + y)).ln();
    let p = if w < 5.0 {
        w -= 2.5;
        let mut p = 2.810_226_36e-08;
        p = 3.432_739_39e-07 + p * w;
        p = -3.523_387_7e-06 + p * w;
        p = -4.391_506_54e-06 + p * w;
        p = 0.000_218_580_87 + p * w;
        p = -0.001_253_725_03 + p * w;
        p = -0.004_177_681_64 + p * w;
        p = 0.246_640_727 + p * w;
        1.501_409_41 + p * w
    } else {
        w = w.sqrt() - 3.0;
        let mut p = -0.000_200_214_257;
        p = 0.000_100_950_558 + p * w;
        p = 0.001_349_343_22 + p * w;
        p = -0.003_673_428_44 + p * w;
        p = 0.005_739_507_73 + p * w;
        p = -0.007_622_461_3 + p * w;
        p = 0.009_438_870_47 + p * w;
        p = 1.001_674_06 + p * w;
        2.832_976_82 + p * w
    };
    let mut x = p * y;
    // Newton on erf (|y| ≤ 0.5) or on erfc of |x| (tails, no cancellation).
    for _ in 0..2 {
        let deriv = 2.0 * INV_SQRT_PI * (-x * x).exp();
        if deriv <= 0.0 || !deriv.is_finite() {
            break;
        }
        let resid = if y.abs() <= 0.5 {
            erf(x) - y
        } else {
            // erf(x) - y = (1 - y) - erfc(x) for y > 0; mirrored for y < 0.
            let s = y.signum();
            s * ((1.0 - y.abs()) - erfc(x.abs()))
        };
        x -= resid / deriv;
    }
    x
}

/// Gauss-Legendre nodes and weights on [-1, 1] (weights sum to 2), by Newton iteration on
/// the Legendre recurrence.
pub(crate) fn gauss_legendre(n: usize) -> (Vec<f64>, Vec<f64>) {
    assert!(n >= 1);
    let mut nodes = vec![0.0; n];
    let mut weights = vec![0.0; n];
    for i in 0..n.div_ceil(2) {
        let mut x = -(std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        let mut dp = 1.0;
        for _ in 0..100 {
            let (p, d) = legendre_pd(n, x);
            dp = d;
            let step = p / d;
            x -= step;
            if step.abs() <= 4.0 * x.abs().max(1e-300) * f64::EPSILON {
                break;
            }
        }
        let (_, d) = legendre_pd(n, x);
        if d.is_finite() {
            dp = d;
        }
        let w = 2.0 / ((1.0 - x * x) * dp * dp);
        nodes[i] = x;
        nodes[n - 1 - i] = -x;
        weights[i] = w;
        weights[n - 1 - i] = w;
    }
    if n % 2 == 1 {
        nodes[n / 2] = 0.0;
    }
    (nodes, weights)
}

/// Legendre polynomial `P_n(x)` and its derivative.
fn legendre_pd(n: usize, x: f64) -> (f64, f64) {
    let (mut p0, mut p1) = (1.0, x);
    if n == 0 {
        return (1.0, 0.0);
    }
    for k in 2..=n {
        let k = k as f64;
        let p2 = ((2.0 * k - 1.0) * x * p1 - (k - 1.0) * p0) / k;
        p0 = p1;
        p1 = p2;
    }
    let d = n as f64 * (x * p1 - p0) / (x * x - 1.0);
    (p1, d)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn erf_reference_values() {
        // Reference values (Abramowitz & Stegun table 7.1 / high-precision tables).
        let refs = [
            (0.1, 0.112_462_916_018_284_9),
            (0.5, 0.520_499_877_813_046_5),
            (1.0, 0.842_700_792_949_714_9),
            (2.0, 0.995_322_265_018_952_7),
            (2.9, 0.999_958_902_121_900_5),
            (3.5, 0.999_999_256_901_627_6),
        ];
        for (x, e) in refs {
            assert!((erf(x) - e).abs() < 2e-15, "erf({x}) = {} vs {e}", erf(x));
            assert!((erf(-x) + e).abs() < 2e-15);
        }
        // erfc tail, relative accuracy.
        let tails = [(3.0, 2.209_049_699_858_544e-5), (5.0, 1.537_459_794_428_035e-12)];
        for (x, e) in tails {
            assert!(((erfc(x) - e) / e).abs() < 1e-10, "erfc({x}) = {}", erfc(x));
        }
        assert_eq!(erfc(40.0), 0.0);
    }

    #[test]
    fn erfc_fast_relative_error() {
        let mut worst: f64 = 0.0;
        for i in 0..=2600 {
            let x = i as f64 * 0.01; // 0 … 26
            let e = erfc(x);
            worst = worst.max(((erfc_fast(x) - e) / e).abs());
        }
        assert!(worst < 1.2e-7, "{worst}");
        assert!(((erfc_fast(-1.0) - erfc(-1.0)) / erfc(-1.0)).abs() < 1.2e-7);
    }

    #[test]
    fn erfinv_inverts_erf() {
        for &y in &[-0.999_999, -0.9, -0.5, -1e-3, 0.0, 0.2, 0.7, 0.99, 1.0 - 1e-12] {
            let x = erfinv(y);
            assert!((erf(x) - y).abs() < 1e-14, "y={y} x={x} erf={}", erf(x));
        }
        assert_eq!(erfinv(1.0), f64::INFINITY);
        assert!(erfinv(1.5).is_nan());
    }

    #[test]
    fn gauss_legendre_integrates_polynomials() {
        for n in [1, 2, 5, 32, 128] {
            let (x, w) = gauss_legendre(n);
            let sum: f64 = w.iter().sum();
            assert!((sum - 2.0).abs() < 1e-12, "n={n}");
            // exact for degree 2n-1: ∫ x^(2k) = 2/(2k+1)
            let k = (n - 1).min(20);
            let q: f64 = x.iter().zip(&w).map(|(x, w)| w * x.powi(2 * k as i32)).sum();
            assert!((q - 2.0 / (2 * k + 1) as f64).abs() < 1e-12, "n={n}");
        }
    }

    #[test]
    fn pow_pos_large_exponent() {
        assert_eq!(pow_pos(0.5, 1e6), 0.0);
        assert_eq!(pow_pos(1.0, 1e7), 1.0);
        assert!((pow_pos(1.0 - 1e-7, 1e6) - (-0.1f64).exp()).abs() < 1e-8);
        assert_eq!(pow_pos(-0.3, 2.0), 0.0);
        assert_eq!(pow_pos(0.3, 0.0), 1.0);
    }
}
