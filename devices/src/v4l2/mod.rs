//! V4L2 camera backend (cargo feature `v4l2`): any Linux camera with a video-capture node
//! (USB UVC webcams, many industrial cameras, capture cards, the kernel's `vivid`).
//!
//! What a measurement needs from a consumer video API, and how it is obtained:
//! - **Format negotiation**: the preferred formats ([`PixelFormat::PREFERENCE`], or the rig
//!   file's list) are intersected with what the device enumerates; `VIDIOC_S_FMT` is asked
//!   for the configured size and whatever the driver returns (size, `bytesperline`,
//!   `sizeimage`, colorimetry) is used and reported back in the [`CameraConfig`].
//! - **mmap streaming with a timeout** ([`stream`]): a stalled camera ends in
//!   [`DeviceError::Timeout`] naming the camera and `VIDIOC_DQBUF`, an unplugged one in
//!   [`DeviceError::Disconnected`], never in a hang or a panic.
//! - **Manual exposure and gain** ([`controls`]): auto modes are switched off, values are
//!   set, read back, and the read-back values are what `configure` returns.
//! - **No motion blur**: a camera streams continuously, so the queue holds frames exposed
//!   while the rig was still moving. The engine calls [`Camera::rig_still`] when all axes
//!   have settled; `capture` then discards every frame whose exposure started before that
//!   instant (driver timestamps are `CLOCK_MONOTONIC`).
//! - **Linear values** ([`format`]): sRGB/BT.709 transfer and BT.601/709 Y'CbCr are undone;
//!   frames carry 16-bit linear RGB (`bit_depth` 16).
//!
//! Device access is blocking; the async trait methods run it on tokio's blocking pool.

pub mod controls;
pub mod format;
pub mod stream;

use std::io;
use std::os::raw::c_void;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use async_trait::async_trait;
use serde::{Deserialize, Serialize};
use v4l::v4l_sys::v4l2_format;
use v4l::video::Capture;

use crate::camera::{Camera, CameraConfig, Frame, FrameMeta};
use crate::DeviceError;
pub use format::{Colorimetry, Layout, PixelFormat};
use stream::{BufferMeta, Dequeued, MmapStream};

/// How to open and drive one V4L2 camera.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct V4l2Options {
    /// Device node, e.g. `/dev/video0`.
    pub device: PathBuf,
    /// Name used in logs and errors.
    pub name: String,
    /// Acceptable formats in order of preference (empty: [`PixelFormat::PREFERENCE`]).
    #[serde(skip)]
    pub formats: Vec<PixelFormat>,
    /// Longest wait for one fresh frame before `capture` fails with a timeout.
    pub timeout: Duration,
    /// Number of mmap buffers to request (the driver may grant another number).
    pub buffers: u32,
    /// Fail `configure` if the camera has no manual exposure time control. Off: such a
    /// camera (a webcam, `vivid`) reports its frame period as the exposure (an upper bound).
    pub require_exposure: bool,
    /// Raw `V4L2_CID_GAIN` value meaning unity gain. V4L2 gain units are driver specific;
    /// by default the control's default value is taken as unity.
    pub gain_unity_raw: Option<i32>,
    /// Frame rate to ask for (Hz; None keeps the driver's). A fresh frame after the rig
    /// stops takes up to two frame periods, so a slow default rate costs time per image.
    pub frame_rate: Option<f64>,
}

impl V4l2Options {
    pub fn new(device: impl Into<PathBuf>) -> Self {
        let device = device.into();
        V4l2Options {
            name: format!("camera {}", device.display()),
            device,
            formats: Vec::new(),
            timeout: Duration::from_secs(2),
            buffers: 4,
            require_exposure: false,
            gain_unity_raw: None,
            frame_rate: None,
        }
    }
}

impl V4l2Options {
    /// Options from a rig file's `[camera]` table with `backend = "v4l2"`: `device`
    /// (default `/dev/video0`), `formats` (names as in [`PixelFormat::parse`]),
    /// `timeout_s`, `buffers`, `require_exposure`, `gain_unity_raw`. Unknown keys are
    /// refused so that a typo does not silently fall back to a default.
    pub fn from_rig(spec: &crate::rig::CameraSpec) -> Result<V4l2Options, DeviceError> {
        let bad = |key: &str, reason: String| DeviceError::Rejected {
            device: "camera".into(),
            command: format!("rig file camera.options.{key}"),
            reason,
        };
        let o = &spec.options;
        let device = match o.get("device") {
            None => "/dev/video0".to_string(),
            Some(v) => v
                .as_str()
                .ok_or_else(|| bad("device", format!("{v}: must be a path string")))?
                .to_string(),
        };
        let mut opts = V4l2Options::new(device);
        for (key, v) in o {
            match key.as_str() {
                "device" => {}
                "formats" => {
                    let list = v
                        .as_array()
                        .ok_or_else(|| bad(key, format!("{v}: must be an array of names")))?;
                    opts.formats = list
                        .iter()
                        .map(|f| {
                            f.as_str().and_then(PixelFormat::parse).ok_or_else(|| {
                                bad(
                                    key,
                                    format!("{f}: use \"rgb24\", \"bgr24\", \"yuyv\", \"grey\" or \"mjpeg\""),
                                )
                            })
                        })
                        .collect::<Result<_, _>>()?;
                }
                "timeout_s" => {
                    let t = v
                        .as_float()
                        .or_else(|| v.as_integer().map(|i| i as f64))
                        .filter(|t| t.is_finite() && *t > 0.0 && *t < 3600.0)
                        .ok_or_else(|| bad(key, format!("{v}: must be seconds in (0, 3600)")))?;
                    opts.timeout = Duration::from_secs_f64(t);
                }
                "buffers" => {
                    opts.buffers = v
                        .as_integer()
                        .filter(|n| (2..=32).contains(n))
                        .ok_or_else(|| bad(key, format!("{v}: must be an integer in 2..=32")))?
                        as u32;
                }
                "require_exposure" => {
                    opts.require_exposure = v
                        .as_bool()
                        .ok_or_else(|| bad(key, format!("{v}: must be true or false")))?;
                }
                "frame_rate" => {
                    let f = v
                        .as_float()
                        .or_else(|| v.as_integer().map(|i| i as f64))
                        .filter(|f| f.is_finite() && *f > 0.0 && *f <= 10_000.0)
                        .ok_or_else(|| bad(key, format!("{v}: must be frames per second in (0, 10000]")))?;
                    opts.frame_rate = Some(f);
                }
                "gain_unity_raw" => {
                    opts.gain_unity_raw = Some(
                        v.as_integer()
                            .filter(|n| *n >= 1 && *n <= i32::MAX as i64)
                            .ok_or_else(|| bad(key, format!("{v}: must be a positive integer")))?
                            as i32,
                    );
                }
                // The engine's capture policy (gonio `engine::capture`), validated there.
                "capture_timeout_s" | "capture_retries" | "saturation" | "saturation_fraction" => {}
                // Whether the readout overlaps the next move: validated (and refused when
                // true, which V4L2 cannot do) by `CameraSpec::readout_overlaps_motion`.
                "overlap_readout" => {}
                other => {
                    return Err(bad(
                        other,
                        "unknown option (device, formats, timeout_s, buffers, frame_rate, require_exposure, gain_unity_raw)".into(),
                    ))
                }
            }
        }
        Ok(opts)
    }
}

/// Counters since the camera was opened, for diagnostics and the vivid check.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct CaptureStats {
    /// Frames returned by `capture`.
    pub frames: u64,
    /// Frames discarded because their exposure started before the rig became still.
    pub stale_discarded: u64,
    /// Buffers the driver flagged `V4L2_BUF_FLAG_ERROR` (discarded).
    pub corrupt_discarded: u64,
    /// Gaps in the driver's sequence numbers (frames the driver dropped).
    pub dropped_by_driver: u64,
    /// Captures that ended in a timeout.
    pub timeouts: u64,
}

/// A V4L2 video-capture device implementing [`Camera`].
pub struct V4l2Camera {
    name: String,
    inner: Arc<Mutex<Inner>>,
    /// CLOCK_MONOTONIC instant the rig last became still (set by `rig_still`, consumed by
    /// the next `capture`).
    still_at: Mutex<Option<f64>>,
}

struct Inner {
    name: String,
    device: v4l::Device,
    opts: V4l2Options,
    layout: Option<Layout>,
    frame_period: f64,
    applied: Option<CameraConfig>,
    stream: Option<MmapStream>,
    last_sequence: Option<u32>,
    stats: CaptureStats,
}

const CAP_VIDEO_CAPTURE: u32 = 0x0000_0001;
const CAP_STREAMING: u32 = 0x0400_0000;
const FIELD_NONE: u32 = 1;

/// Map an ioctl failure to the typed error, naming the camera and the command.
fn io_err(device: &str, command: &str, e: &io::Error) -> DeviceError {
    let device = device.to_string();
    let command = command.to_string();
    match e.raw_os_error() {
        Some(libc::ENODEV) | Some(libc::ENXIO) | Some(libc::EPIPE) | Some(libc::EIO) | Some(libc::ENOENT) => {
            DeviceError::Disconnected {
                device,
                command,
                reason: e.to_string(),
            }
        }
        Some(libc::EBUSY) => DeviceError::Rejected {
            device,
            command,
            reason: format!("{e} (another program is using the camera?)"),
        },
        Some(libc::EINVAL) | Some(libc::ERANGE) | Some(libc::EACCES) | Some(libc::EPERM) => DeviceError::Rejected {
            device,
            command,
            reason: e.to_string(),
        },
        _ => DeviceError::Other {
            device,
            command,
            reason: e.to_string(),
        },
    }
}

/// Whether a dequeued frame may be returned for a rig that became still at `still_at`
/// (CLOCK_MONOTONIC seconds). Drivers stamp either the start of exposure (`SOE`) or the end
/// of the frame (`EOF`, the default); for EOF the exposure started at most one frame period
/// earlier. Frames without monotonic timestamps cannot be judged by time: `None`.
pub fn exposure_started_after(meta_flags: u32, timestamp: f64, frame_period: f64, still_at: f64) -> Option<bool> {
    if meta_flags & stream::BUF_FLAG_TIMESTAMP_MASK != stream::BUF_FLAG_TIMESTAMP_MONOTONIC {
        return None;
    }
    let start = if meta_flags & stream::BUF_FLAG_TSTAMP_SRC_MASK == stream::BUF_FLAG_TSTAMP_SRC_SOE {
        timestamp
    } else {
        timestamp - frame_period
    };
    Some(start >= still_at)
}

impl V4l2Camera {
    /// Open the device node and check it can capture video by streaming.
    pub fn open(opts: V4l2Options) -> Result<V4l2Camera, DeviceError> {
        let name = opts.name.clone();
        let device = v4l::Device::with_path(&opts.device).map_err(|e| io_err(&name, "open", &e))?;
        let caps = device.query_caps().map_err(|e| io_err(&name, "VIDIOC_QUERYCAP", &e))?;
        let bits = caps.capabilities.bits();
        // `capabilities` is the whole physical device's; `v4l` does not expose the node's
        // own `device_caps`, and a node without capture fails at VIDIOC_S_FMT anyway.
        if bits & CAP_VIDEO_CAPTURE == 0 || bits & CAP_STREAMING == 0 {
            return Err(DeviceError::Rejected {
                device: name,
                command: "VIDIOC_QUERYCAP".into(),
                reason: format!(
                    "{} ({}) is not a streaming video-capture device (capabilities {bits:#010x})",
                    opts.device.display(),
                    caps.card
                ),
            });
        }
        tracing::info!(camera = %name, card = %caps.card, driver = %caps.driver, "opened V4L2 camera");
        Ok(V4l2Camera {
            name: name.clone(),
            inner: Arc::new(Mutex::new(Inner {
                name,
                device,
                opts,
                layout: None,
                frame_period: 1.0 / 30.0,
                applied: None,
                stream: None,
                last_sequence: None,
                stats: CaptureStats::default(),
            })),
            still_at: Mutex::new(None),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        // A panic while holding the lock leaves plain data behind; keep going.
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Four-character codes of every format the device offers.
    pub fn offered_formats(&self) -> Result<Vec<String>, DeviceError> {
        let inner = self.lock();
        let list = inner
            .device
            .enum_formats()
            .map_err(|e| io_err(&self.name, "VIDIOC_ENUM_FMT", &e))?;
        Ok(list
            .iter()
            .map(|d| d.fourcc.str().unwrap_or("????").to_string())
            .collect())
    }

    /// The layout negotiated by the last `configure`.
    pub fn layout(&self) -> Option<Layout> {
        self.lock().layout
    }

    /// Frame period the driver reported (seconds).
    pub fn frame_period(&self) -> f64 {
        self.lock().frame_period
    }

    pub fn stats(&self) -> CaptureStats {
        self.lock().stats
    }

    /// Change the formats accepted by the next `configure`.
    pub fn set_formats(&self, formats: Vec<PixelFormat>) {
        self.lock().opts.formats = formats;
    }

    pub fn set_timeout(&self, timeout: Duration) {
        self.lock().opts.timeout = timeout;
    }

    /// Frame rate requested by the next `configure` (None: the driver's).
    pub fn set_frame_rate(&self, fps: Option<f64>) {
        self.lock().opts.frame_rate = fps;
    }

    pub fn set_require_exposure(&self, require: bool) {
        self.lock().opts.require_exposure = require;
    }

    /// Describe a control (None: the device has no such control).
    pub fn control_info(&self, id: u32) -> Result<Option<controls::ControlInfo>, DeviceError> {
        let inner = self.lock();
        controls::query(inner.fd(), id).map_err(|e| io_err(&self.name, &e.command, &e.source))
    }

    /// Read a control.
    pub fn control(&self, id: u32) -> Result<i32, DeviceError> {
        let inner = self.lock();
        controls::get(inner.fd(), id).map_err(|e| io_err(&self.name, &e.command, &e.source))
    }

    /// Set a control and return the value the driver applied.
    pub fn set_control(&self, id: u32, value: i32) -> Result<i32, DeviceError> {
        let inner = self.lock();
        controls::set_and_read(inner.fd(), id, value).map_err(|e| io_err(&self.name, &e.command, &e.source))
    }

    /// Press a button control (e.g. a driver's fault injection).
    pub fn press(&self, id: u32) -> Result<(), DeviceError> {
        let inner = self.lock();
        controls::set(inner.fd(), id, 1).map_err(|e| io_err(&self.name, &e.command, &e.source))
    }

    /// Record that the rig became still at `t` (CLOCK_MONOTONIC seconds).
    pub fn still_at(&self, t: f64) {
        *self.still_at.lock().unwrap_or_else(|p| p.into_inner()) = Some(t);
    }

    /// Blocking `configure`, for callers without an async runtime.
    pub fn configure_blocking(&self, config: &CameraConfig) -> Result<CameraConfig, DeviceError> {
        self.lock().configure(config)
    }

    /// Blocking `capture`, for callers without an async runtime.
    pub fn capture_blocking(&self) -> Result<Frame, DeviceError> {
        let still = self
            .still_at
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take()
            .unwrap_or_else(stream::monotonic_now);
        self.lock().capture(still)
    }
}

impl Inner {
    fn fd(&self) -> i32 {
        self.device.handle().fd()
    }

    fn err(&self, command: &str, e: &io::Error) -> DeviceError {
        io_err(&self.name, command, e)
    }

    /// `VIDIOC_S_FMT` with raw structs (the `v4l` crate's `Format` conversion panics on
    /// colorimetry values it does not know, and omits `ycbcr_enc`).
    fn set_format(&self, fmt: PixelFormat, width: u32, height: u32) -> Result<(u32, Layout), DeviceError> {
        // SAFETY: all-zero is valid for this C struct.
        let mut f: v4l2_format = unsafe { std::mem::zeroed() };
        f.type_ = 1; // V4L2_BUF_TYPE_VIDEO_CAPTURE
                     // The `pix` member of the union is the one selected by type_ = VIDEO_CAPTURE.
        f.fmt.pix.width = width;
        f.fmt.pix.height = height;
        f.fmt.pix.pixelformat = u32::from_le_bytes(fmt.fourcc());
        f.fmt.pix.field = FIELD_NONE;
        // SAFETY: pointer to a live struct of the type VIDIOC_S_FMT expects.
        unsafe {
            v4l::v4l2::ioctl(
                self.fd(),
                v4l::v4l2::vidioc::VIDIOC_S_FMT,
                &mut f as *mut _ as *mut c_void,
            )
        }
        .map_err(|e| self.err(&format!("VIDIOC_S_FMT {fmt} {width}x{height}"), &e))?;
        // SAFETY: the driver filled the `pix` member.
        let p = unsafe { f.fmt.pix };
        let ycbcr_enc = unsafe { p.__bindgen_anon_1.ycbcr_enc };
        let layout = Layout {
            format: fmt,
            width: p.width as usize,
            height: p.height as usize,
            stride: p.bytesperline as usize,
            size: p.sizeimage as usize,
            colorimetry: Colorimetry::from_v4l2(fmt, p.colorspace, p.xfer_func, ycbcr_enc, p.quantization),
        };
        Ok((p.pixelformat, layout))
    }

    fn configure(&mut self, config: &CameraConfig) -> Result<CameraConfig, DeviceError> {
        self.stream = None; // a format change needs the buffers released
        self.last_sequence = None;
        let offered = self
            .device
            .enum_formats()
            .map_err(|e| self.err("VIDIOC_ENUM_FMT", &e))?;
        let offered: Vec<[u8; 4]> = offered.iter().map(|d| d.fourcc.repr).collect();
        let wanted: Vec<PixelFormat> = if self.opts.formats.is_empty() {
            PixelFormat::PREFERENCE.to_vec()
        } else {
            self.opts.formats.clone()
        };
        let candidates: Vec<PixelFormat> = wanted
            .iter()
            .copied()
            .filter(|f| offered.contains(&f.fourcc()))
            .collect();
        if candidates.is_empty() {
            return Err(DeviceError::Rejected {
                device: self.name.clone(),
                command: "VIDIOC_ENUM_FMT".into(),
                reason: format!(
                    "offers none of {:?}; it offers {:?}",
                    wanted.iter().map(|f| f.name()).collect::<Vec<_>>(),
                    offered
                        .iter()
                        .map(|c| String::from_utf8_lossy(c).into_owned())
                        .collect::<Vec<_>>()
                ),
            });
        }
        let (w, h) = (
            config.width.min(u32::MAX as usize) as u32,
            config.height.min(u32::MAX as usize) as u32,
        );
        let mut chosen = None;
        for fmt in candidates {
            let (code, layout) = self.set_format(fmt, w, h)?;
            if code != u32::from_le_bytes(fmt.fourcc()) {
                tracing::debug!(camera = %self.name, asked = %fmt, got = ?code.to_le_bytes(), "driver substituted another format");
                continue;
            }
            if let Some(bpp) = fmt.bytes_per_pixel() {
                if layout.stride < layout.width * bpp || layout.width == 0 || layout.height == 0 {
                    return Err(DeviceError::Garbled {
                        device: self.name.clone(),
                        command: "VIDIOC_S_FMT".into(),
                        reply: format!(
                            "{fmt} {}x{} with bytesperline {} (< {} bytes per row)",
                            layout.width,
                            layout.height,
                            layout.stride,
                            layout.width * bpp
                        ),
                    });
                }
            }
            chosen = Some(layout);
            break;
        }
        let layout = chosen.ok_or_else(|| DeviceError::Rejected {
            device: self.name.clone(),
            command: "VIDIOC_S_FMT".into(),
            reason: "the driver substituted every requested format".into(),
        })?;
        if (layout.width, layout.height) != (config.width, config.height) {
            tracing::info!(camera = %self.name, asked = ?(config.width, config.height), got = ?(layout.width, layout.height), "driver adjusted the frame size");
        }
        if let Some(fps) = self.opts.frame_rate {
            // Ask as a fraction with a millihertz resolution; the driver picks the nearest
            // interval it supports (what it picked is read back below).
            let want = v4l::video::capture::Parameters::new(v4l::Fraction::new(1000, (fps * 1000.0).round() as u32));
            if let Err(e) = self.device.set_params(&want) {
                tracing::warn!(camera = %self.name, fps, error = %e, "VIDIOC_S_PARM failed; keeping the driver's frame rate");
            }
        }
        self.frame_period = match self.device.params() {
            Ok(p) if p.interval.numerator > 0 && p.interval.denominator > 0 => {
                p.interval.numerator as f64 / p.interval.denominator as f64
            }
            Ok(_) | Err(_) => {
                tracing::warn!(camera = %self.name, "driver reports no frame interval; assuming 1/30 s");
                1.0 / 30.0
            }
        };
        let exposure = self.apply_exposure(config.exposure)?;
        let gain = self.apply_gain(config.gain)?;
        self.layout = Some(layout);
        let applied = CameraConfig {
            width: layout.width,
            height: layout.height,
            exposure,
            gain,
            bit_depth: 16,
        };
        self.start_stream()?;
        tracing::info!(camera = %self.name, format = %layout.format, width = layout.width, height = layout.height,
            stride = layout.stride, exposure, gain, "camera configured");
        self.applied = Some(applied.clone());
        Ok(applied)
    }

    fn ctrl_err(&self, e: controls::ControlError) -> DeviceError {
        io_err(&self.name, &e.command, &e.source)
    }

    /// Manual exposure time; returns the applied exposure in seconds.
    fn apply_exposure(&mut self, seconds: f64) -> Result<f64, DeviceError> {
        let fd = self.fd();
        if let Some(auto) = controls::query(fd, controls::cid::EXPOSURE_AUTO).map_err(|e| self.ctrl_err(e))? {
            if auto.writable() {
                let got =
                    controls::set_and_read(fd, auto.id, controls::EXPOSURE_MANUAL).map_err(|e| self.ctrl_err(e))?;
                if got != controls::EXPOSURE_MANUAL {
                    return Err(DeviceError::Rejected {
                        device: self.name.clone(),
                        command: "VIDIOC_S_CTRL V4L2_CID_EXPOSURE_AUTO=manual".into(),
                        reason: format!("read back {got}"),
                    });
                }
            }
        }
        match controls::query(fd, controls::cid::EXPOSURE_ABSOLUTE).map_err(|e| self.ctrl_err(e))? {
            Some(c) if c.writable() => {
                let raw = c.nearest(seconds / controls::EXPOSURE_ABSOLUTE_UNIT_S);
                let got = controls::set_and_read(fd, c.id, raw).map_err(|e| self.ctrl_err(e))?;
                Ok(got as f64 * controls::EXPOSURE_ABSOLUTE_UNIT_S)
            }
            _ if self.opts.require_exposure => Err(DeviceError::Rejected {
                device: self.name.clone(),
                command: "VIDIOC_QUERYCTRL V4L2_CID_EXPOSURE_ABSOLUTE".into(),
                reason: "the camera has no writable manual exposure time control".into(),
            }),
            _ => {
                tracing::warn!(camera = %self.name, asked = seconds, reported = self.frame_period,
                    "no manual exposure control; reporting the frame period as the exposure (upper bound)");
                Ok(self.frame_period)
            }
        }
    }

    /// Manual gain; returns the applied gain (1 = unity, see `gain_unity_raw`).
    fn apply_gain(&mut self, gain: f64) -> Result<f64, DeviceError> {
        let fd = self.fd();
        if let Some(auto) = controls::query(fd, controls::cid::AUTOGAIN).map_err(|e| self.ctrl_err(e))? {
            if auto.writable() {
                let got = controls::set_and_read(fd, auto.id, 0).map_err(|e| self.ctrl_err(e))?;
                if got != 0 {
                    return Err(DeviceError::Rejected {
                        device: self.name.clone(),
                        command: "VIDIOC_S_CTRL V4L2_CID_AUTOGAIN=0".into(),
                        reason: format!("read back {got}"),
                    });
                }
            }
        }
        match controls::query(fd, controls::cid::GAIN).map_err(|e| self.ctrl_err(e))? {
            Some(c) if c.writable() => {
                let unity = self.opts.gain_unity_raw.unwrap_or(c.default).max(1);
                let raw = c.nearest(gain * unity as f64);
                let got = controls::set_and_read(fd, c.id, raw).map_err(|e| self.ctrl_err(e))?;
                let applied = got as f64 / unity as f64;
                if (applied - gain).abs() > 1e-9 {
                    tracing::info!(camera = %self.name, asked = gain, applied, raw = got, "driver adjusted the gain");
                }
                Ok(applied)
            }
            _ => {
                if (gain - 1.0).abs() > 1e-9 {
                    tracing::warn!(camera = %self.name, asked = gain, "camera has no gain control; gain stays at unity");
                }
                Ok(1.0)
            }
        }
    }

    fn start_stream(&mut self) -> Result<(), DeviceError> {
        if self.stream.is_none() {
            let s =
                MmapStream::start(self.fd(), self.opts.buffers.max(2)).map_err(|e| self.err(e.command, &e.source))?;
            tracing::debug!(camera = %self.name, buffers = s.buffer_count(), "streaming");
            self.stream = Some(s);
        }
        Ok(())
    }

    fn capture(&mut self, still_at: f64) -> Result<Frame, DeviceError> {
        let (layout, applied) = match (self.layout, self.applied.clone()) {
            (Some(l), Some(a)) => (l, a),
            _ => {
                return Err(DeviceError::Rejected {
                    device: self.name.clone(),
                    command: "capture".into(),
                    reason: "camera not configured (call configure first)".into(),
                })
            }
        };
        self.start_stream()?;
        let timeout = self.opts.timeout;
        let deadline = Instant::now() + timeout;
        // Without monotonic timestamps, freshness is judged by arrival: buffers already
        // waiting when capture starts are stale, and so is the one being filled then.
        let mut untimed_skip: Option<usize> = None;
        loop {
            let remaining = deadline.saturating_duration_since(Instant::now());
            let stream = self.stream.as_mut().expect("started above");
            let got = if remaining.is_zero() {
                Ok(Dequeued::TimedOut)
            } else {
                stream.dequeue(remaining)
            };
            let meta: BufferMeta = match got {
                Ok(Dequeued::Buffer(m)) => m,
                Ok(Dequeued::TimedOut) => {
                    self.stats.timeouts += 1;
                    return Err(DeviceError::Timeout {
                        device: self.name.clone(),
                        command: "VIDIOC_DQBUF (poll)".into(),
                        seconds: timeout.as_secs_f64(),
                    });
                }
                Err(e) => {
                    let err = self.err(e.command, &e.source);
                    // The queue state is unknown now; start over on the next capture.
                    self.stream = None;
                    return Err(err);
                }
            };
            if let Some(prev) = self.last_sequence {
                let gap = meta.sequence.wrapping_sub(prev);
                if gap > 1 && gap < u32::MAX / 2 {
                    self.stats.dropped_by_driver += (gap - 1) as u64;
                }
            }
            self.last_sequence = Some(meta.sequence);
            let fresh = match exposure_started_after(meta.flags, meta.timestamp, self.frame_period, still_at) {
                Some(f) => f,
                None => {
                    let skip =
                        untimed_skip.get_or_insert_with(|| 1 + self.stream.as_ref().map_or(0, |s| s.buffer_count()));
                    if *skip > 0 {
                        *skip -= 1;
                        false
                    } else {
                        true
                    }
                }
            };
            let corrupt = meta.flags & stream::BUF_FLAG_ERROR != 0;
            let stream = self.stream.as_mut().expect("started above");
            let converted = if fresh && !corrupt {
                Some(format::to_linear_rgb16(&layout, stream.data(&meta)))
            } else {
                None
            };
            if let Err(e) = stream.queue(meta.index) {
                let err = self.err(e.command, &e.source);
                self.stream = None;
                return Err(err);
            }
            if corrupt {
                self.stats.corrupt_discarded += 1;
                tracing::debug!(camera = %self.name, sequence = meta.sequence, "discarded a buffer flagged as corrupt");
                continue;
            }
            let Some(converted) = converted else {
                self.stats.stale_discarded += 1;
                continue;
            };
            let data = converted.map_err(|e| DeviceError::Garbled {
                device: self.name.clone(),
                command: format!("VIDIOC_DQBUF (decode {})", layout.format),
                reply: e.to_string(),
            })?;
            self.stats.frames += 1;
            return Ok(Frame {
                width: layout.width,
                height: layout.height,
                data,
                meta: FrameMeta {
                    timestamp: meta.timestamp,
                    exposure: applied.exposure,
                    gain: applied.gain,
                    sequence: meta.sequence as u64,
                    bit_depth: 16,
                },
            });
        }
    }
}

#[async_trait]
impl Camera for V4l2Camera {
    fn name(&self) -> &str {
        &self.name
    }

    async fn configure(&self, config: &CameraConfig) -> Result<CameraConfig, DeviceError> {
        let config = config.clone();
        crate::camera::blocking_call(&self.name, "configure", &self.inner, move |inner| {
            inner.configure(&config)
        })
        .await
    }

    async fn capture(&self) -> Result<Frame, DeviceError> {
        let still = self
            .still_at
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take()
            .unwrap_or_else(stream::monotonic_now);
        crate::camera::blocking_call(&self.name, "capture", &self.inner, move |inner| inner.capture(still)).await
    }

    fn rig_still(&self) {
        self.still_at(stream::monotonic_now());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MONO_EOF: u32 = stream::BUF_FLAG_TIMESTAMP_MONOTONIC;
    const MONO_SOE: u32 = stream::BUF_FLAG_TIMESTAMP_MONOTONIC | stream::BUF_FLAG_TSTAMP_SRC_SOE;

    #[test]
    fn end_of_frame_stamps_are_moved_back_one_frame_period() {
        // Rig still at t = 10 s, 30 fps: a frame stamped (EOF) at 10.02 s began exposing at
        // 9.987 s, during the move.
        assert_eq!(exposure_started_after(MONO_EOF, 10.02, 1.0 / 30.0, 10.0), Some(false));
        assert_eq!(exposure_started_after(MONO_EOF, 10.04, 1.0 / 30.0, 10.0), Some(true));
        // Start-of-exposure stamps are taken as they are.
        assert_eq!(exposure_started_after(MONO_SOE, 10.02, 1.0 / 30.0, 10.0), Some(true));
        assert_eq!(exposure_started_after(MONO_SOE, 9.99, 1.0 / 30.0, 10.0), Some(false));
    }

    #[test]
    fn non_monotonic_stamps_are_not_judged_by_time() {
        assert_eq!(exposure_started_after(0x4000 /* COPY */, 1e9, 0.03, 0.0), None);
        assert_eq!(exposure_started_after(0, 1e9, 0.03, 0.0), None);
    }

    #[test]
    fn io_errors_map_to_typed_device_errors() {
        let e = io_err("cam", "VIDIOC_DQBUF", &io::Error::from_raw_os_error(libc::ENODEV));
        assert!(matches!(e, DeviceError::Disconnected { .. }));
        assert_eq!(e.device(), "cam");
        assert!(e.to_string().contains("VIDIOC_DQBUF"), "{e}");
        let e = io_err("cam", "VIDIOC_STREAMON", &io::Error::from_raw_os_error(libc::EBUSY));
        assert!(matches!(e, DeviceError::Rejected { .. }));
    }

    #[test]
    fn rig_options_parse_and_refuse_typos() {
        let spec = |opts: &str| -> crate::rig::CameraSpec {
            toml::from_str(&format!(
                "backend = \"v4l2\"\nwidth = 640\nheight = 360\nfocal_length_px = 500.0\nbit_depth = 8\nexposure_s = 0.01\noptions = {{ {opts} }}"
            ))
            .unwrap()
        };
        let o = V4l2Options::from_rig(&spec(
            "device = \"/dev/video3\", formats = [\"yuyv\", \"rgb24\"], timeout_s = 1.5, buffers = 3, require_exposure = true, gain_unity_raw = 16, frame_rate = 30",
        ))
        .unwrap();
        assert_eq!(o.device, PathBuf::from("/dev/video3"));
        assert_eq!(o.formats, vec![PixelFormat::Yuyv, PixelFormat::Rgb24]);
        assert_eq!(
            (o.timeout, o.buffers, o.require_exposure, o.gain_unity_raw),
            (Duration::from_millis(1500), 3, true, Some(16))
        );
        assert_eq!(o.frame_rate, Some(30.0));
        assert_eq!(
            V4l2Options::from_rig(&spec("")).unwrap().device,
            PathBuf::from("/dev/video0")
        );
        for bad in [
            "devcie = \"/dev/video0\"",
            "formats = [\"h264\"]",
            "timeout_s = -1",
            "buffers = 1",
            "frame_rate = 0",
        ] {
            let e = V4l2Options::from_rig(&spec(bad)).unwrap_err();
            assert!(
                matches!(e, DeviceError::Rejected { .. }) && e.to_string().contains("camera.options"),
                "{bad}: {e}"
            );
        }
    }

    #[test]
    fn opening_a_missing_device_is_a_typed_error() {
        let e = V4l2Camera::open(V4l2Options::new("/nonexistent/video99"))
            .err()
            .unwrap();
        assert!(matches!(e, DeviceError::Disconnected { .. }), "{e}");
        assert!(e.to_string().contains("/nonexistent/video99"), "{e}");
    }
}
