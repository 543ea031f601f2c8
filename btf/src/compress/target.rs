//! `gonio compress --target-psnr P`: the smallest `.gbtf` that reaches a quality, and
//! `gonio compress --target-ratio R`: the smallest error at a ratio of at least `R : 1`.
//!
//! **Ratio goal.** The same ladders; the byte budget is `raw 8-bit size / R`. A version
//! over the budget is not evaluated (its size is known before decoding), a rung stops at
//! its first bit count over the budget, and a ladder stops at its first rung whose
//! smallest version is over it (more components only make the file larger). Of every
//! version within the budget, the one with the highest PSNR wins (ties: the smaller file).
//!
//! The search walks **ladders**: each ladder is one method with its knobs in order of
//! growing file size (more components). On each rung the dataset is factorized once and
//! the factors are stored at 8, 10 and 12 bits ([`super::codec`]); each version is
//! serialized, decoded the way a reader decodes it and evaluated. A rung stops at the
//! first bit count that reaches the target (more bits only make the file larger), and a
//! ladder stops at its first rung that reaches it (more components make it larger
//! again). Of everything that reached the target, the smallest file wins; every trial is
//! reported, so the choice can be checked. The quality is the PSNR on 8-bit sRGB codes
//! ([`super::metrics`]) against the dataset's ground truth when it has one (datasets
//! acquired with `--store-truth`), else against its own images (a `gonio sim btf`
//! dataset *is* its ground truth).

use super::container::Gbtf;
use super::data::DatasetViews;
use super::error::CompressError;
use super::factor::{compress, CompressedBtf};
use super::metrics::evaluate;
use super::params::{CodecId, Params};
use super::registry::codec;
use serde::Serialize;

/// Bit counts tried on every rung, smallest first. 6 bits is below the useful range for
/// most factors, but for a ratio goal it can leave room for more components.
pub const BITS: [u32; 4] = [6, 8, 10, 12];

/// What the search optimizes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Goal {
    /// The smallest file with a PSNR of at least this many dB.
    Psnr(f64),
    /// The highest PSNR at a compression ratio of at least this (against raw 8-bit).
    Ratio(f64),
}

pub use super::params::Knobs;

/// The ladders a search climbs: each method's knobs in order of growing file size
/// ([`Codec::ladder`](super::params::Codec::ladder) of the method `--method` names).
/// Without one, PCA, perceptual DFMF and local PCA: PVMF, median cut and homomorphic
/// factorization are left out of the default search, since on the default sample their
/// files are larger at every quality PCA or local PCA reach (docs/guide/compression.md);
/// naming the method still searches them.
pub fn ladders(method: Option<CodecId>, knobs: &Knobs) -> Vec<Vec<Params>> {
    match method {
        None => [CodecId::Pca, CodecId::Dfmf, CodecId::LocalPca]
            .into_iter()
            .flat_map(|id| codec(id).ladder(knobs))
            .collect(),
        Some(id) => codec(id).ladder(knobs),
    }
}

/// One encoded-and-evaluated candidate.
#[derive(Serialize, Clone, Debug, PartialEq)]
pub struct Trial {
    pub method: &'static str,
    pub params: Params,
    pub bits: u32,
    pub stored_bytes: u64,
    /// Against the raw 8-bit size of the full grid.
    pub ratio: f64,
    /// `None` for a version over a ratio goal's budget (not evaluated).
    pub psnr_8bit_db: Option<f64>,
    pub meets_target: bool,
    /// Encode seconds of the rung's factorization (shared by its bit counts).
    pub encode_seconds: f64,
}

/// The outcome of [`search`].
#[derive(Debug)]
pub struct Choice {
    /// The chosen file (quantization marked), or `None` when nothing met the goal.
    pub best: Option<(Gbtf, Trial)>,
    /// Every candidate, in the order tried.
    pub trials: Vec<Trial>,
    /// `truth` or `dataset`: what the PSNR was measured against.
    pub against: &'static str,
    /// The ratio goal's byte budget.
    pub budget_bytes: Option<u64>,
}

/// Raw 8-bit size of the dataset's full grid (L · V · W · H · 3), the ratio's reference.
pub fn raw_8bit_bytes(ds: &DatasetViews) -> u64 {
    (ds.n_lights() * ds.n_views() * ds.texels() * 3) as u64
}

/// Run the ladders (see the module docs) for `goal`.
pub fn search(ds: &DatasetViews, goal: Goal, ladders: &[Vec<Params>]) -> Result<Choice, CompressError> {
    let raw = raw_8bit_bytes(ds);
    let budget = match goal {
        Goal::Psnr(p) if p.is_finite() && p > 0.0 => None,
        Goal::Psnr(p) => {
            return Err(CompressError::Invalid(format!(
                "target PSNR {p} dB: give a positive number of dB, e.g. 35"
            )))
        }
        Goal::Ratio(r) if r.is_finite() && r >= 1.0 => Some((raw as f64 / r).floor() as u64),
        Goal::Ratio(r) => {
            return Err(CompressError::Invalid(format!(
                "target ratio {r}: give a ratio of at least 1, e.g. 300 for 300 : 1"
            )))
        }
    };
    let mut trials = Vec::new();
    let mut best: Option<(Gbtf, Trial)> = None;
    let mut against = "dataset";
    let better = |t: &Trial, b: &Trial| match goal {
        Goal::Psnr(_) => t.stored_bytes < b.stored_bytes,
        Goal::Ratio(_) => {
            let (pt, pb) = (
                t.psnr_8bit_db.unwrap_or(f64::NEG_INFINITY),
                b.psnr_8bit_db.unwrap_or(f64::NEG_INFINITY),
            );
            pt > pb || (pt == pb && t.stored_bytes < b.stored_bytes)
        }
    };
    for ladder in ladders {
        for params in ladder {
            let t0 = std::time::Instant::now();
            let (g, _) = compress(ds, params)?;
            let encode_seconds = t0.elapsed().as_secs_f64();
            let mut stop_rung = false;
            let mut stop_ladder = false;
            for (i, bits) in BITS.into_iter().enumerate() {
                let mut q = g.clone();
                q.quantize(bits)?;
                let bytes = q.to_bytes()?;
                let mut trial = Trial {
                    method: params.method.name(),
                    params: params.clone(),
                    bits,
                    stored_bytes: bytes.len() as u64,
                    ratio: raw as f64 / bytes.len() as f64,
                    psnr_8bit_db: None,
                    meets_target: false,
                    encode_seconds,
                };
                if budget.is_some_and(|b| trial.stored_bytes > b) {
                    // More bits only grow the file; if even the fewest bits are over the
                    // budget, so is every larger rung.
                    stop_ladder = i == 0;
                    tracing::info!(
                        method = trial.method,
                        c = params.components,
                        bits,
                        bytes = bytes.len(),
                        "over budget"
                    );
                    trials.push(trial);
                    break;
                }
                let model = CompressedBtf::new(Gbtf::from_bytes(&bytes, &ds.dir)?)?;
                let ev = evaluate(ds, &model)?;
                let psnr = match &ev.truth {
                    Some(t) => {
                        against = "truth";
                        t.reconstruction.psnr_8bit()
                    }
                    None => ev.stats.psnr_8bit(),
                };
                trial.psnr_8bit_db = Some(psnr);
                trial.meets_target = match goal {
                    Goal::Psnr(p) => psnr >= p,
                    Goal::Ratio(_) => true,
                };
                tracing::info!(
                    method = trial.method,
                    c = params.components,
                    bits,
                    bytes = bytes.len(),
                    psnr,
                    "trial"
                );
                trials.push(trial.clone());
                if trial.meets_target {
                    if best.as_ref().is_none_or(|(_, b)| better(&trial, b)) {
                        best = Some((q, trial));
                    }
                    if matches!(goal, Goal::Psnr(_)) {
                        stop_rung = true;
                        break;
                    }
                }
            }
            if stop_ladder || (stop_rung && matches!(goal, Goal::Psnr(_))) {
                break;
            }
        }
    }
    Ok(Choice {
        best,
        trials,
        against,
        budget_bytes: budget,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compress::params::Method;
    use crate::compress::testdata;

    /// A small textured dataset and two short ladders (PCA c 1, 2, 4; PVMF c 1, 2).
    fn fixture(dir: &std::path::Path) -> (crate::compress::DatasetViews, Vec<Vec<Params>>) {
        let ds = testdata::write(&dir.join("ds"), |l, v, t, c| {
            0.2 + 0.3 * testdata::hash(t % 5, (v * 5 + l) * 3 + c) + 0.02 * testdata::hash(t, l + c)
        });
        let ladders = vec![
            [1, 2, 4].map(|c| Params::new(Method::Pca, c)).to_vec(),
            [1, 2].map(|c| Params::new(Method::Pvmf, c)).to_vec(),
        ];
        (ds, ladders)
    }

    /// The winner reaches the target, is the smallest file that does, and every ladder
    /// stops at its first rung that reaches it; an unreachable target chooses nothing.
    #[test]
    fn chooses_the_smallest_file_reaching_the_target() {
        let tmp = tempfile::tempdir().unwrap();
        let (ds, ladders) = fixture(tmp.path());
        let all = search(&ds, Goal::Psnr(1e-3), &ladders).unwrap();
        assert_eq!(all.against, "dataset");
        // Everything reaches 0.001 dB: one trial per ladder (first rung, 8 bits).
        assert_eq!(all.trials.len(), 2);
        let target = 30.0;
        let ch = search(&ds, Goal::Psnr(target), &ladders).unwrap();
        let psnrs: Vec<Option<f64>> = ch.trials.iter().map(|t| t.psnr_8bit_db).collect();
        let (g, best) = ch.best.unwrap_or_else(|| panic!("30 dB not reached: {psnrs:?}"));
        assert!(best.meets_target && best.psnr_8bit_db.unwrap() >= target);
        let min = ch
            .trials
            .iter()
            .filter(|t| t.meets_target)
            .map(|t| t.stored_bytes)
            .min()
            .unwrap();
        assert_eq!(best.stored_bytes, min);
        assert_eq!(g.to_bytes().unwrap().len() as u64, best.stored_bytes);
        for t in &ch.trials {
            assert!(t.psnr_8bit_db.unwrap().is_finite());
        }
        let none = search(&ds, Goal::Psnr(500.0), &ladders).unwrap();
        assert!(none.best.is_none());
        assert_eq!(none.trials.len(), 5 * BITS.len());
        assert!(search(&ds, Goal::Psnr(f64::NAN), &ladders).is_err());
        assert!(search(&ds, Goal::Ratio(0.5), &ladders).is_err());
    }

    /// A ratio goal: the winner fits the budget and has the highest PSNR of every version
    /// that fits (found by evaluating all of them); versions over the budget are not
    /// evaluated; an unreachable ratio chooses nothing.
    #[test]
    fn ratio_goal_picks_the_best_psnr_within_the_budget() {
        let tmp = tempfile::tempdir().unwrap();
        let (ds, ladders) = fixture(tmp.path());
        // Every version, evaluated (an unreachable PSNR).
        let every = search(&ds, Goal::Psnr(500.0), &ladders).unwrap();
        let mut sizes: Vec<u64> = every.trials.iter().map(|t| t.stored_bytes).collect();
        sizes.sort();
        let budget = sizes[sizes.len() / 2];
        let raw = raw_8bit_bytes(&ds) as f64;
        let ratio = raw / (budget as f64 + 0.5);
        let ch = search(&ds, Goal::Ratio(ratio), &ladders).unwrap();
        assert_eq!(ch.budget_bytes, Some(budget));
        let (g, best) = ch.best.expect("half of the versions fit");
        assert!(best.stored_bytes <= budget && best.ratio >= ratio);
        assert_eq!(g.to_bytes().unwrap().len() as u64, best.stored_bytes);
        let want = every
            .trials
            .iter()
            .filter(|t| t.stored_bytes <= budget)
            .map(|t| t.psnr_8bit_db.unwrap())
            .fold(f64::NEG_INFINITY, f64::max);
        assert_eq!(best.psnr_8bit_db, Some(want));
        for t in &ch.trials {
            assert_eq!(t.psnr_8bit_db.is_some(), t.stored_bytes <= budget, "{t:?}");
        }
        assert!(ch.trials.len() < every.trials.len(), "over-budget rungs are cut short");
        assert!(search(&ds, Goal::Ratio(1e12), &ladders).unwrap().best.is_none());
    }

    /// Every ladder grows in file size (components, boxes or bins, never fewer) and keeps
    /// the knobs it does not vary; the default search leaves PVMF, median cut and
    /// homomorphic factorization out.
    #[test]
    fn ladders_grow_and_keep_the_given_knobs() {
        let knobs = Knobs {
            seed: 7,
            oversample: 5,
            power_iters: 1,
            iters: 3,
            subspace: 16,
            in_passes: true,
            balanced: true,
            min_error_cut: false,
            half_bins: 12,
            sweeps: None,
        };
        let default = ladders(None, &knobs);
        let names: Vec<&str> = default.iter().map(|l| l[0].method.name()).collect();
        assert_eq!(names, ["pca", "dfmf", "local-pca", "local-pca"]);
        for m in super::super::registry::encodable() {
            let ls = ladders(Some(m), &knobs);
            assert!(!ls.is_empty() && ls.iter().all(|l| !l.is_empty()), "{m:?}");
            for l in ls.iter().chain(&default) {
                assert!(
                    l.iter().all(|p| p.seed == 7 && p.oversample == 5 && p.power_iters == 1),
                    "{m:?}"
                );
                assert!(l.windows(2).all(|w| w[0].components <= w[1].components), "{m:?}");
            }
        }
        let lpca = &ladders(Some(CodecId::LocalPca), &knobs)[1][0];
        assert!(matches!(
            lpca.method,
            Method::LocalPca {
                clusters: 32,
                iters: 3,
                subspace: 16,
                in_passes: true
            }
        ));
    }
}
