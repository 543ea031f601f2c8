//! The radiometric target end to end through the CLI: calibrate the white standard
//! on the default simulated rig, acquire the standard with `--calibration`, and check
//! π · BRDF = albedo within 1 % (mean over the sample) at every pair with θ_l, θ_v ≤ 60°.
//! A reduced set of Bonn directions keeps it short; the full 81 × 81 run is a command in
//! the report (`gonio acquire --sample white-standard --calibration …`).

use crate::common;

use common::{fresh_tmp, gonio};
use std::path::{Path, PathBuf};

const ALBEDO: f64 = 0.9;

fn tmp(name: &str) -> PathBuf {
    fresh_tmp("white", name)
}

fn calibrate(dir: &Path) -> serde_json::Value {
    let out = dir.join("cal");
    let o = gonio(&[
        "calibrate",
        "calibration/recipes/white-standard.toml",
        "--rig",
        "devices/rigs/default.toml",
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

#[test]
fn calibrated_acquisition_of_the_white_standard_gives_its_albedo() {
    let dir = tmp("target");
    let result = calibrate(&dir);
    let w = &result["white_standard"];
    let k_err: Vec<f64> = serde_json::from_value(w["k_error_percent"].clone()).unwrap();
    println!(
        "white standard: K error vs truth {k_err:?} %, residual RMS {:.5}, max {:.5}",
        w["residual_rms"], w["residual_max"]
    );
    assert!(k_err.iter().all(|e| e.abs() < 0.5), "K error {k_err:?}");
    assert!(w["residual_rms"].as_f64().unwrap() < 0.02, "{}", w["residual_rms"]);

    // Bonn directions from every ring, including the grazing 75° one (reported, no target).
    let sweep = dir.join("sweep.toml");
    std::fs::write(
        &sweep,
        "lights = [[0, 0], [15, 60], [30, 90], [45, 200], [60, 342], [75, 15]]\n\
         views = [[0, 0], [30, 330], [45, 100], [60, 36], [75, 180]]\n",
    )
    .unwrap();
    let ds = dir.join("ds");
    let cal = dir.join("cal");
    let o = gonio(&[
        "acquire",
        "--rig",
        "devices/rigs/default.toml",
        "--sample",
        "white-standard",
        "--sweep",
        sweep.to_str().unwrap(),
        "--size",
        "24x24",
        "--calibration",
        cal.to_str().unwrap(),
        "--out",
        ds.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(summary["value_unit"], "brdf_per_sr");
    assert_eq!(summary["calibration"], result["id"]);

    let (header, records) = gonio::store::load(&ds).unwrap();
    assert_eq!(header.calibration.as_deref(), result["id"].as_str());
    assert_eq!(header.extra["value_unit"], "brdf_per_sr");
    assert!(ds.join("calibration/white-standard.json").is_file());

    let (mut worst, mut worst_pair) = (0.0f64, String::new());
    let (mut worst_grazing, mut grazing_pair) = (0.0f64, String::new());
    let mut checked = 0;
    for r in &records {
        let Some(img) = &r.image else { continue };
        let img = gonio::store::read_exr(&ds.join(img)).unwrap();
        let n = (img.width * img.height) as f64;
        for c in 0..3 {
            let mean = img.data.iter().skip(c).step_by(3).map(|&v| v as f64).sum::<f64>() / n;
            let err = (std::f64::consts::PI * mean / ALBEDO - 1.0).abs();
            let pair = format!("light {:?} view {:?} channel {c}", r.light_deg, r.view_deg);
            if r.light_deg[0] <= 60.0 + 1e-9 && r.view_deg[0] <= 60.0 + 1e-9 {
                checked += 1;
                if err > worst {
                    (worst, worst_pair) = (err, pair);
                }
            } else if err > worst_grazing {
                (worst_grazing, grazing_pair) = (err, pair);
            }
        }
    }
    println!(
        "pairs with θ ≤ 60°: worst |π·BRDF/albedo − 1| = {:.4} % at {worst_pair} ({} channel checks)",
        100.0 * worst,
        checked
    );
    println!(
        "grazing pairs (θ = 75°): worst {:.4} % at {grazing_pair}",
        100.0 * worst_grazing
    );
    assert!(checked >= 3 * 12, "{checked} checks");
    assert!(worst < 0.01, "worst {worst} at {worst_pair}");

    // Stiff cases: a calibration made on another rig is refused, a missing directory is named.
    let o = gonio(&[
        "acquire",
        "--rig",
        "devices/rigs/gimbal.toml",
        "--sample",
        "white-standard",
        "--sweep",
        sweep.to_str().unwrap(),
        "--size",
        "8x8",
        "--calibration",
        cal.to_str().unwrap(),
        "--out",
        dir.join("other").to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("was made on rig `default`") && err.contains("gimbal"),
        "{err}"
    );
    assert!(!dir.join("other").exists(), "nothing created for a refused calibration");

    let missing = dir.join("no-such-cal");
    let o = gonio(&[
        "acquire",
        "--sample",
        "white-standard",
        "--size",
        "8x8",
        "--calibration",
        missing.to_str().unwrap(),
        "--out",
        dir.join("other2").to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("no-such-cal"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}
