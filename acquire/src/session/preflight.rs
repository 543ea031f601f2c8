//! Before the first frame of a long run: will the dataset fit on the disk, and when will
//! the run end? Both from the plan, so a run that cannot finish fails in the first second,
//! not in its seventh hour.

use crate::plan::Plan;
use serde::Serialize;
use std::collections::HashSet;
use std::path::Path;

/// What the rest of a run will take. A stable struct (the CLI prints it, `--json` too).
#[derive(Clone, Debug, Serialize)]
pub struct Preflight {
    /// Measurements still to take.
    pub remaining: usize,
    /// An upper bound on the bytes they add to the dataset (see [`bytes_per_measurement`]).
    pub planned_bytes: u64,
    /// Free bytes for an unprivileged writer on the dataset's file system (`None`: the
    /// system would not say).
    pub free_bytes: Option<u64>,
    /// Planned rig time of the remaining measurements (the plan's motion model), s.
    pub planned_s: f64,
    /// Planned end on the wall clock, seconds since the Unix epoch (now + `planned_s`).
    pub planned_end_unix_s: u64,
}

impl Preflight {
    /// Whether the planned bytes fit in the free space (true when the free space is unknown).
    pub fn fits(&self) -> bool {
        self.free_bytes.is_none_or(|f| self.planned_bytes <= f)
    }

    /// The planned end as `YYYY-MM-DD HH:MM UTC`.
    pub fn planned_end_utc(&self) -> String {
        utc(self.planned_end_unix_s)
    }
}

/// An upper bound on one measurement's bytes: the rectified image as uncompressed RGB
/// float32 (`width × height × 12`), the same again for a stored truth image, the camera's
/// raw frames with `raw` (`camera pixels × 3 × 4` per exposure of the bracket), and 4 KiB
/// for its journal line and file-system slack. An upper bound on purpose: a run that
/// passes this check does not fill the disk.
pub fn bytes_per_measurement(
    width: usize,
    height: usize,
    store_truth: bool,
    raw: Option<(usize, usize, usize)>,
) -> u64 {
    let rect = (width * height * 12) as u64;
    let truth = if store_truth { rect } else { 0 };
    let raw = raw.map_or(0, |(w, h, exposures)| (w * h * 12 * exposures.max(1)) as u64);
    rect + truth + raw + 4096
}

/// The run's preflight: `per_measurement` from [`bytes_per_measurement`], `done` the
/// measurements already stored, `dir` the dataset directory.
pub fn preflight(plan: &Plan, done: &HashSet<usize>, per_measurement: u64, dir: &Path) -> Preflight {
    let total = plan.steps.len();
    let remaining = plan.steps.iter().filter(|s| !done.contains(&s.index)).count();
    let planned_s = if total == 0 {
        0.0
    } else {
        plan.durations.optimized_s * remaining as f64 / total as f64
    };
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    Preflight {
        remaining,
        planned_bytes: per_measurement * remaining as u64,
        free_bytes: free_bytes(dir),
        planned_s,
        planned_end_unix_s: now + planned_s.max(0.0).round() as u64,
    }
}

/// Free bytes for an unprivileged writer (`statvfs`: `f_bavail × f_frsize`).
pub fn free_bytes(dir: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: `c` is a valid NUL-terminated path and `st` a writable statvfs.
    if unsafe { libc::statvfs(c.as_ptr(), &mut st) } != 0 {
        return None;
    }
    Some((st.f_bavail as u64).saturating_mul(st.f_frsize as u64))
}

/// Seconds since the epoch as `YYYY-MM-DD HH:MM UTC` (civil-from-days, no time zone data).
fn utc(t: u64) -> String {
    let days = (t / 86_400) as i64;
    let (h, m) = ((t % 86_400) / 3600, (t % 3600) / 60);
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let mo = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(mo <= 2);
    format!("{y:04}-{mo:02}-{d:02} {h:02}:{m:02} UTC")
}

/// A byte count for people (`1.5 GiB`).
pub fn human_bytes(b: u64) -> String {
    let mut x = b as f64;
    for unit in ["B", "KiB", "MiB", "GiB", "TiB"] {
        if x < 1024.0 || unit == "TiB" {
            return format!("{x:.1} {unit}");
        }
        x /= 1024.0;
    }
    unreachable!()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utc_dates_are_civil() {
        assert_eq!(utc(0), "1970-01-01 00:00 UTC");
        assert_eq!(utc(951_782_400 + 3_600 + 120), "2000-02-29 01:02 UTC");
    }

    #[test]
    fn the_estimate_counts_every_stored_image() {
        assert_eq!(bytes_per_measurement(10, 10, false, None), 1200 + 4096);
        assert_eq!(
            bytes_per_measurement(10, 10, true, Some((20, 10, 3))),
            2400 + 7200 + 4096
        );
        assert!(free_bytes(Path::new("/")).is_some());
        assert!(free_bytes(Path::new("/no/such/dir")).is_none());
    }
}
