//! The per-texel scaled Lafortune SVBRDF (McAllister et al. 2002) as a `.gbtf`: what
//! `gonio fit --per-texel --out F.gbtf` writes. Decoded here, so `gonio reconstruct`,
//! `gonio render`, `gonio view` (CPU path) and `compress::evaluate` read it like any other
//! method: an SVBRDF is itself a compression method.
//!
//! **Blocks.** `params` (texels × (3 + 5 · lobes)): `kd` RGB, then per lobe the angle γ
//! (radians) of `C = √2 (cos γ, cos γ, sin γ)`, the exponent `n` and `ks` RGB (the layout
//! of `fit::Family` for Lafortune). `gain` (pairs × 9, pair `view · lights + light`): per
//! channel the plane `a + b·u + c·w` (`u`, `w` the texel centre in [−½, ½], `w` growing
//! downwards) that turns a BRDF value into the dataset's units; all zero for a pair the fit
//! had no data for, which decodes to 0.
//!
//! **Header.** `params` is [`Params`] with [`Method::Svbrdf`] (`components` = parameters
//! per texel) plus `geometry`: `{camera_distance_mm, light_distance_mm, size_mm}` when
//! each texel saw its own directions (the rig at a finite distance), `null` for the
//! nominal directions.
//!
//! **Decoder.** Per texel and pair `f = kd/π + Σ ks (n+2)/(2π) max(0, C_x l_x v_x + C_y
//! l_y v_y + C_z l_z v_z)^n` (0 when `l` or `v` is below the horizon), times the gain
//! plane. The lobe is the material library's own (`gonio_brdf::lafortune::lobe_value`, one
//! home of the formula); the tests below check the decoder against the library's model, and
//! `fit`'s tests check that a file decodes to what the fitted models evaluate.

use super::container::{BlockInfo, Gbtf, GbtfHeader};
use super::data::DatasetViews;
use super::error::CompressError;
use super::params::{header_for, Codec, CodecId, Decode, EncodeInfo, Knobs, Layout, Method, Opened, Params, Shard};
use gonio_devices::{Direction, Vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::f64::consts::{PI, SQRT_2};
use std::sync::Arc;

/// Parameters per lobe (γ, n, ks RGB).
pub const PER_LOBE: usize = 5;

/// Largest lobe count a file may declare.
pub const MAX_LOBES: usize = 16;

/// Parameters per texel with `lobes` lobes.
pub fn params_per_texel(lobes: usize) -> usize {
    3 + PER_LOBE * lobes
}

/// Where the texels lie (mm): each texel's own directions toward a lamp and a camera at
/// finite distance, as `gonio sim btf` and an acquisition see them.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
pub struct Geometry {
    pub camera_distance_mm: f64,
    pub light_distance_mm: f64,
    pub size_mm: f64,
}

impl Geometry {
    /// Texel `t`'s light and view directions for the nominal `l`, `v` (row 0 at +y).
    pub fn texel_dirs(&self, l: Vec3, v: Vec3, t: usize, width: usize, height: usize) -> (Vec3, Vec3) {
        let s = self.size_mm;
        let x = ((t % width) as f64 + 0.5) / width as f64 * s - s / 2.0;
        let y = s / 2.0 - ((t / width) as f64 + 0.5) / height as f64 * s;
        let p = Vec3::new(x, y, 0.0);
        (
            (l * self.light_distance_mm - p).normalized(),
            (v * self.camera_distance_mm - p).normalized(),
        )
    }
}

/// The `.gbtf` of a per-texel fit of `ds`: `params` row-major texels × [`params_per_texel`],
/// `gain` pairs × 9 (zeros for pairs without a fit).
pub fn encode(
    ds: &DatasetViews,
    lobes: usize,
    params: Vec<f32>,
    gain: Vec<f32>,
    geometry: Option<Geometry>,
) -> Result<Gbtf, CompressError> {
    let (t, np, pairs) = (ds.texels(), params_per_texel(lobes), ds.n_lights() * ds.n_views());
    if !(1..=MAX_LOBES).contains(&lobes) || params.len() != t * np || gain.len() != pairs * 9 {
        return Err(CompressError::Invalid(format!(
            "svbrdf: {} parameters and {} gains for {t} texels × {np} and {pairs} pairs × 9 ({lobes} lobes)",
            params.len(),
            gain.len()
        )));
    }
    if let Some(i) = params.iter().chain(&gain).position(|x| !x.is_finite()) {
        return Err(CompressError::Invalid(format!("svbrdf: value {i} is not finite")));
    }
    let p = Params::new(Method::Svbrdf { lobes }, np);
    let mut header = header_for(
        ds,
        &p,
        Vec::new(),
        vec![BlockInfo::new("params", t, np), BlockInfo::new("gain", pairs, 9)],
    );
    if let Some(o) = header.params.as_object_mut() {
        o.insert(
            "geometry".into(),
            serde_json::to_value(geometry).map_err(|e| CompressError::Invalid(e.to_string()))?,
        );
    }
    Ok(Gbtf {
        header,
        blocks: vec![params, gain],
    })
}

/// Check an SVBRDF file's header and blocks; returns (lobes, geometry).
pub fn validate(g: &Gbtf) -> Result<(usize, Option<Geometry>), CompressError> {
    let h: &GbtfHeader = &g.header;
    let bad = |r: String| CompressError::Invalid(format!(".gbtf svbrdf: {r}"));
    let params: Params =
        serde_json::from_value(h.params.clone()).map_err(|e| bad(format!("parameters in the header: {e}")))?;
    let Method::Svbrdf { lobes } = params.method else {
        return Err(bad(format!("the header's method is {}", params.method.name())));
    };
    if !(1..=MAX_LOBES).contains(&lobes) {
        return Err(bad(format!("{lobes} lobes; must be 1..={MAX_LOBES}")));
    }
    let geometry: Option<Geometry> = serde_json::from_value(h.params.get("geometry").cloned().unwrap_or_default())
        .map_err(|e| bad(format!("geometry in the header: {e}")))?;
    if let Some(ge) = geometry {
        let ok = |x: f64| x.is_finite() && x > 0.0;
        if !(ok(ge.camera_distance_mm) && ok(ge.light_distance_mm) && ok(ge.size_mm)) {
            return Err(bad(format!("geometry {ge:?}: distances and size must be positive")));
        }
    }
    let (t, np, pairs) = (
        h.width * h.height,
        params_per_texel(lobes),
        h.lights_deg.len() * h.views_deg.len(),
    );
    let got: Vec<(usize, usize)> = h.blocks.iter().map(|b| (b.rows, b.cols)).collect();
    if got != [(t, np), (pairs, 9)] || h.channels != 3 {
        return Err(bad(format!(
            "block shapes {got:?} do not match {t} texels × {np} parameters and {pairs} pairs × 9 gains"
        )));
    }
    Ok((lobes, geometry))
}

/// The BRDF (1/sr, RGB) of one texel's parameters `p` at unit `l`, `v`.
pub fn eval(p: &[f32], lobes: usize, l: Vec3, v: Vec3) -> [f64; 3] {
    if l.z <= 0.0 || v.z <= 0.0 {
        return [0.0; 3];
    }
    let mut out = [0, 1, 2].map(|c| p[c] as f64 / PI);
    for j in 0..lobes {
        let o = 3 + PER_LOBE * j;
        let ks = [p[o + 2] as f64, p[o + 3] as f64, p[o + 4] as f64];
        if ks.iter().all(|k| *k == 0.0) {
            continue;
        }
        let (g, n) = (p[o] as f64, p[o + 1] as f64);
        let c = [SQRT_2 * g.cos(), SQRT_2 * g.cos(), SQRT_2 * g.sin()];
        let val = gonio_brdf::lafortune::lobe_value(c, n, l, v);
        for (o, k) in out.iter_mut().zip(ks) {
            if k != 0.0 {
                *o += k * val;
            }
        }
    }
    out
}

/// Image (`light`, `view`) of a file that passed [`validate`]: interleaved linear RGB.
pub fn reconstruct(g: &Gbtf, lobes: usize, geometry: Option<Geometry>, light: usize, view: usize) -> Vec<f32> {
    let h = &g.header;
    let (w, ht) = (h.width, h.height);
    let np = params_per_texel(lobes);
    let pair = view * h.lights_deg.len() + light;
    let gain = &g.blocks[1][pair * 9..pair * 9 + 9];
    let mut out = vec![0f32; w * ht * 3];
    if gain.iter().all(|x| *x == 0.0) {
        return out;
    }
    let d = |x: [f64; 2]| Direction::from_degrees(x[0], x[1]).vector();
    let (l, v) = (d(h.lights_deg[light]), d(h.views_deg[view]));
    let params = &g.blocks[0];
    out.par_chunks_mut(3).enumerate().for_each(|(t, px)| {
        let (lt, vt) = match &geometry {
            Some(ge) => ge.texel_dirs(l, v, t, w, ht),
            None => (l, v),
        };
        let f = eval(&params[t * np..(t + 1) * np], lobes, lt, vt);
        let u = ((t % w) as f64 + 0.5) / w as f64 - 0.5;
        let y = ((t / w) as f64 + 0.5) / ht as f64 - 0.5;
        for c in 0..3 {
            let k = gain[c * 3] as f64 + gain[c * 3 + 1] as f64 * u + gain[c * 3 + 2] as f64 * y;
            px[c] = (f[c] * k) as f32;
        }
    });
    out
}

/// The per-texel Lafortune SVBRDF in the registry (`super::registry`): decoded here,
/// written by `gonio fit` ([`encode`]), never by `gonio compress`.
pub struct SvbrdfCodec;

impl Codec for SvbrdfCodec {
    fn id(&self) -> CodecId {
        CodecId::Svbrdf
    }
    fn ladder(&self, _: &Knobs) -> Vec<Vec<Params>> {
        Vec::new()
    }
    fn shard(&self, _: &Knobs) -> Shard {
        Shard::No
    }
    fn encode(&self, _: &DatasetViews, _: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
        Err(CompressError::Invalid(
            "svbrdf: the per-texel Lafortune SVBRDF is fitted by `gonio fit DATASET --model lafortune \
             --per-texel --out F.gbtf`, not by gonio compress"
                .into(),
        ))
    }
    fn open(&self, g: &Gbtf) -> Result<Opened, CompressError> {
        let (lobes, geometry) = validate(g)?;
        Ok(Opened {
            method: Method::Svbrdf { lobes },
            components: params_per_texel(lobes),
            layout: Layout::AnalyticPerTexel,
            decoder: Arc::new(Decoder { lobes, geometry }),
        })
    }
}

/// [`reconstruct`] with the file's lobes and geometry.
#[derive(Debug)]
struct Decoder {
    lobes: usize,
    geometry: Option<Geometry>,
}

impl Decode for Decoder {
    fn reconstruct(&self, g: &Gbtf, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        Ok(reconstruct(g, self.lobes, self.geometry, light, view))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use gonio_brdf::{BrdfModel, LafortuneLobe};

    /// The decoder's formula is the material library's Lafortune model, at random
    /// parameters (including a switched-off lobe and a retro-reflective one) and directions
    /// on both sides of the horizon.
    #[test]
    fn eval_matches_the_material_library() {
        let mut z = 0x1234_5678u64;
        let mut r = || {
            z ^= z << 13;
            z ^= z >> 7;
            z ^= z << 17;
            (z % 1_000_000) as f64 / 1_000_000.0
        };
        let mut worst = 0f64;
        for case in 0..400 {
            let lobes = 1 + case % 3;
            let mut p = vec![(0.5 * r()) as f32, (0.5 * r()) as f32, (0.5 * r()) as f32];
            for j in 0..lobes {
                let off = case % 7 == 0 && j == 1;
                p.extend([
                    (PI * r()) as f32,
                    (0.1 + 200.0 * r() * r()) as f32,
                    if off { 0.0 } else { r() as f32 },
                    if off { 0.0 } else { r() as f32 },
                    if off { 0.0 } else { (0.3 * r()) as f32 },
                ]);
            }
            let lib = BrdfModel::Lafortune {
                kd: [p[0] as f64, p[1] as f64, p[2] as f64],
                lobes: (0..lobes)
                    .map(|j| {
                        let o = 3 + PER_LOBE * j;
                        let g = p[o] as f64;
                        LafortuneLobe {
                            c: [SQRT_2 * g.cos(), SQRT_2 * g.cos(), SQRT_2 * g.sin()],
                            exponent: p[o + 1] as f64,
                            ks: [p[o + 2] as f64, p[o + 3] as f64, p[o + 4] as f64],
                        }
                    })
                    .collect(),
            };
            let dir = |t: f64, ph: f64| Direction::from_degrees(t, ph).vector();
            let (l, v) = (dir(95.0 * r(), 360.0 * r()), dir(95.0 * r(), 360.0 * r()));
            let (a, b) = (eval(&p, lobes, l, v), lib.eval(l, v));
            for c in 0..3 {
                assert!(a[c].is_finite());
                worst = worst.max((a[c] - b[c]).abs() / b[c].abs().max(1e-12));
            }
        }
        assert!(worst < 1e-12, "relative difference {worst:e}");
    }

    /// Through the container: a file round-trips, decodes finite values, an unfitted
    /// pair (zero gains) decodes to 0; wrong shapes and `gonio compress --method svbrdf`
    /// are refused with what to do.
    #[test]
    fn files_round_trip_and_bad_ones_are_refused() {
        use crate::compress::testdata::{self, hash};
        use crate::compress::{compress, CompressedBtf};
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), |_, _, _, _| 0.1);
        let (t, pairs, np) = (ds.texels(), ds.n_lights() * ds.n_views(), params_per_texel(1));
        let params: Vec<f32> = (0..t * np)
            .map(|i| match i % np {
                3 => 2.3,
                4 => 20.0,
                _ => 0.2 + 0.5 * hash(i, 1),
            })
            .collect();
        let mut gain: Vec<f32> = (0..pairs * 9).map(|i| if i % 3 == 0 { 1.0 } else { 0.01 }).collect();
        gain[..9].fill(0.0);
        let geometry = Some(Geometry {
            camera_distance_mm: 1000.0,
            light_distance_mm: 1200.0,
            size_mm: 60.0,
        });
        let g = encode(&ds, 1, params.clone(), gain.clone(), geometry).unwrap();
        let file = tmp.path().join("s.gbtf");
        g.write(&file).unwrap();
        let back = Gbtf::read(&file).unwrap();
        assert_eq!(back, g);
        let m = CompressedBtf::new(back).unwrap();
        assert_eq!(m.method(), Method::Svbrdf { lobes: 1 });
        assert!(
            m.reconstruct(0, 0).unwrap().iter().all(|x| *x == 0.0),
            "pair 0 has no fit"
        );
        let img = m.reconstruct(1, 0).unwrap();
        assert!(img.iter().all(|x| x.is_finite() && *x > 0.0));
        // Shapes that do not fit are refused naming what is wrong.
        let e = encode(&ds, 1, params[1..].to_vec(), gain.clone(), None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("svbrdf") && e.contains("parameters"), "{e}");
        let mut wrong = g.clone();
        wrong.header.params["method"] = serde_json::json!({"svbrdf": {"lobes": 2}});
        let e = CompressedBtf::new(wrong).unwrap_err().to_string();
        assert!(e.contains("block shapes"), "{e}");
        let e = compress(&ds, &Params::new(Method::Svbrdf { lobes: 1 }, np))
            .unwrap_err()
            .to_string();
        assert!(e.contains("gonio fit"), "{e}");
    }
}
