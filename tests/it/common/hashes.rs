//! The SHA-256 of every file of an output, with the fields that measure the run itself
//! (wall-clock readings, peak memory) left out by name: what "same bytes" compares.
//!
//! * `manifest.json`: `created_unix`; `records[].wall_time_unix`; `summary.wall_time_s`,
//!   `summary.images_per_s`, `summary.stage_seconds`, `summary.peak_rss_mib`.
//! * `journal.jsonl`: `rec.wall_time_unix` of every line, and the line's `crc` (a CRC of
//!   the record bytes, which include `wall_time_unix`); everything else byte for byte.
//!
//! Every other byte of every other file counts.

use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::path::Path;

/// Manifest fields that hold wall-clock readings (see the module documentation).
const MANIFEST_WALL_CLOCK: [&str; 1] = ["created_unix"];
const SUMMARY_WALL_CLOCK: [&str; 4] = ["wall_time_s", "images_per_s", "stage_seconds", "peak_rss_mib"];
const RECORD_WALL_CLOCK: &str = "wall_time_unix";

pub fn sha(bytes: &[u8]) -> String {
    format!("{:x}", Sha256::digest(bytes))
}

fn drop_keys(v: &mut serde_json::Value, keys: &[&str]) {
    if let Some(o) = v.as_object_mut() {
        for k in keys {
            o.remove(*k);
        }
    }
}

/// The bytes a file is compared by: its own, or for the manifest and the journal the
/// JSON without the wall-clock fields named above.
pub fn comparable(rel: &str, bytes: &[u8]) -> Vec<u8> {
    let name = Path::new(rel).file_name().unwrap().to_string_lossy().into_owned();
    match name.as_str() {
        "manifest.json" => {
            let mut v: serde_json::Value = serde_json::from_slice(bytes).unwrap();
            drop_keys(&mut v, &MANIFEST_WALL_CLOCK);
            if let Some(s) = v.get_mut("summary") {
                drop_keys(s, &SUMMARY_WALL_CLOCK);
            }
            if let Some(rs) = v.get_mut("records").and_then(|r| r.as_array_mut()) {
                for r in rs {
                    drop_keys(r, &[RECORD_WALL_CLOCK]);
                }
            }
            serde_json::to_vec(&v).unwrap()
        }
        "journal.jsonl" => {
            let mut out = Vec::new();
            for line in bytes.split(|&b| b == b'\n').filter(|l| !l.is_empty()) {
                let mut v: serde_json::Value = serde_json::from_slice(line).unwrap();
                drop_keys(&mut v, &["crc"]);
                drop_keys(v.get_mut("rec").unwrap(), &[RECORD_WALL_CLOCK]);
                out.extend(serde_json::to_vec(&v).unwrap());
                out.push(b'\n');
            }
            out
        }
        _ => bytes.to_vec(),
    }
}

/// Relative path → SHA-256 of the comparable bytes, for a file or every file of a tree
/// (a single file is keyed by the empty path).
pub fn hashes(root: &Path) -> BTreeMap<String, String> {
    if root.is_dir() {
        hashes_by(root, &|rel, bytes| sha(&comparable(rel, bytes)))
    } else {
        BTreeMap::from([(String::new(), sha(&std::fs::read(root).unwrap()))])
    }
}

/// Relative path → `one(relative path, bytes)` for every file of a tree; for a single file
/// `one(file name, bytes)`, keyed by the empty path.
pub fn hashes_by(root: &Path, one: &dyn Fn(&str, &[u8]) -> String) -> BTreeMap<String, String> {
    fn walk(root: &Path, dir: &Path, one: &dyn Fn(&str, &[u8]) -> String, out: &mut BTreeMap<String, String>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, one, out);
            } else {
                let rel = p.strip_prefix(root).unwrap().to_string_lossy().into_owned();
                let h = one(&rel, &std::fs::read(&p).unwrap());
                out.insert(rel, h);
            }
        }
    }
    let mut out = BTreeMap::new();
    if root.is_dir() {
        walk(root, root, one, &mut out);
    } else {
        let name = root.file_name().unwrap().to_string_lossy().into_owned();
        out.insert(String::new(), one(&name, &std::fs::read(root).unwrap()));
    }
    out
}
