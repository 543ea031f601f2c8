//! An opt-in mechanical error model for simulated and emulated axes.
//!
//! A real stage's controller counts motor steps; the load (the turntable, the arc) does not
//! sit exactly where that count says. Three effects matter for a gonioreflectometer:
//!
//! - **backlash**: a dead band of width `backlash_deg` between motor and load. The load
//!   only follows once the play is taken up, so a target approached from below ends
//!   `backlash/2` short of it, approached from above `backlash/2` past it;
//! - **homing repeatability**: the reference switch triggers at a slightly different place
//!   every time, so each homing leaves the true zero at a new Gaussian offset
//!   (`home_sigma_deg`, seeded: a run is reproducible);
//! - **positioning error**: a scale error (gear ratio, encoder-wheel diameter) plus a
//!   periodic error (worm or lead-screw run-out).
//!
//! The read-back (step count) sees none of this; only an independent reference does (an
//! encoder on the load side, or the camera). The model is per axis and off by default:
//! with every term zero the load position is the motor position, bit for bit, and nothing
//! is drawn or computed beyond one comparison.
//!
//! In a rig file the model is an axis option table (degrees):
//!
//! ```toml
//! options = { mechanical = { backlash_deg = 0.08, home_sigma_deg = 0.02, scale_error = 5e-4,
//!             periodic_amplitude_deg = 0.01, periodic_period_deg = 45.0, seed = 3 } }
//! ```
//!
//! `encoder = true` (the default once the table exists) gives the axis a load-side encoder
//! that reads the true position: [`gonio_devices::Axis::reference_position`].

use serde::{Deserialize, Serialize};

/// Parameters of the model (degrees, and a dimensionless scale error).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MechanicalErrors {
    /// Width of the dead band between motor and load.
    pub backlash_deg: f64,
    /// Standard deviation of the true zero after each homing.
    pub home_sigma_deg: f64,
    /// Relative scale error: the load turns `(1 + scale_error)` degrees per commanded degree.
    pub scale_error: f64,
    /// Amplitude of the periodic error.
    pub periodic_amplitude_deg: f64,
    /// Period of the periodic error (> 0).
    pub periodic_period_deg: f64,
    /// Phase of the periodic error at motor position 0.
    pub periodic_phase_deg: f64,
    /// Seed of the homing scatter.
    pub seed: u64,
    /// The axis has a load-side encoder that reports the true position.
    pub encoder: bool,
}

impl Default for MechanicalErrors {
    fn default() -> Self {
        MechanicalErrors {
            backlash_deg: 0.0,
            home_sigma_deg: 0.0,
            scale_error: 0.0,
            periodic_amplitude_deg: 0.0,
            periodic_period_deg: 360.0,
            periodic_phase_deg: 0.0,
            seed: 1,
            encoder: true,
        }
    }
}

/// Why a model is refused.
#[derive(Debug, thiserror::Error)]
#[error("mechanical error model: {key}: {message}")]
pub struct MechanicalError {
    pub key: String,
    pub message: String,
}

impl MechanicalErrors {
    /// Every term finite, widths and sigmas ≥ 0, period > 0, |scale error| < 0.1.
    pub fn validate(&self) -> Result<(), MechanicalError> {
        let bad = |key: &str, message: String| {
            Err(MechanicalError {
                key: key.into(),
                message,
            })
        };
        for (key, v) in [
            ("backlash_deg", self.backlash_deg),
            ("home_sigma_deg", self.home_sigma_deg),
            ("periodic_amplitude_deg", self.periodic_amplitude_deg),
        ] {
            if !(v.is_finite() && (0.0..=10.0).contains(&v)) {
                return bad(key, format!("{v}: must be in 0 ..= 10 degrees"));
            }
        }
        if !(self.scale_error.is_finite() && self.scale_error.abs() < 0.1) {
            return bad("scale_error", format!("{}: must be in (-0.1, 0.1)", self.scale_error));
        }
        if !(self.periodic_period_deg.is_finite() && self.periodic_period_deg > 0.0) {
            return bad(
                "periodic_period_deg",
                format!("{}: must be > 0", self.periodic_period_deg),
            );
        }
        if !self.periodic_phase_deg.is_finite() {
            return bad(
                "periodic_phase_deg",
                format!("{}: must be finite", self.periodic_phase_deg),
            );
        }
        Ok(())
    }

    /// The model from a rig file axis' `options.mechanical` table (`None` if absent).
    pub fn from_options(
        options: &std::collections::BTreeMap<String, toml::Value>,
    ) -> Result<Option<MechanicalErrors>, MechanicalError> {
        let Some(v) = options.get("mechanical") else {
            return Ok(None);
        };
        let m: MechanicalErrors = v.clone().try_into().map_err(|e: toml::de::Error| MechanicalError {
            key: "options.mechanical".into(),
            message: e.message().to_string(),
        })?;
        m.validate()?;
        Ok(Some(m))
    }

    /// True when every error term is zero (the load follows the motor exactly).
    pub fn is_zero(&self) -> bool {
        self.backlash_deg == 0.0
            && self.home_sigma_deg == 0.0
            && self.scale_error == 0.0
            && self.periodic_amplitude_deg == 0.0
    }

    /// The drive's positioning error (true − commanded, degrees) at load-side motor
    /// coordinate `x` (degrees), excluding backlash and the homing offset.
    pub fn positioning_error_deg(&self, x: f64) -> f64 {
        let w = std::f64::consts::TAU / self.periodic_period_deg;
        self.scale_error * x + self.periodic_amplitude_deg * (w * x + self.periodic_phase_deg.to_radians()).sin()
    }
}

/// The model's state on one axis, in degrees of motor coordinates.
#[derive(Clone, Debug)]
pub struct MechanicalState {
    pub model: MechanicalErrors,
    /// Load position (motor coordinates, before the positioning error) at the last fold.
    load: f64,
    /// True position of motor zero since the last homing.
    zero: f64,
    /// Every homing offset drawn so far (the truth for homing repeatability).
    offsets: Vec<f64>,
}

impl MechanicalState {
    pub fn new(model: MechanicalErrors) -> Self {
        MechanicalState {
            model,
            load: 0.0,
            zero: 0.0,
            offsets: Vec::new(),
        }
    }

    /// The load under play: it stays put until the motor is `backlash/2` away.
    fn play(&self, load: f64, motor_deg: f64) -> f64 {
        let h = 0.5 * self.model.backlash_deg;
        load.clamp(motor_deg - h, motor_deg + h)
    }

    /// Record that the motor is at `motor_deg` before a direction change may happen (at
    /// the start of each move and on stop): within one monotonic move, [`Self::true_deg`]
    /// is exact from the folded state.
    pub fn fold(&mut self, motor_deg: f64) {
        self.load = self.play(self.load, motor_deg);
    }

    /// A homing cycle: a new zero offset is drawn, and the play is taken up from below
    /// (homing approaches its switch from one side), with the motor at 0.
    pub fn home(&mut self) {
        let k = self.offsets.len() as u64;
        let z = self.model.home_sigma_deg * gaussian(self.model.seed, k);
        self.offsets.push(z);
        self.zero = z;
        self.load = -0.5 * self.model.backlash_deg;
    }

    /// True (load-side) position in degrees with the motor at `motor_deg`.
    pub fn true_deg(&self, motor_deg: f64) -> f64 {
        let l = self.play(self.load, motor_deg);
        self.zero + l + self.model.positioning_error_deg(l)
    }

    /// The zero offsets of every homing so far.
    pub fn home_offsets(&self) -> &[f64] {
        &self.offsets
    }
}

/// Standard normal number `k` of the stream `seed` (Box–Muller on two hashed uniforms), so
/// homing `k` draws the same offset whatever happened before.
fn gaussian(seed: u64, k: u64) -> f64 {
    let a = crate::noise::mix64(seed ^ crate::noise::mix64(2 * k + 1));
    let b = crate::noise::mix64(a ^ 0x9e37_79b9_7f4a_7c15);
    let u1 = ((a >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
    let u2 = (b >> 11) as f64 / (1u64 << 53) as f64;
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> MechanicalErrors {
        MechanicalErrors {
            backlash_deg: 0.1,
            home_sigma_deg: 0.02,
            scale_error: 1e-3,
            periodic_amplitude_deg: 0.01,
            periodic_period_deg: 45.0,
            ..Default::default()
        }
    }

    #[test]
    fn backlash_is_the_difference_of_the_two_approaches() {
        let mut m = MechanicalState::new(MechanicalErrors {
            scale_error: 0.0,
            periodic_amplitude_deg: 0.0,
            home_sigma_deg: 0.0,
            ..model()
        });
        m.home();
        // approach 10° from below
        m.fold(0.0);
        m.fold(9.0);
        let below = m.true_deg(10.0);
        // overshoot and come back from above
        m.fold(10.0);
        m.fold(11.0);
        let above = m.true_deg(10.0);
        assert!((below - 9.95).abs() < 1e-12, "{below}");
        assert!((above - below - 0.1).abs() < 1e-12, "{above} {below}");
        // a reversal smaller than the play does not move the load
        m.fold(10.0);
        assert!((m.true_deg(10.04) - above).abs() < 1e-12);
    }

    #[test]
    fn homing_scatter_is_seeded_and_has_the_stated_sigma() {
        let mut a = MechanicalState::new(model());
        let mut b = MechanicalState::new(model());
        for _ in 0..4000 {
            a.home();
            b.home();
        }
        assert_eq!(a.home_offsets(), b.home_offsets());
        let o = a.home_offsets();
        let mean = o.iter().sum::<f64>() / o.len() as f64;
        let sd = (o.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (o.len() - 1) as f64).sqrt();
        // sampling error of a std over 4000 draws is ~1.1 %
        assert!((sd / 0.02 - 1.0).abs() < 0.05, "{sd}");
        assert!(mean.abs() < 0.002, "{mean}");
    }

    #[test]
    fn zero_model_is_the_identity_and_bad_values_are_refused() {
        let mut m = MechanicalState::new(MechanicalErrors::default());
        m.home();
        for x in [-3.0, 0.0, 1.25, 170.0] {
            m.fold(x);
            assert_eq!(m.true_deg(x), x);
        }
        let mut opts = std::collections::BTreeMap::new();
        assert!(MechanicalErrors::from_options(&opts).unwrap().is_none());
        opts.insert(
            "mechanical".into(),
            toml::Value::Table(toml::toml! { backlash_deg = -1.0 }),
        );
        let e = MechanicalErrors::from_options(&opts).unwrap_err().to_string();
        assert!(e.contains("backlash_deg"), "{e}");
        opts.insert("mechanical".into(), toml::Value::Table(toml::toml! { backlash = 1.0 }));
        let e = MechanicalErrors::from_options(&opts).unwrap_err().to_string();
        assert!(e.contains("backlash"), "{e}");
    }
}
