//! Image buffers shared by devices, the simulator and the processing pipeline.

use serde::{Deserialize, Serialize};

/// The value unit of uncalibrated images (`extra.value_unit`): the sensor's linear signal
/// normalised so that 1 is its full scale ([`crate::rig::FULL_SCALE`]). One home: the
/// acquisition writes it, the dataset's drift correction reads it.
pub const VALUE_UNIT_DN: &str = "normalized_dn";

/// The sRGB transfer curve's inverse (IEC 61966-2-1): a code value in [0, 1] to linear
/// light. The one home of the curve for the readers of sRGB data (camera JPEGs and
/// formats, archives, textures).
pub fn srgb_decode(v: f64) -> f64 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// [`srgb_decode`] of an 8-bit code, in `f32` arithmetic (the bytes of the datasets and
/// caches built with it depend on that precision).
pub fn srgb8_to_linear(code: u8) -> f32 {
    let c = code as f32 / 255.0;
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// An interleaved RGB image of linear `f32` values, row-major, row 0 at the top.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RgbImage {
    pub width: usize,
    pub height: usize,
    /// `width * height * 3` values.
    pub data: Vec<f32>,
}

impl RgbImage {
    pub fn new(width: usize, height: usize) -> Self {
        RgbImage {
            width,
            height,
            data: vec![0.0; width * height * 3],
        }
    }
    #[inline]
    pub fn get(&self, x: usize, y: usize) -> [f32; 3] {
        let i = (y * self.width + x) * 3;
        [self.data[i], self.data[i + 1], self.data[i + 2]]
    }
    #[inline]
    pub fn set(&mut self, x: usize, y: usize, c: [f32; 3]) {
        let i = (y * self.width + x) * 3;
        self.data[i..i + 3].copy_from_slice(&c);
    }
}
