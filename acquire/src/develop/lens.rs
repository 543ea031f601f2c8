//! Lens: a raw frame resampled to the ideal pinhole camera of the calibrated intrinsics, so
//! the homography rectification (markers or pose), which assumes a pinhole, holds on a
//! distorting lens.

use gonio_calibration::intrinsics::CameraModel;
use gonio_devices::image::RgbImage;

/// Resample a raw frame (gonio pixel convention: pixel (i, j) centred at (i + ½, j + ½)) to
/// the distortion-free pinhole camera with the same matrix: each output pixel looks up where
/// the lens put its ray (bilinear). Pixels whose source falls outside the frame become 0.
pub fn undistort_frame(raw: &RgbImage, cam: &CameraModel) -> RgbImage {
    if cam.distortion.iter().all(|&c| c == 0.0) {
        return raw.clone();
    }
    let (w, h) = (raw.width, raw.height);
    let mut out = RgbImage {
        width: w,
        height: h,
        data: vec![0.0; w * h * 3],
    };
    if w < 2 || h < 2 || raw.data.len() != w * h * 3 {
        return out;
    }
    use rayon::prelude::*;
    out.data.par_chunks_mut(w * 3).enumerate().for_each(|(j, row)| {
        let y = (j as f64 + 0.5 - cam.cy) / cam.fy;
        for i in 0..w {
            let x = (i as f64 + 0.5 - cam.cx) / cam.fx;
            let (xd, yd) = cam.distort(x, y);
            let (u, v) = (cam.fx * xd + cam.cx - 0.5, cam.fy * yd + cam.cy - 0.5);
            if !(u >= 0.0 && v >= 0.0 && u <= (w - 1) as f64 && v <= (h - 1) as f64) {
                continue;
            }
            let (i0, j0) = ((u as usize).min(w - 2), (v as usize).min(h - 2));
            let (fu, fv) = ((u - i0 as f64) as f32, (v - j0 as f64) as f32);
            for c in 0..3 {
                let at = |ii: usize, jj: usize| raw.data[(jj * w + ii) * 3 + c];
                let top = at(i0, j0) * (1.0 - fu) + at(i0 + 1, j0) * fu;
                let bot = at(i0, j0 + 1) * (1.0 - fu) + at(i0 + 1, j0 + 1) * fu;
                row[i * 3 + c] = top * (1.0 - fv) + bot * fv;
            }
        }
    });
    out
}
