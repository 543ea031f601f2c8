//! gonio-calibration: the calibration algorithms, pure functions of images and numbers (it
//! never renders and never drives a rig, so it runs the same on real rigs' frames). The
//! root crate's `calibrate/` drives recipes on a rig and calls these; its `develop/` uses
//! the rectification every acquisition runs. The rule: `gonio_calibration::K` fits K,
//! `gonio::calibrate::K` drives recipe kind K on a rig.
//!
//! Geometry of the sample plane (every acquisition):
//! - [`homography`]: the plane → pixel map, exact from a camera pose or fitted to points.
//! - [`markers`]: sub-pixel detection of the holder's border markers, located through a
//!   predicted homography.
//! - [`warp`]: the anti-aliased resampling of a raw frame onto the texel grid.
//! - [`rectify`]: one frame end to end — marker homography where the markers are reliable,
//!   pose homography where they are not, then the warp.
//!
//! Targets and corners:
//! - [`checkerboard`]: corner detection and grid growth, sub-pixel refinement;
//! - [`coded_board`]: the coded-marker board (grids per visible piece, markers read through
//!   local homographies, majority labelling); partial views give the corners they show;
//! - [`board`]: the target a recipe names (either board), one `detect`;
//! - [`wedge`]: a board on a wedge, its points on the tilted plane;
//! - [`corner_model`]: the final sub-pixel step, a model of the corner integrated over the
//!   pixel area and fitted to the raw pixels.
//!
//! Fits:
//! - [`intrinsics`]: Zhang's closed form + LM with OpenCV's distortion model;
//!   [`uncertainty`]: its projection uncertainty over the whole image and the corners' coverage;
//! - [`rig_geometry`]: bundle adjustment of axis zero offsets and the camera mount;
//! - [`light_geometry`]: the lamp axes' zero offsets from a near-mirror's highlight;
//!   the two offset fits share their checks and parameter table (`offset_fit.rs`);
//! - [`radiometric`]: dark frame, flat field, Debevec–Malik response, HDR merge with
//!   diagnosis, colour 3 × 3 (linear algebra from `nalgebra`).

pub mod board;
pub mod checkerboard;
pub mod coded_board;
pub mod corner_model;
pub mod error;
pub mod homography;
pub mod intrinsics;
pub mod light_geometry;
pub mod markers;
pub mod radiometric;
pub mod rectify;
pub mod rig_geometry;
pub mod uncertainty;
pub mod warp;
pub mod wedge;

pub use error::CalibError;
pub use homography::{Correspondence, Homography};
pub use markers::{detect_markers, detect_markers_with, DetectOptions, MarkerDetection};
pub use rectify::{rectify_frame, HomographySource, Rectified, RectifyError};
pub use warp::{texel_samples, warp, RectifyParams};

mod offset_fit;

#[cfg(test)]
mod testutil;
