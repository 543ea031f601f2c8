//! A rig's HDR settings (rig file `[hdr]`, `gonio acquire --hdr`) and the sensor noise model
//! that both the exposure choice (`rig` floor) and the merge (`develop` floor) weigh with.
//!
//! One home for the noise model: a pixel's normalised value `u` (DN / max DN of an ideal
//! linear sensor) collected `u · full_well / gain` electrons, so its variance is
//! `u · gain / full_well` (photon shot noise) `+ (read_noise · gain / full_well)²` (read
//! noise) `+ 1 / (12 · max_dn²)` (quantisation): the sensor model of Hasinoff et al. 2010
//! ("Noise-optimal capture for high dynamic range photography") and Granados et al. 2010
//! ("Optimal HDR reconstruction with linear digital cameras").

use serde::{Deserialize, Serialize};

/// How many exposures a measurement gets.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HdrMode {
    /// One exposure (today's behaviour).
    Off,
    /// Extra exposures only where the sample region saturates or its darkest decile falls
    /// below the SNR floor.
    Auto,
    /// A fixed bracket of N exposures: the base and N − 1 shorter ones, `step` apart.
    Fixed(u32),
}

impl HdrMode {
    /// Parse `off`, `auto` or a count `N` (1 = off, 2 ..= 8).
    pub fn parse(s: &str) -> Result<HdrMode, String> {
        match s.trim() {
            "off" => Ok(HdrMode::Off),
            "auto" => Ok(HdrMode::Auto),
            n => match n.parse::<u32>() {
                Ok(1) => Ok(HdrMode::Off),
                Ok(n @ 2..=8) => Ok(HdrMode::Fixed(n)),
                _ => Err(format!("`{s}`: use off, auto or a number of exposures 2 ..= 8")),
            },
        }
    }

    /// The word `parse` reads back.
    pub fn word(self) -> String {
        match self {
            HdrMode::Off => "off".into(),
            HdrMode::Auto => "auto".into(),
            HdrMode::Fixed(n) => n.to_string(),
        }
    }
}

/// The rig file's `[hdr]` section. Every key has a default, so `[hdr]` with `mode = "auto"`
/// alone is a valid section.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HdrSpec {
    /// `"off"`, `"auto"` or `"N"` (see [`HdrMode::parse`]).
    #[serde(default = "default_mode")]
    pub mode: String,
    /// Ratio between successive exposures of a bracket.
    #[serde(default = "default_step")]
    pub step: f64,
    /// Shortest exposure the camera can take (s).
    #[serde(default = "default_min_exposure")]
    pub min_exposure_s: f64,
    /// Longest exposure allowed (s): the rig's time budget per frame, not the sensor's.
    #[serde(default = "default_max_exposure")]
    pub max_exposure_s: f64,
    /// SNR the darkest decile of the sample region should reach (`auto`).
    #[serde(default = "default_snr_floor")]
    pub snr_floor: f64,
    /// Sample-region pixels at the saturation code a frame may keep before `auto` adds a
    /// shorter exposure (0: none).
    #[serde(default)]
    pub max_saturated_pixels: usize,
    /// Full well (e⁻) and read noise (e⁻ rms) of the sensor; absent: the camera's
    /// `options.full_well_e` / `options.read_noise_e` (the simulator's keys), else
    /// 20000 e⁻ and 4 e⁻.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub full_well_e: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub read_noise_e: Option<f64>,
    /// Extra exposures per measurement `auto` is planned with, each costed as a readout
    /// plus the base exposure (the plan cannot see the sample; the progress bar's ETA
    /// follows the measured rate once the run starts). The default is what `auto` took on
    /// `brushed-metal` (docs/guide/hdr.md).
    #[serde(default = "default_planned_extra")]
    pub planned_extra_exposures: f64,
}

fn default_mode() -> String {
    "auto".into()
}
fn default_step() -> f64 {
    8.0
}
fn default_min_exposure() -> f64 {
    1e-5
}
fn default_max_exposure() -> f64 {
    0.4
}
fn default_snr_floor() -> f64 {
    10.0
}
fn default_planned_extra() -> f64 {
    0.8
}

impl Default for HdrSpec {
    fn default() -> Self {
        HdrSpec {
            mode: default_mode(),
            step: default_step(),
            min_exposure_s: default_min_exposure(),
            max_exposure_s: default_max_exposure(),
            snr_floor: default_snr_floor(),
            max_saturated_pixels: 0,
            full_well_e: None,
            read_noise_e: None,
            planned_extra_exposures: default_planned_extra(),
        }
    }
}

impl HdrSpec {
    /// The mode (validated by [`HdrSpec::validate`]).
    pub fn mode(&self) -> HdrMode {
        HdrMode::parse(&self.mode).unwrap_or(HdrMode::Off)
    }

    /// Check every value; `Err((key, value, message))` names the offending key.
    pub fn validate(&self, base_exposure_s: f64) -> Result<(), (String, String, String)> {
        let bad = |k: &str, v: String, m: &str| Err((format!("hdr.{k}"), v, m.to_string()));
        if let Err(m) = HdrMode::parse(&self.mode) {
            return bad("mode", self.mode.clone(), &m);
        }
        if !(self.step.is_finite() && self.step >= 1.5 && self.step <= 1024.0) {
            return bad("step", self.step.to_string(), "must be a ratio in 1.5 ..= 1024");
        }
        if !(self.min_exposure_s.is_finite() && self.min_exposure_s > 0.0 && self.min_exposure_s <= base_exposure_s) {
            return bad(
                "min_exposure_s",
                self.min_exposure_s.to_string(),
                "must be > 0 and at most camera.exposure_s",
            );
        }
        if !(self.max_exposure_s.is_finite() && self.max_exposure_s >= base_exposure_s) {
            return bad(
                "max_exposure_s",
                self.max_exposure_s.to_string(),
                "must be finite and at least camera.exposure_s",
            );
        }
        if !(self.snr_floor.is_finite() && self.snr_floor >= 0.0) {
            return bad("snr_floor", self.snr_floor.to_string(), "must be a finite number ≥ 0");
        }
        for (k, v) in [("full_well_e", self.full_well_e), ("read_noise_e", self.read_noise_e)] {
            if let Some(v) = v {
                if !(v.is_finite() && v >= 0.0 && (k != "full_well_e" || v >= 1.0)) {
                    return bad(
                        k,
                        v.to_string(),
                        "must be a finite number (full well ≥ 1 e⁻, read noise ≥ 0)",
                    );
                }
            }
        }
        if !(self.planned_extra_exposures.is_finite() && (0.0..=16.0).contains(&self.planned_extra_exposures)) {
            return bad(
                "planned_extra_exposures",
                self.planned_extra_exposures.to_string(),
                "must be in 0 ..= 16",
            );
        }
        Ok(())
    }

    /// The noise model for a camera with these options and `gain`.
    pub fn noise(&self, camera: &crate::rig::CameraSpec, gain: f64) -> SensorNoise {
        let opt = |k: &str| {
            camera
                .options
                .get(k)
                .and_then(|v| v.as_float().or(v.as_integer().map(|i| i as f64)))
        };
        SensorNoise {
            full_well_e: self.full_well_e.or(opt("full_well_e")).unwrap_or(20000.0).max(1.0),
            read_noise_e: self.read_noise_e.or(opt("read_noise_e")).unwrap_or(4.0).max(0.0),
            gain: gain.max(1e-9),
            max_dn: ((1u64 << camera.bit_depth.min(16)) - 1) as f64,
        }
    }

    /// Planned time of one measurement's captures: the base plus the predicted extra
    /// exposures (fixed brackets: exact; `auto`: `planned_extra_exposures` short ones).
    pub fn planned_capture_time(&self, camera: &crate::rig::CameraSpec) -> f64 {
        let base = camera.capture_time();
        match self.mode() {
            HdrMode::Off => base,
            HdrMode::Fixed(n) => {
                let mut t = base;
                let mut e = camera.exposure_s;
                for _ in 1..n {
                    e = (e / self.step).max(self.min_exposure_s);
                    t += e + camera.readout_s;
                }
                t
            }
            HdrMode::Auto => base + self.planned_extra_exposures * (camera.exposure_s + camera.readout_s),
        }
    }
}

/// The sensor noise model (see the module docs), in normalised units (DN / max DN).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SensorNoise {
    pub full_well_e: f64,
    pub read_noise_e: f64,
    pub gain: f64,
    pub max_dn: f64,
}

impl SensorNoise {
    /// Variance of a normalised reading whose expected value is `u` (≥ 0).
    pub fn variance(&self, u: f64) -> f64 {
        let k = self.gain / self.full_well_e;
        u.max(0.0) * k + (self.read_noise_e * k).powi(2) + 1.0 / (12.0 * self.max_dn * self.max_dn)
    }

    /// Signal-to-noise ratio of a reading with expected value `u`.
    pub fn snr(&self, u: f64) -> f64 {
        u.max(0.0) / self.variance(u).sqrt()
    }

    /// The smallest exposure factor `f ≥ 1` that lifts a reading `u` to `snr_floor`
    /// (`None` when `u` is 0: no exposure makes black brighter).
    pub fn factor_for_snr(&self, u: f64, snr_floor: f64) -> Option<f64> {
        if u <= 0.0 {
            return None;
        }
        if self.snr(u) >= snr_floor {
            return Some(1.0);
        }
        // SNR(f u) = f u / sqrt(a f u + b) = s  ⇒  f² u² − s² a f u − s² b = 0.
        let k = self.gain / self.full_well_e;
        let a = k;
        let b = (self.read_noise_e * k).powi(2) + 1.0 / (12.0 * self.max_dn * self.max_dn);
        let s2 = snr_floor * snr_floor;
        let x = (s2 * a + (s2 * s2 * a * a + 4.0 * s2 * b).sqrt()) / 2.0; // x = f u
        Some((x / u).max(1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn modes_parse_and_refuse() {
        assert_eq!(HdrMode::parse("off"), Ok(HdrMode::Off));
        assert_eq!(HdrMode::parse("auto"), Ok(HdrMode::Auto));
        assert_eq!(HdrMode::parse("3"), Ok(HdrMode::Fixed(3)));
        assert_eq!(HdrMode::parse("1"), Ok(HdrMode::Off));
        for bad in ["0", "9", "x", ""] {
            assert!(HdrMode::parse(bad).is_err(), "{bad}");
        }
        for m in [HdrMode::Off, HdrMode::Auto, HdrMode::Fixed(5)] {
            assert_eq!(HdrMode::parse(&m.word()), Ok(m));
        }
    }

    #[test]
    fn snr_factor_reaches_the_floor() {
        let n = SensorNoise {
            full_well_e: 20000.0,
            read_noise_e: 4.0,
            gain: 1.0,
            max_dn: 4095.0,
        };
        for u in [1e-4, 1e-3, 0.01] {
            let f = n.factor_for_snr(u, 20.0).unwrap();
            assert!((n.snr(u * f) - 20.0).abs() < 1e-6 || f == 1.0, "u {u}: f {f}");
        }
        assert_eq!(n.factor_for_snr(0.5, 20.0), Some(1.0));
        assert_eq!(n.factor_for_snr(0.0, 20.0), None);
    }

    #[test]
    fn validation_names_the_key() {
        let mut s = HdrSpec::default();
        assert!(s.validate(0.05).is_ok());
        s.step = 1.0;
        assert_eq!(s.validate(0.05).unwrap_err().0, "hdr.step");
        let s = HdrSpec {
            min_exposure_s: 1.0,
            ..HdrSpec::default()
        };
        assert_eq!(s.validate(0.05).unwrap_err().0, "hdr.min_exposure_s");
        let s = HdrSpec {
            mode: "lots".into(),
            ..HdrSpec::default()
        };
        assert_eq!(s.validate(0.05).unwrap_err().0, "hdr.mode");
    }
}
