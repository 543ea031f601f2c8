//! Same bytes anywhere (`gonio_dataset::store::provenance`): every command that records an input
//! in its output (compress, synthesize from a file and from a dataset, complete, fit, the
//! material and Zarr exports) and the commands whose output names itself (acquire, merge),
//! run on copies of the same inputs in two different directories, write the same bytes.
//!
//! The two trees are `ROOT/one/in`, `ROOT/one/out` and `ROOT/two/deeper/level/in`,
//! `ROOT/two/deeper/level/out`: the outputs sit at the same offset from the inputs (`../in`),
//! nothing else is alike. Every path is passed absolute and every command runs in a third
//! directory, so neither the working directory nor the typed paths can make them agree.
//! Compared are the bytes of every output file, less the fields that measure the run itself
//! ([`common::hashes`]; and a fit's `fit_seconds`).

use crate::common;

use common::bin;
use common::hashes::{comparable, sha};
use gonio::store::{self, Dataset};
use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

/// (step, arguments with `IN` and `OUT` standing for the two directories, outputs under OUT).
fn steps() -> Vec<(&'static str, Vec<&'static str>, Vec<&'static str>)> {
    #[allow(unused_mut)]
    let mut v: Vec<(&'static str, Vec<&'static str>, Vec<&'static str>)> = vec![
        (
            "acquire",
            vec![
                "acquire",
                "--rig",
                "IN/rig.toml",
                "--sweep",
                "IN/sweep6.toml",
                "--size",
                "32x32",
                "--plan-time",
                "0",
                "--seed",
                "7",
                "--out",
                "OUT/acq",
            ],
            vec!["acq"],
        ),
        (
            "merge",
            vec!["merge", "IN/part1", "IN/part2", "--out", "OUT/merged"],
            vec!["merged"],
        ),
        (
            "compress-pca",
            vec![
                "compress",
                "IN/btf",
                "--method",
                "pca",
                "-c",
                "4",
                "--out",
                "OUT/pca.gbtf",
            ],
            vec!["pca.gbtf"],
        ),
        (
            "compress-dfmf",
            vec![
                "compress",
                "IN/btf",
                "--method",
                "dfmf",
                "-c",
                "3",
                "--out",
                "OUT/dfmf.btf",
            ],
            vec!["dfmf.btf"],
        ),
        (
            "compress-target",
            vec![
                "compress",
                "IN/btf",
                "--method",
                "pca",
                "--target-ratio",
                "4",
                "--out",
                "OUT/target.gbtf",
            ],
            vec!["target.gbtf"],
        ),
        (
            "synthesize-gbtf",
            vec![
                "synthesize",
                "IN/pca.gbtf",
                "--method",
                "quilting",
                "--size",
                "48x40",
                "--block",
                "8",
                "--out",
                "OUT/quilt.gbtf",
            ],
            vec!["quilt.gbtf", "quilt.texelmap.png"],
        ),
        (
            "synthesize-btf",
            vec![
                "synthesize",
                "IN/dfmf.btf",
                "--method",
                "tile",
                "--size",
                "48x40",
                "--out",
                "OUT/tile.btf",
            ],
            vec!["tile.btf", "tile.texelmap.png"],
        ),
        (
            "synthesize-dataset",
            vec![
                "synthesize",
                "IN/btf",
                "--method",
                "tile",
                "--size",
                "48x40",
                "--out",
                "OUT/ds.gbtf",
            ],
            vec!["ds.gbtf", "ds.texelmap.png"],
        ),
        (
            "complete",
            vec!["complete", "IN/sparse", "--prior", "IN/p.gprior", "--out", "OUT/full"],
            vec!["full"],
        ),
        (
            "fit-per-texel",
            vec![
                "fit",
                "IN/btf",
                "--white",
                "IN/white",
                "--model",
                "gltf",
                "--per-texel",
                "--texel-iterations",
                "2",
                "--out",
                "OUT/fit.gbtf",
            ],
            vec!["fit.gbtf"],
        ),
        (
            "fit-average",
            vec![
                "fit",
                "IN/btf",
                "--white",
                "IN/white",
                "--model",
                "lafortune",
                "--out",
                "OUT/fit.json",
            ],
            vec!["fit.json"],
        ),
        (
            "export-gltf",
            vec!["export", "IN/fit.gbtf", "--format", "gltf", "OUT/mat.glb"],
            vec!["mat.glb"],
        ),
        (
            "export-rgl",
            vec!["export", "IN/fit.gbtf", "--format", "rgl-bsdf", "OUT/avg.bsdf"],
            vec!["avg.bsdf"],
        ),
    ];
    #[cfg(feature = "zarr")]
    v.push((
        "export-zarr",
        vec!["export", "IN/btf", "--format", "zarr", "OUT/btf.zarr"],
        vec!["btf.zarr"],
    ));
    v
}

fn run(cwd: &Path, args: &[String]) {
    let o = Command::new(bin())
        .current_dir(cwd)
        .env("RAYON_NUM_THREADS", "2")
        .env("RUST_LOG", "warn")
        .args(args)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "gonio {} failed: {}",
        args.join(" "),
        String::from_utf8_lossy(&o.stderr)
    );
}

fn sargs(a: &[&str]) -> Vec<String> {
    a.iter().map(|s| s.to_string()).collect()
}

/// The inputs, made once in `src`: the reduced rig and sweep, a dataset and its white
/// standard, a sharded run's two parts, a PCA `.gbtf`, a DFMF `.btf`, a glTF fit, a prior
/// and a sparse dataset for it.
fn make_inputs(src: &Path) {
    std::fs::create_dir_all(src).unwrap();
    common::write_scene(src);
    std::fs::rename(src.join("rig_small.toml"), src.join("rig.toml")).unwrap();
    let p = |n: &str| src.join(n).display().to_string();
    for (sample, out) in [("wallpaper", "btf"), ("white-standard", "white")] {
        run(
            src,
            &sargs(&[
                "sim",
                "btf",
                "--sample",
                sample,
                "--sweep",
                "fibonacci:6",
                "--size",
                "32",
                "--out",
                &p(out),
            ]),
        );
    }
    for (shard, out) in [("1/2", "part1"), ("2/2", "part2")] {
        run(
            src,
            &sargs(&[
                "sim",
                "btf",
                "--sweep",
                "fibonacci:6",
                "--size",
                "32",
                "--shard",
                shard,
                "--out",
                &p(out),
            ]),
        );
    }
    run(
        src,
        &sargs(&[
            "compress",
            &p("btf"),
            "--method",
            "pca",
            "-c",
            "4",
            "--out",
            &p("pca.gbtf"),
        ]),
    );
    run(
        src,
        &sargs(&[
            "compress",
            &p("btf"),
            "--method",
            "dfmf",
            "-c",
            "3",
            "--out",
            &p("dfmf.btf"),
        ]),
    );
    run(
        src,
        &sargs(&[
            "fit",
            &p("btf"),
            "--white",
            &p("white"),
            "--model",
            "gltf",
            "--per-texel",
            "--texel-iterations",
            "2",
            "--out",
            &p("fit.gbtf"),
        ]),
    );
    // A prior over a 12-direction sweep, and a dataset measured on every third pair of it.
    for (sample, out) in [("wallpaper", "m1"), ("white-standard", "m2")] {
        run(
            src,
            &sargs(&[
                "sim",
                "btf",
                "--sample",
                sample,
                "--sweep",
                "fibonacci:12",
                "--size",
                "16",
                "--out",
                &p(out),
            ]),
        );
    }
    run(
        src,
        &sargs(&[
            "prior",
            "build",
            &p("m1"),
            &p("m2"),
            "--components",
            "4",
            "--texels",
            "64",
            "--out",
            &p("p.gprior"),
        ]),
    );
    let (header, records) = store::load(&src.join("m1")).unwrap();
    let mut ds = Dataset::create(&src.join("sparse"), &header, false).unwrap();
    for r in records.iter().filter(|r| r.index % 3 == 0) {
        let img = store::read_exr(&src.join("m1").join(r.image.as_ref().unwrap())).unwrap();
        ds.store(r.clone(), Some(&img), None).unwrap();
    }
    ds.finish(&serde_json::json!({})).unwrap();
    drop(ds);
    for m in ["m1", "m2"] {
        std::fs::remove_dir_all(src.join(m)).unwrap();
    }
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let p = e.unwrap().path();
        let t = to.join(p.file_name().unwrap());
        if p.is_dir() {
            copy_tree(&p, &t);
        } else {
            std::fs::copy(&p, &t).unwrap();
        }
    }
}

/// The comparable bytes' SHA-256 of every file under `p` (or of the file `p`), by path
/// relative to `p`.
fn hashes(p: &Path) -> BTreeMap<String, String> {
    fn one(rel: &str, bytes: &[u8]) -> String {
        if rel.ends_with(".json") && !rel.ends_with("manifest.json") && !rel.contains(".zarr") {
            // A fit's own wall-clock reading.
            let mut v: serde_json::Value = serde_json::from_slice(bytes).unwrap();
            if let Some(o) = v.as_object_mut() {
                o.remove("fit_seconds");
            }
            return sha(&serde_json::to_vec(&v).unwrap());
        }
        sha(&comparable(rel, bytes))
    }
    common::hashes::hashes_by(p, &one)
}

fn run_tree(cwd: &Path, base: &Path) -> BTreeMap<String, String> {
    let (inp, out) = (base.join("in"), base.join("out"));
    std::fs::create_dir_all(&out).unwrap();
    let mut got = BTreeMap::new();
    for (name, args, outputs) in steps() {
        let args: Vec<String> = args
            .iter()
            .map(|a| {
                if let Some(rest) = a.strip_prefix("IN/") {
                    inp.join(rest).display().to_string()
                } else if let Some(rest) = a.strip_prefix("OUT/") {
                    out.join(rest).display().to_string()
                } else {
                    a.to_string()
                }
            })
            .collect();
        run(cwd, &args);
        for o in outputs {
            for (rel, h) in hashes(&out.join(o)) {
                got.insert(format!("{name}/{o}/{rel}"), h);
            }
        }
    }
    got
}

#[test]
fn outputs_are_the_same_bytes_wherever_the_inputs_sit() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let src = root.join("src");
    make_inputs(&src);
    let (one, two) = (root.join("one"), root.join("two/deeper/level"));
    copy_tree(&src, &one.join("in"));
    copy_tree(&src, &two.join("in"));
    let cwd = root.join("elsewhere");
    std::fs::create_dir_all(&cwd).unwrap();
    let a = run_tree(&cwd, &one);
    let b = run_tree(&cwd, &two);
    assert_eq!(
        a.keys().collect::<Vec<_>>(),
        b.keys().collect::<Vec<_>>(),
        "the two runs wrote different files"
    );
    let differ: Vec<&String> = a.keys().filter(|k| a[*k] != b[*k]).collect();
    assert!(
        differ.is_empty(),
        "outputs differ between inputs in {} and in {}: {differ:?}",
        one.display(),
        two.display()
    );
    // The recorded paths and hashes: relative to the output's directory, and the input's.
    let g = gonio::compress::Gbtf::read(&one.join("out/pca.gbtf")).unwrap();
    assert_eq!(g.header.source["dataset"], "../in/btf");
    // A dataset's SHA-256: of the `sha256sum`-style listing of its images' recorded hashes.
    let (_, records) = store::load(&one.join("in/btf")).unwrap();
    let listing: String = records
        .iter()
        .filter_map(|r| Some(format!("{}  {}\n", r.image_sha256.as_ref()?, r.image.as_ref()?)))
        .collect();
    assert_eq!(
        g.header.source["dataset_sha256"],
        serde_json::json!(sha(listing.as_bytes()))
    );
    assert!(a.len() > 20, "only {} files compared", a.len());
}
