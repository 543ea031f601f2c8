//! The lamp on a Rohde & Schwarz HMP supply: gonio's `hmp` light (gonio_devices::serial::hmp)
//! against the HMP4040 emulator (gonio_simulator::emulate::hmp) over real ptys, and whole
//! `gonio acquire` runs with the lamp on the emulator: every measurement records the lamp's
//! voltage and current, a drifting lamp warns and is counted, and a calibrated output
//! exponent corrects the stored values by exactly (I/I₀)^k.
//!
//! Run: `cargo test -p gonio --test it lamp_hmp:: -- --nocapture`.

use crate::common;

use gonio_devices::serial::hmp::{HmpConfig, HmpLight};
use gonio_devices::serial::Options;
use gonio_devices::{DeviceError, Light};
use gonio_simulator::emulate::hmp::LampLoad;
use gonio_simulator::emulate::{spawn_pty, EmulatorConfig, EmulatorHandle, FaultPlan, Protocol};
use std::path::{Path, PathBuf};

fn emulator(faults: &[&str], drift: f64) -> EmulatorHandle {
    let mut cfg = EmulatorConfig::new(Protocol::Hmp4040, 4).with_faults(FaultPlan::parse(faults).unwrap());
    cfg.lamp.drift = drift;
    spawn_pty(cfg).unwrap()
}

/// The `hmp` light on `h`'s pty with extra options (TOML inline-table body).
fn open(h: &EmulatorHandle, extra: &str) -> Result<HmpLight, gonio_devices::serial::SerialConfigError> {
    let text = format!(
        "port = \"{}\"\nvoltage = 12.0\ncurrent = 10.0\nsettle_s = 0\nreply_timeout_ms = 200\n{extra}",
        h.path().display()
    );
    let map: std::collections::BTreeMap<String, toml::Value> = toml::from_str(&text).unwrap();
    let cfg = HmpConfig::from_options(&Options::for_light(&map))?;
    HmpLight::open(cfg)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hmp_light_switches_and_measures_the_emulated_lamp() {
    let h = emulator(&[], 0.0);
    let l = open(&h, "channel = 3").unwrap();
    let idn = l.identity().await.unwrap();
    assert!(idn.starts_with("ROHDE&SCHWARZ,HMP4040,"), "{idn}");
    let load = LampLoad::default();
    for k in [1.0, 0.5, 0.25] {
        l.set(true, k).await.unwrap();
        let r = l.read_back().await.unwrap().unwrap();
        let (v, i) = load.operating_point(12.0 * k, 10.0, 1.0);
        assert!((r.voltage_v - v).abs() < 1e-3, "intensity {k}: {r:?} vs {v} V");
        assert!((r.current_a - i).abs() < 1e-4, "intensity {k}: {r:?} vs {i} A");
    }
    l.set(false, 0.0).await.unwrap();
    let r = l.read_back().await.unwrap().unwrap();
    assert_eq!((r.voltage_v, r.current_a), (0.0, 0.0));
    let rx = h.received();
    assert!(rx.iter().any(|c| c == "INST:NSEL 3"), "{rx:?}");
    assert!(rx.iter().any(|c| c == "APPL 6,10"), "{rx:?}");
    // every set command was checked in the error queue, and the queue stayed empty
    assert!(rx.iter().filter(|c| *c == "SYST:ERR?").count() >= 10);
    h.stop();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hmp_light_faults_end_in_retries_or_typed_errors() {
    // a garbled reply every 4th: retried, the values are right
    let h = emulator(&["garble:every=4"], 0.0);
    let l = open(&h, "retries = 3").unwrap();
    l.set(true, 1.0).await.unwrap();
    for _ in 0..5 {
        let r = l.read_back().await.unwrap().unwrap();
        assert!((r.current_a - 100.0 / 12.0).abs() < 1e-4, "{r:?}");
    }
    h.stop();
    common::fault_row("hmp: garble:every=4", 0, "retried, values exact");
    // every reply dropped from the 4th command on, no retries: a typed timeout naming the query
    let h = emulator(&["drop:every=1"], 0.0);
    let e = open(&h, "retries = 0").err().unwrap().to_string();
    assert!(e.contains("light.options.port") && e.contains("*IDN?"), "{e}");
    h.stop();
    // Commands: *IDN?, SYST:ERR? (open); INST:NSEL, SYST:ERR?, APPL, SYST:ERR?, OUTP:SEL,
    // SYST:ERR?, OUTP:GEN, SYST:ERR? (set); INST:NSEL, SYST:ERR?, MEAS:VOLT? (13th) …
    let h = emulator(&["drop:at=13"], 0.0);
    let l = open(&h, "retries = 0").unwrap();
    l.set(true, 1.0).await.unwrap();
    match l.read_back().await {
        Err(DeviceError::Timeout { command, .. }) => assert_eq!(command, "MEAS:VOLT?"),
        r => panic!("{r:?}"),
    }
    let r = l.read_back().await.unwrap().unwrap();
    assert!((r.current_a - 100.0 / 12.0).abs() < 1e-4, "{r:?}");
    h.stop();
    common::fault_row(
        "hmp: drop:at=13 (MEAS:VOLT?), retries = 0",
        0,
        "typed Timeout, next reading fine",
    );
    // a channel the rig file cannot have
    let h = emulator(&[], 0.0);
    let e = open(&h, "channel = 5").err().unwrap().to_string();
    assert!(e.contains("light.options.channel"), "{e}");
    h.stop();
}

/// The reduced scene's rig with its lamp on the emulated HMP (`GONIO_LAMP_PORT`) and extra
/// light options.
fn lamp_rig(dir: &Path, extra: &str) -> PathBuf {
    let (rig, _) = common::write_scene(dir);
    let text = std::fs::read_to_string(&rig).unwrap();
    let from = "[light]\nbackend = \"sim\"\n";
    assert!(text.contains(from), "the default rig's [light] table changed");
    let text = text.replacen(
        from,
        // No warm-up wait: the drift fault moves the current at every reading, and the
        // assertions below count the readings (`warm_up_waits_for_a_stable_current` tests it).
        &format!(
            "[light]\nbackend = \"hmp\"\noptions = {{ port = \"${{GONIO_LAMP_PORT}}\", voltage = 12.0, current = 10.0, settle_s = 0.05, warmup_timeout_s = 0{extra} }}\n"
        ),
        1,
    );
    let p = dir.join(format!("rig_hmp{}.toml", extra.len()));
    std::fs::write(&p, text).unwrap();
    p
}

struct Run {
    summary: serde_json::Value,
    stderr: String,
    /// Measured records in drive order.
    records: Vec<gonio::store::MeasurementRecord>,
    out: PathBuf,
}

fn acquire_with_lamp(dir: &Path, name: &str, drift: f64, extra: &str) -> Run {
    let (_, sweep) = common::write_scene(dir);
    let rig = lamp_rig(dir, extra);
    let h = emulator(&[], drift);
    let out = dir.join(name);
    let o = common::acquire_cmd(&rig, &sweep, &out)
        .stdout(std::process::Stdio::piped())
        .env("GONIO_LAMP_PORT", h.path())
        .output()
        .unwrap();
    h.stop();
    let stdout = String::from_utf8_lossy(&o.stdout).into_owned();
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(o.status.success(), "acquire failed: {stderr}\n{stdout}");
    let summary: serde_json::Value = serde_json::from_str(stdout.lines().last().unwrap_or("{}"))
        .or_else(|_| serde_json::from_str(&stdout))
        .unwrap_or_else(|e| panic!("--json output is not JSON ({e}): {stdout}"));
    let (_, mut records) = gonio::store::load(&out).unwrap();
    records.retain(|r| r.image.is_some());
    records.sort_by_key(|r| r.order);
    Run {
        summary,
        stderr,
        records,
        out,
    }
}

#[test]
fn acquisition_records_the_lamp_and_warns_when_it_drifts() {
    let dir = std::env::temp_dir().join(format!("gonio-lamp-hmp-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let load = LampLoad::default();
    let (v0, i0) = load.operating_point(12.0, 10.0, 1.0);

    // A steady lamp: every measurement carries V and I, nothing drifts, nothing corrected.
    let steady = acquire_with_lamp(&dir, "steady", 0.0, "");
    let n = steady.records.len();
    assert!(n >= 10, "{n} measurements");
    for r in &steady.records {
        let l = r
            .lamp
            .as_ref()
            .unwrap_or_else(|| panic!("measurement {} has no lamp record", r.index));
        assert!(
            (l.voltage_v - v0).abs() < 1e-3 && (l.current_a - i0).abs() < 1e-4,
            "{l:?}"
        );
        assert!(!l.drift_warning && l.output_correction.is_none(), "{l:?}");
    }
    assert!(
        steady.summary.get("lamp_drift_warnings").is_none(),
        "{}",
        steady.summary
    );
    assert!(steady.summary["lamp_identity"].as_str().unwrap().contains("HMP4040"));

    // The lamp's resistance grows 1 % per current reading: the reference is reading 0, the
    // m-th measurement (from 1) reads I₀/1.01^m, beyond 2 % from m = 3 (1/1.01² ≈ −1.97 %).
    let drift = acquire_with_lamp(&dir, "drift", 0.01, "");
    assert_eq!(drift.records.len(), n);
    for (k, r) in drift.records.iter().enumerate() {
        let l = r.lamp.as_ref().unwrap();
        let want = i0 / 1.01f64.powi(k as i32 + 1);
        assert!(
            (l.current_a - want).abs() < 1e-4,
            "measurement {k}: {} A vs {want} A",
            l.current_a
        );
        assert_eq!(l.drift_warning, k + 1 >= 3, "measurement {k}: {l:?}");
    }
    let warned = drift
        .records
        .iter()
        .filter(|r| r.lamp.as_ref().unwrap().drift_warning)
        .count();
    assert_eq!(drift.summary["lamp_drift_warnings"], serde_json::json!(warned));
    assert_eq!(warned, n - 2);
    assert!(drift.stderr.contains("lamp drift beyond 2.0 %"), "{}", drift.stderr);

    // The same drift with a calibrated exponent: each stored image is the uncorrected one
    // divided by (I/I₀)^k, and the record says by how much.
    let k = 3.0;
    let corrected = acquire_with_lamp(&dir, "corrected", 0.01, ", output_exponent = 3.0");
    for (a, b) in drift.records.iter().zip(&corrected.records) {
        assert_eq!(a.index, b.index);
        let l = b.lamp.as_ref().unwrap();
        let f = l.output_correction.unwrap();
        assert!((f - (1.0 + l.current_drift).powf(k)).abs() < 1e-12, "{l:?}");
        let ia = gonio::store::read_exr(&drift.out.join(a.image.as_ref().unwrap())).unwrap();
        let ib = gonio::store::read_exr(&corrected.out.join(b.image.as_ref().unwrap())).unwrap();
        let (sa, sb): (f64, f64) = (
            ia.data.iter().map(|x| *x as f64).sum(),
            ib.data.iter().map(|x| *x as f64).sum(),
        );
        assert!(
            (sb * f / sa - 1.0).abs() < 2e-3,
            "measurement {}: corrected sum {sb} × {f} vs {sa}",
            a.index
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Issue 31: before the first frame `Rig::prepare` waits until the lamp's current is
/// stable within `warmup_tolerance`; a lamp still changing at `warmup_timeout_s` fails
/// with the options to change. (Simulated axes and camera: the waits run on the virtual
/// clock.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn warm_up_waits_for_a_stable_current() {
    let sample = gonio_simulator::SampleSpec::resolve("leather").unwrap();
    for (drift, ok) in [(0.0, true), (0.001, true), (0.01, false)] {
        let h = emulator(&[], drift);
        let mut spec = gonio_devices::rig::RigSpec::default_rig();
        spec.light.backend = "hmp".into();
        let options = format!(
            "port = \"{}\"\nvoltage = 12.0\ncurrent = 10.0\nsettle_s = 0\nwarmup_tolerance = 0.005\nwarmup_timeout_s = 3",
            h.path().display()
        );
        spec.light.options = toml::from_str(&options).unwrap();
        let rig = gonio::rig::Rig::build(&spec, &sample, &gonio_simulator::SimOptions::default()).unwrap();
        let r = rig.prepare().await;
        match ok {
            true => assert!(r.is_ok(), "drift {drift}: {r:?}"),
            false => {
                let e = r.unwrap_err().to_string();
                assert!(
                    e.contains("lamp warm-up") && e.contains("warmup_timeout_s"),
                    "drift {drift}: {e}"
                );
            }
        }
        h.stop();
    }
}
