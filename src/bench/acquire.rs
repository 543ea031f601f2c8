//! `gonio bench acquire`: the simulated acquisition against its two lower bounds, in one
//! process and one run, so the ratios hold under any machine load:
//!
//! 1. the acquisition itself (plan, drive, capture, develop, truth, store: the session that
//!    `gonio acquire` runs), into a scratch dataset;
//! 2. `gonio sim btf`'s way of rendering the same pairs' ground truth (each view traced
//!    once, shaded per light, no sensor, nothing stored);
//! 3. raw-frame rendering alone for the same pairs (the simulated camera's renderer, with
//!    and without its sensor model): what any simulated acquisition must spend.
//!
//! Peak resident memory is measured per phase (the kernel's high-water mark is reset
//! between phases), so a short and a full run show whether memory grows with the sweep.

use anyhow::{Context, Result};
use gonio::cli::bench::{load_sample, RigArgs, SweepArgs};
use gonio::synth;
use gonio_acquire::session::{NewSession, PlanRequest, RunRequest, RunSettings, Session};
use gonio_devices::Direction;
use gonio_simulator::{RenderQuality, Renderer, SimOptions};
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct AcquireBenchArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    #[arg(long, default_value = gonio_simulator::sample::DEFAULT_SAMPLE)]
    pub sample: String,
    #[command(flatten)]
    pub sweep: SweepArgs,
    /// Texels per side of the rectified images.
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    /// Measure only the first N measurements of the plan (default: the whole sweep).
    #[arg(long)]
    pub limit: Option<usize>,
    /// Do not compare with (and render) the ground truth in the acquisition.
    #[arg(long)]
    pub no_truth: bool,
    /// Also store the ground truth images (`truth/NNNNN.exr`) in the acquisition.
    #[arg(long)]
    pub store_truth: bool,
    /// Time the baselines on every K-th measured pair only (their cost per image is what is
    /// compared; 1 = every pair).
    #[arg(long, default_value_t = 1)]
    pub baseline_every: usize,
    /// Keep the acquired dataset here (default: a scratch directory, removed afterwards).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct Phase {
    name: &'static str,
    images: usize,
    wall_s: f64,
    ms_per_image: f64,
    /// This phase's ms/image over the acquisition's.
    vs_acquire: f64,
    /// Peak resident memory during this phase (MiB; `None` where Linux's reset of the
    /// high-water mark is unavailable).
    peak_rss_mib: Option<f64>,
}

#[derive(Serialize)]
struct Report {
    rig: String,
    sample: String,
    sweep: String,
    size: usize,
    truth: bool,
    store_truth: bool,
    /// `/proc/loadavg` (1, 5, 15 min) before and after the run.
    load_before: Option<[f64; 3]>,
    load_after: Option<[f64; 3]>,
    threads: usize,
    phases: Vec<Phase>,
    /// Acquisition ms/image over `gonio sim btf`'s (truth only, per view).
    acquire_over_sim_btf: f64,
    /// Acquisition ms/image over raw-frame rendering alone (no sensor).
    acquire_over_raw_render: f64,
    /// Acquisition ms/image over raw-frame rendering with the sensor model.
    acquire_over_raw_capture: f64,
    /// The acquisition's own summary (stage seconds, truth error, peak memory).
    acquisition: gonio_acquire::session::Summary,
}

fn loadavg() -> Option<[f64; 3]> {
    let s = std::fs::read_to_string("/proc/loadavg").ok()?;
    let mut it = s.split_whitespace().map(|x| x.parse::<f64>().ok());
    Some([it.next()??, it.next()??, it.next()??])
}

/// Reset the kernel's peak-RSS mark of this process (`/proc/self/clear_refs`, value 5);
/// false where that is not available (then peaks are the process's so far).
fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

pub fn run(a: AcquireBenchArgs) -> Result<ExitCode> {
    anyhow::ensure!(
        gonio::cli::bench::IMAGE_SIDES.contains(&a.size),
        "--size {}: each side must be 8 ..= 8192",
        a.size
    );
    anyhow::ensure!(a.baseline_every >= 1, "--baseline-every 0: use 1 (every pair) or more");
    anyhow::ensure!(a.limit != Some(0), "--limit 0: measure at least one pair");
    let rig = a.rig.load()?;
    let sample = load_sample(&a.sample)?;
    let sweep = a.sweep.load()?;
    let scratch = a
        .out
        .is_none()
        .then(|| std::env::temp_dir().join(format!("gonio-bench-acquire-{}", std::process::id())));
    let out = a
        .out
        .clone()
        .or_else(|| scratch.clone())
        .expect("one of the two is set");
    let result = bench(&a, &rig, &sample, &sweep, &out);
    if let Some(dir) = &scratch {
        // The scratch dataset is only a by-product of the timing.
        let _ = std::fs::remove_dir_all(dir);
    }
    result
}

fn bench(
    a: &AcquireBenchArgs,
    rig: &gonio_devices::rig::RigSpec,
    sample: &gonio_simulator::SampleSpec,
    sweep: &gonio_dataset::sweep::Sweep,
    out: &std::path::Path,
) -> Result<ExitCode> {
    let load_before = loadavg();
    let session = Session::create(&NewSession {
        out: out.to_path_buf(),
        force: true,
        rig: rig.clone(),
        hdr: None,
        sample: sample.clone(),
        sweep: sweep.clone(),
        plan: PlanRequest {
            options: a.sweep.plan_options()?,
            isotropic: a.sweep.isotropic,
            sparse: None,
            fly: None,
        },
        settings: RunSettings {
            width: a.size,
            height: a.size,
            noise: true,
            truth: !a.no_truth,
            seed: None,
            raw: false,
            store_truth: a.store_truth,
            reference: None,
        },
        calibration: None,
        shard: None,
    })
    .with_context(|| format!("creating the benchmark dataset {}", out.display()))?;
    let steps: Vec<gonio_acquire::plan::Step> = session
        .plan()
        .steps
        .iter()
        .take(a.limit.unwrap_or(usize::MAX))
        .cloned()
        .collect();

    // 1. The acquisition, as `gonio acquire` runs it.
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let reset = reset_peak_rss();
    let t = Instant::now();
    let summary = rt
        .block_on(session.run(
            &RunRequest {
                realtime: false,
                limit: a.limit,
            },
            Arc::new(AtomicBool::new(false)),
            Arc::new(|_: &gonio_acquire::engine::RunEvent<'_>| {}),
        ))
        .with_context(|| format!("acquiring into {}", out.display()))?;
    let acquire_s = t.elapsed().as_secs_f64();
    let acquire_rss = gonio_acquire::session::peak_rss_mib().filter(|_| reset);
    let images = summary.stored_this_run.max(1);
    let acquire_ms = acquire_s * 1e3 / images as f64;

    // The baselines render the pairs the acquisition measured (every K-th of them).
    let picked: Vec<&gonio_acquire::plan::Step> = steps.iter().step_by(a.baseline_every).collect();
    let renderer = Arc::new(Renderer::new(
        Arc::new(sample.clone().build()?),
        RenderQuality::default(),
    ));
    let sim = gonio_simulator::build_sim_rig(rig, renderer.clone(), &SimOptions::default())?;
    let world = sim.world.clone();
    rt.block_on(sim.light.set(true, 1.0))
        .context("switching the simulated lamp on")?;

    // 2. `gonio sim btf`: the same pairs' truth, each view traced once and shaded per light.
    let reset = reset_peak_rss();
    let scale = synth::truth_scale(&world.sensor.lock().expect("sensor lock"));
    let mut by_view: Vec<(usize, Vec<&gonio_acquire::plan::Step>)> = Vec::new();
    for s in &picked {
        match by_view.iter_mut().find(|(v, _)| *v == s.view_index) {
            Some((_, list)) => list.push(s),
            None => by_view.push((s.view_index, vec![s])),
        }
    }
    let t = Instant::now();
    let mut checksum = 0.0f64;
    for (_, list) in &by_view {
        let dir = |d: [f64; 2]| Direction::from_degrees(d[0], d[1]);
        let (camera, _) = synth::positions(rig, dir(list[0].light_deg), dir(list[0].view_deg));
        let traced = renderer.truth_view(camera, a.size, a.size);
        for s in list {
            let (_, lamp) = synth::positions(rig, dir(s.light_deg), dir(s.view_deg));
            let mut img = renderer.shade_truth(&traced, &synth::lamp_at(rig, world.lamp_radius_mm, lamp));
            img.data.iter_mut().for_each(|v| *v *= scale);
            checksum += img.data[img.data.len() / 2] as f64;
        }
    }
    let btf_s = t.elapsed().as_secs_f64();
    let btf_rss = gonio_acquire::session::peak_rss_mib().filter(|_| reset);

    // 3. Raw frames alone: the simulated camera's render, then its sensor model.
    let qs: Vec<Vec<f64>> = picked
        .iter()
        .map(|s| s.axes_deg.iter().map(|d| d.to_radians()).collect())
        .collect();
    let reset = reset_peak_rss();
    let t = Instant::now();
    for q in &qs {
        let rad = world.raw_radiance(q);
        checksum += rad.data[rad.data.len() / 2] as f64;
    }
    let raw_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    for (k, q) in qs.iter().enumerate() {
        let rad = world.raw_radiance(q);
        let pose = world.kinematics.camera_pose(q);
        let roi = world
            .renderer
            .pixel_bounds(&world.intrinsics, &pose, world.width, world.height);
        let sensor = world.sensor.lock().expect("sensor lock").clone();
        let dn = sensor.expose_roi(&rad, k as u64, roi);
        checksum += dn[dn.len() / 2] as f64;
    }
    let capture_s = t.elapsed().as_secs_f64();
    let raw_rss = gonio_acquire::session::peak_rss_mib().filter(|_| reset);
    tracing::debug!(
        checksum,
        "baseline checksum (keeps the renders from being optimised away)"
    );

    let n = picked.len().max(1) as f64;
    let phase = |name, images: usize, wall_s: f64, peak_rss_mib| {
        let ms = wall_s * 1e3 / images.max(1) as f64;
        Phase {
            name,
            images,
            wall_s,
            ms_per_image: ms,
            vs_acquire: ms / acquire_ms,
            peak_rss_mib,
        }
    };
    let phases = vec![
        phase(
            "acquire (gonio acquire)",
            summary.stored_this_run,
            acquire_s,
            acquire_rss,
        ),
        phase("truth per view (gonio sim btf)", picked.len(), btf_s, btf_rss),
        phase("raw-frame render", picked.len(), raw_s, raw_rss),
        phase("raw-frame render + sensor", picked.len(), capture_s, raw_rss),
    ];
    let report = Report {
        rig: rig.name.clone(),
        sample: sample.name.clone(),
        sweep: sweep.name.clone(),
        size: a.size,
        truth: !a.no_truth,
        store_truth: a.store_truth,
        load_before,
        load_after: loadavg(),
        threads: rayon::current_num_threads(),
        acquire_over_sim_btf: acquire_ms / (btf_s * 1e3 / n),
        acquire_over_raw_render: acquire_ms / (raw_s * 1e3 / n),
        acquire_over_raw_capture: acquire_ms / (capture_s * 1e3 / n),
        phases,
        acquisition: summary,
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(ExitCode::SUCCESS);
    }
    let load = |l: Option<[f64; 3]>| l.map_or("?".into(), |l| format!("{:.2} {:.2} {:.2}", l[0], l[1], l[2]));
    println!(
        "rig {} · sample {} · sweep {} · {}² texels · truth {}{} · {} threads · load {} → {}",
        report.rig,
        report.sample,
        report.sweep,
        report.size,
        if report.truth { "on" } else { "off" },
        if report.store_truth { " (stored)" } else { "" },
        report.threads,
        load(report.load_before),
        load(report.load_after)
    );
    println!(
        "{:<32} {:>7} {:>9} {:>10} {:>10} {:>13}",
        "phase", "images", "wall s", "ms/image", "÷ acquire", "peak RSS MiB"
    );
    for p in &report.phases {
        println!(
            "{:<32} {:>7} {:>9.1} {:>10.2} {:>10.3} {:>13}",
            p.name,
            p.images,
            p.wall_s,
            p.ms_per_image,
            p.vs_acquire,
            p.peak_rss_mib.map_or("?".into(), |m| format!("{m:.0}"))
        );
    }
    let s = &report.acquisition.stage_seconds;
    println!(
        "acquire ÷ sim btf {:.2} · acquire ÷ raw render {:.2} · acquire ÷ raw render + sensor {:.2}",
        report.acquire_over_sim_btf, report.acquire_over_raw_render, report.acquire_over_raw_capture
    );
    println!(
        "acquisition stage seconds: motion {:.1}, capture {:.1}, rectify {:.1}, truth {:.1}, store {:.1} (drive and store overlap)",
        s.motion, s.capture, s.rectify, s.truth, s.store
    );
    Ok(ExitCode::SUCCESS)
}
