//! What the viewer shows: a native dataset (raw measurements) or a compressed file.

use gonio_btf::compress::data::DatasetViews;
use gonio_btf::compress::interp::{AnyModel, BtfModel};
use gonio_btf::compress::CompressError;
use gonio_dataset::store;
use std::path::{Path, PathBuf};

/// Errors of opening a viewer source.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    #[error(
        "{path}: {why}; expected a gonio dataset directory (with {manifest}), a .gbtf file or a \
         UBO2014 .btf file",
        manifest = store::MANIFEST_FILE
    )]
    NotViewable { path: PathBuf, why: String },
    #[error(transparent)]
    Compress(#[from] CompressError),
}

/// A native dataset seen as a BTF model: grid pair (l, v) is its measured image. A pair
/// that was not measured (skipped, or not yet acquired) takes the image of the nearest
/// measured light of the same view (smallest angle, ties to the lower index) as
/// `gonio compress` fills it; a view with no measurement yet is black.
pub struct RawModel {
    pub views: DatasetViews,
}

impl RawModel {
    pub fn open(dir: &Path) -> Result<Self, CompressError> {
        Ok(RawModel {
            views: DatasetViews::open(dir)?,
        })
    }

    /// The light whose image stands for pair (`light`, `view`), `None` if the view has no
    /// measured light at all.
    pub fn source_light(&self, light: usize, view: usize) -> Option<usize> {
        super::abrdf_cache::fill_light(&self.views.lights_deg, light, |l| self.views.is_measured(l, view))
    }

    /// Whether an ABRDF (every grid pair at one texel) is cheap enough to decode image by
    /// image on a click: at most [`DIRECT_ABRDF_IMAGES`] images and
    /// [`DIRECT_ABRDF_VALUES`] decoded values. Larger datasets answer from the texel-major
    /// cache ([`super::abrdf_cache`]).
    pub fn abrdf_direct(&self) -> bool {
        let pairs = self.views.n_lights() * self.views.n_views();
        pairs <= DIRECT_ABRDF_IMAGES && pairs * self.views.texels() * 3 <= DIRECT_ABRDF_VALUES
    }
}

/// See [`RawModel::abrdf_direct`].
pub const DIRECT_ABRDF_IMAGES: usize = 1024;
/// See [`RawModel::abrdf_direct`].
pub const DIRECT_ABRDF_VALUES: usize = 1 << 20;

impl BtfModel for RawModel {
    fn width(&self) -> usize {
        self.views.width
    }
    fn height(&self) -> usize {
        self.views.height
    }
    fn lights_deg(&self) -> &[[f64; 2]] {
        &self.views.lights_deg
    }
    fn views_deg(&self) -> &[[f64; 2]] {
        &self.views.views_deg
    }
    fn reconstruct(&self, light: usize, view: usize) -> Result<Vec<f32>, CompressError> {
        let (nl, nv) = (self.views.n_lights(), self.views.n_views());
        if light >= nl || view >= nv {
            return Err(CompressError::Invalid(format!(
                "pair (light {light}, view {view}) outside the {nl} × {nv} grid"
            )));
        }
        match self.source_light(light, view) {
            Some(l) => Ok(self.views.read_image(l, view)?.unwrap_or_default()),
            None => Ok(vec![0.0; self.views.texels() * 3]),
        }
    }
}

/// The kind of a viewer source.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SourceKind {
    Dataset,
    Gbtf,
    Btf,
}

/// An opened viewer source.
pub enum Source {
    Dataset(RawModel),
    Model { model: AnyModel, kind: SourceKind },
}

impl Source {
    /// Open `path`: a directory must be a gonio dataset (it has a manifest), a file must
    /// be a `.gbtf` or a UBO2014 `.btf` (recognised by its first bytes).
    pub fn open(path: &Path) -> Result<Source, SourceError> {
        let not = |why: String| SourceError::NotViewable {
            path: path.to_path_buf(),
            why,
        };
        let meta = std::fs::metadata(path).map_err(|e| not(format!("cannot be read ({e})")))?;
        if meta.is_dir() {
            if !path.join(store::MANIFEST_FILE).is_file() {
                return Err(not(format!("a directory without {}", store::MANIFEST_FILE)));
            }
            return Ok(Source::Dataset(RawModel::open(path)?));
        }
        let mut head = [0u8; 16];
        {
            use std::io::Read;
            let mut f = std::fs::File::open(path).map_err(|e| not(format!("cannot be read ({e})")))?;
            let n = f.read(&mut head).map_err(|e| not(format!("cannot be read ({e})")))?;
            if n < 9 {
                return Err(not(format!("only {n} bytes long")));
            }
        }
        let kind = if head[..8] == gonio_btf::compress::container::MAGIC[..] {
            SourceKind::Gbtf
        } else if gonio_btf::compress::btf_ubo2014::is_dfmf(&head) {
            SourceKind::Btf
        } else {
            return Err(not(
                "a file of unknown type (neither .gbtf nor UBO2014 .btf signature)".into()
            ));
        };
        Ok(Source::Model {
            model: AnyModel::open(path)?,
            kind,
        })
    }

    pub fn kind(&self) -> SourceKind {
        match self {
            Source::Dataset(_) => SourceKind::Dataset,
            Source::Model { kind, .. } => *kind,
        }
    }

    pub fn model(&self) -> &dyn BtfModel {
        match self {
            Source::Dataset(m) => m,
            Source::Model { model, .. } => model.model(),
        }
    }
}
