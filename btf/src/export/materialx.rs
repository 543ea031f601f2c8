//! MaterialX 1.38: a `standard_surface` (base 1, specular 1, specular IOR 1.5, α =
//! `specular_roughness`² as in glTF) fed by `image` nodes (base colour in `srgb_texture`,
//! the others raw) and a tangent-space `normalmap`. Provenance in the document's `doc`
//! attribute (JSON). `OUT/material.mtlx` and `OUT/textures/`.
//!
//! **Anisotropy.** An anisotropic fit (`KHR_materials_anisotropy`) is written exactly with
//! `specular_anisotropy` and `specular_rotation`: MaterialX's `roughness_anisotropy` gives
//! `α_x = r²/√(1 − A)` along the rotated tangent and `α_y = r² √(1 − A)` across it, so
//! `r² = √(α_t α_b)` and `A = 1 − α_b/α_t` (MaterialX clamps A to 0.98: α_b/α_t ≥ 0.02, else
//! a warning). `standard_surface` turns the tangent by `specular_rotation · 360°` with
//! `rotate3d` about the normal, whose matrix (`mx_rotationMatrix(axis, angle) · v`) turns
//! clockwise seen from the normal's tip; glTF's φ is counter-clockwise, so the texture
//! holds `(−φ / 2π) mod 1`. Two more raw textures, `specular_anisotropy.png` and
//! `specular_rotation.png`; the roughness texture holds `r`.

use super::{io, texture, write_textures, xml_escape, ExportError, Material};
use std::path::{Path, PathBuf};

/// MaterialX's largest `specular_anisotropy`.
pub const MAX_ANISOTROPY: f64 = 0.98;

/// `(r, A, rotation)` of `standard_surface` for a texel of roughness `roughness` and
/// anisotropy vector `a` (see the module docs).
pub fn standard_surface_anisotropy(roughness: f64, a: [f64; 2]) -> (f64, f64, f64) {
    let (at, ab) = gonio_brdf::gltf::alphas(roughness, a);
    let (_, phi) = gonio_brdf::gltf::anisotropy_of(a);
    let r = (at * ab).sqrt().sqrt().clamp(0.0, 1.0);
    let aniso = (1.0 - ab / at).clamp(0.0, MAX_ANISOTROPY);
    let rot = (-phi / std::f64::consts::TAU).rem_euclid(1.0);
    (r, aniso, if aniso > 0.0 { rot } else { 0.0 })
}

/// The warning for texels whose anisotropy exceeds MaterialX's [`MAX_ANISOTROPY`].
pub fn clamped_anisotropy(m: &Material) -> Option<String> {
    let n = m
        .roughness
        .iter()
        .zip(&m.anisotropy)
        .filter(|(r, a)| {
            let (at, ab) = gonio_brdf::gltf::alphas(**r as f64, a.map(|c| c as f64));
            1.0 - ab / at > MAX_ANISOTROPY
        })
        .count();
    (n > 0).then(|| {
        format!(
            "{n} of {} texels are more anisotropic than MaterialX's specular_anisotropy holds (α_b/α_t < 0.02); \
             clamped to {MAX_ANISOTROPY}: their highlight is written less elongated",
            m.anisotropy.len()
        )
    })
}

pub fn write(m: &Material, out: &Path) -> Result<Vec<PathBuf>, ExportError> {
    let anisotropic = m.anisotropic_texels() > 0;
    let mut rough = m.clone();
    let mut aniso = Vec::with_capacity(m.roughness.len());
    let mut rotation = Vec::with_capacity(m.roughness.len());
    if anisotropic {
        for (r, a) in rough.roughness.iter_mut().zip(&m.anisotropy) {
            let (r2, an, rot) = standard_surface_anisotropy(*r as f64, a.map(|c| c as f64));
            *r = r2 as f32;
            aniso.push(an as f32);
            rotation.push(rot as f32);
        }
    }
    let [(bc, bcp), (me, mep), (ro, rop), (no, nop)] = write_textures(&rough, out)?;
    let mut extra_files = Vec::new();
    let (mut extra_nodes, mut extra_outputs, mut extra_inputs) = (String::new(), String::new(), String::new());
    if anisotropic {
        for (name, values) in [("specular_anisotropy", &aniso), ("specular_rotation", &rotation)] {
            let rel = format!("textures/{name}.png");
            let p = out.join(&rel);
            std::fs::write(&p, texture::gray_png(m.width, m.height, values, m.bit_depth)?).map_err(io(&p))?;
            extra_files.push(p);
            extra_nodes.push_str(&format!(
                r#"    <image name="{name}" type="float">
      <input name="file" type="filename" value="{rel}" />
      <input name="filtertype" type="string" value="closest" />
    </image>
"#
            ));
            extra_outputs.push_str(&format!(
                "    <output name=\"{name}_out\" type=\"float\" nodename=\"{name}\" />\n"
            ));
            extra_inputs.push_str(&format!(
                "    <input name=\"{name}\" type=\"float\" nodegraph=\"NG_gonio\" output=\"{name}_out\" />\n"
            ));
        }
    }
    let mut prov = m.provenance.clone();
    if let Some(o) = prov.as_object_mut() {
        o.insert("texture_tile_mm".into(), serde_json::json!(m.size_mm));
    }
    let doc = xml_escape(&prov.to_string());
    let text = format!(
        r#"<?xml version="1.0"?>
<materialx version="1.38" doc="{doc}">
  <nodegraph name="NG_gonio">
    <image name="base_color" type="color3">
      <input name="file" type="filename" value="{bc}" colorspace="srgb_texture" />
      <input name="filtertype" type="string" value="closest" />
    </image>
    <image name="metallic" type="float">
      <input name="file" type="filename" value="{me}" />
      <input name="filtertype" type="string" value="closest" />
    </image>
    <image name="roughness" type="float">
      <input name="file" type="filename" value="{ro}" />
      <input name="filtertype" type="string" value="closest" />
    </image>
    <image name="normal_image" type="vector3">
      <input name="file" type="filename" value="{no}" />
      <input name="filtertype" type="string" value="closest" />
    </image>
    <normalmap name="normal" type="vector3">
      <input name="in" type="vector3" nodename="normal_image" />
    </normalmap>
{extra_nodes}    <output name="base_color_out" type="color3" nodename="base_color" />
    <output name="metallic_out" type="float" nodename="metallic" />
    <output name="roughness_out" type="float" nodename="roughness" />
    <output name="normal_out" type="vector3" nodename="normal" />
{extra_outputs}  </nodegraph>
  <standard_surface name="SR_gonio" type="surfaceshader">
    <input name="base" type="float" value="1" />
    <input name="base_color" type="color3" nodegraph="NG_gonio" output="base_color_out" />
    <input name="metalness" type="float" nodegraph="NG_gonio" output="metallic_out" />
    <input name="specular" type="float" value="1" />
    <input name="specular_IOR" type="float" value="1.5" />
    <input name="specular_roughness" type="float" nodegraph="NG_gonio" output="roughness_out" />
    <input name="normal" type="vector3" nodegraph="NG_gonio" output="normal_out" />
{extra_inputs}  </standard_surface>
  <surfacematerial name="M_gonio" type="material">
    <input name="surfaceshader" type="surfaceshader" nodename="SR_gonio" />
  </surfacematerial>
</materialx>
"#
    );
    let p = out.join("material.mtlx");
    std::fs::write(&p, text).map_err(io(&p))?;
    let mut files = vec![p, bcp, mep, rop, nop];
    files.extend(extra_files);
    Ok(files)
}
