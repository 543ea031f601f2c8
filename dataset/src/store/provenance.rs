//! How an output names its inputs, so that the same command on the same input bytes writes
//! the same output bytes wherever the files sit ("same bytes anywhere").
//!
//! An output that records an input (a compressed `.gbtf` its dataset, a synthesized file
//! its exemplar, a completed dataset the sparse one it completed, a fit its dataset) stores
//! two things beside each other:
//!
//! * **the path, relative to the output's directory**: for an output file the directory
//!   that holds it, for an output dataset the dataset directory itself (where its
//!   `manifest.json` is). Separators are `/` on every platform; `..` segments are allowed;
//!   an input in the output's directory itself is `.`. Both paths are made absolute and
//!   symbolic links resolved (as far as the paths exist) before the relative path is taken,
//!   so `a/../b` and a link to `b` name the same input. Readers resolve the stored path
//!   against the output's directory ([`resolve`]).
//! * **the input's SHA-256** (lower-case hex) — see [`input_sha256`]:
//!   - of an input **file**: the SHA-256 of its bytes;
//!   - of an input **dataset** (a directory): the SHA-256 of its *listing*, the text with one
//!     line `<sha256>  <path>\n` (the `sha256sum` format) per stored file the dataset's
//!     records name, in index order: each record's image (`image_sha256`, `image`), then its
//!     raw frame if any (`raw_sha256`, `raw`); a file recorded without a hash is listed with
//!     `-`. The hashes are the ones the journal records (`gonio verify` checks the files
//!     against them), so the images are pinned without being read again, and the
//!     manifest's wall-clock fields (`created_unix`, …) do not enter: two datasets with the
//!     same images have the same SHA-256. Files no record names (`plan.json`,
//!     `calibration/`, `truth/`) and the manifest's header are not covered.
//!
//! **When no relative path exists** (on Windows, input and output on different drives or
//! UNC shares; on Unix one always exists), the path is stored absolute, as the command saw
//! it made absolute. The output's bytes then depend on where the input was; the SHA-256
//! still identifies the input, and [`resolve`] reads an absolute path as it is.

use super::{load, StoreError, MANIFEST_FILE};
use sha2::{Digest, Sha256};
use std::io::Read;
use std::path::{Component, Path, PathBuf};

/// Why an input's SHA-256 could not be recorded.
#[derive(Debug, thiserror::Error)]
pub enum ProvenanceError {
    #[error(
        "{}: could not read it to record its SHA-256 in the output ({source}); check that the input \
         exists and is readable",
        path.display()
    )]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{} is a directory without {MANIFEST_FILE}, so it is not a gonio dataset and has no SHA-256 to \
         record; give a dataset directory (one `gonio acquire` or `gonio sim btf` wrote) or a file",
        path.display()
    )]
    NotADataset { path: PathBuf },
    #[error("{}: could not read its records to record its SHA-256 in the output: {source}", path.display())]
    Dataset {
        path: PathBuf,
        #[source]
        source: Box<StoreError>,
    },
}

/// An input as an output records it: its path relative to the output's directory and its
/// SHA-256 (see the module documentation).
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct InputRef {
    pub path: String,
    pub sha256: String,
}

impl InputRef {
    /// `input` as seen from `out_dir` (the output's directory, see [`output_dir`]).
    pub fn new(input: &Path, out_dir: &Path) -> Result<InputRef, ProvenanceError> {
        Ok(InputRef {
            path: relative_path(out_dir, input),
            sha256: input_sha256(input)?,
        })
    }
}

/// The directory an output file's recorded paths are relative to: the directory that holds
/// it (`.` for a bare file name). For an output dataset, use the dataset directory itself.
pub fn output_dir(out_file: &Path) -> PathBuf {
    match out_file.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// `p` absolute, without `.` and `..`, with the links of its existing prefix resolved: how
/// the parts of a sharded job name an input until their merge knows the output's directory
/// (the merge then stores it relative, as one process would).
pub fn absolute(p: &Path) -> PathBuf {
    absolute_clean(p)
}

/// Set `obj[key]` to `path` and `obj["{key}_sha256"]` to `sha256` right after it; other keys
/// keep their order (a non-object `obj` becomes an object).
pub fn record(obj: &mut serde_json::Value, key: &str, path: String, sha256: String) {
    let old = match obj.take() {
        serde_json::Value::Object(m) => m,
        _ => serde_json::Map::new(),
    };
    let sha_key = format!("{key}_sha256");
    let mut m = serde_json::Map::new();
    let mut pending = Some((path, sha256));
    for (k, v) in old {
        if k == sha_key {
            continue;
        }
        if k == key {
            if let Some((p, s)) = pending.take() {
                m.insert(k, serde_json::Value::String(p));
                m.insert(sha_key.clone(), serde_json::Value::String(s));
            }
        } else {
            m.insert(k, v);
        }
    }
    if let Some((p, s)) = pending {
        m.insert(key.to_string(), serde_json::Value::String(p));
        m.insert(sha_key, serde_json::Value::String(s));
    }
    *obj = serde_json::Value::Object(m);
}

/// Absolute, without `.` and `..`, with the links of its longest existing prefix resolved.
fn absolute_clean(p: &Path) -> PathBuf {
    let abs = std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
    let mut lexical = PathBuf::new();
    for c in abs.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                lexical.pop();
            }
            other => lexical.push(other.as_os_str()),
        }
    }
    // Resolve links in the part that exists; keep the rest (an output not written yet).
    let mut existing = lexical.clone();
    let mut rest = Vec::new();
    loop {
        if let Ok(c) = existing.canonicalize() {
            let mut out = c;
            for r in rest.iter().rev() {
                out.push(r);
            }
            return out;
        }
        match (existing.file_name().map(|n| n.to_os_string()), existing.parent()) {
            (Some(n), Some(parent)) => {
                rest.push(n);
                existing = parent.to_path_buf();
            }
            _ => return lexical,
        }
    }
}

/// `input` relative to the directory `from_dir`, `/`-separated (`.` for the directory
/// itself); absolute when no relative path exists (see the module documentation).
pub fn relative_path(from_dir: &Path, input: &Path) -> String {
    let base = absolute_clean(from_dir);
    let target = absolute_clean(input);
    let b: Vec<Component> = base.components().collect();
    let t: Vec<Component> = target.components().collect();
    // Different roots (Windows drives): no relative path.
    if b.first() != t.first() {
        return target.display().to_string();
    }
    let common = b.iter().zip(&t).take_while(|(x, y)| x == y).count();
    let mut parts: Vec<String> = vec!["..".to_string(); b.len() - common];
    parts.extend(t[common..].iter().map(|c| c.as_os_str().to_string_lossy().into_owned()));
    if parts.is_empty() {
        ".".to_string()
    } else {
        parts.join("/")
    }
}

/// Where a recorded input path points: `recorded` resolved against the output's directory
/// (an absolute `recorded` is returned as it is).
pub fn resolve(out_dir: &Path, recorded: &str) -> PathBuf {
    let p = Path::new(recorded);
    if p.is_absolute() {
        p.to_path_buf()
    } else {
        out_dir.join(p)
    }
}

/// The listing a dataset's SHA-256 is taken of (see the module documentation).
pub fn dataset_listing(dir: &Path) -> Result<String, ProvenanceError> {
    if !dir.join(MANIFEST_FILE).is_file() {
        return Err(ProvenanceError::NotADataset {
            path: dir.to_path_buf(),
        });
    }
    let (_, records) = load(dir).map_err(|source| ProvenanceError::Dataset {
        path: dir.to_path_buf(),
        source: Box::new(source),
    })?;
    let mut text = String::new();
    for r in &records {
        for (file, sha) in [(&r.image, &r.image_sha256), (&r.raw, &r.raw_sha256)] {
            if let Some(file) = file {
                text.push_str(sha.as_deref().unwrap_or("-"));
                text.push_str("  ");
                text.push_str(file);
                text.push('\n');
            }
        }
    }
    Ok(text)
}

/// The SHA-256 an output records for `input`: of a file's bytes, or of a dataset
/// directory's listing ([`dataset_listing`]; see the module documentation).
pub fn input_sha256(input: &Path) -> Result<String, ProvenanceError> {
    if input.is_dir() {
        return Ok(format!("{:x}", Sha256::digest(dataset_listing(input)?.as_bytes())));
    }
    let file = input.to_path_buf();
    let read_err = |source| ProvenanceError::Read {
        path: file.clone(),
        source,
    };
    let mut f = std::fs::File::open(&file).map_err(read_err)?;
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf).map_err(read_err)?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(format!("{:x}", h.finalize()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_paths_climb_and_descend() {
        let t = tempfile::tempdir().unwrap();
        let d = t.path();
        std::fs::create_dir_all(d.join("a/in/ds")).unwrap();
        std::fs::create_dir_all(d.join("a/out")).unwrap();
        assert_eq!(relative_path(&d.join("a/out"), &d.join("a/in/ds")), "../in/ds");
        assert_eq!(relative_path(&d.join("a/in"), &d.join("a/in/ds")), "ds");
        assert_eq!(relative_path(&d.join("a/in/ds"), &d.join("a/in/ds")), ".");
        // Not yet existing output directories, and `..` in the input.
        assert_eq!(
            relative_path(&d.join("a/new/deeper"), &d.join("a/out/../in/ds")),
            "../../in/ds"
        );
        assert_eq!(resolve(&d.join("a/out"), "../in/ds"), d.join("a/out/../in/ds"));
    }

    #[test]
    fn file_hash_is_of_its_bytes_and_a_plain_directory_is_refused() {
        let t = tempfile::tempdir().unwrap();
        let d = t.path();
        std::fs::create_dir_all(d.join("ds")).unwrap();
        assert!(matches!(
            input_sha256(&d.join("ds")),
            Err(ProvenanceError::NotADataset { .. })
        ));
        std::fs::write(d.join("f"), b"{}").unwrap();
        let want = format!("{:x}", Sha256::digest(b"{}"));
        assert_eq!(input_sha256(&d.join("f")).unwrap(), want);
        assert!(matches!(
            input_sha256(&d.join("absent")),
            Err(ProvenanceError::Read { .. })
        ));
    }
}
