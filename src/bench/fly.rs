//! `gonio bench fly`: rig time against error of fly-scan, per blur bound, next to stop and go
//! in the same run (docs/results/rig-time.md).
//!
//! Two parts, because the full sweep's rig time is a plan figure (exact: the engine runs
//! the plan's timing, `tests/it/fly.rs` checks it to 1e-6 s) while the error needs frames:
//!
//! 1. **rig time** of the whole sweep (`--sweep`, default Bonn 81 × 81) per bound: the fly
//!    plan against canonical, stop and go (overlapped readout), its own lower bound and the
//!    camera's readout bound;
//! 2. **error**: simulated acquisitions of a few of the sweep's views with all their lights
//!    (`--views`), per bound and stop and go, each compared with the simulator's truth
//!    (PSNR of the stored linear values, as `gonio acquire` reports it). The camera and
//!    sample stand still in flight, so what a bound costs is the reflectance's blur along
//!    the light's path: nothing on a matte sample, most on a glossy one.

use anyhow::{Context, Result};
use gonio::cli::bench::{load_sample, RigArgs, SweepArgs};
use gonio::cli::bench::{log_log, Series};
use gonio_acquire::plan::fly::FlyOptions;
use gonio_acquire::session::{NewSession, PlanRequest, RunRequest, RunSettings, Session};
use gonio_dataset::sweep::Sweep;
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

#[derive(clap::Args, Debug)]
pub struct FlyBenchArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    #[command(flatten)]
    pub sweep: SweepArgs,
    /// Comma-separated blur bounds (degrees of light direction per exposure).
    #[arg(long, default_value = "0.1,0.25,0.5,1,2")]
    pub blur_deg: String,
    /// Comma-separated samples for the error part (built-in names or TOML files).
    #[arg(long, default_value = "wallpaper,brushed-metal")]
    pub samples: String,
    /// Views of the sweep measured in the error part (spread over its view list), each with
    /// every light.
    #[arg(long, default_value_t = 2)]
    pub views: usize,
    /// Rectified image side (texels).
    #[arg(long, default_value_t = 32)]
    pub size: usize,
    /// Sensor noise in the error part: on (the real case) or off.
    #[arg(long, default_value = "on", value_parser = ["on", "off"])]
    pub noise: String,
    /// Directory for the datasets (replaced).
    #[arg(long, default_value = "gonio-bench-fly")]
    pub out: PathBuf,
    /// Write the PSNR-against-rig-time plot (SVG) to this file.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Fly at one constant velocity per flight instead of a velocity profile per gap (the
    /// plans before per-gap profiles), for comparison.
    #[arg(long)]
    pub fly_constant_velocity: bool,
    #[arg(long)]
    pub json: bool,
}

/// The whole sweep's rig time at one bound (`None`: stop and go).
#[derive(Clone, Debug, Serialize)]
pub struct PlanRow {
    pub blur_deg: Option<f64>,
    pub rig_time_s: f64,
    pub over_canonical: f64,
    pub lower_bound_s: f64,
    pub flown_pairs: usize,
    pub pairs: usize,
    pub max_light_sweep_deg: f64,
    pub max_image_blur_px: f64,
}

/// One measured run of the error part.
#[derive(Clone, Debug, Serialize)]
pub struct ErrorRow {
    pub sample: String,
    pub blur_deg: Option<f64>,
    pub pairs: usize,
    pub flown_pairs: usize,
    pub rig_time_s: f64,
    pub psnr_db: f64,
    /// PSNR minus stop and go's on the same pairs (dB).
    pub delta_db: f64,
    pub wall_s: f64,
}

#[derive(Serialize)]
struct Report {
    sweep: String,
    canonical_s: f64,
    readout_bound_s: f64,
    plans: Vec<PlanRow>,
    measured_sweep: String,
    size: usize,
    noise: bool,
    errors: Vec<ErrorRow>,
}

fn parse_bounds(s: &str) -> Result<Vec<f64>> {
    s.split(',')
        .map(|t| {
            let b: f64 = t
                .trim()
                .parse()
                .with_context(|| format!("--blur-deg: `{t}` is not a number"))?;
            FlyOptions::new(b)?;
            Ok(b)
        })
        .collect()
}

pub fn run(a: FlyBenchArgs) -> Result<ExitCode> {
    let rig = a.rig.load()?;
    let sweep = a.sweep.load()?;
    let bounds = parse_bounds(&a.blur_deg)?;
    anyhow::ensure!(
        a.views >= 1 && a.views <= sweep.views.len(),
        "--views {}: between 1 and the sweep's {} views",
        a.views,
        sweep.views.len()
    );
    let opts = a.sweep.plan_options()?;

    // 1. The whole sweep's rig time.
    let base = gonio_acquire::plan::Plan::build(&rig, &sweep, &opts)?;
    let canonical = base.durations.canonical_s;
    let mut plans = vec![PlanRow {
        blur_deg: None,
        rig_time_s: base.durations.optimized_s,
        over_canonical: base.durations.optimized_s / canonical,
        lower_bound_s: base.durations.lower_bound_s,
        flown_pairs: 0,
        pairs: base.steps.len(),
        max_light_sweep_deg: 0.0,
        max_image_blur_px: 0.0,
    }];
    let mut readout_bound = 0.0;
    for &b in &bounds {
        let p = base.clone().into_fly(
            &rig,
            &opts,
            FlyOptions::new(b)?.with_constant_velocity(a.fly_constant_velocity),
        )?;
        let f = p.fly.as_ref().expect("a fly plan records its figures");
        readout_bound = f.readout_bound_s;
        plans.push(PlanRow {
            blur_deg: Some(b),
            rig_time_s: p.durations.optimized_s,
            over_canonical: p.durations.optimized_s / canonical,
            lower_bound_s: f.lower_bound_s,
            flown_pairs: f.flown_pairs,
            pairs: p.steps.len(),
            max_light_sweep_deg: f.max_light_sweep_deg,
            max_image_blur_px: f.max_image_blur_px,
        });
        if !a.json {
            eprintln!("plan {b} °: {:.0} s", p.durations.optimized_s);
        }
    }

    // 2. The error on a few views with every light.
    let n = sweep.views.len();
    // Spread over the list: the middle of each of `views` equal parts.
    let views: Vec<_> = (0..a.views)
        .map(|k| sweep.views[(2 * k + 1) * n / (2 * a.views)])
        .collect();
    let measured = Sweep {
        name: format!("{}-{}-views", sweep.name, a.views),
        lights: sweep.lights.clone(),
        views,
    };
    let noise = a.noise == "on";
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let mut errors = Vec::new();
    for name in a.samples.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        let sample = load_sample(name)?;
        let mut reference = None;
        for b in std::iter::once(None).chain(bounds.iter().copied().map(Some)) {
            let dir = a.out.join(format!(
                "{name}-{}",
                b.map_or("stop-and-go".to_string(), |b| format!("fly-{b}"))
            ));
            let session = Session::create(&NewSession {
                out: dir.clone(),
                force: true,
                rig: rig.clone(),
                hdr: None,
                sample: sample.clone(),
                sweep: measured.clone(),
                plan: PlanRequest {
                    options: opts.clone(),
                    isotropic: false,
                    sparse: None,
                    fly: b
                        .map(|b| FlyOptions::new(b).map(|f| f.with_constant_velocity(a.fly_constant_velocity)))
                        .transpose()?,
                },
                settings: RunSettings {
                    width: a.size,
                    height: a.size,
                    noise,
                    truth: true,
                    seed: None,
                    raw: false,
                    store_truth: false,
                    reference: None,
                },
                calibration: None,
                shard: None,
            })
            .with_context(|| format!("creating {}", dir.display()))?;
            let flown = session.plan().steps.iter().filter(|s| s.flight.is_some()).count();
            let t = std::time::Instant::now();
            let s = rt
                .block_on(session.run(
                    &RunRequest::default(),
                    Arc::new(AtomicBool::new(false)),
                    Arc::new(|_: &gonio_acquire::engine::RunEvent<'_>| {}),
                ))
                .with_context(|| format!("acquiring {}", dir.display()))?;
            let psnr = s.truth_error.as_ref().map_or(f64::NAN, |e| e.psnr_db);
            let reference_db = *reference.get_or_insert(psnr);
            let row = ErrorRow {
                sample: name.to_string(),
                blur_deg: b,
                pairs: s.stored_this_run,
                flown_pairs: flown,
                rig_time_s: s.sweep_duration_s,
                psnr_db: psnr,
                delta_db: psnr - reference_db,
                wall_s: t.elapsed().as_secs_f64(),
            };
            if !a.json {
                eprintln!(
                    "{name} {}: {:.2} dB, {:.0} s",
                    b.map_or("stop and go".into(), |b| format!("{b} °")),
                    row.psnr_db,
                    row.rig_time_s
                );
            }
            errors.push(row);
        }
    }
    let report = Report {
        sweep: sweep.name.clone(),
        canonical_s: canonical,
        readout_bound_s: readout_bound,
        plans,
        measured_sweep: measured.name.clone(),
        size: a.size,
        noise,
        errors,
    };
    if let Some(path) = &a.plot {
        std::fs::write(path, plot(&report)).with_context(|| format!("writing {}", path.display()))?;
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_report(&report);
    }
    Ok(ExitCode::SUCCESS)
}

fn label(b: Option<f64>) -> String {
    b.map_or("stop and go".into(), |b| format!("fly {b} °"))
}

fn print_report(r: &Report) {
    println!(
        "rig time of sweep {} (canonical {:.0} s; the camera alone needs {:.0} s = {:.3} ×):",
        r.sweep,
        r.canonical_s,
        r.readout_bound_s,
        r.readout_bound_s / r.canonical_s
    );
    println!(
        "  {:<14} {:>9} {:>11} {:>9} {:>7} {:>10}",
        "mode", "rig s", "× canonical", "bound s", "flown", "sweep °"
    );
    for p in &r.plans {
        println!(
            "  {:<14} {:>9.0} {:>11.3} {:>9.0} {:>7} {:>10.3}",
            label(p.blur_deg),
            p.rig_time_s,
            p.over_canonical,
            p.lower_bound_s,
            p.flown_pairs,
            p.max_light_sweep_deg
        );
    }
    println!(
        "error on {} at {}² (noise {}), PSNR of the stored values against the truth:",
        r.measured_sweep,
        r.size,
        if r.noise { "on" } else { "off" }
    );
    println!(
        "  {:<14} {:<14} {:>6} {:>7} {:>8} {:>9} {:>8}",
        "sample", "mode", "pairs", "flown", "rig s", "PSNR dB", "Δ dB"
    );
    for e in &r.errors {
        println!(
            "  {:<14} {:<14} {:>6} {:>7} {:>8.0} {:>9.2} {:>+8.2}",
            e.sample,
            label(e.blur_deg),
            e.pairs,
            e.flown_pairs,
            e.rig_time_s,
            e.psnr_db,
            e.delta_db
        );
    }
}

/// PSNR against rig time (× canonical of the measured views), one curve per sample.
fn plot(r: &Report) -> String {
    let mut series: Vec<Series> = Vec::new();
    for e in &r.errors {
        let pt = (e.rig_time_s, e.psnr_db, label(e.blur_deg));
        match series.iter_mut().find(|s| s.name == e.sample) {
            Some(s) => s.points.push(pt),
            None => series.push(Series {
                name: e.sample.clone(),
                points: vec![pt],
            }),
        }
    }
    log_log(
        &format!("fly-scan: PSNR against rig time ({}, {}²)", r.measured_sweep, r.size),
        "rig time (s)",
        "PSNR vs truth (dB)",
        &series,
    )
}
