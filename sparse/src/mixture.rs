//! A mixture of angular priors: one Gaussian per cluster of ABRDFs, each texel completed in
//! the member that explains its readings best.
//!
//! One global basis has to span every material of its training family at once. A new
//! material then uses its trailing components far more than the training data did (the
//! held-out variances of components 100–511 are 4–43 × the training ones), and the
//! completion either shrinks them (and loses the material's detail) or trusts them (and
//! fits noise). The field's answer (den Brok et al., sparse BTF measurement: a linear model
//! per material cluster; local PCA in BTF compression) is a union of local linear models:
//! ABRDFs of similar shape (a lobe of similar width, a similar shadowing) share a basis
//! that needs far fewer components to reach the same residual.
//!
//! Learning ([`Mixture::learn`]): the training ABRDFs are described by their first
//! coefficients in a small global basis, grouped by k-means (k-means++ seeding from a fixed
//! seed, Lloyd's iterations, ties to the lower index: the same bytes every time), and each
//! cluster gets its own [`Prior`] (mean, basis, λ, ρ, ρ_p; held-out figures from the held
//! rows that fall in that cluster). The members' weights are the clusters' shares.
//!
//! Completion ([`MixtureFit`]): every member completes every texel-channel with the same
//! measured pairs and per-pair noise; the member with the largest log evidence (the
//! marginal likelihood of the readings, [`Completion::log_evidence`], plus its log weight),
//! summed over a texel's channels, completes that texel. The evidence weighs span against
//! spread: a member whose basis fits the readings but only with implausible coefficients
//! loses to one that expects them.
//!
//! File (`.gmix`, little-endian): magic `GPRIOMX\x01`, u64 header length, the header as JSON
//! ([`MixtureHeader`]), then each member's `.gprior` bytes in order (each carries its own
//! payload hash).

use crate::complete::Completion;
use crate::{Normal, Prior, PriorMeta, SparseError, TrainingSource};
use nalgebra::DMatrix;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::Path;

pub const MAGIC: &[u8; 8] = b"GPRIOMX\x01";
pub const FORMAT: &str = "gonio-prior-mixture";
pub const VERSION: u32 = 1;

/// Lloyd's iterations at most (k-means stops earlier when no assignment changes).
const KMEANS_ITERATIONS: usize = 60;

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct MemberEntry {
    /// Share of the training ABRDFs in this member's cluster.
    pub weight: f64,
    /// Training ABRDFs in the cluster.
    pub rows: usize,
    /// Held-out ABRDFs that fell in the cluster (0: its ρ is the training one).
    pub held_rows: usize,
    /// Bytes of the member's `.gprior` in the payload.
    pub bytes: u64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct MixtureHeader {
    pub format: String,
    pub version: u32,
    /// Coefficients of the global basis the clusters were formed in.
    pub features: usize,
    pub seed: u64,
    pub members: Vec<MemberEntry>,
}

/// Priors over one sweep, one per cluster of ABRDFs.
#[derive(Clone, Debug)]
pub struct Mixture {
    pub header: MixtureHeader,
    pub members: Vec<Prior>,
}

/// How [`Mixture::learn`] forms its clusters and members.
#[derive(Clone, Copy, Debug)]
pub struct MixtureOptions {
    pub clusters: usize,
    /// Components per member (fewer when a cluster has few rows).
    pub components: usize,
    /// Global coefficients that describe an ABRDF for the clustering.
    pub features: usize,
    pub seed: u64,
}

impl Mixture {
    /// Learn `opts.clusters` members from `rows` (linear values, D per row, canonical pair
    /// order), with held-out figures per member from `holdout` as [`Prior::learn_with_holdout`].
    pub fn learn(
        meta: PriorMeta,
        rows: &[f32],
        holdout: Option<(&[f32], Vec<TrainingSource>, bool)>,
        opts: MixtureOptions,
    ) -> Result<Mixture, SparseError> {
        let (d, n) = crate::prior::training_shape(&meta, rows)?;
        if opts.clusters < 2 {
            return Err(SparseError::Invalid(
                "a mixture needs at least 2 clusters (one is the plain prior: leave --clusters out)".into(),
            ));
        }
        if n < 4 * opts.clusters {
            return Err(SparseError::Refused(format!(
                "{} clusters from {n} training ABRDFs: need at least 4 per cluster",
                opts.clusters
            )));
        }
        let global = Prior::learn(meta.clone(), rows, opts.features.min(n - 1).max(1), opts.seed)?;
        let feats = features(&global, rows);
        let centres = kmeans(&feats, opts.clusters, opts.seed);
        let assign = assign(&feats, &centres);
        let held_assign = holdout.as_ref().map(|(h, _, _)| assign_rows(&global, h, &centres));
        let mut members = Vec::with_capacity(opts.clusters);
        let mut entries = Vec::with_capacity(opts.clusters);
        for c in 0..opts.clusters {
            let mine: Vec<f32> = gather(rows, d, &assign, c);
            let nc = mine.len() / d;
            let k = opts.components.min(nc / 2).max(1);
            let held: Option<(Vec<f32>, Vec<TrainingSource>, bool)> = match (&holdout, &held_assign) {
                (Some((h, src, var)), Some(ha)) => {
                    let hc = gather(h, d, ha, c);
                    // λ from held rows only when there are more of them than components.
                    (!hc.is_empty()).then(|| {
                        let use_var = *var && hc.len() / d > 2 * k;
                        (hc, src.clone(), use_var)
                    })
                }
                _ => None,
            };
            let held_rows = held.as_ref().map_or(0, |h| h.0.len() / d);
            let p = Prior::learn_with_holdout(
                meta.clone(),
                &mine,
                held.as_ref().map(|(h, s, v)| (h.as_slice(), s.clone(), *v)),
                k,
                opts.seed,
            )
            .map_err(|e| SparseError::Refused(format!("mixture member {c} ({nc} ABRDFs): {e}")))?;
            entries.push(MemberEntry {
                weight: nc as f64 / n as f64,
                rows: nc,
                held_rows,
                bytes: 0,
            });
            members.push(p);
        }
        let header = MixtureHeader {
            format: FORMAT.into(),
            version: VERSION,
            features: global.components(),
            seed: opts.seed,
            members: entries,
        };
        let m = Mixture { header, members };
        // Round through the bytes, as a prior does: in memory equals loaded.
        Mixture::from_bytes(&m.to_bytes()?, "(in memory)")
    }

    pub fn to_bytes(&self) -> Result<Vec<u8>, SparseError> {
        let blobs: Vec<Vec<u8>> = self.members.iter().map(|p| p.to_bytes()).collect::<Result<_, _>>()?;
        let mut header = self.header.clone();
        for (e, b) in header.members.iter_mut().zip(&blobs) {
            e.bytes = b.len() as u64;
        }
        let json = serde_json::to_vec(&header).map_err(|e| SparseError::Invalid(e.to_string()))?;
        let mut out = Vec::with_capacity(16 + json.len() + blobs.iter().map(Vec::len).sum::<usize>());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(json.len() as u64).to_le_bytes());
        out.extend_from_slice(&json);
        for b in &blobs {
            out.extend_from_slice(b);
        }
        Ok(out)
    }

    pub fn from_bytes(bytes: &[u8], file: &str) -> Result<Mixture, SparseError> {
        let bad = |m: String| SparseError::File {
            file: file.into(),
            message: m,
        };
        if bytes.len() < 16 || &bytes[..8] != MAGIC {
            return Err(bad("not a gonio prior mixture (.gmix): wrong magic".into()));
        }
        let hl = u64::from_le_bytes(bytes[8..16].try_into().expect("8 bytes")) as usize;
        let json = bytes
            .get(16..16usize.saturating_add(hl))
            .ok_or_else(|| bad("truncated header".into()))?;
        let header: MixtureHeader = serde_json::from_slice(json).map_err(|e| bad(format!("unreadable header: {e}")))?;
        if header.format != FORMAT || header.version != VERSION {
            return Err(bad(format!(
                "format `{}` version {}: this gonio reads `{FORMAT}` version {VERSION}",
                header.format, header.version
            )));
        }
        let mut at = 16 + hl;
        let mut members = Vec::with_capacity(header.members.len());
        for (i, e) in header.members.iter().enumerate() {
            let end = at
                .checked_add(e.bytes as usize)
                .filter(|&end| end <= bytes.len())
                .ok_or_else(|| bad(format!("member {i} is truncated")))?;
            members.push(Prior::from_bytes(&bytes[at..end], &format!("{file} (member {i})"))?);
            at = end;
        }
        if at != bytes.len() {
            return Err(bad(format!("{} bytes after the last member", bytes.len() - at)));
        }
        if members.len() < 2 {
            return Err(bad(format!("{} members: a mixture has at least 2", members.len())));
        }
        let first = &members[0].header;
        if let Some((i, _)) = members.iter().enumerate().find(|(_, p)| {
            p.header.sweep_hash != first.sweep_hash || p.header.units != first.units || p.header.space != first.space
        }) {
            return Err(bad(format!(
                "member {i} is of another sweep, unit or value space than member 0"
            )));
        }
        Ok(Mixture { header, members })
    }

    pub fn load(path: &Path) -> Result<Mixture, SparseError> {
        let bytes = std::fs::read(path)?;
        Self::from_bytes(&bytes, &path.display().to_string())
    }

    /// Every member's log weight.
    pub fn log_weights(&self) -> Vec<f64> {
        self.header.members.iter().map(|e| e.weight.max(1e-12).ln()).collect()
    }
}

/// Rows of cluster `c`.
fn gather(rows: &[f32], d: usize, assign: &[usize], c: usize) -> Vec<f32> {
    let mut out = Vec::new();
    for (i, &a) in assign.iter().enumerate() {
        if a == c {
            out.extend_from_slice(&rows[i * d..(i + 1) * d]);
        }
    }
    out
}

/// Each row's coefficients in `p`'s basis (model space).
fn features(p: &Prior, rows: &[f32]) -> Vec<Vec<f64>> {
    let d = p.dims();
    let k = p.components();
    let space = p.space();
    rows.par_chunks(d)
        .map(|row| {
            let mut a = vec![0.0; k];
            for (q, &v) in row.iter().enumerate() {
                let x = space.forward(v as f64) - p.mean[q];
                for (j, aj) in a.iter_mut().enumerate() {
                    *aj += p.basis[(q, j)] * x;
                }
            }
            a
        })
        .collect()
}

fn dist2(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// The nearest centre (ties to the lower index).
fn nearest(f: &[f64], centres: &[Vec<f64>]) -> usize {
    let mut best = (f64::INFINITY, 0);
    for (c, z) in centres.iter().enumerate() {
        let d = dist2(f, z);
        if d < best.0 {
            best = (d, c);
        }
    }
    best.1
}

fn assign(feats: &[Vec<f64>], centres: &[Vec<f64>]) -> Vec<usize> {
    feats.par_iter().map(|f| nearest(f, centres)).collect()
}

fn assign_rows(p: &Prior, rows: &[f32], centres: &[Vec<f64>]) -> Vec<usize> {
    assign(&features(p, rows), centres)
}

/// k-means with k-means++ seeding from `seed`; deterministic (sums in index order).
fn kmeans(feats: &[Vec<f64>], k: usize, seed: u64) -> Vec<Vec<f64>> {
    let n = feats.len();
    let mut rng = Normal::new(seed ^ 0x6b6d_6561_6e73);
    let mut centres = vec![feats[(rng.uniform() * n as f64) as usize % n].clone()];
    let mut d2: Vec<f64> = feats.iter().map(|f| dist2(f, &centres[0])).collect();
    while centres.len() < k {
        let total: f64 = d2.iter().sum();
        let pick = if total > 0.0 {
            let mut t = rng.uniform() * total;
            let mut i = 0;
            while i + 1 < n && t >= d2[i] {
                t -= d2[i];
                i += 1;
            }
            i
        } else {
            centres.len() % n
        };
        centres.push(feats[pick].clone());
        let z = centres.last().expect("a centre").clone();
        d2.par_iter_mut().zip(feats).for_each(|(d, f)| *d = d.min(dist2(f, &z)));
    }
    let dim = feats[0].len();
    let mut labels = assign(feats, &centres);
    for _ in 0..KMEANS_ITERATIONS {
        let mut sums = vec![vec![0.0; dim]; k];
        let mut counts = vec![0usize; k];
        for (f, &l) in feats.iter().zip(&labels) {
            counts[l] += 1;
            for (s, v) in sums[l].iter_mut().zip(f) {
                *s += v;
            }
        }
        for c in 0..k {
            if counts[c] > 0 {
                centres[c] = sums[c].iter().map(|s| s / counts[c] as f64).collect();
            } else {
                // An empty cluster restarts at the row farthest from its centre.
                let far = (0..n)
                    .map(|i| (dist2(&feats[i], &centres[labels[i]]), i))
                    .fold((f64::NEG_INFINITY, 0), |a, b| if b.0 > a.0 { b } else { a })
                    .1;
                centres[c] = feats[far].clone();
            }
        }
        let next = assign(feats, &centres);
        if next == labels {
            break;
        }
        labels = next;
    }
    centres
}

/// Every member's completion of one measured set, and the choice among them.
pub struct MixtureFit<'a> {
    pub parts: Vec<Completion<'a>>,
    log_weights: Vec<f64>,
}

impl<'a> MixtureFit<'a> {
    /// `members`: the mixture's members, each truncated to at most the pairs measured;
    /// `noise`: each measured pair's measurement noise (model space), as
    /// [`Completion::with_pair_noise`].
    pub fn new(
        members: &'a [Prior],
        log_weights: Vec<f64>,
        measured: &[usize],
        noise: &[f64],
    ) -> Result<Self, SparseError> {
        if members.len() != log_weights.len() {
            return Err(SparseError::Invalid(format!(
                "{} members and {} weights",
                members.len(),
                log_weights.len()
            )));
        }
        let parts = members
            .iter()
            .map(|p| Completion::with_pair_noise(p, measured, noise))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(MixtureFit { parts, log_weights })
    }

    /// For `y` (S × M, model space) whose columns come in groups of `group` (a texel's
    /// channels): each member's coefficients (from `solve`, e.g. the censored fit) and the
    /// chosen member of every group.
    pub fn choose(
        &self,
        y: &DMatrix<f64>,
        group: usize,
        solve: impl Fn(&Completion<'a>, &DMatrix<f64>) -> DMatrix<f64>,
    ) -> Result<(Vec<DMatrix<f64>>, Vec<usize>), SparseError> {
        let group = group.max(1);
        if !y.ncols().is_multiple_of(group) {
            return Err(SparseError::Invalid(format!(
                "{} columns are not groups of {group}",
                y.ncols()
            )));
        }
        let mut coeffs = Vec::with_capacity(self.parts.len());
        let mut scores = Vec::with_capacity(self.parts.len());
        for (c, lw) in self.parts.iter().zip(&self.log_weights) {
            let a = solve(c, y);
            let e = c.log_evidence(y, &a)?;
            scores.push(
                e.chunks(group)
                    .map(|g| g.iter().sum::<f64>() + lw)
                    .collect::<Vec<f64>>(),
            );
            coeffs.push(a);
        }
        let groups = y.ncols() / group;
        let choice = (0..groups)
            .map(|g| {
                let mut best = (f64::NEG_INFINITY, 0);
                for (m, s) in scores.iter().enumerate() {
                    if s[g] > best.0 {
                        best = (s[g], m);
                    }
                }
                best.1
            })
            .collect();
        Ok((coeffs, choice))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prior::tests::toy;
    use crate::ValueSpace;

    /// Two families the global basis mixes up: each member learns one, the file round
    /// trips byte for byte, learning twice gives the same bytes, and completion chooses
    /// the member of the family a texel came from, completing it better than one plain
    /// prior with as many components as a member (what the same measured pairs support).
    #[test]
    fn members_learn_their_cluster_and_completion_chooses_by_evidence() {
        let (meta, a) = toy(9, 400, 4, 31);
        let d = 81;
        // Family B: the same kind of ABRDFs, mirrored over the pairs (a different shape).
        let family_b = |n: usize, seed: u64| -> Vec<f32> {
            toy(9, n, 4, seed)
                .1
                .chunks(d)
                .flat_map(|r| r.iter().rev().map(|v| (v * 0.6 + 0.2).min(1.0)).collect::<Vec<f32>>())
                .collect()
        };
        let b = family_b(400, 77);
        let mut rows = a.clone();
        rows.extend_from_slice(&b);
        let opts = MixtureOptions {
            clusters: 2,
            components: 4,
            features: 6,
            seed: 3,
        };
        let m = Mixture::learn(meta.clone(), &rows, None, opts).unwrap();
        let bytes = m.to_bytes().unwrap();
        assert_eq!(
            bytes,
            Mixture::learn(meta.clone(), &rows, None, opts)
                .unwrap()
                .to_bytes()
                .unwrap()
        );
        assert_eq!(bytes, Mixture::from_bytes(&bytes, "t").unwrap().to_bytes().unwrap());
        assert!(m.header.members.iter().all(|e| e.rows >= 300), "{:?}", m.header.members);
        // Test texels from both families.
        let (_, ta) = toy(9, 20, 4, 32);
        let tb = family_b(20, 78);
        let mut test = ta.clone();
        test.extend_from_slice(&tb);
        let cols = test.len() / d;
        let truth = DMatrix::from_fn(d, cols, |q, t| ValueSpace::Gamma.forward(test[t * d + q] as f64));
        let measured: Vec<usize> = (0..d).step_by(3).collect();
        let y = truth.select_rows(&measured);
        let noise = vec![1e-6; measured.len()];
        let fit = MixtureFit::new(&m.members, m.log_weights(), &measured, &noise).unwrap();
        let (coeffs, choice) = fit.choose(&y, 1, |c, y| c.coefficients(y)).unwrap();
        // Every column of one family chooses one member, the other family the other.
        assert!(choice[..20].iter().all(|&c| c == choice[0]), "{choice:?}");
        assert!(
            choice[20..].iter().all(|&c| c == choice[20]) && choice[0] != choice[20],
            "{choice:?}"
        );
        let err = |pred: &dyn Fn(usize, usize) -> f64| -> f64 {
            let mut s = 0.0;
            for q in 0..d {
                for t in 0..cols {
                    s += (pred(q, t) - truth[(q, t)]).powi(2);
                }
            }
            s / (d * cols) as f64
        };
        let mix_err = err(&|q, t| {
            let c = &fit.parts[choice[t]];
            c.predict_pair(q, &coeffs[choice[t]].columns(t, 1).into_owned())[0]
        });
        let plain = Prior::learn(meta, &rows, 4, 3).unwrap();
        let pc = Completion::with_pair_noise(&plain, &measured, &noise).unwrap();
        let pa = pc.coefficients(&y);
        let plain_err = err(&|q, t| pc.predict_pair(q, &pa.columns(t, 1).into_owned())[0]);
        assert!(mix_err < plain_err, "mixture {mix_err:.3e}, plain K=4 {plain_err:.3e}");
        // A corrupt file is an error naming what is wrong, not a panic.
        assert!(Mixture::from_bytes(&bytes[..bytes.len() - 3], "t").is_err());
        assert!(Mixture::from_bytes(b"GPRIOMX\x01\xff\xff\xff\xff\xff\xff\xff\xff", "t").is_err());
    }

    /// The evidence is the Gaussian's log density: checked against the dense formula.
    #[test]
    fn log_evidence_matches_the_dense_gaussian() {
        let (meta, rows) = toy(9, 300, 4, 5);
        let p = Prior::learn(meta, &rows, 5, 1).unwrap();
        let measured: Vec<usize> = (0..81).step_by(4).collect();
        let noise: Vec<f64> = (0..measured.len()).map(|i| 1e-4 * (1.0 + i as f64 * 0.1)).collect();
        let c = Completion::with_pair_noise(&p, &measured, &noise).unwrap();
        let s = measured.len();
        let y = DMatrix::from_fn(s, 2, |i, j| 0.3 + 0.01 * ((i * 7 + j * 3) % 11) as f64);
        let a = c.coefficients(&y);
        let e = c.log_evidence(&y, &a).unwrap();
        let us = DMatrix::from_fn(s, p.components(), |i, j| p.basis[(measured[i], j)]);
        let lam = DMatrix::from_diagonal(&nalgebra::DVector::from_vec(p.variances.clone()));
        let mut cov = &us * lam * us.transpose();
        for (i, &q) in measured.iter().enumerate() {
            cov[(i, i)] += noise[i] + p.pair_residual(q);
        }
        let chol = cov.clone().cholesky().unwrap();
        let logdet = 2.0 * chol.l().diagonal().iter().map(|v| v.ln()).sum::<f64>();
        for j in 0..2 {
            let r = nalgebra::DVector::from_fn(s, |i, _| y[(i, j)] - p.mean[measured[i]]);
            let quad = r.dot(&chol.solve(&r));
            let want = -0.5 * (quad + logdet + s as f64 * (2.0 * std::f64::consts::PI).ln());
            assert!((e[j] - want).abs() < 1e-6 * want.abs().max(1.0), "{} vs {want}", e[j]);
        }
    }
}
