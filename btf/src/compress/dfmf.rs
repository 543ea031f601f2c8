//! DFMF: decorrelated full-matrix factorization, the method of Bonn's UBO2014 `.btf` files.
//!
//! The whole BTF is one `measurements × texels` matrix per colour channel (rows
//! `view · L + light`, columns the texels), factorized as `U · (S·V)ᵀ` with `c` components
//! per channel. "Decorrelated" refers to the colour model the channels are in before the
//! factorization. Two models exist, because those are the two the public reader
//! (`btf-extractor` 1.7.0, `btf.hh`, `BTFFetchSpectrum`) decodes:
//!
//! * [`ColorModel::Rgb`] (code 0): the linear R, G, B values as they are.
//! * [`ColorModel::LogYuv`] (code 11): luminance in log space and chroma as ratios to the
//!   luminance: `c₀ = ln(Y + ε)`, `c₁ = (U − ε) / Y`, `c₂ = (V − ε) / Y` with ε = 1e-5 and
//!   (Y, U, V) = `M⁻¹ · (R, G, B)`, `M` the reader's YUV → RGB matrix ([`YUV_TO_RGB`]).
//!   The reader inverts this (`Y = exp(c₀) − ε`, `U = c₁·Y + ε`, …) and **clamps RGB to
//!   [0, 1]**. Why it is worth it: the log compresses the specular dynamic range so the
//!   factorization's squared error is spent evenly over dark and bright measurements, and
//!   the chroma ratios of a material vary little, so they need few components.
//!   Negative inputs (sensor noise below black) are clamped to 0 before the transform,
//!   and the chroma denominator is at least ε, so dark texels cannot blow up the ratios.
//!
//! The factorization is the streamed randomized SVD of PCA (`super::pca`) (Halko,
//! Martinsson, Tropp 2011) run on the three channel matrices in the same passes over the
//! dataset: the full matrix (6561 × 65536 per channel at 256²) is never held. The final
//! small SVD runs in f64 (see the module docs of [`super`] for f32 versus f64).
//!
//! [`Dfmf::reconstruct`] mirrors the reader's arithmetic (f32 dot products, the same ε,
//! the same clamping), so a file decodes to the same images in gonio and in
//! `btf-extractor` (checked by `tests/interop/check_ubo2014.py`).

use super::container::{BlockInfo, Gbtf, GbtfHeader};
use super::data::DatasetViews;
use super::error::CompressError;
use super::linalg::{row_major_f32, truncated_svd, GaussianSketch, SketchKeying};
use super::params::{
    bad_file, header_for, Codec, CodecId, Decode, EncodeInfo, Knobs, Layout, Method, Opened, Params, Shard,
};
use super::rsvd::{Channel, Rsvd, ViewSource};
use faer::{Mat, MatRef};
use serde::{Deserialize, Serialize};
use std::sync::Arc;

/// The ε of the reader's colour model 11 (`drr_eps` in `btf.hh`).
pub const DRR_EPS: f32 = 1e-5;

/// The reader's YUV → RGB matrix (`YUVToRGB` in `btf.hh`); rows give R, G, B.
pub const YUV_TO_RGB: [[f32; 3]; 3] = [[1.0, 0.0, 1.13983], [1.0, -0.39465, -0.5806], [1.0, 2.03211, 0.0]];

pub use super::params::ColorModel;

/// Linear sRGB (D65) → CIE XYZ (IEC 61966-2-1).
const RGB_TO_XYZ: [[f64; 3]; 3] = [
    [0.412_456_4, 0.357_576_1, 0.180_437_5],
    [0.212_672_9, 0.715_152_2, 0.072_175_0],
    [0.019_333_9, 0.119_192_0, 0.950_304_1],
];

/// The white point: XYZ of linear RGB (1, 1, 1), so a grey maps to a* = b* = 0 exactly.
fn lab_white() -> [f64; 3] {
    RGB_TO_XYZ.map(|r| r[0] + r[1] + r[2])
}

/// δ = 6/29 of the CIELab companding function.
const LAB_DELTA: f64 = 6.0 / 29.0;

fn lab_f(t: f64) -> f64 {
    if t > LAB_DELTA * LAB_DELTA * LAB_DELTA {
        t.cbrt()
    } else {
        // The linear segment, extended below 0 (sensor noise below black stays finite
        // and invertible).
        t / (3.0 * LAB_DELTA * LAB_DELTA) + 4.0 / 29.0
    }
}

#[inline]
fn lab_f_inv(t: f32) -> f32 {
    const D: f32 = 6.0 / 29.0;
    if t > D {
        t * t * t
    } else {
        3.0 * D * D * (t - 4.0 / 29.0)
    }
}

/// Inverse of a 3 × 3 matrix by its adjugate (f64); the callers' matrices are fixed and
/// well conditioned.
pub fn inverse3(m: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let cof = |r0: usize, r1: usize, c0: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    let det = m[0][0] * cof(1, 2, 1, 2) - m[0][1] * cof(1, 2, 0, 2) + m[0][2] * cof(1, 2, 0, 1);
    [
        [cof(1, 2, 1, 2) / det, -cof(0, 2, 1, 2) / det, cof(0, 1, 1, 2) / det],
        [-cof(1, 2, 0, 2) / det, cof(0, 2, 0, 2) / det, -cof(0, 1, 0, 2) / det],
        [cof(1, 2, 0, 1) / det, -cof(0, 2, 0, 1) / det, cof(0, 1, 0, 1) / det],
    ]
}

/// Linear RGB → CIELab (f64).
pub fn rgb_to_lab(rgb: [f64; 3]) -> [f64; 3] {
    let w = lab_white();
    let xyz = RGB_TO_XYZ.map(|r| r[0] * rgb[0] + r[1] * rgb[1] + r[2] * rgb[2]);
    let (fx, fy, fz) = (lab_f(xyz[0] / w[0]), lab_f(xyz[1] / w[1]), lab_f(xyz[2] / w[2]));
    [116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)]
}

/// What decoding CIELab needs, precomputed in f32: the white point and XYZ → RGB.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LabDecoder {
    white: [f32; 3],
    xyz_to_rgb: [[f32; 3]; 3],
}

impl Default for LabDecoder {
    fn default() -> Self {
        LabDecoder {
            white: lab_white().map(|v| v as f32),
            xyz_to_rgb: inverse3(&RGB_TO_XYZ).map(|r| r.map(|v| v as f32)),
        }
    }
}

impl LabDecoder {
    /// CIELab → linear RGB (f32), negative results clamped to 0 (no upper clamp: the
    /// dataset's linear values may exceed 1 in highlights).
    #[inline]
    pub fn to_rgb(&self, lab: [f32; 3]) -> [f32; 3] {
        let fy = (lab[0] + 16.0) / 116.0;
        let (fx, fz) = (fy + lab[1] / 500.0, fy - lab[2] / 200.0);
        let xyz = [
            self.white[0] * lab_f_inv(fx),
            self.white[1] * lab_f_inv(fy),
            self.white[2] * lab_f_inv(fz),
        ];
        self.xyz_to_rgb
            .map(|r| (r[0] * xyz[0] + r[1] * xyz[1] + r[2] * xyz[2]).max(0.0))
    }
}

/// `M⁻¹`, the RGB → YUV matrix exactly inverse to [`YUV_TO_RGB`] (computed in f64).
pub fn rgb_to_yuv() -> [[f64; 3]; 3] {
    inverse3(&YUV_TO_RGB.map(|r| r.map(f64::from)))
}

/// Linear RGB → the model's channels.
pub fn encode_color(model: ColorModel, m_inv: &[[f64; 3]; 3], rgb: [f32; 3]) -> [f64; 3] {
    match model {
        ColorModel::Rgb => rgb.map(f64::from),
        ColorModel::LogYuv => {
            let c = rgb.map(|v| f64::from(v.max(0.0)));
            let yuv = m_inv.map(|r| r[0] * c[0] + r[1] * c[1] + r[2] * c[2]);
            let eps = f64::from(DRR_EPS);
            let y = yuv[0].max(0.0);
            let den = y.max(eps);
            [(y + eps).ln(), (yuv[1] - eps) / den, (yuv[2] - eps) / den]
        }
        ColorModel::Lab => rgb_to_lab(rgb.map(f64::from)),
    }
}

/// The model's channels → linear RGB, exactly as `BTFFetchSpectrum` does it (f32).
#[inline]
pub fn decode_color(model: ColorModel, c: [f32; 3]) -> [f32; 3] {
    match model {
        ColorModel::Rgb => c,
        ColorModel::LogYuv => {
            let y = c[0].exp() - DRR_EPS;
            let yuv = [y, c[1] * y + DRR_EPS, c[2] * y + DRR_EPS];
            YUV_TO_RGB.map(|r| (r[0] * yuv[0] + r[1] * yuv[1] + r[2] * yuv[2]).clamp(0.0, 1.0))
        }
        ColorModel::Lab => LabDecoder::default().to_rgb(c),
    }
}

/// Parameters of [`encode`].
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct DfmfParams {
    pub color_model: ColorModel,
    /// Components per channel (channel order of the model: R, G, B or logY, U/Y, V/Y).
    pub components: [usize; 3],
    /// Seed of the Gaussian sketch.
    pub seed: u64,
    pub oversample: usize,
    /// Power iterations (one more pass over the dataset each).
    pub power_iters: usize,
}

impl DfmfParams {
    pub fn new(color_model: ColorModel, components: usize) -> Self {
        DfmfParams {
            color_model,
            components: [components; 3],
            seed: 1,
            oversample: 10,
            power_iters: 2,
        }
    }
}

/// The factors of one channel.
#[derive(Clone, Debug, PartialEq)]
pub struct ChannelFactors {
    /// Components.
    pub c: usize,
    /// Singular values (informative: the reader skips them).
    pub sigma: Vec<f32>,
    /// Row-major `(views · lights) × c`, row `view · L + light`.
    pub u: Vec<f32>,
    /// Row-major `texels × c` (S·V), texel `y · W + x` with row 0 the image's top row.
    pub sxv: Vec<f32>,
}

/// A DFMF-factorized BTF.
#[derive(Clone, Debug, PartialEq)]
pub struct Dfmf {
    pub color_model: ColorModel,
    pub width: usize,
    pub height: usize,
    pub lights_deg: Vec<[f64; 2]>,
    pub views_deg: Vec<[f64; 2]>,
    pub channels: Vec<ChannelFactors>,
}

/// Channel `ch` of the interleaved pixels `out` from texel rows `sxv` (`texels × c`,
/// `c = u.len()`): `out[3t + ch] = Σ_k u[k] · sxv[t, k]`.
///
/// LANES texels at once: independent sums keep the FPU busy where one texel's sum would
/// wait on each add. Every texel's sum runs in the order of a plain loop, so the decoded
/// bytes do not depend on the grouping.
fn decode_channel(out: &mut [f32], ch: usize, u: &[f32], sxv: &[f32]) {
    const LANES: usize = 8;
    let c = u.len();
    if c == 0 {
        for px in out.chunks_exact_mut(3) {
            px[ch] = 0.0;
        }
        return;
    }
    let mut pxs = out.chunks_exact_mut(3 * LANES);
    let mut svs = sxv.chunks_exact(c * LANES);
    for (px, sv) in (&mut pxs).zip(&mut svs) {
        let mut s = [0f32; LANES];
        for (k, &uk) in u.iter().enumerate() {
            for (j, a) in s.iter_mut().enumerate() {
                *a += uk * sv[j * c + k];
            }
        }
        for (j, a) in s.into_iter().enumerate() {
            px[3 * j + ch] = a;
        }
    }
    for (px, sv) in pxs
        .into_remainder()
        .chunks_exact_mut(3)
        .zip(svs.remainder().chunks_exact(c))
    {
        let mut s = 0f32;
        for (uk, v) in u.iter().zip(sv) {
            s += uk * v;
        }
        px[ch] = s;
    }
}

impl Dfmf {
    pub fn n_lights(&self) -> usize {
        self.lights_deg.len()
    }
    pub fn n_views(&self) -> usize {
        self.views_deg.len()
    }
    pub fn texels(&self) -> usize {
        self.width * self.height
    }

    /// Check that every block has the size the grid implies.
    pub fn validate(&self) -> Result<(), CompressError> {
        let rows = self.n_lights() * self.n_views();
        if self.channels.len() != 3 {
            return Err(CompressError::Invalid(format!(
                "DFMF with {} channels, only 3 are supported",
                self.channels.len()
            )));
        }
        for (i, ch) in self.channels.iter().enumerate() {
            if ch.c == 0 || ch.u.len() != rows * ch.c || ch.sxv.len() != self.texels() * ch.c {
                return Err(CompressError::Invalid(format!(
                    "DFMF channel {i}: {} components, U has {} values ({rows} rows needed), S·V has {} ({} texels)",
                    ch.c,
                    ch.u.len(),
                    ch.sxv.len(),
                    self.texels()
                )));
            }
        }
        Ok(())
    }

    /// The model-space values of every texel of measurement row `row` blended with
    /// `weights`: `Σ_k (Σ_r w_r U[r, k]) · SxV[t, k]` per channel. Blending the U rows
    /// first (not the images) is what makes interpolation cost one decode.
    fn decode_rows(&self, rows: &[(usize, f32)]) -> Vec<f32> {
        use rayon::prelude::*;
        let t = self.texels();
        // The blended U row of every channel.
        let us: Vec<Vec<f32>> = self
            .channels
            .iter()
            .map(|f| {
                let c = f.c;
                let mut u = vec![0f32; c];
                for &(r, w) in rows {
                    for (a, b) in u.iter_mut().zip(&f.u[r * c..(r + 1) * c]) {
                        *a += w * b;
                    }
                }
                u
            })
            .collect();
        // Blocks of texels decode independently (each texel's value depends on its own
        // factor row only), so the bytes are the same at any thread count.
        const BLOCK: usize = 4096;
        let lab = LabDecoder::default();
        let mut out = vec![0f32; t * 3];
        out.par_chunks_mut(3 * BLOCK).enumerate().for_each(|(b, o)| {
            let t0 = b * BLOCK;
            let n = o.len() / 3;
            for (ch, (f, u)) in self.channels.iter().zip(&us).enumerate() {
                decode_channel(o, ch, u, &f.sxv[t0 * f.c..(t0 + n) * f.c]);
            }
            for px in o.chunks_exact_mut(3) {
                let rgb = if self.color_model == ColorModel::Lab {
                    lab.to_rgb([px[0], px[1], px[2]])
                } else {
                    decode_color(self.color_model, [px[0], px[1], px[2]])
                };
                px.copy_from_slice(&rgb);
            }
        });
        out
    }

    /// Linear RGB image (interleaved, top row first) of grid pair (`light`, `view`).
    pub fn reconstruct(&self, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        self.reconstruct_weighted(&[(light, view, 1.0)])
    }

    /// Image of a weighted blend of grid pairs, blended in the stored (model) domain.
    pub fn reconstruct_weighted(&self, weights: &[(usize, usize, f32)]) -> Result<Vec<f32>, CompressError> {
        let (nl, nv) = (self.n_lights(), self.n_views());
        let mut rows = Vec::with_capacity(weights.len());
        for &(l, v, w) in weights {
            if l >= nl || v >= nv {
                return Err(CompressError::Invalid(format!(
                    "pair (light {l}, view {v}) outside the {nl} × {nv} grid"
                )));
            }
            rows.push((v * nl + l, w));
        }
        Ok(self.decode_rows(&rows))
    }

    /// Bytes of the factors at `bytes_per_value`.
    pub fn factor_values(&self) -> usize {
        self.channels
            .iter()
            .map(|c| c.u.len() + c.sxv.len() + c.sigma.len())
            .sum()
    }
}

/// Three `texels × lights` channel matrices of one view, and its filled `(light, source)` pairs.
type ChannelMatrices = ([Mat<f64>; 3], Vec<(usize, usize)>);

/// The three channel matrices (`texels × lights`, f64) of one view in the colour model.
fn channel_matrices(
    ds: &DatasetViews,
    view: usize,
    model: ColorModel,
    m_inv: &[[f64; 3]; 3],
) -> Result<ChannelMatrices, CompressError> {
    let vm = ds.view_matrix(view)?;
    let (t, nl) = (vm.rows, ds.n_lights());
    let mut mats = [
        Mat::<f64>::zeros(t, nl),
        Mat::<f64>::zeros(t, nl),
        Mat::<f64>::zeros(t, nl),
    ];
    for l in 0..nl {
        for i in 0..t {
            let o = i * vm.cols + l * 3;
            let c = encode_color(model, m_inv, [vm.data[o], vm.data[o + 1], vm.data[o + 2]]);
            for ch in 0..3 {
                mats[ch][(i, l)] = c[ch];
            }
        }
    }
    Ok((mats, vm.filled))
}

/// Budget for keeping all channel matrices (f64) in memory between the passes.
pub const DFMF_CACHE_BYTES: usize = 1 << 30;

/// Streams the per-view channel matrices, keeping them when they fit the budget.
pub(crate) struct Stream<'a> {
    ds: &'a DatasetViews,
    model: ColorModel,
    m_inv: [[f64; 3]; 3],
    cached: Vec<Option<[Mat<f64>; 3]>>,
    keep: bool,
    /// Whether view `v` has been read (its filled pairs are then listed).
    seen: Vec<bool>,
    /// `[light, view]` of every filled pair, in the order the views were first read.
    pub(crate) filled: Vec<[usize; 2]>,
}

impl<'a> Stream<'a> {
    pub(crate) fn new(ds: &'a DatasetViews, model: ColorModel) -> Self {
        let (t, n) = (ds.texels(), ds.n_lights() * ds.n_views());
        Stream {
            ds,
            model,
            m_inv: rgb_to_yuv(),
            cached: vec![None; ds.n_views()],
            keep: t * n * 3 * 8 <= DFMF_CACHE_BYTES,
            seen: vec![false; ds.n_views()],
            filled: Vec::new(),
        }
    }

    /// Never keep a view: for a process that reads each view once (one shard's pass).
    pub(crate) fn without_cache(mut self) -> Self {
        self.keep = false;
        self
    }
}

impl ViewSource for Stream<'_> {
    fn with_view(&mut self, v: usize, f: &mut dyn FnMut(&[MatRef<'_, f64>])) -> Result<(), CompressError> {
        if let Some(m) = &self.cached[v] {
            f(&[m[0].as_ref(), m[1].as_ref(), m[2].as_ref()]);
            return Ok(());
        }
        let (m, filled) = channel_matrices(self.ds, v, self.model, &self.m_inv)?;
        if !self.seen[v] {
            self.seen[v] = true;
            self.filled.extend(filled.iter().map(|&(l, _)| [l, v]));
        }
        f(&[m[0].as_ref(), m[1].as_ref(), m[2].as_ref()]);
        if self.keep {
            self.cached[v] = Some(m);
        }
        Ok(())
    }
}

/// Factorize `ds` with DFMF.
pub fn encode(ds: &DatasetViews, params: &DfmfParams) -> Result<(Dfmf, EncodeInfo), CompressError> {
    encode_listing_filled(ds, params).map(|(d, i, _)| (d, i))
}

/// The randomized SVD of DFMF for `ds` (three channels of the colour model, each
/// `texels × lights` per view; channel `ch` sketched with seed `seed + ch`).
pub(crate) fn problem(ds: &DatasetViews, params: &DfmfParams) -> Result<Rsvd, CompressError> {
    if params.components.contains(&0) {
        return Err(CompressError::Invalid(format!(
            "DFMF components {:?}: every channel needs at least 1",
            params.components
        )));
    }
    let (t, nl, nv) = (ds.texels(), ds.n_lights(), ds.n_views());
    let n = nl * nv;
    Ok(Rsvd {
        channels: (0..3)
            .map(|ch| Channel {
                rows: t,
                k: (params.components[ch] + params.oversample).min(t).min(n),
                sketch: GaussianSketch::new(params.seed.wrapping_add(ch as u64), SketchKeying::Hashed),
            })
            .collect(),
        width: nl,
        views: nv,
        power_iters: params.power_iters,
    })
}

/// The factors of every channel from the last pass's `Q` and `B = Qᵀ A`.
pub(crate) fn channel_factors(
    params: &DfmfParams,
    q: &[Mat<f64>],
    b: &[Mat<f64>],
) -> Result<Vec<ChannelFactors>, CompressError> {
    let mut channels = Vec::with_capacity(3);
    for ch in 0..3 {
        let c = params.components[ch];
        // B = Qᵀ A ≈ U_B S Vᵀ: texel side S·V = Q U_B S, measurement side U = V.
        let (ubs, vv) = truncated_svd(b[ch].as_ref(), c)?;
        let sxv = &q[ch] * &ubs;
        let sigma = (0..c).map(|j| ubs.col(j).norm_l2() as f32).collect();
        channels.push(ChannelFactors {
            c,
            sigma,
            u: row_major_f32(vv.as_ref()),
            sxv: row_major_f32(sxv.as_ref()),
        });
    }
    Ok(channels)
}

/// [`encode`], also returning the `[light, view]` list of filled pairs.
fn encode_listing_filled(
    ds: &DatasetViews,
    params: &DfmfParams,
) -> Result<(Dfmf, EncodeInfo, Vec<[usize; 2]>), CompressError> {
    let rsvd = problem(ds, params)?;
    let mut s = Stream::new(ds, params.color_model);
    let (q, b) = rsvd.run_all(&mut s)?;
    let dfmf = Dfmf {
        color_model: params.color_model,
        width: ds.width,
        height: ds.height,
        lights_deg: ds.lights_deg.clone(),
        views_deg: ds.views_deg.clone(),
        channels: channel_factors(params, &q, &b)?,
    };
    let passes = if s.keep { 1 } else { rsvd.passes() };
    Ok((
        dfmf,
        EncodeInfo {
            filled: s.filled.len(),
            passes,
            ..Default::default()
        },
        s.filled,
    ))
}

/// The per-channel components of a `.gbtf` DFMF: luminance `params.components`, chroma
/// `chroma_components` (all three equal for RGB, which has no luminance channel).
pub fn channel_components(params: &Params) -> Result<(ColorModel, [usize; 3]), CompressError> {
    let Method::Dfmf {
        color_model,
        chroma_components,
    } = params.method
    else {
        return Err(CompressError::Invalid(format!("{} is not DFMF", params.method.name())));
    };
    let c = params.components;
    Ok(match color_model {
        ColorModel::Rgb => (color_model, [c; 3]),
        _ => (color_model, [c, chroma_components, chroma_components]),
    })
}

/// DFMF stored as `.gbtf` (`gonio compress --method dfmf --format gbtf`), the home of the
/// CIELab model and of quantized DFMF factors. Blocks, per channel `ch` of the model:
/// `u{ch}` (views·lights × c_ch, row `view · L + light`) and `sxv{ch}` (texels × c_ch).
pub fn compress_gbtf(ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
    let dp = gbtf_params(params)?;
    let (d, info, filled) = encode_listing_filled(ds, &dp)?;
    Ok((to_gbtf(header_for(ds, params, filled, Vec::new()), d), info))
}

/// The [`DfmfParams`] of a `.gbtf` DFMF compression with `params`.
pub(crate) fn gbtf_params(params: &Params) -> Result<DfmfParams, CompressError> {
    let (color_model, components) = channel_components(params)?;
    Ok(DfmfParams {
        color_model,
        components,
        seed: params.seed,
        oversample: params.oversample,
        power_iters: params.power_iters,
    })
}

/// `d` as the blocks of a `.gbtf` (see [`compress_gbtf`]) under `header` (its grid,
/// parameters and filled pairs; the block list is set here).
pub(crate) fn to_gbtf(mut header: GbtfHeader, d: Dfmf) -> Gbtf {
    let rows = d.n_lights() * d.n_views();
    let t = d.texels();
    let mut blocks = Vec::with_capacity(6);
    header.blocks.clear();
    for (ch, f) in d.channels.into_iter().enumerate() {
        header.blocks.push(BlockInfo::new(format!("u{ch}"), rows, f.c));
        blocks.push(f.u);
        header.blocks.push(BlockInfo::new(format!("sxv{ch}"), t, f.c));
        blocks.push(f.sxv);
    }
    Gbtf { header, blocks }
}

/// The [`Dfmf`] of a `.gbtf` written by [`compress_gbtf`] (blocks checked against the grid).
pub fn from_gbtf(g: &Gbtf) -> Result<Dfmf, CompressError> {
    let h = &g.header;
    let params: Params = serde_json::from_value(h.params.clone())
        .map_err(|e| CompressError::Invalid(format!(".gbtf dfmf: parameters in the header: {e}")))?;
    let (color_model, components) = channel_components(&params)?;
    let (rows, t) = (h.lights_deg.len() * h.views_deg.len(), h.width * h.height);
    let want: Vec<(usize, usize)> = components.iter().flat_map(|&c| [(rows, c), (t, c)]).collect();
    let got: Vec<(usize, usize)> = h.blocks.iter().map(|b| (b.rows, b.cols)).collect();
    if got != want || g.blocks.len() != 6 {
        return Err(CompressError::Invalid(format!(
            ".gbtf dfmf: block shapes {got:?}, the header's grid and components need {want:?}"
        )));
    }
    let channels = (0..3)
        .map(|ch| ChannelFactors {
            c: components[ch],
            sigma: Vec::new(),
            u: g.blocks[2 * ch].clone(),
            sxv: g.blocks[2 * ch + 1].clone(),
        })
        .collect();
    let d = Dfmf {
        color_model,
        width: h.width,
        height: h.height,
        lights_deg: h.lights_deg.clone(),
        views_deg: h.views_deg.clone(),
        channels,
    };
    d.validate()?;
    Ok(d)
}

/// DFMF stored as `.gbtf` in the registry (`super::registry`); its UBO2014 `.btf` is
/// [`super::btf_ubo2014`].
pub struct DfmfCodec;

impl Codec for DfmfCodec {
    fn id(&self) -> CodecId {
        CodecId::Dfmf
    }
    /// Perceptual DFMF: luminance c, chroma c / 4 (chroma varies less over directions).
    fn ladder(&self, knobs: &Knobs) -> Vec<Vec<Params>> {
        vec![[8, 16, 32, 64]
            .map(|c| {
                let method = Method::Dfmf {
                    color_model: ColorModel::Lab,
                    chroma_components: (c / 4).max(1),
                };
                knobs.params(method, c)
            })
            .to_vec()]
    }
    fn shard(&self, knobs: &Knobs) -> Shard {
        // Range sketch, projection and the power iterations.
        Shard::Passes(2 + knobs.power_iters)
    }
    fn encode(&self, ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
        compress_gbtf(ds, params)
    }
    fn open(&self, g: &Gbtf) -> Result<Opened, CompressError> {
        let d = from_gbtf(g)?;
        let params: Params = serde_json::from_value(g.header.params.clone())
            .map_err(|e| bad_file(g, format!("parameters in the header: {e}")))?;
        Ok(Opened {
            method: params.method,
            components: params.components,
            layout: Layout::ChannelFactors,
            decoder: Arc::new(Decoder(d)),
        })
    }
}

/// The factors as [`Dfmf`], which decodes them.
#[derive(Debug)]
struct Decoder(Dfmf);

impl Decode for Decoder {
    fn reconstruct(&self, _: &Gbtf, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        self.0.reconstruct(light, view)
    }
}

#[cfg(test)]
mod tests {
    use super::super::btf_ubo2014::{self, Precision};
    use super::*;
    use crate::compress::testdata::write_test_dataset;
    use std::path::Path;

    fn lights() -> Vec<[f64; 2]> {
        vec![[0.0, 0.0], [30.0, 0.0], [30.0, 120.0], [30.0, 240.0], [60.0, 90.0]]
    }
    fn views() -> Vec<[f64; 2]> {
        vec![[0.0, 0.0], [45.0, 0.0], [45.0, 180.0], [60.0, 270.0]]
    }
    /// Smooth, positive, colourful, values in (0.02, 0.9).
    fn smooth(l: usize, v: usize, t: usize, c: usize) -> f32 {
        let x = (t % 7) as f32 / 7.0;
        0.02 + 0.3 * (1.0 + ((l as f32 + 1.3 * v as f32) * 0.7 + x * 2.0 + c as f32).sin()) * (0.5 + 0.1 * c as f32)
    }

    /// The grouped decode gives the bytes a plain per-texel sum gives, also for the texels
    /// left over after the last full group (5 × 5 = 25 texels: 3 groups of 8 and 1).
    #[test]
    fn grouped_decode_equals_the_plain_sum_bit_for_bit() {
        let (nl, nv, t) = (3, 2, 25);
        let ch = |c: usize, seed: usize| ChannelFactors {
            c,
            sigma: vec![1.0; c],
            u: (0..nl * nv * c)
                .map(|i| (((i * 7 + seed) % 11) as f32 - 5.0) * 0.137)
                .collect(),
            sxv: (0..t * c)
                .map(|i| (((i * 5 + seed) % 13) as f32 - 6.0) * 0.0731)
                .collect(),
        };
        let d = Dfmf {
            color_model: ColorModel::Rgb,
            width: 5,
            height: 5,
            lights_deg: vec![[0.0, 0.0]; nl],
            views_deg: vec![[0.0, 0.0]; nv],
            channels: vec![ch(7, 1), ch(3, 2), ch(1, 3)],
        };
        let rows = [(4usize, 1f32)];
        let got = d.decode_rows(&rows);
        for (i, px) in got.chunks_exact(3).enumerate() {
            let mut m = [0f32; 3];
            for (k, f) in d.channels.iter().enumerate() {
                let mut s = 0f32;
                for j in 0..f.c {
                    s += f.u[4 * f.c + j] * f.sxv[i * f.c + j];
                }
                m[k] = s;
            }
            let want = decode_color(ColorModel::Rgb, m);
            assert_eq!(
                px.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                want.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "texel {i}"
            );
        }
    }

    #[test]
    #[allow(clippy::needless_range_loop)] // a matrix product reads best with indices
    fn rgb_to_yuv_inverts_the_readers_matrix() {
        let mi = rgb_to_yuv();
        for (i, row) in YUV_TO_RGB.iter().enumerate() {
            for j in 0..3 {
                let p: f64 = (0..3).map(|k| f64::from(row[k]) * mi[k][j]).sum();
                assert!((p - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12, "({i},{j}) = {p}");
            }
        }
        // Luminance row is BT.601's (0.299, 0.587, 0.114) to the matrix's precision.
        assert!((mi[0][0] - 0.299).abs() < 1e-3 && (mi[0][1] - 0.587).abs() < 1e-3);
    }

    #[test]
    fn log_yuv_colour_round_trip_and_its_limits() {
        let mi = rgb_to_yuv();
        for rgb in [
            [0.5f32, 0.25, 0.125],
            [0.9, 0.01, 0.3],
            [1e-3, 2e-3, 5e-4],
            [0.0, 0.0, 0.0],
        ] {
            let c = encode_color(ColorModel::LogYuv, &mi, rgb).map(|x| x as f32);
            let back = decode_color(ColorModel::LogYuv, c);
            // The reader adds ε to U and V after scaling by Y, so black decodes to
            // (1.14, 0, 2.03)·ε: a floor of 2e-5 (0.07 of an 8-bit sRGB code).
            for k in 0..3 {
                assert!((back[k] - rgb[k]).abs() < 2.5e-5, "{rgb:?} → {c:?} → {back:?}");
            }
        }
        // Negative noise is clamped to 0; the reader clamps to [0, 1].
        let c = encode_color(ColorModel::LogYuv, &mi, [-0.1, 0.0, 0.0]);
        assert!(c.iter().all(|x| x.is_finite()));
        let hi = decode_color(
            ColorModel::LogYuv,
            encode_color(ColorModel::LogYuv, &mi, [3.0, 2.0, 1.5]).map(|x| x as f32),
        );
        assert_eq!(hi, [1.0, 1.0, 1.0]);
    }

    #[test]
    fn full_rank_rgb_dfmf_reproduces_every_image_and_the_file_round_trips() {
        let dir = tempfile::tempdir().unwrap();
        let ds = write_test_dataset(dir.path(), (6, 5), &lights(), &views(), &[], smooth);
        // Rank ≤ 20 measurements: c = 20 is exact.
        let (d, info) = encode(&ds, &DfmfParams::new(ColorModel::Rgb, 20)).unwrap();
        assert_eq!((info.filled, info.passes), (0, 1));
        for v in 0..4 {
            for l in 0..5 {
                let img = ds.read_image(l, v).unwrap().unwrap();
                let rec = d.reconstruct(l, v).unwrap();
                let err = img.iter().zip(&rec).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
                assert!(err < 1e-5, "light {l} view {v}: {err}");
            }
        }
        let bytes = btf_ubo2014::to_bytes(&d, Precision::F32, "<x/>").unwrap();
        assert!(bytes.starts_with(b"!DFMF08FCR"));
        let back = btf_ubo2014::from_bytes(&bytes, Path::new("t.btf")).unwrap();
        // 5 lights, 4 views: one zero view of padding in the file, cut on reading.
        assert_eq!(back, d);
        let h = btf_ubo2014::to_bytes(&d, Precision::F16, "").unwrap();
        let back = btf_ubo2014::from_bytes(&h, Path::new("t.btf")).unwrap();
        for (a, b) in back.channels.iter().zip(&d.channels) {
            for (x, y) in a.sxv.iter().zip(&b.sxv).chain(a.u.iter().zip(&b.u)) {
                assert!((x - y).abs() <= 1e-3 * y.abs() + 1e-7, "{x} vs {y}");
            }
        }
    }

    #[test]
    fn log_yuv_dfmf_low_rank_is_close_and_deterministic() {
        let dir = tempfile::tempdir().unwrap();
        let ds = write_test_dataset(dir.path(), (6, 5), &lights(), &views(), &[(2, 1)], smooth);
        let p = DfmfParams::new(ColorModel::LogYuv, 6);
        let (a, info) = encode(&ds, &p).unwrap();
        let (b, _) = encode(&ds, &p).unwrap();
        assert_eq!(a, b, "same seed, same factors");
        assert_eq!(info.filled, 1);
        let ev = super::super::evaluate(&ds, &a).unwrap();
        assert_eq!(ev.images, 19);
        assert!(ev.stats.rmse_linear() < 0.02, "rmse {}", ev.stats.rmse_linear());
        assert!(ev.truth.is_none());
    }

    #[test]
    fn zero_and_constant_inputs_factorize() {
        let dir = tempfile::tempdir().unwrap();
        let ds = write_test_dataset(dir.path(), (4, 4), &lights(), &views(), &[], |_, _, _, _| 0.0);
        let (d, _) = encode(&ds, &DfmfParams::new(ColorModel::LogYuv, 3)).unwrap();
        let rec = d.reconstruct(1, 1).unwrap();
        assert!(rec.iter().all(|&x| (0.0..3e-5).contains(&x)), "{rec:?}");
        let dir2 = tempfile::tempdir().unwrap();
        let ds = write_test_dataset(dir2.path(), (4, 4), &lights(), &views(), &[], |_, _, _, c| {
            0.2 + 0.1 * c as f32
        });
        let (d, _) = encode(&ds, &DfmfParams::new(ColorModel::LogYuv, 1)).unwrap();
        let rec = d.reconstruct(3, 2).unwrap();
        for px in rec.chunks_exact(3) {
            for c in 0..3 {
                assert!((px[c] - (0.2 + 0.1 * c as f32)).abs() < 1e-4, "{px:?}");
            }
        }
        assert!(matches!(
            encode(&ds, &DfmfParams::new(ColorModel::Rgb, 0)),
            Err(CompressError::Invalid(_))
        ));
    }

    #[test]
    fn malformed_btf_files_are_errors_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let ds = write_test_dataset(dir.path(), (4, 3), &lights(), &views(), &[], smooth);
        let (d, _) = encode(&ds, &DfmfParams::new(ColorModel::Rgb, 2)).unwrap();
        let good = btf_ubo2014::to_bytes(&d, Precision::F16, "").unwrap();
        let p = Path::new("/data/x.btf");
        let corrupt = |b: &[u8]| match btf_ubo2014::from_bytes(b, p) {
            Err(CompressError::Corrupt { path, reason }) => {
                assert_eq!(path, p);
                reason
            }
            other => panic!("expected Corrupt, got {other:?}"),
        };
        assert!(corrupt(&good[..good.len() - 1]).contains("truncated"));
        let mut long = good.clone();
        long.push(0);
        assert!(corrupt(&long).contains("trailing"));
        assert!(corrupt(b"!FMF1....").contains("signature"));
        let mut bad_model = good.clone();
        // The colour model: after signature, common header (264 + cosine 4 + XML length 4 +
        // channel count 4 + names "R", "G", "B" 3 × 5), directions, size, rotations, components.
        let (nl, nv) = (5, 4);
        let at = 10 + 291 + 4 + nv * (8 + 4 + nl * 8) + 8 + 4 + 4;
        assert_eq!(&good[at..at + 4], &0u32.to_le_bytes());
        bad_model[at] = 7;
        assert!(corrupt(&bad_model).contains("colour model 7"));
        // More views than lights cannot be written.
        let mut wide = d.clone();
        wide.views_deg = (0..6).map(|i| [40.0, 60.0 * i as f64]).collect();
        for ch in &mut wide.channels {
            ch.u = vec![0.0; 6 * 5 * ch.c];
        }
        assert!(matches!(
            btf_ubo2014::to_bytes(&wide, Precision::F32, ""),
            Err(CompressError::Invalid(m)) if m.contains("views")
        ));
        // Values beyond half range are refused in f16, fine in f32.
        let mut big = d.clone();
        big.channels[0].sxv[0] = 1e6;
        assert!(btf_ubo2014::to_bytes(&big, Precision::F16, "").is_err());
        assert!(btf_ubo2014::to_bytes(&big, Precision::F32, "").is_ok());
    }
}
