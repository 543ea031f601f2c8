//! Same bytes through a refactor: a fixed list of commands (an acquisition, `sim btf`,
//! every compression method, synthesis, a shard merge, the exports), each at 32² on a
//! small sweep, and the SHA-256 of every file they write, held against
//! `tests/it/golden-hashes.txt`.
//!
//! The list is the contract of a move: splitting a crate, renaming a module or changing
//! how an option is read must leave every line of the file as it was. A change that
//! *means* to change an output (a new field, a fixed bug) re-blesses the file and says so in
//! its commit:
//!
//! ```sh
//! GONIO_BLESS=1 cargo test -p gonio --test it golden::
//! ```
//!
//! The hashes leave out only the fields that measure the run itself (wall-clock readings,
//! peak memory; [`common::hashes`]). Every command runs with `RAYON_NUM_THREADS=2` in one
//! temporary directory under relative names, so no absolute path reaches an output.
//! The hashes are of this machine kind's floating point: a different CPU family may
//! legitimately differ in the last bit of a float kernel; the test then names the files.

use crate::common;

use common::hashes::hashes;
use common::{bin, write_scene};
use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

/// The command list: (step name, arguments, output written relative to the work dir).
/// `RIG` and `SWEEP` are replaced by the reduced scene of [`write_scene`].
const STEPS: &[(&str, &[&str], &str)] = &[
    (
        "acquire",
        &[
            "acquire", "--rig", "RIG", "--sweep", "SWEEP", "--size", "32x32", "--seed", "7", "--json", "--out", "acq",
        ],
        "acq",
    ),
    (
        "sim-btf",
        &[
            "sim",
            "btf",
            "--sweep",
            "fibonacci:6",
            "--size",
            "32",
            "--json",
            "--out",
            "btf",
        ],
        "btf",
    ),
    (
        "sim-btf-shard-1",
        &[
            "sim",
            "btf",
            "--sweep",
            "fibonacci:6",
            "--size",
            "32",
            "--shard",
            "1/2",
            "--out",
            "part1",
        ],
        "part1",
    ),
    (
        "sim-btf-shard-2",
        &[
            "sim",
            "btf",
            "--sweep",
            "fibonacci:6",
            "--size",
            "32",
            "--shard",
            "2/2",
            "--out",
            "part2",
        ],
        "part2",
    ),
    (
        "merge",
        &["merge", "part1", "part2", "--out", "merged", "--json"],
        "merged",
    ),
    (
        "pca",
        &[
            "compress", "btf", "--method", "pca", "-c", "4", "--json", "--out", "pca.gbtf",
        ],
        "pca.gbtf",
    ),
    (
        "pvmf",
        &[
            "compress",
            "btf",
            "--method",
            "pvmf",
            "-c",
            "3",
            "--json",
            "--out",
            "pvmf.gbtf",
        ],
        "pvmf.gbtf",
    ),
    (
        "dfmf",
        &[
            "compress", "btf", "--method", "dfmf", "-c", "3", "--json", "--out", "dfmf.btf",
        ],
        "dfmf.btf",
    ),
    (
        "dfmf-lab-q",
        &[
            "compress",
            "btf",
            "--method",
            "dfmf",
            "--color-model",
            "lab",
            "-c",
            "3",
            "--quantize",
            "10",
            "--json",
            "--out",
            "dfmf-lab.gbtf",
        ],
        "dfmf-lab.gbtf",
    ),
    (
        "local-pca",
        &[
            "compress",
            "btf",
            "--method",
            "local-pca",
            "-c",
            "2",
            "--clusters",
            "3",
            "--subspace",
            "8",
            "--json",
            "--out",
            "lpca.gbtf",
        ],
        "lpca.gbtf",
    ),
    (
        "median-cut",
        &[
            "compress",
            "btf",
            "--method",
            "median-cut",
            "--boxes",
            "16",
            "--json",
            "--out",
            "mc.gbtf",
        ],
        "mc.gbtf",
    ),
    (
        "homomorphic",
        &[
            "compress",
            "btf",
            "--method",
            "homomorphic",
            "-c",
            "3",
            "--json",
            "--out",
            "hom.gbtf",
        ],
        "hom.gbtf",
    ),
    (
        "nd",
        &[
            "compress", "btf", "--method", "nd", "-c", "3", "--json", "--out", "nd.gbtf",
        ],
        "nd.gbtf",
    ),
    (
        "svd-j",
        &[
            "compress",
            "btf",
            "--method",
            "svd-j",
            "-c",
            "2",
            "--json",
            "--out",
            "svdj.gbtf",
        ],
        "svdj.gbtf",
    ),
    (
        "gshd",
        &[
            "compress",
            "btf",
            "--method",
            "gshd",
            "-c",
            "3",
            "--json",
            "--out",
            "gshd.gbtf",
        ],
        "gshd.gbtf",
    ),
    (
        "cmf",
        &[
            "compress", "btf", "--method", "cmf", "-c", "2", "--json", "--out", "cmf.gbtf",
        ],
        "cmf.gbtf",
    ),
    (
        "synthesize-quilting",
        &[
            "synthesize",
            "pca.gbtf",
            "--method",
            "quilting",
            "--size",
            "48x40",
            "--block",
            "8",
            "--json",
            "--out",
            "quilt.gbtf",
        ],
        "quilt.gbtf",
    ),
    (
        "synthesize-tile",
        &[
            "synthesize",
            "pvmf.gbtf",
            "--method",
            "tile",
            "--size",
            "48x40",
            "--json",
            "--out",
            "tile.gbtf",
        ],
        "tile.gbtf",
    ),
    (
        "export-npy",
        &["export", "btf", "--format", "npy", "btf.npy", "--json"],
        "btf.npy",
    ),
    (
        "export-ubo2003",
        &["export", "btf", "--format", "ubo2003", "btf.zip", "--json"],
        "btf.zip",
    ),
];

/// The golden file: one `step/path sha256` line per written file, sorted.
fn golden_path() -> &'static Path {
    static P: std::sync::OnceLock<std::path::PathBuf> = std::sync::OnceLock::new();
    P.get_or_init(|| common::root().join("tests/it/golden-hashes.txt"))
}

fn run_all(dir: &Path) -> BTreeMap<String, String> {
    let (rig, sweep) = write_scene(dir);
    let mut out = BTreeMap::new();
    for (name, args, output) in STEPS {
        let args: Vec<String> = args
            .iter()
            .map(|a| match *a {
                "RIG" => rig.file_name().unwrap().to_string_lossy().into_owned(),
                "SWEEP" => sweep.file_name().unwrap().to_string_lossy().into_owned(),
                a => a.to_string(),
            })
            .collect();
        let o = Command::new(bin())
            .current_dir(dir)
            .env("RAYON_NUM_THREADS", "2")
            .env("RUST_LOG", "warn")
            .args(&args)
            .output()
            .unwrap();
        assert!(
            o.status.success(),
            "step {name}: gonio {} failed: {}",
            args.join(" "),
            String::from_utf8_lossy(&o.stderr)
        );
        for (rel, h) in hashes(&dir.join(output)) {
            let key = if rel.is_empty() {
                format!("{name}/{output}")
            } else {
                format!("{name}/{output}/{rel}")
            };
            out.insert(key, h);
        }
    }
    out
}

#[test]
fn fixed_command_list_writes_the_golden_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let got = run_all(tmp.path());
    let text: String = got.iter().map(|(k, v)| format!("{k} {v}\n")).collect();
    if std::env::var_os("GONIO_BLESS").is_some() {
        std::fs::write(golden_path(), &text).unwrap();
        eprintln!("golden: wrote {} hashes to {}", got.len(), golden_path().display());
        return;
    }
    let want_text = std::fs::read_to_string(golden_path())
        .unwrap_or_else(|e| panic!("{}: {e} (create it with GONIO_BLESS=1)", golden_path().display()));
    let want: BTreeMap<String, String> = want_text
        .lines()
        .filter_map(|l| l.split_once(' '))
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect();
    let missing: Vec<&String> = want.keys().filter(|k| !got.contains_key(*k)).collect();
    let extra: Vec<&String> = got.keys().filter(|k| !want.contains_key(*k)).collect();
    let differ: Vec<&String> = want
        .keys()
        .filter(|k| got.get(*k).is_some_and(|h| h != &want[*k]))
        .collect();
    assert!(
        missing.is_empty() && extra.is_empty() && differ.is_empty(),
        "outputs changed against {}:\n  differ: {differ:?}\n  no longer written: {missing:?}\n  new: {extra:?}\n\
         (if the change is meant, re-bless with GONIO_BLESS=1 and say why in the commit)",
        golden_path().display()
    );
    assert!(got.len() > 100, "only {} files hashed", got.len());
}
