//! Injected faults for the controller emulators.
//!
//! A [`FaultPlan`] is parsed from command-line style specs (`garble:every=5`,
//! `disconnect:at-move=3`, …) so the same words work in `gonio sim serve-stage --fault …`,
//! in rig files and in tests. Faults come in two families:
//!
//! - **reply faults** (garble, drop, slow) act on what the emulator writes back; they are
//!   decided by the pty loop, which counts commands and replies;
//! - **motion faults** (stall, limit switch, disconnect) act on the N-th move command (`move
//!   abs`/`move rel`/`move min|max` on Zaber, `PA`/`PR` on the ESP), counted over all axes
//!   and devices from 1; homing is not a move for this count.
//!
//! Every fault is deterministic (no random numbers), so a failing test replays exactly.

use std::fmt;
use std::str::FromStr;
use std::time::Duration;

/// When a reply fault fires.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Trigger {
    /// Every n-th reply line (n ≥ 1), counted from the first reply the emulator writes.
    EveryReply(u64),
    /// The replies to the n-th command line received (1-based; empty lines are not commands).
    AtCommand(u64),
    /// Every reply.
    Always,
}

impl Trigger {
    /// Does the fault fire for reply number `reply_no` (1-based) to command `cmd_no`?
    pub fn fires(&self, cmd_no: u64, reply_no: u64) -> bool {
        match *self {
            Trigger::EveryReply(n) => reply_no.checked_rem(n) == Some(0),
            Trigger::AtCommand(n) => cmd_no == n,
            Trigger::Always => true,
        }
    }
}

/// One injected fault.
#[derive(Clone, Debug, PartialEq)]
pub enum Fault {
    /// Corrupt the bytes of a reply (printable characters XOR 0x5A, which turns digits into
    /// letters and `@` into a control character, so no corrupted reply parses as a valid one).
    Garble(Trigger),
    /// Send nothing for the reply.
    Drop(Trigger),
    /// Delay the reply.
    Slow { delay: Duration, when: Trigger },
    /// At move N the axis stops making progress half way but keeps reporting BUSY (Zaber) /
    /// motion not done (ESP) until `stop`: what a no-progress watchdog must catch.
    Stall { at_move: u64 },
    /// At move N the axis stalls half way and the controller notices and stops it: Zaber
    /// reports IDLE with the `FS` fault flag (stalled and stopped), the ESP queues error x03
    /// (following error threshold exceeded).
    StallStop { at_move: u64 },
    /// At move N the axis hits a limit switch half way and stops: Zaber reports IDLE with the
    /// `WL` warning, the ESP queues error x04/x05 (positive/negative hardware limit).
    LimitSwitch { at_move: u64 },
    /// At move N (before executing it) the emulator closes its pty, as if the cable was
    /// pulled. With [`super::EmulatorConfig::reconnect_after`] it opens a new pty later.
    Disconnect { at_move: u64 },
}

/// Errors in a fault spec; the message quotes the spec.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FaultParseError {
    #[error("fault `{spec}`: unknown kind `{kind}` (known: garble, drop, slow, stall, stall-stop, limit, disconnect)")]
    UnknownKind { spec: String, kind: String },
    #[error("fault `{spec}`: {reason}")]
    Invalid { spec: String, reason: String },
}

impl FromStr for Fault {
    type Err = FaultParseError;

    /// `kind[:key=value[,key=value]]` with kinds `garble`, `drop` (keys `every=N` or `at=N`),
    /// `slow` (`ms=D` plus optional `every=N`/`at=N`; default: every reply), `stall`, `limit`,
    /// `stall-stop`, `disconnect` (key `at-move=N`).
    fn from_str(spec: &str) -> Result<Self, Self::Err> {
        let invalid = |reason: String| FaultParseError::Invalid {
            spec: spec.to_string(),
            reason,
        };
        let (kind, rest) = spec.split_once(':').unwrap_or((spec, ""));
        let mut every = None;
        let mut at = None;
        let mut at_move = None;
        let mut ms = None;
        for kv in rest.split(',').filter(|s| !s.trim().is_empty()) {
            let (k, v) = kv
                .split_once('=')
                .ok_or_else(|| invalid(format!("`{kv}` is not key=value")))?;
            let n: u64 = v
                .trim()
                .parse()
                .map_err(|_| invalid(format!("`{v}` is not a non-negative integer")))?;
            if n == 0 {
                return Err(invalid(format!("`{k}` must be ≥ 1")));
            }
            match k.trim() {
                "every" => every = Some(n),
                "at" => at = Some(n),
                "at-move" => at_move = Some(n),
                "ms" => ms = Some(n),
                other => return Err(invalid(format!("unknown key `{other}`"))),
            }
        }
        let trigger = |default: Option<Trigger>| -> Result<Trigger, FaultParseError> {
            match (every, at) {
                (Some(_), Some(_)) => Err(invalid("give either every=N or at=N, not both".into())),
                (Some(n), None) => Ok(Trigger::EveryReply(n)),
                (None, Some(n)) => Ok(Trigger::AtCommand(n)),
                (None, None) => default.ok_or_else(|| invalid("needs every=N or at=N".into())),
            }
        };
        let need_move = || at_move.ok_or_else(|| invalid("needs at-move=N".into()));
        match kind.trim() {
            "garble" => Ok(Fault::Garble(trigger(None)?)),
            "drop" => Ok(Fault::Drop(trigger(None)?)),
            "slow" => Ok(Fault::Slow {
                delay: Duration::from_millis(ms.ok_or_else(|| invalid("needs ms=D".into()))?),
                when: trigger(Some(Trigger::Always))?,
            }),
            "stall" => Ok(Fault::Stall { at_move: need_move()? }),
            "stall-stop" => Ok(Fault::StallStop { at_move: need_move()? }),
            "limit" | "limit-switch" => Ok(Fault::LimitSwitch { at_move: need_move()? }),
            "disconnect" => Ok(Fault::Disconnect { at_move: need_move()? }),
            other => Err(FaultParseError::UnknownKind {
                spec: spec.to_string(),
                kind: other.to_string(),
            }),
        }
    }
}

impl fmt::Display for Fault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let trig = |t: &Trigger| match t {
            Trigger::EveryReply(n) => format!("every={n}"),
            Trigger::AtCommand(n) => format!("at={n}"),
            Trigger::Always => String::new(),
        };
        match self {
            Fault::Garble(t) => write!(f, "garble:{}", trig(t)),
            Fault::Drop(t) => write!(f, "drop:{}", trig(t)),
            Fault::Slow { delay, when } => {
                let t = trig(when);
                let sep = if t.is_empty() { "" } else { "," };
                write!(f, "slow:ms={}{sep}{t}", delay.as_millis())
            }
            Fault::Stall { at_move } => write!(f, "stall:at-move={at_move}"),
            Fault::StallStop { at_move } => write!(f, "stall-stop:at-move={at_move}"),
            Fault::LimitSwitch { at_move } => write!(f, "limit:at-move={at_move}"),
            Fault::Disconnect { at_move } => write!(f, "disconnect:at-move={at_move}"),
        }
    }
}

/// What a motion fault does to one move.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MoveFault {
    Stall,
    StallStop,
    LimitSwitch,
    Disconnect,
}

/// What the pty loop does with one reply line.
#[derive(Clone, Debug, PartialEq, Eq, Default)]
pub struct ReplyFate {
    pub drop: bool,
    pub garble: bool,
    pub delay: Duration,
}

/// The set of faults of one emulator.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FaultPlan {
    pub faults: Vec<Fault>,
}

impl FaultPlan {
    /// No faults.
    pub fn none() -> Self {
        Self::default()
    }

    /// Parse several specs (e.g. repeated `--fault` options).
    pub fn parse<S: AsRef<str>>(specs: &[S]) -> Result<Self, FaultParseError> {
        let faults = specs.iter().map(|s| s.as_ref().parse()).collect::<Result<_, _>>()?;
        Ok(Self { faults })
    }

    /// Builder-style: add one fault.
    pub fn with(mut self, fault: Fault) -> Self {
        self.faults.push(fault);
        self
    }

    /// The motion fault (if any) for move number `move_no` (1-based). Disconnect wins over
    /// the others because the move never reaches the controller.
    pub fn move_fault(&self, move_no: u64) -> Option<MoveFault> {
        let mut found = None;
        for f in &self.faults {
            match *f {
                Fault::Disconnect { at_move } if at_move == move_no => return Some(MoveFault::Disconnect),
                Fault::Stall { at_move } if at_move == move_no => found = Some(MoveFault::Stall),
                Fault::StallStop { at_move } if at_move == move_no => found = Some(MoveFault::StallStop),
                Fault::LimitSwitch { at_move } if at_move == move_no && found.is_none() => {
                    found = Some(MoveFault::LimitSwitch)
                }
                _ => {}
            }
        }
        found
    }

    /// The fate of reply number `reply_no` (1-based, over the emulator's life) written for
    /// command number `cmd_no`.
    pub fn reply_fate(&self, cmd_no: u64, reply_no: u64) -> ReplyFate {
        let mut fate = ReplyFate::default();
        for f in &self.faults {
            match f {
                Fault::Garble(t) if t.fires(cmd_no, reply_no) => fate.garble = true,
                Fault::Drop(t) if t.fires(cmd_no, reply_no) => fate.drop = true,
                Fault::Slow { delay, when } if when.fires(cmd_no, reply_no) => fate.delay += *delay,
                _ => {}
            }
        }
        fate
    }
}

/// Corrupt a reply line (without its terminator): every printable byte at an even index is
/// XOR-ed with 0x5A. Digits become letters, `@`/`#`/`!` become control characters, so a
/// protocol parser (or a Zaber checksum) always notices.
pub fn garble(line: &[u8]) -> Vec<u8> {
    line.iter()
        .enumerate()
        .map(|(i, &b)| {
            if i % 2 == 0 && b.is_ascii_graphic() {
                b ^ 0x5A
            } else {
                b
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_every_kind_and_round_trips() {
        for s in [
            "garble:every=5",
            "garble:at=7",
            "drop:every=3",
            "drop:at=2",
            "slow:ms=200",
            "slow:ms=50,every=4",
            "stall:at-move=2",
            "stall-stop:at-move=4",
            "limit:at-move=1",
            "disconnect:at-move=3",
        ] {
            let f: Fault = s.parse().unwrap();
            assert_eq!(f.to_string(), s, "{s}");
        }
    }

    #[test]
    fn rejects_bad_specs_with_the_spec_in_the_message() {
        for s in [
            "garble",
            "garble:every=0",
            "garble:every=x",
            "garble:every=2,at=3",
            "drop:when=3",
            "stall",
            "slow:every=2",
            "melt:at=1",
            "limit:at-move",
        ] {
            let e = s.parse::<Fault>().unwrap_err();
            assert!(e.to_string().contains(s), "{s}: {e}");
        }
    }

    #[test]
    fn reply_fates_fire_where_asked() {
        let plan = FaultPlan::parse(&["garble:every=3", "drop:at=2", "slow:ms=10,at=4"]).unwrap();
        assert_eq!(plan.reply_fate(1, 1), ReplyFate::default());
        assert!(plan.reply_fate(2, 2).drop);
        assert!(!plan.reply_fate(2, 2).garble);
        assert!(plan.reply_fate(3, 3).garble);
        assert!(plan.reply_fate(9, 6).garble);
        assert_eq!(plan.reply_fate(4, 4).delay, Duration::from_millis(10));
        assert_eq!(plan.reply_fate(5, 5).delay, Duration::ZERO);
    }

    #[test]
    fn move_faults_pick_the_right_move() {
        let plan = FaultPlan::parse(&["stall:at-move=2", "limit:at-move=3", "disconnect:at-move=3"]).unwrap();
        assert_eq!(plan.move_fault(1), None);
        assert_eq!(plan.move_fault(2), Some(MoveFault::Stall));
        assert_eq!(plan.move_fault(3), Some(MoveFault::Disconnect));
    }

    #[test]
    fn garbled_replies_never_parse_as_numbers_or_zaber_replies() {
        let g = garble(b"@01 1 OK IDLE -- 1000");
        assert_ne!(g[0], b'@');
        let g = garble(b"12.50000");
        assert!(std::str::from_utf8(&g).unwrap().parse::<f64>().is_err());
    }
}
