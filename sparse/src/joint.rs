//! Joint completion across texels: empirical Bayes for a material-specific Gaussian in the
//! prior's coefficient space.
//!
//! Why jointly: the generic prior `a ~ N(0, Λ)` describes every material the family can
//! make; one sample uses a small part of it. All texels of a sample share that part (the
//! same few materials under different normals and shadows), so the texels' measured pairs
//! together say which directions of the coefficient space this material occupies — and how
//! far, which the per-texel ridge cannot know: it shrinks a direction that the generic
//! prior rates rare even when every texel of this sample needs it.
//!
//! Model: `y_t = μ_S + U_S a_t + n`, `a_t ~ N(m, C)`, `n ~ N(0, σ²)`, every texel-channel t
//! measured at the same pairs S. EM for (m, C, σ²) with the generic prior as a conjugate
//! hyperprior (normal–inverse-Wishart centred on `(0, Λ)` with `ν` pseudo-texels, so a
//! direction the data do not determine falls back to the generic prior and `C` stays
//! positive definite):
//!
//! * E: `Σ = (C⁻¹ + U_SᵀU_S/σ²)⁻¹` (shared by all texels), `â_t = Σ (U_Sᵀ(y_t − μ_S)/σ² + C⁻¹m)`;
//! * M: `m = Σ_t â_t / (M + ν)`,
//!   `C = (Σ_t (â_t − m)(â_t − m)ᵀ + M Σ + ν Λ) / (M + ν)`,
//!   `σ² = (Σ_t ‖y_t − μ_S − U_S â_t‖² + M tr(U_SᵀU_S Σ)) / (M S)`.
//!
//! The result is a [`Completion`] with the learned Gaussian: each texel's posterior mean
//! and the shared posterior covariance, so prediction, predicted error and the held-back
//! check work as for the per-texel prior. The fit uses up to `fit_columns` evenly spread
//! texel-channels (the Gaussian has K + K(K+1)/2 parameters; a few thousand texels pin it
//! down) and is then applied to every texel. Sums over texels run in fixed chunks added
//! in order: the same bytes at any thread count.

use crate::complete::Completion;
use crate::{Prior, SparseError};
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;
use serde::Serialize;

/// Options of the joint fit.
#[derive(Clone, Debug, Serialize)]
pub struct JointOptions {
    /// EM iterations at most.
    pub iterations: usize,
    /// Stop when the relative change of σ² and of tr(C) is below this.
    pub tolerance: f64,
    /// Weight of the generic prior, in pseudo-texels (ν); None: K, one pseudo-texel per
    /// component (weak next to thousands of texels, enough to keep every direction the
    /// measured pairs do not reach at the generic prior).
    pub prior_weight: Option<f64>,
    /// Texel-channels the Gaussian is fitted on (evenly spread), at most.
    pub fit_columns: usize,
}

impl Default for JointOptions {
    fn default() -> Self {
        JointOptions {
            iterations: 50,
            tolerance: 1e-4,
            prior_weight: None,
            fit_columns: 12_288,
        }
    }
}

/// What the fit found (reported by `gonio complete` and the bench).
#[derive(Clone, Debug, Serialize)]
pub struct JointReport {
    pub iterations: usize,
    pub fitted_columns: usize,
    /// ν used (pseudo-texels of the generic prior).
    pub prior_weight: f64,
    /// σ² the data gave (model space): noise plus what the basis misses at measured pairs.
    pub noise_var: f64,
    /// Effective dimension of the material's Gaussian, `tr(C)² / tr(C²)`.
    pub effective_dims: f64,
    /// Share of the generic prior's variance the material's Gaussian keeps, `tr(C) / tr(Λ)`.
    pub variance_share: f64,
}

const CHUNK: usize = 1024;

/// Evenly spread column indices, `n` of `m` (all when `n >= m`).
fn spread(m: usize, n: usize) -> Vec<usize> {
    if n >= m {
        return (0..m).collect();
    }
    (0..n).map(|i| i * m / n).collect()
}

fn chol_inverse(m: &DMatrix<f64>, what: &str) -> Result<DMatrix<f64>, SparseError> {
    m.clone()
        .cholesky()
        .map(|c| c.inverse())
        .ok_or_else(|| SparseError::Refused(format!("joint fit: {what} is not positive definite")))
}

/// Fit the material's Gaussian from every texel's measured values and return the completion
/// operator under it. `y` is S × M (model space, rows in the order of `measured`);
/// `noise_floor` is the smallest σ² accepted (model space).
pub fn fit<'a>(
    prior: &'a Prior,
    measured: &[usize],
    y: &DMatrix<f64>,
    noise_floor: f64,
    opts: &JointOptions,
) -> Result<(Completion<'a>, JointReport), SparseError> {
    crate::complete::check_design(prior, measured)?;
    let (k, s) = (prior.components(), measured.len());
    if y.nrows() != s || y.ncols() == 0 {
        return Err(SparseError::Invalid(format!(
            "joint fit: {} × {} values for {s} measured pairs",
            y.nrows(),
            y.ncols()
        )));
    }
    let cols = spread(y.ncols(), opts.fit_columns.max(1));
    let m = cols.len();
    let us = DMatrix::<f64>::from_fn(s, k, |i, j| prior.basis[(measured[i], j)]);
    let g = us.transpose() * &us;
    // Z = U_Sᵀ (y − μ_S) and ‖y − μ_S‖² per fitted column, in fixed chunks.
    let centred = |c: usize| -> DVector<f64> {
        DVector::from_fn(s, |i, _| {
            let v = y[(i, c)];
            if v.is_finite() {
                v - prior.mean[measured[i]]
            } else {
                0.0
            }
        })
    };
    let parts: Vec<(DMatrix<f64>, f64)> = cols
        .par_chunks(CHUNK)
        .map(|ch| {
            let mut yc = DMatrix::<f64>::zeros(s, ch.len());
            for (j, &c) in ch.iter().enumerate() {
                yc.set_column(j, &centred(c));
            }
            let yy = yc.iter().map(|v| v * v).sum::<f64>();
            (us.transpose() * yc, yy)
        })
        .collect();
    let mut z = DMatrix::<f64>::zeros(k, m);
    let mut yy = 0.0;
    for (ci, (zc, q)) in parts.iter().enumerate() {
        z.columns_mut(ci * CHUNK, zc.ncols()).copy_from(zc);
        yy += q;
    }
    let lambda = DMatrix::<f64>::from_diagonal(&DVector::from_vec(prior.variances.clone()));
    let nu = opts.prior_weight.unwrap_or(k as f64).max(0.0);
    let mut mean = DVector::<f64>::zeros(k);
    let mut cov = lambda.clone();
    let mut sigma2 = (prior.header.residual_var).max(noise_floor).max(1e-12);
    let mut it = 0;
    while it < opts.iterations.max(1) {
        it += 1;
        let cinv = chol_inverse(&cov, "the material covariance")?;
        let p = &cinv + &g / sigma2;
        let post = chol_inverse(&p, "the posterior precision")?;
        let bias = &post * (&cinv * &mean);
        let gain = &post / sigma2;
        // â = gain · z + bias; sums of â, ââᵀ and of the residual terms, per chunk.
        let stats: Vec<(DVector<f64>, DMatrix<f64>, f64)> = (0..m.div_ceil(CHUNK))
            .into_par_iter()
            .map(|ci| {
                let (a0, b0) = (ci * CHUNK, ((ci + 1) * CHUNK).min(m));
                let zc = z.columns(a0, b0 - a0);
                let mut a = &gain * zc;
                for mut col in a.column_iter_mut() {
                    col += &bias;
                }
                let sum = a.column_sum();
                let outer = &a * a.transpose();
                // Σ_t (−2 âᵀz + âᵀ G â)
                let ga = &g * &a;
                let mut r = 0.0;
                for j in 0..a.ncols() {
                    r += -2.0 * a.column(j).dot(&zc.column(j)) + a.column(j).dot(&ga.column(j));
                }
                (sum, outer, r)
            })
            .collect();
        let mut sum = DVector::<f64>::zeros(k);
        let mut outer = DMatrix::<f64>::zeros(k, k);
        let mut resid = yy;
        for (a, o, r) in &stats {
            sum += a;
            outer += o;
            resid += r;
        }
        let new_mean = &sum / (m as f64 + nu);
        // Σ_t (â_t − m)(â_t − m)ᵀ = Σ ââᵀ − m sᵀ − s mᵀ + M m mᵀ
        let scatter = &outer - &new_mean * sum.transpose() - &sum * new_mean.transpose()
            + &new_mean * new_mean.transpose() * m as f64;
        let mut new_cov = (scatter + &post * m as f64 + &lambda * nu) / (m as f64 + nu);
        new_cov = (&new_cov + new_cov.transpose()) * 0.5;
        // Keep C positive definite: a floor far below the prior's smallest variance.
        let floor = prior.variances.iter().cloned().fold(f64::MAX, f64::min) * 1e-6;
        for j in 0..k {
            new_cov[(j, j)] += floor;
        }
        let tr_gp = (&g * &post).trace();
        let new_sigma2 = ((resid + m as f64 * tr_gp) / (m as f64 * s as f64))
            .max(noise_floor)
            .max(1e-12);
        let change = ((new_sigma2 - sigma2).abs() / sigma2).max((new_cov.trace() - cov.trace()).abs() / cov.trace());
        mean = new_mean;
        cov = new_cov;
        sigma2 = new_sigma2;
        if change < opts.tolerance {
            break;
        }
    }
    let c = Completion::with_gaussian(prior, measured, &mean, &cov, sigma2)?;
    let tr = cov.trace();
    let tr2 = (&cov * &cov).trace();
    let report = JointReport {
        iterations: it,
        fitted_columns: m,
        prior_weight: nu,
        noise_var: sigma2,
        effective_dims: tr * tr / tr2.max(1e-300),
        variance_share: tr / prior.variances.iter().sum::<f64>(),
    };
    Ok((c, report))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prior::tests::toy;

    /// A material that uses a direction of the generic prior's span the prior rates rare:
    /// the per-texel MAP shrinks it, the joint fit learns it and completes far better.
    #[test]
    fn joint_fit_learns_the_materials_directions() {
        let (meta, rows) = toy(9, 600, 8, 11);
        let p = Prior::learn(meta, &rows, 8, 1).unwrap();
        let d = 81;
        // Texels along the prior's weakest components, far beyond their prior variance.
        let mut rng = crate::Normal::new(5);
        let n = 300;
        let scale = p.variances[7].sqrt() * 30.0;
        let coef: Vec<[f64; 2]> = (0..n).map(|_| [rng.sample() * scale, rng.sample() * scale]).collect();
        let truth = DMatrix::from_fn(d, n, |q, t| {
            p.mean[q] + p.basis[(q, 6)] * coef[t][0] + p.basis[(q, 7)] * coef[t][1]
        });
        let measured: Vec<usize> = (0..d).step_by(7).collect();
        let y = truth.select_rows(&measured);
        let nv = 1e-6;
        let per = Completion::new(&p, &measured, nv).unwrap();
        let err_per = (&per.predict_all(&per.coefficients(&y)) - &truth).norm();
        let (joint, rep) = fit(&p, &measured, &y, nv, &JointOptions::default()).unwrap();
        let full = joint.predict_all(&joint.coefficients(&y));
        let err_joint = (&full - &truth).norm();
        assert!(
            err_joint < 0.5 * err_per,
            "joint {err_joint} per texel {err_per} ({rep:?})"
        );
        assert!(full.iter().all(|v| v.is_finite()));
        assert!(rep.effective_dims < 4.0, "{rep:?}");
        // Same bytes whatever the chunking of rayon's pool: run it again on one thread.
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let (j1, _) = pool.install(|| fit(&p, &measured, &y, nv, &JointOptions::default()).unwrap());
        assert_eq!(j1.coefficients(&y), joint.coefficients(&y));
    }

    #[test]
    fn black_and_constant_texels_stay_finite() {
        let (meta, rows) = toy(6, 200, 4, 12);
        let p = Prior::learn(meta, &rows, 5, 1).unwrap();
        let measured: Vec<usize> = (0..36).step_by(3).collect();
        let y = DMatrix::<f64>::zeros(measured.len(), 40);
        let (c, _) = fit(&p, &measured, &y, 1e-8, &JointOptions::default()).unwrap();
        assert!(c.predict_all(&c.coefficients(&y)).iter().all(|v| v.is_finite()));
    }
}
