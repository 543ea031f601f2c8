//! Sharded PCA, DFMF and local PCA: one pass over one shard's views per process (PCA and
//! DFMF: of the randomized SVD, [`super::rsvd`]; local PCA: one of the nine passes of
//! [`super::local_pca::passes`]), and the files that carry a pass between processes.
//!
//! A randomized SVD needs `2 + power_iters` passes over the data, and every pass after
//! the first starts from the whole previous pass. So a sharded run is a chain of rounds,
//! each a set of N independent processes and one merge:
//!
//! ```text
//! gonio compress DS --method pca -c 8 --shard I/N --out parts/p0-I.gpart        # I = 1..N
//! gonio merge parts/p0-*.gpart --out p0.gstate                                  # exact sums
//! gonio compress DS --method pca -c 8 --shard I/N --state p0.gstate --out parts/p1-I.gpart
//! gonio merge parts/p1-*.gpart --out p1.gstate
//! …                                                                             # power_iters + 2 rounds
//! gonio merge parts/p3-*.gpart --out pca.gbtf                                   # the last pass: the file
//! ```
//!
//! (`gonio batch slurm` writes this chain as dependent jobs.)
//!
//! * A **part** (`.gpart`) holds one shard's share of one pass: the exact partial sums
//!   of the sketch ([`super::exact::ExactMat`], 32 bytes per entry) for the sum passes,
//!   or its views' columns of the projection `B = Qᵀ A` (f64) for the last pass; and the
//!   job, the pass, the shard, and the path and SHA-256 of the state it started from.
//! * A **state** (`.gstate`) is the merged sum of one pass, rounded once to f64: every
//!   process of the next pass computes `Q = orth(Y)` from it, as one process would.
//! * The merge of the last pass reads the parts' state (by its recorded path, checked by
//!   hash), assembles B in view order and finishes exactly as [`super::pca::compress`] or
//!   [`super::dfmf`] do, so the merged `.gbtf` (or `.btf`) equals the single-process file
//!   byte for byte. `tests/it/shard_merge.rs` checks that.
//!
//! Local PCA uses the same files: a part holds its pass's exact sums or its views'
//! columns, a state the merged pass and what the later passes need (the subspace basis,
//! every texel's cluster, the models), and the last merge writes the `.gbtf`.
//!
//! Missing, duplicate, overlapping parts, parts of another job, pass or state are refused
//! by name (the checks of [`gonio_dataset::shard`]).

use super::abrdf::{abrdf_gbtf, keeps_f32, Abrdfs, ABRDF_F32_BUDGET};
use super::container::{Gbtf, GbtfHeader};
use super::data::DatasetViews;
use super::dfmf::{self, DfmfParams, Stream};
use super::error::CompressError;
use super::exact::ExactMat;
use super::linalg::orthonormalize;
use super::local_pca::{
    self,
    passes::{Finished as LocalFinished, Merged, Plan as LocalPlan, State as LocalState},
};
use super::params::{header_for, CodecId, Method, Params};
use super::pca::{self, ViewCache};
use super::rsvd::{PassOutput, Rsvd, ViewSource};
use faer::Mat;
use gonio_dataset::shard::{Shard, ShardInfo};
use gonio_dataset::store::provenance;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};

/// First bytes of a part or state file.
const MAGIC: &[u8; 8] = b"GNRSVD01";

/// The file a sharded job ends in.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(tag = "output", rename_all = "kebab-case")]
pub enum Output {
    /// A `.gbtf` of `params` (method `pca` or `dfmf`), quantized to `quantize` bits if set
    /// (as `gonio compress --quantize` does after encoding).
    Gbtf { params: Params, quantize: Option<u32> },
    /// A UBO2014 DFMF `.btf` with the given factor precision and XML block.
    Btf {
        dfmf: DfmfParams,
        precision: super::btf_ubo2014::Precision,
        xml: String,
    },
}

/// Everything that makes two parts parts of the same job.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct Job {
    pub output: Output,
    /// The single-process `.gbtf` header without its filled pairs and blocks: the grid and
    /// the dataset's provenance.
    pub header: GbtfHeader,
}

/// One block of a part or state file.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
struct BlockSpec {
    name: String,
    rows: usize,
    cols: usize,
    /// `exact256` ([`ExactMat::to_bytes`]) or `f64le`.
    dtype: String,
}

/// The state a part started from.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct StateRef {
    pub path: PathBuf,
    pub sha256: String,
}

/// The header of a `.gpart`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct PartHeader {
    /// `gonio-rsvd-part`.
    pub kind: String,
    pub job: Job,
    pub pass: usize,
    pub passes: usize,
    pub shard: ShardInfo,
    pub state: Option<StateRef>,
    /// `[light, view]` filled pairs of the part's views.
    pub filled: Vec<[usize; 2]>,
    blocks: Vec<BlockSpec>,
    payload_sha256: String,
}

/// The header of a `.gstate`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct StateHeader {
    /// `gonio-rsvd-state`.
    pub kind: String,
    pub job: Job,
    /// The pass whose sums this is.
    pub pass: usize,
    pub passes: usize,
    pub shards: usize,
    blocks: Vec<BlockSpec>,
    payload_sha256: String,
}

const PART_KIND: &str = "gonio-rsvd-part";
const STATE_KIND: &str = "gonio-rsvd-state";

fn invalid(path: &Path, msg: impl std::fmt::Display) -> CompressError {
    CompressError::Invalid(format!("{}: {msg}", path.display()))
}

fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// Write magic, header and payload atomically; returns the file's size in bytes.
fn write_file<H: Serialize>(path: &Path, header: &H, payload: &[u8]) -> Result<u64, CompressError> {
    let h = serde_json::to_vec(header).map_err(|e| invalid(path, e))?;
    let mut bytes = Vec::with_capacity(16 + h.len() + payload.len());
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&(h.len() as u64).to_le_bytes());
    bytes.extend_from_slice(&h);
    bytes.extend_from_slice(payload);
    gonio_dataset::store::atomic::write_atomic(path, &bytes, None)?;
    Ok(bytes.len() as u64)
}

/// Header JSON and payload of a part or state file, and the file's SHA-256.
fn read_file(path: &Path) -> Result<(serde_json::Value, Vec<u8>, String), CompressError> {
    let bytes = std::fs::read(path).map_err(|source| CompressError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    if bytes.len() < 16 || &bytes[..8] != MAGIC {
        return Err(invalid(
            path,
            "not a gonio randomized-SVD part or state (.gpart/.gstate from `gonio compress --shard`)",
        ));
    }
    let n = u64::from_le_bytes(bytes[8..16].try_into().expect("8 bytes")) as usize;
    if bytes.len() < 16 + n {
        return Err(invalid(
            path,
            "truncated header (the file is incomplete; run its shard again)",
        ));
    }
    let header: serde_json::Value =
        serde_json::from_slice(&bytes[16..16 + n]).map_err(|e| invalid(path, format!("header: {e}")))?;
    let sha = sha256_hex(&bytes);
    Ok((header, bytes[16 + n..].to_vec(), sha))
}

fn check_payload(path: &Path, blocks: &[BlockSpec], payload: &[u8], sha: &str) -> Result<(), CompressError> {
    let want: usize = blocks
        .iter()
        .map(|b| b.rows * b.cols * if b.dtype == "exact256" { 32 } else { 8 })
        .sum();
    if payload.len() != want || sha256_hex(payload) != sha {
        return Err(invalid(
            path,
            format!(
                "payload of {} bytes does not match its header ({want} bytes and a SHA-256); the file is damaged, run its shard again",
                payload.len()
            ),
        ));
    }
    Ok(())
}

/// Append `m` to a file's blocks and payload as the f64 block `name`.
fn push_f64_block(name: String, m: &Mat<f64>, blocks: &mut Vec<BlockSpec>, payload: &mut Vec<u8>) {
    blocks.push(BlockSpec {
        name,
        rows: m.nrows(),
        cols: m.ncols(),
        dtype: "f64le".into(),
    });
    f64s_to_bytes(m, payload);
}

fn f64s_to_bytes(m: &Mat<f64>, out: &mut Vec<u8>) {
    for i in 0..m.nrows() {
        for j in 0..m.ncols() {
            out.extend_from_slice(&m[(i, j)].to_le_bytes());
        }
    }
}

fn f64s_from_bytes(rows: usize, cols: usize, b: &[u8]) -> Mat<f64> {
    Mat::from_fn(rows, cols, |i, j| {
        let o = (i * cols + j) * 8;
        f64::from_le_bytes(b[o..o + 8].try_into().expect("8 bytes"))
    })
}

/// Split `payload` by `blocks`.
fn blocks_of<'a>(blocks: &[BlockSpec], payload: &'a [u8]) -> Vec<&'a [u8]> {
    let mut out = Vec::with_capacity(blocks.len());
    let mut o = 0;
    for b in blocks {
        let n = b.rows * b.cols * if b.dtype == "exact256" { 32 } else { 8 };
        out.push(&payload[o..o + n]);
        o += n;
    }
    out
}

impl Job {
    /// The job of compressing `ds` to `output`; refuses methods that are not a
    /// randomized SVD.
    pub fn new(ds: &DatasetViews, output: Output) -> Result<Job, CompressError> {
        let params = match &output {
            Output::Gbtf { params, .. } => {
                match params.method {
                    Method::Pca | Method::Dfmf { .. } => {}
                    Method::LocalPca { in_passes: false, .. } => {
                        return Err(CompressError::Invalid(
                            "a sharded local PCA runs its nine passes (in_passes); the fused encoder is not split"
                                .into(),
                        ))
                    }
                    Method::LocalPca { subspace, .. } => {
                        let dims = ds.n_lights() * 3 * ds.n_views();
                        if !LocalPlan::applies(subspace, dims, ds.texels()) {
                            return Err(CompressError::Invalid(format!(
                                "local PCA with --subspace {subspace} clusters in the full space ({dims}-value ABRDFs, \
                                 {} texels), which is not split into passes; give --subspace d with 0 < d < {}",
                                ds.texels(),
                                dims.min(ds.texels())
                            )));
                        }
                    }
                    Method::Pvmf
                    | Method::MedianCut { .. }
                    | Method::Homomorphic { .. }
                    | Method::Nd
                    | Method::SvdJ
                    | Method::Gshd { .. }
                    | Method::Cmf { .. }
                    | Method::Svbrdf { .. }
                    | Method::Gltf => {
                        return Err(CompressError::Invalid(format!(
                            "method {} is not split into passes; --shard with --state splits pca, dfmf and local-pca \
                             (pvmf splits without --state)",
                            params.method.name()
                        )))
                    }
                }
                params.clone()
            }
            // The .btf's provenance header is only the grid here.
            Output::Btf { .. } => Params::new(Method::Pca, 1),
        };
        let mut header = header_for(ds, &params, Vec::new(), Vec::new());
        // The parts name the dataset absolute, with its SHA-256; the merge writes it relative
        // to the merged file's directory ([`relocate_dataset`]), as one process would.
        let sha = provenance::input_sha256(&ds.dir).map_err(|e| CompressError::Invalid(e.to_string()))?;
        provenance::record(
            &mut header.source,
            "dataset",
            provenance::absolute(&ds.dir).display().to_string(),
            sha,
        );
        if matches!(output, Output::Btf { .. }) {
            header.method = CodecId::Dfmf.name().into();
            header.params = serde_json::Value::Null;
        }
        if matches!(params.method, Method::LocalPca { .. }) {
            // How the ABRDFs are held is decided on the whole dataset; every shard holds
            // its columns that way (see `Abrdfs::load_views`).
            if let Some(o) = header.params.as_object_mut() {
                let exact = keeps_f32(ds, ABRDF_F32_BUDGET);
                o.insert("abrdf_storage".into(), if exact { "f32" } else { "srgb8" }.into());
            }
        }
        Ok(Job { output, header })
    }

    /// The passes of a local PCA job (none for PCA and DFMF).
    pub fn local_pca(&self) -> Option<LocalPlan> {
        let Output::Gbtf { params, .. } = &self.output else {
            return None;
        };
        let Method::LocalPca {
            clusters,
            iters,
            subspace,
            ..
        } = params.method
        else {
            return None;
        };
        let h = &self.header;
        Some(LocalPlan {
            k: clusters,
            c: params.components,
            iters,
            seed: params.seed,
            d: subspace,
            texels: h.width * h.height,
            width: h.lights_deg.len() * 3,
            views: h.views_deg.len(),
        })
    }

    /// Whether a local PCA job holds its ABRDFs as f32.
    fn abrdf_exact(&self) -> bool {
        self.header.params.get("abrdf_storage").and_then(|v| v.as_str()) == Some("f32")
    }

    /// Passes over the data.
    pub fn passes(&self, ds: &DatasetViews) -> Result<usize, CompressError> {
        match self.local_pca() {
            Some(p) => Ok(p.passes()),
            None => Ok(self.problem(ds)?.passes()),
        }
    }

    fn dfmf_params(&self) -> Result<Option<DfmfParams>, CompressError> {
        match &self.output {
            Output::Gbtf { params, .. } if params.method == Method::Pca => Ok(None),
            Output::Gbtf { params, .. } => dfmf::gbtf_params(params).map(Some),
            Output::Btf { dfmf, .. } => Ok(Some(dfmf.clone())),
        }
    }

    /// The randomized SVD of this job.
    pub fn problem(&self, ds: &DatasetViews) -> Result<Rsvd, CompressError> {
        match (&self.output, self.dfmf_params()?) {
            (Output::Gbtf { params, .. }, None) => Ok(pca::problem(ds, params)),
            (_, Some(d)) => dfmf::problem(ds, &d),
            (Output::Btf { .. }, None) => unreachable!("a .btf is DFMF"),
        }
    }

    pub fn method(&self) -> &'static str {
        match &self.output {
            Output::Gbtf { params, .. } => params.method.name(),
            Output::Btf { .. } => CodecId::Dfmf.name(),
        }
    }
}

/// What [`run_shard`] wrote.
#[derive(Serialize, Clone, Debug)]
pub struct PartReport {
    pub pass: usize,
    pub passes: usize,
    /// Whether this was the last pass (its merge writes the compressed file).
    pub last_pass: bool,
    pub shard: ShardInfo,
    pub bytes: u64,
    pub out: PathBuf,
}

/// One shard's share of one pass: pass 0 without `state`, else the pass after the
/// state's. Writes the part to `out`.
pub fn run_shard(
    ds: &DatasetViews,
    output: Output,
    shard: Shard,
    state: Option<&Path>,
    out: &Path,
) -> Result<PartReport, CompressError> {
    let job = Job::new(ds, output)?;
    let passes = job.passes(ds)?;
    shard.check_views(ds.n_views()).map_err(CompressError::Invalid)?;
    let info = shard.info(ds.n_views());
    let (pass, before, state_ref) = match state {
        None => (0, None, None),
        Some(p) => {
            let (h, y, sha) = read_state(p)?;
            if h.job != job {
                let a = serde_json::to_value(&h.job).unwrap_or_default();
                let b = serde_json::to_value(&job).unwrap_or_default();
                let (field, detail) = gonio_dataset::shard::first_difference(&a, &b).unwrap_or_default();
                return Err(invalid(
                    p,
                    format!("is a state of another job: {field} differs ({detail}); give the same dataset and options as its parts"),
                ));
            }
            if h.pass + 1 >= h.passes {
                return Err(invalid(p, "is the state of the last pass; nothing is left to run"));
            }
            let abs = p.canonicalize().map_err(|source| CompressError::Io {
                path: p.to_path_buf(),
                source,
            })?;
            let named = LocalState {
                blocks: h.blocks.iter().map(|b| b.name.clone()).zip(y).collect(),
            };
            (h.pass + 1, Some(named), Some(StateRef { path: abs, sha256: sha }))
        }
    };
    let views = info.first_view..info.end_view;
    let (output, filled) = match job.local_pca() {
        Some(plan) => {
            let a = Abrdfs::load_views(ds, views.clone(), job.abrdf_exact())?;
            let o = plan.run_pass(pass, views, &a, before.as_ref())?;
            (o, a.filled)
        }
        None => {
            let rsvd = job.problem(ds)?;
            let q: Option<Vec<Mat<f64>>> = before.map(|s| s.blocks.iter().map(|(_, y)| orthonormalize(y)).collect());
            match job.dfmf_params()? {
                None => {
                    let mut src = ViewCache::new(ds, 0);
                    let o = rsvd.run_pass(pass, views, q.as_deref(), &mut src as &mut dyn ViewSource)?;
                    (o, src.filled)
                }
                Some(d) => {
                    let mut src = Stream::new(ds, d.color_model).without_cache();
                    let o = rsvd.run_pass(pass, views, q.as_deref(), &mut src as &mut dyn ViewSource)?;
                    (o, src.filled)
                }
            }
        }
    };
    let mut blocks = Vec::new();
    let mut payload = Vec::new();
    match &output {
        PassOutput::Sums(s) => {
            for (ch, m) in s.iter().enumerate() {
                blocks.push(BlockSpec {
                    name: format!("y{ch}"),
                    rows: m.nrows(),
                    cols: m.ncols(),
                    dtype: "exact256".into(),
                });
                payload.extend_from_slice(&m.to_bytes());
            }
        }
        PassOutput::Projection(b) => {
            for (ch, m) in b.iter().enumerate() {
                push_f64_block(format!("b{ch}"), m, &mut blocks, &mut payload);
            }
        }
    }
    let header = PartHeader {
        kind: PART_KIND.into(),
        job,
        pass,
        passes,
        shard: info,
        state: state_ref,
        filled,
        blocks,
        payload_sha256: sha256_hex(&payload),
    };
    let bytes = write_file(out, &header, &payload)?;
    Ok(PartReport {
        pass,
        passes,
        last_pass: pass + 1 == passes,
        shard: info,
        bytes,
        out: out.to_path_buf(),
    })
}

/// A state file's header and sums (f64), and the file's SHA-256.
pub fn read_state(path: &Path) -> Result<(StateHeader, Vec<Mat<f64>>, String), CompressError> {
    let (h, payload, sha) = read_file(path)?;
    if h.get("kind").and_then(|k| k.as_str()) != Some(STATE_KIND) {
        return Err(invalid(
            path,
            "is not a state (.gstate): `--state` takes what `gonio merge` wrote from the previous pass's parts",
        ));
    }
    let h: StateHeader = serde_json::from_value(h).map_err(|e| invalid(path, format!("header: {e}")))?;
    check_payload(path, &h.blocks, &payload, &h.payload_sha256)?;
    let ys = h
        .blocks
        .iter()
        .zip(blocks_of(&h.blocks, &payload))
        .map(|(b, bytes)| f64s_from_bytes(b.rows, b.cols, bytes))
        .collect();
    Ok((h, ys, sha))
}

/// A part file's header, checked against its payload, and the payload.
pub fn read_part(path: &Path) -> Result<(PartHeader, Vec<u8>), CompressError> {
    let (h, payload, _) = read_file(path)?;
    if h.get("kind").and_then(|k| k.as_str()) != Some(PART_KIND) {
        return Err(invalid(path, "is not a part (.gpart) of `gonio compress --shard`"));
    }
    let h: PartHeader = serde_json::from_value(h).map_err(|e| invalid(path, format!("header: {e}")))?;
    check_payload(path, &h.blocks, &payload, &h.payload_sha256)?;
    Ok((h, payload))
}

/// Whether `path` starts like a part or state file.
pub fn is_part_file(path: &Path) -> bool {
    use std::io::Read;
    let mut m = [0u8; 8];
    std::fs::File::open(path).and_then(|mut f| f.read_exact(&mut m)).is_ok() && &m == MAGIC
}

/// What [`merge_parts`] wrote.
#[derive(Serialize, Clone, Debug)]
pub struct MergedPass {
    /// `state` (a sum pass: the input of the next round) or `gbtf` / `btf` (the last pass).
    pub kind: &'static str,
    pub pass: usize,
    pub passes: usize,
    pub bytes: u64,
}

/// Merge the parts of one pass (already checked complete, in shard order, and equal in
/// job, pass and state) into `out`.
pub fn merge_parts(parts: &[(PathBuf, PartHeader, Vec<u8>)], out: &Path) -> Result<MergedPass, CompressError> {
    let (first_path, first, _) = &parts[0];
    let (pass, passes) = (first.pass, first.passes);
    if let Some(plan) = first.job.local_pca() {
        return merge_local_pca(&plan, parts, out);
    }
    if pass + 1 < passes {
        // A sum pass: the exact sum of every part, rounded once.
        let Joined::Sums(sums) = join_parts(parts)? else {
            return Err(invalid(first_path, "its blocks are not the sums of the pass"));
        };
        let mut blocks = Vec::new();
        let mut payload = Vec::new();
        for (ch, s) in sums.iter().enumerate() {
            push_f64_block(format!("y{ch}"), &s.to_mat(), &mut blocks, &mut payload);
        }
        let header = StateHeader {
            kind: STATE_KIND.into(),
            job: first.job.clone(),
            pass,
            passes,
            shards: first.shard.count,
            blocks,
            payload_sha256: sha256_hex(&payload),
        };
        let bytes = write_file(out, &header, &payload)?;
        return Ok(MergedPass {
            kind: "state",
            pass,
            passes,
            bytes,
        });
    }
    // The last pass: Q from the state, B from the parts in view order.
    let sref = first
        .state
        .as_ref()
        .ok_or_else(|| invalid(first_path, "a last-pass part without its state"))?;
    let (sh, y, sha) = read_state(&sref.path).map_err(|e| {
        CompressError::Invalid(format!(
            "{}: reading the state it started from, {} ({e}); the state must stay where its pass was run",
            first_path.display(),
            sref.path.display()
        ))
    })?;
    if sha != sref.sha256 || sh.job != first.job {
        return Err(invalid(
            &sref.path,
            format!(
                "is not the state {} started from (its SHA-256 differs)",
                first_path.display()
            ),
        ));
    }
    let q: Vec<Mat<f64>> = y.iter().map(orthonormalize).collect();
    let nch = q.len();
    let total_cols: usize = parts
        .iter()
        .map(|(_, h, _)| h.blocks.first().map_or(0, |b| b.cols))
        .sum();
    let mut b: Vec<Mat<f64>> = q.iter().map(|q| Mat::zeros(q.ncols(), total_cols)).collect();
    let mut off = 0;
    let mut filled = Vec::new();
    for (p, h, payload) in parts {
        if h.blocks.len() != nch || h.blocks.iter().any(|bl| bl.dtype != "f64le") {
            return Err(invalid(p, "its blocks are not the projection of the last pass"));
        }
        let w = h.blocks[0].cols;
        for ((ch, bl), bytes) in h.blocks.iter().enumerate().zip(blocks_of(&h.blocks, payload)) {
            if bl.rows != q[ch].ncols() || bl.cols != w {
                return Err(invalid(p, format!("block {} is {} × {}", bl.name, bl.rows, bl.cols)));
            }
            b[ch]
                .as_mut()
                .subcols_mut(off, w)
                .copy_from(&f64s_from_bytes(bl.rows, bl.cols, bytes));
        }
        off += w;
        filled.extend_from_slice(&h.filled);
    }
    let job = &first.job;
    let (kind, bytes) = match &job.output {
        Output::Gbtf { params, quantize } => {
            let mut header = job.header.clone();
            relocate_dataset(&mut header, out);
            header.filled = filled;
            let mut g = if params.method == Method::Pca {
                let (infos, blocks) = pca::factors(params, &q[0], &b[0])?;
                header.blocks = infos;
                Gbtf { header, blocks }
            } else {
                let d = dfmf::gbtf_params(params)?;
                dfmf::to_gbtf(header, dfmf_of(job, &d, &q, &b)?)
            };
            if let Some(bits) = quantize {
                g.quantize(*bits)?;
            }
            ("gbtf", g.write(out)?)
        }
        Output::Btf {
            dfmf: d,
            precision,
            xml,
        } => {
            // The XML's `<source>` names the dataset as the job's header does: absolute.
            let xml = match job.header.source.get("dataset").and_then(|d| d.as_str()) {
                Some(abs) => {
                    let rel = provenance::relative_path(&provenance::output_dir(out), Path::new(abs));
                    xml.replacen(
                        &format!("<source>{abs}</source>"),
                        &format!("<source>{rel}</source>"),
                        1,
                    )
                }
                None => xml.clone(),
            };
            (
                "btf",
                super::btf_ubo2014::write(out, &dfmf_of(job, d, &q, &b)?, *precision, &xml)?,
            )
        }
    };
    Ok(MergedPass {
        kind,
        pass,
        passes,
        bytes,
    })
}

/// A merged file's `source.dataset`: the parts' absolute path, relative to the directory of
/// `out` (`gonio_dataset::store::provenance`).
fn relocate_dataset(header: &mut GbtfHeader, out: &Path) {
    if let Some(abs) = header.source.get("dataset").and_then(|d| d.as_str()) {
        let rel = provenance::relative_path(&provenance::output_dir(out), Path::new(abs));
        header.source["dataset"] = serde_json::Value::String(rel);
    }
}

/// A pass's parts put together: the exact sums added exactly, or every block's columns
/// joined in view order (the parts in shard order).
enum Joined {
    Sums(Vec<ExactMat>),
    Columns(Vec<Mat<f64>>),
}

/// Put one pass's parts (in shard order) together, refusing a part whose blocks are not
/// the kind and shape of the first part's.
fn join_parts(parts: &[(PathBuf, PartHeader, Vec<u8>)]) -> Result<Joined, CompressError> {
    let (_, first, _) = &parts[0];
    if first.blocks.iter().all(|b| b.dtype == "exact256") {
        let mut acc: Vec<ExactMat> = first.blocks.iter().map(|b| ExactMat::zeros(b.rows, b.cols)).collect();
        for (p, h, bytes) in parts {
            let same = h.blocks.len() == acc.len()
                && h.blocks
                    .iter()
                    .zip(&first.blocks)
                    .all(|(a, b)| a.dtype == "exact256" && (a.rows, a.cols) == (b.rows, b.cols));
            if !same {
                return Err(invalid(
                    p,
                    "its blocks are not the sums of the pass its first part holds",
                ));
            }
            for ((s, b), raw) in acc.iter_mut().zip(&h.blocks).zip(blocks_of(&h.blocks, bytes)) {
                let m = ExactMat::from_bytes(b.rows, b.cols, raw).map_err(|e| invalid(p, e))?;
                s.add_exact(&m, &p.display().to_string())?;
            }
        }
        return Ok(Joined::Sums(acc));
    }
    let mut out = Vec::with_capacity(first.blocks.len());
    for (i, b) in first.blocks.iter().enumerate() {
        let mut mats = Vec::with_capacity(parts.len());
        for (p, h, bytes) in parts {
            let Some(hb) = h.blocks.get(i).filter(|hb| {
                // every block of a part holds all its views' columns
                h.blocks.len() == first.blocks.len()
                    && hb.dtype == "f64le"
                    && hb.rows == b.rows
                    && hb.name == b.name
                    && hb.cols == h.blocks[0].cols
            }) else {
                return Err(invalid(
                    p,
                    "its blocks are not the columns of the pass its first part holds",
                ));
            };
            mats.push(f64s_from_bytes(hb.rows, hb.cols, blocks_of(&h.blocks, bytes)[i]));
        }
        let cols: usize = mats.iter().map(|m| m.ncols()).sum();
        let mut m = Mat::<f64>::zeros(b.rows, cols);
        let mut off = 0;
        for part in &mats {
            m.as_mut().subcols_mut(off, part.ncols()).copy_from(part);
            off += part.ncols();
        }
        out.push(m);
    }
    Ok(Joined::Columns(out))
}

/// Join one group of a pass's parts (in shard order) into one part of the coarser split
/// `group`: exact sums added exactly, or projection columns joined in view order.
pub fn merge_group(
    parts: &[(PathBuf, PartHeader, Vec<u8>)],
    group: ShardInfo,
    out: &Path,
) -> Result<MergedPass, CompressError> {
    let (_, first, _) = &parts[0];
    let mut blocks = Vec::new();
    let mut payload = Vec::new();
    match join_parts(parts)? {
        Joined::Sums(acc) => {
            for (b, s) in first.blocks.iter().zip(&acc) {
                blocks.push(b.clone());
                payload.extend_from_slice(&s.to_bytes());
            }
        }
        Joined::Columns(cols) => {
            for (b, m) in first.blocks.iter().zip(&cols) {
                push_f64_block(b.name.clone(), m, &mut blocks, &mut payload);
            }
        }
    }
    let header = PartHeader {
        kind: PART_KIND.into(),
        job: first.job.clone(),
        pass: first.pass,
        passes: first.passes,
        shard: group,
        state: first.state.clone(),
        filled: parts.iter().flat_map(|(_, h, _)| h.filled.iter().copied()).collect(),
        blocks,
        payload_sha256: sha256_hex(&payload),
    };
    let bytes = write_file(out, &header, &payload)?;
    Ok(MergedPass {
        kind: "part",
        pass: first.pass,
        passes: first.passes,
        bytes,
    })
}

/// The state `part` started from (its named blocks), read from where its pass ran and
/// checked by hash, job and pass.
fn state_of(part: &Path, h: &PartHeader) -> Result<Option<LocalState>, CompressError> {
    let Some(sref) = h.state.as_ref() else {
        return Ok(None);
    };
    let (sh, y, sha) = read_state(&sref.path).map_err(|e| {
        CompressError::Invalid(format!(
            "{}: reading the state it started from, {} ({e}); the state must stay where its pass was run",
            part.display(),
            sref.path.display()
        ))
    })?;
    if sha != sref.sha256 || sh.job != h.job || sh.pass + 1 != h.pass {
        return Err(invalid(
            &sref.path,
            format!("is not the state {} started from (its SHA-256 differs)", part.display()),
        ));
    }
    Ok(Some(LocalState {
        blocks: sh.blocks.iter().map(|b| b.name.clone()).zip(y).collect(),
    }))
}

/// Merge one pass of a sharded local PCA: sum or join the parts' blocks, then the
/// pass's own step ([`LocalPlan::finish_pass`]) gives the next state or the `.gbtf`.
fn merge_local_pca(
    plan: &LocalPlan,
    parts: &[(PathBuf, PartHeader, Vec<u8>)],
    out: &Path,
) -> Result<MergedPass, CompressError> {
    let (first_path, first, _) = &parts[0];
    let (pass, passes) = (first.pass, first.passes);
    let mut filled = Vec::new();
    let merged = match join_parts(parts)? {
        Joined::Sums(acc) => Merged::Sums(acc.iter().map(ExactMat::to_mat).collect()),
        Joined::Columns(cols) => Merged::Columns(cols),
    };
    for (_, h, _) in parts {
        filled.extend_from_slice(&h.filled);
    }
    let before = state_of(first_path, first)?;
    if pass > 0 && before.is_none() {
        return Err(invalid(
            first_path,
            format!("a part of pass {pass} without the state it started from"),
        ));
    }
    match plan.finish_pass(pass, before.as_ref(), merged)? {
        LocalFinished::State(st) => {
            let mut blocks = Vec::new();
            let mut payload = Vec::new();
            for (name, m) in &st.blocks {
                push_f64_block(name.clone(), m, &mut blocks, &mut payload);
            }
            let header = StateHeader {
                kind: STATE_KIND.into(),
                job: first.job.clone(),
                pass,
                passes,
                shards: first.shard.count,
                blocks,
                payload_sha256: sha256_hex(&payload),
            };
            let bytes = write_file(out, &header, &payload)?;
            Ok(MergedPass {
                kind: "state",
                pass,
                passes,
                bytes,
            })
        }
        LocalFinished::Model(m) => {
            let Output::Gbtf { quantize, .. } = &first.job.output else {
                unreachable!("local PCA writes a .gbtf")
            };
            let (blocks, extra) = local_pca::file_blocks(m, plan.texels, plan.dims(), plan.c, plan.d);
            let mut header = first.job.header.clone();
            relocate_dataset(&mut header, out);
            let mut g = abrdf_gbtf(header, filled, blocks, &extra, first.job.abrdf_exact());
            if let Some(bits) = quantize {
                g.quantize(*bits)?;
            }
            Ok(MergedPass {
                kind: "gbtf",
                pass,
                passes,
                bytes: g.write(out)?,
            })
        }
    }
}

fn dfmf_of(job: &Job, d: &DfmfParams, q: &[Mat<f64>], b: &[Mat<f64>]) -> Result<dfmf::Dfmf, CompressError> {
    let h = &job.header;
    Ok(dfmf::Dfmf {
        color_model: d.color_model,
        width: h.width,
        height: h.height,
        lights_deg: h.lights_deg.clone(),
        views_deg: h.views_deg.clone(),
        channels: dfmf::channel_factors(d, q, b)?,
    })
}
