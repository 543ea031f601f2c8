//! Light-geometry calibration end to end on the simulated rigs: the simulator renders a
//! near-mirror lit by the lamp where it really is (`[sim_misalignment]`), the recipe locates
//! the lamp's reflection in every frame and fits the lamp axes' zero offsets, and applying
//! the estimate makes the planner's commanded light directions the true ones. Degenerate
//! pose sets and unusable frames are refused with their diagnosis.

use crate::common;

use common::run_recipe;
use gonio::calibrate::apply::{AppliedCalibration, LoadedResult};
use gonio::calibrate::recipe::PoseSpec;
use gonio::calibrate::rig_geometry::direction_errors;
use gonio::calibrate::{CalibrateError, Recipe};
use gonio_calibration::light_geometry::{HighlightError, LightGeometryError};
use gonio_devices::rig::RigSpec;
use std::path::Path;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn lamp_rig() -> RigSpec {
    RigSpec::load(&root().join("devices/rigs/misaligned-lamp.toml")).unwrap()
}

fn recipe() -> Recipe {
    Recipe::load(&root().join("calibration/recipes/light-geometry.toml")).unwrap()
}

/// Write a result where `gonio acquire --calibration DIR` would find it and load it back
/// the way acquire does.
fn saved(result: &gonio::calibrate::CalibrationResult, dir: &Path) -> LoadedResult {
    std::fs::create_dir_all(dir).unwrap();
    let file = dir.join("calibration.json");
    std::fs::write(&file, serde_json::to_vec_pretty(result).unwrap()).unwrap();
    LoadedResult::read(&file).unwrap()
}

/// Tolerance on each offset (degrees). What limits the estimate is the highlight's
/// localisation bias (lobe asymmetry along the plane of incidence, ≈ −0.02 px on average,
/// growing with θ), which is the same sign at every pose and so is not averaged away; the
/// measured errors are ≈ 0.0002° (light_base) and ≈ 0.0016° (light_arc).
const TOL_DEG: f64 = 0.005;

#[test]
fn lamp_offsets_are_recovered_and_applying_them_corrects_the_light_directions() {
    let spec = lamp_rig();
    let truth = spec.sim_misalignment.clone().expect("the rig file has a truth");
    let out = run_recipe(&recipe(), &spec).unwrap();
    let r = out.result.light_geometry.as_ref().expect("light-geometry result");
    let fit = &r.fit;
    println!(
        "light-geometry: {} poses, RMS residual {:.4} px (zero offsets {:.4} px), condition {:.3}",
        fit.poses, fit.rms_px, fit.initial_rms_px, fit.condition
    );
    assert_eq!(fit.poses, 12);
    assert!(fit.rms_px < 0.05, "highlight residual {} px", fit.rms_px);
    assert!(
        fit.initial_rms_px > 2.0,
        "zero offsets must not already fit: {}",
        fit.initial_rms_px
    );
    let errors = r.errors.as_ref().unwrap();
    assert_eq!(errors.len(), 2, "{errors:?}");
    for e in errors {
        println!(
            "light-geometry: {:<24} estimate {:+.5}° truth {:+.5}° error {:+.2e}° σ {:.1e}°",
            e.name, e.estimate_deg, e.truth_deg, e.error_deg, e.sigma_deg
        );
        let axis = e.name.strip_prefix("zero_offset.").unwrap();
        assert_eq!(
            e.truth_deg, truth.axis_zero_offset_deg[axis],
            "truth read from the rig file"
        );
        assert!(e.error_deg.abs() < TOL_DEG, "{e:?}");
        assert!(
            e.sigma_deg.is_finite() && e.sigma_deg > 0.0 && e.sigma_deg < TOL_DEG,
            "{e:?}"
        );
    }
    let loc = r.localisation.as_ref().unwrap();
    println!(
        "light-geometry: localisation mean ({:+.4}, {:+.4}) px, RMS {:.4} px, max {:.4} px",
        loc.mean_px[0], loc.mean_px[1], loc.rms_px, loc.max_px
    );
    assert!(loc.rms_px < 0.05 && loc.max_px < 0.1, "{loc:?}");
    for h in &r.highlights {
        println!(
            "light-geometry: {:<40} error {:+.4?} px, other locator − this {:+.4?} px",
            h.label,
            h.error_px.unwrap(),
            h.locator_shift_px
        );
    }
    println!("light-geometry: systematic (other locator) {:?}°", fit.systematic_deg);
    assert!(
        r.highlights.iter().all(|h| h.peak > 0.1 && h.peak < 0.9),
        "exposure: highlights neither faint nor saturated"
    );
    // commanded light directions: off by the offsets before, close after
    let (before, after) = (
        r.directions_before.as_ref().unwrap(),
        r.directions_after.as_ref().unwrap(),
    );
    println!(
        "light-geometry: light direction error over {} Bonn pairs: max {:.4}° mean {:.4}° before, max {:.5}° mean {:.5}° after",
        after.pairs, before.light_max_deg, before.light_mean_deg, after.light_max_deg, after.light_mean_deg
    );
    assert!(
        before.pairs > 6000 && after.pairs == before.pairs,
        "{before:?} {after:?}"
    );
    assert!(before.light_max_deg > 0.3, "{before:?}");
    assert!(after.light_max_deg < TOL_DEG, "{after:?}");
    let u = &r.direction_uncertainty;
    println!(
        "light-geometry: over {} Bonn pairs, light sigma max {:.6}° mean {:.6}°, true error max {:.5}°, \
         worst error / sigma {:?}, beyond 3 sigma {:?}",
        u.pairs,
        u.light_sigma_max_deg,
        u.light_sigma_mean_deg,
        after.light_max_deg,
        u.light_max_error_over_sigma,
        u.light_beyond_3_sigma_fraction
    );
    assert_eq!(u.pairs, after.pairs);
    assert!(u.light_sigma_max_deg > 0.0 && u.light_sigma_max_deg < TOL_DEG, "{u:?}");
    // With the systematic term (the other locator's answer) the σ bounds the true error:
    // without it the error was 10σ on every pair (the centroid bias no residual shows).
    let s = fit
        .systematic_deg
        .as_ref()
        .expect("both locators located every highlight");
    assert!(s.iter().any(|x| x.abs() > 1e-4), "the lobe is asymmetric: {s:?}");
    assert!(
        u.light_max_error_over_sigma.unwrap() < 3.0 && u.light_beyond_3_sigma_fraction == Some(0.0),
        "{u:?}"
    );
    assert!(
        before.light_max_deg / after.light_max_deg > 50.0,
        "{before:?} {after:?}"
    );
    // error against effort: a row per pose count from 3 to 12, each fitted
    assert_eq!(r.effort.len(), 10);
    for row in &r.effort {
        println!(
            "light-geometry: effort {:2} poses  capture {:6.1} s  fit {:.2} ms  max param error {:.5}°",
            row.poses,
            row.capture_s,
            1e3 * row.fit_s,
            row.max_parameter_error_deg.unwrap_or(f64::NAN)
        );
        assert!(row.failure.is_none(), "{row:?}");
        assert!(row.max_parameter_error_deg.unwrap() < TOL_DEG, "{row:?}");
    }
    // the same through what `gonio acquire --calibration DIR` loads and applies
    let dir = std::env::temp_dir().join(format!("gonio-light-geometry-{}", std::process::id()));
    let loaded = saved(&out.result, &dir.join("light"));
    let (applied, skipped) = AppliedCalibration::from_results(&[loaded]).unwrap();
    assert!(skipped.is_empty(), "{skipped:?}");
    assert_eq!(applied.ids, vec![out.result.id.clone()]);
    let mut corrected = spec.clone();
    corrected.sim_misalignment = None;
    applied.correct_rig(&mut corrected);
    let check = direction_errors(&corrected, &spec.simulated_truth());
    assert!((check.light_max_deg - after.light_max_deg).abs() < 1e-12);
    std::fs::remove_dir_all(&dir).ok();
    assert_eq!(out.result.kind, "light-geometry");
}

/// A rig whose camera AND lamp are misaligned (misaligned.toml plus lamp offsets): the
/// rig-geometry calibration first (camera axes and mount), its `[alignment]` put into the rig
/// file, then the light-geometry calibration on that rig; both results applied together
/// correct view and light directions.
#[test]
fn rig_and_light_geometry_combine() {
    let mut both = RigSpec::load(&root().join("devices/rigs/misaligned.toml")).unwrap();
    let t = both.sim_misalignment.as_mut().unwrap();
    t.axis_zero_offset_deg.insert("light_base".into(), -0.35);
    t.axis_zero_offset_deg.insert("light_arc".into(), 0.25);
    // Without the camera's calibration the highlights cannot be explained by lamp offsets
    // alone: refused, not absorbed into the lamp's estimate.
    let e = run_recipe(&recipe(), &both).err().expect("refused");
    println!("light-geometry on an uncalibrated camera: {e}");
    assert!(
        matches!(
            &e,
            CalibrateError::LightGeometry {
                cause: LightGeometryError::PoorFit { rms_px, .. },
                ..
            } if *rms_px > 0.5
        ),
        "{e}"
    );
    let mut rg = Recipe::load(&root().join("calibration/recipes/rig-geometry.toml")).unwrap();
    rg.poses.truncate(8);
    let rg_out = run_recipe(&rg, &both).unwrap();
    // what the operator does: the rig-geometry estimate into the rig file's [alignment]
    let mut calibrated = both.clone();
    rg_out.result.rig_geometry.as_ref().unwrap().apply(&mut calibrated);
    let lg_out = run_recipe(&recipe(), &calibrated).unwrap();
    let lg = lg_out.result.light_geometry.as_ref().unwrap();
    assert!(
        lg.camera_alignment.is_some(),
        "the camera pose came from the calibrated rig"
    );
    for e in lg.errors.as_ref().unwrap() {
        println!(
            "light-geometry after rig-geometry: {:<24} error {:+.2e}°",
            e.name, e.error_deg
        );
        // the camera's residual error (≈ 0.01° from the rig-geometry fit) adds to the lamp's
        assert!(e.error_deg.abs() < 0.02, "{e:?}");
    }
    let dir = std::env::temp_dir().join(format!("gonio-light-rig-geometry-{}", std::process::id()));
    let results = [
        saved(&rg_out.result, &dir.join("rig")),
        saved(&lg_out.result, &dir.join("light")),
    ];
    let (applied, _) = AppliedCalibration::from_results(&results).unwrap();
    let mut nominal = both.clone();
    nominal.sim_misalignment = None;
    let before = direction_errors(&nominal, &both.simulated_truth());
    applied.correct_rig(&mut nominal);
    let a = nominal.alignment.as_ref().unwrap();
    assert_eq!(
        a.axis_zero_offset_deg.len(),
        4,
        "camera axes from one, lamp axes from the other: {a:?}"
    );
    let after = direction_errors(&nominal, &both.simulated_truth());
    println!(
        "rig+light geometry: view max {:.4}° → {:.5}°, light max {:.4}° → {:.5}°",
        before.view_max_deg, after.view_max_deg, before.light_max_deg, after.light_max_deg
    );
    assert!(before.light_max_deg > 0.3 && before.view_max_deg > 0.25, "{before:?}");
    assert!(after.view_max_deg < 0.02 && after.light_max_deg < 0.02, "{after:?}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn degenerate_pose_sets_are_refused_before_the_rig_moves() {
    // The lamp at the pole: its azimuth axis spins it about itself and moves no highlight.
    let mut r = recipe();
    r.poses = [0.0, 120.0, 240.0]
        .into_iter()
        .map(|phi| PoseSpec {
            view: [12.0, phi],
            light: Some([0.0, 0.0]),
        })
        .collect();
    let e = run_recipe(&r, &lamp_rig()).err().expect("refused");
    println!("light-geometry refused: {e}");
    match &e {
        CalibrateError::LightGeometry {
            cause: LightGeometryError::Undetermined { parameters, hint, .. },
            ..
        } => {
            assert_eq!(parameters, &vec!["zero_offset.light_base".to_string()], "{e}");
            assert!(hint.contains("pole"), "{e}");
        }
        other => panic!("expected an undetermined design, got {other}"),
    }
    // A lamp 90° away from the mirror direction: its reflection is off the sample.
    let mut r = recipe();
    r.poses.truncate(4);
    r.poses[2].light = Some([50.0, 290.0]);
    let e = run_recipe(&r, &lamp_rig()).err().expect("refused");
    println!("light-geometry refused: {e}");
    assert!(
        matches!(&e, CalibrateError::LightGeometry { cause: LightGeometryError::OffSample { pose, .. }, .. } if pose.starts_with("pose 2")),
        "{e}"
    );
}

#[test]
fn black_and_saturated_frames_are_diagnosed() {
    let mut r = recipe();
    r.poses.truncate(3);
    r.exposure_s = Some(1e-12);
    let e = run_recipe(&r, &lamp_rig()).err().expect("refused");
    println!("light-geometry refused: {e}");
    assert!(
        matches!(
            e,
            CalibrateError::Highlight {
                index: 0,
                cause: HighlightError::Empty { .. },
                ..
            }
        ),
        "{e}"
    );
    r.exposure_s = Some(1e-4);
    let e = run_recipe(&r, &lamp_rig()).err().expect("refused");
    println!("light-geometry refused: {e}");
    assert!(
        matches!(
            e,
            CalibrateError::Highlight {
                cause: HighlightError::Saturated { .. },
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("exposure_s"), "{e}");
}

#[test]
fn bad_recipe_values_name_the_key() {
    let text = std::fs::read_to_string(root().join("calibration/recipes/light-geometry.toml")).unwrap();
    let bad = text.replacen("threshold_fraction = 0.1", "threshold_fraction = 1.5", 1);
    let e = Recipe::parse(&bad, "t").unwrap_err().to_string();
    assert!(
        e.contains("light_geometry.highlight.threshold_fraction") && e.contains("1.5"),
        "{e}"
    );
    let bad = text.replacen("light = [35.0, 270.0]\n", "", 1);
    let e = Recipe::parse(&bad, "t").unwrap_err().to_string();
    assert!(e.contains("pose[1].light") && e.contains("φ_v + 180°"), "{e}");
    let bad = text.replacen("max_offset_deg = 2.0", "max_offset_deg = 20.0", 1);
    let e = Recipe::parse(&bad, "t").unwrap_err().to_string();
    assert!(e.contains("light_geometry.max_offset_deg"), "{e}");
}
