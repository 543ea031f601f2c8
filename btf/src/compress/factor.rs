//! Encoding a dataset ([`compress`]) and decoding a `.gbtf` ([`CompressedBtf`]) with any
//! method, through the registry (`super::registry`): this file names no method file
//! except PVMF's shards ([`compress_pvmf_shard`]). DFMF can also write Bonn's `.btf`
//! (`super::dfmf`, `super::btf_ubo2014`).

use super::container::{Gbtf, GbtfHeader};
use super::data::DatasetViews;
use super::error::CompressError;
use super::params::{CodecId, Decode, EncodeInfo, Layout, Method, Params};
use super::registry::codec;
use std::sync::Arc;

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

/// Compress the dataset with `params`: the encoder of `params.method`'s codec
/// (`super::registry`).
pub fn compress(ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError> {
    if params.components == 0 {
        return Err(CompressError::Invalid("components must be at least 1".into()));
    }
    codec(params.method.id()).encode(ds, params)
}

/// A decoded `.gbtf`, ready to reconstruct images: the file and its method's decoder.
#[derive(Clone, Debug)]
pub struct CompressedBtf {
    pub gbtf: Gbtf,
    method: Method,
    c: usize,
    layout: Layout,
    decoder: Arc<dyn Decode>,
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
    /// Check the blocks against the header (the checks of the method the header names)
    /// and wrap them.
    pub fn new(gbtf: Gbtf) -> Result<Self, CompressError> {
        let h = &gbtf.header;
        let id = CodecId::from_name(&h.method)
            .ok_or_else(|| CompressError::Invalid(format!(".gbtf {0}: unknown method {0:?}", h.method)))?;
        let o = codec(id).open(&gbtf)?;
        Ok(CompressedBtf {
            gbtf,
            method: o.method,
            c: o.components,
            layout: o.layout,
            decoder: o.decoder,
        })
    }

    pub fn method(&self) -> Method {
        self.method
    }
    pub fn components(&self) -> usize {
        self.c
    }
    /// How the method lays out its blocks: what readers above `compress` match on.
    pub fn layout(&self) -> Layout {
        self.layout
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
        self.decoder.reconstruct(&self.gbtf, light, view)
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
