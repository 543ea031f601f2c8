//! Drift references: a reference pair and a dark frame re-measured during a run
//! (`gonio acquire --reference-every MINUTES`), so optical drift (lamp output, camera gain)
//! is tracked and can be corrected afterwards (`gonio dataset drift`).
//!
//! # Files
//!
//! ```text
//! DIR/
//!   references.jsonl          append-only, one CRC'd line per reference (journal.rs's format)
//!   reference/NNNNN.exr       the reference pair, developed like a measurement
//!   reference/NNNNN-dark.exr  the dark frame: same pose and exposure, light off
//! ```
//!
//! `NNNNN` is the reference's `number` (0, 1, … over the whole dataset, resumed runs
//! included). A separate file, not a new record kind in `journal.jsonl`, because every
//! reader of the journal (resume's one-record-per-index rule, the exporters, `verify`'s
//! counts, `gonio merge`, older gonio versions) takes each journal line for a measurement
//! of the plan: a reference line there would have to be filtered out by every one of them,
//! and an older gonio would refuse the dataset as corrupt. Beside it, nothing that reads
//! measurements changes, and a dataset without references has no such file.
//!
//! # Durability
//!
//! The same discipline as a measurement: both images are written under temporary names,
//! fsynced and renamed into place, then the line is appended and fsynced. A reference
//! counts only once its line is there. A kill -9 in between leaves files without a line:
//! `Dataset::resume` removes them as orphans, and the resumed run takes its own reference
//! before its first measurement (every run starts with one), so the lost reference is
//! replaced, never recorded twice.

use serde::{Deserialize, Serialize};

/// The file of reference records.
pub const REFERENCES_FILE: &str = "references.jsonl";
/// The directory of reference and dark images.
pub const REFERENCE_DIR: &str = "reference";

/// Relative path of reference `number`'s image.
pub fn reference_rel_path(number: usize) -> String {
    format!("{REFERENCE_DIR}/{number:05}.exr")
}

/// Relative path of reference `number`'s dark frame.
pub fn dark_rel_path(number: usize) -> String {
    format!("{REFERENCE_DIR}/{number:05}-dark.exr")
}

/// One re-measurement of the reference pair and a dark frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReferenceRecord {
    /// 0, 1, … in the order taken (names the files).
    pub number: usize,
    /// Which run (process) of the acquisition took it: 0 for the first, +1 per
    /// `--resume`. Rig times compare only within one run (a resumed rig's clock restarts).
    pub run: usize,
    /// Rig-clock time of the reference exposure (s; virtual on a simulated rig).
    pub rig_time_s: f64,
    /// Rig-clock seconds the reference took: the move, both exposures and the light's
    /// settle time after switching it off and on again.
    pub duration_s: f64,
    /// Records in `journal.jsonl` when it was taken: it sits between the journal's line
    /// `stored_before` and the next one.
    pub stored_before: usize,
    /// Index of the last measurement stored before it (`None`: none yet).
    pub after_index: Option<usize>,
    /// Canonical index of the reference pair, and its directions (degrees).
    pub pair_index: usize,
    pub light_deg: [f64; 2],
    pub view_deg: [f64; 2],
    pub exposure_s: f64,
    pub gain: f64,
    /// Per-channel mean of the dark-subtracted reference over the sample region (the
    /// rectified image), in the dataset's value unit.
    pub mean: [f64; 3],
    /// `mean` over the first reference's `mean`, per channel (1 for the first).
    pub ratio: [f64; 3],
    pub image: String,
    pub image_sha256: String,
    pub dark: String,
    pub dark_sha256: String,
}

impl ReferenceRecord {
    /// The largest relative change of any channel against the first reference.
    pub fn drift(&self) -> f64 {
        self.ratio.iter().map(|r| (r - 1.0).abs()).fold(0.0, f64::max)
    }
}
