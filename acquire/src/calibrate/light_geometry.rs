//! Light-geometry calibration: the lamp axes' zero offsets from the specular highlight of a
//! flat near-mirror sample (`kind = "light-geometry"`).
//!
//! The rig-geometry calibration cannot see the lamp (target corners do not move when it
//! does); a mirror can: the lamp's reflection appears where the mirrored camera ray meets
//! it. The runner solves every recipe pose with the rig's inverse kinematics, checks
//! *before moving* that the poses determine both lamp offsets and keep every highlight on
//! the sample for offsets up to `max_offset_deg` ([`check_design`]), then captures each
//! pose, locates the highlight ([`locate_highlight`]) and fits the offsets
//! ([`estimate_light_geometry`]). The camera pose comes from the rig file's kinematics,
//! `[alignment]` included: run the rig-geometry calibration first on a rig whose camera is
//! misaligned, or its error ends up in the lamp's offsets.
//!
//! [`LightGeometryCalibration::apply`] writes the lamp offsets into a rig description's
//! `[alignment]` and keeps the camera's entries, so a rig-geometry and a light-geometry
//! result combine. On the simulator the result also carries the truth (`[sim_misalignment]`),
//! the parameter errors, each highlight's localisation error against its exact position, the
//! light-direction error over all Bonn 81 × 81 pairs before and after applying the estimate,
//! and the error against the number of poses.

use super::offset_fit::{
    camera_model, corrected, direction_errors, direction_uncertainty, nominal_rig, DirectionErrors,
    DirectionUncertainty, EffortFigures, ParameterError,
};
use super::{CalibrateError, CalibrationResult, Recipe, RunOutput};
use crate::develop::frame_to_linear;
use crate::rig::Rig;
use gonio_calibration::light_geometry::{
    check_design, estimate_light_geometry, locate_highlight, predict_highlight, LampPose, LightGeometryFit,
    LightGeometryOptions,
};
use gonio_devices::rig::{AlignmentSpec, RigSpec};
use gonio_devices::Direction;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// One captured pose: where the highlight was found and, on the simulator, where it truly is.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct HighlightRecord {
    pub label: String,
    pub view_deg: [f64; 2],
    pub light_deg: [f64; 2],
    /// Commanded axis positions (degrees, the rig's axis order).
    pub axes_deg: Vec<f64>,
    pub pixel: [f64; 2],
    /// Brightest pixel (linear, 1 = full scale): how close the exposure is to saturation.
    pub peak: f64,
    pub radius_px: f64,
    pub region_px: usize,
    /// The other locator's position minus `pixel` (the lobe's asymmetry, see
    /// `gonio_calibration::light_geometry::Highlight::locator_shift_px`).
    #[serde(default)]
    pub locator_shift_px: Option<[f64; 2]>,
    /// Simulator only: the exact reflection point's pixel on the true mechanism, and the
    /// located − exact difference (the localisation bias of the lobe's shape and sampling).
    pub truth_pixel: Option<[f64; 2]>,
    pub error_px: Option<[f64; 2]>,
}

/// Localisation error of the highlights against the simulator's exact positions.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LocalisationError {
    pub mean_px: [f64; 2],
    pub rms_px: f64,
    pub max_px: f64,
}

/// One row of the error-versus-effort table: the fit on the first `poses` poses.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LightEffortRow {
    pub poses: usize,
    /// Rig time (s) to capture these poses (virtual on the simulator).
    pub capture_s: f64,
    /// Wall time of the fit (s).
    pub fit_s: f64,
    pub rms_px: Option<f64>,
    /// Largest |estimate − truth| over the two offsets (simulator), or against the fit
    /// with all poses (real rig).
    pub max_parameter_error_deg: Option<f64>,
    /// Largest light-direction error over the Bonn pairs after applying this fit
    /// (simulator only).
    pub light_max_error_deg: Option<f64>,
    /// Why the fit was refused, if it was.
    pub failure: Option<String>,
}

/// The `light_geometry` part of `calibration.json`.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LightGeometryCalibration {
    pub fit: LightGeometryFit,
    /// Condition number of the pose design (before capture, zero offsets).
    pub design_condition: f64,
    /// The rig file's `[alignment]` the camera pose was taken from (a rig-geometry
    /// calibration's, or none: nominal kinematics).
    pub camera_alignment: Option<AlignmentSpec>,
    pub highlights: Vec<HighlightRecord>,
    /// Simulator only: the true lamp offsets and the estimate's errors.
    pub truth: Option<AlignmentSpec>,
    pub errors: Option<Vec<ParameterError>>,
    pub localisation: Option<LocalisationError>,
    /// Simulator only: direction errors with the rig file's kinematics and with the lamp
    /// offsets applied.
    pub directions_before: Option<DirectionErrors>,
    pub directions_after: Option<DirectionErrors>,
    /// The light and view directions' one-sigma uncertainty over the Bonn pairs from the
    /// fit's covariance, with the true error in sigmas on the simulator.
    #[serde(default)]
    pub direction_uncertainty: DirectionUncertainty,
    pub effort: Vec<LightEffortRow>,
}

impl LightGeometryCalibration {
    /// Feed the lamp offsets into `rig`'s kinematics (`rig.alignment`), keeping the
    /// camera's entries (a rig-geometry calibration's): after this, IK on `rig` commands
    /// the lamp positions that reach the asked light directions.
    pub fn apply(&self, rig: &mut RigSpec) {
        self.fit.apply(rig);
    }
}

/// Estimates against the truth's lamp entries (absent = 0).
fn parameter_errors(fit: &LightGeometryFit, truth: &AlignmentSpec) -> Vec<ParameterError> {
    fit.parameters
        .iter()
        .map(|p| {
            let axis = p.name.strip_prefix("zero_offset.").unwrap_or(&p.name);
            let t = truth.axis_zero_offset_deg.get(axis).copied().unwrap_or(0.0);
            ParameterError::new(p, t)
        })
        .collect()
}

pub(super) async fn run_light_geometry(recipe: &Recipe, rig: &Rig) -> Result<RunOutput, CalibrateError> {
    let name = recipe.name.clone();
    let opts: LightGeometryOptions = recipe.light_geometry.clone().unwrap_or_default();
    let fit_err = |cause| CalibrateError::LightGeometry {
        recipe: name.clone(),
        cause,
    };
    let camera = camera_model(&rig.spec).map_err(|source| CalibrateError::RigOption {
        recipe: name.clone(),
        rig: rig.spec.name.clone(),
        source,
    })?;
    // The planner's view of the rig: the rig file without the simulator's truth.
    let nominal = nominal_rig(&rig.spec);
    // Solve every pose first (the same IK and chaining `reach_pose` uses), so a pose set
    // that cannot work is refused before the rig moves.
    let mut planned: Vec<(String, Vec<f64>)> = Vec::with_capacity(recipe.poses.len());
    for (index, pose) in recipe.poses.iter().enumerate() {
        let light = pose.light.unwrap_or(recipe.light);
        let unreachable = |reason: String| CalibrateError::Unreachable {
            recipe: name.clone(),
            index,
            view: pose.view,
            light,
            rig: rig.spec.name.clone(),
            reason,
        };
        let prev = planned.last().map(|(_, q)| q.as_slice());
        let q = rig
            .kinematics
            .inverse(
                Direction::from_degrees(light[0], light[1]),
                Direction::from_degrees(pose.view[0], pose.view[1]),
                prev,
            )
            .map_err(|e| unreachable(e.to_string()))?
            .into_iter()
            .next()
            .ok_or_else(|| unreachable("no configuration".into()))?;
        planned.push((
            format!(
                "pose {index} view θ={} φ={} light θ={} φ={}",
                pose.view[0], pose.view[1], light[0], light[1]
            ),
            q,
        ));
    }
    let design_condition = check_design(&nominal, &camera, &planned, &opts).map_err(fit_err)?;
    let t0 = rig.time();
    let config = super::prepare_rig(recipe, rig).await?;
    let policy = super::calibration_policy(recipe, rig)?;
    tracing::info!(recipe = %name, design_condition, "light geometry: capturing {} poses", planned.len());
    let simulated = rig.clock.is_some();
    let truth_spec = simulated.then(|| rig.spec.simulated_truth());
    let mut poses = Vec::with_capacity(planned.len());
    let mut records = Vec::with_capacity(planned.len());
    let mut capture_times = Vec::with_capacity(planned.len());
    let mut prev: Option<Vec<f64>> = None;
    for (index, (pose, (label, planned_q))) in recipe.poses.iter().zip(&planned).enumerate() {
        let light = pose.light.unwrap_or(recipe.light);
        let (q, _) = super::reach_pose(recipe, rig, index, pose.view, light, prev.as_deref()).await?;
        debug_assert_eq!(&q, planned_q, "same IK, same chaining");
        let frame = super::capture_at(recipe, rig, &policy, &config, index, pose.view).await?;
        let raw = frame_to_linear(&frame);
        let h = locate_highlight(&raw, &opts.highlight).map_err(|cause| CalibrateError::Highlight {
            recipe: name.clone(),
            index,
            view: pose.view,
            light,
            cause,
        })?;
        let truth_pixel = truth_spec
            .as_ref()
            .and_then(|t| predict_highlight(t, &camera, &q).map(|(_, px)| px));
        let error_px = truth_pixel.map(|t| [h.pixel[0] - t[0], h.pixel[1] - t[1]]);
        tracing::debug!(index, pixel = ?h.pixel, peak = h.peak, radius_px = h.radius_px, ?error_px, "highlight");
        records.push(HighlightRecord {
            label: label.clone(),
            view_deg: pose.view,
            light_deg: light,
            axes_deg: q.iter().map(|x| x.to_degrees()).collect(),
            pixel: h.pixel,
            peak: h.peak,
            radius_px: h.radius_px,
            region_px: h.region_px,
            locator_shift_px: h.locator_shift_px,
            truth_pixel,
            error_px,
        });
        poses.push(LampPose {
            label: label.clone(),
            q: q.clone(),
            pixel: h.pixel,
            locator_shift_px: h.locator_shift_px,
        });
        capture_times.push(rig.time() - t0);
        prev = Some(q);
    }
    let fit = estimate_light_geometry(&nominal, &camera, &poses, &opts).map_err(fit_err)?;
    let truth = simulated.then(|| {
        let mut t = rig.spec.sim_misalignment.clone().unwrap_or_default();
        t.axis_zero_offset_deg
            .retain(|k, _| fit.alignment.axis_zero_offset_deg.contains_key(k));
        t.camera_rotation_deg = [0.0; 3];
        t
    });
    let errors = truth.as_ref().map(|t| parameter_errors(&fit, t));
    let localisation = simulated.then(|| {
        let errs: Vec<[f64; 2]> = records.iter().filter_map(|r| r.error_px).collect();
        let n = errs.len().max(1) as f64;
        LocalisationError {
            mean_px: [
                errs.iter().map(|e| e[0]).sum::<f64>() / n,
                errs.iter().map(|e| e[1]).sum::<f64>() / n,
            ],
            rms_px: (errs.iter().map(|e| e[0] * e[0] + e[1] * e[1]).sum::<f64>() / n).sqrt(),
            max_px: errs.iter().map(|e| e[0].hypot(e[1])).fold(0.0, f64::max),
        }
    });
    let directions_before = truth_spec.as_ref().map(|t| direction_errors(&nominal, t));
    let directions_after = truth_spec
        .as_ref()
        .map(|t| direction_errors(&corrected(&nominal, |r| fit.apply(r)), t));
    // The highlights' localisation bias is systematic (the same sign at every pose): the
    // direction σ carries it next to the residuals' scatter (`fit.systematic_deg`).
    let (with_bias, with_bias_correlation) = fit.with_systematic();
    let direction_uncertainty = direction_uncertainty(
        &corrected(&nominal, |r| fit.apply(r)),
        &with_bias,
        &with_bias_correlation,
        truth_spec.as_ref(),
    );
    // Error against effort: the same fit on the first k poses.
    let mut effort = Vec::new();
    for k in opts.min_poses.max(1)..=poses.len() {
        let start = Instant::now();
        let r = estimate_light_geometry(&nominal, &camera, &poses[..k], &opts);
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
                    .map(|t| direction_errors(&corrected(&nominal, |r| f.apply(r)), t).light_max_deg),
            ),
            Err(e) => EffortFigures::refused(e),
        };
        effort.push(LightEffortRow {
            poses: k,
            capture_s,
            fit_s,
            rms_px: figures.rms_px,
            max_parameter_error_deg: figures.max_parameter_error_deg,
            light_max_error_deg: figures.max_direction_error_deg,
            failure: figures.failure,
        });
    }
    let result = CalibrationResult {
        light_geometry: Some(LightGeometryCalibration {
            fit,
            design_condition,
            camera_alignment: nominal.alignment.clone(),
            highlights: records,
            truth,
            errors,
            localisation,
            directions_before,
            directions_after,
            direction_uncertainty,
            effort,
        }),
        rig_time_s: rig.time() - t0,
        ..CalibrationResult::new(recipe, rig.spec.name.clone(), simulated)
    }
    .seal();
    Ok(RunOutput { result, corners: None })
}
