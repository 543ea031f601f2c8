//! `gonio bench view-cache DATASET`: the inspect page's ABRDF of a raw dataset through its
//! texel-major cache (`view::abrdf_cache`): the time to build the cache, then the time of
//! single clicks (open the complete cache as a restarted server does, read one texel's
//! ABRDF), and as the baseline the time of decoding one texel's ABRDF image by image
//! (`--direct`, slow on a full dataset: every EXR is read).

use anyhow::{Context, Result};
use gonio::view::abrdf_cache::{self, AbrdfCache, Progress};
use gonio::view::source::RawModel;
use gonio_btf::compress::interp::BtfModel;
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct ViewCacheBenchArgs {
    /// A raw gonio dataset directory.
    pub dataset: PathBuf,
    /// Cache root (as `gonio view --cache`); default: `$XDG_CACHE_HOME/gonio/abrdf`.
    #[arg(long, value_name = "DIR")]
    pub cache: Option<PathBuf>,
    /// Clicks timed after the build (texels spread over the image).
    #[arg(long, default_value_t = 8)]
    pub clicks: usize,
    /// Keep an existing complete cache instead of rebuilding it.
    #[arg(long)]
    pub keep: bool,
    /// Also time one ABRDF decoded image by image (the baseline; reads every EXR).
    #[arg(long)]
    pub direct: bool,
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize, Debug)]
struct Report {
    dataset: String,
    cache_dir: String,
    width: usize,
    height: usize,
    pairs: usize,
    measured: usize,
    dtype: String,
    cache_bytes: u64,
    /// `None` when an existing cache was kept.
    build_s: Option<f64>,
    first_click_ms: f64,
    median_click_ms: f64,
    max_click_ms: f64,
    direct_click_s: Option<f64>,
}

pub fn run(a: ViewCacheBenchArgs) -> Result<ExitCode> {
    let raw = RawModel::open(&a.dataset).with_context(|| format!("opening {}", a.dataset.display()))?;
    let views = &raw.views;
    let root = match a.cache.clone() {
        Some(c) => c,
        None => abrdf_cache::default_root().context("no cache directory: pass --cache DIR")?,
    };
    let key = abrdf_cache::key(&root, views, gonio::view::monitor::journal_len(&a.dataset))?;
    let mut build_s = None;
    if !a.keep || AbrdfCache::open(&key.dir, views, &key)?.is_none() {
        let _ = std::fs::remove_dir_all(&key.dir);
        let t = Instant::now();
        abrdf_cache::build(views, &key, &Progress::default())?;
        build_s = Some(t.elapsed().as_secs_f64());
    }
    let (w, h) = (views.width, views.height);
    let texels: Vec<(usize, usize)> = (0..a.clicks.max(1))
        .map(|i| ((i * 7919 + w / 2) % w, (i * 104_729 + h / 3) % h))
        .collect();
    let mut ms = Vec::new();
    let mut meta = None;
    for &(x, y) in &texels {
        let t = Instant::now();
        let c = AbrdfCache::open(&key.dir, views, &key)?.context("the cache just built is not complete")?;
        let v = c.abrdf(x, y)?;
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        std::hint::black_box(v);
        meta = Some(c.meta);
    }
    let meta = meta.expect("at least one click");
    let direct_click_s = if a.direct {
        let (x, y) = texels[0];
        let t = Instant::now();
        for v in 0..views.n_views() {
            for l in 0..views.n_lights() {
                let img = raw.reconstruct(l, v)?;
                std::hint::black_box(&img[(y * w + x) * 3..(y * w + x) * 3 + 3]);
            }
        }
        Some(t.elapsed().as_secs_f64())
    } else {
        None
    };
    let cache_bytes = std::fs::read_dir(&key.dir)?
        .flatten()
        .filter_map(|e| e.metadata().ok())
        .map(|m| m.len())
        .sum();
    let first = ms[0];
    let mut sorted = ms.clone();
    sorted.sort_by(f64::total_cmp);
    let r = Report {
        dataset: a.dataset.display().to_string(),
        cache_dir: key.dir.display().to_string(),
        width: w,
        height: h,
        pairs: views.n_lights() * views.n_views(),
        measured: views.n_measured(),
        dtype: format!("{:?}", meta.dtype).to_lowercase(),
        cache_bytes,
        build_s,
        first_click_ms: first,
        median_click_ms: sorted[sorted.len() / 2],
        max_click_ms: *sorted.last().unwrap_or(&first),
        direct_click_s,
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        println!(
            "dataset {} ({}×{}, {} of {} pairs measured)",
            r.dataset, w, h, r.measured, r.pairs
        );
        println!(
            "cache   {} ({}, {:.1} MiB)",
            r.cache_dir,
            r.dtype,
            r.cache_bytes as f64 / 1048576.0
        );
        match r.build_s {
            Some(s) => println!("build   {s:.1} s"),
            None => println!("build   (kept the existing cache)"),
        }
        println!(
            "clicks  first {:.2} ms, median {:.2} ms, max {:.2} ms over {} texels (open the cache + read one ABRDF)",
            r.first_click_ms,
            r.median_click_ms,
            r.max_click_ms,
            ms.len()
        );
        if let Some(s) = r.direct_click_s {
            println!("direct  {s:.1} s for one ABRDF decoded image by image (the baseline)");
        }
    }
    Ok(ExitCode::SUCCESS)
}
