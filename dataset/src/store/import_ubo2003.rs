//! Import of a Bonn UBO2003 archive (a ZIP of 8-bit sRGB images) into a native dataset.
//!
//! Why: real BTFs from the field (Bonn's UBO2003 set, or any tool that writes its
//! layout, gonio's own export included) should go through the same compression,
//! verification and export paths as gonio's own acquisitions.
//!
//! What is read: every file entry whose last path component carries the four angles
//! `tlNNN plNNN tvNNN pvNNN` (integer degrees, light first, as in conventions.md and
//! [`super::export::entry_name`]); directories and other files (readme, thumbnails) are
//! listed in the report as ignored. The light and view direction sets are the distinct
//! angles found; if they are exactly the Bonn 81 set they keep the Bonn order, otherwise
//! they are sorted by (θ, φ). Measurement `index = view · lights + light`, the layout
//! `gonio compress` expects; grid pairs absent from the archive are recorded as skipped
//! ("not in the archive"), never invented.
//!
//! Pixel values: sRGB 8-bit → linear f32 in [0, 1] (the inverse of the export's
//! transfer function), so `import` followed by `export --format ubo2003` reproduces the
//! 8-bit values up to the JPEG re-encoding.
//!
//! Outside input is hostile until checked: the archive may be truncated, its names
//! garbled, its entries zip bombs or images with absurd dimensions. Every such case is an
//! [`ImportError`] naming the archive and the entry; limits ([`ImportLimits`]) bound the
//! number of entries, the bytes read per entry and the pixels per image, so no input can
//! make the import allocate without bound. The import is resumable: images are stored
//! one by one through [`Dataset::store`] (durable before journalled), and `resume = true`
//! continues an interrupted import where it stopped.

use super::manifest::{ManifestHeader, MeasurementRecord, MeasurementStatus};
use super::{Dataset, StoreError};
use gonio_devices::image::{srgb8_to_linear, RgbImage};
use rayon::prelude::*;
use std::collections::{BTreeMap, HashSet};
use std::io::Read;
use std::path::{Path, PathBuf};

/// Images decoded in parallel per batch (bounds memory: a batch of 256² images is a few MiB).
const BATCH: usize = 16;

/// Bounds on what an archive may ask for.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImportLimits {
    /// Most image entries accepted (the Bonn set has 6561).
    pub max_entries: usize,
    /// Most bytes read from one entry after decompression.
    pub max_entry_bytes: u64,
    /// Largest accepted image edge, in pixels.
    pub max_edge: u32,
}

impl Default for ImportLimits {
    fn default() -> Self {
        ImportLimits {
            max_entries: 200_000,
            max_entry_bytes: 64 << 20,
            max_edge: 16_384,
        }
    }
}

/// Errors of [`import_ubo2003`]; each names the archive and, where there is one, the entry.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{}: cannot read the archive: {reason}", archive.display())]
    Archive { archive: PathBuf, reason: String },
    #[error("{}: entry {entry:?}: {reason}", archive.display())]
    Entry {
        archive: PathBuf,
        entry: String,
        reason: String,
    },
    #[error(
        "{}: entries {first:?} and {second:?} both hold light {light:?}°, view {view:?}°; \
         remove one of them",
        archive.display()
    )]
    Duplicate {
        archive: PathBuf,
        first: String,
        second: String,
        light: [u32; 2],
        view: [u32; 2],
    },
    #[error(
        "{}: no image entry carries the angles `tlNNN plNNN tvNNN pvNNN` in its name \
         ({ignored} other entries); is this a UBO2003 archive?",
        archive.display()
    )]
    Empty { archive: PathBuf, ignored: usize },
    #[error(
        "{}: {count} image entries exceed the limit of {limit}",
        archive.display()
    )]
    TooMany {
        archive: PathBuf,
        count: usize,
        limit: usize,
    },
    #[error(
        "{}: the dataset {} was imported from another archive or with other images \
         ({reason}); import into a new directory or pass --force",
        archive.display(), out.display()
    )]
    ResumeMismatch {
        archive: PathBuf,
        out: PathBuf,
        reason: String,
    },
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// What an import did.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ImportReport {
    pub archive: PathBuf,
    pub out: PathBuf,
    pub lights: usize,
    pub views: usize,
    pub width: usize,
    pub height: usize,
    /// Images stored by this run.
    pub imported: usize,
    /// Images already stored by an earlier, interrupted run (with `resume`).
    pub already_present: usize,
    /// Grid pairs absent from the archive (recorded as skipped).
    pub missing_pairs: usize,
    /// Entries that carry no angles (directories excluded), e.g. a readme.
    pub ignored_entries: Vec<String>,
    /// Whether the directions are exactly the Bonn 81 set (kept in Bonn order).
    pub bonn81: bool,
}

/// One image entry of the archive, from its name.
#[derive(Clone, Debug)]
struct Entry {
    zip_index: usize,
    name: String,
    light: [u32; 2],
    view: [u32; 2],
}

/// The four integer angles `tl pl tv pv` from an entry's file name, or `None` when the
/// name does not carry them. The last occurrence of each tag counts (directory names
/// such as `tv000_pv000/` repeat the view angles).
pub fn parse_entry_angles(name: &str) -> Option<([u32; 2], [u32; 2])> {
    let file = name.rsplit('/').next().unwrap_or(name);
    let lower = file.to_ascii_lowercase();
    if !(lower.ends_with(".jpg") || lower.ends_with(".jpeg") || lower.ends_with(".png")) {
        return None;
    }
    let tag = |t: &str| -> Option<u32> {
        let at = lower.rfind(t)? + t.len();
        let digits: String = lower[at..].chars().take_while(|c| c.is_ascii_digit()).collect();
        if digits.is_empty() || digits.len() > 3 {
            return None;
        }
        digits.parse().ok()
    };
    Some(([tag("tl")?, tag("pl")?], [tag("tv")?, tag("pv")?]))
}

/// Check one direction's integer angles: θ ∈ [0, 90], φ ∈ [0, 360).
fn check_angles(d: [u32; 2]) -> Result<(), String> {
    if d[0] > 90 {
        return Err(format!("θ = {}° is beyond the horizon (must be 0–90)", d[0]));
    }
    if d[1] >= 360 {
        return Err(format!("φ = {}° must be below 360", d[1]));
    }
    Ok(())
}

/// The Bonn 81 direction set as integer (θ, φ), in Bonn order.
fn bonn81_integer() -> Vec<[u32; 2]> {
    crate::sweep::bonn81()
        .iter()
        .map(|d| super::integer_angles([d.theta_deg(), d.phi_deg()]))
        .collect()
}

/// Order a direction set: Bonn order when it is exactly the Bonn set, else by (θ, φ).
fn order_directions(set: &HashSet<[u32; 2]>) -> (Vec<[u32; 2]>, bool) {
    let bonn = bonn81_integer();
    if set.len() == bonn.len() && bonn.iter().all(|d| set.contains(d)) {
        return (bonn, true);
    }
    let mut v: Vec<[u32; 2]> = set.iter().copied().collect();
    v.sort();
    (v, false)
}

/// Decode one image entry's bytes with the limits applied.
fn decode(bytes: &[u8], limits: &ImportLimits) -> Result<RgbImage, String> {
    let mut reader = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(|e| format!("cannot read the image header: {e}"))?;
    let mut l = image::Limits::default();
    l.max_image_width = Some(limits.max_edge);
    l.max_image_height = Some(limits.max_edge);
    l.max_alloc = Some(limits.max_entry_bytes.saturating_mul(8));
    reader.limits(l);
    let img = reader.decode().map_err(|e| format!("cannot decode the image: {e}"))?;
    let rgb = img.to_rgb8();
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    if w == 0 || h == 0 {
        return Err("the image is empty (0 pixels)".into());
    }
    let lut: Vec<f32> = (0..=255u8).map(srgb8_to_linear).collect();
    let data = rgb.as_raw().iter().map(|&v| lut[v as usize]).collect();
    Ok(RgbImage {
        width: w,
        height: h,
        data,
    })
}

/// Read the archive's central directory: the image entries and the ignored names.
fn list_entries(
    archive_path: &Path,
    zip: &mut zip::ZipArchive<std::fs::File>,
    limits: &ImportLimits,
) -> Result<(Vec<Entry>, Vec<String>), ImportError> {
    let mut entries = Vec::new();
    let mut ignored = Vec::new();
    let mut seen: BTreeMap<([u32; 2], [u32; 2]), String> = BTreeMap::new();
    for i in 0..zip.len() {
        let f = zip.by_index_raw(i).map_err(|e| ImportError::Archive {
            archive: archive_path.to_path_buf(),
            reason: format!("entry #{i}: {e}"),
        })?;
        let name = f.name().to_string();
        if f.is_dir() {
            continue;
        }
        let Some((light, view)) = parse_entry_angles(&name) else {
            if ignored.len() < 1000 {
                ignored.push(name);
            }
            continue;
        };
        let entry_err = |reason: String| ImportError::Entry {
            archive: archive_path.to_path_buf(),
            entry: name.clone(),
            reason,
        };
        check_angles(light).map_err(|r| entry_err(format!("light {r}")))?;
        check_angles(view).map_err(|r| entry_err(format!("view {r}")))?;
        // The pole has no azimuth: θ = 0 with any φ is the same direction.
        let norm = |d: [u32; 2]| if d[0] == 0 { [0, 0] } else { d };
        let (light, view) = (norm(light), norm(view));
        if let Some(first) = seen.insert((light, view), name.clone()) {
            return Err(ImportError::Duplicate {
                archive: archive_path.to_path_buf(),
                first,
                second: name,
                light,
                view,
            });
        }
        entries.push(Entry {
            zip_index: i,
            name,
            light,
            view,
        });
        if entries.len() > limits.max_entries {
            return Err(ImportError::TooMany {
                archive: archive_path.to_path_buf(),
                count: entries.len(),
                limit: limits.max_entries,
            });
        }
    }
    if entries.is_empty() {
        return Err(ImportError::Empty {
            archive: archive_path.to_path_buf(),
            ignored: ignored.len(),
        });
    }
    Ok((entries, ignored))
}

/// Read one entry's bytes, at most `limits.max_entry_bytes`.
fn read_entry(
    archive_path: &Path,
    zip: &mut zip::ZipArchive<std::fs::File>,
    e: &Entry,
    limits: &ImportLimits,
) -> Result<Vec<u8>, ImportError> {
    let err = |reason: String| ImportError::Entry {
        archive: archive_path.to_path_buf(),
        entry: e.name.clone(),
        reason,
    };
    let f = zip.by_index(e.zip_index).map_err(|x| err(x.to_string()))?;
    if f.size() > limits.max_entry_bytes {
        return Err(err(format!(
            "declares {} bytes uncompressed, more than the limit of {}",
            f.size(),
            limits.max_entry_bytes
        )));
    }
    let mut bytes = Vec::with_capacity(f.size().min(limits.max_entry_bytes) as usize);
    f.take(limits.max_entry_bytes + 1)
        .read_to_end(&mut bytes)
        .map_err(|x| err(format!("cannot decompress: {x}")))?;
    if bytes.len() as u64 > limits.max_entry_bytes {
        return Err(err(format!(
            "decompresses to more than the limit of {} bytes",
            limits.max_entry_bytes
        )));
    }
    Ok(bytes)
}

/// Import the UBO2003 archive at `archive` into a new native dataset at `out`.
///
/// `force` replaces an existing gonio dataset at `out` (as `acquire --force`); `resume`
/// continues an import into `out` that was interrupted (same archive).
pub fn import_ubo2003(
    archive: &Path,
    out: &Path,
    force: bool,
    resume: bool,
    limits: &ImportLimits,
    mut progress: impl FnMut(usize, usize),
) -> Result<ImportReport, ImportError> {
    let file = std::fs::File::open(archive).map_err(|e| ImportError::Archive {
        archive: archive.to_path_buf(),
        reason: e.to_string(),
    })?;
    let mut zip = zip::ZipArchive::new(file).map_err(|e| ImportError::Archive {
        archive: archive.to_path_buf(),
        reason: format!("not a readable ZIP file: {e}"),
    })?;
    let (entries, ignored) = list_entries(archive, &mut zip, limits)?;

    let lights_set: HashSet<[u32; 2]> = entries.iter().map(|e| e.light).collect();
    let views_set: HashSet<[u32; 2]> = entries.iter().map(|e| e.view).collect();
    let (lights, lights_bonn) = order_directions(&lights_set);
    let (views, views_bonn) = order_directions(&views_set);
    let light_index: BTreeMap<[u32; 2], usize> = lights.iter().enumerate().map(|(i, d)| (*d, i)).collect();
    let view_index: BTreeMap<[u32; 2], usize> = views.iter().enumerate().map(|(i, d)| (*d, i)).collect();
    let index_of = |e: &Entry| view_index[&e.view] * lights.len() + light_index[&e.light];

    // The first entry fixes the image size; every other must match it.
    let first = &entries[0];
    let first_img = {
        let bytes = read_entry(archive, &mut zip, first, limits)?;
        decode(&bytes, limits).map_err(|reason| ImportError::Entry {
            archive: archive.to_path_buf(),
            entry: first.name.clone(),
            reason,
        })?
    };
    let (width, height) = (first_img.width, first_img.height);
    drop(first_img);

    let deg = |d: &[u32; 2]| [d[0] as f64, d[1] as f64];
    let sweep = serde_json::json!({
        "name": "ubo2003-import",
        "lights_deg": lights.iter().map(deg).collect::<Vec<_>>(),
        "views_deg": views.iter().map(deg).collect::<Vec<_>>(),
        "policy": "skip",
    });
    let archive_name = archive
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let (mut dataset, done): (Dataset, HashSet<usize>) = if resume {
        let (ds, header, records) = Dataset::resume(out)?;
        let mismatch = |reason: String| ImportError::ResumeMismatch {
            archive: archive.to_path_buf(),
            out: out.to_path_buf(),
            reason,
        };
        if header.sweep != sweep {
            return Err(mismatch("its direction sets differ".into()));
        }
        if (header.image_width, header.image_height) != (width, height) {
            return Err(mismatch(format!(
                "its images are {}×{}, the archive's {width}×{height}",
                header.image_width, header.image_height
            )));
        }
        let done = records.iter().map(|r| r.index).collect();
        (ds, done)
    } else {
        let mut header = ManifestHeader::new(
            serde_json::json!({ "name": "imported", "imported_from": "ubo2003" }),
            serde_json::json!({ "name": archive_name }),
            sweep,
            width,
            height,
            "linear sRGB from 8-bit images (UBO2003 import); radiometric scale of the source",
        );
        header.extra = serde_json::json!({ "import": { "format": "ubo2003", "archive": archive_name } });
        (Dataset::create(out, &header, force)?, HashSet::new())
    };

    let todo: Vec<&Entry> = entries.iter().filter(|e| !done.contains(&index_of(e))).collect();
    let total = entries.len();
    let mut imported = 0;
    for chunk in todo.chunks(BATCH) {
        let mut raw = Vec::with_capacity(chunk.len());
        for e in chunk {
            raw.push(read_entry(archive, &mut zip, e, limits)?);
        }
        let decoded: Vec<Result<RgbImage, String>> = raw.par_iter().map(|b| decode(b, limits)).collect();
        for (e, img) in chunk.iter().zip(decoded) {
            let entry_err = |reason: String| ImportError::Entry {
                archive: archive.to_path_buf(),
                entry: e.name.clone(),
                reason,
            };
            let img = img.map_err(entry_err)?;
            if (img.width, img.height) != (width, height) {
                return Err(entry_err(format!(
                    "is {}×{}, but the archive's first image {:?} is {width}×{height}",
                    img.width, img.height, first.name
                )));
            }
            let index = index_of(e);
            let mut rec = MeasurementRecord::new(index, index, deg(&e.light), deg(&e.view));
            rec.extra = serde_json::json!({ "source_entry": e.name });
            dataset.store(rec, Some(&img), None)?;
            imported += 1;
            progress(done.len() + imported, total);
        }
    }

    // Grid pairs the archive does not hold: recorded as skipped, never invented.
    let present: HashSet<usize> = entries.iter().map(index_of).collect();
    let mut missing = 0;
    for (v, view) in views.iter().enumerate() {
        for (l, light) in lights.iter().enumerate() {
            let index = v * lights.len() + l;
            if present.contains(&index) {
                continue;
            }
            missing += 1;
            if done.contains(&index) {
                continue;
            }
            let mut rec = MeasurementRecord::new(index, index, deg(light), deg(view));
            rec.status = MeasurementStatus::Skipped {
                reason: "not in the archive".into(),
            };
            dataset.store(rec, None, None)?;
        }
    }
    let report = ImportReport {
        archive: archive.to_path_buf(),
        out: out.to_path_buf(),
        lights: lights.len(),
        views: views.len(),
        width,
        height,
        imported,
        already_present: entries.len() - todo.len(),
        missing_pairs: missing,
        ignored_entries: ignored,
        bonn81: lights_bonn && views_bonn,
    };
    dataset.finish(&serde_json::to_value(&report).unwrap_or_default())?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entry_names_parse_like_the_public_reader() {
        assert_eq!(
            parse_entry_angles("tv015_pv060/00042 tl030 pl150 tv015 pv060.jpg"),
            Some(([30, 150], [15, 60]))
        );
        assert_eq!(
            parse_entry_angles("a/b/00000 tl000 pl000 tv075 pv345.JPG"),
            Some(([0, 0], [75, 345]))
        );
        assert_eq!(parse_entry_angles("readme.txt"), None);
        assert_eq!(parse_entry_angles("tv000_pv000/"), None);
        assert_eq!(parse_entry_angles("x tl1234 pl000 tv000 pv000.jpg"), None);
        assert_eq!(parse_entry_angles("x tl pl000 tv000 pv000.jpg"), None);
    }

    #[test]
    fn angles_outside_the_hemisphere_are_refused() {
        assert!(check_angles([91, 0]).is_err());
        assert!(check_angles([45, 360]).is_err());
        assert!(check_angles([90, 359]).is_ok());
    }

    #[test]
    fn srgb_round_trip_through_the_export_function() {
        for v in 0..=255u8 {
            assert_eq!(super::super::linear_to_srgb8(srgb8_to_linear(v)), v, "value {v}");
        }
    }
}
