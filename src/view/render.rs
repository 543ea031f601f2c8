//! The CPU reference renderer: a BTF on a plane, a sphere or a cylinder (thesis ch. 7).
//!
//! **Scene** (world frame = the sample frame of conventions.md, +z up):
//! * The **light is directional** (a light at infinity) from direction `light` (θ, φ), and
//!   the **camera is orthographic**, looking along `-view`. Why: a BTF is measured with
//!   (nearly) parallel light and view over the sample, so on the plane every texel sees
//!   exactly the (light, view) pair asked for and the picture is the BTF slice itself; a
//!   point light at a finite distance would add a scene scale the data do not have. The
//!   page draws the same scene.
//! * Camera basis: `w` = view direction (toward the camera), `r = normalize(w_z, 0, −w_x)`,
//!   `u = w × r`. At view θ = 0 this is the rectified frame (right = +x, up = +y). The
//!   image spans [−1, 1] world units on its shorter side (pixel centres).
//! * **plane**: the square [−1, 1]² at z = 0, frame (x, y, z), texture once over it
//!   (column with +x, row with −y as in a rectified image), so the plane seen from θ = 0 on
//!   a square canvas of a square texture's size is the BTF image texel for texel.
//! * **sphere**: radius 1 at the origin; tangent `T` = east (increasing longitude about
//!   +z), `B = N × T` (north); texture repeated twice around, once pole to pole.
//! * **cylinder**: radius 1, axis +y, y ∈ [−1, 1], no caps; `T` = around the axis,
//!   `B` = +y; texture twice around, once along the axis.
//! * Per hit point the light and view directions are expressed in the local frame
//!   (T, B, N) and looked up with [`direction_weights`] exactly as `gonio reconstruct`
//!   interpolates (≤ 3 lights × ≤ 3 views), at the nearest texel (no texture filtering).
//!   A point whose local light has z ≤ 0 is in its own shadow: black. A local direction
//!   farther than `MAX_GAP_DEG` from every measured one is also black (counted in
//!   [`RenderStats::unmeasured_pixels`]).
//! * **Radiance** = exposure × BTF value: a BTF image already contains the cosine of the
//!   light's incidence, so no extra cosine is applied. **Tone mapping**: clamp to [0, 1],
//!   sRGB encoding, 8 bits ([`gonio_dataset::store::linear_to_srgb8`]). Background: black.

use gonio_btf::compress::interp::{cross, direction_weights, dot, normalize, unit, BtfModel};
use gonio_btf::compress::CompressError;
use gonio_btf::compress::{CompressedBtf, Layout};
use serde::Serialize;
use std::collections::BTreeMap;

/// The shape the material is put on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Shape {
    Plane,
    Sphere,
    Cylinder,
}

impl Shape {
    pub fn name(self) -> &'static str {
        match self {
            Shape::Plane => "plane",
            Shape::Sphere => "sphere",
            Shape::Cylinder => "cylinder",
        }
    }
}

/// What to render.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Scene {
    /// Light direction (θ, φ) in degrees, world frame.
    pub light_deg: [f64; 2],
    /// View direction (θ, φ) in degrees, world frame (toward the camera).
    pub view_deg: [f64; 2],
    pub shape: Shape,
    pub width: usize,
    pub height: usize,
    /// Multiplier on the linear value before tone mapping.
    pub exposure: f64,
}

/// A rendered picture: linear values and their tone-mapped 8-bit sRGB.
#[derive(Clone, Debug)]
pub struct Rendered {
    pub width: usize,
    pub height: usize,
    /// Linear RGB (before exposure), interleaved, top row first; 0 off the shape.
    pub linear: Vec<f32>,
    /// 8-bit sRGB, interleaved, top row first.
    pub srgb8: Vec<u8>,
    pub stats: RenderStats,
}

/// Counts of what a render did.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct RenderStats {
    /// Pixels on the shape.
    pub shape_pixels: usize,
    /// Pixels on the shape whose local light is below their horizon.
    pub shadowed_pixels: usize,
    /// Pixels on the shape whose local light or view is too far from every measured one.
    pub unmeasured_pixels: usize,
    /// Distinct (light, view) grid pairs the picture uses.
    pub grid_pairs: usize,
}

/// Where a camera ray meets the shape.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Texture coordinates in [0, 1): u along columns, v along rows (row 0 = v 0).
    pub uv: [f64; 2],
    /// Light and view directions in the local frame (T, B, N), unit vectors.
    pub light_local: [f64; 3],
    pub view_local: [f64; 3],
}

fn fract(x: f64) -> f64 {
    x - x.floor()
}

/// (θ, φ) in degrees of a unit vector with z ≥ 0.
pub fn to_deg(d: [f64; 3]) -> [f64; 2] {
    let th = d[2].clamp(-1.0, 1.0).acos().to_degrees();
    let mut ph = d[1].atan2(d[0]).to_degrees();
    if ph < 0.0 {
        ph += 360.0;
    }
    [th, if th == 0.0 { 0.0 } else { ph }]
}

/// The camera ray through pixel (`px`, `py`) and where it meets the shape.
pub fn hit(scene: &Scene, px: usize, py: usize) -> Option<Hit> {
    let w = unit(scene.view_deg);
    let r = normalize([w[2], 0.0, -w[0]]);
    let u = cross(w, r);
    let (wf, hf) = (scene.width as f64, scene.height as f64);
    let m = wf.min(hf);
    let sx = (2.0 * (px as f64 + 0.5) - wf) / m;
    let sy = (hf - 2.0 * (py as f64 + 0.5)) / m;
    let o: [f64; 3] = std::array::from_fn(|k| sx * r[k] + sy * u[k] + 4.0 * w[k]);
    let d = w.map(|x| -x);
    let at = |t: f64| -> [f64; 3] { std::array::from_fn(|k| o[k] + t * d[k]) };
    let (p, tb, n, uv) = match scene.shape {
        Shape::Plane => {
            let p = at(o[2] / w[2]);
            if p[0].abs() > 1.0 || p[1].abs() > 1.0 {
                return None;
            }
            let uv = [(p[0] + 1.0) / 2.0, (1.0 - p[1]) / 2.0];
            (p, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], [0.0, 0.0, 1.0], uv)
        }
        Shape::Sphere => {
            let b = dot(o, d);
            let disc = b * b - (dot(o, o) - 1.0);
            if disc < 0.0 {
                return None;
            }
            let p = at(-b - disc.sqrt());
            let n = normalize(p);
            let e = [-n[1], n[0], 0.0];
            let t = if dot(e, e) < 1e-18 {
                [1.0, 0.0, 0.0]
            } else {
                normalize(e)
            };
            let lon = fract(n[1].atan2(n[0]) / std::f64::consts::TAU);
            let uv = [fract(2.0 * lon), n[2].clamp(-1.0, 1.0).acos() / std::f64::consts::PI];
            (p, [t, cross(n, t)], n, uv)
        }
        Shape::Cylinder => {
            let a = d[0] * d[0] + d[2] * d[2];
            let b = o[0] * d[0] + o[2] * d[2];
            let c = o[0] * o[0] + o[2] * o[2] - 1.0;
            let disc = b * b - a * c;
            if disc < 0.0 || a < 1e-12 {
                return None;
            }
            let p = at((-b - disc.sqrt()) / a);
            if p[1].abs() > 1.0 {
                return None;
            }
            let n = normalize([p[0], 0.0, p[2]]);
            let t = [n[2], 0.0, -n[0]];
            let ang = fract(n[0].atan2(n[2]) / std::f64::consts::TAU + 0.5);
            let uv = [fract(2.0 * ang), (1.0 - p[1]) / 2.0];
            (p, [t, [0.0, 1.0, 0.0]], n, uv)
        }
    };
    let _ = p;
    let l = unit(scene.light_deg);
    let local = |x: [f64; 3]| [dot(x, tb[0]), dot(x, tb[1]), dot(x, n)];
    Some(Hit {
        uv,
        light_local: local(l),
        view_local: local(w),
    })
}

/// Texel index (row-major, row 0 first) of texture coordinates on a `w × h` image.
pub fn texel(uv: [f64; 2], w: usize, h: usize) -> usize {
    let col = ((uv[0] * w as f64) as usize).min(w - 1);
    let row = ((uv[1] * h as f64) as usize).min(h - 1);
    row * w + col
}

/// `(pixel, texel, weight)`: one pixel's use of one grid pair.
type Use = (usize, usize, f32);

/// One pixel's lookups: texel and `(light, view, weight)` grid pairs.
struct PixelLookup {
    pixel: usize,
    texel: usize,
    pairs: Vec<(usize, usize, f32)>,
}

/// Every pixel's texel and interpolation weights (no decoding).
fn lookups(model: &dyn BtfModel, scene: &Scene) -> Result<(RenderStats, Vec<PixelLookup>), CompressError> {
    let (w, h) = (scene.width, scene.height);
    if w == 0 || h == 0 || w > super::params::MAX_SIDE || h > super::params::MAX_SIDE {
        return Err(CompressError::Invalid(format!("render size {w}×{h} out of range")));
    }
    if !(scene.exposure.is_finite() && scene.exposure > 0.0) {
        return Err(CompressError::Invalid(format!(
            "exposure {} must be > 0",
            scene.exposure
        )));
    }
    for (which, d) in [("light", scene.light_deg), ("view", scene.view_deg)] {
        if !(0.0..90.0).contains(&d[0]) || !d[1].is_finite() {
            return Err(CompressError::Invalid(format!(
                "{which} direction {d:?}°: θ must be in [0, 90)°"
            )));
        }
    }
    let (tw, th) = (model.width(), model.height());
    let mut stats = RenderStats::default();
    let mut lookups = Vec::new();
    for py in 0..h {
        for px in 0..w {
            let Some(hit) = hit(scene, px, py) else { continue };
            stats.shape_pixels += 1;
            if hit.light_local[2] <= 0.0 || hit.view_local[2] <= 0.0 {
                stats.shadowed_pixels += 1;
                continue;
            }
            let wl = direction_weights(model.lights_deg(), to_deg(hit.light_local), "light");
            let wv = direction_weights(model.views_deg(), to_deg(hit.view_local), "view");
            let (Ok(wl), Ok(wv)) = (wl, wv) else {
                stats.unmeasured_pixels += 1;
                continue;
            };
            let mut pairs = Vec::with_capacity(wl.len() * wv.len());
            for &(v, a) in &wv {
                for &(l, b) in &wl {
                    pairs.push((l, v, (a * b) as f32));
                }
            }
            lookups.push(PixelLookup {
                pixel: py * w + px,
                texel: texel(hit.uv, tw, th),
                pairs,
            });
        }
    }
    Ok((stats, lookups))
}

/// The grid pairs a picture of `scene` uses, `(light, view, Σ weight over its pixels)`,
/// most used first (ties: lower view, then lower light). The relight page streams a raw
/// dataset's images in this order, so the current picture is complete first.
pub fn needed_pairs(model: &dyn BtfModel, scene: &Scene) -> Result<Vec<(usize, usize, f64)>, CompressError> {
    let (_, lookups) = lookups(model, scene)?;
    let mut by_pair: BTreeMap<(usize, usize), f64> = BTreeMap::new();
    for lk in &lookups {
        for &(l, v, w) in &lk.pairs {
            *by_pair.entry((v, l)).or_default() += w as f64;
        }
    }
    let mut out: Vec<(usize, usize, f64)> = by_pair.into_iter().map(|((v, l), w)| (l, v, w)).collect();
    out.sort_by(|a, b| b.2.total_cmp(&a.2).then((a.1, a.0).cmp(&(b.1, b.0))));
    Ok(out)
}

/// Render `scene` with `model`. Errors only for an invalid scene or a model that fails to
/// decode; directions without measurements nearby render black.
pub fn render(model: &dyn BtfModel, scene: &Scene) -> Result<Rendered, CompressError> {
    let (w, h) = (scene.width, scene.height);
    let (mut stats, lookups) = lookups(model, scene)?;
    // Group by grid pair (BTreeMap: a fixed summation order for every pixel).
    let mut by_pair: BTreeMap<(usize, usize), Vec<Use>> = BTreeMap::new();
    for lk in &lookups {
        for &(l, v, wt) in &lk.pairs {
            by_pair.entry((v, l)).or_default().push((lk.pixel, lk.texel, wt));
        }
    }
    stats.grid_pairs = by_pair.len();
    let mut linear = vec![0f32; w * h * 3];
    let factors = as_factors(model);
    for (&(v, l), uses) in &by_pair {
        if let Some(f) = &factors {
            for &(pixel, t, wt) in uses {
                let x = f.texel(l, v, t);
                for ch in 0..3 {
                    linear[pixel * 3 + ch] += wt * x[ch];
                }
            }
        } else {
            let img = model.reconstruct(l, v)?;
            for &(pixel, t, wt) in uses {
                for ch in 0..3 {
                    linear[pixel * 3 + ch] += wt * img[t * 3 + ch];
                }
            }
        }
    }
    let e = scene.exposure as f32;
    let srgb8 = linear
        .iter()
        .map(|&x| gonio_dataset::store::linear_to_srgb8(e * x))
        .collect();
    Ok(Rendered {
        width: w,
        height: h,
        linear,
        srgb8,
        stats,
    })
}

/// Direct access to PCA / PVMF factors: one texel of one grid pair without decoding the
/// whole image.
struct Factors<'a> {
    pvmf: bool,
    c: usize,
    nl: usize,
    blocks: &'a [Vec<f32>],
}

impl Factors<'_> {
    fn texel(&self, l: usize, v: usize, t: usize) -> [f32; 3] {
        let c = self.c;
        let (basis, rows, r0) = if self.pvmf {
            (&self.blocks[2 * v], &self.blocks[2 * v + 1], l * 3)
        } else {
            (&self.blocks[0], &self.blocks[1], (v * self.nl + l) * 3)
        };
        let b = &basis[t * c..(t + 1) * c];
        std::array::from_fn(|ch| {
            let row = &rows[(r0 + ch) * c..(r0 + ch + 1) * c];
            b.iter().zip(row).map(|(x, y)| x * y).sum()
        })
    }
}

fn as_factors(model: &dyn BtfModel) -> Option<Factors<'_>> {
    let any = model.as_any()?;
    let m = any.downcast_ref::<CompressedBtf>()?;
    let pvmf = match m.layout() {
        Layout::ViewBases => true,
        Layout::Basis => false,
        Layout::Clusters { .. }
        | Layout::Index { .. }
        | Layout::ChannelFactors
        | Layout::HalfVectorTables { .. }
        | Layout::PerTexel
        | Layout::AnalyticPerTexel => return None,
    };
    Some(Factors {
        pvmf,
        c: m.components(),
        nl: m.header().lights_deg.len(),
        blocks: &m.gbtf.blocks,
    })
}

/// Encode interleaved 8-bit RGB as PNG.
pub fn png(width: usize, height: usize, rgb: &[u8]) -> Result<Vec<u8>, CompressError> {
    use image::ImageEncoder;
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(rgb, width as u32, height as u32, image::ExtendedColorType::Rgb8)
        .map_err(|e| CompressError::Invalid(format!("PNG encoding: {e}")))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use gonio_btf::compress::interp::reconstruct_at;
    use gonio_btf::compress::testdata::write_test_dataset;
    use gonio_btf::compress::{compress, Method, Params};

    fn model() -> (tempfile::TempDir, CompressedBtf) {
        let dir = tempfile::tempdir().unwrap();
        // θ 0°, a ring of 6 at 30° and a ring of 8 at 60°: dense enough that every local
        // direction of a curved shape has measurements within 30°.
        let mut grid = vec![[0.0, 0.0]];
        for (th, n) in [(30.0, 6), (60.0, 8)] {
            for k in 0..n {
                grid.push([th, 360.0 * k as f64 / n as f64]);
            }
        }
        let ds = write_test_dataset(dir.path(), (6, 6), &grid, &grid, &[], |l, v, t, c| {
            0.05 + 0.04 * ((l * 3 + v * 7 + t + c) % 11) as f32
        });
        let m = CompressedBtf::new(compress(&ds, &Params::new(Method::Pvmf, 3)).unwrap().0).unwrap();
        (dir, m)
    }

    /// The plane seen from θ = 0 at the texture's size is the interpolated BTF image,
    /// texel for texel (the per-texel factor path against `reconstruct_at`).
    #[test]
    fn the_plane_from_above_is_the_reconstructed_image() {
        let (_d, m) = model();
        for light in [[30.0, 0.0], [20.0, 50.0], [45.0, 200.0]] {
            let scene = Scene {
                light_deg: light,
                view_deg: [0.0, 0.0],
                shape: Shape::Plane,
                width: 6,
                height: 6,
                exposure: 2.0,
            };
            let pic = render(&m, &scene).unwrap();
            let (img, _) = reconstruct_at(&m, light, [0.0, 0.0]).unwrap();
            for (a, b) in pic.linear.iter().zip(&img) {
                assert!((a - b).abs() < 1e-5, "{light:?}: {a} vs {b}");
            }
            let want: Vec<u8> = img
                .iter()
                .map(|&x| gonio_dataset::store::linear_to_srgb8(2.0 * x))
                .collect();
            assert_eq!(pic.srgb8, want);
            assert_eq!(pic.stats.shape_pixels, 36);
        }
    }

    /// The factor fast path and the generic image path give the same picture.
    #[test]
    fn factor_path_equals_image_path_on_curved_shapes() {
        struct Generic<'a>(&'a CompressedBtf);
        impl BtfModel for Generic<'_> {
            fn width(&self) -> usize {
                self.0.width()
            }
            fn height(&self) -> usize {
                self.0.height()
            }
            fn lights_deg(&self) -> &[[f64; 2]] {
                BtfModel::lights_deg(self.0)
            }
            fn views_deg(&self) -> &[[f64; 2]] {
                BtfModel::views_deg(self.0)
            }
            fn reconstruct(&self, l: usize, v: usize) -> Result<Vec<f32>, CompressError> {
                self.0.reconstruct(l, v)
            }
        }
        let (_d, m) = model();
        for shape in [Shape::Sphere, Shape::Cylinder, Shape::Plane] {
            let scene = Scene {
                light_deg: [35.0, 60.0],
                view_deg: [25.0, 200.0],
                shape,
                width: 24,
                height: 20,
                exposure: 1.0,
            };
            let a = render(&m, &scene).unwrap();
            let b = render(&Generic(&m), &scene).unwrap();
            assert_eq!(a.stats, b.stats);
            assert!(a.stats.shape_pixels > 100 && a.stats.grid_pairs > 1, "{:?}", a.stats);
            for (x, y) in a.linear.iter().zip(&b.linear) {
                assert!((x - y).abs() < 1e-5, "{shape:?}: {x} vs {y}");
            }
        }
    }

    /// The streaming order lists exactly the pairs the picture uses, most used first, and
    /// their weights add up to one per drawn pixel.
    #[test]
    fn needed_pairs_are_the_pairs_the_picture_uses() {
        let (_d, m) = model();
        for shape in [Shape::Plane, Shape::Sphere, Shape::Cylinder] {
            let scene = Scene {
                light_deg: [35.0, 60.0],
                view_deg: [25.0, 200.0],
                shape,
                width: 24,
                height: 20,
                exposure: 1.0,
            };
            let pic = render(&m, &scene).unwrap();
            let need = needed_pairs(&m, &scene).unwrap();
            assert_eq!(need.len(), pic.stats.grid_pairs, "{shape:?}");
            assert!(
                need.windows(2).all(|w| w[0].2 >= w[1].2),
                "{shape:?}: not most used first"
            );
            let drawn = pic.stats.shape_pixels - pic.stats.shadowed_pixels - pic.stats.unmeasured_pixels;
            let total: f64 = need.iter().map(|p| p.2).sum();
            assert!(
                (total - drawn as f64).abs() < 1e-3 * drawn as f64,
                "{shape:?}: {total} vs {drawn}"
            );
        }
        // The plane from above under a measured light uses that one pair.
        let scene = Scene {
            light_deg: [30.0, 60.0],
            view_deg: [0.0, 0.0],
            shape: Shape::Plane,
            width: 6,
            height: 6,
            exposure: 1.0,
        };
        let need = needed_pairs(&m, &scene).unwrap();
        assert_eq!(need.len(), 1);
        assert_eq!((need[0].0, need[0].1), (2, 0));
    }

    /// The whole sphere is drawn, not a dome: seen from near the horizon with the light
    /// there too, points below the equator (lower half of the picture) are lit.
    #[test]
    fn the_sphere_is_drawn_below_its_equator() {
        let (_d, m) = model();
        let scene = Scene {
            light_deg: [80.0, 0.0],
            view_deg: [80.0, 0.0],
            shape: Shape::Sphere,
            width: 32,
            height: 32,
            exposure: 1.0,
        };
        let below = (22..32)
            .flat_map(|py| (0..32).map(move |px| (px, py)))
            .filter(|&(px, py)| hit(&scene, px, py).is_some_and(|h| h.uv[1] > 0.5))
            .count();
        assert!(below > 20, "{below} hits below the equator");
        let pic = render(&m, &scene).unwrap();
        let lit = (22 * 32..32 * 32).filter(|&p| pic.linear[p * 3] > 0.0).count();
        assert!(lit > 20, "{lit} lit pixels in the lower third");
    }

    /// Geometry: the sphere's centre faces the camera; the shadowed side is black; the
    /// local frame is orthonormal.
    #[test]
    fn hits_have_orthonormal_local_directions() {
        for shape in [Shape::Plane, Shape::Sphere, Shape::Cylinder] {
            let scene = Scene {
                light_deg: [50.0, 10.0],
                view_deg: [30.0, 120.0],
                shape,
                width: 33,
                height: 33,
                exposure: 1.0,
            };
            let mut n = 0;
            for py in 0..33 {
                for px in 0..33 {
                    if let Some(h) = hit(&scene, px, py) {
                        n += 1;
                        assert!((dot(h.light_local, h.light_local) - 1.0).abs() < 1e-9);
                        assert!((dot(h.view_local, h.view_local) - 1.0).abs() < 1e-9);
                        // The angle between light and view does not depend on the frame.
                        let cos = dot(unit(scene.light_deg), unit(scene.view_deg));
                        assert!((dot(h.light_local, h.view_local) - cos).abs() < 1e-9);
                        assert!(h.uv.iter().all(|&x| (0.0..=1.0).contains(&x)), "{:?}", h.uv);
                    }
                }
            }
            assert!(n > 200, "{shape:?}: {n} hits");
        }
        // Sphere centre pixel seen along the view: local view = normal.
        let scene = Scene {
            light_deg: [0.0, 0.0],
            view_deg: [40.0, 70.0],
            shape: Shape::Sphere,
            width: 33,
            height: 33,
            exposure: 1.0,
        };
        let h = hit(&scene, 16, 16).unwrap();
        assert!((h.view_local[2] - 1.0).abs() < 1e-9, "{:?}", h.view_local);
    }
}
