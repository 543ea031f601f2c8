//! V4L2 controls: query, set, read back. Manual exposure and gain for radiometry.
//!
//! Only the classic single-value ioctls (`VIDIOC_QUERYCTRL`, `VIDIOC_G_CTRL`,
//! `VIDIOC_S_CTRL`) are used: exposure and gain are 32-bit integer (or menu/boolean)
//! controls on every driver, and these ioctls also handle button controls. Drivers clamp
//! and round what they are given, so every set is followed by a read back and the read
//! back value is what gets reported.

use std::io;
use std::os::raw::c_void;

use v4l::v4l2;
use v4l::v4l_sys::{v4l2_control, v4l2_queryctrl};

/// Standard control ids (videodev2.h / v4l2-controls.h).
pub mod cid {
    pub const BRIGHTNESS: u32 = 0x0098_0900;
    pub const AUTOGAIN: u32 = 0x0098_0912;
    pub const GAIN: u32 = 0x0098_0913;
    /// User-class exposure in driver-specific units (not convertible to seconds).
    pub const EXPOSURE: u32 = 0x0098_0911;
    /// Camera-class auto exposure menu: 1 = manual.
    pub const EXPOSURE_AUTO: u32 = 0x009a_0901;
    /// Camera-class exposure time in units of 100 µs.
    pub const EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
}

/// `V4L2_EXPOSURE_MANUAL`.
pub const EXPOSURE_MANUAL: i32 = 1;
/// Unit of `V4L2_CID_EXPOSURE_ABSOLUTE`, seconds.
pub const EXPOSURE_ABSOLUTE_UNIT_S: f64 = 100e-6;

const CTRL_FLAG_DISABLED: u32 = 0x0001;
const CTRL_FLAG_READ_ONLY: u32 = 0x0004;
const CTRL_FLAG_INACTIVE: u32 = 0x0010;

/// What a driver says about one control.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ControlInfo {
    pub id: u32,
    pub name: String,
    pub minimum: i32,
    pub maximum: i32,
    pub step: i32,
    pub default: i32,
    pub flags: u32,
}

impl ControlInfo {
    pub fn writable(&self) -> bool {
        self.flags & (CTRL_FLAG_DISABLED | CTRL_FLAG_READ_ONLY) == 0
    }

    pub fn inactive(&self) -> bool {
        self.flags & CTRL_FLAG_INACTIVE != 0
    }

    /// The value the driver would accept closest to `v`: clamped to the range and rounded
    /// to the step, as the V4L2 control framework does.
    pub fn nearest(&self, v: f64) -> i32 {
        let step = self.step.max(1) as f64;
        let min = self.minimum as f64;
        let k = ((v - min) / step).round();
        (min + k * step).clamp(self.minimum as f64, self.maximum as f64) as i32
    }
}

/// A failed control ioctl.
#[derive(Debug)]
pub struct ControlError {
    pub command: String,
    pub source: io::Error,
}

/// Query a control; `Ok(None)` when the driver does not have it (EINVAL) or it is disabled.
pub fn query(fd: i32, id: u32) -> Result<Option<ControlInfo>, ControlError> {
    // SAFETY: all-zero is valid for this C struct.
    let mut q: v4l2_queryctrl = unsafe { std::mem::zeroed() };
    q.id = id;
    // SAFETY: pointer to a live struct of the type this ioctl expects.
    match unsafe { v4l2::ioctl(fd, v4l2::vidioc::VIDIOC_QUERYCTRL, &mut q as *mut _ as *mut c_void) } {
        Ok(()) => {}
        Err(e) if e.raw_os_error() == Some(libc::EINVAL) => return Ok(None),
        Err(e) => {
            return Err(ControlError {
                command: format!("VIDIOC_QUERYCTRL {id:#010x}"),
                source: e,
            })
        }
    }
    if q.flags & CTRL_FLAG_DISABLED != 0 {
        return Ok(None);
    }
    // `name` is `[u8; 32]` in these bindings but `c_char` (signed on some targets) in others.
    #[allow(clippy::unnecessary_cast)]
    let name_bytes: Vec<u8> = q.name.iter().take_while(|&&c| c != 0).map(|&c| c as u8).collect();
    Ok(Some(ControlInfo {
        id: q.id,
        name: String::from_utf8_lossy(&name_bytes).into_owned(),
        minimum: q.minimum,
        maximum: q.maximum,
        step: q.step,
        default: q.default_value,
        flags: q.flags,
    }))
}

/// Read a control's current value.
pub fn get(fd: i32, id: u32) -> Result<i32, ControlError> {
    let mut c = v4l2_control { id, value: 0 };
    // SAFETY: as above.
    unsafe { v4l2::ioctl(fd, v4l2::vidioc::VIDIOC_G_CTRL, &mut c as *mut _ as *mut c_void) }.map_err(|e| {
        ControlError {
            command: format!("VIDIOC_G_CTRL {id:#010x}"),
            source: e,
        }
    })?;
    Ok(c.value)
}

/// Set a control (for a button control the value is ignored by the driver).
pub fn set(fd: i32, id: u32, value: i32) -> Result<(), ControlError> {
    let mut c = v4l2_control { id, value };
    // SAFETY: as above.
    unsafe { v4l2::ioctl(fd, v4l2::vidioc::VIDIOC_S_CTRL, &mut c as *mut _ as *mut c_void) }.map_err(|e| ControlError {
        command: format!("VIDIOC_S_CTRL {id:#010x}={value}"),
        source: e,
    })
}

/// Set and read back: what the driver actually applied.
pub fn set_and_read(fd: i32, id: u32, value: i32) -> Result<i32, ControlError> {
    set(fd, id, value)?;
    get(fd, id)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_clamps_and_rounds_to_step() {
        let c = ControlInfo {
            id: cid::GAIN,
            name: "Gain".into(),
            minimum: 2,
            maximum: 250,
            step: 4,
            default: 100,
            flags: 0,
        };
        assert_eq!(c.nearest(99.0), 98); // 2 + 24*4 = 98 is the nearest step
        assert_eq!(c.nearest(101.0), 102);
        assert_eq!(c.nearest(-5.0), 2);
        assert_eq!(c.nearest(1e9), 250);
    }
}
