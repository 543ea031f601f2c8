//! `gonio compress` and `gonio reconstruct`.

use super::common::parse_angles;
use anyhow::{Context, Result};
use gonio_btf::compress::btf_ubo2014::{self, Precision};
use gonio_btf::compress::dfmf::{self, ColorModel, DfmfParams};
use gonio_btf::compress::interp::AnyModel;
use gonio_btf::compress::target::Goal;
use gonio_btf::compress::{self, CodecId, DatasetViews, Method, Params, Shard};
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
    /// DFMF as in Bonn's UBO2014 files: one full-matrix factorization per channel of a
    /// decorrelated colour model; written as a UBO2014 `.btf` (`--format btf`).
    Dfmf,
    /// Local PCA / PCMF: --clusters clusters of ABRDFs, -c eigen-ABRDFs each.
    LocalPca,
    /// Median-cut quantization of ABRDFs into --boxes boxes (index image + BRDF block).
    MedianCut,
    /// Homomorphic factorization per ABRDF (light × view × half-vector factors, log domain).
    Homomorphic,
    /// Normalized decomposition per ABRDF (Wynn): light row norms × view column means of
    /// each texel's lights × views matrix, per channel.
    Nd,
    /// SVD with J = -c terms per ABRDF: rank-J SVD of each texel's lights × views matrix.
    SvdJ,
    /// GSHD per ABRDF: half-vector × difference-vector factors (--half-bins θ bins, twice as
    /// many φ bins; --sweeps of alternating least squares).
    Gshd,
    /// Chained matrix factorization per ABRDF: the GSHD product times a rank -c SVD of the
    /// residual (ABRDF / GSHD) in light × view form.
    Cmf,
}

impl MethodArg {
    /// The registry's method (`gonio_btf::compress::registry`); the value's name is its
    /// [`CodecId::name`] (test `method_values_are_the_registry_names`).
    pub fn id(self) -> CodecId {
        match self {
            MethodArg::Pca => CodecId::Pca,
            MethodArg::Pvmf => CodecId::Pvmf,
            MethodArg::Dfmf => CodecId::Dfmf,
            MethodArg::LocalPca => CodecId::LocalPca,
            MethodArg::MedianCut => CodecId::MedianCut,
            MethodArg::Homomorphic => CodecId::Homomorphic,
            MethodArg::Nd => CodecId::Nd,
            MethodArg::SvdJ => CodecId::SvdJ,
            MethodArg::Gshd => CodecId::Gshd,
            MethodArg::Cmf => CodecId::Cmf,
        }
    }
}

/// How `--shard` splits `--method` with these arguments (the registry's fact).
pub(crate) fn shard_kind(method: MethodArg, args: &CompressArgs) -> Shard {
    compress::codec(method.id()).shard(&knobs(args))
}

/// The method `--method` names, with its knobs from the command line (`components`: -c).
fn method_of(m: MethodArg, args: &CompressArgs, components: usize) -> Method {
    match m {
        MethodArg::Pca => Method::Pca,
        MethodArg::Pvmf => Method::Pvmf,
        MethodArg::Dfmf => Method::Dfmf {
            color_model: color_model(args.color_model),
            chroma_components: args.chroma_components.unwrap_or(components),
        },
        MethodArg::LocalPca => Method::LocalPca {
            clusters: args.clusters,
            iters: args.iters,
            subspace: args.subspace,
            in_passes: args.in_passes,
        },
        MethodArg::MedianCut => Method::MedianCut {
            boxes: args.boxes,
            balanced: args.balanced,
            min_error_cut: args.min_error_cut,
        },
        MethodArg::Homomorphic => Method::Homomorphic {
            half_bins: args.half_bins,
            sweeps: args.sweeps.unwrap_or(20),
        },
        MethodArg::Nd => Method::Nd,
        MethodArg::SvdJ => Method::SvdJ,
        MethodArg::Gshd => Method::Gshd {
            theta_bins: args.half_bins,
            sweeps: args.sweeps.unwrap_or(200),
        },
        MethodArg::Cmf => Method::Cmf {
            theta_bins: args.half_bins,
            sweeps: args.sweeps.unwrap_or(200),
        },
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum FormatArg {
    /// gonio's own container (CRC-checked, self-describing).
    Gbtf,
    /// Bonn's UBO2014 DFMF `.btf`, readable by btf-extractor's `Ubo2014`.
    Btf,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum ColorModelArg {
    /// Linear R, G, B (UBO2014 colour model 0).
    Rgb,
    /// log luminance + chroma/luminance (UBO2014 colour model 11; the reader clamps to [0, 1]).
    LogYuv,
    /// CIELab (perceptual DFMF after Guthe et al. 2009): least squares in Lab is least
    /// ΔE*ab. `.gbtf` only.
    Lab,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum PrecisionArg {
    F16,
    F32,
}

#[derive(clap::Args, Debug, Clone)]
pub struct CompressArgs {
    /// The dataset directory.
    pub dataset: PathBuf,
    /// The method. Optional with --target-psnr (then every method of the search is tried).
    #[arg(long, value_enum, required_unless_present_any = ["target_psnr", "target_ratio"])]
    pub method: Option<MethodArg>,
    /// Pick the method, components and quantization giving the smallest .gbtf whose PSNR
    /// (8-bit sRGB, against the dataset's truth if it has one, else its images) is at
    /// least this many dB; `--method` restricts the search to one method. Every trial and
    /// the reason for the choice are in `--json` (`target`).
    #[arg(long, value_name = "DB", conflicts_with_all = ["components", "quantize", "format", "target_ratio"])]
    pub target_psnr: Option<f64>,
    /// Pick the method, components and quantization giving the highest PSNR (measured as
    /// for --target-psnr) among the .gbtf files at least R times smaller than the raw 8-bit
    /// images (ratio ≥ R : 1); `--method` restricts the search. Every trial and the reason
    /// are in `--json` (`target`).
    #[arg(long, value_name = "R", conflicts_with_all = ["components", "quantize", "format"])]
    pub target_ratio: Option<f64>,
    /// Components kept (per view for PVMF, in total for PCA, per cluster for local PCA,
    /// luminance for DFMF). Required by those methods; median cut and homomorphic
    /// factorization have no components and ignore it.
    #[arg(long, short = 'c')]
    pub components: Option<usize>,
    /// Output file: `.gbtf`, or UBO2014 `.btf` for `--method dfmf`.
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
    /// Local PCA: number of clusters k.
    #[arg(long, default_value_t = 8)]
    pub clusters: usize,
    /// Local PCA: maximum alternation rounds (assignment + per-cluster PCA).
    #[arg(long, default_value_t = 10)]
    pub iters: usize,
    /// Local PCA: dimension of the global PCA subspace the clustering runs in before the
    /// final full-space models (0: every round in the full ABRDF space, the original
    /// algorithm, ~10× slower at 81 × 81).
    #[arg(long, default_value_t = gonio_btf::compress::local_pca::DEFAULT_SUBSPACE)]
    pub subspace: usize,
    /// Local PCA: run the nine passes over the views that `--shard I/N` splits, in this
    /// one process: the file a sharded run merges to, byte for byte (exact sums; about 3×
    /// the fused encoder's time at 256², docs/guide/scale.md). Implied by --shard.
    #[arg(long)]
    pub in_passes: bool,
    /// Median cut: number of boxes (BRDFs).
    #[arg(long, default_value_t = 256)]
    pub boxes: usize,
    /// Median cut: split level by level (2^depth boxes) instead of the longest box first.
    #[arg(long)]
    pub balanced: bool,
    /// Median cut: cut where the two halves' squared error is smallest, not at the median.
    #[arg(long)]
    pub min_error_cut: bool,
    /// Homomorphic: bins of the half vector's polar angle (0: light × view factors only).
    /// GSHD and CMF: θ bins of the half and difference vectors (1–64; twice as many φ bins).
    #[arg(long, default_value_t = 16)]
    pub half_bins: usize,
    /// Homomorphic: backfitting sweeps of the least-squares fit (default 20). GSHD, CMF: at
    /// most this many alternating least-squares sweeps, fewer once converged (default 200).
    #[arg(long)]
    pub sweeps: Option<usize>,
    /// Output container: gonio's `.gbtf`, or Bonn's UBO2014 `.btf` (DFMF only). Default:
    /// `btf` for dfmf, `gbtf` otherwise.
    #[arg(long, value_enum)]
    pub format: Option<FormatArg>,
    /// DFMF: colour model of the factorized channels.
    #[arg(long, value_enum, default_value = "log-yuv")]
    pub color_model: ColorModelArg,
    /// DFMF: components of the two chroma channels (default: -c). Luminance gets -c.
    #[arg(long)]
    pub chroma_components: Option<usize>,
    /// DFMF: stored scalar type (f16 like Bonn's files, or f32).
    #[arg(long, value_enum, default_value = "f16")]
    pub precision: PrecisionArg,
    /// Store the factors quantized to this many bits per value (1–16; 8–12 is the useful
    /// range) with one scale per factor vector, entropy-coded by zstd (a version-2 .gbtf;
    /// index blocks stay exact). Default: plain f32. `.gbtf` only.
    #[arg(long, value_name = "BITS")]
    pub quantize: Option<u32>,
    /// Skip the error evaluation (a second pass reading every image).
    #[arg(long)]
    pub no_eval: bool,
    /// Compute only shard I of N (1-based; a contiguous range of views) and write that
    /// part to --out; `gonio merge` joins the parts into the file one process would have
    /// written, byte for byte. PVMF: one round (a `.gbtf` part). PCA and DFMF: one pass
    /// of the randomized SVD per round (a `.gpart`; `2 + --power-iters` rounds, each
    /// merged into the `--state` of the next; docs/guide/scale.md). Local PCA (with
    /// `--subspace d > 0`): 9 rounds the same way. A part is not evaluated (evaluate
    /// the merged file).
    #[arg(long)]
    pub shard: Option<gonio_dataset::shard::Shard>,
    /// PCA/DFMF/local PCA with --shard: the merged state of the previous pass (`gonio merge` of
    /// its `.gpart` parts); without it the shard runs the first pass.
    #[arg(long, requires = "shard", value_name = "STATE.gstate")]
    pub state: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct ReconstructArgs {
    /// A `.gbtf` or UBO2014 `.btf` file written by `gonio compress`.
    pub file: PathBuf,
    /// Light direction `θ,φ` in degrees; between measured directions the factor rows are
    /// interpolated (barycentric in the enclosing triangle of measured directions).
    #[arg(long, value_parser = parse_angles)]
    pub light: gonio_devices::Direction,
    /// View direction `θ,φ` in degrees (interpolated like --light).
    #[arg(long, value_parser = parse_angles)]
    pub view: gonio_devices::Direction,
    /// Compare with a reference image (.exr, linear), e.g. `gonio sim render --kind truth`.
    #[arg(long)]
    pub compare: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
    /// Output image: .png (8-bit sRGB), .exr (linear float) or .npy (float32 H × W × 3).
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Serialize, Debug, Clone)]
pub struct Report {
    pub method: &'static str,
    pub components: usize,
    /// `gbtf` or `ubo2014-btf`.
    pub format: &'static str,
    /// The method's parameters as stored in the file's header.
    pub params: serde_json::Value,
    /// Bits per stored factor value (`--quantize`); absent for plain f32.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub quantize_bits: Option<u32>,
    pub out: String,
    pub images_measured: usize,
    pub filled_pairs: usize,
    pub dataset_passes: usize,
    pub stored_bytes: u64,
    /// Lights · views · W · H · 3 (one 8-bit RGB image per grid pair).
    pub raw_8bit_bytes: u64,
    pub compression_ratio: f64,
    pub encode_seconds: f64,
    /// The remaining fields are absent with --no-eval.
    pub error_scale: &'static str,
    pub rmse_8bit: Option<f64>,
    pub mean_abs_8bit: Option<f64>,
    pub max_8bit: Option<f64>,
    pub psnr_8bit_db: Option<f64>,
    pub rmse_linear: Option<f64>,
    pub decode_seconds_per_image: Option<f64>,
    /// Against the simulator's ground truth (datasets acquired with --store-truth).
    pub truth: Option<TruthReport>,
    pub peak_memory_bytes: Option<u64>,
    /// Where the encode time went (PVMF: reader wait, factorization, views per path).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub encode_stages: Vec<compress::Stage>,
    /// `--target-psnr`: what was tried and why this file was chosen.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub target: Option<TargetReport>,
}

/// The search of `--target-psnr` (see `compress::target`).
#[derive(Serialize, Debug, Clone)]
pub struct TargetReport {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(crate) target_psnr_db: Option<f64>,
    /// `--target-ratio`: the ratio asked for and the byte budget it gives.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(crate) target_ratio: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(crate) budget_bytes: Option<u64>,
    /// `truth` or `dataset`.
    pub(crate) psnr_against: &'static str,
    pub(crate) reason: String,
    pub(crate) trials: Vec<compress::target::Trial>,
}

/// Errors against the simulator's ground truth; same scales as the main figures.
#[derive(Serialize, Debug, Clone)]
pub struct TruthReport {
    pub images: usize,
    pub rmse_8bit: f64,
    pub mean_abs_8bit: f64,
    pub max_8bit: f64,
    pub psnr_8bit_db: f64,
    pub rmse_linear: f64,
    /// The measurements themselves against truth: the floor set by noise and rectification.
    pub measured_rmse_8bit: f64,
    pub measured_rmse_linear: f64,
}

pub fn run(args: CompressArgs) -> Result<ExitCode> {
    if let (Some(shard), Some(m)) = (args.shard, args.method) {
        if let Shard::Passes(_) = shard_kind(m, &args) {
            return shard_pass(&args, shard);
        }
    }
    let r = compress_report(&args)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        print_report(&r);
    }
    Ok(ExitCode::SUCCESS)
}

/// One shard's pass of a sharded PCA, DFMF or local PCA (`--shard I/N [--state S]`): writes a
/// `.gpart` and says what to run next.
fn shard_pass(args: &CompressArgs, shard: gonio_dataset::shard::Shard) -> Result<ExitCode> {
    use compress::rsvd_shard::{run_shard, Output};
    if args.target_psnr.is_some() || args.target_ratio.is_some() {
        anyhow::bail!(
            "--shard runs one given method; --target-psnr/--target-ratio search in one process (leave out --shard)"
        );
    }
    let ds = DatasetViews::open(&args.dataset).with_context(|| format!("opening {}", args.dataset.display()))?;
    let c = args
        .components
        .context("--method pca|dfmf|local-pca needs -c (components)")?;
    let method = args.method.context("--method is required with --shard")?;
    // The same default format as one process (compress_report).
    let format = args.format.unwrap_or(match (method, args.color_model) {
        (MethodArg::Dfmf, ColorModelArg::Rgb | ColorModelArg::LogYuv) => FormatArg::Btf,
        _ => FormatArg::Gbtf,
    });
    let output = match (method, format) {
        (MethodArg::Dfmf, FormatArg::Btf) => {
            if args.quantize.is_some() {
                anyhow::bail!("--quantize applies to .gbtf files; UBO2014 .btf stores f16 or f32 (--precision)");
            }
            let (dfmf, precision, xml) = btf_job(args, &ds, c)?;
            Output::Btf { dfmf, precision, xml }
        }
        (_, FormatArg::Btf) => anyhow::bail!("--format btf (UBO2014 DFMF) is written by --method dfmf only"),
        (m, FormatArg::Gbtf) => Output::Gbtf {
            params: Params {
                method: match method_of(m, args, c) {
                    // A sharded local PCA always runs the nine passes.
                    Method::LocalPca {
                        clusters,
                        iters,
                        subspace,
                        ..
                    } => Method::LocalPca {
                        clusters,
                        iters,
                        subspace,
                        in_passes: true,
                    },
                    other => other,
                },
                components: c,
                seed: args.seed,
                oversample: args.oversample,
                power_iters: args.power_iters,
            },
            quantize: args.quantize,
        },
    };
    let t0 = Instant::now();
    let r = run_shard(&ds, output, shard, args.state.as_deref(), &args.out)
        .with_context(|| format!("shard {shard} of {}", args.dataset.display()))?;
    let seconds = t0.elapsed().as_secs_f64();
    if args.json {
        let mut v = serde_json::to_value(&r)?;
        v["seconds"] = serde_json::json!(seconds);
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "pass {}/{} of shard {shard} (views {}..{}) → {} ({} bytes) in {seconds:.2} s; next: `gonio merge` of all {} parts of this pass{}",
            r.pass + 1,
            r.passes,
            r.shard.first_view,
            r.shard.end_view,
            r.out.display(),
            r.bytes,
            r.shard.count,
            if r.last_pass { " gives the compressed file" } else { " gives the --state of the next pass" }
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// The DFMF parameters, precision and XML block of a `--format btf` compression: one
/// home for the single-process and the sharded run, so both write the same bytes.
fn btf_job(args: &CompressArgs, ds: &DatasetViews, c: usize) -> Result<(DfmfParams, Precision, String)> {
    let color_model = color_model(args.color_model);
    let precision = match args.precision {
        PrecisionArg::F16 => Precision::F16,
        PrecisionArg::F32 => Precision::F32,
    };
    let cc = args.chroma_components.unwrap_or(c);
    let params = DfmfParams {
        color_model,
        components: match color_model {
            ColorModel::Rgb => [c, c, c],
            _ => [c, cc, cc],
        },
        seed: args.seed,
        oversample: args.oversample,
        power_iters: args.power_iters,
    };
    let pjson = serde_json::json!({"method": "dfmf", "dfmf": params, "precision": precision});
    // The dataset as seen from the output's directory, and its SHA-256 (same bytes
    // wherever the files sit; `gonio_dataset::store::provenance`). A sharded pass's parts
    // name it absolute, as the job's header does: the merge makes it relative.
    let source = match args.shard {
        None => {
            let r = gonio_dataset::store::provenance::InputRef::new(
                &ds.dir,
                &gonio_dataset::store::provenance::output_dir(&args.out),
            )
            .with_context(|| format!("recording the input {} in the output", ds.dir.display()))?;
            format!("<source>{}</source><source_sha256>{}</source_sha256>", r.path, r.sha256)
        }
        Some(_) => {
            let sha = gonio_dataset::store::provenance::input_sha256(&ds.dir)
                .with_context(|| format!("recording the input {} in the output", ds.dir.display()))?;
            let abs = gonio_dataset::store::provenance::absolute(&ds.dir);
            format!("<source>{}</source><source_sha256>{sha}</source_sha256>", abs.display())
        }
    };
    let xml = format!("<gonio>{source}<params>{pjson}</params></gonio>");
    Ok((params, precision, xml))
}

/// Name the dataset in a fresh `.gbtf`'s `source` as seen from the output's directory,
/// with its SHA-256 beside it (`source.dataset`, `source.dataset_sha256`). A shard's part
/// names it absolute: `gonio merge` makes it relative to the merged file's directory.
fn record_dataset(gbtf: &mut compress::Gbtf, args: &CompressArgs) -> Result<()> {
    use gonio_dataset::store::provenance;
    if args.shard.is_some() {
        let sha = provenance::input_sha256(&args.dataset)
            .with_context(|| format!("recording the input {} in the output", args.dataset.display()))?;
        let abs = provenance::absolute(&args.dataset).display().to_string();
        provenance::record(&mut gbtf.header.source, "dataset", abs, sha);
        return Ok(());
    }
    super::common::record_input(
        &mut gbtf.header.source,
        "dataset",
        &args.dataset,
        &provenance::output_dir(&args.out),
    )
}

/// Compress, write, read back and evaluate: what `gonio compress` and `gonio bench
/// compress` report.
pub fn compress_report(args: &CompressArgs) -> Result<Report> {
    if args.shard.is_some()
        && (args.method.map(|m| shard_kind(m, args)) != Some(Shard::Views)
            || args.target_psnr.is_some()
            || args.target_ratio.is_some())
    {
        anyhow::bail!(
            "--shard splits --method pvmf by views, and pca, dfmf and local-pca by passes over the views; \
             other methods are compressed in one process (leave out --shard)"
        );
    }
    let t0 = Instant::now();
    let ds = DatasetViews::open(&args.dataset).with_context(|| format!("opening {}", args.dataset.display()))?;
    if let Some(p) = args.target_psnr {
        return target_report(args, &ds, Goal::Psnr(p), t0);
    }
    if let Some(r) = args.target_ratio {
        return target_report(args, &ds, Goal::Ratio(r), t0);
    }
    let method_arg = args.method.context("--method is required without --target-psnr")?;
    let format = args.format.unwrap_or(match (method_arg, args.color_model) {
        (MethodArg::Dfmf, ColorModelArg::Rgb | ColorModelArg::LogYuv) => FormatArg::Btf,
        _ => FormatArg::Gbtf,
    });
    if format == FormatArg::Btf && !matches!(method_arg, MethodArg::Dfmf) {
        anyhow::bail!("--format btf (UBO2014 DFMF) is written by --method dfmf only");
    }
    if format == FormatArg::Btf && args.quantize.is_some() {
        anyhow::bail!("--quantize applies to .gbtf files; UBO2014 .btf stores f16 or f32 (--precision)");
    }
    let needs_c = !matches!(
        method_arg,
        MethodArg::MedianCut | MethodArg::Homomorphic | MethodArg::Nd | MethodArg::Gshd
    );
    let components = match (args.components, needs_c) {
        (Some(c), _) => c,
        (None, false) => 1,
        (None, true) => {
            anyhow::bail!("this --method needs -c (components); only median-cut, homomorphic, nd and gshd do not")
        }
    };
    let params = Params {
        method: match method_arg {
            MethodArg::Dfmf if format == FormatArg::Btf => return dfmf_report(args, &ds, t0),
            m => method_of(m, args, components),
        },
        components,
        seed: args.seed,
        oversample: args.oversample,
        power_iters: args.power_iters,
    };
    let (mut gbtf, mut info) = match args.shard {
        Some(shard) => compress::compress_pvmf_shard(&ds, &params, shard),
        None => compress::compress(&ds, &params),
    }
    .with_context(|| format!("compressing {}", args.dataset.display()))?;
    if let Some(bits) = args.quantize {
        gbtf.quantize(bits).context("--quantize")?;
    }
    record_dataset(&mut gbtf, args)?;
    let stored = gbtf
        .write(&args.out)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let encode_seconds = t0.elapsed().as_secs_f64();
    drop(gbtf);

    let mut r = Report {
        method: params.method.name(),
        components: params.components,
        format: "gbtf",
        params: serde_json::to_value(&params)?,
        quantize_bits: args.quantize,
        filled_pairs: info.filled,
        dataset_passes: info.passes,
        encode_stages: std::mem::take(&mut info.stages),
        ..report_base(args, &ds, stored, encode_seconds)
    };
    finish_report(args, &ds, &mut r)?;
    Ok(r)
}

/// The report fields that do not depend on the method, with the evaluation fields empty
/// (filled by [`finish_report`]); the callers set method, format, params, fill and stage
/// fields by struct update, so both file formats report the same way.
fn report_base(args: &CompressArgs, ds: &DatasetViews, stored: u64, encode_seconds: f64) -> Report {
    // conventions.md: ratio against the raw 8-bit size of the full grid (L · V · W · H · 3).
    let raw = (ds.n_lights() * ds.n_views() * ds.texels() * 3) as u64;
    Report {
        method: "",
        components: 0,
        format: "",
        params: serde_json::Value::Null,
        quantize_bits: None,
        out: args.out.display().to_string(),
        images_measured: ds.n_measured(),
        filled_pairs: 0,
        dataset_passes: 0,
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
        truth: None,
        peak_memory_bytes: None,
        encode_stages: Vec::new(),
        target: None,
    }
}

/// The knobs of `gonio compress`'s options that the registry's ladders and shard passes
/// read.
pub(crate) fn knobs(args: &CompressArgs) -> compress::Knobs {
    compress::Knobs {
        seed: args.seed,
        oversample: args.oversample,
        power_iters: args.power_iters,
        iters: args.iters,
        subspace: args.subspace,
        in_passes: args.in_passes,
        balanced: args.balanced,
        min_error_cut: args.min_error_cut,
        half_bins: args.half_bins,
        sweeps: args.sweeps,
    }
}

/// The search's ladders for `--method` (`compress::target::ladders`) with the knobs given.
fn ladders(method: Option<MethodArg>, args: &CompressArgs) -> Vec<Vec<Params>> {
    compress::target::ladders(method.map(MethodArg::id), &knobs(args))
}

fn target_report(args: &CompressArgs, ds: &DatasetViews, goal: Goal, t0: Instant) -> Result<Report> {
    let flag = match goal {
        Goal::Psnr(_) => "--target-psnr",
        Goal::Ratio(_) => "--target-ratio",
    };
    let ladders = ladders(args.method, args);
    if ladders.is_empty() {
        anyhow::bail!("{flag} searches the .gbtf methods; UBO2014 DFMF .btf is not searched (leave out --method dfmf)");
    }
    let choice = compress::target::search(ds, goal, &ladders)
        .with_context(|| format!("searching {} for {goal:?}", args.dataset.display()))?;
    let Some((gbtf, best)) = choice.best else {
        match goal {
            Goal::Psnr(target) => {
                let top = choice
                    .trials
                    .iter()
                    .filter_map(|t| t.psnr_8bit_db)
                    .fold(f64::NEG_INFINITY, f64::max);
                anyhow::bail!(
                    "no candidate reached {target} dB (best {top:.2} dB over {} trials); lower --target-psnr or \
                     give --method with more components",
                    choice.trials.len()
                );
            }
            Goal::Ratio(r) => {
                let top = choice.trials.iter().map(|t| t.ratio).fold(0.0, f64::max);
                anyhow::bail!(
                    "no candidate reached {r} : 1 (the smallest file tried gives {top:.1} : 1); lower --target-ratio"
                );
            }
        }
    };
    let mut gbtf = gbtf;
    record_dataset(&mut gbtf, args)?;
    let stored = gbtf
        .write(&args.out)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let reached = choice.trials.iter().filter(|t| t.meets_target).count();
    let what = format!(
        "{} with c = {}{} at {} bits, {:.2} dB, {} bytes ({:.1} : 1)",
        best.method,
        best.params.components,
        match best.params.method {
            Method::LocalPca { clusters, .. } => format!(", k = {clusters}"),
            Method::Dfmf {
                color_model,
                chroma_components,
            } => format!(" ({}, chroma c = {chroma_components})", color_model.name()),
            Method::Pca
            | Method::Pvmf
            | Method::MedianCut { .. }
            | Method::Homomorphic { .. }
            | Method::Nd
            | Method::SvdJ
            | Method::Gshd { .. }
            | Method::Cmf { .. }
            | Method::Svbrdf { .. }
            | Method::Gltf => String::new(),
        },
        best.bits,
        best.psnr_8bit_db.unwrap_or(f64::NAN),
        best.stored_bytes,
        best.ratio
    );
    let reason = match goal {
        Goal::Psnr(target) => format!(
            "smallest of the {reached} candidates (of {} tried) reaching {target} dB against the {}: {what}",
            choice.trials.len(),
            choice.against,
        ),
        Goal::Ratio(r) => format!(
            "highest PSNR against the {} of the {reached} candidates (of {} tried) at ≥ {r} : 1 (≤ {} bytes): {what}",
            choice.against,
            choice.trials.len(),
            choice.budget_bytes.unwrap_or(0),
        ),
    };
    let mut r = Report {
        method: best.method,
        components: best.params.components,
        format: "gbtf",
        params: serde_json::to_value(&best.params)?,
        quantize_bits: Some(best.bits),
        target: Some(TargetReport {
            target_psnr_db: match goal {
                Goal::Psnr(p) => Some(p),
                Goal::Ratio(_) => None,
            },
            target_ratio: match goal {
                Goal::Ratio(r) => Some(r),
                Goal::Psnr(_) => None,
            },
            budget_bytes: choice.budget_bytes,
            psnr_against: choice.against,
            reason,
            trials: choice.trials,
        }),
        ..report_base(args, ds, stored, t0.elapsed().as_secs_f64())
    };
    finish_report(args, ds, &mut r)?;
    Ok(r)
}

/// Read the written file back (checks every CRC or length), evaluate it against the
/// dataset (and its truth), record peak memory.
fn finish_report(args: &CompressArgs, ds: &DatasetViews, r: &mut Report) -> Result<()> {
    if !args.no_eval && args.shard.is_none() {
        let model = AnyModel::open(&args.out).with_context(|| format!("reading {}", args.out.display()))?;
        let ev = compress::evaluate(ds, model.model()).context("evaluating the reconstruction")?;
        r.rmse_8bit = Some(ev.stats.rmse_8bit());
        r.mean_abs_8bit = Some(ev.stats.mean_abs_8bit());
        r.max_8bit = Some(ev.stats.max_8bit);
        r.psnr_8bit_db = Some(ev.stats.psnr_8bit());
        r.rmse_linear = Some(ev.stats.rmse_linear());
        r.decode_seconds_per_image = Some(ev.decode_seconds_per_image);
        r.truth = ev.truth.map(|t| TruthReport {
            images: t.images,
            rmse_8bit: t.reconstruction.rmse_8bit(),
            mean_abs_8bit: t.reconstruction.mean_abs_8bit(),
            max_8bit: t.reconstruction.max_8bit,
            psnr_8bit_db: t.reconstruction.psnr_8bit(),
            rmse_linear: t.reconstruction.rmse_linear(),
            measured_rmse_8bit: t.measurement.rmse_8bit(),
            measured_rmse_linear: t.measurement.rmse_linear(),
        });
    }
    r.peak_memory_bytes = compress::peak_memory_bytes();
    Ok(())
}

fn color_model(a: ColorModelArg) -> ColorModel {
    match a {
        ColorModelArg::Rgb => ColorModel::Rgb,
        ColorModelArg::LogYuv => ColorModel::LogYuv,
        ColorModelArg::Lab => ColorModel::Lab,
    }
}

fn dfmf_report(args: &CompressArgs, ds: &DatasetViews, t0: Instant) -> Result<Report> {
    let c = args.components.context("--method dfmf needs -c (components)")?;
    let (params, precision, xml) = btf_job(args, ds, c)?;
    let (model, info) = dfmf::encode(ds, &params).with_context(|| format!("compressing {}", args.dataset.display()))?;
    let pjson = serde_json::json!({"method": "dfmf", "dfmf": params, "precision": precision});
    let stored = btf_ubo2014::write(&args.out, &model, precision, &xml)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let encode_seconds = t0.elapsed().as_secs_f64();
    drop(model);
    let mut r = Report {
        method: "dfmf",
        components: c,
        format: "ubo2014-btf",
        params: pjson,
        filled_pairs: info.filled,
        dataset_passes: info.passes,
        ..report_base(args, ds, stored, encode_seconds)
    };
    finish_report(args, ds, &mut r)?;
    Ok(r)
}

fn print_report(r: &Report) {
    println!("method         {} c = {} → {}", r.method, r.components, r.out);
    if let Some(b) = r.quantize_bits {
        println!("stored         {b}-bit quantized factors, zstd (.gbtf version 2)");
    }
    if let Some(t) = &r.target {
        println!("chosen         {}", t.reason);
    }
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
    if let Some(t) = &r.truth {
        println!(
            "vs. truth      RMSE {:.5} (/255), PSNR {:.2} dB, linear RMSE {:.6}; measurements themselves: \
             RMSE {:.5} (/255), linear {:.6} ({} images)",
            t.rmse_8bit, t.psnr_8bit_db, t.rmse_linear, t.measured_rmse_8bit, t.measured_rmse_linear, t.images
        );
    }
    if let Some(p) = r.peak_memory_bytes {
        println!("peak memory    {} MiB", p / (1 << 20));
    }
}

pub fn reconstruct(args: ReconstructArgs) -> Result<ExitCode> {
    let any = AnyModel::open(&args.file).with_context(|| format!("reading {}", args.file.display()))?;
    let model = any.model();
    let (l, v) = (
        [args.light.theta_deg(), args.light.phi_deg()],
        [args.view.theta_deg(), args.view.phi_deg()],
    );
    let t0 = Instant::now();
    let (data, how) = compress::interp::reconstruct_at(model, l, v)
        .with_context(|| format!("reconstructing light {l:?}°, view {v:?}° from {}", args.file.display()))?;
    let decode_seconds = t0.elapsed().as_secs_f64();
    if let AnyModel::Gbtf(m) = &any {
        let filled = &m.header().filled;
        for &(li, _, _) in &how.lights {
            for &(vi, _, _) in &how.views {
                if filled.contains(&[li, vi]) {
                    eprintln!(
                        "warning: grid pair light {:?}°, view {:?}° was not measured; its image was filled from \
                         the nearest measured light before compression",
                        m.header().lights_deg[li],
                        m.header().views_deg[vi]
                    );
                }
            }
        }
    }
    let img = RgbImage {
        width: model.width(),
        height: model.height(),
        data,
    };
    let comparison = match &args.compare {
        Some(p) => {
            let reference = gonio_dataset::store::read_exr(p).with_context(|| format!("reading {}", p.display()))?;
            if (reference.width, reference.height) != (img.width, img.height) {
                anyhow::bail!(
                    "{} is {}×{}, the reconstruction is {}×{}",
                    p.display(),
                    reference.width,
                    reference.height,
                    img.width,
                    img.height
                );
            }
            let mut st = compress::ErrorStats::default();
            st.add(&reference.data, &img.data);
            Some(st)
        }
        None => None,
    };
    if args.out.extension().and_then(|e| e.to_str()) == Some("npy") {
        // Raw float32 (H, W, 3) for scripts (tests/interop/check_ubo2014.py).
        let mut bytes = gonio_dataset::store::export::npy_header(&[img.height, img.width, 3]);
        bytes.extend(img.data.iter().flat_map(|v| v.to_le_bytes()));
        gonio_dataset::store::atomic::write_atomic(&args.out, &bytes, None)
            .with_context(|| format!("writing {}", args.out.display()))?;
    } else {
        super::sim::write_image(&args.out, &img)?;
    }
    if args.json {
        let j = serde_json::json!({
            "out": args.out.display().to_string(),
            "light_deg": l,
            "view_deg": v,
            "interpolation": how,
            "decode_seconds": decode_seconds,
            "compare": comparison.as_ref().map(|st| serde_json::json!({
                "reference": args.compare.as_ref().map(|p| p.display().to_string()),
                "rmse_8bit": st.rmse_8bit(),
                "mean_abs_8bit": st.mean_abs_8bit(),
                "max_8bit": st.max_8bit,
                "psnr_8bit_db": st.psnr_8bit(),
                "rmse_linear": st.rmse_linear(),
            })),
        });
        println!("{}", serde_json::to_string_pretty(&j)?);
    } else {
        let fmt = |v: &[(usize, [f64; 2], f64)]| {
            v.iter()
                .map(|(_, d, w)| format!("{:.1},{:.1}° ×{w:.3}", d[0], d[1]))
                .collect::<Vec<_>>()
                .join(" + ")
        };
        println!(
            "{} {}: lights {}; views {}",
            args.out.display(),
            if how.exact { "(measured pair)" } else { "(interpolated)" },
            fmt(&how.lights),
            fmt(&how.views)
        );
        if let Some(st) = &comparison {
            println!(
                "vs. reference  RMSE {:.5} (/255), PSNR {:.2} dB, max {:.5}, linear RMSE {:.6}",
                st.rmse_8bit(),
                st.psnr_8bit(),
                st.max_8bit,
                st.rmse_linear()
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::ValueEnum;

    /// `--method` takes exactly the registry's encodable methods, under their names.
    #[test]
    fn method_values_are_the_registry_names() {
        let values: Vec<(String, CodecId)> = MethodArg::value_variants()
            .iter()
            .map(|m| (m.to_possible_value().unwrap().get_name().to_string(), m.id()))
            .collect();
        for (name, id) in &values {
            assert_eq!(name, id.name());
        }
        let mut ids: Vec<CodecId> = values.iter().map(|v| v.1).collect();
        ids.sort();
        assert_eq!(ids, compress::registry::encodable().collect::<Vec<_>>());
    }
}
