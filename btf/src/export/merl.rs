//! The averaged BRDF as a MERL BRDF binary (Matusik et al. 2003, the MERL/MIT isotropic
//! database's `.binary`), which many renderers and BRDF tools read, plus a sidecar
//! `OUT.binary.json` with the provenance (the format has no metadata field).
//!
//! **Layout** (the public reader's, `BRDFRead.cpp`): three little-endian `i32` dimensions
//! `90 90 180` (θ_h, θ_d, φ_d), then per channel R, G, B the `90·90·180` values as `f64`,
//! φ_d fastest, then θ_d, then θ_h; a reader multiplies red by 1/1500, green by 1.15/1500
//! and blue by 1.66/1500, so the file holds `f / scale`.
//!
//! **Bins.** θ_h is indexed by `⌊√(θ_h / 90°) · 90⌋` (dense near the highlight), θ_d by
//! `⌊θ_d / 1°⌋`, φ_d by `⌊φ_d / 1°⌋` on [0°, 180°) (reciprocity folds φ_d + 180° onto
//! φ_d). Bin `(i, j, k)` holds the BRDF at the angles the indices stand for: θ_h =
//! (i/90)² · 90°, θ_d = j°, φ_d = k°, φ_h = 0 (isotropic), with the incident (light)
//! direction `l = R_z(φ_h) R_y(θ_h) d(θ_d, φ_d)` and the view its mirror about the half
//! vector. Pairs with a direction below the horizon hold 0.

use super::average::AverageBrdf;
use super::{io, ExportError};
use gonio_devices::Vec3;
use rayon::prelude::*;
use serde::Serialize;
use std::f64::consts::{FRAC_PI_2, PI};
use std::path::{Path, PathBuf};

pub const THETA_H: usize = 90;
pub const THETA_D: usize = 90;
pub const PHI_D: usize = 180;
/// The public reader's per-channel factors (file value × scale = BRDF in 1/sr).
pub const SCALE: [f64; 3] = [1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0];

/// What `write` produced.
#[derive(Clone, Debug, Serialize)]
pub struct MerlSummary {
    pub sidecar: PathBuf,
    pub bytes: usize,
    /// Bins with a direction below the horizon (stored as 0).
    pub below_horizon: usize,
}

/// The (light, view) directions of bin (`i`, `j`, `k`).
pub fn bin_directions(i: usize, j: usize, k: usize) -> (Vec3, Vec3) {
    let th = (i as f64 / THETA_H as f64).powi(2) * FRAC_PI_2;
    let td = j as f64 * FRAC_PI_2 / THETA_D as f64;
    let pd = k as f64 * PI / PHI_D as f64;
    let d = Vec3::new(td.sin() * pd.cos(), td.sin() * pd.sin(), td.cos());
    // Rotate the difference vector by θ_h about +y (φ_h = 0).
    let (s, c) = th.sin_cos();
    let l = Vec3::new(d.x * c + d.z * s, d.y, -d.x * s + d.z * c);
    let h = Vec3::new(s, 0.0, c);
    let v = h * (2.0 * h.dot(l)) - l;
    (l, v)
}

/// The `.binary` bytes of `avg` and the count of bins below the horizon.
pub fn encode(avg: &AverageBrdf) -> (Vec<u8>, usize) {
    let per = THETA_D * PHI_D;
    let rows: Vec<(Vec<[f64; 3]>, usize)> = (0..THETA_H)
        .into_par_iter()
        .map(|i| {
            let mut below = 0;
            let vals = (0..per)
                .map(|jk| {
                    let (l, v) = bin_directions(i, jk / PHI_D, jk % PHI_D);
                    if l.z <= 0.0 || v.z <= 0.0 {
                        below += 1;
                        return [0.0; 3];
                    }
                    avg.eval(l, v)
                })
                .collect();
            (vals, below)
        })
        .collect();
    let n = THETA_H * per;
    let mut out = Vec::with_capacity(12 + 3 * n * 8);
    for d in [THETA_H, THETA_D, PHI_D] {
        out.extend_from_slice(&(d as i32).to_le_bytes());
    }
    for (c, scale) in SCALE.iter().enumerate() {
        for (vals, _) in &rows {
            for f in vals {
                out.extend_from_slice(&(f[c] / scale).to_le_bytes());
            }
        }
    }
    (out, rows.iter().map(|r| r.1).sum())
}

/// `OUT.binary.json` beside `out`.
pub fn sidecar_path(out: &Path) -> PathBuf {
    let mut s = out.as_os_str().to_owned();
    s.push(".json");
    PathBuf::from(s)
}

/// Write `avg` as `out` (a `.binary` file) and its sidecar.
pub fn write(avg: &AverageBrdf, out: &Path) -> Result<MerlSummary, ExportError> {
    let (bytes, below) = encode(avg);
    std::fs::write(out, &bytes).map_err(io(out))?;
    let sidecar = sidecar_path(out);
    let meta = serde_json::json!({
        "format": "MERL BRDF binary: i32 dims [90, 90, 180] (theta_h, theta_d, phi_d), then per channel R, G, B \
                   float64 values, phi_d fastest; BRDF (1/sr) = value * scale",
        "scale": SCALE,
        "bins": "theta_h = (i/90)^2 * 90 deg, theta_d = j deg, phi_d = k deg in [0, 180), phi_h = 0; light = \
                 R_z(phi_h) R_y(theta_h) d, view its mirror about the half vector; 0 below the horizon",
        "below_horizon_bins": below,
        "provenance": avg.provenance,
    });
    let text = serde_json::to_string_pretty(&meta).map_err(|e| ExportError::Output {
        path: sidecar.display().to_string(),
        reason: e.to_string(),
    })?;
    std::fs::write(&sidecar, text + "\n").map_err(io(&sidecar))?;
    Ok(MerlSummary {
        sidecar,
        bytes: bytes.len(),
        below_horizon: below,
    })
}
