//! `gonio prior build|show`: the angular prior of sparse acquisition (`gonio-sparse`).
//!
//! Also the helpers the other sparse commands share for reading a dataset's pairs
//! (resolving `--prior` is `super::sparse`, which a lab build has too).

use super::sparse::load_prior;
use crate::compress::data::DatasetViews;
use crate::plan::sparse::units_key;
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
    /// Measure a learned prior on complete datasets it never saw (fresh members of its
    /// family): ρ, the variance its basis leaves out, becomes the held-out figure instead of
    /// the training one, which understates it. The mean and basis are kept.
    Holdout(HoldoutArgs),
}

#[derive(clap::Args, Debug)]
pub struct HoldoutArgs {
    /// The prior (a .gprior file, or `default`).
    pub prior: String,
    /// Complete datasets of the prior's sweep and units that it was not learned from.
    #[arg(required = true)]
    pub datasets: Vec<PathBuf>,
    #[arg(long)]
    pub out: PathBuf,
    /// Texels taken from each dataset (evenly spaced; 3 ABRDFs each).
    #[arg(long, default_value_t = 400)]
    pub texels: usize,
    /// Also take each component's variance (λ) from the held-out datasets.
    #[arg(long)]
    pub variances: bool,
    #[arg(long)]
    pub force: bool,
    #[arg(long)]
    pub json: bool,
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
    /// Hold out every N-th dataset (the N-th, 2N-th, … in the order given): they shape
    /// neither the mean nor the basis, and ρ — the variance the basis leaves out, which the
    /// completion treats as noise and every predicted error includes — is measured on them
    /// instead of on the training data (which fit their own basis and understate it).
    #[arg(long, value_name = "N")]
    pub holdout: Option<usize>,
    /// With --holdout: also take each component's variance (λ, the prior's Gaussian) from
    /// the held-out datasets instead of the training data.
    #[arg(long, requires = "holdout")]
    pub holdout_variances: bool,
    /// Seed of the randomized SVD's sketch.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Learn a mixture of this many priors instead of one (a `.gmix` file): the training
    /// ABRDFs are clustered by k-means on their first `--features` coefficients, and each
    /// cluster gets its own prior of at most `--components` components (with held-out
    /// figures from the held-out rows that fall in it). `gonio bench sparse --mixture`
    /// completes each texel in the member whose evidence is largest.
    #[arg(long, value_name = "C")]
    pub clusters: Option<usize>,
    /// With --clusters: global coefficients describing an ABRDF for the clustering.
    #[arg(long, default_value_t = 16, requires = "clusters")]
    pub features: usize,
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
        PriorCommand::Holdout(a) => holdout(a),
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
    if let Some(o) = &h.held_out {
        println!(
            "  held out {} datasets ({} ABRDFs): residual {:.3e} per pair on them against {:.3e} on the \
             training data ({:.1} ×){}",
            o.datasets.len(),
            o.abrdfs,
            o.residual_var,
            o.training_residual_var,
            o.residual_var / o.training_residual_var.max(1e-300),
            if o.variances_from_held_out {
                "; component variances from the held-out data"
            } else {
                ""
            }
        );
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

/// Refuse a prior for a dataset of another sweep or other value units.
pub fn check_dataset(prior: &Prior, ds: &DatasetViews) -> Result<(), gonio_sparse::SparseError> {
    prior.check_compatible(
        &sweep_name(ds),
        &ds.lights_deg,
        &ds.views_deg,
        &units_key(&ds.header.values),
    )
}

/// Append the ABRDF rows of `texels` spread texels of `ds` (at `dir`) to `rows`, and say
/// where they came from: the directory's own name only, so a prior's bytes do not depend
/// on where its datasets sit.
fn read_source(dir: &Path, ds: &DatasetViews, texels: usize, rows: &mut Vec<f32>) -> Result<TrainingSource> {
    let texels = spread_texels(ds.texels(), texels);
    rows.extend(abrdf_rows(ds, &texels)?);
    Ok(TrainingSource {
        dataset: dir
            .file_name()
            .map_or_else(|| dir.display().to_string(), |f| f.to_string_lossy().into_owned()),
        sample: sample_name(ds),
        texels: texels.len(),
    })
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
    if let Some(n) = a.holdout {
        if n < 2 || n > a.datasets.len() {
            bail!(
                "--holdout {n}: holds out every {n}-th of the {} datasets given; it must be at least 2 \
                 (something must remain to learn from) and at most the number of datasets",
                a.datasets.len()
            );
        }
    }
    let held = |i: usize| a.holdout.is_some_and(|n| (i + 1).is_multiple_of(n));
    let (mut rows, mut held_rows) = (Vec::new(), Vec::new());
    let (mut sources, mut held_sources) = (Vec::new(), Vec::new());
    let mut first: Option<DatasetViews> = None;
    for (i, dir) in a.datasets.iter().enumerate() {
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
        let (rows, sources) = if held(i) {
            (&mut held_rows, &mut held_sources)
        } else {
            (&mut rows, &mut sources)
        };
        sources.push(read_source(dir, &ds, a.texels, rows)?);
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
    let holdout = a
        .holdout
        .map(|_| (held_rows.as_slice(), held_sources, a.holdout_variances));
    if let Some(clusters) = a.clusters {
        let opts = gonio_sparse::mixture::MixtureOptions {
            clusters,
            components: a.components,
            features: a.features,
            seed: a.seed,
        };
        let mix = gonio_sparse::mixture::Mixture::learn(meta, &rows, holdout, opts)?;
        return write_mixture(&mix, &a.out, a.json);
    }
    let prior = Prior::learn_with_holdout(meta, &rows, holdout, a.components, a.seed)?;
    write_prior(&prior, &a.out, a.json)
}

fn write_mixture(mix: &gonio_sparse::mixture::Mixture, out: &Path, json: bool) -> Result<ExitCode> {
    let bytes = mix.to_bytes()?;
    write_file(out, &bytes)?;
    if json {
        let members: Vec<_> = mix
            .members
            .iter()
            .zip(&mix.header.members)
            .map(|(p, e)| {
                serde_json::json!({
                    "weight": e.weight, "rows": e.rows, "held_rows": e.held_rows,
                    "components": p.components(), "residual_var": p.header.residual_var,
                })
            })
            .collect();
        println!(
            "{}",
            serde_json::json!({ "out": out.display().to_string(), "bytes": bytes.len(), "members": members })
        );
    } else {
        println!("{}: a mixture of {} priors", out.display(), mix.members.len());
        for (i, (p, e)) in mix.members.iter().zip(&mix.header.members).enumerate() {
            println!(
                "  member {i}: weight {:.3} ({} ABRDFs, {} held out), K = {}, ρ = {:.3e}",
                e.weight,
                e.rows,
                e.held_rows,
                p.components(),
                p.header.residual_var
            );
        }
        println!("  wrote {} bytes", bytes.len());
    }
    Ok(ExitCode::SUCCESS)
}

fn holdout(a: HoldoutArgs) -> Result<ExitCode> {
    if a.out.exists() && !a.force {
        bail!("{} exists: use --force to replace it", a.out.display());
    }
    let (prior, path) = load_prior(Some(&a.prior))?;
    let mut rows = Vec::new();
    let mut sources = Vec::new();
    for dir in &a.datasets {
        let ds = DatasetViews::open(dir).with_context(|| format!("opening {}", dir.display()))?;
        check_dataset(&prior, &ds).with_context(|| format!("{} against {}", dir.display(), path.display()))?;
        sources.push(read_source(dir, &ds, a.texels, &mut rows)?);
    }
    let out = prior
        .with_held_out(&rows, sources, a.variances)
        .with_context(|| format!("measuring {} on the held-out datasets", path.display()))?;
    write_prior(&out, &a.out, a.json)
}

/// Write a prior's or mixture's bytes atomically, creating the folder.
fn write_file(out: &Path, bytes: &[u8]) -> Result<()> {
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)?;
    }
    crate::store::atomic::write_atomic(out, bytes, None).with_context(|| format!("writing {}", out.display()))
}

fn write_prior(prior: &Prior, out: &Path, json: bool) -> Result<ExitCode> {
    let bytes = prior.to_bytes()?;
    write_file(out, &bytes)?;
    if json {
        let j = BuildJson {
            out: out.display().to_string(),
            bytes: bytes.len(),
            header: &prior.header,
        };
        println!("{}", serde_json::to_string(&j)?);
    } else {
        print_header(prior, out);
        println!("  wrote {} bytes", bytes.len());
    }
    Ok(ExitCode::SUCCESS)
}
