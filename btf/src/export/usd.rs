//! OpenUSD (text `.usda`): a quad mesh of the sample's size (millimetres:
//! `metersPerUnit = 0.001`, Z up) with `st` texture coordinates, bound to a
//! `UsdPreviewSurface` fed by `UsdUVTexture`s (base colour sRGB, the others raw; the normal
//! map scaled ×2 − 1 to tangent space). UsdPreviewSurface has no anisotropy. Provenance in
//! the layer's `customLayerData`. `OUT/material.usda` and `OUT/textures/`.

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
