//! Helpers shared by the campaign tests (each `tests/*.rs` that needs them says `mod common;`).

use std::path::{Path, PathBuf};

/// The binary under test, copied once per test process: other builds sharing the target
/// directory may replace `target/debug/gonio` while a campaign runs (that happened here and
/// made a trial compare two different builds).
pub fn bin() -> &'static Path {
    static BIN: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    BIN.get_or_init(|| {
        let dir = bin_dir();
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("gonio");
        // A hard link keeps the old inode when cargo replaces the file; copy across devices.
        if std::fs::hard_link(env!("CARGO_BIN_EXE_gonio"), &p).is_err() {
            std::fs::copy(env!("CARGO_BIN_EXE_gonio"), &p).unwrap();
        }
        extern "C" fn remove_bin_dir() {
            let _ = std::fs::remove_dir_all(bin_dir());
        }
        // SAFETY: registers a plain function without captured state to run at exit.
        unsafe { libc::atexit(remove_bin_dir) };
        p
    })
}

fn bin_dir() -> PathBuf {
    std::env::temp_dir().join(format!("gonio-campaign-bin-{}", std::process::id()))
}
