//! The camera sensor model: radiance → electrons → digital numbers.
//!
//! `e = L · exposure · sensitivity · vignetting + dark_current · exposure`, then photon
//! shot noise (Poisson; Gaussian above 30 e⁻ where the two agree), read noise (Gaussian),
//! clipping at the full well, conversion with `gain · (2^bits − 1) / full_well` DN per e⁻,
//! rounding and clipping to the ADC range.
//!
//! Opt-in ([`SensorResponse`], rig file `camera.options.response_compression` and
//! `crosstalk`): a 3 × 3 colour crosstalk on the radiance and a non-linear response on the
//! normalised signal just before the ADC — what radiometric calibration has to undo. The
//! default camera is linear and colour-clean and does not pay for either.
//!
//! A noiseless sensor draws no random numbers at all. Noise is seeded per frame and row
//! from (seed, frame sequence, row), so a frame is reproducible whatever the thread count.

use crate::noise::mix64;
use gonio_devices::image::RgbImage;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64Mcg;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SensorModel {
    pub full_well_e: f64,
    pub read_noise_e: f64,
    pub dark_current_e_s: f64,
    /// Electrons per (W m⁻² sr⁻¹ · s) at a pixel: lens aperture, pixel area and QE in one.
    pub sensitivity_e_per_radiance_s: f64,
    /// Relative fall-off at the image corners: factor `1 − v · r²/r_corner²`.
    pub vignetting: f64,
    pub bit_depth: u32,
    pub gain: f64,
    pub exposure_s: f64,
    /// Draw shot, read and dark noise; false gives the expected value, rounded.
    pub noise: bool,
    pub seed: u64,
}

impl SensorModel {
    pub fn max_dn(&self) -> f64 {
        ((1u64 << self.bit_depth) - 1) as f64
    }

    /// DN per electron.
    fn conversion(&self) -> f64 {
        self.gain * self.max_dn() / self.full_well_e
    }

    /// Expected normalised signal (DN / max DN, not clipped) for a radiance, without
    /// vignetting, noise or dark current: the scale of the ground truth.
    pub fn expected_normalized(&self, radiance: f64) -> f64 {
        radiance * self.exposure_s * self.sensitivity_e_per_radiance_s * self.gain / self.full_well_e
    }

    /// Ground-truth image in normalised units from a radiance image.
    pub fn normalize_truth(&self, radiance: &RgbImage) -> RgbImage {
        let k = self.expected_normalized(1.0) as f32;
        RgbImage {
            width: radiance.width,
            height: radiance.height,
            data: radiance.data.iter().map(|v| v * k).collect(),
        }
    }

    /// Convert a radiance image into a frame of DN values.
    pub fn expose(&self, radiance: &RgbImage, sequence: u64) -> Vec<u16> {
        self.expose_roi(radiance, sequence, (0, 0, radiance.width, radiance.height))
    }

    /// Like [`expose`](Self::expose) but reading out only the region of interest
    /// `[x0, x1) × [y0, y1)`; pixels outside it are not read (0), as with a camera's ROI
    /// readout. Noise is reproducible for the same (seed, sequence, ROI).
    pub fn expose_roi(&self, radiance: &RgbImage, sequence: u64, roi: (usize, usize, usize, usize)) -> Vec<u16> {
        let (conv, max_dn, full) = (self.conversion(), self.max_dn(), self.full_well_e);
        // x ≥ 0 is rounded by adding ½ and truncating (libm's round is slow).
        self.expose_with(radiance, sequence, roi, move |e: f64| {
            ((e.min(full) * conv).clamp(0.0, max_dn) + 0.5) as u16
        })
    }

    /// Like [`expose_roi`](Self::expose_roi) through a non-linear camera: `response` maps
    /// the normalised linear signal (DN / max DN before the ADC) to the ADC's input and
    /// `response.crosstalk` mixes the colour channels of the radiance first. A separate
    /// entry point, so a linear colour-clean camera (the default) pays nothing for it.
    pub fn expose_roi_response(
        &self,
        radiance: &RgbImage,
        sequence: u64,
        roi: (usize, usize, usize, usize),
        response: &SensorResponse,
    ) -> Vec<u16> {
        let mixed;
        let radiance = match &response.crosstalk {
            Some(m) => {
                mixed = apply_crosstalk(radiance, m);
                &mixed
            }
            None => radiance,
        };
        let (conv, max_dn, full) = (self.conversion(), self.max_dn(), self.full_well_e);
        let r = response.clone();
        self.expose_with(radiance, sequence, roi, move |e: f64| {
            let u = (e.min(full) * conv / max_dn).clamp(0.0, 1.0);
            (r.curve(u) * max_dn + 0.5) as u16
        })
    }

    fn expose_with<F: Fn(f64) -> u16 + Sync>(
        &self,
        radiance: &RgbImage,
        sequence: u64,
        roi: (usize, usize, usize, usize),
        to_dn: F,
    ) -> Vec<u16> {
        let (rx0, ry0, rx1, ry1) = (roi.0, roi.1, roi.2.min(radiance.width), roi.3.min(radiance.height));
        let (w, h) = (radiance.width, radiance.height);
        let mut out = vec![0u16; w * h * 3];
        let k = self.exposure_s * self.sensitivity_e_per_radiance_s;
        let dark = self.dark_current_e_s * self.exposure_s;
        let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
        let r2_corner = cx * cx + cy * cy;
        let read_sd = self.read_noise_e.max(0.0);
        let read_var = read_sd * read_sd;
        // Pixels with no signal (most of a frame: the background) all have the same
        // Poisson mean; its exp(−mean) is computed once.
        let dark_limit = (-dark).exp();
        out.par_chunks_mut(w * 3).enumerate().for_each(|(row, dst)| {
            if row < ry0 || row >= ry1 {
                return;
            }
            let src = &radiance.data[row * w * 3..(row + 1) * w * 3];
            let dy = row as f64 + 0.5 - cy;
            let vig_row = self.vignetting * dy * dy / r2_corner;
            let to_dn = &to_dn;
            if !self.noise {
                for col in rx0..rx1 {
                    let dx = col as f64 + 0.5 - cx;
                    let vig = 1.0 - vig_row - self.vignetting * dx * dx / r2_corner;
                    for c in 0..3 {
                        dst[col * 3 + c] = to_dn(src[col * 3 + c] as f64 * k * vig + dark);
                    }
                }
                return;
            }
            let mut rng = Pcg64Mcg::seed_from_u64(mix64(self.seed ^ mix64(sequence.wrapping_mul(0x9E37) ^ row as u64)));
            for col in rx0..rx1 {
                let dx = col as f64 + 0.5 - cx;
                let vig = 1.0 - vig_row - self.vignetting * dx * dx / r2_corner;
                for c in 0..3 {
                    let l = src[col * 3 + c] as f64;
                    let z: f64 = rng.sample(rand_distr::StandardNormal);
                    let e = if l <= 0.0 && dark >= 30.0 {
                        // Long exposures: Knuth's product would underflow (≈ 745 draws, a
                        // wrong count); Poisson ≈ Gaussian here as for lit pixels.
                        dark + (dark + read_var).sqrt() * z
                    } else if l <= 0.0 {
                        poisson_with_limit(&mut rng, dark_limit) + read_sd * z
                    } else {
                        let mean = l * k * vig + dark;
                        if mean >= 30.0 {
                            // shot (Poisson ≈ Gaussian here) and read noise in one draw
                            mean + (mean + read_var).sqrt() * z
                        } else {
                            small_poisson(&mut rng, mean) + read_sd * z
                        }
                    };
                    dst[col * 3 + c] = to_dn(e);
                }
            }
        });
        out
    }
}

/// The opt-in non-linearity of a simulated camera (rig file `camera.options`
/// `response_compression` and `crosstalk`): what radiometric calibration must undo.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SensorResponse {
    /// `a` of the response `f(u) = (1 − e^{−a·u}) / (1 − e^{−a})` applied to the normalised
    /// linear signal `u ∈ [0, 1]` before the ADC: a smooth, film-like compression of the
    /// highlights (slope `a / (1 − e^{−a})` at black, `a·e^{−a} / (1 − e^{−a})` at white).
    /// 0 = linear.
    pub compression: f64,
    /// Colour crosstalk: the camera's RGB radiance is `crosstalk · [R, G, B]` (rows: camera
    /// channels). `None` = colour-clean.
    pub crosstalk: Option<[[f64; 3]; 3]>,
}

impl SensorResponse {
    /// The response `f(u)` (normalised in and out).
    #[inline]
    pub fn curve(&self, u: f64) -> f64 {
        let a = self.compression;
        if a <= 1e-9 {
            return u;
        }
        (1.0 - (-a * u).exp()) / (1.0 - (-a).exp())
    }

    /// The inverse `f⁻¹(y)`: the truth a recovered response curve is compared with.
    pub fn inverse(&self, y: f64) -> f64 {
        let a = self.compression;
        if a <= 1e-9 {
            return y;
        }
        -(1.0 - y.clamp(0.0, 1.0) * (1.0 - (-a).exp())).ln() / a
    }
}

/// `m · rgb` for every pixel.
pub fn apply_crosstalk(radiance: &RgbImage, m: &[[f64; 3]; 3]) -> RgbImage {
    let mut data = radiance.data.clone();
    for px in data.chunks_exact_mut(3) {
        let v = [px[0] as f64, px[1] as f64, px[2] as f64];
        for (c, row) in m.iter().enumerate() {
            px[c] = (row[0] * v[0] + row[1] * v[1] + row[2] * v[2]) as f32;
        }
    }
    RgbImage {
        width: radiance.width,
        height: radiance.height,
        data,
    }
}

/// Poisson sample for a small mean (< 30) by Knuth's product of uniforms: about
/// `mean + 1` uniform draws, no set-up cost (dark pixels are most of a frame).
fn small_poisson<R: Rng>(rng: &mut R, mean: f64) -> f64 {
    if mean <= 0.0 {
        return 0.0;
    }
    poisson_with_limit(rng, (-mean).exp())
}

/// Knuth's method with `limit = exp(−mean)` given.
fn poisson_with_limit<R: Rng>(rng: &mut R, limit: f64) -> f64 {
    if limit >= 1.0 {
        return 0.0;
    }
    let mut k = 0u32;
    let mut p: f64 = rng.random();
    while p > limit {
        k += 1;
        p *= rng.random::<f64>();
    }
    k as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model(noise: bool) -> SensorModel {
        SensorModel {
            full_well_e: 20000.0,
            read_noise_e: 4.0,
            dark_current_e_s: 0.0,
            sensitivity_e_per_radiance_s: 1000.0,
            vignetting: 0.0,
            bit_depth: 12,
            gain: 1.0,
            exposure_s: 1.0,
            noise,
            seed: 1,
        }
    }

    #[test]
    fn noiseless_is_expected_value_and_saturates() {
        let img = RgbImage {
            width: 2,
            height: 1,
            data: vec![5.0, 5.0, 5.0, 1e6, 0.0, 0.0],
        };
        let m = model(false);
        let f = m.expose(&img, 0);
        let expect = (5.0 * 1000.0 * m.conversion()).round() as u16;
        assert_eq!(f[0], expect);
        assert_eq!(f[3], 4095, "saturated at full well");
        assert_eq!(f[4], 0, "empty stays empty without noise");
        assert!((m.expected_normalized(5.0) * 4095.0 - expect as f64).abs() < 1.0);
    }

    #[test]
    fn response_and_crosstalk_are_applied_before_the_adc() {
        let img = RgbImage {
            width: 1,
            height: 1,
            data: vec![5.0, 2.0, 0.0],
        };
        let m = model(false);
        let lin = m.expose(&img, 0);
        let identity = SensorResponse {
            compression: 0.0,
            crosstalk: None,
        };
        assert_eq!(m.expose_roi_response(&img, 0, (0, 0, 1, 1), &identity), lin);
        let r = SensorResponse {
            compression: 2.0,
            crosstalk: Some([[0.8, 0.2, 0.0], [0.0, 1.0, 0.0], [0.1, 0.1, 0.8]]),
        };
        let out = m.expose_roi_response(&img, 0, (0, 0, 1, 1), &r);
        let u = |l: f64| l * 1000.0 * m.conversion() / m.max_dn();
        for (c, l) in [0.8 * 5.0 + 0.2 * 2.0, 2.0, 0.1 * 5.0 + 0.1 * 2.0].iter().enumerate() {
            let want = (r.curve(u(*l)) * m.max_dn()).round() as u16;
            assert_eq!(out[c], want, "channel {c}");
            assert!(out[c] as f64 > u(*l) * m.max_dn(), "compression lifts mid-tones");
        }
        for y in [0.0, 0.1, 0.5, 0.99] {
            assert!((r.curve(r.inverse(y)) - y).abs() < 1e-12);
        }
        assert_eq!(r.curve(1.0), 1.0);
    }

    #[test]
    fn shot_noise_has_the_right_variance_and_is_reproducible() {
        let n = 20000;
        let img = RgbImage {
            width: n,
            height: 1,
            data: vec![10.0; n * 3],
        };
        let m = model(true);
        let a = m.expose(&img, 7);
        assert_eq!(a, m.expose(&img, 7), "same seed and sequence, same frame");
        assert_ne!(a, m.expose(&img, 8));
        let conv = m.conversion();
        let e: Vec<f64> = a.iter().map(|&d| d as f64 / conv).collect();
        let mean = e.iter().sum::<f64>() / e.len() as f64;
        let var = e.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / e.len() as f64;
        // small means follow Poisson: mean = variance
        let mut rng = Pcg64Mcg::seed_from_u64(5);
        let xs: Vec<f64> = (0..200_000).map(|_| small_poisson(&mut rng, 2.5)).collect();
        let m = xs.iter().sum::<f64>() / xs.len() as f64;
        let v = xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / xs.len() as f64;
        assert!(
            (m - 2.5).abs() < 0.02 && (v - 2.5).abs() < 0.05,
            "poisson mean {m} var {v}"
        );
        // mean 10000 e⁻: variance = 10000 (shot) + 16 (read) + quantisation (≈ (1/conv)²/12)
        let q = (1.0 / conv).powi(2) / 12.0;
        let want = 10000.0 + 16.0 + q;
        assert!((mean - 10000.0).abs() < 5.0, "mean {mean}");
        assert!((var / want - 1.0).abs() < 0.05, "var {var} want {want}");
    }
}
