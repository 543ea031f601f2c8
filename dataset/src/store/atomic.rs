//! Crash-safe file replacement and directory locking.
//!
//! The store never leaves a half-written file under its final name: every file is
//! written under a temporary name (`.tmp-…` in the same directory, so the rename stays
//! on one file system), fsynced, renamed into place, and the directory is fsynced so
//! the rename itself survives a power cut. Temporary names all start with
//! [`TMP_PREFIX`]; `Dataset::resume` deletes any it finds, which is safe because the
//! dataset lock guarantees no other writer is active.

use super::error::{IoContext, StoreError};
use std::fs::{self, File, OpenOptions};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

/// Prefix of every temporary file the store creates.
pub const TMP_PREFIX: &str = ".tmp-";

/// Temporary sibling of `path`: same directory, name prefixed with [`TMP_PREFIX`] and
/// tagged with the process id so two processes exporting to the same directory do not
/// clobber each other's temporaries.
pub fn tmp_path_for(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = format!("{TMP_PREFIX}{}-{name}", std::process::id());
    match path.parent() {
        Some(p) => p.join(tmp),
        None => PathBuf::from(tmp),
    }
}

/// A temporary file that is deleted when dropped unless [`TempFile::commit`] renamed
/// it into place: an error anywhere between creation and rename cleans up after
/// itself.
pub struct TempFile {
    tmp: PathBuf,
    dest: PathBuf,
    file: Option<File>,
    dataset: Option<PathBuf>,
}

impl TempFile {
    /// Create the temporary sibling of `dest` (truncating a stale one).
    pub fn create(dest: &Path, dataset: Option<&Path>) -> Result<TempFile, StoreError> {
        let tmp = tmp_path_for(dest);
        let file = OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .open(&tmp)
            .ctx("creating", &tmp, dataset)?;
        Ok(TempFile {
            tmp,
            dest: dest.to_path_buf(),
            file: Some(file),
            dataset: dataset.map(Path::to_path_buf),
        })
    }

    /// The open temporary file.
    pub fn file(&mut self) -> &mut File {
        self.file.as_mut().expect("TempFile used after commit")
    }

    /// Path of the temporary file (for error messages).
    pub fn tmp_path(&self) -> &Path {
        &self.tmp
    }

    /// fsync the data, rename it to its final name and fsync the directory.
    pub fn commit(mut self) -> Result<(), StoreError> {
        let dataset = self.dataset.clone();
        let ds = dataset.as_deref();
        let file = self.file.take().expect("TempFile committed twice");
        file.sync_all().ctx("syncing", &self.tmp, ds)?;
        drop(file);
        fs::rename(&self.tmp, &self.dest).ctx("renaming into place", &self.dest, ds)?;
        // The rename happened: from now on the temporary name no longer exists.
        self.tmp = PathBuf::new();
        sync_parent(&self.dest, ds)
    }
}

impl Drop for TempFile {
    fn drop(&mut self) {
        if !self.tmp.as_os_str().is_empty() {
            self.file.take();
            let _ = fs::remove_file(&self.tmp);
        }
    }
}

/// Write `bytes` to `dest` atomically (temp file, fsync, rename, fsync directory).
pub fn write_atomic(dest: &Path, bytes: &[u8], dataset: Option<&Path>) -> Result<(), StoreError> {
    let mut t = TempFile::create(dest, dataset)?;
    let tmp = t.tmp_path().to_path_buf();
    t.file().write_all(bytes).ctx("writing", &tmp, dataset)?;
    t.commit()
}

/// fsync a directory so that entries created, renamed or removed in it are durable.
pub fn sync_dir(dir: &Path, dataset: Option<&Path>) -> Result<(), StoreError> {
    match File::open(dir).and_then(|d| d.sync_all()) {
        Ok(()) => Ok(()),
        // Some file systems refuse fsync on a directory; the rename is still atomic.
        Err(e) if e.kind() == io::ErrorKind::InvalidInput => Ok(()),
        Err(e) => Err(StoreError::io("syncing directory", dir, dataset, e)),
    }
}

/// fsync the directory holding `path`.
pub fn sync_parent(path: &Path, dataset: Option<&Path>) -> Result<(), StoreError> {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => sync_dir(p, dataset),
        _ => sync_dir(Path::new("."), dataset),
    }
}

/// Remove every file whose name starts with [`TMP_PREFIX`] in `dir` (not recursive);
/// returns the removed paths. A missing directory has none.
pub fn remove_temp_files(dir: &Path, dataset: Option<&Path>) -> Result<Vec<PathBuf>, StoreError> {
    let mut removed = Vec::new();
    let entries = match fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(removed),
        Err(e) => return Err(StoreError::io("listing", dir, dataset, e)),
    };
    for entry in entries {
        let entry = entry.ctx("listing", dir, dataset)?;
        if entry.file_name().to_string_lossy().starts_with(TMP_PREFIX) {
            let p = entry.path();
            fs::remove_file(&p).ctx("removing temporary file", &p, dataset)?;
            removed.push(p);
        }
    }
    if !removed.is_empty() {
        sync_dir(dir, dataset)?;
    }
    Ok(removed)
}

/// An exclusive advisory lock on a dataset directory, held for the lifetime of the
/// value. It keeps two acquisitions (or an acquisition and `create --force`) from
/// writing the same dataset; the kernel drops it when the process dies, so a crash
/// never leaves a stale lock behind.
pub struct DirLock {
    _dir: File,
}

impl DirLock {
    /// Try to take the lock without waiting.
    pub fn acquire(dir: &Path) -> Result<DirLock, StoreError> {
        let f = File::open(dir).ctx("opening directory", dir, Some(dir))?;
        #[cfg(unix)]
        {
            use std::os::unix::io::AsRawFd;
            // SAFETY: flock on a file descriptor we own; no memory is passed.
            let r = unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
            if r != 0 {
                let e = io::Error::last_os_error();
                if e.kind() == io::ErrorKind::WouldBlock {
                    return Err(StoreError::Locked {
                        path: dir.to_path_buf(),
                    });
                }
                return Err(StoreError::io("locking", dir, Some(dir), e));
            }
        }
        Ok(DirLock { _dir: f })
    }
}
