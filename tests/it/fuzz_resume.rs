//! Fuzzing (proptest) of the journal and manifest on resume: a small dataset (finished or
//! interrupted) has bytes of `journal.jsonl` or `manifest.json` flipped, truncated,
//! duplicated or replaced with garbage; then `Dataset::resume` must return Ok (with its
//! repairs) or a clear Err within a time limit, never panic or hang. When it returns Ok:
//! every record it kept has intact files (`verify` finds nothing damaged), no index is
//! kept twice, no record it kept was altered, and a second `resume` finds nothing left to
//! repair.
//!
//! CI budget: `GONIO_FUZZ_CASES` cases per target (default 512). Long campaign:
//! `GONIO_FUZZ_CASES=100000 cargo test --release --test fuzz_resume -- --nocapture`.
//! Every file of `tests/campaigns/corpus/journal/` is also replayed as a journal.

use crate::fuzzing;
use gonio::store::{self, Dataset, ManifestHeader, MeasurementRecord, MeasurementStatus};
use gonio_devices::image::RgbImage;

use fuzzing::cases;
use proptest::prelude::*;
use proptest::test_runner::{Config, TestCaseError, TestRunner};
use std::path::{Path, PathBuf};
use std::time::Duration;

fn header() -> ManifestHeader {
    ManifestHeader {
        format: store::FORMAT.into(),
        version: store::FORMAT_VERSION,
        gonio_version: "fuzz".into(),
        created_unix: 0.0,
        rig: serde_json::json!({"name": "fuzz"}),
        sample: serde_json::json!({"name": "fuzz"}),
        sweep: serde_json::json!({"name": "fuzz"}),
        image_width: 8,
        image_height: 8,
        values: "linear".into(),
        seed: 1,
        raw_frames: false,
        calibration: None,
        extra: serde_json::json!({}),
    }
}

/// A dataset of 6 records (5 measured with images, 1 skipped); `finished` decides whether
/// the final manifest (with every record) was written.
fn make_dataset(dir: &Path, finished: bool) {
    let mut ds = Dataset::create(dir, &header(), false).unwrap();
    for i in 0..6usize {
        let mut rec = MeasurementRecord::new(i * 7, i, [15.0 * i as f64, 30.0], [45.0, 60.0 * i as f64]);
        rec.wall_time_unix = 1.7e9 + i as f64;
        if i == 3 {
            rec.status = MeasurementStatus::Skipped { reason: "fuzz".into() };
            ds.store(rec, None, None).unwrap();
        } else {
            let img = RgbImage {
                width: 8,
                height: 8,
                data: (0..192).map(|k| ((k * (i + 1)) % 97) as f32 / 97.0).collect(),
            };
            ds.store(rec, Some(&img), None).unwrap();
        }
    }
    if finished {
        ds.finish(&serde_json::json!({"fuzz": true})).unwrap();
    }
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dest = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &dest);
        } else {
            std::fs::copy(e.path(), dest).unwrap();
        }
    }
}

const GARBAGE: &[&str] = &[
    "\n",
    "}\n",
    "{\"crc\":\"00000000\",\"rec\":{}}\n",
    "{\"crc\":\"zzzzzzzz\",\"rec\":",
    "NaN",
    "1e999",
    "18446744073709551616",
    "\u{0}\u{0}\u{0}\u{0}",
    "\"index\":99999999999999999999",
    "\u{feff}",
    "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[",
    "\"images/../../etc/passwd\"",
];

#[derive(Clone, Debug)]
enum Mutation {
    Flip(usize, u8),
    Truncate(usize),
    Insert(usize, usize),
    /// Duplicate the n-th line (as a crash-and-retry might).
    DuplicateLine(usize),
    /// Replace the n-th line with a line carrying a valid CRC over garbage payload.
    ValidCrcGarbage(usize, usize),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        (any::<usize>(), any::<u8>()).prop_map(|(p, b)| Mutation::Flip(p, b)),
        any::<usize>().prop_map(Mutation::Truncate),
        (any::<usize>(), 0..GARBAGE.len()).prop_map(|(p, g)| Mutation::Insert(p, g)),
        any::<usize>().prop_map(Mutation::DuplicateLine),
        (any::<usize>(), 0..GARBAGE.len()).prop_map(|(p, g)| Mutation::ValidCrcGarbage(p, g)),
    ]
}

fn apply(bytes: &mut Vec<u8>, m: &Mutation) {
    let len = bytes.len().max(1);
    match *m {
        Mutation::Flip(p, x) => {
            if !bytes.is_empty() {
                let i = p % bytes.len();
                bytes[i] ^= x | 1;
            }
        }
        Mutation::Truncate(p) => bytes.truncate(p % len),
        Mutation::Insert(p, g) => {
            let i = p % (bytes.len() + 1);
            bytes.splice(i..i, GARBAGE[g].bytes());
        }
        Mutation::DuplicateLine(p) | Mutation::ValidCrcGarbage(p, _) => {
            let mut lines: Vec<Vec<u8>> = bytes.split_inclusive(|b| *b == b'\n').map(|l| l.to_vec()).collect();
            if lines.is_empty() {
                return;
            }
            let i = p % lines.len();
            if let Mutation::ValidCrcGarbage(_, g) = *m {
                // A payload that passes the CRC: only JSON/record validation can catch it.
                let payload = GARBAGE[g].trim_end_matches('\n').as_bytes().to_vec();
                let mut line = format!("{{\"crc\":\"{:08x}\",\"rec\":", crc32(&payload)).into_bytes();
                line.extend_from_slice(&payload);
                line.extend_from_slice(b"}\n");
                lines[i] = line;
            } else {
                let l = lines[i].clone();
                lines.insert(i, l);
            }
            *bytes = lines.concat();
        }
    }
}

/// CRC-32 (IEEE), bitwise, so the test does not depend on the store's implementation.
fn crc32(data: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &b in data {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// Resume `dir` on a helper thread with a time limit and check the properties above.
/// Returns a description of the violation, if any.
fn check_resume(dir: PathBuf, original: Vec<MeasurementRecord>) -> Result<&'static str, String> {
    fuzzing::guarded(Duration::from_secs(10), move || -> Result<&'static str, String> {
        let (ds, _, kept) = match Dataset::resume(&dir) {
            Ok(v) => v,
            Err(e) => {
                let msg = e.to_string();
                if msg.trim().is_empty() {
                    return Err("empty error message".into());
                }
                return Ok("err");
            }
        };
        let repaired = !ds.recovery().is_clean();
        let mut seen = std::collections::HashSet::new();
        for r in &kept {
            if !seen.insert(r.index) {
                return Err(format!("resume kept index {} twice", r.index));
            }
            // A kept record must be one that was stored (byte corruption that passes the
            // CRC and parses is what the CRC is for; we only accept exact originals).
            if !original.iter().any(|o| o == r) {
                return Err(format!("resume kept a record that was never stored: {r:?}"));
            }
        }
        drop(ds);
        let rep = store::verify(&dir).map_err(|e| format!("verify after resume failed: {e}"))?;
        if !rep.damaged.is_empty() || !rep.duplicates.is_empty() || !rep.orphans.is_empty() {
            return Err(format!("after resume: {rep}"));
        }
        let (ds2, _, kept2) = Dataset::resume(&dir).map_err(|e| format!("second resume failed: {e}"))?;
        if !ds2.recovery().is_clean() {
            return Err(format!("second resume still repaired: {:?}", ds2.recovery()));
        }
        if kept2 != kept {
            return Err("second resume kept other records".into());
        }
        Ok(if repaired { "ok, repaired" } else { "ok, clean" })
    })?
}

fn fuzz_file(file: &'static str) {
    let tmp = tempfile::tempdir().unwrap();
    let mut bases = Vec::new();
    for finished in [false, true] {
        let base = tmp.path().join(format!("base-{finished}"));
        make_dataset(&base, finished);
        bases.push(base);
    }
    let (_, original) = store::load(&bases[0]).unwrap();
    let mut runner = TestRunner::new(Config {
        cases: cases(512),
        failure_persistence: None,
        ..Config::default()
    });
    let counter = std::sync::atomic::AtomicUsize::new(0);
    let outcomes = std::sync::Mutex::new(std::collections::BTreeMap::<&'static str, usize>::new());
    let t0 = std::time::Instant::now();
    let result = runner.run(
        &(any::<bool>(), prop::collection::vec(mutation(), 1..5)),
        |(finished, muts)| {
            let n = counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let dir = tmp.path().join(format!("case-{n}"));
            copy_dir(&bases[finished as usize], &dir);
            let path = dir.join(file);
            let mut bytes = std::fs::read(&path).unwrap();
            for m in &muts {
                apply(&mut bytes, m);
            }
            std::fs::write(&path, &bytes).unwrap();
            let r = check_resume(dir.clone(), original.clone());
            let _ = std::fs::remove_dir_all(&dir);
            match r {
                Ok(kind) => {
                    *outcomes.lock().unwrap().entry(kind).or_default() += 1;
                    Ok(())
                }
                Err(e) => Err(TestCaseError::fail(format!(
                    "{e}\n--- {file} ---\n{}\n---",
                    String::from_utf8_lossy(&bytes)
                ))),
            }
        },
    );
    println!(
        "fuzz resume/{file}: {} cases in {:.1} s, outcomes {:?}",
        cases(512),
        t0.elapsed().as_secs_f64(),
        outcomes.lock().unwrap()
    );
    // The kept file is the mutated `file` (replay it into a copy of the small dataset).
    fuzzing::check(&format!("resume_{file}"), result, |(finished, muts)| {
        let mut bytes = std::fs::read(bases[*finished as usize].join(file)).unwrap_or_default();
        for m in muts {
            apply(&mut bytes, m);
        }
        bytes
    });
}

#[test]
fn fuzz_resume_journal() {
    fuzz_file(store::JOURNAL_FILE);
}

#[test]
fn fuzz_resume_manifest() {
    fuzz_file(store::MANIFEST_FILE);
}

/// The committed journal corpus, each replayed as the journal of the small dataset.
#[test]
fn journal_corpus_resumes_or_fails_clearly() {
    let tmp = tempfile::tempdir().unwrap();
    let base = tmp.path().join("base");
    make_dataset(&base, false);
    let (_, original) = store::load(&base).unwrap();
    let corpus = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/campaigns/corpus/journal");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&corpus).unwrap().map(|e| e.unwrap().path()).collect();
    files.sort();
    assert!(!files.is_empty());
    for f in &files {
        let dir = tmp.path().join(f.file_name().unwrap());
        copy_dir(&base, &dir);
        std::fs::copy(f, dir.join(store::JOURNAL_FILE)).unwrap();
        let r = check_resume(dir, original.clone());
        println!("journal corpus {}: {r:?}", f.display());
        assert!(r.is_ok(), "{}: {r:?}", f.display());
    }
}

/// Regenerates `tests/campaigns/corpus/journal/` from the small dataset (run explicitly:
/// `cargo test --test fuzz_resume -- --ignored write_journal_corpus`).
#[test]
#[ignore = "tool: regenerates the committed journal corpus"]
fn write_journal_corpus() {
    let tmp = tempfile::tempdir().unwrap();
    let base = tmp.path().join("base");
    make_dataset(&base, false);
    let journal = std::fs::read(base.join(store::JOURNAL_FILE)).unwrap();
    let lines: Vec<&[u8]> = journal.split_inclusive(|b| *b == b'\n').collect();
    let corpus = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/campaigns/corpus/journal");
    std::fs::create_dir_all(&corpus).unwrap();
    let write = |name: &str, bytes: Vec<u8>| std::fs::write(corpus.join(name), bytes).unwrap();
    write("intact.jsonl", journal.clone());
    write("empty.jsonl", Vec::new());
    write("torn_tail.jsonl", journal[..journal.len() - 40].to_vec());
    write("missing_newline.jsonl", journal[..journal.len() - 1].to_vec());
    let mut dup = lines.clone();
    dup.insert(2, lines[2]);
    write("duplicate_line.jsonl", dup.concat());
    let mut mid = journal.clone();
    let p = lines[0].len() + lines[1].len() + 60;
    mid[p] ^= 0x04;
    write("corrupt_middle.jsonl", mid);
    let mut garbage = lines.clone();
    let payload = b"{\"index\":99999999999999999999}";
    let mut line = format!("{{\"crc\":\"{:08x}\",\"rec\":", crc32(payload)).into_bytes();
    line.extend_from_slice(payload);
    line.extend_from_slice(b"}\n");
    garbage.push(&line);
    write("valid_crc_garbage_tail.jsonl", garbage.concat());
    write("nul_tail.jsonl", [journal.clone(), vec![0u8; 4096]].concat());
}
