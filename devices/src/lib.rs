//! Hardware side of gonio: the traits every device implements, the rig description
//! (TOML), rig kinematics and the motion model used to plan and simulate moves.
//!
//! The acquisition engine in the `gonio` crate knows only the traits in [`axis`],
//! [`camera`] and [`light`]; simulated devices (crate `gonio-simulator`) and real
//! backends implement them. Nothing in this crate renders, stores or plans.

pub mod axis;
pub mod camera;
pub mod coded_board;
pub mod error;
/// GenICam cameras through Aravis: the camera itself behind the `genicam` feature; pixel
/// formats, demosaicing and the rig-file options in every build.
pub mod genicam;
pub mod geometry;
/// DSLRs through libgphoto2: the camera itself behind the `gphoto2` feature; shutter-speed
/// parsing, choice matching, error mapping and the rig-file options in every build.
pub mod gphoto2;
pub mod hdr;
pub mod image;
pub mod kinematics;
pub mod light;
pub mod motion;
pub mod rig;
/// Serial motor controllers (Zaber ASCII, Newport ESP300) and the lamp supply (R&S HMP);
/// cargo feature `serial`.
#[cfg(feature = "serial")]
pub mod serial;
pub mod target;
#[cfg(feature = "v4l2")]
pub mod v4l2;

pub use axis::{Axis, AxisStatus, SoftLimits};
pub use camera::{Camera, CameraConfig, Frame, FrameMeta, Intrinsics};
pub use error::DeviceError;
pub use geometry::{Direction, Vec3};
pub use light::{LampReading, Light};
pub use motion::{MotionModel, Trajectory};
