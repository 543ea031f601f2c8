//! Sparse BTF acquisition: measure a fraction of a sweep's (light, view) pairs and predict
//! the rest in a learned angular prior.
//!
//! * [`prior`]: a Gaussian prior of per-texel ABRDFs (one vector over the sweep's pairs per
//!   texel and colour channel) — mean, an orthonormal PCA basis and the variance along each
//!   basis vector, plus the variance the basis leaves out. Learned by a deterministic
//!   randomized SVD; stored as a `.gprior` file whose header names the sweep (a hash of its
//!   directions), the value units and the value space.
//! * [`design`]: which pairs to measure — greedy Bayesian A-optimal design (each step adds
//!   the pair that most reduces the expected posterior reconstruction error over every pair
//!   of the sweep), optionally per second of rig time.
//! * [`complete`]: per-texel MAP (ridge with the prior's eigenvalues) from the measured
//!   pairs; predicted values, predicted error per pair, conditioning, held-back residual
//!   check for materials outside the prior.
//! * [`adaptive`]: rounds of measurement — leave-one-out residuals of the measured pairs,
//!   interpolated over the pair geometry, say where the prior fails; the next pairs are
//!   chosen by the design's gain plus that residual, and the predicted error includes it.
//! * [`noise`]: a sensor's noise in the model's value space, per measured pair (the
//!   completion weighs each pair by it; clipped readings are fitted as lower bounds by
//!   [`Completion::coefficients_censored`]).
//! * [`joint`]: the alternative across texels — EM for the material's own Gaussian in the
//!   prior's coefficient space; measured against the per-texel MAP (no better: the prior's
//!   span, not the estimate, limits the completion; docs/guide/sparse.md).
//!
//! Values are modelled in a variance-stabilising space ([`ValueSpace::Gamma`]:
//! `max(x, 0)^(1/2.2)`, close to the sRGB curve the 8-bit error metric uses), so a squared
//! error in the model is close to a squared error of 8-bit codes.
//!
//! Everything is deterministic: the same inputs give the same bytes at any thread count
//! (rayon is used only for independent per-texel work).

// Index loops mirror the formulas of the module docs.
#![allow(clippy::needless_range_loop)]

pub mod adaptive;
pub mod complete;
pub mod design;
pub mod joint;
pub mod mixture;
pub mod noise;
pub mod prior;

pub use complete::{Completion, Conditioning};
pub use design::{greedy_design, DesignStep};
pub use prior::{Prior, PriorHeader, PriorMeta, TrainingSource};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

#[derive(Debug, thiserror::Error)]
pub enum SparseError {
    #[error("{0}")]
    Invalid(String),
    #[error("prior mismatch: {0}")]
    Mismatch(String),
    #[error("refused: {0}")]
    Refused(String),
    #[error("{file}: {message}")]
    File { file: String, message: String },
    #[error("{0}")]
    Io(#[from] std::io::Error),
}

/// The space the prior models values in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ValueSpace {
    /// `y = max(x, 0)^(1/2.2)`: close to sRGB, so model errors are close to 8-bit code errors.
    Gamma,
    /// The linear values themselves.
    Linear,
}

const GAMMA: f64 = 2.2;

impl ValueSpace {
    pub fn forward(self, x: f64) -> f64 {
        let x = if x.is_finite() { x.max(0.0) } else { 0.0 };
        match self {
            ValueSpace::Gamma => x.powf(1.0 / GAMMA),
            ValueSpace::Linear => x,
        }
    }
    pub fn inverse(self, y: f64) -> f64 {
        let y = if y.is_finite() { y.max(0.0) } else { 0.0 };
        match self {
            ValueSpace::Gamma => y.powf(GAMMA),
            ValueSpace::Linear => y,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            ValueSpace::Gamma => "gamma",
            ValueSpace::Linear => "linear",
        }
    }
}

impl std::str::FromStr for ValueSpace {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "gamma" => Ok(ValueSpace::Gamma),
            "linear" => Ok(ValueSpace::Linear),
            _ => Err(format!("value space `{s}`: use gamma or linear")),
        }
    }
}

/// The identity of a sweep: SHA-256 of its light and view directions (degrees, rounded to
/// 1e-6°, in order), hex. Two sweeps with the same directions in the same order share it,
/// whatever their names.
pub fn sweep_hash(lights_deg: &[[f64; 2]], views_deg: &[[f64; 2]]) -> String {
    let mut h = Sha256::new();
    for (tag, list) in [("lights", lights_deg), ("views", views_deg)] {
        h.update(tag.as_bytes());
        h.update((list.len() as u64).to_le_bytes());
        for d in list {
            for v in d {
                let r = (v * 1e6).round() as i64;
                h.update(r.to_le_bytes());
            }
        }
    }
    hex(&h.finalize())
}

/// SHA-256 of `bytes`, hex.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

fn hex(digest: &[u8]) -> String {
    digest.iter().map(|b| format!("{b:02x}")).collect()
}

/// A deterministic stream of uniform and standard normal numbers (SplitMix64 + Box–Muller).
pub struct Normal {
    state: u64,
    spare: Option<f64>,
}

impl Normal {
    pub fn new(seed: u64) -> Self {
        Normal {
            state: seed ^ 0x9e37_79b9_7f4a_7c15,
            spare: None,
        }
    }
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    pub fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    pub fn sample(&mut self) -> f64 {
        if let Some(s) = self.spare.take() {
            return s;
        }
        let (u, v) = (self.uniform(), self.uniform());
        let r = (-2.0 * u.ln()).sqrt();
        let t = std::f64::consts::TAU * v;
        self.spare = Some(r * t.sin());
        r * t.cos()
    }
}

/// `n` distinct indices out of `0..len`, drawn with a fixed seed (partial Fisher–Yates),
/// sorted ascending. Used for the random-pairs baseline and held-back pairs.
pub fn random_subset(len: usize, n: usize, seed: u64) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..len).collect();
    let mut rng = Normal::new(seed);
    let n = n.min(len);
    for i in 0..n {
        let j = i + (rng.next_u64() % (len - i) as u64) as usize;
        idx.swap(i, j);
    }
    let mut out = idx[..n].to_vec();
    out.sort_unstable();
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sweep_hash_depends_on_directions_not_names() {
        let a = [[0.0, 0.0], [15.0, 60.0]];
        let b = [[0.0, 0.0], [15.0, 60.000_000_1]];
        let c = [[0.0, 0.0], [15.0, 61.0]];
        assert_eq!(sweep_hash(&a, &a), sweep_hash(&b, &b));
        assert_ne!(sweep_hash(&a, &a), sweep_hash(&c, &c));
        assert_ne!(sweep_hash(&a, &c), sweep_hash(&c, &a));
    }

    #[test]
    fn gamma_space_round_trips_and_never_gives_nan() {
        for x in [0.0, 1e-6, 0.2, 1.0, 3.5] {
            let s = ValueSpace::Gamma;
            assert!((s.inverse(s.forward(x)) - x).abs() < 1e-12 * (1.0 + x));
        }
        assert_eq!(ValueSpace::Gamma.forward(f64::NAN), 0.0);
        assert_eq!(ValueSpace::Gamma.forward(-1.0), 0.0);
        assert_eq!(ValueSpace::Gamma.inverse(-0.5), 0.0);
    }

    #[test]
    fn random_subset_is_distinct_sorted_and_seeded() {
        let s = random_subset(100, 30, 7);
        assert_eq!(s.len(), 30);
        assert!(s.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(s, random_subset(100, 30, 7));
        assert_ne!(s, random_subset(100, 30, 8));
    }
}
