//! `gonio export --format zarr` through the binary, read back with zarrs: a tiny simulated
//! BTF (4 × 4 directions at 8² texels) exported to Zarr equals the f16 conversion of its
//! EXRs bit for bit; `--shard I/N` parts written in any order into one store give the
//! single-process store byte for byte; a shard part of a dataset exports its missing views
//! as NaN with status 0 (never zero); bad `--shard` forms and foreign outputs are refused.

use crate::common;

use common::bin;
use gonio::store::export::zarr::{STATUS_MEASURED, STATUS_MISSING};
use half::f16;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::Arc;
use zarrs::array::Array;
use zarrs::filesystem::FilesystemStore;

fn gonio(cwd: &Path, args: &[&str]) -> Output {
    Command::new(bin()).current_dir(cwd).args(args).output().unwrap()
}

fn ok(cwd: &Path, args: &[&str]) -> String {
    let o = gonio(cwd, args);
    assert!(
        o.status.success(),
        "gonio {} failed: {}",
        args.join(" "),
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn fails(cwd: &Path, args: &[&str]) -> String {
    let o = gonio(cwd, args);
    assert!(!o.status.success(), "gonio {} should have failed", args.join(" "));
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Relative path → bytes of every file under `dir`, sorted.
fn files(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    fn walk(root: &Path, d: &Path, out: &mut Vec<(PathBuf, Vec<u8>)>) {
        for e in std::fs::read_dir(d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                out.push((p.strip_prefix(root).unwrap().to_path_buf(), std::fs::read(&p).unwrap()));
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}

fn open(store: &Path, name: &str) -> Array<FilesystemStore> {
    let fs = Arc::new(FilesystemStore::new(store).unwrap());
    Array::open(fs, &format!("/{name}")).unwrap()
}

fn read_all<T: zarrs::array::ElementOwned>(a: &Array<FilesystemStore>) -> Vec<T> {
    a.retrieve_array_subset::<Vec<T>>(&a.subset_all()).unwrap()
}

/// The dataset's images as f16, `[view][light]` flattened, NaN where no record.
fn dataset_f16(ds: &Path, nv: usize, nl: usize, texels: usize) -> Vec<f16> {
    let (_, records) = gonio::store::load(ds).unwrap();
    let mut out = vec![f16::NAN; nv * nl * texels * 3];
    for r in records {
        let Some(img) = &r.image else { continue };
        let img = gonio::store::read_exr(&ds.join(img)).unwrap();
        let at = r.index * texels * 3;
        for (d, s) in out[at..at + texels * 3].iter_mut().zip(&img.data) {
            *d = f16::from_f32(*s);
        }
    }
    out
}

#[test]
fn zarr_export_is_bit_exact_and_shards_fill_one_store() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let btf = ["sim", "btf", "--sweep", "fibonacci:4", "--size", "8", "--json"];
    ok(t, &[&btf[..], &["--out", "ds"]].concat());
    let report = ok(
        t,
        &[
            "export",
            "ds",
            "--format",
            "zarr",
            "full.zarr",
            "--mean-image",
            "mean.npy",
            "--json",
        ],
    );
    let report: serde_json::Value = serde_json::from_str(&report).unwrap();
    assert_eq!(report["shape"], serde_json::json!([4, 4, 8, 8, 3]));
    assert_eq!(report["shard_shape"], serde_json::json!([1, 4, 8, 8, 3]));
    assert_eq!(report["chunk_shape"], serde_json::json!([1, 1, 8, 8, 3]));
    assert_eq!(
        (report["measured"].as_u64(), report["missing"].as_u64()),
        (Some(16), Some(0))
    );

    // Values: bit-exact against the dataset's EXRs.
    let full = t.join("full.zarr");
    let a = open(&full, "btf");
    assert_eq!(a.shape(), &[4, 4, 8, 8, 3]);
    let got: Vec<f16> = read_all(&a);
    let want = dataset_f16(&t.join("ds"), 4, 4, 64);
    assert_eq!(got.len(), want.len());
    assert!(got.iter().zip(&want).all(|(g, w)| g.to_bits() == w.to_bits()));
    assert!(got.iter().any(|v| v.to_f32() > 0.0), "a rendered BTF is not all zero");
    let meta = std::fs::read_to_string(full.join("btf/zarr.json")).unwrap();
    for needle in [
        r#""dimension_names""#,
        r#""view""#,
        r#""channel""#,
        r#""sharding_indexed""#,
        r#""zstd""#,
        r#""crc32c""#,
        r#""fill_value": "NaN""#,
    ] {
        assert!(meta.contains(needle), "{needle} not in btf/zarr.json:\n{meta}");
    }
    let status: Vec<u8> = read_all(&open(&full, "status"));
    assert_eq!(status, vec![STATUS_MEASURED; 16]);
    // Coordinates: the sweep's directions as the manifest records them.
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(t.join("ds/manifest.json")).unwrap()).unwrap();
    let views = manifest["sweep"]["views_deg"].as_array().unwrap();
    let theta: Vec<f64> = read_all(&open(&full, "view_theta"));
    let phi: Vec<f64> = read_all(&open(&full, "light_phi"));
    for v in 0..4 {
        assert_eq!(theta[v], views[v][0].as_f64().unwrap());
        assert_eq!(phi[v], manifest["sweep"]["lights_deg"][v][1].as_f64().unwrap());
    }
    let group: serde_json::Value = serde_json::from_slice(&std::fs::read(full.join("zarr.json")).unwrap()).unwrap();
    assert_eq!(group["attributes"]["gonio"]["values"], manifest["values"]);
    assert_eq!(group["attributes"]["gonio"]["missing"], 0);

    // Mean image: the f64 mean of the f16 values over the 16 pairs.
    let npy = std::fs::read(t.join("mean.npy")).unwrap();
    let body = &npy[npy.len() - 8 * 8 * 3 * 8..];
    for k in 0..8 * 8 * 3 {
        let m = f64::from_le_bytes(body[k * 8..k * 8 + 8].try_into().unwrap());
        let sum: f64 = (0..16).map(|p| f64::from(want[p * 192 + k])).sum();
        assert_eq!(m.to_bits(), (sum / 16.0).to_bits(), "texel-channel {k}");
    }

    // Shards, run in any order into one store: the single-process bytes.
    for i in [3, 1, 2] {
        let shard = format!("{i}/3");
        let out = ok(
            t,
            &[
                "export",
                "ds",
                "--format",
                "zarr",
                "sharded.zarr",
                "--shard",
                &shard,
                "--json",
            ],
        );
        let r: serde_json::Value = serde_json::from_str(&out).unwrap();
        assert_eq!(r["shard"]["index"], i);
    }
    let (a, b) = (files(&full), files(&t.join("sharded.zarr")));
    assert_eq!(
        a.iter().map(|f| &f.0).collect::<Vec<_>>(),
        b.iter().map(|f| &f.0).collect::<Vec<_>>()
    );
    assert!(a == b, "sharded store differs from the single-process one");
    assert_eq!(
        a.iter().filter(|(p, _)| p.starts_with("btf/c")).count(),
        4,
        "one shard per view"
    );

    // A part of a sharded sim btf: its missing views are NaN with status 0, not zero.
    ok(t, &[&btf[..], &["--shard", "2/2", "--out", "part"]].concat());
    let out = ok(t, &["export", "part", "--format", "zarr", "part.zarr", "--json"]);
    let r: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!((r["measured"].as_u64(), r["missing"].as_u64()), (Some(8), Some(8)));
    let part = t.join("part.zarr");
    let status: Vec<u8> = read_all(&open(&part, "status"));
    assert_eq!(&status[..8], &[STATUS_MISSING; 8]);
    assert_eq!(&status[8..], &[STATUS_MEASURED; 8]);
    let got: Vec<f16> = read_all(&open(&part, "btf"));
    assert!(got[..8 * 192].iter().all(|v| v.is_nan()), "missing pairs must be NaN");
    assert!(got[8 * 192..]
        .iter()
        .zip(&want[8 * 192..])
        .all(|(g, w)| g.to_bits() == w.to_bits()));
    assert!(
        !part.join("btf/c/0/0/0/0/0").exists(),
        "no shard for a view with no data"
    );

    // Refusals.
    for bad in ["3/2", "0/0", "x"] {
        let e = fails(t, &["export", "ds", "--format", "zarr", "bad.zarr", "--shard", bad]);
        assert!(e.contains("the valid form is I/N"), "{bad}: {e}");
    }
    let e = fails(t, &["export", "ds", "--format", "zarr", "bad.zarr", "--shard", "5/5"]);
    assert!(e.contains("cannot be split into 5 shards"), "{e}");
    let e = fails(t, &["export", "ds", "--format", "zarr", "full.zarr"]);
    assert!(e.contains("already exists") && e.contains("--force"), "{e}");
    ok(t, &["export", "ds", "--format", "zarr", "full.zarr", "--force"]);
    assert!(files(&full) == b, "--force rewrites the same bytes");
    let e = fails(t, &["export", "ds", "--format", "zarr", "part.zarr", "--shard", "1/2"]);
    assert!(e.contains("holds a different Zarr export"), "{e}");
    let e = fails(t, &["export", "ds", "--format", "npy", "x.npy", "--shard", "1/2"]);
    assert!(e.contains("--format zarr only"), "{e}");
}
