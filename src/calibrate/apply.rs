//! Applying calibration results to measurements: pure functions of a frame or rectified
//! image and the measurement's geometry, so the store thread, tests and offline tools all
//! convert values the same way.
//!
//! - **Radiometric conversion** ([`Radiometric::to_brdf`]): a rectified image of linear
//!   sensor values (DN / max DN) becomes BRDF values (1/sr) per texel,
//!   `f = value / (K · exposure · gain · E(x))`, with `E(x) = I · cos θ_l(x) / d(x)²` the
//!   lamp's irradiance at the texel's own position (not the sample centre's): at 1.2 m a
//!   60 mm sample sees the falloff and the cosine change by several percent across it, more
//!   at grazing light, which a single scale per image would leave in the data.
//! - **Undistortion** ([`undistort_frame`]): a raw frame resampled to the ideal pinhole
//!   camera of the calibrated intrinsics, so the homography rectification (markers or pose),
//!   which assumes a pinhole, holds on a distorting lens.
//!
//! Corrected kinematics (axis zero offsets from the rig-geometry calibration) are applied
//! where the camera pose and lamp position come from, see [`AppliedCalibration`].

use gonio_calibration::intrinsics::CameraModel;
use gonio_calibration::warp::RectifyParams;
use gonio_devices::image::RgbImage;
use gonio_devices::rig::RigSpec;
use gonio_devices::{Intrinsics, Vec3};
use serde::{Deserialize, Serialize};
use thiserror::Error;

#[derive(Debug, Error, Clone, PartialEq)]
pub enum ApplyError {
    #[error("rig `{rig}`: {key} = {value}: {message}")]
    RigValue {
        rig: String,
        key: String,
        value: String,
        message: String,
    },
    #[error("image {width}×{height}: buffer holds {len} values, needs {expected}")]
    BadImage {
        width: usize,
        height: usize,
        len: usize,
        expected: usize,
    },
    #[error("measurement exposure {exposure_s} s × gain {gain}: must be > 0 to convert to BRDF")]
    BadExposure { exposure_s: f64, gain: f64 },
}

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
    pub fn from_rig(spec: &RigSpec) -> Result<LampModel, ApplyError> {
        let bad = |key: &str, value: String, message: &str| ApplyError::RigValue {
            rig: spec.name.clone(),
            key: key.into(),
            value,
            message: message.into(),
        };
        let i = spec.light.intensity_w_sr;
        if !(i.is_finite() && i > 0.0) {
            return Err(bad("light.intensity_w_sr", i.to_string(), "must be > 0"));
        }
        let radius_mm = match spec.light.options.get("radius_mm") {
            None => 0.0,
            Some(v) => v
                .as_float()
                .or_else(|| v.as_integer().map(|i| i as f64))
                .filter(|r| r.is_finite() && *r >= 0.0)
                .ok_or_else(|| bad("light.options.radius_mm", v.to_string(), "must be a length ≥ 0 (mm)"))?,
        };
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
    ) -> Result<(), ApplyError> {
        let expected = image.width * image.height * 3;
        if image.data.len() != expected || image.width != params.width || image.height != params.height {
            return Err(ApplyError::BadImage {
                width: params.width,
                height: params.height,
                len: image.data.len(),
                expected: params.width * params.height * 3,
            });
        }
        let scale = exposure_s * gain;
        if !(scale.is_finite() && scale > 0.0) {
            return Err(ApplyError::BadExposure { exposure_s, gain });
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

/// Every calibration an acquisition applies, as the store thread needs it.
#[derive(Clone, Debug, Default)]
pub struct AppliedCalibration {
    /// Ids of the calibration results, in the order applied.
    pub ids: Vec<String>,
    /// Calibrated camera: frames are undistorted with it and rectified with its matrix.
    pub camera: Option<CameraModel>,
    /// Conversion of rectified values to BRDF (1/sr).
    pub radiometric: Option<Radiometric>,
    /// Corrected kinematics: the axis zero offsets and camera mounting rotation of a
    /// rig-geometry calibration. Applied to the rig file *before* planning
    /// ([`AppliedCalibration::correct_rig`]), so the planner commands the positions that
    /// reach the asked directions and the store thread's camera pose and lamp position come
    /// from the same corrected kinematics; the manifest's rig then carries `[alignment]`,
    /// and `--resume` plans nothing again.
    pub rig_geometry: Option<super::rig_geometry::RigGeometryCalibration>,
    /// The lamp axes' zero offsets of a light-geometry calibration, applied with (after)
    /// the rig geometry: each writes only its own axes, so the camera's offsets come from
    /// one and the lamp's from the other.
    pub light_geometry: Option<super::light_geometry::LightGeometryCalibration>,
}

impl AppliedCalibration {
    /// Feed a rig-geometry calibration into `rig`'s kinematics (its `[alignment]`); no-op
    /// without one. Call before planning.
    pub fn correct_rig(&self, rig: &mut gonio_devices::rig::RigSpec) {
        if let Some(g) = &self.rig_geometry {
            g.apply(rig);
        }
        if let Some(g) = &self.light_geometry {
            g.apply(rig);
        }
    }

    /// Unit of the stored values: `brdf_per_sr` with a radiometric conversion, else
    /// `normalized_dn` (linear sensor signal, DN / max DN).
    pub fn value_unit(&self) -> &'static str {
        if self.radiometric.is_some() {
            VALUE_UNIT_BRDF
        } else {
            VALUE_UNIT_DN
        }
    }

    /// Intrinsics for the pose homography: the calibrated ones if present.
    pub fn intrinsics(&self, nominal: &Intrinsics) -> Intrinsics {
        match &self.camera {
            Some(c) => Intrinsics {
                fx: c.fx,
                fy: c.fy,
                cx: c.cx,
                cy: c.cy,
            },
            None => *nominal,
        }
    }
}

/// `value_unit` of BRDF data (1/sr).
pub const VALUE_UNIT_BRDF: &str = "brdf_per_sr";
/// `value_unit` of uncalibrated data (linear normalised sensor signal).
pub const VALUE_UNIT_DN: &str = "normalized_dn";

/// Resample a raw frame (gonio pixel convention: pixel (i, j) centred at (i + ½, j + ½)) to
/// the distortion-free pinhole camera with the same matrix: each output pixel looks up where
/// the lens put its ray (bilinear). Pixels whose source falls outside the frame become 0.
pub fn undistort_frame(raw: &RgbImage, cam: &CameraModel) -> RgbImage {
    if cam.distortion.iter().all(|&c| c == 0.0) {
        return raw.clone();
    }
    let (w, h) = (raw.width, raw.height);
    let mut out = RgbImage {
        width: w,
        height: h,
        data: vec![0.0; w * h * 3],
    };
    if w < 2 || h < 2 || raw.data.len() != w * h * 3 {
        return out;
    }
    use rayon::prelude::*;
    out.data.par_chunks_mut(w * 3).enumerate().for_each(|(j, row)| {
        let y = (j as f64 + 0.5 - cam.cy) / cam.fy;
        for i in 0..w {
            let x = (i as f64 + 0.5 - cam.cx) / cam.fx;
            let (xd, yd) = cam.distort(x, y);
            let (u, v) = (cam.fx * xd + cam.cx - 0.5, cam.fy * yd + cam.cy - 0.5);
            if !(u >= 0.0 && v >= 0.0 && u <= (w - 1) as f64 && v <= (h - 1) as f64) {
                continue;
            }
            let (i0, j0) = ((u as usize).min(w - 2), (v as usize).min(h - 2));
            let (fu, fv) = ((u - i0 as f64) as f32, (v - j0 as f64) as f32);
            for c in 0..3 {
                let at = |ii: usize, jj: usize| raw.data[(jj * w + ii) * 3 + c];
                let top = at(i0, j0) * (1.0 - fu) + at(i0 + 1, j0) * fu;
                let bot = at(i0, j0 + 1) * (1.0 - fu) + at(i0 + 1, j0 + 1) * fu;
                row[i * 3 + c] = top * (1.0 - fv) + bot * fv;
            }
        }
    });
    out
}

/// Why a calibration directory cannot be used.
#[derive(Debug, Error)]
pub enum LoadError {
    #[error("calibration directory {dir}: {source}")]
    Io { dir: String, source: std::io::Error },
    #[error("calibration directory {dir} holds no calibration.json (looked in it and its subdirectories)")]
    Empty { dir: String },
    #[error("calibration result {file}: {message}")]
    Bad { file: String, message: String },
    #[error(
        "calibration result {file} (id {id}) was made on rig `{calibrated}`, this acquisition uses rig `{rig}`: \
         calibrate this rig (or pass its rig file)"
    )]
    WrongRig {
        file: String,
        id: String,
        calibrated: String,
        rig: String,
    },
    #[error("calibration results {first} and {second} are both of kind `{kind}`: keep one per kind")]
    DuplicateKind {
        kind: String,
        first: String,
        second: String,
    },
}

/// One `calibration.json` as found on disk.
#[derive(Clone, Debug)]
pub struct LoadedResult {
    pub file: std::path::PathBuf,
    pub kind: String,
    pub id: String,
    pub rig: String,
    /// The file's bytes (copied into the dataset, so `--resume` applies the same result).
    pub bytes: Vec<u8>,
    pub value: serde_json::Value,
}

impl LoadedResult {
    /// Parse one result file. Read as JSON rather than as `CalibrationResult`, so results
    /// with fields this build does not know (newer kinds) still load.
    pub fn read(file: &std::path::Path) -> Result<LoadedResult, LoadError> {
        let name = file.display().to_string();
        let bad = |message: String| LoadError::Bad {
            file: name.clone(),
            message,
        };
        let bytes = std::fs::read(file).map_err(|e| bad(e.to_string()))?;
        let value: serde_json::Value = serde_json::from_slice(&bytes).map_err(|e| bad(format!("not JSON: {e}")))?;
        let field = |key: &str| {
            value
                .get(key)
                .and_then(|v| v.as_str())
                .map(String::from)
                .ok_or_else(|| bad(format!("no string field `{key}`")))
        };
        let format = field("format")?;
        if format != super::RESULT_FORMAT {
            return Err(bad(format!("format {format:?}, expected {:?}", super::RESULT_FORMAT)));
        }
        Ok(LoadedResult {
            file: file.to_path_buf(),
            kind: field("kind")?,
            id: field("id")?,
            rig: field("rig")?,
            bytes,
            value,
        })
    }
}

/// Every `calibration.json` in `dir` and in its direct subdirectories (one per recipe
/// kind, e.g. `cal/intrinsics/calibration.json`, `cal/white/calibration.json`), checked
/// against the rig the acquisition uses.
pub fn load_dir(dir: &std::path::Path, rig_name: &str) -> Result<Vec<LoadedResult>, LoadError> {
    let d = dir.display().to_string();
    let io = |source| LoadError::Io { dir: d.clone(), source };
    if !dir.is_dir() {
        // metadata gives the precise reason (missing, permission); a file is not a directory
        std::fs::metadata(dir).map_err(io)?;
        return Err(io(std::io::Error::other("not a directory")));
    }
    let mut files = Vec::new();
    let top = dir.join("calibration.json");
    if top.is_file() {
        files.push(top);
    }
    let mut subdirs: Vec<_> = std::fs::read_dir(dir)
        .map_err(io)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir())
        .collect();
    subdirs.sort();
    files.extend(
        subdirs
            .iter()
            .map(|p| p.join("calibration.json"))
            .filter(|p| p.is_file()),
    );
    load_files(&files, rig_name).and_then(|v| {
        if v.is_empty() {
            Err(LoadError::Empty { dir: d.clone() })
        } else {
            Ok(v)
        }
    })
}

/// Load the given result files (see [`load_dir`]).
pub fn load_files(files: &[std::path::PathBuf], rig_name: &str) -> Result<Vec<LoadedResult>, LoadError> {
    let mut out: Vec<LoadedResult> = Vec::new();
    for f in files {
        let r = LoadedResult::read(f)?;
        if r.rig != rig_name {
            return Err(LoadError::WrongRig {
                file: f.display().to_string(),
                id: r.id,
                calibrated: r.rig,
                rig: rig_name.into(),
            });
        }
        if let Some(prev) = out.iter().find(|p| p.kind == r.kind) {
            return Err(LoadError::DuplicateKind {
                kind: r.kind,
                first: prev.file.display().to_string(),
                second: f.display().to_string(),
            });
        }
        out.push(r);
    }
    Ok(out)
}

impl AppliedCalibration {
    /// What an acquisition applies from these results. Kinds it cannot apply yet are
    /// returned in the second list (recorded in the manifest as not applied).
    pub fn from_results(results: &[LoadedResult]) -> Result<(AppliedCalibration, Vec<String>), LoadError> {
        let mut applied = AppliedCalibration::default();
        let mut skipped = Vec::new();
        for r in results {
            let bad = |message: String| LoadError::Bad {
                file: r.file.display().to_string(),
                message,
            };
            match r.kind.as_str() {
                "intrinsics" => {
                    let cam: CameraModel = serde_json::from_value(r.value["intrinsics"]["camera"].clone())
                        .map_err(|e| bad(format!("intrinsics.camera: {e}")))?;
                    applied.camera = Some(cam);
                }
                "white-standard" => {
                    let radio: Radiometric = serde_json::from_value(r.value["white_standard"]["radiometric"].clone())
                        .map_err(|e| bad(format!("white_standard.radiometric: {e}")))?;
                    if radio.k.iter().any(|k| !(k.is_finite() && *k > 0.0)) {
                        return Err(bad(format!("white_standard.radiometric.k {:?}: must be > 0", radio.k)));
                    }
                    applied.radiometric = Some(radio);
                }
                "rig-geometry" => {
                    let geo: super::rig_geometry::RigGeometryCalibration =
                        serde_json::from_value(r.value["rig_geometry"].clone())
                            .map_err(|e| bad(format!("rig_geometry: {e}")))?;
                    applied.rig_geometry = Some(geo);
                }
                "light-geometry" => {
                    let geo: super::light_geometry::LightGeometryCalibration =
                        serde_json::from_value(r.value["light_geometry"].clone())
                            .map_err(|e| bad(format!("light_geometry: {e}")))?;
                    applied.light_geometry = Some(geo);
                }
                other => {
                    skipped.push(other.to_string());
                    continue;
                }
            }
            applied.ids.push(r.id.clone());
        }
        Ok((applied, skipped))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(n: usize) -> RectifyParams {
        RectifyParams {
            width: n,
            height: n,
            sample_mm: 60.0,
            max_supersample: 8,
        }
    }

    #[test]
    fn point_lamp_irradiance_is_inverse_square_and_cosine() {
        let lamp = LampModel {
            intensity_w_sr: 50.0,
            radius_mm: 0.0,
        };
        // straight above at 1 m: E = I / 1 m²
        let e = lamp.irradiance(Vec3::new(0.0, 0.0, 1000.0), Vec3::ZERO);
        assert!((e - 50.0).abs() < 1e-9, "{e}");
        // 60° off the normal at 2 m: I cos 60° / 4
        let at = Vec3::new(2000.0 * 60f64.to_radians().sin(), 0.0, 2000.0 * 0.5);
        assert!((lamp.irradiance(at, Vec3::ZERO) - 50.0 * 0.5 / 4.0).abs() < 1e-9);
        // below the horizon: nothing
        assert_eq!(lamp.irradiance(Vec3::new(1000.0, 0.0, -1.0), Vec3::ZERO), 0.0);
        // the falloff differs across the sample: the near edge is brighter
        let l = Vec3::new(1200.0 * 60f64.to_radians().sin(), 0.0, 600.0);
        let near = lamp.irradiance(l, Vec3::new(30.0, 0.0, 0.0));
        let far = lamp.irradiance(l, Vec3::new(-30.0, 0.0, 0.0));
        assert!(near / far > 1.05, "{near} {far}");
    }

    #[test]
    fn a_small_disc_matches_the_point_and_a_large_one_differs_slightly() {
        let point = LampModel {
            intensity_w_sr: 10.0,
            radius_mm: 0.0,
        };
        let l = Vec3::new(0.0, 0.0, 1000.0);
        let p = Vec3::new(10.0, 5.0, 0.0);
        let small = LampModel {
            radius_mm: 1.0,
            ..point
        };
        let big = LampModel {
            radius_mm: 300.0,
            ..point
        };
        let e0 = point.irradiance(l, p);
        assert!((small.irradiance(l, p) / e0 - 1.0).abs() < 1e-5);
        let rel = big.irradiance(l, p) / e0 - 1.0;
        // off-axis emitters are farther and more oblique: less irradiance
        assert!(rel < -0.01 && rel > -0.3, "{rel}");
    }

    #[test]
    fn brdf_conversion_inverts_the_measurement_model() {
        let radio = Radiometric {
            k: [0.7, 0.8, 0.9],
            lamp: LampModel {
                intensity_w_sr: 50.0,
                radius_mm: 0.0,
            },
        };
        let p = params(8);
        let lamp = Vec3::new(500.0, 300.0, 900.0);
        let e = radio.lamp.irradiance_map(lamp, &p);
        let f = [0.25, 0.1, 0.3];
        let (t, g) = (0.05, 2.0);
        let mut img = RgbImage::new(8, 8);
        for (px, e) in img.data.chunks_exact_mut(3).zip(&e) {
            for c in 0..3 {
                px[c] = (radio.k[c] * t * g * f[c] * e) as f32;
            }
        }
        radio.to_brdf(&mut img, lamp, &p, t, g).unwrap();
        for px in img.data.chunks_exact(3) {
            for c in 0..3 {
                assert!((px[c] as f64 / f[c] - 1.0).abs() < 1e-5, "{px:?}");
            }
        }
        assert!(matches!(
            radio.to_brdf(&mut img, lamp, &p, 0.0, 1.0),
            Err(ApplyError::BadExposure { .. })
        ));
        let mut wrong = RgbImage::new(4, 8);
        assert!(matches!(
            radio.to_brdf(&mut wrong, lamp, &p, t, g),
            Err(ApplyError::BadImage { .. })
        ));
    }

    #[test]
    fn undistortion_moves_content_to_its_pinhole_position() {
        // A frame with one bright pixel where a distorting lens puts the ray of the
        // pinhole pixel (300, 200); after undistortion the light is back at (300, 200).
        let cam = CameraModel {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
            distortion: [-0.2, 0.05, 0.0, 0.0, 0.0],
        };
        let (w, h) = (640, 480);
        let (pi, pj) = (500usize, 400usize);
        let (x, y) = ((pi as f64 + 0.5 - cam.cx) / cam.fx, (pj as f64 + 0.5 - cam.cy) / cam.fy);
        let (xd, yd) = cam.distort(x, y);
        let (u, v) = (cam.fx * xd + cam.cx, cam.fy * yd + cam.cy);
        let mut raw = RgbImage::new(w, h);
        for j in 0..h {
            for i in 0..w {
                let d2 = (i as f64 + 0.5 - u).powi(2) + (j as f64 + 0.5 - v).powi(2);
                let val = (-d2 / 8.0).exp() as f32;
                raw.data[(j * w + i) * 3..(j * w + i) * 3 + 3].copy_from_slice(&[val; 3]);
            }
        }
        let out = undistort_frame(&raw, &cam);
        let (mut best, mut at) = (0.0, 0);
        for (k, px) in out.data.chunks_exact(3).enumerate() {
            if px[0] > best {
                best = px[0];
                at = k;
            }
        }
        assert_eq!((at % w, at / w), (pi, pj), "peak moved back to the pinhole pixel");
        assert!(best > 0.9);
        // no distortion: identity
        let flat = CameraModel {
            distortion: [0.0; 5],
            ..cam
        };
        assert_eq!(undistort_frame(&raw, &flat), raw);
    }
}
