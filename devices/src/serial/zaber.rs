//! Zaber ASCII protocol (version 2), as documented by Zaber.
//!
//! Command: `/<device> <axis> <message id> <command> [data][:<checksum>]` + LF.
//! Reply:   `@<device> <axis> <message id> <OK|RJ> <IDLE|BUSY> <warning flag> <data>[:<checksum>]`
//! + CR LF; info lines start with `#`, unsolicited alerts with `!`.
//!
//! - Message ids (0–99) match replies to requests: a reply carrying another id is the late
//!   answer to an earlier, timed-out request and is dropped (logged), never mistaken for
//!   the current answer.
//! - Checksum: the byte sum of everything between the leading `/` or `@` and the `:`, plus
//!   the checksum, is 0 modulo 256; sent when `checksums = true`, verified whenever a reply
//!   carries one. A checksum mismatch is a [`DeviceError::Garbled`] reply (retried).
//! - The warning flag shows the most important active warning: faults `F*` (e.g. `FS`
//!   stalled and stopped, `FQ` encoder error, `FE` limit error), warnings `W*` (`WL`
//!   unexpected limit trigger, `WR` no reference position, `WH` not homed), notices `N*`.
//! - `RJ` replies carry the reason as data: `BADDATA`, `BADCOMMAND`, `BADAXIS`, `AGAIN` …
//!
//! Positions on the wire are native units (microsteps); the rig file gives
//! `units_per_deg` (native units per degree of axis rotation).

use super::policy::{Driver, Poll, POLICY_KEYS};
use super::{link_error, Link, Options, SerialConfigError, SerialTransport, Transport};
use crate::{DeviceError, SoftLimits};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Zaber's velocity data unit: `maxspeed` and a move's SPEED are native units/s × 1.6384
/// (the firmware counts in 1/16384 s ticks, ten of which make its velocity unit).
pub const SPEED_SCALE: f64 = 1.6384;
/// Zaber's acceleration data unit: `accel` and a move's ACCEL are native units/s² ×
/// 1.6384 / 10 000.
pub const ACCEL_SCALE: f64 = 1.6384 / 10_000.0;

/// The checksum of a message body (the bytes between the type character and the `:`).
pub fn checksum(body: &[u8]) -> u8 {
    let sum = body.iter().fold(0u8, |s, &b| s.wrapping_add(b));
    sum.wrapping_neg()
}

/// One command line, terminated by LF.
pub fn format_command(device: u8, axis: u8, id: Option<u8>, command: &str, with_checksum: bool) -> String {
    let mut body = format!("{device} {axis}");
    if let Some(id) = id {
        body.push_str(&format!(" {id}"));
    }
    if !command.is_empty() {
        body.push(' ');
        body.push_str(command);
    }
    if with_checksum {
        format!("/{body}:{:02X}\n", checksum(body.as_bytes()))
    } else {
        format!("/{body}\n")
    }
}

/// A reply (`@` line).
#[derive(Clone, Debug, PartialEq)]
pub struct Reply {
    pub device: u8,
    pub axis: u8,
    pub id: Option<u8>,
    pub rejected: bool,
    pub busy: bool,
    /// `--` when no warning is active.
    pub warning: String,
    pub data: String,
}

/// Any message a device sends.
#[derive(Clone, Debug, PartialEq)]
pub enum Message {
    Reply(Reply),
    /// `#` lines: extra output of a command (e.g. `help`), not a reply.
    Info {
        device: u8,
        axis: u8,
        text: String,
    },
    /// `!` lines: unsolicited alerts (e.g. an axis became idle).
    Alert {
        device: u8,
        axis: u8,
        text: String,
    },
}

/// Parse one received line; `Err` explains why it is not a valid message.
pub fn parse_message(line: &str) -> Result<Message, String> {
    let line = line.trim_end_matches(['\r', '\n']);
    let kind = line.chars().next().ok_or("empty line")?;
    let mut text = &line[kind.len_utf8()..];
    if let Some(colon) = text.rfind(':') {
        let (body, cs) = (&text[..colon], &text[colon + 1..]);
        if cs.len() == 2 && cs.chars().all(|c| c.is_ascii_hexdigit()) {
            let got = u8::from_str_radix(cs, 16).map_err(|e| e.to_string())?;
            let want = checksum(body.as_bytes());
            if got != want {
                return Err(format!("checksum {cs} does not match {want:02X}"));
            }
            text = body;
        }
    }
    if !text.is_ascii() {
        return Err("non-ASCII bytes".into());
    }
    let mut tok = text.split_whitespace();
    let device: u8 = tok
        .next()
        .filter(|t| t.len() <= 2)
        .and_then(|t| t.parse().ok())
        .ok_or("bad device number")?;
    let axis: u8 = tok
        .next()
        .filter(|t| t.len() == 1)
        .and_then(|t| t.parse().ok())
        .ok_or("bad axis number")?;
    let rest: Vec<&str> = tok.collect();
    match kind {
        '@' => {
            let mut i = 0;
            let id = match rest.first() {
                Some(t) if t.chars().all(|c| c.is_ascii_digit()) => {
                    i = 1;
                    Some(t.parse::<u8>().ok().filter(|&v| v <= 99).ok_or("bad message id")?)
                }
                _ => None,
            };
            let rejected = match rest.get(i) {
                Some(&"OK") => false,
                Some(&"RJ") => true,
                _ => return Err("reply flag is neither OK nor RJ".into()),
            };
            let busy = match rest.get(i + 1) {
                Some(&"BUSY") => true,
                Some(&"IDLE") => false,
                _ => return Err("status is neither IDLE nor BUSY".into()),
            };
            let warning = match rest.get(i + 2) {
                Some(w) if *w == "--" || (w.len() == 2 && w.chars().all(|c| c.is_ascii_uppercase())) => w.to_string(),
                _ => return Err("bad warning flag".into()),
            };
            let data = rest[(i + 3).min(rest.len())..].join(" ");
            Ok(Message::Reply(Reply {
                device,
                axis,
                id,
                rejected,
                busy,
                warning,
                data,
            }))
        }
        '#' => Ok(Message::Info {
            device,
            axis,
            text: rest.join(" "),
        }),
        '!' => Ok(Message::Alert {
            device,
            axis,
            text: rest.join(" "),
        }),
        _ => Err(format!("unknown message type {kind:?}")),
    }
}

/// What an `RJ` reason means, for error messages.
pub fn explain_rejection(reason: &str) -> &'static str {
    match reason.split_whitespace().next().unwrap_or("") {
        "BADDATA" => "data out of range or malformed",
        "BADCOMMAND" => "unknown command, or not allowed in this state",
        "BADAXIS" => "no such axis on this device",
        "BADMESSAGEID" => "message id out of range",
        "DEVICEONLY" => "command must be sent to axis 0",
        "AGAIN" => "device busy, send again later",
        "FULL" => "command buffer full",
        "LOCKSTEP" => "axis is part of a lockstep group",
        "NOACCESS" => "access level too low",
        "PARKED" => "axis is parked",
        "STATUSBUSY" => "not allowed while moving",
        "DRIVERDISABLED" => "driver disabled",
        _ => "see the Zaber ASCII protocol manual",
    }
}

/// A velocity (axis units/s) as Zaber SPEED data for a stage with `units_per_axis_unit`
/// native units per axis unit: rounded to the nearest integer, as the firmware takes it.
pub fn speed_data(velocity: f64, units_per_axis_unit: f64) -> i64 {
    (velocity.abs() * units_per_axis_unit * SPEED_SCALE).round() as i64
}

/// An acceleration (axis units/s²) as Zaber ACCEL data, rounded to the nearest integer.
pub fn accel_data(acceleration: f64, units_per_axis_unit: f64) -> i64 {
    (acceleration.abs() * units_per_axis_unit * ACCEL_SCALE).round() as i64
}

/// Link settings of one Zaber port.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PortConfig {
    pub reply_timeout: Duration,
    pub checksums: bool,
}

struct ZaberLink {
    link: Link,
    next_id: u8,
}

/// One serial port with a daisy chain of Zaber devices; shared by all axes on it.
pub struct ZaberPort {
    path: String,
    config: PortConfig,
    link: Mutex<ZaberLink>,
}

impl ZaberPort {
    pub fn open(path: &str, baud: u32, config: PortConfig) -> std::io::Result<ZaberPort> {
        Ok(Self::with_transport(
            path,
            Box::new(SerialTransport::open(path, baud)?),
            config,
        ))
    }

    pub fn with_transport(path: &str, transport: Box<dyn Transport>, config: PortConfig) -> ZaberPort {
        ZaberPort {
            path: path.to_string(),
            config,
            link: Mutex::new(ZaberLink {
                link: Link::new(transport),
                next_id: 0,
            }),
        }
    }

    pub fn path(&self) -> &str {
        &self.path
    }

    /// Send `command` to `device`/`axis` and return its reply (OK or RJ). `who` (the axis
    /// name) goes into errors. Stale replies, info lines and alerts are skipped.
    pub fn command(&self, who: &str, device: u8, axis: u8, command: &str) -> Result<Reply, DeviceError> {
        let timeout = self.config.reply_timeout;
        let mut g = self.link.lock().unwrap_or_else(|p| p.into_inner());
        let zl = &mut *g;
        zl.link.begin().map_err(|e| link_error(who, command, timeout, e))?;
        zl.next_id = (zl.next_id % 99) + 1;
        let id = zl.next_id;
        let line = format_command(device, axis, Some(id), command, self.config.checksums);
        if let Err(e) = zl.link.send(&line) {
            zl.link.mark_dirty();
            return Err(link_error(who, command, timeout, e));
        }
        let deadline = Instant::now() + timeout;
        // A garbled line may be a late reply to an earlier, timed-out request rather than
        // ours: keep listening for the reply with our id until the deadline, and report
        // the garbled line only if ours never came.
        let mut garbled: Option<String> = None;
        loop {
            let text = match zl.link.read_line(deadline) {
                Ok(t) => t,
                Err(e) => {
                    zl.link.mark_dirty();
                    if let (super::LinkError::Timeout, Some(reply)) = (&e, garbled) {
                        return Err(DeviceError::Garbled {
                            device: who.to_string(),
                            command: command.to_string(),
                            reply,
                        });
                    }
                    return Err(link_error(who, command, timeout, e));
                }
            };
            if text.trim().is_empty() {
                continue;
            }
            match parse_message(&text) {
                Ok(Message::Reply(r)) if r.device == device && r.axis == axis && r.id == Some(id) => return Ok(r),
                Ok(Message::Reply(r)) => {
                    tracing::debug!(axis = %who, "dropping stale Zaber reply {text:?} (waiting for id {id}, got {:?})", r.id)
                }
                Ok(other) => tracing::debug!(axis = %who, "Zaber message while waiting for a reply: {other:?}"),
                Err(why) => {
                    tracing::debug!(axis = %who, "garbled line while waiting for id {id}: {text:?} ({why})");
                    garbled = Some(format!("{text} ({why})"));
                }
            }
        }
    }
}

/// The rig-file options of a Zaber axis.
#[derive(Clone, Debug, PartialEq)]
pub struct ZaberAxisConfig {
    pub port: String,
    pub baud: u32,
    pub device: u8,
    pub axis: u8,
    pub units_per_deg: f64,
    pub checksums: bool,
    pub reply_timeout: Duration,
    /// The stage has a load-side encoder (`get encoder.pos`), used as the independent
    /// reference of mechanical calibration.
    pub encoder: bool,
}

/// Option keys of a Zaber axis besides the policy's.
pub const ZABER_KEYS: &[&str] = &[
    "port",
    "baud",
    "device",
    "axis",
    "units_per_deg",
    "checksums",
    "reply_timeout_ms",
    "encoder",
];

impl ZaberAxisConfig {
    pub fn from_options(o: &Options<'_>) -> Result<Self, SerialConfigError> {
        let known: Vec<&str> = ZABER_KEYS.iter().chain(POLICY_KEYS).copied().collect();
        o.deny_unknown(&known)?;
        let port = o.string("port")?.ok_or_else(|| SerialConfigError::Invalid {
            axis: o.axis.to_string(),
            key: "port".into(),
            message: "missing: the serial port, e.g. \"/dev/ttyUSB0\" or \"${GONIO_PORT_0}\"".into(),
        })?;
        let units = o.f64("units_per_deg")?.ok_or_else(|| SerialConfigError::Invalid {
            axis: o.axis.to_string(),
            key: "units_per_deg".into(),
            message: "missing: microsteps per degree of the stage (see its data sheet)".into(),
        })?;
        if units.is_nan() || units <= 0.0 {
            return Err(SerialConfigError::Invalid {
                axis: o.axis.to_string(),
                key: "units_per_deg".into(),
                message: format!("{units}: must be > 0"),
            });
        }
        Ok(ZaberAxisConfig {
            port,
            baud: o.int("baud", 115_200, 300, 4_000_000)? as u32,
            device: o.int("device", 1, 1, 99)? as u8,
            axis: o.int("axis", 1, 1, 9)? as u8,
            units_per_deg: units,
            checksums: o.bool("checksums", true)?,
            reply_timeout: Duration::from_millis(o.int("reply_timeout_ms", 500, 1, 60_000)? as u64),
            encoder: o.bool("encoder", false)?,
        })
    }

    pub fn port_config(&self) -> PortConfig {
        PortConfig {
            reply_timeout: self.reply_timeout,
            checksums: self.checksums,
        }
    }

    /// Native units per radian.
    pub fn units_per_rad(&self) -> f64 {
        self.units_per_deg.to_degrees()
    }
}

/// One axis of one Zaber device.
pub struct ZaberAxis {
    name: String,
    port: std::sync::Arc<ZaberPort>,
    device: u8,
    axis: u8,
    units_per_rad: f64,
    encoder: bool,
}

impl ZaberAxis {
    pub fn new(name: &str, port: std::sync::Arc<ZaberPort>, device: u8, axis: u8, units_per_rad: f64) -> Self {
        ZaberAxis {
            name: name.to_string(),
            port,
            device,
            axis,
            units_per_rad,
            encoder: false,
        }
    }

    /// Declare a load-side encoder (rig option `encoder = true`): [`Driver::reference`]
    /// then reads `get encoder.pos`. The encoder counts in the same native units as the
    /// motor on the stages this is meant for (and on the emulator).
    pub fn with_encoder(mut self, encoder: bool) -> Self {
        self.encoder = encoder;
        self
    }

    fn native(&self, x: f64) -> i64 {
        (x * self.units_per_rad).round() as i64
    }

    /// A velocity and an acceleration (axis units/s, /s²) in Zaber's data units, rounded
    /// as [`speed_data`] and [`accel_data`] do (the planner's `flight_profile` uses them too).
    fn speed_accel(&self, velocity: f64, acceleration: f64) -> (i64, i64) {
        (
            speed_data(velocity, self.units_per_rad),
            accel_data(acceleration, self.units_per_rad),
        )
    }

    /// Send a command; an `RJ` reply becomes [`DeviceError::Rejected`] (or `NotHomed`
    /// when the device says it has no reference position).
    pub fn ok(&self, command: &str) -> Result<Reply, DeviceError> {
        let r = self.port.command(&self.name, self.device, self.axis, command)?;
        if r.rejected {
            if matches!(r.warning.as_str(), "WR" | "WH") {
                return Err(DeviceError::NotHomed {
                    device: self.name.clone(),
                    command: command.to_string(),
                });
            }
            return Err(DeviceError::Rejected {
                device: self.name.clone(),
                command: command.to_string(),
                reason: format!("{} ({})", r.data, explain_rejection(&r.data)),
            });
        }
        Ok(r)
    }

    fn number(&self, command: &str, r: &Reply) -> Result<f64, DeviceError> {
        r.data
            .split_whitespace()
            .next()
            .and_then(|t| t.parse::<f64>().ok())
            .filter(|x| x.is_finite())
            .ok_or_else(|| DeviceError::Garbled {
                device: self.name.clone(),
                command: command.to_string(),
                reply: format!("data {:?} is not a number", r.data),
            })
    }

    /// Send a relative move (native units computed from `distance`); the policy uses
    /// absolute moves, which stay correct when a command is retried.
    pub fn move_rel(&self, distance: f64) -> Result<(), DeviceError> {
        self.ok(&format!("move rel {}", self.native(distance))).map(|_| ())
    }

    /// The typed error for an active warning flag, if it is one that ends a move.
    fn fault(&self, flag: &str, during: &str, position: f64) -> Option<DeviceError> {
        let device = self.name.clone();
        let command = during.to_string();
        match flag {
            "--" => None,
            "FS" | "FT" | "FQ" => Some(DeviceError::Stall {
                device,
                command,
                position,
            }),
            "FE" | "WL" => Some(DeviceError::LimitSwitch { device, command }),
            "WR" | "WH" if during != "home" => Some(DeviceError::NotHomed { device, command }),
            f if f.starts_with('F') => Some(DeviceError::Other {
                device,
                command,
                reason: format!("controller fault flag {f}"),
            }),
            f => {
                tracing::debug!(axis = %self.name, "Zaber warning flag {f} during `{during}`");
                None
            }
        }
    }
}

impl Driver for ZaberAxis {
    /// `get device.id` and `get version`, asked of the device (axis 0): the same
    /// questions `gonio devices probe` relies on the chain to answer.
    fn identity(&self) -> Result<Option<String>, DeviceError> {
        let get = |what: &str| -> Result<String, DeviceError> {
            let command = format!("get {what}");
            let r = self.port.command(&self.name, self.device, 0, &command)?;
            if r.rejected {
                return Err(DeviceError::Rejected {
                    device: self.name.clone(),
                    command,
                    reason: format!("{} ({})", r.data, explain_rejection(&r.data)),
                });
            }
            Ok(r.data.trim().to_string())
        };
        Ok(Some(format!(
            "Zaber device {} axis {} (device.id {}, firmware {}) on {}",
            self.device,
            self.axis,
            get("device.id")?,
            get("version")?,
            self.port.path()
        )))
    }
    fn clear_faults(&self) -> Result<(), DeviceError> {
        self.ok("warnings clear").map(|_| ())
    }

    fn home(&self) -> Result<(), DeviceError> {
        self.ok("home").map(|_| ())
    }

    fn move_abs(&self, target: f64) -> Result<(), DeviceError> {
        let cmd = self.describe_move(target);
        let r = self.ok(&cmd)?;
        match self.fault(&r.warning, &cmd, f64::NAN) {
            Some(DeviceError::Stall { .. }) | None => Ok(()),
            Some(e) => Err(e),
        }
    }

    fn poll(&self, during: &str) -> Result<Poll, DeviceError> {
        let r = self.ok("get pos")?;
        let position = self.number("get pos", &r)? / self.units_per_rad;
        if let Some(e) = self.fault(&r.warning, during, position) {
            return Err(e);
        }
        Ok(Poll { busy: r.busy, position })
    }

    fn stop(&self) -> Result<(), DeviceError> {
        self.ok("stop").map(|_| ())
    }

    fn device_limits(&self) -> Result<Option<SoftLimits>, DeviceError> {
        let min = self.number("get limit.min", &self.ok("get limit.min")?)? / self.units_per_rad;
        let max = self.number("get limit.max", &self.ok("get limit.max")?)? / self.units_per_rad;
        if min < max {
            Ok(Some(SoftLimits { min, max }))
        } else {
            Ok(None)
        }
    }

    fn resolution(&self) -> f64 {
        1.0 / self.units_per_rad
    }

    fn describe_move(&self, target: f64) -> String {
        format!("move abs {}", self.native(target))
    }

    fn move_abs_at(&self, target: f64, velocity: f64, acceleration: f64) -> Result<(), DeviceError> {
        let cmd = self.describe_move_at(target, velocity, acceleration);
        let (speed, accel) = self.speed_accel(velocity, acceleration);
        if speed < 1 || accel < 1 {
            return Err(DeviceError::Rejected {
                device: self.name.clone(),
                command: cmd,
                reason: "velocity or acceleration below one controller unit".into(),
            });
        }
        let r = self.ok(&cmd)?;
        match self.fault(&r.warning, &cmd, f64::NAN) {
            Some(DeviceError::Stall { .. }) | None => Ok(()),
            Some(e) => Err(e),
        }
    }

    fn describe_move_at(&self, target: f64, velocity: f64, acceleration: f64) -> String {
        let (speed, accel) = self.speed_accel(velocity, acceleration);
        format!("move abs {} {speed} {accel}", self.native(target))
    }

    fn reference(&self) -> Result<Option<f64>, DeviceError> {
        if !self.encoder {
            return Ok(None);
        }
        let r = self.ok("get encoder.pos")?;
        Ok(Some(self.number("get encoder.pos", &r)? / self.units_per_rad))
    }
}

#[cfg(test)]
mod tests {
    use super::super::policy::{MotionPolicy, PolicyAxis};
    use super::super::testing::{ScriptReply, ScriptedTransport};
    use super::*;
    use crate::{Axis, MotionModel};
    use std::sync::{Arc, Mutex};

    #[test]
    fn checksum_and_format_roundtrip() {
        // sum of "01 0 OK IDLE -- 0" + checksum ≡ 0 (mod 256)
        let body = "01 0 OK IDLE -- 0";
        let cs = checksum(body.as_bytes());
        let s: u32 = body.bytes().map(u32::from).sum::<u32>() + u32::from(cs);
        assert_eq!(s % 256, 0);
        let line = format!("@{body}:{cs:02X}");
        assert!(matches!(parse_message(&line), Ok(Message::Reply(_))));
        let bad = format!("@{body}:{:02X}", cs.wrapping_add(1));
        assert!(parse_message(&bad).unwrap_err().contains("checksum"));
        assert_eq!(
            format_command(1, 2, Some(7), "move abs 100", false),
            "/1 2 7 move abs 100\n"
        );
        let c = format_command(1, 0, None, "", true);
        assert!(c.starts_with("/1 0:"), "{c}");
    }

    #[test]
    fn parses_replies_with_and_without_ids() {
        let r = parse_message("@01 0 OK IDLE -- 0").unwrap();
        assert_eq!(
            r,
            Message::Reply(Reply {
                device: 1,
                axis: 0,
                id: None,
                rejected: false,
                busy: false,
                warning: "--".into(),
                data: "0".into()
            })
        );
        match parse_message("@02 1 12 RJ BUSY WR BADDATA").unwrap() {
            Message::Reply(r) => {
                assert_eq!(
                    (r.device, r.axis, r.id, r.rejected, r.busy),
                    (2, 1, Some(12), true, true)
                );
                assert_eq!(r.warning, "WR");
                assert_eq!(r.data, "BADDATA");
            }
            m => panic!("{m:?}"),
        }
        assert!(matches!(parse_message("!01 1 IDLE --"), Ok(Message::Alert { .. })));
        assert!(matches!(parse_message("#01 0 COMMAND USAGE"), Ok(Message::Info { .. })));
        for bad in [
            "",
            "@",
            "@01",
            "@01 0 XX IDLE -- 0",
            "@01 0 OK WAIT -- 0",
            "@01 0 OK IDLE ? 0",
            "x01 0",
        ] {
            assert!(parse_message(bad).is_err(), "{bad:?} should not parse");
        }
    }

    /// A scripted Zaber device (device 1, axis 1) with a position that jumps to the target.
    struct Dev {
        pos: i64,
        busy_polls: u32,
        homed: bool,
    }

    fn parse_cmd(line: &str) -> (u8, u8, u8, String) {
        let body = line.trim_start_matches('/');
        let body = body.split(':').next().unwrap();
        let t: Vec<&str> = body.split_whitespace().collect();
        (
            t[0].parse().unwrap(),
            t[1].parse().unwrap(),
            t[2].parse().unwrap(),
            t[3..].join(" "),
        )
    }

    fn reply(dev: u8, axis: u8, id: u8, rest: &str) -> ScriptReply {
        let body = format!("{dev:02} {axis} {id} {rest}");
        ScriptReply::line(&format!("@{body}:{:02X}", checksum(body.as_bytes())))
    }

    fn port_with(
        f: impl FnMut(&str) -> Vec<ScriptReply> + Send + 'static,
    ) -> (Arc<ZaberPort>, Arc<Mutex<Vec<String>>>) {
        let t = ScriptedTransport::new(f);
        let log = t.log();
        let cfg = PortConfig {
            reply_timeout: Duration::from_millis(80),
            checksums: true,
        };
        (Arc::new(ZaberPort::with_transport("scripted", Box::new(t), cfg)), log)
    }

    /// A well-behaved device; `hook` may replace the reply for a (command, count) pair.
    fn device(
        mut hook: impl FnMut(&str, u32, u8) -> Option<Vec<ScriptReply>> + Send + 'static,
    ) -> impl FnMut(&str) -> Vec<ScriptReply> + Send + 'static {
        let mut d = Dev {
            pos: 0,
            busy_polls: 0,
            homed: false,
        };
        let mut counts = std::collections::HashMap::<String, u32>::new();
        move |line| {
            let (dev, axis, id, cmd) = parse_cmd(line);
            let verb = cmd.split_whitespace().take(2).collect::<Vec<_>>().join(" ");
            let n = counts.entry(verb.clone()).or_default();
            *n += 1;
            if let Some(r) = hook(&verb, *n, id) {
                return r;
            }
            let status = |d: &Dev| if d.busy_polls > 0 { "BUSY" } else { "IDLE" };
            match verb.as_str() {
                "home" => {
                    d.homed = true;
                    d.pos = 0;
                    d.busy_polls = 1;
                    vec![reply(dev, axis, id, "OK BUSY -- 0")]
                }
                "move abs" => {
                    if !d.homed {
                        return vec![reply(dev, axis, id, "RJ IDLE WR BADCOMMAND")];
                    }
                    let x: i64 = cmd.split_whitespace().nth(2).unwrap().parse().unwrap();
                    if !(-100_000..=100_000).contains(&x) {
                        return vec![reply(dev, axis, id, "RJ IDLE -- BADDATA")];
                    }
                    d.pos = x;
                    d.busy_polls = 2;
                    vec![reply(dev, axis, id, "OK BUSY -- 0")]
                }
                "get pos" => {
                    let s = status(&d);
                    d.busy_polls = d.busy_polls.saturating_sub(1);
                    vec![reply(dev, axis, id, &format!("OK {s} -- {}", d.pos))]
                }
                "get limit.min" => vec![reply(dev, axis, id, "OK IDLE -- -100000")],
                "get limit.max" => vec![reply(dev, axis, id, "OK IDLE -- 100000")],
                "stop" | "warnings clear" => vec![reply(dev, axis, id, &format!("OK {} -- 0", status(&d)))],
                _ => vec![reply(dev, axis, id, "RJ IDLE -- BADCOMMAND")],
            }
        }
    }

    fn motion() -> MotionModel {
        MotionModel {
            max_velocity: 1.0,
            acceleration: 10.0,
            jerk: None,
            settle_time: 0.0,
            deadband: 1e-4,
        }
    }

    fn policy() -> MotionPolicy {
        MotionPolicy {
            poll_interval: Duration::from_millis(1),
            timeout_floor_s: 0.5,
            ..MotionPolicy::default()
        }
    }

    /// 1000 microsteps per degree.
    fn axis(port: Arc<ZaberPort>) -> PolicyAxis<ZaberAxis> {
        let upr = 1000.0f64.to_degrees();
        PolicyAxis::new(
            "turntable",
            SoftLimits { min: -3.0, max: 3.0 },
            motion(),
            policy(),
            ZaberAxis::new("turntable", port, 1, 1, upr),
        )
    }

    #[tokio::test]
    async fn home_move_and_read_back_with_checksums() {
        let (port, log) = port_with(device(|_, _, _| None));
        let a = axis(port);
        a.home().await.unwrap();
        // device limits ±100000 µsteps = ±100° narrower than nothing: rig limits ±3 rad stay
        let rb = a.move_abs(10f64.to_radians()).await.unwrap();
        assert!((rb.to_degrees() - 10.0).abs() < 1e-9, "{rb}");
        let log = log.lock().unwrap().clone();
        assert!(
            log.iter()
                .any(|l| l.starts_with("/1 1 ") && l.contains("move abs 10000:")),
            "{log:?}"
        );
        for l in &log {
            let (body, cs) = l[1..].split_once(':').unwrap();
            assert_eq!(u8::from_str_radix(cs, 16).unwrap(), checksum(body.as_bytes()), "{l}");
        }
        // controller limits (±100°) now bound the axis
        assert!((a.limits().max.to_degrees() - 100.0).abs() < 1e-9);
    }

    #[tokio::test]
    async fn flight_is_one_move_abs_with_speed_and_accel_in_zaber_units() {
        // 1000 µsteps/°: 30 °/s = 30 000 µsteps/s × 1.6384 = 49 152; 60 °/s² = 60 000 µsteps/s²
        // × 1.6384e-4 = 9.8304 → 10 (the controller then accelerates at 61.04 °/s²)
        assert_eq!(speed_data(30f64.to_radians(), 1000f64.to_degrees()), 49_152);
        assert_eq!(accel_data(60f64.to_radians(), 1000f64.to_degrees()), 10);
        let (port, log) = port_with(device(|_, _, _| None));
        let mut m = motion();
        m.acceleration = 60f64.to_radians();
        let a = PolicyAxis::new(
            "turntable",
            SoftLimits { min: -3.0, max: 3.0 },
            m,
            policy(),
            ZaberAxis::new("turntable", port, 1, 1, 1000f64.to_degrees()),
        );
        assert!(matches!(
            a.start_move_at(0.2, 0.5).await,
            Err(DeviceError::NotHomed { .. })
        ));
        a.home().await.unwrap();
        let bad = a.start_move_at(0.2, f64::NAN).await.unwrap_err();
        assert!(matches!(bad, DeviceError::Rejected { .. }), "{bad}");
        a.start_move_at(20f64.to_radians(), 30f64.to_radians()).await.unwrap();
        let rb = a.wait_idle().await.unwrap();
        assert!((rb.to_degrees() - 20.0).abs() < 1e-9, "{rb}");
        let log = log.lock().unwrap().clone();
        let moves: Vec<&String> = log.iter().filter(|l| l.contains("move")).collect();
        assert_eq!(moves.len(), 1, "{log:?}");
        assert!(
            moves[0].starts_with("/1 1 ") && moves[0].contains(" move abs 20000 49152 10:"),
            "{moves:?}"
        );
        // below one velocity unit: refused before anything is sent
        let raw = ZaberAxis::new(
            "turntable",
            port_with(device(|_, _, _| None)).0,
            1,
            1,
            1000f64.to_degrees(),
        );
        assert!(matches!(
            raw.move_abs_at(0.1, 1e-9, 1.0),
            Err(DeviceError::Rejected { .. })
        ));
    }

    #[tokio::test]
    async fn stale_reply_with_old_id_is_ignored() {
        // the first `get pos` after homing answers with an old id first, then the real one
        let (port, _) = port_with(device(|verb, n, id| {
            (verb == "get pos" && n == 1).then(|| {
                vec![
                    reply(1, 1, if id == 1 { 99 } else { id - 1 }, "OK IDLE -- 77777"),
                    reply(1, 1, id, "OK IDLE -- 0"),
                ]
            })
        }));
        let a = axis(port);
        a.home().await.unwrap();
        assert_eq!(a.position().await.unwrap(), 0.0);
    }

    #[tokio::test]
    async fn garbled_and_dropped_replies_are_retried() {
        let (port, log) = port_with(device(|verb, n, id| match (verb, n) {
            ("get pos", 1) => Some(vec![ScriptReply::Bytes(b"@01 1 \xff\x00garbage\r\n".to_vec())]),
            ("get pos", 2) => Some(vec![]), // dropped
            ("get pos", 3) => Some(
                vec![reply(1, 1, id, "OK IDLE -- 0").clone()]
                    .into_iter()
                    .map(|r| match r {
                        // corrupt one digit of a checksummed reply: checksum mismatch
                        ScriptReply::Bytes(mut b) => {
                            let i = b.iter().position(|&c| c == b'K').unwrap();
                            b[i] = b'X';
                            ScriptReply::Bytes(b)
                        }
                        r => r,
                    })
                    .collect(),
            ),
            _ => None,
        }));
        let p = MotionPolicy { retries: 3, ..policy() };
        let a = PolicyAxis::new(
            "turntable",
            SoftLimits { min: -3.0, max: 3.0 },
            motion(),
            p,
            ZaberAxis::new("turntable", port, 1, 1, 1000f64.to_degrees()),
        );
        a.home().await.unwrap();
        let n = log.lock().unwrap().iter().filter(|l| l.contains("get pos")).count();
        assert!(n >= 4, "three failed polls then a good one: {n}");
    }

    #[tokio::test]
    async fn garbled_reply_beyond_retries_is_a_typed_error() {
        let (port, _) = port_with(device(|verb, _, _| {
            (verb == "get pos").then(|| vec![ScriptReply::line("@01 1 ??? nonsense")])
        }));
        let a = axis(port);
        match a.position().await.unwrap_err() {
            DeviceError::Garbled { device, command, reply } => {
                assert_eq!(device, "turntable");
                assert_eq!(command, "get pos");
                assert!(reply.contains("nonsense"));
            }
            e => panic!("{e}"),
        }
    }

    #[tokio::test]
    async fn rejection_reasons_map_to_typed_errors() {
        let (port, _) = port_with(device(|_, _, _| None));
        let a = axis(port.clone());
        // the policy refuses before homing; the raw driver shows the device's WR rejection
        let raw = ZaberAxis::new("turntable", port, 1, 1, 1000f64.to_degrees());
        assert!(matches!(raw.move_abs(0.1), Err(DeviceError::NotHomed { .. })));
        a.home().await.unwrap();
        // inside the rig limits but outside the device's range: BADDATA from the device
        match raw.move_abs(2.0) {
            Err(DeviceError::Rejected {
                device,
                command,
                reason,
            }) => {
                assert_eq!(device, "turntable");
                assert!(command.starts_with("move abs"), "{command}");
                assert!(reason.contains("BADDATA"), "{reason}");
            }
            r => panic!("{r:?}"),
        }
        assert!(matches!(raw.ok("fly"), Err(DeviceError::Rejected { .. })));
    }

    #[tokio::test]
    async fn warning_flags_end_moves_with_typed_errors() {
        for (flag, want) in [("FS", "stall"), ("WL", "limit"), ("FQ", "stall"), ("FD", "other")] {
            let (port, _) = port_with(device(move |verb, n, id| {
                (verb == "get pos" && n >= 4).then(|| vec![reply(1, 1, id, &format!("OK IDLE {flag} 1234"))])
            }));
            let a = axis(port);
            a.home().await.unwrap();
            let e = a.move_abs(0.5).await.unwrap_err();
            let ok = match want {
                "stall" => matches!(&e, DeviceError::Stall { command, .. } if command.starts_with("move abs")),
                "limit" => matches!(e, DeviceError::LimitSwitch { .. }),
                _ => matches!(e, DeviceError::Other { .. }),
            };
            assert!(ok, "{flag}: {e}");
        }
    }

    #[tokio::test]
    async fn disconnect_is_reported_after_retries() {
        let (port, _) = port_with(device(|verb, _, _| {
            (verb == "home").then(|| vec![ScriptReply::Disconnect])
        }));
        let a = axis(port);
        match a.home().await.unwrap_err() {
            DeviceError::Disconnected { device, command, .. } => {
                assert_eq!(device, "turntable");
                assert_eq!(command, "home");
            }
            e => panic!("{e}"),
        }
    }

    #[tokio::test]
    async fn slow_reply_times_out() {
        let (port, _) = port_with(device(|verb, _, id| {
            (verb == "stop").then(|| {
                vec![
                    ScriptReply::Delay(Duration::from_millis(300)),
                    reply(1, 1, id, "OK IDLE -- 0"),
                ]
            })
        }));
        let a = axis(port);
        match a.stop().await.unwrap_err() {
            DeviceError::Timeout { command, seconds, .. } => {
                assert_eq!(command, "stop");
                assert!((seconds - 0.08).abs() < 1e-9);
            }
            e => panic!("{e}"),
        }
    }
}
