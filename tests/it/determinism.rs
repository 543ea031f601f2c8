//! Same inputs, same bytes: the same small simulated acquisition, `gonio sim btf` and
//! `gonio compress --method pvmf`, each run twice through the gonio binary with
//! `RAYON_NUM_THREADS=1` and `=2` while a competing busy-looping process loads the CPU,
//! must give byte-identical files.
//!
//! The acquisition uses the **default** planning budget (no `--plan-time`): that budget is
//! a work count, so a loaded machine plans the same order (issue 19: with the former
//! wall-clock budget two runs planned different orders, hence other IK branches, other
//! read-backs and, through pose-seeded noise, other images).
//!
//! Compared: the SHA-256 of every file of the two outputs, walked in sorted order; the file
//! lists must be equal too. Each run works in its own directory under the same relative
//! names (the summary and a `.gbtf` header record the paths they were given). The fields
//! that measure the run itself are left out by name ([`common::hashes`]).
//!
//! `plan.json`, every image and every other byte must match exactly.

use crate::common;

use common::hashes::hashes;
use common::{bin, write_scene};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

/// A busy-looping child (bounded: it exits by itself after `seconds`), so the runs under
/// test compete for the CPU as on a loaded machine.
struct Load(Child);

impl Load {
    fn start(seconds: u32) -> Load {
        let script = format!("end=$((SECONDS+{seconds})); while [ $SECONDS -lt $end ]; do :; done");
        Load(
            Command::new("bash")
                .args(["-c", &script])
                .stdout(Stdio::null())
                .spawn()
                .expect("starting the CPU load"),
        )
    }
}

impl Drop for Load {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Run gonio in `cwd` with `RAYON_NUM_THREADS=threads`.
fn gonio(cwd: &Path, threads: usize, args: &[&str]) {
    std::fs::create_dir_all(cwd).unwrap();
    let out = Command::new(bin())
        .current_dir(cwd)
        .env("RAYON_NUM_THREADS", threads.to_string())
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "gonio {} (RAYON_NUM_THREADS={threads}) failed: {}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
}

fn assert_same(what: &str, a: &Path, b: &Path) -> usize {
    let (ha, hb) = (hashes(a), hashes(b));
    assert_eq!(
        ha.keys().collect::<Vec<_>>(),
        hb.keys().collect::<Vec<_>>(),
        "{what}: the two runs wrote different files"
    );
    let differing: Vec<&String> = ha.keys().filter(|k| ha[*k] != hb[*k]).collect();
    assert!(
        differing.is_empty(),
        "{what}: {} of {} files differ between RAYON_NUM_THREADS=1 and 2 under load: {differing:?}",
        differing.len(),
        ha.len()
    );
    ha.len()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The working directory of run `t` (1 or 2).
fn run_dir(tmp: &Path, t: usize) -> PathBuf {
    tmp.join(format!("run-{t}"))
}

#[test]
fn acquisition_is_byte_identical_across_thread_counts_under_load() {
    let tmp = tempfile::tempdir().unwrap();
    let (rig, sweep) = write_scene(tmp.path());
    let out: Vec<PathBuf> = (1..=2).map(|t| run_dir(tmp.path(), t).join("acq")).collect();
    let _load = Load::start(120);
    let args = [
        "acquire",
        "--rig",
        s(&rig),
        "--sweep",
        s(&sweep),
        "--size",
        "32x32",
        "--seed",
        "7",
        "--json",
        "--out",
        "acq",
    ];
    for t in 1..=2 {
        gonio(&run_dir(tmp.path(), t), t, &args);
    }
    let n = assert_same("gonio acquire", &out[0], &out[1]);
    assert!(out[0].join("plan.json").is_file());
    // manifest, journal, plan and 30 measured images (6 retro pairs are skipped).
    assert!(n >= 33, "only {n} files");
    let plan: serde_json::Value = serde_json::from_slice(&std::fs::read(out[0].join("plan.json")).unwrap()).unwrap();
    assert!(
        plan["budget"]["time_cap_s"].is_null(),
        "default budget has no wall-clock cap"
    );
    assert!(plan.get("plan_time_s").is_none(), "plan.json holds no wall-clock time");
}

#[test]
fn sim_btf_and_pvmf_are_byte_identical_across_thread_counts_under_load() {
    let tmp = tempfile::tempdir().unwrap();
    let _load = Load::start(120);
    let btf = [
        "sim",
        "btf",
        "--sweep",
        "fibonacci:6",
        "--size",
        "24",
        "--json",
        "--out",
        "btf",
    ];
    let pvmf = [
        "compress",
        "btf",
        "--method",
        "pvmf",
        "-c",
        "3",
        "--no-eval",
        "--json",
        "--out",
        "pvmf.gbtf",
    ];
    for t in 1..=2 {
        // Each run compresses its own dataset under the same relative path (the .gbtf
        // header records the path it was given).
        gonio(&run_dir(tmp.path(), t), t, &btf);
        gonio(&run_dir(tmp.path(), t), t, &pvmf);
    }
    let (a, b) = (run_dir(tmp.path(), 1), run_dir(tmp.path(), 2));
    assert_same("gonio sim btf", &a.join("btf"), &b.join("btf"));
    assert_same(
        "gonio compress --method pvmf",
        &a.join("pvmf.gbtf"),
        &b.join("pvmf.gbtf"),
    );
}
