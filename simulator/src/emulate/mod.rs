//! Motor-controller and lamp-supply emulators served over pseudo-terminals.
//!
//! Nobody here owns a Zaber or Newport controller, so gonio's serial drivers and the vendors'
//! own client software (zaber-motion, PyMeasure) are proven against these emulators: each
//! opens a pty pair, hands out the slave path (`/dev/pts/N`) and answers the vendor's wire
//! protocol on the master side, with axes that move in real (wall-clock) time along the
//! simulator's motion model ([`gonio_devices::MotionModel`], trapezoidal profile), so a client
//! sees BUSY while an axis moves and IDLE after.
//!
//! - [`zaber`]: the Zaber ASCII protocol (daisy chain, message ids, checksums, warning flags).
//! - [`esp300`]: the Newport ESP300/ESP301 command set (error queue, `MD?`, `TP`, …).
//! - [`hmp`]: a Rohde & Schwarz HMP4040 power supply (SCPI) with a halogen lamp load
//!   (`gonio sim serve-light`).
//! - [`faults`]: injected faults (garbled/dropped/slow replies, stall, limit switch,
//!   disconnect) so drivers can be tested against every failure they must survive.
//! - [`pty`]: the pty pair.
//!
//! Every received line is logged at `debug` level (target `gonio_simulator::emulate`) and kept
//! in [`EmulatorHandle::received`], so tests and humans can see exactly what a client sent.

pub mod esp300;
pub mod faults;
pub mod hmp;
pub mod pty;
pub mod zaber;

pub use faults::{Fault, FaultParseError, FaultPlan, MoveFault, Trigger};

use gonio_devices::MotionModel;
use serde::{Deserialize, Serialize};
use std::io;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Which controller to emulate.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Protocol {
    /// Zaber ASCII protocol (X-series controllers and integrated stages).
    Zaber,
    /// Newport ESP300 / ESP301 motion controller.
    Esp300,
    /// Rohde & Schwarz HMP4040 power supply with a lamp on each channel (`axes` = channels).
    Hmp4040,
}

impl std::fmt::Display for Protocol {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Protocol::Zaber => "zaber",
            Protocol::Esp300 => "esp300",
            Protocol::Hmp4040 => "hmp4040",
        })
    }
}

/// How to run one emulator.
#[derive(Clone, Debug)]
pub struct EmulatorConfig {
    pub protocol: Protocol,
    /// Axes per device (Zaber) or per controller (ESP: 1 ..= 3).
    pub axes: usize,
    /// Zaber daisy chain length: devices get addresses 1 ..= devices. The ESP ignores it.
    pub devices: usize,
    pub faults: FaultPlan,
    /// Controller units per degree: Zaber native units (microsteps), ESP user units. Default
    /// 1000 for Zaber (a real X-RSW60A has 4266.67 µsteps/°), 1 for the ESP (degrees).
    pub units_per_deg: f64,
    /// Motion model of every axis, in degrees (°/s, °/s²); the settle time is not the
    /// controller's business (the driver waits it), so the emulator ignores it.
    pub motion: MotionModel,
    /// Travel range in degrees (Zaber `limit.min/max`, ESP `SL/SR`); home is 0°.
    pub range_deg: (f64, f64),
    /// Axes start homed (referenced) instead of with an unknown position.
    pub start_homed: bool,
    /// Load axis positions from this JSON file at start (if it exists) and save them on every
    /// move and on stop/disconnect: an "emulator restart" keeps the stage where it was.
    pub state_file: Option<PathBuf>,
    /// Keep a symlink here pointing at the current slave path (stable name across reconnects,
    /// like socat's `link=`).
    pub link: Option<PathBuf>,
    /// After an injected disconnect, open a new pty after this delay (and re-point `link`)
    /// instead of ending the emulator.
    pub reconnect_after: Option<Duration>,
    /// Opt-in mechanical error model of every axis (Zaber only; see [`crate::mechanics`]):
    /// `get encoder.pos` then reads the load side while `get pos` stays the step count.
    /// Axis `k` of the chain (0-based, in state-file order) uses seed `seed + k`, so the
    /// axes scatter independently.
    pub mechanical: Option<crate::mechanics::MechanicalErrors>,
    /// The lamp on each channel of the power-supply emulator (HMP only).
    pub lamp: hmp::LampLoad,
}

impl EmulatorConfig {
    /// Sensible defaults for `protocol` with `axes` axes: 90 °/s, 720 °/s², ±180°, no faults.
    pub fn new(protocol: Protocol, axes: usize) -> Self {
        Self {
            protocol,
            axes,
            devices: 1,
            faults: FaultPlan::none(),
            units_per_deg: match protocol {
                Protocol::Zaber => 1000.0,
                Protocol::Esp300 | Protocol::Hmp4040 => 1.0,
            },
            motion: MotionModel {
                max_velocity: 90.0,
                acceleration: 720.0,
                jerk: None,
                settle_time: 0.0,
                deadband: 0.0,
            },
            range_deg: (-180.0, 180.0),
            start_homed: false,
            state_file: None,
            link: None,
            reconnect_after: None,
            mechanical: None,
            lamp: hmp::LampLoad::default(),
        }
    }

    /// Builder-style: set the fault plan.
    pub fn with_faults(mut self, faults: FaultPlan) -> Self {
        self.faults = faults;
        self
    }

    fn validate(&self) -> io::Result<()> {
        let bad = |m: String| Err(io::Error::new(io::ErrorKind::InvalidInput, m));
        let max_axes = match self.protocol {
            Protocol::Zaber => 9,
            Protocol::Esp300 => 3,
            Protocol::Hmp4040 => 4,
        };
        if self.protocol == Protocol::Hmp4040 {
            self.lamp
                .validate()
                .map_err(|m| io::Error::new(io::ErrorKind::InvalidInput, m))?;
            if let Some(f) = self.faults.faults.iter().find(|f| {
                !matches!(
                    f,
                    faults::Fault::Garble(_) | faults::Fault::Drop(_) | faults::Fault::Slow { .. }
                )
            }) {
                return bad(format!(
                    "hmp4040 emulator: fault `{f}` is a motion fault; a power supply takes garble, drop, slow"
                ));
            }
        }
        if self.axes == 0 || self.axes > max_axes {
            return bad(format!(
                "{} emulator: {} axes (valid 1 ..= {max_axes})",
                self.protocol, self.axes
            ));
        }
        if self.devices == 0 || self.devices > 99 {
            return bad(format!(
                "{} emulator: {} devices (valid 1 ..= 99)",
                self.protocol, self.devices
            ));
        }
        if !(self.units_per_deg.is_finite() && self.units_per_deg > 0.0) {
            return bad(format!(
                "{} emulator: units per degree {} (must be > 0)",
                self.protocol, self.units_per_deg
            ));
        }
        let m = &self.motion;
        if !(m.max_velocity > 0.0 && m.acceleration > 0.0 && m.max_velocity.is_finite() && m.acceleration.is_finite()) {
            return bad(format!(
                "{} emulator: velocity and acceleration must be > 0",
                self.protocol
            ));
        }
        let (lo, hi) = self.range_deg;
        if !(lo.is_finite() && hi.is_finite() && lo <= 0.0 && 0.0 <= hi && lo < hi) {
            return bad(format!(
                "{} emulator: range {lo}..{hi}° must contain home (0°)",
                self.protocol
            ));
        }
        Ok(())
    }
}

/// Positions that survive an emulator restart (see [`EmulatorConfig::state_file`]).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct EmulatorState {
    /// Every axis in order (device 1 axis 1, device 1 axis 2, …, device 2 axis 1, …).
    pub axes: Vec<AxisState>,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AxisState {
    /// Position in controller units.
    pub pos: f64,
    pub homed: bool,
}

impl EmulatorState {
    fn load(path: &Path) -> Option<Self> {
        let text = std::fs::read_to_string(path).ok()?;
        match serde_json::from_str(&text) {
            Ok(s) => Some(s),
            Err(e) => {
                tracing::warn!("emulator state {}: {e}; starting fresh", path.display());
                None
            }
        }
    }

    fn save(&self, path: &Path) {
        let tmp = path.with_extension("tmp");
        let res = serde_json::to_vec_pretty(self)
            .map_err(io::Error::other)
            .and_then(|b| std::fs::write(&tmp, b))
            .and_then(|_| std::fs::rename(&tmp, path));
        if let Err(e) = res {
            tracing::warn!("emulator state {}: cannot save: {e}", path.display());
        }
    }
}

/// How a move ends (decided when it starts, from the fault plan).
#[derive(Clone, Copy, Debug, PartialEq)]
enum MoveEnd {
    Normal,
    /// Frozen half way, still "moving".
    Stall,
    /// Stopped half way by a limit switch.
    Limit,
    /// Stalled half way, noticed and stopped by the controller.
    StallStop,
}

/// What an axis is doing: the three profiles a controller runs.
#[derive(Clone, Copy, Debug)]
enum Kind {
    /// A trapezoidal move to `target` (controller units) under `model` (degrees: the axis'
    /// own, or the move's own speed and acceleration).
    To { target: f64, model: MotionModel },
    /// A velocity move (Zaber `move vel`): accelerate at `accel` to `velocity` (controller
    /// units/s², signed units/s) and keep going until a travel limit.
    Vel { velocity: f64, accel: f64 },
    /// A decelerating stop from `velocity` (signed units/s) at `accel` (units/s²): the axis
    /// is busy until it has come to rest, as a real stage is.
    Decel { velocity: f64, accel: f64 },
}

#[derive(Clone, Copy, Debug)]
struct Motion {
    start_pos: f64,
    start: Instant,
    end: MoveEnd,
    kind: Kind,
}

/// Something that happened to an axis since the controller last looked.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum AxisEvent {
    /// Limit switch hit while moving in the positive (`true`) or negative direction.
    LimitHit { positive: bool },
    /// The controller detected a stall and stopped the axis.
    Stalled,
}

/// One emulated axis: position in controller units moving in wall-clock time.
#[derive(Clone, Debug)]
pub(crate) struct EmuAxis {
    pos: f64,
    pub homed: bool,
    /// Motor power (ESP `MO`/`MF`); Zaber axes are always enabled.
    pub enabled: bool,
    motion: Option<Motion>,
    /// Motion model in degrees.
    model: MotionModel,
    upd: f64,
    /// Travel limits in controller units.
    pub min: f64,
    pub max: f64,
    events: Vec<AxisEvent>,
    /// Mechanical error model (load side vs. step count); `None`: ideal.
    mech: Option<crate::mechanics::MechanicalState>,
}

impl EmuAxis {
    pub(crate) fn new(cfg: &EmulatorConfig, state: Option<AxisState>) -> Self {
        let (pos, homed) = state.map(|s| (s.pos, s.homed)).unwrap_or((0.0, cfg.start_homed));
        Self {
            pos,
            homed,
            enabled: false,
            motion: None,
            model: cfg.motion,
            upd: cfg.units_per_deg,
            min: cfg.range_deg.0 * cfg.units_per_deg,
            max: cfg.range_deg.1 * cfg.units_per_deg,
            events: Vec::new(),
            mech: None,
        }
    }

    /// Give this axis a mechanical error model.
    pub(crate) fn set_mechanics(&mut self, model: crate::mechanics::MechanicalErrors) {
        self.mech = Some(crate::mechanics::MechanicalState::new(model));
    }

    /// A homing cycle for the error model: a new zero offset (call after the homing move
    /// has been started).
    pub(crate) fn home_mechanics(&mut self) {
        if let Some(m) = &mut self.mech {
            m.home();
        }
    }

    /// The load-side position in controller units (what a load-side encoder counts).
    pub(crate) fn encoder_position(&self, now: Instant) -> f64 {
        let p = self.position(now);
        match &self.mech {
            Some(m) if !m.model.is_zero() => m.true_deg(p / self.upd) * self.upd,
            _ => p,
        }
    }

    /// Seconds the profile of `m` lasts, if nothing goes wrong.
    fn profile_secs(&self, m: &Motion) -> f64 {
        match m.kind {
            Kind::To { target, model } => model.profile_time((target - m.start_pos) / self.upd),
            Kind::Vel { velocity, accel } => {
                // until the travel limit in the direction of motion
                let room = if velocity >= 0.0 {
                    self.max - m.start_pos
                } else {
                    m.start_pos - self.min
                }
                .max(0.0);
                let v = velocity.abs();
                if v <= 0.0 {
                    return 0.0;
                }
                let ramp = v * v / (2.0 * accel);
                if room < ramp {
                    (2.0 * room / accel).sqrt()
                } else {
                    v / accel + (room - ramp) / v
                }
            }
            Kind::Decel { velocity, accel } => velocity.abs() / accel,
        }
    }

    /// Seconds after its start at which a move stops (∞ for a stall: it never ends).
    fn stop_secs(&self, m: &Motion) -> f64 {
        let total = self.profile_secs(m);
        match m.end {
            MoveEnd::Normal => total,
            MoveEnd::Limit | MoveEnd::StallStop => total / 2.0,
            MoveEnd::Stall => f64::INFINITY,
        }
    }

    /// Seconds into `m` at which the axis stops making progress (a fault freezes it half way).
    fn moving_secs(&self, m: &Motion, t: f64) -> f64 {
        match m.end {
            MoveEnd::Normal => t,
            MoveEnd::Limit | MoveEnd::Stall | MoveEnd::StallStop => t.min(self.profile_secs(m) / 2.0),
        }
    }

    fn position_of(&self, m: &Motion, now: Instant) -> f64 {
        let t = now.saturating_duration_since(m.start).as_secs_f64();
        let t = self.moving_secs(m, t);
        match m.kind {
            Kind::To { target, model } => {
                let dist_deg = (target - m.start_pos) / self.upd;
                m.start_pos + model.position_at(dist_deg, t) * self.upd
            }
            Kind::Vel { velocity, accel } => {
                let t = t.min(self.profile_secs(m));
                let v = velocity.abs();
                let t_acc = v / accel;
                let d = if t < t_acc {
                    0.5 * accel * t * t
                } else {
                    0.5 * accel * t_acc * t_acc + v * (t - t_acc)
                };
                (m.start_pos + velocity.signum() * d).clamp(self.min, self.max)
            }
            Kind::Decel { velocity, accel } => {
                let t = t.min(self.profile_secs(m));
                m.start_pos + velocity * t - velocity.signum() * 0.5 * accel * t * t
            }
        }
    }

    /// Signed velocity (units/s) of `m` at `now`: what a stop decelerates from.
    fn velocity_of(&self, m: &Motion, now: Instant) -> f64 {
        let t_all = now.saturating_duration_since(m.start).as_secs_f64();
        let t = self.moving_secs(m, t_all);
        if t < t_all || t >= self.profile_secs(m) {
            return 0.0; // frozen by a fault, or at rest
        }
        match m.kind {
            Kind::To { target, model } => {
                let d = ((target - m.start_pos) / self.upd).abs();
                let s = (target - m.start_pos).signum();
                let (a, v) = (model.acceleration, model.max_velocity);
                let total = model.profile_time(d);
                let (t_acc, v_peak) = if d < v * v / a {
                    ((d / a).sqrt(), (d * a).sqrt())
                } else {
                    (v / a, v)
                };
                let deg_s = if t < t_acc {
                    a * t
                } else if t < total - t_acc {
                    v_peak
                } else {
                    a * (total - t).max(0.0)
                };
                s * deg_s * self.upd
            }
            Kind::Vel { velocity, accel } => velocity.signum() * (accel * t).min(velocity.abs()),
            Kind::Decel { velocity, accel } => velocity.signum() * (velocity.abs() - accel * t).max(0.0),
        }
    }

    /// Fold a finished move into the resting position and raise its events.
    pub(crate) fn update(&mut self, now: Instant) {
        if let Some(m) = self.motion {
            let t = now.saturating_duration_since(m.start).as_secs_f64();
            if t >= self.stop_secs(&m) {
                self.pos = self.position_of(&m, now);
                let positive = match m.kind {
                    Kind::To { target, .. } => target > m.start_pos,
                    Kind::Vel { velocity, .. } | Kind::Decel { velocity, .. } => velocity > 0.0,
                };
                match m.end {
                    MoveEnd::Limit => self.events.push(AxisEvent::LimitHit { positive }),
                    MoveEnd::StallStop => self.events.push(AxisEvent::Stalled),
                    MoveEnd::Normal | MoveEnd::Stall => {}
                }
                self.motion = None;
            }
        }
    }

    pub(crate) fn take_events(&mut self) -> Vec<AxisEvent> {
        std::mem::take(&mut self.events)
    }

    pub(crate) fn position(&self, now: Instant) -> f64 {
        match &self.motion {
            Some(m) => self.position_of(m, now),
            None => self.pos,
        }
    }

    pub(crate) fn busy(&self, now: Instant) -> bool {
        match &self.motion {
            Some(m) => now.saturating_duration_since(m.start).as_secs_f64() < self.stop_secs(m),
            None => false,
        }
    }

    /// Where the axis will rest if nothing goes wrong (its target while moving).
    pub(crate) fn destination(&self, now: Instant) -> f64 {
        match self.motion {
            Some(m) if m.end == MoveEnd::Normal => match m.kind {
                Kind::To { target, .. } => target,
                // where a decelerating stop comes to rest
                Kind::Decel { velocity, accel } => m.start_pos + velocity * velocity.abs() / (2.0 * accel),
                Kind::Vel { .. } => self.position(now),
            },
            _ => self.position(now),
        }
    }

    /// Stop where the axis is now; true if it was moving.
    pub(crate) fn stop(&mut self, now: Instant) -> bool {
        self.update(now);
        let was = self.motion.is_some();
        self.pos = self.position(now);
        self.motion = None;
        if let Some(m) = &mut self.mech {
            m.fold(self.pos / self.upd);
        }
        was
    }

    /// Come to rest at the deceleration `accel` (controller units/s²) from wherever the
    /// axis is and however fast it moves (Zaber `stop`, ESP `ST`): busy until at rest.
    /// Returns true if the axis was moving.
    pub(crate) fn decelerate(&mut self, now: Instant, accel: f64) -> bool {
        self.update(now);
        let Some(m) = self.motion else { return false };
        let velocity = self.velocity_of(&m, now);
        if velocity == 0.0 || !(accel.is_finite() && accel > 0.0) {
            return self.stop(now);
        }
        self.pos = self.position(now);
        if let Some(mech) = &mut self.mech {
            mech.fold(self.pos / self.upd);
        }
        self.motion = Some(Motion {
            start_pos: self.pos,
            start: now,
            end: MoveEnd::Normal,
            kind: Kind::Decel { velocity, accel },
        });
        true
    }

    /// The axis' own acceleration in controller units/s².
    pub(crate) fn acceleration_units(&self) -> f64 {
        self.model.acceleration * self.upd
    }

    /// Start a move to `target` (controller units) from wherever the axis is now.
    /// Returns true if a move in progress was interrupted.
    pub(crate) fn start(&mut self, target: f64, now: Instant, fault: Option<MoveFault>) -> bool {
        self.start_with(target, now, fault, None)
    }

    /// [`Self::start`] with the move's own velocity and acceleration (degrees/s, /s²)
    /// instead of the axis' settings (Zaber `move abs X SPEED ACCEL`); the move still
    /// starts from rest (a move in progress is interrupted, not blended).
    pub(crate) fn start_with(
        &mut self,
        target: f64,
        now: Instant,
        fault: Option<MoveFault>,
        profile: Option<(f64, f64)>,
    ) -> bool {
        let interrupted = self.stop(now);
        let end = match fault {
            Some(MoveFault::Stall) => MoveEnd::Stall,
            Some(MoveFault::LimitSwitch) => MoveEnd::Limit,
            Some(MoveFault::StallStop) => MoveEnd::StallStop,
            _ => MoveEnd::Normal,
        };
        let mut model = self.model;
        if let Some((v, a)) = profile {
            model.max_velocity = v;
            model.acceleration = a;
        }
        if (target - self.pos).abs() > 0.0 || end != MoveEnd::Normal {
            self.motion = Some(Motion {
                start_pos: self.pos,
                start: now,
                end,
                kind: Kind::To { target, model },
            });
        }
        interrupted
    }

    /// Start a velocity move (signed controller units/s, acceleration in units/s²) from
    /// rest; a zero velocity decelerates to a stop. Returns true if a move was interrupted.
    pub(crate) fn start_velocity(&mut self, velocity: f64, accel: f64, now: Instant) -> bool {
        if velocity == 0.0 {
            return self.decelerate(now, accel);
        }
        let interrupted = self.stop(now);
        self.motion = Some(Motion {
            start_pos: self.pos,
            start: now,
            end: MoveEnd::Normal,
            kind: Kind::Vel { velocity, accel },
        });
        interrupted
    }

    /// Redefine the current position (ESP `DH`).
    pub(crate) fn define_position(&mut self, value: f64, now: Instant) {
        self.stop(now);
        self.pos = value;
    }

    pub(crate) fn state(&self, now: Instant) -> AxisState {
        AxisState {
            pos: self.destination(now),
            homed: self.homed,
        }
    }

    pub(crate) fn units_per_deg(&self) -> f64 {
        self.upd
    }

    pub(crate) fn model(&self) -> &MotionModel {
        &self.model
    }

    pub(crate) fn model_mut(&mut self) -> &mut MotionModel {
        &mut self.model
    }
}

/// What a controller does in answer to one line.
#[derive(Debug, Default, PartialEq)]
pub struct Handled {
    /// Reply lines, without terminator.
    pub replies: Vec<String>,
    /// Close the pty now (injected disconnect): nothing of this command was executed.
    pub disconnect: bool,
}

/// A protocol engine: text lines in, text lines out. Pure apart from the clock, so it is
/// unit-tested without a pty.
pub trait Controller: Send {
    /// Answer one received line (terminator stripped, may be empty or garbage: never panic).
    fn handle(&mut self, line: &str, now: Instant) -> Handled;
    /// Positions for the state file.
    fn state(&self, now: Instant) -> EmulatorState;
    /// Is any axis still moving? (Used to finish moves before saving state on stop.)
    fn busy(&self, now: Instant) -> bool;
}

/// Build the protocol engine for a config (no pty): what tests and benches drive directly.
pub fn controller(config: &EmulatorConfig, state: Option<EmulatorState>) -> io::Result<Box<dyn Controller>> {
    config.validate()?;
    Ok(match config.protocol {
        Protocol::Zaber => Box::new(zaber::Zaber::new(config, state)),
        Protocol::Esp300 => Box::new(esp300::Esp300::new(config, state)),
        Protocol::Hmp4040 => Box::new(hmp::Hmp::new(config)),
    })
}

#[derive(Debug)]
struct Shared {
    stop: AtomicBool,
    current_path: Mutex<PathBuf>,
    received: Mutex<Vec<String>>,
    disconnects: AtomicU64,
    finished: AtomicBool,
    state: Mutex<EmulatorState>,
}

/// A running emulator (one thread). Dropping it stops the emulator too.
#[derive(Debug)]
pub struct EmulatorHandle {
    path: PathBuf,
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
}

impl EmulatorHandle {
    /// The slave path of the first pty (`/dev/pts/N`): what a client opens.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The slave path of the pty in use now (differs from [`Self::path`] after a reconnect).
    pub fn current_path(&self) -> PathBuf {
        self.shared.current_path.lock().map(|p| p.clone()).unwrap_or_default()
    }

    /// Every line received so far (terminators stripped), in order.
    pub fn received(&self) -> Vec<String> {
        self.shared.received.lock().map(|r| r.clone()).unwrap_or_default()
    }

    /// How many injected disconnects have happened.
    pub fn disconnects(&self) -> u64 {
        self.shared.disconnects.load(Ordering::SeqCst)
    }

    /// True once the emulator thread has ended (stopped, or disconnected without reconnect).
    pub fn is_finished(&self) -> bool {
        self.shared.finished.load(Ordering::SeqCst)
    }

    /// Axis positions as of the last command handled (or the end of the emulator).
    pub fn state(&self) -> EmulatorState {
        self.shared.state.lock().map(|s| s.clone()).unwrap_or_default()
    }

    /// Stop serving, close the pty, save the state file; waits for the thread.
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for EmulatorHandle {
    fn drop(&mut self) {
        self.shutdown();
    }
}

fn update_link(link: &Option<PathBuf>, target: &Path) {
    if let Some(link) = link {
        let _ = std::fs::remove_file(link);
        if let Err(e) = std::os::unix::fs::symlink(target, link) {
            tracing::warn!("emulator link {} → {}: {e}", link.display(), target.display());
        }
    }
}

/// Open a pty and serve `config.protocol` on it in a new thread.
///
/// Returns once the pty exists, so the path can be handed to a client immediately.
pub fn spawn_pty(config: EmulatorConfig) -> io::Result<EmulatorHandle> {
    let state = config.state_file.as_deref().and_then(EmulatorState::load);
    let ctrl = controller(&config, state)?;
    let pty = pty::Pty::open()?;
    let path = pty.slave_path().to_path_buf();
    update_link(&config.link, &path);
    let shared = Arc::new(Shared {
        stop: AtomicBool::new(false),
        current_path: Mutex::new(path.clone()),
        received: Mutex::new(Vec::new()),
        disconnects: AtomicU64::new(0),
        finished: AtomicBool::new(false),
        state: Mutex::new(ctrl.state(Instant::now())),
    });
    tracing::info!(
        "{} emulator ({} axes or channels) on {}",
        config.protocol,
        config.axes,
        path.display()
    );
    let sh = shared.clone();
    let thread = std::thread::Builder::new()
        .name(format!("emulate-{}", config.protocol))
        .spawn(move || run(config, ctrl, pty, sh))?;
    Ok(EmulatorHandle {
        path,
        shared,
        thread: Some(thread),
    })
}

/// Counters that the reply faults key on; they live across reconnects.
#[derive(Default)]
struct Counters {
    commands: u64,
    replies: u64,
}

enum ServeEnd {
    Stopped,
    Disconnected,
}

fn run(config: EmulatorConfig, mut ctrl: Box<dyn Controller>, mut pty: pty::Pty, shared: Arc<Shared>) {
    let mut counters = Counters::default();
    loop {
        let end = serve(&config, ctrl.as_mut(), &pty, &shared, &mut counters);
        let now = Instant::now();
        let st = ctrl.state(now);
        if let Some(f) = &config.state_file {
            st.save(f);
        }
        if let Ok(mut s) = shared.state.lock() {
            *s = st;
        }
        match end {
            ServeEnd::Stopped => break,
            ServeEnd::Disconnected => {
                shared.disconnects.fetch_add(1, Ordering::SeqCst);
                tracing::warn!("{}: injected disconnect, pty closed", pty.slave_path().display());
                drop(pty);
                if let Some(link) = &config.link {
                    let _ = std::fs::remove_file(link);
                }
                let Some(after) = config.reconnect_after else { break };
                let until = Instant::now() + after;
                while Instant::now() < until && !shared.stop.load(Ordering::SeqCst) {
                    std::thread::sleep(Duration::from_millis(10));
                }
                if shared.stop.load(Ordering::SeqCst) {
                    break;
                }
                match pty::Pty::open() {
                    Ok(p) => {
                        pty = p;
                        update_link(&config.link, pty.slave_path());
                        if let Ok(mut c) = shared.current_path.lock() {
                            *c = pty.slave_path().to_path_buf();
                        }
                        tracing::info!(
                            "{} emulator reconnected on {}",
                            config.protocol,
                            pty.slave_path().display()
                        );
                    }
                    Err(e) => {
                        tracing::error!("{} emulator: cannot reopen a pty: {e}", config.protocol);
                        break;
                    }
                }
            }
        }
    }
    if let Some(link) = &config.link {
        let _ = std::fs::remove_file(link);
    }
    shared.finished.store(true, Ordering::SeqCst);
}

/// Longest line accepted; longer garbage is discarded (a real controller's buffer is small).
const MAX_LINE: usize = 1024;

fn serve(
    config: &EmulatorConfig,
    ctrl: &mut dyn Controller,
    pty: &pty::Pty,
    shared: &Shared,
    counters: &mut Counters,
) -> ServeEnd {
    let mut buf = [0u8; 4096];
    let mut line: Vec<u8> = Vec::new();
    let mut connected = false;
    while !shared.stop.load(Ordering::SeqCst) {
        let n = match pty.read(&mut buf, Duration::from_millis(50)) {
            Ok(pty::ReadOutcome::Data(n)) => n,
            Ok(pty::ReadOutcome::Idle) => continue,
            Ok(pty::ReadOutcome::NoClient) => {
                if connected {
                    tracing::debug!("{}: client closed the port", pty.slave_path().display());
                    connected = false;
                    line.clear();
                }
                std::thread::sleep(Duration::from_millis(20));
                continue;
            }
            Err(e) => {
                tracing::error!("{}: read failed: {e}", pty.slave_path().display());
                return ServeEnd::Stopped;
            }
        };
        if !connected {
            tracing::debug!("{}: client connected", pty.slave_path().display());
            connected = true;
        }
        for &b in &buf[..n] {
            if b != b'\r' && b != b'\n' {
                if line.len() < MAX_LINE {
                    line.push(b);
                }
                continue;
            }
            if line.is_empty() {
                continue;
            }
            let text = String::from_utf8_lossy(&line).into_owned();
            line.clear();
            counters.commands += 1;
            tracing::debug!(target: "gonio_simulator::emulate", "{} rx #{}: {text}", config.protocol, counters.commands);
            if let Ok(mut r) = shared.received.lock() {
                r.push(text.clone());
            }
            let now = Instant::now();
            let handled = ctrl.handle(&text, now);
            if let Ok(mut s) = shared.state.lock() {
                *s = ctrl.state(now);
            }
            if handled.disconnect {
                return ServeEnd::Disconnected;
            }
            if config.state_file.is_some() && text_moves(&text) {
                if let Some(f) = &config.state_file {
                    ctrl.state(now).save(f);
                }
            }
            for reply in handled.replies {
                counters.replies += 1;
                let fate = config.faults.reply_fate(counters.commands, counters.replies);
                if !fate.delay.is_zero() {
                    std::thread::sleep(fate.delay);
                }
                if fate.drop {
                    tracing::debug!("{} tx #{} dropped (fault): {reply}", config.protocol, counters.replies);
                    continue;
                }
                let mut bytes = if fate.garble {
                    faults::garble(reply.as_bytes())
                } else {
                    reply.clone().into_bytes()
                };
                tracing::debug!(
                    target: "gonio_simulator::emulate",
                    "{} tx: {}{}",
                    config.protocol,
                    reply,
                    if fate.garble { " (garbled)" } else { "" }
                );
                bytes.extend_from_slice(b"\r\n");
                match pty.write_all(&bytes) {
                    Ok(true) => {}
                    Ok(false) => tracing::debug!("{}: reply for a closed client discarded", config.protocol),
                    Err(e) => tracing::warn!("{}: write failed: {e}", pty.slave_path().display()),
                }
            }
        }
    }
    ServeEnd::Stopped
}

/// Cheap test whether a line may have changed a target (only used to decide when to save).
fn text_moves(text: &str) -> bool {
    let t = text.to_ascii_lowercase();
    t.contains("move")
        || t.contains("home")
        || t.contains("pa")
        || t.contains("pr")
        || t.contains("or")
        || t.contains("dh")
}

#[cfg(test)]
mod tests;
