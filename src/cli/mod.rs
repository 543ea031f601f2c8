//! Command-line interface: argument parsing and one module per subcommand.
//!
//! Library errors are typed; here they get context (which file, which step) through
//! `anyhow`. Every command that prints figures has `--json` for scripts.

mod acquire;
mod batch;
mod bench;
mod bench_acquire;
mod bench_compress;
mod bench_decode;
mod bench_fit;
mod bench_hdr;
mod bench_serial;
mod bench_sparse;
mod bench_synthesize;
mod brdf;
mod calibrate;
mod common;
mod complete;
mod compress;
mod dataset;
mod devices;
mod export;
mod fit;
mod generate;
mod import;
mod merge;
mod plan;
mod prior;
mod render;
mod serve_stage;
mod sim;
mod sim_btf;
mod svg_plot;
mod synthesize;
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
    Acquire(acquire::AcquireArgs),
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
    Compress(compress::CompressArgs),
    /// Fit an analytic BRDF model (lafortune, ward, cook-torrance, rough-conductor) to a
    /// homogeneous sample's averaged BRDF or per texel; parameters, residual, where it fails.
    Fit(Box<fit::FitArgs>),
    /// Find hardware: list serial ports and video devices, probe a port for a controller.
    #[command(subcommand)]
    Devices(devices::DevicesCommand),
    /// Run a calibration recipe (calibration/recipes/*.toml) on a rig; write a versioned result.
    Calibrate(calibrate::CalibrateArgs),
    /// Reconstruct one (light, view) image from a .gbtf file.
    Reconstruct(compress::ReconstructArgs),
    /// A new BTF from one median-cut file's index image and another's BRDF block.
    Generate(generate::GenerateArgs),
    /// Grow a compressed BTF to any size (tile, efros-leung, wei-levoy, quilting).
    Synthesize(synthesize::SynthesizeArgs),
    /// Render a dataset or compressed file on a plane, sphere or cylinder (the viewer's CPU reference).
    Render(render::RenderArgs),
    /// Serve the browser viewer (relight, inspect, live monitor) for a dataset or compressed file.
    View(view::ViewArgs),
    /// Join the parts of a sharded run (`--shard I/N`) into the single-process output.
    Merge(merge::MergeArgs),
    /// Run a sharded command on a cluster scheduler (Slurm job array + merge job).
    #[command(subcommand)]
    Batch(batch::BatchCommand),
    /// Families of synthetic datasets for testing other software.
    #[command(subcommand)]
    Dataset(dataset::DatasetCommand),
    /// Sparse acquisition: learn the angular prior that completes sparsely measured datasets.
    #[command(subcommand)]
    Prior(prior::PriorCommand),
    /// Complete a sparsely measured dataset to the full grid in a prior (status `predicted`).
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
        Command::Acquire(a) => acquire::run(a),
        Command::Plan(a) => plan::run(a),
        Command::Export(a) => export::run(a),
        Command::Verify(a) => export::verify(a),
        Command::Import(a) => import::run(a, cli.quiet),
        Command::Sim(c) => sim::run(c),
        Command::Bench(c) => bench::run(c),
        Command::Brdf(c) => brdf::run(c),
        Command::Compress(a) => compress::run(a),
        Command::Fit(a) => fit::run(*a),
        Command::Devices(c) => devices::run(c),
        Command::Reconstruct(a) => compress::reconstruct(a),
        Command::Generate(a) => generate::run(a),
        Command::Synthesize(a) => synthesize::run(a),
        Command::Calibrate(a) => calibrate::run(a),
        Command::Render(a) => render::run(a),
        Command::View(a) => view::run(a),
        Command::Merge(a) => merge::run(a),
        Command::Batch(c) => batch::run(c),
        Command::Dataset(c) => dataset::run(c),
        Command::Prior(c) => prior::run(c),
        Command::Complete(a) => complete::run(a),
    }
}
