//! Rig-geometry calibration: axis zero offsets and the camera's mounting rotation from
//! checkerboard views at many axis positions (`kind = "rig-geometry"`).
//!
//! The runner moves the rig to every recipe pose through the rig's own inverse kinematics,
//! records the *commanded* axis positions and detects the board; the bundle adjustment
//! ([`gonio_calibration::rig_geometry`]) then explains all views with one set of offsets.
//! The camera's intrinsics are the rig file's (`focal_length_px`, `principal_point_px`,
//! distortion `k1 … k3` in the camera options): run the intrinsics recipe first and put
//! its result there.
//!
//! [`RigGeometryCalibration::apply`] writes the estimate into a rig description's
//! `[alignment]`, so the planner's kinematics reach true directions. On the simulator the
//! result also carries the truth (`[sim_misalignment]`), the parameter errors, the angular
//! error of the view and light directions over all Bonn 81 × 81 pairs before and after
//! applying the estimate, and the error against the number of views.

use super::offset_fit::{camera_model, corrected, nominal_rig, EffortFigures};
pub use super::offset_fit::{
    direction_errors, direction_uncertainty, DirectionErrors, DirectionUncertainty, ParameterError,
};
use super::{CalibrateError, CalibrationResult, Recipe, RunOutput};
use crate::develop::frame_to_linear;
use crate::rig::Rig;
use gonio_calibration::rig_geometry::{estimate_rig_geometry, RigGeometryFit, RigGeometryOptions, RigView};
use gonio_devices::rig::{AlignmentSpec, RigSpec};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// One row of the error-versus-effort table: the fit on the first `views` views.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RigEffortRow {
    pub views: usize,
    /// Rig time (s) to capture these views (virtual on the simulator).
    pub capture_s: f64,
    /// Wall time of the fit (s).
    pub fit_s: f64,
    pub rms_px: Option<f64>,
    /// Largest |estimate − truth| over the estimated parameters (simulator), or against
    /// the fit with all views (real rig).
    pub max_parameter_error_deg: Option<f64>,
    /// Largest view-direction error over the Bonn pairs after applying this fit
    /// (simulator only).
    pub view_max_error_deg: Option<f64>,
    /// Why the fit was refused (undetermined parameters, too few views), if it was.
    pub failure: Option<String>,
}

/// The `rig_geometry` part of `calibration.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RigGeometryCalibration {
    pub fit: RigGeometryFit,
    /// Commanded axis positions (degrees) of every view, in the rig's axis order.
    pub view_axes_deg: Vec<Vec<f64>>,
    /// Simulator only: the true misalignment and the estimate's errors.
    pub truth: Option<AlignmentSpec>,
    pub errors: Option<Vec<ParameterError>>,
    /// Simulator only: direction errors with the nominal kinematics and with the estimate
    /// applied.
    pub directions_before: Option<DirectionErrors>,
    pub directions_after: Option<DirectionErrors>,
    /// The view and light directions' one-sigma uncertainty over the Bonn pairs from the
    /// fit's covariance, with the true error in sigmas on the simulator.
    #[serde(default)]
    pub direction_uncertainty: DirectionUncertainty,
    pub effort: Vec<RigEffortRow>,
}

impl RigGeometryCalibration {
    /// Feed the estimated offsets and mounting rotation into `rig`'s kinematics
    /// (`rig.alignment`): after this, IK on `rig` commands the positions that reach the
    /// asked directions on the real mechanism.
    pub fn apply(&self, rig: &mut RigSpec) {
        self.fit.apply(rig);
    }
}

/// Parameter errors of `fit` against `truth` (absent entries are 0 in the truth).
fn parameter_errors(fit: &RigGeometryFit, truth: &AlignmentSpec) -> Vec<ParameterError> {
    fit.parameters
        .iter()
        .map(|p| {
            let t = if let Some(axis) = p.name.strip_prefix("zero_offset.") {
                truth.axis_zero_offset_deg.get(axis).copied().unwrap_or(0.0)
            } else {
                let c = match p.name.as_str() {
                    "camera_rotation.x" => 0,
                    "camera_rotation.y" => 1,
                    _ => 2,
                };
                truth.camera_rotation_deg[c]
            };
            ParameterError::new(p, t)
        })
        .collect()
}

pub(super) async fn run_rig_geometry(recipe: &Recipe, rig: &Rig) -> Result<RunOutput, CalibrateError> {
    let name = recipe.name.clone();
    let rig_name = rig.spec.name.clone();
    let board = recipe.board().expect("validated: rig-geometry recipes have a board");
    let opts: RigGeometryOptions = recipe.rig_geometry.clone().unwrap_or_default();
    let t0 = rig.time();
    let config = super::prepare_rig(recipe, rig).await?;
    let policy = super::calibration_policy(recipe, rig)?;
    tracing::info!(recipe = %name, "rig geometry: capturing {} poses", recipe.poses.len());
    let mut views = Vec::new();
    let mut capture_times = Vec::new();
    let mut prev: Option<Vec<f64>> = None;
    for (index, pose) in recipe.poses.iter().enumerate() {
        let light = pose.light.unwrap_or(recipe.light);
        let (q, _) = super::reach_pose(recipe, rig, index, pose.view, light, prev.as_deref()).await?;
        let frame = super::capture_at(recipe, rig, &policy, &config, index, pose.view).await?;
        let raw = frame_to_linear(&frame);
        let det = super::detect_board(recipe, &board, &raw, index, pose.view)?;
        views.push(RigView {
            label: format!("pose {index} view θ={} φ={}", pose.view[0], pose.view[1]),
            q: q.clone(),
            object: det.object,
            image: det.image,
        });
        capture_times.push(rig.time() - t0);
        prev = Some(q);
    }
    let camera = camera_model(&rig.spec).map_err(|source| CalibrateError::RigOption {
        recipe: name.clone(),
        rig: rig.spec.name.clone(),
        source,
    })?;
    let fit_err = |cause| CalibrateError::RigGeometry {
        recipe: name.clone(),
        cause,
    };
    let fit = estimate_rig_geometry(&rig.spec, &camera, &views, &opts).map_err(fit_err)?;
    let simulated = rig.clock.is_some();
    // What the planner used: the rig file without its simulator-only truth.
    let nominal = nominal_rig(&rig.spec);
    let truth_spec = simulated.then(|| rig.spec.simulated_truth());
    let truth = simulated.then(|| rig.spec.sim_misalignment.clone().unwrap_or_default());
    let errors = truth.as_ref().map(|t| parameter_errors(&fit, t));
    let directions_before = truth_spec.as_ref().map(|t| direction_errors(&nominal, t));
    let directions_after = truth_spec
        .as_ref()
        .map(|t| direction_errors(&corrected(&nominal, |r| fit.apply(r)), t));
    let direction_uncertainty = direction_uncertainty(
        &corrected(&nominal, |r| fit.apply(r)),
        &fit.parameters,
        &fit.correlation,
        truth_spec.as_ref(),
    );
    // Error against effort: the same fit on the first k views.
    let mut effort = Vec::new();
    for k in opts.min_views.max(1)..=views.len() {
        let start = Instant::now();
        let r = estimate_rig_geometry(&rig.spec, &camera, &views[..k], &opts);
        let fit_s = start.elapsed().as_secs_f64();
        let capture_s = capture_times[k - 1];
        let figures = match r {
            Ok(f) => EffortFigures::of_fit(
                &f.parameters,
                f.rms_px,
                truth.as_ref().map(|t| parameter_errors(&f, t)),
                &fit.parameters,
                truth_spec
                    .as_ref()
                    .map(|t| direction_errors(&corrected(&nominal, |r| f.apply(r)), t).view_max_deg),
            ),
            Err(e) => EffortFigures::refused(e),
        };
        effort.push(RigEffortRow {
            views: k,
            capture_s,
            fit_s,
            rms_px: figures.rms_px,
            max_parameter_error_deg: figures.max_parameter_error_deg,
            view_max_error_deg: figures.max_direction_error_deg,
            failure: figures.failure,
        });
    }
    let result = CalibrationResult {
        rig_geometry: Some(RigGeometryCalibration {
            view_axes_deg: views
                .iter()
                .map(|v| v.q.iter().map(|x| x.to_degrees()).collect())
                .collect(),
            fit,
            truth,
            errors,
            directions_before,
            directions_after,
            direction_uncertainty,
            effort,
        }),
        rig_time_s: rig.time() - t0,
        ..CalibrationResult::new(recipe, rig_name, simulated)
    }
    .seal();
    Ok(RunOutput { result, corners: None })
}
