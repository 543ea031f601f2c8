//! MaterialX 1.38: a `standard_surface` (base 1, specular 1, specular IOR 1.5, α =
//! `specular_roughness`² as in glTF) fed by `image` nodes (base colour in `srgb_texture`,
//! the others raw) and a tangent-space `normalmap`. Provenance in the document's `doc`
//! attribute (JSON). `OUT/material.mtlx` and `OUT/textures/`.

use super::{io, write_textures, xml_escape, ExportError, Material};
use std::path::{Path, PathBuf};

pub fn write(m: &Material, out: &Path) -> Result<Vec<PathBuf>, ExportError> {
    let [(bc, bcp), (me, mep), (ro, rop), (no, nop)] = write_textures(m, out)?;
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
    <output name="base_color_out" type="color3" nodename="base_color" />
    <output name="metallic_out" type="float" nodename="metallic" />
    <output name="roughness_out" type="float" nodename="roughness" />
    <output name="normal_out" type="vector3" nodename="normal" />
  </nodegraph>
  <standard_surface name="SR_gonio" type="surfaceshader">
    <input name="base" type="float" value="1" />
    <input name="base_color" type="color3" nodegraph="NG_gonio" output="base_color_out" />
    <input name="metalness" type="float" nodegraph="NG_gonio" output="metallic_out" />
    <input name="specular" type="float" value="1" />
    <input name="specular_IOR" type="float" value="1.5" />
    <input name="specular_roughness" type="float" nodegraph="NG_gonio" output="roughness_out" />
    <input name="normal" type="vector3" nodegraph="NG_gonio" output="normal_out" />
  </standard_surface>
  <surfacematerial name="M_gonio" type="material">
    <input name="surfaceshader" type="surfaceshader" nodename="SR_gonio" />
  </surfacematerial>
</materialx>
"#
    );
    let p = out.join("material.mtlx");
    std::fs::write(&p, text).map_err(io(&p))?;
    Ok(vec![p, bcp, mep, rop, nop])
}
