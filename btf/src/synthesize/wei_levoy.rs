//! Fast pixel-wise synthesis with tree-structured VQ over a multiresolution pyramid
//! (Wei & Levoy 2000; thesis §6.2.3).
//!
//! * **Pyramids.** A Gaussian pyramid of the exemplar's feature image (5-tap binomial
//!   filter, clamp-to-edge, decimation by 2) with `levels` levels; the output has one
//!   texel map per level, `⌈size / 2^l⌉` texels on a side.
//! * **Order.** Coarse to fine; within a level in raster order. Every output level starts
//!   as random exemplar texels (noise with the exemplar's histogram), as in the paper.
//! * **Neighbourhoods.** The causal half of a `neighbourhood²` square at the current level
//!   (the rows above and the texels to the left) plus the full `parent_neighbourhood²`
//!   square around the parent texel at the next coarser level. The output's
//!   neighbourhoods wrap around its borders (toroidal), so the first rows see the
//!   initial noise at the bottom; the exemplar's candidates are the texels whose current
//!   level neighbourhood lies inside it (parent lookups clamp at the borders).
//! * **Search.** Each level's candidate neighbourhood vectors go into a [`Tsvq`]; every
//!   output texel takes the exemplar texel of its approximate nearest neighbour.
//! * **Coherence** (`coherence` κ > 0). The greedy tree walk alone lets the output drift
//!   onto a few exemplar texels whose neighbourhoods sit near many centroids (measured:
//!   one texel used 760 times, 61 % of the exemplar never used; docs/guide/synthesis.md). Every
//!   already-synthesized causal neighbour also proposes the exemplar texel that continues
//!   its own source patch (Ashikhmin 2001); the best of those is taken when its distance
//!   is within `1 + κ·2⁻ˡ` of the tree's answer (Hertzmann et al. 2001, level `l`, 0 =
//!   finest), so coarse levels follow the tree and fine levels copy coherent patches.
//!
//! The result is the finest level's map. Sequential (every texel depends on the ones
//! before it), so the same seed gives the same map on any machine.

use super::tsvq::{dist2, Tsvq};
use super::{FeatureImage, SplitMix64, SynthError, SynthParams, TexelMap};

pub fn check(ex: &FeatureImage, p: &SynthParams) -> Result<(), SynthError> {
    if p.levels == 0 || p.levels > 10 {
        return Err(SynthError::Invalid(format!("--levels {}: must be 1 ..= 10", p.levels)));
    }
    for (name, v, min) in [
        ("--neighbourhood", p.neighbourhood, 3),
        ("--parent-neighbourhood", p.parent_neighbourhood, 1),
    ] {
        if v < min || v.is_multiple_of(2) {
            return Err(SynthError::Invalid(format!("{name} {v}: must be odd and ≥ {min}")));
        }
    }
    if !(p.coherence.is_finite() && p.coherence >= 0.0) {
        return Err(SynthError::Invalid(format!(
            "--coherence {}: must be a finite number ≥ 0 (0 = no coherence candidates)",
            p.coherence
        )));
    }
    if p.leaf == 0 {
        return Err(SynthError::Invalid(
            "--leaf 0: a TSVQ leaf holds at least one vector".into(),
        ));
    }
    let coarse = |n: usize| (0..p.levels - 1).fold(n, |n, _| n.div_ceil(2));
    let (cw, ch) = (coarse(ex.width), coarse(ex.height));
    let h = p.neighbourhood / 2;
    if cw < 2 * h + 1 || ch < h + 1 {
        return Err(SynthError::Invalid(format!(
            "--levels {}: the coarsest level of the {}×{} exemplar is {cw}×{ch} texels, too small for a \
             {}² neighbourhood; use fewer levels or a smaller neighbourhood",
            p.levels, ex.width, ex.height, p.neighbourhood
        )));
    }
    Ok(())
}

/// One Gaussian-pyramid reduction (binomial 1-4-6-4-1, clamp to edge, keep even texels).
pub fn reduce(f: &FeatureImage) -> FeatureImage {
    const K: [f32; 5] = [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];
    let (w, h, d) = (f.width, f.height, f.dims);
    let (nw, nh) = (w.div_ceil(2), h.div_ceil(2));
    // Horizontal pass at the kept columns, then vertical at the kept rows.
    let mut tmp = vec![0f32; nw * h * d];
    for y in 0..h {
        for x in 0..nw {
            let o = &mut tmp[(y * nw + x) * d..(y * nw + x + 1) * d];
            for (i, &kw) in K.iter().enumerate() {
                let sx = (2 * x as isize + i as isize - 2).clamp(0, w as isize - 1) as usize;
                for (a, &v) in o.iter_mut().zip(f.px(sx, y)) {
                    *a += kw * v;
                }
            }
        }
    }
    let mut data = vec![0f32; nw * nh * d];
    for y in 0..nh {
        for x in 0..nw {
            let o = &mut data[(y * nw + x) * d..(y * nw + x + 1) * d];
            for (i, &kw) in K.iter().enumerate() {
                let sy = (2 * y as isize + i as isize - 2).clamp(0, h as isize - 1) as usize;
                for (a, &v) in o.iter_mut().zip(&tmp[(sy * nw + x) * d..(sy * nw + x + 1) * d]) {
                    *a += kw * v;
                }
            }
        }
    }
    FeatureImage {
        width: nw,
        height: nh,
        dims: d,
        data,
    }
}

/// Offsets of the causal half of an `n × n` square (rows above, then left on the row).
fn causal(n: usize) -> Vec<(isize, isize)> {
    let h = (n / 2) as isize;
    let mut o = Vec::new();
    for dy in -h..=0 {
        for dx in -h..=h {
            if dy < 0 || dx < 0 {
                o.push((dx, dy));
            }
        }
    }
    o
}

fn square(n: usize) -> Vec<(isize, isize)> {
    let h = (n / 2) as isize;
    (-h..=h).flat_map(|dy| (-h..=h).map(move |dx| (dx, dy))).collect()
}

pub fn synthesize(ex: &FeatureImage, p: &SynthParams) -> Result<TexelMap, SynthError> {
    check(ex, p)?;
    let levels = p.levels;
    let mut pyr = vec![ex.clone()];
    for l in 1..levels {
        let next = reduce(&pyr[l - 1]);
        pyr.push(next);
    }
    let k = ex.dims;
    let cz = causal(p.neighbourhood);
    let pz = square(p.parent_neighbourhood);
    let hn = p.neighbourhood / 2;
    let mut rng = SplitMix64::new(p.seed);
    let out_size = |l: usize| {
        let f = |n: usize| (0..l).fold(n, |n, _| n.div_ceil(2));
        (f(p.width), f(p.height))
    };
    // The map of the level above (coarser), if any.
    let mut parent: Option<(Vec<u32>, usize, usize)> = None;
    for l in (0..levels).rev() {
        let e = &pyr[l];
        let (ew, eh) = (e.width, e.height);
        let (ow, oh) = out_size(l);
        let has_parent = l + 1 < levels;
        let dims = (cz.len() + if has_parent { pz.len() } else { 0 }) * k;
        // Exemplar candidate vectors.
        let (cx0, cx1, cy0) = (hn, ew - hn, hn);
        let mut cand_pos = Vec::new();
        let mut vecs = Vec::new();
        for y in cy0..eh {
            for x in cx0..cx1 {
                cand_pos.push((y * ew + x) as u32);
                for &(dx, dy) in &cz {
                    vecs.extend_from_slice(e.px((x as isize + dx) as usize, (y as isize + dy) as usize));
                }
                if has_parent {
                    let pe = &pyr[l + 1];
                    for &(dx, dy) in &pz {
                        let px = (x as isize / 2 + dx).clamp(0, pe.width as isize - 1) as usize;
                        let py = (y as isize / 2 + dy).clamp(0, pe.height as isize - 1) as usize;
                        vecs.extend_from_slice(pe.px(px, py));
                    }
                }
            }
        }
        // Exemplar position → candidate index (u32::MAX: no full neighbourhood there).
        let mut cand_of = vec![u32::MAX; ew * eh];
        for (i, &pos) in cand_pos.iter().enumerate() {
            cand_of[pos as usize] = i as u32;
        }
        let tree = Tsvq::build(vecs, dims, p.leaf);
        let accept = 1.0 + p.coherence as f32 * 0.5f32.powi(l as i32);
        // Output: noise, then raster-order synthesis.
        let mut map: Vec<u32> = (0..ow * oh).map(|_| rng.below(ew * eh) as u32).collect();
        let mut q = vec![0f32; dims];
        for y in 0..oh {
            for x in 0..ow {
                let mut o = 0;
                for &(dx, dy) in &cz {
                    let nx = (x as isize + dx).rem_euclid(ow as isize) as usize;
                    let ny = (y as isize + dy).rem_euclid(oh as isize) as usize;
                    q[o..o + k].copy_from_slice(e.texel(map[ny * ow + nx] as usize));
                    o += k;
                }
                if let Some((pm, pw, ph)) = &parent {
                    let pe = &pyr[l + 1];
                    for &(dx, dy) in &pz {
                        let nx = ((x / 2) as isize + dx).rem_euclid(*pw as isize) as usize;
                        let ny = ((y / 2) as isize + dy).rem_euclid(*ph as isize) as usize;
                        q[o..o + k].copy_from_slice(pe.texel(pm[ny * pw + nx] as usize));
                        o += k;
                    }
                }
                let mut best = tree.nearest(&q, &mut rng);
                if p.coherence > 0.0 {
                    let d_tree = dist2(&q, tree.vector(best));
                    let mut coh = (f32::INFINITY, u32::MAX);
                    for &(dx, dy) in &cz {
                        let nx = (x as isize + dx).rem_euclid(ow as isize) as usize;
                        let ny = (y as isize + dy).rem_euclid(oh as isize) as usize;
                        let s = map[ny * ow + nx] as usize;
                        let (sx, sy) = ((s % ew) as isize - dx, (s / ew) as isize - dy);
                        if sx < 0 || sy < 0 || sx >= ew as isize || sy >= eh as isize {
                            continue;
                        }
                        let c = cand_of[sy as usize * ew + sx as usize];
                        if c != u32::MAX && c != coh.1 {
                            let d = dist2(&q, tree.vector(c));
                            if d < coh.0 || (d == coh.0 && c < coh.1) {
                                coh = (d, c);
                            }
                        }
                    }
                    if coh.1 != u32::MAX && coh.0 <= d_tree * accept {
                        best = coh.1;
                    }
                }
                map[y * ow + x] = cand_pos[best as usize];
            }
        }
        parent = Some((map, ow, oh));
    }
    let (src, _, _) = parent.expect("at least one level");
    Ok(TexelMap {
        width: p.width,
        height: p.height,
        src_width: ex.width,
        src_height: ex.height,
        src,
    })
}

#[cfg(test)]
mod tests {
    use super::super::{synthesize as run, testutil, SynthMethod, SynthParams};
    use super::*;

    #[test]
    fn reduce_keeps_the_mean_of_a_constant() {
        let f = testutil::uniform(9, 7);
        let r = reduce(&f);
        assert_eq!((r.width, r.height), (5, 4));
        assert!(r.data.iter().all(|&v| (v - 0.25).abs() < 1e-6));
    }

    #[test]
    fn deterministic_complete_and_refuses_too_many_levels() {
        let ex = testutil::blobs(32, 32, 7);
        let mut p = SynthParams::new(SynthMethod::WeiLevoy, 48, 40, 32, 32);
        p.levels = 2;
        p.neighbourhood = 5;
        p.parent_neighbourhood = 3;
        let a = run(&ex, &p).unwrap();
        assert_eq!(a.src.len(), 48 * 40);
        assert!(a.src.iter().all(|&s| (s as usize) < 32 * 32));
        assert_eq!(run(&ex, &p).unwrap(), a);
        p.levels = 5;
        let e = run(&ex, &p).unwrap_err().to_string();
        assert!(e.contains("--levels 5") && e.contains("coarsest"), "{e}");
    }

    #[test]
    fn uniform_and_single_bright_exemplars_work() {
        for ex in [testutil::uniform(24, 24), testutil::single_bright(24, 24)] {
            let mut p = SynthParams::new(SynthMethod::WeiLevoy, 30, 26, 24, 24);
            p.levels = 2;
            p.neighbourhood = 5;
            let m = run(&ex, &p).unwrap();
            assert_eq!(m.src.len(), 30 * 26);
        }
    }

    /// The coherence candidates stop the drift onto a few exemplar texels that the greedy
    /// tree walk alone shows (docs/guide/synthesis.md): on a blob texture the most used texel
    /// is used far less often, and more of the exemplar is used at all.
    #[test]
    fn coherence_spreads_the_use_of_the_exemplar() {
        use crate::synthesize::quality::repetition;
        let ex = testutil::blobs(48, 48, 3);
        let mut p = SynthParams::new(SynthMethod::WeiLevoy, 96, 96, 48, 48);
        p.levels = 2;
        p.coherence = 0.0;
        let greedy = repetition(&run(&ex, &p).unwrap());
        p.coherence = 1.0;
        let coherent = repetition(&run(&ex, &p).unwrap());
        assert!(
            coherent.reuse_max * 2 <= greedy.reuse_max,
            "reuse max: greedy {}, coherent {}",
            greedy.reuse_max,
            coherent.reuse_max
        );
        p.coherence = f64::NAN;
        let e = run(&ex, &p).unwrap_err().to_string();
        assert!(e.contains("--coherence"), "{e}");
    }
}
