//! The motion model of one axis: trapezoidal (or S-curve) velocity profile plus settle time.
//!
//! Planning and the simulator use the same formulas, so a planned duration is exactly what
//! the simulated rig takes. Units are the axis' own (radians for rotary axes, millimetres
//! for linear ones) per second.

use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MotionModel {
    /// Maximum velocity (units/s), > 0.
    pub max_velocity: f64,
    /// Acceleration and deceleration (units/s²), > 0.
    pub acceleration: f64,
    /// Optional jerk limit (units/s³); `None` means a trapezoidal profile.
    pub jerk: Option<f64>,
    /// Time the axis needs to come to rest after the profile ends (s).
    pub settle_time: f64,
    /// Moves shorter than this are skipped (no motion, no settle).
    pub deadband: f64,
}

impl MotionModel {
    /// Duration of the velocity profile for a move of `distance` (sign ignored), without settle.
    ///
    /// Trapezoid: short moves never reach `max_velocity` (triangle, t = 2√(d/a)); long ones
    /// cruise (t = d/v + v/a). With a jerk limit each acceleration phase is an S-curve; the
    /// formula used is the standard conservative one: the trapezoid time plus a/j.
    pub fn profile_time(&self, distance: f64) -> f64 {
        let d = distance.abs();
        if d <= self.deadband {
            return 0.0;
        }
        let v = self.max_velocity;
        let a = self.acceleration;
        let base = if d < v * v / a {
            2.0 * (d / a).sqrt()
        } else {
            d / v + v / a
        };
        match self.jerk {
            Some(j) if j > 0.0 && j.is_finite() => base + a / j,
            _ => base,
        }
    }

    /// Duration of a full move including settling; zero for moves inside the deadband.
    pub fn move_time(&self, distance: f64) -> f64 {
        if distance.abs() <= self.deadband {
            0.0
        } else {
            self.profile_time(distance) + self.settle_time
        }
    }

    /// Position along a trapezoidal move of signed `distance` at time `t` since its start
    /// (the jerk limit is ignored here: it shifts timing by a/j but not the path).
    pub fn position_at(&self, distance: f64, t: f64) -> f64 {
        let d = distance.abs();
        let s = distance.signum();
        let total = self.profile_time(distance);
        if d <= self.deadband || t >= total {
            return distance;
        }
        if t <= 0.0 {
            return 0.0;
        }
        let a = self.acceleration;
        let v = self.max_velocity;
        let (t_acc, v_peak) = if d < v * v / a {
            ((d / a).sqrt(), (d * a).sqrt())
        } else {
            (v / a, v)
        };
        let t_cruise = (total - 2.0 * t_acc).max(0.0);
        let p = if t < t_acc {
            0.5 * a * t * t
        } else if t < t_acc + t_cruise {
            0.5 * a * t_acc * t_acc + v_peak * (t - t_acc)
        } else {
            let tr = total - t;
            d - 0.5 * a * tr * tr
        };
        s * p.clamp(0.0, d)
    }
}

/// One phase of a [`Trajectory`]: from `t` on (until the next knot), the position is
/// `x + v·(t' − t) + a·(t' − t)²/2`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Knot {
    pub t: f64,
    pub x: f64,
    pub v: f64,
    pub a: f64,
}

/// A move given phase by phase (constant acceleration within each): what a fly-scan with a
/// velocity profile per gap commands (`Axis::start_trajectory`). Times are relative to the
/// move's start; the last knot is the rest position, where the axis then settles until
/// `end`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Trajectory {
    pub knots: Vec<Knot>,
    /// When the axis stands settled at its last knot (s after the start).
    pub end: f64,
}

impl Trajectory {
    /// Position at `t` since the start (the first knot's before it, the last one's after).
    pub fn position_at(&self, t: f64) -> f64 {
        let Some(first) = self.knots.first() else { return 0.0 };
        if t <= first.t {
            return first.x;
        }
        let i = self.knots.partition_point(|k| k.t <= t) - 1;
        let k = &self.knots[i];
        if i + 1 == self.knots.len() {
            return k.x;
        }
        let dt = t - k.t;
        k.x + k.v * dt + 0.5 * k.a * dt * dt
    }

    /// Velocity at `t` since the start.
    pub fn velocity_at(&self, t: f64) -> f64 {
        let Some(first) = self.knots.first() else { return 0.0 };
        if t <= first.t {
            return 0.0;
        }
        let i = self.knots.partition_point(|k| k.t <= t) - 1;
        let k = &self.knots[i];
        if i + 1 == self.knots.len() {
            return 0.0;
        }
        k.v + k.a * (t - k.t)
    }

    /// The last knot's position (where the move ends).
    pub fn target(&self) -> f64 {
        self.knots.last().map_or(0.0, |k| k.x)
    }

    /// A fly-scan flight with a velocity profile per gap (see `gonio_acquire::plan::fly`):
    /// from rest at `kickoff` the axis accelerates at `a` to the first pose's speed and holds
    /// it (its settle time at cruise, included in `offsets[0]`); pose `k` is exposed from
    /// `offsets[k]` for `exposure` at the constant speed `speeds[k]`, centred on `poses[k]`;
    /// between two exposures the axis ramps (at `a`) to one cruise speed and to the next
    /// pose's speed ([`gap_cruise_speed`], the gap lasting exactly what the offsets leave);
    /// after the last exposure it decelerates to rest at `stop` and settles for `settle`.
    /// `None` when a gap cannot last its time (an inconsistent plan).
    #[allow(clippy::too_many_arguments)]
    pub fn flight(
        kickoff: f64,
        poses: &[f64],
        speeds: &[f64],
        offsets: &[f64],
        exposure: f64,
        a: f64,
        vmax: f64,
        settle: f64,
        stop: f64,
    ) -> Option<Trajectory> {
        let n = poses.len();
        if n == 0 || speeds.len() != n || offsets.len() != n || a.is_nan() || a <= 0.0 {
            return None;
        }
        let s = if stop >= kickoff { 1.0 } else { -1.0 };
        let half = 0.5 * exposure;
        let mut knots = vec![Knot {
            t: 0.0,
            x: kickoff,
            v: 0.0,
            a: s * a,
        }];
        let v0 = speeds[0];
        knots.push(Knot {
            t: v0 / a,
            x: kickoff + s * v0 * v0 / (2.0 * a),
            v: s * v0,
            a: 0.0,
        });
        for k in 0..n {
            let v = speeds[k];
            knots.push(Knot {
                t: offsets[k],
                x: poses[k] - s * v * half,
                v: s * v,
                a: 0.0,
            });
            if k + 1 < n {
                let t0 = offsets[k] + exposure;
                let x0 = poses[k] + s * v * half;
                let v1 = speeds[k + 1];
                let d = s * ((poses[k + 1] - s * v1 * half) - x0);
                let t = offsets[k + 1] - t0;
                let vc = gap_cruise_speed(d, v, v1, a, vmax, t)?;
                gap_knots(&mut knots, t0, x0, s, v, v1, vc, t, a);
            }
        }
        let v = speeds[n - 1];
        let t_out = offsets[n - 1] + exposure;
        knots.push(Knot {
            t: t_out,
            x: poses[n - 1] + s * v * half,
            v: s * v,
            a: -s * a,
        });
        let rest = t_out + v / a;
        knots.push(Knot {
            t: rest,
            x: stop,
            v: 0.0,
            a: 0.0,
        });
        Some(Trajectory {
            knots,
            end: flight_end(offsets[n - 1], exposure, v, a, settle),
        })
    }
}

/// When a per-gap flight stands settled: its last exposure (from `last_offset`, lasting
/// `exposure`) ends, the axis decelerates from `v_last` at `a`, then settles. The planner's
/// flight time and [`Trajectory::flight`]'s `end` (what the simulated axis runs) are this
/// one expression, so the rig clock equals the plan.
pub fn flight_end(last_offset: f64, exposure: f64, v_last: f64, a: f64, settle: f64) -> f64 {
    (last_offset + exposure + v_last / a) + settle
}

/// The knots of one gap from `(t0, x0)` at speed `v0` to speed `v1`, through cruise speed
/// `vc`, lasting `t` (direction `s`).
#[allow(clippy::too_many_arguments)]
fn gap_knots(knots: &mut Vec<Knot>, t0: f64, x0: f64, s: f64, v0: f64, v1: f64, vc: f64, t: f64, a: f64) {
    let t1 = (vc - v0).abs() / a;
    let t3 = (vc - v1).abs() / a;
    let t2 = (t - t1 - t3).max(0.0);
    let mut x = x0;
    if t1 > 0.0 {
        knots.push(Knot {
            t: t0,
            x,
            v: s * v0,
            a: s * (vc - v0).signum() * a,
        });
        x += s * 0.5 * (v0 + vc) * t1;
    }
    knots.push(Knot {
        t: t0 + t1,
        x,
        v: s * vc,
        a: 0.0,
    });
    x += s * vc * t2;
    if t3 > 0.0 {
        knots.push(Knot {
            t: t0 + t1 + t2,
            x,
            v: s * vc,
            a: s * (v1 - vc).signum() * a,
        });
    }
}

/// Duration of the gap profile `v0 → vc → v1` (speeds ≥ 0 along the travel; ramps at `a`,
/// cruise at `vc` in between) over distance `d`; infinite when the ramps alone overrun `d`
/// or `vc` is not positive.
pub fn gap_time(d: f64, v0: f64, v1: f64, a: f64, vc: f64) -> f64 {
    if vc.is_nan() || vc <= 0.0 {
        return f64::INFINITY;
    }
    let ramps = ((vc * vc - v0 * v0).abs() + (vc * vc - v1 * v1).abs()) / (2.0 * a);
    let cruise = d - ramps;
    if cruise < -1e-12 * d.abs().max(1e-3) {
        return f64::INFINITY;
    }
    ((vc - v0).abs() + (vc - v1).abs()) / a + cruise.max(0.0) / vc
}

/// The fastest gap from speed `v0` to `v1` over `d` (trapezoid up to `vmax`, or triangle):
/// `None` when `d` is too short to change speed from one to the other at `a`.
pub fn gap_min_time(d: f64, v0: f64, v1: f64, a: f64, vmax: f64) -> Option<f64> {
    let peak = gap_peak(d, v0, v1, a, vmax)?;
    let t = gap_time(d, v0, v1, a, peak);
    t.is_finite().then_some(t)
}

fn gap_peak(d: f64, v0: f64, v1: f64, a: f64, vmax: f64) -> Option<f64> {
    let (lo, hi) = (v0.min(v1), v0.max(v1));
    if !(d.is_finite() && a > 0.0 && lo >= 0.0) || d < (hi * hi - lo * lo) / (2.0 * a) - 1e-12 * d.abs().max(1e-3) {
        return None;
    }
    // The triangle's peak, capped at the axis' maximum (never below the faster end speed).
    Some(vmax.min((a * d + 0.5 * (v0 * v0 + v1 * v1)).sqrt()).max(hi))
}

/// The cruise speed of the gap `v0 → vc → v1` over `d` that lasts exactly `t` (closed
/// form in each of the three cases: `vc` above both end speeds, between them, below both);
/// `None` when no such profile exists (`t` shorter than [`gap_min_time`], beyond 1 ns, or
/// longer than the slowest profile that still moves forward).
pub fn gap_cruise_speed(d: f64, v0: f64, v1: f64, a: f64, vmax: f64, t: f64) -> Option<f64> {
    let peak = gap_peak(d, v0, v1, a, vmax)?;
    let (lo, hi) = (v0.min(v1), v0.max(v1));
    let t_peak = gap_time(d, v0, v1, a, peak);
    if !t_peak.is_finite() {
        return None;
    }
    if t <= t_peak {
        return (t >= t_peak - 1e-9).then_some(peak);
    }
    if t <= gap_time(d, v0, v1, a, hi) {
        // hi ≤ vc ≤ peak: vc² − (a·t + v0 + v1)·vc + a·K = 0, the smaller root.
        let k = d + (v0 * v0 + v1 * v1) / (2.0 * a);
        let b = a * t + v0 + v1;
        let disc = (b * b - 4.0 * a * k).max(0.0);
        return Some(((b - disc.sqrt()) / 2.0).clamp(hi, peak));
    }
    if lo > 0.0 && t <= gap_time(d, v0, v1, a, lo) {
        // lo ≤ vc ≤ hi: one ramp, the cruise takes the rest.
        let vc = (d - (hi * hi - lo * lo) / (2.0 * a)) / (t - (hi - lo) / a);
        return Some(vc.clamp(lo, hi));
    }
    // 0 < vc ≤ lo: vc² + (a·t − v0 − v1)·vc − L = 0, the larger root.
    let l = a * d - 0.5 * (v0 * v0 + v1 * v1);
    let b = a * t - v0 - v1;
    let disc = b * b + 4.0 * l;
    if disc < 0.0 {
        return None;
    }
    let vc = ((-b + disc.sqrt()) / 2.0).min(lo);
    (vc > 0.0 && gap_time(d, v0, v1, a, vc).is_finite()).then_some(vc)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn m() -> MotionModel {
        MotionModel {
            max_velocity: 2.0,
            acceleration: 4.0,
            jerk: None,
            settle_time: 0.1,
            deadband: 1e-6,
        }
    }

    #[test]
    fn triangle_and_trapezoid() {
        // v²/a = 1: d = 0.25 is a triangle, t = 2 sqrt(0.25/4) = 0.5
        assert!((m().profile_time(0.25) - 0.5).abs() < 1e-12);
        // d = 3: t = 3/2 + 2/4 = 2
        assert!((m().profile_time(-3.0) - 2.0).abs() < 1e-12);
        assert_eq!(m().move_time(1e-9), 0.0);
        // continuity at the switch point d = v²/a
        let a = m().profile_time(1.0 - 1e-12);
        let b = m().profile_time(1.0 + 1e-12);
        assert!((a - b).abs() < 1e-9);
    }

    #[test]
    fn position_profile_ends_at_target() {
        for &d in &[0.25, 3.0, -3.0] {
            let t = m().profile_time(d);
            assert!((m().position_at(d, t) - d).abs() < 1e-12);
            assert_eq!(m().position_at(d, 0.0), 0.0);
            let mid = m().position_at(d, t / 2.0);
            assert!((mid - d / 2.0).abs() < 1e-9, "symmetric profile: {mid} vs {}", d / 2.0);
        }
    }

    /// The default rig's light-azimuth axis (degrees: 20 °/s, 20 °/s², settle 0.3 s).
    const A: f64 = 20.0;
    const VMAX: f64 = 20.0;

    #[test]
    fn a_gap_lasts_exactly_its_time_within_the_axis_limits() {
        for &(d, v0, v1) in &[
            (14.5, 10.0, 10.0),
            (3.0, 5.0, 12.0),
            (0.8, 10.0, 9.0),
            (40.0, 1.0, 2.0),
            (0.5, 1.0, 1.0),
            (9.0, 19.0, 3.0),
        ] {
            let tmin = gap_min_time(d, v0, v1, A, VMAX).unwrap();
            assert!(tmin > 0.0);
            for t in [tmin, tmin + 1e-3, tmin + 0.1, tmin + 1.0, 3.0 * tmin, 50.0] {
                let Some(vc) = gap_cruise_speed(d, v0, v1, A, VMAX, t) else {
                    // Only too long a gap has no profile (it would have to stop).
                    assert!(0.5 * (v0 * v0 + v1 * v1) > A * d, "{d} {v0} {v1} {t}");
                    continue;
                };
                assert!(vc > 0.0 && vc <= VMAX, "{vc}");
                let got = gap_time(d, v0, v1, A, vc);
                assert!((got - t).abs() < 1e-9, "d {d} v {v0}->{v1}: {got} vs {t}");
            }
            assert!(gap_cruise_speed(d, v0, v1, A, VMAX, tmin - 1e-3).is_none());
        }
        // Too short to change speed: no profile.
        assert!(gap_min_time(0.1, 1.0, 10.0, A, VMAX).is_none());
        // Distant poses: cruise at the maximum velocity.
        let t = gap_min_time(100.0, 10.0, 10.0, A, VMAX).unwrap();
        assert!((t - (2.0 * 10.0 / A + (100.0 - 2.0 * (400.0 - 100.0) / (2.0 * A)) / VMAX)).abs() < 1e-12);
    }

    /// Offsets as the planner lays them out: each gap the fastest, never below `readout`.
    fn offsets(poses: &[f64], speeds: &[f64], e: f64, readout: f64, settle: f64, vmax: f64) -> Vec<f64> {
        let mut o = vec![speeds[0] / A + settle];
        for k in 0..poses.len() - 1 {
            let d = (poses[k + 1] - poses[k]).abs() - (speeds[k] + speeds[k + 1]) * e / 2.0;
            let t = gap_min_time(d, speeds[k], speeds[k + 1], A, vmax).unwrap().max(readout);
            o.push(o[k] + e + t);
        }
        o
    }

    #[test]
    fn a_flight_passes_its_poses_at_their_speeds_within_the_limits() {
        let (e, readout, settle) = (0.05, 1.0, 0.3);
        let poses = [0.0, 12.0, 30.0, 55.0, 68.0, 140.0];
        let speeds = [10.0, 8.0, 10.0, 6.0, 10.0, 10.0];
        let o = offsets(&poses, &speeds, e, readout, settle, VMAX);
        let run_up = speeds[0] * speeds[0] / (2.0 * A) + speeds[0] * settle + speeds[0] * e / 2.0;
        let run_out = speeds[5] * e / 2.0 + speeds[5] * speeds[5] / (2.0 * A);
        let tr = Trajectory::flight(-run_up, &poses, &speeds, &o, e, A, VMAX, settle, 140.0 + run_out).unwrap();
        for k in 0..poses.len() {
            // Centred on its pose, at its speed through the exposure.
            assert!((tr.position_at(o[k] + e / 2.0) - poses[k]).abs() < 1e-9, "pose {k}");
            for f in [0.01, 0.5, 0.99] {
                assert!((tr.velocity_at(o[k] + f * e) - speeds[k]).abs() < 1e-9);
            }
            if k > 0 {
                assert!(
                    o[k] - o[k - 1] - e >= readout - 1e-12,
                    "a gap is never shorter than the readout"
                );
            }
        }
        // Never beyond the axis' velocity or acceleration, and continuous.
        for k in &tr.knots {
            assert!(k.v.abs() <= VMAX + 1e-9 && k.a.abs() <= A + 1e-12, "{k:?}");
        }
        let dt = 1e-4;
        let mut t = 0.0;
        while t < tr.end {
            let v = tr.velocity_at(t);
            assert!((0.0..=VMAX + 1e-9).contains(&v), "{t}: {v}");
            let dx = tr.position_at(t + dt) - tr.position_at(t);
            assert!(dx >= -1e-9 && dx <= VMAX * dt + 1e-7, "{t}: {dx}");
            t += dt;
        }
        assert_eq!(tr.position_at(tr.end + 1.0), 140.0 + run_out);
        assert_eq!(tr.end, flight_end(o[5], e, speeds[5], A, settle));
        // Between the distant poses the axis speeds up to its maximum.
        assert!(tr.knots.iter().any(|k| (k.v - VMAX).abs() < 1e-9));
    }

    #[test]
    fn a_constant_velocity_flight_is_the_old_trapezoid() {
        // The axis capped at the flight's velocity: no gap can speed up, and the profile is
        // the constant-velocity move from kickoff to stop, timed as before.
        let (e, readout, settle, v) = (0.05, 0.2, 0.3, 8.0);
        let poses = [10.0, 25.0, 40.0, 55.0];
        let speeds = [v; 4];
        let o = offsets(&poses, &speeds, e, readout, settle, v);
        let run_up = v * v / (2.0 * A) + v * settle + v * e / 2.0;
        let run_out = v * e / 2.0 + v * v / (2.0 * A);
        let (kick, stop) = (poses[0] - run_up, poses[3] + run_out);
        let tr = Trajectory::flight(kick, &poses, &speeds, &o, e, A, v, settle, stop).unwrap();
        let old = MotionModel {
            max_velocity: v,
            acceleration: A,
            jerk: None,
            settle_time: settle,
            deadband: 1e-9,
        };
        assert!(
            (tr.end - old.move_time(stop - kick)).abs() < 1e-9,
            "{} vs {}",
            tr.end,
            old.move_time(stop - kick)
        );
        for k in 0..4 {
            let first_offset = v / A + settle;
            assert!((o[k] - (first_offset + (poses[k] - poses[0]) / v)).abs() < 1e-9);
        }
        let mut t = 0.0;
        while t < tr.end {
            let want = kick + old.position_at(stop - kick, t);
            assert!((tr.position_at(t) - want).abs() < 1e-9, "{t}");
            t += 1e-3;
        }
    }
}
