//! Rig-geometry calibration end to end on the simulated misaligned rig: the simulator
//! renders the checkerboard where the rig really is (`[sim_misalignment]`), the recipe
//! estimates the axis zero offsets and the camera's mounting rotation from the detected
//! corners, and applying the estimate makes the planner's commanded directions the true
//! ones.

use crate::common;

use common::run_recipe;
use gonio::calibrate::recipe::PoseSpec;
use gonio::calibrate::rig_geometry::direction_errors;
use gonio::calibrate::{CalibrateError, Recipe};
use gonio_calibration::rig_geometry::RigGeometryError;
use gonio_devices::rig::RigSpec;
use std::path::Path;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn misaligned() -> RigSpec {
    RigSpec::load(&root().join("devices/rigs/misaligned.toml")).unwrap()
}

fn recipe() -> Recipe {
    Recipe::load(&root().join("calibration/recipes/rig-geometry.toml")).unwrap()
}

#[test]
fn misalignment_is_recovered_and_applying_it_corrects_the_directions() {
    let spec = misaligned();
    let truth = spec.sim_misalignment.clone().expect("the rig file has a truth");
    let mut recipe = recipe();
    // 8 of the shipped 12 poses keep the debug run short; they still tilt the camera at
    // several turntable angles.
    recipe.poses.truncate(8);
    let out = run_recipe(&recipe, &spec).unwrap();
    let r = out.result.rig_geometry.as_ref().expect("rig-geometry result");
    let fit = &r.fit;
    assert_eq!(fit.unobserved_axes, vec!["light_base", "light_arc"]);
    assert!(fit.rms_px < 0.1, "reprojection RMS {} px", fit.rms_px);
    assert!(
        fit.initial_rms_px > 1.0,
        "the nominal model must not already fit: {}",
        fit.initial_rms_px
    );
    // every estimated parameter against the simulator's truth
    let errors = r.errors.as_ref().unwrap();
    assert_eq!(errors.len(), 5, "{errors:?}");
    for e in errors {
        assert!(e.error_deg.abs() < 0.02, "{e:?}");
        assert!(e.sigma_deg.is_finite() && e.sigma_deg < 0.02, "{e:?}");
    }
    assert!((errors[0].truth_deg - truth.axis_zero_offset_deg["turntable"]).abs() < 1e-12);
    // commanded directions: off by a fraction of a degree before, exact after
    let (before, after) = (
        r.directions_before.as_ref().unwrap(),
        r.directions_after.as_ref().unwrap(),
    );
    assert!(
        before.pairs > 6000 && after.pairs == before.pairs,
        "{before:?} {after:?}"
    );
    assert!(before.view_max_deg > 0.25 && before.light_max_deg > 0.3, "{before:?}");
    assert!(after.view_max_deg < 0.02 && after.light_max_deg < 0.02, "{after:?}");
    // the direction uncertainty from the fit's covariance, next to the true error
    let u = &r.direction_uncertainty;
    println!(
        "rig-geometry: over {} Bonn pairs, view sigma max {:.5}° mean {:.5}°, true error max {:.5}°, \
         worst error / sigma {:?}, beyond 3 sigma {:?}; light sigma max {:.5}°, error / sigma {:?}",
        u.pairs,
        u.view_sigma_max_deg,
        u.view_sigma_mean_deg,
        after.view_max_deg,
        u.view_max_error_over_sigma,
        u.view_beyond_3_sigma_fraction,
        u.light_sigma_max_deg,
        u.light_max_error_over_sigma
    );
    assert_eq!(u.pairs, after.pairs);
    assert!(u.view_sigma_max_deg > 0.0 && u.view_sigma_max_deg < 0.02, "{u:?}");
    assert!(u.view_max_error_over_sigma.unwrap() < 3.0, "{u:?}");
    // the same through the public `apply`
    let mut corrected = spec.clone();
    corrected.sim_misalignment = None;
    r.apply(&mut corrected);
    let check = direction_errors(&corrected, &spec.simulated_truth());
    assert!((check.view_max_deg - after.view_max_deg).abs() < 1e-12);
    // error against effort: a row per view count from 3 to 8, each fitted or refused
    assert_eq!(r.effort.len(), 6);
    let last = r.effort.last().unwrap();
    assert_eq!(last.views, 8);
    assert!(
        last.failure.is_none() && last.max_parameter_error_deg.unwrap() < 0.02,
        "{last:?}"
    );
    assert_eq!(out.result.kind, "rig-geometry");
    assert_eq!(out.result.id.len(), 16);
}

#[test]
fn straight_down_views_are_refused_with_a_diagnosis() {
    let mut recipe = recipe();
    recipe.poses = [0.0, 90.0, 200.0]
        .into_iter()
        .map(|phi| PoseSpec {
            view: [0.0, phi],
            light: Some([35.0, phi + 90.0]),
        })
        .collect();
    // Every view straight down: the turntable's offset looks exactly like a camera roll.
    let e = run_recipe(&recipe, &misaligned()).err().expect("refused");
    match &e {
        CalibrateError::RigGeometry {
            cause: RigGeometryError::Undetermined { parameters, hint, .. },
            ..
        } => {
            assert!(parameters.iter().any(|p| p == "zero_offset.turntable"), "{e}");
            assert!(hint.contains("θ ≠ 0"), "{e}");
        }
        other => panic!("expected an undetermined fit, got {other}"),
    }
}
