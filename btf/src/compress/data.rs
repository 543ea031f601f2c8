//! Streaming a native dataset view by view.
//!
//! One view = one matrix of `texels × (lights · 3)` linear f32 values, texel-major rows
//! (texel `t = y · W + x`, row 0 of the image first), column `light · 3 + channel`.
//! Pairs that were skipped (or are missing from the journal) are filled with the image of
//! the nearest measured light of the same view (smallest angle between the light
//! directions; ties go to the lower light index); [`ViewMatrix::filled`] lists them.
//! Substituted measurements are used as measured at their grid position.

use super::error::CompressError;
use faer::Mat;
use gonio_dataset::store::{self, ManifestHeader, MeasurementRecord, MeasurementStatus};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// A dataset opened for compression: its grid, image size and records.
#[derive(Debug, Clone)]
pub struct DatasetViews {
    pub dir: PathBuf,
    pub header: ManifestHeader,
    /// Light directions (θ, φ) in degrees, canonical order.
    pub lights_deg: Vec<[f64; 2]>,
    /// View directions (θ, φ) in degrees, canonical order.
    pub views_deg: Vec<[f64; 2]>,
    pub width: usize,
    pub height: usize,
    /// Image path (relative to `dir`) of each canonical index, `None` if not measured.
    images: Vec<Option<String>>,
}

/// [`DatasetViews::view_columns`]: the column-major f64 view matrix and the
/// `(light, filled from)` list of its unmeasured pairs.
pub type ViewColumns = (Mat<f64>, Vec<(usize, usize)>);

/// All lights of one view.
#[derive(Debug, Clone)]
pub struct ViewMatrix {
    pub view: usize,
    /// Row-major `texels × (lights · 3)`.
    pub data: Vec<f32>,
    pub rows: usize,
    pub cols: usize,
    /// `(light index, light index it was filled from)` for every unmeasured pair.
    pub filled: Vec<(usize, usize)>,
}

fn dir_vec(d: [f64; 2]) -> [f64; 3] {
    let (t, p) = (d[0].to_radians(), d[1].to_radians());
    [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
}

fn parse_dirs(v: &serde_json::Value, key: &str, dir: &Path) -> Result<Vec<[f64; 2]>, CompressError> {
    let bad = |why: &str| CompressError::Dataset {
        dir: dir.to_path_buf(),
        reason: format!("manifest sweep.{key}: {why}"),
    };
    let arr = v.get(key).and_then(|a| a.as_array()).ok_or_else(|| bad("missing"))?;
    arr.iter()
        .map(|d| {
            let p = d
                .as_array()
                .filter(|p| p.len() == 2)
                .ok_or_else(|| bad("not a [θ, φ] pair"))?;
            let t = p[0].as_f64().ok_or_else(|| bad("θ not a number"))?;
            let f = p[1].as_f64().ok_or_else(|| bad("φ not a number"))?;
            Ok([t, f])
        })
        .collect()
}

impl DatasetViews {
    /// Read the manifest and journal of the dataset in `dir`.
    pub fn open(dir: &Path) -> Result<Self, CompressError> {
        let (header, records) = store::load(dir)?;
        Self::from_parts(dir, header, &records)
    }

    fn from_parts(dir: &Path, header: ManifestHeader, records: &[MeasurementRecord]) -> Result<Self, CompressError> {
        let lights_deg = parse_dirs(&header.sweep, "lights_deg", dir)?;
        let views_deg = parse_dirs(&header.sweep, "views_deg", dir)?;
        if lights_deg.is_empty() || views_deg.is_empty() {
            return Err(CompressError::Dataset {
                dir: dir.to_path_buf(),
                reason: "the sweep has no lights or no views".into(),
            });
        }
        let n = lights_deg.len() * views_deg.len();
        let mut images = vec![None; n];
        for r in records {
            if r.index >= n {
                return Err(CompressError::Dataset {
                    dir: dir.to_path_buf(),
                    reason: format!("record index {} outside the {n} pairs of the sweep", r.index),
                });
            }
            if !matches!(r.status, MeasurementStatus::Skipped { .. }) {
                images[r.index] = Some(r.image.clone().unwrap_or_else(|| store::image_rel_path(r.index)));
            }
        }
        Ok(DatasetViews {
            dir: dir.to_path_buf(),
            width: header.image_width,
            height: header.image_height,
            header,
            lights_deg,
            views_deg,
            images,
        })
    }

    pub fn n_lights(&self) -> usize {
        self.lights_deg.len()
    }
    pub fn n_views(&self) -> usize {
        self.views_deg.len()
    }
    pub fn texels(&self) -> usize {
        self.width * self.height
    }
    /// Whether pair `(light, view)` has a stored image.
    pub fn is_measured(&self, light: usize, view: usize) -> bool {
        self.images[view * self.n_lights() + light].is_some()
    }
    /// Number of measured pairs.
    pub fn n_measured(&self) -> usize {
        self.images.iter().filter(|i| i.is_some()).count()
    }

    /// Read one measured image as linear f32 (interleaved RGB); `Ok(None)` if not measured.
    /// NaN or infinity is an error naming the file and measurement.
    pub fn read_image(&self, light: usize, view: usize) -> Result<Option<Vec<f32>>, CompressError> {
        let index = view * self.n_lights() + light;
        let Some(rel) = &self.images[index] else {
            return Ok(None);
        };
        let path = self.dir.join(rel);
        let img = store::read_exr(&path)?;
        if img.width != self.width || img.height != self.height {
            return Err(CompressError::Dataset {
                dir: self.dir.clone(),
                reason: format!(
                    "{} is {}×{}, the manifest says {}×{}",
                    path.display(),
                    img.width,
                    img.height,
                    self.width,
                    self.height
                ),
            });
        }
        if let Some(pos) = img.data.iter().position(|v| !v.is_finite()) {
            return Err(CompressError::NonFinite {
                path,
                index,
                light_deg: self.lights_deg[light],
                view_deg: self.views_deg[view],
                texel: pos / 3,
                value: img.data[pos],
            });
        }
        Ok(Some(img.data))
    }

    /// Read one measured image as three planes (R, G, B; `texels` values each, row 0 of
    /// the image first); `Ok(None)` if not measured. Same checks as [`Self::read_image`].
    ///
    /// Why not `store::read_exr`: that decoder hands every pixel to a closure and
    /// interleaves RGB, which costs about as much as the ZIP inflate itself on 256²
    /// images; PVMF wants one column per channel anyway, so the EXR's flat channel
    /// buffers are taken as they are (`tests::planes_match_read_image` checks both agree).
    pub fn read_planes(&self, light: usize, view: usize) -> Result<Option<[Vec<f32>; 3]>, CompressError> {
        use exr::prelude::{read, FlatSamples, ReadChannels, ReadLayers};
        let index = view * self.n_lights() + light;
        let Some(rel) = &self.images[index] else {
            return Ok(None);
        };
        let path = self.dir.join(rel);
        let bytes = std::fs::read(&path).map_err(|source| CompressError::Io {
            path: path.clone(),
            source,
        })?;
        let bad = |reason: String| CompressError::Dataset {
            dir: self.dir.clone(),
            reason: format!("{}: {reason}", path.display()),
        };
        let image = read()
            .no_deep_data()
            .largest_resolution_level()
            .all_channels()
            .first_valid_layer()
            .all_attributes()
            .non_parallel()
            .from_buffered(std::io::Cursor::new(bytes))
            .map_err(|e| bad(format!("EXR: {e}")))?;
        let layer = image.layer_data;
        if layer.size.width() != self.width || layer.size.height() != self.height {
            return Err(bad(format!(
                "is {}×{}, the manifest says {}×{}",
                layer.size.width(),
                layer.size.height(),
                self.width,
                self.height
            )));
        }
        let plane = |name: &str| -> Result<Vec<f32>, CompressError> {
            let ch = layer
                .channel_data
                .list
                .iter()
                .find(|c| c.name.eq(name))
                .ok_or_else(|| bad(format!("no {name} channel")))?;
            Ok(match &ch.sample_data {
                FlatSamples::F16(v) => v.iter().map(|x| x.to_f32()).collect(),
                FlatSamples::F32(v) => v.clone(),
                FlatSamples::U32(v) => v.iter().map(|&x| x as f32).collect(),
            })
        };
        let planes = [plane("R")?, plane("G")?, plane("B")?];
        for (c, p) in planes.iter().enumerate() {
            if p.len() != self.texels() {
                return Err(bad(format!(
                    "channel {c} holds {} samples, not {}",
                    p.len(),
                    self.texels()
                )));
            }
            if let Some(pos) = p.iter().position(|v| !v.is_finite()) {
                return Err(CompressError::NonFinite {
                    path,
                    index,
                    light_deg: self.lights_deg[light],
                    view_deg: self.views_deg[view],
                    texel: pos,
                    value: p[pos],
                });
            }
        }
        Ok(Some(planes))
    }

    /// The view matrix of `view` as a column-major f64 `texels × (lights · 3)` matrix
    /// (column `light · 3 + channel`), unmeasured pairs filled like [`Self::view_matrix`];
    /// also returns the `(light, filled from)` list.
    ///
    /// Built column by column straight from the decoded planes: converting the row-major
    /// f32 [`ViewMatrix`] to a column-major faer matrix is a strided transpose of 16 M
    /// values per 256² view, which measurably added to PVMF's encode time.
    pub fn view_columns(&self, view: usize) -> Result<ViewColumns, CompressError> {
        let (rows, nl) = (self.texels(), self.n_lights());
        let images: Vec<Option<[Vec<f32>; 3]>> = (0..nl)
            .into_par_iter()
            .map(|l| self.read_planes(l, view))
            .collect::<Result<_, _>>()?;
        let mut src = Vec::with_capacity(nl);
        let mut filled = Vec::new();
        for (l, img) in images.iter().enumerate() {
            if img.is_some() {
                src.push(l);
            } else {
                let s = self.nearest_measured(l, view).ok_or_else(|| CompressError::Dataset {
                    dir: self.dir.clone(),
                    reason: format!("view {view} {:?}° has no measured image at all", self.views_deg[view]),
                })?;
                filled.push((l, s));
                src.push(s);
            }
        }
        let mut m = Mat::<f64>::zeros(rows, nl * 3);
        for j in 0..nl * 3 {
            // `src` names measured lights only, so the image is always there.
            let Some(plane) = images[src[j / 3]].as_ref().map(|p| &p[j % 3]) else {
                continue;
            };
            let col = m.col_mut(j).try_as_col_major_mut().map(|c| c.as_slice_mut());
            match col {
                Some(col) => col.iter_mut().zip(plane).for_each(|(d, &s)| *d = s as f64),
                None => (0..rows).for_each(|i| m[(i, j)] = plane[i] as f64),
            }
        }
        Ok((m, filled))
    }

    /// Nearest measured light of `view` to `light` (angle between directions).
    fn nearest_measured(&self, light: usize, view: usize) -> Option<usize> {
        let a = dir_vec(self.lights_deg[light]);
        (0..self.n_lights())
            .filter(|&l| self.is_measured(l, view))
            .map(|l| {
                let b = dir_vec(self.lights_deg[l]);
                (l, a[0] * b[0] + a[1] * b[1] + a[2] * b[2])
            })
            .fold(None, |best: Option<(usize, f64)>, (l, d)| match best {
                Some((_, bd)) if bd >= d => best,
                _ => Some((l, d)),
            })
            .map(|(l, _)| l)
    }

    /// The `texels × (lights · 3)` matrix of `view`, unmeasured pairs filled.
    pub fn view_matrix(&self, view: usize) -> Result<ViewMatrix, CompressError> {
        let (rows, nl) = (self.texels(), self.n_lights());
        let cols = nl * 3;
        let mut data = vec![0f32; rows * cols];
        let mut filled = Vec::new();
        let mut missing = Vec::new();
        // Decoding the EXRs dominates for small images: read the lights in parallel.
        let images: Vec<Option<Vec<f32>>> = (0..nl)
            .into_par_iter()
            .map(|l| self.read_image(l, view))
            .collect::<Result<_, _>>()?;
        for (l, img) in images.into_iter().enumerate() {
            match img {
                Some(img) => {
                    for t in 0..rows {
                        data[t * cols + l * 3..t * cols + l * 3 + 3].copy_from_slice(&img[t * 3..t * 3 + 3]);
                    }
                }
                None => missing.push(l),
            }
        }
        for l in missing {
            let src = self.nearest_measured(l, view).ok_or_else(|| CompressError::Dataset {
                dir: self.dir.clone(),
                reason: format!("view {view} {:?}° has no measured image at all", self.views_deg[view]),
            })?;
            for t in 0..rows {
                let (d, s) = (t * cols + l * 3, t * cols + src * 3);
                data.copy_within(s..s + 3, d);
            }
            filled.push((l, src));
        }
        Ok(ViewMatrix {
            view,
            data,
            rows,
            cols,
            filled,
        })
    }
}
