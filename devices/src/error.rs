//! Typed device errors. Every variant names the device (axis, camera or light) and,
//! where there is one, the command that failed, so a message is actionable on its own.

use thiserror::Error;

#[derive(Debug, Error, Clone, PartialEq)]
pub enum DeviceError {
    #[error("{device}: target {target:.6} outside soft limits [{min:.6}, {max:.6}] (command `{command}`)")]
    SoftLimit {
        device: String,
        command: String,
        target: f64,
        min: f64,
        max: f64,
    },
    #[error("{device}: limit switch hit during `{command}`")]
    LimitSwitch { device: String, command: String },
    #[error("{device}: `{command}` timed out after {seconds:.3} s")]
    Timeout {
        device: String,
        command: String,
        seconds: f64,
    },
    #[error("{device}: stalled during `{command}` (no progress at position {position:.6})")]
    Stall {
        device: String,
        command: String,
        position: f64,
    },
    #[error(
        "{device}: missed target in `{command}`: read back {read_back:.6}, wanted {target:.6} (deadband {deadband:.6})"
    )]
    MissedTarget {
        device: String,
        command: String,
        target: f64,
        read_back: f64,
        deadband: f64,
    },
    #[error("{device}: command `{command}` rejected: {reason}")]
    Rejected {
        device: String,
        command: String,
        reason: String,
    },
    #[error("{device}: garbled reply to `{command}`: {reply:?}")]
    Garbled {
        device: String,
        command: String,
        reply: String,
    },
    #[error("{device}: disconnected during `{command}`: {reason}")]
    Disconnected {
        device: String,
        command: String,
        reason: String,
    },
    #[error("{device}: not homed; home the axis before `{command}`")]
    NotHomed { device: String, command: String },
    #[error("{device}: `{command}` failed: {reason}")]
    Other {
        device: String,
        command: String,
        reason: String,
    },
}

impl DeviceError {
    /// The device the error is about.
    pub fn device(&self) -> &str {
        match self {
            DeviceError::SoftLimit { device, .. }
            | DeviceError::LimitSwitch { device, .. }
            | DeviceError::Timeout { device, .. }
            | DeviceError::Stall { device, .. }
            | DeviceError::MissedTarget { device, .. }
            | DeviceError::Rejected { device, .. }
            | DeviceError::Garbled { device, .. }
            | DeviceError::Disconnected { device, .. }
            | DeviceError::NotHomed { device, .. }
            | DeviceError::Other { device, .. } => device,
        }
    }

    /// Whether retrying the same command may succeed (transport glitches), as opposed to
    /// errors that need a person (limits, stalls, rejections).
    pub fn is_transient(&self) -> bool {
        matches!(
            self,
            DeviceError::Timeout { .. } | DeviceError::Garbled { .. } | DeviceError::Disconnected { .. }
        )
    }
}
