//! PVMF (Sattler, Sarlette, Klein 2003): per view, the best rank-`c` approximation of the
//! `texels × (lights · 3)` view matrix in the Frobenius norm (no mean subtracted), by the
//! Gram path ([`gram_truncated`]) or, when that is ill-conditioned, the QR + SVD path
//! ([`truncated_svd`]). Stored blocks (`.gbtf`, f32): per view `us{v}` (texels × c) and
//! `v{v}` (lights·3 × c).

use super::container::{BlockInfo, Gbtf};
use super::data::DatasetViews;
use super::error::CompressError;
use super::linalg::{basis_times_rows, gram_truncated, row_major_f32, truncated_svd};
use super::params::{
    check_basis_blocks, header_for, Codec, CodecId, Decode, EncodeInfo, Knobs, Layout, Method, Opened, Params, Shard,
    Stage,
};
use std::sync::Arc;

/// PVMF. The reader runs on its own thread one view ahead of the factorization (bounded
/// channel of one matrix), so decoding view `k + 1`'s EXRs overlaps with factorizing
/// view `k`; both use the rayon pool, so on a small machine this fills the gaps of each
/// stage rather than doubling the throughput. At most three view matrices (f64, 127 MiB
/// each at 256² × 243) are alive at once.
pub fn compress(ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
    compress_views(ds, params, 0..ds.n_views())
}

/// [`compress`] for the views `views` only (one shard of `gonio compress --shard`): each
/// view is factorized on its own, so the shards' blocks are exactly the whole run's.
pub fn compress_views(
    ds: &DatasetViews,
    params: &Params,
    views: std::ops::Range<usize>,
) -> Result<(Gbtf, EncodeInfo), CompressError> {
    use std::sync::mpsc::sync_channel;
    use std::time::Instant;
    let c = params.components;
    let (t, cols, nv) = (ds.texels(), ds.n_lights() * 3, views.len());
    let mut blocks = Vec::with_capacity(2 * nv);
    let mut infos = Vec::with_capacity(2 * nv);
    let mut filled = Vec::new();
    let (mut wait_s, mut factor_s, mut gram_views, mut svd_views) = (0.0, 0.0, 0usize, 0usize);
    std::thread::scope(|scope| -> Result<(), CompressError> {
        let (tx, rx) = sync_channel(1);
        let reader_views = views.clone();
        scope.spawn(move || {
            for v in reader_views {
                let r = ds.view_columns(v);
                let failed = r.is_err();
                // A closed channel means the factorization stopped (error): stop too.
                if tx.send(r).is_err() || failed {
                    break;
                }
            }
        });
        for v in views.clone() {
            let t0 = Instant::now();
            let (a, vf) = rx
                .recv()
                .map_err(|_| CompressError::Invalid(format!("PVMF reader thread ended before view {v}")))??;
            wait_s += t0.elapsed().as_secs_f64();
            filled.extend(vf.iter().map(|&(l, _)| [l, v]));
            let t1 = Instant::now();
            let (us, vv) = match gram_truncated(a.as_ref(), c)? {
                Some(f) => {
                    gram_views += 1;
                    f
                }
                None => {
                    svd_views += 1;
                    tracing::debug!(view = v, c, "PVMF: Gram matrix ill-conditioned, QR + SVD path");
                    truncated_svd(a.as_ref(), c)?
                }
            };
            drop(a);
            blocks.push(row_major_f32(us.as_ref()));
            infos.push(BlockInfo::new(format!("us{v}"), t, c));
            blocks.push(row_major_f32(vv.as_ref()));
            infos.push(BlockInfo::new(format!("v{v}"), cols, c));
            factor_s += t1.elapsed().as_secs_f64();
        }
        Ok(())
    })?;
    tracing::info!(wait_s, factor_s, gram_views, svd_views, "PVMF encoded");
    let stage = |name: &str, value: f64, unit| Stage {
        name: name.into(),
        value,
        unit,
    };
    let info = EncodeInfo {
        filled: filled.len(),
        passes: 1,
        stages: vec![
            stage("read_wait", wait_s, "s"),
            stage("factorize", factor_s, "s"),
            stage("gram_path", gram_views as f64, "views"),
            stage("svd_path", svd_views as f64, "views"),
        ],
    };
    let header = header_for(ds, params, filled, infos);
    Ok((Gbtf { header, blocks }, info))
}

/// PVMF in the registry (`super::registry`).
pub struct PvmfCodec;

impl Codec for PvmfCodec {
    fn id(&self) -> CodecId {
        CodecId::Pvmf
    }
    fn ladder(&self, knobs: &Knobs) -> Vec<Vec<Params>> {
        vec![[1, 2, 4, 8, 16].map(|c| knobs.params(Method::Pvmf, c)).to_vec()]
    }
    fn shard(&self, _: &Knobs) -> Shard {
        Shard::Views
    }
    fn encode(&self, ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
        compress(ds, params)
    }
    fn open(&self, g: &Gbtf) -> Result<Opened, CompressError> {
        let c = check_basis_blocks(g, |t, nl, nv, c| (0..nv).flat_map(|_| [(t, c), (nl * 3, c)]).collect())?;
        Ok(Opened {
            method: Method::Pvmf,
            components: c,
            layout: Layout::ViewBases,
            decoder: Arc::new(Decoder { c }),
        })
    }
}

/// Per view `v`: the texel basis (block `2v`) times the light's three rows of block `2v + 1`.
#[derive(Debug)]
struct Decoder {
    c: usize,
}

impl Decode for Decoder {
    fn reconstruct(&self, g: &Gbtf, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        let c = self.c;
        let vb = &g.blocks[2 * view + 1];
        Ok(basis_times_rows(
            &g.blocks[2 * view],
            &vb[light * 3 * c..(light * 3 + 3) * c],
            c,
        ))
    }
}
