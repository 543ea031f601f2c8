//! `gonio sim btf`: a complete synthetic ground-truth BTF as a native dataset, without
//! simulating the acquisition (see `crate::synth`).

use super::common::{load_sample, RigArgs};
use crate::store::{Dataset, ManifestHeader, MeasurementRecord};
use crate::sweep::Sweep;
use crate::synth;
use anyhow::{bail, Context, Result};
use gonio_simulator::{RenderQuality, Renderer, SimOptions};
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

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
    pub shard: Option<crate::shard::Shard>,
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
    shard: Option<crate::shard::ShardInfo>,
    /// Wall seconds rendering (both cores) and, with --out, storing (the store runs on its
    /// own thread, overlapped with rendering; `total_seconds` is the wall time of both).
    render_seconds: f64,
    total_seconds: f64,
    ms_per_image: f64,
    shadow_maps_built: usize,
    out: Option<PathBuf>,
}

pub fn run(a: BtfArgs) -> Result<ExitCode> {
    if !(8..=4096).contains(&a.size) {
        bail!("--size {}: valid range is 8 ..= 4096", a.size);
    }
    if !(1..=16).contains(&a.supersample) {
        bail!("--supersample {}: valid range is 1 ..= 16", a.supersample);
    }
    let rig = a.rig.load()?;
    let spec = load_sample(&a.sample)?;
    let sweep = Sweep::resolve(&a.sweep).with_context(|| format!("loading sweep `{}`", a.sweep))?;
    let shard = match a.shard {
        Some(s) => {
            s.check_views(sweep.views.len()).map_err(anyhow::Error::msg)?;
            Some(s.info(sweep.views.len()))
        }
        None => None,
    };
    let views = shard.map_or(0..sweep.views.len(), |s| s.first_view..s.end_view);
    let quality = RenderQuality {
        truth_supersample: a.supersample,
        ..Default::default()
    };
    let renderer = Arc::new(Renderer::new(Arc::new(spec.clone().build()?), quality));
    // The acquisition's truth units come from the rig's sensor model; building the sim rig
    // also validates the rig's lamp (`light.options.radius_mm`).
    let sim = gonio_simulator::build_sim_rig(&rig, renderer.clone(), &SimOptions::default())?;
    let radius = sim.world.lamp_radius_mm;
    let scale = synth::truth_scale(&sim.world.sensor.lock().expect("sensor lock"));

    // The store thread: EXR encoding and fsyncs overlap the rendering.
    let (tx, rx) = std::sync::mpsc::sync_channel::<(usize, usize, gonio_devices::image::RgbImage)>(8);
    let store_thread = match &a.out {
        None => None,
        Some(out) => {
            let mut header = ManifestHeader::new(
                serde_json::to_value(&rig)?,
                serde_json::to_value(&spec)?,
                sweep.manifest_json("skip"),
                a.size,
                a.size,
                "ground truth, linear normalised sensor signal (DN / max DN) of the rig's sensor, \
                 no noise (synthetic BTF, `gonio sim btf`)",
            );
            header.extra = serde_json::json!({ "synthetic": { "ideal_rig": true, "supersample": a.supersample } });
            if let Some(s) = &shard {
                header.extra["shard"] = serde_json::to_value(s)?;
            }
            let mut ds = Dataset::create(out, &header, a.force)
                .with_context(|| format!("creating the dataset {}", out.display()))?;
            let nl = sweep.lights.len();
            let (lights, view_dirs) = (sweep.lights.clone(), sweep.views.clone());
            Some(std::thread::spawn(move || -> Result<()> {
                for (vi, li, img) in rx {
                    let index = vi * nl + li;
                    let d = |x: gonio_devices::Direction| [x.theta_deg(), x.phi_deg()];
                    let rec = MeasurementRecord::new(index, index, d(lights[li]), d(view_dirs[vi]));
                    ds.store(rec, Some(&img), None)?;
                }
                ds.finish(&serde_json::json!({ "synthetic": true }))?;
                Ok(())
            }))
        }
    };

    let bar = indicatif::ProgressBar::new((sweep.lights.len() * views.len()) as u64);
    if a.json {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let t0 = Instant::now();
    let mut render_s = 0.0;
    let mut last = Instant::now();
    let storing = store_thread.is_some();
    let send = |vi: usize, li: usize, img: gonio_devices::image::RgbImage| -> Result<()> {
        bar.inc(1);
        if storing {
            tx.send((vi, li, img))
                .map_err(|_| anyhow::anyhow!("the store thread stopped (see its error below)"))?;
        }
        Ok(())
    };
    let result = if a.per_pair {
        let mut r = Ok(());
        'outer: for (vi, &view) in sweep.views.iter().enumerate().skip(views.start).take(views.len()) {
            for (li, &light) in sweep.lights.iter().enumerate() {
                let (cam, lamp) = synth::positions(&rig, light, view);
                let mut img = renderer.render_truth(cam, a.size, a.size, &synth::lamp_at(&rig, radius, lamp));
                img.data.iter_mut().for_each(|v| *v *= scale);
                render_s += last.elapsed().as_secs_f64();
                if let Err(e) = send(vi, li, img) {
                    r = Err(e);
                    break 'outer;
                }
                last = Instant::now();
            }
        }
        r
    } else {
        synth::render_btf_views(
            &renderer,
            &rig,
            radius,
            &sweep,
            views.clone(),
            a.size,
            scale,
            |vi, li, img| {
                render_s += last.elapsed().as_secs_f64();
                send(vi, li, img)?;
                last = Instant::now();
                Ok(())
            },
        )
    };
    drop(tx);
    bar.finish_and_clear();
    if let Some(h) = store_thread {
        h.join().map_err(|_| anyhow::anyhow!("the store thread panicked"))??;
    }
    result?;
    let total = t0.elapsed().as_secs_f64();
    let images = sweep.lights.len() * views.len();
    let report = Report {
        sample: spec.name.clone(),
        sweep: sweep.name.clone(),
        lights: sweep.lights.len(),
        views: sweep.views.len(),
        images,
        size: a.size,
        mode: if a.per_pair { "per-pair" } else { "per-view" },
        shard,
        render_seconds: render_s,
        total_seconds: total,
        ms_per_image: render_s * 1e3 / images as f64,
        shadow_maps_built: renderer.shadow_maps_built(),
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
