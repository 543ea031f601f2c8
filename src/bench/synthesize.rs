//! `gonio bench synthesize`: every synthesis method against a reference rendered by the
//! simulator over 4× the exemplar's area (same material, same texel pitch): seams,
//! statistics distances (all pairs, normal and grazing pairs), repetition and run time;
//! a markdown table, an error-versus-time SVG and a side-by-side picture.
//!
//! Output images are the exemplar model's images gathered through the texel map, which is
//! exactly what the written `.gbtf` decodes to (`synthesize::output` tests that), so no
//! file is written per run.

use anyhow::{bail, Context, Result};
use gonio::cli::bench::parse_size;
use gonio::cli::bench::{log_log, Series};
use gonio::cli::bench::{open_exemplar, SynthArgs};
use gonio_btf::compress::DatasetViews;
use gonio_btf::synthesize::quality::{self, ImageStats};
use gonio_btf::synthesize::{self, features, FeatureImage, SynthMethod, TexelMap};
use serde::Serialize;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct SynthesizeBenchArgs {
    /// The exemplar: a compressed BTF (`.gbtf` or UBO2014 DFMF `.btf`).
    #[arg(long)]
    pub exemplar: PathBuf,
    /// Reference dataset: the same material over a larger area at the same texel pitch and
    /// on the same direction grid (see docs/guide/synthesis.md for the recipe).
    #[arg(long)]
    pub reference: PathBuf,
    /// Output size (default: twice the exemplar's side, 4× its area).
    #[arg(long)]
    pub size: Option<String>,
    /// Methods to run, comma-separated.
    #[arg(long, default_value = "tile,quilting,wei-levoy,efros-leung")]
    pub methods: String,
    /// Feature counts k for the k sweep (quilting and Wei–Levoy), comma-separated.
    #[arg(long, default_value = "1,2,4,8,16")]
    pub ks: String,
    /// (light, view) pairs sampled for the statistics.
    #[arg(long, default_value_t = 48)]
    pub pairs: usize,
    /// Random projections of the sliced Wasserstein distance.
    #[arg(long, default_value_t = 64)]
    pub projections: usize,
    #[command(flatten)]
    pub synth: SynthArgs,
    /// Markdown table output.
    #[arg(long)]
    pub md: Option<PathBuf>,
    /// Error-versus-time SVG.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Side-by-side PNG: rows = a normal and a grazing pair; columns = exemplar, reference,
    /// then each method.
    #[arg(long)]
    pub picture: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize, Clone, Debug)]
struct Row {
    name: String,
    method: String,
    k: usize,
    seconds: f64,
    seams: Option<quality::Seams>,
    repetition: Option<quality::Repetition>,
    /// Sliced Wasserstein distance of the sampled ABRDF vectors to the reference's, over all
    /// sampled pairs, the normal ones and the grazing ones.
    sw_all: f64,
    sw_normal: f64,
    sw_grazing: f64,
    /// Mean luminance-quantile distance and filter-energy distance over the normal and the
    /// grazing sampled pairs (`ImageStats::distance`).
    hist_normal: f64,
    hist_grazing: f64,
    filter_normal: f64,
    filter_grazing: f64,
}

struct Pairs {
    list: Vec<(usize, usize)>,
    normal: Vec<usize>,
    grazing: Vec<usize>,
}

fn pick_pairs(lights: &[[f64; 2]], views: &[[f64; 2]], n: usize) -> Pairs {
    let (nl, nv) = (lights.len(), views.len());
    let total = nl * nv;
    let n = n.clamp(1, total);
    // Spread over the grid, plus every pair that is normal or grazing in both directions'
    // extremes so both groups are populated.
    let mut list: Vec<(usize, usize)> = (0..n).map(|i| i * total / n).map(|p| (p % nl, p / nl)).collect();
    let theta = |l: usize, v: usize| (lights[l][0], views[v][0]);
    let best_normal = (0..total)
        .map(|p| (p % nl, p / nl))
        .min_by(|a, b| {
            let (x, y) = (theta(a.0, a.1), theta(b.0, b.1));
            (x.0 + x.1).total_cmp(&(y.0 + y.1))
        })
        .unwrap();
    let best_grazing = (0..total)
        .map(|p| (p % nl, p / nl))
        .max_by(|a, b| {
            let (x, y) = (theta(a.0, a.1), theta(b.0, b.1));
            x.1.max(x.0)
                .total_cmp(&y.1.max(y.0))
                .then((x.0 + x.1).total_cmp(&(y.0 + y.1)))
        })
        .unwrap();
    for p in [best_normal, best_grazing] {
        if !list.contains(&p) {
            list.push(p);
        }
    }
    let normal = (0..list.len())
        .filter(|&i| {
            let (a, b) = theta(list[i].0, list[i].1);
            a <= 30.0 && b <= 30.0
        })
        .collect();
    let grazing = (0..list.len())
        .filter(|&i| {
            let (a, b) = theta(list[i].0, list[i].1);
            a >= 60.0 || b >= 60.0
        })
        .collect();
    Pairs { list, normal, grazing }
}

/// Per-texel vectors of the chosen pairs' RGB values.
fn vectors(images: &[Vec<f32>], which: &[usize], texels: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(texels * which.len() * 3);
    for t in 0..texels {
        for &p in which {
            out.extend_from_slice(&images[p][t * 3..t * 3 + 3]);
        }
    }
    out
}

fn gather(img: &[f32], map: &TexelMap) -> Vec<f32> {
    let mut out = Vec::with_capacity(map.src.len() * 3);
    for &s in &map.src {
        out.extend_from_slice(&img[s as usize * 3..s as usize * 3 + 3]);
    }
    out
}

struct Scorer<'a> {
    pairs: &'a Pairs,
    reference: Vec<Vec<f32>>,
    ref_size: (usize, usize),
    ref_stats: Vec<ImageStats>,
    projections: usize,
}

impl Scorer<'_> {
    /// Statistics fields of a row for images of `(w, h)`.
    fn score(&self, images: &[Vec<f32>], w: usize, h: usize) -> [f64; 7] {
        let all: Vec<usize> = (0..self.pairs.list.len()).collect();
        let rt = self.ref_size.0 * self.ref_size.1;
        let sw = |which: &[usize]| {
            if which.is_empty() {
                return f64::NAN;
            }
            let a = vectors(images, which, w * h);
            let b = vectors(&self.reference, which, rt);
            quality::sliced_wasserstein(&a, &b, which.len() * 3, self.projections, 7)
        };
        let stats = |which: &[usize]| -> (f64, f64) {
            if which.is_empty() {
                return (f64::NAN, f64::NAN);
            }
            let mut acc = (0.0, 0.0);
            for &p in which {
                let (q, f) = ImageStats::of(&images[p], w, h).distance(&self.ref_stats[p]);
                acc.0 += q;
                acc.1 += f;
            }
            (acc.0 / which.len() as f64, acc.1 / which.len() as f64)
        };
        let (hn, fnm) = stats(&self.pairs.normal);
        let (hg, fg) = stats(&self.pairs.grazing);
        [
            sw(&all),
            sw(&self.pairs.normal),
            sw(&self.pairs.grazing),
            hn,
            hg,
            fnm,
            fg,
        ]
    }
}

fn srgb8(v: f32) -> u8 {
    let v = v.clamp(0.0, 1.0);
    let s = if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5) as u8
}

pub fn run(a: SynthesizeBenchArgs) -> Result<ExitCode> {
    let model = open_exemplar(&a.exemplar)?;
    let (ew, eh) = (model.width(), model.height());
    let (ow, oh) = match &a.size {
        Some(s) => parse_size(s, 1..=usize::MAX).map_err(|e| anyhow::anyhow!("--size {e}"))?,
        None => (2 * ew, 2 * eh),
    };
    let reference = DatasetViews::open(&a.reference).with_context(|| format!("opening {}", a.reference.display()))?;
    let (lights, views) = (model.model().lights_deg().to_vec(), model.model().views_deg().to_vec());
    let same = |x: &[[f64; 2]], y: &[[f64; 2]]| {
        x.len() == y.len()
            && x.iter()
                .zip(y)
                .all(|(p, q)| (p[0] - q[0]).abs() < 0.01 && (p[1] - q[1]).abs() < 0.01)
    };
    if !same(&lights, &reference.lights_deg) || !same(&views, &reference.views_deg) {
        bail!(
            "{}: its direction grid ({} lights × {} views) differs from the exemplar's ({} × {}); render the \
             reference with the exemplar's sweep",
            a.reference.display(),
            reference.lights_deg.len(),
            reference.views_deg.len(),
            lights.len(),
            views.len()
        );
    }
    let pairs = pick_pairs(&lights, &views, a.pairs);
    let mut ref_images = Vec::new();
    for &(l, v) in &pairs.list {
        let img = reference
            .read_image(l, v)?
            .with_context(|| format!("{}: pair (light {l}, view {v}) was not measured", a.reference.display()))?;
        ref_images.push(img);
    }
    let ref_size = (reference.width, reference.height);
    let ref_stats: Vec<ImageStats> = ref_images
        .iter()
        .map(|i| ImageStats::of(i, ref_size.0, ref_size.1))
        .collect();
    let ex_images: Vec<Vec<f32>> = pairs
        .list
        .iter()
        .map(|&(l, v)| model.model().reconstruct(l, v))
        .collect::<Result<_, _>>()?;
    let scorer = Scorer {
        pairs: &pairs,
        reference: ref_images,
        ref_size,
        ref_stats,
        projections: a.projections,
    };

    let t0 = Instant::now();
    let emb = model.embed()?;
    let embed_seconds = t0.elapsed().as_secs_f64();
    let methods: Vec<SynthMethod> = a
        .methods
        .split(',')
        .map(|m| SynthMethod::parse(m.trim()))
        .collect::<Result<_, _>>()?;
    let ks: Vec<usize> =
        a.ks.split(',')
            .map(|k| {
                k.trim()
                    .parse::<usize>()
                    .with_context(|| format!("--ks: {k:?} is not a count"))
            })
            .collect::<Result<_>>()?;
    let mut rows: Vec<Row> = Vec::new();
    let s = scorer.score(&ex_images, ew, eh);
    rows.push(Row {
        name: "exemplar (floor)".into(),
        method: "exemplar".into(),
        k: 0,
        seconds: 0.0,
        seams: None,
        repetition: None,
        sw_all: s[0],
        sw_normal: s[1],
        sw_grazing: s[2],
        hist_normal: s[3],
        hist_grazing: s[4],
        filter_normal: s[5],
        filter_grazing: s[6],
    });
    let default_feats = features::principal(&emb.image, a.synth.k_choice())?;
    let mut maps: Vec<(String, TexelMap)> = Vec::new();
    let mut run_one = |method: SynthMethod, feats: &FeatureImage, label: String, keep: bool| -> Result<()> {
        let p = a.synth.params(ow, oh, ew, eh)?;
        let p = synthesize::SynthParams { method, ..p };
        tracing::info!("bench synthesize: {label}");
        let t = Instant::now();
        let map = synthesize::synthesize(feats, &p).with_context(|| label.clone())?;
        let seconds = t.elapsed().as_secs_f64();
        let out: Vec<Vec<f32>> = ex_images.iter().map(|i| gather(i, &map)).collect();
        let s = scorer.score(&out, ow, oh);
        rows.push(Row {
            name: label.clone(),
            method: method.name().into(),
            k: feats.dims,
            seconds,
            seams: Some(quality::seams(&map, &emb.image)),
            repetition: Some(quality::repetition(&map)),
            sw_all: s[0],
            sw_normal: s[1],
            sw_grazing: s[2],
            hist_normal: s[3],
            hist_grazing: s[4],
            filter_normal: s[5],
            filter_grazing: s[6],
        });
        if keep {
            maps.push((label, map));
        }
        Ok(())
    };
    for &m in &methods {
        run_one(
            m,
            &default_feats.image,
            format!("{} (k = {})", m.name(), default_feats.image.dims),
            true,
        )?;
    }
    for &m in methods
        .iter()
        .filter(|m| matches!(m, SynthMethod::Quilting | SynthMethod::WeiLevoy))
    {
        for &k in &ks {
            if k == default_feats.image.dims || k == 0 || k > emb.image.dims {
                continue;
            }
            let f = features::principal(&emb.image, features::KChoice::Fixed(k))?;
            run_one(m, &f.image, format!("{} k = {k}", m.name()), false)?;
        }
    }

    // Markdown.
    let mut md = String::new();
    let explained: f64 = default_feats.explained[..default_feats.image.dims].iter().sum();
    writeln!(
        md,
        "Exemplar `{}` ({ew}×{eh}, {}), reference `{}` ({}×{}), output {ow}×{oh}; {} sampled pairs ({} normal, {} \
         grazing); ABRDF embedding: {} of {} dims ({embed_seconds:.2} s); default k = {} ({:.1} % of the variance).\n",
        a.exemplar.display(),
        model.model_name(),
        a.reference.display(),
        ref_size.0,
        ref_size.1,
        pairs.list.len(),
        pairs.normal.len(),
        pairs.grazing.len(),
        emb.kind,
        emb.image.dims,
        default_feats.image.dims,
        100.0 * explained
    )?;
    md.push_str(
        "| run | k | time s | seam ratio | seam pairs % | SW all | SW normal | SW grazing | hist normal | hist grazing | filter normal | filter grazing | largest copy % of output | reuse max | unused % |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    let f = |v: f64| {
        if v.is_nan() {
            "–".to_string()
        } else {
            format!("{v:.4}")
        }
    };
    for r in &rows {
        let (sr, sp) = r.seams.as_ref().map_or(("–".into(), "–".into()), |s| {
            (
                format!("{:.3}", s.ratio),
                format!("{:.1}", 100.0 * s.seam_pair_fraction),
            )
        });
        let (lc, rm, un) = r.repetition.as_ref().map_or(("–".into(), "–".into(), "–".into()), |x| {
            (
                format!("{:.2}", 100.0 * x.largest_copy_fraction),
                x.reuse_max.to_string(),
                format!("{:.1}", 100.0 * x.unused_fraction),
            )
        });
        writeln!(
            md,
            "| {} | {} | {:.2} | {sr} | {sp} | {} | {} | {} | {} | {} | {} | {} | {lc} | {rm} | {un} |",
            r.name,
            if r.k == 0 { "–".into() } else { r.k.to_string() },
            r.seconds,
            f(r.sw_all),
            f(r.sw_normal),
            f(r.sw_grazing),
            f(r.hist_normal),
            f(r.hist_grazing),
            f(r.filter_normal),
            f(r.filter_grazing)
        )?;
    }
    if let Some(path) = &a.md {
        std::fs::write(path, &md).with_context(|| format!("writing {}", path.display()))?;
    }
    if let Some(path) = &a.plot {
        let mut series: Vec<Series> = Vec::new();
        for r in rows.iter().filter(|r| r.method != "exemplar") {
            let name = r.method.clone();
            let pt = (r.seconds.max(1e-4), r.sw_all, format!("k={}", r.k));
            match series.iter_mut().find(|s| s.name == name) {
                Some(s) => s.points.push(pt),
                None => series.push(Series { name, points: vec![pt] }),
            }
        }
        for s in &mut series {
            s.points.sort_by(|a, b| a.0.total_cmp(&b.0));
        }
        let svg = log_log(
            "BTF synthesis: distance to the 4×-area reference vs run time",
            "synthesis time (s)",
            "sliced Wasserstein distance (all sampled pairs)",
            &series,
        );
        std::fs::write(path, svg).with_context(|| format!("writing {}", path.display()))?;
    }
    if let Some(path) = &a.picture {
        let rows_pairs = [
            pairs.normal.first().copied().unwrap_or(0),
            pairs.grazing.last().copied().unwrap_or(pairs.list.len() - 1),
        ];
        let gap = 4;
        let cols = 2 + maps.len();
        let (cw, ch) = (ow.max(ref_size.0), oh.max(ref_size.1));
        let (pw, ph) = (cols * cw + (cols + 1) * gap, 2 * ch + 3 * gap);
        let mut px = vec![255u8; pw * ph * 3];
        for (ri, &p) in rows_pairs.iter().enumerate() {
            let mut lum: Vec<f32> = scorer.reference[p]
                .chunks_exact(3)
                .map(|c| 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2])
                .collect();
            lum.sort_by(f32::total_cmp);
            let scale = lum[(lum.len() * 99) / 100].max(1e-6);
            let mut put = |col: usize, img: &[f32], w: usize, h: usize| {
                let (x0, y0) = (gap + col * (cw + gap), gap + ri * (ch + gap));
                for y in 0..h {
                    for x in 0..w {
                        for c in 0..3 {
                            px[((y0 + y) * pw + x0 + x) * 3 + c] = srgb8(img[(y * w + x) * 3 + c] / scale);
                        }
                    }
                }
            };
            put(0, &ex_images[p], ew, eh);
            put(1, &scorer.reference[p], ref_size.0, ref_size.1);
            for (i, (_, map)) in maps.iter().enumerate() {
                put(2 + i, &gather(&ex_images[p], map), ow, oh);
            }
        }
        image::save_buffer(path, &px, pw as u32, ph as u32, image::ColorType::Rgb8)
            .with_context(|| format!("writing {}", path.display()))?;
        let desc: Vec<String> = rows_pairs
            .iter()
            .map(|&p| {
                let (l, v) = pairs.list[p];
                format!("light {:?}°, view {:?}°", lights[l], views[v])
            })
            .collect();
        writeln!(
            md,
            "\nPicture rows: {}; columns: exemplar, reference, {}.",
            desc.join(" / "),
            maps.iter().map(|m| m.0.as_str()).collect::<Vec<_>>().join(", ")
        )?;
        if let Some(mdp) = &a.md {
            std::fs::write(mdp, &md).with_context(|| format!("writing {}", mdp.display()))?;
        }
    }
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "exemplar": a.exemplar.display().to_string(),
                "reference": a.reference.display().to_string(),
                "size": [ow, oh],
                "pairs": pairs.list,
                "embedding_seconds": embed_seconds,
                "rows": rows,
            }))?
        );
    } else {
        print!("{md}");
    }
    Ok(ExitCode::SUCCESS)
}
