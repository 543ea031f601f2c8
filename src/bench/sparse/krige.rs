//! Bench method `ours-krige` (an experiment): ours, then the residual that the prior's
//! span leaves at the measured pairs carried over to the unmeasured ones by a Gaussian
//! process over the pair's directions.
//!
//! Why: the prior models what its K components miss as independent per pair (variance
//! ρ_p), so the completion predicts nothing of it at an unmeasured pair. A material the
//! span does not hold leaves a residual that may vary smoothly over the light and view
//! directions (a shadow that starts a little earlier, a lobe a little wider). Then its
//! value at nearby measured pairs says something about the unmeasured pair. The kernel
//! keeps the prior's own variance per pair, `k(p, q) = √(ρ_p ρ_q) (β c(p, q) + (1−β) δ_pq)`,
//! `c = exp(−d²/2ℓ²)` with `d²` the squared chord distance of both lights and both views;
//! ℓ → 0 is ours exactly. ℓ and β are chosen from the measured values alone, by the
//! closed-form leave-one-out error of the residual field (`e_i = [A⁻¹r]_i / [A⁻¹]_ii`),
//! summed over every texel and channel: no truth.

use anyhow::{Context, Result};
use gonio_btf::compress::interp::unit;
use gonio_sparse::Prior;
use nalgebra::DMatrix;
use rayon::prelude::*;

/// Correlation lengths (chord distance; 0.26 is 15°) and correlated shares β tried.
const LENGTHS: [f64; 5] = [0.08, 0.15, 0.25, 0.4, 0.6];
const SHARES: [f64; 3] = [0.5, 0.8, 0.95];
/// Columns (texel channels) per parallel chunk.
const CHUNK: usize = 256;

/// Squared chord distance between pairs `p` and `q` (canonical index `view · L + light`).
fn dist2(dirs: &[([f64; 3], [f64; 3])], p: usize, q: usize) -> f64 {
    let (a, b) = (&dirs[p], &dirs[q]);
    (0..3)
        .map(|i| (a.0[i] - b.0[i]).powi(2) + (a.1[i] - b.1[i]).powi(2))
        .sum()
}

/// `a · b` by column chunks of `b` in parallel (each column is one product, so the sums are
/// the same at any thread count).
fn mul_cols(a: &DMatrix<f64>, b: &DMatrix<f64>) -> DMatrix<f64> {
    let chunks: Vec<DMatrix<f64>> = (0..b.ncols().div_ceil(CHUNK))
        .into_par_iter()
        .map(|c| {
            let (lo, hi) = (c * CHUNK, ((c + 1) * CHUNK).min(b.ncols()));
            a * b.columns(lo, hi - lo)
        })
        .collect();
    let mut out = DMatrix::<f64>::zeros(a.nrows(), b.ncols());
    for (c, m) in chunks.into_iter().enumerate() {
        out.columns_mut(c * CHUNK, m.ncols()).copy_from(&m);
    }
    out
}

/// What the kriging chose and what leave-one-out said.
struct Choice {
    length: f64,
    share: f64,
    /// Leave-one-out mean square of the residual: predicted as 0 (ours) and by the choice.
    loo_zero: f64,
    loo: f64,
}

/// Model-space values `pred` (D × M, ours) plus the kriged residual at every unmeasured pair;
/// `y` (S × M) the measured values, `ceiling` the model-space full scale (a clipped reading
/// whose prediction is above it gives no residual), `noise` each measured pair's sensor
/// noise variance.
fn krige(
    prior: &Prior,
    dirs: &[([f64; 3], [f64; 3])],
    measured: &[usize],
    y: &DMatrix<f64>,
    pred: &mut DMatrix<f64>,
    noise: &[f64],
    ceiling: f64,
) -> Result<Choice> {
    let s = measured.len();
    let m = y.ncols();
    let r = DMatrix::<f64>::from_fn(s, m, |i, j| {
        let v = y[(i, j)] - pred[(measured[i], j)];
        if y[(i, j)] >= ceiling && v < 0.0 {
            0.0
        } else {
            v
        }
    });
    let sd: Vec<f64> = (0..prior.dims()).map(|p| prior.pair_residual(p).sqrt()).collect();
    let n = (s * m) as f64;
    let loo_zero = r.iter().map(|x| x * x).sum::<f64>() / n;
    let mut best = Choice {
        length: 0.0,
        share: 0.0,
        loo_zero,
        loo: loo_zero,
    };
    let mut best_inv: Option<DMatrix<f64>> = None;
    for &len in &LENGTHS {
        for &share in &SHARES {
            let a = DMatrix::<f64>::from_fn(s, s, |i, j| {
                let (p, q) = (measured[i], measured[j]);
                let c = share * (-dist2(dirs, p, q) / (2.0 * len * len)).exp();
                let k = sd[p] * sd[q] * (c + if i == j { 1.0 - share } else { 0.0 });
                k + if i == j { noise[i] } else { 0.0 }
            });
            let inv = a
                .cholesky()
                .context("the residual kernel is not positive definite")?
                .inverse();
            let w = mul_cols(&inv, &r);
            let loo = (0..s)
                .map(|i| {
                    let d = inv[(i, i)];
                    w.row(i).iter().map(|x| (x / d).powi(2)).sum::<f64>()
                })
                .sum::<f64>()
                / n;
            if loo < best.loo {
                best = Choice {
                    length: len,
                    share,
                    loo_zero,
                    loo,
                };
                best_inv = Some(inv);
            }
        }
    }
    let Some(inv) = best_inv else { return Ok(best) };
    let w = mul_cols(&inv, &r);
    let mut is_m = vec![false; prior.dims()];
    measured.iter().for_each(|&p| is_m[p] = true);
    let rest: Vec<usize> = (0..prior.dims()).filter(|&p| !is_m[p]).collect();
    let kq = DMatrix::<f64>::from_fn(rest.len(), s, |i, j| {
        let (p, q) = (rest[i], measured[j]);
        sd[p] * sd[q] * best.share * (-dist2(dirs, p, q) / (2.0 * best.length * best.length)).exp()
    });
    let g = mul_cols(&kq, &w);
    for (i, &p) in rest.iter().enumerate() {
        for j in 0..m {
            pred[(p, j)] += g[(i, j)];
        }
    }
    Ok(best)
}

/// Ours (sensor noise, censored fit), then [`krige`]: the images, and a note.
pub fn complete(
    prior: &Prior,
    lights_deg: &[[f64; 2]],
    views_deg: &[[f64; 2]],
    measured: &[usize],
    meas: &[Vec<f32>],
    sensor: &gonio_devices::hdr::SensorNoise,
) -> Result<(Vec<Vec<f32>>, String)> {
    let p = prior.truncated(prior.components().min(measured.len()));
    let fit = super::SensorFit::new(&p, measured, meas, sensor)?;
    let space = p.space();
    let m = meas.first().map_or(0, |i| i.len());
    let y = DMatrix::<f64>::from_fn(measured.len(), m, |i, j| space.forward(meas[measured[i]][j] as f64));
    let mut pred = fit.completion.predict_all(&fit.coefficients);
    let l = lights_deg.len();
    let dirs: Vec<([f64; 3], [f64; 3])> = (0..p.dims())
        .map(|q| (unit(lights_deg[q % l]), unit(views_deg[q / l])))
        .collect();
    let choice = krige(&p, &dirs, measured, &y, &mut pred, &fit.noise, space.forward(1.0))?;
    let mut is_m = vec![false; p.dims()];
    measured.iter().for_each(|&q| is_m[q] = true);
    let images = (0..p.dims())
        .into_par_iter()
        .map(|q| {
            if is_m[q] {
                meas[q].clone()
            } else {
                (0..m).map(|j| space.inverse(pred[(q, j)]) as f32).collect()
            }
        })
        .collect();
    let note = format!(
        "K = {}, ℓ = {} (chord), β = {}, leave-one-out residual {:.3e} against {:.3e} predicted as 0",
        p.components(),
        choice.length,
        choice.share,
        choice.loo,
        choice.loo_zero
    );
    Ok((images, note))
}
