//! `gonio calibrate RECIPE --rig R --out DIR`: run a calibration recipe and write its
//! versioned result (`DIR/calibration.json`, plus `DIR/corners.json` for intrinsics).

use super::common::{load_sample, RigArgs};
use anyhow::{Context, Result};
use gonio_acquire::calibrate::{self, Recipe};
use gonio_acquire::rig::Rig;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct CalibrateArgs {
    /// Recipe TOML (see calibration/recipes/).
    pub recipe: PathBuf,
    #[command(flatten)]
    pub rig: RigArgs,
    /// Output directory (created; existing result files in it are replaced).
    #[arg(long, default_value = "gonio-calibration")]
    pub out: PathBuf,
    /// Override the recipe's simulated sensor noise setting: on.
    #[arg(long)]
    pub noise: bool,
    /// Print the result as JSON on stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: CalibrateArgs) -> Result<ExitCode> {
    let recipe = Recipe::load(&a.recipe)?;
    let spec = a.rig.load()?;
    let sample = load_sample(&recipe.target)?;
    let mut opts = recipe.sim_options();
    if a.noise {
        opts.noise = Some(true);
    }
    let rig = Rig::build(&spec, &sample, &opts)?;
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let out = rt.block_on(calibrate::run(&recipe, &rig))?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let path = a.out.join("calibration.json");
    std::fs::write(&path, serde_json::to_string_pretty(&out.result)?)
        .with_context(|| format!("writing {}", path.display()))?;
    if let Some(c) = &out.corners {
        let p = a.out.join("corners.json");
        std::fs::write(&p, serde_json::to_string(c)?).with_context(|| format!("writing {}", p.display()))?;
        if let Some(u) = &out.result.projection_uncertainty {
            let p = a.out.join("uncertainty.png");
            calibrate::uncertainty::heat_map(u, &c.views)
                .save(&p)
                .with_context(|| format!("writing {}", p.display()))?;
        }
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&out.result)?);
        return Ok(ExitCode::SUCCESS);
    }
    let r = &out.result;
    println!(
        "calibration {} ({}) on rig `{}`: id {}",
        recipe.name, r.kind, r.rig, r.id
    );
    if let Some(c) = &r.intrinsics {
        let (m, s) = (&c.camera, &c.sigma);
        println!(
            "  fx {:.3} ± {:.3}  fy {:.3} ± {:.3}  cx {:.3} ± {:.3}  cy {:.3} ± {:.3} px",
            m.fx, s.fx, m.fy, s.fy, m.cx, s.cx, m.cy, s.cy
        );
        println!(
            "  distortion k1 {:.5} k2 {:.5} p1 {:.6} p2 {:.6} k3 {:.5}",
            m.distortion[0], m.distortion[1], m.distortion[2], m.distortion[3], m.distortion[4]
        );
        println!(
            "  {} views, {} corners, reprojection RMS {:.4} px, condition {:.3e}, {} LM iterations",
            c.poses.len(),
            c.points,
            c.rms_px,
            c.condition,
            c.iterations
        );
    }
    if let (Some(t), Some(e)) = (&r.truth, &r.errors) {
        println!(
            "  truth fx {:.3} fy {:.3} cx {:.3} cy {:.3}: errors fx {:+.4} % fy {:+.4} % cx {:+.3} px ({:+.4} %) cy {:+.3} px ({:+.4} %)",
            t.fx, t.fy, t.cx, t.cy, e.fx_percent, e.fy_percent, e.cx_px, e.cx_percent, e.cy_px, e.cy_percent
        );
    }
    if let Some(u) = &r.projection_uncertainty {
        println!(
            "  projection uncertainty (1 sigma): whole image max {:.3} px, median {:.3} px; sample region max {} px; \
             corners cover {:.1} % of the image (bbox {:.0}-{:.0} x {:.0}-{:.0}); covariance condition {:.2e} \
             (uncertainty.png)",
            u.max_px,
            u.median_px,
            u.sample_max_px.map_or("-".into(), |m| format!("{m:.3}")),
            100.0 * u.coverage_fraction,
            u.corner_bbox_px[0],
            u.corner_bbox_px[2],
            u.corner_bbox_px[1],
            u.corner_bbox_px[3],
            u.covariance_condition
        );
        if let Some(w) = &u.warning {
            println!("  WARNING: {w}");
        }
    }
    if let Some(t) = &r.projection_truth {
        println!(
            "  truth: projection error max {:.3} px at ({:.0}, {:.0}), sample region max {} px; \
             max error/sigma {:.2}, {:.1} % of the grid beyond 3 sigma",
            t.max_error_px,
            t.max_error_at_px[0],
            t.max_error_at_px[1],
            t.sample_max_error_px.map_or("-".into(), |m| format!("{m:.3}")),
            t.max_error_over_sigma,
            100.0 * t.beyond_3_sigma_fraction
        );
    }
    if !r.corner_truth_rms_px.is_empty() {
        let v = &r.corner_truth_rms_px;
        println!(
            "  corner error against the simulator's exact projection: RMS per view {:.4} … {:.4} px",
            v.iter().copied().fold(f64::INFINITY, f64::min),
            v.iter().copied().fold(0.0, f64::max)
        );
    }
    if !r.effort.is_empty() {
        println!("  views  capture_s  fit_ms  rms_px   fx_err_%   cx_err_px  cy_err_px");
        for row in &r.effort {
            match &row.failure {
                None => println!(
                    "  {:5}  {:9.1}  {:6.1}  {:6.4}  {:+9.4}  {:+9.3}  {:+9.3}",
                    row.views,
                    row.capture_s,
                    1e3 * row.fit_s,
                    row.rms_px,
                    row.fx_error_percent,
                    row.cx_error_px,
                    row.cy_error_px
                ),
                Some(f) => println!("  {:5}  {:9.1}  refused: {f}", row.views, row.capture_s),
            }
        }
    }
    if let Some(w) = &r.white_standard {
        let k = &w.radiometric.k;
        println!(
            "  K (value per W m⁻² sr⁻¹ · s · gain) R {:.6e} G {:.6e} B {:.6e}; lamp {} W/sr, radius {} mm",
            k[0], k[1], k[2], w.radiometric.lamp.intensity_w_sr, w.radiometric.lamp.radius_mm
        );
        println!(
            "  {} poses × {}² texels, residual |measured/model − 1|: RMS {:.5}, max {:.5}",
            w.poses.len(),
            w.texels,
            w.residual_rms,
            w.residual_max
        );
        if let (Some(t), Some(e)) = (&w.truth_k, &w.k_error_percent) {
            println!(
                "  truth K {:.6e}: errors R {:+.4} % G {:+.4} % B {:+.4} %",
                t[0], e[0], e[1], e[2]
            );
        }
        println!("  poses  capture_s  K error %");
        for row in &w.effort {
            println!("  {:5}  {:9.1}  {:9.4}", row.poses, row.capture_s, row.k_error_percent);
        }
    }
    if let Some(x) = &r.radiometric {
        print!("{}", x.table());
    }
    if let Some(m) = &r.mechanical {
        println!("  axis         repeat_°   backlash_°  offset_°    scale      resid_rms_°  (reference − read-back, approach {} °)", m.approach_deg);
        for a in &m.axes {
            println!(
                "  {:<11} {:9.5}  {:9.5}  {:+9.5}  {:+10.3e}  {:9.5}",
                a.axis,
                a.homing.repeatability_deg,
                a.backlash.mean_deg,
                a.positioning.offset_deg,
                a.positioning.scale_error,
                a.positioning.residual_rms_deg
            );
            if let (Some(t), Some(e)) = (&a.truth, &a.errors) {
                println!(
                    "    truth: backlash {:.5} (error {:+.2e}), repeatability σ {:.5} drawn {:.5} (error {:+.2e}), scale {:+.3e} (error {:+.2e}), residual error {:+.2e}",
                    t.model.backlash_deg,
                    e.backlash_deg,
                    t.model.home_sigma_deg,
                    t.realized_repeatability_deg,
                    e.repeatability_vs_realized_deg,
                    t.fit.scale_error,
                    e.scale_error,
                    e.residual_rms_deg
                );
            }
            for row in a
                .effort
                .iter()
                .filter(|r| r.used == 2 || r.used == 5 || r.stage == "bidirectional" || r.used % 10 == 0)
            {
                println!(
                    "    {:<13} {:4} used  rig {:8.1} s  estimate {:.5}°  error {:+.2e}°",
                    row.stage, row.used, row.rig_time_s, row.estimate_deg, row.error_deg
                );
            }
        }
    }
    if let Some(g) = &r.rig_geometry {
        print_rig_geometry(g);
    }
    if let Some(g) = &r.light_geometry {
        print_light_geometry(g);
    }
    println!("  rig time {:.1} s; wrote {}", r.rig_time_s, path.display());
    Ok(ExitCode::SUCCESS)
}

/// The human summary of a light-geometry calibration: the two lamp offsets (with the truth
/// on the simulator), the highlight residuals and localisation error, the light-direction
/// errors over the Bonn pairs and the error-versus-poses table.
fn print_light_geometry(g: &calibrate::light_geometry::LightGeometryCalibration) {
    let f = &g.fit;
    let peak = g.highlights.iter().map(|h| h.peak).fold(0.0, f64::max);
    println!(
        "  {} poses, highlight RMS residual {:.4} px (zero offsets {:.4} px), condition {:.3} (design {:.3}), {} LM iterations, brightest highlight {:.2} of full scale",
        f.poses, f.rms_px, f.initial_rms_px, f.condition, g.design_condition, f.iterations, peak
    );
    if g.camera_alignment.is_none() {
        println!("  camera pose from the nominal kinematics (no [alignment] in the rig file)");
    }
    println!("  parameter                     estimate_°   σ_°        truth_°    error_°");
    for p in &f.parameters {
        match g.errors.as_ref().and_then(|e| e.iter().find(|e| e.name == p.name)) {
            Some(t) => println!(
                "  {:<28} {:+10.5}  {:9.2e}  {:+9.5}  {:+9.2e}",
                p.name, p.value_deg, p.sigma_deg, t.truth_deg, t.error_deg
            ),
            None => println!("  {:<28} {:+10.5}  {:9.2e}", p.name, p.value_deg, p.sigma_deg),
        }
    }
    if let Some(l) = &g.localisation {
        println!(
            "  highlight localisation vs exact reflection point: mean ({:+.4}, {:+.4}) px, RMS {:.4} px, max {:.4} px",
            l.mean_px[0], l.mean_px[1], l.rms_px, l.max_px
        );
    }
    if let (Some(b), Some(a)) = (&g.directions_before, &g.directions_after) {
        println!(
            "  light direction error over {} Bonn pairs: max {:.4}° mean {:.4}° before, max {:.5}° mean {:.5}° after",
            a.pairs, b.light_max_deg, b.light_mean_deg, a.light_max_deg, a.light_mean_deg
        );
    }
    if !g.effort.is_empty() {
        println!("  poses  capture_s  fit_ms  rms_px   max_param_err_°  light_max_err_°");
        let opt = |x: Option<f64>, w: usize, p: usize| x.map_or(format!("{:>w$}", "-"), |v| format!("{v:w$.p$}"));
        for row in &g.effort {
            match &row.failure {
                None => println!(
                    "  {:5}  {:9.1}  {:6.2}  {}  {}  {}",
                    row.poses,
                    row.capture_s,
                    1e3 * row.fit_s,
                    opt(row.rms_px, 6, 4),
                    opt(row.max_parameter_error_deg, 15, 5),
                    opt(row.light_max_error_deg, 15, 5)
                ),
                Some(e) => println!("  {:5}  {:9.1}  refused: {e}", row.poses, row.capture_s),
            }
        }
    }
}

/// The human summary of a rig-geometry calibration: each estimated parameter (with the
/// truth on the simulator), the reprojection before and after, the direction errors over
/// the Bonn pairs and the error-versus-views table.
fn print_rig_geometry(g: &calibrate::rig_geometry::RigGeometryCalibration) {
    let f = &g.fit;
    println!(
        "  {} views, {} corners, reprojection RMS {:.4} px (nominal kinematics {:.4} px), condition {:.3e}, {} LM iterations",
        g.view_axes_deg.len(),
        f.points,
        f.rms_px,
        f.initial_rms_px,
        f.condition,
        f.iterations
    );
    println!("  parameter                     estimate_°   σ_°        truth_°    error_°");
    for p in &f.parameters {
        let truth = g.errors.as_ref().and_then(|e| e.iter().find(|e| e.name == p.name));
        match truth {
            Some(t) => println!(
                "  {:<28} {:+10.5}  {:9.2e}  {:+9.5}  {:+9.2e}",
                p.name, p.value_deg, p.sigma_deg, t.truth_deg, t.error_deg
            ),
            None => println!("  {:<28} {:+10.5}  {:9.2e}", p.name, p.value_deg, p.sigma_deg),
        }
    }
    if !f.unobserved_axes.is_empty() {
        println!(
            "  not observable from target images (kept as in the rig file): {}",
            f.unobserved_axes.join(", ")
        );
    }
    if let (Some(b), Some(a)) = (&g.directions_before, &g.directions_after) {
        println!(
            "  direction error over {} Bonn pairs: view max {:.4}° mean {:.4}° before, max {:.4}° mean {:.4}° after; light max {:.4}° before, {:.4}° after",
            a.pairs, b.view_max_deg, b.view_mean_deg, a.view_max_deg, a.view_mean_deg, b.light_max_deg, a.light_max_deg
        );
    }
    if !g.effort.is_empty() {
        println!("  views  capture_s  fit_ms  rms_px   max_param_err_°  view_max_err_°");
        let opt = |x: Option<f64>, w: usize, p: usize| x.map_or(format!("{:>w$}", "-"), |v| format!("{v:w$.p$}"));
        for row in &g.effort {
            match &row.failure {
                None => println!(
                    "  {:5}  {:9.1}  {:6.1}  {}  {}  {}",
                    row.views,
                    row.capture_s,
                    1e3 * row.fit_s,
                    opt(row.rms_px, 6, 4),
                    opt(row.max_parameter_error_deg, 15, 5),
                    opt(row.view_max_error_deg, 14, 5)
                ),
                Some(e) => println!("  {:5}  {:9.1}  refused: {e}", row.views, row.capture_s),
            }
        }
    }
}
