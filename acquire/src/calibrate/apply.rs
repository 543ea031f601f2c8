//! What `gonio acquire --calibration DIR` applies: calibration result files loaded, checked
//! against the rig and against each other, and turned into
//!
//! - corrected kinematics (rig and light geometry → the rig's `[alignment]`, before
//!   planning: [`AppliedCalibration::correct_rig`]);
//! - the per-frame [`Corrections`] the `develop` floor applies (intrinsics → undistortion,
//!   dark / response / flat / colour → [`RawCorrection`], white standard →
//!   [`Radiometric`]): [`AppliedCalibration::developer_corrections`].
//!
//! The per-frame steps themselves live in `crate::develop`; this file only loads.

use crate::develop::{
    BlockMap, CameraMismatch, CorrectionSource, Corrections, MapPart, Radiometric, RawCorrection, RawParts,
};
use gonio_calibration::intrinsics::CameraModel;
use gonio_calibration::radiometric::ResponseCurve;
use gonio_devices::Intrinsics;
use thiserror::Error;

/// Every calibration an acquisition applies, as the store thread needs it.
#[derive(Clone, Debug, Default)]
pub struct AppliedCalibration {
    /// Ids of the calibration results, in the order applied.
    pub ids: Vec<String>,
    /// Calibrated camera: frames are undistorted with it and rectified with its matrix.
    pub camera: Option<CameraModel>,
    /// Conversion of rectified values to BRDF (1/sr).
    pub radiometric: Option<Radiometric>,
    /// Corrected kinematics: the axis zero offsets and camera mounting rotation of a
    /// rig-geometry calibration. Applied to the rig file *before* planning
    /// ([`AppliedCalibration::correct_rig`]), so the planner commands the positions that
    /// reach the asked directions and the store thread's camera pose and lamp position come
    /// from the same corrected kinematics; the manifest's rig then carries `[alignment]`,
    /// and `--resume` plans nothing again.
    pub rig_geometry: Option<super::rig_geometry::RigGeometryCalibration>,
    /// The lamp axes' zero offsets of a light-geometry calibration, applied with (after)
    /// the rig geometry: each writes only its own axes, so the camera's offsets come from
    /// one and the lamp's from the other.
    pub light_geometry: Option<super::light_geometry::LightGeometryCalibration>,
    /// Dark, response, flat and colour results: applied to each raw frame before
    /// undistortion and rectification (see [`RawCorrection`]).
    pub raw: Option<RawCorrection>,
}

impl AppliedCalibration {
    /// Feed a rig-geometry calibration into `rig`'s kinematics (its `[alignment]`); no-op
    /// without one. Call before planning.
    pub fn correct_rig(&self, rig: &mut gonio_devices::rig::RigSpec) {
        if let Some(g) = &self.rig_geometry {
            g.apply(rig);
        }
        if let Some(g) = &self.light_geometry {
            g.apply(rig);
        }
    }

    /// Unit of the stored values: `brdf_per_sr` with a radiometric conversion, else
    /// `linear_corrected` with raw-frame corrections only (linear relative values, see
    /// [`RawCorrection`]), else `normalized_dn` (linear sensor signal, DN / max DN).
    pub fn value_unit(&self) -> &'static str {
        if self.radiometric.is_some() {
            VALUE_UNIT_BRDF
        } else if self.raw.is_some() {
            VALUE_UNIT_LINEAR
        } else {
            VALUE_UNIT_DN
        }
    }

    /// The raw-frame corrections applied, in order (`response`, `dark`, `flat`, `colour`).
    pub fn corrections(&self) -> Vec<String> {
        self.raw.as_ref().map(|r| r.kinds()).unwrap_or_default()
    }

    /// The per-frame corrections for a [`crate::develop::Developer`].
    pub fn developer_corrections(&self) -> Corrections {
        Corrections {
            camera: self.camera,
            radiometric: self.radiometric,
            raw: self.raw.clone(),
        }
    }

    /// Intrinsics for the pose homography: the calibrated ones if present.
    pub fn intrinsics(&self, nominal: &Intrinsics) -> Intrinsics {
        match &self.camera {
            Some(c) => Intrinsics {
                fx: c.fx,
                fy: c.fy,
                cx: c.cx,
                cy: c.cy,
            },
            None => *nominal,
        }
    }
}

/// `value_unit` of BRDF data (1/sr).
pub const VALUE_UNIT_BRDF: &str = "brdf_per_sr";
/// `value_unit` of uncalibrated data (linear normalised sensor signal).
pub use gonio_devices::image::VALUE_UNIT_DN;
/// `value_unit` of data with raw-frame corrections but no white standard: linear values on
/// the response curve's relative scale (`½ exp g`), dark-, flat- and colour-corrected.
pub const VALUE_UNIT_LINEAR: &str = "linear_corrected";

/// Why a calibration directory cannot be used.
#[derive(Debug, Error)]
pub enum LoadError {
    #[error("calibration directory {dir}: {source}")]
    Io { dir: String, source: std::io::Error },
    #[error("calibration directory {dir} holds no calibration.json (looked in it and its subdirectories)")]
    Empty { dir: String },
    #[error("calibration result {file}: {message}")]
    Bad { file: String, message: String },
    #[error(
        "calibration result {file} (id {id}) was made on rig `{calibrated}`, this acquisition uses rig `{rig}`: \
         calibrate this rig (or pass its rig file)"
    )]
    WrongRig {
        file: String,
        id: String,
        calibrated: String,
        rig: String,
    },
    /// A correction made on another camera (see [`CameraMismatch`]).
    #[error(transparent)]
    CameraMismatch(#[from] CameraMismatch),
    #[error("calibration results {first} and {second} are both of kind `{kind}`: keep one per kind")]
    DuplicateKind {
        kind: String,
        first: String,
        second: String,
    },
}

/// One `calibration.json` as found on disk.
#[derive(Clone, Debug)]
pub struct LoadedResult {
    pub file: std::path::PathBuf,
    pub kind: String,
    pub id: String,
    pub rig: String,
    /// The file's bytes (copied into the dataset, so `--resume` applies the same result).
    pub bytes: Vec<u8>,
    pub value: serde_json::Value,
}

impl LoadedResult {
    /// Parse one result file. Read as JSON rather than as `CalibrationResult`, so results
    /// with fields this build does not know (newer kinds) still load.
    pub fn read(file: &std::path::Path) -> Result<LoadedResult, LoadError> {
        let name = file.display().to_string();
        let bad = |message: String| LoadError::Bad {
            file: name.clone(),
            message,
        };
        let bytes = std::fs::read(file).map_err(|e| bad(e.to_string()))?;
        let value: serde_json::Value = serde_json::from_slice(&bytes).map_err(|e| bad(format!("not JSON: {e}")))?;
        let field = |key: &str| {
            value
                .get(key)
                .and_then(|v| v.as_str())
                .map(String::from)
                .ok_or_else(|| bad(format!("no string field `{key}`")))
        };
        let format = field("format")?;
        if format != super::RESULT_FORMAT {
            return Err(bad(format!("format {format:?}, expected {:?}", super::RESULT_FORMAT)));
        }
        Ok(LoadedResult {
            file: file.to_path_buf(),
            kind: field("kind")?,
            id: field("id")?,
            rig: field("rig")?,
            bytes,
            value,
        })
    }
}

/// Every `calibration.json` in `dir` and in its direct subdirectories (one per recipe
/// kind, e.g. `cal/intrinsics/calibration.json`, `cal/white/calibration.json`), checked
/// against the rig the acquisition uses.
pub fn load_dir(dir: &std::path::Path, rig_name: &str) -> Result<Vec<LoadedResult>, LoadError> {
    let d = dir.display().to_string();
    let io = |source| LoadError::Io { dir: d.clone(), source };
    if !dir.is_dir() {
        // metadata gives the precise reason (missing, permission); a file is not a directory
        std::fs::metadata(dir).map_err(io)?;
        return Err(io(std::io::Error::other("not a directory")));
    }
    let mut files = Vec::new();
    let top = dir.join("calibration.json");
    if top.is_file() {
        files.push(top);
    }
    let mut subdirs: Vec<_> = std::fs::read_dir(dir)
        .map_err(io)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir())
        .collect();
    subdirs.sort();
    files.extend(
        subdirs
            .iter()
            .map(|p| p.join("calibration.json"))
            .filter(|p| p.is_file()),
    );
    load_files(&files, rig_name).and_then(|v| {
        if v.is_empty() {
            Err(LoadError::Empty { dir: d.clone() })
        } else {
            Ok(v)
        }
    })
}

/// Load the given result files (see [`load_dir`]).
pub fn load_files(files: &[std::path::PathBuf], rig_name: &str) -> Result<Vec<LoadedResult>, LoadError> {
    let mut out: Vec<LoadedResult> = Vec::new();
    for f in files {
        let r = LoadedResult::read(f)?;
        if r.rig != rig_name {
            return Err(LoadError::WrongRig {
                file: f.display().to_string(),
                id: r.id,
                calibrated: r.rig,
                rig: rig_name.into(),
            });
        }
        if let Some(prev) = out.iter().find(|p| p.kind == r.kind) {
            return Err(LoadError::DuplicateKind {
                kind: r.kind,
                first: prev.file.display().to_string(),
                second: f.display().to_string(),
            });
        }
        out.push(r);
    }
    Ok(out)
}

impl AppliedCalibration {
    /// What an acquisition applies from these results. Kinds it cannot apply yet are
    /// returned in the second list (recorded in the manifest as not applied).
    pub fn from_results(results: &[LoadedResult]) -> Result<(AppliedCalibration, Vec<String>), LoadError> {
        let mut applied = AppliedCalibration::default();
        let mut skipped = Vec::new();
        let mut raw = RawParts::default();
        for r in results {
            let bad = |message: String| LoadError::Bad {
                file: r.file.display().to_string(),
                message,
            };
            match r.kind.as_str() {
                "intrinsics" => {
                    let cam: CameraModel = serde_json::from_value(r.value["intrinsics"]["camera"].clone())
                        .map_err(|e| bad(format!("intrinsics.camera: {e}")))?;
                    applied.camera = Some(cam);
                }
                "white-standard" => {
                    let radio: Radiometric = serde_json::from_value(r.value["white_standard"]["radiometric"].clone())
                        .map_err(|e| bad(format!("white_standard.radiometric: {e}")))?;
                    if radio.k.iter().any(|k| !(k.is_finite() && *k > 0.0)) {
                        return Err(bad(format!("white_standard.radiometric.k {:?}: must be > 0", radio.k)));
                    }
                    applied.radiometric = Some(radio);
                }
                "rig-geometry" => {
                    let geo: super::rig_geometry::RigGeometryCalibration =
                        serde_json::from_value(r.value["rig_geometry"].clone())
                            .map_err(|e| bad(format!("rig_geometry: {e}")))?;
                    applied.rig_geometry = Some(geo);
                }
                "light-geometry" => {
                    let geo: super::light_geometry::LightGeometryCalibration =
                        serde_json::from_value(r.value["light_geometry"].clone())
                            .map_err(|e| bad(format!("light_geometry: {e}")))?;
                    applied.light_geometry = Some(geo);
                }
                "dark" | "response" | "flat" | "colour" => {
                    raw_part(r, &mut raw)?;
                    // ids are pushed once the parts are checked against each other
                    continue;
                }
                other => {
                    skipped.push(other.to_string());
                    continue;
                }
            }
            applied.ids.push(r.id.clone());
        }
        applied.raw = RawCorrection::build(raw).map_err(|(file, e)| LoadError::Bad { file, message: e.0 })?;
        applied
            .ids
            .extend(applied.raw.iter().flat_map(|c| c.sources.iter().map(|s| s.id.clone())));
        check_white_corrections(results, applied.raw.as_ref())?;
        Ok((applied, skipped))
    }
}

/// Parse a dark, response, flat or colour result into `parts`.
fn raw_part(r: &LoadedResult, parts: &mut RawParts) -> Result<(), LoadError> {
    let file = r.file.display().to_string();
    let bad = |message: String| LoadError::Bad {
        file: file.clone(),
        message,
    };
    let radio = &r.value["radiometric"];
    let src = CorrectionSource {
        kind: r.kind.clone(),
        id: r.id.clone(),
        file: file.clone(),
    };
    let get = |key: &str| -> Result<serde_json::Value, LoadError> {
        match radio.get(key) {
            Some(v) if !v.is_null() => Ok(v.clone()),
            _ => Err(bad(format!(
                "radiometric.{key} is missing: re-run the {} recipe",
                r.kind
            ))),
        }
    };
    let linearisation = radio.get("linearisation").and_then(|v| v.as_str()).map(String::from);
    let size = |key: &str| -> Result<(usize, usize), LoadError> {
        let v = get(key)?;
        match (v["width"].as_u64(), v["height"].as_u64()) {
            (Some(w), Some(h)) => Ok((w as usize, h as usize)),
            _ => Err(bad(format!("radiometric.{key} has no width/height"))),
        }
    };
    let map = |key: &str| -> Result<BlockMap, LoadError> {
        serde_json::from_value(get(key)?).map_err(|e| bad(format!("radiometric.{key}: {e}")))
    };
    match r.kind.as_str() {
        "response" => {
            let curve: ResponseCurve = serde_json::from_value(get("response")?["curve"].clone())
                .map_err(|e| bad(format!("radiometric.response.curve: {e}")))?;
            parts.response = Some((src, curve));
        }
        "dark" => {
            let exposure = get("dark")?["exposure_s"].as_f64().unwrap_or(f64::NAN);
            parts.dark = Some(MapPart {
                source: src,
                map: map("dark_map")?,
                size: size("dark")?,
                exposure_s: exposure,
                linearisation: None,
            });
        }
        "flat" => {
            parts.flat = Some(MapPart {
                source: src,
                map: map("flat_map")?,
                size: size("flat")?,
                exposure_s: f64::NAN,
                linearisation,
            })
        }
        _ => {
            let m: [[f64; 3]; 3] = serde_json::from_value(get("colour")?["matrix"].clone())
                .map_err(|e| bad(format!("radiometric.colour.matrix: {e}")))?;
            parts.colour = Some((src, m, linearisation));
        }
    }
    Ok(())
}

/// A white standard's `K` holds only for values corrected as they were during its fit: its
/// result lists the raw-correction ids it was measured with (`white_standard.corrections`,
/// empty in results of older builds), which must be exactly the ones applied.
fn check_white_corrections(results: &[LoadedResult], raw: Option<&RawCorrection>) -> Result<(), LoadError> {
    let Some(white) = results.iter().find(|r| r.kind == "white-standard") else {
        return Ok(());
    };
    let mut made: Vec<String> = white.value["white_standard"]["corrections"]
        .as_array()
        .map(|a| a.iter().filter_map(|v| v.as_str().map(String::from)).collect())
        .unwrap_or_default();
    let mut now: Vec<String> = raw
        .map(|c| c.sources.iter().map(|s| s.id.clone()).collect())
        .unwrap_or_default();
    made.sort();
    now.sort();
    if made == now {
        return Ok(());
    }
    Err(LoadError::Bad {
        file: white.file.display().to_string(),
        message: format!(
            "the white standard was fitted on frames corrected with the results {made:?}, this acquisition \
             applies {now:?} (dark/response/flat/colour): put the same results next to it, or re-run \
             white-standard.toml with [white_standard] corrections = \"DIR\" naming the directory of the \
             ones applied"
        ),
    })
}
