//! Raw-frame corrections: the dark, response, flat and colour results applied to a frame's
//! digital numbers before any geometry ([`RawCorrection`]).

use super::DevelopError;
use gonio_calibration::radiometric::ResponseCurve;
use gonio_devices::image::RgbImage;
use gonio_devices::Frame;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// A stored map: block means, `blocks_x × blocks_y × 3` values, row-major. Dark and flat
/// results store their maps at this resolution; [`RawCorrection`] expands them.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct BlockMap {
    pub block: usize,
    pub blocks_x: usize,
    pub blocks_y: usize,
    pub values: Vec<f32>,
}

impl BlockMap {
    /// Block means of `data` (`w × h × 3`), ignoring entries ≤ 0 when `skip_zero`.
    pub fn from_pixels(data: &[f32], w: usize, h: usize, block: usize, skip_zero: bool) -> BlockMap {
        let (bx, by) = (w.div_ceil(block), h.div_ceil(block));
        let mut sum = vec![0f64; bx * by * 3];
        let mut n = vec![0usize; bx * by * 3];
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    let v = data[(y * w + x) * 3 + c];
                    if skip_zero && v <= 0.0 {
                        continue;
                    }
                    let k = ((y / block) * bx + x / block) * 3 + c;
                    sum[k] += v as f64;
                    n[k] += 1;
                }
            }
        }
        BlockMap {
            block,
            blocks_x: bx,
            blocks_y: by,
            values: sum
                .iter()
                .zip(&n)
                .map(|(s, &k)| if k > 0 { (s / k as f64) as f32 } else { 0.0 })
                .collect(),
        }
    }
}

/// A correction made on another camera (size, ROI or bit depth) than the one it is applied
/// to; names the result file and both sides.
#[derive(Debug, Error, Clone, PartialEq)]
#[error(
    "calibration result {file}: the {what} was made for {made}, the camera delivers {camera}: \
     re-run that recipe on this camera (same size, ROI and bit depth)"
)]
pub struct CameraMismatch {
    pub file: String,
    pub what: String,
    pub made: String,
    pub camera: String,
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
///    camera's curve gives `v = code / max_dn`, the scale of [`super::frame_to_linear`]);
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
/// **Consistency** (checked in `calibrate::apply::AppliedCalibration::from_results`): a flat or colour
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
pub(super) fn fill_empty_blocks(map: &BlockMap) -> Option<Vec<f32>> {
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
pub(super) fn expand_blocks(
    values: &[f32],
    block: usize,
    (bx, by): (usize, usize),
    (w, h): (usize, usize),
) -> Vec<f32> {
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
    pub fn check_camera(&self, width: usize, height: usize, bit_depth: u32) -> Result<(), CameraMismatch> {
        for s in &self.sources {
            let mismatch = |what: &str, made: String, camera: String| CameraMismatch {
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
    pub fn apply(&self, frame: &Frame) -> Result<(RgbImage, usize), DevelopError> {
        let (w, h) = (frame.width, frame.height);
        let (ew, eh) = self.size.unwrap_or((w, h));
        if (w, h) != (ew, eh) || frame.data.len() != w * h * 3 {
            return Err(DevelopError::FrameSize {
                width: w,
                height: h,
                len: frame.data.len(),
                expected_width: ew,
                expected_height: eh,
            });
        }
        let max_dn = frame.max_dn();
        if self.response.is_some() && self.lut[0].len() != max_dn as usize + 1 {
            return Err(DevelopError::FrameSize {
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
