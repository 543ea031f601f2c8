//! The harness every fuzz campaign shares (`tests/fuzz_*.rs` say `mod fuzzing;`): the case
//! budget and running one case on a helper thread with a time limit, so that a panic and a
//! hang are both reported as failures of that case instead of killing or stalling the run.

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
