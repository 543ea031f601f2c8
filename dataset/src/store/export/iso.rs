//! Reconstructing the full pair set of an isotropic acquisition on export.
//!
//! A plan built for an isotropic sample (`plan::Plan::build_isotropic`, `--isotropic`)
//! measures one pair per isotropy class and lists every other pair under
//! `isotropic.equivalents` in the dataset's `plan.json`: its representative and the
//! transform `T` (mirror φ → −φ if `mirrored`, then a rotation by ψ about the normal) with
//! `member = T(representative)`. Exports (UBO2003, NumPy) then contain every pair of the
//! sweep: measured ones as stored, the others as their representative's image with the
//! texel grid transformed by `T`, status `"isotropic"`.
//!
//! **Why the texel grid is transformed.** Measuring the sample turned by ψ about its
//! normal at the representative's directions is the same physical configuration as
//! measuring the unturned sample at the member's directions; the surface point that was
//! at `p` is then at `T p`. So `I_member(x) = I_rep(T⁻¹ x)` holds exactly for the turned
//! sample, and for the sample as it is only statistically: a statistically isotropic
//! texture shows a *different* patch with the same statistics. For a homogeneous material
//! the transform changes nothing but the (tiny) resampling blur.
//!
//! **Approximations, stated.** Bilinear resampling (one texel of blur at most); the square
//! sample turned by a ψ that is not a multiple of 90° needs texels from outside the
//! measured square in its corners, which are filled by clamping to the nearest edge texel.
//! Pure quarter turns and mirrors are exact texel permutations.

use super::entry::{entry_name, integer_angles, ExportEntry, IsoTransform};
use crate::store::error::StoreError;
use crate::store::manifest::{MeasurementRecord, MeasurementStatus};
use serde::Deserialize;
use std::collections::HashMap;
use std::path::Path;

/// File of the dataset holding the plan (written by `gonio acquire`).
use crate::store::PLAN_FILE;

/// The part of `plan.json` this module reads (the rest of the plan is not its business).
#[derive(Deserialize)]
struct PlanFile {
    #[serde(default)]
    isotropic: Option<IsoSection>,
}

#[derive(Deserialize)]
struct IsoSection {
    equivalents: Vec<Equivalent>,
}

/// Mirrors `plan::isotropic::Equivalent` (the store does not depend on the planner).
#[derive(Deserialize)]
struct Equivalent {
    index: usize,
    representative: usize,
    light_deg: [f64; 2],
    view_deg: [f64; 2],
    rotation_deg: f64,
    mirrored: bool,
}

/// Read the isotropic equivalents from the dataset's `plan.json` (none when the file or
/// the section is absent: an ordinary dataset).
fn equivalents(dir: &Path) -> Result<Vec<Equivalent>, StoreError> {
    let path = dir.join(PLAN_FILE);
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(StoreError::io("reading", &path, Some(dir), e)),
    };
    let plan: PlanFile = serde_json::from_slice(&bytes).map_err(|source| StoreError::Json { path, source })?;
    Ok(plan.isotropic.map(|s| s.equivalents).unwrap_or_default())
}

/// Add an entry for every isotropic equivalent whose representative was measured, then
/// renumber all entries in canonical order. Returns how many equivalents could not be
/// exported (representative skipped, substituted or not recorded): they are added to the
/// export's "not exported" count, never exported under a direction nobody measured.
pub(crate) fn extend(
    dir: &Path,
    records: &[MeasurementRecord],
    entries: &mut Vec<ExportEntry>,
    out: &Path,
) -> Result<usize, StoreError> {
    let eqs = equivalents(dir)?;
    if eqs.is_empty() {
        return Ok(0);
    }
    let by_index: HashMap<usize, &MeasurementRecord> = records.iter().map(|r| (r.index, r)).collect();
    let mut missing = 0;
    for e in eqs {
        if by_index.contains_key(&e.index) {
            continue; // measured after all (e.g. a plan edited by hand): the measurement wins
        }
        let rep = match by_index.get(&e.representative) {
            Some(r) if r.status == MeasurementStatus::Measured && r.image.is_some() => *r,
            _ => {
                missing += 1;
                continue;
            }
        };
        entries.push(ExportEntry {
            position: 0,
            index: e.index,
            name: String::new(),
            light: integer_angles(e.light_deg),
            view: integer_angles(e.view_deg),
            light_deg: e.light_deg,
            view_deg: e.view_deg,
            status: "isotropic",
            image: rep.image.clone().expect("checked above"),
            image_sha256: rep.image_sha256.clone(),
            transform: Some(IsoTransform {
                representative: e.representative,
                rotation_deg: e.rotation_deg,
                mirrored: e.mirrored,
            }),
        });
    }
    entries.sort_by_key(|e| e.index);
    let mut seen: HashMap<([u32; 2], [u32; 2]), usize> = HashMap::new();
    for (position, e) in entries.iter_mut().enumerate() {
        e.position = position;
        e.name = entry_name(position, e.light_deg, e.view_deg);
        if let Some(first) = seen.insert((e.light, e.view), e.index) {
            return Err(StoreError::ExportConflict {
                path: out.to_path_buf(),
                first,
                second: e.index,
                name: e.name.clone(),
            });
        }
    }
    Ok(missing)
}

#[cfg(test)]
mod tests {
    use super::*;
    use gonio_devices::image::RgbImage;

    fn numbered(w: usize, h: usize) -> RgbImage {
        let mut img = RgbImage::new(w, h);
        for y in 0..h {
            for x in 0..w {
                img.set(x, y, [x as f32, y as f32, (y * w + x) as f32]);
            }
        }
        img
    }

    #[test]
    fn quarter_turns_and_mirrors_permute_texels() {
        let n = 6;
        let img = numbered(n, n);
        let t = |rotation_deg, mirrored| IsoTransform {
            representative: 0,
            rotation_deg,
            mirrored,
        };
        assert_eq!(t(0.0, false).apply(&img).data, img.data);
        assert_eq!(t(360.0, false).apply(&img).data, img.data);
        // +90° about +z: the texel at sample (u, v) moves to (−v, u). In image terms the
        // column index grows with +x and the row index with −y, so the content of
        // (col c, row r) of the representative lands at (col r, row n−1−c).
        let r = t(90.0, false).apply(&img);
        for row in 0..n {
            for col in 0..n {
                assert_eq!(r.get(row, n - 1 - col), img.get(col, row), "col {col} row {row}");
            }
        }
        // mirror y → −y: rows flip
        let m = t(0.0, true).apply(&img);
        for row in 0..n {
            for col in 0..n {
                assert_eq!(m.get(col, n - 1 - row), img.get(col, row));
            }
        }
        // four quarter turns and two mirrors are the identity
        let back = t(90.0, false).apply(&t(90.0, false).apply(&t(90.0, false).apply(&r)));
        assert_eq!(back.data, img.data);
        assert_eq!(t(0.0, true).apply(&m).data, img.data);
    }

    #[test]
    fn any_rotation_keeps_a_homogeneous_image() {
        let mut img = RgbImage::new(8, 8);
        for y in 0..8 {
            for x in 0..8 {
                img.set(x, y, [0.25, 0.5, 0.75]);
            }
        }
        for psi in [17.0, 123.4, 300.0] {
            let out = IsoTransform {
                representative: 0,
                rotation_deg: psi,
                mirrored: psi > 200.0,
            }
            .apply(&img);
            assert!(out.data.iter().zip(&img.data).all(|(a, b)| (a - b).abs() < 1e-6));
        }
    }

    /// End to end through the store: a dataset with one measured representative and a
    /// `plan.json` listing three equivalents exports the two whose representative exists,
    /// as texel permutations of it, and counts the third as not exported.
    #[test]
    fn npy_and_ubo2003_exports_contain_the_reconstructed_pairs() {
        use crate::store::export::export_npy;
        use crate::store::export::export_ubo2003;
        use crate::store::manifest::ManifestHeader;
        use crate::store::{Dataset, FORMAT, FORMAT_VERSION};
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("ds");
        let n = 8;
        let header = ManifestHeader {
            format: FORMAT.into(),
            version: FORMAT_VERSION,
            gonio_version: "test".into(),
            created_unix: 1_700_000_000.0,
            rig: serde_json::json!({"name": "test rig"}),
            sample: serde_json::json!({"name": "iso"}),
            sweep: serde_json::json!({"name": "test"}),
            image_width: n,
            image_height: n,
            values: "linear".into(),
            seed: 1,
            raw_frames: false,
            calibration: None,
            extra: serde_json::Value::Null,
        };
        let mut ds = Dataset::create(&dir, &header, false).unwrap();
        let mut img = RgbImage::new(n, n);
        for y in 0..n {
            for x in 0..n {
                img.set(x, y, [x as f32 / n as f32, y as f32 / n as f32, 0.5]);
            }
        }
        let mut rec = MeasurementRecord::new(0, 0, [30.0, 0.0], [45.0, 90.0]);
        rec.exposure_s = 0.01;
        ds.store(rec, Some(&img), None).unwrap();
        ds.finish(&serde_json::json!({})).unwrap();
        let eq = |index: usize, rep: usize, l: [f64; 2], v: [f64; 2], psi: f64, mirrored: bool| {
            serde_json::json!({"index": index, "representative": rep, "light_deg": l, "view_deg": v,
                               "rotation_deg": psi, "mirrored": mirrored})
        };
        let plan = serde_json::json!({"rig": "r", "isotropic": {"equivalents": [
            eq(1, 0, [30.0, 90.0], [45.0, 180.0], 90.0, false),
            eq(2, 0, [30.0, 0.0], [45.0, 270.0], 0.0, true),
            eq(3, 7, [30.0, 180.0], [45.0, 270.0], 180.0, false),
        ]}});
        std::fs::write(dir.join(PLAN_FILE), serde_json::to_vec(&plan).unwrap()).unwrap();

        let npy = tmp.path().join("x.npy");
        let r = export_npy(&dir, &npy).unwrap();
        assert_eq!((r.entries, r.skipped), (3, 1));
        let bytes = std::fs::read(&npy).unwrap();
        let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        let data: Vec<f32> = bytes[10 + hlen..]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let at = |e: usize, x: usize, y: usize| &data[((e * n + y) * n + x) * 3..][..3];
        for row in 0..n {
            for col in 0..n {
                assert_eq!(at(1, row, n - 1 - col), at(0, col, row), "quarter turn");
                assert_eq!(at(2, col, n - 1 - row), at(0, col, row), "mirror");
            }
        }
        let side: serde_json::Value =
            serde_json::from_slice(&std::fs::read(crate::store::export::npy_sidecar_path(&npy)).unwrap()).unwrap();
        let st: Vec<&str> = side["entries"]
            .as_array()
            .unwrap()
            .iter()
            .map(|e| e["status"].as_str().unwrap())
            .collect();
        assert_eq!(st, ["measured", "isotropic", "isotropic"]);
        assert_eq!(
            side["entries"][1]["entry"],
            "tv045_pv180/00001 tl030 pl090 tv045 pv180.jpg"
        );
        let z = export_ubo2003(&dir, &tmp.path().join("x.zip")).unwrap();
        assert_eq!((z.entries, z.skipped), (3, 1));
    }
}
