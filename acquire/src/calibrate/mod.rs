//! Scripted calibration: run a [`Recipe`] on a [`Rig`] and write a versioned result.
//!
//! The runner drives the rig only through the engine's `Rig` (axes via the `Axis` trait,
//! camera via `Camera`), so a recipe runs the same on the simulator and on hardware. On a
//! simulated rig the result also carries the simulator's truth and the error of every
//! estimate against it.
//!
//! Result file (`calibration.json`, format [`RESULT_FORMAT`]): `id` (a hash of the rest of
//! the file, so an acquisition can reference exactly this calibration), gonio version, rig
//! name, recipe, estimates, one-sigma uncertainties, diagnostics, and on the simulator
//! `truth` and `errors`. An intrinsics run also writes `corners.json` (detected image
//! points and target points per view), the input an independent oracle (OpenCV) needs.

pub mod apply;
mod intrinsics;
pub mod light_geometry;
pub mod mechanical;
pub mod radiometric;
pub mod recipe;
pub mod rig_geometry;
pub mod uncertainty;
pub mod white;
// helpers shared by the rig- and light-geometry recipes
mod offset_fit;

use crate::develop::frame_to_linear;
use crate::rig::{CapturePolicy, Rig, SaturationPolicy};
use gonio_calibration::checkerboard::CheckerboardError;
use gonio_calibration::intrinsics::{
    calibrate_intrinsics, CameraModel, IntrinsicsCalibration, IntrinsicsError, TargetView,
};
use gonio_calibration::wedge::{quarter_turn, WedgeSpec};
use gonio_devices::Direction;
pub use recipe::{Recipe, RecipeError, RecipeKind};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::time::Instant;
use thiserror::Error;

/// Version tag of the result file layout.
pub const RESULT_FORMAT: &str = "gonio-calibration/1";

#[derive(Debug, Error)]
pub enum CalibrateError {
    #[error(
        "recipe `{recipe}`: pose {index} (view {view:?}, light {light:?}) is not reachable on rig `{rig}`: {reason}"
    )]
    Unreachable {
        recipe: String,
        index: usize,
        view: [f64; 2],
        light: [f64; 2],
        rig: String,
        reason: String,
    },
    /// A rig-file option the recipe needs is present but wrong.
    #[error("recipe `{recipe}`: rig `{rig}`: {source}")]
    RigOption {
        recipe: String,
        rig: String,
        source: gonio_devices::rig::OptionError,
    },
    #[error("recipe `{recipe}`: rig `{rig}`: device error while preparing the rig: {cause}")]
    Device {
        recipe: String,
        rig: String,
        cause: Box<gonio_devices::DeviceError>,
    },
    /// The camera failed every attempt the rig's capture policy allows at one pose.
    #[error("recipe `{recipe}`: pose {index} (view {view:?}): camera failed after {attempts} attempt(s): {cause}")]
    Capture {
        recipe: String,
        index: usize,
        view: [f64; 2],
        attempts: u32,
        cause: Box<gonio_devices::DeviceError>,
    },
    #[error("recipe `{recipe}`: rig `{rig}`: {device}: {cause}")]
    Move {
        recipe: String,
        rig: String,
        device: String,
        cause: gonio_devices::DeviceError,
    },
    #[error("recipe `{recipe}`: pose {index} (view {view:?}): {cause}")]
    Detection {
        recipe: String,
        index: usize,
        view: [f64; 2],
        cause: CheckerboardError,
    },
    #[error("recipe `{recipe}`: {cause}")]
    Intrinsics { recipe: String, cause: IntrinsicsError },
    /// A dark, response, flat or colour fit failed (the cause says what to change).
    #[error("recipe `{recipe}`: {cause}")]
    Radiometric {
        recipe: String,
        cause: gonio_calibration::radiometric::RadiometricError,
    },
    #[error("recipe `{recipe}`: [radiometric] response = \"{path}\": {message}")]
    ResponseInput {
        recipe: String,
        path: String,
        message: String,
    },
    #[error("recipe `{recipe}`: key `{key}`: {message}")]
    RecipeInvalid {
        recipe: String,
        key: String,
        message: String,
    },
    /// A mechanical run failed (the error names recipe, axis and command).
    #[error(transparent)]
    Mechanical(Box<mechanical::MechanicalError>),
    #[error("recipe `{recipe}`: white standard: {cause}")]
    White { recipe: String, cause: white::WhiteError },
    #[error("recipe `{recipe}`: {cause}")]
    RigGeometry {
        recipe: String,
        cause: gonio_calibration::rig_geometry::RigGeometryError,
    },
    /// The lamp-offset fit (or its design check before capture) refused.
    #[error("recipe `{recipe}`: {cause}")]
    LightGeometry {
        recipe: String,
        cause: gonio_calibration::light_geometry::LightGeometryError,
    },
    /// No usable highlight in a light-geometry frame (the cause says why and what to change).
    #[error("recipe `{recipe}`: pose {index} (view {view:?}, light {light:?}): {cause}")]
    Highlight {
        recipe: String,
        index: usize,
        view: [f64; 2],
        light: [f64; 2],
        cause: gonio_calibration::light_geometry::HighlightError,
    },
}

/// The corners of every view, as written to `corners.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CornerSet {
    /// Pixel convention of `image`: gonio's (pixel centres at half-integers); OpenCV's
    /// coordinates are these minus ½.
    pub convention: String,
    pub image_size: [usize; 2],
    pub views: Vec<TargetView>,
    /// Simulator only: the exact projection of every detected corner's target point, per
    /// view and in the same order as `views[k].image`, so a detector's error can be
    /// studied corner by corner (`image − truth_image`). Empty on real rigs.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub truth_image: Vec<Vec<[f64; 2]>>,
}

/// Truth of the simulated camera and the estimate's errors against it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct IntrinsicsTruth {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub distortion: [f64; 5],
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct IntrinsicsErrors {
    /// Relative focal errors (estimate − truth) / truth, in percent.
    pub fx_percent: f64,
    pub fy_percent: f64,
    /// Principal point errors in pixels and relative to the true value in percent.
    pub cx_px: f64,
    pub cy_px: f64,
    pub cx_percent: f64,
    pub cy_percent: f64,
    pub distortion_abs: [f64; 5],
}

/// One row of the error-versus-effort table: the fit repeated on the first `views` views.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EffortRow {
    pub views: usize,
    /// Rig time (s) to capture these views (virtual on the simulator).
    pub capture_s: f64,
    /// Wall time of the fit (s).
    pub fit_s: f64,
    pub rms_px: f64,
    pub fx: f64,
    pub cx: f64,
    pub cy: f64,
    /// Relative focal error against the truth (percent); on real rigs, against the fit
    /// with all views.
    pub fx_error_percent: f64,
    pub cx_error_px: f64,
    /// Principal point y error (px), against the same reference as `cx_error_px`.
    #[serde(default)]
    pub cy_error_px: f64,
    /// Why the fit failed (too few views, degenerate), if it did.
    pub failure: Option<String>,
}

/// The versioned result file.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct CalibrationResult {
    pub format: String,
    /// Hash of the file without this field (hex, 16 digits).
    pub id: String,
    pub gonio_version: String,
    pub created_unix: f64,
    pub rig: String,
    pub kind: String,
    pub recipe: Recipe,
    pub simulated: bool,
    pub intrinsics: Option<IntrinsicsCalibration>,
    pub truth: Option<IntrinsicsTruth>,
    pub errors: Option<IntrinsicsErrors>,
    pub effort: Vec<EffortRow>,
    /// Simulator only: RMS distance (px) of the detected corners from their exact
    /// projections, per view — the detector's error, which bounds what the fit can do.
    pub corner_truth_rms_px: Vec<f64>,
    /// Intrinsics: the exposure (s) each view was captured at. Without a recipe exposure
    /// the camera's is lowered until the board's bright squares no longer clip (see
    /// [`capture_unclipped`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub view_exposure_s: Vec<f64>,
    /// Rig time for the whole run (s).
    pub rig_time_s: f64,
    /// Dark, response, flat or colour run: estimates, diagnostics, truth errors, effort.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub radiometric: Option<radiometric::RadiometricCalibration>,
    /// White-standard run: the radiometric conversion to BRDF, residuals, truth errors.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub white_standard: Option<white::WhiteStandardCalibration>,
    /// Mechanical run: homing repeatability, backlash, positioning error per axis.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mechanical: Option<mechanical::MechanicalCalibration>,
    /// Rig-geometry run: axis zero offsets, camera mounting rotation, direction errors.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rig_geometry: Option<rig_geometry::RigGeometryCalibration>,
    /// Light-geometry run: the lamp axes' zero offsets from a mirror's highlights.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub light_geometry: Option<light_geometry::LightGeometryCalibration>,
    /// Intrinsics: the plan check made before the rig moved (predicted conditioning and
    /// parameter sigmas at the planned poses).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plan_check: Option<gonio_calibration::intrinsics::PlanCheck>,
    /// Intrinsics: one-sigma projection uncertainty over the whole image, coverage, and the
    /// warning naming where it exceeds the threshold.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub projection_uncertainty: Option<gonio_calibration::uncertainty::ProjectionUncertainty>,
    /// Intrinsics on the simulator: the true projection error on the same grid.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub projection_truth: Option<uncertainty::ProjectionTruth>,
}

impl CalibrationResult {
    /// An empty result for `recipe` on the rig named `rig`: every estimate `None`. Each
    /// recipe kind fills in its own parts (`..CalibrationResult::new(..)`), so adding a kind
    /// adds one optional field here and touches no other kind.
    pub fn new(recipe: &Recipe, rig: String, simulated: bool) -> Self {
        CalibrationResult {
            format: RESULT_FORMAT.into(),
            id: String::new(),
            gonio_version: env!("CARGO_PKG_VERSION").into(),
            created_unix: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_secs_f64())
                .unwrap_or(0.0),
            rig,
            kind: recipe.kind.name().into(),
            recipe: recipe.clone(),
            simulated,
            intrinsics: None,
            truth: None,
            errors: None,
            effort: Vec::new(),
            corner_truth_rms_px: Vec::new(),
            view_exposure_s: Vec::new(),
            rig_time_s: 0.0,
            radiometric: None,
            white_standard: None,
            mechanical: None,
            rig_geometry: None,
            light_geometry: None,
            plan_check: None,
            projection_uncertainty: None,
            projection_truth: None,
        }
    }

    /// Fill `id` with the hash of the serialized result (with an empty id).
    fn seal(mut self) -> Self {
        self.id.clear();
        let bytes = serde_json::to_vec(&self).unwrap_or_default();
        let digest = Sha256::digest(&bytes);
        self.id = digest.iter().take(8).map(|b| format!("{b:02x}")).collect();
        self
    }
}

/// What [`run`] returns: the result and, for intrinsics, the corners.
pub struct RunOutput {
    pub result: CalibrationResult,
    pub corners: Option<CornerSet>,
}

/// Run a recipe on a built rig. The rig's sample must be the recipe's target.
pub async fn run(recipe: &Recipe, rig: &Rig) -> Result<RunOutput, CalibrateError> {
    match recipe.kind {
        RecipeKind::Intrinsics => intrinsics::run_intrinsics(recipe, rig).await,
        RecipeKind::Dark | RecipeKind::Response | RecipeKind::Flat | RecipeKind::Colour => {
            radiometric::run_radiometric(recipe, rig).await
        }
        RecipeKind::WhiteStandard => white::run_white(recipe, rig).await,
        RecipeKind::Mechanical => mechanical::run(recipe, rig).await,
        RecipeKind::RigGeometry => rig_geometry::run_rig_geometry(recipe, rig).await,
        RecipeKind::LightGeometry => light_geometry::run_light_geometry(recipe, rig).await,
    }
}

/// Reach one pose of a recipe: the rig's inverse kinematics for (`light`, `view`) in
/// degrees, the solution nearest `prev` (the previous pose's axes, so a run does not swing
/// round), every axis moved there. Returns the commanded and the read-back positions.
/// Shared by every recipe kind, so an unreachable pose or a failing axis reads the same in
/// all of them: the recipe, the pose index, the rig and the device are named.
pub(crate) async fn reach_pose(
    recipe: &Recipe,
    rig: &Rig,
    index: usize,
    view: [f64; 2],
    light: [f64; 2],
    prev: Option<&[f64]>,
) -> Result<(Vec<f64>, Vec<f64>), CalibrateError> {
    let unreachable = |reason: String| CalibrateError::Unreachable {
        recipe: recipe.name.clone(),
        index,
        view,
        light,
        rig: rig.spec.name.clone(),
        reason,
    };
    let q = rig
        .kinematics
        .inverse(
            Direction::from_degrees(light[0], light[1]),
            Direction::from_degrees(view[0], view[1]),
            prev,
        )
        .map_err(|e| unreachable(e.to_string()))?
        .into_iter()
        .next()
        .ok_or_else(|| unreachable("no configuration".into()))?;
    // The rig's shared step: every axis starts at once, all are waited for, the camera is
    // told the rig is still (so the capture policy's stale-frame rule applies).
    let q_read = rig.reach(&q).await.map_err(|cause| {
        let device = cause.device().to_string();
        device_error(recipe, rig, &device, cause)
    })?;
    Ok((q, q_read))
}

/// The capture policy calibrations use: the rig file's timeout, retries and stale-frame
/// rule, but saturation only flagged (each recipe decides what a clipped frame means:
/// a response bracket clips on purpose, intrinsics exposes shorter itself).
// Called once per recipe; the error's size costs nothing next to a capture.
#[allow(clippy::result_large_err)]
pub(crate) fn calibration_policy(recipe: &Recipe, rig: &Rig) -> Result<CapturePolicy, CalibrateError> {
    let mut policy = rig.capture_policy().map_err(|cause| CalibrateError::Device {
        recipe: recipe.name.clone(),
        rig: rig.spec.name.clone(),
        cause: Box::new(cause),
    })?;
    policy.saturation = SaturationPolicy::Flag;
    Ok(policy)
}

/// Capture one frame at pose `index` (viewed from `view`) under `policy`; a camera that
/// fails every attempt stops the recipe with an error naming the pose.
pub(crate) async fn capture_at(
    recipe: &Recipe,
    rig: &Rig,
    policy: &CapturePolicy,
    config: &gonio_devices::CameraConfig,
    index: usize,
    view: [f64; 2],
) -> Result<gonio_devices::Frame, CalibrateError> {
    let (frame, notes) = rig.capture(policy, config).await.map_err(|f| CalibrateError::Capture {
        recipe: recipe.name.clone(),
        index,
        view,
        attempts: f.attempts,
        cause: Box::new(f.source),
    })?;
    if notes.retries > 0 {
        tracing::warn!(recipe = %recipe.name, pose = index, retries = notes.retries, faults = ?notes.faults, "calibration capture needed retries");
    }
    Ok(frame)
}

/// Home the rig and set the camera up ([`Rig::prepare`]), then the recipe's exposure if it
/// gives one. Returns the camera configuration in force (as the camera applied it).
pub(crate) async fn prepare_rig(recipe: &Recipe, rig: &Rig) -> Result<gonio_devices::CameraConfig, CalibrateError> {
    let mut config = rig.prepare().await.map_err(|cause| CalibrateError::Device {
        recipe: recipe.name.clone(),
        rig: rig.spec.name.clone(),
        cause: Box::new(cause),
    })?;
    if let Some(e) = recipe.exposure_s {
        config.exposure = e;
        config = rig
            .camera
            .configure(&config)
            .await
            .map_err(|cause| device_error(recipe, rig, rig.camera.name(), cause))?;
    }
    Ok(config)
}

/// A device failure during a recipe, naming the recipe, the rig and the device.
pub(crate) fn device_error(
    recipe: &Recipe,
    rig: &Rig,
    device: &str,
    cause: gonio_devices::DeviceError,
) -> CalibrateError {
    CalibrateError::Move {
        recipe: recipe.name.clone(),
        rig: rig.spec.name.clone(),
        device: device.into(),
        cause,
    }
}

/// The recipe's board in the frame of pose `index`; a failure names the recipe and the
/// pose it was captured at.
// Called once per captured view; the error's size costs nothing next to a capture.
#[allow(clippy::result_large_err)]
fn detect_board(
    recipe: &Recipe,
    board: &gonio_calibration::board::Board,
    raw: &gonio_devices::image::RgbImage,
    index: usize,
    view: [f64; 2],
) -> Result<gonio_calibration::checkerboard::CheckerboardDetection, CalibrateError> {
    board
        .detect(raw, &recipe.detection)
        .map_err(|cause| CalibrateError::Detection {
            recipe: recipe.name.clone(),
            index,
            view,
            cause,
        })
}
