//! OpenUSD (text `.usda`): a quad mesh of the sample's size (millimetres:
//! `metersPerUnit = 0.001`, Z up) with `st` texture coordinates, bound to a
//! `UsdPreviewSurface` fed by `UsdUVTexture`s (base colour sRGB, the others raw; the normal
//! map scaled ×2 − 1 to tangent space). UsdPreviewSurface has no anisotropy. Provenance in
//! the layer's `customLayerData`. `OUT/material.usda` and `OUT/textures/`, or one
//! `OUT.usdz` ([`write_usdz`]).

use super::{io, write_textures, ExportError, Material};
use std::path::{Path, PathBuf};

/// A USD string literal (JSON's escaping is a subset USD reads).
fn usd_string(s: &str) -> String {
    serde_json::to_string(s).expect("a string serializes")
}

pub fn write(m: &Material, out: &Path) -> Result<Vec<PathBuf>, ExportError> {
    let [(bc, bcp), (me, mep), (ro, rop), (no, nop)] = write_textures(m, out)?;
    let h = m.size_mm / 2.0;
    let prov = usd_string(&m.provenance.to_string());
    let tex = |name: &str, file: &str, space: &str, outputs: &str, extra: &str| {
        format!(
            r#"        def Shader "{name}"
        {{
            uniform token info:id = "UsdUVTexture"
            asset inputs:file = @{file}@
            token inputs:sourceColorSpace = "{space}"
            token inputs:wrapS = "repeat"
            token inputs:wrapT = "repeat"
            float2 inputs:st.connect = </Sample/Material/St.outputs:result>
{extra}            {outputs}
        }}
"#
        )
    };
    let text = format!(
        r#"#usda 1.0
(
    customLayerData = {{
        string gonio_provenance = {prov}
    }}
    defaultPrim = "Sample"
    metersPerUnit = 0.001
    upAxis = "Z"
)

def Xform "Sample"
{{
    def Mesh "Quad" (
        prepend apiSchemas = ["MaterialBindingAPI"]
    )
    {{
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
        point3f[] points = [({mh}, {mh}, 0), ({h}, {mh}, 0), ({h}, {h}, 0), ({mh}, {h}, 0)]
        normal3f[] normals = [(0, 0, 1), (0, 0, 1), (0, 0, 1), (0, 0, 1)] (
            interpolation = "vertex"
        )
        texCoord2f[] primvars:st = [(0, 0), (1, 0), (1, 1), (0, 1)] (
            interpolation = "vertex"
        )
        uniform token subdivisionScheme = "none"
        rel material:binding = </Sample/Material>
    }}

    def Material "Material"
    {{
        token outputs:surface.connect = </Sample/Material/Surface.outputs:surface>

        def Shader "Surface"
        {{
            uniform token info:id = "UsdPreviewSurface"
            color3f inputs:diffuseColor.connect = </Sample/Material/BaseColor.outputs:rgb>
            float inputs:metallic.connect = </Sample/Material/Metallic.outputs:r>
            float inputs:roughness.connect = </Sample/Material/Roughness.outputs:r>
            normal3f inputs:normal.connect = </Sample/Material/Normal.outputs:rgb>
            float inputs:ior = 1.5
            int inputs:useSpecularWorkflow = 0
            token outputs:surface
        }}

        def Shader "St"
        {{
            uniform token info:id = "UsdPrimvarReader_float2"
            string inputs:varname = "st"
            float2 outputs:result
        }}

{t1}{t2}{t3}{t4}    }}
}}
"#,
        mh = -h,
        t1 = tex("BaseColor", &bc, "sRGB", "float3 outputs:rgb", ""),
        t2 = tex("Metallic", &me, "raw", "float outputs:r", ""),
        t3 = tex("Roughness", &ro, "raw", "float outputs:r", ""),
        t4 = tex(
            "Normal",
            &no,
            "raw",
            "float3 outputs:rgb",
            "            float4 inputs:scale = (2, 2, 2, 1)\n            float4 inputs:bias = (-1, -1, -1, 0)\n"
        ),
    );
    let p = out.join("material.usda");
    std::fs::write(&p, text).map_err(io(&p))?;
    Ok(vec![p, bcp, mep, rop, nop])
}

/// Bytes of every file's data in a `.usdz` start at a multiple of this (the USDZ
/// specification: 64-byte alignment, so a reader can map the files in place).
pub const USDZ_ALIGN: usize = 64;

/// One `.usdz`: the same `material.usda` (first, as the USDZ specification requires) and
/// its textures in a zip archive, stored (no compression), every file's data 64-byte
/// aligned by padding the local header's extra field (a block of id 0x1986, as OpenUSD's
/// own writer pads), no data descriptors, timestamps fixed at 1980-01-01 00:00 (same
/// bytes for the same material). The parts are written to a sibling folder first, then
/// packed and removed.
pub fn write_usdz(m: &Material, out: &Path) -> Result<PathBuf, ExportError> {
    let name = out.file_name().and_then(|n| n.to_str()).unwrap_or("out.usdz");
    let parts = out.with_file_name(format!(".{name}.parts"));
    if parts.exists() {
        std::fs::remove_dir_all(&parts).map_err(io(&parts))?;
    }
    let files = write(m, &parts)?;
    let mut entries = Vec::with_capacity(files.len());
    for f in &files {
        let rel = f
            .strip_prefix(&parts)
            .map_err(|_| ExportError::Output {
                path: f.display().to_string(),
                reason: "a part outside the package folder".into(),
            })?
            .components()
            .map(|c| c.as_os_str().to_string_lossy().into_owned())
            .collect::<Vec<_>>()
            .join("/");
        entries.push((rel, std::fs::read(f).map_err(io(f))?));
    }
    std::fs::remove_dir_all(&parts).map_err(io(&parts))?;
    let zip = usdz_bytes(&entries).map_err(|reason| ExportError::Output {
        path: out.display().to_string(),
        reason,
    })?;
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(io(parent))?;
    }
    std::fs::write(out, zip).map_err(io(out))?;
    Ok(out.to_path_buf())
}

/// A stored, 64-byte-aligned zip of `entries` (name, bytes), in order.
pub fn usdz_bytes(entries: &[(String, Vec<u8>)]) -> Result<Vec<u8>, String> {
    const DOS_DATE: u16 = (1 << 5) | 1; // 1980-01-01
    let mut out: Vec<u8> = Vec::new();
    let mut central: Vec<u8> = Vec::new();
    let u32_of = |x: usize, what: &str| u32::try_from(x).map_err(|_| format!("{what} {x} exceeds a zip's 4 GiB"));
    for (name, data) in entries {
        let offset = out.len();
        let name_len = u16::try_from(name.len()).map_err(|_| format!("entry name {name} too long"))?;
        let after = offset + 30 + name.len();
        let mut pad = (USDZ_ALIGN - after % USDZ_ALIGN) % USDZ_ALIGN;
        if pad > 0 && pad < 4 {
            pad += USDZ_ALIGN;
        }
        let crc = crc32fast::hash(data);
        let size = u32_of(data.len(), "entry size")?;
        let header = |sig: u32, central: bool| {
            let mut h = Vec::new();
            h.extend(sig.to_le_bytes());
            if central {
                h.extend(20u16.to_le_bytes()); // made by: 2.0
            }
            h.extend(10u16.to_le_bytes()); // needed: 1.0 (stored)
            h.extend(0u16.to_le_bytes()); // flags
            h.extend(0u16.to_le_bytes()); // stored
            h.extend(0u16.to_le_bytes()); // time
            h.extend(DOS_DATE.to_le_bytes());
            h.extend(crc.to_le_bytes());
            h.extend(size.to_le_bytes());
            h.extend(size.to_le_bytes());
            h.extend(name_len.to_le_bytes());
            h
        };
        out.extend(header(0x0403_4b50, false));
        out.extend((pad as u16).to_le_bytes());
        out.extend(name.as_bytes());
        if pad > 0 {
            out.extend(0x1986u16.to_le_bytes());
            out.extend(((pad - 4) as u16).to_le_bytes());
            out.extend(std::iter::repeat_n(0u8, pad - 4));
        }
        debug_assert_eq!(out.len() % USDZ_ALIGN, 0);
        out.extend(data);
        central.extend(header(0x0201_4b50, true));
        central.extend(0u16.to_le_bytes()); // extra
        central.extend(0u16.to_le_bytes()); // comment
        central.extend(0u16.to_le_bytes()); // disk
        central.extend(0u16.to_le_bytes()); // internal attributes
        central.extend(0u32.to_le_bytes()); // external attributes
        central.extend(u32_of(offset, "offset")?.to_le_bytes());
        central.extend(name.as_bytes());
    }
    let n = u16::try_from(entries.len()).map_err(|_| "too many entries".to_string())?;
    let cd_offset = u32_of(out.len(), "offset")?;
    let cd_size = u32_of(central.len(), "central directory")?;
    out.extend(central);
    out.extend(0x0605_4b50u32.to_le_bytes());
    out.extend(0u16.to_le_bytes());
    out.extend(0u16.to_le_bytes());
    out.extend(n.to_le_bytes());
    out.extend(n.to_le_bytes());
    out.extend(cd_size.to_le_bytes());
    out.extend(cd_offset.to_le_bytes());
    out.extend(0u16.to_le_bytes());
    Ok(out)
}
