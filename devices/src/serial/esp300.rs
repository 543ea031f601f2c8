//! Newport ESP300 / ESP301 motion controllers (RS-232, 19200 baud by default).
//!
//! Commands are `<axis><mnemonic>[parameter]` terminated by CR (we send CR LF, which the
//! controller accepts as whitespace): `1MO` motor on, `1OR` home, `1PA12.5` move absolute,
//! `1PR-1` move relative, `1ST` stop, and queries `1TP` (position), `1MD?` (motion done:
//! 1 = done, 0 = moving), `1SL?`/`1SR?` (left/right software limits), `TE?` (error code),
//! `TB?` (`code, timestamp, MESSAGE`), `VE?` (firmware version). Replies end with CR LF.
//!
//! Unlike Zaber, set commands are silent and replies carry no id or checksum, so:
//! - a rejected command is only visible in the error queue: after each motion command the
//!   driver reads `TB?` and turns a non-zero code into a typed error;
//! - after a failed exchange the link drops any late bytes before the next command
//!   ([`super::Link`]'s dirty flag) so a late reply is not taken for the next answer;
//! - a garbled reply is one that does not parse as what the query returns.
//!
//! Error codes: 0 = none; axis errors are `axis × 100 + n` (n: 4/5 positive/negative
//! hardware limit, 6/7 software limit, 3 following error, 8 motor not connected, 13 motor
//! not enabled …); codes below 100 are general (6 unknown command, 7 parameter out of range …).

use super::policy::{Driver, Poll, POLICY_KEYS};
use super::{LinePort, Options, SerialConfigError, SerialTransport, Transport};
use crate::{DeviceError, SoftLimits};
use std::sync::Arc;
use std::time::Duration;

/// Line terminator sent after each command.
pub const TERMINATOR: &str = "\r\n";

/// The meaning of an axis error `n` (code = axis × 100 + n), from the ESP300 manual.
pub fn axis_error_text(n: u32) -> &'static str {
    match n {
        0 => "motor type not defined",
        1 => "parameter out of range",
        2 => "amplifier fault detected",
        3 => "following error threshold exceeded",
        4 => "positive hardware limit detected",
        5 => "negative hardware limit detected",
        6 => "positive software limit detected",
        7 => "negative software limit detected",
        8 => "motor / stage not connected",
        9 => "feedback signal fault detected",
        10 => "maximum velocity exceeded",
        11 => "maximum acceleration exceeded",
        13 => "motor not enabled",
        20 => "homing aborted",
        _ => "see the ESP300 manual",
    }
}

/// The meaning of a general error code (< 100).
pub fn general_error_text(code: u32) -> &'static str {
    match code {
        1 => "PCI communication time-out",
        4 => "emergency stop activated",
        6 => "command does not exist",
        7 => "parameter out of range",
        8 => "cable interlock error",
        9 => "axis number out of range",
        13 => "group number missing",
        _ => "see the ESP300 manual",
    }
}

/// One serial port with an ESP controller; shared by its axes.
pub struct EspPort {
    line: LinePort,
}

impl std::ops::Deref for EspPort {
    type Target = LinePort;
    fn deref(&self) -> &LinePort {
        &self.line
    }
}

impl EspPort {
    pub fn open(path: &str, baud: u32, reply_timeout: Duration) -> std::io::Result<EspPort> {
        Ok(Self::with_transport(
            path,
            Box::new(SerialTransport::open(path, baud)?),
            reply_timeout,
        ))
    }

    pub fn with_transport(path: &str, transport: Box<dyn Transport>, reply_timeout: Duration) -> EspPort {
        EspPort {
            line: LinePort::new(path, transport, reply_timeout, TERMINATOR),
        }
    }

    /// Read one entry of the error queue (`TB?`): `(code, message)`, code 0 = no error.
    pub fn error(&self, who: &str) -> Result<(u32, String), DeviceError> {
        let r = self.query(who, "TB?")?;
        let mut parts = r.splitn(3, ',');
        let code = parts
            .next()
            .and_then(|c| c.trim().parse::<u32>().ok())
            .ok_or_else(|| self.garbled(who, "TB?", &r, "expected `code, timestamp, message`"))?;
        let msg = parts.nth(1).map(|m| m.trim().to_string()).unwrap_or_default();
        Ok((code, msg))
    }
}

/// The rig-file options of an ESP axis.
#[derive(Clone, Debug, PartialEq)]
pub struct EspAxisConfig {
    pub port: String,
    pub baud: u32,
    pub axis: u8,
    /// Controller units per degree (1 for a rotary stage set up in degrees).
    pub units_per_deg: f64,
    pub reply_timeout: Duration,
}

/// Option keys of an ESP axis besides the policy's.
pub const ESP_KEYS: &[&str] = &["port", "baud", "axis", "units_per_deg", "reply_timeout_ms"];

impl EspAxisConfig {
    pub fn from_options(o: &Options<'_>) -> Result<Self, SerialConfigError> {
        let known: Vec<&str> = ESP_KEYS.iter().chain(POLICY_KEYS).copied().collect();
        o.deny_unknown(&known)?;
        let port = o.string("port")?.ok_or_else(|| SerialConfigError::Invalid {
            axis: o.axis.to_string(),
            key: "port".into(),
            message: "missing: the serial port, e.g. \"/dev/ttyUSB0\" or \"${GONIO_PORT_0}\"".into(),
        })?;
        Ok(EspAxisConfig {
            port,
            baud: o.int("baud", 19_200, 300, 921_600)? as u32,
            axis: o.int("axis", 1, 1, 3)? as u8,
            units_per_deg: o.positive("units_per_deg", 1.0)?,
            reply_timeout: Duration::from_millis(o.int("reply_timeout_ms", 500, 1, 60_000)? as u64),
        })
    }

    pub fn units_per_rad(&self) -> f64 {
        self.units_per_deg.to_degrees()
    }
}

/// One axis of an ESP controller.
pub struct EspAxis {
    name: String,
    port: Arc<EspPort>,
    axis: u8,
    units_per_rad: f64,
    /// `VA` and `AC` as they were before a flight changed them (controller units), restored
    /// by [`Driver::end_flight`]: the ESP's velocity and acceleration are settings, not
    /// per-move arguments, and every later stop-and-go move must run at the configured ones.
    saved: std::sync::Mutex<Option<(f64, f64)>>,
}

impl EspAxis {
    pub fn new(name: &str, port: Arc<EspPort>, axis: u8, units_per_rad: f64) -> Self {
        EspAxis {
            name: name.to_string(),
            port,
            axis,
            units_per_rad,
            saved: std::sync::Mutex::new(None),
        }
    }

    fn cmd(&self, mnemonic: &str) -> String {
        format!("{}{}", self.axis, mnemonic)
    }

    /// Map an error-queue entry to a typed error naming `command`.
    fn to_error(&self, command: &str, code: u32, msg: &str, position: f64) -> DeviceError {
        let device = self.name.clone();
        let command = command.to_string();
        let (axis, n) = (code / 100, code % 100);
        let text = if msg.is_empty() {
            if code >= 100 {
                axis_error_text(n)
            } else {
                general_error_text(code)
            }
            .to_string()
        } else {
            msg.to_string()
        };
        let reason = format!("error {code}: {text}");
        if code < 100 {
            return DeviceError::Rejected {
                device,
                command,
                reason,
            };
        }
        if axis != u32::from(self.axis) {
            return DeviceError::Other {
                device,
                command,
                reason: format!("{reason} (reported for axis {axis})"),
            };
        }
        match n {
            4 | 5 => DeviceError::LimitSwitch { device, command },
            3 | 9 => DeviceError::Stall {
                device,
                command,
                position,
            },
            8 => DeviceError::Disconnected {
                device,
                command,
                reason,
            },
            1 | 6 | 7 | 13 | 30 | 32 => DeviceError::Rejected {
                device,
                command,
                reason,
            },
            _ => DeviceError::Other {
                device,
                command,
                reason,
            },
        }
    }

    /// Read the error queue after `command`; the first non-zero entry is the error.
    pub fn check(&self, command: &str) -> Result<(), DeviceError> {
        let (code, msg) = self.port.error(&self.name)?;
        if code == 0 {
            return Ok(());
        }
        // Drain the rest of the queue so the next check starts clean (bounded: ESP300
        // holds at most 10 entries).
        for _ in 0..10 {
            match self.port.error(&self.name) {
                Ok((0, _)) | Err(_) => break,
                Ok((c, m)) => tracing::warn!(axis = %self.name, "further ESP error {c}: {m}"),
            }
        }
        Err(self.to_error(command, code, &msg, f64::NAN))
    }

    fn write_checked(&self, command: &str) -> Result<(), DeviceError> {
        self.port.write(&self.name, command)?;
        self.check(command)
    }

    /// Relative move (controller units from `distance`); the policy uses absolute moves,
    /// which stay correct when a command is retried.
    pub fn move_rel(&self, distance: f64) -> Result<(), DeviceError> {
        self.write_checked(&self.cmd(&format!("PR{}", fmt_num(distance * self.units_per_rad))))
    }

    /// The firmware version string (`VE?`).
    pub fn version(&self) -> Result<String, DeviceError> {
        self.port.query(&self.name, "VE?")
    }
}

/// The smallest step of any value the driver sends (commands carry 6 decimals of the
/// controller's user unit).
pub const VALUE_STEP: f64 = 1e-6;

/// Numbers as the ESP expects them: plain decimal, no exponent.
fn fmt_num(x: f64) -> String {
    let s = format!("{x:.6}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s.is_empty() || s == "-" || s == "-0" {
        "0".into()
    } else {
        s.to_string()
    }
}

impl Driver for EspAxis {
    /// The controller's `VE?` (model and firmware).
    fn identity(&self) -> Result<Option<String>, DeviceError> {
        Ok(Some(format!("{} (axis {})", self.version()?.trim(), self.axis)))
    }
    fn clear_faults(&self) -> Result<(), DeviceError> {
        // Empty the error queue: old entries must not be blamed on the next command.
        for _ in 0..10 {
            if self.port.error(&self.name)?.0 == 0 {
                break;
            }
        }
        Ok(())
    }

    fn home(&self) -> Result<(), DeviceError> {
        self.write_checked(&self.cmd("MO"))?;
        self.write_checked(&self.cmd("OR"))
    }

    fn move_abs(&self, target: f64) -> Result<(), DeviceError> {
        self.write_checked(&self.describe_move(target))
    }

    fn poll(&self, during: &str) -> Result<Poll, DeviceError> {
        let md = self.cmd("MD?");
        let r = self.port.query(&self.name, &md)?;
        let busy = match r.as_str() {
            "0" => true,
            "1" => false,
            _ => return Err(self.port.garbled(&self.name, &md, &r, "expected 0 or 1")),
        };
        let position = self.port.query_number(&self.name, &self.cmd("TP"))? / self.units_per_rad;
        if !busy && during != "get position" && during != "get status" {
            // Motion ended: a limit switch or following error shows in the error queue.
            let (code, msg) = self.port.error(&self.name)?;
            if code != 0 {
                return Err(self.to_error(during, code, &msg, position));
            }
        }
        Ok(Poll { busy, position })
    }

    fn stop(&self) -> Result<(), DeviceError> {
        self.port.write(&self.name, &self.cmd("ST"))
    }

    fn device_limits(&self) -> Result<Option<SoftLimits>, DeviceError> {
        let min = self.port.query_number(&self.name, &self.cmd("SL?"))? / self.units_per_rad;
        let max = self.port.query_number(&self.name, &self.cmd("SR?"))? / self.units_per_rad;
        Ok((min < max).then_some(SoftLimits { min, max }))
    }

    fn resolution(&self) -> f64 {
        // Commands carry 6 decimals of the controller's unit.
        1e-6 / self.units_per_rad
    }

    fn describe_move(&self, target: f64) -> String {
        self.cmd(&format!("PA{}", fmt_num(target * self.units_per_rad)))
    }

    /// `VA` velocity, `AC` acceleration, then `PA`: the first flight saves the settings it
    /// replaces (`VA?`, `AC?`), [`Driver::end_flight`] puts them back.
    fn move_abs_at(&self, target: f64, velocity: f64, acceleration: f64) -> Result<(), DeviceError> {
        let saved = *self.saved.lock().unwrap_or_else(|p| p.into_inner());
        if saved.is_none() {
            let va = self.port.query_number(&self.name, &self.cmd("VA?"))?;
            let ac = self.port.query_number(&self.name, &self.cmd("AC?"))?;
            *self.saved.lock().unwrap_or_else(|p| p.into_inner()) = Some((va, ac));
        }
        let (va, ac) = self.flight_settings(velocity, acceleration);
        self.write_checked(&va)?;
        self.write_checked(&ac)?;
        self.write_checked(&self.describe_move(target))
    }

    fn describe_move_at(&self, target: f64, velocity: f64, acceleration: f64) -> String {
        let (va, ac) = self.flight_settings(velocity, acceleration);
        format!("{va};{ac};{}", self.describe_move(target))
    }

    fn end_flight(&self) -> Result<(), DeviceError> {
        let saved = *self.saved.lock().unwrap_or_else(|p| p.into_inner());
        let Some((va, ac)) = saved else { return Ok(()) };
        self.write_checked(&self.cmd(&format!("VA{}", fmt_num(va))))?;
        self.write_checked(&self.cmd(&format!("AC{}", fmt_num(ac))))?;
        *self.saved.lock().unwrap_or_else(|p| p.into_inner()) = None;
        Ok(())
    }
}

impl EspAxis {
    /// The `VA` and `AC` commands of a flight (controller units, 6 decimals).
    fn flight_settings(&self, velocity: f64, acceleration: f64) -> (String, String) {
        (
            self.cmd(&format!("VA{}", fmt_num(velocity.abs() * self.units_per_rad))),
            self.cmd(&format!("AC{}", fmt_num(acceleration.abs() * self.units_per_rad))),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::super::policy::{MotionPolicy, PolicyAxis};
    use super::super::testing::{ScriptReply, ScriptedTransport};
    use super::*;
    use crate::{Axis, MotionModel};
    use std::sync::Mutex;

    #[test]
    fn numbers_are_plain_decimals() {
        assert_eq!(fmt_num(12.5), "12.5");
        assert_eq!(fmt_num(-0.0000001), "0");
        assert_eq!(fmt_num(3.0), "3");
        assert_eq!(fmt_num(-1e-3), "-0.001");
    }

    /// A scripted one-axis ESP: moves complete after two `MD?` polls; `fault` injects an
    /// error code into the queue at the end of the n-th move.
    fn esp(
        mut hook: impl FnMut(&str, u32) -> Option<Vec<ScriptReply>> + Send + 'static,
        fault_on_move: Option<(u32, u32)>,
    ) -> impl FnMut(&str) -> Vec<ScriptReply> + Send + 'static {
        let mut pos = 0.0f64;
        let mut md_left = 0u32;
        let mut errors: Vec<u32> = Vec::new();
        let mut moves = 0u32;
        let mut on = false;
        let mut counts = std::collections::HashMap::<String, u32>::new();
        move |line| {
            let key: String = line.chars().filter(|c| c.is_ascii_alphabetic() || *c == '?').collect();
            let n = counts.entry(key.clone()).or_default();
            *n += 1;
            if let Some(r) = hook(&key, *n) {
                return r;
            }
            match key.as_str() {
                "MO" => {
                    on = true;
                    vec![]
                }
                "OR" => {
                    pos = 0.0;
                    md_left = 1;
                    vec![]
                }
                "PA" => {
                    if !on {
                        errors.push(113);
                        return vec![];
                    }
                    let x: f64 = line[3..].parse().unwrap();
                    if x.abs() > 170.0 {
                        errors.push(if x > 0.0 { 106 } else { 107 });
                        return vec![];
                    }
                    moves += 1;
                    pos = x;
                    md_left = 2;
                    if let Some((m, code)) = fault_on_move {
                        if m == moves {
                            errors.push(code);
                            pos = x / 2.0;
                        }
                    }
                    vec![]
                }
                "MD?" => {
                    let done = md_left == 0;
                    md_left = md_left.saturating_sub(1);
                    vec![ScriptReply::line(if done { "1" } else { "0" })]
                }
                "TP" => vec![ScriptReply::line(&format!("{pos:.5}"))],
                "SL?" => vec![ScriptReply::line("-170")],
                "SR?" => vec![ScriptReply::line("170")],
                "ST" => {
                    md_left = 0;
                    vec![]
                }
                "TB?" => {
                    if errors.is_empty() {
                        vec![ScriptReply::line("0, 0, NO ERROR DETECTED")]
                    } else {
                        let c = errors.remove(0);
                        vec![ScriptReply::line(&format!("{c}, 1234, ERROR {c}"))]
                    }
                }
                "VE?" => vec![ScriptReply::line("ESP300 Version 3.08 09/09/02")],
                _ => {
                    errors.push(6);
                    vec![]
                }
            }
        }
    }

    fn axis(
        f: impl FnMut(&str) -> Vec<ScriptReply> + Send + 'static,
    ) -> (PolicyAxis<EspAxis>, Arc<Mutex<Vec<String>>>) {
        let t = ScriptedTransport::new(f);
        let log = t.log();
        let port = Arc::new(EspPort::with_transport(
            "scripted",
            Box::new(t),
            Duration::from_millis(80),
        ));
        let m = MotionModel {
            max_velocity: 1.0,
            acceleration: 10.0,
            jerk: None,
            settle_time: 0.0,
            deadband: 1e-5,
        };
        let p = MotionPolicy {
            poll_interval: Duration::from_millis(1),
            timeout_floor_s: 0.5,
            ..MotionPolicy::default()
        };
        let lim = SoftLimits { min: -3.2, max: 3.2 };
        let a = PolicyAxis::new(
            "light_arc",
            lim,
            m,
            p,
            EspAxis::new("light_arc", port, 1, 1f64.to_degrees()),
        );
        (a, log)
    }

    #[tokio::test]
    async fn flight_sets_va_ac_then_pa_and_restores_the_settings() {
        let (a, log) = axis(esp(
            |key, _| match key {
                "VA?" => Some(vec![ScriptReply::line("20.00000")]),
                "AC?" => Some(vec![ScriptReply::line("80.5")]),
                "VA" | "AC" => Some(vec![]),
                _ => None,
            },
            None,
        ));
        let log_handle = log.clone();
        a.home().await.unwrap();
        a.start_move_at(30f64.to_radians(), 15f64.to_radians()).await.unwrap();
        let rb = a.wait_idle().await.unwrap();
        assert!((rb.to_degrees() - 30.0).abs() < 1e-9);
        let log = log.lock().unwrap().clone();
        let sent: Vec<&str> = log
            .iter()
            .map(|l| l.trim_end())
            .filter(|l| l.contains("VA") || l.contains("AC") || l.contains("PA"))
            .collect();
        // the rig's acceleration (10 rad/s²) in degrees, 6 decimals
        assert_eq!(
            sent,
            ["1VA?", "1AC?", "1VA15", "1AC572.957795", "1PA30", "1VA20", "1AC80.5"],
            "{log:?}"
        );
        drop(log);
        // a stop-and-go move afterwards sends no VA/AC
        a.move_abs(0.1).await.unwrap();
        let log = log_handle.lock().unwrap().clone();
        let settings = log.iter().filter(|l| l.contains("VA") || l.contains("AC")).count();
        assert_eq!(settings, 6, "{log:?}");
    }

    #[tokio::test]
    async fn enable_home_move_read_back() {
        let (a, log) = axis(esp(|_, _| None, None));
        a.home().await.unwrap();
        let rb = a.move_abs(30f64.to_radians()).await.unwrap();
        assert!((rb.to_degrees() - 30.0).abs() < 1e-4, "{}", rb.to_degrees());
        let log = log.lock().unwrap().clone();
        assert!(
            log.contains(&"1MO".to_string()) && log.contains(&"1OR".to_string()),
            "{log:?}"
        );
        assert!(log.iter().any(|l| l.starts_with("1PA30")), "{log:?}");
        assert!(log.contains(&"1MD?".to_string()) && log.contains(&"1TP".to_string()));
        // controller soft limits ±170° narrow the rig's ±183°
        assert!((a.limits().max.to_degrees() - 170.0).abs() < 1e-9);
        assert_eq!(a.driver().version().unwrap(), "ESP300 Version 3.08 09/09/02");
    }

    #[tokio::test]
    async fn limit_switch_and_following_error_are_typed() {
        for (code, want) in [(104u32, "limit"), (105, "limit"), (103, "stall")] {
            let (a, _) = axis(esp(|_, _| None, Some((1, code))));
            a.home().await.unwrap();
            let e = a.move_abs(0.5).await.unwrap_err();
            let ok = match want {
                "limit" => {
                    matches!(&e, DeviceError::LimitSwitch { device, command } if device == "light_arc" && command.starts_with("1PA"))
                }
                _ => matches!(e, DeviceError::Stall { .. }),
            };
            assert!(ok, "{code}: {e}");
        }
    }

    #[tokio::test]
    async fn controller_rejection_is_reported_with_its_code() {
        let (_, _) = axis(esp(|_, _| None, None));
        let t = ScriptedTransport::new(esp(|_, _| None, None));
        let port = Arc::new(EspPort::with_transport(
            "scripted",
            Box::new(t),
            Duration::from_millis(80),
        ));
        let d = EspAxis::new("light_arc", port, 1, 1f64.to_degrees());
        // motor off: error 113
        match d.move_abs(0.1) {
            Err(DeviceError::Rejected { reason, command, .. }) => {
                assert!(reason.contains("113"), "{reason}");
                assert!(command.starts_with("1PA"));
            }
            r => panic!("{r:?}"),
        }
        d.home().unwrap();
        // beyond the controller's software limit: 106
        match d.move_abs(3.1) {
            Err(DeviceError::Rejected { reason, .. }) => assert!(reason.contains("106"), "{reason}"),
            r => panic!("{r:?}"),
        }
    }

    #[tokio::test]
    async fn garbled_position_is_retried_then_typed() {
        let (a, _) = axis(esp(
            |k, n| (k == "TP" && n == 1).then(|| vec![ScriptReply::line("1.2.3x")]),
            None,
        ));
        a.home().await.unwrap(); // one garbled TP, retried
        let (a, _) = axis(esp(|k, _| (k == "TP").then(|| vec![ScriptReply::line("#?")]), None));
        match a.position().await.unwrap_err() {
            DeviceError::Garbled { command, .. } => assert_eq!(command, "1TP"),
            e => panic!("{e}"),
        }
    }

    #[tokio::test]
    async fn dropped_reply_times_out_and_late_bytes_are_not_misread() {
        // The first MD? answers late (after the timeout): the retry must not read "0"
        // from that late reply as the answer to the next query.
        let (a, _) = axis(esp(
            |k, n| {
                (k == "MD?" && n == 1)
                    .then(|| vec![ScriptReply::Delay(Duration::from_millis(120)), ScriptReply::line("0")])
            },
            None,
        ));
        a.home().await.unwrap();
        assert_eq!(a.position().await.unwrap(), 0.0);
        let (a, _) = axis(esp(|k, _| (k == "MD?").then(Vec::new), None));
        assert!(matches!(a.home().await.unwrap_err(), DeviceError::Timeout { .. }));
    }

    #[tokio::test]
    async fn disconnect_is_typed() {
        let (a, _) = axis(esp(|k, _| (k == "TP").then(|| vec![ScriptReply::Disconnect]), None));
        assert!(matches!(
            a.position().await.unwrap_err(),
            DeviceError::Disconnected { .. }
        ));
    }
}
