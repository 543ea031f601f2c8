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
pub mod light_geometry;
pub mod mechanical;
pub mod radiometric;
pub mod recipe;
pub mod rig_geometry;
pub mod white;
// helpers shared by the rig- and light-geometry recipes
mod offset_fit;

use crate::engine::{self, frame_to_linear, Rig};
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
    #[error("recipe `{recipe}`: kind `{kind}` is not implemented yet (implemented: intrinsics)")]
    NotImplemented { recipe: String, kind: String },
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
    #[error("recipe `{recipe}`: rig `{rig}`: {cause}")]
    Device {
        recipe: String,
        rig: String,
        cause: Box<engine::EngineError>,
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
        RecipeKind::Intrinsics => run_intrinsics(recipe, rig).await,
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
    let mut q_read = Vec::with_capacity(q.len());
    for (axis, &target) in rig.axes.iter().zip(&q) {
        q_read.push(
            axis.move_abs(target)
                .await
                .map_err(|cause| device_error(recipe, rig, axis.name(), cause))?,
        );
    }
    Ok((q, q_read))
}

/// Home the rig and set the camera up (`engine::prepare`), then the recipe's exposure if it
/// gives one. Returns the camera configuration in force (as the camera applied it).
pub(crate) async fn prepare_rig(recipe: &Recipe, rig: &Rig) -> Result<gonio_devices::CameraConfig, CalibrateError> {
    let mut config = engine::prepare(rig).await.map_err(|cause| CalibrateError::Device {
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

/// Lens distortion of the simulated camera from the rig file's camera options.
fn sim_distortion(rig: &Rig) -> [f64; 5] {
    let mut d = [0.0; 5];
    for (k, key) in ["k1", "k2", "p1", "p2", "k3"].iter().enumerate() {
        if let Some(v) = rig.spec.camera.options.get(*key) {
            d[k] = v.as_float().or_else(|| v.as_integer().map(|i| i as f64)).unwrap_or(0.0);
        }
    }
    d
}

/// RMS distance of detected corners from the exact projection of the target corners
/// (simulated rigs). The board is symmetric, so the detector's grid may be any proper
/// rotation of the true one: the best of the four is taken. Returns the RMS, the exact
/// projections (in the detector's order) under that rotation, and the rotation (quarter
/// turns, [`gonio_calibration::wedge::quarter_turn`]). On a wedge the board points are
/// projected from the tilted plane ([`WedgeSpec::lift`]).
fn corner_truth(
    rig: &Rig,
    q: &[f64],
    wedge: Option<&WedgeSpec>,
    object: &[[f64; 2]],
    image: &[[f64; 2]],
) -> (f64, Vec<[f64; 2]>, u8) {
    let k = rig.spec.camera.intrinsics();
    let cam = CameraModel {
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        distortion: sim_distortion(rig),
    };
    let pose = rig.kinematics.camera_pose(q);
    (0..4u8)
        .map(|r| {
            let proj: Vec<[f64; 2]> = object
                .iter()
                .map(|o| {
                    let p = quarter_turn(*o, r);
                    let [x, y, z] = wedge.map_or([p[0], p[1], 0.0], |w| w.lift(p));
                    let c = pose.to_camera(gonio_devices::Vec3::new(x, y, z));
                    let (u, v) = cam.project_point([c.x, c.y, c.z]);
                    [u, v]
                })
                .collect();
            let sum: f64 = proj
                .iter()
                .zip(image)
                .map(|(p, i)| (p[0] - i[0]).powi(2) + (p[1] - i[1]).powi(2))
                .sum();
            ((sum / object.len().max(1) as f64).sqrt(), proj, r)
        })
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .expect("four rotations")
}

/// The object points of a board on a wedge: the detector's flat board points in true
/// in-plane coordinates ([`WedgeSpec::in_plane`]). The wedge is not symmetric under the
/// board's quarter turns, so which of the detector's four equivalent grids is the printed
/// one is decided first from the rig's nominal geometry (camera pose of the reached axes,
/// nominal intrinsics): the quarter turn whose points on the wedge project nearest the
/// detected corners. The alternatives differ by about a board's size in the image, so a
/// rough nominal geometry is enough. Points come back in the sample frame's orientation.
fn wedge_object_points(
    rig: &Rig,
    q: &[f64],
    wedge: &WedgeSpec,
    object: &[[f64; 2]],
    image: &[[f64; 2]],
) -> Vec<[f64; 2]> {
    let (_, _, r) = corner_truth(rig, q, Some(wedge), object, image);
    object.iter().map(|o| wedge.in_plane(quarter_turn(*o, r))).collect()
}

/// Largest fraction of a target frame's values that may sit at full scale before the frame
/// is taken again shorter: clipped bright squares move every edge toward them.
const MAX_CLIPPED_FRACTION: f64 = 1e-4;

/// How many times an intrinsics view is re-exposed (each time at half the exposure) before
/// the clipped frame is used as it is (the corner model then treats clipped pixels as
/// censored) and the detector diagnoses it if it must.
const MAX_REEXPOSURES: u32 = 6;

/// Capture a target frame. With `auto` (the recipe sets no exposure), a frame whose values
/// clip is captured again at half the exposure, up to [`MAX_REEXPOSURES`] times; the
/// camera's configuration is left at the exposure that worked, so the next view starts
/// there. Returns the frame and the exposure it was taken at.
async fn capture_unclipped(
    recipe: &Recipe,
    rig: &Rig,
    config: &mut gonio_devices::CameraConfig,
    auto: bool,
) -> Result<(gonio_devices::Frame, f64), CalibrateError> {
    let mut tries = 0;
    loop {
        let frame = rig
            .camera
            .capture()
            .await
            .map_err(|cause| device_error(recipe, rig, rig.camera.name(), cause))?;
        let clipped = engine::capture::saturated_fraction(&frame);
        if !auto || clipped <= MAX_CLIPPED_FRACTION || tries >= MAX_REEXPOSURES {
            return Ok((frame, config.exposure));
        }
        tries += 1;
        let mut next = config.clone();
        next.exposure = config.exposure * 0.5;
        let applied = rig
            .camera
            .configure(&next)
            .await
            .map_err(|cause| device_error(recipe, rig, rig.camera.name(), cause))?;
        if applied.exposure >= config.exposure {
            // the camera cannot go shorter: use what it gives
            return Ok((frame, config.exposure));
        }
        tracing::info!(
            clipped_percent = 100.0 * clipped,
            exposure_s = applied.exposure,
            "intrinsics: target frame clips; exposing shorter"
        );
        *config = applied;
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

async fn run_intrinsics(recipe: &Recipe, rig: &Rig) -> Result<RunOutput, CalibrateError> {
    let name = recipe.name.clone();
    let rig_name = rig.spec.name.clone();
    let board = recipe.board().expect("validated: intrinsics recipes have a board");
    let t0 = rig.time();
    let mut config = prepare_rig(recipe, rig).await?;
    let auto_exposure = recipe.exposure_s.is_none();
    let mut view_exposure = Vec::new();
    tracing::info!(recipe = %name, exposure = config.exposure, "intrinsics: capturing {} poses", recipe.poses.len());
    let mut views = Vec::new();
    let mut capture_times = Vec::new();
    let mut corner_rms = Vec::new();
    let mut truth_image = Vec::new();
    let mut prev: Option<Vec<f64>> = None;
    for (index, pose) in recipe.poses.iter().enumerate() {
        let light = pose.light.unwrap_or(recipe.light);
        let (q, _) = reach_pose(recipe, rig, index, pose.view, light, prev.as_deref()).await?;
        let (frame, exposure) = capture_unclipped(recipe, rig, &mut config, auto_exposure).await?;
        view_exposure.push(exposure);
        let raw = frame_to_linear(&frame);
        let det = detect_board(recipe, &board, &raw, index, pose.view)?;
        tracing::debug!(index, candidates = det.candidates, "board found");
        if rig.clock.is_some() {
            let (rms, proj, _) = corner_truth(rig, &q, recipe.wedge.as_ref(), &det.object, &det.image);
            corner_rms.push(rms);
            truth_image.push(proj);
        }
        let object = match &recipe.wedge {
            Some(w) => wedge_object_points(rig, &q, w, &det.object, &det.image),
            None => det.object,
        };
        views.push(TargetView {
            label: format!("pose {index} view θ={} φ={}", pose.view[0], pose.view[1]),
            object,
            image: det.image,
        });
        capture_times.push(rig.time() - t0);
        prev = Some(q);
    }
    let size = (rig.spec.camera.width, rig.spec.camera.height);
    let fit = calibrate_intrinsics(&views, size, &recipe.estimate).map_err(|cause| CalibrateError::Intrinsics {
        recipe: name.clone(),
        cause,
    })?;
    let simulated = rig.clock.is_some();
    let truth = simulated.then(|| {
        let k = rig.spec.camera.intrinsics();
        IntrinsicsTruth {
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            distortion: sim_distortion(rig),
        }
    });
    let errors = truth.as_ref().map(|t| {
        let c = &fit.camera;
        IntrinsicsErrors {
            fx_percent: 100.0 * (c.fx - t.fx) / t.fx,
            fy_percent: 100.0 * (c.fy - t.fy) / t.fy,
            cx_px: c.cx - t.cx,
            cy_px: c.cy - t.cy,
            cx_percent: 100.0 * (c.cx - t.cx) / t.cx,
            cy_percent: 100.0 * (c.cy - t.cy) / t.cy,
            distortion_abs: std::array::from_fn(|k| (c.distortion[k] - t.distortion[k]).abs()),
        }
    });
    // Error against effort: the same fit on the first k views.
    let (ref_fx, ref_cx, ref_cy) =
        truth
            .as_ref()
            .map(|t| (t.fx, t.cx, t.cy))
            .unwrap_or((fit.camera.fx, fit.camera.cx, fit.camera.cy));
    let mut effort = Vec::new();
    for k in 3..=views.len() {
        let start = Instant::now();
        let r = calibrate_intrinsics(&views[..k], size, &recipe.estimate);
        let fit_s = start.elapsed().as_secs_f64();
        let capture_s = capture_times[k - 1];
        effort.push(match r {
            Ok(c) => EffortRow {
                views: k,
                capture_s,
                fit_s,
                rms_px: c.rms_px,
                fx: c.camera.fx,
                cx: c.camera.cx,
                cy: c.camera.cy,
                fx_error_percent: 100.0 * (c.camera.fx - ref_fx) / ref_fx,
                cx_error_px: c.camera.cx - ref_cx,
                cy_error_px: c.camera.cy - ref_cy,
                failure: None,
            },
            Err(e) => EffortRow {
                views: k,
                capture_s,
                fit_s,
                rms_px: f64::NAN,
                fx: f64::NAN,
                cx: f64::NAN,
                cy: f64::NAN,
                fx_error_percent: f64::NAN,
                cx_error_px: f64::NAN,
                cy_error_px: f64::NAN,
                failure: Some(e.to_string()),
            },
        });
    }
    let result = CalibrationResult {
        intrinsics: Some(fit),
        truth,
        errors,
        effort,
        corner_truth_rms_px: corner_rms,
        view_exposure_s: view_exposure,
        rig_time_s: rig.time() - t0,
        ..CalibrationResult::new(recipe, rig_name, simulated)
    }
    .seal();
    Ok(RunOutput {
        result,
        corners: Some(CornerSet {
            convention: "gonio: pixel (i, j) has its centre at (i + 0.5, j + 0.5); OpenCV = this − 0.5".into(),
            image_size: [size.0, size.1],
            views,
            truth_image,
        }),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use gonio_devices::rig::RigSpec;
    use gonio_simulator::SampleSpec;
    use std::path::Path;

    fn root() -> &'static Path {
        Path::new(env!("CARGO_MANIFEST_DIR"))
    }

    fn wide_rig(recipe: &Recipe) -> Rig {
        let spec = RigSpec::load(&root().join("devices/rigs/wide-lens.toml")).unwrap();
        let sample = SampleSpec::resolve(&recipe.target).unwrap();
        let opts = recipe.sim_options();
        Rig::build(&spec, &sample, &opts).unwrap()
    }

    fn shipped() -> Recipe {
        Recipe::load(&root().join("calibration/recipes/intrinsics.toml")).unwrap()
    }

    // The error is matched by variant in the tests; its size does not matter here.
    #[allow(clippy::result_large_err)]
    fn run_blocking(recipe: &Recipe) -> Result<RunOutput, CalibrateError> {
        let rig = wide_rig(recipe);
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        rt.block_on(run(recipe, &rig))
    }

    /// The targets on noiseless simulated images of a distorting wide-angle lens
    /// with an off-centre principal point: focal length and principal point within 0.1 %
    /// of the truth, reprojection RMS < 0.1 px. The rig's default exposure clips the
    /// board's bright squares, so this also checks that the runner exposes shorter.
    #[test]
    fn intrinsics_match_the_simulator_truth() {
        let out = run_blocking(&shipped()).unwrap();
        let r = &out.result;
        let c = r.intrinsics.as_ref().unwrap();
        let t = r.truth.as_ref().unwrap();
        let e = r.errors.as_ref().unwrap();
        assert!(c.rms_px < 0.1, "rms {}", c.rms_px);
        assert!(e.fx_percent.abs() < 0.1 && e.fy_percent.abs() < 0.1, "{e:?}");
        assert!(e.cx_percent.abs() < 0.1 && e.cy_percent.abs() < 0.1, "{e:?}");
        assert!(r.view_exposure_s.iter().all(|&x| x < 0.05), "{:?}", r.view_exposure_s);
        assert!((t.distortion[0] + 0.12).abs() < 1e-12, "truth read from the rig file");
        // barrel distortion is recovered in sign and rough size over the target's field
        assert!(
            (c.camera.distortion[0] - t.distortion[0]).abs() < 0.05,
            "{:?}",
            c.camera
        );
        assert_eq!(r.id.len(), 16);
        assert_eq!(out.corners.as_ref().unwrap().views.len(), 12);
        // the effort table covers 3 ..= 12 views; too few views are refused, not fitted
        assert_eq!(r.effort.len(), 10);
        assert!(r.effort[0].failure.is_some(), "{:?}", r.effort[0]);
    }

    #[test]
    fn parallel_target_poses_are_refused() {
        // θ = 0 at several turntable angles: the target only turns about the optical axis,
        // all target planes are parallel.
        let mut recipe = shipped();
        recipe.poses.truncate(0);
        for phi in [0.0, 70.0, 140.0, 210.0] {
            recipe.poses.push(recipe::PoseSpec {
                view: [0.0, phi],
                light: None,
            });
        }
        let e = run_blocking(&recipe).err().expect("refused");
        let msg = e.to_string();
        assert!(
            matches!(
                e,
                CalibrateError::Intrinsics {
                    cause: IntrinsicsError::Degenerate { .. }
                        | IntrinsicsError::ClosedForm(_)
                        | IntrinsicsError::Undetermined { .. },
                    ..
                }
            ),
            "{msg}"
        );
    }

    #[test]
    fn black_and_saturated_frames_are_diagnosed() {
        let mut recipe = shipped();
        recipe.exposure_s = Some(1e-9);
        let e = run_blocking(&recipe).err().expect("refused");
        assert!(
            matches!(
                e,
                CalibrateError::Detection {
                    index: 0,
                    cause: CheckerboardError::Empty { .. },
                    ..
                }
            ),
            "{e}"
        );
        recipe.exposure_s = Some(100.0);
        let e = run_blocking(&recipe).err().expect("refused");
        assert!(
            matches!(
                e,
                CalibrateError::Detection {
                    cause: CheckerboardError::Saturated { .. },
                    ..
                }
            ),
            "{e}"
        );
    }
}
