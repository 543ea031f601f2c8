//! Exports of a native dataset to the field's interchange formats: Bonn's UBO2003 archive
//! (`ubo2003.rs`), a NumPy reference array (`npy.rs`) and, with the cargo feature `zarr`,
//! a Zarr v3 store (`zarr.rs`). All export the same entries
//! ([`entries`]): every measured record in canonical order, plus, for an isotropic
//! acquisition, every equivalent pair rebuilt from its representative (`iso.rs`).
//! Shared types live in the ground file `entry.rs`.

mod entry;
mod iso;
mod npy;
mod ubo2003;
#[cfg(feature = "zarr")]
pub mod zarr;

pub use entry::{
    entry_name, integer_angles, linear_to_srgb8, plan_export, to_srgb8, ExportEntry, ExportReport, IsoTransform,
};
pub use npy::{export_npy, npy_header, npy_header_typed, npy_sidecar_path};
pub use ubo2003::{encode_jpeg, export_ubo2003, JPEG_QUALITY};

use crate::store::error::StoreError;
use crate::store::manifest::MeasurementRecord;
use std::path::Path;

/// The entries an export writes and the number of pairs it cannot export: the measured
/// records ([`plan_export`]) and, for isotropic acquisitions, the reconstructed pairs
/// (a no-op for other datasets).
pub fn entries(dir: &Path, records: &[MeasurementRecord], out: &Path) -> Result<(Vec<ExportEntry>, usize), StoreError> {
    let (mut entries, skipped) = plan_export(dir, records, out)?;
    let missing = iso::extend(dir, records, &mut entries, out)?;
    Ok((entries, skipped + missing))
}
