//! The material's spatially averaged BRDF, the one thing the tabulated formats (`rgl-bsdf`,
//! `merl`) can hold: they store one BRDF, not a texture of them.
//!
//! **Which BRDF.** The glTF model fitted to the *average* of every texel's measurements
//! (`gonio fit --model gltf`, the fit the per-texel fit starts from), stored by `gonio fit
//! --model gltf --per-texel` in the `.gbtf` header as `source.average_fit` ([`AverageFit`]).
//! Why that fit and not a mean of the per-texel models: it is the BRDF fitted to the
//! averaged data (what a spatially averaged measurement sees), one closed-form model that
//! both writers and the interop checks can evaluate, and reading it needs no refit. A file
//! without it (written before it was stored) is refused with the refit command.
//!
//! **Isotropic.** Both formats are isotropic (RGL's `measured` with one φ_i slice, MERL by
//! construction). The fit's shading normal may be tilted, which makes it anisotropic: the
//! exported BRDF is then the mean over [`ROTATIONS`] rotations of the sample about +z
//! (`f_iso(l, v) = 1/36 Σ_k f(R_k l, R_k v)`), exactly what a sample spun on a turntable
//! reflects on average, and the export warns that the tilt is averaged away.

use super::{calibrated, ExportError};
use crate::compress::container::Gbtf;
use gonio_devices::Vec3;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Azimuthal rotations averaged into the isotropic BRDF (every 10°).
pub const ROTATIONS: usize = 36;

/// Tilts (degrees) below this are reported as isotropic; above it the export warns.
pub const TILT_WARN_DEG: f64 = 0.5;

/// The averaged fit as `gonio fit --model gltf --per-texel` stores it (`source.average_fit`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AverageFit {
    /// Always `gltf` (the model whose parameters follow).
    pub model: String,
    /// Linear RGB.
    pub base_color: [f64; 3],
    pub metallic: f64,
    /// α = roughness².
    pub roughness: f64,
    /// The shading normal's tangent-plane components `[n_x, n_y]`.
    pub normal: [f64; 2],
    /// The `KHR_materials_anisotropy` vector `s·(cos 2φ, sin 2φ)` (`gonio_brdf::gltf`);
    /// absent (0) in files written before anisotropy.
    #[serde(default)]
    pub anisotropy: [f64; 2],
    /// Cosine-weighted relative RMS of the fit against the averaged data.
    pub rel_rms: f64,
    pub observations: usize,
    /// SHA-256 of the source dataset's `journal.jsonl` (which lists every image's SHA-256):
    /// identifies the measurement the fit came from.
    pub dataset_journal_sha256: Option<String>,
}

/// The isotropic averaged BRDF the tabulated formats write.
#[derive(Clone, Debug)]
pub struct AverageBrdf {
    pub fit: AverageFit,
    /// What the writers put in their metadata (generator, source, fit, units).
    pub provenance: serde_json::Value,
    pub warnings: Vec<String>,
}

impl AverageBrdf {
    /// Read `source.average_fit` of a glTF `.gbtf`. Refuses other methods, files without the
    /// averaged fit (naming the refit command) and uncalibrated values unless allowed.
    pub fn from_gbtf(g: &Gbtf, path: &Path, allow_uncalibrated: bool) -> Result<AverageBrdf, ExportError> {
        let input = |reason: String| ExportError::Input {
            path: path.display().to_string(),
            reason,
        };
        let dataset = g
            .header
            .source
            .get("dataset")
            .and_then(|d| d.as_str())
            .unwrap_or("DATASET");
        let refit = format!("gonio fit {dataset} --model gltf --per-texel --out {}", path.display());
        if g.header.method != crate::compress::CodecId::Gltf.name() {
            return Err(input(format!(
                "a `{}` file; the averaged-BRDF formats take a glTF fit: `{refit}`",
                g.header.method
            )));
        }
        let Some(v) = g.header.source.get("average_fit").filter(|v| !v.is_null()) else {
            return Err(input(format!(
                "no averaged fit in its header (`source.average_fit`, stored by gonio fit since the rgl-bsdf and \
                 merl exports): refit with `{refit}`"
            )));
        };
        let fit: AverageFit =
            serde_json::from_value(v.clone()).map_err(|e| input(format!("`source.average_fit` in the header: {e}")))?;
        let finite = fit
            .base_color
            .iter()
            .chain(&fit.normal)
            .chain(&fit.anisotropy)
            .all(|x| x.is_finite())
            && fit.metallic.is_finite()
            && fit.roughness.is_finite();
        if fit.model != "gltf" || !finite || fit.roughness <= 0.0 {
            return Err(input(format!(
                "`source.average_fit` is not a finite glTF fit (model `{}`, roughness {}): refit with `{refit}`",
                fit.model, fit.roughness
            )));
        }
        let calibrated = calibrated(g);
        if !calibrated && !allow_uncalibrated {
            return Err(input(format!(
                "its values are not radiometrically calibrated (\"{}\"): a renderer would read sensor numbers \
                 as BRDF values; fit with --white DIR, or pass --allow-uncalibrated to export them labelled as such",
                g.header.source.get("values").and_then(|v| v.as_str()).unwrap_or("?")
            )));
        }
        let mut warnings = Vec::new();
        let tilt = tilt_deg(fit.normal);
        if tilt > TILT_WARN_DEG {
            warnings.push(format!(
                "the averaged fit is anisotropic: its normal is tilted {tilt:.2}° (n = [{:.4}, {:.4}]); the format \
                 holds an isotropic BRDF, so the export is its mean over {ROTATIONS} rotations about the normal \
                 (the tilt's direction is lost)",
                fit.normal[0], fit.normal[1]
            ));
        }
        let (strength, rotation) = gonio_brdf::gltf::anisotropy_of(fit.anisotropy);
        if strength > 0.0 {
            let (at, ab) = gonio_brdf::gltf::alphas(fit.roughness, fit.anisotropy);
            warnings.push(format!(
                "the averaged fit is anisotropic (KHR_materials_anisotropy strength {strength:.3} at {:.1}°: α \
                 {at:.4} along, {ab:.4} across); the format holds an isotropic BRDF, so the export is its mean \
                 over {ROTATIONS} rotations about the normal (the direction and the elongated highlight are lost)",
                rotation.to_degrees()
            ));
        }
        let provenance = serde_json::json!({
            "generator": concat!("gonio ", env!("CARGO_PKG_VERSION")),
            "source": {
                "fit_file": path.display().to_string(),
                "dataset": g.header.source.get("dataset"),
                "dataset_journal_sha256": fit.dataset_journal_sha256,
                "values": g.header.source.get("values"),
                "calibrated_by": g.header.source.get("calibrated_by"),
            },
            "fit": {
                "model": "gltf metallic-roughness (Lambert + GGX, alpha = roughness^2, Schlick F0 = mix(0.04, base, metallic)), fitted to the average of all texels",
                "base_color": fit.base_color,
                "metallic": fit.metallic,
                "roughness": fit.roughness,
                "normal": fit.normal,
                "anisotropy_strength": anisotropy_of_fit(&fit).0,
                "anisotropy_rotation_rad": anisotropy_of_fit(&fit).1,
                "tilt_deg": tilt,
                "rel_rms": fit.rel_rms,
                "observations": fit.observations,
            },
            "isotropic": format!("mean over {ROTATIONS} rotations about +z (every {}°)", 360 / ROTATIONS),
            "units": if calibrated { "BRDF (1/sr)" } else { "UNCALIBRATED: not BRDF values (--allow-uncalibrated)" },
        });
        Ok(AverageBrdf {
            fit,
            provenance,
            warnings,
        })
    }

    /// The isotropic BRDF (1/sr) at unit `l`, `v` (sample frame, pointing away).
    pub fn eval(&self, l: Vec3, v: Vec3) -> [f64; 3] {
        let f = &self.fit;
        let one = |l: Vec3, v: Vec3| {
            gonio_brdf::gltf::eval(&f.base_color, f.metallic, f.roughness, f.normal, f.anisotropy, l, v)
        };
        if f.normal == [0.0, 0.0] && f.anisotropy == [0.0, 0.0] {
            // Rotation-invariant already: the mean of 36 equal values is the value.
            return one(l, v);
        }
        let mut sum = [0.0; 3];
        for k in 0..ROTATIONS {
            let a = k as f64 * std::f64::consts::TAU / ROTATIONS as f64;
            let x = one(l.rotate_z(a), v.rotate_z(a));
            for c in 0..3 {
                sum[c] += x[c];
            }
        }
        sum.map(|s| s / ROTATIONS as f64)
    }
}

fn anisotropy_of_fit(f: &AverageFit) -> (f64, f64) {
    gonio_brdf::gltf::anisotropy_of(f.anisotropy)
}

/// The tilt (degrees) of a normal of tangent-plane components `n`.
pub fn tilt_deg(n: [f64; 2]) -> f64 {
    gonio_brdf::gltf::normal_vector(n)
        .z
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}
