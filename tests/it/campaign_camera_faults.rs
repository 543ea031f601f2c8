//! Camera fault campaign: the simulated camera's injected faults (rig file
//! `camera.options.fault`, see `gonio_simulator::camera_faults`) against the engine's
//! capture policy (`gonio::rig::capture`), each in a reduced `gonio acquire` (6 × 6
//! pairs, 30 measured). Every fault must end in a bounded retry that succeeds (recorded in
//! the measurement's record), a flagged or re-exposed frame, or, when persistent, a typed
//! error naming the camera and the command, with a consistent journal and a `--resume`
//! that completes. "lost" counts the measurements of an uninterrupted run that the faulted
//! dataset lacks or holds with a different image (the simulator's noise is keyed by pose,
//! so a retried capture gives the very same image); it must be 0.
//!
//! Prints rows in the `faults:` table of `tests/run.sh` (same columns as campaign_faults).
//! Run: `cargo test --test campaign_camera_faults -- --nocapture --test-threads 1`.

use crate::common;

use gonio::store::{self, MeasurementRecord};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use common::{acquire, fault_row, resume, write_scene};

/// The reduced scene with extra camera options (TOML inline-table entries).
fn scene(dir: &Path, camera_options: &str) -> (PathBuf, PathBuf) {
    let (rig, sweep) = write_scene(dir);
    let text = std::fs::read_to_string(&rig).unwrap();
    let anchor = "seed = 1 }";
    assert!(text.contains(anchor), "the default rig's camera options changed");
    std::fs::write(
        &rig,
        text.replacen(anchor, &format!("seed = 1, {camera_options} }}"), 1),
    )
    .unwrap();
    (rig, sweep)
}

fn records(dir: &Path) -> BTreeMap<usize, MeasurementRecord> {
    store::load(dir)
        .map(|(_, r)| r.into_iter().map(|r| (r.index, r)).collect())
        .unwrap_or_default()
}

/// The uninterrupted run every faulted one is compared with (index → image hash).
fn baseline() -> &'static BTreeMap<usize, Option<String>> {
    static BASE: OnceLock<(tempfile::TempDir, BTreeMap<usize, Option<String>>)> = OnceLock::new();
    &BASE
        .get_or_init(|| {
            let tmp = tempfile::tempdir().unwrap();
            let (rig, sweep) = write_scene(tmp.path());
            let dir = tmp.path().join("ds");
            let out = acquire(&rig, &sweep, &dir);
            assert!(
                out.status.success(),
                "baseline: {}",
                String::from_utf8_lossy(&out.stderr)
            );
            let base: BTreeMap<_, _> = records(&dir).into_iter().map(|(i, r)| (i, r.image_sha256)).collect();
            assert_eq!(base.len(), 36, "baseline must hold 36 records");
            (tmp, base)
        })
        .1
}

/// Measurements of the baseline missing from `dir` or stored with another image, except
/// those in `changed_ok` (frames the policy stored on purpose as they were: saturated).
fn lost(dir: &Path, changed_ok: &[usize]) -> usize {
    let got = records(dir);
    baseline()
        .iter()
        .filter(|(i, sha)| match got.get(*i) {
            None => true,
            Some(r) => &r.image_sha256 != *sha && !changed_ok.contains(*i),
        })
        .count()
}

/// A clean, complete dataset of 36 records and 30 images.
fn assert_clean(dir: &Path, what: &str) {
    let rep = store::verify(dir).unwrap_or_else(|e| panic!("{what}: verify failed: {e}"));
    assert!(
        rep.is_clean() && rep.complete && rep.records == 36 && rep.images_ok == 30,
        "{what}: dataset not clean and complete: {rep}"
    );
}

/// Records whose `extra` has `key`.
fn with_extra<'a>(recs: &'a BTreeMap<usize, MeasurementRecord>, key: &str) -> Vec<&'a MeasurementRecord> {
    recs.values().filter(|r| r.extra.get(key).is_some()).collect()
}

/// A transient fault: the run completes; the faulted captures were retried (the record
/// says so with `fault_words` in its fault list); every image equals the baseline's.
fn transient(fault: &str, options: &str, fault_words: &str, min_retried: usize) {
    let tmp = tempfile::tempdir().unwrap();
    let (rig, sweep) = scene(tmp.path(), options);
    let dir = tmp.path().join("ds");
    let out = acquire(&rig, &sweep, &dir);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{fault}: the run failed: {err}");
    assert_clean(&dir, fault);
    let recs = records(&dir);
    let retried: Vec<_> = with_extra(&recs, "capture_retries")
        .into_iter()
        .filter(|r| r.extra["capture_faults"].to_string().contains(fault_words))
        .collect();
    assert!(
        retried.len() >= min_retried,
        "{fault}: expected ≥ {min_retried} records retried for `{fault_words}`, got {}",
        retried.len()
    );
    let lost = lost(&dir, &[]);
    let first = retried[0];
    fault_row(
        fault,
        lost,
        &format!(
            "bounded retry succeeded: {} measurement(s) retried (e.g. #{}: {} retry, `{}`); complete 36/36, images identical to the uninterrupted run",
            retried.len(),
            first.index,
            first.extra["capture_retries"],
            truncate(first.extra["capture_faults"][0].as_str().unwrap_or(""), 90),
        ),
    );
    assert_eq!(lost, 0, "{fault}: {lost} measurements lost or changed");
}

fn truncate(s: &str, n: usize) -> String {
    if s.chars().count() <= n {
        s.into()
    } else {
        format!("{}…", s.chars().take(n).collect::<String>())
    }
}

#[test]
fn camera_timeout_is_retried() {
    transient(
        "camera timeout (capture hangs, sim at=5)",
        r#"fault = "timeout:at=5", capture_timeout_s = 3"#,
        "timed out",
        1,
    );
}

#[test]
fn dropped_frames_are_retried() {
    transient(
        "dropped frames (sim every=7)",
        r#"fault = "drop:every=7""#,
        "frame dropped",
        3,
    );
}

#[test]
fn stale_frames_are_discarded() {
    transient(
        "stale frames (previous frame again, sim every=6)",
        r#"fault = "stale:every=6""#,
        "stale frame",
        3,
    );
}

#[test]
fn saturated_frame_is_flagged() {
    let fault = "saturated frame, policy flag (sim at=8)";
    let tmp = tempfile::tempdir().unwrap();
    let (rig, sweep) = scene(tmp.path(), r#"fault = "saturate:at=8""#);
    let dir = tmp.path().join("ds");
    let out = acquire(&rig, &sweep, &dir);
    assert!(
        out.status.success(),
        "{fault}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_clean(&dir, fault);
    let recs = records(&dir);
    let flagged = with_extra(&recs, "saturated");
    assert_eq!(flagged.len(), 1, "{fault}: exactly the injected frame must be flagged");
    let f = flagged[0];
    assert_eq!(f.extra["saturated_fraction"].as_f64(), Some(1.0));
    assert_ne!(
        baseline()[&f.index],
        f.image_sha256,
        "{fault}: the flagged image should be the saturated one"
    );
    let lost = lost(&dir, &[f.index]);
    fault_row(
        fault,
        lost,
        &format!(
            "stored as captured, record #{} flagged saturated (fraction 1.0); complete 36/36, other 29 images identical",
            f.index
        ),
    );
    assert_eq!(lost, 0);
}

#[test]
fn saturated_frame_is_reexposed() {
    let fault = "saturated frame, policy reexpose (sim at=8)";
    let tmp = tempfile::tempdir().unwrap();
    let (rig, sweep) = scene(tmp.path(), r#"fault = "saturate:at=8", saturation = "reexpose""#);
    let dir = tmp.path().join("ds");
    let out = acquire(&rig, &sweep, &dir);
    assert!(
        out.status.success(),
        "{fault}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_clean(&dir, fault);
    let recs = records(&dir);
    assert!(
        with_extra(&recs, "saturated").is_empty(),
        "{fault}: nothing may stay saturated"
    );
    let re = with_extra(&recs, "reexposures");
    assert_eq!(re.len(), 1, "{fault}: exactly the injected frame must be re-exposed");
    let r = re[0];
    assert_eq!(r.extra["reexposures"].as_u64(), Some(1));
    assert_eq!(r.extra["exposure_scale"].as_f64(), Some(2.0));
    let nominal = recs
        .values()
        .find(|x| x.image.is_some() && x.index != r.index)
        .unwrap()
        .exposure_s;
    assert!(
        (r.exposure_s - nominal / 2.0).abs() < 1e-12,
        "{fault}: exposure {}",
        r.exposure_s
    );
    // The re-exposed image has other noise than the baseline's, so it is not compared by hash.
    let lost = lost(&dir, &[r.index]);
    fault_row(
        fault,
        lost,
        &format!(
            "re-captured at {} s (nominal {nominal} s), stored scaled ×2, record #{} says so; complete 36/36",
            r.exposure_s, r.index
        ),
    );
    assert_eq!(lost, 0);
}

#[test]
fn persistent_timeout_fails_then_resume_completes() {
    let fault = "persistent camera timeout (sim at=25,count=5; 3 attempts)";
    let tmp = tempfile::tempdir().unwrap();
    let (rig, sweep) = scene(
        tmp.path(),
        r#"fault = "timeout:at=25,count=5", capture_timeout_s = 2, capture_retries = 2"#,
    );
    let dir = tmp.path().join("ds");
    let out = acquire(&rig, &sweep, &dir);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    // The error lines only (the log lines before them are the camera's warnings).
    let last = err
        .lines()
        .skip_while(|l| !l.starts_with("error"))
        .filter(|l| !l.trim().is_empty())
        .collect::<Vec<_>>()
        .join(" | ");
    assert!(!out.status.success(), "{fault}: the run succeeded");
    for word in ["sim-camera", "`capture`", "timed out", "after 3 attempt"] {
        assert!(err.contains(word), "{fault}: the error does not say `{word}`: {last}");
    }
    let rep = store::verify(&dir).unwrap();
    assert!(
        rep.damaged.is_empty() && rep.duplicates.is_empty() && !rep.complete,
        "{fault}: journal inconsistent after the fault: {rep}"
    );
    let before: BTreeMap<usize, Option<String>> = records(&dir).into_iter().map(|(i, r)| (i, r.image_sha256)).collect();
    // A resume is a new camera session (the capture counter starts again), like a
    // power-cycled camera: the remaining 6 measurements never reach capture 25.
    let r = resume(&dir);
    assert_eq!(
        r.status.code(),
        Some(0),
        "{fault}: resume: {}",
        String::from_utf8_lossy(&r.stderr)
    );
    assert_clean(&dir, fault);
    let after = records(&dir);
    let dropped = before
        .iter()
        .filter(|(i, sha)| after.get(*i).map(|r| &r.image_sha256) != Some(*sha))
        .count();
    assert_eq!(dropped, 0, "{fault}: the resume changed stored measurements");
    let lost = lost(&dir, &[]);
    fault_row(
        fault,
        lost,
        &format!(
            "exit {:?}, {}; {} records stored before, resume completed 36/36",
            out.status.code(),
            truncate(&last, 260),
            before.len()
        ),
    );
    assert_eq!(lost, 0);
}

#[test]
fn bad_fault_spec_is_refused_with_the_key() {
    let tmp = tempfile::tempdir().unwrap();
    let (rig, sweep) = scene(tmp.path(), r#"fault = "melt:at=1""#);
    let out = acquire(&rig, &sweep, &tmp.path().join("ds"));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("camera.options.fault") && err.contains("melt"),
        "the error must name the key and the value: {err}"
    );
}
