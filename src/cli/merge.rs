//! `gonio merge`: join the parts of a sharded run (`--shard I/N`) into one output.

use anyhow::{Context, Result};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct MergeArgs {
    /// The parts: dataset directories of `gonio sim btf --shard`, `.gbtf` files of
    /// `gonio compress --method pvmf --shard`, or the `.gpart` files of one pass of
    /// `gonio compress --method pca|dfmf|local-pca --shard`; every shard 1..=N exactly once, any order.
    #[arg(required = true)]
    pub parts: Vec<PathBuf>,
    /// The merged dataset directory or `.gbtf` file; for `.gpart` parts the pass's state
    /// (`.gstate`, the next round's `--state`) or, after the last pass, the `.gbtf`/`.btf`.
    #[arg(long)]
    pub out: PathBuf,
    /// Join one group of a pass's `.gpart` parts into one `.gpart` (shards
    /// `(g−1)·m+1 ..= g·m` of N become shard g of N/m), for a tree of merges: every merge
    /// then reads m parts, and the final merge takes the group parts as it takes shards.
    #[arg(long)]
    pub partial: bool,
    /// Replace an existing output.
    #[arg(long)]
    pub force: bool,
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: MergeArgs) -> Result<ExitCode> {
    let t0 = Instant::now();
    let report = if a.partial {
        crate::merge::merge_partial(&a.parts, &a.out, a.force)
    } else {
        crate::merge::merge(&a.parts, &a.out, a.force)
    }
    .with_context(|| format!("merging {} part(s) into {}", a.parts.len(), a.out.display()))?;
    let seconds = t0.elapsed().as_secs_f64();
    if a.json {
        let mut v = serde_json::to_value(&report)?;
        v["seconds"] = serde_json::json!(seconds);
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else if report.kind == "part" {
        println!(
            "joined {} of the {} shards of pass {} into {} in {seconds:.2} s; the final merge takes it like a shard",
            report.parts,
            report.shards,
            report.pass.map_or(0, |p| p[0] + 1),
            report.out.display()
        );
    } else if let Some([pass, passes]) = report.pass {
        println!(
            "merged {} part(s) of pass {}/{passes} ({} shards, {} views) into {} {} in {seconds:.2} s{}",
            report.parts,
            pass + 1,
            report.shards,
            report.views,
            report.kind,
            report.out.display(),
            if pass + 1 < passes {
                format!("; next: the shards with --state {}", report.out.display())
            } else {
                String::new()
            }
        );
    } else {
        println!(
            "merged {} {} part(s) ({} shards, {} views, {} {}) into {} in {seconds:.2} s",
            report.parts,
            report.kind,
            report.shards,
            report.views,
            report.items,
            if report.kind == "dataset" { "records" } else { "blocks" },
            report.out.display()
        );
    }
    Ok(ExitCode::SUCCESS)
}
