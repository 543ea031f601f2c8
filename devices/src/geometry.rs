//! Small 3-vector math and the direction convention of `shared/docs/conventions.md`.
//!
//! A [`Direction`] points away from the sample, θ from +z, φ from +x toward +y.
//! Degrees at interfaces, radians inside: constructors say which they take.

use serde::{Deserialize, Serialize};
use std::ops::{Add, Mul, Neg, Sub};

/// A 3-vector of `f64` (millimetres for points, unitless for directions).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vec3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl Vec3 {
    pub const ZERO: Vec3 = Vec3 { x: 0.0, y: 0.0, z: 0.0 };
    pub const Z: Vec3 = Vec3 { x: 0.0, y: 0.0, z: 1.0 };

    pub const fn new(x: f64, y: f64, z: f64) -> Self {
        Vec3 { x, y, z }
    }
    pub fn dot(self, o: Vec3) -> f64 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }
    pub fn cross(self, o: Vec3) -> Vec3 {
        Vec3::new(
            self.y * o.z - self.z * o.y,
            self.z * o.x - self.x * o.z,
            self.x * o.y - self.y * o.x,
        )
    }
    pub fn norm(self) -> f64 {
        self.dot(self).sqrt()
    }
    /// Unit vector; the zero vector stays zero (callers that can meet it check first).
    pub fn normalized(self) -> Vec3 {
        let n = self.norm();
        if n > 0.0 {
            self * (1.0 / n)
        } else {
            self
        }
    }
    /// Rotation about +z by `a` radians (right-handed).
    pub fn rotate_z(self, a: f64) -> Vec3 {
        let (s, c) = a.sin_cos();
        Vec3::new(c * self.x - s * self.y, s * self.x + c * self.y, self.z)
    }
}

impl Add for Vec3 {
    type Output = Vec3;
    fn add(self, o: Vec3) -> Vec3 {
        Vec3::new(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}
impl Sub for Vec3 {
    type Output = Vec3;
    fn sub(self, o: Vec3) -> Vec3 {
        Vec3::new(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}
impl Mul<f64> for Vec3 {
    type Output = Vec3;
    fn mul(self, s: f64) -> Vec3 {
        Vec3::new(self.x * s, self.y * s, self.z * s)
    }
}
impl Neg for Vec3 {
    type Output = Vec3;
    fn neg(self) -> Vec3 {
        Vec3::new(-self.x, -self.y, -self.z)
    }
}

/// A direction on the upper hemisphere, stored in radians.
///
/// `theta` ∈ [0, π/2), `phi` ∈ [0, 2π); at θ = 0 the azimuth is 0 by definition.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Direction {
    pub theta: f64,
    pub phi: f64,
}

/// Angles closer than this to zero are treated as "at the pole" (azimuth undefined).
pub const POLE_EPS: f64 = 1e-12;

impl Direction {
    /// From degrees, normalizing φ into [0°, 360°) and φ = 0 at the pole.
    pub fn from_degrees(theta_deg: f64, phi_deg: f64) -> Self {
        Self::from_radians(theta_deg.to_radians(), phi_deg.to_radians())
    }
    pub fn from_radians(theta: f64, phi: f64) -> Self {
        let phi = if theta.abs() < POLE_EPS { 0.0 } else { wrap_2pi(phi) };
        Direction { theta, phi }
    }
    /// From a (not necessarily unit) vector with z ≥ 0.
    pub fn from_vector(v: Vec3) -> Self {
        let v = v.normalized();
        let r = (v.x * v.x + v.y * v.y).sqrt();
        let theta = r.atan2(v.z);
        let phi = if r < POLE_EPS { 0.0 } else { v.y.atan2(v.x) };
        Self::from_radians(theta, phi)
    }
    pub fn vector(self) -> Vec3 {
        let (st, ct) = self.theta.sin_cos();
        let (sp, cp) = self.phi.sin_cos();
        Vec3::new(st * cp, st * sp, ct)
    }
    pub fn theta_deg(self) -> f64 {
        self.theta.to_degrees()
    }
    pub fn phi_deg(self) -> f64 {
        self.phi.to_degrees()
    }
    /// Great-circle angle to another direction, in radians (stable for tiny angles).
    pub fn angle_to(self, o: Direction) -> f64 {
        angle_between(self.vector(), o.vector())
    }
}

/// Angle between two vectors, accurate for nearly parallel ones (atan2 of |a×b| and a·b).
pub fn angle_between(a: Vec3, b: Vec3) -> f64 {
    a.cross(b).norm().atan2(a.dot(b))
}

/// Wrap an angle into [0, 2π).
pub fn wrap_2pi(a: f64) -> f64 {
    let t = std::f64::consts::TAU;
    let r = a.rem_euclid(t);
    if r >= t {
        0.0
    } else {
        r
    }
}

/// Wrap an angle into (−π, π].
pub fn wrap_pi(a: f64) -> f64 {
    let pi = std::f64::consts::PI;
    let r = wrap_2pi(a + pi) - pi;
    if r <= -pi {
        r + std::f64::consts::TAU
    } else {
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn direction_round_trip_and_pole() {
        let d = Direction::from_degrees(45.0, 340.0);
        let back = Direction::from_vector(d.vector());
        assert!((back.theta - d.theta).abs() < 1e-12);
        assert!((back.phi - d.phi).abs() < 1e-12);
        let pole = Direction::from_degrees(0.0, 123.0);
        assert_eq!(pole.phi, 0.0);
        assert_eq!(Direction::from_vector(Vec3::Z).phi, 0.0);
    }

    #[test]
    fn wraps() {
        assert!((wrap_pi(3.0 * std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-12);
        assert!(wrap_2pi(-1e-18) < std::f64::consts::TAU);
        assert!((angle_between(Vec3::new(1.0, 0.0, 0.0), Vec3::new(1.0, 1e-9, 0.0)) - 1e-9).abs() < 1e-20);
    }
}
