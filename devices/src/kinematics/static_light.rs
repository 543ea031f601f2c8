//! The static-light rig (RGL pgII principle): the lamp never moves, so its spectrum and
//! power never drift with cable bends or lamp orientation; the camera rides a 2-axis arc
//! and the sample sits on a tilt stage carrying a rotation stage.
//!
//! World vectors: lamp `l_w = (sin λ₀, 0, cos λ₀)` with λ₀ =
//! `geometry.fixed_light_elevation_deg`; camera `(sin ε cos β, sin ε sin β, cos ε)` with β =
//! `camera_azimuth` (the arc's rotation about the vertical) and ε = `camera_elevation`
//! (negative = far side of the pole, |ε| may exceed 90° when the sample is tilted). The
//! sample maps to the world by `R = Ry(τ) · Rz(α)` (τ = `sample_tilt` about world y, α =
//! `sample_rotation` about the sample normal).
//!
//! Closed-form inverse: `Rz(α) l = Ry(−τ) l_w = (sin(λ₀−τ), 0, cos(λ₀−τ))`, so
//! τ = λ₀ ∓ θ_l with α = −φ_l or π − φ_l; the camera then goes where `R v` points.
//!
//! **Singular configurations.** θ_l = 0: the lamp is on the sample normal, α does not move
//! the light and only sets where the view lands; IK keeps α (`prev`) or, without one,
//! offers it every 30°. Camera at the world pole (ε = 0): β is free.
//!
//! **The 1-axis arc variant** (kind `static-light-arc`, roles `camera_elevation`,
//! `sample_tilt`, `sample_rotation`): the camera arc does not turn (β ≡ 0), it lies in the
//! plane of the lamp and the zenith, which also holds the tilted sample normal. Three axes
//! cannot reach a 4-parameter pair set: this rig measures exactly the pairs whose light,
//! view and sample normal are coplanar (φ_v − φ_l = 0° or 180°, or a direction at the
//! pole) — for every light azimuth, because the rotation stage turns the sample. Other
//! pairs get [`Infeasibility::OutOfLimits`] saying so. With the lamp on the normal
//! (θ_l = 0) the rotation is what brings the view into the arc's plane (α = −φ_v or
//! 180° − φ_v).

use super::rot::Mat3;
use super::{fit, light_clearance, out_of_limits, wraps, CameraPose, Infeasibility, Kinematics};
use crate::geometry::{Direction, Vec3, POLE_EPS};
use crate::rig::RigSpec;
use crate::SoftLimits;
use std::f64::consts::PI;

/// Axis roles this kind needs.
pub const ROLES: [&str; 4] = ["camera_azimuth", "camera_elevation", "sample_tilt", "sample_rotation"];

/// Axis roles of the 1-axis camera arc variant (`static-light-arc`).
pub const ROLES_ONE_ARC: [&str; 3] = ["camera_elevation", "sample_tilt", "sample_rotation"];

/// How far (unit-vector component) a view may miss the fixed arc's plane and still count as
/// in it: far below the 1e-9 rad the round trip guarantees.
const PLANE_EPS: f64 = 1e-11;

/// Rotation sampling step (rad) offered when the lamp is on the sample normal.
const POLE_SAMPLE: f64 = PI / 6.0;

pub struct StaticLight {
    n: usize,
    /// `None` on the 1-axis arc variant (the arc never turns: β ≡ 0).
    i_caz: Option<usize>,
    i_cel: usize,
    i_tilt: usize,
    i_rot: usize,
    limits: Vec<SoftLimits>,
    lamp: Vec3,
    camera_distance: f64,
    light_distance: f64,
    block_radius: f64,
}

impl StaticLight {
    pub fn new(rig: &RigSpec) -> Self {
        let idx = |role: &str| {
            rig.axis_by_role(role)
                .map(|(i, _)| i)
                .expect("rig validated: role present")
        };
        let l0 = rig.geometry.fixed_light_elevation_deg.to_radians();
        StaticLight {
            n: rig.axes.len(),
            i_caz: rig.axis_by_role("camera_azimuth").map(|(i, _)| i),
            i_cel: idx("camera_elevation"),
            i_tilt: idx("sample_tilt"),
            i_rot: idx("sample_rotation"),
            limits: rig.axes.iter().map(|a| a.limits()).collect(),
            lamp: Vec3::new(l0.sin(), 0.0, l0.cos()),
            camera_distance: rig.geometry.camera_distance_mm,
            light_distance: rig.geometry.light_distance_mm,
            block_radius: rig.geometry.camera_body_radius_mm + rig.geometry.clearance_mm,
        }
    }

    fn lambda0(&self) -> f64 {
        self.lamp.x.atan2(self.lamp.z)
    }

    /// The arc's rotation β (0 on the 1-axis variant).
    fn beta(&self, q: &[f64]) -> f64 {
        self.i_caz.map_or(0.0, |i| q[i])
    }

    fn rotation(&self, q: &[f64]) -> Mat3 {
        Mat3::ry(q[self.i_tilt]).mul(&Mat3::rz(q[self.i_rot]))
    }

    fn camera_world(q_el: f64, q_az: f64) -> Vec3 {
        Vec3::new(q_el.sin() * q_az.cos(), q_el.sin() * q_az.sin(), q_el.cos())
    }

    /// (tilt, rotation) options that bring the light onto the fixed lamp.
    fn sample_options(&self, light: Direction, view: Direction, prev: Option<&[f64]>) -> Vec<(f64, f64)> {
        let lt = self.limits[self.i_tilt];
        let lr = self.limits[self.i_rot];
        let l0 = self.lambda0();
        let mut out = Vec::new();
        if light.theta < POLE_EPS {
            let Some(t) = fit(lt, l0) else { return out };
            if self.i_caz.is_none() && view.theta >= POLE_EPS {
                // the fixed arc: the rotation must bring the view into the arc's plane
                for a in [-view.phi, PI - view.phi] {
                    for a in wraps(lr, a) {
                        out.push((t, a));
                    }
                }
                return out;
            }
            match prev {
                Some(p) => out.push((t, p[self.i_rot])),
                None => {
                    let mut a = (lr.min / POLE_SAMPLE).ceil() * POLE_SAMPLE;
                    while a <= lr.max + 1e-12 {
                        out.push((t, a.min(lr.max)));
                        a += POLE_SAMPLE;
                    }
                }
            }
            return out;
        }
        for (t, a) in [(l0 - light.theta, -light.phi), (l0 + light.theta, PI - light.phi)] {
            if let Some(t) = fit(lt, t) {
                for a in wraps(lr, a) {
                    out.push((t, a));
                }
            }
        }
        out
    }
}

impl Kinematics for StaticLight {
    fn axis_count(&self) -> usize {
        self.n
    }

    fn forward(&self, q: &[f64]) -> (Direction, Direction) {
        let r = self.rotation(q);
        let c = Self::camera_world(q[self.i_cel], self.beta(q));
        (
            Direction::from_vector(r.apply_t(self.lamp)),
            Direction::from_vector(r.apply_t(c)),
        )
    }

    fn camera_pose(&self, q: &[f64]) -> CameraPose {
        let r = self.rotation(q);
        let c = Self::camera_world(q[self.i_cel], self.beta(q));
        let forward = r.apply_t(-c);
        // image x along the arc's rotation axis, as on the two-arm rig's camera arc
        let right = r.apply_t(Vec3::new(0.0, 1.0, 0.0).rotate_z(self.beta(q)));
        CameraPose {
            position: r.apply_t(c) * self.camera_distance,
            right,
            down: forward.cross(right),
            forward,
        }
    }

    fn light_position(&self, q: &[f64]) -> Vec3 {
        self.rotation(q).apply_t(self.lamp) * self.light_distance
    }

    fn free_axes(&self, light: Direction, view: Direction) -> Vec<usize> {
        // β is free when every way of holding the sample puts the camera at the pole.
        let Some(i_caz) = self.i_caz else {
            return Vec::new();
        };
        let opts = self.sample_options(light, view, None);
        let at_pole = |&(t, a): &(f64, f64)| {
            let c = Mat3::ry(t).mul(&Mat3::rz(a)).apply(view.vector());
            c.x.hypot(c.y) < POLE_EPS && c.z > 0.0
        };
        if !opts.is_empty() && opts.iter().all(at_pole) {
            vec![i_caz]
        } else {
            Vec::new()
        }
    }

    fn inverse(&self, light: Direction, view: Direction, prev: Option<&[f64]>) -> Result<Vec<Vec<f64>>, Infeasibility> {
        let (l, v) = (light.vector(), view.vector());
        let clearance = light_clearance(l * self.light_distance, v * self.camera_distance, self.block_radius);
        if clearance <= 0.0 {
            return Err(Infeasibility::LightBlockedByCamera {
                clearance_mm: clearance,
            });
        }
        let le = self.limits[self.i_cel];
        let mut out = Vec::new();
        let mut off_plane = false;
        for (t, a) in self.sample_options(light, view, prev) {
            let c = Mat3::ry(t).mul(&Mat3::rz(a)).apply(v);
            let r = c.x.hypot(c.y);
            let cams: Vec<(f64, f64)> = if let (None, false) = (self.i_caz, r < POLE_EPS && c.z > 0.0) {
                // fixed arc in the world x-z plane: the camera is at (sin ε, 0, cos ε)
                if c.y.abs() > PLANE_EPS {
                    off_plane = true;
                    Vec::new()
                } else {
                    fit(le, c.x.atan2(c.z)).map(|e| vec![(e, 0.0)]).unwrap_or_default()
                }
            } else if r < POLE_EPS && c.z > 0.0 {
                let b = match (prev, self.i_caz) {
                    (Some(p), Some(i)) => p[i],
                    _ => 0.0,
                };
                fit(le, 0.0).map(|e| vec![(e, b)]).unwrap_or_default()
            } else {
                let la = self.limits[self.i_caz.expect("2-axis arc")];
                let (e, b) = (r.atan2(c.z), c.y.atan2(c.x));
                [(e, b), (-e, b + PI)]
                    .into_iter()
                    .filter_map(|(e, b)| fit(le, e).map(|e| (e, b)))
                    .flat_map(|(e, b)| wraps(la, b).into_iter().map(move |b| (e, b)))
                    .collect()
            };
            for (e, b) in cams {
                let mut q = vec![0.0; self.n];
                if let Some(i) = self.i_caz {
                    q[i] = b;
                }
                q[self.i_cel] = e;
                q[self.i_tilt] = t;
                q[self.i_rot] = a;
                out.push(q);
            }
        }
        if out.is_empty() && off_plane {
            return Err(out_of_limits(
                light,
                view,
                "a 1-axis camera arc reaches only pairs whose light, view and sample normal are coplanar (φ_v − φ_l = 0° or 180°)",
            ));
        }
        if out.is_empty() {
            return Err(out_of_limits(
                light,
                view,
                "no static-light configuration within the limits",
            ));
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::angle_between;
    use crate::kinematics::for_rig;
    use crate::kinematics::tests_support::{bonn, round_trip, shipped};

    fn text() -> String {
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/rigs/static-light.toml")).unwrap()
    }

    #[test]
    fn fk_ik_round_trip_on_all_bonn_pairs() {
        let (fails, worst, ok) = round_trip(&shipped("static-light.toml"), &bonn());
        assert!(worst < 1e-9, "worst round-trip error {worst} rad");
        assert_eq!(fails.get("light_blocked_by_camera"), Some(&81), "{fails:?}");
        assert_eq!(fails.len(), 1, "{fails:?}");
        assert_eq!(ok, 6480);
    }

    /// An oblique fixed lamp exercises the general case (τ ≠ ±θ_l) and the camera arc
    /// beyond 90°; narrow tilt limits then make some pairs genuinely unreachable.
    #[test]
    fn oblique_lamp_round_trip_and_unreachable_pairs_have_a_reason() {
        let t = text().replace("fixed_light_elevation_deg = 0.0", "fixed_light_elevation_deg = 40.0");
        let rig = RigSpec::parse(&t, "oblique.toml").unwrap();
        let (fails, worst, ok) = round_trip(&rig, &bonn());
        assert!(worst < 1e-9, "worst round-trip error {worst} rad");
        assert_eq!(fails.get("light_blocked_by_camera"), Some(&81), "{fails:?}");
        // τ = 40° ∓ θ_l stays within ±80° for every Bonn θ_l ≤ 75°
        assert_eq!(ok, 6480, "{fails:?}");
        let t = t.replace("min_deg = -80.0\nmax_deg = 80.0", "min_deg = -20.0\nmax_deg = 20.0");
        let rig = RigSpec::parse(&t, "narrow.toml").unwrap();
        let (fails, worst, ok) = round_trip(&rig, &bonn());
        assert!(worst < 1e-9);
        let out = fails.get("out_of_limits").copied().unwrap_or(0);
        assert!(out > 0 && ok + out + 81 == 6561, "{fails:?} ok {ok}");
    }

    #[test]
    fn lamp_on_the_normal_keeps_rotation() {
        let k = for_rig(&shipped("static-light.toml"));
        let light = Direction::from_degrees(0.0, 0.0);
        let view = Direction::from_degrees(60.0, 100.0);
        let prev = vec![0.3, 0.5, 0.1, 1.7];
        let sols = k.inverse(light, view, Some(&prev)).unwrap();
        assert!(sols.iter().all(|q| q[3] == 1.7 && q[2] == 0.0), "{sols:?}");
        for q in &sols {
            let (l, v) = k.forward(q);
            assert!(l.angle_to(light) < 1e-9 && v.angle_to(view) < 1e-9);
        }
        assert!(k.inverse(light, view, None).unwrap().len() >= 12);
    }

    #[test]
    fn camera_at_world_pole_frees_its_azimuth() {
        // lamp at 40°: the pair (light 40° φ 180°, view 0°) holds the sample flat with the
        // camera overhead (the other tilt, 80°, puts the camera at 80° from the pole).
        let t = text()
            .replace("fixed_light_elevation_deg = 0.0", "fixed_light_elevation_deg = 40.0")
            .replace("min_deg = -80.0\nmax_deg = 80.0", "min_deg = -60.0\nmax_deg = 60.0");
        let rig = RigSpec::parse(&t, "pole.toml").unwrap();
        let k = for_rig(&rig);
        let light = Direction::from_degrees(40.0, 180.0);
        let view = Direction::from_degrees(0.0, 0.0);
        assert_eq!(k.free_axes(light, view), vec![0]);
        let sols = k.inverse(light, view, Some(&[0.9, 0.0, 0.0, 0.0])).unwrap();
        assert!(sols.iter().any(|q| q[0] == 0.9 && q[1] == 0.0), "{sols:?}");
        for q in &sols {
            let (l, v) = k.forward(q);
            assert!(l.angle_to(light) < 1e-9 && v.angle_to(view) < 1e-9);
        }
    }

    #[test]
    fn light_is_blocked_by_camera_near_retro() {
        let k = for_rig(&shipped("static-light.toml"));
        let e = k
            .inverse(
                Direction::from_degrees(32.0, 0.0),
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
    }

    #[test]
    fn lamp_never_moves_and_pose_is_consistent() {
        let k = StaticLight::new(&shipped("static-light.toml"));
        for q in [vec![0.2, 1.9, -0.7, 3.0], vec![-2.0, -0.4, 0.9, -1.0]] {
            let r = k.rotation(&q);
            // the lamp in the world is the same whatever the axes do
            let world = r.apply(k.light_position(&q));
            assert!((world - Vec3::new(0.0, 0.0, 1500.0)).norm() < 1e-9, "{world:?}");
            let pose = k.camera_pose(&q);
            let c = pose.to_camera(Vec3::ZERO);
            assert!(c.x.abs() < 1e-9 && c.y.abs() < 1e-9 && (c.z - 1000.0).abs() < 1e-9);
            let (_, v) = k.forward(&q);
            assert!(angle_between(pose.position, v.vector()) < 1e-12);
        }
    }

    /// The 1-axis arc variant reaches exactly the coplanar pairs (all of them, except the
    /// retro pairs its camera blocks), and names the reason for the others.
    #[test]
    fn one_axis_arc_reaches_exactly_the_coplanar_pairs() {
        let rig = shipped("static-light-arc.toml");
        let k = for_rig(&rig);
        assert_eq!(k.axis_count(), 3);
        let (fails, worst, ok) = round_trip(&rig, &bonn());
        assert!(worst < 1e-9, "worst round-trip error {worst} rad");
        let coplanar = |l: &Direction, v: &Direction| {
            let d = (l.phi_deg() - v.phi_deg()).rem_euclid(180.0);
            l.theta < POLE_EPS || v.theta < POLE_EPS || d < 1e-9 || 180.0 - d < 1e-9
        };
        let dirs = bonn();
        let mut expected_ok = 0;
        for v in &dirs {
            for l in &dirs {
                let r = k.inverse(*l, *v, None);
                match (coplanar(l, v), l.angle_to(*v) < 1e-12, r) {
                    (_, true, Err(Infeasibility::LightBlockedByCamera { .. })) => {}
                    (true, false, Ok(sols)) => {
                        expected_ok += 1;
                        assert!(sols.iter().all(|q| q.len() == 3));
                    }
                    (false, false, Err(Infeasibility::OutOfLimits { detail })) => {
                        assert!(detail.contains("coplanar"), "{detail}")
                    }
                    (c, retro, r) => panic!("light {l:?} view {v:?} coplanar {c} retro {retro}: {r:?}"),
                }
            }
        }
        assert_eq!(ok, expected_ok);
        assert_eq!(fails["light_blocked_by_camera"], 81);
        // lamp on the normal: the rotation stage brings the view into the arc's plane
        let sols = k
            .inverse(
                Direction::from_degrees(0.0, 0.0),
                Direction::from_degrees(45.0, 70.0),
                None,
            )
            .unwrap();
        assert!(sols.len() >= 2, "{sols:?}");
        assert!(k
            .free_axes(Direction::from_degrees(30.0, 0.0), Direction::from_degrees(0.0, 0.0))
            .is_empty());
    }

    #[test]
    fn one_axis_arc_with_an_oblique_lamp_round_trips() {
        let t = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/rigs/static-light-arc.toml"))
            .unwrap()
            .replace("fixed_light_elevation_deg = 0.0", "fixed_light_elevation_deg = 40.0");
        let rig = RigSpec::parse(&t, "oblique-arc.toml").unwrap();
        let (fails, worst, ok) = round_trip(&rig, &bonn());
        assert!(worst < 1e-9, "{worst}");
        // the same coplanar pairs as with the lamp overhead: τ = 40° ∓ θ_l stays in ±80°
        let (_, _, ok_overhead) = round_trip(&shipped("static-light-arc.toml"), &bonn());
        assert_eq!(ok, ok_overhead, "{fails:?}");
        assert_eq!(ok + fails["out_of_limits"] + fails["light_blocked_by_camera"], 6561);
    }
}
