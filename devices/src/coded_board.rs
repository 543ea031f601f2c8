//! The coded-marker calibration board: a checkerboard whose white squares each carry a
//! small binary marker with its own id (the ChArUco idea), so a view that shows only part
//! of the board — occluded, cut off by the frame, too grazing at one end — still says
//! which corners it shows.
//!
//! Shared by the simulator (which renders it) and the detector in `gonio-calibration`, so
//! both agree on where every square, marker cell and corner is. Lengths in millimetres on
//! the board's plane (the sample frame: x right, y up, origin at the board's centre).
//!
//! ## Layout
//! - `squares_x × squares_y` squares of `pitch_mm`; square (a, b) counts from the −x, −y
//!   corner and is black when `a + b` is even.
//! - Every white square holds a centred marker of `marker_mm`: 6 × 6 cells, the outer ring
//!   black, the inner 4 × 4 the code's bits (1 = white). Bit `k` of the 16 is inner cell
//!   (column `k % 4` from −x, row `k / 4` from +y), read from the most significant bit.
//! - Marker ids run over the white squares in order of increasing b, then a, from
//!   `first_id` on (several boards in one scene can use disjoint id ranges).
//! - Inner corner (i, j), `i < squares_x − 1`, `j < squares_y − 1`, is where squares
//!   (i, j), (i + 1, j), (i, j + 1), (i + 1, j + 1) meet.
//!
//! ## The dictionary
//! [`dictionary`] is generated, not tabulated: 16-bit codes taken greedily in a fixed
//! pseudo-random order, each kept only if
//! - it differs in at least [`MIN_DISTANCE`] bits from every kept code in each of their
//!   four rotations, and from its own three rotations (so a one-bit read error is corrected
//!   and the marker's orientation is never ambiguous);
//! - it has between 4 and 12 white bits (an all-black square is never read as a marker);
//! - its 4 × 4 bits contain no 2 × 2 block of checker pattern. Then a marker has no
//!   X-junction anywhere: the saddle detector that finds the board's corners sees only the
//!   board's own corners, never a marker's insides.

use serde::{Deserialize, Serialize};
use std::sync::OnceLock;

/// Smallest Hamming distance between any two codes in any rotation (and between a code
/// and its own rotations).
pub const MIN_DISTANCE: u32 = 4;

/// Cells across a marker: a black ring around 4 × 4 bits.
pub const MARKER_CELLS: usize = 6;

/// The board's geometry.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CodedBoardSpec {
    /// Squares along the board's x axis.
    pub squares_x: usize,
    /// Squares along the board's y axis.
    pub squares_y: usize,
    /// Square size (mm).
    pub pitch_mm: f64,
    /// Marker edge length (mm), centred in its white square.
    pub marker_mm: f64,
    /// Id of the first marker.
    #[serde(default)]
    pub first_id: usize,
}

impl CodedBoardSpec {
    /// Checks what the renderer and the detector rely on; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        if self.squares_x < 3 || self.squares_y < 3 || self.squares_x > 64 || self.squares_y > 64 {
            return Err(format!(
                "squares_x = {}, squares_y = {}: need 3 ..= 64 squares per side (≥ 2 × 2 inner corners)",
                self.squares_x, self.squares_y
            ));
        }
        if !(self.pitch_mm.is_finite() && self.pitch_mm > 0.0) {
            return Err(format!("pitch_mm = {}: must be a positive length", self.pitch_mm));
        }
        if !(self.marker_mm.is_finite() && self.marker_mm > 0.0 && self.marker_mm <= 0.8 * self.pitch_mm) {
            return Err(format!(
                "marker_mm = {}: must be in (0, 0.8 · pitch_mm = {}]: the white margin around the marker is \
                 where the corners are measured",
                self.marker_mm,
                0.8 * self.pitch_mm
            ));
        }
        let needed = self.first_id + self.marker_count();
        let have = dictionary().len();
        if needed > have {
            return Err(format!(
                "{} × {} squares with first_id = {} need marker ids up to {}, the dictionary has {have}: \
                 use fewer squares or a lower first_id",
                self.squares_x,
                self.squares_y,
                self.first_id,
                needed - 1
            ));
        }
        Ok(())
    }

    /// Board extent (mm) along x and y.
    pub fn size_mm(&self) -> [f64; 2] {
        [
            self.squares_x as f64 * self.pitch_mm,
            self.squares_y as f64 * self.pitch_mm,
        ]
    }

    /// Inner corners along x and y.
    pub fn corners(&self) -> (usize, usize) {
        (self.squares_x - 1, self.squares_y - 1)
    }

    /// Number of markers (white squares).
    pub fn marker_count(&self) -> usize {
        (self.squares_x * self.squares_y) / 2
    }

    /// White margin (mm) between a marker and its square's edges.
    pub fn margin_mm(&self) -> f64 {
        0.5 * (self.pitch_mm - self.marker_mm)
    }

    /// Whether square (a, b) is black.
    pub fn square_is_black(a: usize, b: usize) -> bool {
        (a + b).is_multiple_of(2)
    }

    /// Board-plane position (mm) of inner corner (i, j).
    pub fn corner_point(&self, i: usize, j: usize) -> [f64; 2] {
        let [w, h] = self.size_mm();
        [
            -0.5 * w + (i as f64 + 1.0) * self.pitch_mm,
            -0.5 * h + (j as f64 + 1.0) * self.pitch_mm,
        ]
    }

    /// Id of the marker in white square (a, b); `None` for a black square or one off the board.
    pub fn marker_id(&self, a: usize, b: usize) -> Option<usize> {
        if a >= self.squares_x || b >= self.squares_y || Self::square_is_black(a, b) {
            return None;
        }
        // Count the white squares before (a, b) in id order.
        let mut k = 0;
        for bb in 0..=b {
            for aa in 0..self.squares_x {
                if bb == b && aa == a {
                    return Some(self.first_id + k);
                }
                if !Self::square_is_black(aa, bb) {
                    k += 1;
                }
            }
        }
        None
    }

    /// The white square (a, b) that carries marker `id`.
    pub fn square_of(&self, id: usize) -> Option<(usize, usize)> {
        let k = id.checked_sub(self.first_id)?;
        let mut n = 0;
        for b in 0..self.squares_y {
            for a in 0..self.squares_x {
                if !Self::square_is_black(a, b) {
                    if n == k {
                        return Some((a, b));
                    }
                    n += 1;
                }
            }
        }
        None
    }

    /// Whether the board is black at board-plane point (x, y) (mm). Off the board: white
    /// (`false`), the colour of the surround the board is printed on.
    pub fn is_black(&self, x: f64, y: f64) -> bool {
        let [w, h] = self.size_mm();
        let (u, v) = (x + 0.5 * w, y + 0.5 * h);
        if !(u >= 0.0 && v >= 0.0 && u < w && v < h) {
            return false;
        }
        let (a, b) = ((u / self.pitch_mm) as usize, (v / self.pitch_mm) as usize);
        let (a, b) = (a.min(self.squares_x - 1), b.min(self.squares_y - 1));
        if Self::square_is_black(a, b) {
            return true;
        }
        // Position inside the square, then inside the marker.
        let m = self.margin_mm();
        let (su, sv) = (u - a as f64 * self.pitch_mm - m, v - b as f64 * self.pitch_mm - m);
        if !(su >= 0.0 && sv >= 0.0 && su < self.marker_mm && sv < self.marker_mm) {
            return false;
        }
        let cell = self.marker_mm / MARKER_CELLS as f64;
        let cx = ((su / cell) as usize).min(MARKER_CELLS - 1);
        let cy = ((sv / cell) as usize).min(MARKER_CELLS - 1);
        let id = self.marker_id(a, b).expect("white square on the board");
        let code = dictionary().get(id).copied().unwrap_or(0);
        marker_cell_black(code, cx, cy)
    }
}

/// Whether cell (cx, cy) of a marker with `code` is black; cx counts from −x, cy from −y,
/// both in `0..6`; the outer ring is black.
pub fn marker_cell_black(code: u16, cx: usize, cy: usize) -> bool {
    if cx == 0 || cy == 0 || cx == MARKER_CELLS - 1 || cy == MARKER_CELLS - 1 {
        return true;
    }
    let (bx, by_top) = (cx - 1, MARKER_CELLS - 2 - cy);
    code_bit(code, bx, by_top) == 0
}

/// The mask of the bit at inner cell column `bx` (from −x) and row `row` (from +y).
fn bit_mask(bx: usize, row: usize) -> u16 {
    1 << (15 - (row * 4 + bx))
}

/// Bit of `code` at inner cell column `bx` (from −x) and row `row` (from +y).
pub fn code_bit(code: u16, bx: usize, row: usize) -> u16 {
    u16::from(code & bit_mask(bx, row) != 0)
}

/// The code a marker shows, from which of its cells are white: `white(cx, cy)` with cx from
/// −x and cy from −y in `1..5` (the inner cells; the inverse of [`marker_cell_black`]).
pub fn code_from_cells(white: impl Fn(usize, usize) -> bool) -> u16 {
    let mut code = 0u16;
    for row in 0..4 {
        for bx in 0..4 {
            if white(bx + 1, MARKER_CELLS - 2 - row) {
                code |= bit_mask(bx, row);
            }
        }
    }
    code
}

/// `code` turned by 90° counter-clockwise (seen with +y up): the bit at (column, row)
/// moves to (row, 3 − column).
pub fn rotate_code(code: u16) -> u16 {
    let mut out = 0u16;
    for row in 0..4 {
        for bx in 0..4 {
            if code_bit(code, bx, row) == 1 {
                // counter-clockwise: column c, row r (from top) → column r, row 3 − c
                out |= bit_mask(row, 3 - bx);
            }
        }
    }
    out
}

/// `code` turned by `quarter_turns` × 90° counter-clockwise.
pub fn rotate_code_by(code: u16, quarter_turns: usize) -> u16 {
    (0..quarter_turns % 4).fold(code, |c, _| rotate_code(c))
}

/// Whether the 4 × 4 bits hold a 2 × 2 checker block (an X-junction inside the marker).
fn has_x_junction(code: u16) -> bool {
    (0..3).any(|row| {
        (0..3).any(|bx| {
            let (a, b) = (code_bit(code, bx, row), code_bit(code, bx + 1, row));
            let (c, d) = (code_bit(code, bx, row + 1), code_bit(code, bx + 1, row + 1));
            a == d && b == c && a != b
        })
    })
}

/// The marker dictionary (see the module docs for how it is made and what it guarantees).
pub fn dictionary() -> &'static [u16] {
    static DICT: OnceLock<Vec<u16>> = OnceLock::new();
    DICT.get_or_init(|| {
        let mut kept: Vec<u16> = Vec::new();
        for k in 0u32..65536 {
            // A fixed odd multiplier visits every 16-bit value once, in scattered order.
            let code = (k.wrapping_mul(40_503) ^ 0x5A3C) as u16;
            let ones = code.count_ones();
            if !(4..=12).contains(&ones) || has_x_junction(code) {
                continue;
            }
            let self_ok = (1..4).all(|r| (code ^ rotate_code_by(code, r)).count_ones() >= MIN_DISTANCE);
            if !self_ok {
                continue;
            }
            let far = kept
                .iter()
                .all(|&c| (0..4).all(|r| (code ^ rotate_code_by(c, r)).count_ones() >= MIN_DISTANCE));
            if far {
                kept.push(code);
            }
        }
        kept
    })
}

/// The dictionary entry closest to `read` over the four rotations: `(id, quarter turns r,
/// distance)` such that `read` ≈ `rotate_code_by(dictionary()[id], r)`. `None` if no entry
/// is within `max_distance` bits (at most `(MIN_DISTANCE − 1) / 2` keeps the answer unique).
pub fn decode(read: u16, max_distance: u32) -> Option<(usize, usize, u32)> {
    let mut best: Option<(usize, usize, u32)> = None;
    for (id, &c) in dictionary().iter().enumerate() {
        for r in 0..4 {
            let d = (read ^ rotate_code_by(c, r)).count_ones();
            if d <= max_distance && best.is_none_or(|b| d < b.2) {
                best = Some((id, r, d));
            }
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    fn board() -> CodedBoardSpec {
        CodedBoardSpec {
            squares_x: 8,
            squares_y: 8,
            pitch_mm: 11.0,
            marker_mm: 6.6,
            first_id: 0,
        }
    }

    #[test]
    fn dictionary_keeps_its_promises() {
        let d = dictionary();
        assert!(d.len() >= 50, "only {} codes", d.len());
        for (i, &a) in d.iter().enumerate() {
            assert!(!has_x_junction(a));
            assert!((4..=12).contains(&a.count_ones()));
            for r in 1..4 {
                assert!((a ^ rotate_code_by(a, r)).count_ones() >= MIN_DISTANCE);
            }
            for &b in &d[i + 1..] {
                for r in 0..4 {
                    assert!((a ^ rotate_code_by(b, r)).count_ones() >= MIN_DISTANCE);
                }
            }
        }
    }

    #[test]
    fn cells_and_codes_agree() {
        for &c in dictionary().iter().take(10) {
            assert_eq!(code_from_cells(|cx, cy| !marker_cell_black(c, cx, cy)), c);
        }
    }

    #[test]
    fn rotation_is_a_quarter_turn() {
        let c = 0b1000_0000_0000_0000; // top-left bit
        assert_eq!(rotate_code(c), 0b0000_0000_0000_1000, "top-left → bottom-left");
        for &c in dictionary().iter().take(10) {
            assert_eq!(rotate_code_by(c, 4), c);
        }
    }

    #[test]
    fn one_bit_errors_are_corrected_and_black_is_not_a_marker() {
        for (id, &c) in dictionary().iter().enumerate() {
            for r in 0..4 {
                let seen = rotate_code_by(c, r) ^ (1 << ((id + r) % 16));
                assert_eq!(decode(seen, 1).map(|d| (d.0, d.1)), Some((id, r)));
            }
        }
        assert_eq!(decode(0, 1), None);
        assert_eq!(decode(0xFFFF, 1), None);
    }

    #[test]
    fn ids_and_squares_agree() {
        let b = board();
        b.validate().unwrap();
        assert_eq!(b.marker_count(), 32);
        let mut seen = 0;
        for sb in 0..8 {
            for sa in 0..8 {
                if let Some(id) = b.marker_id(sa, sb) {
                    assert_eq!(b.square_of(id), Some((sa, sb)));
                    seen += 1;
                }
            }
        }
        assert_eq!(seen, 32);
        assert_eq!(b.square_of(32), None);
    }

    #[test]
    fn pattern_matches_the_layout() {
        let b = board();
        // Square (0, 0) is black; square (1, 0) white with marker 0.
        assert!(b.is_black(-43.0, -43.0));
        assert_eq!(b.marker_id(1, 0), Some(0));
        // The margin of square (1, 0) is white, the marker's ring black.
        let (x0, y0) = (-44.0 + 11.0, -44.0);
        assert!(!b.is_black(x0 + 1.0, y0 + 1.0));
        assert!(b.is_black(x0 + 2.2 + 0.5, y0 + 2.2 + 0.5));
        // Inner cell (column 0, row 0 from the top) carries bit 15.
        let cell = 6.6 / 6.0;
        let (x, y) = (x0 + 2.2 + 1.5 * cell, y0 + 2.2 + 4.5 * cell);
        assert_eq!(b.is_black(x, y), code_bit(dictionary()[0], 0, 0) == 0);
        // Corner (0, 0) sits at the meeting of squares (0..2, 0..2).
        assert_eq!(b.corner_point(0, 0), [-33.0, -33.0]);
        assert!(!b.is_black(100.0, 0.0), "off the board: white");
    }

    #[test]
    fn bad_boards_are_refused_by_name() {
        let mut b = board();
        b.marker_mm = 10.0;
        assert!(b.validate().unwrap_err().contains("marker_mm"));
        let mut b = board();
        b.squares_x = 40;
        b.squares_y = 40;
        assert!(b.validate().unwrap_err().contains("dictionary"));
    }
}
