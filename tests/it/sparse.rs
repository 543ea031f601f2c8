//! Sparse acquisition end to end at CI size (16², a 12-direction sweep): a prior learned
//! from a small `gonio dataset generate` family (same bytes at 1 and 2 threads), a sparse
//! plan, a sparse dataset completed by `gonio complete` (measured images bit for bit,
//! every other pair `predicted`, no NaN, close to the truth of a sample the prior never
//! saw), `gonio acquire` of the same sparse plan (interrupted and resumed, completed),
//! `gonio bench sparse` (ours beats the plain-PCA baseline), and the refusals.

use crate::common::cli::{gonio, ok, refused, s};
use gonio::store::{self, Dataset, MeasurementStatus};
use std::path::Path;

const SWEEP: &str = "fibonacci:12";

fn family_spec(dir: &Path) -> std::path::PathBuf {
    let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("simulator/families/prior-base.toml");
    let spec = format!(
        r#"name = "ci-prior"
members = 4
seed = 5
sample = "{}"
sweep = "{SWEEP}"
size = 16

[[vary]]
key = "material.0.alpha"
log_uniform = [0.05, 0.6]

[[vary]]
key = "material.0.diffuse_reflectance"
uniform = [[0.02, 0.02, 0.02], [0.8, 0.8, 0.8]]

[[vary]]
key = "material.1.kd"
uniform = [[0.0, 0.0, 0.0], [0.6, 0.6, 0.6]]

[[vary]]
key = "material.1.alpha_x"
log_uniform = [0.05, 0.6]

[[vary]]
key = "height.amplitude_mm"
uniform = [0.05, 0.6]
"#,
        base.display()
    );
    let p = dir.join("ci-prior.toml");
    std::fs::write(&p, spec).unwrap();
    p
}

#[test]
fn prior_plan_complete_bench_and_refusals() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let fam = d.join("fam");
    ok(&["dataset", "generate", s(&family_spec(d)), "--out", s(&fam)]);
    let members: Vec<String> = (0..4)
        .map(|m| fam.join(format!("members/{m:04}")).display().to_string())
        .collect();
    let prior = d.join("p.gprior");
    let prior2 = d.join("p2.gprior");
    let mut args: Vec<&str> = vec!["prior", "build"];
    args.extend(members.iter().map(|m| m.as_str()));
    let build = |out: &Path, threads: &str| {
        let mut a = args.clone();
        a.extend(["--components", "10", "--texels", "64", "--out", s(out)]);
        let o = gonio(&a, Some(threads));
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    build(&prior, "1");
    build(&prior2, "2");
    assert_eq!(
        std::fs::read(&prior).unwrap(),
        std::fs::read(&prior2).unwrap(),
        "prior bytes depend on the thread count"
    );
    // A mixture of priors (`--clusters`): the same bytes at any thread count too.
    let mix = d.join("m.gmix");
    let mix2 = d.join("m2.gmix");
    for (out, threads) in [(&mix, "1"), (&mix2, "2")] {
        let mut a = args.clone();
        a.extend([
            "--clusters",
            "2",
            "--components",
            "6",
            "--texels",
            "64",
            "--out",
            s(out),
        ]);
        let o = gonio(&a, Some(threads));
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    assert_eq!(
        std::fs::read(&mix).unwrap(),
        std::fs::read(&mix2).unwrap(),
        "mixture bytes depend on the thread count"
    );

    // A held-out sample's truth; a sparse plan; the sparse dataset made from the truth.
    let truth = d.join("truth");
    ok(&[
        "sim",
        "btf",
        "--sample",
        "wallpaper",
        "--sweep",
        SWEEP,
        "--size",
        "16",
        "--out",
        s(&truth),
    ]);
    let plan: serde_json::Value = serde_json::from_str(&ok(&[
        "plan",
        "--sweep",
        SWEEP,
        "--prior",
        s(&prior),
        "--pairs",
        "40",
        "--plan-kicks",
        "200",
        "--json",
    ]))
    .unwrap();
    let chosen: Vec<usize> = plan["steps"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["index"].as_u64().unwrap() as usize)
        .collect();
    assert_eq!(chosen.len(), 40);
    assert_eq!(plan["sparse"]["chosen"], 40);
    assert!(plan["sparse"]["planned_s"].as_f64().unwrap() > 0.0);
    assert!(plan["sparse"]["predicted_psnr_db"].as_f64().unwrap().is_finite());

    let (header, records) = store::load(&truth).unwrap();
    let sparse = d.join("sparse");
    let mut ds = Dataset::create(&sparse, &header, false).unwrap();
    for r in records.iter().filter(|r| chosen.contains(&r.index)) {
        let img = store::read_exr(&truth.join(r.image.as_ref().unwrap())).unwrap();
        ds.store(r.clone(), Some(&img), None).unwrap();
    }
    ds.finish(&serde_json::json!({})).unwrap();
    drop(ds);

    let full = d.join("full");
    let rep: serde_json::Value = serde_json::from_str(&ok(&[
        "complete",
        s(&sparse),
        "--prior",
        s(&prior),
        "--out",
        s(&full),
        "--json",
    ]))
    .unwrap();
    assert_eq!(rep["measured"], 40);
    assert_eq!(rep["predicted"], 144 - 40);
    assert!(rep["conditioning"]["map_condition"].as_f64().unwrap().is_finite());
    assert!(rep["clipped_readings"].as_u64().is_some(), "{rep}");
    let (h2, recs2) = store::load(&full).unwrap();
    assert_eq!(h2.version, store::FORMAT_VERSION);
    // Weighed by the recorded rig's sensor noise, clipped readings as lower bounds at 1.
    assert_eq!(h2.extra["completion"]["noise_model"], "sensor", "{}", h2.extra);
    assert_eq!(h2.extra["completion"]["clip"], 1.0, "{}", h2.extra);
    refused(
        &[
            "complete",
            s(&sparse),
            "--prior",
            s(&prior),
            "--out",
            s(&d.join("bad-clip")),
            "--clip=-1",
        ],
        &["--clip -1", "positive"],
    );
    assert_eq!(recs2.len(), 144);
    let by_index: std::collections::HashMap<usize, &store::MeasurementRecord> =
        records.iter().map(|r| (r.index, r)).collect();
    let (mut sq, mut n) = (0.0f64, 0usize);
    for r in &recs2 {
        let img = store::read_exr(&full.join(r.image.as_ref().unwrap())).unwrap();
        assert!(img.data.iter().all(|v| v.is_finite() && *v >= 0.0), "pair {}", r.index);
        let t = by_index[&r.index];
        if chosen.contains(&r.index) {
            assert_eq!(r.status, MeasurementStatus::Measured);
            assert_eq!(r.image_sha256, t.image_sha256, "measured pair {} changed", r.index);
        } else {
            assert!(
                matches!(r.status, MeasurementStatus::Predicted { predicted_rmse_8bit, .. } if predicted_rmse_8bit.is_finite())
            );
            let ti = store::read_exr(&truth.join(t.image.as_ref().unwrap())).unwrap();
            for (a, b) in img.data.iter().zip(&ti.data) {
                let e = (store::linear_to_srgb8(*a) as f64 - store::linear_to_srgb8(*b) as f64) / 255.0;
                sq += e * e;
                n += 1;
            }
        }
    }
    let psnr = -10.0 * (sq / n as f64).log10();
    assert!(psnr > 25.0, "predicted pairs of a held-out sample: {psnr:.2} dB");
    ok(&["verify", s(&full)]);

    // Bench: ours beats least squares in the plain basis at every budget, both finite.
    let bench: serde_json::Value = serde_json::from_str(&ok(&[
        "bench",
        "sparse",
        "--truth",
        s(&truth),
        "--sweep",
        SWEEP,
        "--prior",
        s(&prior),
        "--fractions",
        "0.15,0.3",
        "--noise",
        "off",
        "--methods",
        "ours,pca-ls,mixture",
        "--mixture",
        s(&mix),
        "--plan-kicks",
        "200",
        "--json",
    ]))
    .unwrap();
    assert_eq!(bench["label"], "held-out");
    // The mixture completes every texel in one of its members (a finite PSNR).
    assert!(
        bench["rows"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|r| r["method"] == "mixture")
            .all(|r| r["psnr_db"].as_f64().is_some_and(|v| v.is_finite() && v > 10.0)),
        "{bench}"
    );
    for f in [0.15, 0.3] {
        let get = |m: &str| {
            bench["rows"]
                .as_array()
                .unwrap()
                .iter()
                .find(|r| r["method"] == m && r["fraction"].as_f64() == Some(f))
                .and_then(|r| r["psnr_db"].as_f64())
                .unwrap_or_else(|| panic!("{m} at {f}: {bench}"))
        };
        assert!(
            get("ours") > get("pca-ls"),
            "fraction {f}: ours {} vs pca-ls {}",
            get("ours"),
            get("pca-ls")
        );
    }

    // Refusals: another sweep, more components than pairs, a degenerate design.
    refused(
        &["plan", "--sweep", "fibonacci:10", "--prior", s(&prior), "--pairs", "20"],
        &["prior mismatch", "fibonacci:12", "fibonacci:10"],
    );
    refused(
        &[
            "plan",
            "--sweep",
            SWEEP,
            "--prior",
            s(&prior),
            "--pairs",
            "6",
            "--plan-kicks",
            "100",
        ],
        &["10 components", "6 pairs"],
    );
    // The remedy the refusal names: the prior's leading components only.
    let plan6 = |c: &'static str| -> Vec<&str> {
        vec![
            "plan",
            "--sweep",
            SWEEP,
            "--prior",
            s(&prior),
            "--pairs",
            "6",
            "--plan-kicks",
            "100",
            "--components",
            c,
        ]
    };
    ok(&plan6("6"));
    refused(&plan6("11"), &["--components 11", "10 components"]);
    // `gonio acquire` runs the same sparse plan: only the chosen pairs, plan.json records
    // the design, an interrupted and resumed run stores the same images, the monitor counts
    // against the chosen pairs, and `gonio complete` fills in the rest.
    let acquire = |out: &Path, extra: &[&str]| {
        let mut a = vec![
            "acquire",
            "--sweep",
            SWEEP,
            "--prior",
            s(&prior),
            "--pairs",
            "40",
            "--plan-kicks",
            "200",
            "--size",
            "16x16",
            "--no-truth",
            "--out",
            s(out),
            "--json",
        ];
        a.extend_from_slice(extra);
        gonio(&a, None)
    };
    let acq = d.join("acq");
    let o = acquire(&acq, &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(summary["measured"], 40, "{summary}");
    assert_eq!(summary["complete"], true);
    let stored_plan: serde_json::Value =
        serde_json::from_slice(&std::fs::read(acq.join(store::PLAN_FILE)).unwrap()).unwrap();
    assert_eq!(stored_plan["sparse"]["chosen"], 40);
    assert_eq!(
        stored_plan["sparse"]["picks"], plan["sparse"]["picks"],
        "acquire and plan chose differently"
    );
    let (_, acq_records) = store::load(&acq).unwrap();
    let mut measured: Vec<usize> = acq_records.iter().map(|r| r.index).collect();
    measured.sort_unstable();
    let mut want = chosen.clone();
    want.sort_unstable();
    assert_eq!(
        measured, want,
        "the acquisition measured other pairs than the plan chose"
    );
    let snap = gonio::view::monitor::snapshot(&acq).unwrap();
    assert_eq!(
        (snap.total, snap.done),
        (40, 40),
        "the monitor counts against the chosen pairs"
    );

    let acq2 = d.join("acq2");
    let o = acquire(&acq2, &["--limit", "15"]);
    assert_eq!(o.status.code(), Some(3), "{}", String::from_utf8_lossy(&o.stderr));
    let snap = gonio::view::monitor::snapshot(&acq2).unwrap();
    assert_eq!((snap.total, snap.done), (40, 15));
    refused(
        &["acquire", "--resume", s(&acq2), "--pairs", "10"],
        &["--resume", "drop them"],
    );
    ok(&["acquire", "--resume", s(&acq2), "--json"]);
    let (_, acq2_records) = store::load(&acq2).unwrap();
    let sha = |recs: &[store::MeasurementRecord]| {
        let mut v: Vec<(usize, String)> = recs
            .iter()
            .map(|r| (r.index, r.image_sha256.clone().unwrap()))
            .collect();
        v.sort();
        v
    };
    assert_eq!(
        sha(&acq_records),
        sha(&acq2_records),
        "interrupted and resumed: other images"
    );

    let acq_full = d.join("acq-full");
    let rep: serde_json::Value = serde_json::from_str(&ok(&[
        "complete",
        s(&acq),
        "--prior",
        s(&prior),
        "--out",
        s(&acq_full),
        "--json",
    ]))
    .unwrap();
    assert_eq!(
        (rep["measured"].as_u64(), rep["predicted"].as_u64()),
        (Some(40), Some(104))
    );
    let snap = gonio::view::monitor::snapshot(&acq_full).unwrap();
    assert_eq!(
        (snap.total, snap.done),
        (40, 40),
        "predicted pairs are not planned steps"
    );

    let one_view = d.join("one-view");
    let mut ds = Dataset::create(&one_view, &header, false).unwrap();
    for r in records.iter().filter(|r| r.index / 12 == 3) {
        let img = store::read_exr(&truth.join(r.image.as_ref().unwrap())).unwrap();
        ds.store(r.clone(), Some(&img), None).unwrap();
    }
    drop(ds);
    refused(
        &["complete", s(&one_view), "--prior", s(&prior), "--out", s(&d.join("x"))],
        &["degenerate", "view"],
    );

    adaptive_acquisition(d, &prior, plan["sparse"]["full_optimized_s"].as_f64().unwrap());
}

/// `gonio acquire --adaptive`: rounds recorded in plan.json before they are measured, the
/// pairs measured are exactly the rounds' pairs, the planned rig time stays within the
/// budget, an interrupted run (stopped inside round 2) resumes to the same plan.json and
/// images byte for byte, the monitor shows the rounds, a PSNR target stops the run, and
/// the bad combinations are refused by name.
fn adaptive_acquisition(d: &Path, prior: &Path, full_s: f64) {
    let budget = format!("{:.0}", 0.8 * full_s);
    let acquire = |out: &Path, stop: &[&str], extra: &[&str]| {
        let mut a = vec![
            "acquire",
            "--sweep",
            SWEEP,
            "--adaptive",
            "--prior",
            s(prior),
            "--plan-kicks",
            "200",
            "--size",
            "16x16",
            "--no-truth",
            "--out",
            s(out),
            "--json",
        ];
        a.extend_from_slice(stop);
        a.extend_from_slice(extra);
        gonio(&a, None)
    };
    let plan_of = |dir: &Path| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(dir.join(store::PLAN_FILE)).unwrap()).unwrap()
    };
    let ad1 = d.join("adaptive");
    let o = acquire(&ad1, &["--rig-budget", &budget], &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(summary["complete"], true, "{summary}");
    let plan = plan_of(&ad1);
    let ad = &plan["sparse"]["adaptive"];
    let rounds = ad["rounds"].as_array().unwrap();
    assert!(rounds.len() >= 2, "one round only: {ad}");
    assert!(ad["finished"].as_str().is_some(), "{ad}");
    assert_eq!(summary["adaptive"]["rounds"].as_array().unwrap().len(), rounds.len());
    let mut chosen: Vec<usize> = rounds
        .iter()
        .flat_map(|r| {
            r["pairs"]
                .as_array()
                .unwrap()
                .iter()
                .map(|p| p.as_u64().unwrap() as usize)
        })
        .collect();
    let n = chosen.len();
    chosen.sort_unstable();
    chosen.dedup();
    assert_eq!(chosen.len(), n, "a pair chosen twice");
    assert_eq!(plan["steps"].as_array().unwrap().len(), n);
    for (i, r) in rounds.iter().enumerate() {
        assert_eq!(r["round"], i + 1);
        assert!(r["predicted_psnr_after_db"].as_f64().unwrap().is_finite());
        if i > 0 {
            assert!(r["observed_residual"].as_f64().unwrap().is_finite(), "{r}");
            assert_eq!(r["allowance_s"], ad["round_allowance_s"], "{r}");
        }
    }
    let spent: f64 = rounds
        .iter()
        .map(|r| r["planned_s"].as_f64().unwrap() + r["allowance_s"].as_f64().unwrap())
        .sum();
    assert!(spent <= budget.parse::<f64>().unwrap() + 1e-6, "{spent} > {budget}");
    let (_, recs) = store::load(&ad1).unwrap();
    let mut measured: Vec<usize> = recs.iter().map(|r| r.index).collect();
    measured.sort_unstable();
    assert_eq!(measured, chosen, "measured pairs are not the rounds' pairs");
    let snap = gonio::view::monitor::snapshot(&ad1).unwrap();
    assert_eq!((snap.total, snap.done), (n, n));
    assert_eq!(snap.rounds.len(), rounds.len());
    assert!(snap.rounds.iter().all(|r| r.done == r.pairs));
    assert!(snap.adaptive_finished.is_some());

    // Interrupted inside round 2 (kill-safe journal: --limit stops like a pause), resumed:
    // the same rounds, the same bytes.
    let first = rounds[0]["pairs"].as_array().unwrap().len();
    let ad2 = d.join("adaptive2");
    let limit = (first + 2).to_string();
    let o = acquire(&ad2, &["--rig-budget", &budget], &["--limit", &limit]);
    assert_eq!(o.status.code(), Some(3), "{}", String::from_utf8_lossy(&o.stderr));
    let mid = plan_of(&ad2);
    assert_eq!(
        mid["sparse"]["adaptive"]["rounds"].as_array().unwrap().len(),
        2,
        "round 2 is recorded before its first move"
    );
    let snap = gonio::view::monitor::snapshot(&ad2).unwrap();
    assert_eq!(snap.rounds[1].done, 2);
    assert!(snap.adaptive_finished.is_none());
    refused(
        &["acquire", "--resume", s(&ad2), "--adaptive", "--rig-budget", "100"],
        &["--resume", "drop them"],
    );
    ok(&["acquire", "--resume", s(&ad2), "--json"]);
    assert_eq!(
        std::fs::read(ad1.join(store::PLAN_FILE)).unwrap(),
        std::fs::read(ad2.join(store::PLAN_FILE)).unwrap(),
        "an interrupted adaptive run chose other rounds"
    );
    let sha = |dir: &Path| {
        let (_, recs) = store::load(dir).unwrap();
        let mut v: Vec<(usize, String)> = recs
            .iter()
            .map(|r| (r.index, r.image_sha256.clone().unwrap()))
            .collect();
        v.sort();
        v
    };
    assert_eq!(sha(&ad1), sha(&ad2), "interrupted and resumed: other images");

    // With drift references (one an hour: the opening one, then each round closes with
    // one): taken across the rounds, placed after each round's last measurement, the same
    // rounds and images as without them, and the dataset verifies.
    let ad4 = d.join("adaptive-references");
    let o = acquire(&ad4, &["--rig-budget", &budget], &["--reference-every", "60"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let refs = store::load_references(&ad4).unwrap();
    println!(
        "adaptive with references: {} rounds, {} references, overhead {:.1} s",
        rounds.len(),
        refs.len(),
        summary["references"]["overhead_s"].as_f64().unwrap_or(f64::NAN)
    );
    assert_eq!(
        std::fs::read(ad1.join(store::PLAN_FILE)).unwrap(),
        std::fs::read(ad4.join(store::PLAN_FILE)).unwrap(),
        "references changed the rounds"
    );
    assert_eq!(sha(&ad1), sha(&ad4), "references changed the images");
    assert_eq!(refs.len(), rounds.len() + 1, "{refs:?}");
    assert!(refs.iter().all(|r| r.run == 0) && refs[0].after_index.is_none());
    let (_, recs4) = store::load(&ad4).unwrap();
    for (k, round) in rounds.iter().enumerate() {
        let pairs: Vec<usize> = round["pairs"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p.as_u64().unwrap() as usize)
            .collect();
        let last = recs4
            .iter()
            .filter(|r| pairs.contains(&r.index))
            .max_by_key(|r| r.order)
            .unwrap()
            .index;
        assert_eq!(
            refs[k + 1].after_index,
            Some(last),
            "round {} closes with a reference",
            k + 1
        );
    }
    let r = store::verify(&ad4).unwrap();
    assert!(r.is_clean() && r.complete && r.references_ok == refs.len(), "{r}");
    let series: serde_json::Value = serde_json::from_str(&ok(&["dataset", "drift", s(&ad4), "--json"])).unwrap();
    assert_eq!(series["measurements"].as_u64(), Some(n as u64), "{series}");

    // A PSNR target alone: the run stops when the prediction reaches it, or says why not.
    let ad3 = d.join("adaptive3");
    let o = acquire(
        &ad3,
        &["--target-psnr", "30"],
        &["--residual-weight", "0.5", "--round-allowance", "5"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // The knobs asked for are the ones recorded (and kept by a resume).
    let ad = &plan_of(&ad3)["sparse"]["adaptive"];
    assert_eq!(
        (ad["residual_weight"].as_f64(), ad["round_allowance_s"].as_f64()),
        (Some(0.5), Some(5.0))
    );
    for r in ad["rounds"].as_array().unwrap().iter().skip(1) {
        assert_eq!(r["allowance_s"].as_f64(), Some(5.0), "{r}");
    }
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let fin = summary["adaptive"]["finished"].as_str().unwrap().to_string();
    let pred = summary["adaptive"]["predicted_psnr_db"].as_f64().unwrap();
    assert!(
        (fin.contains("reached the target") && pred >= 30.0) || fin.contains("rounds") || fin.contains("every"),
        "{fin} at {pred}"
    );

    // Refusals.
    refused(
        &[
            "acquire",
            "--sweep",
            SWEEP,
            "--adaptive",
            "--prior",
            s(prior),
            "--out",
            s(&d.join("x1")),
        ],
        &["--adaptive needs a stop", "--target-psnr", "--rig-budget"],
    );
    refused(
        &[
            "acquire",
            "--sweep",
            SWEEP,
            "--adaptive",
            "--prior",
            s(prior),
            "--pairs",
            "20",
            "--out",
            s(&d.join("x2")),
        ],
        &["--pairs"],
    );
    refused(
        &[
            "acquire",
            "--sweep",
            SWEEP,
            "--adaptive",
            "--prior",
            s(prior),
            "--rig-budget",
            &budget,
            "--fly",
            "--out",
            s(&d.join("x3")),
        ],
        &["--adaptive with --fly"],
    );
    refused(
        &[
            "acquire",
            "--sweep",
            SWEEP,
            "--adaptive",
            "--prior",
            s(prior),
            "--target-psnr",
            "200",
            "--out",
            s(&d.join("x4")),
        ],
        &["--target-psnr 200"],
    );
    refused(
        &[
            "acquire",
            "--sweep",
            SWEEP,
            "--adaptive",
            "--prior",
            s(prior),
            "--target-psnr",
            "30",
            "--round-allowance",
            "-1",
            "--out",
            s(&d.join("x5")),
        ],
        &["--round-allowance -1", "≥ 0"],
    );
}
