//! `journal.jsonl`: the append-only record of stored measurements.
//!
//! One line per measurement, written only after the measurement's files are renamed
//! into place, and fsynced before `Dataset::store` returns. A line is
//!
//! ```text
//! {"crc":"1c291ca3","rec":{...record...}}
//! ```
//!
//! where `crc` is the CRC-32 (IEEE) of the exact bytes of the `rec` value, as 8
//! lower-case hex digits. The line is valid JSON, and the fixed-width prefix lets the
//! reader recover the exact payload bytes without re-serialising. The CRC catches what
//! JSON parsing would not: a line that is syntactically fine but whose digits were
//! damaged, or a crash that persisted the file size but not the data.
//!
//! Because each line is fsynced before the next is written, a crash can damage only
//! the last line; damage anywhere else is reported, never "repaired".

use super::error::StoreError;
use super::manifest::MeasurementRecord;
use serde::de::DeserializeOwned;
use serde::Serialize;
use std::fs::File;
use std::io::{Seek, SeekFrom, Write};
use std::path::Path;

const PREFIX: &[u8] = b"{\"crc\":\"";
const MIDDLE: &[u8] = b"\",\"rec\":";
/// Bytes before the payload: prefix, 8 hex digits, middle.
const HEAD_LEN: usize = PREFIX.len() + 8 + MIDDLE.len();

/// Serialise a record as one journal line, newline included. Generic so other append-only
/// files of a dataset (`references.jsonl`) share the line format and its CRC.
pub fn encode_line<T: Serialize>(rec: &T) -> Result<Vec<u8>, serde_json::Error> {
    let payload = serde_json::to_vec(rec)?;
    let crc = crc32fast::hash(&payload);
    let mut line = Vec::with_capacity(HEAD_LEN + payload.len() + 2);
    line.extend_from_slice(PREFIX);
    line.extend_from_slice(format!("{crc:08x}").as_bytes());
    line.extend_from_slice(MIDDLE);
    line.extend_from_slice(&payload);
    line.extend_from_slice(b"}\n");
    Ok(line)
}

/// Parse one line (without its newline).
pub fn decode_line<T: DeserializeOwned>(line: &[u8]) -> Result<T, String> {
    if line.len() < HEAD_LEN + 1 || !line.starts_with(PREFIX) {
        return Err("not a journal line (missing {\"crc\":\"…\",\"rec\": prefix)".into());
    }
    if &line[PREFIX.len() + 8..HEAD_LEN] != MIDDLE {
        return Err("malformed line prefix".into());
    }
    let hex = std::str::from_utf8(&line[PREFIX.len()..PREFIX.len() + 8]).map_err(|_| "CRC is not hex".to_string())?;
    let crc = u32::from_str_radix(hex, 16).map_err(|_| format!("CRC {hex:?} is not hex"))?;
    if line.last() != Some(&b'}') {
        return Err("line is cut short (no closing brace)".into());
    }
    let payload = &line[HEAD_LEN..line.len() - 1];
    let actual = crc32fast::hash(payload);
    if actual != crc {
        return Err(format!("CRC mismatch (stored {crc:08x}, computed {actual:08x})"));
    }
    serde_json::from_slice(payload).map_err(|e| format!("record does not parse: {e}"))
}

/// The damaged last line of a journal.
#[derive(Clone, Debug, PartialEq)]
pub struct TornTail {
    /// 1-based line number.
    pub line: usize,
    /// Byte offset where the line starts (the journal is truncated to this length).
    pub offset: u64,
    pub reason: String,
}

/// Result of reading a whole journal (of measurement records unless said otherwise).
#[derive(Debug)]
pub struct Scan<T = MeasurementRecord> {
    /// Valid records in file order, with their 1-based line numbers.
    pub records: Vec<(usize, T)>,
    /// The last line, if damaged (crash mid-append).
    pub torn: Option<TornTail>,
    /// The last line is valid but its newline is missing.
    pub missing_newline: bool,
}

impl<T> Default for Scan<T> {
    fn default() -> Self {
        Scan {
            records: Vec::new(),
            torn: None,
            missing_newline: false,
        }
    }
}

/// Read and check every line. Damage on the last line is reported in
/// [`Scan::torn`]; damage anywhere else is [`StoreError::CorruptJournal`].
pub fn scan<T: DeserializeOwned>(path: &Path, dataset: &Path) -> Result<Scan<T>, StoreError> {
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(StoreError::NotADataset {
                path: dataset.to_path_buf(),
                reason: format!("its journal {} is missing", path.display()),
                hint: "restore journal.jsonl from a backup: without it gonio cannot tell which \
                       images were completely stored",
            })
        }
        Err(e) => return Err(StoreError::io("reading", path, Some(dataset), e)),
    };
    scan_bytes(&bytes, path)
}

pub(crate) fn scan_bytes<T: DeserializeOwned>(bytes: &[u8], path: &Path) -> Result<Scan<T>, StoreError> {
    let mut scan = Scan::default();
    let mut lines: Vec<(u64, &[u8])> = Vec::new();
    let mut start = 0usize;
    for (i, b) in bytes.iter().enumerate() {
        if *b == b'\n' {
            lines.push((start as u64, &bytes[start..i]));
            start = i + 1;
        }
    }
    let unterminated = start < bytes.len();
    if unterminated {
        lines.push((start as u64, &bytes[start..]));
    }
    let n = lines.len();
    for (i, (offset, line)) in lines.into_iter().enumerate() {
        let line_no = i + 1;
        match decode_line(line) {
            Ok(rec) => scan.records.push((line_no, rec)),
            Err(reason) if line_no == n => {
                scan.torn = Some(TornTail {
                    line: line_no,
                    offset,
                    reason,
                });
            }
            Err(reason) => {
                return Err(StoreError::CorruptJournal {
                    path: path.to_path_buf(),
                    line: line_no,
                    reason,
                })
            }
        }
    }
    scan.missing_newline = unterminated && scan.torn.is_none();
    Ok(scan)
}

/// Appends lines to an open journal and keeps it consistent when an append fails.
pub struct Appender {
    file: File,
    len: u64,
}

impl Appender {
    /// Wrap a journal opened for writing; `len` is its current (valid) length.
    pub fn new(mut file: File, len: u64) -> std::io::Result<Appender> {
        file.seek(SeekFrom::Start(len))?;
        Ok(Appender { file, len })
    }

    /// Append one line and fsync. On failure the journal is cut back to its previous
    /// length so that no partial line stays behind for a later append to bury; the
    /// `Err` carries the original error and whether that rollback succeeded.
    pub fn append(&mut self, line: &[u8]) -> Result<(), (std::io::Error, bool)> {
        let res = self.file.write_all(line).and_then(|_| self.file.sync_data());
        match res {
            Ok(()) => {
                self.len += line.len() as u64;
                Ok(())
            }
            Err(e) => {
                let rolled_back = self
                    .file
                    .set_len(self.len)
                    .and_then(|_| self.file.seek(SeekFrom::Start(self.len)))
                    .and_then(|_| self.file.sync_data())
                    .is_ok();
                Err((e, rolled_back))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_round_trip_and_crc_detects_damage() {
        let rec = MeasurementRecord::new(7, 3, [15.0, 60.0], [75.0, 345.0]);
        let line = encode_line(&rec).unwrap();
        assert_eq!(*line.last().unwrap(), b'\n');
        let body = &line[..line.len() - 1];
        // Valid JSON as a whole, as promised.
        let v: serde_json::Value = serde_json::from_slice(body).unwrap();
        assert_eq!(v["rec"]["index"], 7);
        assert_eq!(decode_line::<MeasurementRecord>(body).unwrap(), rec);
        // Flip one digit inside the payload: still JSON, but the CRC catches it.
        let mut damaged = body.to_vec();
        let pos = damaged.windows(9).position(|w| w == b"\"index\":7").unwrap();
        damaged[pos + 8] = b'8';
        let err = decode_line::<MeasurementRecord>(&damaged).unwrap_err();
        assert!(err.contains("CRC mismatch"), "{err}");
        // Cut short.
        assert!(decode_line::<MeasurementRecord>(&body[..body.len() / 2]).is_err());
    }
}
