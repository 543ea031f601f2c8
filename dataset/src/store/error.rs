//! The store's error type.
//!
//! Every variant names the file or directory concerned and says what the operator can
//! do about it: these messages end up on the terminal of someone whose overnight
//! acquisition just stopped, so "what now" matters more than the errno.

use std::io;
use std::path::{Path, PathBuf};

/// Errors of the dataset store and its exporters.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The file system is full (ENOSPC). Nothing half-written was recorded: the journal
    /// only ever holds measurements whose files were completely written and fsynced.
    #[error("{}", disk_full_message(path, dataset.as_deref()))]
    DiskFull {
        path: PathBuf,
        /// The dataset directory, when the failing write belonged to a dataset (so the
        /// message can name the resume command); `None` for exports.
        dataset: Option<PathBuf>,
        #[source]
        source: io::Error,
    },

    /// Permission denied or a read-only file system.
    #[error(
        "permission denied while {op} {}: {source} (read-only file system or missing \
         permission); choose a writable directory or fix the permissions, then run the \
         command again",
        path.display()
    )]
    ReadOnly {
        op: &'static str,
        path: PathBuf,
        #[source]
        source: io::Error,
    },

    /// Any other I/O failure.
    #[error("I/O error while {op} {}: {source}", path.display())]
    Io {
        op: &'static str,
        path: PathBuf,
        #[source]
        source: io::Error,
    },

    /// `Dataset::create` on an existing non-empty directory without `force`.
    #[error(
        "{} exists and is not empty: choose another directory, continue it with \
         `gonio acquire --resume {}`, or pass --force to replace the dataset in it",
        path.display(),
        path.display()
    )]
    NotEmpty { path: PathBuf },

    /// The directory is not (or no longer) a gonio dataset.
    #[error(
        "{} is not a gonio dataset ({reason}); {hint}",
        path.display()
    )]
    NotADataset {
        path: PathBuf,
        reason: String,
        hint: &'static str,
    },

    /// The manifest exists but cannot be used.
    #[error("manifest {} is invalid: {reason}; restore it from a backup (the journal \
             journal.jsonl beside it still lists every stored measurement)", path.display())]
    BadManifest { path: PathBuf, reason: String },

    /// The dataset was written by a newer gonio.
    #[error(
        "{} has dataset format version {found}, this gonio reads up to {supported}: \
         use a newer gonio",
        path.display()
    )]
    UnsupportedVersion { path: PathBuf, found: u32, supported: u32 },

    /// A journal line other than the last one is damaged. A crash can only tear the
    /// last line (every line is fsynced before the next is written), so this is real
    /// corruption (disk fault, manual edit) and is not repaired silently.
    #[error(
        "journal {} is corrupt at line {line}: {reason}. Only a damaged last line can come \
         from a crash; inspect the file, delete line {line} by hand if its measurement \
         may be re-measured, then run `gonio acquire --resume` again",
        path.display()
    )]
    CorruptJournal { path: PathBuf, line: usize, reason: String },

    /// Another process (or another `Dataset` in this process) holds the dataset.
    #[error(
        "{} is in use by another gonio process (its lock is held); wait for it to end \
         or stop it first",
        path.display()
    )]
    Locked { path: PathBuf },

    /// `Dataset::store` was given an index that is already stored.
    #[error(
        "measurement index {index} is already stored in {}: each canonical index is \
         stored once (an engine bug; the dataset is unchanged)",
        path.display()
    )]
    DuplicateIndex { path: PathBuf, index: usize },

    /// The record or image handed to `Dataset::store` is inconsistent.
    #[error("cannot store measurement {index} in {}: {reason} (the dataset is unchanged)", path.display())]
    InvalidMeasurement {
        path: PathBuf,
        index: usize,
        reason: String,
    },

    /// The images or values handed to `Dataset::store_reference` are inconsistent.
    #[error("cannot store a drift reference in {}: {reason} (the dataset is unchanged)", path.display())]
    InvalidReference { path: PathBuf, reason: String },

    /// The header handed to `Dataset::create` is inconsistent.
    #[error("invalid manifest header for {}: {reason}", path.display())]
    InvalidHeader { path: PathBuf, reason: String },

    /// An earlier journal append failed and could not be rolled back; writing on
    /// could bury a torn line in the middle of the journal.
    #[error(
        "dataset {} stopped accepting measurements after an earlier write failure \
         ({reason}); run `gonio acquire --resume {}` to repair and continue",
        path.display(),
        path.display()
    )]
    Poisoned { path: PathBuf, reason: String },

    /// A stored image file is missing or does not match the hash its record holds.
    #[error(
        "image {} of measurement {index} is {problem}: run `gonio verify` on the dataset, \
         then `gonio acquire --resume` to re-measure it",
        path.display()
    )]
    DamagedImage {
        path: PathBuf,
        index: usize,
        problem: String,
    },

    /// Two exported measurements would get the same integer angle tuple, which the
    /// UBO2003 reader refuses (it keys images by the four integer angles).
    #[error(
        "cannot export {}: measurements {first} and {second} both round to the angles \
         {name:?}; the UBO2003 format cannot hold both (use the native dataset instead)",
        path.display()
    )]
    ExportConflict {
        path: PathBuf,
        first: usize,
        second: usize,
        name: String,
    },

    /// OpenEXR encoding or decoding failed.
    #[error("OpenEXR error for {}: {source}", path.display())]
    Exr {
        path: PathBuf,
        #[source]
        source: exr::error::Error,
    },

    /// PNG or JPEG encoding or decoding failed.
    #[error("image codec error for {}: {source}", path.display())]
    Codec {
        path: PathBuf,
        #[source]
        source: image::ImageError,
    },

    /// Writing the ZIP archive failed.
    #[error("ZIP error for {}: {source}", path.display())]
    Zip {
        path: PathBuf,
        #[source]
        source: zip::result::ZipError,
    },

    /// A Zarr export cannot be written (zarrs refused the array or a chunk).
    #[error("Zarr export to {}: {reason}", path.display())]
    Zarr { path: PathBuf, reason: String },

    /// The Zarr output path holds something other than this dataset's export.
    #[error(
        "{} already exists and {reason}: choose another output path, or pass --force to \
         replace it (a sharded export (--shard) never replaces: remove it first)",
        path.display()
    )]
    ZarrOutputExists { path: PathBuf, reason: String },

    /// JSON (de)serialisation failed.
    #[error("JSON error for {}: {source}", path.display())]
    Json {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
}

fn disk_full_message(path: &Path, dataset: Option<&Path>) -> String {
    match dataset {
        Some(d) => format!(
            "disk full while writing {}: the dataset's journal is consistent (this \
             measurement was not recorded and will be re-measured); free space, then run \
             `gonio acquire --resume {}`",
            path.display(),
            d.display()
        ),
        None => format!(
            "disk full while writing {}: nothing was left under the final name and the \
             dataset itself is unchanged; free space and run the command again",
            path.display()
        ),
    }
}

/// errno values that `io::ErrorKind` does not map on every supported toolchain.
const ENOSPC: i32 = 28;
const EDQUOT: i32 = 122;
const EROFS: i32 = 30;

/// True for "no space left" (ENOSPC) and "quota exceeded" (EDQUOT): both mean the
/// operator has to free space before the acquisition can go on.
pub fn is_disk_full(e: &io::Error) -> bool {
    e.kind() == io::ErrorKind::StorageFull
        || e.kind() == io::ErrorKind::QuotaExceeded
        || matches!(e.raw_os_error(), Some(ENOSPC) | Some(EDQUOT))
}

fn is_read_only(e: &io::Error) -> bool {
    e.kind() == io::ErrorKind::PermissionDenied
        || e.kind() == io::ErrorKind::ReadOnlyFilesystem
        || e.raw_os_error() == Some(EROFS)
}

impl StoreError {
    /// Classify an I/O error raised while writing or reading `path` inside the dataset
    /// `dataset` (`None` outside a dataset, e.g. an export's output).
    pub fn io(op: &'static str, path: &Path, dataset: Option<&Path>, source: io::Error) -> Self {
        if is_disk_full(&source) {
            StoreError::DiskFull {
                path: path.to_path_buf(),
                dataset: dataset.map(Path::to_path_buf),
                source,
            }
        } else if is_read_only(&source) {
            StoreError::ReadOnly {
                op,
                path: path.to_path_buf(),
                source,
            }
        } else {
            StoreError::Io {
                op,
                path: path.to_path_buf(),
                source,
            }
        }
    }

    /// True if the error means the disk is full.
    pub fn is_disk_full(&self) -> bool {
        matches!(self, StoreError::DiskFull { .. })
    }
}

/// Shorthand used throughout the store: attach the operation, path and dataset to an
/// `io::Result`.
pub(crate) trait IoContext<T> {
    fn ctx(self, op: &'static str, path: &Path, dataset: Option<&Path>) -> Result<T, StoreError>;
}

impl<T> IoContext<T> for io::Result<T> {
    fn ctx(self, op: &'static str, path: &Path, dataset: Option<&Path>) -> Result<T, StoreError> {
        self.map_err(|e| StoreError::io(op, path, dataset, e))
    }
}
