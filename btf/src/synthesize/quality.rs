//! Quality of a synthesis, which has no pixel truth (issue 18's measures):
//!
//! * [`seams`]: the mean ABRDF difference between output neighbours that were **not**
//!   neighbours in the exemplar (block boundaries, pixel-wise jumps), against the
//!   exemplar's own mean neighbour difference. 1 means a seam is no more visible than an
//!   ordinary step in the material.
//! * [`repetition`]: the largest region copied verbatim (a 4-connected set of output
//!   texels with one common exemplar offset), as a fraction of the output, and how often
//!   exemplar texels are reused.
//! * [`sliced_wasserstein`]: distance between two sets of feature vectors (ABRDF samples
//!   of the output and of a reference of the same material), the mean over random
//!   directions of the 2-Wasserstein distance of the projections.
//! * [`ImageStats`]: local statistics of one (light, view) image: luminance quantiles
//!   and filter-response energies (gradient and Laplacian at two scales).

use super::{FeatureImage, SplitMix64, TexelMap};
use serde::Serialize;

#[derive(Serialize, Clone, Debug, PartialEq)]
pub struct Seams {
    /// Fraction of adjacent output pairs that are not adjacent in the exemplar.
    pub seam_pair_fraction: f64,
    /// Mean ABRDF (embedding) distance across those pairs.
    pub seam_mean: f64,
    /// Mean distance between adjacent exemplar texels.
    pub exemplar_mean: f64,
    /// `seam_mean / exemplar_mean` (0 when there is no seam).
    pub ratio: f64,
}

fn dist(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(&x, &y)| (x as f64 - y as f64).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// Is output texel `q` (a neighbour of `p` at offset (dx, dy)) the verbatim continuation
/// of `p`'s source?
#[inline]
fn continues(map: &TexelMap, p: usize, q: usize, dx: usize, dy: usize) -> bool {
    let (ax, ay) = map.source_xy(p);
    let (bx, by) = map.source_xy(q);
    bx == ax + dx && by == ay + dy
}

pub fn seams(map: &TexelMap, emb: &FeatureImage) -> Seams {
    let (mut ex_sum, mut ex_n) = (0f64, 0usize);
    for y in 0..emb.height {
        for x in 0..emb.width {
            if x + 1 < emb.width {
                ex_sum += dist(emb.px(x, y), emb.px(x + 1, y));
                ex_n += 1;
            }
            if y + 1 < emb.height {
                ex_sum += dist(emb.px(x, y), emb.px(x, y + 1));
                ex_n += 1;
            }
        }
    }
    let (mut s_sum, mut s_n, mut all) = (0f64, 0usize, 0usize);
    let w = map.width;
    for y in 0..map.height {
        for x in 0..w {
            let p = y * w + x;
            for (q, dx, dy, ok) in [(p + 1, 1, 0, x + 1 < w), (p + w, 0, 1, y + 1 < map.height)] {
                if !ok {
                    continue;
                }
                all += 1;
                if !continues(map, p, q, dx, dy) {
                    s_sum += dist(emb.texel(map.src[p] as usize), emb.texel(map.src[q] as usize));
                    s_n += 1;
                }
            }
        }
    }
    let exemplar_mean = ex_sum / ex_n.max(1) as f64;
    let seam_mean = s_sum / s_n.max(1) as f64;
    Seams {
        seam_pair_fraction: s_n as f64 / all.max(1) as f64,
        seam_mean,
        exemplar_mean,
        ratio: if exemplar_mean > 0.0 {
            seam_mean / exemplar_mean
        } else {
            0.0
        },
    }
}

#[derive(Serialize, Clone, Debug, PartialEq)]
pub struct Repetition {
    /// Texels of the largest verbatim-copied region.
    pub largest_copy_texels: usize,
    /// ... as a fraction of the output.
    pub largest_copy_fraction: f64,
    /// ... as a fraction of the exemplar's area.
    pub largest_copy_of_exemplar: f64,
    /// Uses of the most used exemplar texel.
    pub reuse_max: u32,
    /// Mean uses per exemplar texel (output area / exemplar area).
    pub reuse_mean: f64,
    /// Coefficient of variation of the use counts (0: every texel used equally often).
    pub reuse_cv: f64,
    /// Fraction of exemplar texels never used.
    pub unused_fraction: f64,
}

pub fn repetition(map: &TexelMap) -> Repetition {
    let (w, h) = (map.width, map.height);
    let n = w * h;
    // Union-find over "continues" links.
    let mut parent: Vec<u32> = (0..n as u32).collect();
    fn find(p: &mut [u32], mut i: u32) -> u32 {
        while p[i as usize] != i {
            p[i as usize] = p[p[i as usize] as usize];
            i = p[i as usize];
        }
        i
    }
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            for (q, dx, dy, ok) in [(p + 1, 1, 0, x + 1 < w), (p + w, 0, 1, y + 1 < h)] {
                if ok && continues(map, p, q, dx, dy) {
                    let (a, b) = (find(&mut parent, p as u32), find(&mut parent, q as u32));
                    if a != b {
                        parent[a.max(b) as usize] = a.min(b);
                    }
                }
            }
        }
    }
    let mut size = vec![0u32; n];
    for i in 0..n {
        let r = find(&mut parent, i as u32);
        size[r as usize] += 1;
    }
    let largest = size.iter().copied().max().unwrap_or(0) as usize;
    let ne = map.src_width * map.src_height;
    let mut uses = vec![0u32; ne];
    for &s in &map.src {
        uses[s as usize] += 1;
    }
    let mean = n as f64 / ne as f64;
    let var = uses.iter().map(|&u| (u as f64 - mean).powi(2)).sum::<f64>() / ne as f64;
    Repetition {
        largest_copy_texels: largest,
        largest_copy_fraction: largest as f64 / n as f64,
        largest_copy_of_exemplar: largest as f64 / ne as f64,
        reuse_max: uses.iter().copied().max().unwrap_or(0),
        reuse_mean: mean,
        reuse_cv: if mean > 0.0 { var.sqrt() / mean } else { 0.0 },
        unused_fraction: uses.iter().filter(|&&u| u == 0).count() as f64 / ne as f64,
    }
}

/// Quantile `q ∈ [0, 1]` of sorted values (linear interpolation).
fn quantile(sorted: &[f64], q: f64) -> f64 {
    let x = q * (sorted.len() - 1) as f64;
    let i = x.floor() as usize;
    let f = x - i as f64;
    if i + 1 < sorted.len() {
        sorted[i] * (1.0 - f) + sorted[i + 1] * f
    } else {
        sorted[i]
    }
}

/// 2-Wasserstein distance between two 1D samples (compared at 1024 quantiles).
pub fn wasserstein_1d(a: &mut [f64], b: &mut [f64]) -> f64 {
    if a.is_empty() || b.is_empty() {
        return 0.0;
    }
    a.sort_by(f64::total_cmp);
    b.sort_by(f64::total_cmp);
    const Q: usize = 1024;
    let mut s = 0.0;
    for i in 0..Q {
        let q = (i as f64 + 0.5) / Q as f64;
        s += (quantile(a, q) - quantile(b, q)).powi(2);
    }
    (s / Q as f64).sqrt()
}

/// Sliced 2-Wasserstein distance between row sets `a` and `b` (`dims` values per row),
/// over `projections` random unit directions drawn from `seed`: the root mean square of
/// the 1D distances.
pub fn sliced_wasserstein(a: &[f32], b: &[f32], dims: usize, projections: usize, seed: u64) -> f64 {
    let mut rng = SplitMix64::new(seed);
    let mut total = 0.0;
    for _ in 0..projections {
        // Gaussian direction (Box–Muller), normalized.
        let mut dir: Vec<f64> = (0..dims)
            .map(|_| {
                let (u1, u2) = (rng.unit().max(1e-300), rng.unit());
                (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
            })
            .collect();
        let n = dir.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-300);
        dir.iter_mut().for_each(|v| *v /= n);
        let proj = |x: &[f32]| -> Vec<f64> {
            x.chunks_exact(dims)
                .map(|r| r.iter().zip(&dir).map(|(&v, &d)| v as f64 * d).sum())
                .collect()
        };
        let (mut pa, mut pb) = (proj(a), proj(b));
        total += wasserstein_1d(&mut pa, &mut pb).powi(2);
    }
    (total / projections.max(1) as f64).sqrt()
}

/// Local statistics of one linear RGB image.
#[derive(Serialize, Clone, Debug, PartialEq)]
pub struct ImageStats {
    /// Luminance at the 1st, 5th, 10th, …, 95th, 99th percentiles (21 values).
    pub luminance_quantiles: Vec<f64>,
    /// Mean squared luminance gradient at scale 1 and 2 (2 × 2 box-downsampled).
    pub gradient_energy: [f64; 2],
    /// Mean squared Laplacian at scale 1 and 2.
    pub laplacian_energy: [f64; 2],
}

fn luminance(rgb: &[f32]) -> Vec<f64> {
    rgb.chunks_exact(3)
        .map(|p| 0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64)
        .collect()
}

fn energies(l: &[f64], w: usize, h: usize) -> (f64, f64) {
    let (mut g, mut lap, mut n) = (0.0, 0.0, 0usize);
    for y in 1..h.saturating_sub(1) {
        for x in 1..w.saturating_sub(1) {
            let c = l[y * w + x];
            let (gx, gy) = (l[y * w + x + 1] - c, l[(y + 1) * w + x] - c);
            g += gx * gx + gy * gy;
            let lp = l[y * w + x - 1] + l[y * w + x + 1] + l[(y - 1) * w + x] + l[(y + 1) * w + x] - 4.0 * c;
            lap += lp * lp;
            n += 1;
        }
    }
    (g / n.max(1) as f64, lap / n.max(1) as f64)
}

impl ImageStats {
    pub fn of(rgb: &[f32], w: usize, h: usize) -> ImageStats {
        let l = luminance(rgb);
        let mut sorted = l.clone();
        sorted.sort_by(f64::total_cmp);
        let qs: Vec<f64> = std::iter::once(0.01)
            .chain((1..=19).map(|i| 0.05 * i as f64))
            .chain(std::iter::once(0.99))
            .map(|q: f64| quantile(&sorted, q.min(1.0)))
            .collect();
        let (g1, l1) = energies(&l, w, h);
        let (w2, h2) = (w / 2, h / 2);
        let mut half = vec![0f64; w2 * h2];
        for y in 0..h2 {
            for x in 0..w2 {
                half[y * w2 + x] = 0.25
                    * (l[2 * y * w + 2 * x]
                        + l[2 * y * w + 2 * x + 1]
                        + l[(2 * y + 1) * w + 2 * x]
                        + l[(2 * y + 1) * w + 2 * x + 1]);
            }
        }
        let (g2, l2) = energies(&half, w2, h2);
        ImageStats {
            luminance_quantiles: qs,
            gradient_energy: [g1, g2],
            laplacian_energy: [l1, l2],
        }
    }

    /// Distance to a reference: the RMS of the quantile differences divided by the
    /// reference's mean luminance quantile, plus the mean absolute log-ratio of the four
    /// filter energies (0 = identical statistics).
    pub fn distance(&self, reference: &ImageStats) -> (f64, f64) {
        let n = self.luminance_quantiles.len() as f64;
        let scale = reference.luminance_quantiles.iter().sum::<f64>() / n;
        let q = (self
            .luminance_quantiles
            .iter()
            .zip(&reference.luminance_quantiles)
            .map(|(a, b)| (a - b).powi(2))
            .sum::<f64>()
            / n)
            .sqrt()
            / scale.max(1e-12);
        let e: Vec<(f64, f64)> = self
            .gradient_energy
            .iter()
            .zip(&reference.gradient_energy)
            .chain(self.laplacian_energy.iter().zip(&reference.laplacian_energy))
            .map(|(&a, &b)| (a, b))
            .collect();
        let f = e
            .iter()
            .map(|&(a, b)| ((a.max(1e-30)) / (b.max(1e-30))).ln().abs())
            .sum::<f64>()
            / e.len() as f64;
        (q, f)
    }
}

#[cfg(test)]
mod tests {
    use super::super::{synthesize, testutil, SynthMethod, SynthParams};
    use super::*;

    #[test]
    fn tiling_has_seams_only_at_tile_borders_and_one_tile_copies() {
        let ex = testutil::blobs(10, 8, 1);
        let p = SynthParams::new(SynthMethod::Tile, 25, 16, 10, 8);
        let m = synthesize(&ex, &p).unwrap();
        let s = seams(&m, &ex);
        // Seams: 2 vertical tile borders × 16 rows + 1 horizontal × 25 columns.
        let pairs = 24 * 16 + 25 * 15;
        assert!((s.seam_pair_fraction - (2.0 * 16.0 + 25.0) / pairs as f64).abs() < 1e-12);
        let r = repetition(&m);
        assert_eq!(r.largest_copy_texels, 80);
        assert!((r.reuse_mean - 5.0).abs() < 1e-12);
        assert_eq!(r.unused_fraction, 0.0);
    }

    #[test]
    fn sliced_wasserstein_is_zero_for_equal_sets_and_grows_with_a_shift() {
        let a: Vec<f32> = (0..600).map(|i| ((i * 37) % 101) as f32 / 100.0).collect();
        let mut b = a.clone();
        assert!(sliced_wasserstein(&a, &b, 3, 16, 1) < 1e-12);
        b.iter_mut().for_each(|v| *v += 0.5);
        let d = sliced_wasserstein(&a, &b, 3, 64, 1);
        // A shift by 0.5 in every coordinate: |(0.5, 0.5, 0.5)·u| averaged over directions.
        assert!(d > 0.3 && d < 0.87, "{d}");
    }

    #[test]
    fn image_stats_distance_is_zero_to_itself() {
        let img: Vec<f32> = (0..16 * 12 * 3).map(|i| ((i * 7) % 13) as f32 / 13.0).collect();
        let s = ImageStats::of(&img, 16, 12);
        assert_eq!(s.distance(&s), (0.0, 0.0));
        assert_eq!(s.luminance_quantiles.len(), 21);
    }
}
