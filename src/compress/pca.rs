//! Full-matrix PCA: one rank-`c` factorization of the whole `texels × (measurements · 3)`
//! matrix by a randomized SVD that streams the views (see the module docs of [`super`]).
//! Stored blocks (`.gbtf`, f32): `us` (texels × c) and `v` (views·lights·3 × c), row
//! `(view · lights + light) · 3 + channel`.

use super::container::{BlockInfo, Gbtf};
use super::data::{DatasetViews, ViewMatrix};
use super::error::CompressError;
use super::linalg::{orthonormalize, row_major_f32, truncated_svd, GaussianSketch, SketchKeying};
use super::params::{header_for, EncodeInfo, Params};
use faer::{Mat, MatRef};

fn to_faer(v: &ViewMatrix) -> Mat<f64> {
    Mat::from_fn(v.rows, v.cols, |i, j| v.data[i * v.cols + j] as f64)
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

pub fn compress(ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
    let c = params.components;
    let (t, lc) = (ds.texels(), ds.n_lights() * 3);
    let n = lc * ds.n_views();
    let k = (c + params.oversample).min(t).min(n);
    let mut cache = ViewCache::new(ds, PCA_CACHE_BYTES);
    let sketch = GaussianSketch::new(params.seed, SketchKeying::Hashed);

    // Y = A Ω, Ω Gaussian (n × k), generated per view block.
    let mut y = Mat::<f64>::zeros(t, k);
    cache.pass(|v, a| {
        let omega = sketch.block(v * lc, lc, k);
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
    let infos = vec![BlockInfo::new("us", t, c), BlockInfo::new("v", n, c)];
    let blocks = vec![row_major_f32(us.as_ref()), row_major_f32(vv.as_ref())];
    let info = EncodeInfo {
        filled: cache.filled.len(),
        passes: cache.passes,
        ..Default::default()
    };
    let header = header_for(ds, params, std::mem::take(&mut cache.filled), infos);
    Ok((Gbtf { header, blocks }, info))
}
