//! BTF compression: full-matrix PCA and per-view matrix factorization (PVMF).
//!
//! * [`data`] streams a native dataset view by view: one `texels × (lights · 3)` linear
//!   f32 matrix per view; unmeasured (skipped) pairs are filled with the nearest measured
//!   light of the same view and listed in the output's header.
//! * [`factor`] holds the methods. **PVMF** (Sattler 2003): per view, the best rank-`c`
//!   approximation of the view matrix in the Frobenius norm (no mean is subtracted),
//!   computed from the eigen-decomposition of the f64 Gram matrix `AᵀA` (243 × 243) and
//!   `U·S = A·V` ([`factor::gram_truncated`]), or by a thin SVD (QR + SVD of R, f64) when
//!   the Gram matrix is too ill-conditioned for `c` ([`factor::GRAM_MIN_EIGEN_RATIO`]:
//!   rank-deficient or constant views). A reader thread decodes view `k + 1` while view
//!   `k` is factorized. Measured on the full 81 × 81 × 256² dataset: 44 s instead of
//!   140 s (machine load 3–4 on 2 cores), reading fully hidden behind the factorization.
//!   **PCA**: one rank-`c` factorization of the whole `texels × (measurements · 3)`
//!   matrix by a randomized SVD (Halko, Martinsson, Tropp 2011) that streams the views:
//!   the full matrix (5 GiB as f32 at 256²) never has to be held. Passes: 1 (range
//!   sketch `A·Ω`, Ω Gaussian from a splitmix64 stream of `seed`) + `power_iters`
//!   (`A·Aᵀ·Q`) + 1 (projection `Qᵀ·A`), then the SVD of the small `(c + oversample) × n`
//!   projection. View matrices are kept in memory (f64) when they all fit 1 GiB, so small
//!   datasets are read once; otherwise every pass re-reads the images. Randomized rather
//!   than exact because an exact SVD needs the whole matrix in memory; with the default 2
//!   power iterations the rank-`c` error is close to the exact one on BTF spectra.
//! * Tall view matrices (texels > 2 · columns) are factorized as Householder QR followed
//!   by the SVD of the small R factor (`factor::truncated_svd`).
//! * [`container`] is the `.gbtf` file: magic, version, JSON header, CRC-checked f32 LE
//!   factor blocks.
//! * [`metrics`] compares reconstructions with the measured images (and, for datasets
//!   acquired with `--store-truth`, with the simulator's ground truth).
//! * [`dfmf`] is DFMF (Bonn's UBO2014 method: per-channel full-matrix factorization in a
//!   log-luminance/chroma colour model) and [`btf_ubo2014`] its `.btf` container, which the
//!   public `btf-extractor` reader loads (`tests/interop/check_ubo2014.py`).
//! * [`interp`] reconstructs any (light, view) direction pair from any model
//!   ([`interp::BtfModel`]) by barycentric interpolation on the direction grid.
//!
//! Stored factors are **f32** (little-endian): for PVMF per view `U·S` (texels × c) and
//! `V` (lights·3 × c); for PCA one `U·S` (texels × c) and one `V` (views·lights·3 × c),
//! row `(view · L + light) · 3 + channel`. Every SVD (PVMF's and PCA's final one, and the
//! QRs) runs in **f64**: `tests::f32_versus_f64_svd_accuracy` measured that an f32 SVD
//! matches the optimal truncation error while the dropped singular values are above
//! ~1e-4 of σ₁ (1.00× at rank 4 and 12, 1.10× at σ ≈ 3e-4) but is stuck at a ~2.5e-4
//! floor below that (98× and 934× the optimum at σ ≈ 3e-6 and 3e-7), whereas f64 stays
//! at the optimum. On real 64² Bonn view matrices of the default sample
//! (`tests::f32_versus_f64_on_a_dataset`, views 0, 40, 80) the f32 SVD's rank-c error
//! was 1.00002–1.0036× the f64 one for c ≤ 9, 1.002–1.055× at c = 15 and 1.05–1.29× at
//! c = 30. Images are half float, so inputs carry ~5e-4 relative noise anyway;
//! f64 costs 2× memory per view matrix (127 MiB at 256²), which the budget allows.
//!
//! Filled (unmeasured) pairs are factorized with the rest so that every grid pair can
//! be reconstructed, but they are excluded from the error statistics.
//!
//! Methods on whole ABRDFs (one per texel, all measurements × 3) read the dataset once
//! into a [`local_pca::Abrdfs`] matrix (f32 up to 1 GiB, else 8-bit sRGB codes with a
//! per-column scale): [`local_pca`] (PCMF, Müller et al. 2003), [`median_cut`] (thesis
//! ch. 8: index image + BRDF block, and `gonio generate`), [`homomorphic`] (McCool et
//! al. 2001, per-ABRDF product of light, view and half-vector factors).

pub mod btf_ubo2014;
pub mod container;
pub mod data;
pub mod dfmf;
pub mod factor;
pub mod homomorphic;
pub mod interp;
pub mod local_pca;
pub mod median_cut;
pub mod metrics;

#[cfg(test)]
mod tests;

pub use container::{BlockInfo, Gbtf, GbtfHeader};
pub use data::{DatasetViews, ViewMatrix};
pub use factor::{compress, compress_pvmf_shard, find_direction, CompressedBtf, EncodeInfo, Method, Params, Stage};
pub use metrics::{evaluate, peak_memory_bytes, ErrorStats, Evaluation};

use crate::store::StoreError;
use std::path::PathBuf;

/// Errors of the compression pipeline.
#[derive(Debug, thiserror::Error)]
pub enum CompressError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("dataset {dir}: {reason}")]
    Dataset { dir: PathBuf, reason: String },
    #[error(
        "{path}: measurement {index} (light {light_deg:?}°, view {view_deg:?}°) has a non-finite value {value} \
         at texel {texel}"
    )]
    NonFinite {
        path: PathBuf,
        index: usize,
        light_deg: [f64; 2],
        view_deg: [f64; 2],
        texel: usize,
        value: f32,
    },
    #[error("{path}: corrupt .gbtf file: {reason}")]
    Corrupt { path: PathBuf, reason: String },
    #[error("invalid input: {0}")]
    Invalid(String),
    #[error("SVD failed: {0}")]
    Svd(String),
    /// An exact lookup (`CompressedBtf::reconstruct_deg`) of a direction that is not on the
    /// grid; [`interp::reconstruct_at`] interpolates instead.
    #[error("{which} direction {deg:?}° is not one of the measured directions (use interpolation)")]
    NotMeasured { which: &'static str, deg: [f64; 2] },
    /// Interpolation refuses to extrapolate far from every measurement.
    #[error(
        "{which} direction {deg:?}° is {gap_deg:.1}° from the nearest measured direction; \
         interpolation uses measurements within {limit_deg}°"
    )]
    TooFar {
        which: &'static str,
        deg: [f64; 2],
        gap_deg: f64,
        limit_deg: f64,
    },
}
