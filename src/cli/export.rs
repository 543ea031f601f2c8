//! `gonio export` and `gonio verify`. A dataset's images go to UBO2003, NumPy or Zarr; a
//! fitted glTF SVBRDF (`gonio fit --per-texel --model gltf --out F.gbtf`, or a dataset,
//! fitted first) to the renderers' formats (`gonio_btf::export`: glTF, MaterialX, USD,
//! Mitsuba; docs/guide/export.md).

use anyhow::{Context, Result};
use gonio_dataset::store;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum ExportFormat {
    /// Bonn's UBO2003 zip of 8-bit sRGB JPEGs (readable by btf-extractor's Ubo2003).
    Ubo2003,
    /// NumPy float32 array [N, H, W, 3] of the 8-bit sRGB values, plus OUT.json index.
    Npy,
    /// Zarr v3 store: float16 [view, light, y, x, channel], one view per shard, one image
    /// per inner chunk, NaN where a pair is missing (needs the cargo feature `zarr`).
    Zarr,
    /// glTF 2.0 metallic-roughness + normal map: OUT.glb (one file) or a folder (needs the
    /// cargo feature `btf`, like the three below).
    Gltf,
    /// MaterialX standard_surface with image nodes: a folder.
    Materialx,
    /// OpenUSD UsdPreviewSurface (.usda and textures): a folder.
    Usd,
    /// Mitsuba 3 scene (principled in a normalmap, bitmap textures): a folder.
    Mitsuba,
    /// The averaged, isotropic BRDF as an RGL tensor file for Mitsuba 3's `measured`
    /// plugin: OUT.bsdf (--size N: grid side, default 64).
    RglBsdf,
    /// The averaged, isotropic BRDF as a MERL binary: OUT.binary and OUT.binary.json.
    Merl,
}

impl ExportFormat {
    /// The formats of a fitted material (the others export a dataset's images).
    fn is_material(self) -> bool {
        matches!(
            self,
            ExportFormat::Gltf
                | ExportFormat::Materialx
                | ExportFormat::Usd
                | ExportFormat::Mitsuba
                | ExportFormat::RglBsdf
                | ExportFormat::Merl
        )
    }
}

#[derive(clap::Args, Debug)]
pub struct ExportArgs {
    /// The dataset directory; for gltf, materialx, usd and mitsuba also a glTF fit
    /// (`gonio fit --per-texel --model gltf --out F.gbtf`).
    pub dir: PathBuf,
    #[arg(long, value_enum)]
    pub format: ExportFormat,
    /// Output file (a directory for --format zarr, materialx, mitsuba; a .glb or a
    /// directory for gltf; a .usdz or a directory for usd).
    pub out: PathBuf,
    /// Material formats: texture side in texels (default: the fit's resolution); rgl-bsdf:
    /// the side of its grids (default 64).
    #[arg(long)]
    pub size: Option<usize>,
    /// Material formats, a --size below the fit's: sample the fit bilinearly between
    /// texel centres instead of prefiltering each texel's footprint (averages, and the
    /// normals' spread added to the roughness; docs/guide/export.md).
    #[arg(long)]
    pub no_prefilter: bool,
    /// Texture formats (gltf, materialx, usd, mitsuba): bits per PNG sample, 8 or 16.
    #[arg(long, default_value_t = 8, value_parser = parse_bit_depth)]
    pub bit_depth: u8,
    /// Material formats: export values that are not radiometrically calibrated, labelled so.
    #[arg(long)]
    pub allow_uncalibrated: bool,
    /// Material formats with a DATASET: the white-standard dataset that calibrates it
    /// (as `gonio fit --white`).
    #[arg(long)]
    pub white: Option<PathBuf>,
    /// The white standard's albedo (as `gonio fit --white-albedo`).
    #[arg(long, default_value_t = 0.9)]
    pub white_albedo: f64,
    /// Material formats with a DATASET: LM iteration cap per texel of the fit.
    #[arg(long, default_value_t = 30)]
    pub texel_iterations: usize,
    /// Zarr only: write the shards of views of part I of N (1-based) into OUT; N such
    /// processes fill one store, equal byte for byte to a single-process export.
    #[arg(long)]
    pub shard: Option<gonio_dataset::shard::Shard>,
    /// Zarr only: replace an existing Zarr store at OUT.
    #[arg(long)]
    pub force: bool,
    /// Zarr only: also write the mean image over all exported pairs (NaN-mean of the
    /// stored float16 values, in float64) as a NumPy float64 array [H, W, 3].
    #[arg(long, value_name = "NPY")]
    pub mean_image: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
}

/// `--bit-depth`: 8 or 16.
fn parse_bit_depth(s: &str) -> std::result::Result<u8, String> {
    match s {
        "8" => Ok(8),
        "16" => Ok(16),
        _ => Err(format!("{s}: PNG textures have 8 or 16 bits per sample")),
    }
}

#[derive(clap::Args, Debug)]
pub struct VerifyArgs {
    pub dir: PathBuf,
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: ExportArgs) -> Result<ExitCode> {
    if args.format.is_material() {
        if args.shard.is_some() || args.force || args.mean_image.is_some() {
            anyhow::bail!(
                "--shard, --force and --mean-image apply to --format zarr only; a material export is one \
                 process and replaces nothing (remove OUT first)"
            );
        }
        return run_material(args);
    }
    if args.size.is_some() || args.allow_uncalibrated || args.white.is_some() || args.bit_depth != 8 {
        anyhow::bail!(
            "--size, --allow-uncalibrated, --white and --bit-depth apply to the material formats (gltf, materialx, \
             usd, mitsuba, rgl-bsdf, merl)"
        );
    }
    if let ExportFormat::Zarr = args.format {
        return run_zarr(args);
    }
    if args.shard.is_some() || args.force || args.mean_image.is_some() {
        anyhow::bail!("--shard, --force and --mean-image apply to --format zarr only");
    }
    let report = match args.format {
        ExportFormat::Ubo2003 => store::export_ubo2003(&args.dir, &args.out),
        ExportFormat::Npy => store::export_npy(&args.dir, &args.out),
        ExportFormat::Zarr
        | ExportFormat::Gltf
        | ExportFormat::Materialx
        | ExportFormat::Usd
        | ExportFormat::Mitsuba
        | ExportFormat::RglBsdf
        | ExportFormat::Merl => {
            unreachable!("handled above")
        }
    }
    .with_context(|| format!("exporting {} to {}", args.dir.display(), args.out.display()))?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "{}: {} images exported ({} with a substituted light direction), {} skipped measurements left out; {} bytes",
            report.path.display(),
            report.entries,
            report.substituted,
            report.skipped,
            report.bytes
        );
        if let Some(sidecar) = &report.sidecar {
            println!("index: {}", sidecar.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// A fitted glTF SVBRDF (or a dataset, fitted first) to a renderer's format.
#[cfg(feature = "btf")]
fn run_material(args: ExportArgs) -> Result<ExitCode> {
    use gonio_btf::compress::Gbtf;
    use gonio_btf::export::{write, ExportOptions, Format, Material};
    let format = match args.format {
        ExportFormat::Gltf => Format::Gltf,
        ExportFormat::Materialx => Format::Materialx,
        ExportFormat::Usd => Format::Usd,
        ExportFormat::Mitsuba => Format::Mitsuba,
        ExportFormat::RglBsdf => Format::RglBsdf,
        ExportFormat::Merl => Format::Merl,
        _ => unreachable!("material formats only"),
    };
    // Refuse a wrong output name before reading or fitting anything.
    let layout = format.check_out(&args.out)?;
    let out_dir = match layout {
        gonio_btf::export::Layout::Folder => args.out.clone(),
        gonio_btf::export::Layout::File => gonio_dataset::store::provenance::output_dir(&args.out),
    };
    let input = args.dir.display().to_string();
    let mut fitted = None;
    let gbtf = if args.dir.is_dir() {
        let white = args.white.as_ref().map(|d| gonio_btf::fit::data::WhiteRef {
            dir: d.clone(),
            albedo: args.white_albedo,
        });
        let (g, summary) = super::fit::fit_gltf(&args.dir, white.as_ref(), args.texel_iterations)
            .with_context(|| format!("fitting {input} (glTF model, per texel) before the export"))?;
        fitted = Some(summary);
        g
    } else if args.dir.is_file() {
        if args.white.is_some() {
            anyhow::bail!("{input}: --white calibrates a dataset before its fit; this file is fitted already");
        }
        Gbtf::read(&args.dir).with_context(|| format!("reading {input}"))?
    } else {
        anyhow::bail!("{input}: no such dataset directory or .gbtf file");
    };
    if format.is_average() {
        if args.bit_depth != 8 {
            anyhow::bail!(
                "--bit-depth applies to the texture formats (gltf, materialx, usd, mitsuba); {} writes float tables",
                format.name()
            );
        }
        return write_average_cli(&args, format, &gbtf, fitted, &out_dir);
    }
    let opts = ExportOptions {
        size: args.size,
        allow_uncalibrated: args.allow_uncalibrated,
        bit_depth: args.bit_depth,
        prefilter: !args.no_prefilter,
    };
    let mut material = Material::from_gbtf(&gbtf, &args.dir, &opts)?;
    if let Some(fit) = material.provenance.get_mut("fit") {
        super::common::record_input(fit, "file", &args.dir, &out_dir)?;
    }
    relocate_inputs(
        &mut material.provenance,
        &gbtf,
        &args.dir,
        args.white.as_deref(),
        &out_dir,
    )?;
    for w in &material.warnings {
        tracing::warn!("{input}: {w}");
    }
    let report =
        write(&material, format, &args.out).with_context(|| format!("exporting {input} to {}", args.out.display()))?;
    if args.json {
        let mut v = serde_json::to_value(&report)?;
        if let Some(s) = fitted {
            v["fit"] = serde_json::to_value(s)?;
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "{}: {} ({} files, {} bytes), textures {}×{} over {} mm",
            report.out.display(),
            format.name(),
            report.files.len(),
            report.bytes,
            report.texture_texels[0],
            report.texture_texels[1],
            report.size_mm
        );
        for w in &report.warnings {
            println!("warning: {w}");
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Name the fitted dataset and the white standard that calibrated it in an export's
/// provenance object `obj` (keys `dataset`, `calibrated_by`) as seen from the export's
/// directory, each with `{key}_sha256` beside it (`gonio_dataset::store::provenance`). `input` is
/// what was exported: the dataset itself (fitted first, `white` its --white), or a `.gbtf`
/// whose `source` paths are relative to the `.gbtf`'s directory (older files: as typed).
#[cfg(feature = "btf")]
fn relocate_inputs(
    obj: &mut serde_json::Value,
    gbtf: &gonio_btf::compress::Gbtf,
    input: &std::path::Path,
    white: Option<&std::path::Path>,
    out_dir: &std::path::Path,
) -> Result<()> {
    use gonio_dataset::store::provenance::{output_dir, relative_path, resolve};
    if input.is_dir() {
        super::common::record_input(obj, "dataset", input, out_dir)?;
        if let Some(w) = white {
            super::common::record_input(obj, "calibrated_by", w, out_dir)?;
        }
        return Ok(());
    }
    for key in ["dataset", "calibrated_by"] {
        let Some(recorded) = gbtf.header.source.get(key).and_then(|d| d.as_str()) else {
            continue;
        };
        let path = resolve(&output_dir(input), recorded);
        let sha_key = format!("{key}_sha256");
        let sha = gbtf.header.source.get(&sha_key).cloned();
        if let Some(o) = obj.as_object_mut() {
            o.insert(key.into(), relative_path(out_dir, &path).into());
            if let Some(sha) = sha {
                o.insert(sha_key, sha);
            }
        }
    }
    Ok(())
}

/// `--format rgl-bsdf | merl`: the averaged fit of a `.gbtf` (or of the dataset fitted
/// first) as one isotropic BRDF.
#[cfg(feature = "btf")]
fn write_average_cli(
    args: &ExportArgs,
    format: gonio_btf::export::Format,
    gbtf: &gonio_btf::compress::Gbtf,
    fitted: Option<gonio_btf::fit::texel::TexelSummary>,
    out_dir: &std::path::Path,
) -> Result<ExitCode> {
    use gonio_btf::export::{average::AverageBrdf, write_average};
    let input = args.dir.display().to_string();
    if format == gonio_btf::export::Format::RglBsdf {
        if let Some(n) = args.size {
            gonio_btf::export::rgl::check_size(n).map_err(|e| anyhow::anyhow!("{input}: {e}"))?;
        }
    }
    let mut avg = AverageBrdf::from_gbtf(gbtf, &args.dir, args.allow_uncalibrated)?;
    if let Some(source) = avg.provenance.get_mut("source") {
        super::common::record_input(source, "fit_file", &args.dir, out_dir)?;
        relocate_inputs(source, gbtf, &args.dir, args.white.as_deref(), out_dir)?;
    }
    for w in &avg.warnings {
        tracing::warn!("{input}: {w}");
    }
    let report = write_average(&avg, format, args.size, &args.out)
        .with_context(|| format!("exporting the averaged BRDF of {input} to {}", args.out.display()))?;
    if args.json {
        let mut v = serde_json::to_value(&report)?;
        if let Some(s) = fitted {
            v["fit"] = serde_json::to_value(s)?;
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "{}: {} ({} files, {} bytes), averaged isotropic BRDF{}",
            report.out.display(),
            format.name(),
            report.files.len(),
            report.bytes,
            report
                .size
                .map(|n| format!(", {n}×{n} grids × 23 θ_i slices"))
                .unwrap_or_default()
        );
        for w in &report.warnings {
            println!("warning: {w}");
        }
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(not(feature = "btf"))]
fn run_material(_args: ExportArgs) -> Result<ExitCode> {
    anyhow::bail!(
        "this gonio was built without the processing of stored BTFs (cargo feature `btf`, on by default): the \
         material formats need it; rebuild without --no-default-features"
    )
}

#[cfg(feature = "zarr")]
fn run_zarr(args: ExportArgs) -> Result<ExitCode> {
    use store::export::zarr::{export_zarr, write_mean_npy, ZarrOptions};
    let opts = ZarrOptions {
        shard: args.shard,
        force: args.force,
        mean: args.mean_image.is_some(),
    };
    let (report, mean) = export_zarr(&args.dir, &args.out, &opts)
        .with_context(|| format!("exporting {} to Zarr {}", args.dir.display(), args.out.display()))?;
    let mut mean_json = serde_json::Value::Null;
    if let (Some(path), Some(mean)) = (&args.mean_image, &mean) {
        write_mean_npy(mean, path).with_context(|| format!("writing the mean image {}", path.display()))?;
        mean_json = serde_json::json!({ "path": path, "images": mean.images, "shape": [mean.height, mean.width, 3] });
    }
    if args.json {
        let mut v = serde_json::to_value(&report)?;
        v["mean_image"] = mean_json;
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!(
            "{}: [view, light, y, x, channel] = {:?} f16; views {}..{} written ({} images, {} files, {} bytes); \
             whole store: {} measured, {} substituted, {} isotropic, {} missing (NaN)",
            report.path.display(),
            report.shape,
            report.views_written[0],
            report.views_written[1],
            report.images_written,
            report.files_written,
            report.bytes_written,
            report.measured,
            report.substituted,
            report.isotropic,
            report.missing
        );
        if let Some(p) = &args.mean_image {
            println!("mean image: {}", p.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

#[cfg(not(feature = "zarr"))]
fn run_zarr(_args: ExportArgs) -> Result<ExitCode> {
    anyhow::bail!(
        "this gonio was built without Zarr support (cargo feature `zarr`, on by default): \
         rebuild with `cargo build --release --features zarr` (or without --no-default-features)"
    )
}

pub fn verify(args: VerifyArgs) -> Result<ExitCode> {
    let report = store::verify(&args.dir).with_context(|| format!("verifying {}", args.dir.display()))?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_verify(&report);
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

/// `gonio verify` for a person: what was checked, then each kind of problem, one line each.
fn print_verify(r: &store::VerifyReport) {
    println!(
        "{}: {} journal records ({} measured, {} substituted, {} skipped), {}; {} images and {} raw frames \
         match their SHA-256 ({} bytes hashed)",
        r.dir.display(),
        r.records,
        r.measured,
        r.substituted,
        r.skipped,
        if r.complete { "complete" } else { "incomplete" },
        r.images_ok,
        r.raw_ok,
        r.bytes_hashed
    );
    if r.references_ok > 0 {
        println!(
            "{} drift references (reference and dark frame) match their SHA-256",
            r.references_ok
        );
    }
    for d in &r.damaged {
        println!("damaged or missing: record {d}");
    }
    if let Some((line, why)) = &r.references_torn_line {
        println!("the last line ({line}) of references.jsonl is torn: {why} (a resume removes it)");
    }
    if !r.orphans.is_empty() {
        println!(
            "{} file(s) without a journal line (a resume removes them)",
            r.orphans.len()
        );
    }
    if !r.temp_files.is_empty() {
        println!(
            "{} leftover temporary file(s) (a resume removes them)",
            r.temp_files.len()
        );
    }
    if !r.duplicates.is_empty() {
        let d: Vec<String> = r.duplicates.iter().map(|i| i.to_string()).collect();
        println!("indices recorded more than once: {}", d.join(", "));
    }
    if let Some((line, why)) = &r.torn_line {
        println!("the journal's last line ({line}) is torn: {why}");
    }
    if r.manifest_stale {
        println!("the manifest's records differ from the journal's (the journal is the record)");
    }
}
