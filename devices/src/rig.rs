//! Rig descriptions: the TOML files under `devices/rigs/`.
//!
//! A rig file says which axes exist (role, limits, motion model, backend), what camera and
//! light it has, and the geometry its kinematics need. Angles are degrees in the file and
//! radians after loading. Every validation error names the file, the key and the valid range.

use crate::target::MarkerBorder;
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

/// A rig-file option that is present but wrong: its key (`camera.options.k1`), its value
/// and what it must be. Every option that more than one place reads has one typed reader on
/// the schema ([`CameraSpec::distortion`], [`CameraSpec::noise_seed`],
/// [`RigSpec::lamp_radius_mm`]), so the rule and its message live in one place.
#[derive(Debug, Clone, PartialEq, Error)]
#[error("`{key}` = {value}: {message}")]
pub struct OptionError {
    pub key: String,
    pub value: String,
    pub message: String,
}

/// A finite number from a TOML value (integer or float).
fn option_number(v: &toml::Value) -> Option<f64> {
    v.as_float()
        .or_else(|| v.as_integer().map(|i| i as f64))
        .filter(|x| x.is_finite())
}

/// What kind of mechanism the rig is; selects the kinematics.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RigKind {
    /// Sample turntable, camera on an elevation arc, light on an elevation arc that sits on
    /// a rotating base.
    TwoArm,
    /// Fixed camera, lamp on one circular arc, sample on a 3-axis gimbal of rotary stages
    /// (Winkler & Zagar 2015): the sample turns, not the camera.
    Gimbal,
    /// The lamp never moves (RGL pgII principle); camera on a 2-axis arc, sample on tilt +
    /// rotation stages.
    StaticLight,
    /// N fixed cameras and M fixed lamps (Bonn's Dome): measuring is selecting. Two selector
    /// axes whose position (degrees at the interface) is the camera / lamp index.
    Dome,
    /// CTU's Lightdrum principle: cameras fixed on an arc that rotates about the vertical,
    /// fixed lamps. An arc rotation axis plus camera / lamp selectors.
    Lightdrum,
    /// The static-light rig with a camera arc that does not turn (1 axis): measures the
    /// pairs whose light, view and normal are coplanar (see `kinematics::static_light`).
    StaticLightArc,
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
    /// Height of the sample holder's rim above the sample surface; 0 = no rim (off).
    #[serde(default)]
    pub holder_rim_height_mm: f64,
    /// Edge length of the (square) sample the rim must not shadow; 0 = off.
    #[serde(default)]
    pub sample_size_mm: f64,
    /// Horizontal gap between the sample's edge and the rim's inner wall. The default is
    /// the marker border's width (`MarkerBorder::default().border_mm`), which lies between
    /// the sample and the rim.
    #[serde(default = "default_rim_gap")]
    pub holder_rim_gap_mm: f64,
    /// The holder's marker border (`[geometry.marker_border]`: `border_mm`, `marker_mm`,
    /// `markers_per_side`), what rectification looks for on a real camera's frames. Absent
    /// = [`MarkerBorder::default`]. A simulated camera renders (and finds) the sample
    /// file's border instead, so the simulator never reads this key.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub marker_border: Option<MarkerBorder>,
    /// static-light: the fixed lamp's angle from the world zenith, in the world x-z plane.
    #[serde(default)]
    pub fixed_light_elevation_deg: f64,
    /// dome: camera directions `[[θ, φ], …]` (degrees, world = sample frame); absent = the
    /// uniform 15° layout (`kinematics::dome::uniform15`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_directions_deg: Option<Vec<[f64; 2]>>,
    /// dome: lamp directions, as `camera_directions_deg`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub light_directions_deg: Option<Vec<[f64; 2]>>,
    /// lightdrum: signed camera elevations along the rotating arc (degrees from the
    /// zenith; negative = far side of the pole). Absent = 0, 15, …, 75°.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arc_camera_elevations_deg: Option<Vec<f64>>,
    /// dome: a named camera / lamp layout used where no explicit list is given:
    /// `uniform15` (80 directions, the default) or `bonn-dome1` (Bonn's Dome, 151).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dome_layout: Option<String>,
    /// dome: a requested direction matches a camera / lamp closer than this. The default is
    /// below 1e-9 rad, so what is measured is what was asked to the planner's precision.
    #[serde(default = "default_dome_tolerance")]
    pub dome_match_tolerance_deg: f64,
}

fn default_rim_gap() -> f64 {
    10.0
}
fn default_dome_tolerance() -> f64 {
    5e-8
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

    /// The lens distortion `[k1, k2, p1, p2, k3]` (OpenCV's order; `camera.options.k1` …),
    /// 0 where absent. Each may be negative and must satisfy |value| < 10.
    pub fn distortion(&self) -> Result<[f64; 5], OptionError> {
        let mut c = [0.0; 5];
        for (k, key) in ["k1", "k2", "p1", "p2", "k3"].iter().enumerate() {
            if let Some(v) = self.options.get(*key) {
                c[k] = option_number(v).filter(|x| x.abs() < 10.0).ok_or_else(|| OptionError {
                    key: format!("camera.options.{key}"),
                    value: v.to_string(),
                    message: "must be a number with |value| < 10".into(),
                })?;
            }
        }
        Ok(c)
    }

    /// The sensor noise seed the rig file sets (`camera.options.seed`, an integer ≥ 0), if
    /// any. `--seed` overrides it; the manifest records the seed actually used.
    pub fn noise_seed(&self) -> Result<Option<u64>, OptionError> {
        let Some(v) = self.options.get("seed") else {
            return Ok(None);
        };
        option_number(v)
            .filter(|x| *x >= 0.0 && x.fract() == 0.0 && *x <= u64::MAX as f64)
            .map(|x| Some(x as u64))
            .ok_or_else(|| OptionError {
                key: "camera.options.seed".into(),
                value: v.to_string(),
                message: "must be a whole number ≥ 0".into(),
            })
    }

    /// Whether the readout may overlap the next move (`camera.options.overlap_readout`).
    ///
    /// The exposed image does not change while the sensor is read out, so the axes may start
    /// as soon as the exposure ends; the next exposure waits for both the move and the
    /// readout. Default: on for the simulated camera, which models a camera that buffers its
    /// frame (`capture` returns when the exposure ends and the sensor stays busy for the
    /// readout); off for every other backend: V4L2's `capture` returns only once the frame is
    /// dequeued, after its readout, so nothing can overlap and the plan must not say it does.
    /// `true` on a backend that cannot do it is refused.
    pub fn readout_overlaps_motion(&self) -> Result<bool, OptionError> {
        let can = self.backend == "sim";
        let Some(v) = self.options.get("overlap_readout") else {
            return Ok(can);
        };
        let err = |message: String| OptionError {
            key: "camera.options.overlap_readout".into(),
            value: v.to_string(),
            message,
        };
        match v.as_bool() {
            None => Err(err("must be true or false".into())),
            Some(true) if !can => Err(err(format!(
                "the `{}` camera returns a frame only after its readout, so the readout cannot overlap the next move; \
                 remove the option or set it to false",
                self.backend
            ))),
            Some(b) => Ok(b),
        }
    }

    /// The part of [`CameraSpec::capture_time`] that overlaps the next move: the readout when
    /// [`CameraSpec::readout_overlaps_motion`], else 0.
    pub fn overlapped_readout_s(&self) -> Result<f64, OptionError> {
        Ok(if self.readout_overlaps_motion()? {
            self.readout_s.max(0.0)
        } else {
            0.0
        })
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
    /// Calibrated alignment the kinematics apply (`[alignment]`, written by the
    /// rig-geometry calibration): absent = the ideal mechanism.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alignment: Option<AlignmentSpec>,
    /// Simulator only: the rig's TRUE misalignment (`[sim_misalignment]`). The simulated
    /// camera and lamp are placed where this puts them, while the kinematics the planner
    /// uses know only `alignment`; so a simulated rig can be wrong the way a real one is,
    /// and a calibration can be checked against the truth. Real backends ignore it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sim_misalignment: Option<AlignmentSpec>,
    /// Exposure bracketing (`[hdr]`, see [`crate::hdr`]): absent = one exposure per
    /// measurement, and the rig snapshot is unchanged.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hdr: Option<crate::hdr::HdrSpec>,
}

/// Deviations of a rig from its ideal kinematics (two-arm rigs).
///
/// Why these parameters: they are what target images over many axis positions can
/// separate. An axis zero offset shifts every position of that axis (the true position is
/// the commanded one plus the offset). The camera's mounting rotation turns the camera
/// about its centre of projection (pointing and roll); it changes what the camera sees but
/// not the view direction. A mounting *translation* along the camera arc is the same as a
/// camera-arc zero offset and is folded into it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AlignmentSpec {
    /// Zero offset per axis name (degrees): true position = commanded position + offset.
    #[serde(default)]
    pub axis_zero_offset_deg: BTreeMap<String, f64>,
    /// Camera mounting rotation (degrees): a rotation vector in the nominal camera frame
    /// (x right, y down, z forward) that turns the nominal camera axes into the true ones.
    #[serde(default)]
    pub camera_rotation_deg: [f64; 3],
}

impl AlignmentSpec {
    /// Largest accepted offset or mounting angle (degrees): beyond it the rig is not
    /// misaligned but mis-described, and IK near the limits would stop making sense.
    pub const MAX_DEG: f64 = 10.0;

    /// Zero offsets in radians, in the rig's axis order (0 for axes not listed).
    pub fn offsets_rad(&self, axes: &[AxisSpec]) -> Vec<f64> {
        axes.iter()
            .map(|a| {
                self.axis_zero_offset_deg
                    .get(&a.name)
                    .copied()
                    .unwrap_or(0.0)
                    .to_radians()
            })
            .collect()
    }

    /// True when it changes nothing.
    pub fn is_identity(&self) -> bool {
        self.axis_zero_offset_deg.values().all(|v| *v == 0.0) && self.camera_rotation_deg.iter().all(|v| *v == 0.0)
    }
}

/// How a run watches the lamp's read-back (`light.options.drift_threshold`,
/// `light.options.output_exponent`; any backend whose light measures, see
/// [`crate::Light::read_back`]).
///
/// The reference is the run's first reading, taken after the lamp was switched on and
/// settled. A measurement whose current or voltage differs from it by more than
/// `drift_threshold` (relative) logs a warning and is counted. With `output_exponent` = k
/// the stored values are divided by (I / I₀)^k: the lamp's output taken as ∝ I^k, a law a
/// lamp follows only near its operating point and with its own k, hence only from a
/// calibration; without it nothing is corrected (the reading is recorded always).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LampMonitor {
    pub drift_threshold: f64,
    pub output_exponent: Option<f64>,
}

/// How a run waits for a real lamp to warm up before its first frame
/// (`light.options.warmup_tolerance`, `warmup_interval_s`, `warmup_timeout_s`).
///
/// Why: a halogen filament's resistance, hence its current and output, settles over
/// seconds to minutes after switch-on; frames taken before then are darker than the rest
/// of an eight-hour run. The lamp counts as warm when two readings `interval_s` apart
/// differ in current by less than `tolerance` (relative). A lamp still changing after
/// `timeout_s` fails the run's start; `timeout_s` = 0 does not wait.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LampWarmup {
    pub tolerance: f64,
    pub interval_s: f64,
    pub timeout_s: f64,
}

impl Default for LampWarmup {
    fn default() -> Self {
        LampWarmup {
            tolerance: 0.005,
            interval_s: 1.0,
            timeout_s: 300.0,
        }
    }
}

/// The default settle time of a light after switching (s, `light.options.settle_s`).
pub const DEFAULT_LIGHT_SETTLE_S: f64 = 1.0;

/// A developed (linear) image's full scale: the value of a saturated pixel, which the
/// rectifier's marker detector and the sparse completion treat as clipped.
pub const FULL_SCALE: f64 = 1.0;

/// The default relative drift that warns (2 %).
pub const DEFAULT_LAMP_DRIFT: f64 = 0.02;

impl RigSpec {
    /// The lamp monitor's options (see [`LampMonitor`]): `drift_threshold` in (0, 1),
    /// default 0.02; `output_exponent` in (0, 20], absent = no correction.
    pub fn lamp_monitor(&self) -> Result<LampMonitor, OptionError> {
        let o = &self.light.options;
        let drift_threshold = match o.get("drift_threshold") {
            None => DEFAULT_LAMP_DRIFT,
            Some(v) => option_number(v)
                .filter(|x| *x > 0.0 && *x < 1.0)
                .ok_or_else(|| OptionError {
                    key: "light.options.drift_threshold".into(),
                    value: v.to_string(),
                    message: "must be a relative change in (0, 1), e.g. 0.02 for 2 %".into(),
                })?,
        };
        let output_exponent = match o.get("output_exponent") {
            None => None,
            Some(v) => Some(option_number(v).filter(|k| *k > 0.0 && *k <= 20.0).ok_or_else(|| {
                OptionError {
                    key: "light.options.output_exponent".into(),
                    value: v.to_string(),
                    message: "must be the calibrated exponent k of output ∝ current^k, in (0, 20]; \
                              leave it out for no correction"
                        .into(),
                }
            })?),
        };
        Ok(LampMonitor {
            drift_threshold,
            output_exponent,
        })
    }

    /// Seconds the light needs after being switched before a frame is taken
    /// (`light.options.settle_s`, in [0, 600]; default [`DEFAULT_LIGHT_SETTLE_S`]): the
    /// drift references switch it off for their dark frame and on again, and pay this
    /// twice in rig time. A lamp that measures also waits for its warm-up after switching
    /// on (see [`LampWarmup`]).
    pub fn light_settle_s(&self) -> Result<f64, OptionError> {
        let Some(v) = self.light.options.get("settle_s") else {
            return Ok(DEFAULT_LIGHT_SETTLE_S);
        };
        option_number(v)
            .filter(|x| (0.0..=600.0).contains(x))
            .ok_or_else(|| OptionError {
                key: "light.options.settle_s".into(),
                value: v.to_string(),
                message: "must be seconds in [0, 600] the light needs after switching".into(),
            })
    }

    /// Simulator only: the simulated lamp's output drift per hour of rig time
    /// (`light.options.drift_per_hour`, relative, in [-0.9, 10]; default 0): its radiant
    /// intensity is multiplied by 1 + drift × hours. Its measured voltage and current do
    /// not follow (an optical drift the lamp monitor cannot see), so only re-measured
    /// references reveal it.
    pub fn sim_light_drift_per_hour(&self) -> Result<f64, OptionError> {
        let Some(v) = self.light.options.get("drift_per_hour") else {
            return Ok(0.0);
        };
        option_number(v)
            .filter(|x| (-0.9..=10.0).contains(x))
            .ok_or_else(|| OptionError {
                key: "light.options.drift_per_hour".into(),
                value: v.to_string(),
                message: "must be a relative change per hour in [-0.9, 10], e.g. 0.05 for +5 %/h".into(),
            })
    }

    /// The lamp warm-up options (see [`LampWarmup`]): `warmup_tolerance` in (0, 0.5)
    /// (default 0.005), `warmup_interval_s` in (0, 60] (default 1), `warmup_timeout_s` in
    /// [0, 7200] (default 300; 0 = no wait).
    pub fn lamp_warmup(&self) -> Result<LampWarmup, OptionError> {
        let o = &self.light.options;
        let d = LampWarmup::default();
        let read = |key: &str, default: f64, ok: &dyn Fn(f64) -> bool, message: &str| match o.get(key) {
            None => Ok(default),
            Some(v) => option_number(v).filter(|x| ok(*x)).ok_or_else(|| OptionError {
                key: format!("light.options.{key}"),
                value: v.to_string(),
                message: message.to_string(),
            }),
        };
        Ok(LampWarmup {
            tolerance: read(
                "warmup_tolerance",
                d.tolerance,
                &|x| x > 0.0 && x < 0.5,
                "must be a relative change of the current in (0, 0.5), e.g. 0.005 for 0.5 %",
            )?,
            interval_s: read(
                "warmup_interval_s",
                d.interval_s,
                &|x| x > 0.0 && x <= 60.0,
                "must be seconds between readings in (0, 60]",
            )?,
            timeout_s: read(
                "warmup_timeout_s",
                d.timeout_s,
                &|x| (0.0..=7200.0).contains(&x),
                "must be seconds in [0, 7200] (0: do not wait for the lamp)",
            )?,
        })
    }

    /// A `sim` light's nominal electrical values, when the rig file asks for them
    /// (`light.options.voltage` and `light.options.current`, both > 0): the simulated lamp
    /// then reports them (scaled by its intensity) as its read-back, so a simulated run
    /// records them like a real one. Absent: it measures nothing and records nothing.
    pub fn sim_lamp_nominal(&self) -> Result<Option<crate::LampReading>, OptionError> {
        let o = &self.light.options;
        let read = |key: &str| -> Result<Option<f64>, OptionError> {
            o.get(key)
                .map(|v| {
                    option_number(v).filter(|x| *x > 0.0).ok_or_else(|| OptionError {
                        key: format!("light.options.{key}"),
                        value: v.to_string(),
                        message: "must be a number > 0 (the simulated lamp's nominal value)".into(),
                    })
                })
                .transpose()
        };
        match (read("voltage")?, read("current")?) {
            (Some(voltage_v), Some(current_a)) => Ok(Some(crate::LampReading { voltage_v, current_a })),
            (None, None) => Ok(None),
            (v, _) => Err(OptionError {
                key: format!("light.options.{}", if v.is_some() { "current" } else { "voltage" }),
                value: "(missing)".into(),
                message: "give both voltage and current for the simulated lamp's read-back, or neither".into(),
            }),
        }
    }

    /// The lamp's disc radius (`light.options.radius_mm`, mm; absent = 0, a point lamp), at
    /// most half the lamp's distance from the sample, so the disc stays a lamp.
    pub fn lamp_radius_mm(&self) -> Result<f64, OptionError> {
        let Some(v) = self.light.options.get("radius_mm") else {
            return Ok(0.0);
        };
        let max = self.geometry.light_distance_mm / 2.0;
        option_number(v)
            .filter(|r| *r >= 0.0 && *r <= max)
            .ok_or_else(|| OptionError {
                key: "light.options.radius_mm".into(),
                value: v.to_string(),
                message: format!("must be a number of millimetres in [0, {max}] (half the lamp distance)"),
            })
    }

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

    /// The rig as it really is, for the simulator: its mechanism is misaligned by
    /// `sim_misalignment` (none: ideal), whatever `alignment` the calibration believes in —
    /// so a calibration applied to a simulated rig corrects the commands, not the mechanism.
    pub fn simulated_truth(&self) -> RigSpec {
        let mut r = self.clone();
        r.alignment = r.sim_misalignment.take();
        r
    }

    /// Whether every device of the rig is simulated (axes, camera and light all `sim`).
    pub fn is_simulated(&self) -> bool {
        self.camera.backend == "sim" && self.light.backend == "sim" && self.axes.iter().all(|a| a.backend == "sim")
    }

    /// The HDR mode this rig runs with (`Off` without an `[hdr]` section).
    pub fn hdr_mode(&self) -> crate::hdr::HdrMode {
        self.hdr.as_ref().map_or(crate::hdr::HdrMode::Off, |h| h.mode())
    }

    /// The linear level at or above which this rig's stored readings were clipped: the
    /// developed image's full scale ([`FULL_SCALE`]), or none when HDR merges brackets
    /// (a merged reading has no fixed clip level). What a completion and the adaptive
    /// analysis fit as lower bounds instead of values.
    pub fn clip_level(&self) -> Option<f64> {
        (self.hdr_mode() == crate::hdr::HdrMode::Off).then_some(FULL_SCALE)
    }

    /// The noise model of this rig's camera at its gain (the `[hdr]` section's sensor
    /// figures where it has them, else the camera's options, else the defaults): what a
    /// completion weighs each measured pair by.
    pub fn sensor_noise(&self) -> crate::hdr::SensorNoise {
        self.hdr
            .clone()
            .unwrap_or_default()
            .noise(&self.camera, self.camera.gain)
    }

    /// Planned time of one measurement's captures, the HDR bracket's extra exposures
    /// included (the camera's `capture_time` without `[hdr]`).
    pub fn planned_capture_time(&self) -> f64 {
        match &self.hdr {
            Some(h) => h.planned_capture_time(&self.camera),
            None => self.camera.capture_time(),
        }
    }

    /// The sample holder a real camera sees: the marker border (`geometry.marker_border`,
    /// default [`MarkerBorder::default`]) and the sample's edge length
    /// (`geometry.sample_size_mm`). Why from the rig file: with a real camera there is no
    /// simulated sample to take them from, and rectification needs both. An error when
    /// `sample_size_mm` is 0 (its "off" value for the rim), which no rectification can use.
    pub fn holder_geometry(&self) -> Result<(MarkerBorder, f64), OptionError> {
        let size = self.geometry.sample_size_mm;
        if size <= 0.0 {
            return Err(OptionError {
                key: "geometry.sample_size_mm".into(),
                value: size.to_string(),
                message: format!(
                    "camera backend `{}` is real, so rectification needs the sample's edge length: set \
                     geometry.sample_size_mm (mm, > 0) in the rig file",
                    self.camera.backend
                ),
            });
        }
        Ok((self.geometry.marker_border.clone().unwrap_or_default(), size))
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
        if let Some(h) = &self.hdr {
            h.validate(self.camera.exposure_s).map_err(|(k, v, m)| bad(k, v, &m))?;
        }
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
        self.validate_kind_geometry(file)?;
        self.validate_alignment(file)?;
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
        let option = |e: OptionError| RigError::Invalid {
            file: file.to_string(),
            key: e.key,
            value: e.value,
            message: e.message,
        };
        self.lamp_monitor().map_err(option)?;
        if self.light.backend == "sim" {
            self.sim_lamp_nominal().map_err(option)?;
        }
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
            // Bounded ranges: absurd values (1e300 s of settling, 1e-300 °/s) would make
            // every planned time overflow and no plan meaningful.
            let within = |key: String, v: f64, lo: f64, hi: f64| {
                if v.is_finite() && v >= lo && v <= hi {
                    Ok(())
                } else {
                    Err(bad(key, v.to_string(), &format!("valid range is {lo:e} ..= {hi:e}")))
                }
            };
            within(k("max_velocity_deg_s"), a.max_velocity_deg_s, 1e-3, 1e7)?;
            within(k("acceleration_deg_s2"), a.acceleration_deg_s2, 1e-3, 1e10)?;
            if let Some(j) = a.jerk_deg_s3 {
                within(k("jerk_deg_s3"), j, 1e-3, 1e13)?;
            }
            if !(a.settle_s >= 0.0 && a.settle_s <= 3600.0) {
                return Err(bad(
                    k("settle_s"),
                    a.settle_s.to_string(),
                    "valid range is 0 ..= 3600 s",
                ));
            }
            if !(a.deadband_deg >= 0.0 && a.deadband_deg < 1.0) {
                return Err(bad(
                    k("deadband_deg"),
                    a.deadband_deg.to_string(),
                    "valid range is 0 ≤ deadband_deg < 1",
                ));
            }
        }
        let roles: &[&str] = crate::kinematics::roles(self.kind);
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
        if matches!(self.kind, RigKind::Dome | RigKind::Lightdrum) {
            let (cams, lamps) = crate::kinematics::dome::directions(self);
            let (n_cams, cam_list) = if self.kind == RigKind::Lightdrum {
                (
                    crate::kinematics::lightdrum::elevations(self).len(),
                    "arc_camera_elevations_deg",
                )
            } else {
                (cams.len(), "camera_directions_deg")
            };
            for (role, n, list) in [
                ("camera_select", n_cams, cam_list),
                ("light_select", lamps.len(), "light_directions_deg"),
            ] {
                let (i, a) = self.axis_by_role(role).expect("roles checked above");
                if a.min_deg > 0.0 || a.max_deg < (n - 1) as f64 {
                    return Err(bad(
                        format!("axis[{i}] ({}).min_deg/max_deg", a.name),
                        format!("[{}, {}]", a.min_deg, a.max_deg),
                        &format!(
                            "a selector's position is the index into geometry.{list} ({n} entries): limits must cover 0 ..= {}",
                            n - 1
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// `[alignment]` and `[sim_misalignment]`: two-arm rigs only (the other kinds would
    /// silently ignore them), known axis names, finite angles below [`AlignmentSpec::MAX_DEG`].
    fn validate_alignment(&self, file: &str) -> Result<(), RigError> {
        for (table, a) in [
            ("alignment", &self.alignment),
            ("sim_misalignment", &self.sim_misalignment),
        ] {
            let Some(a) = a else { continue };
            let bad = |key: String, value: String, message: String| RigError::Invalid {
                file: file.to_string(),
                key,
                value,
                message,
            };
            if self.kind != RigKind::TwoArm {
                return Err(bad(
                    table.into(),
                    format!("{:?}", self.kind),
                    "only `two-arm` rigs have an alignment model".into(),
                ));
            }
            for (name, v) in &a.axis_zero_offset_deg {
                let key = format!("{table}.axis_zero_offset_deg.{name}");
                if !self.axes.iter().any(|x| &x.name == name) {
                    let names: Vec<&str> = self.axes.iter().map(|x| x.name.as_str()).collect();
                    return Err(bad(
                        key,
                        v.to_string(),
                        format!("no axis of that name; axes: {}", names.join(", ")),
                    ));
                }
                if !(v.is_finite() && v.abs() <= AlignmentSpec::MAX_DEG) {
                    return Err(bad(
                        key,
                        v.to_string(),
                        format!("valid range is ±{} degrees", AlignmentSpec::MAX_DEG),
                    ));
                }
            }
            let r = a.camera_rotation_deg;
            if !(r.iter().all(|x| x.is_finite())
                && r.iter().map(|x| x * x).sum::<f64>().sqrt() <= AlignmentSpec::MAX_DEG)
            {
                return Err(bad(
                    format!("{table}.camera_rotation_deg"),
                    format!("{r:?}"),
                    format!(
                        "the rotation's angle must be finite and ≤ {} degrees",
                        AlignmentSpec::MAX_DEG
                    ),
                ));
            }
        }
        Ok(())
    }

    /// Optional geometry keys: the holder rim and the kind-specific ones.
    fn validate_kind_geometry(&self, file: &str) -> Result<(), RigError> {
        let g = &self.geometry;
        let bad = |key: &str, value: String, message: &str| RigError::Invalid {
            file: file.to_string(),
            key: format!("geometry.{key}"),
            value,
            message: message.to_string(),
        };
        for (key, v) in [
            ("holder_rim_height_mm", g.holder_rim_height_mm),
            ("sample_size_mm", g.sample_size_mm),
            ("holder_rim_gap_mm", g.holder_rim_gap_mm),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(bad(key, v.to_string(), "must be a finite number ≥ 0"));
            }
        }
        if let Some(b) = &g.marker_border {
            if !(b.border_mm.is_finite() && b.border_mm > 0.0) {
                return Err(bad(
                    "marker_border.border_mm",
                    b.border_mm.to_string(),
                    "must be a finite number > 0 (the white frame's width, mm)",
                ));
            }
            if !(b.marker_mm.is_finite() && b.marker_mm > 0.0 && b.marker_mm < b.border_mm) {
                return Err(bad(
                    "marker_border.marker_mm",
                    b.marker_mm.to_string(),
                    "must be > 0 and smaller than marker_border.border_mm (a marker lies inside the border)",
                ));
            }
            if !(2..=64).contains(&b.markers_per_side) {
                return Err(bad(
                    "marker_border.markers_per_side",
                    b.markers_per_side.to_string(),
                    "valid range is 2..=64 (corners included)",
                ));
            }
        }
        if g.holder_rim_height_mm > 0.0 && g.sample_size_mm > 0.0 && g.holder_rim_gap_mm <= 0.0 {
            return Err(bad(
                "holder_rim_gap_mm",
                g.holder_rim_gap_mm.to_string(),
                "must be > 0 when a rim is on: a rim at the sample's very edge shadows every direction that is not straight overhead",
            ));
        }
        if !(g.fixed_light_elevation_deg.is_finite() && g.fixed_light_elevation_deg.abs() < 90.0) {
            return Err(bad(
                "fixed_light_elevation_deg",
                g.fixed_light_elevation_deg.to_string(),
                "valid range is -90 < fixed_light_elevation_deg < 90 degrees",
            ));
        }
        if !(g.dome_match_tolerance_deg.is_finite()
            && g.dome_match_tolerance_deg > 0.0
            && g.dome_match_tolerance_deg < 5.0)
        {
            return Err(bad(
                "dome_match_tolerance_deg",
                g.dome_match_tolerance_deg.to_string(),
                "valid range is 0 < dome_match_tolerance_deg < 5 degrees",
            ));
        }
        if let Some(name) = &g.dome_layout {
            if !matches!(self.kind, RigKind::Dome | RigKind::Lightdrum) {
                return Err(bad(
                    "dome_layout",
                    name.clone(),
                    "only a `dome` or `lightdrum` rig has a fixed layout",
                ));
            }
            if crate::kinematics::dome::layout(name).is_none() {
                return Err(bad(
                    "dome_layout",
                    name.clone(),
                    &format!("unknown layout; known: {}", crate::kinematics::dome::LAYOUTS.join(", ")),
                ));
            }
        }
        for (key, list) in [
            ("camera_directions_deg", &g.camera_directions_deg),
            ("light_directions_deg", &g.light_directions_deg),
        ] {
            let Some(list) = list else { continue };
            let lightdrum_lamps = self.kind == RigKind::Lightdrum && key == "light_directions_deg";
            if self.kind != RigKind::Dome && !lightdrum_lamps {
                return Err(bad(
                    key,
                    format!("{} entries", list.len()),
                    "only a `dome` rig has fixed direction lists",
                ));
            }
            if list.is_empty() || list.len() > 721 {
                return Err(bad(key, format!("{} entries", list.len()), "need 1 ..= 721 directions"));
            }
            let mut seen: Vec<crate::Direction> = Vec::with_capacity(list.len());
            for (i, &[t, p]) in list.iter().enumerate() {
                let entry = || format!("entry {i} [{t}, {p}]");
                if !(t.is_finite() && (0.0..90.0).contains(&t) && p.is_finite()) {
                    return Err(bad(key, entry(), "θ must be in [0°, 90°) and φ finite"));
                }
                let d = crate::Direction::from_degrees(t, p);
                if let Some(j) = seen.iter().position(|o| o.angle_to(d) < 1e-9) {
                    return Err(bad(key, entry(), &format!("duplicate of entry {j}")));
                }
                seen.push(d);
            }
        }
        if let Some(list) = &g.arc_camera_elevations_deg {
            let key = "arc_camera_elevations_deg";
            if self.kind != RigKind::Lightdrum {
                return Err(bad(
                    key,
                    format!("{list:?}"),
                    "only a `lightdrum` rig has an arc of cameras",
                ));
            }
            if list.is_empty() || list.len() > 181 {
                return Err(bad(key, format!("{} entries", list.len()), "need 1 ..= 181 elevations"));
            }
            for (i, &e) in list.iter().enumerate() {
                if !(e.is_finite() && e > -90.0 && e < 90.0) {
                    return Err(bad(
                        key,
                        format!("entry {i} ({e})"),
                        "valid range is -90 < elevation < 90 degrees",
                    ));
                }
                if let Some(j) = list[..i].iter().position(|&o| (o - e).abs() < 1e-9) {
                    return Err(bad(key, format!("entry {i} ({e})"), &format!("duplicate of entry {j}")));
                }
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
        assert!(e.contains("max_velocity_deg_s") && e.contains("valid range"), "{e}");
        let e = RigSpec::parse("name = 1", "x.toml").unwrap_err().to_string();
        assert!(e.contains("x.toml"), "{e}");
    }

    #[test]
    fn lamp_options_are_checked_and_name_the_key() {
        let r = RigSpec::default_rig();
        assert_eq!(r.lamp_monitor().unwrap().drift_threshold, DEFAULT_LAMP_DRIFT);
        assert_eq!(r.lamp_monitor().unwrap().output_exponent, None);
        assert_eq!(r.sim_lamp_nominal().unwrap(), None);
        let with = |extra: &str| DEFAULT_RIG_TOML.replace("[light]\n", &format!("[light]\n{extra}\n"));
        let ok = RigSpec::parse(
            &with("options = { drift_threshold = 0.05, output_exponent = 3.4, voltage = 12, current = 8.3 }"),
            "r.toml",
        )
        .unwrap();
        assert_eq!(
            ok.lamp_monitor().unwrap(),
            LampMonitor {
                drift_threshold: 0.05,
                output_exponent: Some(3.4)
            }
        );
        assert_eq!(ok.sim_lamp_nominal().unwrap().unwrap().current_a, 8.3);
        for (opt, key) in [
            ("drift_threshold = 2", "light.options.drift_threshold"),
            ("output_exponent = -1", "light.options.output_exponent"),
            ("voltage = 12", "light.options.current"),
        ] {
            let e = RigSpec::parse(&with(&format!("options = {{ {opt} }}")), "r.toml")
                .unwrap_err()
                .to_string();
            assert!(e.contains("r.toml") && e.contains(key), "{e}");
        }
    }

    #[test]
    fn alignment_tables_are_checked_and_name_the_key() {
        let ok = format!("{DEFAULT_RIG_TOML}\n[sim_misalignment]\naxis_zero_offset_deg = {{ turntable = 0.5 }}\n");
        let r = RigSpec::parse(&ok, "r.toml").unwrap();
        assert!(r.alignment.is_none(), "the truth is not known to the kinematics");
        assert_eq!(
            r.simulated_truth().alignment.unwrap().axis_zero_offset_deg["turntable"],
            0.5
        );
        let typo = format!("{DEFAULT_RIG_TOML}\n[alignment]\naxis_zero_offset_deg = {{ turntabel = 0.5 }}\n");
        let e = RigSpec::parse(&typo, "r.toml").unwrap_err().to_string();
        assert!(
            e.contains("alignment.axis_zero_offset_deg.turntabel") && e.contains("turntable"),
            "{e}"
        );
        let big = format!("{DEFAULT_RIG_TOML}\n[alignment]\ncamera_rotation_deg = [0.0, 12.0, 0.0]\n");
        let e = RigSpec::parse(&big, "r.toml").unwrap_err().to_string();
        assert!(e.contains("alignment.camera_rotation_deg"), "{e}");
    }

    #[test]
    fn the_holder_geometry_of_a_real_camera_comes_from_the_rig_file() {
        let r = RigSpec::parse(DEFAULT_RIG_TOML, "r.toml").unwrap();
        let (border, size) = r.holder_geometry().unwrap();
        assert_eq!((border, size), (MarkerBorder::default(), 50.0));
        let own = format!(
            "{DEFAULT_RIG_TOML}\n[geometry.marker_border]\nborder_mm = 12.0\nmarker_mm = 8.0\nmarkers_per_side = 4\n"
        );
        let (border, _) = RigSpec::parse(&own, "r.toml").unwrap().holder_geometry().unwrap();
        assert_eq!(
            (border.border_mm, border.marker_mm, border.markers_per_side),
            (12.0, 8.0, 4)
        );
        let big = own.replace("marker_mm = 8.0", "marker_mm = 13.0");
        let e = RigSpec::parse(&big, "r.toml").unwrap_err().to_string();
        assert!(e.contains("geometry.marker_border.marker_mm"), "{e}");
        let mut none = r.clone();
        none.geometry.sample_size_mm = 0.0;
        let e = none.holder_geometry().unwrap_err().to_string();
        assert!(e.contains("geometry.sample_size_mm") && e.contains("set"), "{e}");
    }

    #[test]
    fn optional_geometry_keys_are_checked_and_name_the_key() {
        let with_gap0 = DEFAULT_RIG_TOML.replace(
            "sample_size_mm = 50.0",
            "sample_size_mm = 50.0\nholder_rim_gap_mm = 0.0",
        );
        let e = RigSpec::parse(&with_gap0, "r.toml").unwrap_err().to_string();
        assert!(e.contains("geometry.holder_rim_gap_mm") && e.contains("> 0"), "{e}");
        let lists = DEFAULT_RIG_TOML.replace(
            "clearance_mm = 5.0",
            "clearance_mm = 5.0\ncamera_directions_deg = [[0, 0]]",
        );
        let e = RigSpec::parse(&lists, "r.toml").unwrap_err().to_string();
        assert!(
            e.contains("geometry.camera_directions_deg") && e.contains("dome"),
            "{e}"
        );
        let neg = DEFAULT_RIG_TOML.replace("holder_rim_height_mm = 1.5", "holder_rim_height_mm = -1.0");
        let e = RigSpec::parse(&neg, "r.toml").unwrap_err().to_string();
        assert!(e.contains("geometry.holder_rim_height_mm"), "{e}");
        // a rig of one kind with another kind's roles names the missing role
        let wrong = DEFAULT_RIG_TOML.replace("kind = \"two-arm\"", "kind = \"gimbal\"");
        let e = RigSpec::parse(&wrong, "r.toml").unwrap_err().to_string();
        assert!(e.contains("light_arc"), "{e}");
    }
}
