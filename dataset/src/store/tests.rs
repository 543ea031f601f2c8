//! Tests of the dataset store, its crash recovery and its exports.

use super::*;
use std::io::{Read, Write};

fn header(w: usize, h: usize) -> ManifestHeader {
    ManifestHeader {
        format: FORMAT.into(),
        version: FORMAT_VERSION,
        gonio_version: "test".into(),
        created_unix: 1_700_000_000.0,
        rig: serde_json::json!({"name": "test rig"}),
        sample: serde_json::json!({"name": "gradient"}),
        sweep: serde_json::json!({"set": "bonn81"}),
        image_width: w,
        image_height: h,
        values: "linear normalized sensor signal (DN / max DN), radiometrically uncalibrated".into(),
        seed: 42,
        raw_frames: false,
        calibration: None,
        extra: serde_json::Value::Null,
    }
}

/// A colourful non-square test image: R grows with x, G with y, B a hard-edged checker,
/// plus a seed-dependent offset, the shot noise of a 12-bit sensor (σ = √DN / 4095,
/// so JPEG has realistic fine detail to lose), and one over-exposed texel (value > 1).
fn gradient(w: usize, h: usize, seed: usize) -> RgbImage {
    // splitmix64: a deterministic, pattern-free hash of (x, y, channel, seed).
    let hash = |k: u64| {
        let mut z = k.wrapping_add(0x9e37_79b9_7f4a_7c15);
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    };
    let mut img = RgbImage::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let s = (seed % 7) as f32 * 0.05;
            let r = (x as f32 + 0.5) / w as f32 * (1.0 - s) + s;
            let g = (y as f32 + 0.5) / h as f32;
            let b = if ((x / 8) + (y / 8) + seed) & 1 == 0 { 0.8 } else { 0.05 };
            let mut px = [r, g * g, b];
            for (c, v) in px.iter_mut().enumerate() {
                let k = (((seed * 4 + c) * h + y) * w + x) as u64;
                let u = (hash(k) >> 40) as f32 / (1u64 << 24) as f32; // uniform [0, 1)
                let sigma = (v.max(0.0) * 4095.0).sqrt() / 4095.0;
                *v = (*v + (u - 0.5) * 2.0 * 3f32.sqrt() * sigma).max(0.0);
            }
            img.set(x, y, px);
        }
    }
    img.set(0, 0, [1.7, 1.2, 3.0]);
    img
}

fn rec(index: usize, order: usize, light: [f64; 2], view: [f64; 2]) -> MeasurementRecord {
    let mut r = MeasurementRecord::new(index, order, light, view);
    r.exposure_s = 0.01;
    r.rig_time_s = order as f64 * 2.5;
    r.wall_time_unix = 1_700_000_000.0 + order as f64;
    r.extra = serde_json::json!({"truth_rmse": 0.001});
    r
}

fn skipped(index: usize, order: usize, dir: [f64; 2]) -> MeasurementRecord {
    let mut r = rec(index, order, dir, dir);
    r.status = MeasurementStatus::Skipped {
        reason: "camera blocks the lamp at retro-reflection".into(),
    };
    r
}

fn journal_lines(dir: &Path) -> Vec<String> {
    fs::read_to_string(dir.join(JOURNAL_FILE))
        .unwrap()
        .lines()
        .map(str::to_string)
        .collect()
}

/// A dataset with three stored measurements (indices 0, 1, 2).
fn three(dir: &Path) -> Dataset {
    let mut ds = Dataset::create(dir, &header(16, 8), false).unwrap();
    for i in 0..3 {
        ds.store(
            rec(i, i, [15.0, 60.0 * i as f64], [0.0, 0.0]),
            Some(&gradient(16, 8, i)),
            None,
        )
        .unwrap();
    }
    ds
}

#[test]
fn create_store_resume_round_trip() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    let mut ds = Dataset::create(&dir, &header(16, 8), false).unwrap();
    let a = ds
        .store(rec(82, 0, [15.0, 60.0], [15.0, 0.0]), Some(&gradient(16, 8, 1)), None)
        .unwrap();
    assert_eq!(a.image.as_deref(), Some("images/00082.exr"));
    assert_eq!(
        a.image_sha256.as_deref(),
        Some(sha256_hex(&fs::read(dir.join("images/00082.exr")).unwrap()).as_str())
    );
    let mut sub = rec(81, 1, [18.0, 0.0], [15.0, 0.0]);
    sub.status = MeasurementStatus::Substituted {
        requested_light_deg: [15.0, 0.0],
        reason: "retro-reflection".into(),
    };
    let frame = Frame {
        width: 4,
        height: 2,
        data: (0..24).map(|v| v * 2000).collect(),
        meta: gonio_devices::FrameMeta {
            timestamp: 1.0,
            exposure: 0.01,
            gain: 1.0,
            sequence: 7,
            bit_depth: 16,
        },
    };
    let b = ds.store(sub, Some(&gradient(16, 8, 2)), Some(&frame)).unwrap();
    assert_eq!(b.raw.as_deref(), Some("raw/00081.png"));
    let c = ds.store(skipped(0, 2, [0.0, 0.0]), None, None).unwrap();
    assert!(c.image.is_none() && c.image_sha256.is_none());
    assert!(ds.recovery().is_clean());
    drop(ds);

    let (mut ds, h, records) = Dataset::resume(&dir).unwrap();
    assert_eq!(h, header(16, 8));
    assert_eq!(records, vec![a.clone(), b.clone(), c.clone()]);
    assert!(ds.recovery().is_clean(), "{:?}", ds.recovery());
    // The image reads back within f16 precision.
    let back = read_exr(&dir.join("images/00082.exr")).unwrap();
    assert_close_f16(&gradient(16, 8, 1), &back);
    // The raw frame reads back exactly (16-bit PNG, values unscaled).
    let png = image::open(dir.join("raw/00081.png")).unwrap().into_rgb16();
    assert_eq!(png.as_raw(), &frame.data);

    let d = ds
        .store(rec(3, 3, [30.0, 0.0], [0.0, 0.0]), Some(&gradient(16, 8, 3)), None)
        .unwrap();
    ds.finish(&serde_json::json!({"measured": 3})).unwrap();
    drop(ds);

    let m: serde_json::Value = serde_json::from_slice(&fs::read(dir.join(MANIFEST_FILE)).unwrap()).unwrap();
    assert_eq!(m["format"], FORMAT);
    assert_eq!(m["complete"], true);
    assert_eq!(m["summary"]["measured"], 3);
    let idx: Vec<u64> = m["records"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["index"].as_u64().unwrap())
        .collect();
    assert_eq!(idx, vec![0, 3, 81, 82], "manifest records sorted by index");
    assert_eq!(m["records"][2]["status"]["kind"], "substituted");

    let (_, loaded) = load(&dir).unwrap();
    assert_eq!(loaded, vec![c, d, b, a]);
    let v = verify(&dir).unwrap();
    assert!(v.is_clean(), "{v}");
    assert_eq!((v.records, v.measured, v.substituted, v.skipped), (4, 2, 1, 1));
    assert_eq!((v.images_ok, v.raw_ok), (3, 1));
}

fn assert_close_f16(a: &RgbImage, b: &RgbImage) {
    assert_eq!((a.width, a.height), (b.width, b.height));
    for (x, y) in a.data.iter().zip(&b.data) {
        // f16 has 11 significant bits: relative rounding error ≤ 2⁻¹¹; subnormals below
        // 6.1e-5 have an absolute step of 6e-8.
        assert!((x - y).abs() <= x.abs() * 2f32.powi(-11) + 6e-8, "{x} vs {y}");
    }
}

#[test]
fn torn_last_line_is_cut_and_its_orphan_removed() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    let ds = three(&dir);
    let good_len = fs::metadata(dir.join(JOURNAL_FILE)).unwrap().len();
    drop(ds);
    // Simulate a crash while storing index 3: its image was renamed into place, and
    // only half of its journal line reached the disk.
    fs::write(
        dir.join("images/00003.exr"),
        encode_exr(&gradient(16, 8, 3), Path::new("x")).unwrap(),
    )
    .unwrap();
    let line = journal::encode_line(&rec(3, 3, [0.0, 0.0], [0.0, 0.0])).unwrap();
    let mut f = OpenOptions::new().append(true).open(dir.join(JOURNAL_FILE)).unwrap();
    f.write_all(&line[..line.len() / 2]).unwrap();
    drop(f);
    // load() reads around it without modifying anything.
    assert_eq!(load(&dir).unwrap().1.len(), 3);
    assert!(fs::metadata(dir.join(JOURNAL_FILE)).unwrap().len() > good_len);

    let (mut ds, _, records) = Dataset::resume(&dir).unwrap();
    assert_eq!(records.iter().map(|r| r.index).collect::<Vec<_>>(), vec![0, 1, 2]);
    let rep = ds.recovery().clone();
    assert_eq!(rep.torn_line.as_ref().map(|t| t.0), Some(4));
    assert_eq!(rep.orphans_removed, vec![dir.join("images/00003.exr")]);
    assert_eq!(fs::metadata(dir.join(JOURNAL_FILE)).unwrap().len(), good_len);
    assert!(!dir.join("images/00003.exr").exists());
    // Measurement 3 is redone and the journal is clean again.
    ds.store(rec(3, 3, [0.0, 0.0], [0.0, 0.0]), Some(&gradient(16, 8, 3)), None)
        .unwrap();
    drop(ds);
    let (ds, _, records) = Dataset::resume(&dir).unwrap();
    assert_eq!(records.len(), 4);
    assert!(ds.recovery().is_clean(), "{:?}", ds.recovery());
}

#[test]
fn complete_last_line_without_newline_is_kept() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    drop(three(&dir));
    let j = dir.join(JOURNAL_FILE);
    let bytes = fs::read(&j).unwrap();
    fs::write(&j, &bytes[..bytes.len() - 1]).unwrap();
    let (ds, _, records) = Dataset::resume(&dir).unwrap();
    assert_eq!(records.len(), 3);
    assert!(ds.recovery().added_newline);
    drop(ds);
    assert_eq!(fs::read(&j).unwrap(), bytes);
}

#[test]
fn corrupt_middle_line_is_an_error_naming_the_line() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    drop(three(&dir));
    let mut lines = journal_lines(&dir);
    // Damage line 2 so that it is still valid JSON: only the CRC can tell.
    lines[1] = lines[1].replacen("\"order\":1", "\"order\":9", 1);
    fs::write(dir.join(JOURNAL_FILE), lines.join("\n") + "\n").unwrap();
    for err in [
        Dataset::resume(&dir).map(|_| ()).unwrap_err(),
        load(&dir).map(|_| ()).unwrap_err(),
    ] {
        match &err {
            StoreError::CorruptJournal { line, reason, .. } => {
                assert_eq!(*line, 2);
                assert!(reason.contains("CRC"), "{reason}");
            }
            other => panic!("expected CorruptJournal, got {other:?}"),
        }
        assert!(err.to_string().contains("line 2"), "{err}");
    }
    // Nothing was repaired or deleted.
    assert_eq!(journal_lines(&dir).len(), 3);
    assert!(dir.join("images/00001.exr").exists());
}

#[test]
fn damaged_image_is_dropped_and_remeasured() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    drop(three(&dir));
    let victim = dir.join("images/00001.exr");
    let mut bytes = fs::read(&victim).unwrap();
    let n = bytes.len();
    bytes[n - 10] ^= 0xff;
    fs::write(&victim, &bytes).unwrap();
    // A missing image is the same case.
    fs::remove_file(dir.join("images/00002.exr")).unwrap();

    let v = verify(&dir).unwrap();
    assert!(!v.is_ok());
    assert_eq!(v.damaged.len(), 2, "{v}");

    let (mut ds, _, records) = Dataset::resume(&dir).unwrap();
    assert_eq!(records.iter().map(|r| r.index).collect::<Vec<_>>(), vec![0]);
    let dropped: Vec<usize> = ds.recovery().dropped.iter().map(|d| d.0).collect();
    assert_eq!(dropped, vec![1, 2]);
    assert!(!victim.exists());
    assert_eq!(journal_lines(&dir).len(), 1, "journal rewritten without them");
    for i in [1, 2] {
        ds.store(rec(i, 10 + i, [15.0, 0.0], [0.0, 0.0]), Some(&gradient(16, 8, i)), None)
            .unwrap();
    }
    drop(ds);
    let (ds, _, records) = Dataset::resume(&dir).unwrap();
    assert!(ds.recovery().is_clean(), "{:?}", ds.recovery());
    assert_eq!(records.iter().map(|r| r.order).collect::<Vec<_>>(), vec![0, 11, 12]);
    assert!(verify(&dir).unwrap().is_clean());
}

#[test]
fn orphans_and_temp_files_are_removed() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    drop(three(&dir));
    fs::write(dir.join("images/00042.exr"), b"no journal line").unwrap();
    fs::write(dir.join("images/.tmp-999-00043.exr"), b"half written").unwrap();
    fs::write(dir.join(".tmp-999-manifest.json"), b"half").unwrap();
    fs::write(dir.join("images/README"), b"not ours").unwrap();
    let v = verify(&dir).unwrap();
    assert!(v.is_ok() && !v.is_clean());
    assert_eq!(v.orphans, vec![dir.join("images/00042.exr")]);
    assert_eq!(v.temp_files.len(), 2);

    let (ds, _, records) = Dataset::resume(&dir).unwrap();
    assert_eq!(records.len(), 3);
    assert_eq!(ds.recovery().orphans_removed, vec![dir.join("images/00042.exr")]);
    assert_eq!(ds.recovery().temp_removed.len(), 2);
    assert!(!dir.join("images/00042.exr").exists());
    assert!(!dir.join("images/.tmp-999-00043.exr").exists());
    assert!(
        dir.join("images/README").exists(),
        "files the store did not name are kept"
    );
    drop(ds);
    assert!(verify(&dir).unwrap().is_clean());
}

#[test]
fn missing_journal_is_refused_not_treated_as_empty() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    drop(three(&dir));
    fs::remove_file(dir.join(JOURNAL_FILE)).unwrap();
    // Treating it as empty would delete every image as an orphan.
    let e = Dataset::resume(&dir).map(|_| ()).unwrap_err();
    assert!(matches!(e, StoreError::NotADataset { .. }), "{e}");
    assert!(e.to_string().contains("journal"), "{e}");
    assert_eq!(fs::read_dir(dir.join("images")).unwrap().count(), 3);
    assert!(matches!(verify(&dir).unwrap_err(), StoreError::NotADataset { .. }));
}

#[test]
fn duplicate_journal_entries_keep_the_first() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    let mut ds = three(&dir);
    // store() itself refuses a second record for an index, leaving everything as is.
    let err = ds
        .store(rec(1, 9, [0.0, 0.0], [0.0, 0.0]), Some(&gradient(16, 8, 9)), None)
        .unwrap_err();
    assert!(matches!(err, StoreError::DuplicateIndex { index: 1, .. }), "{err}");
    drop(ds);
    assert_eq!(journal_lines(&dir).len(), 3);
    // A duplicate line written by other means: the first is kept.
    let lines = journal_lines(&dir);
    let mut dup = journal::decode_line::<MeasurementRecord>(lines[1].as_bytes()).unwrap();
    dup.order = 99;
    let mut f = OpenOptions::new().append(true).open(dir.join(JOURNAL_FILE)).unwrap();
    f.write_all(&journal::encode_line(&dup).unwrap()).unwrap();
    drop(f);
    let (ds, _, records) = Dataset::resume(&dir).unwrap();
    assert_eq!(ds.recovery().duplicates, vec![1]);
    assert_eq!(records.iter().map(|r| r.order).collect::<Vec<_>>(), vec![0, 1, 2]);
    drop(ds);
    assert_eq!(journal_lines(&dir).len(), 3);
}

#[test]
fn create_refuses_existing_directories() {
    let tmp = tempfile::tempdir().unwrap();
    // A foreign non-empty directory: refused, with and without force, and untouched.
    let foreign = tmp.path().join("foreign");
    fs::create_dir(&foreign).unwrap();
    fs::write(foreign.join("thesis.tex"), b"precious").unwrap();
    let e = Dataset::create(&foreign, &header(4, 4), false).unwrap_err();
    assert!(matches!(e, StoreError::NotEmpty { .. }), "{e}");
    assert!(e.to_string().contains("--force"), "{e}");
    let e = Dataset::create(&foreign, &header(4, 4), true).unwrap_err();
    assert!(matches!(e, StoreError::NotADataset { .. }), "{e}");
    assert!(e.to_string().contains("only replaces gonio datasets"), "{e}");
    assert!(foreign.join("thesis.tex").exists());

    // An empty existing directory is fine.
    let empty = tmp.path().join("empty");
    fs::create_dir(&empty).unwrap();
    drop(Dataset::create(&empty, &header(4, 4), false).unwrap());

    // An existing dataset: refused without force, replaced with it.
    let dir = tmp.path().join("ds");
    drop(three(&dir));
    let e = Dataset::create(&dir, &header(16, 8), false).unwrap_err();
    assert!(matches!(e, StoreError::NotEmpty { .. }), "{e}");
    assert_eq!(journal_lines(&dir).len(), 3);
    let ds = Dataset::create(&dir, &header(16, 8), true).unwrap();
    assert!(ds.records().is_empty());
    assert_eq!(fs::read_dir(dir.join("images")).unwrap().count(), 0);
    assert_eq!(journal_lines(&dir).len(), 0);
    // While it is open, nobody else may write it.
    let e = Dataset::resume(&dir).map(|_| ()).unwrap_err();
    assert!(matches!(e, StoreError::Locked { .. }), "{e}");
    let e = Dataset::create(&dir, &header(16, 8), true).map(|_| ()).unwrap_err();
    assert!(matches!(e, StoreError::Locked { .. }), "{e}");
    drop(ds);
    drop(Dataset::resume(&dir).unwrap());

    // A file is not a directory.
    let file = tmp.path().join("file");
    fs::write(&file, b"x").unwrap();
    assert!(matches!(
        Dataset::create(&file, &header(4, 4), true).unwrap_err(),
        StoreError::NotADataset { .. }
    ));
    // A header that is not a gonio header.
    let mut h = header(4, 4);
    h.format = "other".into();
    assert!(matches!(
        Dataset::create(&tmp.path().join("new"), &h, false).unwrap_err(),
        StoreError::InvalidHeader { .. }
    ));
}

#[test]
fn store_rejects_inconsistent_measurements() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    let mut ds = Dataset::create(&dir, &header(16, 8), false).unwrap();
    let wrong_size = gradient(8, 8, 0);
    for (r, img) in [
        (rec(0, 0, [0.0, 0.0], [0.0, 0.0]), None),
        (rec(1, 1, [0.0, 0.0], [0.0, 0.0]), Some(&wrong_size)),
        (skipped(2, 2, [0.0, 0.0]), Some(&wrong_size)),
    ] {
        let e = ds.store(r, img, None).unwrap_err();
        assert!(matches!(e, StoreError::InvalidMeasurement { .. }), "{e}");
    }
    drop(ds);
    assert!(journal_lines(&dir).is_empty());
    assert_eq!(fs::read_dir(dir.join("images")).unwrap().count(), 0);
}

#[test]
fn exr_round_trip_within_f16_precision() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("img.exr");
    let mut img = gradient(37, 23, 5);
    // Spread values over many octaves, including tiny ones and > 1.
    for (i, v) in img.data.iter_mut().enumerate() {
        *v *= [1e-4f32, 0.01, 1.0, 7.5][i % 4];
    }
    write_exr(&path, &img).unwrap();
    let back = read_exr(&path).unwrap();
    assert_close_f16(&img, &back);
    // Row 0 stays at the top: the over-exposed texel set at (0, 0) is still there.
    assert!(back.get(0, 0)[2] > 1.0 && back.get(0, img.height - 1)[2] <= 1.0);
    // Only the final file exists: no temporary left behind.
    let names: Vec<_> = fs::read_dir(tmp.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names, vec![std::ffi::OsString::from("img.exr")]);
    // The file really is compressed with the chosen method.
    let meta = exr::meta::MetaData::read_from_file(&path, false).unwrap();
    assert_eq!(meta.headers[0].compression, EXR_COMPRESSION);
}

#[test]
fn ubo2003_entry_names_follow_the_convention() {
    assert_eq!(
        entry_name(0, [15.0, 60.0], [75.0, 345.0]),
        "tv075_pv345/00000 tl015 pl060 tv075 pv345.jpg"
    );
    assert_eq!(
        entry_name(6560, [75.0, 345.0], [0.0, 0.0]),
        "tv000_pv000/06560 tl075 pl345 tv000 pv000.jpg"
    );
    // Rounding, azimuth wrap-around, and the pole's azimuth.
    assert_eq!(
        entry_name(12, [17.6, 359.7], [0.2, 90.0]),
        "tv000_pv000/00012 tl018 pl000 tv000 pv000.jpg"
    );
    assert_eq!(integer_angles([45.0, -10.0]), [45, 350]);
    // The reader takes the angles at fixed offsets from the end of the name.
    let n = entry_name(3, [15.0, 60.0], [75.0, 345.0]);
    let at = |a: usize, b: usize| n[n.len() - a..n.len() - b].parse::<u32>().unwrap();
    assert_eq!((at(25, 22), at(19, 16), at(13, 10), at(7, 4)), (15, 60, 75, 345));
}

#[test]
fn srgb_transfer_function() {
    assert_eq!(linear_to_srgb8(0.0), 0);
    assert_eq!(linear_to_srgb8(-1.0), 0);
    assert_eq!(linear_to_srgb8(f32::NAN), 0);
    assert_eq!(linear_to_srgb8(1.0), 255);
    assert_eq!(linear_to_srgb8(4.0), 255);
    // 18 % grey is sRGB 118; linear 0.5 is 188; the linear toe: 0.001 → 3.
    assert_eq!(linear_to_srgb8(0.18), 118);
    assert_eq!(linear_to_srgb8(0.5), 188);
    assert_eq!(linear_to_srgb8(0.001), 3);
}

#[test]
fn disk_full_and_read_only_errors_are_classified() {
    let dir = Path::new("/data/run1");
    let path = dir.join("images/00001.exr");
    let e = StoreError::io(
        "writing",
        &path,
        Some(dir),
        std::io::Error::from(std::io::ErrorKind::StorageFull),
    );
    assert!(e.is_disk_full(), "{e:?}");
    let msg = e.to_string();
    assert!(msg.contains("journal is consistent"), "{msg}");
    assert!(msg.contains("gonio acquire --resume /data/run1"), "{msg}");
    assert!(msg.contains("00001.exr"), "{msg}");
    // The raw errno as the kernel reports it.
    let e = StoreError::io("writing", &path, Some(dir), std::io::Error::from_raw_os_error(28));
    assert!(matches!(e, StoreError::DiskFull { .. }), "{e:?}");
    // Outside a dataset there is no resume to suggest.
    let e = StoreError::io("writing", &path, None, std::io::Error::from_raw_os_error(28));
    assert!(e.is_disk_full() && !e.to_string().contains("--resume"), "{e}");
    // Read-only file system and missing permission.
    for err in [
        std::io::Error::from_raw_os_error(30),
        std::io::Error::from(std::io::ErrorKind::PermissionDenied),
    ] {
        let e = StoreError::io("writing", &path, Some(dir), err);
        assert!(matches!(e, StoreError::ReadOnly { .. }), "{e:?}");
        assert!(
            e.to_string().contains("writable") && e.to_string().contains("00001.exr"),
            "{e}"
        );
    }
    let e = StoreError::io("writing", &path, Some(dir), std::io::Error::other("boom"));
    assert!(matches!(e, StoreError::Io { .. }), "{e:?}");
}

/// Writes a small synthetic dataset for the export tests: measured, substituted and
/// skipped records, non-square images.
fn synthetic_dataset(dir: &Path) -> (usize, usize) {
    let (w, h) = (40, 24);
    let mut ds = Dataset::create(dir, &header(w, h), false).unwrap();
    let mut order = 0;
    let dirs = [[0.0, 0.0], [15.0, 0.0], [15.0, 60.0], [75.0, 345.0]];
    // Light index li, view index vi over four Bonn directions (their canonical indices
    // in the 81-set: 0, 1, 3, 80).
    let canonical = [0usize, 1, 3, 80];
    for (vi, v) in dirs.iter().enumerate() {
        for (li, l) in dirs.iter().enumerate() {
            let index = canonical[vi] * 81 + canonical[li];
            let r = if li == vi && vi == 1 {
                skipped(index, order, *l)
            } else if li == vi {
                let mut r = rec(index, order, [l[0] + 3.0, l[1]], *v);
                r.status = MeasurementStatus::Substituted {
                    requested_light_deg: *l,
                    reason: "retro-reflection".into(),
                };
                r
            } else {
                rec(index, order, *l, *v)
            };
            let img = gradient(w, h, index);
            let is_skipped = matches!(r.status, MeasurementStatus::Skipped { .. });
            ds.store(r, if is_skipped { None } else { Some(&img) }, None).unwrap();
            order += 1;
        }
    }
    ds.finish(&serde_json::json!({})).unwrap();
    (w, h)
}

fn read_npy_f32(path: &Path) -> (Vec<usize>, Vec<f32>) {
    let bytes = fs::read(path).unwrap();
    let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let header = std::str::from_utf8(&bytes[10..10 + hlen]).unwrap();
    let shape_str = header.split("'shape': (").nth(1).unwrap().split(')').next().unwrap();
    let shape = shape_str
        .split(',')
        .filter(|s| !s.trim().is_empty())
        .map(|s| s.trim().parse().unwrap())
        .collect();
    let data = bytes[10 + hlen..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    (shape, data)
}

#[test]
fn exports_match_each_other_and_the_convention() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    let (w, h) = synthetic_dataset(&dir);
    let zip_path = tmp.path().join("out/ubo.zip");
    let npy_path = tmp.path().join("out/ref.npy");
    let zr = export_ubo2003(&dir, &zip_path).unwrap();
    let nr = export_npy(&dir, &npy_path).unwrap();
    assert_eq!((zr.entries, zr.substituted, zr.skipped), (15, 3, 1));
    assert_eq!((nr.entries, nr.substituted, nr.skipped), (15, 3, 1));
    assert_eq!(nr.sidecar.as_deref(), Some(npy_sidecar_path(&npy_path).as_path()));
    let leftovers: Vec<_> = fs::read_dir(tmp.path().join("out"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".tmp-"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");

    let (shape, data) = read_npy_f32(&npy_path);
    assert_eq!(shape, vec![15, h, w, 3]);
    let side: serde_json::Value = serde_json::from_slice(&fs::read(npy_sidecar_path(&npy_path)).unwrap()).unwrap();
    let entries = side["entries"].as_array().unwrap();
    let mut zip = zip::ZipArchive::new(fs::File::open(&zip_path).unwrap()).unwrap();
    let names: Vec<String> = zip.file_names().map(str::to_string).collect();
    assert_eq!(names.len(), 15);
    // Export order is canonical-index order: view (0,0) first, light (0,0) first; the
    // retro-reflection (0,0)/(0,0) is substituted with θ + 3.
    assert_eq!(entries[0]["entry"], "tv000_pv000/00000 tl003 pl000 tv000 pv000.jpg");
    assert_eq!(entries[1]["entry"], "tv000_pv000/00001 tl015 pl000 tv000 pv000.jpg");
    assert_eq!(entries[14]["entry"], "tv075_pv345/00014 tl078 pl345 tv075 pv345.jpg");
    // The skipped (15,0)/(15,0) pair is not exported under any name.
    assert!(!names.iter().any(|n| n.contains("tl015 pl000 tv015 pv000")));
    let frame = w * h * 3;
    let mut worst_mean = 0.0f64;
    for (i, e) in entries.iter().enumerate() {
        let name = e["entry"].as_str().unwrap();
        assert!(names.iter().any(|n| n == name), "{name}");
        let mut jpeg = Vec::new();
        zip.by_name(name).unwrap().read_to_end(&mut jpeg).unwrap();
        let dec = image::load_from_memory_with_format(&jpeg, image::ImageFormat::Jpeg)
            .unwrap()
            .into_rgb8();
        assert_eq!((dec.width() as usize, dec.height() as usize), (w, h));
        let reference = &data[i * frame..(i + 1) * frame];
        // The reference is what the encoder was given: re-derive it from the EXR.
        let rel = format!("images/{:05}.exr", e["index"].as_u64().unwrap());
        let srgb: Vec<f32> = read_exr(&dir.join(rel))
            .unwrap()
            .data
            .iter()
            .map(|&v| f32::from(linear_to_srgb8(v)))
            .collect();
        assert_eq!(reference, &srgb[..]);
        let mean = dec
            .as_raw()
            .iter()
            .zip(reference)
            .map(|(&a, &b)| (f64::from(a) - f64::from(b)).abs())
            .sum::<f64>()
            / frame as f64;
        worst_mean = worst_mean.max(mean);
    }
    // Same limit as tests/interop/check_ubo2003.py (measured ≈ 1.75/255 here).
    assert!(worst_mean <= 2.5, "JPEG mean abs error {worst_mean}/255");
}

#[test]
fn export_refuses_angle_collisions_and_damaged_images() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    let mut ds = Dataset::create(&dir, &header(8, 8), false).unwrap();
    ds.store(rec(1, 0, [15.0, 0.0], [0.0, 0.0]), Some(&gradient(8, 8, 0)), None)
        .unwrap();
    ds.store(rec(2, 1, [15.2, 0.4], [0.0, 0.0]), Some(&gradient(8, 8, 1)), None)
        .unwrap();
    drop(ds);
    let out = tmp.path().join("x.zip");
    let e = export_ubo2003(&dir, &out).unwrap_err();
    assert!(
        matches!(
            e,
            StoreError::ExportConflict {
                first: 1,
                second: 2,
                ..
            }
        ),
        "{e}"
    );
    assert!(!out.exists());

    let dir2 = tmp.path().join("ds2");
    drop(three(&dir2));
    fs::write(dir2.join("images/00001.exr"), b"garbage").unwrap();
    let e = export_npy(&dir2, &tmp.path().join("y.npy")).unwrap_err();
    assert!(matches!(e, StoreError::DamagedImage { index: 1, .. }), "{e}");
    assert!(!tmp.path().join("y.npy").exists());
    let left: Vec<_> = fs::read_dir(tmp.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".tmp-"))
        .collect();
    assert!(left.is_empty(), "{left:?}");
}

/// End to end with the public reader: runs `tests/interop/check_ubo2003.py` when
/// `GONIO_PYTHON` names a Python with `btf_extractor` 1.7.0 (see
/// `tests/interop/setup_python.sh`).
#[test]
fn ubo2003_interop_with_btf_extractor() {
    let Some(python) = std::env::var_os("GONIO_PYTHON") else {
        eprintln!(
            "SKIPPED ubo2003_interop_with_btf_extractor: set GONIO_PYTHON to a python with \
             btf-extractor 1.7.0 (tests/interop/setup_python.sh creates one)"
        );
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    synthetic_dataset(&dir);
    let zip_path = tmp.path().join("ubo.zip");
    let npy_path = tmp.path().join("ref.npy");
    export_ubo2003(&dir, &zip_path).unwrap();
    export_npy(&dir, &npy_path).unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/interop/check_ubo2003.py");
    let out = std::process::Command::new(python)
        .arg(&script)
        .arg(&zip_path)
        .arg(&npy_path)
        .output()
        .expect("running GONIO_PYTHON");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    eprintln!("{stdout}{stderr}");
    assert!(out.status.success(), "check_ubo2003.py failed:\n{stdout}\n{stderr}");
    assert!(stdout.contains("ubo2003 interop: 15 images"), "{stdout}");

    // The check must be able to fail: swap R and B in one reference image (what a
    // BGR/RGB mix-up would look like) and expect a non-zero exit naming that entry.
    let mut bytes = fs::read(&npy_path).unwrap();
    let start = 10 + u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let (w, h) = (40, 24);
    let img7 = start + 7 * w * h * 3 * 4;
    for px in bytes[img7..img7 + w * h * 3 * 4].chunks_exact_mut(12) {
        let (r, rest) = px.split_at_mut(4);
        r.swap_with_slice(&mut rest[4..8]);
    }
    fs::write(&npy_path, &bytes).unwrap();
    let out = std::process::Command::new(std::env::var_os("GONIO_PYTHON").unwrap())
        .arg(&script)
        .arg(&zip_path)
        .arg(&npy_path)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "a channel swap went unnoticed: {stderr}");
    assert!(stderr.contains("/00007 "), "{stderr}");
}

/// Measures EXR write time and size per compression on a 256 × 256 sensor-like image.
/// `cargo test -p gonio --release --lib store::tests::bench_compressions -- --ignored --nocapture`
#[test]
#[ignore = "benchmark; run explicitly in release mode"]
fn bench_compressions() {
    use exr::prelude::Compression;
    let (w, h) = (256, 256);
    // Smooth shading (a lit, slightly textured sample) plus the shot noise of a 12-bit
    // sensor (σ = √DN), from a small deterministic LCG; at mid and at low exposure.
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut noise = || {
        let mut s = 0.0;
        for _ in 0..4 {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            s += (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5;
        }
        s * 1.73
    };
    let mut images = Vec::new();
    for (label, level) in [("mid exposure", 0.35f32), ("dark (grazing)", 0.03)] {
        let mut img = RgbImage::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let shade = level * (1.0 + 0.7 * ((x as f32 / 19.0).sin() * (y as f32 / 23.0).cos()));
                let c = [shade, shade * 0.8, shade * 0.6];
                let px = c.map(|v: f32| (v + noise() * (v * 4095.0).sqrt() / 4095.0).max(0.0));
                img.set(x, y, px);
            }
        }
        images.push((label, img));
    }
    let p = Path::new("bench");
    for (label, img) in &images {
        println!("{label}:");
        for (name, c) in [
            ("none", Compression::Uncompressed),
            ("RLE", Compression::RLE),
            ("ZIPS (1 line)", Compression::ZIP1),
            ("ZIP (16 lines)", Compression::ZIP16),
            ("PIZ", Compression::PIZ),
            ("PXR24", Compression::PXR24),
        ] {
            let back = decode_exr(&exr_io::encode_exr_with(img, c, p).unwrap(), p).unwrap();
            assert_close_f16(img, &back);
            // Best of 5 runs of 20 (the machine is shared: the minimum is the cost).
            let mut best = f64::MAX;
            let mut size = 0;
            for _ in 0..5 {
                let t = std::time::Instant::now();
                for _ in 0..20 {
                    size = exr_io::encode_exr_with(img, c, p).unwrap().len();
                }
                best = best.min(t.elapsed().as_secs_f64() * 1000.0 / 20.0);
            }
            println!("{name:>15}: {best:6.2} ms/image, {:7.1} kB", size as f64 / 1000.0);
        }
    }
}

/// Regression (kill -9 campaign): a `create` killed before its manifest was written left a
/// directory that `--resume` refused (no manifest) and `--force` refused too ("not empty
/// and has no manifest.json"), so the operator had to delete it by hand. `--force` now
/// replaces exactly that skeleton, and still refuses anything else without a manifest.
#[test]
fn force_replaces_the_debris_of_an_interrupted_create() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    // What create leaves when killed just before writing the manifest.
    fs::create_dir_all(dir.join(IMAGES_DIR)).unwrap();
    fs::write(dir.join(JOURNAL_FILE), b"").unwrap();
    fs::write(dir.join(format!("{TMP_PREFIX}123-{MANIFEST_FILE}")), b"{\"format\":").unwrap();
    assert!(matches!(Dataset::resume(&dir), Err(StoreError::NotADataset { .. })));
    assert!(matches!(
        Dataset::create(&dir, &header(8, 8), false),
        Err(StoreError::NotEmpty { .. })
    ));
    let mut ds = Dataset::create(&dir, &header(8, 8), true).expect("--force replaces an interrupted create");
    ds.store(rec(0, 0, [0.0, 0.0], [30.0, 0.0]), Some(&gradient(8, 8, 0)), None)
        .unwrap();
    drop(ds);
    assert!(verify(&dir).unwrap().is_clean());

    // Anything more than that skeleton is still refused and left alone.
    for extra in ["notes.txt", "images/00001.exr"] {
        let d = tmp.path().join(format!("other-{}", extra.len()));
        fs::create_dir_all(d.join(IMAGES_DIR)).unwrap();
        fs::write(d.join(JOURNAL_FILE), b"").unwrap();
        fs::write(d.join(extra), b"keep me").unwrap();
        assert!(matches!(
            Dataset::create(&d, &header(8, 8), true),
            Err(StoreError::NotADataset { .. })
        ));
        assert_eq!(fs::read(d.join(extra)).unwrap(), b"keep me");
    }
    // A non-empty journal means measurements may be in it: refused.
    let d = tmp.path().join("journal-not-empty");
    fs::create_dir_all(d.join(IMAGES_DIR)).unwrap();
    fs::write(d.join(JOURNAL_FILE), b"{}\n").unwrap();
    assert!(matches!(
        Dataset::create(&d, &header(8, 8), true),
        Err(StoreError::NotADataset { .. })
    ));
}

fn reference_rec(mean: f64, t: f64) -> ReferenceRecord {
    ReferenceRecord {
        number: 0,
        run: 0,
        rig_time_s: t,
        duration_s: 5.0,
        stored_before: 0,
        after_index: None,
        pair_index: 0,
        light_deg: [0.0, 0.0],
        view_deg: [30.0, 0.0],
        exposure_s: 0.05,
        gain: 1.0,
        mean: [mean; 3],
        ratio: [1.0; 3],
        image: String::new(),
        image_sha256: String::new(),
        dark: String::new(),
        dark_sha256: String::new(),
    }
}

/// Drift references: stored after their files, numbered, placed in the journal, their
/// ratio against the first; resume removes a reference's files without a line and cuts a
/// torn line, numbers the next run; verify re-hashes them; the factors interpolate in rig
/// time between references of one run and hold across a run boundary.
#[test]
fn references_are_stored_resumed_verified_and_interpolated() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    let mut ds = three(&dir);
    let img = gradient(16, 8, 1);
    let dark = gradient(16, 8, 2);
    let a = ds.store_reference(reference_rec(0.5, 10.0), &img, &dark).unwrap();
    assert_eq!((a.number, a.run, a.stored_before, a.ratio), (0, 0, 3, [1.0; 3]));
    let b = ds.store_reference(reference_rec(0.55, 20.0), &img, &dark).unwrap();
    assert_eq!(b.number, 1);
    assert!((b.ratio[0] - 1.1).abs() < 1e-12 && (b.drift() - 0.1).abs() < 1e-12);
    drop(ds);
    // A reference killed between its files and its line, and a torn line.
    std::fs::copy(dir.join("reference/00001.exr"), dir.join("reference/00002.exr")).unwrap();
    std::fs::copy(
        dir.join("reference/00001-dark.exr"),
        dir.join("reference/00002-dark.exr"),
    )
    .unwrap();
    let mut f = OpenOptions::new().append(true).open(dir.join(REFERENCES_FILE)).unwrap();
    f.write_all(b"{\"crc\":\"0000").unwrap();
    drop(f);
    let v = verify(&dir).unwrap();
    assert_eq!(v.references_ok, 2);
    assert!(
        v.references_torn_line.is_some() && v.orphans.len() == 2 && v.is_ok(),
        "{v}"
    );
    let (mut ds, _, _) = Dataset::resume(&dir).unwrap();
    assert_eq!(ds.references().len(), 2);
    assert!(!dir.join("reference/00002.exr").exists() && !dir.join("reference/00002-dark.exr").exists());
    assert_eq!(ds.recovery().references_dropped.len(), 1);
    let c = ds.store_reference(reference_rec(0.5, 1.0), &img, &dark).unwrap();
    assert_eq!((c.number, c.run), (2, 1), "the resumed run numbers on");
    assert!(verify(&dir).unwrap().is_clean());
    assert_eq!(load_references(&dir).unwrap().len(), 3);

    // Factors: records at journal positions 0..3 lie before reference 0 (stored_before 3).
    let mut refs = load_references(&dir).unwrap();
    refs[0].stored_before = 1;
    refs[1].stored_before = 3;
    refs[2].stored_before = 3;
    let mut records: Vec<MeasurementRecord> = (0..4)
        .map(|i| {
            let mut r = rec(i, i, [0.0, 0.0], [0.0, 0.0]);
            r.image = Some(image_rel_path(i));
            r.rig_time_s = 5.0 * i as f64;
            r
        })
        .collect();
    records[1].rig_time_s = 15.0;
    let f = drift::factors(&records, &refs);
    assert_eq!(f[0].as_ref().unwrap().references, [0, 0], "before any: the first");
    let mid = f[1].as_ref().unwrap();
    assert_eq!(mid.references, [0, 1]);
    assert!((mid.weight - 0.5).abs() < 1e-12 && (mid.ratio[0] - 1.05).abs() < 1e-12);
    assert_eq!(f[3].as_ref().unwrap().references, [2, 2]);
}

/// A drift correction leaves a value clipped at the full scale as it is and counts it,
/// whether the factor would raise it or lower it; an unclipped value is scaled. Without a
/// clip level (given `off`, or a calibrated unit) every value is scaled.
#[test]
fn drift_correction_keeps_clipped_values() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    let mut ds = Dataset::create(&dir, &header(3, 1), false).unwrap();
    let dark = RgbImage::new(3, 1);
    let mut img = RgbImage::new(3, 1);
    img.set(0, 0, [1.0, 0.4, 0.2]);
    // A rounding step below the full scale (stored as f16: 1).
    img.set(1, 0, [0.999_9, 0.6, 0.9]);
    img.set(2, 0, [0.5, 0.5, 0.5]);
    // The lamp dimmed to 0.8 of the first reference: the factor raises values by 1.25.
    ds.store_reference(reference_rec(0.5, 0.0), &img, &dark).unwrap();
    ds.store_reference(reference_rec(0.4, 10.0), &img, &dark).unwrap();
    let mut r = rec(0, 0, [15.0, 0.0], [0.0, 0.0]);
    r.rig_time_s = 10.0; // at the second reference: its factor alone
    ds.store(r, Some(&img), None).unwrap();
    // Then brightened to 1.25: lowered by 0.8.
    ds.store_reference(reference_rec(0.625, 30.0), &img, &dark).unwrap();
    let mut r = rec(1, 1, [15.0, 60.0], [0.0, 0.0]);
    r.rig_time_s = 40.0;
    ds.store(r, Some(&img), None).unwrap();
    // Re-exposed at half the exposure and scaled back by 2: its full scale is 2.
    let mut r = rec(2, 2, [15.0, 120.0], [0.0, 0.0]);
    r.rig_time_s = 41.0;
    r.extra["exposure_scale"] = serde_json::json!(2.0);
    let mut twice = RgbImage::new(3, 1);
    twice.set(0, 0, [2.0, 1.0, 0.5]);
    ds.store(r, Some(&twice), None).unwrap();
    drop(ds);

    let out = tmp.path().join("corrected");
    let rep = drift::correct(&dir, &out, false, drift::Clip::Auto).unwrap();
    assert_eq!((rep.clip_level, rep.clipped_kept), (Some(1.0), 5), "{rep:?}");
    let read = |i: usize| read_exr(&out.join(image_rel_path(i))).unwrap();
    // Within the f16 storage's rounding (11 significant bits).
    let close = |a: [f32; 3], b: [f32; 3]| a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-3 * y.abs().max(1.0));
    let (up, down) = (read(0), read(1));
    assert_eq!(up.get(0, 0)[0], 1.0, "a clipped value is not raised");
    assert_eq!(up.get(1, 0)[0], 1.0);
    assert!(close(up.get(0, 0), [1.0, 0.5, 0.25]), "{:?}", up.get(0, 0));
    assert!(close(up.get(1, 0), [1.0, 0.75, 1.125]), "{:?}", up.get(1, 0));
    assert!(close(up.get(2, 0), [0.625; 3]), "{:?}", up.get(2, 0));
    assert_eq!(down.get(0, 0)[0], 1.0, "nor lowered out of the full scale");
    assert!(close(down.get(2, 0), [0.4; 3]), "{:?}", down.get(2, 0));
    assert!(close(read(2).get(0, 0), [2.0, 0.8, 0.4]), "{:?}", read(2).get(0, 0));
    let (_, recs) = load(&out).unwrap();
    assert_eq!(recs[0].extra["drift_correction"]["clipped_kept"], 2);
    assert!(verify(&out).unwrap().is_clean());

    // Off: every value scaled, the clipped one too.
    let rep = drift::correct(&dir, &out, true, drift::Clip::Off).unwrap();
    assert_eq!((rep.clip_level, rep.clipped_kept), (None, 0));
    assert!(close(read(0).get(0, 0), [1.25, 0.5, 0.25]));
    // A calibrated unit has no single full scale: off by default; a given level applies.
    let mut h = header(3, 1);
    h.extra = serde_json::json!({"value_unit": "brdf_per_sr"});
    assert_eq!(drift::clip_level(&h, drift::Clip::Auto).0, None);
    assert_eq!(drift::clip_level(&h, drift::Clip::Level(2.0)).0, Some(2.0));
    assert_eq!(drift::clip_level(&header(3, 1), drift::Clip::Auto).0, Some(1.0));
    // A record's level moves with its values: × a re-exposure's scale, ÷ the lamp's
    // output correction.
    let mut r = rec(0, 0, [0.0, 0.0], [0.0, 0.0]);
    assert_eq!(drift::record_clip_level(1.0, &r), 1.0);
    r.extra["exposure_scale"] = serde_json::json!(2.0);
    assert_eq!(drift::record_clip_level(1.0, &r), 2.0);
    r.lamp = Some(LampRecord {
        voltage_v: 12.0,
        current_a: 8.0,
        current_drift: 0.0,
        voltage_drift: 0.0,
        drift_warning: false,
        output_correction: Some(1.25),
    });
    assert_eq!(drift::record_clip_level(1.0, &r), 1.6);
}
