//! The harness every fuzz campaign shares (`fuzz_*.rs` say `use crate::fuzzing;`): the case
//! budget and running one case on a helper thread with a time limit, so that a panic and a
//! hang are both reported as failures of that case instead of killing or stalling the run.
//! Each target uses a part of it, hence the `allow`.

#![allow(dead_code)]

use std::sync::mpsc;
use std::time::Duration;

/// Cases per fuzz target: `GONIO_FUZZ_CASES`, else the target's CI default.
pub fn cases(default: u32) -> u32 {
    std::env::var("GONIO_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Run `f` on a helper thread for at most `limit` and return what it returned; Err
/// describes a panic or a hang.
pub fn guarded<T: Send + 'static, F: FnOnce() -> T + Send + 'static>(limit: Duration, f: F) -> Result<T, String> {
    let (tx, rx) = mpsc::channel();
    let h = std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    match rx.recv_timeout(limit) {
        Ok(v) => {
            let _ = h.join();
            Ok(v)
        }
        Err(mpsc::RecvTimeoutError::Disconnected) => Err(match h.join() {
            Err(p) => format!(
                "panicked: {}",
                p.downcast_ref::<String>()
                    .cloned()
                    .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_default()
            ),
            Ok(()) => "thread ended without reporting".into(),
        }),
        Err(mpsc::RecvTimeoutError::Timeout) => Err(format!("no answer within {limit:?} (hang)")),
    }
}

/// The committed corpus of one fuzz target: every file of `tests/campaigns/corpus/<sub>/`,
/// sorted by name. Seeds the mutators together with the shipped files of that kind; a
/// failing input found by a long run is added here (see [`keep_failure`]) so that every
/// later run, and CI's short one, starts from it.
pub fn corpus(sub: &str) -> Vec<Vec<u8>> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/campaigns/corpus")
        .join(sub);
    let mut files: Vec<std::path::PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("corpus {}: {e}", dir.display()))
        .map(|e| e.expect("corpus entry").path())
        .filter(|p| p.is_file())
        .collect();
    files.sort();
    files
        .iter()
        .map(|f| std::fs::read(f).unwrap_or_else(|e| panic!("corpus {}: {e}", f.display())))
        .collect()
}

/// Write a failing input to `target/tmp/fuzz-failures/<target>/<hash>` and return that
/// path, so that a failure is never only a panic message: the file can be replayed and
/// committed to the target's corpus as a regression seed.
pub fn keep_failure(target: &str, input: &[u8]) -> std::path::PathBuf {
    use std::hash::{Hash, Hasher};
    let mut h = std::collections::hash_map::DefaultHasher::new();
    input.hash(&mut h);
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join("fuzz-failures")
        .join(target);
    let path = dir.join(format!("{:016x}", h.finish()));
    let _ = std::fs::create_dir_all(&dir).and_then(|_| std::fs::write(&path, input));
    path
}

/// Unwrap a proptest run; on a failure keep the (shrunk) failing input with
/// [`keep_failure`] and panic naming the file.
pub fn check<T: std::fmt::Debug>(
    target: &str,
    result: Result<(), proptest::test_runner::TestError<T>>,
    to_bytes: impl Fn(&T) -> Vec<u8>,
) {
    match result {
        Ok(()) => {}
        Err(proptest::test_runner::TestError::Fail(why, value)) => {
            let path = keep_failure(target, &to_bytes(&value));
            panic!(
                "fuzz {target}: {why}\nfailing input kept in {} (copy it into tests/campaigns/corpus/ \
                 as a regression seed once fixed)",
                path.display()
            );
        }
        Err(e) => panic!("fuzz {target}: {e}"),
    }
}
