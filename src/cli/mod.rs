//! Command-line interface: argument parsing and one module per subcommand.
//!
//! Library errors are typed; here they get context (which file, which step) through
//! `anyhow`. Every command that prints figures has `--json` for scripts.

mod acquire;
#[cfg(feature = "btf")]
mod batch;
mod bench;
mod bench_acquire;
#[cfg(feature = "btf")]
mod bench_compress;
#[cfg(feature = "btf")]
mod bench_decode;
#[cfg(feature = "btf")]
mod bench_fit;
mod bench_fly;
mod bench_hdr;
mod bench_serial;
#[cfg(feature = "btf")]
mod bench_sparse;
#[cfg(feature = "btf")]
mod bench_synthesize;
#[cfg(feature = "btf")]
mod bench_view;
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
    #[command(subcommand)]
    Bench(bench::BenchCommand),
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
        Command::Bench(c) => bench::run(c),
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
