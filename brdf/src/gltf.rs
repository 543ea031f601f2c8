//! glTF 2.0's metallic-roughness material, the one home of its formula: the per-texel fit
//! (`gonio fit --per-texel --model gltf`), the `.gbtf` decoder that `gonio reconstruct`,
//! `render` and `view` use, and the exports (glTF, MaterialX, USD, Mitsuba) all evaluate
//! this function, so what is fitted is what is decoded and what is written.
//!
//! In the local frame of the shading normal:
//!
//! `f = (1 − m)·c/π + F(v·h) · D(h) · G1(l) G1(v) / (4 (n·l)(n·v))`
//!
//! - `c` the base colour (linear RGB), `m` metallic, `α = roughness²` (clamped to
//!   [`crate::MIN_ROUGHNESS`]);
//! - `D` GGX (Trowbridge–Reitz), `G1` Smith's for GGX, separable (the glTF 2.0
//!   specification's Appendix B, and Mitsuba 3's `roughconductor` and `principled`);
//! - `F` Schlick with `F0 = mix(0.04, c, m)`: `F = F0 + (1 − F0)(1 − v·h)⁵`;
//! - the diffuse term carries no `(1 − F)` factor: it is the sum of a Lambertian base and a
//!   specular lobe, which is what the composed Mitsuba scene of `gonio export --format
//!   mitsuba` evaluates term by term (see docs/guide/export.md).
//!
//! **Anisotropy** (`KHR_materials_anisotropy`). A strength `s ∈ [0, 1]` and a direction at
//! angle `φ` counter-clockwise from the tangent (+x = u) towards the bitangent (+y = v)
//! widen the lobe along that direction: `α_t = mix(α, 1, s²)` along it, `α_b = α` across
//! it (anisotropic GGX, Smith's G separable as above). Stored and fitted as the vector
//! `a = s·(cos 2φ, sin 2φ)` ([`anisotropy_vector`]): a direction and its opposite are the
//! same lobe, `s² = |a|²` is smooth at `a = 0` (no singular direction at isotropy), and
//! texels average as vectors. `a = [0, 0]` is the isotropic model exactly.
//!
//! **Normal.** A texel's shading normal `n = (n_x, n_y, √(1 − n_x² − n_y²))` in the
//! sample's tangent frame (+x = u, +y = v: glTF's tangent-space convention with +Y up)
//! tilts the frame. [`eval`] returns the *macro-surface* BRDF, the value a gonioreflectometer
//! measures against the sample's mean normal: `f_n(l', v') · (n·l) / (z·l)`, with `l'`, `v'`
//! the directions in the tilted frame and `(n·l)/(z·l)` the ratio of the cosines a renderer
//! with a normal map applies to the one the measurement divides out. 0 when either
//! direction is below the macro surface or the tilted one.

use gonio_devices::Vec3;

use super::microfacet::{dg_over_4, Distribution, Masking};
use super::Rgb;

/// Largest tangent-plane component of a normal `|(n_x, n_y)|`: 0.95 (a tilt of 72°).
pub const MAX_NORMAL_XY: f64 = 0.95;

/// The dielectric normal-incidence reflectance of glTF's metallic-roughness model (ior 1.5).
pub const DIELECTRIC_F0: f64 = 0.04;

/// The anisotropy vector `s·(cos 2φ, sin 2φ)` of strength `s` (clamped to [0, 1]) and
/// direction `rotation` = φ (radians, counter-clockwise from the tangent +x).
#[inline]
pub fn anisotropy_vector(strength: f64, rotation: f64) -> [f64; 2] {
    let s = if strength.is_finite() {
        strength.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let r = if rotation.is_finite() { 2.0 * rotation } else { 0.0 };
    [s * r.cos(), s * r.sin()]
}

/// Strength (`|a|`, at most 1) and direction φ ∈ (−π/2, π/2] (radians, counter-clockwise
/// from the tangent) of anisotropy vector `a`; `(0, 0)` for `a = 0`.
#[inline]
pub fn anisotropy_of(a: [f64; 2]) -> (f64, f64) {
    let s = (a[0] * a[0] + a[1] * a[1]).sqrt();
    if !(s > 0.0 && s.is_finite()) {
        return (0.0, 0.0);
    }
    let mut phi = 0.5 * a[1].atan2(a[0]);
    if phi <= -std::f64::consts::FRAC_PI_2 {
        phi += std::f64::consts::PI;
    }
    (s.min(1.0), phi)
}

/// `(α_t, α_b)` of roughness `roughness` and anisotropy vector `a`: `α = roughness²`
/// (at least [`crate::MIN_ROUGHNESS`]), `α_t = mix(α, 1, s²)`, `α_b = α`.
#[inline]
pub fn alphas(roughness: f64, a: [f64; 2]) -> (f64, f64) {
    let alpha = (roughness * roughness).max(crate::MIN_ROUGHNESS);
    let s2 = (a[0] * a[0] + a[1] * a[1]).min(1.0);
    let s2 = if s2.is_finite() { s2 } else { 0.0 };
    (alpha + (1.0 - alpha) * s2, alpha)
}

/// The BRDF in the frame of the shading normal (normal +z), isotropic.
#[inline]
pub fn eval_local(base_color: &Rgb, metallic: f64, roughness: f64, l: Vec3, v: Vec3) -> Rgb {
    eval_local_aniso(base_color, metallic, roughness, [0.0, 0.0], l, v)
}

/// The BRDF in the frame of the shading normal (normal +z, tangent +x) with anisotropy
/// vector `anisotropy` (see the module docs).
#[inline]
pub fn eval_local_aniso(
    base_color: &Rgb,
    metallic: f64,
    roughness: f64,
    anisotropy: [f64; 2],
    l: Vec3,
    v: Vec3,
) -> Rgb {
    if l.z <= 0.0 || v.z <= 0.0 {
        return [0.0; 3];
    }
    let m = metallic.clamp(0.0, 1.0);
    let mut out = base_color.map(|c| (1.0 - m) * c * std::f64::consts::FRAC_1_PI);
    let (at, ab) = alphas(roughness, anisotropy);
    let (l, v) = if at == ab {
        (l, v)
    } else {
        // Into the frame whose +x is the direction of anisotropy.
        let (_, phi) = anisotropy_of(anisotropy);
        let (s, c) = phi.sin_cos();
        let r = |w: Vec3| Vec3::new(c * w.x + s * w.y, -s * w.x + c * w.y, w.z);
        (r(l), r(v))
    };
    if let Some((s, h)) = dg_over_4(Distribution::Ggx, Masking::Separable, l, v, at, ab) {
        if s > 0.0 {
            let w = (1.0 - v.dot(h).abs().min(1.0)).max(0.0);
            let w5 = w * w * w * w * w;
            for (o, c) in out.iter_mut().zip(base_color) {
                let f0 = DIELECTRIC_F0 + m * (c - DIELECTRIC_F0);
                *o += (f0 + (1.0 - f0) * w5) * s;
            }
        }
    }
    out
}

/// The unit shading normal of tangent-plane components `normal` (clamped to
/// [`MAX_NORMAL_XY`]).
#[inline]
pub fn normal_vector(normal: [f64; 2]) -> Vec3 {
    let (mut x, mut y) = (normal[0], normal[1]);
    let r = (x * x + y * y).sqrt();
    if r > MAX_NORMAL_XY {
        x *= MAX_NORMAL_XY / r;
        y *= MAX_NORMAL_XY / r;
    }
    Vec3::new(x, y, (1.0 - x * x - y * y).max(0.0).sqrt())
}

/// The tangent frame `(t, b, n)` of shading normal `n`: `t` is +x made orthogonal to `n`
/// (Gram–Schmidt, as a renderer builds it from the surface's ∂p/∂u), `b = n × t`.
#[inline]
pub fn frame(n: Vec3) -> (Vec3, Vec3) {
    let x = Vec3::new(1.0, 0.0, 0.0);
    let t = (x - n * n.dot(x)).normalized();
    (t, n.cross(t))
}

/// The macro-surface BRDF (1/sr) of a texel with shading normal `normal` and anisotropy
/// vector `anisotropy` (see the module docs); `normal = [0, 0]` is [`eval_local_aniso`].
#[inline]
pub fn eval(
    base_color: &Rgb,
    metallic: f64,
    roughness: f64,
    normal: [f64; 2],
    anisotropy: [f64; 2],
    l: Vec3,
    v: Vec3,
) -> Rgb {
    if l.z <= 0.0 || v.z <= 0.0 {
        return [0.0; 3];
    }
    if normal == [0.0, 0.0] {
        return eval_local_aniso(base_color, metallic, roughness, anisotropy, l, v);
    }
    let n = normal_vector(normal);
    let (nl, nv) = (n.dot(l), n.dot(v));
    if nl <= 0.0 || nv <= 0.0 {
        return [0.0; 3];
    }
    let (t, b) = frame(n);
    let local = |w: Vec3| Vec3::new(t.dot(w), b.dot(w), n.dot(w));
    let f = eval_local_aniso(base_color, metallic, roughness, anisotropy, local(l), local(v));
    let k = nl / l.z;
    f.map(|x| x * k)
}

#[cfg(test)]
mod tests {
    use super::*;
    use gonio_devices::Direction;

    fn dir(t: f64, p: f64) -> Vec3 {
        Direction::from_degrees(t, p).vector()
    }

    /// A metal (m = 1) is the library's GGX rough conductor with Schlick's Fresnel, and a
    /// dielectric's specular lobe is 0.04 of it at normal incidence: the lobe is the
    /// microfacet module's, not a copy.
    #[test]
    fn metal_lobe_matches_the_microfacet_library() {
        for (tl, pl, tv, pv) in [
            (10.0, 0.0, 20.0, 180.0),
            (45.0, 30.0, 50.0, 200.0),
            (70.0, 90.0, 60.0, 300.0),
        ] {
            let (l, v) = (dir(tl, pl), dir(tv, pv));
            let r: f64 = 0.4;
            let a = r * r;
            let (s, h) = dg_over_4(Distribution::Ggx, Masking::Separable, l, v, a, a).unwrap();
            let w = (1.0 - v.dot(h)).powi(5);
            let f = eval_local(&[0.9, 0.5, 0.1], 1.0, r, l, v);
            for (c, b) in [0.9, 0.5, 0.1].iter().enumerate() {
                let want = (b + (1.0 - b) * w) * s;
                assert!((f[c] - want).abs() <= 1e-12 * want.max(1e-12), "{f:?} {want}");
            }
            let d = eval_local(&[0.5; 3], 0.0, r, l, v);
            let want = 0.5 / std::f64::consts::PI + (0.04 + 0.96 * w) * s;
            assert!((d[0] - want).abs() <= 1e-12 * want);
        }
    }

    /// Reciprocal in the tilted frame too (as `f·cos`), 0 below the tilted horizon, and a
    /// tilt towards the light brightens a texel.
    #[test]
    fn normals_tilt_the_frame() {
        let (l, v) = (dir(40.0, 10.0), dir(30.0, 200.0));
        let nrm = [0.2, -0.1];
        let a = eval(&[0.3, 0.4, 0.5], 0.2, 0.5, nrm, [0.0; 2], l, v);
        let b = eval(&[0.3, 0.4, 0.5], 0.2, 0.5, nrm, [0.0; 2], v, l);
        for c in 0..3 {
            // f·cos is what is reciprocal for the macro-surface value: f(l,v) l_z = f_n (n·l)
            let (x, y) = (
                a[c] * l.z / normal_vector(nrm).dot(l),
                b[c] * v.z / normal_vector(nrm).dot(v),
            );
            assert!((x - y).abs() < 1e-12 * x, "{x} {y}");
        }
        assert_eq!(
            eval(&[0.5; 3], 0.0, 0.5, [0.9, 0.0], [0.0; 2], dir(80.0, 180.0), v),
            [0.0; 3]
        );
        let tilt = eval(&[0.5; 3], 0.0, 1.0, [0.3, 0.0], [0.0; 2], dir(45.0, 0.0), dir(0.0, 0.0));
        let flat = eval(&[0.5; 3], 0.0, 1.0, [0.0, 0.0], [0.0; 2], dir(45.0, 0.0), dir(0.0, 0.0));
        assert!(tilt[0] > flat[0], "{tilt:?} {flat:?}");
    }

    /// `KHR_materials_anisotropy`: `α_t = mix(α, 1, s²)` along the direction, `α_b = α`
    /// across it, the library's anisotropic GGX lobe in that frame; a direction and its
    /// opposite are one lobe; strength 0 is the isotropic model; the vector round-trips.
    #[test]
    fn anisotropy_follows_the_extension() {
        let (s, phi, r) = (0.6f64, 0.5f64, 0.3f64);
        let a = anisotropy_vector(s, phi);
        let (s2, phi2) = anisotropy_of(a);
        assert!((s2 - s).abs() < 1e-12 && (phi2 - phi).abs() < 1e-12, "{s2} {phi2}");
        let (at, ab) = alphas(r, a);
        assert!((ab - r * r).abs() < 1e-15);
        assert!((at - (r * r * (1.0 - s * s) + s * s)).abs() < 1e-12);
        let (l, v) = (dir(40.0, 10.0), dir(30.0, 200.0));
        let (sn, cs) = phi.sin_cos();
        let rot = |w: Vec3| Vec3::new(cs * w.x + sn * w.y, -sn * w.x + cs * w.y, w.z);
        let (d, h) = dg_over_4(Distribution::Ggx, Masking::Separable, rot(l), rot(v), at, ab).unwrap();
        let w5 = (1.0 - rot(v).dot(h)).powi(5);
        let f = eval(&[0.9, 0.5, 0.1], 1.0, r, [0.0; 2], a, l, v);
        let want = (0.9 + 0.1 * w5) * d;
        assert!((f[0] - want).abs() <= 1e-12 * want, "{f:?} {want}");
        let opposite = anisotropy_vector(s, phi + std::f64::consts::PI);
        let g = eval(&[0.9, 0.5, 0.1], 1.0, r, [0.0; 2], opposite, l, v);
        assert!((g[0] - f[0]).abs() <= 1e-9 * f[0]);
        assert_eq!(
            eval(&[0.5; 3], 0.3, r, [0.1, 0.0], [0.0; 2], l, v),
            eval(&[0.5; 3], 0.3, r, [0.1, 0.0], anisotropy_vector(0.0, 1.0), l, v)
        );
        // Reciprocal with a tilted normal too (as in `normals_tilt_the_frame`).
        let n = normal_vector([0.2, -0.1]);
        let x = eval(&[0.3; 3], 0.2, r, [0.2, -0.1], a, l, v)[0] * l.z / n.dot(l);
        let y = eval(&[0.3; 3], 0.2, r, [0.2, -0.1], a, v, l)[0] * v.z / n.dot(v);
        assert!((x - y).abs() < 1e-12 * x, "{x} {y}");
        // Along the direction the highlight is wider: off-mirror in-plane along φ is brighter
        // than the same offset across it.
        let along = eval(
            &[0.0; 3],
            1.0,
            0.2,
            [0.0; 2],
            anisotropy_vector(0.7, 0.0),
            dir(30.0, 180.0),
            dir(40.0, 0.0),
        );
        let across = eval(
            &[0.0; 3],
            1.0,
            0.2,
            [0.0; 2],
            anisotropy_vector(0.7, 0.0),
            dir(30.0, 270.0),
            dir(40.0, 90.0),
        );
        assert!(along[0] > 2.0 * across[0], "{along:?} {across:?}");
    }
}
