//! Zarr v3 export (cargo feature `zarr`): the whole BTF as one chunked array for the
//! array world (zarr-python, xarray, dask, tensorstore), written with the `zarrs` crate.
//!
//! # Layout (`OUT.zarr/`)
//!
//! ```text
//! zarr.json          group; attributes "gonio": dataset, units, calibration ids, plan hash, …
//! btf/               float16 [view, light, y, x, channel]; fill value NaN
//!   zarr.json          shard = one view [1, L, H, W, 3], inner chunk = one image
//!                      [1, 1, H, W, 3], zstd per image, crc32c shard index
//!   c/V/0/0/0/0        the shard of view V (absent when no pair of the view was measured)
//! status/            uint8 [view, light]: 0 missing, 1 measured, 2 substituted, 3 isotropic
//! view_theta/ view_phi/    float64 [view], degrees (conventions.md: θ from +z, φ from +x
//! light_theta/ light_phi/  float64 [light]   toward +y), the sweep's planned directions
//! ```
//!
//! * **Values** are the dataset's stored linear values (the EXRs are half floats, so the
//!   conversion is exact for measured pairs); an isotropic equivalent is its
//!   representative's image transformed as in `iso.rs`, then rounded to f16.
//! * **Missing pairs** (skipped, or not yet measured in an incomplete dataset or a shard
//!   part) are NaN, the fill value, and 0 in `status`: a NaN is never a measured zero,
//!   and `status` is authoritative (a measured image could in principle hold a NaN).
//!   A substituted pair holds the image measured with the light direction listed in the
//!   group's `gonio.substituted` (the coordinate arrays hold the planned one).
//! * **Coordinates**: `btf`'s attribute `coordinates` names the direction arrays and
//!   `status`, so xarray attaches them to the `view` and `light` dimensions.
//!
//! # Shards
//!
//! `--shard I/N` writes only the shards of its views ([`Shard::views`]), plus the metadata
//! and coordinate arrays, which every part computes from the whole dataset and writes as
//! the same bytes. Every file is encoded in memory by zarrs and written atomically
//! (temporary name, fsync, rename), so N processes fill one store with no lock: no two
//! write different bytes under one name, and a reader never sees half a file. The result
//! equals the single-process export byte for byte (`tests/it/zarr_export.rs`).

use super::entry::{load_linear, ExportEntry};
use crate::shard::{Shard, ShardInfo};
use crate::store::atomic::write_atomic;
use crate::store::error::{IoContext, StoreError};
use crate::store::manifest::{read_manifest, ManifestHeader};
use crate::store::{load, sha256_hex, PLAN_FILE};
use half::f16;
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use zarrs::array::{codec, data_type, ArrayBuilder};
use zarrs::storage::store::MemoryStore;
use zarrs::storage::{ListableStorageTraits, ReadableStorageTraits, StoreKey};

/// Name of the image array inside the store.
pub const BTF_ARRAY: &str = "btf";
/// Name of the per-pair status array (the mask of missing pairs).
pub const STATUS_ARRAY: &str = "status";
/// `dimension_names` of [`BTF_ARRAY`].
pub const DIMENSIONS: [&str; 5] = ["view", "light", "y", "x", "channel"];
/// `status` codes.
pub const STATUS_MISSING: u8 = 0;
pub const STATUS_MEASURED: u8 = 1;
pub const STATUS_SUBSTITUTED: u8 = 2;
pub const STATUS_ISOTROPIC: u8 = 3;
/// zstd level of every image: 3 is zstd's default (fast; higher levels gained little on
/// noisy half floats).
pub const ZSTD_LEVEL: i32 = 3;
/// Images decoded in parallel at a time inside one view (bounds memory for wide views).
const BATCH: usize = 32;

/// How to export.
#[derive(Clone, Copy, Debug, Default)]
pub struct ZarrOptions {
    /// Write only this shard's views (plus the shared metadata).
    pub shard: Option<Shard>,
    /// Replace an existing Zarr store at the output path (not with `shard`).
    pub force: bool,
    /// Compute the mean image over every exported pair (not with `shard`).
    pub mean: bool,
}

/// The mean over all exported (view, light) pairs of the stored f16 values, per texel and
/// channel, with missing pairs left out (NaN-mean). Sums are f64 in (view, light) order;
/// a sum of f16 values is exact in f64 up to 2^13 images (f16 spans 2^40 with 11 bits),
/// so any reader that sums the same values in f64 in any order gets the same bits.
#[derive(Clone, Debug, PartialEq)]
pub struct MeanImage {
    pub width: usize,
    pub height: usize,
    /// `[y][x][channel]`, row-major; NaN where no pair was exported.
    pub values: Vec<f64>,
    /// Pairs that went into the mean.
    pub images: usize,
}

/// What a Zarr export wrote.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ZarrReport {
    pub path: PathBuf,
    /// `[view, light, y, x, channel]`.
    pub shape: [usize; 5],
    pub shard_shape: [usize; 5],
    pub chunk_shape: [usize; 5],
    /// The part this process wrote, if sharded.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shard: Option<ShardInfo>,
    /// Views whose shards this process wrote: `[first, end)`.
    pub views_written: [usize; 2],
    /// Images (pairs with data) in those views.
    pub images_written: usize,
    /// Pairs of the whole array with data, by status.
    pub measured: usize,
    pub substituted: usize,
    pub isotropic: usize,
    /// Pairs of the whole array without data (NaN, `status` 0).
    pub missing: usize,
    /// Files this process wrote and their total size.
    pub files_written: usize,
    pub bytes_written: u64,
}

/// The store's geometry and per-pair bookkeeping, computed from the whole dataset by every
/// part alike.
struct Layout {
    views: Vec<[f64; 2]>,
    lights: Vec<[f64; 2]>,
    width: usize,
    height: usize,
    /// Entries per view, sorted by light.
    by_view: Vec<Vec<(usize, ExportEntry)>>,
    status: Vec<u8>,
}

fn zerr(out: &Path, e: impl std::fmt::Display) -> StoreError {
    StoreError::Zarr {
        path: out.to_path_buf(),
        reason: e.to_string(),
    }
}

/// `[θ, φ]` list `key` of the manifest's sweep.
fn sweep_dirs(header: &ManifestHeader, key: &str, dir: &Path, out: &Path) -> Result<Vec<[f64; 2]>, StoreError> {
    let list = header.sweep.get(key).cloned().unwrap_or(serde_json::Value::Null);
    let dirs: Vec<[f64; 2]> = serde_json::from_value(list).map_err(|_| {
        zerr(
            out,
            format!(
                "the manifest of {} has no sweep.{key} list of [θ, φ] degrees, so the \
                 [view, light] grid is unknown (datasets written by gonio acquire, sim btf \
                 and import have it)",
                dir.display()
            ),
        )
    })?;
    if dirs.is_empty() {
        return Err(zerr(out, format!("the sweep of {} has no {key}", dir.display())));
    }
    Ok(dirs)
}

fn layout(dir: &Path, header: &ManifestHeader, entries: Vec<ExportEntry>, out: &Path) -> Result<Layout, StoreError> {
    let views = sweep_dirs(header, "views_deg", dir, out)?;
    let lights = sweep_dirs(header, "lights_deg", dir, out)?;
    let (nv, nl) = (views.len(), lights.len());
    let mut by_view: Vec<Vec<(usize, ExportEntry)>> = vec![Vec::new(); nv];
    let mut status = vec![STATUS_MISSING; nv * nl];
    for e in entries {
        if e.index >= nv * nl {
            return Err(zerr(
                out,
                format!(
                    "measurement {} of {} is outside its sweep's {nv} views × {nl} lights",
                    e.index,
                    dir.display()
                ),
            ));
        }
        status[e.index] = match (e.transform.is_some(), e.status) {
            (true, _) => STATUS_ISOTROPIC,
            (false, "substituted") => STATUS_SUBSTITUTED,
            _ => STATUS_MEASURED,
        };
        by_view[e.index / nl].push((e.index % nl, e));
    }
    for v in &mut by_view {
        v.sort_by_key(|(l, _)| *l);
    }
    Ok(Layout {
        views,
        lights,
        width: header.image_width,
        height: header.image_height,
        by_view,
        status,
    })
}

/// The group's `gonio` attribute: what the data are, where they came from.
fn group_attributes(
    dir: &Path,
    out: &Path,
    header: &ManifestHeader,
    lay: &Layout,
) -> Result<serde_json::Value, StoreError> {
    let complete = read_manifest(dir)?.complete;
    // The dataset as seen from the store's directory, and its SHA-256 (same bytes wherever
    // the files sit; `crate::store::provenance`).
    let input = crate::store::provenance::InputRef::new(dir, out).map_err(|e| match e {
        crate::store::provenance::ProvenanceError::Read { path, source } => StoreError::Io {
            op: "hashing",
            path,
            source,
        },
        crate::store::provenance::ProvenanceError::Dataset { source, .. } => *source,
        e @ crate::store::provenance::ProvenanceError::NotADataset { .. } => StoreError::Io {
            op: "hashing",
            path: dir.to_path_buf(),
            source: std::io::Error::other(e.to_string()),
        },
    })?;
    let plan_path = dir.join(PLAN_FILE);
    let plan = match std::fs::read(&plan_path) {
        Ok(bytes) => serde_json::json!({ "path": PLAN_FILE, "sha256": sha256_hex(&bytes) }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => serde_json::Value::Null,
        Err(e) => return Err(StoreError::io("reading", &plan_path, Some(dir), e)),
    };
    let count = |s: u8| lay.status.iter().filter(|&&x| x == s).count();
    let substituted: Vec<serde_json::Value> = lay
        .by_view
        .iter()
        .enumerate()
        .flat_map(|(v, es)| {
            es.iter()
                .filter(|(_, e)| e.status == "substituted" && e.transform.is_none())
                .map(move |(l, e)| serde_json::json!({ "view": v, "light": l, "light_deg_used": e.light_deg }))
        })
        .collect();
    let extra = |k: &str| header.extra.get(k).cloned().unwrap_or(serde_json::Value::Null);
    Ok(serde_json::json!({
        "format": "gonio-zarr",
        "version": 1,
        "gonio_version": env!("CARGO_PKG_VERSION"),
        "dataset": input.path,
        "dataset_sha256": input.sha256,
        "dataset_complete": complete,
        "values": header.values,
        "value_unit": extra("value_unit"),
        "calibration": header.calibration,
        "calibrations": extra("calibrations"),
        "plan": plan,
        "sample": header.sample.get("name").cloned().unwrap_or(serde_json::Value::Null),
        "sweep": header.sweep.get("name").cloned().unwrap_or(serde_json::Value::Null),
        "rig": header.rig.get("name").cloned().unwrap_or(serde_json::Value::Null),
        "seed": header.seed,
        "angles": "degrees; θ polar angle from +z, φ azimuth from +x toward +y (gonio conventions)",
        "image_rows": "row 0 at the top of the rectified image (+y up), channels R, G, B",
        "status_codes": {
            "0": "missing: not measured (skipped pair or incomplete dataset); btf holds NaN",
            "1": "measured at the planned directions",
            "2": "measured with a substituted light direction (see substituted)",
            "3": "isotropic equivalent: the representative's image transformed (plan.json)",
        },
        "pairs": lay.status.len(),
        "measured": count(STATUS_MEASURED),
        "substituted_pairs": count(STATUS_SUBSTITUTED),
        "isotropic": count(STATUS_ISOTROPIC),
        "missing": count(STATUS_MISSING),
        "substituted": substituted,
    }))
}

fn attrs(v: serde_json::Value) -> serde_json::Map<String, serde_json::Value> {
    match v {
        serde_json::Value::Object(m) => m,
        _ => serde_json::Map::new(),
    }
}

/// Refuse an output that is something else; with `force`, clear a Zarr store.
fn prepare_output(out: &Path, opts: &ZarrOptions, group_json: &[u8]) -> Result<(), StoreError> {
    let exists = |reason: &str| StoreError::ZarrOutputExists {
        path: out.to_path_buf(),
        reason: reason.into(),
    };
    if !out.exists() {
        return Ok(());
    }
    if !out.is_dir() {
        return Err(exists("is not a directory"));
    }
    let empty = std::fs::read_dir(out).ctx("reading", out, None)?.next().is_none();
    if empty {
        return Ok(());
    }
    let root = out.join("zarr.json");
    if opts.shard.is_some() {
        // Another part of the same export (or an earlier run of this part) may be there:
        // fine exactly when it describes the same store.
        return match std::fs::read(&root) {
            Ok(b) if b == group_json => Ok(()),
            Ok(_) => Err(exists(
                "holds a different Zarr export (its zarr.json differs: another dataset, \
                 dataset path or gonio version)",
            )),
            // Not renamed into place yet by a part running now: fine if everything there
            // is a name this export writes (or a part's temporary file).
            Err(_) if only_export_names(out)? => Ok(()),
            Err(_) => Err(exists("is not empty and holds no zarr.json")),
        };
    }
    if !opts.force {
        return Err(exists("is not empty"));
    }
    if !root.is_file() {
        return Err(exists(
            "is not a Zarr store (no zarr.json), so --force does not remove it",
        ));
    }
    std::fs::remove_dir_all(out).ctx("removing", out, None)
}

/// Whether every entry of `out` is one a Zarr export writes (or a temporary file).
fn only_export_names(out: &Path) -> Result<bool, StoreError> {
    const NAMES: [&str; 7] = [
        "zarr.json",
        BTF_ARRAY,
        STATUS_ARRAY,
        "view_theta",
        "view_phi",
        "light_theta",
        "light_phi",
    ];
    for e in std::fs::read_dir(out).ctx("reading", out, None)? {
        let name = e.ctx("reading", out, None)?.file_name();
        let name = name.to_string_lossy();
        if !NAMES.contains(&name.as_ref()) && !name.starts_with(crate::store::atomic::TMP_PREFIX) {
            return Ok(false);
        }
    }
    Ok(true)
}

/// Move every key of `mem` to `out` (atomic writes), emptying `mem`.
fn flush(mem: &MemoryStore, out: &Path, files: &mut usize, bytes: &mut u64) -> Result<(), StoreError> {
    let keys = mem.list().map_err(|e| zerr(out, e))?;
    for key in keys {
        let data = mem
            .get(&key)
            .map_err(|e| zerr(out, e))?
            .ok_or_else(|| zerr(out, format!("key {} vanished", key.as_str())))?;
        let dest = out.join(key.as_str());
        if let Some(p) = dest.parent() {
            std::fs::create_dir_all(p).ctx("creating directory", p, None)?;
        }
        write_atomic(&dest, &data, None)?;
        *files += 1;
        *bytes += data.len() as u64;
        zarrs::storage::WritableStorageTraits::erase(mem, &key).map_err(|e| zerr(out, e))?;
    }
    Ok(())
}

/// Export dataset `dir` to the Zarr v3 store `out` (see the module documentation).
/// Returns the report and, with `opts.mean`, the mean image.
pub fn export_zarr(dir: &Path, out: &Path, opts: &ZarrOptions) -> Result<(ZarrReport, Option<MeanImage>), StoreError> {
    if opts.shard.is_some() && (opts.force || opts.mean) {
        return Err(zerr(
            out,
            "--shard writes one part of a shared store: it cannot --force (remove the store \
             first) nor compute the mean image (export without --shard, or compute it from \
             the finished store)",
        ));
    }
    let (header, records) = load(dir)?;
    let (entries, _) = super::entries(dir, &records, out)?;
    let lay = layout(dir, &header, entries, out)?;
    let (nv, nl, h, w) = (lay.views.len(), lay.lights.len(), lay.height, lay.width);
    let views = match opts.shard {
        Some(s) => {
            s.check_views(nv).map_err(|e| zerr(out, e))?;
            s.views(nv)
        }
        None => 0..nv,
    };

    let mem = Arc::new(MemoryStore::new());
    let u = |x: usize| x as u64;
    let zarr = |e: &dyn std::fmt::Display| zerr(out, e);

    // Group and arrays (metadata and small arrays: identical in every part).
    let mut group = zarrs::group::GroupBuilder::new();
    group.attributes(attrs(
        serde_json::json!({ "gonio": group_attributes(dir, out, &header, &lay)? }),
    ));
    let group = group.build(mem.clone(), "/").map_err(|e| zarr(&e))?;
    group.store_metadata().map_err(|e| zarr(&e))?;
    let group_json = mem
        .get(&StoreKey::new("zarr.json").map_err(|e| zarr(&e))?)
        .map_err(|e| zarr(&e))?
        .map(|b| b.to_vec())
        .unwrap_or_default();
    prepare_output(out, opts, &group_json)?;

    let unit = header
        .extra
        .get("value_unit")
        .and_then(|v| v.as_str())
        .map(str::to_string)
        .unwrap_or_else(|| header.values.clone());
    let mut b = ArrayBuilder::new(
        vec![u(nv), u(nl), u(h), u(w), 3],
        vec![1, u(nl), u(h), u(w), 3],
        data_type::float16(),
        f16::NAN,
    );
    // Inner chunks in C order inside a shard: zarrs' default (`Unordered`) places them in
    // the order its threads finish, so the same shard would differ from run to run.
    let ordered = codec::ShardingCodecOptions::default().with_subchunk_write_order(codec::SubchunkWriteOrder::C);
    b.subchunk_shape(vec![1, 1, u(h), u(w), 3])
        .codec_specific_options(zarrs::array::CodecSpecificOptions::default().with_option(ordered))
        .bytes_to_bytes_codecs(vec![Arc::new(codec::ZstdCodec::new(ZSTD_LEVEL, false))])
        .dimension_names(Some(DIMENSIONS))
        .attributes(attrs(serde_json::json!({
            "long_name": "rectified BTF images (linear values)",
            "units": unit,
            "description": header.values,
            "coordinates": "view_theta view_phi light_theta light_phi status",
        })));
    let btf = b.build(mem.clone(), &format!("/{BTF_ARRAY}")).map_err(|e| zarr(&e))?;
    btf.store_metadata().map_err(|e| zarr(&e))?;

    let mut status = ArrayBuilder::new(
        vec![u(nv), u(nl)],
        vec![u(nv), u(nl)],
        data_type::uint8(),
        STATUS_MISSING,
    );
    status
        .dimension_names(Some(["view", "light"]))
        .attributes(attrs(serde_json::json!({
            "long_name": "pair status: 0 missing (NaN in btf), 1 measured, 2 substituted light, 3 isotropic equivalent",
            "flag_values": [0, 1, 2, 3],
            "flag_meanings": "missing measured substituted isotropic",
        })));
    let status = status
        .build(mem.clone(), &format!("/{STATUS_ARRAY}"))
        .map_err(|e| zarr(&e))?;
    status.store_metadata().map_err(|e| zarr(&e))?;
    status.store_chunk(&[0, 0], &lay.status[..]).map_err(|e| zarr(&e))?;

    for (name, dim, vals, what) in [
        (
            "view_theta",
            "view",
            lay.views.iter().map(|d| d[0]).collect::<Vec<f64>>(),
            "view polar angle θ_v",
        ),
        (
            "view_phi",
            "view",
            lay.views.iter().map(|d| d[1]).collect(),
            "view azimuth φ_v",
        ),
        (
            "light_theta",
            "light",
            lay.lights.iter().map(|d| d[0]).collect(),
            "light polar angle θ_l (planned)",
        ),
        (
            "light_phi",
            "light",
            lay.lights.iter().map(|d| d[1]).collect(),
            "light azimuth φ_l (planned)",
        ),
    ] {
        let mut c = ArrayBuilder::new(vec![u(vals.len())], vec![u(vals.len())], data_type::float64(), f64::NAN);
        c.dimension_names(Some([dim]))
            .attributes(attrs(serde_json::json!({ "long_name": what, "units": "degree" })));
        let c = c.build(mem.clone(), &format!("/{name}")).map_err(|e| zarr(&e))?;
        c.store_metadata().map_err(|e| zarr(&e))?;
        c.store_chunk(&[0], &vals[..]).map_err(|e| zarr(&e))?;
    }

    std::fs::create_dir_all(out).ctx("creating directory", out, None)?;
    let (mut files, mut bytes) = (0usize, 0u64);
    flush(&mem, out, &mut files, &mut bytes)?;

    // The shards: one view at a time.
    let image = h * w * 3;
    let mut mean = opts.mean.then(|| (vec![0f64; image], vec![0u32; image], 0usize));
    let mut images_written = 0;
    for v in views.clone() {
        let mut buf = vec![f16::NAN; nl * image];
        for batch in lay.by_view[v].chunks(BATCH) {
            let imgs: Vec<Result<_, StoreError>> =
                batch.par_iter().map(|(_, e)| load_linear(dir, &header, e)).collect();
            for ((l, _), img) in batch.iter().zip(imgs) {
                let img = img?;
                let dst = &mut buf[l * image..(l + 1) * image];
                for (d, s) in dst.iter_mut().zip(&img.data) {
                    *d = f16::from_f32(*s);
                }
                if let Some((sum, count, n)) = &mut mean {
                    for ((s, c), x) in sum.iter_mut().zip(count.iter_mut()).zip(dst.iter()) {
                        *s += f64::from(*x);
                        *c += 1;
                    }
                    *n += 1;
                }
                images_written += 1;
            }
        }
        btf.store_chunk(&[u(v), 0, 0, 0, 0], &buf[..]).map_err(|e| zarr(&e))?;
        let key = format!("{BTF_ARRAY}/c/{v}/0/0/0/0");
        if lay.by_view[v].is_empty() {
            // zarrs writes no shard for an all-missing view: remove a stale one.
            let stale = out.join(&key);
            if stale.exists() {
                std::fs::remove_file(&stale).ctx("removing", &stale, None)?;
            }
        }
        flush(&mem, out, &mut files, &mut bytes)?;
        tracing::debug!(view = v, key = %key, "zarr shard written");
    }

    let count = |s: u8| lay.status.iter().filter(|&&x| x == s).count();
    let report = ZarrReport {
        path: out.to_path_buf(),
        shape: [nv, nl, h, w, 3],
        shard_shape: [1, nl, h, w, 3],
        chunk_shape: [1, 1, h, w, 3],
        shard: opts.shard.map(|s| s.info(nv)),
        views_written: [views.start, views.end],
        images_written,
        measured: count(STATUS_MEASURED),
        substituted: count(STATUS_SUBSTITUTED),
        isotropic: count(STATUS_ISOTROPIC),
        missing: count(STATUS_MISSING),
        files_written: files,
        bytes_written: bytes,
    };
    let mean = mean.map(|(sum, count, n)| MeanImage {
        width: w,
        height: h,
        values: sum
            .iter()
            .zip(&count)
            .map(|(s, &c)| if c == 0 { f64::NAN } else { s / f64::from(c) })
            .collect(),
        images: n,
    });
    Ok((report, mean))
}

/// Write a mean image as a NumPy float64 array `[height, width, 3]`, atomically.
pub fn write_mean_npy(mean: &MeanImage, path: &Path) -> Result<(), StoreError> {
    let mut bytes = super::npy::npy_header_typed("<f8", &[mean.height, mean.width, 3]);
    for v in &mean.values {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    super::entry::ensure_parent(path)?;
    write_atomic(path, &bytes, None)
}
