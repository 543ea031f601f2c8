//! Image quilting (Efros & Freeman 2001; thesis §6.2.4), on ABRDF feature vectors.
//!
//! Blocks of `block × block` exemplar texels are laid in raster order with `overlap`
//! texels shared with the left and upper neighbours. For each block:
//!
//! 1. **Best-block search.** The squared feature error over the overlap is computed for
//!    *every* exemplar position at once: `Σ_q M(q)·‖O(q) − F(p+q)‖²
//!    = Σ M·‖O‖² + (M ⋆ ‖F‖²)(p) − 2 Σ_d (M·O_d ⋆ F_d)(p)`, where ⋆ is cross-correlation,
//!    evaluated with 2D FFTs (two real channels packed per complex transform, all
//!    correlations summed in the frequency domain, one inverse transform per block).
//!    Every position whose error is within `(1 + tolerance)` of the smallest is a
//!    candidate, and one is drawn at random (Efros & Freeman's "within 0.1 of the best").
//! 2. **Minimum-error boundary cut** (thesis eq. 79): over the overlap's per-texel error
//!    surface `e`, dynamic programming `E_ij = e_ij + min(E_{i−1,j−1}, E_{i−1,j},
//!    E_{i−1,j+1})` gives the cheapest vertical path through the left overlap (and,
//!    transposed, horizontal path through the top overlap); texels right of / below the
//!    paths take the new block, the others keep what was there.
//!
//! Blocks at the right and bottom borders are cropped to the output. An exact-zero error
//! (a uniform exemplar) accepts every position; the search always ends after one pass.

use super::fft::{Fft2, C64};
use super::{FeatureImage, SplitMix64, SynthError, SynthParams, TexelMap};
use rayon::prelude::*;

/// Validate quilting's parameters against the exemplar.
pub fn check(ex: &FeatureImage, p: &SynthParams) -> Result<(), SynthError> {
    if p.block < 2 || p.block > ex.width.min(ex.height) {
        return Err(SynthError::Invalid(format!(
            "--block {}: a quilting block must be 2 ..= {} texels (the exemplar is {}×{}); \
             choose a smaller block",
            p.block,
            ex.width.min(ex.height),
            ex.width,
            ex.height
        )));
    }
    if p.overlap == 0 || p.overlap >= p.block {
        return Err(SynthError::Invalid(format!(
            "--overlap {}: must be 1 ..= {} (less than the block, {})",
            p.overlap,
            p.block - 1,
            p.block
        )));
    }
    if !(p.tolerance.is_finite() && p.tolerance >= 0.0) {
        return Err(SynthError::Invalid(format!(
            "--tolerance {}: must be a finite number ≥ 0",
            p.tolerance
        )));
    }
    Ok(())
}

/// The exemplar's channels in the frequency domain: feature channels, then `‖F‖²`,
/// packed two per complex transform.
struct Spectra {
    fft: Fft2,
    pairs: Vec<Vec<C64>>,
}

fn exemplar_spectra(ex: &FeatureImage) -> Spectra {
    let (nx, ny) = (ex.width.next_power_of_two(), ex.height.next_power_of_two());
    let fft = Fft2::new(nx, ny);
    let k = ex.dims;
    let channel = |c: usize, x: usize, y: usize| -> f64 {
        let f = ex.px(x, y);
        if c < k {
            f[c] as f64
        } else {
            f.iter().map(|&v| v as f64 * v as f64).sum()
        }
    };
    let n_pairs = (k + 2) / 2;
    let pairs = (0..n_pairs)
        .into_par_iter()
        .map(|j| {
            let mut a = vec![C64::default(); nx * ny];
            for y in 0..ex.height {
                for x in 0..ex.width {
                    let re = channel(2 * j, x, y);
                    let im = if 2 * j < k { channel(2 * j + 1, x, y) } else { 0.0 };
                    a[y * nx + x] = C64::new(re, im);
                }
            }
            fft.forward(&mut a, ny);
            a
        })
        .collect();
    Spectra { fft, pairs }
}

/// Squared feature error of a `bw × bh` block's overlap against every exemplar position
/// where the block fits (row-major, `(h − bh + 1) × (w − bw + 1)`); `overlap(j, i)` gives
/// the already placed features at block texel (column j, row i), `None` outside the
/// overlap. Negative rounding residues are clamped to 0.
fn overlap_errors<'a>(
    spec: &Spectra,
    ex: &FeatureImage,
    bw: usize,
    bh: usize,
    overlap: impl Fn(usize, usize) -> Option<&'a [f32]> + Sync,
) -> Vec<f64> {
    let (nx, ny, k) = (spec.fft.nx, spec.fft.ny, ex.dims);
    // Templates: −2·M·O_d for the feature channels, M for ‖F‖², two per transform.
    let chan = |c: usize, j: usize, i: usize| -> f64 {
        match overlap(j, i) {
            None => 0.0,
            Some(o) if c < k => -2.0 * o[c] as f64,
            Some(_) => 1.0,
        }
    };
    let spectra: Vec<Vec<C64>> = (0..spec.pairs.len())
        .into_par_iter()
        .map(|jp| {
            let mut a = vec![C64::default(); nx * ny];
            for i in 0..bh {
                for j in 0..bw {
                    let im = if 2 * jp < k { chan(2 * jp + 1, j, i) } else { 0.0 };
                    a[i * nx + j] = C64::new(chan(2 * jp, j, i), im);
                }
            }
            spec.fft.forward(&mut a, bh);
            a
        })
        .collect();
    let mut acc = vec![C64::default(); nx * ny];
    for (y, x) in spectra.iter().zip(&spec.pairs) {
        for ((a, yv), xv) in acc.iter_mut().zip(y).zip(x) {
            let v = yv.conj_mul(*xv);
            a.re += v.re;
            a.im += v.im;
        }
    }
    let (cw, ch) = (ex.width - bw + 1, ex.height - bh + 1);
    spec.fft.inverse(&mut acc, ch);
    let mut const_term = 0.0;
    for i in 0..bh {
        for j in 0..bw {
            if let Some(o) = overlap(j, i) {
                const_term += o.iter().map(|&v| v as f64 * v as f64).sum::<f64>();
            }
        }
    }
    let mut out = Vec::with_capacity(cw * ch);
    for py in 0..ch {
        for px in 0..cw {
            out.push((acc[py * nx + px].re + const_term).max(0.0));
        }
    }
    out
}

/// Minimum-cost path from the first to the last row of `e` (`rows × cols`, row-major),
/// moving at most one column per row (thesis eq. 79); returns the path's column per row.
pub fn min_cut_path(e: &[f64], rows: usize, cols: usize) -> Vec<usize> {
    let mut acc = e[..cols].to_vec();
    let mut from = vec![0usize; rows * cols];
    for i in 1..rows {
        let prev = acc.clone();
        for j in 0..cols {
            let mut best = j;
            if j > 0 && prev[j - 1] < prev[best] {
                best = j - 1;
            }
            if j + 1 < cols && prev[j + 1] < prev[best] {
                best = j + 1;
            }
            from[i * cols + j] = best;
            acc[j] = e[i * cols + j] + prev[best];
        }
    }
    let mut j = (0..cols)
        .min_by(|&a, &b| acc[a].total_cmp(&acc[b]).then(a.cmp(&b)))
        .unwrap_or(0);
    let mut path = vec![0; rows];
    for i in (0..rows).rev() {
        path[i] = j;
        if i > 0 {
            j = from[i * cols + j];
        }
    }
    path
}

pub fn synthesize(ex: &FeatureImage, p: &SynthParams) -> Result<TexelMap, SynthError> {
    check(ex, p)?;
    let (w, h, k) = (ex.width, ex.height, ex.dims);
    let (ow, oh) = (p.width, p.height);
    let (b, ov) = (p.block, p.overlap);
    let step = b - ov;
    let spec = exemplar_spectra(ex);
    let mut rng = SplitMix64::new(p.seed);
    let mut map = vec![u32::MAX; ow * oh];
    let blocks_x = (ow.saturating_sub(ov)).div_ceil(step).max(1);
    let blocks_y = (oh.saturating_sub(ov)).div_ceil(step).max(1);
    let mean_norm2: f64 = ex
        .data
        .chunks_exact(k)
        .map(|f| f.iter().map(|&v| v as f64 * v as f64).sum::<f64>())
        .sum::<f64>()
        / (w * h) as f64;
    for by in 0..blocks_y {
        for bx in 0..blocks_x {
            let (x0, y0) = (bx * step, by * step);
            let (bw, bh) = (b.min(ow - x0), b.min(oh - y0));
            let (left, top) = (bx > 0, by > 0);
            let (lw, th) = (if left { ov.min(bw) } else { 0 }, if top { ov.min(bh) } else { 0 });
            let masked = |j: usize, i: usize| j < lw || i < th;
            let out_feat = |j: usize, i: usize| ex.texel(map[(y0 + i) * ow + x0 + j] as usize);
            let (cw, ch) = (w - bw + 1, h - bh + 1);
            let (sx, sy) = if !left && !top {
                (rng.below(cw), rng.below(ch))
            } else {
                let errs = overlap_errors(&spec, ex, bw, bh, |j, i| {
                    if masked(j, i) {
                        Some(out_feat(j, i))
                    } else {
                        None
                    }
                });
                let emin = errs.iter().copied().fold(f64::INFINITY, f64::min);
                let area = (0..bh)
                    .map(|i| (0..bw).filter(|&j| masked(j, i)).count())
                    .sum::<usize>();
                let const_term: f64 = (0..bh)
                    .flat_map(|i| (0..bw).map(move |j| (j, i)))
                    .filter(|&(j, i)| masked(j, i))
                    .map(|(j, i)| out_feat(j, i).iter().map(|&v| v as f64 * v as f64).sum::<f64>())
                    .sum();
                // Rounding of the FFT sums is ~1e-12 of the energies involved.
                let eps = 1e-9 * (const_term + mean_norm2 * area as f64) + f64::MIN_POSITIVE;
                let limit = emin * (1.0 + p.tolerance) + eps;
                let mut cand = Vec::new();
                for py in 0..ch {
                    for px in 0..cw {
                        if errs[py * cw + px] <= limit {
                            cand.push((px, py));
                        }
                    }
                }
                cand[rng.below(cand.len())]
            };
            // Per-texel overlap error and the boundary cuts.
            let e = |j: usize, i: usize| -> f64 {
                let a = out_feat(j, i);
                let s = ex.px(sx + j, sy + i);
                a.iter().zip(s).map(|(&u, &v)| (u as f64 - v as f64).powi(2)).sum()
            };
            let vcut = if lw > 0 {
                let surf: Vec<f64> = (0..bh)
                    .flat_map(|i| (0..lw).map(move |j| (j, i)))
                    .map(|(j, i)| e(j, i))
                    .collect();
                min_cut_path(&surf, bh, lw)
            } else {
                vec![0; bh]
            };
            let hcut = if th > 0 {
                // Transposed: rows of the DP are the block's columns.
                let surf: Vec<f64> = (0..bw)
                    .flat_map(|j| (0..th).map(move |i| (j, i)))
                    .map(|(j, i)| e(j, i))
                    .collect();
                min_cut_path(&surf, bw, th)
            } else {
                vec![0; bw]
            };
            for (i, &vc) in vcut.iter().enumerate() {
                for (j, &hc) in hcut.iter().enumerate() {
                    let new = (lw == 0 || j >= vc) && (th == 0 || i >= hc);
                    let o = (y0 + i) * ow + x0 + j;
                    if new || map[o] == u32::MAX {
                        map[o] = ((sy + i) * w + sx + j) as u32;
                    }
                }
            }
        }
    }
    debug_assert!(map.iter().all(|&s| s != u32::MAX));
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
    use super::*;

    #[test]
    fn the_cut_follows_the_cheapest_path() {
        // A 4 × 3 surface with a zero-cost path 2, 1, 1, 0.
        let e = [5.0, 5.0, 0.0, 5.0, 0.0, 5.0, 5.0, 0.0, 5.0, 0.0, 5.0, 5.0];
        assert_eq!(min_cut_path(&e, 4, 3), vec![2, 1, 1, 0]);
    }

    #[test]
    fn fft_overlap_errors_equal_the_direct_sums() {
        let ex = testutil::blobs(37, 29, 3);
        let spec = exemplar_spectra(&ex);
        let (bw, bh, ov) = (12, 10, 3);
        let other = testutil::blobs(12, 10, 9);
        let overlap = |j: usize, i: usize| if j < ov || i < ov { Some(other.px(j, i)) } else { None };
        let errs = overlap_errors(&spec, &ex, bw, bh, overlap);
        let (cw, ch) = (37 - bw + 1, 29 - bh + 1);
        assert_eq!(errs.len(), cw * ch);
        for py in 0..ch {
            for px in 0..cw {
                let mut d = 0.0;
                for i in 0..bh {
                    for j in 0..bw {
                        if let Some(o) = overlap(j, i) {
                            for (a, b) in o.iter().zip(ex.px(px + j, py + i)) {
                                d += (*a as f64 - *b as f64).powi(2);
                            }
                        }
                    }
                }
                assert!(
                    (errs[py * cw + px] - d).abs() < 1e-9 * (1.0 + d),
                    "{px},{py}: {} vs {d}",
                    errs[py * cw + px]
                );
            }
        }
    }

    #[test]
    fn with_zero_tolerance_a_verbatim_continuation_is_chosen() {
        // A periodic exemplar: continuing the copy has zero overlap error, so every block
        // continues the first one's period exactly.
        let mut ex = testutil::blobs(32, 32, 3);
        for y in 0..32 {
            for x in 0..32 {
                let v = ((x % 8) * 8 + (y % 8)) as f32;
                let o = (y * 32 + x) * 2;
                ex.data[o] = v;
                ex.data[o + 1] = 0.0;
            }
        }
        let mut p = SynthParams::new(SynthMethod::Quilting, 64, 48, 32, 32);
        p.block = 16;
        p.overlap = 4;
        p.tolerance = 0.0;
        let m = run(&ex, &p).unwrap();
        for t in 0..m.src.len() {
            let (sx, sy) = m.source_xy(t);
            let (x, y) = (t % 64, t / 64);
            let (ax, ay) = m.source_xy(0);
            assert_eq!(
                ((sx + 64 - ax) % 8, (sy + 48 - ay) % 8),
                (x % 8, y % 8),
                "texel {x},{y}"
            );
        }
    }

    #[test]
    fn deterministic_and_complete() {
        let ex = testutil::blobs(48, 40, 5);
        let mut p = SynthParams::new(SynthMethod::Quilting, 101, 77, 48, 40);
        p.block = 16;
        p.overlap = 3;
        let a = run(&ex, &p).unwrap();
        let b = run(&ex, &p).unwrap();
        assert_eq!(a, b);
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let c = pool.install(|| run(&ex, &p).unwrap());
        assert_eq!(a, c);
        assert!(a.src.iter().all(|&s| (s as usize) < 48 * 40));
        p.seed = 2;
        assert_ne!(run(&ex, &p).unwrap(), a);
    }

    #[test]
    fn uniform_and_single_bright_exemplars_work() {
        for ex in [testutil::uniform(20, 20), testutil::single_bright(20, 20)] {
            let mut p = SynthParams::new(SynthMethod::Quilting, 50, 45, 20, 20);
            p.block = 8;
            p.overlap = 2;
            let m = run(&ex, &p).unwrap();
            assert_eq!(m.src.len(), 50 * 45);
        }
    }

    #[test]
    fn a_block_larger_than_the_exemplar_is_refused() {
        let ex = testutil::blobs(20, 16, 1);
        let mut p = SynthParams::new(SynthMethod::Quilting, 40, 40, 20, 16);
        p.block = 17;
        let e = run(&ex, &p).unwrap_err().to_string();
        assert!(e.contains("--block 17") && e.contains("20×16"), "{e}");
        p.block = 8;
        p.overlap = 8;
        assert!(run(&ex, &p).unwrap_err().to_string().contains("--overlap"));
    }

    /// The default overlap (block / 4) gives lower seams (`quality::seams`, mean over three
    /// seeds) than Efros & Freeman's sixth on a high-contrast blob texture: measured 1.20
    /// against 1.36. (The issue's ≤ 1.2 target is measured on the leather bench, see
    /// docs/guide/synthesis.md; this synthetic texture sits at the limit, hence 1.25 here.)
    #[test]
    fn the_default_overlap_lowers_the_seams() {
        let ex = testutil::blobs(64, 64, 11);
        let mean_ratio = |overlap: Option<usize>| -> f64 {
            let mut sum = 0.0;
            for seed in 1..=3 {
                let mut p = SynthParams::new(SynthMethod::Quilting, 128, 128, 64, 64);
                p.seed = seed;
                if let Some(o) = overlap {
                    p.overlap = o;
                }
                sum += super::super::quality::seams(&run(&ex, &p).unwrap(), &ex).ratio;
            }
            sum / 3.0
        };
        let p = SynthParams::new(SynthMethod::Quilting, 128, 128, 64, 64);
        assert_eq!((p.block, p.overlap), (16, 4));
        let (default, sixth) = (mean_ratio(None), mean_ratio(Some(16 / 6)));
        eprintln!("seam ratio: overlap 4 {default:.3}, overlap 2 {sixth:.3}");
        assert!(default <= 1.25, "{default}");
        assert!(default < 0.95 * sixth, "{default} vs {sixth}");
    }
}
