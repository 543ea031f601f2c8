//! Full-matrix PCA: one rank-`c` factorization of the whole `texels × (measurements · 3)`
//! matrix by a randomized SVD that streams the views (see the module docs of [`super`]).
//! Stored blocks (`.gbtf`, f32): `us` (texels × c) and `v` (views·lights·3 × c), row
//! `(view · lights + light) · 3 + channel`.

use super::container::{BlockInfo, Gbtf};
use super::data::{DatasetViews, ViewMatrix};
use super::error::CompressError;
use super::linalg::{basis_times_rows, row_major_f32, truncated_svd, GaussianSketch, SketchKeying};
use super::params::{
    check_basis_blocks, header_for, Codec, CodecId, Decode, EncodeInfo, Knobs, Layout, Method, Opened, Params, Shard,
};
use super::rsvd::{Channel, Rsvd, ViewSource};
use faer::{Mat, MatRef};
use std::sync::Arc;

fn to_faer(v: &ViewMatrix) -> Mat<f64> {
    Mat::from_fn(v.rows, v.cols, |i, j| v.data[i * v.cols + j] as f64)
}

/// Streams view matrices, keeping them in memory when they fit `budget` bytes in total.
pub(crate) struct ViewCache<'a> {
    ds: &'a DatasetViews,
    cached: Vec<Option<Mat<f64>>>,
    keep: bool,
    /// Whether view `v` has been read (its filled pairs are then listed).
    seen: Vec<bool>,
    /// `[light, view]` of every filled pair, in the order the views were first read.
    pub(crate) filled: Vec<[usize; 2]>,
}

impl<'a> ViewCache<'a> {
    pub(crate) fn new(ds: &'a DatasetViews, budget: usize) -> Self {
        let total = ds.texels() * ds.n_lights() * 3 * ds.n_views() * 8;
        ViewCache {
            ds,
            cached: vec![None; ds.n_views()],
            keep: total <= budget,
            seen: vec![false; ds.n_views()],
            filled: Vec::new(),
        }
    }

    /// Passes that read images when all `passes` run in this process: one when every
    /// view stays in memory, else every pass.
    pub(crate) fn reads(&self, passes: usize) -> usize {
        if self.keep {
            1
        } else {
            passes
        }
    }
}

impl ViewSource for ViewCache<'_> {
    fn with_view(&mut self, v: usize, f: &mut dyn FnMut(&[MatRef<'_, f64>])) -> Result<(), CompressError> {
        if let Some(m) = &self.cached[v] {
            f(&[m.as_ref()]);
            return Ok(());
        }
        let vm = self.ds.view_matrix(v)?;
        if !self.seen[v] {
            self.seen[v] = true;
            self.filled.extend(vm.filled.iter().map(|&(l, _)| [l, v]));
        }
        let m = to_faer(&vm);
        drop(vm);
        f(&[m.as_ref()]);
        if self.keep {
            self.cached[v] = Some(m);
        }
        Ok(())
    }
}

/// Budget for keeping all view matrices (f64) in memory during PCA's passes.
pub const PCA_CACHE_BYTES: usize = 1 << 30;

/// The randomized SVD of PCA for `ds` with `params` (one channel: the view matrix).
pub(crate) fn problem(ds: &DatasetViews, params: &Params) -> Rsvd {
    let c = params.components;
    let (t, lc) = (ds.texels(), ds.n_lights() * 3);
    let n = lc * ds.n_views();
    Rsvd {
        channels: vec![Channel {
            rows: t,
            k: (c + params.oversample).min(t).min(n),
            sketch: GaussianSketch::new(params.seed, SketchKeying::Hashed),
        }],
        width: lc,
        views: ds.n_views(),
        power_iters: params.power_iters,
    }
}

/// The stored blocks from the last pass's `Q` and `B = Qᵀ A`: `us = Q · U_B S` and `v`.
pub(crate) fn factors(
    params: &Params,
    q: &Mat<f64>,
    b: &Mat<f64>,
) -> Result<(Vec<BlockInfo>, Vec<Vec<f32>>), CompressError> {
    let c = params.components;
    let (ub, vv) = truncated_svd(b.as_ref(), c)?;
    let us = q * &ub;
    let infos = vec![BlockInfo::new("us", q.nrows(), c), BlockInfo::new("v", b.ncols(), c)];
    Ok((infos, vec![row_major_f32(us.as_ref()), row_major_f32(vv.as_ref())]))
}

pub fn compress(ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
    let rsvd = problem(ds, params);
    let mut cache = ViewCache::new(ds, PCA_CACHE_BYTES);
    let (q, b) = rsvd.run_all(&mut cache)?;
    let info = EncodeInfo {
        filled: cache.filled.len(),
        passes: cache.reads(rsvd.passes()),
        ..Default::default()
    };
    let (infos, blocks) = factors(params, &q[0], &b[0])?;
    let header = header_for(ds, params, std::mem::take(&mut cache.filled), infos);
    Ok((Gbtf { header, blocks }, info))
}

/// PCA in the registry (`super::registry`).
pub struct PcaCodec;

impl Codec for PcaCodec {
    fn id(&self) -> CodecId {
        CodecId::Pca
    }
    fn ladder(&self, knobs: &Knobs) -> Vec<Vec<Params>> {
        vec![[4, 8, 16, 32, 64].map(|c| knobs.params(Method::Pca, c)).to_vec()]
    }
    fn shard(&self, knobs: &Knobs) -> Shard {
        // Range sketch, projection and the power iterations.
        Shard::Passes(2 + knobs.power_iters)
    }
    fn encode(&self, ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
        compress(ds, params)
    }
    fn open(&self, g: &Gbtf) -> Result<Opened, CompressError> {
        let c = check_basis_blocks(g, |t, nl, nv, c| vec![(t, c), (nl * nv * 3, c)])?;
        Ok(Opened {
            method: Method::Pca,
            components: c,
            layout: Layout::Basis,
            decoder: Arc::new(Decoder { c }),
        })
    }
}

/// The texel basis times the pair's three rows of the measurement basis.
#[derive(Debug)]
struct Decoder {
    c: usize,
}

impl Decode for Decoder {
    fn reconstruct(&self, g: &Gbtf, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        let c = self.c;
        let r = (view * g.header.lights_deg.len() + light) * 3;
        Ok(basis_times_rows(&g.blocks[0], &g.blocks[1][r * c..(r + 3) * c], c))
    }
}
