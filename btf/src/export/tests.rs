use super::*;
use crate::compress::gltf::{encode, PARAMS};
use crate::compress::testdata::{self, hash};

/// A glTF `.gbtf` over the test dataset: texel 0's base colour 1.2 (to be clamped), texel
/// 1 flagged as not converged; `calibrated` sets `source.calibrated_by`.
fn file(dir: &Path, calibrated: bool) -> Gbtf {
    let ds = testdata::write(&dir.join("ds"), |_, _, _, _| 0.1);
    let (t, pairs) = (ds.texels(), ds.n_lights() * ds.n_views());
    let mut params: Vec<f32> = (0..t * PARAMS)
        .map(|i| match i % PARAMS {
            3 => hash(i, 2),
            4 => 0.3 + 0.5 * hash(i, 3),
            5 | 6 => 0.3 * (hash(i, 4) - 0.5),
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
        (Format::Usd, "x.usdz"),
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
