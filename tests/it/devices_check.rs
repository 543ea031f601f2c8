//! `gonio devices check --rig FILE` (issue 31) against the emulated controllers over ptys:
//! the Zaber chain (every axis steps and comes back), the HMP lamp supply (`--no-move`:
//! identity and read-back), and a rig whose serial port does not exist (the report names
//! the port and the fix, and the exit code is 1).

use crate::common;

use gonio_simulator::emulate::{spawn_pty, EmulatorConfig, Protocol};
use std::path::Path;
use std::process::Output;

fn rig(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("devices/rigs").join(name)
}

fn check(rig_file: &str, env: (&str, &Path), extra: &[&str]) -> (Output, serde_json::Value) {
    let o = std::process::Command::new(common::bin())
        .args(["devices", "check", "--json", "--rig"])
        .arg(rig(rig_file))
        .args(extra)
        .env(env.0, env.1)
        .output()
        .unwrap();
    let report = serde_json::from_slice(&o.stdout).unwrap_or_else(|e| {
        panic!(
            "--json output is not JSON ({e}): {}\n{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        )
    });
    (o, report)
}

#[test]
fn every_axis_of_the_emulated_zaber_chain_answers_and_steps_back() {
    let mut cfg = EmulatorConfig::new(Protocol::Zaber, 4);
    cfg.range_deg = (-200.0, 200.0);
    let h = spawn_pty(cfg).unwrap();
    let (o, r) = check("emulated-zaber.toml", ("GONIO_ZABER_PORT", h.path()), &[]);
    assert!(o.status.success(), "{r:#}");
    assert_eq!(r["ok"], true, "{r:#}");
    let devices = r["devices"].as_array().unwrap();
    let names: Vec<&str> = devices.iter().map(|d| d["device"].as_str().unwrap()).collect();
    assert_eq!(
        names,
        [
            "axis turntable",
            "axis camera_arc",
            "axis light_base",
            "axis light_arc",
            "camera",
            "light"
        ]
    );
    for d in &devices[..4] {
        assert_eq!(d["answered"], true, "{d:#}");
        let id = d["identity"].as_str().unwrap();
        assert!(
            id.contains("99001") && id.contains("7.38"),
            "device id and firmware: {id}"
        );
        let reported = d["reported"].to_string();
        assert!(
            reported.contains("stepped to") && reported.contains("and back"),
            "{d:#}"
        );
    }
    let frame = devices[4]["reported"].to_string();
    assert!(frame.contains("frame 768×640") && frame.contains("mean"), "{frame}");
    let rx = h.received();
    for axis in 1..=4 {
        let moves = rx
            .iter()
            .filter(|l| l.starts_with(&format!("/1 {axis} ")) && l.contains("move abs"))
            .count();
        assert!(
            moves >= 2,
            "axis {axis} stepped and came back over the pty: {moves} moves"
        );
    }
    h.stop();
}

#[test]
fn no_move_asks_the_hmp_lamp_who_it_is_and_moves_nothing() {
    let h = spawn_pty(EmulatorConfig::new(Protocol::Hmp4040, 4)).unwrap();
    let (o, r) = check("emulated-hmp.toml", ("GONIO_LAMP_PORT", h.path()), &["--no-move"]);
    assert!(o.status.success(), "{r:#}");
    assert_eq!(
        (r["ok"].clone(), r["moved"].clone()),
        (true.into(), false.into()),
        "{r:#}"
    );
    let light = &r["devices"][5];
    assert_eq!(light["device"], "light");
    assert!(light["identity"].as_str().unwrap().contains("HMP4040"), "{light:#}");
    let reported = light["reported"].to_string();
    assert!(reported.contains(" V, ") && reported.contains("off"), "{light:#}");
    for d in &r["devices"].as_array().unwrap()[..4] {
        assert!(!d["reported"].to_string().contains("stepped"), "{d:#}");
    }
    h.stop();
}

#[test]
fn a_missing_serial_port_is_named_with_its_fix_and_exits_1() {
    let port = Path::new("/dev/gonio-no-such-port");
    let (o, r) = check("emulated-zaber.toml", ("GONIO_ZABER_PORT", port), &[]);
    assert_eq!(o.status.code(), Some(1), "{r:#}");
    assert_eq!(r["ok"], false);
    let row = &r["devices"][0];
    assert_eq!(row["answered"], false);
    assert!(
        row["failure"].as_str().unwrap().contains("/dev/gonio-no-such-port"),
        "{row:#}"
    );
    assert!(row["fix"].as_str().unwrap().contains("gonio devices list"), "{row:#}");
    // The table says the same to a person.
    let o = std::process::Command::new(common::bin())
        .args(["devices", "check", "--rig"])
        .arg(rig("emulated-zaber.toml"))
        .env("GONIO_ZABER_PORT", port)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        text.contains("FAILED") && text.contains("fix:") && text.contains("not ready"),
        "{text}"
    );
}

/// A rig file that names a backend this build lacks: the message names the cargo feature.
#[cfg(not(feature = "v4l2"))]
#[test]
fn a_compiled_out_camera_backend_names_the_feature_to_enable() {
    let (o, r) = check("v4l2-vivid.toml", ("GONIO_UNUSED", Path::new("")), &["--no-move"]);
    assert_eq!(o.status.code(), Some(1), "{r:#}");
    let row = &r["devices"][0];
    let failure = row["failure"].as_str().unwrap();
    assert!(
        failure.contains("`v4l2` is not in this build") && failure.contains("--features v4l2"),
        "{failure}"
    );
    assert!(row["fix"].as_str().unwrap().contains("--features v4l2"), "{row:#}");
}
