//! `gonio fit` end to end on simulator samples of known models (`tests/data/fit/`):
//! `gonio sim btf` renders each (8 × 8 texels, Fibonacci 12 × 12 pairs) and the white
//! standard over the same sweep; the fit, calibrated by the white standard, recovers the
//! truth's parameters; the wrong family is reported worse; the per-texel fit finds both
//! materials of a checker and reports its ratio and PSNR; bad inputs are refused naming
//! the input.
//!
//! Tolerances, against the exact in-family fit of `fit::tests` (1 %): here the fit uses
//! the sweep's nominal directions while a texel 26 mm off the centre of the 60 mm sample
//! sees the camera (1 m) and lamp (1.2 m) up to 1.5° away from them. For a cosine lobe of
//! exponent n a direction error δ changes the lobe by about n·δ²/2 (1.4 % at n = 40,
//! δ = 1.5°), and the averaged highlight is that much wider: 5 % on the exponent and the
//! lobe's weight, 3 % on the diffuse albedo, 1° on the lobe's direction.

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

fn gonio(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_gonio")).args(args).output().unwrap()
}

fn ok(args: &[&str]) -> String {
    let o = gonio(args);
    assert!(
        o.status.success(),
        "gonio {args:?} failed:\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn refused(args: &[&str], needles: &[&str]) {
    let o = gonio(args);
    assert!(!o.status.success(), "gonio {args:?} should fail");
    let err = String::from_utf8_lossy(&o.stderr);
    for n in needles {
        assert!(err.contains(n), "gonio {args:?}: {n:?} not in\n{err}");
    }
}

fn sample(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/fit")
        .join(format!("{name}.toml"))
        .to_string_lossy()
        .into_owned()
}

/// The rendered datasets, once per test binary: (temp dir, white standard).
fn renders() -> &'static (tempfile::TempDir, PathBuf) {
    static R: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    R.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let render = |sample: &str, name: &str| {
            let out = dir.path().join(name);
            ok(&[
                "sim",
                "btf",
                "--sample",
                sample,
                "--sweep",
                "fibonacci:12",
                "--size",
                "8",
                "--out",
                out.to_str().unwrap(),
            ]);
            out
        };
        let white = render("white-standard", "white");
        for s in [
            "lafortune",
            "cook-torrance",
            "rough-conductor",
            "lafortune-checker",
            "gltf-checker",
        ] {
            render(&sample(s), s);
        }
        (dir, white)
    })
}

fn fit(name: &str, model: &str, extra: &[&str]) -> Value {
    let (dir, white) = renders();
    let ds = dir.path().join(name);
    let mut args = vec![
        "fit",
        ds.to_str().unwrap(),
        "--model",
        model,
        "--white",
        white.to_str().unwrap(),
        "--json",
    ];
    args.extend_from_slice(extra);
    serde_json::from_str(&ok(&args)).unwrap()
}

fn param(v: &Value, name: &str) -> f64 {
    v["fit"]["params"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p[0] == name)
        .unwrap_or_else(|| panic!("{name} in {}", v["fit"]["params"]))[1]
        .as_f64()
        .unwrap()
}

fn close(got: f64, want: f64, rel: f64, what: &str) {
    assert!(
        (got - want).abs() <= rel * want.abs(),
        "{what}: got {got}, want {want} ±{:.0} %",
        rel * 100.0
    );
}

#[test]
fn lafortune_sample_parameters_are_recovered() {
    let v = fit("lafortune", "lafortune", &[]);
    close(param(&v, "kd.r"), 0.25, 0.03, "kd.r");
    close(param(&v, "kd.g"), 0.18, 0.03, "kd.g");
    close(param(&v, "kd.b"), 0.10, 0.03, "kd.b");
    close(param(&v, "lobes[0].exponent"), 40.0, 0.05, "exponent");
    close(param(&v, "lobes[0].ks.g"), 0.3, 0.05, "ks");
    let g = param(&v, "lobes[0].gamma_rad").to_degrees();
    assert!((g - 135.0).abs() < 1.0, "γ {g}°");
}

#[test]
fn cook_torrance_sample_is_fitted_best_by_its_family() {
    let right = fit("cook-torrance", "cook-torrance", &[]);
    close(param(&right, "lobes[0].m"), 0.2, 0.05, "m");
    close(param(&right, "fresnel.eta"), 1.5, 0.05, "eta");
    close(param(&right, "kd.r"), 0.3, 0.03, "kd.r");
    let wrong = fit("cook-torrance", "lafortune", &[]);
    let (r, w) = (
        right["fit"]["rel_rms"].as_f64().unwrap(),
        wrong["fit"]["rel_rms"].as_f64().unwrap(),
    );
    assert!(w > 2.0 * r, "lafortune {w} vs cook-torrance {r}");
}

#[test]
fn rough_conductor_sample_is_fitted_best_by_its_family() {
    let right = fit("rough-conductor", "rough-conductor", &[]);
    close(param(&right, "alpha"), 0.2, 0.05, "alpha");
    let wrong = fit("rough-conductor", "ward", &[]);
    let (r, w) = (
        right["fit"]["rel_rms"].as_f64().unwrap(),
        wrong["fit"]["rel_rms"].as_f64().unwrap(),
    );
    assert!(w > 2.0 * r, "ward {w} vs rough-conductor {r}");
}

/// Per texel: each texel of the checker gets its own material's exponent (within 5 %), and
/// the SVBRDF is reported as a compression method with a ratio and a PSNR. Its `.gbtf`
/// (`--out F.gbtf`) decodes, through `compress::svbrdf`, to what the fitted models of the
/// material library evaluate (`fit::texel::SvbrdfFit`), and `gonio reconstruct` and
/// `gonio render` read it.
#[test]
fn per_texel_fit_finds_both_materials_and_its_file_decodes() {
    use gonio::compress::interp::BtfModel;
    use gonio::compress::svbrdf::Geometry;
    use gonio::compress::{CompressedBtf, Gbtf};
    use gonio::fit::texel::SvbrdfFit;
    use gonio::fit::{Family, ModelKind};
    let (dir, _) = renders();
    let out = dir.path().join("checker-fit.gbtf");
    let v = fit(
        "lafortune-checker",
        "lafortune",
        &["--per-texel", "--out", out.to_str().unwrap()],
    );
    let t = &v["per_texel"];
    assert_eq!(t["texels"], 64);
    let ratio = t["ratio"].as_f64().unwrap();
    let psnr = t["psnr_8bit_db"].as_f64().unwrap();
    let stored = t["stored_bytes"].as_u64().unwrap();
    assert_eq!(
        stored,
        std::fs::metadata(&out).unwrap().len(),
        "stored_bytes is the file"
    );
    // 144 pairs × 64 texels × 3 bytes raw against the file.
    assert!((ratio - 27648.0 / stored as f64).abs() < 1e-9, "{ratio}");
    assert!(psnr > 40.0, "PSNR {psnr} dB");
    let g = Gbtf::read(&out).unwrap();
    assert_eq!(g.header.method, "svbrdf");
    let family = Family::new(ModelKind::Lafortune, 1);
    let np = family.n_params();
    let ie = family
        .params
        .iter()
        .position(|p| p.name == "lobes[0].exponent")
        .unwrap();
    let mut found = [false; 2];
    for t in 0..64 {
        let n = g.blocks[0][t * np + ie] as f64;
        if (n - 40.0).abs() <= 0.05 * 40.0 {
            found[0] = true;
        } else if (n - 12.0).abs() <= 0.05 * 12.0 {
            found[1] = true;
        } else {
            panic!("texel {t}: exponent {n} is neither material's");
        }
    }
    assert_eq!(found, [true, true]);
    // The file's decoder against the fitted models, every pair and texel.
    let h = g.header.clone();
    let geometry: Option<Geometry> = serde_json::from_value(h.params["geometry"].clone()).unwrap();
    assert!(
        geometry.is_some(),
        "a sim btf dataset gives each texel its own directions"
    );
    let reference = SvbrdfFit {
        family,
        width: h.width,
        height: h.height,
        lights_deg: h.lights_deg.clone(),
        views_deg: h.views_deg.clone(),
        params: g.blocks[0].clone(),
        gain: g.blocks[1]
            .chunks_exact(9)
            .map(|c| {
                (!c.iter().all(|x| *x == 0.0)).then(|| [[c[0], c[1], c[2]], [c[3], c[4], c[5]], [c[6], c[7], c[8]]])
            })
            .collect(),
        geometry,
        residual: vec![0.0; h.width * h.height],
        failed: Vec::new(),
    };
    let decoder = CompressedBtf::new(g).unwrap();
    let (nl, nv) = (h.lights_deg.len(), h.views_deg.len());
    let mut worst = 0f64;
    for view in 0..nv {
        for light in 0..nl {
            let (a, b) = (
                decoder.reconstruct(light, view).unwrap(),
                BtfModel::reconstruct(&reference, light, view).unwrap(),
            );
            let scale = b.iter().fold(1e-6f32, |m, x| m.max(x.abs()));
            for (x, y) in a.iter().zip(&b) {
                worst = worst.max(((x - y).abs() / scale) as f64);
            }
        }
    }
    assert!(
        worst < 1e-5,
        "file decoder vs fitted models: relative difference {worst:e}"
    );
    // gonio reconstruct and gonio render read the file.
    let (light, view) = (7, 5);
    let (ld, vd) = (h.lights_deg[light], h.views_deg[view]);
    let npy = dir.path().join("checker-fit.npy");
    ok(&[
        "reconstruct",
        out.to_str().unwrap(),
        "--light",
        &format!("{},{}", ld[0], ld[1]),
        "--view",
        &format!("{},{}", vd[0], vd[1]),
        "--out",
        npy.to_str().unwrap(),
    ]);
    let bytes = std::fs::read(&npy).unwrap();
    let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let got: Vec<f32> = bytes[10 + hlen..]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    assert_eq!(got, decoder.reconstruct(light, view).unwrap(), "gonio reconstruct");
    let png = dir.path().join("checker-fit-sphere.png");
    ok(&[
        "render",
        out.to_str().unwrap(),
        "--light",
        "30,0",
        "--view",
        "0,0",
        "--shape",
        "sphere",
        "--size",
        "32x32",
        "--out",
        png.to_str().unwrap(),
    ]);
    assert!(std::fs::metadata(&png).unwrap().len() > 0);
}

#[test]
fn bad_inputs_are_refused_naming_the_input() {
    let (dir, white) = renders();
    let ds = dir.path().join("lafortune");
    let (ds, white) = (ds.to_str().unwrap(), white.to_str().unwrap());
    refused(
        &["fit", ds, "--model", "phong", "--white", white],
        &["--model phong", "lafortune, ward"],
    );
    refused(
        &["fit", ds, "--model", "lafortune", "--lobes", "0", "--white", white],
        &["--lobes 0"],
    );
    refused(&["fit", ds, "--model", "lafortune"], &[ds, "--white"]);
    let not_ds = dir.path().join("empty-dir");
    std::fs::create_dir_all(&not_ds).unwrap();
    refused(
        &["fit", not_ds.to_str().unwrap(), "--model", "ward"],
        &["empty-dir", "not a gonio dataset"],
    );
    let csv = dir.path().join("bad.csv");
    std::fs::write(&csv, "theta_l,phi_l,theta_v,phi_v,r,g,b\n30,0,30,180,0.1,0.1\n").unwrap();
    refused(
        &["fit", csv.to_str().unwrap(), "--model", "ward"],
        &["bad.csv", "line 2", "7"],
    );
    refused(
        &["fit", ds, "--model", "ward", "--per-texel", "--white", white],
        &["--per-texel", "lafortune"],
    );
    refused(
        &["fit", ds, "--model", "lafortune", "--white", white, "--out", "avg.gbtf"],
        &["--out avg.gbtf", "--per-texel"],
    );
}

/// The glTF model per texel: each texel of the glTF checker gets its own material's
/// metallic, roughness and base colour back, a flat normal and no texel left unconverged;
/// the `.gbtf` decodes (`gonio render`, and `--material`), and `gonio export` writes every
/// format from it, refusing a wrong output name before any work.
#[test]
fn per_texel_gltf_fit_finds_both_materials_and_exports() {
    use gonio::compress::{CompressedBtf, Gbtf};
    let (dir, _) = renders();
    let out = dir.path().join("gltf-fit.gbtf");
    let v = fit("gltf-checker", "gltf", &["--per-texel", "--out", out.to_str().unwrap()]);
    let t = &v["per_texel"];
    assert_eq!(t["texels"], 64);
    assert_eq!(t["not_converged"], 0, "{t}");
    // Two isotropic materials: the anisotropy test keeps no texel anisotropic.
    assert_eq!(t["anisotropic_texels"], 0, "{t}");
    assert_eq!(v["fit"]["anisotropy"]["kept"], false, "{}", v["fit"]);
    let g = Gbtf::read(&out).unwrap();
    assert_eq!(g.header.method, "gltf");
    assert!(g.header.source["calibrated_by"].is_string());
    let truth = [([0.50, 0.30, 0.20], 0.0, 0.6), ([0.90, 0.70, 0.40], 1.0, 0.5)];
    let mut found = [false; 2];
    for tx in 0..64 {
        let p = &g.blocks[0][tx * 9..tx * 9 + 9];
        assert_eq!((p[7], p[8]), (0.0, 0.0), "texel {tx}: anisotropy {p:?}");
        let hit = truth.iter().position(|(base, metallic, rough)| {
            (p[3] as f64 - metallic).abs() < 0.1
                && (p[4] as f64 - rough).abs() < 0.05 * rough
                && (0..3).all(|c| (p[c] as f64 - base[c]).abs() < 0.05)
        });
        let Some(i) = hit else {
            panic!("texel {tx}: parameters {p:?} are neither material's")
        };
        found[i] = true;
        assert!(
            p[5].abs() < 0.02 && p[6].abs() < 0.02,
            "texel {tx}: normal {p:?} of a flat sample"
        );
    }
    assert_eq!(found, [true, true]);
    assert!(CompressedBtf::new(g).is_ok());
    let png = dir.path().join("gltf.png");
    for extra in [&[][..], &["--material"][..]] {
        let mut args = vec![
            "render",
            out.to_str().unwrap(),
            "--light",
            "45,0",
            "--view",
            "30,180",
            "--size",
            "32x32",
            "--out",
            png.to_str().unwrap(),
        ];
        args.extend(extra);
        ok(&args);
    }
    for (format, name, doc) in [
        ("gltf", "m.glb", ""),
        ("gltf", "gltf", "material.gltf"),
        ("materialx", "mtlx", "material.mtlx"),
        ("usd", "usd", "material.usda"),
        ("mitsuba", "mitsuba", "scene.xml"),
    ] {
        let o = dir.path().join("export").join(name);
        let r: Value = serde_json::from_str(&ok(&[
            "export",
            out.to_str().unwrap(),
            "--format",
            format,
            o.to_str().unwrap(),
            "--size",
            "16",
            "--json",
        ]))
        .unwrap();
        assert_eq!(r["texture_texels"], serde_json::json!([16, 16]));
        let doc = if doc.is_empty() { o.clone() } else { o.join(doc) };
        assert!(doc.is_file(), "{format}: {}", doc.display());
        if name == "gltf" {
            let text = std::fs::read_to_string(&doc).unwrap();
            assert!(
                !text.contains("KHR_materials_anisotropy"),
                "an isotropic fit writes no anisotropy"
            );
            assert!(!o.join("textures/anisotropy.png").exists());
        }
    }
    // A dataset is fitted first (calibrated by its white standard), then exported.
    let (_, white) = renders();
    let glb = dir.path().join("export").join("from-dataset.glb");
    let r: Value = serde_json::from_str(&ok(&[
        "export",
        dir.path().join("gltf-checker").to_str().unwrap(),
        "--white",
        white.to_str().unwrap(),
        "--format",
        "gltf",
        glb.to_str().unwrap(),
        "--json",
    ]))
    .unwrap();
    assert_eq!(r["fit"]["texels"], 64);
    assert!(glb.is_file());
    let wrong = dir.path().join("export").join("wrong.mtlx");
    refused(
        &[
            "export",
            out.to_str().unwrap(),
            "--format",
            "materialx",
            wrong.to_str().unwrap(),
        ],
        &["wrong.mtlx", "folder"],
    );
    assert!(!wrong.exists());
    refused(
        &[
            "export",
            out.to_str().unwrap(),
            "--format",
            "gltf",
            "x.glb",
            "--shard",
            "1/2",
        ],
        &["--shard"],
    );
    averaged_brdf_exports(&out, &dir.path().join("export"));
}

/// `--format rgl-bsdf | merl` (the averaged, isotropic BRDF, issue 33): the fit stored
/// `source.average_fit`, the files are written, bad sizes, a size for merl, an unknown format
/// and a `.gbtf` without the averaged fit are refused; a tilted averaged fit warns.
fn averaged_brdf_exports(gbtf: &Path, dir: &Path) {
    use gonio::compress::Gbtf;
    let g = Gbtf::read(gbtf).unwrap();
    let avg = &g.header.source["average_fit"];
    assert_eq!(avg["model"], "gltf", "{avg}");
    assert_eq!(avg["dataset_journal_sha256"].as_str().map(str::len), Some(64), "{avg}");
    let (bsdf, merl) = (dir.join("avg.bsdf"), dir.join("avg.binary"));
    let r: Value = serde_json::from_str(&ok(&[
        "export",
        gbtf.to_str().unwrap(),
        "--format",
        "rgl-bsdf",
        "--size",
        "8",
        bsdf.to_str().unwrap(),
        "--json",
    ]))
    .unwrap();
    assert_eq!(r["size"], 8);
    assert_eq!(&std::fs::read(&bsdf).unwrap()[..12], b"tensor_file\0");
    ok(&[
        "export",
        gbtf.to_str().unwrap(),
        "--format",
        "merl",
        merl.to_str().unwrap(),
    ]);
    assert_eq!(std::fs::metadata(&merl).unwrap().len(), 12 + 3 * 90 * 90 * 180 * 8);
    assert!(dir.join("avg.binary.json").is_file());
    let g_s = gbtf.to_str().unwrap();
    let x = dir.join("x.bsdf");
    refused(
        &[
            "export",
            g_s,
            "--format",
            "rgl-bsdf",
            "--size",
            "3",
            x.to_str().unwrap(),
        ],
        &["--size 3"],
    );
    refused(
        &["export", g_s, "--format", "merl", "--size", "8", "x.binary"],
        &["--size 8", "fixed bins"],
    );
    refused(&["export", g_s, "--format", "brdf", "x.bsdf"], &["brdf", "rgl-bsdf"]);
    refused(&["export", g_s, "--format", "rgl-bsdf", "x.binary"], &[".bsdf"]);
    assert!(!x.exists());
    // A file written before the averaged fit was stored, and a tilted averaged fit.
    let mut old = g.clone();
    old.header.source.as_object_mut().unwrap().remove("average_fit");
    let old_path = dir.join("old.gbtf");
    old.write(&old_path).unwrap();
    refused(
        &["export", old_path.to_str().unwrap(), "--format", "merl", "y.binary"],
        &["old.gbtf", "gonio fit", "--model gltf --per-texel"],
    );
    let mut tilted = g.clone();
    tilted.header.source["average_fit"]["normal"] = serde_json::json!([0.1, 0.0]);
    let tilted_path = dir.join("tilted.gbtf");
    tilted.write(&tilted_path).unwrap();
    let t = dir.join("tilted.bsdf");
    let r: Value = serde_json::from_str(&ok(&[
        "export",
        tilted_path.to_str().unwrap(),
        "--format",
        "rgl-bsdf",
        "--size",
        "4",
        t.to_str().unwrap(),
        "--json",
    ]))
    .unwrap();
    assert!(r["warnings"][0].as_str().unwrap().contains("anisotropic"), "{r}");
}
