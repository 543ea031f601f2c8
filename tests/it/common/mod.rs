//! Helpers shared by the integration tests (`use crate::common;`).
//! Each module uses a subset of them, hence the `dead_code` allowance.
#![allow(dead_code)]

pub mod cli;
pub mod hashes;

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

/// The binary under test, copied once per test process: other builds sharing the target
/// directory may replace `target/debug/gonio` while a campaign runs (that happened here and
/// made a trial compare two different builds).
pub fn bin() -> &'static Path {
    static BIN: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    BIN.get_or_init(|| {
        let dir = bin_dir();
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("gonio");
        // A hard link keeps the old inode when cargo replaces the file; copy across devices.
        if std::fs::hard_link(env!("CARGO_BIN_EXE_gonio"), &p).is_err() {
            std::fs::copy(env!("CARGO_BIN_EXE_gonio"), &p).unwrap();
        }
        extern "C" fn remove_bin_dir() {
            let _ = std::fs::remove_dir_all(bin_dir());
        }
        // SAFETY: registers a plain function without captured state to run at exit.
        unsafe { libc::atexit(remove_bin_dir) };
        p
    })
}

fn bin_dir() -> PathBuf {
    std::env::temp_dir().join(format!("gonio-campaign-bin-{}", std::process::id()))
}

/// Write the reduced rig and sweep into `dir`; returns (rig, sweep) paths.
pub fn write_scene(dir: &Path) -> (PathBuf, PathBuf) {
    let default_rig = Path::new(env!("CARGO_MANIFEST_DIR")).join("devices/rigs/default.toml");
    let text = std::fs::read_to_string(&default_rig).unwrap();
    let mut small = text.clone();
    for (from, to) in [
        ("width = 768", "width = 192"),
        ("height = 640", "height = 160"),
        ("focal_length_px = 4300.0", "focal_length_px = 1075.0"),
    ] {
        assert!(
            small.contains(from),
            "{} no longer contains `{from}`",
            default_rig.display()
        );
        small = small.replacen(from, to, 1);
    }
    let rig = dir.join("rig_small.toml");
    std::fs::write(&rig, small).unwrap();
    let sweep = dir.join("sweep6.toml");
    std::fs::write(
        &sweep,
        "directions = [[0.0, 0.0], [30.0, 0.0], [30.0, 120.0], [45.0, 240.0], [60.0, 60.0], [75.0, 300.0]]\n",
    )
    .unwrap();
    (rig, sweep)
}

/// `gonio acquire` of the reduced scene: 32² images, no planning time, a fixed seed,
/// JSON progress discarded and stderr captured (the campaigns read the errors).
pub fn acquire_cmd(rig: &Path, sweep: &Path, out: &Path) -> Command {
    let mut c = Command::new(bin());
    c.arg("acquire")
        .arg("--rig")
        .arg(rig)
        .arg("--sweep")
        .arg(sweep)
        .args(["--size", "32x32", "--plan-time", "0", "--seed", "7", "--json", "--out"])
        .arg(out)
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    c
}

/// `gonio acquire --resume DIR`, output handled as by [`acquire_cmd`].
pub fn resume_cmd(dir: &Path) -> Command {
    let mut c = Command::new(bin());
    c.args(["acquire", "--json", "--resume"])
        .arg(dir)
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    c
}

/// Run [`acquire_cmd`] to its end.
pub fn acquire(rig: &Path, sweep: &Path, out: &Path) -> Output {
    acquire_cmd(rig, sweep, out).output().unwrap()
}

/// Run [`resume_cmd`] to its end.
pub fn resume(dir: &Path) -> Output {
    resume_cmd(dir).output().unwrap()
}

/// One row of the `faults:` table that tests/run.sh collects from every campaign.
pub fn fault_row(fault: &str, lost: impl std::fmt::Display, outcome: &str) {
    println!("faults: {:<58} | {:<5} | {outcome}", fault, lost.to_string());
}

/// Run a calibration recipe on a simulated rig file the way `gonio calibrate` does: the
/// recipe's target and simulator settings ([`gonio::calibrate::Recipe::sim_options`]), a
/// current-thread runtime, the recipe to its end.
// The error is matched by variant in the tests; its size does not matter here.
#[allow(clippy::result_large_err)]
pub fn run_recipe(
    recipe: &gonio::calibrate::Recipe,
    spec: &gonio_devices::rig::RigSpec,
) -> Result<gonio::calibrate::RunOutput, gonio::calibrate::CalibrateError> {
    let sample = gonio_simulator::SampleSpec::resolve(&recipe.target).unwrap();
    let rig = gonio::rig::Rig::build(spec, &sample, &recipe.sim_options()).unwrap();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(gonio::calibrate::run(recipe, &rig))
}

/// The workspace root: recipes and rig files are named relative to it.
pub fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// Run the gonio binary in the workspace root with `args`, warnings-only logs.
pub fn gonio(args: &[&str]) -> Output {
    gonio_in(root(), args)
}

/// Run the gonio binary in `dir` with `args`, warnings-only logs: paths a recipe names
/// relative to the working directory (`response = "cal/response/calibration.json"`,
/// `corrections = "cal"`) then resolve below `dir`.
pub fn gonio_in(dir: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_gonio"))
        .args(args)
        .current_dir(dir)
        .env("RUST_LOG", "warn")
        .output()
        .expect("running gonio")
}

/// A fresh, empty temporary directory `gonio-{tag}-{pid}-{name}`.
pub fn fresh_tmp(tag: &str, name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("gonio-{tag}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}
