//! `gonio export` and `gonio verify`.

use crate::store;
use anyhow::{Context, Result};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum ExportFormat {
    /// Bonn's UBO2003 zip of 8-bit sRGB JPEGs (readable by btf-extractor's Ubo2003).
    Ubo2003,
    /// NumPy float32 array [N, H, W, 3] of the 8-bit sRGB values, plus OUT.json index.
    Npy,
}

#[derive(clap::Args, Debug)]
pub struct ExportArgs {
    /// The dataset directory.
    pub dir: PathBuf,
    #[arg(long, value_enum)]
    pub format: ExportFormat,
    /// Output file.
    pub out: PathBuf,
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
    let report = match args.format {
        ExportFormat::Ubo2003 => store::export_ubo2003(&args.dir, &args.out),
        ExportFormat::Npy => store::export_npy(&args.dir, &args.out),
    }
    .with_context(|| format!("exporting {} to {}", args.dir.display(), args.out.display()))?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!("{report:?}");
    }
    Ok(ExitCode::SUCCESS)
}

pub fn verify(args: VerifyArgs) -> Result<ExitCode> {
    let report = store::verify(&args.dir).with_context(|| format!("verifying {}", args.dir.display()))?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!("{report:?}");
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
