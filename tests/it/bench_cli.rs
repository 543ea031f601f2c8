//! `gonio bench …` runs the benchmarks' own binary, `gonio-bench`, from beside `gonio`:
//! the benchmark list, clap's refusals and exit codes come through as they are, gonio's
//! `-v`/`-q` reach it, and a `gonio` without its `gonio-bench` says where it looked and how
//! to build it.

use std::process::{Command, Output};

fn gonio(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_gonio")).args(args).output().unwrap()
}

#[test]
fn bench_help_lists_the_benchmarks() {
    // `gonio help bench` is the benchmarks' list too, not the forwarding subcommand's help.
    for help in [
        &["bench", "--help"][..],
        &["bench", "-h"],
        &["bench"],
        &["help", "bench"],
    ] {
        let o = gonio(help);
        // `gonio bench` alone prints the same list on stderr and exits 2, as clap does.
        let text = String::from_utf8_lossy(if help.len() == 1 { &o.stderr } else { &o.stdout }).into_owned();
        assert_eq!(
            o.status.code(),
            Some(if help.len() == 1 { 2 } else { 0 }),
            "{help:?}: {text}"
        );
        assert!(
            text.contains("Usage: gonio bench [OPTIONS] <COMMAND>"),
            "{help:?}: {text}"
        );
        for b in ["sim", "plan", "render", "serial", "acquire", "hdr", "fly"] {
            assert!(text.contains(&format!("\n  {b} ")), "{help:?}: {b} missing in\n{text}");
        }
    }
    for help in [&["bench", "fit", "--help"][..], &["help", "bench", "fit"]] {
        let o = gonio(help);
        let text = String::from_utf8_lossy(&o.stdout);
        assert!(
            o.status.success() && text.contains("Usage: gonio bench fit [OPTIONS]"),
            "{help:?}: {text}"
        );
    }
}

#[test]
fn refusals_and_exit_codes_come_through() {
    let o = gonio(&["bench", "plan", "--no-such-flag"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("'--no-such-flag'") && err.contains("gonio bench plan"),
        "{err}"
    );
    // A benchmark's own error: exit 1 and its message, as every gonio command.
    let o = gonio(&["-q", "bench", "plan", "--budgets=-1"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("error: --budgets: -1 is not in 0 ..= 600 s"), "{err}");
}

#[test]
fn a_gonio_without_gonio_bench_says_how_to_build_it() {
    let dir = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
    let alone = dir.path().join(format!("gonio{}", std::env::consts::EXE_SUFFIX));
    // A hard link (same file system) or a copy: a symbolic link would resolve to the
    // directory that has gonio-bench.
    if std::fs::hard_link(env!("CARGO_BIN_EXE_gonio"), &alone).is_err() {
        std::fs::copy(env!("CARGO_BIN_EXE_gonio"), &alone).unwrap();
    }
    let o = Command::new(&alone).args(["bench", "sim"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    let missing = dir.path().join(format!("gonio-bench{}", std::env::consts::EXE_SUFFIX));
    assert!(err.contains(&format!("{}", missing.display())), "{err}");
    assert!(err.contains("cargo build -p gonio --bin gonio-bench"), "{err}");
}
