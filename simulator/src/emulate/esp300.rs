//! The Newport ESP300/ESP301 command set, enough for gonio's driver and PyMeasure's `ESP300`.
//!
//! A line holds one or more commands separated by `;`. A command is `[axis]XX[?|params]`:
//! `1MO` (motor on), `1MF` (off), `1MO?`, `1OR[type]` (home search: here, move to 0),
//! `1PA x` / `1PR x` (absolute/relative move), `1TP` (position), `1MD?` (1 = motion done),
//! `1ST` / `ST` (stop one / all, decelerating at `AC`: motion is not done until the axis
//! is at rest), `AB` (abort: at once), `1WS[ms]` (wait for stop), `1DH[x]` (define
//! position), `1SL x` / `1SR x` (software limits), `1VA x` / `1AC x` and their queries,
//! `1SN?` (units: 7 = degree), `1ID?` (stage model), `1DP?` (desired position), `TE?` (pop
//! one error code), `TB?` (pop one error as `code, timestamp, MESSAGE`), `VE?` (firmware).
//!
//! Only queries answer; mistakes are not echoed but queued as error codes, as on the real
//! controller: general errors are 1–99 (6 command does not exist, 7 parameter out of range,
//! 9 axis number out of range, 37 axis number missing, 38 command parameter missing); axis
//! errors are `axis×100 + code` (x03 following error, x04/x05 positive/negative hardware limit, x06/x07
//! positive/negative software limit, x13 motor not enabled).

use super::{AxisEvent, EmuAxis, EmulatorConfig, EmulatorState, Handled};
use crate::emulate::faults::{FaultPlan, MoveFault};
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// Firmware string of `VE?`.
pub const EMULATED_VERSION: &str = "ESP300 Version 3.08 09/09/00 (gonio emulator)";
/// The controller keeps at most this many errors; older ones are lost.
const ERROR_QUEUE: usize = 10;
/// `WS` never blocks longer than this (a stalled axis would block forever otherwise).
const MAX_WAIT: Duration = Duration::from_secs(30);

/// Error codes.
pub mod code {
    pub const NONE: u32 = 0;
    pub const COMMAND_DOES_NOT_EXIST: u32 = 6;
    pub const PARAMETER_OUT_OF_RANGE: u32 = 7;
    pub const AXIS_OUT_OF_RANGE: u32 = 9;
    pub const AXIS_MISSING: u32 = 37;
    pub const PARAMETER_MISSING: u32 = 38;
    /// Axis error codes (added to axis × 100).
    pub const AXIS_PARAMETER_OUT_OF_RANGE: u32 = 1;
    pub const FOLLOWING_ERROR: u32 = 3;
    pub const POSITIVE_HARDWARE_LIMIT: u32 = 4;
    pub const NEGATIVE_HARDWARE_LIMIT: u32 = 5;
    pub const POSITIVE_SOFTWARE_LIMIT: u32 = 6;
    pub const NEGATIVE_SOFTWARE_LIMIT: u32 = 7;
    pub const MOTOR_NOT_ENABLED: u32 = 13;
}

/// The message of an error code, as `TB?` reports it.
pub fn message(c: u32) -> &'static str {
    if c >= 100 {
        return match c % 100 {
            code::AXIS_PARAMETER_OUT_OF_RANGE => "PARAMETER OUT OF RANGE",
            code::FOLLOWING_ERROR => "FOLLOWING ERROR THRESHOLD EXCEEDED",
            code::POSITIVE_HARDWARE_LIMIT => "POSITIVE HARDWARE LIMIT DETECTED",
            code::NEGATIVE_HARDWARE_LIMIT => "NEGATIVE HARDWARE LIMIT DETECTED",
            code::POSITIVE_SOFTWARE_LIMIT => "POSITIVE SOFTWARE LIMIT DETECTED",
            code::NEGATIVE_SOFTWARE_LIMIT => "NEGATIVE SOFTWARE LIMIT DETECTED",
            code::MOTOR_NOT_ENABLED => "MOTOR NOT ENABLED",
            _ => "UNKNOWN AXIS ERROR",
        };
    }
    match c {
        code::NONE => "NO ERROR DETECTED",
        code::COMMAND_DOES_NOT_EXIST => "COMMAND DOES NOT EXIST",
        code::PARAMETER_OUT_OF_RANGE => "PARAMETER OUT OF RANGE",
        code::AXIS_OUT_OF_RANGE => "AXIS NUMBER OUT OF RANGE",
        code::AXIS_MISSING => "AXIS NUMBER MISSING",
        code::PARAMETER_MISSING => "COMMAND PARAMETER MISSING",
        _ => "UNKNOWN ERROR",
    }
}

/// The ESP300 emulator.
pub struct Esp300 {
    axes: Vec<EmuAxis>,
    errors: VecDeque<(u32, u64)>,
    faults: FaultPlan,
    moves: u64,
    started: Instant,
}

/// One parsed command of a line.
#[derive(Debug, PartialEq)]
struct Cmd<'a> {
    axis: Option<u32>,
    mnemonic: String,
    query: bool,
    param: &'a str,
}

fn parse_one(s: &str) -> Option<Cmd<'_>> {
    let s = s.trim();
    let digits = s.bytes().take_while(u8::is_ascii_digit).count();
    let axis = if digits > 0 {
        Some(s[..digits].parse::<u32>().unwrap_or(u32::MAX))
    } else {
        None
    };
    let rest = &s[digits..];
    let mnemonic: String = rest.chars().take(2).collect();
    if mnemonic.chars().count() != 2 || !mnemonic.chars().all(|c| c.is_ascii_alphabetic()) {
        return None;
    }
    let rest = rest[2..].trim();
    let (query, param) = match rest.strip_prefix('?') {
        Some(r) => (true, r.trim()),
        None => (false, rest),
    };
    Some(Cmd {
        axis,
        mnemonic: mnemonic.to_ascii_uppercase(),
        query,
        param,
    })
}

fn fmt_num(v: f64) -> String {
    format!("{v:.5}")
}

enum Arg {
    Missing,
    Bad,
    Value(f64),
}

fn arg(param: &str) -> Arg {
    let p = param.trim();
    if p.is_empty() {
        return Arg::Missing;
    }
    match p.parse::<f64>() {
        Ok(v) if v.is_finite() => Arg::Value(v),
        _ => Arg::Bad,
    }
}

impl Esp300 {
    pub fn new(cfg: &EmulatorConfig, state: Option<EmulatorState>) -> Self {
        let mut saved = state.map(|s| s.axes).unwrap_or_default().into_iter();
        Self {
            axes: (0..cfg.axes).map(|_| EmuAxis::new(cfg, saved.next())).collect(),
            errors: VecDeque::new(),
            faults: cfg.faults.clone(),
            moves: 0,
            started: Instant::now(),
        }
    }

    fn push_error(&mut self, code: u32, now: Instant) {
        if self.errors.len() == ERROR_QUEUE {
            self.errors.pop_front();
        }
        let ts = now.saturating_duration_since(self.started).as_millis() as u64;
        self.errors.push_back((code, ts));
    }

    fn update(&mut self, now: Instant) {
        let mut errs = Vec::new();
        for (i, a) in self.axes.iter_mut().enumerate() {
            a.update(now);
            for e in a.take_events() {
                let c = match e {
                    AxisEvent::LimitHit { positive: true } => code::POSITIVE_HARDWARE_LIMIT,
                    AxisEvent::LimitHit { positive: false } => code::NEGATIVE_HARDWARE_LIMIT,
                    AxisEvent::Stalled => code::FOLLOWING_ERROR,
                };
                errs.push((i as u32 + 1) * 100 + c);
            }
        }
        for c in errs {
            self.push_error(c, now);
        }
    }

    fn busy(&self, now: Instant) -> bool {
        self.axes.iter().any(|a| a.busy(now))
    }

    /// Execute one command; `Err` = injected disconnect.
    fn exec(&mut self, c: &Cmd, now: Instant, out: &mut Vec<String>) -> Result<(), MoveFault> {
        let m = c.mnemonic.as_str();
        // Controller-level commands.
        match (m, c.axis) {
            ("TE", None) => {
                let e = self.errors.pop_front().map(|e| e.0).unwrap_or(code::NONE);
                out.push(e.to_string());
                return Ok(());
            }
            ("TB", None) => {
                let (e, ts) = self.errors.pop_front().unwrap_or((code::NONE, 0));
                out.push(format!("{e}, {ts}, {}", message(e)));
                return Ok(());
            }
            ("VE", None) => {
                out.push(EMULATED_VERSION.to_string());
                return Ok(());
            }
            ("ST", None) => {
                // A stop decelerates at each axis' AC (the axis is moving until at rest);
                // an abort stops at once.
                for a in &mut self.axes {
                    let accel = a.acceleration_units();
                    a.decelerate(now, accel);
                }
                return Ok(());
            }
            ("AB", None) => {
                for a in &mut self.axes {
                    a.stop(now);
                }
                return Ok(());
            }
            ("MO" | "MF", None) if !c.query => {
                for a in &mut self.axes {
                    a.stop(now);
                    a.enabled = m == "MO";
                }
                return Ok(());
            }
            ("TP", None) => {
                out.push(
                    self.axes
                        .iter()
                        .map(|a| fmt_num(a.position(now)))
                        .collect::<Vec<_>>()
                        .join(","),
                );
                return Ok(());
            }
            ("TE" | "TB" | "VE", Some(_)) => {
                self.push_error(code::COMMAND_DOES_NOT_EXIST, now);
                return Ok(());
            }
            _ => {}
        }
        const AXIS_CMDS: &[&str] = &[
            "MO", "MF", "OR", "PA", "PR", "TP", "MD", "ST", "AB", "WS", "DH", "SL", "SR", "VA", "AC", "SN", "ID", "DP",
            "TV",
        ];
        if !AXIS_CMDS.contains(&m) {
            self.push_error(code::COMMAND_DOES_NOT_EXIST, now);
            return Ok(());
        }
        let Some(n) = c.axis else {
            self.push_error(code::AXIS_MISSING, now);
            return Ok(());
        };
        if n == 0 || n as usize > self.axes.len() {
            self.push_error(code::AXIS_OUT_OF_RANGE, now);
            return Ok(());
        }
        let i = n as usize - 1;
        let axis_err = |c: u32| n * 100 + c;
        match (m, c.query) {
            ("MO", false) => self.axes[i].enabled = true,
            ("MF", false) => {
                self.axes[i].stop(now);
                self.axes[i].enabled = false;
            }
            ("MO", true) => out.push(u8::from(self.axes[i].enabled).to_string()),
            ("MD", true) => out.push(u8::from(!self.axes[i].busy(now)).to_string()),
            ("TP", _) => out.push(fmt_num(self.axes[i].position(now))),
            ("DP", true) => out.push(fmt_num(self.axes[i].destination(now))),
            ("TV", _) => out.push(fmt_num(if self.axes[i].busy(now) {
                self.axes[i].model().max_velocity
            } else {
                0.0
            })),
            ("ST", false) => {
                let accel = self.axes[i].acceleration_units();
                self.axes[i].decelerate(now, accel);
            }
            ("AB", false) => {
                self.axes[i].stop(now);
            }
            ("SN", true) => out.push("7".into()),
            ("ID", true) => out.push(format!("EMU-RV360 gonio emulator, SN{n:04}")),
            ("SL", true) => out.push(fmt_num(self.axes[i].min)),
            ("SR", true) => out.push(fmt_num(self.axes[i].max)),
            ("VA", true) => out.push(fmt_num(
                self.axes[i].model().max_velocity * self.axes[i].units_per_deg(),
            )),
            ("AC", true) => out.push(fmt_num(
                self.axes[i].model().acceleration * self.axes[i].units_per_deg(),
            )),
            ("SL" | "SR" | "VA" | "AC", false) => match arg(c.param) {
                Arg::Missing => self.push_error(code::PARAMETER_MISSING, now),
                Arg::Bad => self.push_error(code::PARAMETER_OUT_OF_RANGE, now),
                Arg::Value(v) => {
                    let a = &mut self.axes[i];
                    let u = a.units_per_deg();
                    let ok = match m {
                        "SL" if v <= 0.0 => {
                            a.min = v;
                            true
                        }
                        "SR" if v >= 0.0 => {
                            a.max = v;
                            true
                        }
                        "VA" if v > 0.0 => {
                            a.model_mut().max_velocity = v / u;
                            true
                        }
                        "AC" if v > 0.0 => {
                            a.model_mut().acceleration = v / u;
                            true
                        }
                        _ => false,
                    };
                    if !ok {
                        self.push_error(axis_err(code::AXIS_PARAMETER_OUT_OF_RANGE), now);
                    }
                }
            },
            ("DH", false) => {
                let v = match arg(c.param) {
                    Arg::Missing => 0.0,
                    Arg::Value(v) => v,
                    Arg::Bad => {
                        self.push_error(code::PARAMETER_OUT_OF_RANGE, now);
                        return Ok(());
                    }
                };
                self.axes[i].define_position(v, now);
                self.axes[i].homed = true;
            }
            ("OR", false) => {
                let kind_ok = match arg(c.param) {
                    Arg::Missing => true,
                    Arg::Value(t) => (0.0..=6.0).contains(&t),
                    Arg::Bad => false,
                };
                if !kind_ok {
                    self.push_error(code::PARAMETER_OUT_OF_RANGE, now);
                } else if !self.axes[i].enabled {
                    self.push_error(axis_err(code::MOTOR_NOT_ENABLED), now);
                } else {
                    self.axes[i].start(0.0, now, None);
                    self.axes[i].homed = true;
                }
            }
            ("PA" | "PR", false) => {
                let v = match arg(c.param) {
                    Arg::Missing => {
                        self.push_error(code::PARAMETER_MISSING, now);
                        return Ok(());
                    }
                    Arg::Bad => {
                        self.push_error(code::PARAMETER_OUT_OF_RANGE, now);
                        return Ok(());
                    }
                    Arg::Value(v) => v,
                };
                let a = &self.axes[i];
                let target = if m == "PA" { v } else { a.destination(now) + v };
                if !a.enabled {
                    self.push_error(axis_err(code::MOTOR_NOT_ENABLED), now);
                } else if target > a.max {
                    self.push_error(axis_err(code::POSITIVE_SOFTWARE_LIMIT), now);
                } else if target < a.min {
                    self.push_error(axis_err(code::NEGATIVE_SOFTWARE_LIMIT), now);
                } else {
                    self.moves += 1;
                    let fault = self.faults.move_fault(self.moves);
                    if fault == Some(MoveFault::Disconnect) {
                        return Err(MoveFault::Disconnect);
                    }
                    self.axes[i].start(target, now, fault);
                }
            }
            ("WS", false) => {
                let delay = match arg(c.param) {
                    Arg::Value(ms) if ms >= 0.0 => Duration::from_secs_f64((ms / 1000.0).min(60.0)),
                    _ => Duration::ZERO,
                };
                // Real controllers hold the command queue until the axis stops; we block
                // this emulator thread the same way (bounded, see MAX_WAIT).
                let until = Instant::now() + MAX_WAIT;
                while self.axes[i].busy(Instant::now()) && Instant::now() < until {
                    std::thread::sleep(Duration::from_millis(5));
                }
                std::thread::sleep(delay);
                self.update(Instant::now());
            }
            _ => self.push_error(code::COMMAND_DOES_NOT_EXIST, now),
        }
        Ok(())
    }
}

impl super::Controller for Esp300 {
    fn handle(&mut self, line: &str, now: Instant) -> Handled {
        self.update(now);
        let mut out = Handled::default();
        for part in line.split(';').filter(|p| !p.trim().is_empty()) {
            match parse_one(part) {
                Some(c) => {
                    if self.exec(&c, now, &mut out.replies).is_err() {
                        out.disconnect = true;
                        return out;
                    }
                }
                None => self.push_error(code::COMMAND_DOES_NOT_EXIST, now),
            }
        }
        out
    }

    fn state(&self, now: Instant) -> EmulatorState {
        EmulatorState {
            axes: self.axes.iter().map(|a| a.state(now)).collect(),
        }
    }

    fn busy(&self, now: Instant) -> bool {
        Esp300::busy(self, now)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_commands() {
        let c = parse_one("1PA12.5").unwrap();
        assert_eq!(
            (c.axis, c.mnemonic.as_str(), c.query, c.param),
            (Some(1), "PA", false, "12.5")
        );
        let c = parse_one(" te? ").unwrap();
        assert_eq!((c.axis, c.mnemonic.as_str(), c.query), (None, "TE", true));
        assert!(parse_one("1").is_none());
        assert!(parse_one("1P").is_none());
        assert!(parse_one("1P5").is_none());
        assert!(parse_one("ü€").is_none());
        let c = parse_one("99999999999999MO").unwrap();
        assert_eq!(c.axis, Some(u32::MAX));
    }
}
