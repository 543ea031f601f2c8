//! `gonio acquire`: run (or resume) an acquisition and print its summary.

use super::common::{load_sample, parse_size, RigArgs, SweepArgs, IMAGE_SIDES};
use anyhow::{Context, Result};
use gonio_acquire::engine::{Observer, RunEvent};
use gonio_acquire::session::{
    NewSession, PlanRequest, ReferenceSettings, RunRequest, RunSettings, Session, SparsePlan, Summary,
};
use gonio_devices::hdr::HdrMode;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

#[derive(clap::Args, Debug)]
pub struct AcquireArgs {
    /// Output dataset directory (refused if it exists, unless --force).
    #[arg(long, default_value = "gonio-dataset", conflicts_with = "resume")]
    pub out: PathBuf,
    /// Continue an interrupted acquisition in DIR (rig, sample, sweep and plan come from it).
    #[arg(long, value_name = "DIR")]
    pub resume: Option<PathBuf>,
    /// Replace an existing gonio dataset at --out.
    #[arg(long)]
    pub force: bool,
    #[command(flatten)]
    pub rig: RigArgs,
    /// Built-in sample name or sample TOML file (simulated rigs).
    #[arg(long, default_value = gonio_simulator::sample::DEFAULT_SAMPLE)]
    pub sample: String,
    #[command(flatten)]
    pub sweep: SweepArgs,
    /// Rectified image size in texels (W×H).
    #[arg(long, default_value = "256x256", value_parser = |s: &str| parse_size(s, IMAGE_SIDES))]
    pub size: (usize, usize),
    /// Pace the simulated rig in real time instead of on a virtual clock.
    #[arg(long)]
    pub realtime: bool,
    /// Also store the raw frames (16-bit PNG).
    #[arg(long)]
    pub raw: bool,
    /// Simulated sensor without noise.
    #[arg(long)]
    pub no_noise: bool,
    /// Do not compare with the simulator's ground truth (saves its render time).
    #[arg(long)]
    pub no_truth: bool,
    /// Also write the simulator's exact rectified ground truth as truth/NNNNN.exr.
    #[arg(long, conflicts_with = "no_truth")]
    pub store_truth: bool,
    /// Seed of the simulated sensor noise.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Print the summary as JSON on stdout.
    #[arg(long)]
    pub json: bool,
    /// Run CMD (`sh -c CMD`) when the run pauses (Ctrl-C, --limit), finishes or fails, to
    /// notify someone. Its environment: GONIO_DATASET (the dataset directory),
    /// GONIO_STATE (`paused`, `finished` or `failed`) and GONIO_MESSAGE (the error of a
    /// failed run, else empty). Its failure is reported and does not change the exit code.
    #[arg(long, value_name = "CMD")]
    pub on_pause: Option<String>,
    /// Start even when the planned dataset size (an upper bound) exceeds the free space
    /// of its disk.
    #[arg(long)]
    pub no_space_check: bool,
    /// Stop after this many measurements (the run stays resumable).
    #[arg(long)]
    pub limit: Option<usize>,
    /// Apply the calibration results in DIR (`DIR/calibration.json` and
    /// `DIR/*/calibration.json`, one per kind, made on this rig): intrinsics undistort and
    /// rectify, a white standard converts values to BRDF (1/sr). The manifest records their
    /// ids; copies are kept in the dataset for --resume.
    #[arg(long, value_name = "DIR", conflicts_with = "resume")]
    pub calibration: Option<PathBuf>,
    /// Serve the browser viewer (monitor, relight, inspect) on the dataset being written,
    /// on loopback; its tokened URL is the first line on stderr (`view: http://…`). After
    /// the run it keeps serving until Ctrl-C. Read-only: nothing on the page moves the rig.
    #[arg(long)]
    pub view: bool,
    /// Measure only shard I of N (1-based; the contiguous views `[(I−1)·V/N, I·V/N)`):
    /// the whole sweep is planned as one process would plan it, and only the steps of the
    /// shard's views are run, so `gonio merge` of the N parts gives the single-process
    /// images byte for byte (docs/guide/scale.md). Simulated rigs; not with --isotropic.
    #[arg(long, conflicts_with = "resume")]
    pub shard: Option<gonio_dataset::shard::Shard>,
    /// Port of --view (0 picks a free one).
    #[arg(long, default_value_t = 0, requires = "view")]
    pub view_port: u16,
    /// Exposure bracketing per measurement: `off` (one exposure), `auto` (extra exposures
    /// only where the sample region saturates or its darkest decile is below the SNR
    /// floor), or N fixed exposures (2 ..= 8). Default: the rig file's `[hdr] mode`, else
    /// off. Limits and noise model come from the rig file's `[hdr]` (see docs/guide/hdr.md).
    #[arg(long, value_name = "off|auto|N", value_parser = parse_hdr, conflicts_with = "resume")]
    pub hdr: Option<HdrMode>,
    /// Sparse acquisition (`--prior P --pairs N | --fraction F | --rig-budget S`): measure
    /// the pairs an optimal design in the prior chooses, as `gonio plan` with the same
    /// flags shows; `gonio complete` predicts the rest (docs/guide/sparse.md).
    #[command(flatten)]
    pub sparse: super::sparse::SparseArgs,
    #[command(flatten)]
    pub fly: super::common::FlyArgs,
    /// Re-measure a reference pair and a dark frame (light off, same exposure) before the
    /// first measurement, whenever at least MINUTES of rig time have passed since the last
    /// one (at a measurement boundary), and when the run ends; stored in references.jsonl
    /// and reference/, so optical drift is tracked (the summary's largest drift) and
    /// correctable (`gonio dataset drift DIR --correct --out NEW`). MINUTES: finite, > 0.
    /// Kept in the manifest: --resume continues the schedule.
    #[arg(long, value_name = "MINUTES", allow_hyphen_values = true, conflicts_with = "resume")]
    pub reference_every: Option<f64>,
    /// The reference pair as LIGHT_INDEX,VIEW_INDEX into the sweep (a pair the plan
    /// measures); default: the plan's first measured pair.
    #[arg(long, value_name = "LIGHT,VIEW", value_parser = parse_pair, requires = "reference_every")]
    pub reference_pair: Option<[usize; 2]>,
}

fn parse_pair(s: &str) -> std::result::Result<[usize; 2], String> {
    let bad = || format!("{s:?}: give LIGHT_INDEX,VIEW_INDEX, two indices into the sweep, e.g. 0,3");
    let (l, v) = s.split_once(',').ok_or_else(bad)?;
    Ok([
        l.trim().parse().map_err(|_| bad())?,
        v.trim().parse().map_err(|_| bad())?,
    ])
}

fn parse_hdr(s: &str) -> std::result::Result<HdrMode, String> {
    HdrMode::parse(s)
}

pub fn run(args: AcquireArgs) -> Result<ExitCode> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    rt.block_on(run_async(args))
}

async fn run_async(args: AcquireArgs) -> Result<ExitCode> {
    let session = match &args.resume {
        Some(dir) => {
            if args.fly.fly || args.fly.blur_deg.is_some() || args.fly.fly_constant_velocity {
                anyhow::bail!(
                    "--resume {}: --fly and --blur-deg shape a new acquisition's plan; a resumed one flies as its \
                     plan.json says: drop them",
                    dir.display()
                );
            }
            if args.sparse.prior.is_some() || args.sparse.target()?.is_some() {
                anyhow::bail!(
                    "--resume {}: the sparse flags (--prior, --pairs, --fraction, --rig-budget, --adaptive) choose the pairs of a \
                     new acquisition; a resumed one measures the pairs its plan.json chose: drop them",
                    dir.display()
                );
            }
            Session::resume(dir)?
        }
        None => Session::create(&new_session(&args)?)?,
    };
    if let (Some(info), false) = (&session.plan().sparse, args.json) {
        super::sparse::print_summary(session.plan(), info);
    }
    // Before the first frame: will it fit, and when will it end?
    let pre = session.preflight();
    if !pre.fits() && !args.no_space_check {
        anyhow::bail!(
            "dataset {}: the {} remaining measurements need up to {} and its disk has {} free: free space, \
             write to another disk (--out), or pass --no-space-check (the estimate is an upper bound: \
             uncompressed float32 images)",
            session.dir().display(),
            pre.remaining,
            gonio_acquire::session::preflight::human_bytes(pre.planned_bytes),
            gonio_acquire::session::preflight::human_bytes(pre.free_bytes.unwrap_or(0)),
        );
    }
    tracing::info!(
        remaining = pre.remaining,
        planned_s = pre.planned_s,
        planned_bytes = pre.planned_bytes,
        "planned end {}",
        pre.planned_end_utc()
    );
    if !args.json {
        eprintln!(
            "planned: {} measurements, {:.0} s of rig time, up to {} on disk ({} free); ends about {}",
            pre.remaining,
            pre.planned_s,
            gonio_acquire::session::preflight::human_bytes(pre.planned_bytes),
            pre.free_bytes
                .map_or("unknown".into(), gonio_acquire::session::preflight::human_bytes),
            pre.planned_end_utc()
        );
    }
    let viewer = match args.view {
        true => Some(serve_view(session.dir(), args.view_port).await?),
        false => None,
    };
    let pause = Arc::new(AtomicBool::new(false));
    let pause_task = {
        let pause = pause.clone();
        tokio::spawn(async move {
            if tokio::signal::ctrl_c().await.is_ok() {
                pause.store(true, Ordering::SeqCst);
                eprintln!("\nCtrl-C: pausing at the next measurement boundary (press again to abort)…");
                if tokio::signal::ctrl_c().await.is_ok() {
                    eprintln!("aborted; stored measurements are safe, resume with `gonio acquire --resume`");
                    std::process::exit(130);
                }
            }
        })
    };
    let show = !args.json && std::io::IsTerminal::is_terminal(&std::io::stderr());
    let bar = progress_bar(show);
    let observer: Observer = {
        let bar = bar.clone();
        Arc::new(move |e: &RunEvent<'_>| match e {
            RunEvent::Started { to_do, .. } => bar.set_length(*to_do as u64),
            RunEvent::Captured { .. } => bar.inc(1),
            RunEvent::Stored { .. } | RunEvent::Reference { .. } => {}
        })
    };
    let req = RunRequest {
        realtime: args.realtime,
        limit: args.limit,
    };
    let dataset_dir = session.dir().to_path_buf();
    let summary = session.run(&req, pause, observer).await;
    bar.finish_and_clear();
    if let Some(cmd) = &args.on_pause {
        let (state, message) = match &summary {
            Err(e) => ("failed", error_chain(e)),
            Ok(s) if s.complete => ("finished", String::new()),
            Ok(_) => ("paused", String::new()),
        };
        on_pause(cmd, &dataset_dir, state, &message);
    }
    let summary = summary?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        print_summary(&summary);
    }
    if let Some(url) = viewer {
        pause_task.abort();
        eprintln!("view: the acquisition has ended; still serving {url} until Ctrl-C");
        let _ = tokio::signal::ctrl_c().await;
    }
    Ok(if summary.complete {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(3)
    })
}

/// Start the viewer on the session's dataset (loopback only) and print its URL on stderr.
#[cfg(feature = "monitor")]
async fn serve_view(dir: &std::path::Path, port: u16) -> Result<String> {
    let opts = crate::view::server::ViewOptions {
        path: dir.to_path_buf(),
        bind: std::net::IpAddr::V4(std::net::Ipv4Addr::LOCALHOST),
        port,
        allow_remote: false,
        token: None,
        cache_dir: None,
    };
    let bound = crate::view::server::bind(&opts)
        .await
        .with_context(|| format!("--view: serving {}", dir.display()))?;
    let url = bound.url();
    eprintln!("view: {url}");
    eprintln!("view: the monitor is at /monitor (add the token); it follows the acquisition live");
    tokio::spawn(async move {
        if let Err(e) = bound.serve().await {
            tracing::error!(error = %e, "the viewer stopped");
        }
    });
    Ok(url)
}

/// This build has no browser server (cargo feature `monitor`).
#[cfg(not(feature = "monitor"))]
async fn serve_view(dir: &std::path::Path, _port: u16) -> Result<String> {
    anyhow::bail!(
        "--view: this gonio was built without the live monitor (cargo feature `monitor`, on by default); \
         rebuild with `cargo build --release --features monitor`, or watch {} with `gonio verify` instead",
        dir.display()
    )
}

/// The new session the arguments describe.
fn new_session(args: &AcquireArgs) -> Result<NewSession> {
    let rig = args.rig.load()?;
    let sample = load_sample(&args.sample)?;
    let sweep = args.sweep.load()?;
    Ok(NewSession {
        out: args.out.clone(),
        force: args.force,
        rig,
        hdr: args.hdr,
        sample,
        sweep,
        plan: PlanRequest {
            options: args.sweep.plan_options()?,
            isotropic: args.sweep.isotropic,
            sparse: super::sparse::LoadedSparse::from_args(&args.sparse)?.map(|l| SparsePlan {
                prior: Arc::new(l.prior),
                prior_name: l.name,
                target: l.target,
                design: l.design,
                adaptive: l.adaptive,
                adaptive_tuning: l.adaptive_tuning,
            }),
            fly: args.fly.options()?,
        },
        settings: RunSettings {
            width: args.size.0,
            height: args.size.1,
            noise: !args.no_noise,
            truth: !args.no_truth,
            seed: args.seed,
            raw: args.raw,
            store_truth: args.store_truth,
            reference: args.reference_every.map(|every_min| ReferenceSettings {
                every_min,
                pair: args.reference_pair,
            }),
        },
        calibration: args.calibration.clone(),
        shard: args.shard,
    })
}

/// The measurement bar on stderr (hidden when stderr is not a terminal, or with --json).
fn progress_bar(show: bool) -> indicatif::ProgressBar {
    if !show {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40.cyan/blue}] {pos}/{len} measurements  {per_sec}  ETA {eta}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    bar
}

fn print_summary(s: &Summary) {
    println!("dataset        {}", s.dataset);
    println!("rig / sample   {} / {}", s.rig, s.sample);
    println!("sweep          {} ({} pairs)", s.sweep, s.pairs);
    println!(
        "measurements   {} measured, {} substituted, {} skipped{}",
        s.measured,
        s.substituted,
        s.skipped,
        if s.skipped_reasons.is_empty() {
            String::new()
        } else {
            format!(
                " ({})",
                s.skipped_reasons
                    .iter()
                    .map(|(k, v)| format!("{v} {k}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        }
    );
    println!(
        "this run       {} stored, {} already done, {} remaining{}",
        s.stored_this_run,
        s.already_done,
        s.remaining,
        if s.paused { " (paused)" } else { "" }
    );
    println!(
        "sweep duration {:.0} s = {:.2} h on the rig clock (planned {:.0} s)",
        s.sweep_duration_s,
        s.sweep_duration_s / 3600.0,
        s.planned_duration_s
    );
    println!("wall time      {:.1} s, {:.1} images/s", s.wall_time_s, s.images_per_s);
    if let Some(e) = &s.truth_error {
        println!(
            "vs. truth      RMSE {:.5}, PSNR {:.2} dB, mean abs {:.5}, max abs {:.4} ({} images; linear, DN/max DN)",
            e.rmse, e.psnr_db, e.mean_abs, e.max_abs, e.images
        );
    }
    println!(
        "rectification  {} from markers, {} from pose",
        s.homography_from_markers, s.homography_from_pose
    );
    if let Some(f) = &s.fly {
        println!(
            "fly-scan       {} frames exposed in flight, {} retaken stop and go",
            f.flown, f.retaken_stop_and_go
        );
    }
    if let Some(r) = &s.references {
        println!(
            "references     {} in the dataset ({} this run, every {} min, pair {},{}), {:.1} s of rig time this run; \
             largest drift {:.2} %{}",
            r.count,
            r.this_run,
            r.every_min,
            r.pair[0],
            r.pair[1],
            r.overhead_s,
            r.largest_drift * 100.0,
            if r.drift_warnings > 0 {
                format!(
                    " ({} beyond the threshold: correct with `gonio dataset drift --correct`)",
                    r.drift_warnings
                )
            } else {
                String::new()
            }
        );
    }
    let t = &s.stage_seconds;
    println!(
        "stage seconds  motion {:.1}, capture {:.1}, rectify {:.1}, truth {:.1}, store {:.1}",
        t.motion, t.capture, t.rectify, t.truth, t.store
    );
    if let Some(m) = s.peak_rss_mib {
        println!("peak memory    {m:.0} MiB");
    }
    if !s.complete {
        println!("resume with    gonio acquire --resume {}", s.dataset);
    }
}

/// `--on-pause CMD`: run the notification command and wait for it (a run that ends is
/// not in a hurry); a command that fails or cannot start is reported on stderr only.
fn on_pause(cmd: &str, dataset: &std::path::Path, state: &str, message: &str) {
    let status = std::process::Command::new("sh")
        .arg("-c")
        .arg(cmd)
        .env("GONIO_DATASET", dataset)
        .env("GONIO_STATE", state)
        .env("GONIO_MESSAGE", message)
        .stdin(std::process::Stdio::null())
        .status();
    match status {
        Ok(s) if s.success() => {}
        Ok(s) => eprintln!("--on-pause `{cmd}` ({state}) exited with {s}"),
        Err(e) => eprintln!("--on-pause `{cmd}` ({state}) could not start: {e}"),
    }
}

/// An error and its causes on one line (what `{:#}` prints for an anyhow error).
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        text.push_str(": ");
        text.push_str(&c.to_string());
        cause = c.source();
    }
    text
}
