//! The motion model of one axis: trapezoidal (or S-curve) velocity profile plus settle time.
//!
//! Planning and the simulator use the same formulas, so a planned duration is exactly what
//! the simulated rig takes. Units are the axis' own (radians for rotary axes, millimetres
//! for linear ones) per second.

use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MotionModel {
    /// Maximum velocity (units/s), > 0.
    pub max_velocity: f64,
    /// Acceleration and deceleration (units/s²), > 0.
    pub acceleration: f64,
    /// Optional jerk limit (units/s³); `None` means a trapezoidal profile.
    pub jerk: Option<f64>,
    /// Time the axis needs to come to rest after the profile ends (s).
    pub settle_time: f64,
    /// Moves shorter than this are skipped (no motion, no settle).
    pub deadband: f64,
}

impl MotionModel {
    /// Duration of the velocity profile for a move of `distance` (sign ignored), without settle.
    ///
    /// Trapezoid: short moves never reach `max_velocity` (triangle, t = 2√(d/a)); long ones
    /// cruise (t = d/v + v/a). With a jerk limit each acceleration phase is an S-curve; the
    /// formula used is the standard conservative one: the trapezoid time plus a/j.
    pub fn profile_time(&self, distance: f64) -> f64 {
        let d = distance.abs();
        if d <= self.deadband {
            return 0.0;
        }
        let v = self.max_velocity;
        let a = self.acceleration;
        let base = if d < v * v / a {
            2.0 * (d / a).sqrt()
        } else {
            d / v + v / a
        };
        match self.jerk {
            Some(j) if j > 0.0 && j.is_finite() => base + a / j,
            _ => base,
        }
    }

    /// Duration of a full move including settling; zero for moves inside the deadband.
    pub fn move_time(&self, distance: f64) -> f64 {
        if distance.abs() <= self.deadband {
            0.0
        } else {
            self.profile_time(distance) + self.settle_time
        }
    }

    /// Position along a trapezoidal move of signed `distance` at time `t` since its start
    /// (the jerk limit is ignored here: it shifts timing by a/j but not the path).
    pub fn position_at(&self, distance: f64, t: f64) -> f64 {
        let d = distance.abs();
        let s = distance.signum();
        let total = self.profile_time(distance);
        if d <= self.deadband || t >= total {
            return distance;
        }
        if t <= 0.0 {
            return 0.0;
        }
        let a = self.acceleration;
        let v = self.max_velocity;
        let (t_acc, v_peak) = if d < v * v / a {
            ((d / a).sqrt(), (d * a).sqrt())
        } else {
            (v / a, v)
        };
        let t_cruise = (total - 2.0 * t_acc).max(0.0);
        let p = if t < t_acc {
            0.5 * a * t * t
        } else if t < t_acc + t_cruise {
            0.5 * a * t_acc * t_acc + v_peak * (t - t_acc)
        } else {
            let tr = total - t;
            d - 0.5 * a * tr * tr
        };
        s * p.clamp(0.0, d)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn m() -> MotionModel {
        MotionModel {
            max_velocity: 2.0,
            acceleration: 4.0,
            jerk: None,
            settle_time: 0.1,
            deadband: 1e-6,
        }
    }

    #[test]
    fn triangle_and_trapezoid() {
        // v²/a = 1: d = 0.25 is a triangle, t = 2 sqrt(0.25/4) = 0.5
        assert!((m().profile_time(0.25) - 0.5).abs() < 1e-12);
        // d = 3: t = 3/2 + 2/4 = 2
        assert!((m().profile_time(-3.0) - 2.0).abs() < 1e-12);
        assert_eq!(m().move_time(1e-9), 0.0);
        // continuity at the switch point d = v²/a
        let a = m().profile_time(1.0 - 1e-12);
        let b = m().profile_time(1.0 + 1e-12);
        assert!((a - b).abs() < 1e-9);
    }

    #[test]
    fn position_profile_ends_at_target() {
        for &d in &[0.25, 3.0, -3.0] {
            let t = m().profile_time(d);
            assert!((m().position_at(d, t) - d).abs() < 1e-12);
            assert_eq!(m().position_at(d, 0.0), 0.0);
            let mid = m().position_at(d, t / 2.0);
            assert!((mid - d / 2.0).abs() < 1e-9, "symmetric profile: {mid} vs {}", d / 2.0);
        }
    }
}
