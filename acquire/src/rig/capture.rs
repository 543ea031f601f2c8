//! The engine's capture policy: what happens when the camera misbehaves.
//!
//! A measurement day must not end because one frame went missing, and must not store a
//! frame that shows something else than the commanded pose. So every capture goes through
//! [`capture_measurement`]:
//!
//! | fault | rule |
//! |---|---|
//! | capture does not return | the engine's own wall-clock timeout (`capture_timeout_s`) ends it; retried |
//! | capture error (dropped frame, corrupt buffer) | retried |
//! | stale frame (exposed before the rig was still) | discarded and captured again (counts as a retry) |
//! | saturated frame (more than `saturation_fraction` of the values at max DN) | `saturation = "flag"` (default): stored, flagged in the record; `"reexpose"`: captured again at half the exposure (up to 3 times) if the camera accepts a shorter exposure, scaled back to the nominal exposure when stored, else flagged |
//! | disconnect, rejected command | not retried |
//!
//! Retries are bounded (`capture_retries`, default 2, so 3 attempts); when they run out the
//! run ends with the camera's typed error (device and command named) and the journal is
//! consistent, so `--resume` continues once the cause is fixed. Retries, discarded frames and
//! saturation are written into the measurement's record (`extra`), so a dataset says which
//! images needed help. All of it is read from the rig file's `camera.options`.
//!
//! Staleness is judged here only when the frame timestamps are on the rig clock (the
//! simulated camera on a simulated rig); a streaming V4L2 camera stamps CLOCK_MONOTONIC and
//! applies its own rule inside `capture` after `rig_still` (found by the vivid run: judging
//! its frames against the simulated axes' clock refused every frame).

use gonio_devices::rig::CameraSpec;
use gonio_devices::{Camera, CameraConfig, DeviceError, Frame};
use std::time::Duration;

/// What to do with a saturated frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SaturationPolicy {
    /// Store it, flagged `saturated` in the record: the image is unchanged, the lab decides.
    Flag,
    /// Capture again at half the exposure (if the camera accepts it) and store that frame
    /// scaled to the nominal exposure.
    Reexpose,
}

/// The capture policy from the rig file's `camera.options`.
#[derive(Clone, Debug)]
pub struct CapturePolicy {
    /// Wall-clock limit of one capture (`capture_timeout_s`; default 30 s plus four frame times).
    pub timeout: Duration,
    /// Extra attempts after a failed, timed-out or stale capture (`capture_retries`, default 2).
    pub retries: u32,
    /// `saturation` (`"flag"` default, or `"reexpose"`).
    pub saturation: SaturationPolicy,
    /// A frame is saturated when more than this fraction of its values are at max DN
    /// (`saturation_fraction`, default 0.02: a few specular pixels are not a saturated frame).
    pub saturation_fraction: f64,
    /// Halvings of the exposure tried under `Reexpose`.
    pub max_reexposures: u32,
}

/// The rig-file keys this module reads (other camera backends must accept them).
pub const POLICY_KEYS: [&str; 4] = [
    "capture_timeout_s",
    "capture_retries",
    "saturation",
    "saturation_fraction",
];

impl CapturePolicy {
    /// Read the policy; a bad value is a typed error naming the key.
    pub fn from_spec(spec: &CameraSpec) -> Result<CapturePolicy, DeviceError> {
        let bad = |key: &str, reason: String| DeviceError::Rejected {
            device: "camera".into(),
            command: format!("rig file camera.options.{key}"),
            reason,
        };
        let num = |key: &str| -> Result<Option<f64>, DeviceError> {
            spec.options
                .get(key)
                .map(|v| {
                    v.as_float()
                        .or_else(|| v.as_integer().map(|i| i as f64))
                        .ok_or_else(|| bad(key, format!("{v}: must be a number")))
                })
                .transpose()
        };
        let frame_s = spec.exposure_s.max(0.0) + spec.readout_s.max(0.0);
        let timeout = match num("capture_timeout_s")? {
            None => 30.0 + 4.0 * frame_s,
            Some(t) if t.is_finite() && t > 0.0 && t <= 3600.0 => t,
            Some(t) => return Err(bad("capture_timeout_s", format!("{t}: must be seconds in (0, 3600]"))),
        };
        let retries = match num("capture_retries")? {
            None => 2,
            Some(n) if n.fract() == 0.0 && (0.0..=20.0).contains(&n) => n as u32,
            Some(n) => return Err(bad("capture_retries", format!("{n}: must be an integer in 0..=20"))),
        };
        let saturation_fraction = match num("saturation_fraction")? {
            None => 0.02,
            Some(f) if f > 0.0 && f <= 1.0 => f,
            Some(f) => return Err(bad("saturation_fraction", format!("{f}: must be in (0, 1]"))),
        };
        let saturation = match spec.options.get("saturation") {
            None => SaturationPolicy::Flag,
            Some(v) => match v.as_str() {
                Some("flag") => SaturationPolicy::Flag,
                Some("reexpose") => SaturationPolicy::Reexpose,
                _ => return Err(bad("saturation", format!("{v}: use \"flag\" or \"reexpose\""))),
            },
        };
        Ok(CapturePolicy {
            timeout: Duration::from_secs_f64(timeout),
            retries,
            saturation,
            saturation_fraction,
            max_reexposures: 3,
        })
    }
}

/// What it took to get a measurement's frame; default = nothing unusual.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CaptureNotes {
    /// Attempts beyond the first (failed, timed out or stale).
    pub retries: u32,
    /// Why each retry was needed, in order.
    pub faults: Vec<String>,
    /// Fraction of values at max DN, when above the threshold and stored anyway.
    pub saturated: Option<f64>,
    /// Exposure halvings under `Reexpose`.
    pub reexposures: u32,
    /// Factor to bring the stored image to the nominal exposure (`Some` after a re-exposure).
    pub exposure_scale: Option<f32>,
}

impl CaptureNotes {
    /// The record's `extra` fields for these notes (none when nothing happened, so records of
    /// undisturbed measurements are unchanged).
    pub fn write_extra(&self, extra: &mut serde_json::Value) {
        if self.retries > 0 {
            extra["capture_retries"] = serde_json::json!(self.retries);
            extra["capture_faults"] = serde_json::json!(self.faults);
        }
        if let Some(f) = self.saturated {
            extra["saturated"] = serde_json::json!(true);
            extra["saturated_fraction"] = serde_json::json!(f);
        }
        if self.reexposures > 0 {
            extra["reexposures"] = serde_json::json!(self.reexposures);
            extra["exposure_scale"] = serde_json::json!(self.exposure_scale);
        }
    }
}

/// The camera failed after every attempt the policy allows.
#[derive(Debug)]
pub struct CaptureFailed {
    pub attempts: u32,
    pub source: DeviceError,
}

/// Fraction of the frame's values at the maximum DN.
pub fn saturated_fraction(frame: &Frame) -> f64 {
    if frame.data.is_empty() {
        return 0.0;
    }
    let max = frame.max_dn();
    frame.data.iter().filter(|&&v| v >= max).count() as f64 / frame.data.len() as f64
}

/// Errors worth another attempt: the next frame may well be fine. A disconnected camera or
/// a refused command will not get better by asking again.
fn retriable(e: &DeviceError) -> bool {
    matches!(
        e,
        DeviceError::Timeout { .. } | DeviceError::Other { .. } | DeviceError::Garbled { .. }
    )
}

/// Capture one frame, retrying timeouts, errors and stale frames as the policy allows.
/// `still_at`: rig-clock time the rig became still, when frame timestamps are on that clock.
pub(super) async fn capture_fresh(
    camera: &dyn Camera,
    policy: &CapturePolicy,
    still_at: Option<f64>,
    notes: &mut CaptureNotes,
) -> Result<Frame, CaptureFailed> {
    let mut attempt = 0;
    loop {
        attempt += 1;
        let error = match tokio::time::timeout(policy.timeout, camera.capture()).await {
            Ok(Ok(frame)) => match still_at {
                Some(t) if frame.meta.timestamp < t => DeviceError::Other {
                    device: camera.name().to_string(),
                    command: "capture".into(),
                    reason: format!(
                        "stale frame (sequence {}, exposed at {:.3} s, before the rig was still at {t:.3} s)",
                        frame.meta.sequence, frame.meta.timestamp
                    ),
                },
                _ => return Ok(frame),
            },
            Ok(Err(e)) => e,
            Err(_) => DeviceError::Timeout {
                device: camera.name().to_string(),
                command: "capture".into(),
                seconds: policy.timeout.as_secs_f64(),
            },
        };
        if !retriable(&error) || attempt > policy.retries {
            return Err(CaptureFailed {
                attempts: attempt,
                source: error,
            });
        }
        tracing::warn!(camera = camera.name(), attempt, %error, "capture failed; retrying");
        notes.retries += 1;
        notes.faults.push(error.to_string());
    }
}

/// Capture the frame of one measurement under the policy (see the module docs).
/// `config` is the configuration the camera reported at setup (the nominal exposure).
pub async fn capture_measurement(
    camera: &dyn Camera,
    policy: &CapturePolicy,
    config: &CameraConfig,
    still_at: Option<f64>,
) -> Result<(Frame, CaptureNotes), CaptureFailed> {
    let mut notes = CaptureNotes::default();
    let mut frame = capture_fresh(camera, policy, still_at, &mut notes).await?;
    let mut fraction = saturated_fraction(&frame);
    if fraction <= policy.saturation_fraction {
        return Ok((frame, notes));
    }
    if policy.saturation == SaturationPolicy::Reexpose {
        let mut exposure = config.exposure;
        while fraction > policy.saturation_fraction && notes.reexposures < policy.max_reexposures {
            let wanted = exposure / 2.0;
            let setup = |exposure: f64| CameraConfig {
                exposure,
                ..config.clone()
            };
            let got = camera
                .configure(&setup(wanted))
                .await
                .map_err(|source| CaptureFailed { attempts: 1, source })?;
            if got.exposure >= exposure * 0.99 {
                tracing::warn!(
                    camera = camera.name(),
                    "camera refuses a shorter exposure: frame flagged saturated"
                );
                break;
            }
            exposure = got.exposure;
            notes.reexposures += 1;
            let captured = capture_fresh(camera, policy, still_at, &mut notes).await;
            // Back to the nominal exposure whatever happened, so the next measurement is normal.
            camera
                .configure(config)
                .await
                .map_err(|source| CaptureFailed { attempts: 1, source })?;
            frame = captured?;
            fraction = saturated_fraction(&frame);
            notes.exposure_scale = Some((config.exposure / frame.meta.exposure.max(1e-12)) as f32);
        }
    }
    if fraction > policy.saturation_fraction {
        notes.saturated = Some(fraction);
    }
    Ok((frame, notes))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(options: &str) -> CameraSpec {
        toml::from_str(&format!(
            "width = 8\nheight = 8\nfocal_length_px = 10.0\nbit_depth = 12\nexposure_s = 0.5\nreadout_s = 0.05\noptions = {{ {options} }}"
        ))
        .unwrap()
    }

    #[test]
    fn policy_defaults_and_refusals() {
        let p = CapturePolicy::from_spec(&spec("")).unwrap();
        assert_eq!(p.retries, 2);
        assert_eq!(p.saturation, SaturationPolicy::Flag);
        assert!((p.timeout.as_secs_f64() - 32.2).abs() < 1e-9);
        let p = CapturePolicy::from_spec(&spec(
            "capture_timeout_s = 2, capture_retries = 0, saturation = \"reexpose\", saturation_fraction = 0.5",
        ))
        .unwrap();
        assert_eq!(
            (p.retries, p.saturation, p.saturation_fraction),
            (0, SaturationPolicy::Reexpose, 0.5)
        );
        for (o, key) in [
            ("capture_timeout_s = -1", "capture_timeout_s"),
            ("capture_retries = 1.5", "capture_retries"),
            ("capture_retries = \"x\"", "capture_retries"),
            ("saturation = \"ignore\"", "saturation"),
            ("saturation_fraction = 0", "saturation_fraction"),
        ] {
            let e = CapturePolicy::from_spec(&spec(o)).unwrap_err();
            assert!(e.to_string().contains(&format!("camera.options.{key}")), "{o}: {e}");
        }
    }

    /// A camera whose driver call hangs (a DSLR that stops answering mid-capture, faked by
    /// a call that never returns) behind the gphoto2 backend's deadline
    /// (`gonio_devices::gphoto2::wait_until`, on the blocking pool as the backend runs it):
    /// each capture ends in the backend's typed `Timeout`, the policy retries it
    /// `capture_retries` times, notes each, and then fails with that error (the camera and
    /// the limit named), so the run ends instead of hanging.
    #[test]
    fn a_hung_driver_call_times_out_is_retried_and_then_ends_the_capture() {
        use gonio_devices::gphoto2::{wait_until, Deadline};
        use std::sync::atomic::{AtomicU32, Ordering};
        use std::sync::{Arc, Mutex};

        struct Hung {
            state: Arc<Mutex<()>>,
            calls: AtomicU32,
        }
        #[async_trait::async_trait]
        impl Camera for Hung {
            fn name(&self) -> &str {
                "gphoto2 Nikon DSC D750 on usb:001,001"
            }
            async fn configure(&self, c: &CameraConfig) -> Result<CameraConfig, DeviceError> {
                Ok(c.clone())
            }
            async fn capture(&self) -> Result<Frame, DeviceError> {
                self.calls.fetch_add(1, Ordering::SeqCst);
                let name = self.name().to_string();
                gonio_devices::camera::blocking_call(&name.clone(), "capture", &self.state, move |_| {
                    let mut never = std::future::pending::<Frame>();
                    wait_until(&name, "capture", &mut never, Deadline::after(Duration::from_millis(20)))
                })
                .await
            }
        }
        let cam = Hung {
            state: Arc::new(Mutex::new(())),
            calls: AtomicU32::new(0),
        };
        // The policy's own limit is far longer: the backend's deadline is what ends each try.
        let policy = CapturePolicy::from_spec(&spec("capture_timeout_s = 600, capture_retries = 2")).unwrap();
        let config = CameraConfig {
            width: 8,
            height: 8,
            exposure: 0.5,
            gain: 1.0,
            bit_depth: 16,
        };
        let rt = tokio::runtime::Runtime::new().unwrap();
        let failed = rt
            .block_on(capture_measurement(&cam, &policy, &config, None))
            .expect_err("a hung camera gave a frame");
        assert_eq!(failed.attempts, 3);
        assert_eq!(cam.calls.load(Ordering::SeqCst), 3);
        match &failed.source {
            DeviceError::Timeout { device, command, .. } => {
                assert_eq!((device.as_str(), command.as_str()), (cam.name(), "capture"))
            }
            other => panic!("not the backend's timeout: {other:?}"),
        }
        assert!(
            failed.source.to_string().contains("timed out after 0.020 s"),
            "{}",
            failed.source
        );
    }

    #[test]
    fn saturated_fraction_counts_max_dn() {
        let mut f = Frame {
            width: 2,
            height: 1,
            data: vec![4095, 0, 4095, 10, 4095, 4094],
            meta: gonio_devices::FrameMeta {
                timestamp: 0.0,
                exposure: 1.0,
                gain: 1.0,
                sequence: 0,
                bit_depth: 12,
            },
        };
        assert!((saturated_fraction(&f) - 0.5).abs() < 1e-12);
        f.data.clear();
        assert_eq!(saturated_fraction(&f), 0.0);
    }
}
