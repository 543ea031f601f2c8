//! The `gonio` command line. Each subcommand lives in `src/cli/`; the benchmarks are the
//! `gonio-bench` binary (`src/bench/`), which `gonio bench` runs.

use clap::Parser;

fn main() -> std::process::ExitCode {
    gonio::cli::prepare_process();
    if let Some(code) = gonio::cli::bench::forward_help(&std::env::args_os().collect::<Vec<_>>()) {
        return code;
    }
    let cli = gonio::cli::Cli::parse();
    gonio::cli::init_logging(cli.verbose, cli.quiet);
    match gonio::cli::run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::from(1)
        }
    }
}
