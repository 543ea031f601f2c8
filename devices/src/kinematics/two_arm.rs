//! The two-arm goniometer: sample turntable α, camera elevation arc θc (fixed in the world
//! x-z plane), light azimuth base β and light elevation arc θl.
//!
//! World directions: camera `(sin θc, 0, cos θc)`, lamp `(sin θl cos β, sin θl sin β, cos θl)`.
//! The sample frame is the world rotated by α about z, so a world vector `w` is
//! `Rz(−α) w` in the sample frame. Negative elevations put a device on the far side of the
//! pole; that doubles the solutions and lets the planner avoid long turntable moves.

use super::rot::Mat3;
use super::{CameraPose, Infeasibility, Kinematics};
use crate::geometry::{wrap_pi, Direction, Vec3, POLE_EPS};
use crate::rig::RigSpec;
use crate::SoftLimits;
use std::f64::consts::PI;

/// Axis roles this kind needs, in no particular order.
pub const ROLES: [&str; 4] = [
    "sample_rotation",
    "camera_elevation",
    "light_azimuth",
    "light_elevation",
];

/// Turntable sampling step (rad) offered when the camera is at the pole.
const POLE_SAMPLE: f64 = PI / 12.0;

pub struct TwoArm {
    n: usize,
    i_turn: usize,
    i_cam: usize,
    i_lbase: usize,
    i_larc: usize,
    limits: Vec<SoftLimits>,
    camera_distance: f64,
    light_distance: f64,
    block_radius: f64,
    /// Axis zero offsets (rad, axis order): true position = commanded + offset. `limits`
    /// are stored in true positions (the commanded limits shifted by the offsets), so IK
    /// works on the true mechanism and returns commanded positions.
    offsets: Vec<f64>,
    /// Camera mounting rotation (columns: true camera axes in the nominal camera frame).
    mount: Option<Mat3>,
}

impl TwoArm {
    pub fn new(rig: &RigSpec) -> Self {
        let idx = |role: &str| {
            rig.axis_by_role(role)
                .map(|(i, _)| i)
                .expect("rig validated: role present")
        };
        let alignment = rig.alignment.clone().unwrap_or_default();
        let offsets = alignment.offsets_rad(&rig.axes);
        let r = alignment.camera_rotation_deg;
        let mount = (r != [0.0; 3])
            .then(|| Mat3::from_rotation_vector(Vec3::new(r[0].to_radians(), r[1].to_radians(), r[2].to_radians())));
        TwoArm {
            n: rig.axes.len(),
            i_turn: idx("sample_rotation"),
            i_cam: idx("camera_elevation"),
            i_lbase: idx("light_azimuth"),
            i_larc: idx("light_elevation"),
            limits: rig
                .axes
                .iter()
                .zip(&offsets)
                .map(|(a, o)| {
                    let l = a.limits();
                    SoftLimits {
                        min: l.min + o,
                        max: l.max + o,
                    }
                })
                .collect(),
            offsets,
            mount,
            camera_distance: rig.geometry.camera_distance_mm,
            light_distance: rig.geometry.light_distance_mm,
            block_radius: rig.geometry.camera_body_radius_mm + rig.geometry.clearance_mm,
        }
    }

    /// True axis positions for commanded ones.
    fn true_q(&self, q: &[f64]) -> Vec<f64> {
        q.iter().zip(&self.offsets).map(|(x, o)| x + o).collect()
    }

    /// All values `base + k·2π` inside the limits of an axis (see [`super::wraps`]).
    fn wraps(&self, axis: usize, base: f64) -> Vec<f64> {
        super::wraps(self.limits[axis], base)
    }

    /// Signed elevation / azimuth-offset options for a direction: (elevation, azimuth offset).
    fn elevation_options(&self, axis: usize, theta: f64) -> Vec<(f64, f64)> {
        let l = self.limits[axis];
        [(theta, 0.0), (-theta, PI)]
            .into_iter()
            .filter(|(e, _)| l.contains(*e))
            .collect()
    }

    /// Shortest distance (mm) from the camera body centre to the lamp's ray toward the
    /// sample centre, minus the body radius and clearance: < 0 means blocked.
    fn light_clearance(&self, light: Vec3, view: Vec3) -> f64 {
        let c = view * self.camera_distance;
        let l = light * self.light_distance;
        // segment from l to the origin: points l·(1−t), t ∈ [0, 1]
        let t = ((l - c).dot(l) / l.dot(l)).clamp(0.0, 1.0);
        let closest = l * (1.0 - t);
        (closest - c).norm() - self.block_radius
    }
}

impl Kinematics for TwoArm {
    fn axis_count(&self) -> usize {
        self.n
    }

    fn forward(&self, q: &[f64]) -> (Direction, Direction) {
        let q = &self.true_q(q);
        let alpha = q[self.i_turn];
        let (tc, tl, b) = (q[self.i_cam], q[self.i_larc], q[self.i_lbase]);
        let view_w = Vec3::new(tc.sin(), 0.0, tc.cos());
        let light_w = Vec3::new(tl.sin() * b.cos(), tl.sin() * b.sin(), tl.cos());
        (
            Direction::from_vector(light_w.rotate_z(-alpha)),
            Direction::from_vector(view_w.rotate_z(-alpha)),
        )
    }

    fn camera_pose(&self, q: &[f64]) -> CameraPose {
        let q = &self.true_q(q);
        let alpha = q[self.i_turn];
        let tc = q[self.i_cam];
        let dir_w = Vec3::new(tc.sin(), 0.0, tc.cos());
        let position = (dir_w * self.camera_distance).rotate_z(-alpha);
        let forward = (-dir_w).rotate_z(-alpha);
        // The camera is fixed to its arm with image x along world +y (the arc's axis).
        let right = Vec3::new(0.0, 1.0, 0.0).rotate_z(-alpha);
        let down = forward.cross(right);
        match &self.mount {
            None => CameraPose {
                position,
                right,
                down,
                forward,
            },
            Some(m) => {
                // True axis k = Σ_j m[j][k] · nominal axis j (column k of the mount matrix).
                let axis = |k: usize| right * m.0[0][k] + down * m.0[1][k] + forward * m.0[2][k];
                CameraPose {
                    position,
                    right: axis(0),
                    down: axis(1),
                    forward: axis(2),
                }
            }
        }
    }

    fn light_position(&self, q: &[f64]) -> Vec3 {
        let q = &self.true_q(q);
        let (alpha, tl, b) = (q[self.i_turn], q[self.i_larc], q[self.i_lbase]);
        Vec3::new(tl.sin() * b.cos(), tl.sin() * b.sin(), tl.cos()).rotate_z(-alpha) * self.light_distance
    }

    fn free_axes(&self, light: Direction, view: Direction) -> Vec<usize> {
        // The light base is free when the lamp is at the pole. The turntable is never
        // free on its own: with the camera at the pole it still sets the light's
        // azimuth in the sample frame (φ_l = β − α), so IK offers sampled values instead.
        let _ = view;
        if light.theta < POLE_EPS {
            vec![self.i_lbase]
        } else {
            Vec::new()
        }
    }

    fn inverse(&self, light: Direction, view: Direction, prev: Option<&[f64]>) -> Result<Vec<Vec<f64>>, Infeasibility> {
        // Work in true axis positions; convert back to commanded ones at the end.
        let prev_true = prev.map(|p| self.true_q(p));
        let prev = prev_true.as_deref();
        let clearance = self.light_clearance(light.vector(), view.vector());
        if clearance <= 0.0 {
            return Err(Infeasibility::LightBlockedByCamera {
                clearance_mm: clearance,
            });
        }
        // (camera elevation, turntable) candidates
        let mut view_opts: Vec<(f64, f64)> = Vec::new();
        if view.theta < POLE_EPS {
            // The view azimuth is undefined: keep the turntable where it is, or, with no
            // previous configuration, offer every 15° so the planner can pick.
            match prev {
                Some(p) => view_opts.push((0.0, p[self.i_turn])),
                None => {
                    let l = self.limits[self.i_turn];
                    let mut a = (l.min / POLE_SAMPLE).ceil() * POLE_SAMPLE;
                    while a <= l.max + 1e-12 {
                        view_opts.push((0.0, a.min(l.max)));
                        a += POLE_SAMPLE;
                    }
                }
            }
        } else {
            for (e, off) in self.elevation_options(self.i_cam, view.theta) {
                for a in self.wraps(self.i_turn, wrap_pi(off - view.phi)) {
                    view_opts.push((e, a));
                }
            }
        }
        let mut out = Vec::new();
        for (tc, alpha) in view_opts {
            if light.theta < POLE_EPS {
                let b = prev.map(|p| p[self.i_lbase]).unwrap_or(0.0);
                let mut q = vec![0.0; self.n];
                q[self.i_turn] = alpha;
                q[self.i_cam] = tc;
                q[self.i_lbase] = b;
                q[self.i_larc] = 0.0;
                out.push(q);
                continue;
            }
            for (tl, off) in self.elevation_options(self.i_larc, light.theta) {
                for b in self.wraps(self.i_lbase, wrap_pi(light.phi + alpha + off)) {
                    let mut q = vec![0.0; self.n];
                    q[self.i_turn] = alpha;
                    q[self.i_cam] = tc;
                    q[self.i_lbase] = b;
                    q[self.i_larc] = tl;
                    out.push(q);
                }
            }
        }
        for q in &mut out {
            for ((x, o), l) in q.iter_mut().zip(&self.offsets).zip(&self.limits) {
                // (clamped: subtracting the offset may round a value at a limit just past it)
                *x = (*x - o).clamp(l.min - o, l.max - o);
            }
        }
        if out.is_empty() {
            return Err(Infeasibility::OutOfLimits {
                detail: format!(
                    "no configuration within the limits reaches light θ={:.2}° φ={:.2}°, view θ={:.2}° φ={:.2}°",
                    light.theta_deg(),
                    light.phi_deg(),
                    view.theta_deg(),
                    view.phi_deg()
                ),
            });
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::for_rig;

    fn bonn() -> Vec<Direction> {
        let mut v = vec![];
        for (t, n) in [(0.0, 1), (15.0, 6), (30.0, 12), (45.0, 18), (60.0, 20), (75.0, 24)] {
            for k in 0..n {
                v.push(Direction::from_degrees(t, k as f64 * 360.0 / n as f64));
            }
        }
        v
    }

    #[test]
    fn fk_ik_round_trip_on_all_bonn_pairs() {
        let rig = RigSpec::default_rig();
        let k = for_rig(&rig);
        let dirs = bonn();
        let mut blocked = 0;
        let mut worst: f64 = 0.0;
        for v in &dirs {
            for l in &dirs {
                match k.inverse(*l, *v, None) {
                    Ok(sols) => {
                        assert!(!sols.is_empty());
                        for q in sols {
                            for (i, a) in rig.axes.iter().enumerate() {
                                assert!(a.limits().contains(q[i]), "{} out of limits", a.name);
                            }
                            let (lf, vf) = k.forward(&q);
                            worst = worst.max(lf.angle_to(*l)).max(vf.angle_to(*v));
                        }
                    }
                    Err(Infeasibility::LightBlockedByCamera { .. }) => {
                        blocked += 1;
                        assert!(l.angle_to(*v) < 1e-9, "only retro pairs are blocked");
                    }
                    Err(e) => panic!("unexpected {e}"),
                }
            }
        }
        assert_eq!(blocked, 81);
        assert!(worst < 1e-9, "worst round-trip error {worst} rad");
    }

    #[test]
    fn pole_keeps_previous_azimuths() {
        let rig = RigSpec::default_rig();
        let k = for_rig(&rig);
        let prev = vec![0.7, 0.2, -1.1, 0.3];
        let sols = k.inverse(
            Direction::from_degrees(0.0, 0.0),
            Direction::from_degrees(0.0, 0.0),
            Some(&prev),
        );
        // light == view at the pole: blocked
        assert!(sols.is_err());
        let sols = k
            .inverse(
                Direction::from_degrees(30.0, 90.0),
                Direction::from_degrees(0.0, 0.0),
                Some(&prev),
            )
            .unwrap();
        assert!(
            sols.iter().all(|q| q[0] == 0.7),
            "turntable stays where it was at θv = 0"
        );
        // the light azimuth in the sample frame is still right with the turntable at 0.7
        for q in &sols {
            let (l, _) = k.forward(q);
            assert!(l.angle_to(Direction::from_degrees(30.0, 90.0)) < 1e-9);
        }
        // without a previous configuration, sampled turntable positions are offered
        let sols = k
            .inverse(
                Direction::from_degrees(30.0, 90.0),
                Direction::from_degrees(0.0, 0.0),
                None,
            )
            .unwrap();
        assert!(sols.len() > 10);
        assert!(k
            .free_axes(Direction::from_degrees(30.0, 90.0), Direction::from_degrees(0.0, 0.0))
            .is_empty());
    }

    #[test]
    fn camera_looks_at_sample_centre() {
        let rig = RigSpec::default_rig();
        let k = for_rig(&rig);
        let q = vec![0.3, 0.9, 0.1, -0.4];
        let pose = k.camera_pose(&q);
        let c = pose.to_camera(Vec3::ZERO);
        assert!(c.x.abs() < 1e-9 && c.y.abs() < 1e-9 && (c.z - 1000.0).abs() < 1e-9);
        let (_, v) = k.forward(&q);
        assert!(angle(pose.position, v.vector()) < 1e-12);
    }

    /// With an alignment, IK returns commanded positions whose FK (which adds the zero
    /// offsets) reproduces every pair, inside the commanded limits; the mount rotation turns
    /// the camera axes but not its position (the view direction).
    #[test]
    fn alignment_offsets_round_trip_and_mount_turns_only_the_axes() {
        let mut rig = RigSpec::default_rig();
        let ideal = for_rig(&rig);
        rig.alignment = Some(crate::rig::AlignmentSpec {
            axis_zero_offset_deg: [
                ("turntable".to_string(), 0.7),
                ("camera_arc".to_string(), -0.4),
                ("light_arc".to_string(), 0.2),
            ]
            .into_iter()
            .collect(),
            camera_rotation_deg: [0.3, -0.2, 0.5],
        });
        let k = for_rig(&rig);
        let dirs = bonn();
        let mut worst: f64 = 0.0;
        let mut n = 0;
        for v in dirs.iter().step_by(5) {
            for l in dirs.iter().step_by(7) {
                let Ok(sols) = k.inverse(*l, *v, None) else { continue };
                for q in sols {
                    for (i, a) in rig.axes.iter().enumerate() {
                        assert!(a.limits().contains(q[i]), "{} out of limits", a.name);
                    }
                    let (lf, vf) = k.forward(&q);
                    worst = worst.max(lf.angle_to(*l)).max(vf.angle_to(*v));
                    n += 1;
                }
            }
        }
        assert!(n > 100 && worst < 1e-9, "{n} solutions, worst {worst}");
        // the ideal kinematics at the same commanded q are off by the offsets
        let q = vec![0.3, 0.5, 0.1, 0.4];
        let (_, v_ideal) = ideal.forward(&q);
        let (_, v_true) = k.forward(&q);
        let d = v_ideal.angle_to(v_true).to_degrees();
        assert!(d > 0.3 && d < 1.2, "{d}");
        let (p, p0) = (
            k.camera_pose(&q),
            ideal.camera_pose(&[0.3 + 0.7f64.to_radians(), 0.5 - 0.4f64.to_radians(), 0.0, 0.0]),
        );
        assert!((p.position - p0.position).norm() < 1e-9);
        let turn = angle(p.forward, p0.forward).to_degrees();
        assert!((turn - (0.3f64.powi(2) + 0.2f64.powi(2)).sqrt()).abs() < 1e-3, "{turn}");
        assert!(p.right.cross(p.down).dot(p.forward) > 0.999_999, "still right-handed");
    }

    fn angle(a: Vec3, b: Vec3) -> f64 {
        crate::geometry::angle_between(a, b)
    }
}
