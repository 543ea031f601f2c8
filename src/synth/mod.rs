//! Synthetic BTFs straight from the simulator's ground truth, without simulating an
//! acquisition: every (light, view) pair of a sweep, rendered exactly in texture space.
//!
//! Why: users generate datasets to test other software (compressors, renderers, fitting
//! code) and want the exact BTF fast, with no sensor noise, no rectification error and no
//! rig limits. An acquisition takes hours of rig time (minutes of simulation); this takes
//! one trace per view and one shading per pair: [`Renderer::truth_view`] traces the
//! camera's rays once per view (parallax and masking depend on the camera only), then
//! [`Renderer::shade_truth`] shades them for each light (shadow maps are cached per light).
//!
//! Geometry: an ideal rig in the sample frame, the camera at the rig's
//! `camera_distance_mm` along the view direction, the lamp at `light_distance_mm` along the
//! light direction. No pair is infeasible (nothing blocks the lamp), so the BTF is complete.
//! Values are the acquisition's ground-truth units (normalised sensor signal, as
//! `SimWorld::truth`), so a synthetic BTF and a simulated acquisition of the same sample and
//! rig can be compared directly.

pub mod dataset;
pub mod family;

use gonio_dataset::sweep::Sweep;
use gonio_devices::image::RgbImage;
use gonio_devices::rig::RigSpec;
use gonio_devices::{Direction, Vec3};
use gonio_simulator::sensor::SensorModel;
use gonio_simulator::{PointLight, Renderer};

/// Where the camera and lamp stand for a pair (mm, sample frame).
pub fn positions(rig: &RigSpec, light: Direction, view: Direction) -> (Vec3, Vec3) {
    (
        view.vector() * rig.geometry.camera_distance_mm,
        light.vector() * rig.geometry.light_distance_mm,
    )
}

/// The rig's lamp at `position`, with its disc radius (`gonio_simulator::lamp_radius_mm`,
/// validated once by the caller).
pub fn lamp_at(rig: &RigSpec, radius: f64, position: Vec3) -> PointLight {
    PointLight {
        position,
        intensity: rig.light.intensity_w_sr,
        radius,
    }
}

/// Render every pair of `sweep` view by view; `sink(view, light, image)` receives each
/// image (view-major, lights in sweep order) and may stop the run by returning an error.
/// `scale` converts radiance into the output units (see [`truth_scale`]).
pub fn render_btf<E>(
    renderer: &Renderer,
    rig: &RigSpec,
    radius: f64,
    sweep: &Sweep,
    size: usize,
    scale: f32,
    sink: impl FnMut(usize, usize, RgbImage) -> Result<(), E>,
) -> Result<(), E> {
    render_btf_views(renderer, rig, radius, sweep, 0..sweep.views.len(), size, scale, sink)
}

/// [`render_btf`] for the views `views` only (a shard, see `gonio_dataset::shard`); `sink` gets
/// the canonical view index. Each view is rendered exactly as in a full run, so the
/// shards of a split give the same images as one process.
#[allow(clippy::too_many_arguments)]
pub fn render_btf_views<E>(
    renderer: &Renderer,
    rig: &RigSpec,
    radius: f64,
    sweep: &Sweep,
    views: std::ops::Range<usize>,
    size: usize,
    scale: f32,
    mut sink: impl FnMut(usize, usize, RgbImage) -> Result<(), E>,
) -> Result<(), E> {
    for (vi, &view) in sweep.views.iter().enumerate().skip(views.start).take(views.len()) {
        let (camera, _) = positions(rig, sweep.lights[0], view);
        let traced = renderer.truth_view(camera, size, size);
        for (li, &light) in sweep.lights.iter().enumerate() {
            let (_, lamp) = positions(rig, light, view);
            let mut img = renderer.shade_truth(&traced, &lamp_at(rig, radius, lamp));
            if scale != 1.0 {
                img.data.iter_mut().for_each(|v| *v *= scale);
            }
            sink(vi, li, img)?;
        }
    }
    Ok(())
}

/// The factor from radiance to the acquisition's ground-truth units for a sensor.
pub fn truth_scale(sensor: &SensorModel) -> f32 {
    let one = RgbImage {
        width: 1,
        height: 1,
        data: vec![1.0; 3],
    };
    sensor.normalize_truth(&one).data[0]
}

#[cfg(test)]
mod tests {
    use super::*;
    use gonio_simulator::{RenderQuality, SampleSpec};
    use std::sync::Arc;

    /// The per-view path equals rendering every pair on its own (same physics, one trace).
    #[test]
    fn per_view_rendering_equals_per_pair_rendering() {
        let rig = RigSpec::default_rig();
        let sample = Arc::new(SampleSpec::resolve("wallpaper").unwrap().build().unwrap());
        let r = Renderer::new(sample, RenderQuality::default());
        let sweep = Sweep::resolve("fibonacci:4").unwrap();
        let mut n = 0;
        render_btf(&r, &rig, 0.0, &sweep, 32, 1.0, |vi, li, img| {
            let (cam, lamp) = positions(&rig, sweep.lights[li], sweep.views[vi]);
            let direct = r.render_truth(cam, 32, 32, &lamp_at(&rig, 0.0, lamp));
            assert_eq!(img.data, direct.data, "view {vi} light {li}");
            n += 1;
            Ok::<(), ()>(())
        })
        .unwrap();
        assert_eq!(n, 16);
    }
}
