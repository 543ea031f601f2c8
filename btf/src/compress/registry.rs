//! The one registry of compression methods: [`codec`] maps every [`CodecId`] to the
//! [`Codec`] its method file implements (name, knob ladder, encoder, decoder and the facts
//! others match on: [`Layout`](super::params::Layout), [`Shard`](super::params::Shard)).
//!
//! **A new method** is one new file `compress/NAME.rs` (its encoder, decoder and `impl
//! Codec`), its variant of [`Method`](super::params::Method) (the knobs the file's
//! parameters record) and of [`CodecId`] (with its name) in `params.rs`, and one line in
//! [`codec`]. Every `match` on those enums is exhaustive, so a forgotten line does not
//! compile; [`tests`] walk the registry (names unique and round-tripping, [`CodecId::ALL`]
//! complete, every method with a ladder encodes and opens a small BTF), so a method that
//! is registered but broken fails a test.
//!
//! Who reads the registry: `factor` ([`super::compress`] and
//! [`CompressedBtf::new`](super::CompressedBtf::new)), `target` (the ladders), the CLI
//! (`--method`, `--shard`), and through `CompressedBtf::layout` the readers above
//! `compress` (synthesis, the viewer).

use super::params::{Codec, CodecId};
use super::{cmf, dfmf, gltf, homomorphic, local_pca, median_cut, nd, pca, pvmf, svbrdf, svd_j};

/// The codec of method `id`.
pub fn codec(id: CodecId) -> &'static dyn Codec {
    match id {
        CodecId::Pca => &pca::PcaCodec,
        CodecId::Pvmf => &pvmf::PvmfCodec,
        CodecId::LocalPca => &local_pca::LocalPcaCodec,
        CodecId::MedianCut => &median_cut::MedianCutCodec,
        CodecId::Homomorphic => &homomorphic::HomomorphicCodec,
        CodecId::Dfmf => &dfmf::DfmfCodec,
        CodecId::Nd => &nd::NdCodec,
        CodecId::SvdJ => &svd_j::SvdJCodec,
        CodecId::Gshd => &cmf::GshdCodec,
        CodecId::Cmf => &cmf::CmfCodec,
        CodecId::Svbrdf => &svbrdf::SvbrdfCodec,
        CodecId::Gltf => &gltf::GltfCodec,
    }
}

/// Every codec, in the order of [`CodecId::ALL`].
pub fn codecs() -> impl Iterator<Item = &'static dyn Codec> {
    CodecId::ALL.into_iter().map(codec)
}

/// The methods `gonio compress --method` encodes (those with a knob ladder), in the order
/// of [`CodecId::ALL`].
pub fn encodable() -> impl Iterator<Item = CodecId> {
    codecs().filter(|c| !c.ladder(&KNOBS).is_empty()).map(|c| c.id())
}

/// Knobs for asking a codec whether it has a ladder at all.
const KNOBS: super::params::Knobs = super::params::Knobs {
    seed: 1,
    oversample: 10,
    power_iters: 2,
    iters: 1,
    subspace: 0,
    in_passes: false,
    balanced: false,
    min_error_cut: false,
    half_bins: 4,
    sweeps: None,
};

#[cfg(test)]
mod tests {
    use super::*;
    use crate::compress::params::{Knobs, Params};
    use crate::compress::testdata::{hash, write};
    use crate::compress::{compress, CompressedBtf, DatasetViews, Gbtf};
    use std::collections::BTreeSet;

    #[test]
    fn every_method_is_registered_once_under_its_name() {
        for (i, id) in CodecId::ALL.into_iter().enumerate() {
            // ALL lists the variants in declaration order, without gaps: a variant left out
            // of it would leave a gap here or at the end (the last variant is `Gltf`).
            assert_eq!(id as usize, i, "{id:?}");
            assert_eq!(codec(id).id(), id, "{id:?}");
            assert_eq!(CodecId::from_name(id.name()), Some(id));
        }
        assert_eq!(CodecId::Gltf as usize + 1, CodecId::ALL.len());
        let names: BTreeSet<&str> = CodecId::ALL.iter().map(|c| c.name()).collect();
        assert_eq!(names.len(), CodecId::ALL.len(), "names are unique");
        assert_eq!(CodecId::from_name("no-such-method"), None);
    }

    #[test]
    fn every_ladder_names_its_own_method() {
        let knobs = Knobs {
            half_bins: 12,
            sweeps: Some(3),
            ..KNOBS
        };
        for c in codecs() {
            for ladder in c.ladder(&knobs) {
                assert!(!ladder.is_empty(), "{:?}", c.id());
                assert!(ladder.iter().all(|p| p.method.id() == c.id()), "{:?}", c.id());
            }
        }
        let names: Vec<&str> = encodable().map(CodecId::name).collect();
        assert_eq!(
            names,
            [
                "pca",
                "pvmf",
                "local-pca",
                "median-cut",
                "homomorphic",
                "dfmf",
                "nd",
                "svd-j",
                "gshd",
                "cmf"
            ]
        );
    }

    /// The smallest rung of every method's ladder, made cheap.
    fn small(id: CodecId) -> Option<Params> {
        let knobs = Knobs {
            iters: 2,
            half_bins: 4,
            sweeps: Some(2),
            ..KNOBS
        };
        let mut p = codec(id).ladder(&knobs).into_iter().next()?.into_iter().next()?;
        p.components = p.components.min(2);
        if let crate::compress::Method::MedianCut { boxes, .. } = &mut p.method {
            *boxes = 4;
        }
        if let crate::compress::Method::LocalPca { clusters, .. } = &mut p.method {
            *clusters = 2;
        }
        if let crate::compress::Method::Gshd { theta_bins, .. } = &mut p.method {
            *theta_bins = 4;
        }
        if let crate::compress::Method::Dfmf { chroma_components, .. } = &mut p.method {
            *chroma_components = 1;
        }
        Some(p)
    }

    /// A file of method `id` for the dataset `ds`: its smallest rung through `gonio
    /// compress`'s encoder, or (SVBRDF, glTF: written by `gonio fit`) its writer with
    /// plausible parameters.
    fn small_file(ds: &DatasetViews, id: CodecId) -> Gbtf {
        if let Some(params) = small(id) {
            return compress(ds, &params).unwrap_or_else(|e| panic!("{id:?}: {e}")).0;
        }
        let e = compress(ds, &Params::new(svbrdf_or_gltf(id), 1))
            .unwrap_err()
            .to_string();
        assert!(e.contains("gonio fit"), "{id:?}: {e}");
        let (t, pairs) = (ds.texels(), ds.n_lights() * ds.n_views());
        let gain: Vec<f32> = (0..pairs)
            .flat_map(|_| [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
            .collect();
        match id {
            CodecId::Svbrdf => {
                let np = svbrdf::params_per_texel(1);
                let texel = [0.3, 0.3, 0.3, 0.5, 10.0, 0.1, 0.1, 0.1];
                let params: Vec<f32> = (0..t).flat_map(|_| texel[..np].to_vec()).collect();
                svbrdf::encode(ds, 1, params, gain, None).unwrap()
            }
            CodecId::Gltf => {
                // Isotropic: the anisotropy vector (the last two of `gltf::PARAMS`) is zero.
                let texel = [0.5f32, 0.4, 0.3, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0];
                assert_eq!(texel.len(), gltf::PARAMS);
                let params: Vec<f32> = (0..t).flat_map(|_| texel).collect();
                gltf::encode(ds, params, gain, vec![0.0; t * 2], None).unwrap()
            }
            other => panic!("{other:?} has a ladder"),
        }
    }

    #[test]
    fn every_method_encodes_and_opens_a_small_btf() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = write(tmp.path(), |l, v, t, c| 0.1 + 0.5 * hash(l * 7 + v, t * 3 + c));
        for id in CodecId::ALL {
            let g = small_file(&ds, id);
            assert_eq!(g.header.method, id.name());
            let back = Gbtf::from_bytes(&g.to_bytes().unwrap(), std::path::Path::new("small.gbtf")).unwrap();
            let m = CompressedBtf::new(back).unwrap_or_else(|e| panic!("{id:?}: {e}"));
            assert_eq!(m.method().id(), id);
            let img = m.reconstruct(1, 2).unwrap();
            assert_eq!(img.len(), ds.texels() * 3, "{id:?}");
            assert!(img.iter().all(|x| x.is_finite()), "{id:?}");
            if let Ok(b) = m.layout().texel_blocks(m.gbtf.blocks.len()) {
                assert_eq!(b.len(), m.gbtf.blocks.len(), "{id:?}");
            }
        }
    }

    fn svbrdf_or_gltf(id: CodecId) -> crate::compress::Method {
        match id {
            CodecId::Svbrdf => crate::compress::Method::Svbrdf { lobes: 1 },
            CodecId::Gltf => crate::compress::Method::Gltf,
            other => panic!("{other:?} has a ladder"),
        }
    }
}
