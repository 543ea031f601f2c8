//! `gonio devices …`: find the hardware on this machine.
//!
//! `list` shows serial ports, video devices and the cameras of the camera backends this
//! build has (GenICam through Aravis, DSLRs through libgphoto2; a backend left out of the
//! build gets a line naming its feature); `probe PORT` asks a port who is there
//! (Zaber ASCII at 115200 and 9600 baud, then Newport ESP300 `VE?` at 19200, then an R&S HMP
//! supply's `*IDN?` at 9600). `check --rig FILE` opens every device of a rig file and
//! exercises it (`gonio_acquire::rig::check`; this module parses and prints only).

use super::common::load_sample;
use anyhow::{bail, Context, Result};
use gonio_acquire::rig::backends::{self, Make};
use gonio_acquire::rig::check::{self, CheckOptions, CheckReport};
use gonio_acquire::rig::Backends;
use gonio_devices::camera::FoundCamera;
use gonio_devices::rig::RigSpec;
use gonio_devices::serial::list;
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Subcommand, Debug)]
pub enum DevicesCommand {
    /// Serial ports, /dev/video* devices, and GenICam and libgphoto2 cameras (with the
    /// features that build those backends).
    List(ListArgs),
    /// Identify the motor controller on a serial port (or an emulator's pty).
    Probe(ProbeArgs),
    /// Open every device of a rig file: identity and firmware, a small step of each axis
    /// and back, one frame, the lamp on and off. Exit 0 only when everything answered.
    Check(CheckArgs),
}

#[derive(clap::Args, Debug)]
pub struct CheckArgs {
    /// The rig file to check (TOML, see devices/rigs/).
    #[arg(long)]
    pub rig: PathBuf,
    /// Move nothing: skip each axis' step (and the homing before it).
    #[arg(long)]
    pub no_move: bool,
    /// The step each axis takes and comes back from, degrees.
    #[arg(long, default_value_t = 1.0)]
    pub step_deg: f64,
    /// Sample the simulated camera of a mixed rig renders (unused by real cameras).
    #[arg(long, default_value = gonio_simulator::sample::DEFAULT_SAMPLE)]
    pub sample: String,
    /// Print the report as JSON (one object: rig, ok, moved, devices[]).
    #[arg(long)]
    pub json: bool,
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
    /// One entry per camera backend that can look for its cameras.
    cameras: Vec<CameraBackendListing>,
}

/// One camera backend's part of `gonio devices list`.
#[derive(Serialize)]
struct CameraBackendListing {
    /// The rig file's `camera.backend`.
    backend: &'static str,
    /// The cargo feature that builds it.
    feature: Option<&'static str>,
    /// Whether this build has the backend (when not, `note` names the feature).
    built: bool,
    cameras: Vec<FoundCamera>,
    /// Why the backend could not look (its cameras are then unknown, not absent).
    error: Option<String>,
    /// For a backend not in this build: which feature lists its cameras.
    note: Option<String>,
}

/// What a backend's cameras are, for the line of a compiled-out one.
fn camera_kind(backend: &str) -> &'static str {
    match backend {
        "genicam" => "GigE Vision and USB3 Vision cameras (Aravis)",
        "gphoto2" => "DSLRs and mirrorless cameras (libgphoto2)",
        _ => "its cameras",
    }
}

/// Every camera backend of the table ([`backends::camera_listers`]): the cameras of the
/// ones this build has, the feature of the others.
fn list_cameras() -> Vec<CameraBackendListing> {
    backends::camera_listers()
        .into_iter()
        .map(|row| {
            let mut l = CameraBackendListing {
                backend: row.name,
                feature: row.feature,
                built: false,
                cameras: Vec::new(),
                error: None,
                note: None,
            };
            match row.make {
                Make::Real(list) => {
                    l.built = true;
                    match list() {
                        Ok(cameras) => l.cameras = cameras,
                        Err(e) => l.error = Some(e.to_string()),
                    }
                }
                Make::NotBuilt | Make::Simulated => {
                    l.note = Some(format!(
                        "not in this build: rebuild with `--features {}` to list {}",
                        row.feature.unwrap_or("?"),
                        camera_kind(row.name)
                    ));
                }
            }
            l
        })
        .collect()
}

/// The cameras part of the listing as text, one line each.
fn camera_lines(cameras: &[CameraBackendListing]) -> Vec<String> {
    let mut lines = Vec::new();
    for b in cameras {
        if let Some(note) = &b.note {
            lines.push(format!("cameras ({}): {note}", b.backend));
            continue;
        }
        lines.push(format!("cameras ({}):", b.backend));
        if let Some(e) = &b.error {
            lines.push(format!("  (cannot list: {e})"));
        } else if b.cameras.is_empty() {
            lines.push("  (none)".into());
        }
        for c in &b.cameras {
            lines.push(format!(
                "  {} at {}  (rig file: [camera] backend = \"{}\", options = {{ {} }})",
                c.model, c.address, c.backend, c.rig_options
            ));
        }
    }
    lines
}

pub fn run(cmd: DevicesCommand) -> Result<ExitCode> {
    match cmd {
        DevicesCommand::Check(a) => run_check(a),
        DevicesCommand::List(a) => {
            let (serial_ports, serial_error) = match list::serial_ports() {
                Ok(p) => (p, None),
                Err(e) => (Vec::new(), Some(e.to_string())),
            };
            let l = Listing {
                serial_ports,
                serial_error,
                video_devices: list::video_devices(),
                cameras: list_cameras(),
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
                for line in camera_lines(&l.cameras) {
                    println!("{line}");
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

fn run_check(a: CheckArgs) -> Result<ExitCode> {
    if !(a.step_deg.is_finite() && a.step_deg > 0.0 && a.step_deg <= 10.0) {
        bail!(
            "--step-deg {}: must be a number of degrees in (0, 10] (a small step, inside the limits)",
            a.step_deg
        );
    }
    let spec = RigSpec::load(&a.rig).with_context(|| format!("loading rig {}", a.rig.display()))?;
    let sample = load_sample(&a.sample)?;
    let opts = CheckOptions {
        moves: !a.no_move,
        step_deg: a.step_deg,
    };
    let rt = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    let report = rt.block_on(check::check(
        &spec,
        &sample,
        &gonio_simulator::SimOptions::default(),
        &Backends::builtin(),
        &opts,
    ));
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_check(&report);
    }
    Ok(if report.ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// The report as a table: one block per device (what answered, what it reported, what
/// failed and how to fix it), then the verdict.
fn print_check(r: &CheckReport) {
    println!(
        "rig {}{}",
        r.rig,
        if r.moved { "" } else { " (--no-move: no axis moved)" }
    );
    println!(
        "{:<22} {:<8} {:<9} identity / reported",
        "device", "backend", "answered"
    );
    for d in &r.devices {
        println!(
            "{:<22} {:<8} {:<9} {}",
            d.device,
            d.backend,
            if d.answered { "yes" } else { "NO" },
            d.identity.as_deref().unwrap_or("-")
        );
        for line in &d.reported {
            println!("{:<41} {line}", "");
        }
        if let Some(f) = &d.failure {
            println!("{:<41} FAILED: {f}", "");
        }
        if let Some(f) = &d.fix {
            println!("{:<41} fix: {f}", "");
        }
    }
    let failed: Vec<&str> = r
        .devices
        .iter()
        .filter(|d| !d.answered)
        .map(|d| d.device.as_str())
        .collect();
    if failed.is_empty() {
        println!("every device answered");
    } else {
        println!("not ready: {} failed", failed.join(", "));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A build without a camera backend's feature lists no camera of it, but says which
    /// feature would (in `--json` and in the text).
    #[test]
    fn a_backend_left_out_of_the_build_names_its_feature() {
        let listing = list_cameras();
        let names: Vec<&str> = listing.iter().map(|b| b.backend).collect();
        assert_eq!(names, ["genicam", "gphoto2"]);
        for b in &listing {
            let feature = b.feature.expect("a feature");
            let built = match feature {
                "genicam" => cfg!(feature = "genicam"),
                _ => cfg!(feature = "gphoto2"),
            };
            assert_eq!(b.built, built, "{feature}");
            if !built {
                let note = b.note.as_deref().expect("a note");
                assert!(note.contains(&format!("--features {feature}")), "{note}");
                assert!(b.cameras.is_empty() && b.error.is_none());
                let json = serde_json::to_value(b).unwrap();
                assert_eq!(json["built"], false);
                assert!(json["note"].as_str().unwrap().contains(feature));
            }
        }
        let text = camera_lines(&listing).join("\n");
        if !cfg!(feature = "gphoto2") {
            assert!(
                text.contains("cameras (gphoto2): not in this build: rebuild with `--features gphoto2` to list DSLRs"),
                "{text}"
            );
        }
    }

    /// Found cameras are printed with the rig-file options that open them; a backend that
    /// could not look says why.
    #[test]
    fn found_cameras_and_failures_print_with_what_to_write() {
        let listing = [
            CameraBackendListing {
                backend: "gphoto2",
                feature: Some("gphoto2"),
                built: true,
                cameras: vec![FoundCamera {
                    backend: "gphoto2".into(),
                    model: "Nikon DSC D750".into(),
                    address: "usb:001,001".into(),
                    rig_options: "port = \"usb:001,001\", model = \"Nikon DSC D750\"".into(),
                }],
                error: None,
                note: None,
            },
            CameraBackendListing {
                backend: "genicam",
                feature: Some("genicam"),
                built: true,
                cameras: vec![],
                error: Some("no network interface".into()),
                note: None,
            },
        ];
        assert_eq!(
            camera_lines(&listing),
            [
                "cameras (gphoto2):",
                "  Nikon DSC D750 at usb:001,001  (rig file: [camera] backend = \"gphoto2\", options = { port = \"usb:001,001\", model = \"Nikon DSC D750\" })",
                "cameras (genicam):",
                "  (cannot list: no network interface)",
            ]
        );
    }
}
