//! Local PCA in a subspace ([`super`], `--subspace d > 0`) written as
//! **passes over a range of views**, so that one process runs them all in turn and N
//! processes (`gonio compress --method local-pca --shard I/N`) can each run one pass over
//! their own views, with a merge between passes ([`crate::compress::rsvd_shard`] carries
//! the files).
//!
//! The ABRDF matrix `X` (texels × views · lights · 3) splits by views into column blocks
//! `X_v`. Everything local PCA computes is either a sum over views of per-view products
//! (summed exactly, [`crate::compress::exact`], so the grouping into shards does not show in the
//! bits), columns that belong to one view, or a small global step the merge runs:
//!
//! | pass | a shard computes over its views | the merge after it |
//! |---|---|---|
//! | 0 | `Y = Σ_v X̃_v Ω_v` (X̃: the global column mean removed) | exact sum |
//! | 1 | `Y = Σ_v X̃_v (X̃_vᵀ Q)`, `Q = orth(Y)` | exact sum |
//! | 2 | its columns of `B = Qᵀ X̃` | `G` = the top `d` right singular vectors of B |
//! | 3 | the coordinates `z = Σ_v X̃_v G_v` (texels × d) | exact sum; k-means++ seeding and the clustering rounds on `z`, in the merge |
//! | 4 | per cluster `Y_j = Σ_v X̃_{j,v} Ω_{j,v}` (members, the cluster mean removed) | exact sums |
//! | 5, 6 | per cluster `Y_j = Σ_v X̃_{j,v} (X̃_{j,v}ᵀ Q_j)` | exact sums |
//! | 7 | its columns of `B_j = Q_jᵀ X̃_j` and of the cluster means | eigen-ABRDFs: the top `c` right singular vectors of each `B_j` |
//! | 8 | per texel `Σ_v x_v · w_v` for every mean and eigen-ABRDF `w`, and `Σ_v ‖x_v‖²` | every texel to the cluster that reconstructs it best; coefficients; the `.gbtf` |
//!
//! A column mean and a cluster mean depend on their own column alone, so every shard
//! computes its own. `--in-passes` runs exactly these passes in one process (one "shard"
//! of all views), so a merged sharded run gives its file byte for byte. Without it one
//! process runs the fused encoder (`local_pca::fit_in_subspace`), the same algorithm
//! over whole rows in f32 products, about 3× faster at 256² (docs/guide/scale.md).
//!
//! The coordinates are the exact projection `X̃ G`, not the sketch's `Q (B G)`: that
//! saves pass 3 but clustered worse (on a 64², 81 × 81 sample, k = 32, c = 8, seeds
//! 1–4: 0.2–1.8 dB below the exact projection, which matches the earlier
//! implementation's PSNR to 0.001 dB).
//!
//! **Cost of sharding.** Pass 8's part is `texels × (k (c + 1) + 1)` exact sums of 32
//! bytes (606 MB at 256², k = 32, c = 8): every texel's error under every cluster is a
//! sum over all views. The other parts are the `texels × (d + 10)` and `texels × (c + 10)`
//! sketches and the `(d + 10)`- and `k (c + 10)`-row projections of the shard's columns.

use crate::compress::abrdf::Abrdfs;
use crate::compress::error::CompressError;
use crate::compress::exact::ExactMat;
use crate::compress::linalg::{orthonormalize, GaussianSketch, SketchKeying};
use crate::compress::local_pca::{self, LocalPca};
use crate::compress::rsvd::{Channel, PassOutput, Rsvd, ViewSource};
use faer::{Mat, MatRef};
use rayon::prelude::*;
use std::ops::Range;

/// Power iterations of the global subspace's randomized SVD.
const SUBSPACE_POWER_ITERS: usize = 1;
/// Power iterations of each cluster's randomized SVD.
const CLUSTER_POWER_ITERS: usize = 2;
/// Passes of the subspace's randomized SVD (sketch, power iterations, projection).
const SUBSPACE_PASSES: usize = SUBSPACE_POWER_ITERS + 2;
/// Passes of the clusters' randomized SVDs.
const CLUSTER_PASSES: usize = CLUSTER_POWER_ITERS + 2;
/// All passes: the subspace, the coordinates in it, the clusters, the final assignment.
pub const PASSES: usize = SUBSPACE_PASSES + 1 + CLUSTER_PASSES + 1;

/// What every pass and every shard must agree on.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    /// Clusters asked for.
    pub k: usize,
    /// Eigen-ABRDFs per cluster.
    pub c: usize,
    /// Most clustering rounds (in the subspace).
    pub iters: usize,
    pub seed: u64,
    /// Subspace dimension, `0 < d < min(dims, texels)`.
    pub d: usize,
    pub texels: usize,
    /// Columns per view (lights · 3).
    pub width: usize,
    pub views: usize,
}

/// Which part of the algorithm a pass belongs to.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Stage {
    /// Pass `i` of the subspace's randomized SVD.
    Subspace(usize),
    /// Every ABRDF's coordinates in the subspace.
    Coords,
    /// Pass `i` of the clusters' randomized SVDs.
    Clusters(usize),
    /// The final assignment sums.
    Assign,
}

fn stage(pass: usize) -> Stage {
    if pass < SUBSPACE_PASSES {
        Stage::Subspace(pass)
    } else if pass == SUBSPACE_PASSES {
        Stage::Coords
    } else if pass < SUBSPACE_PASSES + 1 + CLUSTER_PASSES {
        Stage::Clusters(pass - SUBSPACE_PASSES - 1)
    } else {
        Stage::Assign
    }
}

/// Named f64 blocks: what one pass hands the next (`y0`…: rounded sums; `g`: the
/// subspace's basis; `assign`: the
/// cluster of every texel; `meta`: clusters used and rounds; `mean`, `basis`: the models).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct State {
    pub blocks: Vec<(String, Mat<f64>)>,
}

impl State {
    fn get(&self, name: &str) -> Result<&Mat<f64>, CompressError> {
        self.blocks
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, m)| m)
            .ok_or_else(|| CompressError::Invalid(format!("local PCA state without its `{name}` block")))
    }

    fn sums(&self) -> Vec<&Mat<f64>> {
        self.blocks
            .iter()
            .filter(|(n, _)| n.starts_with('y'))
            .map(|(_, m)| m)
            .collect()
    }

    fn carried(&self) -> Vec<(String, Mat<f64>)> {
        self.blocks
            .iter()
            .filter(|(n, _)| n == "assign" || n == "meta")
            .cloned()
            .collect()
    }

    /// The cluster of every texel and the clusters used.
    fn assignment(&self, texels: usize) -> Result<(Vec<u32>, usize), CompressError> {
        let a = self.get("assign")?;
        let meta = self.get("meta")?;
        let k = meta[(0, 0)] as usize;
        if a.nrows() != texels || a.ncols() != 1 || k == 0 {
            return Err(CompressError::Invalid(format!(
                "local PCA state: assignment of {} texels and {k} clusters, {texels} texels expected",
                a.nrows()
            )));
        }
        let assign: Vec<u32> = (0..texels).map(|t| a[(t, 0)] as u32).collect();
        if let Some(t) = (0..texels).find(|&t| a[(t, 0)] != assign[t] as f64 || assign[t] as usize >= k) {
            return Err(CompressError::Invalid(format!(
                "local PCA state: texel {t}'s cluster {} is not one of the {k} clusters",
                a[(t, 0)]
            )));
        }
        Ok((assign, k))
    }
}

/// What merging a pass gives.
pub enum Finished {
    /// The input of the next pass.
    State(State),
    /// The last pass: the model.
    Model(LocalPca),
}

impl Plan {
    pub fn dims(&self) -> usize {
        self.width * self.views
    }

    pub fn passes(&self) -> usize {
        PASSES
    }

    /// Whether `d` makes a subspace fit (else local PCA runs in the full space, which is
    /// not written as passes).
    pub fn applies(d: usize, dims: usize, texels: usize) -> bool {
        d > 0 && d < dims && d < texels
    }

    /// The global subspace's randomized SVD.
    fn subspace(&self) -> Rsvd {
        let kp = (self.d + local_pca::OVERSAMPLE).min(self.texels).min(self.dims());
        Rsvd {
            channels: vec![Channel {
                rows: self.texels,
                k: kp,
                sketch: GaussianSketch::new(self.seed ^ 0x6c6f_6361_6c70_6361, SketchKeying::Stream),
            }],
            width: self.width,
            views: self.views,
            power_iters: SUBSPACE_POWER_ITERS,
        }
    }

    /// The clusters' randomized SVDs: one channel per cluster with members (when c > 0).
    fn clusters(&self, members: &[Vec<u32>]) -> (Rsvd, Vec<usize>) {
        let active: Vec<usize> = (0..members.len())
            .filter(|&j| !members[j].is_empty() && self.c > 0)
            .collect();
        let channels = active
            .iter()
            .map(|&j| Channel {
                rows: members[j].len(),
                k: (self.c + local_pca::OVERSAMPLE).min(members[j].len()).min(self.dims()),
                sketch: GaussianSketch::new(local_pca::cluster_seed(self.seed, j), SketchKeying::Stream),
            })
            .collect();
        (
            Rsvd {
                channels,
                width: self.width,
                views: self.views,
                power_iters: CLUSTER_POWER_ITERS,
            },
            active,
        )
    }

    /// Run `pass` over `views`; `a` holds the ABRDF columns of exactly those views, and
    /// `state` is what the previous pass's merge gave (none for pass 0).
    pub fn run_pass(
        &self,
        pass: usize,
        views: Range<usize>,
        a: &Abrdfs,
        state: Option<&State>,
    ) -> Result<PassOutput, CompressError> {
        if a.dims != views.len() * self.width || a.texels != self.texels || views.end > self.views {
            return Err(CompressError::Invalid(format!(
                "local PCA pass {pass}: {} × {} ABRDF columns given for views {views:?} ({} texels, {} columns per view)",
                a.texels, a.dims, self.texels, self.width
            )));
        }
        fn need(s: Option<&State>, pass: usize) -> Result<&State, CompressError> {
            s.ok_or_else(|| {
                CompressError::Invalid(format!(
                    "local PCA pass {pass} needs the state of pass {}",
                    pass.max(1) - 1
                ))
            })
        }
        match stage(pass) {
            Stage::Subspace(p) => {
                let rsvd = self.subspace();
                let q = match p {
                    0 => None,
                    _ => Some(bases_of(&need(state, pass)?.sums())),
                };
                let mut src = Centred {
                    a,
                    first: views.start,
                    width: self.width,
                    members: None,
                };
                rsvd.run_pass(p, views, q.as_deref(), &mut src)
            }
            Stage::Coords => {
                let g = need(state, pass)?.get("g")?;
                let mut src = Centred {
                    a,
                    first: views.start,
                    width: self.width,
                    members: None,
                };
                let mut z = ExactMat::zeros(self.texels, self.d);
                let mut err = None;
                for v in views {
                    let gv = g.as_ref().subrows(v * self.width, self.width);
                    src.with_view(v, &mut |x| {
                        let term = x[0] * gv;
                        if let Err(e) = z.add(term.as_ref(), &format!("view {v}, local PCA pass {pass}")) {
                            err.get_or_insert(e);
                        }
                    })?;
                }
                match err {
                    Some(e) => Err(e),
                    None => Ok(PassOutput::Sums(vec![z])),
                }
            }
            Stage::Clusters(p) => {
                let st = need(state, pass)?;
                let (assign, k) = st.assignment(self.texels)?;
                let members = members_of(&assign, k);
                let (rsvd, active) = self.clusters(&members);
                let q = match p {
                    0 => None,
                    _ => Some(bases_of(&st.sums())),
                };
                let active_members: Vec<Vec<u32>> = active.iter().map(|&j| members[j].clone()).collect();
                let mut src = Centred {
                    a,
                    first: views.start,
                    width: self.width,
                    members: Some(&active_members),
                };
                let out = rsvd.run_pass(p, views.clone(), q.as_deref(), &mut src)?;
                match out {
                    PassOutput::Projection(mut b) if rsvd.is_projection(p) => {
                        // The cluster means' columns travel with the projection.
                        let mut means = Mat::<f64>::zeros(k, a.dims);
                        for (j, m) in members.iter().enumerate() {
                            if m.is_empty() {
                                continue;
                            }
                            for i in 0..views.len() {
                                let cols = i * self.width..(i + 1) * self.width;
                                for (c, x) in column_means(a, Some(m), cols.clone()).into_iter().enumerate() {
                                    means[(j, cols.start + c)] = x as f64;
                                }
                            }
                        }
                        b.push(means);
                        Ok(PassOutput::Projection(b))
                    }
                    o => Ok(o),
                }
            }
            Stage::Assign => {
                let st = need(state, pass)?;
                let (_, k) = st.assignment(self.texels)?;
                let (mean, basis) = (st.get("mean")?, st.get("basis")?);
                let c = self.c;
                let ncol = k * (c + 1) + 1;
                let mut sums = ExactMat::zeros(self.texels, ncol);
                let mut buf = Vec::new();
                for (i, v) in views.enumerate() {
                    let col0 = v * self.width;
                    let w = Mat::<f32>::from_fn(self.width, k * (c + 1), |r, col| {
                        if col < k {
                            mean[(col, col0 + r)] as f32
                        } else {
                            basis[(col - k, col0 + r)] as f32
                        }
                    });
                    a.decode_cols(None, i * self.width..(i + 1) * self.width, &mut buf);
                    let x = MatRef::from_row_major_slice(&buf[..], self.texels, self.width);
                    let p = x * &w;
                    let mut term = Mat::<f64>::zeros(self.texels, ncol);
                    for col in 0..ncol - 1 {
                        for (o, &v) in term.col_as_slice_mut(col).iter_mut().zip(p.col_as_slice(col)) {
                            *o = v as f64;
                        }
                    }
                    for (o, row) in term
                        .col_as_slice_mut(ncol - 1)
                        .iter_mut()
                        .zip(buf.chunks_exact(self.width))
                    {
                        *o = row.iter().map(|&e| (e as f64) * (e as f64)).sum();
                    }
                    sums.add(term.as_ref(), &format!("view {v}, local PCA pass {pass}"))?;
                }
                Ok(PassOutput::Sums(vec![sums]))
            }
        }
    }

    /// The merge after `pass`: from the state the pass started from and the pass's whole
    /// output (sums exactly summed and rounded, or every view's columns in view order).
    pub fn finish_pass(&self, pass: usize, before: Option<&State>, merged: Merged) -> Result<Finished, CompressError> {
        let need = || {
            before.ok_or_else(|| {
                CompressError::Invalid(format!("merging local PCA pass {pass} needs the state it started from"))
            })
        };
        let sums_state = |carried: Vec<(String, Mat<f64>)>, s: Vec<Mat<f64>>| {
            let mut blocks = carried;
            blocks.extend(s.into_iter().enumerate().map(|(i, m)| (format!("y{i}"), m)));
            Finished::State(State { blocks })
        };
        match (stage(pass), merged) {
            (Stage::Subspace(p), Merged::Sums(s)) if p + 1 < SUBSPACE_PASSES => Ok(sums_state(Vec::new(), s)),
            (Stage::Subspace(_), Merged::Columns(b)) => {
                let b = b
                    .first()
                    .ok_or_else(|| CompressError::Invalid("local PCA pass 2 without its projection".into()))?;
                let g = local_pca::basis_from_bt(b.transpose(), self.d)?;
                Ok(Finished::State(State {
                    blocks: vec![("g".into(), g)],
                }))
            }
            (Stage::Coords, Merged::Sums(s)) => {
                let z = s
                    .first()
                    .ok_or_else(|| CompressError::Invalid("local PCA: the coordinates pass has no sums".into()))?;
                let zf: Vec<f32> = (0..self.texels)
                    .flat_map(|t| (0..self.d).map(move |j| (t, j)))
                    .map(|(t, j)| z[(t, j)] as f32)
                    .collect();
                let coarse = local_pca::fit(
                    &Abrdfs::from_f32(self.texels, self.d, zf)?,
                    self.k,
                    self.c,
                    self.iters,
                    self.seed,
                )?;
                tracing::debug!(
                    rounds = coarse.rounds,
                    d = self.d,
                    "local PCA clustered in its subspace"
                );
                Ok(Finished::State(State {
                    blocks: vec![
                        (
                            "assign".into(),
                            Mat::from_fn(self.texels, 1, |t, _| coarse.assign[t] as f64),
                        ),
                        (
                            "meta".into(),
                            Mat::from_fn(1, 2, |_, j| if j == 0 { coarse.k as f64 } else { coarse.rounds as f64 }),
                        ),
                    ],
                }))
            }
            (Stage::Clusters(p), Merged::Sums(s)) if p + 1 < CLUSTER_PASSES => Ok(sums_state(need()?.carried(), s)),
            (Stage::Clusters(_), Merged::Columns(mut b)) => {
                let st = need()?;
                let (assign, k) = st.assignment(self.texels)?;
                let members = members_of(&assign, k);
                let (rsvd, active) = self.clusters(&members);
                let means = b
                    .pop()
                    .filter(|m| m.nrows() == k && m.ncols() == self.dims())
                    .ok_or_else(|| {
                        CompressError::Invalid(format!(
                            "local PCA pass {pass}: the cluster means are missing or misshapen"
                        ))
                    })?;
                if b.len() != rsvd.channels.len() {
                    return Err(CompressError::Invalid(format!(
                        "local PCA pass {pass}: {} projections for {} clusters",
                        b.len(),
                        rsvd.channels.len()
                    )));
                }
                let dims = self.dims();
                let mut basis = Mat::<f64>::zeros(k * self.c, dims);
                for (bj, &j) in b.iter().zip(&active) {
                    let g = local_pca::basis_from_bt(bj.transpose(), self.c)?;
                    for q in 0..self.c {
                        for i in 0..dims {
                            basis[(j * self.c + q, i)] = g[(i, q)];
                        }
                    }
                }
                let mut blocks = st.carried();
                blocks.push(("mean".into(), means));
                blocks.push(("basis".into(), basis));
                Ok(Finished::State(State { blocks }))
            }
            (Stage::Assign, Merged::Sums(s)) => {
                let st = need()?;
                let (_, k) = st.assignment(self.texels)?;
                let rounds = st.get("meta")?[(0, 1)] as usize;
                let p = s
                    .first()
                    .ok_or_else(|| CompressError::Invalid("local PCA: the last pass has no sums".into()))?;
                Ok(Finished::Model(self.final_model(
                    k,
                    rounds,
                    st.get("mean")?,
                    st.get("basis")?,
                    p,
                )?))
            }
            (s, _) => Err(CompressError::Invalid(format!(
                "local PCA pass {pass} ({s:?}): its parts hold the other kind of blocks"
            ))),
        }
    }

    /// Every texel to the cluster with the smallest reconstruction error, from the summed
    /// products `p` (texels × (k (c + 1) + 1): means, eigen-ABRDFs, ‖x‖²).
    fn final_model(
        &self,
        k: usize,
        rounds: usize,
        mean: &Mat<f64>,
        basis: &Mat<f64>,
        p: &Mat<f64>,
    ) -> Result<LocalPca, CompressError> {
        let (c, dims) = (self.c, self.dims());
        if p.nrows() != self.texels || p.ncols() != k * (c + 1) + 1 {
            return Err(CompressError::Invalid(format!(
                "local PCA: final sums are {} × {}, {} × {} expected",
                p.nrows(),
                p.ncols(),
                self.texels,
                k * (c + 1) + 1
            )));
        }
        let means: Vec<Vec<f32>> = (0..k)
            .map(|j| (0..dims).map(|i| mean[(j, i)] as f32).collect())
            .collect();
        let bases: Vec<Mat<f64>> = (0..k)
            .map(|j| Mat::from_fn(dims, c, |i, q| basis[(j * c + q, i)]))
            .collect();
        let norms = local_pca::ModelNorms::of(&means, &bases, c);
        let res: Vec<(u32, f64, Vec<f32>)> = (0..self.texels)
            .into_par_iter()
            .map(|t| {
                let (j, e) = norms.best(p[(t, k * (c + 1))], |col| p[(t, col)]);
                let coef = (0..c)
                    .map(|q| (p[(t, k + j as usize * c + q)] - norms.bmu[j as usize][q]) as f32)
                    .collect();
                (j, e, coef)
            })
            .collect();
        let mut assign = Vec::with_capacity(self.texels);
        let mut coef = Vec::with_capacity(self.texels * c);
        let mut sse = 0.0;
        for (j, e, cf) in res {
            assign.push(j);
            sse += e;
            coef.extend(cf);
        }
        Ok(local_pca::model(dims, c, assign, coef, &means, &bases, rounds, sse))
    }

    /// All passes in one process: what a merged sharded run reproduces.
    pub fn fit(&self, a: &Abrdfs) -> Result<LocalPca, CompressError> {
        let mut state: Option<State> = None;
        for pass in 0..PASSES {
            let t0 = std::time::Instant::now();
            let out = self.run_pass(pass, 0..self.views, a, state.as_ref())?;
            let t1 = t0.elapsed().as_secs_f64();
            let merged = match out {
                PassOutput::Sums(s) => Merged::Sums(s.iter().map(ExactMat::to_mat).collect()),
                PassOutput::Projection(b) => Merged::Columns(b),
            };
            let fin = self.finish_pass(pass, state.as_ref(), merged)?;
            tracing::debug!(
                pass,
                run_s = t1,
                merge_s = t0.elapsed().as_secs_f64() - t1,
                "local PCA pass"
            );
            match fin {
                Finished::State(s) => state = Some(s),
                Finished::Model(m) => return Ok(m),
            }
        }
        unreachable!("the last pass gives the model")
    }
}

/// A pass's whole output.
pub enum Merged {
    /// The exact sums, rounded once.
    Sums(Vec<Mat<f64>>),
    /// Every view's columns, in view order.
    Columns(Vec<Mat<f64>>),
}

fn bases_of(sums: &[&Mat<f64>]) -> Vec<Mat<f64>> {
    sums.iter().map(|s| orthonormalize(s)).collect()
}

fn members_of(assign: &[u32], k: usize) -> Vec<Vec<u32>> {
    let mut members = vec![Vec::new(); k];
    for (t, &j) in assign.iter().enumerate() {
        members[j as usize].push(t as u32);
    }
    members
}

/// Mean of columns `cols` over `rows` (all texels if `None`): f64 sums in row order,
/// rounded to f32. A column's mean depends on that column alone.
fn column_means(a: &Abrdfs, rows: Option<&[u32]>, cols: Range<usize>) -> Vec<f32> {
    let mut buf = Vec::new();
    a.decode_cols(rows, cols.clone(), &mut buf);
    means_of_block(&buf, cols.len())
}

/// Column means of the row-major block `buf` of `w` columns (f64 sums in row order).
fn means_of_block(buf: &[f32], w: usize) -> Vec<f32> {
    let n = buf.len().checked_div(w).unwrap_or(0);
    let mut s = vec![0f64; w];
    for row in buf.chunks_exact(w.max(1)) {
        for (a, &x) in s.iter_mut().zip(row) {
            *a += x as f64;
        }
    }
    s.into_iter().map(|x| (x / n.max(1) as f64) as f32).collect()
}

/// The view matrices a pass multiplies: all texels less the global column mean, or each
/// cluster's members less the cluster's mean.
struct Centred<'a> {
    a: &'a Abrdfs,
    /// First view held by `a`.
    first: usize,
    width: usize,
    members: Option<&'a [Vec<u32>]>,
}

impl Centred<'_> {
    fn centred(&self, rows: Option<&[u32]>, cols: Range<usize>) -> Mat<f64> {
        let mut buf = Vec::new();
        self.a.decode_cols(rows, cols, &mut buf);
        let w = self.width;
        let mu = means_of_block(&buf, w);
        let n = buf.len().checked_div(w).unwrap_or(0);
        let mut m = Mat::<f64>::zeros(n, w);
        let fill = |j: usize, col: &mut [f64]| {
            for (i, o) in col.iter_mut().enumerate() {
                *o = (buf[i * w + j] - mu[j]) as f64;
            }
        };
        if n >= 1024 {
            m.par_col_iter_mut().enumerate().for_each(|(j, col)| {
                fill(
                    j,
                    col.try_as_col_major_mut()
                        .expect("an owned column is contiguous")
                        .as_slice_mut(),
                )
            });
        } else {
            for j in 0..w {
                fill(j, m.col_as_slice_mut(j));
            }
        }
        m
    }
}

impl ViewSource for Centred<'_> {
    fn with_view(&mut self, v: usize, f: &mut dyn FnMut(&[MatRef<'_, f64>])) -> Result<(), CompressError> {
        let off = (v - self.first) * self.width;
        let cols = off..off + self.width;
        let mats: Vec<Mat<f64>> = match self.members {
            None => vec![self.centred(None, cols)],
            Some(ms) => ms.iter().map(|m| self.centred(Some(m), cols.clone())).collect(),
        };
        let refs: Vec<MatRef<'_, f64>> = mats.iter().map(|m| m.as_ref()).collect();
        f(&refs);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compress::testdata::{self, hash};

    /// Run every pass the way a sharded job does: each range of `splits` on the ABRDF
    /// columns of its views only (loaded alone, stored as `exact` says), sums added
    /// exactly in reverse shard order, columns joined in view order.
    fn sharded(plan: &Plan, ds: &crate::compress::DatasetViews, splits: &[Range<usize>], exact: bool) -> LocalPca {
        let parts: Vec<Abrdfs> = splits
            .iter()
            .map(|r| Abrdfs::load_views(ds, r.clone(), exact).unwrap())
            .collect();
        let mut state: Option<State> = None;
        for pass in 0..PASSES {
            let outs: Vec<PassOutput> = splits
                .iter()
                .zip(&parts)
                .rev()
                .map(|(r, a)| plan.run_pass(pass, r.clone(), a, state.as_ref()).unwrap())
                .collect();
            let merged = match &outs[0] {
                PassOutput::Sums(first) => {
                    let mut acc: Vec<ExactMat> = first.iter().map(|m| ExactMat::zeros(m.nrows(), m.ncols())).collect();
                    for o in &outs {
                        let PassOutput::Sums(s) = o else {
                            panic!("mixed outputs")
                        };
                        for (a, m) in acc.iter_mut().zip(s) {
                            a.add_exact(m, "test").unwrap();
                        }
                    }
                    Merged::Sums(acc.iter().map(ExactMat::to_mat).collect())
                }
                PassOutput::Projection(first) => {
                    let n = first.len();
                    let cols: Vec<Mat<f64>> = (0..n)
                        .map(|b| {
                            let blocks: Vec<&Mat<f64>> = outs
                                .iter()
                                .rev()
                                .map(|o| match o {
                                    PassOutput::Projection(p) => &p[b],
                                    _ => panic!("mixed outputs"),
                                })
                                .collect();
                            let total: usize = blocks.iter().map(|m| m.ncols()).sum();
                            let mut out = Mat::zeros(blocks[0].nrows(), total);
                            let mut off = 0;
                            for m in blocks {
                                out.as_mut().subcols_mut(off, m.ncols()).copy_from(m);
                                off += m.ncols();
                            }
                            out
                        })
                        .collect();
                    Merged::Columns(cols)
                }
            };
            match plan.finish_pass(pass, state.as_ref(), merged).unwrap() {
                Finished::State(s) => state = Some(s),
                Finished::Model(m) => return m,
            }
        }
        unreachable!()
    }

    fn plan(ds: &crate::compress::DatasetViews, k: usize, c: usize, d: usize) -> Plan {
        Plan {
            k,
            c,
            iters: 10,
            seed: 5,
            d,
            texels: ds.texels(),
            width: ds.n_lights() * 3,
            views: ds.n_views(),
        }
    }

    fn same(a: &LocalPca, b: &LocalPca) -> bool {
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        a.assign == b.assign
            && bits(&a.coef) == bits(&b.coef)
            && bits(&a.means) == bits(&b.means)
            && bits(&a.basis) == bits(&b.basis)
            && a.sse.to_bits() == b.sse.to_bits()
            && a.rounds == b.rounds
    }

    /// Any split of the views gives the single process's model bit for bit, with the
    /// ABRDFs held as f32 and as 8-bit codes (each shard's codes from its own columns).
    #[test]
    fn any_split_of_the_views_gives_the_single_process_model() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write_grid(
            &tmp.path().join("ds"),
            16,
            12,
            &testdata::lights(),
            &testdata::views(),
            |l, v, t, c| 0.2 + 0.5 * hash(t % 7, (v * 5 + l) * 3 + c) + 0.1 * hash(t, v * 3 + c),
        );
        let p = plan(&ds, 5, 2, 6);
        for exact in [true, false] {
            let whole = Abrdfs::load_views(&ds, 0..4, exact).unwrap();
            let single = p.fit(&whole).unwrap();
            assert!(single.sse.is_finite() && single.k >= 2, "{} clusters", single.k);
            for splits in [vec![0..2, 2..4], vec![0..1, 1..3, 3..4], vec![0..1, 1..2, 2..3, 3..4]] {
                let m = sharded(&p, &ds, &splits, exact);
                assert!(same(&single, &m), "exact {exact}, splits {splits:?}");
            }
        }
    }

    /// Constant and all-zero ABRDFs: one cluster, zero error, finite factors (rank-zero
    /// sketches must not give NaN bases).
    #[test]
    fn constant_input_gives_one_exact_cluster() {
        let tmp = tempfile::tempdir().unwrap();
        for (name, value) in [("const", 0.25f32), ("zero", 0.0)] {
            let ds = testdata::write(&tmp.path().join(name), |_, _, _, _| value);
            let a = Abrdfs::load(&ds, crate::compress::abrdf::ABRDF_F32_BUDGET).unwrap();
            let m = plan(&ds, 4, 3, 5).fit(&a).unwrap();
            assert_eq!(m.k, 1, "{name}");
            assert!(
                m.coef.iter().chain(&m.means).chain(&m.basis).all(|x| x.is_finite()),
                "{name}"
            );
            assert!(m.sse.abs() < 1e-9, "{name}: SSE {}", m.sse);
        }
    }

    /// A state without what the pass needs is refused by name, not a panic.
    #[test]
    fn a_pass_without_its_state_is_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), |l, v, t, c| hash(t, (v * 5 + l) * 3 + c));
        let a = Abrdfs::load(&ds, crate::compress::abrdf::ABRDF_F32_BUDGET).unwrap();
        let p = plan(&ds, 3, 2, 5);
        let e = p.run_pass(4, 0..4, &a, None).unwrap_err().to_string();
        assert!(e.contains("pass 4 needs the state of pass 3"), "{e}");
        let e = p
            .run_pass(4, 0..4, &a, Some(&State::default()))
            .unwrap_err()
            .to_string();
        assert!(e.contains("`assign`"), "{e}");
        let e = p.run_pass(0, 0..3, &a, None).unwrap_err().to_string();
        assert!(e.contains("views 0..3"), "{e}");
    }
}
