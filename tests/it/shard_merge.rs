//! Shards and merge through the gonio binary: `gonio sim btf --shard I/N`,
//! `gonio acquire --shard I/N` and `gonio compress --method pvmf|pca|dfmf|local-pca
//! --shard I/N` merged by `gonio merge` equal the
//! single-process outputs byte for byte (a dataset's manifest: all but `created_unix`);
//! bad shard specs and bad part sets are refused by name; `gonio batch slurm` writes its
//! scripts without Slurm and, asked to submit without sbatch, says what to install.
//! (tests/slurm/run.sh runs the same through a real Slurm.)

use crate::common;

use common::bin;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn gonio(cwd: &Path, args: &[&str]) -> Output {
    Command::new(bin()).current_dir(cwd).args(args).output().unwrap()
}

fn ok(cwd: &Path, args: &[&str]) {
    let o = gonio(cwd, args);
    assert!(
        o.status.success(),
        "gonio {} failed: {}",
        args.join(" "),
        String::from_utf8_lossy(&o.stderr)
    );
}

/// stderr of a run that must fail.
fn fails(cwd: &Path, args: &[&str]) -> String {
    let o = gonio(cwd, args);
    assert!(!o.status.success(), "gonio {} should have failed", args.join(" "));
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Relative path → bytes of every file under `dir` (the manifest without `created_unix`).
fn files(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    fn walk(root: &Path, d: &Path, out: &mut Vec<(PathBuf, Vec<u8>)>) {
        for e in std::fs::read_dir(d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
                continue;
            }
            let mut bytes = std::fs::read(&p).unwrap();
            if p.file_name().unwrap() == "manifest.json" {
                let text = String::from_utf8(bytes).unwrap();
                bytes = text
                    .lines()
                    .filter(|l| !l.trim_start().starts_with("\"created_unix\""))
                    .collect::<Vec<_>>()
                    .join("\n")
                    .into_bytes();
            }
            out.push((p.strip_prefix(root).unwrap().to_path_buf(), bytes));
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}

const BTF: [&str; 7] = ["sim", "btf", "--sweep", "fibonacci:5", "--size", "16", "--json"];

#[test]
fn sharded_sim_btf_and_pvmf_merge_to_the_single_process_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    ok(t, &[&BTF[..], &["--out", "full"]].concat());
    for i in 1..=3 {
        let shard = format!("{i}/3");
        let out = format!("part-{i}");
        ok(t, &[&BTF[..], &["--shard", &shard, "--out", &out]].concat());
    }
    // Any order of the parts.
    ok(t, &["merge", "part-3", "part-1", "part-2", "--out", "merged", "--json"]);
    let (full, merged) = (files(&t.join("full")), files(&t.join("merged")));
    assert_eq!(full.len(), 2 + 25, "manifest, journal and 25 images");
    assert_eq!(
        full.iter().map(|f| &f.0).collect::<Vec<_>>(),
        merged.iter().map(|f| &f.0).collect::<Vec<_>>()
    );
    for (a, b) in full.iter().zip(&merged) {
        assert!(
            a.1 == b.1,
            "{} differs between the single-process and the merged dataset",
            a.0.display()
        );
    }

    let pvmf = ["compress", "full", "--method", "pvmf", "-c", "3", "--no-eval", "--json"];
    ok(t, &[&pvmf[..], &["--out", "full.gbtf"]].concat());
    for i in 1..=2 {
        let (shard, out) = (format!("{i}/2"), format!("p{i}.gbtf"));
        ok(t, &[&pvmf[..], &["--shard", &shard, "--out", &out]].concat());
    }
    ok(t, &["merge", "p1.gbtf", "p2.gbtf", "--out", "merged.gbtf"]);
    assert!(
        std::fs::read(t.join("full.gbtf")).unwrap() == std::fs::read(t.join("merged.gbtf")).unwrap(),
        "merged PVMF differs from the single-process file"
    );
    // The merged file is a complete model: it reconstructs like the single-process one.
    ok(
        t,
        &[
            "reconstruct",
            "merged.gbtf",
            "--light",
            "30,0",
            "--view",
            "0,0",
            "--out",
            "r.exr",
        ],
    );

    // Bad part sets, each refused by name.
    let e = fails(t, &["merge", "part-1", "part-3", "--out", "m"]);
    assert!(e.contains("missing shard 2/3 (views 1..3)"), "{e}");
    let e = fails(t, &["merge", "part-1", "part-2", "part-2", "part-3", "--out", "m"]);
    assert!(e.contains("shard 2/3 (views 1..3) given twice"), "{e}");
    let e = fails(t, &["merge", "part-1", "part-2", "part-4", "--out", "m"]);
    assert!(e.contains("missing part(s) part-4"), "{e}");
    let e = fails(t, &["merge", "p1.gbtf", "part-2", "--out", "m"]);
    assert!(e.contains("part-2") && e.contains("directory"), "{e}");
    let e = fails(t, &["merge", "full", "--out", "m"]);
    assert!(e.contains("full: not a shard part"), "{e}");
    // A part of another job (other components) is named with the field that differs.
    ok(
        t,
        &[
            "compress",
            "full",
            "--method",
            "pvmf",
            "-c",
            "2",
            "--no-eval",
            "--shard",
            "2/2",
            "--out",
            "q2.gbtf",
        ],
    );
    let e = fails(t, &["merge", "p1.gbtf", "q2.gbtf", "--out", "m.gbtf"]);
    assert!(e.contains("q2.gbtf") && e.contains("params differs"), "{e}");
    // A part as the output would be deleted before it is read: refused.
    let e = fails(
        t,
        &["merge", "part-1", "part-2", "part-3", "--out", "part-2", "--force"],
    );
    assert!(e.contains("part-2: is also the --out"), "{e}");
    assert!(t.join("part-2/manifest.json").is_file());
    // An existing output is kept unless --force.
    let e = fails(t, &["merge", "p1.gbtf", "p2.gbtf", "--out", "merged.gbtf"]);
    assert!(e.contains("--force"), "{e}");
    assert!(!t.join("m").exists() && !t.join("m.gbtf").exists());
}

/// Run every pass of a sharded randomized SVD in `t`: `shards` parts per pass, each pass
/// merged into the next pass's state, the last into `out`. With `tree`, every pass is
/// merged as a tree: pairs of shards first (`gonio merge --partial`), then the pairs.
/// Returns the passes run.
fn sharded_rsvd(t: &Path, args: &[&str], tag: &str, shards: usize, out: &str, tree: bool) -> usize {
    let mut state: Option<String> = None;
    for pass in 0.. {
        let parts: Vec<String> = (1..=shards).map(|i| format!("{tag}-p{pass}-{i}.gpart")).collect();
        // Shards in reverse order, on one thread (the single-process run uses the
        // default pool): nothing may depend on which ran first or on the thread count.
        for i in (1..=shards).rev() {
            let shard = format!("{i}/{shards}");
            let mut a: Vec<&str> = args.to_vec();
            a.extend(["--shard", &shard, "--out", &parts[i - 1]]);
            if let Some(s) = &state {
                a.extend(["--state", s]);
            }
            let o = Command::new(bin())
                .current_dir(t)
                .env("RAYON_NUM_THREADS", "1")
                .args(&a)
                .output()
                .unwrap();
            assert!(
                o.status.success(),
                "gonio {}: {}",
                a.join(" "),
                String::from_utf8_lossy(&o.stderr)
            );
        }
        let groups: Vec<String> = if tree {
            (0..shards / 2)
                .map(|g| {
                    let name = format!("{tag}-p{pass}-g{}.gpart", g + 1);
                    ok(
                        t,
                        &["merge", "--partial", &parts[2 * g + 1], &parts[2 * g], "--out", &name],
                    );
                    name
                })
                .collect()
        } else {
            parts.clone()
        };
        let mut m: Vec<&str> = vec!["merge"];
        m.extend(groups.iter().rev().map(String::as_str));
        let merged = format!("{tag}-s{pass}.gstate");
        let o = gonio(t, &[&m[..], &["--out", &merged, "--json"]].concat());
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        if report["kind"] != "state" {
            std::fs::rename(t.join(&merged), t.join(out)).unwrap();
            return pass + 1;
        }
        state = Some(merged);
    }
    unreachable!()
}

#[test]
fn sharded_pca_and_dfmf_merge_to_the_single_process_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    ok(t, &[&BTF[..], &["--out", "full"]].concat());
    let cases: [(&str, &[&str]); 4] = [
        ("pca", &["compress", "full", "--method", "pca", "-c", "4", "--no-eval"]),
        (
            "lpca",
            &[
                "compress",
                "full",
                "--method",
                "local-pca",
                "-c",
                "2",
                "--clusters",
                "4",
                "--subspace",
                "12",
                "--in-passes",
                "--no-eval",
            ],
        ),
        (
            "lab",
            &[
                "compress",
                "full",
                "--method",
                "dfmf",
                "--color-model",
                "lab",
                "-c",
                "3",
                "--quantize",
                "10",
                "--no-eval",
            ],
        ),
        (
            "btf",
            &[
                "compress",
                "full",
                "--method",
                "dfmf",
                "-c",
                "3",
                "--power-iters",
                "1",
                "--no-eval",
            ],
        ),
    ];
    for (tag, args) in cases {
        let single = format!("{tag}-single");
        let o = Command::new(bin())
            .current_dir(t)
            .env("RAYON_NUM_THREADS", "3")
            .args([args, &["--out", &single]].concat())
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        for (shards, tree) in [(2, false), (3, false), (4, true)] {
            let merged = format!("{tag}-merged-{shards}");
            let passes = sharded_rsvd(t, args, &format!("{tag}{shards}"), shards, &merged, tree);
            let want = match tag {
                "btf" => 3,
                "lpca" => 9,
                _ => 4,
            };
            assert_eq!(passes, want, "{tag}");
            assert!(
                std::fs::read(t.join(&single)).unwrap() == std::fs::read(t.join(&merged)).unwrap(),
                "{tag}: {shards} merged shards differ from the single-process file"
            );
        }
    }

    // Refusals, each naming what is wrong.
    let pca = ["compress", "full", "--method", "pca", "-c", "4", "--no-eval"];

    // A partial merge takes one group of consecutive shards, m dividing N.
    let e = fails(
        t,
        &[
            "merge",
            "--partial",
            "pca4-p0-2.gpart",
            "pca4-p0-3.gpart",
            "--out",
            "g.gpart",
        ],
    );
    assert!(
        e.contains("shards 2..=3 of 4 are not a group") && e.contains("shards 1..=2"),
        "{e}"
    );
    let e = fails(
        t,
        &[
            "merge",
            "--partial",
            "pca4-p0-1.gpart",
            "pca4-p0-3.gpart",
            "--out",
            "g.gpart",
        ],
    );
    assert!(e.contains("shard 2/4 is missing"), "{e}");
    let e = fails(
        t,
        &[
            "merge",
            "--partial",
            "pca4-p0-1.gpart",
            "pca4-p0-2.gpart",
            "pca4-p0-3.gpart",
            "--out",
            "g.gpart",
        ],
    );
    assert!(e.contains("3 does not divide 4"), "{e}");
    // A group part with a shard of the finer split is not one split.
    let e = fails(
        t,
        &[
            "merge",
            "pca4-p0-g1.gpart",
            "pca4-p0-3.gpart",
            "pca4-p0-4.gpart",
            "--out",
            "x.gstate",
        ],
    );
    assert!(e.contains("the same N"), "{e}");
    let e = fails(t, &["merge", "pca2-p0-1.gpart", "--out", "x.gstate"]);
    assert!(e.contains("missing shard 2/2"), "{e}");
    let e = fails(t, &["merge", "pca2-p0-1.gpart", "pca2-p1-2.gpart", "--out", "x.gstate"]);
    assert!(e.contains("pca2-p1-2.gpart") && e.contains("differs"), "{e}");
    // A state of another job (other components).
    let e = fails(
        t,
        &[
            &pca[..4],
            &[
                "-c",
                "3",
                "--no-eval",
                "--shard",
                "1/2",
                "--state",
                "pca2-s0.gstate",
                "--out",
                "y.gpart",
            ],
        ]
        .concat(),
    );
    assert!(e.contains("pca2-s0.gstate") && e.contains("another job"), "{e}");
    // A part where a state belongs.
    let e = fails(
        t,
        &[
            &pca[..],
            &["--shard", "1/2", "--state", "pca2-p0-1.gpart", "--out", "y.gpart"],
        ]
        .concat(),
    );
    assert!(e.contains("is not a state"), "{e}");
    // A damaged part.
    let mut bytes = std::fs::read(t.join("pca2-p0-1.gpart")).unwrap();
    let n = bytes.len();
    bytes[n - 1] ^= 1;
    std::fs::write(t.join("bad.gpart"), &bytes).unwrap();
    let e = fails(t, &["merge", "bad.gpart", "pca2-p0-2.gpart", "--out", "x.gstate"]);
    assert!(e.contains("bad.gpart") && e.contains("damaged"), "{e}");
    // Methods that are not a randomized SVD are not split in passes.
    let e = fails(
        t,
        &[
            "compress",
            "full",
            "--method",
            "median-cut",
            "--shard",
            "1/2",
            "--out",
            "m.gpart",
        ],
    );
    assert!(e.contains("--shard"), "{e}");
    assert!(!t.join("x.gstate").exists() && !t.join("y.gpart").exists());
}

/// The records of a dataset's journal, in journal order.
fn journal(dir: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(dir.join("journal.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["rec"].clone())
        .collect()
}

#[test]
fn sharded_acquisition_merges_to_the_single_process_images() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let acq = [
        "acquire",
        "--sweep",
        "fibonacci:6",
        "--size",
        "24x24",
        "--seed",
        "7",
        "--store-truth",
        "--json",
    ];
    ok(t, &[&acq[..], &["--out", "single"]].concat());
    // Shards in reverse order: a shard's images must not depend on what ran before it.
    for i in (1..=3).rev() {
        let (shard, out) = (format!("{i}/3"), format!("acq-{i}"));
        ok(t, &[&acq[..], &["--shard", &shard, "--out", &out]].concat());
    }
    ok(t, &["merge", "acq-2", "acq-3", "acq-1", "--out", "merged", "--json"]);
    // Every image, truth image and the plan: the same bytes.
    let (single, merged) = (files(&t.join("single")), files(&t.join("merged")));
    assert_eq!(
        single.iter().map(|f| &f.0).collect::<Vec<_>>(),
        merged.iter().map(|f| &f.0).collect::<Vec<_>>()
    );
    let mut images = 0;
    for (a, b) in single.iter().zip(&merged) {
        let name = a.0.display().to_string();
        if name == "journal.jsonl" || name == "manifest.json" {
            continue;
        }
        images += name.ends_with(".exr") as usize;
        assert!(
            a.1 == b.1,
            "{name} differs between the single-process and the merged acquisition"
        );
    }
    assert!(images >= 2 * 30, "{images} images and truth images");
    // The journal: the same records in the same order, but for the fields that measure
    // the run itself (the rig's clock and frame counter started anew in every shard).
    let (ja, jb) = (journal(&t.join("single")), journal(&t.join("merged")));
    assert_eq!(ja.len(), jb.len());
    for (mut x, mut y) in ja.into_iter().zip(jb) {
        for r in [&mut x, &mut y] {
            let o = r.as_object_mut().unwrap();
            for k in ["wall_time_unix", "rig_time_s", "frame_sequence"] {
                o.remove(k);
            }
        }
        assert_eq!(x, y);
    }
    // The summary adds up the parts' counts.
    let m = |d: &str| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(t.join(d).join("manifest.json")).unwrap()).unwrap()
    };
    let (ms, mm) = (m("single"), m("merged"));
    for k in [
        "planned_measurements",
        "measured",
        "skipped",
        "substituted",
        "stored_this_run",
        "remaining",
    ] {
        assert_eq!(ms["summary"][k], mm["summary"][k], "summary.{k}");
    }
    assert_eq!(mm["summary"]["complete"], true);
    assert_eq!(mm["summary"]["parts"].as_array().map(Vec::len), Some(3));
    assert!(mm["extra"].get("shard").is_none());

    // A part planned differently (another kick budget) is refused, naming plan.json.
    ok(
        t,
        &[&acq[..], &["--plan-kicks", "3", "--shard", "2/3", "--out", "other-2"]].concat(),
    );
    let e = fails(t, &["merge", "acq-1", "other-2", "acq-3", "--out", "m"]);
    assert!(e.contains("other-2") && e.contains("plan.json"), "{e}");
    // No shards of an isotropic plan: its pairs stand for other views' pairs.
    let e = fails(
        t,
        &[&acq[..], &["--isotropic", "--shard", "1/3", "--out", "iso"]].concat(),
    );
    assert!(e.contains("isotropic"), "{e}");
    assert!(!t.join("m").exists());
}

#[test]
fn bad_shard_specs_are_refused_with_the_valid_form() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    for bad in ["3/2", "0/0", "0/2", "a/b"] {
        let e = fails(t, &[&BTF[..], &["--shard", bad]].concat());
        assert!(e.contains(bad) && e.contains("valid form is I/N"), "{bad}: {e}");
    }
    let e = fails(t, &[&BTF[..], &["--shard", "1/6"]].concat());
    assert!(e.contains("5 views cannot be split into 6 shards"), "{e}");
    let e = fails(
        t,
        &[
            "compress",
            ".",
            "--method",
            "median-cut",
            "--shard",
            "1/2",
            "--out",
            "x.gbtf",
        ],
    );
    assert!(e.contains("--shard splits --method pvmf"), "{e}");
    // Local PCA is split into passes only when it clusters in a subspace.
    ok(t, &[&BTF[..], &["--out", "ds"]].concat());
    let e = fails(
        t,
        &[
            "compress",
            "ds",
            "--method",
            "local-pca",
            "-c",
            "2",
            "--subspace",
            "0",
            "--shard",
            "1/2",
            "--out",
            "x.gpart",
        ],
    );
    assert!(e.contains("--subspace 0") && e.contains("0 < d < 75"), "{e}");
    // --state belongs to a sharded pass.
    let e = fails(
        t,
        &[
            "compress", ".", "--method", "pca", "-c", "2", "--state", "s.gstate", "--out", "x",
        ],
    );
    assert!(e.contains("--shard"), "{e}");
}

#[test]
fn batch_slurm_writes_scripts_and_names_what_to_install_without_sbatch() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    ok(
        t,
        &[
            "batch", "slurm", "--shards", "4", "--work", "w", "--out", "btf", "--", "sim", "btf", "--size", "16",
        ],
    );
    let array = std::fs::read_to_string(t.join("w/shards.sbatch")).unwrap();
    assert!(
        array.contains("#SBATCH --array=1-4") && array.contains("--shard \"$I/4\""),
        "{array}"
    );
    let merge = std::fs::read_to_string(t.join("w/merge.sbatch")).unwrap();
    assert!(merge.contains(" merge ") && merge.contains("parts/part-4 "), "{merge}");
    // The array script refuses to run outside Slurm (no array task id).
    let o = Command::new("bash").arg(t.join("w/shards.sbatch")).output().unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("sbatch"));

    let o = Command::new(bin())
        .current_dir(t)
        .env("PATH", t.join("no-such-dir"))
        .args([
            "batch", "slurm", "--shards", "2", "--work", "w2", "--out", "o", "--submit", "--", "sim", "btf",
        ])
        .output()
        .unwrap();
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("sbatch is not installed") && e.contains("apt-get install slurm-client"),
        "{e}"
    );
    let e = fails(
        t,
        &[
            "batch", "slurm", "--shards", "2", "--work", "w3", "--out", "o", "--", "plan",
        ],
    );
    assert!(e.contains("cannot be sharded"), "{e}");
    let e = fails(
        t,
        &[
            "batch", "slurm", "--shards", "2", "--work", "w3", "--out", "o", "--", "acquire", "--resume", "d",
        ],
    );
    assert!(e.contains("--resume"), "{e}");
    // PCA: one array and one merge per pass, each round after the previous merge.
    ok(
        t,
        &[
            "batch", "slurm", "--shards", "2", "--work", "w4", "--out", "p.gbtf", "--", "compress", "ds", "--method",
            "pca", "-c", "4",
        ],
    );
    for r in 0..4 {
        assert!(t.join(format!("w4/shards-{r}.sbatch")).is_file() && t.join(format!("w4/merge-{r}.sbatch")).is_file());
    }
    let last = std::fs::read_to_string(t.join("w4/shards-3.sbatch")).unwrap();
    assert!(last.contains("--state") && last.contains("state-2.gstate"), "{last}");
    let e = fails(
        t,
        &[
            "batch", "slurm", "--shards", "2", "--work", "w3", "--out", "o", "--", "sim", "btf", "--out", "x",
        ],
    );
    assert!(e.contains("--out"), "{e}");
}
