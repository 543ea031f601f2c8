//! glTF 2.0: a quad of the sample's size (metres, glTF's unit) in the XY plane facing +Z,
//! tangent +X (texture u), one `pbrMetallicRoughness` material with base colour,
//! metallic-roughness (G = roughness, B = metallic) and tangent-space normal textures.
//! A folder holds `material.gltf`, `material.bin` and `textures/`; a `.glb` holds the same
//! JSON with the geometry and the PNGs in its binary chunk. Provenance in `asset.extras`.
//!
//! An anisotropic fit adds `KHR_materials_anisotropy` (in `extensionsUsed`, not required:
//! a viewer without it shows the isotropic base): `anisotropyStrength` 1, `anisotropyRotation`
//! 0 and an `anisotropyTexture` (linear PNG: RG the direction `(cos φ, sin φ)` in tangent
//! space from [−1, 1] to [0, 1], B the strength), with the quad's tangent +X = u. A fit
//! without anisotropic texels writes no extension and no fourth texture.

use super::{io, texture, ExportError, Material};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// The quad's vertex data (positions, normals, tangents, UVs, indices), little-endian, each
/// part 4-byte aligned: (bytes, [(offset, length)] of the five parts).
fn geometry(size_m: f64) -> (Vec<u8>, [(usize, usize); 5]) {
    let h = (size_m / 2.0) as f32;
    // Counter-clockwise seen from +Z; UV (0, 0) at the image's top-left = the sample's
    // (−x, +y) corner (conventions.md: row 0 is the +y edge).
    let pos: [[f32; 3]; 4] = [[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]];
    let uv: [[f32; 2]; 4] = [[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]];
    let idx: [u16; 6] = [0, 1, 2, 0, 2, 3];
    let mut b = Vec::new();
    let mut parts = [(0, 0); 5];
    let mut push = |b: &mut Vec<u8>, k: usize, bytes: Vec<u8>| {
        parts[k] = (b.len(), bytes.len());
        b.extend(bytes);
        while !b.len().is_multiple_of(4) {
            b.push(0);
        }
    };
    push(&mut b, 0, pos.iter().flatten().flat_map(|x| x.to_le_bytes()).collect());
    push(
        &mut b,
        1,
        (0..4)
            .flat_map(|_| [0f32, 0.0, 1.0])
            .flat_map(|x| x.to_le_bytes())
            .collect(),
    );
    push(
        &mut b,
        2,
        (0..4)
            .flat_map(|_| [1f32, 0.0, 0.0, 1.0])
            .flat_map(|x| x.to_le_bytes())
            .collect(),
    );
    push(&mut b, 3, uv.iter().flatten().flat_map(|x| x.to_le_bytes()).collect());
    push(&mut b, 4, idx.iter().flat_map(|x| x.to_le_bytes()).collect());
    (b, parts)
}

/// The document; `images` are either URIs (folder) or bufferView indices (GLB).
fn document(m: &Material, parts: &[(usize, usize); 5], buffer: Value, images: Vec<Value>, views: Vec<Value>) -> Value {
    let h = (m.size_mm / 2000.0) as f32;
    let mut buffer_views: Vec<Value> = parts
        .iter()
        .enumerate()
        .map(|(k, (off, len))| {
            let target = if k == 4 { 34963 } else { 34962 };
            json!({"buffer": 0, "byteOffset": off, "byteLength": len, "target": target})
        })
        .collect();
    buffer_views.extend(views);
    let mut extras = m.provenance.clone();
    if let Some(o) = extras.as_object_mut() {
        o.insert("texture_tile_m".into(), json!(m.size_mm / 1000.0));
    }
    let mut material = json!({
        "name": "gonio-fit",
        "pbrMetallicRoughness": {
            "baseColorTexture": {"index": 0},
            "metallicRoughnessTexture": {"index": 1},
            "metallicFactor": 1.0,
            "roughnessFactor": 1.0
        },
        "normalTexture": {"index": 2, "scale": 1.0}
    });
    let mut textures = vec![
        json!({"sampler": 0, "source": 0}),
        json!({"sampler": 0, "source": 1}),
        json!({"sampler": 0, "source": 2}),
    ];
    let anisotropic = images.len() > 3;
    if anisotropic {
        textures.push(json!({"sampler": 0, "source": 3}));
        material["extensions"] = json!({ANISOTROPY: {
            "anisotropyStrength": 1.0,
            "anisotropyRotation": 0.0,
            "anisotropyTexture": {"index": 3}
        }});
    }
    let mut doc = json!({
        "asset": {"version": "2.0", "generator": concat!("gonio ", env!("CARGO_PKG_VERSION")), "extras": extras},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "sample"}],
        "meshes": [{"name": "sample", "primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TANGENT": 2, "TEXCOORD_0": 3},
            "indices": 4, "material": 0, "mode": 4
        }]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [-h, -h, 0.0], "max": [h, h, 0.0]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5126, "count": 4, "type": "VEC4"},
            {"bufferView": 3, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 4, "componentType": 5123, "count": 6, "type": "SCALAR"}
        ],
        "bufferViews": buffer_views,
        "buffers": [buffer],
        "materials": [material],
        // Nearest: one texel of the fit per texel of the render, as `gonio render` samples.
        "samplers": [{"magFilter": 9728, "minFilter": 9728, "wrapS": 10497, "wrapT": 10497}],
        "textures": textures,
        "images": images
    });
    if anisotropic {
        doc["extensionsUsed"] = json!([ANISOTROPY]);
    }
    doc
}

/// The extension an anisotropic fit writes.
pub const ANISOTROPY: &str = "KHR_materials_anisotropy";

/// The textures: base colour, metallic-roughness, normal, and the anisotropy texture when
/// any texel is anisotropic.
fn pngs(m: &Material) -> Result<Vec<(&'static str, Vec<u8>)>, ExportError> {
    let mut out = vec![
        ("base_color.png", texture::base_color_png(m)?),
        ("metallic_roughness.png", texture::metallic_roughness_png(m)?),
        ("normal.png", texture::normal_png(m)?),
    ];
    if m.anisotropic_texels() > 0 {
        out.push(("anisotropy.png", texture::anisotropy_png(m)?));
    }
    Ok(out)
}

/// `OUT/material.gltf`, `OUT/material.bin`, `OUT/textures/*.png`.
pub fn write_folder(m: &Material, out: &Path) -> Result<Vec<PathBuf>, ExportError> {
    let (bin, parts) = geometry(m.size_mm / 1000.0);
    let tex = out.join("textures");
    std::fs::create_dir_all(&tex).map_err(io(&tex))?;
    let mut files = vec![out.join("material.gltf"), out.join("material.bin")];
    let mut images = Vec::new();
    for (name, png) in pngs(m)? {
        let p = tex.join(name);
        std::fs::write(&p, png).map_err(io(&p))?;
        images.push(json!({"uri": format!("textures/{name}"), "mimeType": "image/png"}));
        files.push(p);
    }
    let doc = document(
        m,
        &parts,
        json!({"uri": "material.bin", "byteLength": bin.len()}),
        images,
        Vec::new(),
    );
    std::fs::write(&files[1], &bin).map_err(io(&files[1]))?;
    let text = serde_json::to_string_pretty(&doc).expect("a JSON value serializes");
    std::fs::write(&files[0], text).map_err(io(&files[0]))?;
    Ok(files)
}

/// One `.glb`: header, JSON chunk (space-padded), BIN chunk (zero-padded) with the geometry
/// and the three PNGs.
pub fn write_glb(m: &Material, out: &Path) -> Result<PathBuf, ExportError> {
    let (mut bin, parts) = geometry(m.size_mm / 1000.0);
    let mut images = Vec::new();
    let mut views = Vec::new();
    for (k, (_, png)) in pngs(m)?.into_iter().enumerate() {
        views.push(json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": png.len()}));
        images.push(json!({"bufferView": 5 + k, "mimeType": "image/png"}));
        bin.extend(png);
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
    }
    let doc = document(m, &parts, json!({"byteLength": bin.len()}), images, views);
    let mut js = serde_json::to_vec(&doc).expect("a JSON value serializes");
    while !js.len().is_multiple_of(4) {
        js.push(b' ');
    }
    let total = 12 + 8 + js.len() + 8 + bin.len();
    let mut glb = Vec::with_capacity(total);
    glb.extend(b"glTF");
    glb.extend(2u32.to_le_bytes());
    glb.extend((total as u32).to_le_bytes());
    glb.extend((js.len() as u32).to_le_bytes());
    glb.extend(b"JSON");
    glb.extend(js);
    glb.extend((bin.len() as u32).to_le_bytes());
    glb.extend(b"BIN\0");
    glb.extend(bin);
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(io(parent))?;
    }
    std::fs::write(out, glb).map_err(io(out))?;
    Ok(out.to_path_buf())
}
