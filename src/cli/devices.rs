//! `gonio devices …`: find the hardware on this machine.
//!
//! `list` shows serial ports and video devices; `probe PORT` asks a port who is there
//! (Zaber ASCII at 115200 and 9600 baud, then Newport ESP300 `VE?` at 19200, then an R&S HMP
//! supply's `*IDN?` at 9600).

use anyhow::Result;
use gonio_devices::serial::list;
use serde::Serialize;
use std::process::ExitCode;

#[derive(clap::Subcommand, Debug)]
pub enum DevicesCommand {
    /// Serial ports and /dev/video* devices.
    List(ListArgs),
    /// Identify the motor controller on a serial port (or an emulator's pty).
    Probe(ProbeArgs),
}

#[derive(clap::Args, Debug)]
pub struct ListArgs {
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct ProbeArgs {
    /// The port, e.g. /dev/ttyUSB0 or the /dev/pts/N an emulator printed.
    pub port: String,
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct Listing {
    serial_ports: Vec<list::PortInfo>,
    /// Why the serial ports could not be listed (the video list is still valid).
    serial_error: Option<String>,
    video_devices: Vec<String>,
}

pub fn run(cmd: DevicesCommand) -> Result<ExitCode> {
    match cmd {
        DevicesCommand::List(a) => {
            let (serial_ports, serial_error) = match list::serial_ports() {
                Ok(p) => (p, None),
                Err(e) => (Vec::new(), Some(e.to_string())),
            };
            let l = Listing {
                serial_ports,
                serial_error,
                video_devices: list::video_devices(),
            };
            if a.json {
                println!("{}", serde_json::to_string_pretty(&l)?);
            } else {
                println!("serial ports:");
                if let Some(e) = &l.serial_error {
                    println!("  (cannot list: {e})");
                } else if l.serial_ports.is_empty() {
                    println!("  (none)");
                }
                for p in &l.serial_ports {
                    println!("  {:<24} {}", p.path, p.kind);
                }
                println!("video devices:");
                if l.video_devices.is_empty() {
                    println!("  (none)");
                }
                for v in &l.video_devices {
                    println!("  {v}");
                }
            }
            Ok(ExitCode::SUCCESS)
        }
        DevicesCommand::Probe(a) => {
            let r = list::probe(&a.port);
            if a.json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                match r.protocol.as_str() {
                    "zaber" => println!(
                        "{}: Zaber ASCII at {} baud, device(s) {}",
                        r.port,
                        r.baud.unwrap_or(0),
                        r.devices.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")
                    ),
                    "esp300" => println!(
                        "{}: Newport ESP at {} baud: {}",
                        r.port,
                        r.baud.unwrap_or(0),
                        r.replies.first().map(String::as_str).unwrap_or("")
                    ),
                    "hmp" => println!(
                        "{}: power supply at {} baud (light backend `hmp`): {}",
                        r.port,
                        r.baud.unwrap_or(0),
                        r.replies.first().map(String::as_str).unwrap_or("")
                    ),
                    _ => println!("{}: nothing answered", r.port),
                }
                for at in &r.attempts {
                    println!("  {at}");
                }
            }
            // Exit 1 when nothing answered, so scripts can test for a controller.
            Ok(if r.protocol == "none" {
                ExitCode::from(1)
            } else {
                ExitCode::SUCCESS
            })
        }
    }
}
