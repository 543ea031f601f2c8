//! `gonio generate`: a new BTF from one material's median-cut index image and another
//! material's BRDF block (thesis §8.5).
//!
//! Box counts may differ. Boxes are matched by **mean-albedo rank** (the darkest box
//! of the index image gets the darkest BRDF, the brightest the brightest, ranks in
//! between scaled linearly): box numbers of two independent quantizations carry no
//! meaning, so `i mod n` would pair arbitrary reflectances, whereas rank matching keeps
//! the light/dark structure of the index image (its grooves stay dark, its highlights
//! bright). With equal counts it is a permutation, so every BRDF is used. `--map
//! modulo` is kept for comparison.

use anyhow::{Context, Result};
use gonio_btf::compress::median_cut::{self, BoxMap};
use gonio_btf::compress::Gbtf;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum MapArg {
    /// Match boxes by mean-albedo rank (default).
    Rank,
    /// Box i → box i mod n (for comparison only).
    Modulo,
}

#[derive(clap::Args, Debug)]
pub struct GenerateArgs {
    /// Median-cut `.gbtf` whose index image (structure) is kept.
    #[arg(long)]
    pub index: PathBuf,
    /// Median-cut `.gbtf` whose BRDF block (reflectance) is used.
    #[arg(long)]
    pub brdfs: PathBuf,
    /// Output `.gbtf` (a median-cut file: `gonio reconstruct` renders any image of it).
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, value_enum, default_value_t = MapArg::Rank)]
    pub map: MapArg,
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: GenerateArgs) -> Result<ExitCode> {
    let a = Gbtf::read(&args.index).with_context(|| format!("reading {}", args.index.display()))?;
    let b = Gbtf::read(&args.brdfs).with_context(|| format!("reading {}", args.brdfs.display()))?;
    let map = match args.map {
        MapArg::Rank => BoxMap::Rank,
        MapArg::Modulo => BoxMap::Modulo,
    };
    let (g, box_map) = median_cut::generate(&a, &b, map)
        .with_context(|| format!("combining {} with {}", args.index.display(), args.brdfs.display()))?;
    let bytes = g
        .write(&args.out)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let (na, nb) = (box_map.len(), g.header.blocks[1].rows);
    if args.json {
        let r = serde_json::json!({
            "out": args.out.display().to_string(),
            "stored_bytes": bytes,
            "index_boxes": na,
            "brdf_boxes": nb,
            "map": map,
            "box_map": box_map,
        });
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        println!(
            "{}: index image of {} ({na} boxes) with the BRDFs of {} ({nb} boxes), {} map, {bytes} bytes",
            args.out.display(),
            args.index.display(),
            args.brdfs.display(),
            match args.map {
                MapArg::Rank => "rank",
                MapArg::Modulo => "modulo",
            }
        );
    }
    Ok(ExitCode::SUCCESS)
}
