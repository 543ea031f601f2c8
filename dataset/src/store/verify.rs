//! `verify`: check a dataset without modifying it.
//!
//! Re-hashes every image and raw frame against its journal record, and reports what
//! `resume` would repair (torn last line, orphans, temporary files, duplicates) and
//! whether a finished manifest still matches the journal.

use super::atomic::TMP_PREFIX;
use super::error::StoreError;
use super::manifest::{read_manifest, MeasurementStatus};
use super::reference::{ReferenceRecord, REFERENCES_FILE, REFERENCE_DIR};
use super::{
    check_record_files, check_reference_files, dedupe, find_orphans, find_reference_orphans, journal, IMAGES_DIR,
    JOURNAL_FILE, RAW_DIR,
};
use rayon::prelude::*;
use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// Result of [`verify`].
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct VerifyReport {
    pub dir: PathBuf,
    /// The manifest says the acquisition finished.
    pub complete: bool,
    /// Records in the journal (first occurrence of each index).
    pub records: usize,
    pub measured: usize,
    pub substituted: usize,
    pub skipped: usize,
    /// Pairs predicted by `gonio complete` (stored images, not measurements).
    pub predicted: usize,
    /// Images and raw frames whose SHA-256 matched.
    pub images_ok: usize,
    pub raw_ok: usize,
    /// Bytes read and hashed.
    pub bytes_hashed: u64,
    /// Records whose files are missing or damaged: "index: problem".
    pub damaged: Vec<String>,
    /// Store-named files without a journal line.
    pub orphans: Vec<PathBuf>,
    /// Leftover temporary files.
    pub temp_files: Vec<PathBuf>,
    /// Indices appearing more than once in the journal.
    pub duplicates: Vec<usize>,
    /// The journal's last line is torn: (line, reason).
    pub torn_line: Option<(usize, String)>,
    /// The manifest says complete but its records differ from the journal's.
    pub manifest_stale: bool,
    /// Drift references in `references.jsonl` (`--reference-every`) whose two images
    /// matched their SHA-256.
    #[serde(skip_serializing_if = "is_zero")]
    pub references_ok: usize,
    /// The last line of `references.jsonl` is torn: (line, reason).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub references_torn_line: Option<(usize, String)>,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

impl VerifyReport {
    /// Every recorded measurement has intact files and a finished manifest (if any)
    /// agrees with the journal. Debris that `resume` cleans up (orphans, temporary
    /// files, a torn last line) does not make a dataset wrong.
    pub fn is_ok(&self) -> bool {
        self.damaged.is_empty() && !self.manifest_stale && self.duplicates.is_empty()
    }

    /// [`is_ok`](Self::is_ok) and no debris at all.
    pub fn is_clean(&self) -> bool {
        self.is_ok()
            && self.orphans.is_empty()
            && self.temp_files.is_empty()
            && self.torn_line.is_none()
            && self.references_torn_line.is_none()
    }
}

impl std::fmt::Display for VerifyReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}: {} records ({} measured, {} substituted, {} skipped), {}; \
             {} images and {} raw frames verified ({:.1} MB hashed)",
            self.dir.display(),
            self.records,
            self.measured,
            self.substituted,
            self.skipped,
            if self.complete { "complete" } else { "incomplete" },
            self.images_ok,
            self.raw_ok,
            self.bytes_hashed as f64 / 1e6
        )?;
        if self.references_ok > 0 {
            write!(f, "; {} drift references verified", self.references_ok)?;
        }
        for d in &self.damaged {
            write!(f, "\n  damaged: {d}")?;
        }
        if !self.duplicates.is_empty() {
            write!(f, "\n  duplicate indices: {:?}", self.duplicates)?;
        }
        if self.manifest_stale {
            write!(
                f,
                "\n  manifest.json says complete but its records differ from the journal"
            )?;
        }
        if let Some((line, reason)) = &self.torn_line {
            write!(f, "\n  torn last journal line {line}: {reason}")?;
        }
        if let Some((line, reason)) = &self.references_torn_line {
            write!(f, "\n  torn last line {line} of {REFERENCES_FILE}: {reason}")?;
        }
        for p in &self.orphans {
            write!(f, "\n  orphan (no journal line): {}", p.display())?;
        }
        for p in &self.temp_files {
            write!(f, "\n  leftover temporary file: {}", p.display())?;
        }
        Ok(())
    }
}

/// Verify a dataset (read-only). Errors only when the dataset cannot be read at all
/// (no manifest, corrupt journal line before the last); everything else is reported.
pub fn verify(dir: &Path) -> Result<VerifyReport, StoreError> {
    let manifest = read_manifest(dir)?;
    let scan = journal::scan(&dir.join(JOURNAL_FILE), dir)?;
    let mut rep = VerifyReport {
        dir: dir.to_path_buf(),
        complete: manifest.complete,
        torn_line: scan.torn.as_ref().map(|t| (t.line, t.reason.clone())),
        ..Default::default()
    };
    let (records, dups) = dedupe(scan.records);
    rep.duplicates = dups;
    rep.records = records.len();
    for r in &records {
        match r.status {
            MeasurementStatus::Measured => rep.measured += 1,
            MeasurementStatus::Substituted { .. } => rep.substituted += 1,
            MeasurementStatus::Skipped { .. } => rep.skipped += 1,
            MeasurementStatus::Predicted { .. } => rep.predicted += 1,
        }
    }
    let checks: Vec<(Option<String>, u64)> = records
        .par_iter()
        .map(|r| {
            let problem = check_record_files(dir, r);
            let size = |rel: &Option<String>| {
                rel.as_ref()
                    .and_then(|p| std::fs::metadata(dir.join(p)).ok())
                    .map_or(0, |m| m.len())
            };
            let bytes = if problem.is_none() {
                size(&r.image) + size(&r.raw)
            } else {
                0
            };
            (problem, bytes)
        })
        .collect();
    for (r, (problem, bytes)) in records.iter().zip(checks) {
        rep.bytes_hashed += bytes;
        match problem {
            Some(p) => rep.damaged.push(format!("{}: {p}", r.index)),
            None if r.image.is_some() => {
                rep.images_ok += 1;
                if r.raw.is_some() {
                    rep.raw_ok += 1;
                }
            }
            None => {}
        }
    }
    let referenced: HashSet<String> = records
        .iter()
        .flat_map(|r| [r.image.clone(), r.raw.clone()])
        .flatten()
        .collect();
    rep.orphans.extend(find_orphans(dir, IMAGES_DIR, "exr", &referenced)?);
    rep.orphans.extend(find_orphans(dir, RAW_DIR, "png", &referenced)?);
    // Drift references: every line's two images, and their orphans.
    let rpath = dir.join(REFERENCES_FILE);
    let refs: Vec<ReferenceRecord> = match std::fs::read(&rpath) {
        Ok(bytes) => {
            let scan: journal::Scan<ReferenceRecord> = journal::scan_bytes(&bytes, &rpath)?;
            rep.references_torn_line = scan.torn.as_ref().map(|t| (t.line, t.reason.clone()));
            scan.records.into_iter().map(|(_, r)| r).collect()
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
        Err(e) => return Err(StoreError::io("reading", &rpath, Some(dir), e)),
    };
    for r in &refs {
        match check_reference_files(dir, r) {
            Some(p) => rep.damaged.push(format!("reference {}: {p}", r.number)),
            None => rep.references_ok += 1,
        }
    }
    rep.orphans.extend(find_reference_orphans(dir, &refs)?);
    for sub in [
        dir.to_path_buf(),
        dir.join(IMAGES_DIR),
        dir.join(RAW_DIR),
        dir.join(REFERENCE_DIR),
    ] {
        if let Ok(entries) = std::fs::read_dir(&sub) {
            for e in entries.flatten() {
                if e.file_name().to_string_lossy().starts_with(TMP_PREFIX) {
                    rep.temp_files.push(e.path());
                }
            }
        }
    }
    rep.temp_files.sort();
    if manifest.complete {
        // Compare identities and file hashes, not floats: JSON float parsing is not
        // guaranteed to round-trip bit-exactly.
        let key =
            |r: &super::MeasurementRecord| (r.index, r.status.kind(), r.image_sha256.clone(), r.raw_sha256.clone());
        let mut journal_keys: Vec<_> = records.iter().map(key).collect();
        let mut manifest_keys: Vec<_> = manifest.records.iter().map(key).collect();
        journal_keys.sort();
        manifest_keys.sort();
        rep.manifest_stale = journal_keys != manifest_keys;
    }
    Ok(rep)
}
