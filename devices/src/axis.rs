//! The axis trait: one motorized stage (rotary or linear).
//!
//! Positions are in the axis' own units inside the code: radians for rotary axes,
//! millimetres for linear ones. A move is split into `start_move` and `wait_idle` so the
//! engine can start all axes of a transition at once and wait for the slowest.

use crate::{DeviceError, MotionModel};
use async_trait::async_trait;
use serde::{Deserialize, Serialize};

/// Soft limits in the axis' units; `min < max`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SoftLimits {
    pub min: f64,
    pub max: f64,
}

impl SoftLimits {
    pub fn contains(&self, x: f64) -> bool {
        x >= self.min && x <= self.max
    }
}

/// What an axis reports about itself.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AxisStatus {
    pub homed: bool,
    pub moving: bool,
    pub position: f64,
}

#[async_trait]
pub trait Axis: Send + Sync {
    /// The axis name from the rig file (used in every error message).
    fn name(&self) -> &str;
    fn limits(&self) -> SoftLimits;
    fn motion(&self) -> MotionModel;
    /// Find the reference and set the position to zero.
    async fn home(&self) -> Result<(), DeviceError>;
    /// Start a move to an absolute position and return once the controller accepted it.
    /// Targets outside the soft limits are refused before anything moves.
    async fn start_move(&self, target: f64) -> Result<(), DeviceError>;
    /// Wait until the axis is idle and settled; returns the read-back position.
    async fn wait_idle(&self) -> Result<f64, DeviceError>;
    /// Stop any motion now.
    async fn stop(&self) -> Result<(), DeviceError>;
    /// Read back the current position.
    async fn position(&self) -> Result<f64, DeviceError>;
    async fn status(&self) -> Result<AxisStatus, DeviceError>;

    /// An independent reading of where the load really is (a load-side encoder), in the
    /// axis' units; `Ok(None)` when the axis has none (the default).
    ///
    /// Why it exists: the read-back ([`Axis::position`]) is the controller's own step count,
    /// which by construction cannot see backlash, homing scatter or drive errors. Mechanical
    /// calibration (`gonio calibrate` with a `mechanical` recipe) compares the two.
    async fn reference_position(&self) -> Result<Option<f64>, DeviceError> {
        Ok(None)
    }

    /// Start a move to `target` whose cruise velocity is at most `velocity` (units/s, > 0),
    /// with the axis' own acceleration: what a fly-scan flies a light ring with (the
    /// exposures are timed against this profile). Axes whose controller cannot take a
    /// commanded velocity refuse (the default), and the planner flies nothing on them.
    async fn start_move_at(&self, target: f64, velocity: f64) -> Result<(), DeviceError> {
        let _ = (target, velocity);
        Err(DeviceError::Rejected {
            device: self.name().to_string(),
            command: "start_move_at".into(),
            reason: "this axis' backend has no constant-velocity moves; fly-scan needs them".into(),
        })
    }

    /// Start a move that follows `trajectory` phase by phase (its times from now, its
    /// positions absolute; it begins at rest where the axis stands): a fly-scan flight with a
    /// velocity profile per gap (see [`crate::motion::Trajectory::flight`]). Axes whose
    /// controller cannot stream a profile refuse (the default): the planner flies them at
    /// one velocity per flight ([`Axis::start_move_at`]).
    async fn start_trajectory(&self, trajectory: &crate::motion::Trajectory) -> Result<(), DeviceError> {
        let _ = trajectory;
        Err(DeviceError::Rejected {
            device: self.name().to_string(),
            command: "start_trajectory".into(),
            reason: "this axis' backend cannot follow a velocity profile; fly-scan flies it at one velocity".into(),
        })
    }

    /// Who the controller says it is (model or device id, firmware): what `gonio devices
    /// check` prints so a lab sees the hardware it is about to run on. An axis that cannot
    /// tell answers with its name (the default).
    async fn identity(&self) -> Result<String, DeviceError> {
        Ok(self.name().to_string())
    }

    /// Move to `target` and wait until settled; returns the read-back position.
    async fn move_abs(&self, target: f64) -> Result<f64, DeviceError> {
        self.start_move(target).await?;
        self.wait_idle().await
    }
}

/// Check a target against limits with the error every backend should give.
pub fn check_limits(name: &str, limits: SoftLimits, target: f64, command: &str) -> Result<(), DeviceError> {
    if !target.is_finite() || !limits.contains(target) {
        return Err(DeviceError::SoftLimit {
            device: name.to_string(),
            command: command.to_string(),
            target,
            min: limits.min,
            max: limits.max,
        });
    }
    Ok(())
}
