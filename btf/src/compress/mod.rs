//! BTF compression: ten methods, gonio's `.gbtf` container, Bonn's UBO2014 `.btf`, and
//! reconstruction at any direction pair.
//!
//! | method | file | stored as | what is stored |
//! |---|---|---|---|
//! | PCA | [`pca`] | `.gbtf` | one texel basis and one measurement basis for the whole BTF |
//! | PVMF | [`pvmf`] | `.gbtf` | per view, a texel basis and a light basis |
//! | local PCA (PCMF) | [`local_pca`] | `.gbtf` | per texel a cluster index and coefficients; per cluster a mean and eigen-ABRDFs |
//! | median cut | [`median_cut`] | `.gbtf` | index image + BRDF block |
//! | homomorphic | [`homomorphic`] | `.gbtf` | per texel light × view × half-vector factor tables |
//! | ND | [`nd`] | `.gbtf` | per texel and channel, light row norms and view column means (one product) |
//! | SVD-J | [`svd_j`] | `.gbtf` | per texel and channel, a rank-J SVD of the lights × views matrix |
//! | GSHD, CMF | [`cmf`] | `.gbtf` | per texel and channel, half-vector × difference-vector factors (GSHD), times a rank-K SVD of the residual (CMF) |
//! | SVBRDF | [`svbrdf`] | `.gbtf` | per texel a scaled Lafortune model's parameters, per pair a gain plane (written by `gonio fit --per-texel`) |
//! | DFMF | [`dfmf`] | `.btf` ([`btf_ubo2014`]) or `.gbtf` | per colour channel of a decorrelated model (RGB, log-YUV, CIELab: `.gbtf` only), one full-matrix factorization |
//!
//! **Floors.** The method files share a ground floor and never import each other:
//! [`params`] (what a method is and reports, the [`Codec`] trait every method file
//! implements, the [`Layout`] fact readers match on, the common header), [`linalg`]
//! (truncated SVD, Gram path, the one Gaussian sketch generator), [`abrdf`] (the ABRDF
//! matrix of the per-texel methods and their shared encode frame), [`data`] (reading a
//! dataset view by view), [`container`] and [`error`]. [`registry`] is the one list of
//! methods ([`codec`]: [`CodecId`] → its method file's [`Codec`]); [`factor`] ([`compress`],
//! [`CompressedBtf`]), [`target`] and everything above `compress/` reach a method through
//! it. A new method is one file plus its line in [`registry::codec`] (and its variants of
//! [`Method`] and [`CodecId`], which the compiler asks for).
//!
//! * [`data`] streams a native dataset view by view: one `texels × (lights · 3)` linear
//!   f32 matrix per view; unmeasured (skipped) pairs are filled with the nearest measured
//!   light of the same view and listed in the output's header.
//! * **PVMF** (Sattler 2003, [`pvmf`]): per view, the best rank-`c` approximation of the
//!   view matrix in the Frobenius norm (no mean is subtracted), computed from the
//!   eigen-decomposition of the f64 Gram matrix `AᵀA` (243 × 243) and `U·S = A·V`
//!   ([`linalg::gram_truncated`]), or by a thin SVD (QR + SVD of R, f64) when the Gram
//!   matrix is too ill-conditioned for `c` ([`linalg::GRAM_MIN_EIGEN_RATIO`]:
//!   rank-deficient or constant views). A reader thread decodes view `k + 1` while view
//!   `k` is factorized. Measured on the full 81 × 81 × 256² dataset: 44 s instead of
//!   140 s (machine load 3–4 on 2 cores), reading fully hidden behind the factorization.
//! * **PCA** ([`pca`]): one rank-`c` factorization of the whole
//!   `texels × (measurements · 3)` matrix by a randomized SVD (Halko, Martinsson, Tropp
//!   2011) that streams the views: the full matrix (5 GiB as f32 at 256²) never has to be
//!   held. Passes: 1 (range sketch `A·Ω`, Ω Gaussian from [`linalg::GaussianSketch`]) +
//!   `power_iters` (`A·Aᵀ·Q`) + 1 (projection `Qᵀ·A`), then the SVD of the small
//!   `(c + oversample) × n` projection. View matrices are kept in memory (f64) when they
//!   all fit 1 GiB, so small datasets are read once; otherwise every pass re-reads the
//!   images. Randomized rather than exact because an exact SVD needs the whole matrix in
//!   memory; with the default 2 power iterations the rank-`c` error is close to the exact
//!   one on BTF spectra.
//! * Tall view matrices (texels > 2 · columns) are factorized as Householder QR followed
//!   by the SVD of the small R factor ([`linalg::truncated_svd`]).
//! * Methods on whole ABRDFs (one per texel, all measurements × 3) read the dataset once
//!   into an [`abrdf::Abrdfs`] matrix (f32 up to 1 GiB, else 8-bit sRGB codes with a
//!   per-column scale): [`local_pca`] (PCMF, Müller et al. 2003), [`median_cut`] (thesis
//!   ch. 8: index image + BRDF block, and `gonio generate`), [`homomorphic`] (McCool et
//!   al. 2001, per-ABRDF product of light, view and half-vector factors).
//! * [`dfmf`] is DFMF (Bonn's UBO2014 method: per-channel full-matrix factorization in a
//!   log-luminance/chroma colour model) and [`btf_ubo2014`] its `.btf` container, which the
//!   public `btf-extractor` reader loads (`tests/interop/check_ubo2014.py`).
//! * [`container`] is the `.gbtf` file: magic, version, JSON header, CRC-checked f32 LE
//!   factor blocks.
//! * [`metrics`] compares reconstructions with the measured images (and, for datasets
//!   acquired with `--store-truth`, with the simulator's ground truth).
//! * [`interp`] reconstructs any (light, view) direction pair from any model
//!   ([`interp::BtfModel`]) by barycentric interpolation on the direction grid.
//!
//! **Stored factors** are **f32** (little-endian) in `.gbtf` files; each method's file
//! documents its blocks: PVMF per view `U·S` (texels × c) and `V` (lights·3 × c); PCA one
//! `U·S` (texels × c) and one `V` (views·lights·3 × c), row `(view · L + light) · 3 +
//! channel`; local PCA the cluster index, coefficients, means and eigen-ABRDFs; median
//! cut the index image and the BRDF block; homomorphic the per-texel albedo and factor
//! tables. Index blocks hold exact small integers. DFMF's `.btf` stores f16 (Bonn's
//! files) or f32. Every SVD (PVMF's, PCA's, DFMF's and local PCA's final one, and the
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

pub mod abrdf;
pub mod btf_ubo2014;
pub mod cmf;
pub mod codec;
pub mod container;
pub mod data;
pub mod dfmf;
pub mod error;
pub mod exact;
pub mod factor;
pub mod gltf;
pub mod homomorphic;
pub mod interp;
pub mod linalg;
pub mod local_pca;
pub mod median_cut;
pub mod metrics;
pub mod nd;
pub mod params;
pub mod pca;
pub mod pvmf;
pub mod registry;
pub mod rsvd;
pub mod rsvd_shard;
pub mod svbrdf;
pub mod svd_j;
pub mod target;

/// Small synthetic datasets for tests: this crate's, and (feature `testdata`) those of the
/// crates above it; never in a normal build.
#[cfg(any(test, feature = "testdata"))]
pub mod testdata;
#[cfg(test)]
mod tests;

pub use container::{BlockInfo, Gbtf, GbtfHeader};
pub use data::{DatasetViews, ViewMatrix};
pub use error::CompressError;
pub use factor::{compress, compress_pvmf_shard, find_direction, CompressedBtf};
pub use metrics::{evaluate, peak_memory_bytes, ErrorStats, Evaluation};
pub use params::{Codec, CodecId, EncodeInfo, Knobs, Layout, Method, Params, Shard, Stage};
pub use registry::codec;
