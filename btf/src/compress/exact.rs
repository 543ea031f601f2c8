//! Exact, order-independent sums of f64 matrices: what lets a sharded randomized SVD
//! (`gonio compress --method pca|dfmf --shard I/N`, [`super::rsvd`]) give the
//! single-process file byte for byte.
//!
//! Why: the randomized SVD adds one contribution per view (`Y = Σ_v A_v Ω_v`, and the
//! same in every power iteration). In f64 that sum depends on its grouping: shards that
//! sum their own views and a merge that adds the shard sums give
//! `(a + b) + (c + d)` where one process gives `((a + b) + c) + d`, which differ in the
//! last bits, and a randomized SVD turns those bits into different factors. An exact
//! accumulator has no grouping: every entry holds the exact sum of what was added, as a
//! 256-bit two's-complement fixed-point number with 128 fraction bits, and is rounded to
//! f64 once, at the end. Any split into shards, any merge order, any thread count gives
//! the same bits.
//!
//! Range: |sum| < 2¹²⁶ ≈ 8.5·10³⁷ (larger values are refused, never wrapped); the bits
//! of an addend below 2⁻¹²⁸ ≈ 2.9·10⁻³⁹ are dropped (truncated toward zero, per addend,
//! so still independent of the order): an absolute error below 2⁻¹²⁸ per addend, where
//! f64 addition has a relative one of 2⁻⁵³. The sketch entries of a BTF in BRDF units
//! are many orders of magnitude inside both ends. Cost: 32 bytes per entry (38 MiB for a 65536 × 18 sketch) and one
//! 256-bit add per entry and view, small next to the view's matrix product.

use super::error::CompressError;
use faer::{Mat, MatRef};
use rayon::prelude::*;

/// Fraction bits of the fixed-point format.
const FRAC: i32 = 128;

/// One exact fixed-point number: `limbs` is a 256-bit two's-complement integer X
/// (little-endian 64-bit limbs), the value is `X · 2⁻¹²⁸`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Fixed([u64; 4]);

impl Fixed {
    fn add(&mut self, o: &Fixed) {
        let mut carry = 0u64;
        for i in 0..4 {
            let (s1, c1) = self.0[i].overflowing_add(o.0[i]);
            let (s2, c2) = s1.overflowing_add(carry);
            self.0[i] = s2;
            carry = (c1 as u64) + (c2 as u64);
        }
    }

    fn negate(&mut self) {
        for l in &mut self.0 {
            *l = !*l;
        }
        self.add(&Fixed([1, 0, 0, 0]));
    }

    fn is_negative(&self) -> bool {
        self.0[3] >> 63 == 1
    }

    /// `x` exactly (to 2⁻¹²⁸, truncated toward zero); `None` for a non-finite `x` or
    /// |x| ≥ 2¹²⁶ (so that sums of up to 2 such values cannot wrap; the accumulator
    /// checks the running sum's range itself).
    fn from_f64(x: f64) -> Option<Fixed> {
        if !x.is_finite() {
            return None;
        }
        if x == 0.0 {
            return Some(Fixed::default());
        }
        let bits = x.to_bits();
        let exp = ((bits >> 52) & 0x7ff) as i32;
        let frac = bits & ((1u64 << 52) - 1);
        // x = m · 2^e with m an integer < 2⁵³.
        let (m, e) = if exp == 0 {
            (frac, -1074)
        } else {
            (frac | (1u64 << 52), exp - 1075)
        };
        let shift = e + FRAC; // X = m · 2^shift
        if shift + 53 > 254 {
            return None;
        }
        let mut out = Fixed::default();
        if shift >= 0 {
            // Place m at bit `shift` of the 256-bit integer.
            let (limb, bit) = ((shift / 64) as usize, (shift % 64) as u32);
            out.0[limb] = m << bit;
            if bit > 0 && limb + 1 < 4 {
                out.0[limb + 1] = m >> (64 - bit);
            }
        } else if shift > -64 {
            out.0[0] = m >> (-shift) as u32;
        }
        if bits >> 63 == 1 {
            out.negate();
        }
        Some(out)
    }

    /// The nearest f64 (round half to even), computed from the exact value.
    fn to_f64(self) -> f64 {
        let neg = self.is_negative();
        let mut mag = self;
        if neg {
            mag.negate();
        }
        let Some(top) = (0..4).rev().find(|&i| mag.0[i] != 0) else {
            return 0.0;
        };
        let lead = top as i32 * 64 + 63 - mag.0[top].leading_zeros() as i32; // highest set bit
        let v = if lead <= 63 {
            // The whole magnitude is one word: u64 → f64 is the correct rounding.
            (mag.0[0] as f64) * pow2(-FRAC)
        } else {
            // The 64 bits from `lead` down, with a sticky bit for anything below them:
            // bit 0 lies far below the f64 rounding position (bit 11), so the one rounding
            // of u64 → f64 is the correct rounding of the whole value.
            let low = lead - 63;
            let word = shr256_word(&mag, low) | any_below(&mag, low) as u64;
            (word as f64) * pow2(low - FRAC)
        };
        if neg {
            -v
        } else {
            v
        }
    }
}

/// Bits `[s, s + 64)` of the 256-bit magnitude as one word (s ≥ 0).
fn shr256_word(m: &Fixed, s: i32) -> u64 {
    let (limb, bit) = ((s / 64) as usize, (s % 64) as u32);
    let lo = m.0[limb] >> bit;
    let hi = if bit > 0 && limb + 1 < 4 {
        m.0[limb + 1] << (64 - bit)
    } else {
        0
    };
    lo | hi
}

/// 2^k exactly (−1022 ≤ k ≤ 1023).
fn pow2(k: i32) -> f64 {
    f64::from_bits(((k + 1023) as u64) << 52)
}

/// Whether any bit below bit `s` is set.
fn any_below(m: &Fixed, s: i32) -> bool {
    let (limb, bit) = ((s / 64) as usize, (s % 64) as u32);
    m.0[..limb].iter().any(|&l| l != 0) || (bit > 0 && m.0[limb] & ((1u64 << bit) - 1) != 0)
}

/// Largest magnitude a running sum may reach: 2¹²⁶, leaving one bit of headroom so one
/// more addend below 2¹²⁶ cannot wrap before the check.
fn in_range(f: &Fixed) -> bool {
    // |x| < 2¹²⁶: bits 255 … 126 all equal the sign (x in [−2¹²⁶, 2¹²⁶)), less −2¹²⁶
    // itself. Read from the top limb, without negating.
    match f.0[3] >> 62 {
        0 => true,
        3 => !(f.0[3] == 3 << 62 && f.0[..3] == [0, 0, 0]),
        _ => false,
    }
}

/// An exact sum of `rows × cols` f64 matrices ([module docs](self)).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ExactMat {
    rows: usize,
    cols: usize,
    /// Row-major.
    data: Vec<Fixed>,
}

/// Rows per parallel chunk: each entry is independent, so chunking only sets the work size.
const CHUNK_ROWS: usize = 1024;

impl ExactMat {
    pub fn zeros(rows: usize, cols: usize) -> Self {
        ExactMat {
            rows,
            cols,
            data: vec![Fixed::default(); rows * cols],
        }
    }

    pub fn nrows(&self) -> usize {
        self.rows
    }
    pub fn ncols(&self) -> usize {
        self.cols
    }

    /// Add `m` exactly. Refuses a non-finite entry or a sum that leaves the range,
    /// naming `what` (the caller's matrix) — the accumulator is unchanged then only up
    /// to the entries already added, so the caller must treat the error as final.
    pub fn add(&mut self, m: MatRef<'_, f64>, what: &str) -> Result<(), CompressError> {
        if m.nrows() != self.rows || m.ncols() != self.cols {
            return Err(CompressError::Invalid(format!(
                "{what}: adding a {} × {} matrix to a {} × {} sum",
                m.nrows(),
                m.ncols(),
                self.rows,
                self.cols
            )));
        }
        let cols = self.cols;
        // Small sums (a cluster's sketch) are not worth waking the pool for.
        let min_len = if self.data.len() < 1 << 16 { usize::MAX } else { 1 };
        let bad = self
            .data
            .par_chunks_mut(CHUNK_ROWS * cols.max(1))
            .with_min_len(min_len)
            .enumerate()
            .map(|(c, chunk)| {
                let r0 = c * CHUNK_ROWS;
                let rows = chunk.len() / cols.max(1);
                // Column by column from contiguous slices (faer's columns), not `m[(i, j)]`.
                for j in 0..cols {
                    let col = m.col(j).subrows(r0, rows);
                    let at = |i: usize| match col.try_as_col_major() {
                        Some(s) => s.as_slice()[i],
                        None => col[i],
                    };
                    for i in 0..rows {
                        let x = at(i);
                        let acc = &mut chunk[i * cols + j];
                        match Fixed::from_f64(x) {
                            Some(f) => {
                                acc.add(&f);
                                if !in_range(acc) {
                                    return Some((r0 + i, j, x));
                                }
                            }
                            None => return Some((r0 + i, j, x)),
                        }
                    }
                }
                None
            })
            .find_first(|r| r.is_some())
            .flatten();
        match bad {
            None => Ok(()),
            Some((i, j, x)) => Err(CompressError::Invalid(format!(
                "{what}: entry ({i}, {j}) = {x} is not finite or the sum leaves ±2^126; the dataset's values \
                 must be finite and below ~1e37"
            ))),
        }
    }

    /// Add another exact sum (a shard's part) exactly.
    pub fn add_exact(&mut self, o: &ExactMat, what: &str) -> Result<(), CompressError> {
        if o.rows != self.rows || o.cols != self.cols {
            return Err(CompressError::Invalid(format!(
                "{what}: a {} × {} part cannot be added to a {} × {} sum",
                o.rows, o.cols, self.rows, self.cols
            )));
        }
        for (a, b) in self.data.iter_mut().zip(&o.data) {
            a.add(b);
            if !in_range(a) {
                return Err(CompressError::Invalid(format!("{what}: the sum leaves ±2^126")));
            }
        }
        Ok(())
    }

    /// The sum, each entry rounded once to the nearest f64.
    pub fn to_mat(&self) -> Mat<f64> {
        Mat::from_fn(self.rows, self.cols, |i, j| self.data[i * self.cols + j].to_f64())
    }

    /// Little-endian bytes: 32 per entry, row-major (what a part file stores).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.data.len() * 32);
        for f in &self.data {
            for l in f.0 {
                out.extend_from_slice(&l.to_le_bytes());
            }
        }
        out
    }

    /// The inverse of [`ExactMat::to_bytes`].
    pub fn from_bytes(rows: usize, cols: usize, bytes: &[u8]) -> Result<ExactMat, CompressError> {
        if bytes.len() != rows * cols * 32 {
            return Err(CompressError::Invalid(format!(
                "exact sum of {rows} × {cols}: {} bytes, {} expected",
                bytes.len(),
                rows * cols * 32
            )));
        }
        let data = bytes
            .chunks_exact(32)
            .map(|c| {
                let mut l = [0u64; 4];
                for (k, w) in c.chunks_exact(8).enumerate() {
                    l[k] = u64::from_le_bytes(w.try_into().expect("8 bytes"));
                }
                Fixed(l)
            })
            .collect();
        Ok(ExactMat { rows, cols, data })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sum_of(xs: &[f64]) -> f64 {
        let mut acc = Fixed::default();
        for &x in xs {
            acc.add(&Fixed::from_f64(x).unwrap());
        }
        acc.to_f64()
    }

    #[test]
    fn single_values_round_trip_exactly() {
        // Every value whose lowest mantissa bit is at or above 2⁻¹²⁸ (|x| ≥ 2⁻⁷⁵ for a
        // full mantissa) is held exactly.
        let xs = [
            0.0,
            1.0,
            -1.0,
            0.1,
            -0.3,
            1e-20,
            -1e-20,
            3.5e37,
            -3.5e37,
            123_456_789.123_456_78,
            2f64.powi(-120),
            -(2f64.powi(100) + 1.0),
            f64::EPSILON,
        ];
        for x in xs {
            assert_eq!(sum_of(&[x]).to_bits(), x.to_bits(), "{x}");
        }
        // Below that, the bits under 2⁻¹²⁸ are dropped: an absolute error below 2⁻¹²⁸.
        for x in [1e-30, -1e-30, f64::MIN_POSITIVE, 1e-45] {
            let y = sum_of(&[x]);
            assert!((y - x).abs() < 2f64.powi(-128) && y.abs() <= x.abs(), "{x} → {y}");
        }
    }

    #[test]
    fn sums_are_exact_and_independent_of_order() {
        // 1e20 + 1 − 1e20 is 0 in f64 left to right; exactly 1.
        assert_eq!(sum_of(&[1e20, 1.0, -1e20]), 1.0);
        assert_eq!(sum_of(&[1.0, 1e-16, 1e-16]), 1.0 + 2e-16);
        // A pseudo-random list with a wide dynamic range: every permutation and every
        // grouping gives the same bits.
        let mut s = 7u64;
        let xs: Vec<f64> = (0..200)
            .map(|_| {
                let r = super::super::linalg::splitmix(&mut s);
                let m = (r >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
                m * 10f64.powi((r % 24) as i32 - 12)
            })
            .collect();
        let fwd = sum_of(&xs);
        let mut rev = xs.clone();
        rev.reverse();
        assert_eq!(sum_of(&rev).to_bits(), fwd.to_bits());
        // Grouped as shards: sum of partial exact sums.
        let parts: Vec<ExactMat> = xs
            .chunks(37)
            .map(|c| {
                let mut e = ExactMat::zeros(1, 1);
                for &x in c {
                    e.add(Mat::from_fn(1, 1, |_, _| x).as_ref(), "t").unwrap();
                }
                e
            })
            .collect();
        let mut total = ExactMat::zeros(1, 1);
        for p in parts.iter().rev() {
            total.add_exact(p, "t").unwrap();
        }
        assert_eq!(total.to_mat()[(0, 0)].to_bits(), fwd.to_bits());
        // And the result is the correctly rounded sum: compare with a long f64 Kahan–
        // Neumaier sum, which is exact to well below one ulp for this list.
        let (mut sum, mut c) = (0f64, 0f64);
        for &x in &xs {
            let t = sum + x;
            c += if sum.abs() >= x.abs() {
                (sum - t) + x
            } else {
                (x - t) + sum
            };
            sum = t;
        }
        assert!(
            (fwd - (sum + c)).abs() <= f64::EPSILON * fwd.abs().max(1e-300),
            "{fwd} vs {}",
            sum + c
        );
    }

    #[test]
    fn rounding_is_to_nearest_even() {
        // 1 + 2⁻⁵³ is a tie between 1 and 1 + 2⁻⁵²: even is 1.
        assert_eq!(sum_of(&[1.0, 2f64.powi(-53)]), 1.0);
        // 1 + 2⁻⁵³ + 2⁻¹⁰⁰ is just above the tie: rounds up.
        assert_eq!(sum_of(&[1.0, 2f64.powi(-53), 2f64.powi(-100)]), 1.0 + f64::EPSILON);
        // 1 + 3·2⁻⁵³ ties between 1 + 2⁻⁵² and 1 + 2·2⁻⁵²: even is 1 + 2·2⁻⁵².
        assert_eq!(sum_of(&[1.0, 3.0 * 2f64.powi(-53)]), 1.0 + 2.0 * f64::EPSILON);
    }

    #[test]
    fn non_finite_and_out_of_range_are_refused() {
        let mut e = ExactMat::zeros(1, 2);
        let m = Mat::from_fn(1, 2, |_, j| if j == 1 { f64::NAN } else { 1.0 });
        let err = e.add(m.as_ref(), "sketch").unwrap_err().to_string();
        assert!(err.contains("sketch") && err.contains("(0, 1)"), "{err}");
        let mut e = ExactMat::zeros(1, 1);
        let big = Mat::from_fn(1, 1, |_, _| 1e38);
        assert!(e.add(big.as_ref(), "big").is_err());
        // The range is |sum| < 2¹²⁶, on both sides: 2¹²⁵ + 2¹²⁵ and −2¹²⁵ − 2¹²⁵ are out,
        // 2¹²⁵ + (2¹²⁵ − ulp) and its negative are in.
        let p125 = 2f64.powi(125);
        let below = p125 - p125 * f64::EPSILON;
        for (a, b, ok) in [
            (p125, p125, false),
            (-p125, -p125, false),
            (p125, below, true),
            (-p125, -below, true),
        ] {
            let mut e = ExactMat::zeros(1, 1);
            let m = |x: f64| Mat::from_fn(1, 1, move |_, _| x);
            e.add(m(a).as_ref(), "a").unwrap();
            assert_eq!(e.add(m(b).as_ref(), "b").is_ok(), ok, "{a} + {b}");
        }
    }

    #[test]
    fn bytes_round_trip() {
        let mut e = ExactMat::zeros(3, 2);
        e.add(
            Mat::from_fn(3, 2, |i, j| (i as f64 - 1.0) * 1e-7 + j as f64).as_ref(),
            "t",
        )
        .unwrap();
        let b = e.to_bytes();
        let back = ExactMat::from_bytes(3, 2, &b).unwrap();
        assert_eq!(back, e);
        assert!(ExactMat::from_bytes(3, 3, &b).is_err());
    }
}
