//! Issue 31, "no simulator under a real rig": a rig whose axes are serial stages (the
//! emulated Zaber chain over a pty), whose lamp is on an HMP supply (the emulated HMP4040)
//! and whose camera is a lab's own backend (a test camera registered with
//! `Backends::with_camera`, the extension point a camera crate uses) builds, prepares and
//! captures without constructing any part of the simulator.
//!
//! Its own test binary on purpose: `gonio_simulator::constructions()` is process-wide, and
//! a parallel test that builds a simulated rig would move it.

use async_trait::async_trait;
use gonio_acquire::rig::{Backends, Rig, RigBuildError};
use gonio_devices::rig::RigSpec;
use gonio_devices::target::MarkerBorder;
use gonio_devices::{Camera, CameraConfig, DeviceError, Frame, FrameMeta};
use gonio_simulator::emulate::{spawn_pty, EmulatorConfig, Protocol};
use gonio_simulator::{SampleSpec, SimOptions};
use std::path::Path;
use std::sync::{Arc, Mutex};

/// A camera that is not the simulator: grey frames of the configured size.
struct LabCamera {
    config: Mutex<CameraConfig>,
}

#[async_trait]
impl Camera for LabCamera {
    fn name(&self) -> &str {
        "labcam"
    }
    async fn configure(&self, config: &CameraConfig) -> Result<CameraConfig, DeviceError> {
        *self.config.lock().unwrap() = config.clone();
        Ok(config.clone())
    }
    async fn capture(&self) -> Result<Frame, DeviceError> {
        let c = self.config.lock().unwrap().clone();
        Ok(Frame {
            width: c.width,
            height: c.height,
            data: vec![100; c.width * c.height * 3],
            meta: FrameMeta {
                timestamp: 0.0,
                exposure: c.exposure,
                gain: c.gain,
                sequence: 0,
                bit_depth: c.bit_depth,
            },
        })
    }
    async fn identity(&self) -> Result<String, DeviceError> {
        Ok("LabCam 1.0 (test)".into())
    }
}

fn lab_camera(spec: &RigSpec) -> Result<Arc<dyn Camera>, RigBuildError> {
    let c = &spec.camera;
    Ok(Arc::new(LabCamera {
        config: Mutex::new(CameraConfig {
            width: c.width,
            height: c.height,
            exposure: c.exposure_s,
            gain: c.gain,
            bit_depth: c.bit_depth,
        }),
    }))
}

/// The shipped emulated-Zaber rig with `labcam` as camera and the lamp on `lamp_port`.
fn real_rig(zaber_port: &Path, lamp_port: &Path) -> RigSpec {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut text = std::fs::read_to_string(root.join("devices/rigs/emulated-zaber.toml")).unwrap();
    for (from, to) in [
        ("${GONIO_ZABER_PORT}".to_string(), zaber_port.display().to_string()),
        ("[camera]\nbackend = \"sim\"".into(), "[camera]\nbackend = \"labcam\"".into()),
        (
            "[light]\nbackend = \"sim\"".into(),
            format!(
                "[light]\nbackend = \"hmp\"\noptions = {{ port = \"{}\", voltage = 12.0, current = 10.0, settle_s = 0.0 }}",
                lamp_port.display()
            ),
        ),
    ] {
        assert!(text.contains(&from), "emulated-zaber.toml lacks `{from}`");
        text = text.replace(&from, &to);
    }
    RigSpec::parse(&text, "real-rig.toml").unwrap()
}

#[test]
fn a_rig_with_only_real_devices_constructs_no_simulator() {
    let mut cfg = EmulatorConfig::new(Protocol::Zaber, 4);
    cfg.range_deg = (-200.0, 200.0);
    let stage = spawn_pty(cfg).unwrap();
    let lamp = spawn_pty(EmulatorConfig::new(Protocol::Hmp4040, 4)).unwrap();
    let spec = real_rig(stage.path(), lamp.path());
    let sample = SampleSpec::resolve("leather").unwrap();
    let backends = Backends::builtin().with_camera("labcam", lab_camera);

    let before = gonio_simulator::constructions();
    let rig = Rig::build_with(&spec, &sample, &SimOptions::default(), &backends).unwrap();
    assert!(
        rig.truth.is_none() && rig.clock.is_none(),
        "a real rig has no simulated truth or clock"
    );
    // The holder comes from the rig file (sample_size_mm = 50, default border), not from
    // the sample file.
    assert_eq!((rig.border.clone(), rig.sample_mm), (MarkerBorder::default(), 50.0));
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let config = rig.prepare().await.unwrap();
        let q = rig.kinematics.home();
        let mut q2 = q.clone();
        q2[0] += 10f64.to_radians();
        rig.reach(&q2).await.unwrap();
        let frame = rig.capture(&rig.capture_policy().unwrap(), &config).await.unwrap().0;
        assert_eq!((frame.width, frame.height), (spec.camera.width, spec.camera.height));
        assert_eq!(rig.camera.identity().await.unwrap(), "LabCam 1.0 (test)");
        rig.light.set(false, 0.0).await.unwrap();
    });
    assert_eq!(
        gonio_simulator::constructions(),
        before,
        "building and running a real rig constructed part of the simulator"
    );

    // The counter does count: a simulated rig moves it, and so does a mixed rig (serial
    // axes, simulated camera), which still needs its shadow world.
    Rig::build(&RigSpec::default_rig(), &sample, &SimOptions::default()).unwrap();
    let after_sim = gonio_simulator::constructions();
    assert!(after_sim > before, "a simulated rig was not counted");
    let mut mixed = spec.clone();
    mixed.camera.backend = "sim".into();
    mixed.light.backend = "sim".into();
    drop(rig); // the mixed rig opens the same port
    Rig::build(&mixed, &sample, &SimOptions::default()).unwrap();
    assert!(
        gonio_simulator::constructions() > after_sim,
        "a mixed rig was not counted"
    );
    stage.stop();
    lamp.stop();
}
