//! Detection of the coded-marker board ([`gonio_devices::coded_board`]): a checkerboard
//! whose white squares carry markers with ids, so a partial view still names its corners.
//!
//! 1. Frame checks and saddle candidates exactly as for the plain checkerboard
//!    ([`crate::checkerboard`]). The board's markers have no X-junction inside (the
//!    dictionary guarantees it), so the candidates are the board's corners, plus a few
//!    strays where the holder's markers touch the board.
//! 2. Grids: grown from the candidate nearest the centroid, then again from the rest, so
//!    an occluder that cuts the board in pieces gives one grid per piece. A grid's indices
//!    are its own; what they are on the board is not known yet.
//! 3. Labels: every square of a grid (also those at its rim, whose outer corners are not
//!    board corners) is read through a homography fitted to the grid nodes around it: the
//!    6 × 6 marker cells are sampled, thresholded halfway between the square's white margin
//!    and the marker's black ring, and decoded (one wrong bit is corrected). Each decoded
//!    marker says where its square is on the board and how the grid is turned; the grid
//!    takes the labelling most markers agree on, if at least `min_markers` do and no
//!    rival labelling has half as many votes. Grids without such a majority are dropped
//!    (their candidates stay free for the other grids).
//! 4. Corners: every grid node that lands on an inner corner of the board, refined like a
//!    checkerboard corner (gradient estimate, then the corner model on the raw pixels) with
//!    windows kept inside the white margin so the markers never enter them. A corner whose
//!    refinement fails is left out and counted, not guessed.
//!
//! The result is the corners that were seen, in board order, with their board points: a
//! view needs `min_corners` of them, spread over at least two rows and two columns.

use crate::checkerboard::{
    central_seed, grid_bounds, grow_grid, prepare_frame, refine_corner, saddle_candidates, CheckerboardDetection,
    CheckerboardError, CheckerboardOptions, Gray,
};
use crate::homography::Homography;
use gonio_devices::coded_board::{code_from_cells, decode, CodedBoardSpec, MARKER_CELLS};
use gonio_devices::image::RgbImage;
use std::collections::HashMap;

/// A grid's labelling: board corner index = `R_k · grid index + offset`, `R_k` a turn by
/// `k` quarter turns counter-clockwise.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
struct Labelling {
    k: u8,
    offset: (i64, i64),
}

impl Labelling {
    fn apply(&self, g: (i64, i64)) -> (i64, i64) {
        let r = rotate(g, self.k);
        (r.0 + self.offset.0, r.1 + self.offset.1)
    }
}

/// `p` turned by `k` quarter turns counter-clockwise about the origin.
fn rotate(p: (i64, i64), k: u8) -> (i64, i64) {
    match k % 4 {
        0 => p,
        1 => (-p.1, p.0),
        2 => (-p.0, -p.1),
        _ => (p.1, -p.0),
    }
}

/// A grown grid: grid index → candidate.
type Grid = HashMap<(i64, i64), usize>;

/// A marker read in a grid cell.
struct Read {
    id: usize,
    labelling: Labelling,
}

/// Detect the coded board in a linear RGB frame: the corners that are visible.
pub fn detect_coded_board(
    img: &RgbImage,
    spec: &CodedBoardSpec,
    opts: &CheckerboardOptions,
) -> Result<CheckerboardDetection, CheckerboardError> {
    spec.validate().map_err(CheckerboardError::BadSpec)?;
    let frame = prepare_frame(img, opts)?;
    let result = detect_inner(&frame.gray, spec, opts, frame.contrast);
    frame.explain(result, opts)
}

fn detect_inner(
    gray: &Gray,
    spec: &CodedBoardSpec,
    opts: &CheckerboardOptions,
    frame_contrast: f64,
) -> Result<CheckerboardDetection, CheckerboardError> {
    let (cols, rows) = spec.corners();
    let (smooth, cand) = saddle_candidates(gray, opts, frame_contrast);
    let found = cand.len();
    let not_found = |hint: String| CheckerboardError::NotFound {
        found,
        grid_cols: 0,
        grid_rows: 0,
        cols,
        rows,
        hint,
    };
    if found < opts.min_corners.max(4) {
        return Err(not_found(format!(
            "{found} corner candidates, at least {} needed: board out of view, hidden, too blurred or too small",
            opts.min_corners.max(4)
        )));
    }
    // Grids and their labellings; `taken` candidates belong to a labelled grid.
    let mut taken = vec![false; found];
    let mut tried = vec![false; found];
    let mut labelled: Vec<(Grid, Labelling, Vec<usize>)> = Vec::new();
    let mut unlabelled_grids = 0;
    let edge_offset = (0.5 * spec.margin_mm() / spec.pitch_mm).min(0.25);
    let mut best_unlabelled = String::new();
    loop {
        let blocked: Vec<bool> = taken.iter().zip(&tried).map(|(a, b)| *a || *b).collect();
        let Some(seed) = central_seed(&cand, &blocked) else {
            break;
        };
        tried[seed] = true;
        let mut grid = grow_grid(&cand, &smooth, seed, &taken, edge_offset);
        if grid.len() < 4 {
            continue;
        }
        orient(&mut grid, &cand);
        match label(&grid, &cand, gray, spec, opts, frame_contrast) {
            Ok((l, ids)) => {
                for &k in grid.values() {
                    taken[k] = true;
                }
                labelled.push((grid, l, ids));
            }
            Err(why) => {
                for &k in grid.values() {
                    tried[k] = true;
                }
                unlabelled_grids += 1;
                if best_unlabelled.is_empty() {
                    best_unlabelled = why;
                }
            }
        }
    }
    if labelled.is_empty() {
        return Err(not_found(if unlabelled_grids == 0 {
            "no grid of corners could be grown from the candidates".into()
        } else {
            format!("{unlabelled_grids} grid(s) of corners, none named by its markers: {best_unlabelled}")
        }));
    }
    // Board corners from the labelled grids; a corner claimed twice is dropped.
    let mut corners: HashMap<(usize, usize), usize> = HashMap::new();
    let mut claimed_twice = Vec::new();
    let mut markers = Vec::new();
    for (grid, l, ids) in &labelled {
        markers.extend(ids.iter().copied());
        for (&g, &k) in grid {
            let (ci, cj) = l.apply(g);
            if ci < 0 || cj < 0 || ci >= cols as i64 || cj >= rows as i64 {
                continue; // a stray node beside the board
            }
            let key = (ci as usize, cj as usize);
            if corners.insert(key, k).is_some() {
                claimed_twice.push(key);
            }
        }
    }
    for key in claimed_twice {
        corners.remove(&key);
    }
    markers.sort_unstable();
    markers.dedup();
    // Refinement, in board order; windows stay inside the white margin (a marker's nearest
    // cell is margin·√2 from the corner, in board units).
    let clean = 0.9 * spec.margin_mm() * std::f64::consts::SQRT_2 / spec.pitch_mm;
    let mut keys: Vec<(usize, usize)> = corners.keys().copied().collect();
    keys.sort_unstable_by_key(|&(i, j)| (j, i));
    use rayon::prelude::*;
    let refined: Vec<Option<([f64; 2], f64)>> = keys
        .par_iter()
        .map(|&(i, j)| refine(gray, &smooth, &cand, &corners, (i, j), clean, opts))
        .collect();
    // Something that is not the board's corner in a corner's window (an occluder's rim)
    // shows as a poor model fit. The view's typical corner sets what noise alone leaves
    // (the median residual); a corner whose residual exceeds that by more than
    // `max_corner_residual` (in quadrature) is left out rather than pulled.
    let mut residuals: Vec<f64> = refined.iter().flatten().map(|r| r.1).collect();
    residuals.sort_by(f64::total_cmp);
    let typical = residuals.get(residuals.len() / 2).copied().unwrap_or(0.0);
    let limit = (typical * typical + opts.max_corner_residual * opts.max_corner_residual).sqrt();
    let mut good: HashMap<(usize, usize), [f64; 2]> = HashMap::new();
    let mut dropped = 0;
    for (&key, r) in keys.iter().zip(refined) {
        match r {
            Some((q, res)) if res <= limit => {
                good.insert(key, q);
            }
            _ => dropped += 1,
        }
    }
    dropped += drop_inconsistent(&mut good);
    let mut image = Vec::new();
    let mut object = Vec::new();
    let mut moved = 0.0;
    for &(i, j) in &keys {
        if let Some(&q) = good.get(&(i, j)) {
            let p = cand[corners[&(i, j)]];
            moved += (q[0] - p[0]).hypot(q[1] - p[1]);
            image.push(q);
            object.push(spec.corner_point(i, j));
        }
    }
    let distinct = |axis: usize| {
        let mut v: Vec<i64> = object
            .iter()
            .map(|o| (o[axis] / spec.pitch_mm).round() as i64)
            .collect();
        v.sort_unstable();
        v.dedup();
        v.len()
    };
    if image.len() < opts.min_corners.max(4) || distinct(0) < 2 || distinct(1) < 2 {
        return Err(not_found(format!(
            "only {} corners named by markers ({} over {} column(s) and {} row(s); {dropped} failed refinement); \
             at least {} over two rows and two columns are needed: more of the board must be in view",
            image.len(),
            image.len(),
            distinct(0),
            distinct(1),
            opts.min_corners.max(4)
        )));
    }
    let n = image.len();
    Ok(CheckerboardDetection {
        image,
        object,
        candidates: found,
        mean_refinement_px: moved / n as f64,
        markers,
        dropped_corners: dropped,
    })
}

/// Leave out corners that are not where their neighbours put them: each is predicted by a
/// homography through the named corners within two squares of it, and the worst outlier
/// (more than a tenth of a square plus a pixel off) is dropped, until none is. A stray
/// saddle point that joined the grid where a hidden corner should be (an occluder's rim)
/// is caught here; so is a corner that cannot be checked (fewer than 5 neighbours).
/// Returns how many were dropped.
fn drop_inconsistent(good: &mut HashMap<(usize, usize), [f64; 2]>) -> usize {
    let mut dropped = 0;
    loop {
        let mut worst: Option<((usize, usize), f64)> = None;
        for (&(i, j), &q) in good.iter() {
            let mut pairs = Vec::new();
            let mut spacing = f64::INFINITY;
            for dj in -2i64..=2 {
                for di in -2i64..=2 {
                    if (di, dj) == (0, 0) {
                        continue;
                    }
                    let (ii, jj) = (i as i64 + di, j as i64 + dj);
                    if ii < 0 || jj < 0 {
                        continue;
                    }
                    if let Some(&p) = good.get(&(ii as usize, jj as usize)) {
                        pairs.push(((di as f64, dj as f64), (p[0], p[1])));
                        if di.abs() + dj.abs() == 1 {
                            spacing = spacing.min((p[0] - q[0]).hypot(p[1] - q[1]));
                        }
                    }
                }
            }
            let predicted = if pairs.len() >= 5 {
                Homography::fit(&pairs).ok().and_then(|h| h.apply(0.0, 0.0))
            } else {
                None
            };
            let badness = match predicted {
                Some((u, v)) if spacing.is_finite() => (u - q[0]).hypot(v - q[1]) / (0.1 * spacing + 1.0),
                _ => f64::INFINITY, // cannot be checked
            };
            if badness > 1.0 && worst.is_none_or(|w| badness > w.1) {
                worst = Some(((i, j), badness));
            }
        }
        match worst {
            Some((key, _)) => {
                good.remove(&key);
                dropped += 1;
            }
            None => return dropped,
        }
    }
}

/// Make the grid's (i, j) → image map proper as seen from the camera (+i → +u, +j → −v,
/// like the board's +x and +y): flip j if the least-squares affine map has the other
/// handedness. Then the board's labelling is a pure turn plus a shift.
fn orient(grid: &mut HashMap<(i64, i64), usize>, cand: &[[f64; 2]]) {
    let n = grid.len() as f64;
    let (mi, mj) = grid
        .keys()
        .fold((0.0, 0.0), |(a, b), &(i, j)| (a + i as f64 / n, b + j as f64 / n));
    let (mu, mv) = grid
        .values()
        .fold((0.0, 0.0), |(a, b), &k| (a + cand[k][0] / n, b + cand[k][1] / n));
    // Normal equations of (u, v) = A · (i, j) + c.
    let (mut sii, mut sij, mut sjj) = (0.0, 0.0, 0.0);
    let (mut siu, mut sju, mut siv, mut sjv) = (0.0, 0.0, 0.0, 0.0);
    for (&(i, j), &k) in grid.iter() {
        let (di, dj) = (i as f64 - mi, j as f64 - mj);
        let (du, dv) = (cand[k][0] - mu, cand[k][1] - mv);
        sii += di * di;
        sij += di * dj;
        sjj += dj * dj;
        siu += di * du;
        sju += dj * du;
        siv += di * dv;
        sjv += dj * dv;
    }
    let det = sii * sjj - sij * sij;
    if det.abs() < 1e-12 {
        return;
    }
    // A = [[a, b], [c, d]] with u = a i + b j, v = c i + d j.
    let a = (siu * sjj - sju * sij) / det;
    let b = (sju * sii - siu * sij) / det;
    let c = (siv * sjj - sjv * sij) / det;
    let d = (sjv * sii - siv * sij) / det;
    if a * d - b * c > 0.0 {
        let flipped: HashMap<(i64, i64), usize> = grid.drain().map(|((i, j), k)| ((i, -j), k)).collect();
        *grid = flipped;
    }
}

/// Read every square of the grid and vote on its labelling.
fn label(
    grid: &HashMap<(i64, i64), usize>,
    cand: &[[f64; 2]],
    gray: &Gray,
    spec: &CodedBoardSpec,
    opts: &CheckerboardOptions,
    frame_contrast: f64,
) -> Result<(Labelling, Vec<usize>), String> {
    let (imin, imax, jmin, jmax) = grid_bounds(grid);
    let mut reads = Vec::new();
    for j in jmin - 1..=jmax {
        for i in imin - 1..=imax {
            if let Some(r) = read_square(grid, cand, gray, spec, (i, j), opts.min_contrast * frame_contrast) {
                reads.push(r);
            }
        }
    }
    let mut votes: HashMap<Labelling, Vec<usize>> = HashMap::new();
    for r in &reads {
        votes.entry(r.labelling).or_default().push(r.id);
    }
    let mut ranked: Vec<(Labelling, Vec<usize>)> = votes.into_iter().collect();
    ranked.sort_by(|a, b| {
        b.1.len()
            .cmp(&a.1.len())
            .then(a.0.k.cmp(&b.0.k))
            .then(a.0.offset.cmp(&b.0.offset))
    });
    let Some((best, ids)) = ranked.first() else {
        return Err(format!(
            "no marker could be read in its {} corners (markers too small to read: a grazing view or a distant \
             board; blurred; or not this board)",
            grid.len()
        ));
    };
    let rival = ranked.get(1).map(|r| r.1.len()).unwrap_or(0);
    if ids.len() < opts.min_markers.max(1) {
        return Err(format!(
            "{} marker(s) read, {} needed to name the corners (detection.min_markers)",
            ids.len(),
            opts.min_markers.max(1)
        ));
    }
    if 2 * rival >= ids.len() {
        return Err(format!(
            "the markers disagree: {} say one labelling, {rival} another (misread markers, or a second board)",
            ids.len()
        ));
    }
    Ok((*best, ids.clone()))
}

/// Read the marker of the grid square whose lower corner (in grid indices) is `(i, j)`:
/// `None` if it cannot be read (too few grid nodes around, low contrast, a black square, an
/// unreadable or unknown code).
fn read_square(
    grid: &HashMap<(i64, i64), usize>,
    cand: &[[f64; 2]],
    gray: &Gray,
    spec: &CodedBoardSpec,
    (i, j): (i64, i64),
    min_contrast: f64,
) -> Option<Read> {
    // The grid → image homography from the nodes around this square.
    let mut pairs = Vec::new();
    for dj in -2..=3 {
        for di in -2..=3 {
            if let Some(&k) = grid.get(&(i + di, j + dj)) {
                pairs.push(((di as f64, dj as f64), (cand[k][0], cand[k][1])));
            }
        }
    }
    // A square with none of its own corners in the grid is too far out to be read.
    let own = [(0, 0), (1, 0), (0, 1), (1, 1)]
        .iter()
        .filter(|(a, b)| grid.contains_key(&(i + a, j + b)))
        .count();
    if own < 1 || pairs.len() < 5 {
        return None;
    }
    let h = Homography::fit(&pairs).ok()?;
    // Square-local coordinates (s, t) ∈ [0, 1]²: the marker spans [m, 1 − m].
    let m = spec.margin_mm() / spec.pitch_mm;
    let cell = (1.0 - 2.0 * m) / MARKER_CELLS as f64;
    let at = |s: f64, t: f64| -> Option<f64> {
        let (u, v) = h.apply(s, t)?;
        if u < 1.0 || v < 1.0 || u > gray.w as f64 - 1.0 || v > gray.h as f64 - 1.0 {
            return None;
        }
        Some(gray.sample(u, v))
    };
    // Each marker cell: the mean of 3 × 3 points over its central half.
    let mut g = [[0.0f64; MARKER_CELLS]; MARKER_CELLS];
    for (a, col) in g.iter_mut().enumerate() {
        for (b, val) in col.iter_mut().enumerate() {
            let mut acc = 0.0;
            for da in [-0.25, 0.0, 0.25] {
                for db in [-0.25, 0.0, 0.25] {
                    let s = m + (a as f64 + 0.5 + da) * cell;
                    let t = m + (b as f64 + 0.5 + db) * cell;
                    acc += at(s, t)?;
                }
            }
            *val = acc / 9.0;
        }
    }
    // The white margin: points on its centre line, all round.
    let mut white = Vec::new();
    for q in 0..8 {
        let f = (q as f64 + 0.5) / 8.0;
        for (s, t) in [(0.5 * m, f), (1.0 - 0.5 * m, f), (f, 0.5 * m), (f, 1.0 - 0.5 * m)] {
            white.push(at(s, t)?);
        }
    }
    let mut ring: Vec<f64> = Vec::new();
    for (a, col) in g.iter().enumerate() {
        for (b, &v) in col.iter().enumerate() {
            if a == 0 || b == 0 || a == MARKER_CELLS - 1 || b == MARKER_CELLS - 1 {
                ring.push(v);
            }
        }
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (w_level, b_level) = (median(&mut white), median(&mut ring));
    if w_level - b_level < min_contrast.max(1e-6) {
        return None; // a black square, or no contrast
    }
    let mid = 0.5 * (w_level + b_level);
    if ring.iter().filter(|&&v| v > mid).count() > 1 {
        return None; // not a marker's black ring
    }
    // The bits, read as if the grid were the board (cell g[a][b]: a along grid i as board
    // x, b along grid j as board y).
    let code = code_from_cells(|cx, cy| g[cx][cy] > mid);
    let (id, r, _) = decode(code, 1)?;
    let (a_sq, b_sq) = spec.square_of(id)?;
    // The grid shows the marker turned by r: the board is the grid turned back by r.
    let k = ((4 - r) % 4) as u8;
    // Square centre: grid (i + ½, j + ½) ↦ board corner index (A − ½, B − ½), in halves.
    let c2 = rotate((2 * i + 1, 2 * j + 1), k);
    let target = (2 * a_sq as i64 - 1, 2 * b_sq as i64 - 1);
    let offset = ((target.0 - c2.0) / 2, (target.1 - c2.1) / 2);
    Some(Read {
        id,
        labelling: Labelling { k, offset },
    })
}

/// Sub-pixel refinement of board corner (i, j), windows within `clean` × the local
/// spacing; `None` if it fails (the corner is then left out).
fn refine(
    gray: &Gray,
    smooth: &Gray,
    cand: &[[f64; 2]],
    corners: &HashMap<(usize, usize), usize>,
    (i, j): (usize, usize),
    clean: f64,
    opts: &CheckerboardOptions,
) -> Option<([f64; 2], f64)> {
    let p = cand[corners[&(i, j)]];
    let at = |di: i64, dj: i64| -> Option<[f64; 2]> {
        let (ii, jj) = (i as i64 + di, j as i64 + dj);
        if ii < 0 || jj < 0 {
            return None;
        }
        corners.get(&(ii as usize, jj as usize)).map(|&k| cand[k])
    };
    let mut spacing = f64::INFINITY;
    for (di, dj) in [(-1, 0), (1, 0), (0, -1), (0, 1)] {
        if let Some(q) = at(di, dj) {
            spacing = spacing.min((q[0] - p[0]).hypot(q[1] - p[1]));
        }
    }
    if !spacing.is_finite() {
        return None; // an isolated corner: no local scale, no directions
    }
    let win = ((clean.min(0.4) * spacing).floor() as usize).clamp(2, opts.max_window_px.max(2));
    let q = refine_corner(smooth, p, win)?;
    if !opts.model_fit {
        return Some((q, 0.0));
    }
    let axis = |prev: Option<[f64; 2]>, next: Option<[f64; 2]>| -> Option<f64> {
        let (a, b) = match (prev, next) {
            (Some(a), Some(b)) => (a, b),
            (None, Some(b)) => (q, b),
            (Some(a), None) => (a, q),
            (None, None) => return None,
        };
        Some((b[1] - a[1]).atan2(b[0] - a[0]))
    };
    let di = axis(at(-1, 0), at(1, 0));
    let dj = axis(at(0, -1), at(0, 1));
    // A corner with only one axis' neighbours gets the other direction from the board's
    // perpendicular in the image (good enough to start the fit, which estimates both).
    let (di, dj) = match (di, dj) {
        (Some(a), Some(b)) => (a, b),
        (Some(a), None) => (a, a - std::f64::consts::FRAC_PI_2),
        (None, Some(b)) => (b + std::f64::consts::FRAC_PI_2, b),
        (None, None) => return None,
    };
    let radius = (clean.min(0.45) * spacing).min(opts.max_model_radius_px);
    if radius < 2.5 {
        return None;
    }
    let px = |x: usize, y: usize| gray.at(x, y) as f64;
    let fit =
        crate::corner_model::fit_corner(&px, (gray.w, gray.h), q, [di, dj], radius, opts.saturation_level as f64)?;
    Some((fit.q, fit.relative_residual))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::{perturb, pose, render_ss, rig_intrinsics, scene};
    use gonio_devices::kinematics::CameraPose;
    use gonio_devices::target::MarkerBorder;
    use gonio_devices::Vec3;

    const BOARD: CodedBoardSpec = CodedBoardSpec {
        squares_x: 8,
        squares_y: 8,
        pitch_mm: 11.0,
        marker_mm: 6.6,
        first_id: 0,
    };

    /// The board on the holder, with grey discs `(x, y, r)` (mm) lying on it.
    fn view(p: &CameraPose, discs: &[(f64, f64, f64)], blur: f64, noise: f64) -> RgbImage {
        let discs = discs.to_vec();
        let board = move |x: f64, y: f64| -> [f32; 3] {
            if discs.iter().any(|&(cx, cy, r)| (x - cx).hypot(y - cy) <= r) {
                return [0.3; 3];
            }
            if BOARD.is_black(x, y) {
                [0.04; 3]
            } else {
                [0.85; 3]
            }
        };
        let border = MarkerBorder::default();
        let paint = scene(&border, 88.0, &board);
        render_ss(&rig_intrinsics(), p, &paint, 8, blur, noise, 3)
    }

    /// Every detected corner against the exact projection of its board point: the worst
    /// error (pixels). A corner named wrongly is a whole square off and fails any bound.
    fn worst_error(p: &CameraPose, d: &CheckerboardDetection) -> f64 {
        let h = Homography::from_pose(&rig_intrinsics(), p);
        d.object
            .iter()
            .zip(&d.image)
            .map(|(o, i)| {
                let (u, v) = h.apply(o[0], o[1]).unwrap();
                (u - i[0]).hypot(v - i[1])
            })
            .fold(0.0, f64::max)
    }

    #[test]
    fn whole_board_in_any_orientation() {
        // Turntable angles in all four quadrants: the labelling must follow the board.
        for &(t, ph) in &[
            (0.0, 0.0),
            (30.0, 100.0),
            (45.0, 200.0),
            (55.0, 290.0),
            (20.0, 45.0),
            (65.0, 160.0),
        ] {
            let p = pose(t, ph);
            let d = detect_coded_board(&view(&p, &[], 0.0, 0.0), &BOARD, &CheckerboardOptions::default())
                .unwrap_or_else(|e| panic!("θ={t} φ={ph}: {e}"));
            assert_eq!(d.image.len(), 49, "θ={t} φ={ph}: {} corners", d.image.len());
            assert_eq!(d.markers.len(), 32, "θ={t} φ={ph}: markers {:?}", d.markers);
            let e = worst_error(&p, &d);
            eprintln!(
                "whole board θ={t} φ={ph}: {} corners, {} markers, worst error {e:.4} px",
                d.image.len(),
                d.markers.len()
            );
            assert!(e < 0.05, "θ={t} φ={ph}: worst corner error {e:.4} px");
        }
    }

    #[test]
    fn occluded_and_cut_off_views_give_the_visible_corners_correctly_named() {
        // Two discs hide corners and markers; one cuts the board in two.
        let discs = [(-20.0, 18.0, 14.0), (30.0, -30.0, 9.0)];
        for &(t, ph) in &[(0.0, 0.0), (40.0, 130.0)] {
            let p = pose(t, ph);
            let d = detect_coded_board(&view(&p, &discs, 0.0, 0.0), &BOARD, &CheckerboardOptions::default())
                .unwrap_or_else(|e| panic!("θ={t} φ={ph}: {e}"));
            let e = worst_error(&p, &d);
            eprintln!(
                "occluded θ={t} φ={ph}: {} corners ({} left out), {} markers, worst error {e:.4} px",
                d.image.len(),
                d.dropped_corners,
                d.markers.len()
            );
            assert!(e < 0.05, "θ={t} φ={ph}: worst corner error {e:.4} px");
            // No corner under (or at the rim of) a disc.
            for o in &d.object {
                for &(cx, cy, r) in &discs {
                    assert!((o[0] - cx).hypot(o[1] - cy) > r, "corner {o:?} is under a disc");
                }
            }
            // Most visible corners are found: 49 minus those within a disc or 3 mm of it.
            let visible = (0..7)
                .flat_map(|j| (0..7).map(move |i| BOARD.corner_point(i, j)))
                .filter(|o| discs.iter().all(|&(cx, cy, r)| (o[0] - cx).hypot(o[1] - cy) > r + 3.0))
                .count();
            assert!(
                d.image.len() >= visible && d.image.len() < 49,
                "θ={t} φ={ph}: {} corners, {visible} clearly visible",
                d.image.len()
            );
        }
        // The board half out of the frame: the camera moved 60 mm sideways.
        let p = perturb(&pose(10.0, 0.0), 0.0, 0.0, 0.0, Vec3::new(60.0, 0.0, 0.0));
        let d = detect_coded_board(&view(&p, &[], 0.0, 0.0), &BOARD, &CheckerboardOptions::default()).unwrap();
        let e = worst_error(&p, &d);
        eprintln!("cut off: {} corners, worst error {e:.4} px", d.image.len());
        assert!(d.image.len() >= 14 && d.image.len() < 49, "{} corners", d.image.len());
        assert!(e < 0.05);
    }

    /// Beyond about 70° the marker cells are under two pixels across: the board is then
    /// either found with every corner right or refused with the reason, never misnamed.
    #[test]
    fn grazing_views_are_right_or_refused() {
        for &(t, ph) in &[(72.0, 30.0), (76.0, 250.0), (80.0, 100.0)] {
            let p = pose(t, ph);
            match detect_coded_board(&view(&p, &[], 0.0, 0.0), &BOARD, &CheckerboardOptions::default()) {
                Ok(d) => {
                    let e = worst_error(&p, &d);
                    eprintln!("grazing θ={t} φ={ph}: {} corners, worst error {e:.4} px", d.image.len());
                    assert!(e < 0.1, "θ={t} φ={ph}: worst corner error {e:.4} px");
                }
                Err(e) => {
                    eprintln!("grazing θ={t} φ={ph}: refused: {e}");
                    assert!(matches!(e, CheckerboardError::NotFound { .. }), "{e}");
                }
            }
        }
    }

    #[test]
    fn noise_and_blur_keep_the_labels() {
        let p = pose(35.0, 70.0);
        let d = detect_coded_board(
            &view(&p, &[(0.0, 0.0, 10.0)], 1.2, 0.02),
            &BOARD,
            &CheckerboardOptions::default(),
        )
        .unwrap();
        let e = worst_error(&p, &d);
        eprintln!(
            "noise and blur: {} corners ({} left out), worst error {e:.4} px",
            d.image.len(),
            d.dropped_corners
        );
        assert!(d.image.len() >= 40, "{} corners", d.image.len());
        assert!(e < 0.2, "worst corner error {e:.4} px");
    }

    #[test]
    fn a_board_with_other_ids_or_too_little_in_view_is_refused_with_the_reason() {
        let p = pose(20.0, 30.0);
        let img = view(&p, &[], 0.0, 0.0);
        // The same layout with ids from 40 on: no marker on this board is one of those.
        let other = CodedBoardSpec { first_id: 40, ..BOARD };
        let e = detect_coded_board(&img, &other, &CheckerboardOptions::default()).unwrap_err();
        assert!(e.to_string().contains("named by its markers"), "{e}");
        // Almost all hidden: one big disc leaves a few corners at the rim.
        let img = view(&p, &[(0.0, 0.0, 40.0)], 0.0, 0.0);
        let e = detect_coded_board(&img, &BOARD, &CheckerboardOptions::default()).unwrap_err();
        assert!(matches!(e, CheckerboardError::NotFound { .. }), "{e}");
        // Black and saturated frames keep their own diagnosis.
        let black = RgbImage::new(200, 150);
        assert!(matches!(
            detect_coded_board(&black, &BOARD, &CheckerboardOptions::default()),
            Err(CheckerboardError::Empty { .. })
        ));
    }
}
