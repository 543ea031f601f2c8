//! The dome (Bonn's Dome, a light stage): N fixed cameras and M fixed lamps on a
//! hemisphere around the sample. Measuring is selecting, not moving.
//!
//! The configuration is two selector axes, `camera_select` and `light_select`, whose
//! position is the index into the camera / lamp list. At the interface (rig file, plan)
//! the position in "degrees" *is* the index, so `axes_deg = [12, 40]` reads "camera 12,
//! lamp 40"; inside, as for every axis, it is that number in radians. Their motion model is
//! the switching time: a huge velocity and acceleration with `settle_s` = time to switch.
//!
//! The sample frame is the world frame (nothing moves the sample). Directions come from
//! `geometry.camera_directions_deg` / `light_directions_deg`, or default to
//! [`uniform15`] (the layout of the `uniform15` sweep). Inverse kinematics returns the
//! camera and lamp whose directions match the pair within `dome_match_tolerance_deg`, or
//! [`Infeasibility::NotInDome`] naming the nearest available directions.
//!
//! All cameras are always there, so a lamp whose path to the sample passes through any
//! camera body is blocked for every pair — except a lamp in exactly a camera's direction,
//! which is that camera's own flash (as on Bonn's dome) and shines past it.

use super::{light_clearance, CameraPose, Infeasibility, Kinematics};
use crate::geometry::{Direction, Vec3};
use crate::rig::RigSpec;
use crate::SoftLimits;

/// Axis roles this kind needs.
pub const ROLES: [&str; 2] = ["camera_select", "light_select"];

/// The near-uniform 15° layout: θ rings every 15° up to 75°, azimuth steps so neighbours on
/// a ring are about 15° apart (80 directions). Same as the gonio crate's `uniform15` sweep.
pub fn uniform15() -> Vec<Direction> {
    let mut v = vec![Direction::from_degrees(0.0, 0.0)];
    for ring in 1..=5 {
        let t = 15.0 * ring as f64;
        let n = ((360.0 * t.to_radians().sin()) / 15.0).round().max(6.0) as usize;
        for k in 0..n {
            v.push(Direction::from_degrees(t, k as f64 * 360.0 / n as f64));
        }
    }
    v
}

/// Bonn's Dome 1 layout (151 directions; the cameras of the UBO2014 data, whose flashes
/// are the lamps): ten θ rings with their own azimuth counts and offsets, as documented by
/// the University of Bonn (`cgbonn/btflib`, `create_ubo_dome1_sampling.m`). It is *not*
/// the uniform 15° set ([`uniform15`] has 80 directions): the rings are 7.5° apart above
/// 23.5° and alternate rings are turned by half an azimuth step so that neighbours do not
/// line up. Azimuths are wrapped into [0°, 360°) (conventions.md); the canonical order is
/// ring by ring, φ ascending from the ring's offset, as in the Bonn list.
pub fn bonn_dome1() -> Vec<Direction> {
    const RINGS: [(f64, usize, f64); 10] = [
        (0.0, 1, 0.0),
        (11.0, 6, 15.0),
        (23.5, 12, 0.0),
        (30.0, 12, 15.0),
        (37.5, 12, 0.0),
        (45.0, 18, 0.0),
        (52.5, 18, 7.5),
        (60.0, 24, 0.0),
        (67.5, 24, 7.5),
        (75.0, 24, 0.0),
    ];
    let mut v = Vec::with_capacity(151);
    for (t, n, offset) in RINGS {
        for k in 0..n {
            v.push(Direction::from_degrees(
                t,
                (k as f64 * 360.0 / n as f64 + offset).rem_euclid(360.0),
            ));
        }
    }
    v
}

/// Named dome layouts (`geometry.dome_layout`).
pub const LAYOUTS: [&str; 3] = ["uniform15", "bonn-dome1", "bonn81"];

/// The Bonn 81 directions (conventions.md; the gonio crate's `sweep::bonn81`): a lamp
/// layout for a lightdrum that measures the Bonn set.
pub fn bonn81() -> Vec<Direction> {
    let mut v = Vec::with_capacity(81);
    for (t, n) in [(0.0, 1), (15.0, 6), (30.0, 12), (45.0, 18), (60.0, 20), (75.0, 24)] {
        for k in 0..n {
            v.push(Direction::from_degrees(t, k as f64 * 360.0 / n as f64));
        }
    }
    v
}

/// The directions of a named layout, if the name is known.
pub fn layout(name: &str) -> Option<Vec<Direction>> {
    match name {
        "uniform15" => Some(uniform15()),
        "bonn-dome1" | "bonn151" => Some(bonn_dome1()),
        "bonn81" => Some(bonn81()),
        _ => None,
    }
}

/// (camera, lamp) directions of a dome rig file: explicit lists first, then
/// `geometry.dome_layout`, then the uniform 15° layout.
pub fn directions(rig: &RigSpec) -> (Vec<Direction>, Vec<Direction>) {
    let named = || {
        rig.geometry
            .dome_layout
            .as_deref()
            .and_then(layout)
            .unwrap_or_else(uniform15)
    };
    let list = |l: &Option<Vec<[f64; 2]>>| match l {
        Some(l) => l.iter().map(|&[t, p]| Direction::from_degrees(t, p)).collect(),
        None => named(),
    };
    (
        list(&rig.geometry.camera_directions_deg),
        list(&rig.geometry.light_directions_deg),
    )
}

pub struct Dome {
    n: usize,
    i_cam: usize,
    i_light: usize,
    limits: Vec<SoftLimits>,
    cameras: Vec<Direction>,
    lamps: Vec<Direction>,
    tolerance: f64,
    camera_distance: f64,
    light_distance: f64,
    /// Per lamp: the smallest clearance to any camera body it is not mounted on (mm).
    lamp_clearance: Vec<f64>,
}

/// Selector position (rad) of an index.
fn position(index: usize) -> f64 {
    (index as f64).to_radians()
}

/// Index of a selector position (nearest integer "degree").
fn index(q: f64, len: usize) -> usize {
    (q.to_degrees().round().max(0.0) as usize).min(len - 1)
}

impl Dome {
    pub fn new(rig: &RigSpec) -> Self {
        let idx = |role: &str| {
            rig.axis_by_role(role)
                .map(|(i, _)| i)
                .expect("rig validated: role present")
        };
        let (cameras, lamps) = directions(rig);
        let g = &rig.geometry;
        let block = g.camera_body_radius_mm + g.clearance_mm;
        let lamp_clearance = lamps
            .iter()
            .map(|l| {
                let lp = l.vector() * g.light_distance_mm;
                cameras
                    .iter()
                    // a lamp in a camera's direction is that camera's flash
                    .filter(|c| c.angle_to(*l) > 1e-9)
                    .map(|c| light_clearance(lp, c.vector() * g.camera_distance_mm, block))
                    .fold(f64::INFINITY, f64::min)
            })
            .collect();
        Dome {
            n: rig.axes.len(),
            i_cam: idx("camera_select"),
            i_light: idx("light_select"),
            limits: rig.axes.iter().map(|a| a.limits()).collect(),
            cameras,
            lamps,
            tolerance: g.dome_match_tolerance_deg.to_radians(),
            camera_distance: g.camera_distance_mm,
            light_distance: g.light_distance_mm,
            lamp_clearance,
        }
    }

    /// Index and angular distance of the nearest entry.
    fn nearest(list: &[Direction], d: Direction) -> (usize, f64) {
        list.iter()
            .enumerate()
            .map(|(i, x)| (i, x.angle_to(d)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .expect("validated: non-empty direction list")
    }
}

impl Kinematics for Dome {
    fn axis_count(&self) -> usize {
        self.n
    }

    fn forward(&self, q: &[f64]) -> (Direction, Direction) {
        (
            self.lamps[index(q[self.i_light], self.lamps.len())],
            self.cameras[index(q[self.i_cam], self.cameras.len())],
        )
    }

    fn camera_pose(&self, q: &[f64]) -> CameraPose {
        let d = self.cameras[index(q[self.i_cam], self.cameras.len())];
        let dir = d.vector();
        let forward = -dir;
        // image x horizontal (along ẑ × d), as a camera on a two-arm arc at azimuth φ
        let right = Vec3::new(0.0, 1.0, 0.0).rotate_z(d.phi);
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

    fn inverse(
        &self,
        light: Direction,
        view: Direction,
        _prev: Option<&[f64]>,
    ) -> Result<Vec<Vec<f64>>, Infeasibility> {
        let (ci, ca) = Self::nearest(&self.cameras, view);
        let (li, la) = Self::nearest(&self.lamps, light);
        if ca > self.tolerance || la > self.tolerance {
            let show = |what: &str, d: Direction, i: usize, x: Direction, off: f64| {
                format!(
                    "{what} θ={:.2}° φ={:.2}°: nearest {what} #{i} at θ={:.2}° φ={:.2}° ({:.2}° away)",
                    d.theta_deg(),
                    d.phi_deg(),
                    x.theta_deg(),
                    x.phi_deg(),
                    off.to_degrees()
                )
            };
            let mut parts = Vec::new();
            if ca > self.tolerance {
                parts.push(show("camera", view, ci, self.cameras[ci], ca));
            }
            if la > self.tolerance {
                parts.push(show("lamp", light, li, self.lamps[li], la));
            }
            return Err(Infeasibility::NotInDome {
                detail: parts.join("; "),
            });
        }
        if self.lamp_clearance[li] <= 0.0 {
            return Err(Infeasibility::LightBlockedByCamera {
                clearance_mm: self.lamp_clearance[li],
            });
        }
        let (qc, ql) = (position(ci), position(li));
        if !self.limits[self.i_cam].contains(qc) || !self.limits[self.i_light].contains(ql) {
            return Err(super::out_of_limits(
                light,
                view,
                "selector index outside its axis limits",
            ));
        }
        let mut q = vec![0.0; self.n];
        q[self.i_cam] = qc;
        q[self.i_light] = ql;
        Ok(vec![q])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::for_rig;
    use crate::kinematics::tests_support::{bonn, round_trip, shipped};

    fn text() -> String {
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/rigs/dome.toml")).unwrap()
    }

    #[test]
    fn own_directions_round_trip_exactly() {
        let rig = shipped("dome.toml");
        let (cams, lamps) = directions(&rig);
        assert_eq!((cams.len(), lamps.len()), (80, 80));
        let (fails, worst, ok) = round_trip(&rig, &cams);
        assert!(fails.is_empty(), "{fails:?}");
        assert_eq!(ok, 80 * 80);
        assert!(worst < 1e-9, "{worst}");
        // the selector position (degrees at the interface) is the index
        let k = for_rig(&rig);
        let q = &k.inverse(lamps[41], cams[7], None).unwrap()[0];
        assert_eq!(
            q.iter().map(|x| x.to_degrees().round()).collect::<Vec<_>>(),
            vec![7.0, 41.0]
        );
    }

    #[test]
    fn bonn_pairs_not_in_the_dome_name_the_nearest_direction() {
        let rig = shipped("dome.toml");
        let (fails, worst, ok) = round_trip(&rig, &bonn());
        assert!(worst < 1e-9);
        // shared: pole, the 15° and 30° rings (6 and 12 on both), φ = 0 of 45°, 60°, 75°
        assert_eq!(ok, 22 * 22);
        assert_eq!(fails.get("not_in_dome"), Some(&(6561 - 22 * 22)), "{fails:?}");
        let k = for_rig(&rig);
        let e = k
            .inverse(
                Direction::from_degrees(45.0, 20.0),
                Direction::from_degrees(0.0, 0.0),
                None,
            )
            .unwrap_err();
        let s = e.to_string();
        // 45° ring has 17 lamps, 21.18° apart: nearest to φ = 20° is #20 at φ ≈ 21.18°
        assert!(
            s.contains("lamp θ=45.00° φ=20.00°") && s.contains("#20") && s.contains("φ=21.18°"),
            "{s}"
        );
        assert!(!s.contains("camera θ"), "the camera matched: {s}");
    }

    #[test]
    fn explicit_lists_limits_and_blocking() {
        // two cameras, three lamps on a shell outside the cameras: the lamp 3° from camera 1
        // passes 650·sin 3° ≈ 34 mm from its centre (< 65 mm body + clearance) and is blocked
        // for every pair; the lamps in the cameras' own directions are their flashes.
        let t = text().replace(
            "# camera_directions_deg",
            "camera_directions_deg = [[0, 0], [40, 90]]\nlight_directions_deg = [[0, 0], [40, 90], [43, 90]]\n#",
        );
        let t = t.replace("light_distance_mm = 650.0", "light_distance_mm = 800.0");
        let rig = RigSpec::parse(&t, "small_dome.toml").unwrap();
        let k = for_rig(&rig);
        let c0 = Direction::from_degrees(0.0, 0.0);
        let c1 = Direction::from_degrees(40.0, 90.0);
        for v in [c0, c1] {
            assert!(matches!(
                k.inverse(Direction::from_degrees(43.0, 90.0), v, None),
                Err(Infeasibility::LightBlockedByCamera { .. })
            ));
            assert!(k.inverse(c0, v, None).is_ok());
            assert!(k.inverse(c1, v, None).is_ok());
        }
        // a selector that cannot reach every index is a rig-file error naming the key
        let bad = text().replacen("max_deg = 79.0", "max_deg = 50.0", 1);
        let e = RigSpec::parse(&bad, "d.toml").unwrap_err().to_string();
        assert!(e.contains("(cameras)") && e.contains("0 ..= 79"), "{e}");
        let dup = text().replace(
            "# camera_directions_deg",
            "camera_directions_deg = [[10, 0], [10, 360]]\n#",
        );
        let e = RigSpec::parse(&dup, "d.toml").unwrap_err().to_string();
        assert!(
            e.contains("camera_directions_deg") && e.contains("entry 1") && e.contains("duplicate of entry 0"),
            "{e}"
        );
    }

    #[test]
    fn tolerance_matches_nearby_requests_and_pose_is_the_selected_camera() {
        let t = text().replace("dome_match_tolerance_deg = 5e-8", "dome_match_tolerance_deg = 0.5");
        let rig = RigSpec::parse(&t, "tol.toml").unwrap();
        let k = for_rig(&rig);
        let q = &k
            .inverse(
                Direction::from_degrees(30.3, 0.0),
                Direction::from_degrees(15.0, 60.2),
                None,
            )
            .unwrap()[0];
        let (l, v) = k.forward(q);
        assert!(l.angle_to(Direction::from_degrees(30.0, 0.0)) < 1e-12);
        assert!(v.angle_to(Direction::from_degrees(15.0, 60.0)) < 1e-12);
        let pose = k.camera_pose(q);
        let c = pose.to_camera(Vec3::ZERO);
        assert!(c.x.abs() < 1e-9 && c.y.abs() < 1e-9 && (c.z - 650.0).abs() < 1e-9);
        assert!(pose.right.dot(pose.forward).abs() < 1e-12);
    }

    /// Bonn's Dome 1 layout has 151 distinct directions on ten rings, and the shipped
    /// `dome151` rig measures all 151 × 151 pairs with FK(IK) exact.
    #[test]
    fn bonn_dome1_has_151_directions_and_dome151_round_trips() {
        let d = bonn_dome1();
        assert_eq!(d.len(), 151);
        for (i, a) in d.iter().enumerate() {
            assert!(d[..i].iter().all(|b| b.angle_to(*a) > 1e-6), "entry {i} repeats");
            assert!(a.theta_deg() <= 75.0 + 1e-9 && (0.0..360.0).contains(&a.phi_deg()));
        }
        let ring = |t: f64| d.iter().filter(|x| (x.theta_deg() - t).abs() < 1e-9).count();
        assert_eq!(
            [0.0, 11.0, 23.5, 30.0, 37.5, 45.0, 52.5, 60.0, 67.5, 75.0].map(ring),
            [1, 6, 12, 12, 12, 18, 18, 24, 24, 24]
        );
        assert_ne!(
            uniform15().len(),
            151,
            "uniform15 is the 80-direction set, not Bonn's 151"
        );
        let rig = shipped("dome151.toml");
        let (fails, worst, ok) = round_trip(&rig, &d);
        assert!(worst < 1e-12, "{worst}");
        assert!(fails.is_empty(), "{fails:?}");
        assert_eq!(ok, 151 * 151);
        let bad = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/rigs/dome151.toml"))
            .unwrap()
            .replace("dome_layout = \"bonn-dome1\"", "dome_layout = \"bonn-dome2\"");
        let e = RigSpec::parse(&bad, "d.toml").unwrap_err().to_string();
        assert!(e.contains("geometry.dome_layout") && e.contains("bonn-dome1"), "{e}");
    }
}
