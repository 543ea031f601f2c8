//! `gonio dataset generate`: a family of synthetic datasets with their labels (see
//! `crate::synth::family`); `gonio dataset drift`: a dataset's drift references and a
//! drift-corrected copy (`gonio_dataset::store::drift`).

use crate::synth::family::Family;
use anyhow::{Context, Result};
use gonio_dataset::shard::Shard;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Subcommand, Debug)]
pub enum DatasetCommand {
    /// Generate a family of synthetic samples (parameters drawn from declared ranges), one
    /// ground-truth dataset each, with a labels table (labels.csv, family.json).
    Generate(GenerateArgs),
    /// Check a family directory: every member complete and made from its family.toml; names
    /// the missing ones (exit status 1 when any is). The merge step of a sharded run.
    Check(CheckArgs),
    /// The drift references of an acquisition (`gonio acquire --reference-every`): the
    /// reference pair's level per channel against the first reference, over rig time.
    /// With --correct --out NEW: a corrected copy (each measurement's signal divided by the
    /// reference ratio interpolated in rig time, the dark level kept); the original is
    /// never modified.
    Drift(DriftArgs),
}

#[derive(clap::Args, Debug)]
pub struct DriftArgs {
    /// The dataset directory.
    pub dataset: PathBuf,
    /// Write a drift-corrected copy to --out.
    #[arg(long, requires = "out")]
    pub correct: bool,
    /// Directory of the corrected copy (a new dataset).
    #[arg(long, requires = "correct")]
    pub out: Option<PathBuf>,
    /// Replace a gonio dataset at --out.
    #[arg(long, requires = "correct")]
    pub force: bool,
    /// Values at or above this level were clipped at the sensor's full scale: lower
    /// bounds, left unscaled by --correct (and counted). `off` scales every value.
    /// Default: 1 (the full scale of normalised DN) for single exposures, off for HDR
    /// datasets and calibrated units (no single full scale).
    #[arg(long, requires = "correct", value_name = "LEVEL|off")]
    pub clip: Option<String>,
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct CheckArgs {
    /// The family directory (holding family.toml).
    pub dir: PathBuf,
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct GenerateArgs {
    /// The family spec (TOML; see docs/guide/scale.md, "Dataset families").
    pub spec: PathBuf,
    /// The family directory (members/NNNN/ datasets, labels.csv, family.json, family.toml).
    #[arg(long)]
    pub out: PathBuf,
    /// Generate only shard I of N of the members (1-based, contiguous); the shards write
    /// disjoint member directories of the same --out, with no lock.
    #[arg(long)]
    pub shard: Option<Shard>,
    /// Generate N members instead of the spec's `members`. Member m's draws depend only
    /// on the spec's seed and m, so the first members are the same for any N; with
    /// `--shard`, `--members 18 --shard 3/3` draws only members 12–17: fresh members of a
    /// family whose first 12 trained a prior (`gonio prior holdout`).
    #[arg(long, value_name = "N")]
    pub members: Option<usize>,
    /// Replace members (and the spec) of another family at --out.
    #[arg(long)]
    pub force: bool,
    #[arg(long)]
    pub json: bool,
}

pub fn run(c: DatasetCommand) -> Result<ExitCode> {
    match c {
        DatasetCommand::Generate(a) => generate(a),
        DatasetCommand::Check(a) => check(a),
        DatasetCommand::Drift(a) => drift(a),
    }
}

fn drift(a: DriftArgs) -> Result<ExitCode> {
    use gonio_dataset::store::drift;
    if let (true, Some(out)) = (a.correct, &a.out) {
        let clip = match a.clip.as_deref() {
            None => drift::Clip::Auto,
            Some("off") => drift::Clip::Off,
            Some(v) => drift::Clip::Level(
                v.parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite() && *x > 0.0)
                    .with_context(|| format!("--clip {v}: use a positive level in the stored unit (e.g. 1) or off"))?,
            ),
        };
        let r = drift::correct(&a.dataset, out, a.force, clip).with_context(|| {
            format!(
                "writing a drift-corrected copy of {} to {}",
                a.dataset.display(),
                out.display()
            )
        })?;
        if a.json {
            println!("{}", serde_json::to_string_pretty(&r)?);
        } else {
            println!(
                "{}: {} measurements corrected with {} references (factors R {:.4}..{:.4}, G {:.4}..{:.4}, B {:.4}..{:.4}), \
                 {} records without an image copied",
                r.out.display(),
                r.corrected,
                r.references,
                r.factor_min[0],
                r.factor_max[0],
                r.factor_min[1],
                r.factor_max[1],
                r.factor_min[2],
                r.factor_max[2],
                r.copied_without_image
            );
            match r.clip_level {
                Some(_) => println!(
                    "clipped values (clip level {}): {} kept unscaled (lower bounds, not values)",
                    r.clip_level_reason, r.clipped_kept
                ),
                None => println!(
                    "clipped values: not detected, every value scaled (clip level {})",
                    r.clip_level_reason
                ),
            }
            if let (Some(b), Some(c), Some(mb), Some(mc)) = (
                r.truth_psnr_before_db,
                r.truth_psnr_after_db,
                r.truth_rel_mae_before,
                r.truth_rel_mae_after,
            ) {
                println!(
                    "vs. stored truth: PSNR {b:.2} dB before, {c:.2} dB after; relative mean abs error {:.2} % before, {:.2} % after",
                    mb * 100.0,
                    mc * 100.0
                );
            }
        }
        return Ok(ExitCode::SUCCESS);
    }
    let s = drift::series(&a.dataset)
        .with_context(|| format!("reading the drift references of {}", a.dataset.display()))?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&s)?);
    } else {
        println!(
            "{}: {} references, largest drift {:.2} %",
            s.dir.display(),
            s.references.len(),
            s.largest_drift * 100.0
        );
        println!("   #  run  rig time (s)  after  ratio R   ratio G   ratio B   mean R     mean G     mean B");
        for r in &s.references {
            println!(
                "{:4} {:4} {:13.1} {:>6}  {:.5}   {:.5}   {:.5}   {:.6}   {:.6}   {:.6}",
                r.number,
                r.run,
                r.rig_time_s,
                r.after_index.map_or("-".to_string(), |i| i.to_string()),
                r.ratio[0],
                r.ratio[1],
                r.ratio[2],
                r.mean[0],
                r.mean[1],
                r.mean[2]
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn check(a: CheckArgs) -> Result<ExitCode> {
    let spec = a.dir.join("family.toml");
    if !spec.is_file() {
        anyhow::bail!(
            "{}: not a dataset family (no family.toml); give the --out directory of `gonio dataset generate`",
            a.dir.display()
        );
    }
    let family = Family::load(&spec).with_context(|| format!("reading {}", spec.display()))?;
    let r = family
        .check(&a.dir)
        .with_context(|| format!("checking the family at {}", a.dir.display()))?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        println!("family `{}`: {} of {} members complete", r.name, r.complete, r.members);
        if !r.missing.is_empty() {
            println!(
                "missing or partial: members {} (rerun `gonio dataset generate` with the same spec and --out)",
                r.missing.iter().map(|m| m.to_string()).collect::<Vec<_>>().join(", ")
            );
        }
        for (m, why) in &r.stale {
            println!("member {m} is of another sample: {why}");
        }
    }
    Ok(if r.is_complete() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

fn generate(a: GenerateArgs) -> Result<ExitCode> {
    let mut family = Family::load(&a.spec).with_context(|| format!("reading the family spec {}", a.spec.display()))?;
    if let Some(m) = a.members {
        family = family
            .with_members(m)
            .with_context(|| format!("--members {m} for {}", a.spec.display()))?;
    }
    let n = a
        .shard
        .map_or(family.spec.members, |s| s.views(family.spec.members).len());
    let bar = indicatif::ProgressBar::new(n as u64);
    if a.json {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let report = family
        .generate(&a.out, a.shard, a.force, &|_| bar.inc(1))
        .with_context(|| format!("generating family `{}` into {}", family.spec.name, a.out.display()))?;
    bar.finish_and_clear();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "family `{}`{}: {} member(s) rendered, {} already complete (of {}); {} images, render {:.1} s; labels in {}",
            report.name,
            report.shard.as_ref().map(|s| format!(" shard {s}")).unwrap_or_default(),
            report.rendered.len(),
            report.kept.len(),
            report.members,
            report.images,
            report.render_seconds,
            a.out.join("labels.csv").display()
        );
    }
    Ok(ExitCode::SUCCESS)
}
