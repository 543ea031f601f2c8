//! Tests of the per-frame development steps (raw corrections, BRDF conversion, lens).

use super::brdf::*;
use super::lens::undistort_frame;
use super::raw::*;
use gonio_calibration::intrinsics::CameraModel;
use gonio_calibration::radiometric::ResponseCurve;
use gonio_calibration::warp::RectifyParams;
use gonio_devices::image::RgbImage;
use gonio_devices::{Frame, Vec3};

fn params(n: usize) -> RectifyParams {
    RectifyParams {
        width: n,
        height: n,
        sample_mm: 60.0,
        max_supersample: 8,
    }
}

fn src(kind: &str) -> CorrectionSource {
    CorrectionSource {
        kind: kind.into(),
        id: format!("{kind}-id"),
        file: format!("cal/{kind}/calibration.json"),
    }
}

fn frame(w: usize, h: usize, data: Vec<u16>) -> Frame {
    Frame {
        width: w,
        height: h,
        data,
        meta: gonio_devices::FrameMeta {
            timestamp: 0.0,
            exposure: 0.05,
            gain: 1.0,
            sequence: 0,
            bit_depth: 12,
        },
    }
}

/// The compressing response of `radiometric.toml` (a = 2) as a fitted curve would hold it.
fn curve() -> ResponseCurve {
    let inv = |y: f64| -(1.0 - y * (1.0 - (-2f64).exp())).ln() / 2.0;
    let levels = 256;
    let g: Vec<f64> = (0..levels)
        .map(|z| (inv(z as f64 / 255.0).max(1e-9) / inv(0.5)).ln())
        .collect();
    ResponseCurve {
        levels,
        max_dn: 4095.0,
        g: [g.clone(), g.clone(), g],
        validity: Default::default(),
    }
}

#[test]
fn block_maps_are_interpolated_between_block_centres() {
    // 3 × 2 blocks of 4 px over a 10 × 8 frame (last column of blocks 2 px wide)
    let values: Vec<f32> = (0..6).flat_map(|b| [b as f32; 3]).collect();
    let out = expand_blocks(&values, 4, (3, 2), (10, 8));
    let at = |i: usize, j: usize| out[(j * 10 + i) * 3];
    // constant before the first centre (x = 2) and beyond the last (x = 9)
    assert_eq!(at(0, 0), 0.0);
    assert_eq!(at(9, 0), 2.0);
    // between centres 2 and 6 along x, linear: pixel 3 (x = 3.5) is 3/8 of the way
    assert!((at(3, 0) - 0.375).abs() < 1e-6, "{}", at(3, 0));
    // between the centre at 6 and the narrow last block's centre at 9: pixel 7 (7.5) half way
    assert!((at(7, 0) - 1.5).abs() < 1e-6, "{}", at(7, 0));
    // along y between the rows' centres 2 and 6: pixel row 4 (4.5) is 5/8 of the way (+3)
    assert!((at(0, 4) - 0.625 * 3.0).abs() < 1e-6, "{}", at(0, 4));
    // empty flat blocks take their neighbours' mean, outward
    let map = BlockMap {
        block: 4,
        blocks_x: 3,
        blocks_y: 1,
        values: vec![0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0],
    };
    assert_eq!(fill_empty_blocks(&map).unwrap(), vec![1.0; 9]);
    let empty = BlockMap {
        values: vec![0.0; 9],
        ..map
    };
    assert!(fill_empty_blocks(&empty).is_none());
}

/// Codes made the way the simulator makes them (crosstalk → vignetting → dark → response
/// → ADC) come back as the scene's linear values up to one scale.
#[test]
fn raw_correction_inverts_the_sensor_in_reverse_order() {
    let (w, h) = (8usize, 8usize);
    let c = curve();
    let inv = |y: f64| -(1.0 - y * (1.0 - (-2f64).exp())).ln() / 2.0;
    let f = |u: f64| (1.0 - (-2.0 * u).exp()) / (1.0 - (-2f64).exp());
    let x = [[0.85, 0.12, 0.03], [0.08, 0.84, 0.08], [0.03, 0.15, 0.82]];
    // the colour correction: the crosstalk's inverse (rows · columns)
    let m = {
        let d = x[0][0] * (x[1][1] * x[2][2] - x[1][2] * x[2][1]) - x[0][1] * (x[1][0] * x[2][2] - x[1][2] * x[2][0])
            + x[0][2] * (x[1][0] * x[2][1] - x[1][1] * x[2][0]);
        let cof = |r: usize, k: usize| {
            let (r1, r2) = ((r + 1) % 3, (r + 2) % 3);
            let (k1, k2) = ((k + 1) % 3, (k + 2) % 3);
            x[r1][k1] * x[r2][k2] - x[r1][k2] * x[r2][k1]
        };
        let m: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|k| cof(k, r) / d));
        m
    };
    let gain = |p: usize| 1.0 - 0.15 * ((p % w) as f64 - 3.5).powi(2) / 24.5;
    let dark_u = 0.002;
    let scene = [0.30, 0.20, 0.10];
    let mut data = Vec::new();
    for p in 0..w * h {
        let mixed: Vec<f64> = (0..3).map(|r| (0..3).map(|k| x[r][k] * scene[k]).sum()).collect();
        for v in mixed {
            data.push((f(v * gain(p) + dark_u) * 4095.0).round() as u16);
        }
    }
    let dark_dn = (f(dark_u) * 4095.0) as f32;
    let flat_vals: Vec<f32> = (0..w * h).flat_map(|p| [gain(p) as f32; 3]).collect();
    let parts = RawParts {
        response: Some((src("response"), c.clone())),
        dark: Some(MapPart {
            source: src("dark"),
            map: BlockMap {
                block: 1,
                blocks_x: w,
                blocks_y: h,
                values: vec![dark_dn; w * h * 3],
            },
            size: (w, h),
            exposure_s: 0.05,
            linearisation: None,
        }),
        flat: Some(MapPart {
            source: src("flat"),
            map: BlockMap {
                block: 1,
                blocks_x: w,
                blocks_y: h,
                values: flat_vals,
            },
            size: (w, h),
            exposure_s: f64::NAN,
            linearisation: Some("response:response-id".into()),
        }),
        colour: Some((src("colour"), m, Some("response:response-id".into()))),
    };
    let rc = RawCorrection::build(parts.clone()).unwrap().unwrap();
    assert_eq!(rc.kinds(), ["response", "dark", "flat", "colour"]);
    let (img, saturated) = rc.apply(&frame(w, h, data)).unwrap();
    assert_eq!(saturated, 0);
    // ½ exp g = ½ f⁻¹(y) / f⁻¹(½): the scene's values times one common scale
    let s = 0.5 / inv(0.5);
    for px in img.data.chunks_exact(3) {
        for ch in 0..3 {
            let rel = px[ch] as f64 / (s * scene[ch]) - 1.0;
            assert!(rel.abs() < 0.01, "channel {ch}: {px:?} vs {scene:?} (rel {rel})");
        }
    }

    // Extreme frames: all saturated → all counted, neutral and finite; all black → 0.
    let (img, n) = rc.apply(&frame(w, h, vec![4095; w * h * 3])).unwrap();
    assert_eq!(n, w * h);
    assert!(img.data.iter().all(|v| v.is_finite() && *v > 0.0));
    let p = &img.data[..3];
    // a neutral clip stays neutral through the colour matrix (its rows sum to 1)
    assert!(
        (p[0] - p[1]).abs() < 1e-3 * p[0] && (p[1] - p[2]).abs() < 1e-3 * p[0],
        "{p:?}"
    );
    let (img, n) = rc.apply(&frame(w, h, vec![0; w * h * 3])).unwrap();
    assert_eq!(n, 0);
    assert!(img.data.iter().all(|v| *v == 0.0));
    // one saturated channel makes the pixel count, the others are not mixed into a hue
    let mut one = vec![2000u16; w * h * 3];
    one[0] = 4095;
    let (img, n) = rc.apply(&frame(w, h, one)).unwrap();
    assert_eq!(n, 1);
    assert!((img.data[0] - img.data[1]).abs() < 1e-3 * img.data[0]);
    // a frame of another size is an error, not a panic
    assert!(matches!(
        rc.apply(&frame(4, 4, vec![0; 48])),
        Err(super::DevelopError::FrameSize { .. })
    ));

    // Camera checks name both sizes; a 10-bit camera does not fit a 12-bit curve.
    let e = rc.check_camera(16, 8, 12).unwrap_err().to_string();
    assert!(e.contains("8×8") && e.contains("16×8") && e.contains("cal/dark"), "{e}");
    let e = rc.check_camera(8, 8, 10).unwrap_err().to_string();
    assert!(e.contains("response curve") && e.contains("1023"), "{e}");
    rc.check_camera(8, 8, 12).unwrap();

    // Consistency: a flat measured on linear-assumed values with a response applied,
    // or a colour matrix with a response not applied, is refused with the fix.
    let mut bad = parts.clone();
    bad.flat.as_mut().unwrap().linearisation = Some("linear".into());
    let (file, e) = RawCorrection::build(bad).unwrap_err();
    assert_eq!(file, "cal/flat/calibration.json");
    assert!(e.0.contains("`linear`") && e.0.contains("response = "), "{}", e.0);
    let no_response = RawParts {
        response: None,
        flat: None,
        ..parts.clone()
    };
    let (file, e) = RawCorrection::build(no_response).unwrap_err();
    assert_eq!(file, "cal/colour/calibration.json");
    assert!(e.0.contains("no response result is applied"), "{}", e.0);
    // a map that does not tile its declared frame
    let mut torn = parts;
    torn.dark.as_mut().unwrap().size = (9, 8);
    torn.flat = None;
    let (file, e) = RawCorrection::build(torn).unwrap_err();
    assert_eq!(file, "cal/dark/calibration.json");
    assert!(e.0.contains("do not tile a 9×8 frame"), "{}", e.0);
    assert!(RawCorrection::build(RawParts::default()).unwrap().is_none());
}

#[test]
fn point_lamp_irradiance_is_inverse_square_and_cosine() {
    let lamp = LampModel {
        intensity_w_sr: 50.0,
        radius_mm: 0.0,
    };
    // straight above at 1 m: E = I / 1 m²
    let e = lamp.irradiance(Vec3::new(0.0, 0.0, 1000.0), Vec3::ZERO);
    assert!((e - 50.0).abs() < 1e-9, "{e}");
    // 60° off the normal at 2 m: I cos 60° / 4
    let at = Vec3::new(2000.0 * 60f64.to_radians().sin(), 0.0, 2000.0 * 0.5);
    assert!((lamp.irradiance(at, Vec3::ZERO) - 50.0 * 0.5 / 4.0).abs() < 1e-9);
    // below the horizon: nothing
    assert_eq!(lamp.irradiance(Vec3::new(1000.0, 0.0, -1.0), Vec3::ZERO), 0.0);
    // the falloff differs across the sample: the near edge is brighter
    let l = Vec3::new(1200.0 * 60f64.to_radians().sin(), 0.0, 600.0);
    let near = lamp.irradiance(l, Vec3::new(30.0, 0.0, 0.0));
    let far = lamp.irradiance(l, Vec3::new(-30.0, 0.0, 0.0));
    assert!(near / far > 1.05, "{near} {far}");
}

#[test]
fn a_small_disc_matches_the_point_and_a_large_one_differs_slightly() {
    let point = LampModel {
        intensity_w_sr: 10.0,
        radius_mm: 0.0,
    };
    let l = Vec3::new(0.0, 0.0, 1000.0);
    let p = Vec3::new(10.0, 5.0, 0.0);
    let small = LampModel {
        radius_mm: 1.0,
        ..point
    };
    let big = LampModel {
        radius_mm: 300.0,
        ..point
    };
    let e0 = point.irradiance(l, p);
    assert!((small.irradiance(l, p) / e0 - 1.0).abs() < 1e-5);
    let rel = big.irradiance(l, p) / e0 - 1.0;
    // off-axis emitters are farther and more oblique: less irradiance
    assert!(rel < -0.01 && rel > -0.3, "{rel}");
}

#[test]
fn brdf_conversion_inverts_the_measurement_model() {
    let radio = Radiometric {
        k: [0.7, 0.8, 0.9],
        lamp: LampModel {
            intensity_w_sr: 50.0,
            radius_mm: 0.0,
        },
    };
    let p = params(8);
    let lamp = Vec3::new(500.0, 300.0, 900.0);
    let e = radio.lamp.irradiance_map(lamp, &p);
    let f = [0.25, 0.1, 0.3];
    let (t, g) = (0.05, 2.0);
    let mut img = RgbImage::new(8, 8);
    for (px, e) in img.data.chunks_exact_mut(3).zip(&e) {
        for c in 0..3 {
            px[c] = (radio.k[c] * t * g * f[c] * e) as f32;
        }
    }
    radio.to_brdf(&mut img, lamp, &p, t, g).unwrap();
    for px in img.data.chunks_exact(3) {
        for c in 0..3 {
            assert!((px[c] as f64 / f[c] - 1.0).abs() < 1e-5, "{px:?}");
        }
    }
    assert!(matches!(
        radio.to_brdf(&mut img, lamp, &p, 0.0, 1.0),
        Err(super::DevelopError::BadExposure { .. })
    ));
    let mut wrong = RgbImage::new(4, 8);
    assert!(matches!(
        radio.to_brdf(&mut wrong, lamp, &p, t, g),
        Err(super::DevelopError::BadImage { .. })
    ));
}

#[test]
fn undistortion_moves_content_to_its_pinhole_position() {
    // A frame with one bright pixel where a distorting lens puts the ray of the
    // pinhole pixel (300, 200); after undistortion the light is back at (300, 200).
    let cam = CameraModel {
        fx: 500.0,
        fy: 500.0,
        cx: 320.0,
        cy: 240.0,
        distortion: [-0.2, 0.05, 0.0, 0.0, 0.0],
    };
    let (w, h) = (640, 480);
    let (pi, pj) = (500usize, 400usize);
    let (x, y) = ((pi as f64 + 0.5 - cam.cx) / cam.fx, (pj as f64 + 0.5 - cam.cy) / cam.fy);
    let (xd, yd) = cam.distort(x, y);
    let (u, v) = (cam.fx * xd + cam.cx, cam.fy * yd + cam.cy);
    let mut raw = RgbImage::new(w, h);
    for j in 0..h {
        for i in 0..w {
            let d2 = (i as f64 + 0.5 - u).powi(2) + (j as f64 + 0.5 - v).powi(2);
            let val = (-d2 / 8.0).exp() as f32;
            raw.data[(j * w + i) * 3..(j * w + i) * 3 + 3].copy_from_slice(&[val; 3]);
        }
    }
    let out = undistort_frame(&raw, &cam);
    let (mut best, mut at) = (0.0, 0);
    for (k, px) in out.data.chunks_exact(3).enumerate() {
        if px[0] > best {
            best = px[0];
            at = k;
        }
    }
    assert_eq!((at % w, at / w), (pi, pj), "peak moved back to the pinhole pixel");
    assert!(best > 0.9);
    // no distortion: identity
    let flat = CameraModel {
        distortion: [0.0; 5],
        ..cam
    };
    assert_eq!(undistort_frame(&raw, &flat), raw);
}
