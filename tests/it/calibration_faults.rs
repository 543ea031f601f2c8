//! Camera faults during a calibration: every recipe captures through the rig's shared step
//! and capture policy (`gonio::rig`), so a dropped frame, a capture that never returns and
//! a stale frame are retried as in an acquisition, and a camera that keeps failing stops
//! the recipe with a typed error naming the pose. The white-standard recipe (9 poses,
//! 32² texels) on the default simulated rig, faults injected by the simulated camera
//! (`camera.options.fault`, see `simulator/src/camera_faults.rs`).

use crate::common;

use common::{root, run_recipe};
use gonio::calibrate::{CalibrateError, Recipe};
use gonio_devices::rig::RigSpec;

fn recipe() -> Recipe {
    Recipe::load(&root().join("calibration/recipes/white-standard.toml")).unwrap()
}

/// The default rig with camera options added (`key = value` TOML pairs).
fn rig(options: &[(&str, toml::Value)]) -> RigSpec {
    let mut spec = RigSpec::load(&root().join("devices/rigs/default.toml")).unwrap();
    for (k, v) in options {
        spec.camera.options.insert(k.to_string(), v.clone());
    }
    spec
}

// The error is matched by variant; its size does not matter here.
#[allow(clippy::result_large_err)]
fn k_of(spec: &RigSpec) -> Result<[f64; 3], CalibrateError> {
    let out = run_recipe(&recipe(), spec)?;
    Ok(out.result.white_standard.expect("white-standard part").radiometric.k)
}

#[test]
fn transient_camera_faults_are_retried_and_change_nothing() {
    let clean = k_of(&rig(&[])).expect("clean run");
    // Frames are seeded by the pose, so a retried capture gives the very same frame: the
    // result must be identical, not merely close.
    for (fault, extra) in [
        ("drop:at=3", None),
        ("stale:at=4", None),
        // The policy waits this long for the hung capture; generous enough that an honest
        // capture on a loaded CI machine never hits it (a 1 s limit did).
        ("timeout:at=2", Some(("capture_timeout_s", toml::Value::Float(8.0)))),
    ] {
        let mut opts = vec![("fault", toml::Value::String(fault.into()))];
        opts.extend(extra);
        let k = k_of(&rig(&opts)).unwrap_or_else(|e| panic!("{fault}: not recovered: {e}"));
        assert_eq!(k, clean, "{fault}: the retried frame must be the same frame");
        println!("faults: calibration white-standard {fault:<40} | 0     | retried, same K");
    }
}

#[test]
fn a_persistent_camera_fault_stops_the_recipe_naming_the_pose() {
    // The 3rd capture and the retries after it all fail (count above the 2 retries).
    let spec = rig(&[("fault", toml::Value::String("drop:at=3,count=5".into()))]);
    let e = k_of(&spec).expect_err("must stop");
    match &e {
        CalibrateError::Capture {
            recipe,
            index,
            attempts,
            ..
        } => {
            assert_eq!(recipe, "white-standard");
            assert_eq!(*index, 2, "the third pose");
            assert_eq!(*attempts, 3, "one try and the policy's two retries");
        }
        other => panic!("expected a capture error naming the pose, got {other:?}"),
    }
    let msg = e.to_string();
    assert!(msg.contains("pose 2") && msg.contains("3 attempt"), "{msg}");
    println!("faults: calibration white-standard drop:at=3,count=5              | -     | stopped: {msg}");
}
