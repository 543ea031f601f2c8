//! Mechanical calibration: homing repeatability, backlash and positioning error per axis.
//!
//! The read-back of an axis is the controller's step count; it cannot see backlash, homing
//! scatter or drive errors. This run therefore needs an independent reference of where the
//! load really is: [`gonio_devices::Axis::reference_position`] (a load-side encoder; on the
//! simulator, the `options.mechanical` error model's load side). An axis without one is
//! refused with a clear error rather than "measured" as perfect.
//!
//! **The camera as the reference** (`reference = "camera"`): most rigs have no load-side
//! encoder, but the camera sees where the sample holder really is. With the checkerboard
//! target on the holder and the camera parked at `camera_view_deg`, every arrival takes a
//! frame; the detected corners are back-projected onto the sample plane through the
//! nominal camera pose (the measured axis at 0) and a 2-D rigid fit (Procrustes) of the
//! board's corner grid to them gives the holder's in-plane rotation. That observes exactly
//! the axes that turn the sample about its normal (the turntable); any other axis is
//! refused before anything moves, because its error would show as a shift or a tilt of the
//! board that a nominal pose cannot tell from a camera error. Constant biases (the board's
//! placement, the other axes' offsets) fall into the positioning offset; backlash,
//! repeatability, scale and periodic errors are differences and are measured.
//!
//! The scripted run, for each axis of the recipe's `[mechanical]` section:
//!
//! 1. **Homing**: `home_cycles` times: move `home_away_deg` away, home, read reference and
//!    read-back. Repeatability = sample standard deviation of (reference − read-back).
//! 2. **Bidirectional targets**, `repetitions` passes: each target is approached from below
//!    (`target − approach_deg` first) and from above (`target + approach_deg` first); at each
//!    arrival the deviation (reference − read-back) is recorded. Backlash = deviation from
//!    above − deviation from below, averaged over targets and passes.
//! 3. **Positioning error**: the mean of both approaches (backlash cancels) per target, fitted
//!    by offset + scale × position (least squares); the residual is the non-linear part
//!    (periodic error). The offset includes the last homing's zero offset.
//!
//! On a simulated rig every estimate is compared with the rig file's error model (and the
//! homing offsets the simulator actually drew), and an effort table gives the estimate
//! errors against the number of cycles / passes used and the rig time they took.

use super::recipe::Recipe;
use crate::rig::{CapturePolicy, MechanicalErrors, Rig};
use gonio_devices::{Axis, CameraConfig, DeviceError};
use serde::{Deserialize, Serialize};
use std::sync::Arc;
use thiserror::Error;

/// The recipe's `[mechanical]` section.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MechanicalSpec {
    /// Axes by rig-file name; empty: every axis of the rig.
    pub axes: Vec<String>,
    /// Homing cycles for the repeatability (≥ 2).
    pub home_cycles: usize,
    /// How far (degrees, positive side) each homing cycle first moves away from home, so
    /// every homing is a real search from a distance.
    pub home_away_deg: f64,
    /// Bidirectional passes over the targets (≥ 1).
    pub repetitions: usize,
    /// Explicit targets in degrees (every axis); empty: `target_count` targets spread
    /// evenly over the central `span` fraction of each axis' soft range.
    pub targets_deg: Vec<f64>,
    pub target_count: usize,
    pub span: f64,
    /// Approach distance (degrees): each target is reached after a move from this far below
    /// or above; it must exceed the backlash to take the play up.
    pub approach_deg: f64,
    /// Where the load position comes from: `encoder` (`Axis::reference_position`) or
    /// `camera` (the checkerboard target seen by the rig's camera, see the module docs).
    pub reference: ReferenceKind,
    /// Camera reference: the view direction `[θ, φ]` (degrees) the camera is parked at; the
    /// lamp goes to the recipe's `light`.
    pub camera_view_deg: [f64; 2],
}

/// [`MechanicalSpec::reference`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ReferenceKind {
    #[default]
    Encoder,
    Camera,
}

impl ReferenceKind {
    fn name(self) -> &'static str {
        match self {
            ReferenceKind::Encoder => "encoder",
            ReferenceKind::Camera => "camera",
        }
    }
}

impl Default for MechanicalSpec {
    fn default() -> Self {
        MechanicalSpec {
            axes: Vec::new(),
            home_cycles: 10,
            home_away_deg: 10.0,
            repetitions: 2,
            targets_deg: Vec::new(),
            target_count: 9,
            span: 0.8,
            approach_deg: 1.0,
            reference: ReferenceKind::Encoder,
            camera_view_deg: [0.0, 0.0],
        }
    }
}

impl MechanicalSpec {
    /// Check ranges; `Err((key, message))`.
    pub fn validate(&self) -> Result<(), (String, String)> {
        let bad = |k: &str, m: String| Err((format!("mechanical.{k}"), m));
        if !(2..=10_000).contains(&self.home_cycles) {
            return bad(
                "home_cycles",
                format!("{}: valid range is 2 ..= 10000 (a spread needs two)", self.home_cycles),
            );
        }
        if !(1..=1000).contains(&self.repetitions) {
            return bad(
                "repetitions",
                format!("{}: valid range is 1 ..= 1000", self.repetitions),
            );
        }
        if !(self.approach_deg.is_finite() && self.approach_deg > 0.0 && self.approach_deg <= 90.0) {
            return bad(
                "approach_deg",
                format!("{}: must be in (0, 90] degrees", self.approach_deg),
            );
        }
        if !(self.home_away_deg.is_finite() && self.home_away_deg >= 0.0 && self.home_away_deg <= 360.0) {
            return bad(
                "home_away_deg",
                format!("{}: must be in [0, 360] degrees", self.home_away_deg),
            );
        }
        if !self.camera_view_deg.iter().all(|v| v.is_finite()) {
            return bad(
                "camera_view_deg",
                format!("{:?}: not a direction in degrees", self.camera_view_deg),
            );
        }
        if !(self.span.is_finite() && self.span > 0.0 && self.span <= 1.0) {
            return bad("span", format!("{}: must be in (0, 1]", self.span));
        }
        if self.targets_deg.is_empty() {
            if !(3..=1000).contains(&self.target_count) {
                return bad(
                    "target_count",
                    format!(
                        "{}: valid range is 3 ..= 1000 (a line fit with a residual needs 3)",
                        self.target_count
                    ),
                );
            }
        } else {
            if self.targets_deg.len() < 3 {
                return bad(
                    "targets_deg",
                    format!(
                        "{} targets: a line fit with a residual needs at least 3",
                        self.targets_deg.len()
                    ),
                );
            }
            if let Some(t) = self.targets_deg.iter().find(|t| !t.is_finite()) {
                return bad("targets_deg", format!("{t}: not a number of degrees"));
            }
        }
        Ok(())
    }
}

#[derive(Debug, Error)]
pub enum MechanicalError {
    #[error(
        "recipe `{recipe}`: axis `{axis}` has no independent position reference (no load-side encoder): \
         its read-back cannot see backlash or homing scatter. Give it one (Zaber: options.encoder = true on a \
         stage with an encoder; simulated axes: options.mechanical) or leave it out of mechanical.axes"
    )]
    NoReference { recipe: String, axis: String },
    #[error("recipe `{recipe}`: mechanical.axes: rig `{rig}` has no axis `{axis}` (axes: {available})")]
    UnknownAxis {
        recipe: String,
        rig: String,
        axis: String,
        available: String,
    },
    #[error(
        "recipe `{recipe}`: axis `{axis}`: target {target_deg}° ± approach {approach_deg}° leaves the soft limits [{min_deg}°, {max_deg}°]"
    )]
    TargetOutOfRange {
        recipe: String,
        axis: String,
        target_deg: f64,
        approach_deg: f64,
        min_deg: f64,
        max_deg: f64,
    },
    #[error(
        "recipe `{recipe}`: axis `{axis}` cannot be measured through the camera: {reason}. Only axes that turn the \
         sample about its normal (a turntable) are observable this way; use an encoder reference \
         (reference = \"encoder\") or leave the axis out of mechanical.axes"
    )]
    NotObservable {
        recipe: String,
        axis: String,
        reason: String,
    },
    #[error(
        "recipe `{recipe}`: reference = \"camera\" needs the board geometry: add checkerboard = {{ cols = …, rows = …, pitch_mm = … }} or coded_board = {{ squares_x = …, squares_y = …, pitch_mm = …, marker_mm = … }}"
    )]
    NoBoard { recipe: String },
    #[error("recipe `{recipe}`: axis `{axis}`: camera reference at read-back {read_back_deg:.4}°: {message}")]
    CameraReference {
        recipe: String,
        axis: String,
        read_back_deg: f64,
        message: String,
    },
    /// The camera failed every attempt the capture policy allows for a reference frame.
    #[error(
        "recipe `{recipe}`: axis `{axis}`: reference frame at read-back {read_back_deg:.4}°: camera failed after {attempts} attempt(s): {cause}"
    )]
    Capture {
        recipe: String,
        axis: String,
        read_back_deg: f64,
        attempts: u32,
        cause: DeviceError,
    },
    #[error("recipe `{recipe}`: parking the camera for the camera reference: {cause}")]
    Setup {
        recipe: String,
        cause: Box<super::CalibrateError>,
    },
    #[error("recipe `{recipe}`: axis `{axis}`: {command}: {cause}")]
    Device {
        recipe: String,
        axis: String,
        command: String,
        cause: DeviceError,
    },
}

/// Homing repeatability of one axis.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct HomingStats {
    pub cycles: usize,
    /// Reference − read-back after each homing (degrees).
    pub deviations_deg: Vec<f64>,
    pub mean_deg: f64,
    /// Sample standard deviation of the deviations: the homing repeatability (1 σ).
    pub repeatability_deg: f64,
    /// Largest − smallest deviation.
    pub range_deg: f64,
}

/// One target of the bidirectional run (averaged over passes).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TargetRow {
    pub target_deg: f64,
    /// Mean read-back at the target (degrees).
    pub read_back_deg: f64,
    /// Reference − read-back arriving from below / from above (degrees, mean over passes).
    pub deviation_below_deg: f64,
    pub deviation_above_deg: f64,
    /// Above − below: this target's backlash.
    pub backlash_deg: f64,
    /// Mean of both approaches minus the fitted line.
    pub residual_deg: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct BacklashStats {
    /// Samples (targets × passes).
    pub samples: usize,
    pub mean_deg: f64,
    /// Sample standard deviation of the individual samples.
    pub std_deg: f64,
}

/// Positioning error (reference − read-back, both approaches averaged) fitted as
/// `offset + scale_error × read-back`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PositioningFit {
    pub offset_deg: f64,
    pub scale_error: f64,
    /// RMS and largest absolute residual after the line: the non-linear (periodic) error.
    pub residual_rms_deg: f64,
    pub residual_max_deg: f64,
}

/// The simulator's truth for one axis (rig file `options.mechanical` + the drawn offsets).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct AxisTruth {
    pub model: MechanicalErrors,
    /// Sample standard deviation of the homing offsets drawn during this run's cycles.
    pub realized_repeatability_deg: f64,
    /// The drive's positioning error at the targets fitted the same way as the estimate
    /// (the model's scale error is only the linear part of it over a finite set of targets).
    pub fit: PositioningFit,
}

/// Estimate − truth for one axis.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct AxisErrors {
    pub backlash_deg: f64,
    /// Against the homing offsets actually drawn in this run, and against the model's σ.
    pub repeatability_vs_realized_deg: f64,
    pub repeatability_vs_model_deg: f64,
    pub offset_deg: f64,
    pub scale_error: f64,
    pub scale_error_vs_model: f64,
    pub residual_rms_deg: f64,
}

/// One row of the error-versus-effort table.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct EffortRow {
    /// `homing` (rows per cycle count) or `bidirectional` (rows per pass count).
    pub stage: String,
    /// Cycles or passes used.
    pub used: usize,
    /// Rig time spent on this stage up to here (s; virtual on the simulator).
    pub rig_time_s: f64,
    /// The estimate from the first `used` cycles / passes.
    pub estimate_deg: f64,
    /// Its error against the truth (simulator: the model's homing σ, the model's backlash)
    /// or against the estimate from everything (real rigs).
    pub error_deg: f64,
    /// Bidirectional rows: scale error estimate and its error.
    pub scale_error: Option<f64>,
    pub scale_error_error: Option<f64>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct AxisMechanics {
    pub axis: String,
    /// Where the reference came from (`encoder`).
    pub reference: String,
    pub homing: HomingStats,
    pub backlash: BacklashStats,
    pub positioning: PositioningFit,
    pub targets: Vec<TargetRow>,
    pub truth: Option<AxisTruth>,
    pub errors: Option<AxisErrors>,
    pub effort: Vec<EffortRow>,
    pub rig_time_s: f64,
}

/// The `mechanical` part of `calibration.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct MechanicalCalibration {
    pub approach_deg: f64,
    pub axes: Vec<AxisMechanics>,
}

fn mean(x: &[f64]) -> f64 {
    if x.is_empty() {
        return f64::NAN;
    }
    x.iter().sum::<f64>() / x.len() as f64
}

/// Sample standard deviation (n − 1); 0 for fewer than two values.
fn sample_std(x: &[f64]) -> f64 {
    if x.len() < 2 {
        return 0.0;
    }
    let m = mean(x);
    (x.iter().map(|v| (v - m).powi(2)).sum::<f64>() / (x.len() - 1) as f64).sqrt()
}

/// Least-squares line `y = a + b x`; residual RMS and max. Needs ≥ 2 distinct x.
pub fn fit_line(x: &[f64], y: &[f64]) -> PositioningFit {
    let mx = mean(x);
    let my = mean(y);
    let sxx: f64 = x.iter().map(|v| (v - mx).powi(2)).sum();
    let sxy: f64 = x.iter().zip(y).map(|(a, b)| (a - mx) * (b - my)).sum();
    let b = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    let a = my - b * mx;
    let res: Vec<f64> = x.iter().zip(y).map(|(u, v)| v - a - b * u).collect();
    PositioningFit {
        offset_deg: a,
        scale_error: b,
        residual_rms_deg: (res.iter().map(|r| r * r).sum::<f64>() / res.len().max(1) as f64).sqrt(),
        residual_max_deg: res.iter().fold(0.0, |m, r| m.max(r.abs())),
    }
}

/// The targets (degrees) for an axis with soft limits `[lo, hi]` (degrees).
fn targets_for(spec: &MechanicalSpec, lo: f64, hi: f64) -> Vec<f64> {
    if !spec.targets_deg.is_empty() {
        return spec.targets_deg.clone();
    }
    let c = 0.5 * (lo + hi);
    let half = 0.5 * (hi - lo) * spec.span - spec.approach_deg;
    let n = spec.target_count;
    (0..n)
        .map(|i| c - half + 2.0 * half * i as f64 / (n - 1) as f64)
        .map(|t| (t * 1e6).round() / 1e6)
        .collect()
}

/// 2-D rigid fit `q ≈ R(β)·p + t` (Procrustes, centroids removed): β in degrees and the
/// RMS residual (same unit as the points). A mirrored labelling of `p` (the detector may
/// number a square board's grid either way round) is undone first: `p`'s y is flipped when
/// the cross-covariance says the two sets differ by a reflection.
fn rigid_angle_deg(p: &[[f64; 2]], q: &[[f64; 2]]) -> (f64, f64) {
    let n = p.len().max(1) as f64;
    let centroid = |v: &[[f64; 2]]| {
        let s = v.iter().fold([0.0, 0.0], |a, x| [a[0] + x[0], a[1] + x[1]]);
        [s[0] / n, s[1] / n]
    };
    let (cq, cp0) = (centroid(q), centroid(p));
    let cov = |flip: f64| {
        let mut m = [[0.0; 2]; 2];
        for (a, b) in p.iter().zip(q) {
            let pa = [a[0] - cp0[0], flip * (a[1] - cp0[1])];
            let qb = [b[0] - cq[0], b[1] - cq[1]];
            for i in 0..2 {
                for j in 0..2 {
                    m[i][j] += pa[i] * qb[j];
                }
            }
        }
        m
    };
    let m = cov(1.0);
    let flip = if m[0][0] * m[1][1] - m[0][1] * m[1][0] < 0.0 {
        -1.0
    } else {
        1.0
    };
    let m = cov(flip);
    let beta = (m[0][1] - m[1][0]).atan2(m[0][0] + m[1][1]);
    let (c, s_) = (beta.cos(), beta.sin());
    let mut sse = 0.0;
    for (a, b) in p.iter().zip(q) {
        let pa = [a[0] - cp0[0], flip * (a[1] - cp0[1])];
        let r = [c * pa[0] - s_ * pa[1], s_ * pa[0] + c * pa[1]];
        sse += (r[0] - (b[0] - cq[0])).powi(2) + (r[1] - (b[1] - cq[1])).powi(2);
    }
    (beta.to_degrees(), (sse / n).sqrt())
}

/// The camera as the position reference of one axis (see the module docs).
struct CameraReference {
    board: gonio_calibration::board::Board,
    detection: gonio_calibration::checkerboard::CheckerboardOptions,
    camera: gonio_calibration::intrinsics::CameraModel,
    /// Image (px, undistorted) → sample plane (mm) for the nominal pose with the measured
    /// axis at 0.
    image_to_plane: gonio_calibration::homography::Homography,
    /// +1 or −1: the board's in-plane rotation per degree of the axis.
    sign: f64,
}

impl CameraReference {
    /// Set up for axis `index` with the other axes at `q_parked` (radians); refuses an axis
    /// whose motion is not a rotation of the sample about its normal.
    // Called once per axis before anything moves; the error's size costs nothing here.
    #[allow(clippy::result_large_err)]
    fn new(
        recipe: &Recipe,
        rig: &Rig,
        index: usize,
        q_parked: &[f64],
        spec_view: [f64; 2],
    ) -> Result<CameraReference, MechanicalError> {
        use gonio_calibration::homography::Homography;
        let axis = rig.axes[index].name().to_string();
        let board = recipe.board().ok_or_else(|| MechanicalError::NoBoard {
            recipe: recipe.name.clone(),
        })?;
        let intr = rig.spec.camera.intrinsics();
        let at = |deg: f64| {
            let mut q = q_parked.to_vec();
            q[index] = deg.to_radians();
            Homography::from_pose(&intr, &rig.kinematics.camera_pose(&q))
        };
        let h0 = at(0.0);
        let not = |reason: String| MechanicalError::NotObservable {
            recipe: recipe.name.clone(),
            axis: axis.clone(),
            reason,
        };
        let inv = h0
            .inverse()
            .ok_or_else(|| not("the parked camera does not see the sample plane".into()))?;
        // Move the axis by δ in the kinematics and look where a ±20 mm square of sample
        // points lands on the nominal plane: a turntable turns it by ±δ in place. Both a
        // large δ and one of the size of the errors measured, so a pose that follows only
        // large moves (a kinematic singularity) is caught too.
        let p: Vec<[f64; 2]> = (0..25)
            .map(|k| [((k % 5) as f64 - 2.0) * 10.0, ((k / 5) as f64 - 2.0) * 10.0])
            .collect();
        let mut sign = 0.0;
        for delta in [5.0, 0.01] {
            let h1 = at(delta);
            let mut q = Vec::new();
            for x in &p {
                let w = h1
                    .apply(x[0], x[1])
                    .and_then(|(u, v)| inv.apply(u, v))
                    .ok_or_else(|| not("the sample leaves the camera's view when the axis moves".into()))?;
                q.push([w.0, w.1]);
            }
            let (beta, rms) = rigid_angle_deg(&p, &q);
            let shift = {
                let c = q.iter().fold([0.0, 0.0], |a, x| [a[0] + x[0], a[1] + x[1]]);
                (c[0] / 25.0).hypot(c[1] / 25.0)
            };
            if rms > 1e-3 || shift > 1e-3 || ((beta.abs() - delta).abs() > 1e-3 * delta) {
                return Err(not(format!(
                    "at the parked view {:?}° a {delta}° move of it turns the sample by {beta:.5}° about its normal, \
                     shifts it by {shift:.3} mm and deforms it by {rms:.3} mm RMS in the camera's view",
                    spec_view
                )));
            }
            sign = beta.signum();
        }
        Ok(CameraReference {
            board,
            detection: recipe.detection.clone(),
            camera: super::offset_fit::camera_model(&rig.spec).map_err(|e| not(e.to_string()))?,
            image_to_plane: inv,
            sign,
        })
    }

    /// The axis position (degrees) the camera sees: the board's in-plane rotation, taken
    /// within ±45° of the read-back (the square board's labelling repeats every 90°).
    fn position_deg(&self, frame: &gonio_devices::Frame, read_back_deg: f64) -> Result<f64, String> {
        let raw = crate::develop::frame_to_linear(frame);
        let det = self.board.detect(&raw, &self.detection).map_err(|e| e.to_string())?;
        let (cam, mut plane) = (&self.camera, Vec::with_capacity(det.image.len()));
        for px in &det.image {
            let (x, y) = cam.undistort(px[0], px[1]);
            let (u, v) = (cam.fx * x + cam.cx, cam.fy * y + cam.cy);
            let w = self
                .image_to_plane
                .apply(u, v)
                .ok_or("a corner maps behind the camera")?;
            plane.push([w.0, w.1]);
        }
        let (beta, rms) = rigid_angle_deg(&det.object, &plane);
        if rms > 0.05 * self.board.pitch_mm() {
            return Err(format!(
                "the detected corners do not fit a rigid board on the sample plane ({rms:.3} mm RMS): the camera \
                 pose or the board is not what the rig file says"
            ));
        }
        let a = self.sign * beta;
        tracing::debug!(
            read_back_deg,
            board_deg = a,
            rms_mm = rms,
            corners = plane.len(),
            "camera reference"
        );
        Ok(a + 90.0 * ((read_back_deg - a) / 90.0).round())
    }
}

/// One arrival: read-back and reference (degrees).
struct Arrival {
    read_back: f64,
    reference: f64,
}

struct AxisRun<'a> {
    recipe: &'a str,
    axis: &'a Arc<dyn Axis>,
    /// The axis' index in the rig.
    index: usize,
    rig: &'a Rig,
    camera: Option<&'a CameraReference>,
    /// The rig's capture policy (saturation only flagged) and the camera's configuration.
    capture: Option<(CapturePolicy, CameraConfig)>,
}

impl AxisRun<'_> {
    fn err(&self, command: &str, cause: DeviceError) -> MechanicalError {
        MechanicalError::Device {
            recipe: self.recipe.into(),
            axis: self.axis.name().into(),
            command: command.into(),
            cause,
        }
    }

    /// Move to `deg` degrees; returns the read-back in radians (the axis' unit).
    async fn move_to(&self, deg: f64) -> Result<f64, MechanicalError> {
        // One axis alone (the approach side is the point), then the rig is still.
        self.rig
            .reach_axis(self.index, deg.to_radians())
            .await
            .map_err(|e| self.err(&format!("move to {deg}°"), e))
    }

    async fn read(&self, read_back_rad: f64) -> Result<Arrival, MechanicalError> {
        if let Some(cam) = self.camera {
            let read_back = read_back_rad.to_degrees();
            let (policy, config) = self.capture.as_ref().expect("set with a camera reference");
            let (frame, _) = self
                .rig
                .capture(policy, config)
                .await
                .map_err(|f| MechanicalError::Capture {
                    recipe: self.recipe.into(),
                    axis: self.axis.name().into(),
                    read_back_deg: read_back,
                    attempts: f.attempts,
                    cause: f.source,
                })?;
            let reference =
                cam.position_deg(&frame, read_back)
                    .map_err(|message| MechanicalError::CameraReference {
                        recipe: self.recipe.into(),
                        axis: self.axis.name().into(),
                        read_back_deg: read_back,
                        message,
                    })?;
            return Ok(Arrival { read_back, reference });
        }
        let reference = self
            .axis
            .reference_position()
            .await
            .map_err(|e| self.err("read reference", e))?
            .ok_or_else(|| MechanicalError::NoReference {
                recipe: self.recipe.into(),
                axis: self.axis.name().into(),
            })?;
        Ok(Arrival {
            read_back: read_back_rad.to_degrees(),
            reference: reference.to_degrees(),
        })
    }

    async fn home(&self) -> Result<Arrival, MechanicalError> {
        self.axis.home().await.map_err(|e| self.err("home", e))?;
        let p = self.axis.position().await.map_err(|e| self.err("read position", e))?;
        self.read(p).await
    }
}

/// Run the mechanical recipe.
pub async fn run_mechanical(
    recipe: &Recipe,
    spec: &MechanicalSpec,
    rig: &Rig,
) -> Result<MechanicalCalibration, MechanicalError> {
    let names: Vec<String> = if spec.axes.is_empty() {
        rig.axes.iter().map(|a| a.name().to_string()).collect()
    } else {
        spec.axes.clone()
    };
    let mut indices = Vec::new();
    for n in &names {
        let i = rig
            .axes
            .iter()
            .position(|a| a.name() == n)
            .ok_or_else(|| MechanicalError::UnknownAxis {
                recipe: recipe.name.clone(),
                rig: rig.spec.name.clone(),
                axis: n.clone(),
                available: rig.axes.iter().map(|a| a.name()).collect::<Vec<_>>().join(", "),
            })?;
        indices.push(i);
    }
    // Check every target before anything moves.
    let mut plans = Vec::new();
    for &i in &indices {
        let axis = &rig.axes[i];
        let lim = axis.limits();
        let (lo, hi) = (lim.min.to_degrees(), lim.max.to_degrees());
        let targets = targets_for(spec, lo, hi);
        let eps = 1e-9;
        for &t in &targets {
            if t - spec.approach_deg < lo - eps || t + spec.approach_deg > hi + eps {
                return Err(MechanicalError::TargetOutOfRange {
                    recipe: recipe.name.clone(),
                    axis: axis.name().into(),
                    target_deg: t,
                    approach_deg: spec.approach_deg,
                    min_deg: lo,
                    max_deg: hi,
                });
            }
        }
        plans.push((i, targets));
    }
    // Camera reference: home, set the camera up, park camera and lamp, then check every
    // listed axis is observable before any of them is measured.
    let mut cameras: Vec<Option<CameraReference>> = plans.iter().map(|_| None).collect();
    let mut camera_config: Option<CameraConfig> = None;
    if spec.reference == ReferenceKind::Camera {
        if recipe.board().is_none() {
            return Err(MechanicalError::NoBoard {
                recipe: recipe.name.clone(),
            });
        }
        let setup = |cause| MechanicalError::Setup {
            recipe: recipe.name.clone(),
            cause: Box::new(cause),
        };
        camera_config = Some(super::prepare_rig(recipe, rig).await.map_err(setup)?);
        let (_, q_parked) = super::reach_pose(recipe, rig, 0, spec.camera_view_deg, recipe.light, None)
            .await
            .map_err(setup)?;
        for (slot, (i, _)) in cameras.iter_mut().zip(&plans) {
            *slot = Some(CameraReference::new(recipe, rig, *i, &q_parked, spec.camera_view_deg)?);
        }
    }
    let mut axes = Vec::new();
    for ((i, targets), cam) in plans.into_iter().zip(&cameras) {
        let capture = match (cam, &camera_config) {
            (Some(_), Some(c)) => Some((
                super::calibration_policy(recipe, rig).map_err(|cause| MechanicalError::Setup {
                    recipe: recipe.name.clone(),
                    cause: Box::new(cause),
                })?,
                c.clone(),
            )),
            _ => None,
        };
        axes.push(run_axis(recipe, spec, rig, i, &targets, cam.as_ref(), capture).await?);
    }
    Ok(MechanicalCalibration {
        approach_deg: spec.approach_deg,
        axes,
    })
}

/// `gonio calibrate` entry: run the recipe's `[mechanical]` section (defaults if absent)
/// and build the versioned result.
pub async fn run(recipe: &Recipe, rig: &Rig) -> Result<super::RunOutput, super::CalibrateError> {
    let spec = recipe.mechanical.clone().unwrap_or_default();
    let t0 = rig.time();
    let m = run_mechanical(recipe, &spec, rig)
        .await
        .map_err(|e| super::CalibrateError::Mechanical(Box::new(e)))?;
    let result = super::CalibrationResult {
        mechanical: Some(m),
        rig_time_s: rig.time() - t0,
        ..super::CalibrationResult::new(recipe, rig.spec.name.clone(), rig.clock.is_some())
    }
    .seal();
    Ok(super::RunOutput { result, corners: None })
}

/// The simulator's error model of axis `index` (the truth; `None` on hardware).
fn sim_model(rig: &Rig, index: usize) -> Option<MechanicalErrors> {
    rig.mechanical_truth(index)
}

async fn run_axis(
    recipe: &Recipe,
    spec: &MechanicalSpec,
    rig: &Rig,
    index: usize,
    targets: &[f64],
    camera: Option<&CameraReference>,
    capture: Option<(CapturePolicy, CameraConfig)>,
) -> Result<AxisMechanics, MechanicalError> {
    let axis = &rig.axes[index];
    let run = AxisRun {
        recipe: &recipe.name,
        axis,
        index,
        rig,
        camera,
        capture,
    };
    let name = axis.name().to_string();
    let t0 = rig.time();
    let lim = axis.limits();
    let hi = lim.max.to_degrees();
    tracing::info!(axis = %name, cycles = spec.home_cycles, targets = targets.len(), passes = spec.repetitions, "mechanical calibration");

    // 1. Homing repeatability.
    let first_home_index = rig.truth.as_ref().map(|t| t.home_offsets_deg(index).len()).unwrap_or(0);
    // A first homing so that moves are allowed; it is not one of the cycles.
    run.home().await?;
    let first_home_index = first_home_index + 1;
    let mut deviations = Vec::new();
    let mut home_times = Vec::new();
    let away = spec.home_away_deg.min(hi);
    for _ in 0..spec.home_cycles {
        if away > 0.0 {
            run.move_to(away).await?;
        }
        let a = run.home().await?;
        deviations.push(a.reference - a.read_back);
        home_times.push(run.rig.time() - t0);
    }
    let homing = HomingStats {
        cycles: deviations.len(),
        mean_deg: mean(&deviations),
        repeatability_deg: sample_std(&deviations),
        range_deg: deviations.iter().fold(f64::NEG_INFINITY, |m, v| m.max(*v))
            - deviations.iter().fold(f64::INFINITY, |m, v| m.min(*v)),
        deviations_deg: deviations,
    };
    if camera.is_some() && homing.range_deg == 0.0 {
        // A real reference never reads the same to the last bit after different homings:
        // the camera did not resolve the scatter, so every figure below would be noise-free
        // fiction.
        return Err(MechanicalError::CameraReference {
            recipe: recipe.name.clone(),
            axis: name,
            read_back_deg: 0.0,
            message: format!(
                "{} homings read exactly the same angle: the camera does not resolve the axis' scatter (raise \
                 the magnification, or on the simulator the recipe's [simulator] supersample)",
                homing.cycles
            ),
        });
    }
    let t_home_end = rig.time();

    // 2. Bidirectional approach to every target, `repetitions` passes.
    // below[pass][target], above[pass][target]: (read-back, deviation)
    let mut below = Vec::new();
    let mut above = Vec::new();
    let mut pass_times = Vec::new();
    for _ in 0..spec.repetitions {
        let mut b = Vec::new();
        let mut a = Vec::new();
        for &t in targets {
            run.move_to(t - spec.approach_deg).await?;
            let rb = run.move_to(t).await?;
            let x = run.read(rb).await?;
            b.push((x.read_back, x.reference - x.read_back));
            run.move_to(t + spec.approach_deg).await?;
            let rb = run.move_to(t).await?;
            let x = run.read(rb).await?;
            a.push((x.read_back, x.reference - x.read_back));
        }
        below.push(b);
        above.push(a);
        pass_times.push(rig.time() - t_home_end);
    }
    // Leave the axis at home position (read-back 0) for whatever runs next.
    run.move_to(0.0f64.clamp(lim.min.to_degrees(), hi)).await?;

    let summarize = |passes: usize| -> (Vec<TargetRow>, BacklashStats, PositioningFit) {
        let mut rows = Vec::new();
        let mut samples = Vec::new();
        for (k, &t) in targets.iter().enumerate() {
            let lo: Vec<f64> = below[..passes].iter().map(|p| p[k].1).collect();
            let up: Vec<f64> = above[..passes].iter().map(|p| p[k].1).collect();
            let rb: Vec<f64> = below[..passes].iter().chain(&above[..passes]).map(|p| p[k].0).collect();
            samples.extend(lo.iter().zip(&up).map(|(l, u)| u - l));
            rows.push(TargetRow {
                target_deg: t,
                read_back_deg: mean(&rb),
                deviation_below_deg: mean(&lo),
                deviation_above_deg: mean(&up),
                backlash_deg: mean(&up) - mean(&lo),
                residual_deg: 0.0,
            });
        }
        let x: Vec<f64> = rows.iter().map(|r| r.read_back_deg).collect();
        let y: Vec<f64> = rows
            .iter()
            .map(|r| 0.5 * (r.deviation_below_deg + r.deviation_above_deg))
            .collect();
        let fit = fit_line(&x, &y);
        for (r, (xi, yi)) in rows.iter_mut().zip(x.iter().zip(&y)) {
            r.residual_deg = yi - fit.offset_deg - fit.scale_error * xi;
        }
        let stats = BacklashStats {
            samples: samples.len(),
            mean_deg: mean(&samples),
            std_deg: sample_std(&samples),
        };
        (rows, stats, fit)
    };
    let (rows, backlash, positioning) = summarize(spec.repetitions);

    // Truth on the simulator.
    let truth = sim_model(rig, index).map(|model| {
        let offsets = rig
            .truth
            .as_ref()
            .map(|t| t.home_offsets_deg(index))
            .unwrap_or_default();
        let cycles: Vec<f64> = offsets
            .get(first_home_index..(first_home_index + spec.home_cycles).min(offsets.len()))
            .map(|s| s.to_vec())
            .unwrap_or_default();
        let last_zero = offsets.last().copied().unwrap_or(0.0);
        // The bidirectional mean at target x: zero + (e(x − b/2) + e(x + b/2)) / 2.
        let h = 0.5 * model.backlash_deg;
        let x: Vec<f64> = rows.iter().map(|r| r.read_back_deg).collect();
        let y: Vec<f64> = x
            .iter()
            .map(|&v| last_zero + 0.5 * (model.positioning_error_deg(v - h) + model.positioning_error_deg(v + h)))
            .collect();
        (
            AxisTruth {
                model,
                realized_repeatability_deg: sample_std(&cycles),
                fit: fit_line(&x, &y),
            },
            cycles,
        )
    });
    let errors = truth.as_ref().map(|(t, _)| AxisErrors {
        backlash_deg: backlash.mean_deg - t.model.backlash_deg,
        repeatability_vs_realized_deg: homing.repeatability_deg - t.realized_repeatability_deg,
        repeatability_vs_model_deg: homing.repeatability_deg - t.model.home_sigma_deg,
        offset_deg: positioning.offset_deg - t.fit.offset_deg,
        scale_error: positioning.scale_error - t.fit.scale_error,
        scale_error_vs_model: positioning.scale_error - t.model.scale_error,
        residual_rms_deg: positioning.residual_rms_deg - t.fit.residual_rms_deg,
    });

    // Error against effort.
    let mut effort = Vec::new();
    for k in 2..=homing.cycles {
        let est = sample_std(&homing.deviations_deg[..k]);
        // Against the model's σ: how many cycles it takes to know the repeatability (the
        // estimate matches the offsets actually drawn exactly, see `errors`).
        let reference = match &truth {
            Some((t, _)) => t.model.home_sigma_deg,
            None => homing.repeatability_deg,
        };
        effort.push(EffortRow {
            stage: "homing".into(),
            used: k,
            rig_time_s: home_times[k - 1],
            estimate_deg: est,
            error_deg: est - reference,
            scale_error: None,
            scale_error_error: None,
        });
    }
    for p in 1..=spec.repetitions {
        let (_, b, f) = summarize(p);
        let (ref_b, ref_s) = match &truth {
            Some((t, _)) => (t.model.backlash_deg, t.fit.scale_error),
            None => (backlash.mean_deg, positioning.scale_error),
        };
        effort.push(EffortRow {
            stage: "bidirectional".into(),
            used: p,
            rig_time_s: pass_times[p - 1],
            estimate_deg: b.mean_deg,
            error_deg: b.mean_deg - ref_b,
            scale_error: Some(f.scale_error),
            scale_error_error: Some(f.scale_error - ref_s),
        });
    }
    Ok(AxisMechanics {
        axis: name,
        reference: spec.reference.name().into(),
        homing,
        backlash,
        positioning,
        targets: rows,
        truth: truth.map(|(t, _)| t),
        errors,
        effort,
        rig_time_s: rig.time() - t0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_fit_recovers_offset_scale_and_residual() {
        let x = [-10.0, 0.0, 10.0, 20.0];
        let y: Vec<f64> = x.iter().map(|v| 0.5 + 1e-3 * v).collect();
        let f = fit_line(&x, &y);
        assert!((f.offset_deg - 0.5).abs() < 1e-12 && (f.scale_error - 1e-3).abs() < 1e-12);
        assert!(f.residual_rms_deg < 1e-12);
        let y2 = [0.0, 1.0, 0.0, 1.0];
        let f = fit_line(&x, &y2);
        assert!(f.residual_rms_deg > 0.4, "{f:?}");
    }

    /// The camera reference's rigid fit: a rotated, shifted grid gives its angle with zero
    /// residual, whichever way round the grid is labelled (a mirrored labelling included),
    /// and noise on the points shows as residual, not as angle bias.
    #[test]
    fn rigid_fit_recovers_the_rotation_of_a_relabelled_grid() {
        let grid: Vec<[f64; 2]> = (0..30).map(|k| [(k % 6) as f64 * 5.0, (k / 6) as f64 * 5.0]).collect();
        for beta in [-170.0f64, -0.02, 0.0, 0.013, 37.0, 90.0] {
            let (c, s) = (beta.to_radians().cos(), beta.to_radians().sin());
            let q: Vec<[f64; 2]> = grid
                .iter()
                .map(|p| [c * p[0] - s * p[1] + 3.0, s * p[0] + c * p[1] - 7.0])
                .collect();
            let (got, rms) = rigid_angle_deg(&grid, &q);
            assert!((got - beta).abs() < 1e-9, "β = {beta}: got {got}");
            assert!(rms < 1e-9);
            // The same grid labelled mirrored (y flipped): the angle is found after undoing it.
            let mirrored: Vec<[f64; 2]> = grid.iter().map(|p| [p[0], -p[1]]).collect();
            let (_, rms_m) = rigid_angle_deg(&mirrored, &q);
            assert!(rms_m < 1e-9, "β = {beta}: a mirrored labelling must still fit rigidly");
        }
    }

    #[test]
    fn default_targets_stay_inside_the_limits_with_the_approach() {
        let s = MechanicalSpec::default();
        let t = targets_for(&s, -80.0, 80.0);
        assert_eq!(t.len(), 9);
        assert!(t[0] - s.approach_deg >= -80.0 && t[8] + s.approach_deg <= 80.0, "{t:?}");
        assert!((t[4]).abs() < 1e-9);
        let mut bad = s.clone();
        bad.home_cycles = 1;
        assert!(bad.validate().unwrap_err().0.contains("home_cycles"));
        bad = s.clone();
        bad.targets_deg = vec![1.0, f64::NAN, 2.0];
        assert!(bad.validate().is_err());
        assert!(s.validate().is_ok());
    }
}
