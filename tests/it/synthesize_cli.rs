//! `gonio synthesize` end to end: a simulated BTF, compressed, grown to a larger size; the
//! output reads back through `gonio reconstruct`, bad inputs are refused with the reason,
//! and the same seed gives the same bytes at any thread count.

use crate::common::cli::{gonio, ok, refused, s};
use std::path::Path;

#[test]
fn synthesize_reconstruct_refuse_and_reproduce() {
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("ds");
    let ex = dir.path().join("ex.gbtf");
    ok(&["sim", "btf", "--size", "24", "--sweep", "fibonacci:3", "--out", s(&ds)]);
    ok(&["compress", s(&ds), "--method", "pca", "-c", "4", "--out", s(&ex)]);
    let out = dir.path().join("big.gbtf");
    let report = ok(&[
        "synthesize",
        s(&ex),
        "--method",
        "quilting",
        "--size",
        "50x40",
        "--block",
        "8",
        "--out",
        s(&out),
        "--json",
    ]);
    let r: serde_json::Value = serde_json::from_str(&report).unwrap();
    assert_eq!(r["width"], 50);
    assert!(r["k"].as_u64().unwrap() >= 1);
    assert!(dir.path().join("big.texelmap.png").exists());
    // Reconstruct a grid pair of the synthesized file (directions from its header).
    let bytes = std::fs::read(&out).unwrap();
    let hlen = u64::from_le_bytes(bytes[12..20].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[20..20 + hlen]).unwrap();
    assert_eq!(header["source"]["synthesis"]["texel_map"], "big.texelmap.png");
    let d = |v: &serde_json::Value| format!("{},{}", v[0], v[1]);
    let (l, v) = (d(&header["lights_deg"][0]), d(&header["views_deg"][1]));
    let exr = dir.path().join("pair.exr");
    let rec = ok(&[
        "reconstruct",
        s(&out),
        "--light",
        &l,
        "--view",
        &v,
        "--out",
        s(&exr),
        "--json",
    ]);
    assert!(rec.contains("50"), "{rec}");

    // Same seed, one thread versus two: identical files.
    for (name, method) in [("t1.gbtf", "wei-levoy"), ("t2.gbtf", "efros-leung")] {
        // Same file name in two folders: the header names the texel-map sidecar.
        for sub in ["one", "two"] {
            std::fs::create_dir_all(dir.path().join(sub)).unwrap();
        }
        let a = dir.path().join("one").join(name);
        let b = dir.path().join("two").join(name);
        for (p, t) in [(&a, "1"), (&b, "2")] {
            let o = gonio(
                &[
                    "synthesize",
                    s(&ex),
                    "--method",
                    method,
                    "--size",
                    "30x28",
                    "--levels",
                    "2",
                    "--neighbourhood",
                    "5",
                    "--window",
                    "5",
                    "--out",
                    s(p),
                ],
                Some(t),
            );
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        }
        assert!(
            std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap(),
            "{method}: 1 and 2 threads differ"
        );
    }

    let bad = dir.path().join("bad.gbtf");
    refused(
        &[
            "synthesize",
            s(&ex),
            "--method",
            "quilting",
            "--size",
            "20x40",
            "--out",
            s(&bad),
        ],
        &["smaller than the exemplar", "24×24"],
    );
    refused(
        &[
            "synthesize",
            s(&ex),
            "--method",
            "quilting",
            "--size",
            "48x48",
            "--block",
            "30",
            "--out",
            s(&bad),
        ],
        &["--block 30", "exemplar"],
    );
    refused(
        &[
            "synthesize",
            s(&ex),
            "--method",
            "tile",
            "--size",
            "48x48",
            "--k",
            "0",
            "--out",
            s(&bad),
        ],
        &["--k 0"],
    );
    // A dataset input is compressed in memory with PCA (--components): the output decodes
    // to what synthesizing from `gonio compress --method pca -c 4`'s file gives.
    let (from_ds, from_gbtf) = (dir.path().join("from-ds.gbtf"), dir.path().join("from-gbtf.gbtf"));
    let r: serde_json::Value = serde_json::from_str(&ok(&[
        "synthesize",
        s(&ds),
        "--components",
        "4",
        "--method",
        "tile",
        "--size",
        "48x48",
        "--out",
        s(&from_ds),
        "--json",
    ]))
    .unwrap();
    assert_eq!(r["from_dataset"]["components"], 4, "{r}");
    assert_eq!(r["model"], "pca", "{r}");
    ok(&[
        "synthesize",
        s(&ex),
        "--method",
        "tile",
        "--size",
        "48x48",
        "--out",
        s(&from_gbtf),
    ]);
    let decode = |f: &Path, name: &str| {
        let img = dir.path().join(name);
        ok(&["reconstruct", s(f), "--light", &l, "--view", &v, "--out", s(&img)]);
        std::fs::read(img).unwrap()
    };
    assert!(
        decode(&from_ds, "a.exr") == decode(&from_gbtf, "b.exr"),
        "dataset input ≠ its PCA file's"
    );
    refused(
        &[
            "synthesize",
            s(&ds),
            "--components",
            "0",
            "--method",
            "tile",
            "--size",
            "48x48",
            "--out",
            s(&bad),
        ],
        &["--components 0", "ds"],
    );
    refused(
        &[
            "synthesize",
            s(&ex),
            "--method",
            "magic",
            "--size",
            "48x48",
            "--out",
            s(&bad),
        ],
        &["unknown synthesis method"],
    );
    assert!(!bad.exists());
}

/// The float32 `H × W × 3` body of a `.npy` written by `gonio reconstruct`.
fn npy_f32(path: &Path, texels: usize) -> Vec<f32> {
    let b = std::fs::read(path).unwrap();
    b[b.len() - texels * 12..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect()
}

/// A UBO2014 DFMF `.btf` exemplar (made by `gonio compress --method dfmf --format btf`):
/// the synthesized `.btf` decodes through `gonio reconstruct`, for every (light, view) of
/// the grid, to exactly the input's values at the texels the texel map names; `gonio
/// render` reads it; the same seed gives the same bytes at 1 and 2 threads; outputs the
/// container cannot hold and a `.gbtf` name are refused.
#[test]
fn synthesize_from_a_ubo2014_btf() {
    let dir = tempfile::tempdir().unwrap();
    let ds = dir.path().join("ds");
    let ex = dir.path().join("ex.btf");
    ok(&["sim", "btf", "--size", "24", "--sweep", "fibonacci:3", "--out", s(&ds)]);
    ok(&[
        "compress",
        s(&ds),
        "--method",
        "dfmf",
        "-c",
        "3",
        "--format",
        "btf",
        "--no-eval",
        "--out",
        s(&ex),
    ]);
    let out = dir.path().join("big.btf");
    let r: serde_json::Value = serde_json::from_str(&ok(&[
        "synthesize",
        s(&ex),
        "--method",
        "quilting",
        "--size",
        "50x40",
        "--block",
        "8",
        "--out",
        s(&out),
        "--json",
    ]))
    .unwrap();
    assert_eq!(r["model"], "dfmf-btf (log-yuv)", "{r}");
    assert_eq!(r["embedding"], "log-yuv", "{r}");
    assert_eq!(r["compact"], true, "{r}");
    let map = gonio::synthesize::output::read_texel_map(&dir.path().join("big.texelmap.png"), 24, 24).unwrap();
    assert_eq!((map.width, map.height), (50, 40));
    assert!(
        map.src
            .iter()
            .enumerate()
            .any(|(t, &src)| src as usize != (t / 50) * 24 + t % 50),
        "the map is a plain copy"
    );
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(ds.join("manifest.json")).unwrap()).unwrap();
    let sweep = &manifest.get("header").unwrap_or(&manifest)["sweep"];
    let d = |v: &serde_json::Value| format!("{},{}", v[0], v[1]);
    let (lights, views) = (
        sweep["lights_deg"].as_array().unwrap(),
        sweep["views_deg"].as_array().unwrap(),
    );
    assert!(lights.len() * views.len() >= 9);
    for (li, l) in lights.iter().enumerate() {
        for (vi, v) in views.iter().enumerate() {
            let (a, b) = (dir.path().join("in.npy"), dir.path().join("out.npy"));
            for (f, img) in [(&ex, &a), (&out, &b)] {
                ok(&["reconstruct", s(f), "--light", &d(l), "--view", &d(v), "--out", s(img)]);
            }
            let (a, b) = (npy_f32(&a, 24 * 24), npy_f32(&b, 50 * 40));
            for (t, &src) in map.src.iter().enumerate() {
                for c in 0..3 {
                    assert_eq!(
                        b[t * 3 + c].to_bits(),
                        a[src as usize * 3 + c].to_bits(),
                        "pair (light {li}, view {vi}), texel {t}"
                    );
                }
            }
        }
    }
    let png = dir.path().join("sphere.png");
    ok(&[
        "render",
        s(&out),
        "--light",
        &d(&lights[0]),
        "--view",
        &d(&views[0]),
        "--shape",
        "sphere",
        "--size",
        "32x32",
        "--out",
        s(&png),
    ]);
    assert!(png.exists());

    // 1 versus 2 threads: identical .btf and texel map.
    for sub in ["one", "two"] {
        std::fs::create_dir_all(dir.path().join(sub)).unwrap();
    }
    let (a, b) = (dir.path().join("one/w.btf"), dir.path().join("two/w.btf"));
    for (p, t) in [(&a, "1"), (&b, "2")] {
        let o = gonio(
            &[
                "synthesize",
                s(&ex),
                "--method",
                "wei-levoy",
                "--size",
                "30x28",
                "--levels",
                "2",
                "--neighbourhood",
                "5",
                "--out",
                s(p),
            ],
            Some(t),
        );
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    assert!(
        std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap(),
        "1 and 2 threads differ"
    );
    assert!(
        std::fs::read(dir.path().join("one/w.texelmap.png")).unwrap()
            == std::fs::read(dir.path().join("two/w.texelmap.png")).unwrap()
    );

    let bad = dir.path().join("bad.btf");
    refused(
        &[
            "synthesize",
            s(&ex),
            "--method",
            "tile",
            "--size",
            "60000x60000",
            "--out",
            s(&bad),
        ],
        &["ex.btf", "32-bit", "--size"],
    );
    refused(
        &[
            "synthesize",
            s(&ex),
            "--method",
            "tile",
            "--size",
            "48x48",
            "--out",
            s(&dir.path().join("bad.gbtf")),
        ],
        &["bad.gbtf", "UBO2014", "*.btf"],
    );
    refused(
        &[
            "synthesize",
            s(&ex),
            "--method",
            "quilting",
            "--size",
            "20x40",
            "--out",
            s(&bad),
        ],
        &["smaller than the exemplar"],
    );
    assert!(!bad.exists() && !dir.path().join("bad.gbtf").exists());
}
