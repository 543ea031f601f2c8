//! Error of a compressed BTF against its dataset, and peak memory.
//!
//! Errors are computed over every **measured** (light, view) pair (filled pairs are not
//! counted), on two scales:
//! * **8-bit sRGB /255**: both images are encoded to 8-bit sRGB exactly as the UBO2003
//!   export does ([`gonio_dataset::store::linear_to_srgb8`], values clamped to [0, 1]); the
//!   difference of the 8-bit codes is divided by 255. RMSE, mean absolute error and max
//!   error are on this scale, and PSNR = 20·log10(1 / RMSE) dB on it.
//! * **linear**: RMSE of the raw linear values (the dataset's `values` unit).
//!
//! When the dataset was acquired with `--store-truth` (a simulated rig writes the exact
//! noiseless rectified image of measurement `i` as `truth/iiiii.exr`), the reconstruction is
//! also compared with that truth, and so is the measurement itself: the second figure is
//! the floor set by sensor noise and rectification, which no compression of the
//! measurements can beat on average (and which a low-rank model can undercut slightly,
//! because truncation removes some of the noise).

use super::data::DatasetViews;
use super::error::CompressError;
use super::interp::BtfModel;
use gonio_dataset::store::linear_to_srgb8;
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
    /// Add the statistics of another part (e.g. computed in parallel).
    pub fn merge(&mut self, other: &ErrorStats) {
        self.values += other.values;
        self.sum_sq_8bit += other.sum_sq_8bit;
        self.sum_abs_8bit += other.sum_abs_8bit;
        self.max_8bit = self.max_8bit.max(other.max_8bit);
        self.sum_sq_linear += other.sum_sq_linear;
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

/// Error against the simulator's ground truth (datasets acquired with `--store-truth`).
#[derive(Serialize, Clone, Debug, PartialEq)]
pub struct TruthEvaluation {
    /// Measured images that have a truth image.
    pub images: usize,
    /// Reconstruction against truth.
    pub reconstruction: ErrorStats,
    /// Measurement against truth (the noise and rectification floor).
    pub measurement: ErrorStats,
}

/// Result of [`evaluate`].
#[derive(Serialize, Clone, Debug, PartialEq)]
pub struct Evaluation {
    pub images: usize,
    pub stats: ErrorStats,
    /// Mean wall time of [`BtfModel::reconstruct`] per image.
    pub decode_seconds_per_image: f64,
    /// `None` when the dataset has no `truth/` images.
    pub truth: Option<TruthEvaluation>,
}

/// The stored truth image of canonical measurement `index`, if the dataset has one.
pub fn read_truth(ds: &DatasetViews, index: usize) -> Result<Option<Vec<f32>>, CompressError> {
    let path = ds.dir.join(format!("truth/{index:05}.exr"));
    if !path.is_file() {
        return Ok(None);
    }
    let img = gonio_dataset::store::read_exr(&path)?;
    if img.width != ds.width || img.height != ds.height {
        return Err(CompressError::Dataset {
            dir: ds.dir.clone(),
            reason: format!(
                "{} is {}×{}, the images are {}×{}",
                path.display(),
                img.width,
                img.height,
                ds.width,
                ds.height
            ),
        });
    }
    Ok(Some(img.data))
}

/// Reconstruct every measured image of `ds` from `model` and compare (and with the
/// ground truth where the dataset stores it).
pub fn evaluate(ds: &DatasetViews, model: &dyn BtfModel) -> Result<Evaluation, CompressError> {
    if (
        model.width(),
        model.height(),
        model.lights_deg().len(),
        model.views_deg().len(),
    ) != (ds.width, ds.height, ds.n_lights(), ds.n_views())
    {
        return Err(CompressError::Invalid(
            "the compressed file's grid or image size differs from the dataset's".into(),
        ));
    }
    let mut stats = ErrorStats::default();
    let mut truth = TruthEvaluation {
        images: 0,
        reconstruction: ErrorStats::default(),
        measurement: ErrorStats::default(),
    };
    let (mut images, mut decode_s) = (0usize, 0f64);
    for v in 0..ds.n_views() {
        for l in 0..ds.n_lights() {
            let Some(orig) = ds.read_image(l, v)? else { continue };
            let t0 = Instant::now();
            let rec = model.reconstruct(l, v)?;
            decode_s += t0.elapsed().as_secs_f64();
            stats.add(&orig, &rec);
            images += 1;
            if let Some(t) = read_truth(ds, v * ds.n_lights() + l)? {
                truth.reconstruction.add(&t, &rec);
                truth.measurement.add(&t, &orig);
                truth.images += 1;
            }
        }
    }
    Ok(Evaluation {
        images,
        stats,
        decode_seconds_per_image: decode_s / images.max(1) as f64,
        truth: (truth.images > 0).then_some(truth),
    })
}

/// Peak resident set size of this process (VmHWM of /proc/self/status), if available.
pub fn peak_memory_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}
