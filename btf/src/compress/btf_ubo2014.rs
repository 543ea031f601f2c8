//! Bonn's UBO2014 factorized `.btf` container (signature `!DFMF08FC`), written and read.
//!
//! The specification is the public reader `btf-extractor` 1.7.0 (`btf_extractor/c_ext/btf.hh`,
//! `LoadBTF`, DFMF branch), since Bonn never published one. Little-endian throughout:
//!
//! ```text
//! "!" "DFMF" "08FC" ["R"]        signature; "R": a rotation list follows the directions
//! common header (Size bytes, Size counted from here):
//!   u32 Size, u32 Version (4), char[80] MeasurementSetup, char[80] ImageSensor,
//!   char[80] LightSource, f32 PPMM, f32×3 RGB,
//!   u32 CosineFlag (Version > 1), u32 len + XML (Version > 2),
//!   u32 ChannelCount + per channel u32 len + name (Version > 3)
//! u32 ViewCount; per view: f32 θ, f32 φ (radians), u32 LightCount, LightCount × (f32 θ, f32 φ)
//! u32 Width, u32 Height
//! ["R":] u32 rotation count, count × 9 f32            (gonio writes 0 rotations)
//! u32 components (unused by the reader), u32 ColorModel, f32×3 ColorMean, f32×9 ColorTransform
//! per channel: u8 DataSize (2 = half, 4 = f32, 8 = f64), u32 c, u32 rows, u32 columns,
//!   c scalars (singular values), rows × c U (row = view · L + light),
//!   columns × c S·V (column = texel; rows of the image stored bottom row first)
//! end of file (the reader rejects trailing bytes)
//! ```
//!
//! Constraints the reader imposes and [`to_bytes`] checks: `rows` must be `LightCount²`
//! (the reader assumes as many views as lights), so a grid with fewer views than lights is
//! padded with zero U rows and a grid with more views is rejected; ColorMean and
//! ColorTransform are read and ignored (gonio writes zeros and the RGB → YUV matrix for the
//! record). The reader also crashes on a malformed file instead of reporting it, which is
//! why [`from_bytes`] checks every length itself.

use super::dfmf::{rgb_to_yuv, ChannelFactors, ColorModel, Dfmf};
use super::error::CompressError;
use half::f16;
use std::path::Path;

/// The signature, including the rotations flag.
pub const SIGNATURE: &[u8; 10] = b"!DFMF08FCR";
/// Common header version gonio writes (4: cosine flag, XML and channel names present).
pub const HEADER_VERSION: u32 = 4;
/// `sizeof(BTFCommonHeader)`.
const COMMON_HEADER_BYTES: usize = 4 + 4 + 3 * 80 + 4 + 12;

/// Scalar type of the stored factors.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// IEEE half (DataSize 2), as Bonn's files; values beyond ±65504 are an error.
    F16,
    /// f32 (DataSize 4).
    F32,
}

impl Precision {
    pub fn bytes(self) -> usize {
        match self {
            Precision::F16 => 2,
            Precision::F32 => 4,
        }
    }
}

fn put_u32(out: &mut Vec<u8>, v: u32) {
    out.extend_from_slice(&v.to_le_bytes());
}
fn put_f32(out: &mut Vec<u8>, v: f32) {
    out.extend_from_slice(&v.to_le_bytes());
}
fn put_fixed(out: &mut Vec<u8>, s: &str, n: usize) {
    let b = s.as_bytes();
    let k = b.len().min(n - 1);
    out.extend_from_slice(&b[..k]);
    out.resize(out.len() + n - k, 0);
}
fn u32_of(v: usize, what: &str) -> Result<u32, CompressError> {
    u32::try_from(v).map_err(|_| CompressError::Invalid(format!("UBO2014 .btf: {what} = {v} does not fit 32 bits")))
}

fn put_values(out: &mut Vec<u8>, vals: &[f32], p: Precision, what: &str) -> Result<(), CompressError> {
    match p {
        Precision::F32 => vals.iter().for_each(|&v| put_f32(out, v)),
        Precision::F16 => {
            for (i, &v) in vals.iter().enumerate() {
                let h = f16::from_f32(v);
                if !h.is_finite() {
                    return Err(CompressError::Invalid(format!(
                        "UBO2014 .btf: {what} value {i} = {v} does not fit a half float; use f32 precision"
                    )));
                }
                out.extend_from_slice(&h.to_le_bytes());
            }
        }
    }
    Ok(())
}

/// Serialize `d` as a UBO2014 DFMF file. `xml` goes into the header's XML field
/// (provenance; the reader ignores it).
pub fn to_bytes(d: &Dfmf, p: Precision, xml: &str) -> Result<Vec<u8>, CompressError> {
    d.validate()?;
    let Some(model_code) = d.color_model.code() else {
        return Err(CompressError::Invalid(format!(
            "colour model {} is gonio's own and the UBO2014 reader cannot decode it: \
             write it as .gbtf (--format gbtf), or use rgb or log-yuv for .btf",
            d.color_model.name()
        )));
    };
    let m = match d.color_model {
        ColorModel::LogYuv => rgb_to_yuv(),
        _ => [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    };
    let (nl, nv, t, w) = (d.n_lights(), d.n_views(), d.texels(), d.width);
    if nv > nl {
        return Err(CompressError::Invalid(format!(
            "UBO2014 .btf needs at most as many views as lights (the reader expects lights² rows); \
             this grid has {nv} views and {nl} lights"
        )));
    }
    let rows = nl * nl;
    let mut out = Vec::new();
    out.extend_from_slice(SIGNATURE);
    let names = d.color_model.channel_names();
    let size = COMMON_HEADER_BYTES + 4 + 4 + xml.len() + 4 + names.iter().map(|n| 4 + n.len()).sum::<usize>();
    put_u32(&mut out, u32_of(size, "header size")?);
    put_u32(&mut out, HEADER_VERSION);
    put_fixed(&mut out, "gonio simulated gonioreflectometer", 80);
    put_fixed(&mut out, "gonio simulated sensor", 80);
    put_fixed(&mut out, "gonio simulated point light", 80);
    put_f32(&mut out, 0.0); // pixels per mm: unknown here
    for _ in 0..3 {
        put_f32(&mut out, 1.0); // RGB white balance: identity
    }
    put_u32(&mut out, 0); // cosine flag: values are not multiplied by cos θ_i
    put_u32(&mut out, u32_of(xml.len(), "XML length")?);
    out.extend_from_slice(xml.as_bytes());
    put_u32(&mut out, 3);
    for n in names {
        put_u32(&mut out, n.len() as u32);
        out.extend_from_slice(n.as_bytes());
    }
    let rad = |a: [f64; 2]| [a[0].to_radians() as f32, a[1].to_radians() as f32];
    put_u32(&mut out, nv as u32);
    for &v in &d.views_deg {
        let [th, ph] = rad(v);
        put_f32(&mut out, th);
        put_f32(&mut out, ph);
        put_u32(&mut out, nl as u32);
        for &l in &d.lights_deg {
            let [th, ph] = rad(l);
            put_f32(&mut out, th);
            put_f32(&mut out, ph);
        }
    }
    put_u32(&mut out, u32_of(w, "width")?);
    put_u32(&mut out, u32_of(d.height, "height")?);
    put_u32(&mut out, 0); // rotations
    put_u32(&mut out, d.channels.iter().map(|c| c.c).max().unwrap_or(0) as u32);
    put_u32(&mut out, model_code);
    for _ in 0..3 {
        put_f32(&mut out, 0.0);
    }
    for r in m {
        for v in r {
            put_f32(&mut out, v as f32);
        }
    }
    for (i, ch) in d.channels.iter().enumerate() {
        let c = ch.c;
        out.push(p.bytes() as u8);
        put_u32(&mut out, u32_of(c, "components")?);
        put_u32(&mut out, u32_of(rows, "rows")?);
        put_u32(&mut out, u32_of(t, "columns")?);
        // The reader computes plane sizes in 32 bits.
        u32_of(rows.max(t) * c * p.bytes(), "factor plane bytes")?;
        put_values(&mut out, &ch.sigma, p, &format!("channel {i} singular"))?;
        put_values(&mut out, &ch.u, p, &format!("channel {i} U"))?;
        put_values(&mut out, &vec![0.0; (rows - nv * nl) * c], p, "padding")?;
        // Bottom image row first.
        for y in (0..d.height).rev() {
            put_values(
                &mut out,
                &ch.sxv[y * w * c..(y + 1) * w * c],
                p,
                &format!("channel {i} S·V"),
            )?;
        }
    }
    Ok(out)
}

/// Write `d` to `path` (atomically); returns the file size.
pub fn write(path: &Path, d: &Dfmf, p: Precision, xml: &str) -> Result<u64, CompressError> {
    let bytes = to_bytes(d, p, xml)?;
    gonio_dataset::store::atomic::write_atomic(path, &bytes, None)?;
    Ok(bytes.len() as u64)
}

struct Reader<'a> {
    b: &'a [u8],
    pos: usize,
    path: &'a Path,
}

impl<'a> Reader<'a> {
    fn corrupt(&self, reason: String) -> CompressError {
        CompressError::Corrupt {
            path: self.path.to_path_buf(),
            reason,
        }
    }
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], CompressError> {
        if self.b.len() - self.pos < n {
            return Err(self.corrupt(format!(
                "truncated: {what} needs {n} bytes at offset {}, the file has {} left",
                self.pos,
                self.b.len() - self.pos
            )));
        }
        let s = &self.b[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn u32(&mut self, what: &str) -> Result<u32, CompressError> {
        Ok(u32::from_le_bytes(self.take(4, what)?.try_into().expect("4 bytes")))
    }
    fn f32(&mut self, what: &str) -> Result<f32, CompressError> {
        Ok(f32::from_le_bytes(self.take(4, what)?.try_into().expect("4 bytes")))
    }
    fn values(&mut self, n: usize, size: u8, what: &str) -> Result<Vec<f32>, CompressError> {
        let bytes = n
            .checked_mul(size as usize)
            .ok_or_else(|| self.corrupt(format!("{what}: size overflows")))?;
        let raw = self.take(bytes, what)?;
        let v: Vec<f32> = match size {
            2 => raw
                .chunks_exact(2)
                .map(|c| f16::from_le_bytes([c[0], c[1]]).to_f32())
                .collect(),
            4 => raw
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                .collect(),
            8 => raw
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")) as f32)
                .collect(),
            s => return Err(self.corrupt(format!("{what}: unsupported scalar size {s}"))),
        };
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(self.corrupt(format!("{what}: value {i} is {}", v[i])));
        }
        Ok(v)
    }
}

fn deg(th: f32, ph: f32) -> [f64; 2] {
    // Rounded to 1e-4° so that angles written from degrees read back as the same numbers.
    let r = |x: f64| (x * 1e4).round() / 1e4;
    [r(f64::from(th).to_degrees()), r(f64::from(ph).to_degrees())]
}

/// Parse a DFMF `.btf` (colour models 0 and 11). `path` names the file in errors.
pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Dfmf, CompressError> {
    let mut r = Reader { b: bytes, pos: 0, path };
    let sig = r.take(9, "signature")?;
    if sig != &SIGNATURE[..9] {
        return Err(r.corrupt("not a DFMF .btf file (signature is not !DFMF08FC)".into()));
    }
    let rotations = r.b.get(r.pos) == Some(&b'R');
    if rotations {
        r.pos += 1;
    }
    let start = r.pos;
    let size = r.u32("header size")? as usize;
    let version = r.u32("header version")?;
    r.take(COMMON_HEADER_BYTES - 8, "common header")?;
    if version > 1 {
        let cos = r.u32("cosine flag")?;
        if cos != 0 {
            return Err(r.corrupt("cosine-weighted data (CosineFlag) is not supported".into()));
        }
    }
    if version > 2 {
        let n = r.u32("XML length")? as usize;
        r.take(n, "XML")?;
    }
    if version > 3 {
        let n = r.u32("channel count")?;
        if n != 3 {
            return Err(r.corrupt(format!("{n} channels, only 3 are supported")));
        }
        for i in 0..n {
            let k = r.u32("channel name length")? as usize;
            r.take(k, &format!("channel {i} name"))?;
        }
    }
    if r.pos - start != size {
        return Err(r.corrupt(format!("common header is {} bytes, it says {size}", r.pos - start)));
    }
    let nv = r.u32("view count")? as usize;
    let (mut views, mut lights) = (Vec::new(), Vec::new());
    for v in 0..nv {
        let (th, ph) = (r.f32("view θ")?, r.f32("view φ")?);
        views.push(deg(th, ph));
        let nl = r.u32("light count")? as usize;
        if v > 0 && nl != lights.len() {
            return Err(r.corrupt(format!("view {v} lists {nl} lights, view 0 lists {}", lights.len())));
        }
        for _ in 0..nl {
            let (th, ph) = (r.f32("light θ")?, r.f32("light φ")?);
            if v == 0 {
                lights.push(deg(th, ph));
            }
        }
    }
    let nl = lights.len();
    if nv == 0 || nl == 0 || nv > nl {
        return Err(r.corrupt(format!("{nv} views and {nl} lights (needs 1 ≤ views ≤ lights)")));
    }
    let width = r.u32("width")? as usize;
    let height = r.u32("height")? as usize;
    if rotations {
        let n = r.u32("rotation count")? as usize;
        r.take(n.saturating_mul(36), "rotations")?;
    }
    r.u32("components")?;
    let code = r.u32("colour model")?;
    let color_model = ColorModel::from_code(code)
        .ok_or_else(|| r.corrupt(format!("colour model {code} is not supported (0, 11)")))?;
    r.take(12 + 36, "colour mean and transform")?;
    let t = width * height;
    let mut channels = Vec::with_capacity(3);
    for i in 0..3 {
        let size = r.take(1, "scalar size")?[0];
        let c = r.u32("components")? as usize;
        let rows = r.u32("rows")? as usize;
        let cols = r.u32("columns")? as usize;
        if rows != nl * nl || cols != t || c == 0 {
            return Err(r.corrupt(format!(
                "channel {i}: {rows} × {cols} with {c} components, expected {} × {t} (lights² × texels)",
                nl * nl
            )));
        }
        let sigma = r.values(c, size, &format!("channel {i} singular values"))?;
        let mut u = r.values(rows * c, size, &format!("channel {i} U"))?;
        u.truncate(nv * nl * c);
        let flipped = r.values(cols * c, size, &format!("channel {i} S·V"))?;
        let mut sxv = Vec::with_capacity(flipped.len());
        for y in (0..height).rev() {
            sxv.extend_from_slice(&flipped[y * width * c..(y + 1) * width * c]);
        }
        channels.push(ChannelFactors { c, sigma, u, sxv });
    }
    if r.pos != bytes.len() {
        return Err(r.corrupt(format!("{} trailing bytes after the last channel", bytes.len() - r.pos)));
    }
    Ok(Dfmf {
        color_model,
        width,
        height,
        lights_deg: lights,
        views_deg: views,
        channels,
    })
}

/// Read a DFMF `.btf` file.
pub fn read(path: &Path) -> Result<Dfmf, CompressError> {
    let bytes = std::fs::read(path).map_err(|source| CompressError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    from_bytes(&bytes, path)
}

/// Whether `bytes` start like a UBO2014 DFMF file.
pub fn is_dfmf(bytes: &[u8]) -> bool {
    bytes.starts_with(&SIGNATURE[..9])
}
