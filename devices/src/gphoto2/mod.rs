//! DSLR and mirrorless camera backend (cargo feature `gphoto2`): still cameras through
//! libgphoto2 (the `gphoto2` crate over the system library, Debian `libgphoto2-dev`).
//!
//! What a measurement needs from a still camera, and how it is obtained:
//! - **Exposure from the camera's own choices**: a still camera offers a list of shutter
//!   speeds (`shutterspeed`: "1/250", "0.1000s", "30", "Bulb"), not a continuous range.
//!   `configure` picks the choice nearest the asked exposure (on a log scale: one stop
//!   either way counts the same), sets it, reads it back, and returns the read-back
//!   choice parsed to seconds ([`parse_shutter`]); every frame carries that value, and a
//!   different one from the asked is logged. Bulb and time are never chosen (their
//!   length is not the camera's to report).
//! - **Aperture and ISO** from the rig file ([`options`]), matched against the camera's
//!   own choices ([`pick_choice`]); a value the camera does not offer is refused with the
//!   list it does offer, never replaced by a neighbour (aperture changes the image, not
//!   only its brightness).
//! - **Capture → download → delete → decode** ([`camera`]): the file is deleted from the
//!   card after the download (a long run would fill it), then decoded. JPEGs are
//!   display-referred sRGB: they are linearised with the sRGB curve ([`srgb_to_linear16`])
//!   into 16-bit linear RGB, as the V4L2 backend does with its MJPEG frames, so the rest
//!   of gonio sees linear values. A camera's picture style bends its JPEG tone curve away
//!   from pure sRGB: a radiometric calibration (`gonio calibrate response`) measures the
//!   residual; a raw file would avoid it but raw decoding is not done yet (the frame is
//!   refused with a message to set the camera to JPEG).
//! - **Errors** ([`classify`], [`device_error`]): libgphoto2's results are mapped to
//!   gonio's typed [`DeviceError`]s, so the capture policy can retry a busy or timed-out
//!   camera and stop on one that is gone.
//! - **Time limits** ([`wait_until`]): every libgphoto2 call has a deadline (the option
//!   `timeout_s`; a capture gets it plus its exposure for capture, download and delete
//!   together). A call that has not answered by then is cancelled and becomes a
//!   [`DeviceError::Timeout`] naming the camera, the call and the limit: a camera that
//!   stops answering never hangs a run, and the camera's lock is released.
//!
//! [`options`] and everything in this file need no library and are built and tested in
//! every build; [`camera`] (the device itself) only with the feature.

#[cfg(feature = "gphoto2")]
pub mod camera;
pub mod options;

#[cfg(feature = "gphoto2")]
pub use camera::Gphoto2Camera;
pub use options::Gphoto2Options;

use crate::DeviceError;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll, Waker};
use std::time::{Duration, Instant};

/// The config widget of the shutter speed (every PTP camera driver of libgphoto2 2.5).
pub const SHUTTER_KEY: &str = "shutterspeed";
/// The config widgets of the aperture, in the order tried (Nikon, Sony and the PTP generic
/// driver say `f-number`, Canon EOS `aperture`).
pub const APERTURE_KEYS: [&str; 2] = ["f-number", "aperture"];
/// The config widget of the ISO speed.
pub const ISO_KEYS: [&str; 2] = ["iso", "isospeed"];

/// A shutter-speed choice as the camera names it, in seconds, or why it is not one gonio
/// can use.
///
/// Accepts the forms libgphoto2's drivers write: fractions ("1/250", "1/250s"), decimals
/// with or without a unit ("0.1000s", "0.3", "2.5s", Sony's `2.5"`), whole seconds
/// ("30"). Refuses "Bulb"/"Time" (the exposure would be gonio's timing, not the camera's)
/// and anything else (an error naming the choice).
pub fn parse_shutter(choice: &str) -> Result<f64, String> {
    let s = choice.trim();
    let lower = s.to_ascii_lowercase();
    if lower.contains("bulb") || lower == "time" || lower.contains("auto") {
        return Err(format!(
            "shutter speed \"{choice}\" is not a fixed exposure (bulb, time and auto are never chosen)"
        ));
    }
    let body = lower.trim_end_matches(['s', '"']).trim_end_matches("sec").trim();
    let value = match body.split_once('/') {
        Some((num, den)) => {
            let n: f64 = num.trim().parse().map_err(|_| not_a_speed(choice))?;
            let d: f64 = den.trim().parse().map_err(|_| not_a_speed(choice))?;
            n / d
        }
        None => body.parse::<f64>().map_err(|_| not_a_speed(choice))?,
    };
    if value.is_finite() && value > 0.0 {
        Ok(value)
    } else {
        Err(not_a_speed(choice))
    }
}

fn not_a_speed(choice: &str) -> String {
    format!("shutter speed \"{choice}\" is not a number of seconds (expected forms: 1/250, 0.1000s, 30)")
}

/// The shutter-speed choice nearest `seconds` (by the ratio, log scale): its index in
/// `choices` and its value. Choices that are not fixed exposures are skipped. Fails with
/// the list when no choice is usable or `seconds` is not a positive number.
pub fn nearest_shutter(choices: &[String], seconds: f64) -> Result<(usize, f64), String> {
    if !(seconds.is_finite() && seconds > 0.0) {
        return Err(format!("exposure {seconds} s must be a positive number of seconds"));
    }
    choices
        .iter()
        .enumerate()
        .filter_map(|(i, c)| parse_shutter(c).ok().map(|v| (i, v)))
        .min_by(|a, b| {
            let da = (a.1 / seconds).ln().abs();
            let db = (b.1 / seconds).ln().abs();
            da.total_cmp(&db)
        })
        .ok_or_else(|| {
            format!(
                "the camera offers no fixed shutter speed ({}); set the camera's mode dial to M (manual)",
                list(choices)
            )
        })
}

/// A number in a choice or a rig-file value ("f/5.6" → 5.6, "ISO 200" → 200, "100") for
/// matching "8" with "f/8" and "8.0"; None when it has none or more than one.
fn number_in(s: &str) -> Option<f64> {
    let t = s.trim().to_ascii_lowercase();
    let t = t
        .trim_start_matches("iso")
        .trim_start_matches("f/")
        .trim_start_matches('f')
        .trim();
    t.parse::<f64>().ok().filter(|v| v.is_finite())
}

/// The camera's choice for the rig file's `wanted` value of the setting `what`: the
/// choice equal to it as text, or as a number ("8" matches "f/8", "200" matches "200");
/// else the refusal, with the choices the camera offers.
pub fn pick_choice(what: &str, choices: &[String], wanted: &str) -> Result<usize, String> {
    if let Some(i) = choices
        .iter()
        .position(|c| c.trim().eq_ignore_ascii_case(wanted.trim()))
    {
        return Ok(i);
    }
    if let Some(w) = number_in(wanted) {
        if let Some(i) = choices
            .iter()
            .position(|c| number_in(c).is_some_and(|v| (v - w).abs() <= 1e-9 * w.abs().max(1.0)))
        {
            return Ok(i);
        }
    }
    Err(format!(
        "the camera does not offer {what} \"{wanted}\"; it offers: {} (set camera.options.{what} to one of them)",
        list(choices)
    ))
}

fn list(choices: &[String]) -> String {
    if choices.is_empty() {
        "nothing".into()
    } else {
        choices.join(", ")
    }
}

/// sRGB display value (0 ..= 255) to linear 16-bit (0 ..= 65535) with the sRGB curve
/// (IEC 61966-2-1): what a JPEG's 8-bit values mean in light.
pub fn srgb_to_linear16(v: u8) -> u16 {
    let lin = crate::image::srgb_decode(v as f64 / 255.0);
    (lin * 65535.0).round().clamp(0.0, 65535.0) as u16
}

/// What a downloaded file is, from its name and first bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FileKind {
    Jpeg,
    /// A raw file (NEF, CR2, CR3, ARW, DNG, …): not decoded by this backend yet.
    Raw,
    Other,
}

/// Tell a JPEG (by its SOI marker) from a raw file (by its extension) and anything else.
pub fn file_kind(name: &str, data: &[u8]) -> FileKind {
    if data.starts_with(&[0xFF, 0xD8, 0xFF]) {
        return FileKind::Jpeg;
    }
    let ext = name
        .rsplit_once('.')
        .map(|(_, e)| e.to_ascii_lowercase())
        .unwrap_or_default();
    match ext.as_str() {
        "nef" | "nrw" | "cr2" | "cr3" | "crw" | "arw" | "srf" | "sr2" | "dng" | "raf" | "orf" | "rw2" | "pef" => {
            FileKind::Raw
        }
        _ => FileKind::Other,
    }
}

/// What kind of failure a libgphoto2 result is, so the capture policy can tell a glitch
/// worth a retry from a camera that is gone or a request it refuses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ErrorKind {
    /// The camera is unreachable: unplugged, powered off, USB claimed by another program.
    Disconnected,
    /// A transient condition: busy (still writing the last file), timed out, a read
    /// that failed once.
    Transient,
    /// The camera refused the request: bad parameter, not supported, no such file.
    Rejected,
    /// Anything else.
    Other,
}

/// Classify a libgphoto2 error by the name of the `gphoto2` crate's `ErrorKind` variant
/// (its `Debug` form: "Timeout", "IoUsbFind", …; the names are tied to libgphoto2's
/// `GP_ERROR_*` codes by that crate, and a test with the feature checks them).
pub fn classify(kind: &str) -> ErrorKind {
    match kind {
        "IoUsbFind" | "IoUsbClaim" | "IoLock" | "UnknownPort" | "ModelNotFound" | "Io" | "IoWrite"
        | "IoUsbClearHalt" => ErrorKind::Disconnected,
        "CameraBusy" | "Timeout" | "IoRead" | "CorruptedData" => ErrorKind::Transient,
        "BadParameters" | "NotSupported" | "FileNotFound" | "DirectoryNotFound" | "FileExists" | "DirectoryExists"
        | "PathNotAbsolute" | "NoSpace" | "FixedLimitExceeded" | "CameraError" | "IoUpdate" => ErrorKind::Rejected,
        _ => ErrorKind::Other,
    }
}

/// The typed error for a libgphoto2 failure of `command` on `device`.
pub fn device_error(device: &str, command: &str, kind: ErrorKind, message: &str) -> DeviceError {
    let (device, command) = (device.to_string(), command.to_string());
    match kind {
        ErrorKind::Disconnected => DeviceError::Disconnected {
            device,
            command,
            reason: format!(
                "{message} (is the camera on, connected by USB, and not claimed by another program such as \
                 gvfs-gphoto2-volume-monitor? gonio does not reconnect mid-run)"
            ),
        },
        // A busy or timed-out camera is a transient fault: the capture policy retries it.
        ErrorKind::Transient => DeviceError::Garbled {
            device,
            command,
            reply: message.to_string(),
        },
        ErrorKind::Rejected => DeviceError::Rejected {
            device,
            command,
            reason: message.to_string(),
        },
        ErrorKind::Other => DeviceError::Other {
            device,
            command,
            reason: message.to_string(),
        },
    }
}

/// When a libgphoto2 call must have answered: a call that has not by then ends in
/// [`DeviceError::Timeout`] ([`wait_until`]).
#[derive(Clone, Copy, Debug)]
pub struct Deadline {
    at: Instant,
    limit: Duration,
}

impl Deadline {
    /// `limit` from now.
    pub fn after(limit: Duration) -> Deadline {
        Deadline {
            at: Instant::now() + limit,
            limit,
        }
    }

    /// The whole time allowed (what a timeout reports).
    pub fn limit(&self) -> Duration {
        self.limit
    }
}

/// Wakes the thread that waits in [`wait_until`].
struct Unpark(std::thread::Thread);

impl std::task::Wake for Unpark {
    fn wake(self: Arc<Self>) {
        self.0.unpark();
    }
    fn wake_by_ref(self: &Arc<Self>) {
        self.0.unpark();
    }
}

/// Wait on this thread for `call` (a libgphoto2 call running on the `gphoto2` crate's
/// worker thread: its `Task` is a future) until `deadline`. A call that has not answered by
/// then is a [`DeviceError::Timeout`] naming `device`, `command` and the deadline's limit;
/// the call itself is left to the caller (to cancel it: libgphoto2 gives up at its next
/// progress check, and a call stuck in the USB stack keeps the worker thread until it
/// returns, so later calls time out too).
///
/// Why not the crate's own blocking wait: it has no limit, so a camera that stops answering
/// mid-capture (a USB hub resetting, a camera that fell asleep) would hang the run with the
/// camera's lock held. A call whose worker is gone (its channel closed without an answer)
/// never becomes ready and ends in the same timeout.
pub fn wait_until<F: Future + Unpin>(
    device: &str,
    command: &str,
    call: &mut F,
    deadline: Deadline,
) -> Result<F::Output, DeviceError> {
    let waker = Waker::from(Arc::new(Unpark(std::thread::current())));
    let mut cx = Context::from_waker(&waker);
    loop {
        if let Poll::Ready(out) = Pin::new(&mut *call).poll(&mut cx) {
            return Ok(out);
        }
        let now = Instant::now();
        if now >= deadline.at {
            return Err(DeviceError::Timeout {
                device: device.to_string(),
                command: command.to_string(),
                seconds: deadline.limit.as_secs_f64(),
            });
        }
        // Woken by the call's answer; spurious wake-ups only poll again.
        std::thread::park_timeout(deadline.at - now);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(v: &[&str]) -> Vec<String> {
        v.iter().map(|x| x.to_string()).collect()
    }

    #[test]
    fn shutter_choices_parse_to_seconds() {
        for (c, want) in [
            ("1/250", 0.004),
            ("1/250s", 0.004),
            ("0.1000s", 0.1),
            ("0.0001s", 0.0001),
            ("30", 30.0),
            ("2.5\"", 2.5),
            ("0.3", 0.3),
            (" 1/4000 ", 0.00025),
            ("10/13", 10.0 / 13.0),
        ] {
            let got = parse_shutter(c).unwrap_or_else(|e| panic!("{c}: {e}"));
            assert!((got - want).abs() <= 1e-12 * want, "{c}: {got} != {want}");
        }
        for bad in [
            "bulb", "Bulb", "Time", "auto", "", "1/0", "0", "-1/250", "x 1/200s", "fast",
        ] {
            assert!(parse_shutter(bad).is_err(), "{bad} accepted");
        }
        assert!(parse_shutter("Bulb").unwrap_err().contains("never chosen"));
        assert!(parse_shutter("fast").unwrap_err().contains("\"fast\""));
    }

    #[test]
    fn the_nearest_shutter_speed_is_chosen_on_a_log_scale() {
        let vusb = s(&[
            "1.0000s", "0.1000s", "0.0500s", "0.0200s", "0.0100s", "0.0050s", "0.0025s", "0.0012s", "0.0001s",
        ]);
        assert_eq!(nearest_shutter(&vusb, 0.1).unwrap(), (1, 0.1));
        assert_eq!(nearest_shutter(&vusb, 0.012).unwrap(), (4, 0.01));
        // 0.3 s: 0.1 is a ratio of 3, 1.0 of 3.33: 0.1 is nearer in stops.
        assert_eq!(nearest_shutter(&vusb, 0.3).unwrap().0, 1);
        assert_eq!(nearest_shutter(&vusb, 100.0).unwrap(), (0, 1.0));
        let nikon = s(&["Bulb", "30", "1/250", "1/200", "x 1/250"]);
        assert_eq!(nearest_shutter(&nikon, 0.0045).unwrap(), (3, 0.005));
        assert_eq!(nearest_shutter(&nikon, 60.0).unwrap(), (1, 30.0));
        assert!(nearest_shutter(&s(&["Bulb", "Auto"]), 0.1)
            .unwrap_err()
            .contains("Bulb, Auto"));
        assert!(nearest_shutter(&vusb, 0.0).is_err() && nearest_shutter(&vusb, f64::NAN).is_err());
    }

    #[test]
    fn aperture_and_iso_must_be_offered() {
        let f = s(&["f/2.8", "f/4", "f/5.6", "f/8"]);
        assert_eq!(pick_choice("aperture", &f, "f/8"), Ok(3));
        assert_eq!(pick_choice("aperture", &f, "8"), Ok(3));
        assert_eq!(pick_choice("aperture", &f, "5.6"), Ok(2));
        let e = pick_choice("aperture", &f, "f/11").unwrap_err();
        assert!(
            e.contains("\"f/11\"") && e.contains("f/2.8, f/4, f/5.6, f/8") && e.contains("camera.options.aperture"),
            "{e}"
        );
        let iso = s(&["Auto", "100", "200", "400"]);
        assert_eq!(pick_choice("iso", &iso, "200"), Ok(2));
        assert_eq!(pick_choice("iso", &iso, "ISO 400"), Ok(3));
        assert!(pick_choice("iso", &iso, "250").is_err());
        assert!(pick_choice("iso", &[], "100").unwrap_err().contains("offers: nothing"));
    }

    #[test]
    fn srgb_curve_end_points_and_knee() {
        assert_eq!(srgb_to_linear16(0), 0);
        assert_eq!(srgb_to_linear16(255), 65535);
        // 10/255 is on the linear segment: 10/255/12.92 of full scale.
        assert_eq!(
            srgb_to_linear16(10),
            ((10.0 / 255.0 / 12.92) * 65535.0f64).round() as u16
        );
        // Mid grey 118 is ≈ 18 % linear.
        assert!((srgb_to_linear16(118) as f64 / 65535.0 - 0.181).abs() < 0.002);
        assert!((1..=255u8).all(|v| srgb_to_linear16(v) > srgb_to_linear16(v - 1)));
    }

    #[test]
    fn files_are_told_apart() {
        assert_eq!(file_kind("GPH_0099.JPG", &[0xFF, 0xD8, 0xFF, 0xE0]), FileKind::Jpeg);
        assert_eq!(file_kind("DSC_0001.NEF", b"MM\0*"), FileKind::Raw);
        assert_eq!(file_kind("IMG_0001.cr3", b"\0\0\0\x18ftyp"), FileKind::Raw);
        assert_eq!(file_kind("MOV_0001.MOV", b"\0\0"), FileKind::Other);
    }

    #[test]
    fn errors_map_to_typed_device_errors() {
        assert_eq!(classify("IoUsbFind"), ErrorKind::Disconnected);
        assert_eq!(classify("CameraBusy"), ErrorKind::Transient);
        assert_eq!(classify("NotSupported"), ErrorKind::Rejected);
        assert_eq!(classify("Other"), ErrorKind::Other);
        let e = device_error(
            "gphoto2 Nikon",
            "capture",
            ErrorKind::Disconnected,
            "Could not find USB device",
        );
        assert!(
            matches!(e, DeviceError::Disconnected { .. }) && e.to_string().contains("capture"),
            "{e}"
        );
        assert!(device_error("c", "capture", ErrorKind::Transient, "busy").is_transient());
        assert!(!device_error("c", "f-number", ErrorKind::Rejected, "bad").is_transient());
    }

    /// A libgphoto2 call that never answers (a camera hung mid-capture, faked by a future
    /// that is never ready): the wait ends at its deadline with a typed timeout naming the
    /// camera, the call and the limit.
    #[test]
    fn a_call_that_never_answers_ends_in_a_timeout_naming_the_camera() {
        let mut hung = std::future::pending::<Result<Vec<u8>, String>>();
        let cam = "gphoto2 Nikon DSC D750 on usb:001,001";
        let e = wait_until(cam, "capture", &mut hung, Deadline::after(Duration::from_millis(30))).unwrap_err();
        match &e {
            DeviceError::Timeout {
                device,
                command,
                seconds,
            } => assert!(
                device == cam && command == "capture" && (seconds - 0.03).abs() < 1e-12,
                "{e:?}"
            ),
            other => panic!("not a timeout: {other:?}"),
        }
        assert_eq!(
            e.to_string(),
            "gphoto2 Nikon DSC D750 on usb:001,001: `capture` timed out after 0.030 s"
        );
        // The capture policy retries it (a timeout is transient).
        assert!(e.is_transient());
    }

    /// An answer from another thread (as the `gphoto2` crate's worker thread answers) wakes
    /// the wait and is returned.
    #[test]
    fn an_answer_from_the_worker_thread_is_returned() {
        struct Slot {
            value: Option<u32>,
            waker: Option<Waker>,
        }
        struct Answer(Arc<std::sync::Mutex<Slot>>);
        impl Future for Answer {
            type Output = u32;
            fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<u32> {
                let mut s = self.0.lock().unwrap();
                match s.value.take() {
                    Some(v) => Poll::Ready(v),
                    None => {
                        s.waker = Some(cx.waker().clone());
                        Poll::Pending
                    }
                }
            }
        }
        let slot = Arc::new(std::sync::Mutex::new(Slot {
            value: None,
            waker: None,
        }));
        let worker = {
            let slot = slot.clone();
            std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(20));
                let mut s = slot.lock().unwrap();
                s.value = Some(42);
                if let Some(w) = s.waker.take() {
                    w.wake();
                }
            })
        };
        let mut answer = Answer(slot);
        let got = wait_until(
            "cam",
            "download",
            &mut answer,
            Deadline::after(Duration::from_secs(600)),
        );
        worker.join().unwrap();
        assert_eq!(got, Ok(42));
    }
}
