//! Normalized decomposition per ABRDF (ND, after Wynn; the thesis' per-ABRDF
//! factorizations). Every texel's ABRDF, one colour channel at a time, is the
//! `lights × views` matrix `M[l, v] = f(l, v)` ([`channel_matrix`]). ND splits it into two
//! factors, from the row norms and the column means of the row-normalized matrix:
//!
//! ```text
//! n(l) = ‖M[l, ·]‖₂                      (light factor: the row norms)
//! N(v) = mean over l with n(l) > 0 of M[l, v] / n(l)   (view factor)
//! f̂(l, v) = n(l) · N(v)
//! ```
//!
//! A row of zeros (a light that never lights the texel) has n(l) = 0, reconstructs as 0
//! and is left out of the mean (nothing is divided by zero). An ABRDF that is a product
//! `a(l) · b(v)` with `a ≥ 0` is reproduced exactly. Storage per texel:
//! 3 · (lights + views) f32, the same blocks as SVD-J with J = 1 (`light`: texels ×
//! lights·3, `view`: texels × views·3, decoded by [`super::abrdf::reconstruct_products`]).
//! Unlike the rank-1 SVD it needs no iteration or decomposition, one pass over the
//! ABRDF; the rank-1 SVD is its least-squares optimum.

use super::abrdf::{channel_matrix, encode_gbtf, product_terms, Abrdfs, ProductsDecoder, ABRDF_F32_BUDGET};
use super::container::{BlockInfo, Gbtf};
use super::data::DatasetViews;
use super::error::CompressError;
use super::params::{bad_file, Codec, CodecId, EncodeInfo, Knobs, Layout, Method, Opened, Params, Shard};
use rayon::prelude::*;
use std::sync::Arc;

/// The light factor `n` (`nl`) and view factor `N` (`nv`) of one channel matrix, in f64.
pub fn factor(m: faer::MatRef<'_, f64>) -> (Vec<f64>, Vec<f64>) {
    let (nl, nv) = (m.nrows(), m.ncols());
    let n: Vec<f64> = (0..nl)
        .map(|l| (0..nv).map(|v| m[(l, v)] * m[(l, v)]).sum::<f64>().sqrt())
        .collect();
    let rows: Vec<usize> = (0..nl).filter(|&l| n[l] > 0.0 && n[l].is_finite()).collect();
    let mut big_n = vec![0f64; nv];
    if !rows.is_empty() {
        for &l in &rows {
            for (v, x) in big_n.iter_mut().enumerate() {
                *x += m[(l, v)] / n[l];
            }
        }
        big_n.iter_mut().for_each(|x| *x /= rows.len() as f64);
    }
    (n, big_n)
}

/// ND of every texel of `a` (`nl` lights, `nv` views): the `light` and `view` blocks.
pub fn fit(a: &Abrdfs, nl: usize, nv: usize) -> Result<(Vec<f32>, Vec<f32>), CompressError> {
    if a.dims != nl * nv * 3 {
        return Err(CompressError::Invalid(format!(
            "nd: ABRDF length {} is not lights·views·3 = {}",
            a.dims,
            nl * nv * 3
        )));
    }
    let fits: Vec<(Vec<f32>, Vec<f32>)> = (0..a.texels)
        .into_par_iter()
        .map_init(
            || vec![0f32; a.dims],
            |row, t| {
                a.row(t, row);
                let (mut p, mut q) = (vec![0f32; nl * 3], vec![0f32; nv * 3]);
                for ch in 0..3 {
                    let (n, big_n) = factor(channel_matrix(row, nl, nv, ch).as_ref());
                    for (l, x) in n.iter().enumerate() {
                        p[l * 3 + ch] = *x as f32;
                    }
                    for (v, x) in big_n.iter().enumerate() {
                        q[v * 3 + ch] = *x as f32;
                    }
                }
                (p, q)
            },
        )
        .collect();
    let (mut light, mut view) = (
        Vec::with_capacity(a.texels * nl * 3),
        Vec::with_capacity(a.texels * nv * 3),
    );
    for (p, q) in fits {
        light.extend_from_slice(&p);
        view.extend_from_slice(&q);
    }
    Ok((light, view))
}

/// `gonio compress --method nd`.
pub fn compress(ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
    if params.method != Method::Nd {
        return Err(CompressError::Invalid("nd::compress called for another method".into()));
    }
    let (nl, nv) = (ds.n_lights(), ds.n_views());
    let a = Abrdfs::load(ds, ABRDF_F32_BUDGET)?;
    let (light, view) = fit(&a, nl, nv)?;
    let t = a.texels;
    let blocks = vec![
        (BlockInfo::new("light", t, nl * 3), light),
        (BlockInfo::new("view", t, nv * 3), view),
    ];
    Ok(encode_gbtf(ds, params, &a, blocks, &[("terms", 1.into())]))
}

/// ND in the registry (`super::registry`).
pub struct NdCodec;

impl Codec for NdCodec {
    fn id(&self) -> CodecId {
        CodecId::Nd
    }
    fn ladder(&self, knobs: &Knobs) -> Vec<Vec<Params>> {
        vec![vec![knobs.params(Method::Nd, 1)]]
    }
    fn shard(&self, _: &Knobs) -> Shard {
        Shard::No
    }
    fn encode(&self, ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
        compress(ds, params)
    }
    fn open(&self, g: &Gbtf) -> Result<Opened, CompressError> {
        let j = product_terms(&g.header)?;
        if j != 1 {
            return Err(bad_file(g, format!("{j} terms per ABRDF, ND stores one")));
        }
        Ok(Opened {
            method: Method::Nd,
            components: j,
            layout: Layout::PerTexel,
            decoder: Arc::new(ProductsDecoder { j }),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compress::testdata::{self, hash, max_err, round_trip};

    /// A product `a(l) · b(v)` per texel and channel (a ≥ 0) is reproduced exactly (up
    /// to the half-float images), through the container; a full-rank ABRDF is not.
    #[test]
    fn separable_abrdfs_round_trip_exactly() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), |l, v, t, c| {
            (0.2 + hash(t, l * 3 + c)) * (0.1 + 0.5 * hash(t + 50, v * 3 + c))
        });
        let (g, m) = round_trip(&ds, &Params::new(Method::Nd, 1), &tmp.path().join("a.gbtf"));
        assert_eq!(g.header.method, "nd");
        let e = max_err(&ds, &m);
        assert!(e < 1e-3, "separable: max error {e}");
        let ds2 = testdata::write(&tmp.path().join("ds2"), |l, v, t, c| {
            0.05 + 0.6 * hash(t * 3 + c, l * 7 + v)
        });
        let (_, m2) = round_trip(&ds2, &Params::new(Method::Nd, 1), &tmp.path().join("b.gbtf"));
        assert!(max_err(&ds2, &m2) > 0.05, "full rank is not a product");
    }

    /// Zero rows (a light that never reaches the texel) and black texels: no division
    /// by zero, finite factors, black stays black.
    #[test]
    fn zero_rows_stay_finite_and_black() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), |l, v, t, c| {
            if t == 3 || l == 1 {
                0.0
            } else {
                0.1 + 0.5 * hash(t, l * 3 + c) * hash(t + 1, v)
            }
        });
        let (g, m) = round_trip(&ds, &Params::new(Method::Nd, 1), &tmp.path().join("a.gbtf"));
        assert!(g.blocks.iter().flatten().all(|v| v.is_finite()));
        for v in 0..ds.n_views() {
            let img = m.reconstruct(1, v).unwrap();
            assert!(img.iter().all(|&x| x == 0.0), "unlit light stays 0");
            let img = m.reconstruct(0, v).unwrap();
            assert!(img[9..12].iter().all(|&x| x == 0.0), "black texel stays black");
        }
    }

    /// f32 against f64 of the ND formulas on one ABRDF channel with a dynamic range of
    /// 1e6 (a highlight over a dark base): the relative difference of the factors.
    #[test]
    fn f32_versus_f64() {
        let (nl, nv) = (81, 81);
        for range in [1e2f64, 1e6, 1e12, 1e22] {
            let m = faer::Mat::from_fn(nl, nv, |l, v| {
                let base = 0.01 + 0.02 * hash(l, v) as f64;
                if l == v {
                    base * range
                } else {
                    base
                }
            });
            let (n, big_n) = factor(m.as_ref());
            // The same formulas in f32.
            let m32: Vec<f32> = (0..nl * nv).map(|i| m[(i / nv, i % nv)] as f32).collect();
            let n32: Vec<f32> = (0..nl)
                .map(|l| m32[l * nv..(l + 1) * nv].iter().map(|x| x * x).sum::<f32>().sqrt())
                .collect();
            let mut q32 = vec![0f32; nv];
            for l in 0..nl {
                for v in 0..nv {
                    q32[v] += m32[l * nv + v] / n32[l];
                }
            }
            q32.iter_mut().for_each(|x| *x /= nl as f32);
            let rel = |a: &[f64], b: &[f32]| {
                a.iter()
                    .zip(b)
                    .map(|(x, y)| ((*y as f64 - x) / x.abs().max(1e-300)).abs())
                    .fold(0f64, f64::max)
            };
            let (en, eq) = (rel(&n, &n32), rel(&big_n, &q32));
            println!("dynamic range {range:.0e}: f32 relative error light {en:.1e}, view {eq:.1e}");
            assert!(n.iter().chain(&big_n).all(|x| x.is_finite()));
            if range <= 1e6 {
                assert!(en < 1e-5 && eq < 1e-5, "range {range}: {en} {eq}");
            }
        }
    }
}
