//! `gonio plan`: plan a sweep for a rig and print it, moving nothing.

use super::common::{load_sample, RigArgs, SweepArgs};
use anyhow::Result;
use gonio_acquire::plan::{Plan, PlanCounts};
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
    /// Sample to plan for (built-in name or TOML file). A sample that declares
    /// `isotropic = true` is planned as with `--isotropic`, as `gonio acquire` does.
    #[arg(long)]
    pub sample: Option<String>,
    #[command(flatten)]
    pub sparse: super::sparse::SparseArgs,
    #[command(flatten)]
    pub fly: super::common::FlyArgs,
}

/// `gonio plan --json` of a sparse plan: the plan carries its `sparse` field.
#[derive(Serialize)]
struct SparsePlanJson<'a> {
    counts: PlanCounts,
    #[serde(flatten)]
    plan: &'a Plan,
}

#[derive(Serialize)]
struct PlanJson<'a> {
    counts: PlanCounts,
    /// Lower bound ÷ canonical duration: no order can be faster than this fraction of the
    /// canonical one, so it shows which "× canonical" targets are reachable at all.
    bound_over_canonical: f64,
    /// Whether the reduced isotropic set was planned because the sample declares it.
    #[serde(skip_serializing_if = "Option::is_none")]
    isotropic_from_sample: Option<String>,
    /// Wall seconds spent planning (not part of the plan, which is reproducible data).
    plan_time_s: f64,
    #[serde(flatten)]
    plan: &'a Plan,
}

pub fn run(args: PlanArgs) -> Result<ExitCode> {
    let rig = args.rig.load()?;
    let sweep = args.sweep.load()?;
    let sample = args.sample.as_deref().map(load_sample).transpose()?;
    let from_sample = sample
        .as_ref()
        .filter(|s| s.isotropic && !args.sweep.isotropic)
        .map(|s| s.name.clone());
    let sweep_args = SweepArgs {
        isotropic: args.sweep.isotropic || from_sample.is_some(),
        ..args.sweep.clone()
    };
    let fly = args.fly.options()?;
    let plan = sweep_args.plan(&rig, &sweep)?;
    if let Some(sparse) = super::sparse::LoadedSparse::from_args(&args.sparse)? {
        let opts = args.sweep.plan_options()?;
        // An adaptive plan shows its first round: the later ones depend on measured values.
        let plan = match sparse.adaptive {
            Some(stop) => {
                if fly.is_some() {
                    anyhow::bail!("--adaptive with --fly: adaptive rounds are measured stop and go");
                }
                let req = gonio_acquire::plan::adaptive::AdaptiveRequest {
                    prior: &sparse.prior,
                    prior_name: &sparse.name,
                    stop,
                    noise_var: sparse.prior.header.residual_var,
                    tuning: sparse.adaptive_tuning,
                };
                Plan::build_adaptive(&rig, &sweep, &opts, &plan, req)?
            }
            None => Plan::build_sparse(&rig, &sweep, &opts, &plan, sparse.request())?,
        };
        let plan = match fly {
            Some(f) => plan.into_fly(&rig, &opts, f)?,
            None => plan,
        };
        let info = plan.sparse.as_ref().expect("a sparse plan records its design");
        if args.json {
            let j = SparsePlanJson {
                counts: plan.counts(),
                plan: &plan,
            };
            println!("{}", serde_json::to_string(&j)?);
        } else {
            super::sparse::print_summary(&plan, info);
            if let Some(f) = &plan.fly {
                print_fly(f, plan.durations.canonical_s);
            }
        }
        return Ok(ExitCode::SUCCESS);
    }
    let plan = match fly {
        Some(f) => plan.into_fly(&rig, &args.sweep.plan_options()?, f)?,
        None => plan,
    };
    let counts = plan.counts();
    let d = &plan.durations;
    let bound_over_canonical = d.lower_bound_s / d.canonical_s;
    if args.json {
        let out = PlanJson {
            counts,
            bound_over_canonical,
            isotropic_from_sample: from_sample,
            plan_time_s: plan.plan_time_s,
            plan: &plan,
        };
        println!("{}", serde_json::to_string(&out)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "rig {} · sweep {} · {} pairs · policy {}",
        plan.rig,
        plan.sweep,
        plan.pairs,
        match plan.policy {
            gonio_acquire::plan::Policy::Skip => "skip",
            gonio_acquire::plan::Policy::Substitute => "substitute",
        }
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
    if d.readout_overlap_s > 0.0 {
        println!(
            "  optimized, stop and go    {:>9.0} s ({:.2} h, {:.3} × canonical)",
            d.stop_and_go_s,
            d.stop_and_go_s / 3600.0,
            d.stop_and_go_s / d.canonical_s
        );
    }
    println!(
        "  duration optimized order  {:>9.0} s ({:.2} h, {:.3} × canonical{})",
        d.optimized_s,
        d.optimized_s / 3600.0,
        d.optimized_s / d.canonical_s,
        if d.readout_overlap_s > 0.0 {
            format!("; the {:.2} s readout overlaps each move", d.readout_overlap_s)
        } else {
            String::new()
        }
    );
    println!(
        "  lower bound               {:>9.0} s ({:.2} h; optimized = {:.3} × bound)",
        d.lower_bound_s,
        d.lower_bound_s / 3600.0,
        d.optimized_s / d.lower_bound_s
    );
    println!(
        "  bound / canonical         {bound_over_canonical:>9.3}   (no order beats this fraction of the canonical time)"
    );
    println!("  capture per measurement   {:>9.2} s", d.capture_per_measurement_s);
    if let Some(f) = &plan.fly {
        print_fly(f, d.canonical_s);
    }
    if let Some(iso) = &plan.isotropic {
        if let Some(name) = &from_sample {
            println!("  isotropic because sample `{name}` declares it (isotropic = true)");
        }
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
    println!(
        "  plan computed in {:.2} s ({} of {} kicks{})",
        plan.plan_time_s,
        plan.budget.kicks_done,
        plan.budget.kicks,
        plan.budget
            .time_cap_s
            .map(|c| format!(", wall-clock cap {c} s: not reproducible"))
            .unwrap_or_default()
    );
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

/// The fly-scan lines of `gonio plan --fly`.
fn print_fly(f: &gonio_acquire::plan::fly::FlyInfo, canonical: f64) {
    println!(
        "  fly-scan (blur bound {} ° of light direction per exposure; axis {} moves, camera and sample stand still):",
        f.blur_deg, f.axis
    );
    println!(
        "    fly                     {:>9.0} s ({:.2} h, {:.3} × canonical)",
        f.fly_s,
        f.fly_s / 3600.0,
        f.fly_s / canonical
    );
    println!(
        "    stop and go, overlapped {:>9.0} s ({:.3} × canonical)",
        f.stop_and_go_overlapped_s,
        f.stop_and_go_overlapped_s / canonical
    );
    println!(
        "    fly lower bound         {:>9.0} s ({:.3} × canonical; the camera alone needs {:.0} s = {:.3} ×)",
        f.lower_bound_s,
        f.lower_bound_s / canonical,
        f.readout_bound_s,
        f.readout_bound_s / canonical
    );
    println!(
        "    {} of {} segments flown, {} pairs in flight, {} stop and go; largest sweep {:.3} °, image motion {:.2} px",
        f.flown_segments, f.segments, f.flown_pairs, f.stop_and_go_pairs, f.max_light_sweep_deg, f.max_image_blur_px
    );
    for (why, n) in &f.stop_and_go_reasons {
        println!("      stop and go {n:>5} × {why}");
    }
    if let Some(nk) = &f.not_kept {
        println!(
            "    (the fly order kept out: {:.0} s, {} segments / {} pairs in flight; stop and go: {})",
            nk.fly_s,
            nk.flown_segments,
            nk.flown_pairs,
            nk.stop_and_go_reasons
                .iter()
                .map(|(k, n)| format!("{n} × {k}"))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    if !f.velocity_profile.is_empty() {
        match &f.constant_velocity_reason {
            Some(why) => println!("    velocity profile {} ({why})", f.velocity_profile),
            None => println!("    velocity profile {}", f.velocity_profile),
        }
    }
}
