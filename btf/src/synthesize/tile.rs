//! Tiling (thesis §6.2.1): the exemplar repeated edge to edge, cut off at the output's
//! right and bottom borders. No search, no randomness: the baseline whose seams and
//! repetition every other method is measured against.

use super::{FeatureImage, SynthParams, TexelMap};

pub fn synthesize(ex: &FeatureImage, p: &SynthParams) -> TexelMap {
    let mut src = Vec::with_capacity(p.width * p.height);
    for y in 0..p.height {
        let sy = y % ex.height;
        for x in 0..p.width {
            src.push((sy * ex.width + x % ex.width) as u32);
        }
    }
    TexelMap {
        width: p.width,
        height: p.height,
        src_width: ex.width,
        src_height: ex.height,
        src,
    }
}

#[cfg(test)]
mod tests {
    use super::super::{synthesize, testutil, SynthMethod, SynthParams};

    #[test]
    fn tiling_repeats_the_exemplar() {
        let ex = testutil::blobs(8, 6, 1);
        let p = SynthParams::new(SynthMethod::Tile, 20, 13, 8, 6);
        let m = synthesize(&ex, &p).unwrap();
        assert_eq!(m.source_xy(0), (0, 0));
        assert_eq!(m.source_xy(19 + 12 * 20), (3, 0));
        assert_eq!(m.source_xy(9 + 7 * 20), (1, 1));
    }
}
