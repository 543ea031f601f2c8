//! The `.gbtf` container: gonio's own compressed-BTF file.
//!
//! ```text
//! offset  size  content
//! 0       8     magic  b"GBTF\0\r\n\x1a"
//! 8       4     format version (u32 LE): 1, or 2 when a block is coded
//! 12      8     header length H (u64 LE)
//! 20      H     header: UTF-8 JSON (see [`GbtfHeader`])
//! 20+H    4     CRC-32 (IEEE) of the header bytes (u32 LE)
//! then, for each block listed in the header, in order:
//!         8     block length B in bytes (u64 LE); rows · cols · 4 for an f32 block
//!         B     row-major f32 little-endian values, or (version 2, the block's
//!               `codec` set) its quantized zstd-coded form (see [`super::codec`])
//!         4     CRC-32 of the B bytes (u32 LE)
//! end of file (trailing bytes are an error)
//! ```
//!
//! The header is self-describing: method, parameters, image size, light and view
//! directions (degrees), and the name, shape and (version 2) codec of every block.
//! Files without coded blocks are written as version 1, byte for byte as before coded
//! blocks existed; readers decode coded blocks to f32 on load, so every decoder
//! (reconstruction, interpolation, evaluation) works on either version unchanged.

use super::codec::{self, BlockCodec};
use super::error::CompressError;
use serde::{Deserialize, Serialize};
use std::path::Path;

pub const MAGIC: &[u8; 8] = b"GBTF\0\r\n\x1a";
/// Version of files whose blocks are all plain f32.
pub const VERSION: u32 = 1;
/// Version of files with at least one coded block.
pub const VERSION_CODED: u32 = 2;

/// Name and shape of one factor block (row-major f32 once decoded).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct BlockInfo {
    pub name: String,
    pub rows: usize,
    pub cols: usize,
    /// How the block is stored: absent for plain f32 (the only kind in version 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub codec: Option<BlockCodec>,
}

impl BlockInfo {
    /// A plain f32 block.
    pub fn new(name: impl Into<String>, rows: usize, cols: usize) -> Self {
        BlockInfo {
            name: name.into(),
            rows,
            cols,
            codec: None,
        }
    }
}

/// The JSON header of a `.gbtf` file.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct GbtfHeader {
    /// The method's name (`CodecId::name`: `"pca"`, `"pvmf"`, `"local-pca"`, …).
    /// `CompressedBtf::new` opens the file with the codec of that name.
    pub method: String,
    /// Method parameters (components, seed, oversampling, power iterations, …).
    pub params: serde_json::Value,
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    /// Factor value type: always `"f32le"` in version 1.
    pub dtype: String,
    pub lights_deg: Vec<[f64; 2]>,
    pub views_deg: Vec<[f64; 2]>,
    /// `[light, view]` pairs that were not measured and were filled before factorizing.
    pub filled: Vec<[usize; 2]>,
    /// Free-form provenance (source dataset, its `values` and `sample`).
    pub source: serde_json::Value,
    pub blocks: Vec<BlockInfo>,
}

/// A header and its blocks.
#[derive(Clone, Debug, PartialEq)]
pub struct Gbtf {
    pub header: GbtfHeader,
    pub blocks: Vec<Vec<f32>>,
}

impl Gbtf {
    /// Serialize to bytes.
    pub fn to_bytes(&self) -> Result<Vec<u8>, CompressError> {
        if self.header.blocks.len() != self.blocks.len() {
            return Err(CompressError::Invalid(format!(
                "{} block descriptions for {} blocks",
                self.header.blocks.len(),
                self.blocks.len()
            )));
        }
        let header = serde_json::to_vec(&self.header).map_err(|e| CompressError::Invalid(e.to_string()))?;
        let total: usize = self.blocks.iter().map(|b| 12 + b.len() * 4).sum::<usize>() + 24 + header.len();
        let coded = self.header.blocks.iter().any(|b| b.codec.is_some());
        let mut out = Vec::with_capacity(total);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&if coded { VERSION_CODED } else { VERSION }.to_le_bytes());
        out.extend_from_slice(&(header.len() as u64).to_le_bytes());
        out.extend_from_slice(&header);
        out.extend_from_slice(&crc32fast::hash(&header).to_le_bytes());
        for (info, b) in self.header.blocks.iter().zip(&self.blocks) {
            if info.rows * info.cols != b.len() {
                return Err(CompressError::Invalid(format!(
                    "block {}: {}×{} declared, {} values",
                    info.name,
                    info.rows,
                    info.cols,
                    b.len()
                )));
            }
            let start = out.len() + 8;
            if let Some(c) = info.codec {
                let bytes = codec::encode(b, info.rows, info.cols, c)
                    .map_err(|e| CompressError::Invalid(format!("block {}: {e}", info.name)))?;
                out.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
                out.extend_from_slice(&bytes);
            } else {
                out.extend_from_slice(&((b.len() * 4) as u64).to_le_bytes());
                for v in b {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
            let crc = crc32fast::hash(&out[start..]);
            out.extend_from_slice(&crc.to_le_bytes());
        }
        Ok(out)
    }

    /// Parse bytes, checking magic, version, lengths and every CRC. `path` names the
    /// file in errors.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Gbtf, CompressError> {
        let corrupt = |reason: String| CompressError::Corrupt {
            path: path.to_path_buf(),
            reason,
        };
        let mut pos = 0usize;
        let mut take = |n: usize, what: &str| -> Result<&[u8], CompressError> {
            if bytes.len() - pos < n {
                return Err(corrupt(format!(
                    "truncated: {what} needs {n} bytes at offset {pos}, the file has {} left",
                    bytes.len() - pos
                )));
            }
            let s = &bytes[pos..pos + n];
            pos += n;
            Ok(s)
        };
        if take(8, "magic")? != MAGIC {
            return Err(corrupt("not a .gbtf file (bad magic)".into()));
        }
        let version = u32::from_le_bytes(take(4, "version")?.try_into().unwrap());
        if version != VERSION && version != VERSION_CODED {
            return Err(corrupt(format!(
                "format version {version}, this gonio reads versions {VERSION} and {VERSION_CODED}"
            )));
        }
        let hlen = u64::from_le_bytes(take(8, "header length")?.try_into().unwrap());
        let hlen = usize::try_from(hlen).map_err(|_| corrupt("header length overflows".into()))?;
        let hbytes = take(hlen, "header")?;
        let crc = u32::from_le_bytes(take(4, "header CRC")?.try_into().unwrap());
        if crc32fast::hash(hbytes) != crc {
            return Err(corrupt("header CRC mismatch".into()));
        }
        let header: GbtfHeader = serde_json::from_slice(hbytes).map_err(|e| corrupt(format!("header JSON: {e}")))?;
        if header.dtype != "f32le" {
            return Err(corrupt(format!("unknown dtype {:?}", header.dtype)));
        }
        if version == VERSION {
            if let Some(b) = header.blocks.iter().find(|b| b.codec.is_some()) {
                return Err(corrupt(format!(
                    "block {} is coded, which version 1 does not allow",
                    b.name
                )));
            }
        }
        let mut blocks = Vec::with_capacity(header.blocks.len());
        for info in &header.blocks {
            let what = format!("block {}", info.name);
            let len = u64::from_le_bytes(take(8, &what)?.try_into().unwrap());
            if let Some(c) = info.codec {
                let len = usize::try_from(len).map_err(|_| corrupt(format!("{what}: length overflows")))?;
                let data = take(len, &what)?;
                let crc = u32::from_le_bytes(take(4, &what)?.try_into().unwrap());
                if crc32fast::hash(data) != crc {
                    return Err(corrupt(format!("{what}: CRC mismatch")));
                }
                blocks.push(codec::decode(data, info.rows, info.cols, c).map_err(|e| corrupt(format!("{what}: {e}")))?);
                continue;
            }
            let want = (info.rows as u64) * (info.cols as u64) * 4;
            if len != want {
                return Err(corrupt(format!(
                    "{what}: length {len} bytes, its shape {}×{} needs {want}",
                    info.rows, info.cols
                )));
            }
            let data = take(len as usize, &what)?;
            let crc = u32::from_le_bytes(take(4, &what)?.try_into().unwrap());
            if crc32fast::hash(data) != crc {
                return Err(corrupt(format!("{what}: CRC mismatch")));
            }
            blocks.push(
                data.chunks_exact(4)
                    .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
                    .collect(),
            );
        }
        if pos != bytes.len() {
            return Err(corrupt(format!(
                "{} trailing bytes after the last block",
                bytes.len() - pos
            )));
        }
        Ok(Gbtf { header, blocks })
    }

    /// Mark every block for quantization at `bits` per value ([`codec::choose`]: exact
    /// integer blocks stay exact); writing then produces a version-2 file.
    pub fn quantize(&mut self, bits: u32) -> Result<(), CompressError> {
        if !codec::BITS.contains(&bits) {
            return Err(CompressError::Invalid(format!(
                "--quantize {bits}: bits per value must be between {} and {}",
                codec::BITS.start(),
                codec::BITS.end()
            )));
        }
        for (info, b) in self.header.blocks.iter_mut().zip(&self.blocks) {
            info.codec = Some(codec::choose(b, info.rows, info.cols, bits));
        }
        Ok(())
    }

    pub fn write(&self, path: &Path) -> Result<u64, CompressError> {
        let bytes = self.to_bytes()?;
        gonio_dataset::store::atomic::write_atomic(path, &bytes, None)?;
        Ok(bytes.len() as u64)
    }

    pub fn read(path: &Path) -> Result<Gbtf, CompressError> {
        let bytes = std::fs::read(path).map_err(|source| CompressError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Gbtf::from_bytes(&bytes, path)
    }
}

/// Writes a `.gbtf` block by block, so a file larger than memory (a synthesized BTF of
/// 4096² texels) never has to be held whole: the bytes are the ones [`Gbtf::to_bytes`]
/// would produce for the same header and values. Values are appended in block order with
/// [`GbtfStreamWriter::push`]; [`GbtfStreamWriter::finish`] checks that every declared
/// value arrived, then renames the temporary file into place (nothing is left under the
/// final name on error).
pub struct GbtfStreamWriter {
    tmp: gonio_dataset::store::atomic::TempFile,
    buf: Vec<u8>,
    path: std::path::PathBuf,
    /// Values of each block, in order.
    sizes: Vec<u64>,
    block: usize,
    /// Values still expected in the current block (0 before a block is started).
    remaining: u64,
    crc: crc32fast::Hasher,
    written: u64,
}

impl GbtfStreamWriter {
    const FLUSH: usize = 1 << 20;

    /// Create the temporary file and write magic, version and header.
    pub fn create(path: &Path, header: &GbtfHeader) -> Result<Self, CompressError> {
        let hbytes = serde_json::to_vec(header).map_err(|e| CompressError::Invalid(e.to_string()))?;
        let tmp = gonio_dataset::store::atomic::TempFile::create(path, None)?;
        let mut w = GbtfStreamWriter {
            tmp,
            buf: Vec::with_capacity(Self::FLUSH + (1 << 18)),
            path: path.to_path_buf(),
            sizes: header.blocks.iter().map(|b| b.rows as u64 * b.cols as u64).collect(),
            block: 0,
            remaining: 0,
            crc: crc32fast::Hasher::new(),
            written: 0,
        };
        w.put(MAGIC)?;
        w.put(&VERSION.to_le_bytes())?;
        w.put(&(hbytes.len() as u64).to_le_bytes())?;
        w.put(&hbytes)?;
        w.put(&crc32fast::hash(&hbytes).to_le_bytes())?;
        w.open_next()?;
        Ok(w)
    }

    fn put(&mut self, bytes: &[u8]) -> Result<(), CompressError> {
        self.buf.extend_from_slice(bytes);
        self.written += bytes.len() as u64;
        if self.buf.len() >= Self::FLUSH {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<(), CompressError> {
        use std::io::Write;
        let res = self.tmp.file().write_all(&self.buf);
        self.buf.clear();
        res.map_err(|source| CompressError::Io {
            path: self.path.clone(),
            source,
        })
    }

    /// Start the next non-empty block, closing empty ones (their length and CRC).
    fn open_next(&mut self) -> Result<(), CompressError> {
        while self.remaining == 0 && self.block < self.sizes.len() {
            let n = self.sizes[self.block];
            self.put(&(n * 4).to_le_bytes())?;
            self.crc = crc32fast::Hasher::new();
            self.remaining = n;
            if n == 0 {
                self.close_block()?;
            }
        }
        Ok(())
    }

    fn close_block(&mut self) -> Result<(), CompressError> {
        let crc = std::mem::replace(&mut self.crc, crc32fast::Hasher::new()).finalize();
        self.put(&crc.to_le_bytes())?;
        self.block += 1;
        Ok(())
    }

    /// Append values; they may span block boundaries.
    pub fn push(&mut self, mut values: &[f32]) -> Result<(), CompressError> {
        let mut bytes = Vec::with_capacity(values.len().min(1 << 16) * 4);
        while !values.is_empty() {
            if self.remaining == 0 {
                return Err(CompressError::Invalid(format!(
                    "{}: {} values more than the header's blocks declare",
                    self.path.display(),
                    values.len()
                )));
            }
            let n = (self.remaining.min(values.len() as u64) as usize).min(1 << 16);
            bytes.clear();
            for v in &values[..n] {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
            self.crc.update(&bytes);
            self.put(&bytes)?;
            self.remaining -= n as u64;
            values = &values[n..];
            if self.remaining == 0 {
                self.close_block()?;
                self.open_next()?;
            }
        }
        Ok(())
    }

    /// Check completeness, flush, fsync and rename into place; returns the file size.
    pub fn finish(mut self) -> Result<u64, CompressError> {
        if self.block < self.sizes.len() {
            return Err(CompressError::Invalid(format!(
                "{}: block {} of {} is missing {} values",
                self.path.display(),
                self.block,
                self.sizes.len(),
                self.remaining
            )));
        }
        self.flush()?;
        self.tmp.commit()?;
        Ok(self.written)
    }
}
