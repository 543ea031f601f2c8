//! HDR exposure bracketing of one measurement (rig file `[hdr]`, `gonio acquire --hdr`).
//!
//! **Which exposures.** The predictor is the measurement's own base exposure, used as a
//! full-resolution pre-scan that is kept (it is the bracket's first frame, so it costs no
//! extra rig time). Why not the neighbouring pairs: the bracket would then depend on the
//! order the pairs were taken in, and a resumed run (which starts without a neighbour)
//! would store other bytes than an uninterrupted one; a separate low-resolution pre-scan
//! costs a readout per pair — the dominant capture cost on a rig whose readout is 20× its
//! exposure — whether or not the pair needs a second exposure. The base frame tells
//! directly what this pair needs:
//!
//! - `auto`: while more than `max_saturated_pixels` pixels of the **sample region** (the
//!   projected sample square; the holder and markers do not count) are saturated in the
//!   shortest frame so far, a frame `step` times shorter is added, down to the rig's
//!   `min_exposure_s`; a saturated pixel's true value is unknown, so the cascade is the
//!   only safe way down. If the darkest decile of the sample region is below the SNR
//!   floor, one longer exposure is added, as long as the sensor model says the floor needs
//!   (up to `max_exposure_s`). A pair one exposure serves gets one.
//! - `N`: the base and N − 1 shorter exposures, `step` apart (down to `min_exposure_s`).
//!
//! **Bad input** ends the bracket with a reason recorded per measurement, never a silent
//! clip: saturated at the shortest exposure, darkest decile black or below the floor at
//! the longest, and a camera that does not apply the requested exposure (its
//! `configure` read-back differs by more than 1 %, or the frame says another exposure).
//! Whatever happens, the camera is set back to the nominal exposure before the next
//! measurement.

use super::capture::{capture_fresh, CaptureFailed, CaptureNotes, CapturePolicy};
use gonio_devices::hdr::{HdrMode, HdrSpec, SensorNoise};
use gonio_devices::kinematics::CameraPose;
use gonio_devices::{Camera, CameraConfig, Frame, Intrinsics, Vec3};

/// The pixels of a frame that see the sample (a convex quad: the projected sample square).
#[derive(Clone, Debug)]
pub struct SampleRegion {
    /// Pixel indices (row-major, one per pixel) inside the quad.
    pixels: Vec<u32>,
}

impl SampleRegion {
    /// The sample square of edge `sample_mm` seen from `pose` through `intr` in a
    /// `width × height` frame.
    pub fn project(pose: &CameraPose, intr: &Intrinsics, sample_mm: f64, width: usize, height: usize) -> SampleRegion {
        let h = sample_mm / 2.0;
        let corners: Vec<(f64, f64)> = [(-h, -h), (h, -h), (h, h), (-h, h)]
            .iter()
            .map(|&(x, y)| {
                let c = pose.to_camera(Vec3::new(x, y, 0.0));
                intr.project(c.x, c.y, c.z.max(1e-9))
            })
            .collect();
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for &(x, y) in &corners {
            x0 = x0.min(x);
            y0 = y0.min(y);
            x1 = x1.max(x);
            y1 = y1.max(y);
        }
        let clampi = |v: f64, n: usize| (v.max(0.0) as usize).min(n);
        let (xa, xb) = (clampi(x0.floor(), width), clampi(x1.ceil(), width));
        let (ya, yb) = (clampi(y0.floor(), height), clampi(y1.ceil(), height));
        // Inside a convex polygon: the pixel centre on the same side of every edge.
        let side = |i: usize, px: f64, py: f64| {
            let (ax, ay) = corners[i];
            let (bx, by) = corners[(i + 1) % 4];
            (bx - ax) * (py - ay) - (by - ay) * (px - ax)
        };
        let mut pixels = Vec::new();
        for y in ya..yb {
            for x in xa..xb {
                let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
                let s: Vec<f64> = (0..4).map(|i| side(i, px, py)).collect();
                if s.iter().all(|&v| v >= 0.0) || s.iter().all(|&v| v <= 0.0) {
                    pixels.push((y * width + x) as u32);
                }
            }
        }
        SampleRegion { pixels }
    }

    /// Pixels in the region.
    pub fn len(&self) -> usize {
        self.pixels.len()
    }

    /// True when the sample is not in the frame.
    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }

    /// Region pixels with any channel at or above the saturation code.
    pub fn saturated(&self, frame: &Frame) -> usize {
        let max = frame.max_dn();
        self.pixels
            .iter()
            .filter(|&&p| frame.data[p as usize * 3..p as usize * 3 + 3].iter().any(|&v| v >= max))
            .count()
    }

    /// The darkest decile's upper edge (10th percentile of the region's channel values),
    /// normalised (DN / max DN).
    pub fn dark_decile(&self, frame: &Frame) -> f64 {
        if self.pixels.is_empty() {
            return 0.0;
        }
        let max = frame.max_dn() as usize;
        let mut hist = vec![0usize; max + 1];
        for &p in &self.pixels {
            for &v in &frame.data[p as usize * 3..p as usize * 3 + 3] {
                hist[(v as usize).min(max)] += 1;
            }
        }
        let target = (self.pixels.len() * 3).div_ceil(10);
        let mut seen = 0;
        for (dn, n) in hist.iter().enumerate() {
            seen += n;
            if seen >= target {
                return dn as f64 / max as f64;
            }
        }
        1.0
    }
}

/// What bracketing did, beyond the frames.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BracketNotes {
    /// Why the bracket stopped short of what the signal needed (one line each).
    pub reasons: Vec<String>,
}

/// Relative difference above which a camera did not apply the requested exposure.
const READ_BACK_TOLERANCE: f64 = 0.01;

/// Capture the bracket of one measurement (see the module docs). `config` is the nominal
/// configuration (the base exposure, restored at the end). Frames come in capture order,
/// the base first.
pub async fn capture_bracket(
    camera: &dyn Camera,
    policy: &CapturePolicy,
    config: &CameraConfig,
    hdr: &HdrSpec,
    noise: &SensorNoise,
    region: &SampleRegion,
    still_at: Option<f64>,
) -> Result<(Vec<Frame>, CaptureNotes, BracketNotes), CaptureFailed> {
    let mut notes = CaptureNotes::default();
    let mut bn = BracketNotes::default();
    let base = capture_fresh(camera, policy, still_at, &mut notes).await?;
    if (base.meta.exposure / config.exposure - 1.0).abs() > READ_BACK_TOLERANCE {
        bn.reasons.push(format!(
            "base frame exposed {} s instead of the nominal {} s",
            base.meta.exposure, config.exposure
        ));
    }
    let mut frames = vec![base];
    let mut changed = false;
    let result = bracket_rest(
        camera,
        policy,
        config,
        hdr,
        noise,
        region,
        still_at,
        &mut frames,
        &mut notes,
        &mut bn,
        &mut changed,
    )
    .await;
    if changed {
        // Back to the nominal exposure whatever happened, so the next measurement is normal.
        let got = camera
            .configure(config)
            .await
            .map_err(|source| CaptureFailed { attempts: 1, source })?;
        if (got.exposure / config.exposure - 1.0).abs() > READ_BACK_TOLERANCE {
            bn.reasons.push(format!(
                "camera kept {} s when set back to the nominal {} s",
                got.exposure, config.exposure
            ));
        }
    }
    result?;
    Ok((frames, notes, bn))
}

/// Set the exposure and capture; `Ok(None)` (with the reason noted) when the camera did
/// not apply it.
#[allow(clippy::too_many_arguments)]
async fn exposure(
    camera: &dyn Camera,
    policy: &CapturePolicy,
    config: &CameraConfig,
    wanted: f64,
    still_at: Option<f64>,
    notes: &mut CaptureNotes,
    bn: &mut BracketNotes,
    changed: &mut bool,
) -> Result<Option<Frame>, CaptureFailed> {
    *changed = true;
    let got = camera
        .configure(&CameraConfig {
            exposure: wanted,
            ..config.clone()
        })
        .await
        .map_err(|source| CaptureFailed { attempts: 1, source })?;
    if (got.exposure / wanted - 1.0).abs() > READ_BACK_TOLERANCE {
        bn.reasons.push(format!(
            "camera applied {} s for the requested {wanted} s: bracket ended",
            got.exposure
        ));
        return Ok(None);
    }
    let frame = capture_fresh(camera, policy, still_at, notes).await?;
    if (frame.meta.exposure / wanted - 1.0).abs() > READ_BACK_TOLERANCE {
        bn.reasons.push(format!(
            "frame exposed {} s for the requested {wanted} s: bracket ended",
            frame.meta.exposure
        ));
        return Ok(None);
    }
    Ok(Some(frame))
}

#[allow(clippy::too_many_arguments)]
async fn bracket_rest(
    camera: &dyn Camera,
    policy: &CapturePolicy,
    config: &CameraConfig,
    hdr: &HdrSpec,
    noise: &SensorNoise,
    region: &SampleRegion,
    still_at: Option<f64>,
    frames: &mut Vec<Frame>,
    notes: &mut CaptureNotes,
    bn: &mut BracketNotes,
    changed: &mut bool,
) -> Result<(), CaptureFailed> {
    let shortest = |frames: &[Frame]| frames.iter().map(|f| f.meta.exposure).fold(f64::INFINITY, f64::min);
    match hdr.mode() {
        HdrMode::Off => {}
        HdrMode::Fixed(n) => {
            for _ in 1..n {
                let last = shortest(frames);
                let wanted = (last / hdr.step).max(hdr.min_exposure_s);
                if wanted >= last * (1.0 - READ_BACK_TOLERANCE) {
                    bn.reasons.push(format!(
                        "bracket of {n} cut at {} exposures: the shortest exposure {} s is reached",
                        frames.len(),
                        hdr.min_exposure_s
                    ));
                    break;
                }
                match exposure(camera, policy, config, wanted, still_at, notes, bn, changed).await? {
                    Some(f) => frames.push(f),
                    None => return Ok(()),
                }
            }
        }
        HdrMode::Auto => {
            if region.is_empty() {
                bn.reasons
                    .push("the sample is not in the frame: no exposure chosen for it".into());
                return Ok(());
            }
            // Highlights: shorter exposures until the sample region no longer saturates.
            loop {
                let f = frames.last().expect("the base frame");
                let saturated = region.saturated(f);
                if saturated <= hdr.max_saturated_pixels {
                    break;
                }
                let last = shortest(frames);
                let wanted = (last / hdr.step).max(hdr.min_exposure_s);
                if wanted >= last * (1.0 - READ_BACK_TOLERANCE) {
                    bn.reasons.push(format!(
                        "{saturated} sample pixels saturated at the shortest exposure {last} s"
                    ));
                    break;
                }
                match exposure(camera, policy, config, wanted, still_at, notes, bn, changed).await? {
                    Some(f) => frames.push(f),
                    None => return Ok(()),
                }
            }
            // Shadows: one longer exposure if the darkest decile is below the SNR floor.
            let base = &frames[0];
            let u10 = region.dark_decile(base);
            let need = noise.factor_for_snr(u10, hdr.snr_floor);
            let t0 = base.meta.exposure;
            match need {
                Some(f) if f <= 1.0 => {}
                _ if hdr.max_exposure_s <= t0 * (1.0 + READ_BACK_TOLERANCE) => bn.reasons.push(format!(
                    "darkest decile at SNR {:.1} (floor {}) and the longest exposure {} s is the base",
                    noise.snr(u10),
                    hdr.snr_floor,
                    hdr.max_exposure_s
                )),
                need => {
                    // At least twice the base: a longer exposure that barely differs costs a
                    // whole readout for little SNR.
                    let wanted = need.map_or(hdr.max_exposure_s, |f| (t0 * f.max(2.0)).min(hdr.max_exposure_s));
                    let Some(long) = exposure(camera, policy, config, wanted, still_at, notes, bn, changed).await?
                    else {
                        return Ok(());
                    };
                    let u_long = region.dark_decile(&long);
                    if u_long <= 0.0 {
                        bn.reasons
                            .push(format!("darkest decile black at the longest exposure {wanted} s"));
                    } else if noise.snr(u_long) < hdr.snr_floor * 0.9 {
                        bn.reasons.push(format!(
                            "darkest decile at SNR {:.1} (floor {}) at the longest exposure {wanted} s",
                            noise.snr(u_long),
                            hdr.snr_floor
                        ));
                    }
                    frames.push(long);
                }
            }
        }
    }
    Ok(())
}
