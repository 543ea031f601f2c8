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

/// Write the reduced rig and sweep into `dir`; returns (rig, sweep) paths.
pub fn write_scene(dir: &Path) -> (PathBuf, PathBuf) {
    let default_rig = Path::new(env!("CARGO_MANIFEST_DIR")).join("devices/rigs/default.toml");
    let text = std::fs::read_to_string(&default_rig).unwrap();
    let mut small = text.clone();
    for (from, to) in [
        ("width = 768", "width = 192"),
        ("height = 640", "height = 160"),
        ("focal_length_px = 4300.0", "focal_length_px = 1075.0"),
    ] {
        assert!(
            small.contains(from),
            "{} no longer contains `{from}`",
            default_rig.display()
        );
        small = small.replacen(from, to, 1);
    }
    let rig = dir.join("rig_small.toml");
    std::fs::write(&rig, small).unwrap();
    let sweep = dir.join("sweep6.toml");
    std::fs::write(
        &sweep,
        "directions = [[0.0, 0.0], [30.0, 0.0], [30.0, 120.0], [45.0, 240.0], [60.0, 60.0], [75.0, 300.0]]\n",
    )
    .unwrap();
    (rig, sweep)
}
