//! The ground floor every method file shares: what a method is ([`Method`], [`Params`],
//! [`CodecId`]), the one door every method implements ([`Codec`]: its knob ladder, encoder,
//! decoder and the facts the readers match on, [`Layout`] and [`Shard`]), what an encode
//! reports ([`EncodeInfo`], [`Stage`]) and the common `.gbtf` header ([`header_for`]).
//! Method files import this; it imports no method file. The registry that maps a
//! [`CodecId`] to its method file's [`Codec`] is `super::registry`.

use super::container::{BlockInfo, Gbtf, GbtfHeader};
use super::data::DatasetViews;
use super::error::CompressError;
use serde::{Deserialize, Serialize};
use std::sync::Arc;

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
    /// Which method this is, without its knobs.
    pub fn id(self) -> CodecId {
        match self {
            Method::Pca => CodecId::Pca,
            Method::Pvmf => CodecId::Pvmf,
            Method::LocalPca { .. } => CodecId::LocalPca,
            Method::MedianCut { .. } => CodecId::MedianCut,
            Method::Homomorphic { .. } => CodecId::Homomorphic,
            Method::Dfmf { .. } => CodecId::Dfmf,
            Method::Nd => CodecId::Nd,
            Method::SvdJ => CodecId::SvdJ,
            Method::Gshd { .. } => CodecId::Gshd,
            Method::Cmf { .. } => CodecId::Cmf,
            Method::Svbrdf { .. } => CodecId::Svbrdf,
            Method::Gltf => CodecId::Gltf,
        }
    }
    /// The method's name in `.gbtf` headers and on the command line ([`CodecId::name`]).
    pub fn name(self) -> &'static str {
        self.id().name()
    }
}

/// A method without its knobs: the key of the registry (`super::registry::codec`). Every
/// `match` on it is exhaustive, so a new method that misses a fact does not compile.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum CodecId {
    Pca,
    Pvmf,
    LocalPca,
    MedianCut,
    Homomorphic,
    Dfmf,
    Nd,
    SvdJ,
    Gshd,
    Cmf,
    Svbrdf,
    Gltf,
}

impl CodecId {
    /// Every method, in the order of [`CodecId`] (`registry::tests` checks that the list is
    /// complete: each entry's index is its discriminant and [`CodecId::name`] is
    /// exhaustive).
    pub const ALL: [CodecId; 12] = [
        CodecId::Pca,
        CodecId::Pvmf,
        CodecId::LocalPca,
        CodecId::MedianCut,
        CodecId::Homomorphic,
        CodecId::Dfmf,
        CodecId::Nd,
        CodecId::SvdJ,
        CodecId::Gshd,
        CodecId::Cmf,
        CodecId::Svbrdf,
        CodecId::Gltf,
    ];

    /// The one table of method names: the `method` of a `.gbtf` header, the `--method`
    /// value of `gonio compress` and the key of the file's `params.method` JSON.
    pub fn name(self) -> &'static str {
        match self {
            CodecId::Pca => "pca",
            CodecId::Pvmf => "pvmf",
            CodecId::LocalPca => "local-pca",
            CodecId::MedianCut => "median-cut",
            CodecId::Homomorphic => "homomorphic",
            CodecId::Dfmf => "dfmf",
            CodecId::Nd => "nd",
            CodecId::SvdJ => "svd-j",
            CodecId::Gshd => "gshd",
            CodecId::Cmf => "cmf",
            CodecId::Svbrdf => "svbrdf",
            CodecId::Gltf => "gltf",
        }
    }

    /// The method named `name` ([`CodecId::name`]), if any.
    pub fn from_name(name: &str) -> Option<CodecId> {
        CodecId::ALL.into_iter().find(|c| c.name() == name)
    }
}

/// How a method's `.gbtf` blocks are laid out: the fact the readers above the method files
/// (row blending in `interp`, synthesis, the viewer's GPU decoders) match on, instead of
/// method names. A method reuses a layout or adds one; adding one breaks the build of
/// every exhaustive `match` that must learn it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// PCA: one texel basis `U·S` (texels × c) and one measurement basis `V`
    /// (views · lights · 3 × c), row `(view · L + light) · 3 + channel`.
    Basis,
    /// PVMF: per view a texel basis (block `2v`, texels × c) and a light basis (block
    /// `2v + 1`, lights · 3 × c).
    ViewBases,
    /// Local PCA: cluster index, coefficients (texels × c), cluster means and
    /// eigen-ABRDFs (`clusters · c` rows of views · lights · 3).
    Clusters { clusters: usize },
    /// Median cut: index image (texels) and BRDF block (`boxes` rows of views · lights · 3).
    Index { boxes: usize },
    /// DFMF: per colour channel `u{ch}` (measurements × c) then `sxv{ch}` (texels × c).
    ChannelFactors,
    /// Homomorphic: per texel albedo and light, view and half-vector factor tables
    /// (`half_bins` θ_h bins).
    HalfVectorTables { half_bins: usize },
    /// ND, SVD-J, GSHD, CMF: every block indexed by texel, read by the method's own decoder.
    PerTexel,
    /// SVBRDF and glTF: per texel parameters of an analytic model plus per-pair gain planes
    /// over the sample's extent and the rig's geometry.
    AnalyticPerTexel,
}

impl Layout {
    /// PCA's and PVMF's layouts: an image is a texel basis times three rows of a
    /// measurement basis, so readers may blend rows or read a texel's values directly.
    pub fn has_bases(self) -> bool {
        match self {
            Layout::Basis | Layout::ViewBases => true,
            Layout::Clusters { .. }
            | Layout::Index { .. }
            | Layout::ChannelFactors
            | Layout::HalfVectorTables { .. }
            | Layout::PerTexel
            | Layout::AnalyticPerTexel => false,
        }
    }

    /// Which of a file's `n_blocks` blocks are indexed by texel (what a synthesized texture
    /// rearranges), or why the file cannot be synthesized from.
    pub fn texel_blocks(self, n_blocks: usize) -> Result<Vec<bool>, &'static str> {
        Ok(match self {
            Layout::Basis => vec![true, false],
            Layout::ViewBases => (0..n_blocks).map(|i| i % 2 == 0).collect(),
            Layout::Clusters { .. } => vec![true, true, false, false],
            Layout::Index { .. } => vec![true, false],
            Layout::HalfVectorTables { .. } | Layout::PerTexel => vec![true; n_blocks],
            // Per channel `u{ch}` (measurements) then `sxv{ch}` (texels).
            Layout::ChannelFactors => (0..n_blocks).map(|i| i % 2 == 1).collect(),
            Layout::AnalyticPerTexel => {
                return Err(
                    "an SVBRDF file (gonio fit --per-texel) holds gain planes over the sample's extent and the \
                     rig's geometry, which a grown texture does not have; synthesize from the dataset or a \
                     factorized .gbtf instead",
                )
            }
        })
    }
}

/// How `gonio compress --shard I/N` splits a method.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shard {
    /// By views: each shard factorizes its views, `gonio merge` joins the files (PVMF).
    Views,
    /// By passes over the views (`rsvd_shard`), this many: each pass is split into shards.
    Passes(usize),
    /// Not split: compressed in one process.
    No,
}

/// The knobs a method's ladder keeps as given (the ladders vary components, clusters,
/// boxes or bins): `gonio compress`'s options of the same names.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Knobs {
    pub seed: u64,
    pub oversample: usize,
    pub power_iters: usize,
    /// Local PCA: alternation rounds, subspace, the encoder in passes.
    pub iters: usize,
    pub subspace: usize,
    pub in_passes: bool,
    /// Median cut.
    pub balanced: bool,
    pub min_error_cut: bool,
    /// Homomorphic: half-vector bins; CMF: θ bins (at most 8).
    pub half_bins: usize,
    /// Homomorphic (default 20), GSHD and CMF (default 200).
    pub sweeps: Option<usize>,
}

impl Knobs {
    /// The parameters of `method` with `c` components and these knobs.
    pub fn params(&self, method: Method, c: usize) -> Params {
        Params {
            seed: self.seed,
            oversample: self.oversample,
            power_iters: self.power_iters,
            ..Params::new(method, c)
        }
    }
}

/// A method's decoder of one opened file: what `CompressedBtf::reconstruct` calls.
pub trait Decode: std::fmt::Debug + Send + Sync {
    /// The linear RGB image (interleaved, rows top to bottom) of grid pair (`light`,
    /// `view`), already checked to be inside the grid.
    fn reconstruct(&self, g: &Gbtf, light: usize, view: usize) -> Result<Vec<f32>, CompressError>;
}

/// What [`Codec::open`] found in a file.
#[derive(Clone, Debug)]
pub struct Opened {
    /// The method with the knobs the file records (the encoder's knobs that do not change
    /// decoding may be left at 0).
    pub method: Method,
    /// Components (or terms, or parameters) per texel as the method counts them.
    pub components: usize,
    pub layout: Layout,
    pub decoder: Arc<dyn Decode>,
}

/// One compression method: everything the rest of gonio needs to know about it. Each
/// method file implements it; `super::registry::codec` is the one list of them.
pub trait Codec: Sync {
    fn id(&self) -> CodecId;
    /// The ladders a `--target-psnr`/`--target-ratio` search climbs when `--method` names
    /// this method: the method's knobs in order of growing file size. Empty: not encoded
    /// by `gonio compress`.
    fn ladder(&self, knobs: &Knobs) -> Vec<Vec<Params>>;
    /// How `--shard` splits it with these knobs.
    fn shard(&self, knobs: &Knobs) -> Shard;
    /// Encode `ds` (`params.method` is this method, `params.components` ≥ 1).
    fn encode(&self, ds: &DatasetViews, params: &Params) -> Result<(Gbtf, EncodeInfo), CompressError>;
    /// Check a file of this method (its header names it) and build its decoder.
    fn open(&self, g: &Gbtf) -> Result<Opened, CompressError>;
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

/// The error of a file whose header names a method but whose content fails that
/// method's checks: `.gbtf METHOD: why`.
pub fn bad_file(g: &Gbtf, why: impl std::fmt::Display) -> CompressError {
    CompressError::Invalid(format!(".gbtf {}: {why}", g.header.method))
}

/// Check the RGB channels and the block shapes of a file whose first block has `c`
/// columns (`want(texels, lights, views, c)`, PCA's and PVMF's bases) and return `c`.
pub fn check_basis_blocks(
    g: &Gbtf,
    want: impl Fn(usize, usize, usize, usize) -> Vec<(usize, usize)>,
) -> Result<usize, CompressError> {
    let h = &g.header;
    if h.channels != 3 {
        return Err(bad_file(g, format!("{} channels, only RGB is supported", h.channels)));
    }
    let (t, nl, nv) = (h.width * h.height, h.lights_deg.len(), h.views_deg.len());
    let c = h.blocks.first().map(|b| b.cols).unwrap_or(0);
    let got: Vec<(usize, usize)> = h.blocks.iter().map(|b| (b.rows, b.cols)).collect();
    if got != want(t, nl, nv, c) || c == 0 {
        return Err(bad_file(
            g,
            format!("block shapes {got:?} do not match the header's grid"),
        ));
    }
    Ok(c)
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
