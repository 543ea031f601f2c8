//! Synthetic samples: the TOML files under `simulator/samples/`.
//!
//! A sample is a square of `size_mm` with a height field (mesostructure), a material map
//! (which BRDF at which texel, plus a tint that varies the albedo), and the marker border of
//! its holder. [`SampleSpec`] is the file; [`Sample`] is the built, ready-to-render form.
//!
//! What a sample does not need is not built: a flat sample has no height grid at all
//! ([`Surface::Flat`]), a uniform one no material map.

use crate::brdf::{BrdfModel, Rgb};
use crate::noise::{fbm, value_noise};
use gonio_devices::coded_board::CodedBoardSpec;
use gonio_devices::target::MarkerBorder;
use gonio_devices::Vec3;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Built-in samples, embedded so a fresh machine needs no files.
pub const BUILTIN: &[(&str, &str)] = &[
    ("wallpaper", include_str!("../samples/wallpaper.toml")),
    ("fabric", include_str!("../samples/fabric.toml")),
    ("corduroy", include_str!("../samples/corduroy.toml")),
    ("leather", include_str!("../samples/leather.toml")),
    ("white-standard", include_str!("../samples/white-standard.toml")),
    ("calibration-target", include_str!("../samples/calibration-target.toml")),
    (
        "calibration-target-wedge",
        include_str!("../samples/calibration-target-wedge.toml"),
    ),
    (
        "calibration-target-large",
        include_str!("../samples/calibration-target-large.toml"),
    ),
    ("colour-target", include_str!("../samples/colour-target.toml")),
    ("mirror", include_str!("../samples/mirror.toml")),
    ("coded-target", include_str!("../samples/coded-target.toml")),
    ("brushed-metal", include_str!("../samples/brushed-metal.toml")),
];

/// The default sample of the main job.
pub const DEFAULT_SAMPLE: &str = "wallpaper";

#[derive(Debug, Error)]
pub enum SampleError {
    #[error("cannot read sample file {file}: {source}")]
    Io { file: String, source: std::io::Error },
    #[error("sample file {file}: {message}")]
    Parse { file: String, message: String },
    #[error("sample file {file}: key `{key}`: {message}")]
    Invalid { file: String, key: String, message: String },
    #[error("unknown built-in sample `{name}`; built-in samples: {known}; or give a path to a .toml file")]
    Unknown { name: String, known: String },
}

/// Height field (mesostructure) description. Heights in mm around the mean plane z = 0.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum HeightSpec {
    Flat,
    /// Plain weave: warp and weft threads of `period_mm` passing over and under each other.
    Weave {
        period_mm: f64,
        amplitude_mm: f64,
    },
    /// Raised pattern (embossed wallpaper): smooth diamond bumps of `period_mm`.
    Emboss {
        period_mm: f64,
        amplitude_mm: f64,
    },
    /// Parallel ribs along y (corduroy) of `period_mm`.
    Ribs {
        period_mm: f64,
        amplitude_mm: f64,
    },
    /// Fractal noise (leather grain).
    Noise {
        scale_mm: f64,
        amplitude_mm: f64,
        octaves: u32,
        seed: u64,
    },
    /// A tilted plane through the sample centre (a target on a wedge): the normal leans by
    /// `slope_deg` from +z toward the sample-frame azimuth `azimuth_deg` (from +x toward
    /// +y), i.e. `z = −tan(slope)·(x cos(azimuth) + y sin(azimuth))`. The material map stays
    /// a function of the sample-frame (x, y), so on the plane itself a pattern is stretched
    /// by 1 / cos(slope) along the slope. Rendered exactly: a bilinear height grid
    /// reproduces a plane, and its normal is the analytic one. Slopes up to 60° (steeper
    /// planes hide themselves from most of the hemisphere).
    Plane {
        slope_deg: f64,
        #[serde(default)]
        azimuth_deg: f64,
    },
    /// A grayscale PNG (black = −amplitude/2, white = +amplitude/2), stretched over the sample.
    Image {
        path: PathBuf,
        amplitude_mm: f64,
    },
}

/// Material map: which material index at which texel.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum MapSpec {
    /// Material 0 everywhere.
    Uniform,
    /// Two materials following the weave: warp threads 0, weft threads 1.
    Weave { period_mm: f64 },
    /// Materials 0 (ridges) and 1 (grooves) following ribs of `period_mm`.
    Ribs { period_mm: f64 },
    /// Material 1 where fractal noise exceeds `threshold`, else 0 (pores, prints).
    Noise { scale_mm: f64, threshold: f64, seed: u64 },
    /// Material 1 on a pattern of the emboss period (printed motif), else 0.
    Emboss { period_mm: f64 },
    /// Squares of `period_mm` alternating materials 0 and 1.
    Checker { period_mm: f64 },
    /// A colour chart: `cols × rows` square patches of `pitch_mm` centred on the sample,
    /// patch (column i, row j) — row 0 at the +y edge — is material `j · cols + i`; outside
    /// the grid the surround, material `cols · rows`.
    Grid { cols: usize, rows: usize, pitch_mm: f64 },
    /// The coded-marker calibration board ([`CodedBoardSpec`]) centred on the sample:
    /// material 0 where it is white (and around it), 1 where it is black. Its edges fall on
    /// texel boundaries only if `pitch_mm`, the margin and the marker cells are multiples of
    /// the texel size (`size_mm / resolution`); the shipped `coded-target` is laid out so.
    CodedBoard {
        squares_x: usize,
        squares_y: usize,
        pitch_mm: f64,
        marker_mm: f64,
        #[serde(default)]
        first_id: usize,
    },
}

impl MapSpec {
    /// The coded board this map draws, if it is one.
    pub fn coded_board(&self) -> Option<CodedBoardSpec> {
        match *self {
            MapSpec::CodedBoard {
                squares_x,
                squares_y,
                pitch_mm,
                marker_mm,
                first_id,
            } => Some(CodedBoardSpec {
                squares_x,
                squares_y,
                pitch_mm,
                marker_mm,
                first_id,
            }),
            _ => None,
        }
    }
}

/// A disc painted over the material map: something lying on the sample (a clamp, tape, a
/// finger), for testing detectors on partly hidden targets.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Occluder {
    /// Centre on the sample plane (mm).
    pub center_mm: [f64; 2],
    pub radius_mm: f64,
    /// Index of the `[[material]]` it is made of.
    pub material: usize,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SampleSpec {
    pub name: String,
    #[serde(default)]
    pub description: String,
    /// Edge length of the square sample (mm).
    pub size_mm: f64,
    /// Resolution of the height and material grids (texels per side).
    #[serde(default = "default_resolution")]
    pub resolution: usize,
    pub height: HeightSpec,
    pub map: MapSpec,
    /// Relative albedo variation (0 = none): the tint is `1 + tint_amplitude·(noise − ½)·2`.
    #[serde(default)]
    pub tint_amplitude: f64,
    #[serde(default)]
    pub tint_scale_mm: Option<f64>,
    #[serde(default)]
    pub seed: u64,
    #[serde(rename = "material")]
    pub materials: Vec<BrdfModel>,
    #[serde(default)]
    pub border: MarkerBorder,
    /// Albedo of the white holder frame around the sample and of its black markers.
    #[serde(default = "default_frame_albedo")]
    pub frame_albedo: f64,
    #[serde(default = "default_marker_albedo")]
    pub marker_albedo: f64,
    /// The sample looks the same when turned about its normal or mirrored (an isotropic
    /// BRDF with no oriented texture or relief). Declared by the sample file, never
    /// inferred: `gonio plan --sample` and `gonio acquire` then measure one pair per
    /// (θ_l, θ_v, |φ_l − φ_v|) class and export reconstructs the others, which is only
    /// right if it is true.
    #[serde(default)]
    pub isotropic: bool,
    /// Discs painted over the map (`[[occluder]]`); none by default.
    #[serde(default, rename = "occluder")]
    pub occluders: Vec<Occluder>,
    /// Ground-truth rays per height-grid cell and axis (1 ..= 16; default 1). The truth is
    /// the mean over each texel's area, estimated with a stratified grid of rays: one per
    /// grid cell holds where shading varies little within a cell (the normal and the
    /// material are interpolated and looked up per cell). A lobe much narrower than the
    /// relief's change of normal across one cell varies within it, and the estimate needs
    /// more rays (docs/guide/hdr.md measures this on `brushed-metal`). Not written when 1, so
    /// other samples' manifests keep their bytes.
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub truth_rays_per_cell: usize,
}

fn one() -> usize {
    1
}

fn is_one(n: &usize) -> bool {
    *n == 1
}

/// Steepest plane a `plane` height field may have (degrees).
pub const MAX_PLANE_SLOPE_DEG: f64 = 60.0;

/// Unit normal of a `plane` height field (see [`HeightSpec::Plane`]).
pub fn plane_normal(slope_deg: f64, azimuth_deg: f64) -> Vec3 {
    let (s, a) = (slope_deg.to_radians(), azimuth_deg.to_radians());
    Vec3::new(s.sin() * a.cos(), s.sin() * a.sin(), s.cos())
}

fn default_resolution() -> usize {
    256
}
fn default_frame_albedo() -> f64 {
    0.8
}
fn default_marker_albedo() -> f64 {
    0.03
}

/// The height grid of a structured sample, with precomputed normals.
pub struct HeightGrid {
    pub n: usize,
    /// Texel size (mm).
    pub texel: f64,
    pub heights: Vec<f32>,
    pub normals: Vec<[f32; 3]>,
    pub min: f64,
    pub max: f64,
    /// The unit normal when the field is a plane through the origin (`plane` height kind):
    /// the renderer then intersects and shadows it analytically, with no ray march.
    pub plane: Option<Vec3>,
}

/// What the renderer intersects: the mean plane, or a height field.
pub enum Surface {
    Flat,
    Height(HeightGrid),
}

/// A built sample.
pub struct Sample {
    pub spec: SampleSpec,
    pub surface: Surface,
    /// Material index per texel; `None` when the sample has one material.
    pub material_map: Option<Vec<u8>>,
    /// RGB tint per texel; `None` when there is no albedo variation.
    pub tint: Option<Vec<f32>>,
}

impl SampleSpec {
    /// A built-in sample by name, or a TOML file by path.
    pub fn resolve(name_or_path: &str) -> Result<SampleSpec, SampleError> {
        if let Some((_, text)) = BUILTIN.iter().find(|(n, _)| *n == name_or_path) {
            return SampleSpec::parse(text, &format!("<built-in sample {name_or_path}>"), None);
        }
        let p = Path::new(name_or_path);
        if p.extension().is_some() || p.exists() {
            return SampleSpec::load(p);
        }
        Err(SampleError::Unknown {
            name: name_or_path.into(),
            known: BUILTIN.iter().map(|(n, _)| *n).collect::<Vec<_>>().join(", "),
        })
    }

    pub fn load(path: &Path) -> Result<SampleSpec, SampleError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| SampleError::Io {
            file: file.clone(),
            source,
        })?;
        SampleSpec::parse(&text, &file, path.parent())
    }

    /// Parse and validate; relative image paths resolve against `base`.
    pub fn parse(text: &str, file: &str, base: Option<&Path>) -> Result<SampleSpec, SampleError> {
        let mut spec: SampleSpec = toml::from_str(text).map_err(|e| SampleError::Parse {
            file: file.into(),
            message: e.to_string(),
        })?;
        if let (HeightSpec::Image { path, .. }, Some(b)) = (&mut spec.height, base) {
            if path.is_relative() {
                *path = b.join(&*path);
            }
        }
        spec.validate(file)?;
        Ok(spec)
    }

    fn validate(&self, file: &str) -> Result<(), SampleError> {
        let bad = |key: &str, message: String| SampleError::Invalid {
            file: file.into(),
            key: key.into(),
            message,
        };
        if !(self.size_mm > 0.0 && self.size_mm <= 1000.0) {
            return Err(bad("size_mm", format!("{}: valid range is (0, 1000] mm", self.size_mm)));
        }
        if !(8..=4096).contains(&self.resolution) {
            return Err(bad(
                "resolution",
                format!("{}: valid range is 8 ..= 4096", self.resolution),
            ));
        }
        if !(1..=16).contains(&self.truth_rays_per_cell) {
            return Err(bad(
                "truth_rays_per_cell",
                format!("{}: valid range is 1 ..= 16", self.truth_rays_per_cell),
            ));
        }
        if self.materials.is_empty() || self.materials.len() > 255 {
            return Err(bad(
                "material",
                format!("{} materials: need 1 ..= 255 [[material]] tables", self.materials.len()),
            ));
        }
        for (i, m) in self.materials.iter().enumerate() {
            m.validate()
                .map_err(|e| bad(&format!("material[{i}]"), e.to_string()))?;
        }
        let needs_two = !matches!(self.map, MapSpec::Uniform);
        if needs_two && self.materials.len() < 2 {
            return Err(bad(
                "map",
                "this map kind uses materials 0 and 1: add a second [[material]]".into(),
            ));
        }
        let pos = |key: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(bad(key, format!("{v}: must be > 0")))
            }
        };
        let amp = |key: &str, v: f64| {
            if v.is_finite() && v >= 0.0 && v <= self.size_mm / 4.0 {
                Ok(())
            } else {
                Err(bad(key, format!("{v}: valid range is 0 ..= size_mm/4")))
            }
        };
        match &self.height {
            HeightSpec::Flat => {}
            HeightSpec::Weave {
                period_mm,
                amplitude_mm,
            }
            | HeightSpec::Emboss {
                period_mm,
                amplitude_mm,
            }
            | HeightSpec::Ribs {
                period_mm,
                amplitude_mm,
            } => {
                pos("height.period_mm", *period_mm)?;
                amp("height.amplitude_mm", *amplitude_mm)?;
            }
            HeightSpec::Noise {
                scale_mm,
                amplitude_mm,
                octaves,
                ..
            } => {
                pos("height.scale_mm", *scale_mm)?;
                amp("height.amplitude_mm", *amplitude_mm)?;
                if !(1..=12).contains(octaves) {
                    return Err(bad("height.octaves", format!("{octaves}: valid range is 1 ..= 12")));
                }
            }
            HeightSpec::Plane { slope_deg, azimuth_deg } => {
                if !(slope_deg.is_finite() && (0.0..MAX_PLANE_SLOPE_DEG).contains(slope_deg)) {
                    return Err(bad(
                        "height.slope_deg",
                        format!("{slope_deg}: valid range is 0 ≤ slope < {MAX_PLANE_SLOPE_DEG}°"),
                    ));
                }
                if !(azimuth_deg.is_finite() && azimuth_deg.abs() <= 360.0) {
                    return Err(bad(
                        "height.azimuth_deg",
                        format!("{azimuth_deg}: valid range is −360 ..= 360°"),
                    ));
                }
            }
            HeightSpec::Image { path, amplitude_mm } => {
                amp("height.amplitude_mm", *amplitude_mm)?;
                if !path.exists() {
                    return Err(bad(
                        "height.path",
                        format!("height-field image {} does not exist", path.display()),
                    ));
                }
            }
        }
        match &self.map {
            MapSpec::Uniform => {}
            MapSpec::Grid { cols, rows, pitch_mm } => {
                pos("map.pitch_mm", *pitch_mm)?;
                // Saturating: a mutated file can ask for a grid whose patch count overflows
                // (found by `fuzz_sample_toml`; corpus `sample/grid_overflow.toml`).
                let needed = cols.saturating_mul(*rows).saturating_add(1);
                if needed > 256 {
                    // Patch indices are stored as u8 (one byte per map texel).
                    return Err(bad(
                        "map",
                        format!("a {cols} × {rows} grid has more than 255 patches; at most 255 are supported"),
                    ));
                }
                if *cols == 0 || *rows == 0 || needed > self.materials.len() {
                    return Err(bad(
                        "map",
                        format!(
                            "a {cols} × {rows} grid needs {needed} [[material]] tables (one per patch, then the surround), {} given",
                            self.materials.len()
                        ),
                    ));
                }
            }
            MapSpec::Weave { period_mm }
            | MapSpec::Ribs { period_mm }
            | MapSpec::Emboss { period_mm }
            | MapSpec::Checker { period_mm } => pos("map.period_mm", *period_mm)?,
            MapSpec::CodedBoard { .. } => {
                let board = self.map.coded_board().expect("a coded board");
                board.validate().map_err(|m| bad("map", m))?;
                if self.materials.len() < 2 {
                    return Err(bad(
                        "material",
                        "a coded board needs two [[material]] tables: white (0), then black (1)".into(),
                    ));
                }
                let [w, h] = board.size_mm();
                if w > self.size_mm + 1e-9 || h > self.size_mm + 1e-9 {
                    return Err(bad(
                        "map",
                        format!(
                            "the board is {w} × {h} mm, larger than the sample (size_mm = {}): it would be cut off",
                            self.size_mm
                        ),
                    ));
                }
            }
            MapSpec::Noise {
                scale_mm, threshold, ..
            } => {
                pos("map.scale_mm", *scale_mm)?;
                if !(0.0..=1.0).contains(threshold) {
                    return Err(bad("map.threshold", format!("{threshold}: valid range is 0 ..= 1")));
                }
            }
        }
        if !(0.0..1.0).contains(&self.tint_amplitude) {
            return Err(bad(
                "tint_amplitude",
                format!("{}: valid range is 0 ≤ a < 1", self.tint_amplitude),
            ));
        }
        for (k, v) in [
            ("frame_albedo", self.frame_albedo),
            ("marker_albedo", self.marker_albedo),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return Err(bad(k, format!("{v}: valid range is 0 ..= 1")));
            }
        }
        if self.marker_albedo >= self.frame_albedo {
            return Err(bad(
                "marker_albedo",
                "markers must be darker than the frame (marker_albedo < frame_albedo)".into(),
            ));
        }
        self.border.validate("border").map_err(|m| bad("border", m))?;
        for (k, o) in self.occluders.iter().enumerate() {
            if !(o.radius_mm.is_finite() && o.radius_mm > 0.0 && o.center_mm.iter().all(|c| c.is_finite())) {
                return Err(bad(
                    &format!("occluder[{k}]"),
                    format!(
                        "centre {:?}, radius {} mm: need a finite centre and a radius > 0",
                        o.center_mm, o.radius_mm
                    ),
                ));
            }
            if o.material >= self.materials.len() || o.material > 255 {
                return Err(bad(
                    &format!("occluder[{k}].material"),
                    format!(
                        "{}: there are {} [[material]] tables (indices 0 ..= {})",
                        o.material,
                        self.materials.len(),
                        self.materials.len().saturating_sub(1)
                    ),
                ));
            }
        }
        Ok(())
    }

    /// Build grids: only what the spec needs.
    pub fn build(self) -> Result<Sample, SampleError> {
        let n = self.resolution;
        let texel = self.size_mm / n as f64;
        let centre = |i: usize| (i as f64 + 0.5) * texel - self.size_mm / 2.0;
        let surface = match &self.height {
            HeightSpec::Flat => Surface::Flat,
            h => {
                let img = match h {
                    HeightSpec::Image { path, .. } => Some(
                        image::open(path)
                            .map_err(|e| SampleError::Invalid {
                                file: self.name.clone(),
                                key: "height.path".into(),
                                message: format!("cannot read height-field image {}: {e}", path.display()),
                            })?
                            .to_luma16(),
                    ),
                    _ => None,
                };
                let mut heights = vec![0f32; n * n];
                for j in 0..n {
                    for i in 0..n {
                        // row j grows with −y (conventions: row 0 is the +y edge)
                        let (x, y) = (centre(i), -centre(j));
                        heights[j * n + i] = match (h, &img) {
                            (HeightSpec::Image { amplitude_mm, .. }, Some(im)) => {
                                let px = (i * im.width() as usize / n) as u32;
                                let py = (j * im.height() as usize / n) as u32;
                                let v = im.get_pixel(px, py).0[0] as f64 / 65535.0;
                                (amplitude_mm * (v - 0.5)) as f32
                            }
                            _ => height_at(h, x, y) as f32,
                        };
                    }
                }
                let (min, max) = heights.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &h| {
                    (a.min(h as f64), b.max(h as f64))
                });
                let normals = match *h {
                    // The analytic normal: central differences halve the slope on the edge
                    // texels (one-sided there), which a relief never notices but a plane's
                    // shading would.
                    HeightSpec::Plane { slope_deg, azimuth_deg } => {
                        let v = plane_normal(slope_deg, azimuth_deg);
                        vec![[v.x as f32, v.y as f32, v.z as f32]; n * n]
                    }
                    _ => normals(&heights, n, texel),
                };
                let plane = match *h {
                    HeightSpec::Plane { slope_deg, azimuth_deg } => Some(plane_normal(slope_deg, azimuth_deg)),
                    _ => None,
                };
                Surface::Height(HeightGrid {
                    n,
                    texel,
                    heights,
                    normals,
                    min,
                    max,
                    plane,
                })
            }
        };
        let material_map = match &self.map {
            MapSpec::Uniform if self.occluders.is_empty() => None,
            m => {
                let board = m.coded_board();
                let mut map = vec![0u8; n * n];
                for j in 0..n {
                    for i in 0..n {
                        let (x, y) = (centre(i), -centre(j));
                        map[j * n + i] = match &board {
                            Some(b) => u8::from(b.is_black(x, y)),
                            None => material_at(m, x, y),
                        };
                        // Occluders lie on top of the map.
                        if let Some(o) = self
                            .occluders
                            .iter()
                            .rev()
                            .find(|o| (x - o.center_mm[0]).hypot(y - o.center_mm[1]) <= o.radius_mm)
                        {
                            map[j * n + i] = o.material as u8;
                        }
                    }
                }
                Some(map)
            }
        };
        let tint = if self.tint_amplitude > 0.0 {
            let s = self.tint_scale_mm.unwrap_or(self.size_mm / 8.0);
            let mut t = vec![0f32; n * n * 3];
            for j in 0..n {
                for i in 0..n {
                    let (x, y) = (centre(i) / s, -centre(j) / s);
                    for c in 0..3 {
                        let v = fbm(self.seed.wrapping_add(c as u64 * 101), x, y, 3);
                        t[(j * n + i) * 3 + c] = (1.0 + self.tint_amplitude * (2.0 * v - 1.0)) as f32;
                    }
                }
            }
            Some(t)
        } else {
            None
        };
        Ok(Sample {
            spec: self,
            surface,
            material_map,
            tint,
        })
    }
}

/// Procedural height (mm) at a sample-frame point.
fn height_at(h: &HeightSpec, x: f64, y: f64) -> f64 {
    use std::f64::consts::PI;
    match *h {
        HeightSpec::Flat | HeightSpec::Image { .. } => 0.0,
        HeightSpec::Plane { slope_deg, azimuth_deg } => {
            let a = azimuth_deg.to_radians();
            -slope_deg.to_radians().tan() * (x * a.cos() + y * a.sin())
        }
        HeightSpec::Weave {
            period_mm,
            amplitude_mm,
        } => {
            // Threads along x and y; in each cell the thread on top alternates.
            let (u, v) = (x / period_mm, y / period_mm);
            let warp = (PI * (2.0 * v).fract().abs()).sin().abs().sqrt(); // profile across a weft
            let weft = (PI * (2.0 * u).fract().abs()).sin().abs().sqrt();
            let over = ((PI * u).cos() * (PI * v).cos()).signum();
            let s = if over > 0.0 {
                0.5 * weft + 0.5 * warp * 0.6
            } else {
                0.5 * warp + 0.5 * weft * 0.6
            };
            amplitude_mm * (s - 0.4)
        }
        HeightSpec::Emboss {
            period_mm,
            amplitude_mm,
        } => {
            let (u, v) = (2.0 * PI * x / period_mm, 2.0 * PI * y / period_mm);
            let d = 0.5 * (u.cos() + v.cos()) * 0.5 + 0.25 * ((u + v).cos());
            amplitude_mm * d.clamp(-0.5, 0.5)
        }
        HeightSpec::Ribs {
            period_mm,
            amplitude_mm,
        } => {
            let s = (PI * x / period_mm).sin().abs().powf(0.6);
            amplitude_mm * (s - 0.5)
        }
        HeightSpec::Noise {
            scale_mm,
            amplitude_mm,
            octaves,
            seed,
        } => amplitude_mm * (fbm(seed, x / scale_mm, y / scale_mm, octaves) - 0.5),
    }
}

fn material_at(m: &MapSpec, x: f64, y: f64) -> u8 {
    use std::f64::consts::PI;
    match *m {
        MapSpec::Uniform => 0,
        MapSpec::Weave { period_mm } => {
            let (u, v) = (x / period_mm, y / period_mm);
            u8::from(((PI * u).cos() * (PI * v).cos()) < 0.0)
        }
        MapSpec::Ribs { period_mm } => u8::from((PI * x / period_mm).sin().abs() < 0.35),
        MapSpec::Noise {
            scale_mm,
            threshold,
            seed,
        } => u8::from(value_noise(seed, x / scale_mm, y / scale_mm) > threshold),
        MapSpec::Emboss { period_mm } => {
            let (u, v) = (2.0 * PI * x / period_mm, 2.0 * PI * y / period_mm);
            u8::from(0.5 * (u.cos() + v.cos()) * 0.5 + 0.25 * (u + v).cos() > 0.2)
        }
        MapSpec::Checker { period_mm } => {
            let (a, b) = ((x / period_mm).floor() as i64, (y / period_mm).floor() as i64);
            u8::from((a + b).rem_euclid(2) == 1)
        }
        // Drawn by `CodedBoardSpec::is_black` in `build`.
        MapSpec::CodedBoard { .. } => 0,
        MapSpec::Grid { cols, rows, pitch_mm } => {
            let i = (x / pitch_mm + cols as f64 / 2.0).floor();
            let j = (rows as f64 / 2.0 - y / pitch_mm).floor();
            if i >= 0.0 && j >= 0.0 && (i as usize) < cols && (j as usize) < rows {
                (j as usize * cols + i as usize) as u8
            } else {
                cols.saturating_mul(rows).min(255) as u8
            }
        }
    }
}

/// Unit normals by central differences (row j grows with −y, so dh/dy flips sign).
fn normals(h: &[f32], n: usize, texel: f64) -> Vec<[f32; 3]> {
    let at =
        |i: isize, j: isize| h[(j.clamp(0, n as isize - 1) as usize) * n + i.clamp(0, n as isize - 1) as usize] as f64;
    let mut out = vec![[0f32; 3]; n * n];
    for j in 0..n as isize {
        for i in 0..n as isize {
            let dx = (at(i + 1, j) - at(i - 1, j)) / (2.0 * texel);
            let dy = -(at(i, j + 1) - at(i, j - 1)) / (2.0 * texel);
            let v = Vec3::new(-dx, -dy, 1.0).normalized();
            out[j as usize * n + i as usize] = [v.x as f32, v.y as f32, v.z as f32];
        }
    }
    out
}

impl Sample {
    /// Texel indices (i, j) of a sample-frame point, clamped to the grid.
    #[inline]
    pub fn texel_of(&self, x: f64, y: f64) -> (usize, usize) {
        let n = self.spec.resolution;
        let s = self.spec.size_mm;
        // `as usize` saturates negatives to 0 and truncates (= floor for x ≥ 0).
        let i = ((((x + s / 2.0) / s) * n as f64) as usize).min(n - 1);
        let j = ((((s / 2.0 - y) / s) * n as f64) as usize).min(n - 1);
        (i, j)
    }

    /// Material and tint at texel (i, j).
    #[inline]
    pub fn material(&self, i: usize, j: usize) -> (&BrdfModel, Rgb) {
        let n = self.spec.resolution;
        let m = match &self.material_map {
            Some(map) => &self.spec.materials[map[j * n + i] as usize],
            None => &self.spec.materials[0],
        };
        let t = match &self.tint {
            Some(t) => {
                let k = (j * n + i) * 3;
                [t[k] as f64, t[k + 1] as f64, t[k + 2] as f64]
            }
            None => [1.0; 3],
        };
        (m, t)
    }

    /// Whether every texel has the same material and no tint (no map look-ups needed).
    pub fn is_homogeneous(&self) -> bool {
        self.material_map.is_none() && self.tint.is_none()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtins_parse_and_build() {
        for (name, _) in BUILTIN {
            let s = SampleSpec::resolve(name).unwrap_or_else(|e| panic!("{name}: {e}"));
            let b = s.build().unwrap();
            if let Surface::Height(h) = &b.surface {
                assert!(h.max > h.min, "{name} has relief");
                assert!(h.normals.iter().all(|n| n[2] > 0.0));
            }
        }
        assert!(SampleSpec::resolve(DEFAULT_SAMPLE).is_ok());
    }

    /// The coded board is drawn where `CodedBoardSpec::is_black` says, occluders on top;
    /// an occluder of a material that does not exist is refused by name.
    #[test]
    fn coded_board_and_occluders() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/samples/coded-target-occluded.toml");
        let spec = SampleSpec::load(Path::new(path)).unwrap();
        let board = spec.map.coded_board().unwrap();
        let s = spec.clone().build().unwrap();
        let map = s.material_map.as_ref().unwrap();
        let n = spec.resolution;
        let texel = spec.size_mm / n as f64;
        let (mut black, mut hidden) = (0, 0);
        for j in 0..n {
            for i in 0..n {
                let (x, y) = ((i as f64 + 0.5) * texel - 44.0, 44.0 - (j as f64 + 0.5) * texel);
                let under = spec
                    .occluders
                    .iter()
                    .any(|o| (x - o.center_mm[0]).hypot(y - o.center_mm[1]) <= o.radius_mm);
                let want = if under { 2 } else { u8::from(board.is_black(x, y)) };
                assert_eq!(map[j * n + i], want, "texel ({i}, {j})");
                black += usize::from(want == 1);
                hidden += usize::from(under);
            }
        }
        assert!(black > n * n / 3 && hidden > 0);
        let mut bad = spec.clone();
        bad.occluders[0].material = 7;
        let e = bad.validate("occluded").unwrap_err().to_string();
        assert!(e.contains("occluder[0].material"), "{e}");
    }

    /// `isotropic` is declared per file (default false); only the white standard (flat,
    /// uniform, Lambertian) declares it among the shipped samples.
    #[test]
    fn isotropic_is_declared_only_by_the_white_standard() {
        for (name, _) in BUILTIN {
            let s = SampleSpec::resolve(name).unwrap();
            assert_eq!(s.isotropic, *name == "white-standard", "{name}");
        }
        let text = BUILTIN[0]
            .1
            .replacen("size_mm = 60.0", "size_mm = 60.0\nisotropic = \"yes\"", 1);
        let e = SampleSpec::parse(&text, "w.toml", None).unwrap_err().to_string();
        assert!(e.contains("w.toml") && e.contains("isotropic"), "{e}");
    }

    #[test]
    fn bad_samples_are_named() {
        let text = BUILTIN[0].1.replacen("size_mm = 60.0", "size_mm = -3.0", 1);
        let e = SampleSpec::parse(&text, "w.toml", None).unwrap_err().to_string();
        assert!(
            e.contains("w.toml") && e.contains("size_mm") && e.contains("valid range"),
            "{e}"
        );
        let text = "name='x'\nsize_mm=10\nheight={kind='image', path='nope.png', amplitude_mm=0.1}\nmap={kind='uniform'}\n[[material]]\nmodel='lambert'\nalbedo=[0.5,0.5,0.5]\n";
        let e = SampleSpec::parse(text, "x.toml", Some(Path::new("/tmp")))
            .unwrap_err()
            .to_string();
        assert!(e.contains("nope.png") && e.contains("does not exist"), "{e}");
        let e = SampleSpec::resolve("no-such-sample").unwrap_err().to_string();
        assert!(e.contains("wallpaper"), "{e}");
    }

    /// A `plane` height field is the tilted plane, with the analytic normal on every texel,
    /// and bad slopes are refused by name.
    #[test]
    fn plane_heights_and_normals_are_exact_and_bad_slopes_are_refused() {
        let s = SampleSpec::resolve("calibration-target-wedge").unwrap();
        assert_eq!(
            s.height,
            HeightSpec::Plane {
                slope_deg: 20.0,
                azimuth_deg: 0.0
            }
        );
        let text = BUILTIN
            .iter()
            .find(|(n, _)| *n == "calibration-target-wedge")
            .unwrap()
            .1
            .replacen(
                "height = { kind = \"plane\", slope_deg = 20.0, azimuth_deg = 0.0 }",
                "height = { kind = \"plane\", slope_deg = 20.0, azimuth_deg = 120.0 }",
                1,
            );
        let b = SampleSpec::parse(&text, "w.toml", None).unwrap().build().unwrap();
        let Surface::Height(g) = &b.surface else {
            panic!("a plane has a height grid")
        };
        let (t, a) = (20f64.to_radians().tan(), 120f64.to_radians());
        let n = g.n;
        for j in (0..n).step_by(7) {
            for i in (0..n).step_by(5) {
                let x = (i as f64 + 0.5) * g.texel - 30.0;
                let y = 30.0 - (j as f64 + 0.5) * g.texel;
                let want = -t * (x * a.cos() + y * a.sin());
                assert!((g.heights[j * n + i] as f64 - want).abs() < 1e-5, "({i}, {j})");
            }
        }
        // the normal leans toward the azimuth; the same on edge texels as inside
        let want = plane_normal(20.0, 120.0);
        assert!((want.x - 20f64.to_radians().sin() * a.cos()).abs() < 1e-12);
        for k in [0, n - 1, n * n / 2, n * n - 1] {
            let v = g.normals[k];
            let d = Vec3::new(v[0] as f64, v[1] as f64, v[2] as f64) - want;
            assert!(d.dot(d).sqrt() < 1e-6, "texel {k}: {v:?}");
        }
        assert!(
            (g.max - 30.0 * t * (a.cos().abs() + a.sin().abs())).abs() < 0.2,
            "{}",
            g.max
        );
        for (bad, key) in [
            ("slope_deg = 20.0", "slope_deg = 60.0"),
            ("slope_deg = 20.0", "slope_deg = -1.0"),
            ("slope_deg = 20.0", "slope_deg = nan"),
            ("azimuth_deg = 0.0", "azimuth_deg = inf"),
        ] {
            let text = BUILTIN
                .iter()
                .find(|(n, _)| *n == "calibration-target-wedge")
                .unwrap()
                .1
                .replacen(
                    &format!("kind = \"plane\", {}", "slope_deg = 20.0, azimuth_deg = 0.0"),
                    &format!("kind = \"plane\", {}", "slope_deg = 20.0, azimuth_deg = 0.0").replacen(bad, key, 1),
                    1,
                );
            let e = SampleSpec::parse(&text, "w.toml", None).unwrap_err().to_string();
            let k = key.split(' ').next().unwrap();
            assert!(
                e.contains("w.toml") && e.contains(&format!("height.{k}")) && e.contains("valid range"),
                "{e}"
            );
        }
    }
}
