//! The exemplar a synthesis gathers from: a `.gbtf` of any texel-separable kind, or a
//! UBO2014 DFMF `.btf`. Both decode through [`BtfModel`]; they differ in how texels are
//! embedded for matching ([`features::embed`], [`features::embed_dfmf`]) and how the
//! output is written ([`output::write`]: a `.gbtf` of the same kind; [`output::write_dfmf`]:
//! a `.btf` of the same DFMF model with the texel factors gathered through the map).

use super::features::{self, Embedding};
use super::output::{self, Written};
use super::{SynthError, TexelMap};
use crate::compress::dfmf::Dfmf;
use crate::compress::interp::BtfModel;
use crate::compress::{CompressedBtf, Layout};
use std::path::Path;

// One value per run, never in a collection: the size difference costs nothing.
#[allow(clippy::large_enum_variant)]
pub enum Exemplar {
    Gbtf(CompressedBtf),
    /// A UBO2014 DFMF `.btf`.
    Dfmf(Dfmf),
}

impl Exemplar {
    pub fn model(&self) -> &dyn BtfModel {
        match self {
            Exemplar::Gbtf(m) => m,
            Exemplar::Dfmf(d) => d,
        }
    }
    pub fn width(&self) -> usize {
        self.model().width()
    }
    pub fn height(&self) -> usize {
        self.model().height()
    }
    /// The model's name for reports: the `.gbtf` method, or `dfmf-btf` with its colour model.
    pub fn model_name(&self) -> String {
        match self {
            Exemplar::Gbtf(m) => m.method().name().to_string(),
            Exemplar::Dfmf(d) => format!("dfmf-btf ({})", d.color_model.name()),
        }
    }
    /// The file extension of the output: the exemplar's own kind.
    pub fn extension(&self) -> &'static str {
        match self {
            Exemplar::Gbtf(_) => "gbtf",
            Exemplar::Dfmf(_) => "btf",
        }
    }
    /// Whether the output stores only a texel map into shared factors (see
    /// `docs/guide/synthesis.md`, "What is stored").
    pub fn compact(&self) -> bool {
        match self {
            Exemplar::Dfmf(_) => true,
            Exemplar::Gbtf(m) => match m.layout() {
                Layout::Basis
                | Layout::Clusters { .. }
                | Layout::Index { .. }
                | Layout::ChannelFactors
                | Layout::AnalyticPerTexel => true,
                Layout::ViewBases | Layout::HalfVectorTables { .. } | Layout::PerTexel => false,
            },
        }
    }
    pub fn embed(&self) -> Result<Embedding, SynthError> {
        match self {
            Exemplar::Gbtf(m) => features::embed(m),
            Exemplar::Dfmf(d) => features::embed_dfmf(d),
        }
    }
    /// Refuse, before any work, an output the exemplar's container cannot hold.
    pub fn check_output(&self, width: usize, height: usize, input: &Path) -> Result<(), SynthError> {
        match self {
            Exemplar::Gbtf(_) => Ok(()),
            Exemplar::Dfmf(d) => output::check_dfmf_output(d, width, height, input),
        }
    }
    pub fn write(&self, map: &TexelMap, out: &Path, provenance: serde_json::Value) -> Result<Written, SynthError> {
        match self {
            Exemplar::Gbtf(m) => output::write(m, map, out, provenance),
            Exemplar::Dfmf(d) => output::write_dfmf(d, map, out, provenance),
        }
    }
}
