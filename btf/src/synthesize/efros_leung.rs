//! Pixel-wise non-parametric sampling (Efros & Leung 1999; thesis §6.2.2).
//!
//! The output grows outward from a 3 × 3 seed copied from a random exemplar position to
//! the output's centre. In each round the unfilled texels that touch a filled one are
//! visited, those with more filled 8-neighbours first (ties in raster order). For each,
//! the window of `window × window` texels around it is compared with the window around
//! every exemplar texel whose window lies inside the exemplar: the distance is the
//! Gaussian-weighted (σ = window / 6.4) mean squared feature difference over the
//! window's **already filled** texels (thesis eq. 77/78). Every exemplar texel within
//! `(1 + ε)` of the best distance (ε = 0.1, eq. 78) is a candidate and one is drawn at
//! random. No error threshold can reject all candidates, so the search ends after one
//! pass per texel (the original's retry-with-larger-threshold loop is not needed).
//!
//! Cost: texels × exemplar positions × filled window texels × features; the exhaustive
//! search is the method's point, and why the thesis measured hours.

use super::{FeatureImage, SplitMix64, SynthError, SynthParams, TexelMap};
use rayon::prelude::*;

pub fn check(ex: &FeatureImage, p: &SynthParams) -> Result<(), SynthError> {
    if p.window < 3 || p.window.is_multiple_of(2) || p.window > ex.width.min(ex.height) {
        return Err(SynthError::Invalid(format!(
            "--window {}: the Efros–Leung window must be odd, ≥ 3 and fit the {}×{} exemplar",
            p.window, ex.width, ex.height
        )));
    }
    if !(p.epsilon.is_finite() && p.epsilon >= 0.0) {
        return Err(SynthError::Invalid(format!(
            "--epsilon {}: must be a finite number ≥ 0",
            p.epsilon
        )));
    }
    Ok(())
}

pub fn synthesize(ex: &FeatureImage, p: &SynthParams) -> Result<TexelMap, SynthError> {
    check(ex, p)?;
    let (w, h, k) = (ex.width, ex.height, ex.dims);
    let (ow, oh) = (p.width, p.height);
    let hw = p.window / 2;
    let sigma = p.window as f64 / 6.4;
    let gauss = |dx: isize, dy: isize| (-((dx * dx + dy * dy) as f64) / (2.0 * sigma * sigma)).exp();
    let mut rng = SplitMix64::new(p.seed);
    let mut map = vec![u32::MAX; ow * oh];
    // Seed: a 3 × 3 exemplar patch at the output's centre.
    let (sx, sy) = (rng.below(w - 2), rng.below(h - 2));
    let (cx, cy) = (ow / 2 - 1, oh / 2 - 1);
    for dy in 0..3 {
        for dx in 0..3 {
            map[(cy + dy) * ow + cx + dx] = ((sy + dy) * w + sx + dx) as u32;
        }
    }
    let (ccw, cch) = (w - 2 * hw, h - 2 * hw);
    let filled_neighbours = |map: &[u32], x: usize, y: usize| -> usize {
        let mut n = 0;
        for dy in -1isize..=1 {
            for dx in -1isize..=1 {
                let (nx, ny) = (x as isize + dx, y as isize + dy);
                if (dx, dy) != (0, 0)
                    && nx >= 0
                    && ny >= 0
                    && (nx as usize) < ow
                    && (ny as usize) < oh
                    && map[ny as usize * ow + nx as usize] != u32::MAX
                {
                    n += 1;
                }
            }
        }
        n
    };
    let mut dist = vec![0f64; ccw * cch];
    let mut remaining = ow * oh - 9;
    while remaining > 0 {
        let mut front: Vec<(usize, usize)> = Vec::new();
        for y in 0..oh {
            for x in 0..ow {
                if map[y * ow + x] == u32::MAX {
                    let n = filled_neighbours(&map, x, y);
                    if n > 0 {
                        front.push((n, y * ow + x));
                    }
                }
            }
        }
        front.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
        for &(_, t) in &front {
            let (x, y) = (t % ow, t / ow);
            // The filled texels of the window: offset, weight, features.
            let mut known: Vec<(isize, isize, f64, &[f32])> = Vec::new();
            for dy in -(hw as isize)..=hw as isize {
                for dx in -(hw as isize)..=hw as isize {
                    let (nx, ny) = (x as isize + dx, y as isize + dy);
                    if nx < 0 || ny < 0 || nx as usize >= ow || ny as usize >= oh {
                        continue;
                    }
                    let s = map[ny as usize * ow + nx as usize];
                    if s != u32::MAX {
                        known.push((dx, dy, gauss(dx, dy), ex.texel(s as usize)));
                    }
                }
            }
            let wsum: f64 = known.iter().map(|k| k.2).sum();
            dist.par_chunks_mut(ccw).enumerate().for_each(|(j, row)| {
                let cy = j + hw;
                row.iter_mut().for_each(|d| *d = 0.0);
                for &(dx, dy, g, o) in &known {
                    let ry = (cy as isize + dy) as usize;
                    let base = ry * w;
                    for (i, d) in row.iter_mut().enumerate() {
                        let rx = (i + hw) as isize + dx;
                        let s = &ex.data[(base + rx as usize) * k..(base + rx as usize + 1) * k];
                        let mut e = 0f32;
                        for c in 0..k {
                            let u = o[c] - s[c];
                            e += u * u;
                        }
                        *d += g * e as f64;
                    }
                }
                row.iter_mut().for_each(|d| *d /= wsum);
            });
            let dmin = dist.iter().copied().fold(f64::INFINITY, f64::min);
            let limit = dmin * (1.0 + p.epsilon) + 1e-12 * dmin.abs() + f64::MIN_POSITIVE;
            let accepted: Vec<usize> = (0..dist.len()).filter(|&i| dist[i] <= limit).collect();
            let c = accepted[rng.below(accepted.len())];
            let (px, py) = (c % ccw + hw, c / ccw + hw);
            map[t] = (py * w + px) as u32;
            remaining -= 1;
        }
    }
    Ok(TexelMap {
        width: ow,
        height: oh,
        src_width: w,
        src_height: h,
        src: map,
    })
}

#[cfg(test)]
mod tests {
    use super::super::{synthesize as run, testutil, SynthMethod, SynthParams};

    #[test]
    fn fills_everything_deterministically() {
        let ex = testutil::blobs(16, 14, 2);
        let mut p = SynthParams::new(SynthMethod::EfrosLeung, 22, 19, 16, 14);
        p.window = 5;
        let a = run(&ex, &p).unwrap();
        assert!(a.src.iter().all(|&s| (s as usize) < 16 * 14));
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        assert_eq!(pool.install(|| run(&ex, &p).unwrap()), a);
    }

    #[test]
    fn uniform_and_single_bright_exemplars_work() {
        for ex in [testutil::uniform(12, 12), testutil::single_bright(12, 12)] {
            let mut p = SynthParams::new(SynthMethod::EfrosLeung, 16, 14, 12, 12);
            p.window = 5;
            let m = run(&ex, &p).unwrap();
            assert_eq!(m.src.len(), 16 * 14);
        }
    }

    #[test]
    fn epsilon_zero_copies_an_exactly_matching_continuation() {
        // A periodic exemplar of distinct values: with ε = 0 every texel continues the
        // seed's period.
        let mut ex = testutil::blobs(16, 16, 1);
        for t in 0..256 {
            let (x, y) = (t % 16, t / 16);
            ex.data[t * 2] = ((x % 4) * 4 + y % 4) as f32;
            ex.data[t * 2 + 1] = 0.0;
        }
        let mut p = SynthParams::new(SynthMethod::EfrosLeung, 20, 18, 16, 16);
        p.window = 5;
        p.epsilon = 0.0;
        let m = run(&ex, &p).unwrap();
        let (ax, ay) = m.source_xy(8 * 20 + 9);
        for t in 0..m.src.len() {
            let (x, y) = (t % 20, t / 20);
            let (sx, sy) = m.source_xy(t);
            assert_eq!(
                ((sx + 40 - ax) % 4, (sy + 40 - ay) % 4),
                ((x + 40 - 9) % 4, (y + 40 - 8) % 4)
            );
        }
    }
}
