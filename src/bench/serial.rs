//! `gonio bench serial`: what the serial layer costs.
//!
//! Two figures, both against controller emulators served on real ptys in this process
//! (the bytes go through the kernel's pty driver like through a USB-serial adapter, minus
//! the wire time at the baud rate, which a pty does not simulate):
//! - round trips per second of one position query (`get pos` / `1TP`);
//! - per-measurement overhead: a 4-axis step (start all moves, wait for all, as the engine
//!   does) on serial axes whose emulated motion is near-instant, against the same steps on
//!   in-process simulated axes (virtual clock); the difference is protocol + policy cost,
//!   reported as milliseconds per measurement and as a ratio.

use anyhow::{Context, Result};
use gonio_devices::rig::AxisSpec;
use gonio_devices::serial::{esp300, zaber, PortRegistry};
use gonio_devices::{Axis, MotionModel, SoftLimits};
use gonio_simulator::clock::SimClock;
use gonio_simulator::devices::SimAxis;
use gonio_simulator::emulate::{spawn_pty, EmulatorConfig, Protocol};
use serde::Serialize;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

#[derive(clap::Args, Debug)]
pub struct SerialBenchArgs {
    /// Position queries per protocol for the round-trip rate.
    #[arg(long, default_value_t = 500)]
    pub queries: usize,
    /// Measurement steps (4 axes each) for the per-measurement overhead.
    #[arg(long, default_value_t = 30)]
    pub steps: usize,
    /// Poll interval of the motion policy (ms), as the rig file's `poll_ms`.
    #[arg(long, default_value_t = 20)]
    pub poll_ms: u64,
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct Row {
    protocol: &'static str,
    round_trips_per_s: f64,
    ms_per_round_trip: f64,
    /// Wall time per 4-axis measurement step on serial axes (ms).
    serial_ms_per_step: f64,
    /// The same steps on in-process simulated axes (ms).
    sim_ms_per_step: f64,
    /// serial − sim: what the serial layer adds to every measurement (ms).
    overhead_ms_per_step: f64,
    /// serial / sim.
    ratio: f64,
    /// Commands the emulator received per step.
    commands_per_step: f64,
}

const AXES: usize = 4;

fn fast_emulator(protocol: Protocol) -> EmulatorConfig {
    let mut cfg = EmulatorConfig::new(protocol, if protocol == Protocol::Esp300 { 3 } else { AXES });
    // Near-instant motion: what is left is the serial layer's own cost.
    cfg.motion.max_velocity = 1e7;
    cfg.motion.acceleration = 1e9;
    cfg
}

fn spec(name: &str, backend: &str, port: &std::path::Path, axis: usize, poll_ms: u64) -> Result<AxisSpec> {
    let extra = if backend == "zaber" {
        format!("device = 1, axis = {axis}, units_per_deg = 1000.0")
    } else {
        format!("axis = {axis}")
    };
    let text = format!(
        "name = \"{name}\"\nrole = \"r\"\nbackend = \"{backend}\"\nmin_deg = -170.0\nmax_deg = 170.0\n\
         max_velocity_deg_s = 90.0\nacceleration_deg_s2 = 720.0\nsettle_s = 0.0\n\
         options = {{ port = \"{}\", poll_ms = {poll_ms}, {extra} }}\n",
        port.display()
    );
    Ok(toml::from_str(&text)?)
}

fn targets(steps: usize) -> Vec<[f64; AXES]> {
    // Deterministic spread of targets (degrees → radians), all different from step to step.
    (0..steps)
        .map(|k| {
            let mut t = [0.0; AXES];
            for (i, x) in t.iter_mut().enumerate() {
                *x = (((k * 37 + i * 53) % 140) as f64 - 70.0 + 0.25 * i as f64).to_radians();
            }
            t
        })
        .collect()
}

async fn run_steps(axes: &[Arc<dyn Axis>], steps: &[[f64; AXES]]) -> Result<f64> {
    for a in axes {
        a.home().await?;
    }
    let t = Instant::now();
    for s in steps {
        for (a, &x) in axes.iter().zip(s) {
            a.start_move(x).await?;
        }
        for a in axes {
            a.wait_idle().await?;
        }
    }
    Ok(t.elapsed().as_secs_f64() * 1e3 / steps.len() as f64)
}

fn round_trips(protocol: Protocol, n: usize) -> Result<f64> {
    let h = spawn_pty(fast_emulator(protocol)).context("starting the emulator")?;
    let path = h.path().to_string_lossy().into_owned();
    let t;
    match protocol {
        Protocol::Zaber => {
            let cfg = zaber::PortConfig {
                reply_timeout: Duration::from_millis(500),
                checksums: true,
            };
            let port = zaber::ZaberPort::open(&path, 115_200, cfg)?;
            port.command("bench", 1, 1, "get pos")?;
            t = Instant::now();
            for _ in 0..n {
                port.command("bench", 1, 1, "get pos")?;
            }
        }
        Protocol::Esp300 => {
            let port = esp300::EspPort::open(&path, 19_200, Duration::from_millis(500))?;
            port.query("bench", "1TP")?;
            t = Instant::now();
            for _ in 0..n {
                port.query_number("bench", "1TP")?;
            }
        }
        Protocol::Hmp4040 => anyhow::bail!("bench serial: the HMP4040 emulator is a power supply, not a stage"),
    }
    let s = t.elapsed().as_secs_f64();
    h.stop();
    Ok(n as f64 / s)
}

async fn overhead(protocol: Protocol, steps: &[[f64; AXES]], poll_ms: u64) -> Result<(f64, f64)> {
    // ESP300: one controller drives 3 axes; the 4th is on a second controller.
    let h1 = spawn_pty(fast_emulator(protocol))?;
    let h2 = spawn_pty(fast_emulator(protocol))?;
    let mut ports = PortRegistry::new();
    let mut axes: Vec<Arc<dyn Axis>> = Vec::new();
    for i in 0..AXES {
        let (backend, path, axis) = match protocol {
            Protocol::Zaber => ("zaber", h1.path(), i + 1),
            Protocol::Esp300 if i < 3 => ("esp300", h1.path(), i + 1),
            Protocol::Esp300 => ("esp300", h2.path(), 1),
            Protocol::Hmp4040 => anyhow::bail!("bench serial: the HMP4040 emulator drives no axes"),
        };
        axes.push(ports.build_axis(&spec(&format!("a{i}"), backend, path, axis, poll_ms)?)?);
    }
    let ms = run_steps(&axes, steps).await?;
    let commands = (h1.received().len() + h2.received().len()) as f64;
    h1.stop();
    h2.stop();
    Ok((ms, commands / steps.len() as f64))
}

async fn sim_steps(steps: &[[f64; AXES]]) -> Result<f64> {
    let clock = Arc::new(SimClock::new(false));
    let m = MotionModel {
        max_velocity: 90f64.to_radians(),
        acceleration: 720f64.to_radians(),
        jerk: None,
        settle_time: 0.0,
        deadband: 0.001f64.to_radians(),
    };
    let lim = SoftLimits {
        min: -170f64.to_radians(),
        max: 170f64.to_radians(),
    };
    let axes: Vec<Arc<dyn Axis>> = (0..AXES)
        .map(|i| Arc::new(SimAxis::new(&format!("s{i}"), lim, m, clock.clone())) as Arc<dyn Axis>)
        .collect();
    run_steps(&axes, steps).await
}

pub fn run(a: SerialBenchArgs) -> Result<ExitCode> {
    let rt = tokio::runtime::Runtime::new()?;
    let steps = targets(a.steps.max(1));
    // the sim baseline is microseconds: repeat it for a stable figure
    let reps = 200;
    let mut sim_ms = 0.0;
    for _ in 0..reps {
        sim_ms += rt.block_on(sim_steps(&steps))?;
    }
    let sim_ms = sim_ms / reps as f64;
    let mut rows = Vec::new();
    for (protocol, name) in [(Protocol::Zaber, "zaber"), (Protocol::Esp300, "esp300")] {
        let rate = round_trips(protocol, a.queries.max(1))?;
        let (serial_ms, cmds) = rt.block_on(overhead(protocol, &steps, a.poll_ms))?;
        rows.push(Row {
            protocol: name,
            round_trips_per_s: rate,
            ms_per_round_trip: 1e3 / rate,
            serial_ms_per_step: serial_ms,
            sim_ms_per_step: sim_ms,
            overhead_ms_per_step: serial_ms - sim_ms,
            ratio: serial_ms / sim_ms.max(1e-9),
            commands_per_step: cmds,
        });
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&rows)?);
    } else {
        println!(
            "serial layer over a pty ({} queries, {} steps of {AXES} axes, poll {} ms)",
            a.queries, a.steps, a.poll_ms
        );
        println!(
            "{:<8} {:>12} {:>10} {:>14} {:>12} {:>14} {:>10} {:>10}",
            "protocol", "round trip/s", "ms/rt", "serial ms/step", "sim ms/step", "overhead ms", "ratio", "cmds/step"
        );
        for r in &rows {
            println!(
                "{:<8} {:>12.0} {:>10.3} {:>14.2} {:>12.4} {:>14.2} {:>10.0} {:>10.1}",
                r.protocol,
                r.round_trips_per_s,
                r.ms_per_round_trip,
                r.serial_ms_per_step,
                r.sim_ms_per_step,
                r.overhead_ms_per_step,
                r.ratio,
                r.commands_per_step
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
