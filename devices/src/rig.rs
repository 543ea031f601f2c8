//! Rig descriptions: the TOML files under `devices/rigs/`.
//!
//! A rig file says which axes exist (role, limits, motion model, backend), what camera and
//! light it has, and the geometry its kinematics need. Angles are degrees in the file and
//! radians after loading. Every validation error names the file, the key and the valid range.

use crate::{MotionModel, SoftLimits};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;
use thiserror::Error;

/// The default rig, embedded so that a fresh machine runs without any files.
pub const DEFAULT_RIG_TOML: &str = include_str!("../rigs/default.toml");

#[derive(Debug, Error)]
pub enum RigError {
    #[error("cannot read rig file {file}: {source}")]
    Io { file: String, source: std::io::Error },
    #[error("rig file {file}: {message}")]
    Parse { file: String, message: String },
    #[error("rig file {file}: key `{key}` = {value}: {message}")]
    Invalid {
        file: String,
        key: String,
        value: String,
        message: String,
    },
}

/// What kind of mechanism the rig is; selects the kinematics.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RigKind {
    /// Sample turntable, camera on an elevation arc, light on an elevation arc that sits on
    /// a rotating base.
    TwoArm,
}

/// One axis as written in the rig file (degrees for rotary axes).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AxisSpec {
    pub name: String,
    /// The kinematic role, e.g. `sample_rotation`; which roles exist depends on the rig kind.
    pub role: String,
    /// Which device implements it: `sim`, or a real backend name.
    #[serde(default = "default_backend")]
    pub backend: String,
    pub min_deg: f64,
    pub max_deg: f64,
    pub max_velocity_deg_s: f64,
    pub acceleration_deg_s2: f64,
    #[serde(default)]
    pub jerk_deg_s3: Option<f64>,
    #[serde(default)]
    pub settle_s: f64,
    #[serde(default = "default_deadband")]
    pub deadband_deg: f64,
    /// Backend-specific settings (serial port, device number, units per degree …).
    #[serde(default)]
    pub options: BTreeMap<String, toml::Value>,
}

fn default_backend() -> String {
    "sim".into()
}
fn default_deadband() -> f64 {
    0.001
}

impl AxisSpec {
    pub fn limits(&self) -> SoftLimits {
        SoftLimits {
            min: self.min_deg.to_radians(),
            max: self.max_deg.to_radians(),
        }
    }
    pub fn motion(&self) -> MotionModel {
        MotionModel {
            max_velocity: self.max_velocity_deg_s.to_radians(),
            acceleration: self.acceleration_deg_s2.to_radians(),
            jerk: self.jerk_deg_s3.map(f64::to_radians),
            settle_time: self.settle_s,
            deadband: self.deadband_deg.to_radians(),
        }
    }
}

/// Geometry the kinematics and the simulator need (millimetres).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GeometrySpec {
    /// Distance from the sample centre to the camera's centre of projection.
    pub camera_distance_mm: f64,
    /// Distance from the sample centre to the lamp.
    pub light_distance_mm: f64,
    /// Radius of a sphere that encloses the camera body and lens (blocks the light).
    pub camera_body_radius_mm: f64,
    /// Extra clearance kept between the light path and the camera body.
    #[serde(default)]
    pub clearance_mm: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    #[serde(default = "default_backend")]
    pub backend: String,
    pub width: usize,
    pub height: usize,
    /// Focal length in pixels (pinhole model; principal point at the image centre unless given).
    pub focal_length_px: f64,
    #[serde(default)]
    pub principal_point_px: Option<[f64; 2]>,
    pub bit_depth: u32,
    pub exposure_s: f64,
    #[serde(default = "one")]
    pub gain: f64,
    /// Time to read a frame out of the sensor (s), part of the planned capture time.
    #[serde(default)]
    pub readout_s: f64,
    #[serde(default)]
    pub options: BTreeMap<String, toml::Value>,
}

fn one() -> f64 {
    1.0
}

impl CameraSpec {
    pub fn principal_point(&self) -> [f64; 2] {
        self.principal_point_px
            .unwrap_or([self.width as f64 / 2.0, self.height as f64 / 2.0])
    }
    pub fn intrinsics(&self) -> crate::Intrinsics {
        let [cx, cy] = self.principal_point();
        crate::Intrinsics {
            fx: self.focal_length_px,
            fy: self.focal_length_px,
            cx,
            cy,
        }
    }
    /// Time one capture takes on the rig (exposure plus readout).
    pub fn capture_time(&self) -> f64 {
        self.exposure_s + self.readout_s
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LightSpec {
    #[serde(default = "default_backend")]
    pub backend: String,
    /// Radiant intensity (W/sr) at full power.
    pub intensity_w_sr: f64,
    #[serde(default)]
    pub options: BTreeMap<String, toml::Value>,
}

/// A whole rig file.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigSpec {
    pub name: String,
    #[serde(default)]
    pub description: String,
    pub kind: RigKind,
    pub geometry: GeometrySpec,
    pub camera: CameraSpec,
    pub light: LightSpec,
    #[serde(rename = "axis")]
    pub axes: Vec<AxisSpec>,
}

impl RigSpec {
    /// Load and validate a rig file.
    pub fn load(path: &Path) -> Result<RigSpec, RigError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| RigError::Io {
            file: file.clone(),
            source,
        })?;
        Self::parse(&text, &file)
    }

    /// The embedded default rig.
    pub fn default_rig() -> RigSpec {
        Self::parse(DEFAULT_RIG_TOML, "<embedded default rig>").expect("the embedded default rig is valid")
    }

    /// Parse and validate; `file` is only used in messages.
    pub fn parse(text: &str, file: &str) -> Result<RigSpec, RigError> {
        let spec: RigSpec = toml::from_str(text).map_err(|e| RigError::Parse {
            file: file.to_string(),
            message: e.to_string(),
        })?;
        spec.validate(file)?;
        Ok(spec)
    }

    /// The axis with a given role, if present.
    pub fn axis_by_role(&self, role: &str) -> Option<(usize, &AxisSpec)> {
        self.axes.iter().enumerate().find(|(_, a)| a.role == role)
    }

    fn validate(&self, file: &str) -> Result<(), RigError> {
        let bad = |key: String, value: String, message: &str| RigError::Invalid {
            file: file.to_string(),
            key,
            value,
            message: message.to_string(),
        };
        let pos = |key: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(bad(key.to_string(), v.to_string(), "must be a finite number > 0"))
            }
        };
        pos("geometry.camera_distance_mm", self.geometry.camera_distance_mm)?;
        pos("geometry.light_distance_mm", self.geometry.light_distance_mm)?;
        if !(self.geometry.camera_body_radius_mm >= 0.0
            && self.geometry.camera_body_radius_mm < self.geometry.camera_distance_mm)
        {
            return Err(bad(
                "geometry.camera_body_radius_mm".into(),
                self.geometry.camera_body_radius_mm.to_string(),
                "must be in [0, camera_distance_mm)",
            ));
        }
        if !(self.geometry.clearance_mm >= 0.0 && self.geometry.clearance_mm.is_finite()) {
            return Err(bad(
                "geometry.clearance_mm".into(),
                self.geometry.clearance_mm.to_string(),
                "must be ≥ 0",
            ));
        }
        let c = &self.camera;
        if !(16..=16384).contains(&c.width) {
            return Err(bad(
                "camera.width".into(),
                c.width.to_string(),
                "valid range is 16 ..= 16384 pixels",
            ));
        }
        if !(16..=16384).contains(&c.height) {
            return Err(bad(
                "camera.height".into(),
                c.height.to_string(),
                "valid range is 16 ..= 16384 pixels",
            ));
        }
        pos("camera.focal_length_px", c.focal_length_px)?;
        if !matches!(c.bit_depth, 8 | 10 | 12 | 14 | 16) {
            return Err(bad(
                "camera.bit_depth".into(),
                c.bit_depth.to_string(),
                "must be one of 8, 10, 12, 14, 16",
            ));
        }
        pos("camera.exposure_s", c.exposure_s)?;
        pos("camera.gain", c.gain)?;
        if !(c.readout_s >= 0.0 && c.readout_s.is_finite()) {
            return Err(bad("camera.readout_s".into(), c.readout_s.to_string(), "must be ≥ 0"));
        }
        pos("light.intensity_w_sr", self.light.intensity_w_sr)?;
        let mut names = std::collections::BTreeSet::new();
        for (i, a) in self.axes.iter().enumerate() {
            let k = |f: &str| format!("axis[{i}] ({}).{f}", a.name);
            if !names.insert(a.name.clone()) {
                return Err(bad(
                    k("name"),
                    a.name.clone(),
                    "duplicate axis name; names must be unique",
                ));
            }
            if !(a.min_deg.is_finite() && a.max_deg.is_finite() && a.min_deg < a.max_deg) {
                return Err(bad(
                    k("min_deg/max_deg"),
                    format!("[{}, {}]", a.min_deg, a.max_deg),
                    "need finite min_deg < max_deg",
                ));
            }
            if a.min_deg < -720.0 || a.max_deg > 720.0 {
                return Err(bad(
                    k("min_deg/max_deg"),
                    format!("[{}, {}]", a.min_deg, a.max_deg),
                    "valid range is -720 ..= 720 degrees",
                ));
            }
            if !(a.max_deg >= 0.0 && a.min_deg <= 0.0) {
                return Err(bad(
                    k("min_deg/max_deg"),
                    format!("[{}, {}]", a.min_deg, a.max_deg),
                    "the home position 0 must lie inside the limits",
                ));
            }
            pos(&k("max_velocity_deg_s"), a.max_velocity_deg_s)?;
            pos(&k("acceleration_deg_s2"), a.acceleration_deg_s2)?;
            if let Some(j) = a.jerk_deg_s3 {
                pos(&k("jerk_deg_s3"), j)?;
            }
            if !(a.settle_s >= 0.0 && a.settle_s.is_finite()) {
                return Err(bad(k("settle_s"), a.settle_s.to_string(), "must be ≥ 0"));
            }
            if !(a.deadband_deg >= 0.0 && a.deadband_deg < 1.0) {
                return Err(bad(
                    k("deadband_deg"),
                    a.deadband_deg.to_string(),
                    "valid range is 0 ≤ deadband_deg < 1",
                ));
            }
        }
        let roles: &[&str] = match self.kind {
            RigKind::TwoArm => &crate::kinematics::two_arm::ROLES,
        };
        for role in roles {
            if self.axis_by_role(role).is_none() {
                return Err(bad(
                    "axis".into(),
                    format!("{:?}", self.axes.iter().map(|a| a.role.as_str()).collect::<Vec<_>>()),
                    &format!(
                        "rig kind {:?} needs an axis with role `{role}` (roles: {})",
                        self.kind,
                        roles.join(", ")
                    ),
                ));
            }
        }
        for (i, a) in self.axes.iter().enumerate() {
            if !roles.contains(&a.role.as_str()) {
                return Err(bad(
                    format!("axis[{i}] ({}).role", a.name),
                    a.role.clone(),
                    &format!(
                        "unknown role for rig kind {:?}; valid roles: {}",
                        self.kind,
                        roles.join(", ")
                    ),
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_rig_loads() {
        let r = RigSpec::default_rig();
        assert_eq!(r.kind, RigKind::TwoArm);
        assert_eq!(r.axes.len(), 4);
    }

    #[test]
    fn errors_name_file_key_and_range() {
        let bad = DEFAULT_RIG_TOML.replace("bit_depth = 12", "bit_depth = 13");
        let e = RigSpec::parse(&bad, "my_rig.toml").unwrap_err().to_string();
        assert!(
            e.contains("my_rig.toml") && e.contains("camera.bit_depth") && e.contains("8, 10, 12"),
            "{e}"
        );
        let bad = DEFAULT_RIG_TOML.replacen("max_velocity_deg_s = 20.0", "max_velocity_deg_s = -1.0", 1);
        let e = RigSpec::parse(&bad, "r.toml").unwrap_err().to_string();
        assert!(e.contains("max_velocity_deg_s") && e.contains("> 0"), "{e}");
        let e = RigSpec::parse("name = 1", "x.toml").unwrap_err().to_string();
        assert!(e.contains("x.toml"), "{e}");
    }
}
