//! The averaged BRDF as an RGL tensor file (`.bsdf`), the layout of Dupuy & Jakob 2018 ("An
//! adaptive parameterization for efficient material acquisition and rendering") that
//! Mitsuba 3's `measured` plugin loads (RGB variants read the field `rgb`).
//!
//! **Why this layout and not a plain grid.** The paper stores the BRDF not over (ω_i, ω_o)
//! but, per incidence slice, over the unit square of a *warp*: a sample `s ∈ [0,1]²` is
//! mapped by the visible-normal distribution's inverse CDF to a microfacet normal `m`, and
//! `ω_o` is `ω_i` reflected about `m`. A grid in `s` is dense where the lobe is, so a 64²
//! slice resolves a glossy highlight that a 64² angle grid would miss, and the same warp
//! importance-samples the material in the renderer.
//!
//! **What the reader does** (`measured.cpp`, read for this file, no code taken): for
//! `(ω_i, ω_o)`, `m = normalize(ω_i + ω_o)`; `u_m = (√(2θ_m/π), (φ_m − φ_i + π)/2π)` (one φ_i
//! slice: isotropic); `s = vndf⁻¹(u_m)` by the continuous marginal-then-conditional inverse
//! CDF of the bilinear `vndf` grid of the slices around θ_i (linear between slices); the
//! value is `rgb(s)` (bilinear, and linear between slices) times, with `jacobian = 1`,
//! `ndf(u_m) / (4 σ(u_{ω_i}))` (bilinear lookups of the `ndf` and `sigma` grids).
//!
//! **What gonio writes.** One φ_i slice, [`THETA_SLICES`] θ_i slices every 4° from 0° to 88°,
//! `size × size` grids:
//! - `ndf` (`size × size`, rows φ_u, columns θ_u): the NDF from the fitted model's
//!   retro-reflection by the paper's fixed point, `D(ω) ∝ f(ω, ω) cos θ σ_D(ω)` (the
//!   microfacet retro-reflection with `G1(ω) = cos θ / σ(ω)`), iterated from `D ∝ f cos θ`
//!   and normalised to `∫ D cos θ_m dm = 1`; `sigma` its projected area
//!   `σ(ω) = ∫ D(m) ⟨m·ω⟩ dm` (the φ integral in closed form);
//! - `vndf` per slice: the visible-normal density `D(m) ⟨m·ω_i⟩` times the Jacobian of
//!   `u ↦ ω` (`2π² u_θ sin θ_m`), on the `u_m` grid;
//! - `rgb` per slice at each sample-grid node `s`: gonio computes the same warp itself
//!   ([`Warp`], the exact inverse CDF of the bilinear density, as the reader's continuous
//!   `Marginal2D`) to find `m` and `ω_o`, and stores `f_iso(ω_i, ω_o) · 4 σ̃(ω_i) / D̃(m)`,
//!   times `cos θ_o` (Mitsuba's `eval` returns `f · cos θ_o`, and `measured` returns the
//!   table's value: the cosine must be in the table), with `σ̃`, `D̃` the reader's own
//!   bilinear lookups: at every node the reader returns the fitted BRDF (to float
//!   precision); between nodes and slices it interpolates;
//! - `luminance`: the luminance of `rgb` (the sampling weight; a floor keeps every slice
//!   positive), `valid` (u8) 1 where `ω_o` is above the horizon;
//! - `description`: the provenance JSON (gonio version, dataset and its journal hash, fit).

use super::average::AverageBrdf;
use super::{io, ExportError};
use gonio_devices::Vec3;
use rayon::prelude::*;
use serde::Serialize;
use std::f64::consts::{FRAC_PI_2, PI};
use std::path::Path;

/// θ_i slices: 0°, 4°, …, 88°.
pub const THETA_SLICES: usize = 23;
/// Spacing of the θ_i slices (degrees).
pub const THETA_STEP_DEG: f64 = 4.0;
/// Default and accepted grid sides.
pub const DEFAULT_SIZE: usize = 64;
pub const MIN_SIZE: usize = 4;
pub const MAX_SIZE: usize = 512;
/// Nodes of the fine θ grid the NDF fixed point runs on.
const NDF_NODES: usize = 1025;
/// Fixed-point iterations (the change after 20 is below 1e-9 relative on the test materials).
const NDF_ITERATIONS: usize = 40;

/// Tensor-file element types (Mitsuba's `Struct::Type` codes).
const UINT8: u8 = 1;
const FLOAT32: u8 = 10;

/// What `encode` produced, for the report.
#[derive(Clone, Debug, Serialize)]
pub struct RglSummary {
    pub size: usize,
    pub theta_i_deg: Vec<f64>,
    pub bytes: usize,
    /// Sample-grid nodes whose reflected direction falls below the horizon (value 0).
    pub below_horizon: usize,
}

fn u2theta(u: f64) -> f64 {
    u * u * FRAC_PI_2
}
fn theta2u(t: f64) -> f64 {
    (t / FRAC_PI_2).max(0.0).sqrt()
}
fn u2phi(u: f64) -> f64 {
    (2.0 * u - 1.0) * PI
}

fn luminance(c: [f64; 3]) -> f64 {
    0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
}

/// `∫₀^{2π} max(0, a + b cos φ) dφ` for `b ≥ 0`.
fn azimuth_integral(a: f64, b: f64) -> f64 {
    if a >= b {
        2.0 * PI * a
    } else if a <= -b {
        0.0
    } else {
        2.0 * (a * (-a / b).acos() + (b * b - a * a).sqrt())
    }
}

/// An isotropic NDF tabulated over `u = √(2θ/π)` on [`NDF_NODES`] nodes.
struct Ndf {
    d: Vec<f64>,
}

impl Ndf {
    fn theta(i: usize) -> f64 {
        u2theta(i as f64 / (NDF_NODES - 1) as f64)
    }

    /// `D(θ)`, linear in `u` between nodes.
    fn at(&self, theta: f64) -> f64 {
        let x = theta2u(theta).min(1.0) * (NDF_NODES - 1) as f64;
        let i = (x.floor() as usize).min(NDF_NODES - 2);
        let t = x - i as f64;
        self.d[i] * (1.0 - t) + self.d[i + 1] * t
    }

    /// `∫ D(m) w(θ_m) dm` by the trapezoid rule in `u` (`dm = sin θ dθ dφ`, `dθ = π u du`),
    /// `w` the azimuth-integrated weight.
    fn integrate(d: &[f64], w: impl Fn(f64) -> f64) -> f64 {
        let du = 1.0 / (NDF_NODES - 1) as f64;
        (0..NDF_NODES)
            .map(|i| {
                let u = i as f64 * du;
                let th = u2theta(u);
                let edge = if i == 0 || i == NDF_NODES - 1 { 0.5 } else { 1.0 };
                edge * d[i] * w(th) * th.sin() * PI * u * du
            })
            .sum()
    }

    /// Projected area `σ(θ) = ∫ D(m) ⟨m·ω⟩ dm` of the direction at polar angle `theta`.
    fn sigma_of(d: &[f64], theta: f64) -> f64 {
        let (st, ct) = theta.sin_cos();
        Ndf::integrate(d, |tm| azimuth_integral(ct * tm.cos(), st * tm.sin()))
    }

    /// The retro-reflection fixed point: `D ∝ f(ω, ω) cos θ σ_D(ω)`, `∫ D cos θ_m dm = 1`.
    fn from_retro(retro: impl Fn(f64) -> f64) -> Ndf {
        let f: Vec<f64> = (0..NDF_NODES)
            .map(|i| {
                let th = Ndf::theta(i);
                retro(th).max(0.0) * th.cos()
            })
            .collect();
        let normalize = |d: &mut Vec<f64>| {
            let n = Ndf::integrate(d, |tm| 2.0 * PI * tm.cos());
            if n > 0.0 && n.is_finite() {
                d.iter_mut().for_each(|x| *x /= n);
            }
        };
        let mut d = f.clone();
        normalize(&mut d);
        for _ in 0..NDF_ITERATIONS {
            let mut next: Vec<f64> = (0..NDF_NODES)
                .into_par_iter()
                .map(|i| f[i] * Ndf::sigma_of(&d, Ndf::theta(i)))
                .collect();
            normalize(&mut next);
            d = next;
        }
        Ndf { d }
    }
}

/// Bilinear lookup of a `n × n` grid (rows y, columns x) at `(x, y) ∈ [0,1]²`, as the
/// reader interpolates `ndf` and `sigma`.
fn bilinear(grid: &[f64], n: usize, x: f64, y: f64) -> f64 {
    let fx = x.clamp(0.0, 1.0) * (n - 1) as f64;
    let fy = y.clamp(0.0, 1.0) * (n - 1) as f64;
    let (i, j) = ((fx as usize).min(n - 2), (fy as usize).min(n - 2));
    let (tx, ty) = (fx - i as f64, fy - j as f64);
    let g = |i: usize, j: usize| grid[j * n + i];
    (1.0 - ty) * ((1.0 - tx) * g(i, j) + tx * g(i + 1, j)) + ty * ((1.0 - tx) * g(i, j + 1) + tx * g(i + 1, j + 1))
}

/// `t ∈ [0, 1]` with `a t + (b − a) t²/2 = target` (the CDF of the density linear from `a`
/// to `b` on one cell), in the form that is stable when `a ≈ b`.
fn solve_linear_cdf(a: f64, b: f64, target: f64) -> f64 {
    if target <= 0.0 {
        return 0.0;
    }
    let disc = (a * a + 2.0 * (b - a) * target).max(0.0);
    let den = a + disc.sqrt();
    if den > 0.0 {
        (2.0 * target / den).clamp(0.0, 1.0)
    } else {
        0.5
    }
}

/// The sample warp of a bilinear density on an `n × n` grid: the inverse of its marginal
/// CDF in y, then of its conditional CDF in x (the mapping the reader's continuous
/// `Marginal2D` inverts).
pub struct Warp {
    n: usize,
    p: Vec<f64>,
    /// Per row, the running trapezoid integral along x (n values, first 0).
    cond: Vec<f64>,
    /// The running integral of the row totals along y (n values, first 0).
    marg: Vec<f64>,
}

impl Warp {
    pub fn new(p: Vec<f64>, n: usize) -> Warp {
        let mut cond = vec![0.0; n * n];
        for j in 0..n {
            for i in 1..n {
                cond[j * n + i] = cond[j * n + i - 1] + 0.5 * (p[j * n + i - 1] + p[j * n + i]);
            }
        }
        let row = |j: usize| cond[j * n + n - 1];
        let mut marg = vec![0.0; n];
        for j in 1..n {
            marg[j] = marg[j - 1] + 0.5 * (row(j - 1) + row(j));
        }
        Warp { n, p, cond, marg }
    }

    /// `u ∈ [0,1]²` of sample `s ∈ [0,1]²`.
    pub fn sample(&self, s: [f64; 2]) -> [f64; 2] {
        let n = self.n;
        let total = self.marg[n - 1];
        if total <= 0.0 {
            return s;
        }
        // Row: the last interval whose CDF start is below the target.
        let ty_target = s[1].clamp(0.0, 1.0) * total;
        let j = (0..n - 1).rev().find(|&j| self.marg[j] < ty_target).unwrap_or(0);
        let (r0, r1) = (self.cond[j * n + n - 1], self.cond[(j + 1) * n + n - 1]);
        let ty = solve_linear_cdf(r0, r1, ty_target - self.marg[j]);
        // Column, in the row interpolated at ty.
        let c = |i: usize| (1.0 - ty) * self.cond[j * n + i] + ty * self.cond[(j + 1) * n + i];
        let tx_target = s[0].clamp(0.0, 1.0) * c(n - 1);
        let i = (0..n - 1).rev().find(|&i| c(i) < tx_target).unwrap_or(0);
        let q = |i: usize| (1.0 - ty) * self.p[j * n + i] + ty * self.p[(j + 1) * n + i];
        let tx = solve_linear_cdf(q(i), q(i + 1), tx_target - c(i));
        let step = 1.0 / (n - 1) as f64;
        [(i as f64 + tx) * step, (j as f64 + ty) * step]
    }
}

/// A tensor-file field.
struct Field {
    name: &'static str,
    dtype: u8,
    shape: Vec<usize>,
    data: Vec<u8>,
}

fn f32_field(name: &'static str, shape: Vec<usize>, v: &[f64]) -> Field {
    Field {
        name,
        dtype: FLOAT32,
        shape,
        data: v.iter().flat_map(|x| (*x as f32).to_le_bytes()).collect(),
    }
}

/// Mitsuba's tensor-file container: `tensor_file\0`, version 1.0, the field count (u32),
/// per field its name (u16 length + bytes), rank (u16), type (u8), data offset (u64) and
/// shape (u64 each); then the data, each field 8-byte aligned. Little-endian.
fn tensor_file(fields: &[Field]) -> Vec<u8> {
    let header_len: usize = 12
        + 2
        + 4
        + fields
            .iter()
            .map(|f| 2 + f.name.len() + 2 + 1 + 8 + 8 * f.shape.len())
            .sum::<usize>();
    let align = |x: usize| x.div_ceil(8) * 8;
    let mut offsets = Vec::with_capacity(fields.len());
    let mut at = align(header_len);
    for f in fields {
        offsets.push(at);
        at = align(at + f.data.len());
    }
    let mut out = Vec::with_capacity(at);
    out.extend_from_slice(b"tensor_file\0");
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&(fields.len() as u32).to_le_bytes());
    for (f, off) in fields.iter().zip(&offsets) {
        out.extend_from_slice(&(f.name.len() as u16).to_le_bytes());
        out.extend_from_slice(f.name.as_bytes());
        out.extend_from_slice(&(f.shape.len() as u16).to_le_bytes());
        out.push(f.dtype);
        out.extend_from_slice(&(*off as u64).to_le_bytes());
        for s in &f.shape {
            out.extend_from_slice(&(*s as u64).to_le_bytes());
        }
    }
    for (f, off) in fields.iter().zip(&offsets) {
        out.resize(*off, 0);
        out.extend_from_slice(&f.data);
    }
    out.resize(at, 0);
    out
}

/// Check `--size` for this format.
pub fn check_size(size: usize) -> Result<(), String> {
    if (MIN_SIZE..=MAX_SIZE).contains(&size) {
        Ok(())
    } else {
        Err(format!(
            "--size {size}: the rgl-bsdf grid side must be {MIN_SIZE}..={MAX_SIZE} (default {DEFAULT_SIZE}; the reader \
             interpolates bilinearly, so at least 2 nodes per axis, and 4 to resolve a lobe)"
        ))
    }
}

/// The θ_i slices (radians).
pub fn theta_i() -> Vec<f64> {
    (0..THETA_SLICES)
        .map(|k| (k as f64 * THETA_STEP_DEG).to_radians())
        .collect()
}

/// The `.bsdf` bytes of `avg` on `size × size` grids.
pub fn encode(avg: &AverageBrdf, size: usize) -> Result<(Vec<u8>, RglSummary), ExportError> {
    check_size(size).map_err(|reason| ExportError::Output {
        path: "rgl-bsdf".into(),
        reason,
    })?;
    let n = size;
    let dir = |theta: f64, phi: f64| Vec3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos());
    let ndf = Ndf::from_retro(|th| {
        let w = dir(th, 0.0);
        luminance(avg.eval(w, w))
    });
    let node = |k: usize| k as f64 / (n - 1) as f64;
    // ndf and sigma on the u grid (rows φ_u, columns θ_u; isotropic: every row alike).
    let d_row: Vec<f64> = (0..n).map(|i| ndf.at(u2theta(node(i)))).collect();
    let s_row: Vec<f64> = (0..n).map(|i| Ndf::sigma_of(&ndf.d, u2theta(node(i)))).collect();
    let ndf_grid: Vec<f64> = (0..n).flat_map(|_| d_row.iter().copied()).collect();
    let sigma_grid: Vec<f64> = (0..n).flat_map(|_| s_row.iter().copied()).collect();
    let thetas = theta_i();
    struct Slice {
        vndf: Vec<f64>,
        rgb: Vec<f64>,
        lum: Vec<f64>,
        valid: Vec<u8>,
        below: usize,
    }
    let slices: Vec<Slice> = thetas
        .par_iter()
        .map(|&ti| {
            let wi = dir(ti, 0.0);
            let mut vndf = vec![0.0; n * n];
            for j in 0..n {
                for i in 0..n {
                    let (ux, tm, pm) = (node(i), u2theta(node(i)), u2phi(node(j)));
                    let m = dir(tm, pm);
                    vndf[j * n + i] = ndf.at(tm) * m.dot(wi).max(0.0) * 2.0 * PI * PI * ux * tm.sin();
                }
            }
            let warp = Warp::new(vndf.clone(), n);
            let sigma_i = bilinear(&sigma_grid, n, theta2u(ti), 0.5);
            let mut rgb = vec![0.0; 3 * n * n];
            let mut lum = vec![0.0; n * n];
            let mut valid = vec![0u8; n * n];
            let mut below = 0;
            for j in 0..n {
                for i in 0..n {
                    let u = warp.sample([node(i), node(j)]);
                    let m = dir(u2theta(u[0]), u2phi(u[1]));
                    let wo = m * (2.0 * m.dot(wi)) - wi;
                    let d = bilinear(&ndf_grid, n, u[0], u[1]);
                    if wo.z <= 0.0 || d <= 0.0 {
                        below += (wo.z <= 0.0) as usize;
                        continue;
                    }
                    let wo = wo.normalized();
                    let f = avg.eval(wi, wo);
                    // Mitsuba's `eval` returns f · cos θ_o and `measured` returns the table.
                    let scale = wo.z * 4.0 * sigma_i / d;
                    for (c, v) in f.iter().enumerate() {
                        rgb[(c * n + j) * n + i] = v * scale;
                    }
                    lum[j * n + i] = luminance(f) * scale;
                    valid[j * n + i] = 1;
                }
            }
            // Keep the sampling density positive everywhere (the reader normalises it).
            let floor = 1e-6 * lum.iter().cloned().fold(0.0, f64::max).max(1e-12);
            lum.iter_mut().for_each(|x| *x = x.max(floor));
            Slice {
                vndf,
                rgb,
                lum,
                valid,
                below,
            }
        })
        .collect();
    let m = thetas.len();
    let description = serde_json::to_string(&avg.provenance).map_err(|e| ExportError::Output {
        path: "rgl-bsdf".into(),
        reason: e.to_string(),
    })?;
    let cat =
        |get: &dyn Fn(&Slice) -> &Vec<f64>| slices.iter().flat_map(|s| get(s).iter().copied()).collect::<Vec<f64>>();
    let fields = vec![
        Field {
            name: "description",
            dtype: UINT8,
            shape: vec![description.len()],
            data: description.into_bytes(),
        },
        Field {
            name: "jacobian",
            dtype: UINT8,
            shape: vec![1],
            data: vec![1],
        },
        f32_field("theta_i", vec![m], &thetas),
        f32_field("phi_i", vec![1], &[0.0]),
        f32_field("ndf", vec![n, n], &ndf_grid),
        f32_field("sigma", vec![n, n], &sigma_grid),
        f32_field("vndf", vec![1, m, n, n], &cat(&|s| &s.vndf)),
        f32_field("luminance", vec![1, m, n, n], &cat(&|s| &s.lum)),
        f32_field("rgb", vec![1, m, 3, n, n], &cat(&|s| &s.rgb)),
        Field {
            name: "valid",
            dtype: UINT8,
            shape: vec![1, m, n, n],
            data: slices.iter().flat_map(|s| s.valid.iter().copied()).collect(),
        },
    ];
    if let Some(f) = fields.iter().find(|f| {
        f.dtype == FLOAT32
            && f.data
                .chunks_exact(4)
                .any(|b| !f32::from_le_bytes([b[0], b[1], b[2], b[3]]).is_finite())
    }) {
        return Err(ExportError::Output {
            path: "rgl-bsdf".into(),
            reason: format!("field `{}` has a non-finite value (a degenerate fit?)", f.name),
        });
    }
    let bytes = tensor_file(&fields);
    let summary = RglSummary {
        size: n,
        theta_i_deg: thetas.iter().map(|t| t.to_degrees()).collect(),
        bytes: bytes.len(),
        below_horizon: slices.iter().map(|s| s.below).sum(),
    };
    Ok((bytes, summary))
}

/// Write `avg` as `out` (a `.bsdf` file).
pub fn write(avg: &AverageBrdf, size: usize, out: &Path) -> Result<RglSummary, ExportError> {
    let (bytes, summary) = encode(avg, size)?;
    std::fs::write(out, bytes).map_err(io(out))?;
    Ok(summary)
}
