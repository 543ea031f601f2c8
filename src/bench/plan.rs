//! `gonio bench plan`: the planner's quality against its time budget (optimized duration
//! against the lower bound), one row per rig and budget.

use anyhow::Result;
use gonio::cli::bench::RigArgs;
use serde::Serialize;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct PlanBenchArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    /// `bonn81` (default), `uniform15`, `fibonacci:N` or a file.
    #[arg(long, default_value = "bonn81")]
    pub sweep: String,
    /// Optimizer wall-clock caps in seconds (kicks unlimited): how the order improves
    /// with time on this machine, and how many kicks fit (`kicks` column; the reproducible
    /// budget of `gonio plan --plan-kicks`).
    #[arg(long, value_delimiter = ',', default_values_t = [0.0, 0.5, 1.0, 2.0, 5.0])]
    pub budgets: Vec<f64>,
    /// Kick budgets (reproducible), one row each, in addition to --budgets.
    #[arg(long, value_delimiter = ',')]
    pub kicks: Vec<usize>,
    /// Several rig files, comma-separated (e.g. every file in devices/rigs/): one table with
    /// a row per rig and budget. Takes the place of `--rig`.
    #[arg(long, value_delimiter = ',')]
    pub rigs: Vec<std::path::PathBuf>,
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct PlanRow {
    rig: String,
    measured: usize,
    /// Wall-clock cap (null for a kick budget).
    budget_s: Option<f64>,
    /// Kicks that ran.
    kicks: usize,
    canonical_s: f64,
    /// Optimized order, stop and go (no readout overlap).
    stop_and_go_s: f64,
    /// Optimized order as the engine runs it (readout overlapping the next move).
    optimized_s: f64,
    lower_bound_s: f64,
    readout_overlap_s: f64,
    optimized_over_canonical: f64,
    optimized_over_bound: f64,
    /// No order can beat this fraction of the canonical duration.
    bound_over_canonical: f64,
    plan_time_s: f64,
}

pub fn run(a: PlanBenchArgs) -> Result<ExitCode> {
    use anyhow::Context;
    let rigs = if a.rigs.is_empty() {
        vec![a.rig.load()?]
    } else {
        a.rigs
            .iter()
            .map(|p| gonio_devices::rig::RigSpec::load(p).with_context(|| format!("loading rig {}", p.display())))
            .collect::<Result<Vec<_>>>()?
    };
    let sweep = gonio_dataset::sweep::Sweep::resolve(&a.sweep)?;
    for &b in &a.budgets {
        anyhow::ensure!(
            b.is_finite() && (0.0..=600.0).contains(&b),
            "--budgets: {b} is not in 0 ..= 600 s"
        );
    }
    let mut rows = Vec::new();
    let budgets: Vec<(Option<f64>, usize)> = a
        .budgets
        .iter()
        .map(|&b| (Some(b), usize::MAX))
        .chain(a.kicks.iter().map(|&k| (None, k)))
        .collect();
    for (rig, &(b, kicks)) in rigs.iter().flat_map(|r| budgets.iter().map(move |b| (r, b))) {
        let opts = gonio_acquire::plan::PlanOptions {
            kicks,
            time_cap: b.map(std::time::Duration::from_secs_f64),
            ..Default::default()
        };
        let p = gonio_acquire::plan::Plan::build(rig, &sweep, &opts)
            .with_context(|| format!("planning sweep `{}` on rig `{}`", sweep.name, rig.name))?;
        let d = &p.durations;
        rows.push(PlanRow {
            rig: rig.name.clone(),
            measured: p.steps.len(),
            budget_s: b,
            kicks: p.budget.kicks_done,
            canonical_s: d.canonical_s,
            stop_and_go_s: d.stop_and_go_s,
            optimized_s: d.optimized_s,
            lower_bound_s: d.lower_bound_s,
            readout_overlap_s: d.readout_overlap_s,
            optimized_over_canonical: d.optimized_s / d.canonical_s,
            optimized_over_bound: d.optimized_s / d.lower_bound_s,
            bound_over_canonical: d.lower_bound_s / d.canonical_s,
            plan_time_s: p.plan_time_s,
        });
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&rows)?);
    } else {
        println!("sweep {}", sweep.name);
        println!(
            "{:<20} {:>8} {:>8} {:>8} {:>12} {:>12} {:>12} {:>12} {:>10} {:>9} {:>11} {:>10}",
            "rig",
            "measured",
            "budget s",
            "kicks",
            "canonical s",
            "stop+go s",
            "optimized s",
            "bound s",
            "opt/canon",
            "opt/bound",
            "bound/canon",
            "plan s"
        );
        for r in &rows {
            println!(
                "{:<20} {:>8} {:>8} {:>8} {:>12.0} {:>12.0} {:>12.0} {:>12.0} {:>10.3} {:>9.3} {:>11.3} {:>10.2}",
                r.rig,
                r.measured,
                r.budget_s.map(|b| format!("{b:.2}")).unwrap_or_else(|| "-".into()),
                r.kicks,
                r.canonical_s,
                r.stop_and_go_s,
                r.optimized_s,
                r.lower_bound_s,
                r.optimized_over_canonical,
                r.optimized_over_bound,
                r.bound_over_canonical,
                r.plan_time_s
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
