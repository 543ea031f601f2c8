//! `gonio bench sparse`: error against rig time for sparse acquisition.
//!
//! The truth is the simulator's complete BTF of the sample (`gonio sim btf`, rendered here
//! or read with `--truth DIR`). A "measurement" of a pair is its truth image, with sensor
//! noise drawn from the rig's sensor model when noise is on (shot noise in electrons, read
//! noise, quantisation to the sensor's bit depth, clipping at full scale). For each budget
//! (a fraction of the canonical rig time of the whole sweep) every method gets as many
//! pairs as its plan fits in the budget (the existing planner orders and times them):
//!
//! * **ours**: greedy A-optimal design in the prior, per-texel MAP completion;
//! * **ours-auto** (asked for by name): the same design, the MAP's σ² chosen by
//!   leave-one-out on the measured values; measured, not reliably better;
//! * **ours-joint** (asked for by name): the same design, completed jointly across texels
//!   (`gonio_sparse::joint`: the material's Gaussian by EM); measured, not better;
//! * **project** (asked for by name, a diagnosis): the truth projected onto the prior's
//!   span with every pair known — the floor of any estimate in that prior;
//! * **ours-motion** (asked for by name): the motion-aware design (error drop per second
//!   of rig time, `gonio plan --design motion-aware`), the same completion;
//! * **adaptive** (asked for by name): rounds, by the plan steps `gonio acquire --adaptive`
//!   takes (`gonio_acquire::plan::adaptive`) — half the budget on the A-optimal design,
//!   then each round spends half of what is left (the last one all of it) on the pairs
//!   `gonio_sparse::adaptive` chooses from the measured values' residuals; each round is
//!   planned on its own (from home), and each analysis is charged its declared allowance of
//!   rig time (the wall time is in the note). The predicted PSNR is the residual-aware one;
//! * **(a) product**: m lights × m views spread by farthest-point sampling, completed by the
//!   triangle interpolation of `compress::interp` (n/a where its gap limit refuses);
//! * **(c) pca-ls**: random feasible pairs, least squares in the prior's basis (no
//!   eigenvalues), K' = min(K, n/2) components;
//! * **dense**: every feasible pair (blocked pairs completed by ours).
//!
//! PSNR is over every pair of the sweep against the truth on the 8-bit sRGB scale
//! (`compress::metrics::ErrorStats`, as `compress` reports it). Measured pairs are kept as
//! measured (with their noise).

use anyhow::{bail, Context, Result};
use gonio::cli::bench::load_prior;
use gonio::cli::bench::{coefficients, joint_completion, noise_var, predict_image};
use gonio::cli::bench::{load_sample, RigArgs};
use gonio::cli::bench::{log_log, Series};
use gonio_acquire::plan::sparse::{psnr_of_mse, units_key};
use gonio_acquire::plan::{Plan, PlanOptions};
use gonio_btf::compress::data::DatasetViews;
use gonio_btf::compress::interp::{direction_weights, dot, unit};
use gonio_btf::compress::metrics::ErrorStats;
use gonio_dataset::sweep::Sweep;
use gonio_sparse::{Completion, Normal, Prior};
use rayon::prelude::*;
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

mod krige;

#[derive(clap::Args, Debug)]
pub struct SparseBenchArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    /// The sample (built-in name or TOML file).
    #[arg(long, default_value = "wallpaper")]
    pub sample: String,
    /// The prior (.gprior or `default`).
    #[arg(long)]
    pub prior: Option<String>,
    #[arg(long, default_value = "bonn81")]
    pub sweep: String,
    /// Budgets as fractions of the canonical rig time of the whole sweep.
    #[arg(long, value_delimiter = ',', default_value = "0.02,0.05,0.1,0.2,0.5,1")]
    pub fractions: Vec<f64>,
    /// Texels per side of the truth.
    #[arg(long, default_value_t = 32)]
    pub size: usize,
    /// Sensor noise: on, off or both.
    #[arg(long, default_value = "both")]
    pub noise: String,
    /// A complete truth dataset to use instead of rendering (`gonio sim btf` output).
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// Kicks of the order optimizer (per plan; the bisection on pair counts plans often).
    #[arg(long, default_value_t = 2000)]
    pub plan_kicks: usize,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Only these methods (ours, ours-krige, ours-constant, ours-auto, ours-joint, ours-motion, adaptive, mixture, mixture+global,
    /// project, product, pca-ls, dense;
    /// `project` is the diagnosis: the truth projected onto the prior's span).
    #[arg(long, value_delimiter = ',', default_value = "ours,product,pca-ls,dense")]
    pub methods: Vec<String>,
    /// Measurement noise RMS (8-bit codes) the MAP weights and designs assume, added to the
    /// prior's out-of-basis variance (as `gonio complete --noise-codes`).
    #[arg(long, default_value_t = 0.0)]
    pub noise_codes: f64,
    /// Method `adaptive`: the rounds' residual weight (as `gonio acquire --residual-weight`).
    #[arg(long)]
    pub residual_weight: Option<f64>,
    /// Method `adaptive`: seconds charged per analysis (as `gonio acquire --round-allowance`).
    #[arg(long)]
    pub round_allowance: Option<f64>,
    /// Method `mixture`: a prior mixture (`gonio prior build --clusters C`, a .gmix file)
    /// that completes `ours`'s design, each texel in the member of largest evidence.
    #[arg(long)]
    pub mixture: Option<PathBuf>,
    #[arg(long)]
    pub plot: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
}

#[derive(Clone, Debug, Serialize)]
pub struct Row {
    pub noise: bool,
    pub method: String,
    pub fraction: f64,
    pub budget_s: f64,
    pub pairs: usize,
    pub planned_s: f64,
    /// PSNR against the truth, 8-bit sRGB, over every pair of the sweep; None = n/a.
    pub psnr_db: Option<f64>,
    /// What the posterior predicts (ours only).
    pub predicted_psnr_db: Option<f64>,
    pub note: String,
}

#[derive(Serialize)]
struct BenchJson {
    sample: String,
    seen_by_prior: bool,
    label: &'static str,
    prior: String,
    size: usize,
    canonical_s: f64,
    full_optimized_s: f64,
    feasible: usize,
    rows: Vec<Row>,
}

/// The truth BTF: `truth[p]` is pair p's linear interleaved image.
fn render_truth(a: &SparseBenchArgs, rig: &gonio_devices::rig::RigSpec, sweep: &Sweep) -> Result<Vec<Vec<f32>>> {
    use gonio_simulator::{RenderQuality, Renderer, SimOptions};
    let spec = load_sample(&a.sample)?;
    let sample = spec.build().with_context(|| format!("building sample {}", a.sample))?;
    let renderer = Arc::new(Renderer::new(Arc::new(sample), RenderQuality::default()));
    let sim = gonio_simulator::build_sim_rig(rig, renderer.clone(), &SimOptions::default())?;
    let radius = sim.world.lamp_radius_mm;
    let scale = gonio::synth::truth_scale(&sim.world.sensor.lock().expect("sensor lock"));
    let mut out = vec![Vec::new(); sweep.len()];
    let l = sweep.lights.len();
    gonio::synth::render_btf(&renderer, rig, radius, sweep, a.size, scale, |v, li, img| {
        out[v * l + li] = img.data;
        Ok::<(), anyhow::Error>(())
    })?;
    Ok(out)
}

fn read_truth(dir: &std::path::Path) -> Result<(DatasetViews, Vec<Vec<f32>>)> {
    let ds = DatasetViews::open(dir)?;
    let l = ds.n_lights();
    let d = l * ds.n_views();
    let imgs = (0..d)
        .into_par_iter()
        .map(|p| {
            ds.read_image(p % l, p / l)?
                .with_context(|| format!("{}: pair {p} missing; the truth must be complete", dir.display()))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok((ds, imgs))
}

/// Sensor noise on a normalised value (electrons: shot + read; DN quantisation; clip at 1).
struct Noise {
    e_per_unit: f64,
    read_e: f64,
    levels: f64,
}

impl Noise {
    fn apply(&self, img: &[f32], seed: u64) -> Vec<f32> {
        let mut rng = Normal::new(seed);
        img.iter()
            .map(|&s| {
                let e = (s as f64).max(0.0) * self.e_per_unit;
                let n = e + e.sqrt() * rng.sample() + self.read_e * rng.sample();
                let v = (n / self.e_per_unit).clamp(0.0, 1.0);
                ((v * self.levels).round() / self.levels) as f32
            })
            .collect()
    }
}

/// Farthest-point order of directions, starting at the first (the pole for Bonn).
fn farthest_points(dirs: &[[f64; 2]]) -> Vec<usize> {
    let u: Vec<[f64; 3]> = dirs.iter().map(|&d| unit(d)).collect();
    let mut order = vec![0usize];
    let mut near: Vec<f64> = u.iter().map(|&x| 1.0 - dot(x, u[0])).collect();
    while order.len() < u.len() {
        let (mut best, mut arg) = (-1.0, 0);
        for (i, &n) in near.iter().enumerate() {
            if n > best {
                best = n;
                arg = i;
            }
        }
        order.push(arg);
        for (i, &x) in u.iter().enumerate() {
            near[i] = near[i].min(1.0 - dot(x, u[arg]));
        }
    }
    order
}

struct Ctx<'a> {
    rig: &'a gonio_devices::rig::RigSpec,
    sweep: &'a Sweep,
    opts: PlanOptions,
    feasible: Vec<usize>,
    full: &'a Plan,
}

impl Ctx<'_> {
    fn plan(&self, idx: &[usize]) -> Result<Plan> {
        let pairs = self.sweep.pairs();
        let mut idx = idx.to_vec();
        idx.sort_unstable();
        let chosen: Vec<_> = idx.iter().map(|&i| pairs[i]).collect();
        Ok(Plan::build_pairs(self.rig, self.sweep, &chosen, &self.opts)?)
    }
    /// The largest `n` in `1..=max` whose set `set(n)` plans within `budget`, and its plan.
    fn fit(&self, max: usize, budget: f64, set: impl Fn(usize) -> Vec<usize>) -> Result<Option<(usize, Plan)>> {
        if self.full.durations.optimized_s <= budget && max >= self.feasible.len() {
            // Everything fits (the set of `max` is every feasible pair).
            let p = self.plan(&set(max))?;
            if p.durations.optimized_s <= budget {
                return Ok(Some((max, p)));
            }
        }
        let (mut lo, mut hi) = (0usize, max);
        let mut best: Option<Plan> = None;
        while lo < hi {
            let mid = (lo + hi).div_ceil(2);
            let p = self.plan(&set(mid))?;
            if p.durations.optimized_s <= budget {
                lo = mid;
                best = Some(p);
            } else {
                hi = mid - 1;
            }
        }
        if lo == 0 {
            return Ok(None);
        }
        let p = match best {
            Some(p) if p.steps.len() == set(lo).len() => p,
            _ => self.plan(&set(lo))?,
        };
        Ok(Some((lo, p)))
    }
}

fn psnr(truth: &[Vec<f32>], recon: &[Vec<f32>]) -> f64 {
    let parts: Vec<ErrorStats> = truth
        .par_iter()
        .zip(recon)
        .map(|(t, r)| {
            let mut e = ErrorStats::default();
            e.add(t, r);
            e
        })
        .collect();
    let mut e = ErrorStats::default();
    for p in &parts {
        e.merge(p);
    }
    e.psnr_8bit()
}

/// Every pair of the sweep: the measured ones as measured, the others predicted by `c`.
fn fill(c: &Completion, measured: &[usize], meas: &[Vec<f32>]) -> Vec<Vec<f32>> {
    let refs: Vec<&[f32]> = measured.iter().map(|&i| meas[i].as_slice()).collect();
    let a = coefficients(c, &refs);
    fill_from(c, &a, measured, meas)
}

/// The full grid from coefficients `a`: measured pairs as measured, the rest predicted.
fn fill_from(c: &Completion, a: &nalgebra::DMatrix<f64>, measured: &[usize], meas: &[Vec<f32>]) -> Vec<Vec<f32>> {
    let mut is_m = vec![false; c.prior.dims()];
    measured.iter().for_each(|&i| is_m[i] = true);
    (0..c.prior.dims())
        .into_par_iter()
        .map(|q| {
            if is_m[q] {
                meas[q].clone()
            } else {
                predict_image(c, a, q)
            }
        })
        .collect()
}

/// Texels (three channels each) whose measured values choose `ours-auto`'s σ².
const LOO_TEXELS: usize = 512;

/// `ours-constant`, `ours-auto`: MAP completion with one noise variance `nv` for every
/// pair, clipped readings fitted as values (the method before the sensor model).
fn complete_map(prior: &Prior, measured: &[usize], meas: &[Vec<f32>], nv: f64) -> Result<(Vec<Vec<f32>>, f64)> {
    let p = prior.truncated(prior.components().min(measured.len()));
    let c = Completion::new(&p, measured, nv)?;
    Ok((fill(&c, measured, meas), psnr_of_mse(c.predicted_mse())))
}

/// Ours, as `gonio complete` does it: each measured pair weighed by its own sensor noise
/// in model space (`gonio_sparse::noise`, from the rig's sensor model and the pair's
/// readings) on top of the prior's ρ_p, and readings clipped at full scale (1) fitted as
/// lower bounds (`Completion::coefficients_censored`).
fn complete_sensor(
    prior: &Prior,
    measured: &[usize],
    meas: &[Vec<f32>],
    sensor: &gonio_devices::hdr::SensorNoise,
) -> Result<(Vec<Vec<f32>>, f64)> {
    let p = prior.truncated(prior.components().min(measured.len()));
    let fit = SensorFit::new(&p, measured, meas, sensor)?;
    Ok((
        fill_from(&fit.completion, &fit.coefficients, measured, meas),
        psnr_of_mse(fit.completion.predicted_mse()),
    ))
}

/// Ours' fit of the `measured` pairs in `p` (already truncated to at most the pairs), the
/// one [`complete_sensor`] and `ours-krige` share: the completion weighed by each pair's
/// sensor noise, that noise (model space), and the censored coefficients (K × M).
struct SensorFit<'a> {
    completion: Completion<'a>,
    noise: Vec<f64>,
    coefficients: nalgebra::DMatrix<f64>,
}

impl<'a> SensorFit<'a> {
    fn new(
        p: &'a Prior,
        measured: &[usize],
        meas: &[Vec<f32>],
        sensor: &gonio_devices::hdr::SensorNoise,
    ) -> Result<Self> {
        let refs: Vec<&[f32]> = measured.iter().map(|&i| meas[i].as_slice()).collect();
        let noise = gonio::cli::bench::sensor_pair_noise(p.space(), &refs, sensor);
        let completion = Completion::with_pair_noise(p, measured, &noise)?;
        let (coefficients, _clipped) = gonio::cli::bench::coefficients_censored(&completion, &refs, 1.0);
        Ok(SensorFit {
            completion,
            noise,
            coefficients,
        })
    }
}

/// Ours with a prior mixture: the same sensor noise and censored fit as
/// [`complete_sensor`] in every member, each texel completed in the member whose log
/// evidence (over its three channels) is largest. Returns the images and how many texels
/// each member completed.
fn complete_mixture(
    mix: &gonio_sparse::mixture::Mixture,
    global: Option<&Prior>,
    measured: &[usize],
    meas: &[Vec<f32>],
    sensor: &gonio_devices::hdr::SensorNoise,
) -> Result<(Vec<Vec<f32>>, Vec<usize>)> {
    let mut members: Vec<Prior> = mix
        .members
        .iter()
        .map(|p| p.truncated(p.components().min(measured.len())))
        .collect();
    let mut log_weights = mix.log_weights();
    // `mixture+global`: the global prior as one more member, with half the weight.
    if let Some(g) = global {
        members.push(g.truncated(g.components().min(measured.len())));
        log_weights.iter_mut().for_each(|w| *w += 0.5f64.ln());
        log_weights.push(0.5f64.ln());
    }
    let space = members[0].space();
    let refs: Vec<&[f32]> = measured.iter().map(|&i| meas[i].as_slice()).collect();
    let noise = gonio::cli::bench::sensor_pair_noise(space, &refs, sensor);
    let fit = gonio_sparse::mixture::MixtureFit::new(&members, log_weights, measured, &noise)?;
    let m = refs.first().map_or(0, |i| i.len());
    let y = nalgebra::DMatrix::<f64>::from_fn(refs.len(), m, |i, j| space.forward(refs[i][j] as f64));
    let ceiling = space.forward(1.0);
    let (coeffs, choice) = fit.choose(&y, 3, |c, y| c.coefficients_censored(y, ceiling, 50).0)?;
    let mut counts = vec![0usize; members.len()];
    choice.iter().for_each(|&c| counts[c] += 1);
    let mut is_m = vec![false; members[0].dims()];
    measured.iter().for_each(|&i| is_m[i] = true);
    let images = (0..members[0].dims())
        .into_par_iter()
        .map(|q| {
            if is_m[q] {
                return meas[q].clone();
            }
            (0..m)
                .map(|j| {
                    let c = choice[j / 3];
                    let p = &members[c];
                    let v = (p.basis.row(q) * coeffs[c].column(j))[(0, 0)] + p.mean[q];
                    space.inverse(v) as f32
                })
                .collect()
        })
        .collect();
    Ok((images, counts))
}

/// Ours, joint across texels: the material's Gaussian fitted by EM from every texel's
/// measured pairs, then each texel's posterior mean.
fn complete_joint(prior: &Prior, measured: &[usize], meas: &[Vec<f32>]) -> Result<(Vec<Vec<f32>>, f64, String)> {
    let p = prior.truncated(prior.components().min(measured.len()));
    let refs: Vec<&[f32]> = measured.iter().map(|&i| meas[i].as_slice()).collect();
    let (c, rep) = joint_completion(&p, measured, &refs, 0.0)?;
    let note = format!(
        "K = {}, EM {} it, eff. dims {:.1}, σ² {:.2e}",
        p.components(),
        rep.iterations,
        rep.effective_dims,
        rep.noise_var
    );
    Ok((fill(&c, measured, meas), psnr_of_mse(c.predicted_mse()), note))
}

/// Diagnosis: the truth projected onto the prior's span (mean + basis, every pair known):
/// the best any coefficient estimate can do.
fn project(prior: &Prior, truth: &[Vec<f32>]) -> Result<Vec<Vec<f32>>> {
    let all: Vec<usize> = (0..prior.dims()).collect();
    let c = Completion::least_squares(prior, &all)?;
    let refs: Vec<&[f32]> = truth.iter().map(|v| v.as_slice()).collect();
    let a = coefficients(&c, &refs);
    Ok((0..prior.dims())
        .into_par_iter()
        .map(|q| predict_image(&c, &a, q))
        .collect())
}

/// Baseline (c): least squares in the prior's first min(K, n/2) basis vectors.
fn complete_ls(prior: &Prior, measured: &[usize], meas: &[Vec<f32>]) -> Result<Vec<Vec<f32>>> {
    let p = prior.truncated(prior.components().min(measured.len() / 2).max(1));
    let c = Completion::least_squares(&p, measured)?;
    Ok(fill(&c, measured, meas))
}

/// Baseline (a): product subset completed by triangle interpolation; None when the gap
/// limit refuses some pair.
fn complete_product(
    lights_deg: &[[f64; 2]],
    views_deg: &[[f64; 2]],
    ls: &[usize],
    vs: &[usize],
    meas: &[Vec<f32>],
    feasible: &[bool],
) -> Option<Vec<Vec<f32>>> {
    let l = lights_deg.len();
    let sub_l: Vec<[f64; 2]> = ls.iter().map(|&i| lights_deg[i]).collect();
    let sub_v: Vec<[f64; 2]> = vs.iter().map(|&i| views_deg[i]).collect();
    // A blocked pair of the product is filled from the nearest measured light of its view.
    let value = |li: usize, vi: usize| -> &Vec<f32> {
        let p = vs[vi] * l + ls[li];
        if feasible[p] {
            return &meas[p];
        }
        let mut best = (f64::MAX, p);
        for (j, &lj) in ls.iter().enumerate() {
            let q = vs[vi] * l + lj;
            if j != li && feasible[q] {
                let (a, b) = (lights_deg[ls[li]], lights_deg[lj]);
                let dd = (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2);
                if dd < best.0 {
                    best = (dd, q);
                }
            }
        }
        &meas[best.1]
    };
    let wl: Vec<_> = lights_deg
        .iter()
        .map(|&d| direction_weights(&sub_l, d, "light").ok())
        .collect::<Option<Vec<_>>>()?;
    let wv: Vec<_> = views_deg
        .iter()
        .map(|&d| direction_weights(&sub_v, d, "view").ok())
        .collect::<Option<Vec<_>>>()?;
    let m = meas[0].len();
    Some(
        (0..l * views_deg.len())
            .into_par_iter()
            .map(|p| {
                if feasible[p] && ls.contains(&(p % l)) && vs.contains(&(p / l)) {
                    return meas[p].clone();
                }
                let mut out = vec![0f32; m];
                for &(vi, a) in &wv[p / l] {
                    for &(li, b) in &wl[p % l] {
                        let w = (a * b) as f32;
                        for (o, x) in out.iter_mut().zip(value(li, vi)) {
                            *o += w * x;
                        }
                    }
                }
                out
            })
            .collect(),
    )
}

pub fn run(a: SparseBenchArgs) -> Result<ExitCode> {
    let rig = a.rig.load()?;
    let sweep = Sweep::resolve(&a.sweep)?;
    let (prior, prior_path) = load_prior(a.prior.as_deref())?;
    let tuning = gonio_acquire::plan::adaptive::AdaptiveTuning::new(a.residual_weight, a.round_allowance)?;
    let (lights, views) = sweep.directions_deg();
    let (sample_name, truth) = match &a.truth {
        Some(dir) => {
            let (ds, t) = read_truth(dir)?;
            prior.check_compatible(
                &gonio::cli::bench::sweep_name(&ds),
                &ds.lights_deg,
                &ds.views_deg,
                &units_key(&ds.header.values),
            )?;
            (
                gonio::cli::bench::sample_name(&ds).unwrap_or_else(|| a.sample.clone()),
                t,
            )
        }
        None => {
            prior.check_compatible(&sweep.name, &lights, &views, "normalized_signal")?;
            (load_sample(&a.sample)?.name, render_truth(&a, &rig, &sweep)?)
        }
    };
    if truth.len() != sweep.len() {
        bail!("the truth has {} pairs, the sweep {}", truth.len(), sweep.len());
    }
    let seen = prior.has_seen(&sample_name);
    let opts = PlanOptions {
        kicks: a.plan_kicks,
        ..PlanOptions::default()
    };
    let full = Plan::build(&rig, &sweep, &opts)?;
    let mut feasible: Vec<usize> = full.steps.iter().map(|s| s.index).collect();
    feasible.sort_unstable();
    let mut is_feasible = vec![false; sweep.len()];
    feasible.iter().for_each(|&p| is_feasible[p] = true);
    let ctx = Ctx {
        rig: &rig,
        sweep: &sweep,
        opts,
        feasible: feasible.clone(),
        full: &full,
    };
    let canonical = full.durations.canonical_s;
    let nv = noise_var(&prior, a.noise_codes);
    let design: Vec<usize> = gonio_sparse::greedy_design(&prior, &feasible, &[], feasible.len(), nv)?
        .iter()
        .map(|s| s.pair)
        .collect();
    let random: Vec<usize> = {
        // A seeded random order of the feasible pairs (each prefix is a random subset).
        let mut r = Normal::new(a.seed ^ 0xc0ffee);
        let mut v = feasible.clone();
        for i in (1..v.len()).rev() {
            let j = (r.next_u64() % (i as u64 + 1)) as usize;
            v.swap(i, j);
        }
        v
    };
    let fp_l = farthest_points(&lights);
    let fp_v = farthest_points(&views);
    let product = |m: usize| -> (Vec<usize>, Vec<usize>) {
        let mut ls: Vec<usize> = fp_l[..m].to_vec();
        let mut vs: Vec<usize> = fp_v[..m].to_vec();
        ls.sort_unstable();
        vs.sort_unstable();
        (ls, vs)
    };
    let product_pairs = |m: usize| -> Vec<usize> {
        let (ls, vs) = product(m);
        let l = lights.len();
        vs.iter()
            .flat_map(|&v| ls.iter().map(move |&li| v * l + li))
            .filter(|&p| is_feasible[p])
            .collect()
    };
    let noises: Vec<bool> = match a.noise.as_str() {
        "on" => vec![true],
        "off" => vec![false],
        "both" => vec![true, false],
        o => bail!("--noise {o}: use on, off or both"),
    };
    // The rig's sensor noise model from its rig file (the one the simulated camera uses).
    let sensor = gonio_devices::hdr::HdrSpec::default().noise(&rig.camera, rig.camera.gain);
    let noise = Noise {
        e_per_unit: sensor.full_well_e / sensor.gain,
        read_e: sensor.read_noise_e,
        levels: sensor.max_dn,
    };
    let want = |m: &str| a.methods.iter().any(|x| x == m);
    // Methods `mixture` and `mixture+global`: the mixture, loaded once.
    let mixture = if want("mixture") || want("mixture+global") {
        let path = a
            .mixture
            .as_ref()
            .ok_or_else(|| anyhow::anyhow!("methods `mixture` and `mixture+global` need --mixture FILE.gmix"))?;
        Some(gonio_sparse::mixture::Mixture::load(path).with_context(|| format!("--mixture {}", path.display()))?)
    } else {
        None
    };
    let mut rows = Vec::new();
    for &noisy in &noises {
        let meas: Vec<Vec<f32>> = if noisy {
            truth
                .par_iter()
                .enumerate()
                .map(|(p, t)| noise.apply(t, a.seed.wrapping_mul(1_000_003).wrapping_add(p as u64)))
                .collect()
        } else {
            truth.clone()
        };
        if want("project") {
            let rec = project(&prior, &truth)?;
            rows.push(Row {
                noise: noisy,
                method: "project".into(),
                fraction: 0.0,
                budget_s: 0.0,
                pairs: sweep.len(),
                planned_s: 0.0,
                psnr_db: Some(psnr(&truth, &rec)),
                predicted_psnr_db: Some(psnr_of_mse(prior.header.residual_var)),
                note: format!(
                    "diagnosis: the truth projected onto the prior's span (K = {})",
                    prior.components()
                ),
            });
        }
        if want("dense") {
            let (rec, pred) = complete_sensor(&prior, &feasible, &meas, &sensor)?;
            rows.push(Row {
                noise: noisy,
                method: "dense".into(),
                fraction: full.durations.optimized_s / canonical,
                budget_s: full.durations.optimized_s,
                pairs: feasible.len(),
                planned_s: full.durations.optimized_s,
                psnr_db: Some(psnr(&truth, &rec)),
                predicted_psnr_db: Some(pred),
                note: "every feasible pair; blocked pairs completed by ours".into(),
            });
        }
        for &f in &a.fractions {
            let budget = f * canonical;
            // A method completed from the designed pairs: the design's longest prefix whose
            // plan fits the budget, measured, then completed by `complete` (reconstruction,
            // predicted PSNR, note).
            type Completed = (Vec<Vec<f32>>, Option<f64>, String);
            let on_design = |method: &str, complete: &dyn Fn(&[usize]) -> Result<Completed>| -> Result<Row> {
                Ok(match ctx.fit(design.len(), budget, |n| design[..n].to_vec())? {
                    Some((n, plan)) => {
                        let (rec, pred, note) = complete(&design[..n])?;
                        Row {
                            noise: noisy,
                            method: method.into(),
                            fraction: f,
                            budget_s: budget,
                            pairs: n,
                            planned_s: plan.durations.optimized_s,
                            psnr_db: Some(psnr(&truth, &rec)),
                            predicted_psnr_db: pred,
                            note,
                        }
                    }
                    None => na(noisy, method, f, budget, "no pair fits"),
                })
            };
            if want("ours") {
                rows.push(on_design("ours", &|m| {
                    let (rec, pred) = complete_sensor(&prior, m, &meas, &sensor)?;
                    Ok((rec, Some(pred), format!("K = {}", prior.components().min(m.len()))))
                })?);
            }
            if want("ours-krige") {
                rows.push(on_design("ours-krige", &|m| {
                    let (rec, note) = krige::complete(&prior, &lights, &views, m, &meas, &sensor)?;
                    Ok((rec, None, note))
                })?);
            }
            for method in ["mixture", "mixture+global"].into_iter().filter(|m| want(m)) {
                // Loaded above whenever a mixture method is wanted.
                let Some(mix) = mixture.as_ref() else { break };
                let global = (method == "mixture+global").then_some(&prior);
                rows.push(on_design(method, &|m| {
                    let (rec, counts) = complete_mixture(mix, global, m, &meas, &sensor)?;
                    let note = format!("{} members, texels per member {counts:?}", counts.len());
                    Ok((rec, None, note))
                })?);
            }
            if want("ours-constant") {
                rows.push(on_design("ours-constant", &|m| {
                    let (rec, pred) = complete_map(&prior, m, &meas, nv)?;
                    let note = format!(
                        "K = {}, one noise variance for every pair, clipped readings as values",
                        prior.components().min(m.len())
                    );
                    Ok((rec, Some(pred), note))
                })?);
            }
            if want("ours-auto") {
                // The same design; the MAP's σ² chosen by leave-one-out on the measured
                // values (`gonio_sparse::complete::loo_noise_var`). Measured, not adopted
                // (docs/guide/sparse.md).
                rows.push(on_design("ours-auto", &|m| {
                    let n = m.len();
                    let p = prior.truncated(prior.components().min(n));
                    let texels = meas.first().map_or(0, |x| x.len() / 3);
                    let pick = gonio::cli::bench::spread_texels(texels, LOO_TEXELS);
                    let space = prior.space();
                    let y = nalgebra::DMatrix::<f64>::from_fn(n, pick.len() * 3, |i, j| {
                        space.forward(meas[m[i]][3 * pick[j / 3] + j % 3] as f64)
                    });
                    let choice = gonio_sparse::complete::loo_noise_var(&p, m, &y, nv)?;
                    let (rec, pred) = complete_map(&prior, m, &meas, choice.noise_var)?;
                    let note = format!(
                        "K = {}, σ = {:.2} codes by leave-one-out",
                        p.components(),
                        choice.noise_var.sqrt() * 255.0
                    );
                    Ok((rec, Some(pred), note))
                })?);
            }
            if want("ours-joint") {
                rows.push(on_design("ours-joint", &|m| {
                    let (rec, pred, note) = complete_joint(&prior, m, &meas)?;
                    Ok((rec, Some(pred), note))
                })?);
            }
            if want("ours-motion") {
                // The motion-aware design (gain per second of rig time), as
                // `gonio plan --design motion-aware --rig-budget` makes it.
                let req = gonio_acquire::plan::sparse::SparseRequest {
                    prior: &prior,
                    prior_name: "bench",
                    target: gonio_acquire::plan::sparse::SparseTarget::RigBudget(budget),
                    noise_var: nv,
                    design: gonio_acquire::plan::sparse::SparseDesign::MotionAware,
                };
                rows.push(match Plan::build_sparse(&rig, &sweep, &ctx.opts, &full, req) {
                    Ok(plan) => {
                        let mut m: Vec<usize> = plan.steps.iter().map(|s| s.index).collect();
                        m.sort_unstable();
                        let (rec, pred) = complete_sensor(&prior, &m, &meas, &sensor)?;
                        Row {
                            noise: noisy,
                            method: "ours-motion".into(),
                            fraction: f,
                            budget_s: budget,
                            pairs: m.len(),
                            planned_s: plan.durations.optimized_s,
                            psnr_db: Some(psnr(&truth, &rec)),
                            predicted_psnr_db: Some(pred),
                            note: format!("K = {}", prior.components().min(m.len())),
                        }
                    }
                    Err(e) => na(noisy, "ours-motion", f, budget, &e.to_string()),
                });
            }
            if want("adaptive") {
                rows.push(match adaptive(&ctx, &prior, &meas, budget, nv, &sensor, tuning)? {
                    Some(run) => {
                        let (rec, _) = complete_sensor(&prior, &run.measured, &meas, &sensor)?;
                        Row {
                            noise: noisy,
                            method: "adaptive".into(),
                            fraction: f,
                            budget_s: budget,
                            pairs: run.measured.len(),
                            planned_s: run.rig_s,
                            psnr_db: Some(psnr(&truth, &rec)),
                            predicted_psnr_db: Some(run.predicted_psnr_db),
                            note: run.note,
                        }
                    }
                    None => na(noisy, "adaptive", f, budget, "no pair fits"),
                });
            }
            if want("pca-ls") {
                let fit = ctx.fit(random.len(), budget, |n| random[..n].to_vec())?;
                rows.push(match fit {
                    Some((n, plan)) if n >= 2 => {
                        let m: Vec<usize> = {
                            let mut v = random[..n].to_vec();
                            v.sort_unstable();
                            v
                        };
                        match complete_ls(&prior, &m, &meas) {
                            Ok(rec) => Row {
                                noise: noisy,
                                method: "pca-ls".into(),
                                fraction: f,
                                budget_s: budget,
                                pairs: n,
                                planned_s: plan.durations.optimized_s,
                                psnr_db: Some(psnr(&truth, &rec)),
                                predicted_psnr_db: None,
                                note: format!("K' = {}", prior.components().min(n / 2).max(1)),
                            },
                            Err(e) => na(noisy, "pca-ls", f, budget, &e.to_string()),
                        }
                    }
                    _ => na(noisy, "pca-ls", f, budget, "fewer than 2 pairs fit"),
                });
            }
            if want("product") {
                let fit = ctx.fit(lights.len().min(views.len()), budget, product_pairs)?;
                rows.push(match fit {
                    Some((m, plan)) => {
                        let (ls, vs) = product(m);
                        match complete_product(&lights, &views, &ls, &vs, &meas, &is_feasible) {
                            Some(rec) => Row {
                                noise: noisy,
                                method: "product".into(),
                                fraction: f,
                                budget_s: budget,
                                pairs: plan.steps.len(),
                                planned_s: plan.durations.optimized_s,
                                psnr_db: Some(psnr(&truth, &rec)),
                                predicted_psnr_db: None,
                                note: format!("{m} lights × {m} views"),
                            },
                            None => Row {
                                pairs: plan.steps.len(),
                                planned_s: plan.durations.optimized_s,
                                ..na(
                                    noisy,
                                    "product",
                                    f,
                                    budget,
                                    &format!("{m} × {m}: gap limit of compress::interp refuses"),
                                )
                            },
                        }
                    }
                    None => na(noisy, "product", f, budget, "no product set fits"),
                });
            }
        }
    }
    let label = if seen { "seen" } else { "held-out" };
    if let Some(path) = &a.plot {
        let mut series = Vec::new();
        for &noisy in &noises {
            for m in ["ours", "product", "pca-ls", "dense"] {
                let points: Vec<(f64, f64, String)> = rows
                    .iter()
                    .filter(|r| r.noise == noisy && r.method == m)
                    .filter_map(|r| r.psnr_db.map(|p| (r.planned_s, p, format!("{:.2}", r.fraction))))
                    .collect();
                if !points.is_empty() {
                    series.push(Series {
                        name: format!("{m} (noise {})", if noisy { "on" } else { "off" }),
                        points,
                    });
                }
            }
        }
        let svg = log_log(
            &format!("sparse acquisition: {sample_name} ({label}), {}²", a.size),
            "planned rig time (s)",
            "PSNR vs truth (dB, 8-bit sRGB)",
            &series,
        );
        std::fs::write(path, svg).with_context(|| format!("writing {}", path.display()))?;
    }
    let out = BenchJson {
        sample: sample_name.clone(),
        seen_by_prior: seen,
        label,
        prior: prior_path.display().to_string(),
        size: a.size,
        canonical_s: canonical,
        full_optimized_s: full.durations.optimized_s,
        feasible: feasible.len(),
        rows,
    };
    if a.json {
        println!("{}", serde_json::to_string(&out)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "sample {} ({label}) · prior {} · {}² · canonical {:.0} s, dense optimized {:.0} s, {} feasible pairs",
        out.sample, out.prior, a.size, canonical, out.full_optimized_s, out.feasible
    );
    println!(
        "{:>5}  {:<8} {:>6} {:>9} {:>6} {:>9} {:>8} {:>9}  note",
        "noise", "method", "frac", "budget s", "pairs", "planned s", "PSNR dB", "pred dB"
    );
    for r in &out.rows {
        println!(
            "{:>5}  {:<8} {:>6.3} {:>9.0} {:>6} {:>9.0} {:>8} {:>9}  {}",
            if r.noise { "on" } else { "off" },
            r.method,
            r.fraction,
            r.budget_s,
            r.pairs,
            r.planned_s,
            r.psnr_db.map_or("n/a".into(), |p| format!("{p:.2}")),
            r.predicted_psnr_db.map_or("".into(), |p| format!("{p:.2}")),
            r.note
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// One adaptive run's outcome.
struct AdaptiveRun {
    measured: Vec<usize>,
    /// Planned rig time of every round plus the analysis allowances (s).
    rig_s: f64,
    /// The residual-aware prediction after the last round (dB).
    predicted_psnr_db: f64,
    note: String,
}

/// The adaptive rounds against the noisy truth, by the very plan steps `gonio acquire
/// --adaptive` takes ([`Plan::build_adaptive`], [`Plan::adaptive_next`]): a measurement is
/// the noisy truth image, read at the same analysis texels.
fn adaptive(
    ctx: &Ctx,
    prior: &Prior,
    meas: &[Vec<f32>],
    budget: f64,
    nv: f64,
    sensor: &gonio_devices::hdr::SensorNoise,
    tuning: gonio_acquire::plan::adaptive::AdaptiveTuning,
) -> Result<Option<AdaptiveRun>> {
    use gonio_acquire::plan::adaptive::{analysis_row, analysis_texels, AdaptiveRequest, AdaptiveStop};
    let stop = AdaptiveStop::new(None, Some(budget))?;
    let req = AdaptiveRequest {
        prior,
        prior_name: "bench",
        stop,
        noise_var: nv,
        tuning,
    };
    let mut plan = match Plan::build_adaptive(ctx.rig, ctx.sweep, &ctx.opts, ctx.full, req) {
        Ok(p) => p,
        Err(e) => {
            tracing::info!(error = %e, "adaptive: no first round");
            return Ok(None);
        }
    };
    let space = prior.space();
    let texels = meas.first().map_or(0, |m| m.len() / 3);
    let ad_texels = plan.adaptive().map_or(0, |a| a.analysis_texels);
    let pick = analysis_texels(texels, ad_texels);
    let mut compute = 0.0;
    loop {
        let ad = plan.adaptive().expect("adaptive plan");
        let mut measured = ad.chosen();
        measured.sort_unstable();
        let rows: Vec<(Vec<f64>, f64)> = measured
            .iter()
            .map(|&p| analysis_row(&meas[p], &pick, space, sensor))
            .collect();
        let values = nalgebra::DMatrix::<f64>::from_fn(measured.len(), pick.len() * 3, |i, j| rows[i].0[j]);
        let noise: Vec<f64> = rows.iter().map(|r| r.1).collect();
        let t = std::time::Instant::now();
        let added = plan.adaptive_next(ctx.rig, ctx.sweep, &ctx.opts, prior, &measured, &values, &noise)?;
        compute += t.elapsed().as_secs_f64();
        if !added {
            break;
        }
    }
    let ad = plan.adaptive().expect("adaptive plan");
    let mut measured = ad.chosen();
    measured.sort_unstable();
    let rounds: Vec<usize> = ad.rounds.iter().map(|r| r.pairs.len()).collect();
    Ok(Some(AdaptiveRun {
        note: format!(
            "rounds {rounds:?}, analyses {compute:.1} s wall (charged {:.0} s){}",
            ad.round_allowance_s * (ad.rounds.len().saturating_sub(1)) as f64,
            if ad.outside_prior { ", outside the prior" } else { "" }
        ),
        measured,
        rig_s: ad.spent_s(),
        predicted_psnr_db: ad.predicted_psnr_db.unwrap_or(f64::NAN),
    }))
}

fn na(noise: bool, method: &str, f: f64, budget: f64, why: &str) -> Row {
    Row {
        noise,
        method: method.into(),
        fraction: f,
        budget_s: budget,
        pairs: 0,
        planned_s: 0.0,
        psnr_db: None,
        predicted_psnr_db: None,
        note: why.into(),
    }
}
