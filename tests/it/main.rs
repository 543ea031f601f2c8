//! gonio's integration tests, one binary (one link instead of one per file; a module per
//! former test file). Run one group with a filter, e.g.
//! `cargo test -p gonio --test it calibration_` or `--test it campaign_kill9::`.

mod common;
mod fuzzing;

mod acquire_e2e;
mod bench_cli;
mod calibration_coded_board;
mod calibration_faults;
mod calibration_intrinsics_wedge;
mod calibration_light_geometry;
mod calibration_mechanical;
mod calibration_mechanical_camera;
mod calibration_radiometric;
mod calibration_radiometric_apply;
mod calibration_rig_geometry;
mod calibration_white;
mod campaign_camera_faults;
mod campaign_faults;
mod campaign_kill9;
mod determinism;
mod devices_check;
mod drift_references;
mod fit;
mod fly;
mod fuzz_import;
mod fuzz_inputs;
mod fuzz_protocols;
mod fuzz_resume;
mod golden;
mod hdr;
mod lamp_hmp;
mod on_pause;
mod same_bytes_anywhere;
mod serial_drivers;
mod shard_merge;
mod sparse;
mod synthesize_cli;
mod view_server;
#[cfg(feature = "zarr")]
mod zarr_export;
