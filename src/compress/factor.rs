//! The factorizations (PVMF, randomized PCA) and reconstruction from their factors.

use super::container::{BlockInfo, Gbtf, GbtfHeader};
use super::data::{DatasetViews, ViewMatrix};
use super::CompressError;
use faer::{Mat, MatRef};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Compression method.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Full-matrix PCA by randomized SVD.
    Pca,
    /// Per-view matrix factorization (one truncated SVD per view).
    Pvmf,
    /// Local PCA / PCMF (`local_pca`): `clusters` clusters of ABRDFs with `components`
    /// eigen-ABRDFs each, at most `iters` alternation rounds, run in a global subspace of
    /// `subspace` dimensions (0: in the full ABRDF space).
    #[serde(rename = "local-pca")]
    LocalPca {
        clusters: usize,
        iters: usize,
        subspace: usize,
    },
    /// Median-cut quantization of ABRDFs (`median_cut`): index image + BRDF block.
    #[serde(rename = "median-cut")]
    MedianCut {
        boxes: usize,
        balanced: bool,
        min_error_cut: bool,
    },
    /// Homomorphic factorization per ABRDF (`homomorphic`): light × view × half-vector
    /// factors fitted in the log domain (`half_bins` θ_h bins, `sweeps` backfitting sweeps).
    Homomorphic { half_bins: usize, sweeps: usize },
}

impl Method {
    pub fn name(self) -> &'static str {
        match self {
            Method::Pca => "pca",
            Method::Pvmf => "pvmf",
            Method::LocalPca { .. } => "local-pca",
            Method::MedianCut { .. } => "median-cut",
            Method::Homomorphic { .. } => "homomorphic",
        }
    }
}

/// Parameters of [`compress`].
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct Params {
    pub method: Method,
    /// Components kept (per view for PVMF, in total for PCA).
    pub components: usize,
    /// PCA: seed of the Gaussian test matrix.
    pub seed: u64,
    /// PCA: extra sketch columns beyond `components`.
    pub oversample: usize,
    /// PCA: power iterations (each one more pass over the dataset).
    pub power_iters: usize,
}

impl Params {
    pub fn new(method: Method, components: usize) -> Self {
        Params {
            method,
            components,
            seed: 1,
            oversample: 10,
            power_iters: 2,
        }
    }
}

/// What [`compress`] saw besides the factors.
#[derive(Serialize, Clone, Debug, Default, PartialEq)]
pub struct EncodeInfo {
    /// Unmeasured (light, view) pairs filled from the nearest measured light.
    pub filled: usize,
    /// Passes that read the dataset's images. PVMF: 1. PCA: 1 when all view matrices fit
    /// [`PCA_CACHE_BYTES`] as f64 (they are kept in memory for the later passes), else
    /// `2 + power_iters`.
    pub passes: usize,
    /// Where the encode time went (timing spans; empty for methods that do not report
    /// them). PVMF: `read_wait` (time the factorization waited for the reader),
    /// `factorize`, and the counts of views factorized by each path.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub stages: Vec<Stage>,
}

/// One timing span or count of an encode.
#[derive(Serialize, Clone, Debug, Default, PartialEq)]
pub struct Stage {
    pub name: String,
    pub value: f64,
    /// `s` for seconds, `views` for counts.
    pub unit: &'static str,
}

fn to_faer(v: &ViewMatrix) -> Mat<f64> {
    Mat::from_fn(v.rows, v.cols, |i, j| v.data[i * v.cols + j] as f64)
}

fn row_major_f32(m: MatRef<'_, f64>) -> Vec<f32> {
    let mut out = Vec::with_capacity(m.nrows() * m.ncols());
    for i in 0..m.nrows() {
        for j in 0..m.ncols() {
            out.push(m[(i, j)] as f32);
        }
    }
    out
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

/// Deterministic standard normal number for (seed, row, col): splitmix64 + Box-Muller.
fn gaussian(seed: u64, row: usize, col: usize) -> f64 {
    let mix = |k: u64| {
        let mut z = k.wrapping_add(0x9e37_79b9_7f4a_7c15);
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    };
    let k = mix(seed ^ mix((row as u64) << 20 ^ col as u64));
    let u1 = ((k >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
    let u2 = ((mix(k) >> 11) as f64) / (1u64 << 53) as f64;
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn orthonormalize(y: &Mat<f64>) -> Mat<f64> {
    y.qr().compute_thin_Q()
}

pub(super) fn header_for(
    ds: &DatasetViews,
    params: &Params,
    filled: Vec<[usize; 2]>,
    blocks: Vec<BlockInfo>,
) -> GbtfHeader {
    GbtfHeader {
        method: params.method.name().into(),
        params: serde_json::to_value(params).unwrap_or(serde_json::Value::Null),
        width: ds.width,
        height: ds.height,
        channels: 3,
        dtype: "f32le".into(),
        lights_deg: ds.lights_deg.clone(),
        views_deg: ds.views_deg.clone(),
        filled,
        source: serde_json::json!({
            "dataset": ds.dir.display().to_string(),
            "values": ds.header.values,
            "sample": ds.header.sample,
        }),
        blocks,
    }
}

/// One shard of a PVMF compression (`gonio compress --shard`): the factors of the shard's
/// views only, exactly as [`compress`] computes them (each view is factorized on its own),
/// with the shard recorded as `source.shard` for `gonio merge`.
pub fn compress_pvmf_shard(
    ds: &DatasetViews,
    params: &Params,
    shard: crate::shard::Shard,
) -> Result<(Gbtf, EncodeInfo), CompressError> {
    if params.components == 0 {
        return Err(CompressError::Invalid("components must be at least 1".into()));
    }
    if params.method != Method::Pvmf {
        return Err(CompressError::Invalid(format!(
            "--shard splits PVMF by views; method {} is not split (compress it in one process)",
            params.method.name()
        )));
    }
    shard.check_views(ds.n_views()).map_err(CompressError::Invalid)?;
    let info = shard.info(ds.n_views());
    let (mut g, e) = compress_pvmf(ds, params, info.first_view..info.end_view)?;
    g.header.source["shard"] = serde_json::to_value(info).map_err(|e| CompressError::Invalid(e.to_string()))?;
    Ok((g, e))
}

/// Compress the dataset with `params`.
pub fn compress(ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
    if params.components == 0 {
        return Err(CompressError::Invalid("components must be at least 1".into()));
    }
    match params.method {
        Method::Pvmf => compress_pvmf(ds, params, 0..ds.n_views()),
        Method::Pca => compress_pca(ds, params),
        Method::LocalPca { .. } => super::local_pca::compress(ds, params),
        Method::MedianCut { .. } => super::median_cut::compress(ds, params),
        Method::Homomorphic { .. } => super::homomorphic::compress(ds, params),
    }
}

/// PVMF. The reader runs on its own thread one view ahead of the factorization (bounded
/// channel of one matrix), so decoding view `k + 1`'s EXRs overlaps with factorizing
/// view `k`; both use the rayon pool, so on a small machine this fills the gaps of each
/// stage rather than doubling the throughput. At most three view matrices (f64, 127 MiB
/// each at 256² × 243) are alive at once.
fn compress_pvmf(
    ds: &DatasetViews,
    params: &Params,
    views: std::ops::Range<usize>,
) -> Result<(Gbtf, EncodeInfo), CompressError> {
    use std::sync::mpsc::sync_channel;
    use std::time::Instant;
    let c = params.components;
    let (t, cols, nv) = (ds.texels(), ds.n_lights() * 3, views.len());
    let mut blocks = Vec::with_capacity(2 * nv);
    let mut infos = Vec::with_capacity(2 * nv);
    let mut filled = Vec::new();
    let (mut wait_s, mut factor_s, mut gram_views, mut svd_views) = (0.0, 0.0, 0usize, 0usize);
    std::thread::scope(|scope| -> Result<(), CompressError> {
        let (tx, rx) = sync_channel(1);
        let reader_views = views.clone();
        scope.spawn(move || {
            for v in reader_views {
                let r = ds.view_columns(v);
                let failed = r.is_err();
                // A closed channel means the factorization stopped (error): stop too.
                if tx.send(r).is_err() || failed {
                    break;
                }
            }
        });
        for v in views.clone() {
            let t0 = Instant::now();
            let (a, vf) = rx
                .recv()
                .map_err(|_| CompressError::Invalid(format!("PVMF reader thread ended before view {v}")))??;
            wait_s += t0.elapsed().as_secs_f64();
            filled.extend(vf.iter().map(|&(l, _)| [l, v]));
            let t1 = Instant::now();
            let (us, vv) = match gram_truncated(a.as_ref(), c)? {
                Some(f) => {
                    gram_views += 1;
                    f
                }
                None => {
                    svd_views += 1;
                    tracing::debug!(view = v, c, "PVMF: Gram matrix ill-conditioned, QR + SVD path");
                    truncated_svd(a.as_ref(), c)?
                }
            };
            drop(a);
            blocks.push(row_major_f32(us.as_ref()));
            infos.push(BlockInfo {
                name: format!("us{v}"),
                rows: t,
                cols: c,
            });
            blocks.push(row_major_f32(vv.as_ref()));
            infos.push(BlockInfo {
                name: format!("v{v}"),
                rows: cols,
                cols: c,
            });
            factor_s += t1.elapsed().as_secs_f64();
        }
        Ok(())
    })?;
    tracing::info!(wait_s, factor_s, gram_views, svd_views, "PVMF encoded");
    let stage = |name: &str, value: f64, unit| Stage {
        name: name.into(),
        value,
        unit,
    };
    let info = EncodeInfo {
        filled: filled.len(),
        passes: 1,
        stages: vec![
            stage("read_wait", wait_s, "s"),
            stage("factorize", factor_s, "s"),
            stage("gram_path", gram_views as f64, "views"),
            stage("svd_path", svd_views as f64, "views"),
        ],
    };
    let header = header_for(ds, params, filled, infos);
    Ok((Gbtf { header, blocks }, info))
}

/// Streams view matrices, keeping them in memory when they fit `budget` bytes in total.
struct ViewCache<'a> {
    ds: &'a DatasetViews,
    cached: Vec<Option<Mat<f64>>>,
    keep: bool,
    filled: Vec<[usize; 2]>,
    passes: usize,
}

impl<'a> ViewCache<'a> {
    fn new(ds: &'a DatasetViews, budget: usize) -> Self {
        let total = ds.texels() * ds.n_lights() * 3 * ds.n_views() * 8;
        ViewCache {
            ds,
            cached: vec![None; ds.n_views()],
            keep: total <= budget,
            filled: Vec::new(),
            passes: 0,
        }
    }

    /// Call `f(view, matrix)` for every view, in order.
    fn pass(&mut self, mut f: impl FnMut(usize, MatRef<'_, f64>)) -> Result<(), CompressError> {
        let first = self.passes == 0;
        let mut read = false;
        for v in 0..self.ds.n_views() {
            if let Some(m) = &self.cached[v] {
                f(v, m.as_ref());
                continue;
            }
            read = true;
            let vm = self.ds.view_matrix(v)?;
            if first {
                self.filled.extend(vm.filled.iter().map(|&(l, _)| [l, v]));
            }
            let m = to_faer(&vm);
            drop(vm);
            f(v, m.as_ref());
            if self.keep {
                self.cached[v] = Some(m);
            }
        }
        if read || first {
            self.passes += 1;
        }
        Ok(())
    }
}

/// Budget for keeping all view matrices (f64) in memory during PCA's passes.
pub const PCA_CACHE_BYTES: usize = 1 << 30;

fn compress_pca(ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
    let c = params.components;
    let (t, lc) = (ds.texels(), ds.n_lights() * 3);
    let n = lc * ds.n_views();
    let k = (c + params.oversample).min(t).min(n);
    let mut cache = ViewCache::new(ds, PCA_CACHE_BYTES);

    // Y = A Ω, Ω Gaussian (n × k), generated per view block.
    let mut y = Mat::<f64>::zeros(t, k);
    cache.pass(|v, a| {
        let omega = Mat::from_fn(lc, k, |i, j| gaussian(params.seed, v * lc + i, j));
        y += a * &omega;
    })?;
    // Power iterations: Y ← A Aᵀ Q, Q = orth(Y).
    for _ in 0..params.power_iters {
        let q = orthonormalize(&y);
        let mut ny = Mat::<f64>::zeros(t, k);
        cache.pass(|_, a| {
            let z = a.transpose() * &q;
            ny += a * &z;
        })?;
        y = ny;
    }
    let q = orthonormalize(&y);
    // B = Qᵀ A (k × n), one view block of columns at a time.
    let mut b = Mat::<f64>::zeros(q.ncols(), n);
    cache.pass(|v, a| {
        let bv = q.transpose() * a;
        b.as_mut().subcols_mut(v * lc, lc).copy_from(&bv);
    })?;
    let (ub, vv) = truncated_svd(b.as_ref(), c)?;
    let us = &q * &ub;
    let infos = vec![
        BlockInfo {
            name: "us".into(),
            rows: t,
            cols: c,
        },
        BlockInfo {
            name: "v".into(),
            rows: n,
            cols: c,
        },
    ];
    let blocks = vec![row_major_f32(us.as_ref()), row_major_f32(vv.as_ref())];
    let info = EncodeInfo {
        filled: cache.filled.len(),
        passes: cache.passes,
        ..Default::default()
    };
    let header = header_for(ds, params, std::mem::take(&mut cache.filled), infos);
    Ok((Gbtf { header, blocks }, info))
}

/// A decoded `.gbtf`, ready to reconstruct images.
#[derive(Clone, Debug)]
pub struct CompressedBtf {
    pub gbtf: Gbtf,
    method: Method,
    c: usize,
    /// Homomorphic files only: the factor tables in direction-major order for decoding
    /// (see [`super::homomorphic::DirectionMajor`]).
    homomorphic: Option<Box<super::homomorphic::DirectionMajor>>,
}

/// Index of the direction in `list` within 0.01° of `deg` (angle between the unit vectors).
pub fn find_direction(list: &[[f64; 2]], deg: [f64; 2]) -> Option<usize> {
    let v = |d: [f64; 2]| {
        let (t, p) = (d[0].to_radians(), d[1].to_radians());
        [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
    };
    let a = v(deg);
    let cos_tol = 0.01f64.to_radians().cos();
    list.iter()
        .enumerate()
        .map(|(i, &d)| {
            let b = v(d);
            (i, a[0] * b[0] + a[1] * b[1] + a[2] * b[2])
        })
        .filter(|&(_, dot)| dot >= cos_tol)
        .max_by(|x, y| x.1.total_cmp(&y.1))
        .map(|(i, _)| i)
}

impl CompressedBtf {
    /// Check the blocks against the header and wrap them.
    pub fn new(gbtf: Gbtf) -> Result<Self, CompressError> {
        let h = &gbtf.header;
        let bad = |r: String| CompressError::Invalid(format!(".gbtf {}: {r}", h.method));
        let method = match h.method.as_str() {
            "pvmf" => Method::Pvmf,
            "pca" => Method::Pca,
            "local-pca" => {
                let (_, c) = super::local_pca::validate(h)?;
                let k = h.blocks[2].rows;
                super::local_pca::check_indices(&gbtf.blocks[0], k, "cluster")?;
                let method = Method::LocalPca {
                    clusters: k,
                    iters: 0,
                    subspace: 0,
                };
                return Ok(CompressedBtf {
                    gbtf,
                    method,
                    c,
                    homomorphic: None,
                });
            }
            "median-cut" => {
                let boxes = super::median_cut::validate(&gbtf)?;
                let method = Method::MedianCut {
                    boxes,
                    balanced: false,
                    min_error_cut: false,
                };
                return Ok(CompressedBtf {
                    gbtf,
                    method,
                    c: 0,
                    homomorphic: None,
                });
            }
            "homomorphic" => {
                let half_bins = super::homomorphic::validate(h)?;
                let method = Method::Homomorphic { half_bins, sweeps: 0 };
                let tables = Box::new(super::homomorphic::DirectionMajor::new(&gbtf, half_bins));
                return Ok(CompressedBtf {
                    gbtf,
                    method,
                    c: 0,
                    homomorphic: Some(tables),
                });
            }
            m => return Err(bad(format!("unknown method {m:?}"))),
        };
        if h.channels != 3 {
            return Err(bad(format!("{} channels, only RGB is supported", h.channels)));
        }
        let (t, nl, nv) = (h.width * h.height, h.lights_deg.len(), h.views_deg.len());
        let c = h.blocks.first().map(|b| b.cols).unwrap_or(0);
        let want: Vec<(usize, usize)> = match method {
            Method::Pvmf => (0..nv).flat_map(|_| [(t, c), (nl * 3, c)]).collect(),
            Method::Pca => vec![(t, c), (nl * nv * 3, c)],
            _ => Vec::new(),
        };
        let got: Vec<(usize, usize)> = h.blocks.iter().map(|b| (b.rows, b.cols)).collect();
        if got != want || c == 0 {
            return Err(bad(format!("block shapes {got:?} do not match the header's grid")));
        }
        Ok(CompressedBtf {
            gbtf,
            method,
            c,
            homomorphic: None,
        })
    }

    pub fn method(&self) -> Method {
        self.method
    }
    pub fn components(&self) -> usize {
        self.c
    }
    pub fn header(&self) -> &GbtfHeader {
        &self.gbtf.header
    }

    /// Reconstruct the linear RGB image (interleaved, rows top to bottom) of grid pair
    /// (`light`, `view`).
    pub fn reconstruct(&self, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        let h = &self.gbtf.header;
        let (nl, nv) = (h.lights_deg.len(), h.views_deg.len());
        if light >= nl || view >= nv {
            return Err(CompressError::Invalid(format!(
                "pair (light {light}, view {view}) outside the {nl} × {nv} grid"
            )));
        }
        let c = self.c;
        if let Some(tables) = &self.homomorphic {
            return Ok(tables.reconstruct(&self.gbtf.header, light, view));
        }
        if let Method::MedianCut { .. } = self.method {
            return Ok(super::median_cut::reconstruct(&self.gbtf, light, view));
        }
        if let Method::LocalPca { clusters, .. } = self.method {
            return Ok(super::local_pca::reconstruct(&self.gbtf, clusters, c, light, view));
        }
        let (us, vrows) = match self.method {
            Method::Pvmf => {
                let vb = &self.gbtf.blocks[2 * view + 1];
                (&self.gbtf.blocks[2 * view], &vb[light * 3 * c..(light * 3 + 3) * c])
            }
            Method::Pca => {
                let r = (view * nl + light) * 3;
                (&self.gbtf.blocks[0], &self.gbtf.blocks[1][r * c..(r + 3) * c])
            }
            _ => return Err(CompressError::Invalid(format!("no decoder for {:?}", self.method))),
        };
        let (v0, rest) = vrows.split_at(c);
        let (v1, v2) = rest.split_at(c);
        let t = h.width * h.height;
        let mut out = vec![0f32; t * 3];
        for (px, row) in out.chunks_exact_mut(3).zip(us.chunks_exact(c)) {
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
        Ok(out)
    }

    /// Reconstruct by directions in degrees; they must be grid directions (±0.01°).
    pub fn reconstruct_deg(&self, light_deg: [f64; 2], view_deg: [f64; 2]) -> Result<Vec<f32>, CompressError> {
        let h = &self.gbtf.header;
        let l = find_direction(&h.lights_deg, light_deg).ok_or(CompressError::NotMeasured {
            which: "light",
            deg: light_deg,
        })?;
        let v = find_direction(&h.views_deg, view_deg).ok_or(CompressError::NotMeasured {
            which: "view",
            deg: view_deg,
        })?;
        self.reconstruct(l, v)
    }
}
