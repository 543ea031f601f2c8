//! The Zaber ASCII protocol (firmware 7 style), enough for gonio's driver and for Zaber's own
//! `zaber-motion` library.
//!
//! Command: `/[device] [axis] [id] command words[:CC]` + CR and/or LF. Device 0 (or none) is
//! every device, axis 0 (or none) is the device itself. Message ids (0–99) are echoed.
//! `:CC` is an LRC checksum: the two's complement of the byte sum of everything between `/`
//! and `:`; a command whose checksum is wrong is rejected with `BADDATA`.
//!
//! Reply: `@dd a [id] OK|RJ IDLE|BUSY FLAG data` + CRLF, with `:CC` appended when the device's
//! `comm.checksum` setting is 1. FLAG is the most urgent warning (`--` when none): here `WR`
//! (no reference position: not homed yet), `WL` (unexpected limit switch), `FS` (stalled and
//! stopped), `NI` (a movement
//! was interrupted by a new command or `stop`). Rejections carry the reason as data
//! (`BADCOMMAND`, `BADDATA`, `BADAXIS`, `DEVICEONLY`).
//!
//! Positions are integer native units (`EmulatorConfig::units_per_deg` per degree).
//!
//! Motion: `move abs|rel X` under the axis' `maxspeed`/`accel`, `move abs|rel X SPEED
//! ACCEL` under the move's own (data units: native units/s × 1.6384, native units/s² ×
//! 1.6384 / 10 000), `move vel SPEED [ACCEL]` until a travel limit, `stop` decelerating at
//! `accel` (BUSY until the axis is at rest, as on a real stage), `estop` at once.

use super::{AxisEvent, AxisState, EmuAxis, EmulatorConfig, EmulatorState, Handled};
use crate::emulate::faults::{FaultPlan, MoveFault};
use std::time::Instant;

/// The emulated device id (`get device.id`). Not a real product id on purpose: with
/// `identify_devices=False` zaber-motion does not look it up, and a real id would make
/// clients that do look it up believe in a product's settings we do not emulate.
pub const EMULATED_DEVICE_ID: u32 = 99_001;
/// Firmware version reported by `get version`.
pub const EMULATED_VERSION: &str = "7.38";

/// Zaber's speed unit: `maxspeed` = microsteps/s × 1.6384.
const SPEED_SCALE: f64 = 1.6384;
/// Zaber's acceleration unit: `accel` = microsteps/s² × 1.6384 / 10000.
const ACCEL_SCALE: f64 = 1.6384 / 10_000.0;

/// Compute the checksum of `body` (the bytes between the start character and `:`).
pub fn checksum(body: &[u8]) -> u8 {
    let sum = body.iter().fold(0u8, |s, &b| s.wrapping_add(b));
    sum.wrapping_neg()
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Warn {
    // Ordered by urgency: faults (F*) before warnings (W*) before notices (N*).
    StalledAndStopped, // FS
    LimitError,        // WL
    NoReference,       // WR
    Interrupted,       // NI
}

impl Warn {
    fn code(self) -> &'static str {
        match self {
            Warn::StalledAndStopped => "FS",
            Warn::LimitError => "WL",
            Warn::NoReference => "WR",
            Warn::Interrupted => "NI",
        }
    }
}

struct ZAxis {
    axis: EmuAxis,
    stalled: bool,
    limit_hit: bool,
    interrupted: bool,
}

impl ZAxis {
    fn warnings(&self) -> Vec<Warn> {
        let mut w = Vec::new();
        if self.stalled {
            w.push(Warn::StalledAndStopped);
        }
        if self.limit_hit {
            w.push(Warn::LimitError);
        }
        if !self.axis.homed {
            w.push(Warn::NoReference);
        }
        if self.interrupted {
            w.push(Warn::Interrupted);
        }
        w
    }
}

struct Device {
    address: u8,
    axes: Vec<ZAxis>,
    checksum_replies: bool,
    alerts: bool,
}

/// The Zaber emulator: a daisy chain of devices.
pub struct Zaber {
    devices: Vec<Device>,
    faults: FaultPlan,
    moves: u64,
}

enum Reply {
    Ok(String),
    Rj(&'static str),
}

impl Zaber {
    pub fn new(cfg: &EmulatorConfig, state: Option<EmulatorState>) -> Self {
        let mut saved = state.map(|s| s.axes).unwrap_or_default().into_iter();
        let devices = (1..=cfg.devices)
            .map(|d| Device {
                address: d as u8,
                axes: (0..cfg.axes)
                    .map(|k| {
                        let mut axis = EmuAxis::new(cfg, saved.next());
                        axis.enabled = true;
                        if let Some(m) = cfg.mechanical {
                            let index = ((d - 1) * cfg.axes + k) as u64;
                            axis.set_mechanics(crate::mechanics::MechanicalErrors {
                                seed: m.seed.wrapping_add(index),
                                ..m
                            });
                        }
                        ZAxis {
                            axis,
                            stalled: false,
                            limit_hit: false,
                            interrupted: false,
                        }
                    })
                    .collect(),
                checksum_replies: false,
                alerts: false,
            })
            .collect();
        Self {
            devices,
            faults: cfg.faults.clone(),
            moves: 0,
        }
    }

    fn update(&mut self, now: Instant) {
        for d in &mut self.devices {
            for a in &mut d.axes {
                a.axis.update(now);
                for e in a.axis.take_events() {
                    match e {
                        AxisEvent::LimitHit { .. } => a.limit_hit = true,
                        AxisEvent::Stalled => a.stalled = true,
                    }
                }
            }
        }
    }
}

/// A parsed command line.
#[derive(Debug, PartialEq)]
struct Command<'a> {
    device: u8,
    axis: u8,
    id: Option<u8>,
    words: Vec<&'a str>,
    checksum_ok: bool,
}

fn parse(line: &str) -> Option<Command<'_>> {
    let line = line.trim();
    let body = line.strip_prefix('/')?;
    let (body, checksum_ok) = match body.rsplit_once(':') {
        Some((b, c)) => {
            let ok = c.len() == 2 && u8::from_str_radix(c, 16).is_ok_and(|c| checksum(b.as_bytes()) == c);
            (b, ok)
        }
        None => (body, true),
    };
    let mut tokens = body.split_whitespace().peekable();
    let mut nums = Vec::new();
    while nums.len() < 3 {
        match tokens.peek() {
            Some(t) if t.bytes().all(|b| b.is_ascii_digit()) => {
                nums.push(t.parse::<u32>().ok()?);
                tokens.next();
            }
            _ => break,
        }
    }
    // Out-of-range addresses/axes/ids map to values no device answers (255) or get rejected.
    let clamp = |v: u32| u8::try_from(v).unwrap_or(255);
    let device = nums.first().map(|&v| clamp(v)).unwrap_or(0);
    let axis = nums.get(1).map(|&v| clamp(v)).unwrap_or(0);
    let id = nums.get(2).map(|&v| clamp(v));
    Some(Command {
        device,
        axis,
        id,
        words: tokens.collect(),
        checksum_ok,
    })
}

impl Device {
    fn targets(&self, axis: u8) -> std::ops::Range<usize> {
        if axis == 0 {
            0..self.axes.len()
        } else {
            let i = axis as usize - 1;
            i..i + 1
        }
    }

    fn status_busy(&self, axis: u8, now: Instant) -> bool {
        self.targets(axis).any(|i| self.axes[i].axis.busy(now))
    }

    fn flag(&self, axis: u8) -> &'static str {
        self.targets(axis)
            .flat_map(|i| self.axes[i].warnings())
            .min()
            .map(Warn::code)
            .unwrap_or("--")
    }

    fn format(&self, axis: u8, id: Option<u8>, reply: &Reply, now: Instant) -> String {
        let (flag, data) = match reply {
            Reply::Ok(d) => ("OK", d.as_str()),
            Reply::Rj(r) => ("RJ", *r),
        };
        // A rejected bad axis has no axis state to report: use the device's.
        let axis = if (axis as usize) > self.axes.len() { 0 } else { axis };
        let status = if self.status_busy(axis, now) { "BUSY" } else { "IDLE" };
        let id = id.map(|i| format!("{i} ")).unwrap_or_default();
        let body = format!(
            "{:02} {} {}{} {} {} {}",
            self.address,
            axis,
            id,
            flag,
            status,
            self.flag(axis),
            data
        );
        if self.checksum_replies {
            format!("@{body}:{:02X}", checksum(body.as_bytes()))
        } else {
            format!("@{body}")
        }
    }
}

fn parse_number(s: &str) -> Option<f64> {
    s.parse::<f64>().ok().filter(|v| v.is_finite())
}

impl Zaber {
    /// Execute one command on one device.
    fn exec(&mut self, dev: usize, cmd: &Command, now: Instant) -> Result<Reply, MoveFault> {
        let naxes = self.devices[dev].axes.len();
        if cmd.axis as usize > naxes {
            return Ok(Reply::Rj("BADAXIS"));
        }
        if !cmd.checksum_ok {
            return Ok(Reply::Rj("BADDATA"));
        }
        let axis = cmd.axis;
        let words: Vec<String> = cmd.words.iter().map(|w| w.to_ascii_lowercase()).collect();
        let w: Vec<&str> = words.iter().map(String::as_str).collect();
        let d = &mut self.devices[dev];
        let targets = d.targets(axis);
        let reply = match w.as_slice() {
            [] => Reply::Ok("0".into()),
            ["home"] => {
                for i in targets {
                    let a = &mut d.axes[i];
                    a.interrupted |= a.axis.start(0.0, now, None);
                    a.axis.home_mechanics();
                    a.axis.homed = true;
                    a.limit_hit = false;
                    a.stalled = false;
                }
                Reply::Ok("0".into())
            }
            ["move", "vel", rest @ ..] => {
                // `move vel SPEED [ACCEL]`: signed velocity data; the axis' accel if none.
                let speed = match rest {
                    [v] | [v, _] => parse_number(v).map(f64::round),
                    _ => None,
                };
                let accel = match rest {
                    [_, a] => parse_number(a).map(f64::round).filter(|a| *a >= 1.0).map(Some),
                    _ => Some(None),
                };
                let (Some(speed), Some(accel)) = (speed, accel) else {
                    return Ok(Reply::Rj("BADDATA"));
                };
                self.moves += 1;
                if self.faults.move_fault(self.moves) == Some(MoveFault::Disconnect) {
                    return Err(MoveFault::Disconnect);
                }
                let d = &mut self.devices[dev];
                for i in targets {
                    let a = &mut d.axes[i];
                    let accel = accel.map_or(a.axis.acceleration_units(), |x| x / ACCEL_SCALE);
                    a.limit_hit = false;
                    a.stalled = false;
                    a.interrupted |= a.axis.start_velocity(speed / SPEED_SCALE, accel, now);
                }
                Reply::Ok("0".into())
            }
            ["move", kind, rest @ ..] => {
                // `move abs|rel X [SPEED ACCEL]`: the move's own speed and acceleration
                // (data units, both ≥ 1) instead of `maxspeed` and `accel`.
                let profile = match (*kind, rest) {
                    ("abs" | "rel", [_, sp, ac]) => {
                        match (parse_number(sp).map(f64::round), parse_number(ac).map(f64::round)) {
                            (Some(sp), Some(ac)) if sp >= 1.0 && ac >= 1.0 => Some((sp, ac)),
                            _ => return Ok(Reply::Rj("BADDATA")),
                        }
                    }
                    _ => None,
                };
                // Validate every target first: a rejected command moves nothing.
                let mut plan = Vec::new();
                for i in targets.clone() {
                    let a = &d.axes[i].axis;
                    let target = match (*kind, rest) {
                        ("abs", [v] | [v, _, _]) => parse_number(v).map(f64::round),
                        ("rel", [v] | [v, _, _]) => parse_number(v).map(|v| a.destination(now).round() + v.round()),
                        ("min", []) => Some(a.min),
                        ("max", []) => Some(a.max),
                        ("abs" | "rel", _) => None,
                        _ => return Ok(Reply::Rj("BADCOMMAND")),
                    };
                    match target {
                        Some(t) if t >= a.min && t <= a.max => plan.push((i, t)),
                        _ => return Ok(Reply::Rj("BADDATA")),
                    }
                }
                self.moves += 1;
                let fault = self.faults.move_fault(self.moves);
                if fault == Some(MoveFault::Disconnect) {
                    return Err(MoveFault::Disconnect);
                }
                let d = &mut self.devices[dev];
                for (i, t) in plan {
                    let a = &mut d.axes[i];
                    let u = a.axis.units_per_deg();
                    let degrees = profile.map(|(sp, ac)| (sp / SPEED_SCALE / u, ac / ACCEL_SCALE / u));
                    a.limit_hit = false;
                    a.stalled = false;
                    a.interrupted |= a.axis.start_with(t, now, fault, degrees);
                }
                Reply::Ok("0".into())
            }
            ["stop"] => {
                // A stop decelerates at the axis' `accel`: BUSY until at rest.
                for i in targets {
                    let a = &mut d.axes[i];
                    let accel = a.axis.acceleration_units();
                    a.interrupted |= a.axis.decelerate(now, accel);
                }
                Reply::Ok("0".into())
            }
            ["estop"] => {
                for i in targets {
                    let a = &mut d.axes[i];
                    a.interrupted |= a.axis.stop(now);
                }
                Reply::Ok("0".into())
            }
            ["warnings"] | ["warnings", "clear"] => {
                let mut all: Vec<Warn> = targets.clone().flat_map(|i| d.axes[i].warnings()).collect();
                all.sort();
                all.dedup();
                let mut data = format!("{:02}", all.len());
                for f in &all {
                    data.push(' ');
                    data.push_str(f.code());
                }
                if w.len() == 2 {
                    for i in targets {
                        d.axes[i].limit_hit = false;
                        d.axes[i].stalled = false;
                        d.axes[i].interrupted = false;
                    }
                }
                Reply::Ok(data)
            }
            ["get", setting] => match get(d, axis, setting, now) {
                Some(v) => Reply::Ok(v),
                None => Reply::Rj("BADCOMMAND"),
            },
            ["set", setting, value] => set(d, axis, setting, value),
            ["identify"] | ["system", "reset"] | ["system", "restore"] => Reply::Ok("0".into()),
            ["tools", "echo", ..] => Reply::Ok(cmd.words[2..].join(" ")),
            _ => Reply::Rj("BADCOMMAND"),
        };
        Ok(reply)
    }
}

/// `get SETTING`: axis settings on axis 0 list every axis' value, space separated.
fn get(d: &Device, axis: u8, setting: &str, now: Instant) -> Option<String> {
    let per_axis = |f: &dyn Fn(&ZAxis) -> String| -> String {
        d.targets(axis).map(|i| f(&d.axes[i])).collect::<Vec<_>>().join(" ")
    };
    let units = |a: &ZAxis| a.axis.units_per_deg();
    Some(match setting {
        "pos" => per_axis(&|a| format!("{}", a.axis.position(now).round() as i64)),
        // The load-side encoder: equal to `pos` unless a mechanical error model is set.
        "encoder.pos" => per_axis(&|a| format!("{}", a.axis.encoder_position(now).round() as i64)),
        "limit.min" => per_axis(&|a| format!("{}", a.axis.min.round() as i64)),
        "limit.max" => per_axis(&|a| format!("{}", a.axis.max.round() as i64)),
        "limit.home.pos" => per_axis(&|_| "0".into()),
        "maxspeed" => per_axis(&|a| {
            format!(
                "{}",
                (a.axis.model().max_velocity * units(a) * SPEED_SCALE).round() as i64
            )
        }),
        "accel" => per_axis(&|a| {
            format!(
                "{}",
                (a.axis.model().acceleration * units(a) * ACCEL_SCALE).round() as i64
            )
        }),
        "resolution" => per_axis(&|_| "64".into()),
        "peripheral.id" | "peripheralid" => per_axis(&|_| "0".into()),
        "device.id" | "deviceid" => EMULATED_DEVICE_ID.to_string(),
        "system.serial" => format!("{}", 90_000_000 + u32::from(d.address)),
        "version" => EMULATED_VERSION.into(),
        "version.build" => "18543".into(),
        "system.axiscount" => d.axes.len().to_string(),
        "comm.address" => d.address.to_string(),
        "comm.checksum" => u8::from(d.checksum_replies).to_string(),
        "comm.alert" => u8::from(d.alerts).to_string(),
        "comm.protocol" => "2".into(),
        "system.access" => "1".into(),
        _ => return None,
    })
}

/// `set SETTING VALUE`.
fn set(d: &mut Device, axis: u8, setting: &str, value: &str) -> Reply {
    let Some(v) = parse_number(value) else {
        return Reply::Rj("BADDATA");
    };
    let flag = |v: f64| (v == 0.0 || v == 1.0).then_some(v == 1.0);
    match setting {
        "comm.checksum" => match flag(v) {
            Some(b) => d.checksum_replies = b,
            None => return Reply::Rj("BADDATA"),
        },
        "comm.alert" => match flag(v) {
            Some(b) => d.alerts = b,
            None => return Reply::Rj("BADDATA"),
        },
        "maxspeed" | "accel" | "limit.min" | "limit.max" => {
            for i in d.targets(axis) {
                let a = &mut d.axes[i];
                let u = a.axis.units_per_deg();
                match setting {
                    "maxspeed" if v > 0.0 => a.axis.model_mut().max_velocity = v / SPEED_SCALE / u,
                    "accel" if v > 0.0 => a.axis.model_mut().acceleration = v / ACCEL_SCALE / u,
                    "limit.min" if v <= 0.0 => a.axis.min = v,
                    "limit.max" if v >= 0.0 => a.axis.max = v,
                    _ => return Reply::Rj("BADDATA"),
                }
            }
        }
        _ => return Reply::Rj("BADCOMMAND"),
    }
    Reply::Ok("0".into())
}

impl super::Controller for Zaber {
    fn handle(&mut self, line: &str, now: Instant) -> Handled {
        self.update(now);
        let Some(cmd) = parse(line) else {
            // Real devices ignore lines that do not start with `/`.
            tracing::debug!("zaber: ignoring line without `/`: {line:?}");
            return Handled::default();
        };
        let mut out = Handled::default();
        for dev in 0..self.devices.len() {
            let address = self.devices[dev].address;
            if cmd.device != 0 && cmd.device != address {
                continue;
            }
            match self.exec(dev, &cmd, now) {
                Ok(reply) => out
                    .replies
                    .push(self.devices[dev].format(cmd.axis, cmd.id, &reply, now)),
                Err(_) => {
                    out.disconnect = true;
                    return out;
                }
            }
        }
        out
    }

    fn state(&self, now: Instant) -> EmulatorState {
        EmulatorState {
            axes: self
                .devices
                .iter()
                .flat_map(|d| d.axes.iter().map(|a| a.axis.state(now)))
                .collect::<Vec<AxisState>>(),
        }
    }

    fn busy(&self, now: Instant) -> bool {
        self.devices.iter().any(|d| d.axes.iter().any(|a| a.axis.busy(now)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_addresses_ids_and_checksums() {
        let c = parse("/1 2 33 move abs 1000").unwrap();
        assert_eq!((c.device, c.axis, c.id), (1, 2, Some(33)));
        assert_eq!(c.words, vec!["move", "abs", "1000"]);
        let c = parse("/").unwrap();
        assert_eq!((c.device, c.axis, c.id, c.words.len()), (0, 0, None, 0));
        let c = parse("/get pos").unwrap();
        assert_eq!((c.device, c.axis), (0, 0));
        let body = "1 0 get pos";
        let line = format!("/{body}:{:02X}", checksum(body.as_bytes()));
        assert!(parse(&line).unwrap().checksum_ok);
        assert!(!parse("/1 0 get pos:00").unwrap().checksum_ok);
        assert!(!parse("/1 0 get pos:zz").unwrap().checksum_ok);
        assert!(parse("garbage").is_none());
    }

    #[test]
    fn checksum_matches_the_documented_lrc() {
        // Sum of bytes + checksum ≡ 0 (mod 256).
        let body = b"01 0 OK IDLE -- 0";
        let c = checksum(body);
        let s = body.iter().fold(0u32, |s, &b| s + b as u32) + c as u32;
        assert_eq!(s % 256, 0);
    }
}
