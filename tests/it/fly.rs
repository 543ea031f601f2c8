//! Fly-scan (issue 30): the lamp flies through each light ring while the camera exposes.
//! Through the library's session (the path `gonio acquire --fly` takes), on a small ring
//! sweep at 32²: the plan's time is the run's, every flown frame's measured mid-exposure
//! pose is its planned one and its light sweep stays within the bound, a run stopped inside
//! a segment and resumed stores the same bytes, and the error against the truth stays
//! within 0.5 dB of stop and go.

use gonio::engine::{Observer, RunEvent};
use gonio::plan::fly::{FlyOptions, POSE_TOLERANCE_DEG};
use gonio::plan::{Plan, PlanOptions};
use gonio::session::{NewSession, PlanRequest, RunRequest, RunSettings, Session};
use gonio::store::{self, MeasurementStatus};
use gonio::sweep::Sweep;
use gonio_devices::rig::RigSpec;
use gonio_devices::Direction;
use gonio_simulator::SampleSpec;
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// The pole, a ring of 12 at 45° and Bonn's ring of 24 at 75°, seen from one view.
fn rings() -> Sweep {
    let mut lights = vec![Direction::from_degrees(0.0, 0.0)];
    lights.extend((0..12).map(|k| Direction::from_degrees(45.0, 30.0 * k as f64)));
    lights.extend((0..24).map(|k| Direction::from_degrees(75.0, 15.0 * k as f64)));
    Sweep {
        name: "rings".into(),
        lights,
        views: vec![Direction::from_degrees(30.0, 0.0)],
    }
}

fn session(dir: &Path, fly: Option<f64>, sample: &str) -> NewSession {
    NewSession {
        out: dir.to_path_buf(),
        force: true,
        rig: RigSpec::default_rig(),
        hdr: None,
        sample: SampleSpec::resolve(sample).unwrap(),
        sweep: rings(),
        plan: PlanRequest {
            options: PlanOptions {
                kicks: 500,
                ..Default::default()
            },
            isotropic: false,
            sparse: None,
            fly: fly.map(|b| FlyOptions::new(b).unwrap()),
        },
        settings: RunSettings {
            width: 32,
            height: 32,
            noise: true,
            truth: true,
            seed: None,
            raw: false,
            store_truth: false,
            reference: None,
        },
        calibration: None,
        shard: None,
    }
}

fn quiet() -> Observer {
    Arc::new(|_: &RunEvent<'_>| {})
}

/// Image hash by canonical index.
fn hashes(dir: &Path) -> BTreeMap<usize, String> {
    let (_, records) = store::load(dir).unwrap();
    records
        .iter()
        .filter(|r| matches!(r.status, MeasurementStatus::Measured))
        .map(|r| (r.index, r.image_sha256.clone().unwrap()))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fly_scan_runs_as_planned_resumes_to_the_same_bytes_and_keeps_the_error() {
    let tmp = tempfile::tempdir().unwrap();
    let blur = 0.5;

    // Whole run.
    let a = tmp.path().join("fly");
    let s = Session::create(&session(&a, Some(blur), "wallpaper")).unwrap();
    let plan = s.plan().clone();
    let fly = plan.fly.clone().expect("a fly plan records its figures");
    assert_eq!(fly.flown_segments, 2, "both rings are flown: {fly:?}");
    assert_eq!(fly.flown_pairs, 36);
    assert_eq!(fly.stop_and_go_reasons.get("light_at_pole"), Some(&1));
    assert!(plan.durations.optimized_s < fly.stop_and_go_overlapped_s, "{fly:?}");
    assert!(fly.lower_bound_s <= plan.durations.optimized_s + 1e-9);
    assert!(fly.max_light_sweep_deg <= blur + 1e-9 && fly.max_image_blur_px == 0.0);
    let sum = s
        .run(&RunRequest::default(), Arc::new(AtomicBool::new(false)), quiet())
        .await
        .unwrap();
    assert!(sum.complete);
    assert!(
        (sum.sweep_duration_s - plan.durations.optimized_s).abs() < 1e-6,
        "the run takes what the plan says: {} vs {}",
        sum.sweep_duration_s,
        plan.durations.optimized_s
    );
    let (_, records) = store::load(&a).unwrap();
    let mut flown = 0;
    for r in records
        .iter()
        .filter(|r| matches!(r.status, MeasurementStatus::Measured))
    {
        let Some(f) = r.extra.get("flight") else { continue };
        flown += 1;
        let start: Vec<f64> = serde_json::from_value(f["axes_start_deg"].clone()).unwrap();
        let end: Vec<f64> = serde_json::from_value(f["axes_end_deg"].clone()).unwrap();
        assert_ne!(start, end, "index {}: the lamp moved during the exposure", r.index);
        for ((s, e), mid) in start.iter().zip(&end).zip(&r.axes_read_back_deg) {
            assert!(
                ((s + e) / 2.0 - mid).abs() < 1e-9,
                "the stored pose is the mid-exposure one"
            );
        }
        let sweep = f["light_sweep_deg"].as_f64().unwrap();
        assert!(sweep > 0.0 && sweep <= blur + 1e-6, "index {}: sweep {sweep}", r.index);
        let l = r.light_read_back_deg.unwrap();
        let got = Direction::from_degrees(l[0], l[1]);
        let want = Direction::from_degrees(r.light_deg[0], r.light_deg[1]);
        assert!(got.angle_to(want).to_degrees() <= POSE_TOLERANCE_DEG);
    }
    assert_eq!(flown, 36);

    // Stopped inside the first ring, then resumed: the same bytes.
    let b = tmp.path().join("fly-resumed");
    let s = Session::create(&session(&b, Some(blur), "wallpaper")).unwrap();
    let pause = Arc::new(AtomicBool::new(false));
    let first = RunRequest {
        limit: Some(5),
        ..Default::default()
    };
    let part = s.run(&first, pause.clone(), quiet()).await.unwrap();
    assert!(!part.complete);
    let s = Session::resume(&b).unwrap();
    assert!(s.run(&RunRequest::default(), pause, quiet()).await.unwrap().complete);
    assert_eq!(hashes(&a), hashes(&b), "a resumed fly-scan stores the same images");

    // Stop and go over the same pairs: flown frames differ (the lamp moved), the error
    // against the truth does not, beyond the target's 0.5 dB.
    let c = tmp.path().join("stop-and-go");
    let s = Session::create(&session(&c, None, "wallpaper")).unwrap();
    let sg = s
        .run(&RunRequest::default(), Arc::new(AtomicBool::new(false)), quiet())
        .await
        .unwrap();
    let (hf, hs) = (hashes(&a), hashes(&c));
    assert_eq!(hf.len(), hs.len());
    assert!(hf.iter().filter(|(k, v)| hs[k] != **v).count() >= 30);
    let (pf, ps) = (sum.truth_error.unwrap().psnr_db, sg.truth_error.unwrap().psnr_db);
    eprintln!("PSNR vs truth: fly {pf:.3} dB, stop and go {ps:.3} dB");
    assert!((pf - ps).abs() < 0.5, "fly {pf} vs stop and go {ps}");
    assert!(sg.sweep_duration_s > sum.sweep_duration_s);
}

/// A stage that trails its commanded trajectory (the simulator's `flight_lag_s` fault):
/// every flown frame is exposed behind its planned pose, so each is retaken stop and go,
/// counted in its record, and no frame is stored with a pose it was not taken at.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lagging_stage_gets_its_frames_retaken_stop_and_go() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("lag");
    let mut new = session(&dir, Some(0.5), "wallpaper");
    new.sweep.lights.truncate(13); // the pole and the 45° ring
    let axis = new.rig.axes.iter_mut().find(|a| a.role == "light_azimuth").unwrap();
    axis.options.insert("flight_lag_s".into(), toml::Value::Float(0.05));
    let s = Session::create(&new).unwrap();
    let planned = s.plan().durations.optimized_s;
    assert_eq!(s.plan().fly.as_ref().unwrap().flown_pairs, 12);
    let sum = s
        .run(&RunRequest::default(), Arc::new(AtomicBool::new(false)), quiet())
        .await
        .unwrap();
    assert!(sum.complete);
    assert!(sum.sweep_duration_s > planned, "retakes cost rig time");
    let (_, records) = store::load(&dir).unwrap();
    let retaken: Vec<_> = records
        .iter()
        .filter(|r| {
            r.extra
                .get("flight")
                .is_some_and(|f| f.get("retaken_stop_and_go").is_some())
        })
        .collect();
    assert_eq!(retaken.len(), 12, "every flown frame trailed its pose by ≈ 0.7°");
    let fly = sum.fly.as_ref().expect("a fly-scan's summary counts its frames");
    assert_eq!((fly.flown, fly.retaken_stop_and_go), (0, 12), "{fly:?}");
    for r in retaken {
        let why = r.extra["flight"]["retaken_stop_and_go"].as_str().unwrap();
        assert!(why.contains("from the planned"), "{why}");
        for (c, b) in r.axes_commanded_deg.iter().zip(&r.axes_read_back_deg) {
            assert!((c - b).abs() < 1e-9, "index {}: stored at its pose", r.index);
        }
    }
}

#[test]
fn fly_refuses_bad_bounds_and_rigs_that_cannot_fly() {
    for b in [0.0, -1.0, f64::NAN, 10.5] {
        let e = FlyOptions::new(b).unwrap_err().to_string();
        assert!(e.contains("(0, 10]"), "{b}: {e}");
    }
    let opts = PlanOptions {
        kicks: 100,
        ..Default::default()
    };
    let fly = FlyOptions::new(0.5).unwrap();
    // A dome has no moving lamp; a V4L2 camera cannot expose in motion yet.
    let dome = RigSpec::load(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("devices/rigs/dome.toml")
            .as_path(),
    )
    .unwrap();
    let e = gonio::plan::fly::refusal(&dome).unwrap();
    assert!(e.contains("dome"), "{e}");
    let sweep = Sweep::resolve("fibonacci:4").unwrap();
    let mut v4l2 = RigSpec::default_rig();
    let plan = Plan::build(&v4l2, &sweep, &opts).unwrap();
    v4l2.camera.backend = "v4l2".into();
    let e = plan.into_fly(&v4l2, &opts, fly).unwrap_err().to_string();
    assert!(e.contains("v4l2"), "{e}");
}
