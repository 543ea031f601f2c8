//! `gonio bench …`: the benchmarks are their own binary, `gonio-bench` (`src/bench/`,
//! ARCHITECTURE.md, "Crates"). This subcommand runs the `gonio-bench` that sits next to the
//! running `gonio` with the arguments verbatim, so a change in a benchmark recompiles only
//! that binary. What the benchmarks use of the commands' modules is re-exported here
//! (`gonio::cli::bench::…`); the modules themselves stay private to `cli`.

use anyhow::{Context, Result};
use std::ffi::OsString;
use std::path::PathBuf;
use std::process::ExitCode;

pub use super::common::{load_sample, parse_size, RigArgs, SweepArgs, IMAGE_SIDES};
pub use super::sparse::load_prior;
pub use super::svg_plot::{log_log, Series};
#[cfg(feature = "btf")]
pub use super::{
    complete::{coefficients, coefficients_censored, joint_completion, noise_var, predict_image, sensor_pair_noise},
    compress::{compress_report, CompressArgs, Report, TruthReport},
    fit::parse_model,
    prior::{sample_name, spread_texels, sweep_name},
    synthesize::{open_exemplar, SynthArgs},
};

#[derive(clap::Args, Debug)]
pub struct BenchArgs {
    /// The benchmark and its arguments, passed to `gonio-bench` as they are
    /// (`gonio bench --help` lists the benchmarks).
    #[arg(trailing_var_arg = true, allow_hyphen_values = true, value_name = "BENCHMARK")]
    pub args: Vec<OsString>,
}

/// The `gonio-bench` beside the running executable.
fn bench_exe() -> Result<PathBuf> {
    let me = std::env::current_exe().context("finding the running gonio executable")?;
    Ok(me.with_file_name(format!("gonio-bench{}", std::env::consts::EXE_SUFFIX)))
}

/// `gonio help bench [BENCHMARK]`: clap's own `help` would print this forwarding
/// subcommand's help; the benchmarks' help is `gonio-bench`'s (`gonio-bench help
/// [BENCHMARK]`). `Some(exit code)` when `args` (the whole command line) asked for it.
pub fn forward_help(args: &[OsString]) -> Option<ExitCode> {
    if args.get(1).is_none_or(|a| a != "help") || args.get(2).is_none_or(|a| a != "bench") {
        return None;
    }
    let mut forwarded = vec![OsString::from("help")];
    forwarded.extend(args[3..].iter().cloned());
    Some(run(BenchArgs { args: forwarded }, 0, false).unwrap_or_else(|e| {
        eprintln!("error: {e:#}");
        ExitCode::from(1)
    }))
}

/// Runs `gonio-bench` with gonio's `-v`/`-q` and `args`: on Unix it replaces this process
/// (stdin, stdout, stderr, signals and the exit status are the benchmark's own), elsewhere
/// it waits for it and returns its exit code.
pub fn run(a: BenchArgs, verbose: u8, quiet: bool) -> Result<ExitCode> {
    let exe = bench_exe()?;
    if !exe.is_file() {
        anyhow::bail!(
            "the benchmarks are their own binary, {}, which is missing: build it with \
             `cargo build -p gonio --bin gonio-bench` (a plain `cargo build -p gonio` and \
             `cargo install` build it beside gonio)",
            exe.display()
        );
    }
    let mut cmd = std::process::Command::new(&exe);
    cmd.args(std::iter::repeat_n("-v", verbose.into()));
    if quiet {
        cmd.arg("-q");
    }
    cmd.args(&a.args);
    #[cfg(unix)]
    {
        use std::os::unix::process::CommandExt;
        let e = cmd.exec();
        Err(e).with_context(|| format!("running {}", exe.display()))
    }
    #[cfg(not(unix))]
    {
        let status = cmd.status().with_context(|| format!("running {}", exe.display()))?;
        Ok(ExitCode::from(status.code().map_or(1, |c| c.clamp(0, 255) as u8)))
    }
}
