//! The sparse-acquisition flags that `gonio plan` and `gonio acquire` share
//! (`--prior`, `--pairs`, `--fraction`, `--rig-budget`), resolving `--prior`, and the
//! summary both print. Not behind the `btf` feature: a lab build plans and acquires sparse
//! datasets (the design is `gonio_acquire::plan::sparse`); completing them is `gonio
//! complete`'s job.

use anyhow::{bail, Context, Result};
use gonio_acquire::plan::adaptive::{AdaptiveStop, AdaptiveTuning};
use gonio_acquire::plan::sparse::{SparseDesign, SparseInfo, SparseRequest, SparseTarget};
use gonio_acquire::plan::Plan;
use gonio_sparse::Prior;
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug, Clone, Default)]
pub struct SparseArgs {
    /// Sparse acquisition: the prior that chooses the pairs (`default` or a .gprior file;
    /// `default` when omitted). Used with --pairs, --fraction or --rig-budget.
    #[arg(long)]
    pub prior: Option<String>,
    /// Sparse: use only the prior's leading C components (a design or completion needs at
    /// least as many pairs as components; the default prior has 512).
    #[arg(long)]
    pub components: Option<usize>,
    /// Sparse: measure this many pairs (chosen by optimal design in the prior).
    #[arg(long, conflicts_with_all = ["fraction", "rig_budget"])]
    pub pairs: Option<usize>,
    /// Sparse: measure this share of the feasible pairs.
    #[arg(long, conflicts_with = "rig_budget")]
    pub fraction: Option<f64>,
    /// Sparse: at most this planned rig time in seconds (motion counted).
    #[arg(long)]
    pub rig_budget: Option<f64>,
    /// Sparse: how the pairs are chosen: `a-optimal` (largest error drop per pair) or
    /// `motion-aware` (per second of rig time: capture plus the move from the nearest
    /// chosen pair).
    #[arg(long, default_value = "a-optimal", value_parser = |s: &str| s.parse::<SparseDesign>())]
    pub design: SparseDesign,
    /// Adaptive acquisition (`gonio acquire` only): measure in rounds, each chosen from the
    /// values measured so far, until the predicted PSNR reaches --target-psnr or the
    /// --rig-budget is spent (docs/guide/sparse.md).
    #[arg(long, conflicts_with_all = ["pairs", "fraction"])]
    pub adaptive: bool,
    /// Adaptive: stop when the predicted PSNR of the completed dataset reaches this (dB,
    /// 8-bit sRGB). A real rig has no truth, so the target is the prediction.
    #[arg(long, requires = "adaptive")]
    pub target_psnr: Option<f64>,
    /// Adaptive: weight of the residual the measured values show when choosing a round's
    /// pairs, beside the A-optimal gain (default 0: the rounds continue the A-optimal
    /// design and the residual decides when to stop; docs/guide/sparse.md has the
    /// measurements). Recorded in plan.json.
    #[arg(long, requires = "adaptive", allow_negative_numbers = true)]
    pub residual_weight: Option<f64>,
    /// Adaptive: rig time charged for each analysis between rounds, seconds (default 30). A
    /// declared cost, so the rounds do not depend on the machine's speed; the summary
    /// reports the real wall time beside it. Recorded in plan.json.
    #[arg(long, requires = "adaptive", allow_negative_numbers = true)]
    pub round_allowance: Option<f64>,
}

impl SparseArgs {
    /// The target, if a sparse plan is asked for. `--prior` alone is refused: it names the
    /// prior but not how many pairs to measure.
    pub fn target(&self) -> Result<Option<SparseTarget>> {
        let t = SparseTarget::from_flags(self.pairs, self.fraction, self.rig_budget);
        if self.adaptive {
            // The stop is checked by `adaptive_stop`; the budget (if any) is the target.
            return Ok(Some(t.unwrap_or(SparseTarget::RigBudget(f64::INFINITY))));
        }
        if t.is_none() {
            if let Some(p) = &self.prior {
                bail!("--prior {p}: say how much to measure with --pairs N, --fraction F or --rig-budget SECONDS");
            }
        }
        Ok(t)
    }
}

/// The default prior's path: next to the `gonio-sparse` crate in the source tree, or
/// `$GONIO_PRIOR_DEFAULT`.
pub fn default_prior_path() -> PathBuf {
    if let Ok(p) = std::env::var("GONIO_PRIOR_DEFAULT") {
        return PathBuf::from(p);
    }
    Path::new(env!("CARGO_MANIFEST_DIR")).join("sparse/priors/default-bonn81.gprior")
}

/// Load `--prior` (None and `default` mean the default prior).
pub fn load_prior(spec: Option<&str>) -> Result<(Prior, PathBuf)> {
    let path = match spec {
        None | Some("default") => default_prior_path(),
        Some(p) => PathBuf::from(p),
    };
    if !path.is_file() && matches!(spec, None | Some("default")) {
        bail!(
            "the default prior {} is missing: build it with the command in \
             simulator/families/prior-bonn81.toml (or set GONIO_PRIOR_DEFAULT)",
            path.display()
        );
    }
    let p = Prior::load(&path).with_context(|| format!("--prior {}", path.display()))?;
    Ok((p, path))
}

/// The prior with only its leading `components` (`--components`), checked.
pub fn with_components(prior: Prior, components: Option<usize>) -> Result<Prior> {
    match components {
        None => Ok(prior),
        Some(c) if c == 0 || c > prior.components() => bail!(
            "--components {c}: the prior has {} components; use 1 to {}",
            prior.components(),
            prior.components()
        ),
        Some(c) => Ok(prior.truncated(c)),
    }
}

/// A loaded prior and what to ask of it: the session's and the planner's input.
pub struct LoadedSparse {
    pub prior: Prior,
    pub name: String,
    pub target: SparseTarget,
    pub design: SparseDesign,
    /// `--adaptive`: the stop (then `target` is unused).
    pub adaptive: Option<AdaptiveStop>,
    pub adaptive_tuning: AdaptiveTuning,
}

impl LoadedSparse {
    /// Load the prior the flags name, if the flags ask for a sparse plan.
    pub fn from_args(a: &SparseArgs) -> Result<Option<LoadedSparse>> {
        let Some(target) = a.target()? else {
            return Ok(None);
        };
        let (prior, path) = load_prior(a.prior.as_deref())?;
        let prior = with_components(prior, a.components)?;
        let adaptive = if a.adaptive {
            Some(AdaptiveStop::new(a.target_psnr, a.rig_budget).map_err(anyhow::Error::msg)?)
        } else {
            None
        };
        Ok(Some(LoadedSparse {
            prior,
            name: path.display().to_string(),
            target,
            design: a.design,
            adaptive,
            adaptive_tuning: AdaptiveTuning::new(a.residual_weight, a.round_allowance).map_err(anyhow::Error::msg)?,
        }))
    }

    /// The planner's request (the prior's residual variance regularises the design).
    pub fn request(&self) -> SparseRequest<'_> {
        SparseRequest {
            prior: &self.prior,
            prior_name: &self.name,
            target: self.target,
            noise_var: self.prior.header.residual_var,
            design: self.design,
        }
    }
}

/// The sparse plan's summary lines (`gonio plan`, `gonio acquire`).
pub fn print_summary(plan: &Plan, info: &SparseInfo) {
    println!(
        "rig {} · sweep {} · prior {} · {}",
        plan.rig, plan.sweep, info.prior, info.target
    );
    println!(
        "  chosen {} of {} feasible pairs ({:.1} %) by {}",
        info.chosen,
        info.feasible,
        100.0 * info.chosen as f64 / info.feasible.max(1) as f64,
        info.design
    );
    println!(
        "  planned rig time {:>9.0} s ({:.3} × full optimized {:.0} s, {:.3} × canonical {:.0} s)",
        info.planned_s,
        info.planned_s / info.full_optimized_s,
        info.full_optimized_s,
        info.planned_s / info.full_canonical_s,
        info.full_canonical_s
    );
    match &info.adaptive {
        None => println!(
            "  predicted PSNR of the completed dataset {:.2} dB (8-bit sRGB, over the prior, noiseless)",
            info.predicted_psnr_db
        ),
        Some(ad) => {
            for r in &ad.rounds {
                let before = r
                    .predicted_psnr_before_db
                    .map_or("the prior predicts".to_string(), |b| format!("predicted PSNR {b:.2} →"));
                println!(
                    "  round {}: {} pairs, {:.0} s planned (+{:.0} s analysis), {before} {:.2} dB{}",
                    r.round,
                    r.pairs.len(),
                    r.planned_s,
                    r.allowance_s,
                    r.predicted_psnr_after_db,
                    if r.outside_prior { " (outside the prior)" } else { "" }
                );
            }
            if let Some(why) = &ad.finished {
                println!("  finished: {why}");
            }
        }
    }
}
