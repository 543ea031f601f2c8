//! Sparse plans (issue 29): measure the pairs a greedy A-optimal design in an angular prior
//! chooses, and predict the rest (`gonio complete`).
//!
//! Planning a sparse acquisition is planning: the design picks pairs among the full plan's
//! feasible ones, and [`Plan::build_pairs`] orders them like any other plan. It lives here,
//! not in the command line, so `gonio plan --prior` and `gonio acquire --prior` share one
//! path and the lab build (no BTF processing) can run it: the prior's numerics are the
//! `gonio-sparse` crate (nalgebra, no faer). The result is recorded in `plan.json`
//! ([`Plan::sparse`]): the chosen pairs in design order with the expected PSNR after each,
//! the planned rig time and the predicted error.

use super::{Plan, PlanError, PlanOptions};
use gonio_dataset::sweep::Sweep;
use gonio_devices::rig::RigSpec;
use gonio_sparse::Prior;
use serde::{Deserialize, Serialize};

/// What a sparse plan is asked for.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum SparseTarget {
    /// This many pairs.
    Pairs(usize),
    /// This share of the feasible pairs.
    Fraction(f64),
    /// At most this planned rig time (s), motion included.
    RigBudget(f64),
}

impl SparseTarget {
    /// The target of the `--pairs`, `--fraction` and `--rig-budget` flags (at most one is
    /// given; clap enforces it), if any.
    pub fn from_flags(pairs: Option<usize>, fraction: Option<f64>, budget: Option<f64>) -> Option<SparseTarget> {
        pairs
            .map(SparseTarget::Pairs)
            .or(fraction.map(SparseTarget::Fraction))
            .or(budget.map(SparseTarget::RigBudget))
    }
}

/// The sparse part of a plan (`plan.json` field `sparse`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SparseInfo {
    /// The prior the pairs were chosen in (as named on the command line: a path).
    pub prior: String,
    pub design: String,
    pub target: String,
    /// Pairs chosen, and the feasible pairs they were chosen from.
    pub chosen: usize,
    pub feasible: usize,
    /// Planned rig time of the chosen pairs in the optimized order (s).
    pub planned_s: f64,
    /// The full sweep's planned times (s): optimized order, canonical order.
    pub full_optimized_s: f64,
    pub full_canonical_s: f64,
    /// Expected PSNR of the completed dataset over the prior (8-bit sRGB scale, noiseless).
    pub predicted_psnr_db: f64,
    /// The chosen pairs in the order the design picked them, each with the expected PSNR
    /// after it (every prefix is itself a design).
    pub picks: Vec<(usize, f64)>,
    /// Present for an adaptive acquisition: its stop, rounds and analyses.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptive: Option<AdaptiveInfo>,
}

// The records of an adaptive acquisition (`plan.json` `sparse.adaptive`): they live here,
// with the sparse plan they extend; the adaptive planner chooses and fills them.

/// When an adaptive run stops (at least one is given; with both, at whichever comes first).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdaptiveStop {
    /// Stop when the predicted PSNR of the completed dataset reaches this (dB, 8-bit sRGB).
    pub target_psnr_db: Option<f64>,
    /// Stop when the planned rig time (rounds plus analysis allowances) would exceed this (s).
    pub rig_budget_s: Option<f64>,
}

impl AdaptiveStop {
    /// Check the flags: at least one, each a finite positive number.
    pub fn new(target_psnr_db: Option<f64>, rig_budget_s: Option<f64>) -> Result<AdaptiveStop, PlanError> {
        if target_psnr_db.is_none() && rig_budget_s.is_none() {
            return Err(invalid(
                "--adaptive needs a stop: --target-psnr DB (predicted PSNR of the completed dataset) \
                 and/or --rig-budget SECONDS"
                    .into(),
            ));
        }
        if let Some(t) = target_psnr_db {
            if !(t.is_finite() && t > 0.0 && t < 100.0) {
                return Err(invalid(format!(
                    "--target-psnr {t}: use a PSNR in dB between 0 and 100"
                )));
            }
        }
        if let Some(b) = rig_budget_s {
            if !(b.is_finite() && b > 0.0) {
                return Err(invalid(format!(
                    "--rig-budget {b}: must be a positive number of seconds"
                )));
            }
        }
        Ok(AdaptiveStop {
            target_psnr_db,
            rig_budget_s,
        })
    }
}

/// One round as `plan.json` records it (`sparse.adaptive.rounds`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct AdaptiveRound {
    /// 1, 2, …
    pub round: usize,
    /// Pairs measured before the round.
    pub measured_before: usize,
    /// The round's pairs in the order the analysis chose them.
    pub pairs: Vec<usize>,
    /// The round's steps: `plan.steps[first_step..first_step + pairs.len()]`.
    pub first_step: usize,
    /// Planned rig time of the round alone (s), and the analysis allowance charged before it.
    pub planned_s: f64,
    pub allowance_s: f64,
    /// Components of the prior the analysis used (at most the pairs measured).
    pub components: usize,
    /// Predicted PSNR of the completed dataset before the round (dB; none before round 1,
    /// nothing is measured) and after it: round 1's is the prior's own, later rounds'
    /// include the residual the data showed.
    pub predicted_psnr_before_db: Option<f64>,
    pub predicted_psnr_after_db: f64,
    /// Mean leave-one-out residual on the measured pairs, and what the prior expects there
    /// (model space); `None` for round 1.
    pub observed_residual: Option<f64>,
    pub expected_residual: Option<f64>,
    /// The residual is far above what the prior expects: the material is outside it, and
    /// the round's pairs go where the residual is.
    pub outside_prior: bool,
}

/// The adaptive part of a sparse plan (`plan.json` field `sparse.adaptive`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct AdaptiveInfo {
    pub stop: AdaptiveStop,
    /// The prior's payload hash and the components used: a resumed run must analyse with
    /// the very prior the earlier rounds were chosen in.
    pub prior_sha256: String,
    pub components: usize,
    pub noise_var: f64,
    pub first_share: f64,
    pub round_allowance_s: f64,
    /// Weight of the residual term when choosing a round's pairs (the adaptive planner's `RESIDUAL_WEIGHT`).
    pub residual_weight: f64,
    pub analysis_texels: usize,
    pub max_rounds: usize,
    /// The order optimiser's kicks and seed: later rounds (also after a resume) are
    /// planned with the first round's.
    pub plan_kicks: usize,
    pub plan_seed: u64,
    /// Pairs of the sweep the rig cannot measure (never candidates).
    pub infeasible: Vec<usize>,
    pub rounds: Vec<AdaptiveRound>,
    /// Why the run stopped choosing (absent while rounds may follow).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub finished: Option<String>,
    /// The last analysis' predicted PSNR (dB) and whether it found the material outside
    /// the prior (absent until a round after the first was analysed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub predicted_psnr_db: Option<f64>,
    #[serde(default)]
    pub outside_prior: bool,
}

impl AdaptiveInfo {
    /// Every pair chosen so far, in the order chosen.
    pub fn chosen(&self) -> Vec<usize> {
        self.rounds.iter().flat_map(|r| r.pairs.iter().copied()).collect()
    }

    /// Planned rig time so far: rounds plus analysis allowances (s).
    pub fn spent_s(&self) -> f64 {
        self.rounds.iter().map(|r| r.planned_s + r.allowance_s).sum()
    }
}

/// The longest prefix (of `n` picks) whose plan fits `budget`: bisection on quick plans,
/// then the real plan, shortened while it does not fit. `None` when not even one fits.
pub(crate) fn fit_prefix(
    n: usize,
    budget: f64,
    kicks: usize,
    plan_of: impl Fn(usize, usize) -> Result<Plan, PlanError>,
) -> Result<Option<(usize, Plan)>, PlanError> {
    let quick = kicks.min(2000);
    let (mut lo, mut hi) = (0usize, n);
    while lo < hi {
        let mid = (lo + hi).div_ceil(2);
        if plan_of(mid, quick)?.durations.optimized_s <= budget {
            lo = mid;
        } else {
            hi = mid - 1;
        }
    }
    if lo == 0 {
        return Ok(None);
    }
    let mut n = lo;
    let mut plan = plan_of(n, kicks)?;
    while plan.durations.optimized_s > budget && n > 1 {
        n -= 1;
        plan = plan_of(n, kicks)?;
    }
    if plan.durations.optimized_s > budget {
        return Ok(None);
    }
    Ok(Some((n, plan)))
}

/// PSNR (dB) of a model-space mean squared error (the gamma space is close to 8-bit sRGB).
pub fn psnr_of_mse(mse: f64) -> f64 {
    -10.0 * mse.max(1e-20).log10()
}

/// The value unit of a dataset's `values` text, as a prior records it: datasets that differ
/// only in wording (truth vs. measurement of the same normalised signal) share a unit.
pub fn units_key(values: &str) -> String {
    let v = values.to_ascii_lowercase();
    if v.contains("normalised sensor signal") || v.contains("normalized sensor signal") {
        "normalized_signal".into()
    } else if v.contains("brdf (1/sr)") {
        "brdf_1_per_sr".into()
    } else {
        values.to_string()
    }
}

/// How the pairs are chosen.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SparseDesign {
    /// Greedy A-optimal: the largest drop of the expected error per pair.
    #[default]
    AOptimal,
    /// Greedy A-optimal per second of rig time: the drop of the expected error divided by
    /// what the pair costs the rig (its capture plus the move from the nearest chosen pair,
    /// with the readout overlapping the move where the camera does).
    MotionAware,
}

impl std::str::FromStr for SparseDesign {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "a-optimal" => Ok(SparseDesign::AOptimal),
            "motion-aware" => Ok(SparseDesign::MotionAware),
            _ => Err(format!("`{s}`: the designs are `a-optimal` and `motion-aware`")),
        }
    }
}

/// A sparse plan's inputs besides the rig and the sweep.
#[derive(Clone, Copy)]
pub struct SparseRequest<'a> {
    pub prior: &'a Prior,
    /// How the prior is named in `plan.json` (its path).
    pub prior_name: &'a str,
    pub target: SparseTarget,
    /// Noise variance per pair in the prior's value space (the design's regulariser; the
    /// prior's own residual variance when nothing better is known).
    pub noise_var: f64,
    pub design: SparseDesign,
}

fn invalid(message: String) -> PlanError {
    PlanError::Sparse { message }
}

impl Plan {
    /// The adaptive part of a sparse plan, if it is one (`plan.json` `sparse.adaptive`).
    pub fn adaptive(&self) -> Option<&AdaptiveInfo> {
        self.sparse.as_ref().and_then(|s| s.adaptive.as_ref())
    }

    /// Choose pairs by greedy A-optimal design over the feasible pairs of `full` (the plan
    /// of the whole sweep) and plan them. A rig budget is met by the longest greedy prefix
    /// whose plan fits (bisection on quick plans, then the real plan). The prior must be
    /// for this sweep; the chosen set must determine the prior's coefficients.
    pub fn build_sparse(
        rig: &RigSpec,
        sweep: &Sweep,
        opts: &PlanOptions,
        full: &Plan,
        req: SparseRequest,
    ) -> Result<Plan, PlanError> {
        Plan::build_sparse_with(rig, sweep, opts, full, req, true)
    }

    /// [`Plan::build_sparse`]; `all_components`: refuse a design with fewer pairs than the
    /// prior has components (an adaptive first round completes with at most as many
    /// components as it has pairs, and checks that itself).
    pub(crate) fn build_sparse_with(
        rig: &RigSpec,
        sweep: &Sweep,
        opts: &PlanOptions,
        full: &Plan,
        req: SparseRequest,
        all_components: bool,
    ) -> Result<Plan, PlanError> {
        if full.isotropic.is_some() {
            return Err(invalid(
                "an isotropic plan and a sparse design do not combine: the prior chooses among all pairs; \
                 drop --isotropic (or the sample's `isotropic = true`) or the sparse flags"
                    .into(),
            ));
        }
        let prior = req.prior;
        let (lights, views) = sweep.directions_deg();
        prior
            .check_sweep(&sweep.name, &lights, &views)
            .map_err(|e| invalid(format!("prior {}: {e}", req.prior_name)))?;
        let mut feasible: Vec<usize> = full.steps.iter().map(|s| s.index).collect();
        feasible.sort_unstable();
        let nf = feasible.len();
        let capture = full.durations.capture_per_measurement_s.max(1e-6);
        let n_max = match req.target {
            SparseTarget::Pairs(n) => {
                if n == 0 || n > nf {
                    return Err(invalid(format!(
                        "--pairs {n}: choose between 1 and the {nf} feasible pairs"
                    )));
                }
                n
            }
            SparseTarget::Fraction(f) => {
                if !(f > 0.0 && f <= 1.0) {
                    return Err(invalid(format!("--fraction {f}: must be in (0, 1]")));
                }
                ((f * nf as f64).round() as usize).clamp(1, nf)
            }
            SparseTarget::RigBudget(b) => {
                if !(b > 0.0 && b.is_finite()) {
                    return Err(invalid(format!(
                        "--rig-budget {b}: must be a positive number of seconds"
                    )));
                }
                // Every pair costs at least one capture (with or without the readout
                // overlapping the move), so no more than b / capture pairs fit.
                ((b / capture).floor() as usize).min(nf)
            }
        };
        if n_max == 0 {
            return Err(invalid(format!(
                "the budget does not cover one capture ({capture:.2} s)"
            )));
        }
        let design = match req.design {
            SparseDesign::AOptimal => gonio_sparse::greedy_design(prior, &feasible, &[], n_max, req.noise_var)
                .map_err(|e| invalid(format!("prior {}: {e}", req.prior_name)))?,
            SparseDesign::MotionAware => motion_aware(rig, full, prior, &feasible, n_max, req)?,
        };
        if design.is_empty() {
            return Err(invalid("the design chose no pair".into()));
        }
        let pairs = sweep.pairs();
        let plan_of = |n: usize, kicks: usize| -> Result<Plan, PlanError> {
            let mut idx: Vec<usize> = design[..n].iter().map(|s| s.pair).collect();
            idx.sort_unstable();
            let chosen: Vec<_> = idx.iter().map(|&i| pairs[i]).collect();
            let o = PlanOptions { kicks, ..opts.clone() };
            Plan::build_pairs(rig, sweep, &chosen, &o)
        };
        let (n, mut plan) = match req.target {
            SparseTarget::RigBudget(b) => fit_prefix(design.len(), b, opts.kicks, plan_of)?
                .ok_or_else(|| invalid(format!("--rig-budget {b} s: not even one pair fits")))?,
            _ => (design.len(), plan_of(design.len(), opts.kicks)?),
        };
        let picks: Vec<usize> = design[..n].iter().map(|s| s.pair).collect();
        let checked = if all_components {
            gonio_sparse::complete::check_design(prior, &picks)
        } else {
            gonio_sparse::complete::check_design(&prior.truncated(prior.components().min(n)), &picks)
        };
        checked.map_err(|e| invalid(format!("{e} (prior {})", req.prior_name)))?;
        plan.pairs = sweep.len();
        plan.sparse = Some(SparseInfo {
            prior: req.prior_name.to_string(),
            design: match req.design {
                SparseDesign::AOptimal => {
                    "greedy Bayesian A-optimal (expected posterior error over every pair of the sweep)".into()
                }
                SparseDesign::MotionAware => "greedy Bayesian A-optimal per second of rig time (error drop ÷ capture \
                                              and move from the nearest chosen pair)"
                    .into(),
            },
            target: format!("{:?}", req.target),
            chosen: n,
            feasible: nf,
            planned_s: plan.durations.optimized_s,
            full_optimized_s: full.durations.optimized_s,
            full_canonical_s: full.durations.canonical_s,
            predicted_psnr_db: psnr_of_mse(design[n - 1].expected_mse),
            picks: design[..n]
                .iter()
                .map(|s| (s.pair, (psnr_of_mse(s.expected_mse) * 1000.0).round() / 1000.0))
                .collect(),
            adaptive: None,
        });
        Ok(plan)
    }
}

/// The motion-aware greedy over the feasible pairs: each pair's pose is the full plan's, a
/// pair costs `max(move, readout) + exposure` with the readout overlapping the move
/// (`capture + move` stop and go), the move from the nearest chosen pair (from home before
/// the first). The design runs to twice a rig budget's estimate (a nearest-neighbour sum is
/// no tour) and the caller trims the prefix on real plans.
fn motion_aware(
    rig: &RigSpec,
    full: &Plan,
    prior: &Prior,
    feasible: &[usize],
    n_max: usize,
    req: SparseRequest,
) -> Result<Vec<gonio_sparse::DesignStep>, PlanError> {
    use gonio_devices::kinematics;
    let motions: Vec<gonio_devices::MotionModel> = rig.axes.iter().map(|a| a.motion()).collect();
    let home = kinematics::for_rig(rig).home();
    let mut pose: Vec<Vec<f64>> = vec![Vec::new(); prior.dims()];
    for s in &full.steps {
        if let Some(p) = pose.get_mut(s.index) {
            *p = s.axes_deg.iter().map(|x| x.to_radians()).collect();
        }
    }
    let moves = |a: &[f64], b: &[f64]| {
        // A free axis (NaN) stays where it is.
        let b: Vec<f64> = b.iter().zip(a).map(|(&y, &x)| if y.is_nan() { x } else { y }).collect();
        kinematics::transition_time(&motions, a, &b)
    };
    let (c, r) = (
        full.durations.capture_per_measurement_s,
        full.durations.readout_overlap_s,
    );
    let budget = match req.target {
        SparseTarget::RigBudget(b) => 2.0 * b,
        _ => f64::INFINITY,
    };
    let steps = gonio_sparse::design::design_by_time(
        prior,
        feasible,
        req.noise_var,
        |m| m.max(r) + (c - r),
        |q| moves(&home, &pose[q]),
        |a, b| moves(&pose[a], &pose[b]),
        budget,
        n_max,
    );
    Ok(steps)
}
