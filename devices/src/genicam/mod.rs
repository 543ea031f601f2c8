//! GenICam camera backend (cargo feature `genicam`): GigE Vision and USB3 Vision cameras
//! through Aravis (the `aravis` crate over the system libaravis 0.8, Debian
//! `libaravis-dev`).
//!
//! What a measurement needs from a machine-vision camera, and how it is obtained:
//! - **Exposure read back** ([`camera`]): `ExposureTime` (SFNC) or, on older cameras,
//!   `ExposureTimeAbs` ([`exposure_feature`]), auto exposure off; the value the camera
//!   reports after the write is what `configure` returns and what every frame carries, so
//!   an HDR bracket checks the exposure the sensor used, not the one asked for (as with
//!   V4L2). Each capture reads it again: a camera whose exposure changed behind gonio's
//!   back fails the capture instead of storing a frame with the wrong exposure.
//! - **Gain** in dB (`Gain`, 1 = 0 dB) or raw (`GainRaw`, with the rig file's
//!   `gain_unity_raw`), read back likewise.
//! - **Pixel formats** ([`pixel`]): Mono8/16, RGB8 and Bayer RG/BG/GR/GB 8/16 (bilinear
//!   demosaicing) become gonio's interleaved RGB frame with the format's bit depth. Each
//!   buffer's own format and size are checked against the configured ones.
//! - **Software trigger**: the camera exposes when `capture` triggers it, after the rig is
//!   still, so no frame shows motion; buffers that arrived before the trigger are
//!   discarded.
//! - **Timeouts and recovery**: a frame that does not arrive within `timeout_s` is a
//!   [`DeviceError::Timeout`](crate::DeviceError) (the capture policy may retry: the next
//!   capture drains the stream and triggers again); an incomplete frame (lost packets) is
//!   [`DeviceError::Garbled`](crate::DeviceError), also retried; a camera that stops
//!   answering is [`DeviceError::Disconnected`](crate::DeviceError), never a hang.
//!
//! [`pixel`], [`options`] and the decision functions below need no library and are built
//! and tested in every build; [`camera`] (the device itself) only with the feature.

#[cfg(feature = "genicam")]
pub mod camera;
pub mod options;
pub mod pixel;

#[cfg(feature = "genicam")]
pub use camera::{CaptureStats, GenicamCamera};
pub use options::GenicamOptions;
pub use pixel::{Cfa, PixelFormat};

use crate::DeviceError;

/// The exposure-time feature to use: SFNC's `ExposureTime` when the camera has it, else
/// the older `ExposureTimeAbs` (GigE Vision cameras of the 2000s, Aravis' fake camera).
/// Both are in microseconds. None: the camera has no settable exposure time.
pub fn exposure_feature(available: impl Fn(&str) -> bool) -> Option<&'static str> {
    ["ExposureTime", "ExposureTimeAbs"].into_iter().find(|f| available(f))
}

/// How a gain is set on a camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum GainControl {
    /// `Gain` in dB: gonio's gain g is 20·log10(g) dB.
    Decibel { min_db: f64, max_db: f64 },
    /// `GainRaw`, linear with `unity` raw meaning gain 1 (None: only gain 1 is possible,
    /// set as the raw minimum).
    Raw { min: i64, max: i64, unity: Option<i64> },
    /// No gain feature: the sensor works at its fixed gain, reported as 1.
    None,
}

impl GainControl {
    /// The value to write for gain `gain` (dB or raw), clamped into the feature's range,
    /// or why it cannot be set. The caller reads the feature back and reports
    /// [`GainControl::gain_of`] that value.
    pub fn target(&self, gain: f64) -> Result<f64, String> {
        if !(gain.is_finite() && gain > 0.0) {
            return Err(format!("gain {gain} must be a positive number"));
        }
        match *self {
            GainControl::Decibel { min_db, max_db } => Ok((20.0 * gain.log10()).clamp(min_db, max_db)),
            GainControl::Raw {
                min,
                max,
                unity: Some(u),
            } => Ok(((gain * u as f64).round() as i64).clamp(min, max) as f64),
            GainControl::Raw { min, unity: None, .. } if (gain - 1.0).abs() < 1e-9 => Ok(min as f64),
            GainControl::Raw { unity: None, .. } => Err(format!(
                "gain {gain}: the camera's gain is GainRaw with no known unit; set camera.options.gain_unity_raw \
                 (the raw value meaning gain 1) or ask for gain 1"
            )),
            GainControl::None if (gain - 1.0).abs() < 1e-9 => Ok(1.0),
            GainControl::None => Err(format!(
                "gain {gain}: the camera has no Gain or GainRaw feature; set the rig file's gain to 1"
            )),
        }
    }

    /// gonio's gain for a value read back from the camera.
    pub fn gain_of(&self, value: f64) -> f64 {
        match *self {
            GainControl::Decibel { .. } => 10f64.powf(value / 20.0),
            GainControl::Raw { unity: Some(u), .. } => value / u as f64,
            GainControl::Raw { unity: None, .. } | GainControl::None => 1.0,
        }
    }
}

/// What kind of failure an Aravis error is, from its GLib domain and code (libaravis'
/// `ArvDeviceError` and `ArvGcError` enums), so the capture policy can tell a glitch worth
/// a retry from a camera that is gone or a setting it refuses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ErrorKind {
    /// The camera is unreachable: not connected, transfer failed, or a control command
    /// went unanswered through all of Aravis' own retries.
    Disconnected,
    /// The camera (or its GenICam description) refused the request: no such feature, out
    /// of range, read-only, access denied, another controller owns it.
    Rejected,
    /// Anything else.
    Other,
}

/// libaravis' `ArvDeviceError` codes (arvdevice.h, 0.8).
mod device_error {
    pub const WRONG_FEATURE: i32 = 0;
    pub const FEATURE_NOT_FOUND: i32 = 1;
    pub const NOT_CONNECTED: i32 = 2;
    pub const TRANSFER_ERROR: i32 = 4;
    pub const TIMEOUT: i32 = 5;
    pub const NOT_FOUND: i32 = 6;
    pub const INVALID_PARAMETER: i32 = 7;
    pub const NOT_CONTROLLER: i32 = 10;
    /// PROTOCOL_ERROR_NOT_IMPLEMENTED ..= PROTOCOL_ERROR_BUSY.
    pub const PROTOCOL_REFUSALS: std::ops::RangeInclusive<i32> = 12..=18;
}

/// Classify an Aravis error by its GLib domain (`arv-device-error-quark`,
/// `arv-gc-error-quark`) and code.
pub fn classify(domain: &str, code: i32) -> ErrorKind {
    use device_error::*;
    if domain.contains("arv-gc-error") {
        // Every ArvGcError is about the GenICam description or a value: out of range,
        // read-only, no such node or enum entry.
        return ErrorKind::Rejected;
    }
    if domain.contains("arv-device-error") {
        return match code {
            NOT_CONNECTED | TRANSFER_ERROR | TIMEOUT => ErrorKind::Disconnected,
            WRONG_FEATURE | FEATURE_NOT_FOUND | NOT_FOUND | INVALID_PARAMETER | NOT_CONTROLLER => ErrorKind::Rejected,
            c if PROTOCOL_REFUSALS.contains(&c) => ErrorKind::Rejected,
            _ => ErrorKind::Other,
        };
    }
    ErrorKind::Other
}

/// The typed error for an Aravis failure of `command` on `device`.
pub fn device_error(device: &str, command: &str, kind: ErrorKind, message: &str) -> DeviceError {
    let (device, command) = (device.to_string(), command.to_string());
    match kind {
        ErrorKind::Disconnected => DeviceError::Disconnected {
            device,
            command,
            reason: format!("{message} (is the camera powered and on the network? gonio does not reconnect mid-run)"),
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

/// What a delivered buffer says about itself, for [`check_buffer`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BufferInfo {
    /// Whether Aravis received the whole frame (`ARV_BUFFER_STATUS_SUCCESS`).
    pub complete: bool,
    pub pfnc_code: u32,
    pub width: usize,
    pub height: usize,
}

/// Whether a buffer may become a frame with the configured metadata: complete, in the
/// configured pixel format and size. An incomplete frame is [`DeviceError::Garbled`]
/// (retried under the capture policy: the next trigger usually gets a whole one); a
/// different format or size means the camera was reconfigured behind gonio's back, which
/// a retry would not mend: [`DeviceError::Rejected`], and the frame is never stored.
pub fn check_buffer(
    device: &str,
    status: &str,
    got: BufferInfo,
    format: PixelFormat,
    size: (usize, usize),
) -> Result<(), DeviceError> {
    if !got.complete {
        return Err(DeviceError::Garbled {
            device: device.to_string(),
            command: "capture (stream buffer)".into(),
            reply: format!("incomplete frame: {status}"),
        });
    }
    if got.pfnc_code != format.pfnc_code() {
        let name = PixelFormat::from_pfnc_code(got.pfnc_code).map_or(format!("{:#010x}", got.pfnc_code), |f| f.name());
        return Err(DeviceError::Rejected {
            device: device.to_string(),
            command: "capture (stream buffer)".into(),
            reason: format!(
                "the frame is {name} but the camera was configured for {format}: its pixel format changed \
                 during the run (another program? reconfigure the camera and restart the run)"
            ),
        });
    }
    if (got.width, got.height) != size {
        return Err(DeviceError::Rejected {
            device: device.to_string(),
            command: "capture (stream buffer)".into(),
            reason: format!(
                "the frame is {} × {} but the camera was configured for {} × {}: its region changed during the run",
                got.width, got.height, size.0, size.1
            ),
        });
    }
    Ok(())
}

/// The frame's sequence number from the buffer's frame id. GigE Vision 1.x block ids are
/// 16 bits and skip 0 (65535 is followed by 1); gonio's `FrameMeta::sequence` increases by
/// one per frame for the whole run, so a wrap is unwrapped against the previous frame
/// (`prev`: its raw id and sequence). Wider ids (GigE Vision 2, USB3 Vision) pass through.
pub fn unwrap_frame_id(prev: Option<(u64, u64)>, raw: u64) -> u64 {
    match prev {
        Some((prev_raw, prev_seq)) if prev_raw <= 0xFFFF && raw <= 0xFFFF => {
            let step = if raw > prev_raw {
                raw - prev_raw
            } else {
                raw + 0xFFFF - prev_raw
            };
            prev_seq + step
        }
        _ => raw,
    }
}

/// Whether a read-back value still equals the applied one (to a relative 1e-6: the
/// features are floats, written once and read back through the same converter).
pub fn unchanged(applied: f64, read_back: f64) -> bool {
    (applied - read_back).abs() <= 1e-6 * applied.abs().max(1e-12)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exposure_feature_prefers_sfnc_and_falls_back_to_abs() {
        assert_eq!(
            exposure_feature(|f| f == "ExposureTime" || f == "ExposureTimeAbs"),
            Some("ExposureTime")
        );
        assert_eq!(exposure_feature(|f| f == "ExposureTimeAbs"), Some("ExposureTimeAbs"));
        assert_eq!(exposure_feature(|_| false), None);
    }

    #[test]
    fn gain_maps_to_decibels_or_raw_and_back() {
        let db = GainControl::Decibel {
            min_db: 0.0,
            max_db: 24.0,
        };
        assert!((db.target(2.0).unwrap() - 6.0206).abs() < 1e-3);
        assert_eq!(db.target(1.0).unwrap(), 0.0);
        // Clamped into the range: the read-back then tells the truth.
        assert_eq!(db.target(0.5).unwrap(), 0.0);
        assert!((db.gain_of(6.020_599_913) - 2.0).abs() < 1e-9);
        let raw = GainControl::Raw {
            min: 0,
            max: 10,
            unity: Some(4),
        };
        assert_eq!(raw.target(1.5).unwrap(), 6.0);
        assert_eq!(raw.target(100.0).unwrap(), 10.0);
        assert_eq!(raw.gain_of(6.0), 1.5);
        let unknown = GainControl::Raw {
            min: 0,
            max: 10,
            unity: None,
        };
        assert_eq!(unknown.target(1.0).unwrap(), 0.0);
        assert!(unknown.target(2.0).unwrap_err().contains("gain_unity_raw"));
        assert!(GainControl::None.target(2.0).is_err());
        assert!(db.target(f64::NAN).is_err() && db.target(0.0).is_err());
    }

    #[test]
    fn aravis_errors_classify_by_domain_and_code() {
        let dev = "arv-device-error-quark";
        assert_eq!(classify(dev, device_error::TIMEOUT), ErrorKind::Disconnected);
        assert_eq!(classify(dev, device_error::NOT_CONNECTED), ErrorKind::Disconnected);
        assert_eq!(classify(dev, device_error::FEATURE_NOT_FOUND), ErrorKind::Rejected);
        assert_eq!(classify(dev, 15 /* write protect */), ErrorKind::Rejected);
        assert_eq!(classify(dev, 11 /* unknown */), ErrorKind::Other);
        assert_eq!(
            classify("arv-gc-error-quark", 4 /* out of range */),
            ErrorKind::Rejected
        );
        assert_eq!(classify("g-io-error-quark", 24), ErrorKind::Other);
        let e = device_error("cam", "TriggerSoftware", ErrorKind::Disconnected, "timeout");
        assert!(
            matches!(e, DeviceError::Disconnected { .. }) && e.to_string().contains("TriggerSoftware"),
            "{e}"
        );
        assert!(!e.is_transient() || matches!(e, DeviceError::Disconnected { .. }));
    }

    #[test]
    fn buffers_with_wrong_metadata_never_pass() {
        let fmt = PixelFormat::Bayer(Cfa::Rggb, 8);
        let ok = BufferInfo {
            complete: true,
            pfnc_code: fmt.pfnc_code(),
            width: 64,
            height: 48,
        };
        assert!(check_buffer("cam", "success", ok, fmt, (64, 48)).is_ok());
        let e = check_buffer(
            "cam",
            "missing packets",
            BufferInfo { complete: false, ..ok },
            fmt,
            (64, 48),
        )
        .unwrap_err();
        assert!(
            matches!(e, DeviceError::Garbled { .. }) && e.to_string().contains("missing packets"),
            "{e}"
        );
        let e = check_buffer(
            "cam",
            "success",
            BufferInfo {
                pfnc_code: PixelFormat::Mono8.pfnc_code(),
                ..ok
            },
            fmt,
            (64, 48),
        )
        .unwrap_err();
        assert!(matches!(e, DeviceError::Rejected { .. }), "{e}");
        assert!(
            e.to_string().contains("Mono8") && e.to_string().contains("BayerRG8"),
            "{e}"
        );
        let e = check_buffer("cam", "success", BufferInfo { width: 32, ..ok }, fmt, (64, 48)).unwrap_err();
        assert!(e.to_string().contains("32 × 48"), "{e}");
    }

    #[test]
    fn sixteen_bit_block_ids_are_unwrapped() {
        assert_eq!(unwrap_frame_id(None, 65_534), 65_534);
        assert_eq!(unwrap_frame_id(Some((65_534, 65_534)), 65_535), 65_535);
        // 65535 is followed by 1 (0 is not a valid block id).
        assert_eq!(unwrap_frame_id(Some((65_535, 65_535)), 1), 65_536);
        assert_eq!(unwrap_frame_id(Some((1, 65_536)), 3), 65_538);
        // A later wrap keeps counting from the unwrapped sequence.
        assert_eq!(unwrap_frame_id(Some((65_535, 131_070)), 1), 131_071);
        // 64-bit ids pass through.
        assert_eq!(unwrap_frame_id(Some((1 << 40, 1 << 40)), (1 << 40) + 1), (1 << 40) + 1);
    }

    #[test]
    fn read_back_comparison_is_relative() {
        assert!(unchanged(0.01, 0.01));
        assert!(unchanged(10_000.0, 10_000.000_001));
        assert!(!unchanged(0.01, 0.0123));
    }
}
