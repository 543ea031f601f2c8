//! Exercise gonio's V4L2 backend against a real kernel driver, normally `vivid` inside the
//! QEMU VM that `tests/vivid/run.sh` boots: format negotiation and conversion (known test
//! patterns must come out as known linear values), stale-frame discarding, gain and
//! exposure controls with read back, a stalled stream timing out, a corrupt buffer being
//! skipped and an unplugged device ending in a typed error.
//!
//! Usage: `v4l2_check [/dev/video0]`. Prints a PASS/FAIL table, the fault rows in the
//! `faults:` format of the reliability campaign table (`tests/run.sh`; `tests/vivid/run.sh`
//! forwards them from the VM) and a final line `V4L2_CHECK pass=N fail=M skip=K`; exits 1
//! if anything failed.
//!
//! The vivid-specific control ids below come from the driver's source
//! (drivers/media/test-drivers/vivid/vivid-ctrls.c); on another camera the vivid-only rows
//! are skipped.

use std::time::{Duration, Instant};

use gonio_devices::v4l2::controls::cid;
use gonio_devices::v4l2::{PixelFormat, V4l2Camera, V4l2Options};
use gonio_devices::{Camera, CameraConfig, DeviceError, Frame};

const VIVID_BASE: u32 = 0x00f0_f000;
const VIVID_TEST_PATTERN: u32 = VIVID_BASE;
const VIVID_OSD_TEXT_MODE: u32 = VIVID_BASE + 1;
const VIVID_PERC_DROPPED: u32 = VIVID_BASE + 64;
const VIVID_DISCONNECT: u32 = VIVID_BASE + 65;
const VIVID_DQBUF_ERROR: u32 = VIVID_BASE + 66;
// Test pattern menu indices (v4l2-tpg: "100% Black", "100% White", "100% Red", ...).
const PAT_BLACK: i32 = 5;
const PAT_WHITE: i32 = 6;
const PAT_RED: i32 = 7;

struct Report {
    rows: Vec<(String, &'static str, String)>,
    /// Rows of the fault campaign table: (fault, outcome).
    faults: Vec<(String, String)>,
}

impl Report {
    fn row(&mut self, name: impl Into<String>, status: &'static str, detail: impl Into<String>) {
        let (name, detail) = (name.into(), detail.into());
        println!("  {status:<4} {name:<34} {detail}");
        self.rows.push((name, status, detail));
    }
    fn check(&mut self, name: impl Into<String>, ok: bool, detail: impl Into<String>) -> bool {
        self.row(name, if ok { "PASS" } else { "FAIL" }, detail);
        ok
    }
    /// A checked fault: a PASS/FAIL row plus a `faults:` row. "lost" is `n/a`: a camera
    /// check stores no measurements (the in-VM `gonio acquire` covers the dataset side).
    fn fault(&mut self, fault: &str, ok: bool, outcome: String) -> bool {
        let status = if ok { "" } else { "FAILED: " };
        self.faults.push((fault.to_string(), format!("{status}{outcome}")));
        self.check(fault, ok, outcome)
    }
    fn count(&self, s: &str) -> usize {
        self.rows.iter().filter(|r| r.1 == s).count()
    }
}

/// Mean linear RGB (0..1) of the central quarter of a frame (away from borders and OSD).
fn centre_mean(f: &Frame) -> [f64; 3] {
    let (x0, x1, y0, y1) = (f.width * 3 / 8, f.width * 5 / 8, f.height * 3 / 8, f.height * 5 / 8);
    let mut s = [0f64; 3];
    let mut n = 0f64;
    for y in y0..y1 {
        for x in x0..x1 {
            let i = (y * f.width + x) * 3;
            for (acc, &v) in s.iter_mut().zip(&f.data[i..i + 3]) {
                *acc += v as f64 / f.max_dn() as f64;
            }
            n += 1.0;
        }
    }
    s.map(|v| v / n.max(1.0))
}

fn close(a: [f64; 3], b: [f64; 3], tol: f64) -> bool {
    a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
}

fn fmt3(a: [f64; 3]) -> String {
    format!("({:.3}, {:.3}, {:.3})", a[0], a[1], a[2])
}

async fn capture_pattern(cam: &V4l2Camera, pattern: i32) -> Result<Frame, DeviceError> {
    cam.set_control(VIVID_TEST_PATTERN, pattern)?;
    // The pattern applies to frames generated from now on.
    cam.rig_still();
    cam.capture().await
}

#[tokio::main(flavor = "current_thread")]
async fn main() {
    let path = std::env::args().nth(1).unwrap_or_else(|| "/dev/video0".into());
    let t0 = Instant::now();
    let mut r = Report {
        rows: Vec::new(),
        faults: Vec::new(),
    };
    println!("v4l2_check on {path}");
    let mut opts = V4l2Options::new(&path);
    opts.name = format!("vivid {path}");
    opts.timeout = Duration::from_secs(5);
    let cam = match V4l2Camera::open(opts) {
        Ok(c) => c,
        Err(e) => {
            r.check("open device", false, e.to_string());
            finish(&r, t0);
        }
    };
    r.check("open device", true, cam.name().to_string());
    let offered = cam.offered_formats().unwrap_or_default();
    r.row("formats offered", "INFO", offered.join(" "));
    let is_vivid = cam.control_info(VIVID_TEST_PATTERN).ok().flatten().is_some();
    if is_vivid {
        // No on-screen text over the pattern.
        let _ = cam.set_control(VIVID_OSD_TEXT_MODE, 2);
    }

    // Formats: ask for an odd size, the driver must adjust it and we must use its answer.
    let ask = CameraConfig {
        width: 641,
        height: 361,
        exposure: 0.01,
        gain: 1.0,
        bit_depth: 8,
    };
    for fmt in [
        PixelFormat::Yuyv,
        PixelFormat::Rgb24,
        PixelFormat::Grey,
        PixelFormat::Mjpeg,
    ] {
        let label = format!("format {fmt}");
        if !offered.iter().any(|c| c.as_bytes() == fmt.fourcc()) {
            let why = if fmt == PixelFormat::Mjpeg {
                "device offers no MJPEG (vivid has none); decoder covered by unit test"
            } else {
                "not offered by the device"
            };
            r.row(label, "SKIP", why);
            continue;
        }
        cam.set_formats(vec![fmt]);
        let applied = match cam.configure(&ask).await {
            Ok(a) => a,
            Err(e) => {
                r.check(label, false, e.to_string());
                continue;
            }
        };
        let layout = cam.layout().expect("configured");
        let bpp = fmt.bytes_per_pixel().unwrap_or(0);
        r.check(
            format!("{label} negotiated"),
            layout.format == fmt && applied.width == layout.width && layout.stride >= layout.width * bpp,
            format!(
                "asked {}x{}, driver gave {}x{} stride {} size {} ({:?})",
                ask.width, ask.height, layout.width, layout.height, layout.stride, layout.size, layout.colorimetry
            ),
        );
        if !is_vivid {
            match cam.capture().await {
                Ok(f) => r.check(
                    format!("{label} capture"),
                    f.data.len() == f.width * f.height * 3,
                    format!("seq {}", f.meta.sequence),
                ),
                Err(e) => r.check(format!("{label} capture"), false, e.to_string()),
            };
            continue;
        }
        let grey = fmt == PixelFormat::Grey;
        let cases: Vec<(&str, i32, [f64; 3])> = if grey {
            vec![("white", PAT_WHITE, [1.0; 3]), ("black", PAT_BLACK, [0.0; 3])]
        } else {
            vec![
                ("white", PAT_WHITE, [1.0; 3]),
                ("red", PAT_RED, [1.0, 0.0, 0.0]),
                ("black", PAT_BLACK, [0.0; 3]),
            ]
        };
        for (name, pat, want) in cases {
            match capture_pattern(&cam, pat).await {
                Ok(f) => {
                    let m = centre_mean(&f);
                    r.check(
                        format!("{label} {name} -> linear"),
                        f.width == layout.width && f.meta.bit_depth == 16 && close(m, want, 0.02),
                        format!("centre mean {} want {}", fmt3(m), fmt3(want)),
                    );
                }
                Err(e) => {
                    r.check(format!("{label} {name} -> linear"), false, e.to_string());
                }
            }
        }
    }

    // Back to a colour format for the remaining checks, asking for a frame rate: the
    // driver picks the nearest interval it has and that is what gets used.
    let before_period = cam.frame_period();
    cam.set_formats(vec![PixelFormat::Yuyv, PixelFormat::Rgb24]);
    cam.set_frame_rate(Some(30.0));
    let applied = match cam.configure(&ask).await {
        Ok(a) => a,
        Err(e) => {
            r.check("configure YUYV", false, e.to_string());
            finish(&r, t0);
        }
    };
    let period = cam.frame_period();
    r.check(
        "frame rate 30 Hz requested",
        period > 0.0 && (!is_vivid || (period - 1.0 / 30.0).abs() < 1e-6),
        format!("frame period {before_period:.4} s -> driver gave {period:.4} s"),
    );

    // Sequence numbers increase from frame to frame.
    let mut seqs = Vec::new();
    for _ in 0..3 {
        match cam.capture().await {
            Ok(f) => seqs.push(f.meta.sequence),
            Err(e) => {
                r.check("sequence increases", false, e.to_string());
                break;
            }
        }
    }
    if seqs.len() == 3 {
        r.check(
            "sequence increases",
            seqs.windows(2).all(|w| w[1] > w[0]),
            format!("{seqs:?}"),
        );
    }

    // Stale frames: let the queue fill while "moving", then say the rig is still. Every
    // frame already queued began exposing before that and must be discarded.
    let _ = cam.capture().await;
    std::thread::sleep(Duration::from_millis(400));
    let before = cam.stats();
    let still = gonio_devices::v4l2::stream::monotonic_now();
    cam.still_at(still);
    match cam.capture().await {
        Ok(f) => {
            let after = cam.stats();
            let discarded = after.stale_discarded - before.stale_discarded;
            let period = cam.frame_period();
            r.check(
                "stale frames discarded",
                discarded >= 1 && f.meta.timestamp - period >= still - 1e-6,
                format!(
                    "{discarded} discarded; returned frame stamped {:.3} s after still (frame period {:.3} s)",
                    f.meta.timestamp - still,
                    period
                ),
            );
        }
        Err(e) => {
            r.check("stale frames discarded", false, e.to_string());
        }
    }

    // Gain: set, read back, report; out-of-range requests are clamped and reported.
    match cam.control_info(cid::GAIN) {
        Ok(Some(info)) => {
            let unity = info.default.max(1) as f64;
            for want in [1.5, 1000.0] {
                let cfg = CameraConfig {
                    gain: want,
                    ..ask.clone()
                };
                match cam.configure(&cfg).await {
                    Ok(a) => {
                        let raw = cam.control(cid::GAIN).unwrap_or(i32::MIN);
                        let expect = info.nearest(want * unity) as f64 / unity;
                        r.check(
                            format!("gain {want} set+readback"),
                            (a.gain - expect).abs() < 1e-9 && raw as f64 / unity == a.gain,
                            format!(
                                "applied {:.3} (raw {raw}, range {}..{}, unity raw {})",
                                a.gain, info.minimum, info.maximum, info.default
                            ),
                        );
                    }
                    Err(e) => {
                        r.check(format!("gain {want} set+readback"), false, e.to_string());
                    }
                }
            }
            let auto = cam.control(cid::AUTOGAIN);
            r.check("autogain off", matches!(auto, Ok(0) | Err(_)), format!("{auto:?}"));
        }
        Ok(None) => r.row("gain set+readback", "SKIP", "device has no V4L2_CID_GAIN"),
        Err(e) => {
            r.check("gain set+readback", false, e.to_string());
        }
    }

    // Exposure: vivid has no exposure control; strict mode must refuse, lenient mode must
    // report the frame period (an upper bound), never the unapplied request.
    match cam.control_info(cid::EXPOSURE_ABSOLUTE) {
        Ok(Some(info)) => {
            let cfg = CameraConfig {
                exposure: 0.02,
                ..ask.clone()
            };
            match cam.configure(&cfg).await {
                Ok(a) => {
                    let raw = cam.control(cid::EXPOSURE_ABSOLUTE).unwrap_or(-1);
                    r.check(
                        "exposure set+readback",
                        (a.exposure - raw as f64 * 1e-4).abs() < 1e-12,
                        format!(
                            "applied {} s (raw {raw}, range {}..{})",
                            a.exposure, info.minimum, info.maximum
                        ),
                    );
                }
                Err(e) => {
                    r.check("exposure set+readback", false, e.to_string());
                }
            }
        }
        Ok(None) => {
            cam.set_require_exposure(true);
            let strict = cam.configure(&ask).await;
            r.check(
                "exposure: absent -> strict error",
                matches!(&strict, Err(DeviceError::Rejected { command, .. }) if command.contains("EXPOSURE_ABSOLUTE")),
                match &strict {
                    Err(e) => e.to_string(),
                    Ok(_) => "configured without an exposure control".into(),
                },
            );
            cam.set_require_exposure(false);
            match cam.configure(&ask).await {
                Ok(a) => r.check(
                    "exposure: absent -> frame period",
                    (a.exposure - cam.frame_period()).abs() < 1e-12,
                    format!("reported {:.4} s (asked {} s)", a.exposure, ask.exposure),
                ),
                Err(e) => r.check("exposure: absent -> frame period", false, e.to_string()),
            };
        }
        Err(e) => {
            r.check("exposure control query", false, e.to_string());
        }
    }
    let _ = applied;

    if is_vivid {
        // Stall: vivid drops every buffer; capture must time out cleanly, then recover.
        cam.set_timeout(Duration::from_millis(1500));
        let set = cam.set_control(VIVID_PERC_DROPPED, 100);
        let t = Instant::now();
        let res = cam.capture().await;
        let took = t.elapsed().as_secs_f64();
        r.fault(
            "vivid stall (100 % buffers dropped) -> Timeout",
            set == Ok(100)
                && matches!(&res, Err(DeviceError::Timeout { command, .. }) if command.contains("VIDIOC_DQBUF")),
            match &res {
                Err(e) => format!("typed error: {e} (after {took:.2} s)"),
                Ok(f) => format!("got frame seq {}", f.meta.sequence),
            },
        );
        let _ = cam.set_control(VIVID_PERC_DROPPED, 0);
        cam.set_timeout(Duration::from_secs(5));
        match cam.capture().await {
            Ok(f) => r.fault(
                "vivid stall cleared -> next capture",
                true,
                format!("recovered: frame seq {}", f.meta.sequence),
            ),
            Err(e) => r.fault("vivid stall cleared -> next capture", false, e.to_string()),
        };

        // Half the buffers dropped by the driver: every capture still returns a frame (the
        // backend waits for the next one), and the gaps show in the sequence numbers.
        let before = cam.stats();
        let set = cam.set_control(VIVID_PERC_DROPPED, 50);
        let mut seqs = Vec::new();
        let mut failed = None;
        for _ in 0..8 {
            match cam.capture().await {
                Ok(f) => seqs.push(f.meta.sequence),
                Err(e) => {
                    failed = Some(e);
                    break;
                }
            }
        }
        let _ = cam.set_control(VIVID_PERC_DROPPED, 0);
        let gaps = seqs.windows(2).filter(|w| w[1] > w[0] + 1).count();
        let dropped = cam.stats().dropped_by_driver - before.dropped_by_driver;
        r.fault(
            "vivid 50 % buffers dropped -> frames still delivered",
            set == Ok(50) && failed.is_none() && seqs.windows(2).all(|w| w[1] > w[0]),
            match &failed {
                Some(e) => format!("capture failed: {e}"),
                None => format!(
                    "{} frames, {gaps} sequence gap(s), {dropped} counted dropped by driver",
                    seqs.len()
                ),
            },
        );

        // A buffer flagged V4L2_BUF_FLAG_ERROR is skipped, the next good one returned.
        let before = cam.stats().corrupt_discarded;
        let pressed = cam.press(VIVID_DQBUF_ERROR);
        let res = cam.capture().await;
        let skipped = cam.stats().corrupt_discarded - before;
        r.fault(
            "vivid V4L2_BUF_FLAG_ERROR buffer -> skipped",
            pressed.is_ok() && res.is_ok() && skipped >= 1,
            format!(
                "{skipped} corrupt buffer(s) skipped, next good frame returned: {:?}",
                res.as_ref().map(|f| f.meta.sequence).map_err(|e| e.to_string())
            ),
        );

        // Unplug: vivid unregisters the device; capture must end in a typed error.
        let pressed = cam.press(VIVID_DISCONNECT);
        cam.set_timeout(Duration::from_secs(2));
        let res = cam.capture().await;
        r.fault(
            "vivid disconnect -> Disconnected",
            pressed.is_ok() && matches!(res, Err(DeviceError::Disconnected { .. })),
            match &res {
                Err(e) => format!("typed error: {e}"),
                Ok(f) => format!("got frame seq {}", f.meta.sequence),
            },
        );
    } else {
        r.row(
            "stall / corrupt / disconnect",
            "SKIP",
            "needs vivid's fault-injection controls",
        );
    }
    let s = cam.stats();
    r.row(
        "stats",
        "INFO",
        format!(
            "frames {} stale {} corrupt {} dropped-by-driver {} timeouts {}",
            s.frames, s.stale_discarded, s.corrupt_discarded, s.dropped_by_driver, s.timeouts
        ),
    );
    finish(&r, t0);
}

fn finish(r: &Report, t0: Instant) -> ! {
    for (fault, outcome) in &r.faults {
        println!("faults: {fault:<58} | {:<5} | {outcome}", "n/a");
    }
    let (pass, fail, skip) = (r.count("PASS"), r.count("FAIL"), r.count("SKIP"));
    println!(
        "V4L2_CHECK pass={pass} fail={fail} skip={skip} seconds={:.1}",
        t0.elapsed().as_secs_f64()
    );
    std::process::exit(if fail == 0 && pass > 0 { 0 } else { 1 });
}
