//! Export to the Bonn UBO2003 archive layout (a ZIP of 8-bit sRGB JPEGs).
//!
//! Entry names follow conventions.md exactly:
//! `tvNNN_pvNNN/IIIII tlNNN plNNN tvNNN pvNNN.jpg` — integer degrees, three digits,
//! light angles first, `IIIII` a 5-digit running index (0-based, in export order).
//! The public `btf-extractor` reader takes the four angles from fixed offsets counted
//! from the end of the name and keys images by them, so two exported measurements
//! must never round to the same four integers (that is an error here, not a silently
//! overwritten image).
//!
//! What is exported: every record that is not `Skipped` (a dataset never claims what
//! it did not measure), in canonical-index order, substituted ones under the light
//! angles actually used. Angles are rounded to the nearest degree, φ wrapped into
//! [0, 360), and φ set to 0 when θ rounds to 0 (the pole has no azimuth).
//!
//! Pixel values: linear → clamped to [0, 1] → sRGB transfer function → rounded to 8
//! bits ([`linear_to_srgb8`]), then JPEG at quality [`JPEG_QUALITY`] without chroma
//! subsampling (the `image` crate's encoder always writes 4:4:4). The `.npy` export
//! (see `npy.rs`) holds exactly the 8-bit values given to the JPEG encoder, so a
//! reader's output can be compared against it.

use super::atomic::TempFile;
use super::error::{IoContext, StoreError};
use super::exr_io::decode_exr;
use super::manifest::{ManifestHeader, MeasurementRecord, MeasurementStatus};
use super::{load, sha256_hex};
use gonio_devices::image::RgbImage;
use rayon::prelude::*;
use std::collections::HashMap;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// JPEG quality of exported images (libjpeg scale, 1–100).
pub const JPEG_QUALITY: u8 = 95;

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
    /// "isotropic"; `image` is the representative's): see `export_iso`.
    pub transform: Option<super::export_iso::IsoTransform>,
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

/// Choose and name the exported records: not skipped, sorted by canonical index.
/// Returns the entries and the number of skipped records.
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
    // isotropic acquisitions: add the reconstructed pairs (no-op for other datasets)
    let skipped = skipped + super::export_iso::extend(dir, records, &mut entries, out)?;
    Ok((entries, skipped))
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

/// JPEG-encode interleaved 8-bit sRGB at [`JPEG_QUALITY`].
pub fn encode_jpeg(rgb: &[u8], width: usize, height: usize, path: &Path) -> Result<Vec<u8>, StoreError> {
    use image::ImageEncoder;
    let mut out = Vec::with_capacity(rgb.len() / 4);
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, JPEG_QUALITY)
        .write_image(rgb, width as u32, height as u32, image::ExtendedColorType::Rgb8)
        .map_err(|source| StoreError::Codec {
            path: path.to_path_buf(),
            source,
        })?;
    Ok(out)
}

/// Read, hash-check and decode an exported entry's image and return its 8-bit sRGB.
pub(crate) fn load_srgb8(dir: &Path, header: &ManifestHeader, e: &ExportEntry) -> Result<Vec<u8>, StoreError> {
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
    let img = match &e.transform {
        Some(t) => t.apply(&img),
        None => img,
    };
    Ok(to_srgb8(&img))
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

/// Export a dataset as a UBO2003 ZIP archive (see the module documentation). The
/// archive is written under a temporary name and renamed into place when complete.
pub fn export_ubo2003(dir: &Path, out_zip: &Path) -> Result<ExportReport, StoreError> {
    let (header, records) = load(dir)?;
    let (entries, skipped) = plan_export(dir, &records, out_zip)?;
    ensure_parent(out_zip)?;
    let zip_err = |source| StoreError::Zip {
        path: out_zip.to_path_buf(),
        source,
    };
    let mut tmp = TempFile::create(out_zip, None)?;
    let tmp_path = tmp.tmp_path().to_path_buf();
    {
        let mut zip = zip::ZipWriter::new(BufWriter::new(tmp.file()));
        // JPEG data does not deflate; storing keeps the archive fast to read.
        let options = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored)
            .large_file(false);
        let (w, h) = (header.image_width, header.image_height);
        for_each_in_order(
            &entries,
            |e| {
                let rgb = load_srgb8(dir, &header, e)?;
                encode_jpeg(&rgb, w, h, out_zip)
            },
            |e, jpeg| {
                zip.start_file(e.name.as_str(), options).map_err(zip_err)?;
                zip.write_all(&jpeg).ctx("writing", &tmp_path, None)
            },
        )?;
        let mut inner = zip.finish().map_err(zip_err)?;
        inner.flush().ctx("writing", &tmp_path, None)?;
    }
    tmp.commit()?;
    let bytes = std::fs::metadata(out_zip).ctx("reading", out_zip, None)?.len();
    Ok(ExportReport {
        path: out_zip.to_path_buf(),
        entries: entries.len(),
        substituted: entries.iter().filter(|e| e.status == "substituted").count(),
        skipped,
        bytes,
        sidecar: None,
    })
}
