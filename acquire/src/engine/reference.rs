//! Drift references during a run (`gonio acquire --reference-every MINUTES`).
//!
//! Before the run's first measurement, then at the first measurement boundary after at
//! least `every_s` of rig time since the last reference, and once more when the run ends
//! (so the last measurements lie between two references; not when it pauses, see
//! [`closing_due`]), the drive loop measures the
//! reference pair (stop and go, one exposure under the capture policy) and a dark frame
//! (same pose and exposure, light off). Switching the light costs rig time, charged
//! honestly: `settle_s` after switching it off and again after switching it on, plus the
//! lamp's warm-up for a lamp that measures ([`Rig::warm_up_lamp`]).
//!
//! The store thread develops both frames with the measurements' chain, takes the
//! per-channel mean of reference − dark over the rectified sample, and stores them
//! (`Dataset::store_reference`: images renamed into place, then the line in
//! `references.jsonl`), after the measurement before it is committed, so the record's
//! position in the journal is exact.

use super::EngineError;
use crate::plan::Step;
use crate::rig::{CapturePolicy, Rig};
use gonio_devices::image::RgbImage;
use gonio_devices::{CameraConfig, Frame, LampReading};

/// Noise identities of reference frames: far above any canonical pair index, two per
/// reference (the reference, then its dark frame), so a simulated run is reproducible.
const NOISE_KEY_BASE: u64 = 1 << 40;

/// What the session asks of the engine.
#[derive(Clone, Debug)]
pub struct ReferencePlan {
    /// Rig seconds between references (at least).
    pub every_s: f64,
    /// The reference pair's step of the plan (measured stop and go even in a fly plan).
    pub step: Step,
    /// Seconds to wait after switching the light (`light.options.settle_s` for the
    /// simulated lamp; 0 for a driver that waits itself after switching, as the HMP's).
    pub settle_s: f64,
    /// Relative drift of any channel that warns (the lamp monitor's `drift_threshold`).
    pub drift_threshold: f64,
}

/// The schedule: when the last reference was taken (rig clock of this process).
#[derive(Clone, Copy, Debug, Default)]
pub struct Schedule {
    pub last_at: Option<f64>,
}

impl Schedule {
    /// A reference is due at rig time `now`: none yet in this process, or `every_s` passed.
    pub fn due(&self, now: f64, every_s: f64) -> bool {
        self.last_at.is_none_or(|t| now - t >= every_s)
    }
}

/// Whether the run takes a closing reference as it ends: when it measured since its last
/// reference and did not pause. A pause (Ctrl-C) stops at the measurement boundary without
/// it, so the operator does not wait for a move, two exposures and two light settles: the
/// resumed run starts with its own reference (every run does), and the measurements after
/// the pause's last reference keep that reference's ratio (rig times of two runs do not
/// compare, so `gonio dataset drift` would not interpolate across them anyway). A run that
/// completes, ends at `--limit` or between adaptive rounds takes it.
pub fn closing_due(measured_since_reference: bool, paused: bool) -> bool {
    measured_since_reference && !paused
}

/// A reference captured by the drive loop, on its way to the store thread.
pub(super) struct ReferenceJob {
    pub step: Step,
    pub frame: Frame,
    pub dark: Frame,
    pub q_read: Vec<f64>,
    /// Rig time at the end of the reference exposure.
    pub rig_time: f64,
    /// Rig seconds the whole reference took.
    pub duration_s: f64,
    pub exposure_scale: Option<f32>,
    /// The lamp's reading right after the reference exposure (lights that measure).
    pub reading: Option<LampReading>,
    /// The lamp monitor's output correction at that reading (a calibrated exponent), the
    /// same the measurements get, so a reference tracks what the correction leaves.
    pub output_correction: Option<f64>,
}

/// Drive one reference: reach the pair, capture it, switch the light off, capture the
/// dark frame, switch it on again; `number` is its dataset-wide number (noise identity).
pub(super) async fn drive(
    rig: &Rig,
    plan: &ReferencePlan,
    number: usize,
    policy: &CapturePolicy,
    config: &CameraConfig,
) -> Result<(ReferenceJob, f64), EngineError> {
    let index = plan.step.index;
    let dev = |source| EngineError::Device { index, source };
    let failed = |f: crate::rig::CaptureFailed| EngineError::Capture {
        index,
        attempts: f.attempts,
        source: f.source,
    };
    let t0 = rig.time();
    let q: Vec<f64> = plan.step.axes_deg.iter().map(|d| d.to_radians()).collect();
    let q_read = rig.reach(&q).await.map_err(dev)?;
    rig.camera.begin_measurement(NOISE_KEY_BASE + 2 * number as u64);
    let (frame, notes) = rig.capture(policy, config).await.map_err(failed)?;
    let rig_time = rig.time();
    let reading = rig.light.read_back().await.map_err(dev)?;
    rig.light.set(false, 0.0).await.map_err(dev)?;
    rig.wait_until(rig.time() + plan.settle_s).await;
    rig.camera.begin_measurement(NOISE_KEY_BASE + 2 * number as u64 + 1);
    let (dark, _) = rig.capture(policy, config).await.map_err(failed)?;
    rig.light.set(true, 1.0).await.map_err(dev)?;
    rig.wait_until(rig.time() + plan.settle_s).await;
    rig.warm_up_lamp().await.map_err(dev)?;
    let job = ReferenceJob {
        step: plan.step.clone(),
        frame,
        dark,
        q_read,
        rig_time,
        duration_s: rig.time() - t0,
        exposure_scale: notes.exposure_scale,
        reading,
        output_correction: None,
    };
    Ok((job, rig.time() - t0))
}

/// Per-channel mean of `image − dark` over every finite texel.
pub(super) fn dark_subtracted_mean(image: &RgbImage, dark: &RgbImage) -> [f64; 3] {
    let mut sum = [0.0f64; 3];
    let mut n = [0usize; 3];
    for (i, (a, b)) in image.data.iter().zip(&dark.data).enumerate() {
        let v = *a as f64 - *b as f64;
        if v.is_finite() {
            sum[i % 3] += v;
            n[i % 3] += 1;
        }
    }
    std::array::from_fn(|c| sum[c] / n[c].max(1) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schedule_is_due_at_the_start_and_after_the_interval() {
        let mut s = Schedule::default();
        assert!(s.due(0.0, 60.0), "the first reference is due at once");
        s.last_at = Some(10.0);
        assert!(!s.due(69.9, 60.0));
        assert!(s.due(70.0, 60.0));
    }

    #[test]
    fn a_pause_skips_the_closing_reference() {
        assert!(closing_due(true, false), "a run that ends closes with one");
        assert!(!closing_due(true, true), "a paused run does not wait for one");
        assert!(!closing_due(false, false), "nothing measured since the last one");
    }

    #[test]
    fn the_mean_is_per_channel_and_dark_subtracted() {
        let img = RgbImage {
            width: 2,
            height: 1,
            data: vec![1.0, 2.0, 3.0, 3.0, 4.0, 5.0],
        };
        let dark = RgbImage {
            width: 2,
            height: 1,
            data: vec![0.5; 6],
        };
        assert_eq!(dark_subtracted_mean(&img, &dark), [1.5, 2.5, 3.5]);
    }
}
