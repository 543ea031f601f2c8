//! Serial devices: motor controllers (Zaber ASCII protocol v2, Newport ESP300/ESP301) and
//! the lamp's programmable power supply (Rohde & Schwarz HMP series, SCPI: [`hmp`]).
//!
//! Layers, bottom up:
//! - [`Transport`]: raw bytes with a read timeout. [`SerialTransport`] is a real port (crate
//!   `serialport`, built without libudev), [`testing::ScriptedTransport`] an in-memory fake
//!   that answers with canned, garbled, late or missing replies so every error path can be
//!   tested without hardware.
//! - [`Link`]: line framing on top of a transport, plus the "dirty" flag that makes the next
//!   command discard whatever late bytes a failed exchange left in the input buffer.
//! - Protocol ports ([`zaber::ZaberPort`], [`esp300::EspPort`]): one per serial port, shared
//!   by every axis on it (a daisy chain or a multi-axis controller) through a mutex, so one
//!   request/reply exchange is never interleaved with another axis' exchange.
//! - Per-axis drivers implementing [`policy::Driver`]; [`policy::PolicyAxis`] turns a driver
//!   into a `gonio_devices::Axis` with the motion policy (settle, deadband, backlash,
//!   retries, timeouts from the motion model, stall detection).
//!
//! All I/O is blocking and runs on tokio's blocking pool (`spawn_blocking`), because serial
//! ports are file descriptors with termios timeouts, not async sources.

pub mod esp300;
pub mod hmp;
pub mod list;
pub mod policy;
pub mod zaber;

use crate::rig::AxisSpec;
use crate::{Axis, DeviceError};
use std::collections::{BTreeMap, HashMap};
use std::io;
use std::sync::Arc;
use std::time::{Duration, Instant};
use thiserror::Error;

/// Raw bytes with a read timeout.
pub trait Transport: Send {
    fn write_all(&mut self, data: &[u8]) -> io::Result<()>;
    /// Read what is available, waiting at most `timeout`; `Ok(0)` means nothing arrived.
    fn read_some(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize>;
    /// Try to open the port again after an I/O error (a USB adapter that re-enumerated, an
    /// emulator that restarted on the same path). The default cannot.
    fn reopen(&mut self) -> io::Result<()> {
        Err(io::Error::new(
            io::ErrorKind::Unsupported,
            "this transport cannot reopen",
        ))
    }
}

/// A real serial port (or a pty: the emulators in `gonio-simulator` serve one).
pub struct SerialTransport {
    path: String,
    baud: u32,
    port: Option<Box<dyn serialport::SerialPort>>,
}

impl SerialTransport {
    pub fn open(path: &str, baud: u32) -> io::Result<SerialTransport> {
        let mut t = SerialTransport {
            path: path.to_string(),
            baud,
            port: None,
        };
        t.reopen()?;
        Ok(t)
    }

    fn port(&mut self) -> io::Result<&mut Box<dyn serialport::SerialPort>> {
        match self.port {
            Some(ref mut p) => Ok(p),
            None => Err(io::Error::new(io::ErrorKind::NotConnected, "port is closed")),
        }
    }
}

fn serial_to_io(e: serialport::Error) -> io::Error {
    match e.kind {
        serialport::ErrorKind::Io(kind) => io::Error::new(kind, e.description),
        serialport::ErrorKind::NoDevice => io::Error::new(io::ErrorKind::NotFound, e.description),
        _ => io::Error::other(e.description),
    }
}

impl Transport for SerialTransport {
    fn write_all(&mut self, data: &[u8]) -> io::Result<()> {
        let r = self.port().and_then(|p| {
            p.write_all(data)?;
            p.flush()
        });
        if r.is_err() {
            self.port = None;
        }
        r
    }

    fn read_some(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        let p = self.port()?;
        p.set_timeout(timeout.max(Duration::from_millis(1)))
            .map_err(serial_to_io)?;
        match p.read(buf) {
            Ok(0) => {
                // A tty read returning 0 bytes after a poll said "readable" is a hang-up.
                self.port = None;
                Err(io::Error::new(io::ErrorKind::UnexpectedEof, "port hung up"))
            }
            Ok(n) => Ok(n),
            Err(e) if e.kind() == io::ErrorKind::TimedOut || e.kind() == io::ErrorKind::WouldBlock => Ok(0),
            Err(e) => {
                self.port = None;
                Err(e)
            }
        }
    }

    fn reopen(&mut self) -> io::Result<()> {
        self.port = None;
        let port = serialport::new(&self.path, self.baud)
            .timeout(Duration::from_millis(100))
            .open()
            .map_err(serial_to_io)?;
        self.port = Some(port);
        Ok(())
    }
}

/// Line framing over a transport. Lines end with `\n`; a trailing `\r` is removed (both
/// protocols terminate replies with CR LF).
pub struct Link {
    transport: Box<dyn Transport>,
    buf: Vec<u8>,
    /// The last exchange failed part-way: late bytes may still arrive and must be dropped
    /// before the next command so they are not taken as its reply.
    dirty: bool,
    /// The transport failed with an I/O error; try `reopen` before the next command.
    broken: bool,
}

/// What went wrong on a link, before the protocol layer names the axis and the command.
#[derive(Debug)]
pub enum LinkError {
    Timeout,
    Io(io::Error),
}

impl Link {
    pub fn new(transport: Box<dyn Transport>) -> Link {
        Link {
            transport,
            buf: Vec::new(),
            dirty: false,
            broken: false,
        }
    }

    /// Prepare for a new exchange: reopen a broken transport, drop stale input.
    pub fn begin(&mut self) -> Result<(), LinkError> {
        if self.broken {
            self.transport.reopen().map_err(LinkError::Io)?;
            self.broken = false;
            self.dirty = true;
        }
        if self.dirty {
            self.drain(Duration::from_millis(30), Duration::from_millis(300))?;
            self.dirty = false;
        }
        Ok(())
    }

    /// Mark the link so the next exchange starts by draining late bytes.
    pub fn mark_dirty(&mut self) {
        self.dirty = true;
    }

    pub fn send(&mut self, line: &str) -> Result<(), LinkError> {
        tracing::trace!(target: "gonio::serial", "-> {:?}", line);
        self.transport.write_all(line.as_bytes()).map_err(|e| {
            self.broken = true;
            LinkError::Io(e)
        })
    }

    /// The next complete line, waiting until `deadline`.
    pub fn read_line(&mut self, deadline: Instant) -> Result<String, LinkError> {
        loop {
            if let Some(pos) = self.buf.iter().position(|&b| b == b'\n') {
                let mut line: Vec<u8> = self.buf.drain(..=pos).collect();
                line.pop();
                while line.last() == Some(&b'\r') {
                    line.pop();
                }
                let s = String::from_utf8_lossy(&line).into_owned();
                tracing::trace!(target: "gonio::serial", "<- {:?}", s);
                return Ok(s);
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(LinkError::Timeout);
            }
            let mut chunk = [0u8; 256];
            match self.transport.read_some(&mut chunk, deadline - now) {
                Ok(n) => self.buf.extend_from_slice(&chunk[..n]),
                Err(e) => {
                    self.broken = true;
                    return Err(LinkError::Io(e));
                }
            }
        }
    }

    /// Discard input until nothing arrived for `quiet` (at most `max` in total).
    pub fn drain(&mut self, quiet: Duration, max: Duration) -> Result<usize, LinkError> {
        let end = Instant::now() + max;
        let mut dropped = self.buf.len();
        self.buf.clear();
        let mut chunk = [0u8; 256];
        while Instant::now() < end {
            match self.transport.read_some(&mut chunk, quiet) {
                Ok(0) => break,
                Ok(n) => dropped += n,
                Err(e) => {
                    self.broken = true;
                    return Err(LinkError::Io(e));
                }
            }
        }
        if dropped > 0 {
            tracing::debug!(target: "gonio::serial", "dropped {dropped} stale bytes");
        }
        Ok(dropped)
    }
}

/// A controller that speaks one command per line and answers a query with one line (the
/// ESP300 command set, SCPI supplies): the exchange both drivers share. Each driver keeps
/// its own parsing on top (`esp300::EspPort`, `hmp::HmpPort` dereference to it).
pub struct LinePort {
    path: String,
    reply_timeout: Duration,
    /// Appended to every command (`\r\n` for the ESP300, `\n` for SCPI).
    terminator: &'static str,
    link: std::sync::Mutex<Link>,
}

impl LinePort {
    pub fn new(
        path: &str,
        transport: Box<dyn Transport>,
        reply_timeout: Duration,
        terminator: &'static str,
    ) -> LinePort {
        LinePort {
            path: path.to_string(),
            reply_timeout,
            terminator,
            link: std::sync::Mutex::new(Link::new(transport)),
        }
    }

    pub fn path(&self) -> &str {
        &self.path
    }

    /// Send a command that has no reply.
    pub fn write(&self, who: &str, command: &str) -> Result<(), DeviceError> {
        let mut link = self.link.lock().unwrap_or_else(|p| p.into_inner());
        link.begin()
            .map_err(|e| link_error(who, command, self.reply_timeout, e))?;
        link.send(&format!("{command}{}", self.terminator)).map_err(|e| {
            link.mark_dirty();
            link_error(who, command, self.reply_timeout, e)
        })
    }

    /// Send a query and return its (trimmed, non-empty) reply line.
    pub fn query(&self, who: &str, command: &str) -> Result<String, DeviceError> {
        let mut link = self.link.lock().unwrap_or_else(|p| p.into_inner());
        let fail = |link: &mut Link, e| {
            link.mark_dirty();
            link_error(who, command, self.reply_timeout, e)
        };
        link.begin()
            .map_err(|e| link_error(who, command, self.reply_timeout, e))?;
        if let Err(e) = link.send(&format!("{command}{}", self.terminator)) {
            return Err(fail(&mut link, e));
        }
        let deadline = Instant::now() + self.reply_timeout;
        loop {
            match link.read_line(deadline) {
                Ok(l) if l.trim().is_empty() => continue,
                Ok(l) => return Ok(l.trim().to_string()),
                Err(e) => return Err(fail(&mut link, e)),
            }
        }
    }

    /// A reply that does not parse: the link is marked dirty (late bytes are dropped before
    /// the next command) and the error names the reply and why.
    pub fn garbled(&self, who: &str, command: &str, reply: &str, why: &str) -> DeviceError {
        self.link.lock().unwrap_or_else(|p| p.into_inner()).mark_dirty();
        DeviceError::Garbled {
            device: who.to_string(),
            command: command.to_string(),
            reply: format!("{reply} ({why})"),
        }
    }

    /// A query whose reply is one number.
    pub fn query_number(&self, who: &str, command: &str) -> Result<f64, DeviceError> {
        let r = self.query(who, command)?;
        r.parse::<f64>()
            .ok()
            .filter(|x| x.is_finite())
            .ok_or_else(|| self.garbled(who, command, &r, "expected a number"))
    }
}

/// Convert a link failure into the typed error naming the axis and the command.
pub fn link_error(device: &str, command: &str, timeout: Duration, e: LinkError) -> DeviceError {
    match e {
        LinkError::Timeout => DeviceError::Timeout {
            device: device.to_string(),
            command: command.to_string(),
            seconds: timeout.as_secs_f64(),
        },
        LinkError::Io(e) => DeviceError::Disconnected {
            device: device.to_string(),
            command: command.to_string(),
            reason: e.to_string(),
        },
    }
}

/// An invalid `options` entry of a serial axis in the rig file.
#[derive(Debug, Error)]
pub enum SerialConfigError {
    #[error("axis {axis}: options.{key}: {message}")]
    Invalid { axis: String, key: String, message: String },
    #[error("axis {axis}: cannot open serial port {port}: {source}")]
    Open {
        axis: String,
        port: String,
        source: io::Error,
    },
    #[error("axis {axis}: backend `{backend}` is not a serial backend (zaber, esp300)")]
    Backend { axis: String, backend: String },
    /// A `[light]` option of a serial lamp supply.
    #[error("light.options.{key}: {message}")]
    Light { key: String, message: String },
    #[error("light: cannot open serial port {port}: {source}")]
    LightOpen { port: String, source: io::Error },
}

/// Typed access to an axis' `options` table. String values may name environment variables
/// as `${NAME}` (e.g. `port = "${GONIO_PORT_0}"`): a pty path is only known when the
/// emulator runs, and a lab may keep port names out of shared rig files.
pub struct Options<'a> {
    axis: &'a str,
    map: &'a BTreeMap<String, toml::Value>,
    /// The `[light]` table's options (errors then name `light.options.KEY`).
    light: bool,
}

impl<'a> Options<'a> {
    pub fn new(axis: &'a str, map: &'a BTreeMap<String, toml::Value>) -> Self {
        Options {
            axis,
            map,
            light: false,
        }
    }

    /// The options of the rig file's `[light]` table.
    pub fn for_light(map: &'a BTreeMap<String, toml::Value>) -> Self {
        Options {
            axis: "light",
            map,
            light: true,
        }
    }

    /// The error for a wrong or missing `key`, naming it and what it must be.
    pub fn invalid(&self, key: &str, message: String) -> SerialConfigError {
        if self.light {
            return SerialConfigError::Light {
                key: key.to_string(),
                message,
            };
        }
        SerialConfigError::Invalid {
            axis: self.axis.to_string(),
            key: key.to_string(),
            message,
        }
    }

    pub fn string(&self, key: &str) -> Result<Option<String>, SerialConfigError> {
        match self.map.get(key) {
            None => Ok(None),
            Some(toml::Value::String(s)) => substitute_env(s).map(Some).map_err(|m| self.invalid(key, m)),
            Some(v) => Err(self.invalid(key, format!("{v}: expected a string"))),
        }
    }

    pub fn f64(&self, key: &str) -> Result<Option<f64>, SerialConfigError> {
        match self.map.get(key) {
            None => Ok(None),
            Some(toml::Value::Float(x)) if x.is_finite() => Ok(Some(*x)),
            Some(toml::Value::Integer(i)) => Ok(Some(*i as f64)),
            Some(toml::Value::String(s)) => {
                let t = substitute_env(s).map_err(|m| self.invalid(key, m))?;
                t.trim()
                    .parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .map(Some)
                    .ok_or_else(|| self.invalid(key, format!("{t:?}: expected a number")))
            }
            Some(v) => Err(self.invalid(key, format!("{v}: expected a number"))),
        }
    }

    pub fn positive(&self, key: &str, default: f64) -> Result<f64, SerialConfigError> {
        let x = self.f64(key)?.unwrap_or(default);
        if x > 0.0 {
            Ok(x)
        } else {
            Err(self.invalid(key, format!("{x}: must be > 0")))
        }
    }

    pub fn non_negative(&self, key: &str, default: f64) -> Result<f64, SerialConfigError> {
        let x = self.f64(key)?.unwrap_or(default);
        if x >= 0.0 {
            Ok(x)
        } else {
            Err(self.invalid(key, format!("{x}: must be ≥ 0")))
        }
    }

    pub fn int(&self, key: &str, default: i64, min: i64, max: i64) -> Result<i64, SerialConfigError> {
        let x = match self.f64(key)? {
            None => default,
            Some(x) if x.fract() == 0.0 => x as i64,
            Some(x) => return Err(self.invalid(key, format!("{x}: expected an integer"))),
        };
        if (min..=max).contains(&x) {
            Ok(x)
        } else {
            Err(self.invalid(key, format!("{x}: must be in [{min}, {max}]")))
        }
    }

    pub fn bool(&self, key: &str, default: bool) -> Result<bool, SerialConfigError> {
        match self.map.get(key) {
            None => Ok(default),
            Some(toml::Value::Boolean(b)) => Ok(*b),
            Some(v) => Err(self.invalid(key, format!("{v}: expected true or false"))),
        }
    }

    /// Reject keys this backend does not know (a typo must not silently fall back to a default).
    pub fn deny_unknown(&self, known: &[&str]) -> Result<(), SerialConfigError> {
        for k in self.map.keys() {
            if !known.contains(&k.as_str()) {
                return Err(self.invalid(k, format!("unknown option (known: {})", known.join(", "))));
            }
        }
        Ok(())
    }
}

/// Replace `${NAME}` with the environment variable's value; an unset variable is an error
/// that names it.
pub fn substitute_env(s: &str) -> Result<String, String> {
    let mut out = String::new();
    let mut rest = s;
    while let Some(start) = rest.find("${") {
        out.push_str(&rest[..start]);
        let after = &rest[start + 2..];
        let end = after.find('}').ok_or_else(|| format!("{s:?}: unterminated `${{`"))?;
        let name = &after[..end];
        let value = std::env::var(name).map_err(|_| format!("{s:?}: environment variable {name} is not set"))?;
        out.push_str(&value);
        rest = &after[end + 1..];
    }
    out.push_str(rest);
    Ok(out)
}

/// The backends this module provides, as named in rig files.
pub const BACKENDS: &[&str] = &["zaber", "esp300"];

/// How a serial controller will really run a fly-scan's constant-velocity move: its native
/// units quantize the commanded velocity and acceleration, and the planner must time the
/// exposures against what the controller runs, not against the rig file's round numbers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FlightProfile {
    /// One step of the controller's velocity data (axis units/s).
    pub velocity_step: f64,
    /// The acceleration the controller runs (axis units/s²): the rig file's, rounded to
    /// the controller's unit as the driver rounds it on the wire.
    pub acceleration: f64,
}

impl FlightProfile {
    /// The fastest velocity the controller runs that is not above `wanted` (so a blur or
    /// frame-rate bound that gave `wanted` still holds); 0 when `wanted` is below one step.
    pub fn velocity(&self, wanted: f64) -> f64 {
        if !(wanted.is_finite() && wanted > 0.0) {
            return 0.0;
        }
        // The tolerance keeps a velocity that already is a multiple of the step (up to
        // floating-point error) on that multiple.
        (wanted / self.velocity_step * (1.0 + 1e-12)).floor() * self.velocity_step
    }
}

/// The flight profile of a serial axis from its rig-file entry alone (`Ok(None)` for a
/// backend that is not a serial controller): `gonio plan` computes it without opening a
/// port. The driver converts the same way when it flies ([`zaber::speed_data`],
/// [`zaber::accel_data`]; the ESP takes 6 decimals of its user unit).
pub fn flight_profile(spec: &AxisSpec) -> Result<Option<FlightProfile>, SerialConfigError> {
    let opts = Options::new(&spec.name, &spec.options);
    let accel = spec.motion().acceleration;
    match spec.backend.as_str() {
        "zaber" => {
            let units = opts
                .f64("units_per_deg")?
                .filter(|u| *u > 0.0)
                .ok_or_else(|| opts.invalid("units_per_deg", "missing or not > 0: microsteps per degree".into()))?;
            let upr = units.to_degrees();
            let data = zaber::accel_data(accel, upr);
            if data < 1 {
                return Err(opts.invalid(
                    "units_per_deg",
                    format!(
                        "acceleration_deg_s2 {} is below one Zaber acceleration unit at {units} units/°",
                        spec.acceleration_deg_s2
                    ),
                ));
            }
            Ok(Some(FlightProfile {
                velocity_step: 1.0 / (upr * zaber::SPEED_SCALE),
                acceleration: data as f64 / (upr * zaber::ACCEL_SCALE),
            }))
        }
        "esp300" => {
            let upr = opts.positive("units_per_deg", 1.0)?.to_degrees();
            let step = esp300::VALUE_STEP / upr;
            Ok(Some(FlightProfile {
                velocity_step: step,
                acceleration: ((accel / step).round() * step).max(step),
            }))
        }
        _ => Ok(None),
    }
}

/// Opens each serial port once, however many axes of the rig file use it.
#[derive(Default)]
pub struct PortRegistry {
    zaber: HashMap<String, Arc<zaber::ZaberPort>>,
    esp: HashMap<String, Arc<esp300::EspPort>>,
}

impl PortRegistry {
    pub fn new() -> Self {
        Self::default()
    }

    /// Build the axis described by `spec` (backend `zaber` or `esp300`).
    pub fn build_axis(&mut self, spec: &AxisSpec) -> Result<Arc<dyn Axis>, SerialConfigError> {
        let opts = Options::new(&spec.name, &spec.options);
        let open_err = |port: &str, source: io::Error| SerialConfigError::Open {
            axis: spec.name.clone(),
            port: port.to_string(),
            source,
        };
        match spec.backend.as_str() {
            "zaber" => {
                let cfg = zaber::ZaberAxisConfig::from_options(&opts)?;
                let port = match self.zaber.get(&cfg.port) {
                    Some(p) => p.clone(),
                    None => {
                        let p = Arc::new(
                            zaber::ZaberPort::open(&cfg.port, cfg.baud, cfg.port_config())
                                .map_err(|e| open_err(&cfg.port, e))?,
                        );
                        self.zaber.insert(cfg.port.clone(), p.clone());
                        p
                    }
                };
                let policy = policy::MotionPolicy::from_options(&opts, spec)?;
                let driver = zaber::ZaberAxis::new(&spec.name, port, cfg.device, cfg.axis, cfg.units_per_rad())
                    .with_encoder(cfg.encoder);
                Ok(Arc::new(policy::PolicyAxis::new(
                    &spec.name,
                    spec.limits(),
                    spec.motion(),
                    policy,
                    driver,
                )))
            }
            "esp300" => {
                let cfg = esp300::EspAxisConfig::from_options(&opts)?;
                let port = match self.esp.get(&cfg.port) {
                    Some(p) => p.clone(),
                    None => {
                        let p = Arc::new(
                            esp300::EspPort::open(&cfg.port, cfg.baud, cfg.reply_timeout)
                                .map_err(|e| open_err(&cfg.port, e))?,
                        );
                        self.esp.insert(cfg.port.clone(), p.clone());
                        p
                    }
                };
                let policy = policy::MotionPolicy::from_options(&opts, spec)?;
                let driver = esp300::EspAxis::new(&spec.name, port, cfg.axis, cfg.units_per_rad());
                Ok(Arc::new(policy::PolicyAxis::new(
                    &spec.name,
                    spec.limits(),
                    spec.motion(),
                    policy,
                    driver,
                )))
            }
            other => Err(SerialConfigError::Backend {
                axis: spec.name.clone(),
                backend: other.to_string(),
            }),
        }
    }
}

/// Test support: an in-memory transport with scripted replies.
pub mod testing {
    use super::Transport;
    use std::collections::VecDeque;
    use std::io;
    use std::sync::{Arc, Mutex};
    use std::time::{Duration, Instant};

    /// What the fake device does in answer to one command line.
    #[derive(Clone, Debug)]
    pub enum ScriptReply {
        /// Send these bytes.
        Bytes(Vec<u8>),
        /// The bytes after this arrive `Duration` later (a slow device).
        Delay(Duration),
        /// The port goes away (reads and writes fail from then on).
        Disconnect,
    }

    impl ScriptReply {
        pub fn line(s: &str) -> ScriptReply {
            ScriptReply::Bytes(format!("{s}\r\n").into_bytes())
        }
    }

    type Responder = Box<dyn FnMut(&str) -> Vec<ScriptReply> + Send>;

    /// A fake port: every complete command line written is logged and handed to the
    /// responder, whose replies become readable (possibly later).
    pub struct ScriptedTransport {
        responder: Responder,
        inbox: VecDeque<(Instant, Vec<u8>)>,
        partial: Vec<u8>,
        disconnect_at: Option<Instant>,
        log: Arc<Mutex<Vec<String>>>,
    }

    impl ScriptedTransport {
        pub fn new(responder: impl FnMut(&str) -> Vec<ScriptReply> + Send + 'static) -> Self {
            ScriptedTransport {
                responder: Box::new(responder),
                inbox: VecDeque::new(),
                partial: Vec::new(),
                disconnect_at: None,
                log: Arc::new(Mutex::new(Vec::new())),
            }
        }

        /// The command lines written so far (shared: stays readable after the transport
        /// moved into a port).
        pub fn log(&self) -> Arc<Mutex<Vec<String>>> {
            self.log.clone()
        }

        fn gone(&self) -> bool {
            self.disconnect_at.is_some_and(|t| Instant::now() >= t)
        }
    }

    fn hung_up() -> io::Error {
        io::Error::new(io::ErrorKind::BrokenPipe, "scripted port disconnected")
    }

    impl Transport for ScriptedTransport {
        fn write_all(&mut self, data: &[u8]) -> io::Result<()> {
            if self.gone() {
                return Err(hung_up());
            }
            self.partial.extend_from_slice(data);
            while let Some(pos) = self.partial.iter().position(|&b| b == b'\n' || b == b'\r') {
                let line: Vec<u8> = self.partial.drain(..=pos).collect();
                let line = String::from_utf8_lossy(&line).trim().to_string();
                if line.is_empty() {
                    continue;
                }
                self.log.lock().expect("log poisoned").push(line.clone());
                let mut at = Instant::now();
                for r in (self.responder)(&line) {
                    match r {
                        ScriptReply::Bytes(b) => self.inbox.push_back((at, b)),
                        ScriptReply::Delay(d) => at += d,
                        ScriptReply::Disconnect => self.disconnect_at = Some(at),
                    }
                }
            }
            Ok(())
        }

        fn read_some(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
            let deadline = Instant::now() + timeout;
            loop {
                let now = Instant::now();
                if let Some(t) = self.disconnect_at {
                    let before_data = self.inbox.front().is_none_or(|(at, _)| *at >= t);
                    if now >= t && before_data {
                        return Err(hung_up());
                    }
                }
                if let Some((at, _)) = self.inbox.front() {
                    if *at <= now {
                        let (at, mut bytes) = self.inbox.pop_front().expect("front exists");
                        let n = bytes.len().min(buf.len());
                        buf[..n].copy_from_slice(&bytes[..n]);
                        if n < bytes.len() {
                            bytes.drain(..n);
                            self.inbox.push_front((at, bytes));
                        }
                        return Ok(n);
                    }
                }
                if now >= deadline {
                    return Ok(0);
                }
                let next = self.inbox.front().map(|(at, _)| *at).unwrap_or(deadline).min(deadline);
                let next = self.disconnect_at.map_or(next, |t| next.min(t.max(now)));
                std::thread::sleep(next.saturating_duration_since(now).min(Duration::from_millis(5)));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::testing::*;
    use super::*;

    fn spec(backend: &str, accel_deg_s2: f64, options: &str) -> AxisSpec {
        toml::from_str(&format!(
            r#"name = "lamp"
role = "light_azimuth"
backend = "{backend}"
min_deg = -180.0
max_deg = 180.0
max_velocity_deg_s = 30.0
acceleration_deg_s2 = {accel_deg_s2}
options = {{ port = "${{GONIO_NO_SUCH_PORT_VARIABLE}}", {options} }}
"#
        ))
        .unwrap()
    }

    #[test]
    fn flight_profile_rounds_like_the_controller_and_opens_no_port() {
        // Zaber, 1000 µsteps/°: one velocity step is 1/1638.4 °/s; 60 °/s² is ACCEL data
        // 9.8304 → 10, i.e. 10 / 0.16384 = 61.035 °/s². The port option names an unset
        // variable: the profile never reads it.
        let p = flight_profile(&spec("zaber", 60.0, "units_per_deg = 1000.0"))
            .unwrap()
            .unwrap();
        assert!((p.velocity_step.to_degrees() - 1.0 / 1638.4).abs() < 1e-15);
        assert!(
            (p.acceleration.to_degrees() - 10.0 / 0.16384).abs() < 1e-9,
            "{}",
            p.acceleration.to_degrees()
        );
        // velocities are rounded down to whole steps, and a whole step stays itself
        let v = p.velocity(19.05f64.to_radians());
        assert!(v <= 19.05f64.to_radians());
        let data = v.to_degrees() * 1638.4;
        assert!(
            (data - data.round()).abs() < 1e-6 && data.round() == (19.05 * 1638.4f64).floor(),
            "{data}"
        );
        assert_eq!(p.velocity(v), v);
        assert_eq!(
            zaber::speed_data(v, 1000f64.to_degrees()),
            (19.05 * 1638.4f64).floor() as i64
        );
        assert_eq!(p.velocity(0.1 * p.velocity_step), 0.0);
        assert_eq!(p.velocity(f64::NAN), 0.0);
        // an acceleration below one Zaber unit is a typed error naming the option
        let e = flight_profile(&spec("zaber", 0.01, "units_per_deg = 1.0")).unwrap_err();
        assert!(e.to_string().contains("below one Zaber acceleration unit"), "{e}");
        let e = flight_profile(&spec("zaber", 60.0, "device = 1")).unwrap_err();
        assert!(e.to_string().contains("units_per_deg"), "{e}");
        // ESP300 in degrees: 6 decimals
        let p = flight_profile(&spec("esp300", 60.0, "axis = 1")).unwrap().unwrap();
        assert!((p.velocity_step.to_degrees() - 1e-6).abs() < 1e-18);
        assert!((p.acceleration.to_degrees() - 60.0).abs() < 1e-9);
        assert!((p.velocity(12.3456789f64.to_radians()).to_degrees() - 12.345678).abs() < 1e-9);
        // simulated axes have no controller
        assert_eq!(flight_profile(&spec("sim", 60.0, "units_per_deg = 1.0")).unwrap(), None);
    }

    #[test]
    fn link_splits_lines_and_strips_cr() {
        let t = ScriptedTransport::new(|_| vec![ScriptReply::Bytes(b"a\r\nb\n".to_vec())]);
        let mut l = Link::new(Box::new(t));
        l.send("x\n").unwrap();
        let d = Instant::now() + Duration::from_millis(100);
        assert_eq!(l.read_line(d).unwrap(), "a");
        assert_eq!(l.read_line(d).unwrap(), "b");
        assert!(matches!(
            l.read_line(Instant::now() + Duration::from_millis(20)),
            Err(LinkError::Timeout)
        ));
    }

    #[test]
    fn dirty_link_drops_late_bytes_before_next_command() {
        let t = ScriptedTransport::new(|l| {
            if l == "first" {
                vec![ScriptReply::Delay(Duration::from_millis(60)), ScriptReply::line("late")]
            } else {
                vec![ScriptReply::line("fresh")]
            }
        });
        let mut l = Link::new(Box::new(t));
        l.send("first\n").unwrap();
        assert!(matches!(
            l.read_line(Instant::now() + Duration::from_millis(20)),
            Err(LinkError::Timeout)
        ));
        l.mark_dirty();
        std::thread::sleep(Duration::from_millis(60));
        l.begin().unwrap();
        l.send("second\n").unwrap();
        assert_eq!(
            l.read_line(Instant::now() + Duration::from_millis(100)).unwrap(),
            "fresh"
        );
    }

    #[test]
    fn env_substitution_names_missing_variable() {
        std::env::set_var("GONIO_TEST_SERIAL_PORT_X", "/dev/pts/7");
        assert_eq!(substitute_env("${GONIO_TEST_SERIAL_PORT_X}").unwrap(), "/dev/pts/7");
        assert_eq!(substitute_env("a${GONIO_TEST_SERIAL_PORT_X}b").unwrap(), "a/dev/pts/7b");
        let e = substitute_env("${GONIO_TEST_SURELY_UNSET_VAR}").unwrap_err();
        assert!(e.contains("GONIO_TEST_SURELY_UNSET_VAR"), "{e}");
        assert!(substitute_env("${OOPS").is_err());
    }

    #[test]
    fn options_are_typed_and_unknown_keys_rejected() {
        let mut m = BTreeMap::new();
        m.insert("device".to_string(), toml::Value::Integer(3));
        m.insert("units_per_deg".to_string(), toml::Value::Float(-1.0));
        let o = Options::new("turntable", &m);
        assert_eq!(o.int("device", 1, 1, 99).unwrap(), 3);
        let e = o.positive("units_per_deg", 1.0).unwrap_err().to_string();
        assert!(e.contains("turntable") && e.contains("units_per_deg"), "{e}");
        let e = o.deny_unknown(&["device"]).unwrap_err().to_string();
        assert!(e.contains("units_per_deg"), "{e}");
    }
}
