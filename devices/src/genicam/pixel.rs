//! GenICam pixel formats and their conversion to gonio's [`Frame`](crate::Frame) layout
//! (interleaved RGB, `u16` digital numbers, `bit_depth` bits), bilinear demosaicing of
//! Bayer mosaics included.
//!
//! This module needs no camera and no libaravis: it is compiled (and unit-tested on
//! synthetic mosaics) in every build, so the conversions are checked even where the
//! `genicam` feature cannot be built. Values are not rescaled: machine-vision sensors
//! deliver linear DN, and an 8-bit format gives a frame of `bit_depth` 8 (0 ..= 255).

use std::fmt;

/// Which colour sits at the top-left 2 × 2 block of a Bayer mosaic, read row by row
/// (`Rggb`: red at (0, 0), green at (1, 0) and (0, 1), blue at (1, 1)).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Cfa {
    Rggb,
    Bggr,
    Grbg,
    Gbrg,
}

impl Cfa {
    /// The colour channel (0 red, 1 green, 2 blue) of the photosite at (x, y).
    pub fn channel(self, x: usize, y: usize) -> usize {
        let (odd_x, odd_y) = (x % 2 == 1, y % 2 == 1);
        // The 2 × 2 tile as [row 0: (even x, odd x), row 1: (even x, odd x)].
        let tile = match self {
            Cfa::Rggb => [[0, 1], [1, 2]],
            Cfa::Bggr => [[2, 1], [1, 0]],
            Cfa::Grbg => [[1, 0], [2, 1]],
            Cfa::Gbrg => [[1, 2], [0, 1]],
        };
        tile[odd_y as usize][odd_x as usize]
    }

    /// PFNC name fragment (`BayerRG8` …).
    fn pfnc(self) -> &'static str {
        match self {
            Cfa::Rggb => "RG",
            Cfa::Bggr => "BG",
            Cfa::Grbg => "GR",
            Cfa::Gbrg => "GB",
        }
    }
}

/// The pixel formats gonio accepts from a GenICam camera. Anything else (packed 10/12-bit,
/// YUV, …) is refused by name in `configure`, never decoded by guess.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PixelFormat {
    Mono8,
    Mono16,
    Rgb8,
    /// A Bayer mosaic of 8 or 16 bits per photosite, demosaiced bilinearly.
    Bayer(Cfa, u32),
}

impl PixelFormat {
    /// Every accepted format, in the order `configure` prefers them when the rig file names
    /// none: colour before grey, deeper before shallower, demosaiced mosaics last.
    pub const PREFERENCE: [PixelFormat; 11] = [
        PixelFormat::Rgb8,
        PixelFormat::Bayer(Cfa::Rggb, 16),
        PixelFormat::Bayer(Cfa::Bggr, 16),
        PixelFormat::Bayer(Cfa::Grbg, 16),
        PixelFormat::Bayer(Cfa::Gbrg, 16),
        PixelFormat::Bayer(Cfa::Rggb, 8),
        PixelFormat::Bayer(Cfa::Bggr, 8),
        PixelFormat::Bayer(Cfa::Grbg, 8),
        PixelFormat::Bayer(Cfa::Gbrg, 8),
        PixelFormat::Mono16,
        PixelFormat::Mono8,
    ];

    /// The GenICam (PFNC) name, as the `PixelFormat` feature spells its entries.
    pub fn name(self) -> String {
        match self {
            PixelFormat::Mono8 => "Mono8".into(),
            PixelFormat::Mono16 => "Mono16".into(),
            PixelFormat::Rgb8 => "RGB8".into(),
            PixelFormat::Bayer(cfa, bits) => format!("Bayer{}{bits}", cfa.pfnc()),
        }
    }

    /// Parse a PFNC name (`Mono8`, `Mono16`, `RGB8` or `RGB8Packed`, `BayerRG8` …
    /// `BayerGB16`), case-insensitively. None: not a format gonio decodes.
    pub fn parse(name: &str) -> Option<PixelFormat> {
        let lower = name.to_ascii_lowercase();
        match lower.as_str() {
            "mono8" => return Some(PixelFormat::Mono8),
            "mono16" => return Some(PixelFormat::Mono16),
            "rgb8" | "rgb8packed" => return Some(PixelFormat::Rgb8),
            _ => {}
        }
        let rest = lower.strip_prefix("bayer")?;
        let (cfa, bits) = rest.split_at(rest.len().min(2));
        let cfa = match cfa {
            "rg" => Cfa::Rggb,
            "bg" => Cfa::Bggr,
            "gr" => Cfa::Grbg,
            "gb" => Cfa::Gbrg,
            _ => return None,
        };
        match bits {
            "8" => Some(PixelFormat::Bayer(cfa, 8)),
            "16" => Some(PixelFormat::Bayer(cfa, 16)),
            _ => None,
        }
    }

    /// The PFNC 32-bit code the camera reports in each buffer (GigE Vision / USB3 Vision
    /// carry it in the stream's leader), so a buffer's format can be checked against the
    /// configured one without the library.
    pub fn pfnc_code(self) -> u32 {
        match self {
            PixelFormat::Mono8 => 0x0108_0001,
            PixelFormat::Mono16 => 0x0110_0007,
            PixelFormat::Rgb8 => 0x0218_0014,
            PixelFormat::Bayer(Cfa::Grbg, 8) => 0x0108_0008,
            PixelFormat::Bayer(Cfa::Rggb, 8) => 0x0108_0009,
            PixelFormat::Bayer(Cfa::Gbrg, 8) => 0x0108_000A,
            PixelFormat::Bayer(Cfa::Bggr, 8) => 0x0108_000B,
            PixelFormat::Bayer(Cfa::Grbg, _) => 0x0110_002E,
            PixelFormat::Bayer(Cfa::Rggb, _) => 0x0110_002F,
            PixelFormat::Bayer(Cfa::Gbrg, _) => 0x0110_0030,
            PixelFormat::Bayer(Cfa::Bggr, _) => 0x0110_0031,
        }
    }

    /// The format with this PFNC code, if gonio decodes it.
    pub fn from_pfnc_code(code: u32) -> Option<PixelFormat> {
        Self::PREFERENCE.into_iter().find(|f| f.pfnc_code() == code)
    }

    /// Bits per delivered value (the frame's `bit_depth`).
    pub fn bit_depth(self) -> u32 {
        match self {
            PixelFormat::Mono8 | PixelFormat::Rgb8 => 8,
            PixelFormat::Mono16 => 16,
            PixelFormat::Bayer(_, bits) => bits,
        }
    }

    /// Bytes per pixel in the camera's buffer.
    pub fn bytes_per_pixel(self) -> usize {
        match self {
            PixelFormat::Mono8 => 1,
            PixelFormat::Mono16 => 2,
            PixelFormat::Rgb8 => 3,
            PixelFormat::Bayer(_, bits) => bits as usize / 8,
        }
    }
}

impl fmt::Display for PixelFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.name())
    }
}

/// Why a buffer could not be converted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConvertError {
    #[error("{format} buffer of {got} bytes for {width} × {height} pixels (expected at least {expected})")]
    Size {
        format: PixelFormat,
        width: usize,
        height: usize,
        got: usize,
        expected: usize,
    },
}

/// Convert one camera buffer (`width × height` pixels, rows packed without padding,
/// 16-bit values little-endian as GigE Vision and USB3 Vision deliver them) to
/// interleaved RGB `u16` DN. Grey formats are copied to all three channels; Bayer
/// mosaics are demosaiced with [`demosaic_bilinear`].
pub fn to_rgb16(format: PixelFormat, width: usize, height: usize, data: &[u8]) -> Result<Vec<u16>, ConvertError> {
    let n = width * height;
    let expected = n * format.bytes_per_pixel();
    if data.len() < expected {
        return Err(ConvertError::Size {
            format,
            width,
            height,
            got: data.len(),
            expected,
        });
    }
    let samples = |wide: bool| -> Vec<u16> {
        if wide {
            data[..2 * n]
                .chunks_exact(2)
                .map(|b| u16::from_le_bytes([b[0], b[1]]))
                .collect()
        } else {
            data[..n].iter().map(|&v| v as u16).collect()
        }
    };
    Ok(match format {
        PixelFormat::Rgb8 => data[..3 * n].iter().map(|&v| v as u16).collect(),
        PixelFormat::Mono8 | PixelFormat::Mono16 => samples(format == PixelFormat::Mono16)
            .into_iter()
            .flat_map(|v| [v, v, v])
            .collect(),
        PixelFormat::Bayer(cfa, bits) => demosaic_bilinear(cfa, width, height, &samples(bits == 16)),
    })
}

/// Bilinear demosaicing: each missing colour of a photosite is the mean of the photosites
/// of that colour in its 3 × 3 neighbourhood (inside the image), rounded to the nearest
/// DN; the measured colour is kept as it is. In the interior this is the classic
/// bilinear interpolation (green from the 4 edge neighbours, red/blue from the 2 or 4
/// nearest of their colour), which reproduces any image that is linear in x and y exactly;
/// at the border only the neighbours that exist are averaged, so no value is invented.
/// `mosaic` holds `width × height` samples; the result is interleaved RGB.
pub fn demosaic_bilinear(cfa: Cfa, width: usize, height: usize, mosaic: &[u16]) -> Vec<u16> {
    let mut out = vec![0u16; width * height * 3];
    for y in 0..height {
        for x in 0..width {
            let own = cfa.channel(x, y);
            let mut sum = [0u32; 3];
            let mut count = [0u32; 3];
            for yy in y.saturating_sub(1)..(y + 2).min(height) {
                for xx in x.saturating_sub(1)..(x + 2).min(width) {
                    let c = cfa.channel(xx, yy);
                    sum[c] += mosaic[yy * width + xx] as u32;
                    count[c] += 1;
                }
            }
            let o = 3 * (y * width + x);
            for c in 0..3 {
                // A 1-pixel-wide image has no neighbour of some colour (count 0): the best
                // estimate left is the photosite's own value.
                let mean = (sum[c] + count[c] / 2).checked_div(count[c]).map(|m| m as u16);
                out[o + c] = match mean {
                    Some(m) if c != own => m,
                    _ => mosaic[y * width + x],
                };
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const ALL_CFA: [Cfa; 4] = [Cfa::Rggb, Cfa::Bggr, Cfa::Grbg, Cfa::Gbrg];

    /// Sample an RGB image through a colour filter array.
    fn mosaic(cfa: Cfa, w: usize, h: usize, rgb: impl Fn(usize, usize) -> [u16; 3]) -> Vec<u16> {
        (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| rgb(x, y)[cfa.channel(x, y)])
            .collect()
    }

    #[test]
    fn cfa_tiles_match_their_names() {
        // Top-left 2 × 2 block, row by row, as the PFNC names say.
        let tile = |c: Cfa| [c.channel(0, 0), c.channel(1, 0), c.channel(0, 1), c.channel(1, 1)];
        assert_eq!(tile(Cfa::Rggb), [0, 1, 1, 2]);
        assert_eq!(tile(Cfa::Bggr), [2, 1, 1, 0]);
        assert_eq!(tile(Cfa::Grbg), [1, 0, 2, 1]);
        assert_eq!(tile(Cfa::Gbrg), [1, 2, 0, 1]);
        // The tile repeats.
        for c in ALL_CFA {
            assert_eq!(c.channel(4, 6), c.channel(0, 0));
            assert_eq!(c.channel(5, 7), c.channel(1, 1));
        }
    }

    #[test]
    fn names_and_codes_round_trip() {
        for f in PixelFormat::PREFERENCE {
            assert_eq!(PixelFormat::parse(&f.name()), Some(f), "{f}");
            assert_eq!(PixelFormat::from_pfnc_code(f.pfnc_code()), Some(f), "{f}");
        }
        assert_eq!(PixelFormat::parse("bayerrg8"), Some(PixelFormat::Bayer(Cfa::Rggb, 8)));
        assert_eq!(PixelFormat::parse("RGB8Packed"), Some(PixelFormat::Rgb8));
        for bad in ["BayerRG10", "BayerXY8", "YUV422_8", "Mono12Packed", "", "Bayer"] {
            assert_eq!(PixelFormat::parse(bad), None, "{bad}");
        }
        assert_eq!(PixelFormat::from_pfnc_code(0x010C_0006), None); // Mono12Packed
    }

    #[test]
    fn a_uniform_colour_demosaics_to_itself_for_every_pattern_and_depth() {
        for cfa in ALL_CFA {
            for value in [[200u16, 100, 50], [60_000, 30_000, 1]] {
                let m = mosaic(cfa, 7, 5, |_, _| value);
                let out = demosaic_bilinear(cfa, 7, 5, &m);
                for px in out.chunks_exact(3) {
                    assert_eq!(px, value, "{cfa:?}");
                }
            }
        }
    }

    #[test]
    fn a_linear_ramp_is_reproduced_exactly_inside_the_border() {
        // Each channel a different plane in x and y, even values so that every mean of 2
        // or 4 neighbours is whole.
        let rgb = |x: usize, y: usize| {
            [
                (10 + 4 * x + 2 * y) as u16,
                (500 + 2 * x + 6 * y) as u16,
                (900 - 2 * x - 4 * y) as u16,
            ]
        };
        let (w, h) = (10, 8);
        for cfa in ALL_CFA {
            let out = demosaic_bilinear(cfa, w, h, &mosaic(cfa, w, h, rgb));
            for y in 1..h - 1 {
                for x in 1..w - 1 {
                    let o = 3 * (y * w + x);
                    assert_eq!(&out[o..o + 3], &rgb(x, y), "{cfa:?} at ({x}, {y})");
                }
            }
            // The measured colour is never changed, border included.
            for y in 0..h {
                for x in 0..w {
                    let c = cfa.channel(x, y);
                    assert_eq!(out[3 * (y * w + x) + c], rgb(x, y)[c]);
                }
            }
        }
    }

    #[test]
    fn a_red_site_takes_green_from_its_cross_and_blue_from_its_diagonals() {
        // RGGB, the red site at (2, 2) of a 5 × 5 mosaic with distinct values.
        let m: Vec<u16> = (0..25).map(|i| 10 * i as u16).collect();
        let out = demosaic_bilinear(Cfa::Rggb, 5, 5, &m);
        let v = |x: usize, y: usize| m[y * 5 + x] as u32;
        let o = 3 * (2 * 5 + 2);
        assert_eq!(out[o] as u32, v(2, 2));
        assert_eq!(out[o + 1] as u32, (v(1, 2) + v(3, 2) + v(2, 1) + v(2, 3)) / 4);
        assert_eq!(out[o + 2] as u32, (v(1, 1) + v(3, 1) + v(1, 3) + v(3, 3)) / 4);
        // A green site on a red row: red from left/right, blue from above/below.
        let o = 3 * (2 * 5 + 1);
        assert_eq!(out[o] as u32, (v(0, 2) + v(2, 2)) / 2);
        assert_eq!(out[o + 2] as u32, (v(1, 1) + v(1, 3)) / 2);
    }

    #[test]
    fn buffers_convert_by_format_and_short_buffers_are_refused() {
        assert_eq!(
            to_rgb16(PixelFormat::Mono8, 2, 1, &[7, 9]).unwrap(),
            vec![7, 7, 7, 9, 9, 9]
        );
        // 16-bit little-endian: 0x1234, 0xFFFF.
        assert_eq!(
            to_rgb16(PixelFormat::Mono16, 2, 1, &[0x34, 0x12, 0xFF, 0xFF]).unwrap(),
            vec![0x1234, 0x1234, 0x1234, 0xFFFF, 0xFFFF, 0xFFFF]
        );
        assert_eq!(to_rgb16(PixelFormat::Rgb8, 1, 1, &[1, 2, 3]).unwrap(), vec![1, 2, 3]);
        let b16 = PixelFormat::Bayer(Cfa::Gbrg, 16);
        let m = mosaic(Cfa::Gbrg, 4, 4, |_, _| [40_000, 20_000, 10_000]);
        let bytes: Vec<u8> = m.iter().flat_map(|v| v.to_le_bytes()).collect();
        assert!(to_rgb16(b16, 4, 4, &bytes)
            .unwrap()
            .chunks_exact(3)
            .all(|p| p == [40_000, 20_000, 10_000]));
        let e = to_rgb16(PixelFormat::Rgb8, 4, 4, &[0; 47]).unwrap_err();
        assert!(e.to_string().contains("expected at least 48"), "{e}");
        assert_eq!((PixelFormat::Mono8.bit_depth(), b16.bit_depth()), (8, 16));
    }
}
