//! The angular prior: a Gaussian over per-texel ABRDFs, and its `.gprior` file.
//!
//! An ABRDF is one texel's values in one colour channel over every pair of the sweep, in
//! canonical index order (`view · L + light`), mapped to the prior's [`ValueSpace`]. The
//! three channels of a texel are three samples of the same distribution (one basis for all
//! channels: the angular shape of reflectance is shared, colour is in the coefficients).
//!
//! Model: `x = μ + U a + r`, `a ~ N(0, diag(λ))`, `r ~ N(0, ρ I)`, with `U` (D × K)
//! orthonormal, λ the PCA variances and ρ the mean variance per dimension that the K
//! components leave out.
//!
//! Learning: a randomized SVD of the centred training matrix (a Gaussian sketch with a fixed
//! seed, three power iterations with QR re-orthonormalisation, then an exact SVD of the
//! small projected matrix), single-threaded dense algebra: same bytes at any thread count.
//!
//! File (`.gprior`, little-endian): magic `GPRIOR\0\x01`, u64 header length, the header as
//! JSON ([`PriorHeader`]), then the mean (D × f32), the variances (K × f64) and the basis
//! (D × K f32, row-major: one row per pair). The header ends with the SHA-256 of the
//! payload, checked on load.

use crate::{sha256_hex, sweep_hash, Normal, SparseError, ValueSpace};
use nalgebra::DMatrix;
use serde::{Deserialize, Serialize};
use std::path::Path;

pub const MAGIC: &[u8; 8] = b"GPRIOR\0\x01";
pub const FORMAT: &str = "gonio-prior";
pub const VERSION: u32 = 1;
/// Version of files that also store the per-pair residual variances (priors measured on
/// held-out data); version-1 files are written, and read, as before.
pub const VERSION_PAIR_RESIDUAL: u32 = 2;
/// Smallest component variance a prior stores (held-out variances may be ~0 for a
/// component the held-out data do not use; the file requires positive variances).
const VARIANCE_FLOOR: f64 = 1e-12;

/// Where training samples came from (recorded so a bench can label a sample "seen").
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainingSource {
    /// The dataset directory's name (its last path component).
    pub dataset: String,
    /// The sample's name (from the dataset manifest), if known.
    pub sample: Option<String>,
    /// Texels taken from it.
    pub texels: usize,
}

/// What the caller knows about the training data (the numbers come from the data).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PriorMeta {
    pub sweep_name: String,
    pub lights_deg: Vec<[f64; 2]>,
    pub views_deg: Vec<[f64; 2]>,
    /// The datasets' value unit (manifest `values`), e.g. `normalized_signal`.
    pub units: String,
    pub space: ValueSpace,
    pub sources: Vec<TrainingSource>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PriorHeader {
    pub format: String,
    pub version: u32,
    pub sweep_name: String,
    /// [`crate::sweep_hash`] of the sweep's directions.
    pub sweep_hash: String,
    pub lights: usize,
    pub views: usize,
    pub units: String,
    pub space: ValueSpace,
    /// D: pairs of the sweep.
    pub dims: usize,
    /// K: basis vectors.
    pub components: usize,
    /// Mean variance per pair left out by the K components (model space).
    pub residual_var: f64,
    /// Total variance per pair of the training data (model space).
    pub total_var: f64,
    /// Training samples (texels × channels).
    pub samples: usize,
    pub sources: Vec<TrainingSource>,
    /// SHA-256 of the payload after the header (hex).
    pub payload_sha256: String,
    /// ρ and the components' variances measured on datasets the basis never saw (`gonio
    /// prior build --holdout N`); absent in priors learned without a holdout.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_out: Option<HeldOut>,
}

/// What datasets held out of the learning say about the prior.
///
/// The training residual of a K-component PCA is optimistic: on the ABRDFs it was learned
/// from, the basis also fits what is particular to them. Measured on a fresh member of
/// the prior's own family, the default K = 512 prior left out 60 × the variance its
/// training residual claimed (docs/guide/sparse.md). So a prior learned with a holdout
/// takes ρ from the held-out ABRDFs: the completion's noise model and every predicted
/// error then start from what the basis misses on data it has not seen.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HeldOut {
    /// The held-out datasets (they shaped neither the mean nor the basis).
    pub datasets: Vec<TrainingSource>,
    /// Held-out ABRDFs (texels × channels).
    pub abrdfs: usize,
    /// Mean variance per pair that the K components leave out on the *training* ABRDFs.
    pub training_residual_var: f64,
    /// The same on the held-out ABRDFs: the prior's `residual_var`.
    pub residual_var: f64,
    /// Mean squared coefficient of the held-out ABRDFs on each component (model space).
    pub component_var: Vec<f64>,
    /// Whether the prior's component variances (λ) are `component_var` instead of the
    /// training variances.
    pub variances_from_held_out: bool,
}

/// A loaded prior (basis in f64, exactly the stored f32 values).
#[derive(Clone, Debug)]
pub struct Prior {
    pub header: PriorHeader,
    pub mean: Vec<f64>,
    pub variances: Vec<f64>,
    /// D × K.
    pub basis: DMatrix<f64>,
    /// ρ per pair (D), measured on held-out data ([`HeldOut`]): the basis misses far more
    /// at the specular and grazing pairs than at the diffuse ones, so the completion weighs
    /// each measured pair by its own noise and predicts each pair's own error. `None` in
    /// priors without held-out figures (ρ is then the same at every pair).
    pub pair_residual_var: Option<Vec<f64>>,
}

/// Pairs per ABRDF (D) and ABRDFs (n) of training `rows` over `meta`'s sweep; refused when
/// the values do not divide into whole rows.
pub(crate) fn training_shape(meta: &PriorMeta, rows: &[f32]) -> Result<(usize, usize), SparseError> {
    let d = meta.lights_deg.len() * meta.views_deg.len();
    if d == 0 || !rows.len().is_multiple_of(d) {
        return Err(SparseError::Invalid(format!(
            "training rows: {} values is not a multiple of the sweep's {d} pairs",
            rows.len()
        )));
    }
    Ok((d, rows.len() / d))
}

impl Prior {
    pub fn dims(&self) -> usize {
        self.header.dims
    }
    pub fn components(&self) -> usize {
        self.header.components
    }
    pub fn space(&self) -> ValueSpace {
        self.header.space
    }

    /// Learn a prior from `rows` (each D linear values of one texel and channel; `n` rows).
    /// The rows must already be in canonical pair order.
    pub fn learn(meta: PriorMeta, rows: &[f32], components: usize, seed: u64) -> Result<Prior, SparseError> {
        Self::learn_with_holdout(meta, rows, None, components, seed)
    }

    /// [`Prior::learn`], then, when `holdout` is given (rows of datasets kept out of the
    /// learning, their sources, and whether to take λ from them), measure ρ and each
    /// component's variance on those rows ([`HeldOut`]). ρ becomes the held-out one.
    pub fn learn_with_holdout(
        meta: PriorMeta,
        rows: &[f32],
        holdout: Option<(&[f32], Vec<TrainingSource>, bool)>,
        components: usize,
        seed: u64,
    ) -> Result<Prior, SparseError> {
        let (d, n) = training_shape(&meta, rows)?;
        if components == 0 {
            return Err(SparseError::Invalid("--components must be at least 1".into()));
        }
        if n < 2 || components >= n {
            return Err(SparseError::Refused(format!(
                "{components} components from {n} training ABRDFs: need more training samples than components"
            )));
        }
        if components > d {
            return Err(SparseError::Refused(format!(
                "{components} components for a sweep of {d} pairs: at most {d}"
            )));
        }
        let space = meta.space;
        let mut x = DMatrix::<f64>::zeros(n, d);
        for i in 0..n {
            for j in 0..d {
                x[(i, j)] = space.forward(rows[i * d + j] as f64);
            }
        }
        let mut mean = vec![0.0; d];
        for j in 0..d {
            let mut s = 0.0;
            for i in 0..n {
                s += x[(i, j)];
            }
            mean[j] = s / n as f64;
            for i in 0..n {
                x[(i, j)] -= mean[j];
            }
        }
        let total: f64 = x.iter().map(|v| v * v).sum::<f64>() / (n - 1) as f64;
        // Randomized range finder.
        let l = (components + 12).min(d).min(n);
        let mut rng = Normal::new(seed);
        let omega = DMatrix::<f64>::from_fn(d, l, |_, _| rng.sample());
        let mut q = (&x * &omega).qr().q();
        for _ in 0..3 {
            let z = (x.transpose() * &q).qr().q();
            q = (&x * z).qr().q();
        }
        let b = q.transpose() * &x; // l × d
        let bbt = &b * b.transpose();
        let eig = bbt.symmetric_eigen();
        let mut order: Vec<usize> = (0..eig.eigenvalues.len()).collect();
        order.sort_by(|&i, &j| eig.eigenvalues[j].total_cmp(&eig.eigenvalues[i]).then(i.cmp(&j)));
        let mut basis = DMatrix::<f64>::zeros(d, components);
        let mut variances = Vec::with_capacity(components);
        for (k, &o) in order.iter().take(components).enumerate() {
            let s2 = eig.eigenvalues[o].max(0.0);
            if s2 <= 1e-300 {
                return Err(SparseError::Refused(format!(
                    "the training data span only {k} dimensions: ask for at most {k} components"
                )));
            }
            let w = eig.eigenvectors.column(o);
            let mut v = b.transpose() * w;
            let norm = v.norm();
            v /= norm;
            // Sign: the largest-magnitude entry positive (a fixed choice).
            let (mut best, mut arg) = (0.0, 0);
            for (i, &e) in v.iter().enumerate() {
                if e.abs() > best {
                    best = e.abs();
                    arg = i;
                }
            }
            if v[arg] < 0.0 {
                v = -v;
            }
            basis.set_column(k, &v);
            variances.push(s2 / (n - 1) as f64);
        }
        let kept: f64 = variances.iter().sum();
        let residual_var = ((total - kept) / d as f64).max(0.0);
        let header = PriorHeader {
            format: FORMAT.into(),
            version: VERSION,
            sweep_hash: sweep_hash(&meta.lights_deg, &meta.views_deg),
            sweep_name: meta.sweep_name,
            lights: meta.lights_deg.len(),
            views: meta.views_deg.len(),
            units: meta.units,
            space,
            dims: d,
            components,
            residual_var,
            total_var: total / d as f64,
            samples: n,
            sources: meta.sources,
            payload_sha256: String::new(),
            held_out: None,
        };
        let mut p = Prior {
            header,
            mean,
            variances,
            basis,
            pair_residual_var: None,
        };
        // Round through the file representation so an in-memory prior equals a loaded one
        // (and the held-out figures are measured on the stored basis, as `with_held_out`
        // measures them on a loaded prior).
        let bytes = p.to_bytes()?;
        p = Prior::from_bytes(&bytes, "(in memory)")?;
        match holdout {
            Some((held_rows, held_sources, use_variances)) => p.with_held_out(held_rows, held_sources, use_variances),
            None => Ok(p),
        }
    }

    /// This prior with ρ (and, if `use_variances`, λ) measured on `rows` — linear values,
    /// D per row, of datasets it never saw ([`HeldOut`]). The mean and basis are unchanged,
    /// so an existing prior can be given an honest ρ without learning it again. A prior
    /// that already has held-out figures is refused (measure them once, on all the held-out
    /// data together).
    pub fn with_held_out(
        &self,
        rows: &[f32],
        datasets: Vec<TrainingSource>,
        use_variances: bool,
    ) -> Result<Prior, SparseError> {
        if self.header.held_out.is_some() {
            return Err(SparseError::Refused(
                "the prior already has held-out figures: measure them from the prior learned without \
                 them, on every held-out dataset at once"
                    .into(),
            ));
        }
        // The same sample (by name, or by directory name when unnamed) as a training source.
        let same = |d: &TrainingSource, t: &TrainingSource| match (&d.sample, &t.sample) {
            (Some(a), Some(b)) => a == b,
            _ => d.dataset == t.dataset,
        };
        if let Some(s) = datasets.iter().find(|d| self.header.sources.iter().any(|t| same(d, t))) {
            return Err(SparseError::Refused(format!(
                "dataset `{}` ({}) is one the prior was learned from: held-out figures need data it never saw",
                s.dataset,
                s.sample.as_deref().unwrap_or("unnamed sample")
            )));
        }
        let mut p = self.clone();
        p.apply_held_out(rows, datasets, use_variances)?;
        let bytes = p.to_bytes()?;
        Prior::from_bytes(&bytes, "(in memory)")
    }

    fn apply_held_out(
        &mut self,
        rows: &[f32],
        datasets: Vec<TrainingSource>,
        use_variances: bool,
    ) -> Result<(), SparseError> {
        let (h, pair) = self.measure_held_out(rows, datasets, use_variances)?;
        self.header.residual_var = h.residual_var;
        self.header.version = VERSION_PAIR_RESIDUAL;
        self.pair_residual_var = Some(pair);
        if use_variances {
            self.variances = h.component_var.iter().map(|&v| v.max(VARIANCE_FLOOR)).collect();
        }
        self.header.held_out = Some(h);
        Ok(())
    }

    /// ρ and per-component variances of `rows` (linear values, D per row) in this prior.
    fn measure_held_out(
        &self,
        rows: &[f32],
        datasets: Vec<TrainingSource>,
        variances_from_held_out: bool,
    ) -> Result<(HeldOut, Vec<f64>), SparseError> {
        let (d, k) = (self.dims(), self.components());
        if rows.is_empty() || !rows.len().is_multiple_of(d) {
            return Err(SparseError::Invalid(format!(
                "held-out rows: {} values is not a positive multiple of the sweep's {d} pairs",
                rows.len()
            )));
        }
        let n = rows.len() / d;
        let space = self.space();
        let mut coef_sq = vec![0.0f64; k];
        let mut resid = 0.0f64;
        let mut pair = vec![0.0f64; d];
        // Chunks of rows, in order: the sums run in the same order at any thread count.
        const CHUNK: usize = 512;
        let bt = self.basis.transpose();
        for start in (0..n).step_by(CHUNK) {
            let m = CHUNK.min(n - start);
            let e = DMatrix::<f64>::from_fn(d, m, |j, i| {
                space.forward(rows[(start + i) * d + j] as f64) - self.mean[j]
            });
            let c = &bt * &e; // k × m
            let r = &e - &self.basis * &c;
            for i in 0..m {
                for j in 0..k {
                    coef_sq[j] += c[(j, i)] * c[(j, i)];
                }
                resid += r.column(i).norm_squared();
            }
            for (j, row) in r.row_iter().enumerate() {
                pair[j] += row.iter().map(|v| v * v).sum::<f64>();
            }
        }
        let held = HeldOut {
            datasets,
            abrdfs: n,
            training_residual_var: self.header.residual_var,
            residual_var: resid / (n * d) as f64,
            component_var: coef_sq.iter().map(|s| s / n as f64).collect(),
            variances_from_held_out,
        };
        Ok((held, pair.iter().map(|s| s / n as f64).collect()))
    }

    fn payload(&self) -> Vec<u8> {
        let (d, k) = (self.dims(), self.components());
        let mut out = Vec::with_capacity(d * 4 + k * 8 + d * k * 4);
        for &m in &self.mean {
            out.extend_from_slice(&(m as f32).to_le_bytes());
        }
        for &v in &self.variances {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for i in 0..d {
            for j in 0..k {
                out.extend_from_slice(&(self.basis[(i, j)] as f32).to_le_bytes());
            }
        }
        if let Some(v) = &self.pair_residual_var {
            for &x in v {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
        out
    }

    pub fn to_bytes(&self) -> Result<Vec<u8>, SparseError> {
        let payload = self.payload();
        let mut header = self.header.clone();
        header.payload_sha256 = sha256_hex(&payload);
        let json = serde_json::to_vec(&header).map_err(|e| SparseError::Invalid(e.to_string()))?;
        let mut out = Vec::with_capacity(16 + json.len() + payload.len());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(json.len() as u64).to_le_bytes());
        out.extend_from_slice(&json);
        out.extend_from_slice(&payload);
        Ok(out)
    }

    pub fn from_bytes(bytes: &[u8], file: &str) -> Result<Prior, SparseError> {
        let bad = |m: String| SparseError::File {
            file: file.to_string(),
            message: m,
        };
        if bytes.len() < 16 || &bytes[..8] != MAGIC {
            return Err(bad("not a gonio prior (.gprior) file: bad magic".into()));
        }
        let hl = u64::from_le_bytes(bytes[8..16].try_into().unwrap()) as usize;
        if hl > bytes.len() - 16 {
            return Err(bad("truncated header".into()));
        }
        let header: PriorHeader =
            serde_json::from_slice(&bytes[16..16 + hl]).map_err(|e| bad(format!("header: {e}")))?;
        if header.format != FORMAT || !(VERSION..=VERSION_PAIR_RESIDUAL).contains(&header.version) {
            return Err(bad(format!(
                "format {} version {}: this gonio reads {FORMAT} versions {VERSION}–{VERSION_PAIR_RESIDUAL}",
                header.format, header.version
            )));
        }
        let (d, k) = (header.dims, header.components);
        if d != header.lights * header.views || k == 0 || k > d {
            return Err(bad(format!("inconsistent sizes: {d} pairs, {k} components")));
        }
        let payload = &bytes[16 + hl..];
        let has_pair = header.version == VERSION_PAIR_RESIDUAL;
        let want = d * 4 + k * 8 + d * k * 4 + if has_pair { d * 8 } else { 0 };
        if payload.len() != want {
            return Err(bad(format!("payload is {} bytes, expected {want}", payload.len())));
        }
        if sha256_hex(payload) != header.payload_sha256 {
            return Err(bad("payload checksum mismatch (file damaged)".into()));
        }
        let f32_at = |o: usize| f32::from_le_bytes(payload[o..o + 4].try_into().unwrap()) as f64;
        let mean: Vec<f64> = (0..d).map(|i| f32_at(i * 4)).collect();
        let vo = d * 4;
        let variances: Vec<f64> = (0..k)
            .map(|i| f64::from_le_bytes(payload[vo + i * 8..vo + i * 8 + 8].try_into().unwrap()))
            .collect();
        let bo = vo + k * 8;
        let basis = DMatrix::<f64>::from_fn(d, k, |i, j| f32_at(bo + (i * k + j) * 4));
        let ro = bo + d * k * 4;
        let pair_residual_var: Option<Vec<f64>> = has_pair.then(|| {
            (0..d)
                .map(|i| f64::from_le_bytes(payload[ro + i * 8..ro + i * 8 + 8].try_into().unwrap()))
                .collect()
        });
        if pair_residual_var.iter().flatten().any(|v| !v.is_finite() || *v < 0.0) {
            return Err(bad("non-finite or negative per-pair residual variances".into()));
        }
        if mean.iter().chain(&variances).any(|v| !v.is_finite()) || variances.iter().any(|&v| v <= 0.0) {
            return Err(bad("non-finite values or non-positive variances".into()));
        }
        Ok(Prior {
            header,
            mean,
            variances,
            basis,
            pair_residual_var,
        })
    }

    pub fn load(path: &Path) -> Result<Prior, SparseError> {
        let bytes = std::fs::read(path).map_err(|e| SparseError::File {
            file: path.display().to_string(),
            message: e.to_string(),
        })?;
        Prior::from_bytes(&bytes, &path.display().to_string())
    }

    /// The prior with only its first `k` components (the rest join the residual variance).
    pub fn truncated(&self, k: usize) -> Prior {
        let k = k.clamp(1, self.components());
        // What the dropped components held joins ρ: measured on the held-out data when the
        // prior has them, else the training variances.
        let mut header = self.header.clone();
        let dropped: f64 = match &header.held_out {
            Some(h) => h.component_var[k..].iter().sum(),
            None => self.variances[k..].iter().sum(),
        };
        header.components = k;
        header.residual_var += dropped / self.dims() as f64;
        if let Some(h) = &mut header.held_out {
            h.residual_var = header.residual_var;
            if !h.variances_from_held_out {
                h.training_residual_var += self.variances[k..].iter().sum::<f64>() / self.dims() as f64;
            }
            h.component_var.truncate(k);
        }
        // Per pair, the dropped components add their variance times the pair's squared
        // loading (the expected square of what they held there).
        let pair_residual_var = self.pair_residual_var.as_ref().map(|v| {
            let var = |j: usize| match &self.header.held_out {
                Some(h) => h.component_var[j],
                None => self.variances[j],
            };
            v.iter()
                .enumerate()
                .map(|(p, &r)| {
                    r + (k..self.components())
                        .map(|j| var(j) * self.basis[(p, j)].powi(2))
                        .sum::<f64>()
                })
                .collect()
        });
        Prior {
            header,
            mean: self.mean.clone(),
            variances: self.variances[..k].to_vec(),
            basis: self.basis.columns(0, k).into_owned(),
            pair_residual_var,
        }
    }

    /// Refuse a prior built for another sweep or for other value units, naming the mismatch.
    pub fn check_compatible(
        &self,
        sweep_name: &str,
        lights_deg: &[[f64; 2]],
        views_deg: &[[f64; 2]],
        units: &str,
    ) -> Result<(), SparseError> {
        self.check_sweep(sweep_name, lights_deg, views_deg)?;
        self.check_units(units)
    }

    /// Refuse a prior built for another sweep (its directions, whatever its name).
    pub fn check_sweep(
        &self,
        sweep_name: &str,
        lights_deg: &[[f64; 2]],
        views_deg: &[[f64; 2]],
    ) -> Result<(), SparseError> {
        let h = sweep_hash(lights_deg, views_deg);
        if h != self.header.sweep_hash {
            return Err(SparseError::Mismatch(format!(
                "the prior was built for sweep `{}` ({} lights × {} views, directions hash {}), \
                 the data use sweep `{sweep_name}` ({} lights × {} views, hash {})",
                self.header.sweep_name,
                self.header.lights,
                self.header.views,
                &self.header.sweep_hash[..12],
                lights_deg.len(),
                views_deg.len(),
                &h[..12]
            )));
        }
        Ok(())
    }

    /// Refuse data in other value units than the prior's.
    pub fn check_units(&self, units: &str) -> Result<(), SparseError> {
        if units != self.header.units {
            return Err(SparseError::Mismatch(format!(
                "the prior models values in `{}`, the data are in `{units}`",
                self.header.units
            )));
        }
        Ok(())
    }

    /// The noise variance of pair `p` for a fit whose overall noise variance is `noise_var`
    /// (measurement noise plus ρ): ρ replaced by pair `p`'s own when the prior has them.
    pub fn pair_noise_var(&self, p: usize, noise_var: f64) -> f64 {
        match &self.pair_residual_var {
            Some(v) => (noise_var - self.header.residual_var + v[p]).max(1e-12),
            None => noise_var,
        }
    }

    /// The variance the basis leaves out at pair `p` (ρ when the prior has no per-pair figures).
    pub fn pair_residual(&self, p: usize) -> f64 {
        self.pair_residual_var
            .as_ref()
            .map_or(self.header.residual_var, |v| v[p])
    }

    /// Whether a sample of this name was part of the training data.
    pub fn has_seen(&self, sample: &str) -> bool {
        let held = self.header.held_out.iter().flat_map(|h| &h.datasets);
        self.header
            .sources
            .iter()
            .chain(held)
            .any(|s| s.sample.as_deref() == Some(sample))
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A synthetic sweep of `l` × `l` directions and rows drawn from a rank-`r` model.
    pub(crate) fn toy(l: usize, n: usize, r: usize, seed: u64) -> (PriorMeta, Vec<f32>) {
        let dirs: Vec<[f64; 2]> = (0..l).map(|i| [i as f64 * 5.0, 0.0]).collect();
        let d = l * l;
        let mut rng = Normal::new(seed);
        let shapes: Vec<Vec<f64>> = (0..r)
            .map(|k| {
                (0..d)
                    .map(|j| {
                        let (li, vi) = ((j % l) as f64, (j / l) as f64);
                        (0.3 * ((k as f64 + 1.0) * 0.4 * li).cos() * (0.2 * vi * (k as f64 + 0.5)).sin()).abs()
                    })
                    .collect()
            })
            .collect();
        let mut rows = Vec::with_capacity(n * d);
        for _ in 0..n {
            let c: Vec<f64> = (0..r).map(|k| rng.uniform() / (1.0 + k as f64)).collect();
            for j in 0..d {
                let v: f64 = 0.05 + (0..r).map(|k| c[k] * shapes[k][j]).sum::<f64>();
                rows.push(v as f32);
            }
        }
        let meta = PriorMeta {
            sweep_name: "toy".into(),
            lights_deg: dirs.clone(),
            views_deg: dirs,
            units: "normalized_signal".into(),
            space: ValueSpace::Gamma,
            sources: vec![TrainingSource {
                dataset: "toy".into(),
                sample: Some("toy-sample".into()),
                texels: n,
            }],
        };
        (meta, rows)
    }

    #[test]
    fn learn_is_deterministic_orthonormal_and_round_trips() {
        let (meta, rows) = toy(8, 300, 5, 1);
        let p = Prior::learn(meta.clone(), &rows, 6, 1).unwrap();
        let q = Prior::learn(meta, &rows, 6, 1).unwrap();
        let (a, b) = (p.to_bytes().unwrap(), q.to_bytes().unwrap());
        assert_eq!(a, b);
        let back = Prior::from_bytes(&a, "t").unwrap();
        assert_eq!(back.to_bytes().unwrap(), a);
        let g = p.basis.transpose() * &p.basis;
        for i in 0..6 {
            for j in 0..6 {
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((g[(i, j)] - want).abs() < 1e-5, "{i},{j}: {}", g[(i, j)]);
            }
        }
        assert!(p.variances.windows(2).all(|w| w[0] >= w[1]));
        assert!(p.has_seen("toy-sample") && !p.has_seen("wallpaper"));
    }

    #[test]
    fn mismatched_sweep_or_units_is_named() {
        let (meta, rows) = toy(6, 100, 3, 2);
        let p = Prior::learn(meta.clone(), &rows, 3, 1).unwrap();
        let other: Vec<[f64; 2]> = (0..6).map(|i| [i as f64 * 6.0, 0.0]).collect();
        let e = p
            .check_compatible("other", &other, &other, "normalized_signal")
            .unwrap_err()
            .to_string();
        assert!(e.contains("sweep `toy`") && e.contains("sweep `other`"), "{e}");
        let e = p
            .check_compatible("toy", &meta.lights_deg, &meta.views_deg, "brdf_1_per_sr")
            .unwrap_err()
            .to_string();
        assert!(e.contains("brdf_1_per_sr") && e.contains("normalized_signal"), "{e}");
        p.check_compatible("renamed", &meta.lights_deg, &meta.views_deg, "normalized_signal")
            .unwrap();
    }

    #[test]
    fn held_out_residual_is_measured_on_unseen_rows() {
        // Training rows of rank 5; a basis of 3 leaves out some of it. Held-out rows of
        // the same model leave out about as much; rows with a shape the training never had
        // leave out far more, and that is what ρ becomes.
        let (meta, rows) = toy(7, 400, 5, 4);
        let (_, same) = toy(7, 200, 5, 5);
        let d = 49;
        let odd: Vec<f32> = same
            .iter()
            .enumerate()
            .map(|(i, &v)| v + 0.2 * (((i % d) * 7 % 11) as f32 / 11.0))
            .collect();
        let src = vec![TrainingSource {
            dataset: "held".into(),
            sample: None,
            texels: 200,
        }];
        let plain = Prior::learn(meta.clone(), &rows, 3, 1).unwrap();
        let p = Prior::learn_with_holdout(meta.clone(), &rows, Some((&same, src.clone(), false)), 3, 1).unwrap();
        let h = p.header.held_out.clone().unwrap();
        assert_eq!(h.abrdfs, 200);
        assert_eq!(h.training_residual_var, plain.header.residual_var);
        assert_eq!(p.header.residual_var, h.residual_var);
        let pv = p.pair_residual_var.clone().unwrap();
        let mean = pv.iter().sum::<f64>() / d as f64;
        assert!(
            (mean - h.residual_var).abs() <= 1e-9 * h.residual_var,
            "{mean} vs {}",
            h.residual_var
        );
        assert!(plain.pair_residual_var.is_none() && p.header.version == VERSION_PAIR_RESIDUAL);
        assert!(h.residual_var > 0.3 * h.training_residual_var && h.residual_var < 3.0 * h.training_residual_var);
        // Same basis and variances as without a holdout; the file round-trips.
        assert_eq!(p.basis, plain.basis);
        assert_eq!(p.variances, plain.variances);
        let b = p.to_bytes().unwrap();
        assert_eq!(Prior::from_bytes(&b, "t").unwrap().to_bytes().unwrap(), b);
        let q = Prior::learn_with_holdout(meta.clone(), &rows, Some((&odd, src.clone(), true)), 3, 1).unwrap();
        let hq = q.header.held_out.clone().unwrap();
        assert!(
            hq.residual_var > 20.0 * h.residual_var,
            "{} vs {}",
            hq.residual_var,
            h.residual_var
        );
        assert_eq!(q.variances, hq.component_var);
        // Truncation adds the held-out variance of the dropped components.
        let t = p.truncated(2);
        let want = h.residual_var + h.component_var[2] / d as f64;
        assert!((t.header.residual_var - want).abs() <= 1e-12 * want);
        assert_eq!(t.header.held_out.unwrap().component_var.len(), 2);
        let tv = t.pair_residual_var.unwrap();
        let tmean = tv.iter().sum::<f64>() / d as f64;
        assert!(
            (tmean - t.header.residual_var).abs() <= 1e-6 * tmean,
            "{tmean} vs {}",
            t.header.residual_var
        );
        // Measured afterwards on the learned prior: the same file as learning with the holdout.
        let later = plain.with_held_out(&same, src.clone(), false).unwrap();
        assert_eq!(later.to_bytes().unwrap(), p.to_bytes().unwrap());
        assert!(later.with_held_out(&same, src.clone(), false).is_err());
        let seen = vec![TrainingSource {
            dataset: "other-dir".into(),
            sample: Some("toy-sample".into()),
            texels: 1,
        }];
        assert!(plain
            .with_held_out(&same, seen, false)
            .unwrap_err()
            .to_string()
            .contains("toy-sample"));
        // Rows of another sweep size are refused.
        assert!(Prior::learn_with_holdout(meta, &rows, Some((&same[..10], src, false)), 3, 1).is_err());
    }

    #[test]
    fn damaged_files_are_refused() {
        let (meta, rows) = toy(5, 60, 3, 3);
        let mut b = Prior::learn(meta, &rows, 3, 1).unwrap().to_bytes().unwrap();
        let n = b.len();
        b[n - 3] ^= 0x40;
        let e = Prior::from_bytes(&b, "x.gprior").unwrap_err().to_string();
        assert!(e.contains("checksum"), "{e}");
        assert!(Prior::from_bytes(b"nonsense", "x").is_err());
    }
}
