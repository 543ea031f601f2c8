//! Calibration recipes: the TOML scripts under `calibration/recipes/`.
//!
//! A recipe says what to estimate (`kind`), with which target, at which rig poses or
//! exposures, and with which fitting options; `gonio calibrate RECIPE --rig R` runs it on
//! any rig. Unknown keys are errors, so a typo never silently falls back to a default.

use gonio_calibration::board::Board;
use gonio_calibration::checkerboard::{CheckerboardOptions, CheckerboardSpec};
use gonio_calibration::intrinsics::IntrinsicsOptions;
use gonio_devices::coded_board::CodedBoardSpec;
use serde::{Deserialize, Serialize};
use std::path::Path;
use thiserror::Error;

#[derive(Debug, Error)]
pub enum RecipeError {
    #[error("cannot read recipe {file}: {source}")]
    Io { file: String, source: std::io::Error },
    #[error("recipe {file}: {message}")]
    Parse { file: String, message: String },
    #[error("recipe {file}: key `{key}`: {message}")]
    Invalid { file: String, key: String, message: String },
}

/// What a recipe estimates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RecipeKind {
    /// Camera intrinsics and lens distortion (Zhang) from views of a planar target.
    Intrinsics,
    /// Pixel value → BRDF (1/sr) from a white reflectance standard of known albedo.
    WhiteStandard,
    /// Dark frame (mean of frames with the light off).
    Dark,
    /// Flat field (per-pixel gain).
    Flat,
    /// Camera response curve from exposure brackets (Debevec-Malik).
    Response,
    /// 3 × 3 colour correction from a colour target.
    Colour,
    /// Homing repeatability, backlash, positioning error.
    Mechanical,
    /// Axis zero offsets and the camera's mounting rotation (bundle adjustment over
    /// checkerboard views at many axis positions).
    RigGeometry,
    /// Zero offsets of the lamp's axes from the specular highlight of a near-mirror sample
    /// over many axis positions.
    LightGeometry,
}

impl RecipeKind {
    pub fn name(self) -> &'static str {
        match self {
            RecipeKind::Intrinsics => "intrinsics",
            RecipeKind::WhiteStandard => "white-standard",
            RecipeKind::Dark => "dark",
            RecipeKind::Flat => "flat",
            RecipeKind::Response => "response",
            RecipeKind::Colour => "colour",
            RecipeKind::Mechanical => "mechanical",
            RecipeKind::RigGeometry => "rig-geometry",
            RecipeKind::LightGeometry => "light-geometry",
        }
    }
}

/// One capture position: camera (view) and lamp directions `[θ, φ]` in degrees, reached
/// through the rig's inverse kinematics.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseSpec {
    pub view: [f64; 2],
    /// Lamp direction; default: the recipe's `light`.
    #[serde(default)]
    pub light: Option<[f64; 2]>,
}

/// Settings of the simulated rig used when the recipe runs on the simulator (ignored on
/// real hardware).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimulatorSettings {
    /// Render samples per pixel and axis: target edges need area integration for
    /// sub-pixel corners (1 = point sampling, aliased edges).
    pub supersample: usize,
    /// Sensor noise on.
    pub noise: bool,
}

impl Default for SimulatorSettings {
    fn default() -> Self {
        SimulatorSettings {
            supersample: 6,
            noise: false,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Recipe {
    pub kind: RecipeKind,
    pub name: String,
    #[serde(default)]
    pub description: String,
    /// The target: a built-in sample name or sample file (what the simulator renders; on
    /// a real rig, what must be mounted).
    pub target: String,
    /// Board geometry (intrinsics, rig geometry, mechanical through the camera): a plain
    /// checkerboard, or `coded_board` (below), one of the two.
    #[serde(default)]
    pub checkerboard: Option<CheckerboardSpec>,
    /// The coded-marker board (`devices/src/coded_board.rs`; the simulator's
    /// `coded-target`): views may show only part of it.
    #[serde(default)]
    pub coded_board: Option<CodedBoardSpec>,
    /// Intrinsics: the wedge the board sits on (`wedge = { slope_deg, azimuth_deg }`, see
    /// [`gonio_calibration::wedge`]); the board's points are then taken on the tilted plane.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub wedge: Option<gonio_calibration::wedge::WedgeSpec>,
    #[serde(default)]
    pub detection: CheckerboardOptions,
    /// Fitting options (intrinsics).
    #[serde(default)]
    pub estimate: IntrinsicsOptions,
    /// Default lamp direction `[θ, φ]` (degrees).
    #[serde(default = "default_light")]
    pub light: [f64; 2],
    #[serde(default, rename = "pose")]
    pub poses: Vec<PoseSpec>,
    /// Camera exposure (s); default: the rig file's.
    #[serde(default)]
    pub exposure_s: Option<f64>,
    #[serde(default)]
    pub simulator: SimulatorSettings,
    /// Mechanical run: axes, homing cycles, targets, approach (`kind = "mechanical"`;
    /// defaults apply when the section is absent).
    #[serde(default)]
    pub mechanical: Option<super::mechanical::MechanicalSpec>,
    /// White standard: its albedo and the fit's texel grid (`kind = "white-standard"`).
    #[serde(default)]
    pub white_standard: Option<super::white::WhiteStandardSpec>,
    /// Dark, response, flat and colour recipes: frames, exposure bracket, fit options,
    /// colour patches (`[radiometric]`).
    #[serde(default)]
    pub radiometric: Option<super::radiometric::RadiometricSpec>,
    /// Rig geometry: fit options and refusal limits (`kind = "rig-geometry"`; defaults
    /// apply when the section is absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rig_geometry: Option<gonio_calibration::rig_geometry::RigGeometryOptions>,
    /// Light geometry: fit options, refusal limits and highlight detection
    /// (`kind = "light-geometry"`; defaults apply when the section is absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub light_geometry: Option<gonio_calibration::light_geometry::LightGeometryOptions>,
}

fn default_light() -> [f64; 2] {
    [35.0, 180.0]
}

impl Recipe {
    /// The simulator settings the recipe asks for (`[simulator]`: supersampling, noise):
    /// what `gonio calibrate` builds a simulated rig with, so tests and scripts that build
    /// the rig themselves render the same frames.
    pub fn sim_options(&self) -> gonio_simulator::SimOptions {
        gonio_simulator::SimOptions {
            noise: Some(self.simulator.noise),
            quality: gonio_simulator::RenderQuality {
                supersample: self.simulator.supersample,
                ..Default::default()
            },
            ..Default::default()
        }
    }

    pub fn load(path: &Path) -> Result<Recipe, RecipeError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| RecipeError::Io {
            file: file.clone(),
            source,
        })?;
        Recipe::parse(&text, &file)
    }

    pub fn parse(text: &str, file: &str) -> Result<Recipe, RecipeError> {
        let r: Recipe = toml::from_str(text).map_err(|e| RecipeError::Parse {
            file: file.into(),
            message: e.to_string(),
        })?;
        r.validate(file)?;
        Ok(r)
    }

    fn validate(&self, file: &str) -> Result<(), RecipeError> {
        let bad = |key: &str, message: String| RecipeError::Invalid {
            file: file.into(),
            key: key.into(),
            message,
        };
        let dir_ok = |d: [f64; 2]| d.iter().all(|x| x.is_finite()) && (0.0..=90.0).contains(&d[0]);
        if !dir_ok(self.light) {
            return Err(bad("light", format!("{:?}: θ must be in 0 ..= 90°", self.light)));
        }
        for (k, p) in self.poses.iter().enumerate() {
            if !dir_ok(p.view) || !p.light.is_none_or(dir_ok) {
                return Err(bad(&format!("pose[{k}]"), format!("{p:?}: θ must be in 0 ..= 90°")));
            }
        }
        if let Some(e) = self.exposure_s {
            if !(e > 0.0 && e.is_finite()) {
                return Err(bad("exposure_s", format!("{e}: must be > 0")));
            }
        }
        if !(1..=16).contains(&self.simulator.supersample) {
            return Err(bad(
                "simulator.supersample",
                format!("{}: valid range is 1 ..= 16", self.simulator.supersample),
            ));
        }
        if matches!(
            self.kind,
            RecipeKind::Dark | RecipeKind::Response | RecipeKind::Flat | RecipeKind::Colour
        ) {
            if let Some(r) = &self.radiometric {
                r.validate(self.kind).map_err(|(key, message)| bad(&key, message))?;
            } else if matches!(self.kind, RecipeKind::Response | RecipeKind::Colour) {
                return Err(bad(
                    "radiometric",
                    "this recipe needs [radiometric] exposures_s = [...] (and patches for colour)".into(),
                ));
            }
        }
        if self.kind == RecipeKind::WhiteStandard {
            let Some(w) = &self.white_standard else {
                return Err(bad(
                    "white_standard",
                    "a white-standard recipe needs [white_standard] albedo = [r, g, b]".into(),
                ));
            };
            if w.albedo.iter().any(|a| !(a.is_finite() && *a > 0.0 && *a <= 1.0)) {
                return Err(bad(
                    "white_standard.albedo",
                    format!("{:?}: each channel must be in (0, 1]", w.albedo),
                ));
            }
            if !(4..=1024).contains(&w.texels) {
                return Err(bad(
                    "white_standard.texels",
                    format!("{}: valid range is 4 ..= 1024", w.texels),
                ));
            }
            if self.poses.is_empty() {
                return Err(bad(
                    "pose",
                    "a white-standard recipe needs at least one [[pose]]".into(),
                ));
            }
        }
        if self.kind == RecipeKind::Mechanical {
            if let Err((key, message)) = self.mechanical.clone().unwrap_or_default().validate() {
                return Err(bad(&key, message));
            }
        }
        if self.kind == RecipeKind::RigGeometry {
            self.validate_board(file, "a rig-geometry recipe")?;
            let min = self.rig_geometry.as_ref().map(|o| o.min_views).unwrap_or(3).max(1);
            if self.poses.len() < min {
                return Err(bad(
                    "pose",
                    format!(
                        "{} poses: the rig-geometry fit needs at least {min} views",
                        self.poses.len()
                    ),
                ));
            }
        }
        if self.kind == RecipeKind::LightGeometry {
            let opts = self.light_geometry.clone().unwrap_or_default();
            opts.validate()
                .map_err(|(key, message)| bad(&format!("light_geometry.{key}"), message))?;
            if self.poses.len() < opts.min_poses {
                return Err(bad(
                    "pose",
                    format!(
                        "{} poses: the light-geometry fit needs at least {} (light_geometry.min_poses); add [[pose]] \
                         entries with the lamp in the mirror direction of the view",
                        self.poses.len(),
                        opts.min_poses
                    ),
                ));
            }
            if let Some(k) = self.poses.iter().position(|p| p.light.is_none()) {
                return Err(bad(
                    &format!("pose[{k}].light"),
                    "missing: a light-geometry pose needs its lamp direction (the mirror of its view: \
                     light = [θ_v, φ_v + 180°])"
                        .into(),
                ));
            }
        }
        if self.kind == RecipeKind::Intrinsics {
            self.validate_board(file, "an intrinsics recipe")?;
            if self.poses.len() < 3 {
                return Err(bad(
                    "pose",
                    format!("{} poses: Zhang's method needs at least 3 views", self.poses.len()),
                ));
            }
        }
        if let Some(w) = &self.wedge {
            if self.kind != RecipeKind::Intrinsics {
                return Err(bad("wedge", "only intrinsics recipes use a wedge".into()));
            }
            w.validate().map_err(|m| bad("wedge", m))?;
        }
        // A partial plain-board view is indexed from the piece seen, not the board: only a
        // fit with a free board pose per view (intrinsics on a flat board) can use it.
        if self.detection.partial && (self.kind != RecipeKind::Intrinsics || self.wedge.is_some()) {
            return Err(bad(
                "detection.partial",
                "partial plain-board views name their corners only up to the board's lattice, which \
                 only an intrinsics fit on a flat board (a free pose per view) can use; remove it, or use \
                 the coded board (coded_board = { ... }), whose views name every corner"
                    .into(),
            ));
        }
        Ok(())
    }
}

impl Recipe {
    /// The target board, if the recipe names one.
    pub fn board(&self) -> Option<Board> {
        match (&self.checkerboard, &self.coded_board) {
            (_, Some(c)) => Some(Board::Coded(*c)),
            (Some(cb), None) => Some(Board::Checkerboard(*cb)),
            (None, None) => None,
        }
    }

    /// Exactly one board, and a sound one.
    fn validate_board(&self, file: &str, what: &str) -> Result<(), RecipeError> {
        let bad = |key: &str, message: String| RecipeError::Invalid {
            file: file.into(),
            key: key.into(),
            message,
        };
        match (&self.checkerboard, &self.coded_board) {
            (None, None) => Err(bad(
                "checkerboard",
                format!(
                    "{what} needs a board: checkerboard = {{ cols, rows, pitch_mm }} or \
                     coded_board = {{ squares_x, squares_y, pitch_mm, marker_mm }}"
                ),
            )),
            (Some(_), Some(_)) => Err(bad(
                "coded_board",
                "both checkerboard and coded_board are set: a recipe uses one target; remove one".into(),
            )),
            (Some(cb), None) => {
                if cb.cols < 2 || cb.rows < 2 || cb.pitch_mm.is_nan() || cb.pitch_mm <= 0.0 {
                    return Err(bad(
                        "checkerboard",
                        format!("{cb:?}: need ≥ 2 × 2 inner corners and pitch_mm > 0"),
                    ));
                }
                Ok(())
            }
            (None, Some(c)) => c.validate().map_err(|m| bad("coded_board", m)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_recipes_parse() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../calibration/recipes");
        let mut n = 0;
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.extension().is_some_and(|x| x == "toml") {
                Recipe::load(&p).unwrap_or_else(|e| panic!("{e}"));
                n += 1;
            }
        }
        assert!(n >= 1);
    }

    #[test]
    fn typos_and_bad_values_are_errors() {
        let base = "kind = \"intrinsics\"\nname = \"x\"\ntarget = \"calibration-target\"\n\
                    checkerboard = { cols = 11, rows = 11, pitch_mm = 5.0 }\n";
        let poses = "[[pose]]\nview = [0, 0]\n[[pose]]\nview = [20, 0]\n[[pose]]\nview = [20, 90]\n";
        assert!(Recipe::parse(&format!("{base}{poses}"), "t").is_ok());
        let e = Recipe::parse(&format!("{base}exposur_s = 0.1\n{poses}"), "t").unwrap_err();
        assert!(e.to_string().contains("exposur_s"), "{e}");
        let e = Recipe::parse(&format!("{base}[[pose]]\nview = [0, 0]\n"), "t").unwrap_err();
        assert!(e.to_string().contains("at least 3"), "{e}");
        let e = Recipe::parse(&format!("{base}light = [95, 0]\n{poses}"), "t").unwrap_err();
        assert!(e.to_string().contains("light"), "{e}");
        let r = Recipe::parse(&format!("{base}wedge = {{ slope_deg = 15.0 }}\n{poses}"), "t").unwrap();
        assert_eq!(r.wedge.map(|w| (w.slope_deg, w.azimuth_deg)), Some((15.0, 0.0)));
        let e = Recipe::parse(&format!("{base}wedge = {{ slope_deg = 60.0 }}\n{poses}"), "t").unwrap_err();
        assert!(
            e.to_string().contains("wedge") && e.to_string().contains("valid range"),
            "{e}"
        );
        let e = Recipe::parse(&format!("{base}wedge = {{ slope = 15.0 }}\n{poses}"), "t").unwrap_err();
        assert!(e.to_string().contains("slope"), "{e}");
        let e = Recipe::parse("kind = \"focus\"\nname = \"x\"\ntarget = \"t\"\n", "t").unwrap_err();
        assert!(e.to_string().contains("focus"), "{e}");
    }
}
