//! `gonio import`: a foreign archive (Bonn UBO2003) into a native dataset.

use anyhow::{Context, Result};
use gonio_dataset::store::import_ubo2003::{import_ubo2003, ImportLimits};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum ImportFormat {
    /// Bonn's UBO2003 zip of 8-bit sRGB images named `… tlNNN plNNN tvNNN pvNNN.jpg`.
    Ubo2003,
}

#[derive(clap::Args, Debug)]
pub struct ImportArgs {
    /// The archive to import.
    pub archive: PathBuf,
    #[arg(long, value_enum, default_value = "ubo2003")]
    pub format: ImportFormat,
    /// The new dataset directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Replace an existing gonio dataset at --out.
    #[arg(long, conflicts_with = "resume")]
    pub force: bool,
    /// Continue an interrupted import into --out.
    #[arg(long)]
    pub resume: bool,
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: ImportArgs, quiet: bool) -> Result<ExitCode> {
    let bar = if quiet || args.json {
        indicatif::ProgressBar::hidden()
    } else {
        indicatif::ProgressBar::new(0).with_style(
            indicatif::ProgressStyle::with_template("importing {bar:40} {pos}/{len} images ({eta})")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        )
    };
    let report = match args.format {
        ImportFormat::Ubo2003 => import_ubo2003(
            &args.archive,
            &args.out,
            args.force,
            args.resume,
            &ImportLimits::default(),
            |done, total| {
                bar.set_length(total as u64);
                bar.set_position(done as u64);
            },
        ),
    }
    .with_context(|| format!("importing {} into {}", args.archive.display(), args.out.display()))?;
    bar.finish_and_clear();
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "{}: {} lights × {} views of {}×{} ({} imported, {} already present, {} pairs not in the archive{})",
            report.out.display(),
            report.lights,
            report.views,
            report.width,
            report.height,
            report.imported,
            report.already_present,
            report.missing_pairs,
            if report.bonn81 { ", Bonn 81 order" } else { "" }
        );
        if !report.ignored_entries.is_empty() {
            println!(
                "ignored {} entries without angles, e.g. {:?}",
                report.ignored_entries.len(),
                report.ignored_entries[0]
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
