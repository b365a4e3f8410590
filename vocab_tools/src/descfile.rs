//! The descriptor file written by `vocab-tools extract` and read by the other commands.
//!
//! A small versioned little-endian binary:
//!
//! ```text
//! magic    8 bytes  "HMDESC\0\0"
//! version  u32      1
//! frames   u64      number of frames
//! per frame:
//!   t      f64      time stamp (seconds, as in the TUM lists)
//!   n      u32      number of descriptors
//!   n × 32 bytes    ORB descriptors (OpenCV's byte order)
//! ```
//!
//! Nothing may follow the last frame. The file is written atomically
//! ([`homing::io::atomic_write`]); reading checks every length against what is left, so a
//! truncated or corrupt file is an error naming the file, never a panic or a huge allocation.

use homing::components::preprocess::Descriptor;
use homing::io::atomic_write;
use homing::{Error, Result};
use std::path::Path;

pub const MAGIC: [u8; 8] = *b"HMDESC\0\0";
pub const VERSION: u32 = 1;
const HEADER_LEN: usize = 8 + 4 + 8;
const FRAME_HEADER_LEN: usize = 8 + 4;

/// The descriptors of one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameDescriptors {
    pub t: f64,
    pub descriptors: Vec<Descriptor>,
}

/// All frames of a descriptor file, in sequence order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DescriptorFile {
    pub frames: Vec<FrameDescriptors>,
}

impl DescriptorFile {
    pub fn n_descriptors(&self) -> usize {
        self.frames.iter().map(|f| f.descriptors.len()).sum()
    }

    /// The file's bytes.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out =
            Vec::with_capacity(HEADER_LEN + self.n_descriptors() * 32 + 12 * self.frames.len());
        out.extend_from_slice(&MAGIC);
        out.extend_from_slice(&VERSION.to_le_bytes());
        out.extend_from_slice(&(self.frames.len() as u64).to_le_bytes());
        for f in &self.frames {
            out.extend_from_slice(&f.t.to_le_bytes());
            out.extend_from_slice(&(f.descriptors.len() as u32).to_le_bytes());
            for d in &f.descriptors {
                out.extend_from_slice(d);
            }
        }
        out
    }

    /// Parses the file's bytes; `path` is only used in error messages.
    pub fn from_bytes(bytes: &[u8], path: &Path) -> Result<Self> {
        let bad = |msg: String| Error::file(path, format!("not a valid descriptor file: {msg}"));
        if bytes.len() < HEADER_LEN {
            if bytes.len() >= 8 && bytes[..8] != MAGIC {
                return Err(bad(
                    "wrong magic (not written by vocab-tools extract)".into()
                ));
            }
            return Err(bad(format!(
                "{} bytes is shorter than the {HEADER_LEN}-byte header (truncated)",
                bytes.len()
            )));
        }
        if bytes[..8] != MAGIC {
            return Err(bad(
                "wrong magic (not written by vocab-tools extract)".into()
            ));
        }
        let version = u32::from_le_bytes(bytes[8..12].try_into().expect("4 bytes"));
        if version != VERSION {
            return Err(bad(format!(
                "version {version}, this vocab-tools reads version {VERSION}"
            )));
        }
        let n_frames = u64::from_le_bytes(bytes[12..20].try_into().expect("8 bytes"));
        // Every frame takes at least its header: bounds the allocation on a corrupt count.
        let rest = (bytes.len() - HEADER_LEN) as u64;
        if n_frames > rest / FRAME_HEADER_LEN as u64 {
            return Err(bad(format!(
                "header says {n_frames} frames but only {rest} bytes follow (truncated or corrupt)"
            )));
        }
        let mut frames = Vec::with_capacity(n_frames as usize);
        let mut pos = HEADER_LEN;
        for k in 0..n_frames {
            if bytes.len() - pos < FRAME_HEADER_LEN {
                return Err(bad(format!(
                    "ends inside the header of frame {k} of {n_frames} at byte {pos} (truncated)"
                )));
            }
            let t = f64::from_le_bytes(bytes[pos..pos + 8].try_into().expect("8 bytes"));
            let n = u32::from_le_bytes(bytes[pos + 8..pos + 12].try_into().expect("4 bytes"));
            pos += FRAME_HEADER_LEN;
            if !t.is_finite() {
                return Err(bad(format!("frame {k} has time stamp {t}")));
            }
            if let Some(prev) = frames.last().map(|f: &FrameDescriptors| f.t)
                && t <= prev
            {
                return Err(bad(format!(
                    "frame {k} has time stamp {t:.6}, not after the previous {prev:.6} (corrupt)"
                )));
            }
            let len = n as usize * 32;
            if bytes.len() - pos < len {
                return Err(bad(format!(
                    "frame {k} of {n_frames} (t = {t:.6}) should have {n} descriptors but the file \
                     ends {} bytes into them (truncated)",
                    bytes.len() - pos
                )));
            }
            let descriptors = bytes[pos..pos + len]
                .chunks_exact(32)
                .map(|c| <Descriptor>::try_from(c).expect("32 bytes"))
                .collect();
            pos += len;
            frames.push(FrameDescriptors { t, descriptors });
        }
        if pos != bytes.len() {
            return Err(bad(format!(
                "{} bytes follow the last of the {n_frames} frames (corrupt)",
                bytes.len() - pos
            )));
        }
        Ok(Self { frames })
    }

    /// Writes the file atomically (temporary file, then rename).
    pub fn write(&self, path: &Path) -> Result<()> {
        atomic_write(path, &self.to_bytes())
    }

    /// Reads and checks a descriptor file.
    pub fn read(path: &Path) -> Result<Self> {
        let bytes =
            std::fs::read(path).map_err(|e| Error::file(path, format!("cannot read: {e}")))?;
        Self::from_bytes(&bytes, path)
    }
}
