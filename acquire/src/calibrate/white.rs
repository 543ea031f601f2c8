//! White-standard calibration: linear sensor values → BRDF (1/sr).
//!
//! The rig photographs a flat Lambertian standard of known albedo `ρ` (BRDF `ρ/π`) at the
//! recipe's (light, view) poses. Every frame is rectified exactly as an acquisition
//! rectifies it, and every texel gives one equation
//!
//! `value(x) = K · exposure · gain · (ρ/π) · E(x)`,  `E(x) = I · cos θ_l(x) / d(x)²`,
//!
//! with the lamp position taken from the rig's kinematics at the read-back axis positions,
//! so the light's falloff and angle over the sample area are modelled per texel rather than
//! absorbed into a single factor (see [`super::apply`]). `K` (per channel) is the least
//! squares fit over all texels of all poses; the residuals say how well the model holds
//! (vignetting, stray light, a lamp that is not where the kinematics say). Exposure and
//! gain are divided out, so a calibration made at one exposure applies at another.

use super::{CalibrateError, CalibrationResult, Recipe, RunOutput};
use crate::develop::frame_to_linear;
use crate::develop::rectify::{rectify_frame, RectifyParams};
use crate::develop::{LampModel, Radiometric};
use crate::rig::Rig;
use serde::{Deserialize, Serialize};
use std::time::Instant;
use thiserror::Error;

/// The recipe's `[white_standard]` table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WhiteStandardSpec {
    /// Albedo (directional-hemispherical reflectance) of the standard per channel, from its
    /// certificate.
    pub albedo: [f64; 3],
    /// Rectified texels per side used for the fit (the model is smooth; a few thousand
    /// texels per pose are plenty).
    #[serde(default = "default_texels")]
    pub texels: usize,
    /// A directory of dark / response / flat / colour results (`DIR/*/calibration.json`, made
    /// on this rig; other kinds there are ignored) to correct each frame with before the fit,
    /// exactly as `gonio acquire --calibration` corrects it: `K` is only valid for values
    /// corrected the same way, so the result lists their ids and an acquisition applying
    /// other corrections refuses it. Relative paths are relative to the working directory.
    #[serde(default)]
    pub corrections: Option<String>,
}

fn default_texels() -> usize {
    32
}

#[derive(Debug, Error, Clone, PartialEq)]
pub enum WhiteError {
    #[error(
        "pose {index} (light {light:?}, view {view:?}): {fraction:.1} % of the texels are saturated \
         (≥ {level} of full scale): lower the exposure"
    )]
    Saturated {
        index: usize,
        light: [f64; 2],
        view: [f64; 2],
        fraction: f64,
        level: f64,
    },
    #[error(
        "pose {index} (light {light:?}, view {view:?}): the standard is dark (mean {mean:.2e} of full scale): \
         lamp off, shutter closed or exposure too short"
    )]
    Dark {
        index: usize,
        light: [f64; 2],
        view: [f64; 2],
        mean: f64,
    },
    #[error("pose {index}: rectification failed: {message}")]
    Rectify { index: usize, message: String },
    #[error("{0}")]
    Lamp(#[from] crate::develop::DevelopError),
    #[error("no texel is lit at any pose: cannot fit the scale")]
    NoData,
    #[error("[white_standard] corrections: {0}")]
    Corrections(String),
}

/// One pose of the fit.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WhitePose {
    pub light_deg: [f64; 2],
    pub view_deg: [f64; 2],
    pub exposure_s: f64,
    pub gain: f64,
    /// Where the homography came from (`markers` or `pose`).
    pub homography: String,
    /// Mean over the sample of measured / modelled value per channel (1 = the fit holds).
    pub mean_ratio: [f64; 3],
    /// RMS and largest |measured / modelled − 1| over the texels (all channels).
    pub residual_rms: f64,
    pub residual_max: f64,
}

/// K fitted on the first `poses` poses (error against run time).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WhiteEffort {
    pub poses: usize,
    /// Rig time to capture them (s).
    pub capture_s: f64,
    pub k: [f64; 3],
    /// Largest |K − K_ref| / K_ref over the channels (percent); K_ref is the simulator's
    /// truth, or on real rigs the fit with all poses.
    pub k_error_percent: f64,
}

/// The result of a white-standard run (`calibration.json` field `white_standard`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct WhiteStandardCalibration {
    pub albedo: [f64; 3],
    /// The conversion an acquisition applies.
    pub radiometric: Radiometric,
    pub texels: usize,
    pub sample_mm: f64,
    pub poses: Vec<WhitePose>,
    /// Over all texels and poses: RMS and largest |measured / modelled − 1|.
    pub residual_rms: f64,
    pub residual_max: f64,
    /// Simulator only: the true K (sensor sensitivity / full well, per exposure second and
    /// unit gain) and the fit's error against it (percent per channel).
    pub truth_k: Option<[f64; 3]>,
    pub k_error_percent: Option<[f64; 3]>,
    pub effort: Vec<WhiteEffort>,
    /// Ids of the raw-frame corrections (dark, response, flat, colour) the frames were
    /// corrected with before the fit; empty = uncorrected linear DN values.
    #[serde(default)]
    pub corrections: Vec<String>,
}

/// Values this close to full scale count as saturated.
const SATURATION: f64 = 0.98;
/// Largest share of saturated texels a pose may have (percent).
const MAX_SATURATED_PERCENT: f64 = 0.5;
/// Mean value (of full scale) below which a pose is "dark".
const DARK_MEAN: f64 = 1e-3;

/// Per-pose data kept for the residuals: measured value and model (without K) per texel.
struct PoseData {
    values: Vec<f32>,
    model: Vec<f64>,
}

/// The simulated sensor's true K (`sensitivity / full well`), from the rig's ground truth.
fn sim_truth_k(rig: &Rig) -> Option<f64> {
    rig.truth.as_ref().and_then(|t| t.sensor()).map(|s| s.k())
}

fn fit_k(data: &[PoseData]) -> [f64; 3] {
    let mut num = [0.0; 3];
    let mut den = [0.0; 3];
    for p in data {
        for (v, m) in p.values.chunks_exact(3).zip(p.model.chunks_exact(3)) {
            for c in 0..3 {
                num[c] += v[c] as f64 * m[c];
                den[c] += m[c] * m[c];
            }
        }
    }
    std::array::from_fn(|c| if den[c] > 0.0 { num[c] / den[c] } else { f64::NAN })
}

pub(super) async fn run_white(recipe: &Recipe, rig: &Rig) -> Result<RunOutput, CalibrateError> {
    let name = recipe.name.clone();
    let rig_name = rig.spec.name.clone();
    let spec = recipe
        .white_standard
        .clone()
        .expect("validated: white-standard recipes have [white_standard]");
    let fail = |cause: WhiteError| CalibrateError::White {
        recipe: name.clone(),
        cause,
    };
    let lamp = LampModel::from_rig(&rig.spec).map_err(|e| fail(e.into()))?;
    let correction = match &spec.corrections {
        None => None,
        Some(dir) => {
            load_corrections(std::path::Path::new(dir), &rig.spec).map_err(|m| fail(WhiteError::Corrections(m)))?
        }
    };
    let t0 = rig.time();
    let config = super::prepare_rig(recipe, rig).await?;
    let policy = super::calibration_policy(recipe, rig)?;
    let params = RectifyParams {
        width: spec.texels,
        height: spec.texels,
        sample_mm: rig.sample_mm,
        max_supersample: 8,
    };
    let intr = rig.spec.camera.intrinsics();
    tracing::info!(recipe = %name, poses = recipe.poses.len(), "white standard: capturing");
    let mut data = Vec::new();
    let mut poses = Vec::new();
    let mut capture_times = Vec::new();
    let mut prev: Option<Vec<f64>> = None;
    for (index, pose) in recipe.poses.iter().enumerate() {
        let light = pose.light.unwrap_or(recipe.light);
        let (q, q_read) = super::reach_pose(recipe, rig, index, pose.view, light, prev.as_deref()).await?;
        let frame = super::capture_at(recipe, rig, &policy, &config, index, pose.view).await?;
        let (raw, saturated_px) = match &correction {
            Some(c) => {
                let (img, n) = c.apply(&frame).map_err(|e| fail(e.into()))?;
                (img, Some(n))
            }
            None => (frame_to_linear(&frame), None),
        };
        let cam_pose = rig.kinematics.camera_pose(&q_read);
        let rect = rectify_frame(&raw, &intr, &cam_pose, &rig.border, &params).map_err(|e| {
            fail(WhiteError::Rectify {
                index,
                message: e.to_string(),
            })
        })?;
        let n = rect.image.data.len().max(1);
        // Corrected values have no fixed full scale: there the raw frame's saturated pixels
        // count, as a share of the standard's footprint (frame pixels above 5 % of the
        // brightest).
        let fraction = match saturated_px {
            None => {
                let saturated = rect.image.data.iter().filter(|&&v| v as f64 >= SATURATION).count();
                100.0 * saturated as f64 / n as f64
            }
            Some(s) => {
                let top = raw.data.iter().fold(0f32, |a, &b| a.max(b));
                let lit = raw.data.chunks_exact(3).filter(|p| p[1] > 0.05 * top).count().max(1);
                100.0 * s as f64 / lit as f64
            }
        };
        if fraction > MAX_SATURATED_PERCENT {
            return Err(fail(WhiteError::Saturated {
                index,
                light,
                view: pose.view,
                fraction,
                level: SATURATION,
            }));
        }
        let mean = rect.image.data.iter().map(|&v| v as f64).sum::<f64>() / n as f64;
        if mean.is_nan() || mean < DARK_MEAN {
            return Err(fail(WhiteError::Dark {
                index,
                light,
                view: pose.view,
                mean,
            }));
        }
        let lamp_at = rig.kinematics.light_position(&q_read);
        let e = lamp.irradiance_map(lamp_at, &params);
        let scale = frame.meta.exposure * frame.meta.gain;
        let model: Vec<f64> = e
            .iter()
            .flat_map(|&e| (0..3).map(move |c| scale * spec.albedo[c] / std::f64::consts::PI * e))
            .collect();
        poses.push(WhitePose {
            light_deg: light,
            view_deg: pose.view,
            exposure_s: frame.meta.exposure,
            gain: frame.meta.gain,
            homography: serde_json::to_value(rect.source)
                .ok()
                .and_then(|v| v.as_str().map(String::from))
                .unwrap_or_default(),
            mean_ratio: [0.0; 3],
            residual_rms: 0.0,
            residual_max: 0.0,
        });
        data.push(PoseData {
            values: rect.image.data,
            model,
        });
        capture_times.push(rig.time() - t0);
        prev = Some(q);
    }
    let k = fit_k(&data);
    if k.iter().any(|x| !(x.is_finite() && *x > 0.0)) {
        return Err(fail(WhiteError::NoData));
    }
    // Residuals of the model with the fitted K.
    let (mut sum2, mut count, mut worst) = (0.0, 0usize, 0.0f64);
    for (p, d) in poses.iter_mut().zip(&data) {
        let (mut s2, mut cnt, mut mx) = (0.0, 0usize, 0.0f64);
        let mut ratio_sum = [0.0; 3];
        let mut ratio_n = [0usize; 3];
        for (v, m) in d.values.chunks_exact(3).zip(d.model.chunks_exact(3)) {
            for c in 0..3 {
                let model = k[c] * m[c];
                if model <= 0.0 {
                    continue;
                }
                let r = v[c] as f64 / model;
                ratio_sum[c] += r;
                ratio_n[c] += 1;
                s2 += (r - 1.0) * (r - 1.0);
                cnt += 1;
                mx = mx.max((r - 1.0).abs());
            }
        }
        p.mean_ratio = std::array::from_fn(|c| ratio_sum[c] / ratio_n[c].max(1) as f64);
        p.residual_rms = (s2 / cnt.max(1) as f64).sqrt();
        p.residual_max = mx;
        sum2 += s2;
        count += cnt;
        worst = worst.max(mx);
    }
    let simulated = rig.clock.is_some();
    // The truth K is on the scale of uncorrected values (DN / max DN); corrected values are
    // on the response curve's own scale, which has no truth to compare with.
    let truth_k = sim_truth_k(rig)
        .filter(|_| simulated && correction.is_none())
        .map(|k| [k; 3]);
    let k_error_percent = truth_k.map(|t| std::array::from_fn(|c| 100.0 * (k[c] - t[c]) / t[c]));
    let reference = truth_k.unwrap_or(k);
    let effort = (1..=data.len())
        .map(|n| {
            let start = Instant::now();
            let kn = fit_k(&data[..n]);
            tracing::trace!(n, fit_s = start.elapsed().as_secs_f64(), "white effort row");
            WhiteEffort {
                poses: n,
                capture_s: capture_times[n - 1],
                k: kn,
                k_error_percent: (0..3)
                    .map(|c| (100.0 * (kn[c] - reference[c]) / reference[c]).abs())
                    .fold(0.0, f64::max),
            }
        })
        .collect();
    let white = WhiteStandardCalibration {
        albedo: spec.albedo,
        radiometric: Radiometric { k, lamp },
        texels: spec.texels,
        sample_mm: rig.sample_mm,
        poses,
        residual_rms: (sum2 / count.max(1) as f64).sqrt(),
        residual_max: worst,
        truth_k,
        k_error_percent,
        effort,
        corrections: correction
            .as_ref()
            .map(|c| c.sources.iter().map(|s| s.id.clone()).collect())
            .unwrap_or_default(),
    };
    let result = CalibrationResult {
        white_standard: Some(white),
        rig_time_s: rig.time() - t0,
        ..CalibrationResult::new(recipe, rig_name, simulated)
    }
    .seal();
    Ok(RunOutput { result, corners: None })
}

/// The raw-frame correction of the dark / response / flat / colour results in `dir`,
/// checked against the rig's camera; `None` if `dir` holds none of them.
fn load_corrections(
    dir: &std::path::Path,
    rig: &gonio_devices::rig::RigSpec,
) -> Result<Option<crate::develop::RawCorrection>, String> {
    use super::apply::{load_dir, AppliedCalibration};
    let results: Vec<_> = load_dir(dir, &rig.name)
        .map_err(|e| e.to_string())?
        .into_iter()
        .filter(|r| matches!(r.kind.as_str(), "dark" | "response" | "flat" | "colour"))
        .collect();
    if results.is_empty() {
        return Err(format!(
            "{} holds no dark, response, flat or colour result: run those recipes first (--out {}/KIND)",
            dir.display(),
            dir.display()
        ));
    }
    let (applied, _) = AppliedCalibration::from_results(&results).map_err(|e| e.to_string())?;
    if let Some(c) = &applied.raw {
        let cam = &rig.camera;
        c.check_camera(cam.width, cam.height, cam.bit_depth)
            .map_err(|e| e.to_string())?;
    }
    tracing::info!(corrections = ?applied.corrections(), "white standard: frames corrected before the fit");
    Ok(applied.raw)
}
