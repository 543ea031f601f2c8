//! `gonio plan`: plan a sweep for a rig and print it, moving nothing.

use super::common::{RigArgs, SweepArgs};
use crate::plan::{Plan, PlanCounts};
use anyhow::Result;
use serde::Serialize;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct PlanArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    #[command(flatten)]
    pub sweep: SweepArgs,
    /// Print the whole plan (summary, durations, every step, every skipped pair) as JSON.
    #[arg(long)]
    pub json: bool,
    /// In text mode, list this many steps of the optimized order.
    #[arg(long, default_value_t = 10)]
    pub show: usize,
}

#[derive(Serialize)]
struct PlanJson<'a> {
    counts: PlanCounts,
    #[serde(flatten)]
    plan: &'a Plan,
}

pub fn run(args: PlanArgs) -> Result<ExitCode> {
    let rig = args.rig.load()?;
    let sweep = args.sweep.load()?;
    let plan = args.sweep.plan(&rig, &sweep)?;
    let counts = plan.counts();
    if args.json {
        println!("{}", serde_json::to_string(&PlanJson { counts, plan: &plan })?);
        return Ok(ExitCode::SUCCESS);
    }
    let d = &plan.durations;
    println!(
        "rig {} · sweep {} · {} pairs · policy {:?}",
        plan.rig, plan.sweep, plan.pairs, plan.policy
    );
    println!(
        "  feasible {}  substituted {}  skipped {}",
        counts.feasible, counts.substituted, counts.skipped
    );
    for (k, v) in &counts.skipped_reasons {
        println!("    skipped {v:>5} × {k}");
    }
    println!(
        "  duration canonical order  {:>9.0} s ({:.2} h)",
        d.canonical_s,
        d.canonical_s / 3600.0
    );
    println!(
        "  duration optimized order  {:>9.0} s ({:.2} h, {:.3} × canonical)",
        d.optimized_s,
        d.optimized_s / 3600.0,
        d.optimized_s / d.canonical_s
    );
    println!(
        "  lower bound               {:>9.0} s ({:.2} h; optimized = {:.3} × bound)",
        d.lower_bound_s,
        d.lower_bound_s / 3600.0,
        d.optimized_s / d.lower_bound_s
    );
    println!("  capture per measurement   {:>9.2} s", d.capture_per_measurement_s);
    if let Some(iso) = &plan.isotropic {
        println!(
            "  isotropic: {} classes ({} unreachable), {} pairs measured, {} reconstructed on export",
            iso.classes,
            iso.unreachable_classes,
            plan.steps.len(),
            counts.reconstructed
        );
        println!(
            "  full sweep would take     {:>9.0} s ({:.2} h optimized; canonical {:.0} s); saved {:.0} s ({:.1} %)",
            iso.full_durations.optimized_s,
            iso.full_durations.optimized_s / 3600.0,
            iso.full_durations.canonical_s,
            iso.saved_s,
            100.0 * iso.saved_s / iso.full_durations.optimized_s
        );
    }
    println!("  plan computed in {:.2} s", plan.plan_time_s);
    if args.show > 0 {
        println!("  first steps (index: light θ,φ → view θ,φ; axes °; move s):");
        for s in plan.steps.iter().take(args.show) {
            println!(
                "    {:>5}: ({:>4.1},{:>5.1}) → ({:>4.1},{:>5.1})  [{}]  {:.2}",
                s.index,
                s.light_deg[0],
                s.light_deg[1],
                s.view_deg[0],
                s.view_deg[1],
                s.axes_deg
                    .iter()
                    .map(|a| format!("{a:8.2}"))
                    .collect::<Vec<_>>()
                    .join(" "),
                s.transition_s
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
