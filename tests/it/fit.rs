//! `gonio fit` end to end on simulator samples of known models (`tests/data/fit/`):
//! `gonio sim btf` renders each (8 × 8 texels, Fibonacci 12 × 12 pairs) and the white
//! standard over the same sweep; the fit, calibrated by the white standard, recovers the
//! truth's parameters; the wrong family is reported worse; the per-texel fit finds both
//! materials of a checker and reports its ratio and PSNR; bad inputs are refused naming
//! the input.
//!
//! Tolerances, against the exact in-family fit of `fit::tests` (1 %): here the fit uses
//! the sweep's nominal directions while a texel 26 mm off the centre of the 60 mm sample
//! sees the camera (1 m) and lamp (1.2 m) up to 1.5° away from them. For a cosine lobe of
//! exponent n a direction error δ changes the lobe by about n·δ²/2 (1.4 % at n = 40,
//! δ = 1.5°), and the averaged highlight is that much wider: 5 % on the exponent and the
//! lobe's weight, 3 % on the diffuse albedo, 1° on the lobe's direction.

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

fn gonio(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_gonio")).args(args).output().unwrap()
}

fn ok(args: &[&str]) -> String {
    let o = gonio(args);
    assert!(
        o.status.success(),
        "gonio {args:?} failed:\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn refused(args: &[&str], needles: &[&str]) {
    let o = gonio(args);
    assert!(!o.status.success(), "gonio {args:?} should fail");
    let err = String::from_utf8_lossy(&o.stderr);
    for n in needles {
        assert!(err.contains(n), "gonio {args:?}: {n:?} not in\n{err}");
    }
}

fn sample(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/fit")
        .join(format!("{name}.toml"))
        .to_string_lossy()
        .into_owned()
}

/// The rendered datasets, once per test binary: (temp dir, white standard).
fn renders() -> &'static (tempfile::TempDir, PathBuf) {
    static R: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    R.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let render = |sample: &str, name: &str| {
            let out = dir.path().join(name);
            ok(&[
                "sim",
                "btf",
                "--sample",
                sample,
                "--sweep",
                "fibonacci:12",
                "--size",
                "8",
                "--out",
                out.to_str().unwrap(),
            ]);
            out
        };
        let white = render("white-standard", "white");
        for s in ["lafortune", "cook-torrance", "rough-conductor", "lafortune-checker"] {
            render(&sample(s), s);
        }
        (dir, white)
    })
}

fn fit(name: &str, model: &str, extra: &[&str]) -> Value {
    let (dir, white) = renders();
    let ds = dir.path().join(name);
    let mut args = vec![
        "fit",
        ds.to_str().unwrap(),
        "--model",
        model,
        "--white",
        white.to_str().unwrap(),
        "--json",
    ];
    args.extend_from_slice(extra);
    serde_json::from_str(&ok(&args)).unwrap()
}

fn param(v: &Value, name: &str) -> f64 {
    v["fit"]["params"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p[0] == name)
        .unwrap_or_else(|| panic!("{name} in {}", v["fit"]["params"]))[1]
        .as_f64()
        .unwrap()
}

fn close(got: f64, want: f64, rel: f64, what: &str) {
    assert!(
        (got - want).abs() <= rel * want.abs(),
        "{what}: got {got}, want {want} ±{:.0} %",
        rel * 100.0
    );
}

#[test]
fn lafortune_sample_parameters_are_recovered() {
    let v = fit("lafortune", "lafortune", &[]);
    close(param(&v, "kd.r"), 0.25, 0.03, "kd.r");
    close(param(&v, "kd.g"), 0.18, 0.03, "kd.g");
    close(param(&v, "kd.b"), 0.10, 0.03, "kd.b");
    close(param(&v, "lobes[0].exponent"), 40.0, 0.05, "exponent");
    close(param(&v, "lobes[0].ks.g"), 0.3, 0.05, "ks");
    let g = param(&v, "lobes[0].gamma_rad").to_degrees();
    assert!((g - 135.0).abs() < 1.0, "γ {g}°");
}

#[test]
fn cook_torrance_sample_is_fitted_best_by_its_family() {
    let right = fit("cook-torrance", "cook-torrance", &[]);
    close(param(&right, "lobes[0].m"), 0.2, 0.05, "m");
    close(param(&right, "fresnel.eta"), 1.5, 0.05, "eta");
    close(param(&right, "kd.r"), 0.3, 0.03, "kd.r");
    let wrong = fit("cook-torrance", "lafortune", &[]);
    let (r, w) = (
        right["fit"]["rel_rms"].as_f64().unwrap(),
        wrong["fit"]["rel_rms"].as_f64().unwrap(),
    );
    assert!(w > 2.0 * r, "lafortune {w} vs cook-torrance {r}");
}

#[test]
fn rough_conductor_sample_is_fitted_best_by_its_family() {
    let right = fit("rough-conductor", "rough-conductor", &[]);
    close(param(&right, "alpha"), 0.2, 0.05, "alpha");
    let wrong = fit("rough-conductor", "ward", &[]);
    let (r, w) = (
        right["fit"]["rel_rms"].as_f64().unwrap(),
        wrong["fit"]["rel_rms"].as_f64().unwrap(),
    );
    assert!(w > 2.0 * r, "ward {w} vs rough-conductor {r}");
}

/// Per texel: each texel of the checker gets its own material's exponent (within 5 %), and
/// the SVBRDF is reported as a compression method with a ratio and a PSNR.
#[test]
fn per_texel_fit_finds_both_materials() {
    let (dir, _) = renders();
    let out = dir.path().join("checker-fit.json");
    let v = fit(
        "lafortune-checker",
        "lafortune",
        &["--per-texel", "--out", out.to_str().unwrap()],
    );
    let t = &v["per_texel"];
    assert_eq!(t["texels"], 64);
    let ratio = t["ratio"].as_f64().unwrap();
    let psnr = t["psnr_8bit_db"].as_f64().unwrap();
    // 144 pairs × 64 texels × 3 bytes raw against 64 × 8 f32 + 144 × 9 f32 gain planes
    // + 3 f32 geometry
    assert!(
        (ratio - 27648.0 / (64.0 * 8.0 * 4.0 + 144.0 * 9.0 * 4.0 + 12.0)).abs() < 1e-9,
        "{ratio}"
    );
    assert!(psnr > 40.0, "PSNR {psnr} dB");
    let full: Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let names: Vec<&str> = full["per_texel"]["parameter_names"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n.as_str().unwrap())
        .collect();
    let np = names.len();
    let ie = names.iter().position(|n| *n == "lobes[0].exponent").unwrap();
    let params = full["per_texel"]["parameters"].as_array().unwrap();
    let mut found = [false; 2];
    for t in 0..64 {
        let n = params[t * np + ie].as_f64().unwrap();
        if (n - 40.0).abs() <= 0.05 * 40.0 {
            found[0] = true;
        } else if (n - 12.0).abs() <= 0.05 * 12.0 {
            found[1] = true;
        } else {
            panic!("texel {t}: exponent {n} is neither material's");
        }
    }
    assert_eq!(found, [true, true]);
}

#[test]
fn bad_inputs_are_refused_naming_the_input() {
    let (dir, white) = renders();
    let ds = dir.path().join("lafortune");
    let (ds, white) = (ds.to_str().unwrap(), white.to_str().unwrap());
    refused(
        &["fit", ds, "--model", "phong", "--white", white],
        &["--model phong", "lafortune, ward"],
    );
    refused(
        &["fit", ds, "--model", "lafortune", "--lobes", "0", "--white", white],
        &["--lobes 0"],
    );
    refused(&["fit", ds, "--model", "lafortune"], &[ds, "--white"]);
    let not_ds = dir.path().join("empty-dir");
    std::fs::create_dir_all(&not_ds).unwrap();
    refused(
        &["fit", not_ds.to_str().unwrap(), "--model", "ward"],
        &["empty-dir", "not a gonio dataset"],
    );
    let csv = dir.path().join("bad.csv");
    std::fs::write(&csv, "theta_l,phi_l,theta_v,phi_v,r,g,b\n30,0,30,180,0.1,0.1\n").unwrap();
    refused(
        &["fit", csv.to_str().unwrap(), "--model", "ward"],
        &["bad.csv", "line 2", "7"],
    );
    refused(
        &["fit", ds, "--model", "ward", "--per-texel", "--white", white],
        &["--per-texel", "lafortune"],
    );
}
