//! Radiometric recipes: dark frame, camera response (Debevec-Malik), flat field, colour.
//!
//! Each recipe captures frames at one (light, view) pose through the `Camera` trait and
//! hands them to `gonio_calibration::radiometric`. On a simulated rig the result also holds
//! the simulator's truth (the sensor model of the rig file) and the error of every estimate
//! against it, and an effort table: the same fit on fewer frames or exposures, with the rig
//! time those cost, so a lab can choose how long to calibrate.
//!
//! Order: `dark` and `response` stand alone; `flat` and `colour` need linear values, so
//! they take a response curve (`[radiometric] response = "DIR"`, the output directory or
//! `DIR/calibration.json` of a response run, checked before the rig moves), or recover one
//! from their own bracket when it has ≥ 2 exposures, or otherwise assume a linear camera
//! (said in `notes`). An acquisition applies a flat or colour result only with the response
//! result it was linearised with, so the shipped flat and colour recipes both name
//! `cal/response`.
//!
//! Maps (dark, flat) are stored at block resolution (`map_block` pixels per side): the
//! sensor effects they describe are smooth, and a full-resolution map would make
//! `calibration.json` tens of megabytes.

use super::{CalibrateError, CalibrationResult, Recipe, RecipeKind, RunOutput};
use crate::develop::BlockMap;
use crate::rig::{Rig, SensorResponse, SensorTruth};
use gonio_calibration::radiometric::{
    colour_matrix, dark_frame, flat_field, merge_hdr, recover_response, ColourMatrix, DarkFrame, FlatField,
    HdrDiagnosis, RadiometricError, ResponseCurve, ResponseFit, ResponseOptions,
};
use gonio_devices::image::RgbImage;
use gonio_devices::{CameraConfig, Frame, Vec3};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// The recipe's `[radiometric]` table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RadiometricSpec {
    /// Frames averaged (dark, flat: per exposure).
    #[serde(default = "default_frames")]
    pub frames: usize,
    /// Exposure bracket (s); dark: the first is the dark exposure (default: the rig's).
    #[serde(default)]
    pub exposures_s: Vec<f64>,
    /// Debevec-Malik options (levels, λ, samples, validity limits).
    #[serde(default)]
    pub fit: ResponseOptions,
    /// A response calibration for flat and colour: the `calibration.json` of a `response`
    /// run or its output directory; relative paths are relative to the working directory.
    /// Checked before the rig moves (a response result, made on this rig's camera).
    #[serde(default)]
    pub response: Option<String>,
    /// Flat field: pixels below this fraction of the brightest are outside the target.
    #[serde(default = "default_min_signal")]
    pub min_signal: f64,
    /// Colour target layout and the patches' known linear-sRGB reflectances.
    #[serde(default)]
    pub patches: Option<PatchGrid>,
    /// Effort table: frame / exposure counts to repeat the fit with (each ≤ the total).
    #[serde(default)]
    pub effort: Vec<usize>,
    /// Pixels per side of a stored map block.
    #[serde(default = "default_block")]
    pub map_block: usize,
}

fn default_frames() -> usize {
    8
}
fn default_min_signal() -> f64 {
    0.5
}
fn default_block() -> usize {
    16
}

/// A grid of flat patches centred on the sample, row 0 at the +y edge, column 0 at −x.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PatchGrid {
    pub cols: usize,
    pub rows: usize,
    pub pitch_mm: f64,
    /// Fraction of the pitch (centred) averaged per patch: edges blur and mix neighbours.
    #[serde(default = "default_inset")]
    pub inset: f64,
    /// Reflectances row by row (`cols · rows` entries).
    pub reference: Vec<[f64; 3]>,
}

fn default_inset() -> f64 {
    0.5
}

impl RadiometricSpec {
    /// Check the table for `kind`; errors name the key.
    pub fn validate(&self, kind: RecipeKind) -> Result<(), (String, String)> {
        let bad = |k: &str, m: String| Err((format!("radiometric.{k}"), m));
        if !(1..=1000).contains(&self.frames) {
            return bad("frames", format!("{}: valid range is 1 ..= 1000", self.frames));
        }
        if let Some(e) = self.exposures_s.iter().find(|e| !(e.is_finite() && **e > 0.0)) {
            return bad("exposures_s", format!("{e}: exposures must be > 0 s"));
        }
        if kind == RecipeKind::Response && self.exposures_s.len() < 2 {
            return bad(
                "exposures_s",
                format!(
                    "{:?}: a response recipe needs a bracket of at least 2 exposures",
                    self.exposures_s
                ),
            );
        }
        if self.response.is_some() && !matches!(kind, RecipeKind::Flat | RecipeKind::Colour) {
            return bad(
                "response",
                format!(
                    "only flat and colour recipes take a response result, this is a {} recipe: remove the key",
                    kind.name()
                ),
            );
        }
        if !(self.min_signal > 0.0 && self.min_signal < 1.0) {
            return bad("min_signal", format!("{}: valid range is (0, 1)", self.min_signal));
        }
        if !(1..=256).contains(&self.map_block) {
            return bad("map_block", format!("{}: valid range is 1 ..= 256", self.map_block));
        }
        if kind == RecipeKind::Colour {
            let Some(p) = &self.patches else {
                return bad("patches", "a colour recipe needs [radiometric.patches]".into());
            };
            if p.cols * p.rows < 3 || p.reference.len() != p.cols * p.rows {
                return bad(
                    "patches.reference",
                    format!(
                        "{} references for {} × {} patches: need one per patch, at least 3",
                        p.reference.len(),
                        p.cols,
                        p.rows
                    ),
                );
            }
            if !(p.pitch_mm > 0.0 && p.pitch_mm.is_finite() && p.inset > 0.0 && p.inset <= 1.0) {
                return bad(
                    "patches",
                    format!("pitch_mm {} > 0 and inset {} in (0, 1] needed", p.pitch_mm, p.inset),
                );
            }
        }
        Ok(())
    }
}

/// One row of the error-versus-effort table.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RadiometricEffort {
    /// Frames (dark, flat) or exposures (response, colour) used.
    pub count: usize,
    /// Rig time to capture them (s).
    pub capture_s: f64,
    /// Wall time of the fit (s).
    pub fit_s: f64,
    /// What `error` measures (against the simulator's truth, or on real rigs against the
    /// estimate from all frames).
    pub metric: String,
    pub error: f64,
    pub failure: Option<String>,
}

/// Simulator truth of the dark frame (from the rig file's sensor model).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DarkTruth {
    /// Expected dark level (DN) before the clip at zero.
    pub mean_dn: f64,
    /// Read noise in DN at black (read noise · conversion · response slope at black).
    pub read_noise_dn: f64,
}

/// A colour patch: where, what was measured, what it should be.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PatchResult {
    pub index: usize,
    pub centre_px: [f64; 2],
    pub measured: [f64; 3],
    pub reference: [f64; 3],
    pub corrected: [f64; 3],
}

/// `calibration.json` field `radiometric`.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct RadiometricCalibration {
    pub view_deg: [f64; 2],
    pub light_deg: [f64; 2],
    pub exposures_s: Vec<f64>,
    pub dark: Option<DarkFrame>,
    pub dark_map: Option<BlockMap>,
    pub dark_truth: Option<DarkTruth>,
    pub response: Option<ResponseFit>,
    /// Simulator: RMS relative error of the recovered inverse response `exp g` against the
    /// truth where the hat weight is ≥ 0.05 (2.9 % … 96 % of full scale with the default
    /// limits), per channel (one free scale per channel).
    pub response_error_rms: Option<[f64; 3]>,
    /// Shift `g − ln f⁻¹` per channel (the free constant), used for the colour truth.
    #[serde(skip)]
    pub response_shift: Option<[f64; 3]>,
    pub hdr: Option<HdrDiagnosis>,
    pub flat: Option<FlatField>,
    pub flat_map: Option<BlockMap>,
    /// Simulator: RMS of (gain − vignetting truth) over the covered pixels, both normalised
    /// to mean 1 there. Includes the target's illumination non-uniformity (lamp falloff
    /// across the sample), which a flat taken on the sample cannot tell from vignetting.
    pub flat_error_rms: Option<f64>,
    pub colour: Option<ColourMatrix>,
    pub patches: Vec<PatchResult>,
    /// Simulator: `‖T/τ − I‖_F / √3` with `T = C · diag(e^{−shift}) · crosstalk`, τ its
    /// mean diagonal: how far the correction is from undoing the crosstalk.
    pub colour_matrix_error: Option<f64>,
    pub effort: Vec<RadiometricEffort>,
    /// Assumptions the run made (e.g. a linear response because none was given).
    pub notes: Vec<String>,
    /// Flat and colour runs: how their values were made linear — `response:ID` (the
    /// response result with that id), `own-bracket` (a curve fitted on the run's own
    /// bracket, not stored) or `linear` (camera assumed linear). An acquisition applies a
    /// flat or colour result only together with the same linearisation (see
    /// `develop::RawCorrection`): a gain or matrix measured on differently linearised values
    /// would scale each level differently. `None` in results of older builds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub linearisation: Option<String>,
}

impl RadiometricCalibration {
    /// The human-readable summary and effort table the CLI prints.
    pub fn table(&self) -> String {
        let mut s = String::new();
        if let Some(d) = &self.dark {
            s += &format!(
                "  dark: {} frames at {} s: mean {:.3?} DN, read noise {:?} DN, {:.1} % clipped at 0, {} hot pixels\n",
                d.frames,
                d.exposure_s,
                d.mean_dn,
                d.read_noise_dn.map(|r| r.map(|x| (x * 1000.0).round() / 1000.0)),
                100.0 * d.clipped_at_zero,
                d.hot_pixels
            );
        }
        if let Some(t) = &self.dark_truth {
            s += &format!(
                "  dark truth: mean {:.3} DN, read noise {:.3} DN\n",
                t.mean_dn, t.read_noise_dn
            );
        }
        if let Some(r) = &self.response {
            s += &format!(
                "  response: {} levels, samples {:?}, unobserved levels {:?}, residual {:.4?}\n",
                r.curve.levels, r.samples, r.unobserved_levels, r.residual_rms
            );
        }
        if let Some(e) = &self.response_error_rms {
            s += &format!("  response error vs truth (RMS relative, per channel): {:.4?}\n", e);
        }
        if let Some(h) = &self.hdr {
            s += &format!("  HDR: {}\n", h.summary());
        }
        if let Some(f) = &self.flat {
            s += &format!(
                "  flat: {} frames, {} covered pixels, gain {:.4} … {:.4}, noise {:?}\n",
                f.frames, f.covered_pixels, f.gain_min, f.gain_max, f.relative_noise
            );
        }
        if let Some(e) = self.flat_error_rms {
            s += &format!("  flat error vs vignetting truth: RMS {e:.5}\n");
        }
        if let Some(c) = &self.colour {
            s += &format!(
                "  colour: {} patches, condition {:.2}, residual RMS {:.4} max {:.4}, matrix {:.4?}\n",
                c.patches, c.condition, c.residual_rms, c.residual_max, c.matrix
            );
        }
        if let Some(e) = self.colour_matrix_error {
            s += &format!("  colour matrix error vs crosstalk truth: {e:.4}\n");
        }
        for n in &self.notes {
            s += &format!("  note: {n}\n");
        }
        if !self.effort.is_empty() {
            s += "  count  capture_s  fit_ms  error      metric\n";
            for e in &self.effort {
                match &e.failure {
                    None => {
                        s += &format!(
                            "  {:5}  {:9.2}  {:6.1}  {:9.5}  {}\n",
                            e.count,
                            e.capture_s,
                            1e3 * e.fit_s,
                            e.error,
                            e.metric
                        )
                    }
                    Some(f) => s += &format!("  {:5}  {:9.2}  refused: {f}\n", e.count, e.capture_s),
                }
            }
        }
        s
    }
}

fn fail(recipe: &Recipe, cause: RadiometricError) -> CalibrateError {
    CalibrateError::Radiometric {
        recipe: recipe.name.clone(),
        cause,
    }
}

fn spec_of(recipe: &Recipe) -> RadiometricSpec {
    recipe.radiometric.clone().unwrap_or(RadiometricSpec {
        frames: default_frames(),
        exposures_s: Vec::new(),
        fit: ResponseOptions::default(),
        response: None,
        min_signal: default_min_signal(),
        patches: None,
        effort: Vec::new(),
        map_block: default_block(),
    })
}

/// Move to the recipe's first pose (default: view straight down, lamp at `light`).
async fn goto_pose(recipe: &Recipe, rig: &Rig) -> Result<([f64; 2], [f64; 2], Vec<f64>), CalibrateError> {
    let (view, light) = match recipe.poses.first() {
        Some(p) => (p.view, p.light.unwrap_or(recipe.light)),
        None => ([0.0, 0.0], recipe.light),
    };
    let (q, _) = super::reach_pose(recipe, rig, 0, view, light, None).await?;
    Ok((view, light, q))
}

/// Frames at each exposure (`per` frames each), with the rig time after each exposure's
/// frames.
async fn capture(
    recipe: &Recipe,
    rig: &Rig,
    (config, view): (&CameraConfig, [f64; 2]),
    exposures: &[f64],
    per: usize,
) -> Result<(Vec<Vec<Frame>>, Vec<f64>), CalibrateError> {
    let t0 = rig.time();
    let policy = super::calibration_policy(recipe, rig)?;
    let dev = |cause| super::device_error(recipe, rig, rig.camera.name(), cause);
    let mut out = Vec::new();
    let mut times = Vec::new();
    for &e in exposures {
        let c = CameraConfig {
            exposure: e,
            ..config.clone()
        };
        let applied = rig.camera.configure(&c).await.map_err(dev)?;
        let mut frames = Vec::new();
        for _ in 0..per {
            frames.push(super::capture_at(recipe, rig, &policy, &applied, 0, view).await?);
        }
        out.push(frames);
        times.push(rig.time() - t0);
    }
    Ok((out, times))
}

/// Evenly spread subset of `n` of `total` indices, always with the first and last.
fn spread(total: usize, n: usize) -> Vec<usize> {
    if n >= total {
        return (0..total).collect();
    }
    if n <= 1 {
        return vec![0];
    }
    let mut v: Vec<usize> = (0..n)
        .map(|k| ((k as f64) * (total - 1) as f64 / (n - 1) as f64).round() as usize)
        .collect();
    v.dedup();
    v
}

/// The simulated sensor (the truth the estimates are checked against), from the rig's
/// ground truth.
fn sim_sensor(rig: &Rig) -> Option<SensorTruth> {
    rig.truth.as_ref().and_then(|t| t.sensor())
}

/// The simulated sensor's response: its curve, or the linear colour-clean default.
fn sim_response(rig: &Rig) -> Option<SensorResponse> {
    let truth = rig.truth.as_ref()?;
    truth.sensor_response().or(Some(SensorResponse {
        compression: 0.0,
        crosstalk: None,
    }))
}

/// Normalised DN values where the errors of a response curve are evaluated: where the hat
/// weight is ≥ 0.05. Closer to black the curve is ln of almost nothing (read noise and
/// dark current dominate, the fit gives them no weight) and relative errors there say
/// nothing about the calibration.
fn error_range(curve: &ResponseCurve) -> Vec<f64> {
    let v = curve.validity;
    let margin = 0.025 * (v.saturation_fraction - v.black_fraction);
    let (lo, hi) = (v.black_fraction + margin, v.saturation_fraction - margin);
    (0..200).map(|k| lo + (hi - lo) * (k as f64 + 0.5) / 200.0).collect()
}

/// RMS relative error of `exp g` against the true inverse response over [`error_range`],
/// after the free per-channel scale; also that scale's log (`g − ln f⁻¹`).
fn response_error(curve: &ResponseCurve, truth: &SensorResponse) -> ([f64; 3], [f64; 3]) {
    let ys = error_range(curve);
    let mut err = [0.0; 3];
    let mut shift = [0.0; 3];
    for c in 0..3 {
        let d: Vec<f64> = ys
            .iter()
            .map(|&y| curve.g_at(c, y * curve.max_dn) - truth.inverse(y).max(1e-12).ln())
            .collect();
        let s = d.iter().sum::<f64>() / d.len() as f64;
        shift[c] = s;
        err[c] = (d.iter().map(|x| ((x - s).exp() - 1.0).powi(2)).sum::<f64>() / d.len() as f64).sqrt();
    }
    (err, shift)
}

/// Linear images of frames: through the response (or a linear camera), one per frame.
fn linearise(frames: &[Frame], curve: &ResponseCurve) -> Result<Vec<RgbImage>, RadiometricError> {
    frames
        .iter()
        .map(|f| merge_hdr(std::slice::from_ref(f), curve).map(|h| h.image))
        .collect()
}

/// A response result named by `[radiometric] response` (flat and colour recipes), loaded
/// and checked against the rig before anything moves.
#[derive(Clone, Debug)]
struct GivenResponse {
    curve: ResponseCurve,
    /// Where it came from (a `notes` line).
    note: String,
    /// The [`RadiometricCalibration::linearisation`] tag: `response:ID`.
    tag: String,
}

/// Load `[radiometric] response = "PATH"`: the `calibration.json` of a response run, or the
/// directory holding it (the run's `--out`). Refused, with the fix, when the file is
/// missing or unreadable, is not a response result, or was made on another rig or a camera
/// of another bit depth (its curve would linearise the wrong codes).
// CalibrateError is large (other recipe kinds' variants); it is built once per failed run.
#[allow(clippy::result_large_err)]
fn load_response(
    recipe: &Recipe,
    path: &str,
    rig: &gonio_devices::rig::RigSpec,
) -> Result<GivenResponse, CalibrateError> {
    let bad = |message: String| CalibrateError::ResponseInput {
        recipe: recipe.name.clone(),
        path: path.to_string(),
        message,
    };
    let mut file = std::path::PathBuf::from(path);
    if file.is_dir() {
        file.push("calibration.json");
    }
    let text = std::fs::read_to_string(&file).map_err(|e| {
        bad(format!(
            "{}: {e}: run a response recipe first on rig `{}` (gonio calibrate calibration/recipes/response.toml \
             --rig RIG --out cal/response) and name its output directory or calibration.json here, or remove the \
             key to recover a response from this recipe's own bracket (relative paths are relative to the \
             working directory)",
            file.display(),
            rig.name
        ))
    })?;
    let r: CalibrationResult =
        serde_json::from_str(&text).map_err(|e| bad(format!("{}: not a calibration result: {e}", file.display())))?;
    let Some(fit) = r.radiometric.and_then(|x| x.response) else {
        return Err(bad(format!(
            "{} is a `{}` result (id {}) and holds no response curve: name the output of response.toml \
             (e.g. cal/response)",
            file.display(),
            r.kind,
            r.id
        )));
    };
    if r.rig != rig.name {
        return Err(bad(format!(
            "made on rig `{}`, this run is on rig `{}`: a response curve belongs to one camera; re-run \
             response.toml on rig `{}`",
            r.rig, rig.name, rig.name
        )));
    }
    let bits = rig.camera.bit_depth;
    let max = ((1u64 << bits.min(16)) - 1) as f64;
    if (fit.curve.max_dn - max).abs() > 0.5 {
        return Err(bad(format!(
            "the curve covers codes 0 ..= {}, this camera delivers {bits}-bit codes 0 ..= {max}: re-run \
             response.toml on this camera",
            fit.curve.max_dn
        )));
    }
    Ok(GivenResponse {
        curve: fit.curve,
        note: format!("response curve from {} (calibration {})", file.display(), r.id),
        tag: format!("response:{}", r.id),
    })
}

/// The response curve flat and colour runs use, a note on where it came from and its
/// [`RadiometricCalibration::linearisation`] tag: the `given` response result, else one
/// recovered from the bracket when it has ≥ 2 exposures, else a linear camera.
// CalibrateError is large (other recipe kinds' variants); it is built once per failed run.
#[allow(clippy::result_large_err)]
fn response_for(
    recipe: &Recipe,
    spec: &RadiometricSpec,
    given: Option<&GivenResponse>,
    bracket: &[Frame],
) -> Result<(ResponseCurve, String, String), CalibrateError> {
    if let Some(g) = given {
        return Ok((g.curve.clone(), g.note.clone(), g.tag.clone()));
    }
    let mut distinct: Vec<f64> = bracket.iter().map(|f| f.meta.exposure).collect();
    distinct.sort_by(|a, b| a.total_cmp(b));
    distinct.dedup();
    if distinct.len() >= 2 {
        let fit = recover_response(bracket, &spec.fit).map_err(|e| fail(recipe, e))?;
        return Ok((
            fit.curve,
            "response curve recovered from this recipe's own bracket".into(),
            "own-bracket".into(),
        ));
    }
    let max_dn = bracket.first().map(|f| f.max_dn() as f64).unwrap_or(4095.0);
    Ok((
        ResponseCurve::linear(max_dn, spec.fit.levels),
        "no response calibration given and a single exposure: the camera is assumed linear".into(),
        "linear".into(),
    ))
}

/// Run a dark, response, flat or colour recipe.
#[allow(clippy::result_large_err)]
pub async fn run_radiometric(recipe: &Recipe, rig: &Rig) -> Result<RunOutput, CalibrateError> {
    let spec = spec_of(recipe);
    spec.validate(recipe.kind)
        .map_err(|(key, message)| CalibrateError::RecipeInvalid {
            recipe: recipe.name.clone(),
            key,
            message,
        })?;
    // A named response result is checked before the rig moves.
    let given = match (&spec.response, recipe.kind) {
        (Some(path), RecipeKind::Flat | RecipeKind::Colour) => Some(load_response(recipe, path, &rig.spec)?),
        _ => None,
    };
    let name = recipe.name.clone();
    let rig_name = rig.spec.name.clone();
    let simulated = rig.clock.is_some();
    let t0 = rig.time();
    let config = super::prepare_rig(recipe, rig).await?;
    let (view, light, q) = goto_pose(recipe, rig).await?;
    let mut exposures = spec.exposures_s.clone();
    if exposures.is_empty() {
        exposures.push(recipe.exposure_s.unwrap_or(config.exposure));
    }
    let mut out = RadiometricCalibration {
        view_deg: view,
        light_deg: light,
        exposures_s: exposures.clone(),
        ..Default::default()
    };
    let truth_resp = if simulated { sim_response(rig) } else { None };
    tracing::info!(recipe = %name, kind = recipe.kind.name(), ?exposures, frames = spec.frames, "radiometric: capturing");
    match recipe.kind {
        RecipeKind::Dark => {
            rig.light.set(false, 0.0).await.map_err(|cause| CalibrateError::Move {
                recipe: name.clone(),
                rig: rig_name.clone(),
                device: "light".into(),
                cause,
            })?;
            let (frames, _) = capture(recipe, rig, (&config, view), &exposures[..1], spec.frames).await?;
            let frames = &frames[0];
            let d = dark_frame(frames).map_err(|e| fail(recipe, e))?;
            let per_frame = (rig.time() - t0) / frames.len() as f64;
            out.dark_map = Some(BlockMap::from_pixels(&d.mean, d.width, d.height, spec.map_block, false));
            let truth = truth_resp.as_ref().zip(sim_sensor(rig)).map(|(r, s)| {
                let max_dn = frames[0].max_dn() as f64;
                let conv = config.gain * max_dn / s.full_well_e;
                let dark_e = s.dark_current_e_s * exposures[0];
                let u = dark_e * conv / max_dn;
                let slope = (r.curve(u + 1e-4) - r.curve(u)) / 1e-4;
                DarkTruth {
                    mean_dn: r.curve(u) * max_dn,
                    read_noise_dn: s.read_noise_e * conv * slope,
                }
            });
            let reference = |d: &DarkFrame| d.read_noise_dn.map(|r| r.iter().sum::<f64>() / 3.0).unwrap_or(f64::NAN);
            let ref_rn = truth.as_ref().map(|t| t.read_noise_dn).unwrap_or_else(|| reference(&d));
            for &k in &spec.effort {
                let k = k.min(frames.len());
                let t = Instant::now();
                let r = dark_frame(&frames[..k]);
                let fit_s = t.elapsed().as_secs_f64();
                out.effort.push(match r {
                    Ok(dk) if dk.read_noise_dn.is_some() => RadiometricEffort {
                        count: k,
                        capture_s: per_frame * k as f64,
                        fit_s,
                        metric: "read noise relative error".into(),
                        error: (reference(&dk) - ref_rn).abs() / ref_rn,
                        failure: None,
                    },
                    Ok(_) => effort_failure(k, per_frame * k as f64, "one frame: no temporal noise estimate"),
                    Err(e) => effort_failure(k, per_frame * k as f64, &e.to_string()),
                });
            }
            out.dark = Some(d);
            out.dark_truth = truth;
            if simulated {
                out.notes.push(
                    "dark truth ignores the ADC's clip at 0: with most values clipped the measured \
                     mean is above and the noise below it"
                        .into(),
                );
            }
        }
        RecipeKind::Response | RecipeKind::Colour => {
            let (frames, times) = capture(recipe, rig, (&config, view), &exposures, 1).await?;
            let bracket: Vec<Frame> = frames.into_iter().flatten().collect();
            let t = Instant::now();
            let (curve, how) = if recipe.kind == RecipeKind::Response {
                let fit = recover_response(&bracket, &spec.fit).map_err(|e| fail(recipe, e))?;
                let c = fit.curve.clone();
                out.response = Some(fit);
                (c, "response recovered from the bracket".to_string())
            } else {
                let (c, how, tag) = response_for(recipe, &spec, given.as_ref(), &bracket)?;
                out.linearisation = Some(tag);
                (c, how)
            };
            let fit_s = t.elapsed().as_secs_f64();
            out.notes.push(how);
            if let Some(tr) = &truth_resp {
                let (e, s) = response_error(&curve, tr);
                if recipe.kind == RecipeKind::Response {
                    out.response_error_rms = Some(e);
                }
                out.response_shift = Some(s);
            }
            let hdr = merge_hdr(&bracket, &curve).map_err(|e| fail(recipe, e))?;
            out.hdr = Some(hdr.diagnosis.clone());
            if recipe.kind == RecipeKind::Response {
                for &k in &spec.effort {
                    let idx = spread(bracket.len(), k);
                    let sub: Vec<Frame> = idx.iter().map(|&i| bracket[i].clone()).collect();
                    let capture_s = idx
                        .iter()
                        .map(|&i| times[i] - if i > 0 { times[i - 1] } else { 0.0 })
                        .sum();
                    let t = Instant::now();
                    let r = recover_response(&sub, &spec.fit);
                    let fs = t.elapsed().as_secs_f64();
                    out.effort.push(match r {
                        Ok(f) => {
                            let (error, metric) = match &truth_resp {
                                Some(tr) => {
                                    let e = response_error(&f.curve, tr).0;
                                    (
                                        e.iter().copied().fold(0.0, f64::max),
                                        "response RMS relative error (worst channel) vs truth",
                                    )
                                }
                                None => {
                                    let e = curve_difference(&f.curve, &curve);
                                    (e, "response RMS relative difference vs the full bracket")
                                }
                            };
                            RadiometricEffort {
                                count: sub.len(),
                                capture_s,
                                fit_s: fs,
                                metric: metric.into(),
                                error,
                                failure: None,
                            }
                        }
                        Err(e) => effort_failure(sub.len(), capture_s, &e.to_string()),
                    });
                }
                let _ = fit_s;
            } else {
                colour_fit(recipe, rig, &spec, &q, &hdr.image, &mut out)?;
                let cm_all = out.colour.clone();
                for &k in &spec.effort {
                    let idx = spread(bracket.len(), k);
                    let sub: Vec<Frame> = idx.iter().map(|&i| bracket[i].clone()).collect();
                    let capture_s = idx
                        .iter()
                        .map(|&i| times[i] - if i > 0 { times[i - 1] } else { 0.0 })
                        .sum();
                    let t = Instant::now();
                    let mut tmp = RadiometricCalibration::default();
                    let r = response_for(recipe, &spec, given.as_ref(), &sub)
                        .and_then(|(c, _, _)| merge_hdr(&sub, &c).map_err(|e| fail(recipe, e)))
                        .and_then(|h| colour_fit(recipe, rig, &spec, &q, &h.image, &mut tmp));
                    let fs = t.elapsed().as_secs_f64();
                    out.effort.push(match (r, tmp.colour) {
                        (Ok(()), Some(c)) => RadiometricEffort {
                            count: sub.len(),
                            capture_s,
                            fit_s: fs,
                            metric: "corrected patch RMS error (linear reflectance)".into(),
                            error: c.residual_rms,
                            failure: None,
                        },
                        (Err(e), _) => effort_failure(sub.len(), capture_s, &e.to_string()),
                        (Ok(()), None) => effort_failure(sub.len(), capture_s, "no fit"),
                    });
                }
                out.colour = cm_all;
            }
        }
        RecipeKind::Flat => {
            let (frames, times) = capture(recipe, rig, (&config, view), &exposures, spec.frames).await?;
            // The response: given, or from the exposure-bracket (first frame per exposure).
            let bracket: Vec<Frame> = frames.iter().map(|f| f[0].clone()).collect();
            let (curve, how, tag) = response_for(recipe, &spec, given.as_ref(), &bracket)?;
            out.notes.push(how);
            out.linearisation = Some(tag);
            // All frames of the exposure with the most valid values (the middle of a bracket).
            let best = frames
                .iter()
                .enumerate()
                .max_by_key(|(_, f)| {
                    let v = curve.validity;
                    f[0].data
                        .iter()
                        .filter(|&&d| v.weight(d as f64 / f[0].max_dn() as f64) > 0.5)
                        .count()
                })
                .map(|(i, _)| i)
                .unwrap_or(0);
            let lin = linearise(&frames[best], &curve).map_err(|e| fail(recipe, e))?;
            let f = flat_field(&lin, spec.min_signal).map_err(|e| fail(recipe, e))?;
            let truth = simulated.then(|| vignetting_truth(rig, &f));
            let per_frame = (times[best] - if best > 0 { times[best - 1] } else { 0.0 }) / spec.frames as f64;
            for &k in &spec.effort {
                let k = k.min(lin.len());
                let t = Instant::now();
                let r = flat_field(&lin[..k], spec.min_signal);
                let fs = t.elapsed().as_secs_f64();
                out.effort.push(match r {
                    Ok(fk) => RadiometricEffort {
                        count: k,
                        capture_s: per_frame * k as f64,
                        fit_s: fs,
                        metric: if simulated {
                            "flat RMS error vs vignetting truth".into()
                        } else {
                            "flat RMS difference vs all frames".into()
                        },
                        error: match &truth {
                            Some(t) => gain_rms(&fk, t),
                            None => gain_rms(&fk, &f.gain),
                        },
                        failure: None,
                    },
                    Err(e) => effort_failure(k, per_frame * k as f64, &e.to_string()),
                });
            }
            out.flat_error_rms = truth.as_ref().map(|t| gain_rms(&f, t));
            out.flat_map = Some(BlockMap::from_pixels(&f.gain, f.width, f.height, spec.map_block, true));
            out.flat = Some(f);
            if simulated {
                out.notes.push(
                    "flat truth is the sensor's vignetting only; the lamp's falloff across the target is \
                     part of the measured gain and of the reported error"
                        .into(),
                );
            }
        }
        _ => unreachable!("run_radiometric is only called for radiometric kinds"),
    }
    let result = CalibrationResult {
        rig_time_s: rig.time() - t0,
        radiometric: Some(out),
        ..CalibrationResult::new(recipe, rig_name, simulated)
    }
    .seal();
    Ok(RunOutput { result, corners: None })
}

fn effort_failure(count: usize, capture_s: f64, why: &str) -> RadiometricEffort {
    RadiometricEffort {
        count,
        capture_s,
        fit_s: 0.0,
        metric: String::new(),
        error: f64::NAN,
        failure: Some(why.into()),
    }
}

/// RMS relative difference of two curves' `exp g` over the valid range (free scale).
fn curve_difference(a: &ResponseCurve, b: &ResponseCurve) -> f64 {
    let ys = error_range(a);
    let mut worst = 0f64;
    for c in 0..3 {
        let d: Vec<f64> = ys
            .iter()
            .map(|&y| a.g_at(c, y * a.max_dn) - b.g_at(c, y * b.max_dn))
            .collect();
        let s = d.iter().sum::<f64>() / d.len() as f64;
        worst = worst.max((d.iter().map(|x| ((x - s).exp() - 1.0).powi(2)).sum::<f64>() / d.len() as f64).sqrt());
    }
    worst
}

/// The simulator's vignetting `1 − v r²/r_corner²` on the flat's covered pixels, normalised
/// to mean 1 there (0 elsewhere).
fn vignetting_truth(rig: &Rig, f: &FlatField) -> Vec<f32> {
    let v = sim_sensor(rig).map_or(0.0, |s| s.vignetting);
    let (w, h) = (f.width, f.height);
    let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
    let rc2 = cx * cx + cy * cy;
    let mut t = vec![0f32; w * h * 3];
    let mut sum = 0.0;
    let mut n = 0usize;
    for y in 0..h {
        for x in 0..w {
            let k = (y * w + x) * 3;
            if f.gain[k] <= 0.0 {
                continue;
            }
            let (dx, dy) = (x as f64 + 0.5 - cx, y as f64 + 0.5 - cy);
            let g = 1.0 - v * (dx * dx + dy * dy) / rc2;
            for c in 0..3 {
                t[k + c] = g as f32;
            }
            sum += g;
            n += 1;
        }
    }
    let mean = sum / n.max(1) as f64;
    t.iter_mut().for_each(|x| *x = (*x as f64 / mean) as f32);
    t
}

/// RMS of `gain − truth` over the pixels both cover.
fn gain_rms(f: &FlatField, truth: &[f32]) -> f64 {
    let (mut s, mut n) = (0.0, 0usize);
    for (g, t) in f.gain.iter().zip(truth) {
        if *g > 0.0 && *t > 0.0 {
            s += (*g as f64 - *t as f64).powi(2);
            n += 1;
        }
    }
    (s / n.max(1) as f64).sqrt()
}

/// Patch means of a linear image of the colour target (camera pose from the kinematics at
/// `q`, points projected through the rig's intrinsics), the 3 × 3 fit and, on the
/// simulator, its error against the crosstalk.
#[allow(clippy::result_large_err)]
fn colour_fit(
    recipe: &Recipe,
    rig: &Rig,
    spec: &RadiometricSpec,
    q: &[f64],
    image: &RgbImage,
    out: &mut RadiometricCalibration,
) -> Result<(), CalibrateError> {
    let grid = spec.patches.as_ref().expect("validated: colour recipes have patches");
    let pose = rig.kinematics.camera_pose(q);
    let intr = rig.spec.camera.intrinsics();
    let (w, h) = (image.width, image.height);
    let steps = 9;
    let mut measured = Vec::new();
    let mut centres = Vec::new();
    for j in 0..grid.rows {
        for i in 0..grid.cols {
            let x0 = (i as f64 + 0.5 - grid.cols as f64 / 2.0) * grid.pitch_mm;
            let y0 = (grid.rows as f64 / 2.0 - j as f64 - 0.5) * grid.pitch_mm;
            let half = 0.5 * grid.inset * grid.pitch_mm;
            let mut sum = [0.0; 3];
            let mut n = 0usize;
            for a in 0..steps {
                for b in 0..steps {
                    let x = x0 - half + 2.0 * half * (a as f64 + 0.5) / steps as f64;
                    let y = y0 - half + 2.0 * half * (b as f64 + 0.5) / steps as f64;
                    let c = pose.to_camera(Vec3::new(x, y, 0.0));
                    if c.z <= 0.0 {
                        continue;
                    }
                    let (u, v) = intr.project(c.x, c.y, c.z);
                    if u < 0.0 || v < 0.0 || u >= w as f64 || v >= h as f64 {
                        continue;
                    }
                    let k = (v as usize * w + u as usize) * 3;
                    for (ch, acc) in sum.iter_mut().enumerate() {
                        *acc += image.data[k + ch] as f64;
                    }
                    n += 1;
                }
            }
            let c = pose.to_camera(Vec3::new(x0, y0, 0.0));
            let (u, v) = intr.project(c.x, c.y, c.z);
            centres.push([u, v]);
            measured.push(if n == 0 {
                [f64::NAN; 3]
            } else {
                sum.map(|s| s / n as f64)
            });
        }
    }
    let cm = colour_matrix(&measured, &grid.reference).map_err(|e| fail(recipe, e))?;
    out.patches = measured
        .iter()
        .zip(&grid.reference)
        .zip(&centres)
        .enumerate()
        .map(|(index, ((m, r), c))| PatchResult {
            index,
            centre_px: *c,
            measured: *m,
            reference: *r,
            corrected: cm.apply(*m),
        })
        .collect();
    if let (Some(shift), Some(tr)) = (out.response_shift, sim_response(rig).filter(|_| rig.clock.is_some())) {
        let m = tr
            .crosstalk
            .unwrap_or([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
        // measured_c ∝ e^{shift_c} (M ρ)_c, so C · diag(e^{shift}) · M should be ∝ I.
        let t: [[f64; 3]; 3] = std::array::from_fn(|r| {
            std::array::from_fn(|k| (0..3).map(|j| cm.matrix[r][j] * shift[j].exp() * m[j][k]).sum())
        });
        let tau = (t[0][0] + t[1][1] + t[2][2]) / 3.0;
        let mut e2 = 0.0;
        for (r, row) in t.iter().enumerate() {
            for (k, x) in row.iter().enumerate() {
                e2 += (x / tau - f64::from(u8::from(r == k))).powi(2);
            }
        }
        out.colour_matrix_error = Some((e2 / 3.0).sqrt());
    }
    out.colour = Some(cm);
    Ok(())
}
