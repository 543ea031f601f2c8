//! Linear values → BRDF (1/sr): the white standard's radiometric conversion
//! ([`Radiometric::to_brdf`]).
//!
//! A rectified image of linear sensor values (DN / max DN) becomes BRDF values per texel,
//! `f = value / (K · exposure · gain · E(x))`, with `E(x) = I · cos θ_l(x) / d(x)²` the
//! lamp's irradiance at the texel's own position (not the sample centre's): at 1.2 m a
//! 60 mm sample sees the falloff and the cosine change by several percent across it, more
//! at grazing light, which a single scale per image would leave in the data.

use super::DevelopError;
use gonio_calibration::warp::RectifyParams;
use gonio_devices::image::RgbImage;
use gonio_devices::rig::RigSpec;
use gonio_devices::Vec3;
use serde::{Deserialize, Serialize};

/// The lamp as the radiometric model sees it: a point (radius 0) or a disc of isotropic
/// emitters facing the sample centre, with the rig file's nominal intensity. A wrong
/// nominal intensity does no harm as long as calibration and acquisition use the same rig
/// file: only the product `K · I` enters the conversion.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct LampModel {
    /// Radiant intensity (W/sr) of the whole lamp at full power (`light.intensity_w_sr`).
    pub intensity_w_sr: f64,
    /// Disc radius (mm; `light.options.radius_mm`, 0 = point lamp).
    pub radius_mm: f64,
}

/// Rings × spokes of the disc quadrature (area-weighted midpoints): the disc's effect on
/// the falloff is of order (r/d)², so this resolves it far below the 1 % target.
const DISC_RINGS: usize = 6;
const DISC_SPOKES: usize = 12;

impl LampModel {
    /// The lamp of a rig file.
    pub fn from_rig(spec: &RigSpec) -> Result<LampModel, DevelopError> {
        let bad = |key: &str, value: String, message: &str| DevelopError::RigValue {
            rig: spec.name.clone(),
            key: key.into(),
            value,
            message: message.into(),
        };
        let i = spec.light.intensity_w_sr;
        if !(i.is_finite() && i > 0.0) {
            return Err(bad("light.intensity_w_sr", i.to_string(), "must be > 0"));
        }
        let radius_mm = spec.lamp_radius_mm().map_err(|e| bad(&e.key, e.value, &e.message))?;
        Ok(LampModel {
            intensity_w_sr: i,
            radius_mm,
        })
    }

    /// Irradiance (W/m²) on the sample plane (normal +z) at `p` (mm) from the lamp whose
    /// centre is at `lamp` (mm); 0 where the lamp is below the point's horizon.
    pub fn irradiance(&self, lamp: Vec3, p: Vec3) -> f64 {
        let point = |at: Vec3, intensity: f64| -> f64 {
            let to_l = at - p;
            let r2 = to_l.dot(to_l);
            if to_l.z <= 0.0 || r2 <= 0.0 {
                return 0.0;
            }
            // mm² → m²
            intensity * (to_l.z / r2.sqrt()) / (r2 * 1e-6)
        };
        if self.radius_mm <= 0.0 {
            return point(lamp, self.intensity_w_sr);
        }
        let n = (Vec3::ZERO - lamp).normalized();
        let helper = if n.z.abs() < 0.9 {
            Vec3::Z
        } else {
            Vec3::new(1.0, 0.0, 0.0)
        };
        let u = helper.cross(n).normalized();
        let v = n.cross(u);
        let per = self.intensity_w_sr / (DISC_RINGS * DISC_SPOKES) as f64;
        let mut e = 0.0;
        for ring in 0..DISC_RINGS {
            // equal-area rings: radius at the ring's area midpoint
            let r = self.radius_mm * ((ring as f64 + 0.5) / DISC_RINGS as f64).sqrt();
            for s in 0..DISC_SPOKES {
                let a = std::f64::consts::TAU * (s as f64 + 0.5 * (ring % 2) as f64) / DISC_SPOKES as f64;
                e += point(lamp + u * (r * a.cos()) + v * (r * a.sin()), per);
            }
        }
        e
    }

    /// Irradiance at every texel centre of a rectified image (row-major, W/m²).
    pub fn irradiance_map(&self, lamp: Vec3, params: &RectifyParams) -> Vec<f64> {
        let mut out = Vec::with_capacity(params.width * params.height);
        for j in 0..params.height {
            for i in 0..params.width {
                let (x, y) = params.texel_centre(i, j);
                out.push(self.irradiance(lamp, Vec3::new(x, y, 0.0)));
            }
        }
        out
    }
}

/// The radiometric conversion of a white-standard calibration.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Radiometric {
    /// Per channel: normalised sensor value per unit radiance (W m⁻² sr⁻¹), exposure
    /// second and unit gain, i.e. `value = K · exposure · gain · L`.
    pub k: [f64; 3],
    pub lamp: LampModel,
}

impl Radiometric {
    /// Convert a rectified image of linear values into BRDF values (1/sr) in place. `lamp`
    /// is the lamp's position (mm, sample frame) for this measurement. Texels the lamp does
    /// not reach (E = 0) become 0: no BRDF can be measured there.
    pub fn to_brdf(
        &self,
        image: &mut RgbImage,
        lamp: Vec3,
        params: &RectifyParams,
        exposure_s: f64,
        gain: f64,
    ) -> Result<(), DevelopError> {
        let expected = image.width * image.height * 3;
        if image.data.len() != expected || image.width != params.width || image.height != params.height {
            return Err(DevelopError::BadImage {
                width: params.width,
                height: params.height,
                len: image.data.len(),
                expected: params.width * params.height * 3,
            });
        }
        let scale = exposure_s * gain;
        if !(scale.is_finite() && scale > 0.0) {
            return Err(DevelopError::BadExposure { exposure_s, gain });
        }
        let e = self.lamp.irradiance_map(lamp, params);
        for (px, &e) in image.data.chunks_exact_mut(3).zip(&e) {
            for (v, k) in px.iter_mut().zip(&self.k) {
                let d = k * scale * e;
                *v = if d > 0.0 { (*v as f64 / d) as f32 } else { 0.0 };
            }
        }
        Ok(())
    }
}
