//! SVD with J terms per ABRDF (the thesis' per-ABRDF factorizations): every texel's
//! ABRDF, one colour channel at a time, is the `lights × views` matrix
//! `M[l, v] = f(l, v)` ([`channel_matrix`]), approximated by its best rank-`J`
//! approximation in the Frobenius norm (Eckart–Young), computed by a thin SVD in f64
//! ([`truncated_svd`]):
//!
//! ```text
//! f̂(l, v) = Σ_{j<J} (U·S)[l, j] · V[v, j]
//! ```
//!
//! No structure across texels is used, only within one ABRDF. J = min(lights, views)
//! reproduces the ABRDF exactly (up to f32 storage). Storage per texel:
//! 3 · J · (lights + views) f32. Stored blocks (`.gbtf`): `light` (texels × lights·J·3,
//! `U·S`) and `view` (texels × views·J·3, `V`), column `(direction · J + j) · 3 + channel`
//! ([`reconstruct_products`] decodes them).

use super::abrdf::{channel_matrix, encode_gbtf, product_terms, put_terms, Abrdfs, ProductsDecoder, ABRDF_F32_BUDGET};
use super::container::{BlockInfo, Gbtf};
use super::data::DatasetViews;
use super::error::CompressError;
use super::linalg::truncated_svd;
use super::params::{Codec, CodecId, EncodeInfo, Knobs, Layout, Method, Opened, Params, Shard};
use rayon::prelude::*;
use std::sync::Arc;

/// Factor blocks of all texels (row-major, as stored).
pub struct Products {
    pub light: Vec<f32>,
    pub view: Vec<f32>,
}

/// One texel's `light` and `view` rows.
type TexelFactors = (Vec<f32>, Vec<f32>);

/// Rank-`j` factorization of every texel's ABRDF channel matrices (`nl` lights, `nv` views).
pub fn fit(a: &Abrdfs, nl: usize, nv: usize, j: usize) -> Result<Products, CompressError> {
    if a.dims != nl * nv * 3 {
        return Err(CompressError::Invalid(format!(
            "svd-j: ABRDF length {} is not lights·views·3 = {}",
            a.dims,
            nl * nv * 3
        )));
    }
    let max = nl.min(nv);
    if j == 0 || j > max {
        return Err(CompressError::Invalid(format!(
            "svd-j: -c {j} terms per ABRDF; must be 1..={max} (the rank of a {nl} × {nv} ABRDF matrix)"
        )));
    }
    let fits: Vec<Result<TexelFactors, CompressError>> = (0..a.texels)
        .into_par_iter()
        .map_init(
            || vec![0f32; a.dims],
            |row, t| {
                a.row(t, row);
                let (mut p, mut q) = (vec![0f32; nl * j * 3], vec![0f32; nv * j * 3]);
                for ch in 0..3 {
                    let m = channel_matrix(row, nl, nv, ch);
                    let (us, vv) = truncated_svd(m.as_ref(), j)?;
                    put_terms(&mut p, &mut q, us.as_ref(), vv.as_ref(), ch);
                }
                Ok((p, q))
            },
        )
        .collect();
    let mut out = Products {
        light: Vec::with_capacity(a.texels * nl * j * 3),
        view: Vec::with_capacity(a.texels * nv * j * 3),
    };
    for f in fits {
        let (p, q) = f?;
        out.light.extend_from_slice(&p);
        out.view.extend_from_slice(&q);
    }
    Ok(out)
}

/// `gonio compress --method svd-j -c J`.
pub fn compress(ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
    if params.method != Method::SvdJ {
        return Err(CompressError::Invalid(
            "svd_j::compress called for another method".into(),
        ));
    }
    let (nl, nv, j) = (ds.n_lights(), ds.n_views(), params.components);
    if j == 0 || j > nl.min(nv) {
        return Err(CompressError::Invalid(format!(
            "svd-j: -c {j} terms per ABRDF; must be 1..={} (the rank of a {nl} × {nv} ABRDF matrix)",
            nl.min(nv)
        )));
    }
    let a = Abrdfs::load(ds, ABRDF_F32_BUDGET)?;
    let f = fit(&a, nl, nv, j)?;
    let t = a.texels;
    let blocks = vec![
        (BlockInfo::new("light", t, nl * j * 3), f.light),
        (BlockInfo::new("view", t, nv * j * 3), f.view),
    ];
    Ok(encode_gbtf(ds, params, &a, blocks, &[("terms", j.into())]))
}

/// SVD-J in the registry (`super::registry`).
pub struct SvdJCodec;

impl Codec for SvdJCodec {
    fn id(&self) -> CodecId {
        CodecId::SvdJ
    }
    fn ladder(&self, knobs: &Knobs) -> Vec<Vec<Params>> {
        vec![[1, 2, 4, 8].map(|c| knobs.params(Method::SvdJ, c)).to_vec()]
    }
    fn shard(&self, _: &Knobs) -> Shard {
        Shard::No
    }
    fn encode(&self, ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
        compress(ds, params)
    }
    fn open(&self, g: &Gbtf) -> Result<Opened, CompressError> {
        let j = product_terms(&g.header)?;
        Ok(Opened {
            method: Method::SvdJ,
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
    use crate::compress::{compress, evaluate, CompressedBtf};

    fn full_rank(l: usize, v: usize, t: usize, c: usize) -> f32 {
        0.05 + 0.6 * hash(t * 3 + c, l * 7 + v)
    }

    /// J = min(lights, views) reproduces every ABRDF (up to f32 storage); the error
    /// falls with J; J = 1 is never worse than ND (the rank-1 SVD is the least-squares
    /// optimum among products ND is one of).
    #[test]
    fn full_rank_is_exact_and_error_falls_with_j() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), full_rank);
        let (nl, nv) = (ds.n_lights(), ds.n_views());
        let mut last = f32::INFINITY;
        for j in 1..=nl.min(nv) {
            let (g, m) = round_trip(&ds, &Params::new(Method::SvdJ, j), &tmp.path().join("a.gbtf"));
            assert_eq!(g.blocks[0].len(), ds.texels() * nl * j * 3);
            let e = max_err(&ds, &m);
            assert!(e < last, "J = {j}: max error {e} not below J − 1's {last}");
            last = e;
        }
        assert!(last < 1e-5, "full rank: max error {last}");
        let rmse = |p: Params| {
            let (g, _) = compress(&ds, &p).unwrap();
            evaluate(&ds, &CompressedBtf::new(g).unwrap())
                .unwrap()
                .stats
                .rmse_linear()
        };
        let (svd1, nd) = (rmse(Params::new(Method::SvdJ, 1)), rmse(Params::new(Method::Nd, 1)));
        assert!(svd1 <= nd * (1.0 + 1e-6), "SVD J=1 RMSE {svd1} above ND's {nd}");
    }

    /// J = 0 and J above the ABRDF matrix's rank are refused, naming the range.
    #[test]
    fn bad_j_is_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), full_rank);
        let e = compress(&ds, &Params::new(Method::SvdJ, 0)).unwrap_err().to_string();
        assert!(e.contains("at least 1"), "{e}");
        let e = compress(&ds, &Params::new(Method::SvdJ, 5)).unwrap_err().to_string();
        assert!(e.contains("-c 5") && e.contains("1..=4"), "{e}");
    }

    /// f32 against f64: the same per-ABRDF SVD done in f32 on 81 × 81-like graded
    /// matrices. Prints where f32 leaves the optimum (see docs/guide/compression.md).
    #[test]
    fn f32_versus_f64_per_abrdf() {
        let (nl, nv) = (81, 81);
        for (decay, j) in [(0.5f64, 4usize), (0.5, 12), (0.2, 8), (0.1, 8)] {
            // M = Σ_k decay^k · u_k v_kᵀ with pseudo-random u, v: σ_k ≈ decay^k.
            let m = faer::Mat::from_fn(nl, nv, |l, v| {
                (0..20)
                    .map(|k| decay.powi(k as i32) * (hash(k, l) as f64 - 0.5) * (hash(k + 100, v) as f64 - 0.5))
                    .sum::<f64>()
            });
            let err = |us: &faer::Mat<f64>, vv: &faer::Mat<f64>| {
                let r = &m - us * vv.transpose();
                r.norm_l2()
            };
            let (us, vv) = truncated_svd(m.as_ref(), j).unwrap();
            let e64 = err(&us, &vv);
            let m32 = faer::Mat::<f32>::from_fn(nl, nv, |l, v| m[(l, v)] as f32);
            let svd = m32.thin_svd().unwrap();
            let (u, s, v) = (svd.U(), svd.S().column_vector(), svd.V());
            let us32 = faer::Mat::from_fn(nl, j, |i, k| (u[(i, k)] * s[k]) as f64);
            let vv32 = faer::Mat::from_fn(nv, j, |i, k| v[(i, k)] as f64);
            let e32 = err(&us32, &vv32);
            println!(
                "decay {decay}, J = {j}: σ_J+1/σ_1 ≈ {:.1e}, f32/f64 error {:.3}",
                decay.powi(j as i32),
                e32 / e64
            );
            assert!(e64.is_finite() && e32.is_finite());
            assert!(e32 >= e64 * (1.0 - 1e-6), "f32 below the optimum: {e32} < {e64}");
        }
    }
}
