//! Fitting analytic BRDF models to measured data (`gonio fit`).
//!
//! Why: a measured BTF or BRDF is a table; renderers and the field's comparisons want a
//! handful of parameters. The fit answers "which model, which parameters, and where does
//! it fail" — the last part as a residual per elevation band and per distance from the
//! mirror direction, so Fresnel at grazing or a lobe of the wrong shape is visible.
//!
//! - [`fit`] fits one family to observations `(l, v, f)` (BRDF values in 1/sr) by
//!   Levenberg–Marquardt ([`lm`]) from several deterministic starts ([`models`]), in log
//!   space (`ln(f cos θ_l + ε)`: the highlight and the diffuse floor weigh alike) or
//!   cosine-weighted linear space (`f cos θ_l`, what a radiance image weighs).
//! - [`data`] turns a dataset (averaged over texels, or per texel) or a CSV table into
//!   observations, radiometrically calibrated by a white-standard dataset when the
//!   dataset's values are not BRDF values.
//! - [`texel`] fits every texel (McAllister 2002's SBRDF: a scaled Lafortune model per
//!   texel, started from the average's fit): an SVBRDF, and so a compression method whose
//!   ratio and error [`texel::SvbrdfFit`] reports in the terms of `gonio compress`.
//!
//! The models are the simulator's material library (`gonio_brdf`, the same
//! evaluation the renderer and the Mitsuba cross-checks use); nothing here re-implements
//! them, and nothing here reads the simulator's truths.
//!
//! Same inputs, same bytes: starts run in parallel but are reduced in start order, texels
//! in parallel into their own slots, every sum in a fixed order.

pub mod data;
pub mod lm;
pub mod models;
pub mod texel;

#[cfg(test)]
mod tests;

use gonio_brdf::BrdfModel;
use gonio_devices::Vec3;
use lm::{LmOptions, Stop};
pub use models::{Family, ModelKind};
use rayon::prelude::*;
use serde::Serialize;
use thiserror::Error;

/// RGB triple (linear).
pub type Rgb = [f64; 3];

#[derive(Debug, Error)]
pub enum FitError {
    #[error("{input}: {reason}")]
    Input { input: String, reason: String },
    #[error("{what}: {reason}")]
    Options { what: String, reason: String },
    #[error("{input}: reading the dataset: {source}")]
    Dataset {
        input: String,
        #[source]
        source: crate::compress::CompressError,
    },
    #[error("{input}: {source}")]
    Io {
        input: String,
        #[source]
        source: std::io::Error,
    },
}

/// Measured BRDF values at direction pairs (local frame: normal +z, tangent +x).
#[derive(Clone, Debug, Default)]
pub struct Observations {
    pub l: Vec<Vec3>,
    pub v: Vec<Vec3>,
    /// BRDF values (1/sr) per channel.
    pub f: Vec<Rgb>,
}

impl Observations {
    pub fn len(&self) -> usize {
        self.f.len()
    }
    pub fn is_empty(&self) -> bool {
        self.f.is_empty()
    }
    pub fn push(&mut self, l: Vec3, v: Vec3, f: Rgb) {
        self.l.push(l);
        self.v.push(v);
        self.f.push(f);
    }
    /// Observations of `model` at the pairs of `dirs` (both directions above the horizon).
    pub fn of_model(model: &BrdfModel, pairs: &[(Vec3, Vec3)]) -> Observations {
        let mut o = Observations::default();
        for &(l, v) in pairs {
            if l.z > 0.0 && v.z > 0.0 {
                o.push(l, v, model.eval(l, v));
            }
        }
        o
    }
}

/// The residual space.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Space {
    /// `ln(f_model cos θ_l + ε) − ln(f_data cos θ_l + ε)`, ε = 1 % of the data's mean
    /// `f cos θ_l` per channel: relative error, highlight and floor weigh alike.
    Log,
    /// `(f_model − f_data) cos θ_l / s`, s = RMS of the data's `f cos θ_l`: absolute
    /// error of a radiance image under unit irradiance; the highlight dominates.
    Cosine,
}

impl Space {
    pub fn parse(s: &str) -> Option<Space> {
        match s {
            "log" => Some(Space::Log),
            "cosine" => Some(Space::Cosine),
            _ => None,
        }
    }
}

/// Knobs of [`fit`].
#[derive(Clone, Debug, Serialize)]
pub struct FitOptions {
    pub kind: ModelKind,
    pub lobes: usize,
    pub space: Space,
    /// Deterministic starts (≥ 1).
    pub starts: usize,
    pub lm: LmOptions,
}

impl FitOptions {
    pub fn new(kind: ModelKind) -> Self {
        FitOptions {
            kind,
            lobes: 1,
            space: Space::Log,
            starts: 8,
            lm: LmOptions::default(),
        }
    }
    /// Refuse what cannot run: no lobes, no starts, no iterations, `--lobes` > 1 for a
    /// single-lobe family.
    pub fn check(&self) -> Result<(), FitError> {
        let bad = |what: &str, reason: String| {
            Err(FitError::Options {
                what: what.into(),
                reason,
            })
        };
        if self.lobes == 0 {
            return bad(
                "--lobes 0",
                "a model needs at least one lobe: use --lobes 1 or more".into(),
            );
        }
        if self.lobes > 8 {
            return bad(
                &format!("--lobes {}", self.lobes),
                "at most 8 lobes (each adds 5–6 parameters the data must determine)".into(),
            );
        }
        if self.lobes > 1 && !self.kind.multi_lobe() {
            return bad(
                &format!("--lobes {}", self.lobes),
                format!(
                    "model `{}` has one lobe; lafortune and cook-torrance take several",
                    self.kind.name()
                ),
            );
        }
        if self.starts == 0 {
            return bad("--starts 0", "at least one start is needed".into());
        }
        if self.lm.max_iterations == 0 {
            return bad("--iterations 0", "at least one iteration is needed".into());
        }
        Ok(())
    }
}

/// Residual of a model against the data in one group of observations.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Band {
    pub label: String,
    pub observations: usize,
    /// `√(Σ (f_m − f_d)² cos²θ_l / Σ f_d² cos²θ_l)` over the band (all channels).
    pub rel_rms: f64,
    /// Mean of `ln((f_m cos + ε)/(f_d cos + ε))`: > 0 the model is too bright here.
    pub log_bias: f64,
}

/// One start's outcome.
#[derive(Clone, Debug, Serialize)]
pub struct StartOutcome {
    pub start: usize,
    pub cost: f64,
    pub iterations: usize,
    pub stop: Stop,
}

/// The result of [`fit`].
#[derive(Clone, Debug, Serialize)]
pub struct FitReport {
    pub model: ModelKind,
    pub lobes: usize,
    pub space: Space,
    /// The fitted model, as a sample file's `[[material]]` would write it.
    pub brdf: BrdfModel,
    /// Free parameters by name, in their own units.
    pub params: Vec<(String, f64)>,
    /// Parameters that ended on a bound (a stiff case: lobe narrower than the sampling,
    /// no signal for a parameter).
    pub at_bounds: Vec<String>,
    pub observations: usize,
    /// Observations left out as saturated (clipped at the data's maximum).
    pub saturated_excluded: usize,
    /// `½ Σ r²` / residual count in the fit space.
    pub cost_per_residual: f64,
    /// Cosine-weighted relative RMS over all observations (comparable across models).
    pub rel_rms: f64,
    /// RMS of the log ratio (comparable across models).
    pub log_rms: f64,
    /// By `max(θ_l, θ_v)`.
    pub by_elevation: Vec<Band>,
    /// By the half vector's angle from the normal (distance from the mirror direction).
    pub by_half_angle: Vec<Band>,
    /// Plain sentences on where the model fails (empty when no band stands out).
    pub failures: Vec<String>,
    pub best_start: usize,
    pub stop: Stop,
    pub iterations: usize,
    pub starts: Vec<StartOutcome>,
    /// glTF only: the anisotropy test (`KHR_materials_anisotropy`), see [`select_anisotropy`].
    #[serde(skip_serializing_if = "Option::is_none")]
    pub anisotropy: Option<AnisotropyTest>,
}

/// The anisotropic glTF fit is kept only when its relative RMS is at most `1 −` this times
/// the isotropic fit's (half). Two more parameters always lower the residual a little, and
/// mesostructure (shadowing, parallax) looks direction-dependent to a texel: on the
/// simulated wallpaper (isotropic materials on a relief, 12-direction sweep) the texels'
/// ratio anisotropic/isotropic is 0.75 at its 1st percentile and 0.93 at the median; on
/// brushed metal it is 0.08 at the median and ≤ 0.5 for 795 of 1024 texels
/// (docs/guide/export.md).
pub const ANISOTROPY_MARGIN: f64 = 0.5;

/// Strength of the anisotropy starts (`a = s·(cos 2φ, sin 2φ)`): away from 0, where the
/// direction has no gradient, and from 1, where `α_t` saturates.
pub const ANISOTROPY_START: f64 = 0.5;

/// The glTF model's anisotropy test: the isotropic fit against the anisotropic one that
/// starts from it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct AnisotropyTest {
    /// Cosine-weighted relative RMS without and with anisotropy.
    pub isotropic_rel_rms: f64,
    pub anisotropic_rel_rms: f64,
    /// [`ANISOTROPY_MARGIN`].
    pub margin: f64,
    /// Whether the anisotropic fit is kept (`anisotropic ≤ (1 − margin) · isotropic`).
    pub kept: bool,
    /// The anisotropic fit's strength and direction (degrees, counter-clockwise from the
    /// tangent +x), kept or not.
    pub strength: f64,
    pub rotation_deg: f64,
}

/// The anisotropy test of a glTF fit. `iso` are the isotropic fit's solver coordinates
/// ([`Family::gltf_isotropic`]) with relative RMS `iso_rel`; the anisotropic family
/// (`Family::new(ModelKind::Gltf, 1)`) is fitted from them with each anisotropy vector of
/// `starts` (the lowest cost wins, ties to the earlier start). Returns the full family's
/// coordinates (anisotropy 0 unless kept), the LM run kept (`None`: the isotropic one),
/// and the test.
pub(crate) fn select_anisotropy(
    obs: &Observations,
    space: Space,
    scales: &Scales,
    iso: &[f64],
    iso_rel: f64,
    starts: &[[f64; 2]],
    opts: &LmOptions,
) -> (Vec<f64>, Option<lm::LmResult>, AnisotropyTest) {
    let full = Family::new(ModelKind::Gltf, 1);
    let mut padded = iso.to_vec();
    padded.resize(full.n_params(), 0.0);
    let mut best: Option<lm::LmResult> = None;
    for a in starts {
        let mut x0 = iso.to_vec();
        x0.extend(a);
        let r = fit_from(&full, obs, space, scales, &x0, opts);
        if r.cost.is_finite() && best.as_ref().is_none_or(|b| r.cost < b.cost) {
            best = Some(r);
        }
    }
    let Some(best) = best else {
        let test = AnisotropyTest {
            isotropic_rel_rms: iso_rel,
            anisotropic_rel_rms: iso_rel,
            margin: ANISOTROPY_MARGIN,
            kept: false,
            strength: 0.0,
            rotation_deg: 0.0,
        };
        return (padded, None, test);
    };
    let values = full.values(&best.params);
    let rel = diagnose(&full.model(&values), obs, scales).rel_rms;
    let (strength, rotation) = gonio_brdf::gltf::anisotropy_of([values[7], values[8]]);
    let kept = rel.is_finite() && iso_rel.is_finite() && rel <= (1.0 - ANISOTROPY_MARGIN) * iso_rel;
    let test = AnisotropyTest {
        isotropic_rel_rms: iso_rel,
        anisotropic_rel_rms: rel,
        margin: ANISOTROPY_MARGIN,
        kept,
        strength,
        rotation_deg: rotation.to_degrees(),
    };
    if kept {
        (best.params.clone(), Some(best), test)
    } else {
        (padded, None, test)
    }
}

/// The anisotropy starts of an averaged fit: strength [`ANISOTROPY_START`] along 0°, 45°,
/// 90° and 135°.
pub fn anisotropy_starts() -> Vec<[f64; 2]> {
    (0..4)
        .map(|k| gonio_brdf::gltf::anisotropy_vector(ANISOTROPY_START, k as f64 * std::f64::consts::FRAC_PI_4))
        .collect()
}

/// Per-channel ε of the log space and scale of the cosine space.
#[derive(Clone, Copy, Debug)]
pub struct Scales {
    eps: Rgb,
    rms: Rgb,
}

impl Scales {
    pub fn of(obs: &Observations) -> Scales {
        let n = obs.len().max(1) as f64;
        let mut mean = [0.0; 3];
        let mut sq = [0.0; 3];
        for (l, f) in obs.l.iter().zip(&obs.f) {
            for c in 0..3 {
                let y = f[c] * l.z;
                mean[c] += y / n;
                sq[c] += y * y / n;
            }
        }
        Scales {
            eps: mean.map(|m| (0.01 * m).max(1e-12)),
            rms: sq.map(|s| s.sqrt().max(1e-12)),
        }
    }
}

/// Write the residuals of `model` against `obs` (3 per observation).
pub(crate) fn residuals(model: &BrdfModel, obs: &Observations, space: Space, s: &Scales, out: &mut [f64]) {
    for (i, ((l, v), f)) in obs.l.iter().zip(&obs.v).zip(&obs.f).enumerate() {
        let m = model.eval(*l, *v);
        for c in 0..3 {
            out[3 * i + c] = match space {
                Space::Log => ((m[c] * l.z + s.eps[c]) / (f[c] * l.z + s.eps[c])).ln(),
                Space::Cosine => (m[c] - f[c]) * l.z / s.rms[c],
            };
        }
    }
}

/// Leave out observations clipped at the data's maximum: a channel whose maximum is
/// reached (to 10⁻⁶) by at least 3 observations, and lies above 1.5 × its median, is
/// saturated there; those values are lower bounds, not measurements. Returns the kept observations and the count left out.
pub fn drop_saturated(obs: &Observations) -> (Observations, usize) {
    let mut max = [0.0f64; 3];
    for f in &obs.f {
        for c in 0..3 {
            max[c] = max[c].max(f[c]);
        }
    }
    let clipped = |f: &Rgb, c: usize| max[c] > 0.0 && f[c] >= max[c] * (1.0 - 1e-6);
    // A plateau at the maximum is clipping only above a darker majority: a constant
    // (Lambertian) data set has its maximum everywhere and is not saturated.
    let saturated: [bool; 3] = std::array::from_fn(|c| {
        let mut vals: Vec<f64> = obs.f.iter().map(|f| f[c]).collect();
        vals.sort_by(f64::total_cmp);
        let median = vals.get(vals.len() / 2).copied().unwrap_or(0.0);
        obs.f.iter().filter(|f| clipped(f, c)).count() >= 3 && max[c] > 1.5 * median
    });
    let mut out = Observations::default();
    let mut dropped = 0;
    for i in 0..obs.len() {
        if (0..3).any(|c| saturated[c] && clipped(&obs.f[i], c)) {
            dropped += 1;
        } else {
            out.push(obs.l[i], obs.v[i], obs.f[i]);
        }
    }
    (out, dropped)
}

/// Check the data can be fitted: some observations, all finite and ≥ 0, some signal.
pub fn check_observations(obs: &Observations, input: &str) -> Result<(), FitError> {
    let bad = |reason: String| {
        Err(FitError::Input {
            input: input.into(),
            reason,
        })
    };
    if obs.is_empty() {
        return bad("no observations (no measured pair with light and view above the horizon)".into());
    }
    for (i, f) in obs.f.iter().enumerate() {
        if f.iter().any(|x| !x.is_finite()) {
            return bad(format!("observation {i} has a non-finite value {f:?}"));
        }
        if f.iter().any(|x| *x < 0.0) {
            return bad(format!(
                "observation {i} has a negative value {f:?}: a BRDF is ≥ 0 (subtract the dark frame before, not after)"
            ));
        }
    }
    if obs.f.iter().all(|f| f.iter().all(|x| *x == 0.0)) {
        return bad("every value is zero: nothing to fit (a black sample, or the lamp was off)".into());
    }
    for (i, (l, v)) in obs.l.iter().zip(&obs.v).enumerate() {
        if !(l.z > 0.0 && v.z > 0.0) {
            return bad(format!("observation {i}: light or view below the horizon"));
        }
    }
    Ok(())
}

/// Per-channel diffuse estimate (π × the 25th percentile of the values) and the peak,
/// for the starts.
fn data_estimates(obs: &Observations) -> (Rgb, f64) {
    let mut d = [0.0; 3];
    for (c, dc) in d.iter_mut().enumerate() {
        let mut vals: Vec<f64> = obs.f.iter().map(|f| f[c]).collect();
        vals.sort_by(f64::total_cmp);
        *dc = (std::f64::consts::PI * vals[vals.len() / 4]).clamp(0.0, 1.0);
    }
    let peak = obs.f.iter().flat_map(|f| f.iter().copied()).fold(0.0f64, f64::max);
    (d, peak)
}

/// Fit from one start `x0` (solver coordinates); the workhorse of [`fit`] and of the
/// per-texel fit.
pub(crate) fn fit_from(
    family: &Family,
    obs: &Observations,
    space: Space,
    scales: &Scales,
    x0: &[f64],
    opts: &LmOptions,
) -> lm::LmResult {
    let (lo, hi): (Vec<f64>, Vec<f64>) = family.params.iter().map(|p| p.x_bounds()).unzip();
    let f = |x: &[f64], out: &mut [f64]| {
        let model = family.model(&family.values(x));
        residuals(&model, obs, space, scales, out);
    };
    lm::minimize(&f, 3 * obs.len(), x0, &lo, &hi, opts)
}

/// Fit `opts.kind` to `obs`. Errors only on unusable input or options; a fit that ends on
/// a bound, at the iteration cap or stalled is still a result, with the reason in `stop`.
pub fn fit(obs: &Observations, opts: &FitOptions, input: &str) -> Result<FitReport, FitError> {
    opts.check()?;
    check_observations(obs, input)?;
    let (kept, saturated) = drop_saturated(obs);
    if kept.len() < 3 {
        return Err(FitError::Input {
            input: input.into(),
            reason: format!(
                "{} of {} observations are saturated (clipped at the maximum): too few left to fit; \
                 measure with HDR (`--hdr auto`) or a shorter exposure",
                saturated,
                obs.len()
            ),
        });
    }
    let gltf = opts.kind == ModelKind::Gltf;
    let family = if gltf {
        Family::gltf_isotropic()
    } else {
        Family::new(opts.kind, opts.lobes)
    };
    let scales = Scales::of(&kept);
    let (diffuse, peak) = data_estimates(&kept);
    let runs: Vec<lm::LmResult> = (0..opts.starts)
        .into_par_iter()
        .map(|i| {
            let x0 = family.start(i, diffuse, peak);
            fit_from(&family, &kept, opts.space, &scales, &x0, &opts.lm)
        })
        .collect();
    // Lowest finite cost; ties go to the earlier start.
    let best = (0..runs.len())
        .filter(|&i| runs[i].cost.is_finite())
        .min_by(|&a, &b| runs[a].cost.total_cmp(&runs[b].cost).then(a.cmp(&b)))
        .ok_or_else(|| FitError::Input {
            input: input.into(),
            reason: format!(
                "no start of model `{}` gives finite residuals on these data",
                opts.kind.name()
            ),
        })?;
    let mut r = runs[best].clone();
    let mut family = family;
    let mut anisotropy = None;
    if gltf {
        // The anisotropy test (KHR_materials_anisotropy): from the isotropic fit, with
        // four directions; kept only past the margin.
        let iso_rel = diagnose(&family.model(&family.values(&r.params)), &kept, &scales).rel_rms;
        let (x, run, test) = select_anisotropy(
            &kept,
            opts.space,
            &scales,
            &r.params,
            iso_rel,
            &anisotropy_starts(),
            &opts.lm,
        );
        family = Family::new(ModelKind::Gltf, 1);
        r.params = x;
        if let Some(run) = run {
            r = run;
        }
        anisotropy = Some(test);
    }
    let values = family.values(&r.params);
    let brdf = family.model(&values);
    let stats = diagnose(&brdf, &kept, &scales);
    let m = 3 * kept.len();
    Ok(FitReport {
        model: opts.kind,
        lobes: family.lobes,
        space: opts.space,
        params: family.params.iter().map(|p| p.name.clone()).zip(values).collect(),
        anisotropy,
        at_bounds: family.at_bounds(&r.params),
        brdf,
        observations: kept.len(),
        saturated_excluded: saturated,
        cost_per_residual: r.cost / m as f64,
        rel_rms: stats.rel_rms,
        log_rms: stats.log_rms,
        failures: failures(&stats),
        by_elevation: stats.by_elevation,
        by_half_angle: stats.by_half_angle,
        best_start: best,
        stop: r.stop,
        iterations: r.iterations,
        starts: runs
            .iter()
            .enumerate()
            .map(|(i, r)| StartOutcome {
                start: i,
                cost: r.cost,
                iterations: r.iterations,
                stop: r.stop,
            })
            .collect(),
    })
}

/// Residual statistics of a model against observations.
#[derive(Clone, Debug)]
pub struct Diagnosis {
    pub rel_rms: f64,
    pub log_rms: f64,
    pub by_elevation: Vec<Band>,
    pub by_half_angle: Vec<Band>,
}

const ELEVATION_EDGES: [f64; 5] = [0.0, 30.0, 60.0, 75.0, 90.0];
const HALF_EDGES: [f64; 5] = [0.0, 5.0, 15.0, 40.0, 90.0];

#[derive(Default, Clone, Copy)]
struct Acc {
    n: usize,
    sq: f64,
    ref_sq: f64,
    log: f64,
    log_sq: f64,
}

impl Acc {
    fn band(&self, label: String) -> Band {
        Band {
            label,
            observations: self.n,
            rel_rms: if self.ref_sq > 0.0 {
                (self.sq / self.ref_sq).sqrt()
            } else {
                0.0
            },
            log_bias: self.log / (3 * self.n).max(1) as f64,
        }
    }
}

/// Residuals of `model` on `obs`, overall and by band.
pub fn diagnose(model: &BrdfModel, obs: &Observations, s: &Scales) -> Diagnosis {
    let mut all = Acc::default();
    let mut elev = [Acc::default(); 4];
    let mut half = [Acc::default(); 4];
    let band_of = |edges: &[f64; 5], a: f64| (0..4).find(|&b| a < edges[b + 1]).unwrap_or(3);
    for ((l, v), f) in obs.l.iter().zip(&obs.v).zip(&obs.f) {
        let m = model.eval(*l, *v);
        let mut a = Acc {
            n: 1,
            ..Default::default()
        };
        for c in 0..3 {
            let d = (m[c] - f[c]) * l.z;
            a.sq += d * d;
            a.ref_sq += (f[c] * l.z).powi(2);
            let lr = ((m[c] * l.z + s.eps[c]) / (f[c] * l.z + s.eps[c])).ln();
            a.log += lr;
            a.log_sq += lr * lr;
        }
        let th = l.z.min(v.z).clamp(-1.0, 1.0).acos().to_degrees();
        let h = (*l + *v).normalized();
        let th_h = h.z.clamp(-1.0, 1.0).acos().to_degrees();
        for acc in [
            &mut all,
            &mut elev[band_of(&ELEVATION_EDGES, th)],
            &mut half[band_of(&HALF_EDGES, th_h)],
        ] {
            acc.n += a.n;
            acc.sq += a.sq;
            acc.ref_sq += a.ref_sq;
            acc.log += a.log;
            acc.log_sq += a.log_sq;
        }
    }
    let label = |edges: &[f64; 5], b: usize, what: &str| format!("{what} {}–{}°", edges[b], edges[b + 1]);
    Diagnosis {
        rel_rms: all.band(String::new()).rel_rms,
        log_rms: (all.log_sq / (3 * all.n).max(1) as f64).sqrt(),
        by_elevation: (0..4)
            .filter(|&b| elev[b].n > 0)
            .map(|b| elev[b].band(label(&ELEVATION_EDGES, b, "max(θ_l, θ_v)")))
            .collect(),
        by_half_angle: (0..4)
            .filter(|&b| half[b].n > 0)
            .map(|b| half[b].band(label(&HALF_EDGES, b, "θ_h")))
            .collect(),
    }
}

/// Sentences on the bands where the model is off by more than 10 % on average (|log bias|
/// > 0.1) or whose relative RMS is over twice the overall one.
fn failures(d: &Diagnosis) -> Vec<String> {
    let mut out = Vec::new();
    for (bands, hint) in [
        (
            &d.by_elevation,
            "grazing angles: Fresnel and shadowing-masking are where models differ",
        ),
        (&d.by_half_angle, "the lobe's shape around the mirror direction"),
    ] {
        for b in bands {
            let biased = b.log_bias.abs() > 0.1;
            let rough = d.rel_rms > 0.0 && b.rel_rms > 2.0 * d.rel_rms && b.rel_rms > 0.05;
            if biased || rough {
                let dir = if b.log_bias > 0.0 { "too bright" } else { "too dark" };
                out.push(format!(
                    "{}: model {dir} by {:.0} % on average (relative RMS {:.3} vs {:.3} overall; {} observations) — {hint}",
                    b.label,
                    100.0 * (b.log_bias.exp() - 1.0).abs(),
                    b.rel_rms,
                    d.rel_rms,
                    b.observations
                ));
            }
        }
    }
    out
}
