//! Radiometric recipes on the simulated radiometric rig (`devices/rigs/radiometric.toml`:
//! non-linear response, colour crosstalk, vignetting, per-frame noise): every estimate is
//! recovered within the stated tolerance of the simulator's truth, and brackets that cannot
//! work are refused with a typed error.

use crate::common;

use common::run_recipe;
use gonio::calibrate::{self, CalibrateError, Recipe};
use gonio_calibration::radiometric::RadiometricError;
use gonio_devices::rig::RigSpec;
use std::path::{Path, PathBuf};

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn recipe(name: &str) -> Recipe {
    Recipe::load(&root().join("calibration/recipes").join(name)).unwrap()
}

// The error is matched by variant in the tests; its size does not matter here.
#[allow(clippy::result_large_err)]
fn run(recipe: &Recipe) -> Result<calibrate::RunOutput, CalibrateError> {
    run_recipe(
        recipe,
        &RigSpec::load(&root().join("devices/rigs/radiometric.toml")).unwrap(),
    )
}

fn tmpdir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("gonio-radiometric-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Response recovered within 3 % RMS of the true inverse response where the hat weight is
/// ≥ 0.05 (per channel), then the flat field on the white standard through that response
/// within 1.2 % RMS of the vignetting. The flat's error is dominated by the lamp's falloff
/// across the standard and the response's residual wiggles, not by the frame count.
#[test]
fn response_then_flat_match_the_truth() {
    let out = run(&recipe("response.toml")).unwrap();
    let r = out.result.radiometric.as_ref().unwrap();
    println!("{}", r.table());
    let e = r.response_error_rms.unwrap();
    assert!(e.iter().all(|x| *x < 0.03), "response error {e:?}");
    assert_eq!(r.effort.len(), 4);
    // two exposures are a fit too, just a worse one; eight are the full bracket
    assert!(r.effort.iter().all(|x| x.failure.is_none()), "{:?}", r.effort);
    assert!(r.hdr.as_ref().unwrap().total > 0);

    let dir = tmpdir("flat");
    let path = dir.join("calibration.json");
    std::fs::write(&path, serde_json::to_string(&out.result).unwrap()).unwrap();
    let mut flat = recipe("flat.toml");
    flat.radiometric.as_mut().unwrap().response = Some(path.display().to_string());
    let out = run(&flat).unwrap();
    let r = out.result.radiometric.as_ref().unwrap();
    println!("{}", r.table());
    let f = r.flat.as_ref().unwrap();
    assert!(f.covered_pixels > 10_000, "{f:?}");
    let err = r.flat_error_rms.unwrap();
    assert!(err < 0.012, "flat error {err}");
    // the vignetting is actually seen: the gain spans more than the error
    assert!(f.gain_max - f.gain_min > 0.01, "{f:?}");
    std::fs::remove_dir_all(dir).ok();

    // Without the response run the flat recipe says what to do.
    let mut missing = recipe("flat.toml");
    missing.radiometric.as_mut().unwrap().response = Some("/nonexistent/calibration.json".into());
    let e = run(&missing).err().expect("refused");
    assert!(e.to_string().contains("run a response recipe first"), "{e}");
}

/// `[radiometric] response` takes a response run's output directory as well as its
/// `calibration.json`; a missing file, another kind of result, a result of another rig or
/// of a camera with another bit depth are refused before the rig moves, naming the key and
/// the fix.
#[test]
fn a_response_reference_is_checked_before_the_rig_moves() {
    let out = run(&recipe("response.toml")).unwrap();
    let dir = tmpdir("reference");
    let good: serde_json::Value = serde_json::to_value(&out.result).unwrap();
    let write = |name: &str, v: &serde_json::Value| -> String {
        let d = dir.join(name);
        std::fs::create_dir_all(&d).unwrap();
        std::fs::write(d.join("calibration.json"), serde_json::to_string(v).unwrap()).unwrap();
        d.display().to_string()
    };
    let refused = |response: String| -> String {
        let mut colour = recipe("colour.toml");
        colour.radiometric.as_mut().unwrap().response = Some(response);
        let e = run(&colour).err().expect("refused");
        let text = e.to_string();
        println!("refused: {text}");
        assert!(
            matches!(e, CalibrateError::ResponseInput { .. }),
            "a reference error, not a capture or fit error: {text}"
        );
        assert!(text.contains("[radiometric] response = "), "names the key: {text}");
        text
    };

    let e = refused(dir.join("absent").display().to_string());
    assert!(
        e.contains("run a response recipe first") && e.contains("remove the key"),
        "{e}"
    );

    let mut dark = good.clone();
    dark["kind"] = "dark".into();
    dark["radiometric"]["response"] = serde_json::Value::Null;
    let e = refused(write("dark", &dark));
    assert!(e.contains("`dark` result") && e.contains("response.toml"), "{e}");

    let mut other = good.clone();
    other["rig"] = "another-rig".into();
    let e = refused(write("other-rig", &other));
    assert!(e.contains("another-rig") && e.contains("re-run"), "{e}");

    let mut bits = good.clone();
    bits["radiometric"]["response"]["curve"]["max_dn"] = 1023.0.into();
    let e = refused(write("bits", &bits));
    assert!(e.contains("0 ..= 1023") && e.contains("re-run"), "{e}");

    // The run's directory and its calibration.json are the same reference.
    let d = write("good", &good);
    let mut flat = recipe("flat.toml");
    flat.radiometric.as_mut().unwrap().response = Some(d);
    flat.radiometric.as_mut().unwrap().frames = 1;
    flat.radiometric.as_mut().unwrap().effort.clear();
    let r = run(&flat).unwrap();
    assert_eq!(
        r.result.radiometric.unwrap().linearisation.unwrap(),
        format!("response:{}", out.result.id)
    );

    // A response key on a recipe that does not use one is a recipe error.
    let text = std::fs::read_to_string(root().join("calibration/recipes/dark.toml")).unwrap();
    let dark_with = text.replacen("[radiometric]\n", "[radiometric]\nresponse = \"cal/response\"\n", 1);
    let e = Recipe::parse(&dark_with, "t").unwrap_err();
    assert!(e.to_string().contains("radiometric.response"), "{e}");
    std::fs::remove_dir_all(dir).ok();
}

/// The colour matrix undoes the crosstalk: corrected patches within 0.02 (linear
/// reflectance) RMS of their references, and the matrix within 5 % of the crosstalk's
/// inverse (relative Frobenius).
#[test]
fn colour_matrix_matches_the_truth() {
    // Stand-alone: the shipped recipe reads cal/response, this recovers its own curve.
    let mut colour = recipe("colour.toml");
    colour.radiometric.as_mut().unwrap().response = None;
    let out = run(&colour).unwrap();
    let r = out.result.radiometric.as_ref().unwrap();
    println!("{}", r.table());
    let c = r.colour.as_ref().unwrap();
    assert_eq!(c.patches, 24);
    assert!(c.residual_rms < 0.02, "{c:?}");
    let m = r.colour_matrix_error.unwrap();
    assert!(m < 0.05, "matrix error {m}");
    assert_eq!(out.result.id.len(), 16);
}

#[test]
fn dark_frame_is_measured_and_its_clipping_reported() {
    let out = run(&recipe("dark.toml")).unwrap();
    let r = out.result.radiometric.as_ref().unwrap();
    println!("{}", r.table());
    let d = r.dark.as_ref().unwrap();
    let t = r.dark_truth.as_ref().unwrap();
    assert_eq!(d.frames, 16);
    let rn = d.read_noise_dn.unwrap();
    // The ADC clips at 0: about half the dark values are 0 and the measured noise is a
    // lower bound of the true read noise, which the result says.
    assert!(d.clipped_at_zero > 0.2, "{d:?}");
    assert!(
        rn.iter().all(|x| *x > 0.3 * t.read_noise_dn && *x < t.read_noise_dn),
        "{rn:?} vs {t:?}"
    );
    assert!(d.mean_dn.iter().all(|m| *m >= 0.0 && *m < 3.0), "{d:?}");
    assert_eq!(d.hot_pixels, 0);
    assert_eq!(r.effort.len(), 4);
}

/// A bracket where every frame saturates and one where every frame is black are refused
/// with errors that say which way to change the exposure. (Saturating the dark background
/// too takes dark current beyond the full well: exposures of thousands of seconds.)
#[test]
fn saturated_and_black_brackets_are_refused() {
    let mut rc = recipe("response.toml");
    rc.radiometric.as_mut().unwrap().exposures_s = vec![5000.0, 10000.0];
    rc.radiometric.as_mut().unwrap().effort.clear();
    let e = run(&rc).err().expect("refused");
    assert!(
        matches!(
            e,
            CalibrateError::Radiometric {
                cause: RadiometricError::AllSaturated { .. },
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("shorten"), "{e}");
    rc.radiometric.as_mut().unwrap().exposures_s = vec![1e-9, 2e-9];
    let e = run(&rc).err().expect("refused");
    assert!(
        matches!(
            e,
            CalibrateError::Radiometric {
                cause: RadiometricError::AllBlack { .. },
                ..
            }
        ),
        "{e}"
    );
}

#[test]
fn recipes_refuse_bad_radiometric_tables() {
    let text = std::fs::read_to_string(root().join("calibration/recipes/response.toml")).unwrap();
    let one = text.replace(
        "exposures_s = [0.003125, 0.00625, 0.0125, 0.025, 0.05, 0.1, 0.2, 0.4]",
        "exposures_s = [0.05]",
    );
    let e = Recipe::parse(&one, "t").unwrap_err();
    assert!(e.to_string().contains("radiometric.exposures_s"), "{e}");
    let typo = text.replace("lambda = 150.0", "lamda = 150.0");
    assert_ne!(typo, text, "response.toml no longer contains `lambda = 150.0`");
    let e = Recipe::parse(&typo, "t").unwrap_err();
    assert!(e.to_string().contains("lamda"), "{e}");
    let neg = text.replace("0.003125,", "-1.0,");
    assert!(Recipe::parse(&neg, "t").is_err());
}
