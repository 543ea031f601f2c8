//! The native gonio dataset: crash-safe storage of an acquisition, and exports.
//!
//! # Format (`"format": "gonio-dataset"`, version 1)
//!
//! A dataset is a directory:
//!
//! ```text
//! DIR/
//!   manifest.json     header; after `finish` also "complete": true, summary, all records
//!   journal.jsonl     append-only, one line per stored measurement (the source of truth)
//!   images/NNNNN.exr  rectified image of measurement NNNNN (RGB half float, ZIP)
//!   raw/NNNNN.png     optional raw frame of measurement NNNNN (16-bit RGB PNG, DN as read)
//!   plan.json         the executed plan (written once at creation; `--resume` follows it)
//!   truth/NNNNN.exr   optional exact rectified ground truth of simulated rigs (`--store-truth`)
//!   calibration/KIND.json  copies of the calibration results applied (`--calibration`)
//!   references.jsonl  optional drift references (`--reference-every`), see `reference.rs`
//!   reference/NNNNN.exr, reference/NNNNN-dark.exr  their reference and dark images
//! ```
//!
//! [`Dataset`] writes every one of these files (one writer): the plan as opaque bytes (the
//! store does not depend on the planner), the truth images and the calibration copies
//! through the same atomic write as the images.
//!
//! * **`NNNNN`** is the record's canonical `index` (`view_index · 81 + light_index` for
//!   the Bonn set), zero-padded to five digits (wider if ever needed).
//! * **`manifest.json`** is a JSON object whose top-level fields are those of
//!   [`ManifestHeader`] (`format`, `version`, `gonio_version`, `created_unix`, `rig`,
//!   `sample`, `sweep`, `image_width`, `image_height`, `values`, `seed`, `raw_frames`,
//!   `calibration`, `extra`), followed by `complete` (bool), `journal`
//!   (`"journal.jsonl"`), `summary` (the engine's summary, `null` until `finish`) and
//!   `records` (every [`MeasurementRecord`] sorted by index; empty until `finish`). It is
//!   only ever replaced atomically. `values` states what the pixel values mean; data
//!   that are not radiometrically calibrated say so there.
//! * **`journal.jsonl`**: one line per stored measurement, in the order they were
//!   stored: `{"crc":"<8 hex digits>","rec":{…record…}}` with the CRC-32 of the exact
//!   `rec` bytes (details in `journal.rs`). Readers must use the journal, not the
//!   manifest's `records`, unless `complete` is true.
//! * **Images** hold linear values (not sRGB), rows top to bottom, in the rectified
//!   frame of conventions.md; the record's `image_sha256` is the SHA-256 of the file.
//! * **Raw frames** hold the camera's digital numbers unscaled (a 12-bit camera's
//!   values stay in 0‥4095); `raw_sha256` is the file's SHA-256.
//! * Record angles are degrees, (θ, φ), `light_deg` being the light direction actually
//!   used: a `substituted` record keeps the planned one in its status, a `skipped`
//!   record has no files and is never exported.
//!
//! # Durability
//!
//! A measurement counts as stored only when its files are renamed into place **and**
//! its journal line is fsynced ([`Dataset::store`]): files are written under a
//! temporary name (`.tmp-…`), fsynced, renamed, and the directory fsynced; then the
//! journal line is appended and fsynced. So after any crash:
//!
//! * a file without a journal line is an orphan (removed by [`Dataset::resume`]);
//! * only the last journal line can be torn (cut off by [`Dataset::resume`]);
//! * no file under a final name is ever half-written.
//!
//! `resume` also re-hashes every stored file and drops (and deletes) records whose
//! files are missing or damaged, so that they are measured again. A directory lock
//! (`flock`) keeps two processes from writing one dataset.
//!
//! # Exports
//!
//! [`export_ubo2003`] writes the Bonn UBO2003 ZIP of 8-bit sRGB JPEGs read by the public
//! `btf-extractor` reader; [`export_npy`] writes the exact 8-bit values behind those
//! JPEGs for interop tests (`tests/interop/check_ubo2003.py`).

pub mod atomic;
pub mod drift;
mod error;
pub mod export;
pub mod exr_io;
pub mod import_ubo2003;
mod journal;
mod manifest;
pub mod provenance;
pub mod reference;
pub mod verify;

#[cfg(test)]
mod tests;

pub use error::StoreError;
pub use export::{
    entry_name, export_npy, export_ubo2003, integer_angles, linear_to_srgb8, npy_sidecar_path, ExportReport,
    JPEG_QUALITY,
};
pub use exr_io::{decode_exr, encode_exr, read_exr, write_exr, COMPRESSION as EXR_COMPRESSION};
pub use manifest::{LampRecord, ManifestHeader, MeasurementRecord, MeasurementStatus};
pub use reference::{ReferenceRecord, REFERENCES_FILE, REFERENCE_DIR};
pub use verify::{verify, VerifyReport};

use atomic::{remove_temp_files, sync_dir, sync_parent, write_atomic, DirLock, TMP_PREFIX};
use error::IoContext;
use gonio_devices::image::RgbImage;
use gonio_devices::Frame;
use journal::{encode_line, Appender};
use manifest::{probe_manifest, read_manifest, validate_header, write_manifest, ManifestFile, ManifestProbe};
use sha2::{Digest, Sha256};
use std::collections::{HashMap, HashSet};
use std::fs::{self, OpenOptions};
use std::path::{Path, PathBuf};

/// Value of the manifest's `format` field.
pub const FORMAT: &str = "gonio-dataset";
/// Version of the dataset layout this gonio writes (and the newest it reads). Version 2
/// adds the measurement status `predicted` (`gonio complete`); version 1 files are read.
pub const FORMAT_VERSION: u32 = 2;
/// File names inside a dataset directory.
pub const MANIFEST_FILE: &str = "manifest.json";
pub const JOURNAL_FILE: &str = "journal.jsonl";
pub const IMAGES_DIR: &str = "images";
pub const RAW_DIR: &str = "raw";
pub const PLAN_FILE: &str = "plan.json";
pub const TRUTH_DIR: &str = "truth";
pub const CALIBRATION_DIR: &str = "calibration";

/// Rewrite a journal-format file (`journal.jsonl`, `references.jsonl`) atomically with only
/// the `records` that `resume` keeps; returns the new length, where appending continues.
fn rewrite_lines<T: serde::Serialize>(path: &Path, records: &[T], dir: &Path) -> Result<u64, StoreError> {
    let mut bytes = Vec::new();
    for r in records {
        bytes.extend(encode_line(r).map_err(|source| StoreError::Json {
            path: path.to_path_buf(),
            source,
        })?);
    }
    write_atomic(path, &bytes, Some(dir))?;
    Ok(bytes.len() as u64)
}

/// Remove the files written for a record that will not be recorded (best effort: only its
/// line makes a file part of the dataset, and resume removes orphans).
fn remove_files(paths: &[PathBuf]) {
    for p in paths {
        let _ = fs::remove_file(p);
    }
}

/// The last step of storing a record (a measurement's in `journal.jsonl`, a drift
/// reference's in `references.jsonl`) whose files `written` are already renamed into place:
/// append its line to `appender` (the file `path`) and fsync. On failure the files are
/// removed, so nothing is recorded; a partial line that could not be rolled back poisons
/// the store, which then refuses every further write.
fn append_record_line(
    appender: &mut Appender,
    line: &[u8],
    path: &Path,
    ds: Option<&Path>,
    written: &[PathBuf],
    poisoned: &mut Option<String>,
) -> Result<(), StoreError> {
    if let Err((e, rolled_back)) = appender.append(line) {
        remove_files(written);
        if !rolled_back {
            *poisoned = Some(format!(
                "appending to {} failed ({e}) and the partial line could not be removed",
                path.display()
            ));
        }
        return Err(StoreError::io("appending to", path, ds, e));
    }
    Ok(())
}

/// Relative path of the stored ground truth of measurement `index`.
pub fn truth_rel_path(index: usize) -> String {
    format!("{TRUTH_DIR}/{index:05}.exr")
}

/// Relative path of the copy of the calibration result of `kind`.
pub fn calibration_rel_path(kind: &str) -> String {
    format!("{CALIBRATION_DIR}/{kind}.json")
}

/// Relative path of the rectified image of measurement `index`.
pub fn image_rel_path(index: usize) -> String {
    format!("{IMAGES_DIR}/{index:05}.exr")
}

/// Relative path of the raw frame of measurement `index`.
pub fn raw_rel_path(index: usize) -> String {
    format!("{RAW_DIR}/{index:05}.png")
}

/// Lower-case hex SHA-256.
pub(crate) fn sha256_hex(bytes: &[u8]) -> String {
    let digest = Sha256::digest(bytes);
    let mut s = String::with_capacity(64);
    for b in digest {
        s.push_str(&format!("{b:02x}"));
    }
    s
}

/// What [`Dataset::resume`] found and repaired (also logged as warnings).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RecoveryReport {
    /// The journal's last line was torn: (line number, reason). It was cut off.
    pub torn_line: Option<(usize, String)>,
    /// The last line was complete but lacked its newline; one was added.
    pub added_newline: bool,
    /// Indices that appeared more than once in the journal (the first was kept).
    pub duplicates: Vec<usize>,
    /// Records dropped because a file was missing or damaged: (index, problem). Their
    /// measurements must be redone.
    pub dropped: Vec<(usize, String)>,
    /// Files without a journal line, removed.
    pub orphans_removed: Vec<PathBuf>,
    /// Drift references dropped because a file was missing or damaged, or their line was
    /// torn: (number, problem). The resumed run takes a reference of its own at its start.
    pub references_dropped: Vec<(usize, String)>,
    /// Leftover temporary files, removed.
    pub temp_removed: Vec<PathBuf>,
}

impl RecoveryReport {
    /// True if resume found nothing to repair.
    pub fn is_clean(&self) -> bool {
        *self == RecoveryReport::default()
    }
}

/// An open dataset being written. Holds the dataset's lock until dropped.
pub struct Dataset {
    dir: PathBuf,
    header: ManifestHeader,
    journal: Appender,
    /// Stored records in journal order.
    records: Vec<MeasurementRecord>,
    indices: HashSet<usize>,
    /// Whether manifest.json currently says "complete": true.
    manifest_complete: bool,
    /// Set when a failed journal append could not be rolled back.
    poisoned: Option<String>,
    recovery: RecoveryReport,
    /// Drift references stored so far (`references.jsonl`), in order.
    references: Vec<ReferenceRecord>,
    /// `references.jsonl`, opened at the first reference of this process.
    ref_journal: Option<Appender>,
    /// This process's run number (see [`ReferenceRecord::run`]).
    run: usize,
    _lock: DirLock,
}

impl std::fmt::Debug for Dataset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Dataset")
            .field("dir", &self.dir)
            .field("records", &self.records.len())
            .field("complete", &self.manifest_complete)
            .finish()
    }
}

impl Dataset {
    /// Create a new dataset in `dir` (created if missing).
    ///
    /// An existing non-empty directory is refused unless `force`; with `force` a gonio
    /// dataset's contents are deleted first, while any other non-empty directory is
    /// still refused (gonio never deletes data it did not write).
    pub fn create(dir: &Path, header: &ManifestHeader, force: bool) -> Result<Dataset, StoreError> {
        validate_header(dir, header)?;
        let mut lock = None;
        match fs::metadata(dir) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                fs::create_dir_all(dir).ctx("creating directory", dir, Some(dir))?;
                sync_parent(dir, Some(dir))?;
            }
            Err(e) => return Err(StoreError::io("opening", dir, Some(dir), e)),
            Ok(m) if !m.is_dir() => {
                return Err(StoreError::NotADataset {
                    path: dir.to_path_buf(),
                    reason: "it is a file, not a directory".into(),
                    hint: "choose a directory path for the dataset",
                })
            }
            Ok(_) => {
                let non_empty = fs::read_dir(dir).ctx("listing", dir, Some(dir))?.next().is_some();
                if non_empty {
                    if !force {
                        return Err(StoreError::NotEmpty {
                            path: dir.to_path_buf(),
                        });
                    }
                    match probe_manifest(dir)? {
                        ManifestProbe::Ok(_) | ManifestProbe::Broken(_) => {}
                        // A `create` interrupted before its manifest was written (a kill,
                        // a power cut) leaves only the store's own skeleton: replaceable.
                        ManifestProbe::Missing if is_interrupted_create(dir) => {}
                        ManifestProbe::Missing => {
                            return Err(StoreError::NotADataset {
                                path: dir.to_path_buf(),
                                reason: "it is not empty and has no manifest.json".into(),
                                hint: "--force only replaces gonio datasets; remove the \
                                       directory yourself or choose another one",
                            })
                        }
                        ManifestProbe::Foreign(reason) => {
                            return Err(StoreError::NotADataset {
                                path: dir.to_path_buf(),
                                reason,
                                hint: "--force only replaces gonio datasets; remove the \
                                       directory yourself or choose another one",
                            })
                        }
                    }
                    let l = DirLock::acquire(dir)?;
                    tracing::warn!(dir = %dir.display(), "--force: deleting the existing dataset");
                    // Manifest first: an interrupted deletion then no longer looks
                    // like a complete dataset.
                    let manifest = dir.join(MANIFEST_FILE);
                    match fs::remove_file(&manifest) {
                        Ok(()) => {}
                        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                        Err(e) => return Err(StoreError::io("removing", &manifest, Some(dir), e)),
                    }
                    for entry in fs::read_dir(dir).ctx("listing", dir, Some(dir))? {
                        let entry = entry.ctx("listing", dir, Some(dir))?;
                        let p = entry.path();
                        let is_dir = entry.file_type().map(|t| t.is_dir()).unwrap_or(false);
                        if is_dir {
                            fs::remove_dir_all(&p).ctx("removing", &p, Some(dir))?;
                        } else {
                            fs::remove_file(&p).ctx("removing", &p, Some(dir))?;
                        }
                    }
                    sync_dir(dir, Some(dir))?;
                    lock = Some(l);
                }
            }
        }
        let lock = match lock {
            Some(l) => l,
            None => DirLock::acquire(dir)?,
        };

        let images = dir.join(IMAGES_DIR);
        fs::create_dir_all(&images).ctx("creating directory", &images, Some(dir))?;
        if header.raw_frames {
            let raw = dir.join(RAW_DIR);
            fs::create_dir_all(&raw).ctx("creating directory", &raw, Some(dir))?;
        }
        let jpath = dir.join(JOURNAL_FILE);
        let jfile = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(&jpath)
            .ctx("creating", &jpath, Some(dir))?;
        jfile.sync_all().ctx("syncing", &jpath, Some(dir))?;
        sync_dir(dir, Some(dir))?;
        // The manifest comes last: its presence means the dataset was fully created.
        write_manifest(
            dir,
            &ManifestFile {
                header: header.clone(),
                complete: false,
                journal: Some(JOURNAL_FILE.into()),
                summary: serde_json::Value::Null,
                records: Vec::new(),
            },
        )?;
        Ok(Dataset {
            dir: dir.to_path_buf(),
            header: header.clone(),
            journal: Appender::new(jfile, 0).ctx("opening", &jpath, Some(dir))?,
            records: Vec::new(),
            indices: HashSet::new(),
            manifest_complete: false,
            poisoned: None,
            recovery: RecoveryReport::default(),
            references: Vec::new(),
            ref_journal: None,
            run: 0,
            _lock: lock,
        })
    }

    /// Reopen an interrupted (or finished) dataset to continue it.
    ///
    /// Repairs what a crash can leave behind and returns the header and the records
    /// that are safely stored, in journal order; every planned measurement not among
    /// them must be measured (again). What was repaired is logged and available from
    /// [`Dataset::recovery`].
    pub fn resume(dir: &Path) -> Result<(Dataset, ManifestHeader, Vec<MeasurementRecord>), StoreError> {
        let manifest = read_manifest(dir)?;
        let lock = DirLock::acquire(dir)?;
        let mut report = RecoveryReport::default();

        // 1. Temporary files: nobody else writes (we hold the lock), so they are debris.
        for sub in [
            dir.to_path_buf(),
            dir.join(IMAGES_DIR),
            dir.join(RAW_DIR),
            dir.join(REFERENCE_DIR),
        ] {
            report.temp_removed.extend(remove_temp_files(&sub, Some(dir))?);
        }
        for p in &report.temp_removed {
            tracing::warn!(file = %p.display(), "resume: removed leftover temporary file");
        }

        // 2. Journal: cut a torn last line, complete a missing newline.
        let jpath = dir.join(JOURNAL_FILE);
        let scan = journal::scan(&jpath, dir)?;
        let jfile = OpenOptions::new()
            .read(true)
            .write(true)
            .open(&jpath)
            .ctx("opening", &jpath, Some(dir))?;
        let mut len = jfile.metadata().ctx("reading", &jpath, Some(dir))?.len();
        if let Some(t) = &scan.torn {
            tracing::warn!(
                journal = %jpath.display(), line = t.line, reason = %t.reason,
                "resume: the last journal line is torn (crash while appending); removing it"
            );
            jfile.set_len(t.offset).ctx("truncating", &jpath, Some(dir))?;
            jfile.sync_all().ctx("syncing", &jpath, Some(dir))?;
            len = t.offset;
            report.torn_line = Some((t.line, t.reason.clone()));
        }
        let mut journal = Appender::new(jfile, len).ctx("opening", &jpath, Some(dir))?;
        if scan.missing_newline {
            tracing::warn!(journal = %jpath.display(), "resume: adding the missing final newline");
            journal
                .append(b"\n")
                .map_err(|(e, _)| StoreError::io("appending to", &jpath, Some(dir), e))?;
            report.added_newline = true;
        }

        // 3. Duplicates: keep the first.
        let (records, dups) = dedupe(scan.records);
        for i in &dups {
            tracing::warn!(
                index = i,
                "resume: index stored twice in the journal; keeping the first"
            );
        }
        report.duplicates = dups;

        // 4. Re-hash every file; drop records whose files are missing or damaged.
        use rayon::prelude::*;
        let problems: Vec<Option<String>> = records.par_iter().map(|r| check_record_files(dir, r)).collect();
        let mut kept = Vec::with_capacity(records.len());
        for (r, problem) in records.into_iter().zip(problems) {
            match problem {
                None => kept.push(r),
                Some(p) => {
                    tracing::warn!(index = r.index, problem = %p,
                        "resume: dropping the record so the measurement is redone");
                    for rel in [image_rel_path(r.index), raw_rel_path(r.index)] {
                        let f = dir.join(rel);
                        match fs::remove_file(&f) {
                            Ok(()) => {}
                            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                            Err(e) => return Err(StoreError::io("removing", &f, Some(dir), e)),
                        }
                    }
                    report.dropped.push((r.index, p));
                }
            }
        }

        // 5. Orphans: files no kept record refers to.
        let referenced: HashSet<String> = kept
            .iter()
            .flat_map(|r| [r.image.clone(), r.raw.clone()])
            .flatten()
            .collect();
        for (sub, ext) in [(IMAGES_DIR, "exr"), (RAW_DIR, "png")] {
            report
                .orphans_removed
                .extend(remove_orphans(dir, sub, ext, &referenced)?);
        }

        // 6. If records were dropped, rewrite the journal without them, so a re-measured
        // index is not shadowed by its old line ("keep first") on the next resume.
        if !report.dropped.is_empty() || !report.duplicates.is_empty() {
            let len = rewrite_lines(&jpath, &kept, dir)?;
            let jfile = OpenOptions::new()
                .read(true)
                .write(true)
                .open(&jpath)
                .ctx("opening", &jpath, Some(dir))?;
            journal = Appender::new(jfile, len).ctx("opening", &jpath, Some(dir))?;
        }
        for sub in [IMAGES_DIR, RAW_DIR] {
            let d = dir.join(sub);
            if d.is_dir() {
                sync_dir(&d, Some(dir))?;
            }
        }

        let (references, ref_journal) = resume_references(dir, &mut report)?;
        let run = references.last().map_or(0, |r| r.run + 1);

        let header = manifest.header.clone();
        let ds = Dataset {
            dir: dir.to_path_buf(),
            header: manifest.header,
            journal,
            indices: kept.iter().map(|r| r.index).collect(),
            records: kept.clone(),
            manifest_complete: manifest.complete,
            poisoned: None,
            recovery: report,
            references,
            ref_journal,
            run,
            _lock: lock,
        };
        Ok((ds, header, kept))
    }

    /// Store one measurement: write its image (and raw frame) durably, then append and
    /// fsync its journal line. Returns the record with `image`, `image_sha256`, `raw`
    /// and `raw_sha256` filled in. Measured and substituted records need an image;
    /// skipped ones must have none. On error nothing is recorded: the measurement can
    /// be retried (or redone after `resume`).
    pub fn store(
        &mut self,
        mut rec: MeasurementRecord,
        image: Option<&RgbImage>,
        raw: Option<&Frame>,
    ) -> Result<MeasurementRecord, StoreError> {
        let dir = self.dir.clone();
        let ds = Some(dir.as_path());
        if let Some(reason) = &self.poisoned {
            return Err(StoreError::Poisoned {
                path: dir,
                reason: reason.clone(),
            });
        }
        let invalid = |reason: String| StoreError::InvalidMeasurement {
            path: dir.clone(),
            index: rec.index,
            reason,
        };
        if self.indices.contains(&rec.index) {
            return Err(StoreError::DuplicateIndex {
                path: dir.clone(),
                index: rec.index,
            });
        }
        let skipped = matches!(rec.status, MeasurementStatus::Skipped { .. });
        match (skipped, image, raw) {
            (true, Some(_), _) | (true, _, Some(_)) => {
                return Err(invalid("a skipped measurement has no image or raw frame".into()))
            }
            (false, None, _) => return Err(invalid(format!("a {} measurement needs its image", rec.status.kind()))),
            _ => {}
        }
        if let Some(img) = image {
            if img.width != self.header.image_width
                || img.height != self.header.image_height
                || img.data.len() != img.width * img.height * 3
            {
                return Err(invalid(format!(
                    "image is {}×{} with {} values; the dataset's images are {}×{} RGB",
                    img.width,
                    img.height,
                    img.data.len(),
                    self.header.image_width,
                    self.header.image_height
                )));
            }
        }
        if let Some(f) = raw {
            if f.data.len() != f.width * f.height * 3 || f.width == 0 || f.height == 0 {
                return Err(invalid(format!(
                    "raw frame is {}×{} with {} values",
                    f.width,
                    f.height,
                    f.data.len()
                )));
            }
        }

        if self.manifest_complete {
            // New data after `finish`: the manifest's record list is no longer complete.
            write_manifest(
                &dir,
                &ManifestFile {
                    header: self.header.clone(),
                    complete: false,
                    journal: Some(JOURNAL_FILE.into()),
                    summary: serde_json::Value::Null,
                    records: Vec::new(),
                },
            )?;
            self.manifest_complete = false;
        }

        rec.image = None;
        rec.image_sha256 = None;
        rec.raw = None;
        rec.raw_sha256 = None;
        let mut written: Vec<PathBuf> = Vec::new();
        let result = (|| -> Result<(), StoreError> {
            if let Some(img) = image {
                let rel = image_rel_path(rec.index);
                let path = dir.join(&rel);
                let bytes = encode_exr(img, &path)?;
                rec.image_sha256 = Some(sha256_hex(&bytes));
                write_atomic(&path, &bytes, ds)?;
                written.push(path);
                rec.image = Some(rel);
            }
            if let Some(frame) = raw {
                let rawdir = dir.join(RAW_DIR);
                if !rawdir.is_dir() {
                    fs::create_dir_all(&rawdir).ctx("creating directory", &rawdir, ds)?;
                    sync_dir(&dir, ds)?;
                }
                let rel = raw_rel_path(rec.index);
                let path = dir.join(&rel);
                let bytes = encode_raw_png(frame, &path)?;
                rec.raw_sha256 = Some(sha256_hex(&bytes));
                write_atomic(&path, &bytes, ds)?;
                written.push(path);
                rec.raw = Some(rel);
            }
            Ok(())
        })();
        if let Err(e) = result {
            remove_files(&written);
            return Err(e);
        }

        let jpath = dir.join(JOURNAL_FILE);
        let line = match encode_line(&rec) {
            Ok(l) => l,
            Err(source) => {
                remove_files(&written);
                return Err(StoreError::Json { path: jpath, source });
            }
        };
        append_record_line(&mut self.journal, &line, &jpath, ds, &written, &mut self.poisoned)?;
        self.indices.insert(rec.index);
        self.records.push(rec.clone());
        Ok(rec)
    }

    /// Store a drift reference (see [`reference`]): the reference pair's developed image
    /// and the dark frame's, renamed into place, then its line appended to
    /// `references.jsonl` and fsynced. The store fills in `number`, `run`,
    /// `stored_before`, `after_index`, `ratio` (against the first reference) and the
    /// files; the caller gives the rest. On error nothing is recorded.
    pub fn store_reference(
        &mut self,
        mut rec: ReferenceRecord,
        image: &RgbImage,
        dark: &RgbImage,
    ) -> Result<ReferenceRecord, StoreError> {
        let dir = self.dir.clone();
        let ds = Some(dir.as_path());
        if let Some(reason) = &self.poisoned {
            return Err(StoreError::Poisoned {
                path: dir,
                reason: reason.clone(),
            });
        }
        let (w, h) = (self.header.image_width, self.header.image_height);
        for (what, img) in [("reference", image), ("dark frame", dark)] {
            if img.width != w || img.height != h || img.data.len() != w * h * 3 {
                return Err(StoreError::InvalidReference {
                    path: dir.clone(),
                    reason: format!(
                        "its {what} is {}×{} with {} values; the dataset's images are {w}×{h} RGB",
                        img.width,
                        img.height,
                        img.data.len()
                    ),
                });
            }
        }
        if !rec.mean.iter().all(|m| m.is_finite()) {
            return Err(StoreError::InvalidReference {
                path: dir.clone(),
                reason: format!("its mean {:?} is not finite", rec.mean),
            });
        }
        rec.number = self.references.last().map_or(0, |r| r.number + 1);
        rec.run = self.run;
        rec.stored_before = self.records.len();
        rec.after_index = self.records.iter().rev().find(|r| r.image.is_some()).map(|r| r.index);
        let first = self.references.first().map_or(rec.mean, |r| r.mean);
        rec.ratio = std::array::from_fn(|c| if first[c] != 0.0 { rec.mean[c] / first[c] } else { 1.0 });
        let rdir = dir.join(REFERENCE_DIR);
        if !rdir.is_dir() {
            fs::create_dir_all(&rdir).ctx("creating directory", &rdir, ds)?;
            sync_dir(&dir, ds)?;
        }
        let mut written: Vec<PathBuf> = Vec::new();
        let result = (|| -> Result<(), StoreError> {
            for (rel, img, sha) in [
                (reference::reference_rel_path(rec.number), image, &mut rec.image_sha256),
                (reference::dark_rel_path(rec.number), dark, &mut rec.dark_sha256),
            ] {
                let path = dir.join(&rel);
                let bytes = encode_exr(img, &path)?;
                *sha = sha256_hex(&bytes);
                write_atomic(&path, &bytes, ds)?;
                written.push(path);
            }
            Ok(())
        })();
        if let Err(e) = result {
            remove_files(&written);
            return Err(e);
        }
        rec.image = reference::reference_rel_path(rec.number);
        rec.dark = reference::dark_rel_path(rec.number);
        let rpath = dir.join(REFERENCES_FILE);
        let line = match encode_line(&rec) {
            Ok(l) => l,
            Err(source) => {
                remove_files(&written);
                return Err(StoreError::Json { path: rpath, source });
            }
        };
        if self.ref_journal.is_none() {
            let opened = OpenOptions::new()
                .read(true)
                .write(true)
                .create(true)
                .truncate(false)
                .open(&rpath)
                .and_then(|f| {
                    let len = f.metadata()?.len();
                    Appender::new(f, len)
                });
            match opened {
                Ok(a) => {
                    sync_dir(&dir, ds)?;
                    self.ref_journal = Some(a);
                }
                Err(e) => {
                    remove_files(&written);
                    return Err(StoreError::io("opening", &rpath, ds, e));
                }
            }
        }
        let appender = self.ref_journal.as_mut().expect("opened above");
        append_record_line(appender, &line, &rpath, ds, &written, &mut self.poisoned)?;
        self.references.push(rec.clone());
        Ok(rec)
    }

    /// Drift references stored so far (including those found by `resume`), in order.
    pub fn references(&self) -> &[ReferenceRecord] {
        &self.references
    }

    /// Mark the dataset complete: rewrite `manifest.json` atomically with the header,
    /// `"complete": true`, `summary` and every record sorted by index.
    pub fn finish(&mut self, summary: &serde_json::Value) -> Result<(), StoreError> {
        let mut records = self.records.clone();
        records.sort_by_key(|r| r.index);
        write_manifest(
            &self.dir,
            &ManifestFile {
                header: self.header.clone(),
                complete: true,
                journal: Some(JOURNAL_FILE.into()),
                summary: summary.clone(),
                records,
            },
        )?;
        self.manifest_complete = true;
        Ok(())
    }

    /// The dataset directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The dataset's header.
    pub fn header(&self) -> &ManifestHeader {
        &self.header
    }

    /// Records stored so far (including those found by `resume`), in journal order.
    pub fn records(&self) -> &[MeasurementRecord] {
        &self.records
    }

    /// What `resume` repaired (empty for a created dataset).
    pub fn recovery(&self) -> &RecoveryReport {
        &self.recovery
    }

    /// Write the executed plan (`plan.json`, atomically); the bytes are the planner's JSON.
    pub fn write_plan(&self, bytes: &[u8]) -> Result<(), StoreError> {
        atomic::write_atomic(&self.dir.join(PLAN_FILE), bytes, Some(&self.dir))
    }

    /// The stored plan's bytes; `None` when the dataset has none yet (interrupted between
    /// its creation and the plan's write).
    pub fn read_plan(&self) -> Result<Option<Vec<u8>>, StoreError> {
        let path = self.dir.join(PLAN_FILE);
        match fs::read(&path) {
            Ok(b) => Ok(Some(b)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(e) => Err(StoreError::io("reading", &path, Some(&self.dir), e)),
        }
    }

    /// Write the ground truth of measurement `index` (`truth/NNNNN.exr`, atomically);
    /// returns its relative path for the record.
    pub fn store_truth(&self, index: usize, image: &RgbImage) -> Result<String, StoreError> {
        let rel = truth_rel_path(index);
        let path = self.dir.join(&rel);
        fs::create_dir_all(self.dir.join(TRUTH_DIR))
            .map_err(|e| StoreError::io("creating", &path, Some(&self.dir), e))?;
        let bytes = encode_exr(image, &path)?;
        atomic::write_atomic(&path, &bytes, Some(&self.dir))?;
        Ok(rel)
    }

    /// Keep a copy of an applied calibration result (`calibration/KIND.json`).
    pub fn store_calibration_copy(&self, kind: &str, bytes: &[u8]) -> Result<(), StoreError> {
        let dir = self.dir.join(CALIBRATION_DIR);
        let path = self.dir.join(calibration_rel_path(kind));
        fs::create_dir_all(&dir).map_err(|e| StoreError::io("creating", &dir, Some(&self.dir), e))?;
        atomic::write_atomic(&path, bytes, Some(&self.dir))
    }
}

/// True if `dir` holds nothing but what `Dataset::create` writes before its manifest: an
/// empty `journal.jsonl`, empty `images/` and `raw/` directories and the store's temporary
/// files. Such a directory is the debris of a create that was interrupted (no measurement
/// can have been stored: the manifest is written before the first one), so `--force` may
/// replace it even though it has no manifest.
fn is_interrupted_create(dir: &Path) -> bool {
    let Ok(entries) = fs::read_dir(dir) else {
        return false;
    };
    let mut any = false;
    for entry in entries {
        let Ok(entry) = entry else { return false };
        any = true;
        let name = entry.file_name().to_string_lossy().into_owned();
        let Ok(meta) = fs::symlink_metadata(entry.path()) else {
            return false;
        };
        let ok = if name.starts_with(TMP_PREFIX) {
            meta.is_file()
        } else if name == JOURNAL_FILE {
            meta.is_file() && meta.len() == 0
        } else if name == IMAGES_DIR || name == RAW_DIR {
            meta.is_dir() && fs::read_dir(entry.path()).is_ok_and(|mut d| d.next().is_none())
        } else {
            false
        };
        if !ok {
            return false;
        }
    }
    any
}

/// Keep the first record of each index; return the kept records (in order) and the
/// indices that had duplicates.
fn dedupe(lines: Vec<(usize, MeasurementRecord)>) -> (Vec<MeasurementRecord>, Vec<usize>) {
    let mut seen: HashMap<usize, ()> = HashMap::new();
    let mut dups = Vec::new();
    let mut out = Vec::with_capacity(lines.len());
    for (_, r) in lines {
        if seen.insert(r.index, ()).is_some() {
            if !dups.contains(&r.index) {
                dups.push(r.index);
            }
        } else {
            out.push(r);
        }
    }
    (out, dups)
}

/// Check that a record's files are where the store puts them and hash as recorded.
/// Returns the problem, if any. Never follows a path other than the canonical ones,
/// so a damaged record cannot point resume at an unrelated file.
pub(crate) fn check_record_files(dir: &Path, r: &MeasurementRecord) -> Option<String> {
    let skipped = matches!(r.status, MeasurementStatus::Skipped { .. });
    if skipped {
        return None;
    }
    let check = |rel: &Option<String>, sha: &Option<String>, expected_rel: String, what: &str| match (rel, sha) {
        (Some(rel), Some(sha)) if *rel == expected_rel => match fs::read(dir.join(rel)) {
            Ok(bytes) if sha256_hex(&bytes) == *sha => None,
            Ok(_) => Some(format!("{what} {rel} does not match its SHA-256")),
            Err(e) => Some(format!("{what} {rel} cannot be read: {e}")),
        },
        (Some(rel), _) if *rel != expected_rel => Some(format!("{what} path {rel:?} is not {expected_rel:?}")),
        _ => Some(format!("{what} has no path or hash in the journal")),
    };
    if let Some(p) = check(&r.image, &r.image_sha256, image_rel_path(r.index), "image") {
        return Some(p);
    }
    if r.raw.is_some() || r.raw_sha256.is_some() {
        return check(&r.raw, &r.raw_sha256, raw_rel_path(r.index), "raw frame");
    }
    None
}

/// Files in `dir/sub` named like store files (`<digits>.<ext>`) that no record refers
/// to. Other files are left alone.
pub(crate) fn find_orphans(
    dir: &Path,
    sub: &str,
    ext: &str,
    referenced: &HashSet<String>,
) -> Result<Vec<PathBuf>, StoreError> {
    find_orphans_named(dir, sub, ext, &[], referenced)
}

/// [`find_orphans`] for store files whose stem may also end in one of `suffixes`
/// (`<digits><suffix>.<ext>`, as a reference's `-dark` frame).
fn find_orphans_named(
    dir: &Path,
    sub: &str,
    ext: &str,
    suffixes: &[&str],
    referenced: &HashSet<String>,
) -> Result<Vec<PathBuf>, StoreError> {
    let d = dir.join(sub);
    let entries = match fs::read_dir(&d) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(StoreError::io("listing", &d, Some(dir), e)),
    };
    let mut out = Vec::new();
    for entry in entries {
        let entry = entry.ctx("listing", &d, Some(dir))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(stem) = name.strip_suffix(&format!(".{ext}")) else {
            continue;
        };
        let stem = suffixes.iter().find_map(|s| stem.strip_suffix(s)).unwrap_or(stem);
        if name.starts_with(TMP_PREFIX) || stem.is_empty() || !stem.bytes().all(|b| b.is_ascii_digit()) {
            continue;
        }
        if !referenced.contains(&format!("{sub}/{name}")) {
            out.push(entry.path());
        }
    }
    out.sort();
    Ok(out)
}

fn remove_orphans(dir: &Path, sub: &str, ext: &str, referenced: &HashSet<String>) -> Result<Vec<PathBuf>, StoreError> {
    let orphans = find_orphans(dir, sub, ext, referenced)?;
    for p in &orphans {
        tracing::warn!(file = %p.display(), "resume: removing a file that has no journal line");
        fs::remove_file(p).ctx("removing", p, Some(dir))?;
    }
    Ok(orphans)
}

/// Check a reference's files: where the store puts them and hashing as recorded.
pub(crate) fn check_reference_files(dir: &Path, r: &ReferenceRecord) -> Option<String> {
    for (rel, sha, expected, what) in [
        (
            &r.image,
            &r.image_sha256,
            reference::reference_rel_path(r.number),
            "reference image",
        ),
        (
            &r.dark,
            &r.dark_sha256,
            reference::dark_rel_path(r.number),
            "dark frame",
        ),
    ] {
        if *rel != expected {
            return Some(format!("{what} path {rel:?} is not {expected:?}"));
        }
        match fs::read(dir.join(rel)) {
            Ok(bytes) if sha256_hex(&bytes) == *sha => {}
            Ok(_) => return Some(format!("{what} {rel} does not match its SHA-256")),
            Err(e) => return Some(format!("{what} {rel} cannot be read: {e}")),
        }
    }
    None
}

/// Files in `reference/` named like reference files (`<digits>.exr`, `<digits>-dark.exr`)
/// that no record refers to.
pub(crate) fn find_reference_orphans(dir: &Path, records: &[ReferenceRecord]) -> Result<Vec<PathBuf>, StoreError> {
    let referenced: HashSet<String> = records.iter().flat_map(|r| [r.image.clone(), r.dark.clone()]).collect();
    find_orphans_named(dir, REFERENCE_DIR, "exr", &["-dark"], &referenced)
}

/// `resume`'s repair of the drift references: cut a torn last line, drop references
/// whose files are missing or damaged (rewriting the file without them), remove image
/// files without a line. Returns the kept references and the open file to append to.
fn resume_references(
    dir: &Path,
    report: &mut RecoveryReport,
) -> Result<(Vec<ReferenceRecord>, Option<Appender>), StoreError> {
    let rpath = dir.join(REFERENCES_FILE);
    let scan: journal::Scan<ReferenceRecord> = match fs::read(&rpath) {
        Ok(bytes) => journal::scan_bytes(&bytes, &rpath)?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => journal::Scan::default(),
        Err(e) => return Err(StoreError::io("reading", &rpath, Some(dir), e)),
    };
    if let Some(t) = &scan.torn {
        tracing::warn!(file = %rpath.display(), line = t.line, reason = %t.reason,
            "resume: the last reference line is torn (crash while appending); removing it");
        report
            .references_dropped
            .push((scan.records.len(), format!("torn line {}: {}", t.line, t.reason)));
    }
    let mut kept: Vec<ReferenceRecord> = Vec::new();
    let mut changed = scan.torn.is_some() || scan.missing_newline;
    for (_, r) in scan.records {
        let expected = kept.last().map_or(0, |k| k.number + 1);
        let problem = if r.number != expected {
            Some(format!("its number {} is not the next one ({expected})", r.number))
        } else {
            check_reference_files(dir, &r)
        };
        match problem {
            None => kept.push(r),
            Some(p) => {
                tracing::warn!(reference = r.number, problem = %p, "resume: dropping the drift reference");
                report.references_dropped.push((r.number, p));
                changed = true;
            }
        }
    }
    let orphans = find_reference_orphans(dir, &kept)?;
    for p in &orphans {
        tracing::warn!(file = %p.display(), "resume: removing a reference file that has no line");
        fs::remove_file(p).ctx("removing", p, Some(dir))?;
    }
    report.orphans_removed.extend(orphans);
    if !rpath.exists() {
        return Ok((kept, None));
    }
    let mut len = fs::metadata(&rpath).ctx("reading", &rpath, Some(dir))?.len();
    if changed {
        len = rewrite_lines(&rpath, &kept, dir)?;
    }
    let file = OpenOptions::new()
        .read(true)
        .write(true)
        .open(&rpath)
        .ctx("opening", &rpath, Some(dir))?;
    let appender = Appender::new(file, len).ctx("opening", &rpath, Some(dir))?;
    Ok((kept, Some(appender)))
}

/// The drift references of the dataset at `dir` (read-only; a torn last line is ignored
/// with a warning, as [`load`] does for the journal). Empty without `references.jsonl`.
pub fn load_references(dir: &Path) -> Result<Vec<ReferenceRecord>, StoreError> {
    let rpath = dir.join(REFERENCES_FILE);
    let bytes = match fs::read(&rpath) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(StoreError::io("reading", &rpath, Some(dir), e)),
    };
    let scan: journal::Scan<ReferenceRecord> = journal::scan_bytes(&bytes, &rpath)?;
    if let Some(t) = &scan.torn {
        tracing::warn!(file = %rpath.display(), line = t.line, reason = %t.reason,
            "ignoring the torn last reference line");
    }
    Ok(scan.records.into_iter().map(|(_, r)| r).collect())
}

/// Encode a raw frame as a 16-bit RGB PNG (values unscaled).
fn encode_raw_png(frame: &Frame, path: &Path) -> Result<Vec<u8>, StoreError> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::ImageEncoder;
    let mut bytes = Vec::with_capacity(frame.data.len() * 2);
    for v in &frame.data {
        bytes.extend_from_slice(&v.to_ne_bytes());
    }
    let mut out = Vec::new();
    PngEncoder::new_with_quality(&mut out, CompressionType::Fast, FilterType::Adaptive)
        .write_image(
            &bytes,
            frame.width as u32,
            frame.height as u32,
            image::ExtendedColorType::Rgb16,
        )
        .map_err(|source| StoreError::Codec {
            path: path.to_path_buf(),
            source,
        })?;
    Ok(out)
}

/// The header of the dataset at `dir` and whether it is complete (`Dataset::finish` ran),
/// without reading its journal.
pub fn read_header(dir: &Path) -> Result<(ManifestHeader, bool), StoreError> {
    let m = read_manifest(dir)?;
    Ok((m.header, m.complete))
}

/// Read a dataset for export or inspection: the header and every record of the journal
/// (the source of truth), first occurrence of each index, sorted by index. A torn last
/// journal line (an acquisition that crashed or is still running) is ignored with a
/// warning; the dataset is not modified.
pub fn load(dir: &Path) -> Result<(ManifestHeader, Vec<MeasurementRecord>), StoreError> {
    let manifest = read_manifest(dir)?;
    let jpath = dir.join(JOURNAL_FILE);
    let scan = journal::scan(&jpath, dir)?;
    if let Some(t) = &scan.torn {
        tracing::warn!(journal = %jpath.display(), line = t.line, reason = %t.reason,
            "ignoring the torn last journal line");
    }
    let (mut records, dups) = dedupe(scan.records);
    for i in dups {
        tracing::warn!(index = i, "index stored twice in the journal; using the first");
    }
    records.sort_by_key(|r| r.index);
    Ok((manifest.header, records))
}
