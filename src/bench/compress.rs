//! `gonio bench compress DATASET`: every compression method over its knob, error against
//! encode time and against compression ratio (table, JSON and an SVG plot).
//!
//! Each run is exactly `gonio compress DATASET <args> --out FILE` (the same code path,
//! [`gonio::cli::bench::compress_report`]), so the figures are the ones a user gets. The
//! sweep is a plain list of argument vectors ([`sweep`]): adding a method or a knob value
//! is one line. A run that fails (e.g. a method that rejects a parameter for this dataset)
//! is reported in the table with its error and the sweep goes on.

use anyhow::{Context, Result};
use clap::Parser;
use gonio::cli::bench::{compress_report, CompressArgs, Report};
use serde::Serialize;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct CompressBenchArgs {
    /// The dataset directory.
    pub dataset: PathBuf,
    /// Where the table (compress.md, compress.json), the plot (compress.svg) and the
    /// compressed files (files/, removed after each run unless --keep) go.
    #[arg(long, default_value = "bench-compress")]
    pub out: PathBuf,
    /// Only these methods (comma-separated method names as in `gonio compress --method`).
    #[arg(long, value_delimiter = ',')]
    pub methods: Option<Vec<String>>,
    /// Keep the compressed files.
    #[arg(long)]
    pub keep: bool,
    /// Sweep the rate–quality frontier instead ([`frontier_sweep`]): quantized PCA,
    /// perceptual (CIELab) DFMF and local PCA at the knobs that reach 100–2000 : 1.
    #[arg(long)]
    pub frontier: bool,
    /// Instead of the sweep: PVMF speed on this dataset (read vs. factorization per view,
    /// faer's GEMM rate on the same shapes, extrapolation to 81 × 81 × 256²) and decode
    /// time per 256² image.
    #[arg(long)]
    pub speed: bool,
    #[arg(long)]
    pub json: bool,
}

/// Components swept for the factorizations (the thesis' Tables 7.1 / 8.1 values).
pub const C_SWEEP: [usize; 8] = [2, 4, 7, 9, 15, 17, 22, 30];

/// The sweep: `(method, arguments of gonio compress)`.
pub fn sweep() -> Vec<(&'static str, Vec<String>)> {
    let a = |s: &str| s.split_whitespace().map(String::from).collect::<Vec<_>>();
    let mut v = Vec::new();
    for c in C_SWEEP {
        v.push(("pvmf", a(&format!("--method pvmf -c {c}"))));
        v.push(("pca", a(&format!("--method pca -c {c}"))));
        v.push(("dfmf", a(&format!("--method dfmf -c {c}"))));
        // Decorrelation pays when chroma gets fewer components than luminance.
        let cc = (c / 4).max(1);
        v.push((
            "dfmf-lowchroma",
            a(&format!("--method dfmf -c {c} --chroma-components {cc}")),
        ));
    }
    for k in [8, 16, 32] {
        v.push(("local-pca", a(&format!("--method local-pca --clusters {k} -c 8"))));
    }
    for b in [256, 400, 1024] {
        v.push(("median-cut", a(&format!("--method median-cut --boxes {b}"))));
    }
    v.push(("homomorphic", a("--method homomorphic")));
    // The per-ABRDF factorizations: storage grows with J per texel, so small J only.
    v.push(("nd", a("--method nd")));
    for j in [1, 2, 4] {
        v.push(("svd-j", a(&format!("--method svd-j -c {j}"))));
    }
    for b in [4, 8] {
        v.push(("gshd", a(&format!("--method gshd --half-bins {b}"))));
    }
    for k in [1, 2] {
        v.push(("cmf", a(&format!("--method cmf --half-bins 4 -c {k}"))));
    }
    v
}

/// The rate–quality frontier (`--frontier`): every entry is stored quantized (`.gbtf`
/// version 2), so the ratios are the ones a user gets with `--quantize`.
pub fn frontier_sweep() -> Vec<(&'static str, Vec<String>)> {
    let a = |s: &str| s.split_whitespace().map(String::from).collect::<Vec<_>>();
    let mut v = Vec::new();
    for c in [8, 16, 32, 48, 64] {
        for bits in [6, 8] {
            v.push(("pca", a(&format!("--method pca -c {c} --quantize {bits}"))));
        }
    }
    for c in [8, 16, 32, 48, 64] {
        let cc = (c / 4).max(1);
        for bits in [6, 8] {
            v.push((
                "dfmf-lab",
                a(&format!(
                    "--method dfmf --color-model lab -c {c} --chroma-components {cc} --format gbtf --quantize {bits}"
                )),
            ));
        }
    }
    for c in [16, 32] {
        v.push((
            "dfmf-logyuv",
            a(&format!(
                "--method dfmf --color-model log-yuv -c {c} --chroma-components {} --format gbtf --quantize 8",
                c / 4
            )),
        ));
    }
    for c in [2, 4, 8] {
        v.push((
            "local-pca",
            a(&format!("--method local-pca --clusters 8 -c {c} --quantize 8")),
        ));
    }
    v.push(("nd", a("--method nd --quantize 8")));
    for j in [1, 2, 4] {
        v.push(("svd-j", a(&format!("--method svd-j -c {j} --quantize 8"))));
    }
    v.push(("gshd", a("--method gshd --half-bins 4 --quantize 8")));
    for k in [1, 2] {
        v.push(("cmf", a(&format!("--method cmf --half-bins 4 -c {k} --quantize 8"))));
    }
    v
}

#[derive(clap::Parser, Debug)]
#[command(no_binary_name = true)]
struct OneRun {
    #[command(flatten)]
    args: CompressArgs,
}

#[derive(Serialize, Debug)]
struct Row {
    method: String,
    args: String,
    /// The `gonio compress --json` report; absent when the run failed.
    report: Option<Report>,
    error: Option<String>,
}

/// Reset this process's peak RSS (VmHWM) so each run reports its own peak.
fn reset_peak_rss() {
    // Linux ≥ 4.0: writing 5 to clear_refs resets VmHWM. Best effort: if it fails, the
    // peaks are cumulative, which the table says.
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

pub fn run(a: CompressBenchArgs) -> Result<ExitCode> {
    if a.speed {
        return speed(&a);
    }
    let files = a.out.join("files");
    std::fs::create_dir_all(&files).with_context(|| format!("creating {}", files.display()))?;
    let mut rows = Vec::new();
    let list = if a.frontier { frontier_sweep() } else { sweep() };
    for (i, (method, extra)) in list.into_iter().enumerate() {
        if let Some(m) = &a.methods {
            if !m.iter().any(|x| x == method) {
                continue;
            }
        }
        let gbtf = !method.starts_with("dfmf") || extra.windows(2).any(|w| w[0] == "--format" && w[1] == "gbtf");
        let ext = if gbtf { "gbtf" } else { "btf" };
        let file = files.join(format!("{i:02}-{method}.{ext}"));
        let mut argv: Vec<String> = vec![
            a.dataset.display().to_string(),
            "--out".into(),
            file.display().to_string(),
        ];
        argv.extend(extra.iter().cloned());
        let label = extra.join(" ");
        tracing::info!("bench compress: {label}");
        reset_peak_rss();
        let result = OneRun::try_parse_from(&argv)
            .map_err(anyhow::Error::from)
            .and_then(|o| compress_report(&o.args));
        let row = match result {
            Ok(r) => Row {
                method: method.into(),
                args: label,
                report: Some(r),
                error: None,
            },
            Err(e) => Row {
                method: method.into(),
                args: label,
                report: None,
                error: Some(format!("{e:#}")),
            },
        };
        if !a.json {
            eprintln!("{}", row_line(&row));
        }
        rows.push(row);
        if !a.keep {
            let _ = std::fs::remove_file(&file);
        }
    }
    let md = markdown(&a.dataset, &rows);
    std::fs::write(a.out.join("compress.md"), &md).with_context(|| format!("writing {}", a.out.display()))?;
    let json = serde_json::to_string_pretty(&rows)?;
    std::fs::write(a.out.join("compress.json"), &json)?;
    std::fs::write(a.out.join("compress.svg"), svg(&rows))?;
    if a.json {
        println!("{json}");
    } else {
        print!("{md}");
        println!("\nwrote {}/compress.{{md,json,svg}}", a.out.display());
    }
    Ok(ExitCode::SUCCESS)
}

fn row_line(r: &Row) -> String {
    match (&r.report, &r.error) {
        (Some(p), _) => format!(
            "{:<12} {:<40} ratio {:>8.1}  RMSE {:.5}  encode {:>7.2} s",
            r.method,
            r.args,
            p.compression_ratio,
            p.rmse_8bit.unwrap_or(f64::NAN),
            p.encode_seconds
        ),
        (None, e) => format!("{:<12} {:<40} FAILED: {}", r.method, r.args, e.as_deref().unwrap_or("")),
    }
}

fn markdown(dataset: &Path, rows: &[Row]) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# gonio bench compress {}\n", dataset.display());
    let _ = writeln!(
        s,
        "Errors on the 8-bit sRGB scale /255 over all measured images (UBO2003 encoding); ratio against \
         the raw 8-bit grid (L·V·W·H·3 bytes); peak RSS per run (VmHWM reset before each run).\n"
    );
    let _ = writeln!(
        s,
        "| method | arguments | bytes | ratio | RMSE | mean abs | max | PSNR dB | RMSE vs truth | PSNR vs truth dB | encode s | decode ms/img | peak MiB |"
    );
    let _ = writeln!(s, "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in rows {
        match &r.report {
            Some(p) => {
                let o = |v: Option<f64>, d: usize| v.map_or("–".to_string(), |v| format!("{v:.d$}"));
                let _ = writeln!(
                    s,
                    "| {} | `{}` | {} | {:.1} | {} | {} | {} | {} | {} | {} | {:.2} | {} | {} |",
                    r.method,
                    r.args,
                    p.stored_bytes,
                    p.compression_ratio,
                    o(p.rmse_8bit, 5),
                    o(p.mean_abs_8bit, 5),
                    o(p.max_8bit, 4),
                    o(p.psnr_8bit_db, 2),
                    o(p.truth.as_ref().map(|t| t.rmse_8bit), 5),
                    o(p.truth.as_ref().map(|t| t.psnr_8bit_db), 2),
                    p.encode_seconds,
                    o(p.decode_seconds_per_image.map(|d| d * 1e3), 3),
                    p.peak_memory_bytes.map_or("–".into(), |b| (b >> 20).to_string()),
                );
            }
            None => {
                let _ = writeln!(
                    s,
                    "| {} | `{}` | failed: {} | | | | | | | | | | |",
                    r.method,
                    r.args,
                    r.error.as_deref().unwrap_or("").replace('|', "\\|").replace('\n', " ")
                );
            }
        }
    }
    s
}

const COLORS: [&str; 8] = [
    "#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf",
];

/// Two log-x panels: RMSE (/255) against encode seconds and against compression ratio.
/// Filled markers and solid lines: error against the dataset's images. On a dataset with
/// `truth/` images (an acquisition with `--store-truth`), open markers and dashed lines
/// add the error against the truth, and a grey dashed line the measured images' own error
/// against the truth (the noise floor).
fn svg(rows: &[Row]) -> String {
    let mut methods: Vec<&str> = Vec::new();
    for r in rows {
        if r.report.is_some() && !methods.contains(&r.method.as_str()) {
            methods.push(&r.method);
        }
    }
    let points_of = |f: &dyn Fn(&Report) -> f64, truth: bool| -> Vec<(usize, f64, f64)> {
        rows.iter()
            .filter_map(|r| {
                let p = r.report.as_ref()?;
                let m = methods.iter().position(|m| *m == r.method)?;
                let y = if truth {
                    p.truth.as_ref()?.rmse_8bit
                } else {
                    p.rmse_8bit?
                };
                let x = f(p);
                (x.is_finite() && x > 0.0 && y.is_finite()).then_some((m, x, y))
            })
            .collect()
    };
    let points = |f: &dyn Fn(&Report) -> f64| points_of(f, false);
    let truth_points = |f: &dyn Fn(&Report) -> f64| points_of(f, true);
    // The measured images against the truth: the same for every run of one dataset.
    let floor = rows
        .iter()
        .find_map(|r| r.report.as_ref()?.truth.as_ref().map(|t| t.measured_rmse_8bit))
        .filter(|f| f.is_finite());
    let (w, h) = (1000.0, 460.0);
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" font-family=\"sans-serif\" font-size=\"12\">\n\
         <rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n"
    );
    type Panel<'a> = (&'a str, Vec<(usize, f64, f64)>, Vec<(usize, f64, f64)>, f64);
    let panels: [Panel; 2] = [
        (
            "encode time (s, log)",
            points(&|p| p.encode_seconds),
            truth_points(&|p| p.encode_seconds),
            60.0,
        ),
        (
            "compression ratio (log)",
            points(&|p| p.compression_ratio),
            truth_points(&|p| p.compression_ratio),
            540.0,
        ),
    ];
    let ymax = panels
        .iter()
        .flat_map(|p| p.1.iter().chain(&p.2).map(|q| q.2))
        .chain(floor)
        .fold(0.0f64, f64::max)
        .max(1e-6)
        * 1.05;
    for (title, pts, tpts, x0) in &panels {
        let (pw, ph, y0) = (400.0, 340.0, 40.0);
        let _ = writeln!(
            s,
            "<rect x=\"{x0}\" y=\"{y0}\" width=\"{pw}\" height=\"{ph}\" fill=\"none\" stroke=\"#444\"/>"
        );
        let _ = writeln!(
            s,
            "<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">{title}</text>",
            x0 + pw / 2.0,
            y0 + ph + 36.0
        );
        let _ = writeln!(
            s,
            "<text transform=\"translate({},{}) rotate(-90)\" text-anchor=\"middle\">RMSE (8-bit sRGB /255)</text>",
            x0 - 44.0,
            y0 + ph / 2.0
        );
        if pts.is_empty() {
            continue;
        }
        let lx = |x: f64| x.log10();
        let (mut xmin, mut xmax) = pts
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(lx(p.1)), b.max(lx(p.1))));
        xmin = xmin.floor();
        xmax = xmax.ceil().max(xmin + 1.0);
        let px = |x: f64| x0 + (lx(x) - xmin) / (xmax - xmin) * pw;
        let py = |y: f64| y0 + ph - y / ymax * ph;
        for d in (xmin as i32)..=(xmax as i32) {
            let xx = x0 + (d as f64 - xmin) / (xmax - xmin) * pw;
            let _ = writeln!(
                s,
                "<line x1=\"{xx:.1}\" y1=\"{y0}\" x2=\"{xx:.1}\" y2=\"{}\" stroke=\"#ddd\"/>\
                 <text x=\"{xx:.1}\" y=\"{}\" text-anchor=\"middle\">1e{d}</text>",
                y0 + ph,
                y0 + ph + 16.0
            );
        }
        for k in 0..=4 {
            let y = ymax * k as f64 / 4.0;
            let _ = writeln!(
                s,
                "<line x1=\"{x0}\" y1=\"{:.1}\" x2=\"{}\" y2=\"{:.1}\" stroke=\"#eee\"/>\
                 <text x=\"{}\" y=\"{:.1}\" text-anchor=\"end\">{y:.3}</text>",
                py(y),
                x0 + pw,
                py(y),
                x0 - 4.0,
                py(y) + 4.0
            );
        }
        for (m, _) in methods.iter().enumerate() {
            let mut mp: Vec<(f64, f64)> = pts.iter().filter(|p| p.0 == m).map(|p| (p.1, p.2)).collect();
            mp.sort_by(|a, b| a.0.total_cmp(&b.0));
            let color = COLORS[m % COLORS.len()];
            if mp.len() > 1 {
                let path: Vec<String> = mp.iter().map(|&(x, y)| format!("{:.1},{:.1}", px(x), py(y))).collect();
                let _ = writeln!(
                    s,
                    "<polyline points=\"{}\" fill=\"none\" stroke=\"{color}\" stroke-width=\"1.5\"/>",
                    path.join(" ")
                );
            }
            for &(x, y) in &mp {
                let _ = writeln!(
                    s,
                    "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"3.5\" fill=\"{color}\"/>",
                    px(x),
                    py(y)
                );
            }
        }
        for (m, _) in methods.iter().enumerate() {
            let mut mp: Vec<(f64, f64)> = tpts.iter().filter(|p| p.0 == m).map(|p| (p.1, p.2)).collect();
            mp.sort_by(|a, b| a.0.total_cmp(&b.0));
            let color = COLORS[m % COLORS.len()];
            if mp.len() > 1 {
                let path: Vec<String> = mp.iter().map(|&(x, y)| format!("{:.1},{:.1}", px(x), py(y))).collect();
                let _ = writeln!(
                    s,
                    "<polyline points=\"{}\" fill=\"none\" stroke=\"{color}\" stroke-width=\"1.2\" stroke-dasharray=\"4 3\"/>",
                    path.join(" ")
                );
            }
            for &(x, y) in &mp {
                let _ = writeln!(
                    s,
                    "<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"3.5\" fill=\"white\" stroke=\"{color}\" stroke-width=\"1.5\"/>",
                    px(x),
                    py(y)
                );
            }
        }
        if let Some(f) = floor {
            let _ = writeln!(
                s,
                "<line x1=\"{x0}\" y1=\"{:.1}\" x2=\"{}\" y2=\"{:.1}\" stroke=\"#888\" stroke-dasharray=\"6 4\"/>\
                 <text x=\"{}\" y=\"{:.1}\" text-anchor=\"end\" fill=\"#666\">measured vs truth</text>",
                py(f),
                x0 + pw,
                py(f),
                x0 + pw - 4.0,
                py(f) - 4.0
            );
        }
    }
    for (m, name) in methods.iter().enumerate() {
        let x = 60.0 + 120.0 * m as f64;
        let _ = writeln!(
            s,
            "<circle cx=\"{x}\" cy=\"18\" r=\"5\" fill=\"{}\"/><text x=\"{}\" y=\"22\">{name}</text>",
            COLORS[m % COLORS.len()],
            x + 9.0
        );
    }
    if panels.iter().any(|p| !p.2.is_empty()) {
        let _ = writeln!(
            s,
            "<text x=\"{}\" y=\"{}\" fill=\"#444\">filled: vs the dataset's images; open, dashed: vs truth/</text>",
            60.0,
            h - 12.0
        );
    }
    s.push_str("</svg>\n");
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_sweep_entry_parses_as_gonio_compress_arguments() {
        for (method, args) in sweep().into_iter().chain(frontier_sweep()) {
            let mut argv = vec!["DS".to_string(), "--out".into(), "X".into()];
            argv.extend(args.clone());
            let parsed = OneRun::try_parse_from(&argv);
            assert!(parsed.is_ok(), "{method} {args:?}: {:?}", parsed.err());
        }
    }

    /// Median cut and homomorphic factorization have no components: `gonio compress`
    /// runs them without `-c`, while the factorizations refuse to guess one.
    #[test]
    fn components_are_required_only_by_the_factorizations() {
        let tmp = tempfile::tempdir().unwrap();
        let ds = tmp.path().join("ds");
        let dirs = [[0.0, 0.0], [40.0, 90.0], [60.0, 200.0]];
        gonio_btf::compress::testdata::write_test_dataset(&ds, (4, 3), &dirs, &dirs, &[], |l, v, t, c| {
            0.1 + 0.02 * (l + 2 * v + 3 * c) as f32 + 0.01 * (t % 5) as f32
        });
        let out = tmp.path().join("x.gbtf");
        let run = |extra: &str| {
            let mut argv = vec![ds.display().to_string(), "--out".into(), out.display().to_string()];
            argv.extend(extra.split_whitespace().map(String::from));
            compress_report(&OneRun::try_parse_from(&argv).unwrap().args)
        };
        for ok in [
            "--method median-cut --boxes 2",
            "--method homomorphic --half-bins 2",
            "--method nd",
            "--method gshd --half-bins 2",
        ] {
            let r = run(ok).unwrap_or_else(|e| panic!("{ok}: {e:#}"));
            assert!(r.rmse_8bit.is_some_and(f64::is_finite), "{ok}");
        }
        for needs in [
            "--method pvmf",
            "--method pca",
            "--method local-pca",
            "--method dfmf",
            "--method svd-j",
            "--method cmf",
        ] {
            let e = run(needs).err().unwrap_or_else(|| panic!("{needs} ran without -c"));
            assert!(format!("{e:#}").contains("-c"), "{needs}: {e:#}");
        }
        // SVD-J refuses J above the 3 × 3 ABRDF matrices' rank, naming the range.
        let Err(e) = run("--method svd-j -c 4") else {
            panic!("svd-j -c 4 ran on a 3 × 3 grid");
        };
        assert!(format!("{e:#}").contains("1..=3"), "{e:#}");
        let r = run("--method pvmf -c 2").unwrap();
        assert_eq!(r.components, 2);
        assert!(r.encode_stages.iter().any(|s| s.name == "factorize"));
    }

    #[test]
    fn svg_has_one_marker_per_successful_run_and_panel() {
        let ok = |m: &str, ratio: f64, rmse: f64| Row {
            method: m.into(),
            args: String::new(),
            report: Some(Report {
                method: "pvmf",
                components: 1,
                format: "gbtf",
                params: serde_json::Value::Null,
                quantize_bits: None,
                target: None,
                out: String::new(),
                images_measured: 1,
                filled_pairs: 0,
                dataset_passes: 1,
                stored_bytes: 1,
                raw_8bit_bytes: 1,
                compression_ratio: ratio,
                encode_seconds: 0.5,
                error_scale: "",
                rmse_8bit: Some(rmse),
                mean_abs_8bit: None,
                max_8bit: None,
                psnr_8bit_db: None,
                rmse_linear: None,
                decode_seconds_per_image: None,
                truth: None,
                peak_memory_bytes: None,
                encode_stages: Vec::new(),
            }),
            error: None,
        };
        let failed = Row {
            method: "x".into(),
            args: String::new(),
            report: None,
            error: Some("no".into()),
        };
        let s = svg(&[ok("a", 10.0, 0.01), ok("a", 100.0, 0.02), ok("b", 50.0, 0.03), failed]);
        // 3 runs × 2 panels + 2 legend entries.
        assert_eq!(s.matches("<circle").count(), 3 * 2 + 2);
        assert_eq!(
            s.matches("<polyline").count(),
            2,
            "one line per panel for method a only"
        );
        assert!(!s.contains("measured vs truth") && !s.contains("fill=\"white\" stroke"));
        // With truth/: one open marker per run and panel, a dashed line per method with two
        // runs, and the measured-vs-truth floor in each panel.
        let with_truth = |m: &str, ratio: f64, rmse: f64, truth: f64| {
            let mut r = ok(m, ratio, rmse);
            r.report.as_mut().unwrap().truth = Some(gonio::cli::bench::TruthReport {
                images: 1,
                rmse_8bit: truth,
                mean_abs_8bit: 0.0,
                max_8bit: 0.0,
                psnr_8bit_db: 0.0,
                rmse_linear: 0.0,
                measured_rmse_8bit: 0.04,
                measured_rmse_linear: 0.0,
            });
            r
        };
        let s = svg(&[with_truth("a", 10.0, 0.05, 0.02), with_truth("a", 100.0, 0.06, 0.03)]);
        assert_eq!(s.matches("fill=\"white\" stroke").count(), 2 * 2);
        assert_eq!(s.matches("stroke-dasharray=\"4 3\"").count(), 2);
        assert_eq!(s.matches("measured vs truth").count(), 2);
    }
}

#[derive(Serialize, Debug)]
struct SpeedReport {
    texels: usize,
    columns: usize,
    views: usize,
    views_timed: usize,
    /// EXR decode + column-major f64 view matrix (`DatasetViews::view_columns`).
    read_seconds_per_view: f64,
    /// Householder QR + SVD of R (`linalg::truncated_svd`, PVMF's fallback), c = 8.
    qr_svd_seconds_per_view: f64,
    /// Gram path (`linalg::gram_truncated`, PVMF's default): AᵀA (lower triangle), its
    /// eigen-decomposition, A·V; c = 8.
    gram_seconds_per_view: f64,
    /// Views of the timed ones on which the Gram path declined (ill-conditioned for c).
    gram_declined: usize,
    /// Relative Frobenius error Gram path / QR path on the timed views (1 = same).
    gram_vs_qr_error_ratio: f64,
    /// faer f64 GEMM (texels × cols)·(cols × cols) on this dataset's shape, GFLOP/s.
    gemm_gflops: f64,
    /// FLOPs of the QR path per view (2mn² QR + 2mn² forming Q + 2mnc) over its time.
    qr_path_gflops: f64,
    /// Useful FLOPs of the Gram path per view (m·n·(n+1) for the triangle of AᵀA + 2mnc
    /// for A·V) over its time (eigen-decomposition included), and the ratio to `gemm_gflops`.
    gram_path_gflops: f64,
    gram_path_vs_gemm: f64,
    /// One full-size 65536 × cols view matrix (synthetic values: the cost does not depend
    /// on them): QR path, Gram path, and the parts of the Gram path against faer's own
    /// GEMM on the same shapes.
    full_view_qr_svd_seconds: f64,
    full_view_gram_seconds: f64,
    /// AᵀA lower triangle as PVMF computes it (`linalg::gram_by_row_chunks`), GFLOP/s
    /// counting m·n·(n+1).
    full_view_gram_product_gflops: f64,
    /// Plain faer `Aᵀ * A` (all n² entries), GFLOP/s counting 2·m·n².
    full_view_gemm_ata_gflops: f64,
    /// Plain faer `A * Y` with Y n × n, GFLOP/s counting 2·m·n².
    full_view_gemm_gflops: f64,
    /// `linalg::gram_lower` with b column blocks: (b, seconds), the rejected alternative
    /// to the triangular product PVMF uses (`full_view_triangular_gram_seconds`).
    full_view_gram_blocked_seconds: Vec<(usize, f64)>,
    /// faer's own parallel triangular product (`triangular::matmul`, PVMF's product until
    /// session 4) and the row-chunked product PVMF uses now, alone on an idle pool.
    full_view_triangular_gram_seconds: f64,
    full_view_chunked_gram_seconds: f64,
    /// The same two while another thread reads a view (`DatasetViews::view_columns`, its
    /// own rayon tasks), as PVMF's reader thread does during the encode. faer's parallel
    /// product splits the output between the threads and waits for the slowest; the
    /// chunked one hands out 16 whole products that either thread can take.
    full_view_triangular_gram_under_read_seconds: f64,
    full_view_chunked_gram_under_read_seconds: f64,
    /// Gram product rate over the plain AᵀA GEMM rate (same flop count convention).
    full_view_gram_product_vs_gemm: f64,
    /// Whole Gram path (useful flops as above over its time) over the plain GEMM rate.
    full_view_gram_path_vs_gemm: f64,
    /// Reading extrapolated linearly in texels to 81 views × 256².
    extrapolated_full_read_seconds: f64,
    /// 81 × (read + factorization) at 256², per path, without overlap (PVMF overlaps
    /// reading and factorizing; `gonio compress --json`'s `encode_stages` shows how much).
    extrapolated_full_encode_seconds_qr: f64,
    extrapolated_full_encode_seconds_gram: f64,
    /// Decode of one 256² image with c = 8 (RGB model: 3 dot products per texel, like PVMF/PCA).
    decode_ms_256_rgb_c8: f64,
    /// The same with DFMF's log-YUV colour model (exp per texel). Open question: on these
    /// synthetic factors this measured 14.8 ms (release), while real DFMF files decode at
    /// 0.084 ms per 64² image (≈ 1.3 ms per 256²): something in the synthetic values is
    /// slow (not yet explained), so read this figure next to `gonio compress --json`'s.
    decode_ms_256_logyuv_c8: f64,
    peak_memory_bytes: Option<u64>,
}

fn speed(a: &CompressBenchArgs) -> Result<ExitCode> {
    use faer::linalg::matmul::triangular::{matmul as tri_matmul, BlockStructure};
    use faer::Mat;
    use gonio_btf::compress::dfmf::{ChannelFactors, ColorModel, Dfmf};
    use gonio_btf::compress::linalg::{gram_truncated, truncated_svd};
    use std::time::Instant;
    let ds = gonio_btf::compress::DatasetViews::open(&a.dataset)
        .with_context(|| format!("opening {}", a.dataset.display()))?;
    let (t, n, nv) = (ds.texels(), ds.n_lights() * 3, ds.n_views());
    let c = 8;
    let timed = nv.min(6);
    let (mut read_s, mut qr_s, mut gram_s, mut ratio, mut declined) = (0.0, 0.0, 0.0, 0.0, 0);
    for k in 0..timed {
        let v = k * nv / timed;
        let t0 = Instant::now();
        let (m, _) = ds.view_columns(v)?;
        read_s += t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        let (us, vv) = truncated_svd(m.as_ref(), c)?;
        qr_s += t1.elapsed().as_secs_f64();
        let t2 = Instant::now();
        let gram = gram_truncated(m.as_ref(), c)?;
        gram_s += t2.elapsed().as_secs_f64();
        let err = |us: &Mat<f64>, vv: &Mat<f64>| (&m - us * vv.transpose()).norm_l2();
        match gram {
            Some((usg, vg)) => ratio += err(&usg, &vg) / err(&us, &vv).max(1e-300),
            None => declined += 1,
        }
    }
    let per = |x: f64| x / timed as f64;
    let ratio = ratio / (timed - declined).max(1) as f64;
    let useful_gram_flops = |m: usize| (m * n * (n + 1)) as f64 + 2.0 * (m * n * c) as f64;
    // faer GEMM rate on the view matrix shape.
    let x = Mat::from_fn(t, n, |i, j| ((i * 31 + j * 17) % 101) as f64 * 0.01);
    let y = Mat::from_fn(n, n, |i, j| ((i * 7 + j * 13) % 97) as f64 * 0.01);
    let _ = &x * &y; // warm-up
    let reps = 3;
    let tg = Instant::now();
    for _ in 0..reps {
        std::hint::black_box(&x * &y);
    }
    let gemm_s = tg.elapsed().as_secs_f64() / reps as f64;
    let gemm_gflops = 2.0 * (t * n * n) as f64 / gemm_s / 1e9;
    drop(x);
    let qr_flops = 4.0 * (t * n * n) as f64 + 2.0 * (t * n * c) as f64;
    let scale = 81.0 * 65536.0 / t as f64;
    // One full-size view matrix.
    let big = Mat::from_fn(65536, n, |i, j| {
        (((i * 31 + j * 17) % 101) as f64 * 0.01).sin() + 0.01 * j as f64
    });
    let tb = Instant::now();
    std::hint::black_box(truncated_svd(big.as_ref(), c)?);
    let full_qr = tb.elapsed().as_secs_f64();
    let tb = Instant::now();
    std::hint::black_box(gram_truncated(big.as_ref(), c)?);
    let full_gram = tb.elapsed().as_secs_f64();
    // Best of 3 for the products: they are short and the machine is shared.
    let best = |f: &mut dyn FnMut()| {
        (0..3)
            .map(|_| {
                let t0 = Instant::now();
                f();
                t0.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min)
    };
    let mut g = Mat::<f64>::zeros(n, n);
    // faer's own parallel triangular AᵀA (PVMF's product before the row chunks).
    let mut triangular = || {
        tri_matmul(
            g.as_mut(),
            BlockStructure::TriangularLower,
            faer::Accum::Replace,
            big.transpose(),
            BlockStructure::Rectangular,
            big.as_ref(),
            BlockStructure::Rectangular,
            1.0,
            faer::get_global_parallelism(),
        )
    };
    let tri_s = best(&mut triangular);
    let chunked = |big: &Mat<f64>| {
        std::hint::black_box(gonio_btf::compress::linalg::gram_by_row_chunks(big.as_ref()));
    };
    let chunk_s = best(&mut || chunked(&big));
    // Both products again while a reader thread loads views, as during PVMF's encode.
    let under_read = |f: &mut dyn FnMut()| -> f64 {
        use std::sync::atomic::{AtomicBool, Ordering};
        let stop = AtomicBool::new(false);
        std::thread::scope(|scope| {
            scope.spawn(|| {
                while !stop.load(Ordering::Relaxed) {
                    let _ = std::hint::black_box(ds.view_columns(0));
                }
            });
            // The mean, not the best: contention is what is measured here.
            let reps = 8;
            let t0 = Instant::now();
            (0..reps).for_each(|_| f());
            stop.store(true, Ordering::Relaxed);
            t0.elapsed().as_secs_f64() / reps as f64
        })
    };
    let tri_read_s = under_read(&mut triangular);
    let chunk_read_s = under_read(&mut || chunked(&big));
    let ata_s = best(&mut || {
        std::hint::black_box(big.transpose() * &big);
    });
    let ay_s = best(&mut || {
        std::hint::black_box(&big * &y);
    });
    let blocked: Vec<(usize, f64)> = [1, 3, 9]
        .into_iter()
        .map(|b| {
            let s = best(&mut || {
                std::hint::black_box(gonio_btf::compress::linalg::gram_lower(big.as_ref(), b));
            });
            (b, s)
        })
        .collect();
    let tri_gflops = (65536 * n * (n + 1)) as f64 / chunk_s / 1e9;
    let ata_gflops = 2.0 * (65536 * n * n) as f64 / ata_s / 1e9;
    let full_gemm = 2.0 * (65536 * n * n) as f64 / ay_s / 1e9;
    drop(big);
    // Decode timing on synthetic 256² factors.
    let synth = |model| {
        let ch = || ChannelFactors {
            c,
            sigma: vec![1.0; c],
            u: (0..81 * 81 * c).map(|i| ((i % 13) as f32 - 6.0) * 0.01).collect(),
            sxv: (0..65536 * c).map(|i| ((i % 7) as f32 - 3.0) * 0.02).collect(),
        };
        Dfmf {
            color_model: model,
            width: 256,
            height: 256,
            lights_deg: vec![[0.0, 0.0]; 81],
            views_deg: vec![[0.0, 0.0]; 81],
            channels: vec![ch(), ch(), ch()],
        }
    };
    let decode_ms = |d: &Dfmf| -> Result<f64> {
        for i in 0..5 {
            std::hint::black_box(d.reconstruct(i, i)?);
        }
        let td = Instant::now();
        let k = 40;
        for i in 0..k {
            std::hint::black_box(d.reconstruct(i % 81, (i * 7) % 81)?);
        }
        Ok(td.elapsed().as_secs_f64() * 1e3 / k as f64)
    };
    let r = SpeedReport {
        texels: t,
        columns: n,
        views: nv,
        views_timed: timed,
        read_seconds_per_view: per(read_s),
        qr_svd_seconds_per_view: per(qr_s),
        gram_seconds_per_view: per(gram_s),
        gram_declined: declined,
        gram_vs_qr_error_ratio: ratio,
        gemm_gflops,
        qr_path_gflops: qr_flops / per(qr_s) / 1e9,
        gram_path_gflops: useful_gram_flops(t) / per(gram_s) / 1e9,
        gram_path_vs_gemm: useful_gram_flops(t) / per(gram_s) / 1e9 / gemm_gflops,
        full_view_qr_svd_seconds: full_qr,
        full_view_gram_seconds: full_gram,
        full_view_gram_product_gflops: tri_gflops,
        full_view_gemm_ata_gflops: ata_gflops,
        full_view_gemm_gflops: full_gemm,
        full_view_gram_blocked_seconds: blocked,
        full_view_triangular_gram_seconds: tri_s,
        full_view_chunked_gram_seconds: chunk_s,
        full_view_triangular_gram_under_read_seconds: tri_read_s,
        full_view_chunked_gram_under_read_seconds: chunk_read_s,
        full_view_gram_product_vs_gemm: tri_gflops / ata_gflops,
        full_view_gram_path_vs_gemm: useful_gram_flops(65536) / full_gram / 1e9 / ata_gflops,
        extrapolated_full_read_seconds: per(read_s) * scale,
        extrapolated_full_encode_seconds_qr: per(read_s) * scale + 81.0 * full_qr,
        extrapolated_full_encode_seconds_gram: per(read_s) * scale + 81.0 * full_gram,
        decode_ms_256_rgb_c8: decode_ms(&synth(ColorModel::Rgb))?,
        decode_ms_256_logyuv_c8: decode_ms(&synth(ColorModel::LogYuv))?,
        peak_memory_bytes: gonio_btf::compress::peak_memory_bytes(),
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        print_speed(&r);
    }
    Ok(ExitCode::SUCCESS)
}

/// The speed report in sentences (`--json` has every field).
fn print_speed(r: &SpeedReport) {
    println!(
        "dataset: {} texels × {} columns, {} views ({} timed)",
        r.texels, r.columns, r.views, r.views_timed
    );
    println!(
        "per view: read {:.4} s; QR + SVD {:.4} s ({:.2} GFLOP/s); Gram path {:.4} s ({:.2} GFLOP/s, {:.2} × faer's GEMM at {:.2} GFLOP/s)",
        r.read_seconds_per_view,
        r.qr_svd_seconds_per_view,
        r.qr_path_gflops,
        r.gram_seconds_per_view,
        r.gram_path_gflops,
        r.gram_path_vs_gemm,
        r.gemm_gflops
    );
    println!(
        "the Gram path declined {} of the timed views; its error is {:.4} × the QR path's",
        r.gram_declined, r.gram_vs_qr_error_ratio
    );
    println!(
        "one full-size view: QR + SVD {:.3} s, Gram path {:.3} s ({:.2} × the plain GEMM rate)",
        r.full_view_qr_svd_seconds, r.full_view_gram_seconds, r.full_view_gram_path_vs_gemm
    );
    println!(
        "  AᵀA: PVMF's product {:.2} GFLOP/s ({:.2} × plain AᵀA at {:.2} GFLOP/s); A·Y GEMM {:.2} GFLOP/s",
        r.full_view_gram_product_gflops,
        r.full_view_gram_product_vs_gemm,
        r.full_view_gemm_ata_gflops,
        r.full_view_gemm_gflops
    );
    let blocked: Vec<String> = r
        .full_view_gram_blocked_seconds
        .iter()
        .map(|(b, t)| format!("{b} blocks {t:.3} s"))
        .collect();
    println!("  blocked AᵀA (rejected): {}", blocked.join(", "));
    println!(
        "  triangular product {:.3} s alone, {:.3} s while a view is read; row-chunked {:.3} s alone, {:.3} s while a view is read",
        r.full_view_triangular_gram_seconds,
        r.full_view_triangular_gram_under_read_seconds,
        r.full_view_chunked_gram_seconds,
        r.full_view_chunked_gram_under_read_seconds
    );
    println!(
        "extrapolated to 81 views × 256²: reading {:.1} s; encode without overlap {:.1} s (QR path), {:.1} s (Gram path)",
        r.extrapolated_full_read_seconds, r.extrapolated_full_encode_seconds_qr, r.extrapolated_full_encode_seconds_gram
    );
    println!(
        "decode of one 256² image with c = 8: {:.3} ms (RGB), {:.3} ms (log-YUV)",
        r.decode_ms_256_rgb_c8, r.decode_ms_256_logyuv_c8
    );
    if let Some(b) = r.peak_memory_bytes {
        println!("peak memory {:.0} MiB", b as f64 / (1024.0 * 1024.0));
    }
}
