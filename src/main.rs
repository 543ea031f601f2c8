//! The `gonio` command line. Each subcommand lives in `src/cli/`.

use clap::Parser;

fn main() -> std::process::ExitCode {
    // Rust ignores SIGPIPE, so `println!` into a closed pipe (`gonio … --json | head`)
    // panics. Restore the default action: like every Unix filter, gonio then ends quietly
    // when its reader goes away. Nothing is lost by it: datasets are durable against any
    // kill (every stored measurement is fsynced before it is journalled), and progress
    // and logs go to stderr, so only a command's final report can meet a closed pipe.
    // SAFETY: called first thing in main, before any other thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
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
