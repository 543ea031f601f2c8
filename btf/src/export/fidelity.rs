//! What a texture export costs in accuracy: the material a renderer reads back from the
//! exported textures against the per-texel fit they were written from.
//!
//! A renderer does not see the fit. It sees the textures: resampled to `--size`, quantized
//! to 8 or 16 bits (the base colour through the sRGB curve), the normal decoded from
//! `n/2 + 1/2` and renormalized, the anisotropy from its direction and strength, all
//! sampled bilinearly where the sample's texels were. [`measure`] rebuilds exactly that
//! material at the fit's texel centres and evaluates both with the glTF BRDF
//! ([`gonio_brdf::gltf::eval`]) over a fixed set of light and view directions, cosine-
//! weighted as the fit's residual is. The reference is the fit itself, so the figure is
//! what the texture size and bit depth cost, not the model's error against the data
//! (that is the fit's own residual, `gonio fit --json`).

use super::texture::{self, linear8, quantize16, srgb_encode};
use super::{ExportError, ExportOptions, Material};
use crate::compress::abrdf::srgb_to_linear;
use crate::compress::container::Gbtf;
use crate::compress::gltf as gltf_file;
use gonio_devices::Vec3;
use rayon::prelude::*;
use serde::Serialize;
use std::path::Path;

/// Parameters per texel of the rebuilt material: base colour (3), metallic, roughness,
/// normal (x, y), anisotropy vector (2), as in a 9-parameter glTF `.gbtf`.
const PARAMS: usize = 9;

/// Directions at or below this zenith angle (degrees) are evaluated; beyond, every model
/// goes to zero with the cosine and the relative error means little.
pub const MAX_THETA_DEG: f64 = 80.0;

/// The glTF textures' maps, each quantized on its own by [`MapDepths`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Map {
    BaseColor,
    Metallic,
    Roughness,
    Normal,
    Anisotropy,
}

impl Map {
    pub const ALL: [Map; 5] = [
        Map::BaseColor,
        Map::Metallic,
        Map::Roughness,
        Map::Normal,
        Map::Anisotropy,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Map::BaseColor => "base_color",
            Map::Metallic => "metallic",
            Map::Roughness => "roughness",
            Map::Normal => "normal",
            Map::Anisotropy => "anisotropy",
        }
    }
}

/// The bit depth each map is read back at: all alike as the export writes them, or one
/// map at 8 bits and the rest at 16, to tell which map's quantization costs what.
#[derive(Clone, Copy, Debug)]
struct MapDepths {
    base_color: u8,
    metallic: u8,
    roughness: u8,
    normal: u8,
    anisotropy: u8,
}

impl MapDepths {
    fn uniform(bits: u8) -> Self {
        MapDepths {
            base_color: bits,
            metallic: bits,
            roughness: bits,
            normal: bits,
            anisotropy: bits,
        }
    }

    /// `map` at 8 bits, every other map at 16.
    fn only_8_bit(map: Map) -> Self {
        let mut d = Self::uniform(16);
        *match map {
            Map::BaseColor => &mut d.base_color,
            Map::Metallic => &mut d.metallic,
            Map::Roughness => &mut d.roughness,
            Map::Normal => &mut d.normal,
            Map::Anisotropy => &mut d.anisotropy,
        } = 8;
        d
    }
}

/// One export setting's cost.
#[derive(Clone, Debug, Serialize)]
pub struct Fidelity {
    /// Texture side (texels).
    pub size: usize,
    pub bit_depth: u8,
    /// Whether a texture smaller than the fit was prefiltered ([`ExportOptions::prefilter`]).
    pub prefiltered: bool,
    /// A texture smaller than the fit: each exported texel against the mean of its
    /// footprint's fitted BRDFs (what a renderer pixel covering the footprint shows),
    /// relative RMS over every texel, pair and channel. `None` at the fit's size or above.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub footprint_rel_rms: Option<f64>,
    /// Set when only this map was read back at 8 bits and every other at 16 (`bit_depth`
    /// and `png_bytes` are then those of the 16-bit export).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub only_8_bit: Option<Map>,
    /// The glTF textures' PNG bytes (base colour, metallic-roughness, normal, and the
    /// anisotropy texture when a texel is anisotropic).
    pub png_bytes: usize,
    /// Relative RMS of the cosine-weighted BRDF over every texel, pair and channel.
    pub rel_rms: f64,
    /// Per texel RMS error relative to the material's RMS: mean, 99th percentile, largest.
    pub texel_mean: f64,
    pub texel_p99: f64,
    pub texel_max: f64,
    /// Wall time of building the textures and the read-back (s).
    pub seconds: f64,
}

/// `n` directions on the upper hemisphere up to [`MAX_THETA_DEG`] (a Fibonacci spiral,
/// equal solid angle each): the lights, and again the views, of the comparison.
pub fn directions(n: usize) -> Vec<Vec3> {
    let zmin = MAX_THETA_DEG.to_radians().cos();
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - (1.0 - zmin) * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = golden * i as f64;
            Vec3::new(r * phi.cos(), r * phi.sin(), z)
        })
        .collect()
}

/// 8- or 16-bit code of a value in [0, 1], decoded back.
fn quantized(v: f32, bits: u8) -> f32 {
    if bits == 16 {
        quantize16(v) as f32 / 65535.0
    } else {
        linear8(v) as f32 / 255.0
    }
}

/// The sRGB-encoded base colour as the texture stores it, decoded back to linear.
fn quantized_srgb(v: f32, bits: u8) -> f32 {
    if bits == 16 {
        gonio_devices::image::srgb_decode(quantize16(srgb_encode(v)) as f64 / 65535.0) as f32
    } else {
        srgb_to_linear(gonio_dataset::store::linear_to_srgb8(v))
    }
}

/// The material a renderer reads from `m`'s textures, texel by texel ([`PARAMS`] each),
/// each map at its depth in `d`.
fn read_back(m: &Material, d: MapDepths) -> Vec<f32> {
    let mut out = Vec::with_capacity(m.width * m.height * PARAMS);
    for t in 0..m.width * m.height {
        out.extend(m.base_color[t].map(|c| quantized_srgb(c, d.base_color)));
        out.push(quantized(m.metallic[t], d.metallic));
        out.push(quantized(m.roughness[t], d.roughness));
        // The normal map stores n/2 + 1/2; a renderer decodes and renormalizes.
        let n = m.normal[t].map(|c| 2.0 * quantized(0.5 * c + 0.5, d.normal) - 1.0);
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().max(1e-12);
        out.extend([n[0] / len, n[1] / len]);
        // Direction (cos φ, sin φ) and strength, as `texture::anisotropy_png` writes them.
        let a = m.anisotropy[t];
        let (s, phi) = gonio_brdf::gltf::anisotropy_of([a[0] as f64, a[1] as f64]);
        let bits = d.anisotropy;
        let dx = 2.0 * quantized(0.5 * phi.cos() as f32 + 0.5, bits) - 1.0;
        let dy = 2.0 * quantized(0.5 * phi.sin() as f32 + 0.5, bits) - 1.0;
        let s = quantized(s as f32, bits) as f64;
        let v = gonio_brdf::gltf::anisotropy_vector(s, (dy as f64).atan2(dx as f64));
        out.extend([v[0] as f32, v[1] as f32]);
    }
    out
}

/// PNG bytes of the glTF export's textures.
fn png_bytes(m: &Material) -> Result<usize, ExportError> {
    let mut n =
        texture::base_color_png(m)?.len() + texture::metallic_roughness_png(m)?.len() + texture::normal_png(m)?.len();
    if m.anisotropic_texels() > 0 {
        n += texture::anisotropy_png(m)?.len();
    }
    Ok(n)
}

/// The glTF BRDF of `p` (a texel's parameters, 7 or 9), cosine-weighted by the light.
fn radiance(p: &[f64], l: Vec3, v: Vec3) -> [f64; 3] {
    let a = if p.len() >= 9 { [p[7], p[8]] } else { [0.0, 0.0] };
    let f = gonio_brdf::gltf::eval(&[p[0], p[1], p[2]], p[3], p[4], [p[5], p[6]], a, l, v);
    f.map(|x| x * l.z)
}

/// Σ Δ² and Σ ref² over every pair of `dirs` × `dirs` and channel: the exported texel's
/// radiance against `reference` (one fitted texel, or a footprint's mean).
fn squared_error(dirs: &[Vec3], exported: &[f64], reference: impl Fn(Vec3, Vec3) -> [f64; 3]) -> (f64, f64) {
    let (mut d2, mut r2) = (0.0, 0.0);
    for &l in dirs {
        for &v in dirs {
            let a = reference(l, v);
            let b = radiance(exported, l, v);
            for c in 0..3 {
                d2 += (b[c] - a[c]).powi(2);
                r2 += a[c] * a[c];
            }
        }
    }
    (d2, r2)
}

/// The sums of per-texel `(Σ Δ², Σ ref²)`, in texel order (the same at any thread count).
fn sum_pairs(parts: &[(f64, f64)]) -> (f64, f64) {
    parts.iter().fold((0.0, 0.0), |(d, r), x| (d + x.0, r + x.1))
}

/// One export setting to measure: the texture side (`None`: the fit's own), the bit depth,
/// whether a smaller texture is prefiltered (the export's default) or sampled bilinearly,
/// and optionally one map read back at 8 bits with the others at 16 (`bit_depth` is then
/// 16).
#[derive(Clone, Copy, Debug)]
pub struct Setting {
    pub size: Option<usize>,
    pub bit_depth: u8,
    pub prefilter: bool,
    pub only_8_bit: Option<Map>,
}

impl Setting {
    /// As `gonio export --size S --bit-depth B` writes it.
    pub fn export(size: Option<usize>, bit_depth: u8) -> Self {
        Setting {
            size,
            bit_depth,
            prefilter: true,
            only_8_bit: None,
        }
    }

    /// The prefilter's baseline: a smaller texture sampled bilinearly between texel centres.
    pub fn bilinear(size: Option<usize>, bit_depth: u8) -> Self {
        Setting {
            prefilter: false,
            ..Self::export(size, bit_depth)
        }
    }

    /// Only `map` at 8 bits, the others at 16: what that map's quantization alone costs.
    pub fn map_at_8_bits(size: Option<usize>, map: Map) -> Self {
        Setting {
            only_8_bit: Some(map),
            ..Self::export(size, 16)
        }
    }
}

/// The cost of exporting the glTF fit `g` (read from `path`) with `setting`, over every
/// pair of `dirs` × `dirs`.
pub fn measure(g: &Gbtf, path: &Path, setting: Setting, dirs: &[Vec3]) -> Result<Fidelity, ExportError> {
    let Setting {
        size,
        bit_depth,
        prefilter,
        only_8_bit,
    } = setting;
    let t0 = std::time::Instant::now();
    let opts = ExportOptions {
        size,
        allow_uncalibrated: true,
        bit_depth,
        prefilter,
    };
    let m = Material::from_gbtf(g, path, &opts)?;
    let png = png_bytes(&m)?;
    let depths = only_8_bit.map_or(MapDepths::uniform(bit_depth), MapDepths::only_8_bit);
    let back = read_back(&m, depths);
    let (w, h) = (g.header.width, g.header.height);
    let np = gltf_file::params_per_texel(g);
    let fit = &g.blocks[0];
    // Per texel (in order, so the sums are the same at any thread count): Σ Δ² and Σ ref².
    let per_texel: Vec<(f64, f64)> = (0..w * h)
        .into_par_iter()
        .map(|t| {
            let (i, j) = (t % w, t / w);
            let exported = texture::bilinear(&back, PARAMS, m.width, m.height, i, j, w, h);
            let reference: Vec<f64> = fit[t * np..(t + 1) * np].iter().map(|&x| x as f64).collect();
            squared_error(dirs, &exported, |l, v| radiance(&reference, l, v))
        })
        .collect();
    let (d2, r2) = sum_pairs(&per_texel);
    let downsampled = texture::downsamples(w, h, m.width, m.height);
    let footprint_rel_rms = downsampled.then(|| {
        let per_out: Vec<(f64, f64)> = (0..m.width * m.height)
            .into_par_iter()
            .map(|c| {
                let fp = texture::footprint(w, h, c % m.width, c / m.width, m.width, m.height);
                let exported: Vec<f64> = back[c * PARAMS..(c + 1) * PARAMS].iter().map(|&x| x as f64).collect();
                let refs: Vec<Vec<f64>> = fp
                    .iter()
                    .map(|&t| fit[t * np..(t + 1) * np].iter().map(|&x| x as f64).collect())
                    .collect();
                squared_error(dirs, &exported, |l, v| {
                    let mut a = [0.0; 3];
                    for r in &refs {
                        let x = radiance(r, l, v);
                        (0..3).for_each(|k| a[k] += x[k] / refs.len() as f64);
                    }
                    a
                })
            })
            .collect();
        let (d, r) = sum_pairs(&per_out);
        if r > 0.0 {
            (d / r).sqrt()
        } else {
            0.0
        }
    });
    // Each texel's RMS error relative to the material's RMS (not to its own: a dark texel
    // next to a bright one would read as an error of hundreds of times its value).
    let texels = per_texel.len().max(1) as f64;
    let mut rel: Vec<f64> = per_texel
        .iter()
        .map(|&(d, _)| if r2 > 0.0 { (d * texels / r2).sqrt() } else { 0.0 })
        .collect();
    let texel_mean = rel.iter().sum::<f64>() / rel.len().max(1) as f64;
    rel.sort_by(f64::total_cmp);
    let pick = |q: f64| {
        rel.get(((rel.len() as f64 - 1.0) * q).round() as usize)
            .copied()
            .unwrap_or(0.0)
    };
    Ok(Fidelity {
        size: m.width,
        bit_depth,
        prefiltered: prefilter && downsampled,
        footprint_rel_rms,
        only_8_bit,
        png_bytes: png,
        rel_rms: if r2 > 0.0 { (d2 / r2).sqrt() } else { 0.0 },
        texel_mean,
        texel_p99: pick(0.99),
        texel_max: pick(1.0),
        seconds: t0.elapsed().as_secs_f64(),
    })
}
