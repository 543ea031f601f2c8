//! The acquisition engine: executes a [`Plan`] through the hardware traits.
//!
//! Two stages run at once so the rig never waits for the disk:
//! 1. the *drive* loop (async): for each step, start every axis, wait until all are
//!    settled, read back positions, capture a frame; it checks the pause flag at every
//!    measurement boundary (Ctrl-C) and stops if the store stage failed;
//! 2. the *store* thread: converts the frame to linear values, rectifies it, compares it
//!    with the ground truth when the rig has one, and stores image and journal record.
//!
//! A bounded channel between them keeps memory flat however long the sweep (stream, don't
//! hoard). A measurement is stored only once its image is in place and its journal line
//! is synced (see `store`), so a crash at any moment loses at most the frames in flight
//! (captured, or developed but not yet journaled), which `--resume` measures again. The
//! store thread writes measurement k (EXR encoding, fsyncs, journal line: `commit`) on a
//! scoped thread while it develops measurement k + 1.

mod fly;
pub mod lamp;
pub mod metrics;
pub mod reference;

use crate::develop::rectify::HomographySource;
use crate::develop::{DevelopError, Developer};
use crate::plan::{Plan, Step, StepStatus};
use crate::rig::{BracketNotes, CaptureNotes, CapturePolicy, Rig};
use gonio_dataset::store::{Dataset, LampRecord, MeasurementRecord, MeasurementStatus, ReferenceRecord, StoreError};
use gonio_devices::hdr::{HdrMode, HdrSpec};
use gonio_devices::image::RgbImage;
use gonio_devices::{CameraConfig, DeviceError, Direction, Frame};
use metrics::ErrorAccumulator;
use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum EngineError {
    #[error("device error at measurement {index}")]
    Device { index: usize, source: DeviceError },
    /// The camera failed every attempt the capture policy allows (see `rig::capture`).
    #[error("camera failed at measurement {index} after {attempts} attempt(s)")]
    Capture {
        index: usize,
        attempts: u32,
        source: DeviceError,
    },
    #[error("device error while preparing the rig: {0}")]
    Setup(DeviceError),
    #[error("storing measurement {index} failed")]
    Store { index: usize, source: StoreError },
    #[error("rectifying measurement {index} failed: {message}")]
    Rectify { index: usize, message: String },
    #[error("the store thread stopped unexpectedly")]
    StoreThread,
    #[error("applying the calibration to measurement {index} failed: {source}")]
    Calibration { index: usize, source: DevelopError },
}

#[derive(Clone, Debug)]
pub struct RunOptions {
    /// Develops every frame into the stored values (see `crate::develop`).
    pub developer: Arc<Developer>,
    pub raw_frames: bool,
    /// Compare with the simulator's ground truth (if the rig has one).
    pub truth: bool,
    /// Also store the ground truth as `truth/NNNNN.exr` (the exact rectified BTF).
    pub store_truth: bool,
    /// Re-measure a reference pair and a dark frame during the run ([`reference`]).
    pub references: Option<reference::ReferencePlan>,
    /// When this process last took a reference (carried across adaptive rounds).
    pub reference_schedule: reference::Schedule,
}

/// What the engine reports while it runs, to whoever watches (a progress bar, a web
/// monitor, a test). Sent from the drive loop (`Started`, `Captured`) and from the store
/// thread (`Stored`), so observers must be `Send + Sync`; they must not block.
#[derive(Debug)]
pub enum RunEvent<'a> {
    /// The run begins: `to_do` measurements this run, `already_done` from earlier runs.
    Started { to_do: usize, already_done: usize },
    /// A frame of measurement `index` was captured and is on its way to storage.
    Captured { index: usize },
    /// A measurement is stored (its image in place, its journal line synced).
    Stored { record: &'a MeasurementRecord },
    /// A drift reference is stored (its images in place, its line synced).
    Reference { record: &'a ReferenceRecord },
}

/// Receives [`RunEvent`]s.
pub type Observer = Arc<dyn Fn(&RunEvent<'_>) + Send + Sync>;

/// What one run of the engine did.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunReport {
    pub stored_this_run: usize,
    pub already_done: usize,
    pub remaining: usize,
    pub paused: bool,
    pub complete: bool,
    /// Rig-clock seconds this run spent (virtual on a simulated rig).
    pub rig_time_s: f64,
    pub wall_time_s: f64,
    pub truth_error: ErrorAccumulator,
    pub homography_from_markers: usize,
    pub homography_from_pose: usize,
    /// Wall seconds spent per stage (stages overlap: drive and store run concurrently).
    pub stage_seconds: StageSeconds,
    /// Measurements whose lamp current or voltage drifted beyond the rig's threshold
    /// (lights whose supply measures; see [`lamp`]).
    #[serde(default)]
    pub lamp_drift_warnings: usize,
    /// The lamp supply's identity (`*IDN?`), for lights whose supply measures.
    #[serde(default)]
    pub lamp_identity: Option<String>,
    /// Drift references this run took (`--reference-every`).
    #[serde(default)]
    pub references: ReferenceStats,
}

/// What the drift references of one run did.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct ReferenceStats {
    /// References stored this run.
    pub taken: usize,
    /// Rig seconds they took (moves, exposures, the light's settle times).
    pub overhead_s: f64,
    /// References whose drift (any channel, against the dataset's first) exceeded the
    /// threshold.
    pub warnings: usize,
    /// Rig time of the last reference of this process (the schedule's state).
    pub last_at: Option<f64>,
}

/// Where the wall time goes, summed over all measurements of a run.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct StageSeconds {
    /// Drive loop: commanding axes and waiting for them (near zero on a virtual clock).
    pub motion: f64,
    /// Drive loop: camera capture (rendering, on the simulated rig).
    pub capture: f64,
    /// Store thread: DN → linear conversion and rectification.
    pub rectify: f64,
    /// Store thread: rendering the ground truth (simulated rigs only).
    pub truth: f64,
    /// Store thread: encoding and durably writing image and journal line.
    pub store: f64,
}

/// What the drive loop hands the store thread, in order.
enum Work {
    Measure(Box<Job>),
    Reference(Box<reference::ReferenceJob>),
}

/// A captured frame on its way to the store thread.
struct Job {
    order: usize,
    step: Step,
    frame: Frame,
    q_cmd: Vec<f64>,
    q_read: Vec<f64>,
    rig_time: f64,
    wall_time: f64,
    /// Retries, discarded frames, saturation: written into the record.
    notes: CaptureNotes,
    /// With HDR on: the bracket's further exposures (`frame` is its base).
    bracket: Option<Bracket>,
    /// The lamp's reading after the capture (lights whose supply measures).
    lamp: Option<LampRecord>,
    /// A flown frame's measured poses (`extra.flight`, see [`fly`]).
    flight: Option<serde_json::Value>,
    /// The camera's sensor temperature after the capture, where it reports one
    /// (`extra.camera_temperature_c`).
    camera_temperature_c: Option<f64>,
}

/// The exposures of an HDR bracket beyond its base frame, and what bracketing noted.
struct Bracket {
    more: Vec<Frame>,
    notes: BracketNotes,
    /// The nominal (base) exposure: the merged values' scale.
    base_exposure_s: f64,
}

fn unix_now() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

fn deg2(d: Direction) -> [f64; 2] {
    [d.theta_deg(), d.phi_deg()]
}

/// Record of a skipped pair (no image).
pub fn skipped_record(index: usize, light_deg: [f64; 2], view_deg: [f64; 2], reason: String) -> MeasurementRecord {
    let mut r = MeasurementRecord::new(index, usize::MAX, light_deg, view_deg);
    r.status = MeasurementStatus::Skipped { reason };
    r.wall_time_unix = unix_now();
    r
}

/// Execute the plan's steps that are not in `done`, developing every frame with
/// `opts.developer` (see `crate::develop`). Returns the dataset (for `finish`) and a report; on a
/// failure the error says which measurement, and the dataset is handed back when it is
/// still consistent.
pub async fn run(
    rig: Arc<Rig>,
    plan: Arc<Plan>,
    dataset: Dataset,
    done: HashSet<usize>,
    opts: RunOptions,
    pause: Arc<AtomicBool>,
    observer: Observer,
) -> Result<(Dataset, RunReport), (Option<Dataset>, EngineError)> {
    let t_wall = Instant::now();
    let rig_t0 = rig.time();
    let todo: Vec<(usize, &Step)> = plan
        .steps
        .iter()
        .enumerate()
        .filter(|(_, s)| !done.contains(&s.index))
        .collect();
    let already_done = plan.steps.len() - todo.len();
    observer(&RunEvent::Started {
        to_do: todo.len(),
        already_done,
    });
    let (tx, rx) = tokio::sync::mpsc::channel::<Work>(2);
    // Drift references: the dataset-wide number of the next one, and the schedule.
    let mut next_reference = dataset.references().last().map_or(0, |r| r.number + 1);
    let mut schedule = opts.reference_schedule;
    let mut reference_overhead = 0.0;
    let mut measured_since_reference = false;
    let failed = Arc::new(AtomicBool::new(false));
    let store = {
        let rig = rig.clone();
        let opts = opts.clone();
        let failed = failed.clone();
        let observer = observer.clone();
        std::thread::Builder::new()
            .name("gonio-store".into())
            .spawn(move || store_loop(rig, dataset, rx, opts, failed, observer))
            .map_err(|_| (None, EngineError::StoreThread))?
    };
    let mut drive_err = None;
    let mut paused = false;
    let mut drive_times = StageSeconds::default();
    // The capture policy (retries, timeout, saturation) and the camera's actual settings.
    let setup = match rig.capture_policy() {
        Ok(policy) => rig.prepare().await.map(|config| (policy, config)),
        Err(e) => Err(e),
    }
    .map_err(EngineError::Setup);
    let setup = setup.map_err(|e| drive_err = Some(e)).ok();
    // The lamp monitor: its reference is the reading once the lamp is on and settled.
    let mut lamp = lamp::LampWatch::new(rig.lamp_monitor);
    let mut lamp_identity = None;
    if setup.is_some() {
        match lamp_reference(&rig, &mut lamp).await {
            Ok(identity) => lamp_identity = identity,
            Err(e) => drive_err = Some(EngineError::Setup(e)),
        }
    }
    // HDR bracketing (rig file `[hdr]` / `--hdr`); off: exactly the single-exposure path.
    let hdr = rig.spec.hdr.clone().filter(|h| h.mode() != HdrMode::Off);
    // Rig-clock end of the last exposure: a flight's first exposure waits for its readout.
    let mut last_end: Option<f64> = None;
    let mut k = 0;
    while k < todo.len() {
        if drive_err.is_some() || failed.load(Ordering::SeqCst) {
            break;
        }
        if pause.load(Ordering::SeqCst) {
            paused = true;
            break;
        }
        let Some((policy, camera_config)) = &setup else {
            break;
        };
        if let Some(rp) = opts
            .references
            .as_ref()
            .filter(|rp| schedule.due(rig.time(), rp.every_s))
        {
            match take_reference(&rig, rp, next_reference, policy, camera_config, &lamp, &tx).await {
                Ok(Some(spent)) => {
                    next_reference += 1;
                    reference_overhead += spent;
                    schedule.last_at = Some(rig.time());
                    last_end = Some(rig.time());
                }
                Ok(None) => break, // store thread ended (failed): its error is reported below
                Err(e) => {
                    drive_err = Some(e);
                    break;
                }
            }
        }
        measured_since_reference = true;
        let (order, step) = todo[k];
        // A flown segment is one step of the drive loop: its poses still to measure, flown
        // together; a pause waits for the segment's end.
        let flown: Vec<fly::Flown> = if let Some(f) = &step.flight {
            let same = |s: &Step| s.flight.as_ref().is_some_and(|g| g.segment == f.segment);
            let wanted: HashSet<usize> = todo[k..]
                .iter()
                .take_while(|(_, s)| same(s))
                .map(|(_, s)| s.index)
                .collect();
            k += wanted.len();
            let lo = (0..=order)
                .rev()
                .take_while(|&i| same(&plan.steps[i]))
                .last()
                .unwrap_or(order);
            let seg: Vec<(usize, &Step)> = (lo..plan.steps.len())
                .take_while(|&i| same(&plan.steps[i]))
                .map(|i| (i, &plan.steps[i]))
                .collect();
            match fly::drive_segment(
                &rig,
                &seg,
                &wanted,
                &mut drive_times,
                policy,
                camera_config,
                &mut last_end,
            )
            .await
            {
                Ok(v) => v,
                Err(e) => {
                    drive_err = Some(e);
                    break;
                }
            }
        } else {
            k += 1;
            match drive_step(&rig, step, &mut drive_times, policy, camera_config, hdr.as_ref()).await {
                Ok(driven) => {
                    last_end = Some(rig.time());
                    vec![fly::Flown {
                        order,
                        step: step.clone(),
                        driven,
                        flight: serde_json::Value::Null,
                        rig_time: rig.time(),
                    }]
                }
                Err(e) => {
                    drive_err = Some(e);
                    break;
                }
            }
        };
        for f in flown {
            let lamp_record = match read_lamp(&rig, f.step.index, &mut lamp).await {
                Ok(l) => l,
                Err(e) => {
                    drive_err = Some(e);
                    break;
                }
            };
            let camera_temperature_c = camera_temperature(&rig).await;
            let (frame, notes, bracket, q_cmd, q_read) = f.driven;
            let job = Job {
                order: f.order,
                step: f.step,
                frame,
                q_cmd,
                q_read,
                rig_time: f.rig_time,
                wall_time: unix_now(),
                notes,
                bracket,
                lamp: lamp_record,
                flight: (!f.flight.is_null()).then_some(f.flight),
                camera_temperature_c,
            };
            let index = job.step.index;
            if tx.send(Work::Measure(Box::new(job))).await.is_err() {
                break; // store thread ended (failed): its error is reported below
            }
            observer(&RunEvent::Captured { index });
        }
    }
    // A closing reference, so the run's last measurements lie between two references; a
    // pause stops without one (the resumed run starts with its own).
    if let (Some(rp), Some((policy, camera_config)), None, false) =
        (&opts.references, &setup, &drive_err, failed.load(Ordering::SeqCst))
    {
        if reference::closing_due(measured_since_reference, paused) {
            match take_reference(&rig, rp, next_reference, policy, camera_config, &lamp, &tx).await {
                Ok(Some(spent)) => {
                    reference_overhead += spent;
                    schedule.last_at = Some(rig.time());
                }
                Ok(None) => {}
                Err(e) => drive_err = Some(e),
            }
        }
    }
    if setup.is_some() {
        rig.camera.readout_done().await;
    }
    drop(tx);
    let stored = store.join();
    let (dataset, stats) = match stored {
        Ok(Ok(v)) => v,
        Ok(Err(b)) => {
            let (ds, e) = *b;
            return Err((Some(ds), e));
        }
        Err(_) => return Err((None, EngineError::StoreThread)),
    };
    if let Some(e) = drive_err {
        return Err((Some(dataset), e));
    }
    let remaining = todo.len() - stats.stored;
    Ok((
        dataset,
        RunReport {
            stored_this_run: stats.stored,
            already_done,
            remaining,
            paused,
            complete: remaining == 0,
            rig_time_s: rig.time() - rig_t0,
            wall_time_s: t_wall.elapsed().as_secs_f64(),
            truth_error: stats.error,
            homography_from_markers: stats.markers,
            homography_from_pose: stats.pose,
            stage_seconds: StageSeconds {
                motion: drive_times.motion,
                capture: drive_times.capture,
                ..stats.times
            },
            lamp_drift_warnings: lamp.warnings(),
            lamp_identity,
            references: ReferenceStats {
                taken: stats.references,
                overhead_s: reference_overhead,
                warnings: stats.reference_warnings,
                last_at: schedule.last_at,
            },
        },
    ))
}

/// Drive one drift reference and hand it to the store thread. `Ok(None)`: the store
/// thread has ended (its error is reported by the caller); else the rig seconds it took.
async fn take_reference(
    rig: &Rig,
    rp: &reference::ReferencePlan,
    number: usize,
    policy: &CapturePolicy,
    camera_config: &CameraConfig,
    lamp: &lamp::LampWatch,
    tx: &tokio::sync::mpsc::Sender<Work>,
) -> Result<Option<f64>, EngineError> {
    let (mut job, spent) = reference::drive(rig, rp, number, policy, camera_config).await?;
    job.output_correction = match (rig.lamp_monitor.output_exponent, lamp.reference(), job.reading) {
        (Some(k), Some(r0), Some(r)) if r0.current_a > 0.0 && r.current_a > 0.0 => {
            Some((r.current_a / r0.current_a).powf(k))
        }
        _ => None,
    };
    tracing::info!(
        reference = number,
        rig_time_s = job.rig_time,
        seconds = spent,
        "drift reference: pair {} and a dark frame",
        rp.step.index
    );
    if tx.send(Work::Reference(Box::new(job))).await.is_err() {
        return Ok(None);
    }
    Ok(Some(spent))
}

/// After the rig is prepared (lamp on, settled): the lamp's reference reading and its
/// supply's identity, for a light that measures (`None` otherwise: nothing is recorded).
async fn lamp_reference(rig: &Rig, watch: &mut lamp::LampWatch) -> Result<Option<String>, DeviceError> {
    let Some(r) = rig.light.read_back().await? else {
        return Ok(None);
    };
    let identity = rig.light.identity().await?;
    tracing::info!(
        "lamp {identity}: reference {:.3} V, {:.4} A (drift warns beyond {:.1} %{})",
        r.voltage_v,
        r.current_a,
        rig.lamp_monitor.drift_threshold * 100.0,
        rig.lamp_monitor
            .output_exponent
            .map_or(String::new(), |k| format!("; output corrected as (I/I0)^{k}"))
    );
    watch.set_reference(r);
    Ok(Some(identity))
}

/// The lamp's reading for measurement `index`, taken right after its capture.
/// The camera's temperature for the record. A camera that fails to say does not stop a
/// run (the frame is fine): the failure is logged and the record has no temperature.
async fn camera_temperature(rig: &Rig) -> Option<f64> {
    match rig.camera.temperature_c().await {
        Ok(t) => t.filter(|t| t.is_finite()),
        Err(e) => {
            tracing::warn!("camera temperature: {e}");
            None
        }
    }
}

async fn read_lamp(rig: &Rig, index: usize, watch: &mut lamp::LampWatch) -> Result<Option<LampRecord>, EngineError> {
    match rig.light.read_back().await {
        Ok(Some(r)) => Ok(Some(watch.observe(index, r))),
        Ok(None) => Ok(None),
        Err(source) => Err(EngineError::Device { index, source }),
    }
}

/// What the drive loop hands on per step: frame, capture notes, the HDR bracket's other
/// exposures, commanded and read-back axes.
type Driven = (Frame, CaptureNotes, Option<Bracket>, Vec<f64>, Vec<f64>);

/// One step: the rig's shared move-and-capture ([`Rig::reach`], then [`Rig::capture`] under
/// the capture policy), with the wall time of each part.
async fn drive_step(
    rig: &Rig,
    step: &Step,
    times: &mut StageSeconds,
    policy: &CapturePolicy,
    camera_config: &CameraConfig,
    hdr: Option<&HdrSpec>,
) -> Result<Driven, EngineError> {
    let index = step.index;
    let t0 = Instant::now();
    let q: Vec<f64> = step.axes_deg.iter().map(|d| d.to_radians()).collect();
    let read = rig
        .reach(&q)
        .await
        .map_err(|source| EngineError::Device { index, source })?;
    let t1 = Instant::now();
    // The measurement's identity (its canonical pair index): a simulated camera keys its
    // noise on it, so the same measurement gives the same bytes in any order or run.
    rig.camera.begin_measurement(index as u64);
    let failed = |f: crate::rig::CaptureFailed| EngineError::Capture {
        index,
        attempts: f.attempts,
        source: f.source,
    };
    let (frame, notes, bracket) = match hdr {
        None => {
            let (frame, notes) = rig.capture(policy, camera_config).await.map_err(failed)?;
            (frame, notes, None)
        }
        Some(hdr) => {
            let (mut frames, notes, bn) = rig
                .capture_bracket(policy, camera_config, hdr, &read)
                .await
                .map_err(failed)?;
            let base = frames.remove(0);
            let bracket = Bracket {
                more: frames,
                notes: bn,
                base_exposure_s: camera_config.exposure,
            };
            (base, notes, Some(bracket))
        }
    };
    times.motion += (t1 - t0).as_secs_f64();
    times.capture += t1.elapsed().as_secs_f64();
    Ok((frame, notes, bracket, q, read))
}

struct StoreStats {
    times: StageSeconds,
    stored: usize,
    error: ErrorAccumulator,
    markers: usize,
    pose: usize,
    references: usize,
    reference_warnings: usize,
}

type StoreResult = Result<(Dataset, StoreStats), Box<(Dataset, EngineError)>>;

fn store_loop(
    rig: Arc<Rig>,
    mut dataset: Dataset,
    mut rx: tokio::sync::mpsc::Receiver<Work>,
    opts: RunOptions,
    failed: Arc<AtomicBool>,
    observer: Observer,
) -> StoreResult {
    let developer = opts.developer.clone();
    let mut stats = StoreStats {
        times: StageSeconds::default(),
        stored: 0,
        error: ErrorAccumulator::default(),
        markers: 0,
        pose: 0,
        references: 0,
        reference_warnings: 0,
    };
    let (width, height) = (developer.params().width, developer.params().height);
    let noise = rig
        .spec
        .hdr
        .as_ref()
        .map(|h| h.noise(&rig.spec.camera, rig.spec.camera.gain));
    let fail = |dataset: Dataset, err: EngineError| {
        failed.store(true, Ordering::SeqCst);
        Err(Box::new((dataset, err)))
    };
    // The previous measurement, developed, whose files and journal line are written while
    // this one develops (see `commit`).
    let mut pending: Option<Pending> = None;
    while let Some(work) = rx.blocking_recv() {
        let job = match work {
            Work::Measure(job) => *job,
            Work::Reference(r) => {
                // The measurement before it is committed first: the reference's place in
                // the journal (`stored_before`) is then exact.
                if let Some(p) = pending.take() {
                    match commit(&mut dataset, p, &observer) {
                        Ok(t) => {
                            stats.times.store += t;
                            stats.stored += 1;
                        }
                        Err(e) => return fail(dataset, e),
                    }
                }
                match store_reference(&rig, &mut dataset, &developer, *r, &opts, &observer) {
                    Ok(warned) => {
                        stats.references += 1;
                        stats.reference_warnings += warned as usize;
                    }
                    Err(e) => return fail(dataset, e),
                }
                continue;
            }
        };
        let index = job.step.index;
        let pose = rig.kinematics.camera_pose(&job.q_read);
        // The lamp position from the same (corrected) kinematics as the camera pose.
        let lamp = rig.kinematics.light_position(&job.q_read);
        let (((developed, t_rect), (truth, t_truth)), committed) = std::thread::scope(|s| {
            let committing = pending.take().map(|p| {
                let (dataset, observer) = (&mut dataset, &observer);
                s.spawn(move || commit(dataset, p, observer))
            });
            let work = rayon::join(
                || {
                    let t = Instant::now();
                    let d = match (&job.bracket, &noise) {
                        (Some(b), Some(noise)) => {
                            let frames: Vec<Frame> = std::iter::once(job.frame.clone())
                                .chain(b.more.iter().cloned())
                                .collect();
                            developer
                                .develop_bracket(&frames, &pose, lamp, b.base_exposure_s, noise)
                                .map(|(d, r)| (d, Some(r)))
                        }
                        _ => developer
                            .develop(&job.frame, &pose, lamp, job.notes.exposure_scale)
                            .map(|d| (d, None)),
                    };
                    (d, t.elapsed().as_secs_f64())
                },
                || {
                    let t = Instant::now();
                    let truth = match (&rig.truth, opts.truth, &job.bracket) {
                        // The camera's setting may be another bracket's exposure by now.
                        (Some(t), true, Some(b)) => {
                            Some(t.truth_at(&job.q_read, width, height, b.base_exposure_s, job.frame.meta.gain))
                        }
                        (Some(t), true, None) => Some(t.truth(&job.q_read, width, height)),
                        _ => None,
                    };
                    (truth, t.elapsed().as_secs_f64())
                },
            );
            (work, committing.map(|h| h.join()))
        });
        match committed {
            None => {}
            Some(Ok(Ok(t))) => {
                stats.times.store += t;
                stats.stored += 1;
            }
            Some(Ok(Err(e))) => return fail(dataset, e),
            Some(Err(panic)) => std::panic::resume_unwind(panic),
        }
        stats.times.rectify += t_rect;
        stats.times.truth += t_truth;
        let (mut rect, saturated, merge_report) = match developed {
            Ok((d, report)) => (d.rectified, d.saturated, report),
            Err(DevelopError::Rectify(message)) => return fail(dataset, EngineError::Rectify { index, message }),
            Err(source) => return fail(dataset, EngineError::Calibration { index, source }),
        };
        let mut truth = truth;
        if let Some(img) = truth.as_mut() {
            let t = job
                .bracket
                .as_ref()
                .map_or(job.frame.meta.exposure, |b| b.base_exposure_s);
            let g = job.frame.meta.gain;
            if let Err(source) = developer.develop_truth(img, lamp, t, g) {
                return fail(dataset, EngineError::Calibration { index, source });
            }
        }
        if let Some(f) = job.lamp.as_ref().and_then(|l| l.output_correction) {
            // The lamp's output changed by f since the reference: back to the reference's.
            let k = (1.0 / f) as f32;
            rect.image.data.iter_mut().for_each(|v| *v *= k);
        }
        match rect.source {
            HomographySource::Markers => stats.markers += 1,
            HomographySource::Pose => stats.pose += 1,
        }
        let mut extra = serde_json::json!({
            "homography": rect.source,
            "markers_found": rect.markers_found,
            "marker_rms_px": rect.marker_rms_px,
        });
        if let Some(n) = saturated {
            // Pixels at or above the saturation code: corrected as neutral clipped white,
            // a lower bound (see `RawCorrection`).
            extra["saturated_pixels"] = serde_json::json!(n);
        }
        if let (Some(t), true) = (&truth, opts.store_truth) {
            match dataset.store_truth(index, t) {
                Ok(rel) => extra["truth_image"] = serde_json::json!(rel),
                Err(e) => return fail(dataset, EngineError::Store { index, source: e }),
            }
        }
        if let Some(t) = &truth {
            let e = metrics::image_error(&rect.image, t);
            extra["truth_rmse"] = serde_json::json!((e.0 / e.3.max(1) as f64).sqrt());
            stats.error.add(e);
        }
        let (l_rb, v_rb) = rig.kinematics.forward(&job.q_read);
        let mut rec = MeasurementRecord::new(index, job.order, job.step.light_deg, job.step.view_deg);
        rec.light_read_back_deg = Some(deg2(l_rb));
        rec.view_read_back_deg = Some(deg2(v_rb));
        rec.axes_commanded_deg = job.q_cmd.iter().map(|x| x.to_degrees()).collect();
        rec.axes_read_back_deg = job.q_read.iter().map(|x| x.to_degrees()).collect();
        rec.exposure_s = job.frame.meta.exposure;
        rec.gain = job.frame.meta.gain;
        rec.frame_sequence = Some(job.frame.meta.sequence);
        rec.rig_time_s = job.rig_time;
        rec.wall_time_unix = job.wall_time;
        rec.status = match &job.step.status {
            StepStatus::Measure => MeasurementStatus::Measured,
            StepStatus::Substitute {
                requested_light_deg,
                reason,
            } => MeasurementStatus::Substituted {
                requested_light_deg: *requested_light_deg,
                reason: reason.to_string(),
            },
        };
        if let Some(f) = &job.flight {
            extra["flight"] = f.clone();
        }
        if let Some(t) = job.camera_temperature_c {
            extra["camera_temperature_c"] = serde_json::json!(t);
        }
        job.notes.write_extra(&mut extra);
        if let (Some(b), Some(r)) = (&job.bracket, &merge_report) {
            extra["hdr"] = serde_json::json!({
                "mode": rig.spec.hdr_mode().word(),
                "exposures_s": r.exposures_s,
                "pixels_contributed": r.pixels_contributed,
                "clipped_pixels": r.clipped_pixels,
                "black_pixels": r.black_pixels,
                "dynamic_range_stops": r.dynamic_range_stops,
                "reasons": b.notes.reasons,
            });
        }
        rec.extra = extra;
        rec.lamp = job.lamp;
        pending = Some(Pending {
            rec,
            image: rect.image,
            raw: if opts.raw_frames { Some(job.frame) } else { None },
        });
    }
    if let Some(p) = pending.take() {
        match commit(&mut dataset, p, &observer) {
            Ok(t) => {
                stats.times.store += t;
                stats.stored += 1;
            }
            Err(e) => return fail(dataset, e),
        }
    }
    Ok((dataset, stats))
}

/// Develop a reference and its dark frame with the measurements' chain, take the mean of
/// their difference, store both (`Dataset::store_reference`) and tell the observer.
/// Returns whether its drift exceeded the threshold (logged as a warning).
fn store_reference(
    rig: &Rig,
    dataset: &mut Dataset,
    developer: &Developer,
    job: reference::ReferenceJob,
    opts: &RunOptions,
    observer: &Observer,
) -> Result<bool, EngineError> {
    let index = job.step.index;
    let pose = rig.kinematics.camera_pose(&job.q_read);
    let lamp = rig.kinematics.light_position(&job.q_read);
    let develop = |frame: &Frame| match developer.develop(frame, &pose, lamp, job.exposure_scale) {
        Ok(d) => {
            let mut img = d.rectified.image;
            if let Some(f) = job.output_correction {
                let k = (1.0 / f) as f32;
                img.data.iter_mut().for_each(|v| *v *= k);
            }
            Ok(img)
        }
        Err(DevelopError::Rectify(message)) => Err(EngineError::Rectify { index, message }),
        Err(source) => Err(EngineError::Calibration { index, source }),
    };
    let (image, dark) = rayon::join(|| develop(&job.frame), || develop(&job.dark));
    let (image, dark) = (image?, dark?);
    let rec = ReferenceRecord {
        number: 0,
        run: 0,
        rig_time_s: job.rig_time,
        duration_s: job.duration_s,
        stored_before: 0,
        after_index: None,
        pair_index: index,
        light_deg: job.step.light_deg,
        view_deg: job.step.view_deg,
        exposure_s: job.frame.meta.exposure,
        gain: job.frame.meta.gain,
        mean: reference::dark_subtracted_mean(&image, &dark),
        ratio: [1.0; 3],
        image: String::new(),
        image_sha256: String::new(),
        dark: String::new(),
        dark_sha256: String::new(),
    };
    let stored = dataset
        .store_reference(rec, &image, &dark)
        .map_err(|source| EngineError::Store { index, source })?;
    let threshold = opts.references.as_ref().map_or(f64::INFINITY, |r| r.drift_threshold);
    let warned = stored.drift() > threshold;
    if warned {
        tracing::warn!(
            reference = stored.number,
            "optical drift beyond {:.1} %: the reference pair reads {:.4} / {:.4} / {:.4} (R/G/B) of the first reference; \
             `gonio dataset drift {} --correct --out NEW` corrects it",
            threshold * 100.0,
            stored.ratio[0],
            stored.ratio[1],
            stored.ratio[2],
            dataset.dir().display()
        );
    }
    observer(&RunEvent::Reference { record: &stored });
    Ok(warned)
}

/// A developed measurement on its way to the dataset.
struct Pending {
    rec: MeasurementRecord,
    image: RgbImage,
    raw: Option<Frame>,
}

/// Store a developed measurement (EXR encoding, durable writes, then its journal line:
/// `Dataset::store`) and tell the observer. The store loop runs this for measurement k on
/// a thread of its own while it develops measurement k + 1: encoding and fsyncs are then
/// off the critical path, the order of journal lines stays the plan's, and the bytes are
/// the same. A crash loses at most the measurements not yet journaled (the one being
/// committed and the one being developed), which `--resume` measures again.
fn commit(dataset: &mut Dataset, p: Pending, observer: &Observer) -> Result<f64, EngineError> {
    let t = Instant::now();
    let index = p.rec.index;
    dataset
        .store(p.rec, Some(&p.image), p.raw.as_ref())
        .map_err(|source| EngineError::Store { index, source })?;
    if let Some(record) = dataset.records().last() {
        observer(&RunEvent::Stored { record });
    }
    Ok(t.elapsed().as_secs_f64())
}
