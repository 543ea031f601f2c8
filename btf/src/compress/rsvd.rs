//! The streamed randomized SVD (Halko, Martinsson, Tropp 2011) that PCA ([`super::pca`])
//! and DFMF ([`super::dfmf`]) share, written as **passes over a range of views** so that
//! one process can run all of them, or N processes (`--shard I/N`) can each run one pass
//! over their own views and a merge can put the pass back together.
//!
//! Each method hands over one or more *channels* (PCA: the `texels × (lights · 3)` view
//! matrix; DFMF: three `texels × lights` colour-channel matrices), and per channel a
//! sketch width `k` and the Gaussian sketch Ω. With `A = [A_0 … A_{V−1}]` (view blocks of
//! columns), the passes are:
//!
//! | pass | computes | a shard's part | merge |
//! |---|---|---|---|
//! | 0 | `Y = Σ_v A_v Ω_v` | the exact partial sum over its views | exact sum of the parts |
//! | 1 … p | `Y = Σ_v A_v (A_vᵀ Q)`, `Q = orth(Y_prev)` | the same | the same |
//! | p + 1 | `B_v = Qᵀ A_v`, `Q = orth(Y_p)` | its views' columns of B | columns in view order |
//!
//! after which the method takes the SVD of the small `k × n` matrix B. The sums over
//! views are **exact** ([`super::exact::ExactMat`]), so they do not depend on how the
//! views were grouped: a merged sharded run gives the single-process factors bit for bit,
//! and both give the same bits at any thread count. A view's own products are computed
//! by the same code in both cases.

use super::error::CompressError;
use super::exact::ExactMat;
use super::linalg::{orthonormalize, GaussianSketch};
use faer::{Mat, MatRef};
use std::ops::Range;

/// One channel of the factorization.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Channel {
    /// Rows of the channel's matrix (PCA, DFMF: the texels; local PCA's clusters: their
    /// members).
    pub rows: usize,
    /// Sketch width (components + oversampling, at most the matrix's smaller side).
    pub k: usize,
    /// Ω, row `v · width + j` for column `j` of view `v`.
    pub sketch: GaussianSketch,
}

/// The shape of the problem: what every pass and every shard must agree on.
#[derive(Clone, Debug, PartialEq)]
pub struct Rsvd {
    pub channels: Vec<Channel>,
    /// Columns per view of every channel matrix.
    pub width: usize,
    pub views: usize,
    pub power_iters: usize,
}

/// Where the views' channel matrices come from (a dataset, with or without a cache).
pub trait ViewSource {
    /// Call `f` with the channel matrices of view `v` (one per [`Channel`], each
    /// `channel.rows × width`).
    fn with_view(&mut self, v: usize, f: &mut dyn FnMut(&[MatRef<'_, f64>])) -> Result<(), CompressError>;
}

/// Per channel `Q` (orthonormal, rows × k) and `B = Qᵀ A` (k × columns).
pub type Bases = (Vec<Mat<f64>>, Vec<Mat<f64>>);

/// What one pass over a range of views gives.
#[derive(Clone, Debug, PartialEq)]
pub enum PassOutput {
    /// Passes `0..=power_iters`: per channel the exact partial sum of Y (`rows × k`).
    Sums(Vec<ExactMat>),
    /// The last pass: per channel the columns of B of the range's views
    /// (`k × width · views in the range`).
    Projection(Vec<Mat<f64>>),
}

impl Rsvd {
    /// Passes over the data: the range sketch, the power iterations, the projection.
    pub fn passes(&self) -> usize {
        self.power_iters + 2
    }

    /// Whether `pass` is the last (projection) pass.
    pub fn is_projection(&self, pass: usize) -> bool {
        pass == self.power_iters + 1
    }

    /// Run `pass` over `views`. `q` holds, for every pass after the first, the
    /// orthonormal bases `Q = orth(Y)` of the previous pass (one per channel).
    pub fn run_pass(
        &self,
        pass: usize,
        views: Range<usize>,
        q: Option<&[Mat<f64>]>,
        src: &mut dyn ViewSource,
    ) -> Result<PassOutput, CompressError> {
        if pass >= self.passes() || views.end > self.views {
            return Err(CompressError::Invalid(format!(
                "randomized SVD pass {pass} of {} over views {views:?} of {}",
                self.passes(),
                self.views
            )));
        }
        let (w, nc) = (self.width, self.channels.len());
        let q = match (pass, q) {
            (0, _) => None,
            (_, Some(q)) if q.len() == nc => Some(q),
            _ => {
                return Err(CompressError::Invalid(format!(
                    "randomized SVD pass {pass} needs the {nc} bases of the previous pass"
                )))
            }
        };
        if self.is_projection(pass) {
            let qs = q.expect("checked above");
            let mut b: Vec<Mat<f64>> = qs.iter().map(|q| Mat::zeros(q.ncols(), w * views.len())).collect();
            for v in views.clone() {
                let off = (v - views.start) * w;
                src.with_view(v, &mut |a| {
                    for ch in 0..nc {
                        let bv = qs[ch].transpose() * a[ch];
                        b[ch].as_mut().subcols_mut(off, w).copy_from(&bv);
                    }
                })?;
            }
            return Ok(PassOutput::Projection(b));
        }
        let mut sums: Vec<ExactMat> = self.channels.iter().map(|c| ExactMat::zeros(c.rows, c.k)).collect();
        for v in views {
            let mut err = None;
            src.with_view(v, &mut |a| {
                for ch in 0..nc {
                    let term = match q {
                        None => {
                            let omega = self.channels[ch].sketch.block(v * w, w, self.channels[ch].k);
                            a[ch] * &omega
                        }
                        Some(q) => {
                            let z = a[ch].transpose() * &q[ch];
                            a[ch] * &z
                        }
                    };
                    if let Err(e) = sums[ch].add(term.as_ref(), &format!("view {v}, channel {ch}, pass {pass}")) {
                        err.get_or_insert(e);
                    }
                }
            })?;
            if let Some(e) = err {
                return Err(e);
            }
        }
        Ok(PassOutput::Sums(sums))
    }

    /// All passes over all views in one process: per channel `Q` (rows × k, orthonormal)
    /// and `B = Qᵀ A` (k × width · views).
    pub fn run_all(&self, src: &mut dyn ViewSource) -> Result<Bases, CompressError> {
        let mut q: Option<Vec<Mat<f64>>> = None;
        for pass in 0..self.passes() {
            match self.run_pass(pass, 0..self.views, q.as_deref(), src)? {
                PassOutput::Sums(s) => q = Some(bases(&s)),
                PassOutput::Projection(b) => return Ok((q.expect("after the sums"), b)),
            }
        }
        unreachable!("the last pass is the projection")
    }
}

/// `Q = orth(Y)` of every channel's sum: what the pass after a sum pass starts from.
pub fn bases(sums: &[ExactMat]) -> Vec<Mat<f64>> {
    sums.iter().map(|s| orthonormalize(&s.to_mat())).collect()
}
