//! `gonio sim serve-light`: a Rohde & Schwarz HMP4040 power supply with a halogen lamp on
//! each channel, emulated on a pty until Ctrl-C / SIGTERM (the lamp backend `hmp`'s
//! counterpart, as `serve-stage` is the stages').
//!
//! Prints the device path first (one line, or `{"path": …}` with `--json`) and flushes.
//! Every received command is logged at debug level (`RUST_LOG=gonio_simulator::emulate=debug`).

use anyhow::{Context, Result};
use gonio_simulator::emulate::{self, hmp::LampLoad, EmulatorConfig, FaultPlan, Protocol};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct ServeLightArgs {
    /// Channels (an HMP4040 has 4, an HMP2020 2).
    #[arg(long, default_value_t = 4)]
    pub channels: usize,
    /// Injected reply fault, repeatable: garble:every=N|at=N, drop:every=N|at=N,
    /// slow:ms=D[,every=N|at=N].
    #[arg(long = "fault")]
    pub faults: Vec<String>,
    /// Slow drift of the lamp: its resistance grows by this fraction at every `MEAS:CURR?`
    /// of a channel that is on (e.g. 0.005: after 4 readings the current is ~2 % lower).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub drift: f64,
    /// The lamp's rated voltage (V).
    #[arg(long, default_value_t = 12.0)]
    pub rated_voltage: f64,
    /// The lamp's rated power (W); hot resistance = V² / P.
    #[arg(long, default_value_t = 100.0)]
    pub rated_power: f64,
    /// The filament's cold resistance (Ω).
    #[arg(long, default_value_t = 0.12)]
    pub cold_resistance: f64,
    /// Keep a symlink to the pty here.
    #[arg(long)]
    pub link: Option<PathBuf>,
    /// Print `{"path": …, …}` instead of the bare path.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: ServeLightArgs) -> Result<ExitCode> {
    let mut cfg = EmulatorConfig::new(Protocol::Hmp4040, a.channels);
    cfg.faults = FaultPlan::parse(&a.faults)?;
    cfg.link = a.link.clone();
    cfg.lamp = LampLoad {
        rated_voltage_v: a.rated_voltage,
        rated_power_w: a.rated_power,
        cold_resistance_ohm: a.cold_resistance,
        drift: a.drift,
    };
    let faults: Vec<String> = cfg.faults.faults.iter().map(|f| f.to_string()).collect();
    let lamp = cfg.lamp;
    let handle = emulate::spawn_pty(cfg).context("starting the HMP4040 emulator")?;
    let info = serde_json::json!({
        "protocol": Protocol::Hmp4040,
        "idn": emulate::hmp::EMULATED_IDN,
        "channels": a.channels,
        "faults": faults,
        "link": a.link,
        "lamp": {
            "rated_voltage_v": lamp.rated_voltage_v,
            "rated_power_w": lamp.rated_power_w,
            "hot_resistance_ohm": lamp.hot_resistance_ohm(),
            "cold_resistance_ohm": lamp.cold_resistance_ohm,
            "drift": lamp.drift,
        },
    });
    super::serve_stage::serve(handle, a.json, info)
}
