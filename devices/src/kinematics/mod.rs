//! Rig kinematics: axis positions ↔ (light, view) directions in the sample frame.
//!
//! A configuration `q` is the vector of axis positions in the order of the rig file's axes
//! (radians). Inverse kinematics returns *every* solution inside the soft limits; choosing
//! among them (the one closest in time to the previous configuration) is
//! [`fastest_from`], used by the planner.

pub mod two_arm;

use crate::geometry::{Direction, Vec3};
use crate::rig::{RigKind, RigSpec};
use crate::MotionModel;
use serde::{Deserialize, Serialize};

/// Why a (light, view) pair cannot be measured as asked.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "reason", rename_all = "snake_case")]
pub enum Infeasibility {
    /// No configuration inside the axis limits reaches the pair.
    OutOfLimits { detail: String },
    /// The camera body sits in the lamp's path to the sample.
    LightBlockedByCamera { clearance_mm: f64 },
}

impl std::fmt::Display for Infeasibility {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Infeasibility::OutOfLimits { detail } => write!(f, "out of axis limits: {detail}"),
            Infeasibility::LightBlockedByCamera { clearance_mm } => {
                write!(
                    f,
                    "light blocked by the camera (clearance {clearance_mm:.1} mm, needs > 0)"
                )
            }
        }
    }
}

/// A pinhole camera's pose in the sample frame (millimetres).
///
/// `right`, `down`, `forward` are orthonormal (OpenCV convention: x right, y down, z into
/// the scene); `position` is the centre of projection.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraPose {
    pub position: Vec3,
    pub right: Vec3,
    pub down: Vec3,
    pub forward: Vec3,
}

impl CameraPose {
    /// Camera-frame coordinates of a sample-frame point.
    pub fn to_camera(&self, p: Vec3) -> Vec3 {
        let d = p - self.position;
        Vec3::new(d.dot(self.right), d.dot(self.down), d.dot(self.forward))
    }
}

pub trait Kinematics: Send + Sync {
    /// Number of axes (= length of a configuration).
    fn axis_count(&self) -> usize;
    /// (light, view) directions in the sample frame for a configuration.
    fn forward(&self, q: &[f64]) -> (Direction, Direction);
    /// Camera pose in the sample frame.
    fn camera_pose(&self, q: &[f64]) -> CameraPose;
    /// Lamp position in the sample frame (mm).
    fn light_position(&self, q: &[f64]) -> Vec3;
    /// Every configuration inside the limits that measures the pair. `prev` resolves free
    /// parameters (the azimuth at θ = 0) to "do not move".
    fn inverse(&self, light: Direction, view: Direction, prev: Option<&[f64]>) -> Result<Vec<Vec<f64>>, Infeasibility>;
    /// Axes whose position does not matter for this pair (e.g. the turntable when the
    /// camera looks straight down): the planner lets them stay where they are.
    fn free_axes(&self, _light: Direction, _view: Direction) -> Vec<usize> {
        Vec::new()
    }
    /// The configuration the rig is in after homing.
    fn home(&self) -> Vec<f64> {
        vec![0.0; self.axis_count()]
    }
}

/// Kinematics for a rig file.
pub fn for_rig(rig: &RigSpec) -> Box<dyn Kinematics> {
    match rig.kind {
        RigKind::TwoArm => Box::new(two_arm::TwoArm::new(rig)),
    }
}

/// Time to go from `a` to `b` with all axes moving at once: the slowest axis decides.
pub fn transition_time(motions: &[MotionModel], a: &[f64], b: &[f64]) -> f64 {
    motions
        .iter()
        .zip(a.iter().zip(b))
        .map(|(m, (x, y))| m.move_time(y - x))
        .fold(0.0, f64::max)
}

/// Among `solutions`, the one reached fastest from `prev` (ties: smallest total travel).
pub fn fastest_from<'a>(motions: &[MotionModel], prev: &[f64], solutions: &'a [Vec<f64>]) -> &'a [f64] {
    let mut best = &solutions[0];
    let mut best_key = (f64::INFINITY, f64::INFINITY);
    for s in solutions {
        let t = transition_time(motions, prev, s);
        let travel: f64 = s.iter().zip(prev).map(|(x, y)| (x - y).abs()).sum();
        if (t, travel) < best_key {
            best_key = (t, travel);
            best = s;
        }
    }
    best
}
