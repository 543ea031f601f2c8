//! Mitsuba 3: a scene file (XML) with the material as a `normalmap` around a `principled`
//! BSDF fed by bitmap textures (base colour sRGB, the others `raw`; nearest filtering, one
//! fitted texel per rendered texel as `gonio render` samples) on a `rectangle` of the
//! sample's size (millimetres). No emitter and no sensor: the scene is the material; add
//! them or reference the BSDF by its id `gonio_material`. Provenance in an XML comment.
//!
//! Mitsuba's `principled` is not glTF's model term for term: its diffuse is Burley's (with a
//! retro-reflection term growing with roughness) and its dielectric Fresnel the exact one at
//! η = 1.5 (Schlick's 0.04 at normal incidence); Mitsuba 3 has no BSDF that *adds* two
//! others (`blendbsdf` is a convex mix), so the glTF sum `(1 − m)c/π + specular` cannot be
//! composed exactly from its plugins. docs/guide/export.md states what the difference
//! costs, measured against `gonio render`.

use super::{io, write_textures, xml_escape, ExportError, Material};
use std::path::{Path, PathBuf};

fn bitmap(name: &str, file: &str, raw: bool) -> String {
    format!(
        r#"            <texture type="bitmap" name="{name}">
                <string name="filename" value="{file}"/>
                <string name="filter_type" value="nearest"/>
                <boolean name="raw" value="{raw}"/>
                <!-- image row 0 is the sample's +y edge (v = 1 on the rectangle) -->
                <transform name="to_uv">
                    <scale x="1" y="-1"/>
                    <translate x="0" y="1"/>
                </transform>
            </texture>
"#
    )
}

pub fn write(m: &Material, out: &Path) -> Result<Vec<PathBuf>, ExportError> {
    let [(bc, bcp), (me, mep), (ro, rop), (no, nop)] = write_textures(m, out)?;
    // `--` may not appear inside an XML comment.
    let prov = xml_escape(&m.provenance.to_string()).replace("--", "- -");
    let h = m.size_mm / 2.0;
    let text = format!(
        r#"<?xml version="1.0" encoding="utf-8"?>
<!-- gonio provenance: {prov} -->
<scene version="3.0.0">
    <bsdf type="normalmap" id="gonio_material">
{normal}        <bsdf type="principled">
{base}{metallic}{roughness}            <float name="specular" value="0.5"/>
        </bsdf>
    </bsdf>
    <shape type="rectangle" id="sample">
        <transform name="to_world">
            <scale x="{h}" y="{h}" z="1"/>
        </transform>
        <ref id="gonio_material"/>
    </shape>
</scene>
"#,
        normal = bitmap("normalmap", &no, true).replace("            <texture", "        <texture"),
        base = bitmap("base_color", &bc, false),
        metallic = bitmap("metallic", &me, true),
        roughness = bitmap("roughness", &ro, true),
    );
    let p = out.join("scene.xml");
    std::fs::write(&p, text).map_err(io(&p))?;
    Ok(vec![p, bcp, mep, rop, nop])
}
