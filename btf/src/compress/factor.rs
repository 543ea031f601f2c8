//! Dispatch of every `.gbtf` method ([`compress`]) and decoding of their files
//! ([`CompressedBtf`]): PCA, PVMF, local PCA, median cut and homomorphic factorization.
//! DFMF writes Bonn's `.btf` instead (`super::dfmf`). This file, `interp.rs` and `rsvd_shard.rs`
//! (sharded PCA and DFMF) are the only ones that name method files.

use super::container::{Gbtf, GbtfHeader};
use super::data::DatasetViews;
use super::error::CompressError;
use super::params::{EncodeInfo, Method, Params};
use super::{abrdf, cmf, dfmf, gltf, homomorphic, local_pca, median_cut, nd, pca, pvmf, svbrdf, svd_j};

/// One shard of a PVMF compression (`gonio compress --shard`): the factors of the shard's
/// views only, exactly as [`compress`] computes them (each view is factorized on its own),
/// with the shard recorded as `source.shard` for `gonio merge`.
pub fn compress_pvmf_shard(
    ds: &DatasetViews,
    params: &Params,
    shard: gonio_dataset::shard::Shard,
) -> Result<(Gbtf, EncodeInfo), CompressError> {
    if params.components == 0 {
        return Err(CompressError::Invalid("components must be at least 1".into()));
    }
    if params.method != Method::Pvmf {
        return Err(CompressError::Invalid(format!(
            "--shard splits PVMF by views; method {} is not split (compress it in one process)",
            params.method.name()
        )));
    }
    shard.check_views(ds.n_views()).map_err(CompressError::Invalid)?;
    let info = shard.info(ds.n_views());
    let (mut g, e) = super::pvmf::compress_views(ds, params, info.first_view..info.end_view)?;
    g.header.source["shard"] = serde_json::to_value(info).map_err(|e| CompressError::Invalid(e.to_string()))?;
    Ok((g, e))
}

/// Compress the dataset with `params`.
pub fn compress(ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
    if params.components == 0 {
        return Err(CompressError::Invalid("components must be at least 1".into()));
    }
    match params.method {
        Method::Pvmf => pvmf::compress(ds, params),
        Method::Pca => pca::compress(ds, params),
        Method::LocalPca { .. } => local_pca::compress(ds, params),
        Method::MedianCut { .. } => median_cut::compress(ds, params),
        Method::Homomorphic { .. } => homomorphic::compress(ds, params),
        Method::Dfmf { .. } => dfmf::compress_gbtf(ds, params),
        Method::Nd => nd::compress(ds, params),
        Method::SvdJ => svd_j::compress(ds, params),
        Method::Gshd { .. } | Method::Cmf { .. } => cmf::compress(ds, params),
        Method::Svbrdf { .. } => Err(CompressError::Invalid(
            "svbrdf: the per-texel Lafortune SVBRDF is fitted by `gonio fit DATASET --model lafortune \
             --per-texel --out F.gbtf`, not by gonio compress"
                .into(),
        )),
        Method::Gltf => Err(CompressError::Invalid(
            "gltf: the per-texel glTF SVBRDF is fitted by `gonio fit DATASET --model gltf --per-texel --out \
             F.gbtf`, not by gonio compress"
                .into(),
        )),
    }
}

/// A decoded `.gbtf`, ready to reconstruct images.
#[derive(Clone, Debug)]
pub struct CompressedBtf {
    pub gbtf: Gbtf,
    method: Method,
    c: usize,
    /// Homomorphic files only: the factor tables in direction-major order for decoding
    /// (see [`homomorphic::DirectionMajor`]).
    homomorphic: Option<Box<homomorphic::DirectionMajor>>,
    /// DFMF files only: the factors as [`dfmf::Dfmf`], which decodes them.
    dfmf: Option<Box<dfmf::Dfmf>>,
}

/// Index of the direction in `list` within 0.01° of `deg` (angle between the unit vectors).
pub fn find_direction(list: &[[f64; 2]], deg: [f64; 2]) -> Option<usize> {
    let v = |d: [f64; 2]| {
        let (t, p) = (d[0].to_radians(), d[1].to_radians());
        [t.sin() * p.cos(), t.sin() * p.sin(), t.cos()]
    };
    let a = v(deg);
    let cos_tol = 0.01f64.to_radians().cos();
    list.iter()
        .enumerate()
        .map(|(i, &d)| {
            let b = v(d);
            (i, a[0] * b[0] + a[1] * b[1] + a[2] * b[2])
        })
        .filter(|&(_, dot)| dot >= cos_tol)
        .max_by(|x, y| x.1.total_cmp(&y.1))
        .map(|(i, _)| i)
}

impl CompressedBtf {
    /// Check the blocks against the header and wrap them.
    pub fn new(gbtf: Gbtf) -> Result<Self, CompressError> {
        let h = &gbtf.header;
        let bad = |r: String| CompressError::Invalid(format!(".gbtf {}: {r}", h.method));
        let method = match h.method.as_str() {
            "pvmf" => Method::Pvmf,
            "pca" => Method::Pca,
            "local-pca" => {
                let (_, c) = local_pca::validate(h)?;
                let k = h.blocks[2].rows;
                abrdf::check_indices(&gbtf.blocks[0], k, "cluster")?;
                let method = Method::LocalPca {
                    clusters: k,
                    iters: 0,
                    subspace: 0,
                    in_passes: false,
                };
                return Ok(CompressedBtf {
                    gbtf,
                    method,
                    c,
                    homomorphic: None,
                    dfmf: None,
                });
            }
            "median-cut" => {
                let boxes = median_cut::validate(&gbtf)?;
                let method = Method::MedianCut {
                    boxes,
                    balanced: false,
                    min_error_cut: false,
                };
                return Ok(CompressedBtf {
                    gbtf,
                    method,
                    c: 0,
                    homomorphic: None,
                    dfmf: None,
                });
            }
            "homomorphic" => {
                let half_bins = homomorphic::validate(h)?;
                let method = Method::Homomorphic { half_bins, sweeps: 0 };
                let tables = Box::new(homomorphic::DirectionMajor::new(&gbtf, half_bins));
                return Ok(CompressedBtf {
                    gbtf,
                    method,
                    c: 0,
                    homomorphic: Some(tables),
                    dfmf: None,
                });
            }
            "gshd" | "cmf" => {
                let (theta_bins, k) = cmf::validate(h)?;
                let method = if h.method == "gshd" {
                    Method::Gshd { theta_bins, sweeps: 0 }
                } else {
                    Method::Cmf { theta_bins, sweeps: 0 }
                };
                return Ok(CompressedBtf {
                    gbtf,
                    method,
                    c: k,
                    homomorphic: None,
                    dfmf: None,
                });
            }
            "nd" | "svd-j" => {
                let j = abrdf::product_terms(h)?;
                let method = if h.method == "nd" { Method::Nd } else { Method::SvdJ };
                if method == Method::Nd && j != 1 {
                    return Err(bad(format!("{j} terms per ABRDF, ND stores one")));
                }
                return Ok(CompressedBtf {
                    gbtf,
                    method,
                    c: j,
                    homomorphic: None,
                    dfmf: None,
                });
            }
            "svbrdf" => {
                let (lobes, _) = svbrdf::validate(&gbtf)?;
                return Ok(CompressedBtf {
                    gbtf,
                    method: Method::Svbrdf { lobes },
                    c: svbrdf::params_per_texel(lobes),
                    homomorphic: None,
                    dfmf: None,
                });
            }
            "gltf" => {
                gltf::validate(&gbtf)?;
                return Ok(CompressedBtf {
                    gbtf,
                    method: Method::Gltf,
                    c: gltf::PARAMS,
                    homomorphic: None,
                    dfmf: None,
                });
            }
            "dfmf" => {
                let d = dfmf::from_gbtf(&gbtf)?;
                let params: Params = serde_json::from_value(gbtf.header.params.clone())
                    .map_err(|e| bad(format!("parameters in the header: {e}")))?;
                return Ok(CompressedBtf {
                    method: params.method,
                    c: params.components,
                    gbtf,
                    homomorphic: None,
                    dfmf: Some(Box::new(d)),
                });
            }
            m => return Err(bad(format!("unknown method {m:?}"))),
        };
        if h.channels != 3 {
            return Err(bad(format!("{} channels, only RGB is supported", h.channels)));
        }
        let (t, nl, nv) = (h.width * h.height, h.lights_deg.len(), h.views_deg.len());
        let c = h.blocks.first().map(|b| b.cols).unwrap_or(0);
        let want: Vec<(usize, usize)> = match method {
            Method::Pvmf => (0..nv).flat_map(|_| [(t, c), (nl * 3, c)]).collect(),
            Method::Pca => vec![(t, c), (nl * nv * 3, c)],
            _ => Vec::new(),
        };
        let got: Vec<(usize, usize)> = h.blocks.iter().map(|b| (b.rows, b.cols)).collect();
        if got != want || c == 0 {
            return Err(bad(format!("block shapes {got:?} do not match the header's grid")));
        }
        Ok(CompressedBtf {
            gbtf,
            method,
            c,
            homomorphic: None,
            dfmf: None,
        })
    }

    pub fn method(&self) -> Method {
        self.method
    }
    pub fn components(&self) -> usize {
        self.c
    }
    pub fn header(&self) -> &GbtfHeader {
        &self.gbtf.header
    }

    /// Reconstruct the linear RGB image (interleaved, rows top to bottom) of grid pair
    /// (`light`, `view`).
    pub fn reconstruct(&self, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        let h = &self.gbtf.header;
        let (nl, nv) = (h.lights_deg.len(), h.views_deg.len());
        if light >= nl || view >= nv {
            return Err(CompressError::Invalid(format!(
                "pair (light {light}, view {view}) outside the {nl} × {nv} grid"
            )));
        }
        let c = self.c;
        if let Some(d) = &self.dfmf {
            return d.reconstruct(light, view);
        }
        if let Some(tables) = &self.homomorphic {
            return Ok(tables.reconstruct(&self.gbtf.header, light, view));
        }
        if let Method::Gshd { theta_bins, .. } | Method::Cmf { theta_bins, .. } = self.method {
            return Ok(cmf::reconstruct(&self.gbtf, theta_bins, c, light, view));
        }
        if let Method::Svbrdf { lobes } = self.method {
            let (_, geometry) = svbrdf::validate(&self.gbtf)?;
            return Ok(svbrdf::reconstruct(&self.gbtf, lobes, geometry, light, view));
        }
        if let Method::Gltf = self.method {
            let geometry = gltf::validate(&self.gbtf)?;
            return Ok(gltf::reconstruct(&self.gbtf, geometry, light, view));
        }
        if let Method::Nd | Method::SvdJ = self.method {
            return Ok(abrdf::reconstruct_products(&self.gbtf, c, light, view));
        }
        if let Method::MedianCut { .. } = self.method {
            return Ok(median_cut::reconstruct(&self.gbtf, light, view));
        }
        if let Method::LocalPca { clusters, .. } = self.method {
            return Ok(local_pca::reconstruct(&self.gbtf, clusters, c, light, view));
        }
        let (us, vrows) = match self.method {
            Method::Pvmf => {
                let vb = &self.gbtf.blocks[2 * view + 1];
                (&self.gbtf.blocks[2 * view], &vb[light * 3 * c..(light * 3 + 3) * c])
            }
            Method::Pca => {
                let r = (view * nl + light) * 3;
                (&self.gbtf.blocks[0], &self.gbtf.blocks[1][r * c..(r + 3) * c])
            }
            _ => return Err(CompressError::Invalid(format!("no decoder for {:?}", self.method))),
        };
        let (v0, rest) = vrows.split_at(c);
        let (v1, v2) = rest.split_at(c);
        let t = h.width * h.height;
        let mut out = vec![0f32; t * 3];
        // LANES texels at once (3 · LANES independent sums, see `dfmf::Dfmf::decode_rows`);
        // each sum runs in the order of a plain loop, so the bytes do not change.
        const LANES: usize = 4;
        let mut pxs = out.chunks_exact_mut(3 * LANES);
        let mut rows = us.chunks_exact(c * LANES);
        for (px, row) in (&mut pxs).zip(&mut rows) {
            let mut s = [[0f32; 3]; LANES];
            for j in 0..c {
                let (x0, x1, x2) = (v0[j], v1[j], v2[j]);
                for (i, a) in s.iter_mut().enumerate() {
                    let r = row[i * c + j];
                    a[0] += r * x0;
                    a[1] += r * x1;
                    a[2] += r * x2;
                }
            }
            for (o, a) in px.chunks_exact_mut(3).zip(s) {
                o.copy_from_slice(&a);
            }
        }
        for (px, row) in pxs
            .into_remainder()
            .chunks_exact_mut(3)
            .zip(rows.remainder().chunks_exact(c))
        {
            let (mut a, mut b, mut d) = (0f32, 0f32, 0f32);
            for j in 0..c {
                a += row[j] * v0[j];
                b += row[j] * v1[j];
                d += row[j] * v2[j];
            }
            px[0] = a;
            px[1] = b;
            px[2] = d;
        }
        Ok(out)
    }

    /// Reconstruct by directions in degrees; they must be grid directions (±0.01°).
    pub fn reconstruct_deg(&self, light_deg: [f64; 2], view_deg: [f64; 2]) -> Result<Vec<f32>, CompressError> {
        let h = &self.gbtf.header;
        let l = find_direction(&h.lights_deg, light_deg).ok_or(CompressError::NotMeasured {
            which: "light",
            deg: light_deg,
        })?;
        let v = find_direction(&h.views_deg, view_deg).ok_or(CompressError::NotMeasured {
            which: "view",
            deg: view_deg,
        })?;
        self.reconstruct(l, v)
    }
}
