//! The radiometric corrections applied in an acquisition, end to end through the CLI, on the
//! simulated radiometric rig (`devices/rigs/radiometric.toml`: non-linear response, colour
//! crosstalk, vignetting, per-frame noise):
//!
//! 1. the shipped dark → response → flat → colour recipes as they are (flat and colour read
//!    `cal/response`), then the white standard fitted on frames corrected with them
//!    (`white-standard.toml` with its `corrections = "cal"` line on);
//! 2. the white standard acquired with `--calibration` (all five) and, for comparison, with
//!    a white standard alone (made and applied without corrections);
//! 3. π · BRDF / albedo of the standard against 1 at every pair with θ_l, θ_v ≤ 60°: within
//!    1 % with the corrections (after an interrupted run resumed with `--resume`), clearly
//!    worse without;
//! 4. error against run time: the same with fewer dark and flat frames averaged;
//! 5. the colour target acquired with and without the colour matrix: π · BRDF of its 24
//!    patches against their albedos, within 0.01 with it, clearly worse without;
//! 6. a dark map made on a camera of another size is refused before anything is created.
//!
//! `cargo test -p gonio --test calibration_radiometric_apply -- --nocapture` prints the
//! figures.

use crate::common;

use common::{fresh_tmp, gonio, gonio_in, root};
use std::path::{Path, PathBuf};

const ALBEDO: f64 = 0.9;
const RIG: &str = "devices/rigs/radiometric.toml";

fn tmp(name: &str) -> PathBuf {
    fresh_tmp("radapply", name)
}

/// A copy of a shipped recipe with `edits` (each `from` must occur) written to `dir`.
fn recipe_copy(dir: &Path, name: &str, edits: &[(&str, String)]) -> PathBuf {
    let src = root().join("calibration/recipes").join(name);
    let mut text = std::fs::read_to_string(&src).unwrap();
    for (from, to) in edits {
        assert!(text.contains(from), "{} no longer contains `{from}`", src.display());
        text = text.replacen(from, to, 1);
    }
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

/// `gonio calibrate RECIPE --rig RIG --out OUT --json` run in `cwd` (where the recipe's
/// relative `response` and `corrections` paths resolve); `rig` is relative to the workspace.
fn calibrate(cwd: &Path, recipe: &Path, rig: &str, out: &Path) -> serde_json::Value {
    let rig = root().join(rig);
    let o = gonio_in(
        cwd,
        &[
            "calibrate",
            recipe.to_str().unwrap(),
            "--rig",
            rig.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--json",
        ],
    );
    assert!(
        o.status.success(),
        "{}: {}",
        recipe.display(),
        String::from_utf8_lossy(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).unwrap()
}

/// `gonio acquire --json` of `sample` on the radiometric rig at `size` texels with the
/// results in `cal`, into `ds`, over `sweep` (default: the built-in sweep).
fn acquire_output(sweep: Option<&Path>, sample: &str, size: &str, cal: &Path, ds: &Path) -> std::process::Output {
    let mut args = vec!["acquire", "--rig", RIG, "--sample", sample, "--size", size, "--json"];
    if let Some(sweep) = sweep {
        args.extend(["--sweep", sweep.to_str().unwrap()]);
    }
    args.extend(["--calibration", cal.to_str().unwrap(), "--out", ds.to_str().unwrap()]);
    gonio(&args)
}

/// [`acquire_output`] that must succeed; returns its `--json` summary.
fn acquire(sweep: &Path, sample: &str, size: &str, cal: &Path, ds: &Path) -> serde_json::Value {
    let o = acquire_output(Some(sweep), sample, size, cal, ds);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

/// An 8 × 8 acquisition of the white standard with the results in `cal` that must be
/// refused before `ds` is created; returns the error.
fn refused_acquire(cal: &Path, ds: &Path) -> String {
    let o = acquire_output(None, "white-standard", "8x8", cal, ds);
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!o.status.success(), "{err}");
    assert!(!ds.exists(), "no dataset for a refused calibration");
    err
}

/// What one acquisition of the white standard measured at the pairs with θ ≤ 60°.
struct WhiteErrors {
    summary: serde_json::Value,
    /// Worst |π · mean BRDF / albedo − 1| (mean over the sample, per channel) and where.
    worst_mean: f64,
    at: String,
    /// RMS of π · BRDF / albedo − 1 over every texel and channel (noise included).
    texel_rms: f64,
}

/// Acquire the white standard with the results in `cal`; with `resume`, the last five
/// journal lines are then dropped (as after a crash) and `--resume` measures them again
/// with the dataset's own calibration copies before the figures are taken.
fn acquire_white(dir: &Path, cal: &Path, tag: &str, resume: bool) -> WhiteErrors {
    let sweep = dir.join("sweep.toml");
    if !sweep.exists() {
        std::fs::write(
            &sweep,
            "lights = [[0, 0], [15, 60], [30, 90], [45, 200], [60, 342]]\n\
             views = [[0, 0], [30, 330], [45, 100], [60, 36]]\n",
        )
        .unwrap();
    }
    let ds = dir.join(format!("ds-{tag}"));
    let summary = acquire(&sweep, "white-standard", "24x24", cal, &ds);
    assert_eq!(summary["value_unit"], "brdf_per_sr");
    if resume {
        let journal = ds.join("journal.jsonl");
        let text = std::fs::read_to_string(&journal).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        std::fs::write(&journal, lines[..lines.len() - 5].join("\n") + "\n").unwrap();
        let o = gonio(&["acquire", "--json", "--resume", ds.to_str().unwrap()]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let resumed: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert!(resumed["stored_this_run"].as_u64().unwrap() >= 1, "{resumed}");
        assert_eq!(resumed["complete"], true);
        for key in ["corrections", "calibration", "value_unit"] {
            assert_eq!(resumed[key], summary[key], "--resume applies the same: {key}");
        }
    }
    let (_, records) = gonio::store::load(&ds).unwrap();
    let (mut worst, mut at, mut checked) = (0.0f64, String::new(), 0);
    let (mut sum2, mut count) = (0.0f64, 0usize);
    for r in &records {
        let Some(img) = &r.image else { continue };
        if r.light_deg[0] > 60.0 + 1e-9 || r.view_deg[0] > 60.0 + 1e-9 {
            continue;
        }
        let img = gonio::store::read_exr(&ds.join(img)).unwrap();
        let n = (img.width * img.height) as f64;
        for v in &img.data {
            sum2 += (std::f64::consts::PI * *v as f64 / ALBEDO - 1.0).powi(2);
            count += 1;
        }
        for c in 0..3 {
            let mean = img.data.iter().skip(c).step_by(3).map(|&v| v as f64).sum::<f64>() / n;
            let err = (std::f64::consts::PI * mean / ALBEDO - 1.0).abs();
            checked += 1;
            if err > worst {
                worst = err;
                at = format!("light {:?} view {:?} channel {c}", r.light_deg, r.view_deg);
            }
        }
        // every corrected measurement says how many pixels were saturated
        let corrected = summary["corrections"].as_array().is_some_and(|a| !a.is_empty());
        assert_eq!(
            r.extra.get("saturated_pixels").is_some(),
            corrected,
            "record {}: {}",
            r.index,
            r.extra
        );
    }
    assert!(checked >= 3 * 15, "{checked} channel checks");
    let _ = std::fs::remove_dir_all(&ds);
    WhiteErrors {
        summary,
        worst_mean: worst,
        at,
        texel_rms: (sum2 / count.max(1) as f64).sqrt(),
    }
}

/// The colour target's patch albedos (linear sRGB), row 0 at +y, column 0 at −x: the
/// `reference` of `calibration/recipes/colour.toml`, read from there.
fn patch_references() -> Vec<[f64; 3]> {
    let text = std::fs::read_to_string(root().join("calibration/recipes/colour.toml")).unwrap();
    let v: toml::Value = toml::from_str(&text).unwrap();
    serde_json::from_value(serde_json::to_value(&v["radiometric"]["patches"]["reference"]).unwrap()).unwrap()
}

/// Acquire the colour target with the results in `cal` (BRDF); returns the RMS and the
/// largest |π · BRDF − albedo| over the 24 patches' central 3 × 3 texels, every channel and
/// every pair.
fn acquire_colour(dir: &Path, cal: &Path, tag: &str) -> (f64, f64) {
    let sweep = dir.join("sweep-colour.toml");
    std::fs::write(
        &sweep,
        "lights = [[0, 0], [30, 90]]
views = [[0, 0], [30, 330]]
",
    )
    .unwrap();
    let ds = dir.join(format!("colour-{tag}"));
    acquire(&sweep, "colour-target", "60x60", cal, &ds);
    let refs = patch_references();
    let (_, records) = gonio::store::load(&ds).unwrap();
    let (mut sum2, mut n, mut worst) = (0.0f64, 0usize, 0.0f64);
    for r in &records {
        let Some(img) = &r.image else { continue };
        let img = gonio::store::read_exr(&ds.join(img)).unwrap();
        // 60 mm sample on 60 texels: 1 mm per texel, texel (i, j) centred at
        // (i + ½ − 30, 30 − j − ½) mm
        for (k, reference) in refs.iter().enumerate() {
            let (pi, pj) = ((k % 6) as f64, (k / 6) as f64);
            let (x0, y0) = ((pi + 0.5 - 3.0) * 7.5, (2.0 - pj - 0.5) * 7.5);
            let (ci, cj) = ((x0 + 30.0 - 0.5).round() as usize, (30.0 - y0 - 0.5).round() as usize);
            let mut mean = [0.0f64; 3];
            for j in cj - 1..=cj + 1 {
                for i in ci - 1..=ci + 1 {
                    for (c, m) in mean.iter_mut().enumerate() {
                        *m += img.data[(j * img.width + i) * 3 + c] as f64 / 9.0;
                    }
                }
            }
            for c in 0..3 {
                let e = std::f64::consts::PI * mean[c] - reference[c];
                sum2 += e * e;
                n += 1;
                worst = worst.max(e.abs());
            }
        }
    }
    // 3 of the 4 pairs: light = view = (0, 0) is blocked by the camera and skipped
    assert!(n >= 3 * 24 * 3, "{n}");
    let _ = std::fs::remove_dir_all(&ds);
    ((sum2 / n as f64).sqrt(), worst)
}

/// Copy `kinds` (subdirectories `KIND/calibration.json`) of `from` into a new directory.
fn cal_set(dir: &Path, name: &str, from: &[(&Path, &str)]) -> PathBuf {
    let d = dir.join(name);
    for (src, kind) in from {
        std::fs::create_dir_all(d.join(kind)).unwrap();
        std::fs::copy(
            src.join(kind).join("calibration.json"),
            d.join(kind).join("calibration.json"),
        )
        .unwrap();
    }
    d
}

/// `white-standard.toml` with its `corrections` line switched on, naming `corrections`.
fn white_recipe(dir: &Path, corrections: &Path) -> PathBuf {
    recipe_copy(
        dir,
        "white-standard.toml",
        &[(
            "# corrections = \"cal\"\n",
            format!("corrections = \"{}\"\n", corrections.display()),
        )],
    )
}

/// The ids of the raw corrections a white-standard result was fitted on.
fn white_corrections(w: &serde_json::Value) -> Vec<String> {
    w["white_standard"]["corrections"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap().to_string())
        .collect()
}

#[test]
fn radiometric_corrections_make_the_white_standard_read_its_albedo() {
    let t0 = std::time::Instant::now();
    let dir = tmp("main");
    let cal = dir.join("cal");
    let shipped = |name: &str| root().join("calibration/recipes").join(name);

    // The documented chain with the shipped recipes, run in `dir`: flat.toml and colour.toml
    // read `cal/response/calibration.json` there; the white standard is fitted on frames
    // corrected with `cal`'s dark, response, flat and colour (its `corrections` line on).
    let dark = calibrate(&dir, &shipped("dark.toml"), RIG, &cal.join("dark"));
    let response = calibrate(&dir, &shipped("response.toml"), RIG, &cal.join("response"));
    let flat = calibrate(&dir, &shipped("flat.toml"), RIG, &cal.join("flat"));
    let colour = calibrate(&dir, &shipped("colour.toml"), RIG, &cal.join("colour"));
    let linearised = format!("response:{}", response["id"].as_str().unwrap());
    for (kind, r) in [("flat", &flat), ("colour", &colour)] {
        assert_eq!(r["radiometric"]["linearisation"], linearised.as_str(), "{kind}");
    }
    let white = calibrate(&dir, &white_recipe(&dir, Path::new("cal")), RIG, &cal.join("white"));
    assert_eq!(
        white_corrections(&white).len(),
        4,
        "white standard corrected with dark, response, flat, colour: {white}"
    );
    let full_resid = white["white_standard"]["residual_rms"].as_f64().unwrap();
    let full_capture_s = dark["rig_time_s"].as_f64().unwrap() + flat["rig_time_s"].as_f64().unwrap();
    let with = acquire_white(&dir, &cal, "with", true);
    let (summary, with_err, with_at) = (&with.summary, with.worst_mean, &with.at);
    assert_eq!(
        summary["corrections"],
        serde_json::json!(["response", "dark", "flat", "colour"]),
        "{summary}"
    );
    assert_eq!(
        summary["calibration"].as_str().unwrap().split(',').count(),
        5,
        "{summary}"
    );

    // Dark and flat with `frames` frames each (no effort tables), the shipped response and
    // colour, then the white standard on frames corrected with those; returns the directory
    // of the five results and the rig time of the dark and flat runs.
    let run_set = |frames: usize| -> (PathBuf, f64) {
        let sub = dir.join(format!("frames{frames}"));
        std::fs::create_dir_all(&sub).unwrap();
        let dark = recipe_copy(
            &sub,
            "dark.toml",
            &[
                ("frames = 16", format!("frames = {frames}")),
                ("effort = [2, 4, 8, 16]", "effort = []".into()),
            ],
        );
        let flat = recipe_copy(
            &sub,
            "flat.toml",
            &[
                ("frames = 8", format!("frames = {frames}")),
                ("effort = [1, 2, 4, 8]", "effort = []".into()),
            ],
        );
        let set = cal_set(&sub, "cal", &[(&cal, "response"), (&cal, "colour")]);
        let d = calibrate(&dir, &dark, RIG, &set.join("dark"));
        let f = calibrate(&dir, &flat, RIG, &set.join("flat"));
        let w = calibrate(&dir, &white_recipe(&sub, &set), RIG, &set.join("white"));
        let ids = white_corrections(&w);
        assert_eq!(ids.len(), 4, "{ids:?}");
        let capture_s = d["rig_time_s"].as_f64().unwrap() + f["rig_time_s"].as_f64().unwrap();
        (set, capture_s)
    };

    // Without: the white standard alone, made and applied on uncorrected values.
    let plain = dir.join("plain");
    let w0 = calibrate(&dir, &shipped("white-standard.toml"), RIG, &plain.join("white"));
    let without = acquire_white(&dir, &plain, "without", false);
    let (without_err, without_at) = (without.worst_mean, &without.at);
    assert_eq!(without.summary["corrections"], serde_json::json!([]));

    println!(
        "white standard on {RIG}, pairs with θ ≤ 60°, worst |π·BRDF/albedo − 1| (mean over the sample):\n  \
         shipped dark+response+flat+colour: {:.3} % at {with_at} (texel RMS {:.3} %, white fit residual RMS {:.4})\n  \
         white standard only:               {:.3} % at {without_at} (texel RMS {:.3} %, white fit residual RMS {:.4})",
        100.0 * with_err,
        100.0 * with.texel_rms,
        full_resid,
        100.0 * without_err,
        100.0 * without.texel_rms,
        w0["white_standard"]["residual_rms"].as_f64().unwrap(),
    );
    assert!(with_err < 0.01, "with corrections: {with_err} at {with_at}");
    assert!(
        without_err > 3.0 * with_err && without_err > 0.02,
        "the corrections must do measurable work: without {without_err}, with {with_err}"
    );

    // Error against run time: fewer dark and flat frames.
    // (Rig time of the dark and flat runs, homing and moves included.)
    println!("  dark/flat frames  rig_time_s  worst mean error  texel RMS   (θ ≤ 60°)");
    let mut rows = Vec::new();
    for frames in [1usize, 4] {
        let (set, capture_s) = run_set(frames);
        let e = acquire_white(&dir, &set, &format!("f{frames}"), false);
        rows.push((format!("{frames}/{frames}"), capture_s, e.worst_mean, e.texel_rms));
    }
    rows.push(("16/8 (shipped)".into(), full_capture_s, with_err, with.texel_rms));
    for (frames, capture_s, e, rms) in &rows {
        println!(
            "  {frames:>16}  {capture_s:>10.2}  {:>14.3} %  {:>7.3} %",
            100.0 * e,
            100.0 * rms
        );
        assert!(e.is_finite() && *e < 0.05 && rms.is_finite(), "{frames} frames: {e}");
    }

    // The colour matrix's work: on the neutral standard it changes nothing, on the colour
    // target it undoes the crosstalk. Without it (dark + response + flat, white standard
    // refitted on those) the patches keep the crosstalk's mixing.
    let nocolour = cal_set(&dir, "nocolour", &[(&cal, "dark"), (&cal, "response"), (&cal, "flat")]);
    calibrate(&dir, &white_recipe(&dir, &nocolour), RIG, &nocolour.join("white"));
    let (with_rms, with_max) = acquire_colour(&dir, &cal, "with");
    let (without_rms, without_max) = acquire_colour(&dir, &nocolour, "without");
    println!(
        "colour target, 24 patches × 3 pairs, |π·BRDF − albedo| (linear reflectance):\n  \
         with the colour matrix:    RMS {with_rms:.4}, max {with_max:.4}\n  \
         without (dark+resp+flat):  RMS {without_rms:.4}, max {without_max:.4}"
    );
    assert!(with_rms < 0.01, "colour RMS with the matrix {with_rms}");
    assert!(
        without_rms > 5.0 * with_rms,
        "the colour matrix must do measurable work: {without_rms} vs {with_rms}"
    );

    // A white standard fitted on corrected frames is refused without those corrections.
    let lone = cal_set(&dir, "lone", &[(&cal, "white")]);
    let err = refused_acquire(&lone, &dir.join("refused"));
    assert!(
        err.contains("white standard was fitted on frames corrected") && err.contains("corrections = "),
        "{err}"
    );
    println!("  test run time {:.1} s", t0.elapsed().as_secs_f64());
    let _ = std::fs::remove_dir_all(&dir);
}

/// A dark map made on a camera of another size is refused at load time, naming the file and
/// both sizes, and no dataset is created.
#[test]
fn a_dark_map_from_another_camera_size_is_refused() {
    let dir = tmp("size");
    let text = std::fs::read_to_string(root().join(RIG)).unwrap();
    let small = text
        .replacen("width = 768", "width = 192", 1)
        .replacen("height = 640", "height = 160", 1)
        .replacen("focal_length_px = 4300.0", "focal_length_px = 1075.0", 1);
    assert_ne!(small, text);
    let small_rig = dir.join("radiometric-small.toml");
    std::fs::write(&small_rig, small).unwrap();
    let dark = recipe_copy(&dir, "dark.toml", &[("frames = 16", "frames = 2".into())]);
    let cal = dir.join("cal");
    calibrate(&dir, &dark, small_rig.to_str().unwrap(), &cal.join("dark"));
    let err = refused_acquire(&cal, &dir.join("ds"));
    println!("refused: {err}");
    assert!(
        err.contains("dark/calibration.json")
            && err.contains("192×160")
            && err.contains("768×640")
            && err.contains("re-run"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
