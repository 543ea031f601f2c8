//! Calibration for gonio: plane homographies, marker detection on the sample holder and
//! the rectification of raw frames onto the sample's texel grid.
//!
//! - [`homography`]: the plane → pixel map, exact from a camera pose or fitted to points.
//! - [`markers`]: sub-pixel detection of the holder's border markers, located through a
//!   predicted homography.
//! - [`warp`]: the anti-aliased resampling of a raw frame onto the texel grid.
//! - [`rectify`]: one frame end to end — marker homography where the markers are reliable,
//!   pose homography where they are not, then the warp. The root crate's `rectify` module
//!   re-exports it.

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
