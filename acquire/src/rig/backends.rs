//! The backend tables: one per device family (camera, light, axis), each row a backend
//! name as rig files write it, the cargo feature it needs, and its constructor.
//!
//! Why tables: a new backend is one folder in `gonio-devices` plus one row here, and the
//! rig builder never string-matches a backend name. A row stays in the table when its
//! feature is off ([`Make::NotBuilt`]), so a rig file that names it gets "rebuild with
//! `--features X`" instead of "unknown backend". A library user (a lab's own camera crate)
//! adds rows to [`Backends::builtin`] and builds with [`super::Rig::build_with`].
//!
//! `sim` rows are [`Make::Simulated`]: the simulated devices come out of one simulated
//! world (`gonio_simulator::build_sim_rig`), which the builder constructs only when some
//! part of the rig is simulated (see `build.rs`).

use gonio_devices::camera::FoundCamera;
use gonio_devices::rig::{AxisSpec, RigSpec};
use gonio_devices::{Axis, Camera, DeviceError, Light};
use std::sync::Arc;

#[derive(Debug, thiserror::Error)]
pub enum RigBuildError {
    #[error("rig {rig}: {part} uses backend `{backend}`, which this build does not provide (available: {available})")]
    UnknownBackend {
        rig: String,
        part: String,
        backend: String,
        available: String,
    },
    /// The backend exists but its cargo feature was off when this binary was built.
    #[error(
        "rig {rig}: {part} backend `{backend}` is not in this build: rebuild with `--features {feature}` \
         (e.g. `cargo build --release -p gonio --features {feature}`)"
    )]
    NotBuilt {
        rig: String,
        part: String,
        backend: String,
        feature: String,
    },
    /// (`error` is not a `source`: its text is already in the message, and anyhow's chain
    /// would print it twice.)
    #[error("rig {rig}: {error}")]
    Serial {
        rig: String,
        error: gonio_devices::serial::SerialConfigError,
    },
    /// A real camera that could not be configured or opened (its error names the device).
    #[error("rig {rig}: {source}")]
    Camera { rig: String, source: DeviceError },
    /// A rig-file option that is present but wrong (its key names it).
    #[error("rig {rig}: {error}")]
    Option {
        rig: String,
        error: gonio_devices::rig::OptionError,
    },
    #[error(transparent)]
    Sim(#[from] gonio_simulator::devices::SimRigError),
    #[error(transparent)]
    Sample(#[from] gonio_simulator::sample::SampleError),
}

/// Opens a camera from the rig file (`spec.camera`).
pub type CameraCtor = fn(&RigSpec) -> Result<Arc<dyn Camera>, RigBuildError>;
/// Opens a light from the rig file (`spec.light`).
pub type LightCtor = fn(&RigSpec) -> Result<Arc<dyn Light>, RigBuildError>;
/// Opens one axis; `ports` is shared by every axis of the rig (a daisy chain is one port).
pub type AxisCtor = fn(&RigSpec, &AxisSpec, &mut Ports) -> Result<Arc<dyn Axis>, RigBuildError>;

/// What stands behind a row.
#[derive(Clone, Copy)]
pub enum Make<C> {
    /// Part of the simulated world (the builder builds the world and takes it from there).
    Simulated,
    /// A real device, opened by this constructor.
    Real(C),
    /// Known, but its cargo feature was off in this build.
    NotBuilt,
}

/// One backend of a family.
#[derive(Clone, Copy)]
pub struct Row<C> {
    /// The name rig files give as `backend`.
    pub name: &'static str,
    /// The cargo feature of the `gonio` crate that builds it (`None`: always built).
    pub feature: Option<&'static str>,
    pub make: Make<C>,
}

/// The ports the axes of one rig share.
#[derive(Default)]
pub struct Ports {
    pub serial: gonio_devices::serial::PortRegistry,
}

/// The three tables a rig is built from.
#[derive(Clone)]
pub struct Backends {
    pub cameras: Vec<Row<CameraCtor>>,
    pub lights: Vec<Row<LightCtor>>,
    pub axes: Vec<Row<AxisCtor>>,
}

impl Backends {
    /// The backends of this build: every known backend, compiled-out ones as
    /// [`Make::NotBuilt`].
    pub fn builtin() -> Backends {
        Backends {
            cameras: vec![
                Row {
                    name: "sim",
                    feature: None,
                    make: Make::Simulated,
                },
                Row {
                    name: "v4l2",
                    feature: Some("v4l2"),
                    #[cfg(feature = "v4l2")]
                    make: Make::Real(v4l2_camera),
                    #[cfg(not(feature = "v4l2"))]
                    make: Make::NotBuilt,
                },
                Row {
                    name: "genicam",
                    feature: Some("genicam"),
                    #[cfg(feature = "genicam")]
                    make: Make::Real(genicam_camera),
                    #[cfg(not(feature = "genicam"))]
                    make: Make::NotBuilt,
                },
                Row {
                    name: "gphoto2",
                    feature: Some("gphoto2"),
                    #[cfg(feature = "gphoto2")]
                    make: Make::Real(gphoto2_camera),
                    #[cfg(not(feature = "gphoto2"))]
                    make: Make::NotBuilt,
                },
            ],
            lights: vec![
                Row {
                    name: "sim",
                    feature: None,
                    make: Make::Simulated,
                },
                Row {
                    name: "hmp",
                    feature: None,
                    make: Make::Real(hmp_light),
                },
            ],
            axes: vec![
                Row {
                    name: "sim",
                    feature: None,
                    make: Make::Simulated,
                },
                Row {
                    name: "zaber",
                    feature: None,
                    make: Make::Real(serial_axis),
                },
                Row {
                    name: "esp300",
                    feature: None,
                    make: Make::Real(serial_axis),
                },
            ],
        }
    }

    /// Add (or replace) a camera backend: a lab's own camera, or a test's.
    pub fn with_camera(mut self, name: &'static str, make: CameraCtor) -> Backends {
        upsert(&mut self.cameras, name, make);
        self
    }

    /// Add (or replace) a light backend.
    pub fn with_light(mut self, name: &'static str, make: LightCtor) -> Backends {
        upsert(&mut self.lights, name, make);
        self
    }

    /// Add (or replace) an axis backend.
    pub fn with_axis(mut self, name: &'static str, make: AxisCtor) -> Backends {
        upsert(&mut self.axes, name, make);
        self
    }

    pub fn camera(&self, spec: &RigSpec) -> Result<Make<CameraCtor>, RigBuildError> {
        find(&self.cameras, spec, "camera", &spec.camera.backend)
    }

    pub fn light(&self, spec: &RigSpec) -> Result<Make<LightCtor>, RigBuildError> {
        find(&self.lights, spec, "light", &spec.light.backend)
    }

    pub fn axis(&self, spec: &RigSpec, axis: &AxisSpec) -> Result<Make<AxisCtor>, RigBuildError> {
        find(&self.axes, spec, &format!("axis {}", axis.name), &axis.backend)
    }
}

/// Looks for the cameras of one backend on this machine (`gonio devices list`).
pub type CameraLister = fn() -> Result<Vec<FoundCamera>, DeviceError>;

/// The camera backends that can look for their cameras, a table like the others: a row
/// whose feature is off is [`Make::NotBuilt`], so `gonio devices list` says which feature
/// lists them. (V4L2 cameras are listed as video device nodes.)
pub fn camera_listers() -> Vec<Row<CameraLister>> {
    vec![
        Row {
            name: "genicam",
            feature: Some("genicam"),
            #[cfg(feature = "genicam")]
            make: Make::Real(list_genicam),
            #[cfg(not(feature = "genicam"))]
            make: Make::NotBuilt,
        },
        Row {
            name: "gphoto2",
            feature: Some("gphoto2"),
            #[cfg(feature = "gphoto2")]
            make: Make::Real(list_gphoto2),
            #[cfg(not(feature = "gphoto2"))]
            make: Make::NotBuilt,
        },
    ]
}

/// GenICam cameras: Aravis' device enumeration (GigE Vision discovery, USB3 Vision).
#[cfg(feature = "genicam")]
fn list_genicam() -> Result<Vec<FoundCamera>, DeviceError> {
    Ok(gonio_devices::genicam::camera::list_cameras())
}

/// Still cameras: libgphoto2's auto-detection (what `gphoto2 --auto-detect` prints).
#[cfg(feature = "gphoto2")]
fn list_gphoto2() -> Result<Vec<FoundCamera>, DeviceError> {
    gonio_devices::gphoto2::camera::list_cameras(std::time::Duration::from_secs(20))
}

fn upsert<C>(rows: &mut Vec<Row<C>>, name: &'static str, make: C) {
    let row = Row {
        name,
        feature: None,
        make: Make::Real(make),
    };
    match rows.iter_mut().find(|r| r.name == name) {
        Some(r) => *r = row,
        None => rows.push(row),
    }
}

/// The row named `backend`, or the error a person can act on: the feature to enable for a
/// known backend that is compiled out, the available names for an unknown one.
fn find<C: Copy>(rows: &[Row<C>], spec: &RigSpec, part: &str, backend: &str) -> Result<Make<C>, RigBuildError> {
    match rows.iter().find(|r| r.name == backend) {
        Some(Row {
            make: Make::NotBuilt,
            feature,
            ..
        }) => Err(RigBuildError::NotBuilt {
            rig: spec.name.clone(),
            part: part.to_string(),
            backend: backend.to_string(),
            feature: feature.unwrap_or("?").to_string(),
        }),
        Some(r) => Ok(r.make),
        None => Err(RigBuildError::UnknownBackend {
            rig: spec.name.clone(),
            part: part.to_string(),
            backend: backend.to_string(),
            available: available(rows),
        }),
    }
}

/// The names of a table, compiled-out ones with the feature that builds them.
fn available<C>(rows: &[Row<C>]) -> String {
    rows.iter()
        .map(|r| match (&r.make, r.feature) {
            (Make::NotBuilt, Some(f)) => format!("{} (feature `{f}`)", r.name),
            _ => r.name.to_string(),
        })
        .collect::<Vec<_>>()
        .join(", ")
}

// ---- constructors --------------------------------------------------------------------

/// A serial controller axis (`zaber`, `esp300`; options in the axis' `options` table, see
/// `gonio_devices::serial`).
fn serial_axis(spec: &RigSpec, axis: &AxisSpec, ports: &mut Ports) -> Result<Arc<dyn Axis>, RigBuildError> {
    ports.serial.build_axis(axis).map_err(|error| RigBuildError::Serial {
        rig: spec.name.clone(),
        error,
    })
}

/// A lamp on a Rohde & Schwarz HMP supply (options in `[light] options`, see
/// `gonio_devices::serial::hmp`).
fn hmp_light(spec: &RigSpec) -> Result<Arc<dyn Light>, RigBuildError> {
    let serial = |error| RigBuildError::Serial {
        rig: spec.name.clone(),
        error,
    };
    let opts = gonio_devices::serial::Options::for_light(&spec.light.options);
    let config = gonio_devices::serial::hmp::HmpConfig::from_options(&opts).map_err(serial)?;
    let real = gonio_devices::serial::hmp::HmpLight::open(config).map_err(serial)?;
    Ok(Arc::new(real))
}

/// A real camera's `from_rig` error as the rig builder reports it.
#[cfg(any(feature = "genicam", feature = "gphoto2"))]
fn open_error(spec: &RigSpec, e: gonio_devices::camera::FromRigError) -> RigBuildError {
    use gonio_devices::camera::FromRigError;
    match e {
        FromRigError::Option(error) => RigBuildError::Option {
            rig: spec.name.clone(),
            error,
        },
        FromRigError::Device(source) => RigBuildError::Camera {
            rig: spec.name.clone(),
            source,
        },
    }
}

/// A GenICam camera through Aravis (feature `genicam`, devices/src/genicam): opened here
/// so that a missing camera or a wrong option fails the rig build, not step one.
#[cfg(feature = "genicam")]
fn genicam_camera(spec: &RigSpec) -> Result<Arc<dyn Camera>, RigBuildError> {
    use gonio_devices::genicam::camera::GenicamCamera;
    let camera = GenicamCamera::from_rig(&spec.camera).map_err(|e| open_error(spec, e))?;
    Ok(Arc::new(camera))
}

/// A DSLR through libgphoto2 (feature `gphoto2`, devices/src/gphoto2): opened here so
/// that a missing camera or a wrong option fails the rig build, not step one.
#[cfg(feature = "gphoto2")]
fn gphoto2_camera(spec: &RigSpec) -> Result<Arc<dyn Camera>, RigBuildError> {
    use gonio_devices::gphoto2::camera::Gphoto2Camera;
    let camera = Gphoto2Camera::from_rig(&spec.camera).map_err(|e| open_error(spec, e))?;
    Ok(Arc::new(camera))
}

/// A V4L2 camera (feature `v4l2`, devices/src/v4l2): opened and checked here so that a
/// missing or wrong device fails the rig build, not step one.
#[cfg(feature = "v4l2")]
fn v4l2_camera(spec: &RigSpec) -> Result<Arc<dyn Camera>, RigBuildError> {
    use gonio_devices::v4l2::{V4l2Camera, V4l2Options};
    let err = |source| RigBuildError::Camera {
        rig: spec.name.clone(),
        source,
    };
    let opts = V4l2Options::from_rig(&spec.camera).map_err(err)?;
    let camera = V4l2Camera::open(opts).map_err(err)?;
    Ok(Arc::new(camera))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unknown_backend_lists_the_available_ones() {
        let mut spec = RigSpec::default_rig();
        spec.camera.backend = "nikon".into();
        let e = Backends::builtin().camera(&spec).err().unwrap().to_string();
        assert!(e.contains("`nikon`") && e.contains("sim") && e.contains("v4l2"), "{e}");
    }

    #[cfg(not(feature = "v4l2"))]
    #[test]
    fn a_compiled_out_backend_names_its_feature() {
        let mut spec = RigSpec::default_rig();
        spec.camera.backend = "v4l2".into();
        let e = Backends::builtin().camera(&spec).err().unwrap().to_string();
        assert!(e.contains("not in this build") && e.contains("--features v4l2"), "{e}");
    }

    #[cfg(not(feature = "gphoto2"))]
    #[test]
    fn the_gphoto2_backend_names_its_feature_when_compiled_out() {
        let mut spec = RigSpec::default_rig();
        spec.camera.backend = "gphoto2".into();
        let e = Backends::builtin().camera(&spec).err().unwrap().to_string();
        assert!(
            e.contains("not in this build") && e.contains("--features gphoto2"),
            "{e}"
        );
    }

    /// Every real camera backend can list its cameras, and a compiled-out one is a
    /// `NotBuilt` row naming its feature (what `gonio devices list` prints for it).
    #[test]
    fn every_listing_backend_is_a_camera_backend_with_its_feature() {
        let b = Backends::builtin();
        let listers = camera_listers();
        assert_eq!(
            listers.iter().map(|r| r.name).collect::<Vec<_>>(),
            ["genicam", "gphoto2"]
        );
        for l in &listers {
            let camera = b.cameras.iter().find(|r| r.name == l.name).expect("a camera row");
            assert_eq!(l.feature, camera.feature, "{}", l.name);
            assert_eq!(
                matches!(l.make, Make::NotBuilt),
                matches!(camera.make, Make::NotBuilt),
                "{}: listed and built under the same feature",
                l.name
            );
        }
        #[cfg(not(feature = "gphoto2"))]
        assert!(matches!(listers[1].make, Make::NotBuilt));
    }

    #[test]
    fn every_serial_backend_of_the_devices_crate_has_a_row() {
        let b = Backends::builtin();
        for name in gonio_devices::serial::BACKENDS {
            assert!(b.axes.iter().any(|r| r.name == *name), "{name}");
        }
    }
}
