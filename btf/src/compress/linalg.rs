//! The ground floor of linear algebra every factorization shares: the truncated SVD (QR
//! first for tall matrices), PVMF's Gram path, orthonormalization, f64 → f32 packing, and
//! the one deterministic Gaussian sketch generator ([`GaussianSketch`]) of the randomized
//! SVDs (PCA, DFMF, local PCA). Everything runs in f64 (see the module docs of [`super`]
//! for f32 versus f64).

use super::error::CompressError;
use faer::{Mat, MatRef};
use rayon::prelude::*;

/// Pack an f64 matrix row-major as f32 (the stored factor type).
pub fn row_major_f32(m: MatRef<'_, f64>) -> Vec<f32> {
    let mut out = Vec::with_capacity(m.nrows() * m.ncols());
    for i in 0..m.nrows() {
        for j in 0..m.ncols() {
            out.push(m[(i, j)] as f32);
        }
    }
    out
}

/// splitmix64 (Steele, Lea, Flood 2014): advance `state` by the golden-ratio increment and
/// return the mixed word. The deterministic generator of seeding and sketches.
pub fn splitmix(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The splitmix64 output for state `x` (one step from `x`, without keeping the state).
fn mix(x: u64) -> u64 {
    let mut s = x;
    splitmix(&mut s)
}

/// How a [`GaussianSketch`] turns (seed, row, col) into the two 64-bit words of one
/// Box–Muller draw.
///
/// Two keyings exist because the methods were written with two, and changing either would
/// change the files they write (same inputs must keep giving the same bytes). Both are
/// splitmix64 words; they differ only in how the position enters the state.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SketchKeying {
    /// PCA and DFMF: `k = mix(seed ⊕ mix(row ≪ 20 ⊕ col))`, words `k` and `mix(k)`.
    Hashed,
    /// Local PCA: state `seed ⊕ (row ≪ 24) ⊕ col · 0x2545f4914f6cdd1d`, words the next two
    /// splitmix64 outputs of that state.
    Stream,
}

/// A deterministic standard-normal test matrix Ω of the randomized SVDs (Halko,
/// Martinsson, Tropp 2011): entry (row, col) depends only on the seed and the position,
/// so Ω can be generated block by block while streaming the views, on any thread, with
/// the same values.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GaussianSketch {
    pub seed: u64,
    pub keying: SketchKeying,
}

impl GaussianSketch {
    pub fn new(seed: u64, keying: SketchKeying) -> Self {
        GaussianSketch { seed, keying }
    }

    /// Standard normal number at (row, col): Box–Muller on two splitmix64 words.
    pub fn at(&self, row: usize, col: usize) -> f64 {
        let (a, b) = match self.keying {
            SketchKeying::Hashed => {
                let k = mix(self.seed ^ mix(((row as u64) << 20) ^ col as u64));
                (k, mix(k))
            }
            SketchKeying::Stream => {
                let mut s = self.seed ^ ((row as u64) << 24) ^ (col as u64).wrapping_mul(0x2545_f491_4f6c_dd1d);
                (splitmix(&mut s), splitmix(&mut s))
            }
        };
        let u1 = ((a >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
        let u2 = (b >> 11) as f64 / (1u64 << 53) as f64;
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    /// The `rows × cols` block of Ω whose first row is row `row0` of the whole sketch.
    pub fn block(&self, row0: usize, rows: usize, cols: usize) -> Mat<f64> {
        Mat::from_fn(rows, cols, |i, j| self.at(row0 + i, j))
    }
}

/// Rank-`c` truncated SVD `A ≈ (U·S) · Vᵀ` in f64. Returns `U·S` (m × c) and `V` (n × c);
/// when `c` exceeds `min(m, n)` the extra columns are zero.
pub fn truncated_svd(a: MatRef<'_, f64>, c: usize) -> Result<(Mat<f64>, Mat<f64>), CompressError> {
    let (m, n) = (a.nrows(), a.ncols());
    let k = c.min(m).min(n);
    if m > 2 * n {
        // Tall (texels ≫ lights · 3): Householder QR first, then the SVD of the small
        // n × n factor R = U_R S Vᵀ, so A = (Q U_R) S Vᵀ. Backward stable like the direct
        // SVD, and several times faster on 4096 × 243 view matrices.
        let qr = a.qr();
        let r = qr.thin_R();
        let svd = r.svd().map_err(|e| CompressError::Svd(format!("{e:?}")))?;
        let (ur, s, v) = (svd.U(), svd.S().column_vector(), svd.V());
        let q = qr.compute_thin_Q();
        let urs = Mat::from_fn(n, c, |i, j| if j < k { ur[(i, j)] * s[j] } else { 0.0 });
        let vv = Mat::from_fn(n, c, |i, j| if j < k { v[(i, j)] } else { 0.0 });
        return Ok((&q * &urs, vv));
    }
    let svd = a.thin_svd().map_err(|e| CompressError::Svd(format!("{e:?}")))?;
    let (u, s, v) = (svd.U(), svd.S().column_vector(), svd.V());
    let us = Mat::from_fn(m, c, |i, j| if j < k { u[(i, j)] * s[j] } else { 0.0 });
    let vv = Mat::from_fn(n, c, |i, j| if j < k { v[(i, j)] } else { 0.0 });
    Ok((us, vv))
}

/// `(U·S, V)` of a rank-`c` factorization.
pub type Factors = (Mat<f64>, Mat<f64>);

/// Smallest `λ_c / λ_1` (eigenvalues of `AᵀA`, i.e. `(σ_c / σ_1)²`) for which PVMF trusts
/// the Gram path; below it the view is factorized by [`truncated_svd`].
///
/// Why: forming `G = AᵀA` squares the condition number. In f64 the eigenvalues of `G`
/// carry an absolute error of about `n · ε · λ_1` (n = 243 columns, ε = 2.2e-16, so
/// ≈ 5e-14 · λ_1). At `λ_c ≥ 1e-8 · λ_1` (σ_c ≥ 1e-4 · σ_1) that is a relative error of
/// at most ~5e-6 on `λ_c`, and the rank-`c` subspace is as good as the SVD's for the
/// reconstruction error (`tests::gram_path_matches_the_svd_path` measures it). Below
/// that — rank-deficient or constant views, or c beyond the data's numerical rank — the
/// squared spectrum would be dominated by rounding, so the backward-stable QR + SVD path
/// is used. Half-float images carry ~5e-4 relative noise, so real view matrices rarely
/// have σ_c below 1e-4 · σ_1 for the c values that matter.
pub const GRAM_MIN_EIGEN_RATIO: f64 = 1e-8;

/// `AᵀA` with its lower triangle (and the diagonal blocks in full) computed as plain
/// faer GEMMs over `blocks` column blocks; the rest is left zero. Only `gonio bench
/// compress --speed` uses it, as the alternative that was measured and rejected: on a
/// 65536 × 243 view (release, 2 cores at load ≈ 6) b = 1 took 1.08 s, b = 3 2.23 s,
/// b = 9 1.82 s, against 1.05 s for faer's parallel triangular product (PVMF's product
/// until it was replaced by the row-chunked [`gram_by_row_chunks`]).
pub fn gram_lower(a: MatRef<'_, f64>, blocks: usize) -> Mat<f64> {
    let n = a.ncols();
    let nb = blocks.clamp(1, n.max(1));
    let edge = |b: usize| b * n / nb;
    let mut g = Mat::<f64>::zeros(n, n);
    for bi in 0..nb {
        let (i0, i1) = (edge(bi), edge(bi + 1));
        for bj in 0..=bi {
            let (j0, j1) = (edge(bj), edge(bj + 1));
            faer::linalg::matmul::matmul(
                g.as_mut().submatrix_mut(i0, j0, i1 - i0, j1 - j0),
                faer::Accum::Replace,
                a.subcols(i0, i1 - i0).transpose(),
                a.subcols(j0, j1 - j0),
                1.0,
                faer::get_global_parallelism(),
            );
        }
    }
    g
}

/// Rows per chunk of [`gram_by_row_chunks`]: a 4096 × 243 f64 chunk is 8 MiB, so a
/// chunk's product streams through L2/L3 once while faer's kernel runs at its full rate.
const GRAM_CHUNK_ROWS: usize = 4096;

/// The lower triangle (with the diagonal) of `AᵀA`, as a sum of per-chunk products over
/// fixed blocks of [`GRAM_CHUNK_ROWS`] rows.
///
/// Why: alone on an idle pool faer's own parallel triangular product is as fast (0.056 s
/// per 65536 × 243 view against 0.055 s), but PVMF runs it while its reader thread
/// decodes the next view on the same rayon pool, and there the parallel product waits
/// for the busy threads: 0.142 s against 0.114 s per view, and 16.1 s against 12.3 s for
/// the whole encode (`gonio bench compress DATASET --speed`, fields
/// `full_view_*_gram_under_read_seconds`). Whole chunks go to whichever thread is free.
/// The chunk boundaries do not depend on the thread count and the partial sums are added
/// in chunk order, so the result is the same bits on any machine for the same input.
pub fn gram_by_row_chunks(a: MatRef<'_, f64>) -> Mat<f64> {
    use faer::linalg::matmul::triangular::{matmul, BlockStructure};
    let (m, n) = (a.nrows(), a.ncols());
    let chunks = m.div_ceil(GRAM_CHUNK_ROWS).max(1);
    let partial: Vec<Mat<f64>> = (0..chunks)
        .into_par_iter()
        .map(|k| {
            // k < chunks = ⌈m / GRAM_CHUNK_ROWS⌉, so r0 ≤ m (= only for m = 0).
            let r0 = k * GRAM_CHUNK_ROWS;
            let s = a.subrows(r0, GRAM_CHUNK_ROWS.min(m - r0));
            let mut g = Mat::<f64>::zeros(n, n);
            matmul(
                g.as_mut(),
                BlockStructure::TriangularLower,
                faer::Accum::Replace,
                s.transpose(),
                BlockStructure::Rectangular,
                s,
                BlockStructure::Rectangular,
                1.0,
                faer::Par::Seq,
            );
            g
        })
        .collect();
    let mut sum = Mat::<f64>::zeros(n, n);
    for g in &partial {
        for j in 0..n {
            for i in j..n {
                sum[(i, j)] += g[(i, j)];
            }
        }
    }
    sum
}

/// Rank-`c` factorization `A ≈ (A·V)·Vᵀ` from the eigen-decomposition of the Gram matrix
/// `G = AᵀA` (all in f64): `V` = the eigenvectors of the `c` largest eigenvalues, which are
/// the right singular vectors of `A`, and `A·V = U·S`. Returns `None` when the Gram
/// matrix is too ill-conditioned for `c` (see [`GRAM_MIN_EIGEN_RATIO`]); the caller then
/// uses [`truncated_svd`].
///
/// Why: for a tall `m × n` view matrix (65536 × 243) the Gram matrix is one symmetric
/// product (`m·n²` flops: [`gram_by_row_chunks`] computes the lower triangle only) and
/// `A·V` another `2·m·n·c`;
/// the QR path costs `4·m·n²` (factorization plus forming Q). The eigen-decomposition of
/// the 243 × 243 Gram matrix is negligible.
pub fn gram_truncated(a: MatRef<'_, f64>, c: usize) -> Result<Option<Factors>, CompressError> {
    let (m, n) = (a.nrows(), a.ncols());
    let k = c.min(m).min(n);
    if k == 0 {
        return Ok(None);
    }
    let g = gram_by_row_chunks(a);
    let eig = g
        .self_adjoint_eigen(faer::Side::Lower)
        .map_err(|e| CompressError::Svd(format!("Gram eigen-decomposition: {e:?}")))?;
    // Eigenvalues ascending: the largest is the last.
    let lam = eig.S().column_vector();
    let top = lam[n - 1];
    let kth = lam[n - k];
    if !(top.is_finite() && top > 0.0 && kth >= GRAM_MIN_EIGEN_RATIO * top) {
        return Ok(None);
    }
    let u = eig.U();
    let vv = Mat::from_fn(n, c, |i, j| if j < k { u[(i, n - 1 - j)] } else { 0.0 });
    let us = a * &vv;
    Ok(Some((us, vv)))
}

/// Orthonormal basis of the columns of `y` (thin Q of its QR factorization).
pub fn orthonormalize(y: &Mat<f64>) -> Mat<f64> {
    y.qr().compute_thin_Q()
}

/// The image `out[t, ch] = Σ_j us[t, j] · vrows[ch · c + j]` of a texel basis `us`
/// (texels × c) and three rows of a measurement basis (`vrows`, 3 × c): the decoder of
/// PCA's and PVMF's blocks.
pub fn basis_times_rows(us: &[f32], vrows: &[f32], c: usize) -> Vec<f32> {
    let (v0, rest) = vrows.split_at(c);
    let (v1, v2) = rest.split_at(c);
    let t = us.len() / c;
    let mut out = vec![0f32; t * 3];
    // LANES texels at once (3 · LANES independent sums, see `dfmf::Dfmf::decode_rows`);
    // each sum runs in the order of a plain loop, so the bytes do not change.
    const LANES: usize = 4;
    let mut pxs = out.chunks_exact_mut(3 * LANES);
    let mut rows = us.chunks_exact(c * LANES);
    for (px, row) in (&mut pxs).zip(&mut rows) {
        let mut s = [[0f32; 3]; LANES];
        for j in 0..c {
            let (x0, x1, x2) = (v0[j], v1[j], v2[j]);
            for (i, a) in s.iter_mut().enumerate() {
                let r = row[i * c + j];
                a[0] += r * x0;
                a[1] += r * x1;
                a[2] += r * x2;
            }
        }
        for (o, a) in px.chunks_exact_mut(3).zip(s) {
            o.copy_from_slice(&a);
        }
    }
    for (px, row) in pxs
        .into_remainder()
        .chunks_exact_mut(3)
        .zip(rows.remainder().chunks_exact(c))
    {
        let (mut a, mut b, mut d) = (0f32, 0f32, 0f32);
        for j in 0..c {
            a += row[j] * v0[j];
            b += row[j] * v1[j];
            d += row[j] * v2[j];
        }
        px[0] = a;
        px[1] = b;
        px[2] = d;
    }
    out
}
