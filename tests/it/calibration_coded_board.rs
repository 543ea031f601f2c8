//! Intrinsics from the coded-marker board end to end on the simulated rigs: the shipped
//! recipe `calibration/recipes/intrinsics-coded.toml` reaches the targets (focal
//! length and principal point within 0.1 % of the simulator's truth, reprojection RMS under
//! 0.1 px), and a partly hidden board (`simulator/samples/coded-target-occluded.toml`)
//! gives fewer corners per view, every one of them where the truth puts it.

use crate::common;

use common::{root, run_recipe};
use gonio::calibrate::Recipe;
use gonio_devices::rig::RigSpec;

fn recipe() -> Recipe {
    Recipe::load(&root().join("calibration/recipes/intrinsics-coded.toml")).unwrap()
}

fn rig(name: &str) -> RigSpec {
    RigSpec::load(&root().join(format!("devices/rigs/{name}.toml"))).unwrap()
}

#[test]
fn the_long_lens_of_the_default_rig_is_within_a_thousandth() {
    let out = run_recipe(&recipe(), &rig("default")).unwrap();
    let r = &out.result;
    let fit = r.intrinsics.as_ref().unwrap();
    let e = r.errors.as_ref().unwrap();
    eprintln!(
        "coded board, default rig: fx {:+.4} % fy {:+.4} % cx {:+.4} % cy {:+.4} % (σ cx {:.3} px, cy {:.3} px), RMS {:.4} px",
        e.fx_percent, e.fy_percent, e.cx_percent, e.cy_percent, fit.sigma.cx, fit.sigma.cy, fit.rms_px
    );
    assert!(fit.rms_px < 0.1, "reprojection RMS {} px", fit.rms_px);
    for (what, v) in [
        ("fx", e.fx_percent),
        ("fy", e.fy_percent),
        ("cx", e.cx_percent),
        ("cy", e.cy_percent),
    ] {
        assert!(v.abs() < 0.1, "{what} off by {v} %");
    }
    // Corners against the simulator's exact projection.
    for (k, rms) in r.corner_truth_rms_px.iter().enumerate() {
        assert!(*rms < 0.01, "view {k}: corner RMS {rms} px against the truth");
    }
}

#[test]
fn a_partly_hidden_board_gives_its_visible_corners_and_the_same_camera() {
    let mut recipe = recipe();
    recipe.target = root()
        .join("simulator/samples/coded-target-occluded.toml")
        .to_string_lossy()
        .into_owned();
    let out = run_recipe(&recipe, &rig("default")).unwrap();
    let corners = out.corners.as_ref().unwrap();
    let counts: Vec<usize> = corners.views.iter().map(|v| v.image.len()).collect();
    eprintln!("occluded board, corners per view: {counts:?}");
    assert!(counts.iter().all(|&n| (8..49).contains(&n)), "{counts:?}");
    let r = &out.result;
    for (k, rms) in r.corner_truth_rms_px.iter().enumerate() {
        assert!(*rms < 0.01, "view {k}: corner RMS {rms} px against the truth");
    }
    let e = r.errors.as_ref().unwrap();
    let fit = r.intrinsics.as_ref().unwrap();
    eprintln!(
        "occluded board, default rig: fx {:+.4} % cx {:+.4} % cy {:+.4} % (σ cx {:.3} px, cy {:.3} px), RMS {:.4} px",
        e.fx_percent, e.cx_percent, e.cy_percent, fit.sigma.cx, fit.sigma.cy, fit.rms_px
    );
    // A quarter of the corners gone weakens the principal point most (this rig tilts the
    // board about one camera axis only): it must be right within its own stated σ.
    assert!(e.fx_percent.abs() < 0.1, "{e:?}");
    assert!(
        e.cx_px.abs() < 3.0 * fit.sigma.cx && e.cy_px.abs() < 3.0 * fit.sigma.cy,
        "{e:?} {:?}",
        fit.sigma
    );
}
