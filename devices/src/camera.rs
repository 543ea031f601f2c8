//! The camera trait and the frame it returns.

use crate::DeviceError;
use async_trait::async_trait;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex};

/// Settings a camera is asked for. Real drivers adjust what they are asked (sizes,
/// exposure steps): `Camera::configure` returns what was actually applied.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraConfig {
    pub width: usize,
    pub height: usize,
    /// Exposure time in seconds.
    pub exposure: f64,
    /// Analogue gain (1 = unity).
    pub gain: f64,
    /// ADC bit depth of the delivered values (8, 12, 16).
    pub bit_depth: u32,
}

/// Pinhole intrinsics in pixels (OpenCV convention: x right, y down, origin at the
/// top-left pixel's corner, so pixel (i, j) has its centre at (i + ½, j + ½)).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Intrinsics {
    /// Pixel coordinates of a camera-frame point (z > 0).
    pub fn project(&self, x: f64, y: f64, z: f64) -> (f64, f64) {
        (self.fx * x / z + self.cx, self.fy * y / z + self.cy)
    }
}

/// Metadata of one captured frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameMeta {
    /// Capture time in seconds on the rig's clock (virtual for a simulated rig).
    pub timestamp: f64,
    pub exposure: f64,
    pub gain: f64,
    /// Increases by one per captured frame, so dropped frames are visible.
    pub sequence: u64,
    pub bit_depth: u32,
}

/// A raw RGB frame of digital numbers (DN), interleaved, row 0 at the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub width: usize,
    pub height: usize,
    /// `width * height * 3` values in `0 ..= 2^bit_depth − 1`.
    pub data: Vec<u16>,
    pub meta: FrameMeta,
}

impl Frame {
    /// The largest value the ADC can deliver.
    pub fn max_dn(&self) -> u16 {
        ((1u32 << self.meta.bit_depth.min(16)) - 1) as u16
    }
}

#[async_trait]
pub trait Camera: Send + Sync {
    fn name(&self) -> &str;
    /// Apply settings; returns the settings the device actually uses.
    async fn configure(&self, config: &CameraConfig) -> Result<CameraConfig, DeviceError>;
    /// Capture one frame with the current settings.
    async fn capture(&self) -> Result<Frame, DeviceError>;
    /// The rig has just become still (every axis settled). A streaming camera (V4L2)
    /// holds frames exposed during the move in its queue; it must not return any frame
    /// whose exposure started before this call. Cameras that expose only when `capture`
    /// is called (the simulated one) need nothing, hence the empty default.
    fn rig_still(&self) {}
    /// The captures that follow (until the next call) belong to the measurement with
    /// canonical pair index `index` (the plan step's `index`): exposure 0 until the camera
    /// is reconfigured (a re-exposure), then 1, …; retries of a failed capture repeat their
    /// exposure. The engine calls it just before a step's capture.
    /// A simulated camera derives its sensor noise from this identity (and its seed), so a
    /// measurement gets the same noise whatever order, machine or resume it was taken in;
    /// real cameras have nothing to do with it, hence the empty default.
    fn begin_measurement(&self, _index: u64) {}
    /// Wait until the last frame's readout has ended. A camera whose `capture` returns when
    /// the exposure ends, its readout overlapping the next move
    /// ([`crate::rig::CameraSpec::readout_overlaps_motion`]; the simulated one), finishes
    /// it here; the others return at once (their `capture` returned after the readout),
    /// hence the empty default. The engine calls it when a run ends, so the run's rig time
    /// includes the last readout.
    async fn readout_done(&self) {}
    /// Who the camera says it is (driver, card or model, firmware where it reports one),
    /// for `gonio devices check`; a camera that cannot tell answers with its name (the
    /// default).
    async fn identity(&self) -> Result<String, DeviceError> {
        Ok(self.name().to_string())
    }
    /// The sensor's temperature (°C) where the camera reports one (GenICam's
    /// `DeviceTemperature`, say), `Ok(None)` otherwise (the default). Why: dark current
    /// and gain drift with it over a long run; each measurement's record keeps it
    /// (`extra.camera_temperature_c`), so a drift can be told from the sample.
    async fn temperature_c(&self) -> Result<Option<f64>, DeviceError> {
        Ok(None)
    }
    /// Whether the camera may expose while the rig moves (fly-scan): its frames then show
    /// the motion of one exposure, and the engine stamps them with the stages' positions at
    /// exposure start and end. Only the simulated camera, which renders that motion, does.
    fn exposes_in_motion(&self) -> bool {
        false
    }
}

/// A camera a backend found on this machine (`gonio devices list`), with the rig-file
/// options that open exactly it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FoundCamera {
    /// The rig file's `camera.backend`.
    pub backend: String,
    /// Vendor and model as the backend reports them.
    pub model: String,
    /// Where it is, in the backend's terms (libgphoto2 port; GenICam protocol and address).
    pub address: String,
    /// What goes into the rig file's `[camera] options` to open it (`port = "usb:001,004"`).
    pub rig_options: String,
}

/// Run one call of a blocking camera driver (V4L2 ioctls, libaravis, libgphoto2) on tokio's
/// blocking pool with the driver's state locked: the one place where a real camera backend
/// turns its blocking library into the async [`Camera`] trait. A poisoned lock is taken
/// over (the state is the driver's own, and a call that panicked stored no frame), and a
/// worker that panicked becomes a typed error naming the device and the command.
pub async fn blocking_call<S, T>(
    device: &str,
    command: &str,
    state: &Arc<Mutex<S>>,
    call: impl FnOnce(&mut S) -> Result<T, DeviceError> + Send + 'static,
) -> Result<T, DeviceError>
where
    S: Send + 'static,
    T: Send + 'static,
{
    let state = state.clone();
    tokio::task::spawn_blocking(move || call(&mut state.lock().unwrap_or_else(|p| p.into_inner())))
        .await
        .map_err(|e| DeviceError::Other {
            device: device.to_string(),
            command: command.to_string(),
            reason: format!("worker task failed: {e}"),
        })?
}

/// Why a rig file's camera could not be opened: an option the backend refused (its key
/// names it) or the device itself. Shared by the real camera backends, so the rig builder
/// maps one type.
#[derive(Debug, thiserror::Error)]
pub enum FromRigError {
    #[error(transparent)]
    Option(#[from] crate::rig::OptionError),
    #[error(transparent)]
    Device(#[from] DeviceError),
}
