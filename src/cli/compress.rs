//! `gonio compress` and `gonio reconstruct`.

use super::common::parse_angles;
use crate::compress::{self, CompressedBtf, DatasetViews, Gbtf, Method, Params};
use anyhow::{Context, Result};
use gonio_devices::image::RgbImage;
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum MethodArg {
    /// Full-matrix PCA (randomized SVD streamed over the views).
    Pca,
    /// Per-view matrix factorization (one truncated SVD per view).
    Pvmf,
}

#[derive(clap::Args, Debug)]
pub struct CompressArgs {
    /// The dataset directory.
    pub dataset: PathBuf,
    #[arg(long, value_enum)]
    pub method: MethodArg,
    /// Components kept (per view for PVMF, in total for PCA).
    #[arg(long, short = 'c')]
    pub components: usize,
    /// Output `.gbtf` file.
    #[arg(long)]
    pub out: PathBuf,
    /// PCA: seed of the random sketch.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// PCA: power iterations (one extra pass over the dataset each).
    #[arg(long, default_value_t = 2)]
    pub power_iters: usize,
    /// PCA: oversampling of the sketch.
    #[arg(long, default_value_t = 10)]
    pub oversample: usize,
    /// Skip the error evaluation (a second pass reading every image).
    #[arg(long)]
    pub no_eval: bool,
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct ReconstructArgs {
    /// A `.gbtf` file written by `gonio compress`.
    pub file: PathBuf,
    /// Light direction `θ,φ` in degrees (must be a measured grid direction).
    #[arg(long, value_parser = parse_angles)]
    pub light: gonio_devices::Direction,
    /// View direction `θ,φ` in degrees (must be a measured grid direction).
    #[arg(long, value_parser = parse_angles)]
    pub view: gonio_devices::Direction,
    /// Output image: .png (8-bit sRGB) or .exr (linear float).
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Serialize, Debug)]
struct Report {
    method: &'static str,
    components: usize,
    out: String,
    images_measured: usize,
    filled_pairs: usize,
    dataset_passes: usize,
    stored_bytes: u64,
    /// Lights · views · W · H · 3 (one 8-bit RGB image per grid pair).
    raw_8bit_bytes: u64,
    compression_ratio: f64,
    encode_seconds: f64,
    /// The remaining fields are absent with --no-eval.
    error_scale: &'static str,
    rmse_8bit: Option<f64>,
    mean_abs_8bit: Option<f64>,
    max_8bit: Option<f64>,
    psnr_8bit_db: Option<f64>,
    rmse_linear: Option<f64>,
    decode_seconds_per_image: Option<f64>,
    peak_memory_bytes: Option<u64>,
}

pub fn run(args: CompressArgs) -> Result<ExitCode> {
    let t0 = Instant::now();
    let ds = DatasetViews::open(&args.dataset).with_context(|| format!("opening {}", args.dataset.display()))?;
    let params = Params {
        method: match args.method {
            MethodArg::Pca => Method::Pca,
            MethodArg::Pvmf => Method::Pvmf,
        },
        components: args.components,
        seed: args.seed,
        oversample: args.oversample,
        power_iters: args.power_iters,
    };
    let (gbtf, info) =
        compress::compress(&ds, &params).with_context(|| format!("compressing {}", args.dataset.display()))?;
    let stored = gbtf
        .write(&args.out)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let encode_seconds = t0.elapsed().as_secs_f64();
    drop(gbtf);

    // conventions.md: ratio against the raw 8-bit size of the full grid (L · V · W · H · 3).
    let raw = (ds.n_lights() * ds.n_views() * ds.texels() * 3) as u64;
    let mut r = Report {
        method: params.method.name(),
        components: params.components,
        out: args.out.display().to_string(),
        images_measured: ds.n_measured(),
        filled_pairs: info.filled,
        dataset_passes: info.passes,
        stored_bytes: stored,
        raw_8bit_bytes: raw,
        compression_ratio: raw as f64 / stored as f64,
        encode_seconds,
        error_scale: "8-bit sRGB codes / 255 (UBO2003 encoding); linear in the dataset's values",
        rmse_8bit: None,
        mean_abs_8bit: None,
        max_8bit: None,
        psnr_8bit_db: None,
        rmse_linear: None,
        decode_seconds_per_image: None,
        peak_memory_bytes: None,
    };
    if !args.no_eval {
        // Evaluate what was written: read the file back (checks every CRC).
        let model =
            CompressedBtf::new(Gbtf::read(&args.out).with_context(|| format!("reading {}", args.out.display()))?)?;
        let ev = compress::evaluate(&ds, &model).context("evaluating the reconstruction")?;
        r.rmse_8bit = Some(ev.stats.rmse_8bit());
        r.mean_abs_8bit = Some(ev.stats.mean_abs_8bit());
        r.max_8bit = Some(ev.stats.max_8bit);
        r.psnr_8bit_db = Some(ev.stats.psnr_8bit());
        r.rmse_linear = Some(ev.stats.rmse_linear());
        r.decode_seconds_per_image = Some(ev.decode_seconds_per_image);
    }
    r.peak_memory_bytes = compress::peak_memory_bytes();
    if args.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        print_report(&r);
    }
    Ok(ExitCode::SUCCESS)
}

fn print_report(r: &Report) {
    println!("method         {} c = {} → {}", r.method, r.components, r.out);
    println!(
        "images         {} measured, {} unmeasured pairs filled from the nearest light, {} pass(es)",
        r.images_measured, r.filled_pairs, r.dataset_passes
    );
    println!(
        "size           {} bytes, ratio {:.2} against {} bytes of raw 8-bit images (full grid)",
        r.stored_bytes, r.compression_ratio, r.raw_8bit_bytes
    );
    println!("encode         {:.2} s", r.encode_seconds);
    if let (Some(rmse), Some(mae), Some(max), Some(psnr), Some(lin), Some(dec)) = (
        r.rmse_8bit,
        r.mean_abs_8bit,
        r.max_8bit,
        r.psnr_8bit_db,
        r.rmse_linear,
        r.decode_seconds_per_image,
    ) {
        println!("error (/255)   RMSE {rmse:.5}, mean abs {mae:.5}, max {max:.5}, PSNR {psnr:.2} dB (8-bit sRGB)");
        println!("error linear   RMSE {lin:.6}");
        println!("decode         {:.3} ms per image", dec * 1e3);
    }
    if let Some(p) = r.peak_memory_bytes {
        println!("peak memory    {} MiB", p / (1 << 20));
    }
}

pub fn reconstruct(args: ReconstructArgs) -> Result<ExitCode> {
    let model = CompressedBtf::new(Gbtf::read(&args.file).with_context(|| format!("reading {}", args.file.display()))?)
        .with_context(|| format!("{}", args.file.display()))?;
    let (l, v) = (
        [args.light.theta_deg(), args.light.phi_deg()],
        [args.view.theta_deg(), args.view.phi_deg()],
    );
    let data = model
        .reconstruct_deg(l, v)
        .with_context(|| format!("reconstructing light {l:?}°, view {v:?}° from {}", args.file.display()))?;
    let h = model.header();
    if let (Some(li), Some(vi)) = (
        compress::find_direction(&h.lights_deg, l),
        compress::find_direction(&h.views_deg, v),
    ) {
        if h.filled.contains(&[li, vi]) {
            eprintln!(
                "warning: light {l:?}°, view {v:?}° was not measured; its image was filled from the \
                 nearest measured light before compression"
            );
        }
    }
    let img = RgbImage {
        width: h.width,
        height: h.height,
        data,
    };
    super::sim::write_image(&args.out, &img)?;
    Ok(ExitCode::SUCCESS)
}
