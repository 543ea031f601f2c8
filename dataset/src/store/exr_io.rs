//! OpenEXR reading and writing of rectified images.
//!
//! Images are stored as RGB half floats (f16): 11 significant bits (relative step
//! 2⁻¹¹ ≈ 0.05 %) are far finer than the camera's noise and quantisation, and they
//! halve the size of f32. Values above 65504 (f16 max) become +inf; normalised sensor
//! signals never get near that.
//!
//! Compression: [`COMPRESSION`] (ZIP, 16 scan lines per block) was picked by measuring
//! write time and size on 256 × 256 sensor-like images, see `bench_compressions` in the
//! tests (`cargo test -p gonio --release --lib store::tests::bench_compressions --
//! --ignored --nocapture`); the numbers are in the doc comment of [`COMPRESSION`].
//!
//! The exr crate builds a new thread pool for every parallel read or write, which
//! costs more than compressing a 256 × 256 image; the store therefore always
//! reads and writes single-threaded and parallelises across images instead.

use super::atomic::write_atomic;
use super::error::{IoContext, StoreError};
use exr::prelude::{
    f16, read, AnyChannel, AnyChannels, Blocks, Compression, Encoding, FlatSamples, Image, Layer, LayerAttributes,
    LineOrder, ReadChannels, ReadLayers, RgbaChannels, SmallVec, Vec2, WritableImage,
};
use gonio_devices::image::RgbImage;
use std::io::Cursor;
use std::path::Path;

/// Compression of stored EXR images.
///
/// Measured with `bench_compressions` (release build, encoding to memory, no fsync,
/// best of 5 × 20 runs on this project's shared 2-core machine) on two 256 × 256 RGB f16
/// images: smooth shading with 12-bit shot noise at mid exposure, and the same at low
/// exposure (grazing angles), where noise fills more of the mantissa:
///
/// | compression    | mid: write | mid: size | dark: write | dark: size |
/// |----------------|-----------:|----------:|------------:|-----------:|
/// | none           |   0.67 ms  |  397.7 kB |    0.79 ms  |  397.7 kB  |
/// | RLE            |   2.78 ms  |  312.5 kB |    2.68 ms  |  386.9 kB  |
/// | ZIPS (1 line)  |  19.4 ms   |  265.9 kB |   22.1 ms   |  306.3 kB  |
/// | ZIP (16 lines) |  15.6 ms   |  240.1 kB |   16.1 ms   |  279.7 kB  |
/// | PIZ            |  17.3 ms   |  214.2 kB |   20.0 ms   |  256.5 kB  |
/// | PXR24          |  15.9 ms   |  249.3 kB |   16.0 ms   |  283.7 kB  |
///
/// RLE is fastest but stops compressing on dark, noisy images (−3 %), so it does not
/// reliably "still compress". Of the methods that do, ZIP (16 lines) is the fastest
/// (tied with PXR24, which gives larger files) and saves 30–40 %; PIZ saves another
/// 10 % at 10–25 % more time. ZIP it is: 16 ms per image is under 2 minutes of CPU for
/// 6561 images, negligible against the rig's motion, and every OpenEXR reader has it.
pub const COMPRESSION: Compression = Compression::ZIP16;

/// Encode an image as an RGB f16 OpenEXR file in memory with the given compression.
pub fn encode_exr_with(
    img: &RgbImage,
    compression: Compression,
    path_for_errors: &Path,
) -> Result<Vec<u8>, StoreError> {
    check_size(img, path_for_errors)?;
    let (w, h) = (img.width, img.height);
    // One flat f16 vector per channel: much faster than a per-pixel closure.
    let plane = |c: usize| -> Vec<f16> { img.data.iter().skip(c).step_by(3).map(|&v| f16::from_f32(v)).collect() };
    let channels = AnyChannels::sort(SmallVec::from_vec(vec![
        AnyChannel::new("R", FlatSamples::F16(plane(0))),
        AnyChannel::new("G", FlatSamples::F16(plane(1))),
        AnyChannel::new("B", FlatSamples::F16(plane(2))),
    ]));
    let encoding = Encoding {
        compression,
        blocks: Blocks::ScanLines,
        line_order: LineOrder::Increasing,
    };
    let layer = Layer::new((w, h), LayerAttributes::default(), encoding, channels);
    let image = Image::from_layer(layer);
    let mut out = Cursor::new(Vec::with_capacity(w * h * 6 + 1024));
    image
        .write()
        .non_parallel()
        .to_buffered(&mut out)
        .map_err(|source| StoreError::Exr {
            path: path_for_errors.to_path_buf(),
            source,
        })?;
    Ok(out.into_inner())
}

/// Encode with the store's [`COMPRESSION`].
pub fn encode_exr(img: &RgbImage, path_for_errors: &Path) -> Result<Vec<u8>, StoreError> {
    encode_exr_with(img, COMPRESSION, path_for_errors)
}

/// Decode an OpenEXR file held in memory: the first layer with R, G, B channels (any
/// sample type, converted to f32; alpha ignored).
pub fn decode_exr(bytes: &[u8], path_for_errors: &Path) -> Result<RgbImage, StoreError> {
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .rgba_channels(
            |size: Vec2<usize>, _: &RgbaChannels| RgbImage::new(size.width(), size.height()),
            |img: &mut RgbImage, pos: Vec2<usize>, (r, g, b, _a): (f32, f32, f32, f32)| {
                img.set(pos.x(), pos.y(), [r, g, b]);
            },
        )
        .first_valid_layer()
        .all_attributes()
        .non_parallel()
        .from_buffered(Cursor::new(bytes))
        .map_err(|source| StoreError::Exr {
            path: path_for_errors.to_path_buf(),
            source,
        })?;
    Ok(image.layer_data.channel_data.pixels)
}

/// Write an image as RGB f16 OpenEXR with [`COMPRESSION`], atomically (temporary file,
/// fsync, rename, fsync directory).
pub fn write_exr(path: &Path, img: &RgbImage) -> Result<(), StoreError> {
    let bytes = encode_exr(img, path)?;
    write_atomic(path, &bytes, None)
}

/// Read an OpenEXR file (see [`decode_exr`]).
pub fn read_exr(path: &Path) -> Result<RgbImage, StoreError> {
    let bytes = std::fs::read(path).ctx("reading", path, None)?;
    decode_exr(&bytes, path)
}

fn check_size(img: &RgbImage, path: &Path) -> Result<(), StoreError> {
    if img.width == 0 || img.height == 0 || img.data.len() != img.width * img.height * 3 {
        return Err(StoreError::Io {
            op: "encoding",
            path: path.to_path_buf(),
            source: std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!(
                    "image is {}×{} but holds {} values (expected {})",
                    img.width,
                    img.height,
                    img.data.len(),
                    img.width * img.height * 3
                ),
            ),
        });
    }
    Ok(())
}
