//! `gonio sim …`: the simulator on its own.

use super::common::{load_sample, parse_angles, RigArgs};
use anyhow::{bail, Context, Result};
use gonio_acquire::develop::frame_to_linear;
use gonio_acquire::develop::rectify::{self, RectifyParams};
use gonio_acquire::rig::Rig;
use gonio_dataset::store;
use gonio_devices::image::RgbImage;
use gonio_devices::Direction;
use gonio_simulator::{RenderQuality, SimOptions};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(clap::Subcommand, Debug)]
pub enum SimCommand {
    /// Render one measurement: the raw frame, its rectification, or the exact ground truth.
    Render(RenderArgs),
    /// A complete synthetic ground-truth BTF (every pair of a sweep, exact, noiseless) as
    /// a native dataset, without simulating the acquisition.
    Btf(super::sim_btf::BtfArgs),
    /// Emulate a motor controller (Zaber ASCII or Newport ESP300) on a pty until killed.
    ServeStage(super::serve_stage::ServeStageArgs),
    /// Emulate the lamp's power supply (a Rohde & Schwarz HMP4040 with a halogen lamp on
    /// each channel) on a pty until killed.
    ServeLight(super::serve_light::ServeLightArgs),
}

#[derive(Clone, Copy, Debug, clap::ValueEnum, PartialEq)]
pub enum RenderKind {
    /// The camera's raw frame (sensor model applied).
    Raw,
    /// The raw frame rectified onto the sample plane.
    Rectified,
    /// The exact rectified image rendered in texture space (no sensor noise).
    Truth,
    /// The radiance image the camera sees (W m⁻² sr⁻¹ per pixel, before the sensor):
    /// what an independent renderer (Mitsuba, tests/interop/mitsuba_frame.py) is compared with.
    Radiance,
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
    /// Also write the scene (camera pose and intrinsics, light position and intensity,
    /// sample size; millimetres, sample frame) as JSON, for rendering it elsewhere.
    #[arg(long)]
    pub scene_json: Option<PathBuf>,
    /// Print what was written as JSON on stdout (out, kind, width, height, radiance_unit,
    /// scene_json) instead of the sentence on stderr.
    #[arg(long)]
    pub json: bool,
}

pub fn run(cmd: SimCommand) -> Result<ExitCode> {
    match cmd {
        SimCommand::Render(a) => render(a),
        SimCommand::Btf(a) => super::sim_btf::run(a),
        SimCommand::ServeStage(a) => super::serve_stage::run(a),
        SimCommand::ServeLight(a) => super::serve_light::run(a),
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
    if let Some(path) = &a.scene_json {
        write_scene_json(path, &spec, &rig, &sample, a.light, a.view)?;
    }
    let q = configuration(&rig, a.light, a.view)?;
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let img = rt.block_on(async {
        let config = rig.prepare().await?;
        rig.reach(&q).await?;
        match kind {
            RenderKind::Truth | RenderKind::Radiance => {
                let t = rig.truth.as_ref().expect("simulated rig has truth");
                Ok::<RgbImage, anyhow::Error>(if kind == RenderKind::Truth {
                    t.truth(&q, a.size, a.size)
                } else {
                    t.radiance(&q)
                })
            }
            _ => {
                let policy = rig.capture_policy()?;
                let (frame, _) = rig
                    .capture(&policy, &config)
                    .await
                    .map_err(|f| anyhow::anyhow!("camera failed after {} attempt(s): {}", f.attempts, f.source))?;
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
    let unit = if kind == RenderKind::Radiance {
        ", radiance W m⁻² sr⁻¹"
    } else {
        ""
    };
    if a.json {
        let r = serde_json::json!({
            "out": a.out.display().to_string(),
            "kind": clap::ValueEnum::to_possible_value(&kind).map(|v| v.get_name().to_string()),
            "width": img.width,
            "height": img.height,
            // radiance in W m⁻² sr⁻¹; every other kind in the dataset's linear unit
            "radiance_unit": (kind == RenderKind::Radiance).then_some("W m^-2 sr^-1"),
            "scene_json": a.scene_json.as_ref().map(|p| p.display().to_string()),
        });
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        eprintln!("wrote {} ({}×{}{unit})", a.out.display(), img.width, img.height);
    }
    Ok(ExitCode::SUCCESS)
}

/// The first IK solution of a pair, or an error naming the rig.
fn configuration(rig: &Rig, light: Direction, view: Direction) -> Result<Vec<f64>> {
    let sols = rig
        .kinematics
        .inverse(light, view, None)
        .map_err(|e| anyhow::anyhow!("rig `{}` cannot measure this pair: {e}", rig.spec.name))?;
    Ok(sols[0].clone())
}

/// The scene of one measurement as JSON (see `--scene-json`).
fn write_scene_json(
    path: &Path,
    spec: &gonio_devices::rig::RigSpec,
    rig: &Rig,
    sample: &gonio_simulator::SampleSpec,
    light: Direction,
    view: Direction,
) -> Result<()> {
    let q = configuration(rig, light, view)?;
    let pose = rig.kinematics.camera_pose(&q);
    let lp = rig.kinematics.light_position(&q);
    let v = |p: gonio_devices::geometry::Vec3| [p.x, p.y, p.z];
    let intr = spec.camera.intrinsics();
    let scene = serde_json::json!({
        "units": "mm, sample frame (z = sample normal); radiance W m^-2 sr^-1",
        "camera": {
            "position": v(pose.position), "right": v(pose.right), "down": v(pose.down), "forward": v(pose.forward),
            "fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
            "width": spec.camera.width, "height": spec.camera.height,
        },
        "light": { "position": v(lp), "intensity_w_sr": spec.light.intensity_w_sr },
        "sample": { "name": sample.name, "size_mm": sample.size_mm },
        "axes_deg": q.iter().map(|x| x.to_degrees()).collect::<Vec<_>>(),
    });
    std::fs::write(path, serde_json::to_vec_pretty(&scene)?).with_context(|| format!("writing {}", path.display()))
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
            let bytes = store::export::to_srgb8(img);
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
