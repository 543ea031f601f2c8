//! Sample holder shadowing at grazing angles.
//!
//! The sample (a square of edge `s`, centred, in the z = 0 plane) sits in a pocket whose
//! rim is a square wall of height `h` at a horizontal gap `g` outside the sample's edge.
//! A lamp or camera at `P` (sample frame, mm) sees every point of the sample only if the
//! segment from each point to `P` passes over the wall.
//!
//! For a point `p` the segment crosses the wall plane `x = w` (w = s/2 + g, when
//! |P_x| > w) at the height `P_z · (w − p_x)/(P_x − p_x)`, which is lowest for the point
//! nearest that wall, `p_x = s/2`: `P_z · g / (|P_x| − s/2)`. The same holds for y; the
//! lowest crossing over both walls and all points decides. This is exact for a finite
//! distance (no far-field approximation), and it is why the check needs `g` > 0: a wall
//! at the very edge shadows the adjacent strip for any lamp not overhead.
//!
//! The rim does not depend on how the mechanism reaches a pair, so [`Shadowed`] checks it
//! in front of any kind's inverse kinematics.

use super::{CameraPose, Infeasibility, Kinematics};
use crate::geometry::{Direction, Vec3};
use crate::rig::RigSpec;

/// The holder pocket as the rig file describes it (mm).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Holder {
    pub rim_height: f64,
    pub half_sample: f64,
    pub gap: f64,
    pub light_distance: f64,
    pub camera_distance: f64,
}

impl Holder {
    /// `None` when the rig has no rim (`holder_rim_height_mm` or `sample_size_mm` is 0).
    pub fn from_rig(rig: &RigSpec) -> Option<Holder> {
        let g = &rig.geometry;
        (g.holder_rim_height_mm > 0.0 && g.sample_size_mm > 0.0).then_some(Holder {
            rim_height: g.holder_rim_height_mm,
            half_sample: g.sample_size_mm / 2.0,
            gap: g.holder_rim_gap_mm,
            light_distance: g.light_distance_mm,
            camera_distance: g.camera_distance_mm,
        })
    }

    /// Lowest height (mm) at which a segment from a sample point to `p` crosses the rim's
    /// walls; `+∞` when `p` is above the pocket (no wall crossed).
    pub fn crossing_height(&self, p: Vec3) -> f64 {
        let w = self.half_sample + self.gap;
        [p.x.abs(), p.y.abs()]
            .into_iter()
            .filter(|&c| c > w)
            .map(|c| p.z * self.gap / (c - self.half_sample))
            .fold(f64::INFINITY, f64::min)
    }

    /// The reason if the rim shadows the light or the view ray of a pair.
    pub fn check(&self, light: Direction, view: Direction) -> Result<(), Infeasibility> {
        for (ray, d, dist) in [
            ("light", light, self.light_distance),
            ("view", view, self.camera_distance),
        ] {
            let z = self.crossing_height(d.vector() * dist);
            if z < self.rim_height {
                return Err(Infeasibility::HolderShadow {
                    ray: ray.into(),
                    crossing_height_mm: z,
                    rim_height_mm: self.rim_height,
                });
            }
        }
        Ok(())
    }
}

/// Any kind's kinematics with the holder rim checked first.
pub struct Shadowed {
    inner: Box<dyn Kinematics>,
    holder: Holder,
}

impl Shadowed {
    pub fn new(inner: Box<dyn Kinematics>, holder: Holder) -> Self {
        Shadowed { inner, holder }
    }
}

impl Kinematics for Shadowed {
    fn axis_count(&self) -> usize {
        self.inner.axis_count()
    }
    fn forward(&self, q: &[f64]) -> (Direction, Direction) {
        self.inner.forward(q)
    }
    fn camera_pose(&self, q: &[f64]) -> CameraPose {
        self.inner.camera_pose(q)
    }
    fn light_position(&self, q: &[f64]) -> Vec3 {
        self.inner.light_position(q)
    }
    fn inverse(&self, light: Direction, view: Direction, prev: Option<&[f64]>) -> Result<Vec<Vec<f64>>, Infeasibility> {
        self.holder.check(light, view)?;
        self.inner.inverse(light, view, prev)
    }
    fn free_axes(&self, light: Direction, view: Direction) -> Vec<usize> {
        self.inner.free_axes(light, view)
    }
    fn home(&self) -> Vec<f64> {
        self.inner.home()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::for_rig;
    use crate::rig::{RigSpec, DEFAULT_RIG_TOML};

    fn holder(h: f64) -> Holder {
        Holder {
            rim_height: h,
            half_sample: 25.0,
            gap: 10.0,
            light_distance: 1200.0,
            camera_distance: 1000.0,
        }
    }

    /// The closed form against brute force: segments from a grid of sample points, each
    /// marched to where it leaves the pocket.
    #[test]
    fn crossing_height_matches_brute_force() {
        let h = holder(3.0);
        let w = h.half_sample + h.gap;
        for (t, p) in [(75.0, 0.0), (75.0, 45.0), (60.0, 200.0), (80.0, 300.0), (89.0, 10.0)] {
            let pos = Direction::from_degrees(t, p).vector() * 1000.0;
            let mut lowest = f64::INFINITY;
            let n = 40;
            for i in 0..=n {
                for j in 0..=n {
                    let x = -h.half_sample + 2.0 * h.half_sample * i as f64 / n as f64;
                    let y = -h.half_sample + 2.0 * h.half_sample * j as f64 / n as f64;
                    // parameter where the segment (x, y, 0) → pos leaves |x|, |y| ≤ w
                    let mut s_exit = f64::INFINITY;
                    for (a, b) in [(x, pos.x), (y, pos.y)] {
                        if b.abs() > w {
                            s_exit = s_exit.min((w * b.signum() - a) / (b - a));
                        }
                    }
                    lowest = lowest.min(s_exit * pos.z);
                }
            }
            let closed = h.crossing_height(pos);
            assert!((closed - lowest).abs() < 1e-9, "θ={t} φ={p}: {closed} vs {lowest}");
        }
        // straight overhead: no wall crossed
        assert_eq!(h.crossing_height(Vec3::new(0.0, 0.0, 1000.0)), f64::INFINITY);
    }

    #[test]
    fn high_rim_shadows_grazing_pairs_and_names_the_ray() {
        let h = holder(5.0);
        // 75° along +x: crossing at 1000·cos75·10/(1000·sin75 − 25) ≈ 2.75 mm < 5
        let e = h
            .check(Direction::from_degrees(30.0, 0.0), Direction::from_degrees(75.0, 0.0))
            .unwrap_err();
        assert!(
            matches!(e, Infeasibility::HolderShadow { ref ray, .. } if ray == "view"),
            "{e}"
        );
        assert!(h
            .check(Direction::from_degrees(30.0, 0.0), Direction::from_degrees(45.0, 0.0))
            .is_ok());
    }

    #[test]
    fn low_rim_on_default_rig_keeps_every_bonn_pair_and_deep_rim_does_not() {
        let dirs = crate::kinematics::tests_support::bonn();
        let rig = RigSpec::default_rig();
        assert!(rig.geometry.holder_rim_height_mm > 0.0, "the default rig ships a rim");
        let k = for_rig(&rig);
        let ok = dirs
            .iter()
            .flat_map(|v| dirs.iter().map(move |l| (*l, *v)))
            .filter(|(l, v)| k.inverse(*l, *v, None).is_ok())
            .count();
        assert_eq!(ok, 6480);
        // nothing the arcs can reach (θ ≤ 80°) is shadowed, so the rim changes no plan,
        // not even the substitutes tried for blocked pairs
        for phi in [0.0, 30.0, 45.0, 90.0, 135.0] {
            let d = Direction::from_degrees(80.0, phi);
            assert!(k.inverse(d, Direction::from_degrees(30.0, phi + 180.0), None).is_ok());
            assert!(k.inverse(Direction::from_degrees(30.0, phi + 180.0), d, None).is_ok());
        }
        let deep = DEFAULT_RIG_TOML.replace("holder_rim_height_mm = 1.5", "holder_rim_height_mm = 6.0");
        let rig = RigSpec::parse(&deep, "deep.toml").unwrap();
        let k = for_rig(&rig);
        let mut shadowed = 0;
        for v in &dirs {
            for l in &dirs {
                if let Err(Infeasibility::HolderShadow { .. }) = k.inverse(*l, *v, None) {
                    shadowed += 1;
                    assert!(l.theta_deg() > 50.0 || v.theta_deg() > 50.0, "{l:?} {v:?}");
                }
            }
        }
        assert!(shadowed > 0);
    }
}
