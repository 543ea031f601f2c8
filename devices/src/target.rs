//! The sample holder's marker border: black square markers on a white frame around the
//! sample, used to find each raw frame's homography onto the sample plane.
//!
//! Shared by the simulator (which renders it) and the rectifier (which detects it), so both
//! agree on where every marker is. Lengths in millimetres, sample frame (z = 0 plane).

use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MarkerBorder {
    /// Width of the white frame around the sample (mm).
    pub border_mm: f64,
    /// Edge length of each square marker (mm); must fit inside the border.
    pub marker_mm: f64,
    /// Markers per side, corners included (≥ 2).
    pub markers_per_side: usize,
}

impl Default for MarkerBorder {
    fn default() -> Self {
        MarkerBorder {
            border_mm: 10.0,
            marker_mm: 6.0,
            markers_per_side: 5,
        }
    }
}

/// One marker: its centre on the sample plane and half its edge length (mm).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Marker {
    pub x: f64,
    pub y: f64,
    pub half: f64,
}

impl MarkerBorder {
    /// Marker centres for a square sample of edge `sample_mm`, counter-clockwise from the
    /// (−x, −y) corner; each lies on the centre line of the border strip.
    pub fn markers(&self, sample_mm: f64) -> Vec<Marker> {
        let r = sample_mm / 2.0 + self.border_mm / 2.0;
        let n = self.markers_per_side.max(2);
        let half = self.marker_mm / 2.0;
        let mut out = Vec::with_capacity(4 * (n - 1));
        let corners = [(-r, -r), (r, -r), (r, r), (-r, r)];
        for s in 0..4 {
            let (x0, y0) = corners[s];
            let (x1, y1) = corners[(s + 1) % 4];
            for k in 0..n - 1 {
                let t = k as f64 / (n - 1) as f64;
                out.push(Marker {
                    x: x0 + t * (x1 - x0),
                    y: y0 + t * (y1 - y0),
                    half,
                });
            }
        }
        out
    }

    /// Whether a sample-plane point lies on a marker (black) for a sample of edge `sample_mm`.
    pub fn is_marker(&self, sample_mm: f64, x: f64, y: f64) -> bool {
        let r = sample_mm / 2.0 + self.border_mm / 2.0;
        let n = self.markers_per_side.max(2);
        let step = 2.0 * r / (n - 1) as f64;
        let half = self.marker_mm / 2.0;
        let near = |c: f64| {
            let k = ((c + r) / step).round();
            (c - (-r + k * step)).abs() <= half && (0.0..=(n - 1) as f64).contains(&k)
        };
        ((x.abs() - r).abs() <= half && near(y)) || ((y.abs() - r).abs() <= half && near(x))
    }

    /// Half the edge of the whole holder (sample plus border), mm.
    pub fn outer_half(&self, sample_mm: f64) -> f64 {
        sample_mm / 2.0 + self.border_mm
    }

    /// Check the layout fits; `key` prefixes messages (e.g. `sample.border`).
    pub fn validate(&self, key: &str) -> Result<(), String> {
        if !(self.border_mm > 0.0 && self.border_mm.is_finite()) {
            return Err(format!("{key}.border_mm = {}: must be > 0", self.border_mm));
        }
        if !(self.marker_mm > 0.0 && self.marker_mm < self.border_mm) {
            return Err(format!(
                "{key}.marker_mm = {}: must be in (0, border_mm = {})",
                self.marker_mm, self.border_mm
            ));
        }
        if !(2..=64).contains(&self.markers_per_side) {
            return Err(format!(
                "{key}.markers_per_side = {}: valid range is 2 ..= 64",
                self.markers_per_side
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn markers_are_where_is_marker_says() {
        let b = MarkerBorder::default();
        let ms = b.markers(60.0);
        assert_eq!(ms.len(), 16);
        for m in &ms {
            assert!(b.is_marker(60.0, m.x, m.y));
            assert!(b.is_marker(60.0, m.x + 0.9 * m.half, m.y - 0.9 * m.half));
        }
        assert!(!b.is_marker(60.0, 0.0, 0.0));
        assert!(!b.is_marker(60.0, 35.0, 7.5), "between two markers");
    }
}
