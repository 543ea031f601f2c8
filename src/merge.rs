//! `gonio merge`: put the parts of a sharded job back together ([`gonio_dataset::shard`]).
//!
//! Two kinds of parts:
//! * **datasets** (`gonio sim btf --shard`): every record and image of every part, written
//!   through [`Dataset::store`] in the single-process order (shards in order, each in its
//!   journal order). Each image is decoded and stored again, and the hash of the stored
//!   file must equal the part's recorded `image_sha256`, so the merged dataset is proven
//!   byte-identical image by image. The manifest is the parts' manifest without
//!   `extra.shard`; its `created_unix` is the earliest part's.
//! * **`.gbtf` files** (`gonio compress --method pvmf --shard`): PVMF's blocks are per
//!   view, so the merged file is the parts' blocks and filled pairs concatenated in view
//!   order under the parts' common header (without `source.shard`): byte-identical to the
//!   single-process file.
//!
//! Every part must be a complete part of the same job: missing, duplicate, overlapping,
//! incomplete or mismatched parts are refused, naming the part and the field.

use gonio_btf::compress::rsvd_shard::{self, PartHeader};
use gonio_btf::compress::{Gbtf, GbtfHeader};
use gonio_dataset::shard::{self, first_difference, ShardError, ShardInfo};
use gonio_dataset::store::{self, provenance, Dataset, ManifestHeader, MeasurementRecord, StoreError};
use std::path::{Path, PathBuf};

/// Errors of a merge; each names the part (or output) concerned.
#[derive(Debug, thiserror::Error)]
pub enum MergeError {
    #[error(transparent)]
    Shard(#[from] ShardError),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(transparent)]
    Compress(#[from] gonio_btf::compress::CompressError),
    #[error("{path}: {reason}")]
    Part { path: PathBuf, reason: String },
    #[error(
        "missing part(s) {}: their shard did not write them (failed or not run); re-run those shards \
         and merge again",
        parts.join(", ")
    )]
    Absent { parts: Vec<String> },
    #[error("{path} exists; pass --force to replace it")]
    Exists { path: PathBuf },
    #[error(
        "{path}: measurement {index} stored as {stored} but the part recorded {recorded}: the merged image \
         would not be byte-identical"
    )]
    HashMismatch {
        path: PathBuf,
        index: usize,
        stored: String,
        recorded: String,
    },
}

/// What a merge did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct MergeReport {
    /// `dataset`, `gbtf`; for `.gpart` parts `state`, `gbtf`, `btf`, or `part` (a
    /// partial merge).
    pub kind: &'static str,
    pub parts: usize,
    pub shards: usize,
    pub views: usize,
    /// Records (dataset), factor blocks (gbtf) or parts (a randomized-SVD pass) written.
    pub items: usize,
    /// A randomized-SVD pass (`.gpart` parts): which pass of how many; `kind` is `state`
    /// before the last pass (the next round's `--state`), `gbtf` or `btf` after it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pass: Option<[usize; 2]>,
    pub out: PathBuf,
}

/// Merge `parts` into `out` (a dataset directory or a `.gbtf` file, by the parts' kind).
pub fn merge(parts: &[PathBuf], out: &Path, force: bool) -> Result<MergeReport, MergeError> {
    let first = parts.first().ok_or(ShardError::NoParts)?;
    let absent: Vec<String> = parts
        .iter()
        .filter(|p| !p.exists())
        .map(|p| p.display().to_string())
        .collect();
    if !absent.is_empty() {
        return Err(MergeError::Absent { parts: absent });
    }
    // `--out` naming one of the parts would delete that part (--force) before it is read.
    if let Ok(o) = out.canonicalize() {
        if let Some(p) = parts.iter().find(|p| p.canonicalize().is_ok_and(|c| c == o)) {
            return Err(part_err(
                p,
                "is also the --out of the merge; write the merged result elsewhere",
            ));
        }
    }
    if first.is_dir() {
        merge_datasets(parts, out, force)
    } else if rsvd_shard::is_part_file(first) {
        merge_rsvd(parts, out, force)
    } else {
        merge_gbtf(parts, out, force)
    }
}

fn part_err(path: &Path, reason: impl Into<String>) -> MergeError {
    MergeError::Part {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

fn not_a_part(path: &Path, reason: impl Into<String>) -> MergeError {
    MergeError::Shard(ShardError::NotAPart {
        path: path.to_path_buf(),
        reason: reason.into(),
    })
}

fn shard_of(path: &Path, v: Option<&serde_json::Value>, where_: &str) -> Result<ShardInfo, MergeError> {
    let v = v.ok_or_else(|| not_a_part(path, format!("it has no {where_}")))?;
    serde_json::from_value(v.clone()).map_err(|e| not_a_part(path, format!("{where_} does not parse: {e}")))
}

/// Check that every part agrees with the first on `normalised` (a JSON value of what
/// must be equal), naming the first field that differs.
fn check_same(parts: &[PathBuf], normalised: &[serde_json::Value]) -> Result<(), MergeError> {
    for (p, v) in parts.iter().zip(normalised).skip(1) {
        if let Some((field, detail)) = first_difference(&normalised[0], v) {
            return Err(ShardError::Mismatch {
                path: p.clone(),
                first: parts[0].clone(),
                field,
                detail,
            }
            .into());
        }
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------
// Datasets
// ---------------------------------------------------------------------------------------

struct DatasetPart {
    header: ManifestHeader,
    records: Vec<MeasurementRecord>,
    shard: ShardInfo,
    /// `gonio acquire --shard` parts: the whole plan (the same bytes in every part).
    plan: Option<Vec<u8>>,
    /// The part's own summary (an acquisition's differs per part: its own counts, times).
    summary: serde_json::Value,
}

/// Files a dataset part may hold besides what the store writes per record: a
/// `gonio sim btf` part has the first three, a `gonio acquire` part may have all.
const STORE_FILES: [&str; 6] = [
    store::MANIFEST_FILE,
    store::JOURNAL_FILE,
    store::IMAGES_DIR,
    store::PLAN_FILE,
    store::TRUTH_DIR,
    store::CALIBRATION_DIR,
];

fn read_dataset_part(dir: &Path) -> Result<(DatasetPart, serde_json::Value), MergeError> {
    let mpath = dir.join(store::MANIFEST_FILE);
    let bytes = std::fs::read(&mpath).map_err(|e| part_err(dir, format!("reading {}: {e}", mpath.display())))?;
    let manifest: serde_json::Value =
        serde_json::from_slice(&bytes).map_err(|e| part_err(dir, format!("manifest.json: {e}")))?;
    let shard = shard_of(dir, manifest.pointer("/extra/shard"), "extra.shard in manifest.json")?;
    if manifest.get("complete") != Some(&serde_json::Value::Bool(true)) {
        return Err(part_err(
            dir,
            format!(
                "shard {}/{} is incomplete (its run did not finish); run it again with --shard {}/{} --force",
                shard.index, shard.count, shard.index, shard.count
            ),
        ));
    }
    for entry in std::fs::read_dir(dir).map_err(|e| part_err(dir, format!("listing: {e}")))? {
        let entry = entry.map_err(|e| part_err(dir, format!("listing: {e}")))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if !STORE_FILES.contains(&name.as_str()) && !name.starts_with('.') {
            return Err(part_err(
                dir,
                format!(
                    "holds `{name}`, which merge does not know how to combine (sharded `gonio sim btf` and \
                     `gonio acquire` datasets merge)"
                ),
            ));
        }
    }
    let (header, mut records) = store::load(dir)?;
    records.sort_by_key(|r| (r.order, r.index));
    let plan = match std::fs::read(dir.join(store::PLAN_FILE)) {
        Ok(b) => Some(b),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        Err(e) => return Err(part_err(dir, format!("reading {}: {e}", store::PLAN_FILE))),
    };
    let summary = manifest.get("summary").cloned().unwrap_or(serde_json::Value::Null);
    // What must be equal across parts: everything but the records, the creation time and
    // the part's own shard (and an acquisition's own summary: its counts and times).
    let mut norm = manifest;
    if let Some(o) = norm.as_object_mut() {
        o.remove("records");
        o.remove("created_unix");
        if plan.is_some() {
            o.remove("summary");
        }
    }
    if let Some(extra) = norm.get_mut("extra").and_then(|e| e.as_object_mut()) {
        extra.remove("shard");
    }
    Ok((
        DatasetPart {
            header,
            records,
            shard,
            plan,
            summary,
        },
        norm,
    ))
}

fn merge_datasets(parts: &[PathBuf], out: &Path, force: bool) -> Result<MergeReport, MergeError> {
    let mut read = Vec::with_capacity(parts.len());
    let mut norms = Vec::with_capacity(parts.len());
    for p in parts {
        if !p.is_dir() {
            return Err(not_a_part(p, "the first part is a dataset directory, this is not"));
        }
        let (part, norm) = read_dataset_part(p)?;
        read.push(part);
        norms.push(norm);
    }
    let infos: Vec<(PathBuf, ShardInfo)> = parts.iter().cloned().zip(read.iter().map(|r| r.shard)).collect();
    let order = shard::check_complete(&infos)?;
    check_same(parts, &norms)?;
    let n_lights = read[0]
        .header
        .sweep
        .get("lights_deg")
        .and_then(|l| l.as_array())
        .map(|l| l.len())
        .ok_or_else(|| part_err(&parts[0], "manifest sweep has no lights_deg"))?;
    // Each part holds exactly the pairs of its views.
    for (p, part) in parts.iter().zip(&read) {
        let want: Vec<usize> = (part.shard.first_view * n_lights..part.shard.end_view * n_lights).collect();
        let mut have: Vec<usize> = part.records.iter().map(|r| r.index).collect();
        have.sort_unstable();
        if have != want {
            let missing = want.iter().filter(|i| have.binary_search(i).is_err()).count();
            let foreign = have.iter().filter(|i| want.binary_search(i).is_err()).count();
            return Err(part_err(
                p,
                format!(
                    "shard {}/{} should hold the {} pairs of views {}..{}; {missing} of them are missing and \
                     {foreign} records belong to other views",
                    part.shard.index,
                    part.shard.count,
                    want.len(),
                    part.shard.first_view,
                    part.shard.end_view
                ),
            ));
        }
        if let Some(r) = part.records.iter().find(|r| r.raw.is_some()) {
            return Err(part_err(
                p,
                format!(
                    "measurement {} has a raw frame; merge handles rectified images only",
                    r.index
                ),
            ));
        }
    }
    if out.exists() && !force {
        return Err(MergeError::Exists {
            path: out.to_path_buf(),
        });
    }
    // Acquisition parts all planned the whole sweep: the same plan.json, byte for byte.
    for (p, part) in parts.iter().zip(&read).skip(1) {
        if part.plan != read[0].plan {
            return Err(part_err(
                p,
                format!(
                    "its {} differs from {}'s: the parts were not planned alike (same rig, sweep, sample and \
                     planning options, and the default kick budget rather than a --plan-time cap)",
                    store::PLAN_FILE,
                    parts[0].display()
                ),
            ));
        }
    }
    let acquisition = read[0].plan.is_some();
    let mut header = read[0].header.clone();
    header.created_unix = read.iter().map(|r| r.header.created_unix).fold(f64::INFINITY, f64::min);
    if let Some(extra) = header.extra.as_object_mut() {
        extra.remove("shard");
    }
    let summary = if acquisition {
        acquisition_summary(&read.iter().map(|r| r.summary.clone()).collect::<Vec<_>>())
    } else {
        norms[0].get("summary").cloned().unwrap_or(serde_json::Value::Null)
    };
    // The single-process journal order: skipped pairs first (recorded before the run, by
    // index), then the measurements in plan order (`order`, the step's place in the whole
    // plan). For `sim btf` parts (order = index) this is the shards one after the other.
    let mut all: Vec<(usize, &MeasurementRecord)> = order
        .iter()
        .flat_map(|&k| read[k].records.iter().map(move |r| (k, r)))
        .collect();
    all.sort_by_key(|(_, r)| (r.order != usize::MAX, r.order, r.index));
    let mut ds = Dataset::create(out, &header, force)?;
    if let Some(plan) = &read[0].plan {
        ds.write_plan(plan)?;
    }
    // Calibration copies are the same in every part (one calibration for the job).
    let cal = parts[0].join(store::CALIBRATION_DIR);
    if cal.is_dir() {
        for e in std::fs::read_dir(&cal).map_err(|e| part_err(&parts[0], format!("listing calibration/: {e}")))? {
            let e = e.map_err(|e| part_err(&parts[0], format!("listing calibration/: {e}")))?;
            let name = e.file_name().to_string_lossy().into_owned();
            if let Some(kind) = name.strip_suffix(".json") {
                let bytes =
                    std::fs::read(e.path()).map_err(|err| part_err(&parts[0], format!("reading {name}: {err}")))?;
                ds.store_calibration_copy(kind, &bytes)?;
            }
        }
    }
    let mut items = 0;
    for (k, rec) in all {
        let dir = &parts[k];
        let image = match &rec.image {
            Some(rel) => Some(store::read_exr(&dir.join(rel))?),
            None => None,
        };
        let truth = dir.join(store::truth_rel_path(rec.index));
        if truth.is_file() {
            let bytes =
                std::fs::read(&truth).map_err(|e| part_err(dir, format!("reading {}: {e}", truth.display())))?;
            let rel = ds.store_truth(rec.index, &store::read_exr(&truth)?)?;
            if std::fs::read(out.join(&rel)).ok().as_deref() != Some(&bytes[..]) {
                return Err(part_err(
                    dir,
                    format!("{}: the stored copy would not be byte-identical", truth.display()),
                ));
            }
        }
        let stored = ds.store(rec.clone(), image.as_ref(), None)?;
        if stored.image_sha256 != rec.image_sha256 {
            return Err(MergeError::HashMismatch {
                path: dir.clone(),
                index: rec.index,
                stored: stored.image_sha256.unwrap_or_default(),
                recorded: rec.image_sha256.clone().unwrap_or_default(),
            });
        }
        items += 1;
    }
    ds.finish(&summary)?;
    Ok(MergeReport {
        kind: "dataset",
        parts: parts.len(),
        shards: read[0].shard.count,
        views: read[0].shard.views_total,
        items,
        pass: None,
        out: out.to_path_buf(),
    })
}

/// The summary of a merged acquisition: the parts' counts and times added up, and every
/// part's own summary under `parts` (their truth-error figures cannot be combined without
/// the per-measurement values, which are in the journal's records).
fn acquisition_summary(parts: &[serde_json::Value]) -> serde_json::Value {
    let mut s = parts[0].clone();
    let Some(o) = s.as_object_mut() else {
        return serde_json::Value::Null;
    };
    let num = |key: &str| {
        parts
            .iter()
            .map(|p| p.get(key).and_then(|v| v.as_f64()).unwrap_or(0.0))
            .sum::<f64>()
    };
    for key in [
        "planned_measurements",
        "measured",
        "substituted",
        "skipped",
        "stored_this_run",
        "already_done",
        "remaining",
        "homography_from_markers",
        "homography_from_pose",
    ] {
        o.insert(key.into(), serde_json::json!(num(key) as u64));
    }
    for key in ["sweep_duration_s", "wall_time_s"] {
        o.insert(key.into(), serde_json::json!(num(key)));
    }
    let stored = num("stored_this_run");
    o.insert(
        "images_per_s".into(),
        serde_json::json!(stored / num("wall_time_s").max(1e-9)),
    );
    let mut reasons = serde_json::Map::new();
    for p in parts {
        for (k, v) in p
            .get("skipped_reasons")
            .and_then(|r| r.as_object())
            .into_iter()
            .flatten()
        {
            let n = reasons.get(k).and_then(|x| x.as_u64()).unwrap_or(0) + v.as_u64().unwrap_or(0);
            reasons.insert(k.clone(), serde_json::json!(n));
        }
    }
    o.insert("skipped_reasons".into(), serde_json::Value::Object(reasons));
    let all = |key: &str| parts.iter().all(|p| p.get(key) == Some(&serde_json::Value::Bool(true)));
    o.insert("complete".into(), serde_json::json!(all("complete")));
    o.insert("paused".into(), serde_json::json!(false));
    // The dataset itself, relative to its own directory, as `gonio acquire` stores it (a
    // dataset's bytes do not depend on where it was written; `gonio_dataset::store::provenance`).
    o.insert("dataset".into(), serde_json::json!("."));
    o.insert("truth_error".into(), serde_json::Value::Null);
    o.insert("stage_seconds".into(), serde_json::Value::Null);
    o.insert(
        "peak_rss_mib".into(),
        serde_json::json!(parts
            .iter()
            .filter_map(|p| p.get("peak_rss_mib").and_then(|v| v.as_f64()))
            .fold(0.0, f64::max)),
    );
    o.insert("parts".into(), serde_json::Value::Array(parts.to_vec()));
    s
}

// ---------------------------------------------------------------------------------------
// .gbtf (PVMF)
// ---------------------------------------------------------------------------------------

fn merge_gbtf(parts: &[PathBuf], out: &Path, force: bool) -> Result<MergeReport, MergeError> {
    let mut read: Vec<(Gbtf, ShardInfo)> = Vec::with_capacity(parts.len());
    let mut norms = Vec::with_capacity(parts.len());
    for p in parts {
        if p.is_dir() {
            return Err(not_a_part(p, "the first part is a .gbtf file, this is a directory"));
        }
        let g = Gbtf::read(p)?;
        let shard = shard_of(p, g.header.source.get("shard"), "source.shard in its header")?;
        if g.header.method != gonio_btf::compress::CodecId::Pvmf.name() {
            return Err(part_err(
                p,
                format!(
                    "method {}: only PVMF parts merge (its blocks are per view)",
                    g.header.method
                ),
            ));
        }
        let nv = g.header.views_deg.len();
        if shard.views_total != nv {
            return Err(part_err(
                p,
                format!("its shard says {} views, its header lists {nv}", shard.views_total),
            ));
        }
        let want: Vec<String> = (shard.first_view..shard.end_view)
            .flat_map(|v| [format!("us{v}"), format!("v{v}")])
            .collect();
        let have: Vec<&str> = g.header.blocks.iter().map(|b| b.name.as_str()).collect();
        if have != want {
            return Err(part_err(
                p,
                format!(
                    "shard {}/{} should hold blocks {} … {} of views {}..{}, it holds {} blocks",
                    shard.index,
                    shard.count,
                    want.first().map(String::as_str).unwrap_or("-"),
                    want.last().map(String::as_str).unwrap_or("-"),
                    shard.first_view,
                    shard.end_view,
                    have.len()
                ),
            ));
        }
        if let Some(f) = g
            .header
            .filled
            .iter()
            .find(|f| !(shard.first_view..shard.end_view).contains(&f[1]))
        {
            return Err(part_err(p, format!("filled pair {f:?} lies outside its views")));
        }
        let mut norm = serde_json::to_value(&g.header).map_err(|e| part_err(p, e.to_string()))?;
        if let Some(o) = norm.as_object_mut() {
            o.remove("blocks");
            o.remove("filled");
        }
        if let Some(s) = norm.get_mut("source").and_then(|s| s.as_object_mut()) {
            s.remove("shard");
        }
        norms.push(norm);
        read.push((g, shard));
    }
    let infos: Vec<(PathBuf, ShardInfo)> = parts.iter().cloned().zip(read.iter().map(|r| r.1)).collect();
    let order = shard::check_complete(&infos)?;
    check_same(parts, &norms)?;
    if out.exists() && !force {
        return Err(MergeError::Exists {
            path: out.to_path_buf(),
        });
    }
    let mut header: GbtfHeader = read[0].0.header.clone();
    if let Some(s) = header.source.as_object_mut() {
        s.remove("shard");
    }
    // The parts name the dataset absolute; the merged file names it relative to its own
    // directory, as one process would (`gonio_dataset::store::provenance`).
    if let Some(abs) = header.source.get("dataset").and_then(|d| d.as_str()) {
        let rel = provenance::relative_path(&provenance::output_dir(out), Path::new(abs));
        header.source["dataset"] = serde_json::Value::String(rel);
    }
    header.blocks.clear();
    header.filled.clear();
    let mut blocks = Vec::new();
    for &k in &order {
        let g = &mut read[k].0;
        header.blocks.append(&mut g.header.blocks);
        header.filled.append(&mut g.header.filled);
        blocks.append(&mut g.blocks);
    }
    let items = blocks.len();
    Gbtf { header, blocks }.write(out)?;
    Ok(MergeReport {
        kind: "gbtf",
        parts: parts.len(),
        shards: read[0].1.count,
        views: read[0].1.views_total,
        items,
        pass: None,
        out: out.to_path_buf(),
    })
}

// ---------------------------------------------------------------------------------------
// .gpart (one pass of a sharded PCA, DFMF or local PCA)
// ---------------------------------------------------------------------------------------

/// A read `.gpart`: its path, header and payload.
type ReadPart = (PathBuf, PartHeader, Vec<u8>);

/// Read and check the `.gpart` parts of one pass: the same job, pass and state, filled
/// pairs inside their views.
fn read_rsvd_parts(parts: &[PathBuf]) -> Result<Vec<ReadPart>, MergeError> {
    let mut read: Vec<(PathBuf, PartHeader, Vec<u8>)> = Vec::with_capacity(parts.len());
    let mut norms = Vec::with_capacity(parts.len());
    for p in parts {
        if p.is_dir() || !rsvd_shard::is_part_file(p) {
            return Err(not_a_part(
                p,
                "the first part is a .gpart of `gonio compress --shard` (pca/dfmf/local-pca), this is not",
            ));
        }
        let (h, payload) = rsvd_shard::read_part(p)?;
        // What must be equal across the parts of one pass: job, pass and state.
        let norm = serde_json::json!({"job": h.job, "pass": h.pass, "passes": h.passes, "state": h.state});
        norms.push(norm);
        read.push((p.clone(), h, payload));
    }
    check_same(parts, &norms)?;
    for (p, h, _) in &read {
        if let Some(f) = h
            .filled
            .iter()
            .find(|f| !(h.shard.first_view..h.shard.end_view).contains(&f[1]))
        {
            return Err(part_err(p, format!("filled pair {f:?} lies outside its views")));
        }
    }
    Ok(read)
}

fn in_order(read: Vec<ReadPart>, order: &[usize]) -> Vec<ReadPart> {
    let mut slots: Vec<Option<ReadPart>> = read.into_iter().map(Some).collect();
    order
        .iter()
        .map(|&k| slots[k].take().expect("each part once"))
        .collect()
}

fn merge_rsvd(parts: &[PathBuf], out: &Path, force: bool) -> Result<MergeReport, MergeError> {
    let read = read_rsvd_parts(parts)?;
    let infos: Vec<(PathBuf, ShardInfo)> = read.iter().map(|(p, h, _)| (p.clone(), h.shard)).collect();
    let order = shard::check_complete(&infos)?;
    if out.exists() && !force {
        return Err(MergeError::Exists {
            path: out.to_path_buf(),
        });
    }
    let (shards, views) = (read[0].1.shard.count, read[0].1.shard.views_total);
    let ordered = in_order(read, &order);
    let merged = rsvd_shard::merge_parts(&ordered, out)?;
    Ok(pass_report(parts.len(), shards, views, merged, out))
}

/// `gonio merge --partial`: join one group of a pass's `.gpart` parts (shards
/// `(g−1)·m + 1 ..= g·m` of N, see [`shard::check_group`]) into one `.gpart`, shard `g` of
/// `N / m`. The final merge takes such parts like any others, so merges can form a tree
/// whose every node reads `m` parts; exact sums keep every tree's result the same bytes.
pub fn merge_partial(parts: &[PathBuf], out: &Path, force: bool) -> Result<MergeReport, MergeError> {
    let first = parts.first().ok_or(ShardError::NoParts)?;
    if let Some(p) = parts.iter().find(|p| !p.exists()) {
        return Err(MergeError::Absent {
            parts: vec![p.display().to_string()],
        });
    }
    if !rsvd_shard::is_part_file(first) {
        return Err(not_a_part(
            first,
            "--partial joins the .gpart parts of one pass of `gonio compress --shard` (pca/dfmf/local-pca)",
        ));
    }
    let read = read_rsvd_parts(parts)?;
    let infos: Vec<(PathBuf, ShardInfo)> = read.iter().map(|(p, h, _)| (p.clone(), h.shard)).collect();
    let (order, group) = shard::check_group(&infos)?;
    if out.exists() && !force {
        return Err(MergeError::Exists {
            path: out.to_path_buf(),
        });
    }
    let (shards, views) = (read[0].1.shard.count, read[0].1.shard.views_total);
    let ordered = in_order(read, &order);
    let merged = rsvd_shard::merge_group(&ordered, group.info(views), out)?;
    Ok(pass_report(parts.len(), shards, views, merged, out))
}

/// The report of a merged `.gpart` pass (flat or partial).
fn pass_report(parts: usize, shards: usize, views: usize, merged: rsvd_shard::MergedPass, out: &Path) -> MergeReport {
    MergeReport {
        kind: merged.kind,
        parts,
        shards,
        views,
        items: parts,
        pass: Some([merged.pass, merged.passes]),
        out: out.to_path_buf(),
    }
}
