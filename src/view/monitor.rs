//! Progress of a dataset, read from its directory only (manifest, journal and drift
//! references), so that the
//! monitor works the same on a dataset written by another process (`gonio acquire`) as on
//! one written in-process: nothing here talks to the rig, and nothing can move it.

use gonio_dataset::store::{self, MeasurementStatus};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::Path;

/// One planned pair as the timeline shows it: `(order, index, kind)`, kind 0 measured,
/// 1 substituted, 2 skipped.
pub type TimelineEntry = (usize, usize, u8);

/// The last stored measurement.
#[derive(Serialize, Clone, Debug, PartialEq)]
pub struct LastMeasurement {
    pub index: usize,
    pub order: usize,
    pub light_deg: [f64; 2],
    pub view_deg: [f64; 2],
    pub axes_deg: Vec<f64>,
    pub rig_time_s: f64,
    pub wall_time_unix: f64,
    /// Whether it has an image (`/api/frame?index=…`).
    pub has_image: bool,
}

/// What the monitor page shows.
#[derive(Serialize, Clone, Debug, PartialEq)]
pub struct Snapshot {
    /// Journal records the plan will write (its steps and skipped pairs; lights × views
    /// without a plan): what progress and ETA count against.
    pub total: usize,
    /// Journal records (measured + substituted + skipped).
    pub done: usize,
    pub measured: usize,
    pub substituted: usize,
    pub skipped: usize,
    /// `reason → count` of skipped pairs.
    pub skipped_reasons: BTreeMap<String, usize>,
    /// `manifest.json` says the acquisition finished.
    pub complete: bool,
    /// Stored measurements per wall-clock second over the journal so far.
    pub rate_per_s: Option<f64>,
    /// Remaining pairs at that rate, seconds.
    pub eta_s: Option<f64>,
    pub last: Option<LastMeasurement>,
    /// In plan order.
    pub timeline: Vec<TimelineEntry>,
    /// `(order, truth RMSE)` of measurements compared with the simulator's truth.
    pub truth_rmse: Vec<(usize, f64)>,
    /// The summary's stage seconds once the acquisition has finished (`null` before).
    pub stage_seconds: serde_json::Value,
    /// Bytes of the journal read (the page's "something changed" marker).
    pub journal_bytes: u64,
    /// An adaptive acquisition's rounds so far (empty for any other plan): the total above
    /// grows as rounds are recorded, so progress and ETA count the chosen pairs.
    pub rounds: Vec<RoundProgress>,
    /// Why an adaptive acquisition stopped choosing rounds, once it has.
    pub adaptive_finished: Option<String>,
    /// Drift references so far (`gonio acquire --reference-every`), in the order taken;
    /// empty without them.
    pub references: Vec<ReferencePoint>,
    /// Why `references.jsonl` could not be read (the list is then empty).
    pub references_error: Option<String>,
}

/// One drift reference as the monitor shows it.
#[derive(Serialize, Clone, Debug, PartialEq)]
pub struct ReferencePoint {
    pub number: usize,
    /// The run that took it (0, +1 per `--resume`): rig times compare within a run only.
    pub run: usize,
    pub rig_time_s: f64,
    /// The last measurement stored before it (`None`: none yet).
    pub after_index: Option<usize>,
    /// Per channel: its level over the first reference's.
    pub ratio: [f64; 3],
    /// The largest relative change of any channel against the first reference (0.02 = 2 %).
    pub drift: f64,
}

/// Size of `references.jsonl` (0 when there is none): with the journal's, what says the
/// monitor's data changed.
pub fn references_len(dir: &Path) -> u64 {
    std::fs::metadata(dir.join(store::REFERENCES_FILE))
        .map(|m| m.len())
        .unwrap_or(0)
}

/// The drift references of the dataset in `dir`, or why they could not be read.
fn references(dir: &Path) -> (Vec<ReferencePoint>, Option<String>) {
    match store::load_references(dir) {
        Ok(refs) => (
            refs.iter()
                .map(|r| ReferencePoint {
                    number: r.number,
                    run: r.run,
                    rig_time_s: r.rig_time_s,
                    after_index: r.after_index,
                    ratio: r.ratio,
                    drift: r.drift(),
                })
                .collect(),
            None,
        ),
        Err(e) => (Vec::new(), Some(e.to_string())),
    }
}

/// One adaptive round as the monitor shows it.
#[derive(Serialize, Clone, Debug, PartialEq)]
pub struct RoundProgress {
    pub round: usize,
    pub pairs: usize,
    /// Of them, stored in the journal.
    pub done: usize,
    /// Predicted PSNR before (none before round 1) and after the round (dB).
    pub predicted_psnr_before_db: Option<f64>,
    pub predicted_psnr_after_db: f64,
    pub outside_prior: bool,
}

/// The rounds of an adaptive plan (`plan.json` `sparse.adaptive`), with how many of each
/// round's pairs the journal holds.
fn rounds(plan: &serde_json::Value, stored: &std::collections::HashSet<usize>) -> (Vec<RoundProgress>, Option<String>) {
    let Some(ad) = plan.get("sparse").and_then(|s| s.get("adaptive")) else {
        return (Vec::new(), None);
    };
    let f = |r: &serde_json::Value, k: &str| r.get(k).and_then(|v| v.as_f64()).unwrap_or(f64::NAN);
    let list = ad
        .get("rounds")
        .and_then(|r| r.as_array())
        .map(|rs| {
            rs.iter()
                .map(|r| {
                    let pairs: Vec<usize> = r
                        .get("pairs")
                        .and_then(|p| p.as_array())
                        .map(|a| a.iter().filter_map(|x| x.as_u64()).map(|x| x as usize).collect())
                        .unwrap_or_default();
                    RoundProgress {
                        round: r.get("round").and_then(|v| v.as_u64()).unwrap_or(0) as usize,
                        pairs: pairs.len(),
                        done: pairs.iter().filter(|p| stored.contains(p)).count(),
                        predicted_psnr_before_db: r.get("predicted_psnr_before_db").and_then(|v| v.as_f64()),
                        predicted_psnr_after_db: f(r, "predicted_psnr_after_db"),
                        outside_prior: r.get("outside_prior").and_then(|v| v.as_bool()).unwrap_or(false),
                    }
                })
                .collect()
        })
        .unwrap_or_default();
    let finished = ad.get("finished").and_then(|v| v.as_str()).map(str::to_string);
    (list, finished)
}

/// Size of the journal file (0 when it does not exist yet).
pub fn journal_len(dir: &Path) -> u64 {
    std::fs::metadata(dir.join(store::JOURNAL_FILE))
        .map(|m| m.len())
        .unwrap_or(0)
}

/// The journal records the plan will write (its steps and skipped pairs), from
/// `plan.json`: a sparse or isotropic plan measures fewer pairs than the grid holds, and
/// progress and ETA count against what is planned. `None` when there is no readable plan
/// (an imported dataset): then the grid counts.
fn planned_records(plan: &serde_json::Value) -> Option<usize> {
    let len = |k: &str| plan.get(k).and_then(|a| a.as_array()).map(Vec::len);
    Some(len("steps")? + len("skipped").unwrap_or(0))
}

fn read_plan(dir: &Path) -> Option<serde_json::Value> {
    let bytes = std::fs::read(dir.join(store::PLAN_FILE)).ok()?;
    serde_json::from_slice(&bytes).ok()
}

/// Read the dataset in `dir` as it is now.
pub fn snapshot(dir: &Path) -> Result<Snapshot, store::StoreError> {
    let journal_bytes = journal_len(dir);
    let (header, mut records) = store::load(dir)?;
    let n = |k: &str| header.sweep.get(k).and_then(|a| a.as_array()).map_or(0, |a| a.len());
    let plan = read_plan(dir);
    let total = plan
        .as_ref()
        .and_then(planned_records)
        .unwrap_or_else(|| n("lights_deg") * n("views_deg"));
    let stored: std::collections::HashSet<usize> = records.iter().map(|r| r.index).collect();
    let (rounds, adaptive_finished) = plan.as_ref().map(|p| rounds(p, &stored)).unwrap_or_default();
    records.sort_by_key(|r| (r.order, r.index));
    let manifest: serde_json::Value = std::fs::read(dir.join(store::MANIFEST_FILE))
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok())
        .unwrap_or_default();
    let complete = manifest.get("complete").and_then(|c| c.as_bool()).unwrap_or(false);
    let stage_seconds = manifest
        .get("summary")
        .and_then(|s| s.get("stage_seconds"))
        .cloned()
        .unwrap_or(serde_json::Value::Null);
    let (references, references_error) = references(dir);
    let mut s = Snapshot {
        total,
        done: records.len(),
        measured: 0,
        substituted: 0,
        skipped: 0,
        skipped_reasons: BTreeMap::new(),
        complete,
        rate_per_s: None,
        eta_s: None,
        last: None,
        timeline: Vec::with_capacity(records.len()),
        truth_rmse: Vec::new(),
        stage_seconds,
        journal_bytes,
        rounds,
        adaptive_finished,
        references,
        references_error,
    };
    for r in &records {
        let kind = match &r.status {
            MeasurementStatus::Measured => {
                s.measured += 1;
                0
            }
            MeasurementStatus::Substituted { .. } => {
                s.substituted += 1;
                1
            }
            // A completed dataset's predicted pairs were never on the rig: not a step.
            MeasurementStatus::Predicted { .. } => continue,
            MeasurementStatus::Skipped { reason } => {
                s.skipped += 1;
                *s.skipped_reasons.entry(reason.clone()).or_default() += 1;
                2
            }
        };
        s.timeline.push((r.order, r.index, kind));
        if let Some(e) = r.extra.get("truth_rmse").and_then(|x| x.as_f64()) {
            s.truth_rmse.push((r.order, e));
        }
    }
    // Predicted pairs (a completed sparse dataset) were never planned steps.
    s.done = s.measured + s.substituted + s.skipped;
    let stored: Vec<_> = records
        .iter()
        .filter(|r| {
            matches!(
                r.status,
                MeasurementStatus::Measured | MeasurementStatus::Substituted { .. }
            )
        })
        .collect();
    if let Some(r) = stored
        .iter()
        .max_by(|a, b| a.wall_time_unix.total_cmp(&b.wall_time_unix))
    {
        s.last = Some(LastMeasurement {
            index: r.index,
            order: r.order,
            light_deg: r.light_deg,
            view_deg: r.view_deg,
            axes_deg: if r.axes_read_back_deg.is_empty() {
                r.axes_commanded_deg.clone()
            } else {
                r.axes_read_back_deg.clone()
            },
            rig_time_s: r.rig_time_s,
            wall_time_unix: r.wall_time_unix,
            has_image: r.image.is_some(),
        });
    }
    if stored.len() >= 2 {
        let t0 = stored.iter().map(|r| r.wall_time_unix).fold(f64::INFINITY, f64::min);
        let t1 = stored
            .iter()
            .map(|r| r.wall_time_unix)
            .fold(f64::NEG_INFINITY, f64::max);
        if t1 > t0 {
            let rate = (stored.len() - 1) as f64 / (t1 - t0);
            s.rate_per_s = Some(rate);
            if !complete {
                s.eta_s = Some(total.saturating_sub(s.done) as f64 / rate);
            }
        }
    }
    if complete {
        s.eta_s = Some(0.0);
    }
    Ok(s)
}
