use super::*;
use crate::compress::gltf::{encode, PARAMS};
use crate::compress::testdata::{self, hash};

/// A glTF `.gbtf` over the test dataset: texel 0's base colour 1.2 (to be clamped), texel
/// 1 flagged as not converged; `calibrated` sets `source.calibrated_by`.
fn file(dir: &Path, calibrated: bool) -> Gbtf {
    file_with(dir, calibrated, 0.0)
}

/// [`file`] with anisotropy vectors of length up to `aniso` (0: isotropic).
fn file_with(dir: &Path, calibrated: bool, aniso: f32) -> Gbtf {
    let ds = testdata::write(&dir.join("ds"), |_, _, _, _| 0.1);
    let (t, pairs) = (ds.texels(), ds.n_lights() * ds.n_views());
    let mut params: Vec<f32> = (0..t * PARAMS)
        .map(|i| match i % PARAMS {
            3 => hash(i, 2),
            4 => 0.3 + 0.5 * hash(i, 3),
            5 | 6 => 0.3 * (hash(i, 4) - 0.5),
            7 | 8 => aniso * (hash(i, 5) - 0.5),
            _ => 0.1 + 0.8 * hash(i, 1),
        })
        .collect();
    params[0] = 1.2;
    let mut quality = vec![0.0; 2 * t];
    quality[3] = 1.0;
    let mut g = encode(&ds, params, vec![1.0; pairs * 9], quality, None).unwrap();
    if calibrated {
        g.header.source["calibrated_by"] = serde_json::json!("white");
    }
    g
}

fn opts(size: Option<usize>) -> ExportOptions {
    ExportOptions {
        size,
        allow_uncalibrated: false,
        bit_depth: 8,
        prefilter: true,
    }
}

/// A path with the wrong extension is refused before anything is read or written.
#[test]
fn wrong_extensions_are_refused_before_any_work() {
    assert_eq!(Format::Gltf.check_out(Path::new("a/b.glb")).unwrap(), Layout::File);
    assert_eq!(Format::Gltf.check_out(Path::new("a/b")).unwrap(), Layout::Folder);
    for (f, p) in [
        (Format::Gltf, "x.usda"),
        (Format::Materialx, "x.mtlx"),
        (Format::Usd, "x.usd"),
        (Format::Mitsuba, "x.glb"),
    ] {
        let e = f.check_out(Path::new(p)).unwrap_err().to_string();
        assert!(e.contains(p) && e.contains(f.name()), "{e}");
    }
}

/// Textures: base colour clamped to 1 with a warning, not-converged texels listed, unit
/// normals, no NaN; `--size` resamples; uncalibrated values need the flag and are labelled.
#[test]
fn materials_clamp_list_and_refuse_uncalibrated_values() {
    let tmp = tempfile::tempdir().unwrap();
    let g = file(tmp.path(), true);
    let m = Material::from_gbtf(&g, Path::new("f.gbtf"), &opts(None)).unwrap();
    assert_eq!((m.width, m.height), (g.header.width, g.header.height));
    assert_eq!(m.base_color[0][0], 1.0);
    assert!(m.warnings.iter().any(|w| w.contains("clamped")), "{:?}", m.warnings);
    assert_eq!(m.provenance["not_converged_texels"], serde_json::json!([1]));
    for n in &m.normal {
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        assert!((len - 1.0).abs() < 1e-5 && n[2] > 0.0, "{n:?}");
    }
    let big = Material::from_gbtf(&g, Path::new("f.gbtf"), &opts(Some(37))).unwrap();
    assert_eq!((big.width, big.height, big.metallic.len()), (37, 37, 37 * 37));
    assert!(big
        .base_color
        .iter()
        .flatten()
        .all(|x| x.is_finite() && (0.0..=1.0).contains(x)));
    let raw = file(&tmp.path().join("raw"), false);
    let e = Material::from_gbtf(&raw, Path::new("raw.gbtf"), &opts(None))
        .unwrap_err()
        .to_string();
    assert!(e.contains("--allow-uncalibrated") && e.contains("raw.gbtf"), "{e}");
    let ok = Material::from_gbtf(
        &raw,
        Path::new("raw.gbtf"),
        &ExportOptions {
            size: None,
            allow_uncalibrated: true,
            bit_depth: 8,
            prefilter: true,
        },
    )
    .unwrap();
    assert!(ok.provenance["units"].as_str().unwrap().starts_with("UNCALIBRATED"));
}

/// Every format writes its document and textures; the GLB's header, chunk lengths and
/// JSON are consistent; provenance sits in each format's metadata field.
#[test]
fn every_format_writes_its_files_with_provenance() {
    let tmp = tempfile::tempdir().unwrap();
    let g = file(tmp.path(), true);
    let m = Material::from_gbtf(&g, Path::new("f.gbtf"), &opts(Some(8))).unwrap();
    let glb = write(&m, Format::Gltf, &tmp.path().join("m.glb")).unwrap();
    let bytes = std::fs::read(&glb.files[0]).unwrap();
    assert_eq!(&bytes[..4], b"glTF");
    assert_eq!(
        u32::from_le_bytes(bytes[8..12].try_into().unwrap()) as usize,
        bytes.len()
    );
    let jl = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    assert_eq!(&bytes[16..20], b"JSON");
    let doc: serde_json::Value = serde_json::from_slice(&bytes[20..20 + jl]).unwrap();
    assert_eq!(doc["asset"]["version"], "2.0");
    assert!(doc["asset"]["extras"]["dataset"].is_string());
    let bl = u32::from_le_bytes(bytes[20 + jl..24 + jl].try_into().unwrap()) as usize;
    assert_eq!(&bytes[24 + jl..28 + jl], b"BIN\0");
    assert_eq!(doc["buffers"][0]["byteLength"].as_u64().unwrap() as usize, bl);
    assert_eq!(28 + jl + bl, bytes.len());
    for (f, doc, needle) in [
        (Format::Gltf, "material.gltf", "\"extras\""),
        (Format::Materialx, "material.mtlx", "doc=\""),
        (Format::Usd, "material.usda", "gonio_provenance"),
        (Format::Mitsuba, "scene.xml", "<!-- gonio provenance"),
    ] {
        let out = tmp.path().join(f.name());
        let r = write(&m, f, &out).unwrap();
        assert_eq!(r.files[0], out.join(doc));
        let text = std::fs::read_to_string(&r.files[0]).unwrap();
        assert!(text.contains(needle) && text.contains("not_converged_texels"), "{f:?}");
        for p in &r.files {
            assert!(p.is_file(), "{}", p.display());
        }
    }
}

/// `file` with an averaged fit in its header, tilted by `normal`.
fn with_average(dir: &Path, normal: [f64; 2]) -> Gbtf {
    let mut g = file(dir, true);
    g.header.source["average_fit"] = serde_json::to_value(average::AverageFit {
        model: "gltf".into(),
        base_color: [0.5, 0.3, 0.2],
        metallic: 0.1,
        roughness: 0.4,
        normal,
        anisotropy: [0.0, 0.0],
        rel_rms: 0.05,
        observations: 100,
        dataset_journal_sha256: Some("ab".repeat(32)),
    })
    .unwrap();
    g
}

/// The averaged-BRDF formats need `source.average_fit`: a file without it is refused with
/// the refit command; a tilted fit warns that it is made isotropic; an untilted one does not.
#[test]
fn average_fit_is_required_and_a_tilt_warns() {
    let tmp = tempfile::tempdir().unwrap();
    let old = file(tmp.path(), true);
    let e = average::AverageBrdf::from_gbtf(&old, Path::new("old.gbtf"), false)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("old.gbtf") && e.contains("gonio fit") && e.contains("--model gltf --per-texel"),
        "{e}"
    );
    let flat = average::AverageBrdf::from_gbtf(
        &with_average(&tmp.path().join("a"), [0.0, 0.0]),
        Path::new("f.gbtf"),
        false,
    )
    .unwrap();
    assert!(flat.warnings.is_empty(), "{:?}", flat.warnings);
    let tilted = average::AverageBrdf::from_gbtf(
        &with_average(&tmp.path().join("b"), [0.1, 0.05]),
        Path::new("f.gbtf"),
        false,
    )
    .unwrap();
    assert!(
        tilted.warnings.iter().any(|w| w.contains("anisotropic")),
        "{:?}",
        tilted.warnings
    );
    // Isotropic: the same value for a pair rotated by any angle (the mean over 36 rotations
    // is invariant under the rotations by 10°; the flat fit under every rotation).
    let d = |t: f64, p: f64| gonio_devices::Direction::from_degrees(t, p).vector();
    for (b, rot) in [(&flat, 37.0), (&tilted, 30.0)] {
        let (x, y) = (
            b.eval(d(30.0, 10.0), d(50.0, 200.0)),
            b.eval(d(30.0, 10.0 + rot), d(50.0, 200.0 + rot)),
        );
        for c in 0..3 {
            assert!((x[c] - y[c]).abs() <= 1e-12 * x[c], "{x:?} {y:?}");
        }
    }
}

/// The sample warp is the inverse CDF of the bilinear density: the identity for a constant
/// density, `u = √s` for a density growing linearly in x.
#[test]
fn the_warp_inverts_the_bilinear_cdf() {
    let n = 9;
    let flat = rgl::Warp::new(vec![1.0; n * n], n);
    let ramp = rgl::Warp::new((0..n * n).map(|k| (k % n) as f64).collect(), n);
    for s in [[0.0, 0.0], [0.3, 0.7], [0.5, 0.5], [0.91, 0.12], [1.0, 1.0]] {
        let u = flat.sample(s);
        assert!(
            (u[0] - s[0]).abs() < 1e-12 && (u[1] - s[1]).abs() < 1e-12,
            "{u:?} {s:?}"
        );
        let u = ramp.sample(s);
        assert!(
            (u[0] - s[0].sqrt()).abs() < 1e-12 && (u[1] - s[1]).abs() < 1e-12,
            "{u:?} {s:?}"
        );
    }
}

/// A tensor file's fields: name → (dtype, shape, bytes).
fn tensor_fields(b: &[u8]) -> std::collections::BTreeMap<String, (u8, Vec<usize>, &[u8])> {
    assert_eq!(&b[..12], b"tensor_file\0");
    assert_eq!(&b[12..14], &[1, 0]);
    let n = u32::from_le_bytes(b[14..18].try_into().unwrap());
    let mut at = 18;
    let mut out = std::collections::BTreeMap::new();
    let u16_at = |p: usize| u16::from_le_bytes(b[p..p + 2].try_into().unwrap()) as usize;
    let u64_at = |p: usize| u64::from_le_bytes(b[p..p + 8].try_into().unwrap()) as usize;
    for _ in 0..n {
        let len = u16_at(at);
        let name = String::from_utf8(b[at + 2..at + 2 + len].to_vec()).unwrap();
        at += 2 + len;
        let ndim = u16_at(at);
        let dtype = b[at + 2];
        let off = u64_at(at + 3);
        at += 11;
        let shape: Vec<usize> = (0..ndim).map(|k| u64_at(at + 8 * k)).collect();
        at += 8 * ndim;
        let size = if dtype == 10 { 4 } else { 1 } * shape.iter().product::<usize>();
        assert_eq!(off % 8, 0, "{name}");
        out.insert(name, (dtype, shape, &b[off..off + size]));
    }
    out
}

/// The `.bsdf` has every field `measured.cpp` checks, with its types and shapes (one φ_i
/// slice, 23 θ_i slices, `size²` grids), the provenance in `description`, the same bytes
/// for the same input; at every grid node the stored value times the reader's Jacobian
/// `ndf(u_m) / (4 σ(u_i))` is the fitted BRDF times cos θ_o (Mitsuba's `eval`) at the
/// direction pair the warp maps it to.
#[test]
fn rgl_file_has_the_measured_plugins_layout() {
    let tmp = tempfile::tempdir().unwrap();
    let avg =
        average::AverageBrdf::from_gbtf(&with_average(tmp.path(), [0.0, 0.0]), Path::new("f.gbtf"), false).unwrap();
    let n = 8;
    let (b, s) = rgl::encode(&avg, n).unwrap();
    assert_eq!(b, rgl::encode(&avg, n).unwrap().0, "same input, same bytes");
    assert_eq!(s.bytes, b.len());
    let f = tensor_fields(&b);
    let m = rgl::THETA_SLICES;
    for (name, dtype, shape) in [
        ("theta_i", 10, vec![m]),
        ("phi_i", 10, vec![1]),
        ("ndf", 10, vec![n, n]),
        ("sigma", 10, vec![n, n]),
        ("vndf", 10, vec![1, m, n, n]),
        ("luminance", 10, vec![1, m, n, n]),
        ("rgb", 10, vec![1, m, 3, n, n]),
        ("valid", 1, vec![1, m, n, n]),
        ("jacobian", 1, vec![1]),
    ] {
        let (d, sh, _) = &f[name];
        assert_eq!((*d, sh), (dtype, &shape), "{name}");
    }
    assert_eq!(f["jacobian"].2, &[1]);
    let desc: serde_json::Value = serde_json::from_slice(f["description"].2).unwrap();
    assert!(desc["generator"].as_str().unwrap().starts_with("gonio "));
    assert_eq!(desc["fit"]["roughness"], 0.4);
    let floats = |name: &str| -> Vec<f64> {
        f[name]
            .2
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()) as f64)
            .collect()
    };
    let (theta, ndf, sigma, rgb, vndf) = (
        floats("theta_i"),
        floats("ndf"),
        floats("sigma"),
        floats("rgb"),
        floats("vndf"),
    );
    assert!(rgb.iter().chain(&vndf).chain(&ndf).all(|x| x.is_finite() && *x >= 0.0));
    assert!((theta[m - 1].to_degrees() - 88.0).abs() < 1e-4);
    let bil = |g: &[f64], x: f64, y: f64| {
        let (fx, fy) = (x * (n - 1) as f64, y * (n - 1) as f64);
        let (i, j) = ((fx as usize).min(n - 2), (fy as usize).min(n - 2));
        let (tx, ty) = (fx - i as f64, fy - j as f64);
        let at = |i: usize, j: usize| g[j * n + i];
        (1.0 - ty) * ((1.0 - tx) * at(i, j) + tx * at(i + 1, j))
            + ty * ((1.0 - tx) * at(i, j + 1) + tx * at(i + 1, j + 1))
    };
    let mut checked = 0;
    for k in [0, 7, 15, 22] {
        let ti = theta[k];
        let wi = gonio_devices::Vec3::new(ti.sin(), 0.0, ti.cos());
        let warp = rgl::Warp::new(vndf[k * n * n..(k + 1) * n * n].to_vec(), n);
        for j in 0..n {
            for i in 0..n {
                let u = warp.sample([i as f64 / (n - 1) as f64, j as f64 / (n - 1) as f64]);
                let (tm, pm) = (
                    u[0] * u[0] * std::f64::consts::FRAC_PI_2,
                    (2.0 * u[1] - 1.0) * std::f64::consts::PI,
                );
                let mm = gonio_devices::Vec3::new(tm.sin() * pm.cos(), tm.sin() * pm.sin(), tm.cos());
                let wo = mm * (2.0 * mm.dot(wi)) - wi;
                if wo.z <= 1e-3 {
                    continue;
                }
                let wo = wo.normalized();
                let want = avg.eval(wi, wo).map(|x| x * wo.z);
                let jac = bil(&ndf, u[0], u[1]) / (4.0 * bil(&sigma, (ti / std::f64::consts::FRAC_PI_2).sqrt(), 0.5));
                for (c, want) in want.iter().enumerate() {
                    let got = rgb[((k * 3 + c) * n + j) * n + i] * jac;
                    assert!(
                        (got - want).abs() <= 1e-5 * want.max(1e-6),
                        "slice {k} node ({i}, {j}) c{c}: {got} vs {want}"
                    );
                }
                checked += 1;
            }
        }
    }
    assert!(checked > 100, "{checked}");
}

/// `--size` and the output name are checked before any work; merl refuses a size.
#[test]
fn average_exports_refuse_bad_sizes_and_names() {
    for bad in [0, 1, 3, rgl::MAX_SIZE + 1] {
        assert!(rgl::check_size(bad).unwrap_err().contains(&format!("--size {bad}")));
    }
    for (f, p) in [
        (Format::RglBsdf, "x.binary"),
        (Format::RglBsdf, "x"),
        (Format::Merl, "x.bsdf"),
    ] {
        let e = f.check_out(Path::new(p)).unwrap_err().to_string();
        assert!(e.contains(f.name()), "{e}");
    }
    let tmp = tempfile::tempdir().unwrap();
    let avg =
        average::AverageBrdf::from_gbtf(&with_average(tmp.path(), [0.0, 0.0]), Path::new("f.gbtf"), false).unwrap();
    let e = write_average(&avg, Format::Merl, Some(32), &tmp.path().join("m.binary"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("--size 32"), "{e}");
    let e = write_average(&avg, Format::RglBsdf, Some(2), &tmp.path().join("m.bsdf"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("--size 2"), "{e}");
    assert!(!tmp.path().join("m.bsdf").exists() && !tmp.path().join("m.binary").exists());
}

/// The MERL binary: its header, its length, and at every probed bin `value × scale` is the
/// BRDF at the bin's direction pair; the sidecar holds the provenance.
#[test]
fn merl_binary_layout_and_values() {
    let tmp = tempfile::tempdir().unwrap();
    let avg =
        average::AverageBrdf::from_gbtf(&with_average(tmp.path(), [0.0, 0.0]), Path::new("f.gbtf"), false).unwrap();
    let out = tmp.path().join("m.binary");
    let r = write_average(&avg, Format::Merl, None, &out).unwrap();
    let b = std::fs::read(&out).unwrap();
    let cells = merl::THETA_H * merl::THETA_D * merl::PHI_D;
    assert_eq!(b.len(), 12 + 3 * cells * 8);
    let dims: Vec<i32> = (0..3)
        .map(|k| i32::from_le_bytes(b[4 * k..4 * k + 4].try_into().unwrap()))
        .collect();
    assert_eq!(dims, [90, 90, 180]);
    for (i, j, k) in [(0, 0, 0), (10, 20, 30), (45, 10, 90), (89, 89, 179), (60, 70, 5)] {
        let (l, v) = merl::bin_directions(i, j, k);
        let want = if l.z > 0.0 && v.z > 0.0 {
            avg.eval(l, v)
        } else {
            [0.0; 3]
        };
        let idx = k + merl::PHI_D * (j + merl::THETA_D * i);
        for (c, (want, scale)) in want.iter().zip(merl::SCALE).enumerate() {
            let p = 12 + 8 * (c * cells + idx);
            let got = f64::from_le_bytes(b[p..p + 8].try_into().unwrap()) * scale;
            assert!(
                (got - want).abs() <= 1e-12 * want.abs().max(1e-12),
                "({i},{j},{k}) c{c}: {got} {want}"
            );
        }
    }
    let side: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&r.files[1]).unwrap()).unwrap();
    assert_eq!(r.files[1], tmp.path().join("m.binary.json"));
    assert_eq!(side["provenance"]["fit"]["roughness"], 0.4);
    assert_eq!(side["scale"][1], 1.15 / 1500.0);
}

/// `--bit-depth 16` writes 16-bit PNGs that decode to the maps' values within 1/65535
/// (sRGB-encoded base colour, linear others); 8 bits within 1/255.
#[test]
fn sixteen_bit_textures_decode_to_the_maps() {
    let tmp = tempfile::tempdir().unwrap();
    let g = file(tmp.path(), true);
    for bits in [8u8, 16] {
        let m = Material::from_gbtf(
            &g,
            Path::new("f.gbtf"),
            &ExportOptions {
                size: None,
                allow_uncalibrated: false,
                bit_depth: bits,
                prefilter: true,
            },
        )
        .unwrap();
        let step = if bits == 16 { 1.0 / 65535.0 } else { 1.0 / 255.0 };
        let png = texture::gray_png(m.width, m.height, &m.roughness, bits).unwrap();
        let img = image::load_from_memory(&png).unwrap().into_luma16();
        for (p, r) in img.pixels().zip(&m.roughness) {
            assert!(
                (p[0] as f64 / 65535.0 - *r as f64).abs() <= 0.51 * step + 1e-9,
                "{bits} bits: {} vs {r}",
                p[0]
            );
        }
        let png = texture::base_color_png(&m).unwrap();
        let img = image::load_from_memory(&png).unwrap().into_rgb16();
        for (p, c) in img.pixels().zip(&m.base_color) {
            let want = texture::srgb_encode(c[0]) as f64;
            assert!(
                (p[0] as f64 / 65535.0 - want).abs() <= 0.51 * step + 1e-6,
                "{bits} bits: {} vs {want}",
                p[0]
            );
        }
    }
    let e = Material::from_gbtf(
        &g,
        Path::new("f.gbtf"),
        &ExportOptions {
            size: None,
            allow_uncalibrated: false,
            bit_depth: 12,
            prefilter: true,
        },
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("--bit-depth 12"), "{e}");
}

/// KHR_materials_anisotropy: an anisotropic fit's glTF lists the extension and carries a
/// fourth (linear) texture whose RG is the direction and B the strength; an isotropic fit
/// writes neither; the formats without anisotropy warn, naming what is lost, and write the
/// isotropic roughness √(α_t α_b)^½.
#[test]
fn anisotropy_is_written_to_gltf_and_approximated_elsewhere() {
    let tmp = tempfile::tempdir().unwrap();
    let iso = Material::from_gbtf(&file(tmp.path(), true), Path::new("f.gbtf"), &opts(None)).unwrap();
    let r = write(&iso, Format::Gltf, &tmp.path().join("iso")).unwrap();
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&r.files[0]).unwrap()).unwrap();
    assert!(doc.get("extensionsUsed").is_none() && doc["materials"][0].get("extensions").is_none());
    assert_eq!(doc["images"].as_array().unwrap().len(), 3);
    assert!(r.warnings.iter().all(|w| !w.contains("anisotrop")), "{:?}", r.warnings);

    let g = file_with(&tmp.path().join("a"), true, 1.2);
    let m = Material::from_gbtf(&g, Path::new("a.gbtf"), &opts(None)).unwrap();
    assert_eq!(m.anisotropic_texels(), m.anisotropy.len());
    let r = write(&m, Format::Gltf, &tmp.path().join("aniso")).unwrap();
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&r.files[0]).unwrap()).unwrap();
    assert_eq!(doc["extensionsUsed"], serde_json::json!(["KHR_materials_anisotropy"]));
    let ext = &doc["materials"][0]["extensions"]["KHR_materials_anisotropy"];
    assert_eq!(ext["anisotropyTexture"]["index"], 3);
    assert_eq!(doc["textures"][3]["source"], 3);
    assert_eq!(doc["images"][3]["uri"], "textures/anisotropy.png");
    let png = image::open(tmp.path().join("aniso/textures/anisotropy.png"))
        .unwrap()
        .to_rgb8();
    for t in [0usize, 5, 17] {
        let (x, y) = ((t % m.width) as u32, (t / m.width) as u32);
        let px = png.get_pixel(x, y).0.map(|c| c as f64 / 255.0);
        let a = m.anisotropy[t].map(|c| c as f64);
        let (s, phi) = gonio_brdf::gltf::anisotropy_of(a);
        assert!((px[2] - s).abs() <= 0.5 / 255.0 + 1e-6, "{px:?} {s}");
        let (dx, dy) = (2.0 * px[0] - 1.0, 2.0 * px[1] - 1.0);
        assert!(
            (dx - phi.cos()).abs() < 0.01 && (dy - phi.sin()).abs() < 0.01,
            "{px:?} {phi}"
        );
    }
    let glb = write(&m, Format::Gltf, &tmp.path().join("aniso.glb")).unwrap();
    assert!(glb.files[0].is_file());
    for f in [Format::Usd, Format::Mitsuba] {
        let r = write(&m, f, &tmp.path().join(format!("a-{}", f.name()))).unwrap();
        let w = r.warnings.iter().find(|w| w.contains("anisotropic")).unwrap();
        assert!(
            w.contains(f.name()) && w.contains("lost") && w.contains("isotropic"),
            "{w}"
        );
    }
    // MaterialX: exact through specular_anisotropy and specular_rotation (MaterialX's
    // roughness_anisotropy and its clockwise rotate3d), no anisotropy warning.
    let r = write(&m, Format::Materialx, &tmp.path().join("a-mtlx")).unwrap();
    assert!(r.warnings.iter().all(|w| !w.contains("lost")), "{:?}", r.warnings);
    let text = std::fs::read_to_string(&r.files[0]).unwrap();
    assert!(
        text.contains("name=\"specular_anisotropy\" type=\"float\" nodegraph"),
        "{text}"
    );
    assert!(tmp.path().join("a-mtlx/textures/specular_rotation.png").is_file());
    for t in 0..m.anisotropy.len() {
        let a = m.anisotropy[t].map(|c| c as f64);
        let (at, ab) = gonio_brdf::gltf::alphas(m.roughness[t] as f64, a);
        let (r, an, rot) = materialx::standard_surface_anisotropy(m.roughness[t] as f64, a);
        if 1.0 - ab / at > materialx::MAX_ANISOTROPY {
            continue;
        }
        let aspect = (1.0 - an).sqrt();
        assert!((r * r / aspect - at).abs() < 1e-9 && (r * r * aspect - ab).abs() < 1e-9);
        // The tangent turned clockwise by rot·360° (mx_rotationMatrix · v) is the direction φ.
        let (_, phi) = gonio_brdf::gltf::anisotropy_of(a);
        let turn = -rot * std::f64::consts::TAU;
        assert!(
            (turn.cos() * phi.cos() + turn.sin() * phi.sin()).abs() > 1.0 - 1e-9,
            "{rot} {phi}"
        );
    }
    let mut iso = m.clone();
    iso.make_isotropic(Format::Usd).unwrap();
    let (at, ab) = gonio_brdf::gltf::alphas(m.roughness[3] as f64, m.anisotropy[3].map(|c| c as f64));
    assert!(((iso.roughness[3] as f64).powi(4) - at * ab).abs() < 1e-5);
    assert_eq!(iso.anisotropic_texels(), 0);
}

/// `--format usd OUT.usdz`: one zip, stored, the `.usda` first, every file's data 64-byte
/// aligned, the same bytes twice, no parts folder left behind.
#[test]
fn usdz_is_a_stored_aligned_zip() {
    let tmp = tempfile::tempdir().unwrap();
    let m = Material::from_gbtf(&file(tmp.path(), true), Path::new("f.gbtf"), &opts(None)).unwrap();
    assert_eq!(Format::Usd.check_out(Path::new("a.usdz")).unwrap(), Layout::File);
    let out = tmp.path().join("m.usdz");
    let r = write(&m, Format::Usd, &out).unwrap();
    assert_eq!(r.files, vec![out.clone()]);
    let bytes = std::fs::read(&out).unwrap();
    let again = tmp.path().join("again.usdz");
    write(&m, Format::Usd, &again).unwrap();
    assert_eq!(std::fs::read(&again).unwrap(), bytes);
    assert!(!tmp.path().join(".m.usdz.parts").exists());
    // Walk the local headers.
    let (mut at, mut names) = (0usize, Vec::new());
    let u16_at = |b: &[u8], i: usize| u16::from_le_bytes([b[i], b[i + 1]]) as usize;
    let u32_at = |b: &[u8], i: usize| u32::from_le_bytes(b[i..i + 4].try_into().unwrap()) as usize;
    while u32_at(&bytes, at) == 0x0403_4b50 {
        assert_eq!(u16_at(&bytes, at + 8), 0, "stored");
        let (size, nl, el) = (
            u32_at(&bytes, at + 18),
            u16_at(&bytes, at + 26),
            u16_at(&bytes, at + 28),
        );
        let data = at + 30 + nl + el;
        assert_eq!(data % 64, 0);
        assert_eq!(
            crc32fast::hash(&bytes[data..data + size]),
            u32_at(&bytes, at + 14) as u32
        );
        names.push(String::from_utf8(bytes[at + 30..at + 30 + nl].to_vec()).unwrap());
        at = data + size;
    }
    assert_eq!(names[0], "material.usda");
    assert!(names.contains(&"textures/base_color.png".to_string()), "{names:?}");
    assert_eq!(names.len(), 5);
}

/// The export's cost against the fit falls with bit depth and texture size, and is
/// (nearly) nothing at the fit's own size with 16 bits: what is left there is texel 0's
/// base colour of 1.2, clamped to 1 by every export.
#[test]
fn the_exports_fidelity_grows_with_bits_and_size() {
    let dir = tempfile::tempdir().unwrap();
    let g = file_with(dir.path(), true, 0.6);
    let path = dir.path().join("f.gbtf");
    let dirs = fidelity::directions(24);
    let w = g.header.width;
    let run = |size: Option<usize>, bits: u8| {
        fidelity::measure(&g, &path, fidelity::Setting::export(size, bits), &dirs).unwrap()
    };
    let full16 = run(None, 16);
    let full8 = run(None, 8);
    let half8 = run(Some(w / 2), 8);
    let double8 = run(Some(2 * w), 8);
    // Measured here (8 × 8 texels of random parameters, 24 × 24 pairs; per texel, the RMS
    // error relative to the material's RMS): texel mean 0.0028 at 16 bits and 0.015 at 8;
    // the clamped texel 0 is the largest (0.134) in both; resampled to 4 × 4 and back, 0.52;
    // to 16 × 16 and back, 0.27 (read back at the fit's texel centres, the upsampled
    // texture blends each texel with its neighbours).
    assert!(full16.texel_mean < 0.005, "{full16:?}");
    assert!(full16.texel_max > 0.05, "the clamped base colour must show: {full16:?}");
    assert!(full8.texel_mean > 2.0 * full16.texel_mean, "{full8:?} vs {full16:?}");
    assert!(half8.rel_rms > 5.0 * full8.rel_rms, "{half8:?} vs {full8:?}");
    assert!(double8.rel_rms > full8.rel_rms, "{double8:?} vs {full8:?}");
    assert_eq!((full16.size, half8.size, double8.size), (w, w / 2, 2 * w));
    assert!(half8.png_bytes < full8.png_bytes && full8.png_bytes < double8.png_bytes);
    assert!(full8.png_bytes < full16.png_bytes);
    // One map at 8 bits: each costs something over the 16-bit read-back, none more than
    // all of them together, and the rows say which map they are.
    let texel_mean_sq = |f: &fidelity::Fidelity| f.texel_mean * f.texel_mean;
    let mut excess = 0.0;
    for m in fidelity::Map::ALL {
        let one = fidelity::measure(&g, &path, fidelity::Setting::map_at_8_bits(None, m), &dirs).unwrap();
        assert_eq!(one.only_8_bit, Some(m));
        assert!(
            one.rel_rms >= full16.rel_rms * (1.0 - 1e-9),
            "{m:?}: {one:?} vs {full16:?}"
        );
        assert!(one.rel_rms <= full8.rel_rms * 1.5, "{m:?}: {one:?} vs {full8:?}");
        excess += texel_mean_sq(&one) - texel_mean_sq(&full16);
    }
    assert!(excess > 0.0, "some map's quantization must cost something");
    // The directions: as many as asked, on the hemisphere up to the cut-off.
    let zmin = fidelity::MAX_THETA_DEG.to_radians().cos() - 1e-12;
    assert!(dirs.len() == 24 && dirs.iter().all(|d| d.z >= zmin && (d.norm() - 1.0).abs() < 1e-12));
}

/// Below the fit's size the export prefilters each texel's footprint: the footprints
/// partition the fit's texels, and against the footprint means (what a renderer pixel
/// covering one shows) the prefiltered texture is closer than the bilinear one, since the
/// normals' spread widens the lobe. At the fit's own size nothing is prefiltered.
#[test]
fn a_smaller_texture_is_prefiltered_over_its_footprint() {
    for (w, ow) in [(8, 4), (8, 3), (7, 2), (8, 8), (5, 1)] {
        let mut seen = vec![0; w * w];
        for j in 0..ow {
            for i in 0..ow {
                for t in super::texture::footprint(w, w, i, j, ow, ow) {
                    seen[t] += 1;
                }
            }
        }
        assert!(seen.iter().all(|&c| c == 1), "{w} → {ow}: {seen:?}");
    }
    let dir = tempfile::tempdir().unwrap();
    let g = file_with(dir.path(), true, 0.0);
    let path = dir.path().join("f.gbtf");
    let dirs = fidelity::directions(24);
    let half = Some(g.header.width / 2);
    let pre = fidelity::measure(&g, &path, fidelity::Setting::export(half, 16), &dirs).unwrap();
    let bil = fidelity::measure(&g, &path, fidelity::Setting::bilinear(half, 16), &dirs).unwrap();
    assert!(pre.prefiltered && !bil.prefiltered);
    let (p, b) = (pre.footprint_rel_rms.unwrap(), bil.footprint_rel_rms.unwrap());
    assert!(p < b, "prefiltered {p} against bilinear {b}");
    let own = fidelity::measure(&g, &path, fidelity::Setting::export(None, 16), &dirs).unwrap();
    assert!(!own.prefiltered && own.footprint_rel_rms.is_none());
}
