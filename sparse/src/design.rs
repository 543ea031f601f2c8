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
pub struct Greedy<'a> {
    prior: &'a Prior,
    noise_var: f64,
    b: Vec<f64>, // D × K row-major
    trace: f64,
    chosen: Vec<bool>,
}

impl<'a> Greedy<'a> {
    /// Start from the prior alone; `noise_var` is σ² in model space (measurement noise plus
    /// the out-of-basis residual).
    pub fn new(prior: &'a Prior, noise_var: f64) -> Greedy<'a> {
        let (d, k) = (prior.dims(), prior.components());
        let mut b = vec![0.0; d * k];
        for i in 0..d {
            for j in 0..k {
                b[i * k + j] = prior.basis[(i, j)] * prior.variances[j];
            }
        }
        Greedy {
            prior,
            noise_var: noise_var.max(1e-12),
            b,
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
    /// (what q's prediction still misses inside the basis).
    pub fn gain_and_var(&self, q: usize) -> (f64, f64) {
        let k = self.prior.components();
        let row = &self.b[q * k..q * k + k];
        let mut nn = 0.0;
        let mut qu = 0.0;
        for j in 0..k {
            nn += row[j] * row[j];
            qu += row[j] * self.prior.basis[(q, j)];
        }
        (nn / (self.noise_var + qu), qu.max(0.0))
    }

    pub fn is_chosen(&self, q: usize) -> bool {
        self.chosen[q]
    }

    /// Add pair q (measured, or chosen for measurement).
    pub fn add(&mut self, q: usize) {
        let (d, k) = (self.prior.dims(), self.prior.components());
        let g: Vec<f64> = self.b[q * k..q * k + k].to_vec(); // Σ u_q
        let c: f64 = self.noise_var + (0..k).map(|j| g[j] * self.prior.basis[(q, j)]).sum::<f64>();
        let gn: f64 = g.iter().map(|x| x * x).sum();
        // U g: D-vector.
        for i in 0..d {
            let mut ug = 0.0;
            for j in 0..k {
                ug += self.prior.basis[(i, j)] * g[j];
            }
            let s = ug / c;
            let row = &mut self.b[i * k..i * k + k];
            for j in 0..k {
                row[j] -= s * g[j];
            }
        }
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
