//! A Rohde & Schwarz HMP4040 programmable power supply (SCPI), with a halogen lamp on every
//! channel: enough for gonio's `hmp` light and PyMeasure's `HMP4040` class.
//!
//! A line holds one or more commands separated by `;`. Headers take the SCPI short or long
//! form in any case (`INST:NSEL`, `instrument:nselect`), optional nodes may be left out
//! (`[SOURce:]VOLTage[:LEVel][:IMMediate][:AMPLitude]`, `OUTPut[:STATe]`,
//! `MEASure[:SCALar]`, `SYSTem:ERRor[:NEXT]?`). Supported:
//! - `*IDN?`, `*RST`, `*CLS`, `*OPC?`, `SYST:VERS?`, `SYST:ERR?`, `SYST:REM|LOC|MIX|RWL`,
//!   `SYST:BEEP`;
//! - `INST:NSEL n` / `INST:NSEL?`, `INST[:SEL] OUT1|OUTP1|OUTPUT1` / `INST?`;
//! - `VOLT v|MIN|MAX|UP|DOWN`, `VOLT? [MIN|MAX]`, `VOLT:STEP s` / `VOLT:STEP?`, likewise
//!   `CURR`; `APPL v,i` / `APPL?`;
//! - `OUTP:SEL 0|1|OFF|ON` / `OUTP:SEL?` (channel active), `OUTP:GEN …` / `OUTP:GEN?`
//!   (master output), `OUTP 0|1|OFF|ON` / `OUTP?` (the selected channel, and on also the
//!   master output, as the HMP does);
//! - `MEAS:VOLT?`, `MEAS:CURR?` (the selected channel's output; 0 when it is off).
//!
//! Mistakes are not answered but queued, as on the instrument: -113 "Undefined header",
//! -109 "Missing parameter", -104 "Data type error", -222 "Data out of range", -350
//! "Queue overflow" (the queue holds [`ERROR_QUEUE`] entries); `SYST:ERR?` pops one,
//! `0,"No error"` when empty.
//!
//! The load ([`LampLoad`]): a 12 V / 100 W halogen lamp whose filament resistance rises with
//! its temperature, from a cold resistance to the hot one at the rated voltage:
//! `R(V) = R_cold + (R_hot − R_cold)·(V/V_rated)^0.5`, `R_hot = V_rated²/P_rated`, so the
//! current `I = V/R(V)` follows the set voltage non-linearly. When that current would
//! exceed the channel's limit the channel regulates the current instead (constant current:
//! the voltage where `V/R(V)` equals the limit). `drift` (relative, per `MEAS:CURR?` of a
//! channel that is on) multiplies the resistance by `(1 + drift)^n` after n such queries:
//! a slow, deterministic drift of the lamp that a monitor must notice.

use super::{EmulatorConfig, EmulatorState, Handled};
use std::collections::VecDeque;
use std::time::Instant;

/// `*IDN?` of the emulated supply.
pub const EMULATED_IDN: &str = "ROHDE&SCHWARZ,HMP4040,000000,HW50020001/SW2.70 (gonio emulator)";
/// The error queue's depth.
pub const ERROR_QUEUE: usize = 10;
/// Range of a channel's settings (HMP4040).
pub const MAX_VOLTAGE_V: f64 = 32.05;
pub const MAX_CURRENT_A: f64 = 10.01;

/// SCPI error codes the emulator queues.
pub mod code {
    pub const DATA_TYPE: i32 = -104;
    pub const MISSING_PARAMETER: i32 = -109;
    pub const UNDEFINED_HEADER: i32 = -113;
    pub const DATA_OUT_OF_RANGE: i32 = -222;
    pub const QUEUE_OVERFLOW: i32 = -350;
}

/// The message of an error code, as `SYST:ERR?` reports it.
pub fn message(c: i32) -> &'static str {
    match c {
        0 => "No error",
        code::DATA_TYPE => "Data type error",
        code::MISSING_PARAMETER => "Missing parameter",
        code::UNDEFINED_HEADER => "Undefined header",
        code::DATA_OUT_OF_RANGE => "Data out of range",
        code::QUEUE_OVERFLOW => "Queue overflow",
        _ => "Unknown error",
    }
}

/// The lamp on each channel (see the module documentation for the model).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LampLoad {
    pub rated_voltage_v: f64,
    pub rated_power_w: f64,
    /// Filament resistance at room temperature (Ω).
    pub cold_resistance_ohm: f64,
    /// Relative resistance change per `MEAS:CURR?` of a channel that is on (0 = none).
    pub drift: f64,
}

impl Default for LampLoad {
    /// A 12 V / 100 W halogen: 1.44 Ω hot, 0.12 Ω cold (tungsten: about 1/12).
    fn default() -> Self {
        LampLoad {
            rated_voltage_v: 12.0,
            rated_power_w: 100.0,
            cold_resistance_ohm: 0.12,
            drift: 0.0,
        }
    }
}

impl LampLoad {
    pub fn hot_resistance_ohm(&self) -> f64 {
        self.rated_voltage_v * self.rated_voltage_v / self.rated_power_w
    }

    /// Filament resistance at voltage `v` (no drift).
    pub fn resistance(&self, v: f64) -> f64 {
        let (rc, rh) = (self.cold_resistance_ohm, self.hot_resistance_ohm());
        rc + (rh - rc) * (v.max(0.0) / self.rated_voltage_v).sqrt()
    }

    /// The output (V, I) of a channel set to `v_set` with current limit `i_limit`, the
    /// resistance scaled by `scale` (drift).
    pub fn operating_point(&self, v_set: f64, i_limit: f64, scale: f64) -> (f64, f64) {
        let current = |v: f64| {
            if v <= 0.0 {
                0.0
            } else {
                v / (self.resistance(v) * scale)
            }
        };
        if current(v_set) <= i_limit {
            return (v_set, current(v_set));
        }
        // Constant current: V / R(V) is increasing in V, so bisect for current(V) = limit.
        let (mut lo, mut hi) = (0.0, v_set);
        for _ in 0..80 {
            let mid = 0.5 * (lo + hi);
            if current(mid) > i_limit {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        (lo, current(lo))
    }

    pub fn validate(&self) -> Result<(), String> {
        let ok = |x: f64| x.is_finite() && x > 0.0;
        if !(ok(self.rated_voltage_v) && ok(self.rated_power_w) && ok(self.cold_resistance_ohm)) {
            return Err("lamp: rated voltage, rated power and cold resistance must be > 0".into());
        }
        if self.cold_resistance_ohm >= self.hot_resistance_ohm() {
            return Err(format!(
                "lamp: cold resistance {} Ω must be below the hot one, {} Ω (V²/P)",
                self.cold_resistance_ohm,
                self.hot_resistance_ohm()
            ));
        }
        if !(self.drift.is_finite() && self.drift.abs() < 0.5) {
            return Err(format!(
                "lamp: drift {} must be in (-0.5, 0.5) per measurement",
                self.drift
            ));
        }
        Ok(())
    }
}

#[derive(Clone, Debug)]
struct Channel {
    voltage: f64,
    current: f64,
    voltage_step: f64,
    current_step: f64,
    active: bool,
    /// `MEAS:CURR?` queries while on (the drift's clock).
    measured: u64,
}

impl Channel {
    fn new() -> Self {
        Channel {
            voltage: 0.0,
            current: 0.1,
            voltage_step: 1.0,
            current_step: 0.1,
            active: false,
            measured: 0,
        }
    }
}

/// The HMP4040 emulator.
pub struct Hmp {
    channels: Vec<Channel>,
    selected: usize,
    general: bool,
    errors: VecDeque<i32>,
    lamp: LampLoad,
}

/// The mnemonics the emulator knows, long form with the short form in capitals.
const MNEMONICS: &[&str] = &[
    "INSTrument",
    "NSELect",
    "SELect",
    "SOURce",
    "VOLTage",
    "CURRent",
    "LEVel",
    "IMMediate",
    "AMPLitude",
    "STEP",
    "INCRement",
    "APPLy",
    "OUTPut",
    "GENeral",
    "STATe",
    "MEASure",
    "SCALar",
    "SYSTem",
    "ERRor",
    "NEXT",
    "VERSion",
    "REMote",
    "LOCal",
    "MIXed",
    "RWLock",
    "BEEPer",
];

/// A header node's short form, if it is one of [`MNEMONICS`] in short or long form.
fn short_form(node: &str) -> Option<&'static str> {
    let up = node.to_ascii_uppercase();
    MNEMONICS.iter().find_map(|m| {
        let short_len = m.chars().take_while(|c| c.is_ascii_uppercase()).count();
        let short = &m[..short_len];
        (up == short || up == m.to_ascii_uppercase()).then_some(short)
    })
}

/// `ON|OFF|1|0` → bool.
fn parse_bool(p: &str) -> Option<bool> {
    match p.to_ascii_uppercase().as_str() {
        "1" | "ON" => Some(true),
        "0" | "OFF" => Some(false),
        _ => None,
    }
}

impl Hmp {
    pub fn new(config: &EmulatorConfig) -> Self {
        Hmp {
            channels: vec![Channel::new(); config.axes],
            selected: 0,
            general: false,
            errors: VecDeque::new(),
            lamp: config.lamp,
        }
    }

    fn push_error(&mut self, c: i32) {
        if self.errors.len() >= ERROR_QUEUE {
            if let Some(last) = self.errors.back_mut() {
                *last = code::QUEUE_OVERFLOW;
            }
            return;
        }
        self.errors.push_back(c);
    }

    fn ch(&mut self) -> &mut Channel {
        &mut self.channels[self.selected]
    }

    /// The selected channel's output (V, I): 0 unless active and the master output is on.
    fn output(&self, idx: usize) -> (f64, f64) {
        let c = &self.channels[idx];
        if !(c.active && self.general) {
            return (0.0, 0.0);
        }
        let scale = (1.0 + self.lamp.drift).powf(c.measured as f64);
        self.lamp.operating_point(c.voltage, c.current, scale)
    }

    /// A set value: a number in [0, max], or MIN, MAX, UP, DOWN.
    fn level(&mut self, p: Option<&str>, now: f64, step: f64, max: f64) -> Option<f64> {
        let Some(p) = p else {
            self.push_error(code::MISSING_PARAMETER);
            return None;
        };
        let x = match p.to_ascii_uppercase().as_str() {
            "MIN" | "MINIMUM" => 0.0,
            "MAX" | "MAXIMUM" => max,
            "UP" => (now + step).min(max),
            "DOWN" => (now - step).max(0.0),
            _ => match p.parse::<f64>() {
                Ok(x) if x.is_finite() => x,
                _ => {
                    self.push_error(code::DATA_TYPE);
                    return None;
                }
            },
        };
        if !(0.0..=max).contains(&x) {
            self.push_error(code::DATA_OUT_OF_RANGE);
            return None;
        }
        Some(x)
    }

    fn number(&mut self, p: Option<&str>, max: f64) -> Option<f64> {
        self.level(p, 0.0, 0.0, max)
    }

    fn flag(&mut self, p: Option<&str>) -> Option<bool> {
        match p.map(parse_bool) {
            None => {
                self.push_error(code::MISSING_PARAMETER);
                None
            }
            Some(None) => {
                self.push_error(code::DATA_TYPE);
                None
            }
            Some(Some(b)) => Some(b),
        }
    }

    /// One command (no `;`); returns its reply, if it is a query that answers.
    fn command(&mut self, cmd: &str) -> Option<String> {
        let cmd = cmd.trim();
        let (header, params) = match cmd.find(char::is_whitespace) {
            Some(i) => (&cmd[..i], cmd[i..].trim()),
            None => (cmd, ""),
        };
        let params: Vec<&str> = if params.is_empty() {
            Vec::new()
        } else {
            params.split(',').map(str::trim).collect()
        };
        let p0 = params.first().copied();
        let query = header.ends_with('?');
        let header = header.trim_end_matches('?').trim_start_matches(':');
        if header.starts_with('*') {
            return match (header.to_ascii_uppercase().as_str(), query) {
                ("*IDN", true) => Some(EMULATED_IDN.to_string()),
                ("*OPC", true) => Some("1".into()),
                ("*RST", false) => {
                    let n = self.channels.len();
                    self.channels = vec![Channel::new(); n];
                    self.selected = 0;
                    self.general = false;
                    None
                }
                ("*CLS", false) => {
                    self.errors.clear();
                    None
                }
                _ => {
                    self.push_error(code::UNDEFINED_HEADER);
                    None
                }
            };
        }
        let mut nodes = Vec::new();
        for n in header.split(':') {
            match short_form(n) {
                Some(s) => nodes.push(s),
                None => {
                    self.push_error(code::UNDEFINED_HEADER);
                    return None;
                }
            }
        }
        // Optional nodes: [SOURce:] first, [:LEVel][:IMMediate][:AMPLitude], [:SCALar], [:NEXT].
        if nodes.first() == Some(&"SOUR") {
            nodes.remove(0);
        }
        nodes.retain(|n| !matches!(*n, "LEV" | "IMM" | "AMPL" | "SCAL" | "NEXT"));
        if nodes.len() == 2 && nodes[0] == "OUTP" && nodes[1] == "STAT" {
            nodes.pop();
        }
        let path = nodes.join(":");
        let n_ch = self.channels.len();
        match (path.as_str(), query) {
            ("SYST:ERR", true) => {
                let c = self.errors.pop_front().unwrap_or(0);
                Some(format!("{c},\"{}\"", message(c)))
            }
            ("SYST:VERS", true) => Some("1999.0".into()),
            ("SYST:REM" | "SYST:LOC" | "SYST:MIX" | "SYST:RWL" | "SYST:BEEP", false) => None,
            ("INST:NSEL", true) => Some(format!("{}", self.selected + 1)),
            ("INST:NSEL", false) => {
                match p0.map(|p| p.parse::<usize>()) {
                    None => self.push_error(code::MISSING_PARAMETER),
                    Some(Ok(n)) if (1..=n_ch).contains(&n) => self.selected = n - 1,
                    Some(Ok(_)) => self.push_error(code::DATA_OUT_OF_RANGE),
                    Some(Err(_)) => self.push_error(code::DATA_TYPE),
                }
                None
            }
            ("INST" | "INST:SEL", true) => Some(format!("OUTP{}", self.selected + 1)),
            ("INST" | "INST:SEL", false) => {
                let Some(p) = p0 else {
                    self.push_error(code::MISSING_PARAMETER);
                    return None;
                };
                let up = p.to_ascii_uppercase();
                let digits = up
                    .strip_prefix("OUTPUT")
                    .or_else(|| up.strip_prefix("OUTP"))
                    .or_else(|| up.strip_prefix("OUT"));
                match digits.and_then(|d| d.parse::<usize>().ok()) {
                    Some(n) if (1..=n_ch).contains(&n) => self.selected = n - 1,
                    Some(_) => self.push_error(code::DATA_OUT_OF_RANGE),
                    None => self.push_error(code::DATA_TYPE),
                }
                None
            }
            ("VOLT", true) | ("CURR", true) => {
                let volt = path == "VOLT";
                let (now, max) = if volt {
                    (self.channels[self.selected].voltage, MAX_VOLTAGE_V)
                } else {
                    (self.channels[self.selected].current, MAX_CURRENT_A)
                };
                let x = match p0.map(|p| p.to_ascii_uppercase()) {
                    None => now,
                    Some(p) if p == "MIN" || p == "MINIMUM" => 0.0,
                    Some(p) if p == "MAX" || p == "MAXIMUM" => max,
                    Some(_) => {
                        self.push_error(code::DATA_TYPE);
                        return None;
                    }
                };
                Some(if volt { format!("{x:.3}") } else { format!("{x:.4}") })
            }
            ("VOLT", false) => {
                let c = self.channels[self.selected].clone();
                if let Some(v) = self.level(p0, c.voltage, c.voltage_step, MAX_VOLTAGE_V) {
                    self.ch().voltage = v;
                }
                None
            }
            ("CURR", false) => {
                let c = self.channels[self.selected].clone();
                if let Some(i) = self.level(p0, c.current, c.current_step, MAX_CURRENT_A) {
                    self.ch().current = i;
                }
                None
            }
            ("VOLT:STEP", true) => Some(format!("{:.3}", self.channels[self.selected].voltage_step)),
            ("CURR:STEP", true) => Some(format!("{:.4}", self.channels[self.selected].current_step)),
            ("VOLT:STEP", false) => {
                if let Some(s) = self.number(p0, MAX_VOLTAGE_V) {
                    self.ch().voltage_step = s;
                }
                None
            }
            ("CURR:STEP", false) => {
                if let Some(s) = self.number(p0, MAX_CURRENT_A) {
                    self.ch().current_step = s;
                }
                None
            }
            ("APPL", true) => {
                let c = &self.channels[self.selected];
                Some(format!("{:.3},{:.4}", c.voltage, c.current))
            }
            ("APPL", false) => {
                if params.len() != 2 {
                    self.push_error(code::MISSING_PARAMETER);
                    return None;
                }
                let v = self.number(Some(params[0]), MAX_VOLTAGE_V)?;
                let i = self.number(Some(params[1]), MAX_CURRENT_A)?;
                let c = self.ch();
                c.voltage = v;
                c.current = i;
                None
            }
            ("OUTP:SEL", true) => Some(u8::from(self.channels[self.selected].active).to_string()),
            ("OUTP:SEL", false) => {
                if let Some(b) = self.flag(p0) {
                    self.ch().active = b;
                }
                None
            }
            ("OUTP:GEN", true) => Some(u8::from(self.general).to_string()),
            ("OUTP:GEN", false) => {
                if let Some(b) = self.flag(p0) {
                    self.general = b;
                }
                None
            }
            ("OUTP", true) => {
                let on = self.channels[self.selected].active && self.general;
                Some(u8::from(on).to_string())
            }
            ("OUTP", false) => {
                if let Some(b) = self.flag(p0) {
                    self.ch().active = b;
                    if b {
                        self.general = true;
                    }
                }
                None
            }
            ("MEAS:VOLT", true) => Some(format!("{:.3}", self.output(self.selected).0)),
            ("MEAS:CURR", true) => {
                let i = self.output(self.selected).1;
                let c = &mut self.channels[self.selected];
                if c.active && self.general {
                    c.measured += 1;
                }
                Some(format!("{i:.4}"))
            }
            _ => {
                self.push_error(code::UNDEFINED_HEADER);
                None
            }
        }
    }
}

impl super::Controller for Hmp {
    fn handle(&mut self, line: &str, _now: Instant) -> Handled {
        let mut replies = Vec::new();
        for cmd in line.split(';').filter(|c| !c.trim().is_empty()) {
            if let Some(r) = self.command(cmd) {
                replies.push(r);
            }
        }
        Handled {
            replies,
            disconnect: false,
        }
    }

    fn state(&self, _now: Instant) -> EmulatorState {
        EmulatorState::default()
    }

    fn busy(&self, _now: Instant) -> bool {
        false
    }
}

#[cfg(test)]
mod tests {
    use super::super::{Controller, EmulatorConfig, Protocol};
    use super::*;

    fn hmp() -> Hmp {
        Hmp::new(&EmulatorConfig::new(Protocol::Hmp4040, 4))
    }

    fn ask(h: &mut Hmp, line: &str) -> Vec<String> {
        h.handle(line, Instant::now()).replies
    }

    #[test]
    fn lamp_model_is_the_rated_lamp_at_rated_voltage() {
        let l = LampLoad::default();
        assert!((l.resistance(12.0) - 1.44).abs() < 1e-12);
        assert!((l.resistance(0.0) - 0.12).abs() < 1e-12);
        let (v, i) = l.operating_point(12.0, 10.0, 1.0);
        assert_eq!(v, 12.0);
        assert!((v * i - 100.0).abs() < 1e-9, "{}", v * i);
        // current limit below the lamp's draw: constant current at the limit
        let (v, i) = l.operating_point(12.0, 5.0, 1.0);
        assert!((i - 5.0).abs() < 1e-9 && v < 12.0, "{v} {i}");
        assert!(l.validate().is_ok());
    }

    #[test]
    fn identity_select_apply_output_measure() {
        let mut h = hmp();
        assert_eq!(ask(&mut h, "*IDN?"), vec![EMULATED_IDN]);
        assert!(ask(&mut h, "INST:NSEL 3").is_empty());
        assert_eq!(ask(&mut h, "INST:NSEL?"), vec!["3"]);
        assert!(ask(&mut h, "instrument:select output2").is_empty());
        assert_eq!(ask(&mut h, "INST?"), vec!["OUTP2"]);
        ask(&mut h, "APPL 12, 9");
        assert_eq!(ask(&mut h, "APPL?"), vec!["12.000,9.0000"]);
        assert_eq!(ask(&mut h, "MEAS:VOLT?;MEAS:CURR?"), vec!["0.000", "0.0000"]);
        ask(&mut h, "OUTPUT:SEL 1");
        assert_eq!(ask(&mut h, "MEAS:CURR?"), vec!["0.0000"], "master output still off");
        ask(&mut h, "OUTP:GEN ON");
        assert_eq!(ask(&mut h, "MEAS:VOLT?"), vec!["12.000"]);
        assert_eq!(ask(&mut h, "MEAS:CURR?"), vec!["8.3333"]);
        ask(&mut h, "SOUR:VOLT:LEV:IMM:AMPL 6");
        assert_eq!(ask(&mut h, "VOLT?"), vec!["6.000"]);
        let i: f64 = ask(&mut h, "MEASure:SCALar:CURRent?")[0].parse().unwrap();
        let want = 6.0 / (0.12 + 1.32 * 0.5f64.sqrt());
        assert!((i - want).abs() < 1e-4, "{i} vs {want}");
        ask(&mut h, "OUTP OFF");
        assert_eq!(ask(&mut h, "OUTP?"), vec!["0"]);
        assert_eq!(ask(&mut h, "SYST:ERR?"), vec!["0,\"No error\""]);
    }

    #[test]
    fn mistakes_go_to_the_error_queue() {
        let mut h = hmp();
        assert!(ask(&mut h, "FOO:BAR 1").is_empty());
        ask(&mut h, "INST:NSEL 5");
        ask(&mut h, "VOLT 40");
        ask(&mut h, "VOLT abc");
        ask(&mut h, "APPL 1");
        let errs: Vec<String> = (0..6).map(|_| ask(&mut h, "SYST:ERR?").remove(0)).collect();
        assert_eq!(
            errs,
            vec![
                "-113,\"Undefined header\"",
                "-222,\"Data out of range\"",
                "-222,\"Data out of range\"",
                "-104,\"Data type error\"",
                "-109,\"Missing parameter\"",
                "0,\"No error\"",
            ]
        );
        for _ in 0..(ERROR_QUEUE + 3) {
            ask(&mut h, "NOPE");
        }
        let mut last = String::new();
        for _ in 0..ERROR_QUEUE {
            last = ask(&mut h, "SYST:ERR?").remove(0);
        }
        assert_eq!(last, "-350,\"Queue overflow\"");
        ask(&mut h, "NOPE");
        ask(&mut h, "*CLS");
        assert_eq!(ask(&mut h, "SYST:ERR:NEXT?"), vec!["0,\"No error\""]);
    }

    #[test]
    fn drift_raises_the_resistance_per_current_measurement() {
        let mut cfg = EmulatorConfig::new(Protocol::Hmp4040, 4);
        cfg.lamp.drift = 0.01;
        let mut h = Hmp::new(&cfg);
        ask(&mut h, "APPL 12,10;OUTP:SEL 1;OUTP:GEN 1");
        let currents: Vec<f64> = (0..4).map(|_| ask(&mut h, "MEAS:CURR?")[0].parse().unwrap()).collect();
        for (n, i) in currents.iter().enumerate() {
            let want = 12.0 / (1.44 * 1.01f64.powi(n as i32));
            assert!((i - want).abs() < 1e-4, "{n}: {i} vs {want}");
        }
    }
}
