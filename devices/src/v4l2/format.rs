//! Pixel formats a V4L2 camera delivers and their conversion to linear RGB.
//!
//! A BTF is a radiometric measurement: the store and the compression expect values
//! proportional to radiance. Consumer video formats are gamma-encoded (sRGB or BT.709
//! transfer function) and YUV formats are in addition matrix-encoded (BT.601 or BT.709) and
//! usually limited range (16..235). Everything is undone here, once, so the rest of gonio
//! sees linear RGB in `0 ..= 65535` (16 bits: an 8-bit code linearised needs more than 8
//! bits in the darks, where gamma encoding spent most of its codes).
//!
//! Layouts come from the driver (`bytesperline`, `sizeimage`), never from `width * bpp`:
//! real drivers pad rows.

use thiserror::Error;

/// The pixel formats gonio can convert. Order of preference for radiometry: uncompressed
/// RGB first (no chroma subsampling, no compression), then YUYV, then greyscale, then MJPEG
/// (lossy: only when nothing else is offered).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PixelFormat {
    /// `RGB3`: 8-bit R, G, B.
    Rgb24,
    /// `BGR3`: 8-bit B, G, R.
    Bgr24,
    /// `YUYV`: packed 4:2:2, Y0 Cb Y1 Cr per two pixels.
    Yuyv,
    /// `GREY`: 8-bit luma only.
    Grey,
    /// `MJPG`: one JPEG image per frame (often without Huffman tables).
    Mjpeg,
}

impl PixelFormat {
    /// All supported formats in order of preference.
    pub const PREFERENCE: [PixelFormat; 5] = [
        PixelFormat::Rgb24,
        PixelFormat::Bgr24,
        PixelFormat::Yuyv,
        PixelFormat::Grey,
        PixelFormat::Mjpeg,
    ];

    /// The V4L2 four-character code.
    pub fn fourcc(self) -> [u8; 4] {
        match self {
            PixelFormat::Rgb24 => *b"RGB3",
            PixelFormat::Bgr24 => *b"BGR3",
            PixelFormat::Yuyv => *b"YUYV",
            PixelFormat::Grey => *b"GREY",
            PixelFormat::Mjpeg => *b"MJPG",
        }
    }

    pub fn from_fourcc(code: [u8; 4]) -> Option<PixelFormat> {
        PixelFormat::PREFERENCE.into_iter().find(|f| f.fourcc() == code)
    }

    /// Parse a user-facing name (`rgb24`, `yuyv`, `grey`/`gray`, `mjpeg`/`mjpg`, `bgr24`) or
    /// a four-character code.
    pub fn parse(s: &str) -> Option<PixelFormat> {
        match s.to_ascii_lowercase().as_str() {
            "rgb24" | "rgb3" => Some(PixelFormat::Rgb24),
            "bgr24" | "bgr3" => Some(PixelFormat::Bgr24),
            "yuyv" | "yuy2" => Some(PixelFormat::Yuyv),
            "grey" | "gray" | "y8" => Some(PixelFormat::Grey),
            "mjpeg" | "mjpg" => Some(PixelFormat::Mjpeg),
            _ => None,
        }
    }

    /// Bytes per pixel of a packed format (None for compressed formats).
    pub fn bytes_per_pixel(self) -> Option<usize> {
        match self {
            PixelFormat::Rgb24 | PixelFormat::Bgr24 => Some(3),
            PixelFormat::Yuyv => Some(2),
            PixelFormat::Grey => Some(1),
            PixelFormat::Mjpeg => None,
        }
    }

    /// Whether the format carries Y'CbCr (or luma) rather than R'G'B'.
    pub fn is_yuv(self) -> bool {
        matches!(self, PixelFormat::Yuyv | PixelFormat::Grey)
    }

    pub fn name(self) -> &'static str {
        match self {
            PixelFormat::Rgb24 => "RGB24",
            PixelFormat::Bgr24 => "BGR24",
            PixelFormat::Yuyv => "YUYV",
            PixelFormat::Grey => "GREY",
            PixelFormat::Mjpeg => "MJPEG",
        }
    }
}

impl std::fmt::Display for PixelFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Opto-electronic transfer function the codes were encoded with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Transfer {
    /// IEC 61966-2-1 (sRGB, also JPEG).
    Srgb,
    /// ITU-R BT.709 / BT.601 (SMPTE 170M) camera curve.
    Rec709,
    /// Already linear.
    Linear,
}

/// Y'CbCr → R'G'B' matrix.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum YcbcrMatrix {
    Bt601,
    Bt709,
}

/// Code range of Y'CbCr (and of luma-only) data.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Range {
    /// Y' in 16..=235, Cb/Cr in 16..=240 (8 bit).
    Limited,
    /// 0..=255.
    Full,
}

// V4L2 colorimetry constants (videodev2.h), so this module needs no bindings.
const V4L2_COLORSPACE_SMPTE170M: u32 = 1;
const V4L2_COLORSPACE_REC709: u32 = 3;
const V4L2_COLORSPACE_470_SYSTEM_M: u32 = 5;
const V4L2_COLORSPACE_470_SYSTEM_BG: u32 = 6;
const V4L2_COLORSPACE_JPEG: u32 = 7;
const V4L2_XFER_FUNC_DEFAULT: u32 = 0;
const V4L2_XFER_FUNC_709: u32 = 1;
const V4L2_XFER_FUNC_SRGB: u32 = 2;
const V4L2_XFER_FUNC_NONE: u32 = 5;
const V4L2_YCBCR_ENC_DEFAULT: u32 = 0;
const V4L2_YCBCR_ENC_709: u32 = 2;
const V4L2_QUANTIZATION_DEFAULT: u32 = 0;
const V4L2_QUANTIZATION_FULL_RANGE: u32 = 1;

/// What the driver reported about the colorimetry of the negotiated format, resolved to
/// concrete choices following the kernel's `V4L2_MAP_*_DEFAULT` rules.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Colorimetry {
    pub transfer: Transfer,
    pub matrix: YcbcrMatrix,
    pub range: Range,
}

impl Colorimetry {
    /// Resolve the raw `v4l2_pix_format` fields (colorspace, xfer_func, ycbcr_enc,
    /// quantization). Unknown values fall back to sRGB / BT.601 with a warning: better a
    /// slightly wrong curve than refusing a camera.
    pub fn from_v4l2(format: PixelFormat, colorspace: u32, xfer: u32, ycbcr_enc: u32, quantization: u32) -> Self {
        let transfer = match xfer {
            V4L2_XFER_FUNC_709 => Transfer::Rec709,
            V4L2_XFER_FUNC_SRGB => Transfer::Srgb,
            V4L2_XFER_FUNC_NONE => Transfer::Linear,
            V4L2_XFER_FUNC_DEFAULT => match colorspace {
                V4L2_COLORSPACE_SMPTE170M
                | V4L2_COLORSPACE_REC709
                | V4L2_COLORSPACE_470_SYSTEM_M
                | V4L2_COLORSPACE_470_SYSTEM_BG => Transfer::Rec709,
                _ => Transfer::Srgb,
            },
            other => {
                tracing::warn!(xfer_func = other, "unsupported V4L2 transfer function; assuming sRGB");
                Transfer::Srgb
            }
        };
        let matrix = match ycbcr_enc {
            V4L2_YCBCR_ENC_709 => YcbcrMatrix::Bt709,
            V4L2_YCBCR_ENC_DEFAULT if colorspace == V4L2_COLORSPACE_REC709 => YcbcrMatrix::Bt709,
            _ => YcbcrMatrix::Bt601,
        };
        let range = match quantization {
            V4L2_QUANTIZATION_FULL_RANGE => Range::Full,
            V4L2_QUANTIZATION_DEFAULT if !format.is_yuv() || colorspace == V4L2_COLORSPACE_JPEG => Range::Full,
            V4L2_QUANTIZATION_DEFAULT => Range::Limited,
            _ => Range::Limited,
        };
        // A JPEG stream is always full range BT.601 with the sRGB curve (JFIF), whatever the
        // driver says about the container.
        if format == PixelFormat::Mjpeg {
            return Colorimetry {
                transfer: Transfer::Srgb,
                matrix: YcbcrMatrix::Bt601,
                range: Range::Full,
            };
        }
        Colorimetry {
            transfer,
            matrix,
            range,
        }
    }
}

/// The negotiated layout of one frame buffer, as the driver returned it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Layout {
    pub format: PixelFormat,
    pub width: usize,
    pub height: usize,
    /// Bytes from one row to the next (`bytesperline`), ≥ `width * bytes_per_pixel`.
    pub stride: usize,
    /// Size of one image in bytes (`sizeimage`).
    pub size: usize,
    pub colorimetry: Colorimetry,
}

#[derive(Debug, Error, Clone, PartialEq)]
pub enum ConvertError {
    #[error("{format} frame has {got} bytes, layout needs {need} ({width}x{height}, stride {stride})")]
    ShortBuffer {
        format: PixelFormat,
        got: usize,
        need: usize,
        width: usize,
        height: usize,
        stride: usize,
    },
    #[error("stride {stride} is smaller than a {format} row of {width} pixels")]
    BadStride {
        format: PixelFormat,
        stride: usize,
        width: usize,
    },
    #[error("MJPEG frame does not decode: {0}")]
    Jpeg(String),
    #[error("MJPEG frame is {got_w}x{got_h}, negotiated {width}x{height}")]
    JpegSize {
        got_w: usize,
        got_h: usize,
        width: usize,
        height: usize,
    },
}

/// Lookup table from a 12-bit non-linear code value to a 16-bit linear value. 12 bits of
/// input resolution are finer than any 8-bit source, so the table adds no visible error.
struct Eotf {
    table: Vec<u16>,
}

const LUT_BITS: u32 = 12;
const LUT_MAX: f32 = ((1 << LUT_BITS) - 1) as f32;

impl Eotf {
    fn new(transfer: Transfer) -> Self {
        let table = (0..(1u32 << LUT_BITS))
            .map(|i| {
                let v = i as f64 / LUT_MAX as f64;
                (eotf(transfer, v) * 65535.0).round().clamp(0.0, 65535.0) as u16
            })
            .collect();
        Eotf { table }
    }

    /// Linear 16-bit value of a non-linear value in [0, 1] (clamped).
    #[inline]
    fn apply(&self, v: f32) -> u16 {
        let i = (v.clamp(0.0, 1.0) * LUT_MAX + 0.5) as usize;
        self.table[i]
    }
}

/// Non-linear → linear for one value in [0, 1].
pub fn eotf(transfer: Transfer, v: f64) -> f64 {
    match transfer {
        Transfer::Linear => v,
        Transfer::Srgb => crate::image::srgb_decode(v),
        Transfer::Rec709 => {
            if v < 0.081 {
                v / 4.5
            } else {
                ((v + 0.099) / 1.099).powf(1.0 / 0.45)
            }
        }
    }
}

/// Convert one frame to interleaved linear RGB in `0 ..= 65535` (`width * height * 3`
/// values). `data` is the dequeued buffer limited to `bytesused`.
pub fn to_linear_rgb16(layout: &Layout, data: &[u8]) -> Result<Vec<u16>, ConvertError> {
    let (w, h) = (layout.width, layout.height);
    let eotf = Eotf::new(layout.colorimetry.transfer);
    if layout.format == PixelFormat::Mjpeg {
        return mjpeg_to_linear(layout, data, &eotf);
    }
    let bpp = layout.format.bytes_per_pixel().unwrap_or(1);
    if layout.stride < w * bpp {
        return Err(ConvertError::BadStride {
            format: layout.format,
            stride: layout.stride,
            width: w,
        });
    }
    // The last row needs only its pixels, not its padding.
    let need = if h == 0 { 0 } else { layout.stride * (h - 1) + w * bpp };
    if data.len() < need {
        return Err(ConvertError::ShortBuffer {
            format: layout.format,
            got: data.len(),
            need,
            width: w,
            height: h,
            stride: layout.stride,
        });
    }
    let mut out = vec![0u16; w * h * 3];
    let range = layout.colorimetry.range;
    let matrix = layout.colorimetry.matrix;
    for y in 0..h {
        let row = &data[y * layout.stride..y * layout.stride + w * bpp];
        let dst = &mut out[y * w * 3..(y + 1) * w * 3];
        match layout.format {
            PixelFormat::Rgb24 | PixelFormat::Bgr24 => {
                let swap = layout.format == PixelFormat::Bgr24;
                for (px, d) in row.chunks_exact(3).zip(dst.chunks_exact_mut(3)) {
                    let (r, b) = if swap { (px[2], px[0]) } else { (px[0], px[2]) };
                    d[0] = eotf.apply(r as f32 / 255.0);
                    d[1] = eotf.apply(px[1] as f32 / 255.0);
                    d[2] = eotf.apply(b as f32 / 255.0);
                }
            }
            PixelFormat::Grey => {
                for (&yv, d) in row.iter().zip(dst.chunks_exact_mut(3)) {
                    let l = eotf.apply(luma(yv, range));
                    d.fill(l);
                }
            }
            PixelFormat::Yuyv => {
                for (x, d) in dst.chunks_exact_mut(3).enumerate() {
                    let pair = &row[(x / 2) * 4..(x / 2) * 4 + 4];
                    let yv = if x % 2 == 0 { pair[0] } else { pair[2] };
                    let (r, g, b) = ycbcr_to_rgb(yv, pair[1], pair[3], matrix, range);
                    d[0] = eotf.apply(r);
                    d[1] = eotf.apply(g);
                    d[2] = eotf.apply(b);
                }
            }
            PixelFormat::Mjpeg => unreachable!("handled above"),
        }
    }
    Ok(out)
}

/// Normalised luma of an 8-bit Y' code.
#[inline]
fn luma(y: u8, range: Range) -> f32 {
    match range {
        Range::Full => y as f32 / 255.0,
        Range::Limited => (y as f32 - 16.0) / 219.0,
    }
}

/// Y'CbCr (8 bit) → normalised R'G'B'.
#[inline]
pub fn ycbcr_to_rgb(y: u8, cb: u8, cr: u8, matrix: YcbcrMatrix, range: Range) -> (f32, f32, f32) {
    let yn = luma(y, range);
    let (pb, pr) = match range {
        Range::Full => ((cb as f32 - 128.0) / 255.0, (cr as f32 - 128.0) / 255.0),
        Range::Limited => ((cb as f32 - 128.0) / 224.0, (cr as f32 - 128.0) / 224.0),
    };
    // Kr, Kb of the matrix; R' = Y' + 2(1−Kr)Pr, B' = Y' + 2(1−Kb)Pb, G' from Y'.
    let (kr, kb) = match matrix {
        YcbcrMatrix::Bt601 => (0.299f32, 0.114f32),
        YcbcrMatrix::Bt709 => (0.2126f32, 0.0722f32),
    };
    let kg = 1.0 - kr - kb;
    let r = yn + 2.0 * (1.0 - kr) * pr;
    let b = yn + 2.0 * (1.0 - kb) * pb;
    let g = (yn - kr * r - kb * b) / kg;
    (r, g, b)
}

fn mjpeg_to_linear(layout: &Layout, data: &[u8], eotf: &Eotf) -> Result<Vec<u16>, ConvertError> {
    use zune_jpeg::zune_core::bytestream::ZCursor;
    use zune_jpeg::zune_core::colorspace::ColorSpace;
    use zune_jpeg::zune_core::options::DecoderOptions;
    let options = DecoderOptions::default()
        .jpeg_set_out_colorspace(ColorSpace::RGB)
        .set_max_width(layout.width.max(1) * 2)
        .set_max_height(layout.height.max(1) * 2);
    let mut dec = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(data), options);
    let rgb = dec.decode().map_err(|e| ConvertError::Jpeg(format!("{e:?}")))?;
    let info = dec.info().ok_or_else(|| ConvertError::Jpeg("no image header".into()))?;
    let (gw, gh) = (info.width as usize, info.height as usize);
    if gw != layout.width || gh != layout.height || rgb.len() < gw * gh * 3 {
        return Err(ConvertError::JpegSize {
            got_w: gw,
            got_h: gh,
            width: layout.width,
            height: layout.height,
        });
    }
    Ok(rgb[..gw * gh * 3]
        .iter()
        .map(|&v| eotf.apply(v as f32 / 255.0))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout(format: PixelFormat, width: usize, height: usize, stride: usize) -> Layout {
        Layout {
            format,
            width,
            height,
            stride,
            size: stride * height,
            colorimetry: Colorimetry::from_v4l2(format, 8 /* sRGB */, 0, 0, 0),
        }
    }

    #[test]
    fn srgb_eotf_known_points() {
        assert_eq!(eotf(Transfer::Srgb, 0.0), 0.0);
        assert!((eotf(Transfer::Srgb, 1.0) - 1.0).abs() < 1e-12);
        // sRGB code 128/255 is 21.6 % linear (a classic figure).
        assert!((eotf(Transfer::Srgb, 128.0 / 255.0) - 0.2158605).abs() < 1e-6);
        assert!((eotf(Transfer::Rec709, 0.5) - 0.2596).abs() < 1e-3);
    }

    #[test]
    fn rgb24_respects_stride_and_linearises() {
        // 2x2 image, stride 8 (2 bytes of padding per row, filled with junk).
        let data = [255, 0, 0, 0, 255, 0, 0xAA, 0xAA, 0, 0, 255, 128, 128, 128, 0xAA, 0xAA];
        let out = to_linear_rgb16(&layout(PixelFormat::Rgb24, 2, 2, 8), &data).unwrap();
        assert_eq!(&out[0..6], &[65535, 0, 0, 0, 65535, 0]);
        assert_eq!(&out[6..9], &[0, 0, 65535]);
        let mid = (0.2158605f64 * 65535.0).round() as i32;
        for &v in &out[9..12] {
            assert!((v as i32 - mid).abs() <= 20, "{v} vs {mid}");
        }
    }

    #[test]
    fn bgr24_swaps_channels() {
        let out = to_linear_rgb16(&layout(PixelFormat::Bgr24, 1, 1, 3), &[255, 0, 0]).unwrap();
        assert_eq!(out, vec![0, 0, 65535]);
    }

    #[test]
    fn yuyv_limited_range_bt601_primaries() {
        // Full red in BT.601 limited range: Y=81, Cb=90, Cr=240; white: Y=235, Cb=Cr=128;
        // black: Y=16.
        let data = [81, 90, 81, 240, 235, 128, 16, 128];
        let out = to_linear_rgb16(&layout(PixelFormat::Yuyv, 4, 1, 8), &data).unwrap();
        let close = |v: u16, want: u16| (v as i32 - want as i32).abs() <= 700; // ~1 % of full scale
        assert!(
            close(out[0], 65535) && close(out[1], 0) && close(out[2], 0),
            "{:?}",
            &out[0..3]
        );
        assert!(close(out[3], 65535) && close(out[4], 0) && close(out[5], 0));
        assert_eq!(&out[6..9], &[65535, 65535, 65535]);
        assert_eq!(&out[9..12], &[0, 0, 0]);
    }

    #[test]
    fn grey_limited_range_replicates() {
        let out = to_linear_rgb16(&layout(PixelFormat::Grey, 3, 1, 4), &[16, 235, 255, 0]).unwrap();
        assert_eq!(out, vec![0, 0, 0, 65535, 65535, 65535, 65535, 65535, 65535]);
    }

    #[test]
    fn short_buffer_and_bad_stride_are_errors() {
        let e = to_linear_rgb16(&layout(PixelFormat::Rgb24, 2, 2, 6), &[0; 11]).unwrap_err();
        assert!(matches!(e, ConvertError::ShortBuffer { need: 12, got: 11, .. }), "{e}");
        let e = to_linear_rgb16(&layout(PixelFormat::Yuyv, 4, 1, 6), &[0; 8]).unwrap_err();
        assert!(matches!(e, ConvertError::BadStride { .. }), "{e}");
    }

    #[test]
    fn colorimetry_defaults_follow_v4l2_rules() {
        let c = Colorimetry::from_v4l2(PixelFormat::Yuyv, 8, 0, 0, 0);
        assert_eq!(
            (c.transfer, c.matrix, c.range),
            (Transfer::Srgb, YcbcrMatrix::Bt601, Range::Limited)
        );
        let c = Colorimetry::from_v4l2(PixelFormat::Rgb24, 8, 0, 0, 0);
        assert_eq!(c.range, Range::Full);
        let c = Colorimetry::from_v4l2(PixelFormat::Yuyv, V4L2_COLORSPACE_REC709, 0, 0, 0);
        assert_eq!((c.transfer, c.matrix), (Transfer::Rec709, YcbcrMatrix::Bt709));
        let c = Colorimetry::from_v4l2(PixelFormat::Mjpeg, V4L2_COLORSPACE_REC709, 1, 2, 2);
        assert_eq!((c.transfer, c.range), (Transfer::Srgb, Range::Full));
    }

    #[test]
    fn mjpeg_decodes_and_linearises() {
        // A 16x8 JPEG: left half white, right half black, encoded by `image`.
        let (w, h) = (16u32, 8u32);
        let img = image::RgbImage::from_fn(w, h, |x, _| {
            if x < 8 {
                image::Rgb([255, 255, 255])
            } else {
                image::Rgb([0, 0, 0])
            }
        });
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 95)
            .encode_image(&img)
            .unwrap();
        let l = layout(PixelFormat::Mjpeg, 16, 8, 0);
        let out = to_linear_rgb16(&l, &jpeg).unwrap();
        assert_eq!(out.len(), 16 * 8 * 3);
        // Away from the edge (JPEG ringing), white is ~65535 and black ~0.
        assert!(out[3 * (4 * 16 + 2)] > 64000, "{}", out[3 * (4 * 16 + 2)]);
        assert!(out[3 * (4 * 16 + 13)] < 500, "{}", out[3 * (4 * 16 + 13)]);
        let wrong = layout(PixelFormat::Mjpeg, 32, 8, 0);
        assert!(matches!(
            to_linear_rgb16(&wrong, &jpeg),
            Err(ConvertError::JpegSize { .. })
        ));
        assert!(matches!(to_linear_rgb16(&l, &jpeg[..20]), Err(ConvertError::Jpeg(_))));
    }
}
