//! Mechanical calibration (`calibration/recipes/mechanical.toml`) against known truth:
//! on the simulated rig with an error model (`devices/rigs/mechanical-errors.toml`) every
//! estimate must match the model; with the model zeroed every estimate must be 0; on an
//! emulated Zaber chain over a pty (load-side encoder via `get encoder.pos`) the estimates
//! match the emulator's model within the encoder's resolution; an axis without a reference
//! is refused.
//!
//! Run: `cargo test --test calibration_mechanical -- --nocapture` (prints the tables).

use gonio::calibrate::mechanical::{fit_line, AxisMechanics, MechanicalError};
use gonio::calibrate::{self, CalibrateError, Recipe};
use gonio::rig::Rig;
use gonio_devices::rig::RigSpec;
use gonio_simulator::emulate::{spawn_pty, EmulatorConfig, Protocol};
use gonio_simulator::mechanics::{MechanicalErrors, MechanicalState};
use gonio_simulator::{SampleSpec, SimOptions};
use std::path::Path;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn shipped_recipe() -> Recipe {
    Recipe::load(&root().join("calibration/recipes/mechanical.toml")).unwrap()
}

fn build(spec: &RigSpec, recipe: &Recipe) -> Rig {
    let sample = SampleSpec::resolve(&recipe.target).unwrap();
    let opts = SimOptions {
        noise: Some(false),
        ..Default::default()
    };
    Rig::build(spec, &sample, &opts).unwrap()
}

// The error is matched by variant; its size does not matter here.
#[allow(clippy::result_large_err)]
fn run(spec: &RigSpec, recipe: &Recipe) -> Result<calibrate::RunOutput, CalibrateError> {
    let rig = build(spec, recipe);
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(calibrate::run(recipe, &rig))
}

fn print_axis(a: &AxisMechanics) {
    println!(
        "mechanical: {:<11} repeatability {:.5}° backlash {:.5}° (±{:.5}, n={}) offset {:+.5}° scale {:+.3e} residual rms {:.5}° max {:.5}°",
        a.axis,
        a.homing.repeatability_deg,
        a.backlash.mean_deg,
        a.backlash.std_deg,
        a.backlash.samples,
        a.positioning.offset_deg,
        a.positioning.scale_error,
        a.positioning.residual_rms_deg,
        a.positioning.residual_max_deg
    );
    if let Some(e) = &a.errors {
        println!(
            "mechanical:   errors vs truth: backlash {:+.2e}° repeatability {:+.2e}° (vs model σ {:+.2e}°) offset {:+.2e}° scale {:+.2e} (vs model {:+.2e}) residual {:+.2e}°",
            e.backlash_deg,
            e.repeatability_vs_realized_deg,
            e.repeatability_vs_model_deg,
            e.offset_deg,
            e.scale_error,
            e.scale_error_vs_model,
            e.residual_rms_deg
        );
    }
    for r in &a.effort {
        println!(
            "mechanical:   effort {:<13} used {:3}  rig {:8.1} s  estimate {:.5}°  error {:+.2e}°{}",
            r.stage,
            r.used,
            r.rig_time_s,
            r.estimate_deg,
            r.error_deg,
            r.scale_error_error
                .map(|s| format!("  scale error {s:+.2e}"))
                .unwrap_or_default()
        );
    }
}

/// The check: on the simulated rig every estimate against the simulator's truth.
/// Tolerances: the encoder is exact on the simulator, so what is left is the physics the
/// estimators approximate: backlash is measured as B + e(x + B/2) − e(x − B/2) (drive error
/// across the dead band, ≤ B·(|s| + 2πA/P) ≈ 1.3e-4° here: tolerance 3e-4°); repeatability,
/// offset, scale and residual are compared with the same statistic of the truth (homing
/// offsets the simulator drew, drive error at the targets) and agree to rounding (1e-9).
#[test]
fn simulated_estimates_match_the_rig_files_error_model() {
    let spec = RigSpec::load(&root().join("devices/rigs/mechanical-errors.toml")).unwrap();
    let recipe = shipped_recipe();
    let out = run(&spec, &recipe).unwrap();
    let r = &out.result;
    assert_eq!(r.kind, "mechanical");
    assert!(r.simulated);
    assert_eq!(r.id.len(), 16);
    let m = r.mechanical.as_ref().expect("mechanical result");
    assert_eq!(m.axes.len(), 4);
    for a in &m.axes {
        print_axis(a);
        let t = a.truth.as_ref().expect("truth on the simulator");
        let e = a.errors.as_ref().unwrap();
        assert_eq!(a.homing.cycles, 20);
        assert_eq!(a.backlash.samples, 9 * 3);
        assert!(e.backlash_deg.abs() < 3e-4, "{}: {e:?}", a.axis);
        assert!(e.repeatability_vs_realized_deg.abs() < 1e-9, "{}: {e:?}", a.axis);
        assert!(e.offset_deg.abs() < 1e-9, "{}: {e:?}", a.axis);
        assert!(e.scale_error.abs() < 1e-9, "{}: {e:?}", a.axis);
        assert!(e.residual_rms_deg.abs() < 1e-9, "{}: {e:?}", a.axis);
        // 20 cycles estimate the model's σ to ~16 % (1 σ of a sample std): 3 σ allowed.
        assert!(
            e.repeatability_vs_model_deg.abs() <= 0.5 * t.model.home_sigma_deg + 1e-12,
            "{}: {e:?}",
            a.axis
        );
        // The nominal scale error: the periodic term leaks into the line over 9 targets.
        assert!(e.scale_error_vs_model.abs() < 1e-4, "{}: {e:?}", a.axis);
        // The effort table: one row per homing-cycle count 2..=20 and per pass count 1..=3,
        // with rig time growing.
        let homing: Vec<_> = a.effort.iter().filter(|r| r.stage == "homing").collect();
        let passes: Vec<_> = a.effort.iter().filter(|r| r.stage == "bidirectional").collect();
        assert_eq!((homing.len(), passes.len()), (19, 3));
        assert!(homing.windows(2).all(|w| w[1].rig_time_s > w[0].rig_time_s));
    }
    // the axes with a real model show it, the zero-model axis shows nothing
    let by = |n: &str| m.axes.iter().find(|a| a.axis == n).unwrap();
    assert!((by("turntable").backlash.mean_deg - 0.08).abs() < 3e-4);
    assert!((by("light_base").backlash.mean_deg - 0.12).abs() < 3e-4);
    assert!(by("turntable").homing.repeatability_deg > 0.01);
    let z = by("light_arc");
    assert!(z.backlash.mean_deg.abs() < 1e-9 && z.homing.repeatability_deg < 1e-9);
    assert!(z.positioning.scale_error.abs() < 1e-9 && z.positioning.residual_rms_deg < 1e-9);
}

/// With every error term zero (encoders still present) all estimates are 0.
#[test]
fn zero_model_gives_zero_estimates() {
    let text = std::fs::read_to_string(root().join("devices/rigs/mechanical-errors.toml")).unwrap();
    let zeroed: String = text
        .lines()
        .map(|l| {
            if l.starts_with("options = { mechanical") {
                "options = { mechanical = { encoder = true } }"
            } else {
                l
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    let spec = RigSpec::parse(&zeroed, "zeroed.toml").unwrap();
    let mut recipe = shipped_recipe();
    let mech = recipe.mechanical.as_mut().unwrap();
    mech.home_cycles = 4;
    mech.repetitions = 1;
    let out = run(&spec, &recipe).unwrap();
    for a in &out.result.mechanical.as_ref().unwrap().axes {
        print_axis(a);
        assert!(a.homing.repeatability_deg < 1e-9, "{}", a.axis);
        assert!(a.backlash.mean_deg.abs() < 1e-9, "{}", a.axis);
        assert!(a.positioning.offset_deg.abs() < 1e-9, "{}", a.axis);
        assert!(a.positioning.scale_error.abs() < 1e-9, "{}", a.axis);
        assert!(a.positioning.residual_rms_deg < 1e-9, "{}", a.axis);
    }
}

/// No reference, no estimate: the default rig's axes have no encoder.
#[test]
fn axes_without_a_reference_and_bad_targets_are_refused() {
    let spec = RigSpec::load(&root().join("devices/rigs/default.toml")).unwrap();
    let recipe = shipped_recipe();
    let e = run(&spec, &recipe).err().expect("refused");
    let msg = e.to_string();
    assert!(
        matches!(&e, CalibrateError::Mechanical(b) if matches!(**b, MechanicalError::NoReference { .. })),
        "{msg}"
    );
    assert!(msg.contains("turntable") && msg.contains("encoder"), "{msg}");

    let spec = RigSpec::load(&root().join("devices/rigs/mechanical-errors.toml")).unwrap();
    let mut recipe = shipped_recipe();
    let mech = recipe.mechanical.as_mut().unwrap();
    mech.axes = vec!["camera_arc".into()];
    mech.targets_deg = vec![-10.0, 0.0, 79.5];
    let e = run(&spec, &recipe).err().expect("refused");
    let msg = e.to_string();
    assert!(msg.contains("camera_arc") && msg.contains("79.5"), "{msg}");
    mech_unknown_axis(&spec);

    let e = Recipe::parse(
        "kind = \"mechanical\"\nname = \"m\"\ntarget = \"calibration-target\"\n[mechanical]\nhome_cycles = 1\n",
        "t",
    )
    .unwrap_err();
    assert!(e.to_string().contains("home_cycles"), "{e}");
    let e = Recipe::parse(
        "kind = \"mechanical\"\nname = \"m\"\ntarget = \"calibration-target\"\n[mechanical]\napproach = 1\n",
        "t",
    )
    .unwrap_err();
    assert!(e.to_string().contains("approach"), "{e}");
}

fn mech_unknown_axis(spec: &RigSpec) {
    let mut recipe = shipped_recipe();
    recipe.mechanical.as_mut().unwrap().axes = vec!["tilt".into()];
    let e = run(spec, &recipe).err().expect("refused");
    let msg = e.to_string();
    assert!(msg.contains("tilt") && msg.contains("turntable"), "{msg}");
}

/// The same run on an emulated Zaber chain over a pty: `get pos` is the step count, `get
/// encoder.pos` the load side of the emulator's error model. The truth is rebuilt from the
/// model (the emulator seeds axis k with `seed + k` and draws one offset per `home`).
/// Tolerances: the encoder counts 0.001°, so single deviations are quantized to ±0.0005°.
#[test]
fn emulated_zaber_encoder_gives_the_same_estimates() {
    let model = MechanicalErrors {
        backlash_deg: 0.08,
        home_sigma_deg: 0.02,
        scale_error: 5e-4,
        periodic_amplitude_deg: 0.01,
        periodic_period_deg: 45.0,
        periodic_phase_deg: 30.0,
        seed: 21,
        encoder: true,
    };
    let mut cfg = EmulatorConfig::new(Protocol::Zaber, 4);
    cfg.range_deg = (-200.0, 200.0);
    cfg.mechanical = Some(model);
    let h = spawn_pty(cfg).unwrap();
    let text = std::fs::read_to_string(root().join("devices/rigs/emulated-zaber.toml"))
        .unwrap()
        .replace("${GONIO_ZABER_PORT}", &h.path().display().to_string())
        .replace(
            "units_per_deg = 1000.0 }",
            "units_per_deg = 1000.0, encoder = true, poll_ms = 5 }",
        );
    let spec = RigSpec::parse(&text, "emulated.toml").unwrap();
    let cycles = 6;
    let recipe = Recipe::parse(
        &format!(
            "kind = \"mechanical\"\nname = \"m\"\ntarget = \"calibration-target\"\n[mechanical]\n\
             axes = [\"turntable\"]\nhome_cycles = {cycles}\nhome_away_deg = 3.0\nrepetitions = 1\n\
             targets_deg = [-30.0, -10.0, 10.0, 30.0, 50.0]\napproach_deg = 1.0\n"
        ),
        "emulated-recipe.toml",
    )
    .unwrap();
    let out = run(&spec, &recipe).unwrap();
    h.stop();
    let r = &out.result;
    assert!(!r.simulated);
    let a = &r.mechanical.as_ref().unwrap().axes[0];
    print_axis(a);
    assert!(a.truth.is_none(), "a serial rig has no simulator truth");
    // Rebuild the truth: turntable is device 1 axis 1 (seed + 0); one homing before the cycles.
    let mut st = MechanicalState::new(model);
    for _ in 0..=cycles {
        st.home();
    }
    let offsets = &st.home_offsets()[1..];
    let m = offsets.iter().sum::<f64>() / cycles as f64;
    let sigma = (offsets.iter().map(|o| (o - m).powi(2)).sum::<f64>() / (cycles - 1) as f64).sqrt();
    assert!(
        (a.homing.repeatability_deg - sigma).abs() < 1e-3,
        "repeatability {} vs realized {sigma}",
        a.homing.repeatability_deg
    );
    assert!(
        (a.backlash.mean_deg - 0.08).abs() < 1.5e-3,
        "backlash {}",
        a.backlash.mean_deg
    );
    let h2 = 0.5 * model.backlash_deg;
    let x: Vec<f64> = a.targets.iter().map(|t| t.read_back_deg).collect();
    let last = *st.home_offsets().last().unwrap();
    let y: Vec<f64> = x
        .iter()
        .map(|&v| last + 0.5 * (model.positioning_error_deg(v - h2) + model.positioning_error_deg(v + h2)))
        .collect();
    let t = fit_line(&x, &y);
    let p = &a.positioning;
    assert!((p.offset_deg - t.offset_deg).abs() < 1e-3, "{p:?} vs {t:?}");
    assert!((p.scale_error - t.scale_error).abs() < 3e-5, "{p:?} vs {t:?}");
    assert!((p.residual_rms_deg - t.residual_rms_deg).abs() < 1e-3, "{p:?} vs {t:?}");
}
