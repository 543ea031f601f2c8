//! Reference export for interop tests: the exact 8-bit sRGB values the UBO2003
//! exporter hands to its JPEG encoder, as a NumPy `.npy` array.
//!
//! `OUT` is a float32 array of shape `[N, H, W, 3]` (RGB, row 0 at the top, values
//! 0‥255), one image per exported measurement in UBO2003 export order. Next to it,
//! `OUT.json` (the `.npy` path with `.json` appended) lists per image the ZIP entry
//! name, the integer angles in the name and the exact angles of the record. Written
//! as a stream (a full Bonn dataset is 6561 × 256 × 256 × 3 floats = 5.2 GB), each
//! file under a temporary name renamed into place when complete.

use super::entry::{ensure_parent, for_each_in_order, load_srgb8, ExportReport};
use crate::store::atomic::{write_atomic, TempFile};
use crate::store::error::{IoContext, StoreError};
use crate::store::load;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// The sidecar JSON of an `.npy` export: `OUT` with `.json` appended.
pub fn npy_sidecar_path(out: &Path) -> PathBuf {
    let mut s = out.as_os_str().to_os_string();
    s.push(".json");
    PathBuf::from(s)
}

/// The `.npy` (format 1.0) header for a little-endian float32 C-order array.
pub fn npy_header(shape: &[usize]) -> Vec<u8> {
    npy_header_typed("<f4", shape)
}

/// The `.npy` (format 1.0) header for a C-order array of NumPy type `descr` (e.g. `<f8`).
pub fn npy_header_typed(descr: &str, shape: &[usize]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape_str = if dims.len() == 1 {
        format!("({},)", dims[0])
    } else {
        format!("({})", dims.join(", "))
    };
    let mut dict = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape_str}, }}");
    // magic (6) + version (2) + header length (2) + dict + '\n' must be a multiple of 64.
    let unpadded = 10 + dict.len() + 1;
    dict.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    dict.push('\n');
    let mut out = Vec::with_capacity(10 + dict.len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out
}

/// Write the reference array and its sidecar (see the module documentation).
pub fn export_npy(dir: &Path, out: &Path) -> Result<ExportReport, StoreError> {
    let (header, records) = load(dir)?;
    let (entries, skipped) = super::entries(dir, &records, out)?;
    ensure_parent(out)?;
    let (w, h) = (header.image_width, header.image_height);

    let mut tmp = TempFile::create(out, None)?;
    let tmp_path = tmp.tmp_path().to_path_buf();
    {
        let mut wr = BufWriter::with_capacity(1 << 20, tmp.file());
        wr.write_all(&npy_header(&[entries.len(), h, w, 3]))
            .ctx("writing", &tmp_path, None)?;
        for_each_in_order(
            &entries,
            |e| {
                let rgb = load_srgb8(dir, &header, e)?;
                let mut buf = Vec::with_capacity(rgb.len() * 4);
                for v in rgb {
                    buf.extend_from_slice(&f32::from(v).to_le_bytes());
                }
                Ok(buf)
            },
            |_, buf| wr.write_all(&buf).ctx("writing", &tmp_path, None),
        )?;
        wr.flush().ctx("writing", &tmp_path, None)?;
    }
    tmp.commit()?;

    let sidecar = npy_sidecar_path(out);
    let list: Vec<serde_json::Value> = entries
        .iter()
        .map(|e| {
            serde_json::json!({
                "position": e.position,
                "index": e.index,
                "entry": e.name,
                "tl": e.light[0], "pl": e.light[1], "tv": e.view[0], "pv": e.view[1],
                "light_deg": e.light_deg,
                "view_deg": e.view_deg,
                "status": e.status,
            })
        })
        .collect();
    let doc = serde_json::json!({
        "npy": out.file_name().map(|n| n.to_string_lossy().into_owned()),
        "shape": [entries.len(), h, w, 3],
        "values": "8-bit sRGB code values (0..255) stored as float32, RGB order, row 0 at \
                   the top: exactly the input of the UBO2003 exporter's JPEG encoder",
        "jpeg_quality": super::ubo2003::JPEG_QUALITY,
        "skipped_not_exported": skipped,
        "entries": list,
    });
    let mut bytes = serde_json::to_vec_pretty(&doc).map_err(|source| StoreError::Json {
        path: sidecar.clone(),
        source,
    })?;
    bytes.push(b'\n');
    write_atomic(&sidecar, &bytes, None)?;

    let bytes = std::fs::metadata(out).ctx("reading", out, None)?.len();
    Ok(ExportReport {
        path: out.to_path_buf(),
        entries: entries.len(),
        substituted: entries.iter().filter(|e| e.status == "substituted").count(),
        skipped,
        bytes,
        sidecar: Some(sidecar),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_is_aligned_and_parsable() {
        for shape in [vec![0, 4, 4, 3], vec![12, 256, 256, 3], vec![5]] {
            let h = npy_header(&shape);
            assert_eq!(h.len() % 64, 0);
            assert_eq!(&h[..8], b"\x93NUMPY\x01\x00");
            let len = u16::from_le_bytes([h[8], h[9]]) as usize;
            assert_eq!(10 + len, h.len());
            assert_eq!(*h.last().unwrap(), b'\n');
            let text = std::str::from_utf8(&h[10..]).unwrap();
            assert!(text.contains("'descr': '<f4'"), "{text}");
        }
        let h = npy_header(&[12, 256, 256, 3]);
        assert!(std::str::from_utf8(&h[10..])
            .unwrap()
            .contains("'shape': (12, 256, 256, 3)"));
        assert!(std::str::from_utf8(&npy_header(&[5])[10..])
            .unwrap()
            .contains("'shape': (5,)"));
    }
}
