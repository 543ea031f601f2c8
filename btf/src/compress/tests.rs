//! Tests of the compression pipeline on small synthetic datasets written with `store`.

use super::*;
use faer::Mat;
use gonio_dataset::store;
use gonio_devices::image::RgbImage;
use std::path::Path;

const W: usize = 8;
const H: usize = 6;

fn lights() -> Vec<[f64; 2]> {
    vec![[0.0, 0.0], [30.0, 0.0], [30.0, 120.0], [30.0, 240.0], [60.0, 90.0]]
}
fn views() -> Vec<[f64; 2]> {
    vec![[0.0, 0.0], [45.0, 0.0], [45.0, 180.0], [60.0, 270.0]]
}

/// Write a dataset whose image (light, view) is `f(light, view, texel, channel)`;
/// pairs in `skip` are recorded as skipped.
fn write_dataset(dir: &Path, skip: &[(usize, usize)], f: impl Fn(usize, usize, usize, usize) -> f32) {
    super::testdata::write_test_dataset(dir, (W, H), &lights(), &views(), skip, f);
}

/// An exactly rank-3 BTF whose values are exact in half float (multiples of 1/128 below
/// 0.5), so the EXR round trip does not perturb the rank: a_k(texel) ∈ {0,¼,½,¾},
/// b_k(light, view, channel) ∈ {0, 1/32, …, 7/32}.
fn rank3(l: usize, v: usize, t: usize, c: usize) -> f32 {
    (0..3)
        .map(|k| {
            let a = ((t * (k + 1) + k * 5 + t / 3) % 4) as f32 / 4.0;
            let b = ((l * 3 + v * (k + 2) + c * (k + 1) + k) % 8) as f32 / 32.0;
            a * b
        })
        .sum()
}

/// A full-rank BTF (hash noise plus structure).
fn noisy(l: usize, v: usize, t: usize, c: usize) -> f32 {
    let mut z = ((l * 131 + v * 17 + t * 7 + c) as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z ^= z >> 29;
    z = z.wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z ^= z >> 32;
    0.3 * ((t % W) as f32 / W as f32) * (1.0 + l as f32 * 0.1) + 0.2 * (z % 1000) as f32 / 1000.0
}

fn max_err(ds: &DatasetViews, m: &CompressedBtf) -> f32 {
    let mut e = 0f32;
    for v in 0..ds.n_views() {
        for l in 0..ds.n_lights() {
            if let Some(orig) = ds.read_image(l, v).unwrap() {
                let rec = m.reconstruct(l, v).unwrap();
                for (a, b) in orig.iter().zip(&rec) {
                    assert!(b.is_finite());
                    e = e.max((a - b).abs());
                }
            }
        }
    }
    e
}

/// Compress, write, read back and wrap.
fn round_trip(ds: &DatasetViews, p: &Params, file: &Path) -> (CompressedBtf, EncodeInfo) {
    let (g, info) = compress(ds, p).unwrap();
    let bytes = g.write(file).unwrap();
    assert_eq!(bytes, std::fs::metadata(file).unwrap().len());
    let back = Gbtf::read(file).unwrap();
    assert_eq!(back, g);
    (CompressedBtf::new(back).unwrap(), info)
}

#[test]
fn rank3_is_reproduced_by_both_methods_with_c3() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    write_dataset(&dir, &[], rank3);
    let ds = DatasetViews::open(&dir).unwrap();
    assert_eq!((ds.n_lights(), ds.n_views(), ds.n_measured()), (5, 4, 20));
    // The data are exactly rank 3, not less: c = 2 must lose something.
    for method in [Method::Pvmf, Method::Pca] {
        let (m, info) = round_trip(&ds, &Params::new(method, 3), &tmp.path().join("a.gbtf"));
        assert_eq!(info.filled, 0);
        let e = max_err(&ds, &m);
        assert!(e < 1e-5, "{method:?}: max error {e}");
        let (m2, _) = round_trip(&ds, &Params::new(method, 2), &tmp.path().join("b.gbtf"));
        let e2 = max_err(&ds, &m2);
        assert!(e2 > 1e-3, "{method:?}: c = 2 max error {e2}");
        // Reconstruction by directions selects the same pair.
        assert_eq!(
            m.reconstruct_deg([30.0, 120.0], [45.0, 180.0]).unwrap(),
            m.reconstruct(2, 2).unwrap()
        );
        assert!(matches!(
            m.reconstruct_deg([31.0, 120.0], [45.0, 180.0]),
            Err(CompressError::NotMeasured { which: "light", .. })
        ));
    }
}

#[test]
fn error_decreases_with_components() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    write_dataset(&dir, &[], noisy);
    let ds = DatasetViews::open(&dir).unwrap();
    for method in [Method::Pvmf, Method::Pca] {
        let mut last = f64::INFINITY;
        for c in [1, 2, 4, 8, 12] {
            let (g, _) = compress(&ds, &Params::new(method, c)).unwrap();
            let ev = evaluate(&ds, &CompressedBtf::new(g).unwrap()).unwrap();
            let e = ev.stats.rmse_linear();
            assert_eq!(ev.images, 20);
            assert!(e < last * 0.999, "{method:?} c = {c}: rmse {e} not below {last}");
            last = e;
        }
        // PVMF with c = 15 = lights · 3 is lossless (up to f32).
        if method == Method::Pvmf {
            let (g, _) = compress(&ds, &Params::new(method, 15)).unwrap();
            assert!(max_err(&ds, &CompressedBtf::new(g).unwrap()) < 1e-5);
        }
    }
}

#[test]
fn rank_deficient_and_constant_inputs() {
    type Field = fn(usize, usize, usize, usize) -> f32;
    let cases: [(&str, Field); 3] = [
        ("rank 1", |l, v, t, c| {
            ((t % 4) as f32 / 4.0) * ((l + v + c) % 8) as f32 / 32.0
        }),
        ("constant", |_, _, _, _| 0.5),
        ("zero", |_, _, _, _| 0.0),
    ];
    for (name, f) in cases {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("ds");
        write_dataset(&dir, &[], f);
        let ds = DatasetViews::open(&dir).unwrap();
        // c above the rank, and (PVMF: 20 > 15 columns) above the matrix size.
        for method in [Method::Pvmf, Method::Pca] {
            for c in [1, 5, 20] {
                let (m, _) = round_trip(&ds, &Params::new(method, c), &tmp.path().join("x.gbtf"));
                let e = max_err(&ds, &m);
                assert!(e < 1e-5, "{name} {method:?} c = {c}: max error {e}");
            }
        }
    }
}

#[test]
fn pca_is_deterministic_for_a_fixed_seed() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    write_dataset(&dir, &[], noisy);
    let ds = DatasetViews::open(&dir).unwrap();
    let p = Params {
        seed: 7,
        power_iters: 0,
        oversample: 1,
        ..Params::new(Method::Pca, 4)
    };
    let a = compress(&ds, &p).unwrap().0.to_bytes().unwrap();
    let b = compress(&ds, &p).unwrap().0.to_bytes().unwrap();
    assert_eq!(a, b, "same seed, different files");
    // With no power iteration and little oversampling the sketch matters: another seed
    // gives other factors (so the seed is really used).
    let c = compress(&ds, &Params { seed: 8, ..p.clone() })
        .unwrap()
        .0
        .to_bytes()
        .unwrap();
    assert_ne!(a, c);
    let pv = Params::new(Method::Pvmf, 4);
    assert_eq!(
        compress(&ds, &pv).unwrap().0.to_bytes().unwrap(),
        compress(&ds, &pv).unwrap().0.to_bytes().unwrap()
    );
}

#[test]
fn container_corruption_is_detected() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    write_dataset(&dir, &[], rank3);
    let ds = DatasetViews::open(&dir).unwrap();
    let (g, _) = compress(&ds, &Params::new(Method::Pvmf, 2)).unwrap();
    let bytes = g.to_bytes().unwrap();
    let p = Path::new("f.gbtf");
    assert_eq!(Gbtf::from_bytes(&bytes, p).unwrap(), g);
    let err = |b: &[u8]| match Gbtf::from_bytes(b, p) {
        Err(CompressError::Corrupt { reason, .. }) => reason,
        other => panic!("expected Corrupt, got {other:?}"),
    };
    // Every truncation is refused.
    for cut in [0, 5, 12, 19, 30, bytes.len() / 2, bytes.len() - 1] {
        assert!(err(&bytes[..cut]).contains("truncated") || cut < 8, "cut at {cut}");
    }
    let mut b = bytes.clone();
    b[0] ^= 1;
    assert!(err(&b).contains("magic"));
    let mut b = bytes.clone();
    b[8] = 3;
    assert!(err(&b).contains("version 3"));
    let mut b = bytes.clone();
    b[25] ^= 0x20;
    assert!(err(&b).contains("header CRC"));
    // A flipped bit in the last block's data.
    let mut b = bytes.clone();
    let n = b.len();
    b[n - 10] ^= 0x01;
    let r = err(&b);
    assert!(r.contains("CRC mismatch") && r.contains("block v3"), "{r}");
    let mut b = bytes.clone();
    b.push(0);
    assert!(err(&b).contains("trailing"));
    // And through the file reader, the error names the file.
    let f = tmp.path().join("bad.gbtf");
    std::fs::write(&f, &bytes[..bytes.len() - 3]).unwrap();
    let msg = Gbtf::read(&f).unwrap_err().to_string();
    assert!(msg.contains("bad.gbtf") && msg.contains("truncated"), "{msg}");
}

#[test]
fn skipped_pairs_are_filled_from_the_nearest_light() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    // Light 1 (30°, 0°) of view 1 skipped; its nearest measured light is light 0 (0°, 0°)
    // at 30°, nearer than lights 2, 3 (≈ 52°) and 4 (≈ 67°).
    write_dataset(&dir, &[(1, 1), (4, 3)], noisy);
    let ds = DatasetViews::open(&dir).unwrap();
    assert_eq!(ds.n_measured(), 18);
    let vm = ds.view_matrix(1).unwrap();
    assert_eq!(vm.filled, vec![(1, 0)]);
    for t in 0..vm.rows {
        assert_eq!(
            vm.data[t * vm.cols + 3..t * vm.cols + 6],
            vm.data[t * vm.cols..t * vm.cols + 3]
        );
    }
    let (g, info) = compress(&ds, &Params::new(Method::Pvmf, 2)).unwrap();
    assert_eq!(info.filled, 2);
    assert_eq!(g.header.filled, vec![[1, 1], [4, 3]]);
    let (g, info) = compress(&ds, &Params::new(Method::Pca, 2)).unwrap();
    assert_eq!((info.filled, g.header.filled.len()), (2, 2));
    let ev = evaluate(&ds, &CompressedBtf::new(g).unwrap()).unwrap();
    assert_eq!(ev.images, 18, "filled pairs are not counted in the error");
}

#[test]
fn non_finite_input_is_rejected_naming_file_and_measurement() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    write_dataset(&dir, &[], rank3);
    let mut img = RgbImage::new(W, H);
    img.data[7] = f32::NAN;
    store::write_exr(&dir.join("images/00013.exr"), &img).unwrap();
    let ds = DatasetViews::open(&dir).unwrap();
    for method in [Method::Pvmf, Method::Pca] {
        let e = compress(&ds, &Params::new(method, 2)).unwrap_err();
        match &e {
            CompressError::NonFinite { index, texel, .. } => assert_eq!((*index, *texel), (13, 2)),
            other => panic!("{other:?}"),
        }
        let msg = e.to_string();
        assert!(msg.contains("00013.exr") && msg.contains("measurement 13"), "{msg}");
    }
}

/// An m × n matrix with known singular values 1 … 1e-7 (log-spaced) and generic singular
/// vectors: the large dynamic range of a view matrix (specular highlight against shadowed
/// texels). Returns the matrix and its singular values.
fn graded_matrix(m: usize, n: usize) -> (Mat<f64>, Vec<f64>) {
    let u = Mat::<f64>::from_fn(m, n, |i, j| {
        noisy(j % 5, j / 5, i, 0) as f64 - 0.2 + (i == j) as u8 as f64
    });
    let v = Mat::<f64>::from_fn(n, n, |i, j| noisy(i % 5, 3, j, 1) as f64 + (i == j) as u8 as f64);
    let qu = u.qr().compute_thin_Q();
    let qv = v.qr().compute_thin_Q();
    let sigma: Vec<f64> = (0..n).map(|k| 10f64.powf(-7.0 * k as f64 / (n - 1) as f64)).collect();
    let a = Mat::<f64>::from_fn(m, n, |i, j| (0..n).map(|k| qu[(i, k)] * sigma[k] * qv[(j, k)]).sum());
    (a, sigma)
}

/// f32 against f64 SVD on one view-sized matrix with a large dynamic range (singular
/// values 1 … 1e-7, as between a specular highlight and shadowed texels). The truncation
/// error of the f64 SVD is the optimal one (the dropped singular values); f32's floor is
/// ~1e-7 relative to σ₁, so it cannot resolve components below that. Printed with
/// `--nocapture`; the production code runs the SVD in f64.
#[test]
fn f32_versus_f64_svd_accuracy() {
    let (m, n) = (512, 45);
    let (a, sigma) = graded_matrix(m, n);
    let a32 = Mat::<f32>::from_fn(m, n, |i, j| a[(i, j)] as f32);
    let svd = a32.thin_svd().unwrap();
    let (u32m, s32, v32) = (svd.U(), svd.S().column_vector(), svd.V());
    for c in [4, 12, 24, 36, 42] {
        let optimal = sigma[c..].iter().map(|s| s * s).sum::<f64>().sqrt();
        let (us, vv) = linalg::truncated_svd(a.as_ref(), c).unwrap();
        let e64 = (&a - &us * vv.transpose()).norm_l2();
        let r32 = Mat::<f64>::from_fn(m, n, |i, j| {
            (0..c)
                .map(|k| u32m[(i, k)] as f64 * s32[k] as f64 * v32[(j, k)] as f64)
                .sum()
        });
        let e32 = (&a - &r32).norm_l2();
        println!(
            "rank-{c:2} truncation error: optimal {optimal:.3e}, f64 SVD {e64:.3e} ({:.4}×), f32 SVD {e32:.3e} ({:.2}×)",
            e64 / optimal,
            e32 / optimal
        );
        assert!(
            (e64 / optimal - 1.0).abs() < 1e-6,
            "c = {c}: f64 {e64} vs optimal {optimal}"
        );
        if c == 42 {
            // Below ~1e-6 of σ₁ the f32 SVD is dominated by its own rounding.
            assert!(e32 > 5.0 * optimal, "c = {c}: f32 {e32} vs optimal {optimal}");
        }
        if c == 4 {
            assert!(e32 < 1.01 * optimal, "c = {c}: f32 {e32} vs optimal {optimal}");
        }
    }
}

#[test]
fn error_stats_are_on_the_8bit_srgb_scale() {
    let mut s = ErrorStats::default();
    // linear 1.0 → code 255, 0.0 → 0, 0.214 → sRGB ≈ 0.498 → code 127; 2.0 clamps to 255.
    s.add(&[0.0, 1.0, 0.214, 2.0], &[0.0, 0.0, 0.0, 1.0]);
    assert_eq!(s.values, 4);
    assert_eq!(store::linear_to_srgb8(0.214), 127);
    let d = [0.0, 1.0, 127.0 / 255.0, 0.0];
    let mae = d.iter().sum::<f64>() / 4.0;
    let rmse = (d.iter().map(|x| x * x).sum::<f64>() / 4.0).sqrt();
    assert!((s.mean_abs_8bit() - mae).abs() < 1e-12, "{}", s.mean_abs_8bit());
    assert!((s.rmse_8bit() - rmse).abs() < 1e-12);
    assert_eq!(s.max_8bit, 1.0);
    assert!((s.psnr_8bit() + 20.0 * rmse.log10()).abs() < 1e-9);
    let lin = ((1.0f64 + 0.214f32 as f64 * 0.214f32 as f64 + 1.0) / 4.0).sqrt();
    assert!((s.rmse_linear() - lin).abs() < 1e-7);
    assert!(peak_memory_bytes().unwrap() > 1 << 20);
}

/// f32 against f64 SVD on a real view matrix: `GONIO_COMPRESS_DATASET=DIR cargo test
/// --release -p gonio --lib compress::tests::f32_versus_f64_on_a_dataset -- --ignored
/// --nocapture`. Prints the rank-c Frobenius error of both, relative to ‖A‖.
#[test]
#[ignore = "needs a dataset: set GONIO_COMPRESS_DATASET"]
fn f32_versus_f64_on_a_dataset() {
    let dir = std::env::var("GONIO_COMPRESS_DATASET").expect("GONIO_COMPRESS_DATASET");
    let ds = DatasetViews::open(Path::new(&dir)).unwrap();
    for view in [0, ds.n_views() / 2, ds.n_views() - 1] {
        let vm = ds.view_matrix(view).unwrap();
        let a = Mat::<f64>::from_fn(vm.rows, vm.cols, |i, j| vm.data[i * vm.cols + j] as f64);
        let a32 = Mat::<f32>::from_fn(vm.rows, vm.cols, |i, j| vm.data[i * vm.cols + j]);
        let norm = a.norm_l2();
        let svd = a32.thin_svd().unwrap();
        let (u, s, v) = (svd.U(), svd.S().column_vector(), svd.V());
        for c in [2, 4, 9, 15, 30] {
            let (us, vv) = linalg::truncated_svd(a.as_ref(), c).unwrap();
            let e64 = (&a - &us * vv.transpose()).norm_l2() / norm;
            let r32 = Mat::<f64>::from_fn(vm.rows, vm.cols, |i, j| {
                (0..c).map(|k| u[(i, k)] as f64 * s[k] as f64 * v[(j, k)] as f64).sum()
            });
            let e32 = (&a - &r32).norm_l2() / norm;
            println!(
                "view {view:2} c = {c:2}: relative error f64 {e64:.6e}, f32 {e32:.6e}, ratio {:.6}",
                e32 / e64
            );
            assert!(e64 <= e32 * (1.0 + 1e-3));
        }
    }
}

/// The Gram path of PVMF (`linalg::gram_truncated`: f64 `AᵀA`, its eigen-decomposition,
/// `U·S = A·V`) against the QR + SVD path on a view-sized matrix with singular values
/// 1 … 1e-7: where it accepts `c` its rank-`c` error equals the optimal one, where the
/// Gram matrix is too ill-conditioned for `c` it declines (and PVMF falls back). The same
/// in f32 shows why the Gram step stays in f64: squaring the spectrum puts σ below
/// ~1e-3 · σ₁ into f32's rounding (printed: 1.06× the optimal error at c = 24, 1.36× at
/// c = 26, 32× at c = 36, where f64 is at 1.000000×).
#[test]
fn gram_path_matches_the_svd_path() {
    let (m, n) = (2048, 45);
    let (a, sigma) = graded_matrix(m, n);
    let a32 = Mat::<f32>::from_fn(m, n, |i, j| a[(i, j)] as f32);
    let g32 = a32.transpose() * &a32;
    let eig32 = g32.self_adjoint_eigen(faer::Side::Lower).unwrap();
    for c in [1, 4, 12, 24, 26, 27, 36, 42] {
        let optimal = sigma[c..].iter().map(|s| s * s).sum::<f64>().sqrt();
        let (us, vv) = linalg::truncated_svd(a.as_ref(), c).unwrap();
        let e_svd = (&a - &us * vv.transpose()).norm_l2();
        // λ_c / λ_1 = σ_{c-1}² (0-based σ) against the documented threshold.
        let accept = sigma[c - 1] * sigma[c - 1] >= linalg::GRAM_MIN_EIGEN_RATIO;
        let gram = linalg::gram_truncated(a.as_ref(), c).unwrap();
        assert_eq!(gram.is_some(), accept, "c = {c}: σ_c = {:.2e}", sigma[c - 1]);
        let v32 = Mat::<f64>::from_fn(n, c, |i, j| eig32.U()[(i, n - 1 - j)] as f64);
        let e_g32 = (&a - &a * &v32 * v32.transpose()).norm_l2();
        match gram {
            Some((usg, vg)) => {
                let e_gram = (&a - &usg * vg.transpose()).norm_l2();
                println!(
                    "c = {c:2}: optimal {optimal:.3e}, QR+SVD {:.6}×, Gram f64 {:.6}×, Gram f32 {:.2}×",
                    e_svd / optimal,
                    e_gram / optimal,
                    e_g32 / optimal
                );
                assert!(
                    (e_gram / e_svd - 1.0).abs() < 1e-6,
                    "c = {c}: Gram {e_gram:.6e} vs SVD {e_svd:.6e}"
                );
                if c == 26 {
                    // Measured 1.36×: f32 rounding of the squared spectrum tilts the subspace.
                    assert!(e_g32 > 1.2 * optimal, "c = {c}: f32 Gram {e_g32:.3e} vs {optimal:.3e}");
                }
            }
            None => println!(
                "c = {c:2}: optimal {optimal:.3e}, Gram declined (fallback to QR + SVD); Gram f32 would give {:.2}×",
                e_g32 / optimal
            ),
        }
    }
}

/// PVMF reports which path factorized each view: the Gram path on full-rank data, the
/// QR + SVD fallback on a constant dataset (λ₂ = 0, so any c > 1 is ill-conditioned),
/// with the same exact round trip.
#[test]
fn pvmf_falls_back_to_the_svd_on_ill_conditioned_views() {
    let stage = |info: &EncodeInfo, name: &str| info.stages.iter().find(|s| s.name == name).map(|s| s.value);
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("noisy");
    write_dataset(&dir, &[], noisy);
    let ds = DatasetViews::open(&dir).unwrap();
    let (_, info) = round_trip(&ds, &Params::new(Method::Pvmf, 3), &tmp.path().join("a.gbtf"));
    assert_eq!(stage(&info, "gram_path"), Some(4.0));
    assert_eq!(stage(&info, "svd_path"), Some(0.0));
    let dir = tmp.path().join("const");
    write_dataset(&dir, &[], |_, _, _, _| 0.5);
    let ds = DatasetViews::open(&dir).unwrap();
    let (m, info) = round_trip(&ds, &Params::new(Method::Pvmf, 3), &tmp.path().join("b.gbtf"));
    assert_eq!(stage(&info, "gram_path"), Some(0.0));
    assert_eq!(stage(&info, "svd_path"), Some(4.0));
    assert!(max_err(&ds, &m) < 1e-6);
}

/// The planes/columns readers PVMF uses give the same values as `read_image` and
/// `view_matrix` (including filled pairs).
#[test]
fn planes_match_read_image() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    write_dataset(&dir, &[(1, 2), (4, 0)], noisy);
    let ds = DatasetViews::open(&dir).unwrap();
    for v in 0..ds.n_views() {
        for l in 0..ds.n_lights() {
            let img = ds.read_image(l, v).unwrap();
            let planes = ds.read_planes(l, v).unwrap();
            assert_eq!(img.is_some(), planes.is_some());
            if let (Some(img), Some(p)) = (img, planes) {
                for t in 0..ds.texels() {
                    for c in 0..3 {
                        assert_eq!(img[t * 3 + c], p[c][t], "light {l} view {v} texel {t} channel {c}");
                    }
                }
            }
        }
        let vm = ds.view_matrix(v).unwrap();
        let (m, filled) = ds.view_columns(v).unwrap();
        assert_eq!(vm.filled, filled);
        assert_eq!((m.nrows(), m.ncols()), (vm.rows, vm.cols));
        for i in 0..vm.rows {
            for j in 0..vm.cols {
                assert_eq!(m[(i, j)], vm.data[i * vm.cols + j] as f64, "view {v} ({i}, {j})");
            }
        }
    }
}

/// Gram path against the QR + SVD path on real view matrices: `GONIO_COMPRESS_DATASET=DIR
/// cargo test -p gonio --lib compress::tests::gram_versus_svd_on_a_dataset -- --ignored
/// --nocapture`. Prints the rank-c errors relative to ‖A‖ and their ratio.
#[test]
#[ignore = "needs a dataset: set GONIO_COMPRESS_DATASET"]
fn gram_versus_svd_on_a_dataset() {
    let dir = std::env::var("GONIO_COMPRESS_DATASET").expect("GONIO_COMPRESS_DATASET");
    let ds = DatasetViews::open(Path::new(&dir)).unwrap();
    for view in [0, ds.n_views() / 2, ds.n_views() - 1] {
        let (a, _) = ds.view_columns(view).unwrap();
        let norm = a.norm_l2();
        for c in [2, 4, 8, 15, 30] {
            let (us, vv) = linalg::truncated_svd(a.as_ref(), c).unwrap();
            let e_svd = (&a - &us * vv.transpose()).norm_l2() / norm;
            match linalg::gram_truncated(a.as_ref(), c).unwrap() {
                Some((usg, vg)) => {
                    let e_gram = (&a - &usg * vg.transpose()).norm_l2() / norm;
                    println!(
                        "view {view:2} c = {c:2}: relative error QR+SVD {e_svd:.6e}, Gram {e_gram:.6e}, ratio {:.8}",
                        e_gram / e_svd
                    );
                    assert!(e_gram <= e_svd * (1.0 + 1e-6));
                }
                None => println!("view {view:2} c = {c:2}: QR+SVD {e_svd:.6e}, Gram declined"),
            }
        }
    }
}

/// Decode cost of `read_image` (store's per-pixel decoder) against `read_planes` (flat
/// channel buffers): `GONIO_COMPRESS_DATASET=DIR cargo test -p gonio --lib
/// compress::tests::decode_cost_on_a_dataset -- --ignored --nocapture`. Prints only.
#[test]
#[ignore = "needs a dataset: set GONIO_COMPRESS_DATASET"]
fn decode_cost_on_a_dataset() {
    let dir = std::env::var("GONIO_COMPRESS_DATASET").expect("GONIO_COMPRESS_DATASET");
    let ds = DatasetViews::open(Path::new(&dir)).unwrap();
    let n = 81.min(ds.n_lights());
    for round in 0..2 {
        let t0 = std::time::Instant::now();
        for l in 0..n {
            std::hint::black_box(ds.read_image(l, 40 % ds.n_views()).unwrap());
        }
        let a = t0.elapsed().as_secs_f64() / n as f64;
        let t0 = std::time::Instant::now();
        for l in 0..n {
            std::hint::black_box(ds.read_planes(l, 40 % ds.n_views()).unwrap());
        }
        let b = t0.elapsed().as_secs_f64() / n as f64;
        println!(
            "round {round}: read_image {:.3} ms, read_planes {:.3} ms per image",
            a * 1e3,
            b * 1e3
        );
    }
}

/// PVMF's row-chunked Gram product (`linalg::gram_by_row_chunks`) against faer's plain
/// `AᵀA` on a matrix that is not a multiple of the chunk size (so the last chunk is
/// short), and bit-for-bit the same result with one thread and with four: the chunks and
/// their summation order do not depend on the thread count, so a fixed input gives the
/// same factors on any machine.
#[test]
fn chunked_gram_equals_the_plain_product_and_is_thread_count_independent() {
    let (m, n) = (9000, 21);
    let (a, _) = graded_matrix(m, n);
    let plain = a.transpose() * &a;
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| linalg::gram_by_row_chunks(a.as_ref()))
    };
    let (g1, g4) = (run(1), run(4));
    let scale = plain.norm_max();
    for j in 0..n {
        for i in 0..n {
            if i >= j {
                assert!(
                    (g1[(i, j)] - plain[(i, j)]).abs() <= 1e-12 * scale,
                    "({i}, {j}): chunked {} vs plain {}",
                    g1[(i, j)],
                    plain[(i, j)]
                );
                assert_eq!(
                    g1[(i, j)].to_bits(),
                    g4[(i, j)].to_bits(),
                    "({i}, {j}) differs by thread count"
                );
            } else {
                assert_eq!(g1[(i, j)], 0.0, "upper triangle ({i}, {j}) must stay zero");
            }
        }
    }
}

/// The one Gaussian sketch generator gives, bit for bit, the numbers of the copies it
/// replaced (PCA's and DFMF's, which were identical, and local PCA's variant), so files
/// written before and after the split are the same bytes. The old copies are written out
/// here as they were.
#[test]
fn gaussian_sketch_reproduces_the_replaced_generators() {
    use linalg::{GaussianSketch, SketchKeying};
    fn old_hashed(seed: u64, row: usize, col: usize) -> f64 {
        let mix = |k: u64| {
            let mut z = k.wrapping_add(0x9e37_79b9_7f4a_7c15);
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        };
        let k = mix(seed ^ mix(((row as u64) << 20) ^ col as u64));
        let u1 = ((k >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
        let u2 = ((mix(k) >> 11) as f64) / (1u64 << 53) as f64;
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
    fn old_stream(seed: u64, row: usize, col: usize) -> f64 {
        let mut s = seed ^ ((row as u64) << 24) ^ (col as u64).wrapping_mul(0x2545_f491_4f6c_dd1d);
        let (a, b) = (linalg::splitmix(&mut s), linalg::splitmix(&mut s));
        let u1 = ((a >> 11) as f64 + 0.5) / (1u64 << 53) as f64;
        let u2 = (b >> 11) as f64 / (1u64 << 53) as f64;
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
    let (mut sum, mut sq, mut n) = (0.0, 0.0, 0.0);
    for seed in [0u64, 1, 2, 7, 0x6c6f_6361_6c70_6361, u64::MAX] {
        let (h, s) = (
            GaussianSketch::new(seed, SketchKeying::Hashed),
            GaussianSketch::new(seed, SketchKeying::Stream),
        );
        for row in (0..20_000).step_by(97) {
            for col in 0..40 {
                assert_eq!(h.at(row, col).to_bits(), old_hashed(seed, row, col).to_bits());
                assert_eq!(s.at(row, col).to_bits(), old_stream(seed, row, col).to_bits());
                for x in [h.at(row, col), s.at(row, col)] {
                    assert!(x.is_finite());
                    sum += x;
                    sq += x * x;
                    n += 1.0;
                }
            }
        }
        let b = h.block(300, 5, 4);
        assert_eq!(b[(2, 3)].to_bits(), h.at(302, 3).to_bits());
    }
    // Standard normal: mean ≈ 0, variance ≈ 1 over ~2.5e5 draws.
    let (mean, var) = (sum / n, sq / n - (sum / n).powi(2));
    assert!(
        mean.abs() < 0.01 && (var - 1.0).abs() < 0.02,
        "mean {mean}, variance {var}"
    );
}

/// The layering rule of the compress folder: a method file imports only the ground floor
/// (`params`, `linalg`, `abrdf`, `data`, `container`, `error`; DFMF also its own `.btf`
/// container), the ground floor imports no method file, and only `factor.rs` and
/// `interp.rs` name method files. Reads the sources (code before the first `#[cfg(test)]`;
/// comment lines skipped) and lists every `super::x` / `crate::compress::x` it finds.
#[test]
fn method_files_import_only_the_ground_floor() {
    const GROUND: &[&str] = &["params", "linalg", "abrdf", "data", "container", "error", "rsvd"];
    let files: &[(&str, &str, &[&str])] = &[
        ("pca", include_str!("pca.rs"), GROUND),
        ("pvmf", include_str!("pvmf.rs"), GROUND),
        ("local_pca", include_str!("local_pca.rs"), GROUND),
        (
            "local_pca/passes",
            include_str!("local_pca/passes.rs"),
            &["abrdf", "error", "exact", "linalg", "rsvd", "local_pca"],
        ),
        ("median_cut", include_str!("median_cut.rs"), GROUND),
        ("homomorphic", include_str!("homomorphic.rs"), GROUND),
        ("dfmf", include_str!("dfmf.rs"), GROUND),
        ("nd", include_str!("nd.rs"), GROUND),
        ("svd_j", include_str!("svd_j.rs"), GROUND),
        ("cmf", include_str!("cmf.rs"), GROUND),
        ("svbrdf", include_str!("svbrdf.rs"), GROUND),
        // the glTF SVBRDF shares the SVBRDF's texel geometry (`svbrdf::Geometry`)
        (
            "gltf",
            include_str!("gltf.rs"),
            &[
                "params",
                "linalg",
                "abrdf",
                "data",
                "container",
                "error",
                "rsvd",
                "svbrdf",
            ],
        ),
        ("params", include_str!("params.rs"), &["data", "container", "error"]),
        ("linalg", include_str!("linalg.rs"), &["error"]),
        ("exact", include_str!("exact.rs"), &["error", "linalg"]),
        ("rsvd", include_str!("rsvd.rs"), &["error", "exact", "linalg"]),
        (
            "abrdf",
            include_str!("abrdf.rs"),
            &["params", "data", "container", "error"],
        ),
        ("error", include_str!("error.rs"), &[]),
        ("data", include_str!("data.rs"), &["error"]),
        ("container", include_str!("container.rs"), &["codec", "error"]),
        ("codec", include_str!("codec.rs"), &[]),
        ("btf_ubo2014", include_str!("btf_ubo2014.rs"), &["dfmf", "error"]),
    ];
    let mut bad = Vec::new();
    for (name, src, allowed) in files {
        let code = src.split("#[cfg(test)]").next().unwrap_or("");
        for line in code.lines().filter(|l| !l.trim_start().starts_with("//")) {
            for prefix in ["super::", "crate::compress::"] {
                for (at, _) in line.match_indices(prefix) {
                    let rest = &line[at + prefix.len()..];
                    let names: Vec<&str> = if let Some(group) = rest.strip_prefix('{') {
                        group.split('}').next().unwrap_or("").split(',').collect()
                    } else {
                        vec![rest]
                    };
                    for n in names {
                        let id: String = n
                            .trim()
                            .chars()
                            .take_while(|c| c.is_alphanumeric() || *c == '_')
                            .collect();
                        if !allowed.contains(&id.as_str()) {
                            bad.push(format!("{name}.rs imports `{id}`: {}", line.trim()));
                        }
                    }
                }
            }
        }
    }
    assert!(
        bad.is_empty(),
        "imports across the compress floors:\n{}",
        bad.join("\n")
    );
}

/// Write `g` quantized at `bits`, read it back (version 2) and wrap it.
fn quantized_round_trip(g: &Gbtf, bits: u32, file: &Path) -> CompressedBtf {
    let mut q = g.clone();
    q.quantize(bits).unwrap();
    q.write(file).unwrap();
    let bytes = std::fs::read(file).unwrap();
    assert_eq!(
        u32::from_le_bytes(bytes[8..12].try_into().unwrap()),
        container::VERSION_CODED
    );
    let back = Gbtf::read(file).unwrap();
    assert_eq!(back.header.blocks, q.header.blocks);
    CompressedBtf::new(back).unwrap()
}

/// Every `.gbtf` method decodes a quantized file (reconstruction and interpolation) to
/// within its quantization error of the f32 file, index blocks exactly; 12 bits is
/// closer than 8. Plain files are still version 1.
#[test]
fn quantized_files_decode_for_every_method() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    write_dataset(&dir, &[], noisy);
    let ds = DatasetViews::open(&dir).unwrap();
    let methods = [
        Params::new(Method::Pvmf, 3),
        Params::new(Method::Pca, 4),
        Params::new(
            Method::LocalPca {
                clusters: 3,
                iters: 5,
                subspace: 0,
                in_passes: false,
            },
            2,
        ),
        Params::new(
            Method::MedianCut {
                boxes: 5,
                balanced: false,
                min_error_cut: false,
            },
            1,
        ),
        Params::new(
            Method::Homomorphic {
                half_bins: 4,
                sweeps: 5,
            },
            1,
        ),
        Params::new(Method::Nd, 1),
        Params::new(Method::SvdJ, 2),
        Params::new(
            Method::Gshd {
                theta_bins: 4,
                sweeps: 5,
            },
            1,
        ),
        Params::new(
            Method::Cmf {
                theta_bins: 4,
                sweeps: 5,
            },
            2,
        ),
    ];
    for p in &methods {
        let name = p.method.name();
        let (g, _) = compress(&ds, p).unwrap();
        let plain_file = tmp.path().join(format!("{name}.gbtf"));
        g.write(&plain_file).unwrap();
        let plain_bytes = std::fs::read(&plain_file).unwrap();
        assert_eq!(
            u32::from_le_bytes(plain_bytes[8..12].try_into().unwrap()),
            container::VERSION
        );
        let exact = CompressedBtf::new(g.clone()).unwrap();
        let mut last = f32::INFINITY;
        for bits in [8, 12] {
            let file = tmp.path().join(format!("{name}-{bits}.gbtf"));
            let q = quantized_round_trip(&g, bits, &file);
            assert!(
                std::fs::metadata(&file).unwrap().len() < plain_bytes.len() as u64,
                "{name}: not smaller"
            );
            for (info, b) in q.gbtf.header.blocks.iter().zip(&q.gbtf.blocks) {
                if info.codec == Some(codec::BlockCodec::Integer) {
                    let i = g.header.blocks.iter().position(|x| x.name == info.name).unwrap();
                    assert_eq!(b, &g.blocks[i], "{name}: index block {} must be exact", info.name);
                }
            }
            let mut e = 0f32;
            for v in 0..ds.n_views() {
                for l in 0..ds.n_lights() {
                    let (a, b) = (exact.reconstruct(l, v).unwrap(), q.reconstruct(l, v).unwrap());
                    for (x, y) in a.iter().zip(&b) {
                        assert!(y.is_finite(), "{name} {bits} bits: non-finite");
                        e = e.max((x - y).abs());
                    }
                }
            }
            // Values here are ≤ ~1: a few quantization steps of a unit-range factor.
            let tol = if bits == 8 { 0.08 } else { 0.006 };
            assert!(e < tol, "{name} {bits} bits: max deviation {e} from the f32 file");
            assert!(e <= last, "{name}: {bits} bits worse than fewer bits");
            last = e;
            let (img, _) = interp::reconstruct_at(&q, [20.0, 40.0], [30.0, 100.0]).unwrap();
            assert!(img.iter().all(|x| x.is_finite()));
        }
    }
}

/// The degenerate inputs of the stability tests: all zero, constant 0.375, rank 3.
fn degenerate_datasets(dir: &std::path::Path) -> Vec<DatasetViews> {
    [
        (|_, _, _, _| 0.0) as fn(usize, usize, usize, usize) -> f32,
        |_, _, _, _| 0.375,
        rank3,
    ]
    .into_iter()
    .enumerate()
    .map(|(i, f)| {
        let ds = dir.join(format!("ds{i}"));
        write_dataset(&ds, &[], f);
        DatasetViews::open(&ds).unwrap()
    })
    .collect()
}

/// Quantization never turns a constant, zero or rank-deficient input into NaN: the
/// unused components are zero columns, which decode exactly.
#[test]
fn quantizing_constant_and_rank_deficient_inputs_stays_finite() {
    let tmp = tempfile::tempdir().unwrap();
    for (i, ds) in degenerate_datasets(tmp.path()).into_iter().enumerate() {
        for method in [Method::Pvmf, Method::Pca] {
            let (g, _) = compress(&ds, &Params::new(method, 6)).unwrap();
            let q = quantized_round_trip(&g, 8, &tmp.path().join(format!("q{i}.gbtf")));
            assert!(q.gbtf.blocks.iter().flatten().all(|v| v.is_finite()));
            let e = max_err(&ds, &q);
            // Constant inputs are exact up to f32; rank 3 within 8-bit steps.
            let tol = if i < 2 { 1e-6 } else { 0.02 };
            assert!(e <= tol, "dataset {i} {method:?}: max error {e}");
        }
        // The per-ABRDF factorizations: ND (a constant ABRDF is a product, exact) and
        // SVD-J at J = 4 = the full rank of the 5 × 4 ABRDF matrices (exact on all three;
        // on the zero and constant inputs most terms are zero columns).
        // GSHD: a constant is one product (exact); CMF at K = 4 adds the full-rank residual.
        let gshd = Method::Gshd {
            theta_bins: 4,
            sweeps: 5,
        };
        let cmf = Method::Cmf {
            theta_bins: 4,
            sweeps: 5,
        };
        for p in [
            Params::new(Method::Nd, 1),
            Params::new(Method::SvdJ, 4),
            Params::new(gshd, 1),
            Params::new(cmf, 4),
        ] {
            let (g, _) = compress(&ds, &p).unwrap();
            let exact = CompressedBtf::new(g.clone()).unwrap();
            let q = quantized_round_trip(&g, 8, &tmp.path().join(format!("q{i}.gbtf")));
            assert!(q.gbtf.blocks.iter().flatten().all(|v| v.is_finite()));
            let e = max_err(&ds, &q);
            let name = p.method.name();
            if i < 2 {
                assert!(e <= 1e-6, "dataset {i} {name}: max error {e}");
            } else {
                // Rank 3: within 8-bit steps of the f32 file (SVD-J: of the input).
                let d = max_err(&ds, &exact);
                assert!(e <= d + 0.03, "dataset {i} {name}: {e} against the f32 file's {d}");
            }
        }
    }
}

/// Version 1 may not carry coded blocks; a damaged coded block is reported by name.
#[test]
fn coded_block_corruption_is_detected() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    write_dataset(&dir, &[], noisy);
    let ds = DatasetViews::open(&dir).unwrap();
    let (mut g, _) = compress(&ds, &Params::new(Method::Pca, 3)).unwrap();
    g.quantize(10).unwrap();
    let mut bytes = g.to_bytes().unwrap();
    let p = Path::new("q.gbtf");
    assert!(Gbtf::from_bytes(&bytes, p).is_ok());
    let mut v1 = bytes.clone();
    v1[8..12].copy_from_slice(&container::VERSION.to_le_bytes());
    let e = Gbtf::from_bytes(&v1, p).unwrap_err().to_string();
    assert!(e.contains("version 1"), "{e}");
    let n = bytes.len();
    bytes[n - 10] ^= 0x40;
    let e = Gbtf::from_bytes(&bytes, p).unwrap_err().to_string();
    assert!(e.contains("block v") && e.contains("CRC"), "{e}");
    assert!(g.clone().quantize(0).is_err() && g.quantize(17).is_err());
}

/// CIELab there and back: the identity on linear RGB (negative values clamp to 0 on the
/// way back, values above 1 stay), greys have a* = b* = 0, and nothing becomes NaN.
#[test]
fn lab_round_trip_is_the_identity_and_finite() {
    let dec = dfmf::LabDecoder::default();
    let vals = [0.0, 1e-6, 0.002, 0.0088, 0.05, 0.2, 0.5, 0.9, 1.0, 3.5];
    for &r in &vals {
        for &g in &vals {
            for &b in &vals {
                let lab = dfmf::rgb_to_lab([r, g, b]);
                assert!(lab.iter().all(|v| v.is_finite()));
                let back = dec.to_rgb(lab.map(|v| v as f32));
                for (x, y) in [r, g, b].iter().zip(back) {
                    assert!(
                        (*x as f32 - y).abs() <= 2e-5 * (1.0 + *x as f32),
                        "{r},{g},{b} → {back:?}"
                    );
                }
            }
        }
        let grey = dfmf::rgb_to_lab([r, r, r]);
        assert!(grey[1].abs() < 1e-9 && grey[2].abs() < 1e-9, "{grey:?}");
    }
    let neg = dec.to_rgb(dfmf::rgb_to_lab([-0.01, 0.5, 0.2]).map(|v| v as f32));
    assert!(neg[0] == 0.0 && (neg[1] - 0.5).abs() < 1e-3, "{neg:?}");
    for lab in [[f32::MAX, 0.0, 0.0], [-1e30, 1e30, -1e30], [0.0; 3]] {
        assert!(dec.to_rgb(lab).iter().all(|v| !v.is_nan()), "{lab:?}");
    }
}

fn dfmf_params(model: dfmf::ColorModel, c: usize, cc: usize) -> Params {
    Params::new(
        Method::Dfmf {
            color_model: model,
            chroma_components: cc,
        },
        c,
    )
}

/// DFMF stored as `.gbtf` (every colour model): the file reads back to the same factors,
/// full rank reproduces the data, quantized files decode to finite images close to the
/// f32 ones, and CIELab refuses the UBO2014 `.btf` container with a reason.
#[test]
fn dfmf_gbtf_round_trips_in_every_colour_model() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("ds");
    write_dataset(&dir, &[], noisy);
    let ds = DatasetViews::open(&dir).unwrap();
    let full = lights().len() * views().len();
    for model in [dfmf::ColorModel::Lab, dfmf::ColorModel::LogYuv, dfmf::ColorModel::Rgb] {
        let (m, info) = round_trip(&ds, &dfmf_params(model, full, full), &tmp.path().join("f.gbtf"));
        assert_eq!((info.passes, m.method().name()), (1, "dfmf"));
        let e = max_err(&ds, &m);
        assert!(e < 2e-3, "{model:?} at full rank: max error {e}");
        let (g, _) = compress(&ds, &dfmf_params(model, 4, 2)).unwrap();
        let f32_err = max_err(&ds, &CompressedBtf::new(g.clone()).unwrap());
        let q = quantized_round_trip(&g, 10, &tmp.path().join("q.gbtf"));
        let q_err = max_err(&ds, &q);
        assert!(q_err <= f32_err + 0.02, "{model:?}: 10 bits {q_err} vs f32 {f32_err}");
    }
    let (d, _) = dfmf::encode(&ds, &dfmf::DfmfParams::new(dfmf::ColorModel::Lab, 2)).unwrap();
    let e = btf_ubo2014::to_bytes(&d, btf_ubo2014::Precision::F32, "")
        .unwrap_err()
        .to_string();
    assert!(e.contains("gonio's own") && e.contains("gbtf"), "{e}");
}

/// The quantized perceptual DFMF of constant and rank-deficient inputs (c above the rank,
/// so whole factor columns are zero): finite, constants exact to the Lab round trip.
#[test]
fn quantized_dfmf_of_constant_and_rank_deficient_inputs_stays_finite() {
    let tmp = tempfile::tempdir().unwrap();
    for (i, ds) in degenerate_datasets(tmp.path()).into_iter().enumerate() {
        for model in [dfmf::ColorModel::Lab, dfmf::ColorModel::LogYuv] {
            let (g, _) = compress(&ds, &dfmf_params(model, 6, 6)).unwrap();
            for bits in [6, 8] {
                let q = quantized_round_trip(&g, bits, &tmp.path().join(format!("q{i}.gbtf")));
                assert!(q.gbtf.blocks.iter().flatten().all(|v| v.is_finite()));
                let e = max_err(&ds, &q);
                // Rank 3 in linear RGB is not low rank in Lab; the bound is 6 bits' worth.
                let tol = if i < 2 { 1e-4 } else { 0.05 };
                assert!(e <= tol, "dataset {i} {model:?} {bits} bits: max error {e}");
            }
        }
    }
}

/// f32 against f64 for the perceptual DFMF's factorization, on the L*, a* and b* channel
/// matrices of real views: `GONIO_COMPRESS_DATASET=DIR cargo test --release -p gonio --lib
/// compress::tests::lab_f32_versus_f64_on_a_dataset -- --ignored --nocapture`.
#[test]
#[ignore = "needs a dataset: set GONIO_COMPRESS_DATASET"]
fn lab_f32_versus_f64_on_a_dataset() {
    let dir = std::env::var("GONIO_COMPRESS_DATASET").expect("GONIO_COMPRESS_DATASET");
    let ds = DatasetViews::open(Path::new(&dir)).unwrap();
    for view in [0, ds.n_views() / 2, ds.n_views() - 1] {
        let vm = ds.view_matrix(view).unwrap();
        let nl = ds.n_lights();
        let lab: Vec<[f64; 3]> = vm
            .data
            .chunks_exact(3)
            .map(|p| dfmf::rgb_to_lab([p[0] as f64, p[1] as f64, p[2] as f64]))
            .collect();
        for (ch, name) in ["L*", "a*", "b*"].iter().enumerate() {
            let a = Mat::<f64>::from_fn(vm.rows, nl, |i, j| lab[i * nl + j][ch]);
            let a32 = Mat::<f32>::from_fn(vm.rows, nl, |i, j| lab[i * nl + j][ch] as f32);
            let norm = a.norm_l2();
            let svd = a32.thin_svd().unwrap();
            let (u, s, v) = (svd.U(), svd.S().column_vector(), svd.V());
            for c in [2, 4, 9, 16, 32] {
                let (us, vv) = linalg::truncated_svd(a.as_ref(), c).unwrap();
                let e64 = (&a - &us * vv.transpose()).norm_l2() / norm;
                let r32 = Mat::<f64>::from_fn(vm.rows, nl, |i, j| {
                    (0..c).map(|k| u[(i, k)] as f64 * s[k] as f64 * v[(j, k)] as f64).sum()
                });
                let e32 = (&a - &r32).norm_l2() / norm;
                println!(
                    "view {view:2} {name} c = {c:2}: σ_c/σ_1 {:.2e}, relative error f64 {e64:.6e}, f32 {e32:.6e}, ratio {:.6}",
                    s[c.min(s.nrows() - 1)] / s[0],
                    e32 / e64
                );
                assert!(e64 <= e32 * (1.0 + 1e-3));
            }
        }
    }
}

/// A deterministic value in [0, 1) for the f32-versus-f64 matrices below.
fn unit_hash(a: usize, b: usize) -> f64 {
    let mut z = ((a as u64) << 32 ^ b as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    z ^= z >> 29;
    z = z.wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z ^= z >> 32;
    (z % 1_000_003) as f64 / 1_000_003.0
}

/// f32 against f64 for GSHD and CMF (`compress::cmf`) on one 81 × 81 Bonn ABRDF channel
/// (8 half/difference θ bins). The f64 side is the production code (`cmf::fit_channel`);
/// the f32 side is the same alternating least squares in f32 (`cmf::fit_link::<f32>`),
/// the residual `M / F` in f32 and faer's f32 SVD. Errors are ‖M − M̂‖ / ‖M‖ in f64, on
/// inputs rounded to f32 first (the production input is f32). Prints the table of
/// docs/guide/compression.md with `--nocapture`.
///
/// - GSHD on `M = G(h) · E(d) · (1 + ε n(l, v))`: how close to a product the data is (ε)
///   and the highlight's dynamic range `R` (half vectors within 22.5° of the normal are `R`
///   times the rest).
/// - CMF on `M = G(h) E(d) · (1 + ε Σ_k q^k u_k(l) w_k(v))` with K = 4 residual terms: how
///   far from the link the data is (ε) and how fast the light × view terms fall (q).
#[test]
fn f32_versus_f64_gshd_and_cmf() {
    use super::cmf::{bins, fit_channel, fit_link, grid_bins};
    let dirs: Vec<[f64; 2]> = gonio_dataset::sweep::bonn81()
        .iter()
        .map(|d| [d.theta_deg(), d.phi_deg()])
        .collect();
    let (nl, nv, tb) = (dirs.len(), dirs.len(), 8);
    let pb = grid_bins(&dirs, &dirs, tb);
    let nb = bins(tb);
    let rel = |m: &[f32], rec: &dyn Fn(usize) -> f64| {
        let (mut num, mut den) = (0f64, 0f64);
        for (i, &x) in m.iter().enumerate() {
            num += (x as f64 - rec(i)).powi(2);
            den += (x as f64).powi(2);
        }
        (num / den).sqrt()
    };
    let product = |range: f64, i: usize| {
        let (h, d) = pb[i];
        let g = if h / (4 * tb as u32) == 0 {
            range
        } else {
            0.2 + unit_hash(h as usize, 1)
        };
        g * (0.3 + unit_hash(d as usize, 2))
    };
    // GSHD: (ε, R).
    let mut rows = Vec::new();
    for (eps, range) in [
        (1e-2, 1e1),
        (1e-4, 1e1),
        (1e-6, 1e1),
        (1e-8, 1e1),
        (1e-3, 1e3),
        (1e-3, 1e6),
        (1e-3, 1e12),
        (1e-3, 1e20),
    ] {
        let m: Vec<f32> = (0..nl * nv)
            .map(|i| (product(range, i) * (1.0 + eps * (unit_hash(i, 3) - 0.5))) as f32)
            .collect();
        let m64: Vec<f64> = m.iter().map(|x| *x as f64).collect();
        let (g, e, _) = fit_channel(&m64, &pb, nb, 200, (nl, nv, 0)).unwrap();
        assert!(
            g.iter().chain(&e).all(|x| x.is_finite()),
            "f64 GSHD not finite at R = {range:e}"
        );
        let e64 = rel(&m, &|i| g[pb[i].0 as usize] as f64 * e[pb[i].1 as usize] as f64);
        let (g32, e32f) = fit_link::<f32>(&m, &pb, nb, 200);
        let finite32 = g32.iter().chain(&e32f).all(|x| x.is_finite());
        let e32 = rel(&m, &|i| g32[pb[i].0 as usize] as f64 * e32f[pb[i].1 as usize] as f64);
        println!(
            "GSHD ε {eps:.0e}, R {range:.0e}: error f64 {e64:.3e}, f32 {e32:.3e}, ratio {:.4}{}",
            e32 / e64,
            if finite32 { "" } else { " (f32 factors not finite)" }
        );
        rows.push((eps, range, e64, e32, finite32));
    }
    // CMF: residual with singular values ≈ q^k, K = 4 terms kept.
    let k = 4;
    for (eps, q) in [
        (1.0, 0.3f64),
        (1.0, 0.01),
        (1e-2, 0.3),
        (1e-4, 0.3),
        (1e-6, 0.3),
        (1e-8, 0.3),
    ] {
        let m: Vec<f32> = (0..nl * nv)
            .map(|i| {
                let (l, v) = (i % nl, i / nl);
                let r: f64 = (0..12)
                    .map(|j| q.powi(j as i32) * (unit_hash(j, l + 7) - 0.5) * (unit_hash(j + 50, v + 9) - 0.5))
                    .sum();
                (product(1e1, i) * (1.0 + eps * r)) as f32
            })
            .collect();
        let m64: Vec<f64> = m.iter().map(|x| *x as f64).collect();
        let (g, e, res) = fit_channel(&m64, &pb, nb, 200, (nl, nv, k)).unwrap();
        let (us, vv) = res.unwrap();
        let e64 = rel(&m, &|i| {
            let (l, v) = (i % nl, i / nl);
            let link = g[pb[i].0 as usize] as f64 * e[pb[i].1 as usize] as f64;
            link * (0..k).map(|j| us[(l, j)] * vv[(v, j)]).sum::<f64>()
        });
        // The same chain in f32.
        let (g32, e32f) = fit_link::<f32>(&m, &pb, nb, 200);
        let floor = 1e-3 * m.iter().map(|x| x.abs()).sum::<f32>() / m.len() as f32;
        let r32 = Mat::<f32>::from_fn(nl, nv, |l, v| {
            let i = v * nl + l;
            let fl = g32[pb[i].0 as usize] * e32f[pb[i].1 as usize];
            if fl.abs() > floor {
                m[i] / fl
            } else {
                1.0
            }
        });
        let svd = r32.thin_svd().unwrap();
        let (u, s, w) = (svd.U(), svd.S().column_vector(), svd.V());
        let e32 = rel(&m, &|i| {
            let (l, v) = (i % nl, i / nl);
            let link = g32[pb[i].0 as usize] as f64 * e32f[pb[i].1 as usize] as f64;
            link * (0..k).map(|j| (u[(l, j)] * s[j] * w[(v, j)]) as f64).sum::<f64>()
        });
        println!(
            "CMF ε {eps:.0e}, q {q}, K = {k}: σ_5/σ_1 of the residual's terms ≈ {:.1e}, error f64 {e64:.3e}, \
             f32 {e32:.3e}, ratio {:.4}",
            q.powi(k as i32),
            e32 / e64
        );
        assert!(e64.is_finite() && e32.is_finite());
        rows.push((eps, -q, e64, e32, true));
    }
    for r in &rows {
        assert!(r.2.is_finite(), "f64 error not finite: {r:?}");
    }
    // Where f32 holds and where it fails (measured; docs/guide/compression.md): far from a
    // product and within f32's range it matches f64, ...
    for r in rows
        .iter()
        .filter(|r| (r.1 > 0.0 && r.0 >= 1e-4 && r.1 <= 1e12) || (r.1 < 0.0 && r.0 >= 1e-2))
    {
        assert!(r.3 <= 1.01 * r.2, "f32 should match f64 here: {r:?}");
    }
    // ... close to the model (GSHD 1e-8, CMF 1e-6) it is stuck at its rounding floor, and a highlight of
    // 1e20 overflows its squared sums.
    for r in rows
        .iter()
        .filter(|r| (r.1 > 0.0 && (r.0 <= 1e-8 || r.1 >= 1e20)) || (r.1 < 0.0 && r.0 <= 1e-6))
    {
        assert!(r.3 > 2.0 * r.2, "f32 was expected to fail here: {r:?}");
    }
}
