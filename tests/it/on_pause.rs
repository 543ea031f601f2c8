//! `gonio acquire --on-pause CMD` (issue 31): the command runs when the run pauses
//! (`--limit`), finishes or fails, with GONIO_DATASET, GONIO_STATE and GONIO_MESSAGE.

use crate::common;

use std::path::Path;

fn notified(out: &Path, note: &Path, extra: &[&str], rig: &Path, sweep: &Path) -> (Option<i32>, String) {
    let _ = std::fs::remove_file(note);
    let cmd = format!(
        "printf '%s|%s|%s' \"$GONIO_STATE\" \"$GONIO_DATASET\" \"$GONIO_MESSAGE\" > '{}'",
        note.display()
    );
    let o = common::acquire_cmd(rig, sweep, out)
        .args(["--on-pause", &cmd])
        .args(extra)
        .env("GONIO_ZABER_PORT", "/dev/gonio-no-such-port")
        .output()
        .unwrap();
    let text = std::fs::read_to_string(note).unwrap_or_else(|e| {
        panic!(
            "the --on-pause command did not run ({e}): {}",
            String::from_utf8_lossy(&o.stderr)
        )
    });
    (o.status.code(), text)
}

#[test]
fn the_command_hears_paused_finished_and_failed() {
    let dir = common::fresh_tmp("on-pause", "run");
    let (rig, sweep) = common::write_scene(&dir);
    let note = dir.join("note.txt");

    let out = dir.join("ds");
    let (code, text) = notified(&out, &note, &["--limit", "2"], &rig, &sweep);
    assert_eq!(code, Some(3), "a limited run is not complete");
    assert_eq!(text, format!("paused|{}|", out.display()));

    let out2 = dir.join("ds2");
    let (code, text) = notified(&out2, &note, &[], &rig, &sweep);
    assert_eq!(code, Some(0));
    assert_eq!(text, format!("finished|{}|", out2.display()));

    // A rig whose serial port does not exist fails when the run builds it.
    let zaber = Path::new(env!("CARGO_MANIFEST_DIR")).join("devices/rigs/emulated-zaber.toml");
    let out3 = dir.join("ds3");
    let (code, text) = notified(&out3, &note, &[], &zaber, &sweep);
    assert_ne!(code, Some(0));
    assert!(
        text.starts_with(&format!("failed|{}|", out3.display())) && text.contains("/dev/gonio-no-such-port"),
        "{text}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
