//! The flyer step: one fly-scan segment (see `plan::fly`), Bluesky's kickoff / complete /
//! collect in the engine's terms.
//!
//! 1. **kickoff**: [`Rig::reach`] the segment's kickoff configuration (stop and go, as any
//!    step), wait until the previous frame's readout leaves room for the first exposure,
//!    then start the moving axis towards the stop position at the segment's velocity
//!    ([`gonio_devices::Axis::start_move_at`]);
//! 2. **collect**, per pose: wait on the rig clock until the exposure's planned start, read
//!    every axis back, capture under the same capture policy as a still step, read every
//!    axis back again. The frame's pose is the mean of the two read-backs (the stages move
//!    at constant velocity through an exposure), measured, not assumed; a frame whose
//!    mid-exposure light or view direction is more than [`POSE_TOLERANCE_DEG`] from the
//!    planned one, or that needed a retry (a retry exposes later, elsewhere), is not kept;
//! 3. **complete**: wait until the axis has stopped and settled, then retake the frames not
//!    kept stop and go ([`super::drive_step`]), so no frame is stored with a pose it was not
//!    taken at.
//!
//! Every frame's record carries `extra.flight`: the axes read back at the start and end of
//! its exposure, the light and view directions they give, the exposure's start on the rig
//! clock, and the segment and velocity (or why it was retaken).
//!
//! A resumed run flies a partly measured segment whole and exposes only the poses still
//! missing: the timing of every exposure relative to the kickoff is the plan's, so on a
//! simulated rig the images are the same bytes as in an uninterrupted run.

use super::{drive_step, Driven, EngineError, StageSeconds};
use crate::plan::fly::POSE_TOLERANCE_DEG;
use crate::plan::Step;
use crate::rig::{CapturePolicy, Rig};
use gonio_devices::{CameraConfig, Direction};
use std::collections::HashSet;
use std::time::Instant;

/// A frame of a segment, on its way to the store thread.
pub(super) struct Flown {
    pub order: usize,
    pub step: Step,
    pub driven: Driven,
    /// The record's `extra.flight`.
    pub flight: serde_json::Value,
    /// Rig-clock time the frame's exposure ended (the record's `rig_time_s`).
    pub rig_time: f64,
}

fn deg2(d: Direction) -> [f64; 2] {
    [d.theta_deg(), d.phi_deg()]
}

fn degs(q: &[f64]) -> Vec<f64> {
    q.iter().map(|x| x.to_degrees()).collect()
}

/// Fly one segment: `seg` is every step of it in plan order (with its plan index), `wanted`
/// the canonical indices still to measure. `last_end` is the rig-clock end of the previous
/// exposure (its readout must be over before the first exposure here); it is updated.
#[allow(clippy::too_many_arguments)]
pub(super) async fn drive_segment(
    rig: &Rig,
    seg: &[(usize, &Step)],
    wanted: &HashSet<usize>,
    times: &mut StageSeconds,
    policy: &CapturePolicy,
    config: &CameraConfig,
    last_end: &mut Option<f64>,
) -> Result<Vec<Flown>, EngineError> {
    let (_, first) = seg[0];
    let f0 = first.flight.as_ref().expect("a segment's steps are flown");
    let axis = f0.axis;
    let index0 = first.index;
    let device = |index: usize| move |source| EngineError::Device { index, source };
    let t_motion = Instant::now();
    // kickoff
    let mut q_kick: Vec<f64> = first.axes_deg.iter().map(|d| d.to_radians()).collect();
    q_kick[axis] = f0.kickoff_deg.to_radians();
    rig.reach(&q_kick).await.map_err(device(index0))?;
    let readout = rig.spec.camera.overlapped_readout_s().unwrap_or(0.0);
    let mut kick = rig.time();
    if let Some(e) = *last_end {
        kick = kick.max(e + readout - f0.exposure_offset_s);
    }
    rig.wait_until(kick).await;
    let kick = rig.time();
    rig.axes[axis]
        .start_move_at(f0.stop_deg.to_radians(), f0.velocity_deg_s.abs().to_radians())
        .await
        .map_err(device(index0))?;
    times.motion += t_motion.elapsed().as_secs_f64();
    // collect
    let mut out = Vec::new();
    let mut retake: Vec<(usize, &Step, String)> = Vec::new();
    for &(order, step) in seg {
        if !wanted.contains(&step.index) {
            continue;
        }
        let index = step.index;
        let f = step.flight.as_ref().expect("a segment's steps are flown");
        let t_cap = Instant::now();
        rig.wait_until(kick + f.exposure_offset_s).await;
        let q_start = rig.positions().await.map_err(device(index))?;
        let exposure_start = rig.time();
        rig.camera.begin_measurement(index as u64);
        let (frame, notes) = rig.capture(policy, config).await.map_err(|e| EngineError::Capture {
            index,
            attempts: e.attempts,
            source: e.source,
        })?;
        let q_end = rig.positions().await.map_err(device(index))?;
        let exposure_end = rig.time();
        *last_end = Some(exposure_end);
        times.capture += t_cap.elapsed().as_secs_f64();
        let q_mid: Vec<f64> = q_start.iter().zip(&q_end).map(|(a, b)| 0.5 * (a + b)).collect();
        let q_plan: Vec<f64> = step.axes_deg.iter().map(|d| d.to_radians()).collect();
        let (l_mid, v_mid) = rig.kinematics.forward(&q_mid);
        let (l_plan, v_plan) = rig.kinematics.forward(&q_plan);
        let off = l_mid.angle_to(l_plan).max(v_mid.angle_to(v_plan)).to_degrees();
        if notes.retries > 0 {
            retake.push((order, step, format!("{} capture retries in flight", notes.retries)));
            continue;
        }
        if off > POSE_TOLERANCE_DEG {
            tracing::warn!(
                index,
                off_deg = off,
                "flown frame {off:.3}° from its planned directions: retaken stop and go"
            );
            retake.push((
                order,
                step,
                format!("mid-exposure directions {off:.4}° from the planned ones (tolerance {POSE_TOLERANCE_DEG}°)"),
            ));
            continue;
        }
        let (l0, v0) = rig.kinematics.forward(&q_start);
        let (l1, v1) = rig.kinematics.forward(&q_end);
        let flight = serde_json::json!({
            "segment": f.segment,
            "velocity_deg_s": f.velocity_deg_s,
            "exposure_start_s": exposure_start,
            "axes_start_deg": degs(&q_start),
            "axes_end_deg": degs(&q_end),
            "light_start_deg": deg2(l0),
            "light_end_deg": deg2(l1),
            "view_start_deg": deg2(v0),
            "view_end_deg": deg2(v1),
            "light_sweep_deg": l0.angle_to(l1).to_degrees(),
            "mid_off_planned_deg": off,
        });
        out.push(Flown {
            order,
            step: step.clone(),
            driven: (frame, notes, None, q_plan, q_mid),
            flight,
            rig_time: exposure_end,
        });
    }
    // complete
    let t_motion = Instant::now();
    rig.axes[axis].wait_idle().await.map_err(device(index0))?;
    times.motion += t_motion.elapsed().as_secs_f64();
    for (order, step, why) in retake {
        let driven = drive_step(rig, step, times, policy, config, None).await?;
        let end = rig.time();
        *last_end = Some(end);
        out.push(Flown {
            order,
            step: step.clone(),
            driven,
            flight: serde_json::json!({
                "segment": step.flight.as_ref().map(|f| f.segment),
                "retaken_stop_and_go": why,
            }),
            rig_time: end,
        });
    }
    Ok(out)
}
