//! `gonio sim serve-stage`: a motor-controller emulator on a pty, until Ctrl-C / SIGTERM.
//!
//! Prints the device path first (one line, or `{"path": …}` with `--json`) and flushes, so a
//! script can start it in the background, read the path and point a client (gonio's driver,
//! zaber-motion, PyMeasure) at it. Every received command is logged at debug level
//! (`-vv`, or `RUST_LOG=gonio_simulator::emulate=debug`).

use anyhow::{bail, Context, Result};
use gonio_simulator::emulate::{self, EmulatorConfig, FaultPlan, Protocol};
use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum ProtocolArg {
    /// Zaber ASCII protocol.
    Zaber,
    /// Newport ESP300 / ESP301 command set.
    Esp300,
}

#[derive(clap::Args, Debug)]
pub struct ServeStageArgs {
    /// Which controller to emulate.
    #[arg(long, value_enum)]
    pub protocol: ProtocolArg,
    /// Axes per device (Zaber 1 ..= 9, ESP 1 ..= 3).
    #[arg(long, default_value_t = 1)]
    pub axes: usize,
    /// Zaber daisy-chain length (devices 1 ..= N).
    #[arg(long, default_value_t = 1)]
    pub devices: usize,
    /// Injected fault, repeatable: garble:every=N|at=N, drop:every=N|at=N,
    /// slow:ms=D[,every=N|at=N], stall:at-move=N (BUSY, no progress), stall-stop:at-move=N
    /// (stopped with Zaber FS / ESP x03), limit:at-move=N, disconnect:at-move=N.
    #[arg(long = "fault")]
    pub faults: Vec<String>,
    /// Controller units per degree (default: Zaber 1000 native units/°, ESP 1 = degrees).
    #[arg(long)]
    pub units_per_deg: Option<f64>,
    /// Maximum velocity of every axis (°/s).
    #[arg(long, default_value_t = 90.0)]
    pub max_velocity: f64,
    /// Acceleration of every axis (°/s²).
    #[arg(long, default_value_t = 720.0)]
    pub acceleration: f64,
    /// Travel range in degrees, `MIN,MAX` (must contain home, 0°).
    #[arg(long, default_value = "-180,180", allow_hyphen_values = true)]
    pub range: String,
    /// Start with every axis homed (referenced).
    #[arg(long)]
    pub homed: bool,
    /// JSON state file: positions are loaded from it at start and saved to it on every move,
    /// so a restarted emulator continues where the old one stopped.
    #[arg(long)]
    pub state: Option<PathBuf>,
    /// Keep a symlink to the current pty here (stable across reconnects).
    #[arg(long)]
    pub link: Option<PathBuf>,
    /// After an injected disconnect, open a new pty after this many ms (else exit).
    #[arg(long)]
    pub reconnect_after_ms: Option<u64>,
    /// Print `{"path": …, …}` instead of the bare path.
    #[arg(long)]
    pub json: bool,
    /// Mechanical error model of every axis (Zaber), as the body of a TOML inline table,
    /// e.g. `backlash_deg = 0.08, home_sigma_deg = 0.02, scale_error = 5e-4, seed = 3`:
    /// `get encoder.pos` then reads the load side (keys: simulator/src/mechanics.rs; axis k
    /// uses seed + k). For `gonio calibrate calibration/recipes/mechanical.toml`.
    #[arg(long)]
    pub mechanical: Option<String>,
}

/// `--mechanical` body → model.
fn parse_mechanical(s: &str) -> Result<gonio_simulator::mechanics::MechanicalErrors> {
    #[derive(serde::Deserialize)]
    struct W {
        m: gonio_simulator::mechanics::MechanicalErrors,
    }
    let w: W = toml::from_str(&format!("m = {{ {s} }}"))
        .map_err(|e| anyhow::anyhow!("--mechanical `{s}`: {}", e.message()))?;
    w.m.validate().map_err(|e| anyhow::anyhow!("--mechanical `{s}`: {e}"))?;
    Ok(w.m)
}

fn parse_range(s: &str) -> Result<(f64, f64)> {
    let (a, b) = s
        .split_once(',')
        .with_context(|| format!("--range `{s}`: expected MIN,MAX in degrees"))?;
    let a: f64 = a.trim().parse().with_context(|| format!("--range `{s}`: bad MIN"))?;
    let b: f64 = b.trim().parse().with_context(|| format!("--range `{s}`: bad MAX"))?;
    Ok((a, b))
}

pub fn run(a: ServeStageArgs) -> Result<ExitCode> {
    let protocol = match a.protocol {
        ProtocolArg::Zaber => Protocol::Zaber,
        ProtocolArg::Esp300 => Protocol::Esp300,
    };
    let mut cfg = EmulatorConfig::new(protocol, a.axes);
    cfg.devices = a.devices;
    cfg.faults = FaultPlan::parse(&a.faults)?;
    if let Some(u) = a.units_per_deg {
        cfg.units_per_deg = u;
    }
    cfg.motion.max_velocity = a.max_velocity;
    cfg.motion.acceleration = a.acceleration;
    cfg.range_deg = parse_range(&a.range)?;
    cfg.start_homed = a.homed;
    cfg.state_file = a.state.clone();
    cfg.link = a.link.clone();
    cfg.reconnect_after = a.reconnect_after_ms.map(Duration::from_millis);
    if let Some(m) = &a.mechanical {
        cfg.mechanical = Some(parse_mechanical(m)?);
    }
    let faults: Vec<String> = cfg.faults.faults.iter().map(|f| f.to_string()).collect();
    let units_per_deg = cfg.units_per_deg;
    let handle = emulate::spawn_pty(cfg).with_context(|| format!("starting the {protocol} emulator"))?;
    let info = serde_json::json!({
        "protocol": protocol,
        "axes": a.axes,
        "devices": a.devices,
        "units_per_deg": units_per_deg,
        "faults": faults,
        "link": a.link,
        "state": a.state,
    });
    serve(handle, a.json, info)
}

/// Print the pty path (or, with `json`, `{"path": …}` merged with `info`), then serve until
/// Ctrl-C / SIGTERM or until the emulator ends by itself (an injected disconnect).
pub(super) fn serve(handle: emulate::EmulatorHandle, json: bool, mut info: serde_json::Value) -> Result<ExitCode> {
    let path = handle.path().display().to_string();
    {
        let mut out = std::io::stdout().lock();
        if json {
            info["path"] = serde_json::json!(path);
            writeln!(out, "{info}")?;
        } else {
            writeln!(out, "{path}")?;
        }
        out.flush()?;
    }
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let ended_by_itself = rt.block_on(async {
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
        let mut tick = tokio::time::interval(Duration::from_millis(100));
        loop {
            tokio::select! {
                _ = tokio::signal::ctrl_c() => return Ok::<bool, std::io::Error>(false),
                _ = term.recv() => return Ok(false),
                _ = tick.tick() => if handle.is_finished() { return Ok(true) },
            }
        }
    })?;
    let disconnects = handle.disconnects();
    handle.stop();
    if ended_by_itself {
        if disconnects > 0 {
            eprintln!("{path}: injected disconnect; emulator ended (use --reconnect-after-ms to reopen)");
            return Ok(ExitCode::from(3));
        }
        bail!("{path}: the emulator ended unexpectedly");
    }
    Ok(ExitCode::SUCCESS)
}
