//! `gonio synthesize`: grow a compressed BTF to any size (thesis ch. 6) by tiling,
//! Efros–Leung, Wei–Levoy or image quilting on ABRDF features; the output is a `.gbtf` of
//! the input's kind (readable by `reconstruct`, `render`, `export`) plus its texel map.

use super::common::parse_size;
use anyhow::{bail, Context, Result};
use gonio_btf::compress::interp::AnyModel;
use gonio_btf::compress::CompressedBtf;
use gonio_btf::synthesize::exemplar::Exemplar;
use gonio_btf::synthesize::{self, features, SynthMethod, SynthParams};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

#[derive(clap::Args, Debug, Clone)]
pub struct SynthArgs {
    /// Method and its knobs (shared with `gonio bench synthesize`).
    #[arg(long, default_value = "quilting")]
    pub method: String,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Matching features: keep this many principal components (overrides --energy).
    #[arg(long)]
    pub k: Option<usize>,
    /// Matching features: the fewest principal components explaining this fraction of the
    /// ABRDF variance.
    #[arg(long, default_value_t = 0.95)]
    pub energy: f64,
    /// Quilting block edge in texels (default: exemplar side / 4, 4 ..= 64).
    #[arg(long)]
    pub block: Option<usize>,
    /// Quilting overlap in texels (default: block / 4).
    #[arg(long)]
    pub overlap: Option<usize>,
    /// Quilting: accept blocks within (1 + tolerance) of the best overlap error.
    #[arg(long, default_value_t = 0.1)]
    pub tolerance: f64,
    /// Efros–Leung window edge (odd).
    #[arg(long, default_value_t = 7)]
    pub window: usize,
    /// Efros–Leung acceptance ε (thesis eq. 78).
    #[arg(long, default_value_t = 0.1)]
    pub epsilon: f64,
    /// Wei–Levoy pyramid levels (default: down to ≥ 32 texels, at most 5).
    #[arg(long)]
    pub levels: Option<usize>,
    /// Wei–Levoy neighbourhood edge at the current level (odd; causal half used).
    #[arg(long, default_value_t = 7)]
    pub neighbourhood: usize,
    /// Wei–Levoy neighbourhood edge at the coarser level (odd).
    #[arg(long, default_value_t = 5)]
    pub parent_neighbourhood: usize,
    /// Wei–Levoy TSVQ leaf size.
    #[arg(long, default_value_t = 8)]
    pub leaf: usize,
    /// Wei–Levoy coherence κ: prefer the texel continuing a neighbour's source patch when
    /// its neighbourhood distance is within 1 + κ·2⁻ˡ of the tree's match (0 = the tree's
    /// match alone, as Wei & Levoy; see docs/guide/synthesis.md).
    #[arg(long, default_value_t = 1.0)]
    pub coherence: f64,
}

#[derive(clap::Args, Debug)]
pub struct SynthesizeArgs {
    /// A compressed BTF (`.gbtf` of PCA, PVMF, local PCA, median cut or homomorphic; a
    /// UBO2014 DFMF `.btf`), or a dataset directory (compressed in memory with PCA,
    /// `--components`, first).
    pub input: PathBuf,
    /// Dataset input only: PCA components of the in-memory model the synthesis gathers
    /// from (the output is that PCA model of the grown sample).
    #[arg(long, default_value_t = 16)]
    pub components: usize,
    /// Output size, `WxH` texels (at least the exemplar's).
    #[arg(long)]
    pub size: String,
    /// Output file of the input's kind (`.gbtf`; `.btf` for a `.btf` input); the texel map
    /// goes beside it as `<stem>.texelmap.png`.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub synth: SynthArgs,
    #[arg(long)]
    pub json: bool,
}

/// Open a compressed BTF that synthesis can gather rows from (a `.gbtf`, or a UBO2014
/// DFMF `.btf`), or say why not.
pub fn open_exemplar(path: &Path) -> Result<Exemplar> {
    if path.is_dir() {
        bail!(
            "{} is a dataset directory: synthesis matches ABRDFs through a compressed model; compress it \
             first (`gonio compress {} --method pca --out ex.gbtf`) and synthesize from the .gbtf",
            path.display(),
            path.display()
        );
    }
    Ok(
        match AnyModel::open(path).with_context(|| format!("reading {}", path.display()))? {
            AnyModel::Gbtf(m) => Exemplar::Gbtf(m),
            AnyModel::Dfmf(d) => Exemplar::Dfmf(d),
        },
    )
}

/// The output is a file of the exemplar's own kind: refuse an `--out` whose extension
/// names the other kind (a `.btf` exemplar writes a UBO2014 `.btf`, anything else a `.gbtf`).
fn check_out_extension(ex: &Exemplar, input: &Path, out: &Path) -> Result<()> {
    let ext = out.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase());
    let want = ex.extension();
    let other = if want == "btf" { "gbtf" } else { "btf" };
    if ext.as_deref() == Some(other) {
        bail!(
            "--out {}: the exemplar {} is a {} ({}), so the output is a .{want} of the same model; \
             name the output *.{want}",
            out.display(),
            input.display(),
            if want == "btf" { "UBO2014 DFMF .btf" } else { ".gbtf" },
            ex.model_name()
        );
    }
    Ok(())
}

impl SynthArgs {
    pub fn params(&self, width: usize, height: usize, ex_w: usize, ex_h: usize) -> Result<SynthParams> {
        let method = SynthMethod::parse(&self.method)?;
        let mut p = SynthParams::new(method, width, height, ex_w, ex_h);
        p.seed = self.seed;
        if let Some(b) = self.block {
            p.block = b;
            p.overlap = SynthParams::default_overlap(b);
        }
        if let Some(o) = self.overlap {
            p.overlap = o;
        }
        p.tolerance = self.tolerance;
        p.window = self.window;
        p.epsilon = self.epsilon;
        if let Some(l) = self.levels {
            p.levels = l;
        }
        p.neighbourhood = self.neighbourhood;
        p.parent_neighbourhood = self.parent_neighbourhood;
        p.leaf = self.leaf;
        p.coherence = self.coherence;
        Ok(p)
    }

    pub fn k_choice(&self) -> features::KChoice {
        match self.k {
            Some(k) => features::KChoice::Fixed(k),
            None => features::KChoice::Energy(self.energy),
        }
    }
}

/// A dataset input is first compressed to PCA with `c` components in memory: synthesis
/// gathers whole per-texel factor rows, which a dataset of images does not have, and an
/// output of raw images (6561 × 1024² texels: 41 GB as half floats) would not be a useful
/// file. What was done is reported as `from_dataset` in `--json`.
fn dataset_exemplar(dir: &Path, c: usize, out: &Path) -> Result<(CompressedBtf, serde_json::Value)> {
    if c == 0 {
        bail!(
            "--components 0: the in-memory PCA of dataset {} needs at least one component",
            dir.display()
        );
    }
    let ds =
        gonio_btf::compress::DatasetViews::open(dir).with_context(|| format!("opening dataset {}", dir.display()))?;
    let t0 = Instant::now();
    let params = gonio_btf::compress::Params::new(gonio_btf::compress::Method::Pca, c);
    let (mut gbtf, info) = gonio_btf::compress::compress(&ds, &params)
        .with_context(|| format!("compressing dataset {} to PCA c = {c}", dir.display()))?;
    // The in-memory model has no directory of its own: its `source.dataset` (the output's
    // `exemplar_source.dataset`) is relative to the output's directory, like `exemplar`.
    super::common::record_input(
        &mut gbtf.header.source,
        "dataset",
        dir,
        &gonio_dataset::store::provenance::output_dir(out),
    )?;
    let model = CompressedBtf::new(gbtf)?;
    let note = serde_json::json!({
        "dataset": dir.display().to_string(),
        "model": "pca",
        "components": c,
        "filled_pairs": info.filled,
        "seconds": t0.elapsed().as_secs_f64(),
        "note": format!("the output is a PCA c = {c} model; its fidelity to the dataset is that of \
                         `gonio compress {} --method pca -c {c}`", dir.display()),
    });
    Ok((model, note))
}

pub fn run(a: SynthesizeArgs) -> Result<ExitCode> {
    let (w, h) = parse_size(&a.size, 1..=usize::MAX).map_err(|e| anyhow::anyhow!("--size {e}"))?;
    let (model, from_dataset) = if a.input.is_dir() {
        let (m, note) = dataset_exemplar(&a.input, a.components, &a.out)?;
        (Exemplar::Gbtf(m), Some(note))
    } else {
        (open_exemplar(&a.input)?, None)
    };
    let (ew, eh) = (model.width(), model.height());
    check_out_extension(&model, &a.input, &a.out)?;
    let p = a.synth.params(w, h, ew, eh)?;
    model.check_output(w, h, &a.input)?;
    let t0 = Instant::now();
    let emb = model
        .embed()
        .with_context(|| format!("embedding the ABRDFs of {}", a.input.display()))?;
    let feats = features::principal(&emb.image, a.synth.k_choice())?;
    let feature_seconds = t0.elapsed().as_secs_f64();
    let k = feats.image.dims;
    let explained: f64 = feats.explained[..k].iter().sum();
    let t1 = Instant::now();
    let map = synthesize::synthesize(&feats.image, &p)
        .with_context(|| format!("synthesizing {w}×{h} from {}", a.input.display()))?;
    let synth_seconds = t1.elapsed().as_secs_f64();
    // The file names its exemplar as seen from the output's directory, with the exemplar's
    // SHA-256 (`exemplar`, `exemplar_sha256`; `gonio_dataset::store::provenance`), and leaves the
    // in-memory PCA's wall-clock seconds to --json: same bytes wherever the files sit.
    let out_dir = gonio_dataset::store::provenance::output_dir(&a.out);
    let mut provenance = serde_json::json!({
        "method": p.method.name(),
        "params": &p,
        "exemplar": a.input.display().to_string(),
        "exemplar_size": [ew, eh],
        "features": { "embedding": emb.kind, "embedding_dims": emb.image.dims, "k": k, "explained": explained },
        "from_dataset": &from_dataset,
    });
    super::common::record_input(&mut provenance, "exemplar", &a.input, &out_dir)?;
    if let Some(note) = provenance.get_mut("from_dataset").filter(|n| n.is_object()) {
        let rel = gonio_dataset::store::provenance::relative_path(&out_dir, &a.input);
        if let Some(o) = note.as_object_mut() {
            o.remove("seconds");
            o.insert("dataset".into(), serde_json::Value::String(rel.clone()));
            o.insert(
                "note".into(),
                serde_json::Value::String(format!(
                    "the output is a PCA c = {c} model; its fidelity to the dataset is that of \
                     `gonio compress {rel} --method pca -c {c}`",
                    c = a.components
                )),
            );
        }
    }
    let t2 = Instant::now();
    let written = model
        .write(&map, &a.out, provenance)
        .with_context(|| format!("writing {}", a.out.display()))?;
    let write_seconds = t2.elapsed().as_secs_f64();
    let compact = model.compact();
    if a.json {
        let r = serde_json::json!({
            "input": a.input.display().to_string(),
            "model": model.model_name(),
            "method": p.method.name(),
            "width": w,
            "height": h,
            "seed": p.seed,
            "params": &p,
            "embedding": emb.kind,
            "embedding_dims": emb.image.dims,
            "k": k,
            "explained_energy": explained,
            "feature_seconds": feature_seconds,
            "synthesis_seconds": synth_seconds,
            "write_seconds": write_seconds,
            "out": written,
            "compact": compact,
            "from_dataset": &from_dataset,
            "peak_memory_bytes": gonio_btf::compress::peak_memory_bytes(),
        });
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        if from_dataset.is_some() {
            println!(
                "dataset {} compressed in memory to PCA c = {} (the output is that PCA model)",
                a.input.display(),
                a.components
            );
        }
        println!(
            "{} {w}×{h} from {} ({ew}×{eh}, {}): k = {k} features ({:.1} % of the ABRDF variance, {} embedding of {} dims)",
            p.method.name(),
            a.input.display(),
            model.model_name(),
            100.0 * explained,
            emb.kind,
            emb.image.dims
        );
        println!("  features {feature_seconds:.2} s, synthesis {synth_seconds:.2} s, write {write_seconds:.2} s");
        println!(
            "  wrote {} ({} bytes, {} bytes per texel{}) and {} ({} bytes)",
            written.file.display(),
            written.bytes,
            written.bytes_per_texel,
            if compact {
                ""
            } else {
                ": not compact, every texel stores its own factor rows"
            },
            written.texel_map.display(),
            written.texel_map_bytes
        );
    }
    Ok(ExitCode::SUCCESS)
}
