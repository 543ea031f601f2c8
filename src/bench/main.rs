//! `gonio-bench`, the benchmarks' own binary: `gonio bench …` runs it with its arguments
//! (`src/cli/bench.rs`), and it runs on its own too. Each benchmark is one module here,
//! reported as ratios against a baseline measured in the same process (absolute times
//! vary with the machine). A benchmark drives the commands' own code through the `gonio`
//! library (`gonio::cli::bench` re-exports what it needs of the CLI), so the figures are
//! the ones a user gets; nothing in the library imports from here (ARCHITECTURE.md,
//! "Crates").

use anyhow::Result;
use clap::Parser;
use std::process::ExitCode;

mod acquire;
#[cfg(feature = "btf")]
mod compress;
#[cfg(feature = "btf")]
mod decode;
#[cfg(feature = "btf")]
mod export;
#[cfg(feature = "btf")]
mod fit;
mod fly;
mod hdr;
mod plan;
mod render;
mod serial;
mod sim;
#[cfg(feature = "btf")]
mod sparse;
#[cfg(feature = "btf")]
mod synthesize;
// The viewer's cache lives in `gonio::view`, which the `monitor` feature builds.
#[cfg(feature = "monitor")]
mod view_cache;

/// The command line of `gonio bench` (named so in its usage lines and errors, as before the
/// benchmarks had their own binary).
#[derive(Parser, Debug)]
#[command(
    name = "gonio-bench",
    bin_name = "gonio bench",
    about = "Benchmarks (ratios against a baseline run in the same process)"
)]
struct Cli {
    /// More log output (-v info, -vv debug); logs go to stderr. RUST_LOG overrides.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    /// Only errors on stderr.
    #[arg(short, long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: BenchCommand,
}

#[derive(clap::Subcommand, Debug)]
enum BenchCommand {
    /// Time the simulator's stages (raw render, ground truth, sensor) per sample kind.
    Sim(sim::SimBenchArgs),
    /// Planner quality against its time budget: optimized duration vs. the lower bound.
    Plan(plan::PlanBenchArgs),
    /// Render error against a high-sample reference versus time, per quality knob.
    Render(render::RenderBenchArgs),
    /// Serial layer cost over a pty: round trips/s and per-measurement overhead vs. sim axes.
    Serial(serial::SerialBenchArgs),
    /// Every compression method over its knob: error vs. encode time and vs. ratio (table + SVG).
    #[cfg(feature = "btf")]
    Compress(compress::CompressBenchArgs),
    /// Every synthesis method against a 4×-area simulator reference: seams, statistics, repetition, time.
    #[cfg(feature = "btf")]
    Synthesize(Box<synthesize::SynthesizeBenchArgs>),
    /// The full simulated acquisition against `gonio sim btf` and raw-frame rendering alone
    /// (ms/image ratios measured in one run, peak memory per phase).
    Acquire(Box<acquire::AcquireBenchArgs>),
    /// HDR acquisition per mode (off, fixed brackets, auto): clipping, error vs. unclipped truth, rig and wall time (table + SVG).
    Hdr(hdr::HdrBenchArgs),
    /// Fly-scan per blur bound against stop and go: the sweep's rig time, and PSNR against the truth on a few views.
    Fly(Box<fly::FlyBenchArgs>),
    /// Sparse acquisition: PSNR of the completed dataset against rig time, with baselines.
    #[cfg(feature = "btf")]
    Sparse(Box<sparse::SparseBenchArgs>),
    /// Decode time of one image of a compressed BTF, on its own (median of rounds; EXR reads of the same images as the baseline).
    #[cfg(feature = "btf")]
    Decode(decode::DecodeBenchArgs),
    /// The renderer exports' error against texture size and bit depth, against the per-texel fit (table or --json).
    #[cfg(feature = "btf")]
    Export(export::ExportBenchArgs),
    /// The inspect page's ABRDF of a raw dataset: texel-major cache build time and per-click time.
    #[cfg(feature = "monitor")]
    ViewCache(view_cache::ViewCacheBenchArgs),
    /// BRDF fitting: starts × iterations against residual and time, on data of known models.
    #[cfg(feature = "btf")]
    Fit(fit::FitBenchArgs),
}

fn run(cmd: BenchCommand) -> Result<ExitCode> {
    match cmd {
        BenchCommand::Sim(a) => sim::run(a),
        BenchCommand::Plan(a) => plan::run(a),
        BenchCommand::Render(a) => render::run(a),
        BenchCommand::Serial(a) => serial::run(a),
        #[cfg(feature = "btf")]
        BenchCommand::Compress(a) => compress::run(a),
        #[cfg(feature = "btf")]
        BenchCommand::Synthesize(a) => synthesize::run(*a),
        BenchCommand::Acquire(a) => acquire::run(*a),
        BenchCommand::Hdr(a) => hdr::run(a),
        BenchCommand::Fly(a) => fly::run(*a),
        #[cfg(feature = "btf")]
        BenchCommand::Sparse(a) => sparse::run(*a),
        #[cfg(feature = "btf")]
        BenchCommand::Decode(a) => decode::run(a),
        #[cfg(feature = "btf")]
        BenchCommand::Export(a) => export::run(a),
        #[cfg(feature = "monitor")]
        BenchCommand::ViewCache(a) => view_cache::run(a),
        #[cfg(feature = "btf")]
        BenchCommand::Fit(a) => fit::run(a),
    }
}

fn main() -> ExitCode {
    // The same process set-up as `gonio` (SIGPIPE, the allocator's mmap threshold): a
    // benchmark times what the command it measures would take.
    gonio::cli::prepare_process();
    let cli = Cli::parse();
    gonio::cli::init_logging(cli.verbose, cli.quiet);
    match run(cli.command) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(1)
        }
    }
}
