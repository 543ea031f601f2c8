//! Reconstruction at any (light, view) pair, including directions between measured ones.
//!
//! **Scheme.** Light and view are interpolated separately (the BTF is sampled on a product
//! grid) and the weights multiply: up to 3 lights × 3 views = 9 grid pairs. For one
//! direction `q` on the hemisphere the weights are **barycentric coordinates in a
//! spherical triangle of measured directions that contains `q`**: the 8 measured
//! directions nearest to `q` are projected gnomonically onto the tangent plane at `q`
//! (great circles map to straight lines, so "the plane triangle contains the origin" is
//! exactly "the spherical triangle contains `q`"), every triangle of them that contains the
//! origin is a candidate, and the most local one (smallest sum of squared projected
//! distances) wins. Why this and not inverse-distance weighting: it reproduces a BTF that
//! varies linearly over the tangent plane exactly, it is exact at measured directions
//! (weight 1, tested), and only 3 directions contribute, so highlights are not smeared
//! over a whole neighbourhood. Why not a global Delaunay triangulation: the Bonn grid's
//! rings are cocircular in every azimuthal projection, which makes a Delaunay
//! triangulation degenerate and its construction fragile; a local containing triangle needs
//! no global consistency. Outside the convex hull of the measured directions (e.g. θ beyond
//! the grid's last ring) `q` is clamped to the nearest hull edge of its neighbours (two
//! weights). Directions farther than [`MAX_GAP_DEG`] from every measured one are an error.
//!
//! **Cost.** Interpolation happens on the factor rows, not on images: methods whose factors
//! share one texel basis across all measurements (PCA, DFMF) blend the ≤ 9 measurement rows
//! and decode once; PVMF has one basis per view, so it blends the light rows within each of
//! the ≤ 3 views and decodes once per view.

use super::btf_ubo2014;
use super::container::Gbtf;
use super::dfmf::Dfmf;
use super::error::CompressError;
use super::factor::CompressedBtf;
use super::params::Layout;
use serde::Serialize;
use std::path::Path;

/// Measured directions farther than this from the query are not used for interpolation.
pub const MAX_GAP_DEG: f64 = 30.0;

/// Exactness tolerance: a query within this angle of a measured direction uses it alone.
pub const SAME_DEG: f64 = 0.01;

/// Neighbours considered when looking for a containing triangle.
const NEIGHBOURS: usize = 8;

/// A compressed BTF that can decode grid pairs.
pub trait BtfModel {
    fn width(&self) -> usize;
    fn height(&self) -> usize;
    fn lights_deg(&self) -> &[[f64; 2]];
    fn views_deg(&self) -> &[[f64; 2]];
    /// Linear RGB image (interleaved, top row first) of grid pair (`light`, `view`).
    fn reconstruct(&self, light: usize, view: usize) -> Result<Vec<f32>, CompressError>;
    /// `Σ w · image(light, view)`. The default blends decoded images; methods override it
    /// to blend factor rows and decode once.
    fn reconstruct_weighted(&self, weights: &[(usize, usize, f32)]) -> Result<Vec<f32>, CompressError> {
        let mut out = vec![0f32; self.width() * self.height() * 3];
        for &(l, v, w) in weights {
            for (o, x) in out.iter_mut().zip(self.reconstruct(l, v)?) {
                *o += w * x;
            }
        }
        Ok(out)
    }
    /// The model as `Any`, for callers with a faster path for one concrete type (the
    /// viewer reads PCA/PVMF factors texel by texel). `None`: no such path.
    fn as_any(&self) -> Option<&dyn std::any::Any> {
        None
    }
}

impl BtfModel for Dfmf {
    fn width(&self) -> usize {
        self.width
    }
    fn height(&self) -> usize {
        self.height
    }
    fn lights_deg(&self) -> &[[f64; 2]] {
        &self.lights_deg
    }
    fn views_deg(&self) -> &[[f64; 2]] {
        &self.views_deg
    }
    fn reconstruct(&self, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        Dfmf::reconstruct(self, light, view)
    }
    fn reconstruct_weighted(&self, weights: &[(usize, usize, f32)]) -> Result<Vec<f32>, CompressError> {
        Dfmf::reconstruct_weighted(self, weights)
    }
}

/// `Σ_j u[j] · basis[t, j]` for every texel, 3 channels from 3 rows of `u`.
fn decode3(basis: &[f32], c: usize, u: &[[f32; 64]; 3], out: &mut [f32], scale: f32) {
    for (px, row) in out.chunks_exact_mut(3).zip(basis.chunks_exact(c)) {
        let (mut a, mut b, mut d) = (0f32, 0f32, 0f32);
        for j in 0..c {
            a += row[j] * u[0][j];
            b += row[j] * u[1][j];
            d += row[j] * u[2][j];
        }
        px[0] += scale * a;
        px[1] += scale * b;
        px[2] += scale * d;
    }
}

impl BtfModel for CompressedBtf {
    fn width(&self) -> usize {
        self.header().width
    }
    fn height(&self) -> usize {
        self.header().height
    }
    fn lights_deg(&self) -> &[[f64; 2]] {
        &self.header().lights_deg
    }
    fn views_deg(&self) -> &[[f64; 2]] {
        &self.header().views_deg
    }
    fn reconstruct(&self, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        CompressedBtf::reconstruct(self, light, view)
    }
    fn as_any(&self) -> Option<&dyn std::any::Any> {
        Some(self)
    }
    fn reconstruct_weighted(&self, weights: &[(usize, usize, f32)]) -> Result<Vec<f32>, CompressError> {
        let (nl, nv, c) = (self.lights_deg().len(), self.views_deg().len(), self.components());
        if weights.iter().any(|&(l, v, _)| l >= nl || v >= nv) {
            return Err(CompressError::Invalid(format!(
                "a pair of {weights:?} is outside the {nl} × {nv} grid"
            )));
        }
        // Row-blending needs the PCA/PVMF block layout; other layouts blend images.
        if c > 64 || !self.layout().has_bases() {
            let mut out = vec![0f32; self.width() * self.height() * 3];
            for &(l, v, w) in weights {
                for (o, x) in out.iter_mut().zip(CompressedBtf::reconstruct(self, l, v)?) {
                    *o += w * x;
                }
            }
            return Ok(out);
        }
        let blocks = &self.gbtf.blocks;
        let mut out = vec![0f32; self.width() * self.height() * 3];
        let blend = |vblock: &[f32], rows: &mut dyn Iterator<Item = (usize, f32)>| {
            let mut u = [[0f32; 64]; 3];
            for (r, w) in rows {
                for (ch, uc) in u.iter_mut().enumerate() {
                    for (a, b) in uc.iter_mut().zip(&vblock[(r * 3 + ch) * c..(r * 3 + ch + 1) * c]) {
                        *a += w * b;
                    }
                }
            }
            u
        };
        if self.layout() == Layout::Basis {
            let u = blend(&blocks[1], &mut weights.iter().map(|&(l, v, w)| (v * nl + l, w)));
            decode3(&blocks[0], c, &u, &mut out, 1.0);
        } else {
            let mut views: Vec<usize> = weights.iter().map(|w| w.1).collect();
            views.sort_unstable();
            views.dedup();
            for v in views {
                let u = blend(
                    &blocks[2 * v + 1],
                    &mut weights.iter().filter(|w| w.1 == v).map(|&(l, _, w)| (l, w)),
                );
                decode3(&blocks[2 * v], c, &u, &mut out, 1.0);
            }
        }
        Ok(out)
    }
}

/// A compressed file of either kind, opened by its signature.
// One value per opened file, never in a collection: the size difference costs nothing.
#[allow(clippy::large_enum_variant)]
pub enum AnyModel {
    Gbtf(CompressedBtf),
    Dfmf(Dfmf),
}

impl AnyModel {
    /// Open a `.gbtf` or a UBO2014 DFMF `.btf`, whichever the file's first bytes say.
    pub fn open(path: &Path) -> Result<AnyModel, CompressError> {
        let bytes = std::fs::read(path).map_err(|source| CompressError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        if btf_ubo2014::is_dfmf(&bytes) {
            Ok(AnyModel::Dfmf(btf_ubo2014::from_bytes(&bytes, path)?))
        } else {
            Ok(AnyModel::Gbtf(CompressedBtf::new(Gbtf::from_bytes(&bytes, path)?)?))
        }
    }
    pub fn model(&self) -> &dyn BtfModel {
        match self {
            AnyModel::Gbtf(m) => m,
            AnyModel::Dfmf(m) => m,
        }
    }
}

/// Small vector helpers on `[f64; 3]` (the viewer's renderer uses them too): `unit` turns
/// (θ, φ) in degrees into a unit vector of the sample frame.
pub fn unit(d: [f64; 2]) -> [f64; 3] {
    let (t, p) = (d[0].to_radians(), d[1].to_radians());
    [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
}
pub fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
pub fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
pub fn normalize(a: [f64; 3]) -> [f64; 3] {
    let n = dot(a, a).sqrt();
    a.map(|x| x / n)
}

/// Interpolation weights `(index into list, weight)` of direction `deg` over the measured
/// directions `list` (weights sum to 1). `which` names the direction in errors.
pub fn direction_weights(
    list: &[[f64; 2]],
    deg: [f64; 2],
    which: &'static str,
) -> Result<Vec<(usize, f64)>, CompressError> {
    if !deg[1].is_finite() || !(0.0..=90.0).contains(&deg[0]) {
        return Err(CompressError::Invalid(format!(
            "{which} direction {deg:?}°: θ must be in [0, 90]°"
        )));
    }
    let q = unit(deg);
    let mut near: Vec<(usize, f64)> = list.iter().enumerate().map(|(i, &d)| (i, dot(q, unit(d)))).collect();
    near.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    let Some(&(best, best_dot)) = near.first() else {
        return Err(CompressError::NotMeasured { which, deg });
    };
    let gap = best_dot.clamp(-1.0, 1.0).acos().to_degrees();
    if gap <= SAME_DEG {
        return Ok(vec![(best, 1.0)]);
    }
    let max_cos = MAX_GAP_DEG.to_radians().cos();
    near.retain(|&(_, d)| d >= max_cos);
    near.truncate(NEIGHBOURS);
    if near.is_empty() {
        return Err(CompressError::TooFar {
            which,
            deg,
            gap_deg: gap,
            limit_deg: MAX_GAP_DEG,
        });
    }
    // Tangent basis at q and gnomonic projection (all neighbours have d·q ≥ cos 30° > 0).
    let helper = if q[2].abs() < 0.9 {
        [0.0, 0.0, 1.0]
    } else {
        [1.0, 0.0, 0.0]
    };
    let e1 = normalize(cross(helper, q));
    let e2 = cross(q, e1);
    let p: Vec<[f64; 2]> = near
        .iter()
        .map(|&(i, dq)| {
            let d = unit(list[i]);
            [dot(d, e1) / dq, dot(d, e2) / dq]
        })
        .collect();
    let r2 = |a: [f64; 2]| a[0] * a[0] + a[1] * a[1];
    let n = p.len();
    let mut best_tri: Option<(f64, [usize; 3], [f64; 3])> = None;
    for i in 0..n {
        for j in i + 1..n {
            for k in j + 1..n {
                let (a, b, c) = (p[i], p[j], p[k]);
                let det = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
                let scale = r2([b[0] - a[0], b[1] - a[1]]).max(r2([c[0] - a[0], c[1] - a[1]]));
                if det.abs() <= 1e-9 * scale {
                    continue; // degenerate (collinear) triangle
                }
                // Barycentric coordinates of the origin.
                let lb = ((-a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (-a[1])) / det;
                let lc = ((b[0] - a[0]) * (-a[1]) - (-a[0]) * (b[1] - a[1])) / det;
                let la = 1.0 - lb - lc;
                if la < -1e-12 || lb < -1e-12 || lc < -1e-12 {
                    continue;
                }
                let score = r2(a) + r2(b) + r2(c);
                if best_tri.as_ref().is_none_or(|t| score < t.0) {
                    best_tri = Some((score, [i, j, k], [la, lb, lc]));
                }
            }
        }
    }
    if let Some((_, idx, w)) = best_tri {
        return Ok(idx
            .iter()
            .zip(w)
            .filter(|(_, w)| *w > 0.0)
            .map(|(&i, w)| (near[i].0, w.clamp(0.0, 1.0)))
            .collect());
    }
    // Outside the hull of the neighbours: the nearest point on a segment between two.
    let mut best_seg: Option<(f64, usize, usize, f64)> = Some((r2(p[0]), 0, 0, 0.0));
    for i in 0..n {
        for j in i + 1..n {
            let (a, b) = (p[i], p[j]);
            let ab = [b[0] - a[0], b[1] - a[1]];
            let len2 = r2(ab);
            if len2 <= 0.0 {
                continue;
            }
            let s = ((-a[0]) * ab[0] + (-a[1]) * ab[1]) / len2;
            let s = s.clamp(0.0, 1.0);
            let d = r2([a[0] + s * ab[0], a[1] + s * ab[1]]);
            if best_seg.as_ref().is_none_or(|t| d < t.0) {
                best_seg = Some((d, i, j, s));
            }
        }
    }
    let (_, i, j, s) = best_seg.expect("at least one neighbour");
    if i == j || s == 0.0 {
        return Ok(vec![(near[i].0, 1.0)]);
    }
    if s == 1.0 {
        return Ok(vec![(near[j].0, 1.0)]);
    }
    Ok(vec![(near[i].0, 1.0 - s), (near[j].0, s)])
}

/// How a pair was reconstructed.
#[derive(Serialize, Clone, Debug, PartialEq)]
pub struct Interpolation {
    /// `(light index, light direction °, weight)`.
    pub lights: Vec<(usize, [f64; 2], f64)>,
    pub views: Vec<(usize, [f64; 2], f64)>,
    /// True when both directions are measured ones (no interpolation happened).
    pub exact: bool,
}

/// Reconstruct the image at any (light, view) pair of directions in degrees.
pub fn reconstruct_at(
    model: &dyn BtfModel,
    light_deg: [f64; 2],
    view_deg: [f64; 2],
) -> Result<(Vec<f32>, Interpolation), CompressError> {
    let wl = direction_weights(model.lights_deg(), light_deg, "light")?;
    let wv = direction_weights(model.views_deg(), view_deg, "view")?;
    let mut pairs = Vec::with_capacity(wl.len() * wv.len());
    for &(v, a) in &wv {
        for &(l, b) in &wl {
            pairs.push((l, v, (a * b) as f32));
        }
    }
    let img = model.reconstruct_weighted(&pairs)?;
    let info = Interpolation {
        exact: wl.len() == 1 && wv.len() == 1,
        lights: wl.iter().map(|&(i, w)| (i, model.lights_deg()[i], w)).collect(),
        views: wv.iter().map(|&(i, w)| (i, model.views_deg()[i], w)).collect(),
    };
    Ok((img, info))
}

#[cfg(test)]
mod tests {
    use super::super::dfmf::{self, ColorModel, DfmfParams};
    use super::*;
    use crate::compress::testdata::write_test_dataset;
    use crate::compress::{compress, Method, Params};
    use gonio_acquire::rig::Rig;
    use gonio_devices::rig::RigSpec;
    use gonio_devices::Direction;
    use gonio_simulator::sample::{SampleSpec, DEFAULT_SAMPLE};
    use gonio_simulator::SimOptions;

    fn bonn() -> Vec<[f64; 2]> {
        gonio_dataset::sweep::bonn81()
            .iter()
            .map(|d| [d.theta_deg(), d.phi_deg()])
            .collect()
    }

    #[test]
    fn a_measured_direction_gets_weight_one() {
        let b = bonn();
        for (i, &d) in b.iter().enumerate() {
            assert_eq!(direction_weights(&b, d, "light").unwrap(), vec![(i, 1.0)]);
        }
    }

    /// Barycentric weights in the gnomonic projection reproduce the query: Σ wᵢ dᵢ/(dᵢ·q)
    /// is parallel to q (linear precision on the tangent plane); weights are ≥ 0, sum to 1
    /// and use at most 3 directions, all near the query.
    #[test]
    fn weights_reproduce_the_query_direction() {
        let b = bonn();
        let mut k = 0u64;
        for i in 0..400 {
            k = k.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let th = (k >> 40) as f64 / (1u64 << 24) as f64 * 74.0 + 0.05;
            let ph = (i as f64 * 37.7) % 360.0;
            let q = unit([th, ph]);
            let w = direction_weights(&b, [th, ph], "light").unwrap();
            assert!(!w.is_empty() && w.len() <= 3, "{th},{ph}: {w:?}");
            let sum: f64 = w.iter().map(|x| x.1).sum();
            assert!((sum - 1.0).abs() < 1e-9 && w.iter().all(|x| x.1 >= 0.0), "{w:?}");
            let mut p = [0.0; 3];
            for &(j, wj) in &w {
                let d = unit(b[j]);
                let s = wj / dot(d, q);
                for a in 0..3 {
                    p[a] += s * d[a];
                }
            }
            let c = cross(normalize(p), q);
            assert!(
                dot(c, c).sqrt() < 1e-9,
                "θ {th} φ {ph}: {w:?} misses the query by {c:?}"
            );
            for &(j, _) in &w {
                assert!(
                    dot(unit(b[j]), q).acos().to_degrees() < 20.0,
                    "{th},{ph}: {:?} too far",
                    b[j]
                );
            }
        }
    }

    #[test]
    fn beyond_the_last_ring_clamps_to_the_hull_and_far_away_is_an_error() {
        let b = bonn();
        // θ = 80°: outside the 75° ring, two ring neighbours (or one) carry the weight.
        let w = direction_weights(&b, [80.0, 7.0], "view").unwrap();
        assert!(w.len() <= 2 && w.iter().all(|&(j, _)| b[j][0] == 75.0), "{w:?}");
        let pole_only = [[0.0, 0.0]];
        assert!(matches!(
            direction_weights(&pole_only, [60.0, 0.0], "light"),
            Err(CompressError::TooFar { which: "light", .. })
        ));
        assert!(matches!(
            direction_weights(&b, [95.0, 0.0], "light"),
            Err(CompressError::Invalid(_))
        ));
    }

    #[test]
    fn reconstruction_at_measured_pairs_is_exactly_the_grid_image() {
        let dir = tempfile::tempdir().unwrap();
        let lights = vec![[0.0, 0.0], [30.0, 0.0], [30.0, 120.0], [30.0, 240.0], [60.0, 90.0]];
        let views = vec![[0.0, 0.0], [45.0, 0.0], [45.0, 180.0], [60.0, 270.0]];
        let ds = write_test_dataset(dir.path(), (5, 4), &lights, &views, &[], |l, v, t, c| {
            0.1 + 0.05 * ((l * 3 + v * 7 + t + c) % 11) as f32
        });
        let pvmf = CompressedBtf::new(compress(&ds, &Params::new(Method::Pvmf, 3)).unwrap().0).unwrap();
        let pca = CompressedBtf::new(compress(&ds, &Params::new(Method::Pca, 4)).unwrap().0).unwrap();
        let dfmf = dfmf::encode(&ds, &DfmfParams::new(ColorModel::LogYuv, 4)).unwrap().0;
        let models: [&dyn BtfModel; 3] = [&pvmf, &pca, &dfmf];
        for m in models {
            for (v, &vd) in views.iter().enumerate() {
                for (l, &ld) in lights.iter().enumerate() {
                    let (img, how) = reconstruct_at(m, ld, vd).unwrap();
                    assert!(how.exact);
                    assert_eq!(img, m.reconstruct(l, v).unwrap(), "light {l} view {v}");
                }
            }
            // Between grid directions the blend is a convex combination of grid images
            // (for row-blending models exactly so for PCA/PVMF: linear in the rows).
            let (img, how) = reconstruct_at(m, [20.0, 30.0], [50.0, 200.0]).unwrap();
            assert!(!how.exact);
            assert_eq!(img.len(), 5 * 4 * 3);
        }
        // PCA and PVMF are linear in their rows: row blending equals image blending.
        for m in [&pvmf as &dyn BtfModel, &pca] {
            let w = [(1usize, 1usize, 0.25f32), (2, 1, 0.5), (0, 2, 0.25)];
            let rows = m.reconstruct_weighted(&w).unwrap();
            let mut imgs = vec![0f32; rows.len()];
            for &(l, v, x) in &w {
                for (o, y) in imgs.iter_mut().zip(m.reconstruct(l, v).unwrap()) {
                    *o += x * y;
                }
            }
            for (a, b) in rows.iter().zip(&imgs) {
                assert!((a - b).abs() < 1e-5, "{a} vs {b}");
            }
        }
    }

    /// The simulator renders the truth at any direction: a coarse grid of truth images is
    /// "measured", stored losslessly (full-rank PVMF), and reconstructed at directions
    /// between the grid's. Barycentric interpolation must beat taking the nearest grid pair.
    #[test]
    fn interpolation_between_grid_directions_beats_nearest_against_the_truth() {
        const S: usize = 16;
        let spec = RigSpec::default_rig();
        let sample = SampleSpec::resolve(DEFAULT_SAMPLE).unwrap();
        let rig = Rig::build(&spec, &sample, &SimOptions::default()).unwrap();
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        rt.block_on(rig.light.set(true, 1.0)).unwrap();
        let truth = rig.truth.clone().unwrap();
        let render = |l: [f64; 2], v: [f64; 2]| -> Option<Vec<f32>> {
            let q = rig
                .kinematics
                .inverse(
                    Direction::from_degrees(l[0], l[1]),
                    Direction::from_degrees(v[0], v[1]),
                    None,
                )
                .ok()?;
            Some(truth.truth(&q[0], S, S).data)
        };
        let mut grid = vec![[0.0, 0.0]];
        for (th, n) in [(20.0, 6), (40.0, 8), (60.0, 10)] {
            for k in 0..n {
                grid.push([th, 360.0 * k as f64 / n as f64]);
            }
        }
        let images: Vec<Vec<Option<Vec<f32>>>> = grid
            .iter()
            .map(|&v| grid.iter().map(|&l| render(l, v)).collect())
            .collect();
        let skip: Vec<(usize, usize)> = (0..grid.len())
            .flat_map(|v| (0..grid.len()).map(move |l| (l, v)))
            .filter(|&(l, v)| images[v][l].is_none())
            .collect();
        let dir = tempfile::tempdir().unwrap();
        let ds = write_test_dataset(dir.path(), (S, S), &grid, &grid, &skip, |l, v, t, c| {
            images[v][l].as_ref().map_or(0.0, |i| i[t * 3 + c])
        });
        let model = CompressedBtf::new(compress(&ds, &Params::new(Method::Pvmf, grid.len() * 3)).unwrap().0).unwrap();
        let (mut e_interp, mut e_near, mut n) = (0.0f64, 0.0f64, 0usize);
        for (l, v) in [
            ([30.0, 25.0], [50.0, 200.0]),
            ([50.0, 100.0], [30.0, 290.0]),
            ([10.0, 60.0], [45.0, 160.0]),
            ([35.0, 340.0], [25.0, 150.0]),
        ] {
            let Some(t) = render(l, v) else { continue };
            let (img, how) = reconstruct_at(&model, l, v).unwrap();
            assert!(!how.exact);
            let near = |list: &[[f64; 2]], d: [f64; 2]| {
                let q = unit(d);
                (0..list.len())
                    .max_by(|&a, &b| dot(unit(list[a]), q).total_cmp(&dot(unit(list[b]), q)))
                    .unwrap()
            };
            let nn = model.reconstruct(near(&grid, l), near(&grid, v)).unwrap();
            let rmse = |a: &[f32]| {
                (a.iter().zip(&t).map(|(x, y)| ((x - y) as f64).powi(2)).sum::<f64>() / t.len() as f64).sqrt()
            };
            eprintln!(
                "light {l:?} view {v:?}: RMSE vs truth interpolated {:.5}, nearest {:.5} (truth mean {:.4})",
                rmse(&img),
                rmse(&nn),
                t.iter().map(|&x| x as f64).sum::<f64>() / t.len() as f64
            );
            e_interp += rmse(&img);
            e_near += rmse(&nn);
            n += 1;
        }
        assert!(n >= 3, "the rig could measure only {n} of the query pairs");
        assert!(
            e_interp < e_near,
            "interpolated {e_interp:.5} vs nearest {e_near:.5} (sum of RMSE)"
        );
    }
}
