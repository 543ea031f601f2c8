//! `gonio bench sim`: the simulator's stages (raw render, ground truth, sensor) timed per
//! sample kind, as ratios to the first sample.

use anyhow::Result;
use gonio::cli::bench::{load_sample, RigArgs};
use gonio_dataset::sweep;
use gonio_devices::kinematics;
use gonio_simulator::sensor::SensorModel;
use gonio_simulator::{PointLight, RenderQuality, Renderer};
use serde::Serialize;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

#[derive(clap::Args, Debug)]
pub struct SimBenchArgs {
    #[command(flatten)]
    pub rig: RigArgs,
    /// Samples to time (built-in names or files).
    #[arg(long, num_args = 1.., default_values_t = ["white-standard".to_string(), "calibration-target".to_string(), "wallpaper".to_string(), "leather".to_string()])]
    pub samples: Vec<String>,
    /// Measurements (Bonn pairs, spread over the sweep) per sample.
    #[arg(long, default_value_t = 40)]
    pub measurements: usize,
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct SimRow {
    sample: String,
    relief: bool,
    homogeneous: bool,
    raw_ms: f64,
    truth_ms: f64,
    sensor_noise_ms: f64,
    sensor_noiseless_ms: f64,
    shadow_maps_built: usize,
    raw_vs_first: f64,
}

pub fn run(a: SimBenchArgs) -> Result<ExitCode> {
    let rig = a.rig.load()?;
    let kin = kinematics::for_rig(&rig);
    let dirs = sweep::bonn81();
    let pairs: Vec<_> = (0..a.measurements.max(1))
        .map(|k| {
            let idx = (k * 6561 / a.measurements.max(1) + 7) % 6561;
            (dirs[idx % 81], dirs[idx / 81])
        })
        .filter_map(|(l, v)| kin.inverse(l, v, None).ok().map(|s| s[0].clone()))
        .collect();
    let intr = rig.camera.intrinsics();
    let mut rows: Vec<SimRow> = Vec::new();
    for name in &a.samples {
        let spec = load_sample(name)?;
        let sample = Arc::new(spec.build()?);
        let relief = matches!(sample.surface, gonio_simulator::sample::Surface::Height(_));
        let homogeneous = sample.is_homogeneous();
        let r = Renderer::new(sample, RenderQuality::default());
        let lights: Vec<PointLight> = pairs
            .iter()
            .map(|q| PointLight::point(kin.light_position(q), 50.0))
            .collect();
        let t = Instant::now();
        let mut last = None;
        for (q, l) in pairs.iter().zip(&lights) {
            last = Some(r.render_raw(&intr, &kin.camera_pose(q), rig.camera.width, rig.camera.height, l));
        }
        let raw_ms = t.elapsed().as_secs_f64() * 1e3 / pairs.len() as f64;
        let t = Instant::now();
        for (q, l) in pairs.iter().zip(&lights) {
            let _ = r.render_truth(kin.camera_pose(q).position, 256, 256, l);
        }
        let truth_ms = t.elapsed().as_secs_f64() * 1e3 / pairs.len() as f64;
        let frame = last.expect("at least one measurement");
        let mut sensor = SensorModel {
            full_well_e: 20000.0,
            read_noise_e: 4.0,
            dark_current_e_s: 5.0,
            sensitivity_e_per_radiance_s: 14000.0,
            vignetting: 0.05,
            bit_depth: 12,
            gain: 1.0,
            exposure_s: 0.05,
            noise: true,
            seed: 1,
        };
        let reps = 10;
        let t = Instant::now();
        for k in 0..reps {
            let _ = sensor.expose(&frame, k);
        }
        let sensor_noise_ms = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
        sensor.noise = false;
        let t = Instant::now();
        for k in 0..reps {
            let _ = sensor.expose(&frame, k);
        }
        let sensor_noiseless_ms = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
        let first = rows.first().map(|r| r.raw_ms).unwrap_or(raw_ms);
        rows.push(SimRow {
            sample: name.clone(),
            relief,
            homogeneous,
            raw_ms,
            truth_ms,
            sensor_noise_ms,
            sensor_noiseless_ms,
            shadow_maps_built: r.shadow_maps_built(),
            raw_vs_first: raw_ms / first,
        });
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&rows)?);
    } else {
        println!(
            "{:<20} {:>6} {:>5} {:>9} {:>9} {:>11} {:>14} {:>7} {:>8}",
            "sample", "relief", "homog", "raw ms", "truth ms", "sensor ms", "noiseless ms", "shadows", "raw/1st"
        );
        for r in &rows {
            println!(
                "{:<20} {:>6} {:>5} {:>9.2} {:>9.2} {:>11.2} {:>14.2} {:>7} {:>8.2}",
                r.sample,
                r.relief,
                r.homogeneous,
                r.raw_ms,
                r.truth_ms,
                r.sensor_noise_ms,
                r.sensor_noiseless_ms,
                r.shadow_maps_built,
                r.raw_vs_first
            );
        }
        println!(
            "({} measurements per sample, {}×{} raw frames, 256² truth)",
            pairs.len(),
            rig.camera.width,
            rig.camera.height
        );
    }
    Ok(ExitCode::SUCCESS)
}
