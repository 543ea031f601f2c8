//! `gonio bench …`: benchmarks run by the CLI itself, reported as ratios against a
//! baseline measured in the same process (absolute times vary with the machine).

use super::common::{load_sample, RigArgs};
use anyhow::Result;
use gonio_dataset::sweep;
use gonio_devices::kinematics;
use gonio_simulator::sensor::SensorModel;
use gonio_simulator::{PointLight, RenderQuality, Renderer};
use serde::Serialize;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

#[derive(clap::Subcommand, Debug)]
pub enum BenchCommand {
    /// Time the simulator's stages (raw render, ground truth, sensor) per sample kind.
    Sim(SimBenchArgs),
    /// Planner quality against its time budget: optimized duration vs. the lower bound.
    Plan(PlanBenchArgs),
    /// Render error against a high-sample reference versus time, per quality knob.
    Render(RenderBenchArgs),
    /// Serial layer cost over a pty: round trips/s and per-measurement overhead vs. sim axes.
    Serial(super::bench_serial::SerialBenchArgs),
    /// Every compression method over its knob: error vs. encode time and vs. ratio (table + SVG).
    #[cfg(feature = "btf")]
    Compress(super::bench_compress::CompressBenchArgs),
    /// Every synthesis method against a 4×-area simulator reference: seams, statistics, repetition, time.
    #[cfg(feature = "btf")]
    Synthesize(Box<super::bench_synthesize::SynthesizeBenchArgs>),
    /// The full simulated acquisition against `gonio sim btf` and raw-frame rendering alone
    /// (ms/image ratios measured in one run, peak memory per phase).
    Acquire(Box<super::bench_acquire::AcquireBenchArgs>),
    /// HDR acquisition per mode (off, fixed brackets, auto): clipping, error vs. unclipped truth, rig and wall time (table + SVG).
    Hdr(super::bench_hdr::HdrBenchArgs),
    /// Fly-scan per blur bound against stop and go: the sweep's rig time, and PSNR against the truth on a few views.
    Fly(Box<super::bench_fly::FlyBenchArgs>),
    /// Sparse acquisition: PSNR of the completed dataset against rig time, with baselines.
    #[cfg(feature = "btf")]
    Sparse(Box<super::bench_sparse::SparseBenchArgs>),
    /// Decode time of one image of a compressed BTF, on its own (median of rounds; EXR reads of the same images as the baseline).
    #[cfg(feature = "btf")]
    Decode(super::bench_decode::DecodeBenchArgs),
    /// The inspect page's ABRDF of a raw dataset: texel-major cache build time and per-click time.
    #[cfg(feature = "btf")]
    ViewCache(super::bench_view::ViewCacheBenchArgs),
    /// BRDF fitting: starts × iterations against residual and time, on data of known models.
    #[cfg(feature = "btf")]
    Fit(super::bench_fit::FitBenchArgs),
}

#[derive(clap::Args, Debug)]
pub struct RenderBenchArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    #[arg(long, default_value = gonio_simulator::sample::DEFAULT_SAMPLE)]
    pub sample: String,
    /// Measurements (Bonn pairs spread over the sweep).
    #[arg(long, default_value_t = 8)]
    pub measurements: usize,
    /// Samples per pixel and axis of the reference.
    #[arg(long, default_value_t = 8)]
    pub reference: usize,
    /// Radius (mm) of a disc lamp to render with (default: the rig's
    /// `light.options.radius_mm`, else a point lamp); adds rows for its emitter count.
    #[arg(long)]
    pub lamp_radius: Option<f64>,
    /// Write the error-versus-time plot (SVG, log–log, one line per knob) to this file.
    #[arg(long)]
    pub plot: Option<std::path::PathBuf>,
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct RenderRow {
    image: &'static str,
    /// Which knob this row turns (the rows of one family share the plot's line).
    family: &'static str,
    knob: String,
    ms_per_image: f64,
    /// RMSE against the reference, relative to the reference's mean value.
    relative_rmse: f64,
}

fn render(a: RenderBenchArgs) -> Result<ExitCode> {
    let rig = a.rig.load()?;
    let kin = kinematics::for_rig(&rig);
    let dirs = sweep::bonn81();
    // Views spread over the sweep, lights stepping through all rings (a stride of 37 of
    // the 81 Bonn lights) so that grazing lights, where shadow maps matter, are included.
    let qs: Vec<Vec<f64>> = (0..a.measurements.max(1))
        .map(|k| (k * 81 / a.measurements.max(1)) * 81 + (k * 37 + 13) % 81)
        .filter_map(|idx| {
            kin.inverse(dirs[idx % 81], dirs[idx / 81], None)
                .ok()
                .map(|s| s[0].clone())
        })
        .collect();
    let spec = load_sample(&a.sample)?;
    let sample = Arc::new(spec.build()?);
    let intr = rig.camera.intrinsics();
    let radius = match a.lamp_radius {
        Some(r) if r.is_finite() && r >= 0.0 && r <= rig.geometry.light_distance_mm / 2.0 => r,
        Some(r) => anyhow::bail!(
            "--lamp-radius {r}: must be between 0 and {} mm (half the lamp distance)",
            rig.geometry.light_distance_mm / 2.0
        ),
        None => gonio_simulator::lamp_radius_mm(&rig)?,
    };
    let light = |q: &[f64]| PointLight {
        position: kin.light_position(q),
        intensity: rig.light.intensity_w_sr,
        radius,
    };
    let raw = |quality: RenderQuality| {
        let r = Renderer::new(sample.clone(), quality);
        let t = Instant::now();
        let imgs: Vec<_> = qs
            .iter()
            .map(|q| {
                r.render_raw(
                    &intr,
                    &kin.camera_pose(q),
                    rig.camera.width,
                    rig.camera.height,
                    &light(q),
                )
            })
            .collect();
        (imgs, t.elapsed().as_secs_f64() * 1e3 / qs.len() as f64)
    };
    let truth = |quality: RenderQuality| {
        let r = Renderer::new(sample.clone(), quality);
        let t = Instant::now();
        let imgs: Vec<_> = qs
            .iter()
            .map(|q| r.render_truth(kin.camera_pose(q).position, 256, 256, &light(q)))
            .collect();
        (imgs, t.elapsed().as_secs_f64() * 1e3 / qs.len() as f64)
    };
    let rel_rmse = |a: &[gonio_devices::image::RgbImage], b: &[gonio_devices::image::RgbImage]| {
        let (mut sq, mut sum, mut n) = (0.0f64, 0.0f64, 0usize);
        for (x, y) in a.iter().zip(b) {
            for (p, r) in x.data.iter().zip(&y.data) {
                sq += ((p - r) as f64).powi(2);
                sum += *r as f64;
                n += 1;
            }
        }
        (sq / n as f64).sqrt() / (sum / n as f64).max(1e-30)
    };
    let q = |supersample, shadow_scale, truth_supersample, area_samples| RenderQuality {
        supersample,
        shadow_scale,
        truth_supersample,
        area_samples,
    };
    // A disc lamp's emitters are a knob too (reference: 64); a point lamp has none.
    let (area_ref, area_knobs): (usize, &[usize]) = if radius > 0.0 { (64, &[1, 4, 16]) } else { (1, &[]) };
    let mut rows = Vec::new();
    // Pixel and shadow knobs are measured with a point lamp (each disc emitter would
    // multiply the reference's cost); the disc's emitter count has its own reference.
    let (raw_ref, _) = raw(q(a.reference, 4, 1, 1));
    for (ss, sh) in [(1, 1), (2, 1), (4, 1), (1, 2), (1, 4), (2, 2)] {
        let (imgs, ms) = raw(q(ss, sh, 1, 1));
        rows.push(RenderRow {
            image: "raw",
            family: match (ss, sh) {
                (_, 1) => "raw: pixel supersampling",
                (1, _) => "raw: shadow-map resolution",
                _ => "raw: both",
            },
            knob: format!("supersample {ss}, shadow map ×{sh}"),
            ms_per_image: ms,
            relative_rmse: rel_rmse(&imgs, &raw_ref),
        });
    }
    let (truth_ref, _) = truth(q(1, 4, a.reference, 1));
    for (ts, sh) in [(1, 1), (2, 1), (4, 1), (1, 4)] {
        let (imgs, ms) = truth(q(1, sh, ts, 1));
        rows.push(RenderRow {
            image: "truth",
            family: if sh == 1 {
                "truth: samples per texel"
            } else {
                "truth: shadow-map resolution"
            },
            knob: format!("samples/texel {ts}², shadow map ×{sh}"),
            ms_per_image: ms,
            relative_rmse: rel_rmse(&imgs, &truth_ref),
        });
    }
    if !area_knobs.is_empty() {
        // Truth images (1 sample per texel): what the disc's emitter count alone costs.
        let (area_ref_imgs, _) = truth(q(1, 1, 1, area_ref));
        for &k in area_knobs {
            let (imgs, ms) = truth(q(1, 1, 1, k));
            rows.push(RenderRow {
                image: "truth",
                family: "truth: disc-lamp emitters",
                knob: format!("disc lamp r = {radius} mm, {k} emitters (ref. {area_ref})"),
                ms_per_image: ms,
                relative_rmse: rel_rmse(&imgs, &area_ref_imgs),
            });
        }
    }
    if let Some(path) = &a.plot {
        std::fs::write(path, render_plot(&a.sample, &rows))
            .map_err(|e| anyhow::anyhow!("--plot {}: cannot write the plot: {e}", path.display()))?;
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&rows)?);
    } else {
        println!(
            "sample {} · {} measurements · reference: {}² samples per pixel/texel, shadow map ×4",
            a.sample,
            qs.len(),
            a.reference
        );
        println!("{:<6} {:<34} {:>12} {:>14}", "image", "knob", "ms/image", "rel. RMSE");
        for r in &rows {
            println!(
                "{:<6} {:<34} {:>12.2} {:>14.5}",
                r.image, r.knob, r.ms_per_image, r.relative_rmse
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Error against time, one line per knob family. A family's first setting (1 sample,
/// shadow map ×1) is also the start of the other families, so each line starts there.
fn render_plot(sample: &str, rows: &[RenderRow]) -> String {
    use super::svg_plot::{log_log, Series};
    let mut series: Vec<Series> = Vec::new();
    for r in rows {
        let point = (r.ms_per_image, r.relative_rmse, r.knob.clone());
        match series.iter_mut().find(|s| s.name == r.family) {
            Some(s) => s.points.push(point),
            None => series.push(Series {
                name: r.family.into(),
                points: vec![point],
            }),
        }
    }
    for s in &mut series {
        s.points.sort_by(|a, b| a.0.total_cmp(&b.0));
    }
    log_log(
        &format!("gonio bench render · sample {sample}: error against a high-sample reference"),
        "ms per image",
        "relative RMSE",
        &series,
    )
}

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

fn plan(a: PlanBenchArgs) -> Result<ExitCode> {
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

#[derive(clap::Args, Debug)]
pub struct SimBenchArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    /// Samples to time (built-in names or files).
    #[arg(long, num_args = 1.., default_values_t = ["white-standard".to_string(), "calibration-target".to_string(), "wallpaper".to_string(), "leather".to_string()])]
    pub samples: Vec<String>,
    /// Measurements (Bonn pairs, spread over the sweep) per sample.
    #[arg(long, default_value_t = 40)]
    pub measurements: usize,
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct SimRow {
    sample: String,
    relief: bool,
    homogeneous: bool,
    raw_ms: f64,
    truth_ms: f64,
    sensor_noise_ms: f64,
    sensor_noiseless_ms: f64,
    shadow_maps_built: usize,
    raw_vs_first: f64,
}

pub fn run(cmd: BenchCommand) -> Result<ExitCode> {
    match cmd {
        BenchCommand::Sim(a) => sim(a),
        BenchCommand::Plan(a) => plan(a),
        BenchCommand::Render(a) => render(a),
        BenchCommand::Serial(a) => super::bench_serial::run(a),
        #[cfg(feature = "btf")]
        BenchCommand::Compress(a) => super::bench_compress::run(a),
        #[cfg(feature = "btf")]
        BenchCommand::Synthesize(a) => super::bench_synthesize::run(*a),
        BenchCommand::Acquire(a) => super::bench_acquire::run(*a),
        BenchCommand::Hdr(a) => super::bench_hdr::run(a),
        BenchCommand::Fly(a) => super::bench_fly::run(*a),
        #[cfg(feature = "btf")]
        BenchCommand::Sparse(a) => super::bench_sparse::run(*a),
        #[cfg(feature = "btf")]
        BenchCommand::Decode(a) => super::bench_decode::run(a),
        #[cfg(feature = "btf")]
        BenchCommand::ViewCache(a) => super::bench_view::run(a),
        #[cfg(feature = "btf")]
        BenchCommand::Fit(a) => super::bench_fit::run(a),
    }
}

fn sim(a: SimBenchArgs) -> Result<ExitCode> {
    let rig = a.rig.load()?;
    let kin = kinematics::for_rig(&rig);
    let dirs = sweep::bonn81();
    let pairs: Vec<_> = (0..a.measurements.max(1))
        .map(|k| {
            let idx = (k * 6561 / a.measurements.max(1) + 7) % 6561;
            (dirs[idx % 81], dirs[idx / 81])
        })
        .filter_map(|(l, v)| kin.inverse(l, v, None).ok().map(|s| s[0].clone()))
        .collect();
    let intr = rig.camera.intrinsics();
    let mut rows: Vec<SimRow> = Vec::new();
    for name in &a.samples {
        let spec = load_sample(name)?;
        let sample = Arc::new(spec.build()?);
        let relief = matches!(sample.surface, gonio_simulator::sample::Surface::Height(_));
        let homogeneous = sample.is_homogeneous();
        let r = Renderer::new(sample, RenderQuality::default());
        let lights: Vec<PointLight> = pairs
            .iter()
            .map(|q| PointLight::point(kin.light_position(q), 50.0))
            .collect();
        let t = Instant::now();
        let mut last = None;
        for (q, l) in pairs.iter().zip(&lights) {
            last = Some(r.render_raw(&intr, &kin.camera_pose(q), rig.camera.width, rig.camera.height, l));
        }
        let raw_ms = t.elapsed().as_secs_f64() * 1e3 / pairs.len() as f64;
        let t = Instant::now();
        for (q, l) in pairs.iter().zip(&lights) {
            let _ = r.render_truth(kin.camera_pose(q).position, 256, 256, l);
        }
        let truth_ms = t.elapsed().as_secs_f64() * 1e3 / pairs.len() as f64;
        let frame = last.expect("at least one measurement");
        let mut sensor = SensorModel {
            full_well_e: 20000.0,
            read_noise_e: 4.0,
            dark_current_e_s: 5.0,
            sensitivity_e_per_radiance_s: 14000.0,
            vignetting: 0.05,
            bit_depth: 12,
            gain: 1.0,
            exposure_s: 0.05,
            noise: true,
            seed: 1,
        };
        let reps = 10;
        let t = Instant::now();
        for k in 0..reps {
            let _ = sensor.expose(&frame, k);
        }
        let sensor_noise_ms = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
        sensor.noise = false;
        let t = Instant::now();
        for k in 0..reps {
            let _ = sensor.expose(&frame, k);
        }
        let sensor_noiseless_ms = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
        let first = rows.first().map(|r| r.raw_ms).unwrap_or(raw_ms);
        rows.push(SimRow {
            sample: name.clone(),
            relief,
            homogeneous,
            raw_ms,
            truth_ms,
            sensor_noise_ms,
            sensor_noiseless_ms,
            shadow_maps_built: r.shadow_maps_built(),
            raw_vs_first: raw_ms / first,
        });
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&rows)?);
    } else {
        println!(
            "{:<20} {:>6} {:>5} {:>9} {:>9} {:>11} {:>14} {:>7} {:>8}",
            "sample", "relief", "homog", "raw ms", "truth ms", "sensor ms", "noiseless ms", "shadows", "raw/1st"
        );
        for r in &rows {
            println!(
                "{:<20} {:>6} {:>5} {:>9.2} {:>9.2} {:>11.2} {:>14.2} {:>7} {:>8.2}",
                r.sample,
                r.relief,
                r.homogeneous,
                r.raw_ms,
                r.truth_ms,
                r.sensor_noise_ms,
                r.sensor_noiseless_ms,
                r.shadow_maps_built,
                r.raw_vs_first
            );
        }
        println!(
            "({} measurements per sample, {}×{} raw frames, 256² truth)",
            pairs.len(),
            rig.camera.width,
            rig.camera.height
        );
    }
    Ok(ExitCode::SUCCESS)
}
