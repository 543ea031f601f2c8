//! `gonio render`: the CPU reference picture of the viewer (see `gonio::view::render`).

use crate::view::params;
use crate::view::render::{self, Scene, Shape};
use crate::view::source::Source;
use anyhow::{Context, Result};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub struct RenderArgs {
    /// A gonio dataset directory, a `.gbtf` or a UBO2014 `.btf` file.
    pub file: PathBuf,
    /// Light direction `θ,φ` in degrees (directional light, world = sample frame).
    #[arg(long, value_parser = |s: &str| params::direction("light", s))]
    pub light: [f64; 2],
    /// View direction `θ,φ` in degrees (orthographic camera looking along −view).
    #[arg(long, value_parser = |s: &str| params::direction("view", s))]
    pub view: [f64; 2],
    /// plane, sphere or cylinder.
    #[arg(long, default_value = "plane", value_parser = |s: &str| params::shape("shape", s))]
    pub shape: Shape,
    /// Picture size WxH in pixels.
    #[arg(long, default_value = "256x256", value_parser = |s: &str| params::size("size", s))]
    pub size: (usize, usize),
    /// Multiplier on the linear values before tone mapping (clamp, sRGB, 8 bits).
    #[arg(long, default_value = "1", value_parser = |s: &str| params::exposure("exposure", s))]
    pub exposure: f64,
    /// Output PNG (8-bit sRGB).
    #[arg(long)]
    pub out: PathBuf,
    /// A glTF fit (`gonio fit --model gltf --per-texel`) as the exported material: unit
    /// irradiance, nominal directions, no rig gain (what `gonio export --format mitsuba`
    /// renders to in Mitsuba with a unit `directional` emitter).
    #[arg(long)]
    pub material: bool,
    #[arg(long)]
    pub json: bool,
}

#[derive(serde::Serialize)]
struct Report<'a> {
    source: crate::view::source::SourceKind,
    out: String,
    scene: &'a Scene,
    stats: &'a render::RenderStats,
    seconds: f64,
}

pub fn run(a: RenderArgs) -> Result<ExitCode> {
    let t0 = std::time::Instant::now();
    let src = Source::open(&a.file).with_context(|| format!("opening {}", a.file.display()))?;
    let material = if a.material {
        let g = gonio_btf::compress::Gbtf::read(&a.file).with_context(|| format!("reading {}", a.file.display()))?;
        Some(gonio_btf::export::UnitIrradiance::new(g).with_context(|| format!("--material: {}", a.file.display()))?)
    } else {
        None
    };
    let scene = Scene {
        light_deg: a.light,
        view_deg: a.view,
        shape: a.shape,
        width: a.size.0,
        height: a.size.1,
        exposure: a.exposure,
    };
    let model: &dyn gonio_btf::compress::interp::BtfModel = match &material {
        Some(m) => m,
        None => src.model(),
    };
    let pic = render::render(model, &scene).with_context(|| format!("rendering {}", a.file.display()))?;
    let png = render::png(pic.width, pic.height, &pic.srgb8)?;
    gonio_dataset::store::atomic::write_atomic(&a.out, &png, None)
        .with_context(|| format!("writing {}", a.out.display()))?;
    let report = Report {
        source: src.kind(),
        out: a.out.display().to_string(),
        scene: &scene,
        stats: &pic.stats,
        seconds: t0.elapsed().as_secs_f64(),
    };
    if a.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "{}: {} {}×{}, light {:?}°, view {:?}°: {} shape pixels ({} in shadow, {} without measurements nearby), {} grid pairs, {:.2} s",
            report.out,
            scene.shape.name(),
            scene.width,
            scene.height,
            scene.light_deg,
            scene.view_deg,
            pic.stats.shape_pixels,
            pic.stats.shadowed_pixels,
            pic.stats.unmeasured_pixels,
            pic.stats.grid_pairs,
            report.seconds
        );
    }
    Ok(ExitCode::SUCCESS)
}
