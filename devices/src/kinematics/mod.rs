//! Rig kinematics: axis positions ↔ (light, view) directions in the sample frame.
//!
//! A configuration `q` is the vector of axis positions in the order of the rig file's axes
//! (radians). Inverse kinematics returns *every* solution inside the soft limits; choosing
//! among them (the one closest in time to the previous configuration) is
//! [`fastest_from`], used by the planner.

pub mod dome;
pub mod gimbal;
pub mod holder;
pub mod lightdrum;
mod rot;
pub mod static_light;
pub mod two_arm;

use crate::geometry::{Direction, Vec3};
use crate::rig::{RigKind, RigSpec};
use crate::{MotionModel, SoftLimits};
use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;

/// Why a (light, view) pair cannot be measured as asked.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "reason", rename_all = "snake_case")]
pub enum Infeasibility {
    /// No configuration inside the axis limits reaches the pair.
    OutOfLimits { detail: String },
    /// The camera body sits in the lamp's path to the sample.
    LightBlockedByCamera { clearance_mm: f64 },
    /// A dome measures only the directions it has a camera / lamp for ("measuring is
    /// selecting"); the detail names the nearest available ones.
    NotInDome { detail: String },
    /// The sample holder's rim is in the way of the light or the view ray for some point
    /// of the sample (grazing angles).
    HolderShadow {
        /// `light` or `view`.
        ray: String,
        /// Lowest height (mm) at which a ray from the sample to the device crosses the rim.
        crossing_height_mm: f64,
        rim_height_mm: f64,
    },
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
            Infeasibility::NotInDome { detail } => write!(f, "not in the dome: {detail}"),
            Infeasibility::HolderShadow {
                ray,
                crossing_height_mm,
                rim_height_mm,
            } => write!(
                f,
                "holder rim shadows the {ray} ray (crosses the rim at {crossing_height_mm:.2} mm, rim {rim_height_mm:.2} mm)"
            ),
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
///
/// With a holder rim configured (`holder_rim_height_mm` > 0), the kind's kinematics are
/// wrapped in [`holder::Shadowed`], which refuses pairs the rim shadows before asking the
/// mechanism: the rim does not depend on how the rig reaches a pair.
pub fn for_rig(rig: &RigSpec) -> Box<dyn Kinematics> {
    let inner: Box<dyn Kinematics> = match rig.kind {
        RigKind::TwoArm => Box::new(two_arm::TwoArm::new(rig)),
        RigKind::Gimbal => Box::new(gimbal::Gimbal::new(rig)),
        RigKind::StaticLight => Box::new(static_light::StaticLight::new(rig)),
        RigKind::Dome => Box::new(dome::Dome::new(rig)),
        RigKind::Lightdrum => Box::new(lightdrum::Lightdrum::new(rig)),
        RigKind::StaticLightArc => Box::new(static_light::StaticLight::new(rig)),
    };
    match holder::Holder::from_rig(rig) {
        Some(h) => Box::new(holder::Shadowed::new(inner, h)),
        None => inner,
    }
}

/// Axis roles a rig kind needs (each exactly one axis; no other roles allowed).
pub fn roles(kind: RigKind) -> &'static [&'static str] {
    match kind {
        RigKind::TwoArm => &two_arm::ROLES,
        RigKind::Gimbal => &gimbal::ROLES,
        RigKind::StaticLight => &static_light::ROLES,
        RigKind::Dome => &dome::ROLES,
        RigKind::Lightdrum => &lightdrum::ROLES,
        RigKind::StaticLightArc => &static_light::ROLES_ONE_ARC,
    }
}

/// Targets this close (rad) outside a soft limit are snapped onto it: a pair exactly at a
/// limit (θ = 75° with the arc ending at 75°) must not fail on the last bit of rounding.
pub const LIMIT_SNAP: f64 = 1e-9;

/// `x` if inside the limits, snapped onto a limit it misses by at most [`LIMIT_SNAP`].
pub fn fit(l: SoftLimits, x: f64) -> Option<f64> {
    if l.contains(x) {
        Some(x)
    } else if x >= l.min - LIMIT_SNAP && x <= l.max + LIMIT_SNAP {
        Some(x.clamp(l.min, l.max))
    } else {
        None
    }
}

/// All values `base + k·2π` inside the limits: the wrap-arounds of a rotary axis whose
/// cable limits allow more than one turn (or less than one: then possibly none).
pub fn wraps(l: SoftLimits, base: f64) -> Vec<f64> {
    let mut out = Vec::new();
    let mut x = base - TAU * ((base - l.min) / TAU).floor() - TAU;
    while x <= l.max + LIMIT_SNAP {
        if let Some(v) = fit(l, x) {
            if out.last().is_none_or(|&p: &f64| (v - p).abs() > LIMIT_SNAP) {
                out.push(v);
            }
        }
        x += TAU;
    }
    out
}

/// Clearance (mm) between the lamp's straight path to the sample centre and a sphere of
/// radius `block_radius` around the camera centre; ≤ 0 means the camera blocks the light.
/// Both positions in the same frame (mm, sample centre at the origin).
pub fn light_clearance(lamp: Vec3, camera: Vec3, block_radius: f64) -> f64 {
    // segment from the lamp to the origin: points lamp·(1−t), t ∈ [0, 1]
    let t = ((lamp - camera).dot(lamp) / lamp.dot(lamp)).clamp(0.0, 1.0);
    (lamp * (1.0 - t) - camera).norm() - block_radius
}

/// The usual "no configuration reaches it" reason, with the pair in degrees.
pub(crate) fn out_of_limits(light: Direction, view: Direction, why: &str) -> Infeasibility {
    Infeasibility::OutOfLimits {
        detail: format!(
            "{why}: light θ={:.2}° φ={:.2}°, view θ={:.2}° φ={:.2}°",
            light.theta_deg(),
            light.phi_deg(),
            view.theta_deg(),
            view.phi_deg()
        ),
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

#[cfg(test)]
pub(crate) mod tests_support {
    use super::*;
    use std::collections::BTreeMap;

    /// The Bonn 81 directions (the gonio crate's `sweep::bonn81`, which this crate cannot
    /// depend on).
    pub fn bonn() -> Vec<Direction> {
        let mut v = vec![];
        for (t, n) in [(0.0, 1), (15.0, 6), (30.0, 12), (45.0, 18), (60.0, 20), (75.0, 24)] {
            for k in 0..n {
                v.push(Direction::from_degrees(t, k as f64 * 360.0 / n as f64));
            }
        }
        v
    }

    /// Every light × view pair of `dirs` through IK: every solution must lie inside the
    /// limits and reproduce the pair under FK (worst error returned); failures are counted
    /// by reason. With `prev` = the first solution, IK must offer that solution again.
    pub fn round_trip(rig: &RigSpec, dirs: &[Direction]) -> (BTreeMap<&'static str, usize>, f64, usize) {
        let k = for_rig(rig);
        let limits: Vec<SoftLimits> = rig.axes.iter().map(|a| a.limits()).collect();
        let mut fails = BTreeMap::new();
        let mut worst: f64 = 0.0;
        let mut ok = 0;
        for v in dirs {
            for l in dirs {
                match k.inverse(*l, *v, None) {
                    Ok(sols) => {
                        ok += 1;
                        assert!(!sols.is_empty());
                        for q in &sols {
                            for (i, lim) in limits.iter().enumerate() {
                                assert!(lim.contains(q[i]), "axis {i} = {} outside {lim:?}", q[i]);
                            }
                            let (lf, vf) = k.forward(q);
                            worst = worst.max(lf.angle_to(*l)).max(vf.angle_to(*v));
                        }
                        let again = k.inverse(*l, *v, Some(&sols[0])).unwrap();
                        let free = k.free_axes(*l, *v);
                        assert!(
                            again.iter().any(|q| q
                                .iter()
                                .zip(&sols[0])
                                .enumerate()
                                .all(|(i, (a, b))| free.contains(&i) || (a - b).abs() < 1e-12)),
                            "IK from a solution does not offer staying there"
                        );
                    }
                    Err(e) => {
                        let key = match e {
                            Infeasibility::OutOfLimits { .. } => "out_of_limits",
                            Infeasibility::LightBlockedByCamera { .. } => "light_blocked_by_camera",
                            Infeasibility::NotInDome { .. } => "not_in_dome",
                            Infeasibility::HolderShadow { .. } => "holder_shadow",
                        };
                        *fails.entry(key).or_default() += 1;
                    }
                }
            }
        }
        (fails, worst, ok)
    }

    /// A shipped rig file, parsed and validated.
    pub fn shipped(name: &str) -> RigSpec {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("rigs").join(name);
        RigSpec::load(&path).unwrap()
    }
}
