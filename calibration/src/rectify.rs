//! Rectifying one raw frame: choose the homography, then [`warp`].
//!
//! "Refined from the known pose" means: the rig's kinematics give a predicted homography
//! (exact up to calibration error: a few pixels); it locates the markers, and the markers'
//! sub-pixel centres give the homography actually used — **where they are reliable**. They
//! are reliable when at least [`MIN_MARKERS`] are found and the fit through them has an RMS
//! reprojection error below [`MAX_MARKER_RMS_PX`]. A marker whose residual is far out of
//! line with the others (a misdetection: dust, a shadow edge, texture) is dropped first, as
//! long as enough remain. Otherwise (grazing views where the markers are a few pixels tall,
//! markers hidden, glare) the **pose** homography is used as is: at worst a few pixels off,
//! which is better than a fit through unreliable points. [`Rectified::source`] records
//! which one was used, so a dataset can say so per image.

use crate::homography::{Correspondence, Homography};
use crate::markers::detect_markers;
use crate::warp::{warp, RectifyParams};
use gonio_devices::camera::Intrinsics;
use gonio_devices::image::RgbImage;
use gonio_devices::kinematics::CameraPose;
use gonio_devices::target::MarkerBorder;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Fewest markers a fit is trusted with: 8 unknowns need 4, the rest is redundancy to
/// measure the RMS and to survive dropping a bad one.
pub const MIN_MARKERS: usize = 6;

/// Largest RMS reprojection error (pixels) of a trusted marker fit. Good detections give a
/// few hundredths of a pixel; above this something is systematically wrong.
pub const MAX_MARKER_RMS_PX: f64 = 1.5;

/// A residual this many times the median (and above [`OUTLIER_MIN_PX`]) marks an outlier.
const OUTLIER_FACTOR: f64 = 4.0;
const OUTLIER_MIN_PX: f64 = 0.5;

/// Which homography rectified a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HomographySource {
    /// Fitted to the detected markers.
    Markers,
    /// Predicted from the rig's camera pose (markers unusable for this view).
    Pose,
}

/// A rectified frame and how it was obtained.
#[derive(Clone, Debug, PartialEq)]
pub struct Rectified {
    pub image: RgbImage,
    pub source: HomographySource,
    /// Markers detected and kept (after dropping outliers); with `source == Pose` these
    /// were too few or fitted too poorly to be used.
    pub markers_found: usize,
    /// RMS reprojection error (pixels) of the marker fit, whenever a fit was possible
    /// (also when it was rejected as too poor); `None` when no fit could be made.
    pub marker_rms_px: Option<f64>,
}

#[derive(Clone, Debug, PartialEq, Error)]
pub enum RectifyError {
    #[error("invalid rectify parameters: {0}")]
    InvalidParams(String),
    /// The buffer does not match the size, or the frame is smaller than 2 × 2 pixels.
    #[error(
        "raw image: buffer holds {len} values for {width}×{height} RGB (needs {expected}, and at least 2×2 pixels)"
    )]
    BadImage {
        len: usize,
        width: usize,
        height: usize,
        expected: usize,
    },
    #[error("the camera pose does not see the whole sample: {0}")]
    PoseUnusable(String),
}

/// The marker fit of a frame: homography (if trusted), markers kept, RMS (if a fit exists).
struct MarkerFit {
    homography: Option<Homography>,
    kept: usize,
    rms: Option<f64>,
}

/// Fit through the detected markers, dropping one clear outlier at a time while at least
/// [`MIN_MARKERS`] remain.
fn marker_fit(mut pairs: Vec<Correspondence>) -> MarkerFit {
    loop {
        let kept = pairs.len();
        if kept < MIN_MARKERS {
            // Still report the RMS of what there is, for the record.
            let rms = Homography::fit(&pairs).ok().map(|h| h.rms_error(&pairs));
            return MarkerFit {
                homography: None,
                kept,
                rms,
            };
        }
        let Ok(h) = Homography::fit(&pairs) else {
            return MarkerFit {
                homography: None,
                kept,
                rms: None,
            };
        };
        let rms = h.rms_error(&pairs);
        let resid: Vec<f64> = pairs
            .iter()
            .map(|&((x, y), (u, v))| h.apply(x, y).map_or(f64::INFINITY, |(pu, pv)| (pu - u).hypot(pv - v)))
            .collect();
        let mut sorted = resid.clone();
        sorted.sort_by(f64::total_cmp);
        let med = sorted[sorted.len() / 2];
        let (worst, &worst_r) = resid
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .expect("non-empty");
        if worst_r > OUTLIER_MIN_PX && worst_r > OUTLIER_FACTOR * med && kept > MIN_MARKERS {
            pairs.swap_remove(worst);
            continue;
        }
        let trusted = rms < MAX_MARKER_RMS_PX;
        return MarkerFit {
            homography: trusted.then_some(h),
            kept,
            rms: Some(rms),
        };
    }
}

/// Rectify one raw frame taken from `pose` with intrinsics `intr` (see the module
/// documentation for how the homography is chosen).
pub fn rectify_frame(
    raw: &RgbImage,
    intr: &Intrinsics,
    pose: &CameraPose,
    border: &MarkerBorder,
    params: &RectifyParams,
) -> Result<Rectified, RectifyError> {
    params.validate().map_err(RectifyError::InvalidParams)?;
    let expected = raw.width * raw.height * 3;
    if raw.data.len() != expected || raw.width < 2 || raw.height < 2 {
        return Err(RectifyError::BadImage {
            len: raw.data.len(),
            width: raw.width,
            height: raw.height,
            expected,
        });
    }
    let predicted = Homography::from_pose(intr, pose);
    let s2 = params.sample_mm / 2.0;
    for (x, y) in [(-s2, -s2), (s2, -s2), (s2, s2), (-s2, s2)] {
        if predicted.apply(x, y).is_none() {
            return Err(RectifyError::PoseUnusable(format!(
                "sample corner ({x}, {y}) mm is behind the camera"
            )));
        }
    }
    let detection = detect_markers(raw, &predicted, border, params.sample_mm);
    let fit = marker_fit(detection.pairs());
    let (h, source) = match fit.homography {
        Some(h) => (h, HomographySource::Markers),
        None => (predicted, HomographySource::Pose),
    };
    Ok(Rectified {
        image: warp(raw, &h, params),
        source,
        markers_found: fit.kept,
        marker_rms_px: fit.rms,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::*;
    use gonio_devices::Vec3;

    fn rmse(a: &RgbImage, b: &RgbImage) -> f64 {
        let s: f64 = a.data.iter().zip(&b.data).map(|(x, y)| ((x - y) as f64).powi(2)).sum();
        (s / a.data.len() as f64).sqrt()
    }

    fn params() -> RectifyParams {
        RectifyParams {
            width: 128,
            height: 128,
            sample_mm: SAMPLE_MM,
            max_supersample: 8,
        }
    }

    /// Render the holder at (θ, φ) with `paint`, rectify with a pose that is a few pixels
    /// off, and compare with rectifying through the true homography.
    fn case(theta: f64, phi: f64, paint: &(dyn Fn(f64, f64) -> [f32; 3] + Sync), noise: f64) -> (Rectified, f64, f64) {
        let intr = rig_intrinsics();
        let truth_pose = pose(theta, phi);
        let img = render(&intr, &truth_pose, paint, 0.7, noise, 21);
        let believed = perturb(&truth_pose, 0.04, 0.03, 0.3, Vec3::new(0.3, 0.3, -0.2));
        let p = params();
        let r = rectify_frame(&img, &intr, &believed, &MarkerBorder::default(), &p).unwrap();
        let ideal = warp(&img, &Homography::from_pose(&intr, &truth_pose), &p);
        let posed = warp(&img, &Homography::from_pose(&intr, &believed), &p);
        let (e, e_pose) = (rmse(&r.image, &ideal), rmse(&posed, &ideal));
        eprintln!(
            "rectify θ={theta} φ={phi}: source {:?}, {} markers, rms {:?} px; RMSE vs true-H warp {e:.5} \
             (pose-only warp {e_pose:.5})",
            r.source, r.markers_found, r.marker_rms_px
        );
        (r, e, e_pose)
    }

    #[test]
    fn markers_refine_an_inaccurate_pose() {
        let border = MarkerBorder::default();
        let tex = default_texture;
        let paint = scene(&border, SAMPLE_MM, &tex);
        for (theta, phi) in [(0.0, 0.0), (45.0, 60.0), (60.0, 162.0)] {
            let (r, e, e_pose) = case(theta, phi, &paint, 0.01);
            assert_eq!(r.source, HomographySource::Markers);
            assert_eq!(r.markers_found, 16);
            assert!(r.marker_rms_px.unwrap() < 0.1);
            assert!(e < 0.25 * e_pose, "markers {e} vs pose {e_pose}");
        }
    }

    #[test]
    fn falls_back_to_the_pose_where_markers_are_unreliable() {
        let border = MarkerBorder::default();
        let tex = default_texture;
        // Grazing: markers too small.
        let paint = scene(&border, SAMPLE_MM, &tex);
        let (r, _, _) = case(82.0, 0.0, &paint, 0.01);
        assert_eq!(
            (r.source, r.markers_found, r.marker_rms_px),
            (HomographySource::Pose, 0, None)
        );
        // No markers on the holder at all.
        let blank = |x: f64, y: f64| {
            let c = scene(&border, SAMPLE_MM, &tex)(x, y);
            if c == [0.05; 3] {
                [0.9; 3]
            } else {
                c
            }
        };
        let (r, e, e_pose) = case(30.0, 0.0, &blank, 0.01);
        assert_eq!(r.source, HomographySource::Pose);
        assert_eq!(e, e_pose, "the pose fallback is exactly the pose warp");
    }

    #[test]
    fn a_misplaced_marker_is_dropped() {
        // The marker at (35, 0) is printed 1.5 mm off its nominal place: its detection is
        // a gross outlier (≈ 7 px) that must not bend the fit.
        let border = MarkerBorder::default();
        let tex = default_texture;
        let shifted = |x: f64, y: f64| {
            if (32.0..38.0).contains(&x) && (-3.0..3.0).contains(&(y - 1.5)) {
                [0.05; 3]
            } else if (32.0..38.0).contains(&x) && (-3.0..3.0).contains(&y) {
                [0.9; 3]
            } else {
                scene(&border, SAMPLE_MM, &tex)(x, y)
            }
        };
        let (r, e, e_pose) = case(30.0, 90.0, &shifted, 0.01);
        assert_eq!(r.source, HomographySource::Markers);
        assert_eq!(r.markers_found, 15);
        assert!(r.marker_rms_px.unwrap() < 0.1);
        assert!(e < 0.25 * e_pose);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let intr = rig_intrinsics();
        let img = RgbImage::new(64, 48);
        let p0 = pose(0.0, 0.0);
        let b = MarkerBorder::default();
        let bad = RectifyParams { width: 0, ..params() };
        assert!(matches!(
            rectify_frame(&img, &intr, &p0, &b, &bad),
            Err(RectifyError::InvalidParams(_))
        ));
        let bad = RectifyParams {
            sample_mm: f64::NAN,
            ..params()
        };
        assert!(matches!(
            rectify_frame(&img, &intr, &p0, &b, &bad),
            Err(RectifyError::InvalidParams(_))
        ));
        let bad = RectifyParams {
            max_supersample: 0,
            ..params()
        };
        assert!(matches!(
            rectify_frame(&img, &intr, &p0, &b, &bad),
            Err(RectifyError::InvalidParams(_))
        ));
        let mut short = img.clone();
        short.data.pop();
        assert!(matches!(
            rectify_frame(&short, &intr, &p0, &b, &params()),
            Err(RectifyError::BadImage { .. })
        ));
        // A camera below the sample plane looking away from it.
        let mut away = p0;
        away.position = Vec3::new(0.0, 0.0, -1000.0);
        assert!(matches!(
            rectify_frame(&img, &intr, &away, &b, &params()),
            Err(RectifyError::PoseUnusable(_))
        ));
    }
}
