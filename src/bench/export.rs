//! `gonio bench export F.gbtf`: what the renderer exports cost in accuracy against the
//! texture size and bit depth, and what they weigh.
//!
//! For each size and bit depth, the material a renderer reads back from the glTF textures
//! (`gonio_btf::export::fidelity`) against the per-texel fit itself, over the same light
//! and view directions, with the PNG bytes and the time. The baseline in the same run is
//! the fit's own size at 16 bits: what is left there is the base colour clamped to 1.
//! Below the fit's size each setting is measured prefiltered (the export's default) and
//! sampled bilinearly, and also against each texel's footprint mean (what a renderer
//! pixel covering it shows).

use anyhow::{bail, Context, Result};
use gonio_btf::compress::Gbtf;
use gonio_btf::export::fidelity::{self, Fidelity};
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct ExportBenchArgs {
    /// A per-texel glTF fit (`gonio fit DATASET --model gltf --per-texel --out F.gbtf`).
    pub file: PathBuf,
    /// Texture sides to export at (texels; the fit's own side is always measured too).
    #[arg(long, value_delimiter = ',', default_value = "8,16,32,64,128")]
    pub sizes: Vec<usize>,
    /// PNG bit depths (8, 16).
    #[arg(long, value_delimiter = ',', default_value = "8,16")]
    pub bit_depths: Vec<u8>,
    /// Light directions, and again view directions, of the comparison (a Fibonacci set up
    /// to 80°; the pairs are their product).
    #[arg(long, default_value_t = 32)]
    pub directions: usize,
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct Report {
    file: String,
    texels: [usize; 2],
    pairs: usize,
    /// The fit's own size at 16 bits: what every other row is compared with.
    baseline: Fidelity,
    rows: Vec<Fidelity>,
    /// The fit's own size with one map at 8 bits and the others at 16, for each map:
    /// which map's quantization costs what (`only_8_bit` names it).
    by_map: Vec<Fidelity>,
}

pub fn run(a: ExportBenchArgs) -> Result<ExitCode> {
    if a.directions == 0 {
        bail!("--directions 0: the comparison needs at least one direction (e.g. 32)");
    }
    if let Some(b) = a.bit_depths.iter().find(|b| !matches!(b, 8 | 16)) {
        bail!("--bit-depths {b}: PNG textures are written with 8 or 16 bits");
    }
    if a.sizes.contains(&0) {
        bail!("--sizes 0: a texture needs at least one texel");
    }
    let g = Gbtf::read(&a.file).with_context(|| format!("reading {}", a.file.display()))?;
    let dirs = fidelity::directions(a.directions);
    let measure = |setting: fidelity::Setting| {
        fidelity::measure(&g, &a.file, setting, &dirs).with_context(|| format!("measuring {}", a.file.display()))
    };
    let own = g.header.width.max(g.header.height);
    let baseline = measure(fidelity::Setting::export(None, 16))?;
    let mut sizes = a.sizes.clone();
    sizes.push(own);
    sizes.sort_unstable();
    sizes.dedup();
    let mut rows = Vec::new();
    for &s in &sizes {
        for &b in &a.bit_depths {
            let size = if s == own { None } else { Some(s) };
            rows.push(measure(fidelity::Setting::export(size, b))?);
            if s < own {
                // The prefilter's baseline: the same texture sampled bilinearly.
                rows.push(measure(fidelity::Setting::bilinear(size, b))?);
            }
        }
    }
    let by_map = fidelity::Map::ALL
        .iter()
        .map(|&m| measure(fidelity::Setting::map_at_8_bits(None, m)))
        .collect::<Result<Vec<_>>>()?;
    let report = Report {
        file: a.file.display().to_string(),
        texels: [g.header.width, g.header.height],
        pairs: dirs.len() * dirs.len(),
        baseline,
        rows,
        by_map,
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "{}: {} × {} texels, {} light × view pairs (θ ≤ {}°); error of the read-back textures against the fit",
        report.file,
        report.texels[0],
        report.texels[1],
        report.pairs,
        fidelity::MAX_THETA_DEG
    );
    println!(
        "{:>6} {:>4} {:>10} {:>9} {:>11} {:>10} {:>10} {:>10} {:>8}",
        "size", "bits", "PNG bytes", "rel RMS", "texel mean", "texel p99", "texel max", "footprint", "time s"
    );
    let line = |r: &Fidelity, tag: &str| {
        let footprint = r.footprint_rel_rms.map_or("–".to_string(), |f| format!("{f:.5}"));
        let how = if r.prefiltered {
            "  (prefiltered)"
        } else if r.footprint_rel_rms.is_some() {
            "  (bilinear)"
        } else {
            ""
        };
        println!(
            "{:>6} {:>4} {:>10} {:>9.5} {:>11.5} {:>10.5} {:>10.5} {:>10} {:>8.3}{how}{tag}",
            r.size, r.bit_depth, r.png_bytes, r.rel_rms, r.texel_mean, r.texel_p99, r.texel_max, footprint, r.seconds
        )
    };
    line(&report.baseline, "  (baseline: the fit's own size, 16 bits)");
    for r in &report.rows {
        line(r, "");
    }
    println!("one map at 8 bits, the others at 16 (the fit's own size):");
    for r in &report.by_map {
        line(r, &format!("  ({} at 8 bits)", r.only_8_bit.map_or("", |m| m.name())));
    }
    Ok(ExitCode::SUCCESS)
}
