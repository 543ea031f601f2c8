//! The summary of one run of a session (`gonio acquire`'s output and `--json`, and the
//! manifest's `summary` once complete).

use crate::calibrate::apply::{AppliedCalibration, VALUE_UNIT_DN};
use crate::engine::metrics::ErrorFigures;
use crate::engine::{RunReport, StageSeconds};
use crate::plan::Plan;
use gonio_devices::rig::RigSpec;
use gonio_simulator::SampleSpec;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashSet};

/// The summary printed at the end (and with --json).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Summary {
    pub dataset: String,
    pub rig: String,
    pub sample: String,
    pub sweep: String,
    pub pairs: usize,
    pub planned_measurements: usize,
    pub measured: usize,
    pub substituted: usize,
    pub skipped: usize,
    pub skipped_reasons: BTreeMap<String, usize>,
    pub stored_this_run: usize,
    pub already_done: usize,
    pub remaining: usize,
    pub complete: bool,
    pub paused: bool,
    pub planned_duration_s: f64,
    pub sweep_duration_s: f64,
    pub wall_time_s: f64,
    pub images_per_s: f64,
    pub truth_error: Option<ErrorFigures>,
    pub homography_from_markers: usize,
    pub homography_from_pose: usize,
    pub stage_seconds: StageSeconds,
    /// Peak resident memory of this process (MiB, from /proc/self/status VmHWM).
    pub peak_rss_mib: Option<f64>,
    /// Unit of the stored values: `normalized_dn` or (white-standard calibration applied)
    /// `brdf_per_sr`; the truth error is on the same scale.
    #[serde(default)]
    pub value_unit: String,
    /// Ids of the calibration results applied (comma-separated).
    #[serde(default)]
    pub calibration: Option<String>,
    /// Raw-frame corrections applied to every frame, in order (`response`, `dark`, `flat`,
    /// `colour`); empty without. Saturated pixels are counted per measurement
    /// (`extra.saturated_pixels` of its record).
    #[serde(default)]
    pub corrections: Vec<String>,
    /// Measurements whose lamp current or voltage drifted beyond the rig's threshold
    /// (`light.options.drift_threshold`; lights whose supply measures). Absent when 0.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub lamp_drift_warnings: usize,
    /// The lamp supply's identity (`*IDN?`), when the light measures.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lamp_identity: Option<String>,
    /// An adaptive acquisition's rounds and stop (`gonio acquire --adaptive`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptive: Option<AdaptiveSummary>,
    /// A fly-scan's frames: how many were exposed in flight and how many were retaken stop
    /// and go (`gonio acquire --fly`), over the whole dataset (resumed runs included).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fly: Option<FlySummary>,
    /// Drift references (`gonio acquire --reference-every`): how many, their cost and the
    /// largest drift, over the whole dataset (resumed runs included).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub references: Option<ReferenceSummary>,
}

/// What the drift references found (see `crate::engine::reference`).
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct ReferenceSummary {
    /// Minutes of rig time between references.
    pub every_min: f64,
    /// The reference pair: [light index, view index] into the sweep.
    pub pair: [usize; 2],
    /// References in the dataset, and taken by this run.
    pub count: usize,
    pub this_run: usize,
    /// Rig seconds this run's references took (moves, exposures, light settle times).
    pub overhead_s: f64,
    /// Largest relative change of any channel against the first reference (0.03 = 3 %).
    pub largest_drift: f64,
    /// References whose drift exceeded the threshold (`light.options.drift_threshold`).
    pub drift_warnings: usize,
}

impl ReferenceSummary {
    pub fn new(
        settings: &super::ReferenceSettings,
        all: &[gonio_dataset::store::ReferenceRecord],
        run: &crate::engine::ReferenceStats,
    ) -> ReferenceSummary {
        ReferenceSummary {
            every_min: settings.every_min,
            pair: settings.pair.unwrap_or_default(),
            count: all.len(),
            this_run: run.taken,
            overhead_s: run.overhead_s,
            largest_drift: all.iter().map(|r| r.drift()).fold(0.0, f64::max),
            drift_warnings: run.warnings,
        }
    }
}

/// What a fly-scan did, read from the journal's records (`extra.flight`).
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct FlySummary {
    /// Frames exposed while the axis moved and kept.
    pub flown: usize,
    /// Frames of a flight retaken stop and go (a capture retry in flight, or the
    /// mid-exposure directions off the planned ones by more than the tolerance).
    pub retaken_stop_and_go: usize,
}

impl FlySummary {
    /// Count the flown and retaken frames among `records`; None when none was flown.
    pub fn from_records(records: &[gonio_dataset::store::MeasurementRecord]) -> Option<FlySummary> {
        let mut s = FlySummary::default();
        for r in records {
            let f = &r.extra["flight"];
            if f.is_null() {
                continue;
            }
            if f.get("retaken_stop_and_go").is_some() {
                s.retaken_stop_and_go += 1;
            } else {
                s.flown += 1;
            }
        }
        (s != FlySummary::default()).then_some(s)
    }
}

/// What an adaptive acquisition did: its rounds, its prediction and why it stopped.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct AdaptiveSummary {
    /// Pairs per round, in order.
    pub rounds: Vec<usize>,
    /// Predicted PSNR of the completed dataset after the last analysis (dB, 8-bit sRGB;
    /// residual-aware), or the first round's prior prediction before any analysis.
    pub predicted_psnr_db: f64,
    /// The last analysis found the material outside the prior.
    pub outside_prior: bool,
    /// Why the run stopped choosing (absent while rounds may follow).
    pub finished: Option<String>,
    /// Planned rig time of the rounds plus the analysis allowances (s).
    pub planned_s: f64,
    /// Wall seconds the analyses between rounds took in this run (charged to the plan as
    /// the declared allowance per round).
    pub analysis_wall_s: f64,
}

impl AdaptiveSummary {
    pub fn new(ad: &crate::plan::adaptive::AdaptiveInfo, analysis_wall_s: f64) -> AdaptiveSummary {
        AdaptiveSummary {
            rounds: ad.rounds.iter().map(|r| r.pairs.len()).collect(),
            predicted_psnr_db: ad
                .predicted_psnr_db
                .or_else(|| ad.rounds.last().map(|r| r.predicted_psnr_after_db))
                .unwrap_or(0.0),
            outside_prior: ad.outside_prior,
            finished: ad.finished.clone(),
            planned_s: ad.spent_s(),
            analysis_wall_s,
        }
    }
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

impl Summary {
    /// The summary of a run of `plan` that started with `done` already stored.
    pub(super) fn new(
        dataset: &str,
        rig: &RigSpec,
        sample: &SampleSpec,
        plan: &Plan,
        done: &HashSet<usize>,
        report: &RunReport,
        calibration: Option<&AppliedCalibration>,
    ) -> Summary {
        let counts = plan.counts();
        let remaining = plan.steps.iter().filter(|s| !done.contains(&s.index)).count() - report.stored_this_run;
        Summary {
            dataset: dataset.to_string(),
            rig: rig.name.clone(),
            sample: sample.name.clone(),
            sweep: plan.sweep.clone(),
            pairs: plan.pairs,
            planned_measurements: plan.steps.len(),
            measured: counts.feasible,
            substituted: counts.substituted,
            skipped: counts.skipped,
            skipped_reasons: counts.skipped_reasons.clone(),
            stored_this_run: report.stored_this_run,
            already_done: report.already_done,
            remaining,
            complete: remaining == 0,
            paused: report.paused,
            planned_duration_s: plan.durations.optimized_s,
            sweep_duration_s: report.rig_time_s,
            wall_time_s: report.wall_time_s,
            images_per_s: report.stored_this_run as f64 / report.wall_time_s.max(1e-9),
            truth_error: report.truth_error.figures(),
            homography_from_markers: report.homography_from_markers,
            homography_from_pose: report.homography_from_pose,
            stage_seconds: report.stage_seconds.clone(),
            peak_rss_mib: peak_rss_mib(),
            value_unit: calibration.map_or(VALUE_UNIT_DN, |c| c.value_unit()).to_string(),
            calibration: calibration.map(|c| c.ids.join(",")),
            corrections: calibration.map(|c| c.corrections()).unwrap_or_default(),
            lamp_drift_warnings: report.lamp_drift_warnings,
            lamp_identity: report.lamp_identity.clone(),
            adaptive: None,
            fly: None,
            references: None,
        }
    }
}

/// Peak resident set size of this process in MiB (Linux), for the memory benchmark.
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}
