//! The noise-optimal merge of one measurement's exposure bracket into a single linear frame.
//!
//! Each exposure `j` of a bracket is first linearised like any frame (raw corrections
//! through the calibrated response when applied, else DN / max DN) and brought to the base
//! exposure's scale (`x_j = linear_j · t_base / t_j`). Per pixel, the merged value is the
//! inverse-variance weighted mean of the exposures that did not saturate there:
//!
//! `x = Σ w_j x_j / Σ w_j`,  `w_j = 1 / Var(x_j) = 1 / (s_j² · σ²(x̂ / s_j))`,  `s_j = t_base / t_j`,
//!
//! with `σ²(u)` the sensor's variance at normalised reading `u` (shot + read +
//! quantisation, [`SensorNoise`]). That is the minimum-variance unbiased combination of
//! independent estimates (Granados et al. 2010; Hasinoff et al. 2010) — not a hat function.
//! The variance is evaluated at the *estimated* signal `x̂`, never at the reading itself
//! (weights from the noisy readings favour the readings that came out low and bias the
//! merge): `x̂` starts as the longest valid exposure's value and is refined once.
//!
//! Per pixel: an exposure whose pixel is at or above the saturation code (any channel, as
//! raw corrections treat a clipped pixel as neutral) does not contribute. A pixel saturated
//! in every exposure keeps the shortest exposure's value — a lower bound — and is counted
//! as `clipped`; a pixel that reads 0 in every valid exposure is counted as `black`. Both
//! are written into the measurement's record, never hidden.

use gonio_devices::hdr::SensorNoise;
use gonio_devices::image::RgbImage;
use gonio_devices::Frame;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// One exposure of a bracket, linearised.
pub struct Layer<'a> {
    /// Linear values (DN / max DN or through the raw corrections) at this exposure.
    pub linear: RgbImage,
    /// The raw frame (its DN decide saturation; its `meta.exposure` the scale).
    pub frame: &'a Frame,
    /// DN at and above which a value is saturated.
    pub saturation_code: u16,
}

/// What a merge did: written into the measurement's record (`extra.hdr`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MergeReport {
    /// Exposure times (s) as the camera applied them, in capture order.
    pub exposures_s: Vec<f64>,
    /// Pixels each exposure contributed to (same order).
    pub pixels_contributed: Vec<usize>,
    /// Pixels saturated in every exposure (their value is a lower bound).
    pub clipped_pixels: usize,
    /// Pixels that read 0 in every unsaturated exposure.
    pub black_pixels: usize,
    /// Brightest / darkest non-zero merged value of the unclipped pixels, in stops (log2).
    pub dynamic_range_stops: f64,
}

/// Merge `layers` (base exposure `base_exposure_s`) under `noise`; values come out on the
/// base exposure's scale (1.0 = the base exposure's full scale).
pub fn merge(layers: &[Layer<'_>], base_exposure_s: f64, noise: &SensorNoise) -> (RgbImage, MergeReport) {
    let (w, h) = (layers[0].linear.width, layers[0].linear.height);
    let scales: Vec<f64> = layers
        .iter()
        .map(|l| base_exposure_s / l.frame.meta.exposure.max(1e-15))
        .collect();
    // Longest exposure first: the first valid one is the best initial estimate.
    let mut order: Vec<usize> = (0..layers.len()).collect();
    order.sort_by(|&a, &b| scales[a].total_cmp(&scales[b]).then(a.cmp(&b)));
    let mut out = RgbImage {
        width: w,
        height: h,
        data: vec![0.0; w * h * 3],
    };
    let n = layers.len();
    /// Per-chunk tallies: contributions per layer, clipped, black, min, max.
    #[derive(Clone)]
    struct Tally {
        contributed: Vec<usize>,
        clipped: usize,
        black: usize,
        lo: f64,
        hi: f64,
    }
    let empty = Tally {
        contributed: vec![0; n],
        clipped: 0,
        black: 0,
        lo: f64::INFINITY,
        hi: 0.0,
    };
    let rows: Vec<Tally> = out
        .data
        .par_chunks_mut(w * 3)
        .enumerate()
        .map(|(y, row)| {
            let mut t = empty.clone();
            let mut valid = vec![false; n];
            for x in 0..w {
                let p = (y * w + x) * 3;
                for (j, l) in layers.iter().enumerate() {
                    valid[j] = l.frame.data[p..p + 3].iter().all(|&v| v < l.saturation_code);
                }
                let Some(&first) = order.iter().find(|&&j| valid[j]) else {
                    // Saturated everywhere: the shortest exposure's value, a lower bound.
                    let j = *order.last().expect("a bracket has an exposure");
                    for c in 0..3 {
                        row[x * 3 + c] = (layers[j].linear.data[p + c] as f64 * scales[j]) as f32;
                    }
                    t.clipped += 1;
                    continue;
                };
                let mut all_zero = true;
                for c in 0..3 {
                    let mut est = layers[first].linear.data[p + c] as f64 * scales[first];
                    for _ in 0..2 {
                        let (mut num, mut den) = (0.0, 0.0);
                        for j in (0..n).filter(|&j| valid[j]) {
                            let s = scales[j];
                            let wgt = 1.0 / (s * s * noise.variance(est / s));
                            num += wgt * layers[j].linear.data[p + c] as f64 * s;
                            den += wgt;
                        }
                        est = num / den;
                    }
                    all_zero &= est <= 0.0;
                    row[x * 3 + c] = est as f32;
                    if est > 0.0 {
                        t.lo = t.lo.min(est);
                        t.hi = t.hi.max(est);
                    }
                }
                for j in (0..n).filter(|&j| valid[j]) {
                    t.contributed[j] += 1;
                }
                t.black += usize::from(all_zero);
            }
            t
        })
        .collect();
    let mut total = empty;
    for r in rows {
        total
            .contributed
            .iter_mut()
            .zip(&r.contributed)
            .for_each(|(a, b)| *a += b);
        total.clipped += r.clipped;
        total.black += r.black;
        total.lo = total.lo.min(r.lo);
        total.hi = total.hi.max(r.hi);
    }
    let report = MergeReport {
        exposures_s: layers.iter().map(|l| l.frame.meta.exposure).collect(),
        pixels_contributed: total.contributed,
        clipped_pixels: total.clipped,
        black_pixels: total.black,
        dynamic_range_stops: if total.hi > 0.0 && total.lo.is_finite() {
            (total.hi / total.lo).log2()
        } else {
            0.0
        },
    };
    (out, report)
}

/// The inverse-variance weights of readings with variances `var` (normalised to sum 1):
/// the minimum-variance unbiased combination of independent estimates.
pub fn inverse_variance_weights(var: &[f64]) -> Vec<f64> {
    let inv: Vec<f64> = var.iter().map(|v| 1.0 / v).collect();
    let s: f64 = inv.iter().sum();
    inv.iter().map(|w| w / s).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use gonio_devices::FrameMeta;
    use proptest::prelude::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    const MAX: f64 = 4095.0;

    fn noise() -> SensorNoise {
        SensorNoise {
            full_well_e: 20000.0,
            read_noise_e: 4.0,
            gain: 1.0,
            max_dn: MAX,
        }
    }

    /// A frame of a linear 12-bit sensor seeing `radiance` (base-exposure scale) at
    /// `exposure` (base 1.0), with the model's noise when `rng` is given.
    fn expose(radiance: &[f64], exposure: f64, rng: Option<&mut rand_pcg::Pcg64Mcg>) -> (Frame, RgbImage) {
        let n = noise();
        let mut rng = rng;
        let data: Vec<u16> = radiance
            .iter()
            .map(|&x| {
                let u = x * exposure;
                let v = match rng.as_deref_mut() {
                    Some(r) => u + Normal::new(0.0, n.variance(u).sqrt()).unwrap().sample(r),
                    None => u,
                };
                (v * MAX).round().clamp(0.0, MAX) as u16
            })
            .collect();
        let frame = Frame {
            width: radiance.len() / 3,
            height: 1,
            data,
            meta: FrameMeta {
                timestamp: 0.0,
                exposure,
                gain: 1.0,
                sequence: 0,
                bit_depth: 12,
            },
        };
        let linear = RgbImage {
            width: frame.width,
            height: 1,
            data: frame.data.iter().map(|&v| (v as f64 / MAX) as f32).collect(),
        };
        (frame, linear)
    }

    fn merge_bracket(
        radiance: &[f64],
        exposures: &[f64],
        rng: Option<&mut rand_pcg::Pcg64Mcg>,
    ) -> (RgbImage, MergeReport) {
        let mut rng = rng;
        let shots: Vec<(Frame, RgbImage)> = exposures
            .iter()
            .map(|&e| expose(radiance, e, rng.as_deref_mut()))
            .collect();
        let layers: Vec<Layer<'_>> = shots
            .iter()
            .map(|(f, l)| Layer {
                linear: l.clone(),
                frame: f,
                saturation_code: MAX as u16,
            })
            .collect();
        merge(&layers, 1.0, &noise())
    }

    proptest! {
        /// Noise-free: the merge of a linear sensor's bracket returns the scene radiance
        /// (to the quantisation of the longest exposure that did not saturate).
        #[test]
        fn noise_free_merge_returns_radiance(log_x in -8.0f64..9.0, step in 2.0f64..32.0, n in 2usize..6) {
            let x = 2f64.powf(log_x);
            let exposures: Vec<f64> = (0..n).map(|k| step.powi(-(k as i32))).collect();
            let shortest = *exposures.last().unwrap();
            let (img, report) = merge_bracket(&[x, x, x], &exposures, None);
            if x * shortest < (MAX - 0.5) / MAX {
                // Half a DN of quantisation at each unsaturated exposure's scale, averaged
                // with the merge's weights (10 % slack: the weights are evaluated at the
                // estimate, not at x).
                let (mut num, mut den) = (0.0, 0.0);
                for e in exposures.iter().copied().filter(|e| x * e < (MAX - 0.5) / MAX) {
                    let w = e * e / noise().variance(x * e);
                    num += w * 0.5 / MAX / e;
                    den += w;
                }
                let tol = 1.1 * num / den + 1e-6 * x;
                prop_assert!((img.data[0] as f64 - x).abs() <= tol, "x {} merged {} tol {}", x, img.data[0], tol);
                prop_assert_eq!(report.clipped_pixels, 0);
            } else {
                prop_assert_eq!(report.clipped_pixels, 1);
                prop_assert!(img.data[0] as f64 <= x * 1.0001);
            }
        }

        /// Inverse-variance weights are minimum variance: any other normalised weights give
        /// a larger variance of the combination.
        #[test]
        fn weights_are_minimum_variance(v in prop::collection::vec(1e-6f64..1.0, 2..6), d in prop::collection::vec(-0.2f64..0.2, 6)) {
            let w = inverse_variance_weights(&v);
            let var = |w: &[f64]| w.iter().zip(&v).map(|(w, v)| w * w * v).sum::<f64>();
            let best = var(&w);
            let mut other: Vec<f64> = w.iter().zip(&d).map(|(w, d)| (w + d).max(0.0)).collect();
            let s: f64 = other.iter().sum();
            prop_assume!(s > 0.0);
            other.iter_mut().for_each(|x| *x /= s);
            prop_assert!(var(&other) >= best * (1.0 - 1e-12));
        }
    }

    /// Noisy: over many pixels of one radiance, the merge is unbiased and its spread is the
    /// predicted minimum variance 1 / Σ w — below the best single exposure's.
    #[test]
    fn noisy_merge_is_unbiased_with_the_predicted_variance() {
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(7);
        let n = noise();
        for &x in &[0.02, 0.3, 3.0] {
            let exposures = [1.0, 0.25, 1.0 / 16.0];
            let radiance = vec![x; 3 * 20000];
            let (img, report) = merge_bracket(&radiance, &exposures, Some(&mut rng));
            let vals: Vec<f64> = img.data.iter().map(|&v| v as f64).collect();
            let mean = vals.iter().sum::<f64>() / vals.len() as f64;
            let var = vals.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (vals.len() - 1) as f64;
            let valid: Vec<f64> = exposures.iter().copied().filter(|e| x * e < 0.95).collect();
            let predicted = 1.0 / valid.iter().map(|e| 1.0 / (n.variance(x * e) / (e * e))).sum::<f64>();
            let single = valid
                .iter()
                .map(|e| n.variance(x * e) / (e * e))
                .fold(f64::INFINITY, f64::min);
            assert!(
                (mean - x).abs() < 4.0 * (predicted / vals.len() as f64).sqrt() + 1e-4 * x,
                "x {x}: mean {mean}"
            );
            assert!(
                (var / predicted - 1.0).abs() < 0.1,
                "x {x}: variance {var} vs predicted {predicted}"
            );
            assert!(
                var <= single * 1.02,
                "x {x}: merged variance {var} above the best single {single}"
            );
            assert_eq!(report.clipped_pixels, 0);
            assert_eq!(report.pixels_contributed.len(), 3);
        }
    }

    /// A pixel saturated in every exposure keeps the shortest one's value and is counted;
    /// a black one is counted too.
    #[test]
    fn clipped_and_black_pixels_are_counted() {
        let (img, r) = merge_bracket(&[1e6, 1e6, 1e6, 0.0, 0.0, 0.0, 0.5, 0.5, 0.5], &[1.0, 0.125], None);
        assert_eq!((r.clipped_pixels, r.black_pixels), (1, 1));
        assert!((img.data[0] - 8.0).abs() < 1e-3, "lower bound {}", img.data[0]);
        // Exposure 1: the black and the mid pixel; 1/8: the same (the bright one saturates in both).
        assert_eq!(r.pixels_contributed, vec![2, 2]);
        assert!((img.data[6] - 0.5).abs() < 1e-3);
    }

    /// Through a non-linear (calibrated) response: the inversion is monotone up to both
    /// ends of the curve, so a ramp of radiances spanning beyond either end merges to a
    /// non-decreasing ramp.
    #[test]
    fn response_inversion_is_monotone_at_the_curve_ends() {
        use gonio_calibration::radiometric::ResponseCurve;
        // A compressive camera response y = u^(1/2.2); g = ln(exposure) at each level.
        let levels = 256;
        let g: Vec<f64> = (0..levels)
            .map(|z| {
                let y = (z as f64 / (levels - 1) as f64).max(0.5 / (levels - 1) as f64);
                y.powf(2.2).ln()
            })
            .collect();
        let mut curve = ResponseCurve::linear(MAX, levels);
        curve.g = [g.clone(), g.clone(), g];
        let mut prev = 0.0;
        for dn in 0..=MAX as u32 {
            let e = curve.exposure_of(0, dn as f64);
            assert!(e.is_finite() && e >= prev, "dn {dn}: {e} after {prev}");
            prev = e;
        }
        let max_lin = curve.exposure_of(0, MAX);
        let ramp: Vec<f64> = (0..300).map(|i| 2f64.powf(-14.0 + i as f64 * 0.07)).collect();
        let exposures = [1.0, 1.0 / 8.0, 1.0 / 64.0];
        let shots: Vec<Frame> = exposures
            .iter()
            .map(|&e| {
                let data = ramp
                    .iter()
                    .flat_map(|&x| {
                        let u = (x * e).min(1.0);
                        let dn = (u.powf(1.0 / 2.2) * MAX).round() as u16;
                        [dn; 3]
                    })
                    .collect();
                Frame {
                    width: ramp.len(),
                    height: 1,
                    data,
                    meta: FrameMeta {
                        timestamp: 0.0,
                        exposure: e,
                        gain: 1.0,
                        sequence: 0,
                        bit_depth: 12,
                    },
                }
            })
            .collect();
        let layers: Vec<Layer<'_>> = shots
            .iter()
            .map(|f| Layer {
                linear: RgbImage {
                    width: f.width,
                    height: 1,
                    data: f
                        .data
                        .iter()
                        .map(|&v| (curve.exposure_of(0, v as f64) / max_lin) as f32)
                        .collect(),
                },
                frame: f,
                saturation_code: MAX as u16,
            })
            .collect();
        let (img, _) = merge(&layers, 1.0, &noise());
        let merged: Vec<f32> = img.data.chunks(3).map(|p| p[0]).collect();
        for (i, pair) in merged.windows(2).enumerate() {
            assert!(pair[1] >= pair[0], "ramp {i}: {} then {}", pair[0], pair[1]);
        }
        // Mid-ramp values come back to within the curve's quantisation (a few %).
        for (i, &x) in ramp.iter().enumerate().filter(|(_, &x)| (0.01..30.0).contains(&x)) {
            assert!((merged[i] as f64 / x - 1.0).abs() < 0.05, "x {x}: merged {}", merged[i]);
        }
    }
}
