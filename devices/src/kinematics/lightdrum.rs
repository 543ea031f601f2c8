//! The lightdrum (CTU's Lightdrum principle): a dome-like light stage whose cameras sit on
//! one arc that rotates about the vertical axis, while the lamps are fixed. Lamps are
//! selected ("measuring is selecting"); cameras are selected *and* moved by turning the arc.
//!
//! Axes: `arc_rotation` β (a real rotary axis, with cable limits), `camera_select` (index
//! into `geometry.arc_camera_elevations_deg`) and `light_select` (index into the lamp
//! list: `geometry.light_directions_deg`, else the named `geometry.dome_layout`, else the
//! uniform 15° layout). Selector positions are indices, as on the dome (degrees at the
//! interface = index).
//!
//! Camera `i` sits at the signed elevation `e_i` from the zenith along the arc, so in the
//! sample frame (= world, nothing moves the sample) its direction is
//! `(sin e_i cos β, sin e_i sin β, cos e_i)`: a negative `e_i` is on the far side of the
//! pole, at azimuth β + 180°.
//!
//! **Inverse kinematics** (all solutions): every camera whose |e_i| equals θ_v (within
//! `dome_match_tolerance_deg`) with β = φ_v (e_i > 0) or φ_v + 180° (e_i < 0), at every
//! wrap of β inside the arc's limits; the lamp within the tolerance of the requested light.
//! A camera at the zenith (e_i = 0) sees the same direction for every β: β is free
//! ([`Kinematics::free_axes`]), IK keeps it where it was.
//!
//! **Feasibility**: the lamp list is fixed, so a light direction without a lamp is
//! [`Infeasibility::NotInDome`]; a view elevation without a camera likewise. All cameras on
//! the arc are always there: a configuration whose lamp path passes through *any* camera
//! body on the arc (at that β) is blocked; if every configuration of the pair is blocked
//! the reason is [`Infeasibility::LightBlockedByCamera`] with the best clearance found.
//! The arc's own structure is not modelled as an obstacle (it is thin next to the camera
//! bodies); the body radius in the rig file should include it where it matters.

use super::{light_clearance, wraps, CameraPose, Infeasibility, Kinematics};
use crate::geometry::{Direction, Vec3, POLE_EPS};
use crate::rig::RigSpec;
use crate::SoftLimits;
use std::f64::consts::PI;

/// Axis roles this kind needs.
pub const ROLES: [&str; 3] = ["arc_rotation", "camera_select", "light_select"];

/// Camera elevations (degrees) used when the rig file gives none: the Bonn θ rings.
pub const DEFAULT_ELEVATIONS_DEG: [f64; 6] = [0.0, 15.0, 30.0, 45.0, 60.0, 75.0];

/// Signed camera elevations (rad) of a lightdrum rig file.
pub fn elevations(rig: &RigSpec) -> Vec<f64> {
    rig.geometry
        .arc_camera_elevations_deg
        .clone()
        .unwrap_or_else(|| DEFAULT_ELEVATIONS_DEG.to_vec())
        .iter()
        .map(|e| e.to_radians())
        .collect()
}

/// Lamp directions of a lightdrum rig file (the dome's lamp rules).
pub fn lamps(rig: &RigSpec) -> Vec<Direction> {
    super::dome::directions(rig).1
}

pub struct Lightdrum {
    n: usize,
    i_arc: usize,
    i_cam: usize,
    i_light: usize,
    limits: Vec<SoftLimits>,
    elevations: Vec<f64>,
    lamps: Vec<Direction>,
    tolerance: f64,
    camera_distance: f64,
    light_distance: f64,
    block_radius: f64,
}

fn position(index: usize) -> f64 {
    (index as f64).to_radians()
}

fn index(q: f64, len: usize) -> usize {
    (q.to_degrees().round().max(0.0) as usize).min(len - 1)
}

impl Lightdrum {
    pub fn new(rig: &RigSpec) -> Self {
        let idx = |role: &str| {
            rig.axis_by_role(role)
                .map(|(i, _)| i)
                .expect("rig validated: role present")
        };
        let g = &rig.geometry;
        Lightdrum {
            n: rig.axes.len(),
            i_arc: idx("arc_rotation"),
            i_cam: idx("camera_select"),
            i_light: idx("light_select"),
            limits: rig.axes.iter().map(|a| a.limits()).collect(),
            elevations: elevations(rig),
            lamps: lamps(rig),
            tolerance: g.dome_match_tolerance_deg.to_radians(),
            camera_distance: g.camera_distance_mm,
            light_distance: g.light_distance_mm,
            block_radius: g.camera_body_radius_mm + g.clearance_mm,
        }
    }

    /// Unit vector of camera `i` with the arc at `beta`.
    fn camera_dir(&self, i: usize, beta: f64) -> Vec3 {
        let e = self.elevations[i];
        Vec3::new(e.sin() * beta.cos(), e.sin() * beta.sin(), e.cos())
    }

    /// Smallest clearance between the lamp's path and any camera body on the arc at `beta`.
    fn clearance(&self, lamp: Direction, beta: f64) -> f64 {
        let lp = lamp.vector() * self.light_distance;
        (0..self.elevations.len())
            .map(|i| light_clearance(lp, self.camera_dir(i, beta) * self.camera_distance, self.block_radius))
            .fold(f64::INFINITY, f64::min)
    }

    /// Cameras that see `view` and the arc angle each needs (`None` = any β: zenith).
    fn cameras_for(&self, view: Direction) -> Vec<(usize, Option<f64>)> {
        let mut out = Vec::new();
        for (i, &e) in self.elevations.iter().enumerate() {
            if (e.abs() - view.theta).abs() > self.tolerance {
                continue;
            }
            if e.abs() < POLE_EPS {
                out.push((i, None));
            } else if e > 0.0 {
                out.push((i, Some(view.phi)));
            } else {
                out.push((i, Some(view.phi + PI)));
            }
        }
        out
    }

    fn nearest_lamp(&self, d: Direction) -> (usize, f64) {
        self.lamps
            .iter()
            .enumerate()
            .map(|(i, x)| (i, x.angle_to(d)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .expect("validated: non-empty lamp list")
    }
}

impl Kinematics for Lightdrum {
    fn axis_count(&self) -> usize {
        self.n
    }

    fn forward(&self, q: &[f64]) -> (Direction, Direction) {
        let ci = index(q[self.i_cam], self.elevations.len());
        (
            self.lamps[index(q[self.i_light], self.lamps.len())],
            Direction::from_vector(self.camera_dir(ci, q[self.i_arc])),
        )
    }

    fn camera_pose(&self, q: &[f64]) -> CameraPose {
        let ci = index(q[self.i_cam], self.elevations.len());
        let beta = q[self.i_arc];
        let dir = self.camera_dir(ci, beta);
        let forward = -dir;
        // image x along the arc's rotation axis direction (normal to the arc's plane)
        let right = Vec3::new(0.0, 1.0, 0.0).rotate_z(beta);
        CameraPose {
            position: dir * self.camera_distance,
            right,
            down: forward.cross(right),
            forward,
        }
    }

    fn light_position(&self, q: &[f64]) -> Vec3 {
        self.lamps[index(q[self.i_light], self.lamps.len())].vector() * self.light_distance
    }

    fn free_axes(&self, _light: Direction, view: Direction) -> Vec<usize> {
        let cams = self.cameras_for(view);
        if !cams.is_empty() && cams.iter().all(|(_, b)| b.is_none()) {
            vec![self.i_arc]
        } else {
            Vec::new()
        }
    }

    fn inverse(&self, light: Direction, view: Direction, prev: Option<&[f64]>) -> Result<Vec<Vec<f64>>, Infeasibility> {
        let cams = self.cameras_for(view);
        let (li, la) = self.nearest_lamp(light);
        let mut missing = Vec::new();
        if cams.is_empty() {
            let nearest = self
                .elevations
                .iter()
                .map(|e| e.abs())
                .min_by(|a, b| (a - view.theta).abs().total_cmp(&(b - view.theta).abs()))
                .unwrap_or(0.0);
            missing.push(format!(
                "view θ={:.2}°: no camera on the arc at that elevation (nearest {:.2}°)",
                view.theta_deg(),
                nearest.to_degrees()
            ));
        }
        if la > self.tolerance {
            let x = self.lamps[li];
            missing.push(format!(
                "lamp θ={:.2}° φ={:.2}°: nearest lamp #{li} at θ={:.2}° φ={:.2}° ({:.2}° away)",
                light.theta_deg(),
                light.phi_deg(),
                x.theta_deg(),
                x.phi_deg(),
                la.to_degrees()
            ));
        }
        if !missing.is_empty() {
            return Err(Infeasibility::NotInDome {
                detail: missing.join("; "),
            });
        }
        let (lc, ll) = (self.limits[self.i_cam], self.limits[self.i_light]);
        let ql = position(li);
        if !ll.contains(ql) {
            return Err(super::out_of_limits(
                light,
                view,
                "lamp selector index outside its axis limits",
            ));
        }
        let la_lim = self.limits[self.i_arc];
        let mut out = Vec::new();
        let mut best_blocked = f64::NEG_INFINITY;
        let mut any_in_limits = false;
        for (ci, beta) in cams {
            let qc = position(ci);
            if !lc.contains(qc) {
                continue;
            }
            let betas = match beta {
                Some(b) => wraps(la_lim, b),
                None => {
                    let keep = prev.map(|p| p[self.i_arc]).unwrap_or(0.0);
                    super::fit(la_lim, keep).into_iter().collect()
                }
            };
            for b in betas {
                any_in_limits = true;
                let c = self.clearance(self.lamps[li], b);
                if c <= 0.0 {
                    best_blocked = best_blocked.max(c);
                    continue;
                }
                let mut q = vec![0.0; self.n];
                q[self.i_arc] = b;
                q[self.i_cam] = qc;
                q[self.i_light] = ql;
                out.push(q);
            }
        }
        if out.is_empty() {
            if any_in_limits {
                return Err(Infeasibility::LightBlockedByCamera {
                    clearance_mm: best_blocked,
                });
            }
            return Err(super::out_of_limits(
                light,
                view,
                "no arc angle / camera index within the limits",
            ));
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::for_rig;
    use crate::kinematics::tests_support::{bonn, round_trip, shipped};

    fn text() -> String {
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/rigs/lightdrum.toml")).unwrap()
    }

    #[test]
    fn fk_ik_round_trip_on_the_bonn_pairs_it_can_reach() {
        let rig = shipped("lightdrum.toml");
        let (fails, worst, ok) = round_trip(&rig, &bonn());
        assert!(worst < 1e-9, "worst round-trip error {worst} rad");
        // every Bonn view has a camera and every Bonn light a lamp: only blocking remains
        assert_eq!(fails.len(), 1, "{fails:?}");
        let blocked = fails["light_blocked_by_camera"];
        assert_eq!(ok + blocked, 6561);
        // the zenith lamp is behind the zenith camera for every view
        assert!(blocked >= 81 && ok > 5000, "ok {ok}, blocked {blocked}");
    }

    #[test]
    fn every_blocked_pair_really_has_a_camera_in_the_lamp_path() {
        let rig = shipped("lightdrum.toml");
        let k = Lightdrum::new(&rig);
        let dirs = bonn();
        for v in &dirs {
            for l in &dirs {
                let r = k.inverse(*l, *v, None);
                // reachable configurations keep every camera body out of the lamp path
                match r {
                    Ok(sols) => {
                        for q in sols {
                            assert!(k.clearance(*l, q[0]) > 0.0);
                        }
                    }
                    Err(Infeasibility::LightBlockedByCamera { clearance_mm }) => {
                        assert!(clearance_mm <= 0.0);
                        // both arc wraps are blocked: check the principal one directly
                        let beta = if v.theta < 1e-12 { 0.0 } else { v.phi };
                        assert!(k.clearance(*l, beta) <= 0.0);
                    }
                    Err(e) => panic!("unexpected reason {e}"),
                }
            }
        }
    }

    #[test]
    fn zenith_view_frees_the_arc_and_keeps_it() {
        let k = for_rig(&shipped("lightdrum.toml"));
        let l = Direction::from_degrees(45.0, 40.0);
        let v = Direction::from_degrees(0.0, 0.0);
        assert_eq!(k.free_axes(l, v), vec![0]);
        let sols = k.inverse(l, v, Some(&[1.1, 0.0, 0.0])).unwrap();
        assert!(sols.iter().all(|q| q[0] == 1.1), "{sols:?}");
        // a view at 30°: both wraps of β inside ±270° are offered
        let sols = k.inverse(l, Direction::from_degrees(30.0, 100.0), None).unwrap();
        assert_eq!(sols.len(), 2, "{sols:?}");
        assert!((sols[1][0] - sols[0][0] - 2.0 * PI).abs() < 1e-12);
    }

    #[test]
    fn missing_cameras_and_lamps_are_named() {
        let k = for_rig(&shipped("lightdrum.toml"));
        let e = k
            .inverse(
                Direction::from_degrees(45.0, 10.0),
                Direction::from_degrees(37.0, 0.0),
                None,
            )
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("not in the dome") && e.contains("nearest 30.00°") && e.contains("lamp θ=45.00° φ=10.00°"),
            "{e}"
        );
    }

    #[test]
    fn far_side_cameras_and_narrow_arc_limits() {
        // cameras on both sides of the pole and an arc that turns only ±100°: views on the
        // other half are reached with the far-side camera (β = φ + 180°).
        let t = text()
            .replace(
                "arc_camera_elevations_deg = [0.0, 15.0, 30.0, 45.0, 60.0, 75.0]",
                "arc_camera_elevations_deg = [0.0, 15.0, 30.0, 45.0, 60.0, 75.0, -15.0, -30.0, -45.0, -60.0, -75.0]",
            )
            .replace("min_deg = -270.0\nmax_deg = 270.0", "min_deg = -100.0\nmax_deg = 100.0")
            .replace("max_deg = 5.0", "max_deg = 10.0");
        let rig = RigSpec::parse(&t, "two-sided.toml").unwrap();
        let (fails, worst, ok) = round_trip(&rig, &bonn());
        assert!(worst < 1e-9, "{worst}");
        assert!(!fails.contains_key("out_of_limits"), "{fails:?}");
        assert!(ok > 5000, "{fails:?}");
        let k = for_rig(&rig);
        let v = Direction::from_degrees(45.0, 180.0);
        let sols = k.inverse(Direction::from_degrees(30.0, 90.0), v, None).unwrap();
        for q in &sols {
            assert!(q[0].abs() <= 100f64.to_radians() + 1e-12);
            assert!(k.forward(q).1.angle_to(v) < 1e-9);
        }
        // without the far-side cameras the same arc limits leave views unreachable
        let t = text().replace("min_deg = -270.0\nmax_deg = 270.0", "min_deg = -100.0\nmax_deg = 100.0");
        let rig = RigSpec::parse(&t, "one-sided.toml").unwrap();
        let (fails, _, _) = round_trip(&rig, &bonn());
        assert!(fails.get("out_of_limits").copied().unwrap_or(0) > 0, "{fails:?}");
    }

    #[test]
    fn pose_looks_at_the_sample() {
        let k = Lightdrum::new(&shipped("lightdrum.toml"));
        for q in [vec![0.7, 3f64.to_radians(), 10f64.to_radians()], vec![-2.0, 0.0, 0.0]] {
            let pose = k.camera_pose(&q);
            let c = pose.to_camera(Vec3::ZERO);
            assert!(c.x.abs() < 1e-9 && c.y.abs() < 1e-9 && (c.z - k.camera_distance).abs() < 1e-9);
            assert!(pose.right.dot(pose.forward).abs() < 1e-12);
            let (_, v) = k.forward(&q);
            assert!(crate::geometry::angle_between(pose.position, v.vector()) < 1e-12);
        }
    }
}
