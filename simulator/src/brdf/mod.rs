//! The material library: analytic BRDF models.
//!
//! Every model is evaluated in the local shading frame: the normal is +z, the tangent +x
//! (texture u), the bitangent +y. `l` points to the light, `v` to the viewer, both unit
//! vectors; values are RGB BRDF values in 1/sr. Directions below the surface give 0.

use gonio_devices::Vec3;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// RGB triple (linear).
pub type Rgb = [f64; 3];

#[derive(Debug, Error, Clone, PartialEq)]
pub enum BrdfError {
    #[error("model `{model}`: parameter `{param}` = {value}: {message}")]
    BadParameter { model: String, param: String, value: String, message: String },
}

/// A BRDF model with its parameters, as written in sample files and `gonio brdf eval`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "kebab-case", deny_unknown_fields)]
pub enum BrdfModel {
    /// `f = albedo / π`: albedo is the directional albedo for every incidence.
    Lambert { albedo: Rgb },
    /// Modified Phong (Lewis 1994): `f = kd/π + ks (n+2)/(2π) max(0, r·v)^n`; reciprocal,
    /// energy conserving when `kd + ks ≤ 1` per channel.
    ModifiedPhong { kd: Rgb, ks: Rgb, exponent: f64 },
}

impl BrdfModel {
    pub fn name(&self) -> &'static str {
        match self {
            BrdfModel::Lambert { .. } => "lambert",
            BrdfModel::ModifiedPhong { .. } => "modified-phong",
        }
    }

    /// BRDF value (1/sr) for unit `l`, `v` in the local frame.
    pub fn eval(&self, l: Vec3, v: Vec3) -> Rgb {
        if l.z <= 0.0 || v.z <= 0.0 {
            return [0.0; 3];
        }
        match self {
            BrdfModel::Lambert { albedo } => albedo.map(|a| a * std::f64::consts::FRAC_1_PI),
            BrdfModel::ModifiedPhong { kd, ks, exponent } => {
                let r = Vec3::new(-l.x, -l.y, l.z);
                let c = r.dot(v).max(0.0);
                let lobe = if c > 0.0 { (exponent * c.ln()).exp() } else { 0.0 };
                let s = (exponent + 2.0) / (2.0 * std::f64::consts::PI) * lobe;
                [0, 1, 2].map(|i| kd[i] * std::f64::consts::FRAC_1_PI + ks[i] * s)
            }
        }
    }

    /// Whether the value is the same for every direction pair up to the cosine (Lambert):
    /// lets the renderer skip per-direction work.
    pub fn is_lambertian(&self) -> bool {
        matches!(self, BrdfModel::Lambert { .. })
    }

    /// Check parameter ranges; errors name the model, parameter and valid range.
    pub fn validate(&self) -> Result<(), BrdfError> {
        let bad = |param: &str, value: String, message: &str| BrdfError::BadParameter {
            model: self.name().into(),
            param: param.into(),
            value,
            message: message.into(),
        };
        let unit = |param: &str, c: &Rgb| {
            if c.iter().all(|x| x.is_finite() && (0.0..=1.0).contains(x)) {
                Ok(())
            } else {
                Err(bad(param, format!("{c:?}"), "each channel must be in [0, 1]"))
            }
        };
        match self {
            BrdfModel::Lambert { albedo } => unit("albedo", albedo),
            BrdfModel::ModifiedPhong { kd, ks, exponent } => {
                unit("kd", kd)?;
                unit("ks", ks)?;
                if (0..3).any(|i| kd[i] + ks[i] > 1.0 + 1e-12) {
                    return Err(bad("kd + ks", format!("{kd:?} + {ks:?}"), "kd + ks ≤ 1 per channel (energy conservation)"));
                }
                if !(exponent.is_finite() && *exponent >= 0.0 && *exponent <= 1e7) {
                    return Err(bad("exponent", exponent.to_string(), "valid range is 0 ..= 1e7"));
                }
                Ok(())
            }
        }
    }
}
