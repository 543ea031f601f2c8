//! What every export shares: the choice and naming of the exported images
//! ([`ExportEntry`], in canonical order, named as UBO2003 names them), the isotropy
//! transform of a reconstructed pair ([`IsoTransform`]), linear → 8-bit sRGB, and the
//! bounded parallel decode-then-write loop. The ground file of `export/`: the exporters
//! and `iso.rs` import it, it imports none of them.

use crate::store::error::{IoContext, StoreError};
use crate::store::exr_io::decode_exr;
use crate::store::manifest::{ManifestHeader, MeasurementRecord, MeasurementStatus};
use crate::store::sha256_hex;
use gonio_devices::image::RgbImage;
use rayon::prelude::*;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Images decoded and encoded in parallel per batch: bounds memory while keeping both
/// cores busy.
const BATCH: usize = 32;

/// What an export wrote.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ExportReport {
    /// The file written.
    pub path: PathBuf,
    /// Images exported.
    pub entries: usize,
    /// Of those, measured with a substituted light direction.
    pub substituted: usize,
    /// Skipped measurements, not exported.
    pub skipped: usize,
    /// Size of the written file in bytes.
    pub bytes: u64,
    /// The sidecar file (the `.npy` export's JSON), if any.
    pub sidecar: Option<PathBuf>,
}

/// One image of an export.
#[derive(Clone, Debug, PartialEq)]
pub struct ExportEntry {
    /// Running index (`IIIII`).
    pub position: usize,
    /// Canonical measurement index.
    pub index: usize,
    /// Full ZIP entry name.
    pub name: String,
    /// Integer (θ, φ) of the light and view as written in the name.
    pub light: [u32; 2],
    pub view: [u32; 2],
    /// Exact angles from the record.
    pub light_deg: [f64; 2],
    pub view_deg: [f64; 2],
    /// "measured" or "substituted".
    pub status: &'static str,
    /// Image path relative to the dataset and its expected hash.
    pub image: String,
    pub image_sha256: Option<String>,
    /// Set for a pair reconstructed from an isotropy-equivalent measurement (status
    /// "isotropic"; `image` is the representative's): see `iso.rs`.
    pub transform: Option<IsoTransform>,
}

/// Round a (θ, φ) direction in degrees to the integers used in UBO2003 names.
pub fn integer_angles(deg: [f64; 2]) -> [u32; 2] {
    let theta = deg[0].round().max(0.0) as u32;
    let phi = if theta == 0 {
        0
    } else {
        (deg[1].round().rem_euclid(360.0)) as u32 % 360
    };
    [theta, phi]
}

/// The ZIP entry name of an exported image (see the module documentation).
pub fn entry_name(position: usize, light_deg: [f64; 2], view_deg: [f64; 2]) -> String {
    let [tl, pl] = integer_angles(light_deg);
    let [tv, pv] = integer_angles(view_deg);
    format!("tv{tv:03}_pv{pv:03}/{position:05} tl{tl:03} pl{pl:03} tv{tv:03} pv{pv:03}.jpg")
}

/// Choose and name the measured records: not skipped, sorted by canonical index.
/// Returns the entries and the number of skipped records (isotropic equivalents are added
/// by [`super::entries`]).
pub fn plan_export(
    dir: &Path,
    records: &[MeasurementRecord],
    out: &Path,
) -> Result<(Vec<ExportEntry>, usize), StoreError> {
    let mut recs: Vec<&MeasurementRecord> = records.iter().collect();
    recs.sort_by_key(|r| r.index);
    let mut skipped = 0;
    let mut entries = Vec::new();
    let mut seen: HashMap<([u32; 2], [u32; 2]), usize> = HashMap::new();
    for r in recs {
        let status = match r.status {
            MeasurementStatus::Skipped { .. } => {
                skipped += 1;
                continue;
            }
            MeasurementStatus::Measured => "measured",
            MeasurementStatus::Substituted { .. } => "substituted",
            MeasurementStatus::Predicted { .. } => "predicted",
        };
        let Some(image) = r.image.clone() else {
            return Err(StoreError::DamagedImage {
                path: dir.to_path_buf(),
                index: r.index,
                problem: format!("not recorded although the measurement is {status}"),
            });
        };
        let light = integer_angles(r.light_deg);
        let view = integer_angles(r.view_deg);
        let position = entries.len();
        let name = entry_name(position, r.light_deg, r.view_deg);
        if let Some(first) = seen.insert((light, view), r.index) {
            return Err(StoreError::ExportConflict {
                path: out.to_path_buf(),
                first,
                second: r.index,
                name,
            });
        }
        entries.push(ExportEntry {
            position,
            index: r.index,
            name,
            light,
            view,
            light_deg: r.light_deg,
            view_deg: r.view_deg,
            status,
            image,
            image_sha256: r.image_sha256.clone(),
            transform: None,
        });
    }
    Ok((entries, skipped))
}

/// How an exported image is made from its representative's.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IsoTransform {
    /// Canonical index of the measured representative.
    pub representative: usize,
    /// Rotation ψ about the sample normal, degrees.
    pub rotation_deg: f64,
    /// Mirror φ → −φ (y → −y) before the rotation.
    pub mirrored: bool,
}

impl IsoTransform {
    /// The member's image from the representative's: `out(x) = rep(T⁻¹ x)`, bilinear,
    /// clamped at the edges (see the module documentation).
    pub fn apply(&self, rep: &RgbImage) -> RgbImage {
        let (w, h) = (rep.width, rep.height);
        let mut out = RgbImage::new(w, h);
        // (sin ψ, cos ψ), exact for quarter turns so that those are texel permutations
        let psi = self.rotation_deg.rem_euclid(360.0);
        let quarter = psi / 90.0;
        let (s, c) = if (quarter - quarter.round()).abs() < 1e-9 {
            match (quarter.round() as i64).rem_euclid(4) {
                0 => (0.0, 1.0),
                1 => (1.0, 0.0),
                2 => (0.0, -1.0),
                _ => (-1.0, 0.0),
            }
        } else {
            psi.to_radians().sin_cos()
        };
        for j in 0..h {
            for i in 0..w {
                // sample-plane coordinates in units of the sample size (rows grow with −y)
                let u = (i as f64 + 0.5) / w as f64 - 0.5;
                let v = 0.5 - (j as f64 + 0.5) / h as f64;
                // T⁻¹ = M · Rz(−ψ)
                let (ru, rv) = (c * u + s * v, -s * u + c * v);
                let rv = if self.mirrored { -rv } else { rv };
                let x = (ru + 0.5) * w as f64 - 0.5;
                let y = (0.5 - rv) * h as f64 - 0.5;
                out.set(i, j, bilinear(rep, x, y));
            }
        }
        out
    }
}

/// Bilinear sample at texel coordinates (texel centres at integers), edge-clamped.
fn bilinear(img: &RgbImage, x: f64, y: f64) -> [f32; 3] {
    // positions within 1e-9 texel of a centre are that centre: rotations by quarter turns
    // then copy texels exactly instead of blending in rounding noise
    let cl = |v: f64, n: usize| {
        let v = if (v - v.round()).abs() < 1e-9 { v.round() } else { v };
        v.clamp(0.0, (n - 1) as f64)
    };
    let (x, y) = (cl(x, img.width), cl(y, img.height));
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(img.width - 1), (y0 + 1).min(img.height - 1));
    let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let (a, b, c, d) = (img.get(x0, y0), img.get(x1, y0), img.get(x0, y1), img.get(x1, y1));
    let mut px = [0.0f32; 3];
    for k in 0..3 {
        let top = a[k] + (b[k] - a[k]) * fx;
        let bottom = c[k] + (d[k] - c[k]) * fx;
        px[k] = top + (bottom - top) * fy;
    }
    px
}

/// Linear value → 8-bit sRGB code value. Clamps to [0, 1] first (NaN → 0), so
/// over-exposed highlights saturate instead of wrapping.
pub fn linear_to_srgb8(v: f32) -> u8 {
    let v = if v > 0.0 { v.min(1.0) } else { 0.0 };
    let s = if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5).clamp(0.0, 255.0) as u8
}

/// Interleaved 8-bit sRGB of a linear image.
pub fn to_srgb8(img: &RgbImage) -> Vec<u8> {
    img.data.iter().map(|&v| linear_to_srgb8(v)).collect()
}

/// Read, hash-check and decode an exported entry's image and return its 8-bit sRGB.
pub(crate) fn load_srgb8(dir: &Path, header: &ManifestHeader, e: &ExportEntry) -> Result<Vec<u8>, StoreError> {
    Ok(to_srgb8(&load_linear(dir, header, e)?))
}

/// Read, hash-check and decode an exported entry's image (an isotropic equivalent
/// transformed from its representative's): the linear values every export starts from.
pub(crate) fn load_linear(dir: &Path, header: &ManifestHeader, e: &ExportEntry) -> Result<RgbImage, StoreError> {
    let path = dir.join(&e.image);
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(err) if err.kind() == std::io::ErrorKind::NotFound => {
            return Err(StoreError::DamagedImage {
                path,
                index: e.index,
                problem: "missing".into(),
            })
        }
        Err(err) => return Err(StoreError::io("reading", &path, Some(dir), err)),
    };
    if let Some(expected) = &e.image_sha256 {
        if sha256_hex(&bytes) != *expected {
            return Err(StoreError::DamagedImage {
                path,
                index: e.index,
                problem: "damaged (its SHA-256 differs from the journal's)".into(),
            });
        }
    }
    let img = decode_exr(&bytes, &path)?;
    if img.width != header.image_width || img.height != header.image_height {
        return Err(StoreError::DamagedImage {
            path,
            index: e.index,
            problem: format!(
                "{}×{} instead of the dataset's {}×{}",
                img.width, img.height, header.image_width, header.image_height
            ),
        });
    }
    Ok(match &e.transform {
        Some(t) => t.apply(&img),
        None => img,
    })
}

/// Run `f` over `entries` in parallel batches, handing results to `sink` in order.
pub(crate) fn for_each_in_order<T: Send>(
    entries: &[ExportEntry],
    f: impl Fn(&ExportEntry) -> Result<T, StoreError> + Sync,
    mut sink: impl FnMut(&ExportEntry, T) -> Result<(), StoreError>,
) -> Result<(), StoreError> {
    for batch in entries.chunks(BATCH) {
        let results: Vec<Result<T, StoreError>> = batch.par_iter().map(&f).collect();
        for (e, r) in batch.iter().zip(results) {
            sink(e, r?)?;
        }
    }
    Ok(())
}

/// Make sure the directory that will hold `out` exists.
pub(crate) fn ensure_parent(out: &Path) -> Result<(), StoreError> {
    if let Some(p) = out.parent() {
        if !p.as_os_str().is_empty() {
            std::fs::create_dir_all(p).ctx("creating directory", p, None)?;
        }
    }
    Ok(())
}
