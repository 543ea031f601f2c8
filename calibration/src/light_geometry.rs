//! Light geometry: the zero offsets of the axes that move the lamp, from the specular
//! highlight of a flat near-mirror sample over many axis positions.
//!
//! Why a mirror: target images cannot see the lamp (the corners do not move when it does,
//! see [`crate::rig_geometry`]), but a mirror shows the lamp's reflection at the sample point
//! `x` where the mirrored camera ray meets it: the direction `x → lamp` is the mirror image
//! of `x → camera` about the normal +z. Equivalently, `x` is where the segment from the lamp
//! to the camera's mirror image `C' = (Cx, Cy, −Cz)` crosses the plane z = 0.
//!
//! Model: with commanded axis positions `q`, lamp axis offsets `δ` and the camera pose from
//! the rig's kinematics (its `[alignment]`: nominal, or the rig-geometry calibration's), the
//! highlight is predicted at pixel `π(K, pose · x(C(q), L(q + δ)))`. Gauss-Newton with
//! Levenberg-Marquardt damping minimises the pixel distance between predicted and located
//! highlights over all poses. The residuals are in pixels, not angles at the lamp, because
//! that is where the measurement error lives (the highlight's localisation), so one
//! residual variance gives a meaningful covariance.
//!
//! What highlights cannot tell: with the lamp at the pole (θ_l = 0) the lamp's azimuth
//! axis only turns the lamp about its own position, so its offset has no effect; and the
//! offset of an axis the fit does not own (the turntable, the camera arc) is taken from the
//! rig's `[alignment]`, not estimated. A set of poses that leaves a parameter undetermined
//! is refused with the parameter named ([`check_design`] says so before the rig moves).
//!
//! Highlight localisation ([`locate_highlight`]): the peak of the luminance, the connected
//! region around it above a fraction of the peak (above the frame's median background), and
//! either the intensity-weighted centroid of that region (threshold subtracted, so pixels
//! at the rim weigh nothing and a truncation of the region shifts little) or the vertex of a
//! quadratic fitted to the log-intensity (exact for a Gaussian lobe, which a small-roughness
//! Beckmann lobe is in the tangent of the half-vector angle). Saturated, empty and truncated
//! highlights are errors, not estimates: a clipped blob's centroid is biased toward
//! wherever the clipping is widest.

use crate::intrinsics::CameraModel;
use crate::offset_fit::{axis_count_problem, parameter_table, sigmas_and_correlation, ParameterEstimate};
use gonio_devices::image::RgbImage;
use gonio_devices::kinematics;
use gonio_devices::rig::{AlignmentSpec, RigKind, RigSpec};
use gonio_devices::Vec3;
use nalgebra::{DMatrix, DVector, Matrix6, Vector6};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Axis roles whose offsets this fit estimates, in parameter order.
pub const LAMP_ROLES: [&str; 2] = ["light_azimuth", "light_elevation"];

/// How the highlight's sub-pixel position is computed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Locator {
    /// Intensity-weighted centroid of the region above the threshold (threshold
    /// subtracted). Makes no assumption on the lobe's shape beyond its symmetry.
    #[default]
    Centroid,
    /// Vertex of a least-squares quadratic in log-intensity over the region: exact for a
    /// Gaussian lobe and insensitive to where the threshold cuts it.
    LogQuadratic,
}

/// Highlight detection settings (`[light_geometry.highlight]` in a recipe).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HighlightOptions {
    pub locator: Locator,
    /// Region threshold as a fraction of the peak above background, in (0, 1).
    pub threshold_fraction: f64,
    /// Smallest peak above background (linear, 1 = full scale) accepted as a highlight.
    pub min_contrast: f64,
    /// A channel value at or above this (linear, 1 = full scale) counts as saturated.
    pub saturation_level: f64,
    /// Largest region (pixels) still taken for a highlight: a bigger one is a diffuse
    /// sample or a lamp reflection spread over the frame, not a mirror's highlight.
    pub max_region_px: usize,
}

impl Default for HighlightOptions {
    fn default() -> Self {
        HighlightOptions {
            locator: Locator::Centroid,
            threshold_fraction: 0.1,
            min_contrast: 0.02,
            saturation_level: 0.995,
            max_region_px: 5_000,
        }
    }
}

impl HighlightOptions {
    /// Range checks; the error names the key (relative to the options table) and the fix.
    pub fn validate(&self) -> Result<(), (String, String)> {
        let f = self.threshold_fraction;
        if !(f > 0.0 && f < 1.0) {
            return Err(("threshold_fraction".into(), format!("{f}: must be in (0, 1), e.g. 0.1")));
        }
        let c = self.min_contrast;
        if !(c > 0.0 && c < 1.0) {
            return Err(("min_contrast".into(), format!("{c}: must be in (0, 1), e.g. 0.02")));
        }
        let s = self.saturation_level;
        if !(s > c && s <= 1.0) {
            return Err((
                "saturation_level".into(),
                format!("{s}: must be in (min_contrast, 1], e.g. 0.995"),
            ));
        }
        if self.max_region_px < 4 {
            return Err(("max_region_px".into(), format!("{}: must be ≥ 4", self.max_region_px)));
        }
        Ok(())
    }
}

/// A located highlight.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Highlight {
    /// Sub-pixel position (gonio's convention: pixel centres at half-integers).
    pub pixel: [f64; 2],
    /// Brightest pixel's luminance and the frame's median (linear, 1 = full scale).
    pub peak: f64,
    pub background: f64,
    /// Pixels in the region above the threshold.
    pub region_px: usize,
    /// Intensity-weighted RMS radius of the region (px): the lobe's size in the image.
    pub radius_px: f64,
    /// Where the *other* locator puts the same highlight, minus [`Highlight::pixel`] (px);
    /// `None` when the log-quadratic has no maximum. Both locators are unbiased for a
    /// symmetric lobe, so their disagreement measures the lobe's asymmetry: the one
    /// localisation error that no residual shows (it is nearly the same at every pose and
    /// the fit absorbs it). [`estimate_light_geometry`] turns it into a systematic term.
    pub locator_shift_px: Option<[f64; 2]>,
}

#[derive(Clone, Debug, PartialEq, Error)]
pub enum HighlightError {
    #[error("image {width}×{height}: buffer holds {len} values, needs {expected}")]
    BadImage {
        width: usize,
        height: usize,
        len: usize,
        expected: usize,
    },
    #[error(
        "no highlight: the brightest pixel is {peak:.4} against a background of {background:.4} (need {min_contrast} above it): \
         the frame is black or flat — lamp off, exposure too short, or the highlight falls off the sample (light not in the \
         mirror direction of the view: use light = [θ_v, φ_v + 180°])"
    )]
    Empty {
        peak: f64,
        background: f64,
        min_contrast: f64,
    },
    #[error(
        "saturated highlight: {pixels} pixel(s) at or above {level} of full scale: its centroid would be biased; \
         shorten `exposure_s` (or lower the lamp's power)"
    )]
    Saturated { pixels: usize, level: f64 },
    #[error(
        "highlight at pixel ({u:.1}, {v:.1}) touches the frame's edge: part of it is cut off and its centre would be \
         biased; choose poses that put it nearer the image centre"
    )]
    Truncated { u: f64, v: f64 },
    #[error(
        "the bright region around pixel ({u:.1}, {v:.1}) covers {pixels} pixels (limit {max}): not a mirror's \
         highlight — is the sample a near-mirror (see simulator/samples/mirror.toml)?"
    )]
    NotCompact { u: f64, v: f64, pixels: usize, max: usize },
    #[error(
        "highlight near pixel ({u:.1}, {v:.1}): the log-intensity is not peaked (quadratic not concave); use \
         locator = \"centroid\""
    )]
    NotPeaked { u: f64, v: f64 },
}

/// Locate the specular highlight in a linear RGB frame (values 1 = full scale).
pub fn locate_highlight(img: &RgbImage, opts: &HighlightOptions) -> Result<Highlight, HighlightError> {
    let (w, h) = (img.width, img.height);
    let expected = w * h * 3;
    if img.data.len() != expected || w == 0 || h == 0 {
        return Err(HighlightError::BadImage {
            width: w,
            height: h,
            len: img.data.len(),
            expected,
        });
    }
    // Luminance as the channel mean: a tinted conductor's highlight has the same position in
    // every channel, and the mean keeps the full dynamic range of the brightest one.
    let lum: Vec<f64> = img
        .data
        .chunks_exact(3)
        .map(|p| (p[0] as f64 + p[1] as f64 + p[2] as f64) / 3.0)
        .collect();
    let background = {
        let mut s: Vec<f64> = lum.iter().copied().filter(|x| x.is_finite()).collect();
        if s.is_empty() {
            0.0
        } else {
            let mid = s.len() / 2;
            *s.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1
        }
    };
    let (imax, peak) = lum
        .iter()
        .enumerate()
        .filter(|(_, x)| x.is_finite())
        .fold((0, f64::NEG_INFINITY), |b, (i, &x)| if x > b.1 { (i, x) } else { b });
    if peak - background < opts.min_contrast {
        return Err(HighlightError::Empty {
            peak: peak.max(0.0),
            background,
            min_contrast: opts.min_contrast,
        });
    }
    let (pu, pv) = ((imax % w) as f64 + 0.5, (imax / w) as f64 + 0.5);
    let threshold = background + opts.threshold_fraction * (peak - background);
    // The connected region above the threshold (4-neighbourhood flood fill from the peak).
    let mut inside = vec![false; w * h];
    let mut stack = vec![imax];
    inside[imax] = true;
    let mut region = Vec::new();
    let mut touches_edge = false;
    while let Some(i) = stack.pop() {
        region.push(i);
        if region.len() > opts.max_region_px {
            return Err(HighlightError::NotCompact {
                u: pu,
                v: pv,
                pixels: region.len(),
                max: opts.max_region_px,
            });
        }
        let (x, y) = (i % w, i / w);
        if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
            touches_edge = true;
        }
        let mut push = |j: usize| {
            if !inside[j] && lum[j] > threshold {
                inside[j] = true;
                stack.push(j);
            }
        };
        if x > 0 {
            push(i - 1);
        }
        if x + 1 < w {
            push(i + 1);
        }
        if y > 0 {
            push(i - w);
        }
        if y + 1 < h {
            push(i + w);
        }
    }
    if touches_edge {
        return Err(HighlightError::Truncated { u: pu, v: pv });
    }
    let saturated = region
        .iter()
        .filter(|&&i| {
            img.data[3 * i..3 * i + 3]
                .iter()
                .any(|&c| c as f64 >= opts.saturation_level)
        })
        .count();
    if saturated > 0 {
        return Err(HighlightError::Saturated {
            pixels: saturated,
            level: opts.saturation_level,
        });
    }
    // Centroid (threshold subtracted) and RMS radius.
    let (mut sw, mut su, mut sv) = (0.0, 0.0, 0.0);
    for &i in &region {
        let wgt = lum[i] - threshold;
        sw += wgt;
        su += wgt * ((i % w) as f64 + 0.5);
        sv += wgt * ((i / w) as f64 + 0.5);
    }
    let (cu, cv) = (su / sw, sv / sw);
    let radius_px = (region
        .iter()
        .map(|&i| {
            let (du, dv) = ((i % w) as f64 + 0.5 - cu, (i / w) as f64 + 0.5 - cv);
            (lum[i] - threshold) * (du * du + dv * dv)
        })
        .sum::<f64>()
        / sw)
        .sqrt();
    let vertex = log_quadratic_vertex(&region, &lum, w, background, [pu, pv]);
    let (pixel, other) = match opts.locator {
        Locator::Centroid => ([cu, cv], vertex),
        Locator::LogQuadratic => (
            vertex.ok_or(HighlightError::NotPeaked { u: pu, v: pv })?,
            Some([cu, cv]),
        ),
    };
    Ok(Highlight {
        pixel,
        peak,
        background,
        region_px: region.len(),
        radius_px,
        locator_shift_px: other.map(|o| [o[0] - pixel[0], o[1] - pixel[1]]),
    })
}

/// Vertex of `log(I − bg) ≈ a + b·du + c·dv + d·du² + e·du·dv + f·dv²` over the region
/// (coordinates relative to the peak pixel for conditioning), weighted by `(I − bg)²`: the
/// log's noise grows as 1/I, so the squared intensity is its inverse variance. `None` if
/// the quadratic is not concave (no maximum) or its vertex leaves the region's extent.
fn log_quadratic_vertex(region: &[usize], lum: &[f64], w: usize, bg: f64, peak: [f64; 2]) -> Option<[f64; 2]> {
    let mut ata = Matrix6::<f64>::zeros();
    let mut atb = Vector6::<f64>::zeros();
    let (mut umin, mut umax, mut vmin, mut vmax) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for &i in region {
        let s = lum[i] - bg;
        if s <= 0.0 {
            continue;
        }
        let (du, dv) = ((i % w) as f64 + 0.5 - peak[0], (i / w) as f64 + 0.5 - peak[1]);
        umin = umin.min(du);
        umax = umax.max(du);
        vmin = vmin.min(dv);
        vmax = vmax.max(dv);
        let row = Vector6::new(1.0, du, dv, du * du, du * dv, dv * dv);
        let wgt = s * s;
        ata += row * row.transpose() * wgt;
        atb += row * (wgt * s.ln());
    }
    let x = ata.cholesky()?.solve(&atb);
    let (b, c, d, e, f) = (x[1], x[2], x[3], x[4], x[5]);
    // Hessian [2d e; e 2f] must be negative definite.
    let det = 4.0 * d * f - e * e;
    if !(d < 0.0 && det > 0.0) {
        return None;
    }
    let du = (-2.0 * f * b + e * c) / det;
    let dv = (e * b - 2.0 * d * c) / det;
    let inside = (umin - 0.5..=umax + 0.5).contains(&du) && (vmin - 0.5..=vmax + 0.5).contains(&dv);
    inside.then_some([peak[0] + du, peak[1] + dv])
}

/// One pose: commanded axis positions and the highlight located there.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LampPose {
    /// A name for messages (e.g. the recipe pose it was captured at).
    pub label: String,
    /// Commanded axis positions (radians, the rig file's axis order).
    pub q: Vec<f64>,
    /// The located highlight (px, gonio's convention).
    pub pixel: [f64; 2],
    /// The other locator's position minus `pixel` ([`Highlight::locator_shift_px`]);
    /// absent in results written before it existed.
    #[serde(default)]
    pub locator_shift_px: Option<[f64; 2]>,
}

/// When to stop and when to refuse (`[light_geometry]` in a recipe).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LightGeometryOptions {
    pub min_poses: usize,
    pub max_iterations: usize,
    /// Largest accepted condition number of the column-normalised Jacobian: 1 when the two
    /// offsets move the highlight in perpendicular directions, → ∞ when one does nothing.
    pub max_condition: f64,
    /// A fit whose RMS highlight residual (px) is above this does not describe the rig.
    pub max_rms_px: f64,
    /// Largest offset (degrees) the poses must tolerate: every highlight must stay on the
    /// sample (inside `edge_margin_mm`) for any lamp offsets up to this.
    pub max_offset_deg: f64,
    /// Distance (mm) a highlight must keep from the sample's edge.
    pub edge_margin_mm: f64,
    pub highlight: HighlightOptions,
}

impl Default for LightGeometryOptions {
    fn default() -> Self {
        LightGeometryOptions {
            min_poses: 3,
            max_iterations: 50,
            max_condition: 100.0,
            // Located highlights scatter by a few hundredths of a pixel; an uncalibrated
            // camera pose (0.3° of turntable) leaves ≈ 1 px: refuse well below that.
            max_rms_px: 0.25,
            max_offset_deg: 2.0,
            edge_margin_mm: 3.0,
            highlight: HighlightOptions::default(),
        }
    }
}

impl LightGeometryOptions {
    /// Range checks; the error names the key (relative to `[light_geometry]`) and the fix.
    pub fn validate(&self) -> Result<(), (String, String)> {
        if self.min_poses < 1 {
            return Err((
                "min_poses".into(),
                "0: must be ≥ 1 (2 offsets need ≥ 1 pose with θ_l > 0)".into(),
            ));
        }
        if !(1..=10_000).contains(&self.max_iterations) {
            return Err((
                "max_iterations".into(),
                format!("{}: valid range is 1 ..= 10000", self.max_iterations),
            ));
        }
        if self.max_condition.is_nan() || self.max_condition < 1.0 {
            return Err(("max_condition".into(), format!("{}: must be ≥ 1", self.max_condition)));
        }
        if !(self.max_rms_px > 0.0 && self.max_rms_px.is_finite()) {
            return Err(("max_rms_px".into(), format!("{}: must be > 0", self.max_rms_px)));
        }
        if !(self.max_offset_deg >= 0.0 && self.max_offset_deg <= AlignmentSpec::MAX_DEG) {
            return Err((
                "max_offset_deg".into(),
                format!(
                    "{}: valid range is 0 ..= {}",
                    self.max_offset_deg,
                    AlignmentSpec::MAX_DEG
                ),
            ));
        }
        if !(self.edge_margin_mm >= 0.0 && self.edge_margin_mm.is_finite()) {
            return Err(("edge_margin_mm".into(), format!("{}: must be ≥ 0", self.edge_margin_mm)));
        }
        self.highlight
            .validate()
            .map_err(|(k, m)| (format!("highlight.{k}"), m))
    }
}

/// The result of [`estimate_light_geometry`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LightGeometryFit {
    /// The estimate as the kinematics take it: the lamp axes' zero offsets only.
    pub alignment: AlignmentSpec,
    pub parameters: Vec<ParameterEstimate>,
    /// Correlation matrix of `parameters` (same order).
    pub correlation: Vec<Vec<f64>>,
    /// Condition number of the column-normalised Jacobian at the solution.
    pub condition: f64,
    pub rms_px: f64,
    /// RMS residual with zero lamp offsets, before the fit.
    pub initial_rms_px: f64,
    /// Per pose: predicted − located highlight (px) at the solution.
    pub residuals_px: Vec<[f64; 2]>,
    pub iterations: usize,
    pub poses: usize,
    /// How far the estimate moves (degrees, parameter order) when every highlight is
    /// located by the other locator instead ([`Highlight::locator_shift_px`]), to first
    /// order `(JᵀJ)⁻¹ Jᵀ s`: the systematic part of the uncertainty, which the residuals
    /// cannot show because the localisation bias is nearly the same at every pose. `None`
    /// when some pose has no second position (results written before it existed, or a
    /// log-quadratic without a maximum).
    #[serde(default)]
    pub systematic_deg: Option<Vec<f64>>,
}

impl LightGeometryFit {
    /// The parameters with σ from the covariance `Σ_stat + s sᵀ` (statistical plus the
    /// systematic shift [`LightGeometryFit::systematic_deg`] as a 1σ, fully correlated
    /// term), and its correlation matrix: what a direction uncertainty should propagate.
    /// Without a systematic term this is the statistical table unchanged.
    pub fn with_systematic(&self) -> (Vec<ParameterEstimate>, Vec<Vec<f64>>) {
        let Some(s) = self
            .systematic_deg
            .as_ref()
            .filter(|s| s.len() == self.parameters.len())
        else {
            return (self.parameters.clone(), self.correlation.clone());
        };
        let n = self.parameters.len();
        let cov = DMatrix::from_fn(n, n, |a, b| {
            let c = self.correlation.get(a).and_then(|r| r.get(b)).copied().unwrap_or(0.0);
            let c = if c.is_finite() { c } else { 0.0 };
            self.parameters[a].sigma_deg * self.parameters[b].sigma_deg * c + s[a] * s[b]
        });
        let (sig, correlation) = sigmas_and_correlation(&cov);
        let parameters = self
            .parameters
            .iter()
            .zip(sig)
            .map(|(p, sigma_deg)| ParameterEstimate { sigma_deg, ..p.clone() })
            .collect();
        (parameters, correlation)
    }

    /// Feed the lamp offsets into a rig description (`rig.alignment`); every other entry
    /// (the camera axes' offsets and mounting rotation of a rig-geometry calibration) is
    /// kept, so both calibrations combine in either order.
    pub fn apply(&self, rig: &mut RigSpec) {
        let mut a = rig.alignment.clone().unwrap_or_default();
        for (k, v) in &self.alignment.axis_zero_offset_deg {
            a.axis_zero_offset_deg.insert(k.clone(), *v);
        }
        rig.alignment = Some(a);
    }
}

#[derive(Clone, Debug, PartialEq, Error)]
pub enum LightGeometryError {
    #[error("light geometry: rig `{rig}` is of kind {kind:?}; only `two-arm` rigs have a lamp alignment model")]
    Unsupported { rig: String, kind: RigKind },
    #[error("light geometry: {got} poses, need at least {needed}")]
    TooFewPoses { needed: usize, got: usize },
    #[error("light geometry: pose `{pose}`: {reason}")]
    BadPose { pose: String, reason: String },
    #[error(
        "light geometry: pose `{pose}`: the highlight falls at ({x_mm:.1}, {y_mm:.1}) mm for lamp offsets up to \
         ±{max_offset_deg}°, off the sample (|x|, |y| ≤ {limit_mm:.1} mm): put the lamp in the mirror direction of \
         the view (light = [θ_v, φ_v + 180°]), or lower `max_offset_deg`"
    )]
    OffSample {
        pose: String,
        x_mm: f64,
        y_mm: f64,
        limit_mm: f64,
        max_offset_deg: f64,
    },
    #[error(
        "light geometry: these poses do not determine {parameters:?} (condition {condition:.3e} > {max:.0e}): {hint}"
    )]
    Undetermined {
        parameters: Vec<String>,
        condition: f64,
        max: f64,
        hint: String,
    },
    #[error(
        "light geometry: RMS highlight residual {rms_px:.3} px after the fit (limit {max_px} px): the model does not \
         describe these images: is the camera calibrated (run rig-geometry.toml first and put its `[alignment]` into the rig file; intrinsics in the camera options)? Or the sample is tilted, or the lamp distance is wrong"
    )]
    PoorFit { rms_px: f64, max_px: f64 },
}

/// Where the lamp's reflection appears for commanded `q` on the mechanism `rig` describes
/// (its `alignment` included): the sample point (mm) and its pixel. `None` when the camera
/// or the lamp is not above the sample plane, or the point is behind the camera.
pub fn predict_highlight(rig: &RigSpec, camera: &CameraModel, q: &[f64]) -> Option<(Vec3, [f64; 2])> {
    let k = kinematics::for_rig(rig);
    predict_with(&*k, camera, q)
}

fn predict_with(k: &dyn kinematics::Kinematics, camera: &CameraModel, q: &[f64]) -> Option<(Vec3, [f64; 2])> {
    let pose = k.camera_pose(q);
    let (c, l) = (pose.position, k.light_position(q));
    if !(c.z > 0.0 && l.z > 0.0) {
        return None;
    }
    let mirrored = Vec3::new(c.x, c.y, -c.z);
    let x = l + (mirrored - l) * (l.z / (l.z + c.z));
    let p = pose.to_camera(Vec3::new(x.x, x.y, 0.0));
    if p.z <= 1e-9 {
        return None;
    }
    let (u, v) = camera.project_point([p.x, p.y, p.z]);
    Some((x, [u, v]))
}

/// The parameter vector's meaning: the lamp axes' offsets on top of `base`'s alignment.
struct Model<'a> {
    rig: &'a RigSpec,
    camera: &'a CameraModel,
    /// Axis indices of the lamp's azimuth and elevation axes.
    axes: [usize; 2],
}

impl Model<'_> {
    fn spec(&self, p: &[f64]) -> RigSpec {
        let mut spec = self.rig.clone();
        spec.sim_misalignment = None;
        let mut a = spec.alignment.clone().unwrap_or_default();
        for (k, &i) in self.axes.iter().enumerate() {
            a.axis_zero_offset_deg
                .insert(self.rig.axes[i].name.clone(), p[k].to_degrees());
        }
        spec.alignment = Some(a);
        spec
    }

    fn names(&self) -> Vec<String> {
        self.axes
            .iter()
            .map(|&i| format!("zero_offset.{}", self.rig.axes[i].name))
            .collect()
    }

    /// Predicted highlight pixels of every pose.
    fn predict(&self, p: &[f64], qs: &[&[f64]]) -> Vec<Option<[f64; 2]>> {
        let k = kinematics::for_rig(&self.spec(p));
        qs.iter()
            .map(|q| predict_with(&*k, self.camera, q).map(|(_, px)| px))
            .collect()
    }

    fn residuals(&self, p: &[f64], poses: &[LampPose]) -> Vec<f64> {
        let qs: Vec<&[f64]> = poses.iter().map(|x| x.q.as_slice()).collect();
        let mut out = Vec::with_capacity(2 * poses.len());
        for (pred, pose) in self.predict(p, &qs).into_iter().zip(poses) {
            // no reflection (a device below the horizon): a large, smooth penalty
            let [u, v] = pred.unwrap_or([1e6, 1e6]);
            out.push(u - pose.pixel[0]);
            out.push(v - pose.pixel[1]);
        }
        out
    }

    /// Central-difference Jacobian of the predicted pixels (same for residuals).
    fn jacobian(&self, p: &[f64], qs: &[&[f64]]) -> DMatrix<f64> {
        let h = 1e-6;
        let mut j = DMatrix::zeros(2 * qs.len(), 2);
        for c in 0..2 {
            let (mut a, mut b) = (p.to_vec(), p.to_vec());
            a[c] += h;
            b[c] -= h;
            let (pa, pb) = (self.predict(&a, qs), self.predict(&b, qs));
            for (r, (x, y)) in pa.iter().zip(&pb).enumerate() {
                let (x, y) = (x.unwrap_or([0.0; 2]), y.unwrap_or([0.0; 2]));
                j[(2 * r, c)] = (x[0] - y[0]) / (2.0 * h);
                j[(2 * r + 1, c)] = (x[1] - y[1]) / (2.0 * h);
            }
        }
        j
    }
}

fn lamp_axes(rig: &RigSpec) -> Result<[usize; 2], LightGeometryError> {
    if rig.kind != RigKind::TwoArm {
        return Err(LightGeometryError::Unsupported {
            rig: rig.name.clone(),
            kind: rig.kind,
        });
    }
    let idx = |role: &str| {
        rig.axis_by_role(role)
            .map(|(i, _)| i)
            .ok_or(LightGeometryError::Unsupported {
                rig: rig.name.clone(),
                kind: rig.kind,
            })
    };
    Ok([idx(LAMP_ROLES[0])?, idx(LAMP_ROLES[1])?])
}

/// Condition number (column-normalised) and the parameters in the direction of the
/// smallest singular value; zero columns count as infinitely ill-conditioned.
fn conditioning(j: &DMatrix<f64>, names: &[String]) -> (f64, Vec<String>) {
    let norms: Vec<f64> = j.column_iter().map(|c| c.norm()).collect();
    let scale = norms.iter().cloned().fold(0.0, f64::max);
    let dead: Vec<String> = norms
        .iter()
        .zip(names)
        .filter(|(n, _)| **n <= 1e-9 * scale.max(1e-300))
        .map(|(_, n)| n.clone())
        .collect();
    if !dead.is_empty() {
        return (f64::INFINITY, dead);
    }
    let mut jn = j.clone();
    for (mut col, n) in jn.column_iter_mut().zip(&norms) {
        col /= *n;
    }
    let svd = jn.svd(false, true);
    let s = &svd.singular_values;
    let (imin, smin) = s
        .iter()
        .enumerate()
        .fold((0, f64::INFINITY), |b, (i, &x)| if x < b.1 { (i, x) } else { b });
    let smax = s.iter().cloned().fold(0.0, f64::max);
    let cond = if smin > 0.0 { smax / smin } else { f64::INFINITY };
    let vt = svd.v_t.expect("requested");
    let involved = vt
        .row(imin)
        .iter()
        .zip(names)
        .filter(|(x, _)| x.abs() >= 0.25)
        .map(|(_, n)| n.clone())
        .collect();
    (cond, involved)
}

/// What to change in the pose set when `parameters` are undetermined.
fn hint(rig: &RigSpec, axes: [usize; 2], qs: &[&[f64]], parameters: &[String]) -> String {
    let (base, arc) = (&rig.axes[axes[0]], &rig.axes[axes[1]]);
    let max_tilt = qs.iter().map(|q| q[axes[1]].abs()).fold(0.0, f64::max).to_degrees();
    if parameters.iter().any(|p| p.ends_with(&base.name)) && max_tilt < 1.0 {
        return format!(
            "every pose has `{}` within {max_tilt:.2}° of 0 (lamp at the pole, θ_l = 0), where turning `{}` only spins \
             the lamp about itself and moves no highlight; add poses with the lamp tilted (θ_l ≥ 15°, camera in the \
             mirror direction)",
            arc.name, base.name
        );
    }
    format!(
        "add poses with the lamp at larger and more varied tilts (`{}` reaches at most {max_tilt:.1}° in these poses)",
        arc.name
    )
}

/// Check, from the commanded axis positions alone, that a pose set can determine the lamp
/// offsets and keeps every highlight on the sample for offsets up to
/// `opts.max_offset_deg`: the runner calls this before moving the rig, so a useless recipe
/// is refused with its diagnosis instead of after a wasted run. Returns the design's
/// condition number.
pub fn check_design(
    rig: &RigSpec,
    camera: &CameraModel,
    poses: &[(String, Vec<f64>)],
    opts: &LightGeometryOptions,
) -> Result<f64, LightGeometryError> {
    let axes = lamp_axes(rig)?;
    let model = Model { rig, camera, axes };
    let qs: Vec<&[f64]> = poses.iter().map(|(_, q)| q.as_slice()).collect();
    let names = model.names();
    let j = model.jacobian(&[0.0, 0.0], &qs);
    let (condition, involved) = conditioning(&j, &names);
    if condition.is_nan() || condition > opts.max_condition {
        return Err(LightGeometryError::Undetermined {
            hint: hint(rig, axes, &qs, &involved),
            parameters: involved,
            condition,
            max: opts.max_condition,
        });
    }
    let limit = 0.5 * rig.geometry.sample_size_mm - opts.edge_margin_mm;
    let m = opts.max_offset_deg.to_radians();
    for (label, q) in poses {
        for corner in [[0.0, 0.0], [m, m], [m, -m], [-m, m], [-m, -m]] {
            let k = kinematics::for_rig(&model.spec(&corner));
            let at = predict_with(&*k, camera, q).map(|(x, _)| x);
            let off = at.is_none_or(|x| rig.geometry.sample_size_mm > 0.0 && (x.x.abs() > limit || x.y.abs() > limit));
            if off {
                let x = at.unwrap_or(Vec3::new(f64::NAN, f64::NAN, 0.0));
                return Err(LightGeometryError::OffSample {
                    pose: label.clone(),
                    x_mm: x.x,
                    y_mm: x.y,
                    limit_mm: limit,
                    max_offset_deg: opts.max_offset_deg,
                });
            }
        }
    }
    Ok(condition)
}

/// Estimate the lamp axes' zero offsets of `rig` from located highlights. `rig` gives the
/// kinematics, including the camera's alignment (`[alignment]`, e.g. from a rig-geometry
/// calibration), held fixed; lamp offsets already in it are ignored (the estimate is
/// absolute). `camera` is the calibrated camera, held fixed.
pub fn estimate_light_geometry(
    rig: &RigSpec,
    camera: &CameraModel,
    poses: &[LampPose],
    opts: &LightGeometryOptions,
) -> Result<LightGeometryFit, LightGeometryError> {
    let axes = lamp_axes(rig)?;
    let needed = opts.min_poses.max(1);
    if poses.len() < needed {
        return Err(LightGeometryError::TooFewPoses {
            needed,
            got: poses.len(),
        });
    }
    for p in poses {
        let bad = |reason: String| LightGeometryError::BadPose {
            pose: p.label.clone(),
            reason,
        };
        if let Some(reason) = axis_count_problem(&p.q, rig.axes.len()) {
            return Err(bad(reason));
        }
        if !p.q.iter().chain(&p.pixel).all(|x| x.is_finite()) {
            return Err(bad("non-finite axis position or highlight pixel".into()));
        }
    }
    let model = Model { rig, camera, axes };
    let names = model.names();
    let qs: Vec<&[f64]> = poses.iter().map(|x| x.q.as_slice()).collect();
    let check = |j: &DMatrix<f64>| -> Result<f64, LightGeometryError> {
        let (condition, involved) = conditioning(j, &names);
        if condition <= opts.max_condition {
            return Ok(condition);
        }
        Err(LightGeometryError::Undetermined {
            hint: hint(rig, axes, &qs, &involved),
            parameters: involved,
            condition,
            max: opts.max_condition,
        })
    };
    let mut p = vec![0.0; 2];
    let mut r = model.residuals(&p, poses);
    let m = r.len();
    let sum_sq = |r: &[f64]| r.iter().map(|x| x * x).sum::<f64>();
    let initial_rms_px = (sum_sq(&r) / poses.len() as f64).sqrt();
    let mut cost = sum_sq(&r);
    let mut j = model.jacobian(&p, &qs);
    check(&j)?;
    let mut lambda = 1e-4;
    let mut iterations = 0;
    for it in 0..opts.max_iterations {
        iterations = it + 1;
        let jtj = j.transpose() * &j;
        let g = j.transpose() * DVector::from_vec(r.clone());
        let mut improved = false;
        for _ in 0..30 {
            let mut a = jtj.clone();
            for d in 0..2 {
                a[(d, d)] += lambda * jtj[(d, d)].max(1e-12);
            }
            let Some(step) = a.cholesky().map(|c| c.solve(&(-&g))) else {
                lambda *= 10.0;
                continue;
            };
            let cand: Vec<f64> = p.iter().zip(step.iter()).map(|(x, s)| x + s).collect();
            let rc = model.residuals(&cand, poses);
            let cc = sum_sq(&rc);
            if cc < cost {
                let rel = (cost - cc) / cost.max(1e-300);
                improved = step.norm() > 1e-13 && rel > 1e-14;
                p = cand;
                r = rc;
                cost = cc;
                lambda = (lambda / 10.0).max(1e-12);
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
        j = model.jacobian(&p, &qs);
    }
    let condition = check(&j)?;
    let rms_px = (cost / poses.len() as f64).sqrt();
    if rms_px.is_nan() || rms_px > opts.max_rms_px {
        return Err(LightGeometryError::PoorFit {
            rms_px,
            max_px: opts.max_rms_px,
        });
    }
    // Covariance σ² (JᵀJ)⁻¹, σ² the residual variance per coordinate. With exact
    // (noiseless) highlights σ² is the localisation bias' scatter, not noise: still the
    // honest spread of what the data say.
    let dof = m.saturating_sub(2).max(1);
    let s2 = cost / dof as f64;
    let cov = (j.transpose() * &j)
        .try_inverse()
        .unwrap_or_else(|| DMatrix::from_element(2, 2, f64::NAN))
        * s2;
    let (sig, correlation) = sigmas_and_correlation(&cov);
    // The other locator's answer, to first order: at the optimum Jᵀr = 0, so moving every
    // located highlight by s moves the estimate by (JᵀJ)⁻¹ Jᵀ s.
    let systematic_deg = poses
        .iter()
        .map(|p| p.locator_shift_px)
        .collect::<Option<Vec<[f64; 2]>>>()
        .and_then(|s| {
            let s = DVector::from_iterator(m, s.iter().flat_map(|x| [x[0], x[1]]));
            let dp = (j.transpose() * &j).try_inverse()? * (j.transpose() * s);
            dp.iter()
                .all(|x| x.is_finite())
                .then(|| dp.iter().map(|x| x.to_degrees()).collect())
        });
    let mut alignment = AlignmentSpec::default();
    for (k, &i) in axes.iter().enumerate() {
        alignment
            .axis_zero_offset_deg
            .insert(rig.axes[i].name.clone(), p[k].to_degrees());
    }
    Ok(LightGeometryFit {
        alignment,
        parameters: parameter_table(&names, &p, &sig),
        correlation,
        condition,
        rms_px,
        initial_rms_px,
        residuals_px: r.chunks_exact(2).map(|c| [c[0], c[1]]).collect(),
        iterations,
        poses: poses.len(),
        systematic_deg,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use gonio_devices::Direction;

    fn camera() -> CameraModel {
        CameraModel {
            fx: 1100.0,
            fy: 1100.0,
            cx: 391.5,
            cy: 313.25,
            distortion: [-0.12, 0.09, 0.0006, -0.0004, 0.0],
        }
    }

    fn rig() -> RigSpec {
        let mut r = RigSpec::default_rig();
        r.geometry.camera_distance_mm = 300.0;
        r.geometry.light_distance_mm = 600.0;
        r.geometry.camera_body_radius_mm = 30.0;
        r.geometry.sample_size_mm = 50.0;
        r
    }

    fn truth() -> AlignmentSpec {
        AlignmentSpec {
            axis_zero_offset_deg: [
                ("turntable".to_string(), 0.3),
                ("light_base".to_string(), 0.45),
                ("light_arc".to_string(), -0.3),
            ]
            .into_iter()
            .collect(),
            camera_rotation_deg: [0.2, -0.1, 0.3],
        }
    }

    /// Specular poses (light = mirror of the view), commanded through the nominal IK of `r`.
    fn commanded(r: &RigSpec, views: &[[f64; 2]]) -> Vec<Vec<f64>> {
        let k = kinematics::for_rig(r);
        views
            .iter()
            .map(|&[t, p]| {
                let l = if t == 0.0 { [10.0, 0.0] } else { [t, p + 180.0] };
                k.inverse(Direction::from_degrees(l[0], l[1]), Direction::from_degrees(t, p), None)
                    .unwrap()
                    .remove(0)
            })
            .collect()
    }

    /// The rig the fit believes in: the camera part of the truth known (as after a
    /// rig-geometry calibration), the lamp's not.
    fn believed() -> RigSpec {
        let mut r = rig();
        let mut a = truth();
        a.axis_zero_offset_deg.retain(|k, _| !k.starts_with("light"));
        r.alignment = Some(a);
        r
    }

    fn exact_poses(views: &[[f64; 2]]) -> Vec<LampPose> {
        let mut t = rig();
        t.alignment = Some(truth());
        let cam = camera();
        commanded(&believed(), views)
            .into_iter()
            .enumerate()
            .map(|(n, q)| LampPose {
                label: format!("p{n}"),
                pixel: predict_highlight(&t, &cam, &q).unwrap().1,
                locator_shift_px: None,
                q,
            })
            .collect()
    }

    const VIEWS: [[f64; 2]; 6] = [
        [20.0, 0.0],
        [30.0, 90.0],
        [45.0, 200.0],
        [40.0, 300.0],
        [60.0, 45.0],
        [60.0, 160.0],
    ];

    #[test]
    fn the_specular_point_obeys_the_mirror_law() {
        let r = believed();
        let q = &commanded(&r, &[[35.0, 70.0]])[0];
        let mut moved = q.clone();
        moved[3] += 1.5f64.to_radians();
        let k = kinematics::for_rig(&r);
        let (x, _) = predict_highlight(&r, &camera(), &moved).unwrap();
        let (c, l) = (k.camera_pose(&moved).position, k.light_position(&moved));
        let (to_c, to_l) = ((c - x).normalized(), (l - x).normalized());
        // mirror of x→camera about +z is x→lamp
        let mirrored = Vec3::new(-to_c.x, -to_c.y, to_c.z);
        assert!((mirrored - to_l).norm() < 1e-12, "{mirrored:?} {to_l:?}");
        assert!(
            x.x.hypot(x.y) > 1.0,
            "a tilted lamp moves the highlight off the centre: {x:?}"
        );
    }

    #[test]
    fn recovers_the_lamp_offsets_from_exact_highlights() {
        let poses = exact_poses(&VIEWS);
        let fit = estimate_light_geometry(&believed(), &camera(), &poses, &Default::default()).unwrap();
        let t = truth();
        for axis in ["light_base", "light_arc"] {
            let e = fit.alignment.axis_zero_offset_deg[axis];
            assert!((e - t.axis_zero_offset_deg[axis]).abs() < 1e-7, "{axis}: {e}");
        }
        assert_eq!(fit.alignment.axis_zero_offset_deg.len(), 2, "only the lamp's axes");
        assert!(fit.rms_px < 1e-6 && fit.initial_rms_px > 1.0, "{fit:?}");
        assert!(fit.condition < 10.0, "{}", fit.condition);
        // apply keeps the camera's alignment
        let mut r = believed();
        fit.apply(&mut r);
        let a = r.alignment.unwrap();
        assert_eq!(a.axis_zero_offset_deg.len(), 3);
        assert_eq!(a.camera_rotation_deg, truth().camera_rotation_deg);
    }

    #[test]
    fn sigma_matches_the_scatter_of_noisy_highlights() {
        // Deterministic pseudo-noise of 0.2 px on 6 poses, 40 draws: the estimates scatter
        // by about their reported σ (within a factor 2 either way).
        let mut state = 12345u64;
        let mut gauss = || {
            let mut s = 0.0;
            for _ in 0..12 {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                s += (state >> 11) as f64 / (1u64 << 53) as f64;
            }
            s - 6.0
        };
        let exact = exact_poses(&VIEWS);
        let (mut sq, mut sig) = (0.0, 0.0);
        let draws = 40;
        for _ in 0..draws {
            let mut poses = exact.clone();
            for p in &mut poses {
                p.pixel[0] += 0.2 * gauss();
                p.pixel[1] += 0.2 * gauss();
            }
            let loose = LightGeometryOptions {
                max_rms_px: 1.0,
                ..Default::default()
            };
            let fit = estimate_light_geometry(&believed(), &camera(), &poses, &loose).unwrap();
            let e = fit.parameters[1].value_deg - truth().axis_zero_offset_deg["light_arc"];
            sq += e * e;
            sig += fit.parameters[1].sigma_deg;
        }
        let (scatter, sigma) = ((sq / draws as f64).sqrt(), sig / draws as f64);
        assert!(
            scatter > 0.5 * sigma && scatter < 2.0 * sigma,
            "scatter {scatter} σ {sigma}"
        );
    }

    #[test]
    fn lamp_at_the_pole_leaves_the_light_base_undetermined() {
        let r = believed();
        let k = kinematics::for_rig(&r);
        let poses: Vec<(String, Vec<f64>)> = [[12.0, 0.0], [12.0, 90.0], [14.0, 200.0]]
            .iter()
            .enumerate()
            .map(|(n, &[t, p])| {
                let q = k
                    .inverse(Direction::from_degrees(0.0, 0.0), Direction::from_degrees(t, p), None)
                    .unwrap()
                    .remove(0);
                (format!("p{n}"), q)
            })
            .collect();
        let e = check_design(&r, &camera(), &poses, &Default::default()).unwrap_err();
        match &e {
            LightGeometryError::Undetermined { parameters, hint, .. } => {
                assert_eq!(parameters, &vec!["zero_offset.light_base".to_string()], "{e}");
                assert!(hint.contains("pole"), "{e}");
            }
            _ => panic!("{e}"),
        }
        // the same from the fit itself
        let lp: Vec<LampPose> = poses
            .iter()
            .map(|(label, q)| LampPose {
                label: label.clone(),
                q: q.clone(),
                pixel: predict_highlight(&r, &camera(), q).unwrap().1,
                locator_shift_px: None,
            })
            .collect();
        let e = estimate_light_geometry(&r, &camera(), &lp, &Default::default()).unwrap_err();
        assert!(matches!(e, LightGeometryError::Undetermined { .. }), "{e}");
    }

    #[test]
    fn design_check_refuses_off_sample_poses_and_accepts_specular_ones() {
        let r = believed();
        let named = |qs: Vec<Vec<f64>>| -> Vec<(String, Vec<f64>)> {
            qs.into_iter().enumerate().map(|(n, q)| (format!("p{n}"), q)).collect()
        };
        let good = named(commanded(&r, &VIEWS));
        let cond = check_design(&r, &camera(), &good, &Default::default()).unwrap();
        assert!(cond < 10.0, "{cond}");
        // light 90° away from the mirror direction: its reflection is far off the sample
        let k = kinematics::for_rig(&r);
        let mut bad = good.clone();
        bad[2].1 = k
            .inverse(
                Direction::from_degrees(45.0, 290.0),
                Direction::from_degrees(45.0, 200.0),
                None,
            )
            .unwrap()
            .remove(0);
        let e = check_design(&r, &camera(), &bad, &Default::default()).unwrap_err();
        assert!(
            matches!(&e, LightGeometryError::OffSample { pose, .. } if pose == "p2"),
            "{e}"
        );
        assert!(e.to_string().contains("φ_v + 180°"), "{e}");
    }

    #[test]
    fn bad_inputs_are_named() {
        let mut poses = exact_poses(&VIEWS[..3]);
        poses[1].q.pop();
        let e = estimate_light_geometry(&believed(), &camera(), &poses, &Default::default()).unwrap_err();
        assert!(
            matches!(&e, LightGeometryError::BadPose { pose, .. } if pose == "p1"),
            "{e}"
        );
        let e = estimate_light_geometry(&believed(), &camera(), &poses[..2], &Default::default()).unwrap_err();
        assert!(
            matches!(e, LightGeometryError::TooFewPoses { needed: 3, got: 2 }),
            "{e}"
        );
        // a highlight far from where any offset puts it: refused as a poor fit
        let mut poses = exact_poses(&VIEWS);
        poses[0].pixel[0] += 40.0;
        let e = estimate_light_geometry(&believed(), &camera(), &poses, &Default::default()).unwrap_err();
        assert!(matches!(e, LightGeometryError::PoorFit { .. }), "{e}");
        let mut o = LightGeometryOptions::default();
        o.highlight.threshold_fraction = 1.5;
        assert_eq!(o.validate().unwrap_err().0, "highlight.threshold_fraction");
    }

    /// A frame with a pixel-integrated Gaussian lobe of σ = `s` px at (u0, v0) scaled to
    /// `peak`, on a background of 0.001; `skew` stretches its +u side (an asymmetric lobe).
    fn blob(u0: f64, v0: f64, s: f64, peak: f64, skew: f64) -> RgbImage {
        let (w, h) = (120, 100);
        let mut img = RgbImage::new(w, h);
        let n = 8;
        for j in 0..h {
            for i in 0..w {
                let mut acc = 0.0;
                for k in 0..n * n {
                    let u = i as f64 + ((k % n) as f64 + 0.5) / n as f64 - u0;
                    let v = j as f64 + ((k / n) as f64 + 0.5) / n as f64 - v0;
                    let su = if u > 0.0 { s * (1.0 + skew) } else { s };
                    acc += (-0.5 * (u * u / (su * su) + v * v / (s * s))).exp();
                }
                let val = (0.001 + peak * acc / (n * n) as f64) as f32;
                img.data[3 * (j * w + i)..3 * (j * w + i) + 3].copy_from_slice(&[val, 0.9 * val, 1.1 * val]);
            }
        }
        img
    }

    #[test]
    fn highlights_are_located_to_a_few_hundredths_of_a_pixel() {
        for locator in [Locator::Centroid, Locator::LogQuadratic] {
            let opts = HighlightOptions {
                locator,
                ..Default::default()
            };
            for (u0, v0, s) in [(60.3, 47.8, 2.0), (40.71, 55.15, 1.2), (75.5, 30.02, 4.0)] {
                let h = locate_highlight(&blob(u0, v0, s, 0.6, 0.0), &opts).unwrap();
                let e = (h.pixel[0] - u0).hypot(h.pixel[1] - v0);
                assert!(e < 0.03, "{locator:?} σ {s}: {:?} vs ({u0}, {v0}): {e}", h.pixel);
                assert!((h.radius_px - s).abs() < 0.6 * s, "{h:?}");
            }
        }
        // an asymmetric lobe: both locators are pulled toward its long side, by less than
        // a fraction of its width (this is the bias the runner measures on the simulator)
        for locator in [Locator::Centroid, Locator::LogQuadratic] {
            let opts = HighlightOptions {
                locator,
                ..Default::default()
            };
            let h = locate_highlight(&blob(60.0, 50.0, 2.0, 0.6, 0.2), &opts).unwrap();
            let bias = h.pixel[0] - 60.0;
            assert!(bias > 0.0 && bias < 0.6, "{locator:?}: bias {bias}");
        }
        // the two locators agree on a symmetric lobe and disagree on an asymmetric one,
        // along its long axis: the disagreement is what the fit's systematic term uses
        let opts = HighlightOptions::default();
        let sym = locate_highlight(&blob(60.3, 47.8, 2.0, 0.6, 0.0), &opts).unwrap();
        let [du, dv] = sym.locator_shift_px.unwrap();
        assert!(du.hypot(dv) < 0.02, "symmetric: {du} {dv}");
        let skew = locate_highlight(&blob(60.0, 50.0, 2.0, 0.6, 0.2), &opts).unwrap();
        let [du, dv] = skew.locator_shift_px.unwrap();
        assert!(du.abs() > 5.0 * dv.abs() && du.abs() > 0.02, "asymmetric: {du} {dv}");
    }

    #[test]
    fn the_systematic_term_is_the_refit_with_the_other_locator() {
        // every highlight shifted by the same 0.05 px in v (a lobe asymmetry the residuals
        // cannot show): the first-order term equals refitting on the shifted highlights
        let shift = [0.01, 0.05];
        let mut poses = exact_poses(&VIEWS);
        for p in &mut poses {
            p.locator_shift_px = Some(shift);
        }
        let fit = estimate_light_geometry(&believed(), &camera(), &poses, &Default::default()).unwrap();
        let s = fit.systematic_deg.clone().expect("every pose has a shift");
        let moved: Vec<LampPose> = poses
            .iter()
            .map(|p| LampPose {
                pixel: [p.pixel[0] + shift[0], p.pixel[1] + shift[1]],
                ..p.clone()
            })
            .collect();
        let refit = estimate_light_geometry(&believed(), &camera(), &moved, &Default::default()).unwrap();
        for (k, name) in ["light_base", "light_arc"].iter().enumerate() {
            let d = refit.alignment.axis_zero_offset_deg[*name] - fit.alignment.axis_zero_offset_deg[*name];
            assert!(d.abs() > 1e-5, "{name}: the shift must move the estimate ({d})");
            assert!(
                (s[k] - d).abs() < 0.02 * d.abs(),
                "{name}: first order {} vs refit {d}",
                s[k]
            );
        }
        // the exact fit has (almost) no statistical σ: the total σ is the systematic term
        let (total, _) = fit.with_systematic();
        for (p, sk) in total.iter().zip(&s) {
            assert!((p.sigma_deg - sk.abs()).abs() < 1e-3 * sk.abs() + 1e-9, "{p:?} vs {sk}");
        }
        // a pose without a second position: no systematic term, σ unchanged
        poses[0].locator_shift_px = None;
        let fit = estimate_light_geometry(&believed(), &camera(), &poses, &Default::default()).unwrap();
        assert!(fit.systematic_deg.is_none());
        assert_eq!(fit.with_systematic().0, fit.parameters);
    }

    #[test]
    fn bad_frames_are_diagnosed() {
        let opts = HighlightOptions::default();
        let black = RgbImage::new(64, 48);
        assert!(matches!(
            locate_highlight(&black, &opts),
            Err(HighlightError::Empty { .. })
        ));
        let e = locate_highlight(&blob(60.0, 50.0, 2.0, 3.0, 0.0), &opts).unwrap_err();
        assert!(
            matches!(e, HighlightError::Saturated { pixels, .. } if pixels > 1),
            "{e}"
        );
        assert!(e.to_string().contains("exposure_s"), "{e}");
        let e = locate_highlight(&blob(1.0, 50.0, 2.0, 0.5, 0.0), &opts).unwrap_err();
        assert!(matches!(e, HighlightError::Truncated { .. }), "{e}");
        // a lamp on a diffuse sample: bright everywhere, no compact highlight
        let diffuse = blob(60.0, 50.0, 40.0, 0.5, 0.0);
        let small = HighlightOptions {
            max_region_px: 2000,
            ..Default::default()
        };
        let e = locate_highlight(&diffuse, &small).unwrap_err();
        assert!(
            matches!(e, HighlightError::NotCompact { .. } | HighlightError::Truncated { .. }),
            "{e}"
        );
        let bad = RgbImage {
            width: 4,
            height: 4,
            data: vec![0.0; 5],
        };
        assert!(matches!(
            locate_highlight(&bad, &opts),
            Err(HighlightError::BadImage { .. })
        ));
    }
}
