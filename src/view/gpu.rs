//! The factor blocks the relight page's shader decodes for DFMF (UBO2014 `.btf` and
//! `.gbtf`), median cut and homomorphic files, and what the page needs to know about them.
//!
//! PVMF, PCA and local PCA are served by `server::gpu_blocks`; this module adds the other
//! three decoders. Each decoder is a transcription of its CPU decoder in `src/compress/`
//! (the page then interpolates the decoded grid-pair values exactly as `gonio render`
//! does: `Σ w · decode(pair)`):
//!
//! * **DFMF** (`dfmf.rs`, `Dfmf::reconstruct` of one grid pair): per channel of the colour
//!   model `c_ch = Σ_k U[view·L + light, k] · SxV[texel, k]`, then the colour model's
//!   inverse with its clamping ([`gonio_btf::compress::dfmf::decode_color`]: RGB as is;
//!   log-YUV `Y = e^{c₀} − ε`, `U = c₁·Y + ε`, `V = c₂·Y + ε`, RGB = `M·YUV` clamped to
//!   [0, 1]; CIELab through XYZ, negative RGB clamped to 0). Blocks: `sxv0..2` (texels ×
//!   c_ch, padded to a multiple of 4 columns) and one block of all U rows laid out for a
//!   texture of `views · Σ c4_ch` columns × `lights` rows.
//! * **Median cut** (`median_cut.rs`, `reconstruct`): `brdfs[index[texel], (view·L +
//!   light)·3 + ch]`. Blocks: the index image (f32, exact integers), then one block per
//!   view: `boxes × lights` RGBA.
//! * **Homomorphic** (`homomorphic.rs`, `reconstruct`): per channel `A > 0 ?
//!   max(A·(exp(P[l] + Q[v] + R[bin(l, v)]) − ε), 0) : 0`. Blocks: the half-vector bin of
//!   every grid pair (f32, `views × lights`), then one RGBA plane of all texels per table
//!   entry: albedo, every light, every view, every bin.
//!
//! **Precision.** Texel-side values go as half floats (RGBA16F textures) where that costs
//! nothing visible: median-cut centroids (linear values, relative error ≤ 2⁻¹¹) and the
//! S·V of an RGB DFMF (a linear sum, like PVMF's bases), or any block whose values are
//! exactly representable in f16 (a `.btf` written with `--precision f16`). Values that go
//! through `exp` or a cube (log-YUV and CIELab DFMF, homomorphic tables) are sent as f32:
//! an absolute error of 2⁻¹¹·|x| in an exponent of magnitude ~10 is a relative error of
//! 0.5 % in the result, about 0.6/255 on a bright value. Rows of U are f32 (small).

use super::source::Source;
use gonio_btf::compress::dfmf::{self, inverse3, ColorModel};
use gonio_btf::compress::homomorphic;
use gonio_btf::compress::interp::AnyModel;
use gonio_btf::compress::{CodecId, CompressedBtf, Layout, Params};
use serde_json::{json, Value};

/// Linear sRGB (D65) → CIE XYZ: the matrix of `compress::dfmf` (IEC 61966-2-1); the unit
/// test `lab_constants_decode_as_the_cpu_does` checks that the page's constants derived
/// from it decode exactly as [`dfmf::decode_color`].
const RGB_TO_XYZ: [[f64; 3]; 3] = [
    [0.412_456_4, 0.357_576_1, 0.180_437_5],
    [0.212_672_9, 0.715_152_2, 0.072_175_0],
    [0.019_333_9, 0.119_192_0, 0.950_304_1],
];

/// CIELab decoding constants in f32 as `dfmf::LabDecoder` computes them: the white point
/// (XYZ of RGB (1, 1, 1)) and XYZ → RGB.
pub fn lab_constants() -> ([f32; 3], [[f32; 3]; 3]) {
    let white = RGB_TO_XYZ.map(|r| (r[0] + r[1] + r[2]) as f32);
    let m = inverse3(&RGB_TO_XYZ).map(|r| r.map(|v| v as f32));
    (white, m)
}

/// The DFMF factors of a source, whichever container holds them.
pub struct DfmfFactors<'a> {
    pub model: ColorModel,
    pub c: [usize; 3],
    pub u: [&'a [f32]; 3],
    pub sxv: [&'a [f32]; 3],
}

/// Which of this module's decoders a source uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Dfmf,
    MedianCut,
    Homomorphic,
}

impl Kind {
    pub fn name(self) -> &'static str {
        match self {
            Kind::Dfmf => CodecId::Dfmf.name(),
            Kind::MedianCut => CodecId::MedianCut.name(),
            Kind::Homomorphic => CodecId::Homomorphic.name(),
        }
    }
}

fn gbtf(src: &Source) -> Option<&CompressedBtf> {
    match src {
        Source::Model {
            model: AnyModel::Gbtf(m),
            ..
        } => Some(m),
        _ => None,
    }
}

/// This module's decoder for `src`, if any.
pub fn kind(src: &Source) -> Option<Kind> {
    match src {
        Source::Model {
            model: AnyModel::Dfmf(_),
            ..
        } => Some(Kind::Dfmf),
        _ => match gbtf(src)?.layout() {
            Layout::ChannelFactors => Some(Kind::Dfmf),
            Layout::Index { .. } => Some(Kind::MedianCut),
            Layout::HalfVectorTables { .. } => Some(Kind::Homomorphic),
            // PCA, PVMF and local PCA: `server::gpu_blocks`; the rest has no GPU decoder.
            Layout::Basis
            | Layout::ViewBases
            | Layout::Clusters { .. }
            | Layout::PerTexel
            | Layout::AnalyticPerTexel => None,
        },
    }
}

/// The DFMF factors of `src` (a UBO2014 `.btf` or a DFMF `.gbtf`).
pub fn dfmf_factors(src: &Source) -> Option<DfmfFactors<'_>> {
    match src {
        Source::Model {
            model: AnyModel::Dfmf(d),
            ..
        } => Some(DfmfFactors {
            model: d.color_model,
            c: std::array::from_fn(|ch| d.channels[ch].c),
            u: std::array::from_fn(|ch| &d.channels[ch].u[..]),
            sxv: std::array::from_fn(|ch| &d.channels[ch].sxv[..]),
        }),
        _ => {
            let m = gbtf(src)?;
            if m.layout() != Layout::ChannelFactors {
                return None;
            }
            let (model, c) = dfmf::channel_components(&Params::new(m.method(), m.components())).ok()?;
            let b = &m.gbtf.blocks;
            Some(DfmfFactors {
                model,
                c,
                u: std::array::from_fn(|ch| &b[2 * ch][..]),
                sxv: std::array::from_fn(|ch| &b[2 * ch + 1][..]),
            })
        }
    }
}

fn c4(c: usize) -> usize {
    c.div_ceil(4)
}

fn exact_in_f16(v: &[f32]) -> bool {
    v.iter().all(|&x| half::f16::from_f32(x).to_f32() == x)
}

/// Whether the texel-side blocks go as f16 (see the module doc).
fn texel_half(src: &Source, k: Kind) -> bool {
    match k {
        Kind::MedianCut => true,
        Kind::Homomorphic => false,
        Kind::Dfmf => {
            dfmf_factors(src).is_some_and(|f| f.model == ColorModel::Rgb || f.sxv.iter().all(|s| exact_in_f16(s)))
        }
    }
}

/// Half-vector bins of a homomorphic file (0 for other layouts, which have no bins).
fn half_bins(m: &CompressedBtf) -> usize {
    match m.layout() {
        Layout::HalfVectorTables { half_bins } => half_bins,
        Layout::Basis
        | Layout::ViewBases
        | Layout::Clusters { .. }
        | Layout::Index { .. }
        | Layout::ChannelFactors
        | Layout::PerTexel
        | Layout::AnalyticPerTexel => 0,
    }
}

/// Boxes of a median-cut file (0 for other layouts, which have no boxes).
fn boxes(m: &CompressedBtf) -> usize {
    match m.layout() {
        Layout::Index { boxes } => boxes,
        Layout::Basis
        | Layout::ViewBases
        | Layout::Clusters { .. }
        | Layout::ChannelFactors
        | Layout::HalfVectorTables { .. }
        | Layout::PerTexel
        | Layout::AnalyticPerTexel => 0,
    }
}

/// Number of blocks of `/api/factors` for this decoder.
pub fn block_count(src: &Source, k: Kind) -> usize {
    let m = src.model();
    let (nl, nv) = (m.lights_deg().len(), m.views_deg().len());
    match k {
        Kind::Dfmf => 4,
        Kind::MedianCut => 1 + nv,
        Kind::Homomorphic => 2 + nl + nv + gbtf(src).map(half_bins).unwrap_or(0),
    }
}

/// The page's description of the decoder (merged into `/api/info`).
pub fn describe(src: &Source, k: Kind) -> Value {
    let half = texel_half(src, k);
    let mut v = json!({
        "gpu_blocks": block_count(src, k),
        "texel_format": if half { "f16" } else { "f32" },
    });
    match k {
        Kind::Dfmf => {
            if let Some(f) = dfmf_factors(src) {
                let (white, xyz_to_rgb) = lab_constants();
                v["color_model"] = json!(match f.model {
                    ColorModel::Rgb => 0,
                    ColorModel::LogYuv => 1,
                    ColorModel::Lab => 2,
                });
                v["channel_components"] = json!(f.c);
                v["lab_white"] = json!(white);
                v["lab_xyz_to_rgb"] = json!(xyz_to_rgb);
            }
        }
        Kind::MedianCut => v["boxes"] = json!(gbtf(src).map(boxes).unwrap_or(0)),
        Kind::Homomorphic => v["half_bins"] = json!(gbtf(src).map(half_bins).unwrap_or(0)),
    }
    v
}

fn push(out: &mut Vec<u8>, x: f32, half: bool) {
    if half {
        out.extend_from_slice(&half::f16::from_f32(x).to_le_bytes());
    } else {
        out.extend_from_slice(&x.to_le_bytes());
    }
}

/// Rows of `cols` values padded to `4 · c4(cols)` columns.
fn padded(data: &[f32], cols: usize, half: bool) -> Vec<u8> {
    let w = 4 * c4(cols);
    let rows = data.len().checked_div(cols).unwrap_or(0);
    let mut out = Vec::with_capacity(rows * w * if half { 2 } else { 4 });
    for r in 0..rows {
        for j in 0..w {
            push(&mut out, if j < cols { data[r * cols + j] } else { 0.0 }, half);
        }
    }
    out
}

/// Block `i` (checked by the caller to be below [`block_count`]) as little-endian bytes:
/// f16 or f32 per [`describe`]'s `texel_format` for texel-side blocks, f32 otherwise.
pub fn block(src: &Source, k: Kind, i: usize) -> Vec<u8> {
    let half = texel_half(src, k);
    let m = src.model();
    let (nl, nv, t) = (m.lights_deg().len(), m.views_deg().len(), m.width() * m.height());
    match k {
        Kind::Dfmf => {
            let Some(f) = dfmf_factors(src) else { return Vec::new() };
            if i < 3 {
                return padded(f.sxv[i], f.c[i], half);
            }
            // U rows: texture row = light, column = view · Σc4 + offset(ch) + k.
            let mut out = Vec::with_capacity(nl * nv * 4 * (c4(f.c[0]) + c4(f.c[1]) + c4(f.c[2])) * 4);
            for l in 0..nl {
                for v in 0..nv {
                    let r = v * nl + l;
                    for ch in 0..3 {
                        let c = f.c[ch];
                        for j in 0..4 * c4(c) {
                            push(&mut out, if j < c { f.u[ch][r * c + j] } else { 0.0 }, false);
                        }
                    }
                }
            }
            out
        }
        Kind::MedianCut => {
            let Some(g) = gbtf(src) else { return Vec::new() };
            let (index, brdfs) = (&g.gbtf.blocks[0], &g.gbtf.blocks[1]);
            if i == 0 {
                return index.iter().flat_map(|x| x.to_le_bytes()).collect();
            }
            let v = i - 1;
            let dims = nl * nv * 3;
            let mut out = Vec::new();
            for b in 0..boxes(g) {
                for l in 0..nl {
                    let o = b * dims + (v * nl + l) * 3;
                    for ch in 0..4 {
                        push(&mut out, if ch < 3 { brdfs[o + ch] } else { 0.0 }, half);
                    }
                }
            }
            out
        }
        Kind::Homomorphic => {
            let Some(g) = gbtf(src) else { return Vec::new() };
            let nh = half_bins(g);
            if i == 0 {
                let h = g.header();
                let bins = homomorphic::half_bins_of(&h.lights_deg, &h.views_deg, nh);
                return bins.iter().flat_map(|&b| (b as f32).to_le_bytes()).collect();
            }
            // Plane i − 1: albedo, lights, views, bins.
            let p = i - 1;
            let b = &g.gbtf.blocks;
            let (block, dirs, d) = if p == 0 {
                (&b[0], 1, 0)
            } else if p <= nl {
                (&b[1], nl, p - 1)
            } else if p <= nl + nv {
                (&b[2], nv, p - 1 - nl)
            } else {
                (&b[3], nh, p - 1 - nl - nv)
            };
            let mut out = Vec::with_capacity(t * 4 * if half { 2 } else { 4 });
            for texel in 0..t {
                let o = (texel * dirs + d) * 3;
                for ch in 0..4 {
                    push(&mut out, if ch < 3 { block[o + ch] } else { 0.0 }, half);
                }
            }
            out
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The constants the page uses for CIELab, with the page's arithmetic (f32), decode
    /// as `dfmf::decode_color` does, bit for bit.
    #[test]
    fn lab_constants_decode_as_the_cpu_does() {
        let (white, m) = lab_constants();
        let finv = |t: f32| {
            const D: f32 = 6.0 / 29.0;
            if t > D {
                t * t * t
            } else {
                3.0 * D * D * (t - 4.0 / 29.0)
            }
        };
        for (i, lab) in [
            [50.0f32, 10.0, -20.0],
            [0.0, 0.0, 0.0],
            [100.0, 0.0, 0.0],
            [3.0, -40.0, 60.0],
            [75.5, 80.0, 30.0],
        ]
        .into_iter()
        .enumerate()
        {
            let fy = (lab[0] + 16.0) / 116.0;
            let (fx, fz) = (fy + lab[1] / 500.0, fy - lab[2] / 200.0);
            let xyz = [white[0] * finv(fx), white[1] * finv(fy), white[2] * finv(fz)];
            let rgb = m.map(|r| (r[0] * xyz[0] + r[1] * xyz[1] + r[2] * xyz[2]).max(0.0));
            assert_eq!(rgb, dfmf::decode_color(ColorModel::Lab, lab), "case {i}: {lab:?}");
        }
    }
}
