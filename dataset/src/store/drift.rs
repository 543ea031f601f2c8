//! `gonio dataset drift`: the drift references' series, and a drift-corrected copy.
//!
//! A measurement between references a and b (by its place in the journal, see
//! [`ReferenceRecord::stored_before`]) of the same run gets the ratio interpolated
//! linearly in rig time, r = (1 − w)·r_a + w·r_b, w = (t − t_a)/(t_b − t_a) clamped to
//! [0, 1], and the dark frame d interpolated with the same w, per texel. A measurement
//! whose next reference belongs to another run (the run was killed before its closing
//! reference: a resumed rig's clock restarts, so times of two runs do not compare) keeps
//! its last reference's ratio; one before any reference, the first reference's.
//!
//! The stored values include the dark signal unless a dark calibration was applied (then
//! the developed dark frames are ≈ 0), so the correction scales the signal only:
//! v' = (v − d) / r + d, per channel. The copy keeps the dataset's unit and dark level.
//!
//! A value clipped at the sensor's full scale (at or above the clip level, [`Clip`]) is
//! not a value but a lower bound, and is left as it is, counted (`clipped_kept`): scaled
//! up it would claim a reading no sensor gave, and a clip at the reference level would
//! still be a clip; scaled down it would leave the full scale and be taken for a value by
//! every reader that recognises clips by their level (`gonio complete --clip`). The level
//! is the full scale of the stored unit: 1 for single exposures in normalised DN (the
//! default unit), none for HDR datasets (merged values go above 1, nothing is clipped
//! there but a pixel saturated in every exposure, which the merge counts itself) and for
//! calibrated units (linear or BRDF: the full scale differs per texel, so no one level
//! marks it). A record's own level follows what was done to its values: × its
//! `extra.exposure_scale` (a frame re-exposed after saturating, scaled back to the nominal
//! exposure) and ÷ its lamp's `output_correction` (the lamp monitor's correction).
//!
//! The original is never modified: the copy is a new dataset (`Dataset::create`, every
//! file written atomically), its records carry `extra.drift_correction` (the factor per
//! channel and the references it came from), its manifest `extra.drift_correction` (the
//! source and the method). Raw frames are left out (they are the camera's numbers, not
//! corrected values); stored truths, the plan and calibration copies are copied, so the
//! copy can be compared with the truth and resumed readers find what they expect.

use super::error::StoreError;
use super::journal;
use super::manifest::{read_manifest, MeasurementRecord, MeasurementStatus};
use super::reference::ReferenceRecord;
use super::{dedupe, load_references, read_exr, Dataset, ManifestHeader, JOURNAL_FILE, PLAN_FILE};
use gonio_devices::hdr::HdrMode;
use gonio_devices::image::RgbImage;
use gonio_devices::rig::RigSpec;
use serde::Serialize;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Why a drift series or correction could not be made.
#[derive(Debug, thiserror::Error)]
pub enum DriftError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(
        "{}: no drift references (references.jsonl is missing or empty); acquire with \
         `gonio acquire --reference-every MINUTES` to track drift",
        dir.display()
    )]
    NoReferences { dir: PathBuf },
    #[error("--out {}: it is the source dataset itself; the original is never modified, choose another directory", out.display())]
    SameDirectory { out: PathBuf },
}

/// The factor of one measurement: the interpolated ratio and where it came from.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Factor {
    /// Per channel: stored value's signal / the first reference's level.
    pub ratio: [f64; 3],
    /// The references interpolated between (equal when one was used alone).
    pub references: [usize; 2],
    /// Weight of the second reference.
    pub weight: f64,
}

/// The factor of every record (journal order) from the references.
pub fn factors(records: &[MeasurementRecord], refs: &[ReferenceRecord]) -> Vec<Option<Factor>> {
    records
        .iter()
        .enumerate()
        .map(|(pos, r)| {
            r.image.as_ref()?;
            let a = refs.iter().rev().find(|x| x.stored_before <= pos);
            let b = refs.iter().find(|x| x.stored_before > pos);
            let one = |x: &ReferenceRecord| Factor {
                ratio: x.ratio,
                references: [x.number, x.number],
                weight: 0.0,
            };
            Some(match (a, b) {
                (Some(a), Some(b)) if a.run == b.run => {
                    let span = b.rig_time_s - a.rig_time_s;
                    let w = if span > 0.0 {
                        ((r.rig_time_s - a.rig_time_s) / span).clamp(0.0, 1.0)
                    } else {
                        0.0
                    };
                    Factor {
                        ratio: std::array::from_fn(|c| (1.0 - w) * a.ratio[c] + w * b.ratio[c]),
                        references: [a.number, b.number],
                        weight: w,
                    }
                }
                (Some(a), _) => one(a),
                (None, Some(b)) => one(b),
                (None, None) => return None,
            })
        })
        .collect()
}

/// The records of a dataset's journal in journal order (first occurrence of each index).
fn journal_records(dir: &Path) -> Result<Vec<MeasurementRecord>, StoreError> {
    let scan: journal::Scan = journal::scan(&dir.join(JOURNAL_FILE), dir)?;
    Ok(dedupe(scan.records).0)
}

/// The drift series of a dataset (`gonio dataset drift DIR`).
#[derive(Clone, Debug, Serialize)]
pub struct DriftSeries {
    pub dir: PathBuf,
    pub references: Vec<ReferenceRecord>,
    /// Largest relative change of any channel against the first reference.
    pub largest_drift: f64,
    /// Measurements with an image, and the range of their factors (per channel min, max).
    pub measurements: usize,
    pub factor_min: [f64; 3],
    pub factor_max: [f64; 3],
}

/// Read the references of the dataset at `dir` and the factors they give.
pub fn series(dir: &Path) -> Result<DriftSeries, DriftError> {
    read_manifest(dir)?;
    let references = load_references(dir)?;
    if references.is_empty() {
        return Err(DriftError::NoReferences { dir: dir.to_path_buf() });
    }
    let records = journal_records(dir)?;
    let f: Vec<Factor> = factors(&records, &references).into_iter().flatten().collect();
    let mut factor_min = [f64::INFINITY; 3];
    let mut factor_max = [f64::NEG_INFINITY; 3];
    for x in &f {
        for c in 0..3 {
            factor_min[c] = factor_min[c].min(x.ratio[c]);
            factor_max[c] = factor_max[c].max(x.ratio[c]);
        }
    }
    Ok(DriftSeries {
        dir: dir.to_path_buf(),
        largest_drift: references.iter().map(|r| r.drift()).fold(0.0, f64::max),
        references,
        measurements: f.len(),
        factor_min,
        factor_max,
    })
}

/// The level at and above which a stored value was clipped at the sensor's full scale.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Clip {
    /// The stored unit's full scale (see [`clip_level`]).
    #[default]
    Auto,
    /// This level (in the stored unit).
    Level(f64),
    /// Nothing is clipped: every value is scaled.
    Off,
}

/// The value unit of uncalibrated data (normalised DN: 1 is the sensor's full scale), as
/// `gonio acquire` writes it into `extra.value_unit`; a dataset without one has it.
pub use gonio_devices::image::VALUE_UNIT_DN;

/// Relative margin below the level that still counts as clipped: half a step of the stored
/// f16 (11 significant bits), so a value the storage rounds to the level and the level
/// itself are alike (at level 1, every stored value in the margin reads exactly 1).
const CLIP_TOLERANCE: f64 = 1.0 / 4096.0;

/// The clip level of a dataset for `clip`, and why (for the report).
pub fn clip_level(header: &ManifestHeader, clip: Clip) -> (Option<f64>, String) {
    match clip {
        Clip::Level(l) => (Some(l), "given".into()),
        Clip::Off => (None, "off (given)".into()),
        Clip::Auto => {
            let unit = header
                .extra
                .get("value_unit")
                .and_then(|u| u.as_str())
                .unwrap_or(VALUE_UNIT_DN);
            let hdr = serde_json::from_value::<RigSpec>(header.rig.clone())
                .ok()
                .is_some_and(|r| r.hdr_mode() != HdrMode::Off);
            if hdr {
                (None, "off: HDR dataset (merged values have no full scale)".into())
            } else if unit != VALUE_UNIT_DN {
                (
                    None,
                    format!("off: value unit {unit} (calibrated values have no single full scale)"),
                )
            } else {
                (
                    Some(gonio_devices::rig::FULL_SCALE),
                    "1: full scale of normalised DN".into(),
                )
            }
        }
    }
}

/// The clip level of one record's stored values for the dataset's `level` (see the module
/// docs): scaled with them by a re-exposure's `exposure_scale` and the lamp's output
/// correction.
pub fn record_clip_level(level: f64, rec: &MeasurementRecord) -> f64 {
    let scale = rec
        .extra
        .get("exposure_scale")
        .and_then(|v| v.as_f64())
        .filter(|k| k.is_finite() && *k > 0.0)
        .unwrap_or(1.0);
    let lamp = rec
        .lamp
        .as_ref()
        .and_then(|l| l.output_correction)
        .filter(|f| f.is_finite() && *f > 0.0)
        .unwrap_or(1.0);
    level * scale / lamp
}

/// Correct `img` in place: v' = (v − d) / r + d with d interpolated between the dark
/// frames `da` and `db` by `w`; values at or above `clip` are left as they are. Returns how
/// many were left.
pub fn correct_image(
    img: &mut RgbImage,
    da: &RgbImage,
    db: &RgbImage,
    w: f64,
    ratio: [f64; 3],
    clip: Option<f64>,
) -> usize {
    let w = w as f32;
    let ceiling = clip.map_or(f32::INFINITY, |l| (l * (1.0 - CLIP_TOLERANCE)) as f32);
    let mut kept = 0;
    for (i, v) in img.data.iter_mut().enumerate() {
        if *v >= ceiling {
            kept += 1;
            continue;
        }
        let d = (1.0 - w) * da.data[i] + w * db.data[i];
        *v = (*v - d) / ratio[i % 3] as f32 + d;
    }
    kept
}

/// What [`correct`] did.
#[derive(Clone, Debug, Serialize)]
pub struct CorrectReport {
    pub source: PathBuf,
    pub out: PathBuf,
    pub corrected: usize,
    /// Records copied without an image (skipped pairs).
    pub copied_without_image: usize,
    pub references: usize,
    pub factor_min: [f64; 3],
    pub factor_max: [f64; 3],
    /// The level at and above which a value counts as clipped (`None`: off), and why.
    pub clip_level: Option<f64>,
    pub clip_level_reason: String,
    /// Texel values (channels) at or above the clip level, left unscaled.
    pub clipped_kept: usize,
    /// With stored truths (`--store-truth`): PSNR (dB, values clamped to [0, 1]) of the
    /// images against them before and after the correction.
    pub truth_psnr_before_db: Option<f64>,
    pub truth_psnr_after_db: Option<f64>,
    /// With stored truths: the relative mean absolute error Σ|x − t| / Σ|t| before and
    /// after. A drift is a bias of every texel; PSNR, weighted to the largest errors
    /// (edges, highlights), sees it less.
    pub truth_rel_mae_before: Option<f64>,
    pub truth_rel_mae_after: Option<f64>,
}

/// Errors against a truth, values clamped to [0, 1] as the acquisition's truth error:
/// summed squared error, summed absolute error, summed |truth|.
#[derive(Clone, Copy, Default)]
struct Sums {
    sq: f64,
    abs: f64,
    truth: f64,
    n: usize,
}

impl Sums {
    fn add(&mut self, a: &RgbImage, t: &RgbImage) {
        for (x, y) in a.data.iter().zip(&t.data) {
            let (x, y) = (x.clamp(0.0, 1.0) as f64, y.clamp(0.0, 1.0) as f64);
            self.sq += (x - y) * (x - y);
            self.abs += (x - y).abs();
            self.truth += y;
        }
        self.n += a.data.len();
    }

    fn psnr(&self) -> Option<f64> {
        (self.n > 0).then(|| -10.0 * (self.sq / self.n as f64).max(1e-30).log10())
    }

    fn rel_mae(&self) -> Option<f64> {
        (self.n > 0 && self.truth > 0.0).then(|| self.abs / self.truth)
    }
}

/// Write a drift-corrected copy of the dataset at `src` to `out` (see the module docs).
/// `force` replaces a gonio dataset at `out`; `clip` says which values were clipped.
pub fn correct(src: &Path, out: &Path, force: bool, clip: Clip) -> Result<CorrectReport, DriftError> {
    if let (Ok(a), Ok(b)) = (src.canonicalize(), out.canonicalize()) {
        if a == b {
            return Err(DriftError::SameDirectory { out: out.to_path_buf() });
        }
    }
    let manifest = read_manifest(src)?;
    let refs = load_references(src)?;
    if refs.is_empty() {
        return Err(DriftError::NoReferences { dir: src.to_path_buf() });
    }
    let records = journal_records(src)?;
    let factors = factors(&records, &refs);
    let (clip_level, clip_level_reason) = clip_level(&manifest.header, clip);
    let mut header = manifest.header.clone();
    header.raw_frames = false;
    header.extra["drift_correction"] = serde_json::json!({
        "source_references": refs.len(),
        "method": "v' = (v - d) / r + d per channel; r and the dark frame d interpolated linearly \
                   in rig time between the references around each measurement; values at or above \
                   clip_level (clipped at the sensor's full scale, lower bounds) left unscaled",
        "clip_level": clip_level,
    });
    let mut ds = Dataset::create(out, &header, force)?;
    let plan_path = src.join(PLAN_FILE);
    match std::fs::read(&plan_path) {
        Ok(plan) => ds.write_plan(&plan)?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(StoreError::io("reading", &plan_path, Some(src), e).into()),
    }
    if let Some(list) = manifest.header.extra.get("calibrations").and_then(|v| v.as_array()) {
        for e in list {
            if let (Some(kind), Some(file)) = (
                e.get("kind").and_then(|k| k.as_str()),
                e.get("file").and_then(|f| f.as_str()),
            ) {
                let path = src.join(file);
                let bytes = std::fs::read(&path).map_err(|e| StoreError::io("reading", &path, Some(src), e))?;
                ds.store_calibration_copy(kind, &bytes)?;
            }
        }
    }
    let mut darks: HashMap<usize, RgbImage> = HashMap::new();
    let mut dark = |n: usize| -> Result<RgbImage, StoreError> {
        if let Some(d) = darks.get(&n) {
            return Ok(d.clone());
        }
        let d = read_exr(&src.join(&refs[n].dark))?;
        darks.insert(n, d.clone());
        Ok(d)
    };
    let mut report = CorrectReport {
        source: src.to_path_buf(),
        out: out.to_path_buf(),
        corrected: 0,
        copied_without_image: 0,
        references: refs.len(),
        factor_min: [f64::INFINITY; 3],
        factor_max: [f64::NEG_INFINITY; 3],
        clip_level,
        clip_level_reason,
        clipped_kept: 0,
        truth_psnr_before_db: None,
        truth_psnr_after_db: None,
        truth_rel_mae_before: None,
        truth_rel_mae_after: None,
    };
    let (mut before, mut after) = (Sums::default(), Sums::default());
    for (rec, f) in records.into_iter().zip(factors) {
        let (Some(rel), Some(f)) = (rec.image.clone(), f) else {
            report.copied_without_image += 1;
            ds.store(rec, None, None)?;
            continue;
        };
        let mut img = read_exr(&src.join(&rel))?;
        let original = img.clone();
        let predicted = matches!(rec.status, MeasurementStatus::Predicted { .. });
        let mut kept = 0;
        if !predicted {
            let (da, db) = (dark(f.references[0])?, dark(f.references[1])?);
            let level = clip_level.map(|l| record_clip_level(l, &rec));
            kept = correct_image(&mut img, &da, &db, f.weight, f.ratio, level);
            report.clipped_kept += kept;
            for c in 0..3 {
                report.factor_min[c] = report.factor_min[c].min(f.ratio[c]);
                report.factor_max[c] = report.factor_max[c].max(f.ratio[c]);
            }
        }
        let mut rec = rec;
        rec.extra["drift_correction"] = serde_json::json!({
            "factor": if predicted { [1.0; 3] } else { f.ratio },
            "references": f.references,
            "weight": f.weight,
            "clipped_kept": kept,
        });
        if let Some(t) = rec
            .extra
            .get("truth_image")
            .and_then(|t| t.as_str())
            .map(str::to_string)
        {
            let truth = read_exr(&src.join(&t))?;
            before.add(&original, &truth);
            after.add(&img, &truth);
            ds.store_truth(rec.index, &truth)?;
        }
        ds.store(rec, Some(&img), None)?;
        report.corrected += 1;
    }
    report.truth_psnr_before_db = before.psnr();
    report.truth_psnr_after_db = after.psnr();
    report.truth_rel_mae_before = before.rel_mae();
    report.truth_rel_mae_after = after.rel_mae();
    if manifest.complete {
        let mut summary = manifest.summary.clone();
        if summary.is_object() {
            summary["drift_corrected"] = serde_json::json!(true);
        }
        ds.finish(&summary)?;
    }
    Ok(report)
}
