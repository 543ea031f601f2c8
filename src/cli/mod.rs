//! Command-line interface: argument parsing and one module per subcommand.
//!
//! Library errors are typed; here they get context (which file, which step) through
//! `anyhow`. Every command that prints figures has `--json` for scripts.

mod acquire;
#[cfg(feature = "btf")]
mod batch;
pub mod bench;
mod brdf;
mod calibrate;
mod common;
#[cfg(feature = "btf")]
mod complete;
#[cfg(feature = "btf")]
mod compress;
mod dataset;
mod devices;
mod export;
#[cfg(feature = "btf")]
mod fit;
#[cfg(feature = "btf")]
mod generate;
mod import;
#[cfg(feature = "btf")]
mod merge;
mod plan;
#[cfg(feature = "btf")]
mod prior;
#[cfg(feature = "monitor")]
mod render;
mod serve_light;
mod serve_stage;
mod sim;
mod sim_btf;
mod sparse;
mod svg_plot;
#[cfg(feature = "btf")]
mod synthesize;
#[cfg(feature = "monitor")]
mod view;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[derive(Parser, Debug)]
#[command(
    name = "gonio",
    version,
    about = "Plan, drive, rectify, store and compress gonioreflectometer (BTF) acquisitions"
)]
pub struct Cli {
    /// More log output (-v info, -vv debug); logs go to stderr. RUST_LOG overrides.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    pub verbose: u8,
    /// Only errors on stderr.
    #[arg(short, long, global = true)]
    pub quiet: bool,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Run an acquisition (default: simulated rig, default sample, Bonn 81 × 81 sweep).
    Acquire(Box<acquire::AcquireArgs>),
    /// Plan a sweep for a rig without moving anything.
    Plan(plan::PlanArgs),
    /// Export a dataset to an interchange format.
    Export(export::ExportArgs),
    /// Import a foreign archive (Bonn UBO2003 zip) into a native dataset.
    Import(import::ImportArgs),
    /// Check every stored image of a dataset against its recorded hash.
    Verify(export::VerifyArgs),
    /// The simulator: render single measurements, write ground truth.
    #[command(subcommand)]
    Sim(sim::SimCommand),
    /// The BRDF material library: list models, evaluate one.
    #[command(subcommand)]
    Brdf(brdf::BrdfCommand),
    /// Benchmarks (ratios against a baseline run in the same process).
    ///
    /// They are their own binary, `gonio-bench`, next to `gonio`: `gonio bench ARGS…` runs
    /// it with ARGS as they are. `gonio bench --help` lists the benchmarks.
    #[command(disable_help_flag = true)]
    Bench(bench::BenchArgs),
    /// Compress a dataset (PCA, PVMF, local PCA, median cut, homomorphic: .gbtf; DFMF: UBO2014 .btf)
    /// and report its size and error.
    #[cfg(feature = "btf")]
    Compress(compress::CompressArgs),
    /// Fit an analytic BRDF model (lafortune, ward, cook-torrance, rough-conductor) to a
    /// homogeneous sample's averaged BRDF or per texel; parameters, residual, where it fails.
    #[cfg(feature = "btf")]
    Fit(Box<fit::FitArgs>),
    /// Find hardware: list serial ports and video devices, probe a port for a controller.
    #[command(subcommand)]
    Devices(devices::DevicesCommand),
    /// Run a calibration recipe (calibration/recipes/*.toml) on a rig; write a versioned result.
    Calibrate(calibrate::CalibrateArgs),
    /// Reconstruct one (light, view) image from a .gbtf file.
    #[cfg(feature = "btf")]
    Reconstruct(compress::ReconstructArgs),
    /// A new BTF from one median-cut file's index image and another's BRDF block.
    #[cfg(feature = "btf")]
    Generate(generate::GenerateArgs),
    /// Grow a compressed BTF to any size (tile, efros-leung, wei-levoy, quilting).
    #[cfg(feature = "btf")]
    Synthesize(synthesize::SynthesizeArgs),
    /// Render a dataset or compressed file on a plane, sphere or cylinder (the viewer's CPU reference).
    #[cfg(feature = "monitor")]
    Render(render::RenderArgs),
    /// Serve the browser viewer (relight, inspect, live monitor) for a dataset or compressed file.
    #[cfg(feature = "monitor")]
    View(view::ViewArgs),
    /// Join the parts of a sharded run (`--shard I/N`) into the single-process output.
    #[cfg(feature = "btf")]
    Merge(merge::MergeArgs),
    /// Run a sharded command on a cluster scheduler (Slurm job array + merge job).
    #[cfg(feature = "btf")]
    #[command(subcommand)]
    Batch(batch::BatchCommand),
    /// Families of synthetic datasets for testing other software.
    #[command(subcommand)]
    Dataset(dataset::DatasetCommand),
    /// Sparse acquisition: learn the angular prior that completes sparsely measured datasets.
    #[cfg(feature = "btf")]
    #[command(subcommand)]
    Prior(prior::PriorCommand),
    /// Complete a sparsely measured dataset to the full grid in a prior (status `predicted`).
    #[cfg(feature = "btf")]
    Complete(complete::CompleteArgs),
}

/// Process set-up shared by `gonio` and `gonio-bench`, called first thing in `main`, before
/// any other thread exists: the default SIGPIPE action and the allocator's mmap threshold
/// ([`keep_freed_images_mapped`]).
pub fn prepare_process() {
    // Rust ignores SIGPIPE, so `println!` into a closed pipe (`gonio … --json | head`)
    // panics. Restore the default action: like every Unix filter, gonio then ends quietly
    // when its reader goes away. Nothing is lost by it: datasets are durable against any
    // kill (every stored measurement is fsynced before it is journalled), and progress
    // and logs go to stderr, so only a command's final report can meet a closed pipe.
    // SAFETY: the callers call this first thing in main, before any other thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    keep_freed_images_mapped();
}

/// Stop glibc's malloc from unmapping every freed image.
///
/// gonio allocates and frees a frame-sized buffer (0.8 MiB for a 256² RGB f32 image, 9 MiB
/// for a 1024 × 768 raw frame) thousands of times, on rayon's threads. glibc serves such
/// sizes with mmap and returns them with munmap (its threshold adapts upward only for
/// allocations of the thread that frees them), so every new image page-faults its memory in
/// again and every unmap stops both cores for a TLB shoot-down: `gonio sim btf` (6561
/// truth images of 256²) took 33.5 s on two cores, slower than the 27.4 s of one thread.
/// With buffers up to 32 MiB served from the heap it takes 11–14 s (measured with
/// `MALLOC_MMAP_THRESHOLD_`, which glibc reads first and which then still wins).
/// The trim threshold stays glibc's, so freed heap memory is still given back: keeping
/// 128 MiB of it as well bought no speed and made the soak campaign's acquisition hold
/// 90 MiB instead of 43 MiB, with a 12 MiB step after 200 s (`tests/campaigns/soak.sh`).
fn keep_freed_images_mapped() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    if std::env::var_os("MALLOC_MMAP_THRESHOLD_").is_none() {
        // SAFETY: mallopt only changes allocator parameters; called before any thread exists.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        }
    }
}

pub fn init_logging(verbose: u8, quiet: bool) {
    let default = if quiet {
        "error"
    } else {
        match verbose {
            0 => "warn",
            1 => "info",
            _ => "debug",
        }
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

pub fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Acquire(a) => acquire::run(*a),
        Command::Plan(a) => plan::run(a),
        Command::Export(a) => export::run(a),
        Command::Verify(a) => export::verify(a),
        Command::Import(a) => import::run(a, cli.quiet),
        Command::Sim(c) => sim::run(c),
        Command::Bench(a) => bench::run(a, cli.verbose, cli.quiet),
        Command::Brdf(c) => brdf::run(c),
        #[cfg(feature = "btf")]
        Command::Compress(a) => compress::run(a),
        #[cfg(feature = "btf")]
        Command::Fit(a) => fit::run(*a),
        Command::Devices(c) => devices::run(c),
        #[cfg(feature = "btf")]
        Command::Reconstruct(a) => compress::reconstruct(a),
        #[cfg(feature = "btf")]
        Command::Generate(a) => generate::run(a),
        #[cfg(feature = "btf")]
        Command::Synthesize(a) => synthesize::run(a),
        Command::Calibrate(a) => calibrate::run(a),
        #[cfg(feature = "monitor")]
        Command::Render(a) => render::run(a),
        #[cfg(feature = "monitor")]
        Command::View(a) => view::run(a),
        #[cfg(feature = "btf")]
        Command::Merge(a) => merge::run(a),
        #[cfg(feature = "btf")]
        Command::Batch(c) => batch::run(c),
        Command::Dataset(c) => dataset::run(c),
        #[cfg(feature = "btf")]
        Command::Prior(c) => prior::run(c),
        #[cfg(feature = "btf")]
        Command::Complete(a) => complete::run(a),
    }
}
