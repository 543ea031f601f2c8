//! HDR acquisition end to end on the reduced scene (36 pairs, 192×160 camera, 32² texels)
//! with the `brushed-metal` sample: the bracket and its merge are recorded per
//! measurement; limits and a camera that ignores the requested exposure end a bracket with
//! the reason recorded; kill -9 during brackets and `--resume` give the same bytes as an
//! uninterrupted run (a measurement is redone whole, never half a bracket).

use crate::common;

use gonio::store::{self, MeasurementRecord};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use common::{acquire_cmd, resume, write_scene};

/// The reduced scene; `camera_options` are added to the camera's options, `hdr` appended
/// as the rig file's `[hdr]` section body (empty: none).
fn scene(dir: &Path, camera_options: &str, hdr: &str) -> (PathBuf, PathBuf) {
    let (rig, sweep) = write_scene(dir);
    let mut text = std::fs::read_to_string(&rig).unwrap();
    if !camera_options.is_empty() {
        text = text.replacen("seed = 1 }", &format!("seed = 1, {camera_options} }}"), 1);
    }
    if !hdr.is_empty() {
        text.push_str(&format!("\n[hdr]\n{hdr}\n"));
    }
    std::fs::write(&rig, text).unwrap();
    (rig, sweep)
}

fn acquire(rig: &Path, sweep: &Path, out: &Path, extra: &[&str]) -> Command {
    let mut c = acquire_cmd(rig, sweep, out);
    c.args(["--sample", "brushed-metal"]).args(extra);
    c
}

fn measured(dir: &Path) -> Vec<MeasurementRecord> {
    let (_, recs) = store::load(dir).unwrap();
    recs.into_iter().filter(|r| r.image.is_some()).collect()
}

fn hdr_of(r: &MeasurementRecord) -> &serde_json::Value {
    r.extra
        .get("hdr")
        .unwrap_or_else(|| panic!("measurement {} has no hdr record", r.index))
}

fn exposures(r: &MeasurementRecord) -> Vec<f64> {
    serde_json::from_value(hdr_of(r)["exposures_s"].clone()).unwrap()
}

fn reasons(r: &MeasurementRecord) -> Vec<String> {
    serde_json::from_value(hdr_of(r)["reasons"].clone()).unwrap()
}

fn run_ok(mut c: Command, what: &str) {
    let out = c.output().unwrap();
    assert!(out.status.success(), "{what}: {}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn auto_brackets_only_what_saturates_and_records_the_merge() {
    let tmp = tempfile::tempdir().unwrap();
    let (rig, sweep) = scene(tmp.path(), "", "");
    let dir = tmp.path().join("ds");
    run_ok(acquire(&rig, &sweep, &dir, &["--hdr", "auto"]), "auto");
    let recs = measured(&dir);
    assert_eq!(recs.len(), 30);
    let mut shorter = 0;
    for r in &recs {
        let e = exposures(r);
        let h = hdr_of(r);
        assert_eq!(e[0], 0.05, "measurement {}: the base exposure comes first", r.index);
        let contributed: Vec<usize> = serde_json::from_value(h["pixels_contributed"].clone()).unwrap();
        assert_eq!(contributed.len(), e.len());
        assert!(h["dynamic_range_stops"].as_f64().unwrap() > 0.0);
        if e.iter().any(|&t| t < 0.05) {
            shorter += 1;
        }
        // Nothing stays clipped silently: clipped pixels come with a reason.
        if h["clipped_pixels"].as_u64().unwrap() > 0 {
            assert!(
                !reasons(r).is_empty(),
                "measurement {}: clipped without a reason",
                r.index
            );
        }
    }
    // The glossy sample's highlights need shorter exposures, but not on every pair.
    assert!(
        shorter > 0 && shorter < recs.len(),
        "{shorter} of {} pairs got shorter exposures",
        recs.len()
    );
}

#[test]
fn limits_end_the_bracket_with_the_reason_recorded() {
    let tmp = tempfile::tempdir().unwrap();
    // No exposure shorter or longer than the base allowed, an unreachable SNR floor.
    let (rig, sweep) = scene(
        tmp.path(),
        "",
        "mode = \"auto\"\nmin_exposure_s = 0.05\nmax_exposure_s = 0.05\nsnr_floor = 1000.0",
    );
    let dir = tmp.path().join("ds");
    run_ok(acquire(&rig, &sweep, &dir, &[]), "limits");
    let recs = measured(&dir);
    let mut saturated = 0;
    for r in &recs {
        assert_eq!(exposures(r), vec![0.05], "measurement {}", r.index);
        let why = reasons(r).join("; ");
        assert!(why.contains("longest exposure"), "measurement {}: {why}", r.index);
        if why.contains("saturated at the shortest exposure") {
            saturated += 1;
        }
    }
    assert!(saturated > 0, "the highlights must report the shortest-exposure limit");
}

#[test]
fn a_camera_that_ignores_the_exposure_ends_each_bracket_with_the_reason() {
    let tmp = tempfile::tempdir().unwrap();
    let (rig, sweep) = scene(tmp.path(), "fault = \"exposure:every=1\"", "");
    let dir = tmp.path().join("ds");
    run_ok(acquire(&rig, &sweep, &dir, &["--hdr", "3"]), "exposure fault");
    let recs = measured(&dir);
    assert_eq!(recs.len(), 30);
    for r in &recs {
        // Only the base frame: the camera applied none of the requested exposures.
        assert_eq!(exposures(r), vec![0.05], "measurement {}", r.index);
        let why = reasons(r).join("; ");
        assert!(
            why.contains("camera applied 0.05 s for the requested 0.00625 s"),
            "measurement {}: {why}",
            r.index
        );
    }
}

#[test]
fn kill_9_during_brackets_then_resume_gives_the_uninterrupted_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let (rig, sweep) = scene(tmp.path(), "", "");
    let reference = tmp.path().join("ref");
    run_ok(acquire(&rig, &sweep, &reference, &["--hdr", "5"]), "reference");
    let want: Vec<(usize, Option<String>)> = measured(&reference)
        .into_iter()
        .map(|r| (r.index, r.image_sha256))
        .collect();
    for (trial, delay_ms) in [150u64, 400, 900].into_iter().enumerate() {
        let dir = tmp.path().join(format!("kill{trial}"));
        let mut child = acquire(&rig, &sweep, &dir, &["--hdr", "5"]).spawn().unwrap();
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_millis(delay_ms) && child.try_wait().unwrap().is_none() {
            std::thread::sleep(Duration::from_millis(5));
        }
        let _ = child.kill(); // SIGKILL
        let _ = child.wait();
        if !dir.join(store::MANIFEST_FILE).exists() {
            continue; // killed before the dataset existed: nothing to resume
        }
        let mut tries = 0;
        loop {
            let out = resume(&dir);
            if out.status.success() {
                break;
            }
            tries += 1;
            assert!(tries < 3, "trial {trial}: {}", String::from_utf8_lossy(&out.stderr));
        }
        let got: Vec<(usize, Option<String>)> = measured(&dir).into_iter().map(|r| (r.index, r.image_sha256)).collect();
        let mut got_sorted = got.clone();
        got_sorted.sort();
        let mut want_sorted = want.clone();
        want_sorted.sort();
        assert_eq!(got_sorted, want_sorted, "trial {trial} (kill after {delay_ms} ms)");
    }
}
