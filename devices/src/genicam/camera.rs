//! The GenICam [`Camera`] over Aravis: open, configure (pixel format, region, exposure,
//! gain, software trigger, stream), capture (drain, trigger, wait, check, convert).
//!
//! Aravis is blocking; the async trait methods run it on tokio's blocking pool, one
//! camera behind one mutex (an `aravis::Camera` may be sent between threads, not shared).

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use aravis::prelude::*;
use aravis::{Auto, BufferStatus, GvStreamOption};
use async_trait::async_trait;
use serde::Serialize;

use super::options::GenicamOptions;
use super::pixel::{self, PixelFormat};
use super::{
    check_buffer, classify, device_error, exposure_feature, unchanged, unwrap_frame_id, BufferInfo, GainControl,
};
use crate::camera::{Camera, CameraConfig, FoundCamera, Frame, FrameMeta};
use crate::rig::CameraSpec;
use crate::DeviceError;

/// Counters since the camera was opened, for diagnostics and the fake-camera checks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct CaptureStats {
    /// Frames returned by `capture`.
    pub frames: u64,
    /// Buffers that were waiting when a capture started (exposed before its trigger):
    /// discarded.
    pub stale_discarded: u64,
    /// Incomplete buffers (lost packets, stream timeout): reported as garbled frames.
    pub incomplete: u64,
    /// Captures that ended in a timeout.
    pub timeouts: u64,
}

/// A GenICam camera implementing [`Camera`].
pub struct GenicamCamera {
    name: String,
    inner: Arc<Mutex<Inner>>,
    /// Set by Aravis' `control-lost` signal (heartbeat failed: the camera is gone).
    lost: Arc<AtomicBool>,
}

/// What the last `configure` applied (read back from the camera).
#[derive(Clone, Debug)]
struct Applied {
    config: CameraConfig,
    format: PixelFormat,
    exposure_feature: &'static str,
    gain: GainControl,
    /// The gain feature's value as read back (dB or raw), for the per-frame check.
    gain_value: Option<f64>,
}

struct Inner {
    name: String,
    opts: GenicamOptions,
    camera: aravis::Camera,
    stream: Option<aravis::Stream>,
    applied: Option<Applied>,
    stats: CaptureStats,
    /// The size the last full `configure` was asked for (the camera may have adjusted
    /// it): the same size again keeps the stream (see `configure`).
    requested_size: Option<(usize, usize)>,
    /// The last frame's raw id and sequence (see [`super::unwrap_frame_id`]).
    last_frame: Option<(u64, u64)>,
    /// The last capture timed out: restart the acquisition before the next trigger (a
    /// camera that stopped acquiring, or lost its trigger state, resumes).
    rearm: bool,
}

impl Drop for Inner {
    fn drop(&mut self) {
        if self.stream.take().is_some() {
            let _ = self.camera.stop_acquisition();
        }
    }
}

/// libaravis' `ArvDeviceError` domain, only to read an error's code (glib exposes the code
/// through a domain type).
#[derive(Clone, Copy)]
struct ArvDeviceCode(i32);

impl aravis::glib::error::ErrorDomain for ArvDeviceCode {
    fn domain() -> aravis::glib::Quark {
        aravis::glib::Quark::from_str("arv-device-error-quark")
    }
    fn code(self) -> i32 {
        self.0
    }
    fn from(code: i32) -> Option<Self> {
        Some(ArvDeviceCode(code))
    }
}

/// The GenICam cameras Aravis finds on this machine (GigE Vision discovery on every
/// interface, USB3 Vision), for `gonio devices list`: vendor and model, protocol and
/// address, and the `device` option (the Aravis device id) that opens exactly it.
pub fn list_cameras() -> Vec<FoundCamera> {
    static LISTING: Mutex<()> = Mutex::new(());
    let _one_at_a_time = LISTING.lock().unwrap_or_else(|p| p.into_inner());
    // SAFETY: Aravis' device list is global state of the library, valid until the next
    // update; the lock keeps gonio's own enumerations apart, and the list is copied out
    // before the lock is released. It is called where no camera is being opened (the
    // `devices list` command).
    let devices = unsafe { aravis::get_device_list() };
    let text = |c: &std::ffi::CString| c.to_string_lossy().trim().to_string();
    devices
        .iter()
        .map(|d| {
            let model = [text(&d.vendor), text(&d.model)]
                .into_iter()
                .filter(|s| !s.is_empty())
                .collect::<Vec<_>>()
                .join(" ");
            FoundCamera {
                backend: "genicam".into(),
                model,
                address: format!("{} {}", text(&d.protocol), text(&d.address)).trim().to_string(),
                rig_options: format!("device = \"{}\"", text(&d.id)),
            }
        })
        .collect()
}

/// The typed error of a failed Aravis call.
fn arv_err(device: &str, command: &str, e: &aravis::glib::Error) -> DeviceError {
    let domain = e.domain().as_str();
    // Codes matter only in the device domain; every GenICam (gc) error is a refusal.
    let code = e.kind::<ArvDeviceCode>().map_or(-1, |c| c.0);
    device_error(device, command, classify(domain, code), e.message())
}

impl GenicamCamera {
    /// Open the camera the options name (the first one Aravis finds when they name none).
    pub fn open(opts: GenicamOptions) -> Result<GenicamCamera, DeviceError> {
        let name = format!("genicam {}", opts.device.as_deref().unwrap_or("(first found)"));
        let camera = aravis::Camera::new(opts.device.as_deref()).map_err(|e| DeviceError::Disconnected {
            device: name.clone(),
            command: "open".into(),
            reason: format!(
                "{} (check camera.options.device: an Aravis device id as `arv-tool-0.8` lists it, or the camera's IP address)",
                e.message()
            ),
        })?;
        if camera.is_gv_device() && !opts.packet_socket {
            camera.gv_set_stream_options(GvStreamOption::PACKET_SOCKET_DISABLED);
        }
        let lost = Arc::new(AtomicBool::new(false));
        if let Some(device) = camera.device() {
            let flag = lost.clone();
            device.connect_control_lost(move |_| flag.store(true, Ordering::SeqCst));
        }
        let model = camera.model_name().map(|s| s.to_string()).unwrap_or_default();
        let id = camera.device_id().map(|s| s.to_string()).unwrap_or_default();
        tracing::info!(camera = %name, model, id, "opened GenICam camera");
        Ok(GenicamCamera {
            name: name.clone(),
            inner: Arc::new(Mutex::new(Inner {
                name,
                opts,
                camera,
                stream: None,
                applied: None,
                stats: CaptureStats::default(),
                rearm: false,
                last_frame: None,
                requested_size: None,
            })),
            lost,
        })
    }

    /// Open the camera a rig file's `[camera]` table describes (`backend = "genicam"`).
    pub fn from_rig(spec: &CameraSpec) -> Result<GenicamCamera, FromRigError> {
        let opts = GenicamOptions::from_rig(spec)?;
        Ok(GenicamCamera::open(opts)?)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    pub fn stats(&self) -> CaptureStats {
        self.lock().stats
    }

    /// The pixel format chosen by the last `configure`.
    pub fn pixel_format(&self) -> Option<PixelFormat> {
        self.lock().applied.as_ref().map(|a| a.format)
    }

    /// Pixel format names the camera offers.
    pub fn offered_formats(&self) -> Result<Vec<String>, DeviceError> {
        let inner = self.lock();
        inner
            .camera
            .dup_available_pixel_formats_as_strings()
            .map(|v| v.into_iter().map(|s| s.to_string()).collect())
            .map_err(|e| arv_err(&self.name, "PixelFormat (list)", &e))
    }

    /// Change the formats accepted by the next `configure`.
    pub fn set_formats(&self, formats: Vec<PixelFormat>) {
        let mut inner = self.lock();
        inner.opts.pixel_formats = formats;
        // The next configure chooses the format again (a full one).
        inner.requested_size = None;
    }

    /// Write a GenICam feature directly (tests: provoke a camera changed behind gonio's back).
    pub fn set_feature_string(&self, feature: &str, value: &str) -> Result<(), DeviceError> {
        let inner = self.lock();
        inner
            .camera
            .set_string(feature, value)
            .map_err(|e| arv_err(&self.name, feature, &e))
    }

    /// Write a float feature directly (tests, as [`GenicamCamera::set_feature_string`]).
    pub fn set_feature_float(&self, feature: &str, value: f64) -> Result<(), DeviceError> {
        let inner = self.lock();
        inner
            .camera
            .set_float(feature, value)
            .map_err(|e| arv_err(&self.name, feature, &e))
    }

    /// Execute a GenICam command feature directly (tests: stop the acquisition behind
    /// gonio's back).
    pub fn execute(&self, command: &str) -> Result<(), DeviceError> {
        let inner = self.lock();
        inner
            .camera
            .execute_command(command)
            .map_err(|e| arv_err(&self.name, command, &e))
    }

    /// Configure and capture without an async runtime (the checks in examples/).
    pub fn configure_blocking(&self, config: &CameraConfig) -> Result<CameraConfig, DeviceError> {
        self.lock().configure(config)
    }

    /// Capture without an async runtime.
    pub fn capture_blocking(&self) -> Result<Frame, DeviceError> {
        let lost = self.lost.clone();
        self.lock().capture(&lost)
    }
}

pub use crate::camera::FromRigError;

impl Inner {
    fn err(&self, command: &str, e: &aravis::glib::Error) -> DeviceError {
        arv_err(&self.name, command, e)
    }

    fn rejected(&self, command: &str, reason: String) -> DeviceError {
        DeviceError::Rejected {
            device: self.name.clone(),
            command: command.to_string(),
            reason,
        }
    }

    fn stop(&mut self) {
        if self.stream.take().is_some() {
            if let Err(e) = self.camera.stop_acquisition() {
                tracing::warn!(camera = %self.name, error = %e, "AcquisitionStop failed");
            }
        }
    }

    fn has(&self, feature: &str) -> bool {
        self.camera.is_feature_available(feature).unwrap_or(false)
    }

    fn configure(&mut self, config: &CameraConfig) -> Result<CameraConfig, DeviceError> {
        // Only exposure or gain changed (an HDR bracket, a re-exposure): set them while
        // the camera streams, as cameras allow; restarting the stream would cost every
        // bracket step an AcquisitionStop/Start.
        // (The pixel format is read first: a camera reconfigured behind gonio's back gets a
        // full configure.)
        let same_format = |inner: &Self| {
            inner.applied.as_ref().is_some_and(|a| {
                inner
                    .camera
                    .pixel_format()
                    .is_ok_and(|f| f.raw() == a.format.pfnc_code())
            })
        };
        if self.stream.is_some() && self.requested_size == Some((config.width, config.height)) && same_format(self) {
            if let Some(a) = self.applied.take() {
                let (exposure_feature, exposure) = self.apply_exposure(config.exposure)?;
                let (gain_control, gain_value, gain) = self.apply_gain(config.gain)?;
                let applied = CameraConfig {
                    exposure,
                    gain,
                    ..a.config
                };
                tracing::debug!(camera = %self.name, exposure, gain, "exposure and gain changed while streaming");
                self.applied = Some(Applied {
                    config: applied.clone(),
                    exposure_feature,
                    gain: gain_control,
                    gain_value,
                    ..a
                });
                return Ok(applied);
            }
        }
        // Formats and regions are locked while the camera streams (TLParamsLocked).
        self.stop();
        self.applied = None;
        self.requested_size = Some((config.width, config.height));
        let format = self.apply_format()?;
        let (width, height) = self.apply_region(config.width, config.height)?;
        let (exposure_feature, exposure) = self.apply_exposure(config.exposure)?;
        let (gain_control, gain_value, gain) = self.apply_gain(config.gain)?;
        self.camera
            .set_trigger("Software")
            .map_err(|e| self.err("TriggerMode=On, TriggerSource=Software", &e))?;
        let applied = CameraConfig {
            width,
            height,
            exposure,
            gain,
            bit_depth: format.bit_depth(),
        };
        self.start_stream()?;
        tracing::info!(camera = %self.name, %format, width, height, exposure, gain, "camera configured");
        self.applied = Some(Applied {
            config: applied.clone(),
            format,
            exposure_feature,
            gain: gain_control,
            gain_value,
        });
        Ok(applied)
    }

    fn apply_format(&mut self) -> Result<PixelFormat, DeviceError> {
        let offered: Vec<String> = self
            .camera
            .dup_available_pixel_formats_as_strings()
            .map_err(|e| self.err("PixelFormat (list)", &e))?
            .into_iter()
            .map(|s| s.to_string())
            .collect();
        let wanted = self.opts.formats();
        let pick = wanted.iter().find_map(|f| {
            offered
                .iter()
                .find(|o| PixelFormat::parse(o) == Some(*f))
                .map(|o| (*f, o.clone()))
        });
        let Some((format, entry)) = pick else {
            return Err(self.rejected(
                "PixelFormat",
                format!(
                    "the camera offers {} and none of them is acceptable ({}); set camera.options.pixel_formats \
                     to one gonio decodes that the camera offers",
                    offered.join(", "),
                    wanted.iter().map(|f| f.name()).collect::<Vec<_>>().join(", ")
                ),
            ));
        };
        self.camera
            .set_pixel_format_from_string(&entry)
            .map_err(|e| self.err(&format!("PixelFormat={entry}"), &e))?;
        let got = self
            .camera
            .pixel_format()
            .map_err(|e| self.err("PixelFormat (read)", &e))?;
        if got.raw() != format.pfnc_code() {
            return Err(self.rejected(
                &format!("PixelFormat={entry}"),
                format!("read back {:#010x} instead of {format}", got.raw()),
            ));
        }
        Ok(format)
    }

    /// The region nearest the asked size that the camera allows (bounds and increments),
    /// at offset 0, as read back.
    fn apply_region(&mut self, width: usize, height: usize) -> Result<(usize, usize), DeviceError> {
        let fit = |asked: usize, (lo, hi): (i32, i32), inc: i32| -> i32 {
            let inc = inc.max(1);
            let v = (asked.min(i32::MAX as usize) as i32).clamp(lo, hi);
            (lo + (v - lo) / inc * inc).clamp(lo, hi)
        };
        let wb = self.camera.width_bounds().map_err(|e| self.err("Width (bounds)", &e))?;
        let hb = self
            .camera
            .height_bounds()
            .map_err(|e| self.err("Height (bounds)", &e))?;
        let wi = self.camera.width_increment().unwrap_or(1);
        let hi = self.camera.height_increment().unwrap_or(1);
        let (w, h) = (fit(width, wb, wi), fit(height, hb, hi));
        self.camera
            .set_region(0, 0, w, h)
            .map_err(|e| self.err(&format!("region 0, 0, {w} × {h}"), &e))?;
        let (_, _, rw, rh) = self.camera.region().map_err(|e| self.err("region (read)", &e))?;
        if (rw as usize, rh as usize) != (width, height) {
            tracing::info!(camera = %self.name, asked = ?(width, height), got = ?(rw, rh), "camera adjusted the frame size");
        }
        Ok((rw.max(0) as usize, rh.max(0) as usize))
    }

    /// Manual exposure; returns the feature used and the read-back exposure in seconds.
    fn apply_exposure(&mut self, seconds: f64) -> Result<(&'static str, f64), DeviceError> {
        if !(seconds.is_finite() && seconds > 0.0) {
            return Err(self.rejected("exposure", format!("{seconds} s: must be a positive number of seconds")));
        }
        if self.camera.is_exposure_auto_available().unwrap_or(false) {
            self.camera
                .set_exposure_time_auto(Auto::Off)
                .map_err(|e| self.err("ExposureAuto=Off", &e))?;
        }
        let Some(feature) = exposure_feature(|f| self.has(f)) else {
            return Err(self.rejected(
                "ExposureTime",
                "the camera has neither ExposureTime nor ExposureTimeAbs".into(),
            ));
        };
        let (lo, hi) = self
            .camera
            .float_bounds(feature)
            .map_err(|e| self.err(&format!("{feature} (bounds)"), &e))?;
        let us = seconds * 1e6;
        let target = us.clamp(lo, hi);
        if target != us {
            tracing::warn!(camera = %self.name, asked_us = us, min_us = lo, max_us = hi, "exposure outside the camera's range; clamped");
        }
        self.camera
            .set_float(feature, target)
            .map_err(|e| self.err(&format!("{feature}={target}"), &e))?;
        let got = self
            .camera
            .float(feature)
            .map_err(|e| self.err(&format!("{feature} (read)"), &e))?;
        if !(got.is_finite() && got > 0.0) {
            return Err(self.rejected(feature, format!("read back {got} µs after writing {target} µs")));
        }
        Ok((feature, got * 1e-6))
    }

    /// Manual gain; returns how it is set, the feature's read-back value and gonio's gain.
    fn apply_gain(&mut self, gain: f64) -> Result<(GainControl, Option<f64>, f64), DeviceError> {
        if self.camera.is_gain_auto_available().unwrap_or(false) {
            self.camera
                .set_gain_auto(Auto::Off)
                .map_err(|e| self.err("GainAuto=Off", &e))?;
        }
        let control = if self.has("Gain") {
            let (min_db, max_db) = self
                .camera
                .float_bounds("Gain")
                .map_err(|e| self.err("Gain (bounds)", &e))?;
            GainControl::Decibel { min_db, max_db }
        } else if self.has("GainRaw") {
            let (min, max) = self
                .camera
                .integer_bounds("GainRaw")
                .map_err(|e| self.err("GainRaw (bounds)", &e))?;
            GainControl::Raw {
                min,
                max,
                unity: self.opts.gain_unity_raw,
            }
        } else {
            GainControl::None
        };
        let target = control.target(gain).map_err(|reason| self.rejected("gain", reason))?;
        let value = match control {
            GainControl::Decibel { .. } => {
                self.camera
                    .set_float("Gain", target)
                    .map_err(|e| self.err(&format!("Gain={target}"), &e))?;
                Some(self.camera.float("Gain").map_err(|e| self.err("Gain (read)", &e))?)
            }
            GainControl::Raw { .. } => {
                let raw = target as i64;
                self.camera
                    .set_integer("GainRaw", raw)
                    .map_err(|e| self.err(&format!("GainRaw={raw}"), &e))?;
                Some(
                    self.camera
                        .integer("GainRaw")
                        .map_err(|e| self.err("GainRaw (read)", &e))? as f64,
                )
            }
            GainControl::None => None,
        };
        let applied = value.map_or(1.0, |v| control.gain_of(v));
        Ok((control, value, applied))
    }

    fn start_stream(&mut self) -> Result<(), DeviceError> {
        let stream = self.camera.create_stream().map_err(|e| self.err("create stream", &e))?;
        let payload = self.camera.payload().map_err(|e| self.err("PayloadSize", &e))? as usize;
        for _ in 0..self.opts.buffers.max(2) {
            stream.push_buffer(aravis::Buffer::new_allocate(payload));
        }
        self.camera
            .start_acquisition()
            .map_err(|e| self.err("AcquisitionStart", &e))?;
        self.stream = Some(stream);
        Ok(())
    }

    fn capture(&mut self, lost: &AtomicBool) -> Result<Frame, DeviceError> {
        let Some(applied) = self.applied.clone() else {
            return Err(self.rejected("capture", "camera not configured (call configure first)".into()));
        };
        let gone = |name: &str, command: &str| DeviceError::Disconnected {
            device: name.to_string(),
            command: command.to_string(),
            reason: "the camera stopped answering its heartbeat (control lost): unplugged, powered off or \
                     its network link is down"
                .into(),
        };
        if lost.load(Ordering::SeqCst) {
            return Err(gone(&self.name, "capture"));
        }
        if self.stream.is_none() {
            self.start_stream()?;
        }
        let stream = self.stream.clone().expect("started above");
        if std::mem::take(&mut self.rearm) {
            tracing::info!(camera = %self.name, "re-arming the acquisition after a timeout");
            let _ = self.camera.stop_acquisition();
            self.camera
                .set_trigger("Software")
                .map_err(|e| self.err("TriggerMode=On, TriggerSource=Software", &e))?;
            self.camera
                .start_acquisition()
                .map_err(|e| self.err("AcquisitionStart", &e))?;
        }
        // Frames that arrived before this trigger (a late frame of a timed-out capture)
        // were exposed before the rig became still: never return them.
        while let Some(b) = stream.try_pop_buffer() {
            self.stats.stale_discarded += 1;
            stream.push_buffer(b);
        }
        self.camera
            .software_trigger()
            .map_err(|e| self.err("TriggerSoftware", &e))?;
        let timeout = self.opts.timeout;
        let start = Instant::now();
        let buffer = loop {
            let remaining = timeout.saturating_sub(start.elapsed());
            // Wait in slices, so a lost camera ends the wait at once.
            let slice = remaining.min(std::time::Duration::from_millis(100));
            if let Some(b) = stream.timeout_pop_buffer(slice.as_micros() as u64) {
                break b;
            }
            if lost.load(Ordering::SeqCst) {
                return Err(gone(&self.name, "capture (waiting for the frame)"));
            }
            if start.elapsed() >= timeout {
                self.stats.timeouts += 1;
                self.rearm = true;
                return Err(DeviceError::Timeout {
                    device: self.name.clone(),
                    command: "capture (frame after TriggerSoftware)".into(),
                    seconds: timeout.as_secs_f64(),
                });
            }
        };
        let status = buffer.status();
        let info = BufferInfo {
            complete: status == BufferStatus::Success,
            pfnc_code: if status == BufferStatus::Success {
                buffer.image_pixel_format().raw()
            } else {
                0
            },
            width: buffer.image_width().max(0) as usize,
            height: buffer.image_height().max(0) as usize,
        };
        let size = (applied.config.width, applied.config.height);
        if let Err(e) = check_buffer(&self.name, &format!("{status:?}"), info, applied.format, size) {
            if !info.complete {
                self.stats.incomplete += 1;
            }
            stream.push_buffer(buffer);
            return Err(e);
        }
        let data = buffer.image_data();
        let (raw_id, ts, sys_ts) = (buffer.frame_id(), buffer.timestamp(), buffer.system_timestamp());
        stream.push_buffer(buffer);
        // The exposure and gain the frame carries are read again now: a camera changed
        // behind gonio's back must not give a frame with the wrong metadata.
        let exposure_us = self
            .camera
            .float(applied.exposure_feature)
            .map_err(|e| self.err(&format!("{} (read)", applied.exposure_feature), &e))?;
        if !unchanged(applied.config.exposure, exposure_us * 1e-6) {
            return Err(self.rejected(
                applied.exposure_feature,
                format!(
                    "exposure changed during the run: {} µs read back, {} µs configured (another program \
                     or an auto mode?); the frame is discarded",
                    exposure_us,
                    applied.config.exposure * 1e6
                ),
            ));
        }
        let gain_now = match applied.gain {
            GainControl::Decibel { .. } => self.camera.float("Gain").ok(),
            GainControl::Raw { .. } => self.camera.integer("GainRaw").ok().map(|v| v as f64),
            GainControl::None => None,
        };
        if let (Some(was), Some(now)) = (applied.gain_value, gain_now) {
            if !unchanged(was.abs().max(1.0), now.abs().max(1.0)) || (was - now).abs() > 1e-6 {
                return Err(self.rejected(
                    "gain",
                    format!("gain changed during the run: {now} read back, {was} configured; the frame is discarded"),
                ));
            }
        }
        let rgb = pixel::to_rgb16(applied.format, size.0, size.1, &data).map_err(|e| DeviceError::Garbled {
            device: self.name.clone(),
            command: format!("capture (decode {})", applied.format),
            reply: e.to_string(),
        })?;
        self.stats.frames += 1;
        let frame_id = unwrap_frame_id(self.last_frame, raw_id);
        self.last_frame = Some((raw_id, frame_id));
        // The camera's own timestamp (ns on its clock, taken at exposure); cameras without
        // one give 0, then the host's reception time stands in.
        let timestamp = if ts != 0 { ts } else { sys_ts } as f64 * 1e-9;
        Ok(Frame {
            width: size.0,
            height: size.1,
            data: rgb,
            meta: FrameMeta {
                timestamp,
                exposure: applied.config.exposure,
                gain: applied.config.gain,
                sequence: frame_id,
                bit_depth: applied.format.bit_depth(),
            },
        })
    }
}

#[async_trait]
impl Camera for GenicamCamera {
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
        let lost = self.lost.clone();
        crate::camera::blocking_call(&self.name, "capture", &self.inner, move |inner| inner.capture(&lost)).await
    }

    /// Vendor, model, serial number and firmware, as the camera's standard features
    /// (`DeviceVendorName`, `DeviceModelName`, `DeviceSerialNumber`/`DeviceID`,
    /// `DeviceFirmwareVersion`/`DeviceVersion`) report them; the ones it lacks are left out.
    async fn identity(&self) -> Result<String, DeviceError> {
        let inner = self.lock();
        let c = &inner.camera;
        let mut parts: Vec<String> = Vec::new();
        for v in [c.vendor_name(), c.model_name()].into_iter().flatten() {
            if !v.is_empty() {
                parts.push(v.to_string());
            }
        }
        if let Some(sn) = [c.device_serial_number(), c.device_id()]
            .into_iter()
            .flatten()
            .find(|v| !v.is_empty())
        {
            parts.push(format!("S/N {sn}"));
        }
        if let Some(fw) = ["DeviceFirmwareVersion", "DeviceVersion"]
            .into_iter()
            .filter(|f| inner.has(f))
            .find_map(|f| c.string(f).ok().filter(|v| !v.is_empty()))
        {
            parts.push(format!("firmware {fw}"));
        }
        if parts.is_empty() {
            return Ok(self.name.clone());
        }
        Ok(parts.join(", "))
    }

    /// `DeviceTemperature` (°C, the SFNC feature) where the camera has it.
    async fn temperature_c(&self) -> Result<Option<f64>, DeviceError> {
        let inner = self.lock();
        if !inner.has("DeviceTemperature") {
            return Ok(None);
        }
        inner
            .camera
            .float("DeviceTemperature")
            .map(Some)
            .map_err(|e| inner.err("DeviceTemperature", &e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The PFNC codes of `pixel` (written without the library) are libaravis' own.
    #[test]
    fn pfnc_codes_match_libaravis() {
        use aravis::PixelFormat as A;
        use pixel::Cfa::*;
        for (ours, theirs) in [
            (PixelFormat::Mono8, A::MONO_8),
            (PixelFormat::Mono16, A::MONO_16),
            (PixelFormat::Rgb8, A::RGB_8_PACKED),
            (PixelFormat::Bayer(Rggb, 8), A::BAYER_RG_8),
            (PixelFormat::Bayer(Bggr, 8), A::BAYER_BG_8),
            (PixelFormat::Bayer(Grbg, 8), A::BAYER_GR_8),
            (PixelFormat::Bayer(Gbrg, 8), A::BAYER_GB_8),
            (PixelFormat::Bayer(Rggb, 16), A::BAYER_RG_16),
            (PixelFormat::Bayer(Bggr, 16), A::BAYER_BG_16),
            (PixelFormat::Bayer(Grbg, 16), A::BAYER_GR_16),
            (PixelFormat::Bayer(Gbrg, 16), A::BAYER_GB_16),
        ] {
            assert_eq!(ours.pfnc_code(), theirs.raw(), "{ours}");
        }
    }

    #[test]
    fn opening_a_missing_camera_is_a_typed_error_naming_the_option() {
        let opts = GenicamOptions {
            device: Some("No-Such-Camera-4711".into()),
            ..GenicamOptions::default()
        };
        let e = GenicamCamera::open(opts).err().unwrap();
        assert!(matches!(e, DeviceError::Disconnected { .. }), "{e}");
        assert!(e.to_string().contains("camera.options.device"), "{e}");
    }
}
