//! `gonio prior build|show`: the angular prior of sparse acquisition (`gonio-sparse`).
//!
//! Also the helpers the other sparse commands share: resolving `--prior` (a file, or
//! `default`: `sparse/priors/default-bonn81.gprior`) and reading a dataset's pairs.

use crate::compress::data::DatasetViews;
use anyhow::{bail, Context, Result};
use gonio_sparse::{Prior, PriorMeta, TrainingSource, ValueSpace};
use rayon::prelude::*;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(clap::Subcommand, Debug)]
pub enum PriorCommand {
    /// Learn an angular prior (mean, PCA basis and variances of per-texel ABRDFs) from
    /// complete datasets of one sweep (e.g. the members of a `gonio dataset generate` family).
    Build(BuildArgs),
    /// Print a prior's header: sweep, units, components, training data.
    Show(ShowArgs),
}

#[derive(clap::Args, Debug)]
pub struct BuildArgs {
    /// Complete datasets (every pair stored), all of the same sweep and value units.
    #[arg(required = true)]
    pub datasets: Vec<PathBuf>,
    #[arg(long)]
    pub out: PathBuf,
    /// Basis vectors kept (K).
    #[arg(long, short = 'c', default_value_t = 96)]
    pub components: usize,
    /// Texels taken from each dataset (evenly spaced; each gives 3 ABRDFs, one per channel).
    #[arg(long, default_value_t = 400)]
    pub texels: usize,
    /// Value space of the model: `gamma` (x^(1/2.2), close to the 8-bit sRGB metric) or `linear`.
    #[arg(long, default_value = "gamma")]
    pub space: ValueSpace,
    /// Seed of the randomized SVD's sketch.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[arg(long)]
    pub force: bool,
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct ShowArgs {
    /// A .gprior file, or `default`.
    pub prior: String,
    #[arg(long)]
    pub json: bool,
}

pub fn run(c: PriorCommand) -> Result<ExitCode> {
    match c {
        PriorCommand::Build(a) => build(a),
        PriorCommand::Show(a) => {
            let (p, path) = load_prior(Some(&a.prior))?;
            if a.json {
                println!("{}", serde_json::to_string(&p.header)?);
            } else {
                print_header(&p, &path);
            }
            Ok(ExitCode::SUCCESS)
        }
    }
}

fn print_header(p: &Prior, path: &Path) {
    let h = &p.header;
    println!("{}", path.display());
    println!(
        "  sweep {} ({} lights × {} views, hash {}) · units `{}` · space {}",
        h.sweep_name,
        h.lights,
        h.views,
        &h.sweep_hash[..12],
        h.units,
        h.space.name()
    );
    println!(
        "  {} components from {} ABRDFs; variance kept {:.2} % (residual {:.3e} per pair)",
        h.components,
        h.samples,
        100.0 * (1.0 - h.residual_var / h.total_var.max(1e-300)),
        h.residual_var
    );
    let names: Vec<String> = h
        .sources
        .iter()
        .map(|s| s.sample.clone().unwrap_or_else(|| s.dataset.clone()))
        .collect();
    println!("  trained on {} datasets: {}", names.len(), names.join(", "));
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
    let p = Prior::load(&path)?;
    Ok((p, path))
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

/// The sample name a dataset's manifest records.
pub fn sample_name(ds: &DatasetViews) -> Option<String> {
    ds.header
        .sample
        .get("name")
        .and_then(|n| n.as_str())
        .map(str::to_string)
}

pub fn sweep_name(ds: &DatasetViews) -> String {
    ds.header
        .sweep
        .get("name")
        .and_then(|n| n.as_str())
        .unwrap_or("?")
        .to_string()
}

/// `texels` evenly spaced texel indices out of `total`.
pub fn spread_texels(total: usize, texels: usize) -> Vec<usize> {
    let n = texels.min(total).max(1);
    (0..n).map(|i| ((2 * i + 1) * total) / (2 * n)).collect()
}

/// Linear ABRDF rows (texel-major, channel, then every pair in canonical order) of the
/// given texels; every pair must be stored.
fn abrdf_rows(ds: &DatasetViews, texels: &[usize]) -> Result<Vec<f32>> {
    let (l, v) = (ds.n_lights(), ds.n_views());
    let d = l * v;
    let images: Vec<Vec<f32>> = (0..d)
        .into_par_iter()
        .map(|p| -> Result<Vec<f32>> {
            let img = ds.read_image(p % l, p / l)?.with_context(|| {
                format!(
                    "{}: pair {p} is not stored; a prior is learned from complete datasets",
                    ds.dir.display()
                )
            })?;
            Ok(texels
                .iter()
                .flat_map(|&t| [img[3 * t], img[3 * t + 1], img[3 * t + 2]])
                .collect())
        })
        .collect::<Result<_>>()?;
    let mut rows = vec![0f32; texels.len() * 3 * d];
    for (p, img) in images.iter().enumerate() {
        for (i, c) in img.iter().enumerate() {
            rows[i * d + p] = *c;
        }
    }
    Ok(rows)
}

#[derive(Serialize)]
struct BuildJson<'a> {
    out: String,
    bytes: usize,
    header: &'a gonio_sparse::PriorHeader,
}

fn build(a: BuildArgs) -> Result<ExitCode> {
    if a.out.exists() && !a.force {
        bail!("{} exists: use --force to replace it", a.out.display());
    }
    let mut rows = Vec::new();
    let mut sources = Vec::new();
    let mut first: Option<DatasetViews> = None;
    for dir in &a.datasets {
        let ds = DatasetViews::open(dir).with_context(|| format!("opening {}", dir.display()))?;
        if let Some(f) = &first {
            if f.lights_deg != ds.lights_deg || f.views_deg != ds.views_deg {
                bail!(
                    "{} uses sweep `{}`, {} uses `{}`: a prior is learned over one sweep",
                    dir.display(),
                    sweep_name(&ds),
                    f.dir.display(),
                    sweep_name(f)
                );
            }
            if units_key(&f.header.values) != units_key(&ds.header.values) {
                bail!(
                    "{} holds `{}`, {} holds `{}`: a prior is learned in one value unit",
                    dir.display(),
                    ds.header.values,
                    f.dir.display(),
                    f.header.values
                );
            }
        }
        let texels = spread_texels(ds.texels(), a.texels);
        rows.extend(abrdf_rows(&ds, &texels)?);
        sources.push(TrainingSource {
            // The directory's own name only: the prior's bytes do not depend on where the
            // training data sit.
            dataset: dir
                .file_name()
                .map_or_else(|| dir.display().to_string(), |f| f.to_string_lossy().into_owned()),
            sample: sample_name(&ds),
            texels: texels.len(),
        });
        if first.is_none() {
            first = Some(ds);
        }
    }
    let f = first.expect("at least one dataset");
    let meta = PriorMeta {
        sweep_name: sweep_name(&f),
        lights_deg: f.lights_deg.clone(),
        views_deg: f.views_deg.clone(),
        units: units_key(&f.header.values),
        space: a.space,
        sources,
    };
    let prior = Prior::learn(meta, &rows, a.components, a.seed)?;
    let bytes = prior.to_bytes()?;
    if let Some(parent) = a.out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)?;
    }
    crate::store::atomic::write_atomic(&a.out, &bytes, None).with_context(|| format!("writing {}", a.out.display()))?;
    if a.json {
        let j = BuildJson {
            out: a.out.display().to_string(),
            bytes: bytes.len(),
            header: &prior.header,
        };
        println!("{}", serde_json::to_string(&j)?);
    } else {
        print_header(&prior, &a.out);
        println!("  wrote {} bytes", bytes.len());
    }
    Ok(ExitCode::SUCCESS)
}

/// What a sparse plan is asked for.
#[derive(Clone, Copy, Debug)]
pub enum Target {
    /// This many pairs.
    Pairs(usize),
    /// This share of the feasible pairs.
    Fraction(f64),
    /// At most this planned rig time (s), motion included.
    RigBudget(f64),
}

/// The sparse part of a plan (`plan.json` field `sparse`).
#[derive(Clone, Debug, Serialize)]
pub struct SparseInfo {
    pub prior: String,
    pub design: &'static str,
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
}

/// PSNR (dB) of a model-space mean squared error (the gamma space is close to 8-bit sRGB).
pub fn psnr_of_mse(mse: f64) -> f64 {
    -10.0 * mse.max(1e-20).log10()
}

/// Choose pairs by greedy A-optimal design over the feasible pairs of `full` (the plan of
/// the whole sweep) and plan them. A rig budget is met by the longest greedy prefix whose
/// plan fits (bisection on quick plans, then the real plan).
#[allow(clippy::too_many_arguments)]
pub fn sparse_plan(
    prior: &Prior,
    prior_name: &str,
    rig: &gonio_devices::rig::RigSpec,
    sweep: &crate::sweep::Sweep,
    opts: &crate::plan::PlanOptions,
    full: &crate::plan::Plan,
    target: Target,
    noise_var: f64,
) -> Result<(crate::plan::Plan, SparseInfo)> {
    use crate::plan::{Plan, PlanOptions};
    let mut feasible: Vec<usize> = full.steps.iter().map(|s| s.index).collect();
    feasible.sort_unstable();
    let nf = feasible.len();
    let capture = full.durations.capture_per_measurement_s.max(1e-6);
    let n_max = match target {
        Target::Pairs(n) => {
            anyhow::ensure!(n >= 1, "--pairs must be at least 1");
            anyhow::ensure!(n <= nf, "--pairs {n}: only {nf} pairs are feasible");
            n
        }
        Target::Fraction(f) => {
            anyhow::ensure!(f > 0.0 && f <= 1.0, "--fraction {f}: must be in (0, 1]");
            ((f * nf as f64).round() as usize).clamp(1, nf)
        }
        Target::RigBudget(b) => {
            anyhow::ensure!(
                b > 0.0 && b.is_finite(),
                "--rig-budget {b}: must be a positive number of seconds"
            );
            ((b / capture).floor() as usize).min(nf)
        }
    };
    anyhow::ensure!(n_max >= 1, "the budget does not cover one capture ({capture:.2} s)");
    let design = gonio_sparse::greedy_design(prior, &feasible, &[], n_max, noise_var)?;
    let pairs = sweep.pairs();
    let plan_of = |n: usize, kicks: usize| -> Result<Plan> {
        let mut idx: Vec<usize> = design[..n].iter().map(|s| s.pair).collect();
        idx.sort_unstable();
        let chosen: Vec<_> = idx.iter().map(|&i| pairs[i]).collect();
        let o = PlanOptions { kicks, ..opts.clone() };
        Ok(Plan::build_pairs(rig, sweep, &chosen, &o)?)
    };
    let n = match target {
        Target::RigBudget(b) => {
            let quick = opts.kicks.min(2000);
            let (mut lo, mut hi) = (0usize, design.len());
            // Largest n with a quick plan within the budget.
            while lo < hi {
                let mid = (lo + hi).div_ceil(2);
                if plan_of(mid, quick)?.durations.optimized_s <= b {
                    lo = mid;
                } else {
                    hi = mid - 1;
                }
            }
            anyhow::ensure!(lo >= 1, "--rig-budget {b} s: not even one pair fits");
            lo
        }
        _ => design.len(),
    };
    let mut n = n;
    let mut plan = plan_of(n, opts.kicks)?;
    if let Target::RigBudget(b) = target {
        while plan.durations.optimized_s > b && n > 1 {
            n -= 1;
            plan = plan_of(n, opts.kicks)?;
        }
    }
    plan.pairs = sweep.len();
    let info = SparseInfo {
        prior: prior_name.to_string(),
        design: "greedy Bayesian A-optimal (expected posterior error over every pair of the sweep)",
        target: format!("{target:?}"),
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
    };
    Ok((plan, info))
}

/// The sparse target of `gonio plan` flags, if any.
pub fn sparse_target(pairs: Option<usize>, fraction: Option<f64>, budget: Option<f64>) -> Option<Target> {
    pairs
        .map(Target::Pairs)
        .or(fraction.map(Target::Fraction))
        .or(budget.map(Target::RigBudget))
}

#[derive(Serialize)]
struct SparsePlanJson<'a> {
    counts: crate::plan::PlanCounts,
    sparse: &'a SparseInfo,
    #[serde(flatten)]
    plan: &'a crate::plan::Plan,
}

/// `gonio plan --prior P (--pairs N | --fraction F | --rig-budget S)`.
pub fn plan_sparse(
    args: &super::plan::PlanArgs,
    rig: &gonio_devices::rig::RigSpec,
    sweep: &crate::sweep::Sweep,
    full: &crate::plan::Plan,
    target: Target,
) -> Result<ExitCode> {
    anyhow::ensure!(
        full.isotropic.is_none(),
        "--isotropic and a sparse design do not combine: the prior chooses among all pairs"
    );
    let (prior, path) = load_prior(args.prior.as_deref())?;
    let (lights, views) = sweep.directions_deg();
    // A plan does not know the values' unit yet: check the sweep only.
    prior.check_sweep(&sweep.name, &lights, &views)?;
    let opts = args.sweep.plan_options()?;
    let (plan, info) = sparse_plan(
        &prior,
        &path.display().to_string(),
        rig,
        sweep,
        &opts,
        full,
        target,
        prior.header.residual_var,
    )?;
    if let Err(e) = gonio_sparse::complete::check_design(&prior, &info.picks.iter().map(|p| p.0).collect::<Vec<_>>()) {
        anyhow::bail!("{e} (prior {})", path.display());
    }
    if args.json {
        let j = SparsePlanJson {
            counts: plan.counts(),
            sparse: &info,
            plan: &plan,
        };
        println!("{}", serde_json::to_string(&j)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "rig {} · sweep {} · prior {} · {:?}",
        plan.rig, plan.sweep, info.prior, target
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
    println!(
        "  predicted PSNR of the completed dataset {:.2} dB (8-bit sRGB, over the prior, noiseless)",
        info.predicted_psnr_db
    );
    Ok(ExitCode::SUCCESS)
}
