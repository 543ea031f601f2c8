//! Error of a compressed BTF against its dataset, and peak memory.
//!
//! Errors are computed over every **measured** (light, view) pair (filled pairs are not
//! counted), on two scales:
//! * **8-bit sRGB /255**: both images are encoded to 8-bit sRGB exactly as the UBO2003
//!   export does ([`crate::store::linear_to_srgb8`], values clamped to [0, 1]); the
//!   difference of the 8-bit codes is divided by 255. RMSE, mean absolute error and max
//!   error are on this scale, and PSNR = 20·log10(1 / RMSE) dB on it.
//! * **linear**: RMSE of the raw linear values (the dataset's `values` unit).

use super::data::DatasetViews;
use super::factor::CompressedBtf;
use super::CompressError;
use crate::store::linear_to_srgb8;
use serde::Serialize;
use std::time::Instant;

/// Running error statistics.
#[derive(Serialize, Clone, Debug, Default, PartialEq)]
pub struct ErrorStats {
    /// Values compared (texels · 3 · images).
    pub values: u64,
    pub sum_sq_8bit: f64,
    pub sum_abs_8bit: f64,
    pub max_8bit: f64,
    pub sum_sq_linear: f64,
}

impl ErrorStats {
    /// Add one image pair (interleaved linear RGB of equal length).
    pub fn add(&mut self, original: &[f32], reconstructed: &[f32]) {
        for (&a, &b) in original.iter().zip(reconstructed) {
            let d8 = (linear_to_srgb8(a) as f64 - linear_to_srgb8(b) as f64).abs() / 255.0;
            self.sum_sq_8bit += d8 * d8;
            self.sum_abs_8bit += d8;
            self.max_8bit = self.max_8bit.max(d8);
            let dl = a as f64 - b as f64;
            self.sum_sq_linear += dl * dl;
        }
        self.values += original.len().min(reconstructed.len()) as u64;
    }
    fn n(&self) -> f64 {
        self.values.max(1) as f64
    }
    /// RMSE on the 8-bit sRGB scale /255.
    pub fn rmse_8bit(&self) -> f64 {
        (self.sum_sq_8bit / self.n()).sqrt()
    }
    /// Mean absolute error on the 8-bit sRGB scale /255.
    pub fn mean_abs_8bit(&self) -> f64 {
        self.sum_abs_8bit / self.n()
    }
    /// PSNR in dB on the 8-bit sRGB scale (peak 1 = 255/255); infinite if exact.
    pub fn psnr_8bit(&self) -> f64 {
        -20.0 * self.rmse_8bit().log10()
    }
    /// RMSE of the linear values.
    pub fn rmse_linear(&self) -> f64 {
        (self.sum_sq_linear / self.n()).sqrt()
    }
}

/// Result of [`evaluate`].
#[derive(Serialize, Clone, Debug, PartialEq)]
pub struct Evaluation {
    pub images: usize,
    pub stats: ErrorStats,
    /// Mean wall time of [`CompressedBtf::reconstruct`] per image.
    pub decode_seconds_per_image: f64,
}

/// Reconstruct every measured image of `ds` from `model` and compare.
pub fn evaluate(ds: &DatasetViews, model: &CompressedBtf) -> Result<Evaluation, CompressError> {
    let h = model.header();
    if (h.width, h.height, h.lights_deg.len(), h.views_deg.len()) != (ds.width, ds.height, ds.n_lights(), ds.n_views())
    {
        return Err(CompressError::Invalid(
            "the compressed file's grid or image size differs from the dataset's".into(),
        ));
    }
    let mut stats = ErrorStats::default();
    let (mut images, mut decode_s) = (0usize, 0f64);
    for v in 0..ds.n_views() {
        for l in 0..ds.n_lights() {
            let Some(orig) = ds.read_image(l, v)? else { continue };
            let t0 = Instant::now();
            let rec = model.reconstruct(l, v)?;
            decode_s += t0.elapsed().as_secs_f64();
            stats.add(&orig, &rec);
            images += 1;
        }
    }
    Ok(Evaluation {
        images,
        stats,
        decode_seconds_per_image: decode_s / images.max(1) as f64,
    })
}

/// Peak resident set size of this process (VmHWM of /proc/self/status), if available.
pub fn peak_memory_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}
