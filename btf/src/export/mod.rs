//! Exports of a fitted glTF SVBRDF (`gonio fit --per-texel --model gltf --out F.gbtf`) to
//! the formats renderers read: glTF 2.0 (`.gltf` folder or one `.glb`), MaterialX
//! (`standard_surface`), OpenUSD (`UsdPreviewSurface`, `.usda`) and Mitsuba 3 (XML scene).
//!
//! Why a room of `gonio-btf` and not of the CLI: the writers are library code that tests and
//! scripts call without the binary, they read the `.gbtf` container (`compress`), and they
//! sit beside the fit whose parameters they carry; the CLI only parses flags and prints.
//! Hand-written documents (JSON, XML, USDA text) and PNGs from the `image` crate the crate
//! already links: no new dependency.
//!
//! Conventions every format shares ([`Material`]):
//! - textures are PNG; the base colour is sRGB-encoded, every other map linear;
//! - the normal map is tangent space, +X = u (right), +Y = up in the image (glTF's and
//!   MaterialX's convention; OpenGL-style), stored as `n · ½ + ½`;
//! - the base colour is clamped to ≤ 1 (a warning counts the texels clamped);
//! - one texture tile spans the sample's physical size (`size_mm` of the dataset), so the
//!   UV scale carries it: the exported quad is that size;
//! - texels the fit did not converge on were filled from their neighbours; the export's
//!   metadata lists them;
//! - provenance (dataset, fit, units) in each format's own metadata field.
//!
//! Two formats hold one BRDF, not textures: `rgl-bsdf` (Mitsuba 3's `measured`, [`rgl`]) and
//! `merl` (the MERL binary, [`merl`]). They take the material's averaged fit, made
//! isotropic ([`average`]).

pub mod average;
pub mod fidelity;
pub mod gltf;
pub mod materialx;
pub mod merl;
pub mod mitsuba;
pub mod rgl;
pub mod texture;
pub mod usd;

use crate::compress::container::Gbtf;
use crate::compress::gltf as gltf_file;
use serde::Serialize;
use std::path::{Path, PathBuf};
use thiserror::Error;

#[derive(Debug, Error)]
pub enum ExportError {
    #[error("{path}: {reason}")]
    Input { path: String, reason: String },
    #[error("{path}: {reason}")]
    Output { path: String, reason: String },
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> ExportError + '_ {
    move |source| ExportError::Io {
        path: path.display().to_string(),
        source,
    }
}

/// A format a fitted material is exported to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Format {
    Gltf,
    Materialx,
    Usd,
    Mitsuba,
    /// Mitsuba 3 `measured`: the averaged BRDF as an RGL tensor file (`.bsdf`).
    RglBsdf,
    /// The averaged BRDF as a MERL binary (`.binary`, plus `OUT.binary.json`).
    Merl,
}

impl Format {
    pub fn name(self) -> &'static str {
        match self {
            Format::Gltf => "gltf",
            Format::Materialx => "materialx",
            Format::Usd => "usd",
            Format::Mitsuba => "mitsuba",
            Format::RglBsdf => "rgl-bsdf",
            Format::Merl => "merl",
        }
    }

    /// Whether the format holds the averaged BRDF ([`average`]) rather than textures.
    pub fn is_average(self) -> bool {
        matches!(self, Format::RglBsdf | Format::Merl)
    }

    /// Check OUT before any work: `.glb` (one file) or a folder for glTF, a folder for the
    /// others (named anything but a file extension the format does not write).
    pub fn check_out(self, out: &Path) -> Result<Layout, ExportError> {
        let ext = out.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
        let bad = |reason: String| ExportError::Output {
            path: out.display().to_string(),
            reason,
        };
        match (self, ext.as_deref()) {
            (Format::RglBsdf, Some("bsdf")) | (Format::Merl, Some("binary")) => Ok(Layout::File),
            (Format::RglBsdf, _) => Err(bad(
                "--format rgl-bsdf writes one RGL tensor file: give a name ending in .bsdf".into(),
            )),
            (Format::Merl, _) => Err(bad(
                "--format merl writes one MERL binary (and OUT.binary.json beside it): give a name ending in .binary"
                    .into(),
            )),
            (Format::Gltf, Some("glb")) => Ok(Layout::File),
            (_, None) => Ok(Layout::Folder),
            (Format::Gltf, Some(e)) => Err(bad(format!(
                "--format gltf writes one .glb file or a folder (no extension); `.{e}` is neither"
            ))),
            (Format::Usd, Some("usdz")) => Ok(Layout::File),
            (f, Some(e)) => Err(bad(format!(
                "--format {} writes a folder (the document and its textures); give a name without the `.{e}` \
                 extension",
                f.name()
            ))),
        }
    }
}

/// What OUT is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    File,
    Folder,
}

/// The export's options.
#[derive(Clone, Debug)]
pub struct ExportOptions {
    /// Texture side in texels (`None`: the fit's own resolution).
    pub size: Option<usize>,
    /// Accept values that are not radiometrically calibrated (labelled so).
    pub allow_uncalibrated: bool,
    /// Bits per PNG sample: 8 or 16.
    pub bit_depth: u8,
    /// A texture smaller than the fit is prefiltered over each texel's footprint
    /// ([`texture::prefiltered`]: averages, and the normals' spread added to the roughness)
    /// instead of sampled bilinearly between texel centres.
    pub prefilter: bool,
}

/// The material as textures, ready for the writers.
#[derive(Clone, Debug)]
pub struct Material {
    pub width: usize,
    pub height: usize,
    /// Linear RGB, clamped to [0, 1], row 0 at the sample's +y edge (image top).
    pub base_color: Vec<[f32; 3]>,
    pub metallic: Vec<f32>,
    pub roughness: Vec<f32>,
    /// Unit tangent-space normals (+z out of the surface).
    pub normal: Vec<[f32; 3]>,
    /// The `KHR_materials_anisotropy` vector `s·(cos 2φ, sin 2φ)` per texel
    /// (`gonio_brdf::gltf`), resampled as a vector; all 0 for an isotropic fit.
    pub anisotropy: Vec<[f32; 2]>,
    /// The sample's side (mm): the size of one texture tile.
    pub size_mm: f64,
    pub provenance: serde_json::Value,
    pub warnings: Vec<String>,
    /// Bits per PNG sample of the textures: 8 or 16.
    pub bit_depth: u8,
}

impl Material {
    /// Texels with a non-zero anisotropy strength.
    pub fn anisotropic_texels(&self) -> usize {
        self.anisotropy.iter().filter(|a| a[0] != 0.0 || a[1] != 0.0).count()
    }

    /// The best isotropic approximation of the anisotropic texels, for the formats without
    /// anisotropy (`usd`, `mitsuba`): the roughness whose α is the geometric mean
    /// `√(α_t α_b)` of the two, the isotropic GGX lobe of the same peak height
    /// (`D(0) = 1/(π α_t α_b)`) and the same solid angle of the highlight. Returns the
    /// warning that names what is lost; `None` when no texel is anisotropic.
    pub fn make_isotropic(&mut self, format: Format) -> Option<String> {
        let n = self.anisotropic_texels();
        if n == 0 {
            return None;
        }
        let mut strongest = 0.0f64;
        for (r, a) in self.roughness.iter_mut().zip(self.anisotropy.iter_mut()) {
            let v = [a[0] as f64, a[1] as f64];
            let (at, ab) = gonio_brdf::gltf::alphas(*r as f64, v);
            strongest = strongest.max(gonio_brdf::gltf::anisotropy_of(v).0);
            *r = ((at * ab).sqrt().sqrt()).clamp(0.0, 1.0) as f32;
            *a = [0.0, 0.0];
        }
        let why = match format {
            Format::Mitsuba => "Mitsuba's principled has anisotropy only along the tangent, not per-texel directions",
            _ => "the format has no anisotropy",
        };
        Some(format!(
            "{n} of {} texels are anisotropic (KHR_materials_anisotropy, strength up to {strongest:.3}); --format {}: \
             {why}, so their elongated highlight and its direction are lost: written as the best isotropic GGX, \
             roughness² = √(α_t α_b) (the same peak height and highlight area)",
            self.anisotropy.len(),
            format.name()
        ))
    }
}

/// Whether a `.gbtf`'s values are calibrated: BRDF values, or calibrated by a white standard.
fn calibrated(g: &Gbtf) -> bool {
    let s = &g.header.source;
    let values = s.get("values").and_then(|v| v.as_str()).unwrap_or("");
    crate::fit::data::values_are_brdf(values) || s.get("calibrated_by").is_some_and(|c| !c.is_null())
}

impl Material {
    /// Read a glTF SVBRDF `.gbtf` (method `gltf`) and resample it to `opts.size`.
    pub fn from_gbtf(g: &Gbtf, path: &Path, opts: &ExportOptions) -> Result<Material, ExportError> {
        let input = |reason: String| ExportError::Input {
            path: path.display().to_string(),
            reason,
        };
        if g.header.method != crate::compress::CodecId::Gltf.name() {
            return Err(input(format!(
                "a `{}` file; the renderers' formats take the glTF model's per-texel fit: `gonio fit DATASET \
                 --model gltf --per-texel --out F.gbtf` (or give the dataset to gonio export)",
                g.header.method
            )));
        }
        gltf_file::validate(g).map_err(|e| input(e.to_string()))?;
        let calibrated = calibrated(g);
        if !calibrated && !opts.allow_uncalibrated {
            return Err(input(format!(
                "its values are not radiometrically calibrated (\"{}\"): a renderer would read sensor numbers \
                 as reflectance; fit with --white DIR, or pass --allow-uncalibrated to export them labelled \
                 as such",
                g.header.source.get("values").and_then(|v| v.as_str()).unwrap_or("?")
            )));
        }
        let (w, h) = (g.header.width, g.header.height);
        let (ow, oh) = match opts.size {
            None => (w, h),
            Some(0) => return Err(input("--size 0: a texture needs at least one texel".into())),
            Some(s) => (s, s),
        };
        if !matches!(opts.bit_depth, 8 | 16) {
            return Err(ExportError::Output {
                path: path.display().to_string(),
                reason: format!(
                    "--bit-depth {}: PNG textures are written with 8 or 16 bits",
                    opts.bit_depth
                ),
            });
        }
        let quality = &g.blocks[2];
        let failed: Vec<usize> = (0..w * h).filter(|t| quality[2 * t + 1] != 0.0).collect();
        let mut warnings = Vec::new();
        let mut clamped = 0usize;
        let n = ow * oh;
        let mut m = Material {
            width: ow,
            height: oh,
            base_color: Vec::with_capacity(n),
            metallic: Vec::with_capacity(n),
            roughness: Vec::with_capacity(n),
            normal: Vec::with_capacity(n),
            anisotropy: Vec::with_capacity(n),
            size_mm: g.header.source.get("sample").map_or(60.0, |s| s.get_size_mm()),
            provenance: serde_json::Value::Null,
            warnings: Vec::new(),
            bit_depth: opts.bit_depth,
        };
        for j in 0..oh {
            for i in 0..ow {
                let np = gltf_file::params_per_texel(g);
                let p = if opts.prefilter && texture::downsamples(w, h, ow, oh) {
                    texture::prefiltered(&g.blocks[0], np, w, h, i, j, ow, oh)
                } else {
                    texture::bilinear(&g.blocks[0], np, w, h, i, j, ow, oh)
                };
                let mut over = false;
                let bc = [0, 1, 2].map(|c| {
                    let x = p[c];
                    over |= x > 1.0;
                    x.clamp(0.0, 1.0) as f32
                });
                clamped += over as usize;
                m.base_color.push(bc);
                m.metallic.push(p[3].clamp(0.0, 1.0) as f32);
                m.roughness.push(p[4].clamp(0.0, 1.0) as f32);
                let nv = gonio_brdf::gltf::normal_vector([p[5], p[6]]);
                m.normal.push([nv.x as f32, nv.y as f32, nv.z as f32]);
                m.anisotropy.push(match p.get(7..9) {
                    Some(a) => [a[0] as f32, a[1] as f32],
                    None => [0.0, 0.0],
                });
            }
        }
        if clamped > 0 {
            warnings.push(format!(
                "{clamped} of {n} texels have a base colour above 1 (brighter than a white Lambertian surface: \
                 calibration, or light the model cannot place in its lobe); clamped to 1"
            ));
        }
        if !failed.is_empty() {
            warnings.push(format!(
                "{} of {} texels did not converge in the fit; filled from their neighbours and listed in the \
                 metadata",
                failed.len(),
                w * h
            ));
        }
        m.provenance = serde_json::json!({
            "generator": concat!("gonio ", env!("CARGO_PKG_VERSION")),
            "fit": {
                "file": path.display().to_string(),
                "model": "gltf metallic-roughness (Lambert + GGX, alpha = roughness^2, Schlick F0 = mix(0.04, base, metallic)) + normal per texel",
                "texels": [w, h],
            },
            "dataset": g.header.source.get("dataset"),
            "values": g.header.source.get("values"),
            "calibrated_by": g.header.source.get("calibrated_by"),
            "units": if calibrated {
                "base colour: linear reflectance of the BRDF fitted to calibrated BRDF values (1/sr)"
            } else {
                "UNCALIBRATED: fitted to values that are not BRDF values (--allow-uncalibrated)"
            },
            "sample_size_mm": m.size_mm,
            "texture_texels": [ow, oh],
            "base_color_texels_clamped": clamped,
            "not_converged_texels": failed,
            "normal_map": "tangent space, +X = u (right), +Y = up in the image (OpenGL), n/2 + 1/2",
            "anisotropic_texels": m.anisotropic_texels(),
            "png_bit_depth": opts.bit_depth,
        });
        m.warnings = warnings;
        Ok(m)
    }
}

/// The sample's size from a `.gbtf` header's `sample` object (60 mm when absent).
trait SizeMm {
    fn get_size_mm(&self) -> f64;
}

impl SizeMm for serde_json::Value {
    fn get_size_mm(&self) -> f64 {
        self.get("size_mm")
            .and_then(|v| v.as_f64())
            .filter(|s| s.is_finite() && *s > 0.0)
            .unwrap_or(60.0)
    }
}

/// What an export wrote.
#[derive(Clone, Debug, Serialize)]
pub struct ExportReport {
    pub format: Format,
    pub out: PathBuf,
    /// Every file written (the document first).
    pub files: Vec<PathBuf>,
    pub bytes: u64,
    pub texture_texels: [usize; 2],
    pub size_mm: f64,
    pub warnings: Vec<String>,
}

/// Write `m` as `format` to `out` (checked by [`Format::check_out`] first).
pub fn write(m: &Material, format: Format, out: &Path) -> Result<ExportReport, ExportError> {
    let layout = format.check_out(out)?;
    // Formats without anisotropy get the best isotropic approximation, with a warning.
    let mut iso;
    let mut m = m;
    let mut warnings = m.warnings.clone();
    if format == Format::Materialx {
        if let Some(w) = materialx::clamped_anisotropy(m) {
            warnings.push(w);
        }
    }
    if matches!(format, Format::Usd | Format::Mitsuba) && m.anisotropic_texels() > 0 {
        iso = m.clone();
        if let Some(w) = iso.make_isotropic(format) {
            warnings.push(w);
        }
        m = &iso;
    }
    let files = match (format, layout) {
        (Format::Gltf, Layout::File) => vec![gltf::write_glb(m, out)?],
        (Format::Gltf, Layout::Folder) => gltf::write_folder(m, out)?,
        (Format::Materialx, _) => materialx::write(m, out)?,
        (Format::Usd, Layout::File) => vec![usd::write_usdz(m, out)?],
        (Format::Usd, Layout::Folder) => usd::write(m, out)?,
        (Format::Mitsuba, _) => mitsuba::write(m, out)?,
        (Format::RglBsdf | Format::Merl, _) => {
            return Err(ExportError::Output {
                path: out.display().to_string(),
                reason: format!("--format {} holds the averaged BRDF: use write_average", format.name()),
            })
        }
    };
    let mut bytes = 0;
    for f in &files {
        bytes += std::fs::metadata(f).map_err(io(f))?.len();
    }
    Ok(ExportReport {
        format,
        out: out.to_path_buf(),
        files,
        bytes,
        texture_texels: [m.width, m.height],
        size_mm: m.size_mm,
        warnings,
    })
}

/// What an export of the averaged BRDF wrote.
#[derive(Clone, Debug, Serialize)]
pub struct AverageReport {
    pub format: Format,
    pub out: PathBuf,
    /// Every file written (the BRDF first).
    pub files: Vec<PathBuf>,
    pub bytes: u64,
    /// rgl-bsdf: the grid side; merl: null.
    pub size: Option<usize>,
    /// rgl-bsdf: the θ_i slices (degrees).
    pub theta_i_deg: Option<Vec<f64>>,
    pub tilt_deg: f64,
    pub warnings: Vec<String>,
}

/// Write the averaged BRDF `avg` as `format` (`rgl-bsdf` on `size × size` grids, default
/// [`rgl::DEFAULT_SIZE`]; `merl`, which has its own fixed bins, refuses a size).
pub fn write_average(
    avg: &average::AverageBrdf,
    format: Format,
    size: Option<usize>,
    out: &Path,
) -> Result<AverageReport, ExportError> {
    format.check_out(out)?;
    let bad = |reason: String| ExportError::Output {
        path: out.display().to_string(),
        reason,
    };
    let (files, size, theta) = match format {
        Format::RglBsdf => {
            let n = size.unwrap_or(rgl::DEFAULT_SIZE);
            rgl::check_size(n).map_err(bad)?;
            let s = rgl::write(avg, n, out)?;
            (vec![out.to_path_buf()], Some(n), Some(s.theta_i_deg))
        }
        Format::Merl => {
            if let Some(n) = size {
                return Err(bad(format!(
                    "--size {n}: a MERL binary has fixed bins (90 θ_h × 90 θ_d × 180 φ_d); leave --size out"
                )));
            }
            let s = merl::write(avg, out)?;
            (vec![out.to_path_buf(), s.sidecar], None, None)
        }
        f => {
            return Err(bad(format!(
                "--format {} writes textures, not the averaged BRDF",
                f.name()
            )))
        }
    };
    let mut bytes = 0;
    for f in &files {
        bytes += std::fs::metadata(f).map_err(io(f))?.len();
    }
    Ok(AverageReport {
        format,
        out: out.to_path_buf(),
        files,
        bytes,
        size,
        theta_i_deg: theta,
        tilt_deg: average::tilt_deg(avg.fit.normal),
        warnings: avg.warnings.clone(),
    })
}

/// Create the folder OUT (and `OUT/textures`) and write the shared textures; returns
/// their paths relative to OUT: base colour, metallic, roughness, normal.
pub(crate) fn write_textures(m: &Material, out: &Path) -> Result<[(String, PathBuf); 4], ExportError> {
    let dir = out.join("textures");
    std::fs::create_dir_all(&dir).map_err(io(&dir))?;
    let write = |name: &str, png: Vec<u8>| -> Result<(String, PathBuf), ExportError> {
        let p = dir.join(name);
        std::fs::write(&p, png).map_err(io(&p))?;
        Ok((format!("textures/{name}"), p))
    };
    Ok([
        write("base_color.png", texture::base_color_png(m)?)?,
        write(
            "metallic.png",
            texture::gray_png(m.width, m.height, &m.metallic, m.bit_depth)?,
        )?,
        write(
            "roughness.png",
            texture::gray_png(m.width, m.height, &m.roughness, m.bit_depth)?,
        )?,
        write("normal.png", texture::normal_png(m)?)?,
    ])
}

/// A glTF fit seen as a renderer sees the exported material: every texel lit by a
/// directional light of unit irradiance at the nominal grid directions, radiance
/// `f(l, v) · cos θ_l` (the shading normal's cosine is inside `f`, see
/// `gonio_brdf::gltf`), without the rig's gain planes or per-texel directions. What `gonio
/// render --material` draws, and what a Mitsuba render of the exported scene with a
/// unit-irradiance `directional` emitter must reproduce.
pub struct UnitIrradiance {
    gbtf: Gbtf,
}

impl UnitIrradiance {
    /// `g` must be a glTF `.gbtf` (method `gltf`).
    pub fn new(g: Gbtf) -> Result<UnitIrradiance, crate::compress::CompressError> {
        if g.header.method != crate::compress::CodecId::Gltf.name() {
            return Err(crate::compress::CompressError::Invalid(format!(
                "a `{}` file: only a glTF fit (`gonio fit --model gltf --per-texel`) is a material to light",
                g.header.method
            )));
        }
        gltf_file::validate(&g)?;
        Ok(UnitIrradiance { gbtf: g })
    }
}

impl crate::compress::interp::BtfModel for UnitIrradiance {
    fn width(&self) -> usize {
        self.gbtf.header.width
    }
    fn height(&self) -> usize {
        self.gbtf.header.height
    }
    fn lights_deg(&self) -> &[[f64; 2]] {
        &self.gbtf.header.lights_deg
    }
    fn views_deg(&self) -> &[[f64; 2]] {
        &self.gbtf.header.views_deg
    }
    fn reconstruct(&self, light: usize, view: usize) -> Result<Vec<f32>, crate::compress::CompressError> {
        let h = &self.gbtf.header;
        let (Some(ld), Some(vd)) = (h.lights_deg.get(light), h.views_deg.get(view)) else {
            return Err(crate::compress::CompressError::Invalid(format!(
                "pair (light {light}, view {view}) outside the grid"
            )));
        };
        let d = |x: &[f64; 2]| gonio_devices::Direction::from_degrees(x[0], x[1]).vector();
        let (l, v) = (d(ld), d(vd));
        Ok((0..h.width * h.height)
            .flat_map(|t| {
                gltf_file::texel(&self.gbtf, t)
                    .eval(l, v)
                    .map(|f| (f * l.z.max(0.0)) as f32)
            })
            .collect())
    }
}

/// XML attribute or text escaping.
pub(crate) fn xml_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
        .replace('\'', "&apos;")
}

#[cfg(test)]
mod tests;
