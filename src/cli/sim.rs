//! `gonio sim …`: the simulator on its own.

use super::common::{load_sample, parse_angles, RigArgs};
use crate::engine::{frame_to_linear, Rig};
use crate::rectify::{self, RectifyParams};
use crate::store;
use anyhow::{bail, Context, Result};
use gonio_devices::image::RgbImage;
use gonio_devices::Direction;
use gonio_simulator::{RenderQuality, SimOptions};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(clap::Subcommand, Debug)]
pub enum SimCommand {
    /// Render one measurement: the raw frame, its rectification, or the exact ground truth.
    Render(RenderArgs),
}

#[derive(Clone, Copy, Debug, clap::ValueEnum, PartialEq)]
pub enum RenderKind {
    /// The camera's raw frame (sensor model applied).
    Raw,
    /// The raw frame rectified onto the sample plane.
    Rectified,
    /// The exact rectified image rendered in texture space (no sensor noise).
    Truth,
}

#[derive(clap::Args, Debug)]
pub struct RenderArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    /// Built-in sample name or sample TOML file.
    #[arg(long, default_value = gonio_simulator::sample::DEFAULT_SAMPLE)]
    pub sample: String,
    /// Light direction `θ,φ` in degrees.
    #[arg(long, value_parser = parse_angles)]
    pub light: Direction,
    /// View direction `θ,φ` in degrees.
    #[arg(long, value_parser = parse_angles)]
    pub view: Direction,
    #[arg(long, value_enum, default_value = "raw")]
    pub kind: RenderKind,
    /// Shorthand for --kind raw.
    #[arg(long, conflicts_with_all = ["kind", "rectified"])]
    pub raw: bool,
    /// Shorthand for --kind rectified.
    #[arg(long, conflicts_with = "kind")]
    pub rectified: bool,
    /// Rectified/truth size (texels per side).
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    #[arg(long)]
    pub no_noise: bool,
    /// Pixel supersampling per axis of the raw render.
    #[arg(long, default_value_t = 1)]
    pub supersample: usize,
    /// Output image: .png (8-bit sRGB) or .exr (linear float).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(cmd: SimCommand) -> Result<ExitCode> {
    match cmd {
        SimCommand::Render(a) => render(a),
    }
}

fn render(a: RenderArgs) -> Result<ExitCode> {
    let kind = if a.raw {
        RenderKind::Raw
    } else if a.rectified {
        RenderKind::Rectified
    } else {
        a.kind
    };
    if !(8..=8192).contains(&a.size) {
        bail!("--size {}: valid range is 8 ..= 8192", a.size);
    }
    if !(1..=16).contains(&a.supersample) {
        bail!("--supersample {}: valid range is 1 ..= 16", a.supersample);
    }
    let spec = a.rig.load()?;
    let sample = load_sample(&a.sample)?;
    let opts = SimOptions {
        noise: Some(!a.no_noise),
        quality: RenderQuality {
            supersample: a.supersample,
            ..Default::default()
        },
        ..Default::default()
    };
    let rig = Rig::build(&spec, &sample, &opts)?;
    let sols = rig
        .kinematics
        .inverse(a.light, a.view, None)
        .map_err(|e| anyhow::anyhow!("rig `{}` cannot measure this pair: {e}", spec.name))?;
    let q = sols[0].clone();
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let img = rt.block_on(async {
        crate::engine::prepare(&rig).await?;
        for (axis, &t) in rig.axes.iter().zip(&q) {
            axis.move_abs(t).await.map_err(crate::engine::EngineError::Setup)?;
        }
        match kind {
            RenderKind::Truth => {
                let t = rig.truth.as_ref().expect("simulated rig has truth");
                Ok::<RgbImage, anyhow::Error>(t.truth(&q, a.size, a.size))
            }
            _ => {
                let frame = rig.camera.capture().await.map_err(crate::engine::EngineError::Setup)?;
                let raw = frame_to_linear(&frame);
                if kind == RenderKind::Raw {
                    return Ok(raw);
                }
                let params = RectifyParams {
                    width: a.size,
                    height: a.size,
                    sample_mm: rig.sample_mm,
                    max_supersample: 8,
                };
                let pose = rig.kinematics.camera_pose(&q);
                let r = rectify::rectify_frame(&raw, &spec.camera.intrinsics(), &pose, &rig.border, &params)
                    .map_err(|e| anyhow::anyhow!("rectification failed: {e}"))?;
                Ok(r.image)
            }
        }
    })?;
    write_image(&a.out, &img)?;
    eprintln!("wrote {} ({}×{})", a.out.display(), img.width, img.height);
    Ok(ExitCode::SUCCESS)
}

/// Write PNG (8-bit sRGB, values clamped to [0, 1]) or EXR (linear) by extension.
pub fn write_image(path: &Path, img: &RgbImage) -> Result<()> {
    match path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .as_deref()
    {
        Some("exr") => store::write_exr(path, img).with_context(|| format!("writing {}", path.display()))?,
        Some("png") => {
            let bytes = store::ubo2003::to_srgb8(img);
            image::save_buffer(
                path,
                &bytes,
                img.width as u32,
                img.height as u32,
                image::ColorType::Rgb8,
            )
            .with_context(|| format!("writing {}", path.display()))?;
        }
        _ => bail!(
            "{}: unknown image type; use .png (8-bit sRGB) or .exr (linear float)",
            path.display()
        ),
    }
    Ok(())
}
