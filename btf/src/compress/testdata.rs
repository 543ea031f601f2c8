//! Small synthetic datasets for the tests of every method (test builds only).

use crate::compress::{compress, CompressedBtf, DatasetViews, Gbtf, Params};
use gonio_dataset::store::{self, Dataset, ManifestHeader, MeasurementRecord, MeasurementStatus};
use gonio_devices::image::RgbImage;
use std::path::Path;

/// Write a dataset on the grid `lights` × `views` whose image (light, view) is
/// `f(light, view, texel, channel)`; pairs in `skip` are recorded as skipped.
pub fn write_test_dataset(
    dir: &Path,
    (w, h): (usize, usize),
    lights: &[[f64; 2]],
    views: &[[f64; 2]],
    skip: &[(usize, usize)],
    f: impl Fn(usize, usize, usize, usize) -> f32,
) -> DatasetViews {
    let header = ManifestHeader {
        format: store::FORMAT.into(),
        version: store::FORMAT_VERSION,
        gonio_version: "test".into(),
        created_unix: 1_700_000_000.0,
        rig: serde_json::json!({"name": "test rig"}),
        sample: serde_json::json!({"name": "synthetic"}),
        sweep: serde_json::json!({"name": "t", "lights_deg": lights, "views_deg": views}),
        image_width: w,
        image_height: h,
        values: "synthetic".into(),
        seed: 1,
        raw_frames: false,
        calibration: None,
        extra: serde_json::Value::Null,
    };
    let mut ds = Dataset::create(dir, &header, false).unwrap();
    for (v, vd) in views.iter().enumerate() {
        for (l, ld) in lights.iter().enumerate() {
            let index = v * lights.len() + l;
            let mut rec = MeasurementRecord::new(index, index, *ld, *vd);
            if skip.contains(&(l, v)) {
                rec.status = MeasurementStatus::Skipped { reason: "test".into() };
                ds.store(rec, None, None).unwrap();
                continue;
            }
            let mut img = RgbImage::new(w, h);
            for t in 0..w * h {
                for c in 0..3 {
                    img.data[t * 3 + c] = f(l, v, t, c);
                }
            }
            ds.store(rec, Some(&img), None).unwrap();
        }
    }
    ds.finish(&serde_json::json!({})).unwrap();
    DatasetViews::open(dir).unwrap()
}

pub const W: usize = 8;
pub const H: usize = 6;

pub fn lights() -> Vec<[f64; 2]> {
    vec![[0.0, 0.0], [30.0, 0.0], [30.0, 120.0], [30.0, 240.0], [60.0, 90.0]]
}
pub fn views() -> Vec<[f64; 2]> {
    vec![[0.0, 0.0], [45.0, 0.0], [45.0, 180.0], [60.0, 270.0]]
}

/// Write a dataset of `w × h` texels on the given grid whose image (light, view) is
/// `f(light, view, texel, channel)`, and open it.
pub fn write_grid(
    dir: &Path,
    w: usize,
    h: usize,
    ls: &[[f64; 2]],
    vs: &[[f64; 2]],
    f: impl Fn(usize, usize, usize, usize) -> f32,
) -> DatasetViews {
    write_test_dataset(dir, (w, h), ls, vs, &[], f)
}

/// [`write_grid`] on the default 8 × 6 texel, 5 light × 4 view grid.
pub fn write(dir: &Path, f: impl Fn(usize, usize, usize, usize) -> f32) -> DatasetViews {
    write_grid(dir, W, H, &lights(), &views(), f)
}

/// Largest absolute difference between the stored images and the reconstruction.
pub fn max_err(ds: &DatasetViews, m: &CompressedBtf) -> f32 {
    let mut e = 0f32;
    for v in 0..ds.n_views() {
        for l in 0..ds.n_lights() {
            let orig = ds.read_image(l, v).unwrap().unwrap();
            let rec = m.reconstruct(l, v).unwrap();
            for (a, b) in orig.iter().zip(&rec) {
                assert!(b.is_finite());
                e = e.max((a - b).abs());
            }
        }
    }
    e
}

/// Compress, write, read back (every CRC), compare and wrap.
pub fn round_trip(ds: &DatasetViews, p: &Params, file: &Path) -> (Gbtf, CompressedBtf) {
    let (g, _) = compress(ds, p).unwrap();
    g.write(file).unwrap();
    let back = Gbtf::read(file).unwrap();
    assert_eq!(back, g);
    (g, CompressedBtf::new(back).unwrap())
}

/// Deterministic hash in [0, 1).
pub fn hash(a: usize, b: usize) -> f32 {
    let mut s = (a as u64) << 32 ^ b as u64;
    (crate::compress::linalg::splitmix(&mut s) >> 40) as f32 / (1u64 << 24) as f32
}
