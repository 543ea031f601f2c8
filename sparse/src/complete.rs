//! Completion: predict every pair of a texel's ABRDF from its measured pairs.
//!
//! Per texel and channel, the MAP estimate of the coefficients under the prior is ridge
//! regression with the prior's eigenvalues:
//! `â = (U_SᵀU_S + σ² Λ⁻¹)⁻¹ U_Sᵀ (y_S − μ_S)`, then `x̂ = μ + U â` for every pair.
//! Every texel measured the same pairs, so the K × S operator is factored once and applied
//! to all texels as one matrix product; each texel still uses every one of its measured
//! pairs. Texels are independent given the prior (the prior is angular; neighbouring texels
//! share no coefficients), which keeps the result exact per texel, parallel and
//! independent of the image size. Ridge also makes the answer defined for any data: a
//! black or saturated texel gets a bounded estimate, never NaN.
//!
//! The posterior covariance `Σ = σ² (U_SᵀU_S + σ²Λ⁻¹)⁻¹` gives each unmeasured pair its
//! predicted error `u_pᵀ Σ u_p + ρ`.

use crate::{Prior, SparseError};
use nalgebra::{DMatrix, DVector};
use serde::Serialize;

/// How well the measured pairs pin down the coefficients.
#[derive(Clone, Debug, Serialize)]
pub struct Conditioning {
    pub measured_pairs: usize,
    pub components: usize,
    /// Condition number of the MAP normal matrix `U_SᵀU_S + σ²Λ⁻¹` (what is solved).
    pub map_condition: f64,
    /// Condition number of `U_SᵀU_S` alone (plain least squares; infinite when singular).
    pub least_squares_condition: f64,
}

/// The measured set's reconstruction operator.
pub struct Completion<'a> {
    pub prior: &'a Prior,
    pub measured: Vec<usize>,
    pub noise_var: f64,
    /// K × S.
    w: DMatrix<f64>,
    /// K × K posterior covariance.
    post: DMatrix<f64>,
    /// K: added to every texel's coefficients (`m − W U_S m` for a prior mean m ≠ 0).
    offset: DVector<f64>,
    /// For [`Self::log_evidence`], set by the per-pair builds: each measured pair's total
    /// variance σ_s² and `log det C` of the measured values' covariance
    /// `C = U_S Λ U_Sᵀ + diag(σ_s²)` (by the determinant lemma:
    /// `Σ log σ_s² + Σ log λ_j + log det(U_SᵀDU_S + Λ⁻¹)`).
    evidence: Option<(Vec<f64>, f64)>,
    pub conditioning: Conditioning,
}

/// Refuse designs the prior cannot complete: more components than pairs, or every pair at
/// one light or one view.
pub fn check_design(prior: &Prior, measured: &[usize]) -> Result<(), SparseError> {
    let (k, s) = (prior.components(), measured.len());
    if s == 0 {
        return Err(SparseError::Refused("no measured pairs".into()));
    }
    if k > s {
        return Err(SparseError::Refused(format!(
            "the prior has {k} components but only {s} pairs are measured: measure at least {k} \
             pairs, or use fewer components (--components)"
        )));
    }
    let l = prior.header.lights;
    if s > 1 {
        let one_light = measured.iter().all(|&p| p % l == measured[0] % l);
        let one_view = measured.iter().all(|&p| p / l == measured[0] / l);
        if one_light || one_view {
            return Err(SparseError::Refused(format!(
                "degenerate design: all {s} measured pairs share one {} ({}), so the other {} \
                 is never varied",
                if one_light { "light" } else { "view" },
                if one_light { measured[0] % l } else { measured[0] / l },
                if one_light { "light" } else { "view" }
            )));
        }
    }
    if let Some(&bad) = measured.iter().find(|&&p| p >= prior.dims()) {
        return Err(SparseError::Invalid(format!(
            "pair {bad} outside the sweep's {} pairs",
            prior.dims()
        )));
    }
    Ok(())
}

fn condition(m: &DMatrix<f64>) -> f64 {
    let e = m.clone().symmetric_eigen().eigenvalues;
    let max = e.iter().cloned().fold(f64::MIN, f64::max);
    let min = e.iter().cloned().fold(f64::MAX, f64::min);
    if min <= max * 1e-15 {
        f64::INFINITY
    } else {
        max / min
    }
}

impl<'a> Completion<'a> {
    /// MAP completion from `measured` (canonical pair indices) with noise variance σ²
    /// (model space; the prior's residual variance is a good floor).
    pub fn new(prior: &'a Prior, measured: &[usize], noise_var: f64) -> Result<Self, SparseError> {
        Self::build(prior, measured, noise_var, false)
    }

    /// Plain least squares in the prior's basis (no eigenvalues): baseline (c).
    pub fn least_squares(prior: &'a Prior, measured: &[usize]) -> Result<Self, SparseError> {
        Self::build(prior, measured, 0.0, true)
    }

    /// MAP completion under a Gaussian `a ~ N(mean, cov)` in the prior's coefficient space
    /// instead of `N(0, Λ)` (the material's own Gaussian from [`crate::joint::fit`]).
    pub fn with_gaussian(
        prior: &'a Prior,
        measured: &[usize],
        mean: &DVector<f64>,
        cov: &DMatrix<f64>,
        noise_var: f64,
    ) -> Result<Self, SparseError> {
        let k = prior.components();
        if mean.len() != k || cov.nrows() != k || cov.ncols() != k {
            return Err(SparseError::Invalid(format!(
                "a Gaussian of {} coefficients for a prior of {k} components",
                mean.len()
            )));
        }
        let cinv = cov
            .clone()
            .cholesky()
            .ok_or_else(|| SparseError::Refused("the coefficient covariance is not positive definite".into()))?
            .inverse();
        let mut c = Self::build_with(prior, measured, noise_var, |p, s2| *p += cinv * s2)?;
        let us = DMatrix::<f64>::from_fn(measured.len(), k, |i, j| prior.basis[(measured[i], j)]);
        c.offset = mean - &c.w * (us * mean);
        Ok(c)
    }

    fn build(prior: &'a Prior, measured: &[usize], noise_var: f64, plain: bool) -> Result<Self, SparseError> {
        if plain {
            return Self::build_plain(prior, measured);
        }
        if prior.pair_residual_var.is_some() {
            return Self::build_per_pair(prior, measured, noise_var);
        }
        Self::build_with(prior, measured, noise_var, |p, s2| {
            for j in 0..prior.components() {
                p[(j, j)] += s2 / prior.variances[j];
            }
        })
    }

    fn build_plain(prior: &'a Prior, measured: &[usize]) -> Result<Self, SparseError> {
        check_design(prior, measured)?;
        let k = prior.components();
        let s = measured.len();
        let us = DMatrix::<f64>::from_fn(s, k, |i, j| prior.basis[(measured[i], j)]);
        let ls_cond = condition(&(us.transpose() * &us));
        let svd = us.svd(true, true);
        let w = svd
            .pseudo_inverse(1e-10)
            .map_err(|e| SparseError::Invalid(e.to_string()))?;
        Self::finish(prior, measured, 0.0, w, DMatrix::zeros(k, k), ls_cond, ls_cond)
    }

    /// MAP with each measured pair's own noise variance σ_s² (measurement noise plus the
    /// prior's ρ at that pair, [`Prior::pair_noise_var`]): with `D = diag(1/σ_s²)`,
    /// `â = (U_SᵀDU_S + Λ⁻¹)⁻¹ U_SᵀD (y_S − μ_S)` and `Σ = (U_SᵀDU_S + Λ⁻¹)⁻¹`. A pair where
    /// the basis is known to miss much (a specular peak) then pulls the coefficients less
    /// than one where it fits well; with equal σ_s² this is the plain MAP.
    fn build_per_pair(prior: &'a Prior, measured: &[usize], noise_var: f64) -> Result<Self, SparseError> {
        let var: Vec<f64> = measured.iter().map(|&p| prior.pair_noise_var(p, noise_var)).collect();
        Self::build_weighted(prior, measured, &var, noise_var)
    }

    /// MAP with a measurement noise variance of its own at each measured pair (model
    /// space, in the order of `measured`), on top of the variance the prior's basis leaves
    /// out there (ρ_p, or ρ): `σ_s² = noise_s + ρ_s`. This is how a sensor's noise enters:
    /// shot noise grows with the signal and the value space's curve stretches the dark end
    /// ([`crate::noise`]), so a dark pair is far noisier in the model than a bright one, and
    /// a constant σ² would either trust the dark pairs' noise or throw away the bright
    /// pairs' detail.
    pub fn with_pair_noise(prior: &'a Prior, measured: &[usize], noise: &[f64]) -> Result<Self, SparseError> {
        if noise.len() != measured.len() {
            return Err(SparseError::Invalid(format!(
                "{} noise variances for {} measured pairs",
                noise.len(),
                measured.len()
            )));
        }
        if let Some(bad) = noise.iter().position(|v| !v.is_finite() || *v < 0.0) {
            return Err(SparseError::Invalid(format!(
                "the noise variance of measured pair {} is {} (must be finite and ≥ 0)",
                measured[bad], noise[bad]
            )));
        }
        let var: Vec<f64> = measured
            .iter()
            .zip(noise)
            .map(|(&p, &n)| (n + prior.pair_residual(p)).max(1e-12))
            .collect();
        let mean = noise.iter().sum::<f64>() / noise.len().max(1) as f64 + prior.header.residual_var;
        Self::build_weighted(prior, measured, &var, mean)
    }

    /// MAP with each measured pair's own variance `var[i]` (model space, in the order of
    /// `measured`): with `D = diag(1/σ_s²)`, `â = (U_SᵀDU_S + Λ⁻¹)⁻¹ U_SᵀD (y_S − μ_S)` and
    /// `Σ = (U_SᵀDU_S + Λ⁻¹)⁻¹`. `noise_var` is the overall figure the completion reports.
    fn build_weighted(prior: &'a Prior, measured: &[usize], var: &[f64], noise_var: f64) -> Result<Self, SparseError> {
        check_design(prior, measured)?;
        let k = prior.components();
        let s = measured.len();
        let sd: Vec<f64> = var.iter().map(|v| v.max(1e-12).sqrt()).collect();
        let us = DMatrix::<f64>::from_fn(s, k, |i, j| prior.basis[(measured[i], j)]);
        let ls_cond = condition(&(us.transpose() * &us));
        let white = DMatrix::<f64>::from_fn(s, k, |i, j| us[(i, j)] / sd[i]);
        let mut p = white.transpose() * &white;
        for j in 0..k {
            p[(j, j)] += 1.0 / prior.variances[j];
        }
        let cond = condition(&p);
        let chol = p.cholesky().ok_or_else(|| {
            SparseError::Refused(format!(
                "the MAP system is not positive definite (condition {cond:.3e})"
            ))
        })?;
        let mut w = chol.solve(&white.transpose());
        for (i, mut col) in w.column_iter_mut().enumerate() {
            col /= sd[i];
        }
        let log_det = var.iter().map(|v| v.max(1e-12).ln()).sum::<f64>()
            + prior.variances.iter().map(|l| l.ln()).sum::<f64>()
            + 2.0 * chol.l_dirty().diagonal().iter().map(|d| d.ln()).sum::<f64>();
        let post = chol.inverse();
        let mut c = Self::finish(prior, measured, noise_var, w, post, cond, ls_cond)?;
        c.evidence = Some((var.iter().map(|v| v.max(1e-12)).collect(), log_det));
        Ok(c)
    }

    /// MAP: `(U_SᵀU_S + σ² C⁻¹)`, where `regularize(p, σ²)` adds `σ² C⁻¹` to `p`.
    fn build_with(
        prior: &'a Prior,
        measured: &[usize],
        noise_var: f64,
        regularize: impl FnOnce(&mut DMatrix<f64>, f64),
    ) -> Result<Self, SparseError> {
        check_design(prior, measured)?;
        let k = prior.components();
        let s = measured.len();
        let us = DMatrix::<f64>::from_fn(s, k, |i, j| prior.basis[(measured[i], j)]);
        let gram = us.transpose() * &us;
        let ls_cond = condition(&gram);
        let sigma2 = noise_var.max(1e-12);
        let mut p = gram;
        regularize(&mut p, sigma2);
        let cond = condition(&p);
        let chol = p.cholesky().ok_or_else(|| {
            SparseError::Refused(format!(
                "the MAP system is not positive definite (condition {cond:.3e})"
            ))
        })?;
        let w = chol.solve(&us.transpose());
        let post = chol.inverse() * sigma2;
        Self::finish(prior, measured, sigma2, w, post, cond, ls_cond)
    }

    fn finish(
        prior: &'a Prior,
        measured: &[usize],
        sigma2: f64,
        w: DMatrix<f64>,
        post: DMatrix<f64>,
        map_cond: f64,
        ls_cond: f64,
    ) -> Result<Self, SparseError> {
        if w.iter().any(|v| !v.is_finite()) {
            return Err(SparseError::Refused("the reconstruction operator is not finite".into()));
        }
        let k = prior.components();
        Ok(Completion {
            prior,
            measured: measured.to_vec(),
            noise_var: sigma2.max(1e-12),
            w,
            post,
            offset: DVector::zeros(k),
            evidence: None,
            conditioning: Conditioning {
                measured_pairs: measured.len(),
                components: k,
                map_condition: map_cond,
                least_squares_condition: ls_cond,
            },
        })
    }

    /// Coefficients for many texel-channels at once: `y` is S × M (model space, rows in
    /// the order of `measured`); returns K × M.
    pub fn coefficients(&self, y: &DMatrix<f64>) -> DMatrix<f64> {
        let mut c = y.clone();
        for (i, &p) in self.measured.iter().enumerate() {
            let m = self.prior.mean[p];
            c.row_mut(i).iter_mut().for_each(|v| {
                *v = if v.is_finite() { *v - m } else { 0.0 };
            });
        }
        let mut a = &self.w * c;
        for mut col in a.column_iter_mut() {
            col += &self.offset;
        }
        a
    }

    /// Coefficients when some readings were clipped at the sensor's full scale: a reading
    /// at or above `ceiling` (model space) says only that the value is *at least* that, and
    /// fitting it as the value would pull the whole texel's ABRDF down towards the clip
    /// (a specular peak flattened at full scale spreads its error over every predicted
    /// pair). Each clipped reading is replaced by the larger of the ceiling and the
    /// completion's own prediction there, and the coefficients are solved again, until
    /// nothing moves (at most `iterations` times): the fixed point is the censored MAP, in
    /// which a clipped reading whose prediction is above the clip exerts no pull and one
    /// whose prediction falls below it pulls it up to the clip. Columns without a clipped
    /// reading are as [`Self::coefficients`] gives them. Returns the coefficients and the
    /// number of clipped readings.
    pub fn coefficients_censored(&self, y: &DMatrix<f64>, ceiling: f64, iterations: usize) -> (DMatrix<f64>, usize) {
        let mut a = self.coefficients(y);
        let mut clipped = 0;
        for j in 0..y.ncols() {
            if let Some((_, aj, n)) = self.censored_column(y, &a, j, ceiling, iterations) {
                a.set_column(j, &aj);
                clipped += n;
            }
        }
        (a, clipped)
    }

    /// The values the censored fit ([`Self::coefficients_censored`]) ends on: `y` with
    /// each clipped reading replaced by the larger of the ceiling and the fit's prediction
    /// there. A linear analysis of these values (leave-one-out residuals) treats a clipped
    /// reading as the lower bound it is: its residual is zero where the fit already
    /// predicts at least the clip, and the shortfall below the clip otherwise. Returns the
    /// values and the number of clipped readings.
    pub fn impute_censored(&self, y: &DMatrix<f64>, ceiling: f64, iterations: usize) -> (DMatrix<f64>, usize) {
        let a = self.coefficients(y);
        let mut out = y.clone();
        let mut clipped = 0;
        for j in 0..y.ncols() {
            if let Some((yj, _, n)) = self.censored_column(y, &a, j, ceiling, iterations) {
                out.set_column(j, &yj);
                clipped += n;
            }
        }
        (out, clipped)
    }

    /// Column `j`'s censored fixed point from the uncensored coefficients `a`: its imputed
    /// values, its coefficients and its number of clipped readings; `None` when nothing in
    /// the column is clipped.
    ///
    /// The coefficients are linear in the readings (`a = W (y − μ_S) + offset`), so only the
    /// `r` clipped readings move: with `W_R` the columns of `W` at them and `U_R` the basis
    /// at their pairs, a change `δ` of those readings moves the coefficients by `W_R δ` and
    /// the predictions there by `U_R W_R δ`. Each step of the fixed point is then an
    /// `r × r` product instead of a whole solve (the analysis between adaptive rounds runs
    /// it on every clipped texel-channel it reads).
    fn censored_column(
        &self,
        y: &DMatrix<f64>,
        a: &DMatrix<f64>,
        j: usize,
        ceiling: f64,
        iterations: usize,
    ) -> Option<(DVector<f64>, DVector<f64>, usize)> {
        let rows: Vec<usize> = (0..y.nrows()).filter(|&i| y[(i, j)] >= ceiling).collect();
        if rows.is_empty() {
            return None;
        }
        let k = self.prior.components();
        let w_r = self.w.select_columns(&rows);
        let u_r = DMatrix::from_fn(rows.len(), k, |t, c| self.prior.basis[(self.measured[rows[t]], c)]);
        let moves = &u_r * &w_r;
        let a0 = a.column(j).clone_owned();
        let mean = DVector::from_iterator(rows.len(), rows.iter().map(|&i| self.prior.mean[self.measured[i]]));
        let pred0 = &u_r * &a0 + mean;
        let y0 = DVector::from_iterator(rows.len(), rows.iter().map(|&i| y[(i, j)]));
        let mut yr = y0.clone();
        for _ in 0..iterations {
            let pred = &pred0 + &moves * (&yr - &y0);
            let mut moved = 0f64;
            for (v, p) in yr.iter_mut().zip(pred.iter()) {
                let next = p.max(ceiling);
                moved = moved.max((next - *v).abs());
                *v = next;
            }
            if moved <= 1e-9 * ceiling.abs().max(1.0) {
                break;
            }
        }
        let aj = a0 + &w_r * (&yr - &y0);
        let mut yj = y.column(j).clone_owned();
        for (t, &i) in rows.iter().enumerate() {
            yj[i] = yr[t];
        }
        Some((yj, aj, rows.len()))
    }

    /// Log marginal likelihood of each column of `y` (S × M, model space, rows in the order
    /// of `measured`) under this prior and the per-pair variances, given its coefficients
    /// `a` (from [`Self::coefficients`] or [`Self::coefficients_censored`]):
    /// `−½ (rᵀC⁻¹r + log det C + S log 2π)` with `r = y_S − μ_S`, where by Woodbury
    /// `rᵀC⁻¹r = rᵀD(r − U_S â)`. It is how well a prior explains a texel's readings, its
    /// span and its spread together: the evidence a mixture chooses its member by.
    /// Non-finite readings count as their prediction. Only for completions built with
    /// per-pair variances ([`Self::with_pair_noise`], or a prior with ρ_p).
    pub fn log_evidence(&self, y: &DMatrix<f64>, a: &DMatrix<f64>) -> Result<Vec<f64>, SparseError> {
        let (var, log_det) = self.evidence.as_ref().ok_or_else(|| {
            SparseError::Invalid("the evidence needs a completion built with per-pair variances".into())
        })?;
        if y.nrows() != self.measured.len() || a.ncols() != y.ncols() || a.nrows() != self.prior.components() {
            return Err(SparseError::Invalid(format!(
                "evidence of {} × {} values with {} × {} coefficients for {} pairs and {} components",
                y.nrows(),
                y.ncols(),
                a.nrows(),
                a.ncols(),
                self.measured.len(),
                self.prior.components()
            )));
        }
        let s = self.measured.len() as f64;
        let konst = log_det + s * (2.0 * std::f64::consts::PI).ln();
        Ok((0..y.ncols())
            .map(|j| {
                let mut quad = 0.0;
                for (i, &p) in self.measured.iter().enumerate() {
                    let fit = (self.prior.basis.row(p) * a.column(j))[(0, 0)];
                    let v = y[(i, j)];
                    let r = if v.is_finite() { v - self.prior.mean[p] } else { fit };
                    quad += r * (r - fit) / var[i];
                }
                -0.5 * (quad + konst)
            })
            .collect())
    }

    /// The leverage of each measured pair (diagonal of the hat matrix `U_S W`, in the order
    /// of `measured`): how much of its own value a pair's fit reproduces. With ridge it is
    /// below 1, so leave-one-out residuals `r / (1 − h)` stay finite.
    pub fn leverage(&self) -> Vec<f64> {
        let k = self.prior.components();
        self.measured
            .iter()
            .enumerate()
            .map(|(i, &p)| (0..k).map(|j| self.prior.basis[(p, j)] * self.w[(j, i)]).sum::<f64>())
            .collect()
    }

    /// Predicted model-space values of pair `p` for every column of `a` (K × M).
    pub fn predict_pair(&self, p: usize, a: &DMatrix<f64>) -> DVector<f64> {
        let u = self.prior.basis.row(p);
        let mut out = (u * a).transpose();
        out.add_scalar_mut(self.prior.mean[p]);
        out
    }

    /// Predicted values of every pair: D × M.
    pub fn predict_all(&self, a: &DMatrix<f64>) -> DMatrix<f64> {
        let mut out = &self.prior.basis * a;
        for (i, mut row) in out.row_iter_mut().enumerate() {
            row.add_scalar_mut(self.prior.mean[i]);
        }
        out
    }

    /// Predicted mean squared error of pair `p` (model space): posterior variance in the
    /// basis plus what the basis leaves out.
    pub fn predicted_var(&self, p: usize) -> f64 {
        let u = self.prior.basis.row(p).transpose();
        (u.transpose() * &self.post * &u)[(0, 0)].max(0.0) + self.prior.pair_residual(p)
    }

    /// Mean predicted squared error over every pair of the sweep (model space):
    /// `Σ_p u_pᵀ Σ u_p / D + ρ = tr(Σ) / D + ρ` (U orthonormal; ρ is also the mean of the
    /// per-pair residuals), the quantity the design
    /// minimizes (`design::Greedy::expected_mse`).
    pub fn predicted_mse(&self) -> f64 {
        self.post.trace().max(0.0) / self.prior.dims() as f64 + self.prior.header.residual_var
    }
}

/// The noise variance chosen from the data ([`loo_noise_var`]): the candidates tried and
/// each one's mean leave-one-out residual (model space).
#[derive(Clone, Debug, Serialize)]
pub struct NoiseChoice {
    pub noise_var: f64,
    pub tried: Vec<(f64, f64)>,
}

/// Candidates of [`loo_noise_var`]: the floor times 2^0 … 2^12 (σ from the floor's up to 64×).
pub const LOO_NOISE_STEPS: u32 = 12;

/// The MAP's noise variance σ² chosen by leave-one-out on the measured values (empirical
/// Bayes): of `floor · 2^i`, the one whose completion predicts each measured pair best
/// from the others (`r / (1 − h)`, exact for ridge, no refit).
///
/// Why: σ² weighs the prior against the data. The prior's own figure (its out-of-basis
/// variance from training) is what it achieves on its training materials; on a new
/// material its span misses more, and with as many components as pairs the MAP then
/// nearly interpolates the measured values and swings between them. Measured on a fresh
/// draw of the default prior's own family (32², 5 %): the prior's figure completes at
/// 29.8 dB, 2 codes of noise at 32.1 dB (docs/guide/sparse.md). `y` is S × M (model space,
/// rows in the order of `measured`), a spread sample of texel-channels.
pub fn loo_noise_var(
    prior: &Prior,
    measured: &[usize],
    y: &DMatrix<f64>,
    floor: f64,
) -> Result<NoiseChoice, SparseError> {
    check_design(prior, measured)?;
    if y.nrows() != measured.len() {
        return Err(SparseError::Invalid(format!(
            "{} rows of values for {} measured pairs",
            y.nrows(),
            measured.len()
        )));
    }
    let k = prior.components();
    let s = measured.len();
    let us = DMatrix::<f64>::from_fn(s, k, |i, j| prior.basis[(measured[i], j)]);
    let gram = us.transpose() * &us;
    let mut yc = y.clone();
    for (i, &p) in measured.iter().enumerate() {
        let m = prior.mean[p];
        yc.row_mut(i)
            .iter_mut()
            .for_each(|v| *v = if v.is_finite() { *v - m } else { 0.0 });
    }
    let floor = floor.max(1e-12);
    let mut tried = Vec::new();
    for i in 0..=LOO_NOISE_STEPS {
        let sigma2 = floor * f64::from(1u32 << i);
        let mut p = gram.clone();
        for j in 0..k {
            p[(j, j)] += sigma2 / prior.variances[j];
        }
        let Some(chol) = p.cholesky() else { continue };
        let w = chol.solve(&us.transpose()); // K × S
        let fit = &us * (&w * &yc); // S × M
        let mut sum = 0.0;
        for r in 0..s {
            let h = (0..k).map(|j| us[(r, j)] * w[(j, r)]).sum::<f64>();
            let scale = 1.0 / (1.0 - h).max(1e-3);
            for c in 0..yc.ncols() {
                let e = (yc[(r, c)] - fit[(r, c)]) * scale;
                sum += e * e;
            }
        }
        tried.push((sigma2, sum / (s * yc.ncols().max(1)) as f64));
    }
    let best = tried
        .iter()
        .copied()
        .filter(|t| t.1.is_finite())
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .ok_or_else(|| SparseError::Refused("no noise variance gave a finite leave-one-out residual".into()))?;
    Ok(NoiseChoice {
        noise_var: best.0,
        tried,
    })
}

/// The residual of a completion on measured pairs that were held back from it: a material
/// the prior does not describe (mirror, strong anisotropy) predicts its own held-back pairs
/// badly, and the observed error exceeds the predicted one.
#[derive(Clone, Debug, Serialize)]
pub struct Holdout {
    pub held_back: usize,
    /// RMS error on the held-back pairs (model space).
    pub observed_rms: f64,
    /// RMS error the posterior predicts there (model space, with the noise variance).
    pub predicted_rms: f64,
    /// observed / predicted.
    pub ratio: f64,
    /// The ratio above which the material is reported as outside the prior.
    pub limit: f64,
    pub outside_prior: bool,
}

pub const HOLDOUT_LIMIT: f64 = 2.0;

/// Fixed-point steps of the censored fit at most ([`Completion::coefficients_censored`]):
/// it settles in a few on clipped peaks.
pub const CENSORED_ITERATIONS: usize = 50;

/// Hold back every `stride`-th measured pair (at least one), complete from the rest, and
/// compare. `y` is S × M in the order of `measured`. None when too few pairs remain.
pub fn holdout_check(
    prior: &Prior,
    measured: &[usize],
    y: &DMatrix<f64>,
    noise_var: f64,
    stride: usize,
) -> Option<Holdout> {
    let stride = stride.max(2);
    let (keep, held): (Vec<usize>, Vec<usize>) = (0..measured.len()).partition(|i| i % stride != stride / 2);
    if held.is_empty() || keep.len() < prior.components() {
        return None;
    }
    let kept_pairs: Vec<usize> = keep.iter().map(|&i| measured[i]).collect();
    let c = Completion::new(prior, &kept_pairs, noise_var).ok()?;
    let yk = y.select_rows(&keep);
    let a = c.coefficients(&yk);
    let mut sq = 0.0;
    let mut pred = 0.0;
    let m = y.ncols();
    for &i in &held {
        let p = measured[i];
        let yp = c.predict_pair(p, &a);
        for j in 0..m {
            let d = y[(i, j)] - yp[j];
            sq += d * d;
        }
        pred += c.predicted_var(p) + noise_var;
    }
    let observed_rms = (sq / (held.len() * m) as f64).sqrt();
    let predicted_rms = (pred / held.len() as f64).sqrt();
    let ratio = observed_rms / predicted_rms.max(1e-12);
    Some(Holdout {
        held_back: held.len(),
        observed_rms,
        predicted_rms,
        ratio,
        limit: HOLDOUT_LIMIT,
        outside_prior: ratio > HOLDOUT_LIMIT,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::design::greedy_design;
    use crate::prior::tests::toy;
    use crate::ValueSpace;

    fn model_rows(rows: &[f32], d: usize, n: usize) -> DMatrix<f64> {
        // D × n, model space.
        DMatrix::from_fn(d, n, |p, t| ValueSpace::Gamma.forward(rows[t * d + p] as f64))
    }

    /// Leave-one-out finds the noise it was given: clean data choose a σ² near the floor,
    /// data with added noise of variance ν choose one within a factor 8 of ν (the grid's
    /// steps are ×2), and black data stay finite.
    #[test]
    fn leave_one_out_chooses_the_noise_variance_of_the_data() {
        let (meta, rows) = toy(9, 500, 5, 31);
        let p = Prior::learn(meta, &rows, 6, 1).unwrap();
        let d = 81;
        let (_, test) = toy(9, 60, 5, 32);
        let truth = model_rows(&test, d, 60);
        let floor = p.header.residual_var.max(1e-8);
        let cand: Vec<usize> = (0..d).collect();
        let design: Vec<usize> = greedy_design(&p, &cand, &[], 40, floor)
            .unwrap()
            .iter()
            .map(|s| s.pair)
            .collect();
        let clean = truth.select_rows(&design);
        let c = loo_noise_var(&p, &design, &clean, floor).unwrap();
        assert_eq!(c.tried.len(), LOO_NOISE_STEPS as usize + 1);
        assert!(
            c.noise_var <= 8.0 * floor,
            "clean data chose {} (floor {floor})",
            c.noise_var
        );
        let nu = 256.0 * floor;
        // Uniform noise of variance ν (±√(3ν)) from a splitmix hash of the entry's index.
        let uniform = |i: u64| {
            let mut z = i.wrapping_add(0x9e37_79b9_7f4a_7c15);
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut noisy = clean.clone();
        for (i, v) in noisy.iter_mut().enumerate() {
            *v += (uniform(i as u64) * 2.0 - 1.0) * (3.0 * nu).sqrt();
        }
        let c = loo_noise_var(&p, &design, &noisy, floor).unwrap();
        assert!(
            c.noise_var >= nu / 8.0 && c.noise_var <= 8.0 * nu,
            "noise {nu} chose {} ({:?})",
            c.noise_var,
            c.tried
        );
        let black = DMatrix::<f64>::zeros(design.len(), 6);
        assert!(loo_noise_var(&p, &design, &black, floor).unwrap().noise_var.is_finite());
        assert!(loo_noise_var(&p, &design, &black.rows(0, 3).into_owned(), floor).is_err());
    }

    #[test]
    fn per_pair_residuals_weigh_pairs_and_reduce_to_the_plain_map() {
        let (meta, rows) = toy(9, 500, 6, 5);
        let plain = Prior::learn(meta, &rows, 8, 1).unwrap();
        let d = 81;
        let (_, test) = toy(9, 20, 6, 99);
        let truth = model_rows(&test, d, 20);
        let design: Vec<usize> = (0..d).step_by(4).collect();
        let nv = plain.header.residual_var + 1e-6;
        // Equal per-pair residuals: the weighted MAP is the plain one.
        let mut equal = plain.clone();
        equal.pair_residual_var = Some(vec![plain.header.residual_var; d]);
        let (a, b) = (
            Completion::new(&plain, &design, nv).unwrap(),
            Completion::new(&equal, &design, nv).unwrap(),
        );
        let y = truth.select_rows(&design);
        let (fa, fb) = (a.predict_all(&a.coefficients(&y)), b.predict_all(&b.coefficients(&y)));
        assert!((&fa - &fb).amax() < 1e-9, "{}", (&fa - &fb).amax());
        assert!((a.predicted_var(3) - b.predicted_var(3)).abs() < 1e-12);
        // One pair declared unreliable (a large residual there, the mean kept): a gross error
        // on that pair's measurement moves the completion far less, and its own predicted
        // error is its residual.
        let bad = design[5];
        let mut uneven = vec![plain.header.residual_var * 0.5; d];
        uneven[bad] = plain.header.residual_var * 0.5 + 0.5 * d as f64 * plain.header.residual_var;
        let mut weighted = plain.clone();
        weighted.pair_residual_var = Some(uneven);
        let c = Completion::new(&weighted, &design, nv).unwrap();
        let mut y_bad = y.clone();
        y_bad.row_mut(5).add_scalar_mut(0.3);
        let shift =
            |c: &Completion| (c.predict_all(&c.coefficients(&y_bad)) - c.predict_all(&c.coefficients(&y))).norm();
        assert!(
            shift(&c) < 0.5 * shift(&a),
            "weighted {} plain {}",
            shift(&c),
            shift(&a)
        );
        assert!(c.predicted_var(bad) > a.predicted_var(bad));
        // The greedy design sees the same weights: it does not start at the unreliable pair.
        let cand: Vec<usize> = (0..d).collect();
        let first = greedy_design(&weighted, &cand, &[], 1, nv).unwrap()[0].pair;
        assert_ne!(first, bad);
        let same = greedy_design(&equal, &cand, &[], 12, nv).unwrap();
        assert_eq!(same, greedy_design(&plain, &cand, &[], 12, nv).unwrap());
    }

    #[test]
    fn map_completes_a_held_out_member_and_beats_least_squares() {
        let (meta, rows) = toy(9, 500, 6, 5);
        let p = Prior::learn(meta, &rows, 8, 1).unwrap();
        let d = 81;
        let (_, test) = toy(9, 20, 6, 99); // same model, other draws
        let truth = model_rows(&test, d, 20);
        let cand: Vec<usize> = (0..d).collect();
        let design: Vec<usize> = greedy_design(&p, &cand, &[], 12, p.header.residual_var + 1e-6)
            .unwrap()
            .iter()
            .map(|s| s.pair)
            .collect();
        let y = truth.select_rows(&design);
        let c = Completion::new(&p, &design, p.header.residual_var + 1e-6).unwrap();
        let a = c.coefficients(&y);
        let full = c.predict_all(&a);
        let err = (&full - &truth).norm() / (d as f64 * 20.0).sqrt();
        assert!(err < 0.01, "rms {err}");
        assert!(full.iter().all(|v| v.is_finite()));
        assert!(c.conditioning.map_condition.is_finite());
        // Black texels: finite.
        let zero = DMatrix::<f64>::zeros(design.len(), 1);
        assert!(c.predict_all(&c.coefficients(&zero)).iter().all(|v| v.is_finite()));
        // Plain least squares on as many random pairs is no better.
        let r = crate::random_subset(d, 12, 3);
        let ls = Completion::least_squares(&p, &r).unwrap();
        let full_ls = ls.predict_all(&ls.coefficients(&truth.select_rows(&r)));
        let err_ls = (&full_ls - &truth).norm() / (d as f64 * 20.0).sqrt();
        assert!(err <= err_ls, "map {err} ls {err_ls}");
    }

    #[test]
    fn refusals_name_the_reason() {
        let (meta, rows) = toy(6, 200, 4, 6);
        let p = Prior::learn(meta, &rows, 5, 1).unwrap();
        let e = Completion::new(&p, &[1, 8, 15], 1e-4).err().unwrap().to_string();
        assert!(e.contains("5 components") && e.contains("3 pairs"), "{e}");
        let one_view: Vec<usize> = (12..18).collect();
        let e = Completion::new(&p, &one_view, 1e-4).err().unwrap().to_string();
        assert!(e.contains("degenerate") && e.contains("view"), "{e}");
        let one_light: Vec<usize> = (0..6).map(|v| v * 6 + 2).collect();
        let e = Completion::new(&p, &one_light, 1e-4).err().unwrap().to_string();
        assert!(e.contains("degenerate") && e.contains("light"), "{e}");
    }

    #[test]
    fn holdout_flags_data_outside_the_prior() {
        let (meta, rows) = toy(9, 400, 4, 7);
        let p = Prior::learn(meta, &rows, 5, 1).unwrap();
        let d = 81;
        let measured: Vec<usize> = (0..d).step_by(2).collect();
        let (_, inside) = toy(9, 10, 4, 70);
        let y_in = model_rows(&inside, d, 10).select_rows(&measured);
        let nv = p.header.residual_var + 1e-6;
        let h = holdout_check(&p, &measured, &y_in, nv, 8).unwrap();
        assert!(!h.outside_prior, "{h:?}");
        // A "mirror": one bright pair per ABRDF at a random place.
        let mut y_out = DMatrix::<f64>::from_element(measured.len(), 10, 0.2);
        for j in 0..10 {
            y_out[((j * 7) % measured.len(), j)] = 1.0;
            y_out[((j * 7 + 4) % measured.len(), j)] = 0.9;
        }
        let h = holdout_check(&p, &measured, &y_out, nv, 4).unwrap();
        assert!(h.outside_prior, "{h:?}");
    }

    /// Readings clipped at full scale: fitted as values they drag the whole ABRDF down;
    /// as lower bounds (the censored fit) the completion comes back close to the fit of
    /// unclipped data, clipped readings whose prediction is above the clip are left there,
    /// and columns without clipped readings are untouched.
    #[test]
    fn clipped_readings_are_lower_bounds() {
        let (meta, rows) = toy(9, 500, 6, 5);
        let p = Prior::learn(meta, &rows, 8, 1).unwrap();
        let d = 81;
        let (_, test) = toy(9, 20, 6, 99);
        let truth = model_rows(&test, d, 20);
        let design: Vec<usize> = (0..d).step_by(3).collect();
        let c = Completion::new(&p, &design, p.header.residual_var + 1e-6).unwrap();
        let y = truth.select_rows(&design);
        // Clip at a level that cuts the brightest readings of most columns.
        let mut sorted: Vec<f64> = y.iter().copied().collect();
        sorted.sort_by(f64::total_cmp);
        let ceiling = sorted[sorted.len() * 9 / 10];
        let clipped = y.map(|v| v.min(ceiling));
        let err = |a: &DMatrix<f64>| (c.predict_all(a) - &truth).norm();
        let exact = err(&c.coefficients(&y));
        let naive = err(&c.coefficients(&clipped));
        let (a, n) = c.coefficients_censored(&clipped, ceiling, 50);
        let censored = err(&a);
        assert!(n > 0 && n == clipped.iter().filter(|&&v| v >= ceiling).count());
        assert!(
            censored < 0.6 * naive,
            "censored {censored:.4} naive {naive:.4} exact {exact:.4}"
        );
        assert!(censored < 2.0 * exact + 1e-9, "censored {censored:.4} exact {exact:.4}");
        for (j, col) in clipped.column_iter().enumerate() {
            if col.iter().all(|&v| v < ceiling) {
                assert_eq!(a.column(j), c.coefficients(&clipped).column(j));
            }
        }
        // Nothing at the ceiling: the plain coefficients, bit for bit.
        let (b, none) = c.coefficients_censored(&y, f64::INFINITY, 50);
        assert_eq!(none, 0);
        assert_eq!(b, c.coefficients(&y));
    }

    /// Per-pair noise: with equal noise at every pair and no ρ_p it is the plain MAP; a
    /// noisier pair pulls the completion less; bad variances are refused by name.
    #[test]
    fn per_pair_noise_weighs_measured_pairs() {
        let (meta, rows) = toy(9, 500, 6, 5);
        let p = Prior::learn(meta, &rows, 8, 1).unwrap();
        let d = 81;
        let (_, test) = toy(9, 20, 6, 99);
        let truth = model_rows(&test, d, 20);
        let design: Vec<usize> = (0..d).step_by(4).collect();
        let extra = 1e-5;
        let plain = Completion::new(&p, &design, p.header.residual_var + extra).unwrap();
        let same = Completion::with_pair_noise(&p, &design, &vec![extra; design.len()]).unwrap();
        let y = truth.select_rows(&design);
        let (fa, fb) = (
            plain.predict_all(&plain.coefficients(&y)),
            same.predict_all(&same.coefficients(&y)),
        );
        assert!((&fa - &fb).amax() < 1e-9, "{}", (&fa - &fb).amax());
        let mut noise = vec![extra; design.len()];
        noise[5] = 1.0;
        let loud = Completion::with_pair_noise(&p, &design, &noise).unwrap();
        let mut y_bad = y.clone();
        y_bad.row_mut(5).add_scalar_mut(0.3);
        let moved =
            |c: &Completion| (c.predict_all(&c.coefficients(&y_bad)) - c.predict_all(&c.coefficients(&y))).norm();
        assert!(
            moved(&loud) < 0.05 * moved(&same),
            "{} vs {}",
            moved(&loud),
            moved(&same)
        );
        let mut nan = vec![extra; design.len()];
        nan[2] = f64::NAN;
        let e = Completion::with_pair_noise(&p, &design, &nan)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains(&format!("pair {}", design[2])), "{e}");
        assert!(Completion::with_pair_noise(&p, &design, &[extra]).is_err());
    }
}
