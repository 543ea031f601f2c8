//! Which pairs to measure: greedy Bayesian A-optimal design.
//!
//! With the prior's coefficients `a ~ N(0, Λ)` and measurements `y_p = μ_p + u_pᵀa + n`,
//! `n ~ N(0, σ²)`, the posterior covariance after the set S is
//! `Σ_S = (Λ⁻¹ + U_Sᵀ U_S / σ²)⁻¹`, and the expected squared reconstruction error summed
//! over every pair of the sweep is `tr(U Σ_S Uᵀ) + D ρ = tr(Σ_S) + D ρ` (U orthonormal).
//! Adding pair q lowers the trace by `‖Σ u_q‖² / (σ² + u_qᵀ Σ u_q)` (Sherman–Morrison).
//! The greedy keeps `B = U Σ` (D × K): row q of B is `(Σ u_q)ᵀ`, so every candidate's gain
//! costs O(K) and the update O(D K) per step.
//!
//! Motion: with a cost per candidate (`cost(q)`: seconds this pair would add, e.g. capture
//! time plus the move from the nearest chosen pair) the greedy picks the largest gain per
//! second instead (`design_by_time`); the caller updates costs after each pick.

use crate::{Prior, SparseError};

/// One greedy step: the pair added and the expected error after it.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct DesignStep {
    /// Canonical pair index.
    pub pair: usize,
    /// Expected mean squared error per pair (model space) after this step.
    pub expected_mse: f64,
}

/// The greedy state (reusable for adaptive designs and for a motion-aware caller).
///
/// Layout for speed: the prior's basis is a column-major D × K matrix, and every step of
/// the greedy walks it by rows (pair q's coefficients `u_q`). Walking a column-major matrix
/// by rows misses the cache on every element, which made `add` and `gain` 91 % of a
/// 5 %-budget plan's run time. So the state keeps a row-major copy `u` beside `B`, and
/// `add` refreshes each row's `‖B_q‖²` and `B_q · u_q` in the same pass that updates the
/// row (while it is in cache): a candidate's gain is then O(1), not O(K). Every sum runs in
/// the same order as the plain formulas (j = 0..K), so the numbers, and the designs, are
/// bit for bit what the straightforward code gives, at any thread count (rows are
/// independent; nothing is reduced across threads).
pub struct Greedy<'a> {
    prior: &'a Prior,
    noise_var: f64,
    /// Per pair σ_q² when the prior has per-pair residuals ([`Prior::pair_noise_var`]).
    pair_noise: Option<Vec<f64>>,
    k: usize,
    u: Vec<f64>, // D × K row-major copy of the basis
    b: Vec<f64>, // D × K row-major, B = U Σ
    /// Per row q: `‖B_q‖²` and `B_q · u_q` (= `u_qᵀ Σ u_q`).
    nn: Vec<f64>,
    qu: Vec<f64>,
    trace: f64,
    chosen: Vec<bool>,
}

/// `‖row‖²` and `row · u`, summed in index order.
fn norms(row: &[f64], u: &[f64]) -> (f64, f64) {
    let mut nn = 0.0;
    let mut qu = 0.0;
    for (r, x) in row.iter().zip(u) {
        nn += r * r;
        qu += r * x;
    }
    (nn, qu)
}

impl<'a> Greedy<'a> {
    /// Start from the prior alone; `noise_var` is σ² in model space (measurement noise plus
    /// the out-of-basis residual).
    pub fn new(prior: &'a Prior, noise_var: f64) -> Greedy<'a> {
        use rayon::prelude::*;
        let (d, k) = (prior.dims(), prior.components());
        let mut u = vec![0.0; d * k];
        let mut b = vec![0.0; d * k];
        for j in 0..k {
            let col = prior.basis.column(j);
            let var = prior.variances[j];
            for (i, &x) in col.iter().enumerate() {
                u[i * k + j] = x;
                b[i * k + j] = x * var;
            }
        }
        let (nn, qu): (Vec<f64>, Vec<f64>) = if k == 0 {
            (vec![0.0; d], vec![0.0; d])
        } else {
            b.par_chunks(k)
                .zip(u.par_chunks(k))
                .map(|(row, ur)| norms(row, ur))
                .unzip()
        };
        let noise_var = noise_var.max(1e-12);
        let pair_noise = prior
            .pair_residual_var
            .as_ref()
            .map(|_| (0..d).map(|q| prior.pair_noise_var(q, noise_var)).collect());
        Greedy {
            prior,
            noise_var,
            pair_noise,
            k,
            u,
            b,
            nn,
            qu,
            trace: prior.variances.iter().sum(),
            chosen: vec![false; d],
        }
    }

    /// Expected mean squared error per pair now (model space).
    pub fn expected_mse(&self) -> f64 {
        self.trace.max(0.0) / self.prior.dims() as f64 + self.prior.header.residual_var
    }

    /// The trace reduction of adding pair q.
    pub fn gain(&self, q: usize) -> f64 {
        self.gain_and_var(q).0
    }

    /// The trace reduction of adding pair q and q's own posterior variance `u_qᵀ Σ u_q`
    /// (what q's prediction still misses inside the basis). O(1): both come from the
    /// per-row sums `add` keeps.
    pub fn gain_and_var(&self, q: usize) -> (f64, f64) {
        let qu = self.qu[q];
        (self.nn[q] / (self.noise(q) + qu), qu.max(0.0))
    }

    /// σ_q²: the noise variance of a measurement of pair q.
    fn noise(&self, q: usize) -> f64 {
        self.pair_noise.as_ref().map_or(self.noise_var, |v| v[q])
    }

    pub fn is_chosen(&self, q: usize) -> bool {
        self.chosen[q]
    }

    /// Add pair q (measured, or chosen for measurement): `B ← B − (U g) gᵀ / c` with
    /// `g = Σ u_q` and `c = σ² + u_qᵀ Σ u_q` (Sherman–Morrison), one row at a time.
    pub fn add(&mut self, q: usize) {
        use rayon::prelude::*;
        let k = self.k;
        if k == 0 {
            self.chosen[q] = true;
            return;
        }
        let g: Vec<f64> = self.b[q * k..q * k + k].to_vec(); // Σ u_q
        let c: f64 = self.noise(q) + g.iter().zip(&self.u[q * k..q * k + k]).map(|(a, b)| a * b).sum::<f64>();
        let gn: f64 = g.iter().map(|x| x * x).sum();
        let g = &g;
        self.b
            .par_chunks_mut(k)
            .zip(self.u.par_chunks(k))
            .zip(self.nn.par_iter_mut().zip(self.qu.par_iter_mut()))
            .with_min_len(64)
            .for_each(|((row, ur), (nn, qu))| {
                let mut ug = 0.0;
                for (x, gj) in ur.iter().zip(g) {
                    ug += x * gj;
                }
                let s = ug / c;
                for (r, gj) in row.iter_mut().zip(g) {
                    *r -= s * gj;
                }
                (*nn, *qu) = norms(row, ur);
            });
        self.trace -= gn / c;
        self.chosen[q] = true;
    }

    /// The unchosen candidate with the largest `gain / cost` (ties: lowest index).
    pub fn best(&self, candidates: &[usize], cost: impl Fn(usize) -> f64) -> Option<usize> {
        let mut best: Option<(f64, usize)> = None;
        for &q in candidates {
            if self.chosen[q] {
                continue;
            }
            let s = self.gain(q) / cost(q).max(1e-9);
            if best.is_none_or(|(b, _)| s > b) {
                best = Some((s, q));
            }
        }
        best.map(|(_, q)| q)
    }
}

/// Greedy A-optimal design: `n` pairs out of `candidates` (feasible pairs), after the pairs
/// already in `start` (e.g. measured in an earlier round). Returns the sequence in the order
/// chosen, each with the expected error after it; every prefix is itself a greedy design.
pub fn greedy_design(
    prior: &Prior,
    candidates: &[usize],
    start: &[usize],
    n: usize,
    noise_var: f64,
) -> Result<Vec<DesignStep>, SparseError> {
    let d = prior.dims();
    if let Some(&bad) = candidates.iter().chain(start).find(|&&q| q >= d) {
        return Err(SparseError::Invalid(format!(
            "pair {bad} is outside the prior's sweep of {d} pairs"
        )));
    }
    let mut g = Greedy::new(prior, noise_var);
    for &q in start {
        g.add(q);
    }
    let mut out = Vec::with_capacity(n);
    while out.len() < n {
        let Some(q) = g.best(candidates, |_| 1.0) else {
            break;
        };
        g.add(q);
        out.push(DesignStep {
            pair: q,
            expected_mse: g.expected_mse(),
        });
    }
    Ok(out)
}

/// Motion-aware greedy: largest gain per second, where a pair's cost is `pair_s(m)` of `m`,
/// the move time from the nearest already-chosen pair (`move_s(a, b)`; `home_s(q)` from the
/// start pose before any pick). `pair_s` says what a pair costs the rig given its move: stop
/// and go `capture + m`; with the readout overlapping the move `max(m, readout) + exposure`,
/// so pairs within a readout's move of a chosen one cost only their capture. Stops when the
/// estimated time (the sum of those costs, a nearest-neighbour tour) would exceed `budget_s`
/// or `max_pairs` are chosen; the caller plans the real order and trims to the budget.
#[allow(clippy::too_many_arguments)]
pub fn design_by_time(
    prior: &Prior,
    candidates: &[usize],
    noise_var: f64,
    pair_s: impl Fn(f64) -> f64,
    home_s: impl Fn(usize) -> f64,
    move_s: impl Fn(usize, usize) -> f64 + Sync,
    budget_s: f64,
    max_pairs: usize,
) -> Vec<DesignStep> {
    use rayon::prelude::*;
    let mut g = Greedy::new(prior, noise_var);
    let mut near: Vec<f64> = vec![f64::INFINITY; prior.dims()];
    for &q in candidates {
        near[q] = home_s(q);
    }
    let mut out = Vec::new();
    let mut spent = 0.0;
    while out.len() < max_pairs {
        let Some(q) = g.best(candidates, |q| pair_s(near[q])) else {
            break;
        };
        let add = pair_s(near[q]);
        if spent + add > budget_s {
            break;
        }
        spent += add;
        g.add(q);
        out.push(DesignStep {
            pair: q,
            expected_mse: g.expected_mse(),
        });
        let upd: Vec<(usize, f64)> = candidates
            .par_iter()
            .filter(|&&c| !g.is_chosen(c))
            .map(|&c| (c, move_s(q, c)))
            .collect();
        for (c, t) in upd {
            if t < near[c] {
                near[c] = t;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prior::tests::toy;

    #[test]
    fn greedy_lowers_the_expected_error_and_never_repeats() {
        let (meta, rows) = toy(8, 400, 5, 4);
        let p = Prior::learn(meta, &rows, 6, 1).unwrap();
        let cand: Vec<usize> = (0..64).filter(|q| q % 9 != 0).collect(); // no "retro" pairs
        let s = greedy_design(&p, &cand, &[], 20, 1e-4).unwrap();
        assert_eq!(s.len(), 20);
        assert!(s.windows(2).all(|w| w[1].expected_mse <= w[0].expected_mse + 1e-15));
        let mut seen = std::collections::BTreeSet::new();
        assert!(s.iter().all(|x| seen.insert(x.pair) && x.pair % 9 != 0));
        // Better than the same number of evenly spaced pairs.
        let mut g = Greedy::new(&p, 1e-4);
        for q in cand.iter().step_by(cand.len() / 20).take(20) {
            g.add(*q);
        }
        assert!(s[19].expected_mse <= g.expected_mse());
        // A prefix design is the greedy of that size.
        let s5 = greedy_design(&p, &cand, &[], 5, 1e-4).unwrap();
        assert_eq!(&s5[..], &s[..5]);
    }

    /// The motion-aware greedy spends at most its budget (by its own estimate), never
    /// repeats a pair, and with free moves is the plain greedy; a costly pair far from
    /// everything is taken later than the plain greedy takes it.
    #[test]
    fn motion_aware_greedy_respects_the_budget_and_reduces_to_the_plain_one() {
        let (meta, rows) = toy(8, 400, 5, 4);
        let p = Prior::learn(meta, &rows, 6, 1).unwrap();
        let cand: Vec<usize> = (0..64).collect();
        let plain = greedy_design(&p, &cand, &[], 20, 1e-4).unwrap();
        // No motion: cost = capture for every pair, the plain greedy's sequence.
        let free = design_by_time(&p, &cand, 1e-4, |m| 1.0 + m, |_| 0.0, |_, _| 0.0, f64::INFINITY, 20);
        assert_eq!(free, plain);
        // Pairs on a line, moves cost their distance: within budget, no repeats.
        let pos = |q: usize| q as f64;
        let cost = |m: f64| m.max(1.0) + 0.05;
        let budget = 40.0;
        let timed = design_by_time(&p, &cand, 1e-4, cost, pos, |a, b| (pos(a) - pos(b)).abs(), budget, 64);
        let mut seen = std::collections::BTreeSet::new();
        assert!(timed.iter().all(|x| seen.insert(x.pair)));
        let mut near = vec![f64::INFINITY; 64];
        let mut spent = 0.0;
        for (i, x) in timed.iter().enumerate() {
            let m = if i == 0 { pos(x.pair) } else { near[x.pair] };
            spent += cost(m);
            for (c, n) in near.iter_mut().enumerate() {
                *n = n.min((pos(c) - pos(x.pair)).abs());
            }
        }
        assert!(spent <= budget + 1e-9, "spent {spent} of {budget}");
        assert!(timed.windows(2).all(|w| w[1].expected_mse <= w[0].expected_mse + 1e-15));
    }
}
