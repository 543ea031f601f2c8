//! `gonio compress --target-psnr P`: the smallest `.gbtf` that reaches a quality.
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
use super::params::Params;
use serde::Serialize;

/// Bit counts tried on every rung, smallest first.
pub const BITS: [u32; 3] = [8, 10, 12];

/// One encoded-and-evaluated candidate.
#[derive(Serialize, Clone, Debug, PartialEq)]
pub struct Trial {
    pub method: &'static str,
    pub params: Params,
    pub bits: u32,
    pub stored_bytes: u64,
    pub psnr_8bit_db: f64,
    pub meets_target: bool,
}

/// The outcome of [`search`].
#[derive(Debug)]
pub struct Choice {
    /// The smallest file that reached the target (quantization marked), or `None`.
    pub best: Option<(Gbtf, Trial)>,
    /// Every candidate, in the order tried.
    pub trials: Vec<Trial>,
    /// `truth` or `dataset`: what the PSNR was measured against.
    pub against: &'static str,
}

/// Run the ladders (see the module docs) for `target_psnr` dB.
pub fn search(ds: &DatasetViews, target_psnr: f64, ladders: &[Vec<Params>]) -> Result<Choice, CompressError> {
    if !target_psnr.is_finite() || target_psnr <= 0.0 {
        return Err(CompressError::Invalid(format!(
            "target PSNR {target_psnr} dB: give a positive number of dB, e.g. 35"
        )));
    }
    let mut trials = Vec::new();
    let mut best: Option<(Gbtf, Trial)> = None;
    let mut against = "dataset";
    for ladder in ladders {
        for params in ladder {
            let (g, _) = compress(ds, params)?;
            let mut reached = false;
            for bits in BITS {
                let mut q = g.clone();
                q.quantize(bits)?;
                let bytes = q.to_bytes()?;
                let model = CompressedBtf::new(Gbtf::from_bytes(&bytes, &ds.dir)?)?;
                let ev = evaluate(ds, &model)?;
                let psnr = match &ev.truth {
                    Some(t) => {
                        against = "truth";
                        t.reconstruction.psnr_8bit()
                    }
                    None => ev.stats.psnr_8bit(),
                };
                let trial = Trial {
                    method: params.method.name(),
                    params: params.clone(),
                    bits,
                    stored_bytes: bytes.len() as u64,
                    psnr_8bit_db: psnr,
                    meets_target: psnr >= target_psnr,
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
                    if best.as_ref().is_none_or(|(_, b)| trial.stored_bytes < b.stored_bytes) {
                        best = Some((q, trial));
                    }
                    reached = true;
                    break;
                }
            }
            if reached {
                break;
            }
        }
    }
    Ok(Choice { best, trials, against })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compress::params::Method;
    use crate::compress::testdata;

    /// The winner reaches the target, is the smallest file that does, and every ladder
    /// stops at its first rung that reaches it; an unreachable target chooses nothing.
    #[test]
    fn chooses_the_smallest_file_reaching_the_target() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), |l, v, t, c| {
            0.2 + 0.3 * testdata::hash(t % 5, (v * 5 + l) * 3 + c) + 0.02 * testdata::hash(t, l + c)
        });
        let ladders = vec![
            [1, 2, 4].map(|c| Params::new(Method::Pca, c)).to_vec(),
            [1, 2].map(|c| Params::new(Method::Pvmf, c)).to_vec(),
        ];
        let all = search(&ds, 1e-3, &ladders).unwrap();
        assert_eq!(all.against, "dataset");
        // Everything reaches 0.001 dB: one trial per ladder (first rung, 8 bits).
        assert_eq!(all.trials.len(), 2);
        let target = 30.0;
        let ch = search(&ds, target, &ladders).unwrap();
        let psnrs: Vec<f64> = ch.trials.iter().map(|t| t.psnr_8bit_db).collect();
        let (g, best) = ch.best.unwrap_or_else(|| panic!("30 dB not reached: {psnrs:?}"));
        assert!(best.meets_target && best.psnr_8bit_db >= target);
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
            assert!(t.psnr_8bit_db.is_finite());
        }
        let none = search(&ds, 500.0, &ladders).unwrap();
        assert!(none.best.is_none());
        assert_eq!(none.trials.len(), 5 * BITS.len());
        assert!(search(&ds, f64::NAN, &ladders).is_err());
    }
}
