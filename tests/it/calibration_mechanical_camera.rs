//! The mechanical calibration with the camera as the reference
//! (`calibration/recipes/mechanical-camera.toml`): on the simulated rig with an error
//! model (`devices/rigs/mechanical-errors.toml`, its turntable's load-side encoder switched
//! off, so only the camera can see the load) the turntable's backlash, homing
//! repeatability and scale error must match the simulator's truth; an axis the camera
//! cannot observe (the lamp arm) is refused before anything moves, and so is a recipe
//! without the board's geometry.
//!
//! Run: `cargo test --test calibration_mechanical_camera -- --nocapture` (prints the figures).

use crate::common;

use common::run_recipe;
use gonio::calibrate::mechanical::MechanicalError;
use gonio::calibrate::{CalibrateError, Recipe};
use gonio_devices::rig::RigSpec;
use std::path::Path;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn recipe() -> Recipe {
    Recipe::load(&root().join("calibration/recipes/mechanical-camera.toml")).unwrap()
}

/// The mechanical-errors rig with the turntable's encoder off.
fn rig_without_encoder() -> RigSpec {
    let path = root().join("devices/rigs/mechanical-errors.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let anchor = "periodic_phase_deg = 30.0, seed = 11 }";
    assert!(text.contains(anchor), "{} changed", path.display());
    let text = text.replacen(anchor, "periodic_phase_deg = 30.0, seed = 11, encoder = false }", 1);
    RigSpec::parse(&text, "mechanical-errors without turntable encoder").unwrap()
}

#[test]
fn the_camera_measures_the_turntable_against_the_truth() {
    let out = run_recipe(&recipe(), &rig_without_encoder()).unwrap();
    let m = out.result.mechanical.expect("a mechanical result");
    let a = &m.axes[0];
    assert_eq!((a.axis.as_str(), a.reference.as_str()), ("turntable", "camera"));
    let (t, e) = (a.truth.as_ref().unwrap(), a.errors.as_ref().unwrap());
    println!(
        "mechanical (camera): backlash {:.5}° (truth {:.5}, error {:+.2e}), repeatability {:.5}° (drawn {:.5}, error {:+.2e}), scale {:+.3e} (truth fit {:+.3e}, error {:+.2e})",
        a.backlash.mean_deg,
        t.model.backlash_deg,
        e.backlash_deg,
        a.homing.repeatability_deg,
        t.realized_repeatability_deg,
        e.repeatability_vs_realized_deg,
        a.positioning.scale_error,
        t.fit.scale_error,
        e.scale_error
    );
    // Measured: +7.4e-5°, −7.4e-5°, −5.1e-6; the bounds leave a factor ≥ 4 for the
    // renderer's and detector's changes.
    assert!(e.backlash_deg.abs() < 1e-3, "backlash error {:+.2e}°", e.backlash_deg);
    assert!(
        e.repeatability_vs_realized_deg.abs() < 1e-3,
        "repeatability error {:+.2e}°",
        e.repeatability_vs_realized_deg
    );
    assert!(e.scale_error.abs() < 2e-5, "scale error {:+.2e}", e.scale_error);
}

#[test]
fn axes_the_camera_cannot_see_and_a_missing_board_are_refused() {
    let mut r = recipe();
    r.mechanical.as_mut().unwrap().axes = vec!["light_arc".into()];
    match run_recipe(&r, &rig_without_encoder()) {
        Err(CalibrateError::Mechanical(e)) => match *e {
            MechanicalError::NotObservable { ref axis, .. } => {
                assert_eq!(axis, "light_arc");
                println!("refused: {e}");
            }
            other => panic!("expected NotObservable, got {other}"),
        },
        Err(other) => panic!("expected a mechanical error, got {other}"),
        Ok(_) => panic!("the lamp arm must be refused"),
    }
    // Too coarse a render (2 × 2 point samples per pixel, board edges parallel to the
    // pixel grid): the homing scatter does not change a single sample, every homing reads
    // the same angle, and the run says so instead of reporting a perfect axis.
    let mut r = recipe();
    r.simulator.supersample = 2;
    match run_recipe(&r, &rig_without_encoder()) {
        Err(CalibrateError::Mechanical(e)) => {
            assert!(matches!(*e, MechanicalError::CameraReference { .. }), "got {e}");
            println!("refused: {e}");
        }
        Err(other) => panic!("expected a mechanical error, got {other}"),
        Ok(out) => panic!(
            "an unresolved camera reference must be refused, got repeatability {:?}",
            out.result.mechanical.map(|m| m.axes[0].homing.repeatability_deg)
        ),
    }
    let mut r = recipe();
    r.checkerboard = None;
    match run_recipe(&r, &rig_without_encoder()) {
        Err(CalibrateError::Mechanical(e)) => {
            assert!(matches!(*e, MechanicalError::NoBoard { .. }), "got {e}");
        }
        Err(other) => panic!("expected a mechanical error, got {other}"),
        Ok(_) => panic!("a camera reference without a board must be refused"),
    }
}
