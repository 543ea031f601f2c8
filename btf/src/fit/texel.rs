//! The per-texel fit (`gonio fit --per-texel`): McAllister et al. 2002's SBRDF, a scaled
//! Lafortune model per texel (diffuse RGB, and per lobe the direction angle γ of
//! `C = √2 (cos γ, cos γ, sin γ)`, the exponent and RGB `ks`), or glTF's metallic-roughness
//! model with a shading normal per texel (`--model gltf`: what renderers read).
//!
//! **Texels that fail.** A texel without usable data, whose start or result is not finite,
//! or whose LM ran into its iteration cap with a residual that stands out (over twice the
//! texels' median and over 5 %) is *not converged*: it is listed ([`SvbrdfFit::failed`]),
//! its parameters are filled from its converged neighbours (the mean of the 8-neighbours,
//! growing rings until some are found; the average's fit when none is), and it is flagged
//! in the file. No parameter is ever NaN. Every texel's residual (cosine-weighted relative
//! RMS against its own data) is kept: the map of where the SVBRDF fails.
//!
//! As in McAllister's fitting, the average BRDF is fitted first (several starts); every
//! texel then starts from that solution, so a homogeneous region converges in a few
//! iterations and neighbouring texels land in the same basin. Texels are independent
//! (parallel, each into its own slot: the output does not depend on the thread count).
//!
//! The result is an SVBRDF: `texels × params` f32 plus one gain per pair and channel (the
//! white standard's mean value over ρ/π, which turns a BRDF value back into the
//! dataset's units; 1 for BRDF data). [`SvbrdfFit`] decodes any grid pair from it with
//! the material library's models; [`SvbrdfFit::to_gbtf`] stores it as a `.gbtf` whose
//! decoder (`compress::svbrdf`) is what `gonio reconstruct`, `gonio render` and the error
//! report use, checked against this one by `fit::tests::svbrdf_file_decodes_to_the_fitted_models`.

use super::data::Loaded;
use super::lm::{LmOptions, Stop};
use super::{
    check_observations, drop_saturated, fit_from, select_anisotropy, Family, FitError, FitReport, ModelKind, Scales,
    Space, ANISOTROPY_START,
};
use crate::compress::interp::BtfModel;
use crate::compress::CompressError;
use rayon::prelude::*;
use serde::Serialize;
use std::collections::BTreeMap;

/// Per-texel parameters of one family.
#[derive(Clone, Debug)]
pub struct SvbrdfFit {
    pub family: Family,
    pub width: usize,
    pub height: usize,
    pub lights_deg: Vec<[f64; 2]>,
    pub views_deg: Vec<[f64; 2]>,
    /// Row-major `texels × n_params`, parameter values in their own units.
    pub params: Vec<f32>,
    /// Per grid pair (`view · lights + light`) the gain plane `[a, b, c]` per channel
    /// (`a + b·u + c·w`, u and w the texel centre in [−½, ½]); `None` = not fitted (below
    /// the horizon or not measured): decoded as 0.
    pub gain: Vec<Option<[[f32; 3]; 3]>>,
    /// Each texel's own directions (as the fit used them), if the dataset gives them.
    pub geometry: Option<super::data::Geometry>,
    /// Per texel the cosine-weighted relative RMS of its fit against its data (0 where it
    /// had none).
    pub residual: Vec<f32>,
    /// Texels that did not converge (ascending), filled from their neighbours.
    pub failed: Vec<usize>,
}

/// Summary of a per-texel fit.
#[derive(Clone, Debug, Serialize)]
pub struct TexelSummary {
    pub texels: usize,
    pub params_per_texel: usize,
    /// How the texels' fits ended (reason → count), in a fixed order.
    pub stops: BTreeMap<String, usize>,
    /// Texels with nothing to fit (all zero or no calibrated pair): stored as the average.
    pub texels_without_data: usize,
    /// Mean over texels of the cosine-weighted relative RMS.
    pub mean_rel_rms: f64,
    /// Worst texel's relative RMS, and which.
    pub max_rel_rms: f64,
    pub worst_texel: usize,
    /// Texels not converged (no data, non-finite start or iteration cap), filled from
    /// their neighbours and flagged; the first 100 are listed.
    pub not_converged: usize,
    pub not_converged_texels: Vec<usize>,
    /// Bytes of the SVBRDF as f32 (parameters + per-pair gains).
    pub bytes: usize,
    /// glTF only: texels whose anisotropic fit passed the test (`super::ANISOTROPY_MARGIN`)
    /// and keep `KHR_materials_anisotropy`; the others have none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub anisotropic_texels: Option<usize>,
    /// glTF only: the mean over texels of the isotropic fit's relative RMS (`mean_rel_rms`
    /// is that of the kept fits), the residual without anisotropy.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mean_rel_rms_isotropic: Option<f64>,
}

/// Fit every texel of `loaded`, starting from `average` (the fit of the averaged BRDF with
/// the same family). `iterations` caps each texel's LM.
pub fn fit_texels(
    loaded: &Loaded,
    average: &FitReport,
    space: Space,
    iterations: usize,
) -> Result<(SvbrdfFit, TexelSummary), FitError> {
    if !matches!(average.model, ModelKind::Lafortune | ModelKind::Gltf) {
        return Err(FitError::Options {
            what: format!("--per-texel with --model {}", average.model.name()),
            reason: "the per-texel fit is McAllister's scaled Lafortune SBRDF (--model lafortune) or glTF's \
                     metallic-roughness model (--model gltf)"
                .into(),
        });
    }
    let family = Family::new(average.model, average.lobes);
    let gltf = average.model == ModelKind::Gltf;
    // glTF: each texel fits the isotropic model, then the anisotropy test from its result
    // with the average's anisotropy as the start (or two orthogonal directions when the
    // average has none), so a texel is anisotropic only where its own data say so.
    let iso_family = if gltf { Family::gltf_isotropic() } else { family.clone() };
    let x0: Vec<f64> = family
        .params
        .iter()
        .zip(&average.params)
        .map(|(s, (_, v))| s.to_x(*v))
        .collect();
    let opts = LmOptions {
        max_iterations: iterations.max(1),
        ..Default::default()
    };
    let np = family.n_params();
    let x0_iso = x0[..iso_family.n_params()].to_vec();
    let aniso_starts: Vec<[f64; 2]> = match x0.get(7..9) {
        Some(a) if a[0] != 0.0 || a[1] != 0.0 => vec![[a[0], a[1]]],
        _ => vec![[ANISOTROPY_START, 0.0], [-ANISOTROPY_START, 0.0]],
    };
    // (solver coordinates, stop, relative RMS kept, isotropic relative RMS, anisotropic)
    type TexelResult = (Vec<f64>, Option<Stop>, f64, f64, bool);
    let results: Vec<TexelResult> = (0..loaded.texels())
        .into_par_iter()
        .map(|t| {
            let obs = loaded.texel(t);
            if check_observations(&obs, "texel").is_err() {
                return (x0.clone(), None, 0.0, 0.0, false);
            }
            let (kept, _) = drop_saturated(&obs);
            if kept.len() < 3 {
                return (x0.clone(), None, 0.0, 0.0, false);
            }
            let scales = Scales::of(&kept);
            let r = fit_from(&iso_family, &kept, space, &scales, &x0_iso, &opts);
            let model = iso_family.model(&iso_family.values(&r.params));
            let rel = super::diagnose(&model, &kept, &scales).rel_rms;
            if !gltf || !r.cost.is_finite() {
                let mut x = r.params;
                x.resize(np, 0.0);
                return (x, Some(r.stop), rel, rel, false);
            }
            let (x, run, test) = select_anisotropy(&kept, space, &scales, &r.params, rel, &aniso_starts, &opts);
            match run {
                Some(a) => (x, Some(a.stop), test.anisotropic_rel_rms, rel, true),
                None => (x, Some(r.stop), rel, rel, false),
            }
        })
        .collect();
    let mut params = Vec::with_capacity(loaded.texels() * np);
    let mut stops = BTreeMap::new();
    let (mut empty, mut sum, mut worst, mut worst_t) = (0, 0.0, 0.0f64, 0);
    let mut failed = Vec::new();
    let mut residual = Vec::with_capacity(loaded.texels());
    // A capped LM whose residual is in line with the others has found its texel's material
    // (exact data converge slower than the relative cost tolerance); an outlier has not.
    let mut rels: Vec<f64> = results.iter().map(|r| r.2).filter(|r| r.is_finite()).collect();
    rels.sort_by(f64::total_cmp);
    let median = rels.get(rels.len() / 2).copied().unwrap_or(0.0);
    let outlier = |rel: f64| rel > 2.0 * median && rel > 0.05;
    let anisotropic = results.iter().filter(|r| r.4).count();
    let iso_sum: f64 = results
        .iter()
        .filter(|r| r.1.is_some() && r.3.is_finite())
        .map(|r| r.3)
        .sum();
    for (t, (x, stop, rel, _, _)) in results.iter().enumerate() {
        let values = family.values(x);
        params.extend(values.iter().map(|v| *v as f32));
        match stop {
            None => empty += 1,
            Some(s) => *stops.entry(s.reason().to_string()).or_insert(0) += 1,
        }
        let finite = values.iter().all(|v| v.is_finite()) && rel.is_finite();
        let capped = matches!(stop, Some(Stop::MaxIterations)) && outlier(*rel);
        if !finite || capped || matches!(stop, None | Some(Stop::NonFiniteStart)) {
            failed.push(t);
        }
        let rel = if rel.is_finite() { *rel } else { 0.0 };
        residual.push(rel as f32);
        sum += rel;
        if rel > worst {
            worst = rel;
            worst_t = t;
        }
    }
    let fallback: Vec<f32> = average.params.iter().map(|(_, v)| *v as f32).collect();
    fill_from_neighbours(&mut params, np, loaded.width, loaded.height, &failed, &fallback);
    let nl = loaded.lights_deg.len();
    let mut gain = vec![None; nl * loaded.views_deg.len()];
    for (p, g) in loaded.pairs.iter().zip(loaded.gain_planes()) {
        gain[p.view * nl + p.light] = Some(g);
    }
    let fit = SvbrdfFit {
        family,
        width: loaded.width,
        height: loaded.height,
        lights_deg: loaded.lights_deg.clone(),
        views_deg: loaded.views_deg.clone(),
        params,
        gain,
        geometry: loaded.geometry,
        residual,
        failed,
    };
    let summary = TexelSummary {
        texels: loaded.texels(),
        params_per_texel: np,
        stops,
        texels_without_data: empty,
        mean_rel_rms: sum / (loaded.texels() - empty).max(1) as f64,
        max_rel_rms: worst,
        worst_texel: worst_t,
        not_converged: fit.failed.len(),
        not_converged_texels: fit.failed.iter().take(100).copied().collect(),
        bytes: fit.bytes(),
        anisotropic_texels: gltf.then_some(anisotropic),
        mean_rel_rms_isotropic: gltf.then(|| iso_sum / (loaded.texels() - empty).max(1) as f64),
    };
    Ok((fit, summary))
}

/// Replace the parameters of the `failed` texels (ascending) by the mean of their nearest
/// non-failed neighbours: the ring at Chebyshev distance 1, 2, … up to the image's size,
/// the first ring that holds any; `fallback` (the average's fit) when no texel converged.
/// Reads only non-failed texels, so the result does not depend on the order.
pub fn fill_from_neighbours(params: &mut [f32], np: usize, w: usize, h: usize, failed: &[usize], fallback: &[f32]) {
    if failed.is_empty() {
        return;
    }
    let bad: std::collections::BTreeSet<usize> = failed.iter().copied().collect();
    let fills: Vec<(usize, Vec<f32>)> = failed
        .par_iter()
        .map(|&t| {
            let (x, y) = ((t % w) as i64, (t / w) as i64);
            for r in 1..=(w.max(h) as i64) {
                let mut sum = vec![0f64; np];
                let mut n = 0usize;
                for yy in (y - r)..=(y + r) {
                    for xx in (x - r)..=(x + r) {
                        let ring = (xx - x).abs() == r || (yy - y).abs() == r;
                        if !ring || xx < 0 || yy < 0 || xx >= w as i64 || yy >= h as i64 {
                            continue;
                        }
                        let u = yy as usize * w + xx as usize;
                        if bad.contains(&u) {
                            continue;
                        }
                        for (s, p) in sum.iter_mut().zip(&params[u * np..(u + 1) * np]) {
                            *s += *p as f64;
                        }
                        n += 1;
                    }
                }
                if n > 0 {
                    return (t, sum.iter().map(|s| (s / n as f64) as f32).collect());
                }
            }
            (t, fallback.to_vec())
        })
        .collect();
    for (t, p) in fills {
        params[t * np..(t + 1) * np].copy_from_slice(&p);
    }
}

impl SvbrdfFit {
    /// Size as stored: f32 parameters per texel, a f32 gain plane per pair and channel,
    /// and the geometry (3 f32).
    pub fn bytes(&self) -> usize {
        let quality = if self.family.kind == ModelKind::Gltf {
            8 * self.width * self.height
        } else {
            0
        };
        4 * self.params.len() + 4 * 9 * self.gain.len() + 12 + quality
    }

    /// The fit as a `.gbtf` (`compress::svbrdf`, method `svbrdf`, or `compress::gltf` for
    /// the glTF model): what `gonio fit --per-texel --out F.gbtf` writes and `gonio reconstruct`/`render`/`view` decode. Pairs
    /// without a fit get an all-zero gain plane, which decodes to 0 as here.
    pub fn to_gbtf(&self, ds: &crate::compress::DatasetViews) -> Result<crate::compress::Gbtf, CompressError> {
        if (ds.width, ds.height, ds.n_lights(), ds.n_views())
            != (self.width, self.height, self.lights_deg.len(), self.views_deg.len())
        {
            return Err(CompressError::Invalid(format!(
                "{}: its grid or image size is not the fitted one",
                ds.dir.display()
            )));
        }
        let gain: Vec<f32> = self
            .gain
            .iter()
            .flat_map(|g| g.unwrap_or([[0.0; 3]; 3]).into_iter().flatten())
            .collect();
        if self.family.kind == ModelKind::Gltf {
            let flagged: std::collections::BTreeSet<usize> = self.failed.iter().copied().collect();
            let quality = (0..self.width * self.height)
                .flat_map(|t| [self.residual[t], if flagged.contains(&t) { 1.0 } else { 0.0 }])
                .collect();
            return crate::compress::gltf::encode(ds, self.params.clone(), gain, quality, self.geometry);
        }
        crate::compress::svbrdf::encode(ds, self.family.lobes, self.params.clone(), gain, self.geometry)
    }

    /// Parameter values of texel `t`.
    pub fn texel_params(&self, t: usize) -> Vec<f64> {
        let np = self.family.n_params();
        self.params[t * np..(t + 1) * np].iter().map(|v| *v as f64).collect()
    }
}

impl BtfModel for SvbrdfFit {
    fn width(&self) -> usize {
        self.width
    }
    fn height(&self) -> usize {
        self.height
    }
    fn lights_deg(&self) -> &[[f64; 2]] {
        &self.lights_deg
    }
    fn views_deg(&self) -> &[[f64; 2]] {
        &self.views_deg
    }
    fn reconstruct(&self, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        let n = self.width * self.height;
        let Some(g) = self
            .gain
            .get(view * self.lights_deg.len() + light)
            .copied()
            .ok_or_else(|| CompressError::Invalid(format!("pair (light {light}, view {view}) outside the grid")))?
        else {
            return Ok(vec![0.0; 3 * n]);
        };
        let d = |x: [f64; 2]| gonio_devices::Direction::from_degrees(x[0], x[1]).vector();
        let (l, v) = (d(self.lights_deg[light]), d(self.views_deg[view]));
        let (w, h) = (self.width, self.height);
        let out: Vec<f32> = (0..n)
            .into_par_iter()
            .flat_map_iter(|t| {
                let (lt, vt) = match &self.geometry {
                    Some(g) => g.texel_dirs(l, v, t, w, h),
                    None => (l, v),
                };
                let f = self.family.model(&self.texel_params(t)).eval(lt, vt);
                let u = ((t % w) as f64 + 0.5) / w as f64 - 0.5;
                let y = ((t / w) as f64 + 0.5) / h as f64 - 0.5;
                (0..3).map(move |c| {
                    let gain = g[c][0] as f64 + g[c][1] as f64 * u + g[c][2] as f64 * y;
                    (f[c] * gain) as f32
                })
            })
            .collect();
        Ok(out)
    }
}
