//! `gonio fit DATASET|FILE --model M`: fit an analytic BRDF model to a homogeneous sample's
//! averaged BRDF, or to every texel (`--per-texel`, McAllister's scaled Lafortune SBRDF),
//! and report the parameters, the residual and where the model fails (see `gonio_btf::fit`,
//! docs/guide/fitting.md).

use anyhow::{anyhow, Context, Result};
use gonio_btf::compress::{CompressedBtf, DatasetViews};
use gonio_btf::fit::data::{load_csv, load_dataset, WhiteRef};
use gonio_btf::fit::lm::LmOptions;
use gonio_btf::fit::texel::{fit_texels, TexelSummary};
use gonio_btf::fit::{fit, Band, FitOptions, FitReport, ModelKind, Space};
use serde::Serialize;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct FitArgs {
    /// A gonio dataset directory, or a CSV table `theta_l,phi_l,theta_v,phi_v,r,g,b`
    /// (degrees, BRDF in 1/sr).
    pub input: PathBuf,
    /// lafortune | ward | cook-torrance | rough-conductor | gltf (metallic-roughness + normal;
    /// with --per-texel, what `gonio export` writes for renderers).
    #[arg(long)]
    pub model: String,
    /// Lobes (lafortune: cosine lobes; cook-torrance: Beckmann lobes).
    #[arg(long, default_value_t = 1)]
    pub lobes: usize,
    /// Fit every texel after the average (McAllister 2002's scaled Lafortune SBRDF, or
    /// glTF's model with --model gltf); reports it as a compression method (ratio, PSNR).
    #[arg(long)]
    pub per_texel: bool,
    /// A dataset of the white standard over the same sweep and size: calibrates values that
    /// are not BRDF values (e.g. `gonio sim btf` output).
    #[arg(long)]
    pub white: Option<PathBuf>,
    /// The white standard's albedo (the simulator's `white-standard` is 0.9).
    #[arg(long, default_value_t = 0.9)]
    pub white_albedo: f64,
    /// Residual space: `log` (relative error) or `cosine` (f·cos θ_l, absolute).
    #[arg(long, default_value = "log")]
    pub space: String,
    /// Deterministic starts (lobe widths from wide to narrow).
    #[arg(long, default_value_t = 8)]
    pub starts: usize,
    /// Levenberg–Marquardt iteration cap per start.
    #[arg(long, default_value_t = 100)]
    pub iterations: usize,
    /// Iteration cap per texel with --per-texel (each starts from the average's fit).
    #[arg(long, default_value_t = 30)]
    pub texel_iterations: usize,
    /// Write the result: `F.gbtf` (with --per-texel) the SVBRDF as a `.gbtf` that `gonio
    /// reconstruct`, `gonio render` and `gonio view` decode; any other name the full result
    /// as JSON (with --per-texel: every texel's parameters).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
}

/// The per-texel fit as a compression method, in `gonio compress`'s terms.
#[derive(Serialize)]
struct TexelResult {
    #[serde(flatten)]
    summary: TexelSummary,
    /// Raw 8-bit size of the dataset's grid (`lights · views · W · H · 3` bytes).
    raw_bytes: usize,
    /// Size of the SVBRDF's `.gbtf` (method `svbrdf`, as `--out F.gbtf` writes it).
    stored_bytes: usize,
    /// `raw_bytes / stored_bytes`.
    ratio: f64,
    /// The `.gbtf`'s decoder against the dataset's images, 8-bit sRGB scale /255 (as
    /// `gonio compress`).
    psnr_8bit_db: f64,
    rmse_8bit: f64,
    mean_abs_8bit: f64,
    max_8bit: f64,
    rmse_linear: f64,
    /// Against `truth/` images where the dataset has them (acquisitions with
    /// `--store-truth`; a `gonio sim btf` dataset is the truth itself).
    psnr_truth_8bit_db: Option<f64>,
    rmse_truth_8bit: Option<f64>,
    /// The measured images against `truth/`: the noise floor.
    psnr_measured_vs_truth_8bit_db: Option<f64>,
    decode_ms_per_image: f64,
    fit_seconds: f64,
}

#[derive(Serialize)]
struct Output {
    input: String,
    values: String,
    calibrated_by: Option<PathBuf>,
    fit: FitReport,
    fit_seconds: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    per_texel: Option<TexelResult>,
}

/// The per-texel glTF fit of a dataset with the default options (`gonio export DATASET`
/// fits first): the `.gbtf` that `gonio fit DATASET --model gltf --per-texel --out F.gbtf`
/// writes, and the texels' summary.
pub(super) fn fit_gltf(
    dataset: &std::path::Path,
    white: Option<&WhiteRef>,
    texel_iterations: usize,
) -> Result<(gonio_btf::compress::Gbtf, TexelSummary)> {
    let input = dataset.display().to_string();
    let loaded = load_dataset(dataset, white)?;
    let report = fit(&loaded.averaged(), &FitOptions::new(ModelKind::Gltf), &input)?;
    let (svbrdf, summary) = fit_texels(&loaded, &report, Space::Log, texel_iterations.max(1))?;
    let ds = DatasetViews::open(dataset).with_context(|| format!("re-opening {input}"))?;
    let mut gbtf = svbrdf
        .to_gbtf(&ds)
        .with_context(|| format!("storing the SVBRDF of {input}"))?;
    gbtf.header.source["calibrated_by"] = serde_json::to_value(&loaded.calibrated_by)?;
    store_average_fit(&mut gbtf, &report, dataset)?;
    Ok((gbtf, summary))
}

/// Store the averaged fit (the one the per-texel fit starts from) in a glTF `.gbtf`'s
/// header as `source.average_fit`, with the SHA-256 of the dataset's journal: the
/// averaged-BRDF exports (`gonio export --format rgl-bsdf | merl`) read it instead of
/// fitting again. Other models store nothing.
fn store_average_fit(
    gbtf: &mut gonio_btf::compress::Gbtf,
    report: &FitReport,
    dataset: &std::path::Path,
) -> Result<()> {
    use gonio_btf::export::average::AverageFit;
    let gonio_brdf::BrdfModel::Gltf {
        base_color,
        metallic,
        roughness,
        normal,
        anisotropy_strength,
        anisotropy_rotation,
    } = report.brdf
    else {
        return Ok(());
    };
    let journal = dataset.join(gonio_dataset::store::JOURNAL_FILE);
    let sha = match std::fs::read(&journal) {
        Ok(bytes) => {
            use sha2::Digest;
            Some(format!("{:x}", sha2::Sha256::digest(&bytes)))
        }
        Err(_) => None,
    };
    let fit = AverageFit {
        model: "gltf".into(),
        base_color,
        metallic,
        roughness,
        normal,
        anisotropy: gonio_brdf::gltf::anisotropy_vector(anisotropy_strength, anisotropy_rotation),
        rel_rms: report.rel_rms,
        observations: report.observations,
        dataset_journal_sha256: sha,
    };
    gbtf.header.source["average_fit"] = serde_json::to_value(fit)?;
    Ok(())
}

/// `flag`'s value as a model, or an error naming the flag and the models there are.
pub fn parse_model(flag: &str, s: &str) -> Result<ModelKind> {
    ModelKind::parse(s).ok_or_else(|| {
        anyhow!(
            "{flag} {s}: unknown model; use one of {}",
            ModelKind::ALL.map(|k| k.name()).join(", ")
        )
    })
}

pub fn run(a: FitArgs) -> Result<ExitCode> {
    let kind = parse_model("--model", &a.model)?;
    let space = Space::parse(&a.space).ok_or_else(|| anyhow!("--space {}: use `log` or `cosine`", a.space))?;
    let opts = FitOptions {
        kind,
        lobes: a.lobes,
        space,
        starts: a.starts,
        lm: LmOptions {
            max_iterations: a.iterations,
            ..Default::default()
        },
    };
    opts.check()?;
    if a.per_texel && !matches!(kind, ModelKind::Lafortune | ModelKind::Gltf) {
        return Err(anyhow!(
            "--per-texel with --model {}: the per-texel fit is McAllister's scaled Lafortune SBRDF (--model \
             lafortune) or glTF's metallic-roughness model with a normal per texel (--model gltf)",
            kind.name()
        ));
    }
    let out_gbtf = a
        .out
        .as_ref()
        .is_some_and(|p| p.extension().and_then(|e| e.to_str()) == Some("gbtf"));
    if out_gbtf && !a.per_texel {
        return Err(anyhow!(
            "--out {}: a .gbtf holds the per-texel SVBRDF; add --per-texel, or give a .json name for the \
             averaged fit",
            a.out.as_ref().map(|p| p.display().to_string()).unwrap_or_default()
        ));
    }
    if a.per_texel && a.texel_iterations == 0 {
        return Err(anyhow!("--texel-iterations 0: at least one iteration is needed"));
    }
    let input = a.input.display().to_string();
    let white = a.white.as_ref().map(|d| WhiteRef {
        dir: d.clone(),
        albedo: a.white_albedo,
    });
    let (obs, loaded) = if a.input.is_dir() {
        let loaded = load_dataset(&a.input, white.as_ref())?;
        (loaded.averaged(), Some(loaded))
    } else if a.input.is_file() {
        if a.per_texel {
            return Err(anyhow!("{input}: --per-texel needs a dataset directory, not a table"));
        }
        if a.white.is_some() {
            return Err(anyhow!(
                "{input}: --white calibrates a dataset; a table holds BRDF values already"
            ));
        }
        (load_csv(&a.input)?, None)
    } else {
        return Err(anyhow!(
            "{input}: no such dataset directory or table file; give a gonio dataset or a .csv of \
             theta_l,phi_l,theta_v,phi_v,r,g,b"
        ));
    };
    let t0 = Instant::now();
    let report = fit(&obs, &opts, &input)?;
    let fit_seconds = t0.elapsed().as_secs_f64();
    let mut texel_fit = None;
    let per_texel = match (&loaded, a.per_texel) {
        (Some(loaded), true) => {
            let t1 = Instant::now();
            let (svbrdf, summary) = fit_texels(loaded, &report, space, a.texel_iterations)?;
            let secs = t1.elapsed().as_secs_f64();
            let ds = DatasetViews::open(&a.input).with_context(|| format!("re-opening {input}"))?;
            let mut gbtf = svbrdf
                .to_gbtf(&ds)
                .with_context(|| format!("storing the SVBRDF of {input}"))?;
            gbtf.header.source["calibrated_by"] = serde_json::to_value(&loaded.calibrated_by)?;
            store_average_fit(&mut gbtf, &report, &a.input)?;
            if let Some(path) = a.out.as_ref().filter(|_| out_gbtf) {
                // `source.dataset` as seen from the file's directory, `source.dataset_sha256`
                // beside it (`gonio_dataset::store::provenance`).
                let dir = gonio_dataset::store::provenance::output_dir(path);
                super::common::record_input(&mut gbtf.header.source, "dataset", &a.input, &dir)?;
                if let Some(w) = &a.white {
                    super::common::record_input(&mut gbtf.header.source, "calibrated_by", w, &dir)?;
                }
            }
            let stored = gbtf.to_bytes().context("encoding the SVBRDF's .gbtf")?.len();
            let decoder = CompressedBtf::new(gbtf.clone()).context("decoding the SVBRDF's .gbtf")?;
            let ev = gonio_btf::compress::evaluate(&ds, &decoder)
                .with_context(|| format!("decoding the SVBRDF of {input}"))?;
            let raw = svbrdf.lights_deg.len() * svbrdf.views_deg.len() * svbrdf.width * svbrdf.height * 3;
            let r = TexelResult {
                raw_bytes: raw,
                stored_bytes: stored,
                ratio: raw as f64 / stored as f64,
                psnr_8bit_db: ev.stats.psnr_8bit(),
                rmse_8bit: ev.stats.rmse_8bit(),
                mean_abs_8bit: ev.stats.mean_abs_8bit(),
                max_8bit: ev.stats.max_8bit,
                rmse_linear: ev.stats.rmse_linear(),
                psnr_truth_8bit_db: ev.truth.as_ref().map(|t| t.reconstruction.psnr_8bit()),
                rmse_truth_8bit: ev.truth.as_ref().map(|t| t.reconstruction.rmse_8bit()),
                psnr_measured_vs_truth_8bit_db: ev.truth.as_ref().map(|t| t.measurement.psnr_8bit()),
                decode_ms_per_image: 1e3 * ev.decode_seconds_per_image,
                fit_seconds: secs,
                summary,
            };
            if out_gbtf {
                let path = a.out.as_ref().expect("checked above");
                gbtf.write(path)
                    .with_context(|| format!("writing {}", path.display()))?;
            }
            texel_fit = Some(svbrdf);
            Some(r)
        }
        _ => None,
    };
    let out = Output {
        input: input.clone(),
        values: loaded
            .as_ref()
            .map_or_else(|| "BRDF (1/sr), table".to_string(), |l| l.values.clone()),
        calibrated_by: loaded.as_ref().and_then(|l| l.calibrated_by.clone()),
        fit: report,
        fit_seconds,
        per_texel,
    };
    if let Some(path) = a.out.as_ref().filter(|_| !out_gbtf) {
        let mut v = serde_json::to_value(&out)?;
        // The file names its input as seen from its own directory, with the input's SHA-256
        // (`input`, `input_sha256`; `gonio_dataset::store::provenance`); --json keeps the path as given.
        let dir = gonio_dataset::store::provenance::output_dir(path);
        super::common::record_input(&mut v, "input", &a.input, &dir)?;
        if let Some(w) = &a.white {
            super::common::record_input(&mut v, "calibrated_by", w, &dir)?;
        }
        if let Some(s) = &texel_fit {
            v["per_texel"]["parameter_names"] =
                serde_json::to_value(s.family.params.iter().map(|p| &p.name).collect::<Vec<_>>())?;
            v["per_texel"]["parameters"] = serde_json::to_value(&s.params)?;
            v["per_texel"]["gain"] = serde_json::to_value(&s.gain)?;
        }
        std::fs::write(path, serde_json::to_string_pretty(&v)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&out)?);
    } else {
        print_text(&out);
    }
    Ok(ExitCode::SUCCESS)
}

fn print_bands(title: &str, bands: &[Band]) {
    println!("  {title}");
    println!("    {:<24} {:>6} {:>9} {:>9}", "band", "n", "rel RMS", "bias %");
    for b in bands {
        println!(
            "    {:<24} {:>6} {:>9.4} {:>+9.1}",
            b.label,
            b.observations,
            b.rel_rms,
            100.0 * (b.log_bias.exp() - 1.0)
        );
    }
}

fn print_text(o: &Output) {
    let r = &o.fit;
    println!(
        "{}: {} ({} lobe{}), {} space, {} observations{}",
        o.input,
        r.model.name(),
        r.lobes,
        if r.lobes == 1 { "" } else { "s" },
        match r.space {
            Space::Log => "log",
            Space::Cosine => "cosine-weighted",
        },
        r.observations,
        if r.saturated_excluded > 0 {
            format!(" ({} saturated left out)", r.saturated_excluded)
        } else {
            String::new()
        }
    );
    println!(
        "  best of {} starts: start {}, {} after {} iterations ({:.2} s)",
        r.starts.len(),
        r.best_start,
        r.stop.reason(),
        r.iterations,
        o.fit_seconds
    );
    println!("  parameters:");
    for (n, v) in &r.params {
        println!("    {n:<24} {v:.6}");
    }
    if !r.at_bounds.is_empty() {
        println!("  on a bound (not determined by the data): {}", r.at_bounds.join(", "));
    }
    println!(
        "  residual: relative RMS (cosine-weighted) {:.4}, log RMS {:.4}",
        r.rel_rms, r.log_rms
    );
    if let Some(a) = &r.anisotropy {
        println!(
            "  anisotropy (KHR_materials_anisotropy): relative RMS {:.4} isotropic, {:.4} anisotropic (strength \
             {:.3} at {:.1}°): {}",
            a.isotropic_rel_rms,
            a.anisotropic_rel_rms,
            a.strength,
            a.rotation_deg,
            if a.kept {
                format!("kept (≥ {:.0} % lower)", 100.0 * a.margin)
            } else {
                format!("not kept (needs ≥ {:.0} % lower)", 100.0 * a.margin)
            }
        );
    }
    print_bands("by max(θ_l, θ_v):", &r.by_elevation);
    print_bands("by θ_h (distance from the mirror direction):", &r.by_half_angle);
    if r.failures.is_empty() {
        println!("  where it fails: no band is off by more than 10 % on average");
    } else {
        println!("  where it fails:");
        for f in &r.failures {
            println!("    {f}");
        }
    }
    if let Some(t) = &o.per_texel {
        println!(
            "  per texel: {} texels × {} parameters, {} bytes, ratio {:.1} : 1, PSNR {:.2} dB (8-bit){}, \
             mean relative RMS {:.4} (worst {:.4} at texel {}), {:.2} s fit, {:.3} ms/image decode",
            t.summary.texels,
            t.summary.params_per_texel,
            t.stored_bytes,
            t.ratio,
            t.psnr_8bit_db,
            t.psnr_truth_8bit_db
                .map_or(String::new(), |p| format!(", {p:.2} dB against truth/")),
            t.summary.mean_rel_rms,
            t.summary.max_rel_rms,
            t.summary.worst_texel,
            t.fit_seconds,
            t.decode_ms_per_image
        );
        if let (Some(n), Some(iso)) = (t.summary.anisotropic_texels, t.summary.mean_rel_rms_isotropic) {
            println!(
                "    {n} texels anisotropic (KHR_materials_anisotropy); mean relative RMS without anisotropy {iso:.4}"
            );
        }
        for (reason, n) in &t.summary.stops {
            println!("    {n} texels: {reason}");
        }
        if t.summary.not_converged > 0 {
            println!(
                "    {} texels not converged, filled from their neighbours and flagged (first: {:?})",
                t.summary.not_converged,
                &t.summary.not_converged_texels[..t.summary.not_converged_texels.len().min(10)]
            );
        }
        if t.summary.texels_without_data > 0 {
            println!(
                "    {} texels without data (kept the average)",
                t.summary.texels_without_data
            );
        }
    }
}
