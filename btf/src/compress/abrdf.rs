//! The ABRDF matrix shared by the methods on whole ABRDFs (local PCA, median cut,
//! homomorphic factorization): one row per texel, every measurement × 3 values, and the
//! frame their encoders share ([`encode_gbtf`]).
//!
//! **Memory.** The methods that need whole ABRDFs (local PCA, median cut, homomorphic
//! factorization) read the dataset once into an [`Abrdfs`] matrix. It is kept as f32
//! while it fits [`ABRDF_F32_BUDGET`] (64² × 19683 values: 308 MiB); larger datasets
//! (256² × 19683 = 4.8 GiB as f32) are kept as **8-bit sRGB codes of the value divided
//! by its column's maximum** (1.2 GiB at 256², plus one f32 scale per column). 8 bits of
//! sRGB is the precision the UBO2003 data were published in and what the error
//! statistics are computed on; the per-column scale keeps values above 1 (highlights).
//! All arithmetic runs on decoded blocks of a few hundred rows (≤ 32 MiB), so the peak
//! stays near the size of the code matrix.

use super::container::{BlockInfo, Gbtf};
use super::data::DatasetViews;
use super::error::CompressError;
use super::params::{header_for, Decode, EncodeInfo, Params};
use faer::MatRef;
use rayon::prelude::*;

/// Largest ABRDF matrix kept as f32; larger ones are kept as 8-bit sRGB codes.
pub const ABRDF_F32_BUDGET: usize = 1 << 30;

/// Rows decoded at a time (bounded to ~32 MiB of f32).
fn block_rows(dims: usize) -> usize {
    ((32usize << 20) / (dims.max(1) * 4)).clamp(1, 4096)
}

/// How the values are held (see the module docs, "Memory").
enum Store {
    F32(Vec<f32>),
    Srgb8 {
        codes: Vec<u8>,
        /// Per-column scale (the column's maximum).
        scale: Vec<f32>,
        /// sRGB code → linear value in [0, 1].
        lut: Box<[f32; 256]>,
    },
}

/// All ABRDFs of a dataset: `texels × dims`, dims = views · lights · 3, column
/// `(view · lights + light) · 3 + channel`.
pub struct Abrdfs {
    pub texels: usize,
    pub dims: usize,
    /// `[light, view]` pairs filled from the nearest measured light.
    pub filled: Vec<[usize; 2]>,
    store: Store,
}

/// The sRGB transfer function's inverse for an 8-bit code.
pub use gonio_devices::image::srgb8_to_linear as srgb_to_linear;

impl Abrdfs {
    /// Read the dataset once, view by view. f32 when `texels · dims · 4 ≤ budget`, else
    /// 8-bit sRGB codes with a per-column scale (see the module docs).
    pub fn load(ds: &DatasetViews, budget: usize) -> Result<Self, CompressError> {
        Self::load_views(ds, 0..ds.n_views(), keeps_f32(ds, budget))
    }

    /// The ABRDFs' columns of `views` only (column `(v − views.start) · lights · 3 + …`),
    /// kept as f32 if `exact`, else as 8-bit codes. A shard of a sharded local PCA holds
    /// its views this way; `exact` comes from [`keeps_f32`] of the whole dataset, and a
    /// column's 8-bit scale depends on that column alone, so every shard holds its columns
    /// as the single process holds them.
    pub fn load_views(ds: &DatasetViews, views: std::ops::Range<usize>, exact: bool) -> Result<Self, CompressError> {
        let (t, lc) = (ds.texels(), ds.n_lights() * 3);
        let dims = lc * views.len();
        let mut filled = Vec::new();
        let mut f32s = if exact { vec![0f32; t * dims] } else { Vec::new() };
        let mut codes = if exact { Vec::new() } else { vec![0u8; t * dims] };
        let mut scale = if exact { Vec::new() } else { vec![0f32; dims] };
        for (i, v) in views.clone().enumerate() {
            let vm = ds.view_matrix(v)?;
            filled.extend(vm.filled.iter().map(|&(l, _)| [l, v]));
            let off = i * lc;
            if exact {
                f32s.par_chunks_mut(dims)
                    .zip(vm.data.par_chunks(lc))
                    .for_each(|(row, src)| row[off..off + lc].copy_from_slice(src));
            } else {
                for j in 0..lc {
                    let m = vm.data.chunks(lc).map(|r| r[j]).fold(0f32, f32::max);
                    scale[off + j] = if m > 0.0 { m } else { 1.0 };
                }
                let sc = &scale[off..off + lc];
                codes
                    .par_chunks_mut(dims)
                    .zip(vm.data.par_chunks(lc))
                    .for_each(|(row, src)| {
                        for ((o, &x), &s) in row[off..off + lc].iter_mut().zip(src).zip(sc) {
                            *o = gonio_dataset::store::linear_to_srgb8(x / s);
                        }
                    });
            }
        }
        let store = if exact {
            Store::F32(f32s)
        } else {
            let mut lut = Box::new([0f32; 256]);
            for (i, l) in lut.iter_mut().enumerate() {
                *l = srgb_to_linear(i as u8);
            }
            Store::Srgb8 { codes, scale, lut }
        };
        tracing::info!(texels = t, dims, exact, views = ?views, "ABRDF matrix loaded");
        Ok(Abrdfs {
            texels: t,
            dims,
            filled,
            store,
        })
    }

    /// Wrap an in-memory f32 matrix (row-major `texels × dims`).
    pub fn from_f32(texels: usize, dims: usize, data: Vec<f32>) -> Result<Self, CompressError> {
        if data.len() != texels * dims {
            return Err(CompressError::Invalid(format!(
                "ABRDF matrix {texels}×{dims} needs {} values, got {}",
                texels * dims,
                data.len()
            )));
        }
        if let Some(p) = data.iter().position(|v| !v.is_finite()) {
            return Err(CompressError::Invalid(format!(
                "ABRDF matrix: non-finite value {} at texel {}, column {}",
                data[p],
                p / dims.max(1),
                p % dims.max(1)
            )));
        }
        Ok(Abrdfs {
            texels,
            dims,
            filled: Vec::new(),
            store: Store::F32(data),
        })
    }

    /// Whether values are kept exactly (f32) rather than as 8-bit codes.
    pub fn is_exact(&self) -> bool {
        matches!(self.store, Store::F32(_))
    }

    /// Bytes held by the matrix.
    pub fn bytes(&self) -> usize {
        match &self.store {
            Store::F32(d) => d.len() * 4,
            Store::Srgb8 { codes, scale, .. } => codes.len() + scale.len() * 4,
        }
    }

    /// Decode row `t` into `out` (length `dims`).
    pub fn row(&self, t: usize, out: &mut [f32]) {
        let d = self.dims;
        match &self.store {
            Store::F32(v) => out.copy_from_slice(&v[t * d..(t + 1) * d]),
            Store::Srgb8 { codes, scale, lut } => {
                for ((o, &c), &s) in out.iter_mut().zip(&codes[t * d..(t + 1) * d]).zip(scale) {
                    *o = lut[c as usize] * s;
                }
            }
        }
    }

    /// One value.
    pub fn value(&self, t: usize, j: usize) -> f32 {
        match &self.store {
            Store::F32(v) => v[t * self.dims + j],
            Store::Srgb8 { codes, scale, lut } => lut[codes[t * self.dims + j] as usize] * scale[j],
        }
    }

    /// Decode `rows` into the row-major `buf` (resized), subtracting `mean` if given.
    pub fn decode_rows(&self, rows: &[u32], mean: Option<&[f32]>, buf: &mut Vec<f32>) {
        buf.resize(rows.len() * self.dims, 0.0);
        buf.par_chunks_mut(self.dims.max(1))
            .zip(rows.par_iter())
            .for_each(|(out, &r)| {
                self.row(r as usize, out);
                if let Some(m) = mean {
                    for (o, &mm) in out.iter_mut().zip(m) {
                        *o -= mm;
                    }
                }
            });
    }

    /// Decode columns `cols` of `rows` (all rows if `None`) into the row-major `out`
    /// (resized to `rows × cols.len()`).
    pub fn decode_cols(&self, rows: Option<&[u32]>, cols: std::ops::Range<usize>, out: &mut Vec<f32>) {
        let (d, w) = (self.dims, cols.len());
        let n = rows.map_or(self.texels, |r| r.len());
        out.resize(n * w, 0.0);
        out.par_chunks_mut(w.max(1))
            .with_min_len(256)
            .enumerate()
            .for_each(|(i, o)| {
                let t = rows.map_or(i, |r| r[i] as usize);
                match &self.store {
                    Store::F32(v) => o.copy_from_slice(&v[t * d + cols.start..t * d + cols.end]),
                    Store::Srgb8 { codes, scale, lut } => {
                        for ((o, &c), &s) in o
                            .iter_mut()
                            .zip(&codes[t * d + cols.start..t * d + cols.end])
                            .zip(&scale[cols.clone()])
                        {
                            *o = lut[c as usize] * s;
                        }
                    }
                }
            });
    }

    /// Call `f(offset, block)` for consecutive blocks of `rows` (decoded, `mean`
    /// subtracted); `offset` is the position of the block's first row in `rows`.
    pub fn for_blocks(
        &self,
        rows: &[u32],
        mean: Option<&[f32]>,
        mut f: impl FnMut(usize, MatRef<'_, f32>) -> Result<(), CompressError>,
    ) -> Result<(), CompressError> {
        let bs = block_rows(self.dims);
        let mut buf = Vec::new();
        for (bi, chunk) in rows.chunks(bs).enumerate() {
            self.decode_rows(chunk, mean, &mut buf);
            f(bi * bs, MatRef::from_row_major_slice(&buf[..], chunk.len(), self.dims))?;
        }
        Ok(())
    }

    /// Mean (f64 accumulation) of `rows`.
    pub fn mean_of(&self, rows: &[u32]) -> Vec<f32> {
        let mut sum = vec![0f64; self.dims];
        let _ = self.for_blocks(rows, None, |_, b| {
            for i in 0..b.nrows() {
                for (s, &x) in sum.iter_mut().zip(b.row(i).iter()) {
                    *s += x as f64;
                }
            }
            Ok(())
        });
        let n = rows.len().max(1) as f64;
        sum.into_iter().map(|s| (s / n) as f32).collect()
    }
}

/// Whether the ABRDF matrix of `ds` is kept as f32 under `budget` bytes (else as 8-bit
/// codes): decided on the whole matrix, whichever views a process holds.
pub fn keeps_f32(ds: &DatasetViews, budget: usize) -> bool {
    let dims = ds.n_lights() * 3 * ds.n_views();
    ds.texels().saturating_mul(dims).saturating_mul(4) <= budget
}

/// Check that every texel's index block entry is an integer in `0..n`.
pub fn check_indices(idx: &[f32], n: usize, what: &str) -> Result<(), CompressError> {
    if let Some((t, v)) = idx
        .iter()
        .enumerate()
        .find(|(_, &v)| v.is_nan() || v < 0.0 || v.fract() != 0.0 || v as usize >= n)
    {
        return Err(CompressError::Invalid(format!(
            ".gbtf: {what} index {v} of texel {t} is not an integer in 0..{n}"
        )));
    }
    Ok(())
}

/// The `.gbtf` of an ABRDF method: the common header ([`header_for`]) with the method's
/// own `extra` entries and `abrdf_storage` (`f32` or `srgb8`) added to its parameters,
/// the blocks as given, and the encode report (one pass over the dataset).
pub fn encode_gbtf(
    ds: &DatasetViews,
    params: &Params,
    a: &Abrdfs,
    blocks: Vec<(BlockInfo, Vec<f32>)>,
    extra: &[(&str, serde_json::Value)],
) -> (Gbtf, EncodeInfo) {
    let header = header_for(ds, params, Vec::new(), Vec::new());
    let g = abrdf_gbtf(header, a.filled.clone(), blocks, extra, a.is_exact());
    let info = EncodeInfo {
        filled: a.filled.len(),
        passes: 1,
        ..Default::default()
    };
    (g, info)
}

/// The `.gbtf` of an ABRDF method from the common header: its filled pairs and blocks,
/// the method's `extra` parameters, then `abrdf_storage` (`f32` if `exact`, else
/// `srgb8`). The merge of a sharded local PCA builds its file here too, so both files
/// have the same bytes.
pub fn abrdf_gbtf(
    mut header: super::container::GbtfHeader,
    filled: Vec<[usize; 2]>,
    blocks: Vec<(BlockInfo, Vec<f32>)>,
    extra: &[(&str, serde_json::Value)],
    exact: bool,
) -> Gbtf {
    let (infos, blocks): (Vec<BlockInfo>, Vec<Vec<f32>>) = blocks.into_iter().unzip();
    header.filled = filled;
    header.blocks = infos;
    if let Some(o) = header.params.as_object_mut() {
        o.shift_remove("abrdf_storage");
        for (k, v) in extra {
            o.insert((*k).into(), v.clone());
        }
        o.insert("abrdf_storage".into(), if exact { "f32" } else { "srgb8" }.into());
    }
    Gbtf { header, blocks }
}

/// One colour channel of an ABRDF row (column `(view · nl + light) · 3 + ch`) as the
/// `nl × nv` matrix `M[light, view]` in f64: what the per-ABRDF matrix factorizations
/// (ND, SVD-J) factorize.
pub fn channel_matrix(row: &[f32], nl: usize, nv: usize, ch: usize) -> faer::Mat<f64> {
    faer::Mat::from_fn(nl, nv, |l, v| row[(v * nl + l) * 3 + ch] as f64)
}

/// Shapes of a per-texel product file (ND, SVD-J): blocks `light` (texels × nl·J·3) and
/// `view` (texels × nv·J·3), column `(direction · J + j) · 3 + channel`. Returns J.
pub fn product_terms(h: &super::container::GbtfHeader) -> Result<usize, CompressError> {
    let t = h.width * h.height;
    let (nl, nv) = (h.lights_deg.len(), h.views_deg.len());
    let got: Vec<(usize, usize)> = h.blocks.iter().map(|b| (b.rows, b.cols)).collect();
    let j = match got.first() {
        Some(&(_, c)) if nl > 0 && c % (nl * 3) == 0 => c / (nl * 3),
        _ => 0,
    };
    if j == 0 || got != [(t, nl * j * 3), (t, nv * j * 3)] {
        return Err(CompressError::Invalid(format!(
            ".gbtf {}: block shapes {got:?} do not match the header's grid ({t} texels, \
             {nl} lights, {nv} views, J terms)",
            h.method
        )));
    }
    Ok(j)
}

/// Image (`light`, `view`) of a per-texel product file whose shapes passed
/// [`product_terms`] (J terms): per texel and channel `Σ_j P[light, j] · Q[view, j]`, the
/// sum in order of `j`. Interleaved linear RGB.
pub fn reconstruct_products(g: &Gbtf, j: usize, light: usize, view: usize) -> Vec<f32> {
    products_image(&g.header, &g.blocks[0], &g.blocks[1], j, light, view)
}

/// Write one channel's rank-`k` factors (`us`: lights × k, `vv`: views × k) into a texel's
/// `light` row `p` and `view` row `q`, column `(direction · k + j) · 3 + ch`: the layout
/// [`products_image`] reads (SVD-J, CMF's residual).
pub fn put_terms(p: &mut [f32], q: &mut [f32], us: faer::MatRef<'_, f64>, vv: faer::MatRef<'_, f64>, ch: usize) {
    let k = us.ncols();
    for j in 0..k {
        for l in 0..us.nrows() {
            p[(l * k + j) * 3 + ch] = us[(l, j)] as f32;
        }
        for v in 0..vv.nrows() {
            q[(v * k + j) * 3 + ch] = vv[(v, j)] as f32;
        }
    }
}

/// [`reconstruct_products`] from the `light` block `pb` and `view` block `qb` wherever
/// they sit in the file (CMF keeps them after its half/difference blocks).
pub fn products_image(
    h: &super::container::GbtfHeader,
    pb: &[f32],
    qb: &[f32],
    j: usize,
    light: usize,
    view: usize,
) -> Vec<f32> {
    let (nl, nv) = (h.lights_deg.len(), h.views_deg.len());
    let t = h.width * h.height;
    let mut out = vec![0f32; t * 3];
    out.par_chunks_mut(3).enumerate().for_each(|(i, px)| {
        let p = &pb[(i * nl + light) * j * 3..][..j * 3];
        let q = &qb[(i * nv + view) * j * 3..][..j * 3];
        for (ch, o) in px.iter_mut().enumerate() {
            let mut s = 0f32;
            for k in 0..j {
                s += p[k * 3 + ch] * q[k * 3 + ch];
            }
            *o = s;
        }
    });
    out
}

/// [`reconstruct_products`] of a file with `j` terms per ABRDF (ND and SVD-J).
#[derive(Debug)]
pub struct ProductsDecoder {
    pub j: usize,
}

impl Decode for ProductsDecoder {
    fn reconstruct(&self, g: &Gbtf, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        Ok(reconstruct_products(g, self.j, light, view))
    }
}
