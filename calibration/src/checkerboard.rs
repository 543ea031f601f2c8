//! Checkerboard corner detection with sub-pixel refinement, for camera calibration.
//!
//! 1. Frame checks first, so a useless frame gets a diagnosis rather than "not found":
//!    an empty (black, or uniform) frame and a saturated one are reported as such.
//! 2. Candidates: saddle points of the Gaussian-smoothed image (the Hessian determinant is
//!    strongly negative only where two dark and two bright quadrants meet), kept if a
//!    circle around them crosses the mean level exactly four times. This rejects the
//!    L-shaped corners of the holder's markers and of the board's outer squares, which
//!    cross it twice.
//! 3. Grid: grown from the candidate nearest the centroid by predicting each neighbour from
//!    the local grid vectors (updated as it grows, so perspective is followed), then checked
//!    to be exactly the expected `cols × rows` with every node present.
//! 4. Sub-pixel: the cornerSubPix principle — at the true corner q every image gradient g
//!    at p in the window is orthogonal to p − q — solved by weighted least squares on a
//!    bilinearly resampled window re-centred on each iterate, with the window sized to the
//!    local square size so it never reaches the next corner.
//!
//! Pixel convention: pixel (i, j) has its centre at (i + ½, j + ½).

use gonio_devices::image::RgbImage;
use nalgebra::{Matrix2, Vector2};
use serde::{Deserialize, Serialize};
use std::collections::{HashMap, VecDeque};
use thiserror::Error;

/// The board: inner corners along its x and y axes and their pitch.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CheckerboardSpec {
    /// Inner corners along the target's x axis.
    pub cols: usize,
    /// Inner corners along the target's y axis.
    pub rows: usize,
    /// Square size (mm).
    pub pitch_mm: f64,
}

impl CheckerboardSpec {
    /// Target-plane position (mm) of inner corner (i, j): the board is centred on the
    /// origin, i grows with +x and j with +y.
    pub fn object_point(&self, i: usize, j: usize) -> [f64; 2] {
        [
            (i as f64 - (self.cols as f64 - 1.0) / 2.0) * self.pitch_mm,
            (j as f64 - (self.rows as f64 - 1.0) / 2.0) * self.pitch_mm,
        ]
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CheckerboardOptions {
    /// Gaussian σ (pixels) of the smoothing before the saddle detector.
    pub smoothing_px: f64,
    /// Radius (pixels) of the four-crossings circle test; must be below half a square.
    pub ring_radius_px: f64,
    /// A candidate's ring contrast must exceed this fraction of the frame's contrast.
    pub min_contrast: f64,
    /// Values at or above this are saturated (linear frame units).
    pub saturation_level: f32,
    /// Frames where more than this fraction of the bright pixels is saturated are reported
    /// as saturated when no board is found.
    pub max_saturated_fraction: f64,
    /// Largest sub-pixel window half-size (pixels).
    pub max_window_px: usize,
    /// Refine every corner further by fitting a model of the blurred X-junction to the
    /// raw pixels ([`crate::corner_model`]): several times more accurate than the gradient
    /// estimate alone, which a narrow-field camera needs. `false` keeps the gradient
    /// estimate (faster, ≈ 0.02–0.07 px on rendered boards).
    pub model_fit: bool,
    /// Largest radius (pixels) of the model fit's window; it is also kept below half the
    /// local square size so no neighbouring corner enters it.
    pub max_model_radius_px: f64,
    /// Frames whose 1st–99th percentile spread is below this fraction of
    /// `saturation_level` are empty (black, lens cap, light off): too little signal for
    /// corners, whatever the detector would make of the noise.
    pub min_frame_contrast: f64,
    /// Coded boards only: markers that must agree on a grid's labelling before its corners
    /// are named (one misread marker must not name a grid).
    pub min_markers: usize,
    /// Fewest corners a partial view must give (coded boards always, plain checkerboards
    /// with `partial`): it is used if it has this many, over at least two rows and two
    /// columns.
    pub min_corners: usize,
    /// Plain checkerboards: accept a view that shows only part of the board (a board larger
    /// than the field of view, one cut off by the frame). The corners of the connected piece
    /// seen are indexed from the piece, not from the board: which printed corner is which
    /// is not known, only their lattice. That is all a fit needs where every view has its
    /// own free board pose (intrinsics): another labelling of the same lattice is a rigid
    /// motion of the board in its plane, which the view's pose absorbs. Not for fits that
    /// use the board's absolute position (rig geometry, mechanical); recipes refuse it
    /// there. Corners closer to the frame's edge than the corner model's window, and
    /// corners whose refinement fails, are left out. A view showing the whole board still
    /// gives the board's own labelling.
    pub partial: bool,
    /// Coded boards only: a corner whose model fit leaves an RMS residual (as a fraction of
    /// the corner's contrast) above the view's median by more than this, in quadrature, is
    /// left out: something else lies in its window.
    pub max_corner_residual: f64,
}

impl Default for CheckerboardOptions {
    fn default() -> Self {
        CheckerboardOptions {
            smoothing_px: 1.2,
            ring_radius_px: 3.5,
            min_contrast: 0.15,
            saturation_level: 1.0,
            max_saturated_fraction: 0.2,
            max_window_px: 6,
            model_fit: true,
            max_model_radius_px: 8.0,
            min_frame_contrast: 0.01,
            min_markers: 2,
            min_corners: 8,
            max_corner_residual: 0.02,
            partial: false,
        }
    }
}

/// A detected board: corners in grid order (i fastest), their target-plane points.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CheckerboardDetection {
    pub image: Vec<[f64; 2]>,
    pub object: Vec<[f64; 2]>,
    /// Saddle candidates found before the grid was grown (diagnostics).
    pub candidates: usize,
    /// Mean distance the sub-pixel step moved the corners (pixels).
    pub mean_refinement_px: f64,
    /// Coded boards: the ids of the markers that named the corners (empty for a plain
    /// checkerboard).
    #[serde(default)]
    pub markers: Vec<usize>,
    /// Coded boards: corners that were named but whose refinement failed, left out.
    #[serde(default)]
    pub dropped_corners: usize,
}

#[derive(Debug, Error, Clone, PartialEq)]
pub enum CheckerboardError {
    #[error("checkerboard: empty frame: almost no contrast (1st–99th percentile {p1:.4}–{p99:.4} of full scale); is the light on, the lens cap off, the target in view?")]
    Empty { p1: f32, p99: f32 },
    #[error(
        "checkerboard: saturated frame: {percent:.1} % of the bright pixels at or above {level}; shorten the exposure"
    )]
    Saturated { percent: f64, level: f32 },
    #[error("checkerboard: the board was not found: {found} corner candidates, grid of {grid_cols}×{grid_rows} grown, expected {cols}×{rows} inner corners ({hint})")]
    NotFound {
        found: usize,
        grid_cols: usize,
        grid_rows: usize,
        cols: usize,
        rows: usize,
        hint: String,
    },
    #[error("checkerboard: image of {width}×{height} pixels has {len} values, expected width·height·3")]
    BadImage { width: usize, height: usize, len: usize },
    #[error("checkerboard: invalid spec: {0}")]
    BadSpec(String),
}

/// A single-channel image, row-major.
pub(crate) struct Gray {
    pub w: usize,
    pub h: usize,
    pub d: Vec<f32>,
}

impl Gray {
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> f32 {
        self.d[y * self.w + x]
    }
    /// Bilinear value at pixel coordinates (u, v) (centres at half-integers), clamped.
    #[inline]
    pub fn sample(&self, u: f64, v: f64) -> f64 {
        let x = (u - 0.5).clamp(0.0, (self.w - 1) as f64);
        let y = (v - 0.5).clamp(0.0, (self.h - 1) as f64);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(self.w - 1), (y0 + 1).min(self.h - 1));
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let a = self.at(x0, y0) as f64 * (1.0 - fx) + self.at(x1, y0) as f64 * fx;
        let b = self.at(x0, y1) as f64 * (1.0 - fx) + self.at(x1, y1) as f64 * fx;
        a * (1.0 - fy) + b * fy
    }
}

fn gaussian_blur(g: &Gray, sigma: f64) -> Gray {
    if sigma <= 0.0 {
        return Gray {
            w: g.w,
            h: g.h,
            d: g.d.clone(),
        };
    }
    let r = (3.0 * sigma).ceil() as isize;
    let k: Vec<f32> = (-r..=r)
        .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    let ks: f32 = k.iter().sum();
    let k: Vec<f32> = k.iter().map(|v| v / ks).collect();
    let (w, h) = (g.w as isize, g.h as isize);
    let mut tmp = vec![0.0f32; g.d.len()];
    for y in 0..h {
        for x in 0..w {
            let mut s = 0.0;
            for (t, kv) in k.iter().enumerate() {
                let xx = (x + t as isize - r).clamp(0, w - 1);
                s += kv * g.d[(y * w + xx) as usize];
            }
            tmp[(y * w + x) as usize] = s;
        }
    }
    let mut out = vec![0.0f32; g.d.len()];
    for y in 0..h {
        for x in 0..w {
            let mut s = 0.0;
            for (t, kv) in k.iter().enumerate() {
                let yy = (y + t as isize - r).clamp(0, h - 1);
                s += kv * tmp[(yy * w + x) as usize];
            }
            out[(y * w + x) as usize] = s;
        }
    }
    Gray { w: g.w, h: g.h, d: out }
}

/// Detect a `spec.cols × spec.rows` checkerboard in a linear RGB frame.
pub fn detect_checkerboard(
    img: &RgbImage,
    spec: &CheckerboardSpec,
    opts: &CheckerboardOptions,
) -> Result<CheckerboardDetection, CheckerboardError> {
    if spec.cols < 2 || spec.rows < 2 || !(spec.pitch_mm > 0.0 && spec.pitch_mm.is_finite()) {
        return Err(CheckerboardError::BadSpec(format!(
            "{}×{} inner corners, pitch {} mm: need ≥ 2×2 corners and a pitch > 0",
            spec.cols, spec.rows, spec.pitch_mm
        )));
    }
    let frame = prepare_frame(img, opts)?;
    let result = detect_inner(&frame.gray, spec, opts, frame.contrast);
    frame.explain(result, opts)
}

/// A frame that passed the frame-level checks: its luminance, contrast and clipping.
pub(crate) struct Frame {
    pub gray: Gray,
    /// 1st–99th percentile spread (frame units).
    pub contrast: f64,
    /// Fraction of the bright pixels that clip.
    pub saturated: f64,
}

impl Frame {
    /// A board not found in a frame that clips a lot is reported as saturated: clipping is
    /// the likelier cause, and shortening the exposure the fix.
    pub fn explain<T>(
        &self,
        r: Result<T, CheckerboardError>,
        opts: &CheckerboardOptions,
    ) -> Result<T, CheckerboardError> {
        match r {
            Err(_) if self.saturated > opts.max_saturated_fraction => Err(CheckerboardError::Saturated {
                percent: 100.0 * self.saturated,
                level: opts.saturation_level,
            }),
            other => other,
        }
    }
}

/// Luminance and the frame-level diagnosis: a useless frame (empty, black, saturated)
/// gets its own error before any corner is looked for.
pub(crate) fn prepare_frame(img: &RgbImage, opts: &CheckerboardOptions) -> Result<Frame, CheckerboardError> {
    if img.data.len() != img.width * img.height * 3 || img.width < 8 || img.height < 8 {
        return Err(CheckerboardError::BadImage {
            width: img.width,
            height: img.height,
            len: img.data.len(),
        });
    }
    let gray = Gray {
        w: img.width,
        h: img.height,
        d: img
            .data
            .chunks_exact(3)
            .map(|c| {
                let v = (c[0] + c[1] + c[2]) / 3.0;
                if v.is_finite() {
                    v
                } else {
                    0.0
                }
            })
            .collect(),
    };
    // Frame-level diagnosis.
    let mut sorted = gray.d.clone();
    sorted.sort_by(f32::total_cmp);
    let pct = |p: f64| sorted[((sorted.len() - 1) as f64 * p) as usize];
    let (p1, p99) = (pct(0.01), pct(0.99));
    // Saturation is judged among the bright pixels (above half-way from the dark floor to
    // the maximum): a board filling a tenth of the frame is fully clipped even though most
    // of the frame is dark background.
    let bright_level = p1 + 0.5 * (sorted[sorted.len() - 1] - p1);
    let (mut lit, mut clipped) = (0usize, 0usize);
    for (c, &gv) in img.data.chunks_exact(3).zip(&gray.d) {
        if gv >= bright_level {
            lit += 1;
            if c.iter().any(|&v| v >= opts.saturation_level) {
                clipped += 1;
            }
        }
    }
    let saturated = clipped as f64 / lit.max(1) as f64;
    let frame_contrast = p99 - p1;
    // NaN-safe: a NaN contrast counts as no contrast.
    let enough =
        frame_contrast > 0.0 && frame_contrast as f64 >= opts.min_frame_contrast * opts.saturation_level as f64;
    if !enough {
        if saturated > opts.max_saturated_fraction {
            return Err(CheckerboardError::Saturated {
                percent: 100.0 * saturated,
                level: opts.saturation_level,
            });
        }
        return Err(CheckerboardError::Empty { p1, p99 });
    }
    Ok(Frame {
        gray,
        contrast: frame_contrast as f64,
        saturated,
    })
}

/// Saddle-point corner candidates (module docs, step 2) and the smoothed image they were
/// found on.
pub(crate) fn saddle_candidates(gray: &Gray, opts: &CheckerboardOptions, frame_contrast: f64) -> (Gray, Vec<[f64; 2]>) {
    let smooth = gaussian_blur(gray, opts.smoothing_px);
    let (w, h) = (gray.w, gray.h);
    // Saddle response: −det(Hessian) of the smoothed image.
    let mut resp = vec![0.0f32; w * h];
    let mut max_resp = 0.0f32;
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let c = smooth.at(x, y);
            let fxx = smooth.at(x + 1, y) - 2.0 * c + smooth.at(x - 1, y);
            let fyy = smooth.at(x, y + 1) - 2.0 * c + smooth.at(x, y - 1);
            let fxy = (smooth.at(x + 1, y + 1) - smooth.at(x - 1, y + 1) - smooth.at(x + 1, y - 1)
                + smooth.at(x - 1, y - 1))
                / 4.0;
            let s = fxy * fxy - fxx * fyy;
            if s > 0.0 {
                resp[y * w + x] = s;
                max_resp = max_resp.max(s);
            }
        }
    }
    let thresh = 0.02 * max_resp;
    let ring = opts.ring_radius_px.max(1.5);
    let margin = (ring.ceil() as usize + 2).min(w / 2).min(h / 2);
    let mut candidates: Vec<[f64; 2]> = Vec::new();
    const NMS: isize = 2;
    for y in margin..h - margin {
        for x in margin..w - margin {
            let s = resp[y * w + x];
            if s <= thresh {
                continue;
            }
            let mut is_max = true;
            'n: for dy in -NMS..=NMS {
                for dx in -NMS..=NMS {
                    if dx == 0 && dy == 0 {
                        continue;
                    }
                    let (xx, yy) = ((x as isize + dx) as usize, (y as isize + dy) as usize);
                    let o = resp[yy * w + xx];
                    // ties broken toward the first (top-left) pixel
                    if o > s || (o == s && (dy < 0 || (dy == 0 && dx < 0))) {
                        is_max = false;
                        break 'n;
                    }
                }
            }
            if !is_max {
                continue;
            }
            let (u, v) = (x as f64 + 0.5, y as f64 + 0.5);
            if ring_crossings(&smooth, u, v, ring, opts.min_contrast * frame_contrast) {
                candidates.push([u, v]);
            }
        }
    }
    (smooth, candidates)
}

/// A grown grid's index range: (i_min, i_max, j_min, j_max).
pub(crate) fn grid_bounds(grid: &HashMap<(i64, i64), usize>) -> (i64, i64, i64, i64) {
    grid.keys()
        .fold((i64::MAX, i64::MIN, i64::MAX, i64::MIN), |(a, b, c, d), &(i, j)| {
            (a.min(i), b.max(i), c.min(j), d.max(j))
        })
}

/// The candidate nearest the candidates' centroid, among those not `taken`.
pub(crate) fn central_seed(pts: &[[f64; 2]], taken: &[bool]) -> Option<usize> {
    let free: Vec<usize> = (0..pts.len()).filter(|&k| !taken[k]).collect();
    if free.is_empty() {
        return None;
    }
    let n = free.len() as f64;
    let cx = free.iter().map(|&k| pts[k][0]).sum::<f64>() / n;
    let cy = free.iter().map(|&k| pts[k][1]).sum::<f64>() / n;
    let d2 = |k: usize| (pts[k][0] - cx).powi(2) + (pts[k][1] - cy).powi(2);
    free.into_iter().min_by(|&a, &b| d2(a).total_cmp(&d2(b)))
}

fn detect_inner(
    gray: &Gray,
    spec: &CheckerboardSpec,
    opts: &CheckerboardOptions,
    frame_contrast: f64,
) -> Result<CheckerboardDetection, CheckerboardError> {
    let (smooth, candidates) = saddle_candidates(gray, opts, frame_contrast);
    let found = candidates.len();
    let not_found = |gc: usize, gr: usize, hint: &str| CheckerboardError::NotFound {
        found,
        grid_cols: gc,
        grid_rows: gr,
        cols: spec.cols,
        rows: spec.rows,
        hint: hint.into(),
    };
    if found
        < if opts.partial {
            opts.min_corners.max(4)
        } else {
            spec.cols * spec.rows
        }
    {
        return Err(not_found(
            0,
            0,
            if opts.partial {
                "too few corner candidates: board out of view, occluded, too blurred or too small"
            } else {
                "too few corner candidates: board out of view, occluded, too blurred or too small; \
                 `partial = true` under [detection] accepts part of the board for intrinsics"
            },
        ));
    }
    let grid = match central_seed(&candidates, &vec![false; found]) {
        Some(seed) => grow_grid(&candidates, &smooth, seed, &vec![false; found], 0.25),
        None => HashMap::new(),
    };
    let (imin, imax, jmin, jmax) = grid_bounds(&grid);
    let (gc, gr) = ((imax - imin + 1) as usize, (jmax - jmin + 1) as usize);
    let (cols, rows) = (spec.cols, spec.rows);
    // The grown grid may carry stray X-junctions next to the board (a holder marker
    // touching a dark square at its corner): keep the unique complete window of the
    // board's size, in either orientation.
    let mut windows = Vec::new();
    for (wc, wr, swap) in [(cols, rows, false), (rows, cols, true)] {
        if wc > gc || wr > gr || (swap && cols == rows) {
            continue;
        }
        for i0 in imin..=imax - wc as i64 + 1 {
            for j0 in jmin..=jmax - wr as i64 + 1 {
                let full = (0..wc as i64).all(|di| (0..wr as i64).all(|dj| grid.contains_key(&(i0 + di, j0 + dj))));
                if full {
                    windows.push((i0, j0, wc as i64, wr as i64, swap));
                }
            }
        }
    }
    let complete = match windows.as_slice() {
        [one] => Some(*one),
        [] if opts.partial => None,
        [] => {
            let hint = if grid.len() < cols * rows {
                "corners missing (occlusion, glare, part of the board out of view, too grazing a view; \
                 `partial = true` under [detection] accepts part of the board for intrinsics)"
            } else {
                "no complete board-sized window in the grid: holes, or a wrong board spec"
            };
            return Err(not_found(gc, gr, hint));
        }
        _ => {
            return Err(not_found(
                gc,
                gr,
                "more than one board-sized window: wrong board spec (too small)?",
            ))
        }
    };
    // A partial view: the whole grown piece, if it fits the board in one orientation.
    let (i0, j0, wc, wr, swap) = match complete {
        Some(w) => w,
        None => {
            let swap = if gc <= cols && gr <= rows {
                false
            } else if gc <= rows && gr <= cols {
                true
            } else {
                return Err(not_found(
                    gc,
                    gr,
                    "the piece of board seen is larger than the board: wrong board spec (too small)?",
                ));
            };
            (imin, jmin, gc as i64, gr as i64, swap)
        }
    };
    // Normalize indices to start at 0 and arrange the axes so that i runs along the
    // board's `cols`, the (i, j) → (x, y) map is a proper rotation seen from the camera
    // (no mirror), and — for determinism — the i axis points as far right as possible.
    let mut pts: Vec<((i64, i64), usize)> = grid
        .iter()
        .filter(|(&(i, j), _)| i >= i0 && i < i0 + wc && j >= j0 && j < j0 + wr)
        .map(|(&(i, j), &k)| ((i - i0, j - j0), k))
        .collect();
    // fixed order, whatever the hash map's
    pts.sort_unstable();
    let (mut nc, mut nr) = (wc, wr);
    if swap {
        for p in pts.iter_mut() {
            p.0 = (p.0 .1, p.0 .0);
        }
        std::mem::swap(&mut nc, &mut nr);
    }
    let lookup = |pts: &[((i64, i64), usize)], i: i64, j: i64| pts.iter().find(|p| p.0 == (i, j)).map(|p| p.1);
    // The image directions of the board's i and j axes: corner to corner on a complete
    // board; on a piece, the sum of every step between neighbours along each axis.
    let axis_dirs = |pts: &[((i64, i64), usize)]| -> ([f64; 2], [f64; 2]) {
        if complete.is_some() {
            let p00 = candidates[lookup(pts, 0, 0).expect("complete grid")];
            let pi = candidates[lookup(pts, nc - 1, 0).expect("complete grid")];
            let pj = candidates[lookup(pts, 0, nr - 1).expect("complete grid")];
            return ([pi[0] - p00[0], pi[1] - p00[1]], [pj[0] - p00[0], pj[1] - p00[1]]);
        }
        let (mut a, mut b) = ([0.0; 2], [0.0; 2]);
        for &((i, j), k) in pts {
            let p = candidates[k];
            if let Some(m) = lookup(pts, i + 1, j) {
                a = [a[0] + candidates[m][0] - p[0], a[1] + candidates[m][1] - p[1]];
            }
            if let Some(m) = lookup(pts, i, j + 1) {
                b = [b[0] + candidates[m][0] - p[0], b[1] + candidates[m][1] - p[1]];
            }
        }
        (a, b)
    };
    let (a, b) = axis_dirs(&pts);
    // Seen from the camera, +x → +u and +y → −v: the image cross product a × b is negative.
    if a[0] * b[1] - a[1] * b[0] > 0.0 {
        for p in pts.iter_mut() {
            p.0 .1 = nr - 1 - p.0 .1;
        }
    }
    // Candidate symmetries keeping handedness: 180° always; 90° steps if square (the
    // window's for a complete board, the board's for a piece, whose extent may then swap).
    let square = if complete.is_some() { nc == nr } else { cols == rows };
    let rotations: &[u8] = if square { &[0, 1, 2, 3] } else { &[0, 2] };
    let rotate = |p: (i64, i64), r: u8| -> (i64, i64) {
        match r {
            0 => p,
            1 => (p.1, nc - 1 - p.0),
            2 => (nc - 1 - p.0, nr - 1 - p.1),
            _ => (nr - 1 - p.1, p.0),
        }
    };
    let mut best = (f64::NEG_INFINITY, 0u8);
    for &r in rotations {
        let rp: Vec<_> = pts.iter().map(|&(ij, k)| (rotate(ij, r), k)).collect();
        let (a, _) = axis_dirs(&rp);
        let score = a[0] / (a[0].hypot(a[1]) + 1e-12);
        if score > best.0 + 1e-9 {
            best = (score, r);
        }
    }
    let mut pts: Vec<_> = pts.iter().map(|&(ij, k)| (rotate(ij, best.1), k)).collect();
    pts.sort_unstable_by_key(|&((i, j), _)| (j, i));
    let node: HashMap<(i64, i64), usize> = pts.iter().copied().collect();
    let at = |i: i64, j: i64| node.get(&(i, j)).map(|&k| candidates[k]);
    // Partial views: corners whose refinement windows would leave the frame are left out.
    let border = if opts.model_fit {
        1.5 * opts.max_model_radius_px + 2.0
    } else {
        opts.max_window_px as f64 + 2.0
    };
    let inside = |p: [f64; 2]| {
        p[0] >= border && p[1] >= border && p[0] <= gray.w as f64 - border && p[1] <= gray.h as f64 - border
    };
    // Sub-pixel refinement, window from the local grid spacing.
    // Corners are refined independently (in parallel); the first failure in grid order is
    // reported, so the message does not depend on the thread count. In a partial view a
    // corner that fails is left out instead.
    use rayon::prelude::*;
    let refined: Vec<Result<Option<[f64; 2]>, CheckerboardError>> = pts
        .par_iter()
        .map(|&((i, j), k)| {
            let p = candidates[k];
            if complete.is_none() && !inside(p) {
                return Ok(None);
            }
            let fail = |what: &str, q: [f64; 2], advice: &str| {
                if complete.is_none() {
                    return Ok(None);
                }
                Err(not_found(
                    cols,
                    rows,
                    &format!(
                        "{what} of corner ({i}, {j}) near ({:.1}, {:.1}) px failed{advice}",
                        q[0], q[1]
                    ),
                ))
            };
            let mut spacing = f64::INFINITY;
            for (di, dj) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                if let Some(q) = at(i + di, j + dj) {
                    spacing = spacing.min((q[0] - p[0]).hypot(q[1] - p[1]));
                }
            }
            if !spacing.is_finite() {
                return fail("sub-pixel refinement", p, " (no neighbour)");
            }
            let win = ((0.4 * spacing).floor() as usize).clamp(2, opts.max_window_px.max(2));
            let Some(q) = refine_corner(&smooth, p, win) else {
                return fail("sub-pixel refinement", p, "");
            };
            if !opts.model_fit {
                return Ok(Some(q));
            }
            match model_refine(gray, &at, (i, j), q, spacing, opts) {
                Some(m) => Ok(Some(m)),
                None => fail(
                    "corner model fit",
                    q,
                    " (set model_fit = false to keep the gradient estimate)",
                ),
            }
        })
        .collect();
    let mut image = Vec::with_capacity(pts.len());
    let mut object = Vec::with_capacity(pts.len());
    let mut moved = 0.0;
    let mut dropped = 0;
    for (&((i, j), k), r) in pts.iter().zip(refined) {
        let Some(q) = r? else {
            dropped += 1;
            continue;
        };
        let p = candidates[k];
        moved += (q[0] - p[0]).hypot(q[1] - p[1]);
        image.push(q);
        object.push(spec.object_point(i as usize, j as usize));
    }
    if complete.is_none() {
        let distinct = |f: fn(&[f64; 2]) -> f64| {
            let mut v: Vec<i64> = object.iter().map(|o| (f(o) / spec.pitch_mm).round() as i64).collect();
            v.sort_unstable();
            v.dedup();
            v.len()
        };
        let need = opts.min_corners.max(4);
        if image.len() < need || distinct(|o| o[0]) < 2 || distinct(|o| o[1]) < 2 {
            return Err(not_found(
                gc,
                gr,
                &format!(
                    "partial view: {} usable corners, at least {need} over two rows and two columns are needed",
                    image.len()
                ),
            ));
        }
    }
    Ok(CheckerboardDetection {
        candidates: found,
        mean_refinement_px: moved / image.len().max(1) as f64,
        image,
        object,
        markers: Vec::new(),
        dropped_corners: dropped,
    })
}

/// The model fit of corner (i, j) ([`crate::corner_model::fit_corner`]) on the raw pixels,
/// started at the gradient estimate `q`, with the board axes' image directions from the
/// neighbouring corners (`at`; both sides where present, so perspective is followed).
fn model_refine(
    gray: &Gray,
    at: &(dyn Fn(i64, i64) -> Option<[f64; 2]> + Sync),
    (i, j): (i64, i64),
    q: [f64; 2],
    spacing: f64,
    opts: &CheckerboardOptions,
) -> Option<[f64; 2]> {
    let axis = |prev: Option<[f64; 2]>, next: Option<[f64; 2]>| -> Option<f64> {
        let (a, b) = match (prev, next) {
            (Some(a), Some(b)) => (a, b),
            (None, Some(b)) => (q, b),
            (Some(a), None) => (a, q),
            (None, None) => return None,
        };
        Some((b[1] - a[1]).atan2(b[0] - a[0]))
    };
    let di = axis(at(i - 1, j), at(i + 1, j));
    let dj = axis(at(i, j - 1), at(i, j + 1));
    // A corner of a piece with neighbours along one axis only takes the other direction
    // as the image perpendicular (the fit estimates both).
    let (di, dj) = match (di, dj) {
        (Some(a), Some(b)) => (a, b),
        (Some(a), None) => (a, a - std::f64::consts::FRAC_PI_2),
        (None, Some(b)) => (b + std::f64::consts::FRAC_PI_2, b),
        (None, None) => (0.0, 0.0),
    };
    let radius = (0.45 * spacing).min(opts.max_model_radius_px);
    if radius < 2.5 {
        return None;
    }
    let px = |x: usize, y: usize| gray.at(x, y) as f64;
    crate::corner_model::fit_corner(&px, (gray.w, gray.h), q, [di, dj], radius, opts.saturation_level as f64)
        .map(|f| f.q)
}

/// The four-crossings test: a circle around an X-corner alternates dark, bright, dark,
/// bright; an L-corner (marker, board edge) only has one dark or one bright arc.
fn ring_crossings(g: &Gray, u: f64, v: f64, r: f64, min_contrast: f64) -> bool {
    const N: usize = 32;
    let vals: Vec<f64> = (0..N)
        .map(|k| {
            let a = k as f64 * std::f64::consts::TAU / N as f64;
            g.sample(u + r * a.cos(), v + r * a.sin())
        })
        .collect();
    let (lo, hi) = vals
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| (a.min(x), b.max(x)));
    if hi - lo < min_contrast {
        return false;
    }
    let mid = 0.5 * (lo + hi);
    let signs: Vec<bool> = vals.iter().map(|&x| x > mid).collect();
    let mut crossings = 0;
    let mut run = 0;
    let mut shortest = usize::MAX;
    // start at a crossing so runs are counted whole
    let start = (0..N).find(|&k| signs[k] != signs[(k + N - 1) % N]);
    let Some(start) = start else { return false };
    for t in 0..N {
        let k = (start + t) % N;
        if t > 0 && signs[k] != signs[(k + N - 1) % N] {
            crossings += 1;
            shortest = shortest.min(run);
            run = 0;
        }
        run += 1;
    }
    crossings += 1; // the crossing at `start`
    shortest = shortest.min(run);
    // Opposite quadrants must agree: a real X-corner's arcs are each ≥ 2 samples long.
    crossings == 4 && shortest >= 2
}

/// Grow a 4-connected grid from candidate `seed` over the candidates not `taken`.
/// `edge_offset` (a fraction of a step) is how far to each side of a step the image is
/// sampled to tell a board axis from a diagonal: within a square's plain part (a quarter
/// for a checkerboard; within the white margin for a coded board, whose markers would
/// otherwise make a diagonal through a white square look like an edge).
pub(crate) fn grow_grid(
    pts: &[[f64; 2]],
    smooth: &Gray,
    seed: usize,
    taken: &[bool],
    edge_offset: f64,
) -> HashMap<(i64, i64), usize> {
    let n = pts.len();
    let mut grid = HashMap::new();
    if n < 5 || taken[seed] {
        return grid;
    }
    let d2 = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2);
    // Local basis at the seed. Under strong perspective a diagonal of the grid can be
    // shorter than an axis, so neighbours are classified by the image, not by distance: a
    // step along a board axis follows an edge between a dark and a bright square (the two
    // sides of its midpoint differ), a diagonal step crosses the middle of one square.
    let mut near: Vec<usize> = (0..n).filter(|&k| k != seed && !taken[k]).collect();
    near.sort_by(|&a, &b| d2(pts[a], pts[seed]).total_cmp(&d2(pts[b], pts[seed])));
    // Enough neighbours that the board's own are among them even where small marks (a coded
    // board's marker cells at a grazing view) crowd the corner.
    near.truncate(24);
    let vec = |k: usize| [pts[k][0] - pts[seed][0], pts[k][1] - pts[seed][1]];
    // Sampled at three places along the step, `edge_offset` × its length to either side:
    // an edge has the same two colours all along it, with the same sign.
    let edge_score = |from: usize, to: usize| {
        let v = [pts[to][0] - pts[from][0], pts[to][1] - pts[from][1]];
        let len = v[0].hypot(v[1]).max(1e-9);
        let nrm = [-v[1] / len, v[0] / len];
        let off = edge_offset * len;
        let diffs: Vec<f64> = [0.3, 0.5, 0.7]
            .iter()
            .map(|&f| {
                let mid = [pts[from][0] + f * v[0], pts[from][1] + f * v[1]];
                smooth.sample(mid[0] + nrm[0] * off, mid[1] + nrm[1] * off)
                    - smooth.sample(mid[0] - nrm[0] * off, mid[1] - nrm[1] * off)
            })
            .collect();
        let same_sign = diffs.iter().all(|&d| d > 0.0) || diffs.iter().all(|&d| d < 0.0);
        if same_sign {
            diffs.iter().map(|d| d.abs()).fold(f64::INFINITY, f64::min)
        } else {
            0.0
        }
    };
    let scores: Vec<f64> = near.iter().map(|&k| edge_score(seed, k)).collect();
    let best_score = scores.iter().copied().fold(0.0, f64::max);
    let edges: Vec<usize> = near
        .iter()
        .zip(&scores)
        .filter(|(_, &s)| s >= 0.5 * best_score)
        .map(|(&k, _)| k)
        .collect();
    let Some(&first) = edges.first() else {
        return grid;
    };
    let e1 = vec(first);
    let Some(e2) = edges.iter().map(|&k| vec(k)).find(|v| {
        let c = (v[0] * e1[0] + v[1] * e1[1]) / (v[0].hypot(v[1]) * e1[0].hypot(e1[1]) + 1e-12);
        c.abs() < 0.95
    }) else {
        return grid;
    };
    let mut owner: HashMap<usize, (i64, i64)> = HashMap::new();
    let mut queue = VecDeque::new();
    grid.insert((0, 0), seed);
    owner.insert(seed, (0, 0));
    queue.push_back(((0i64, 0i64), seed, e1, e2));
    while let Some(((i, j), k, a, b)) = queue.pop_front() {
        let p = pts[k];
        for (di, dj, d) in [(1, 0, a), (-1, 0, [-a[0], -a[1]]), (0, 1, b), (0, -1, [-b[0], -b[1]])] {
            let key = (i + di, j + dj);
            if grid.contains_key(&key) {
                continue;
            }
            let q = [p[0] + d[0], p[1] + d[1]];
            let tol = 0.3 * a[0].hypot(a[1]).min(b[0].hypot(b[1]));
            // The nearest candidate to the prediction that is joined to this node by an
            // edge of the board (not a stray point beside the corner it should be).
            let mut near_q: Vec<usize> = (0..n).filter(|&m| !taken[m] && d2(pts[m], q) < tol * tol).collect();
            near_q.sort_by(|&x, &y| d2(pts[x], q).total_cmp(&d2(pts[y], q)));
            let best = near_q.into_iter().find(|&m| edge_score(k, m) >= 0.3 * best_score);
            let Some(m) = best else { continue };
            if owner.contains_key(&m) {
                continue;
            }
            grid.insert(key, m);
            owner.insert(m, key);
            let step = [pts[m][0] - p[0], pts[m][1] - p[1]];
            let (na, nb) = match (di, dj) {
                (1, 0) => (step, b),
                (-1, 0) => ([-step[0], -step[1]], b),
                (0, 1) => (a, step),
                _ => (a, [-step[0], -step[1]]),
            };
            queue.push_back((key, m, na, nb));
        }
    }
    grid
}

/// cornerSubPix-style refinement: solve Σ w g gᵀ q = Σ w g gᵀ p over the pixels within
/// `win` of the current estimate, iterated. The gradients are taken at pixel centres by
/// central differences of the original pixels (no resampling: bilinear interpolation is
/// not shift-invariant and biases the result by a few hundredths of a pixel); the
/// Gaussian weights follow the estimate, so the window stays centred on it. `None` if it
/// does not converge or wanders off by more than the window.
pub(crate) fn refine_corner(g: &Gray, start: [f64; 2], win: usize) -> Option<[f64; 2]> {
    let mut q = Vector2::new(start[0], start[1]);
    let reach = win as isize + 1;
    let sigma = win as f64 * 0.6;
    let (w, h) = (g.w as isize, g.h as isize);
    for _ in 0..50 {
        let (ci, cj) = ((q.x - 0.5).round() as isize, (q.y - 0.5).round() as isize);
        let mut a = Matrix2::zeros();
        let mut bv = Vector2::zeros();
        for y in cj - reach..=cj + reach {
            for x in ci - reach..=ci + reach {
                if x < 1 || y < 1 || x >= w - 1 || y >= h - 1 {
                    continue;
                }
                let p = Vector2::new(x as f64 + 0.5, y as f64 + 0.5);
                let r2 = (p - q).norm_squared();
                if r2 > ((win as f64) + 0.5).powi(2) {
                    continue;
                }
                let (xu, yu) = (x as usize, y as usize);
                let gx = 0.5 * (g.at(xu + 1, yu) - g.at(xu - 1, yu)) as f64;
                let gy = 0.5 * (g.at(xu, yu + 1) - g.at(xu, yu - 1)) as f64;
                let wt = (-r2 / (2.0 * sigma * sigma)).exp();
                let gg = Matrix2::new(gx * gx, gx * gy, gx * gy, gy * gy) * wt;
                a += gg;
                bv += gg * p;
            }
        }
        let next = a.try_inverse().map(|inv| inv * bv)?;
        if !(next.x.is_finite() && next.y.is_finite()) {
            return None;
        }
        let shift = (next - q).norm();
        q = next;
        if (q.x - start[0]).hypot(q.y - start[1]) > win as f64 {
            return None;
        }
        if shift < 1e-5 {
            break;
        }
    }
    Some([q.x, q.y])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::{gaussian_blur as blur_rgb, pose, rig_intrinsics, Rng};
    use crate::Homography;

    const SPEC: CheckerboardSpec = CheckerboardSpec {
        cols: 11,
        rows: 11,
        pitch_mm: 5.0,
    };

    /// Render the 60 mm board (12 × 12 squares of 5 mm, dark square at x, y ∈ [0, 5)) on a
    /// white 10 mm frame with black background, box-filtered over each pixel.
    fn render(h: &Homography, w: usize, ht: usize, ss: usize, level: (f32, f32)) -> RgbImage {
        let inv = h.inverse().unwrap();
        let mut img = RgbImage::new(w, ht);
        for y in 0..ht {
            for x in 0..w {
                let mut acc = 0.0f32;
                for k in 0..ss * ss {
                    let u = x as f64 + ((k % ss) as f64 + 0.5) / ss as f64;
                    let v = y as f64 + ((k / ss) as f64 + 0.5) / ss as f64;
                    let val = match inv.apply(u, v) {
                        Some((px, py)) if px.abs() < 30.0 && py.abs() < 30.0 => {
                            let (a, b) = ((px / 5.0).floor() as i64, (py / 5.0).floor() as i64);
                            if (a + b).rem_euclid(2) == 0 {
                                level.0
                            } else {
                                level.1
                            }
                        }
                        Some((px, py)) if px.abs() < 40.0 && py.abs() < 40.0 => level.1,
                        _ => 0.0,
                    };
                    acc += val;
                }
                let v = acc / (ss * ss) as f32;
                img.set(x, y, [v, v, v]);
            }
        }
        img
    }

    fn check(theta: f64, phi: f64, blur: f64, noise: f32, tol: f64) -> f64 {
        let intr = rig_intrinsics();
        let h = Homography::from_pose(&intr, &pose(theta, phi));
        let mut img = render(&h, 768, 640, 6, (0.04, 0.8));
        if blur > 0.0 {
            blur_rgb(&mut img, blur);
        }
        if noise > 0.0 {
            let mut rng = Rng::new(5);
            for v in img.data.iter_mut() {
                *v += noise * rng.normal() as f32;
            }
        }
        let d = detect_checkerboard(&img, &SPEC, &CheckerboardOptions::default()).unwrap();
        assert_eq!(d.image.len(), 121);
        // The grid may be any proper rotation of the board (the board is symmetric): take
        // the rotation that fits each corner best.
        let mut worst: f64 = 0.0;
        let mut sum = 0.0;
        for (o, i) in d.object.iter().zip(&d.image) {
            let best = (0..4)
                .map(|r| {
                    let (x, y) = match r {
                        0 => (o[0], o[1]),
                        1 => (-o[1], o[0]),
                        2 => (-o[0], -o[1]),
                        _ => (o[1], -o[0]),
                    };
                    let (u, v) = h.apply(x, y).unwrap();
                    (u - i[0]).hypot(v - i[1])
                })
                .fold(f64::INFINITY, f64::min);
            worst = worst.max(best);
            sum += best * best;
        }
        let rms = (sum / 121.0).sqrt();
        assert!(rms < tol, "θ={theta} φ={phi}: rms {rms} worst {worst}");
        rms
    }

    #[test]
    fn noiseless_views_are_subpixel_exact() {
        for &(t, p) in &[(0.0, 0.0), (30.0, 40.0), (50.0, 200.0), (65.0, 120.0)] {
            check(t, p, 0.0, 0.0, if t > 60.0 { 0.08 } else { 0.05 });
        }
    }

    #[test]
    fn robust_to_blur_and_noise() {
        check(20.0, 10.0, 1.5, 0.02, 0.08);
        check(45.0, 300.0, 1.0, 0.03, 0.12);
    }

    #[test]
    fn empty_and_saturated_frames_are_diagnosed() {
        let black = RgbImage::new(200, 150);
        assert!(matches!(
            detect_checkerboard(&black, &SPEC, &CheckerboardOptions::default()),
            Err(CheckerboardError::Empty { .. })
        ));
        let mut white = RgbImage::new(200, 150);
        white.data.iter_mut().for_each(|v| *v = 1.0);
        assert!(matches!(
            detect_checkerboard(&white, &SPEC, &CheckerboardOptions::default()),
            Err(CheckerboardError::Saturated { .. })
        ));
        // A board rendered so bright that both colours clip.
        let h = Homography::from_pose(&rig_intrinsics(), &pose(10.0, 0.0));
        let img = render(&h, 768, 640, 2, (1.0, 1.0));
        let e = detect_checkerboard(&img, &SPEC, &CheckerboardOptions::default()).unwrap_err();
        assert!(matches!(e, CheckerboardError::Saturated { .. }), "{e}");
    }

    #[test]
    fn wrong_spec_or_partial_board_is_not_found() {
        let h = Homography::from_pose(&rig_intrinsics(), &pose(20.0, 0.0));
        let img = render(&h, 768, 640, 2, (0.04, 0.8));
        let spec = CheckerboardSpec { cols: 9, ..SPEC };
        assert!(matches!(
            detect_checkerboard(&img, &spec, &CheckerboardOptions::default()),
            Err(CheckerboardError::NotFound { .. })
        ));
        // occlude a band across the board
        let mut img = img;
        for y in 300..330 {
            for x in 0..768 {
                img.set(x, y, [0.4, 0.4, 0.4]);
            }
        }
        assert!(matches!(
            detect_checkerboard(&img, &SPEC, &CheckerboardOptions::default()),
            Err(CheckerboardError::NotFound { .. })
        ));
    }

    /// `partial = true`: the piece of the board seen is taken, corners named up to the
    /// board's lattice (a proper rotation and a whole number of squares), each where the
    /// exact projection of some board corner is.
    #[test]
    fn partial_views_give_the_lattice_of_the_piece_seen() {
        // the frame ends across the board (a board larger than the field, cut by the frame)
        let h = Homography::from_pose(&rig_intrinsics(), &pose(20.0, 30.0));
        let img = render(&h, 420, 640, 6, (0.04, 0.8));
        let opts = CheckerboardOptions {
            partial: true,
            ..CheckerboardOptions::default()
        };
        let d = detect_checkerboard(&img, &SPEC, &opts).unwrap();
        assert!(d.image.len() >= 30 && d.image.len() < 121, "{}", d.image.len());
        let board: Vec<[f64; 2]> = (0..11)
            .flat_map(|j| (0..11).map(move |i| SPEC.object_point(i, j)))
            .collect();
        // the true board point of each detected corner: the nearest exact projection
        let truth: Vec<[f64; 2]> = d
            .image
            .iter()
            .map(|p| {
                let (b, e) = board
                    .iter()
                    .map(|o| {
                        let (u, v) = h.apply(o[0], o[1]).unwrap();
                        (*o, (u - p[0]).hypot(v - p[1]))
                    })
                    .min_by(|a, b| a.1.total_cmp(&b.1))
                    .unwrap();
                assert!(e < 0.08, "corner {p:?} is {e} px from the nearest board corner");
                b
            })
            .collect();
        // one proper rotation and one lattice shift map every true point to its label
        let rot = |o: [f64; 2], r: u8| match r {
            0 => o,
            1 => [-o[1], o[0]],
            2 => [-o[0], -o[1]],
            _ => [o[1], -o[0]],
        };
        let consistent = (0..4u8).any(|r| {
            let t0 = rot(truth[0], r);
            let shift = [d.object[0][0] - t0[0], d.object[0][1] - t0[1]];
            truth.iter().zip(&d.object).all(|(t, o)| {
                let t = rot(*t, r);
                (t[0] + shift[0] - o[0]).abs() < 1e-9 && (t[1] + shift[1] - o[1]).abs() < 1e-9
            })
        });
        assert!(consistent, "labels are not one rigid motion of the lattice");
        // without `partial` the same view is refused, naming the option
        let e = detect_checkerboard(&img, &SPEC, &CheckerboardOptions::default()).unwrap_err();
        assert!(e.to_string().contains("partial"), "{e}");
    }
}
