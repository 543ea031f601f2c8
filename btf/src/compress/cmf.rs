//! GSHD and chained matrix factorization (CMF) per ABRDF: the thesis' per-ABRDF
//! factorizations in the half/difference parametrization (§3.5.3.2, §3.5.3.5, after Wynn
//! and Suykens et al. 2003). GSHD is the first link of CMF's chain, so both live here:
//! `--method gshd` stores the link alone, `--method cmf -c K` adds the residual's factors.
//!
//! **GSHD.** Per (light, view) pair the half vector `H = (L + V)/‖L + V‖` gets a frame by
//! Gram–Schmidt (`t` = the x axis made orthogonal to `H`, `s = H × t`) and the difference
//! vector is `D = (L·t, L·s, L·H)` (eq. 41). Each is binned by its polar and azimuth angle
//! (`theta_bins` θ bins over [0°, 90°] × `2·theta_bins` φ bins over [0°, 360°)), so every
//! texel's channel becomes a sparse matrix `M[h, d]` (eq. 61). GSHD fits the product
//! `f(l, v) ≈ G(h(l, v)) · E(d(l, v))` (eq. 43) to the measured pairs by alternating least
//! squares (`sweeps` sweeps, `E = 1` to start, so the first `G` is each half bin's mean):
//! the rank-1 factorization of a matrix with missing cells, which on a full grid would
//! be the SVD of eq. 62. A bin no pair falls into stays 0 and is never read.
//!
//! **CMF.** The GSHD product `F(l, v)` is divided out of the light × view matrix (the
//! residual `R = M / F`, eq. 63; where `|F|` is below 10⁻³ of the channel's mean the
//! residual is taken as 1, so nothing is divided by a near-zero) and `R` is approximated
//! by its rank-K SVD (eq. 64): `f̂ = F · Σ_k U[l, k] V[v, k]` (eq. 65, the four-factor
//! chain). K = min(lights, views) reproduces the ABRDF wherever `|F|` is not tiny.
//!
//! Storage per texel and channel: `G` and `E` (`theta_bins · 2·theta_bins` each), plus
//! `K · (lights + views)` for CMF. Blocks (`.gbtf`): `half` (texels × bins·3), `diff`
//! (texels × bins·3), and for CMF `light` (texels × lights·K·3) and `view` (texels ×
//! views·K·3), column `(bin · K + k) · 3 + channel` as SVD-J's
//! ([`super::abrdf::products_image`]).

use super::abrdf::{encode_gbtf, product_terms, products_image, put_terms, Abrdfs, ABRDF_F32_BUDGET};
use super::container::{BlockInfo, Gbtf, GbtfHeader};
use super::data::DatasetViews;
use super::error::CompressError;
use super::linalg::truncated_svd;
use super::params::{Codec, CodecId, Decode, EncodeInfo, Knobs, Layout, Method, Opened, Params, Shard};
use rayon::prelude::*;
use std::sync::Arc;

/// Largest accepted `theta_bins` (`--half-bins`): 64 × 128 bins per factor already exceed
/// the 6561 pairs of a Bonn ABRDF.
pub const MAX_THETA_BINS: usize = 64;

/// Residual cells where the GSHD product is below this fraction of the channel's mean
/// absolute value are taken as 1 (eq. 63 would divide by nearly zero).
const RESIDUAL_FLOOR: f64 = 1e-3;

fn unit(d: [f64; 2]) -> [f64; 3] {
    let (t, p) = (d[0].to_radians(), d[1].to_radians());
    [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn normalized(a: [f64; 3]) -> [f64; 3] {
    let n = dot(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

/// Bins per factor for `theta_bins` θ bins.
pub fn bins(theta_bins: usize) -> usize {
    theta_bins * 2 * theta_bins
}

fn bin_of(v: [f64; 3], theta_bins: usize) -> u32 {
    let nphi = 2 * theta_bins;
    let theta = v[2].clamp(-1.0, 1.0).acos();
    let tb = ((theta / std::f64::consts::FRAC_PI_2 * theta_bins as f64) as usize).min(theta_bins - 1);
    let phi = v[1].atan2(v[0]).rem_euclid(std::f64::consts::TAU);
    let pb = ((phi / std::f64::consts::TAU * nphi as f64) as usize).min(nphi - 1);
    (tb * nphi + pb) as u32
}

/// The (half, difference) bins of the pair (`light`, `view`) (degrees θ, φ).
pub fn pair_bins(light: [f64; 2], view: [f64; 2], theta_bins: usize) -> (u32, u32) {
    let (l, v) = (unit(light), unit(view));
    let h = normalized([l[0] + v[0], l[1] + v[1], l[2] + v[2]]);
    // Gram–Schmidt: the x axis (the y axis if H is along x) made orthogonal to H.
    let axis = if h[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let a = dot(axis, h);
    let t = normalized([axis[0] - a * h[0], axis[1] - a * h[1], axis[2] - a * h[2]]);
    let s = [
        h[1] * t[2] - h[2] * t[1],
        h[2] * t[0] - h[0] * t[2],
        h[0] * t[1] - h[1] * t[0],
    ];
    let d = [dot(l, t), dot(l, s), dot(l, h)];
    (bin_of(h, theta_bins), bin_of(d, theta_bins))
}

/// Bins of every grid pair, index `view · lights + light`.
pub(crate) fn grid_bins(lights: &[[f64; 2]], views: &[[f64; 2]], theta_bins: usize) -> Vec<(u32, u32)> {
    views
        .iter()
        .flat_map(|&v| lights.iter().map(move |&l| pair_bins(l, v, theta_bins)))
        .collect()
}

/// The float type the link is computed in: f64 in [`compress`], f32 only in the test
/// that measures what single precision would lose (`compress::tests::f32_versus_f64_gshd_and_cmf`).
pub(crate) trait Real:
    Copy
    + PartialOrd
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
    + std::ops::Div<Output = Self>
    + std::ops::AddAssign
    + std::ops::MulAssign
    + std::ops::DivAssign
{
    const ZERO: Self;
    const ONE: Self;
    fn of(x: f64) -> Self;
    fn sqrt(self) -> Self;
    fn is_finite(self) -> bool;
}

macro_rules! real {
    ($t:ty) => {
        impl Real for $t {
            const ZERO: Self = 0.0;
            const ONE: Self = 1.0;
            fn of(x: f64) -> Self {
                x as $t
            }
            fn sqrt(self) -> Self {
                <$t>::sqrt(self)
            }
            fn is_finite(self) -> bool {
                <$t>::is_finite(self)
            }
        }
    };
}
real!(f64);
real!(f32);

/// Rank-1 fit `f[p] ≈ g[hb[p]] · e[db[p]]` by alternating least squares, `f` over the
/// pairs. Deterministic (fixed order); empty bins and zero data give zeros, never NaN.
pub(crate) fn fit_link<T: Real>(f: &[T], pb: &[(u32, u32)], nb: usize, sweeps: usize) -> (Vec<T>, Vec<T>) {
    let (mut g, mut e) = (vec![T::ZERO; nb], vec![T::ONE; nb]);
    let (mut num, mut den) = (vec![T::ZERO; nb], vec![T::ZERO; nb]);
    let mut prev: Option<T> = None;
    for _ in 0..sweeps.max(1) {
        num.fill(T::ZERO);
        den.fill(T::ZERO);
        for (&x, &(h, d)) in f.iter().zip(pb) {
            num[h as usize] += x * e[d as usize];
            den[h as usize] += e[d as usize] * e[d as usize];
        }
        for (gi, (n, d)) in g.iter_mut().zip(num.iter().zip(&den)) {
            *gi = if *d > T::ZERO { *n / *d } else { T::ZERO };
        }
        num.fill(T::ZERO);
        den.fill(T::ZERO);
        for (&x, &(h, d)) in f.iter().zip(pb) {
            num[d as usize] += x * g[h as usize];
            den[d as usize] += g[h as usize] * g[h as usize];
        }
        for (ei, (n, d)) in e.iter_mut().zip(num.iter().zip(&den)) {
            *ei = if *d > T::ZERO { *n / *d } else { T::ZERO };
        }
        // Fix the scale between the factors (RMS of E over its used bins = 1).
        let (ss, n) = pb.iter().fold((T::ZERO, 0usize), |(s, n), &(_, d)| {
            let x = e[d as usize];
            (s + x * x, n + 1)
        });
        let rms = (ss / T::of(n.max(1) as f64)).sqrt();
        if rms > T::ZERO && rms.is_finite() {
            e.iter_mut().for_each(|x| *x /= rms);
            g.iter_mut().for_each(|x| *x *= rms);
        }
        // Converged: another sweep would not change the fit (ALS never increases the cost).
        let cost = f.iter().zip(pb).fold(T::ZERO, |s, (&x, &(h, d))| {
            let r = x - g[h as usize] * e[d as usize];
            s + r * r
        });
        if let Some(p) = prev {
            if p.is_finite() && p - cost <= T::of(1e-12) * p {
                break;
            }
        }
        prev = Some(cost);
    }
    (g, e)
}

/// A channel's fit: the link's `G` and `E` as stored, and the residual's `(U·S, V)` (CMF).
pub(crate) type ChannelFit = (Vec<f32>, Vec<f32>, Option<(faer::Mat<f64>, faer::Mat<f64>)>);

/// One channel `f` (pairs in grid order `view · lights + light`) of one texel: the link's
/// factors as stored (f32), and for `k > 0` the rank-`k` SVD `(U·S, V)` of the residual
/// `M / F` computed from the stored link, as the decoder sees it.
pub(crate) fn fit_channel(
    f: &[f64],
    pb: &[(u32, u32)],
    nb: usize,
    sweeps: usize,
    (nl, nv, k): (usize, usize, usize),
) -> Result<ChannelFit, CompressError> {
    let (g, e) = fit_link(f, pb, nb, sweeps);
    let (g, e): (Vec<f32>, Vec<f32>) = (
        g.iter().map(|x| *x as f32).collect(),
        e.iter().map(|x| *x as f32).collect(),
    );
    if k == 0 {
        return Ok((g, e, None));
    }
    let floor = RESIDUAL_FLOOR * f.iter().map(|x| x.abs()).sum::<f64>() / f.len().max(1) as f64;
    let m = faer::Mat::<f64>::from_fn(nl, nv, |l, v| {
        let (h, d) = pb[v * nl + l];
        let fl = g[h as usize] as f64 * e[d as usize] as f64;
        if fl.abs() > floor && floor > 0.0 {
            f[v * nl + l] / fl
        } else {
            1.0
        }
    });
    let (us, vv) = truncated_svd(m.as_ref(), k)?;
    Ok((g, e, Some((us, vv))))
}

/// The knobs of a GSHD or CMF method: (θ bins, sweeps, residual terms K).
fn knobs(params: &Params) -> Result<(usize, usize, usize), CompressError> {
    let (tb, sweeps, k) = match params.method {
        Method::Gshd { theta_bins, sweeps } => (theta_bins, sweeps, 0),
        Method::Cmf { theta_bins, sweeps } => (theta_bins, sweeps, params.components),
        _ => return Err(CompressError::Invalid("cmf::compress called for another method".into())),
    };
    if !(1..=MAX_THETA_BINS).contains(&tb) {
        return Err(CompressError::Invalid(format!(
            "{}: --half-bins {tb}: the half/difference θ bins must be 1..={MAX_THETA_BINS}",
            params.method.name()
        )));
    }
    if sweeps == 0 {
        return Err(CompressError::Invalid(format!(
            "{}: --sweeps 0: the alternating least squares needs at least one sweep",
            params.method.name()
        )));
    }
    Ok((tb, sweeps, k))
}

/// `gonio compress --method gshd|cmf`.
pub fn compress(ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
    let (tb, sweeps, k) = knobs(params)?;
    let (nl, nv) = (ds.n_lights(), ds.n_views());
    if matches!(params.method, Method::Cmf { .. }) && (k == 0 || k > nl.min(nv)) {
        return Err(CompressError::Invalid(format!(
            "cmf: -c {k} residual terms per ABRDF; must be 1..={} (the rank of a {nl} × {nv} ABRDF matrix)",
            nl.min(nv)
        )));
    }
    let pb = grid_bins(&ds.lights_deg, &ds.views_deg, tb);
    let nb = bins(tb);
    let a = Abrdfs::load(ds, ABRDF_F32_BUDGET)?;
    type Texel = (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>);
    let fits: Vec<Result<Texel, CompressError>> = (0..a.texels)
        .into_par_iter()
        .map_init(
            || vec![0f32; a.dims],
            |row, t| {
                a.row(t, row);
                let (mut hg, mut he) = (vec![0f32; nb * 3], vec![0f32; nb * 3]);
                let (mut p, mut q) = (vec![0f32; nl * k * 3], vec![0f32; nv * k * 3]);
                for ch in 0..3 {
                    let f: Vec<f64> = (0..nl * nv).map(|i| row[i * 3 + ch] as f64).collect();
                    let (g, e, residual) = fit_channel(&f, &pb, nb, sweeps, (nl, nv, k))?;
                    for b in 0..nb {
                        hg[b * 3 + ch] = g[b];
                        he[b * 3 + ch] = e[b];
                    }
                    if let Some((us, vv)) = residual {
                        put_terms(&mut p, &mut q, us.as_ref(), vv.as_ref(), ch);
                    }
                }
                Ok((hg, he, p, q))
            },
        )
        .collect();
    let t = a.texels;
    let (mut half, mut diff) = (Vec::with_capacity(t * nb * 3), Vec::with_capacity(t * nb * 3));
    let (mut light, mut view) = (Vec::with_capacity(t * nl * k * 3), Vec::with_capacity(t * nv * k * 3));
    for f in fits {
        let (hg, he, p, q) = f?;
        half.extend_from_slice(&hg);
        diff.extend_from_slice(&he);
        light.extend_from_slice(&p);
        view.extend_from_slice(&q);
    }
    let mut blocks = vec![
        (BlockInfo::new("half", t, nb * 3), half),
        (BlockInfo::new("diff", t, nb * 3), diff),
    ];
    if k > 0 {
        blocks.push((BlockInfo::new("light", t, nl * k * 3), light));
        blocks.push((BlockInfo::new("view", t, nv * k * 3), view));
    }
    Ok(encode_gbtf(
        ds,
        params,
        &a,
        blocks,
        &[("theta_bins", tb.into()), ("terms", k.into())],
    ))
}

/// Check a GSHD/CMF file's blocks against its header; returns (θ bins, K).
pub fn validate(h: &GbtfHeader) -> Result<(usize, usize), CompressError> {
    let params: Params = serde_json::from_value(h.params.clone())
        .map_err(|e| CompressError::Invalid(format!(".gbtf {}: parameters in the header: {e}", h.method)))?;
    let (tb, _, k) = knobs(&params)?;
    let (t, nb) = (h.width * h.height, bins(tb));
    let got: Vec<(usize, usize)> = h.blocks.iter().map(|b| (b.rows, b.cols)).collect();
    let link_ok = got.len() >= 2 && got[..2] == [(t, nb * 3), (t, nb * 3)];
    let rest_ok = if k == 0 {
        got.len() == 2
    } else {
        let tail = GbtfHeader {
            blocks: h.blocks[2.min(h.blocks.len())..].to_vec(),
            ..h.clone()
        };
        product_terms(&tail).ok() == Some(k)
    };
    if !(link_ok && rest_ok) {
        return Err(CompressError::Invalid(format!(
            ".gbtf {}: block shapes {got:?} do not match {t} texels, {nb} half/difference bins and {k} residual terms",
            h.method
        )));
    }
    Ok((tb, k))
}

/// Image (`light`, `view`) of a GSHD/CMF file that passed [`validate`]: per texel and
/// channel `G[h] · E[d]`, times `Σ_k U[l, k] V[v, k]` for CMF. Interleaved linear RGB.
pub fn reconstruct(g: &Gbtf, theta_bins: usize, k: usize, light: usize, view: usize) -> Vec<f32> {
    let h = &g.header;
    let (hb, db) = pair_bins(h.lights_deg[light], h.views_deg[view], theta_bins);
    let nb = bins(theta_bins);
    let residual = (k > 0).then(|| products_image(h, &g.blocks[2], &g.blocks[3], k, light, view));
    let (gb, eb) = (&g.blocks[0], &g.blocks[1]);
    let mut out = vec![0f32; h.width * h.height * 3];
    out.par_chunks_mut(3).enumerate().for_each(|(i, px)| {
        for (ch, o) in px.iter_mut().enumerate() {
            let link = gb[(i * nb + hb as usize) * 3 + ch] * eb[(i * nb + db as usize) * 3 + ch];
            *o = match &residual {
                Some(r) => link * r[i * 3 + ch],
                None => link,
            };
        }
    });
    out
}

/// GSHD in the registry (`super::registry`).
pub struct GshdCodec;

impl Codec for GshdCodec {
    fn id(&self) -> CodecId {
        CodecId::Gshd
    }
    fn ladder(&self, knobs: &Knobs) -> Vec<Vec<Params>> {
        vec![[4, 8, 16]
            .map(|b| {
                let method = Method::Gshd {
                    theta_bins: b,
                    sweeps: knobs.sweeps.unwrap_or(200),
                };
                knobs.params(method, 1)
            })
            .to_vec()]
    }
    fn shard(&self, _: &Knobs) -> Shard {
        Shard::No
    }
    fn encode(&self, ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
        compress(ds, params)
    }
    fn open(&self, g: &Gbtf) -> Result<Opened, CompressError> {
        open(g, |theta_bins| Method::Gshd { theta_bins, sweeps: 0 })
    }
}

/// CMF in the registry (`super::registry`).
pub struct CmfCodec;

impl Codec for CmfCodec {
    fn id(&self) -> CodecId {
        CodecId::Cmf
    }
    fn ladder(&self, knobs: &Knobs) -> Vec<Vec<Params>> {
        vec![[1, 2, 4]
            .map(|c| {
                let method = Method::Cmf {
                    theta_bins: knobs.half_bins.min(8),
                    sweeps: knobs.sweeps.unwrap_or(200),
                };
                knobs.params(method, c)
            })
            .to_vec()]
    }
    fn shard(&self, _: &Knobs) -> Shard {
        Shard::No
    }
    fn encode(&self, ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
        compress(ds, params)
    }
    fn open(&self, g: &Gbtf) -> Result<Opened, CompressError> {
        open(g, |theta_bins| Method::Cmf { theta_bins, sweeps: 0 })
    }
}

/// Open a GSHD or CMF file (one format; `method` names which, from its θ bins).
fn open(g: &Gbtf, method: impl FnOnce(usize) -> Method) -> Result<Opened, CompressError> {
    let (theta_bins, k) = validate(&g.header)?;
    Ok(Opened {
        method: method(theta_bins),
        components: k,
        layout: Layout::PerTexel,
        decoder: Arc::new(Decoder { theta_bins, k }),
    })
}

/// [`reconstruct`] of a GSHD (`k` = 0) or CMF file.
#[derive(Debug)]
struct Decoder {
    theta_bins: usize,
    k: usize,
}

impl Decode for Decoder {
    fn reconstruct(&self, g: &Gbtf, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        Ok(reconstruct(g, self.theta_bins, self.k, light, view))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compress::testdata::{self, hash, max_err, round_trip};

    fn gshd(theta_bins: usize) -> Params {
        Params::new(
            Method::Gshd {
                theta_bins,
                sweeps: 200,
            },
            1,
        )
    }

    fn cmf(theta_bins: usize, k: usize) -> Params {
        Params::new(
            Method::Cmf {
                theta_bins,
                sweeps: 200,
            },
            k,
        )
    }

    /// The half vector of a mirror pair is the normal; D is then L itself seen from H.
    #[test]
    fn the_half_and_difference_bins_follow_the_geometry() {
        let (h, d) = pair_bins([30.0, 0.0], [30.0, 180.0], 8);
        assert_eq!(h / 16, 0, "mirror pair: H at the pole");
        assert_eq!(d / 16, 2, "θ_d = 30° is the third of 8 bins of 11.25°");
        // swapping light and view keeps H and mirrors D
        let (h2, d2) = pair_bins([30.0, 180.0], [30.0, 0.0], 8);
        assert_eq!(h2, h);
        assert_eq!(d2 / 16, d / 16);
        assert_ne!(d2 % 16, d % 16, "the azimuth of D turns by 180°");
    }

    /// A product of a half-bin and a difference-bin function is reproduced exactly by
    /// GSHD; an ABRDF that is not such a product is not, and CMF's residual terms reduce
    /// the error monotonically to exact at full rank.
    #[test]
    fn gshd_reproduces_half_difference_products_and_cmf_closes_the_gap() {
        let tmp = tempfile::tempdir().unwrap();
        let lights = testdata::lights();
        let views = testdata::views();
        let tb = 4;
        let prod = |l: usize, v: usize, t: usize, c: usize| {
            let (h, d) = pair_bins(lights[l], views[v], tb);
            (0.2 + hash(t * 3 + c, h as usize)) * (0.3 + hash(t + 99, d as usize * 3 + c))
        };
        let ds = testdata::write(&tmp.path().join("ds"), prod);
        let (g, m) = round_trip(&ds, &gshd(tb), &tmp.path().join("a.gbtf"));
        assert_eq!(g.header.method, "gshd");
        let e = max_err(&ds, &m);
        assert!(e < 2e-3, "half/difference product: max error {e}");

        let ds2 = testdata::write(&tmp.path().join("ds2"), |l, v, t, c| {
            0.05 + 0.6 * hash(t * 3 + c, l * 7 + v)
        });
        let (_, m) = round_trip(&ds2, &gshd(tb), &tmp.path().join("b.gbtf"));
        let e_gshd = max_err(&ds2, &m);
        assert!(e_gshd > 0.05, "full-rank data is not a product: {e_gshd}");
        let full = lights.len().min(views.len());
        let mut last = f32::INFINITY;
        for k in [1, full] {
            let (g, m) = round_trip(&ds2, &cmf(tb, k), &tmp.path().join(format!("c{k}.gbtf")));
            assert_eq!(g.header.method, "cmf");
            let e = max_err(&ds2, &m);
            assert!(e <= last + 1e-4, "K = {k}: {e} after {last}");
            last = e;
        }
        assert!(last < 2e-3, "full-rank residual: max error {last}");
    }

    #[test]
    fn zero_and_degenerate_inputs_stay_finite_and_bad_knobs_are_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("z"), |_, _, _, _| 0.0);
        for p in [gshd(4), cmf(4, 2)] {
            let (_, m) = round_trip(&ds, &p, &tmp.path().join("z.gbtf"));
            let img = m.reconstruct(0, 0).unwrap();
            assert!(img.iter().all(|x| *x == 0.0), "{p:?}");
        }
        for (p, needle) in [
            (gshd(0), "--half-bins 0"),
            (gshd(MAX_THETA_BINS + 1), "--half-bins"),
            (cmf(4, 0), "-c 0"),
            (
                Params::new(
                    Method::Gshd {
                        theta_bins: 4,
                        sweeps: 0,
                    },
                    1,
                ),
                "--sweeps 0",
            ),
        ] {
            let e = compress(&ds, &p).unwrap_err().to_string();
            assert!(e.contains(needle), "{e}");
        }
    }
}
