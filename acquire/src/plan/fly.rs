//! Fly-scan planning: expose while the lamp moves (`gonio plan --fly`).
//!
//! # Why the lamp, and only the lamp
//!
//! A two-arm rig measures the lights of one θ ring, at one view, by turning the light base
//! alone: the camera and the sample stand still. If the base keeps turning through the
//! ring at a constant velocity and the camera exposes as the lamp passes each light
//! direction, the image does not blur geometrically at all (the camera, the sample and the
//! footprint of every texel are fixed); only the illumination direction sweeps a small arc
//! during the exposure, which is an angular blur of the reflectance in the light direction.
//! That arc is what the blur bound limits ([`FlyOptions::blur_deg`], degrees of light
//! direction per exposure). Moving the camera or the sample instead would smear the image
//! itself, so those axes are always taken stop and go.
//!
//! # The model
//!
//! A *segment* is a run of the plan's pairs at one view whose axis configurations differ in
//! the light-azimuth axis only (one light ring; a blocked light inside it is simply not
//! exposed). The axis starts at rest at the *kickoff* position, accelerates to the segment's
//! velocity `w`, holds it for its settle time, and then passes every pose of the run at
//! `w`; the exposure of a pose is centred on it, so its mid-exposure configuration is the
//! planned one. After the last exposure the axis decelerates and settles at the *stop*
//! position. `w` is the largest velocity that keeps (a) the light's angular sweep within one
//! exposure below the blur bound, (b) the time between two poses at least one frame
//! (exposure + readout: the camera reads out while the lamp moves on) and (c) the axis'
//! maximum velocity. A segment is flown only if that is faster than stop and go over the
//! same poses and its kickoff and stop positions are inside the axis limits; otherwise its
//! poses are taken stop and go inside the same plan, and the plan counts why.
//!
//! Views are ordered by the order optimiser ([`super::order`]) over their camera and sample
//! axes; within a view, segments and single poses follow nearest-first from where the
//! previous one left the axes, each flown in the direction whose kickoff is reached
//! sooner. The times are those of the engine's run (see [`schedule`]): a flight starts no
//! earlier than its first exposure allows after the previous frame's readout.

use super::order::{self, Node, OrderOptions};
use super::{node_for, Durations, Plan, PlanError, Step};
use gonio_devices::kinematics::{self, Kinematics};
use gonio_devices::motion::{flight_end, gap_cruise_speed, gap_min_time};
use gonio_devices::rig::RigSpec;
use gonio_devices::serial::FlightProfile;
use gonio_devices::{Direction, MotionModel};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The blur bound when `--blur-deg` is not given (degrees of light direction swept during
/// one exposure). `gonio bench fly` measures PSNR and rig time across bounds; see
/// `docs/results/rig-time.md` for why this value.
pub const DEFAULT_BLUR_DEG: f64 = 0.5;
/// Largest blur bound accepted (degrees): beyond it a "pair" is an average over a wide arc.
pub const MAX_BLUR_DEG: f64 = 10.0;
/// A flown frame whose mid-exposure light or view direction is farther than this from the
/// planned one (degrees) is retaken stop and go by the engine.
pub const POSE_TOLERANCE_DEG: f64 = 0.05;

/// What `--fly` asks for.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FlyOptions {
    /// Light direction swept during one exposure, at most (degrees, in (0, 10]).
    pub blur_deg: f64,
    /// Fly every flight at one constant velocity even where the axis could follow a
    /// velocity profile per gap (`--fly-constant-velocity`: the plans before per-gap
    /// profiles, for comparison).
    pub constant_velocity: bool,
}

impl FlyOptions {
    /// Check the bound; the error names the flag and the valid range.
    pub fn new(blur_deg: f64) -> Result<FlyOptions, PlanError> {
        if !(blur_deg.is_finite() && blur_deg > 0.0 && blur_deg <= MAX_BLUR_DEG) {
            return Err(PlanError::Fly {
                message: format!(
                    "--blur-deg {blur_deg}: the blur bound must be in (0, {MAX_BLUR_DEG}] degrees of light direction per exposure (default {DEFAULT_BLUR_DEG})"
                ),
            });
        }
        Ok(FlyOptions {
            blur_deg,
            constant_velocity: false,
        })
    }

    /// The same bound, flown at one constant velocity per flight.
    pub fn with_constant_velocity(self, constant: bool) -> FlyOptions {
        FlyOptions {
            constant_velocity: constant,
            ..self
        }
    }
}

/// A step taken in flight: what the engine needs to fly its segment.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepFlight {
    /// The segment (consecutive steps of one segment share it).
    pub segment: usize,
    /// The axis that moves (index in the rig file's order); every other axis stands still
    /// at the step's `axes_deg`.
    pub axis: usize,
    /// Signed velocity of the moving axis during this step's exposure (degrees/s): the
    /// segment's one velocity in a constant-velocity flight; this pose's own in a per-gap
    /// one (`per_gap`).
    pub velocity_deg_s: f64,
    /// Where the moving axis starts, at rest, and where it stops (degrees).
    pub kickoff_deg: f64,
    pub stop_deg: f64,
    /// Start of this step's exposure after the axis starts moving (s).
    pub exposure_offset_s: f64,
    /// Light direction swept during the exposure (degrees).
    pub light_sweep_deg: f64,
    /// A velocity profile per gap: the axis holds `velocity_deg_s` through this exposure
    /// only and, between two exposures, ramps (at the axis' acceleration, up to its maximum
    /// velocity) to one cruise velocity and down (or up) to the next pose's, arriving as its
    /// exposure starts (`gonio_devices::motion::Trajectory::flight` rebuilds the profile from
    /// the segment's steps). Absent (`false`, plans before it): one constant velocity
    /// through the segment.
    #[serde(default, skip_serializing_if = "is_false")]
    pub per_gap: bool,
}

fn is_false(b: &bool) -> bool {
    !*b
}

/// The fly-scan part of a plan (`plan.json` → `fly`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FlyInfo {
    /// The blur bound asked for (degrees of light direction per exposure).
    pub blur_deg: f64,
    /// The moving axis' name.
    pub axis: String,
    /// Segments formed (runs of ≥ 2 poses differing in the moving axis only) and how many
    /// of them are flown.
    pub segments: usize,
    pub flown_segments: usize,
    pub flown_pairs: usize,
    pub stop_and_go_pairs: usize,
    /// Why the stop-and-go pairs are not flown (counts by reason).
    pub stop_and_go_reasons: BTreeMap<String, usize>,
    /// The fly plan's rig time (also `durations.optimized_s`), s.
    pub fly_s: f64,
    /// A lower bound on any order of these segments and poses at these velocities, and the
    /// camera's own limit (every pair costs at least one exposure and one readout), s.
    pub lower_bound_s: f64,
    pub readout_bound_s: f64,
    /// The same pairs planned stop and go with the readout overlapping the moves (the
    /// non-fly plan's `optimized_s`), s.
    pub stop_and_go_overlapped_s: f64,
    /// Largest light-direction sweep of a flown exposure (degrees) and largest image motion
    /// of the sample during one (pixels; 0 while only the lamp moves).
    pub max_light_sweep_deg: f64,
    pub max_image_blur_px: f64,
    /// How flights move between exposures: `per_gap` (a velocity profile per gap: speed up
    /// between distant poses) or `constant` (one velocity per flight); empty in plans made
    /// before per-gap profiles (constant).
    #[serde(default)]
    pub velocity_profile: String,
    /// Why flights keep one constant velocity (a serial stage flies one commanded move).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub constant_velocity_reason: Option<String>,
    /// When the stop-and-go plan was kept (`whole_plan_faster_stop_and_go`): the fly order
    /// it beat, as planned (its time, what it flew and why the rest was stop and go).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub not_kept: Option<NotKept>,
}

/// The fly order of a plan that kept stop and go (`FlyInfo::not_kept`).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct NotKept {
    pub fly_s: f64,
    pub flown_segments: usize,
    pub flown_pairs: usize,
    pub stop_and_go_reasons: BTreeMap<String, usize>,
}

/// One unit of the flown order: a single stop-and-go pose or a flown segment.
#[derive(Clone, Debug)]
enum Item {
    Stop {
        step: usize,
        q: Vec<f64>,
    },
    Flight {
        /// Base-plan steps in pass order (forward) and their moving-axis values.
        steps: Vec<usize>,
        base: Vec<f64>,
        values: Vec<f64>,
        /// Speed of each pose's exposure (radians/s, > 0), pass order; all equal in a
        /// constant-velocity flight.
        speeds: Vec<f64>,
        /// Per-gap flights: time from one exposure's end to the next one's start (s), pass
        /// order. Empty: a constant-velocity flight (one move at `speeds[0]`).
        gaps: Vec<f64>,
        /// Run-up and run-out lengths (radians), and theirs when flown the other way (a
        /// per-gap flight starts and ends at its end poses' own speeds).
        run_up: f64,
        run_out: f64,
        rev_run_up: f64,
        rev_run_out: f64,
    },
}

/// Per-axis-role facts the fly planner needs.
struct Setup<'a> {
    rig: &'a RigSpec,
    kin: Box<dyn Kinematics>,
    motions: Vec<MotionModel>,
    /// The moving axis' motion in flight: the rig file's, with the acceleration its
    /// controller really runs (stop-and-go moves keep the rig file's figures).
    fly_motion: MotionModel,
    /// The controller's rounding of a flight's velocity (serial axes; `None`: simulated).
    profile: Option<FlightProfile>,
    /// One constant velocity per flight was asked for (`FlyOptions::constant_velocity`).
    constant_asked: bool,
    axis: usize,
    light_axes: Vec<usize>,
    exposure: f64,
    readout: f64,
    blur_rad: f64,
}

/// Why a rig cannot fly at all (`None`: it can).
pub fn refusal(rig: &RigSpec) -> Option<String> {
    if rig.axes.is_empty() {
        return Some(format!(
            "rig `{}` has no moving parts (a dome switches lamps and cameras): there is nothing to fly",
            rig.name
        ));
    }
    if !rig.axes.iter().any(|a| a.role == "light_azimuth") {
        return Some(format!(
            "rig `{}` has no light-azimuth axis: fly-scan moves only the lamp (moving the camera or the sample would blur the image), so this rig is measured stop and go",
            rig.name
        ));
    }
    if rig.camera.backend != "sim" {
        return Some(format!(
            "camera backend `{}` cannot expose while the rig moves (its frames are not stamped against the stages yet); fly-scan runs with the simulated camera",
            rig.camera.backend
        ));
    }
    None
}

/// Why the light-azimuth axis cannot fly on this rig although the rig could (`None`: it
/// can): the plan then stays stop and go as a whole and says why.
fn axis_fallback(rig: &RigSpec) -> Option<String> {
    let axis = rig.axes.iter().find(|a| a.role == "light_azimuth")?;
    if axis.backend != "sim" && !gonio_devices::serial::BACKENDS.contains(&axis.backend.as_str()) {
        return Some(format!(
            "axis_backend: axis `{}` (backend `{}`) has no constant-velocity moves in gonio yet",
            axis.name, axis.backend
        ));
    }
    if axis.jerk_deg_s3.is_some() {
        return Some(format!(
            "axis_jerk_limit: axis `{}` has a jerk limit, so its position in a move is not the trapezoid the flight timing assumes",
            axis.name
        ));
    }
    None
}

/// The moving axis' flight motion and its controller's velocity rounding, from the rig file
/// alone (no port is opened: see `gonio_devices::serial::flight_profile`).
fn flight_motion(rig: &RigSpec, axis: usize) -> Result<(MotionModel, Option<FlightProfile>), PlanError> {
    let spec = &rig.axes[axis];
    let mut m = spec.motion();
    let profile = gonio_devices::serial::flight_profile(spec).map_err(|e| PlanError::Fly {
        message: format!("rig `{}`: {e}", rig.name),
    })?;
    if let Some(p) = &profile {
        m.acceleration = p.acceleration;
    }
    Ok((m, profile))
}

impl Plan {
    /// Regroup this stop-and-go plan for fly-scan (see the module docs). Its feasibility,
    /// substitutions, skips and reductions (isotropic, sparse) are kept, and its figures
    /// stay the reference (`fly.stop_and_go_overlapped_s`); only the order and the timing
    /// of its steps change.
    pub fn into_fly(self, rig: &RigSpec, opts: &super::PlanOptions, fly: FlyOptions) -> Result<Plan, PlanError> {
        if let Some(why) = refusal(rig) {
            return Err(PlanError::Fly { message: why });
        }
        let t0 = std::time::Instant::now();
        let base = self;
        let overlap = rig
            .camera
            .overlapped_readout_s()
            .map_err(|source| PlanError::RigOption {
                rig: rig.name.clone(),
                source,
            })?;
        let axis = rig
            .axes
            .iter()
            .position(|a| a.role == "light_azimuth")
            .ok_or_else(|| PlanError::Fly {
                message: format!("rig `{}` has no light-azimuth axis", rig.name),
            })?;
        let (fly_motion, profile) = match axis_fallback(rig) {
            None => flight_motion(rig, axis)?,
            Some(_) => (rig.axes[axis].motion(), None),
        };
        let s = Setup {
            rig,
            kin: kinematics::for_rig(rig),
            motions: rig.axes.iter().map(|a| a.motion()).collect(),
            fly_motion,
            profile,
            constant_asked: fly.constant_velocity,
            axis,
            light_axes: (0..rig.axes.len())
                .filter(|&i| rig.axes[i].role.starts_with("light_"))
                .collect(),
            exposure: rig.camera.exposure_s.max(0.0),
            readout: overlap,
            blur_rad: fly.blur_deg.to_radians(),
        };
        let hdr = rig
            .hdr
            .as_ref()
            .is_some_and(|h| h.mode() != gonio_devices::hdr::HdrMode::Off);
        let mut reasons: BTreeMap<String, usize> = BTreeMap::new();
        let mut segments = 0;
        let items = match axis_fallback(rig) {
            None => s.items(&base, opts, hdr, &mut reasons, &mut segments)?,
            Some(why) => {
                reasons.insert(why, base.steps.len());
                Vec::new()
            }
        };
        if items.is_empty() {
            // Nothing can fly: the stop-and-go plan, saying why.
            let n = base.steps.len();
            let mut plan = base;
            plan.fly = Some(FlyInfo {
                blur_deg: fly.blur_deg,
                axis: rig.axes[s.axis].name.clone(),
                segments,
                flown_segments: 0,
                flown_pairs: 0,
                stop_and_go_pairs: n,
                stop_and_go_reasons: reasons,
                fly_s: plan.durations.optimized_s,
                lower_bound_s: plan.durations.lower_bound_s,
                readout_bound_s: n as f64 * (s.exposure + s.readout),
                stop_and_go_overlapped_s: plan.durations.optimized_s,
                max_light_sweep_deg: 0.0,
                max_image_blur_px: 0.0,
                velocity_profile: s.velocity_profile().into(),
                constant_velocity_reason: s.constant_velocity_reason(),
                not_kept: None,
            });
            plan.plan_time_s += t0.elapsed().as_secs_f64();
            return Ok(plan);
        }
        let (steps, fly_s, motion_s, _) = s.schedule(&base, &items);
        let n = steps.len();
        let flown_pairs = steps.iter().filter(|st| st.flight.is_some()).count();
        let flown_segments = items.iter().filter(|i| matches!(i, Item::Flight { .. })).count();
        let frame = s.exposure + s.readout;
        let readout_bound = if n == 0 { 0.0 } else { n as f64 * frame };
        let lower = s.lower_bound(&items).max(readout_bound);
        let max_sweep = steps
            .iter()
            .filter_map(|st| st.flight.as_ref().map(|f| f.light_sweep_deg))
            .fold(0.0, f64::max);
        let max_image = steps
            .iter()
            .filter_map(|st| st.flight.as_ref().map(|f| s.image_blur_px(st, f)))
            .fold(0.0, f64::max);
        let info = FlyInfo {
            blur_deg: fly.blur_deg,
            axis: rig.axes[s.axis].name.clone(),
            segments,
            flown_segments,
            flown_pairs,
            stop_and_go_pairs: n - flown_pairs,
            stop_and_go_reasons: reasons,
            fly_s,
            lower_bound_s: lower,
            readout_bound_s: readout_bound,
            stop_and_go_overlapped_s: base.durations.optimized_s,
            max_light_sweep_deg: max_sweep,
            max_image_blur_px: max_image,
            velocity_profile: s.velocity_profile().into(),
            constant_velocity_reason: s.constant_velocity_reason(),
            not_kept: None,
        };
        let mut plan = base;
        if fly_s >= plan.durations.optimized_s {
            // At a tight bound the rings fly so slowly that the whole stop-and-go plan (whose
            // order the optimiser chose over every pair) is faster: keep it, and say so.
            let mut info = info;
            info.not_kept = Some(NotKept {
                fly_s: info.fly_s,
                flown_segments: info.flown_segments,
                flown_pairs: info.flown_pairs,
                stop_and_go_reasons: std::mem::take(&mut info.stop_and_go_reasons),
            });
            info.stop_and_go_reasons = BTreeMap::from([("whole_plan_faster_stop_and_go".to_string(), n)]);
            info.flown_segments = 0;
            info.flown_pairs = 0;
            info.stop_and_go_pairs = n;
            info.fly_s = plan.durations.optimized_s;
            info.max_light_sweep_deg = 0.0;
            info.max_image_blur_px = 0.0;
            plan.fly = Some(info);
            plan.plan_time_s += t0.elapsed().as_secs_f64();
            return Ok(plan);
        }
        plan.durations = Durations {
            optimized_s: fly_s,
            lower_bound_s: lower,
            optimized_motion_s: motion_s,
            ..plan.durations
        };
        plan.steps = steps;
        plan.fly = Some(info);
        plan.plan_time_s += t0.elapsed().as_secs_f64();
        Ok(plan)
    }
}

/// Whether two axis values agree (NaN = free agrees with NaN only).
fn same(a: f64, b: f64) -> bool {
    (a.is_nan() && b.is_nan()) || (a - b).abs() < 1e-9
}

impl Setup<'_> {
    /// Per-gap profiles fly where the axis follows a profile (the simulated stage); a
    /// serial stage flies one commanded velocity per flight.
    fn per_gap(&self) -> bool {
        self.profile.is_none() && !self.constant_asked
    }

    fn velocity_profile(&self) -> &'static str {
        if self.per_gap() {
            "per_gap"
        } else {
            "constant"
        }
    }

    fn constant_velocity_reason(&self) -> Option<String> {
        (!self.per_gap()).then(|| {
            let a = &self.rig.axes[self.axis];
            if self.profile.is_none() {
                return "asked: --fly-constant-velocity".to_string();
            }
            format!(
                "serial_stage: axis `{}` (backend `{}`) flies one move at one commanded velocity per flight",
                a.name, a.backend
            )
        })
    }

    /// Length the axis travels from rest until the first exposure starts at speed `v`
    /// (acceleration, settle at cruise, half an exposure), and after the last one ends.
    fn run_up(&self, v: f64) -> f64 {
        let m = self.fly_motion;
        v * v / (2.0 * m.acceleration) + v * m.settle_time + v * self.exposure / 2.0
    }

    fn run_out(&self, v: f64) -> f64 {
        v * self.exposure / 2.0 + v * v / (2.0 * self.fly_motion.acceleration)
    }

    /// Per-gap speeds (each pose's own blur bound and the axis' maximum) and the time of
    /// every gap: the fastest profile between two exposures, never shorter than the
    /// readout. Candidates: those speeds; them capped by the frame-rate bound of their gaps
    /// (close poses, where a gap cannot change speed in its length); the constant velocity
    /// `w` through every exposure (still speeding up between them). The quickest feasible
    /// one is flown.
    fn per_gap_speeds(&self, values: &[f64], rates: &[f64], w: f64) -> Option<(Vec<f64>, Vec<f64>)> {
        let m = self.fly_motion;
        let (a, vmax, e) = (m.acceleration, m.max_velocity, self.exposure);
        let n = values.len();
        let own: Vec<f64> = rates
            .iter()
            .map(|&r| {
                if e > 0.0 && r > 1e-12 {
                    vmax.min(self.blur_rad / (e * r))
                } else {
                    vmax
                }
            })
            .collect();
        let frame = e + self.readout;
        let gap_len = |k: usize| (values[k + 1] - values[k]).abs();
        let capped: Vec<f64> = (0..n)
            .map(|k| {
                let mut v = own[k];
                if frame > 0.0 {
                    if k > 0 {
                        v = v.min(gap_len(k - 1) / frame);
                    }
                    if k + 1 < n {
                        v = v.min(gap_len(k) / frame);
                    }
                }
                v
            })
            .collect();
        let gaps_of = |sp: &[f64]| -> Option<Vec<f64>> {
            let mut gaps = Vec::with_capacity(n.saturating_sub(1));
            for k in 0..n - 1 {
                let d = gap_len(k) - (sp[k] + sp[k + 1]) * e / 2.0;
                let t = gap_min_time(d, sp[k], sp[k + 1], a, vmax)?.max(self.readout);
                gap_cruise_speed(d, sp[k], sp[k + 1], a, vmax, t)?;
                gaps.push(t);
            }
            Some(gaps)
        };
        // Of the feasible candidates, the quickest flight (faster exposures are not always
        // quicker: where the readout paces the gaps, they only lengthen the run-up and
        // run-out).
        let mut best: Option<(f64, Vec<f64>, Vec<f64>)> = None;
        for sp in [own, capped, vec![w; n]] {
            if sp.iter().any(|v| !(v.is_finite() && *v > 1e-9)) {
                continue;
            }
            if let Some(g) = gaps_of(&sp) {
                let o = self.offsets(&sp, &g);
                let t = flight_end(o[n - 1], e, sp[n - 1], a, m.settle_time);
                if !matches!(&best, Some((bt, _, _)) if t >= *bt - 1e-12) {
                    best = Some((t, sp, g));
                }
            }
        }
        best.map(|(_, sp, g)| (sp, g))
    }

    /// Start of each exposure after the kickoff (s) of a per-gap flight.
    fn offsets(&self, speeds: &[f64], gaps: &[f64]) -> Vec<f64> {
        let m = self.fly_motion;
        let mut o = Vec::with_capacity(speeds.len());
        o.push(speeds[0] / m.acceleration + m.settle_time);
        for g in gaps {
            let last = o[o.len() - 1];
            o.push(last + self.exposure + g);
        }
        o
    }

    fn is_light(&self, i: usize) -> bool {
        self.light_axes.contains(&i)
    }

    /// The configuration of the view axes (light axes free).
    fn view_key(&self, q: &[f64]) -> Vec<f64> {
        q.iter()
            .enumerate()
            .map(|(i, &x)| if self.is_light(i) { f64::NAN } else { x })
            .collect()
    }

    /// Candidates of a base step (its measured light and view).
    fn candidates(&self, step: &Step) -> Vec<Vec<f64>> {
        let l = Direction::from_degrees(step.light_deg[0], step.light_deg[1]);
        let v = Direction::from_degrees(step.view_deg[0], step.view_deg[1]);
        node_for(self.kin.as_ref(), l, v)
            .map(|n| n.candidates)
            .unwrap_or_else(|_| vec![step.axes_deg.iter().map(|d| d.to_radians()).collect()])
    }

    /// Group the base plan's steps into flown segments and single poses, in flown order.
    fn items(
        &self,
        base: &Plan,
        opts: &super::PlanOptions,
        hdr: bool,
        reasons: &mut BTreeMap<String, usize>,
        formed: &mut usize,
    ) -> Result<Vec<Item>, PlanError> {
        // Steps by view; each view gets one configuration of its camera and sample axes.
        let mut by_view: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
        for (i, st) in base.steps.iter().enumerate() {
            by_view.entry(st.view_index).or_default().push(i);
        }
        let cands: Vec<Vec<Vec<f64>>> = base.steps.iter().map(|st| self.candidates(st)).collect();
        // A view node per group of steps sharing a view configuration.
        let mut groups: Vec<(Vec<usize>, Vec<Vec<f64>>)> = Vec::new();
        for steps in by_view.values() {
            let mut left = steps.clone();
            while !left.is_empty() {
                let mut keys: Vec<Vec<f64>> = Vec::new();
                for &i in &left {
                    for c in &cands[i] {
                        let k = self.view_key(c);
                        if !keys.iter().any(|x| x.iter().zip(&k).all(|(a, b)| same(*a, *b))) {
                            keys.push(k);
                        }
                    }
                }
                let covers = |k: &Vec<f64>| -> Vec<usize> {
                    left.iter()
                        .copied()
                        .filter(|&i| {
                            cands[i]
                                .iter()
                                .any(|c| self.view_key(c).iter().zip(k).all(|(a, b)| same(*a, *b)))
                        })
                        .collect()
                };
                let counts: Vec<usize> = keys.iter().map(|k| covers(k).len()).collect();
                let best = counts.iter().copied().max().unwrap_or(0);
                let chosen: Vec<Vec<f64>> = keys
                    .iter()
                    .zip(&counts)
                    .filter(|(_, &c)| c == best)
                    .map(|(k, _)| k.clone())
                    .collect();
                let members = covers(&chosen[0]);
                left.retain(|i| !members.contains(i));
                groups.push((members, chosen));
            }
        }
        let nodes: Vec<Node> = groups
            .iter()
            .map(|(_, keys)| Node {
                candidates: keys.clone(),
            })
            .collect();
        let home = self.kin.home();
        let route = order::optimize(
            &nodes,
            &self.motions,
            &home,
            &OrderOptions {
                kicks: opts.kicks.min(2_000),
                time_cap: opts.time_cap,
                seed: opts.seed,
            },
        );
        let mut items = Vec::new();
        let mut cur = home.clone();
        for (&gi, &ci) in route.order.iter().zip(&route.choice) {
            let (members, keys) = &groups[gi];
            let key = &keys[ci];
            let mut view_items = self.view_items(&cands, members, key, hdr, reasons, formed);
            // Nearest first from where the previous item left the axes.
            while !view_items.is_empty() {
                let mut best = (f64::INFINITY, 0usize, false);
                for (k, it) in view_items.iter().enumerate() {
                    for rev in [false, true] {
                        if rev && matches!(it, Item::Stop { .. }) {
                            continue;
                        }
                        let it = if rev { reversed(it.clone()) } else { it.clone() };
                        let Some(entry) = self.entry(&it, &cur) else { continue };
                        let t = kinematics::transition_time(&self.motions, &cur, &entry);
                        if t < best.0 - 1e-12 {
                            best = (t, k, rev);
                        }
                    }
                }
                let mut it = view_items.remove(best.1);
                if best.2 {
                    it = reversed(it);
                }
                cur = self.exit(&it, &cur);
                items.push(it);
            }
        }
        Ok(items)
    }

    /// The items of one view group whose camera and sample axes are at `key`.
    fn view_items(
        &self,
        cands: &[Vec<Vec<f64>>],
        members: &[usize],
        key: &[f64],
        hdr: bool,
        reasons: &mut BTreeMap<String, usize>,
        formed: &mut usize,
    ) -> Vec<Item> {
        // Each step's configuration under this view key; group by the other light axes.
        let mut runs: BTreeMap<Vec<u64>, Vec<(usize, Vec<f64>)>> = BTreeMap::new();
        let mut items = Vec::new();
        for &i in members {
            let q = cands[i]
                .iter()
                .find(|c| self.view_key(c).iter().zip(key).all(|(a, b)| same(*a, *b)))
                .expect("the view group's key covers its members")
                .clone();
            if q[self.axis].is_nan() {
                // The lamp at the pole: the moving axis is free, there is nothing to sweep.
                *reasons.entry("light_at_pole".into()).or_default() += 1;
                items.push(Item::Stop { step: i, q });
                continue;
            }
            let rk: Vec<u64> = q
                .iter()
                .enumerate()
                .filter(|(a, _)| *a != self.axis)
                .map(|(_, x)| {
                    if x.is_nan() {
                        u64::MAX
                    } else {
                        ((x * 1e9).round() as i64) as u64
                    }
                })
                .collect();
            runs.entry(rk).or_default().push((i, q));
        }
        for (_, mut run) in runs {
            run.sort_by(|a, b| a.1[self.axis].total_cmp(&b.1[self.axis]).then(a.0.cmp(&b.0)));
            self.unwrap_arc(&mut run);
            if run.len() >= 2 {
                *formed += 1;
            }
            let why = if run.len() < 2 {
                Some("single_pose")
            } else if hdr {
                Some("hdr_bracket")
            } else {
                None
            };
            let flight = match why {
                Some(w) => Err(w),
                None => self.flight(&run),
            };
            match flight {
                Ok(f) => items.push(f),
                Err(w) => {
                    *reasons.entry(w.into()).or_default() += run.len();
                    items.extend(run.into_iter().map(|(step, q)| Item::Stop { step, q }));
                }
            }
        }
        items
    }

    /// Lay a ring's poses out as one contiguous arc of the moving axis: the inverse
    /// kinematics may give one light at 170° and its neighbour at −190°, which is the same
    /// pose but splits the ring. Values are taken modulo a turn; of every place to cut the
    /// circle and every whole-turn shift, the arc kept is the one that sits deepest inside
    /// the axis limits (room for the run-up and run-out), ties going to the wider cut gap
    /// (a ring's blocked light, say). A shifted pose is kept only if the forward kinematics
    /// confirm it measures the same directions.
    fn unwrap_arc(&self, run: &mut Vec<(usize, Vec<f64>)>) {
        use std::f64::consts::TAU;
        let ax = self.axis;
        let mut m: Vec<(f64, usize)> = run
            .iter()
            .enumerate()
            .map(|(k, (_, q))| (q[ax].rem_euclid(TAU), k))
            .collect();
        m.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let n = m.len();
        let lim = self.rig.axes[ax].limits();
        // (margin, cut gap, start, shift)
        let mut best: Option<(f64, f64, usize, f64)> = None;
        for start in 0..n {
            let prev = (start + n - 1) % n;
            let cut = (m[start].0 - m[prev].0).rem_euclid(TAU);
            let cut = if n == 1 { TAU } else { cut };
            let lo = m[start].0;
            let hi = lo + (TAU - cut);
            let k_mid = ((lim.min + lim.max) / 2.0 - (lo + hi) / 2.0) / TAU;
            for k in [k_mid.floor(), k_mid.ceil()] {
                let sh = k * TAU;
                let margin = (lo + sh - lim.min).min(lim.max - (hi + sh));
                if margin < 0.0 {
                    continue;
                }
                let better = match best {
                    None => true,
                    Some((bm, bc, _, _)) => margin > bm + 1e-9 || ((margin - bm).abs() <= 1e-9 && cut > bc + 1e-9),
                };
                if better {
                    best = Some((margin, cut, start, sh));
                }
            }
        }
        let Some((_, _, start, sh)) = best else { return };
        let mut out = Vec::with_capacity(n);
        let base = m[start].0;
        for j in 0..n {
            let (v, k) = m[(start + j) % n];
            let v = if v < base { v + TAU } else { v };
            let (i, q) = &run[k];
            let mut q2 = q.clone();
            q2[ax] = v + sh;
            let (l1, v1) = self.kin.forward(q);
            let (l2, v2) = self.kin.forward(&q2);
            if l1.angle_to(l2) > 1e-9 || v1.angle_to(v2) > 1e-9 {
                return;
            }
            out.push((*i, q2));
        }
        *run = out;
    }

    /// Light (or view) direction change per radian of the moving axis at `q`.
    fn sweep_rate(&self, q: &[f64]) -> f64 {
        let h = 1e-5;
        let mut a = q.to_vec();
        let mut b = q.to_vec();
        a[self.axis] -= h;
        b[self.axis] += h;
        let (la, va) = self.kin.forward(&a);
        let (lb, vb) = self.kin.forward(&b);
        (la.angle_to(lb) + va.angle_to(vb)) / (2.0 * h)
    }

    /// A flown segment over `run` (sorted by the moving axis), or why it is not flown.
    fn flight(&self, run: &[(usize, Vec<f64>)]) -> Result<Item, &'static str> {
        let ax = self.axis;
        let m = self.fly_motion;
        let values: Vec<f64> = run.iter().map(|(_, q)| q[ax]).collect();
        let min_gap = values.windows(2).map(|w| w[1] - w[0]).fold(f64::INFINITY, f64::min);
        if min_gap <= 1e-9 {
            return Err("repeated_pose");
        }
        let rates: Vec<f64> = run.iter().map(|(_, q)| self.sweep_rate(q)).collect();
        let rate = rates.iter().copied().fold(0.0, f64::max);
        let frame = self.exposure + self.readout;
        let mut speed = m.max_velocity;
        if frame > 0.0 {
            speed = speed.min(min_gap / frame);
        }
        if self.exposure > 0.0 && rate > 1e-12 {
            speed = speed.min(self.blur_rad / (self.exposure * rate));
        }
        if let Some(p) = &self.profile {
            // What the controller runs, never above the bounds (it counts in whole units).
            speed = p.velocity(speed);
        }
        if !(speed.is_finite() && speed > 1e-9) {
            return Err("blur_bound");
        }
        let (speeds, gaps) = match self.per_gap() {
            true => self
                .per_gap_speeds(&values, &rates, speed)
                .unwrap_or_else(|| (vec![speed; values.len()], Vec::new())),
            false => (vec![speed; values.len()], Vec::new()),
        };
        let (run_up, run_out) = if gaps.is_empty() {
            // One constant velocity: the formulas the serial stages' flights were timed with.
            let up = speed * speed / (2.0 * m.acceleration) + speed * m.settle_time + speed * self.exposure / 2.0;
            let out = speed * self.exposure / 2.0 + speed * speed / (2.0 * m.acceleration);
            ((up, out), (up, out))
        } else {
            let (first, last) = (speeds[0], speeds[speeds.len() - 1]);
            (
                (self.run_up(first), self.run_out(last)),
                (self.run_up(last), self.run_out(first)),
            )
        };
        let ((run_up, run_out), (rev_run_up, rev_run_out)) = (run_up, run_out);
        let lim = self.rig.axes[ax].limits();
        let (lo, hi) = (values[0], values[values.len() - 1]);
        let fwd_ok = lim.contains(lo - run_up) && lim.contains(hi + run_out);
        let rev_ok = lim.contains(hi + rev_run_up) && lim.contains(lo - rev_run_out);
        if !fwd_ok && !rev_ok {
            return Err("axis_limit");
        }
        let item = Item::Flight {
            steps: run.iter().map(|(i, _)| *i).collect(),
            base: run[0].1.clone(),
            values,
            speeds,
            gaps,
            run_up,
            run_out,
            rev_run_up,
            rev_run_out,
        };
        // Flown only when faster than stop and go over the same poses.
        let fly = self.flight_time(&item);
        let mut stop = 0.0;
        let mut first = true;
        for w in run.windows(2) {
            let d = kinematics::transition_time(&self.motions, &w[0].1, &w[1].1);
            stop += if first { self.exposure } else { 0.0 } + d.max(self.readout) + self.exposure;
            first = false;
        }
        if fly >= stop {
            return Err("slower_than_stop_and_go");
        }
        Ok(item)
    }

    /// Kickoff to standstill at the stop position, settled (s).
    fn flight_time(&self, it: &Item) -> f64 {
        let Item::Flight {
            values,
            speeds,
            gaps,
            run_up,
            run_out,
            ..
        } = it
        else {
            return 0.0;
        };
        let m = self.fly_motion;
        if !gaps.is_empty() {
            let offsets = self.offsets(speeds, gaps);
            let v = speeds[speeds.len() - 1];
            return flight_end(
                offsets[offsets.len() - 1],
                self.exposure,
                v,
                m.acceleration,
                m.settle_time,
            );
        }
        let mut m = m;
        m.max_velocity = speeds[0];
        let span = (values[values.len() - 1] - values[0]).abs();
        m.move_time(run_up + span + run_out)
    }

    /// Where an item begins (a flight at its kickoff, in its pass order), resolving free
    /// axes from `cur`; `None` when the flight's kickoff or stop leaves the axis limits.
    fn entry(&self, it: &Item, cur: &[f64]) -> Option<Vec<f64>> {
        match it {
            Item::Stop { q, .. } => Some(resolve(q, cur)),
            Item::Flight {
                base, values, run_up, ..
            } => {
                let mut q = resolve(base, cur);
                let dir = pass_direction(values);
                q[self.axis] = values[0] - dir * run_up;
                let stop = self.exit(it, cur)[self.axis];
                let lim = self.rig.axes[self.axis].limits();
                (lim.contains(q[self.axis]) && lim.contains(stop)).then_some(q)
            }
        }
    }

    /// Where an item leaves the axes.
    fn exit(&self, it: &Item, cur: &[f64]) -> Vec<f64> {
        match it {
            Item::Stop { q, .. } => resolve(q, cur),
            Item::Flight {
                base, values, run_out, ..
            } => {
                let mut q = resolve(base, cur);
                // `values` is in pass order (see `reversed`): the stop is past the last pose.
                let dir = pass_direction(values);
                q[self.axis] = values[values.len() - 1] + dir * run_out;
                q
            }
        }
    }

    /// The times of the engine's run over `items`: each step's transition and capture start,
    /// its flight data, the total, the motion time and the number of segments formed.
    fn schedule(&self, base: &Plan, items: &[Item]) -> (Vec<Step>, f64, f64, usize) {
        let mut steps = Vec::with_capacity(base.steps.len());
        let mut cur = self.kin.home();
        let mut now = 0.0f64;
        let mut motion = 0.0;
        // End of the last exposure, if any (its readout ends `readout` later).
        let mut last_end: Option<f64> = None;
        let mut segment = 0;
        for it in items {
            match it {
                Item::Stop { step, q } => {
                    let q = resolve(q, &cur);
                    let d = kinematics::transition_time(&self.motions, &cur, &q);
                    motion += d;
                    let arrive = now + d;
                    let start = match last_end {
                        Some(e) => arrive.max(e + self.readout),
                        None => arrive,
                    };
                    let mut st = base.steps[*step].clone();
                    st.axes_deg = q.iter().map(|x| (x.to_degrees() * 1e9).round() / 1e9).collect();
                    st.transition_s = d;
                    st.capture_start_s = start;
                    st.flight = None;
                    steps.push(st);
                    now = start + self.exposure;
                    last_end = Some(now);
                    cur = q;
                }
                Item::Flight {
                    steps: members,
                    base: bq,
                    values,
                    speeds,
                    gaps,
                    run_up,
                    ..
                } => {
                    let per_gap = !gaps.is_empty();
                    let offsets = if per_gap {
                        self.offsets(speeds, gaps)
                    } else {
                        Vec::new()
                    };
                    let speed = &speeds[0];
                    let dir = pass_direction(values);
                    let mut kick = resolve(bq, &cur);
                    kick[self.axis] = values[0] - dir * run_up;
                    let d = kinematics::transition_time(&self.motions, &cur, &kick);
                    motion += d;
                    let m = self.fly_motion;
                    let first_offset = speed / m.acceleration + m.settle_time;
                    // The first exposure needs the sensor free: the engine kicks off no
                    // earlier than the previous readout allows.
                    let kickoff = match last_end {
                        Some(e) => (now + d).max(e + self.readout - first_offset),
                        None => now + d,
                    };
                    let exit = self.exit(it, &kick);
                    let flight = self.flight_time(it);
                    motion += flight;
                    let stop_deg = exit[self.axis].to_degrees();
                    let mut prev_start: Option<f64> = None;
                    for (k, &si) in members.iter().enumerate() {
                        let offset = if per_gap {
                            offsets[k]
                        } else {
                            first_offset + (values[k] - values[0]).abs() / speed
                        };
                        let speed = speeds[k];
                        let start = kickoff + offset;
                        let mut q = kick.clone();
                        q[self.axis] = values[k];
                        let mut st = base.steps[si].clone();
                        st.axes_deg = q.iter().map(|x| (x.to_degrees() * 1e9).round() / 1e9).collect();
                        st.transition_s = match prev_start {
                            Some(p) => start - p - self.exposure,
                            None => start - now,
                        };
                        st.capture_start_s = start;
                        let sweep = {
                            let mut a = q.clone();
                            let mut b = q.clone();
                            a[self.axis] -= dir * speed * self.exposure / 2.0;
                            b[self.axis] += dir * speed * self.exposure / 2.0;
                            let (la, _) = self.kin.forward(&a);
                            let (lb, _) = self.kin.forward(&b);
                            la.angle_to(lb).to_degrees()
                        };
                        st.flight = Some(StepFlight {
                            segment,
                            axis: self.axis,
                            velocity_deg_s: (dir * speed).to_degrees(),
                            kickoff_deg: kick[self.axis].to_degrees(),
                            stop_deg,
                            exposure_offset_s: offset,
                            light_sweep_deg: (sweep * 1e9).round() / 1e9,
                            per_gap,
                        });
                        prev_start = Some(start);
                        last_end = Some(start + self.exposure);
                        steps.push(st);
                    }
                    segment += 1;
                    now = kickoff + flight;
                    cur = exit;
                }
            }
        }
        let end = match last_end {
            Some(e) => now.max(e + self.readout),
            None => now,
        };
        let segments = segment;
        (steps, end, motion, segments)
    }

    /// Largest image motion of the sample's corners during one flown exposure (pixels).
    fn image_blur_px(&self, st: &Step, f: &StepFlight) -> f64 {
        let q: Vec<f64> = st.axes_deg.iter().map(|d| d.to_radians()).collect();
        let half = f.velocity_deg_s.to_radians() * self.exposure / 2.0;
        let mut a = q.clone();
        let mut b = q;
        a[f.axis] -= half;
        b[f.axis] += half;
        let (pa, pb) = (self.kin.camera_pose(&a), self.kin.camera_pose(&b));
        let k = self.rig.camera.intrinsics();
        let h = self.rig.geometry.sample_size_mm / 2.0;
        let mut worst: f64 = 0.0;
        for (x, y) in [(-h, -h), (h, -h), (h, h), (-h, h)] {
            let p = gonio_devices::Vec3::new(x, y, 0.0);
            let (ca, cb) = (pa.to_camera(p), pb.to_camera(p));
            let (ua, va) = k.project(ca.x, ca.y, ca.z);
            let (ub, vb) = k.project(cb.x, cb.y, cb.z);
            worst = worst.max(((ua - ub).powi(2) + (va - vb).powi(2)).sqrt());
        }
        worst
    }

    /// Every item's own time plus the quickest way into it from home or any other item's
    /// end: a bound on any order of these items at these velocities.
    fn lower_bound(&self, items: &[Item]) -> f64 {
        let home = self.kin.home();
        let ends: Vec<Vec<f64>> = items
            .iter()
            .flat_map(|it| {
                let mut v = vec![self.exit(it, &home)];
                if matches!(it, Item::Flight { .. }) {
                    v.push(self.exit(&reversed(it.clone()), &home));
                }
                v
            })
            .collect();
        let mut total = 0.0;
        for it in items {
            total += match it {
                Item::Stop { .. } => self.exposure,
                Item::Flight { .. } => self.flight_time(it),
            };
            let mut best = f64::INFINITY;
            for it in [it.clone(), reversed(it.clone())] {
                let Some(entry) = self.entry(&it, &home) else { continue };
                best = best.min(kinematics::transition_time(&self.motions, &home, &entry));
                for e in &ends {
                    // Free axes of the entry take the source's value: resolve against it.
                    if let Some(entry) = self.entry(&it, e) {
                        best = best.min(kinematics::transition_time(&self.motions, e, &entry));
                    }
                }
            }
            total += if best.is_finite() { best } else { 0.0 };
        }
        total
    }
}

/// The item flown the other way (a stop is its own reverse).
fn reversed(it: Item) -> Item {
    match it {
        Item::Flight {
            mut steps,
            base,
            mut values,
            mut speeds,
            mut gaps,
            run_up,
            run_out,
            rev_run_up,
            rev_run_out,
        } => {
            steps.reverse();
            values.reverse();
            speeds.reverse();
            gaps.reverse();
            Item::Flight {
                steps,
                base,
                values,
                speeds,
                gaps,
                run_up: rev_run_up,
                run_out: rev_run_out,
                rev_run_up: run_up,
                rev_run_out: run_out,
            }
        }
        s => s,
    }
}

/// `q` with its free (NaN) axes left where `cur` has them.
fn resolve(q: &[f64], cur: &[f64]) -> Vec<f64> {
    q.iter()
        .zip(cur)
        .map(|(&x, &p)| if x.is_nan() { p } else { x })
        .collect()
}

/// +1 when a flight's poses pass in increasing axis values, −1 otherwise.
fn pass_direction(values: &[f64]) -> f64 {
    if values[values.len() - 1] >= values[0] {
        1.0
    } else {
        -1.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::PlanOptions;
    use gonio_dataset::sweep::Sweep;
    use gonio_devices::Trajectory;

    /// Bonn's ring of 24 at 75° with every third light left out (scattered poses, as a
    /// sparse design leaves them) and a ring of 12 at 45°, seen from one view.
    fn rings() -> Sweep {
        let mut lights = vec![Direction::from_degrees(45.0, 0.0)];
        lights.extend((1..12).map(|k| Direction::from_degrees(45.0, 30.0 * k as f64)));
        lights.extend(
            (0..24)
                .filter(|k| k % 3 != 1)
                .map(|k| Direction::from_degrees(75.0, 15.0 * k as f64)),
        );
        Sweep {
            name: "rings".into(),
            lights,
            views: vec![Direction::from_degrees(30.0, 0.0)],
        }
    }

    #[test]
    fn per_gap_flights_respect_the_readout_the_blur_bound_and_the_axis() {
        let rig = RigSpec::default_rig();
        let opts = PlanOptions {
            kicks: 200,
            ..Default::default()
        };
        let base = Plan::build(&rig, &rings(), &opts).unwrap();
        let plan = base.into_fly(&rig, &opts, FlyOptions::new(0.5).unwrap()).unwrap();
        let fly = plan.fly.as_ref().unwrap();
        assert_eq!(fly.velocity_profile, "per_gap");
        assert_eq!(fly.flown_segments, 2, "{fly:?}");
        assert!(fly.max_light_sweep_deg <= 0.5 + 1e-6, "{fly:?}");
        let spec = &rig.axes.iter().find(|a| a.role == "light_azimuth").unwrap();
        let m = spec.motion();
        let e = rig.camera.exposure_s;
        let readout = rig.camera.overlapped_readout_s().unwrap();
        let flown: Vec<&Step> = plan.steps.iter().filter(|s| s.flight.is_some()).collect();
        for seg in 0..fly.flown_segments {
            let steps: Vec<&Step> = flown
                .iter()
                .copied()
                .filter(|s| s.flight.as_ref().unwrap().segment == seg)
                .collect();
            let fs: Vec<&StepFlight> = steps.iter().map(|s| s.flight.as_ref().unwrap()).collect();
            assert!(fs.iter().all(|f| f.per_gap));
            for w in steps.windows(2) {
                assert!(
                    w[1].capture_start_s - w[0].capture_start_s - e >= readout - 1e-9,
                    "consecutive exposures are a readout apart"
                );
            }
            for f in &fs {
                assert!(f.velocity_deg_s.abs().to_radians() <= m.max_velocity * (1.0 + 1e-12));
            }
            // The profile the engine rebuilds passes every pose mid-exposure.
            let ax = fs[0].axis;
            let tr = Trajectory::flight(
                fs[0].kickoff_deg.to_radians(),
                &steps.iter().map(|s| s.axes_deg[ax].to_radians()).collect::<Vec<_>>(),
                &fs.iter()
                    .map(|f| f.velocity_deg_s.abs().to_radians())
                    .collect::<Vec<_>>(),
                &fs.iter().map(|f| f.exposure_offset_s).collect::<Vec<_>>(),
                e,
                m.acceleration,
                m.max_velocity,
                m.settle_time,
                fs[0].stop_deg.to_radians(),
            )
            .unwrap();
            for (s, f) in steps.iter().zip(&fs) {
                let x = tr.position_at(f.exposure_offset_s + e / 2.0).to_degrees();
                assert!((x - s.axes_deg[ax]).abs() < 1e-6, "{x} vs {}", s.axes_deg[ax]);
            }
            assert!(tr.knots.iter().all(|k| k.v.abs() <= m.max_velocity * (1.0 + 1e-9)));
            assert!(tr.knots.iter().all(|k| k.a.abs() <= m.acceleration * (1.0 + 1e-12)));
        }
        assert!(plan.durations.optimized_s < fly.stop_and_go_overlapped_s);
    }
}
