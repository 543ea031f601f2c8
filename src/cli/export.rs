//! `gonio export` and `gonio verify`.

use anyhow::{Context, Result};
use gonio_dataset::store;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum ExportFormat {
    /// Bonn's UBO2003 zip of 8-bit sRGB JPEGs (readable by btf-extractor's Ubo2003).
    Ubo2003,
    /// NumPy float32 array [N, H, W, 3] of the 8-bit sRGB values, plus OUT.json index.
    Npy,
    /// Zarr v3 store: float16 [view, light, y, x, channel], one view per shard, one image
    /// per inner chunk, NaN where a pair is missing (needs the cargo feature `zarr`).
    Zarr,
}

#[derive(clap::Args, Debug)]
pub struct ExportArgs {
    /// The dataset directory.
    pub dir: PathBuf,
    #[arg(long, value_enum)]
    pub format: ExportFormat,
    /// Output file (a directory for --format zarr).
    pub out: PathBuf,
    /// Zarr only: write the shards of views of part I of N (1-based) into OUT; N such
    /// processes fill one store, equal byte for byte to a single-process export.
    #[arg(long)]
    pub shard: Option<gonio_dataset::shard::Shard>,
    /// Zarr only: replace an existing Zarr store at OUT.
    #[arg(long)]
    pub force: bool,
    /// Zarr only: also write the mean image over all exported pairs (NaN-mean of the
    /// stored float16 values, in float64) as a NumPy float64 array [H, W, 3].
    #[arg(long, value_name = "NPY")]
    pub mean_image: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct VerifyArgs {
    pub dir: PathBuf,
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: ExportArgs) -> Result<ExitCode> {
    if let ExportFormat::Zarr = args.format {
        return run_zarr(args);
    }
    if args.shard.is_some() || args.force || args.mean_image.is_some() {
        anyhow::bail!("--shard, --force and --mean-image apply to --format zarr only");
    }
    let report = match args.format {
        ExportFormat::Ubo2003 => store::export_ubo2003(&args.dir, &args.out),
        ExportFormat::Npy => store::export_npy(&args.dir, &args.out),
        ExportFormat::Zarr => unreachable!("handled above"),
    }
    .with_context(|| format!("exporting {} to {}", args.dir.display(), args.out.display()))?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "{}: {} images exported ({} with a substituted light direction), {} skipped measurements left out; {} bytes",
            report.path.display(),
            report.entries,
            report.substituted,
            report.skipped,
            report.bytes
        );
        if let Some(sidecar) = &report.sidecar {
            println!("index: {}", sidecar.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(feature = "zarr")]
fn run_zarr(args: ExportArgs) -> Result<ExitCode> {
    use store::export::zarr::{export_zarr, write_mean_npy, ZarrOptions};
    let opts = ZarrOptions {
        shard: args.shard,
        force: args.force,
        mean: args.mean_image.is_some(),
    };
    let (report, mean) = export_zarr(&args.dir, &args.out, &opts)
        .with_context(|| format!("exporting {} to Zarr {}", args.dir.display(), args.out.display()))?;
    let mut mean_json = serde_json::Value::Null;
    if let (Some(path), Some(mean)) = (&args.mean_image, &mean) {
        write_mean_npy(mean, path).with_context(|| format!("writing the mean image {}", path.display()))?;
        mean_json = serde_json::json!({ "path": path, "images": mean.images, "shape": [mean.height, mean.width, 3] });
    }
    if args.json {
        let mut v = serde_json::to_value(&report)?;
        v["mean_image"] = mean_json;
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "{}: [view, light, y, x, channel] = {:?} f16; views {}..{} written ({} images, {} files, {} bytes); \
             whole store: {} measured, {} substituted, {} isotropic, {} missing (NaN)",
            report.path.display(),
            report.shape,
            report.views_written[0],
            report.views_written[1],
            report.images_written,
            report.files_written,
            report.bytes_written,
            report.measured,
            report.substituted,
            report.isotropic,
            report.missing
        );
        if let Some(p) = &args.mean_image {
            println!("mean image: {}", p.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(not(feature = "zarr"))]
fn run_zarr(_args: ExportArgs) -> Result<ExitCode> {
    anyhow::bail!(
        "this gonio was built without Zarr support (cargo feature `zarr`, on by default): \
         rebuild with `cargo build --release --features zarr` (or without --no-default-features)"
    )
}

pub fn verify(args: VerifyArgs) -> Result<ExitCode> {
    let report = store::verify(&args.dir).with_context(|| format!("verifying {}", args.dir.display()))?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_verify(&report);
    }
    if report.damaged.is_empty() {
        Ok(ExitCode::SUCCESS)
    } else {
        eprintln!(
            "{}: {} damaged or missing file(s); `gonio acquire --resume {}` measures them again",
            args.dir.display(),
            report.damaged.len(),
            args.dir.display()
        );
        Ok(ExitCode::from(2))
    }
}

/// `gonio verify` for a person: what was checked, then each kind of problem, one line each.
fn print_verify(r: &store::VerifyReport) {
    println!(
        "{}: {} journal records ({} measured, {} substituted, {} skipped), {}; {} images and {} raw frames \
         match their SHA-256 ({} bytes hashed)",
        r.dir.display(),
        r.records,
        r.measured,
        r.substituted,
        r.skipped,
        if r.complete { "complete" } else { "incomplete" },
        r.images_ok,
        r.raw_ok,
        r.bytes_hashed
    );
    for d in &r.damaged {
        println!("damaged or missing: record {d}");
    }
    if !r.orphans.is_empty() {
        println!(
            "{} file(s) without a journal line (a resume removes them)",
            r.orphans.len()
        );
    }
    if !r.temp_files.is_empty() {
        println!(
            "{} leftover temporary file(s) (a resume removes them)",
            r.temp_files.len()
        );
    }
    if !r.duplicates.is_empty() {
        let d: Vec<String> = r.duplicates.iter().map(|i| i.to_string()).collect();
        println!("indices recorded more than once: {}", d.join(", "));
    }
    if let Some((line, why)) = &r.torn_line {
        println!("the journal's last line ({line}) is torn: {why}");
    }
    if r.manifest_stale {
        println!("the manifest's records differ from the journal's (the journal is the record)");
    }
}
