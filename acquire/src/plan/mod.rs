//! Sweep planning: which axis configuration measures each (light, view) pair, which pairs
//! are impossible and why, in what order, and how long it takes.
//!
//! A [`Plan`] is data: it is printed by `gonio plan`, stored with every dataset
//! (`plan.json`) and executed step by step by the acquisition engine, which resumes it
//! by skipping the steps the journal already holds.

pub mod adaptive;
pub mod fly;
pub mod isotropic;
pub mod order;
pub mod sparse;

use gonio_dataset::sweep::{Pair, Sweep};
use gonio_devices::kinematics::{self, Infeasibility, Kinematics};
use gonio_devices::rig::RigSpec;
use gonio_devices::{Direction, MotionModel};
use order::{Node, OrderOptions};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::time::{Duration, Instant};
use thiserror::Error;

#[derive(Debug, Error)]
pub enum PlanError {
    #[error("rig `{rig}` cannot measure any pair of sweep `{sweep}`: {reasons}. Widen the axis limits in the rig file or choose another sweep")]
    Empty {
        rig: String,
        sweep: String,
        reasons: String,
    },
    #[error("rig `{rig}`: {source}")]
    RigOption {
        rig: String,
        source: gonio_devices::rig::OptionError,
    },
    /// A sparse plan that cannot be made as asked (prior for another sweep, a target out of
    /// range, a design that cannot determine the prior).
    #[error("sparse plan: {message}")]
    Sparse { message: String },
    /// A fly-scan plan that cannot be made (a rig that cannot fly, a bad blur bound).
    #[error("fly-scan plan: {message}")]
    Fly { message: String },
    /// A plan asked to start from a pose the rig does not have (see [`Plan::build_pairs_from`]).
    #[error("plan start: {message}")]
    Start { message: String },
}

/// What to do with a pair the rig cannot measure as asked.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Policy {
    /// Leave it out; the dataset records it as skipped.
    #[default]
    Skip,
    /// Measure the nearest feasible light direction instead (as UTIA does) and record it.
    Substitute,
}

impl std::str::FromStr for Policy {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "skip" => Ok(Policy::Skip),
            "substitute" => Ok(Policy::Substitute),
            _ => Err(format!("unknown policy `{s}`: use `skip` or `substitute`")),
        }
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum StepStatus {
    Measure,
    Substitute {
        requested_light_deg: [f64; 2],
        reason: Infeasibility,
    },
}

/// One measurement in execution order.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Step {
    /// Canonical index (`view_index · L + light_index`).
    pub index: usize,
    pub light_index: usize,
    pub view_index: usize,
    /// Light direction actually measured (differs from the sweep's when substituted).
    pub light_deg: [f64; 2],
    pub view_deg: [f64; 2],
    pub status: StepStatus,
    /// Axis targets in the rig file's axis order (degrees).
    pub axes_deg: Vec<f64>,
    /// Planned motion time into this step (s) and planned start of its capture (s).
    pub transition_s: f64,
    pub capture_start_s: f64,
    /// Present when the step is exposed in flight (`gonio plan --fly`, [`fly`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flight: Option<fly::StepFlight>,
}

/// A pair left out, with the reason.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Skipped {
    pub index: usize,
    pub light_deg: [f64; 2],
    pub view_deg: [f64; 2],
    pub reason: Infeasibility,
}

/// Planned rig time. `optimized_s` is what the engine does: the optimized order with the
/// readout overlapping the next move where the camera allows it ([`Overlap`]).
/// `canonical_s` is the fixed reference every speed-up is stated against: canonical order,
/// stop and go (expose, read out, then move), as before the overlap existed.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Durations {
    /// Canonical order, stop and go (motion + full capture per pair), s: the reference.
    pub canonical_s: f64,
    /// Canonical order with the readout overlapping the move (equal to `canonical_s` when
    /// the camera does not overlap), s.
    #[serde(default)]
    pub canonical_overlapped_s: f64,
    /// Optimized order, stop and go, s.
    #[serde(default)]
    pub stop_and_go_s: f64,
    /// Optimized order as the engine runs it (readout overlapping the move when
    /// `readout_overlap_s` > 0), s.
    pub optimized_s: f64,
    /// A lower bound on the total time of any order in the engine's mode, s.
    pub lower_bound_s: f64,
    /// Capture time per measurement (exposure + readout, the whole HDR bracket with HDR), s.
    pub capture_per_measurement_s: f64,
    /// The part of each capture that overlaps the next move (the camera's readout; 0 when
    /// it cannot overlap), s.
    #[serde(default)]
    pub readout_overlap_s: f64,
    /// Motion time of the optimized order (its moves alone), s.
    pub optimized_motion_s: f64,
}

/// The timing of a capture whose last readout overlaps the next move.
///
/// A measurement exposes while the rig stands still; its readout `r` (the last one of an
/// HDR bracket) then runs while the axes already move to the next pair, and that pair's
/// exposure starts once both the move and the readout are done. So a transition of `d`
/// seconds costs `max(d, r)` after a measurement, `d` from home, and the run ends with one
/// readout. The order optimiser still minimises motion (`max(d, r)` is monotone in `d`, so
/// its neighbour lists are unchanged); the plan's times are exact for the order it returns.
/// With `r = 0` every figure is the stop-and-go one.
pub struct Overlap {
    readout: f64,
    capture: f64,
    first: bool,
}

impl Overlap {
    pub fn new(readout: f64, capture: f64) -> Overlap {
        Overlap {
            readout,
            capture,
            first: true,
        }
    }
    /// Time from the end of the last exposure (or from home) until the next exposure starts.
    pub fn wait(&mut self, transition: f64) -> f64 {
        if std::mem::replace(&mut self.first, false) {
            transition
        } else {
            transition.max(self.readout)
        }
    }
    /// Time the rig stands still for one measurement.
    pub fn still(&self) -> f64 {
        self.capture - self.readout
    }
    /// The readout after the last exposure (nothing follows it).
    pub fn last_readout(&self) -> f64 {
        if self.first {
            0.0
        } else {
            self.readout
        }
    }
    /// The total time of a route given its transitions in order.
    pub fn total(readout: f64, capture: f64, transitions: &[f64]) -> f64 {
        let mut o = Overlap::new(readout, capture);
        let mut t = 0.0;
        for &d in transitions {
            t += o.wait(d) + o.still();
        }
        t + o.last_readout()
    }
    /// A lower bound of any route over `n` measurements whose motion is at least `motion`:
    /// every transition after the first costs at least the readout.
    pub fn lower_bound(readout: f64, capture: f64, motion: f64, n: usize) -> f64 {
        if n == 0 {
            return 0.0;
        }
        motion.max((n - 1) as f64 * readout) + n as f64 * (capture - readout) + readout
    }
}

/// The transition times of a route, in its order (free axes resolved as the route runs).
fn canonical_transitions(nodes: &[Node], motions: &[MotionModel], home: &[f64], route: &order::Route) -> Vec<f64> {
    let mut prev = home.to_vec();
    route
        .order
        .iter()
        .zip(&route.choice)
        .map(|(&ni, &ci)| {
            let q: Vec<f64> = nodes[ni].candidates[ci]
                .iter()
                .zip(&prev)
                .map(|(&x, &p)| if x.is_nan() { p } else { x })
                .collect();
            let dt = kinematics::transition_time(motions, &prev, &q);
            prev = q;
            dt
        })
        .collect()
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Plan {
    pub rig: String,
    pub sweep: String,
    pub policy: Policy,
    pub pairs: usize,
    /// Measurements in execution order.
    pub steps: Vec<Step>,
    pub skipped: Vec<Skipped>,
    pub durations: Durations,
    /// The order optimiser's budget and what it used: part of the plan, so two plans can
    /// be told apart by their inputs (a wall-clock cap makes the order machine-dependent).
    #[serde(default)]
    pub budget: PlanBudget,
    /// Wall seconds spent planning. Not stored in `plan.json` (it differs between
    /// identical runs, and a plan is byte-identical data); `gonio plan` prints it.
    #[serde(skip)]
    pub plan_time_s: f64,
    /// Number of directions in the sweep's light list (for the canonical index).
    pub light_count: usize,
    /// Present when the sample was declared isotropic: the pairs left out because an
    /// equivalent one is measured, and what that saves ([`Plan::build_isotropic`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub isotropic: Option<IsotropicPlan>,
    /// Present for a sparse acquisition: the prior, the design's picks and the predicted
    /// error ([`Plan::build_sparse`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sparse: Option<sparse::SparseInfo>,
    /// Present for a fly-scan plan: the blur bound, the segments and the fly figures
    /// ([`Plan::build_fly`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fly: Option<fly::FlyInfo>,
}

/// The isotropic reduction of a plan (see [`isotropic`]).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct IsotropicPlan {
    /// Class tolerance on θ_l, θ_v and |φ_l − φ_v| (degrees).
    pub tolerance_deg: f64,
    /// Whether the mirror φ → −φ is used (|Δφ| instead of the signed difference).
    pub mirror_symmetry: bool,
    /// Isotropy classes in the sweep.
    pub classes: usize,
    /// Classes no member of which the rig reaches (not reduced: each member is skipped or
    /// substituted on its own).
    pub unreachable_classes: usize,
    /// Counts and durations of planning every pair (no reduction), for comparison.
    pub full_counts: PlanCounts,
    pub full_durations: Durations,
    /// Optimized duration saved by the reduction (full − reduced), s.
    pub saved_s: f64,
    /// Every pair not measured, with its representative and the transform that maps the
    /// representative onto it (what export uses to reconstruct the full set).
    pub equivalents: Vec<isotropic::Equivalent>,
}

/// The order optimiser's budget as recorded in `plan.json`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PlanBudget {
    /// Kicks of the iterated local search asked for ([`order::OrderOptions::kicks`]).
    pub kicks: usize,
    /// Kicks that ran (summed over the plans an isotropic plan builds); fewer than asked
    /// only when the wall-clock cap stopped the search or the instance was solved exactly.
    pub kicks_done: usize,
    /// The wall-clock cap, if one was given (`--plan-time`). Present means the order may
    /// differ between machines and runs; absent means it depends only on the inputs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_cap_s: Option<f64>,
}

#[derive(Clone, Debug)]
pub struct PlanOptions {
    pub policy: Policy,
    /// Kicks the optimizer may spend improving the order (deterministic budget).
    pub kicks: usize,
    /// Optional wall-clock cap on the improvement (not reproducible; recorded in the plan).
    pub time_cap: Option<Duration>,
    pub seed: u64,
}

impl Default for PlanOptions {
    fn default() -> Self {
        PlanOptions {
            policy: Policy::Skip,
            kicks: order::DEFAULT_KICKS,
            time_cap: None,
            seed: 1,
        }
    }
}

/// Degrees, rounded to 1e-9° so that 30° does not print as 29.999999999999996°.
fn deg(d: Direction) -> [f64; 2] {
    let r = |x: f64| (x * 1e9).round() / 1e9;
    [r(d.theta_deg()), r(d.phi_deg())]
}

/// Light directions tried in place of a blocked one, nearest first.
fn substitutes(light: Direction) -> Vec<Direction> {
    let mut c = Vec::new();
    for step in [5.0f64, 7.5, 10.0, 15.0] {
        let t = light.theta_deg();
        for dt in [step, -step] {
            if (0.0..89.0).contains(&(t + dt)) {
                c.push(Direction::from_degrees(t + dt, light.phi_deg()));
            }
        }
        if t > 1.0 {
            let dphi = step / t.to_radians().sin();
            for s in [1.0, -1.0] {
                c.push(Direction::from_degrees(t, light.phi_deg() + s * dphi));
            }
        }
    }
    c.sort_by(|a, b| a.angle_to(light).total_cmp(&b.angle_to(light)));
    c
}

/// Candidates for a node with free axes marked NaN (the order optimizer lets them stay).
fn node_for(kin: &dyn Kinematics, light: Direction, view: Direction) -> Result<Node, Infeasibility> {
    let mut cands = kin.inverse(light, view, None)?;
    let free = kin.free_axes(light, view);
    for q in &mut cands {
        for &i in &free {
            q[i] = f64::NAN;
        }
    }
    cands.dedup_by(|a, b| {
        a.iter()
            .zip(b.iter())
            .all(|(x, y)| x == y || (x.is_nan() && y.is_nan()))
    });
    Ok(Node { candidates: cands })
}

impl Plan {
    pub fn build(rig: &RigSpec, sweep: &Sweep, opts: &PlanOptions) -> Result<Plan, PlanError> {
        Self::build_pairs(rig, sweep, &sweep.pairs(), opts)
    }

    /// Plan for a sample declared isotropic: measure one reachable pair per isotropy class
    /// (see [`isotropic`]) and record how every other pair is reconstructed. The full plan
    /// is computed too (half the kick budget and half of any time cap each), so the saving
    /// is a planned figure, not an estimate.
    pub fn build_isotropic(rig: &RigSpec, sweep: &Sweep, opts: &PlanOptions) -> Result<Plan, PlanError> {
        let t0 = Instant::now();
        let half = PlanOptions {
            kicks: opts.kicks / 2,
            time_cap: opts.time_cap.map(|c| c / 2),
            ..opts.clone()
        };
        let pairs = sweep.pairs();
        let full = Self::build_pairs(rig, sweep, &pairs, &half)?;
        let kin = kinematics::for_rig(rig);
        let classes = isotropic::classes(&pairs);
        let mut measured: Vec<Pair> = Vec::new();
        let mut equivalents = Vec::new();
        let mut unreachable = 0;
        for class in &classes {
            let rep = class
                .iter()
                .copied()
                .find(|&i| kin.inverse(pairs[i].light, pairs[i].view, None).is_ok());
            match rep {
                Some(r) => {
                    measured.push(pairs[r]);
                    for &m in class.iter().filter(|&&m| m != r) {
                        let (psi, mirrored) = isotropic::transform(&pairs[r], &pairs[m]);
                        equivalents.push(isotropic::Equivalent {
                            index: pairs[m].index,
                            representative: pairs[r].index,
                            light_deg: deg(pairs[m].light),
                            view_deg: deg(pairs[m].view),
                            rotation_deg: (psi * 1e9).round() / 1e9,
                            mirrored,
                        });
                    }
                }
                None => {
                    unreachable += 1;
                    measured.extend(class.iter().map(|&i| pairs[i]));
                }
            }
        }
        measured.sort_by_key(|p| p.index);
        equivalents.sort_by_key(|e| e.index);
        let mut plan = Self::build_pairs(rig, sweep, &measured, &half)?;
        plan.isotropic = Some(IsotropicPlan {
            tolerance_deg: isotropic::TOLERANCE_DEG,
            mirror_symmetry: true,
            classes: classes.len(),
            unreachable_classes: unreachable,
            full_counts: full.counts(),
            saved_s: full.durations.optimized_s - plan.durations.optimized_s,
            full_durations: full.durations,
            equivalents,
        });
        plan.pairs = pairs.len();
        plan.budget = PlanBudget {
            kicks: opts.kicks,
            kicks_done: full.budget.kicks_done + plan.budget.kicks_done,
            time_cap_s: opts.time_cap.map(|c| c.as_secs_f64()),
        };
        plan.plan_time_s = t0.elapsed().as_secs_f64();
        Ok(plan)
    }

    /// Plan the given pairs of `sweep` (all of them, or the representatives of an
    /// isotropic reduction, or a sparse design: `gonio plan --prior`), from home.
    pub fn build_pairs(rig: &RigSpec, sweep: &Sweep, pairs: &[Pair], opts: &PlanOptions) -> Result<Plan, PlanError> {
        Self::build_pairs_from(rig, sweep, pairs, opts, None)
    }

    /// [`Self::build_pairs`] from the axes' pose `start` (radians, one per axis; `None`:
    /// home): a plan that continues another, as an adaptive round continues from where the
    /// previous round left the rig. Its first move, its order, its canonical figures and
    /// its bound all start there.
    pub fn build_pairs_from(
        rig: &RigSpec,
        sweep: &Sweep,
        pairs: &[Pair],
        opts: &PlanOptions,
        start: Option<&[f64]>,
    ) -> Result<Plan, PlanError> {
        let t0 = Instant::now();
        let kin = kinematics::for_rig(rig);
        let motions: Vec<MotionModel> = rig.axes.iter().map(|a| a.motion()).collect();
        let capture = rig.planned_capture_time();
        // The last readout of a measurement overlaps the move to the next one when the
        // camera allows it; the rig then stands still only for the rest of the capture.
        let overlap = rig
            .camera
            .overlapped_readout_s()
            .map_err(|source| PlanError::RigOption {
                rig: rig.name.clone(),
                source,
            })?;
        let mut nodes: Vec<Node> = Vec::new();
        let mut info: Vec<(Pair, Direction, StepStatus)> = Vec::new();
        let mut skipped = Vec::new();
        for &pair in pairs {
            match node_for(kin.as_ref(), pair.light, pair.view) {
                Ok(n) => {
                    nodes.push(n);
                    info.push((pair, pair.light, StepStatus::Measure));
                }
                Err(reason) => {
                    let sub = if opts.policy == Policy::Substitute {
                        substitutes(pair.light)
                            .into_iter()
                            .find_map(|l| node_for(kin.as_ref(), l, pair.view).ok().map(|n| (l, n)))
                    } else {
                        None
                    };
                    match sub {
                        Some((l, n)) => {
                            nodes.push(n);
                            info.push((
                                pair,
                                l,
                                StepStatus::Substitute {
                                    requested_light_deg: deg(pair.light),
                                    reason,
                                },
                            ));
                        }
                        None => skipped.push(Skipped {
                            index: pair.index,
                            light_deg: deg(pair.light),
                            view_deg: deg(pair.view),
                            reason,
                        }),
                    }
                }
            }
        }
        if nodes.is_empty() {
            let mut counts: BTreeMap<String, usize> = BTreeMap::new();
            for s in &skipped {
                *counts.entry(reason_key(&s.reason)).or_default() += 1;
            }
            return Err(PlanError::Empty {
                rig: rig.name.clone(),
                sweep: sweep.name.clone(),
                reasons: counts
                    .iter()
                    .map(|(k, v)| format!("{v} × {k}"))
                    .collect::<Vec<_>>()
                    .join(", "),
            });
        }
        let home = match start {
            Some(p) if p.len() == motions.len() && p.iter().all(|x| x.is_finite()) => p.to_vec(),
            Some(p) => {
                return Err(PlanError::Start {
                    message: format!(
                        "the start pose has {} finite axis positions, the rig {} axes",
                        p.iter().filter(|x| x.is_finite()).count(),
                        motions.len()
                    ),
                })
            }
            None => kin.home(),
        };
        let canonical = order::canonical(&nodes, &motions, &home);
        let opt = order::optimize(
            &nodes,
            &motions,
            &home,
            &OrderOptions {
                kicks: opts.kicks,
                time_cap: opts.time_cap,
                seed: opts.seed,
            },
        );
        let bound = order::lower_bound(&nodes, &motions, &home);
        // Resolve the route into concrete axis targets (free axes stay where they are).
        let mut steps = Vec::with_capacity(nodes.len());
        let mut prev = home.clone();
        let mut t = 0.0;
        let mut overlapped = Overlap::new(overlap, capture);
        for (&ni, &ci) in opt.order.iter().zip(&opt.choice) {
            let q: Vec<f64> = nodes[ni].candidates[ci]
                .iter()
                .zip(&prev)
                .map(|(&x, &p)| if x.is_nan() { p } else { x })
                .collect();
            let dt = kinematics::transition_time(&motions, &prev, &q);
            t += overlapped.wait(dt);
            let (pair, light, status) = &info[ni];
            steps.push(Step {
                index: pair.index,
                light_index: pair.light_index,
                view_index: pair.view_index,
                light_deg: deg(*light),
                view_deg: deg(pair.view),
                status: status.clone(),
                axes_deg: q.iter().map(|x| (x.to_degrees() * 1e9).round() / 1e9).collect(),
                transition_s: dt,
                capture_start_s: t,
                flight: None,
            });
            t += overlapped.still();
            prev = q;
        }
        t += overlapped.last_readout();
        let n = nodes.len() as f64;
        let canonical_steps = canonical_transitions(&nodes, &motions, &home, &canonical);
        Ok(Plan {
            rig: rig.name.clone(),
            sweep: sweep.name.clone(),
            policy: opts.policy,
            pairs: pairs.len(),
            steps,
            skipped,
            durations: Durations {
                canonical_s: canonical.motion_time + n * capture,
                canonical_overlapped_s: Overlap::total(overlap, capture, &canonical_steps),
                stop_and_go_s: opt.motion_time + n * capture,
                optimized_s: t,
                lower_bound_s: Overlap::lower_bound(overlap, capture, bound, nodes.len()),
                capture_per_measurement_s: capture,
                readout_overlap_s: overlap,
                optimized_motion_s: opt.motion_time,
            },
            budget: PlanBudget {
                kicks: opts.kicks,
                kicks_done: opt.kicks_done,
                time_cap_s: opts.time_cap.map(|c| c.as_secs_f64()),
            },
            plan_time_s: t0.elapsed().as_secs_f64(),
            light_count: sweep.lights.len(),
            isotropic: None,
            sparse: None,
            fly: None,
        })
    }

    /// Counts by outcome and skip reason, for summaries.
    pub fn counts(&self) -> PlanCounts {
        let substituted = self
            .steps
            .iter()
            .filter(|s| matches!(s.status, StepStatus::Substitute { .. }))
            .count();
        let mut reasons: BTreeMap<String, usize> = BTreeMap::new();
        for s in &self.skipped {
            *reasons.entry(reason_key(&s.reason)).or_default() += 1;
        }
        PlanCounts {
            pairs: self.pairs,
            feasible: self.steps.len() - substituted,
            substituted,
            skipped: self.skipped.len(),
            skipped_reasons: reasons,
            reconstructed: self.isotropic.as_ref().map_or(0, |i| i.equivalents.len()),
        }
    }
}

/// A short stable key for a reason (for counting).
pub fn reason_key(r: &Infeasibility) -> String {
    match r {
        Infeasibility::OutOfLimits { .. } => "out_of_limits".into(),
        Infeasibility::LightBlockedByCamera { .. } => "light_blocked_by_camera".into(),
        Infeasibility::NotInDome { .. } => "not_in_dome".into(),
        Infeasibility::HolderShadow { .. } => "holder_shadow".into(),
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct PlanCounts {
    pub pairs: usize,
    pub feasible: usize,
    pub substituted: usize,
    pub skipped: usize,
    pub skipped_reasons: BTreeMap<String, usize>,
    /// Pairs not measured because an isotropy-equivalent pair is (reconstructed on export).
    #[serde(default)]
    pub reconstructed: usize,
}

#[cfg(test)]
mod tests {
    use super::Overlap;

    /// The overlap's timing: stop and go without a readout to overlap, `max(d, r)` after a
    /// measurement otherwise, one readout at the end, and a bound below every route.
    #[test]
    fn overlapped_readout_timing() {
        let d = [3.0, 0.2, 2.0, 0.0, 1.5];
        let (c, r) = (1.05, 1.0);
        assert!((Overlap::total(0.0, c, &d) - (6.7 + 5.0 * c)).abs() < 1e-12);
        // 3 (from home) + 1 + 2 + 1 + 1.5 moves, 5 × 0.05 exposures, the last readout.
        let t = Overlap::total(r, c, &d);
        assert!(
            (t - (3.0 + 1.0 + 2.0 + 1.0 + 1.5 + 5.0 * 0.05 + 1.0)).abs() < 1e-12,
            "{t}"
        );
        assert!(t < Overlap::total(0.0, c, &d));
        assert!(Overlap::lower_bound(r, c, 6.7, d.len()) <= t + 1e-12);
        assert!(Overlap::lower_bound(r, c, 0.0, d.len()) <= t + 1e-12);
        assert_eq!(Overlap::total(r, c, &[]), 0.0);
        assert_eq!(Overlap::lower_bound(r, c, 0.0, 0), 0.0);
        // No motion at all (a dome): overlap saves nothing.
        assert!((Overlap::total(r, c, &[0.0; 4]) - 4.0 * c).abs() < 1e-12);
    }

    use super::*;

    fn small_sweep() -> Sweep {
        let d = vec![
            Direction::from_degrees(0.0, 0.0),
            Direction::from_degrees(30.0, 0.0),
            Direction::from_degrees(30.0, 120.0),
            Direction::from_degrees(60.0, 240.0),
        ];
        Sweep {
            name: "small".into(),
            lights: d.clone(),
            views: d,
        }
    }

    #[test]
    fn default_rig_skips_exactly_the_retro_pairs_and_never_commands_them() {
        let rig = RigSpec::default_rig();
        let plan = Plan::build(
            &rig,
            &small_sweep(),
            &PlanOptions {
                kicks: 1_000,
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(plan.skipped.len(), 4);
        assert_eq!(plan.steps.len(), 12);
        let kin = kinematics::for_rig(&rig);
        for s in &plan.steps {
            assert!(s.light_deg != s.view_deg, "a blocked pair is never commanded");
            let q: Vec<f64> = s.axes_deg.iter().map(|x| x.to_radians()).collect();
            let (l, v) = kin.forward(&q);
            let want_l = Direction::from_degrees(s.light_deg[0], s.light_deg[1]);
            let want_v = Direction::from_degrees(s.view_deg[0], s.view_deg[1]);
            assert!(l.angle_to(want_l) < 1e-9 && v.angle_to(want_v) < 1e-9);
            for (i, a) in rig.axes.iter().enumerate() {
                assert!(a.limits().contains(q[i]));
            }
        }
        let mut idx: Vec<usize> = plan
            .steps
            .iter()
            .map(|s| s.index)
            .chain(plan.skipped.iter().map(|s| s.index))
            .collect();
        idx.sort();
        assert_eq!(idx, (0..16).collect::<Vec<_>>());
        assert!(plan.durations.optimized_s <= plan.durations.canonical_s + 1e-9);
        assert!(plan.durations.lower_bound_s <= plan.durations.optimized_s + 1e-9);
    }

    /// A plan that continues another starts where the rig stands: the first transition is
    /// timed from the start pose (zero when the rig already stands at the first pair), and
    /// a start pose of the wrong shape is refused with what is wrong.
    #[test]
    fn a_plan_from_a_start_pose_moves_from_there() {
        let rig = RigSpec::default_rig();
        let sweep = small_sweep();
        let opts = PlanOptions {
            kicks: 1_000,
            ..Default::default()
        };
        let pairs = sweep.pairs();
        let from_home = Plan::build_pairs(&rig, &sweep, &pairs, &opts).unwrap();
        assert!(from_home.steps[0].transition_s > 0.0);
        // Standing at one of the plan's pairs: the order starts there, with no move.
        let there: Vec<f64> = from_home.steps[3].axes_deg.iter().map(|x| x.to_radians()).collect();
        let continued = Plan::build_pairs_from(&rig, &sweep, &pairs, &opts, Some(&there)).unwrap();
        assert_eq!(continued.steps.len(), from_home.steps.len());
        assert!(
            continued.steps[0].transition_s < 1e-9,
            "{}",
            continued.steps[0].transition_s
        );
        assert!(continued.durations.lower_bound_s <= continued.durations.optimized_s + 1e-9);
        // From home explicitly: the same plan as without a start.
        let home = kinematics::for_rig(&rig).home();
        let same = Plan::build_pairs_from(&rig, &sweep, &pairs, &opts, Some(&home)).unwrap();
        assert_eq!(same.durations.optimized_s, from_home.durations.optimized_s);
        for bad in [vec![0.0], vec![f64::NAN; there.len()]] {
            let e = Plan::build_pairs_from(&rig, &sweep, &pairs, &opts, Some(&bad)).unwrap_err();
            assert!(e.to_string().contains("start pose"), "{e}");
        }
    }

    #[test]
    fn substitute_policy_measures_a_nearby_light() {
        let rig = RigSpec::default_rig();
        let plan = Plan::build(
            &rig,
            &small_sweep(),
            &PlanOptions {
                policy: Policy::Substitute,
                kicks: 1_000,
                time_cap: None,
                seed: 1,
            },
        )
        .unwrap();
        assert_eq!(plan.skipped.len(), 0);
        assert_eq!(plan.counts().substituted, 4);
        for s in &plan.steps {
            if let StepStatus::Substitute {
                requested_light_deg, ..
            } = s.status
            {
                let a = Direction::from_degrees(requested_light_deg[0], requested_light_deg[1]);
                let b = Direction::from_degrees(s.light_deg[0], s.light_deg[1]);
                assert!(a.angle_to(b).to_degrees() <= 10.0 + 1e-9);
            }
        }
    }

    #[test]
    fn limits_that_empty_the_sweep_are_an_error() {
        let text = gonio_devices::rig::DEFAULT_RIG_TOML
            .replace("min_deg = -80.0\nmax_deg = 80.0", "min_deg = 0.0\nmax_deg = 1.0");
        let rig = RigSpec::parse(&text, "narrow.toml").unwrap();
        let sweep = Sweep {
            name: "s".into(),
            lights: vec![Direction::from_degrees(45.0, 0.0)],
            views: vec![Direction::from_degrees(45.0, 90.0)],
        };
        let e = Plan::build(&rig, &sweep, &PlanOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("out_of_limits") && e.contains("Widen"), "{e}");
    }

    /// The isotropic plan measures one reachable pair per class, accounts for every pair
    /// exactly once (measured, skipped or reconstructed from a *measured* representative
    /// by an exact transform) and is faster than the full plan.
    #[test]
    fn isotropic_plan_covers_every_pair_once_and_saves_time() {
        let rig = RigSpec::default_rig();
        let sweep = Sweep::resolve("bonn81").unwrap();
        let opts = PlanOptions {
            kicks: 2_000,
            ..Default::default()
        };
        let plan = Plan::build_isotropic(&rig, &sweep, &opts).unwrap();
        let iso = plan.isotropic.as_ref().unwrap();
        let pairs = sweep.pairs();
        let mut seen = vec![0u8; pairs.len()];
        for s in &plan.steps {
            seen[s.index] += 1;
        }
        for s in &plan.skipped {
            seen[s.index] += 1;
        }
        let measured: std::collections::HashMap<usize, &Step> = plan
            .steps
            .iter()
            .filter(|s| matches!(s.status, StepStatus::Measure))
            .map(|s| (s.index, s))
            .collect();
        for e in &iso.equivalents {
            seen[e.index] += 1;
            let rep = measured.get(&e.representative).expect("representative is measured");
            let (p, r) = (&pairs[e.index], &pairs[rep.index]);
            assert!(isotropic::apply(r.light, e.rotation_deg, e.mirrored).angle_to(p.light) < 1e-9);
            assert!(isotropic::apply(r.view, e.rotation_deg, e.mirrored).angle_to(p.view) < 1e-9);
        }
        assert!(seen.iter().all(|&n| n == 1), "every pair exactly once");
        assert_eq!(
            plan.steps.len() + plan.skipped.len(),
            iso.classes - iso.unreachable_classes + plan.skipped.len()
        );
        let c = plan.counts();
        assert_eq!(c.reconstructed + c.feasible + c.skipped + c.substituted, 6561);
        // retro pairs are one class per θ ring, unreachable on this rig: skipped, not reduced
        assert_eq!(iso.unreachable_classes, 6);
        assert_eq!(plan.skipped.len(), 81);
        assert_eq!(iso.full_counts.feasible, 6480);
        assert!(plan.steps.len() * 4 < 6480, "{} steps", plan.steps.len());
        assert!(plan.durations.optimized_s < 0.5 * iso.full_durations.optimized_s);
        assert!((iso.saved_s - (iso.full_durations.optimized_s - plan.durations.optimized_s)).abs() < 1e-6);
        assert!(plan.durations.lower_bound_s <= plan.durations.optimized_s + 1e-9);
        // the stored plan round-trips through JSON with its reduction
        let back: Plan = serde_json::from_str(&serde_json::to_string(&plan).unwrap()).unwrap();
        assert_eq!(back.isotropic.unwrap().equivalents, iso.equivalents);
    }

    /// A pair outside the rig's limits is still measured through a reachable rotation of it.
    #[test]
    fn isotropic_plan_measures_a_reachable_rotation_of_an_unreachable_pair() {
        // turntable and light base limited to ±10°: most azimuths are out of reach
        let text = gonio_devices::rig::DEFAULT_RIG_TOML
            .replace("min_deg = -200.0\nmax_deg = 200.0", "min_deg = -10.0\nmax_deg = 10.0");
        let rig = RigSpec::parse(&text, "narrow-turntable.toml").unwrap();
        let kin = kinematics::for_rig(&rig);
        let ring = |t: f64| {
            (0..4)
                .map(|k| Direction::from_degrees(t, 90.0 * k as f64))
                .collect::<Vec<_>>()
        };
        let sweep = Sweep {
            name: "rings".into(),
            lights: ring(45.0),
            views: ring(30.0),
        };
        let pairs = sweep.pairs();
        let reachable: Vec<bool> = pairs
            .iter()
            .map(|p| kin.inverse(p.light, p.view, None).is_ok())
            .collect();
        let plan = Plan::build_isotropic(&rig, &sweep, &PlanOptions::default()).unwrap();
        let iso = plan.isotropic.as_ref().unwrap();
        // (45°, 30°) with |Δφ| ∈ {0°, 90°, 180°}: three classes
        assert_eq!(iso.classes, 3);
        let rescued: Vec<usize> = iso
            .equivalents
            .iter()
            .filter(|e| !reachable[e.index])
            .map(|e| e.index)
            .collect();
        assert!(
            !rescued.is_empty(),
            "some unreachable pair is reconstructed from a reachable one"
        );
        for e in &iso.equivalents {
            assert!(reachable[e.representative]);
        }
        for s in &plan.steps {
            assert!(reachable[s.index], "only reachable pairs are commanded");
        }
        let full = Plan::build(&rig, &sweep, &PlanOptions::default()).unwrap();
        assert_eq!(full.skipped.len(), reachable.iter().filter(|r| !**r).count());
        assert!(plan.skipped.len() < full.skipped.len());
    }
}
