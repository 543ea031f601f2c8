//! `manifest.json`: the dataset header, and at `finish` the summary and every record.
//!
//! The header fields sit at the top level of the JSON object (so `format` and `version`
//! are the first thing a person or another tool sees); `complete`, `summary` and
//! `records` follow. While an acquisition runs the manifest holds only the header with
//! `"complete": false`: the journal is the record of what was measured.

use super::atomic::write_atomic;
use super::error::{IoContext, StoreError};
use super::{FORMAT, FORMAT_VERSION, MANIFEST_FILE};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Everything known about a dataset before its first measurement.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct ManifestHeader {
    /// Always [`FORMAT`]: lets tools (and `create --force`) recognise a gonio dataset.
    pub format: String,
    /// [`FORMAT_VERSION`] of the writer.
    pub version: u32,
    /// Version of the gonio that wrote the dataset.
    pub gonio_version: String,
    /// Creation time, seconds since the Unix epoch.
    pub created_unix: f64,
    /// The rig description used (as loaded from its TOML).
    pub rig: serde_json::Value,
    /// What was measured.
    pub sample: serde_json::Value,
    /// The sweep (direction set, ordering, retro-reflection policy).
    pub sweep: serde_json::Value,
    /// Size of every rectified image.
    pub image_width: usize,
    pub image_height: usize,
    /// What the pixel values mean, e.g. "linear normalized sensor signal (DN / max DN),
    /// radiometrically uncalibrated".
    pub values: String,
    /// Seed of every random process (simulated rigs, ordering).
    pub seed: u64,
    /// Whether raw 16-bit frames are kept under `raw/`.
    pub raw_frames: bool,
    /// Identifier of the radiometric/geometric calibration applied, if any.
    pub calibration: Option<String>,
    /// Anything else the engine wants to keep.
    #[serde(default)]
    pub extra: serde_json::Value,
}

impl ManifestHeader {
    /// A header of this gonio's format and version, created now, with the given content;
    /// seed 0, no raw frames, no calibration, nothing extra (callers set what differs).
    pub fn new(
        rig: serde_json::Value,
        sample: serde_json::Value,
        sweep: serde_json::Value,
        image_width: usize,
        image_height: usize,
        values: impl Into<String>,
    ) -> ManifestHeader {
        ManifestHeader {
            format: super::FORMAT.into(),
            version: super::FORMAT_VERSION,
            gonio_version: env!("CARGO_PKG_VERSION").into(),
            created_unix: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_secs_f64())
                .unwrap_or(0.0),
            rig,
            sample,
            sweep,
            image_width,
            image_height,
            values: values.into(),
            seed: 0,
            raw_frames: false,
            calibration: None,
            extra: serde_json::Value::Null,
        }
    }
}

/// What happened to one planned (light, view) pair.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum MeasurementStatus {
    /// Measured at the planned directions.
    Measured,
    /// Measured with a light direction other than the planned one (e.g. the camera
    /// blocks the lamp at retro-reflection); the record's `light_deg` holds the one
    /// actually used.
    Substituted {
        requested_light_deg: [f64; 2],
        reason: String,
    },
    /// Not measured; such a record has no image and is never exported.
    Skipped { reason: String },
    /// Not measured: predicted from the measured pairs in a prior by `gonio complete`
    /// (format version 2). `predicted_rmse_8bit` is the prior's predicted RMS error of the
    /// image on the 8-bit sRGB scale /255; `prior` names the prior file's payload hash.
    Predicted { predicted_rmse_8bit: f64, prior: String },
}

impl MeasurementStatus {
    /// Short name: "measured", "substituted", "skipped" or "predicted".
    pub fn kind(&self) -> &'static str {
        match self {
            MeasurementStatus::Measured => "measured",
            MeasurementStatus::Substituted { .. } => "substituted",
            MeasurementStatus::Skipped { .. } => "skipped",
            MeasurementStatus::Predicted { .. } => "predicted",
        }
    }
}

/// One measurement (or one skipped pair) as stored in the journal and manifest.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct MeasurementRecord {
    /// Canonical index (`view_index · 81 + light_index` for the Bonn set); names the
    /// image files.
    pub index: usize,
    /// Position in the executed plan.
    pub order: usize,
    /// Light direction actually used, (θ, φ) in degrees.
    pub light_deg: [f64; 2],
    /// View direction, (θ, φ) in degrees.
    pub view_deg: [f64; 2],
    #[serde(default)]
    pub light_read_back_deg: Option<[f64; 2]>,
    #[serde(default)]
    pub view_read_back_deg: Option<[f64; 2]>,
    #[serde(default)]
    pub axes_commanded_deg: Vec<f64>,
    #[serde(default)]
    pub axes_read_back_deg: Vec<f64>,
    /// Exposure time in seconds.
    pub exposure_s: f64,
    pub gain: f64,
    #[serde(default)]
    pub frame_sequence: Option<u64>,
    /// Time on the rig's clock (virtual for simulated rigs), seconds.
    pub rig_time_s: f64,
    pub wall_time_unix: f64,
    pub status: MeasurementStatus,
    /// Path of the rectified EXR relative to the dataset directory (filled by the store).
    #[serde(default)]
    pub image: Option<String>,
    /// Lower-case hex SHA-256 of the EXR file (filled by the store).
    #[serde(default)]
    pub image_sha256: Option<String>,
    /// Path of the raw 16-bit PNG relative to the dataset directory (filled by the store).
    #[serde(default)]
    pub raw: Option<String>,
    #[serde(default)]
    pub raw_sha256: Option<String>,
    /// The engine's per-measurement metrics (e.g. `truth_rmse`).
    #[serde(default)]
    pub extra: serde_json::Value,
    /// The lamp's measured voltage and current at this measurement, for lights whose
    /// supply measures (absent otherwise, and in datasets written before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lamp: Option<LampRecord>,
}

/// The lamp's electrical state at one measurement (see `gonio_devices::rig::LampMonitor`).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct LampRecord {
    /// Measured output voltage (V).
    pub voltage_v: f64,
    /// Measured output current (A).
    pub current_a: f64,
    /// Relative change from the run's reference reading (taken once the lamp was on and
    /// settled): `I / I₀ − 1` and `V / V₀ − 1`.
    pub current_drift: f64,
    pub voltage_drift: f64,
    /// The drift exceeded the rig's threshold (a warning was logged).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub drift_warning: bool,
    /// With a calibrated output exponent k: the stored values were divided by this factor,
    /// `(I / I₀)^k`. Absent: not corrected.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub output_correction: Option<f64>,
}

impl MeasurementRecord {
    /// A record with the given identity and directions and neutral defaults for the
    /// rest (status `Measured`, unit gain, no read-backs, no files).
    pub fn new(index: usize, order: usize, light_deg: [f64; 2], view_deg: [f64; 2]) -> Self {
        MeasurementRecord {
            index,
            order,
            light_deg,
            view_deg,
            light_read_back_deg: None,
            view_read_back_deg: None,
            axes_commanded_deg: Vec::new(),
            axes_read_back_deg: Vec::new(),
            exposure_s: 0.0,
            gain: 1.0,
            frame_sequence: None,
            rig_time_s: 0.0,
            wall_time_unix: 0.0,
            status: MeasurementStatus::Measured,
            image: None,
            image_sha256: None,
            raw: None,
            raw_sha256: None,
            extra: serde_json::Value::Null,
            lamp: None,
        }
    }
}

/// The whole `manifest.json`.
#[derive(Serialize, Deserialize, Clone, Debug)]
pub(crate) struct ManifestFile {
    #[serde(flatten)]
    pub header: ManifestHeader,
    /// True once `Dataset::finish` ran (and no measurement was stored since).
    #[serde(default)]
    pub complete: bool,
    /// Name of the journal file, for readers that find the manifest first.
    #[serde(default)]
    pub journal: Option<String>,
    #[serde(default)]
    pub summary: serde_json::Value,
    /// Every record sorted by index; empty until `finish`.
    #[serde(default)]
    pub records: Vec<MeasurementRecord>,
}

/// Check the header a caller wants to create a dataset with.
pub(crate) fn validate_header(dir: &Path, h: &ManifestHeader) -> Result<(), StoreError> {
    let bad = |reason: String| {
        Err(StoreError::InvalidHeader {
            path: dir.to_path_buf(),
            reason,
        })
    };
    if h.format != FORMAT {
        return bad(format!("format is {:?}, expected {FORMAT:?}", h.format));
    }
    if h.version != FORMAT_VERSION {
        return bad(format!(
            "version is {}, this gonio writes version {FORMAT_VERSION}",
            h.version
        ));
    }
    if h.image_width == 0 || h.image_height == 0 {
        return bad(format!("image size {}×{} is empty", h.image_width, h.image_height));
    }
    Ok(())
}

/// Write `manifest.json` atomically.
pub(crate) fn write_manifest(dir: &Path, m: &ManifestFile) -> Result<(), StoreError> {
    let path = dir.join(MANIFEST_FILE);
    let mut bytes = serde_json::to_vec_pretty(m).map_err(|source| StoreError::Json {
        path: path.clone(),
        source,
    })?;
    bytes.push(b'\n');
    write_atomic(&path, &bytes, Some(dir))
}

/// How a directory relates to the dataset format.
pub(crate) enum ManifestProbe {
    /// No `manifest.json`.
    Missing,
    /// A `manifest.json` that is not a gonio manifest (reason).
    Foreign(String),
    /// A gonio manifest that fails to parse or is too new.
    Broken(StoreError),
    /// A readable gonio manifest.
    Ok(Box<ManifestFile>),
}

/// Read `dir/manifest.json` and classify it.
pub(crate) fn probe_manifest(dir: &Path) -> Result<ManifestProbe, StoreError> {
    let path = dir.join(MANIFEST_FILE);
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(ManifestProbe::Missing),
        Err(e) => return Err(StoreError::io("reading", &path, Some(dir), e)),
    };
    let value: serde_json::Value = match serde_json::from_slice(&bytes) {
        Ok(v) => v,
        Err(e) => return Ok(ManifestProbe::Foreign(format!("manifest.json is not JSON: {e}"))),
    };
    match value.get("format").and_then(|f| f.as_str()) {
        Some(FORMAT) => {}
        Some(other) => return Ok(ManifestProbe::Foreign(format!("manifest.json has format {other:?}"))),
        None => return Ok(ManifestProbe::Foreign("manifest.json has no \"format\" field".into())),
    }
    if let Some(v) = value.get("version").and_then(|v| v.as_u64()) {
        if v > u64::from(FORMAT_VERSION) {
            return Ok(ManifestProbe::Broken(StoreError::UnsupportedVersion {
                path: path.clone(),
                found: v.min(u64::from(u32::MAX)) as u32,
                supported: FORMAT_VERSION,
            }));
        }
    }
    match serde_json::from_value::<ManifestFile>(value) {
        Ok(m) => Ok(ManifestProbe::Ok(Box::new(m))),
        Err(e) => Ok(ManifestProbe::Broken(StoreError::BadManifest {
            path,
            reason: e.to_string(),
        })),
    }
}

/// Read the manifest of an existing dataset, or explain why `dir` is not one.
pub(crate) fn read_manifest(dir: &Path) -> Result<ManifestFile, StoreError> {
    if !dir.is_dir() {
        // Distinguish "no such directory" from permission problems via metadata.
        std::fs::metadata(dir).ctx("opening", dir, None)?;
        return Err(StoreError::NotADataset {
            path: dir.to_path_buf(),
            reason: "it is not a directory".into(),
            hint: "give the dataset directory (the one holding manifest.json)",
        });
    }
    match probe_manifest(dir)? {
        ManifestProbe::Ok(m) => Ok(*m),
        ManifestProbe::Broken(e) => Err(e),
        ManifestProbe::Missing => Err(StoreError::NotADataset {
            path: dir.to_path_buf(),
            reason: "it has no manifest.json".into(),
            hint: "give the dataset directory (the one holding manifest.json)",
        }),
        ManifestProbe::Foreign(reason) => Err(StoreError::NotADataset {
            path: dir.to_path_buf(),
            reason,
            hint: "give the dataset directory (the one holding manifest.json)",
        }),
    }
}
