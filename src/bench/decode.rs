//! `gonio bench decode FILE`: the decode time of one (light, view) image of a compressed
//! BTF, on its own.
//!
//! `gonio compress` reports a decode time too, but measures it inside its evaluation loop,
//! interleaved with reading every EXR of the dataset, so on a loaded machine it is mostly
//! noise. Here the same images are decoded back to back (after a warm-up), several rounds,
//! and the median round is reported. The baseline in the same run is reading the same
//! images from the dataset's EXR files (`--dataset`): what decoding replaces.

use anyhow::{bail, Context, Result};
use gonio_btf::compress::interp::AnyModel;
use gonio_btf::compress::DatasetViews;
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct DecodeBenchArgs {
    /// A compressed BTF (`.gbtf` or UBO2014 `.btf`).
    pub file: PathBuf,
    /// The dataset the file was compressed from: its EXR reads of the same images are the
    /// baseline.
    #[arg(long)]
    pub dataset: Option<PathBuf>,
    /// Images per round, spread over the (light, view) grid.
    #[arg(long, default_value_t = 32)]
    pub images: usize,
    /// Rounds; the median round is reported.
    #[arg(long, default_value_t = 5)]
    pub rounds: usize,
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize, Debug)]
struct DecodeReport {
    file: String,
    method: String,
    width: usize,
    height: usize,
    images_per_round: usize,
    rounds: usize,
    /// Median over the rounds of (round time / images).
    decode_ms_per_image: f64,
    decode_ms_per_image_min: f64,
    /// Same images read from the dataset's EXRs (median round), when `--dataset` is given.
    exr_read_ms_per_image: Option<f64>,
    /// decode / EXR read: below 1, decoding is cheaper than reading the raw image.
    decode_vs_exr_read: Option<f64>,
    load_average_1min: Option<f64>,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

pub fn run(a: DecodeBenchArgs) -> Result<ExitCode> {
    if a.images == 0 || a.rounds == 0 {
        bail!("--images {} --rounds {}: both must be at least 1", a.images, a.rounds);
    }
    let any = AnyModel::open(&a.file).with_context(|| format!("reading {}", a.file.display()))?;
    let method = match &any {
        AnyModel::Gbtf(m) => m.method().name().to_string(),
        AnyModel::Dfmf(_) => "dfmf (UBO2014 .btf)".to_string(),
    };
    let m = any.model();
    let (nl, nv) = (m.lights_deg().len(), m.views_deg().len());
    let pairs = nl * nv;
    if pairs == 0 {
        bail!("{}: the file has no (light, view) pair to decode", a.file.display());
    }
    // Pairs spread over the grid with a stride coprime to the light count, so the images
    // come from different views and lights.
    let n = a.images.min(pairs);
    let stride = (pairs / n).max(1) | 1;
    let picks: Vec<(usize, usize)> = (0..n).map(|i| (i * stride) % pairs).map(|p| (p % nl, p / nl)).collect();
    for &(l, v) in picks.iter().take(3) {
        std::hint::black_box(m.reconstruct(l, v)?);
    }
    let mut rounds = Vec::with_capacity(a.rounds);
    for _ in 0..a.rounds {
        let t = Instant::now();
        for &(l, v) in &picks {
            std::hint::black_box(m.reconstruct(l, v)?);
        }
        rounds.push(t.elapsed().as_secs_f64() * 1e3 / n as f64);
    }
    let exr = match &a.dataset {
        None => None,
        Some(dir) => {
            let ds = DatasetViews::open(dir).with_context(|| format!("opening dataset {}", dir.display()))?;
            if (ds.n_lights(), ds.n_views(), ds.width, ds.height) != (nl, nv, m.width(), m.height()) {
                bail!(
                    "--dataset {}: its grid or image size differs from {}'s; give the dataset the file was \
                     compressed from",
                    dir.display(),
                    a.file.display()
                );
            }
            let mut r = Vec::with_capacity(a.rounds);
            for _ in 0..a.rounds {
                let t = Instant::now();
                for &(l, v) in &picks {
                    std::hint::black_box(ds.read_image(l, v)?);
                }
                r.push(t.elapsed().as_secs_f64() * 1e3 / n as f64);
            }
            Some(median(r))
        }
    };
    let decode = median(rounds.clone());
    let r = DecodeReport {
        file: a.file.display().to_string(),
        method,
        width: m.width(),
        height: m.height(),
        images_per_round: n,
        rounds: a.rounds,
        decode_ms_per_image: decode,
        decode_ms_per_image_min: rounds.iter().copied().fold(f64::INFINITY, f64::min),
        exr_read_ms_per_image: exr,
        decode_vs_exr_read: exr.map(|e| decode / e),
        load_average_1min: load_average(),
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        println!(
            "{} ({}, {}×{}): decode {:.3} ms per image (median of {} rounds of {} images; min {:.3} ms)",
            r.file, r.method, r.width, r.height, r.decode_ms_per_image, r.rounds, n, r.decode_ms_per_image_min
        );
        if let (Some(e), Some(x)) = (r.exr_read_ms_per_image, r.decode_vs_exr_read) {
            println!("  EXR read of the same images: {e:.3} ms per image; decode / read = {x:.3}");
        }
        if let Some(l) = r.load_average_1min {
            println!("  load average (1 min): {l:.2}");
        }
    }
    Ok(ExitCode::SUCCESS)
}
