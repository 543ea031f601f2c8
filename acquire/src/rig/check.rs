//! `gonio devices check`: before an eight-hour run, ask every device of a rig file whether
//! it answers, what it is, and whether it does what the run will ask of it.
//!
//! The check builds the rig as a run would ([`Rig::build_with`], so a missing port,
//! misspelt backend or compiled-out feature fails here, with the same message), then per
//! device: its identity (model, firmware), for each axis a small step toward the middle of
//! its soft limits and back (homing it first when the controller has no reference yet),
//! one frame at the rig's exposure, and the lamp switched on (its voltage and current read
//! back where the supply measures them) and off. Every failure is kept with a fix a person
//! can act on; the report is plain data (the CLI prints it as a table or JSON).

use super::backends::{Backends, RigBuildError};
use super::Rig;
use gonio_devices::rig::RigSpec;
use gonio_devices::{CameraConfig, DeviceError, Vec3};
use gonio_simulator::{SampleSpec, SimOptions};
use serde::Serialize;

/// What the check may do.
#[derive(Clone, Debug)]
pub struct CheckOptions {
    /// Step each axis and back (`--no-move` turns it off: no axis moves or homes).
    pub moves: bool,
    /// The step, in the axis' unit at the interface: degrees (rotary axes).
    pub step_deg: f64,
}

impl Default for CheckOptions {
    fn default() -> Self {
        CheckOptions {
            moves: true,
            step_deg: 1.0,
        }
    }
}

/// The whole check: `ok` only when every device answered and did what it was asked.
/// A stable struct: `gonio devices check --json` prints it as is.
#[derive(Clone, Debug, Serialize)]
pub struct CheckReport {
    pub rig: String,
    pub ok: bool,
    pub moved: bool,
    pub devices: Vec<DeviceCheck>,
}

/// One device's row.
#[derive(Clone, Debug, Serialize)]
pub struct DeviceCheck {
    /// `axis NAME`, `camera`, `light`, or `rig` (the rig could not be built).
    pub device: String,
    /// The rig file's backend (`sim`, `zaber`, `hmp`, …).
    pub backend: String,
    /// Whether the device answered every question the check asked it.
    pub answered: bool,
    /// What the device says it is, when it answered that.
    pub identity: Option<String>,
    /// What it reported, one sentence each (positions, frame statistics, lamp read-back).
    pub reported: Vec<String>,
    /// The first failure, as the device or driver put it.
    pub failure: Option<String>,
    /// What to do about the failure.
    pub fix: Option<String>,
}

impl DeviceCheck {
    fn new(device: String, backend: &str) -> Self {
        DeviceCheck {
            device,
            backend: backend.to_string(),
            answered: true,
            identity: None,
            reported: Vec::new(),
            failure: None,
            fix: None,
        }
    }

    fn fail(&mut self, failure: String, fix: String) {
        self.answered = false;
        if self.failure.is_none() {
            self.failure = Some(failure);
            self.fix = Some(fix);
        }
    }

    fn device_error(&mut self, what: &str, e: &DeviceError) {
        self.fail(format!("{what}: {e}"), fix_device(e));
    }
}

/// Check every device of `spec` (see the module doc). `sample` and `sim` are used only by
/// the simulated parts of a mixed rig; a rig with no simulated part builds no simulator.
pub async fn check(
    spec: &RigSpec,
    sample: &SampleSpec,
    sim: &SimOptions,
    backends: &Backends,
    opts: &CheckOptions,
) -> CheckReport {
    let mut report = CheckReport {
        rig: spec.name.clone(),
        ok: false,
        moved: opts.moves,
        devices: Vec::new(),
    };
    let rig = match Rig::build_with(spec, sample, sim, backends) {
        Ok(r) => r,
        Err(e) => {
            let mut row = DeviceCheck::new("rig".into(), "-");
            row.fail(e.to_string(), fix_build(&e));
            row.reported
                .push("no device was asked anything: the rig stops building at its first failure".into());
            report.devices.push(row);
            return report;
        }
    };
    for (i, axis) in rig.axes.iter().enumerate() {
        let a = &spec.axes[i];
        let mut row = DeviceCheck::new(format!("axis {}", a.name), &a.backend);
        check_axis(&rig, i, axis.as_ref(), opts, &mut row).await;
        report.devices.push(row);
    }
    // The lamp is on while the camera takes its frame, so the frame's statistics say
    // whether the camera sees a lit scene (a dark frame from a working camera would pass).
    let mut light = DeviceCheck::new("light".into(), &spec.light.backend);
    let lit = switch_on(&rig, &mut light).await;
    let mut camera = DeviceCheck::new("camera".into(), &spec.camera.backend);
    check_camera(&rig, &mut camera).await;
    if lit {
        match rig.light.set(false, 0.0).await {
            Ok(()) => light.reported.push("off".into()),
            Err(e) => light.device_error("switch off", &e),
        }
    }
    report.devices.push(camera);
    report.devices.push(light);
    report.ok = report.devices.iter().all(|d| d.answered);
    report
}

async fn check_axis(
    rig: &Rig,
    index: usize,
    axis: &dyn gonio_devices::Axis,
    opts: &CheckOptions,
    row: &mut DeviceCheck,
) {
    match axis.identity().await {
        Ok(id) => row.identity = Some(id),
        Err(e) => return row.device_error("identity", &e),
    }
    // A controller without a reference position may refuse to say where it is (Zaber
    // does): that is an answer, not a failure; the step below homes it first.
    let p = match axis.position().await {
        Ok(p) => Some(p),
        Err(DeviceError::NotHomed { .. }) => None,
        Err(e) => return row.device_error("position", &e),
    };
    let homed = match (p, axis.status().await) {
        (None, _) => false,
        (Some(_), Ok(s)) => s.homed,
        (Some(_), Err(e)) => return row.device_error("status", &e),
    };
    match p {
        Some(p) => row.reported.push(format!(
            "position {:.3}°{}",
            p.to_degrees(),
            if homed { "" } else { " (not homed)" }
        )),
        None => row.reported.push("not homed: no position until it is".into()),
    }
    if !opts.moves {
        return;
    }
    let p = match p {
        Some(p) if homed => p,
        _ => {
            if let Err(e) = axis.home().await {
                return row.device_error("home", &e);
            }
            match axis.position().await {
                Ok(p) => {
                    row.reported.push(format!("homed: position {:.3}°", p.to_degrees()));
                    p
                }
                Err(e) => return row.device_error("position after homing", &e),
            }
        }
    };
    let Some(target) = step_target(rig, index, p, opts.step_deg.to_radians()) else {
        row.reported.push(format!(
            "step skipped: no {}° step from {:.3}° stays inside the soft limits and clear of the camera body",
            opts.step_deg,
            p.to_degrees()
        ));
        return;
    };
    let there = match axis.move_abs(target).await {
        Ok(x) => x,
        Err(e) => return row.device_error("step", &e),
    };
    let back = match axis.move_abs(p).await {
        Ok(x) => x,
        Err(e) => return row.device_error("step back", &e),
    };
    row.reported.push(format!(
        "stepped to {:.3}° (read back {:.3}°) and back to {:.3}° (read back {:.3}°)",
        target.to_degrees(),
        there.to_degrees(),
        p.to_degrees(),
        back.to_degrees()
    ));
}

/// Where axis `index` steps from `p`: `step` toward the middle of its soft limits, or away
/// from it if that does not fit; never to a pose whose lamp comes nearer the camera than
/// the camera body's radius plus the rig's clearance unless it already was that near.
/// (The rig file has no model of the arms themselves; the camera body sphere is the
/// obstacle the planner already keeps the lamp's path clear of.)
fn step_target(rig: &Rig, index: usize, p: f64, step: f64) -> Option<f64> {
    let lim = rig.axes[index].limits();
    let toward_middle = if p <= (lim.min + lim.max) / 2.0 { step } else { -step };
    // The rest of the rig where the kinematics puts it after homing (the check moves one
    // axis at a time from there; the other axes' real positions are close to it).
    let mut q = rig.kinematics.home();
    let clear = |q: &[f64]| -> f64 {
        let lamp: Vec3 = rig.kinematics.light_position(q);
        let camera = rig.kinematics.camera_pose(q).position;
        (lamp - camera).norm() - rig.spec.geometry.camera_body_radius_mm - rig.spec.geometry.clearance_mm
    };
    if index >= q.len() {
        return None;
    }
    q[index] = p;
    let now = clear(&q);
    [toward_middle, -toward_middle].into_iter().find_map(|d| {
        let t = p + d;
        if !(lim.min..=lim.max).contains(&t) {
            return None;
        }
        q[index] = t;
        let c = clear(&q);
        (c > 0.0 || c >= now).then_some(t)
    })
}

async fn check_camera(rig: &Rig, row: &mut DeviceCheck) {
    match rig.camera.identity().await {
        Ok(id) => row.identity = Some(id),
        Err(e) => return row.device_error("identity", &e),
    }
    let c = &rig.spec.camera;
    let want = CameraConfig {
        width: c.width,
        height: c.height,
        exposure: c.exposure_s,
        gain: c.gain,
        bit_depth: c.bit_depth,
    };
    let config = match rig.camera.configure(&want).await {
        Ok(k) => k,
        Err(e) => return row.device_error("configure", &e),
    };
    row.reported.push(format!(
        "configured {}×{}, exposure {} s, gain {}, {} bit",
        config.width, config.height, config.exposure, config.gain, config.bit_depth
    ));
    let policy = match rig.capture_policy() {
        Ok(p) => p,
        Err(e) => return row.device_error("capture policy", &e),
    };
    match rig.capture(&policy, &config).await {
        Ok((frame, _)) => {
            let n = frame.data.len().max(1) as f64;
            let mean = frame.data.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
            let max = frame.data.iter().copied().max().unwrap_or(0);
            row.reported.push(format!(
                "frame {}×{} at {} s: mean {:.1} DN, max {} DN of {}",
                frame.width,
                frame.height,
                frame.meta.exposure,
                mean,
                max,
                frame.max_dn()
            ));
        }
        Err(e) => row.fail(
            format!("capture (after {} attempt(s)): {}", e.attempts, e.source),
            "check the camera's cable and power, that no other program holds it, and the \
             exposure and capture timeout in the rig file's [camera]"
                .into(),
        ),
    }
}

/// Identity, switch on, read back; whether the lamp is on (to be switched off).
async fn switch_on(rig: &Rig, row: &mut DeviceCheck) -> bool {
    match rig.light.identity().await {
        Ok(id) => row.identity = Some(id),
        Err(e) => {
            row.device_error("identity", &e);
            return false;
        }
    }
    if let Err(e) = rig.light.set(true, 1.0).await {
        row.device_error("switch on", &e);
        return false;
    }
    match rig.light.read_back().await {
        Ok(Some(r)) => row
            .reported
            .push(format!("on: {:.3} V, {:.3} A", r.voltage_v, r.current_a)),
        Ok(None) => row.reported.push("on (this light measures nothing)".into()),
        Err(e) => row.device_error("read back", &e),
    }
    true
}

/// What to do about a rig that does not build.
fn fix_build(e: &RigBuildError) -> String {
    use gonio_devices::serial::SerialConfigError as S;
    match e {
        RigBuildError::NotBuilt { feature, .. } => {
            format!("rebuild gonio with `--features {feature}`, or name another backend in the rig file")
        }
        RigBuildError::UnknownBackend { available, .. } => {
            format!("use one of the available backends in the rig file: {available}")
        }
        RigBuildError::Serial { error, .. } => match error {
            S::Open { port, .. } | S::LightOpen { port, .. } => format!(
                "check that {port} exists (`gonio devices list`), that the controller is powered and \
                 cabled, that you may open it (group `dialout`) and that no other program holds it; \
                 then `gonio devices probe {port}`. For the emulators, start `gonio sim serve-stage` \
                 or `gonio sim serve-light` and use the port it prints"
            ),
            _ => "fix the named option in the rig file (the header comment of devices/rigs/emulated-zaber.toml \
                  and emulated-hmp.toml lists every option)"
                .into(),
        },
        RigBuildError::Camera { .. } => {
            "check that the camera device exists (`gonio devices list`; a still camera: `gphoto2 \
             --auto-detect`), that you may open it (group `video`, or `plugdev` for USB) and that no \
             other program streams from it or holds it (a desktop's gvfs-gphoto2-volume-monitor)"
                .into()
        }
        RigBuildError::Option { .. } | RigBuildError::Sim(_) => "fix the named key in the rig file".into(),
        RigBuildError::Sample(_) => "fix the sample file (or pass another --sample)".into(),
    }
}

/// What to do about a device that failed a question.
fn fix_device(e: &DeviceError) -> String {
    match e {
        DeviceError::Timeout { .. } | DeviceError::Disconnected { .. } | DeviceError::Garbled { .. } => {
            "the device stopped answering: check power, cable and baud rate (`gonio devices probe PORT`)".into()
        }
        DeviceError::NotHomed { .. } => "home the axis (run the check without --no-move, or home it by hand)".into(),
        DeviceError::SoftLimit { .. } => "the axis stands outside its soft limits: move it inside by hand, or \
                                         check min_deg/max_deg in the rig file"
            .into(),
        DeviceError::LimitSwitch { .. } | DeviceError::Stall { .. } | DeviceError::MissedTarget { .. } => {
            "the axis could not move freely: look for an obstacle or a loose coupling, then clear the \
             controller's fault"
                .into()
        }
        DeviceError::Rejected { .. } | DeviceError::Other { .. } => {
            "the controller refused: read its reason above and the device's manual".into()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_step_goes_toward_the_middle_of_the_limits_and_stays_inside() {
        let spec = RigSpec::default_rig();
        let sample = SampleSpec::resolve("leather").unwrap();
        let rig = Rig::build(&spec, &sample, &SimOptions::default()).unwrap();
        let step = 1f64.to_radians();
        let lim = rig.axes[0].limits();
        // Below the middle: up; above it: down; at the upper limit: down, inside.
        assert_eq!(step_target(&rig, 0, 0.0, step), Some(step));
        let down = step_target(&rig, 0, lim.max - 0.1 * step, step).unwrap();
        assert!((down - (lim.max - 1.1 * step)).abs() < 1e-12, "{down}");
        assert_eq!(step_target(&rig, 0, lim.min, step), Some(lim.min + step));
        // A step larger than the whole range fits nowhere.
        assert_eq!(step_target(&rig, 0, 0.0, 10.0 * (lim.max - lim.min)), None);
    }
}
