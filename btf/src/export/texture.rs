//! The textures of an export: resampling the fitted parameters to the asked resolution and
//! encoding them as 8- or 16-bit PNG (`--bit-depth`; base colour sRGB-encoded, every other
//! map linear). 16 bits: an sRGB step of 1/65535 instead of 1/255, for materials whose
//! maps are smooth enough that 8-bit banding shows in renders (docs/guide/export.md
//! measures the difference inside texels).

use super::{ExportError, Material};
use gonio_dataset::store::linear_to_srgb8;
use image::ImageEncoder;

/// Parameters of output texel (`i`, `j`) of an `ow × oh` texture resampled from `params`
/// (`w × h` texels × `np`): bilinear between texel centres, edges clamped (the nearest
/// texel itself when the size is unchanged).
#[allow(clippy::too_many_arguments)]
pub fn bilinear(params: &[f32], np: usize, w: usize, h: usize, i: usize, j: usize, ow: usize, oh: usize) -> Vec<f64> {
    let at = |x: usize, y: usize, k: usize| params[(y * w + x) * np + k] as f64;
    if (ow, oh) == (w, h) {
        return (0..np).map(|k| at(i, j, k)).collect();
    }
    let sx = ((i as f64 + 0.5) * w as f64 / ow as f64 - 0.5).clamp(0.0, (w - 1) as f64);
    let sy = ((j as f64 + 0.5) * h as f64 / oh as f64 - 0.5).clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (sx.floor() as usize, sy.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (sx - x0 as f64, sy - y0 as f64);
    (0..np)
        .map(|k| {
            let top = at(x0, y0, k) * (1.0 - fx) + at(x1, y0, k) * fx;
            let bottom = at(x0, y1, k) * (1.0 - fx) + at(x1, y1, k) * fx;
            top * (1.0 - fy) + bottom * fy
        })
        .collect()
}

/// Whether an `ow × oh` texture of a `w × h` fit is a downsampling (smaller, not the same
/// size): what the export prefilters and the fidelity compares against footprints.
pub fn downsamples(w: usize, h: usize, ow: usize, oh: usize) -> bool {
    ow <= w && oh <= h && (ow, oh) != (w, h)
}

/// The fine texels (`w × h`) whose centres fall inside output texel (`i`, `j`) of an
/// `ow × oh` texture: its footprint. Never empty (the nearest texel when none does).
pub fn footprint(w: usize, h: usize, i: usize, j: usize, ow: usize, oh: usize) -> Vec<usize> {
    let range = |k: usize, n: usize, on: usize| {
        // Centres (x + ½) in [k, k + 1) · n / on.
        let lo = ((k * n) as f64 / on as f64 - 0.5).ceil().max(0.0) as usize;
        let hi = ((((k + 1) * n) as f64 / on as f64 - 0.5).ceil() as usize).min(n);
        if lo < hi {
            lo..hi
        } else {
            let c = (((k as f64 + 0.5) * n as f64 / on as f64) as usize).min(n - 1);
            c..c + 1
        }
    };
    let (xs, ys) = (range(i, w, ow), range(j, h, oh));
    ys.flat_map(|y| xs.clone().map(move |x| y * w + x)).collect()
}

/// glTF parameters of output texel (`i`, `j`) prefiltered over its footprint (downsampling,
/// `ow ≤ w` and `oh ≤ h`): what a renderer should see when one of its pixels covers the
/// footprint. Base colour, metallic and the anisotropy vector `s·(cos 2φ, sin 2φ)` (an
/// axial mean) are averaged; the normals are averaged as unit vectors, and their spread
/// widens the lobe (Toksvig 2005; the von Mises–Fisher form of Han et al. 2007): with `L`
/// the length of the mean normal, κ ≈ (3L − L³)/(1 − L²), and a GGX lobe of α acts like
/// κ ≈ 2/α², so the variances add: `α'² = ⟨α²⟩ + 2/κ`, roughness `= α'^½`. Without that
/// term, a texture smaller than the fit blends normals into a flat one and keeps the
/// narrow lobes: the highlight a bumpy surface spreads over the footprint becomes one
/// sharp spot.
#[allow(clippy::too_many_arguments)] // the same texel addressing as `bilinear`
pub fn prefiltered(
    params: &[f32],
    np: usize,
    w: usize,
    h: usize,
    i: usize,
    j: usize,
    ow: usize,
    oh: usize,
) -> Vec<f64> {
    let fp = footprint(w, h, i, j, ow, oh);
    let at = |t: usize, k: usize| params[t * np + k] as f64;
    let n = fp.len() as f64;
    let mut out = vec![0.0; np];
    let mut mean_n = [0.0f64; 3];
    let mut alpha2 = 0.0;
    for &t in &fp {
        for (k, o) in out.iter_mut().enumerate() {
            if !matches!(k, 4..=6) {
                *o += at(t, k) / n;
            }
        }
        let r = at(t, 4).clamp(0.0, 1.0);
        alpha2 += r.powi(4) / n;
        let v = gonio_brdf::gltf::normal_vector([at(t, 5), at(t, 6)]);
        mean_n[0] += v.x / n;
        mean_n[1] += v.y / n;
        mean_n[2] += v.z / n;
    }
    let len = (mean_n[0].powi(2) + mean_n[1].powi(2) + mean_n[2].powi(2)).sqrt();
    let spread = if len < 1.0 - 1e-12 {
        let l = len.max(1e-6);
        2.0 * (1.0 - l * l) / (3.0 * l - l * l * l)
    } else {
        0.0
    };
    out[4] = (alpha2 + spread).sqrt().sqrt().min(1.0);
    let l = len.max(1e-12);
    out[5] = mean_n[0] / l;
    out[6] = mean_n[1] / l;
    out
}

fn encode(width: usize, height: usize, data: &[u8], color: image::ExtendedColorType) -> Result<Vec<u8>, ExportError> {
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(data, width as u32, height as u32, color)
        .map_err(|e| ExportError::Output {
            path: "texture".into(),
            reason: format!("PNG encoding: {e}"),
        })?;
    Ok(out)
}

/// Code values in [0, 1] (already transfer-encoded), `channels` per texel, as an 8- or
/// 16-bit PNG (16-bit samples handed to the encoder in native byte order, which it
/// writes big-endian as PNG stores them).
fn encode_bits(width: usize, height: usize, values: &[f32], channels: usize, bits: u8) -> Result<Vec<u8>, ExportError> {
    use image::ExtendedColorType as C;
    if bits == 16 {
        let data: Vec<u8> = values.iter().flat_map(|v| quantize16(*v).to_ne_bytes()).collect();
        let color = if channels == 1 { C::L16 } else { C::Rgb16 };
        return encode(width, height, &data, color);
    }
    let data: Vec<u8> = values.iter().map(|v| linear8(*v)).collect();
    encode(width, height, &data, if channels == 1 { C::L8 } else { C::Rgb8 })
}

/// Linear [0, 1] → 8-bit code value (no transfer curve).
pub fn linear8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

/// [0, 1] → 16-bit code value.
pub fn quantize16(v: f32) -> u16 {
    (v.clamp(0.0, 1.0) as f64 * 65535.0 + 0.5) as u16
}

/// The sRGB transfer curve on [0, 1] (the same curve `linear_to_srgb8` quantizes).
pub fn srgb_encode(v: f32) -> f32 {
    let v = if v > 0.0 { v.min(1.0) } else { 0.0 };
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// The base colour, sRGB-encoded RGB (8 or 16 bits).
pub fn base_color_png(m: &Material) -> Result<Vec<u8>, ExportError> {
    if m.bit_depth == 16 {
        let v: Vec<f32> = m.base_color.iter().flat_map(|c| c.map(srgb_encode)).collect();
        return encode_bits(m.width, m.height, &v, 3, 16);
    }
    let data: Vec<u8> = m.base_color.iter().flat_map(|c| c.map(linear_to_srgb8)).collect();
    encode(m.width, m.height, &data, image::ExtendedColorType::Rgb8)
}

/// A linear single-channel map (metallic, roughness), L8 or L16.
pub fn gray_png(width: usize, height: usize, v: &[f32], bits: u8) -> Result<Vec<u8>, ExportError> {
    encode_bits(width, height, v, 1, bits)
}

/// glTF's packed metallic-roughness texture: G = roughness, B = metallic (linear), R unused (0).
pub fn metallic_roughness_png(m: &Material) -> Result<Vec<u8>, ExportError> {
    let v: Vec<f32> = m
        .roughness
        .iter()
        .zip(&m.metallic)
        .flat_map(|(r, mt)| [0.0, *r, *mt])
        .collect();
    encode_bits(m.width, m.height, &v, 3, m.bit_depth)
}

/// The tangent-space normal map: `n · ½ + ½` per component, linear RGB (+Y up).
pub fn normal_png(m: &Material) -> Result<Vec<u8>, ExportError> {
    let v: Vec<f32> = m.normal.iter().flat_map(|n| n.map(|c| 0.5 * c + 0.5)).collect();
    encode_bits(m.width, m.height, &v, 3, m.bit_depth)
}

/// `KHR_materials_anisotropy`'s texture: RG the direction `(cos φ, sin φ)` in tangent space
/// mapped from [−1, 1] to [0, 1], B the strength; linear. An isotropic texel is direction +x,
/// strength 0.
pub fn anisotropy_png(m: &Material) -> Result<Vec<u8>, ExportError> {
    let v: Vec<f32> = m
        .anisotropy
        .iter()
        .flat_map(|a| {
            let (s, phi) = gonio_brdf::gltf::anisotropy_of([a[0] as f64, a[1] as f64]);
            let (sn, cs) = phi.sin_cos();
            [0.5 * cs as f32 + 0.5, 0.5 * sn as f32 + 0.5, s as f32]
        })
        .collect();
    encode_bits(m.width, m.height, &v, 3, m.bit_depth)
}
