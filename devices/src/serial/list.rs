//! Finding devices: serial ports and video devices on this machine, and probing a port for
//! the controllers gonio speaks to.

use super::{zaber, Link, SerialTransport, Transport};
use serde::Serialize;
use std::time::{Duration, Instant};

/// A serial port the OS reports.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PortInfo {
    pub path: String,
    /// `usb`, `pci`, `bluetooth` or `unknown` (without libudev little more is known).
    pub kind: String,
}

/// Serial ports the OS knows (USB adapters, built-in UARTs). Ptys are not listed: they are
/// only found by the path an emulator prints.
pub fn serial_ports() -> Result<Vec<PortInfo>, std::io::Error> {
    let ports = serialport::available_ports().map_err(|e| std::io::Error::other(e.description))?;
    let mut out: Vec<PortInfo> = ports
        .into_iter()
        .map(|p| PortInfo {
            path: p.port_name,
            kind: match p.port_type {
                serialport::SerialPortType::UsbPort(_) => "usb",
                serialport::SerialPortType::PciPort => "pci",
                serialport::SerialPortType::BluetoothPort => "bluetooth",
                serialport::SerialPortType::Unknown => "unknown",
            }
            .into(),
        })
        .collect();
    out.sort_by(|a, b| a.path.cmp(&b.path));
    Ok(out)
}

/// `/dev/video*` device nodes.
pub fn video_devices() -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir("/dev")
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| n.starts_with("video") && n[5..].chars().all(|c| c.is_ascii_digit()) && n.len() > 5)
                .map(|n| format!("/dev/{n}"))
                .collect()
        })
        .unwrap_or_default();
    v.sort_by_key(|p| p[10..].parse::<u32>().unwrap_or(u32::MAX));
    v
}

/// What answered a probe.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ProbeResult {
    pub port: String,
    /// `zaber`, `esp300`, `hmp` or `none`.
    pub protocol: String,
    pub baud: Option<u32>,
    /// Zaber: the device numbers that answered; ESP: empty.
    pub devices: Vec<u8>,
    /// The raw lines received (for a person to judge).
    pub replies: Vec<String>,
    /// What each attempt did, in order.
    pub attempts: Vec<String>,
}

/// Collect lines for `wait` after sending `line`.
fn exchange(t: Box<dyn Transport>, line: &str, wait: Duration) -> Result<Vec<String>, String> {
    let mut link = Link::new(t);
    link.drain(Duration::from_millis(20), Duration::from_millis(200))
        .map_err(|e| format!("{e:?}"))?;
    link.send(line).map_err(|e| format!("{e:?}"))?;
    let deadline = Instant::now() + wait;
    let mut lines = Vec::new();
    while let Ok(l) = link.read_line(deadline) {
        if !l.trim().is_empty() {
            lines.push(l);
        }
    }
    Ok(lines)
}

/// Probe with a transport factory (`open(baud)`), so tests can use scripted transports.
pub fn probe_with(
    port: &str,
    mut open: impl FnMut(u32) -> std::io::Result<Box<dyn Transport>>,
    wait: Duration,
) -> ProbeResult {
    let mut res = ProbeResult {
        port: port.to_string(),
        protocol: "none".into(),
        baud: None,
        devices: Vec::new(),
        replies: Vec::new(),
        attempts: Vec::new(),
    };
    // Zaber: the empty broadcast command `/` makes every device on the chain reply.
    for baud in [115_200, 9_600] {
        let lines = match open(baud)
            .map_err(|e| e.to_string())
            .and_then(|t| exchange(t, "/\n", wait))
        {
            Ok(l) => l,
            Err(e) => {
                res.attempts.push(format!("zaber @ {baud}: {e}"));
                continue;
            }
        };
        let mut devs: Vec<u8> = lines
            .iter()
            .filter_map(|l| match zaber::parse_message(l) {
                Ok(zaber::Message::Reply(r)) => Some(r.device),
                _ => None,
            })
            .collect();
        devs.sort_unstable();
        devs.dedup();
        res.attempts.push(format!(
            "zaber @ {baud}: {} line(s), {} device(s)",
            lines.len(),
            devs.len()
        ));
        if !devs.is_empty() {
            res.protocol = "zaber".into();
            res.baud = Some(baud);
            res.devices = devs;
            res.replies = lines;
            return res;
        }
    }
    // ESP300: `VE?` returns the firmware version (`ESP300 Version …`).
    let baud = 19_200;
    match open(baud)
        .map_err(|e| e.to_string())
        .and_then(|t| exchange(t, "VE?\r\n", wait))
    {
        Ok(lines) => {
            res.attempts.push(format!("esp300 @ {baud}: {} line(s)", lines.len()));
            if lines.iter().any(|l| l.to_ascii_uppercase().contains("ESP")) {
                res.protocol = "esp300".into();
                res.baud = Some(baud);
                res.replies = lines;
            }
        }
        Err(e) => res.attempts.push(format!("esp300 @ {baud}: {e}")),
    }
    if res.protocol != "none" {
        return res;
    }
    // A Rohde & Schwarz HMP supply (the lamp): `*IDN?` names the model (`…,HMP4040,…`).
    let baud = 9_600;
    match open(baud)
        .map_err(|e| e.to_string())
        .and_then(|t| exchange(t, "*IDN?\n", wait))
    {
        Ok(lines) => {
            res.attempts.push(format!("hmp @ {baud}: {} line(s)", lines.len()));
            if lines.iter().any(|l| {
                l.split(',')
                    .nth(1)
                    .is_some_and(|m| m.trim().to_ascii_uppercase().starts_with("HMP"))
            }) {
                res.protocol = "hmp".into();
                res.baud = Some(baud);
                res.replies = lines;
            }
        }
        Err(e) => res.attempts.push(format!("hmp @ {baud}: {e}")),
    }
    res
}

/// Probe a real port: Zaber ASCII at 115200 and 9600 baud, then ESP300 `VE?` at 19200,
/// then an HMP supply's `*IDN?` at 9600.
pub fn probe(port: &str) -> ProbeResult {
    probe_with(
        port,
        |baud| SerialTransport::open(port, baud).map(|t| Box::new(t) as Box<dyn Transport>),
        Duration::from_millis(400),
    )
}

#[cfg(test)]
mod tests {
    use super::super::testing::{ScriptReply, ScriptedTransport};
    use super::*;

    #[test]
    fn probe_identifies_zaber_chain_and_esp() {
        let z = probe_with(
            "fake",
            |baud| {
                Ok(Box::new(ScriptedTransport::new(move |l| {
                    if baud == 115_200 && l == "/" {
                        vec![
                            ScriptReply::line("@01 0 OK IDLE -- 0"),
                            ScriptReply::line("@02 0 OK IDLE -- 0"),
                        ]
                    } else {
                        vec![]
                    }
                })))
            },
            Duration::from_millis(30),
        );
        assert_eq!(z.protocol, "zaber");
        assert_eq!(z.devices, vec![1, 2]);
        let e = probe_with(
            "fake",
            |_| {
                Ok(Box::new(ScriptedTransport::new(|l| {
                    if l == "VE?" {
                        vec![ScriptReply::line("ESP300 Version 3.08 09/09/02")]
                    } else {
                        vec![]
                    }
                })))
            },
            Duration::from_millis(30),
        );
        assert_eq!((e.protocol.as_str(), e.baud), ("esp300", Some(19_200)));
        let n = probe_with(
            "fake",
            |_| Ok(Box::new(ScriptedTransport::new(|_| vec![]))),
            Duration::from_millis(10),
        );
        assert_eq!(n.protocol, "none");
        assert_eq!(n.attempts.len(), 4);
        let h = probe_with(
            "fake",
            |_| {
                Ok(Box::new(ScriptedTransport::new(|l| {
                    if l == "*IDN?" {
                        vec![ScriptReply::line("ROHDE&SCHWARZ,HMP4040,101234,HW50020001/SW2.70")]
                    } else {
                        vec![]
                    }
                })))
            },
            Duration::from_millis(30),
        );
        assert_eq!((h.protocol.as_str(), h.baud), ("hmp", Some(9_600)));
    }
}
