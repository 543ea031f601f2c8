//! The lamp's programmable power supply: Rohde & Schwarz (formerly Hameg) HMP series
//! (HMP4040, HMP4030, HMP2030, HMP2020) over its serial port (RS-232 or the USB virtual COM
//! port), speaking SCPI.
//!
//! Commands are lines terminated by LF; set commands are silent, queries answer one line:
//! - `*IDN?` → `ROHDE&SCHWARZ,HMP4040,<serial>,HW…/SW…` (maker, model, serial, firmware);
//! - `INST:NSEL n` selects channel n (every later command acts on it);
//! - `APPL v,i` sets the selected channel's voltage and current limit (`VOLT v`, `CURR i`
//!   one at a time);
//! - `OUTP:SEL 1|0` activates / deactivates the selected channel, `OUTP:GEN 1|0` switches
//!   the outputs of all active channels (a channel supplies power only when both are on);
//! - `MEAS:VOLT?`, `MEAS:CURR?` measure the selected channel's output;
//! - `SYST:ERR?` pops the error queue: `0,"No error"` or e.g. `-113,"Undefined header"`.
//!
//! As with the ESP300, a set command's failure shows only in the error queue, so the
//! driver reads `SYST:ERR?` after every set command and turns a non-zero code into a typed
//! error; a reply that does not parse is `Garbled`, a missing one a `Timeout`, and either
//! is retried (`retries`) after the link dropped any late bytes ([`super::Link`]).
//!
//! Rig file (`[light] backend = "hmp"`), options:
//! - `port` (required; `${VAR}` substitution), `baud` (9600), `channel` (1),
//! - `voltage` (V, required) and `current` (A, the current limit, required),
//! - `settle_s` (1.0: seconds waited after switching, so the filament reaches its
//!   temperature before a frame), `reply_timeout_ms` (1000), `retries` (2),
//! - `drift_threshold`, `output_exponent`: the lamp monitor's, read by
//!   [`crate::rig::RigSpec::lamp_monitor`] for any backend;
//! - `warmup_tolerance`, `warmup_interval_s`, `warmup_timeout_s`: the warm-up wait before
//!   a run's first frame, read by [`crate::rig::RigSpec::lamp_warmup`].
//!
//! `intensity` ∈ [0, 1] scales the voltage: the channel is set to `voltage × intensity`
//! with the current limit `current` (constant-voltage operation; a halogen lamp's output
//! is not linear in either, see `docs/guide/hardware.md`). Intensity 0 or `on = false`
//! deactivates the channel.

use super::{LinePort, Options, SerialConfigError, SerialTransport, Transport};
use crate::{DeviceError, LampReading, Light};
use async_trait::async_trait;
use std::sync::Arc;
use std::time::Duration;

/// Line terminator sent after each command.
pub const TERMINATOR: &str = "\n";

/// Largest voltage and current an HMP channel sets (HMP4040: 32 V, 10 A).
pub const MAX_VOLTAGE_V: f64 = 32.05;
pub const MAX_CURRENT_A: f64 = 10.01;

/// Option keys of the `hmp` light (the lamp monitor's included).
pub const HMP_KEYS: &[&str] = &[
    "port",
    "baud",
    "channel",
    "voltage",
    "current",
    "settle_s",
    "reply_timeout_ms",
    "retries",
    "drift_threshold",
    "output_exponent",
    "warmup_tolerance",
    "warmup_interval_s",
    "warmup_timeout_s",
];

/// Channels of an HMP model named in its `*IDN?` (`None`: not an HMP model we know).
pub fn channels_of(model: &str) -> Option<u8> {
    match model.trim().to_ascii_uppercase().as_str() {
        "HMP4040" => Some(4),
        "HMP4030" | "HMP2030" => Some(3),
        "HMP2020" => Some(2),
        _ => None,
    }
}

/// The rig-file options of an `hmp` light.
#[derive(Clone, Debug, PartialEq)]
pub struct HmpConfig {
    pub port: String,
    pub baud: u32,
    pub channel: u8,
    /// Voltage at full intensity (V).
    pub voltage: f64,
    /// Current limit (A).
    pub current: f64,
    /// Wait after switching.
    pub settle: Duration,
    pub reply_timeout: Duration,
    /// Retries of an exchange that failed transiently (timeout, garbled, disconnect).
    pub retries: u32,
}

impl HmpConfig {
    /// Read and check the `[light]` options; an error names `light.options.KEY` and what
    /// the value must be.
    pub fn from_options(o: &Options<'_>) -> Result<Self, SerialConfigError> {
        o.deny_unknown(HMP_KEYS)?;
        let port = o.string("port")?.ok_or_else(|| {
            o.invalid(
                "port",
                "missing: the supply's serial port, e.g. \"/dev/ttyACM0\" or \"${GONIO_LAMP_PORT}\"".into(),
            )
        })?;
        let within = |key: &str, max: f64, what: &str| -> Result<f64, SerialConfigError> {
            let x = o.f64(key)?.ok_or_else(|| {
                o.invalid(
                    key,
                    format!("missing: the lamp's {what}, e.g. {key} = 12.0 (0 < {key} ≤ {max})"),
                )
            })?;
            if x > 0.0 && x <= max {
                Ok(x)
            } else {
                Err(o.invalid(
                    key,
                    format!("{x}: must be in (0, {max}] (the HMP's range; the lamp's {what})"),
                ))
            }
        };
        let voltage = within("voltage", MAX_VOLTAGE_V, "rated voltage in volts")?;
        let current = within("current", MAX_CURRENT_A, "current limit in amperes")?;
        let settle_s = o.non_negative("settle_s", 1.0)?;
        if settle_s > 600.0 {
            return Err(o.invalid("settle_s", format!("{settle_s}: must be in [0, 600] seconds")));
        }
        Ok(HmpConfig {
            port,
            baud: o.int("baud", 9600, 300, 921_600)? as u32,
            channel: o.int("channel", 1, 1, 4)? as u8,
            voltage,
            current,
            settle: Duration::from_secs_f64(settle_s),
            reply_timeout: Duration::from_millis(o.int("reply_timeout_ms", 1000, 1, 60_000)? as u64),
            retries: o.int("retries", 2, 0, 20)? as u32,
        })
    }
}

/// One entry of the SCPI error queue.
#[derive(Clone, Debug, PartialEq)]
pub struct ScpiError {
    pub code: i32,
    pub message: String,
}

/// Parse a `SYST:ERR?` reply: `code,"message"`.
pub fn parse_error(reply: &str) -> Option<ScpiError> {
    let (code, msg) = reply.split_once(',').unwrap_or((reply, ""));
    let code = code.trim().parse::<i32>().ok()?;
    Some(ScpiError {
        code,
        message: msg.trim().trim_matches('"').to_string(),
    })
}

/// Numbers as sent: plain decimals, no exponent, at most `decimals` places.
fn fmt_num(x: f64, decimals: usize) -> String {
    let s = format!("{x:.decimals$}");
    let s = if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.')
    } else {
        s.as_str()
    };
    if s.is_empty() || s == "-0" {
        "0".into()
    } else {
        s.to_string()
    }
}

/// The serial line to the supply.
pub struct HmpPort {
    line: LinePort,
}

impl std::ops::Deref for HmpPort {
    type Target = LinePort;
    fn deref(&self) -> &LinePort {
        &self.line
    }
}

impl HmpPort {
    pub fn open(path: &str, baud: u32, reply_timeout: Duration) -> std::io::Result<HmpPort> {
        Ok(Self::with_transport(
            path,
            Box::new(SerialTransport::open(path, baud)?),
            reply_timeout,
        ))
    }

    pub fn with_transport(path: &str, transport: Box<dyn Transport>, reply_timeout: Duration) -> HmpPort {
        HmpPort {
            line: LinePort::new(path, transport, reply_timeout, TERMINATOR),
        }
    }

    /// Pop one entry of the error queue (`SYST:ERR?`); code 0 = empty.
    pub fn error(&self, who: &str) -> Result<ScpiError, DeviceError> {
        let r = self.query(who, "SYST:ERR?")?;
        parse_error(&r).ok_or_else(|| self.garbled(who, "SYST:ERR?", &r, "expected `code,\"message\"`"))
    }
}

/// The blocking driver: one channel of one supply.
pub struct HmpDriver {
    name: String,
    port: Arc<HmpPort>,
    config: HmpConfig,
}

impl HmpDriver {
    pub fn new(name: &str, port: Arc<HmpPort>, config: HmpConfig) -> Self {
        HmpDriver {
            name: name.to_string(),
            port,
            config,
        }
    }

    pub fn config(&self) -> &HmpConfig {
        &self.config
    }

    /// One exchange, again after a transient failure (at most `retries` more times): a
    /// retry repeats only the exchange that failed, so a sequence of commands is not
    /// started over (and a fault that recurs every few replies cannot defeat it).
    fn retried<T>(&self, f: impl FnMut() -> Result<T, DeviceError>) -> Result<T, DeviceError> {
        retry(self.config.retries, f)
    }

    fn error(&self) -> Result<ScpiError, DeviceError> {
        self.retried(|| self.port.error(&self.name))
    }

    /// `*IDN?`: maker, model, serial number, firmware (the reply as it came).
    pub fn identify(&self) -> Result<String, DeviceError> {
        let r = self.retried(|| self.port.query(&self.name, "*IDN?"))?;
        if r.split(',').count() < 2 {
            return Err(self
                .port
                .garbled(&self.name, "*IDN?", &r, "expected `maker,model,serial,firmware`"));
        }
        Ok(r)
    }

    /// Empty the error queue (old entries must not be blamed on the next command);
    /// bounded: the queue holds a few entries.
    pub fn clear_errors(&self) -> Result<(), DeviceError> {
        for _ in 0..32 {
            if self.error()?.code == 0 {
                break;
            }
        }
        Ok(())
    }

    /// Read the error queue after `command`: its first entry is the command's error.
    pub fn check(&self, command: &str) -> Result<(), DeviceError> {
        let e = self.error()?;
        if e.code == 0 {
            return Ok(());
        }
        for _ in 0..32 {
            match self.error() {
                Ok(ScpiError { code: 0, .. }) | Err(_) => break,
                Ok(more) => tracing::warn!(light = %self.name, "further SCPI error {}: {}", more.code, more.message),
            }
        }
        let reason = format!("SCPI error {}: {}", e.code, e.message);
        let (device, command) = (self.name.clone(), command.to_string());
        // -100 … -199 command errors, -200 … -299 execution errors: the supply refused.
        Err(if (-299..=-100).contains(&e.code) {
            DeviceError::Rejected {
                device,
                command,
                reason,
            }
        } else {
            DeviceError::Other {
                device,
                command,
                reason,
            }
        })
    }

    fn write_checked(&self, command: &str) -> Result<(), DeviceError> {
        self.retried(|| self.port.write(&self.name, command))?;
        self.check(command)
    }

    fn select(&self) -> Result<(), DeviceError> {
        self.write_checked(&format!("INST:NSEL {}", self.config.channel))
    }

    /// Switch the channel: on with `voltage × intensity` and the current limit, or off.
    pub fn switch(&self, on: bool, intensity: f64) -> Result<(), DeviceError> {
        if !(0.0..=1.0).contains(&intensity) {
            return Err(DeviceError::Rejected {
                device: self.name.clone(),
                command: format!("set intensity {intensity}"),
                reason: "intensity must be in [0, 1]".into(),
            });
        }
        self.select()?;
        if on && intensity > 0.0 {
            let v = self.config.voltage * intensity;
            self.write_checked(&format!("APPL {},{}", fmt_num(v, 3), fmt_num(self.config.current, 4)))?;
            self.write_checked("OUTP:SEL 1")?;
            self.write_checked("OUTP:GEN 1")
        } else {
            self.write_checked("OUTP:SEL 0")
        }
    }

    /// The channel's measured output.
    pub fn measure(&self) -> Result<LampReading, DeviceError> {
        self.select()?;
        let voltage_v = self.retried(|| self.port.query_number(&self.name, "MEAS:VOLT?"))?;
        let current_a = self.retried(|| self.port.query_number(&self.name, "MEAS:CURR?"))?;
        Ok(LampReading { voltage_v, current_a })
    }
}

/// A [`Light`] on an HMP channel: the driver on tokio's blocking pool, and the settle time.
pub struct HmpLight {
    name: String,
    driver: Arc<HmpDriver>,
    identity: String,
}

impl HmpLight {
    /// Open the port, read the identity, empty the error queue and check the channel
    /// exists on this model. Fails with the option to fix.
    pub fn open(config: HmpConfig) -> Result<HmpLight, SerialConfigError> {
        let port = HmpPort::open(&config.port, config.baud, config.reply_timeout).map_err(|source| {
            SerialConfigError::LightOpen {
                port: config.port.clone(),
                source,
            }
        })?;
        Self::with_port(Arc::new(port), config)
    }

    /// As [`Self::open`] on a given port (tests: a scripted transport).
    pub fn with_port(port: Arc<HmpPort>, config: HmpConfig) -> Result<HmpLight, SerialConfigError> {
        let name = format!("hmp:{}:ch{}", port.path(), config.channel);
        let driver = HmpDriver::new(&name, port, config);
        let fail = |what: &str, e: DeviceError| SerialConfigError::Light {
            key: "port".into(),
            message: format!(
                "{what} failed ({e}); is an HMP supply on {} at {} baud?",
                driver.config.port, driver.config.baud
            ),
        };
        let identity = driver.identify().map_err(|e| fail("*IDN?", e))?;
        let model = identity.split(',').nth(1).unwrap_or("").trim();
        match channels_of(model) {
            Some(n) if driver.config.channel > n => {
                return Err(SerialConfigError::Light {
                    key: "channel".into(),
                    message: format!("{}: the {model} has channels 1 ..= {n}", driver.config.channel),
                })
            }
            Some(_) => {}
            None => tracing::warn!(
                light = %name,
                "`{identity}` is not an HMP model this driver knows (HMP4040/4030/2030/2020); continuing"
            ),
        }
        driver.clear_errors().map_err(|e| fail("SYST:ERR?", e))?;
        tracing::info!(light = %name, "lamp supply: {identity}");
        Ok(HmpLight {
            name,
            driver: Arc::new(driver),
            identity,
        })
    }

    pub fn driver(&self) -> &HmpDriver {
        &self.driver
    }

    async fn blocking<T: Send + 'static>(
        &self,
        what: &str,
        f: impl Fn(&HmpDriver) -> Result<T, DeviceError> + Send + Sync + 'static,
    ) -> Result<T, DeviceError> {
        let d = self.driver.clone();
        tokio::task::spawn_blocking(move || f(&d)).await.unwrap_or_else(|e| {
            Err(DeviceError::Other {
                device: self.name.clone(),
                command: what.to_string(),
                reason: format!("driver task failed: {e}"),
            })
        })
    }
}

/// Run `f`, again after a transient failure, at most `retries` more times.
fn retry<T>(retries: u32, mut f: impl FnMut() -> Result<T, DeviceError>) -> Result<T, DeviceError> {
    let mut attempt = 0;
    loop {
        match f() {
            Err(e) if e.is_transient() && attempt < retries => {
                attempt += 1;
                tracing::warn!(light = %e.device(), "{e}; retrying ({attempt}/{retries})");
            }
            r => return r,
        }
    }
}

#[async_trait]
impl Light for HmpLight {
    fn name(&self) -> &str {
        &self.name
    }

    async fn set(&self, on: bool, intensity: f64) -> Result<(), DeviceError> {
        self.blocking("switch", move |d| d.switch(on, intensity)).await?;
        let settle = self.driver.config.settle;
        if !settle.is_zero() {
            tokio::time::sleep(settle).await;
        }
        Ok(())
    }

    async fn identity(&self) -> Result<String, DeviceError> {
        Ok(self.identity.clone())
    }

    async fn read_back(&self) -> Result<Option<LampReading>, DeviceError> {
        self.blocking("measure", |d| d.measure()).await.map(Some)
    }
}

#[cfg(test)]
mod tests {
    use super::super::testing::{ScriptReply, ScriptedTransport};
    use super::*;
    use std::collections::BTreeMap;
    use std::sync::Mutex;

    fn opts(pairs: &[(&str, toml::Value)]) -> BTreeMap<String, toml::Value> {
        pairs.iter().map(|(k, v)| (k.to_string(), v.clone())).collect()
    }

    fn good() -> BTreeMap<String, toml::Value> {
        opts(&[
            ("port", toml::Value::String("/dev/ttyACM0".into())),
            ("voltage", toml::Value::Float(12.0)),
            ("current", toml::Value::Float(9.0)),
        ])
    }

    #[test]
    fn options_defaults_and_errors_name_the_key() {
        let m = good();
        let c = HmpConfig::from_options(&Options::for_light(&m)).unwrap();
        assert_eq!((c.channel, c.baud, c.retries), (1, 9600, 2));
        assert_eq!(c.settle, Duration::from_secs(1));
        for (key, value, want) in [
            ("voltage", toml::Value::Float(40.0), "light.options.voltage"),
            ("current", toml::Value::Float(-1.0), "light.options.current"),
            ("channel", toml::Value::Integer(5), "light.options.channel"),
            ("settle_s", toml::Value::Float(-0.5), "light.options.settle_s"),
            ("voltag", toml::Value::Float(1.0), "light.options.voltag"),
            ("current", toml::Value::String("lots".into()), "light.options.current"),
        ] {
            let mut m = good();
            m.insert(key.into(), value);
            let e = HmpConfig::from_options(&Options::for_light(&m))
                .unwrap_err()
                .to_string();
            assert!(e.starts_with(want), "{e}");
        }
        let mut m = good();
        m.remove("voltage");
        let e = HmpConfig::from_options(&Options::for_light(&m))
            .unwrap_err()
            .to_string();
        assert!(e.contains("light.options.voltage") && e.contains("missing"), "{e}");
    }

    #[test]
    fn error_queue_replies_parse() {
        assert_eq!(
            parse_error("-113,\"Undefined header\""),
            Some(ScpiError {
                code: -113,
                message: "Undefined header".into()
            })
        );
        assert_eq!(parse_error("0,\"No error\"").unwrap().code, 0);
        assert_eq!(parse_error("garbage"), None);
        assert_eq!(fmt_num(12.0, 3), "12");
        assert_eq!(fmt_num(8.33333, 4), "8.3333");
        assert_eq!(fmt_num(0.0, 3), "0");
    }

    /// A scripted HMP: answers the command set, queues -113 for anything else; `hook` may
    /// replace the reply to the n-th occurrence of a command.
    fn hmp(
        mut hook: impl FnMut(&str, u32) -> Option<Vec<ScriptReply>> + Send + 'static,
    ) -> impl FnMut(&str) -> Vec<ScriptReply> + Send + 'static {
        let mut errors: Vec<String> = Vec::new();
        let mut counts = std::collections::HashMap::<String, u32>::new();
        let (mut v, mut on) = (0.0f64, false);
        move |line| {
            let head = line.split_whitespace().next().unwrap_or("").to_string();
            let n = counts.entry(head.clone()).or_default();
            *n += 1;
            if let Some(r) = hook(&head, *n) {
                return r;
            }
            match head.as_str() {
                "*IDN?" => vec![ScriptReply::line("ROHDE&SCHWARZ,HMP2020,100001,HW50020001/SW2.70")],
                "INST:NSEL" => {
                    if !matches!(line.split_whitespace().nth(1), Some("1" | "2")) {
                        errors.push("-222,\"Data out of range\"".into());
                    }
                    vec![]
                }
                "APPL" => {
                    let x: f64 = line[5..].split(',').next().unwrap().parse().unwrap();
                    if x > MAX_VOLTAGE_V {
                        errors.push("-222,\"Data out of range\"".into());
                    } else {
                        v = x;
                    }
                    vec![]
                }
                "OUTP:SEL" => {
                    on = line.ends_with('1');
                    vec![]
                }
                "OUTP:GEN" => vec![],
                "MEAS:VOLT?" => vec![ScriptReply::line(&format!("{:.3}", if on { v } else { 0.0 }))],
                "MEAS:CURR?" => vec![ScriptReply::line(&format!("{:.4}", if on { v / 1.44 } else { 0.0 }))],
                "SYST:ERR?" => {
                    let e = if errors.is_empty() {
                        "0,\"No error\"".to_string()
                    } else {
                        errors.remove(0)
                    };
                    vec![ScriptReply::line(&e)]
                }
                _ => {
                    errors.push("-113,\"Undefined header\"".into());
                    vec![]
                }
            }
        }
    }

    fn light(
        f: impl FnMut(&str) -> Vec<ScriptReply> + Send + 'static,
        channel: u8,
    ) -> (Result<HmpLight, SerialConfigError>, Arc<Mutex<Vec<String>>>) {
        let t = ScriptedTransport::new(f);
        let log = t.log();
        let port = Arc::new(HmpPort::with_transport(
            "scripted",
            Box::new(t),
            Duration::from_millis(80),
        ));
        let mut m = good();
        m.insert("channel".into(), toml::Value::Integer(channel as i64));
        m.insert("settle_s".into(), toml::Value::Float(0.0));
        let c = HmpConfig::from_options(&Options::for_light(&m)).unwrap();
        (HmpLight::with_port(port, c), log)
    }

    #[tokio::test]
    async fn switch_measure_and_identity() {
        let (l, log) = light(hmp(|_, _| None), 2);
        let l = l.unwrap();
        assert!(l.identity().await.unwrap().contains("HMP2020"));
        l.set(true, 0.5).await.unwrap();
        let r = l.read_back().await.unwrap().unwrap();
        assert_eq!(r.voltage_v, 6.0);
        assert!((r.current_a - 6.0 / 1.44).abs() < 1e-4, "{r:?}");
        l.set(false, 0.0).await.unwrap();
        assert_eq!(l.read_back().await.unwrap().unwrap().current_a, 0.0);
        let log = log.lock().unwrap().clone();
        for cmd in [
            "*IDN?",
            "INST:NSEL 2",
            "APPL 6,9",
            "OUTP:SEL 1",
            "OUTP:GEN 1",
            "OUTP:SEL 0",
        ] {
            assert!(log.iter().any(|l| l == cmd), "{cmd} not in {log:?}");
        }
        // every set command is followed by an error-queue check
        let i = log.iter().position(|l| l == "APPL 6,9").unwrap();
        assert_eq!(log[i + 1], "SYST:ERR?");
    }

    #[tokio::test]
    async fn a_channel_the_model_lacks_names_the_option() {
        let (l, _) = light(hmp(|_, _| None), 3);
        let e = l.err().unwrap().to_string();
        assert!(e.contains("light.options.channel") && e.contains("HMP2020"), "{e}");
    }

    #[tokio::test]
    async fn a_rejected_command_is_typed_with_its_scpi_error() {
        // 40 V is beyond the supply's range: the scripted HMP queues -222 for it.
        let (l, _) = light(hmp(|_, _| None), 1);
        let l = l.unwrap();
        l.driver().write_checked("APPL 6,1").unwrap();
        match l.driver().write_checked("APPL 40,1").unwrap_err() {
            DeviceError::Rejected { command, reason, .. } => {
                assert_eq!(command, "APPL 40,1");
                assert!(
                    reason.contains("-222") && reason.contains("Data out of range"),
                    "{reason}"
                );
            }
            e => panic!("{e}"),
        }
        match l.driver().write_checked("VOLT:FOO 1").unwrap_err() {
            DeviceError::Rejected { reason, .. } => assert!(reason.contains("-113"), "{reason}"),
            e => panic!("{e}"),
        }
        // the queue is empty again: the next command is not blamed
        l.set(true, 1.0).await.unwrap();
        match l.set(true, 1.5).await.unwrap_err() {
            DeviceError::Rejected { reason, .. } => assert!(reason.contains("[0, 1]"), "{reason}"),
            e => panic!("{e}"),
        }
    }

    #[tokio::test]
    async fn garbled_and_dropped_replies_are_retried_then_typed() {
        let (l, _) = light(
            hmp(|h, n| (h == "MEAS:CURR?" && n == 1).then(|| vec![ScriptReply::line("8.3#x")])),
            1,
        );
        let l = l.unwrap();
        l.set(true, 1.0).await.unwrap();
        let r = l.read_back().await.unwrap().unwrap();
        assert!((r.current_a - 12.0 / 1.44).abs() < 1e-4);
        let (l, _) = light(hmp(|h, _| (h == "MEAS:VOLT?").then(Vec::new)), 1);
        let l = l.unwrap();
        match l.read_back().await.unwrap_err() {
            DeviceError::Timeout { command, .. } => assert_eq!(command, "MEAS:VOLT?"),
            e => panic!("{e}"),
        }
        let (l, _) = light(hmp(|h, _| (h == "*IDN?").then(|| vec![ScriptReply::Disconnect])), 1);
        let e = l.err().unwrap().to_string();
        assert!(e.contains("light.options.port") && e.contains("*IDN?"), "{e}");
    }
}
