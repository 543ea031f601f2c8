//! The `gonio` command line. Each subcommand lives in `src/cli/`.

use clap::Parser;

fn main() -> std::process::ExitCode {
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
