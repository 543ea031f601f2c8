//! `gonio sim btf`: a complete synthetic ground-truth BTF as a native dataset, without
//! simulating the acquisition (see `crate::synth`).

use super::common::{load_sample, RigArgs};
use crate::synth::dataset::{write_btf, BtfJob, BtfOutput};
use anyhow::{Context, Result};
use gonio_dataset::sweep::Sweep;
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct BtfArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    /// Built-in sample name or sample TOML file.
    #[arg(long, default_value = gonio_simulator::sample::DEFAULT_SAMPLE)]
    pub sample: String,
    /// `bonn81` (default), `uniform15`, `fibonacci:N`, or a .toml/.csv direction list.
    #[arg(long, default_value = "bonn81")]
    pub sweep: String,
    /// Texels per side of every image.
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    /// Truth samples per texel and axis (at least one per grid texel of the sample).
    #[arg(long, default_value_t = 1)]
    pub supersample: usize,
    /// Output dataset directory; without it nothing is written (a timing run).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Replace an existing gonio dataset at --out.
    #[arg(long)]
    pub force: bool,
    /// Render each pair on its own (trace + shade per pair) instead of tracing once per
    /// view: the baseline the per-view path is measured against.
    #[arg(long)]
    pub per_pair: bool,
    /// Render only shard I of N (1-based; a contiguous range of views) into --out; `gonio
    /// merge` joins the parts into the dataset one process would have written.
    #[arg(long)]
    pub shard: Option<gonio_dataset::shard::Shard>,
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct Report {
    sample: String,
    sweep: String,
    lights: usize,
    views: usize,
    images: usize,
    size: usize,
    mode: &'static str,
    /// `I/N` and the views rendered, for a shard.
    #[serde(skip_serializing_if = "Option::is_none")]
    shard: Option<gonio_dataset::shard::ShardInfo>,
    /// Wall seconds rendering (both cores) and, with --out, storing (the store runs on its
    /// own thread, overlapped with rendering; `total_seconds` is the wall time of both).
    render_seconds: f64,
    total_seconds: f64,
    ms_per_image: f64,
    shadow_maps_built: usize,
    out: Option<PathBuf>,
}

pub fn run(a: BtfArgs) -> Result<ExitCode> {
    let rig = a.rig.load()?;
    let spec = load_sample(&a.sample)?;
    let sweep = Sweep::resolve(&a.sweep).with_context(|| format!("loading sweep `{}`", a.sweep))?;
    let job = BtfJob {
        rig: &rig,
        sample: &spec,
        sweep: &sweep,
        size: a.size,
        supersample: a.supersample,
        shard: a.shard,
        per_pair: a.per_pair,
    };
    let out = a.out.as_deref().map(|dir| BtfOutput {
        dir,
        force: a.force,
        extra: serde_json::Value::Null,
    });
    let views = a.shard.map_or(sweep.views.len(), |s| s.views(sweep.views.len()).len());
    let bar = indicatif::ProgressBar::new((sweep.lights.len() * views) as u64);
    if a.json {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let stats = write_btf(&job, out, &|| bar.inc(1)).with_context(|| match &a.out {
        Some(o) => format!("writing the synthetic BTF of `{}` to {}", a.sample, o.display()),
        None => format!("rendering the synthetic BTF of `{}`", a.sample),
    })?;
    bar.finish_and_clear();
    let report = Report {
        sample: spec.name.clone(),
        sweep: sweep.name.clone(),
        lights: stats.lights,
        views: stats.views,
        images: stats.images,
        size: a.size,
        mode: if a.per_pair { "per-pair" } else { "per-view" },
        shard: stats.shard,
        render_seconds: stats.render_seconds,
        total_seconds: stats.total_seconds,
        ms_per_image: stats.render_seconds * 1e3 / stats.images as f64,
        shadow_maps_built: stats.shadow_maps_built,
        out: a.out.clone(),
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "{} × {} {}² truth images of `{}` ({}): render {:.1} s ({:.2} ms/image), total {:.1} s{}",
            report.lights,
            report.views,
            report.size,
            report.sample,
            report.mode,
            report.render_seconds,
            report.ms_per_image,
            report.total_seconds,
            report
                .out
                .as_ref()
                .map(|o| format!(", written to {}", o.display()))
                .unwrap_or_default()
        );
    }
    Ok(ExitCode::SUCCESS)
}
