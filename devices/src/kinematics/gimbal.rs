//! The gimbal rig (Winkler & Zagar 2015 style): the camera is fixed at the world zenith
//! looking down, the lamp rides a circular arc in the world x-z plane, and the sample sits
//! on a 3-axis gimbal of rotary stages.
//!
//! World vectors: camera `ẑ`, lamp `l_w(λ) = (sin λ, 0, cos λ)` (λ = `light_arc`,
//! negative = the −x side). The gimbal maps sample-frame vectors to the world by
//! `R = Rz(β) · Rx(τ) · Rz(α)`: `sample_base` β turns the whole cradle about the vertical,
//! `sample_tilt` τ tilts it about the (turned) x axis, `sample_azimuth` α spins the sample
//! about its own normal. A direction `d` in the sample frame is `Rᵀ d_w`.
//!
//! Closed-form inverse (no iteration, so FK∘IK is exact to rounding): the view is
//! `Rᵀ ẑ`, so τ = ±θ_v and α = ±π/2 − φ_v; the lamp's angle to the camera equals the
//! pair's light–view angle γ, so λ = ±γ; β then turns the lamp's azimuth into place.
//!
//! **Gimbal lock.** At τ = 0 (the sample normal points at the camera, θ_v = 0) base and
//! azimuth turn about the same axis and only β + α matters: IK keeps α where it was
//! (`prev`) and solves β, or without a previous configuration offers α every 30° so the
//! planner can choose.

use super::rot::Mat3;
use super::{fit, light_clearance, out_of_limits, wraps, CameraPose, Infeasibility, Kinematics};
use crate::geometry::{angle_between, Direction, Vec3, POLE_EPS};
use crate::rig::RigSpec;
use crate::SoftLimits;
use std::f64::consts::{FRAC_PI_2, PI};

/// Axis roles this kind needs.
pub const ROLES: [&str; 4] = ["light_arc", "sample_base", "sample_tilt", "sample_azimuth"];

/// Azimuth sampling step (rad) offered at gimbal lock without a previous configuration.
const LOCK_SAMPLE: f64 = PI / 6.0;

pub struct Gimbal {
    n: usize,
    i_arc: usize,
    i_base: usize,
    i_tilt: usize,
    i_azi: usize,
    limits: Vec<SoftLimits>,
    camera_distance: f64,
    light_distance: f64,
    block_radius: f64,
}

impl Gimbal {
    pub fn new(rig: &RigSpec) -> Self {
        let idx = |role: &str| {
            rig.axis_by_role(role)
                .map(|(i, _)| i)
                .expect("rig validated: role present")
        };
        Gimbal {
            n: rig.axes.len(),
            i_arc: idx("light_arc"),
            i_base: idx("sample_base"),
            i_tilt: idx("sample_tilt"),
            i_azi: idx("sample_azimuth"),
            limits: rig.axes.iter().map(|a| a.limits()).collect(),
            camera_distance: rig.geometry.camera_distance_mm,
            light_distance: rig.geometry.light_distance_mm,
            block_radius: rig.geometry.camera_body_radius_mm + rig.geometry.clearance_mm,
        }
    }

    /// Sample → world rotation of a configuration.
    fn rotation(&self, q: &[f64]) -> Mat3 {
        Mat3::rz(q[self.i_base])
            .mul(&Mat3::rx(q[self.i_tilt]))
            .mul(&Mat3::rz(q[self.i_azi]))
    }

    fn lamp_world(lambda: f64) -> Vec3 {
        Vec3::new(lambda.sin(), 0.0, lambda.cos())
    }

    /// (tilt, azimuth) options that put the view on the camera.
    fn view_options(&self, view: Direction, prev: Option<&[f64]>) -> Vec<(f64, f64)> {
        let lt = self.limits[self.i_tilt];
        let la = self.limits[self.i_azi];
        let mut out = Vec::new();
        if view.theta < POLE_EPS {
            // gimbal lock: τ = 0, α arbitrary (β absorbs it)
            if fit(lt, 0.0).is_none() {
                return out;
            }
            match prev {
                Some(p) => out.push((0.0, p[self.i_azi])),
                None => {
                    let mut a = (la.min / LOCK_SAMPLE).ceil() * LOCK_SAMPLE;
                    while a <= la.max + 1e-12 {
                        out.push((0.0, a.min(la.max)));
                        a += LOCK_SAMPLE;
                    }
                }
            }
            return out;
        }
        for (t, a) in [(view.theta, FRAC_PI_2 - view.phi), (-view.theta, -FRAC_PI_2 - view.phi)] {
            if let Some(t) = fit(lt, t) {
                for a in wraps(la, a) {
                    out.push((t, a));
                }
            }
        }
        out
    }
}

impl Kinematics for Gimbal {
    fn axis_count(&self) -> usize {
        self.n
    }

    fn forward(&self, q: &[f64]) -> (Direction, Direction) {
        let r = self.rotation(q);
        (
            Direction::from_vector(r.apply_t(Self::lamp_world(q[self.i_arc]))),
            Direction::from_vector(r.apply_t(Vec3::Z)),
        )
    }

    fn camera_pose(&self, q: &[f64]) -> CameraPose {
        let r = self.rotation(q);
        let forward = r.apply_t(-Vec3::Z);
        // the fixed camera's image x is world +y
        let right = r.apply_t(Vec3::new(0.0, 1.0, 0.0));
        CameraPose {
            position: r.apply_t(Vec3::Z) * self.camera_distance,
            right,
            down: forward.cross(right),
            forward,
        }
    }

    fn light_position(&self, q: &[f64]) -> Vec3 {
        self.rotation(q).apply_t(Self::lamp_world(q[self.i_arc])) * self.light_distance
    }

    fn inverse(&self, light: Direction, view: Direction, prev: Option<&[f64]>) -> Result<Vec<Vec<f64>>, Infeasibility> {
        let (l, v) = (light.vector(), view.vector());
        let clearance = light_clearance(l * self.light_distance, v * self.camera_distance, self.block_radius);
        if clearance <= 0.0 {
            return Err(Infeasibility::LightBlockedByCamera {
                clearance_mm: clearance,
            });
        }
        let gamma = angle_between(l, v);
        let lb = self.limits[self.i_base];
        let larc = self.limits[self.i_arc];
        let mut out = Vec::new();
        for (t, a) in self.view_options(view, prev) {
            // the lamp in the frame after tilt and azimuth: u = Rz(−β) l_w(λ)
            let u = Mat3::rx(t).mul(&Mat3::rz(a)).apply(l);
            for lambda in [gamma, -gamma] {
                let Some(lambda) = fit(larc, lambda) else { continue };
                let bases = if gamma.sin() < POLE_EPS {
                    // lamp on the camera axis: β does not matter
                    vec![prev.map(|p| p[self.i_base]).unwrap_or(0.0)]
                } else {
                    let s = lambda.signum();
                    wraps(lb, (-u.y * s).atan2(u.x * s))
                };
                for b in bases {
                    let mut q = vec![0.0; self.n];
                    q[self.i_arc] = lambda;
                    q[self.i_base] = b;
                    q[self.i_tilt] = t;
                    q[self.i_azi] = a;
                    out.push(q);
                }
            }
        }
        if out.is_empty() {
            return Err(out_of_limits(light, view, "no gimbal configuration within the limits"));
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::for_rig;
    use crate::kinematics::tests_support::{bonn, round_trip, shipped};

    fn rig() -> RigSpec {
        shipped("gimbal.toml")
    }

    #[test]
    fn fk_ik_round_trip_on_all_bonn_pairs() {
        let (fails, worst, ok) = round_trip(&rig(), &bonn());
        assert!(worst < 1e-9, "worst round-trip error {worst} rad");
        // the lamp arc rides outside the fixed camera: exactly the retro pairs are blocked
        assert_eq!(fails.get("light_blocked_by_camera"), Some(&81), "{fails:?}");
        assert_eq!(fails.len(), 1, "{fails:?}");
        assert_eq!(ok, 6480);
    }

    #[test]
    fn gimbal_lock_keeps_azimuth_and_solves_the_base() {
        let k = for_rig(&rig());
        let light = Direction::from_degrees(45.0, 130.0);
        let view = Direction::from_degrees(0.0, 0.0);
        let prev = vec![0.4, 1.0, 0.2, -2.5];
        let sols = k.inverse(light, view, Some(&prev)).unwrap();
        assert!(sols.iter().all(|q| q[3] == -2.5 && q[2] == 0.0), "{sols:?}");
        for q in &sols {
            let (l, v) = k.forward(q);
            assert!(l.angle_to(light) < 1e-9 && v.angle_to(view) < 1e-9);
        }
        // without a previous configuration: sampled azimuths, all valid
        let sols = k.inverse(light, view, None).unwrap();
        assert!(sols.len() >= 12, "{}", sols.len());
        let mut azis: Vec<f64> = sols.iter().map(|q| q[3]).collect();
        azis.dedup();
        assert!(azis.len() >= 12);
        // just off the lock the closed form still holds
        let near = Direction::from_radians(1e-7, 0.3);
        let sols = k.inverse(light, near, None).unwrap();
        for q in &sols {
            let (l, v) = k.forward(q);
            assert!(l.angle_to(light) < 1e-9 && v.angle_to(near) < 1e-9);
        }
    }

    #[test]
    fn wrap_around_offers_both_turns_and_limits_cut_them() {
        let k = for_rig(&rig());
        // φv = 280° → α = 90° − 280° = −190° (also 170°) for τ > 0: both inside ±200°
        let sols = k
            .inverse(
                Direction::from_degrees(30.0, 0.0),
                Direction::from_degrees(45.0, 280.0),
                None,
            )
            .unwrap();
        let azis: Vec<f64> = sols.iter().filter(|q| q[2] > 0.0).map(|q| q[3].to_degrees()).collect();
        assert!(azis.iter().any(|a| (a + 190.0).abs() < 1e-9), "{azis:?}");
        assert!(azis.iter().any(|a| (a - 170.0).abs() < 1e-9), "{azis:?}");
    }

    #[test]
    fn target_exactly_at_a_limit_is_reached() {
        let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/rigs/gimbal.toml"))
            .unwrap()
            .replace("min_deg = -80.0\nmax_deg = 80.0", "min_deg = -75.0\nmax_deg = 75.0");
        let rig = RigSpec::parse(&text, "edge.toml").unwrap();
        assert_eq!(rig.axis_by_role("sample_tilt").unwrap().1.max_deg, 75.0);
        let k = for_rig(&rig);
        let view = Direction::from_degrees(75.0, 33.0);
        let sols = k.inverse(Direction::from_degrees(30.0, 200.0), view, None).unwrap();
        assert!(sols.iter().any(|q| q[2] == 75f64.to_radians()));
        // and one hair beyond is refused with a reason
        let e = k
            .inverse(
                Direction::from_degrees(30.0, 200.0),
                Direction::from_degrees(75.001, 33.0),
                None,
            )
            .unwrap_err();
        assert!(matches!(e, Infeasibility::OutOfLimits { .. }), "{e}");
    }

    #[test]
    fn lamp_next_to_camera_is_blocked_by_geometry() {
        let k = Gimbal::new(&rig());
        // 3° apart: the lamp at 1200 mm passes 1000·sin 3° ≈ 52 mm from the camera centre,
        // inside body radius + clearance (65 mm); 10° apart passes ≈ 174 mm away.
        let e = k
            .inverse(
                Direction::from_degrees(33.0, 0.0),
                Direction::from_degrees(30.0, 0.0),
                None,
            )
            .unwrap_err();
        assert!(matches!(e, Infeasibility::LightBlockedByCamera { .. }), "{e}");
        assert!(k
            .inverse(
                Direction::from_degrees(40.0, 0.0),
                Direction::from_degrees(30.0, 0.0),
                None
            )
            .is_ok());
        // the simulated lamp really sits outside the camera body in that configuration
        let q = &k
            .inverse(
                Direction::from_degrees(40.0, 0.0),
                Direction::from_degrees(30.0, 0.0),
                None,
            )
            .unwrap()[0];
        let pose = k.camera_pose(q);
        assert!((k.light_position(q) - pose.position).norm() > 65.0);
    }

    #[test]
    fn camera_pose_looks_at_the_sample_centre() {
        let k = Gimbal::new(&rig());
        let q = vec![0.7, -1.1, 0.5, 2.0];
        let pose = k.camera_pose(&q);
        let c = pose.to_camera(Vec3::ZERO);
        assert!(c.x.abs() < 1e-9 && c.y.abs() < 1e-9 && (c.z - 1000.0).abs() < 1e-9);
        assert!(pose.right.dot(pose.forward).abs() < 1e-12 && (pose.down.norm() - 1.0).abs() < 1e-12);
        let (l, v) = k.forward(&q);
        assert!(angle_between(pose.position, v.vector()) < 1e-12);
        assert!(angle_between(k.light_position(&q), l.vector()) < 1e-12);
    }
}
