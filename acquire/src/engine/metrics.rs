//! Error of rectified images against the simulator's ground truth.
//!
//! Values are linear, normalised sensor units (DN / max DN); both images are clipped at
//! 1.0 (saturation) before comparing, since no camera can report more. PSNR uses peak 1.

use gonio_devices::image::RgbImage;
use serde::{Deserialize, Serialize};

/// Running sums over many images.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct ErrorAccumulator {
    pub sum_sq: f64,
    pub sum_abs: f64,
    pub max_abs: f64,
    pub count: u64,
    pub images: u64,
}

/// Summary figures of an accumulator.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ErrorFigures {
    pub rmse: f64,
    pub mean_abs: f64,
    pub max_abs: f64,
    pub psnr_db: f64,
    pub images: u64,
    /// The scale of the figures.
    pub scale: String,
}

/// Error of one image: (sum of squares, sum of abs, max abs, count).
pub fn image_error(a: &RgbImage, truth: &RgbImage) -> (f64, f64, f64, u64) {
    let mut sq = 0.0;
    let mut ab = 0.0;
    let mut mx: f64 = 0.0;
    for (x, t) in a.data.iter().zip(&truth.data) {
        let d = (x.clamp(0.0, 1.0) - t.clamp(0.0, 1.0)) as f64;
        sq += d * d;
        ab += d.abs();
        mx = mx.max(d.abs());
    }
    (sq, ab, mx, a.data.len() as u64)
}

impl ErrorAccumulator {
    pub fn add(&mut self, e: (f64, f64, f64, u64)) {
        self.sum_sq += e.0;
        self.sum_abs += e.1;
        self.max_abs = self.max_abs.max(e.2);
        self.count += e.3;
        self.images += 1;
    }

    pub fn merge(&mut self, o: &ErrorAccumulator) {
        self.sum_sq += o.sum_sq;
        self.sum_abs += o.sum_abs;
        self.max_abs = self.max_abs.max(o.max_abs);
        self.count += o.count;
        self.images += o.images;
    }

    pub fn figures(&self) -> Option<ErrorFigures> {
        if self.count == 0 {
            return None;
        }
        let rmse = (self.sum_sq / self.count as f64).sqrt();
        Some(ErrorFigures {
            rmse,
            mean_abs: self.sum_abs / self.count as f64,
            max_abs: self.max_abs,
            psnr_db: if rmse > 0.0 {
                -20.0 * rmse.log10()
            } else {
                f64::INFINITY
            },
            images: self.images,
            scale: "linear, normalised sensor signal (DN / max DN), clipped at 1; PSNR peak 1".into(),
        })
    }
}

/// RMSE of one image against truth.
pub fn rmse(a: &RgbImage, truth: &RgbImage) -> f64 {
    let (sq, _, _, n) = image_error(a, truth);
    (sq / n.max(1) as f64).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psnr_of_known_error() {
        let a = RgbImage {
            width: 1,
            height: 1,
            data: vec![0.5, 0.5, 0.5],
        };
        let b = RgbImage {
            width: 1,
            height: 1,
            data: vec![0.6, 0.4, 2.0],
        };
        let mut acc = ErrorAccumulator::default();
        acc.add(image_error(&a, &b));
        let f = acc.figures().unwrap();
        // errors 0.1, 0.1, 0.5 (2.0 clipped to 1.0)
        let want = ((0.01 + 0.01 + 0.25) / 3.0f64).sqrt();
        assert!((f.rmse - want).abs() < 1e-6);
        assert!((f.max_abs - 0.5).abs() < 1e-6);
        assert!((f.psnr_db + 20.0 * want.log10()).abs() < 1e-4);
    }
}
