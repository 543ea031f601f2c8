//! The intrinsics recipe: the board at many poses, corners detected and refined, Zhang +
//! LM with OpenCV's distortion model (`gonio_calibration::intrinsics`), an effort table
//! (fit on the first k views), and on the simulator the corners' exact projections and the
//! error of every estimate against the truth.

use super::*;
use crate::rig::capture::saturated_fraction;

/// The simulated camera's exact model: its intrinsics and the simulator's lens distortion.
fn true_camera(rig: &Rig) -> CameraModel {
    let k = rig.spec.camera.intrinsics();
    CameraModel {
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        distortion: sim_distortion(rig),
    }
}

/// Lens distortion of the simulated camera (the ground truth's; zero on hardware, where
/// the corner truth is not used and the wedge's nominal geometry needs no lens).
fn sim_distortion(rig: &Rig) -> [f64; 5] {
    rig.truth.as_ref().map_or([0.0; 5], |t| t.distortion())
}

/// RMS distance of detected corners from the exact projection of the target corners
/// (simulated rigs). The board is symmetric, so the detector's grid may be any proper
/// rotation of the true one: the best of the four is taken. Returns the RMS, the exact
/// projections (in the detector's order) under that rotation, and the rotation (quarter
/// turns, [`gonio_calibration::wedge::quarter_turn`]). On a wedge the board points are
/// projected from the tilted plane ([`WedgeSpec::lift`]).
fn corner_truth(
    rig: &Rig,
    q: &[f64],
    wedge: Option<&WedgeSpec>,
    object: &[[f64; 2]],
    image: &[[f64; 2]],
) -> (f64, Vec<[f64; 2]>, u8) {
    let cam = true_camera(rig);
    let pose = rig.kinematics.camera_pose(q);
    (0..4u8)
        .map(|r| {
            let proj: Vec<[f64; 2]> = object
                .iter()
                .map(|o| {
                    let p = quarter_turn(*o, r);
                    let [x, y, z] = wedge.map_or([p[0], p[1], 0.0], |w| w.lift(p));
                    let c = pose.to_camera(gonio_devices::Vec3::new(x, y, z));
                    let (u, v) = cam.project_point([c.x, c.y, c.z]);
                    [u, v]
                })
                .collect();
            let sum: f64 = proj
                .iter()
                .zip(image)
                .map(|(p, i)| (p[0] - i[0]).powi(2) + (p[1] - i[1]).powi(2))
                .sum();
            ((sum / object.len().max(1) as f64).sqrt(), proj, r)
        })
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .expect("four rotations")
}

/// [`corner_truth`] for partial views (`detection.partial`), whose corners are indexed
/// from the piece seen: each detected corner is matched to the nearest exact projection of
/// any of the board's corners (they are a square apart, tens of pixels; the detector is
/// within a fraction of one).
fn lattice_truth(
    rig: &Rig,
    q: &[f64],
    board: &gonio_calibration::board::Board,
    image: &[[f64; 2]],
) -> (f64, Vec<[f64; 2]>) {
    let cam = true_camera(rig);
    let pose = rig.kinematics.camera_pose(q);
    let exact: Vec<[f64; 2]> = board
        .all_corners()
        .iter()
        .filter_map(|o| {
            let c = pose.to_camera(gonio_devices::Vec3::new(o[0], o[1], 0.0));
            (c.z > 0.0).then(|| {
                let (u, v) = cam.project_point([c.x, c.y, c.z]);
                [u, v]
            })
        })
        .collect();
    let d2 = |a: &[f64; 2], b: &[f64; 2]| (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2);
    let proj: Vec<[f64; 2]> = image
        .iter()
        .map(|p| {
            *exact
                .iter()
                .min_by(|a, b| d2(a, p).total_cmp(&d2(b, p)))
                .unwrap_or(&[f64::NAN; 2])
        })
        .collect();
    let sum: f64 = proj.iter().zip(image).map(|(a, b)| d2(a, b)).sum();
    ((sum / image.len().max(1) as f64).sqrt(), proj)
}

/// The object points of a board on a wedge: the detector's flat board points in true
/// in-plane coordinates ([`WedgeSpec::in_plane`]). The wedge is not symmetric under the
/// board's quarter turns, so which of the detector's four equivalent grids is the printed
/// one is decided first from the rig's nominal geometry (camera pose of the reached axes,
/// nominal intrinsics): the quarter turn whose points on the wedge project nearest the
/// detected corners. The alternatives differ by about a board's size in the image, so a
/// rough nominal geometry is enough. Points come back in the sample frame's orientation.
fn wedge_object_points(
    rig: &Rig,
    q: &[f64],
    wedge: &WedgeSpec,
    object: &[[f64; 2]],
    image: &[[f64; 2]],
) -> Vec<[f64; 2]> {
    let (_, _, r) = corner_truth(rig, q, Some(wedge), object, image);
    object.iter().map(|o| wedge.in_plane(quarter_turn(*o, r))).collect()
}

/// Largest fraction of a target frame's values that may sit at full scale before the frame
/// is taken again shorter: clipped bright squares move every edge toward them.
const MAX_CLIPPED_FRACTION: f64 = 1e-4;

/// How many times an intrinsics view is re-exposed (each time at half the exposure) before
/// the clipped frame is used as it is (the corner model then treats clipped pixels as
/// censored) and the detector diagnoses it if it must.
const MAX_REEXPOSURES: u32 = 6;

/// Capture a target frame. With `auto` (the recipe sets no exposure), a frame whose values
/// clip is captured again at half the exposure, up to [`MAX_REEXPOSURES`] times; the
/// camera's configuration is left at the exposure that worked, so the next view starts
/// there. Returns the frame and the exposure it was taken at.
async fn capture_unclipped(
    recipe: &Recipe,
    rig: &Rig,
    policy: &CapturePolicy,
    config: &mut gonio_devices::CameraConfig,
    auto: bool,
    (index, view): (usize, [f64; 2]),
) -> Result<(gonio_devices::Frame, f64), CalibrateError> {
    let mut tries = 0;
    loop {
        let frame = capture_at(recipe, rig, policy, config, index, view).await?;
        let clipped = saturated_fraction(&frame);
        if !auto || clipped <= MAX_CLIPPED_FRACTION || tries >= MAX_REEXPOSURES {
            return Ok((frame, config.exposure));
        }
        tries += 1;
        let mut next = config.clone();
        next.exposure = config.exposure * 0.5;
        let applied = rig
            .camera
            .configure(&next)
            .await
            .map_err(|cause| device_error(recipe, rig, rig.camera.name(), cause))?;
        if applied.exposure >= config.exposure {
            // the camera cannot go shorter: use what it gives
            return Ok((frame, config.exposure));
        }
        tracing::info!(
            clipped_percent = 100.0 * clipped,
            exposure_s = applied.exposure,
            "intrinsics: target frame clips; exposing shorter"
        );
        *config = applied;
    }
}

pub(super) async fn run_intrinsics(recipe: &Recipe, rig: &Rig) -> Result<RunOutput, CalibrateError> {
    let name = recipe.name.clone();
    let rig_name = rig.spec.name.clone();
    let board = recipe.board().expect("validated: intrinsics recipes have a board");
    let t0 = rig.time();
    // before anything moves: can these poses determine the camera at all?
    let plan_check = super::uncertainty::check_intrinsics_plan(recipe, rig, &board)?;
    let mut config = prepare_rig(recipe, rig).await?;
    let policy = calibration_policy(recipe, rig)?;
    let auto_exposure = recipe.exposure_s.is_none();
    let mut view_exposure = Vec::new();
    tracing::info!(recipe = %name, exposure = config.exposure, "intrinsics: capturing {} poses", recipe.poses.len());
    let mut views = Vec::new();
    let mut capture_times = Vec::new();
    let mut corner_rms = Vec::new();
    let mut truth_image = Vec::new();
    let mut prev: Option<Vec<f64>> = None;
    for (index, pose) in recipe.poses.iter().enumerate() {
        let light = pose.light.unwrap_or(recipe.light);
        let (q, _) = reach_pose(recipe, rig, index, pose.view, light, prev.as_deref()).await?;
        let (frame, exposure) =
            capture_unclipped(recipe, rig, &policy, &mut config, auto_exposure, (index, pose.view)).await?;
        view_exposure.push(exposure);
        let raw = frame_to_linear(&frame);
        let det = detect_board(recipe, &board, &raw, index, pose.view)?;
        tracing::debug!(index, candidates = det.candidates, "board found");
        if rig.clock.is_some() {
            let (rms, proj) = if recipe.detection.partial {
                lattice_truth(rig, &q, &board, &det.image)
            } else {
                let (rms, proj, _) = corner_truth(rig, &q, recipe.wedge.as_ref(), &det.object, &det.image);
                (rms, proj)
            };
            corner_rms.push(rms);
            truth_image.push(proj);
        }
        let object = match &recipe.wedge {
            Some(w) => wedge_object_points(rig, &q, w, &det.object, &det.image),
            None => det.object,
        };
        views.push(TargetView {
            label: format!("pose {index} view θ={} φ={}", pose.view[0], pose.view[1]),
            object,
            image: det.image,
        });
        capture_times.push(rig.time() - t0);
        prev = Some(q);
    }
    let size = (rig.spec.camera.width, rig.spec.camera.height);
    let fit = calibrate_intrinsics(&views, size, &recipe.estimate).map_err(|cause| CalibrateError::Intrinsics {
        recipe: name.clone(),
        cause,
    })?;
    let simulated = rig.clock.is_some();
    let truth = simulated.then(|| {
        let k = rig.spec.camera.intrinsics();
        IntrinsicsTruth {
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            distortion: sim_distortion(rig),
        }
    });
    let errors = truth.as_ref().map(|t| {
        let c = &fit.camera;
        IntrinsicsErrors {
            fx_percent: 100.0 * (c.fx - t.fx) / t.fx,
            fy_percent: 100.0 * (c.fy - t.fy) / t.fy,
            cx_px: c.cx - t.cx,
            cy_px: c.cy - t.cy,
            cx_percent: 100.0 * (c.cx - t.cx) / t.cx,
            cy_percent: 100.0 * (c.cy - t.cy) / t.cy,
            distortion_abs: std::array::from_fn(|k| (c.distortion[k] - t.distortion[k]).abs()),
        }
    });
    // Error against effort: the same fit on the first k views.
    let (ref_fx, ref_cx, ref_cy) =
        truth
            .as_ref()
            .map(|t| (t.fx, t.cx, t.cy))
            .unwrap_or((fit.camera.fx, fit.camera.cx, fit.camera.cy));
    let mut effort = Vec::new();
    for k in 3..=views.len() {
        let start = Instant::now();
        let r = calibrate_intrinsics(&views[..k], size, &recipe.estimate);
        let fit_s = start.elapsed().as_secs_f64();
        let capture_s = capture_times[k - 1];
        effort.push(match r {
            Ok(c) => EffortRow {
                views: k,
                capture_s,
                fit_s,
                rms_px: c.rms_px,
                fx: c.camera.fx,
                cx: c.camera.cx,
                cy: c.camera.cy,
                fx_error_percent: 100.0 * (c.camera.fx - ref_fx) / ref_fx,
                cx_error_px: c.camera.cx - ref_cx,
                cy_error_px: c.camera.cy - ref_cy,
                failure: None,
            },
            Err(e) => EffortRow {
                views: k,
                capture_s,
                fit_s,
                rms_px: f64::NAN,
                fx: f64::NAN,
                cx: f64::NAN,
                cy: f64::NAN,
                fx_error_percent: f64::NAN,
                cx_error_px: f64::NAN,
                cy_error_px: f64::NAN,
                failure: Some(e.to_string()),
            },
        });
    }
    let projection = super::uncertainty::report(rig, &fit, &views);
    if let Some(w) = &projection.warning {
        tracing::warn!(recipe = %name, "{w}");
    }
    let projection_truth = truth.as_ref().map(|t| {
        let true_cam = CameraModel {
            fx: t.fx,
            fy: t.fy,
            cx: t.cx,
            cy: t.cy,
            distortion: t.distortion,
        };
        super::uncertainty::truth_check(&fit.camera, &true_cam, &projection)
    });
    let result = CalibrationResult {
        intrinsics: Some(fit),
        plan_check,
        projection_uncertainty: Some(projection),
        projection_truth,
        truth,
        errors,
        effort,
        corner_truth_rms_px: corner_rms,
        view_exposure_s: view_exposure,
        rig_time_s: rig.time() - t0,
        ..CalibrationResult::new(recipe, rig_name, simulated)
    }
    .seal();
    Ok(RunOutput {
        result,
        corners: Some(CornerSet {
            convention: "gonio: pixel (i, j) has its centre at (i + 0.5, j + 0.5); OpenCV = this − 0.5".into(),
            image_size: [size.0, size.1],
            views,
            truth_image,
        }),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use gonio_devices::rig::RigSpec;
    use gonio_simulator::SampleSpec;
    use std::path::Path;

    /// The workspace root (rig files and recipes are named relative to it).
    fn root() -> &'static Path {
        Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
    }

    fn wide_rig(recipe: &Recipe) -> Rig {
        let spec = RigSpec::load(&root().join("devices/rigs/wide-lens.toml")).unwrap();
        let sample = SampleSpec::resolve(&recipe.target).unwrap();
        let opts = recipe.sim_options();
        Rig::build(&spec, &sample, &opts).unwrap()
    }

    fn shipped() -> Recipe {
        Recipe::load(&root().join("calibration/recipes/intrinsics.toml")).unwrap()
    }

    // The error is matched by variant in the tests; its size does not matter here.
    #[allow(clippy::result_large_err)]
    fn run_blocking(recipe: &Recipe) -> Result<RunOutput, CalibrateError> {
        let rig = wide_rig(recipe);
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        rt.block_on(run(recipe, &rig))
    }

    /// The targets on noiseless simulated images of a distorting wide-angle lens
    /// with an off-centre principal point: focal length and principal point within 0.1 %
    /// of the truth, reprojection RMS < 0.1 px. The rig's default exposure clips the
    /// board's bright squares, so this also checks that the runner exposes shorter.
    #[test]
    fn intrinsics_match_the_simulator_truth() {
        let out = run_blocking(&shipped()).unwrap();
        let r = &out.result;
        let c = r.intrinsics.as_ref().unwrap();
        let t = r.truth.as_ref().unwrap();
        let e = r.errors.as_ref().unwrap();
        assert!(c.rms_px < 0.1, "rms {}", c.rms_px);
        assert!(e.fx_percent.abs() < 0.1 && e.fy_percent.abs() < 0.1, "{e:?}");
        assert!(e.cx_percent.abs() < 0.1 && e.cy_percent.abs() < 0.1, "{e:?}");
        assert!(r.view_exposure_s.iter().all(|&x| x < 0.05), "{:?}", r.view_exposure_s);
        assert!((t.distortion[0] + 0.12).abs() < 1e-12, "truth read from the rig file");
        // barrel distortion is recovered in sign and rough size over the target's field
        assert!(
            (c.camera.distortion[0] - t.distortion[0]).abs() < 0.05,
            "{:?}",
            c.camera
        );
        assert_eq!(r.id.len(), 16);
        assert_eq!(out.corners.as_ref().unwrap().views.len(), 12);
        // the effort table covers 3 ..= 12 views; too few views are refused, not fitted
        assert_eq!(r.effort.len(), 10);
        assert!(r.effort[0].failure.is_some(), "{:?}", r.effort[0]);
        // The plan was checked before the rig moved.
        let plan = r.plan_check.as_ref().expect("plan checked");
        assert!(
            plan.predicted_sigma[0] > 0.0 && plan.predicted_sigma[0] < 5.5,
            "{plan:?}"
        );
        // The board stays near the image centre on this rig, so the distortion model
        // extrapolates to the image corners: the true projection error there is pixels
        // (k2 comes out far from the truth), and the report must say so, with a sigma
        // that keeps the true error within 3 sigma over the whole image.
        let u = r.projection_uncertainty.as_ref().unwrap();
        let pt = r.projection_truth.as_ref().unwrap();
        assert!(pt.max_error_px > 5.0, "{pt:?}");
        assert!(pt.max_error_over_sigma < 3.0, "{}", pt.max_error_over_sigma);
        assert_eq!(pt.beyond_3_sigma_fraction, 0.0);
        assert!(u.max_px > 2.0, "{}", u.max_px);
        assert!(
            u.coverage_fraction > 0.03 && u.coverage_fraction < 0.15,
            "{}",
            u.coverage_fraction
        );
        let w = u.warning.as_ref().expect("flagged");
        assert!(w.contains("top-left") && w.contains("bottom-right"), "{w}");
        // inside the sample's region the error is small and so is the sigma
        assert!(
            pt.sample_max_error_px.unwrap() < 0.5 && u.sample_max_px.unwrap() < 0.5,
            "{u:?}"
        );
    }

    #[test]
    fn parallel_target_poses_are_refused() {
        // θ = 0 at several turntable angles: the target only turns about the optical axis,
        // all target planes are parallel.
        let mut recipe = shipped();
        recipe.poses.truncate(0);
        for phi in [0.0, 70.0, 140.0, 210.0] {
            recipe.poses.push(recipe::PoseSpec {
                view: [0.0, phi],
                light: None,
            });
        }
        // refused from the plan, before the rig moved (no rig time spent), naming what
        // the poses cannot determine
        let rig = wide_rig(&recipe);
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let e = rt.block_on(run(&recipe, &rig)).err().expect("refused");
        let msg = e.to_string();
        assert!(
            matches!(
                e,
                CalibrateError::Intrinsics {
                    cause: IntrinsicsError::PlanUndetermined { .. },
                    ..
                }
            ),
            "{msg}"
        );
        assert!(msg.contains("fx") && msg.contains("cx"), "{msg}");
        assert_eq!(rig.time(), 0.0, "the rig moved before the refusal");
        // too few views, likewise
        let mut recipe = shipped();
        recipe.poses.truncate(2);
        let e = run_blocking(&recipe).err().expect("refused");
        assert!(e.to_string().contains("planned views"), "{e}");
    }

    #[test]
    fn black_and_saturated_frames_are_diagnosed() {
        let mut recipe = shipped();
        recipe.exposure_s = Some(1e-9);
        let e = run_blocking(&recipe).err().expect("refused");
        assert!(
            matches!(
                e,
                CalibrateError::Detection {
                    index: 0,
                    cause: CheckerboardError::Empty { .. },
                    ..
                }
            ),
            "{e}"
        );
        recipe.exposure_s = Some(100.0);
        let e = run_blocking(&recipe).err().expect("refused");
        assert!(
            matches!(
                e,
                CalibrateError::Detection {
                    cause: CheckerboardError::Saturated { .. },
                    ..
                }
            ),
            "{e}"
        );
    }
}
