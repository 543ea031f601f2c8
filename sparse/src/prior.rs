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
}

/// A loaded prior (basis in f64, exactly the stored f32 values).
#[derive(Clone, Debug)]
pub struct Prior {
    pub header: PriorHeader,
    pub mean: Vec<f64>,
    pub variances: Vec<f64>,
    /// D × K.
    pub basis: DMatrix<f64>,
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
        let d = meta.lights_deg.len() * meta.views_deg.len();
        if d == 0 || !rows.len().is_multiple_of(d) {
            return Err(SparseError::Invalid(format!(
                "training rows: {} values is not a multiple of the sweep's {d} pairs",
                rows.len()
            )));
        }
        let n = rows.len() / d;
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
        };
        // Round through the file representation so an in-memory prior equals a loaded one.
        let mut p = Prior {
            header,
            mean,
            variances,
            basis,
        };
        let bytes = p.to_bytes()?;
        p = Prior::from_bytes(&bytes, "(in memory)")?;
        Ok(p)
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
        if header.format != FORMAT || header.version != VERSION {
            return Err(bad(format!(
                "format {} version {}: this gonio reads {FORMAT} version {VERSION}",
                header.format, header.version
            )));
        }
        let (d, k) = (header.dims, header.components);
        if d != header.lights * header.views || k == 0 || k > d {
            return Err(bad(format!("inconsistent sizes: {d} pairs, {k} components")));
        }
        let payload = &bytes[16 + hl..];
        let want = d * 4 + k * 8 + d * k * 4;
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
        if mean.iter().chain(&variances).any(|v| !v.is_finite()) || variances.iter().any(|&v| v <= 0.0) {
            return Err(bad("non-finite values or non-positive variances".into()));
        }
        Ok(Prior {
            header,
            mean,
            variances,
            basis,
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
        let dropped: f64 = self.variances[k..].iter().sum();
        let mut header = self.header.clone();
        header.components = k;
        header.residual_var += dropped / self.dims() as f64;
        Prior {
            header,
            mean: self.mean.clone(),
            variances: self.variances[..k].to_vec(),
            basis: self.basis.columns(0, k).into_owned(),
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

    /// Whether a sample of this name was part of the training data.
    pub fn has_seen(&self, sample: &str) -> bool {
        self.header.sources.iter().any(|s| s.sample.as_deref() == Some(sample))
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
