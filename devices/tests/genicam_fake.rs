//! The GenICam backend against a real GigE Vision device on the wire: Debian's
//! `arv-fake-gv-camera-0.8` (package aravis-tools) on the loopback interface.
//!
//! Run: `cargo test -p gonio-devices --features genicam --test genicam_fake`
//! (tests/genicam/run.sh does, in CI). Without the feature, or without the fake camera
//! program, the test prints why it was skipped (and fails under CI, where both must be
//! there).
//!
//! What the fake gives (libaravis 0.8.26, src/arvfakecamera.c): `ExposureTimeAbs` in whole
//! microseconds, `GainRaw` 0..=10, pixel formats Mono8, Mono16, RGB8 and Bayer RG/BG/GR/GB 8,
//! and a diagonal ramp: with d = (x + y + frame id) and s = 1 + GainRaw +
//! log10(exposure µs / 10000), Mono8 is `clamp(⌊(d mod 255)·s⌋, 0, 255)`, Mono16
//! `clamp(⌊(256·d mod 65535)·s⌋, 0, 65535)`; RGB8 and the Bayer mosaics colour the same
//! index through a colour map (the Bayer frames are checked against the RGB8 frame).

#[cfg(not(feature = "genicam"))]
#[test]
fn genicam_fake_camera() {
    println!(
        "genicam_fake: SKIPPED: gonio-devices was built without the `genicam` feature \
         (run: cargo test -p gonio-devices --features genicam --test genicam_fake; needs libaravis-dev and aravis-tools)"
    );
}

#[cfg(feature = "genicam")]
mod fake {
    use gonio_devices::genicam::pixel::demosaic_bilinear;
    use gonio_devices::genicam::{Cfa, GenicamCamera, GenicamOptions, PixelFormat};
    use gonio_devices::{CameraConfig, DeviceError, Frame};
    use std::process::{Child, Command, Stdio};
    use std::sync::{Mutex, MutexGuard};
    use std::time::Duration;

    const FAKE: &str = "arv-fake-gv-camera-0.8";

    /// One fake per host (it binds the GigE Vision control port): the tests take turns.
    static HOST: Mutex<()> = Mutex::new(());

    /// A running fake camera, killed (by its own pid) when dropped.
    struct Fake {
        child: Child,
        _turn: MutexGuard<'static, ()>,
    }

    impl Drop for Fake {
        fn drop(&mut self) {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }

    /// Start the fake on loopback, or None (printed) when the program is missing outside CI.
    fn start(extra: &[&str]) -> Option<Fake> {
        let turn = HOST.lock().unwrap_or_else(|p| p.into_inner());
        let child = match Command::new(FAKE)
            .args(["-i", "127.0.0.1"])
            .args(extra)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
        {
            Ok(c) => c,
            Err(e) => {
                let msg = format!("genicam_fake: SKIPPED: cannot start {FAKE} ({e}); apt-get install aravis-tools");
                if std::env::var_os("CI").is_some() {
                    panic!("{msg} (mandatory under CI)");
                }
                println!("{msg}");
                return None;
            }
        };
        Some(Fake { child, _turn: turn })
    }

    fn options() -> GenicamOptions {
        GenicamOptions {
            device: Some("127.0.0.1".into()),
            // The packet socket sees nothing of a loopback stream (tested: no frames as
            // root); an ordinary UDP socket does.
            packet_socket: false,
            timeout: Duration::from_millis(1500),
            ..GenicamOptions::default()
        }
    }

    /// Open the fake once it answers (it needs a moment to bind its sockets).
    fn open(fake: &Fake) -> GenicamCamera {
        let _ = fake;
        let mut last = None;
        for _ in 0..50 {
            match GenicamCamera::open(options()) {
                Ok(c) => return c,
                Err(e) => last = Some(e),
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        panic!("the fake camera never answered on 127.0.0.1: {last:?}");
    }

    fn config(width: usize, height: usize, exposure: f64) -> CameraConfig {
        CameraConfig {
            width,
            height,
            exposure,
            gain: 1.0,
            bit_depth: 8,
        }
    }

    fn use_format(cam: &GenicamCamera, name: &str) {
        cam.set_formats(vec![PixelFormat::parse(name).unwrap()]);
    }

    /// The fake's Mono ramp (see the module doc), `scale` from the read-back exposure.
    fn ramp(x: usize, y: usize, frame_id: u64, scale: f64, sixteen: bool) -> u16 {
        let d = x as u64 + y as u64 + frame_id;
        if sixteen {
            (((256 * d) % 65535) as f64 * scale).clamp(0.0, 65535.0) as u16
        } else {
            ((d % 255) as f64 * scale).clamp(0.0, 255.0) as u16
        }
    }

    fn scale(exposure_s: f64) -> f64 {
        // The fake's exposure register holds whole microseconds.
        1.0 + ((exposure_s * 1e6).round() / 10_000.0).log10()
    }

    fn mean(f: &Frame) -> f64 {
        f.data.iter().map(|&v| v as f64).sum::<f64>() / f.data.len() as f64
    }

    #[test]
    fn exposure_is_read_back_and_frames_match_the_fake_pattern() {
        let Some(fake) = start(&[]) else { return };
        let cam = open(&fake);
        use_format(&cam, "Mono8");
        // 12 345.6 µs asked; the fake keeps whole microseconds: the read-back is the truth.
        let applied = cam.configure_blocking(&config(64, 48, 0.012_345_6)).unwrap();
        assert_eq!((applied.width, applied.height, applied.bit_depth), (64, 48, 8));
        assert!((applied.exposure - 0.012_345).abs() < 1e-12, "{applied:?}");
        assert_eq!(applied.gain, 1.0);
        let s = scale(applied.exposure);
        let mut last: Option<Frame> = None;
        for _ in 0..3 {
            let f = cam.capture_blocking().unwrap();
            assert_eq!(
                f.meta.exposure, applied.exposure,
                "every frame carries the read-back exposure"
            );
            assert_eq!(f.meta.bit_depth, 8);
            for y in 0..48 {
                for x in 0..64 {
                    let want = ramp(x, y, f.meta.sequence, s, false);
                    let o = 3 * (y * 64 + x);
                    assert_eq!(
                        &f.data[o..o + 3],
                        &[want; 3],
                        "Mono8 at ({x}, {y}), frame {}",
                        f.meta.sequence
                    );
                }
            }
            if let Some(p) = &last {
                assert_eq!(f.meta.sequence, p.meta.sequence + 1, "one frame per software trigger");
                assert!(f.meta.timestamp > p.meta.timestamp);
            }
            println!(
                "genicam_fake: Mono8 64x48 frame {} exposure {} s: mean {:.3} DN (pattern predicts it exactly)",
                f.meta.sequence,
                f.meta.exposure,
                mean(&f)
            );
            last = Some(f);
        }

        // Mono16 at twice the exposure: the ramp scales by 1 + log10(2) (saturating).
        use_format(&cam, "Mono16");
        let applied = cam.configure_blocking(&config(32, 16, 0.02)).unwrap();
        assert_eq!((applied.exposure, applied.bit_depth), (0.02, 16));
        let f = cam.capture_blocking().unwrap();
        let s = scale(0.02);
        for y in 0..16 {
            for x in 0..32 {
                let want = ramp(x, y, f.meta.sequence, s, true);
                assert_eq!(f.data[3 * (y * 32 + x)], want, "Mono16 at ({x}, {y})");
            }
        }
        println!("genicam_fake: Mono16 32x16 exposure 0.02 s: mean {:.1} DN", mean(&f));

        // An exposure outside the camera's range (10 µs ..= 10 s) is clamped, and the frame
        // says what the camera used, not what was asked.
        use_format(&cam, "Mono8");
        let long = cam.configure_blocking(&config(16, 16, 100.0)).unwrap();
        assert!((long.exposure - 10.0).abs() < 1e-12, "{long:?}");
        let short = cam.configure_blocking(&config(16, 16, 1e-7)).unwrap();
        assert!((short.exposure - 10e-6).abs() < 1e-15, "{short:?}");
        assert_eq!(cam.capture_blocking().unwrap().meta.exposure, short.exposure);
    }

    /// `gonio devices check` and each record ask the camera who it is and how warm: the
    /// fake answers from its GenICam description (vendor, model, serial number).
    #[test]
    fn identity_and_temperature_come_from_the_standard_features() {
        use gonio_devices::Camera;
        let Some(fake) = start(&[]) else { return };
        let cam = open(&fake);
        let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
        let id = rt.block_on(cam.identity()).unwrap();
        assert!(id.contains("S/N") && id != cam.name(), "{id}");
        let t = rt.block_on(cam.temperature_c()).unwrap();
        assert!(t.is_none_or(|c| c.is_finite()), "{t:?}");
        println!("genicam_fake: identity `{id}`, temperature {t:?}");
    }

    #[test]
    fn bayer_frames_demosaic_to_the_fakes_colour_pattern() {
        let Some(fake) = start(&[]) else { return };
        let cam = open(&fake);
        // The reference: the same colour-mapped ramp as RGB8, one colour per diagonal.
        use_format(&cam, "RGB8");
        cam.configure_blocking(&config(96, 96, 0.01)).unwrap();
        let rgb = cam.capture_blocking().unwrap();
        let colour = |d: u64| -> [u16; 3] {
            // Pixel (k, 0) of the reference has diagonal rgb.sequence + k.
            let k = (d - rgb.meta.sequence) as usize;
            assert!(k < 96, "reference too short for diagonal {d}");
            let o = 3 * k;
            [rgb.data[o], rgb.data[o + 1], rgb.data[o + 2]]
        };
        // (name, the layout the name means, the layout the fake writes): libaravis'
        // arvfakecamera.c swaps RG and BG (its BayerRG8 has blue at (0, 0)). gonio decodes
        // by the PFNC name, so the frame is the fake's mosaic demosaiced as the name says.
        for (name, cfa, written) in [
            ("BayerRG8", Cfa::Rggb, Cfa::Bggr),
            ("BayerBG8", Cfa::Bggr, Cfa::Rggb),
            ("BayerGR8", Cfa::Grbg, Cfa::Grbg),
            ("BayerGB8", Cfa::Gbrg, Cfa::Gbrg),
        ] {
            use_format(&cam, name);
            let applied = cam.configure_blocking(&config(16, 12, 0.01)).unwrap();
            assert_eq!(applied.bit_depth, 8);
            let f = cam.capture_blocking().unwrap();
            let (w, h) = (16, 12);
            let mosaic: Vec<u16> = (0..h)
                .flat_map(|y| (0..w).map(move |x| (x, y)))
                .map(|(x, y)| colour(x as u64 + y as u64 + f.meta.sequence)[written.channel(x, y)])
                .collect();
            let want = demosaic_bilinear(cfa, w, h, &mosaic);
            let differ = f.data.iter().zip(&want).filter(|(a, b)| a != b).count();
            println!(
                "genicam_fake: {name} 16x12 frame {}: mean R/G/B {:.1}/{:.1}/{:.1} DN, {differ} of {} values differ from the demosaiced RGB8 reference",
                f.meta.sequence,
                channel_mean(&f, 0),
                channel_mean(&f, 1),
                channel_mean(&f, 2),
                want.len()
            );
            assert_eq!(
                differ, 0,
                "{name}: the demosaiced frame must equal the reference mosaic demosaiced"
            );
        }
    }

    fn channel_mean(f: &Frame, c: usize) -> f64 {
        let v: Vec<f64> = f.data.iter().skip(c).step_by(3).map(|&v| v as f64).collect();
        v.iter().sum::<f64>() / v.len() as f64
    }

    #[test]
    fn exposure_changes_between_frames_give_each_frame_its_own_exposure() {
        let Some(fake) = start(&[]) else { return };
        let cam = open(&fake);
        use_format(&cam, "Mono8");
        // An HDR-like sequence: base, 1/8, base again; each frame must be the pattern of
        // the exposure it reports.
        for asked in [0.012_345_6, 0.012_345_6 / 8.0, 0.05, 0.012_345_6] {
            let applied = cam.configure_blocking(&config(48, 32, asked)).unwrap();
            // The fake keeps the whole microseconds of what it is asked.
            assert!(
                (applied.exposure * 1e6 - (asked * 1e6).floor()).abs() < 1e-6,
                "{asked} s asked: {applied:?}"
            );
            let f = cam.capture_blocking().unwrap();
            assert_eq!(f.meta.exposure, applied.exposure);
            let s = scale(f.meta.exposure);
            for y in 0..32 {
                for x in 0..48 {
                    assert_eq!(
                        f.data[3 * (y * 48 + x)],
                        ramp(x, y, f.meta.sequence, s, false),
                        "{asked} s at ({x}, {y})"
                    );
                }
            }
            println!(
                "genicam_fake: exposure {asked} s asked, {} s applied: frame {} mean {:.3} DN, exact",
                applied.exposure,
                f.meta.sequence,
                mean(&f)
            );
        }
    }

    #[test]
    fn a_camera_changed_behind_our_back_never_gives_a_frame() {
        let Some(fake) = start(&[]) else { return };
        let cam = open(&fake);
        use_format(&cam, "Mono8");
        cam.configure_blocking(&config(32, 32, 0.01)).unwrap();
        cam.capture_blocking().unwrap();
        // Same payload, other format: the buffer says BayerRG8, gonio configured Mono8.
        cam.set_feature_string("PixelFormat", "BayerRG8").unwrap();
        let e = cam.capture_blocking().unwrap_err();
        assert!(matches!(e, DeviceError::Rejected { .. }), "{e}");
        assert!(
            e.to_string().contains("BayerRG8") && e.to_string().contains("Mono8"),
            "{e}"
        );
        println!("genicam_fake: pixel format changed mid-run -> {e}");
        // Reconfiguring mends it.
        cam.configure_blocking(&config(32, 32, 0.01)).unwrap();
        cam.capture_blocking().unwrap();
        // The exposure changed: the frame is refused, not stored with the old exposure.
        cam.set_feature_float("ExposureTimeAbs", 20_000.0).unwrap();
        let e = cam.capture_blocking().unwrap_err();
        assert!(
            matches!(e, DeviceError::Rejected { .. }) && e.to_string().contains("exposure changed"),
            "{e}"
        );
        println!("genicam_fake: exposure changed mid-run -> {e}");
    }

    #[test]
    fn a_stopped_acquisition_times_out_and_the_next_capture_recovers() {
        let Some(fake) = start(&[]) else { return };
        let cam = open(&fake);
        use_format(&cam, "Mono8");
        cam.configure_blocking(&config(32, 32, 0.01)).unwrap();
        cam.capture_blocking().unwrap();
        // Someone stops the acquisition: the trigger brings no frame.
        cam.execute("AcquisitionStop").unwrap();
        let e = cam.capture_blocking().unwrap_err();
        assert!(matches!(e, DeviceError::Timeout { .. }), "{e}");
        println!("genicam_fake: stopped acquisition -> {e}");
        // The next capture re-arms the acquisition.
        let f = cam.capture_blocking().unwrap();
        assert_eq!(f.data.len(), 32 * 32 * 3);
        let stats = cam.stats();
        assert_eq!((stats.timeouts, stats.frames), (1, 2), "{stats:?}");
        println!("genicam_fake: recovered after the timeout: {stats:?}");
    }

    #[test]
    fn a_lossy_stream_gives_correct_frames_or_typed_errors_never_a_wrong_frame() {
        // The fake drops 30 % of its stream packets (`-r 300`, per thousand).
        let Some(fake) = start(&["-r", "300"]) else { return };
        let cam = open(&fake);
        use_format(&cam, "Mono8");
        let applied = cam.configure_blocking(&config(96, 64, 0.01)).unwrap();
        let s = scale(applied.exposure);
        let (mut good, mut failed) = (0, Vec::new());
        for _ in 0..20 {
            match cam.capture_blocking() {
                Ok(f) => {
                    for y in 0..64 {
                        for x in 0..96 {
                            let want = ramp(x, y, f.meta.sequence, s, false);
                            assert_eq!(
                                f.data[3 * (y * 96 + x)],
                                want,
                                "frame {} at ({x}, {y})",
                                f.meta.sequence
                            );
                        }
                    }
                    good += 1;
                }
                Err(e) => {
                    assert!(
                        matches!(e, DeviceError::Garbled { .. } | DeviceError::Timeout { .. }),
                        "a lost packet must be a retriable error: {e}"
                    );
                    failed.push(e.to_string());
                }
            }
        }
        println!(
            "genicam_fake: 30 % packet loss: {good} of 20 frames whole and exact, {} retriable errors{}",
            failed.len(),
            failed.first().map(|e| format!(" (first: {e})")).unwrap_or_default()
        );
        println!("genicam_fake: stats {:?}", cam.stats());
    }

    #[test]
    fn a_fake_killed_mid_run_is_a_typed_error_never_a_frame() {
        let Some(mut fake) = start(&[]) else { return };
        let cam = open(&fake);
        use_format(&cam, "Mono8");
        cam.configure_blocking(&config(32, 32, 0.01)).unwrap();
        cam.capture_blocking().unwrap();
        fake.child.kill().unwrap();
        fake.child.wait().unwrap();
        let mut kinds = Vec::new();
        // Every capture fails; Aravis' heartbeat notices within its timeout (3 s on the
        // fake), after which the error says the camera is gone.
        for _ in 0..8 {
            match cam.capture_blocking() {
                Ok(f) => panic!("a frame (sequence {}) from a camera that is gone", f.meta.sequence),
                Err(e) => {
                    assert!(
                        matches!(e, DeviceError::Timeout { .. } | DeviceError::Disconnected { .. }),
                        "{e}"
                    );
                    let gone = matches!(e, DeviceError::Disconnected { .. });
                    kinds.push(e.to_string());
                    if gone {
                        break;
                    }
                }
            }
        }
        println!("genicam_fake: after kill: {kinds:#?}");
        assert!(
            kinds.last().is_some_and(|k| k.contains("disconnected")),
            "the camera's loss must end in a Disconnected error: {kinds:?}"
        );
    }
}
