//! Sweeps: the set of directions to measure and the (light, view) pairs built from them.
//!
//! The Bonn 81-direction set is the default (conventions.md); explicit lists come from TOML
//! or CSV files. A measurement's canonical index is `view_index · L + light_index`.

use gonio_devices::Direction;
use serde::{Deserialize, Serialize};
use std::path::Path;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum SweepError {
    #[error("cannot read sweep file {file}: {source}")]
    Io { file: String, source: std::io::Error },
    #[error("sweep file {file}: {message}")]
    Parse { file: String, message: String },
    #[error("sweep {file}: entry {entry} ({what}): {message}")]
    Invalid {
        file: String,
        entry: usize,
        what: String,
        message: String,
    },
    #[error(
        "unknown sweep `{0}`: use `bonn81`, `uniform15`, `bonn151`, `fibonacci:N`, or a path to a .toml/.csv file"
    )]
    Unknown(String),
}

/// A sweep: light and view direction lists; every pair is measured.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Sweep {
    pub name: String,
    pub lights: Vec<Direction>,
    pub views: Vec<Direction>,
}

/// A (light, view) pair with its canonical index.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pair {
    pub index: usize,
    pub light_index: usize,
    pub view_index: usize,
    pub light: Direction,
    pub view: Direction,
}

/// The Bonn 81 directions in canonical order (θ ascending, then φ ascending).
pub fn bonn81() -> Vec<Direction> {
    let mut v = Vec::with_capacity(81);
    for (t, n) in [(0.0, 1), (15.0, 6), (30.0, 12), (45.0, 18), (60.0, 20), (75.0, 24)] {
        for k in 0..n {
            v.push(Direction::from_degrees(t, k as f64 * 360.0 / n as f64));
        }
    }
    v
}

/// A near-uniform 15° set: θ rings every 15° up to 75°, azimuth steps so neighbours on a
/// ring are about 15° apart (80 directions; the dome rig's default layout).
pub fn uniform15() -> Vec<Direction> {
    gonio_devices::kinematics::dome::uniform15()
}

/// Bonn's Dome 1 layout, 151 directions (the UBO2014 data; the `dome151` rig's cameras
/// and lamps): see `gonio_devices::kinematics::dome::bonn_dome1`.
pub fn bonn151() -> Vec<Direction> {
    gonio_devices::kinematics::dome::bonn_dome1()
}

/// `n` directions on a spherical Fibonacci lattice over the hemisphere up to `max_theta_deg`.
pub fn fibonacci(n: usize, max_theta_deg: f64) -> Vec<Direction> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let cmin = max_theta_deg.to_radians().cos();
    (0..n)
        .map(|i| {
            let z = 1.0 - (1.0 - cmin) * (i as f64 + 0.5) / n as f64;
            Direction::from_radians(z.acos(), golden * i as f64)
        })
        .collect()
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SweepFile {
    name: Option<String>,
    /// `[[θ, φ], …]` in degrees; used for both lights and views unless they are given.
    directions: Option<Vec<[f64; 2]>>,
    lights: Option<Vec<[f64; 2]>>,
    views: Option<Vec<[f64; 2]>>,
}

impl Sweep {
    /// The light and view directions as (θ, φ) in degrees, the form datasets, compressed
    /// files and priors record them in.
    pub fn directions_deg(&self) -> (Vec<[f64; 2]>, Vec<[f64; 2]>) {
        let deg = |v: &[Direction]| v.iter().map(|d| [d.theta_deg(), d.phi_deg()]).collect::<Vec<_>>();
        (deg(&self.lights), deg(&self.views))
    }

    /// The sweep as a dataset manifest records it (`name`, `lights_deg`, `views_deg` in
    /// degrees, and the policy for pairs the rig cannot measure).
    pub fn manifest_json(&self, policy: impl Serialize) -> serde_json::Value {
        let (lights, views) = self.directions_deg();
        serde_json::json!({
            "name": self.name,
            "lights_deg": lights,
            "views_deg": views,
            "policy": policy,
        })
    }

    /// Every light × view pair, in canonical index order.
    pub fn pairs(&self) -> Vec<Pair> {
        let l = self.lights.len();
        let mut out = Vec::with_capacity(l * self.views.len());
        for (vi, v) in self.views.iter().enumerate() {
            for (li, li_dir) in self.lights.iter().enumerate() {
                out.push(Pair {
                    index: vi * l + li,
                    light_index: li,
                    view_index: vi,
                    light: *li_dir,
                    view: *v,
                });
            }
        }
        out
    }

    pub fn len(&self) -> usize {
        self.lights.len() * self.views.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// `bonn81`, `uniform15`, `bonn151` (alias `dome151`), `fibonacci:N`, or a TOML/CSV file.
    pub fn resolve(spec: &str) -> Result<Sweep, SweepError> {
        let same = |name: &str, d: Vec<Direction>| Sweep {
            name: name.into(),
            lights: d.clone(),
            views: d,
        };
        match spec {
            "bonn81" | "bonn" => return Ok(same("bonn81", bonn81())),
            "uniform15" => return Ok(same("uniform15", uniform15())),
            "bonn151" | "dome151" => return Ok(same("bonn151", bonn151())),
            _ => {}
        }
        if let Some(n) = spec.strip_prefix("fibonacci:") {
            let n: usize = n
                .parse()
                .ok()
                .filter(|n| (1..=10_000).contains(n))
                .ok_or_else(|| SweepError::Invalid {
                    file: spec.into(),
                    entry: 0,
                    what: "N".into(),
                    message: "fibonacci:N needs 1 ≤ N ≤ 10000".into(),
                })?;
            return Ok(same(spec, fibonacci(n, 80.0)));
        }
        let p = Path::new(spec);
        match p.extension().and_then(|e| e.to_str()) {
            Some("toml") | Some("csv") => Sweep::load(p),
            _ => Err(SweepError::Unknown(spec.into())),
        }
    }

    pub fn load(path: &Path) -> Result<Sweep, SweepError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| SweepError::Io {
            file: file.clone(),
            source,
        })?;
        let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("sweep").to_string();
        if path.extension().and_then(|e| e.to_str()) == Some("csv") {
            Self::parse_csv(&text, &file, &stem)
        } else {
            Self::parse_toml(&text, &file, &stem)
        }
    }

    /// TOML: `directions = [[θ, φ], …]` or `lights`/`views` lists (degrees).
    pub fn parse_toml(text: &str, file: &str, default_name: &str) -> Result<Sweep, SweepError> {
        let f: SweepFile = toml::from_str(text).map_err(|e| SweepError::Parse {
            file: file.into(),
            message: e.to_string(),
        })?;
        let lights = f.lights.or_else(|| f.directions.clone());
        let views = f.views.or(f.directions);
        let (Some(lights), Some(views)) = (lights, views) else {
            return Err(SweepError::Parse {
                file: file.into(),
                message: "give `directions = [[θ, φ], …]`, or both `lights` and `views` (degrees)".into(),
            });
        };
        Ok(Sweep {
            name: f.name.unwrap_or_else(|| default_name.into()),
            lights: check_list(&lights, file, "light")?,
            views: check_list(&views, file, "view")?,
        })
    }

    /// CSV: one `theta,phi` per line (degrees), `#` comments, optional header; the same list
    /// serves as lights and views.
    pub fn parse_csv(text: &str, file: &str, name: &str) -> Result<Sweep, SweepError> {
        let mut raw = Vec::new();
        for (ln, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') || line.starts_with(|c: char| c.is_alphabetic()) {
                continue;
            }
            let parts: Vec<&str> = line.split(',').map(str::trim).collect();
            let parse = |s: &str| s.parse::<f64>().ok();
            match (
                parts.len(),
                parts.first().and_then(|s| parse(s)),
                parts.get(1).and_then(|s| parse(s)),
            ) {
                (2, Some(t), Some(p)) => raw.push([t, p]),
                _ => {
                    return Err(SweepError::Parse {
                        file: file.into(),
                        message: format!("line {}: expected `theta,phi` in degrees, got {line:?}", ln + 1),
                    })
                }
            }
        }
        let d = check_list(&raw, file, "direction")?;
        Ok(Sweep {
            name: name.into(),
            lights: d.clone(),
            views: d,
        })
    }
}

/// Validate a list of (θ, φ) degrees: ranges and duplicates, naming the entry.
fn check_list(list: &[[f64; 2]], file: &str, what: &str) -> Result<Vec<Direction>, SweepError> {
    if list.is_empty() {
        return Err(SweepError::Invalid {
            file: file.into(),
            entry: 0,
            what: what.into(),
            message: "empty list".into(),
        });
    }
    let mut out: Vec<Direction> = Vec::with_capacity(list.len());
    for (i, &[t, p]) in list.iter().enumerate() {
        let bad = |message: String| SweepError::Invalid {
            file: file.into(),
            entry: i,
            what: format!("{what} [{t}, {p}]"),
            message,
        };
        if !(t.is_finite() && (0.0..90.0).contains(&t)) {
            return Err(bad("θ must be in [0°, 90°)".into()));
        }
        if !(p.is_finite() && (0.0..360.0).contains(&p)) {
            return Err(bad("φ must be in [0°, 360°)".into()));
        }
        let d = Direction::from_degrees(t, p);
        if let Some(j) = out.iter().position(|o| o.angle_to(d) < 1e-9) {
            return Err(bad(format!("duplicate of entry {j}")));
        }
        out.push(d);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bonn_has_81_and_canonical_index() {
        let s = Sweep::resolve("bonn81").unwrap();
        assert_eq!(s.lights.len(), 81);
        let pairs = s.pairs();
        assert_eq!(pairs.len(), 6561);
        let p = pairs[5 * 81 + 7];
        assert_eq!((p.view_index, p.light_index, p.index), (5, 7, 5 * 81 + 7));
        assert_eq!(pairs.iter().filter(|p| p.light == p.view).count(), 81);
    }

    #[test]
    fn bad_lists_name_the_entry() {
        let e = Sweep::parse_toml("directions = [[0, 0], [95, 10]]", "s.toml", "s")
            .unwrap_err()
            .to_string();
        assert!(e.contains("s.toml") && e.contains("entry 1") && e.contains("θ"), "{e}");
        let e = Sweep::parse_toml("directions = [[30, 10], [30, 10]]", "s.toml", "s")
            .unwrap_err()
            .to_string();
        assert!(e.contains("duplicate of entry 0"), "{e}");
        let e = Sweep::parse_csv("0,0\n15,abc\n", "d.csv", "d").unwrap_err().to_string();
        assert!(e.contains("line 2"), "{e}");
        let ok = Sweep::parse_csv("theta,phi\n0,0\n45,90\n", "d.csv", "d").unwrap();
        assert_eq!(ok.len(), 4);
    }

    #[test]
    fn named_sets_have_their_sizes() {
        assert_eq!(Sweep::resolve("uniform15").unwrap().lights.len(), 80);
        let b = Sweep::resolve("bonn151").unwrap();
        assert_eq!((b.name.as_str(), b.lights.len(), b.len()), ("bonn151", 151, 22801));
        assert_eq!(Sweep::resolve("dome151").unwrap().lights, b.lights);
        let e = Sweep::resolve("bonn152").unwrap_err().to_string();
        assert!(e.contains("bonn151"), "{e}");
    }

    #[test]
    fn fibonacci_is_on_the_hemisphere() {
        let d = fibonacci(100, 80.0);
        assert!(d.iter().all(|x| x.theta < 80f64.to_radians() + 1e-12));
    }
}
