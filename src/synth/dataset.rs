//! One synthetic BTF written as a native dataset: what `gonio sim btf` does, and what every
//! member of a dataset family (`family.rs`) does.
//!
//! Why a library function: the command line and the family generator must write the same
//! bytes for the same sample, so both call [`write_btf`]. Rendering runs on the calling
//! thread (rayon inside the renderer); a store thread encodes EXR and fsyncs, overlapped
//! with the rendering, fed in canonical order so the dataset does not depend on timing.

use super::{lamp_at, positions, render_btf_views, truth_scale};
use gonio_dataset::shard::{Shard, ShardInfo};
use gonio_dataset::store::{Dataset, ManifestHeader, MeasurementRecord, StoreError};
use gonio_dataset::sweep::Sweep;
use gonio_devices::image::RgbImage;
use gonio_devices::rig::RigSpec;
use gonio_simulator::{RenderQuality, Renderer, SampleSpec, SimOptions};
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

/// What to render: a sample under a sweep, on a rig, at a size.
pub struct BtfJob<'a> {
    pub rig: &'a RigSpec,
    pub sample: &'a SampleSpec,
    pub sweep: &'a Sweep,
    /// Texels per side of every image (8 ..= 4096).
    pub size: usize,
    /// Truth samples per texel and axis (1 ..= 16).
    pub supersample: usize,
    /// Render only these views (a shard); `None` renders all.
    pub shard: Option<Shard>,
    /// Render each pair on its own (trace + shade per pair): the baseline the per-view path
    /// is measured against. Same images.
    pub per_pair: bool,
}

/// Where to write, if anywhere (without it the job is a timing run).
pub struct BtfOutput<'a> {
    pub dir: &'a Path,
    /// Replace an existing gonio dataset at `dir`.
    pub force: bool,
    /// Merged into the manifest header's `extra` (e.g. a family member's labels).
    pub extra: serde_json::Value,
}

/// What a run did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct BtfStats {
    pub lights: usize,
    pub views: usize,
    /// Images rendered (lights × the shard's views).
    pub images: usize,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shard: Option<ShardInfo>,
    /// Wall seconds rendering and, with an output, in all (the store overlaps rendering).
    pub render_seconds: f64,
    pub total_seconds: f64,
    pub shadow_maps_built: usize,
}

/// Why a synthetic BTF could not be written.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    #[error("size {0}: valid range is 8 ..= 4096 texels per side")]
    Size(usize),
    #[error("supersample {0}: valid range is 1 ..= 16")]
    Supersample(usize),
    #[error("{0}")]
    Shard(String),
    #[error("sample `{sample}`: {source}")]
    Sample {
        sample: String,
        #[source]
        source: gonio_simulator::sample::SampleError,
    },
    #[error(transparent)]
    Rig(#[from] gonio_simulator::devices::SimRigError),
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("encoding the manifest header: {0}")]
    Header(#[from] serde_json::Error),
    #[error("the store thread stopped: {0}")]
    StoreThread(String),
}

/// Render `job` and, with `out`, write it as a dataset; `progress` is called once per
/// image rendered (from the rendering thread).
pub fn write_btf(job: &BtfJob<'_>, out: Option<BtfOutput<'_>>, progress: &dyn Fn()) -> Result<BtfStats, SynthError> {
    if !(8..=4096).contains(&job.size) {
        return Err(SynthError::Size(job.size));
    }
    if !(1..=16).contains(&job.supersample) {
        return Err(SynthError::Supersample(job.supersample));
    }
    let sweep = job.sweep;
    let nv = sweep.views.len();
    let shard = match job.shard {
        Some(s) => {
            s.check_views(nv).map_err(SynthError::Shard)?;
            Some(s.info(nv))
        }
        None => None,
    };
    let views = shard.map_or(0..nv, |s| s.first_view..s.end_view);
    let quality = RenderQuality {
        truth_supersample: job.supersample,
        ..Default::default()
    };
    let sample = job.sample.clone().build().map_err(|source| SynthError::Sample {
        sample: job.sample.name.clone(),
        source,
    })?;
    let renderer = Arc::new(Renderer::new(Arc::new(sample), quality));
    // The acquisition's truth units come from the rig's sensor model; building the sim rig
    // also validates the rig's lamp (`light.options.radius_mm`).
    let sim = gonio_simulator::build_sim_rig(job.rig, renderer.clone(), &SimOptions::default())?;
    let radius = sim.world.lamp_radius_mm;
    let scale = truth_scale(&sim.world.sensor.lock().expect("sensor lock"));

    let (tx, rx) = std::sync::mpsc::sync_channel::<(usize, usize, RgbImage)>(8);
    let store_thread = match out {
        None => None,
        Some(out) => {
            let mut header = ManifestHeader::new(
                serde_json::to_value(job.rig)?,
                serde_json::to_value(job.sample)?,
                sweep.manifest_json("skip"),
                job.size,
                job.size,
                "ground truth, linear normalised sensor signal (DN / max DN) of the rig's sensor, \
                 no noise (synthetic BTF, `gonio sim btf`)",
            );
            let mut extra = serde_json::json!({
                "synthetic": { "ideal_rig": true, "supersample": job.supersample }
            });
            if let Some(s) = &shard {
                extra["shard"] = serde_json::to_value(s)?;
            }
            if let serde_json::Value::Object(more) = out.extra {
                for (k, v) in more {
                    extra[k] = v;
                }
            }
            header.extra = extra;
            let mut ds = Dataset::create(out.dir, &header, out.force)?;
            let nl = sweep.lights.len();
            let (lights, view_dirs) = (sweep.lights.clone(), sweep.views.clone());
            Some(std::thread::spawn(move || -> Result<(), StoreError> {
                for (vi, li, img) in rx {
                    let index = vi * nl + li;
                    let d = |x: gonio_devices::Direction| [x.theta_deg(), x.phi_deg()];
                    let rec = MeasurementRecord::new(index, index, d(lights[li]), d(view_dirs[vi]));
                    ds.store(rec, Some(&img), None)?;
                }
                ds.finish(&serde_json::json!({ "synthetic": true }))?;
                Ok(())
            }))
        }
    };

    let t0 = Instant::now();
    let mut render_s = 0.0;
    let mut last = Instant::now();
    let storing = store_thread.is_some();
    let stopped = || SynthError::StoreThread("it ended early (its error follows)".into());
    let mut send = |vi: usize, li: usize, img: RgbImage, render_s: &mut f64| -> Result<(), SynthError> {
        *render_s += last.elapsed().as_secs_f64();
        progress();
        if storing {
            tx.send((vi, li, img)).map_err(|_| stopped())?;
        }
        last = Instant::now();
        Ok(())
    };
    let result = if job.per_pair {
        let mut r = Ok(());
        'outer: for (vi, &view) in sweep.views.iter().enumerate().skip(views.start).take(views.len()) {
            for (li, &light) in sweep.lights.iter().enumerate() {
                let (cam, lamp) = positions(job.rig, light, view);
                let mut img = renderer.render_truth(cam, job.size, job.size, &lamp_at(job.rig, radius, lamp));
                img.data.iter_mut().for_each(|v| *v *= scale);
                if let Err(e) = send(vi, li, img, &mut render_s) {
                    r = Err(e);
                    break 'outer;
                }
            }
        }
        r
    } else {
        render_btf_views(
            &renderer,
            job.rig,
            radius,
            sweep,
            views.clone(),
            job.size,
            scale,
            |vi, li, img| send(vi, li, img, &mut render_s),
        )
    };
    drop(tx);
    if let Some(h) = store_thread {
        // The store's own error explains a send failure, so it wins over `result`.
        h.join().map_err(|_| SynthError::StoreThread("it panicked".into()))??;
    }
    result?;
    Ok(BtfStats {
        lights: sweep.lights.len(),
        views: nv,
        images: sweep.lights.len() * views.len(),
        shard,
        render_seconds: render_s,
        total_seconds: t0.elapsed().as_secs_f64(),
        shadow_maps_built: renderer.shadow_maps_built(),
    })
}
