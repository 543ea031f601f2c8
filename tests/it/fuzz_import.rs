//! Fuzzing (proptest) of `gonio import`'s UBO2003 reader: archives are outside input.
//!
//! Seeds are small valid UBO2003 zips built here (JPEG and PNG entries, a readme, a
//! directory entry). Mutations: byte flips anywhere (central directory, local headers,
//! compressed data, image bytes), truncation, inserted garbage, and entry names rewritten
//! (angles out of range, duplicates, missing tags). Property: the import returns Ok or a
//! typed error within the time limit, never panics; and an import that succeeds yields a
//! dataset that `gonio verify` accepts. Regression tests pin the limit checks (zip bomb,
//! absurd image dimensions, mixed image sizes, duplicates).
//!
//! CI budget: `GONIO_FUZZ_CASES` cases (default 256, a few seconds).
//! Long campaign: `GONIO_FUZZ_CASES=100000 cargo test --release --test fuzz_import -- --nocapture`.

use crate::fuzzing;

use fuzzing::{cases, guarded};
use gonio::store::import_ubo2003::{import_ubo2003, ImportError, ImportLimits};
use proptest::prelude::*;
use proptest::test_runner::{Config, TestCaseError, TestRunner};
use std::io::{Cursor, Write};
use std::path::Path;
use std::time::Duration;

const TIME_LIMIT: Duration = Duration::from_secs(30);

/// An 8×8 test image, encoded as JPEG or PNG.
fn image_bytes(seed: u8, png: bool, w: u32, h: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| {
        image::Rgb([seed.wrapping_mul(7).wrapping_add(x as u8 * 9), y as u8 * 20, seed])
    });
    let mut out = Cursor::new(Vec::new());
    let fmt = if png {
        image::ImageFormat::Png
    } else {
        image::ImageFormat::Jpeg
    };
    img.write_to(&mut out, fmt).unwrap();
    out.into_inner()
}

/// A zip with the given (name, bytes) entries, deflated.
fn zip_bytes(entries: &[(String, Vec<u8>)]) -> Vec<u8> {
    try_zip_bytes(entries).expect("valid entry names")
}

/// As [`zip_bytes`]; `None` when the zip writer itself refuses a name (a duplicate).
fn try_zip_bytes(entries: &[(String, Vec<u8>)]) -> Option<Vec<u8>> {
    let mut w = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Deflated);
    w.add_directory("tv000_pv000/", opts).ok()?;
    for (name, bytes) in entries {
        w.start_file(name.as_str(), opts).ok()?;
        w.write_all(bytes).ok()?;
    }
    Some(w.finish().ok()?.into_inner())
}

fn name(i: usize, l: [u32; 2], v: [u32; 2], ext: &str) -> String {
    format!(
        "tv{:03}_pv{:03}/{i:05} tl{:03} pl{:03} tv{:03} pv{:03}.{ext}",
        v[0], v[1], l[0], l[1], v[0], v[1]
    )
}

/// A valid 3 lights × 2 views archive with one pair missing and a readme.
fn seed_archive() -> Vec<u8> {
    let lights = [[0, 0], [30, 90], [60, 300]];
    let views = [[0, 0], [45, 120]];
    let mut entries = Vec::new();
    let mut i = 0;
    for v in views {
        for l in lights {
            if l == [60, 300] && v == [45, 120] {
                continue;
            }
            entries.push((
                name(i, l, v, if i % 2 == 0 { "jpg" } else { "png" }),
                image_bytes(i as u8, i % 2 == 1, 8, 8),
            ));
            i += 1;
        }
    }
    entries.push(("readme.txt".into(), b"a test archive".to_vec()));
    zip_bytes(&entries)
}

fn import(bytes: &[u8], limits: ImportLimits) -> Result<(), ImportError> {
    let dir = tempfile::tempdir().unwrap();
    let zip = dir.path().join("a.zip");
    std::fs::write(&zip, bytes).unwrap();
    let out = dir.path().join("ds");
    import_ubo2003(&zip, &out, false, false, &limits, |_, _| {})?;
    let report = gonio::store::verify(&out).expect("an imported dataset verifies");
    assert!(report.damaged.is_empty(), "{report:?}");
    Ok(())
}

#[derive(Clone, Debug)]
enum Mutation {
    Flip { at: usize, xor: u8 },
    Truncate { keep: usize },
    Insert { at: usize, bytes: Vec<u8> },
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        4 => (any::<usize>(), 1u8..=255).prop_map(|(at, xor)| Mutation::Flip { at, xor }),
        1 => any::<usize>().prop_map(|keep| Mutation::Truncate { keep }),
        1 => (any::<usize>(), prop::collection::vec(any::<u8>(), 1..64)).prop_map(|(at, bytes)| Mutation::Insert { at, bytes }),
    ]
}

fn apply(mut b: Vec<u8>, ms: &[Mutation]) -> Vec<u8> {
    for m in ms {
        if b.is_empty() {
            break;
        }
        match m {
            Mutation::Flip { at, xor } => {
                let i = at % b.len();
                b[i] ^= xor;
            }
            Mutation::Truncate { keep } => b.truncate(keep % b.len()),
            Mutation::Insert { at, bytes } => {
                let i = at % b.len();
                b.splice(i..i, bytes.iter().copied());
            }
        }
    }
    b
}

#[test]
fn the_seed_archive_imports() {
    import(&seed_archive(), ImportLimits::default()).expect("the seed is a valid archive");
}

#[test]
fn fuzz_ubo2003_archives_never_panic_or_hang() {
    let seed = seed_archive();
    let mut runner = TestRunner::new(Config {
        cases: cases(256),
        failure_persistence: None,
        ..Config::default()
    });
    let counts = std::sync::Arc::new(std::sync::Mutex::new((0usize, 0usize)));
    let c2 = counts.clone();
    let seed2 = seed.clone();
    let result = runner.run(&prop::collection::vec(mutation(), 1..6), move |ms| {
        let bytes = apply(seed.clone(), &ms);
        let c = c2.clone();
        guarded(TIME_LIMIT, move || {
            let r = import(&bytes, ImportLimits::default());
            let mut g = c.lock().unwrap();
            if r.is_ok() {
                g.0 += 1
            } else {
                g.1 += 1
            }
        })
        .map_err(TestCaseError::fail)
    });
    fuzzing::check("ubo2003_zip", result, |ms| apply(seed2.clone(), ms));
    let (ok, err) = *counts.lock().unwrap();
    println!(
        "fuzz_import: {} cases, {ok} imported, {err} refused with an error, 0 panics, 0 hangs",
        ok + err
    );
}

#[test]
fn fuzz_entry_names_never_panic() {
    let mut runner = TestRunner::new(Config {
        cases: cases(256),
        failure_persistence: None,
        ..Config::default()
    });
    let img = image_bytes(3, false, 8, 8);
    let zip_of = move |names: &Vec<String>| {
        let entries: Vec<(String, Vec<u8>)> = names.iter().map(|n| (n.clone(), img.clone())).collect();
        try_zip_bytes(&entries)
    };
    let zip2 = zip_of.clone();
    let result = runner.run(&prop::collection::vec("[a-z0-9_ ./]{0,40}", 1..5), move |names| {
        let Some(bytes) = zip_of(&names) else {
            return Ok(());
        };
        guarded(TIME_LIMIT, move || {
            let _ = import(&bytes, ImportLimits::default());
        })
        .map_err(TestCaseError::fail)
    });
    fuzzing::check("ubo2003_names", result, |names| zip2(names).unwrap_or_default());
}

fn expect_entry_error(bytes: &[u8], limits: ImportLimits, needle: &str) {
    match import(bytes, limits) {
        Err(e @ ImportError::Entry { .. }) | Err(e @ ImportError::Duplicate { .. }) => {
            let msg = e.to_string();
            assert!(msg.contains(needle), "{msg:?} should mention {needle:?}");
        }
        other => panic!("expected an entry error mentioning {needle:?}, got {other:?}"),
    }
}

#[test]
fn a_zip_bomb_entry_is_refused_by_the_byte_limit() {
    let big = vec![0u8; 4 << 20];
    let bytes = zip_bytes(&[(name(0, [0, 0], [0, 0], "jpg"), big)]);
    assert!(bytes.len() < 64 << 10, "deflate packs 4 MiB of zeros small");
    let limits = ImportLimits {
        max_entry_bytes: 1 << 20,
        ..ImportLimits::default()
    };
    expect_entry_error(&bytes, limits, "limit");
}

#[test]
fn absurd_image_dimensions_are_refused_before_allocation() {
    // A PNG header claiming 60000 × 60000 pixels (10.8 GB decoded) with no data.
    let mut png = image_bytes(1, true, 8, 8);
    let ihdr = png.windows(4).position(|w| w == b"IHDR").unwrap() + 4;
    png[ihdr..ihdr + 4].copy_from_slice(&60000u32.to_be_bytes());
    png[ihdr + 4..ihdr + 8].copy_from_slice(&60000u32.to_be_bytes());
    let bytes = zip_bytes(&[(name(0, [0, 0], [0, 0], "png"), png)]);
    let limits = ImportLimits {
        max_edge: 16384,
        ..ImportLimits::default()
    };
    expect_entry_error(&bytes, limits, "decode");
}

#[test]
fn mixed_image_sizes_and_bad_angles_and_duplicates_are_named() {
    let a = image_bytes(1, false, 8, 8);
    let b = image_bytes(2, false, 16, 8);
    let mixed = zip_bytes(&[
        (name(0, [0, 0], [0, 0], "jpg"), a.clone()),
        (name(1, [30, 0], [0, 0], "jpg"), b),
    ]);
    expect_entry_error(&mixed, ImportLimits::default(), "16×8");
    let bad = zip_bytes(&[(name(0, [95, 0], [0, 0], "jpg"), a.clone())]);
    expect_entry_error(&bad, ImportLimits::default(), "horizon");
    let dup = zip_bytes(&[
        (name(0, [30, 10], [0, 0], "jpg"), a.clone()),
        (name(1, [30, 10], [0, 0], "jpg"), a.clone()),
    ]);
    expect_entry_error(&dup, ImportLimits::default(), "both hold");
    // The pole has no azimuth: (0, 0) and (0, 90) are the same light.
    let pole = zip_bytes(&[
        (name(0, [0, 0], [0, 0], "jpg"), a.clone()),
        (name(1, [0, 90], [0, 0], "jpg"), a),
    ]);
    expect_entry_error(&pole, ImportLimits::default(), "both hold");
}

#[test]
fn an_interrupted_import_resumes_to_the_same_dataset() {
    let dir = tempfile::tempdir().unwrap();
    let zip = dir.path().join("a.zip");
    std::fs::write(&zip, seed_archive()).unwrap();
    let full = dir.path().join("full");
    let r = import_ubo2003(&zip, &full, false, false, &ImportLimits::default(), |_, _| {}).unwrap();
    assert_eq!((r.lights, r.views, r.imported, r.missing_pairs), (3, 2, 5, 1));
    assert_eq!(r.ignored_entries, vec!["readme.txt".to_string()]);
    // Interrupt after 2 images: the progress callback panics (as a crash would stop it).
    let part = dir.path().join("part");
    let z2 = zip.clone();
    let p2 = part.clone();
    let crashed = std::thread::spawn(move || {
        import_ubo2003(&z2, &p2, false, false, &ImportLimits::default(), |done, _| {
            if done == 2 {
                panic!("simulated crash after 2 images")
            }
        })
    })
    .join();
    assert!(crashed.is_err());
    let r2 = import_ubo2003(&zip, &part, false, true, &ImportLimits::default(), |_, _| {}).unwrap();
    assert_eq!((r2.already_present, r2.imported), (2, 3));
    let (_, a) = gonio::store::load(&full).unwrap();
    let (_, b) = gonio::store::load(&part).unwrap();
    let key = |r: &gonio::store::MeasurementRecord| (r.index, r.image_sha256.clone(), r.status.kind());
    let mut ka: Vec<_> = a.iter().map(key).collect();
    let mut kb: Vec<_> = b.iter().map(key).collect();
    ka.sort();
    kb.sort();
    assert_eq!(ka, kb, "resumed import equals the uninterrupted one");
}

#[test]
fn a_missing_archive_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let e = import_ubo2003(
        Path::new("/nonexistent/a.zip"),
        &dir.path().join("x"),
        false,
        false,
        &ImportLimits::default(),
        |_, _| {},
    )
    .unwrap_err();
    assert!(e.to_string().contains("/nonexistent/a.zip"), "{e}");
}
