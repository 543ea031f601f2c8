//! What `gonio fit` reads: a native dataset (every measured pair, held in memory) or a CSV
//! table of BRDF values, turned into [`Observations`].
//!
//! **Units.** A fit needs BRDF values (1/sr). A dataset whose manifest `values` start with
//! "BRDF" (an acquisition developed with a white-standard calibration) is used as it is.
//! Any other dataset (a `gonio sim btf`, an uncalibrated acquisition) needs a white
//! standard measured over the same sweep and image size (`--white DIR`, albedo
//! `--white-albedo`, 0.9 for the simulator's `white-standard`): per texel and pair,
//! `f = value · (ρ/π) / white`, which divides out the lamp's irradiance, the cosine, the
//! distance and the sensor's scale exactly where the two samples share the geometry (same
//! `size_mm` and rig). This is the calibration a real gonioreflectometer does with its
//! reference tile (`develop/brdf.rs`).
//!
//! **Directions** are the sweep's nominal ones (the sample's centre seen from the rig's
//! distance). A texel off the centre sees the lamp and camera up to `atan(size/2 / d)`
//! away from them (1.7° for a 60 mm sample at 1 m); the fit of a lobe much narrower than
//! that is blurred accordingly (see docs/guide/fitting.md).

use super::{FitError, Observations, Rgb};
use crate::compress::DatasetViews;
use gonio_devices::{Direction, Vec3};
use std::path::{Path, PathBuf};

/// Largest dataset held in memory (data + white, f32).
pub const MEMORY_BUDGET: usize = 1 << 30;

/// The white standard that calibrates a dataset.
#[derive(Clone, Debug)]
pub struct WhiteRef {
    pub dir: PathBuf,
    /// Its albedo (Lambertian).
    pub albedo: f64,
}

/// One measured pair of a dataset, in memory.
#[derive(Clone, Debug)]
pub struct Pair {
    pub light: usize,
    pub view: usize,
    pub l: Vec3,
    pub v: Vec3,
    /// Interleaved RGB per texel, the dataset's units.
    pub data: Vec<f32>,
    /// `value = f · gain` per texel and channel (the white standard's value over ρ/π);
    /// `None` when the values are BRDF values already.
    pub gain: Option<Vec<f32>>,
}

/// A dataset in memory with its calibration.
#[derive(Clone, Debug)]
pub struct Loaded {
    pub input: String,
    pub width: usize,
    pub height: usize,
    pub lights_deg: Vec<[f64; 2]>,
    pub views_deg: Vec<[f64; 2]>,
    /// Measured pairs with both directions above the horizon, view-major.
    pub pairs: Vec<Pair>,
    /// What the values are, from the manifest.
    pub values: String,
    pub calibrated_by: Option<PathBuf>,
    /// Where the texels lie, when the manifest says (see the module docs).
    pub geometry: Option<Geometry>,
}

/// The rig's distances and the sample's size (mm): each texel's own directions (the
/// decoder of the SVBRDF file uses the same type).
pub use crate::compress::svbrdf::Geometry;

impl Geometry {
    fn from_manifest(rig: &serde_json::Value, sample: &serde_json::Value) -> Option<Geometry> {
        let g = Geometry {
            camera_distance_mm: rig.get("geometry")?.get("camera_distance_mm")?.as_f64()?,
            light_distance_mm: rig.get("geometry")?.get("light_distance_mm")?.as_f64()?,
            size_mm: sample.get("size_mm")?.as_f64()?,
        };
        let ok = |x: f64| x.is_finite() && x > 0.0;
        (ok(g.camera_distance_mm) && ok(g.light_distance_mm) && ok(g.size_mm) && g.size_mm < g.camera_distance_mm)
            .then_some(g)
    }
}

fn dir_of(d: [f64; 2]) -> Vec3 {
    Direction::from_degrees(d[0], d[1]).vector()
}

fn input_err(input: &str, reason: impl Into<String>) -> FitError {
    FitError::Input {
        input: input.into(),
        reason: reason.into(),
    }
}

/// Whether a manifest's `values` are BRDF values already.
pub fn values_are_brdf(values: &str) -> bool {
    values.trim_start().starts_with("BRDF")
}

/// Open a dataset directory with its calibration and read every measured pair.
pub fn load_dataset(dir: &Path, white: Option<&WhiteRef>) -> Result<Loaded, FitError> {
    let input = dir.display().to_string();
    if !dir.join("manifest.json").is_file() {
        return Err(input_err(
            &input,
            "not a gonio dataset (no manifest.json); give a dataset directory or a .csv table of \
             theta_l,phi_l,theta_v,phi_v,r,g,b",
        ));
    }
    let ds = DatasetViews::open(dir).map_err(|source| FitError::Dataset {
        input: input.clone(),
        source,
    })?;
    let values = ds.header.values.clone();
    let white_ds = match white {
        None if values_are_brdf(&values) => None,
        None => {
            return Err(input_err(
                &input,
                format!(
                    "its values are not BRDF values (manifest: \"{values}\"); give --white DIR, a dataset of \
                     the white standard over the same sweep and size (e.g. `gonio sim btf --sample white-standard`)"
                ),
            ))
        }
        Some(w) => {
            let wi = w.dir.display().to_string();
            if !(w.albedo.is_finite() && w.albedo > 0.0 && w.albedo <= 1.0) {
                return Err(FitError::Options {
                    what: format!("--white-albedo {}", w.albedo),
                    reason: "the white standard's albedo must be in (0, 1]".into(),
                });
            }
            if !w.dir.join("manifest.json").is_file() {
                return Err(input_err(&wi, "--white: not a gonio dataset (no manifest.json)"));
            }
            let wd = DatasetViews::open(&w.dir).map_err(|source| FitError::Dataset {
                input: wi.clone(),
                source,
            })?;
            if wd.lights_deg != ds.lights_deg || wd.views_deg != ds.views_deg {
                return Err(input_err(
                    &wi,
                    format!(
                        "--white: its sweep differs from {input}'s; measure the white standard over the same sweep"
                    ),
                ));
            }
            if (wd.width, wd.height) != (ds.width, ds.height) {
                return Err(input_err(
                    &wi,
                    format!(
                        "--white: images are {}×{}, {input}'s are {}×{}",
                        wd.width, wd.height, ds.width, ds.height
                    ),
                ));
            }
            Some(wd)
        }
    };
    let bytes = ds.n_measured() * ds.texels() * 3 * 4 * if white_ds.is_some() { 2 } else { 1 };
    if bytes > MEMORY_BUDGET {
        return Err(input_err(
            &input,
            format!(
                "{} MiB of images to hold ({} pairs × {} texels); the fit holds at most {} MiB: \
                 fit a smaller rendering (`gonio sim btf --size`) or a crop",
                bytes >> 20,
                ds.n_measured(),
                ds.texels(),
                MEMORY_BUDGET >> 20
            ),
        ));
    }
    let albedo_pi = white.map_or(1.0, |w| w.albedo / std::f64::consts::PI) as f32;
    let mut pairs = Vec::new();
    for view in 0..ds.n_views() {
        for light in 0..ds.n_lights() {
            let (l, v) = (dir_of(ds.lights_deg[light]), dir_of(ds.views_deg[view]));
            if l.z <= 1e-9 || v.z <= 1e-9 {
                continue;
            }
            let Some(data) = ds.read_image(light, view).map_err(|source| FitError::Dataset {
                input: input.clone(),
                source,
            })?
            else {
                continue;
            };
            let gain = match &white_ds {
                None => None,
                Some(wd) => {
                    let Some(w) = wd.read_image(light, view).map_err(|source| FitError::Dataset {
                        input: wd.dir.display().to_string(),
                        source,
                    })?
                    else {
                        continue; // the white standard lacks this pair: not calibrated
                    };
                    Some(w.iter().map(|x| x / albedo_pi).collect())
                }
            };
            pairs.push(Pair {
                light,
                view,
                l,
                v,
                data,
                gain,
            });
        }
    }
    Ok(Loaded {
        input,
        width: ds.width,
        height: ds.height,
        lights_deg: ds.lights_deg.clone(),
        views_deg: ds.views_deg.clone(),
        pairs,
        geometry: Geometry::from_manifest(&ds.header.rig, &ds.header.sample),
        values,
        calibrated_by: white.map(|w| w.dir.clone()),
    })
}

impl Loaded {
    pub fn texels(&self) -> usize {
        self.width * self.height
    }

    /// The averaged BRDF of a homogeneous sample: per pair and channel
    /// `Σ_t value / Σ_t gain` (a ratio of sums: the white's per-texel noise averages out).
    /// Pairs where the white standard saw nothing (shadowed, or 0) are left out.
    pub fn averaged(&self) -> Observations {
        let mut o = Observations::default();
        for p in &self.pairs {
            let mut num = [0.0f64; 3];
            let mut den = [0.0f64; 3];
            for t in 0..self.texels() {
                for c in 0..3 {
                    num[c] += p.data[3 * t + c] as f64;
                    den[c] += p.gain.as_ref().map_or(1.0, |g| g[3 * t + c] as f64);
                }
            }
            if den.iter().all(|d| *d > 0.0) {
                o.push(p.l, p.v, [0, 1, 2].map(|c| num[c] / den[c]));
            }
        }
        o
    }

    /// The observations of texel `t` at its own directions (see the module docs; pairs
    /// where its white value is 0 left out).
    pub fn texel(&self, t: usize) -> Observations {
        let mut o = Observations::default();
        for p in &self.pairs {
            let v: Rgb = [0, 1, 2].map(|c| p.data[3 * t + c] as f64);
            let (dl, dv) = match &self.geometry {
                Some(g) => g.texel_dirs(p.l, p.v, t, self.width, self.height),
                None => (p.l, p.v),
            };
            if dl.z <= 1e-9 || dv.z <= 1e-9 {
                continue;
            }
            match &p.gain {
                None => o.push(dl, dv, v),
                Some(g) => {
                    let g: Rgb = [0, 1, 2].map(|c| g[3 * t + c] as f64);
                    if g.iter().all(|x| *x > 0.0) {
                        o.push(dl, dv, [0, 1, 2].map(|c| v[c] / g[c]));
                    }
                }
            }
        }
        o
    }

    /// Per pair and channel, the gain over the sample as a plane `a + b·u + c·w`
    /// (`u`, `w` the texel centre's position in [−½, ½], least squares; `[1, 0, 0]` for
    /// BRDF data): what the per-texel fit's decoder multiplies a BRDF value by to give the
    /// dataset's units. A plane, not one number, because the lamp's cosine changes across
    /// the sample: ±12 % over a 60 mm sample at θ_l = 80° and 1.2 m.
    pub fn gain_planes(&self) -> Vec<[[f32; 3]; 3]> {
        let (w, h) = (self.width, self.height);
        let coord = |i: usize, n: usize| (i as f64 + 0.5) / n as f64 - 0.5;
        let su2: f64 = (0..w).map(|i| coord(i, w).powi(2)).sum::<f64>() * h as f64;
        let sw2: f64 = (0..h).map(|j| coord(j, h).powi(2)).sum::<f64>() * w as f64;
        let n = (w * h).max(1) as f64;
        self.pairs
            .iter()
            .map(|p| match &p.gain {
                None => [[1.0, 0.0, 0.0]; 3],
                Some(g) => std::array::from_fn(|c| {
                    let (mut s, mut su, mut sw) = (0.0, 0.0, 0.0);
                    for j in 0..h {
                        for i in 0..w {
                            let x = g[3 * (j * w + i) + c] as f64;
                            s += x;
                            su += x * coord(i, w);
                            sw += x * coord(j, h);
                        }
                    }
                    let slope = |num: f64, den: f64| if den > 0.0 { num / den } else { 0.0 };
                    [(s / n) as f32, slope(su, su2) as f32, slope(sw, sw2) as f32]
                }),
            })
            .collect()
    }
}

/// Read a CSV table of BRDF values: `theta_l,phi_l,theta_v,phi_v,r,g,b` in degrees and
/// 1/sr, one pair a line; `#` comments and one header line (non-numeric) are skipped.
pub fn load_csv(path: &Path) -> Result<Observations, FitError> {
    let input = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| FitError::Io {
        input: input.clone(),
        source,
    })?;
    let mut o = Observations::default();
    let mut header_seen = false;
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let cols: Vec<&str> = line.split(',').map(str::trim).collect();
        let nums: Result<Vec<f64>, _> = cols.iter().map(|c| c.parse::<f64>()).collect();
        let nums = match nums {
            Ok(n) => n,
            Err(_) if !header_seen && o.is_empty() => {
                header_seen = true;
                continue;
            }
            Err(e) => return Err(input_err(&input, format!("line {}: {e}: `{line}`", i + 1))),
        };
        if nums.len() != 7 {
            return Err(input_err(
                &input,
                format!(
                    "line {}: {} columns, expected 7 (theta_l,phi_l,theta_v,phi_v,r,g,b)",
                    i + 1,
                    nums.len()
                ),
            ));
        }
        if nums[0] < 0.0 || nums[0] >= 90.0 || nums[2] < 0.0 || nums[2] >= 90.0 {
            return Err(input_err(
                &input,
                format!(
                    "line {}: θ must be in [0, 90) degrees, got {} and {}",
                    i + 1,
                    nums[0],
                    nums[2]
                ),
            ));
        }
        o.push(
            dir_of([nums[0], nums[1]]),
            dir_of([nums[2], nums[3]]),
            [nums[4], nums[5], nums[6]],
        );
    }
    Ok(o)
}
