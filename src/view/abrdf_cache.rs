//! A texel-major cache of a raw dataset, so that the inspect page's ABRDF of one texel
//! (every grid pair's RGB at that texel) is one small read instead of decoding every image.
//!
//! **Why.** A raw dataset stores one EXR per (light, view) pair, image-major: the ABRDF of
//! one texel of an 81 × 81 Bonn dataset touches all 6561 files (the server used to refuse
//! it, "too much work per click"). The cache transposes the dataset once: tile files of
//! [`TILE`]² texels, each holding, texel after texel, every cached pair's RGB. A texel's
//! ABRDF is then one contiguous read of `pairs × 3` values from one tile file.
//!
//! **Where.** Outside the dataset (it has one writer, and `--resume` removes files it does
//! not know): `ROOT/<D>/<K>/` with ROOT = `gonio view --cache DIR`, else
//! `$XDG_CACHE_HOME/gonio/abrdf`, else `~/.cache/gonio/abrdf`; D = the first 16 hex digits
//! of the SHA-256 of the dataset's canonical path, K = the SHA-256 of (canonical path,
//! manifest bytes, journal length, which pairs are measured). Removing ROOT (or any part
//! of it) at any time is safe: a missing cache is rebuilt.
//!
//! **Invariants.**
//! * *Never stale.* K changes whenever the manifest or the journal changes (a live
//!   acquisition grows the journal), so a cache is only ever taken for the exact state it
//!   was built from. While the newer one builds, the server may answer from the older
//!   one, saying so (the answer names how many pairs it covers).
//! * *Complete or ignored.* `meta.json` is the completion marker, written last (temporary
//!   file, fsync, rename) after every tile has been written the same way; a directory
//!   without it (a crash or a kill mid-build) is not a cache and is rebuilt. On opening,
//!   the meta must describe the dataset (size, grid, measured pairs) and every tile must
//!   have its exact size.
//! * *Exact.* Values are the decoded images' f32 values, stored as f16 when every value is
//!   exactly an f16 (gonio's EXRs are f16, so this is lossless) and as f32 otherwise.
//!   Unmeasured pairs are filled at read time by the rule of `RawModel` ([`fill_light`]),
//!   so the cache's ABRDF equals decoding the images one by one.
//! * *Reproducible.* The same dataset gives the same bytes (no time stamps, no paths in
//!   the files; tiles written in a fixed order).
//! * *Bounded memory.* The build streams the images once, a batch of at most
//!   [`BATCH_BYTES`] of decoded images at a time, appending each tile's part to a scratch
//!   file (pair-major), then transposes one tile at a time (one tile in memory).
//! * *Never blocks the server.* [`Caches`] builds in a background thread, one build at a
//!   time per server; lookups meanwhile get the build's progress.

use gonio_btf::compress::data::DatasetViews;
use gonio_btf::compress::CompressError;
use gonio_dataset::store;
use half::f16;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

/// Side of a tile in texels (edge tiles are smaller).
pub const TILE: usize = 16;
/// Decoded image bytes (f32 RGB) held at once while building.
pub const BATCH_BYTES: usize = 64 << 20;
/// The completion marker and description of a cache directory.
pub const META_FILE: &str = "meta.json";
const FORMAT: &str = "gonio-abrdf-cache";
const VERSION: u32 = 1;

/// Errors of building or reading a cache.
#[derive(Debug, thiserror::Error)]
pub enum CacheError {
    #[error("ABRDF cache {path}: {source} (check the directory is writable, or pass `gonio view --cache DIR`)")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("building the ABRDF cache: {0}")]
    Dataset(#[from] CompressError),
    #[error("no directory for the ABRDF cache: neither XDG_CACHE_HOME nor HOME is set; pass `gonio view --cache DIR`")]
    NoRoot,
    #[error("ABRDF cache {path}: {why}; delete that directory to rebuild it")]
    Invalid { path: PathBuf, why: String },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> CacheError + '_ {
    move |source| CacheError::Io {
        path: path.to_path_buf(),
        source,
    }
}

impl From<store::StoreError> for CacheError {
    fn from(e: store::StoreError) -> Self {
        CacheError::Io {
            path: PathBuf::new(),
            source: std::io::Error::other(e.to_string()),
        }
    }
}

/// The default cache root: `$XDG_CACHE_HOME/gonio/abrdf`, else `~/.cache/gonio/abrdf`.
pub fn default_root() -> Option<PathBuf> {
    let nonempty = |k: &str| std::env::var_os(k).filter(|v| !v.is_empty()).map(PathBuf::from);
    nonempty("XDG_CACHE_HOME")
        .filter(|p| p.is_absolute())
        .or_else(|| nonempty("HOME").map(|h| h.join(".cache")))
        .map(|c| c.join("gonio").join("abrdf"))
}

/// The light whose image stands for pair (`light`, some view) when only the lights with
/// `measured(l)` have images: `light` itself if measured, else the measured light of
/// smallest angle to it (ties to the lower index); `None` if none is measured. The rule of
/// `gonio compress` and of the viewer's `RawModel`.
pub fn fill_light(lights_deg: &[[f64; 2]], light: usize, measured: impl Fn(usize) -> bool) -> Option<usize> {
    if measured(light) {
        return Some(light);
    }
    let u = |d: [f64; 2]| {
        let (t, p) = (d[0].to_radians(), d[1].to_radians());
        [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
    };
    let q = u(lights_deg[light]);
    (0..lights_deg.len())
        .filter(|&l| measured(l))
        .map(|l| {
            let d = u(lights_deg[l]);
            (l, q[0] * d[0] + q[1] * d[1] + q[2] * d[2])
        })
        .max_by(|a, b| a.1.total_cmp(&b.1).then(b.0.cmp(&a.0)))
        .map(|(l, _)| l)
}

/// Where a dataset's caches live and which one fits its present state.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CacheKey {
    /// `ROOT/<D>`: every cache of this dataset.
    pub dataset_dir: PathBuf,
    /// `ROOT/<D>/<K>`: the cache of this state.
    pub dir: PathBuf,
    pub journal_bytes: u64,
    /// SHA-256 of the manifest bytes (hex).
    pub manifest_sha256: String,
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

/// The key of `views` (opened when its journal was `journal_bytes` long) under `root`.
pub fn key(root: &Path, views: &DatasetViews, journal_bytes: u64) -> Result<CacheKey, CacheError> {
    let canon = views.dir.canonicalize().map_err(io(&views.dir))?;
    let mpath = views.dir.join(store::MANIFEST_FILE);
    let manifest = std::fs::read(&mpath).map_err(io(&mpath))?;
    let path_bytes = canon.as_os_str().as_encoded_bytes();
    let mut h = Sha256::new();
    h.update(format!("{FORMAT} {VERSION}\0").as_bytes());
    h.update((path_bytes.len() as u64).to_le_bytes());
    h.update(path_bytes);
    h.update((manifest.len() as u64).to_le_bytes());
    h.update(&manifest);
    h.update(journal_bytes.to_le_bytes());
    let n = views.n_lights() * views.n_views();
    h.update((n as u64).to_le_bytes());
    h.update(
        (0..n)
            .map(|i| views.is_measured(i % views.n_lights(), i / views.n_lights()) as u8)
            .collect::<Vec<u8>>(),
    );
    let k = hex(&h.finalize());
    let d = hex(&Sha256::digest(path_bytes))[..16].to_string();
    Ok(CacheKey {
        dataset_dir: root.join(&d),
        dir: root.join(&d).join(k),
        journal_bytes,
        manifest_sha256: hex(&Sha256::digest(&manifest)),
    })
}

/// Stored value type.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Dtype {
    F16,
    F32,
}

impl Dtype {
    fn bytes(self) -> usize {
        match self {
            Dtype::F16 => 2,
            Dtype::F32 => 4,
        }
    }
}

/// `meta.json`: what the cache holds. Written last: its presence marks a complete cache.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Meta {
    pub format: String,
    pub version: u32,
    pub width: usize,
    pub height: usize,
    pub lights: usize,
    pub views: usize,
    pub tile: usize,
    pub dtype: Dtype,
    /// Journal length (bytes) of the dataset state the cache was built from.
    pub journal_bytes: u64,
    pub manifest_sha256: String,
    /// Canonical indices (`view · lights + light`) of the cached pairs, ascending: the
    /// pairs measured when the cache was built. Slot `s` of a texel holds `measured[s]`.
    pub measured: Vec<usize>,
}

impl Meta {
    fn tiles(&self) -> (usize, usize) {
        (self.width.div_ceil(self.tile), self.height.div_ceil(self.tile))
    }
    /// Texels of tile (tx, ty).
    fn tile_texels(&self, tx: usize, ty: usize) -> usize {
        let w = (self.width - tx * self.tile).min(self.tile);
        let h = (self.height - ty * self.tile).min(self.tile);
        w * h
    }
    fn tile_bytes(&self, tx: usize, ty: usize) -> u64 {
        (self.tile_texels(tx, ty) * self.measured.len() * 3 * self.dtype.bytes()) as u64
    }
}

fn tile_name(tx: usize, ty: usize) -> String {
    format!("tile-{ty:04}-{tx:04}.bin")
}

/// A complete cache, opened.
#[derive(Debug)]
pub struct AbrdfCache {
    pub dir: PathBuf,
    pub meta: Meta,
    /// Canonical pair index → slot, `None` if not cached.
    slot_of: Vec<Option<usize>>,
    lights_deg: Vec<[f64; 2]>,
}

impl AbrdfCache {
    fn from_meta(dir: &Path, meta: Meta, lights_deg: Vec<[f64; 2]>) -> Result<Self, CacheError> {
        let n = meta.lights * meta.views;
        let mut slot_of = vec![None; n];
        let bad = |why: String| CacheError::Invalid {
            path: dir.to_path_buf(),
            why,
        };
        for (s, &i) in meta.measured.iter().enumerate() {
            if i >= n || (s > 0 && meta.measured[s - 1] >= i) {
                return Err(bad(format!("measured pair list is not ascending below {n}")));
            }
            slot_of[i] = Some(s);
        }
        Ok(AbrdfCache {
            dir: dir.to_path_buf(),
            meta,
            slot_of,
            lights_deg,
        })
    }

    /// Open the complete cache in `dir` built for `views` at `key`; `Ok(None)` if there is
    /// none (no directory, no completion marker, or one that does not describe this state:
    /// it is then rebuilt).
    pub fn open(dir: &Path, views: &DatasetViews, key: &CacheKey) -> Result<Option<Self>, CacheError> {
        let mpath = dir.join(META_FILE);
        let bytes = match std::fs::read(&mpath) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(io(&mpath)(e)),
        };
        let meta: Meta = match serde_json::from_slice(&bytes) {
            Ok(m) => m,
            Err(e) => {
                tracing::warn!(path = %mpath.display(), error = %e, "unreadable cache description; rebuilding");
                return Ok(None);
            }
        };
        let want = expected_meta(views, key, meta.dtype);
        if meta != want {
            tracing::warn!(path = %mpath.display(), "cache describes another dataset state; rebuilding");
            return Ok(None);
        }
        let (nx, ny) = meta.tiles();
        for ty in 0..ny {
            for tx in 0..nx {
                let p = dir.join(tile_name(tx, ty));
                let len = std::fs::metadata(&p).map(|m| m.len()).unwrap_or(u64::MAX);
                if len != meta.tile_bytes(tx, ty) {
                    tracing::warn!(path = %p.display(), "cache tile missing or of the wrong size; rebuilding");
                    return Ok(None);
                }
            }
        }
        Self::from_meta(dir, meta, views.lights_deg.clone()).map(Some)
    }

    /// Number of cached pairs.
    pub fn pairs(&self) -> usize {
        self.meta.measured.len()
    }

    /// The cached values of texel (x, y): `pairs() × 3` f32, slot after slot.
    pub fn texel(&self, x: usize, y: usize) -> Result<Vec<f32>, CacheError> {
        let m = &self.meta;
        if x >= m.width || y >= m.height {
            return Err(CacheError::Invalid {
                path: self.dir.clone(),
                why: format!("texel ({x}, {y}) outside its {}×{} texels", m.width, m.height),
            });
        }
        let (tx, ty) = (x / m.tile, y / m.tile);
        let tw = (m.width - tx * m.tile).min(m.tile);
        let i = (y - ty * m.tile) * tw + (x - tx * m.tile);
        let n = self.pairs() * 3;
        let b = m.dtype.bytes();
        let p = self.dir.join(tile_name(tx, ty));
        let mut f = std::fs::File::open(&p).map_err(io(&p))?;
        f.seek(SeekFrom::Start((i * n * b) as u64)).map_err(io(&p))?;
        let mut raw = vec![0u8; n * b];
        f.read_exact(&mut raw).map_err(io(&p))?;
        Ok(match m.dtype {
            Dtype::F16 => raw
                .chunks_exact(2)
                .map(|c| f16::from_le_bytes([c[0], c[1]]).to_f32())
                .collect(),
            Dtype::F32 => raw
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
        })
    }

    /// The ABRDF of texel (x, y): `views × lights` RGB, index `view · lights + light`; an
    /// uncached pair takes the value of [`fill_light`] among the cached lights of its view
    /// (black if the view has none), as `RawModel` fills unmeasured pairs.
    pub fn abrdf(&self, x: usize, y: usize) -> Result<Vec<[f32; 3]>, CacheError> {
        let vals = self.texel(x, y)?;
        let (nl, nv) = (self.meta.lights, self.meta.views);
        let mut out = vec![[0f32; 3]; nl * nv];
        for v in 0..nv {
            let cached = |l: usize| self.slot_of[v * nl + l].is_some();
            for l in 0..nl {
                if let Some(s) = fill_light(&self.lights_deg, l, cached).and_then(|l2| self.slot_of[v * nl + l2]) {
                    out[v * nl + l] = [vals[s * 3], vals[s * 3 + 1], vals[s * 3 + 2]];
                }
            }
        }
        Ok(out)
    }
}

fn expected_meta(views: &DatasetViews, key: &CacheKey, dtype: Dtype) -> Meta {
    let nl = views.n_lights();
    Meta {
        format: FORMAT.into(),
        version: VERSION,
        width: views.width,
        height: views.height,
        lights: nl,
        views: views.n_views(),
        tile: TILE,
        dtype,
        journal_bytes: key.journal_bytes,
        manifest_sha256: key.manifest_sha256.clone(),
        measured: (0..nl * views.n_views())
            .filter(|&i| views.is_measured(i % nl, i / nl))
            .collect(),
    }
}

/// Progress of a build, shared with the server's lookups.
#[derive(Debug, Default)]
pub struct Progress {
    pub images_done: AtomicUsize,
    pub images_total: AtomicUsize,
    pub tiles_done: AtomicUsize,
    pub tiles_total: AtomicUsize,
}

/// A snapshot of [`Progress`] (the server's 202 answer).
#[derive(Clone, Debug, Serialize, PartialEq, Eq)]
pub struct ProgressSnapshot {
    /// `images` (reading the dataset) or `tiles` (writing the cache).
    pub phase: &'static str,
    pub images_done: usize,
    pub images_total: usize,
    pub tiles_done: usize,
    pub tiles_total: usize,
}

impl Progress {
    pub fn snapshot(&self) -> ProgressSnapshot {
        let g = |a: &AtomicUsize| a.load(Ordering::Relaxed);
        let (id, it) = (g(&self.images_done), g(&self.images_total));
        ProgressSnapshot {
            phase: if it > 0 && id >= it { "tiles" } else { "images" },
            images_done: id,
            images_total: it,
            tiles_done: g(&self.tiles_done),
            tiles_total: g(&self.tiles_total),
        }
    }
}

impl std::fmt::Display for ProgressSnapshot {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "building: {}/{} images read, {}/{} tiles written",
            self.images_done, self.images_total, self.tiles_done, self.tiles_total
        )
    }
}

/// A value needs f32 (the build restarts in f32).
struct NeedsF32;

/// Build the cache of `views` (state `key`) in `key.dir`, replacing whatever incomplete
/// build is there. Streams the images once; see the module doc.
pub fn build(views: &DatasetViews, key: &CacheKey, progress: &Progress) -> Result<AbrdfCache, CacheError> {
    let t0 = std::time::Instant::now();
    let dir = &key.dir;
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    // An incomplete build of this state (ours, crashed): start over, and drop the scratch
    // of builders that are gone (a killed server's).
    let _ = std::fs::remove_file(dir.join(META_FILE));
    for e in std::fs::read_dir(dir).map_err(io(dir))?.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if let Some(pid) = name.strip_prefix("scratch-").and_then(|p| p.parse::<u32>().ok()) {
            if pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists() {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
    }
    let meta = match build_as(views, key, Dtype::F16, progress)? {
        Ok(m) => m,
        Err(NeedsF32) => {
            tracing::info!(dir = %dir.display(), "values not exact in f16: building the ABRDF cache in f32");
            progress.images_done.store(0, Ordering::Relaxed);
            progress.tiles_done.store(0, Ordering::Relaxed);
            match build_as(views, key, Dtype::F32, progress)? {
                Ok(m) => m,
                Err(NeedsF32) => unreachable!("f32 holds every f32"),
            }
        }
    };
    let bytes = serde_json::to_vec_pretty(&meta).map_err(|e| io(dir)(std::io::Error::other(e)))?;
    store::atomic::sync_dir(dir, None)?;
    store::atomic::write_atomic(&dir.join(META_FILE), &bytes, None)?;
    tracing::info!(
        dir = %dir.display(),
        pairs = meta.measured.len(),
        dtype = ?meta.dtype,
        seconds = t0.elapsed().as_secs_f64(),
        "ABRDF cache built"
    );
    AbrdfCache::from_meta(dir, meta, views.lights_deg.clone())
}

fn build_as(
    views: &DatasetViews,
    key: &CacheKey,
    dtype: Dtype,
    progress: &Progress,
) -> Result<Result<Meta, NeedsF32>, CacheError> {
    use rayon::prelude::*;
    let meta = expected_meta(views, key, dtype);
    let dir = &key.dir;
    let (w, nl) = (meta.width, meta.lights);
    let (nx, ny) = meta.tiles();
    let scratch = dir.join(format!("scratch-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&scratch);
    std::fs::create_dir_all(&scratch).map_err(io(&scratch))?;
    let part = |tx: usize, ty: usize| scratch.join(tile_name(tx, ty));
    progress.images_total.store(meta.measured.len(), Ordering::Relaxed);
    progress.tiles_total.store(nx * ny, Ordering::Relaxed);
    // Pass 1: images in batches, each tile's block appended to its part file (pair-major).
    let per_image = (w * meta.height * 12).max(1);
    let batch = (BATCH_BYTES / per_image).clamp(1, 256);
    let b = dtype.bytes();
    let result = (|| -> Result<Result<(), NeedsF32>, CacheError> {
        for chunk in meta.measured.chunks(batch) {
            let planes: Vec<[Vec<f32>; 3]> = chunk
                .par_iter()
                .map(|&i| {
                    views
                        .read_planes(i % nl, i / nl)?
                        .ok_or_else(|| CompressError::Invalid(format!("pair {i} vanished from the dataset")))
                })
                .collect::<Result<_, CompressError>>()?;
            for ty in 0..ny {
                for tx in 0..nx {
                    let (x0, y0) = (tx * meta.tile, ty * meta.tile);
                    let (tw, th) = ((w - x0).min(meta.tile), (meta.height - y0).min(meta.tile));
                    let mut buf = Vec::with_capacity(chunk.len() * tw * th * 3 * b);
                    for p in &planes {
                        for y in y0..y0 + th {
                            for x in x0..x0 + tw {
                                for c in p {
                                    let v = c[y * w + x];
                                    match dtype {
                                        Dtype::F16 => {
                                            let h = f16::from_f32(v);
                                            if h.to_f32().to_bits() != v.to_bits() {
                                                return Ok(Err(NeedsF32));
                                            }
                                            buf.extend_from_slice(&h.to_le_bytes());
                                        }
                                        Dtype::F32 => buf.extend_from_slice(&v.to_le_bytes()),
                                    }
                                }
                            }
                        }
                    }
                    let p = part(tx, ty);
                    let mut f = std::fs::OpenOptions::new()
                        .create(true)
                        .append(true)
                        .open(&p)
                        .map_err(io(&p))?;
                    f.write_all(&buf).map_err(io(&p))?;
                }
            }
            progress.images_done.fetch_add(chunk.len(), Ordering::Relaxed);
        }
        // Pass 2: one tile at a time, pair-major → texel-major, written atomically.
        let np = meta.measured.len();
        for ty in 0..ny {
            for tx in 0..nx {
                let n = meta.tile_texels(tx, ty);
                let p = part(tx, ty);
                let src = if np == 0 {
                    Vec::new()
                } else {
                    std::fs::read(&p).map_err(io(&p))?
                };
                if src.len() as u64 != meta.tile_bytes(tx, ty) {
                    return Err(CacheError::Invalid {
                        path: p,
                        why: format!(
                            "scratch tile holds {} bytes, not {}",
                            src.len(),
                            meta.tile_bytes(tx, ty)
                        ),
                    });
                }
                let e = 3 * b;
                let mut out = vec![0u8; src.len()];
                for s in 0..np {
                    for t in 0..n {
                        let from = (s * n + t) * e;
                        let to = (t * np + s) * e;
                        out[to..to + e].copy_from_slice(&src[from..from + e]);
                    }
                }
                store::atomic::write_atomic(&dir.join(tile_name(tx, ty)), &out, None)?;
                let _ = std::fs::remove_file(&p);
                progress.tiles_done.fetch_add(1, Ordering::Relaxed);
            }
        }
        Ok(Ok(()))
    })();
    let _ = std::fs::remove_dir_all(&scratch);
    Ok(result?.map(|()| meta))
}

/// What [`Caches::lookup`] found for the dataset's present state.
pub enum Lookup {
    /// The cache of this state.
    Ready(Arc<AbrdfCache>),
    /// A cache of an earlier state (fewer pairs), while this state's cache builds.
    Older {
        cache: Arc<AbrdfCache>,
        building: ProgressSnapshot,
    },
    /// No cache yet; one is being built.
    Building(ProgressSnapshot),
    /// Building this state's cache failed (it is retried once the dataset changes).
    Failed(String),
}

#[derive(Default)]
struct State {
    /// The newest complete cache this server has opened or built.
    ready: Option<(CacheKey, Arc<AbrdfCache>)>,
    /// The build under way (one at a time).
    building: Option<(CacheKey, Arc<Progress>)>,
    /// The last failed build.
    failed: Option<(CacheKey, String)>,
}

/// The caches of one served dataset: lookups, and builds in a background thread.
pub struct Caches {
    root: Option<PathBuf>,
    state: Mutex<State>,
}

impl Caches {
    /// Caches under `root` (`None`: no cache directory could be determined; lookups say so).
    pub fn new(root: Option<PathBuf>) -> Arc<Caches> {
        Arc::new(Caches {
            root,
            state: Mutex::new(State::default()),
        })
    }

    pub fn root(&self) -> Option<&Path> {
        self.root.as_deref()
    }

    /// The cache for `views` (opened when the journal was `journal_bytes` long): the one on
    /// disk if complete, else a build is started (unless one is under way) and its progress
    /// returned. Blocking (reads the manifest, stats the tiles): call it off async threads.
    pub fn lookup(self: &Arc<Self>, views: &DatasetViews, journal_bytes: u64) -> Result<Lookup, CacheError> {
        let root = self.root.as_deref().ok_or(CacheError::NoRoot)?;
        let key = key(root, views, journal_bytes)?;
        let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((k, c)) = &st.ready {
            if *k == key {
                return Ok(Lookup::Ready(c.clone()));
            }
        }
        if st.building.is_none() {
            if let Some((k, why)) = &st.failed {
                if *k == key {
                    return Ok(Lookup::Failed(why.clone()));
                }
            }
            if let Some(c) = AbrdfCache::open(&key.dir, views, &key)? {
                let c = Arc::new(c);
                st.ready = Some((key, c.clone()));
                return Ok(Lookup::Ready(c));
            }
            let progress = Arc::new(Progress::default());
            progress.images_total.store(views.n_measured(), Ordering::Relaxed);
            let tiles = views.width.div_ceil(TILE) * views.height.div_ceil(TILE);
            progress.tiles_total.store(tiles, Ordering::Relaxed);
            st.building = Some((key.clone(), progress.clone()));
            let (me, views) = (self.clone(), views.clone());
            tracing::info!(dir = %key.dir.display(), images = views.n_measured(), "building the ABRDF cache");
            let spawned = std::thread::Builder::new()
                .name("abrdf-cache".into())
                .spawn(move || me.finish(key.clone(), build(&views, &key, &progress)));
            if let Err(e) = spawned {
                st.building = None;
                return Err(io(root)(e));
            }
        }
        let building = st
            .building
            .as_ref()
            .map(|(_, p)| p.snapshot())
            .unwrap_or_else(|| Progress::default().snapshot());
        Ok(match &st.ready {
            Some((_, c)) => Lookup::Older {
                cache: c.clone(),
                building,
            },
            None => Lookup::Building(building),
        })
    }

    fn finish(&self, key: CacheKey, r: Result<AbrdfCache, CacheError>) {
        let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
        st.building = None;
        match r {
            Ok(c) => {
                // Published first, then the older states removed: a lookup from now on
                // gets the new cache.
                st.ready = Some((key.clone(), Arc::new(c)));
                st.failed = None;
                drop(st);
                prune(&key);
            }
            Err(e) => {
                tracing::error!(dir = %key.dir.display(), error = %e, "building the ABRDF cache failed");
                st.failed = Some((key, e.to_string()));
            }
        }
    }
}

/// Remove the dataset's other caches (earlier states) once a newer one is complete.
fn prune(key: &CacheKey) {
    let Ok(entries) = std::fs::read_dir(&key.dataset_dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        if p != key.dir && p.is_dir() {
            match std::fs::remove_dir_all(&p) {
                Ok(()) => tracing::info!(dir = %p.display(), "removed an ABRDF cache of an earlier dataset state"),
                Err(err) => tracing::warn!(dir = %p.display(), error = %err, "could not remove an old ABRDF cache"),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::view::source::RawModel;
    use gonio_btf::compress::interp::BtfModel;
    use gonio_btf::compress::testdata::write_test_dataset;

    fn grid(n: usize, th: f64) -> Vec<[f64; 2]> {
        (0..n).map(|k| [th, 360.0 * k as f64 / n as f64]).collect()
    }

    /// A 19×21 dataset (edge tiles smaller than 16²) on 5 lights × 3 views, two pairs
    /// skipped; values exact in f16 unless `f32_values` (then rounded by the store's f16 EXRs).
    fn dataset(dir: &Path, f32_values: bool) -> DatasetViews {
        let f = move |l: usize, v: usize, t: usize, c: usize| {
            let x = 0.01 + 0.125 * ((l * 7 + v * 3 + t * 5 + c) % 23) as f32;
            if f32_values {
                x + 1e-6 * (t % 3) as f32
            } else {
                x
            }
        };
        write_test_dataset(dir, (19, 21), &grid(5, 40.0), &grid(3, 20.0), &[(1, 0), (4, 2)], f)
    }

    fn direct(raw: &RawModel, x: usize, y: usize) -> Vec<[f32; 3]> {
        let (nl, nv, t) = (raw.views.n_lights(), raw.views.n_views(), y * raw.width() + x);
        let mut out = vec![[0f32; 3]; nl * nv];
        for v in 0..nv {
            for l in 0..nl {
                let img = raw.reconstruct(l, v).unwrap();
                out[v * nl + l] = [img[t * 3], img[t * 3 + 1], img[t * 3 + 2]];
            }
        }
        out
    }

    fn build_here(ds: &Path, root: &Path) -> (AbrdfCache, CacheKey) {
        let views = DatasetViews::open(ds).unwrap();
        let k = key(root, &views, crate::view::monitor::journal_len(ds)).unwrap();
        (build(&views, &k, &Progress::default()).unwrap(), k)
    }

    #[test]
    fn cached_abrdfs_equal_decoding_the_images_and_the_bytes_are_reproducible() {
        let tmp = tempfile::tempdir().unwrap();
        // The store writes f16 EXRs, so the f16 cache is exact (the f32 fallback is for
        // datasets whose EXRs hold f32 values).
        for (name, f32_values, dtype) in [("a", false, Dtype::F16), ("b", true, Dtype::F16)] {
            let ds = tmp.path().join(name);
            dataset(&ds, f32_values);
            let raw = RawModel::open(&ds).unwrap();
            let (c, k) = build_here(&ds, &tmp.path().join("cache1"));
            assert_eq!(c.meta.dtype, dtype);
            assert_eq!(c.pairs(), 13);
            for (x, y) in [(0, 0), (18, 20), (16, 16), (15, 3), (7, 17)] {
                assert_eq!(c.abrdf(x, y).unwrap(), direct(&raw, x, y), "{name} texel ({x}, {y})");
            }
            // Reopened from disk: the same.
            let views = DatasetViews::open(&ds).unwrap();
            let again = AbrdfCache::open(&k.dir, &views, &k).unwrap().unwrap();
            assert_eq!(again.abrdf(18, 20).unwrap(), direct(&raw, 18, 20));
            // Built again elsewhere: the same bytes, file for file.
            let (c2, _) = build_here(&ds, &tmp.path().join("cache2"));
            let files = |d: &Path| {
                let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(d)
                    .unwrap()
                    .map(|e| {
                        let e = e.unwrap();
                        (
                            e.file_name().to_string_lossy().into_owned(),
                            std::fs::read(e.path()).unwrap(),
                        )
                    })
                    .collect();
                v.sort();
                v
            };
            assert_eq!(files(&c.dir), files(&c2.dir), "{name}");
            assert_eq!(files(&c.dir).len(), 2 * 2 + 1, "4 tiles and the meta");
        }
    }

    #[test]
    fn a_grown_journal_is_another_key_and_an_interrupted_build_is_not_a_cache() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = tmp.path().join("ds");
        dataset(&ds, false);
        let root = tmp.path().join("cache");
        let (_c, k) = build_here(&ds, &root);
        let views = DatasetViews::open(&ds).unwrap();
        assert!(AbrdfCache::open(&k.dir, &views, &k).unwrap().is_some());
        // The journal grows (a live run): the key changes, the old cache is not taken.
        let j = ds.join(store::JOURNAL_FILE);
        let mut f = std::fs::OpenOptions::new().append(true).open(&j).unwrap();
        f.write_all(b"\n").unwrap();
        drop(f);
        let n = crate::view::monitor::journal_len(&ds);
        let k2 = key(&root, &views, n).unwrap();
        assert_ne!(k2.dir, k.dir);
        assert_eq!(k2.dataset_dir, k.dataset_dir);
        assert!(AbrdfCache::open(&k2.dir, &views, &k2).unwrap().is_none());
        // Even a cache copied to the new key's place is refused: its meta names the old length.
        std::fs::create_dir_all(&k2.dataset_dir).unwrap();
        copy_dir(&k.dir, &k2.dir);
        assert!(AbrdfCache::open(&k2.dir, &views, &k2).unwrap().is_none());
        // No completion marker: not a cache. A truncated tile: not a cache either.
        std::fs::remove_file(k.dir.join(META_FILE)).unwrap();
        assert!(AbrdfCache::open(&k.dir, &views, &k).unwrap().is_none());
        let (_c, _) = build_here(&ds, &root);
        let t = k.dir.join(tile_name(1, 1));
        let len = std::fs::metadata(&t).unwrap().len();
        std::fs::OpenOptions::new()
            .write(true)
            .open(&t)
            .unwrap()
            .set_len(len - 6)
            .unwrap();
        assert!(AbrdfCache::open(&k.dir, &views, &k).unwrap().is_none());
    }

    fn copy_dir(from: &Path, to: &Path) {
        std::fs::create_dir_all(to).unwrap();
        for e in std::fs::read_dir(from).unwrap() {
            let e = e.unwrap();
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }

    #[test]
    fn the_manager_builds_in_the_background_rebuilds_after_a_crash_and_prunes_older_states() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = tmp.path().join("ds");
        dataset(&ds, false);
        let root = tmp.path().join("cache");
        let caches = Caches::new(Some(root.clone()));
        let views = DatasetViews::open(&ds).unwrap();
        let n = crate::view::monitor::journal_len(&ds);
        // A crashed build left tiles but no marker.
        let k = key(&root, &views, n).unwrap();
        std::fs::create_dir_all(&k.dir).unwrap();
        std::fs::write(k.dir.join(tile_name(0, 0)), b"partial").unwrap();
        // … and the scratch of a builder that is gone (no such pid: above Linux's pid_max).
        let dead = k.dir.join("scratch-999999999");
        std::fs::create_dir_all(&dead).unwrap();
        std::fs::write(dead.join(tile_name(0, 0)), b"part").unwrap();
        let wait = |caches: &Arc<Caches>, n: u64| loop {
            match caches.lookup(&views, n).unwrap() {
                Lookup::Ready(c) => return c,
                Lookup::Building(p) | Lookup::Older { building: p, .. } => {
                    assert_eq!((p.images_total, p.tiles_total), (13, 4));
                    std::thread::sleep(std::time::Duration::from_millis(20));
                }
                Lookup::Failed(e) => panic!("{e}"),
            }
        };
        assert!(matches!(caches.lookup(&views, n).unwrap(), Lookup::Building(_)));
        let c = wait(&caches, n);
        assert_eq!(c.dir, k.dir);
        assert!(k.dir.join(META_FILE).is_file());
        assert!(!dead.exists(), "a dead builder's scratch is removed");
        let n_files = std::fs::read_dir(&k.dir).unwrap().count();
        assert_eq!(n_files, 2 * 2 + 1, "4 tiles and the meta, nothing else");
        // Another state of the same dataset: the older cache answers while the new one builds.
        let mut f = std::fs::OpenOptions::new()
            .append(true)
            .open(ds.join(store::JOURNAL_FILE))
            .unwrap();
        f.write_all(b"\n").unwrap();
        drop(f);
        let n2 = crate::view::monitor::journal_len(&ds);
        match caches.lookup(&views, n2).unwrap() {
            Lookup::Older { cache, .. } => assert_eq!(cache.dir, k.dir),
            _ => panic!("expected the older cache while building"),
        }
        let c2 = wait(&caches, n2);
        assert_ne!(c2.dir, k.dir);
        // Pruned right after the new cache is published (polled: the builder thread does it).
        for _ in 0..500 {
            if !k.dir.exists() {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        assert!(!k.dir.exists(), "the older state's cache was pruned");
        // A new manager (a restarted server) opens the complete cache without building.
        let fresh = Caches::new(Some(root));
        assert!(matches!(fresh.lookup(&views, n2).unwrap(), Lookup::Ready(_)));
    }
}
