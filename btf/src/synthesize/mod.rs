//! BTF synthesis (thesis ch. 6): grow a measured sample to any size.
//!
//! A BTF is treated as a texture whose "pixels" are whole ABRDFs (thesis §6.3). Every
//! method here produces a **texel map**: for each output texel, the exemplar texel whose
//! complete ABRDF it takes. Structure is therefore consistent across all (light, view)
//! pairs by construction, and the output is stored as a model of the exemplar's own kind
//! whose per-texel rows are gathered through the map ([`output`]).
//!
//! Matching does not compare 19 683-value ABRDFs: [`features`] embeds every texel's ABRDF
//! isometrically (Euclidean distances between embedded texels are the L2 distances
//! between their reconstructed ABRDFs) and keeps the first `k` principal components
//! (by explained energy, or a fixed `k`). For a median-cut model the embedding of a texel
//! is that of its box's centroid, so matching runs on the index image's reflectances.
//!
//! Methods, one file each:
//! * [`tile`]: the exemplar repeated (the ceiling every other method must beat).
//! * [`efros_leung`]: pixel-wise non-parametric MRF sampling (Efros & Leung 1999) with
//!   the ε = 0.1 acceptance of thesis eq. 78.
//! * [`wei_levoy`]: raster-order synthesis over a Gaussian pyramid, best matches found
//!   with tree-structured vector quantization ([`tsvq`]) (Wei & Levoy 2000).
//! * [`quilting`]: image quilting with overlap, best-block search within a tolerance and
//!   the minimum-error boundary cut of thesis eq. 79 (Efros & Freeman 2001).
//!
//! Every random choice comes from a [`SplitMix64`] stream of the seed and every
//! parallel reduction has a fixed order, so a seed gives the same bytes at any thread
//! count.

pub mod efros_leung;
pub mod exemplar;
pub mod features;
mod fft;
pub mod output;
pub mod quality;
pub mod quilting;
pub mod tile;
pub mod tsvq;
pub mod wei_levoy;

use crate::compress::CompressError;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Errors of synthesis.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    /// A parameter or input that cannot be synthesized from; the message says why and how
    /// to fix it.
    #[error("{0}")]
    Invalid(String),
    #[error(transparent)]
    Compress(#[from] CompressError),
    #[error("{path}: {reason}")]
    File { path: PathBuf, reason: String },
}

/// Synthesis method.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum SynthMethod {
    Tile,
    EfrosLeung,
    WeiLevoy,
    Quilting,
}

impl SynthMethod {
    pub const ALL: [SynthMethod; 4] = [
        SynthMethod::Tile,
        SynthMethod::EfrosLeung,
        SynthMethod::WeiLevoy,
        SynthMethod::Quilting,
    ];
    pub fn name(self) -> &'static str {
        match self {
            SynthMethod::Tile => "tile",
            SynthMethod::EfrosLeung => "efros-leung",
            SynthMethod::WeiLevoy => "wei-levoy",
            SynthMethod::Quilting => "quilting",
        }
    }
    pub fn parse(s: &str) -> Result<Self, SynthError> {
        Self::ALL.into_iter().find(|m| m.name() == s).ok_or_else(|| {
            SynthError::Invalid(format!(
                "unknown synthesis method {s:?}: use tile, efros-leung, wei-levoy or quilting"
            ))
        })
    }
}

/// Parameters of [`synthesize`]. Sizes are in texels.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct SynthParams {
    pub method: SynthMethod,
    pub width: usize,
    pub height: usize,
    pub seed: u64,
    /// Quilting: block edge.
    pub block: usize,
    /// Quilting: overlap between neighbouring blocks.
    pub overlap: usize,
    /// Quilting: blocks whose overlap error is within `(1 + tolerance)` of the best are
    /// candidates (Efros & Freeman use 0.1).
    pub tolerance: f64,
    /// Efros–Leung: window edge (odd).
    pub window: usize,
    /// Efros–Leung: acceptance ε of eq. 78.
    pub epsilon: f64,
    /// Wei–Levoy: pyramid levels (1 = single resolution).
    pub levels: usize,
    /// Wei–Levoy: neighbourhood edge at the current level (odd; its causal half is used).
    pub neighbourhood: usize,
    /// Wei–Levoy: neighbourhood edge at the next coarser level (odd, full square).
    pub parent_neighbourhood: usize,
    /// Wei–Levoy: TSVQ leaf size (vectors searched exhaustively at a leaf).
    pub leaf: usize,
    /// Wei–Levoy: coherence κ (Ashikhmin 2001 candidates weighed as in Hertzmann et al.
    /// 2001): the exemplar texel that continues a neighbour's source is kept when its
    /// neighbourhood distance is within `1 + κ·2⁻ˡ` of the TSVQ match's (level `l`, 0 =
    /// finest). 0 = the TSVQ match alone, as in the paper. Files written before the knob
    /// existed read as 0, which is what they were made with.
    #[serde(default)]
    pub coherence: f64,
}

impl SynthParams {
    /// The default quilting overlap for a block edge: a quarter of the block. Efros &
    /// Freeman's sixth leaves the boundary cut too little room on ABRDF features: on the
    /// quality bench (docs/guide/synthesis.md) block 32 with overlap 5 gave seam ratios of
    /// 1.13–1.21 over three seeds, overlap 8 gave 1.07–1.08.
    pub fn default_overlap(block: usize) -> usize {
        (block / 4).max(1)
    }

    /// Defaults for an exemplar of `ex_w × ex_h` texels.
    pub fn new(method: SynthMethod, width: usize, height: usize, ex_w: usize, ex_h: usize) -> Self {
        let m = ex_w.min(ex_h);
        let block = (m / 4).clamp(4, 64).min(m);
        let mut levels = 1;
        while levels < 5 && m >> levels >= 32 {
            levels += 1;
        }
        SynthParams {
            method,
            width,
            height,
            seed: 1,
            block,
            overlap: Self::default_overlap(block),
            tolerance: 0.1,
            window: 7,
            epsilon: 0.1,
            levels,
            neighbourhood: 7,
            parent_neighbourhood: 5,
            leaf: 8,
            coherence: 1.0,
        }
    }
}

/// A `width × height` image of `dims`-dimensional feature vectors (row-major, row 0 first).
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureImage {
    pub width: usize,
    pub height: usize,
    pub dims: usize,
    pub data: Vec<f32>,
}

impl FeatureImage {
    #[inline]
    pub fn px(&self, x: usize, y: usize) -> &[f32] {
        let o = (y * self.width + x) * self.dims;
        &self.data[o..o + self.dims]
    }
    #[inline]
    pub fn texel(&self, t: usize) -> &[f32] {
        &self.data[t * self.dims..(t + 1) * self.dims]
    }
}

/// For each output texel (row-major), the exemplar texel (`sy · src_width + sx`) it takes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TexelMap {
    pub width: usize,
    pub height: usize,
    pub src_width: usize,
    pub src_height: usize,
    pub src: Vec<u32>,
}

impl TexelMap {
    #[inline]
    pub fn source_xy(&self, t: usize) -> (usize, usize) {
        let s = self.src[t] as usize;
        (s % self.src_width, s / self.src_width)
    }
}

/// Deterministic pseudo-random numbers (splitmix64): small, seedable, and identical on
/// every platform.
#[derive(Clone, Debug)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        SplitMix64(seed ^ 0x5851_f42d_4c95_7f2d)
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    /// Uniform in `0..n` (`n > 0`).
    pub fn below(&mut self, n: usize) -> usize {
        ((self.next_u64() as u128 * n as u128) >> 64) as usize
    }
    /// Uniform in `[0, 1)`.
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Checks shared by every method: an output at least as large as the exemplar (a smaller
/// one is a crop, not a synthesis), a non-empty exemplar and finite features.
fn check_common(ex: &FeatureImage, p: &SynthParams) -> Result<(), SynthError> {
    if ex.width == 0 || ex.height == 0 || ex.dims == 0 {
        return Err(SynthError::Invalid(format!(
            "the exemplar is {}×{} texels with {} feature dimensions: nothing to synthesize from",
            ex.width, ex.height, ex.dims
        )));
    }
    if p.width < ex.width || p.height < ex.height {
        return Err(SynthError::Invalid(format!(
            "--size {}x{} is smaller than the exemplar ({}×{}): synthesis grows a sample; \
             ask for at least {}x{} (to make it smaller, crop instead)",
            p.width, p.height, ex.width, ex.height, ex.width, ex.height
        )));
    }
    if p.width > 65535 || p.height > 65535 || ex.width > 65535 || ex.height > 65535 {
        return Err(SynthError::Invalid(format!(
            "--size {}x{}: at most 65535 texels per side (the texel map stores 16-bit coordinates)",
            p.width, p.height
        )));
    }
    if let Some(i) = ex.data.iter().position(|v| !v.is_finite()) {
        return Err(SynthError::Invalid(format!(
            "exemplar feature {} of texel {} is {}: the model decodes to non-finite values",
            i % ex.dims,
            i / ex.dims,
            ex.data[i]
        )));
    }
    Ok(())
}

/// Synthesize a `p.width × p.height` texel map from the exemplar's feature image.
pub fn synthesize(ex: &FeatureImage, p: &SynthParams) -> Result<TexelMap, SynthError> {
    check_common(ex, p)?;
    match p.method {
        SynthMethod::Tile => Ok(tile::synthesize(ex, p)),
        SynthMethod::Quilting => quilting::synthesize(ex, p),
        SynthMethod::EfrosLeung => efros_leung::synthesize(ex, p),
        SynthMethod::WeiLevoy => wei_levoy::synthesize(ex, p),
    }
}

#[cfg(test)]
pub(crate) mod testutil {
    use super::FeatureImage;
    use crate::compress::DatasetViews;
    use std::path::Path;

    pub const LIGHTS: [[f64; 2]; 5] = [[0.0, 0.0], [30.0, 0.0], [30.0, 120.0], [30.0, 240.0], [70.0, 90.0]];
    pub const VIEWS: [[f64; 2]; 4] = [[0.0, 0.0], [45.0, 0.0], [45.0, 180.0], [75.0, 270.0]];

    /// Write a `w × h` dataset on the [`LIGHTS`] × [`VIEWS`] grid whose image
    /// (light, view) is `f(light, view, x, y, channel)`, and open it.
    pub fn write_dataset(
        dir: &Path,
        w: usize,
        h: usize,
        f: impl Fn(usize, usize, usize, usize, usize) -> f32,
    ) -> DatasetViews {
        crate::compress::testdata::write_test_dataset(dir, (w, h), &LIGHTS, &VIEWS, &[], |l, v, t, c| {
            f(l, v, t % w, t / w, c)
        })
    }

    /// A textured test BTF: two materials in blobs, shading that depends on the pair.
    pub fn textured(l: usize, v: usize, x: usize, y: usize, c: usize) -> f32 {
        let blob = ((x as f32 * 0.9).sin() * (y as f32 * 0.7).cos() + 0.3 * ((x * 7 + y * 13) % 5) as f32) > 0.4;
        let base = if blob { [0.7, 0.5, 0.2] } else { [0.2, 0.3, 0.6] };
        let shade = 1.0 - 0.1 * l as f32 + 0.05 * v as f32 * if blob { 2.0 } else { -1.0 };
        base[c] * shade + 0.01 * ((x + 3 * y + l + c) % 7) as f32
    }

    /// A smooth, non-periodic 2-channel test texture with blobs.
    pub fn blobs(w: usize, h: usize, seed: u64) -> FeatureImage {
        let mut rng = super::SplitMix64::new(seed);
        let centres: Vec<(f64, f64, f64)> = (0..(w * h / 64).max(3))
            .map(|_| (rng.unit() * w as f64, rng.unit() * h as f64, 1.5 + 2.5 * rng.unit()))
            .collect();
        let mut data = Vec::with_capacity(w * h * 2);
        for y in 0..h {
            for x in 0..w {
                let mut a = 0.0;
                for &(cx, cy, r) in &centres {
                    let d2 = (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2);
                    a += (-d2 / (r * r)).exp();
                }
                data.push(a as f32);
                data.push((0.3 * (x as f64 * 0.7).sin() * (y as f64 * 0.4).cos()) as f32);
            }
        }
        FeatureImage {
            width: w,
            height: h,
            dims: 2,
            data,
        }
    }

    pub fn uniform(w: usize, h: usize) -> FeatureImage {
        FeatureImage {
            width: w,
            height: h,
            dims: 3,
            data: vec![0.25; w * h * 3],
        }
    }

    pub fn single_bright(w: usize, h: usize) -> FeatureImage {
        let mut f = uniform(w, h);
        let t = (h / 2) * w + w / 3;
        f.data[t * 3] = 1000.0;
        f
    }
}
