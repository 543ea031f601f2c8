//! A checkerboard on a wedge: the target plane tilted by a known angle relative to the
//! turntable, so that turning the turntable swings the tilt direction.
//!
//! A two-arm rig tilts a flat target about one camera axis only (the camera arc; the
//! turntable turns the target in its own plane), so every target plane contains the
//! camera's x direction — a critical configuration of Zhang's method (Sturm–Maybank) that
//! leaves the principal point across the tilt axis undetermined on a long lens. A wedge
//! breaks it: its plane's normal leans toward the turntable's azimuth, which the turntable
//! turns relative to the camera arc.
//!
//! Geometry ([`WedgeSpec`]): the plane passes through the sample centre and its normal leans
//! by `slope_deg` from the turntable axis (+z) toward the sample-frame azimuth
//! `azimuth_deg` (from +x toward +y); it is the simulator's `plane` height field. The board
//! is printed as seen from above: a board point (x, y) of the flat board's coordinates lies
//! at (x, y, −tan(slope)·(x cos(azimuth) + y sin(azimuth))) ([`WedgeSpec::lift`]), so along
//! the slope its squares are 1 / cos(slope) longer on the plane. The intrinsics fit needs
//! true in-plane coordinates ([`WedgeSpec::in_plane`]): the lifted point turned about the
//! plane's level line (through the origin) into z = 0.

use serde::{Deserialize, Serialize};

/// Steepest wedge accepted (degrees); the simulator's `plane` height field has the same limit.
pub const MAX_WEDGE_SLOPE_DEG: f64 = 60.0;

/// The wedge under a planar target (recipe key `wedge = { slope_deg, azimuth_deg }`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WedgeSpec {
    /// Angle between the target plane and the turntable (degrees), 0 ≤ slope < 60.
    pub slope_deg: f64,
    /// Sample-frame azimuth (degrees, from +x toward +y) toward which the plane's normal
    /// leans, i.e. where the plane descends.
    #[serde(default)]
    pub azimuth_deg: f64,
}

impl WedgeSpec {
    /// Why the wedge is unusable, if it is.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.slope_deg.is_finite() && (0.0..MAX_WEDGE_SLOPE_DEG).contains(&self.slope_deg)) {
            return Err(format!(
                "slope_deg = {}: valid range is 0 ≤ slope < {MAX_WEDGE_SLOPE_DEG}°",
                self.slope_deg
            ));
        }
        if !(self.azimuth_deg.is_finite() && self.azimuth_deg.abs() <= 360.0) {
            return Err(format!(
                "azimuth_deg = {}: valid range is −360 ..= 360°",
                self.azimuth_deg
            ));
        }
        Ok(())
    }

    /// Unit vector of the descent direction in the sample frame's xy plane.
    fn descent(&self) -> [f64; 2] {
        let a = self.azimuth_deg.to_radians();
        [a.cos(), a.sin()]
    }

    /// Unit normal of the target plane in the sample frame.
    pub fn normal(&self) -> [f64; 3] {
        let (s, [dx, dy]) = (self.slope_deg.to_radians(), self.descent());
        [s.sin() * dx, s.sin() * dy, s.cos()]
    }

    /// Sample-frame point (mm) of the printed board point `p` = (x, y): on the plane, above
    /// or below (x, y).
    pub fn lift(&self, p: [f64; 2]) -> [f64; 3] {
        let [dx, dy] = self.descent();
        let s = p[0] * dx + p[1] * dy;
        [p[0], p[1], -self.slope_deg.to_radians().tan() * s]
    }

    /// True in-plane coordinates (mm) of the printed board point `p`: [`Self::lift`] turned
    /// about the plane's level line through the origin into z = 0. Distances along the level
    /// line are kept; along the slope they grow by 1 / cos(slope).
    pub fn in_plane(&self, p: [f64; 2]) -> [f64; 2] {
        let [dx, dy] = self.descent();
        let s = p[0] * dx + p[1] * dy;
        let stretch = s * (1.0 / self.slope_deg.to_radians().cos() - 1.0);
        [p[0] + stretch * dx, p[1] + stretch * dy]
    }
}

/// Board point `p` turned by `r` quarter turns (counter-clockwise seen from +z): the
/// symmetries of a square board's grid, which a detector cannot tell apart.
pub fn quarter_turn(p: [f64; 2], r: u8) -> [f64; 2] {
    match r % 4 {
        0 => p,
        1 => [-p[1], p[0]],
        2 => [-p[0], -p[1]],
        _ => [p[1], -p[0]],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dist3(a: [f64; 3], b: [f64; 3]) -> f64 {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    }

    fn dist2(a: [f64; 2], b: [f64; 2]) -> f64 {
        (a[0] - b[0]).hypot(a[1] - b[1])
    }

    /// In-plane coordinates are an isometry of the lifted points (a planar target), the
    /// lifted points lie on the plane of the stated normal, and along the slope a 5 mm print
    /// pitch becomes 5 / cos(slope).
    #[test]
    fn in_plane_coordinates_are_isometric_to_the_points_on_the_wedge() {
        for (slope, az) in [(15.0, 0.0), (20.0, 37.0), (45.0, -120.0), (0.0, 10.0)] {
            let w = WedgeSpec {
                slope_deg: slope,
                azimuth_deg: az,
            };
            w.validate().unwrap();
            let n = w.normal();
            let pts: Vec<[f64; 2]> = (0..25)
                .map(|k| [(k % 5) as f64 * 7.0 - 14.0, (k / 5) as f64 * 6.0 - 11.0])
                .collect();
            for a in &pts {
                let pa = w.lift(*a);
                assert!(
                    (pa[0] * n[0] + pa[1] * n[1] + pa[2] * n[2]).abs() < 1e-12,
                    "on the plane"
                );
                for b in &pts {
                    let (d3, d2) = (dist3(pa, w.lift(*b)), dist2(w.in_plane(*a), w.in_plane(*b)));
                    assert!((d3 - d2).abs() < 1e-12, "slope {slope} az {az}: {d3} vs {d2}");
                }
            }
            let a = az.to_radians();
            let along = dist2(w.in_plane([0.0, 0.0]), w.in_plane([5.0 * a.cos(), 5.0 * a.sin()]));
            assert!((along - 5.0 / slope.to_radians().cos()).abs() < 1e-12, "{along}");
            let across = dist2(w.in_plane([0.0, 0.0]), w.in_plane([-5.0 * a.sin(), 5.0 * a.cos()]));
            assert!((across - 5.0).abs() < 1e-12, "{across}");
        }
    }

    #[test]
    fn bad_wedges_are_refused_and_quarter_turns_compose() {
        for (s, a) in [
            (60.0, 0.0),
            (75.0, 0.0),
            (-1.0, 0.0),
            (f64::NAN, 0.0),
            (15.0, f64::INFINITY),
        ] {
            let e = WedgeSpec {
                slope_deg: s,
                azimuth_deg: a,
            }
            .validate()
            .unwrap_err();
            assert!(e.contains("valid range"), "{e}");
        }
        let p = [3.0, -2.0];
        assert_eq!(quarter_turn(quarter_turn(p, 1), 3), p);
        assert_eq!(quarter_turn(p, 1), [2.0, 3.0]);
        assert_eq!(quarter_turn(p, 2), quarter_turn(quarter_turn(p, 1), 1));
    }
}
