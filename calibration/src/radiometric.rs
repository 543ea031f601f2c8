//! Radiometric camera calibration: dark frame, flat field, response curve (Debevec-Malik),
//! HDR merging of exposure brackets and a 3 × 3 colour correction.
//!
//! Pure algorithms on frames (`gonio_devices::Frame`, digital numbers) and linear images
//! (`RgbImage`); nothing here renders or knows the simulator, so the same code calibrates a
//! real camera. The order a lab runs them in: dark → response → flat → colour, because the
//! flat field and the colour target must be measured on *linear* values and a camera with a
//! non-linear response only gives those after its response is known.
//!
//! Validity of a digital number: values at or below `black_fraction · max_dn` carry no
//! signal (read noise and the clip at zero dominate) and values at or above
//! `saturation_fraction · max_dn` are clipped; both get zero weight in the response fit and
//! in the HDR merge. Between them the weight is Debevec and Malik's hat, peaking mid-range
//! where the response is best conditioned.

use gonio_devices::image::RgbImage;
use gonio_devices::Frame;
use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Errors of the radiometric algorithms; each names what was wrong and what to change.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum RadiometricError {
    #[error("{what}: no frames given")]
    NoFrames { what: &'static str },
    #[error("{what}: frame {index} is {got:?} (width, height), the first frame is {expected:?}")]
    SizeMismatch {
        what: &'static str,
        index: usize,
        expected: (usize, usize),
        got: (usize, usize),
    },
    #[error("{what}: frame {index} has {got} values, {width} × {height} × 3 = {want} expected")]
    BadLength {
        what: &'static str,
        index: usize,
        width: usize,
        height: usize,
        got: usize,
        want: usize,
    },
    #[error("{what}: frame {index} has exposure {exposure} s: exposures must be finite and > 0")]
    BadExposure {
        what: &'static str,
        index: usize,
        exposure: f64,
    },
    #[error("option `{key}`: {message}")]
    BadOption { key: &'static str, message: String },
    #[error(
        "{what}: every frame of the bracket is saturated (exposures {exposures:?} s): \
         shorten the shortest exposure (below {suggest_s:.3e} s) or lower the gain or the lamp"
    )]
    AllSaturated {
        what: &'static str,
        exposures: Vec<f64>,
        suggest_s: f64,
    },
    #[error(
        "{what}: every frame is black (exposures {exposures:?} s, no value above {black_dn:.1} DN): \
         lamp off, shutter or lens cap closed, or lengthen the exposure (beyond {suggest_s:.3e} s)"
    )]
    AllBlack {
        what: &'static str,
        exposures: Vec<f64>,
        black_dn: f64,
        suggest_s: f64,
    },
    #[error(
        "response: the bracket has {distinct} distinct exposure(s) {exposures:?} s: the response curve \
         needs at least 2 different exposures of the same scene (Debevec-Malik compares them)"
    )]
    TooFewExposures { distinct: usize, exposures: Vec<f64> },
    #[error(
        "response, channel {channel}: only {usable} pixel samples are valid (neither black nor saturated) \
         in at least two exposures, {needed} needed: widen the bracket or use a target with more grey levels"
    )]
    TooFewSamples {
        channel: usize,
        usable: usize,
        needed: usize,
    },
    #[error("{what}: least-squares solve failed: {message}")]
    Solve { what: &'static str, message: String },
    #[error(
        "flat field: the target is dark (no pixel reaches {threshold:.3e}, brightest {max:.3e}): \
         lamp off or exposure too short"
    )]
    FlatDark { threshold: f64, max: f64 },
    #[error("colour: {patches} patches given, at least 3 with known reflectances are needed for a 3 × 3 matrix")]
    TooFewPatches { patches: usize },
    #[error(
        "colour: patch {index} has a non-finite or negative value (measured {measured:?}, reference {reference:?})"
    )]
    BadPatch {
        index: usize,
        measured: [f64; 3],
        reference: [f64; 3],
    },
    #[error(
        "colour: the measured patch colours are (nearly) collinear, condition number {condition:.3e}: \
         the 3 × 3 matrix is not determined; use a target with saturated red, green and blue patches"
    )]
    ColourDegenerate { condition: f64 },
}

/// Which values of a frame count as valid signal.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Validity {
    /// Values ≤ this fraction of full scale are "black" (no usable signal).
    pub black_fraction: f64,
    /// Values ≥ this fraction of full scale are saturated.
    pub saturation_fraction: f64,
}

impl Default for Validity {
    fn default() -> Self {
        Validity {
            black_fraction: 0.004,
            saturation_fraction: 0.985,
        }
    }
}

impl Validity {
    fn check(&self) -> Result<(), RadiometricError> {
        if !(self.black_fraction >= 0.0
            && self.black_fraction < self.saturation_fraction
            && self.saturation_fraction <= 1.0)
        {
            return Err(RadiometricError::BadOption {
                key: "black_fraction / saturation_fraction",
                message: format!(
                    "{} / {}: need 0 ≤ black < saturation ≤ 1",
                    self.black_fraction, self.saturation_fraction
                ),
            });
        }
        Ok(())
    }

    /// Debevec-Malik's hat on a normalised value `x = DN / max_dn`: 0 at or outside the
    /// black and saturation limits, 1 half-way between them.
    pub fn weight(&self, x: f64) -> f64 {
        let (b, s) = (self.black_fraction, self.saturation_fraction);
        if x <= b || x >= s {
            return 0.0;
        }
        let half = 0.5 * (s - b);
        ((x - b).min(s - x) / half).clamp(0.0, 1.0)
    }
}

fn check_frames(what: &'static str, frames: &[&Frame]) -> Result<(usize, usize), RadiometricError> {
    let first = frames.first().ok_or(RadiometricError::NoFrames { what })?;
    let expected = (first.width, first.height);
    for (index, f) in frames.iter().enumerate() {
        if (f.width, f.height) != expected {
            return Err(RadiometricError::SizeMismatch {
                what,
                index,
                expected,
                got: (f.width, f.height),
            });
        }
        let want = f.width * f.height * 3;
        if f.data.len() != want {
            return Err(RadiometricError::BadLength {
                what,
                index,
                width: f.width,
                height: f.height,
                got: f.data.len(),
                want,
            });
        }
        if !(f.meta.exposure.is_finite() && f.meta.exposure > 0.0) {
            return Err(RadiometricError::BadExposure {
                what,
                index,
                exposure: f.meta.exposure,
            });
        }
    }
    Ok(expected)
}

// ---------------------------------------------------------------------------------------
// Dark frame
// ---------------------------------------------------------------------------------------

/// Mean of frames taken with no light: the per-pixel offset to subtract and the noise floor.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DarkFrame {
    pub width: usize,
    pub height: usize,
    pub frames: usize,
    pub exposure_s: f64,
    /// Per pixel and channel mean (DN), `width · height · 3` values (not serialized: large;
    /// the runner writes it as an image file).
    #[serde(skip)]
    pub mean: Vec<f32>,
    /// Mean over the frame per channel (DN).
    pub mean_dn: [f64; 3],
    /// Temporal noise per channel (DN): the RMS over pixels of each pixel's standard deviation
    /// over the frames. `None` with a single frame (no temporal statistics).
    pub read_noise_dn: Option<[f64; 3]>,
    /// Spatial spread of the per-pixel means (DN): fixed-pattern noise plus the residual
    /// temporal noise `read_noise / √frames`.
    pub spatial_sd_dn: [f64; 3],
    /// Fraction of values at 0 DN: the ADC clips negative excursions, so a large fraction
    /// means the noise estimate is a lower bound (the camera needs a black-level offset).
    pub clipped_at_zero: f64,
    /// Pixels (any channel) whose mean exceeds the frame mean by more than 6 temporal
    /// sigmas (hot pixels); 0 without temporal statistics.
    pub hot_pixels: usize,
}

/// Dark frame from frames taken with the lamp off (same exposure as the measurement).
pub fn dark_frame(frames: &[Frame]) -> Result<DarkFrame, RadiometricError> {
    let refs: Vec<&Frame> = frames.iter().collect();
    let (w, h) = check_frames("dark frame", &refs)?;
    let n = frames.len();
    let len = w * h * 3;
    let mut sum = vec![0f64; len];
    let mut sum2 = vec![0f64; len];
    let mut zeros = 0usize;
    for f in frames {
        for (k, &v) in f.data.iter().enumerate() {
            let v = v as f64;
            sum[k] += v;
            sum2[k] += v * v;
            zeros += usize::from(v == 0.0);
        }
    }
    let mean: Vec<f64> = sum.iter().map(|s| s / n as f64).collect();
    let px = (w * h).max(1) as f64;
    let mut mean_dn = [0.0; 3];
    for (k, m) in mean.iter().enumerate() {
        mean_dn[k % 3] += m / px;
    }
    let mut spatial = [0.0; 3];
    for (k, m) in mean.iter().enumerate() {
        spatial[k % 3] += (m - mean_dn[k % 3]).powi(2) / px;
    }
    let read_noise_dn = (n >= 2).then(|| {
        let mut var = [0.0; 3];
        for k in 0..len {
            let v = (sum2[k] - sum[k] * sum[k] / n as f64) / (n as f64 - 1.0);
            var[k % 3] += v.max(0.0) / px;
        }
        var.map(f64::sqrt)
    });
    let hot_pixels = match read_noise_dn {
        Some(rn) => (0..w * h)
            .filter(|p| (0..3).any(|c| mean[p * 3 + c] - mean_dn[c] > 6.0 * rn[c].max(0.5)))
            .count(),
        None => 0,
    };
    Ok(DarkFrame {
        width: w,
        height: h,
        frames: n,
        exposure_s: frames[0].meta.exposure,
        mean: mean.iter().map(|&m| m as f32).collect(),
        mean_dn,
        read_noise_dn,
        spatial_sd_dn: spatial.map(f64::sqrt),
        clipped_at_zero: zeros as f64 / (len * n).max(1) as f64,
        hot_pixels,
    })
}

// ---------------------------------------------------------------------------------------
// Flat field
// ---------------------------------------------------------------------------------------

/// Per-pixel relative gain from images of a uniform target.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FlatField {
    pub width: usize,
    pub height: usize,
    pub frames: usize,
    /// Relative gain per pixel and channel, mean 1 over the covered pixels; 0 where the
    /// target did not cover the pixel (not serialized: large, written as an image file).
    #[serde(skip)]
    pub gain: Vec<f32>,
    /// Pixels where every channel reached `min_signal` of the brightest level.
    pub covered_pixels: usize,
    pub min_signal: f64,
    /// Smallest and largest gain over the covered pixels (all channels).
    pub gain_min: f64,
    pub gain_max: f64,
    /// Relative standard error of the gain from the frame-to-frame scatter (RMS over the
    /// covered pixels); `None` with one frame.
    pub relative_noise: Option<f64>,
}

/// Flat field from linear images (linearised with the response, dark subtracted) of a
/// uniformly lit, uniform target. Pixels where any channel is below `min_signal` times the
/// 99th percentile of the mean image are outside the target and get gain 0.
pub fn flat_field(images: &[RgbImage], min_signal: f64) -> Result<FlatField, RadiometricError> {
    let what = "flat field";
    let first = images.first().ok_or(RadiometricError::NoFrames { what })?;
    let (w, h) = (first.width, first.height);
    if !(min_signal > 0.0 && min_signal < 1.0) {
        return Err(RadiometricError::BadOption {
            key: "min_signal",
            message: format!("{min_signal}: valid range is (0, 1)"),
        });
    }
    for (index, im) in images.iter().enumerate() {
        if (im.width, im.height) != (w, h) {
            return Err(RadiometricError::SizeMismatch {
                what,
                index,
                expected: (w, h),
                got: (im.width, im.height),
            });
        }
        if im.data.len() != w * h * 3 {
            return Err(RadiometricError::BadLength {
                what,
                index,
                width: w,
                height: h,
                got: im.data.len(),
                want: w * h * 3,
            });
        }
    }
    let n = images.len() as f64;
    let len = w * h * 3;
    let mut sum = vec![0f64; len];
    let mut sum2 = vec![0f64; len];
    for im in images {
        for (k, &v) in im.data.iter().enumerate() {
            let v = if v.is_finite() { v as f64 } else { 0.0 };
            sum[k] += v;
            sum2[k] += v * v;
        }
    }
    let mean: Vec<f64> = sum.iter().map(|s| s / n).collect();
    let mut sorted: Vec<f64> = mean.clone();
    sorted.sort_by(|a, b| a.total_cmp(b));
    let top = sorted[((sorted.len() as f64 - 1.0) * 0.99) as usize];
    let threshold = min_signal * top;
    let covered: Vec<bool> = (0..w * h)
        .map(|p| top > 0.0 && (0..3).all(|c| mean[p * 3 + c] >= threshold))
        .collect();
    let count = covered.iter().filter(|&&c| c).count();
    if count == 0 {
        return Err(RadiometricError::FlatDark {
            threshold,
            max: sorted.last().copied().unwrap_or(0.0),
        });
    }
    let mut chan_mean = [0.0; 3];
    for p in (0..w * h).filter(|&p| covered[p]) {
        for (c, m) in chan_mean.iter_mut().enumerate() {
            *m += mean[p * 3 + c] / count as f64;
        }
    }
    let mut gain = vec![0f32; len];
    let (mut lo, mut hi) = (f64::INFINITY, 0f64);
    let mut noise2 = 0.0;
    for p in (0..w * h).filter(|&p| covered[p]) {
        for (c, cm) in chan_mean.iter().enumerate() {
            let k = p * 3 + c;
            let g = mean[k] / cm;
            gain[k] = g as f32;
            lo = lo.min(g);
            hi = hi.max(g);
            if images.len() >= 2 {
                let var = ((sum2[k] - sum[k] * sum[k] / n) / (n - 1.0)).max(0.0);
                noise2 += var / n / (mean[k] * mean[k]);
            }
        }
    }
    Ok(FlatField {
        width: w,
        height: h,
        frames: images.len(),
        gain,
        covered_pixels: count,
        min_signal,
        gain_min: lo,
        gain_max: hi,
        relative_noise: (images.len() >= 2).then(|| (noise2 / (3 * count) as f64).sqrt()),
    })
}

// ---------------------------------------------------------------------------------------
// Response curve (Debevec-Malik)
// ---------------------------------------------------------------------------------------

/// Options of the response fit.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ResponseOptions {
    /// Number of levels the DN range is divided into (one unknown each): 4096 unknowns for a
    /// 12-bit camera would make the dense solve slow for no gain, the curve is smooth.
    pub levels: usize,
    /// Smoothness weight λ (second differences of g); 0 = data only.
    pub lambda: f64,
    /// Pixel samples per channel, chosen to spread over the brightness range.
    pub samples: usize,
    pub validity: Validity,
}

impl Default for ResponseOptions {
    fn default() -> Self {
        ResponseOptions {
            levels: 256,
            lambda: 20.0,
            samples: 200,
            validity: Validity::default(),
        }
    }
}

/// The inverse response: `g(z) = ln(exposure)` for a level `z`, per channel, up to an
/// additive constant per channel (fixed by `g(mid) = 0`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ResponseCurve {
    pub levels: usize,
    pub max_dn: f64,
    /// `g[c][z]`, z = 0 ..= levels − 1 at DN `z · max_dn / (levels − 1)`.
    pub g: [Vec<f64>; 3],
    pub validity: Validity,
}

impl ResponseCurve {
    /// The linear (identity) response of a camera with `max_dn`.
    pub fn linear(max_dn: f64, levels: usize) -> ResponseCurve {
        let levels = levels.max(2);
        let g: Vec<f64> = (0..levels)
            .map(|z| {
                let x = (z as f64 / (levels - 1) as f64).max(0.5 / (levels - 1) as f64);
                (x / 0.5).ln()
            })
            .collect();
        ResponseCurve {
            levels,
            max_dn,
            g: [g.clone(), g.clone(), g],
            validity: Validity::default(),
        }
    }

    /// `g` at a DN value, linearly interpolated between levels.
    pub fn g_at(&self, channel: usize, dn: f64) -> f64 {
        let t = (dn / self.max_dn).clamp(0.0, 1.0) * (self.levels - 1) as f64;
        let i = (t.floor() as usize).min(self.levels - 2);
        let f = t - i as f64;
        let g = &self.g[channel];
        g[i] * (1.0 - f) + g[i + 1] * f
    }

    /// Relative exposure (`exp g`) of a DN value: linear in scene radiance × time.
    pub fn exposure_of(&self, channel: usize, dn: f64) -> f64 {
        self.g_at(channel, dn).exp()
    }
}

/// Diagnostics of the response fit, per channel.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ResponseFit {
    pub curve: ResponseCurve,
    pub exposures_s: Vec<f64>,
    pub samples: [usize; 3],
    /// Levels with no data equation (filled from neighbours; with λ = 0 by interpolation).
    pub unobserved_levels: [usize; 3],
    /// RMS of the weighted data residuals `w (g(z) − ln E − ln Δt)` (natural log units).
    pub residual_rms: [f64; 3],
}

/// Least squares `min ‖A X − B‖` for a tall `A` (rows ≥ columns) by Householder QR with
/// column pivoting (`A P = Q R`, then `X = P R⁻¹ Qᵀ B`): stable on the ill-conditioned
/// systems of the response and colour fits without forming `AᵀA`. `None` when `A` is wide
/// or `R` is singular.
fn lstsq(a: DMatrix<f64>, mut b: DMatrix<f64>) -> Option<DMatrix<f64>> {
    let n = a.ncols();
    if a.nrows() < n {
        return None;
    }
    let qr = a.col_piv_qr();
    qr.q_tr_mul(&mut b);
    let r = qr.r();
    let r = r.view((0, 0), (n, n));
    let mut x = b.rows(0, n).into_owned();
    if !r.solve_upper_triangular_mut(&mut x) {
        return None;
    }
    qr.p().inv_permute_rows(&mut x);
    Some(x)
}

/// Recover the inverse response from frames of the same static scene at different
/// exposures (Debevec & Malik 1997): minimise
/// `Σ w(z_ij) (g(z_ij) − ln E_i − ln Δt_j)² + λ² Σ w(z) g''(z)²` with `g(mid) = 0`,
/// solved as one dense least-squares problem (column-pivoted QR, [`lstsq`]).
pub fn recover_response(frames: &[Frame], opts: &ResponseOptions) -> Result<ResponseFit, RadiometricError> {
    let what = "response";
    opts.validity.check()?;
    if !(16..=1024).contains(&opts.levels) {
        return Err(RadiometricError::BadOption {
            key: "levels",
            message: format!("{}: valid range is 16 ..= 1024", opts.levels),
        });
    }
    if !(opts.lambda.is_finite() && opts.lambda >= 0.0) {
        return Err(RadiometricError::BadOption {
            key: "lambda",
            message: format!("{}: must be ≥ 0", opts.lambda),
        });
    }
    if !(8..=5000).contains(&opts.samples) {
        return Err(RadiometricError::BadOption {
            key: "samples",
            message: format!("{}: valid range is 8 ..= 5000", opts.samples),
        });
    }
    let refs: Vec<&Frame> = frames.iter().collect();
    let (w, h) = check_frames(what, &refs)?;
    let exposures: Vec<f64> = frames.iter().map(|f| f.meta.exposure).collect();
    bracket_extremes(what, frames, &opts.validity)?;
    let mut distinct = exposures.clone();
    distinct.sort_by(|a, b| a.total_cmp(b));
    distinct.dedup_by(|a, b| (*a / *b - 1.0).abs() < 1e-9);
    if distinct.len() < 2 {
        return Err(RadiometricError::TooFewExposures {
            distinct: distinct.len(),
            exposures,
        });
    }
    let max_dn = frames.iter().map(|f| f.max_dn()).max().unwrap_or(1) as f64;
    let l = opts.levels;
    let level_of = |dn: u16| ((dn as f64 / max_dn) * (l - 1) as f64).round() as usize;
    let wz: Vec<f64> = (0..l)
        .map(|z| opts.validity.weight(z as f64 / (l - 1) as f64))
        .collect();
    let mut g: [Vec<f64>; 3] = Default::default();
    let mut samples = [0; 3];
    let mut unobserved = [0; 3];
    let mut residual = [0.0; 3];
    for c in 0..3 {
        // Candidate pixels: valid in at least two frames. Sort them by their brightness in
        // the frame where they are best exposed and take evenly spaced quantiles, so the
        // samples cover the whole range rather than the most common value (background).
        let mut cand: Vec<(f64, usize)> = Vec::new();
        for p in 0..w * h {
            let mut valid = 0;
            let mut key = 0.0;
            for f in frames {
                let dn = f.data[p * 3 + c];
                if wz[level_of(dn)] > 0.0 {
                    valid += 1;
                    key = (dn as f64 / f.meta.exposure).max(key);
                }
            }
            if valid >= 2 {
                cand.push((key, p));
            }
        }
        let needed = (l / distinct.len()).max(8);
        if cand.len() < needed {
            return Err(RadiometricError::TooFewSamples {
                channel: c,
                usable: cand.len(),
                needed,
            });
        }
        cand.sort_by(|a, b| a.0.total_cmp(&b.0));
        let take = opts.samples.min(cand.len());
        let picked: Vec<usize> = (0..take)
            .map(|k| cand[((k as f64 + 0.5) / take as f64 * cand.len() as f64) as usize].1)
            .collect();
        samples[c] = take;
        // Observed levels: those with at least one weighted data equation.
        let mut observed = vec![false; l];
        for &p in &picked {
            for f in frames {
                let z = level_of(f.data[p * 3 + c]);
                if wz[z] > 0.0 {
                    observed[z] = true;
                }
            }
        }
        unobserved[c] = (1..l - 1).filter(|&z| !observed[z]).count();
        // Columns: the g unknowns (all levels with λ > 0, only observed levels with λ = 0,
        // where unobserved ones have no equation at all), then ln E per sample.
        let use_level: Vec<bool> = (0..l).map(|z| opts.lambda > 0.0 || observed[z] || z == l / 2).collect();
        let mut col_of = vec![usize::MAX; l];
        let mut ng = 0;
        for z in 0..l {
            if use_level[z] {
                col_of[z] = ng;
                ng += 1;
            }
        }
        let mut rows: Vec<(Vec<(usize, f64)>, f64)> = Vec::new();
        for (i, &p) in picked.iter().enumerate() {
            for f in frames {
                let z = level_of(f.data[p * 3 + c]);
                let wt = wz[z];
                if wt > 0.0 {
                    rows.push((vec![(col_of[z], wt), (ng + i, -wt)], wt * f.meta.exposure.ln()));
                }
            }
        }
        let data_rows = rows.len();
        rows.push((vec![(col_of[l / 2], 1.0)], 0.0));
        if opts.lambda > 0.0 {
            for z in 1..l - 1 {
                // A floor on the hat weight keeps the ends of the curve tied to their
                // neighbours (the pure hat is 0 there and would leave them free).
                let s = opts.lambda * wz[z].max(0.05);
                rows.push((vec![(col_of[z - 1], s), (col_of[z], -2.0 * s), (col_of[z + 1], s)], 0.0));
            }
        }
        let ncols = ng + take;
        let mut a = DMatrix::<f64>::zeros(rows.len(), ncols);
        let mut b = DMatrix::<f64>::zeros(rows.len(), 1);
        for (r, (entries, rhs)) in rows.iter().enumerate() {
            for &(col, v) in entries {
                a[(r, col)] += v;
            }
            b[(r, 0)] = *rhs;
        }
        let x = lstsq(a, b).unwrap_or_else(|| DMatrix::from_element(ncols, 1, f64::NAN));
        if (0..ncols).any(|k| !x[(k, 0)].is_finite()) {
            return Err(RadiometricError::Solve {
                what,
                message: format!("channel {c}: non-finite solution"),
            });
        }
        let mut gc = vec![f64::NAN; l];
        for z in 0..l {
            if use_level[z] {
                gc[z] = x[(col_of[z], 0)];
            }
        }
        fill_gaps(&mut gc);
        let mut r2 = 0.0;
        for (entries, rhs) in rows.iter().take(data_rows) {
            let v: f64 = entries.iter().map(|&(col, a)| a * x[(col, 0)]).sum();
            r2 += (v - rhs).powi(2);
        }
        residual[c] = (r2 / data_rows.max(1) as f64).sqrt();
        // g must increase with z; a non-monotonic fit (noise, λ = 0) is made monotonic by
        // a running maximum so the HDR merge never inverts values.
        for z in 1..l {
            if gc[z] < gc[z - 1] {
                gc[z] = gc[z - 1];
            }
        }
        g[c] = gc;
    }
    Ok(ResponseFit {
        curve: ResponseCurve {
            levels: l,
            max_dn,
            g,
            validity: opts.validity,
        },
        exposures_s: exposures,
        samples,
        unobserved_levels: unobserved,
        residual_rms: residual,
    })
}

/// Replace NaNs by linear interpolation between the nearest defined neighbours (constant
/// extrapolation at the ends).
fn fill_gaps(g: &mut [f64]) {
    let defined: Vec<usize> = (0..g.len()).filter(|&z| g[z].is_finite()).collect();
    if defined.is_empty() {
        return;
    }
    for z in 0..g.len() {
        if g[z].is_finite() {
            continue;
        }
        let lo = defined.iter().rev().find(|&&d| d < z).copied();
        let hi = defined.iter().find(|&&d| d > z).copied();
        g[z] = match (lo, hi) {
            (Some(a), Some(b)) => g[a] + (g[b] - g[a]) * (z - a) as f64 / (b - a) as f64,
            (Some(a), None) => g[a],
            (None, Some(b)) => g[b],
            (None, None) => 0.0,
        };
    }
}

/// Refuse a bracket where every value of every frame is saturated, or every value is
/// black: nothing can be recovered and the fix is an exposure change.
fn bracket_extremes(what: &'static str, frames: &[Frame], v: &Validity) -> Result<(), RadiometricError> {
    let exposures: Vec<f64> = frames.iter().map(|f| f.meta.exposure).collect();
    let all = |pred: &dyn Fn(f64) -> bool| {
        frames
            .iter()
            .all(|f| f.data.iter().all(|&d| pred(d as f64 / f.max_dn() as f64)))
    };
    let lo = exposures.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = exposures.iter().copied().fold(0.0, f64::max);
    if all(&|x| x >= v.saturation_fraction) {
        return Err(RadiometricError::AllSaturated {
            what,
            exposures,
            suggest_s: lo / 16.0,
        });
    }
    if all(&|x| x <= v.black_fraction) {
        let max_dn = frames.iter().map(|f| f.max_dn()).max().unwrap_or(1) as f64;
        return Err(RadiometricError::AllBlack {
            what,
            exposures,
            black_dn: v.black_fraction * max_dn,
            suggest_s: hi * 16.0,
        });
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------
// HDR merge
// ---------------------------------------------------------------------------------------

/// Per-exposure share of saturated and black values.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ExposureStats {
    pub exposure_s: f64,
    pub saturated_fraction: f64,
    pub black_fraction: f64,
}

/// What the merge could not measure.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct HdrDiagnosis {
    /// Values (pixel × channel) saturated in every frame: the merged value is only a lower
    /// bound (the shortest exposure's saturation level).
    pub saturated_everywhere: usize,
    /// Values black in every frame: merged as 0.
    pub black_everywhere: usize,
    /// Values with no valid frame that are neither: black in the longer exposures' frames
    /// nowhere, but a gap in the bracket (black in the short, saturated in the long frames).
    pub bracket_gap: usize,
    pub total: usize,
    pub per_exposure: Vec<ExposureStats>,
}

impl HdrDiagnosis {
    /// One sentence for logs and reports.
    pub fn summary(&self) -> String {
        let pct = |n: usize| 100.0 * n as f64 / self.total.max(1) as f64;
        format!(
            "{} values: {} ({:.2} %) saturated in every exposure, {} ({:.2} %) black in every exposure, {} ({:.2} %) in a gap of the bracket",
            self.total,
            self.saturated_everywhere,
            pct(self.saturated_everywhere),
            self.black_everywhere,
            pct(self.black_everywhere),
            self.bracket_gap,
            pct(self.bracket_gap)
        )
    }
}

/// A merged image: relative radiance `exp(g) / Δt` per pixel and channel (the scale of `g`).
#[derive(Clone, Debug)]
pub struct HdrImage {
    pub image: RgbImage,
    pub diagnosis: HdrDiagnosis,
}

/// Merge a bracket with a recovered response: `ln E = Σ w (g(z) − ln Δt) / Σ w`, black and
/// saturated values weighted 0. Values with no valid frame are counted in the diagnosis;
/// a bracket with no valid value anywhere is an error that says which way to change it.
pub fn merge_hdr(frames: &[Frame], curve: &ResponseCurve) -> Result<HdrImage, RadiometricError> {
    let what = "HDR merge";
    let refs: Vec<&Frame> = frames.iter().collect();
    let (w, h) = check_frames(what, &refs)?;
    let v = curve.validity;
    bracket_extremes(what, frames, &v)?;
    let len = w * h * 3;
    let mut out = vec![0f32; len];
    let mut d = HdrDiagnosis {
        total: len,
        ..Default::default()
    };
    for f in frames {
        let m = f.max_dn() as f64;
        let sat = f
            .data
            .iter()
            .filter(|&&x| x as f64 / m >= v.saturation_fraction)
            .count();
        let blk = f.data.iter().filter(|&&x| x as f64 / m <= v.black_fraction).count();
        d.per_exposure.push(ExposureStats {
            exposure_s: f.meta.exposure,
            saturated_fraction: sat as f64 / len as f64,
            black_fraction: blk as f64 / len as f64,
        });
    }
    let shortest = frames
        .iter()
        .min_by(|a, b| a.meta.exposure.total_cmp(&b.meta.exposure))
        .expect("non-empty");
    for (k, o) in out.iter_mut().enumerate() {
        let c = k % 3;
        let (mut num, mut den) = (0.0, 0.0);
        let (mut n_sat, mut n_blk) = (0, 0);
        for f in frames {
            let x = f.data[k] as f64 / f.max_dn() as f64;
            let wt = v.weight(x);
            if x >= v.saturation_fraction {
                n_sat += 1;
            } else if x <= v.black_fraction {
                n_blk += 1;
            }
            if wt > 0.0 {
                num += wt * (curve.g_at(c, f.data[k] as f64) - f.meta.exposure.ln());
                den += wt;
            }
        }
        *o = if den > 0.0 {
            (num / den).exp() as f32
        } else if n_sat == frames.len() {
            d.saturated_everywhere += 1;
            (curve.g_at(c, v.saturation_fraction * curve.max_dn) - shortest.meta.exposure.ln()).exp() as f32
        } else if n_blk == frames.len() {
            d.black_everywhere += 1;
            0.0
        } else {
            d.bracket_gap += 1;
            0.0
        };
    }
    Ok(HdrImage {
        image: RgbImage {
            width: w,
            height: h,
            data: out,
        },
        diagnosis: d,
    })
}

// ---------------------------------------------------------------------------------------
// Colour
// ---------------------------------------------------------------------------------------

/// A 3 × 3 matrix taking measured linear camera RGB to linear sRGB reflectance.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ColourMatrix {
    /// `reference ≈ matrix · measured` (rows: output R, G, B).
    pub matrix: [[f64; 3]; 3],
    pub patches: usize,
    /// Ratio of the largest to the smallest singular value of the measured patch matrix:
    /// how well the patches determine the matrix (large = nearly collinear colours).
    pub condition: f64,
    /// RMS and largest residual of the corrected patches against their references.
    pub residual_rms: f64,
    pub residual_max: f64,
}

impl ColourMatrix {
    pub fn apply(&self, rgb: [f64; 3]) -> [f64; 3] {
        std::array::from_fn(|r| (0..3).map(|k| self.matrix[r][k] * rgb[k]).sum())
    }
}

/// Condition numbers above this refuse the fit.
pub const MAX_COLOUR_CONDITION: f64 = 1e6;

/// Least-squares 3 × 3 colour matrix from patch means (linear camera values) and the
/// patches' known linear-sRGB reflectances.
pub fn colour_matrix(measured: &[[f64; 3]], reference: &[[f64; 3]]) -> Result<ColourMatrix, RadiometricError> {
    let p = measured.len().min(reference.len());
    if p < 3 || measured.len() != reference.len() {
        return Err(RadiometricError::TooFewPatches { patches: p });
    }
    for (index, (m, r)) in measured.iter().zip(reference).enumerate() {
        if m.iter().chain(r).any(|v| !v.is_finite() || *v < 0.0) {
            return Err(RadiometricError::BadPatch {
                index,
                measured: *m,
                reference: *r,
            });
        }
    }
    let a = DMatrix::<f64>::from_fn(p, 3, |i, j| measured[i][j]);
    let b = DMatrix::<f64>::from_fn(p, 3, |i, j| reference[i][j]);
    let sv = a.clone().singular_values();
    let smax = sv.iter().copied().fold(0.0, f64::max);
    let smin = sv.iter().copied().fold(f64::INFINITY, f64::min);
    let condition = if smin > 0.0 { smax / smin } else { f64::INFINITY };
    if condition.is_nan() || condition > MAX_COLOUR_CONDITION {
        return Err(RadiometricError::ColourDegenerate { condition });
    }
    let x = lstsq(a, b).ok_or(RadiometricError::ColourDegenerate {
        condition: f64::INFINITY,
    })?;
    let matrix: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|k| x[(k, r)]));
    let cm = ColourMatrix {
        matrix,
        patches: p,
        condition,
        residual_rms: 0.0,
        residual_max: 0.0,
    };
    let mut s2 = 0.0;
    let mut mx = 0f64;
    for (m, r) in measured.iter().zip(reference) {
        let c = cm.apply(*m);
        for k in 0..3 {
            let e = (c[k] - r[k]).abs();
            s2 += e * e;
            mx = mx.max(e);
        }
    }
    Ok(ColourMatrix {
        residual_rms: (s2 / (3 * p) as f64).sqrt(),
        residual_max: mx,
        ..cm
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The pivoted-QR least squares recovers an exact solution of a tall, badly scaled
    /// system, and its least-squares answer satisfies the normal equations.
    #[test]
    fn lstsq_solves_tall_systems() {
        // A Vandermonde matrix with columns scaled by 1, 10³, 10⁶: full rank, badly scaled.
        let a = DMatrix::<f64>::from_fn(7, 3, |i, j| {
            (0.37 * i as f64 + 1.0).powi(j as i32) * 10f64.powi(j as i32 * 3)
        });
        let x_true = DMatrix::<f64>::from_column_slice(3, 2, &[1.0, -2.0, 0.5, 3.0, 0.25, -1.0]);
        let x = lstsq(a.clone(), &a * &x_true).unwrap();
        assert!((&x - &x_true).abs().max() < 1e-6, "{x}");
        let b = DMatrix::<f64>::from_fn(7, 1, |i, _| (i as f64).cos());
        let x = lstsq(a.clone(), b.clone()).unwrap();
        let normal = a.transpose() * (&a * &x - &b);
        assert!(normal.abs().max() < 1e-6 * a.norm() * b.norm(), "{normal}");
        assert!(lstsq(DMatrix::zeros(2, 3), DMatrix::zeros(2, 1)).is_none());
    }
    use gonio_devices::FrameMeta;

    /// A smooth non-linear camera: `f(u) = (1 − e^{−a u}) / (1 − e^{−a})`.
    fn respond(u: f64, a: f64) -> f64 {
        (1.0 - (-a * u).exp()) / (1.0 - (-a).exp())
    }
    fn inverse(y: f64, a: f64) -> f64 {
        -(1.0 - y * (1.0 - (-a).exp())).ln() / a
    }

    fn frame(w: usize, h: usize, data: Vec<u16>, exposure: f64) -> Frame {
        Frame {
            width: w,
            height: h,
            data,
            meta: FrameMeta {
                timestamp: 0.0,
                exposure,
                gain: 1.0,
                sequence: 0,
                bit_depth: 12,
            },
        }
    }

    /// Tiny deterministic generator (tests must not depend on a rand version).
    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((self.0 >> 11) as f64) / (1u64 << 53) as f64
        }
        fn normal(&mut self) -> f64 {
            let (u, v) = (self.next().max(1e-12), self.next());
            (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
        }
    }

    /// A scene of log-spaced radiances photographed at `exposures` through `respond`.
    fn bracket(exposures: &[f64], a: f64, noise_dn: f64, seed: u64) -> (Vec<Frame>, Vec<f64>) {
        let (w, h) = (64, 32);
        let mut rng = Lcg(seed);
        let radiance: Vec<f64> = (0..w * h * 3)
            .map(|k| 10f64.powf(-3.0 + 3.0 * ((k / 3) as f64 / (w * h) as f64)) * [1.0, 0.8, 0.6][k % 3])
            .collect();
        let frames = exposures
            .iter()
            .map(|&t| {
                let data = radiance
                    .iter()
                    .map(|&l| {
                        let y = respond((l * t).min(1.0), a) * 4095.0 + noise_dn * rng.normal();
                        y.round().clamp(0.0, 4095.0) as u16
                    })
                    .collect();
                frame(w, h, data, t)
            })
            .collect();
        (frames, radiance)
    }

    /// RMS relative error of the recovered inverse response against the truth over the
    /// valid DN range, after the one free scale per channel.
    fn response_error(curve: &ResponseCurve, a: f64, channel: usize) -> f64 {
        let zs: Vec<f64> = (1..40).map(|k| 0.03 + 0.9 * k as f64 / 40.0).collect();
        let logs: Vec<f64> = zs
            .iter()
            .map(|&y| curve.g_at(channel, y * 4095.0) - inverse(y, a).ln())
            .collect();
        let shift = logs.iter().sum::<f64>() / logs.len() as f64;
        (logs.iter().map(|d| ((d - shift).exp() - 1.0).powi(2)).sum::<f64>() / logs.len() as f64).sqrt()
    }

    #[test]
    fn response_recovers_a_nonlinear_curve() {
        let exps = [0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0];
        let (frames, _) = bracket(&exps, 2.0, 0.0, 1);
        let fit = recover_response(&frames, &ResponseOptions::default()).unwrap();
        for c in 0..3 {
            let e = response_error(&fit.curve, 2.0, c);
            assert!(e < 0.01, "channel {c}: rms relative error {e}");
        }
        // A linear camera's curve is not mistaken for the non-linear one.
        let (frames, _) = bracket(&exps, 1e-6, 0.0, 1);
        let fit = recover_response(&frames, &ResponseOptions::default()).unwrap();
        assert!(response_error(&fit.curve, 1e-6, 0) < 0.01);
        assert!(
            response_error(&fit.curve, 2.0, 0) > 0.05,
            "the test can tell curves apart"
        );
    }

    #[test]
    fn noisy_bracket_and_lambda_zero() {
        let exps = [0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0];
        let (frames, _) = bracket(&exps, 2.0, 4.0, 7);
        let fit = recover_response(&frames, &ResponseOptions::default()).unwrap();
        let e = response_error(&fit.curve, 2.0, 1);
        assert!(e < 0.03, "noisy: {e}");
        // λ = 0: only data; noise makes it rougher but the levels are dense, so it still fits.
        let opts = ResponseOptions {
            lambda: 0.0,
            samples: 400,
            ..Default::default()
        };
        let fit0 = recover_response(&frames, &opts).unwrap();
        let e0 = response_error(&fit0.curve, 2.0, 1);
        assert!(e0.is_finite() && e0 < 0.1, "λ = 0: {e0}");
        assert!(fit0.curve.g[1].windows(2).all(|p| p[1] >= p[0]), "monotonic");
        // With few samples and λ = 0 levels go unobserved: reported and filled.
        let opts = ResponseOptions {
            lambda: 0.0,
            samples: 10,
            ..Default::default()
        };
        let fit1 = recover_response(&frames, &opts).unwrap();
        assert!(fit1.unobserved_levels[0] > 0);
        assert!(fit1.curve.g[0].iter().all(|g| g.is_finite()));
    }

    #[test]
    fn single_exposure_all_saturated_all_black_are_refused() {
        let (frames, _) = bracket(&[1.0], 2.0, 0.0, 1);
        let e = recover_response(&frames, &ResponseOptions::default()).unwrap_err();
        assert!(
            matches!(e, RadiometricError::TooFewExposures { distinct: 1, .. }),
            "{e}"
        );
        // the same exposure twice is still one exposure
        let two = vec![frames[0].clone(), frames[0].clone()];
        let e = recover_response(&two, &ResponseOptions::default()).unwrap_err();
        assert!(matches!(e, RadiometricError::TooFewExposures { .. }), "{e}");

        let sat: Vec<Frame> = [1.0, 2.0].iter().map(|&t| frame(4, 4, vec![4095; 48], t)).collect();
        let e = recover_response(&sat, &ResponseOptions::default()).unwrap_err();
        assert!(matches!(e, RadiometricError::AllSaturated { .. }), "{e}");
        assert!(e.to_string().contains("shorten"), "{e}");
        let e = merge_hdr(&sat, &ResponseCurve::linear(4095.0, 256)).unwrap_err();
        assert!(matches!(e, RadiometricError::AllSaturated { .. }), "{e}");

        let black: Vec<Frame> = [1.0, 2.0].iter().map(|&t| frame(4, 4, vec![3; 48], t)).collect();
        let e = recover_response(&black, &ResponseOptions::default()).unwrap_err();
        assert!(matches!(e, RadiometricError::AllBlack { .. }), "{e}");
        assert!(e.to_string().contains("lamp off"), "{e}");
        let e = merge_hdr(&black, &ResponseCurve::linear(4095.0, 256)).unwrap_err();
        assert!(matches!(e, RadiometricError::AllBlack { .. }), "{e}");

        let bad = vec![frame(4, 4, vec![100; 48], 1.0), frame(4, 4, vec![100; 48], -1.0)];
        let e = recover_response(&bad, &ResponseOptions::default()).unwrap_err();
        assert!(matches!(e, RadiometricError::BadExposure { index: 1, .. }), "{e}");
    }

    #[test]
    fn hdr_merge_recovers_radiance_and_reports_unmeasurable_pixels() {
        let exps = [0.25, 1.0, 4.0, 16.0];
        let (frames, radiance) = bracket(&exps, 2.0, 0.0, 3);
        let fit = recover_response(&frames, &ResponseOptions::default()).unwrap();
        let hdr = merge_hdr(&frames, &fit.curve).unwrap();
        // Compare up to the per-channel scale over values measured in some frame.
        for c in 0..3 {
            let pairs: Vec<(f64, f64)> = (0..radiance.len() / 3)
                .map(|p| (hdr.image.data[p * 3 + c] as f64, radiance[p * 3 + c]))
                .filter(|(m, _)| *m > 0.0)
                .collect();
            let scale = (pairs.iter().map(|(m, t)| (t / m).ln()).sum::<f64>() / pairs.len() as f64).exp();
            let rms =
                (pairs.iter().map(|(m, t)| (m * scale / t - 1.0).powi(2)).sum::<f64>() / pairs.len() as f64).sqrt();
            assert!(rms < 0.02, "channel {c}: {rms}");
        }
        let d = &hdr.diagnosis;
        assert_eq!(
            d.black_everywhere + d.saturated_everywhere + d.bracket_gap,
            0,
            "{}",
            d.summary()
        );
        // Only the short exposures: the scene's darkest values are black in both, counted
        // (and merged as 0), not invented.
        let short: Vec<Frame> = frames[..2].to_vec();
        let hdr = merge_hdr(&short, &fit.curve).unwrap();
        assert!(hdr.diagnosis.black_everywhere > 0, "{}", hdr.diagnosis.summary());
        assert_eq!(hdr.diagnosis.saturated_everywhere, 0);
        let black: Vec<usize> = (0..hdr.image.data.len())
            .filter(|&k| short.iter().all(|f| f.data[k] as f64 <= 0.004 * 4095.0))
            .collect();
        assert_eq!(black.len(), hdr.diagnosis.black_everywhere);
        assert!(black.iter().all(|&k| hdr.image.data[k] == 0.0));
        // Only the long exposures: the brightest values saturate everywhere.
        let long: Vec<Frame> = frames[2..].to_vec();
        let hdr = merge_hdr(&long, &fit.curve).unwrap();
        assert!(hdr.diagnosis.saturated_everywhere > 0, "{}", hdr.diagnosis.summary());
        assert_eq!(hdr.diagnosis.per_exposure.len(), 2);
        assert!(hdr.diagnosis.per_exposure[1].saturated_fraction > hdr.diagnosis.per_exposure[0].saturated_fraction);
    }

    #[test]
    fn dark_frame_mean_and_read_noise() {
        let (w, h, n) = (50, 40, 16);
        let mut rng = Lcg(9);
        let offset = 100.0;
        let sd = 3.0;
        let frames: Vec<Frame> = (0..n)
            .map(|_| {
                let data = (0..w * h * 3)
                    .map(|k| {
                        let hot = if k == 3 * 77 { 200.0 } else { 0.0 };
                        (offset + hot + sd * rng.normal()).round() as u16
                    })
                    .collect();
                frame(w, h, data, 0.05)
            })
            .collect();
        let d = dark_frame(&frames).unwrap();
        for c in 0..3 {
            assert!((d.mean_dn[c] - offset).abs() < 0.2, "{:?}", d.mean_dn);
            let rn = d.read_noise_dn.unwrap()[c];
            // rounding adds 1/12 DN² of variance
            assert!((rn - (sd * sd + 1.0 / 12.0).sqrt()).abs() < 0.1, "read noise {rn}");
        }
        assert_eq!(d.hot_pixels, 1);
        assert_eq!(d.mean.len(), w * h * 3);
        assert!(dark_frame(&frames[..1]).unwrap().read_noise_dn.is_none());
        assert!(matches!(dark_frame(&[]), Err(RadiometricError::NoFrames { .. })));
        let mut bad = frames[..2].to_vec();
        bad[1].width = 10;
        assert!(matches!(
            dark_frame(&bad),
            Err(RadiometricError::SizeMismatch { index: 1, .. })
        ));
    }

    #[test]
    fn flat_field_recovers_vignetting() {
        let (w, h) = (60, 40);
        let truth = |x: usize, y: usize| {
            let (dx, dy) = (x as f64 - 30.0, y as f64 - 20.0);
            1.0 - 0.2 * (dx * dx + dy * dy) / (30.0f64 * 30.0 + 20.0 * 20.0)
        };
        let mut rng = Lcg(4);
        let images: Vec<RgbImage> = (0..8)
            .map(|_| RgbImage {
                width: w,
                height: h,
                data: (0..w * h * 3)
                    .map(|k| {
                        let p = k / 3;
                        (0.5 * truth(p % w, p / w) * (1.0 + 0.01 * rng.normal())) as f32
                    })
                    .collect(),
            })
            .collect();
        let f = flat_field(&images, 0.3).unwrap();
        assert_eq!(f.covered_pixels, w * h);
        let mean_truth = (0..w * h).map(|p| truth(p % w, p / w)).sum::<f64>() / (w * h) as f64;
        let rms = ((0..w * h * 3)
            .map(|k| (f.gain[k] as f64 - truth((k / 3) % w, k / 3 / w) / mean_truth).powi(2))
            .sum::<f64>()
            / (w * h * 3) as f64)
            .sqrt();
        assert!(rms < 0.01 / 8f64.sqrt() * 2.0, "rms {rms}");
        let rn = f.relative_noise.unwrap();
        assert!((rn - 0.01 / 8f64.sqrt()).abs() < 0.001, "{rn}");
        let dark = vec![RgbImage {
            width: 4,
            height: 4,
            data: vec![0.0; 48],
        }];
        assert!(matches!(flat_field(&dark, 0.3), Err(RadiometricError::FlatDark { .. })));
    }

    #[test]
    #[allow(clippy::needless_range_loop)]
    fn colour_matrix_inverts_crosstalk() {
        let crosstalk = [[0.8, 0.15, 0.05], [0.1, 0.8, 0.1], [0.05, 0.2, 0.75]];
        let refs: Vec<[f64; 3]> = (0..24)
            .map(|k| {
                let k = k as f64;
                [
                    0.05 + 0.9 * (k * 0.37).fract(),
                    0.05 + 0.9 * (k * 0.61).fract(),
                    0.05 + 0.9 * (k * 0.83).fract(),
                ]
            })
            .collect();
        let meas: Vec<[f64; 3]> = refs
            .iter()
            .map(|r| std::array::from_fn(|i| 2.0 * (0..3).map(|k| crosstalk[i][k] * r[k]).sum::<f64>()))
            .collect();
        let cm = colour_matrix(&meas, &refs).unwrap();
        assert!(cm.residual_max < 1e-9, "{cm:?}");
        // matrix · (2 · crosstalk) = identity
        for i in 0..3 {
            for j in 0..3 {
                let v: f64 = (0..3).map(|k| cm.matrix[i][k] * 2.0 * crosstalk[k][j]).sum();
                assert!((v - f64::from(u8::from(i == j))).abs() < 1e-9, "{i},{j}: {v}");
            }
        }
        // grey patches only: degenerate, refused with the condition number
        let grey: Vec<[f64; 3]> = (1..10).map(|k| [k as f64 / 10.0; 3]).collect();
        let e = colour_matrix(&grey, &grey).unwrap_err();
        assert!(matches!(e, RadiometricError::ColourDegenerate { .. }), "{e}");
        assert!(matches!(
            colour_matrix(&meas[..2], &refs[..2]),
            Err(RadiometricError::TooFewPatches { patches: 2 })
        ));
        let mut bad = meas.clone();
        bad[5][1] = f64::NAN;
        assert!(matches!(
            colour_matrix(&bad, &refs),
            Err(RadiometricError::BadPatch { index: 5, .. })
        ));
    }
}
