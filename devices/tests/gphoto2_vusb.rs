//! The gphoto2 backend against libgphoto2's `vusb` virtual camera: a PTP camera emulated
//! inside libgphoto2 (2.5.34's `vusb` io library; it appears as a Nikon on `usb:001,001`)
//! that serves the JPEGs of the folder `VCAMERADIR` as its captures.
//!
//! Run: `bash tests/gphoto2/run.sh` (it fetches the libgphoto2 with vusb from the `gphoto2`
//! Python wheel, points the loader at it and runs this test). Without the feature, or
//! without `VCAMERADIR`, the test prints why it was skipped.
//!
//! What is checked: the camera is found; the shutter speed is the nearest of its choices
//! and read back; aperture is set from its choices and refused with the list when not
//! offered; ISO (which vusb lacks) is refused naming the setting; a gain is refused; a
//! capture is downloaded, decoded to the JPEG put into `VCAMERADIR` (pixel for pixel
//! against the same decoder, near the drawn pattern) and deleted from the card.

#[cfg(not(feature = "gphoto2"))]
#[test]
fn gphoto2_vusb_camera() {
    println!(
        "gphoto2_vusb: SKIPPED: gonio-devices was built without the `gphoto2` feature \
         (run: bash tests/gphoto2/run.sh; needs libgphoto2-dev and libclang)"
    );
}

#[cfg(feature = "gphoto2")]
mod vusb {
    use gonio_devices::gphoto2::camera::decode_jpeg;
    use gonio_devices::gphoto2::{srgb_to_linear16, Gphoto2Camera, Gphoto2Options};
    use gonio_devices::{Camera, CameraConfig, DeviceError};
    use std::path::Path;

    const W: usize = 96;
    const H: usize = 64;
    const REF: &str = "gonio_vusb_reference.jpg";

    /// The drawn pattern: red ramps along x, green along y, blue a checkerboard of 8-pixel
    /// squares (a JPEG keeps all three within a few counts at quality 95).
    fn pattern() -> Vec<u8> {
        let mut v = Vec::with_capacity(W * H * 3);
        for y in 0..H {
            for x in 0..W {
                v.push((x * 255 / (W - 1)) as u8);
                v.push((y * 255 / (H - 1)) as u8);
                v.push(if (x / 8 + y / 8) % 2 == 0 { 40 } else { 200 });
            }
        }
        v
    }

    /// Write the reference JPEG into the virtual camera's folder; its bytes.
    fn write_reference(dir: &Path) -> Vec<u8> {
        let others: Vec<_> = std::fs::read_dir(dir)
            .unwrap_or_else(|e| panic!("VCAMERADIR {}: {e}", dir.display()))
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().to_string())
            .filter(|n| n != REF)
            .collect();
        assert!(
            others.is_empty(),
            "VCAMERADIR {} must hold only the test's JPEG (vusb serves every file in it), found {others:?}",
            dir.display()
        );
        let mut bytes = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, 95)
            .encode(&pattern(), W as u32, H as u32, image::ExtendedColorType::Rgb8)
            .expect("encode the reference JPEG");
        std::fs::write(dir.join(REF), &bytes).expect("write the reference JPEG");
        bytes
    }

    fn config(exposure: f64) -> CameraConfig {
        CameraConfig {
            width: W,
            height: H,
            exposure,
            gain: 1.0,
            bit_depth: 16,
        }
    }

    fn open(opts: Gphoto2Options) -> Gphoto2Camera {
        Gphoto2Camera::open(opts).unwrap_or_else(|e| panic!("the vusb camera was not found: {e}"))
    }

    #[test]
    fn gphoto2_vusb_camera() {
        let Some(dir) = std::env::var_os("VCAMERADIR") else {
            println!(
                "gphoto2_vusb: SKIPPED: VCAMERADIR is not set (the vusb virtual camera needs it; \
                 run bash tests/gphoto2/run.sh)"
            );
            return;
        };
        let reference = write_reference(Path::new(&dir));
        let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();

        // Found, by no option and then by its port.
        let cam = open(Gphoto2Options::default());
        let (model, port) = cam.model_and_port();
        println!("gphoto2_vusb: found {model} on {port}");
        assert!(port.starts_with("usb:"), "{port}");
        let cam = open(Gphoto2Options {
            port: Some(port.clone()),
            aperture: Some("8".into()),
            ..Gphoto2Options::default()
        });
        println!("gphoto2_vusb: identity: {}", rt.block_on(cam.identity()).unwrap());

        // Shutter speed: the nearest choice, read back and parsed; the frame carries it.
        let (choices, current) = cam.choices("shutterspeed").unwrap();
        println!("gphoto2_vusb: shutterspeed choices {choices:?} (was {current})");
        let applied = cam.configure_blocking(&config(0.012)).unwrap();
        println!("gphoto2_vusb: asked 0.012 s, applied {} s", applied.exposure);
        assert_eq!(cam.choices("shutterspeed").unwrap().1, "0.0100s");
        assert!((applied.exposure - 0.01).abs() < 1e-12, "{applied:?}");
        let applied = rt.block_on(cam.configure(&config(0.1))).unwrap();
        assert_eq!(cam.choices("shutterspeed").unwrap().1, "0.1000s");
        assert_eq!((applied.exposure, applied.bit_depth, applied.gain), (0.1, 16, 1.0));
        println!(
            "gphoto2_vusb: asked 0.1 s, applied {} s, read back \"0.1000s\"",
            applied.exposure
        );
        // Aperture from the camera's choices ("8" is its "f/8").
        assert_eq!(cam.choices("f-number").unwrap().1, "f/8");

        // Capture → download → delete → decode.
        let frame = rt.block_on(cam.capture()).unwrap();
        let (folder, file) = cam.last_file().expect("a captured file");
        println!(
            "gphoto2_vusb: captured {folder}/{file}: {} × {}, exposure {} s, bit depth {}, sequence {}",
            frame.width, frame.height, frame.meta.exposure, frame.meta.bit_depth, frame.meta.sequence
        );
        assert_eq!((frame.width, frame.height, frame.meta.bit_depth), (W, H, 16));
        assert_eq!(
            (frame.meta.exposure, frame.meta.gain, frame.meta.sequence),
            (0.1, 1.0, 1)
        );
        let (rw, rh, ref_rgb) = decode_jpeg(&reference).unwrap();
        assert_eq!((rw, rh), (W, H));
        let expected: Vec<u16> = ref_rgb.iter().map(|&v| srgb_to_linear16(v)).collect();
        assert!(
            frame.data == expected,
            "the downloaded image is not the JPEG put into VCAMERADIR"
        );
        // And that JPEG is the drawn pattern (within JPEG's loss).
        let worst = ref_rgb
            .iter()
            .zip(pattern())
            .map(|(&a, b)| (a as i32 - b as i32).abs())
            .max()
            .unwrap();
        println!("gphoto2_vusb: downloaded image equals the reference JPEG pixel for pixel; worst 8-bit deviation from the drawn pattern {worst}");
        assert!(worst <= 8, "decoded reference deviates {worst} from the pattern");
        let listing = cam.files_in(&folder).unwrap();
        assert!(!listing.contains(&file), "{file} is still on the card: {listing:?}");
        println!("gphoto2_vusb: {file} deleted from the card (folder {folder} now holds {listing:?})");

        // A second capture: the next sequence number, the same image.
        let frame2 = cam.capture_blocking().unwrap();
        assert_eq!(frame2.meta.sequence, 2);
        assert!(frame2.data == expected);
        drop(cam);

        // The listing does show a captured file that is kept (so the check above means
        // the deletion, not a listing that never shows captures).
        let cam = open(Gphoto2Options {
            keep_on_card: true,
            ..Gphoto2Options::default()
        });
        cam.configure_blocking(&config(0.1)).unwrap();
        cam.capture_blocking().unwrap();
        let (kept_folder, kept) = cam.last_file().unwrap();
        let listing = cam.files_in(&kept_folder).unwrap();
        println!("gphoto2_vusb: with keep_on_card the card lists {listing:?} in {kept_folder}");
        assert!(listing.contains(&kept), "{kept} kept but not listed: {listing:?}");
        drop(cam);

        // Refusals: an aperture the camera does not offer (with its list), ISO on a camera
        // without an ISO setting, a gain.
        let cam = open(Gphoto2Options {
            aperture: Some("f/1.2".into()),
            ..Gphoto2Options::default()
        });
        let e = cam.configure_blocking(&config(0.1)).unwrap_err();
        println!("gphoto2_vusb: refused: {e}");
        assert!(matches!(e, DeviceError::Rejected { .. }), "{e}");
        assert!(
            e.to_string().contains("f/1.2") && e.to_string().contains("f/2.8, f/3.5"),
            "{e}"
        );
        drop(cam);
        let cam = open(Gphoto2Options {
            iso: Some("100".into()),
            ..Gphoto2Options::default()
        });
        let e = cam.configure_blocking(&config(0.1)).unwrap_err();
        println!("gphoto2_vusb: refused: {e}");
        assert!(e.to_string().contains("no iso setting"), "{e}");
        drop(cam);
        let cam = open(Gphoto2Options::default());
        let e = cam
            .configure_blocking(&CameraConfig {
                gain: 2.0,
                ..config(0.1)
            })
            .unwrap_err();
        assert!(e.to_string().contains("camera.options.iso"), "{e}");
        // Capturing unconfigured is refused, not a frame with unknown exposure.
        assert!(cam.capture_blocking().is_err());
        // A frame of another size than the rig file's is refused, naming the fix.
        cam.configure_blocking(&CameraConfig {
            width: 100,
            ..config(0.1)
        })
        .unwrap();
        let e = cam.capture_blocking().unwrap_err();
        assert!(e.to_string().contains("camera.width"), "{e}");
        println!("gphoto2_vusb: passed");
    }
}
