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

use super::entry::{ensure_parent, for_each_in_order, load_srgb8, ExportReport};
use crate::store::atomic::TempFile;
use crate::store::error::{IoContext, StoreError};
use crate::store::load;
use std::io::{BufWriter, Write};
use std::path::Path;

/// JPEG quality of exported images (libjpeg scale, 1–100).
pub const JPEG_QUALITY: u8 = 95;

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

/// Export a dataset as a UBO2003 ZIP archive (see the module documentation). The
/// archive is written under a temporary name and renamed into place when complete.
pub fn export_ubo2003(dir: &Path, out_zip: &Path) -> Result<ExportReport, StoreError> {
    let (header, records) = load(dir)?;
    let (entries, skipped) = super::entries(dir, &records, out_zip)?;
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
