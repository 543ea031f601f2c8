//! The flyer step: one fly-scan segment (see `plan::fly`), Bluesky's kickoff / complete /
//! collect in the engine's terms.
//!
//! 1. **kickoff**: [`Rig::reach`] the segment's kickoff configuration (stop and go, as any
//!    step), wait until the previous frame's readout leaves room for the first exposure,
//!    then start the moving axis towards the stop position at the segment's velocity
//!    ([`gonio_devices::Axis::start_move_at`]);
//! 2. **collect**, per pose: read the moving axis back just before the exposure's planned
//!    start (issued one round trip early, so the exposure starts on time), wait on the rig
//!    clock until that start, capture under the same capture policy as a still step, read
//!    the moving axis back again. Only the moving axis is read during a flight: the others
//!    stand still at their kickoff read-back, and every read is a serial round trip on a
//!    real rig. Each read-back is stamped at the middle of its round trip (the controller
//!    sampled the position somewhere inside it), and the frame's pose is the read-backs'
//!    linear interpolation at mid-exposure (the axis runs at constant velocity through the
//!    exposure): measured, not assumed. A frame whose mid-exposure light or view direction
//!    is more than [`POSE_TOLERANCE_DEG`] from the planned one, or that needed a retry (a
//!    retry exposes later, elsewhere), is not kept. On a mixed rig (serial stages,
//!    simulated camera) the flyer paces each exposure on the wall clock and shows the
//!    simulated camera the pose predicted for mid-exposure ([`Rig::show_pose`]);
//! 3. **complete**: wait until the axis has stopped and settled, then retake the frames not
//!    kept stop and go ([`super::drive_step`]), so no frame is stored with a pose it was not
//!    taken at.
//!
//! Every frame's record carries `extra.flight`: the axes read back before and after its
//! exposure (`axes_start_deg`, `axes_end_deg`) and when (`read_back_at_s`, rig clock), the
//! light and view directions they give, the exposure's start and end on the rig clock
//! (`exposure_start_s`, `exposure_end_s`), and the segment and velocity (or why it was
//! retaken); the record's `axes_read_back_deg` is the interpolated mid-exposure pose.
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

/// Read the moving axis back, stamped on the rig clock at the middle of the exchange (a
/// serial round trip: the controller sampled the position somewhere inside it, and the
/// middle is the unbiased guess).
/// Returns the position, its time and the round trip's duration.
async fn read_back(
    rig: &Rig,
    moving: &std::sync::Arc<dyn gonio_devices::Axis>,
) -> Result<(f64, f64, f64), gonio_devices::DeviceError> {
    let before = rig.time();
    let x = moving.position().await?;
    let after = rig.time();
    Ok((x, 0.5 * (before + after), after - before))
}

/// The value at `t` on the line through two stamped read-backs; their mean when they
/// carry the same time (a simulated rig reads back in no time).
fn interpolate((ta, xa): (f64, f64), (tb, xb): (f64, f64), t: f64) -> f64 {
    if (tb - ta).abs() < 1e-9 {
        0.5 * (xa + xb)
    } else {
        xa + (xb - xa) * (t - ta) / (tb - ta)
    }
}

/// The per-gap profile of a segment (see `gonio_devices::motion::Trajectory::flight`), from
/// its steps' poses, exposure velocities and offsets and the axis' motion.
fn segment_trajectory(
    rig: &Rig,
    seg: &[(usize, &Step)],
) -> Result<gonio_devices::Trajectory, gonio_devices::DeviceError> {
    let f0 = seg[0].1.flight.as_ref().expect("a segment's steps are flown");
    let axis = f0.axis;
    let spec = &rig.spec.axes[axis];
    let m = spec.motion();
    let mut poses = Vec::with_capacity(seg.len());
    let mut speeds = Vec::with_capacity(seg.len());
    let mut offsets = Vec::with_capacity(seg.len());
    for (_, st) in seg {
        let f = st.flight.as_ref().expect("a segment's steps are flown");
        poses.push(st.axes_deg[axis].to_radians());
        speeds.push(f.velocity_deg_s.abs().to_radians());
        offsets.push(f.exposure_offset_s);
    }
    gonio_devices::Trajectory::flight(
        f0.kickoff_deg.to_radians(),
        &poses,
        &speeds,
        &offsets,
        rig.spec.camera.exposure_s.max(0.0),
        m.acceleration,
        m.max_velocity,
        m.settle_time,
        f0.stop_deg.to_radians(),
    )
    .ok_or_else(|| gonio_devices::DeviceError::Rejected {
        device: spec.name.clone(),
        command: "start_trajectory".into(),
        reason: "the segment's per-gap profile is inconsistent (a gap cannot last its planned time)".into(),
    })
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
    let q_read = rig.reach(&q_kick).await.map_err(device(index0))?;
    let readout = rig.spec.camera.overlapped_readout_s().unwrap_or(0.0);
    let mut kick = rig.time();
    if let Some(e) = *last_end {
        kick = kick.max(e + readout - f0.exposure_offset_s);
    }
    rig.wait_until(kick).await;
    // A per-gap flight follows the profile the planner timed, rebuilt from the segment's
    // steps before the kickoff (the same numbers on every run of the plan).
    let trajectory = if f0.per_gap {
        Some(segment_trajectory(rig, seg).map_err(device(index0))?)
    } else {
        None
    };
    let before = rig.time();
    match &trajectory {
        Some(tr) => rig.axes[axis].start_trajectory(tr).await,
        None => {
            rig.axes[axis]
                .start_move_at(f0.stop_deg.to_radians(), f0.velocity_deg_s.abs().to_radians())
                .await
        }
    }
    .map_err(device(index0))?;
    // The controller starts the move when the command arrives, inside the exchange: the
    // middle of the round trip is the kickoff every exposure is timed from.
    let after = rig.time();
    let kick = 0.5 * (before + after);
    times.motion += t_motion.elapsed().as_secs_f64();
    // collect
    let moving = rig.axes[axis].clone();
    // The still axes were read back when the kickoff configuration was reached; during
    // the flight only the moving axis is read (each read is a serial round trip on a real
    // rig, and the still ones cannot have moved).
    let q_still = q_read;
    let exposure_s = rig.spec.camera.exposure_s.max(0.0);
    // A mixed rig (serial stages, simulated camera) renders on its shadow world's virtual
    // clock: the flyer paces its exposures on the wall clock, as a real camera takes them.
    let paced = rig.clock.is_none() && rig.spec.camera.backend == "sim";
    // The last read-back's round trip: the read before an exposure is issued that much
    // ahead of it, so the exposure starts on time.
    let mut round_trip = after - before;
    let mut out = Vec::new();
    let mut retake: Vec<(usize, &Step, String)> = Vec::new();
    for &(order, step) in seg {
        if !wanted.contains(&step.index) {
            continue;
        }
        let index = step.index;
        let f = step.flight.as_ref().expect("a segment's steps are flown");
        // The axis holds this velocity through the exposure (the segment's one velocity, or
        // this pose's own in a per-gap flight).
        let velocity = f.velocity_deg_s.to_radians();
        let t_cap = Instant::now();
        let planned_start = kick + f.exposure_offset_s;
        rig.wait_until(planned_start - round_trip).await;
        let (x_start, at_start, rt) = read_back(rig, &moving).await.map_err(device(index))?;
        round_trip = rt;
        rig.wait_until(planned_start).await;
        let exposure_start = rig.time();
        // The simulated camera of a mixed rig renders its shadow axes: show it the pose
        // predicted for mid-exposure from this read-back.
        rig.show_pose(
            axis,
            x_start + velocity * (exposure_start - at_start + exposure_s / 2.0),
        )
        .await
        .map_err(device(index))?;
        rig.camera.begin_measurement(index as u64);
        let (frame, notes) = rig.capture(policy, config).await.map_err(|e| EngineError::Capture {
            index,
            attempts: e.attempts,
            source: e.source,
        })?;
        let exposure_end = if paced {
            // The simulated camera's exposure is [start, start + exposure] by definition;
            // rendering it is computation that may run longer (the first frame builds the
            // renderer's caches) and must not move the exposure's middle.
            rig.wait_until(exposure_start + exposure_s).await;
            exposure_start + exposure_s
        } else {
            rig.time()
        };
        let (x_end, at_end, _) = read_back(rig, &moving).await.map_err(device(index))?;
        *last_end = Some(exposure_end);
        times.capture += t_cap.elapsed().as_secs_f64();
        // The axis runs at constant velocity through the exposure: the pose at its middle
        // is the read-backs' interpolation at that time (their own times are the middles
        // of their round trips).
        let mid_t = 0.5 * (exposure_start + exposure_end);
        let x_mid = interpolate((at_start, x_start), (at_end, x_end), mid_t);
        let with = |x: f64| {
            let mut q = q_still.clone();
            q[axis] = x;
            q
        };
        let (q_start, q_end, q_mid) = (with(x_start), with(x_end), with(x_mid));
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
            "exposure_end_s": exposure_end,
            "axes_start_deg": degs(&q_start),
            "axes_end_deg": degs(&q_end),
            "read_back_at_s": [at_start, at_end],
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
