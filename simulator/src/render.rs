//! The physically based renderer of the simulated camera.
//!
//! Two routines answer "what radiance (W m⁻² sr⁻¹) arrives at `origin` along a ray":
//! `trace` finds the first visible surface point (parallax on the height field, so masking
//! toward the camera comes for free) and its texel; `shade` looks up the texel's material,
//! tests self-shadowing toward the lamp in a per-light-direction shadow map, and applies
//! the lamp's inverse-square falloff and cosine. Raw frames ([`Renderer::render_raw`]) and
//! the ground-truth BTF in texture space ([`Renderer::render_truth`]) both call them, so
//! they cannot disagree about the physics. Tracing depends on the camera only, so both
//! images split into a traced view ([`RawView`], [`TruthView`]) and its shading per light:
//! a simulated acquisition traces each camera pose once (see [`ViewCache`]).
//!
//! What a scene does not need is not computed: a flat sample intersects one plane and builds
//! no shadow maps; a homogeneous sample does no map look-ups; pixels outside the holder's
//! projected bounding box are not traced at all.

use crate::sample::{HeightGrid, Sample, Surface};
use gonio_devices::image::RgbImage;
use gonio_devices::kinematics::CameraPose;
use gonio_devices::{Intrinsics, Vec3};
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

/// The lamp: a point, or (with `radius` > 0) a disc facing the sample centre.
///
/// A disc lamp is rendered as [`RenderQuality::area_samples`] isotropic point emitters
/// spread evenly over the disc (a Vogel spiral), each with `intensity / samples`: that
/// gives the soft shadow edges and the near-field falloff of a real lamp's finite size.
/// Each emitter has its own shadow map, so the cost grows with the samples; a point lamp
/// (`radius` 0, the default) pays nothing for it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointLight {
    /// Position (the disc's centre) in the sample frame (mm).
    pub position: Vec3,
    /// Radiant intensity (W/sr) of the whole lamp.
    pub intensity: f64,
    /// Disc radius (mm); 0 = a point lamp.
    pub radius: f64,
}

impl PointLight {
    /// A point lamp.
    pub fn point(position: Vec3, intensity: f64) -> Self {
        PointLight {
            position,
            intensity,
            radius: 0.0,
        }
    }
}

/// One emitter of a lamp with its shadow map (`None` on flat samples).
type Emitter = (PointLight, Option<Arc<ShadowMap>>);

/// OpenCV's radial-tangential lens distortion `[k1, k2, p1, p2, k3]` of the simulated
/// camera (rig file `camera.options`: `k1`, `k2`, `p1`, `p2`, `k3`; default 0 = pinhole).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LensDistortion(pub [f64; 5]);

impl LensDistortion {
    pub fn is_zero(&self) -> bool {
        self.0.iter().all(|&c| c == 0.0)
    }

    /// Distorted normalized coordinates of undistorted `(x, y) = (X/Z, Y/Z)`.
    #[inline]
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.0;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// Inverse of [`distort`](Self::distort) by fixed-point iteration (identity when zero).
    #[inline]
    pub fn undistort(&self, xd: f64, yd: f64) -> (f64, f64) {
        if self.is_zero() {
            return (xd, yd);
        }
        let (mut x, mut y) = (xd, yd);
        for _ in 0..40 {
            let (dx, dy) = self.distort(x, y);
            let (ex, ey) = (dx - xd, dy - yd);
            x -= ex;
            y -= ey;
            if ex.abs().max(ey.abs()) < 1e-14 {
                break;
            }
        }
        (x, y)
    }
}

/// Knobs that trade render error for time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderQuality {
    /// Stratified samples per pixel and axis (1 = pixel centre only).
    pub supersample: usize,
    /// Shadow-map resolution relative to the height grid (1 = one shadow texel per height texel).
    pub shadow_scale: usize,
    /// Samples per texel and axis of the ground truth: a texel's true value is the mean
    /// over its area (what an ideal, alias-free rectification delivers).
    pub truth_supersample: usize,
    /// Point emitters a disc lamp is sampled with (ignored for point lamps).
    pub area_samples: usize,
}

impl Default for RenderQuality {
    fn default() -> Self {
        RenderQuality {
            supersample: 1,
            shadow_scale: 1,
            truth_supersample: 1,
            area_samples: 16,
        }
    }
}

/// Binary shadow map of the height field for one light position: 1 = lit.
struct ShadowMap {
    n: usize,
    lit: Vec<u8>,
}

/// Renders a built sample under a point lamp.
pub struct Renderer {
    pub sample: Arc<Sample>,
    pub quality: RenderQuality,
    /// Shadow maps by quantised light position; built once per light direction.
    shadows: Mutex<HashMap<[i64; 3], Arc<ShadowMap>>>,
}

/// Samples per axis for pixels that see the holder frame rather than the sample.
const FRAME_SS: usize = 4;

/// Maximum number of cached shadow maps (81 Bonn light directions × 16 disc emitters fit).
const SHADOW_CACHE: usize = 4096;
/// Memory the cached shadow maps may take (81 lights × 16 disc emitters of a 256² map fit).
const SHADOW_CACHE_BYTES: usize = 96 << 20;

#[derive(Clone, Copy, Debug)]
enum Hit {
    Sample { p: Vec3, i: usize, j: usize, normal: Vec3 },
    Frame { p: Vec3, albedo: f64 },
    Background,
}

impl Renderer {
    pub fn new(sample: Arc<Sample>, quality: RenderQuality) -> Self {
        crate::count_construction();
        Renderer {
            sample,
            quality,
            shadows: Mutex::new(HashMap::new()),
        }
    }

    /// Number of shadow maps built so far (for the "built once per direction" check).
    pub fn shadow_maps_built(&self) -> usize {
        self.shadows.lock().map(|m| m.len()).unwrap_or(0)
    }

    fn half(&self) -> f64 {
        self.sample.spec.size_mm / 2.0
    }

    /// First surface hit along `origin + t·dir` (dir unit, pointing down toward the sample).
    fn trace(&self, origin: Vec3, dir: Vec3) -> Hit {
        if dir.z >= 0.0 {
            return Hit::Background;
        }
        let half = self.half();
        if let Surface::Height(g) = &self.sample.surface {
            // Only rays that can reach the sample square are marched through the relief.
            if self.hits_sample_area(origin, dir) {
                if let Some((p, i, j, normal)) = self.march(g, origin, dir) {
                    return Hit::Sample { p, i, j, normal };
                }
            }
        }
        // The mean plane z = 0: the flat sample, or the holder frame around it.
        let t = -origin.z / dir.z;
        let p = origin + dir * t;
        if p.x.abs() <= half && p.y.abs() <= half {
            if matches!(self.sample.surface, Surface::Height(_)) {
                // The march found nothing over the sample: the ray grazes past its edge.
                return Hit::Background;
            }
            let (i, j) = self.sample.texel_of(p.x, p.y);
            return Hit::Sample {
                p,
                i,
                j,
                normal: Vec3::Z,
            };
        }
        let outer = self.sample.spec.border.outer_half(self.sample.spec.size_mm);
        if p.x.abs() <= outer && p.y.abs() <= outer {
            let spec = &self.sample.spec;
            let albedo = if spec.border.is_marker(spec.size_mm, p.x, p.y) {
                spec.marker_albedo
            } else {
                spec.frame_albedo
            };
            return Hit::Frame { p, albedo };
        }
        Hit::Background
    }

    /// Ray-march the height field between its top and bottom planes.
    fn march(&self, g: &HeightGrid, origin: Vec3, dir: Vec3) -> Option<(Vec3, usize, usize, Vec3)> {
        let half = self.half();
        let t0 = ((origin.z - g.max) / -dir.z).max(0.0);
        let t1 = (origin.z - g.min) / -dir.z;
        let horiz = (dir.x * dir.x + dir.y * dir.y).sqrt();
        // One step per grid texel: the bilinear surface has no detail finer than that.
        let step_len = g.texel;
        let steps = (((t1 - t0) * horiz / step_len).ceil() as usize).clamp(1, 4 * g.n);
        let dt = (t1 - t0) / steps as f64;
        // The relief's edge texels continue a little past the sample square (its cut
        // edge), so rays grazing the edge hit the sample instead of falling through.
        let reach = half + 2.0 * g.texel;
        if let Some(n) = g.plane {
            // A plane through the origin: one exact intersection. Rays from behind it, or
            // meeting it outside the square (they pass the wedge's cut edge), see nothing.
            let nd = n.dot(dir);
            if nd >= 0.0 {
                return None;
            }
            let t = -n.dot(origin) / nd;
            let p = origin + dir * t;
            if t < 0.0 || p.x.abs() > reach || p.y.abs() > reach {
                return None;
            }
            let (i, j) = self.sample.texel_of(p.x, p.y);
            return Some((p, i, j, n));
        }
        let f = |t: f64| {
            let p = origin + dir * t;
            if p.x.abs() > reach || p.y.abs() > reach {
                None
            } else {
                Some(p.z - self.height(g, p.x, p.y))
            }
        };
        let mut ta = t0;
        let mut fa = f(ta);
        for k in 1..=steps {
            let tb = t0 + dt * k as f64;
            let fb = f(tb);
            if let (Some(a), Some(b)) = (fa, fb) {
                if a > 0.0 && b <= 0.0 {
                    // Regula falsi (Illinois variant) inside the bracketing step: the
                    // height field is smooth at this scale, so 4 iterations reach
                    // ~1e-4 texel where plain bisection needs 12.
                    let (mut lo, mut hi, mut flo, mut fhi) = (ta, tb, a, b);
                    let mut side = 0i8;
                    for _ in 0..3 {
                        let t = (lo * fhi - hi * flo) / (fhi - flo);
                        match f(t) {
                            Some(m) if m > 0.0 => {
                                lo = t;
                                flo = m;
                                if side == 1 {
                                    fhi *= 0.5;
                                }
                                side = 1;
                            }
                            Some(m) => {
                                hi = t;
                                fhi = m;
                                if side == -1 {
                                    flo *= 0.5;
                                }
                                side = -1;
                            }
                            None => hi = t,
                        }
                    }
                    let t = if fhi < flo {
                        (lo * fhi - hi * flo) / (fhi - flo)
                    } else {
                        hi
                    };
                    let p = origin + dir * t.max(lo.min(hi)).min(hi.max(lo));
                    let (i, j) = self.sample.texel_of(p.x, p.y);
                    return Some((p, i, j, self.normal(g, p.x, p.y)));
                }
            } else if let (Some(a), None) = (fa, fb) {
                // leaving the sample area above the surface: no hit on the sample
                if a > 0.0 {
                    return None;
                }
            }
            ta = tb;
            fa = fb;
        }
        None
    }

    /// Bilinear height (mm) at a sample-frame point.
    #[inline(always)]
    fn height(&self, g: &HeightGrid, x: f64, y: f64) -> f64 {
        let (i0, j0, fx, fy) = grid_coords(g, self.half(), x, y);
        let n = g.n;
        let h = |i: usize, j: usize| g.heights[j * n + i] as f64;
        let (i1, j1) = ((i0 + 1).min(n - 1), (j0 + 1).min(n - 1));
        let top = h(i0, j0) + (h(i1, j0) - h(i0, j0)) * fx;
        let bot = h(i0, j1) + (h(i1, j1) - h(i0, j1)) * fx;
        top + (bot - top) * fy
    }

    /// Bilinear normal at a sample-frame point.
    #[inline]
    fn normal(&self, g: &HeightGrid, x: f64, y: f64) -> Vec3 {
        let (i0, j0, fx, fy) = grid_coords(g, self.half(), x, y);
        let n = g.n;
        let (i1, j1) = ((i0 + 1).min(n - 1), (j0 + 1).min(n - 1));
        let v = |i: usize, j: usize| {
            let a = g.normals[j * n + i];
            Vec3::new(a[0] as f64, a[1] as f64, a[2] as f64)
        };
        let top = v(i0, j0) * (1.0 - fx) + v(i1, j0) * fx;
        let bot = v(i0, j1) * (1.0 - fx) + v(i1, j1) * fx;
        (top * (1.0 - fy) + bot * fy).normalized()
    }

    /// The shadow map for a light position, built on first use.
    fn shadow_map(&self, g: &HeightGrid, light: Vec3) -> Arc<ShadowMap> {
        let key = [
            (light.x * 1e4).round() as i64,
            (light.y * 1e4).round() as i64,
            (light.z * 1e4).round() as i64,
        ];
        if let Some(m) = self.shadows.lock().expect("shadow cache poisoned").get(&key) {
            return m.clone();
        }
        let map = Arc::new(self.build_shadow_map(g, light));
        let mut cache = self.shadows.lock().expect("shadow cache poisoned");
        // Bounded by count and by bytes (disc lamps need one map per emitter and light).
        let bytes_each = map.lit.len().max(1);
        if cache.len() >= SHADOW_CACHE || (cache.len() + 1) * bytes_each > SHADOW_CACHE_BYTES {
            cache.clear();
        }
        cache.insert(key, map.clone());
        map
    }

    /// March from every shadow texel toward the lamp; lit if no height rises above the ray.
    ///
    /// The lamp is a point, so the direction is taken per texel from the texel to the lamp
    /// (exact for the finite distance, not a directional approximation).
    fn build_shadow_map(&self, g: &HeightGrid, light: Vec3) -> ShadowMap {
        let n = g.n * self.quality.shadow_scale.max(1);
        let half = self.half();
        let cell = 2.0 * half / n as f64;
        let mut lit = vec![1u8; n * n];
        lit.par_chunks_mut(n).enumerate().for_each(|(j, row)| {
            for (i, out) in row.iter_mut().enumerate() {
                let x = (i as f64 + 0.5) * cell - half;
                let y = half - (j as f64 + 0.5) * cell;
                if let Some(normal) = g.plane {
                    // A plane shadows nothing of itself: lit where the lamp is on its front.
                    let p = Vec3::new(x, y, self.height(g, x, y));
                    *out = u8::from(normal.dot(light - p) > 0.0);
                    continue;
                }
                let z = self.height(g, x, y) + 1e-4;
                let d = (light - Vec3::new(x, y, z)).normalized();
                if d.z <= 0.0 {
                    *out = 0;
                    continue;
                }
                let horiz = (d.x * d.x + d.y * d.y).sqrt();
                if horiz < 1e-9 {
                    continue;
                }
                // Walk until the ray is above the highest point of the field.
                let rise = (g.max - z).max(0.0);
                let t_max = rise / d.z;
                let step = 0.5 * g.texel / horiz;
                let mut t = step;
                while t <= t_max {
                    let p = Vec3::new(x, y, z) + d * t;
                    if p.x.abs() > half || p.y.abs() > half {
                        break;
                    }
                    if self.height(g, p.x, p.y) > p.z {
                        *out = 0;
                        break;
                    }
                    t += step;
                }
            }
        });
        ShadowMap { n, lit }
    }

    /// [`Self::shade`] summed over a lamp's emitters.
    #[inline]
    fn shade_all(&self, hit: &Hit, dir: Vec3, lamp: &[Emitter]) -> [f64; 3] {
        if let [(light, shadow)] = lamp {
            return self.shade(hit, dir, light, shadow.as_deref());
        }
        let mut acc = [0.0; 3];
        for (light, shadow) in lamp {
            let r = self.shade(hit, dir, light, shadow.as_deref());
            acc[0] += r[0];
            acc[1] += r[1];
            acc[2] += r[2];
        }
        acc
    }

    /// The emitters a lamp is rendered with, each with its shadow map: the lamp itself if
    /// it is a point, else `area_samples` points on its disc (see [`PointLight`]).
    fn emitters(&self, light: &PointLight) -> Vec<Emitter> {
        let k = self.quality.area_samples.max(1);
        if light.radius <= 0.0 || k == 1 {
            let p = PointLight::point(light.position, light.intensity);
            return vec![(p, self.shadow_for(&p))];
        }
        // The disc faces the sample centre: two unit vectors spanning its plane.
        let n = (Vec3::ZERO - light.position).normalized();
        let helper = if n.z.abs() < 0.9 {
            Vec3::Z
        } else {
            Vec3::new(1.0, 0.0, 0.0)
        };
        let u = helper.cross(n).normalized();
        let v = n.cross(u);
        const GOLDEN_ANGLE: f64 = 2.399_963_229_728_653;
        (0..k)
            .map(|i| {
                let r = light.radius * ((i as f64 + 0.5) / k as f64).sqrt();
                let a = i as f64 * GOLDEN_ANGLE;
                let p = PointLight::point(
                    light.position + u * (r * a.cos()) + v * (r * a.sin()),
                    light.intensity / k as f64,
                );
                (p, self.shadow_for(&p))
            })
            .collect()
    }

    /// Radiance leaving the surface point `hit` (found along unit `dir`) toward the ray's
    /// origin: the light-dependent half of tracing and shading, so a view's hits can
    /// be traced once and shaded for every light ([`TruthView`]).
    #[inline]
    fn shade(&self, hit: &Hit, dir: Vec3, light: &PointLight, shadow: Option<&ShadowMap>) -> [f64; 3] {
        match *hit {
            Hit::Background => [0.0; 3],
            Hit::Frame { p, albedo } => {
                let to_l = light.position - p;
                let r2 = to_l.dot(to_l);
                let cos_l = to_l.z / r2.sqrt();
                if cos_l <= 0.0 {
                    return [0.0; 3];
                }
                let e = light.intensity * cos_l / (r2 * 1e-6);
                let v = albedo * std::f64::consts::FRAC_1_PI * e;
                [v, v, v]
            }
            Hit::Sample { p, i, j, normal } => {
                let to_l = light.position - p;
                let r2 = to_l.dot(to_l);
                let l = to_l * (1.0 / r2.sqrt());
                let v = -dir;
                let cos_l = normal.dot(l);
                if cos_l <= 0.0 || normal.dot(v) <= 0.0 {
                    return [0.0; 3];
                }
                if let Some(s) = shadow {
                    let half = self.half();
                    let si = ((((p.x + half) / (2.0 * half)) * s.n as f64) as usize).min(s.n - 1);
                    let sj = ((((half - p.y) / (2.0 * half)) * s.n as f64) as usize).min(s.n - 1);
                    if s.lit[sj * s.n + si] == 0 {
                        return [0.0; 3];
                    }
                }
                // Local shading frame: normal, tangent along texture u (+x) projected.
                let (l_loc, v_loc) = if normal.z > 1.0 - 1e-12 {
                    (l, v)
                } else {
                    let t = (Vec3::new(1.0, 0.0, 0.0) - normal * normal.x).normalized();
                    let b = normal.cross(t);
                    (
                        Vec3::new(l.dot(t), l.dot(b), cos_l),
                        Vec3::new(v.dot(t), v.dot(b), normal.dot(v)),
                    )
                };
                let (model, tint) = self.sample.material(i, j);
                let f = model.eval(l_loc, v_loc);
                let e = light.intensity * cos_l / (r2 * 1e-6);
                [f[0] * tint[0] * e, f[1] * tint[1] * e, f[2] * tint[2] * e]
            }
        }
    }

    fn shadow_for(&self, light: &PointLight) -> Option<Arc<ShadowMap>> {
        match &self.sample.surface {
            Surface::Height(g) => Some(self.shadow_map(g, light.position)),
            Surface::Flat => None,
        }
    }

    /// Radiance image of a raw frame seen by a pinhole camera (no sensor effects).
    pub fn render_raw(
        &self,
        intr: &Intrinsics,
        pose: &CameraPose,
        width: usize,
        height: usize,
        light: &PointLight,
    ) -> RgbImage {
        self.render_raw_distorted(intr, &LensDistortion::default(), pose, width, height, light)
    }

    /// [`render_raw`](Self::render_raw) through a lens with OpenCV radial-tangential
    /// distortion: each pixel sample's ray is found by undistorting its pixel position, so
    /// the image is exactly what `cv2.projectPoints` with these coefficients predicts.
    /// Zero distortion costs nothing extra.
    pub fn render_raw_distorted(
        &self,
        intr: &Intrinsics,
        lens: &LensDistortion,
        pose: &CameraPose,
        width: usize,
        height: usize,
        light: &PointLight,
    ) -> RgbImage {
        self.shade_raw(&self.raw_view(intr, lens, pose, width, height), light)
    }

    /// Trace every ray of a raw frame once: the light-independent half of
    /// [`Self::render_raw_distorted`] (which pixels are traced, how many samples each takes,
    /// and what each sample's ray hits depend on the camera only).
    pub fn raw_view(
        &self,
        intr: &Intrinsics,
        lens: &LensDistortion,
        pose: &CameraPose,
        width: usize,
        height: usize,
    ) -> RawView {
        let (x0, y0, x1, y1) = if lens.is_zero() {
            self.pixel_bounds(intr, pose, width, height)
        } else {
            // The pinhole bounds do not hold through a distorting lens: trace everything.
            (0, 0, width, height)
        };
        let mut view = RawView {
            width,
            height,
            x0,
            y0,
            rows: Vec::new(),
        };
        if x0 >= x1 || y0 >= y1 {
            return view;
        }
        let ss = self.quality.supersample.max(1);
        view.rows = (y0..y1)
            .into_par_iter()
            .map(|row| {
                let mut traced = RawRow {
                    samples: Vec::with_capacity(x1 - x0),
                    rays: Vec::with_capacity(x1 - x0),
                };
                for col in x0..x1 {
                    let ray = |u: f64, v: f64| {
                        let (x, y) = lens.undistort((u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy);
                        (pose.right * x + pose.down * y + pose.forward).normalized()
                    };
                    // Pixels off the sample (holder frame, markers, background) are cheap and
                    // hold the sharp marker edges the rectifier measures: integrate them over
                    // the pixel area with a 4×4 sheared grid. Sample pixels use `supersample`.
                    let centre = ray(col as f64 + 0.5, row as f64 + 0.5);
                    let on_sample = self.hits_sample_area(pose.position, centre);
                    let n = if on_sample {
                        ss
                    } else {
                        // Only pixels on an edge (corners differ in what they see) need the
                        // area integral; flat frame or background pixels take one sample.
                        let c0 = self.frame_class(pose.position, ray(col as f64, row as f64));
                        let uniform = [(1.0, 0.0), (0.0, 1.0), (1.0, 1.0)].iter().all(|&(dx, dy)| {
                            self.frame_class(pose.position, ray(col as f64 + dx, row as f64 + dy)) == c0
                        });
                        if uniform {
                            1
                        } else {
                            FRAME_SS
                        }
                    };
                    traced.samples.push(n as u32);
                    for k in 0..n * n {
                        let (sx, sy) = (k % n, k / n);
                        // sheared grid: distinct offsets along both axes (no aligned rows)
                        let u = col as f64 + (sx as f64 + (sy as f64 + 0.5) / n as f64) / n as f64;
                        let v = row as f64 + (sy as f64 + (sx as f64 + 0.5) / n as f64) / n as f64;
                        let d = if n == 1 { centre } else { ray(u, v) };
                        traced.rays.push((self.trace(pose.position, d), d));
                    }
                }
                traced
            })
            .collect();
        view
    }

    /// Shade a traced raw frame for one light: the light-dependent half of
    /// [`Self::render_raw_distorted`]; pixels outside the traced rectangle stay black.
    pub fn shade_raw(&self, view: &RawView, light: &PointLight) -> RgbImage {
        let width = view.width;
        let mut img = RgbImage::new(width, view.height);
        let lamp = self.emitters(light);
        if view.rows.is_empty() {
            return img;
        }
        let (x0, y0) = (view.x0, view.y0);
        img.data
            .par_chunks_mut(width * 3)
            .skip(y0)
            .zip(view.rows.par_iter())
            .for_each(|(out, traced)| {
                let mut rays = traced.rays.iter();
                for (c, &n) in traced.samples.iter().enumerate() {
                    let col = x0 + c;
                    let n = n as usize;
                    let mut acc = [0.0; 3];
                    for (hit, d) in rays.by_ref().take(n * n) {
                        let r = self.shade_all(hit, *d, &lamp);
                        acc[0] += r[0];
                        acc[1] += r[1];
                        acc[2] += r[2];
                    }
                    let w = 1.0 / (n * n) as f64;
                    for c in 0..3 {
                        out[col * 3 + c] = (acc[c] * w) as f32;
                    }
                }
            });
        img
    }

    /// What a ray sees on the mean plane, coarsely: 0 background, 1 frame, 2 marker,
    /// 3 sample area. Used to find pixels that straddle an edge.
    fn frame_class(&self, origin: Vec3, dir: Vec3) -> u8 {
        if dir.z >= 0.0 {
            return 0;
        }
        if self.hits_sample_area(origin, dir) {
            return 3;
        }
        let p = origin + dir * (-origin.z / dir.z);
        let spec = &self.sample.spec;
        let outer = spec.border.outer_half(spec.size_mm);
        if p.x.abs() > outer || p.y.abs() > outer {
            0
        } else if spec.border.is_marker(spec.size_mm, p.x, p.y) {
            2
        } else {
            1
        }
    }

    /// Whether a ray meets the mean plane inside the sample square (grown by the relief's
    /// parallax margin), i.e. whether it may see the sample rather than the holder.
    fn hits_sample_area(&self, origin: Vec3, dir: Vec3) -> bool {
        if dir.z >= 0.0 {
            return false;
        }
        let t = -origin.z / dir.z;
        let p = origin + dir * t;
        let margin = match &self.sample.surface {
            Surface::Height(g) => {
                let h = g.max.abs().max(g.min.abs());
                h * (dir.x * dir.x + dir.y * dir.y).sqrt() / -dir.z + g.texel
            }
            Surface::Flat => 0.0,
        };
        let half = self.half() + margin;
        p.x.abs() <= half && p.y.abs() <= half
    }

    /// Pixel rectangle [x0, x1) × [y0, y1) that can see the holder (its corners at the
    /// lowest and highest surface heights, projected, plus a margin).
    pub fn pixel_bounds(
        &self,
        intr: &Intrinsics,
        pose: &CameraPose,
        width: usize,
        height: usize,
    ) -> (usize, usize, usize, usize) {
        let outer = self.sample.spec.border.outer_half(self.sample.spec.size_mm);
        let (zmin, zmax) = match &self.sample.surface {
            Surface::Height(g) => (g.min.min(0.0), g.max.max(0.0)),
            Surface::Flat => (0.0, 0.0),
        };
        let (mut a, mut b, mut c, mut d) = (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
        for &x in &[-outer, outer] {
            for &y in &[-outer, outer] {
                for &z in &[zmin, zmax] {
                    let pc = pose.to_camera(Vec3::new(x, y, z));
                    if pc.z <= 1e-9 {
                        return (0, 0, width, height);
                    }
                    let (u, v) = intr.project(pc.x, pc.y, pc.z);
                    a = a.min(u);
                    b = b.min(v);
                    c = c.max(u);
                    d = d.max(v);
                }
            }
        }
        let clamp = |v: f64, hi: usize| v.clamp(0.0, hi as f64) as usize;
        (
            clamp(a - 2.0, width),
            clamp(b - 2.0, height),
            clamp(c + 3.0, width),
            clamp(d + 3.0, height),
        )
    }

    /// The exact rectified image in texture space: texel (i, j) shows what the camera at
    /// `camera` sees through the point of the mean plane at the texel centre (conventions:
    /// column grows with +x, row with −y), averaged over the texel area with
    /// `truth_supersample²` rays. Radiance, no sensor effects.
    ///
    /// Equal to `shade_truth(&truth_view(camera, width, height), light)`; call those two
    /// directly to render many lights for one view (the ray march is then done once).
    pub fn render_truth(&self, camera: Vec3, width: usize, height: usize, light: &PointLight) -> RgbImage {
        self.shade_truth(&self.truth_view(camera, width, height), light)
    }

    /// Truth samples per texel and axis for a `width × height` truth image: at least one
    /// sample per grid texel of the sample, so coarse outputs still see every detail of
    /// the structure they average over, times the sample's `truth_rays_per_cell` (a sharp
    /// lobe varies within a grid cell); at most 16.
    pub fn truth_samples(&self, width: usize, height: usize) -> usize {
        let grid = self.sample.spec.resolution.div_ceil(width.min(height).max(1));
        let per_cell = self.sample.spec.truth_rays_per_cell.max(1);
        self.quality.truth_supersample.max(grid * per_cell).clamp(1, 16)
    }

    /// Bytes [`Self::truth_view`] holds for a `width × height` view.
    pub fn truth_view_bytes(&self, width: usize, height: usize) -> usize {
        let n = self.truth_samples(width, height);
        width * height * n * n * std::mem::size_of::<(Hit, Vec3)>()
    }

    /// Trace every truth ray of a view once: the light-independent half of
    /// [`Self::render_truth`] (parallax and masking depend on the camera only).
    pub fn truth_view(&self, camera: Vec3, width: usize, height: usize) -> TruthView {
        let s = self.sample.spec.size_mm;
        let n = self.truth_samples(width, height);
        let per_row = width * n * n;
        let mut rays = vec![(Hit::Background, Vec3::Z); per_row * height];
        rays.par_chunks_mut(per_row.max(1)).enumerate().for_each(|(j, row)| {
            for i in 0..width {
                for k in 0..n * n {
                    // sheared grid over the texel (distinct offsets on both axes)
                    let (a, b) = (k % n, k / n);
                    let fx = (a as f64 + (b as f64 + 0.5) / n as f64) / n as f64;
                    let fy = (b as f64 + (a as f64 + 0.5) / n as f64) / n as f64;
                    let x = (i as f64 + fx) / width as f64 * s - s / 2.0;
                    let y = s / 2.0 - (j as f64 + fy) / height as f64 * s;
                    let d = (Vec3::new(x, y, 0.0) - camera).normalized();
                    row[i * n * n + k] = (self.trace(camera, d), d);
                }
            }
        });
        TruthView {
            width,
            height,
            samples: n,
            camera,
            rays,
        }
    }

    /// Shade a traced view for one light: the light-dependent half of [`Self::render_truth`].
    pub fn shade_truth(&self, view: &TruthView, light: &PointLight) -> RgbImage {
        let (width, n) = (view.width, view.samples);
        let mut img = RgbImage::new(width, view.height);
        let lamp = self.emitters(light);
        let w = 1.0 / (n * n) as f64;
        let per_row = width * n * n;
        img.data.par_chunks_mut(width * 3).enumerate().for_each(|(j, out)| {
            let row = &view.rays[j * per_row..(j + 1) * per_row];
            for i in 0..width {
                let mut acc = [0.0; 3];
                for (hit, d) in &row[i * n * n..(i + 1) * n * n] {
                    let r = self.shade_all(hit, *d, &lamp);
                    acc[0] += r[0];
                    acc[1] += r[1];
                    acc[2] += r[2];
                }
                out[i * 3] = (acc[0] * w) as f32;
                out[i * 3 + 1] = (acc[1] * w) as f32;
                out[i * 3 + 2] = (acc[2] * w) as f32;
            }
        });
        img
    }
}

/// The traced truth rays of one view ([`Renderer::truth_view`]): what the camera sees
/// through each sample point of each texel. Shading it for a light
/// ([`Renderer::shade_truth`]) costs a shadow-map look-up and a BRDF evaluation per ray,
/// no marching; a full BTF traces 81 views once each instead of 6561 times.
/// About 80 bytes per ray (5 MiB for a 256² view with one ray per texel).
pub struct TruthView {
    pub width: usize,
    pub height: usize,
    /// Rays per texel and axis.
    pub samples: usize,
    /// Where the camera was (mm, sample frame).
    pub camera: Vec3,
    rays: Vec<(Hit, Vec3)>,
}

impl TruthView {
    /// Bytes this view holds.
    pub fn bytes(&self) -> usize {
        self.rays.capacity() * std::mem::size_of::<(Hit, Vec3)>()
    }
}

/// The traced rays of one raw frame ([`Renderer::raw_view`]): which pixels are traced,
/// with how many samples, and what each sample's ray hits. Shading it for a light
/// ([`Renderer::shade_raw`]) gives exactly [`Renderer::render_raw_distorted`]'s image.
/// About 100 bytes per ray.
pub struct RawView {
    pub width: usize,
    pub height: usize,
    /// Top-left pixel of the traced rectangle.
    x0: usize,
    y0: usize,
    /// One entry per traced row, from `y0` down.
    rows: Vec<RawRow>,
}

/// The traced pixels of one row: samples per axis of each pixel, then all rays in order.
struct RawRow {
    samples: Vec<u32>,
    rays: Vec<(Hit, Vec3)>,
}

impl RawView {
    /// Rays traced (each is shaded once per light).
    pub fn rays(&self) -> usize {
        self.rows.iter().map(|r| r.rays.len()).sum()
    }

    /// Bytes this view holds (its rays and per-pixel sample counts).
    pub fn bytes(&self) -> usize {
        self.rows
            .iter()
            .map(|r| r.rays.capacity() * std::mem::size_of::<(Hit, Vec3)>() + r.samples.capacity() * 4)
            .sum()
    }
}

/// A cached view: its key, the view, its size in bytes.
type CacheEntry<V> = (Vec<u64>, Arc<V>, usize);

/// Traced views kept for reuse ([`TruthView`], [`RawView`]), so that the many pairs an
/// acquisition measures from one camera pose are traced once and shaded per light, even
/// though it visits them in a tour order rather than view by view.
///
/// The key is the exact bits of everything the trace depends on (camera pose, image size,
/// lens): a hit is the very view a fresh trace would give, so shading it gives the same
/// bytes as tracing again. At most `capacity` views are kept, least recently used first
/// out, so memory is bounded however long the sweep; with a byte budget
/// ([`ViewCache::with_budget`]) also at most that many bytes (but always the newest view),
/// so samples whose truth needs many rays per texel do not hold `capacity` large views.
pub struct ViewCache<V> {
    capacity: usize,
    budget_bytes: usize,
    /// Most recently used last, each with its size in bytes.
    entries: Mutex<Vec<CacheEntry<V>>>,
    hits: std::sync::atomic::AtomicU64,
    misses: std::sync::atomic::AtomicU64,
}

impl<V> ViewCache<V> {
    /// A cache of at most `capacity` views (0: nothing is kept, every call traces).
    pub fn new(capacity: usize) -> Self {
        Self::with_budget(capacity, usize::MAX)
    }

    /// A cache of at most `capacity` views and `budget_bytes` bytes (as given to
    /// [`ViewCache::get_sized`]), keeping at least the newest view.
    pub fn with_budget(capacity: usize, budget_bytes: usize) -> Self {
        ViewCache {
            capacity,
            budget_bytes,
            entries: Mutex::new(Vec::new()),
            hits: Default::default(),
            misses: Default::default(),
        }
    }

    /// The view under `key`, from the cache or made now by `trace`.
    pub fn get(&self, key: Vec<u64>, trace: impl FnOnce() -> V) -> Arc<V> {
        self.get_sized(key, 0, trace)
    }

    /// [`ViewCache::get`] for a view of `bytes` bytes (counted against the budget).
    pub fn get_sized(&self, key: Vec<u64>, bytes: usize, trace: impl FnOnce() -> V) -> Arc<V> {
        use std::sync::atomic::Ordering::Relaxed;
        let over = |entries: &[CacheEntry<V>]| {
            !entries.is_empty()
                && (entries.len() >= self.capacity
                    || entries.iter().map(|e| e.2).sum::<usize>().saturating_add(bytes) > self.budget_bytes)
        };
        {
            let mut entries = self.entries.lock().expect("view cache poisoned");
            if let Some(k) = entries.iter().position(|(e, _, _)| *e == key) {
                let entry = entries.remove(k);
                let view = entry.1.clone();
                entries.push(entry);
                self.hits.fetch_add(1, Relaxed);
                return view;
            }
        }
        self.misses.fetch_add(1, Relaxed);
        // A full cache lets go of its least recently used view before the new one is traced,
        // so at most `capacity` views are alive at once and the allocator reuses the freed
        // memory: the process's footprint is flat once the cache is full.
        {
            let mut entries = self.entries.lock().expect("view cache poisoned");
            while over(&entries) {
                entries.remove(0);
            }
        }
        // Traced outside the lock; a concurrent miss on the same key traces the same bytes
        // and the cache keeps one copy.
        let view = Arc::new(trace());
        if self.capacity > 0 {
            let mut entries = self.entries.lock().expect("view cache poisoned");
            if !entries.iter().any(|(e, _, _)| *e == key) {
                while over(&entries) {
                    entries.remove(0);
                }
                entries.push((key, view.clone(), bytes));
            }
        }
        view
    }

    /// Views held now (at most the capacity).
    pub fn len(&self) -> usize {
        self.entries.lock().map(|e| e.len()).unwrap_or(0)
    }

    /// Whether no view is held.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Calls answered from the cache and calls that traced, so far.
    pub fn stats(&self) -> (u64, u64) {
        use std::sync::atomic::Ordering::Relaxed;
        (self.hits.load(Relaxed), self.misses.load(Relaxed))
    }
}

/// The bits of `values`, a [`ViewCache`] key.
pub fn key_bits(values: &[f64]) -> Vec<u64> {
    values.iter().map(|v| v.to_bits()).collect()
}

/// Grid cell and fractions for bilinear interpolation at (x, y).
#[inline]
fn grid_coords(g: &HeightGrid, half: f64, x: f64, y: f64) -> (usize, usize, f64, f64) {
    let n = g.n;
    let inv = 1.0 / g.texel; // constant per grid: the compiler hoists it out of the loops
    let gx = ((x + half) * inv - 0.5).clamp(0.0, (n - 1) as f64);
    let gy = ((half - y) * inv - 0.5).clamp(0.0, (n - 1) as f64);
    // gx, gy ≥ 0 here, so truncation is floor (and avoids a libm call per lookup).
    let (i0, j0) = (gx as usize, gy as usize);
    (i0.min(n - 1), j0.min(n - 1), gx - i0 as f64, gy - j0 as f64)
}

#[cfg(test)]
mod lens_tests {
    use super::LensDistortion;

    #[test]
    fn undistort_inverts_distort_and_zero_is_identity() {
        let lens = LensDistortion([-0.12, 0.09, 0.0006, -0.0004, 0.0]);
        for &(x, y) in &[(0.0, 0.0), (0.2, -0.1), (-0.33, 0.27)] {
            let (xd, yd) = lens.distort(x, y);
            let (xu, yu) = lens.undistort(xd, yd);
            assert!((xu - x).abs() < 1e-12 && (yu - y).abs() < 1e-12, "({x}, {y})");
        }
        // barrel distortion pulls points toward the centre
        assert!(lens.distort(0.3, 0.0).0 < 0.3);
        let zero = LensDistortion::default();
        assert!(zero.is_zero());
        assert_eq!(zero.undistort(0.3, -0.2), (0.3, -0.2));
    }
}

#[cfg(test)]
mod view_cache_tests {
    use super::ViewCache;

    /// A byte budget keeps the cache under it (but always the newest view); without one,
    /// only the count limits it. A hit never traces.
    #[test]
    fn a_byte_budget_bounds_the_cache_and_keeps_the_newest_view() {
        let cache = ViewCache::with_budget(8, 100);
        for k in 0..4u64 {
            cache.get_sized(vec![k], 40, || k);
        }
        assert_eq!(cache.len(), 2, "two 40-byte views fit in 100 bytes");
        assert_eq!(*cache.get_sized(vec![3], 40, || unreachable!()), 3);
        assert_eq!(*cache.get_sized(vec![9], 500, || 9), 9);
        assert_eq!(cache.len(), 1, "a view above the budget is kept alone");
        let count_only = ViewCache::new(3);
        for k in 0..5u64 {
            count_only.get_sized(vec![k], 1 << 40, || k);
        }
        assert_eq!(count_only.len(), 3);
        assert_eq!(count_only.stats(), (0, 5));
    }
}

#[cfg(test)]
mod truth_sampling_tests {
    use super::{RenderQuality, Renderer};
    use crate::SampleSpec;
    use std::sync::Arc;

    fn samples(name: &str, per_cell: Option<usize>, size: usize) -> usize {
        let mut spec = SampleSpec::resolve(name).unwrap();
        if let Some(k) = per_cell {
            spec.truth_rays_per_cell = k;
        }
        let r = Renderer::new(Arc::new(spec.build().unwrap()), RenderQuality::default());
        r.truth_samples(size, size)
    }

    /// One ray per grid cell by default; a sample's `truth_rays_per_cell` multiplies it,
    /// up to 16 per texel and axis.
    #[test]
    fn truth_rays_per_cell_multiplies_the_rays_per_texel() {
        assert_eq!(samples("wallpaper", None, 64), 4);
        assert_eq!(samples("wallpaper", None, 256), 1);
        assert_eq!(samples("wallpaper", Some(2), 64), 8);
        assert_eq!(samples("brushed-metal", None, 256), 4);
        assert_eq!(samples("brushed-metal", None, 64), 16);
        assert_eq!(samples("brushed-metal", None, 32), 16, "clamped");
    }

    #[test]
    fn truth_rays_per_cell_out_of_range_is_refused_by_name() {
        let text =
            include_str!("../samples/brushed-metal.toml").replace("truth_rays_per_cell = 4", "truth_rays_per_cell = 0");
        let e = SampleSpec::parse(&text, "bm.toml", None).unwrap_err().to_string();
        assert!(e.contains("truth_rays_per_cell") && e.contains("1 ..= 16"), "{e}");
    }
}

#[cfg(test)]
mod disc_lamp_tests {
    use super::{PointLight, RenderQuality, Renderer};
    use crate::SampleSpec;
    use gonio_devices::Vec3;
    use std::sync::Arc;

    fn renderer(sample: &str, area_samples: usize) -> Renderer {
        let s = Arc::new(SampleSpec::resolve(sample).unwrap().build().unwrap());
        Renderer::new(
            s,
            RenderQuality {
                area_samples,
                ..Default::default()
            },
        )
    }

    fn mean(img: &gonio_devices::image::RgbImage) -> f64 {
        img.data.iter().map(|&v| v as f64).sum::<f64>() / img.data.len() as f64
    }

    /// A small disc far away is a point: same total intensity, positions within r ≪ d.
    #[test]
    fn a_small_disc_on_a_flat_sample_matches_the_point_lamp() {
        let r = renderer("white-standard", 16);
        let cam = Vec3::new(0.0, 0.0, 1000.0);
        let pos = Vec3::new(600.0, 0.0, 1039.2);
        let point = r.render_truth(cam, 32, 32, &PointLight::point(pos, 50.0));
        let disc = r.render_truth(
            cam,
            32,
            32,
            &PointLight {
                position: pos,
                intensity: 50.0,
                radius: 10.0,
            },
        );
        let rel = (mean(&disc) / mean(&point) - 1.0).abs();
        // (r/d)² ≈ 7e-5: the disc's emitters are slightly farther than its centre.
        assert!(rel < 2e-4, "relative difference {rel}");
        assert_eq!(r.shadow_maps_built(), 0, "a flat sample builds no shadow maps");
    }

    /// On a relief at a grazing light, a disc softens shadows: the hard point-lamp shadow
    /// mask (0 or lit) becomes partial, and one emitter equals the point lamp exactly.
    #[test]
    fn a_disc_lamp_softens_shadows_and_one_emitter_is_the_point() {
        let cam = Vec3::new(0.0, 0.0, 1000.0);
        let pos = Vec3::new(1150.0, 0.0, 310.0); // θ ≈ 75°
        let lamp = PointLight {
            position: pos,
            intensity: 50.0,
            radius: 150.0,
        };
        let point = renderer("corduroy", 1).render_truth(cam, 64, 64, &PointLight::point(pos, 50.0));
        let one = renderer("corduroy", 1).render_truth(cam, 64, 64, &lamp);
        assert_eq!(one.data, point.data);
        let r16 = renderer("corduroy", 16);
        let soft = r16.render_truth(cam, 64, 64, &lamp);
        assert!(r16.shadow_maps_built() == 16, "one shadow map per emitter");
        let dark = |img: &gonio_devices::image::RgbImage| img.data.iter().filter(|&&v| v == 0.0).count();
        assert!(dark(&point) > 0, "the point lamp casts hard shadows here");
        assert!(
            dark(&soft) < dark(&point),
            "penumbrae replace part of the umbra: {} vs {}",
            dark(&soft),
            dark(&point)
        );
        let rel = (mean(&soft) / mean(&point) - 1.0).abs();
        assert!(rel < 0.2, "same lamp power, similar mean: {rel}");
    }
}

#[cfg(test)]
mod plane_tests {
    use super::{Hit, PointLight, RenderQuality, Renderer};
    use crate::sample::{plane_normal, Surface};
    use crate::SampleSpec;
    use gonio_devices::Vec3;
    use std::sync::Arc;

    /// A steep plane (a target on a wedge) is rendered exactly: every ray that meets it
    /// hits the plane itself (to 1e-6 mm; a bilinear grid reproduces a plane and the march
    /// brackets its single crossing), with the analytic normal, and a lamp on its lit side
    /// casts no shadow on it.
    #[test]
    fn a_tilted_plane_is_hit_exactly_and_not_self_shadowed() {
        for analytic in [true, false] {
            plane_is_exact(analytic);
        }
    }

    /// `analytic` false: the general height-field march and shadow walk on the plane's grid.
    fn plane_is_exact(analytic: bool) {
        let mut s = SampleSpec::resolve("calibration-target-wedge")
            .unwrap()
            .build()
            .unwrap();
        if let Surface::Height(g) = &mut s.surface {
            assert!(g.plane.is_some());
            if !analytic {
                g.plane = None;
            }
        }
        let r = Renderer::new(Arc::new(s), RenderQuality::default());
        let normal = plane_normal(20.0, 0.0);
        let tan = 20f64.to_radians().tan();
        for (theta, phi) in [
            (0.0f64, 0.0f64),
            (45.0, 0.0),
            (60.0, 90.0),
            (60.0, 180.0),
            (70.0, 300.0),
        ] {
            let (t, p) = (theta.to_radians(), phi.to_radians());
            let cam = Vec3::new(t.sin() * p.cos(), t.sin() * p.sin(), t.cos()) * 1000.0;
            for (x, y) in [(0.0, 0.0), (-22.5, 17.5), (24.0, -24.0), (10.0, 3.0)] {
                let target = Vec3::new(x, y, -tan * x);
                let dir = (target - cam).normalized();
                match r.trace(cam, dir) {
                    Hit::Sample { p, normal: n, .. } => {
                        let d = p - target;
                        assert!(
                            d.dot(d).sqrt() < 1e-6,
                            "θ {theta} φ {phi} ({x}, {y}), analytic {analytic}: hit {p:?}"
                        );
                        let dn = n - normal;
                        assert!(dn.dot(dn).sqrt() < 1e-6, "{n:?}");
                    }
                    h => panic!("θ {theta} φ {phi} ({x}, {y}): {h:?}"),
                }
            }
        }
        // lamp at θ = 35° on either side of the slope: lit everywhere the plane is
        for phi in [0.0f64, 90.0, 180.0, 270.0] {
            let (t, p) = (35f64.to_radians(), phi.to_radians());
            let lamp = Vec3::new(t.sin() * p.cos(), t.sin() * p.sin(), t.cos()) * 1200.0;
            let img = r.render_truth(Vec3::new(0.0, 0.0, 1000.0), 48, 48, &PointLight::point(lamp, 50.0));
            let dark = img.data.iter().filter(|&&v| v <= 0.0).count();
            assert_eq!(dark, 0, "lamp φ {phi}, analytic {analytic}: {dark} unlit values");
        }
    }
}
