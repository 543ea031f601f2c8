//! The motion policy shared by every serial axis: when is a move done, what is retried,
//! how long may it take.
//!
//! A controller saying "idle" is not enough to take a picture: the stage may still ring
//! (settle time), may have stopped short (a stall, a following error, a lost step), and a
//! lead screw or worm gear has backlash, so the same target approached from two sides gives
//! two positions. [`PolicyAxis`] wraps a protocol [`Driver`] and implements
//! `gonio_devices::Axis` with these rules:
//! - a move is done only when the controller reports idle, the settle time has passed
//!   since, and |read-back − target| ≤ deadband (else it is re-commanded, at most `retries`
//!   times, then [`DeviceError::MissedTarget`]);
//! - backlash: with `backlash_deg ≠ 0` every target is approached from the same side
//!   (from below for a positive value): a move arriving from the other side first goes
//!   past the target by that amount;
//! - transient errors (garbled reply, reply timeout, disconnect) are retried, at most
//!   `retries` times per command;
//! - a move may take `timeout_factor × profile time + timeout_floor_s` (profile time from
//!   the rig file's motion model), after which the axis is stopped ([`DeviceError::Timeout`]);
//! - a moving axis whose read-back does not change for `stall_s` is stopped
//!   ([`DeviceError::Stall`]);
//! - moves shorter than the deadband send nothing.

use super::{Options, SerialConfigError};
use crate::axis::check_limits;
use crate::rig::AxisSpec;
use crate::{Axis, AxisStatus, DeviceError, MotionModel, SoftLimits};
use async_trait::async_trait;
use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// What one status poll of a controller says.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Poll {
    pub busy: bool,
    /// Read-back position in the axis' units (radians or mm).
    pub position: f64,
}

/// One axis of one controller, in the axis' units (radians or mm). Blocking: the policy
/// runs these on tokio's blocking pool. Errors name the axis and the command.
pub trait Driver: Send + Sync + 'static {
    /// Clear latched faults/warnings before homing (a stall flag stays set until cleared).
    fn clear_faults(&self) -> Result<(), DeviceError> {
        Ok(())
    }
    /// Start homing; returns once the controller accepted the command.
    fn home(&self) -> Result<(), DeviceError>;
    /// Start an absolute move; returns once the controller accepted the command.
    fn move_abs(&self, target: f64) -> Result<(), DeviceError>;
    /// Busy flag and position. Faults the controller reports (limit switch, stall …) are
    /// errors naming `during`, the motion command in progress.
    fn poll(&self, during: &str) -> Result<Poll, DeviceError>;
    fn stop(&self) -> Result<(), DeviceError>;
    /// The controller's own travel limits, if it has any.
    fn device_limits(&self) -> Result<Option<SoftLimits>, DeviceError>;
    /// The controller's identity (device id, firmware version) for `gonio devices check`;
    /// `None` when the protocol has no such query (the default).
    fn identity(&self) -> Result<Option<String>, DeviceError> {
        Ok(None)
    }
    /// Check for errors after a motion ended (controllers with an error queue).
    fn after_motion(&self, _during: &str) -> Result<(), DeviceError> {
        Ok(())
    }
    /// One native unit (microstep, encoder count) in axis units.
    fn resolution(&self) -> f64;
    /// The command text for a move to `target`, for error messages.
    fn describe_move(&self, target: f64) -> String;
    /// A load-side reference reading (encoder) in axis units, if the device has one
    /// configured; see [`crate::Axis::reference_position`].
    fn reference(&self) -> Result<Option<f64>, DeviceError> {
        Ok(None)
    }
    /// Start an absolute move to `target` that cruises at `velocity` and accelerates at
    /// `acceleration` (axis units/s, units/s²; both > 0): a fly-scan's constant-velocity
    /// pass. Controllers without per-move velocity refuse (the default).
    fn move_abs_at(&self, target: f64, velocity: f64, acceleration: f64) -> Result<(), DeviceError> {
        let _ = (velocity, acceleration);
        Err(DeviceError::Rejected {
            device: "serial axis".into(),
            command: self.describe_move(target),
            reason: "this controller's driver has no constant-velocity moves".into(),
        })
    }
    /// The command text for [`Driver::move_abs_at`], for error messages.
    fn describe_move_at(&self, target: f64, velocity: f64, acceleration: f64) -> String {
        let _ = (velocity, acceleration);
        self.describe_move(target)
    }
    /// Undo what [`Driver::move_abs_at`] changed in the controller's settings (called once
    /// the flight's motion has ended or was stopped). Per-move settings need nothing.
    fn end_flight(&self) -> Result<(), DeviceError> {
        Ok(())
    }
}

/// Policy parameters; see the module documentation.
#[derive(Clone, Debug, PartialEq)]
pub struct MotionPolicy {
    pub backlash: f64,
    pub retries: u32,
    pub poll_interval: Duration,
    pub timeout_factor: f64,
    pub timeout_floor_s: f64,
    pub stall_s: f64,
    /// Homing timeout; `None`: computed from the travel range and the motion model.
    pub home_timeout_s: Option<f64>,
}

impl Default for MotionPolicy {
    fn default() -> Self {
        MotionPolicy {
            backlash: 0.0,
            retries: 2,
            poll_interval: Duration::from_millis(20),
            timeout_factor: 1.5,
            timeout_floor_s: 2.0,
            stall_s: 1.0,
            home_timeout_s: None,
        }
    }
}

/// The `options` keys [`MotionPolicy::from_options`] reads (every serial backend accepts them).
pub const POLICY_KEYS: &[&str] = &[
    "backlash_deg",
    "retries",
    "poll_ms",
    "timeout_factor",
    "timeout_floor_s",
    "stall_s",
    "home_timeout_s",
];

impl MotionPolicy {
    pub fn from_options(opts: &Options<'_>, _spec: &AxisSpec) -> Result<MotionPolicy, SerialConfigError> {
        let d = MotionPolicy::default();
        Ok(MotionPolicy {
            backlash: opts.f64("backlash_deg")?.unwrap_or(0.0).to_radians(),
            retries: opts.int("retries", d.retries as i64, 0, 20)? as u32,
            poll_interval: Duration::from_millis(opts.int("poll_ms", 20, 1, 10_000)? as u64),
            timeout_factor: opts.positive("timeout_factor", d.timeout_factor)?.max(1.0),
            timeout_floor_s: opts.non_negative("timeout_floor_s", d.timeout_floor_s)?,
            stall_s: opts.positive("stall_s", d.stall_s)?,
            home_timeout_s: opts.f64("home_timeout_s")?.filter(|x| *x > 0.0),
        })
    }
}

struct Pending {
    target: f64,
    /// Legs still to command after the current one (the last is `target`).
    legs: VecDeque<f64>,
    /// The leg in motion: (from, to, command text, when it was commanded).
    current: Option<(f64, f64, String, Instant)>,
    corrections: u32,
    /// The current leg is a flight at this velocity (axis units/s): its timeout follows
    /// that velocity, and the driver's [`Driver::end_flight`] runs once it has ended.
    flight: Option<f64>,
}

struct State {
    homed: bool,
    device_limits: Option<SoftLimits>,
    last: Option<f64>,
    pending: Option<Pending>,
}

/// A serial axis: a protocol driver plus the motion policy.
pub struct PolicyAxis<D: Driver> {
    name: String,
    limits: SoftLimits,
    motion: MotionModel,
    policy: MotionPolicy,
    driver: Arc<D>,
    state: Mutex<State>,
}

impl<D: Driver> PolicyAxis<D> {
    pub fn new(name: &str, limits: SoftLimits, motion: MotionModel, policy: MotionPolicy, driver: D) -> Self {
        PolicyAxis {
            name: name.to_string(),
            limits,
            motion,
            policy,
            driver: Arc::new(driver),
            state: Mutex::new(State {
                homed: false,
                device_limits: None,
                last: None,
                pending: None,
            }),
        }
    }

    pub fn driver(&self) -> &D {
        &self.driver
    }

    /// The deadband actually used: the rig file's, but never below half a native unit
    /// plus a margin (a target is rounded to the nearest unit, so a tighter deadband could
    /// never be met).
    pub fn deadband(&self) -> f64 {
        self.motion.deadband.max(0.51 * self.driver.resolution())
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        // A panic while holding this lock leaves only plain data behind; keep going.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Rig limits intersected with the controller's own.
    fn effective_limits(&self) -> SoftLimits {
        match self.lock().device_limits {
            Some(d) => SoftLimits {
                min: self.limits.min.max(d.min),
                max: self.limits.max.min(d.max),
            },
            None => self.limits,
        }
    }

    /// Run a blocking driver call, retrying transient failures.
    async fn call<T, F>(&self, what: &str, f: F) -> Result<T, DeviceError>
    where
        T: Send + 'static,
        F: Fn(&D) -> Result<T, DeviceError> + Send + Sync + 'static,
    {
        let f = Arc::new(f);
        let mut attempt = 0;
        loop {
            let d = self.driver.clone();
            let g = f.clone();
            let r = tokio::task::spawn_blocking(move || g(&d)).await.unwrap_or_else(|e| {
                Err(DeviceError::Other {
                    device: self.name.clone(),
                    command: what.to_string(),
                    reason: format!("driver task failed: {e}"),
                })
            });
            match r {
                Err(e) if e.is_transient() && attempt < self.policy.retries => {
                    attempt += 1;
                    tracing::warn!(axis = %self.name, "{e}; retrying `{what}` ({attempt}/{})", self.policy.retries);
                }
                r => return r,
            }
        }
    }

    async fn poll(&self, during: &str) -> Result<Poll, DeviceError> {
        let during = during.to_string();
        self.call("poll", move |d| d.poll(&during)).await
    }

    async fn command_move(&self, to: f64) -> Result<String, DeviceError> {
        let cmd = self.driver.describe_move(to);
        self.call(&cmd, move |d| d.move_abs(to)).await?;
        Ok(cmd)
    }

    async fn end_flight_quietly(&self) {
        if let Err(e) = self.call("end flight", |d| d.end_flight()).await {
            tracing::warn!(axis = %self.name, "restoring the controller after a flight failed: {e}");
        }
    }

    async fn stop_quietly(&self) {
        if let Err(e) = self.call("stop", |d| d.stop()).await {
            tracing::warn!(axis = %self.name, "stop after a failed move also failed: {e}");
        }
    }

    /// Poll until the controller is idle; timeout and stall detection as documented.
    async fn wait_motion(&self, command: &str, since: Instant, timeout_s: f64) -> Result<f64, DeviceError> {
        let progress_step = (2.0 * self.driver.resolution()).max(self.motion.deadband);
        let mut progress: Option<(f64, Instant)> = None;
        loop {
            let p = self.poll(command).await.inspect_err(|_| self.lock().last = None)?;
            self.lock().last = Some(p.position);
            if !p.busy {
                return Ok(p.position);
            }
            let now = Instant::now();
            match progress {
                Some((x, _)) if (p.position - x).abs() > progress_step => progress = Some((p.position, now)),
                None => progress = Some((p.position, since)),
                Some((x, t)) if (now - t).as_secs_f64() > self.policy.stall_s => {
                    self.stop_quietly().await;
                    let _ = x;
                    return Err(DeviceError::Stall {
                        device: self.name.clone(),
                        command: command.to_string(),
                        position: p.position,
                    });
                }
                Some(_) => {}
            }
            if (now - since).as_secs_f64() > timeout_s {
                self.stop_quietly().await;
                return Err(DeviceError::Timeout {
                    device: self.name.clone(),
                    command: command.to_string(),
                    seconds: timeout_s,
                });
            }
            tokio::time::sleep(self.policy.poll_interval).await;
        }
    }

    fn move_timeout(&self, distance: f64) -> f64 {
        self.policy.timeout_factor * self.motion.profile_time(distance) + self.policy.timeout_floor_s
    }

    async fn settle(&self) {
        if self.motion.settle_time > 0.0 {
            tokio::time::sleep(Duration::from_secs_f64(self.motion.settle_time)).await;
        }
    }

    /// The legs of a move from `from` to `target` with one-sided approach.
    fn legs(&self, from: f64, target: f64) -> VecDeque<f64> {
        let b = self.policy.backlash;
        let mut legs = VecDeque::new();
        if b != 0.0 && (target - from) * b < 0.0 {
            // Arriving from the wrong side: overshoot by |b| then come back.
            let lim = self.effective_limits();
            let pre = (target - b).clamp(lim.min, lim.max);
            if (pre - target).abs() > self.deadband() {
                legs.push_back(pre);
            }
        }
        legs.push_back(target);
        legs
    }
}

#[async_trait]
impl<D: Driver> Axis for PolicyAxis<D> {
    fn name(&self) -> &str {
        &self.name
    }

    fn limits(&self) -> SoftLimits {
        self.effective_limits()
    }

    async fn identity(&self) -> Result<String, DeviceError> {
        Ok(self
            .call("identity", |d| d.identity())
            .await?
            .unwrap_or_else(|| self.name.clone()))
    }

    fn motion(&self) -> MotionModel {
        self.motion
    }

    async fn home(&self) -> Result<(), DeviceError> {
        self.lock().pending = None;
        self.call("warnings clear", |d| d.clear_faults()).await?;
        self.call("home", |d| d.home()).await?;
        let since = Instant::now();
        let range = (self.limits.max - self.limits.min).abs();
        let timeout = self.policy.home_timeout_s.unwrap_or_else(|| self.move_timeout(range));
        self.wait_motion("home", since, timeout).await?;
        self.settle().await;
        self.call("home", |d| d.after_motion("home")).await?;
        let p = self.poll("home").await?;
        let dl = match self.call("get limits", |d| d.device_limits()).await {
            Ok(l) => l,
            Err(e) if e.is_transient() => return Err(e),
            Err(e) => {
                tracing::warn!(axis = %self.name, "cannot read the controller's travel limits: {e}");
                None
            }
        };
        if let Some(d) = dl {
            if d.min > self.limits.min || d.max < self.limits.max {
                tracing::warn!(
                    axis = %self.name,
                    "controller travel [{:.3}°, {:.3}°] is narrower than the rig file's [{:.3}°, {:.3}°]; using the intersection",
                    d.min.to_degrees(), d.max.to_degrees(), self.limits.min.to_degrees(), self.limits.max.to_degrees()
                );
            }
        }
        let mut s = self.lock();
        s.homed = true;
        s.device_limits = dl;
        s.last = Some(p.position);
        Ok(())
    }

    async fn start_move(&self, target: f64) -> Result<(), DeviceError> {
        check_limits(&self.name, self.effective_limits(), target, "move_abs")?;
        let (homed, last) = {
            let s = self.lock();
            (s.homed, s.last)
        };
        if !homed {
            return Err(DeviceError::NotHomed {
                device: self.name.clone(),
                command: "move_abs".into(),
            });
        }
        let from = match last {
            Some(x) => x,
            None => self.poll("move_abs").await?.position,
        };
        if (target - from).abs() <= self.deadband() {
            self.lock().pending = Some(Pending {
                target,
                legs: VecDeque::new(),
                current: None,
                corrections: 0,
                flight: None,
            });
            return Ok(());
        }
        let mut legs = self.legs(from, target);
        let first = legs.pop_front().expect("at least the target");
        let cmd = self.command_move(first).await?;
        self.lock().pending = Some(Pending {
            target,
            legs,
            current: Some((from, first, cmd, Instant::now())),
            corrections: 0,
            flight: None,
        });
        Ok(())
    }

    async fn wait_idle(&self) -> Result<f64, DeviceError> {
        let Some(mut p) = self.lock().pending.take() else {
            return self.position().await;
        };
        loop {
            let moved = p.current.is_some();
            if let Some((from, to, cmd, since)) = p.current.take() {
                let flight = p.flight.take();
                let timeout = match flight {
                    Some(v) => {
                        let m = MotionModel {
                            max_velocity: v,
                            ..self.motion
                        };
                        self.policy.timeout_factor * m.profile_time(to - from) + self.policy.timeout_floor_s
                    }
                    None => self.move_timeout(to - from),
                };
                let waited = self.wait_motion(&cmd, since, timeout).await;
                if flight.is_some() {
                    self.end_flight_quietly().await;
                }
                waited?;
                if let Some(next) = p.legs.pop_front() {
                    let cmd = self.command_move(next).await?;
                    p.current = Some((to, next, cmd, Instant::now()));
                    continue;
                }
                self.settle().await;
            }
            let during = self.driver.describe_move(p.target);
            if moved {
                let d2 = during.clone();
                self.call(&during, move |d| d.after_motion(&d2)).await?;
            }
            let rb = self.poll(&during).await?;
            self.lock().last = Some(rb.position);
            if (rb.position - p.target).abs() <= self.deadband() {
                return Ok(rb.position);
            }
            if p.corrections >= self.policy.retries {
                return Err(DeviceError::MissedTarget {
                    device: self.name.clone(),
                    command: during,
                    target: p.target,
                    read_back: rb.position,
                    deadband: self.deadband(),
                });
            }
            p.corrections += 1;
            tracing::warn!(
                axis = %self.name,
                "read back {:.6}, wanted {:.6}: re-commanding ({}/{})",
                rb.position, p.target, p.corrections, self.policy.retries
            );
            p.legs = self.legs(rb.position, p.target);
            let next = p.legs.pop_front().expect("at least the target");
            let cmd = self.command_move(next).await?;
            p.current = Some((rb.position, next, cmd, Instant::now()));
        }
    }

    async fn stop(&self) -> Result<(), DeviceError> {
        let flying = self.lock().pending.take().is_some_and(|p| p.flight.is_some());
        let r = self.call("stop", |d| d.stop()).await;
        if flying {
            self.end_flight_quietly().await;
        }
        r
    }

    async fn start_move_at(&self, target: f64, velocity: f64) -> Result<(), DeviceError> {
        check_limits(&self.name, self.effective_limits(), target, "start_move_at")?;
        if !(velocity.is_finite() && velocity > 0.0) {
            return Err(DeviceError::Rejected {
                device: self.name.clone(),
                command: "start_move_at".into(),
                reason: format!("velocity {velocity}: must be finite and > 0"),
            });
        }
        let (homed, last) = {
            let s = self.lock();
            (s.homed, s.last)
        };
        if !homed {
            return Err(DeviceError::NotHomed {
                device: self.name.clone(),
                command: "start_move_at".into(),
            });
        }
        let from = match last {
            Some(x) => x,
            None => self.poll("start_move_at").await?.position,
        };
        // A flight is one leg at the asked velocity: no backlash overshoot (the flown
        // poses are read back, not assumed), and the rig file's acceleration, which the
        // planner rounded the way the controller will (`serial::flight_profile`).
        let accel = self.motion.acceleration;
        let cmd = self.driver.describe_move_at(target, velocity, accel);
        self.call(&cmd, move |d| d.move_abs_at(target, velocity, accel)).await?;
        self.lock().pending = Some(Pending {
            target,
            legs: VecDeque::new(),
            current: Some((from, target, cmd, Instant::now())),
            corrections: 0,
            flight: Some(velocity),
        });
        Ok(())
    }

    async fn position(&self) -> Result<f64, DeviceError> {
        let p = self.poll("get position").await?;
        self.lock().last = Some(p.position);
        Ok(p.position)
    }

    async fn reference_position(&self) -> Result<Option<f64>, DeviceError> {
        self.call("get reference", |d| d.reference()).await
    }

    async fn status(&self) -> Result<AxisStatus, DeviceError> {
        let p = self.poll("get status").await?;
        let mut s = self.lock();
        s.last = Some(p.position);
        Ok(AxisStatus {
            homed: s.homed,
            moving: p.busy,
            position: p.position,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A driver simulating a stage in wall time, with switchable misbehaviour.
    #[derive(Default)]
    struct FakeStage {
        s: Mutex<Fake>,
    }
    #[derive(Default)]
    struct Fake {
        pos: f64,
        from: f64,
        to: f64,
        t0: Option<Instant>,
        speed: f64,
        /// Stops moving at this position (a jammed stage that still says BUSY).
        jam_at: Option<f64>,
        /// Lands this far from the target.
        offset: f64,
        /// Number of next polls that fail with a garbled reply.
        garble_polls: u32,
        moves: Vec<f64>,
        stops: u32,
    }
    impl FakeStage {
        fn new(speed: f64) -> Self {
            let f = FakeStage::default();
            f.s.lock().unwrap().speed = speed;
            f
        }
        fn update(f: &mut Fake) -> bool {
            let Some(t0) = f.t0 else { return false };
            let d = f.to - f.from;
            let travelled = (t0.elapsed().as_secs_f64() * f.speed).min(d.abs());
            let mut p = f.from + d.signum() * travelled;
            if let Some(j) = f.jam_at {
                if (p - f.from).abs() >= (j - f.from).abs() && (j - f.from) * d > 0.0 {
                    f.pos = j;
                    return true;
                }
            }
            if travelled >= d.abs() {
                p = f.to + f.offset;
                f.t0 = None;
            }
            f.pos = p;
            f.t0.is_some()
        }
    }
    impl Driver for FakeStage {
        fn home(&self) -> Result<(), DeviceError> {
            let mut f = self.s.lock().unwrap();
            f.pos = 0.0;
            Ok(())
        }
        fn move_abs(&self, target: f64) -> Result<(), DeviceError> {
            let mut f = self.s.lock().unwrap();
            Self::update(&mut f);
            f.moves.push(target);
            f.from = f.pos;
            f.to = target;
            f.t0 = Some(Instant::now());
            Ok(())
        }
        fn poll(&self, during: &str) -> Result<Poll, DeviceError> {
            let mut f = self.s.lock().unwrap();
            if f.garble_polls > 0 {
                f.garble_polls -= 1;
                return Err(DeviceError::Garbled {
                    device: "fake".into(),
                    command: during.into(),
                    reply: "@0\u{1}".into(),
                });
            }
            let busy = Self::update(&mut f);
            Ok(Poll { busy, position: f.pos })
        }
        fn stop(&self) -> Result<(), DeviceError> {
            let mut f = self.s.lock().unwrap();
            f.stops += 1;
            f.t0 = None;
            f.jam_at = None;
            Ok(())
        }
        fn device_limits(&self) -> Result<Option<SoftLimits>, DeviceError> {
            Ok(None)
        }
        fn resolution(&self) -> f64 {
            1e-6
        }
        fn describe_move(&self, target: f64) -> String {
            format!("fake move {target}")
        }
    }

    fn model(settle: f64) -> MotionModel {
        MotionModel {
            max_velocity: 10.0,
            acceleration: 100.0,
            jerk: None,
            settle_time: settle,
            deadband: 1e-3,
        }
    }

    fn policy() -> MotionPolicy {
        MotionPolicy {
            poll_interval: Duration::from_millis(2),
            timeout_floor_s: 0.3,
            stall_s: 0.15,
            ..MotionPolicy::default()
        }
    }

    fn axis(stage: FakeStage, p: MotionPolicy, settle: f64) -> PolicyAxis<FakeStage> {
        PolicyAxis::new("fake", SoftLimits { min: -5.0, max: 5.0 }, model(settle), p, stage)
    }

    #[tokio::test]
    async fn move_settles_and_reads_back_within_deadband() {
        let a = axis(FakeStage::new(10.0), policy(), 0.05);
        assert!(matches!(a.start_move(1.0).await, Err(DeviceError::NotHomed { .. })));
        a.home().await.unwrap();
        let t = Instant::now();
        let rb = a.move_abs(0.5).await.unwrap();
        assert!((rb - 0.5).abs() <= 1e-3);
        assert!(
            t.elapsed() >= Duration::from_millis(50 + 40),
            "motion + settle: {:?}",
            t.elapsed()
        );
        // a tiny move sends nothing
        a.move_abs(0.5 + 1e-4).await.unwrap();
        assert_eq!(a.driver().s.lock().unwrap().moves, vec![0.5]);
        // soft limits checked before anything moves
        let e = a.start_move(6.0).await.unwrap_err();
        assert!(matches!(e, DeviceError::SoftLimit { .. }), "{e}");
    }

    #[tokio::test]
    async fn backlash_approaches_from_below() {
        let p = MotionPolicy {
            backlash: 0.2,
            ..policy()
        };
        let a = axis(FakeStage::new(50.0), p, 0.0);
        a.home().await.unwrap();
        a.move_abs(1.0).await.unwrap(); // from below: one leg
        a.move_abs(0.5).await.unwrap(); // from above: overshoot to 0.3, then 0.5
        let moves = a.driver().s.lock().unwrap().moves.clone();
        assert_eq!(moves.len(), 3, "{moves:?}");
        assert!(
            (moves[1] - 0.3).abs() < 1e-12 && (moves[2] - 0.5).abs() < 1e-12,
            "{moves:?}"
        );
    }

    #[tokio::test]
    async fn stall_is_detected_and_axis_stopped() {
        let s = FakeStage::new(10.0);
        s.s.lock().unwrap().jam_at = Some(0.2);
        let a = axis(s, policy(), 0.0);
        a.home().await.unwrap();
        let e = a.move_abs(2.0).await.unwrap_err();
        match &e {
            DeviceError::Stall {
                device,
                command,
                position,
            } => {
                assert_eq!(device, "fake");
                assert!(command.contains("fake move 2"), "{command}");
                assert!((position - 0.2).abs() < 1e-9);
            }
            other => panic!("expected a stall, got {other}"),
        }
        assert_eq!(a.driver().s.lock().unwrap().stops, 1);
    }

    #[tokio::test]
    async fn slow_stage_times_out_from_the_motion_model() {
        // the model says 10 units/s, the stage does 1: 2 units take 2 s > 1.5 × 0.3 s + 0.3 s
        let a = axis(FakeStage::new(1.0), policy(), 0.0);
        a.home().await.unwrap();
        let t = Instant::now();
        let e = a.move_abs(2.0).await.unwrap_err();
        assert!(matches!(e, DeviceError::Timeout { .. }), "{e}");
        assert!(t.elapsed() < Duration::from_millis(1500), "{:?}", t.elapsed());
    }

    #[tokio::test]
    async fn missed_target_is_recommanded_then_reported() {
        let s = FakeStage::new(100.0);
        s.s.lock().unwrap().offset = 0.01; // always lands 0.01 off (> deadband 1e-3)
        let a = axis(s, policy(), 0.0);
        a.home().await.unwrap();
        let e = a.move_abs(1.0).await.unwrap_err();
        match e {
            DeviceError::MissedTarget { target, read_back, .. } => {
                assert_eq!(target, 1.0);
                assert!((read_back - 1.01).abs() < 1e-9);
            }
            other => panic!("expected MissedTarget, got {other}"),
        }
        // initial move + `retries` (2) corrections
        assert_eq!(a.driver().s.lock().unwrap().moves.len(), 3);
    }

    #[tokio::test]
    async fn transient_poll_errors_are_retried_within_bound() {
        let s = FakeStage::new(100.0);
        s.s.lock().unwrap().garble_polls = 2;
        let a = axis(s, policy(), 0.0);
        a.home().await.unwrap(); // two garbled polls, two retries: succeeds
        a.driver().s.lock().unwrap().garble_polls = 3;
        let e = a.position().await.unwrap_err();
        assert!(matches!(e, DeviceError::Garbled { .. }), "{e}");
    }
}
