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
//! is synced (see `store`), so a crash at any moment loses at most the frame in flight,
//! which `--resume` measures again.

pub mod capture;
pub mod metrics;
pub mod rig;

use crate::calibrate::apply::AppliedCalibration;
use crate::plan::{Plan, Step, StepStatus};
use crate::rectify::{self, HomographySource, RectifyParams};
use crate::store::{Dataset, MeasurementRecord, MeasurementStatus, StoreError};
use gonio_devices::image::RgbImage;
use gonio_devices::{CameraConfig, DeviceError, Direction, Frame};
use metrics::ErrorAccumulator;
pub use rig::{GroundTruth, Rig};
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
    /// The camera failed every attempt the capture policy allows (see [`capture`]).
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
    Calibration {
        index: usize,
        source: crate::calibrate::apply::ApplyError,
    },
}

#[derive(Clone, Debug)]
pub struct RunOptions {
    pub width: usize,
    pub height: usize,
    pub raw_frames: bool,
    /// Compare with the simulator's ground truth (if the rig has one).
    pub truth: bool,
    /// Also store the ground truth as `truth/NNNNN.exr` (the exact rectified BTF).
    pub store_truth: bool,
    pub show_progress: bool,
    /// Supersampling cap of the rectification filter.
    pub max_supersample: usize,
}

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
    notes: capture::CaptureNotes,
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

/// Convert a frame of DN values into linear normalised values (DN / max DN).
pub fn frame_to_linear(frame: &Frame) -> RgbImage {
    let k = 1.0 / frame.max_dn() as f32;
    RgbImage {
        width: frame.width,
        height: frame.height,
        data: frame.data.iter().map(|&v| v as f32 * k).collect(),
    }
}

/// Record of a skipped pair (no image).
pub fn skipped_record(index: usize, light_deg: [f64; 2], view_deg: [f64; 2], reason: String) -> MeasurementRecord {
    let mut r = MeasurementRecord::new(index, usize::MAX, light_deg, view_deg);
    r.status = MeasurementStatus::Skipped { reason };
    r.wall_time_unix = unix_now();
    r
}

/// Home the rig, switch the light on and configure the camera.
pub async fn prepare(rig: &Rig) -> Result<CameraConfig, EngineError> {
    for a in &rig.axes {
        a.home().await.map_err(EngineError::Setup)?;
    }
    rig.light.set(true, 1.0).await.map_err(EngineError::Setup)?;
    let c = &rig.spec.camera;
    rig.camera
        .configure(&CameraConfig {
            width: c.width,
            height: c.height,
            exposure: c.exposure_s,
            gain: c.gain,
            bit_depth: c.bit_depth,
        })
        .await
        .map_err(EngineError::Setup)
}

/// Execute the plan's steps that are not in `done`. Returns the dataset (for `finish`)
/// and a report; on a store failure the error says which measurement.
pub async fn run(
    rig: Arc<Rig>,
    plan: Arc<Plan>,
    dataset: Dataset,
    done: HashSet<usize>,
    opts: RunOptions,
    pause: Arc<AtomicBool>,
) -> Result<(Dataset, RunReport), (Option<Dataset>, EngineError)> {
    run_calibrated(rig, plan, dataset, done, opts, pause, None).await
}

/// [`run`], applying calibration results in the store thread (see
/// `calibrate::apply`): undistortion and calibrated intrinsics before rectification, the
/// radiometric conversion to BRDF after it. The ground truth is converted the same way, so
/// the truth error stays on the scale of the stored values.
pub async fn run_calibrated(
    rig: Arc<Rig>,
    plan: Arc<Plan>,
    dataset: Dataset,
    done: HashSet<usize>,
    opts: RunOptions,
    pause: Arc<AtomicBool>,
    calibration: Option<Arc<AppliedCalibration>>,
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
    let bar = progress_bar(todo.len() as u64, opts.show_progress);
    let (tx, rx) = tokio::sync::mpsc::channel::<Job>(2);
    let failed = Arc::new(AtomicBool::new(false));
    let store = {
        let rig = rig.clone();
        let opts = opts.clone();
        let failed = failed.clone();
        std::thread::Builder::new()
            .name("gonio-store".into())
            .spawn(move || store_loop(rig, dataset, rx, opts, failed, calibration))
            .map_err(|_| (None, EngineError::StoreThread))?
    };
    let mut drive_err = None;
    let mut paused = false;
    let mut drive_times = StageSeconds::default();
    // The capture policy (retries, timeout, saturation) and the camera's actual settings.
    let setup = match capture::CapturePolicy::from_spec(&rig.spec.camera).map_err(EngineError::Setup) {
        Ok(policy) => prepare(&rig).await.map(|config| (policy, config)),
        Err(e) => Err(e),
    };
    let setup = setup.map_err(|e| drive_err = Some(e)).ok();
    for (order, step) in todo.iter().copied() {
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
        match drive_step(&rig, step, &mut drive_times, policy, camera_config).await {
            Ok((frame, notes, q_cmd, q_read)) => {
                let job = Job {
                    order,
                    step: step.clone(),
                    frame,
                    q_cmd,
                    q_read,
                    rig_time: rig.time(),
                    wall_time: unix_now(),
                    notes,
                };
                if tx.send(job).await.is_err() {
                    break; // store thread ended (failed): its error is reported below
                }
                bar.inc(1);
            }
            Err(e) => drive_err = Some(e),
        }
    }
    drop(tx);
    let stored = store.join();
    bar.finish_and_clear();
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
        },
    ))
}

/// What the drive loop hands on per step: frame, capture notes, commanded and read-back axes.
type Driven = (Frame, capture::CaptureNotes, Vec<f64>, Vec<f64>);

/// Move all axes to the step's targets (concurrently), wait until settled, capture (under
/// the capture policy: bounded retries, stale frames discarded, saturation handled).
///
/// Whether the engine can judge a frame stale by its timestamp: only the simulated camera
/// stamps frames on the rig clock. A V4L2 camera stamps CLOCK_MONOTONIC and applies its own
/// rule after `rig_still`, also when the axes are simulated (the vivid campaign found the
/// engine refusing every vivid frame when this looked at the clock alone).
fn frames_on_rig_clock(spec: &gonio_devices::rig::RigSpec, rig_has_clock: bool) -> bool {
    rig_has_clock && spec.camera.backend == "sim"
}

async fn drive_step(
    rig: &Rig,
    step: &Step,
    times: &mut StageSeconds,
    policy: &capture::CapturePolicy,
    camera_config: &CameraConfig,
) -> Result<Driven, EngineError> {
    let index = step.index;
    let device = |source: DeviceError| EngineError::Device { index, source };
    let t0 = Instant::now();
    let q: Vec<f64> = step.axes_deg.iter().map(|d| d.to_radians()).collect();
    for (axis, &target) in rig.axes.iter().zip(&q) {
        axis.start_move(target).await.map_err(device)?;
    }
    // Every axis is already moving; waiting one after the other ends with the slowest.
    let mut read = Vec::with_capacity(q.len());
    for axis in &rig.axes {
        read.push(axis.wait_idle().await.map_err(device)?);
    }
    // A streaming camera must not hand out frames exposed during the move.
    rig.camera.rig_still();
    let still_at = frames_on_rig_clock(&rig.spec, rig.clock.is_some()).then(|| rig.time());
    let t1 = Instant::now();
    rig.camera.begin_measurement(index as u64);
    let (frame, notes) = capture::capture_measurement(rig.camera.as_ref(), policy, camera_config, still_at)
        .await
        .map_err(|f| EngineError::Capture {
            index,
            attempts: f.attempts,
            source: f.source,
        })?;
    times.motion += (t1 - t0).as_secs_f64();
    times.capture += t1.elapsed().as_secs_f64();
    Ok((frame, notes, q, read))
}

struct StoreStats {
    times: StageSeconds,
    stored: usize,
    error: ErrorAccumulator,
    markers: usize,
    pose: usize,
}

type StoreResult = Result<(Dataset, StoreStats), Box<(Dataset, EngineError)>>;

fn store_loop(
    rig: Arc<Rig>,
    mut dataset: Dataset,
    mut rx: tokio::sync::mpsc::Receiver<Job>,
    opts: RunOptions,
    failed: Arc<AtomicBool>,
    calibration: Option<Arc<AppliedCalibration>>,
) -> StoreResult {
    let mut stats = StoreStats {
        times: StageSeconds::default(),
        stored: 0,
        error: ErrorAccumulator::default(),
        markers: 0,
        pose: 0,
    };
    let params = RectifyParams {
        width: opts.width,
        height: opts.height,
        sample_mm: rig.sample_mm,
        max_supersample: opts.max_supersample,
    };
    let intr = match &calibration {
        Some(c) => c.intrinsics(&rig.spec.camera.intrinsics()),
        None => rig.spec.camera.intrinsics(),
    };
    let undistort = calibration.as_ref().and_then(|c| c.camera);
    let radiometric = calibration.as_ref().and_then(|c| c.radiometric);
    let raw_correction = calibration.as_ref().and_then(|c| c.raw.as_ref());
    while let Some(job) = rx.blocking_recv() {
        let index = job.step.index;
        let pose = rig.kinematics.camera_pose(&job.q_read);
        let ((rect, t_rect), (truth, t_truth)) = rayon::join(
            || {
                let t = Instant::now();
                // Dark, response, flat, colour: on the raw frame, before the geometry.
                let (mut raw, saturated) = match raw_correction {
                    Some(c) => match c.apply(&job.frame) {
                        Ok((img, n)) => (img, Some(n)),
                        Err(e) => return (Err(e), 0.0),
                    },
                    None => (frame_to_linear(&job.frame), None),
                };
                if let (Some(k), None) = (job.notes.exposure_scale, &radiometric) {
                    // Re-exposed after saturating: back to the nominal exposure's scale (a
                    // radiometric calibration divides by each frame's own exposure instead).
                    raw.data.iter_mut().for_each(|v| *v *= k);
                }
                if let Some(cam) = &undistort {
                    raw = crate::calibrate::apply::undistort_frame(&raw, cam);
                }
                (
                    Ok((
                        rectify::rectify_frame(&raw, &intr, &pose, &rig.border, &params),
                        saturated,
                    )),
                    t.elapsed().as_secs_f64(),
                )
            },
            || {
                let t = Instant::now();
                let truth = match (&rig.truth, opts.truth) {
                    (Some(t), true) => Some(t.truth(&job.q_read, opts.width, opts.height)),
                    _ => None,
                };
                (truth, t.elapsed().as_secs_f64())
            },
        );
        stats.times.rectify += t_rect;
        stats.times.truth += t_truth;
        let (rect, saturated) = match rect {
            Ok(r) => r,
            Err(source) => {
                failed.store(true, Ordering::SeqCst);
                return Err(Box::new((dataset, EngineError::Calibration { index, source })));
            }
        };
        let mut rect = match rect {
            Ok(r) => r,
            Err(e) => {
                failed.store(true, Ordering::SeqCst);
                let err = EngineError::Rectify {
                    index,
                    message: e.to_string(),
                };
                return Err(Box::new((dataset, err)));
            }
        };
        let mut truth = truth;
        if let Some(r) = &radiometric {
            // HOOK (corrected kinematics): with a rig-geometry calibration the lamp position
            // must come from the corrected kinematics.
            let lamp = rig.kinematics.light_position(&job.q_read);
            let (t, g) = (job.frame.meta.exposure, job.frame.meta.gain);
            let mut converted = r.to_brdf(&mut rect.image, lamp, &params, t, g);
            // The truth is on the scale of an ideal linear sensor (DN / max DN); with raw-frame
            // corrections the fitted K is on the response curve's scale instead, so the truth
            // is converted with the simulated sensor's true K (the simulator knows it).
            let truth_radio = match raw_correction {
                Some(_) => crate::calibrate::apply::Radiometric {
                    k: [crate::calibrate::white::sim_truth_k(&rig); 3],
                    lamp: r.lamp,
                },
                None => *r,
            };
            if let (Ok(()), Some(img)) = (&converted, truth.as_mut()) {
                converted = truth_radio.to_brdf(img, lamp, &params, t, g);
            }
            if let Err(source) = converted {
                failed.store(true, Ordering::SeqCst);
                return Err(Box::new((dataset, EngineError::Calibration { index, source })));
            }
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
            let rel = format!("truth/{index:05}.exr");
            let path = dataset.dir().join(&rel);
            let written = std::fs::create_dir_all(dataset.dir().join("truth"))
                .map_err(|e| StoreError::io("creating", &path, Some(dataset.dir()), e))
                .and_then(|_| crate::store::encode_exr(t, &path))
                .and_then(|bytes| crate::store::atomic::write_atomic(&path, &bytes, Some(dataset.dir())));
            if let Err(e) = written {
                failed.store(true, Ordering::SeqCst);
                return Err(Box::new((dataset, EngineError::Store { index, source: e })));
            }
            extra["truth_image"] = serde_json::json!(rel);
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
        job.notes.write_extra(&mut extra);
        rec.extra = extra;
        let raw_frame = if opts.raw_frames { Some(&job.frame) } else { None };
        let t_store = Instant::now();
        let stored = dataset.store(rec, Some(&rect.image), raw_frame);
        stats.times.store += t_store.elapsed().as_secs_f64();
        if let Err(e) = stored {
            failed.store(true, Ordering::SeqCst);
            return Err(Box::new((dataset, EngineError::Store { index, source: e })));
        }
        stats.stored += 1;
    }
    Ok((dataset, stats))
}

fn progress_bar(len: u64, show: bool) -> indicatif::ProgressBar {
    if !show {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40.cyan/blue}] {pos}/{len} measurements  {per_sec}  ETA {eta}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
        .progress_chars("=> "),
    );
    bar
}

#[cfg(test)]
mod stale_rule_tests {
    /// Regression (vivid campaign): simulated axes with a V4L2 camera must not have their
    /// frames judged on the rig clock.
    #[test]
    fn only_the_simulated_camera_is_judged_on_the_rig_clock() {
        let mut spec = gonio_devices::rig::RigSpec::default_rig();
        assert!(super::frames_on_rig_clock(&spec, true));
        assert!(!super::frames_on_rig_clock(&spec, false));
        spec.camera.backend = "v4l2".into();
        assert!(!super::frames_on_rig_clock(&spec, true));
    }
}
