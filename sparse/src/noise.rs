//! A sensor's noise in the prior's value space, per measured pair.
//!
//! A camera's reading `x` (linear, normalised) has a variance `v(x)` that grows with the
//! signal (shot noise) on top of a floor (read noise, quantisation): the caller's sensor
//! model gives it (`gonio_devices::hdr::SensorNoise::variance`; this crate depends on
//! nothing of ours, so it takes a function). The MAP works in the prior's value space,
//! where [`ValueSpace::Gamma`] stretches the dark end: by the delta method the model-space
//! variance is `g'(x)² v(x)` with `g'(x) = x^(1/2.2 − 1) / 2.2`. That derivative is
//! unbounded at 0, where the delta method no longer holds (the noise is larger than the
//! signal), so it is taken at `max(x, √v(x))`: a reading at or below its own noise counts
//! as a reading of one noise's height, which keeps black pixels finite and close to the
//! spread of `g(max(x + n, 0))` they really have.
//!
//! The MAP's weights are shared by every texel of a pair (one factorization per design),
//! so a pair's noise is the mean over its readings: the pair's typical noise, not one
//! texel's.

use crate::ValueSpace;

/// Model-space variance of a reading whose linear value is `x` and linear variance `v`.
pub fn model_var(space: ValueSpace, x: f64, v: f64) -> f64 {
    let v = if v.is_finite() { v.max(0.0) } else { 0.0 };
    match space {
        ValueSpace::Linear => v,
        ValueSpace::Gamma => {
            let x = if x.is_finite() { x.max(0.0) } else { 0.0 };
            let at = x.max(v.sqrt());
            if at <= 0.0 {
                return 0.0;
            }
            let d = at.powf(1.0 / 2.2 - 1.0) / 2.2;
            d * d * v
        }
    }
}

/// The measurement noise of one pair in model space: the mean of [`model_var`] over its
/// readings (every texel and channel of the pair's image), with `linear_var` the sensor's
/// variance of a linear reading. An empty image has no noise to report (0).
pub fn pair_noise(space: ValueSpace, readings: &[f32], linear_var: impl Fn(f64) -> f64) -> f64 {
    if readings.is_empty() {
        return 0.0;
    }
    let sum: f64 = readings
        .iter()
        .map(|&r| {
            let x = r as f64;
            model_var(space, x, linear_var(x.max(0.0)))
        })
        .sum();
    sum / readings.len() as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Shot noise of 20 000 e⁻ full well, 4 e⁻ read noise, 16 bits (the default camera).
    fn sensor(x: f64) -> f64 {
        let k = 1.0 / 20000.0;
        x.max(0.0) * k + (4.0 * k) * (4.0 * k) + 1.0 / (12.0 * 65535.0f64.powi(2))
    }

    /// The delta method matches a Monte-Carlo estimate where it holds (bright readings),
    /// and black stays finite and of the order of the real spread of `g(max(n, 0))`.
    #[test]
    fn gamma_variance_follows_the_curve_and_stays_finite_at_black() {
        let g = |x: f64| x.max(0.0).powf(1.0 / 2.2);
        let mut rng = crate::Normal::new(7);
        for &x in &[0.0, 1e-4, 0.01, 0.2, 0.9] {
            let v = sensor(x);
            let n = 20000;
            let draws: Vec<f64> = (0..n).map(|_| g(x + v.sqrt() * rng.sample())).collect();
            let mean = draws.iter().sum::<f64>() / n as f64;
            let mc = draws.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / n as f64;
            let ours = model_var(ValueSpace::Gamma, x, v);
            assert!(ours.is_finite() && ours > 0.0, "x = {x}: {ours}");
            let ratio = ours / mc;
            let tol = if x >= 0.01 { 1.2 } else { 4.0 };
            assert!(
                ratio < tol && ratio > 1.0 / tol,
                "x = {x}: model {ours:.3e} vs Monte Carlo {mc:.3e}"
            );
        }
        assert_eq!(model_var(ValueSpace::Linear, 0.3, 2e-5), 2e-5);
        assert_eq!(model_var(ValueSpace::Gamma, 0.0, 0.0), 0.0);
        assert!(model_var(ValueSpace::Gamma, f64::NAN, f64::NAN) == 0.0);
    }

    /// A pair's noise is the mean over its readings; dark pairs are noisier in gamma space.
    #[test]
    fn dark_pairs_are_noisier_in_gamma_space() {
        let dark = pair_noise(ValueSpace::Gamma, &[0.001; 12], sensor);
        let bright = pair_noise(ValueSpace::Gamma, &[0.5; 12], sensor);
        assert!(dark > 3.0 * bright, "dark {dark:.3e} bright {bright:.3e}");
        assert_eq!(pair_noise(ValueSpace::Gamma, &[], sensor), 0.0);
        let mixed = pair_noise(ValueSpace::Gamma, &[0.001, 0.5], sensor);
        assert!((mixed - (dark + bright) / 2.0).abs() < 1e-15);
    }
}
