//! Local PCA / PCMF (Müller, Meseth, Klein 2003): the ABRDFs (one per texel: every
//! measurement × 3 values) are clustered into `k` clusters and each cluster is
//! represented by its mean and `c` eigen-ABRDFs. Encoding alternates
//!
//! 1. per-cluster PCA (mean subtracted; basis by a randomized SVD that streams the
//!    cluster's rows, final SVD by faer in f64), and
//! 2. assignment of every ABRDF to the cluster that reconstructs it with the smallest
//!    squared error (one GEMM of all ABRDFs against all means and bases),
//!
//! starting from a k-means++ seeding (D² sampling, deterministic for a fixed seed) and
//! stopping when at most 0.1 % of the ABRDFs change cluster or after `iters` rounds. Empty clusters are
//! re-seeded with the worst-reconstructed ABRDF. When the data have fewer distinct
//! ABRDFs than `k`, seeding stops early and fewer clusters are stored (the header's
//! `clusters_used` says how many).
//!
//! **Clustering in a subspace** ([`fit_in_subspace`], `--subspace d`, default 64). At
//! 81 × 81 an ABRDF has 19683 values, and every full-space round projects all of them on
//! all k · (c + 1) means and eigen-ABRDFs (0.74 TFLOP per round at 256², k = 32, c = 8).
//! Instead the rounds run on each ABRDF's coordinates in a global d-dimensional PCA
//! subspace: if every cluster's mean and basis lie in that subspace, an ABRDF's full
//! reconstruction error is its error there plus its distance from the subspace, which is
//! the same for every cluster, so the assignments are the ones the restricted models
//! would make. The models are then refitted in the full space from the clusters' members
//! and every ABRDF reassigned there once. Measured on the full default dataset (k = 32,
//! c = 8, idle): d = 16 / 64 / 128 encode in 56.0 / 54.5 / 71.0 s with mean error
//! 0.0061 / 0.0053 / 0.0055 (/255), where the full-space rounds took 1075 s (under load)
//! for 0.0063 (README, Benchmarks).
//!
//! The ABRDFs are read once into an [`Abrdfs`] matrix (module `abrdf`: f32, or 8-bit
//! sRGB codes with a per-column scale for large datasets).
//!
//! Stored blocks (`.gbtf`, f32): `cluster` (texels × 1, the cluster index as an exact
//! small integer), `coef` (texels × c), `mean` (k × M) and `basis` (k·c × M, row
//! `j·c + i` is eigen-ABRDF `i` of cluster `j`), with M = views · lights · 3 and column
//! `(view · lights + light) · 3 + channel` as for PCA.

use super::abrdf::{check_indices, encode_gbtf, Abrdfs, ABRDF_F32_BUDGET};
use super::container::{BlockInfo, Gbtf, GbtfHeader};
use super::data::DatasetViews;
use super::error::CompressError;
use super::linalg::{splitmix, truncated_svd, GaussianSketch, SketchKeying};
use super::params::{Codec, CodecId, Decode, EncodeInfo, Knobs, Layout, Method, Opened, Params, Shard};
use faer::Mat;
use rayon::prelude::*;
use std::sync::Arc;

pub mod passes;

/// Candidates for k-means++ seeding: at most this many rows (evenly strided), so seeding
/// costs `k · 4096 · dims` however large the image.
const SEED_CANDIDATES: usize = 4096;
/// Extra sketch columns of the per-cluster randomized SVD.
pub(crate) const OVERSAMPLE: usize = 10;
/// Power iterations of the per-cluster randomized SVD.
const POWER_ITERS: usize = 2;

/// A fitted local-PCA model.
#[derive(Clone, Debug)]
pub struct LocalPca {
    pub k: usize,
    pub c: usize,
    pub dims: usize,
    pub assign: Vec<u32>,
    /// texels × c.
    pub coef: Vec<f32>,
    /// k × dims.
    pub means: Vec<f32>,
    /// (k · c) × dims.
    pub basis: Vec<f32>,
    /// Alternation rounds run.
    pub rounds: usize,
    /// Sum of squared reconstruction errors over all ABRDF values (linear).
    pub sse: f64,
}

/// k-means++ centers (decoded rows) among evenly strided candidate rows.
fn seed_centers(a: &Abrdfs, k: usize, seed: u64) -> Result<Vec<Vec<f32>>, CompressError> {
    let stride = a.texels.div_ceil(SEED_CANDIDATES).max(1);
    let cand: Vec<u32> = (0..a.texels).step_by(stride).map(|t| t as u32).collect();
    let mut rng = seed ^ 0x5eed_5eed_1234_5678;
    let mut row = vec![0f32; a.dims];
    a.row(
        cand[(splitmix(&mut rng) % cand.len() as u64) as usize] as usize,
        &mut row,
    );
    let mut centers = vec![row.clone()];
    let mut d2 = vec![f64::INFINITY; cand.len()];
    loop {
        let c = centers.last().expect("at least one center");
        a.for_blocks(&cand, None, |off, b| {
            let d: Vec<f64> = (0..b.nrows())
                .into_par_iter()
                .map(|i| b.row(i).iter().zip(c).map(|(&x, &y)| ((x - y) as f64).powi(2)).sum())
                .collect();
            for (o, v) in d2[off..off + d.len()].iter_mut().zip(d) {
                *o = o.min(v);
            }
            Ok(())
        })?;
        if centers.len() >= k {
            break;
        }
        let total: f64 = d2.iter().sum();
        if total <= 0.0 {
            break; // fewer distinct candidate ABRDFs than k
        }
        let r = (splitmix(&mut rng) >> 11) as f64 / (1u64 << 53) as f64 * total;
        let mut acc = 0.0;
        let mut pick = None;
        for (i, &d) in d2.iter().enumerate() {
            if d > 0.0 {
                acc += d;
                pick = Some(i);
                if acc >= r {
                    break;
                }
            }
        }
        let Some(i) = pick else { break };
        a.row(cand[i] as usize, &mut row);
        centers.push(row.clone());
    }
    Ok(centers)
}

/// Orthonormal basis (dims × c, zero columns where the cluster's rank is below c) of the
/// centered rows `members`, by randomized SVD streaming the rows.
fn cluster_basis(
    a: &Abrdfs,
    members: &[u32],
    mean: &[f32],
    c: usize,
    seed: u64,
    power_iters: usize,
) -> Result<Mat<f64>, CompressError> {
    let (n, dims) = (members.len(), a.dims);
    let kp = (c + OVERSAMPLE).min(n).min(dims);
    if c == 0 || kp == 0 {
        return Ok(Mat::zeros(dims, c));
    }
    let sketch = GaussianSketch::new(seed, SketchKeying::Stream);
    let omega = Mat::<f32>::from_fn(dims, kp, |i, j| sketch.at(i, j) as f32);
    let mut y = Mat::<f64>::zeros(n, kp);
    let fill_y = |y: &mut Mat<f64>, m: &Mat<f32>| -> Result<(), CompressError> {
        a.for_blocks(members, Some(mean), |off, b| {
            let yb = b * m;
            for i in 0..yb.nrows() {
                for j in 0..kp {
                    y[(off + i, j)] = yb[(i, j)] as f64;
                }
            }
            Ok(())
        })
    };
    fill_y(&mut y, &omega)?;
    // Xᵀ Q accumulated block by block in f64.
    let xt_q = |q: &Mat<f64>| -> Result<Mat<f64>, CompressError> {
        let qf = Mat::<f32>::from_fn(n, kp, |i, j| q[(i, j)] as f32);
        let mut z = Mat::<f64>::zeros(dims, kp);
        a.for_blocks(members, Some(mean), |off, b| {
            let zb = b.transpose() * qf.as_ref().subrows(off, b.nrows());
            z += Mat::<f64>::from_fn(dims, kp, |i, j| zb[(i, j)] as f64);
            Ok(())
        })?;
        Ok(z)
    };
    for _ in 0..power_iters {
        let q = y.qr().compute_thin_Q();
        let z = xt_q(&q)?;
        let zq = z.qr().compute_thin_Q();
        let zf = Mat::<f32>::from_fn(dims, kp, |i, j| zq[(i, j)] as f32);
        fill_y(&mut y, &zf)?;
    }
    let q = y.qr().compute_thin_Q();
    let bt = xt_q(&q)?; // (Qᵀ X)ᵀ: dims × kp
    basis_from_bt(bt.as_ref(), c)
}

/// The orthonormal basis (dims × c) of the top `c` left singular vectors of `bt = (Qᵀ X)ᵀ`,
/// with zero columns where the rank is below `c` (singular values below 10⁻⁹ of the
/// largest).
pub(crate) fn basis_from_bt(bt: faer::MatRef<'_, f64>, c: usize) -> Result<Mat<f64>, CompressError> {
    let dims = bt.nrows();
    let (us, _) = truncated_svd(bt, c)?;
    let norms: Vec<f64> = (0..c).map(|j| us.col(j).norm_l2()).collect();
    let top = norms.iter().cloned().fold(0.0, f64::max);
    Ok(Mat::from_fn(dims, c, |i, j| {
        if norms[j] > top * 1e-9 && norms[j] > 0.0 {
            us[(i, j)] / norms[j]
        } else {
            0.0
        }
    }))
}

/// Result of one assignment pass.
struct Assignment {
    assign: Vec<u32>,
    coef: Vec<f32>,
    err: Vec<f64>,
    sse: f64,
}

/// Assign every row to the cluster (mean `means[j]`, basis `bases[j]`) with the smallest
/// reconstruction error; coefficients are the projections on that basis.
fn assign(a: &Abrdfs, means: &[Vec<f32>], bases: &[Mat<f64>], c: usize) -> Result<Assignment, CompressError> {
    let (k, dims) = (means.len(), a.dims);
    let w = Mat::<f32>::from_fn(dims, k * (c + 1), |i, col| {
        if col < k {
            means[col][i]
        } else {
            let (j, q) = ((col - k) / c, (col - k) % c);
            bases[j][(i, q)] as f32
        }
    });
    let norms = ModelNorms::of(means, bases, c);
    let all: Vec<u32> = (0..a.texels as u32).collect();
    let mut out = Assignment {
        assign: vec![0; a.texels],
        coef: vec![0.0; a.texels * c],
        err: vec![0.0; a.texels],
        sse: 0.0,
    };
    a.for_blocks(&all, None, |off, b| {
        let p = b * &w;
        let res: Vec<(u32, f64)> = (0..b.nrows())
            .into_par_iter()
            .map(|i| {
                let xsq: f64 = b.row(i).iter().map(|&x| (x as f64).powi(2)).sum();
                norms.best(xsq, |col| p[(i, col)] as f64)
            })
            .collect();
        for (i, (j, e)) in res.into_iter().enumerate() {
            let t = off + i;
            out.assign[t] = j;
            out.err[t] = e;
            out.sse += e;
            for q in 0..c {
                out.coef[t * c + q] = (p[(i, k + j as usize * c + q)] as f64 - norms.bmu[j as usize][q]) as f32;
            }
        }
        Ok(())
    })?;
    Ok(out)
}

/// What the reconstruction error of an ABRDF `x` under each cluster needs besides `x`'s
/// products with the means and eigen-ABRDFs: `‖μ_j‖²` and `b_jqᵀ μ_j`.
pub(crate) struct ModelNorms {
    k: usize,
    c: usize,
    mu_sq: Vec<f64>,
    pub(crate) bmu: Vec<Vec<f64>>,
}

impl ModelNorms {
    pub(crate) fn of(means: &[Vec<f32>], bases: &[Mat<f64>], c: usize) -> Self {
        let k = means.len();
        let dims = means.first().map_or(0, |m| m.len());
        ModelNorms {
            k,
            c,
            mu_sq: means
                .iter()
                .map(|m| m.iter().map(|&x| (x as f64).powi(2)).sum())
                .collect(),
            bmu: (0..k)
                .map(|j| {
                    (0..c)
                        .map(|q| (0..dims).map(|i| bases[j][(i, q)] * means[j][i] as f64).sum())
                        .collect()
                })
                .collect(),
        }
    }

    /// The cluster with the smallest error `‖x − μ_j‖² − Σ_q (b_jqᵀ(x − μ_j))²` (the
    /// first on ties) and that error (clamped at 0), from `‖x‖²` and `p(col)`: `x · μ_j`
    /// at column `j`, `x · b_jq` at column `k + j·c + q`.
    pub(crate) fn best(&self, xsq: f64, p: impl Fn(usize) -> f64) -> (u32, f64) {
        let (k, c) = (self.k, self.c);
        let mut best = (0u32, f64::INFINITY);
        for j in 0..k {
            let mut e = xsq - 2.0 * p(j) + self.mu_sq[j];
            for q in 0..c {
                let cq = p(k + j * c + q) - self.bmu[j][q];
                e -= cq * cq;
            }
            if e < best.1 {
                best = (j as u32, e);
            }
        }
        (best.0, best.1.max(0.0))
    }
}

/// Fit `k` clusters with `c` eigen-ABRDFs each, at most `iters` alternation rounds.
pub fn fit(a: &Abrdfs, k: usize, c: usize, iters: usize, seed: u64) -> Result<LocalPca, CompressError> {
    if k == 0 {
        return Err(CompressError::Invalid("local PCA needs at least 1 cluster".into()));
    }
    if a.texels == 0 || a.dims == 0 {
        return Err(CompressError::Invalid("local PCA of an empty ABRDF matrix".into()));
    }
    let centers = seed_centers(a, k, seed)?;
    let k = centers.len();
    let none: Vec<Mat<f64>> = (0..k).map(|_| Mat::zeros(a.dims, 0)).collect();
    let mut cur = assign(a, &centers, &none, 0)?;
    let mut means = centers;
    let mut bases = none;
    let mut coef = Vec::new();
    let mut rounds = 0;
    for round in 0..iters.max(1) {
        rounds = round + 1;
        let mut members: Vec<Vec<u32>> = vec![Vec::new(); k];
        for (t, &j) in cur.assign.iter().enumerate() {
            members[j as usize].push(t as u32);
        }
        // Re-seed empty clusters with the worst-reconstructed rows of clusters that keep
        // at least one member.
        if members.iter().any(|m| m.is_empty()) {
            let mut order: Vec<usize> = (0..a.texels).collect();
            order.sort_by(|&x, &y| cur.err[y].total_cmp(&cur.err[x]).then(x.cmp(&y)));
            let mut next = order.into_iter();
            for j in 0..k {
                if !members[j].is_empty() {
                    continue;
                }
                for t in next.by_ref() {
                    let from = cur.assign[t] as usize;
                    if members[from].len() > 1 && cur.err[t] > 0.0 {
                        members[from].retain(|&r| r as usize != t);
                        members[j].push(t as u32);
                        cur.assign[t] = j as u32;
                        break;
                    }
                }
            }
        }
        means = members
            .iter()
            .map(|m| if m.is_empty() { vec![0f32; a.dims] } else { a.mean_of(m) })
            .collect();
        bases = members
            .iter()
            .zip(&means)
            .enumerate()
            .map(|(j, (m, mu))| cluster_basis(a, m, mu, c, cluster_seed(seed, j), POWER_ITERS))
            .collect::<Result<_, _>>()?;
        let next = assign(a, &means, &bases, c)?;
        let changed = next.assign.iter().zip(&cur.assign).filter(|(x, y)| x != y).count();
        tracing::debug!(round, changed, sse = next.sse, "local PCA round");
        cur = next;
        coef = std::mem::take(&mut cur.coef);
        // Converged when at most 0.1 % of the ABRDFs moved: with randomized bases a
        // handful of borderline ABRDFs can flip back and forth for many rounds while the
        // error no longer changes.
        if changed * 1000 <= a.texels {
            break;
        }
    }
    Ok(model(a.dims, c, cur.assign, coef, &means, &bases, rounds, cur.sse))
}

/// Seed of cluster `j`'s randomized SVD.
pub(crate) fn cluster_seed(seed: u64, j: usize) -> u64 {
    seed ^ (j as u64 + 1).wrapping_mul(0x9e37)
}

/// Pack means and bases into a [`LocalPca`].
#[allow(clippy::too_many_arguments)]
pub(crate) fn model(
    dims: usize,
    c: usize,
    assign: Vec<u32>,
    coef: Vec<f32>,
    means: &[Vec<f32>],
    bases: &[Mat<f64>],
    rounds: usize,
    sse: f64,
) -> LocalPca {
    let k = means.len();
    let mut basis = vec![0f32; k * c * dims];
    for (j, b) in bases.iter().enumerate() {
        for q in 0..c {
            for i in 0..dims {
                basis[(j * c + q) * dims + i] = b[(i, q)] as f32;
            }
        }
    }
    LocalPca {
        k,
        c,
        dims,
        assign,
        coef,
        means: means.concat(),
        basis,
        rounds,
        sse,
    }
}

/// Default dimension of the global subspace the clustering runs in (`--subspace`).
pub const DEFAULT_SUBSPACE: usize = 64;

/// Power iterations of the global subspace's randomized SVD.
const SUBSPACE_POWER_ITERS: usize = 1;

/// Local PCA with the alternation run in a `d`-dimensional global subspace (see the
/// module docs, "Clustering in a subspace"), fused: every step over whole ABRDF rows in
/// f32 products; `d = 0` (or `d ≥ dims`) runs [`fit`] in the full space. The default;
/// [`fit_in_passes`] is the same algorithm written as the passes `--shard` splits.
///
/// 1. A randomized SVD of all mean-centred ABRDFs gives an orthonormal basis `G`
///    (dims × d) and every ABRDF's coordinates `z = Gᵀ(x − μ)`: one sketch pass, two per
///    power iteration and one projection pass over the data.
/// 2. [`fit`] on the `texels × d` coordinates: seeding, assignment and per-cluster PCA
///    there cost `d / dims` of the full-space rounds (64 / 19683 at 81 × 81).
/// 3. In the full space, once: each cluster's mean and eigen-ABRDFs from its members, then
///    one assignment pass (the final coefficients, and every texel moved to the cluster
///    whose full-space model reconstructs it best).
pub fn fit_in_subspace(
    a: &Abrdfs,
    k: usize,
    c: usize,
    iters: usize,
    seed: u64,
    d: usize,
) -> Result<LocalPca, CompressError> {
    if !passes::Plan::applies(d, a.dims, a.texels) {
        return fit(a, k, c, iters, seed);
    }
    if k == 0 {
        return Err(CompressError::Invalid("local PCA needs at least 1 cluster".into()));
    }
    let all: Vec<u32> = (0..a.texels as u32).collect();
    let mu = a.mean_of(&all);
    let g = cluster_basis(a, &all, &mu, d, seed ^ 0x6c6f_6361_6c70_6361, SUBSPACE_POWER_ITERS)?;
    let gf = Mat::<f32>::from_fn(a.dims, d, |i, j| g[(i, j)] as f32);
    let mut z = vec![0f32; a.texels * d];
    a.for_blocks(&all, Some(&mu), |off, b| {
        let zb = b * &gf;
        for i in 0..zb.nrows() {
            for j in 0..d {
                z[(off + i) * d + j] = zb[(i, j)];
            }
        }
        Ok(())
    })?;
    let coarse = fit(&Abrdfs::from_f32(a.texels, d, z)?, k, c, iters, seed)?;
    let mut members: Vec<Vec<u32>> = vec![Vec::new(); coarse.k];
    for (t, &j) in coarse.assign.iter().enumerate() {
        members[j as usize].push(t as u32);
    }
    let means: Vec<Vec<f32>> = members
        .iter()
        .map(|m| if m.is_empty() { vec![0f32; a.dims] } else { a.mean_of(m) })
        .collect();
    let bases: Vec<Mat<f64>> = members
        .iter()
        .zip(&means)
        .enumerate()
        .map(|(j, (m, mu))| cluster_basis(a, m, mu, c, cluster_seed(seed, j), POWER_ITERS))
        .collect::<Result<_, _>>()?;
    let mut fin = assign(a, &means, &bases, c)?;
    let coef = std::mem::take(&mut fin.coef);
    tracing::debug!(rounds = coarse.rounds, d, sse = fin.sse, "local PCA in a subspace");
    Ok(model(
        a.dims,
        c,
        fin.assign,
        coef,
        &means,
        &bases,
        coarse.rounds,
        fin.sse,
    ))
}

/// Local PCA with the alternation run in a `d`-dimensional global subspace (see the
/// module docs, "Clustering in a subspace") of ABRDFs made of `views` equal blocks of
/// columns, as nine passes over view ranges; `d = 0` (or `d ≥ dims`, `d ≥ texels`) runs
/// [`fit`] in the full space.
///
/// 1. A randomized SVD of all mean-centred ABRDFs gives an orthonormal basis `G`
///    (dims × d) and every ABRDF's coordinates `z ≈ Gᵀ(x − μ)` (`Q B G`): one sketch
///    pass, one power iteration and one projection pass over the data.
/// 2. [`fit`] on the `texels × d` coordinates: seeding, assignment and per-cluster PCA
///    there cost `d / dims` of the full-space rounds (64 / 19683 at 81 × 81).
/// 3. In the full space, once: each cluster's mean and eigen-ABRDFs from its members
///    (a randomized SVD of four passes), then one assignment pass (the final
///    coefficients, and every texel moved to the cluster whose full-space model
///    reconstructs it best).
///
/// The steps are written as passes over ranges of views ([`passes`]),
/// which is what lets `--shard I/N` split them; one process runs the same passes.
pub fn fit_in_passes(
    a: &Abrdfs,
    views: usize,
    k: usize,
    c: usize,
    iters: usize,
    seed: u64,
    d: usize,
) -> Result<LocalPca, CompressError> {
    if !passes::Plan::applies(d, a.dims, a.texels) {
        return fit(a, k, c, iters, seed);
    }
    if k == 0 {
        return Err(CompressError::Invalid("local PCA needs at least 1 cluster".into()));
    }
    if views == 0 || !a.dims.is_multiple_of(views) {
        return Err(CompressError::Invalid(format!(
            "local PCA: {} ABRDF columns do not split into {views} views",
            a.dims
        )));
    }
    let plan = passes::Plan {
        k,
        c,
        iters,
        seed,
        d,
        texels: a.texels,
        width: a.dims / views,
        views,
    };
    plan.fit(a)
}

/// `gonio compress --method local-pca`.
pub fn compress(ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
    let Method::LocalPca {
        clusters,
        iters,
        subspace,
        in_passes,
    } = params.method
    else {
        return Err(CompressError::Invalid(
            "local_pca::compress called for another method".into(),
        ));
    };
    let a = Abrdfs::load(ds, ABRDF_F32_BUDGET)?;
    let (c, seed) = (params.components, params.seed);
    let m = if in_passes {
        fit_in_passes(&a, ds.n_views(), clusters, c, iters, seed, subspace)?
    } else {
        fit_in_subspace(&a, clusters, c, iters, seed, subspace)?
    };
    let (blocks, extra) = file_blocks(m, a.texels, a.dims, params.components, subspace);
    Ok(encode_gbtf(ds, params, &a, blocks, &extra))
}

/// Blocks of a `.gbtf` and the method's extra parameters.
pub(crate) type FileBlocks = (Vec<(BlockInfo, Vec<f32>)>, [(&'static str, serde_json::Value); 3]);

/// The stored blocks and extra parameters of a fitted model: what one process and the
/// merge of a sharded run both write.
pub(crate) fn file_blocks(m: LocalPca, texels: usize, dims: usize, c: usize, subspace: usize) -> FileBlocks {
    let info = BlockInfo::new;
    let blocks = vec![
        (info("cluster", texels, 1), m.assign.iter().map(|&j| j as f32).collect()),
        (info("coef", texels, c), m.coef),
        (info("mean", m.k, dims), m.means),
        (info("basis", m.k * c, dims), m.basis),
    ];
    let extra = [
        ("clusters_used", m.k.into()),
        ("rounds", m.rounds.into()),
        ("subspace", subspace.into()),
    ];
    (blocks, extra)
}

/// Check the block shapes of a local-PCA file; returns (k, c).
pub fn validate(h: &GbtfHeader) -> Result<(usize, usize), CompressError> {
    let t = h.width * h.height;
    let dims = h.lights_deg.len() * h.views_deg.len() * 3;
    let got: Vec<(usize, usize)> = h.blocks.iter().map(|b| (b.rows, b.cols)).collect();
    let (k, c) = match got.as_slice() {
        [_, (_, c), (k, _), _] => (*k, *c),
        _ => (0, 0),
    };
    if k == 0 || got != [(t, 1), (t, c), (k, dims), (k * c, dims)] {
        return Err(CompressError::Invalid(format!(
            ".gbtf local-pca: block shapes {got:?} do not match the header's grid"
        )));
    }
    Ok((k, c))
}

/// Reconstruct image (`light`, `view`) of a validated local-PCA file.
pub fn reconstruct(g: &Gbtf, k: usize, c: usize, light: usize, view: usize) -> Vec<f32> {
    let h = &g.header;
    let dims = h.lights_deg.len() * h.views_deg.len() * 3;
    let col = (view * h.lights_deg.len() + light) * 3;
    let (cluster, coef, mean, basis) = (&g.blocks[0], &g.blocks[1], &g.blocks[2], &g.blocks[3]);
    // Per cluster: 3 mean values then c × 3 basis values of this pair's columns.
    let mut table = vec![0f32; k * (c + 1) * 3];
    for j in 0..k {
        let tj = &mut table[j * (c + 1) * 3..(j + 1) * (c + 1) * 3];
        tj[..3].copy_from_slice(&mean[j * dims + col..j * dims + col + 3]);
        for q in 0..c {
            let r = (j * c + q) * dims + col;
            tj[3 + q * 3..6 + q * 3].copy_from_slice(&basis[r..r + 3]);
        }
    }
    let t = h.width * h.height;
    let mut out = vec![0f32; t * 3];
    for (i, px) in out.chunks_exact_mut(3).enumerate() {
        let j = cluster[i] as usize;
        let tj = &table[j * (c + 1) * 3..(j + 1) * (c + 1) * 3];
        let (mut r, mut gg, mut b) = (tj[0], tj[1], tj[2]);
        for (q, &w) in coef[i * c..(i + 1) * c].iter().enumerate() {
            r += w * tj[3 + q * 3];
            gg += w * tj[4 + q * 3];
            b += w * tj[5 + q * 3];
        }
        px[0] = r;
        px[1] = gg;
        px[2] = b;
    }
    out
}

/// Local PCA in the registry (`super::registry`).
pub struct LocalPcaCodec;

impl Codec for LocalPcaCodec {
    fn id(&self) -> CodecId {
        CodecId::LocalPca
    }
    fn ladder(&self, knobs: &Knobs) -> Vec<Vec<Params>> {
        let method = |k: usize| Method::LocalPca {
            clusters: k,
            iters: knobs.iters,
            subspace: knobs.subspace,
            in_passes: knobs.in_passes,
        };
        [8, 32]
            .map(|k| [2, 4, 8, 16].map(|c| knobs.params(method(k), c)).to_vec())
            .to_vec()
    }
    fn shard(&self, _: &Knobs) -> Shard {
        Shard::Passes(passes::PASSES)
    }
    fn encode(&self, ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
        compress(ds, params)
    }
    fn open(&self, g: &Gbtf) -> Result<Opened, CompressError> {
        let (k, c) = validate(&g.header)?;
        check_indices(&g.blocks[0], k, "cluster")?;
        Ok(Opened {
            method: Method::LocalPca {
                clusters: k,
                iters: 0,
                subspace: 0,
                in_passes: false,
            },
            components: c,
            layout: Layout::Clusters { clusters: k },
            decoder: Arc::new(Decoder { k, c }),
        })
    }
}

/// [`reconstruct`] with the file's cluster and component counts.
#[derive(Debug)]
struct Decoder {
    k: usize,
    c: usize,
}

impl Decode for Decoder {
    fn reconstruct(&self, g: &Gbtf, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        Ok(reconstruct(g, self.k, self.c, light, view))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compress::testdata::{self, hash, max_err, round_trip};
    use crate::compress::{evaluate, CompressedBtf};

    /// The full-space algorithm (subspace 0) with a seed.
    fn params(k: usize, c: usize, seed: u64) -> Params {
        Params {
            seed,
            ..in_subspace(k, c, 0)
        }
    }

    fn in_subspace(k: usize, c: usize, d: usize) -> Params {
        Params::new(
            Method::LocalPca {
                clusters: k,
                iters: 20,
                subspace: d,
                in_passes: false,
            },
            c,
        )
    }

    /// Clustering in a global subspace: exact where the full-space algorithm is exact
    /// (three affine rank-1 groups span 5 centred dimensions, d = 8 holds them), and on
    /// noisy groups within 10 % of the full-space algorithm's squared error.
    #[test]
    fn clustering_in_a_subspace_matches_the_full_space_fit() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), three_groups);
        let (g, m) = round_trip(&ds, &in_subspace(3, 1, 8), &tmp.path().join("s.gbtf"));
        assert_eq!(g.header.params["subspace"], 8);
        let e = max_err(&ds, &m);
        assert!(e < 1.5e-3, "subspace 8: max error {e}");

        let noisy = testdata::write(&tmp.path().join("noisy"), |l, v, t, c| {
            three_groups(l, v, t, c) + 0.05 * hash(t + 1000, (v * 5 + l) * 3 + c)
        });
        let a = Abrdfs::load(&noisy, ABRDF_F32_BUDGET).unwrap();
        let full = fit(&a, 4, 2, 20, 3).unwrap();
        let sub = fit_in_subspace(&a, 4, 2, 20, 3, 12).unwrap();
        println!(
            "noisy groups: full-space SSE {:.4e}, subspace 12 SSE {:.4e}",
            full.sse, sub.sse
        );
        assert!(
            sub.sse <= full.sse * 1.10,
            "subspace SSE {} vs full {}",
            sub.sse,
            full.sse
        );
        // The same algorithm as the nine passes `--shard` splits: as close to the full
        // space as the fused encoder.
        let passes = fit_in_passes(&a, noisy.n_views(), 4, 2, 20, 3, 12).unwrap();
        assert!(
            passes.sse <= full.sse * 1.10,
            "in passes SSE {} vs full {}",
            passes.sse,
            full.sse
        );
    }

    /// Three well separated groups of texels, each an affine rank-1 family
    /// base_g + s_t · dir_g: local PCA with k = 3, c = 1 represents it exactly.
    fn three_groups(l: usize, v: usize, t: usize, c: usize) -> f32 {
        let g = (t * 7) % 3;
        let col = (v * 5 + l) * 3 + c;
        let base = 0.2 + 0.6 * g as f32 + 0.1 * hash(g, col);
        let dir = hash(g + 10, col) - 0.5;
        base + 0.2 * hash(99, t) * dir
    }

    #[test]
    fn round_trip_reproduces_piecewise_affine_rank1_data() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), three_groups);
        let (g, m) = round_trip(&ds, &params(3, 1, 1), &tmp.path().join("a.gbtf"));
        assert_eq!(g.header.params["clusters_used"], 3);
        // Exact up to the half-float rounding of the stored images (values ≤ 1.4: half
        // an ulp ≤ 5e-4, which is not on the rank-1 lines).
        let e = max_err(&ds, &m);
        assert!(e < 1.5e-3, "k = 3, c = 1: max error {e}");
        // One cluster cannot: the three groups are not one affine line.
        let (_, m1) = round_trip(&ds, &params(1, 1, 1), &tmp.path().join("b.gbtf"));
        assert!(max_err(&ds, &m1) > 1e-2);
        // Errors are reported like every other method's.
        let ev = evaluate(&ds, &m).unwrap();
        assert_eq!(ev.images, 20);
        assert!(ev.stats.rmse_linear() < 5e-4);
    }

    #[test]
    fn same_seed_same_file_and_more_clusters_fit_better() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), |l, v, t, c| {
            0.3 * hash(t % 5, (v * 5 + l) * 3 + c) + 0.05 * hash(t, l * 3 + c)
        });
        let a = compress(&ds, &params(4, 2, 7)).unwrap().0;
        let b = compress(&ds, &params(4, 2, 7)).unwrap().0;
        assert_eq!(a, b, "same seed, same result");
        let abr = Abrdfs::load(&ds, ABRDF_F32_BUDGET).unwrap();
        let sse = |k: usize| fit(&abr, k, 2, 20, 7).unwrap().sse;
        let (s1, s5) = (sse(1), sse(5));
        assert!(s5 < 0.5 * s1, "k = 5: {s5}, k = 1: {s1}");
    }

    #[test]
    fn constant_and_rank_deficient_input() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), |_, _, _, _| 0.25);
        let (g, m) = round_trip(&ds, &params(4, 3, 1), &tmp.path().join("a.gbtf"));
        assert_eq!(g.header.params["clusters_used"], 1, "one distinct ABRDF, one cluster");
        assert_eq!(max_err(&ds, &m), 0.0);
        assert!(g.blocks.iter().flatten().all(|v| v.is_finite()));
        // All zeros.
        let ds0 = testdata::write(&tmp.path().join("z"), |_, _, _, _| 0.0);
        let (_, m0) = round_trip(&ds0, &params(2, 2, 1), &tmp.path().join("z.gbtf"));
        assert_eq!(max_err(&ds0, &m0), 0.0);
    }

    #[test]
    fn more_clusters_than_distinct_abrdfs() {
        let tmp = tempfile::tempdir().unwrap();
        // Two distinct ABRDFs; ask for 10 clusters of c = 2.
        let ds = testdata::write(&tmp.path().join("ds"), |l, v, t, c| hash(t % 2, (v * 5 + l) * 3 + c));
        let (g, m) = round_trip(&ds, &params(10, 2, 3), &tmp.path().join("a.gbtf"));
        let used = g.header.params["clusters_used"].as_u64().unwrap();
        assert!((1..=2).contains(&used), "{used} clusters for 2 distinct ABRDFs");
        assert!(max_err(&ds, &m) < 1e-5);
    }

    #[test]
    fn eight_bit_storage_is_within_its_quantization() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), three_groups);
        let exact = Abrdfs::load(&ds, ABRDF_F32_BUDGET).unwrap();
        let q = Abrdfs::load(&ds, 0).unwrap();
        assert!(exact.is_exact() && !q.is_exact());
        assert!(q.bytes() * 3 < exact.bytes());
        let (mut a, mut b) = (vec![0f32; q.dims], vec![0f32; q.dims]);
        for t in 0..q.texels {
            exact.row(t, &mut a);
            q.row(t, &mut b);
            for j in 0..q.dims {
                // 8-bit sRGB step relative to the column maximum (< 1.3 here) is ≤ 1.2 %.
                assert!(
                    (a[j] - b[j]).abs() <= 0.012 * 1.3,
                    "texel {t} column {j}: {} vs {}",
                    a[j],
                    b[j]
                );
            }
        }
        // Local PCA on the 8-bit copy still separates the three groups.
        let m = fit(&q, 3, 1, 20, 1).unwrap();
        let mut groups = std::collections::BTreeSet::new();
        for t in 0..q.texels {
            groups.insert(((t * 7) % 3, m.assign[t]));
        }
        assert_eq!(groups.len(), 3, "each group is one cluster: {groups:?}");
    }

    #[test]
    fn non_finite_input_is_rejected_naming_the_measurement() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("ds");
        testdata::write(&dir, three_groups);
        let mut img = gonio_devices::image::RgbImage::new(testdata::W, testdata::H);
        img.data[4] = f32::INFINITY;
        gonio_dataset::store::write_exr(&dir.join("images/00006.exr"), &img).unwrap();
        let ds = DatasetViews::open(&dir).unwrap();
        let e = compress(&ds, &params(2, 1, 1)).unwrap_err();
        assert!(
            matches!(e, CompressError::NonFinite { index: 6, texel: 1, .. }),
            "{e:?}"
        );
        assert!(e.to_string().contains("00006.exr"), "{e}");
    }

    #[test]
    fn corrupt_cluster_index_is_rejected() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), three_groups);
        let (mut g, _) = compress(&ds, &params(3, 1, 1)).unwrap();
        g.blocks[0][5] = 7.0;
        let e = CompressedBtf::new(g).unwrap_err();
        assert!(e.to_string().contains("texel 5"), "{e}");
    }
}
