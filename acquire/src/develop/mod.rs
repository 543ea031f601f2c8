//! Develop: one captured frame → the values a dataset stores (as a photographer develops a
//! negative). The whole per-frame chain lives here, in the order the light went through
//! the rig backwards:
//!
//! 1. **raw corrections** (`raw.rs`): inverse response, dark, flat, colour on the frame's
//!    digital numbers; without them, DN / max DN ([`frame_to_linear`]);
//! 2. **exposure scale** of a re-exposed frame, back to the nominal exposure; or, for an
//!    HDR bracket, the noise-optimal **merge** of its exposures (`hdr.rs`) onto the base
//!    exposure's scale;
//! 3. **lens** (`lens.rs`): undistortion to the calibrated pinhole camera;
//! 4. **rectification** (`rectify.rs`): markers or pose homography onto the sample's texel
//!    grid;
//! 5. **BRDF** (`brdf.rs`): the white standard's conversion of linear values to 1/sr.
//!
//! [`Developer`] holds what one acquisition applies and runs the chain with
//! [`Developer::develop`]; the engine calls only that and knows nothing of calibration
//! kinds. `calibrate::apply` builds a developer's [`Corrections`] from result files. This
//! folder imports no other folder of `src/` (ARCHITECTURE.md, invariant 2).

pub mod brdf;
pub mod hdr;
pub mod lens;
pub mod raw;
pub mod rectify;
#[cfg(test)]
mod tests;

pub use brdf::{LampModel, Radiometric};
pub use lens::undistort_frame;
pub use raw::{BlockMap, CameraMismatch, CorrectionSource, MapPart, RawCorrection, RawCorrectionError, RawParts};

use gonio_calibration::intrinsics::CameraModel;
use gonio_devices::image::RgbImage;
use gonio_devices::kinematics::CameraPose;
use gonio_devices::target::MarkerBorder;
use gonio_devices::{Frame, Intrinsics, Vec3};
use rectify::{Rectified, RectifyParams};
use thiserror::Error;

#[derive(Debug, Error, Clone, PartialEq)]
pub enum DevelopError {
    #[error("rig `{rig}`: {key} = {value}: {message}")]
    RigValue {
        rig: String,
        key: String,
        value: String,
        message: String,
    },
    #[error("image {width}×{height}: buffer holds {len} values, needs {expected}")]
    BadImage {
        width: usize,
        height: usize,
        len: usize,
        expected: usize,
    },
    #[error("measurement exposure {exposure_s} s × gain {gain}: must be > 0 to convert to BRDF")]
    BadExposure { exposure_s: f64, gain: f64 },
    #[error(
        "frame {width}×{height} ({len} values): the radiometric corrections were made for \
         {expected_width}×{expected_height} frames"
    )]
    FrameSize {
        width: usize,
        height: usize,
        len: usize,
        expected_width: usize,
        expected_height: usize,
    },
    /// Rectification refused the frame (the message says why: parameters or image).
    #[error("rectification: {0}")]
    Rectify(String),
}

/// Convert a frame of DN values into linear normalised values (DN / max DN).
pub fn frame_to_linear(frame: &Frame) -> RgbImage {
    let k = 1.0 / frame.max_dn() as f32;
    RgbImage {
        width: frame.width,
        height: frame.height,
        data: frame.data.iter().map(|&v| v as f32 * k).collect(),
    }
}

/// The corrections an acquisition applies (all optional; none = DN / max DN rectified
/// through the nominal camera).
#[derive(Clone, Debug, Default)]
pub struct Corrections {
    /// Calibrated camera: frames are undistorted with it and rectified with its matrix.
    pub camera: Option<CameraModel>,
    /// Conversion of rectified values to BRDF (1/sr).
    pub radiometric: Option<Radiometric>,
    /// Dark, response, flat and colour on each raw frame.
    pub raw: Option<RawCorrection>,
}

/// One developed frame: the rectified image in the stored unit, how it was rectified, and
/// how many raw pixels were saturated (with raw corrections; `None` without).
#[derive(Clone, Debug)]
pub struct Developed {
    pub rectified: Rectified,
    pub saturated: Option<usize>,
}

/// The per-frame chain of one acquisition (see the module docs).
#[derive(Clone, Debug)]
pub struct Developer {
    params: RectifyParams,
    intrinsics: Intrinsics,
    border: MarkerBorder,
    corrections: Corrections,
    /// The simulated sensor's true `K`, for the ground truth's conversion to BRDF when raw
    /// corrections put the fitted `K` on the response curve's scale (simulated rigs only).
    truth_k: Option<f64>,
}

impl Developer {
    /// A developer for rectified images of `params`, rectifying through `nominal` intrinsics
    /// (replaced by the calibrated camera's when `corrections` has one) and the holder's
    /// marker `border`. `truth_k`: the simulated sensor's true `K` (see [`Developer`]).
    pub fn new(
        params: RectifyParams,
        nominal: Intrinsics,
        border: MarkerBorder,
        corrections: Corrections,
        truth_k: Option<f64>,
    ) -> Developer {
        let intrinsics = match &corrections.camera {
            Some(c) => Intrinsics {
                fx: c.fx,
                fy: c.fy,
                cx: c.cx,
                cy: c.cy,
            },
            None => nominal,
        };
        Developer {
            params,
            intrinsics,
            border,
            corrections,
            truth_k,
        }
    }

    /// The rectification parameters (size, sample edge, supersampling cap).
    pub fn params(&self) -> &RectifyParams {
        &self.params
    }

    /// Develop one frame seen from `pose` with the lamp at `lamp` (mm, sample frame).
    /// `exposure_scale`: the factor that brings a re-exposed frame back to the nominal
    /// exposure (ignored with a radiometric conversion, which divides by each frame's own
    /// exposure).
    pub fn develop(
        &self,
        frame: &Frame,
        pose: &CameraPose,
        lamp: Vec3,
        exposure_scale: Option<f32>,
    ) -> Result<Developed, DevelopError> {
        let c = &self.corrections;
        let (mut raw, saturated) = self.linearize(frame)?;
        if let (Some(k), None) = (exposure_scale, &c.radiometric) {
            // Re-exposed after saturating: back to the nominal exposure's scale.
            raw.data.iter_mut().for_each(|v| *v *= k);
        }
        let rectified = self.develop_linear(raw, pose, lamp, frame.meta.exposure, frame.meta.gain)?;
        Ok(Developed { rectified, saturated })
    }

    /// Dark, response, flat, colour: on the raw frame, before the geometry. Returns the
    /// linear image and the saturated pixel count (with raw corrections).
    fn linearize(&self, frame: &Frame) -> Result<(RgbImage, Option<usize>), DevelopError> {
        Ok(match &self.corrections.raw {
            Some(r) => {
                let (img, n) = r.apply(frame)?;
                (img, Some(n))
            }
            None => (frame_to_linear(frame), None),
        })
    }

    /// Develop an HDR bracket (`frames[0]` the base exposure, `base_exposure_s` the
    /// nominal one): each frame linearised, merged noise-optimally onto the base exposure's
    /// scale ([`hdr::merge`]), then lens, rectification and BRDF as for one frame (the BRDF
    /// conversion divides by the base exposure, the scale of the merged values).
    pub fn develop_bracket(
        &self,
        frames: &[Frame],
        pose: &CameraPose,
        lamp: Vec3,
        base_exposure_s: f64,
        noise: &gonio_devices::hdr::SensorNoise,
    ) -> Result<(Developed, hdr::MergeReport), DevelopError> {
        let mut layers = Vec::with_capacity(frames.len());
        for f in frames {
            let (linear, _) = self.linearize(f)?;
            let saturation_code = match &self.corrections.raw {
                Some(r) => r.saturation_code(f.max_dn()),
                None => f.max_dn(),
            };
            layers.push(hdr::Layer {
                linear,
                frame: f,
                saturation_code,
            });
        }
        let (merged, report) = hdr::merge(&layers, base_exposure_s, noise);
        drop(layers);
        let gain = frames[0].meta.gain;
        let rectified = self.develop_linear(merged, pose, lamp, base_exposure_s, gain)?;
        let saturated = self.corrections.raw.as_ref().map(|_| report.clipped_pixels);
        Ok((Developed { rectified, saturated }, report))
    }

    /// Lens, rectification and BRDF conversion of a linear frame exposed `exposure_s` at
    /// `gain`.
    fn develop_linear(
        &self,
        mut raw: RgbImage,
        pose: &CameraPose,
        lamp: Vec3,
        exposure_s: f64,
        gain: f64,
    ) -> Result<Rectified, DevelopError> {
        let c = &self.corrections;
        if let Some(cam) = &c.camera {
            raw = undistort_frame(&raw, cam);
        }
        let mut rectified = rectify::rectify_frame(&raw, &self.intrinsics, pose, &self.border, &self.params)
            .map_err(|e| DevelopError::Rectify(e.to_string()))?;
        if let Some(r) = &c.radiometric {
            r.to_brdf(&mut rectified.image, lamp, &self.params, exposure_s, gain)?;
        }
        Ok(rectified)
    }

    /// Bring the simulator's ground truth (normalised sensor signal of an ideal linear
    /// sensor) to the unit of the developed images, so the truth error compares like with
    /// like. With raw corrections the fitted `K` is on the response curve's scale, so the
    /// truth is converted with the simulated sensor's true `K` instead.
    pub fn develop_truth(
        &self,
        truth: &mut RgbImage,
        lamp: Vec3,
        exposure_s: f64,
        gain: f64,
    ) -> Result<(), DevelopError> {
        let Some(r) = &self.corrections.radiometric else {
            return Ok(());
        };
        let radio = match (&self.corrections.raw, self.truth_k) {
            (Some(_), Some(k)) => Radiometric {
                k: [k; 3],
                lamp: r.lamp,
            },
            _ => *r,
        };
        radio.to_brdf(truth, lamp, &self.params, exposure_s, gain)
    }
}
