//! Test helpers: camera poses of the default rig and a synthetic renderer of the sample
//! holder (markers, white border, textured sample) with supersampling, blur and noise.

use crate::Homography;
use gonio_devices::camera::Intrinsics;
use gonio_devices::image::RgbImage;
use gonio_devices::kinematics::{for_rig, CameraPose};
use gonio_devices::rig::RigSpec;
use gonio_devices::target::MarkerBorder;
use gonio_devices::Vec3;
use rayon::prelude::*;

pub const WIDTH: usize = 768;
pub const HEIGHT: usize = 640;
pub const SAMPLE_MM: f64 = 60.0;

/// The test camera: the default rig's sensor with a fixed focal length of 5000 px, so
/// the tests' geometry does not drift when the default rig's lens changes.
pub fn rig_intrinsics() -> Intrinsics {
    let mut rig = RigSpec::default_rig();
    assert_eq!((rig.camera.width, rig.camera.height), (WIDTH, HEIGHT));
    rig.camera.focal_length_px = 5000.0;
    rig.camera.intrinsics()
}

/// The default rig's camera pose for view direction (θ, φ) in degrees.
pub fn pose(theta_deg: f64, phi_deg: f64) -> CameraPose {
    let rig = RigSpec::default_rig();
    let k = for_rig(&rig);
    // Axes: turntable, camera arc, light base, light arc. The turntable at −φ puts the
    // camera (fixed in the world x-z plane) at azimuth φ in the sample frame.
    k.camera_pose(&[-phi_deg.to_radians(), theta_deg.to_radians(), 0.0, 0.0])
}

/// Rotate `v` about unit `axis` by `a` radians (Rodrigues).
fn rotate(v: Vec3, axis: Vec3, a: f64) -> Vec3 {
    let (s, c) = a.sin_cos();
    v * c + axis.cross(v) * s + axis * (axis.dot(v) * (1.0 - c))
}

/// `pose` with its orientation rotated by (pan, tilt, roll) degrees about the camera's own
/// down, right and forward axes and its centre moved by `shift` mm: the "known" rig pose
/// is then this far from the truth.
pub fn perturb(p: &CameraPose, pan_deg: f64, tilt_deg: f64, roll_deg: f64, shift: Vec3) -> CameraPose {
    let mut q = *p;
    for (axis, a) in [(p.down, pan_deg), (p.right, tilt_deg), (p.forward, roll_deg)] {
        let a = a.to_radians();
        q.right = rotate(q.right, axis, a);
        q.down = rotate(q.down, axis, a);
        q.forward = rotate(q.forward, axis, a);
    }
    q.position = q.position + shift;
    q
}

/// Deterministic PRNG (splitmix64) with Box-Muller normals, so tests need no extra crates.
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed)
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in (0, 1).
    pub fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    pub fn normal(&mut self) -> f64 {
        let (a, b) = (self.uniform(), self.uniform());
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    }
}

/// Colours of the standard scene: marker 0.05, white border 0.9, sample `texture`,
/// everything else 0.02.
pub fn scene<'a>(
    border: &'a MarkerBorder,
    sample_mm: f64,
    texture: &'a (dyn Fn(f64, f64) -> [f32; 3] + Sync),
) -> impl Fn(f64, f64) -> [f32; 3] + Sync + 'a {
    move |x, y| {
        let h = sample_mm / 2.0;
        if x.abs() <= h && y.abs() <= h {
            texture(x, y)
        } else if x.abs() <= border.outer_half(sample_mm) && y.abs() <= border.outer_half(sample_mm) {
            if border.is_marker(sample_mm, x, y) {
                [0.05; 3]
            } else {
                [0.9; 3]
            }
        } else {
            [0.02; 3]
        }
    }
}

/// A mid-grey texture with some structure (so the sample is not mistaken for white).
pub fn default_texture(x: f64, y: f64) -> [f32; 3] {
    let a = 0.45 + 0.2 * (x * 0.7).sin() * (y * 0.5).cos();
    [a as f32, (a * 0.8) as f32, (a * 0.6 + 0.1) as f32]
}

/// Render what the camera at `pose` sees: each pixel is the mean of 4 × 4 (sheared) sub-samples of
/// `paint` on the plane (pixels whose ray misses the plane get 0.02), then an optional
/// Gaussian blur (σ in pixels, `blur` = 0 for none), then Gaussian noise of σ `noise`.
pub fn render(
    intr: &Intrinsics,
    pose: &CameraPose,
    paint: &(dyn Fn(f64, f64) -> [f32; 3] + Sync),
    blur: f64,
    noise: f64,
    seed: u64,
) -> RgbImage {
    render_ss(intr, pose, paint, 4, blur, noise, seed)
}

/// [`render`] with `ss × ss` sheared sub-samples per pixel (corner tests that measure
/// hundredths of a pixel need more than 4 × 4).
pub fn render_ss(
    intr: &Intrinsics,
    pose: &CameraPose,
    paint: &(dyn Fn(f64, f64) -> [f32; 3] + Sync),
    ss: usize,
    blur: f64,
    noise: f64,
    seed: u64,
) -> RgbImage {
    let inv = Homography::from_pose(intr, pose).inverse().unwrap();
    let mut img = RgbImage::new(WIDTH, HEIGHT);
    img.data.par_chunks_mut(WIDTH * 3).enumerate().for_each(|(j, row)| {
        for i in 0..WIDTH {
            let mut acc = [0.0f32; 3];
            let n = ss as f64;
            for a in 0..ss {
                for b in 0..ss {
                    // A sheared ss × ss grid: all sub-samples have distinct u and
                    // distinct v offsets, so edges along the pixel axes (which the
                    // rig's views at φ = 0° and 90° produce) are resolved to 1/ss² px
                    // instead of 1/ss px.
                    let u = i as f64 + (a as f64 + (b as f64 + 0.5) / n) / n;
                    let v = j as f64 + (b as f64 + (a as f64 + 0.5) / n) / n;
                    let c = match inv.apply(u, v) {
                        Some((x, y)) => paint(x, y),
                        None => [0.02; 3],
                    };
                    for k in 0..3 {
                        acc[k] += c[k] / (n * n) as f32;
                    }
                }
            }
            row[i * 3..i * 3 + 3].copy_from_slice(&acc);
        }
    });
    if blur > 0.0 {
        gaussian_blur(&mut img, blur);
    }
    if noise > 0.0 {
        let mut rng = Rng::new(seed);
        for v in &mut img.data {
            *v += (noise * rng.normal()) as f32;
        }
    }
    img
}

/// Separable Gaussian blur with clamped edges.
pub fn gaussian_blur(img: &mut RgbImage, sigma: f64) {
    let r = (3.0 * sigma).ceil() as isize;
    let k: Vec<f32> = (-r..=r)
        .map(|d| (-(d * d) as f64 / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    let sum: f32 = k.iter().sum();
    let k: Vec<f32> = k.iter().map(|v| v / sum).collect();
    let (w, h) = (img.width as isize, img.height as isize);
    for horizontal in [true, false] {
        let src = img.data.clone();
        for y in 0..h {
            for x in 0..w {
                let mut acc = [0.0f32; 3];
                for (t, kv) in k.iter().enumerate() {
                    let d = t as isize - r;
                    let (sx, sy) = if horizontal {
                        ((x + d).clamp(0, w - 1), y)
                    } else {
                        (x, (y + d).clamp(0, h - 1))
                    };
                    let idx = ((sy * w + sx) * 3) as usize;
                    for c in 0..3 {
                        acc[c] += kv * src[idx + c];
                    }
                }
                let idx = ((y * w + x) * 3) as usize;
                img.data[idx..idx + 3].copy_from_slice(&acc);
            }
        }
    }
}
