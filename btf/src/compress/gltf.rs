//! The per-texel glTF metallic-roughness SVBRDF as a `.gbtf` (method `gltf`): what `gonio
//! fit --per-texel --model gltf --out F.gbtf` writes and `gonio export` turns into glTF,
//! MaterialX, USD and Mitsuba files. Decoded here like every other method, so `gonio
//! reconstruct`, `render`, `view` and `compress::evaluate` read it.
//!
//! **Blocks.**
//! - `params` (texels × [`PARAMS`]): base colour RGB (linear), metallic, roughness
//!   (α = roughness²), the shading normal's tangent-plane components `n_x`, `n_y`
//!   (tangent frame +x = u, +y = v; the layout of `fit::Family` for `gltf`), and the
//!   `KHR_materials_anisotropy` vector `s·(cos 2φ, sin 2φ)` (`gonio_brdf::gltf`; 0 where
//!   the texel is isotropic). Files written before anisotropy have the first
//!   [`PARAMS_ISOTROPIC`] columns only and decode as isotropic.
//! - `gain` (pairs × 9): as in [`super::svbrdf`], per channel the plane that turns a BRDF
//!   value into the dataset's units; all zero for a pair without a fit (decodes to 0).
//! - `quality` (texels × 2): the texel's residual (cosine-weighted relative RMS of the
//!   model against its own measurements) and a flag: 0 fitted, 1 not converged or without
//!   data, its parameters filled from its neighbours. The residual map is where the
//!   SVBRDF fails (mesostructure: shadowing, parallax, interreflection).
//!
//! **Header.** [`Params`] with [`Method::Gltf`] plus `geometry` (as in `svbrdf`).
//!
//! **Decoder.** Per texel and pair `gonio_brdf::gltf::eval` (the one home of the
//! formula) at the texel's directions, times the gain plane.

use super::container::{BlockInfo, Gbtf, GbtfHeader};
use super::data::DatasetViews;
use super::error::CompressError;
use super::params::{header_for, Codec, CodecId, Decode, EncodeInfo, Knobs, Layout, Method, Opened, Params, Shard};
use super::svbrdf::Geometry;
use gonio_devices::Direction;
use rayon::prelude::*;
use std::sync::Arc;

/// Parameters per texel: base colour RGB, metallic, roughness, normal x, normal y,
/// anisotropy x, anisotropy y.
pub const PARAMS: usize = 9;

/// Parameters per texel of a file written before anisotropy (no anisotropy columns).
pub const PARAMS_ISOTROPIC: usize = 7;

/// One texel's material, read from the `params` block.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Texel {
    pub base_color: [f64; 3],
    pub metallic: f64,
    pub roughness: f64,
    pub normal: [f64; 2],
    /// `s·(cos 2φ, sin 2φ)` (`gonio_brdf::gltf::anisotropy_of` gives strength and angle).
    pub anisotropy: [f64; 2],
}

impl Texel {
    /// From a row of [`PARAMS`] (or [`PARAMS_ISOTROPIC`]) values.
    pub fn of(p: &[f32]) -> Texel {
        Texel {
            base_color: [p[0] as f64, p[1] as f64, p[2] as f64],
            metallic: p[3] as f64,
            roughness: p[4] as f64,
            normal: [p[5] as f64, p[6] as f64],
            anisotropy: match p.get(7..9) {
                Some(a) => [a[0] as f64, a[1] as f64],
                None => [0.0, 0.0],
            },
        }
    }
    /// BRDF (1/sr) at unit `l`, `v` (sample frame).
    pub fn eval(&self, l: gonio_devices::Vec3, v: gonio_devices::Vec3) -> [f64; 3] {
        gonio_brdf::gltf::eval(
            &self.base_color,
            self.metallic,
            self.roughness,
            self.normal,
            self.anisotropy,
            l,
            v,
        )
    }
}

/// The `.gbtf` of a per-texel glTF fit of `ds`.
pub fn encode(
    ds: &DatasetViews,
    params: Vec<f32>,
    gain: Vec<f32>,
    quality: Vec<f32>,
    geometry: Option<Geometry>,
) -> Result<Gbtf, CompressError> {
    let (t, pairs) = (ds.texels(), ds.n_lights() * ds.n_views());
    if params.len() != t * PARAMS || gain.len() != pairs * 9 || quality.len() != t * 2 {
        return Err(CompressError::Invalid(format!(
            "gltf: {} parameters, {} gains and {} quality values for {t} texels × {PARAMS}, {pairs} pairs × 9 \
             and {t} texels × 2",
            params.len(),
            gain.len(),
            quality.len()
        )));
    }
    if let Some(i) = params.iter().chain(&gain).chain(&quality).position(|x| !x.is_finite()) {
        return Err(CompressError::Invalid(format!("gltf: value {i} is not finite")));
    }
    let p = Params::new(Method::Gltf, PARAMS);
    let mut header = header_for(
        ds,
        &p,
        Vec::new(),
        vec![
            BlockInfo::new("params", t, PARAMS),
            BlockInfo::new("gain", pairs, 9),
            BlockInfo::new("quality", t, 2),
        ],
    );
    if let Some(o) = header.params.as_object_mut() {
        o.insert(
            "geometry".into(),
            serde_json::to_value(geometry).map_err(|e| CompressError::Invalid(e.to_string()))?,
        );
    }
    Ok(Gbtf {
        header,
        blocks: vec![params, gain, quality],
    })
}

/// Check a glTF SVBRDF file's header and blocks; returns its geometry.
pub fn validate(g: &Gbtf) -> Result<Option<Geometry>, CompressError> {
    let h: &GbtfHeader = &g.header;
    let bad = |r: String| CompressError::Invalid(format!(".gbtf gltf: {r}"));
    let params: Params =
        serde_json::from_value(h.params.clone()).map_err(|e| bad(format!("parameters in the header: {e}")))?;
    if params.method != Method::Gltf {
        return Err(bad(format!("the header's method is {}", params.method.name())));
    }
    let geometry: Option<Geometry> = serde_json::from_value(h.params.get("geometry").cloned().unwrap_or_default())
        .map_err(|e| bad(format!("geometry in the header: {e}")))?;
    if let Some(ge) = geometry {
        let ok = |x: f64| x.is_finite() && x > 0.0;
        if !(ok(ge.camera_distance_mm) && ok(ge.light_distance_mm) && ok(ge.size_mm)) {
            return Err(bad(format!("geometry {ge:?}: distances and size must be positive")));
        }
    }
    let (t, pairs) = (h.width * h.height, h.lights_deg.len() * h.views_deg.len());
    let got: Vec<(usize, usize)> = h.blocks.iter().map(|b| (b.rows, b.cols)).collect();
    let shapes = |np: usize| [(t, np), (pairs, 9), (t, 2)];
    if (got != shapes(PARAMS) && got != shapes(PARAMS_ISOTROPIC)) || h.channels != 3 {
        return Err(bad(format!(
            "block shapes {got:?} do not match {t} texels × {PARAMS} (or {PARAMS_ISOTROPIC}) parameters, {pairs} \
             pairs × 9 gains and {t} texels × 2 quality values"
        )));
    }
    if g.blocks.iter().zip(&h.blocks).any(|(b, i)| b.len() != i.rows * i.cols) {
        return Err(bad("a block's length does not match its shape".into()));
    }
    if let Some(i) = g.blocks.iter().flatten().position(|x| !x.is_finite()) {
        return Err(bad(format!("value {i} is not finite")));
    }
    Ok(geometry)
}

/// Parameters per texel of a file that passed [`validate`]: [`PARAMS`] or
/// [`PARAMS_ISOTROPIC`].
pub fn params_per_texel(g: &Gbtf) -> usize {
    g.header.blocks[0].cols
}

/// Texel `t`'s material of a file that passed [`validate`].
pub fn texel(g: &Gbtf, t: usize) -> Texel {
    let np = params_per_texel(g);
    Texel::of(&g.blocks[0][t * np..(t + 1) * np])
}

/// Image (`light`, `view`) of a file that passed [`validate`]: interleaved linear RGB.
pub fn reconstruct(g: &Gbtf, geometry: Option<Geometry>, light: usize, view: usize) -> Vec<f32> {
    let h = &g.header;
    let (w, ht) = (h.width, h.height);
    let pair = view * h.lights_deg.len() + light;
    let gain = &g.blocks[1][pair * 9..pair * 9 + 9];
    let mut out = vec![0f32; w * ht * 3];
    if gain.iter().all(|x| *x == 0.0) {
        return out;
    }
    let d = |x: [f64; 2]| Direction::from_degrees(x[0], x[1]).vector();
    let (l, v) = (d(h.lights_deg[light]), d(h.views_deg[view]));
    out.par_chunks_mut(3).enumerate().for_each(|(t, px)| {
        let (lt, vt) = match &geometry {
            Some(ge) => ge.texel_dirs(l, v, t, w, ht),
            None => (l, v),
        };
        let f = texel(g, t).eval(lt, vt);
        let u = ((t % w) as f64 + 0.5) / w as f64 - 0.5;
        let y = ((t / w) as f64 + 0.5) / ht as f64 - 0.5;
        for c in 0..3 {
            let k = gain[c * 3] as f64 + gain[c * 3 + 1] as f64 * u + gain[c * 3 + 2] as f64 * y;
            px[c] = (f[c] * k) as f32;
        }
    });
    out
}

/// The per-texel glTF SVBRDF in the registry (`super::registry`): decoded here, written by
/// `gonio fit` ([`encode`]), never by `gonio compress`.
pub struct GltfCodec;

impl Codec for GltfCodec {
    fn id(&self) -> CodecId {
        CodecId::Gltf
    }
    fn ladder(&self, _: &Knobs) -> Vec<Vec<Params>> {
        Vec::new()
    }
    fn shard(&self, _: &Knobs) -> Shard {
        Shard::No
    }
    fn encode(&self, _: &DatasetViews, _: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
        Err(CompressError::Invalid(
            "gltf: the per-texel glTF SVBRDF is fitted by `gonio fit DATASET --model gltf --per-texel --out \
             F.gbtf`, not by gonio compress"
                .into(),
        ))
    }
    fn open(&self, g: &Gbtf) -> Result<Opened, CompressError> {
        let geometry = validate(g)?;
        Ok(Opened {
            method: Method::Gltf,
            components: params_per_texel(g),
            layout: Layout::AnalyticPerTexel,
            decoder: Arc::new(Decoder { geometry }),
        })
    }
}

/// [`reconstruct`] with the file's geometry.
#[derive(Debug)]
struct Decoder {
    geometry: Option<Geometry>,
}

impl Decode for Decoder {
    fn reconstruct(&self, g: &Gbtf, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        Ok(reconstruct(g, self.geometry, light, view))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compress::testdata::{self, hash};
    use crate::compress::CompressedBtf;

    /// A file round-trips through the container and decodes to the library's formula
    /// times the gain; an unfitted pair decodes to 0; wrong shapes and a NaN are refused.
    #[test]
    fn files_round_trip_decode_the_library_formula_and_bad_ones_are_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = testdata::write(&tmp.path().join("ds"), |_, _, _, _| 0.1);
        let (t, pairs) = (ds.texels(), ds.n_lights() * ds.n_views());
        let params: Vec<f32> = (0..t * PARAMS)
            .map(|i| match i % PARAMS {
                3 => hash(i, 2),
                4 => 0.2 + 0.6 * hash(i, 3),
                5 | 6 => 0.2 * (hash(i, 4) - 0.5),
                7 | 8 => 0.6 * (hash(i, 5) - 0.5),
                _ => 0.1 + 0.8 * hash(i, 1),
            })
            .collect();
        let mut gain: Vec<f32> = (0..pairs * 9).map(|i| if i % 3 == 0 { 2.0 } else { 0.0 }).collect();
        gain[..9].fill(0.0);
        let quality = vec![0.0; t * 2];
        let g = encode(&ds, params.clone(), gain.clone(), quality.clone(), None).unwrap();
        let file = tmp.path().join("m.gbtf");
        g.write(&file).unwrap();
        let back = Gbtf::read(&file).unwrap();
        assert_eq!(back, g);
        let m = CompressedBtf::new(back).unwrap();
        assert_eq!(m.method(), Method::Gltf);
        assert!(m.reconstruct(0, 0).unwrap().iter().all(|x| *x == 0.0));
        let (light, view) = (1, 0);
        let img = m.reconstruct(light, view).unwrap();
        let h = &g.header;
        let d = |x: [f64; 2]| Direction::from_degrees(x[0], x[1]).vector();
        let (l, v) = (d(h.lights_deg[light]), d(h.views_deg[view]));
        for tx in [0, t / 2, t - 1] {
            let p = &params[tx * PARAMS..(tx + 1) * PARAMS];
            let want = gonio_brdf::BrdfModel::Gltf {
                base_color: [p[0] as f64, p[1] as f64, p[2] as f64],
                metallic: p[3] as f64,
                roughness: p[4] as f64,
                normal: [p[5] as f64, p[6] as f64],
                anisotropy_strength: gonio_brdf::gltf::anisotropy_of([p[7] as f64, p[8] as f64]).0,
                anisotropy_rotation: gonio_brdf::gltf::anisotropy_of([p[7] as f64, p[8] as f64]).1,
            }
            .eval(l, v);
            for c in 0..3 {
                let got = img[3 * tx + c] as f64;
                assert!(
                    (got - 2.0 * want[c]).abs() <= 1e-5 * want[c].max(1e-6),
                    "{got} {want:?}"
                );
            }
        }
        let e = encode(&ds, params[1..].to_vec(), gain.clone(), quality.clone(), None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("gltf") && e.contains("parameters"), "{e}");
        let mut nan = params.clone();
        nan[5] = f32::NAN;
        let e = encode(&ds, nan, gain, quality, None).unwrap_err().to_string();
        assert!(e.contains("not finite"), "{e}");
        let mut wrong = g.clone();
        wrong.header.blocks.pop();
        wrong.blocks.pop();
        let e = CompressedBtf::new(wrong).unwrap_err().to_string();
        assert!(e.contains("block shapes"), "{e}");
    }
}
