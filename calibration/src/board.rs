//! The calibration target a recipe names: a plain checkerboard (every corner must be in
//! view) or the coded-marker board (any part of it will do). Everything downstream (the
//! intrinsics, rig-geometry and mechanical fits) only sees corners and their board points,
//! so they take either.

use crate::checkerboard::{
    detect_checkerboard, CheckerboardDetection, CheckerboardError, CheckerboardOptions, CheckerboardSpec,
};
use crate::coded_board::detect_coded_board;
use gonio_devices::coded_board::CodedBoardSpec;
use gonio_devices::image::RgbImage;

/// A planar target with known corner positions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Board {
    Checkerboard(CheckerboardSpec),
    Coded(CodedBoardSpec),
}

impl Board {
    /// Find the board's corners in a linear RGB frame.
    pub fn detect(
        &self,
        img: &RgbImage,
        opts: &CheckerboardOptions,
    ) -> Result<CheckerboardDetection, CheckerboardError> {
        match self {
            Board::Checkerboard(spec) => detect_checkerboard(img, spec, opts),
            Board::Coded(spec) => detect_coded_board(img, spec, opts),
        }
    }

    /// Square size (mm).
    pub fn pitch_mm(&self) -> f64 {
        match self {
            Board::Checkerboard(spec) => spec.pitch_mm,
            Board::Coded(spec) => spec.pitch_mm,
        }
    }

    /// Every inner corner's board-plane position (mm), row by row: what a view showing the
    /// whole board gives (used to predict views before they are captured).
    pub fn all_corners(&self) -> Vec<[f64; 2]> {
        match self {
            Board::Checkerboard(spec) => (0..spec.rows)
                .flat_map(|j| (0..spec.cols).map(move |i| spec.object_point(i, j)))
                .collect(),
            Board::Coded(spec) => {
                let (nx, ny) = spec.corners();
                (0..ny)
                    .flat_map(|j| (0..nx).map(move |i| spec.corner_point(i, j)))
                    .collect()
            }
        }
    }
}
