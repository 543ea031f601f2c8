//! The ground floor every method file shares: what a method is ([`Method`], [`Params`]),
//! what an encode reports ([`EncodeInfo`], [`Stage`]) and the common `.gbtf` header
//! ([`header_for`]). Method files import this; it imports no method file.

use super::container::{BlockInfo, GbtfHeader};
use super::data::DatasetViews;
use serde::{Deserialize, Serialize};

/// Compression method.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Full-matrix PCA by randomized SVD.
    Pca,
    /// Per-view matrix factorization (one truncated SVD per view).
    Pvmf,
    /// Local PCA / PCMF (`local_pca`): `clusters` clusters of ABRDFs with `components`
    /// eigen-ABRDFs each, at most `iters` alternation rounds, run in a global subspace of
    /// `subspace` dimensions (0: in the full ABRDF space).
    /// `in_passes`: run as the nine passes over the views that `--shard I/N` splits
    /// (`local_pca::passes`; exact sums, slower in one process) instead of the fused
    /// encoder; absent from the file's parameters when false, so fused files keep their
    /// bytes.
    #[serde(rename = "local-pca")]
    LocalPca {
        clusters: usize,
        iters: usize,
        subspace: usize,
        #[serde(default, skip_serializing_if = "std::ops::Not::not")]
        in_passes: bool,
    },
    /// Median-cut quantization of ABRDFs (`median_cut`): index image + BRDF block.
    #[serde(rename = "median-cut")]
    MedianCut {
        boxes: usize,
        balanced: bool,
        min_error_cut: bool,
    },
    /// Homomorphic factorization per ABRDF (`homomorphic`): light × view × half-vector
    /// factors fitted in the log domain (`half_bins` θ_h bins, `sweeps` backfitting sweeps).
    Homomorphic { half_bins: usize, sweeps: usize },
    /// DFMF (`dfmf`) stored as `.gbtf`: one factorization per channel of `color_model`,
    /// `components` for the first (luminance) channel and `chroma_components` for the
    /// other two (all three get `components` in [`ColorModel::Rgb`]).
    Dfmf {
        color_model: ColorModel,
        chroma_components: usize,
    },
    /// Normalized decomposition per ABRDF (`nd`, Wynn): row norms × column means of the
    /// row-normalized `lights × views` matrix, per texel and channel.
    Nd,
    /// SVD with J terms per ABRDF (`svd_j`): the rank-J truncated SVD of every texel's
    /// `lights × views` matrix per channel; J is [`Params::components`].
    #[serde(rename = "svd-j")]
    SvdJ,
    /// GSHD per ABRDF (`cmf`): one product of a half-vector and a difference-vector factor
    /// (`theta_bins` θ bins × twice as many φ bins each), fitted by `sweeps` sweeps of
    /// alternating least squares.
    Gshd { theta_bins: usize, sweeps: usize },
    /// Chained matrix factorization per ABRDF (`cmf`): the GSHD product times a rank-K SVD
    /// (K = [`Params::components`]) of the residual `M / GSHD` in light × view form.
    Cmf { theta_bins: usize, sweeps: usize },
    /// Per-texel scaled Lafortune SVBRDF (`svbrdf`): written by `gonio fit --per-texel
    /// --out F.gbtf` (the fit lives in `fit/`), decoded like every other method.
    Svbrdf { lobes: usize },
    /// Per-texel glTF metallic-roughness SVBRDF (`gltf`): written by `gonio fit --per-texel
    /// --model gltf --out F.gbtf`, decoded like every other method, exported by `gonio export`.
    Gltf,
}

impl Method {
    pub fn name(self) -> &'static str {
        match self {
            Method::Pca => "pca",
            Method::Pvmf => "pvmf",
            Method::LocalPca { .. } => "local-pca",
            Method::MedianCut { .. } => "median-cut",
            Method::Homomorphic { .. } => "homomorphic",
            Method::Dfmf { .. } => "dfmf",
            Method::Nd => "nd",
            Method::SvdJ => "svd-j",
            Method::Gshd { .. } => "gshd",
            Method::Cmf { .. } => "cmf",
            Method::Svbrdf { .. } => "svbrdf",
            Method::Gltf => "gltf",
        }
    }
}

/// Colour model of the factorized channels (the `ColorModel` field of a DFMF file).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[serde(rename_all = "kebab-case")]
pub enum ColorModel {
    /// Linear RGB, no transform (code 0).
    Rgb,
    /// log luminance + chroma / luminance (code 11).
    LogYuv,
    /// CIELab (D65 white = linear RGB (1, 1, 1)): the perceptual DFMF of Guthe et al. 2009.
    /// gonio's own model, stored in `.gbtf` only (the UBO2014 reader has no code for it).
    Lab,
}

impl ColorModel {
    /// The code stored in a UBO2014 file; `None` for [`ColorModel::Lab`], which the
    /// public reader cannot decode.
    pub fn code(self) -> Option<u32> {
        match self {
            ColorModel::Rgb => Some(0),
            ColorModel::LogYuv => Some(11),
            ColorModel::Lab => None,
        }
    }
    pub fn from_code(code: u32) -> Option<Self> {
        match code {
            0 => Some(ColorModel::Rgb),
            11 => Some(ColorModel::LogYuv),
            _ => None,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            ColorModel::Rgb => "rgb",
            ColorModel::LogYuv => "log-yuv",
            ColorModel::Lab => "lab",
        }
    }
    /// Channel names written to the file's header.
    pub fn channel_names(self) -> [&'static str; 3] {
        match self {
            ColorModel::Rgb => ["R", "G", "B"],
            ColorModel::LogYuv => ["logY", "U/Y", "V/Y"],
            ColorModel::Lab => ["L*", "a*", "b*"],
        }
    }
}

/// Parameters of `compress::compress`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct Params {
    pub method: Method,
    /// Components kept (per view for PVMF, in total for PCA).
    pub components: usize,
    /// PCA: seed of the Gaussian test matrix.
    pub seed: u64,
    /// PCA: extra sketch columns beyond `components`.
    pub oversample: usize,
    /// PCA: power iterations (each one more pass over the dataset).
    pub power_iters: usize,
}

impl Params {
    pub fn new(method: Method, components: usize) -> Self {
        Params {
            method,
            components,
            seed: 1,
            oversample: 10,
            power_iters: 2,
        }
    }
}

/// What `compress::compress` saw besides the factors.
#[derive(Serialize, Clone, Debug, Default, PartialEq)]
pub struct EncodeInfo {
    /// Unmeasured (light, view) pairs filled from the nearest measured light.
    pub filled: usize,
    /// Passes that read the dataset's images. PVMF: 1. PCA: 1 when all view matrices fit
    /// `pca::PCA_CACHE_BYTES` as f64 (they are kept in memory for the later passes), else
    /// `2 + power_iters`.
    pub passes: usize,
    /// Where the encode time went (timing spans; empty for methods that do not report
    /// them). PVMF: `read_wait` (time the factorization waited for the reader),
    /// `factorize`, and the counts of views factorized by each path.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub stages: Vec<Stage>,
}

/// One timing span or count of an encode.
#[derive(Serialize, Clone, Debug, Default, PartialEq)]
pub struct Stage {
    pub name: String,
    pub value: f64,
    /// `s` for seconds, `views` for counts.
    pub unit: &'static str,
}

/// The `.gbtf` header of a compression of `ds` with `params`: method name, the
/// parameters as JSON, grid, filled pairs, provenance and the block list.
pub fn header_for(ds: &DatasetViews, params: &Params, filled: Vec<[usize; 2]>, blocks: Vec<BlockInfo>) -> GbtfHeader {
    GbtfHeader {
        method: params.method.name().into(),
        params: serde_json::to_value(params).unwrap_or(serde_json::Value::Null),
        width: ds.width,
        height: ds.height,
        channels: 3,
        dtype: "f32le".into(),
        lights_deg: ds.lights_deg.clone(),
        views_deg: ds.views_deg.clone(),
        filled,
        source: serde_json::json!({
            "dataset": ds.dir.display().to_string(),
            "values": ds.header.values,
            "sample": ds.header.sample,
        }),
        blocks,
    }
}
