//! Running the gonio binary from a test: the output, success with its stdout, or a
//! refusal whose stderr names the reason.

use std::path::Path;
use std::process::{Command, Output};

/// The gonio binary with `args`, `RAYON_NUM_THREADS=threads` when given.
pub fn gonio(args: &[&str], threads: Option<&str>) -> Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_gonio"));
    c.args(args);
    if let Some(t) = threads {
        c.env("RAYON_NUM_THREADS", t);
    }
    c.output().unwrap()
}

/// Run gonio and require success; its stdout.
pub fn ok(args: &[&str]) -> String {
    let o = gonio(args, None);
    assert!(
        o.status.success(),
        "gonio {args:?} failed:\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Run gonio and require a refusal whose stderr contains every one of `needles`.
pub fn refused(args: &[&str], needles: &[&str]) {
    let o = gonio(args, None);
    assert!(!o.status.success(), "gonio {args:?} should fail");
    let err = String::from_utf8_lossy(&o.stderr);
    for n in needles {
        assert!(err.contains(n), "gonio {args:?}: {n:?} not in\n{err}");
    }
}

pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}
