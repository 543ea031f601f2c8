//! `gonio bench hdr`: error against run time of HDR acquisition (docs/guide/hdr.md).
//!
//! Runs the same acquisition (rig, sample, sweep, size, seed) once per HDR mode — `off`,
//! fixed brackets and `auto` — with the simulator's unclipped ground truth stored, then
//! compares every stored texel with its truth. Per mode:
//!
//! - **clipped texels**: texels at the ceiling of the record's shortest exposure (≥ 99 % of
//!   `t_base / t_min` on the base exposure's scale), and those of them whose truth is below
//!   2¹⁰ × the base range (the target: none);
//! - **relative RMSE** `√(Σ(x − t)² / Σt²)` over all texels and over the highlights (truth
//!   above the single exposure's range, 1.0);
//! - **SNR of the darkest decile**: `√(Σt² / Σ(x − t)²)` over the texels whose truth is in
//!   the lowest 10 % of the non-zero truths (the error includes the rectification's own
//!   difference to the truth rendering, so it is a lower bound on the sensor SNR);
//! - **rig time** (the rig clock; virtual on the simulator) and its ratio to `off`, and the
//!   wall time of the whole run (capture, merge, rectification, truth, storage).
//!
//! Values are linear, normalised to the base exposure (no white standard), so the
//! comparison with the truth is like for like.

use anyhow::{Context, Result};
use gonio::cli::bench::{load_sample, RigArgs, SweepArgs};
use gonio::cli::bench::{log_log, Series};
use gonio_acquire::session::{NewSession, PlanRequest, RunRequest, RunSettings, Session};
use gonio_dataset::store;
use gonio_devices::hdr::HdrMode;
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

#[derive(clap::Args, Debug)]
pub struct HdrBenchArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    /// Built-in sample name or sample TOML file.
    #[arg(long, default_value = "brushed-metal")]
    pub sample: String,
    #[command(flatten)]
    pub sweep: SweepArgs,
    /// Rectified image size in texels (W×H).
    #[arg(long, default_value = "128x128", value_parser = |s: &str| gonio::cli::bench::parse_size(s, gonio::cli::bench::IMAGE_SIDES))]
    pub size: (usize, usize),
    /// Comma-separated HDR modes to compare.
    #[arg(long, default_value = "off,2,3,5,auto")]
    pub modes: String,
    /// Measure only the first N planned measurements of each run (a reduced sweep).
    #[arg(long)]
    pub limit: Option<usize>,
    /// Directory for the datasets (one per mode; replaced).
    #[arg(long, default_value = "gonio-bench-hdr")]
    pub out: PathBuf,
    /// Write the error-against-rig-time plot (SVG) to this file.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Simulated sensor without noise (isolates what is not noise: clipping, and the
    /// rectification's own difference to the truth rendering).
    #[arg(long)]
    pub no_noise: bool,
    #[arg(long)]
    pub json: bool,
}

/// One mode's figures.
#[derive(Clone, Debug, Serialize)]
pub struct HdrRow {
    pub mode: String,
    pub measurements: usize,
    /// Exposures taken, summed over the measurements.
    pub exposures: usize,
    pub texels: usize,
    pub clipped_fraction: f64,
    /// Clipped texels whose truth is below 2¹⁰ × the base range.
    pub clipped_below_2e10: usize,
    pub highlight_texels: usize,
    pub rel_rmse: f64,
    pub rel_rmse_highlights: f64,
    pub snr_dark_decile: f64,
    pub rig_time_s: f64,
    pub planned_rig_time_s: f64,
    pub rig_time_ratio: f64,
    pub wall_time_s: f64,
    /// Measurements whose record carries an HDR reason (limits reached, camera faults).
    pub measurements_with_reasons: usize,
}

pub fn run(args: HdrBenchArgs) -> Result<ExitCode> {
    let modes: Vec<HdrMode> = args
        .modes
        .split(',')
        .map(|m| HdrMode::parse(m).map_err(|e| anyhow::anyhow!("--modes: {e}")))
        .collect::<Result<_>>()?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let mut rows: Vec<HdrRow> = Vec::new();
    for mode in modes {
        let rig = args.rig.load()?;
        let dir = args.out.join(format!("hdr-{}", mode.word()));
        let new = NewSession {
            out: dir.clone(),
            force: true,
            rig,
            hdr: Some(mode),
            sample: load_sample(&args.sample)?,
            sweep: args.sweep.load()?,
            plan: PlanRequest {
                options: args.sweep.plan_options()?,
                isotropic: args.sweep.isotropic,
                sparse: None,
                fly: None,
            },
            settings: RunSettings {
                width: args.size.0,
                height: args.size.1,
                noise: !args.no_noise,
                truth: true,
                seed: None,
                raw: false,
                store_truth: true,
                reference: None,
            },
            calibration: None,
            shard: None,
        };
        let session = Session::create(&new)?;
        let req = RunRequest {
            realtime: false,
            limit: args.limit,
        };
        let summary = rt.block_on(session.run(&req, Arc::new(AtomicBool::new(false)), Arc::new(|_| {})))?;
        let mut row = evaluate(&dir, &mode.word())?;
        row.rig_time_s = summary.sweep_duration_s;
        row.wall_time_s = summary.wall_time_s;
        row.planned_rig_time_s = summary.planned_duration_s;
        rows.push(row);
        tracing::info!(mode = %mode.word(), "done");
    }
    let base = rows.iter().find(|r| r.mode == "off").map(|r| r.rig_time_s);
    for r in &mut rows {
        r.rig_time_ratio = base.map_or(f64::NAN, |b| r.rig_time_s / b);
    }
    if let Some(path) = &args.plot {
        let series = vec![
            Series {
                name: "highlights".into(),
                points: rows
                    .iter()
                    .map(|r| (r.rig_time_s, r.rel_rmse_highlights, r.mode.clone()))
                    .collect(),
            },
            Series {
                name: "all texels".into(),
                points: rows
                    .iter()
                    .map(|r| (r.rig_time_s, r.rel_rmse, r.mode.clone()))
                    .collect(),
            },
        ];
        let svg = log_log(
            &format!("HDR on {}: relative RMSE against rig time", args.sample),
            "rig time (s, simulated clock)",
            "relative RMSE vs. unclipped truth",
            &series,
        );
        std::fs::write(path, svg).with_context(|| format!("writing {}", path.display()))?;
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&rows)?);
    } else {
        println!("| mode | exposures | clipped texels | clipped < 2^10 | rel. RMSE | rel. RMSE highlights | SNR dark decile | rig time (s) | × off | planned (s) | wall (s) | with reasons |");
        println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
        for r in &rows {
            println!(
                "| {} | {} | {:.4} % | {} | {:.4} | {:.4} ({} texels) | {:.1} | {:.0} | {:.3} | {:.0} | {:.1} | {} |",
                r.mode,
                r.exposures,
                100.0 * r.clipped_fraction,
                r.clipped_below_2e10,
                r.rel_rmse,
                r.rel_rmse_highlights,
                r.highlight_texels,
                r.snr_dark_decile,
                r.rig_time_s,
                r.rig_time_ratio,
                r.planned_rig_time_s,
                r.wall_time_s,
                r.measurements_with_reasons
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Compare the stored images of the dataset in `dir` with its stored truths.
fn evaluate(dir: &std::path::Path, mode: &str) -> Result<HdrRow> {
    let (_, records) = store::load(dir).with_context(|| format!("reading {}", dir.display()))?;
    let (mut texels, mut clipped, mut clipped_low, mut hl) = (0usize, 0usize, 0usize, 0usize);
    let (mut se, mut st, mut se_hl, mut st_hl) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    let (mut measurements, mut exposures, mut with_reasons) = (0, 0, 0);
    // (truth, error²) of every texel value, for the darkest decile.
    let mut dark: Vec<(f32, f32)> = Vec::new();
    for r in records.iter().filter(|r| r.image.is_some()) {
        measurements += 1;
        let hdr = r.extra.get("hdr");
        let exps: Vec<f64> = hdr
            .and_then(|h| h.get("exposures_s"))
            .and_then(|e| serde_json::from_value(e.clone()).ok())
            .unwrap_or_else(|| vec![r.exposure_s]);
        exposures += exps.len();
        if hdr
            .and_then(|h| h.get("reasons"))
            .and_then(|v| v.as_array())
            .is_some_and(|a| !a.is_empty())
        {
            with_reasons += 1;
        }
        let t_min = exps.iter().copied().fold(f64::INFINITY, f64::min);
        let ceiling = (r.exposure_s / t_min) as f32;
        let img = store::read_exr(&dir.join(store::image_rel_path(r.index)))?;
        let truth = store::read_exr(&dir.join(store::truth_rel_path(r.index)))?;
        anyhow::ensure!(
            img.data.len() == truth.data.len(),
            "measurement {}: image and truth differ in size",
            r.index
        );
        for (&x, &t) in img.data.iter().zip(&truth.data) {
            texels += 1;
            let e2 = ((x - t) as f64).powi(2);
            se += e2;
            st += (t as f64).powi(2);
            if x >= 0.99 * ceiling {
                clipped += 1;
                if t < 1024.0 {
                    clipped_low += 1;
                }
            }
            if t > 1.0 {
                hl += 1;
                se_hl += e2;
                st_hl += (t as f64).powi(2);
            }
            if t > 0.0 {
                dark.push((t, e2 as f32));
            }
        }
    }
    dark.sort_by(|a, b| a.0.total_cmp(&b.0));
    let decile = &dark[..dark.len().div_ceil(10)];
    let (dt, de) = decile.iter().fold((0.0f64, 0.0f64), |(a, b), (t, e)| {
        (a + (*t as f64).powi(2), b + *e as f64)
    });
    Ok(HdrRow {
        mode: mode.to_string(),
        measurements,
        exposures,
        texels,
        clipped_fraction: clipped as f64 / texels.max(1) as f64,
        clipped_below_2e10: clipped_low,
        highlight_texels: hl,
        rel_rmse: (se / st.max(1e-30)).sqrt(),
        rel_rmse_highlights: if hl > 0 { (se_hl / st_hl).sqrt() } else { 0.0 },
        snr_dark_decile: (dt / de.max(1e-30)).sqrt(),
        rig_time_s: 0.0,
        planned_rig_time_s: 0.0,
        rig_time_ratio: 0.0,
        wall_time_s: 0.0,
        measurements_with_reasons: with_reasons,
    })
}
