//! Adaptive acquisition (issue 29, `gonio acquire --adaptive`): measure in rounds, and
//! let what the first rounds measured decide where the next ones go.
//!
//! A fixed sparse plan ([`super::sparse`]) trusts the prior: its predicted error is the
//! posterior's, which knows nothing of the material's own departure from the prior's
//! span. An adaptive run measures a first design, then before each further round
//! analyses the values it has ([`gonio_sparse::adaptive::next_round`]: leave-one-out
//! residuals of the completion, spread over the pair geometry) and gets an honest
//! predicted error and the pairs that lower it most. It stops at the target PSNR (a real
//! rig has no truth: the target is the *predicted* PSNR) or when the rig budget is spent.
//!
//! Invariants, each relied on by resume:
//! - **A round is recorded before its first move.** [`Plan::adaptive_next`] appends the
//!   round's steps and its record to the plan; the session writes `plan.json` before the
//!   engine runs the round. A resumed run reads the rounds and never recomputes one.
//! - **Choices depend on the data and declared costs only.** The analysis between rounds
//!   is charged as a declared allowance of rig time ([`ROUND_ALLOWANCE_S`]), not as the
//!   wall clock, so the same measured values choose the same pairs on any machine at any
//!   load. What the analysis really took is logged and reported by the bench beside it.
//! - Every round is planned by the existing planner (from home, so its planned time is an
//!   upper bound of what the engine spends moving there from the last pose).

use super::sparse::{fit_prefix, psnr_of_mse, SparseDesign, SparseRequest, SparseTarget};
pub use super::sparse::{AdaptiveInfo, AdaptiveRound, AdaptiveStop};
use super::{Plan, PlanError, PlanOptions};
use gonio_dataset::sweep::Sweep;
use gonio_devices::hdr::SensorNoise;
use gonio_devices::rig::RigSpec;
use gonio_sparse::adaptive::{next_round, PairGeometry, Readings};
use gonio_sparse::{Prior, ValueSpace};
use nalgebra::DMatrix;

/// Share of a rig budget that the first (A-optimal) round spends; each later round spends
/// half of what is left, the last one all of it.
pub const FIRST_SHARE: f64 = 0.5;
/// Rig time charged for the analysis before each later round (s): a declared cost, so
/// choices do not depend on the machine's load. The summary reports the real wall time
/// beside it (`adaptive.analysis_wall_s`); docs/guide/sparse.md has what was measured.
pub const ROUND_ALLOWANCE_S: f64 = 30.0;
/// Weight of the residual term in the next pairs' score (see
/// [`gonio_sparse::adaptive::next_round`]). Measured on brushed metal (32², noise on,
/// 5 % and 10 % of the canonical rig time, docs/guide/sparse.md): weight 1 chose pairs in
/// the lobes and completed 1.6–3.0 dB worse than the fixed design at the same pair count,
/// so the rounds continue the A-optimal design and the analysis decides when to stop
/// (its residual-aware prediction) and flags a material outside the prior.
pub const RESIDUAL_WEIGHT: f64 = 0.0;
/// Texels whose values the analysis reads (spread over the image, three channels each):
/// enough for a stable mean residual per pair, and a fixed cost whatever the texel count.
pub const ANALYSIS_TEXELS: usize = 512;
/// At most this many rounds.
pub const MAX_ROUNDS: usize = 8;
/// Without a rig budget, a later round adds at most as many pairs as are measured (the
/// set at most doubles per round), and at least this many.
pub const MIN_ROUND_PAIRS: usize = 8;

/// An adaptive plan's inputs besides the rig and the sweep.
#[derive(Clone, Copy)]
pub struct AdaptiveRequest<'a> {
    pub prior: &'a Prior,
    pub prior_name: &'a str,
    pub stop: AdaptiveStop,
    pub noise_var: f64,
    pub tuning: AdaptiveTuning,
}

/// The two declared knobs of the rounds (`--residual-weight`, `--round-allowance`),
/// recorded in plan.json so that a resumed run keeps them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdaptiveTuning {
    /// Weight of the residual term when choosing a round's pairs ([`RESIDUAL_WEIGHT`]).
    pub residual_weight: f64,
    /// Rig time charged for each analysis between rounds, seconds ([`ROUND_ALLOWANCE_S`]).
    pub round_allowance_s: f64,
}

impl Default for AdaptiveTuning {
    fn default() -> Self {
        AdaptiveTuning {
            residual_weight: RESIDUAL_WEIGHT,
            round_allowance_s: ROUND_ALLOWANCE_S,
        }
    }
}

impl AdaptiveTuning {
    /// From the flags (None: the default), each a finite number ≥ 0.
    pub fn new(residual_weight: Option<f64>, round_allowance_s: Option<f64>) -> Result<AdaptiveTuning, PlanError> {
        let d = AdaptiveTuning::default();
        let check = |flag: &str, v: Option<f64>, default: f64| match v {
            None => Ok(default),
            Some(x) if x.is_finite() && x >= 0.0 => Ok(x),
            Some(x) => Err(invalid(format!("{flag} {x}: must be a finite number ≥ 0"))),
        };
        Ok(AdaptiveTuning {
            residual_weight: check("--residual-weight", residual_weight, d.residual_weight)?,
            round_allowance_s: check("--round-allowance", round_allowance_s, d.round_allowance_s)?,
        })
    }
}

fn invalid(message: String) -> PlanError {
    PlanError::Sparse { message }
}

/// The texels (of `total`) the analysis reads: `n` spread evenly over the image.
pub fn analysis_texels(total: usize, n: usize) -> Vec<usize> {
    let n = n.min(total).max(1);
    (0..n).map(|i| ((2 * i + 1) * total) / (2 * n)).collect()
}

/// One measured image (interleaved RGB, linear) as the analysis reads it: its values at the
/// texels `pick` ([`analysis_texels`]; texel-major, then channel; in the prior's value
/// space) and its measurement noise in that space under the rig's sensor model
/// ([`gonio_sparse::noise::pair_noise`] over the same readings). Both callers of
/// [`Plan::adaptive_next`] (the session and the bench) read images through this, so the
/// bench's rounds are the acquisition's.
pub fn analysis_row(image: &[f32], pick: &[usize], space: ValueSpace, sensor: &SensorNoise) -> (Vec<f64>, f64) {
    let readings: Vec<f32> = pick
        .iter()
        .flat_map(|&t| (0..3).map(move |c| 3 * t + c))
        .map(|i| image.get(i).copied().unwrap_or(0.0))
        .collect();
    let values = readings.iter().map(|&r| space.forward(r as f64)).collect();
    let noise = gonio_sparse::noise::pair_noise(space, &readings, |x| sensor.variance(x));
    (values, noise)
}

impl Plan {
    /// Plan an adaptive acquisition's first round: the greedy A-optimal design, as much of
    /// it as [`FIRST_SHARE`] of the rig budget holds, or (target only) the shortest prefix
    /// the prior predicts to reach the target. The prior is used with at most as many
    /// components as the round has pairs; later rounds use more as pairs accrue.
    pub fn build_adaptive(
        rig: &RigSpec,
        sweep: &Sweep,
        opts: &PlanOptions,
        full: &Plan,
        req: AdaptiveRequest,
    ) -> Result<Plan, PlanError> {
        let prior = req.prior;
        let feasible = full.steps.len();
        let capture = full.durations.capture_per_measurement_s.max(1e-6);
        let target = match (req.stop.rig_budget_s, req.stop.target_psnr_db) {
            (Some(b), _) => {
                let first = FIRST_SHARE * b;
                if first < capture {
                    return Err(invalid(format!(
                        "--rig-budget {b}: the first round ({FIRST_SHARE} of it) does not cover one capture \
                         ({capture:.2} s)"
                    )));
                }
                SparseTarget::RigBudget(first)
            }
            (None, Some(t)) => {
                // The prior's own prediction is optimistic (it knows no departure from its
                // span), so its prefix is a lower bound of what the target needs.
                let mut ids: Vec<usize> = full.steps.iter().map(|s| s.index).collect();
                ids.sort_unstable();
                let cap = (4 * prior.components()).min(ids.len());
                let design = gonio_sparse::greedy_design(prior, &ids, &[], cap, req.noise_var)
                    .map_err(|e| invalid(format!("prior {}: {e}", req.prior_name)))?;
                let n = design
                    .iter()
                    .position(|s| psnr_of_mse(s.expected_mse) >= t)
                    .map_or(design.len(), |i| i + 1);
                SparseTarget::Pairs(n.max(MIN_ROUND_PAIRS.min(feasible)).min(feasible))
            }
            (None, None) => unreachable!("AdaptiveStop::new requires a stop"),
        };
        // The design uses every component (a Bayesian design is well posed with more
        // components than pairs); the analysis completes with at most as many as measured.
        let r = SparseRequest {
            prior,
            prior_name: req.prior_name,
            target,
            noise_var: req.noise_var,
            design: SparseDesign::AOptimal,
        };
        let plan = Plan::build_sparse_with(rig, sweep, opts, full, r, false)?;
        let mut plan = plan;
        let sp = plan.sparse.as_mut().expect("build_sparse sets sparse");
        let pairs: Vec<usize> = sp.picks.iter().map(|p| p.0).collect();
        let pairs_len = pairs.len();
        let infeasible: Vec<usize> = {
            let mut f = vec![true; sweep.len()];
            for s in &full.steps {
                f[s.index] = false;
            }
            (0..sweep.len()).filter(|&i| f[i]).collect()
        };
        sp.design = "adaptive: greedy Bayesian A-optimal first round, then rounds chosen from the measured \
                     values' leave-one-out residuals (gonio_sparse::adaptive)"
            .into();
        sp.target = describe(req.stop);
        sp.adaptive = Some(AdaptiveInfo {
            stop: req.stop,
            prior_sha256: prior.header.payload_sha256.clone(),
            components: prior.components(),
            noise_var: req.noise_var,
            first_share: FIRST_SHARE,
            round_allowance_s: req.tuning.round_allowance_s,
            residual_weight: req.tuning.residual_weight,
            analysis_texels: ANALYSIS_TEXELS,
            max_rounds: MAX_ROUNDS,
            plan_kicks: opts.kicks,
            plan_seed: opts.seed,
            infeasible,
            rounds: vec![AdaptiveRound {
                round: 1,
                measured_before: 0,
                pairs,
                first_step: 0,
                planned_s: plan.durations.optimized_s,
                allowance_s: 0.0,
                components: prior.components().min(pairs_len),
                predicted_psnr_before_db: None,
                predicted_psnr_after_db: sp.predicted_psnr_db,
                observed_residual: None,
                expected_residual: None,
                outside_prior: false,
            }],
            finished: None,
            predicted_psnr_db: None,
            outside_prior: false,
        });
        Ok(plan)
    }

    /// After every chosen pair is measured: analyse and append the next round, or mark the
    /// run finished. `measured` are the pairs with values (in any order), `values` their
    /// values at the analysis texels (rows in the order of `measured`, model space) and
    /// `pair_noise` each one's measurement noise in model space
    /// ([`analysis_row`], from the rig's sensor model).
    /// Returns `true` when a round was added (write `plan.json`, then run it).
    // Each argument is one input of the analysis; the values and their noise come together
    // from one reader ([`analysis_row`]) in both callers.
    #[allow(clippy::too_many_arguments)]
    pub fn adaptive_next(
        &mut self,
        rig: &RigSpec,
        sweep: &Sweep,
        opts: &PlanOptions,
        prior: &Prior,
        measured: &[usize],
        values: &DMatrix<f64>,
        pair_noise: &[f64],
    ) -> Result<bool, PlanError> {
        let offset = self.durations.optimized_s;
        let first_step = self.steps.len();
        let sp = self
            .sparse
            .as_mut()
            .ok_or_else(|| invalid("not a sparse plan".into()))?;
        let ad = sp
            .adaptive
            .as_mut()
            .ok_or_else(|| invalid("not an adaptive plan".into()))?;
        if ad.finished.is_some() {
            return Ok(false);
        }
        if prior.header.payload_sha256 != ad.prior_sha256 {
            return Err(invalid(format!(
                "the prior's payload hash is {}, the plan's rounds were chosen in {}: resume with the same prior",
                &prior.header.payload_sha256[..16.min(prior.header.payload_sha256.len())],
                &ad.prior_sha256[..16.min(ad.prior_sha256.len())]
            )));
        }
        let prior = if prior.components() > ad.components {
            prior.truncated(ad.components)
        } else {
            prior.clone()
        };
        let (lights, views) = sweep.directions_deg();
        let geom = PairGeometry::new(&lights, &views);
        let chosen = ad.chosen();
        let mut taken = vec![false; sweep.len()];
        for &i in chosen.iter().chain(&ad.infeasible) {
            taken[i] = true;
        }
        let candidates: Vec<usize> = (0..sweep.len()).filter(|&i| !taken[i]).collect();
        let capture = self.durations.capture_per_measurement_s.max(1e-6);
        // How many pairs the round may take.
        let spent = ad.spent_s() + ad.round_allowance_s;
        let round_budget = ad.stop.rig_budget_s.map(|b| {
            let left = b - spent;
            let last = ad.rounds.len() + 1 == ad.max_rounds;
            if last || left < 0.25 * b {
                left
            } else {
                left / 2.0
            }
        });
        let n_max = match round_budget {
            Some(rb) => ((rb / capture).max(0.0).floor() as usize).min(candidates.len()),
            None => measured.len().max(MIN_ROUND_PAIRS).min(candidates.len()),
        };
        // Clipped readings are lower bounds, at the rig's clip level (none under HDR).
        let ceiling = rig.clip_level().map(|c| prior.space().forward(c));
        let readings = Readings {
            values,
            noise: pair_noise,
            ceiling,
        };
        let choice = next_round(
            &prior,
            &geom,
            &candidates,
            measured,
            &readings,
            ad.noise_var,
            ad.residual_weight,
            n_max,
        )
        .map_err(|e| invalid(format!("adaptive analysis: {e}")))?;
        let now = psnr_of_mse(choice.predicted_mse);
        ad.predicted_psnr_db = Some(round3(now));
        ad.outside_prior = choice.outside_prior;
        if choice.outside_prior {
            tracing::warn!(
                observed = choice.observed_residual,
                expected = choice.expected_residual,
                "the measured values depart from the prior far more than it expects: the material is outside \
                 the prior; the next rounds go where the residual is"
            );
        }
        let stop = |ad: &mut AdaptiveInfo, why: String| {
            tracing::info!(reason = %why, "adaptive acquisition finished");
            ad.finished = Some(why);
            Ok(false)
        };
        if let Some(t) = ad.stop.target_psnr_db {
            if now >= t {
                return stop(ad, format!("predicted PSNR {now:.2} dB reached the target {t} dB"));
            }
        }
        if ad.rounds.len() >= ad.max_rounds {
            return stop(
                ad,
                format!("{} rounds measured (the most a run takes)", ad.rounds.len()),
            );
        }
        if candidates.is_empty() {
            return stop(ad, "every feasible pair is measured".into());
        }
        if n_max == 0 || choice.picks.is_empty() {
            return stop(ad, budget_spent(ad));
        }
        // With a target: as many picks as the prediction says it needs (at least a few).
        let mut n = choice.picks.len();
        if let Some(t) = ad.stop.target_psnr_db {
            if let Some(i) = choice.picks.iter().position(|s| psnr_of_mse(s.expected_mse) >= t) {
                n = (i + 1).max(MIN_ROUND_PAIRS).min(choice.picks.len());
            }
        }
        let picks: Vec<usize> = choice.picks[..n].iter().map(|s| s.pair).collect();
        let all = sweep.pairs();
        // The round starts where the previous one left the rig, not at home: its first move
        // and its order are planned from there, as the engine will move.
        let start: Option<Vec<f64>> = self
            .steps
            .last()
            .map(|s| s.axes_deg.iter().map(|x| x.to_radians()).collect());
        let plan_of = |n: usize, kicks: usize| -> Result<Plan, PlanError> {
            let mut idx = picks[..n].to_vec();
            idx.sort_unstable();
            let chosen: Vec<_> = idx.iter().map(|&i| all[i]).collect();
            Plan::build_pairs_from(
                rig,
                sweep,
                &chosen,
                &PlanOptions { kicks, ..opts.clone() },
                start.as_deref(),
            )
        };
        let (n, round) = match round_budget {
            None => (n, plan_of(n, opts.kicks)?),
            Some(rb) => match fit_prefix(n, rb, opts.kicks, plan_of)? {
                Some(x) => x,
                None => return stop(ad, budget_spent(ad)),
            },
        };
        let allowance = ad.round_allowance_s;
        let record = AdaptiveRound {
            round: ad.rounds.len() + 1,
            measured_before: measured.len(),
            pairs: picks[..n].to_vec(),
            first_step,
            planned_s: round.durations.optimized_s,
            allowance_s: allowance,
            components: choice.components,
            predicted_psnr_before_db: Some(round3(now)),
            predicted_psnr_after_db: round3(psnr_of_mse(choice.picks[n - 1].expected_mse)),
            observed_residual: Some(choice.observed_residual),
            expected_residual: Some(choice.expected_residual),
            outside_prior: choice.outside_prior,
        };
        ad.rounds.push(record);
        sp.chosen += n;
        sp.planned_s += round.durations.optimized_s + allowance;
        sp.predicted_psnr_db = round3(psnr_of_mse(choice.picks[n - 1].expected_mse));
        for s in &choice.picks[..n] {
            sp.picks.push((s.pair, round3(psnr_of_mse(s.expected_mse))));
        }
        let shift = offset + allowance;
        for mut s in round.steps {
            s.capture_start_s += shift;
            self.steps.push(s);
        }
        self.skipped.extend(round.skipped);
        let d = &mut self.durations;
        let r = &round.durations;
        d.optimized_s += r.optimized_s + allowance;
        d.stop_and_go_s += r.stop_and_go_s + allowance;
        d.canonical_s += r.canonical_s;
        d.canonical_overlapped_s += r.canonical_overlapped_s;
        d.lower_bound_s += r.lower_bound_s;
        d.optimized_motion_s += r.optimized_motion_s;
        Ok(true)
    }
}

/// The stop reason when the next round does not fit the rig budget.
fn budget_spent(ad: &AdaptiveInfo) -> String {
    format!(
        "the rig budget is spent ({:.0} s planned of {:.0} s)",
        ad.spent_s(),
        ad.stop.rig_budget_s.unwrap_or(f64::NAN)
    )
}

fn round3(x: f64) -> f64 {
    (x * 1000.0).round() / 1000.0
}

/// How `plan.json`'s `sparse.target` names an adaptive stop.
fn describe(stop: AdaptiveStop) -> String {
    match (stop.target_psnr_db, stop.rig_budget_s) {
        (Some(t), Some(b)) => format!("adaptive: predicted PSNR {t} dB or rig budget {b} s"),
        (Some(t), None) => format!("adaptive: predicted PSNR {t} dB"),
        (None, Some(b)) => format!("adaptive: rig budget {b} s"),
        (None, None) => "adaptive".into(),
    }
}
