//! `gonio complete DATASET --prior P --out FULL`: a sparsely measured dataset completed to
//! the full grid in an angular prior (`gonio-sparse`).
//!
//! Every measured pair of every texel is used: per texel and channel, the MAP estimate of
//! the prior's coefficients (ridge with the prior's eigenvalues) from all of the texel's
//! measured values; the operator is factored once (every texel measured the same pairs).
//! Measured images are written through the store unchanged (their SHA-256 is checked
//! against the input's record); every other pair of the sweep gets status `predicted` with
//! its predicted RMS error. Substituted measurements are used at their grid position (as
//! `compress` does); skipped pairs are predicted.

use super::prior::sample_name;
use super::sparse::load_prior;
use crate::compress::data::DatasetViews;
use crate::plan::sparse::psnr_of_mse;
use crate::store::{self, Dataset, MeasurementRecord, MeasurementStatus, FORMAT_VERSION};
use anyhow::{bail, Context, Result};
use gonio_devices::image::RgbImage;
use gonio_devices::rig::RigSpec;
use gonio_sparse::complete::{holdout_check, Holdout, CENSORED_ITERATIONS};
use gonio_sparse::joint::{self, JointOptions, JointReport};
use gonio_sparse::{Completion, Conditioning, Prior};
use nalgebra::DMatrix;
use rayon::prelude::*;
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct CompleteArgs {
    /// The sparsely measured dataset.
    pub dataset: PathBuf,
    /// The prior (.gprior file or `default`).
    #[arg(long)]
    pub prior: Option<String>,
    /// Use only the prior's leading C components (at most the number of measured pairs).
    #[arg(long)]
    pub components: Option<usize>,
    /// The completed dataset (full grid).
    #[arg(long)]
    pub out: PathBuf,
    /// Measurement noise RMS to assume, on the 8-bit scale (codes); added to the prior's
    /// out-of-basis variance in the MAP weights.
    #[arg(long, default_value_t = 0.0)]
    pub noise_codes: f64,
    /// How measured pairs are weighed: `sensor` (each pair by its own sensor noise, from
    /// the camera of the rig recorded in the manifest and the pair's readings: shot noise
    /// grows with the signal and the gamma space stretches the dark end; docs/guide/sparse.md)
    /// or `constant` (one variance for every pair: the prior's ρ_p plus --noise-codes).
    /// `sensor` falls back to `constant`, with a warning, when the manifest has no rig.
    #[arg(long, default_value = "sensor", value_parser = ["sensor", "constant"])]
    pub noise_model: String,
    /// Readings at or above this linear value were clipped at the sensor's full scale and
    /// are fitted as lower bounds, not as values (a clipped highlight would drag the whole
    /// texel's ABRDF down). `off` fits them as values. Default: 1 (the full scale of
    /// `normalized_signal`) for single exposures, off for HDR datasets (their merged
    /// values go above 1).
    #[arg(long, value_name = "LEVEL|off")]
    pub clip: Option<String>,
    #[arg(long)]
    pub force: bool,
    #[arg(long)]
    pub json: bool,
}

/// Columns per chunk of the per-texel solves (fixed, so results do not depend on threads).
const CHUNK: usize = 4096;

/// Coefficients (K × M) of every texel-channel from the measured images (`images[i]` is
/// the linear interleaved image of `c.measured[i]`, M values each).
pub fn coefficients(c: &Completion, images: &[&[f32]]) -> DMatrix<f64> {
    let space = c.prior.space();
    let m = images.first().map_or(0, |i| i.len());
    let s = images.len();
    let k = c.prior.components();
    let chunks: Vec<DMatrix<f64>> = (0..m.div_ceil(CHUNK))
        .into_par_iter()
        .map(|ci| {
            let (a, b) = (ci * CHUNK, ((ci + 1) * CHUNK).min(m));
            let y = DMatrix::<f64>::from_fn(s, b - a, |i, j| space.forward(images[i][a + j] as f64));
            c.coefficients(&y)
        })
        .collect();
    let mut out = DMatrix::<f64>::zeros(k, m);
    for (ci, ch) in chunks.iter().enumerate() {
        out.columns_mut(ci * CHUNK, ch.ncols()).copy_from(ch);
    }
    out
}

/// Each measured image's noise in model space under the sensor's model
/// (`gonio_sparse::noise::pair_noise`), in the order of `images`.
pub fn sensor_pair_noise(
    space: gonio_sparse::ValueSpace,
    images: &[&[f32]],
    sensor: &gonio_devices::hdr::SensorNoise,
) -> Vec<f64> {
    images
        .iter()
        .map(|img| gonio_sparse::noise::pair_noise(space, img, |x| sensor.variance(x)))
        .collect()
}

/// [`coefficients`] for readings clipped at the sensor's full scale `full_scale` (linear):
/// readings at or above it are lower bounds ([`Completion::coefficients_censored`]).
/// Returns the coefficients and the number of clipped readings.
pub fn coefficients_censored(c: &Completion, images: &[&[f32]], full_scale: f64) -> (DMatrix<f64>, usize) {
    let space = c.prior.space();
    let ceiling = space.forward(full_scale);
    let m = images.first().map_or(0, |i| i.len());
    let s = images.len();
    let k = c.prior.components();
    let chunks: Vec<(DMatrix<f64>, usize)> = (0..m.div_ceil(CHUNK))
        .into_par_iter()
        .map(|ci| {
            let (a, b) = (ci * CHUNK, ((ci + 1) * CHUNK).min(m));
            let y = DMatrix::<f64>::from_fn(s, b - a, |i, j| space.forward(images[i][a + j] as f64));
            c.coefficients_censored(&y, ceiling, CENSORED_ITERATIONS)
        })
        .collect();
    let mut out = DMatrix::<f64>::zeros(k, m);
    let mut clipped = 0;
    for (ci, (ch, n)) in chunks.iter().enumerate() {
        out.columns_mut(ci * CHUNK, ch.ncols()).copy_from(ch);
        clipped += n;
    }
    (out, clipped)
}

/// The predicted linear image of pair `p`.
pub fn predict_image(c: &Completion, a: &DMatrix<f64>, p: usize) -> Vec<f32> {
    let space = c.prior.space();
    c.predict_pair(p, a).iter().map(|&y| space.inverse(y) as f32).collect()
}

/// Texels (of the measured values) that are black everywhere or saturated somewhere.
pub fn count_ill(images: &[&[f32]], texels: usize) -> (usize, usize) {
    let mut black = 0;
    let mut saturated = 0;
    for t in 0..texels {
        let mut max = 0f32;
        for img in images {
            max = max.max(img[3 * t]).max(img[3 * t + 1]).max(img[3 * t + 2]);
        }
        if max <= 1e-6 {
            black += 1;
        }
        if max >= 1.0 {
            saturated += 1;
        }
    }
    (black, saturated)
}

/// The noise variance (model space) for the MAP weights: the prior's out-of-basis variance
/// plus the assumed measurement noise.
pub fn noise_var(prior: &Prior, noise_codes: f64) -> f64 {
    prior.header.residual_var + (noise_codes / 255.0).powi(2)
}

/// Texels the joint fit learns the material's Gaussian from (evenly spread; 3 channels each).
pub const JOINT_FIT_TEXELS: usize = 4096;

/// The joint completion (`gonio_sparse::joint`): the material's Gaussian in the prior's
/// coefficient space, fitted by EM on up to [`JOINT_FIT_TEXELS`] spread texels of the
/// measured images, then applied to every texel.
pub fn joint_completion<'a>(
    prior: &'a Prior,
    measured: &[usize],
    images: &[&[f32]],
    noise_floor: f64,
) -> Result<(Completion<'a>, JointReport)> {
    let space = prior.space();
    let texels = images.first().map_or(0, |i| i.len() / 3);
    let pick = super::prior::spread_texels(texels, JOINT_FIT_TEXELS);
    let y = DMatrix::<f64>::from_fn(images.len(), pick.len() * 3, |i, j| {
        space.forward(images[i][3 * pick[j / 3] + j % 3] as f64)
    });
    let opts = JointOptions {
        fit_columns: y.ncols(),
        ..JointOptions::default()
    };
    Ok(joint::fit(prior, measured, &y, noise_floor, &opts)?)
}

/// Held-back residual on up to 1000 spread texels (3000 texel-channels).
pub fn holdout(c: &Completion, images: &[&[f32]], texels: usize) -> Option<Holdout> {
    let space = c.prior.space();
    let pick = super::prior::spread_texels(texels, 1000);
    let y = DMatrix::<f64>::from_fn(images.len(), pick.len() * 3, |i, j| {
        space.forward(images[i][3 * pick[j / 3] + j % 3] as f64)
    });
    holdout_check(c.prior, &c.measured, &y, c.noise_var, 8)
}

#[derive(Serialize)]
struct CompleteJson {
    out: String,
    prior: String,
    measured: usize,
    predicted: usize,
    conditioning: Conditioning,
    /// Predicted PSNR of the completed dataset (8-bit sRGB scale, from the posterior).
    predicted_psnr_db: f64,
    black_texels: usize,
    saturated_texels: usize,
    /// Readings at or above the clip level, fitted as lower bounds.
    clipped_readings: usize,
    holdout: Option<Holdout>,
    warnings: Vec<String>,
}

pub fn run(a: CompleteArgs) -> Result<ExitCode> {
    let (prior, prior_path) = load_prior(a.prior.as_deref())?;
    let prior = super::sparse::with_components(prior, a.components)?;
    let ds = DatasetViews::open(&a.dataset).with_context(|| format!("opening {}", a.dataset.display()))?;
    super::prior::check_dataset(&prior, &ds)
        .with_context(|| format!("prior {} for {}", prior_path.display(), a.dataset.display()))?;
    let (_, records) = store::load(&a.dataset)?;
    let l = ds.n_lights();
    let d = l * ds.n_views();
    let mut by_index: Vec<Option<MeasurementRecord>> = vec![None; d];
    for r in records {
        if matches!(
            r.status,
            MeasurementStatus::Measured | MeasurementStatus::Substituted { .. }
        ) {
            let i = r.index;
            by_index[i] = Some(r);
        }
    }
    let measured: Vec<usize> = (0..d).filter(|&p| by_index[p].is_some()).collect();
    let images: Vec<Vec<f32>> = measured
        .par_iter()
        .map(|&p| {
            ds.read_image(p % l, p / l)?
                .with_context(|| format!("pair {p}: recorded but no image"))
        })
        .collect::<Result<_>>()?;
    let refs: Vec<&[f32]> = images.iter().map(|v| v.as_slice()).collect();
    let mut warnings = Vec::new();
    let rig: Option<RigSpec> = serde_json::from_value(ds.header.rig.clone()).ok();
    let sensor = match (a.noise_model.as_str(), &rig) {
        ("sensor", Some(r)) => Some(r.sensor_noise()),
        ("sensor", None) => {
            warnings.push(format!(
                "{}: the manifest records no rig, so its sensor's noise is unknown: every pair \
                 weighed alike (--noise-model constant, --noise-codes {})",
                a.dataset.display(),
                a.noise_codes
            ));
            None
        }
        _ => None,
    };
    // Per measured pair: its measurement noise in model space.
    let pair_noise: Vec<f64> = match &sensor {
        Some(s) => sensor_pair_noise(prior.space(), &refs, s),
        None => vec![(a.noise_codes / 255.0).powi(2); measured.len()],
    };
    let clip: Option<f64> = match a.clip.as_deref() {
        Some("off") => None,
        Some(v) => Some(
            v.parse::<f64>()
                .ok()
                .filter(|x| x.is_finite() && *x > 0.0)
                .with_context(|| format!("--clip {v}: use a positive linear level (e.g. 1) or off"))?,
        ),
        // The rig's own clip level (none under HDR); a dataset without a rig: full scale.
        None => rig
            .as_ref()
            .map_or(Some(gonio_devices::rig::FULL_SCALE), |r| r.clip_level()),
    };
    let c = Completion::with_pair_noise(&prior, &measured, &pair_noise)
        .with_context(|| format!("completing {}", a.dataset.display()))?;
    let texels = ds.texels();
    let (black, saturated) = count_ill(&refs, texels);
    let hold = holdout(&c, &refs, texels);
    let (coeffs, clipped) = match clip {
        Some(level) => coefficients_censored(&c, &refs, level),
        None => (coefficients(&c, &refs), 0),
    };
    if let Some(h) = hold.as_ref().filter(|h| h.outside_prior) {
        warnings.push(format!(
            "material outside the prior: on {} held-back measured pairs the error is {:.1} × the \
             predicted one ({:.4} vs {:.4} RMS, limit {:.1} ×); the predicted pairs are likely wrong \
             (mirror-like, strongly anisotropic or retro-reflective?) — measure more pairs",
            h.held_back, h.ratio, h.observed_rms, h.predicted_rms, h.limit
        ));
    }
    if black + saturated > 0 {
        warnings.push(format!(
            "{black} black and {saturated} saturated texels: regularized by the prior (bounded, never NaN)"
        ));
    }

    // Write the full grid through the store's one writer.
    let mut header = ds.header.clone();
    header.version = FORMAT_VERSION;
    let prior_id = format!(
        "{} ({})",
        prior_path
            .file_name()
            .map(|f| f.to_string_lossy().to_string())
            .unwrap_or_default(),
        &prior.header.payload_sha256[..16]
    );
    let mut extra = match header.extra.take() {
        serde_json::Value::Object(m) => m,
        _ => serde_json::Map::new(),
    };
    // The sparse dataset as seen from the output dataset's directory, with its SHA-256
    // (`from`, `from_sha256`; `gonio_dataset::store::provenance`): same bytes wherever it sits.
    let mut completion = serde_json::json!({
        "from": a.dataset.display().to_string(),
        "prior": prior_id,
        "measured": measured.len(),
        "conditioning": c.conditioning,
        "method": "per-texel MAP in the prior (ridge with the prior's eigenvalues), gamma space",
        "noise_model": if sensor.is_some() { "sensor" } else { "constant" },
        "clip": clip,
    });
    super::common::record_input(&mut completion, "from", &a.dataset, &a.out)?;
    extra.insert("completion".into(), completion);
    header.extra = serde_json::Value::Object(extra);
    let mut out = Dataset::create(&a.out, &header, a.force)?;
    // The input's plan (read only: the input dataset is never opened for writing).
    if let Ok(plan) = std::fs::read(a.dataset.join(store::PLAN_FILE)) {
        out.write_plan(&plan)?;
    }
    let (w, h) = (ds.width, ds.height);
    for (i, &p) in measured.iter().enumerate() {
        let rec = by_index[p].clone().expect("measured");
        let want = rec.image_sha256.clone();
        let img = RgbImage {
            width: w,
            height: h,
            data: images[i].clone(),
        };
        let stored = out.store(rec, Some(&img), None)?;
        if want.is_some() && stored.image_sha256 != want {
            bail!("pair {p}: the re-stored image differs from the measured one (EXR encoding changed?)");
        }
    }
    let mut order = measured.len();
    let mut mse_sum: f64 = pair_noise.iter().sum();
    for (p, rec) in by_index.iter().enumerate() {
        if rec.is_some() {
            continue;
        }
        let var = c.predicted_var(p);
        mse_sum += var;
        let img = RgbImage {
            width: w,
            height: h,
            data: predict_image(&c, &coeffs, p),
        };
        let mut rec = MeasurementRecord::new(p, order, ds.lights_deg[p % l], ds.views_deg[p / l]);
        rec.status = MeasurementStatus::Predicted {
            predicted_rmse_8bit: var.sqrt(),
            prior: prior_id.clone(),
        };
        out.store(rec, Some(&img), None)?;
        order += 1;
    }
    let predicted_psnr_db = psnr_of_mse(mse_sum / d as f64);
    let report = CompleteJson {
        out: a.out.display().to_string(),
        prior: prior_id,
        measured: measured.len(),
        predicted: d - measured.len(),
        conditioning: c.conditioning.clone(),
        predicted_psnr_db,
        black_texels: black,
        saturated_texels: saturated,
        clipped_readings: clipped,
        holdout: hold,
        warnings: warnings.clone(),
    };
    // The manifest's summary leaves out `out` (the dataset's own path as typed, which
    // --json reports): a dataset's bytes do not depend on where it was written.
    let mut stored = serde_json::to_value(&report)?;
    if let Some(o) = stored.as_object_mut() {
        o.remove("out");
    }
    out.finish(&serde_json::json!({ "completion": stored }))?;
    if a.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!(
            "{} ({}): {} measured + {} predicted → {}",
            a.dataset.display(),
            sample_name(&ds).unwrap_or_default(),
            report.measured,
            report.predicted,
            a.out.display()
        );
        println!(
            "  conditioning: MAP {:.3e}, plain least squares {:.3e} ({} components)",
            c.conditioning.map_condition, c.conditioning.least_squares_condition, c.conditioning.components
        );
        println!("  predicted PSNR {predicted_psnr_db:.2} dB (8-bit sRGB scale, from the posterior)");
        if let Some(h) = &report.holdout {
            println!(
                "  held-back check: {} pairs, error {:.2} × predicted (limit {:.1} ×)",
                h.held_back, h.ratio, h.limit
            );
        }
    }
    for wmsg in &warnings {
        eprintln!("warning: {wmsg}");
    }
    Ok(ExitCode::SUCCESS)
}
