//! Rectification of raw frames onto the sample's texel grid (the frontal view of
//! `shared/docs/conventions.md`: columns along +x, rows along −y, row 0 the +y edge).
//!
//! The work lives in the `gonio-calibration` crate, where it is tested against synthetic
//! frames; this module is the pipeline's entry point and re-exports it unchanged:
//!
//! - [`rectify_frame`]: predicted homography from the rig's camera pose → marker detection →
//!   marker homography if at least [`MIN_MARKERS`] markers fit with an RMS below
//!   [`MAX_MARKER_RMS_PX`] (clear outliers dropped first), otherwise the pose homography
//!   ("refined from the known pose": markers where they are reliable, the pose where they
//!   are not; [`Rectified::source`] says which) → [`warp`].
//! - [`warp`]: per-texel box prefilter of `n_u × n_v` bilinear samples, `n` from the
//!   homography's Jacobian (clamped to `1 ..= max_supersample`), so minified views do not
//!   alias and magnified (grazing) ones fall back to bilinear; parallel over rows.
//!
//! Frames are expected in linear values normalized to the sensor's full scale (1.0): the
//! marker detector treats values ≥ 1.0 as clipped and rejects markers that touch them.

pub use gonio_calibration::markers::{detect_markers, detect_markers_with, DetectOptions, MarkerDetection};
pub use gonio_calibration::rectify::{
    rectify_frame, HomographySource, Rectified, RectifyError, MAX_MARKER_RMS_PX, MIN_MARKERS,
};
pub use gonio_calibration::warp::{texel_samples, warp, RectifyParams};
pub use gonio_calibration::Homography;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn homography_source_is_snake_case_in_manifests() {
        assert_eq!(
            serde_json::to_string(&HomographySource::Markers).unwrap(),
            "\"markers\""
        );
        assert_eq!(serde_json::to_string(&HomographySource::Pose).unwrap(), "\"pose\"");
        let back: HomographySource = serde_json::from_str("\"pose\"").unwrap();
        assert_eq!(back, HomographySource::Pose);
    }

    #[test]
    fn a_uniform_frame_rectifies_through_the_pose() {
        // Whole pipeline through this module's names: a featureless frame has no markers,
        // so the pose homography is used and the uniform value comes through the filter.
        use gonio_devices::image::RgbImage;
        use gonio_devices::kinematics::for_rig;
        use gonio_devices::rig::RigSpec;
        use gonio_devices::target::MarkerBorder;
        let rig = RigSpec::default_rig();
        let pose = for_rig(&rig).camera_pose(&[0.0, 0.5, 0.0, 0.0]);
        let mut raw = RgbImage::new(rig.camera.width, rig.camera.height);
        raw.data.iter_mut().for_each(|v| *v = 0.25);
        let params = RectifyParams {
            width: 64,
            height: 64,
            sample_mm: 60.0,
            max_supersample: 8,
        };
        let r = rectify_frame(&raw, &rig.camera.intrinsics(), &pose, &MarkerBorder::default(), &params).unwrap();
        assert_eq!(r.source, HomographySource::Pose);
        assert_eq!((r.image.width, r.image.height), (64, 64));
        assert!(r.image.data.iter().all(|&v| (v - 0.25).abs() < 1e-6));
    }
}
