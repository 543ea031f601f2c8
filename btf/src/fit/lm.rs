//! Levenberg–Marquardt with box bounds (projected steps) and a forward-difference Jacobian.
//!
//! Why its own small solver: the fits here have 7–20 parameters and thousands of residuals;
//! the normal equations `(JᵀJ + λ·diag JᵀJ) δ = −Jᵀr` are a tiny dense system, solved by
//! faer's Cholesky (the linear algebra the crate already uses). Bounds are enforced by
//! clamping every trial point into the box (a projected step): the models are only defined
//! inside it (exponents ≥ 0, roughness ≥ 10⁻⁴), and a stiff case (a lobe narrower than the
//! sampling, no signal in a direction) pushes a parameter onto its bound instead of to
//! infinity.
//!
//! Termination is guaranteed: at most `max_iterations` Jacobians, and inside one iteration
//! at most [`MAX_DAMPING_TRIES`] damping increases (λ grows ×4 per rejected step up to
//! `max_lambda`). A trial point whose residuals are not finite counts as a rejected step;
//! a start whose residuals are not finite is refused ([`Stop::NonFiniteStart`]).

use faer::linalg::solvers::Solve;
use faer::{Mat, Side};
use serde::Serialize;

/// Why a minimisation ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Stop {
    /// The cost fell by less than the relative tolerance in an accepted step.
    Converged,
    /// The gradient (projected onto the box) vanished.
    ZeroGradient,
    /// The accepted step moved the parameters by less than the step tolerance.
    SmallStep,
    /// The iteration cap was reached.
    MaxIterations,
    /// No damped step lowered the cost before λ reached its cap: a local minimum on the
    /// box, or a cost too flat to make progress on.
    Stalled,
    /// The start's residuals were not finite.
    NonFiniteStart,
}

impl Stop {
    /// A short sentence for reports.
    pub fn reason(self) -> &'static str {
        match self {
            Stop::Converged => "converged (relative cost change below tolerance)",
            Stop::ZeroGradient => "converged (gradient zero on the bounds)",
            Stop::SmallStep => "converged (step below tolerance)",
            Stop::MaxIterations => "iteration cap reached",
            Stop::Stalled => "stalled (no damped step lowers the cost)",
            Stop::NonFiniteStart => "start rejected (residuals not finite)",
        }
    }
}

/// Knobs of [`minimize`].
#[derive(Clone, Copy, Debug, Serialize)]
pub struct LmOptions {
    pub max_iterations: usize,
    /// Stop when an accepted step lowers the cost by less than this fraction.
    pub cost_tolerance: f64,
    /// Largest damping λ before giving up ([`Stop::Stalled`]).
    pub max_lambda: f64,
}

impl Default for LmOptions {
    fn default() -> Self {
        LmOptions {
            max_iterations: 100,
            cost_tolerance: 1e-9,
            max_lambda: 1e10,
        }
    }
}

/// Rejected damped steps tried per iteration at most (λ ×4 each: 4²⁰ ≈ 10¹²).
pub const MAX_DAMPING_TRIES: usize = 20;

/// Result of [`minimize`].
#[derive(Clone, Debug)]
pub struct LmResult {
    pub params: Vec<f64>,
    /// `½ Σ r²` at `params`.
    pub cost: f64,
    pub iterations: usize,
    /// Residual-vector evaluations (Jacobian columns included).
    pub evaluations: usize,
    pub stop: Stop,
}

fn cost_of(r: &[f64]) -> f64 {
    let c = 0.5 * r.iter().map(|x| x * x).sum::<f64>();
    if c.is_finite() {
        c
    } else {
        f64::INFINITY
    }
}

fn clamp_into(p: &mut [f64], lo: &[f64], hi: &[f64]) {
    for ((x, l), h) in p.iter_mut().zip(lo).zip(hi) {
        *x = x.clamp(*l, *h);
    }
}

/// Minimise `½ Σ r(p)²` over the box `lo ≤ p ≤ hi` from `p0`. `residuals(p, out)` writes
/// `m` residuals; it may write non-finite values (the step is then rejected).
pub fn minimize(
    residuals: &dyn Fn(&[f64], &mut [f64]),
    m: usize,
    p0: &[f64],
    lo: &[f64],
    hi: &[f64],
    opts: &LmOptions,
) -> LmResult {
    let n = p0.len();
    let mut p = p0.to_vec();
    clamp_into(&mut p, lo, hi);
    let mut r = vec![0.0; m];
    residuals(&p, &mut r);
    let mut evaluations = 1;
    let mut cost = cost_of(&r);
    let done = |p: Vec<f64>, cost: f64, iterations: usize, evaluations: usize, stop: Stop| LmResult {
        params: p,
        cost,
        iterations,
        evaluations,
        stop,
    };
    if !cost.is_finite() {
        return done(p, cost, 0, evaluations, Stop::NonFiniteStart);
    }
    if n == 0 || m == 0 {
        return done(p, cost, 0, evaluations, Stop::ZeroGradient);
    }
    let mut lambda = 1e-3;
    let mut jac = vec![0.0; m * n]; // column-major: column j = ∂r/∂p_j
    let mut rp = vec![0.0; m];
    let mut trial = vec![0.0; n];
    let mut rt = vec![0.0; m];
    for it in 0..opts.max_iterations {
        // Forward differences; towards the inside of the box at an upper bound.
        for j in 0..n {
            let h0 = 1e-6 * p[j].abs().max(1e-3);
            let h = if p[j] + h0 > hi[j] { -h0 } else { h0 };
            let mut q = p.clone();
            q[j] += h;
            residuals(&q, &mut rp);
            evaluations += 1;
            for i in 0..m {
                let d = (rp[i] - r[i]) / h;
                jac[j * m + i] = if d.is_finite() { d } else { 0.0 };
            }
        }
        let a = Mat::<f64>::from_fn(n, n, |i, k| {
            let (ci, ck) = (&jac[i * m..(i + 1) * m], &jac[k * m..(k + 1) * m]);
            ci.iter().zip(ck).map(|(x, y)| x * y).sum()
        });
        let g: Vec<f64> = (0..n)
            .map(|j| jac[j * m..(j + 1) * m].iter().zip(&r).map(|(x, y)| x * y).sum())
            .collect();
        // Projected gradient: a component pushing out of the box at a bound does not count.
        let pg = (0..n)
            .map(|j| {
                let at_lo = p[j] <= lo[j] && g[j] > 0.0;
                let at_hi = p[j] >= hi[j] && g[j] < 0.0;
                if at_lo || at_hi {
                    0.0
                } else {
                    g[j].abs()
                }
            })
            .fold(0.0f64, f64::max);
        if pg <= 1e-14 * (1.0 + cost) {
            return done(p, cost, it, evaluations, Stop::ZeroGradient);
        }
        let dmax = (0..n).map(|j| a[(j, j)]).fold(0.0f64, f64::max).max(1e-300);
        let mut accepted = false;
        for _ in 0..MAX_DAMPING_TRIES {
            let damped = Mat::<f64>::from_fn(n, n, |i, k| {
                if i == k {
                    a[(i, i)] + lambda * a[(i, i)].max(1e-9 * dmax)
                } else {
                    a[(i, k)]
                }
            });
            let step = match damped.llt(Side::Lower) {
                Ok(llt) => {
                    let mut rhs = Mat::<f64>::from_fn(n, 1, |i, _| -g[i]);
                    llt.solve_in_place(rhs.as_mut());
                    Some((0..n).map(|i| rhs[(i, 0)]).collect::<Vec<f64>>())
                }
                Err(_) => None,
            };
            let Some(step) = step.filter(|s| s.iter().all(|x| x.is_finite())) else {
                lambda *= 4.0;
                if lambda > opts.max_lambda {
                    return done(p, cost, it + 1, evaluations, Stop::Stalled);
                }
                continue;
            };
            for j in 0..n {
                trial[j] = p[j] + step[j];
            }
            clamp_into(&mut trial, lo, hi);
            let moved = trial.iter().zip(&p).map(|(a, b)| (a - b).abs()).fold(0.0f64, f64::max);
            let scale = p.iter().map(|x| x.abs()).fold(1.0f64, f64::max);
            if moved <= 1e-12 * scale {
                return done(p, cost, it + 1, evaluations, Stop::SmallStep);
            }
            residuals(&trial, &mut rt);
            evaluations += 1;
            let c = cost_of(&rt);
            if c < cost {
                let gain = (cost - c) / cost.max(1e-300);
                p.copy_from_slice(&trial);
                std::mem::swap(&mut r, &mut rt);
                cost = c;
                lambda = (lambda / 3.0).max(1e-12);
                accepted = true;
                if gain < opts.cost_tolerance {
                    return done(p, cost, it + 1, evaluations, Stop::Converged);
                }
                break;
            }
            lambda *= 4.0;
            if lambda > opts.max_lambda {
                return done(p, cost, it + 1, evaluations, Stop::Stalled);
            }
        }
        if !accepted {
            return done(p, cost, it + 1, evaluations, Stop::Stalled);
        }
    }
    done(p, cost, opts.max_iterations, evaluations, Stop::MaxIterations)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rosenbrock as residuals (10(y − x²), 1 − x): the classic narrow valley.
    #[test]
    fn finds_the_rosenbrock_minimum() {
        let f = |p: &[f64], r: &mut [f64]| {
            r[0] = 10.0 * (p[1] - p[0] * p[0]);
            r[1] = 1.0 - p[0];
        };
        let res = minimize(&f, 2, &[-1.2, 1.0], &[-5.0; 2], &[5.0; 2], &LmOptions::default());
        assert!((res.params[0] - 1.0).abs() < 1e-5, "{res:?}");
        assert!((res.params[1] - 1.0).abs() < 1e-5, "{res:?}");
        assert_ne!(res.stop, Stop::MaxIterations);
    }

    /// The box holds: the unconstrained minimum x = −3 lies outside [0, 10].
    #[test]
    fn respects_the_bounds() {
        let f = |p: &[f64], r: &mut [f64]| r[0] = p[0] + 3.0;
        let res = minimize(&f, 1, &[5.0], &[0.0], &[10.0], &LmOptions::default());
        assert_eq!(res.params[0], 0.0);
        assert!(matches!(res.stop, Stop::ZeroGradient | Stop::SmallStep | Stop::Stalled));
    }

    /// A residual that is NaN everywhere is refused at the start; one that turns NaN away
    /// from the start only rejects those steps.
    #[test]
    fn non_finite_residuals_end_with_a_reason() {
        let nan = |_: &[f64], r: &mut [f64]| r[0] = f64::NAN;
        let res = minimize(&nan, 1, &[1.0], &[0.0], &[2.0], &LmOptions::default());
        assert_eq!(res.stop, Stop::NonFiniteStart);
        let cliff = |p: &[f64], r: &mut [f64]| r[0] = if p[0] < 0.5 { f64::NAN } else { p[0] };
        let res = minimize(&cliff, 1, &[1.0], &[0.0], &[2.0], &LmOptions::default());
        assert!(res.cost.is_finite() && res.params[0] >= 0.5, "{res:?}");
    }

    /// The cap holds on a problem that never converges to tolerance in a few steps.
    #[test]
    fn the_iteration_cap_holds() {
        let f = |p: &[f64], r: &mut [f64]| {
            r[0] = 10.0 * (p[1] - p[0] * p[0]);
            r[1] = 1.0 - p[0];
        };
        let opts = LmOptions {
            max_iterations: 3,
            ..Default::default()
        };
        let res = minimize(&f, 2, &[-1.2, 1.0], &[-5.0; 2], &[5.0; 2], &opts);
        assert!(res.iterations <= 3);
        assert_eq!(res.stop, Stop::MaxIterations);
    }
}
