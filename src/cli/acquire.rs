//! `gonio acquire`: run (or resume) an acquisition and print its summary.

use super::common::{load_sample, RigArgs, SweepArgs};
use crate::engine::metrics::ErrorFigures;
use crate::engine::{self, Rig, RunOptions};
use crate::plan::{Plan, PlanOptions};
use crate::store::{self, Dataset, ManifestHeader};
use crate::sweep::Sweep;
use anyhow::{bail, Context, Result};
use gonio_devices::rig::RigSpec;
use gonio_devices::Direction;
use gonio_simulator::{RenderQuality, SampleSpec, SimOptions};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};
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
    #[arg(long, default_value = "256x256", value_parser = parse_size)]
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
    /// Stop after this many measurements (the run stays resumable).
    #[arg(long)]
    pub limit: Option<usize>,
    /// Apply the calibration results in DIR (`DIR/calibration.json` and
    /// `DIR/*/calibration.json`, one per kind, made on this rig): intrinsics undistort and
    /// rectify, a white standard converts values to BRDF (1/sr). The manifest records their
    /// ids; copies are kept in the dataset for --resume.
    #[arg(long, value_name = "DIR", conflicts_with = "resume")]
    pub calibration: Option<PathBuf>,
}

fn parse_size(s: &str) -> std::result::Result<(usize, usize), String> {
    let (a, b) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("`{s}`: expected WxH, e.g. 256x256"))?;
    let w: usize = a.parse().map_err(|_| format!("`{s}`: width is not a number"))?;
    let h: usize = b.parse().map_err(|_| format!("`{s}`: height is not a number"))?;
    if !(8..=8192).contains(&w) || !(8..=8192).contains(&h) {
        return Err(format!("`{s}`: each side must be 8 ..= 8192"));
    }
    Ok((w, h))
}

/// Settings recorded in the manifest so `--resume` rebuilds the same rig.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct RunSettings {
    width: usize,
    height: usize,
    noise: bool,
    truth: bool,
    seed: Option<u64>,
    raw: bool,
    #[serde(default)]
    store_truth: bool,
}

/// The summary printed at the end (and with --json).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Summary {
    pub dataset: String,
    pub rig: String,
    pub sample: String,
    pub sweep: String,
    pub pairs: usize,
    pub planned_measurements: usize,
    pub measured: usize,
    pub substituted: usize,
    pub skipped: usize,
    pub skipped_reasons: BTreeMap<String, usize>,
    pub stored_this_run: usize,
    pub already_done: usize,
    pub remaining: usize,
    pub complete: bool,
    pub paused: bool,
    pub planned_duration_s: f64,
    pub sweep_duration_s: f64,
    pub wall_time_s: f64,
    pub images_per_s: f64,
    pub truth_error: Option<ErrorFigures>,
    pub homography_from_markers: usize,
    pub homography_from_pose: usize,
    pub stage_seconds: engine::StageSeconds,
    /// Peak resident memory of this process (MiB, from /proc/self/status VmHWM).
    pub peak_rss_mib: Option<f64>,
    /// Unit of the stored values: `normalized_dn` or (white-standard calibration applied)
    /// `brdf_per_sr`; the truth error is on the same scale.
    #[serde(default)]
    pub value_unit: String,
    /// Ids of the calibration results applied (comma-separated).
    #[serde(default)]
    pub calibration: Option<String>,
    /// Raw-frame corrections applied to every frame, in order (`response`, `dark`, `flat`,
    /// `colour`); empty without. Saturated pixels are counted per measurement
    /// (`extra.saturated_pixels` of its record).
    #[serde(default)]
    pub corrections: Vec<String>,
}

/// Peak resident set size of this process in MiB (Linux), for the memory benchmark.
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
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
    let (rig_spec, sample, plan, settings, mut dataset, done) = match &args.resume {
        Some(dir) => open_resume(dir)?,
        None => create_new(&args)?,
    };
    let sim = SimOptions {
        realtime: args.realtime,
        noise: Some(settings.noise),
        seed: settings.seed,
        quality: RenderQuality::default(),
    };
    let rig = Arc::new(Rig::build(&rig_spec, &sample, &sim).context("building the rig")?);
    let calibration = dataset_calibration(dataset.header(), dataset.dir(), &rig_spec)?;
    // Skipped pairs are recorded once, so the dataset says what it did not measure and why.
    for s in &plan.skipped {
        if !done.contains(&s.index) {
            let rec = engine::skipped_record(s.index, s.light_deg, s.view_deg, s.reason.to_string());
            dataset
                .store(rec, None, None)
                .with_context(|| format!("recording skipped pair {}", s.index))?;
        }
    }
    let pause = Arc::new(AtomicBool::new(false));
    {
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
        });
    }
    let mut plan_run = plan.clone();
    if let Some(limit) = args.limit {
        let mut left = limit;
        plan_run.steps.retain(|s| {
            if done.contains(&s.index) {
                return true;
            }
            if left == 0 {
                return false;
            }
            left -= 1;
            true
        });
    }
    let plan_run = Arc::new(plan_run);
    let opts = RunOptions {
        width: settings.width,
        height: settings.height,
        raw_frames: settings.raw,
        truth: settings.truth,
        store_truth: settings.store_truth,
        show_progress: !args.json && !args.quiet_progress(),
        max_supersample: 8,
    };
    let dir = dataset.dir().to_path_buf();
    let result = engine::run_calibrated(
        rig.clone(),
        plan_run.clone(),
        dataset,
        done.clone(),
        opts,
        pause,
        calibration.clone(),
    )
    .await;
    let (mut dataset, report) = match result {
        Ok(v) => v,
        Err((_, e)) => {
            let hint = format!(
                "the journal is consistent; fix the cause and run `gonio acquire --resume {}`",
                dir.display()
            );
            return Err(anyhow::Error::new(e).context(hint));
        }
    };
    let counts = plan.counts();
    let remaining_total = plan.steps.iter().filter(|s| !done.contains(&s.index)).count() - report.stored_this_run;
    let complete = remaining_total == 0;
    let summary = Summary {
        dataset: dir.display().to_string(),
        rig: rig_spec.name.clone(),
        sample: sample.name.clone(),
        sweep: plan.sweep.clone(),
        pairs: plan.pairs,
        planned_measurements: plan.steps.len(),
        measured: counts.feasible,
        substituted: counts.substituted,
        skipped: counts.skipped,
        skipped_reasons: counts.skipped_reasons.clone(),
        stored_this_run: report.stored_this_run,
        already_done: report.already_done,
        remaining: remaining_total,
        complete,
        paused: report.paused,
        planned_duration_s: plan.durations.optimized_s,
        sweep_duration_s: report.rig_time_s,
        wall_time_s: report.wall_time_s,
        images_per_s: report.stored_this_run as f64 / report.wall_time_s.max(1e-9),
        truth_error: report.truth_error.figures(),
        homography_from_markers: report.homography_from_markers,
        homography_from_pose: report.homography_from_pose,
        stage_seconds: report.stage_seconds.clone(),
        peak_rss_mib: peak_rss_mib(),
        value_unit: calibration
            .as_ref()
            .map_or(APPLY_UNIT_DN, |c| c.value_unit())
            .to_string(),
        calibration: calibration.as_ref().map(|c| c.ids.join(",")),
        corrections: calibration.as_ref().map(|c| c.corrections()).unwrap_or_default(),
    };
    if complete {
        dataset
            .finish(&serde_json::to_value(&summary)?)
            .context("writing the final manifest")?;
    }
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        print_summary(&summary);
    }
    Ok(if complete { ExitCode::SUCCESS } else { ExitCode::from(3) })
}

impl AcquireArgs {
    fn quiet_progress(&self) -> bool {
        !std::io::IsTerminal::is_terminal(&std::io::stderr())
    }
}

type Opened = (RigSpec, SampleSpec, Plan, RunSettings, Dataset, HashSet<usize>);

fn create_new(args: &AcquireArgs) -> Result<Opened> {
    let mut rig = args.rig.load()?;
    // A rig-geometry calibration corrects the kinematics before anything is planned.
    if let Some(dir) = &args.calibration {
        let results = crate::calibrate::apply::load_dir(dir, &rig.name)?;
        let (applied, _) = crate::calibrate::apply::AppliedCalibration::from_results(&results)?;
        applied.correct_rig(&mut rig);
    }
    let sample = load_sample(&args.sample)?;
    let sweep = args.sweep.load()?;
    // A sample file that declares `isotropic = true` gets the reduced plan without
    // `--isotropic`; the plan records it (and the time saved) like the flag does.
    let sweep_args = SweepArgs {
        isotropic: args.sweep.isotropic || sample.isotropic,
        ..args.sweep.clone()
    };
    let plan = sweep_args.plan(&rig, &sweep).context("planning the sweep")?;
    let settings = RunSettings {
        width: args.size.0,
        height: args.size.1,
        noise: !args.no_noise,
        truth: !args.no_truth,
        seed: args.seed,
        raw: args.raw,
        store_truth: args.store_truth,
    };
    let mut header = ManifestHeader::new(
        serde_json::to_value(&rig)?,
        serde_json::to_value(&sample)?,
        sweep.manifest_json(plan.policy),
        settings.width,
        settings.height,
        "linear normalised sensor signal (DN / max DN), radiometrically uncalibrated",
    );
    header.seed = settings.seed.unwrap_or(1);
    header.raw_frames = settings.raw;
    header.extra = serde_json::json!({ "run_settings": settings });
    let calibration = match &args.calibration {
        Some(dir) => Some(prepare_calibration(dir, &rig, &mut header)?),
        None => None,
    };
    let dataset = Dataset::create(&args.out, &header, args.force).with_context(|| {
        format!(
            "creating dataset {} (use --force to replace a dataset, --resume to continue one)",
            args.out.display()
        )
    })?;
    if let Some(results) = &calibration {
        store_calibration_copies(&args.out, results)?;
    }
    write_plan(&args.out, &plan)?;
    Ok((rig, sample, plan, settings, dataset, HashSet::new()))
}

const APPLY_UNIT_DN: &str = crate::calibrate::apply::VALUE_UNIT_DN;

/// Where a dataset keeps the copy of a calibration result it applies.
fn calibration_copy(kind: &str) -> String {
    format!("calibration/{kind}.json")
}

/// Load the results in `dir` for rig `rig_name` and describe them in the header:
/// `calibration` = the applied ids (comma-separated), `values` and `extra.value_unit` = the
/// unit of the stored values, `extra.calibrations` = every result found (kind, id, source
/// file, copy in the dataset, applied or not).
fn prepare_calibration(
    dir: &Path,
    rig: &RigSpec,
    header: &mut ManifestHeader,
) -> Result<Vec<crate::calibrate::apply::LoadedResult>> {
    use crate::calibrate::apply::{load_dir, AppliedCalibration};
    let results = load_dir(dir, &rig.name)?;
    let (applied, not_applied) = AppliedCalibration::from_results(&results)?;
    check_raw_correction(&applied, rig)?;
    for kind in &not_applied {
        tracing::warn!(kind = %kind, "calibration kind is not applied by acquire yet: recorded as not applied");
    }
    if !applied.ids.is_empty() {
        header.calibration = Some(applied.ids.join(","));
    }
    if applied.radiometric.is_some() {
        header.values = "BRDF (1/sr) per texel, radiometrically calibrated with a white standard \
                         (value / (K · exposure · gain · E(x)), E from the lamp position per texel)"
            .into();
    }
    if let Some(raw) = &applied.raw {
        let kinds = raw.kinds().join(", ");
        header.values = if applied.radiometric.is_some() {
            format!("{} Raw frames corrected first: {kinds}.", header.values)
        } else {
            format!(
                "linear values (½ exp g of the response curve's scale), raw frames corrected: {kinds}; \
                 no white standard, so not BRDF"
            )
        };
        header.extra["corrections"] = serde_json::json!(raw.sources);
    }
    header.extra["value_unit"] = serde_json::json!(applied.value_unit());
    header.extra["calibrations"] = serde_json::Value::Array(
        results
            .iter()
            .map(|r| {
                serde_json::json!({
                    "kind": r.kind,
                    "id": r.id,
                    "source": r.file.display().to_string(),
                    "file": calibration_copy(&r.kind),
                    "applied": !not_applied.contains(&r.kind),
                })
            })
            .collect(),
    );
    Ok(results)
}

/// Refuse raw-frame corrections made on another camera (size, bit depth) before anything is
/// created; warn when the dark frames were taken at another exposure (dark current scales
/// with it).
fn check_raw_correction(applied: &crate::calibrate::apply::AppliedCalibration, rig: &RigSpec) -> Result<()> {
    let Some(raw) = &applied.raw else { return Ok(()) };
    let c = &rig.camera;
    raw.check_camera(c.width, c.height, c.bit_depth)?;
    if let Some(t) = raw.dark_exposure_s {
        if (t - c.exposure_s).abs() > 1e-3 * c.exposure_s.abs().max(1e-9) {
            tracing::warn!(
                dark_exposure_s = t,
                exposure_s = c.exposure_s,
                "the dark frame was taken at another exposure than the camera's: its dark current differs"
            );
        }
    }
    Ok(())
}

/// Copy the result files into the dataset (`calibration/KIND.json`).
fn store_calibration_copies(out: &Path, results: &[crate::calibrate::apply::LoadedResult]) -> Result<()> {
    let dir = out.join("calibration");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    for r in results {
        let path = out.join(calibration_copy(&r.kind));
        store::atomic::write_atomic(&path, &r.bytes, Some(out))
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// The calibration a dataset applies, from its own copies (new run and `--resume` alike);
/// `None` for an uncalibrated dataset.
fn dataset_calibration(
    header: &ManifestHeader,
    dir: &Path,
    rig: &RigSpec,
) -> Result<Option<Arc<crate::calibrate::apply::AppliedCalibration>>> {
    let rig_name = &rig.name;
    use crate::calibrate::apply::{load_files, AppliedCalibration};
    let Some(list) = header.extra.get("calibrations").and_then(|v| v.as_array()) else {
        return Ok(None);
    };
    let files: Vec<PathBuf> = list
        .iter()
        .filter_map(|e| e.get("file").and_then(|f| f.as_str()))
        .map(|f| dir.join(f))
        .collect();
    let results =
        load_files(&files, rig_name).with_context(|| format!("loading the calibration of {}", dir.display()))?;
    let (applied, _) = AppliedCalibration::from_results(&results)?;
    check_raw_correction(&applied, rig)?;
    let expected = header.calibration.clone().unwrap_or_default();
    if applied.ids.join(",") != expected {
        bail!(
            "dataset {}: its calibration copies have ids {:?}, the manifest says {:?}",
            dir.display(),
            applied.ids.join(","),
            expected
        );
    }
    Ok(Some(Arc::new(applied)))
}

fn plan_path(dir: &Path) -> PathBuf {
    dir.join("plan.json")
}

/// The executed plan is stored with the dataset, so a resume follows the same order.
fn write_plan(dir: &Path, plan: &Plan) -> Result<()> {
    let bytes = serde_json::to_vec(plan)?;
    store::atomic::write_atomic(&plan_path(dir), &bytes, Some(dir)).context("writing plan.json")?;
    Ok(())
}

fn open_resume(dir: &Path) -> Result<Opened> {
    let (dataset, header, records) =
        Dataset::resume(dir).with_context(|| format!("resuming dataset {}", dir.display()))?;
    let rig: RigSpec =
        serde_json::from_value(header.rig.clone()).context("reading the rig snapshot from the manifest")?;
    let sample: SampleSpec =
        serde_json::from_value(header.sample.clone()).context("reading the sample snapshot from the manifest")?;
    let plan_file = plan_path(dir);
    let plan: Plan = if !plan_file.exists() && records.is_empty() {
        // Interrupted between creating the dataset and writing its plan: nothing was
        // measured yet, so plan again from the manifest's snapshots.
        tracing::warn!(dir = %dir.display(), "plan.json missing in an empty dataset: planning again");
        let sweep = sweep_from_header(&header.sweep).context("reading the sweep snapshot from the manifest")?;
        let policy = serde_json::from_value(header.sweep["policy"].clone()).unwrap_or_default();
        let plan = Plan::build(
            &rig,
            &sweep,
            &PlanOptions {
                policy,
                kicks: 0,
                time_cap: None,
                seed: 1,
            },
        )?;
        write_plan(dir, &plan)?;
        plan
    } else {
        serde_json::from_slice(&std::fs::read(&plan_file).with_context(|| format!("reading {}", plan_file.display()))?)
            .with_context(|| format!("parsing {}", plan_file.display()))?
    };
    let settings: RunSettings = serde_json::from_value(header.extra["run_settings"].clone())
        .context("reading run settings from the manifest")?;
    let done: HashSet<usize> = records.iter().map(|r| r.index).collect();
    if done.len() > plan.pairs {
        bail!(
            "dataset {} holds {} records but its plan has {} pairs",
            dir.display(),
            done.len(),
            plan.pairs
        );
    }
    Ok((rig, sample, plan, settings, dataset, done))
}

/// The sweep recorded in a manifest header (`lights_deg`, `views_deg`, degrees).
fn sweep_from_header(v: &serde_json::Value) -> Result<Sweep> {
    let list = |key: &str| -> Result<Vec<Direction>> {
        let raw: Vec<[f64; 2]> = serde_json::from_value(v[key].clone()).with_context(|| format!("sweep.{key}"))?;
        Ok(raw.iter().map(|[t, p]| Direction::from_degrees(*t, *p)).collect())
    };
    Ok(Sweep {
        name: v["name"].as_str().unwrap_or("sweep").to_string(),
        lights: list("lights_deg")?,
        views: list("views_deg")?,
    })
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
