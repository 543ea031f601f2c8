//! Camera intrinsics of the default rig's long lens (4300 px, ±5° field) with the
//! checkerboard on a wedge (`calibration/recipes/intrinsics-wedge.toml`): the simulator
//! renders the board on the tilted plane, the recipe states the wedge, and focal length and
//! principal point must come out within 0.1 % of the simulator's camera. On a flat board
//! the two-arm rig only tilts the target about the camera's x axis and the principal
//! point's y misses (intrinsics-telephoto.toml: cy −0.14 %, σ 1.4 px).
//!
//! One simulated run (≈ 60–75 s in a debug build on a busy 2-core machine, most of it
//! rendering); the second half reuses its corners, so checking that the wedge matters
//! costs no rendering.

use crate::common;

use common::{root, run_recipe};
use gonio::calibrate::Recipe;
use gonio_calibration::intrinsics::{calibrate_intrinsics, TargetView};
use gonio_devices::rig::RigSpec;
use gonio_simulator::sample::HeightSpec;
use gonio_simulator::SampleSpec;

/// The target: focal length and principal point within 0.1 % of the truth.
const TOL_PERCENT: f64 = 0.1;

#[test]
fn a_wedge_pins_the_long_lens_principal_point() {
    let recipe = Recipe::load(&root().join("calibration/recipes/intrinsics-wedge.toml")).unwrap();
    let wedge = recipe.wedge.expect("the recipe states its wedge");
    // What the recipe says is what the simulator renders.
    let sample = SampleSpec::resolve(&recipe.target).unwrap();
    assert_eq!(
        sample.height,
        HeightSpec::Plane {
            slope_deg: wedge.slope_deg,
            azimuth_deg: wedge.azimuth_deg
        },
        "recipe wedge and target sample disagree"
    );
    let spec = RigSpec::load(&root().join("devices/rigs/default.toml")).unwrap();
    let start = std::time::Instant::now();
    let out = run_recipe(&recipe, &spec).unwrap();
    let r = &out.result;
    let c = r.intrinsics.as_ref().unwrap();
    let e = r.errors.as_ref().unwrap();
    println!(
        "wedge {}° at {}°: {} views in {:.1} s wall ({:.0} s rig): fx {:+.4} %, cx {:+.4} %, cy {:+.4} % \
         (σ_cx {:.3} px, σ_cy {:.3} px), RMS {:.4} px, corner error ≤ {:.4} px",
        wedge.slope_deg,
        wedge.azimuth_deg,
        c.view_rms_px.len(),
        start.elapsed().as_secs_f64(),
        r.rig_time_s,
        e.fx_percent,
        e.cx_percent,
        e.cy_percent,
        c.sigma.cx,
        c.sigma.cy,
        c.rms_px,
        r.corner_truth_rms_px.iter().cloned().fold(0.0, f64::max)
    );
    for (name, v) in [
        ("fx", e.fx_percent),
        ("fy", e.fy_percent),
        ("cx", e.cx_percent),
        ("cy", e.cy_percent),
    ] {
        assert!(
            v.abs() < TOL_PERCENT,
            "{name} error {v:+.4} % (limit {TOL_PERCENT} %): {e:?}"
        );
    }
    assert!(c.rms_px < 0.02, "reprojection RMS {} px", c.rms_px);
    assert!(
        r.corner_truth_rms_px.iter().all(|&x| x < 0.03),
        "corner errors {:?}",
        r.corner_truth_rms_px
    );

    // The same corners with the board taken as flat (the wedge not stated): the object
    // points lose the 1/cos stretch along the slope and the planar model no longer fits.
    let views = &out.corners.as_ref().unwrap().views;
    let (ca, d) = (
        wedge.slope_deg.to_radians().cos(),
        [
            wedge.azimuth_deg.to_radians().cos(),
            wedge.azimuth_deg.to_radians().sin(),
        ],
    );
    let flat: Vec<TargetView> = views
        .iter()
        .map(|v| TargetView {
            object: v
                .object
                .iter()
                .map(|p| {
                    let s = p[0] * d[0] + p[1] * d[1];
                    [p[0] - s * (1.0 - ca) * d[0], p[1] - s * (1.0 - ca) * d[1]]
                })
                .collect(),
            ..v.clone()
        })
        .collect();
    let size = (spec.camera.width, spec.camera.height);
    match calibrate_intrinsics(&flat, size, &recipe.estimate) {
        Ok(f) => {
            println!(
                "the board taken flat: RMS {:.3} px, cx {:+.2} px, cy {:+.2} px off",
                f.rms_px,
                f.camera.cx - spec.camera.intrinsics().cx,
                f.camera.cy - spec.camera.intrinsics().cy
            );
            assert!(
                f.rms_px > 20.0 * c.rms_px,
                "an unstated wedge must show: RMS {} px vs {} px",
                f.rms_px,
                c.rms_px
            )
        }
        Err(err) => println!("an unstated wedge is refused: {err}"),
    }
}
