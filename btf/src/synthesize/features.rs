//! ABRDF features for matching (thesis §6.3: "the dimension of the BRDFs is reduced
//! first").
//!
//! **Embedding.** Every model gonio synthesizes from is linear per texel: a texel's
//! ABRDF is `Bᵀ·w_t`, with basis rows `B` shared by all texels and a short weight vector
//! `w_t` (PCA: the texel's coefficient row and the `V` columns; PVMF: the same per view,
//! views on disjoint columns; local PCA: a one in its cluster's mean slot and its
//! coefficients in that cluster's eigen-ABRDF slots; median cut: a one in its box's
//! centroid slot). With `G = B·Bᵀ = Q·Λ·Qᵀ`, `z_t = Λ^{1/2}·Qᵀ·w_t` is an **isometric**
//! embedding: `‖z_s − z_t‖ = ‖ABRDF_s − ABRDF_t‖` exactly, over all
//! `views · lights · 3` values, without decoding a single image. Its dimension is the
//! rank of `G` (PCA: c, PVMF: views · c, local PCA ≤ k(c + 1), median cut ≤ boxes).
//! Models without such a structure (homomorphic) are embedded by sampling: the values at
//! up to [`SAMPLED_PAIRS`] grid pairs spread over the grid, scaled so distances estimate
//! the full-ABRDF distance.
//!
//! **Principal features.** The embedded texels are centred and rotated onto their
//! principal axes (covariance in f64 from fixed-size row chunks summed in order, then a
//! sequential eigen-decomposition, so the result does not depend on the thread count);
//! the first `k` coordinates are the matching features, `k` the smallest count that
//! explains `energy` of the variance (default 0.95), or fixed by the caller.

use super::{FeatureImage, SynthError};
use crate::compress::dfmf::{ColorModel, Dfmf};
use crate::compress::interp::BtfModel;
use crate::compress::{CompressedBtf, Layout};
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::evd::{self_adjoint_evd, self_adjoint_evd_scratch, ComputeEigenvectors};
use faer::{Mat, Par};
use rayon::prelude::*;
use serde::Serialize;

/// Grid pairs sampled for models without a linear texel structure.
pub const SAMPLED_PAIRS: usize = 96;

/// Rows per partial sum of the covariance (fixed, so the summation order is too).
const CHUNK: usize = 2048;

/// Texels embedded so that Euclidean distance is ABRDF distance.
#[derive(Clone, Debug)]
pub struct Embedding {
    pub image: FeatureImage,
    /// `"exact"` (linear model, isometric) or `"sampled"` (values at sampled pairs).
    pub kind: &'static str,
}

/// Principal features of an embedding.
#[derive(Clone, Debug)]
pub struct Features {
    pub image: FeatureImage,
    /// Fraction of the variance explained by each principal axis, largest first (all
    /// axes, not only the kept ones).
    pub explained: Vec<f64>,
}

/// How many principal features to keep.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub enum KChoice {
    /// The smallest k whose cumulative explained variance reaches this fraction.
    Energy(f64),
    Fixed(usize),
}

/// Eigen-decomposition of the symmetric `n × n` row-major `a`, sequentially (the same
/// bits at any thread count). Returns eigenvalues in decreasing order and the matching
/// eigenvectors, each contiguous (`vecs[i·n..(i+1)·n]`).
pub fn sym_eigen_desc(a: &[f64], n: usize) -> Result<(Vec<f64>, Vec<f64>), SynthError> {
    if n == 0 {
        return Ok((Vec::new(), Vec::new()));
    }
    let m = Mat::from_fn(n, n, |i, j| a[i * n + j]);
    let mut s = faer::diag::Diag::<f64>::zeros(n);
    let mut u = Mat::<f64>::zeros(n, n);
    let req = self_adjoint_evd_scratch::<f64>(n, ComputeEigenvectors::Yes, Par::Seq, Default::default());
    let mut buf = MemBuffer::new(req);
    self_adjoint_evd(
        m.as_ref(),
        s.as_mut(),
        Some(u.as_mut()),
        Par::Seq,
        MemStack::new(&mut buf),
        Default::default(),
    )
    .map_err(|e| SynthError::Invalid(format!("eigen-decomposition of a {n}×{n} matrix failed: {e:?}")))?;
    let sv = s.column_vector();
    let mut vals = Vec::with_capacity(n);
    let mut vecs = Vec::with_capacity(n * n);
    for i in (0..n).rev() {
        vals.push(sv[i]);
        vecs.extend((0..n).map(|r| u[(r, i)]));
    }
    Ok((vals, vecs))
}

/// `Λ^{1/2}·Qᵀ` (`r × n`, row-major) of the Gram matrix `g`, dropping directions whose
/// eigenvalue is below 1e-12 of the largest (they carry no ABRDF energy).
fn isometry(g: &[f64], n: usize) -> Result<(Vec<f64>, usize), SynthError> {
    let (vals, vecs) = sym_eigen_desc(g, n)?;
    let top = vals.first().copied().unwrap_or(0.0).max(0.0);
    let r = vals.iter().take_while(|&&l| l > 1e-12 * top && l > 0.0).count().max(1);
    let mut m = Vec::with_capacity(r * n);
    for i in 0..r {
        let s = vals[i].max(0.0).sqrt();
        m.extend(vecs[i * n..(i + 1) * n].iter().map(|&q| s * q));
    }
    Ok((m, r))
}

/// Gram matrix `B·Bᵀ` of `n` row-major rows of length `d` (each entry one sequential f64
/// sum; rows in parallel).
fn gram_rows(b: &[f32], n: usize, d: usize) -> Vec<f64> {
    let rows: Vec<Vec<f64>> = (0..n)
        .into_par_iter()
        .map(|i| {
            let ri = &b[i * d..(i + 1) * d];
            (0..n)
                .map(|j| {
                    let rj = &b[j * d..(j + 1) * d];
                    ri.iter().zip(rj).map(|(&x, &y)| x as f64 * y as f64).sum()
                })
                .collect()
        })
        .collect();
    rows.concat()
}

/// Gram matrix `Vᵀ·V` of a row-major `rows × c` block.
fn gram_cols(v: &[f32], c: usize) -> Vec<f64> {
    let mut g = vec![0f64; c * c];
    for row in v.chunks_exact(c) {
        for a in 0..c {
            for b in 0..c {
                g[a * c + b] += row[a] as f64 * row[b] as f64;
            }
        }
    }
    g
}

/// `out[i] = Σ_j m[i, j] · w[j]` for `r × n` row-major `m`.
fn apply(m: &[f64], r: usize, n: usize, w: &[f32], out: &mut [f32]) {
    for i in 0..r {
        let row = &m[i * n..(i + 1) * n];
        out[i] = row.iter().zip(w).map(|(&a, &b)| a * b as f64).sum::<f64>() as f32;
    }
}

/// Embed every texel of `model` (see the module docs).
pub fn embed(model: &CompressedBtf) -> Result<Embedding, SynthError> {
    let h = model.header();
    let (w, ht) = (h.width, h.height);
    let t = w * ht;
    let blocks = &model.gbtf.blocks;
    let (dims, data, kind) = match model.layout() {
        Layout::Basis => {
            let c = model.components();
            let (m, r) = isometry(&gram_cols(&blocks[1], c), c)?;
            let mut data = vec![0f32; t * r];
            data.par_chunks_mut(r)
                .zip(blocks[0].par_chunks(c))
                .for_each(|(z, u)| apply(&m, r, c, u, z));
            (r, data, "exact")
        }
        Layout::ViewBases => {
            let c = model.components();
            let nv = h.views_deg.len();
            let isos = (0..nv)
                .map(|v| isometry(&gram_cols(&blocks[2 * v + 1], c), c))
                .collect::<Result<Vec<_>, _>>()?;
            let dims: usize = isos.iter().map(|x| x.1).sum();
            let mut data = vec![0f32; t * dims];
            data.par_chunks_mut(dims).enumerate().for_each(|(i, z)| {
                let mut off = 0;
                for (v, (m, r)) in isos.iter().enumerate() {
                    apply(m, *r, c, &blocks[2 * v][i * c..(i + 1) * c], &mut z[off..off + r]);
                    off += r;
                }
            });
            (dims, data, "exact")
        }
        Layout::Clusters { clusters } => {
            let c = model.components();
            let d = h.lights_deg.len() * h.views_deg.len() * 3;
            let n = clusters * (c + 1);
            let mut b = Vec::with_capacity(n * d);
            b.extend_from_slice(&blocks[2]);
            b.extend_from_slice(&blocks[3]);
            let (m, r) = isometry(&gram_rows(&b, n, d), n)?;
            let (cluster, coef) = (&blocks[0], &blocks[1]);
            let mut data = vec![0f32; t * r];
            data.par_chunks_mut(r).enumerate().for_each(|(i, z)| {
                let k = cluster[i] as usize;
                for (a, zi) in z.iter_mut().enumerate() {
                    let row = &m[a * n..(a + 1) * n];
                    let mut s = row[k];
                    for (q, &wq) in coef[i * c..(i + 1) * c].iter().enumerate() {
                        s += row[clusters + k * c + q] * wq as f64;
                    }
                    *zi = s as f32;
                }
            });
            (r, data, "exact")
        }
        // DFMF stored as `.gbtf` (e.g. CIELab): the same factor embedding as a `.btf`.
        Layout::ChannelFactors => return embed_dfmf(&crate::compress::dfmf::from_gbtf(&model.gbtf)?),
        Layout::Index { boxes } => {
            let d = h.lights_deg.len() * h.views_deg.len() * 3;
            let (m, r) = isometry(&gram_rows(&blocks[1], boxes, d), boxes)?;
            let mut data = vec![0f32; t * r];
            data.par_chunks_mut(r).zip(&blocks[0]).for_each(|(z, &b)| {
                for (a, zi) in z.iter_mut().enumerate() {
                    *zi = m[a * boxes + b as usize] as f32;
                }
            });
            (r, data, "exact")
        }
        // Factors only the method's decoder reads: embed sampled decoded images.
        Layout::HalfVectorTables { .. } | Layout::PerTexel | Layout::AnalyticPerTexel => {
            let (nl, nv) = (h.lights_deg.len(), h.views_deg.len());
            let total = nl * nv;
            let n = total.min(SAMPLED_PAIRS);
            let pairs: Vec<(usize, usize)> = (0..n).map(|i| i * total / n).map(|p| (p % nl, p / nl)).collect();
            let scale = (total as f64 / n as f64).sqrt() as f32;
            let images = pairs
                .par_iter()
                .map(|&(l, v)| BtfModel::reconstruct(model, l, v))
                .collect::<Result<Vec<_>, _>>()?;
            let dims = n * 3;
            let mut data = vec![0f32; t * dims];
            data.par_chunks_mut(dims).enumerate().for_each(|(i, z)| {
                for (p, img) in images.iter().enumerate() {
                    for ch in 0..3 {
                        z[p * 3 + ch] = scale * img[i * 3 + ch];
                    }
                }
            });
            (dims, data, "sampled")
        }
    };
    Ok(Embedding {
        image: FeatureImage {
            width: w,
            height: ht,
            dims,
            data,
        },
        kind,
    })
}

/// Embed every texel of a UBO2014 DFMF model (`.btf`) from its texel factors alone.
///
/// Channel `ch` of the file's colour space (R, G, B, or ln Y, U/Y, V/Y) is
/// `m_ch(r, t) = U_ch[r]·SxV_ch[t]` over the measurement rows `r`. With the Gram matrix
/// `G_ch = U_chᵀ·U_ch = Q·Λ·Qᵀ` (`c_ch × c_ch`), `z_t,ch = Λ^{1/2}·Qᵀ·SxV_ch[t]` gives
/// `‖z_s,ch − z_t,ch‖² = Σ_r (m_ch(r, s) − m_ch(r, t))²` exactly: the texel coefficients
/// weighted by the component scales (for an orthonormal `U`, as a truncated SVD gives,
/// `G = I` and `z` is the `S·V` row up to a rotation, which already carries the singular
/// values; a file whose `U` carries the scales is handled the same way). The three channels are
/// concatenated, so the distance is the L2 distance of the whole ABRDFs in the file's
/// colour space: for colour model RGB that is the decoded-ABRDF distance (kind `"exact"`);
/// for log-YUV (kind `"log-yuv"`) it is the distance in (ln Y, U/Y, V/Y), i.e. to first
/// order the decoded distance with each measurement weighted by 1/Y: relative luminance
/// differences plus chromaticity differences. That is the metric the factorization itself
/// was fitted in, it keeps specular peaks from dominating the matching, and it ignores the
/// reader's clamping of decoded RGB to [0, 1].
pub fn embed_dfmf(d: &Dfmf) -> Result<Embedding, SynthError> {
    d.validate()?;
    let t = d.texels();
    let rows = d.n_lights() * d.n_views();
    let isos = d
        .channels
        .iter()
        .map(|ch| {
            debug_assert_eq!(ch.u.len(), rows * ch.c);
            isometry(&gram_cols(&ch.u, ch.c), ch.c)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let dims: usize = isos.iter().map(|x| x.1).sum();
    let mut data = vec![0f32; t * dims];
    data.par_chunks_mut(dims).enumerate().for_each(|(i, z)| {
        let mut off = 0;
        for (ch, (m, r)) in d.channels.iter().zip(&isos) {
            apply(m, *r, ch.c, &ch.sxv[i * ch.c..(i + 1) * ch.c], &mut z[off..off + r]);
            off += r;
        }
    });
    Ok(Embedding {
        image: FeatureImage {
            width: d.width,
            height: d.height,
            dims,
            data,
        },
        kind: match d.color_model {
            ColorModel::Rgb => "exact",
            ColorModel::LogYuv => "log-yuv",
            ColorModel::Lab => "lab",
        },
    })
}

/// Mean and covariance (f64, row-major) of the rows of `f`, in a fixed summation order.
pub fn mean_cov(f: &FeatureImage) -> (Vec<f64>, Vec<f64>) {
    let d = f.dims;
    let n = f.width * f.height;
    let sums: Vec<Vec<f64>> = f
        .data
        .par_chunks(CHUNK * d)
        .map(|c| {
            let mut s = vec![0f64; d];
            for row in c.chunks_exact(d) {
                for (a, &v) in s.iter_mut().zip(row) {
                    *a += v as f64;
                }
            }
            s
        })
        .collect();
    let mut mean = vec![0f64; d];
    for s in &sums {
        for (a, b) in mean.iter_mut().zip(s) {
            *a += b;
        }
    }
    mean.iter_mut().for_each(|m| *m /= n.max(1) as f64);
    let parts: Vec<Vec<f64>> = f
        .data
        .par_chunks(CHUNK * d)
        .map(|c| {
            let rows = c.len() / d;
            let x = Mat::from_fn(rows, d, |i, j| c[i * d + j] as f64 - mean[j]);
            let mut g = Mat::<f64>::zeros(d, d);
            faer::linalg::matmul::matmul(
                g.as_mut(),
                faer::Accum::Replace,
                x.transpose(),
                x.as_ref(),
                1.0,
                Par::Seq,
            );
            (0..d * d).map(|k| g[(k / d, k % d)]).collect()
        })
        .collect();
    let mut cov = vec![0f64; d * d];
    for p in &parts {
        for (a, b) in cov.iter_mut().zip(p) {
            *a += b;
        }
    }
    cov.iter_mut().for_each(|v| *v /= n.max(1) as f64);
    (mean, cov)
}

/// The first `k` principal coordinates of the embedding (see the module docs).
pub fn principal(e: &FeatureImage, choice: KChoice) -> Result<Features, SynthError> {
    let d = e.dims;
    match choice {
        KChoice::Fixed(0) => {
            return Err(SynthError::Invalid(
                "--k 0: matching needs at least one feature per texel (use --k 1 or more, or --energy)".into(),
            ))
        }
        KChoice::Energy(x) if !(x > 0.0 && x <= 1.0) => {
            return Err(SynthError::Invalid(format!(
                "--energy {x}: the explained-variance fraction must be in (0, 1]"
            )))
        }
        _ => {}
    }
    let (mean, cov) = mean_cov(e);
    let (vals, vecs) = sym_eigen_desc(&cov, d)?;
    let total: f64 = vals.iter().map(|v| v.max(0.0)).sum();
    let explained: Vec<f64> = vals
        .iter()
        .map(|v| if total > 0.0 { v.max(0.0) / total } else { 0.0 })
        .collect();
    let k = match choice {
        KChoice::Fixed(k) => k.min(d),
        KChoice::Energy(x) => {
            if total <= 0.0 {
                1 // a uniform exemplar: one (constant) feature
            } else {
                let mut acc = 0.0;
                let mut k = 0;
                while k < d && acc < x - 1e-12 {
                    acc += explained[k];
                    k += 1;
                }
                k.max(1)
            }
        }
    };
    let n = e.width * e.height;
    let mut data = vec![0f32; n * k];
    data.par_chunks_mut(k).zip(e.data.par_chunks(d)).for_each(|(o, z)| {
        for (i, oi) in o.iter_mut().enumerate() {
            let v = &vecs[i * d..(i + 1) * d];
            *oi = v
                .iter()
                .zip(z)
                .zip(&mean)
                .map(|((&a, &b), &m)| a * (b as f64 - m))
                .sum::<f64>() as f32;
        }
    });
    Ok(Features {
        image: FeatureImage {
            width: e.width,
            height: e.height,
            dims: k,
            data,
        },
        explained,
    })
}

#[cfg(test)]
mod tests {
    use super::super::testutil;
    use super::*;
    use crate::compress::{compress, Method, Params};

    /// ABRDF of texel `t` decoded image by image.
    fn abrdf(m: &CompressedBtf, t: usize) -> Vec<f64> {
        let h = m.header();
        let mut out = Vec::new();
        for v in 0..h.views_deg.len() {
            for l in 0..h.lights_deg.len() {
                let img = m.reconstruct(l, v).unwrap();
                out.extend(img[t * 3..t * 3 + 3].iter().map(|&x| x as f64));
            }
        }
        out
    }

    #[test]
    fn the_embedding_is_an_isometry_for_every_linear_model() {
        let dir = tempfile::tempdir().unwrap();
        let ds = testutil::write_dataset(dir.path(), 8, 6, testutil::textured);
        for method in [
            Method::Pca,
            Method::Pvmf,
            Method::LocalPca {
                clusters: 3,
                iters: 4,
                subspace: 0,
                in_passes: false,
            },
            Method::MedianCut {
                boxes: 5,
                balanced: false,
                min_error_cut: false,
            },
        ] {
            let m = CompressedBtf::new(compress(&ds, &Params::new(method, 3)).unwrap().0).unwrap();
            let e = embed(&m).unwrap();
            assert_eq!(e.kind, "exact");
            let t = 8 * 6;
            let decoded: Vec<Vec<f64>> = (0..t).map(|i| abrdf(&m, i)).collect();
            for (a, b) in [(0, 1), (3, 17), (40, 2), (10, 47)] {
                let d_true: f64 = decoded[a]
                    .iter()
                    .zip(&decoded[b])
                    .map(|(x, y)| (x - y).powi(2))
                    .sum::<f64>()
                    .sqrt();
                let d_emb: f64 = e
                    .image
                    .texel(a)
                    .iter()
                    .zip(e.image.texel(b))
                    .map(|(&x, &y)| (x as f64 - y as f64).powi(2))
                    .sum::<f64>()
                    .sqrt();
                assert!(
                    (d_true - d_emb).abs() <= 1e-4 * (1.0 + d_true),
                    "{}: texels {a},{b}: {d_true} vs {d_emb}",
                    method.name()
                );
            }
        }
    }

    #[test]
    fn k_by_energy_and_bad_k() {
        let dir = tempfile::tempdir().unwrap();
        let ds = testutil::write_dataset(dir.path(), 8, 6, testutil::textured);
        let m = CompressedBtf::new(compress(&ds, &Params::new(Method::Pca, 4)).unwrap().0).unwrap();
        let e = embed(&m).unwrap();
        let all = principal(&e.image, KChoice::Energy(1.0)).unwrap();
        let some = principal(&e.image, KChoice::Energy(0.5)).unwrap();
        assert!(some.image.dims <= all.image.dims && some.image.dims >= 1);
        let s: f64 = all.explained.iter().sum();
        assert!((s - 1.0).abs() < 1e-9);
        assert!(all.explained.windows(2).all(|w| w[0] >= w[1] - 1e-12));
        let e0 = principal(&e.image, KChoice::Fixed(0)).unwrap_err().to_string();
        assert!(e0.contains("--k 0"), "{e0}");
        // Centred principal coordinates have zero mean.
        let f = principal(&e.image, KChoice::Fixed(2)).unwrap().image;
        let mean0: f64 = f.data.iter().step_by(2).map(|&v| v as f64).sum::<f64>() / (f.width * f.height) as f64;
        assert!(mean0.abs() < 1e-4);
    }

    /// DFMF: distances of the embedded texels are the L2 distances of the texels' whole
    /// ABRDFs in the file's colour space (computed here from the factors, row by row), and
    /// for the RGB model the distances of the decoded ABRDFs.
    #[test]
    fn the_dfmf_embedding_is_an_isometry_in_the_files_colour_space() {
        use crate::compress::dfmf::{self, ColorModel, DfmfParams};
        let dir = tempfile::tempdir().unwrap();
        let ds = testutil::write_dataset(dir.path(), 8, 6, testutil::textured);
        for model in [ColorModel::LogYuv, ColorModel::Rgb] {
            let mut d = dfmf::encode(&ds, &DfmfParams::new(model, 3)).unwrap().0;
            // A U that carries the scales (not orthonormal) must give the same distances.
            for ch in &mut d.channels {
                for (i, u) in ch.u.iter_mut().enumerate() {
                    *u *= 1.0 + (i % ch.c) as f32;
                }
            }
            let e = embed_dfmf(&d).unwrap();
            assert_eq!(e.kind, if model == ColorModel::Rgb { "exact" } else { "log-yuv" });
            let rows = d.n_lights() * d.n_views();
            let space = |t: usize| -> Vec<f64> {
                let mut v = Vec::new();
                for ch in &d.channels {
                    for r in 0..rows {
                        let s: f64 = (0..ch.c)
                            .map(|k| ch.u[r * ch.c + k] as f64 * ch.sxv[t * ch.c + k] as f64)
                            .sum();
                        v.push(s);
                    }
                }
                v
            };
            let decoded: Vec<Vec<f64>> = (0..48)
                .map(|t| {
                    let mut v = Vec::new();
                    for vi in 0..d.n_views() {
                        for l in 0..d.n_lights() {
                            let img = d.reconstruct(l, vi).unwrap();
                            v.extend(img[t * 3..t * 3 + 3].iter().map(|&x| x as f64));
                        }
                    }
                    v
                })
                .collect();
            let l2 = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>().sqrt();
            for (a, b) in [(0, 1), (3, 17), (40, 2), (10, 47)] {
                let d_emb: f64 = l2(
                    &e.image.texel(a).iter().map(|&x| x as f64).collect::<Vec<_>>(),
                    &e.image.texel(b).iter().map(|&x| x as f64).collect::<Vec<_>>(),
                );
                let d_space = l2(&space(a), &space(b));
                assert!(
                    (d_space - d_emb).abs() <= 1e-4 * (1.0 + d_space),
                    "{}: texels {a},{b}: {d_space} vs {d_emb}",
                    model.name()
                );
                if model == ColorModel::Rgb {
                    let d_dec = l2(&decoded[a], &decoded[b]);
                    assert!(
                        (d_dec - d_emb).abs() <= 1e-4 * (1.0 + d_dec),
                        "rgb decoded: {d_dec} vs {d_emb}"
                    );
                }
            }
        }
    }

    /// A DFMF `.gbtf` (here CIELab, gonio's own model) is embedded from its factors like a
    /// `.btf`, not by sampling pairs.
    #[test]
    fn a_dfmf_gbtf_uses_the_factor_embedding() {
        use crate::compress::dfmf::ColorModel;
        let dir = tempfile::tempdir().unwrap();
        let ds = testutil::write_dataset(dir.path(), 8, 6, testutil::textured);
        let method = Method::Dfmf {
            color_model: ColorModel::Lab,
            chroma_components: 2,
        };
        let m = CompressedBtf::new(compress(&ds, &Params::new(method, 3)).unwrap().0).unwrap();
        let e = embed(&m).unwrap();
        assert_eq!(e.kind, "lab");
        let direct = embed_dfmf(&crate::compress::dfmf::from_gbtf(&m.gbtf).unwrap()).unwrap();
        assert_eq!(e.image, direct.image);
        assert_eq!(e.image.dims, 3 + 2 + 2);
    }
}
