//! Opt-in fault injection for the simulated camera (rig file `camera.options.fault`), so
//! the engine's capture policy (bounded retry, stale-frame rule, saturation handling) can
//! be exercised without hardware, the way `emulate/` does for serial controllers.
//!
//! The spec uses the serial emulators' `--fault` words: `kind[:key=value[,key=value]]`
//! with kinds
//! - `timeout`: the capture never returns (the engine's capture timeout must fire);
//! - `drop`: the capture fails once with an error (a frame lost in transfer);
//! - `stale`: the camera hands out the previous frame again (sequence and timestamp from
//!   before the last move), as a streaming camera does with a frame still in its queue;
//! - `saturate`: every pixel at the maximum DN (a lamp flash, an exposure far too long);
//! - `exposure`: a `configure` that changes the exposure keeps the old one and reports it
//!   (a driver that rounds or ignores the request): counted per such `configure`, not per
//!   capture, so `exposure:at=1` is the first exposure change after setup;
//!
//! and keys `every=N` (every N-th capture) or `at=N` (the N-th capture, 1-based), plus
//! `count=K` (with `at`: K consecutive faulty captures, default 1; a count above the
//! engine's retries makes the fault persistent). Captures are counted per camera session,
//! i.e. per process: a `--resume` starts a fresh session, like a power-cycled camera.
//!
//! Without `fault` the camera carries `None` and pays nothing.

use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};

/// What goes wrong.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CameraFaultKind {
    Timeout,
    Drop,
    Stale,
    Saturate,
    Exposure,
}

impl CameraFaultKind {
    fn word(self) -> &'static str {
        match self {
            CameraFaultKind::Timeout => "timeout",
            CameraFaultKind::Drop => "drop",
            CameraFaultKind::Stale => "stale",
            CameraFaultKind::Saturate => "saturate",
            CameraFaultKind::Exposure => "exposure",
        }
    }
}

/// When it goes wrong (capture numbers are 1-based).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CameraFaultTrigger {
    Every(u64),
    At { first: u64, count: u64 },
}

/// One injected camera fault plus the capture counter it is judged against.
#[derive(Debug)]
pub struct CameraFault {
    pub kind: CameraFaultKind,
    pub trigger: CameraFaultTrigger,
    captures: AtomicU64,
}

/// A malformed fault spec; the message quotes it.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("camera fault `{spec}`: {reason}")]
pub struct CameraFaultParseError {
    pub spec: String,
    pub reason: String,
}

impl CameraFault {
    /// Parse `kind[:every=N | :at=N[,count=K]]`.
    pub fn parse(spec: &str) -> Result<CameraFault, CameraFaultParseError> {
        let bad = |reason: String| CameraFaultParseError {
            spec: spec.to_string(),
            reason,
        };
        let (kind, rest) = spec.split_once(':').unwrap_or((spec, ""));
        let kind = match kind.trim() {
            "timeout" => CameraFaultKind::Timeout,
            "drop" => CameraFaultKind::Drop,
            "stale" => CameraFaultKind::Stale,
            "saturate" => CameraFaultKind::Saturate,
            "exposure" => CameraFaultKind::Exposure,
            other => {
                return Err(bad(format!(
                    "unknown kind `{other}` (known: timeout, drop, stale, saturate, exposure)"
                )))
            }
        };
        let (mut every, mut at, mut count) = (None, None, None);
        for kv in rest.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            let (k, v) = kv
                .split_once('=')
                .ok_or_else(|| bad(format!("`{kv}`: expected key=value")))?;
            let n: u64 = v
                .trim()
                .parse()
                .ok()
                .filter(|n| *n >= 1)
                .ok_or_else(|| bad(format!("`{kv}`: the value must be an integer ≥ 1")))?;
            match k.trim() {
                "every" => every = Some(n),
                "at" => at = Some(n),
                "count" => count = Some(n),
                other => return Err(bad(format!("unknown key `{other}` (every, at, count)"))),
            }
        }
        let trigger = match (every, at, count) {
            (Some(_), Some(_), _) => return Err(bad("give either every=N or at=N, not both".into())),
            (Some(_), None, Some(_)) => return Err(bad("count=K goes with at=N, not every=N".into())),
            (Some(n), None, None) => CameraFaultTrigger::Every(n),
            (None, Some(first), count) => CameraFaultTrigger::At {
                first,
                count: count.unwrap_or(1),
            },
            (None, None, _) => return Err(bad("needs every=N or at=N".into())),
        };
        Ok(CameraFault {
            kind,
            trigger,
            captures: AtomicU64::new(0),
        })
    }

    /// Count one capture; the fault kind if this capture is a faulty one. An `exposure`
    /// fault is counted by [`CameraFault::next_exposure_change`] instead.
    pub fn next_capture(&self) -> Option<CameraFaultKind> {
        if self.kind == CameraFaultKind::Exposure {
            return None;
        }
        self.count()
    }

    /// Count one `configure` that changes the exposure; true if an `exposure` fault makes
    /// the camera ignore it.
    pub fn next_exposure_change(&self) -> bool {
        self.kind == CameraFaultKind::Exposure && self.count().is_some()
    }

    fn count(&self) -> Option<CameraFaultKind> {
        let n = self.captures.fetch_add(1, Ordering::SeqCst) + 1;
        let fires = match self.trigger {
            CameraFaultTrigger::Every(k) => n.is_multiple_of(k),
            CameraFaultTrigger::At { first, count } => n >= first && n - first < count,
        };
        fires.then_some(self.kind)
    }
}

impl fmt::Display for CameraFault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.trigger {
            CameraFaultTrigger::Every(n) => write!(f, "{}:every={n}", self.kind.word()),
            CameraFaultTrigger::At { first, count: 1 } => write!(f, "{}:at={first}", self.kind.word()),
            CameraFaultTrigger::At { first, count } => write!(f, "{}:at={first},count={count}", self.kind.word()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_round_trips_and_fires() {
        for s in [
            "timeout:at=3",
            "drop:every=4",
            "stale:at=2",
            "saturate:at=5,count=3",
            "exposure:every=2",
        ] {
            assert_eq!(CameraFault::parse(s).unwrap().to_string(), s);
        }
        let f = CameraFault::parse("drop:every=3").unwrap();
        let fired: Vec<bool> = (0..7).map(|_| f.next_capture().is_some()).collect();
        assert_eq!(fired, [false, false, true, false, false, true, false]);
        let f = CameraFault::parse("timeout:at=2,count=2").unwrap();
        let fired: Vec<_> = (0..5).map(|_| f.next_capture()).collect();
        let t = Some(CameraFaultKind::Timeout);
        assert_eq!(fired, [None, t, t, None, None]);
        // An exposure fault does not count captures, only exposure changes.
        let f = CameraFault::parse("exposure:at=2").unwrap();
        assert!((0..5).all(|_| f.next_capture().is_none()));
        let fired: Vec<bool> = (0..3).map(|_| f.next_exposure_change()).collect();
        assert_eq!(fired, [false, true, false]);
    }

    #[test]
    fn refuses_bad_specs_with_a_reason() {
        for (s, why) in [
            ("melt:at=1", "unknown kind"),
            ("drop", "needs every=N or at=N"),
            ("drop:every=0", "≥ 1"),
            ("drop:every=2,at=3", "either"),
            ("drop:every=2,count=3", "count=K goes with at=N"),
            ("stale:at", "key=value"),
            ("stale:when=3", "unknown key"),
        ] {
            let e = CameraFault::parse(s).unwrap_err();
            assert!(e.to_string().contains(why), "{s}: {e}");
            assert!(e.to_string().contains(s), "{s}: {e}");
        }
    }
}
