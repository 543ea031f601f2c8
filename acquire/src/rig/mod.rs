//! The assembled rig and how to step it: the floor under the acquisition engine and the
//! calibration recipes.
//!
//! [`Rig`] holds the hardware as trait objects (axes, camera, light) plus the kinematics,
//! built from a rig file ([`Rig::build`], `build.rs`); a simulated rig also offers the
//! ground truth ([`GroundTruth`], `truth.rs`). One step of any plan, acquisition or
//! calibration alike, is the same two calls:
//!
//! 1. [`Rig::reach`]: every axis starts at once, all are waited for (the slowest ends the
//!    move), and the camera is told the rig is still (a streaming camera then drops frames
//!    exposed during the move);
//! 2. [`Rig::capture`]: a frame under the [`CapturePolicy`] (`capture.rs`: capture timeout,
//!    bounded retries of timeouts, errors and stale frames, saturated frames flagged or
//!    re-exposed); or, with HDR on, [`Rig::capture_bracket`]: the measurement's exposure
//!    bracket (`bracket.rs`) under the same policy.
//!
//! So a calibration gets the same timeouts, retries and stale-frame rule as an acquisition,
//! and a fault reads the same in both. This folder imports no other folder of `src/`.

pub mod backends;
pub mod bracket;
mod build;
pub mod capture;
pub mod check;
mod truth;

pub use backends::{Backends, RigBuildError};
pub use bracket::{BracketNotes, SampleRegion};
pub use build::{MirroredAxis, MirroredLight};
pub use capture::{CaptureFailed, CaptureNotes, CapturePolicy, SaturationPolicy};
pub use truth::{GroundTruth, MechanicalErrors, SensorResponse, SensorTruth};

use gonio_devices::kinematics::Kinematics;
use gonio_devices::rig::RigSpec;
use gonio_devices::target::MarkerBorder;
use gonio_devices::{Axis, Camera, CameraConfig, DeviceError, Frame, Light};
use gonio_simulator::clock::SimClock;
use std::sync::Arc;

pub struct Rig {
    pub spec: RigSpec,
    pub kinematics: Box<dyn Kinematics>,
    pub axes: Vec<Arc<dyn Axis>>,
    pub camera: Arc<dyn Camera>,
    pub light: Arc<dyn Light>,
    /// How a run watches the lamp's read-back (rig file `light.options`).
    pub lamp_monitor: gonio_devices::rig::LampMonitor,
    /// How [`Rig::prepare`] waits for a real lamp to warm up (`None`: a simulated lamp).
    pub lamp_warmup: Option<gonio_devices::rig::LampWarmup>,
    pub truth: Option<Arc<dyn GroundTruth>>,
    /// The simulated rig's clock (virtual time); `None` on real hardware (wall time).
    /// `None` with `truth` `None` and no shadows: the rig built no simulator at all.
    pub clock: Option<Arc<SimClock>>,
    /// The holder's marker border and the sample edge length (mm), for rectification: the
    /// rendered sample's with a simulated camera, the rig file's with a real one
    /// (`RigSpec::holder_geometry`).
    pub border: MarkerBorder,
    pub sample_mm: f64,
    started: std::time::Instant,
    /// The simulated axis behind each serial axis of a mixed rig (what its simulated camera
    /// renders), by axis index; `None` for simulated axes.
    shadows: Vec<Option<Arc<gonio_simulator::devices::SimAxis>>>,
    /// Rig-clock time the rig last became still (set by [`Rig::reach`]), when frame
    /// timestamps are on that clock: the stale-frame rule's reference.
    still_at: std::sync::Mutex<Option<f64>>,
}

impl Rig {
    /// Seconds on the rig's clock: virtual for a simulated rig, wall time otherwise.
    pub fn time(&self) -> f64 {
        match &self.clock {
            Some(c) => c.now(),
            None => self.started.elapsed().as_secs_f64(),
        }
    }

    /// Wait until rig-clock time `t` (virtual on a simulated rig, a sleep otherwise): a
    /// fly-scan times its kickoff and exposures on this clock.
    pub async fn wait_until(&self, t: f64) {
        match &self.clock {
            Some(c) => c.wait_until(t).await,
            None => {
                // tokio's timer has millisecond granularity and wakes late by up to one
                // tick; an exposure planned against a stage moving at 20 °/s must start
                // within a fraction of that. Sleep to within SPIN_S, then yield until due.
                const SPIN_S: f64 = 0.002;
                let dt = t - self.time();
                if dt > SPIN_S {
                    tokio::time::sleep(std::time::Duration::from_secs_f64(dt - SPIN_S)).await;
                }
                while self.time() < t {
                    tokio::task::yield_now().await;
                }
            }
        }
    }

    /// Show the simulated camera of a mixed rig axis `index` at `x` (radians) while the
    /// serial axis flies: the camera renders its shadow axes, which otherwise follow only
    /// settled read-backs. A no-op for a simulated axis (the camera sees it move).
    pub async fn show_pose(&self, index: usize, x: f64) -> Result<(), DeviceError> {
        let Some(Some(shadow)) = self.shadows.get(index) else {
            return Ok(());
        };
        build::mirror(shadow, x).await
    }

    /// Read back every axis now (radians, the rig's axis order).
    pub async fn positions(&self) -> Result<Vec<f64>, DeviceError> {
        let mut q = Vec::with_capacity(self.axes.len());
        for a in &self.axes {
            q.push(a.position().await?);
        }
        Ok(q)
    }

    /// Home every axis, switch the light on, wait for a real lamp to warm up
    /// ([`Rig::warm_up_lamp`]) and configure the camera from the rig file.
    /// Returns the configuration the camera applied.
    pub async fn prepare(&self) -> Result<CameraConfig, DeviceError> {
        for a in &self.axes {
            a.home().await?;
        }
        self.light.set(true, 1.0).await?;
        self.warm_up_lamp().await?;
        let c = &self.spec.camera;
        self.camera
            .configure(&CameraConfig {
                width: c.width,
                height: c.height,
                exposure: c.exposure_s,
                gain: c.gain,
                bit_depth: c.bit_depth,
            })
            .await
    }

    /// Wait until the lamp's current is stable (see `gonio_devices::rig::LampWarmup`): two
    /// readings `interval_s` apart within `tolerance`. Returns at once for a simulated lamp,
    /// a lamp that measures nothing, or `warmup_timeout_s` = 0; an error naming the lamp,
    /// the last change and the options to change when it is still changing at the timeout.
    pub async fn warm_up_lamp(&self) -> Result<(), DeviceError> {
        let Some(w) = self.lamp_warmup.filter(|w| w.timeout_s > 0.0) else {
            return Ok(());
        };
        let Some(mut last) = self.light.read_back().await? else {
            return Ok(());
        };
        let start = self.time();
        loop {
            self.wait_until(self.time() + w.interval_s).await;
            let Some(now) = self.light.read_back().await? else {
                return Ok(());
            };
            let change = (now.current_a - last.current_a).abs() / last.current_a.abs().max(1e-9);
            if change < w.tolerance {
                tracing::info!(
                    lamp = %self.light.name(),
                    current_a = now.current_a,
                    "lamp warm after {:.1} s",
                    self.time() - start
                );
                return Ok(());
            }
            if self.time() - start >= w.timeout_s {
                return Err(DeviceError::Other {
                    device: self.light.name().to_string(),
                    command: "lamp warm-up".into(),
                    reason: format!(
                        "the current still changes {:.2} % between readings {} s apart after {:.0} s \
                         (wanted < {:.2} %): check the lamp and its supply, or raise \
                         light.options.warmup_timeout_s or warmup_tolerance in the rig file",
                        change * 100.0,
                        w.interval_s,
                        self.time() - start,
                        w.tolerance * 100.0
                    ),
                });
            }
            last = now;
        }
    }

    /// Move every axis to `q` (radians, the rig's axis order): all start together, then all
    /// are waited for, then the camera is told the rig is still. Returns the read-back
    /// positions. A failure is the failing axis' typed error (it names the device).
    pub async fn reach(&self, q: &[f64]) -> Result<Vec<f64>, DeviceError> {
        for (axis, &target) in self.axes.iter().zip(q) {
            axis.start_move(target).await?;
        }
        // Every axis is already moving; waiting one after the other ends with the slowest.
        let mut read = Vec::with_capacity(q.len());
        for axis in &self.axes {
            read.push(axis.wait_idle().await?);
        }
        self.mark_still();
        Ok(read)
    }

    /// Move one axis alone (a mechanical calibration approaches a target from one side on
    /// purpose) and mark the rig still; returns its read-back.
    pub async fn reach_axis(&self, index: usize, target: f64) -> Result<f64, DeviceError> {
        let read = self.axes[index].move_abs(target).await?;
        self.mark_still();
        Ok(read)
    }

    /// Tell the camera the rig is still, and remember when (for the stale-frame rule).
    fn mark_still(&self) {
        self.camera.rig_still();
        let at = frames_on_rig_clock(&self.spec, self.clock.is_some()).then(|| self.time());
        *self.still_at.lock().expect("still_at poisoned") = at;
    }

    /// Capture one frame under `policy` (see [`capture`]); `config` is the camera
    /// configuration in force (the nominal exposure a re-exposure returns to).
    pub async fn capture(
        &self,
        policy: &CapturePolicy,
        config: &CameraConfig,
    ) -> Result<(Frame, CaptureNotes), CaptureFailed> {
        let still_at = *self.still_at.lock().expect("still_at poisoned");
        capture::capture_measurement(self.camera.as_ref(), policy, config, still_at).await
    }

    /// Capture the HDR bracket of the measurement at axes `q` (read back) under `policy`
    /// (see [`bracket`]); `config` is the nominal configuration, restored afterwards.
    pub async fn capture_bracket(
        &self,
        policy: &CapturePolicy,
        config: &CameraConfig,
        hdr: &gonio_devices::hdr::HdrSpec,
        q: &[f64],
    ) -> Result<(Vec<Frame>, CaptureNotes, BracketNotes), CaptureFailed> {
        let still_at = *self.still_at.lock().expect("still_at poisoned");
        let pose = self.kinematics.camera_pose(q);
        let region = SampleRegion::project(
            &pose,
            &self.spec.camera.intrinsics(),
            self.sample_mm,
            config.width,
            config.height,
        );
        let noise = hdr.noise(&self.spec.camera, config.gain);
        bracket::capture_bracket(self.camera.as_ref(), policy, config, hdr, &noise, &region, still_at).await
    }

    /// The capture policy of this rig's camera (rig file `camera.options`).
    pub fn capture_policy(&self) -> Result<CapturePolicy, DeviceError> {
        CapturePolicy::from_spec(&self.spec.camera)
    }

    /// The simulator's mechanical error model of axis `index`: the truth a mechanical
    /// calibration is checked against. `None` on hardware and for serial axes of a mixed rig
    /// (their errors are the real controller's, unknown to the simulator).
    pub fn mechanical_truth(&self, index: usize) -> Option<MechanicalErrors> {
        self.clock.as_ref()?;
        if self.spec.axes.get(index)?.backend != "sim" {
            return None;
        }
        self.truth.as_ref()?.mechanical_errors(index)
    }
}

/// Whether the stale-frame rule can judge a frame by its timestamp: only the simulated
/// camera stamps frames on the rig clock. A V4L2 camera stamps CLOCK_MONOTONIC and applies
/// its own rule after `rig_still`, also when the axes are simulated (the vivid campaign
/// found the engine refusing every vivid frame when this looked at the clock alone).
fn frames_on_rig_clock(spec: &RigSpec, rig_has_clock: bool) -> bool {
    rig_has_clock && spec.camera.backend == "sim"
}

#[cfg(test)]
mod stale_rule_tests {
    /// Regression (vivid campaign): simulated axes with a V4L2 camera must not have their
    /// frames judged on the rig clock.
    #[test]
    fn only_the_simulated_camera_is_judged_on_the_rig_clock() {
        let mut spec = gonio_devices::rig::RigSpec::default_rig();
        assert!(super::frames_on_rig_clock(&spec, true));
        assert!(!super::frames_on_rig_clock(&spec, false));
        spec.camera.backend = "v4l2".into();
        assert!(!super::frames_on_rig_clock(&spec, true));
    }
}
