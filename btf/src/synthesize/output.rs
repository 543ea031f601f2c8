//! Writing a synthesized BTF: a `.gbtf` of the exemplar's own kind whose per-texel rows
//! are gathered through the texel map, plus the map itself as a sidecar PNG.
//!
//! Which blocks are per texel, by method (all others are copied unchanged):
//!
//! | method | per-texel blocks (gathered) | shared blocks (copied) | output size per texel |
//! |---|---|---|---|
//! | pca | `us` (c values) | `v` | 4·c bytes: compact |
//! | local-pca | `cluster` (1), `coef` (c) | `mean`, `basis` | 4·(c + 1) bytes: compact |
//! | median-cut | `index` (1) | `brdfs` | 4 bytes: compact (the index image) |
//! | pvmf | every view's `us` (c each) | every view's `v` | 4·c·views bytes: **not** compact (81 views · c = 4: 1.3 KiB per texel, 1.3 GiB at 1024²) |
//! | homomorphic | all four | none | 4·3·(1 + lights + views + bins): **not** compact |
//!
//! The output file is streamed block by block ([`GbtfStreamWriter`]): memory is the texel
//! map (4 bytes per output texel) plus the exemplar, never an image of the output.
//!
//! **Texel map sidecar** (`<out stem>.texelmap.png`): a 16-bit RGB PNG of the output's
//! size, red = exemplar column, green = exemplar row, blue = 0; deflate makes it small
//! because synthesized maps are piecewise affine. The `.gbtf` header's `source.synthesis`
//! names it and records method, parameters, seed, features and the exemplar.

use super::{SynthError, TexelMap};
use crate::compress::btf_ubo2014::{self, Precision};
use crate::compress::container::{BlockInfo, GbtfStreamWriter};
use crate::compress::dfmf::{ChannelFactors, Dfmf};
use crate::compress::{CompressedBtf, GbtfHeader};
use std::path::{Path, PathBuf};

/// Which blocks of the exemplar's file are indexed by texel, or why the model cannot be
/// synthesized from (its layout's [`Layout::texel_blocks`](crate::compress::Layout::texel_blocks)).
pub fn texel_blocks(model: &CompressedBtf) -> Result<Vec<bool>, SynthError> {
    model
        .layout()
        .texel_blocks(model.header().blocks.len())
        .map_err(|why| SynthError::Invalid(why.into()))
}

/// The sidecar path for an output file.
pub fn texel_map_path(out: &Path) -> PathBuf {
    let stem = out
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    out.with_file_name(format!("{stem}.texelmap.png"))
}

/// What was written.
#[derive(serde::Serialize, Clone, Debug)]
pub struct Written {
    pub file: PathBuf,
    pub bytes: u64,
    pub texel_map: PathBuf,
    pub texel_map_bytes: u64,
    /// Bytes per output texel in the `.gbtf` (per-texel blocks only).
    pub bytes_per_texel: usize,
}

/// The header of the synthesized file: the exemplar's with the output size, per-texel
/// block shapes and provenance.
pub fn header_for(
    model: &CompressedBtf,
    map: &TexelMap,
    provenance: serde_json::Value,
) -> Result<GbtfHeader, SynthError> {
    let per_texel = texel_blocks(model)?;
    let mut h = model.header().clone();
    let t_in = h.width * h.height;
    let t_out = map.width * map.height;
    h.blocks = h
        .blocks
        .iter()
        .zip(&per_texel)
        .map(|(b, &pt)| {
            debug_assert!(!pt || b.rows == t_in);
            // Rows are written as plain f32 (the exemplar's decoded values), whatever codec
            // the input used.
            BlockInfo::new(b.name.clone(), if pt { t_out } else { b.rows }, b.cols)
        })
        .collect();
    h.width = map.width;
    h.height = map.height;
    let old = std::mem::take(&mut h.source);
    h.source = serde_json::json!({ "synthesis": provenance, "exemplar_source": old });
    Ok(h)
}

/// Write the synthesized model to `out` and the texel map beside it.
pub fn write(
    model: &CompressedBtf,
    map: &TexelMap,
    out: &Path,
    provenance: serde_json::Value,
) -> Result<Written, SynthError> {
    let eh = model.header();
    if (map.src_width, map.src_height) != (eh.width, eh.height) {
        return Err(SynthError::Invalid(format!(
            "the texel map indexes a {}×{} exemplar, the model is {}×{}",
            map.src_width, map.src_height, eh.width, eh.height
        )));
    }
    let sidecar = texel_map_path(out);
    let mut prov = provenance;
    if let Some(o) = prov.as_object_mut() {
        o.insert(
            "texel_map".into(),
            serde_json::Value::String(sidecar.file_name().unwrap_or_default().to_string_lossy().into_owned()),
        );
    }
    let header = header_for(model, map, prov)?;
    let per_texel = texel_blocks(model)?;
    let mut w = GbtfStreamWriter::create(out, &header)?;
    const ROWS: usize = 4096;
    let mut bytes_per_texel = 0;
    for ((block, info), &pt) in model.gbtf.blocks.iter().zip(&eh.blocks).zip(&per_texel) {
        if !pt {
            w.push(block)?;
            continue;
        }
        let c = info.cols;
        bytes_per_texel += 4 * c;
        let mut buf = Vec::with_capacity(ROWS * c);
        for chunk in map.src.chunks(ROWS) {
            buf.clear();
            for &s in chunk {
                let s = s as usize;
                buf.extend_from_slice(&block[s * c..(s + 1) * c]);
            }
            w.push(&buf)?;
        }
    }
    let bytes = w.finish()?;
    let texel_map_bytes = write_texel_map(map, &sidecar)?;
    Ok(Written {
        file: out.to_path_buf(),
        bytes,
        texel_map: sidecar,
        texel_map_bytes,
        bytes_per_texel,
    })
}

/// The scalar size a synthesized UBO2014 file is written with: half floats when every
/// factor of the exemplar is exactly a half float (a file stored in half precision, read
/// into f32), else f32. Either way the output holds the exemplar's factors bit for bit.
pub fn dfmf_precision(d: &Dfmf) -> Precision {
    let exact = |v: &[f32]| {
        v.iter()
            .all(|&x| half::f16::from_f32(x).to_f32().to_bits() == x.to_bits())
    };
    if d.channels
        .iter()
        .all(|c| exact(&c.sigma) && exact(&c.u) && exact(&c.sxv))
    {
        Precision::F16
    } else {
        Precision::F32
    }
}

/// Refuse an output the UBO2014 container cannot hold, before any work: the public
/// reader computes every factor plane's byte count in 32 bits.
pub fn check_dfmf_output(d: &Dfmf, width: usize, height: usize, input: &Path) -> Result<(), SynthError> {
    let p = dfmf_precision(d);
    let c = d.channels.iter().map(|c| c.c).max().unwrap_or(0);
    let t = width as u128 * height as u128;
    let plane = t * c as u128 * p.bytes() as u128;
    if plane > u32::MAX as u128 {
        let max_t = u32::MAX as u128 / (c as u128 * p.bytes() as u128);
        let side = (max_t as f64).sqrt().floor() as u64;
        return Err(SynthError::Invalid(format!(
            "{}: a {width}×{height} UBO2014 .btf with {c} components per channel at {} bytes per value \
             needs {plane} bytes per S·V plane, more than the format's 32-bit sizes allow; ask for at most \
             {max_t} texels (e.g. --size {side}x{side})",
            input.display(),
            p.bytes()
        )));
    }
    Ok(())
}

/// The exemplar's DFMF model with every channel's texel factors (`S·V` rows) gathered
/// through the map: measurement factors `U`, singular values, colour model and
/// directions unchanged.
pub fn gather_dfmf(d: &Dfmf, map: &TexelMap) -> Result<Dfmf, SynthError> {
    if (map.src_width, map.src_height) != (d.width, d.height) {
        return Err(SynthError::Invalid(format!(
            "the texel map indexes a {}×{} exemplar, the model is {}×{}",
            map.src_width, map.src_height, d.width, d.height
        )));
    }
    let channels = d
        .channels
        .iter()
        .map(|ch| {
            let c = ch.c;
            let mut sxv = Vec::with_capacity(map.src.len() * c);
            for &s in &map.src {
                let s = s as usize;
                sxv.extend_from_slice(&ch.sxv[s * c..(s + 1) * c]);
            }
            ChannelFactors {
                c,
                sigma: ch.sigma.clone(),
                u: ch.u.clone(),
                sxv,
            }
        })
        .collect();
    Ok(Dfmf {
        color_model: d.color_model,
        width: map.width,
        height: map.height,
        lights_deg: d.lights_deg.clone(),
        views_deg: d.views_deg.clone(),
        channels,
    })
}

/// Write the synthesized DFMF model to `out` as a UBO2014 `.btf` (the exemplar's model,
/// texel factors gathered through the map; provenance as JSON in the header's XML field)
/// and the texel map beside it. Memory: the gathered factors and the serialized file
/// (`4 + p` bytes per output texel and component, p = 2 or 4), since the container is
/// written in one piece.
pub fn write_dfmf(d: &Dfmf, map: &TexelMap, out: &Path, provenance: serde_json::Value) -> Result<Written, SynthError> {
    let sidecar = texel_map_path(out);
    let mut prov = provenance;
    if let Some(o) = prov.as_object_mut() {
        o.insert(
            "texel_map".into(),
            serde_json::Value::String(sidecar.file_name().unwrap_or_default().to_string_lossy().into_owned()),
        );
    }
    let precision = dfmf_precision(d);
    let g = gather_dfmf(d, map)?;
    let xml = format!("<gonio><synthesis>{prov}</synthesis></gonio>");
    let bytes = btf_ubo2014::write(out, &g, precision, &xml)?;
    let bytes_per_texel = g.channels.iter().map(|c| c.c).sum::<usize>() * precision.bytes();
    drop(g);
    let texel_map_bytes = write_texel_map(map, &sidecar)?;
    Ok(Written {
        file: out.to_path_buf(),
        bytes,
        texel_map: sidecar,
        texel_map_bytes,
        bytes_per_texel,
    })
}

/// Write the map as a 16-bit RGB PNG (red = exemplar column, green = row).
pub fn write_texel_map(map: &TexelMap, path: &Path) -> Result<u64, SynthError> {
    let mut raw: Vec<u16> = Vec::with_capacity(map.src.len() * 3);
    for t in 0..map.src.len() {
        let (x, y) = map.source_xy(t);
        raw.extend_from_slice(&[x as u16, y as u16, 0]);
    }
    let img = image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(map.width as u32, map.height as u32, raw)
        .ok_or_else(|| SynthError::Invalid("texel map buffer size".into()))?;
    let mut bytes = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
        .map_err(|e| SynthError::File {
            path: path.to_path_buf(),
            reason: format!("encoding the texel map PNG: {e}"),
        })?;
    gonio_dataset::store::atomic::write_atomic(path, &bytes, None).map_err(crate::compress::CompressError::from)?;
    Ok(bytes.len() as u64)
}

/// Read a texel map sidecar back (`src_width × src_height` is the exemplar's size, which
/// the PNG does not carry).
pub fn read_texel_map(path: &Path, src_width: usize, src_height: usize) -> Result<TexelMap, SynthError> {
    let bad = |reason: String| SynthError::File {
        path: path.to_path_buf(),
        reason,
    };
    let img = image::open(path).map_err(|e| bad(format!("reading the texel map: {e}")))?;
    let img = match img {
        image::DynamicImage::ImageRgb16(i) => i,
        other => {
            return Err(bad(format!(
                "a texel map is a 16-bit RGB PNG, this is {:?}",
                other.color()
            )))
        }
    };
    let (w, h) = (img.width() as usize, img.height() as usize);
    let mut src = Vec::with_capacity(w * h);
    for p in img.pixels() {
        let (x, y) = (p.0[0] as usize, p.0[1] as usize);
        if x >= src_width || y >= src_height {
            return Err(bad(format!(
                "texel ({x}, {y}) is outside the {src_width}×{src_height} exemplar"
            )));
        }
        src.push((y * src_width + x) as u32);
    }
    Ok(TexelMap {
        width: w,
        height: h,
        src_width,
        src_height,
        src,
    })
}

#[cfg(test)]
mod tests {
    use super::super::{features, synthesize, testutil, SynthMethod, SynthParams};
    use super::*;
    use crate::compress::interp::BtfModel;
    use crate::compress::{compress, Gbtf, Method, Params};

    /// For every model kind: the written file reads back as a model whose every image is
    /// the exemplar's image gathered through the texel map, and the streamed bytes equal
    /// `Gbtf::to_bytes` of the same content.
    #[test]
    fn written_models_decode_to_gathered_exemplar_images() {
        let dir = tempfile::tempdir().unwrap();
        let ds = testutil::write_dataset(&dir.path().join("ds"), 12, 10, testutil::textured);
        for method in [
            Method::Pca,
            Method::Pvmf,
            Method::LocalPca {
                clusters: 3,
                iters: 4,
                subspace: 0,
                in_passes: false,
            },
            Method::MedianCut {
                boxes: 6,
                balanced: false,
                min_error_cut: false,
            },
            Method::Homomorphic {
                half_bins: 0,
                sweeps: 2,
            },
        ] {
            let ex = CompressedBtf::new(compress(&ds, &Params::new(method, 3)).unwrap().0).unwrap();
            let e = features::embed(&ex).unwrap();
            let f = features::principal(&e.image, features::KChoice::Energy(0.95)).unwrap();
            let mut p = SynthParams::new(SynthMethod::Quilting, 29, 23, 12, 10);
            p.block = 6;
            p.overlap = 2;
            let map = synthesize(&f.image, &p).unwrap();
            let out = dir.path().join(format!("{}.gbtf", method.name()));
            let info = write(&ex, &map, &out, serde_json::json!({"method": "quilting"})).unwrap();
            let back = Gbtf::read(&out).unwrap();
            assert_eq!(back.to_bytes().unwrap().len() as u64, info.bytes);
            assert_eq!(std::fs::read(&out).unwrap(), back.to_bytes().unwrap());
            let m = CompressedBtf::new(back).unwrap();
            assert_eq!((m.width(), m.height()), (29, 23));
            for (l, v) in [(0, 0), (4, 3), (2, 1)] {
                let a = ex.reconstruct(l, v).unwrap();
                let b = m.reconstruct(l, v).unwrap();
                for (t, &s) in map.src.iter().enumerate() {
                    for c in 0..3 {
                        let (x, y) = (b[t * 3 + c], a[s as usize * 3 + c]);
                        assert!((x - y).abs() <= 1e-6 * (1.0 + y.abs()), "{}: {x} vs {y}", method.name());
                    }
                }
            }
            let back_map = read_texel_map(&info.texel_map, 12, 10).unwrap();
            assert_eq!(back_map, map);
        }
    }

    /// A UBO2014 `.btf` exemplar (log-YUV at half precision, RGB at f32): the written
    /// `.btf` reads back (gonio's reader) as the exemplar's model with the texel factors
    /// gathered, and decodes, for every (light, view), to exactly (bit for bit) the
    /// exemplar texel's values that the map names.
    #[test]
    fn written_btf_decodes_to_the_mapped_exemplar_texels_bit_for_bit() {
        use crate::compress::dfmf::{self, ColorModel, DfmfParams};
        use crate::compress::interp::AnyModel;
        let dir = tempfile::tempdir().unwrap();
        let ds = testutil::write_dataset(&dir.path().join("ds"), 12, 10, testutil::textured);
        for (model, precision) in [(ColorModel::LogYuv, Precision::F16), (ColorModel::Rgb, Precision::F32)] {
            let d = dfmf::encode(&ds, &DfmfParams::new(model, 3)).unwrap().0;
            let ex_path = dir.path().join(format!("ex-{}.btf", model.name()));
            btf_ubo2014::write(&ex_path, &d, precision, "<x/>").unwrap();
            let ex = btf_ubo2014::read(&ex_path).unwrap();
            assert_eq!(dfmf_precision(&ex), precision, "{}", model.name());
            let e = features::embed_dfmf(&ex).unwrap();
            let f = features::principal(&e.image, features::KChoice::Energy(0.95)).unwrap();
            let mut p = SynthParams::new(SynthMethod::Quilting, 29, 23, 12, 10);
            p.block = 6;
            p.overlap = 2;
            let map = synthesize(&f.image, &p).unwrap();
            // Not the identity: the test would pass trivially on a plain copy.
            assert!(map
                .src
                .iter()
                .enumerate()
                .any(|(t, &s)| s as usize != (t / 29) * 12 + t % 29));
            let out = dir.path().join(format!("big-{}.btf", model.name()));
            let info = write_dfmf(&ex, &map, &out, serde_json::json!({"method": "quilting"})).unwrap();
            assert_eq!(std::fs::metadata(&out).unwrap().len(), info.bytes);
            let AnyModel::Dfmf(back) = AnyModel::open(&out).unwrap() else {
                panic!("{}: not read back as a .btf", out.display())
            };
            assert_eq!(back, gather_dfmf(&ex, &map).unwrap());
            assert_eq!((back.width, back.height), (29, 23));
            for v in 0..ex.n_views() {
                for l in 0..ex.n_lights() {
                    let a = ex.reconstruct(l, v).unwrap();
                    let b = back.reconstruct(l, v).unwrap();
                    for (t, &s) in map.src.iter().enumerate() {
                        for c in 0..3 {
                            assert_eq!(
                                b[t * 3 + c].to_bits(),
                                a[s as usize * 3 + c].to_bits(),
                                "{}: pair ({l}, {v}), texel {t}",
                                model.name()
                            );
                        }
                    }
                }
            }
            assert_eq!(read_texel_map(&info.texel_map, 12, 10).unwrap(), map);
        }
    }

    #[test]
    fn a_btf_output_beyond_the_containers_32_bit_sizes_is_refused_before_any_work() {
        use crate::compress::dfmf::{self, ColorModel, DfmfParams};
        let dir = tempfile::tempdir().unwrap();
        let ds = testutil::write_dataset(&dir.path().join("ds"), 8, 6, testutil::textured);
        let d = dfmf::encode(&ds, &DfmfParams::new(ColorModel::Rgb, 2)).unwrap().0;
        // f32 factors (not half floats): 4 bytes per value, 2 components.
        assert_eq!(dfmf_precision(&d), Precision::F32);
        check_dfmf_output(&d, 20000, 20000, Path::new("ex.btf")).unwrap();
        let e = check_dfmf_output(&d, 40000, 40000, Path::new("ex.btf"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("ex.btf") && e.contains("40000×40000") && e.contains("--size"),
            "{e}"
        );
    }
}
