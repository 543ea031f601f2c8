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
//! - **Raw-frame correction** ([`RawCorrection`]): the dark, response, flat and colour
//!   results turn a frame's digital numbers into linear, vignetting-free linear-sRGB values
//!   before undistortion and rectification (the white standard's `K` is then fitted on, and
//!   applied to, the same corrected values).
//!
//! Corrected kinematics (axis zero offsets from the rig-geometry calibration) are applied
//! where the camera pose and lamp position come from, see [`AppliedCalibration`].

use super::radiometric::BlockMap;
use gonio_calibration::intrinsics::CameraModel;
use gonio_calibration::radiometric::ResponseCurve;
use gonio_calibration::warp::RectifyParams;
use gonio_devices::image::RgbImage;
use gonio_devices::rig::RigSpec;
use gonio_devices::Frame;
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
    #[error(
        "frame {width}×{height} ({len} values): the radiometric corrections were made for \
         {expected_width}×{expected_height} frames"
    )]
    FrameSize {
        width: usize,
        height: usize,
        len: usize,
        expected_width: usize,
        expected_height: usize,
    },
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

/// One calibration result a [`RawCorrection`] uses.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CorrectionSource {
    /// `response`, `dark`, `flat` or `colour`.
    pub kind: String,
    pub id: String,
    pub file: String,
}

/// The raw-frame correction of the dark, response, flat and colour results: digital numbers
/// → linear, dark-free, vignetting-free values in linear sRGB, per pixel of the raw frame.
///
/// The order is the reverse of the sensor's (`simulator/src/sensor.rs`: crosstalk mixes
/// the radiance, vignetting scales it, dark current adds electrons, the response curve
/// compresses the sum, the ADC quantises):
///
/// 1. **inverse response** per channel: `v = ½ · exp g(code)` (`g(mid) = 0`, so a linear
///    camera's curve gives `v = code / max_dn`, the scale of [`crate::engine::frame_to_linear`]);
///    below the curve's black limit, where its fit had no data, `v` falls linearly to 0;
///    without a response result `v = code / max_dn`;
/// 2. **minus the dark frame**, linearised through the same curve: the dark current adds
///    electrons *before* the response, so it is subtracted after inverting it, never from
///    the codes (and it also removes whatever offset the curve has at black);
/// 3. **÷ flat field** (relative gain, mean 1 where the flat saw its target): vignetting
///    scales the linear signal;
/// 4. **colour matrix** 3 × 3 to linear sRGB: crosstalk mixed the radiance first, so it is
///    undone last;
/// 5. values are clamped at 0: a BRDF is not negative (only values within the read noise
///    of black are affected).
///
/// Dark and flat maps are stored at block resolution ([`BlockMap`]) and interpolated
/// bilinearly between block centres (constant beyond the outermost centres), so a smooth
/// effect gets no block steps. Flat blocks the flat's target did not cover (the holder
/// frame around the standard) take the mean of their covered neighbours, repeatedly
/// outward: the markers there are only located, never measured.
///
/// **Saturated pixels** — any channel's code at or above the saturation code (the response
/// curve's `saturation_fraction · max_dn`, without a response the ADC's maximum) — carry
/// only a lower bound. They are counted ([`RawCorrection::apply`] returns the count; the
/// store loop writes it as `saturated_pixels` into the measurement record) and corrected
/// as a *neutral* pixel with every channel at the saturation code: a clipped channel mixed
/// through the colour matrix would otherwise invent a hue and pull its neighbours down.
/// They come out as the brightest white the camera can represent at that pixel, not as a
/// plausible estimate of the true value.
///
/// **Consistency** (checked in [`AppliedCalibration::from_results`]): a flat or colour
/// result applies only with the linearisation it was measured with — with the applied
/// response result's id (`linearisation = "response:ID"`), or `linear` when no response is
/// applied. A gain or matrix measured on values linearised differently is wrong level by
/// level, so it is refused with the fix (re-run the recipe with `response = …`). A flat is
/// measured without dark subtraction; on a lit white standard the dark level is far below
/// the signal (0.05 % on `radiometric.toml`), so it is applied together with a dark.
#[derive(Clone)]
pub struct RawCorrection {
    /// Frame size the maps were made for (`None`: no map, any size).
    pub size: Option<(usize, usize)>,
    response: Option<ResponseCurve>,
    /// Per channel, `½ exp g(code)` for every code `0 ..= max_dn` of the curve.
    lut: [Vec<f32>; 3],
    /// Dark map in DN (full resolution).
    dark_dn: Option<Vec<f32>>,
    /// The same linearised through the response (with one).
    dark_lin: Option<Vec<f32>>,
    /// Exposure the dark frames were taken at (s).
    pub dark_exposure_s: Option<f64>,
    /// 1 / flat gain (full resolution).
    inv_flat: Option<Vec<f32>>,
    colour: Option<[[f32; 3]; 3]>,
    /// The results used, in the order applied (response, dark, flat, colour).
    pub sources: Vec<CorrectionSource>,
}

impl std::fmt::Debug for RawCorrection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RawCorrection")
            .field("size", &self.size)
            .field("kinds", &self.kinds())
            .field("sources", &self.sources)
            .finish()
    }
}

/// Why a raw correction cannot be built from its results (the caller names the file).
#[derive(Debug, Error, Clone, PartialEq)]
#[error("{0}")]
pub struct RawCorrectionError(pub String);

/// The parts of a [`RawCorrection`] as loaded, before they are checked against each other.
#[derive(Clone, Debug, Default)]
pub struct RawParts {
    pub response: Option<(CorrectionSource, ResponseCurve)>,
    pub dark: Option<MapPart>,
    pub flat: Option<MapPart>,
    /// Matrix, the result's `linearisation` tag.
    pub colour: Option<(CorrectionSource, [[f64; 3]; 3], Option<String>)>,
}

/// A dark or flat map as loaded.
#[derive(Clone, Debug)]
pub struct MapPart {
    pub source: CorrectionSource,
    pub map: BlockMap,
    /// Frame size (pixels) the map was made for.
    pub size: (usize, usize),
    /// Dark: exposure of the dark frames (s); flat: unused (NaN).
    pub exposure_s: f64,
    /// Flat: the result's `linearisation` tag.
    pub linearisation: Option<String>,
}

/// Check that `map` is a block grid for a `w × h` frame.
fn check_block_map(map: &BlockMap, (w, h): (usize, usize)) -> Result<(), String> {
    if map.block == 0 || w == 0 || h == 0 {
        return Err(format!("block {} for a {w}×{h} frame: both must be ≥ 1", map.block));
    }
    let (bx, by) = (w.div_ceil(map.block), h.div_ceil(map.block));
    if (map.blocks_x, map.blocks_y) != (bx, by) || map.values.len() != bx * by * 3 {
        return Err(format!(
            "{}×{} blocks of {} px with {} values do not tile a {w}×{h} frame (needs {bx}×{by} blocks, {} values)",
            map.blocks_x,
            map.blocks_y,
            map.block,
            map.values.len(),
            bx * by * 3
        ));
    }
    if let Some(v) = map.values.iter().find(|v| !v.is_finite()) {
        return Err(format!("holds a non-finite value {v}"));
    }
    Ok(())
}

/// Fill blocks ≤ 0 (per channel) with the mean of their filled 8-neighbours, outward until
/// every block has a value; `None` if no block of some channel has one.
fn fill_empty_blocks(map: &BlockMap) -> Option<Vec<f32>> {
    let (bx, by) = (map.blocks_x, map.blocks_y);
    let mut v = map.values.clone();
    for c in 0..3 {
        loop {
            let empty: Vec<usize> = (0..bx * by).filter(|&b| v[b * 3 + c] <= 0.0).collect();
            if empty.is_empty() {
                break;
            }
            let mut filled = Vec::new();
            for &b in &empty {
                let (x, y) = ((b % bx) as i64, (b / bx) as i64);
                let (mut s, mut n) = (0.0f64, 0usize);
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let (nx, ny) = (x + dx, y + dy);
                        if nx < 0 || ny < 0 || nx >= bx as i64 || ny >= by as i64 {
                            continue;
                        }
                        let val = v[(ny as usize * bx + nx as usize) * 3 + c];
                        if val > 0.0 {
                            s += val as f64;
                            n += 1;
                        }
                    }
                }
                if n > 0 {
                    filled.push((b, (s / n as f64) as f32));
                }
            }
            if filled.is_empty() {
                return None;
            }
            for (b, val) in filled {
                v[b * 3 + c] = val;
            }
        }
    }
    Some(v)
}

/// Bilinear interpolation of block values (`blocks_x × blocks_y × 3`) between block centres
/// to every pixel of a `w × h` frame; constant beyond the outermost centres.
fn expand_blocks(values: &[f32], block: usize, (bx, by): (usize, usize), (w, h): (usize, usize)) -> Vec<f32> {
    // (lower block, upper block, weight of the upper) for each pixel centre along an axis
    let axis = |n: usize, blocks: usize| -> Vec<(usize, usize, f32)> {
        let centre = |b: usize| (b * block + ((b + 1) * block).min(n)) as f64 / 2.0;
        (0..n)
            .map(|i| {
                let x = i as f64 + 0.5;
                if blocks == 1 || x <= centre(0) {
                    return (0, 0, 0.0);
                }
                if x >= centre(blocks - 1) {
                    return (blocks - 1, blocks - 1, 0.0);
                }
                let b = ((x / block as f64 - 0.5).floor().max(0.0) as usize).min(blocks - 2);
                // the last block may be narrower: step until x is bracketed
                let mut b = b;
                while b + 2 < blocks && x >= centre(b + 1) {
                    b += 1;
                }
                while b > 0 && x < centre(b) {
                    b -= 1;
                }
                let t = (x - centre(b)) / (centre(b + 1) - centre(b));
                (b, b + 1, t as f32)
            })
            .collect()
    };
    let (xs, ys) = (axis(w, bx), axis(h, by));
    let mut out = vec![0f32; w * h * 3];
    for (j, &(y0, y1, ty)) in ys.iter().enumerate() {
        for (i, &(x0, x1, tx)) in xs.iter().enumerate() {
            for c in 0..3 {
                let at = |x: usize, y: usize| values[(y * bx + x) * 3 + c];
                let top = at(x0, y0) * (1.0 - tx) + at(x1, y0) * tx;
                let bot = at(x0, y1) * (1.0 - tx) + at(x1, y1) * tx;
                out[(j * w + i) * 3 + c] = top * (1.0 - ty) + bot * ty;
            }
        }
    }
    out
}

impl RawCorrection {
    /// Build the correction from its parts; `None` when there are none. Errors name the
    /// part's file and say what to change.
    pub fn build(parts: RawParts) -> Result<Option<RawCorrection>, (String, RawCorrectionError)> {
        let bad = |s: &CorrectionSource, m: String| (s.file.clone(), RawCorrectionError(m));
        let mut sources = Vec::new();
        // Consistency: flat and colour need the linearisation they were measured with.
        let size = match (&parts.dark, &parts.flat) {
            (Some(d), Some(f)) if d.size != f.size => {
                return Err(bad(
                    &f.source,
                    format!(
                        "flat map made for {}×{} frames, the dark map ({}) for {}×{}: both must come from this camera",
                        f.size.0, f.size.1, d.source.file, d.size.0, d.size.1
                    ),
                ))
            }
            (Some(m), _) | (None, Some(m)) => Some(m.size),
            (None, None) => None,
        };
        let mut lut: [Vec<f32>; 3] = Default::default();
        if let Some((src, curve)) = &parts.response {
            if curve.levels < 2
                || curve
                    .g
                    .iter()
                    .any(|g| g.len() != curve.levels || g.iter().any(|x| !x.is_finite()))
            {
                return Err(bad(
                    src,
                    format!(
                        "response curve: {} levels, g must have that many finite values per channel",
                        curve.levels
                    ),
                ));
            }
            if !(curve.max_dn >= 1.0 && curve.max_dn <= u16::MAX as f64) {
                return Err(bad(
                    src,
                    format!("response curve max_dn {}: must be 1 ..= 65535", curve.max_dn),
                ));
            }
            let n = curve.max_dn.round() as usize + 1;
            // Below the black limit the fit has no data (zero weight) and the curve is only
            // the smoothness term's extrapolation: on radiometric.toml it gives code 0 a
            // value of 1.7 % of mid-grey (0.0086 against 0.5), which a dark subtraction
            // through it would remove from every pixel. A response passes through 0 at no
            // signal, so the curve is continued linearly from the black limit to 0 instead.
            let zb = ((curve.validity.black_fraction * curve.max_dn).ceil() as usize).clamp(1, n - 1);
            lut = std::array::from_fn(|c| {
                let at_black = 0.5 * curve.g_at(c, zb as f64).exp();
                (0..n)
                    .map(|z| {
                        if z < zb {
                            (at_black * z as f64 / zb as f64) as f32
                        } else {
                            (0.5 * curve.g_at(c, z as f64).exp()) as f32
                        }
                    })
                    .collect()
            });
            sources.push(src.clone());
        }
        let (mut dark_dn, mut dark_lin, mut dark_exposure_s) = (None, None, None);
        if let Some(MapPart {
            source: src,
            map,
            size: sz,
            exposure_s: exposure,
            ..
        }) = &parts.dark
        {
            check_block_map(map, *sz).map_err(|m| bad(src, format!("dark map: {m}")))?;
            if let Some(v) = map.values.iter().find(|v| **v < 0.0) {
                return Err(bad(src, format!("dark map holds a negative level {v} DN")));
            }
            let full = expand_blocks(&map.values, map.block, (map.blocks_x, map.blocks_y), *sz);
            if parts.response.is_some() {
                // through the same table as the frames (fractional DN interpolated)
                dark_lin = Some(
                    full.iter()
                        .enumerate()
                        .map(|(k, &d)| {
                            let l = &lut[k % 3];
                            let x = (d as f64).clamp(0.0, (l.len() - 1) as f64);
                            let i = (x.floor() as usize).min(l.len() - 2);
                            let f = (x - i as f64) as f32;
                            l[i] * (1.0 - f) + l[i + 1] * f
                        })
                        .collect(),
                );
            }
            dark_dn = Some(full);
            dark_exposure_s = Some(*exposure);
            sources.push(src.clone());
        }
        let wanted = match &parts.response {
            Some((s, _)) => format!("response:{}", s.id),
            None => "linear".to_string(),
        };
        let linearisation_fix = |src: &CorrectionSource, had: &Option<String>| {
            let had = had.clone().unwrap_or_else(|| "not recorded (older result)".into());
            let how = match &parts.response {
                Some((s, _)) => format!(
                    "the applied response result {} (id {}); re-run the {} recipe with [radiometric] response = \"{}\"",
                    s.file, s.id, src.kind, s.file
                ),
                None => format!(
                    "no response result is applied, so values are taken as linear; apply the response result it \
                     was made with, or re-run the {} recipe with a single exposure and no response",
                    src.kind
                ),
            };
            bad(
                src,
                format!(
                    "{} was linearised with `{had}`, but this acquisition uses {how}",
                    src.kind
                ),
            )
        };
        let mut inv_flat = None;
        if let Some(MapPart {
            source: src,
            map,
            size: sz,
            linearisation: lin,
            ..
        }) = &parts.flat
        {
            check_block_map(map, *sz).map_err(|m| bad(src, format!("flat map: {m}")))?;
            if lin.as_deref() != Some(wanted.as_str()) {
                return Err(linearisation_fix(src, lin));
            }
            let filled = fill_empty_blocks(map).ok_or_else(|| {
                bad(
                    src,
                    "flat map covers no pixel in some channel: re-run the flat recipe".into(),
                )
            })?;
            let full = expand_blocks(&filled, map.block, (map.blocks_x, map.blocks_y), *sz);
            inv_flat = Some(full.iter().map(|g| 1.0 / g).collect());
            sources.push(src.clone());
        }
        let mut colour = None;
        if let Some((src, m, lin)) = &parts.colour {
            if lin.as_deref() != Some(wanted.as_str()) {
                return Err(linearisation_fix(src, lin));
            }
            if m.iter().flatten().any(|x| !x.is_finite()) {
                return Err(bad(src, format!("colour matrix {m:?} holds a non-finite value")));
            }
            colour = Some(m.map(|r| r.map(|x| x as f32)));
            sources.push(src.clone());
        }
        if sources.is_empty() {
            return Ok(None);
        }
        Ok(Some(RawCorrection {
            size,
            response: parts.response.map(|(_, c)| c),
            lut,
            dark_dn,
            dark_lin,
            dark_exposure_s,
            inv_flat,
            colour,
            sources,
        }))
    }

    /// The kinds applied, in order (`response`, `dark`, `flat`, `colour`).
    pub fn kinds(&self) -> Vec<String> {
        self.sources.iter().map(|s| s.kind.clone()).collect()
    }

    /// Check the correction against a camera delivering `width × height` frames of
    /// `bit_depth` bits: a map or curve made on another camera is refused, naming the file
    /// and both sizes.
    pub fn check_camera(&self, width: usize, height: usize, bit_depth: u32) -> Result<(), LoadError> {
        for s in &self.sources {
            let mismatch = |what: &str, made: String, camera: String| LoadError::CameraMismatch {
                file: s.file.clone(),
                what: what.to_string(),
                made,
                camera,
            };
            match s.kind.as_str() {
                "dark" | "flat" => {
                    let (w, h) = self.size.unwrap_or((width, height));
                    if (w, h) != (width, height) {
                        return Err(mismatch(
                            &format!("{} map", s.kind),
                            format!("{w}×{h} pixels"),
                            format!("{width}×{height} pixels"),
                        ));
                    }
                }
                "response" => {
                    let max = ((1u64 << bit_depth.min(16)) - 1) as f64;
                    let curve_max = self.response.as_ref().map_or(max, |c| c.max_dn);
                    if (curve_max - max).abs() > 0.5 {
                        return Err(mismatch(
                            "response curve",
                            format!("codes 0 ..= {curve_max}"),
                            format!("{bit_depth}-bit codes 0 ..= {max}"),
                        ));
                    }
                }
                _ => {}
            }
        }
        Ok(())
    }

    /// The code at and above which a value is saturated for frames with `max_dn`.
    pub fn saturation_code(&self, max_dn: u16) -> u16 {
        match &self.response {
            Some(c) => ((c.validity.saturation_fraction * c.max_dn).ceil() as u16).min(max_dn),
            None => max_dn,
        }
    }

    /// Correct a raw frame (see the type's documentation for the order and for what happens
    /// to saturated pixels). Returns the linear image and the number of saturated pixels.
    pub fn apply(&self, frame: &Frame) -> Result<(RgbImage, usize), ApplyError> {
        let (w, h) = (frame.width, frame.height);
        let (ew, eh) = self.size.unwrap_or((w, h));
        if (w, h) != (ew, eh) || frame.data.len() != w * h * 3 {
            return Err(ApplyError::FrameSize {
                width: w,
                height: h,
                len: frame.data.len(),
                expected_width: ew,
                expected_height: eh,
            });
        }
        let max_dn = frame.max_dn();
        if self.response.is_some() && self.lut[0].len() != max_dn as usize + 1 {
            return Err(ApplyError::FrameSize {
                width: w,
                height: h,
                len: frame.data.len(),
                expected_width: ew,
                expected_height: eh,
            });
        }
        let sat = self.saturation_code(max_dn);
        let inv_max = 1.0 / max_dn as f32;
        let lin = |c: usize, code: u16| -> f32 {
            if self.response.is_some() {
                self.lut[c][code.min(max_dn) as usize]
            } else {
                code as f32 * inv_max
            }
        };
        let mut out = RgbImage {
            width: w,
            height: h,
            data: vec![0.0; w * h * 3],
        };
        let mut saturated = 0usize;
        for (p, (px, dst)) in frame.data.chunks_exact(3).zip(out.data.chunks_exact_mut(3)).enumerate() {
            let clipped = px.iter().any(|&v| v >= sat);
            saturated += usize::from(clipped);
            let mut v: [f32; 3] = std::array::from_fn(|c| lin(c, if clipped { sat } else { px[c] }));
            let k = p * 3;
            match (&self.dark_lin, &self.dark_dn) {
                (Some(d), _) => v.iter_mut().enumerate().for_each(|(c, x)| *x -= d[k + c]),
                (None, Some(d)) => v.iter_mut().enumerate().for_each(|(c, x)| *x -= d[k + c] * inv_max),
                (None, None) => {}
            }
            if let Some(f) = &self.inv_flat {
                v.iter_mut().enumerate().for_each(|(c, x)| *x *= f[k + c]);
            }
            if let Some(m) = &self.colour {
                v = std::array::from_fn(|r| m[r][0] * v[0] + m[r][1] * v[1] + m[r][2] * v[2]);
            }
            for (d, x) in dst.iter_mut().zip(v) {
                *d = x.max(0.0);
            }
        }
        Ok((out, saturated))
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
    /// Dark, response, flat and colour results: applied to each raw frame before
    /// undistortion and rectification (see [`RawCorrection`]).
    pub raw: Option<RawCorrection>,
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
    /// `linear_corrected` with raw-frame corrections only (linear relative values, see
    /// [`RawCorrection`]), else `normalized_dn` (linear sensor signal, DN / max DN).
    pub fn value_unit(&self) -> &'static str {
        if self.radiometric.is_some() {
            VALUE_UNIT_BRDF
        } else if self.raw.is_some() {
            VALUE_UNIT_LINEAR
        } else {
            VALUE_UNIT_DN
        }
    }

    /// The raw-frame corrections applied, in order (`response`, `dark`, `flat`, `colour`).
    pub fn corrections(&self) -> Vec<String> {
        self.raw.as_ref().map(|r| r.kinds()).unwrap_or_default()
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
/// `value_unit` of data with raw-frame corrections but no white standard: linear values on
/// the response curve's relative scale (`½ exp g`), dark-, flat- and colour-corrected.
pub const VALUE_UNIT_LINEAR: &str = "linear_corrected";

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
    #[error(
        "calibration result {file}: the {what} was made for {made}, the camera delivers {camera}: \
         re-run that recipe on this camera (same size, ROI and bit depth)"
    )]
    CameraMismatch {
        file: String,
        what: String,
        made: String,
        camera: String,
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
        let mut raw = RawParts::default();
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
                "dark" | "response" | "flat" | "colour" => {
                    raw_part(r, &mut raw)?;
                    // ids are pushed once the parts are checked against each other
                    continue;
                }
                other => {
                    skipped.push(other.to_string());
                    continue;
                }
            }
            applied.ids.push(r.id.clone());
        }
        applied.raw = RawCorrection::build(raw).map_err(|(file, e)| LoadError::Bad { file, message: e.0 })?;
        applied
            .ids
            .extend(applied.raw.iter().flat_map(|c| c.sources.iter().map(|s| s.id.clone())));
        check_white_corrections(results, applied.raw.as_ref())?;
        Ok((applied, skipped))
    }
}

/// Parse a dark, response, flat or colour result into `parts`.
fn raw_part(r: &LoadedResult, parts: &mut RawParts) -> Result<(), LoadError> {
    let file = r.file.display().to_string();
    let bad = |message: String| LoadError::Bad {
        file: file.clone(),
        message,
    };
    let radio = &r.value["radiometric"];
    let src = CorrectionSource {
        kind: r.kind.clone(),
        id: r.id.clone(),
        file: file.clone(),
    };
    let get = |key: &str| -> Result<serde_json::Value, LoadError> {
        match radio.get(key) {
            Some(v) if !v.is_null() => Ok(v.clone()),
            _ => Err(bad(format!(
                "radiometric.{key} is missing: re-run the {} recipe",
                r.kind
            ))),
        }
    };
    let linearisation = radio.get("linearisation").and_then(|v| v.as_str()).map(String::from);
    let size = |key: &str| -> Result<(usize, usize), LoadError> {
        let v = get(key)?;
        match (v["width"].as_u64(), v["height"].as_u64()) {
            (Some(w), Some(h)) => Ok((w as usize, h as usize)),
            _ => Err(bad(format!("radiometric.{key} has no width/height"))),
        }
    };
    let map = |key: &str| -> Result<BlockMap, LoadError> {
        serde_json::from_value(get(key)?).map_err(|e| bad(format!("radiometric.{key}: {e}")))
    };
    match r.kind.as_str() {
        "response" => {
            let curve: ResponseCurve = serde_json::from_value(get("response")?["curve"].clone())
                .map_err(|e| bad(format!("radiometric.response.curve: {e}")))?;
            parts.response = Some((src, curve));
        }
        "dark" => {
            let exposure = get("dark")?["exposure_s"].as_f64().unwrap_or(f64::NAN);
            parts.dark = Some(MapPart {
                source: src,
                map: map("dark_map")?,
                size: size("dark")?,
                exposure_s: exposure,
                linearisation: None,
            });
        }
        "flat" => {
            parts.flat = Some(MapPart {
                source: src,
                map: map("flat_map")?,
                size: size("flat")?,
                exposure_s: f64::NAN,
                linearisation,
            })
        }
        _ => {
            let m: [[f64; 3]; 3] = serde_json::from_value(get("colour")?["matrix"].clone())
                .map_err(|e| bad(format!("radiometric.colour.matrix: {e}")))?;
            parts.colour = Some((src, m, linearisation));
        }
    }
    Ok(())
}

/// A white standard's `K` holds only for values corrected as they were during its fit: its
/// result lists the raw-correction ids it was measured with (`white_standard.corrections`,
/// empty in results of older builds), which must be exactly the ones applied.
fn check_white_corrections(results: &[LoadedResult], raw: Option<&RawCorrection>) -> Result<(), LoadError> {
    let Some(white) = results.iter().find(|r| r.kind == "white-standard") else {
        return Ok(());
    };
    let mut made: Vec<String> = white.value["white_standard"]["corrections"]
        .as_array()
        .map(|a| a.iter().filter_map(|v| v.as_str().map(String::from)).collect())
        .unwrap_or_default();
    let mut now: Vec<String> = raw
        .map(|c| c.sources.iter().map(|s| s.id.clone()).collect())
        .unwrap_or_default();
    made.sort();
    now.sort();
    if made == now {
        return Ok(());
    }
    Err(LoadError::Bad {
        file: white.file.display().to_string(),
        message: format!(
            "the white standard was fitted on frames corrected with the results {made:?}, this acquisition \
             applies {now:?} (dark/response/flat/colour): put the same results next to it, or re-run \
             white-standard.toml with [white_standard] corrections = \"DIR\" naming the directory of the \
             ones applied"
        ),
    })
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

    fn src(kind: &str) -> CorrectionSource {
        CorrectionSource {
            kind: kind.into(),
            id: format!("{kind}-id"),
            file: format!("cal/{kind}/calibration.json"),
        }
    }

    fn frame(w: usize, h: usize, data: Vec<u16>) -> Frame {
        Frame {
            width: w,
            height: h,
            data,
            meta: gonio_devices::FrameMeta {
                timestamp: 0.0,
                exposure: 0.05,
                gain: 1.0,
                sequence: 0,
                bit_depth: 12,
            },
        }
    }

    /// The compressing response of `radiometric.toml` (a = 2) as a fitted curve would hold it.
    fn curve() -> ResponseCurve {
        let inv = |y: f64| -(1.0 - y * (1.0 - (-2f64).exp())).ln() / 2.0;
        let levels = 256;
        let g: Vec<f64> = (0..levels)
            .map(|z| (inv(z as f64 / 255.0).max(1e-9) / inv(0.5)).ln())
            .collect();
        ResponseCurve {
            levels,
            max_dn: 4095.0,
            g: [g.clone(), g.clone(), g],
            validity: Default::default(),
        }
    }

    #[test]
    fn block_maps_are_interpolated_between_block_centres() {
        // 3 × 2 blocks of 4 px over a 10 × 8 frame (last column of blocks 2 px wide)
        let values: Vec<f32> = (0..6).flat_map(|b| [b as f32; 3]).collect();
        let out = expand_blocks(&values, 4, (3, 2), (10, 8));
        let at = |i: usize, j: usize| out[(j * 10 + i) * 3];
        // constant before the first centre (x = 2) and beyond the last (x = 9)
        assert_eq!(at(0, 0), 0.0);
        assert_eq!(at(9, 0), 2.0);
        // between centres 2 and 6 along x, linear: pixel 3 (x = 3.5) is 3/8 of the way
        assert!((at(3, 0) - 0.375).abs() < 1e-6, "{}", at(3, 0));
        // between the centre at 6 and the narrow last block's centre at 9: pixel 7 (7.5) half way
        assert!((at(7, 0) - 1.5).abs() < 1e-6, "{}", at(7, 0));
        // along y between the rows' centres 2 and 6: pixel row 4 (4.5) is 5/8 of the way (+3)
        assert!((at(0, 4) - 0.625 * 3.0).abs() < 1e-6, "{}", at(0, 4));
        // empty flat blocks take their neighbours' mean, outward
        let map = BlockMap {
            block: 4,
            blocks_x: 3,
            blocks_y: 1,
            values: vec![0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0],
        };
        assert_eq!(fill_empty_blocks(&map).unwrap(), vec![1.0; 9]);
        let empty = BlockMap {
            values: vec![0.0; 9],
            ..map
        };
        assert!(fill_empty_blocks(&empty).is_none());
    }

    /// Codes made the way the simulator makes them (crosstalk → vignetting → dark → response
    /// → ADC) come back as the scene's linear values up to one scale.
    #[test]
    fn raw_correction_inverts_the_sensor_in_reverse_order() {
        let (w, h) = (8usize, 8usize);
        let c = curve();
        let inv = |y: f64| -(1.0 - y * (1.0 - (-2f64).exp())).ln() / 2.0;
        let f = |u: f64| (1.0 - (-2.0 * u).exp()) / (1.0 - (-2f64).exp());
        let x = [[0.85, 0.12, 0.03], [0.08, 0.84, 0.08], [0.03, 0.15, 0.82]];
        // the colour correction: the crosstalk's inverse (rows · columns)
        let m = {
            let d = x[0][0] * (x[1][1] * x[2][2] - x[1][2] * x[2][1])
                - x[0][1] * (x[1][0] * x[2][2] - x[1][2] * x[2][0])
                + x[0][2] * (x[1][0] * x[2][1] - x[1][1] * x[2][0]);
            let cof = |r: usize, k: usize| {
                let (r1, r2) = ((r + 1) % 3, (r + 2) % 3);
                let (k1, k2) = ((k + 1) % 3, (k + 2) % 3);
                x[r1][k1] * x[r2][k2] - x[r1][k2] * x[r2][k1]
            };
            let m: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|k| cof(k, r) / d));
            m
        };
        let gain = |p: usize| 1.0 - 0.15 * ((p % w) as f64 - 3.5).powi(2) / 24.5;
        let dark_u = 0.002;
        let scene = [0.30, 0.20, 0.10];
        let mut data = Vec::new();
        for p in 0..w * h {
            let mixed: Vec<f64> = (0..3).map(|r| (0..3).map(|k| x[r][k] * scene[k]).sum()).collect();
            for v in mixed {
                data.push((f(v * gain(p) + dark_u) * 4095.0).round() as u16);
            }
        }
        let dark_dn = (f(dark_u) * 4095.0) as f32;
        let flat_vals: Vec<f32> = (0..w * h).flat_map(|p| [gain(p) as f32; 3]).collect();
        let parts = RawParts {
            response: Some((src("response"), c.clone())),
            dark: Some(MapPart {
                source: src("dark"),
                map: BlockMap {
                    block: 1,
                    blocks_x: w,
                    blocks_y: h,
                    values: vec![dark_dn; w * h * 3],
                },
                size: (w, h),
                exposure_s: 0.05,
                linearisation: None,
            }),
            flat: Some(MapPart {
                source: src("flat"),
                map: BlockMap {
                    block: 1,
                    blocks_x: w,
                    blocks_y: h,
                    values: flat_vals,
                },
                size: (w, h),
                exposure_s: f64::NAN,
                linearisation: Some("response:response-id".into()),
            }),
            colour: Some((src("colour"), m, Some("response:response-id".into()))),
        };
        let rc = RawCorrection::build(parts.clone()).unwrap().unwrap();
        assert_eq!(rc.kinds(), ["response", "dark", "flat", "colour"]);
        let (img, saturated) = rc.apply(&frame(w, h, data)).unwrap();
        assert_eq!(saturated, 0);
        // ½ exp g = ½ f⁻¹(y) / f⁻¹(½): the scene's values times one common scale
        let s = 0.5 / inv(0.5);
        for px in img.data.chunks_exact(3) {
            for ch in 0..3 {
                let rel = px[ch] as f64 / (s * scene[ch]) - 1.0;
                assert!(rel.abs() < 0.01, "channel {ch}: {px:?} vs {scene:?} (rel {rel})");
            }
        }

        // Extreme frames: all saturated → all counted, neutral and finite; all black → 0.
        let (img, n) = rc.apply(&frame(w, h, vec![4095; w * h * 3])).unwrap();
        assert_eq!(n, w * h);
        assert!(img.data.iter().all(|v| v.is_finite() && *v > 0.0));
        let p = &img.data[..3];
        // a neutral clip stays neutral through the colour matrix (its rows sum to 1)
        assert!(
            (p[0] - p[1]).abs() < 1e-3 * p[0] && (p[1] - p[2]).abs() < 1e-3 * p[0],
            "{p:?}"
        );
        let (img, n) = rc.apply(&frame(w, h, vec![0; w * h * 3])).unwrap();
        assert_eq!(n, 0);
        assert!(img.data.iter().all(|v| *v == 0.0));
        // one saturated channel makes the pixel count, the others are not mixed into a hue
        let mut one = vec![2000u16; w * h * 3];
        one[0] = 4095;
        let (img, n) = rc.apply(&frame(w, h, one)).unwrap();
        assert_eq!(n, 1);
        assert!((img.data[0] - img.data[1]).abs() < 1e-3 * img.data[0]);
        // a frame of another size is an error, not a panic
        assert!(matches!(
            rc.apply(&frame(4, 4, vec![0; 48])),
            Err(ApplyError::FrameSize { .. })
        ));

        // Camera checks name both sizes; a 10-bit camera does not fit a 12-bit curve.
        let e = rc.check_camera(16, 8, 12).unwrap_err().to_string();
        assert!(e.contains("8×8") && e.contains("16×8") && e.contains("cal/dark"), "{e}");
        let e = rc.check_camera(8, 8, 10).unwrap_err().to_string();
        assert!(e.contains("response curve") && e.contains("1023"), "{e}");
        rc.check_camera(8, 8, 12).unwrap();

        // Consistency: a flat measured on linear-assumed values with a response applied,
        // or a colour matrix with a response not applied, is refused with the fix.
        let mut bad = parts.clone();
        bad.flat.as_mut().unwrap().linearisation = Some("linear".into());
        let (file, e) = RawCorrection::build(bad).unwrap_err();
        assert_eq!(file, "cal/flat/calibration.json");
        assert!(e.0.contains("`linear`") && e.0.contains("response = "), "{}", e.0);
        let no_response = RawParts {
            response: None,
            flat: None,
            ..parts.clone()
        };
        let (file, e) = RawCorrection::build(no_response).unwrap_err();
        assert_eq!(file, "cal/colour/calibration.json");
        assert!(e.0.contains("no response result is applied"), "{}", e.0);
        // a map that does not tile its declared frame
        let mut torn = parts;
        torn.dark.as_mut().unwrap().size = (9, 8);
        torn.flat = None;
        let (file, e) = RawCorrection::build(torn).unwrap_err();
        assert_eq!(file, "cal/dark/calibration.json");
        assert!(e.0.contains("do not tile a 9×8 frame"), "{}", e.0);
        assert!(RawCorrection::build(RawParts::default()).unwrap().is_none());
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
