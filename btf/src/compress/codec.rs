//! Quantized, entropy-coded factor blocks (`.gbtf` version 2).
//!
//! Factors are stored as f32 by default: 4 bytes per value, most of which carry noise far
//! below what the reconstruction error can see. A coded block instead holds
//!
//! * **[`BlockCodec::Quantized`]**: `bits` (1–16) per value with one affine scale per
//!   *vector* — per column when the block has at least as many rows as columns (a factor
//!   such as `U·S`, texels × c: one scale per component), else per row (a block of
//!   eigen-ABRDFs or BRDFs, one per row). Vector `j` stores `lo_j` (its minimum) and
//!   `step_j = (max_j − lo_j) / (2^bits − 1)` as f32; value `x` becomes the code
//!   `round((x − lo_j) / step_j)` and decodes to `lo_j + code · step_j`, so the error is
//!   at most `step_j / 2` (plus f32 rounding). A constant vector (all zeros: the unused
//!   components of a rank-deficient input) gets `step_j = 0` and every code 0: it
//!   decodes exactly and nothing is ever divided by zero, so a constant or rank-deficient
//!   input cannot turn into NaN.
//! * **[`BlockCodec::Integer`]**: blocks whose values are all integers in `0..=65535`
//!   (cluster and box indices) are stored exactly as 16-bit codes.
//!
//! The codes are laid out vector by vector (each vector contiguous), as one byte plane
//! (≤ 8 bits) or two (low bytes, then high bytes), and then either kept as they are or
//! replaced by the zigzag-coded difference to the previous code of the same vector
//! (neighbouring texels and neighbouring measurements are alike, so differences are
//! small). Both filters are tried and the smaller result is kept; the first byte of the
//! stored block says which. The payload is compressed by zstd at the fixed level
//! [`ZSTD_LEVEL`] in one thread (the `zstd` crate's bulk API; no worker threads), so the
//! same block gives the same bytes on any machine.

use serde::{Deserialize, Serialize};

/// zstd level of coded blocks. Fixed: the bytes of a file must not depend on anything
/// but its content. Level 19 is the highest "normal" level; coded blocks are small
/// (megabytes), so its encode time (seconds) is a small part of a compression run.
pub const ZSTD_LEVEL: i32 = 19;

/// How a block is stored in a version-2 `.gbtf` file.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(tag = "codec", rename_all = "kebab-case")]
pub enum BlockCodec {
    /// Exact integers in `0..=65535`, 16-bit codes, zstd.
    Integer,
    /// `bits` per value, one affine scale per vector along `axis`, zstd.
    Quantized { bits: u32, axis: Axis },
}

/// Which vectors of a block get their own scale.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub enum Axis {
    /// One scale per column (blocks with rows ≥ cols).
    Columns,
    /// One scale per row.
    Rows,
}

/// Bits a quantized block may use.
pub const BITS: std::ops::RangeInclusive<u32> = 1..=16;

/// The codec for a block of `rows × cols` values at `bits` per value: [`BlockCodec::Integer`]
/// when every value is an integer in `0..=65535` (exact), else quantized with one scale
/// per vector of the shorter side.
pub fn choose(values: &[f32], rows: usize, cols: usize, bits: u32) -> BlockCodec {
    if !values.is_empty() && values.iter().all(|&v| (0.0..=65535.0).contains(&v) && v.fract() == 0.0) {
        return BlockCodec::Integer;
    }
    let axis = if rows >= cols { Axis::Columns } else { Axis::Rows };
    BlockCodec::Quantized { bits, axis }
}

/// Vectors of a block: (count, length, index of element `i` of vector `j` in the
/// row-major block).
fn vectors(rows: usize, cols: usize, axis: Axis) -> (usize, usize, impl Fn(usize, usize) -> usize) {
    let (n, len) = match axis {
        Axis::Columns => (cols, rows),
        Axis::Rows => (rows, cols),
    };
    (n, len, move |j: usize, i: usize| match axis {
        Axis::Columns => i * cols + j,
        Axis::Rows => j * cols + i,
    })
}

/// Encode a row-major `rows × cols` block. Errors (as text; the container names the
/// block) on non-finite values or a bad bit count.
pub fn encode(values: &[f32], rows: usize, cols: usize, codec: BlockCodec) -> Result<Vec<u8>, String> {
    if values.len() != rows * cols {
        return Err(format!("{} values for a {rows}×{cols} block", values.len()));
    }
    if let Some(p) = values.iter().position(|v| !v.is_finite()) {
        return Err(format!(
            "non-finite value {} at row {}, column {}",
            values[p],
            p / cols.max(1),
            p % cols.max(1)
        ));
    }
    let (codes, bits, payload) = match codec {
        BlockCodec::Integer => {
            if let Some(v) = values
                .iter()
                .find(|&&v| !((0.0..=65535.0).contains(&v) && v.fract() == 0.0))
            {
                return Err(format!("value {v} is not an integer in 0..=65535"));
            }
            let (n, len, at) = vectors(rows, cols, Axis::Columns);
            let codes: Vec<u16> = (0..n)
                .flat_map(|j| (0..len).map(move |i| (j, i)))
                .map(|(j, i)| values[at(j, i)] as u16)
                .collect();
            (codes, 16, Vec::new())
        }
        BlockCodec::Quantized { bits, axis } => {
            if !BITS.contains(&bits) {
                return Err(format!(
                    "{bits} bits per value; quantization takes {} to {}",
                    BITS.start(),
                    BITS.end()
                ));
            }
            let (n, len, at) = vectors(rows, cols, axis);
            let top = ((1u32 << bits) - 1) as f64;
            let mut scales = Vec::with_capacity(n * 8);
            let mut codes = Vec::with_capacity(rows * cols);
            for j in 0..n {
                let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                for i in 0..len {
                    let v = values[at(j, i)];
                    lo = lo.min(v);
                    hi = hi.max(v);
                }
                if len == 0 {
                    (lo, hi) = (0.0, 0.0);
                }
                let step = ((hi as f64 - lo as f64) / top) as f32;
                // A zero, subnormal-underflowed or otherwise unusable step: a constant vector.
                let step = if step.is_finite() && step > 0.0 { step } else { 0.0 };
                scales.extend_from_slice(&lo.to_le_bytes());
                scales.extend_from_slice(&step.to_le_bytes());
                for i in 0..len {
                    let q = if step > 0.0 {
                        ((values[at(j, i)] as f64 - lo as f64) / step as f64)
                            .round()
                            .clamp(0.0, top)
                    } else {
                        0.0
                    };
                    codes.push(q as u16);
                }
            }
            (codes, bits, scales)
        }
    };
    let len = match codec {
        BlockCodec::Integer => rows,
        BlockCodec::Quantized { axis, .. } => vectors(rows, cols, axis).1,
    };
    let mut best: Option<Vec<u8>> = None;
    for filter in [Filter::None, Filter::Delta] {
        let mut p = payload.clone();
        p.extend(planes(&filtered(&codes, len, bits, filter), bits));
        let z = zstd::bulk::compress(&p, ZSTD_LEVEL).map_err(|e| format!("zstd: {e}"))?;
        let mut out = Vec::with_capacity(z.len() + 1);
        out.push(filter as u8);
        out.extend(z);
        if best.as_ref().is_none_or(|b| out.len() < b.len()) {
            best = Some(out);
        }
    }
    Ok(best.unwrap_or_default())
}

/// Decode a block written by [`encode`] into row-major f32 values.
pub fn decode(bytes: &[u8], rows: usize, cols: usize, codec: BlockCodec) -> Result<Vec<f32>, String> {
    let (&filter, z) = bytes.split_first().ok_or("empty coded block")?;
    let filter = match filter {
        0 => Filter::None,
        1 => Filter::Delta,
        f => return Err(format!("unknown filter {f}")),
    };
    let total = rows.checked_mul(cols).ok_or("block size overflows")?;
    let (axis, bits) = match codec {
        BlockCodec::Integer => (Axis::Columns, 16),
        BlockCodec::Quantized { bits, axis } => {
            if !BITS.contains(&bits) {
                return Err(format!(
                    "{bits} bits per value is not between {} and {}",
                    BITS.start(),
                    BITS.end()
                ));
            }
            (axis, bits)
        }
    };
    let (n, len, at) = vectors(rows, cols, axis);
    let scale_bytes = if matches!(codec, BlockCodec::Integer) {
        0
    } else {
        n.checked_mul(8).ok_or("block size overflows")?
    };
    let want = total
        .checked_mul(if bits <= 8 { 1 } else { 2 })
        .and_then(|b| b.checked_add(scale_bytes))
        .ok_or("block size overflows")?;
    // The frame states its size: check it against the shape before allocating, and
    // allocate fallibly, so a damaged or hostile header is an error, not an abort.
    match zstd::zstd_safe::get_frame_content_size(z) {
        Ok(Some(n)) if n == want as u64 => {}
        Ok(n) => return Err(format!("zstd frame holds {n:?} bytes, the shape needs {want}")),
        Err(_) => return Err("not a zstd frame".into()),
    }
    let mut p = Vec::new();
    p.try_reserve_exact(want)
        .map_err(|_| format!("cannot allocate {want} bytes for a {rows}×{cols} block"))?;
    zstd::bulk::Decompressor::new()
        .and_then(|mut d| d.decompress_to_buffer(z, &mut p))
        .map_err(|e| format!("zstd: {e}"))?;
    if p.len() != want {
        return Err(format!("{} bytes after decompression, the shape needs {want}", p.len()));
    }
    let (scales, planes_bytes) = p.split_at(scale_bytes);
    let codes = unfiltered(&unplanes(planes_bytes, total, bits), len, bits, filter);
    let mut out = Vec::new();
    out.try_reserve_exact(total)
        .map_err(|_| format!("cannot allocate {total} values for a {rows}×{cols} block"))?;
    out.resize(total, 0f32);
    for j in 0..n {
        let (lo, step) = match codec {
            BlockCodec::Integer => (0.0, 1.0),
            _ => {
                let f = |o: usize| f32::from_le_bytes(scales[o..o + 4].try_into().expect("4 bytes"));
                (f(j * 8), f(j * 8 + 4))
            }
        };
        if !(lo.is_finite() && step.is_finite() && step >= 0.0) {
            return Err(format!("vector {j}: scale lo {lo}, step {step} is not usable"));
        }
        let top = ((1u32 << bits) - 1) as u16;
        for i in 0..len {
            let c = codes[j * len + i];
            if bits < 16 && c > top {
                return Err(format!("vector {j}: code {c} exceeds {bits} bits"));
            }
            // In f64: `c · step` alone may exceed the f32 range when `lo` is very negative.
            out[at(j, i)] = (lo as f64 + c as f64 * step as f64) as f32;
        }
    }
    Ok(out)
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Filter {
    None = 0,
    Delta = 1,
}

/// Codes after the filter: unchanged, or per vector the first code then the zigzag of the
/// difference to the previous code, modulo `2^bits` (invertible, and small differences
/// stay small whichever their sign).
fn filtered(codes: &[u16], len: usize, bits: u32, filter: Filter) -> Vec<u16> {
    if filter == Filter::None || len == 0 {
        return codes.to_vec();
    }
    let mask = if bits >= 16 { u16::MAX } else { (1u16 << bits) - 1 };
    let half = 1u32 << (bits - 1);
    let mut out = Vec::with_capacity(codes.len());
    for v in codes.chunks(len) {
        let mut prev = 0u16;
        for &c in v {
            let d = c.wrapping_sub(prev) & mask;
            // Signed value of d in bits-wide two's complement, then zigzag.
            let s = if (d as u32) < half {
                d as i32
            } else {
                d as i32 - (1i32 << bits)
            };
            out.push((((s << 1) ^ (s >> 31)) as u32 & mask as u32) as u16);
            prev = c;
        }
    }
    out
}

fn unfiltered(codes: &[u16], len: usize, bits: u32, filter: Filter) -> Vec<u16> {
    if filter == Filter::None || len == 0 {
        return codes.to_vec();
    }
    let mask = if bits >= 16 { u16::MAX } else { (1u16 << bits) - 1 };
    let mut out = Vec::with_capacity(codes.len());
    for v in codes.chunks(len) {
        let mut prev = 0u16;
        for &z in v {
            let z = z as i32;
            let s = (z >> 1) ^ -(z & 1);
            let c = (prev as i32).wrapping_add(s) as u16 & mask;
            out.push(c);
            prev = c;
        }
    }
    out
}

/// One byte per code (≤ 8 bits), else all low bytes then all high bytes.
fn planes(codes: &[u16], bits: u32) -> Vec<u8> {
    if bits <= 8 {
        codes.iter().map(|&c| c as u8).collect()
    } else {
        codes
            .iter()
            .map(|&c| c as u8)
            .chain(codes.iter().map(|&c| (c >> 8) as u8))
            .collect()
    }
}

fn unplanes(bytes: &[u8], n: usize, bits: u32) -> Vec<u16> {
    if bits <= 8 {
        bytes.iter().map(|&b| b as u16).collect()
    } else {
        (0..n).map(|i| bytes[i] as u16 | (bytes[n + i] as u16) << 8).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(values: &[f32], rows: usize, cols: usize, bits: u32) -> (BlockCodec, Vec<u8>, Vec<f32>) {
        let codec = choose(values, rows, cols, bits);
        let bytes = encode(values, rows, cols, codec).unwrap();
        let back = decode(&bytes, rows, cols, codec).unwrap();
        assert_eq!(back.len(), values.len());
        assert!(back.iter().all(|v| v.is_finite()));
        (codec, bytes, back)
    }

    /// Error within half a step of its vector, for every bit count and both axes.
    #[test]
    fn quantization_error_is_within_half_a_step() {
        for (rows, cols) in [(300, 5), (4, 250)] {
            let v: Vec<f32> = (0..rows * cols)
                .map(|k| ((k as f32 * 0.37).sin() * (1.0 + (k % cols) as f32)) - 0.2)
                .collect();
            for bits in [1, 4, 8, 9, 12, 16] {
                let (codec, _, back) = round_trip(&v, rows, cols, bits);
                let axis = if rows >= cols { Axis::Columns } else { Axis::Rows };
                assert_eq!(codec, BlockCodec::Quantized { bits, axis });
                let (n, len, at) = vectors(rows, cols, axis);
                for j in 0..n {
                    let xs: Vec<f32> = (0..len).map(|i| v[at(j, i)]).collect();
                    let (lo, hi) = xs.iter().fold((f32::MAX, f32::MIN), |(a, b), &x| (a.min(x), b.max(x)));
                    let half = (hi - lo) / ((1u32 << bits) - 1) as f32 / 2.0;
                    for i in 0..len {
                        let e = (back[at(j, i)] - v[at(j, i)]).abs();
                        assert!(
                            e <= half * 1.001 + 1e-6 * hi.abs().max(lo.abs()),
                            "bits {bits} vector {j}: {e} > {half}"
                        );
                    }
                }
            }
        }
    }

    /// Constant blocks, zero columns (rank-deficient factors), a single value, tiny and
    /// huge magnitudes: never NaN, constants exact.
    #[test]
    fn constant_and_rank_deficient_blocks_never_become_nan() {
        let zeros = vec![0f32; 64 * 3];
        let (_, _, back) = round_trip(&zeros, 64, 3, 8);
        assert_eq!(back, zeros);
        let c = vec![0.3f32; 64 * 3];
        let (codec, _, back) = round_trip(&c, 64, 3, 10);
        assert!(matches!(codec, BlockCodec::Quantized { .. }));
        assert_eq!(back, c);
        // Rank 1 padded with zero columns (truncated_svd's extra columns).
        let v: Vec<f32> = (0..100 * 4)
            .map(|k| if k % 4 == 0 { (k as f32).sqrt() } else { 0.0 })
            .collect();
        let (_, _, back) = round_trip(&v, 100, 4, 12);
        for (k, b) in back.iter().enumerate() {
            if k % 4 != 0 {
                assert_eq!(*b, 0.0);
            }
        }
        // Spans near f32 limits and subnormal steps.
        let w = vec![1e-44f32, 2e-44, 3e-44, 1e-44];
        round_trip(&w, 4, 1, 16);
        let big = vec![-3e38f32, 3e38, 0.0, 1.0];
        let (_, _, back) = round_trip(&big, 4, 1, 8);
        assert!(back.iter().all(|x| x.is_finite()));
        let one = [0.5f32];
        assert_eq!(round_trip(&one, 1, 1, 8).2, one);
        assert_eq!(round_trip(&[], 0, 3, 8).2, Vec::<f32>::new());
    }

    #[test]
    fn integer_blocks_are_exact() {
        let idx: Vec<f32> = (0..1000).map(|k| ((k * 7) % 300) as f32).collect();
        let (codec, bytes, back) = round_trip(&idx, 1000, 1, 8);
        assert_eq!(codec, BlockCodec::Integer);
        assert_eq!(back, idx);
        assert!(bytes.len() < 1000, "{} bytes", bytes.len());
        assert!(encode(&[0.5], 1, 1, BlockCodec::Integer).is_err());
    }

    #[test]
    fn smooth_data_compresses_and_bytes_are_deterministic() {
        let v: Vec<f32> = (0..4096 * 4)
            .map(|k| ((k / 4) as f32 * 0.01).sin() + (k % 4) as f32)
            .collect();
        let codec = choose(&v, 4096, 4, 10);
        let a = encode(&v, 4096, 4, codec).unwrap();
        let b = encode(&v, 4096, 4, codec).unwrap();
        assert_eq!(a, b);
        // 10-bit codes of a smooth signal: the delta filter wins and beats 2 bytes/value.
        assert_eq!(a[0], Filter::Delta as u8);
        assert!(a.len() * 4 < v.len() * 2, "{} bytes for {} values", a.len(), v.len());
    }

    #[test]
    fn bad_input_and_corrupt_bytes_are_errors() {
        assert!(encode(
            &[f32::NAN, 1.0],
            2,
            1,
            BlockCodec::Quantized {
                bits: 8,
                axis: Axis::Columns
            }
        )
        .is_err());
        assert!(encode(
            &[1.0, 2.0],
            2,
            1,
            BlockCodec::Quantized {
                bits: 0,
                axis: Axis::Columns
            }
        )
        .is_err());
        assert!(encode(
            &[1.0, 2.0],
            2,
            1,
            BlockCodec::Quantized {
                bits: 17,
                axis: Axis::Columns
            }
        )
        .is_err());
        let v: Vec<f32> = (0..50).map(|k| k as f32 * 0.1).collect();
        let codec = choose(&v, 50, 1, 8);
        let mut bytes = encode(&v, 50, 1, codec).unwrap();
        assert!(decode(&bytes, 51, 1, codec).is_err(), "wrong shape");
        let e = decode(&bytes, 1 << 40, 1 << 20, codec).unwrap_err();
        assert!(e.contains("zstd frame holds") || e.contains("overflows"), "{e}");
        assert!(decode(&[], 50, 1, codec).is_err());
        bytes[0] = 9;
        assert!(decode(&bytes, 50, 1, codec).is_err(), "unknown filter");
    }

    #[test]
    fn delta_filter_inverts_at_every_width() {
        for bits in [1, 3, 8, 9, 15, 16] {
            let top = ((1u32 << bits) - 1) as u16;
            let codes: Vec<u16> = (0..200u32)
                .map(|k| (k.wrapping_mul(2654435761u32) >> 7) as u16 & top)
                .collect();
            let f = filtered(&codes, 50, bits, Filter::Delta);
            assert!(f.iter().all(|&c| c <= top));
            assert_eq!(unfiltered(&f, 50, bits, Filter::Delta), codes, "bits {bits}");
        }
    }
}
