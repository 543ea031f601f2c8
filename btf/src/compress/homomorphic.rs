//! Homomorphic factorization per ABRDF (McCool, Ang, Ahmad 2001).
//!
//! For every texel and colour channel the ABRDF `f(l, v)` is approximated as a product
//! of factors that each depend on one direction: the light, the view and (optionally)
//! the half vector `h = (l + v)/‖l + v‖`. Taking the logarithm turns the product into a
//! sum, which is fitted by linear least squares:
//!
//! ```text
//! y(l, v) = ln((max(f, 0) + ε·A) / A) ≈ P(l) + Q(v) + R(bin(θ_h))
//! f̂(l, v) = A · exp(P(l) + Q(v) + R(bin(θ_h))) − ε·A
//! ```
//!
//! with `A` the mean of the ABRDF channel and ε = [`EPSILON`] = 1e-5 as in the domain
//! notes: ε keeps zeros (shadowed or black measurements) finite under the logarithm
//! (they become ln ε ≈ −11.5, reconstructed as exactly 0 again), and dividing by `A`
//! makes ε relative to the texel's brightness. Negative inputs (sensor noise) are
//! clamped to 0 first; a channel whose mean is not positive is stored as all-zero.
//!
//! The factors are tables over the measured directions (`lights` entries for P,
//! `views` entries for Q) and over `half_bins` bins of the half vector's polar angle
//! θ_h ∈ [0°, 90°] (uniform). McCool et al. parametrize factors continuously over a
//! hemisphere map; on a fixed measurement grid the tables are the same least-squares
//! problem with one unknown per grid direction. The least-squares solution is found by
//! backfitting (Gauss–Seidel on the normal equations: each factor is in turn the mean
//! residual over the measurements that share its argument); with `half_bins = 0` the
//! first sweep is already the exact solution of the two-way additive model.
//!
//! Storage per texel: 3 · (1 + lights + views + half_bins) f32, with no shared data —
//! unlike PVMF there is no structure across texels, only within one ABRDF. Stored
//! blocks (`.gbtf`): `albedo` (texels × 3, the means A), `light` (texels × lights·3),
//! `view` (texels × views·3) and, if `half_bins > 0`, `half` (texels × half_bins·3);
//! column `direction · 3 + channel`.

use super::abrdf::{encode_gbtf, Abrdfs, ABRDF_F32_BUDGET};
use super::container::{BlockInfo, Gbtf, GbtfHeader};
use super::data::DatasetViews;
use super::error::CompressError;
use super::params::{Codec, CodecId, Decode, EncodeInfo, Knobs, Layout, Method, Opened, Params, Shard};
use rayon::prelude::*;
use std::sync::Arc;

/// ε under the logarithm, relative to the ABRDF channel's mean.
pub const EPSILON: f64 = 1e-5;

fn unit(d: [f64; 2]) -> [f64; 3] {
    let (t, p) = (d[0].to_radians(), d[1].to_radians());
    [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
}

/// Half-vector bin of every (light, view) pair, index `view · lights + light`.
pub fn half_bins_of(lights_deg: &[[f64; 2]], views_deg: &[[f64; 2]], bins: usize) -> Vec<u32> {
    let mut out = Vec::with_capacity(lights_deg.len() * views_deg.len());
    for &v in views_deg {
        for &l in lights_deg {
            if bins == 0 {
                out.push(0);
                continue;
            }
            let (a, b) = (unit(l), unit(v));
            let h = [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
            let n = (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).sqrt();
            // Opposite directions (n = 0) have no half vector: put them in the last bin.
            let theta = if n > 1e-12 {
                (h[2] / n).clamp(-1.0, 1.0).acos().to_degrees()
            } else {
                90.0
            };
            out.push(((theta / 90.0 * bins as f64).floor() as usize).min(bins - 1) as u32);
        }
    }
    out
}

/// Factors of one texel: albedo (3), P (nl·3), Q (nv·3), R (nh·3).
struct TexelFactors {
    albedo: [f32; 3],
    p: Vec<f32>,
    q: Vec<f32>,
    r: Vec<f32>,
}

/// Fit one ABRDF row (column `(view · nl + light) · 3 + ch`).
// The sweeps index a (light, view) grid and three factor tables at once; explicit
// indices say which is which better than zipped iterators.
#[allow(clippy::needless_range_loop)]
fn fit_texel(row: &[f32], nl: usize, nv: usize, bins: &[u32], nh: usize, sweeps: usize) -> TexelFactors {
    let mut out = TexelFactors {
        albedo: [0.0; 3],
        p: vec![0.0; nl * 3],
        q: vec![0.0; nv * 3],
        r: vec![0.0; nh * 3],
    };
    let n = nl * nv;
    let mut y = vec![0f64; n];
    let mut bin_count = vec![0usize; nh];
    for &b in bins {
        if nh > 0 {
            bin_count[b as usize] += 1;
        }
    }
    for ch in 0..3 {
        let a = (0..n).map(|i| row[i * 3 + ch].max(0.0) as f64).sum::<f64>() / n as f64;
        if a <= 0.0 || !a.is_finite() {
            continue; // all-zero channel: albedo 0 reconstructs 0 everywhere
        }
        out.albedo[ch] = a as f32;
        for (i, yi) in y.iter_mut().enumerate() {
            *yi = ((row[i * 3 + ch].max(0.0) as f64 + EPSILON * a) / a).ln();
        }
        let (mut p, mut q, mut r) = (vec![0f64; nl], vec![0f64; nv], vec![0f64; nh]);
        for _ in 0..sweeps.max(1) {
            p.iter_mut().for_each(|x| *x = 0.0);
            for v in 0..nv {
                for l in 0..nl {
                    let i = v * nl + l;
                    let rb = if nh > 0 { r[bins[i] as usize] } else { 0.0 };
                    p[l] += y[i] - q[v] - rb;
                }
            }
            p.iter_mut().for_each(|x| *x /= nv as f64);
            for v in 0..nv {
                let mut s = 0.0;
                for l in 0..nl {
                    let i = v * nl + l;
                    let rb = if nh > 0 { r[bins[i] as usize] } else { 0.0 };
                    s += y[i] - p[l] - rb;
                }
                q[v] = s / nl as f64;
            }
            if nh == 0 {
                break; // two-way additive model: one sweep is the exact least-squares fit
            }
            r.iter_mut().for_each(|x| *x = 0.0);
            for v in 0..nv {
                for l in 0..nl {
                    let i = v * nl + l;
                    r[bins[i] as usize] += y[i] - p[l] - q[v];
                }
            }
            for (x, &c) in r.iter_mut().zip(&bin_count) {
                if c > 0 {
                    *x /= c as f64;
                }
            }
        }
        for l in 0..nl {
            out.p[l * 3 + ch] = p[l] as f32;
        }
        for v in 0..nv {
            out.q[v * 3 + ch] = q[v] as f32;
        }
        for b in 0..nh {
            out.r[b * 3 + ch] = r[b] as f32;
        }
    }
    out
}

/// Fitted factors of all texels (row-major blocks as stored).
#[derive(Clone, Debug)]
pub struct Homomorphic {
    pub albedo: Vec<f32>,
    pub light: Vec<f32>,
    pub view: Vec<f32>,
    pub half: Vec<f32>,
}

/// Fit every texel of `a` (grid of `lights_deg` × `views_deg`).
pub fn fit(
    a: &Abrdfs,
    lights_deg: &[[f64; 2]],
    views_deg: &[[f64; 2]],
    half_bins: usize,
    sweeps: usize,
) -> Result<Homomorphic, CompressError> {
    let (nl, nv, nh) = (lights_deg.len(), views_deg.len(), half_bins);
    if a.dims != nl * nv * 3 {
        return Err(CompressError::Invalid(format!(
            "homomorphic: ABRDF length {} is not lights·views·3 = {}",
            a.dims,
            nl * nv * 3
        )));
    }
    let bins = half_bins_of(lights_deg, views_deg, nh);
    let fits: Vec<TexelFactors> = (0..a.texels)
        .into_par_iter()
        .map_init(
            || vec![0f32; a.dims],
            |row, t| {
                a.row(t, row);
                fit_texel(row, nl, nv, &bins, nh, sweeps)
            },
        )
        .collect();
    let mut h = Homomorphic {
        albedo: Vec::with_capacity(a.texels * 3),
        light: Vec::with_capacity(a.texels * nl * 3),
        view: Vec::with_capacity(a.texels * nv * 3),
        half: Vec::with_capacity(a.texels * nh * 3),
    };
    for f in fits {
        h.albedo.extend_from_slice(&f.albedo);
        h.light.extend_from_slice(&f.p);
        h.view.extend_from_slice(&f.q);
        h.half.extend_from_slice(&f.r);
    }
    Ok(h)
}

/// `gonio compress --method homomorphic`.
pub fn compress(ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
    let Method::Homomorphic { half_bins, sweeps } = params.method else {
        return Err(CompressError::Invalid(
            "homomorphic::compress called for another method".into(),
        ));
    };
    let a = Abrdfs::load(ds, ABRDF_F32_BUDGET)?;
    let m = fit(&a, &ds.lights_deg, &ds.views_deg, half_bins, sweeps)?;
    let t = a.texels;
    let mut infos = vec![
        BlockInfo::new("albedo", t, 3),
        BlockInfo::new("light", t, ds.n_lights() * 3),
        BlockInfo::new("view", t, ds.n_views() * 3),
    ];
    let mut blocks = vec![m.albedo, m.light, m.view];
    if half_bins > 0 {
        infos.push(BlockInfo::new("half", t, half_bins * 3));
        blocks.push(m.half);
    }
    let blocks = infos.into_iter().zip(blocks).collect();
    Ok(encode_gbtf(ds, params, &a, blocks, &[("epsilon", EPSILON.into())]))
}

/// Check block shapes; returns the number of half-vector bins.
pub fn validate(h: &GbtfHeader) -> Result<usize, CompressError> {
    let t = h.width * h.height;
    let (nl, nv) = (h.lights_deg.len(), h.views_deg.len());
    let got: Vec<(usize, usize)> = h.blocks.iter().map(|b| (b.rows, b.cols)).collect();
    let nh = match got.get(3) {
        Some(&(_, c)) if c % 3 == 0 && c > 0 => c / 3,
        _ => 0,
    };
    let mut want = vec![(t, 3), (t, nl * 3), (t, nv * 3)];
    if nh > 0 {
        want.push((t, nh * 3));
    }
    if got != want {
        return Err(CompressError::Invalid(format!(
            ".gbtf homomorphic: block shapes {got:?} do not match the header's grid"
        )));
    }
    Ok(nh)
}

/// The factor tables of a validated homomorphic file in direction-major order: for each
/// light (view, half-vector bin) the `texels × 3` values of all texels, contiguous.
///
/// Why: the file stores the factors texel-major (one ABRDF's tables together, which is
/// what fitting writes and what the container's per-texel layout documents), so decoding
/// one image from it gathers three values per texel from rows 81 · 3 floats apart: one
/// cache miss each, 6.19 ms per 256² image (idle machine; 1.94 ms with this layout).
/// Transposed once when the file is opened, an
/// image is three contiguous streams and one `exp` per value, split across the threads.
/// It costs a second copy of the tables in memory while the file is open. The arithmetic
/// is the file-layout decoder's ([`reconstruct`]), in the same order, so the images are
/// bit-identical (a test checks it).
#[derive(Clone, Debug, PartialEq)]
pub struct DirectionMajor {
    albedo: Vec<f32>,
    light: Vec<f32>,
    view: Vec<f32>,
    half: Vec<f32>,
    half_bins: usize,
}

impl DirectionMajor {
    /// Transpose the blocks of a file that passed [`validate`] (`half_bins` from it).
    pub fn new(g: &Gbtf, half_bins: usize) -> Self {
        let t = g.header.width * g.header.height;
        let transpose = |block: &[f32], dirs: usize| {
            let mut out = vec![0f32; dirs * t * 3];
            out.par_chunks_mut(t * 3).enumerate().for_each(|(d, plane)| {
                for (i, px) in plane.chunks_exact_mut(3).enumerate() {
                    px.copy_from_slice(&block[(i * dirs + d) * 3..(i * dirs + d) * 3 + 3]);
                }
            });
            out
        };
        DirectionMajor {
            albedo: g.blocks[0].clone(),
            light: transpose(&g.blocks[1], g.header.lights_deg.len()),
            view: transpose(&g.blocks[2], g.header.views_deg.len()),
            half: if half_bins > 0 {
                transpose(&g.blocks[3], half_bins)
            } else {
                Vec::new()
            },
            half_bins,
        }
    }

    /// Image (`light`, `view`), interleaved linear RGB; indices checked by the caller.
    pub fn reconstruct(&self, h: &GbtfHeader, light: usize, view: usize) -> Vec<f32> {
        let n = self.albedo.len();
        let (p, q) = (&self.light[light * n..][..n], &self.view[view * n..][..n]);
        let r = (self.half_bins > 0).then(|| {
            let bin = half_bins_of(&[h.lights_deg[light]], &[h.views_deg[view]], self.half_bins)[0] as usize;
            &self.half[bin * n..][..n]
        });
        let mut out = vec![0f32; n];
        const CHUNK: usize = 8192;
        out.par_chunks_mut(CHUNK).enumerate().for_each(|(k, o)| {
            let i0 = k * CHUNK;
            for (j, o) in o.iter_mut().enumerate() {
                let i = i0 + j;
                let a = self.albedo[i];
                if a <= 0.0 {
                    continue;
                }
                let mut s = p[i] + q[i];
                if let Some(r) = r {
                    s += r[i];
                }
                *o = (a * (s.exp() - EPSILON as f32)).max(0.0);
            }
        });
        out
    }
}

/// Reconstruct image (`light`, `view`) of a validated homomorphic file from its own
/// (texel-major) layout: the reference decoder; [`DirectionMajor`] is the fast one.
pub fn reconstruct(g: &Gbtf, nh: usize, light: usize, view: usize) -> Vec<f32> {
    let h = &g.header;
    let (nl, nv) = (h.lights_deg.len(), h.views_deg.len());
    let bin = if nh > 0 {
        half_bins_of(&[h.lights_deg[light]], &[h.views_deg[view]], nh)[0] as usize
    } else {
        0
    };
    let t = h.width * h.height;
    let mut out = vec![0f32; t * 3];
    for (i, px) in out.chunks_exact_mut(3).enumerate() {
        for (ch, o) in px.iter_mut().enumerate() {
            let a = g.blocks[0][i * 3 + ch];
            if a <= 0.0 {
                continue;
            }
            let mut s = g.blocks[1][(i * nl + light) * 3 + ch] + g.blocks[2][(i * nv + view) * 3 + ch];
            if nh > 0 {
                s += g.blocks[3][(i * nh + bin) * 3 + ch];
            }
            *o = (a * (s.exp() - EPSILON as f32)).max(0.0);
        }
    }
    out
}

/// Homomorphic factorization in the registry (`super::registry`).
pub struct HomomorphicCodec;

impl Codec for HomomorphicCodec {
    fn id(&self) -> CodecId {
        CodecId::Homomorphic
    }
    fn ladder(&self, knobs: &Knobs) -> Vec<Vec<Params>> {
        let method = Method::Homomorphic {
            half_bins: knobs.half_bins,
            sweeps: knobs.sweeps.unwrap_or(20),
        };
        vec![vec![knobs.params(method, 1)]]
    }
    fn shard(&self, _: &Knobs) -> Shard {
        Shard::No
    }
    fn encode(&self, ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
        compress(ds, params)
    }
    fn open(&self, g: &Gbtf) -> Result<Opened, CompressError> {
        let half_bins = validate(&g.header)?;
        Ok(Opened {
            method: Method::Homomorphic { half_bins, sweeps: 0 },
            components: 0,
            layout: Layout::HalfVectorTables { half_bins },
            decoder: Arc::new(DirectionMajor::new(g, half_bins)),
        })
    }
}

impl Decode for DirectionMajor {
    fn reconstruct(&self, g: &Gbtf, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        Ok(DirectionMajor::reconstruct(self, &g.header, light, view))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compress::testdata::{self, hash, max_err, round_trip};
    use crate::compress::{compress, evaluate, CompressedBtf};

    fn params(half_bins: usize) -> Params {
        Params::new(Method::Homomorphic { half_bins, sweeps: 30 }, 1)
    }

    /// The direction-major decoder gives the file-layout decoder's images bit for bit, on
    /// a fitted file and on a 64² file of arbitrary factors (more values than one decode
    /// chunk, some texels with a non-positive mean), with and without half-vector bins.
    #[test]
    fn direction_major_decoder_is_bit_identical_to_the_reference() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), |l, v, t, c| {
            0.1 + hash(t, c) * hash(t + 7, l * 3 + c) * (0.3 + hash(t + 9, v))
        });
        for bins in [0, 3] {
            let (g, m) = round_trip(&ds, &params(bins), &tmp.path().join("a.gbtf"));
            let mut big = g.clone();
            let (w, h) = (64, 64);
            big.header.width = w;
            big.header.height = h;
            let t = w * h;
            for (k, (info, block)) in big.header.blocks.iter_mut().zip(big.blocks.iter_mut()).enumerate() {
                info.rows = t;
                *block = (0..t * info.cols)
                    .map(|i| {
                        let x = hash(i, k + 40);
                        if k == 0 {
                            x - 0.1 // some means ≤ 0: decoded as 0
                        } else {
                            3.0 * x - 2.0
                        }
                    })
                    .collect();
            }
            let nh = validate(&big.header).unwrap();
            assert_eq!(nh, bins);
            let fast = DirectionMajor::new(&big, nh);
            let (nl, nv) = (g.header.lights_deg.len(), g.header.views_deg.len());
            for l in 0..nl {
                for v in 0..nv {
                    let a = reconstruct(&big, nh, l, v);
                    let b = fast.reconstruct(&big.header, l, v);
                    assert!(
                        a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
                        "64², {bins} bins, pair ({l}, {v}) differs"
                    );
                    let small = m.reconstruct(l, v).unwrap();
                    assert!(
                        small
                            .iter()
                            .zip(reconstruct(&g, nh, l, v))
                            .all(|(x, y)| x.to_bits() == y.to_bits()),
                        "fitted file, {bins} bins, pair ({l}, {v}) differs"
                    );
                }
            }
        }
    }

    #[test]
    fn separable_abrdfs_round_trip() {
        let tmp = tempfile::tempdir().unwrap();
        // f = a(t) · p_t(l) · q_t(v): a product of a light and a view factor per texel.
        let ds = testdata::write(&tmp.path().join("ds"), |l, v, t, c| {
            (0.2 + 0.3 * hash(t, c)) * (0.5 + hash(t + 100, l * 3 + c)) * (0.5 + hash(t + 200, v * 3 + c))
        });
        for bins in [0, 4] {
            let (_, m) = round_trip(&ds, &params(bins), &tmp.path().join("a.gbtf"));
            // Exact up to the half-float rounding of the stored images (values ≤ 1.2,
            // half an ulp ≤ 5e-4), which makes them not exactly separable.
            let e = max_err(&ds, &m);
            assert!(e < 1e-3, "{bins} half bins: max error {e}");
        }
    }

    #[test]
    fn half_vector_factor_captures_a_half_vector_lobe() {
        let tmp = tempfile::tempdir().unwrap();
        let (ls, vs) = (testdata::lights(), testdata::views());
        let bins = half_bins_of(&ls, &vs, 6);
        let ds = testdata::write(&tmp.path().join("ds"), |l, v, t, c| {
            let lobe = [1.0, 0.6, 0.3, 0.2, 0.1, 0.05][bins[v * ls.len() + l] as usize];
            (0.3 + 0.1 * hash(t, c)) * (0.6 + 0.4 * hash(t + 7, l)) * lobe
        });
        let rmse = |nh: usize| {
            let (g, _) = compress(&ds, &params(nh)).unwrap();
            evaluate(&ds, &CompressedBtf::new(g).unwrap())
                .unwrap()
                .stats
                .rmse_linear()
        };
        let (without, with) = (rmse(0), rmse(6));
        assert!(
            with < 1e-4 && without > 10.0 * with,
            "with θ_h factor {with}, without {without}"
        );
    }

    #[test]
    fn zeros_under_the_logarithm_stay_finite_and_zero() {
        let tmp = tempfile::tempdir().unwrap();
        // Half of the measurements are black (shadowed); one texel is black everywhere;
        // one channel of another texel is negative noise.
        let ds = testdata::write(&tmp.path().join("ds"), |l, v, t, c| {
            if t == 5 || (l + v) % 2 == 0 {
                0.0
            } else if t == 6 && c == 1 {
                -0.01
            } else {
                0.1 + 0.5 * hash(t, l * 3 + c) * hash(t + 1, v * 3 + c)
            }
        });
        let (g, m) = round_trip(&ds, &params(4), &tmp.path().join("a.gbtf"));
        assert!(g.blocks.iter().flatten().all(|v| v.is_finite()));
        for v in 0..4 {
            for l in 0..5 {
                let img = m.reconstruct(l, v).unwrap();
                assert!(img.iter().all(|x| x.is_finite() && *x >= 0.0));
                assert!(img[5 * 3..6 * 3].iter().all(|&x| x == 0.0), "black texel stays black");
                assert_eq!(img[6 * 3 + 1], 0.0, "negative input clamps to 0");
            }
        }
        // The black measurements (a checkerboard, which a product of a light and a view
        // factor cannot represent exactly) come back dark: ln ε pulls them far down.
        let img = m.reconstruct(0, 0).unwrap();
        assert!(img.iter().all(|&x| x < 5e-3), "{:?}", &img[..12]);
        assert!(max_err(&ds, &m) < 0.6);
    }

    /// Where homomorphic factorization wins and loses against PVMF at (about) equal
    /// storage, on a 9 × 9 grid of 16 × 16 texels. Prints the numbers.
    #[test]
    fn against_pvmf_at_equal_storage() {
        let tmp = tempfile::tempdir().unwrap();
        let ls: Vec<[f64; 2]> = (0..9)
            .map(|i| [10.0 + 7.0 * (i / 3) as f64, 120.0 * (i % 3) as f64])
            .collect();
        let vs: Vec<[f64; 2]> = (0..9)
            .map(|i| [5.0 + 8.0 * (i / 3) as f64, 40.0 + 120.0 * (i % 3) as f64])
            .collect();
        // Homomorphic (no half factor): 3 · (1 + 9 + 9) = 57 floats per texel; PVMF:
        // 9 · (256 + 27) · c floats in total → c = 57 · 256 / 2547 ≈ 5.7; compare c = 6.
        type Btf = Box<dyn Fn(usize, usize, usize, usize) -> f32>;
        let cases: [(&str, Btf); 2] = [
            (
                "per-texel separable lobes (every texel its own light and view factors)",
                Box::new(|l, v, t, c| {
                    (0.1 + 0.4 * hash(t, c)) * (0.2 + hash(t + 1000, l)) * (0.2 + hash(t + 2000, v * 3 + c))
                }),
            ),
            (
                "sum of two shared materials (rank 2 across texels, not a product)",
                Box::new(|l, v, t, c| {
                    let w = hash(t, 0);
                    w * (0.1 + 0.8 * hash(1, (v * 9 + l) * 3 + c))
                        + (1.0 - w) * (0.05 + 0.3 * hash(2, (v * 9 + l) * 3 + c))
                }),
            ),
        ];
        let mut wins = Vec::new();
        for (i, (name, f)) in cases.iter().enumerate() {
            let ds = testdata::write_grid(&tmp.path().join(format!("ds{i}")), 16, 16, &ls, &vs, f);
            let run = |p: Params| {
                let (g, _) = compress(&ds, &p).unwrap();
                let floats: usize = g.blocks.iter().map(|b| b.len()).sum();
                let ev = evaluate(&ds, &CompressedBtf::new(g).unwrap()).unwrap();
                (floats, ev.stats.rmse_linear(), ev.stats.mean_abs_8bit())
            };
            let hm = run(params(0));
            let pv = run(Params::new(Method::Pvmf, 6));
            println!(
                "{name}:\n  homomorphic {} floats, RMSE {:.5}, mean abs /255 {:.5}\n  PVMF c=6    {} floats, RMSE {:.5}, mean abs /255 {:.5}",
                hm.0, hm.1, hm.2, pv.0, pv.1, pv.2
            );
            assert!(
                (hm.0 as f64 / pv.0 as f64 - 1.0).abs() < 0.1,
                "storage {} vs {}",
                hm.0,
                pv.0
            );
            wins.push(hm.1 < pv.1);
        }
        assert_eq!(
            wins,
            vec![true, false],
            "homomorphic wins on separable lobes, loses on sums"
        );
    }
}
