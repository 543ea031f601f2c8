//! `gonio bench render`: render error against a high-sample reference versus time, per
//! quality knob (pixel supersampling, shadow-map resolution, samples per texel, disc-lamp
//! emitters).

use anyhow::Result;
use gonio::cli::bench::{load_sample, RigArgs};
use gonio_dataset::sweep;
use gonio_devices::kinematics;
use gonio_simulator::{PointLight, RenderQuality, Renderer};
use serde::Serialize;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct RenderBenchArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    #[arg(long, default_value = gonio_simulator::sample::DEFAULT_SAMPLE)]
    pub sample: String,
    /// Measurements (Bonn pairs spread over the sweep).
    #[arg(long, default_value_t = 8)]
    pub measurements: usize,
    /// Samples per pixel and axis of the reference.
    #[arg(long, default_value_t = 8)]
    pub reference: usize,
    /// Radius (mm) of a disc lamp to render with (default: the rig's
    /// `light.options.radius_mm`, else a point lamp); adds rows for its emitter count.
    #[arg(long)]
    pub lamp_radius: Option<f64>,
    /// Write the error-versus-time plot (SVG, log–log, one line per knob) to this file.
    #[arg(long)]
    pub plot: Option<std::path::PathBuf>,
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct RenderRow {
    image: &'static str,
    /// Which knob this row turns (the rows of one family share the plot's line).
    family: &'static str,
    knob: String,
    ms_per_image: f64,
    /// RMSE against the reference, relative to the reference's mean value.
    relative_rmse: f64,
}

pub fn run(a: RenderBenchArgs) -> Result<ExitCode> {
    let rig = a.rig.load()?;
    let kin = kinematics::for_rig(&rig);
    let dirs = sweep::bonn81();
    // Views spread over the sweep, lights stepping through all rings (a stride of 37 of
    // the 81 Bonn lights) so that grazing lights, where shadow maps matter, are included.
    let qs: Vec<Vec<f64>> = (0..a.measurements.max(1))
        .map(|k| (k * 81 / a.measurements.max(1)) * 81 + (k * 37 + 13) % 81)
        .filter_map(|idx| {
            kin.inverse(dirs[idx % 81], dirs[idx / 81], None)
                .ok()
                .map(|s| s[0].clone())
        })
        .collect();
    let spec = load_sample(&a.sample)?;
    let sample = Arc::new(spec.build()?);
    let intr = rig.camera.intrinsics();
    let radius = match a.lamp_radius {
        Some(r) if r.is_finite() && r >= 0.0 && r <= rig.geometry.light_distance_mm / 2.0 => r,
        Some(r) => anyhow::bail!(
            "--lamp-radius {r}: must be between 0 and {} mm (half the lamp distance)",
            rig.geometry.light_distance_mm / 2.0
        ),
        None => gonio_simulator::lamp_radius_mm(&rig)?,
    };
    let light = |q: &[f64]| PointLight {
        position: kin.light_position(q),
        intensity: rig.light.intensity_w_sr,
        radius,
    };
    let raw = |quality: RenderQuality| {
        let r = Renderer::new(sample.clone(), quality);
        let t = Instant::now();
        let imgs: Vec<_> = qs
            .iter()
            .map(|q| {
                r.render_raw(
                    &intr,
                    &kin.camera_pose(q),
                    rig.camera.width,
                    rig.camera.height,
                    &light(q),
                )
            })
            .collect();
        (imgs, t.elapsed().as_secs_f64() * 1e3 / qs.len() as f64)
    };
    let truth = |quality: RenderQuality| {
        let r = Renderer::new(sample.clone(), quality);
        let t = Instant::now();
        let imgs: Vec<_> = qs
            .iter()
            .map(|q| r.render_truth(kin.camera_pose(q).position, 256, 256, &light(q)))
            .collect();
        (imgs, t.elapsed().as_secs_f64() * 1e3 / qs.len() as f64)
    };
    let rel_rmse = |a: &[gonio_devices::image::RgbImage], b: &[gonio_devices::image::RgbImage]| {
        let (mut sq, mut sum, mut n) = (0.0f64, 0.0f64, 0usize);
        for (x, y) in a.iter().zip(b) {
            for (p, r) in x.data.iter().zip(&y.data) {
                sq += ((p - r) as f64).powi(2);
                sum += *r as f64;
                n += 1;
            }
        }
        (sq / n as f64).sqrt() / (sum / n as f64).max(1e-30)
    };
    let q = |supersample, shadow_scale, truth_supersample, area_samples| RenderQuality {
        supersample,
        shadow_scale,
        truth_supersample,
        area_samples,
    };
    // A disc lamp's emitters are a knob too (reference: 64); a point lamp has none.
    let (area_ref, area_knobs): (usize, &[usize]) = if radius > 0.0 { (64, &[1, 4, 16]) } else { (1, &[]) };
    let mut rows = Vec::new();
    // Pixel and shadow knobs are measured with a point lamp (each disc emitter would
    // multiply the reference's cost); the disc's emitter count has its own reference.
    let (raw_ref, _) = raw(q(a.reference, 4, 1, 1));
    for (ss, sh) in [(1, 1), (2, 1), (4, 1), (1, 2), (1, 4), (2, 2)] {
        let (imgs, ms) = raw(q(ss, sh, 1, 1));
        rows.push(RenderRow {
            image: "raw",
            family: match (ss, sh) {
                (_, 1) => "raw: pixel supersampling",
                (1, _) => "raw: shadow-map resolution",
                _ => "raw: both",
            },
            knob: format!("supersample {ss}, shadow map ×{sh}"),
            ms_per_image: ms,
            relative_rmse: rel_rmse(&imgs, &raw_ref),
        });
    }
    let (truth_ref, _) = truth(q(1, 4, a.reference, 1));
    for (ts, sh) in [(1, 1), (2, 1), (4, 1), (1, 4)] {
        let (imgs, ms) = truth(q(1, sh, ts, 1));
        rows.push(RenderRow {
            image: "truth",
            family: if sh == 1 {
                "truth: samples per texel"
            } else {
                "truth: shadow-map resolution"
            },
            knob: format!("samples/texel {ts}², shadow map ×{sh}"),
            ms_per_image: ms,
            relative_rmse: rel_rmse(&imgs, &truth_ref),
        });
    }
    if !area_knobs.is_empty() {
        // Truth images (1 sample per texel): what the disc's emitter count alone costs.
        let (area_ref_imgs, _) = truth(q(1, 1, 1, area_ref));
        for &k in area_knobs {
            let (imgs, ms) = truth(q(1, 1, 1, k));
            rows.push(RenderRow {
                image: "truth",
                family: "truth: disc-lamp emitters",
                knob: format!("disc lamp r = {radius} mm, {k} emitters (ref. {area_ref})"),
                ms_per_image: ms,
                relative_rmse: rel_rmse(&imgs, &area_ref_imgs),
            });
        }
    }
    if let Some(path) = &a.plot {
        std::fs::write(path, render_plot(&a.sample, &rows))
            .map_err(|e| anyhow::anyhow!("--plot {}: cannot write the plot: {e}", path.display()))?;
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&rows)?);
    } else {
        println!(
            "sample {} · {} measurements · reference: {}² samples per pixel/texel, shadow map ×4",
            a.sample,
            qs.len(),
            a.reference
        );
        println!("{:<6} {:<34} {:>12} {:>14}", "image", "knob", "ms/image", "rel. RMSE");
        for r in &rows {
            println!(
                "{:<6} {:<34} {:>12.2} {:>14.5}",
                r.image, r.knob, r.ms_per_image, r.relative_rmse
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Error against time, one line per knob family. A family's first setting (1 sample,
/// shadow map ×1) is also the start of the other families, so each line starts there.
fn render_plot(sample: &str, rows: &[RenderRow]) -> String {
    use gonio::cli::bench::{log_log, Series};
    let mut series: Vec<Series> = Vec::new();
    for r in rows {
        let point = (r.ms_per_image, r.relative_rmse, r.knob.clone());
        match series.iter_mut().find(|s| s.name == r.family) {
            Some(s) => s.points.push(point),
            None => series.push(Series {
                name: r.family.into(),
                points: vec![point],
            }),
        }
    }
    for s in &mut series {
        s.points.sort_by(|a, b| a.0.total_cmp(&b.0));
    }
    log_log(
        &format!("gonio bench render · sample {sample}: error against a high-sample reference"),
        "ms per image",
        "relative RMSE",
        &series,
    )
}
