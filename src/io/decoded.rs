//! Decoded frames: a sequence's frames as the run sees them after PNG (or bag) decoding, in
//! one raw file, so that many runs on the same sequence decode it once.
//!
//! `homing bench robustness` runs every sequence 60–84 times (its perturbations × 4 controllers);
//! PNG decoding was a quarter of each 640×480 run's CPU time. The bench writes one file per
//! sequence and hands it to its runs (`homing run --decoded-frames FILE`); a run reads frame
//! `i` from it instead of decoding, and computes exactly what it computes from the PNGs (the
//! bytes are the decoded frames themselves; `tests/it/decoded_frames.rs` compares the outputs).
//!
//! Layout (little-endian): the magic, `u32` version, `u64` frame count, `u32` width and
//! height, `u8` 1 when every frame has depth; the frames' time stamps (`f64` each); then one
//! fixed-size record per frame: RGB bytes (`width·height·3`), and with depth its metres
//! (`f32`, `width·height`).

use super::tum::{DepthImage, Frame, FrameSource};
use crate::error::{Error, Result};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

const MAGIC: &[u8; 16] = b"homing-frames\0\0\0";
const VERSION: u32 = 1;
/// Magic, version, count, width, height, depth flag.
const HEADER_BYTES: u64 = 16 + 4 + 8 + 4 + 4 + 1;

/// Writes every frame of `source` to `path` (through a temporary file renamed at the end: a
/// reader never sees a half-written file). Frames are decoded on `jobs` threads.
pub fn write(path: &Path, source: &(dyn FrameSource + Sync), jobs: usize) -> Result<()> {
    let n = source.len();
    if n == 0 {
        return Err(Error::invalid("no frames to write"));
    }
    let first = source.load(0)?;
    let (width, height) = first.rgb.dimensions();
    let depth = first.depth.is_some();
    // A scratch file, rebuilt by every benchmark: not synced to disk (2.9 GB for the bench).
    super::write_via_temporary(path, false, |w| {
        let err = |e: std::io::Error| Error::file(path, format!("cannot write: {e}"));
        w.write_all(MAGIC).map_err(err)?;
        w.write_all(&VERSION.to_le_bytes()).map_err(err)?;
        w.write_all(&(n as u64).to_le_bytes()).map_err(err)?;
        w.write_all(&width.to_le_bytes()).map_err(err)?;
        w.write_all(&height.to_le_bytes()).map_err(err)?;
        w.write_all(&[depth as u8]).map_err(err)?;
        for i in 0..n {
            w.write_all(&source.timestamp(i).to_le_bytes())
                .map_err(err)?;
        }
        let mut put = |i: usize, f: &Frame| -> Result<()> {
            if f.rgb.dimensions() != (width, height) || f.depth.is_some() != depth {
                return Err(Error::file(
                    path,
                    format!(
                        "frame {i} differs from frame 0 in size or in having depth; \
                         cannot store the sequence as fixed-size records"
                    ),
                ));
            }
            w.write_all(f.rgb.as_raw()).map_err(err)?;
            if let Some(d) = &f.depth {
                let bytes: Vec<u8> = d.data.iter().flat_map(|v| v.to_le_bytes()).collect();
                w.write_all(&bytes).map_err(err)?;
            }
            Ok(())
        };
        put(0, &first)?;
        // The others decoded `jobs` frames at a time (one thread each), written in order.
        let batch = jobs.max(1);
        let mut next = 1;
        while next < n {
            let end = (next + batch).min(n);
            let frames: Vec<Result<Frame>> = std::thread::scope(|s| {
                let handles: Vec<_> = (next..end)
                    .map(|i| s.spawn(move || source.load(i)))
                    .collect();
                handles
                    .into_iter()
                    .map(|h| {
                        h.join()
                            .unwrap_or_else(|_| Err(Error::invalid("frame decoding panicked")))
                    })
                    .collect()
            });
            for (i, f) in (next..end).zip(frames) {
                put(i, &f?)?;
            }
            next = end;
        }
        Ok(())
    })
}

/// A file written by [`write()`], read as a [`FrameSource`].
#[derive(Debug)]
pub struct DecodedFrames {
    path: PathBuf,
    file: Mutex<std::fs::File>,
    stamps: Vec<f64>,
    width: u32,
    height: u32,
    depth: bool,
    /// Byte offset of frame 0's record.
    start: u64,
}

impl DecodedFrames {
    /// Opens `path` as the decoded frames of `source`: the frame count, every time stamp
    /// and the image size (`width`×`height`, the camera's) must match, and the file must hold
    /// depth when `need_depth`. A stale or foreign file is an error naming it, never frames
    /// from another sequence.
    pub fn open(
        path: &Path,
        source: &dyn FrameSource,
        width: u32,
        height: u32,
        need_depth: bool,
    ) -> Result<Self> {
        let bad = |msg: String| Error::file(path, msg);
        let mut file = std::fs::File::open(path).map_err(|e| bad(format!("cannot open: {e}")))?;
        let len = file
            .metadata()
            .map_err(|e| bad(format!("cannot read: {e}")))?
            .len();
        let mut header = [0u8; HEADER_BYTES as usize];
        file.read_exact(&mut header)
            .map_err(|_| bad("is not a decoded-frames file (too short)".into()))?;
        if &header[..16] != MAGIC {
            return Err(bad("is not a decoded-frames file (wrong magic)".into()));
        }
        let u32_at = |o: usize| u32::from_le_bytes(header[o..o + 4].try_into().expect("4 bytes"));
        let version = u32_at(16);
        if version != VERSION {
            return Err(bad(format!(
                "decoded-frames version {version}; this build reads {VERSION}"
            )));
        }
        let n = u64::from_le_bytes(header[20..28].try_into().expect("8 bytes"));
        let (w, h) = (u32_at(28), u32_at(32));
        let depth = header[36] == 1;
        if n != source.len() as u64 {
            return Err(bad(format!(
                "holds {n} frames; the sequence has {}",
                source.len()
            )));
        }
        if (w, h) != (width, height) {
            return Err(bad(format!(
                "frames are {w}x{h}, the camera config says {width}x{height}"
            )));
        }
        if need_depth && !depth {
            return Err(bad("holds no depth; the run needs it".into()));
        }
        let mut raw = vec![0u8; 8 * n as usize];
        file.read_exact(&mut raw)
            .map_err(|_| bad("is truncated (time stamps)".into()))?;
        let stamps: Vec<f64> = raw
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect();
        for (i, &t) in stamps.iter().enumerate() {
            if t.to_bits() != source.timestamp(i).to_bits() {
                return Err(bad(format!(
                    "frame {i} is stamped {t:.6}; the sequence's is {:.6} (a file of another \
                     sequence, or of an older version of it)",
                    source.timestamp(i)
                )));
            }
        }
        let start = HEADER_BYTES + 8 * n;
        let this = Self {
            path: path.to_path_buf(),
            file: Mutex::new(file),
            stamps,
            width,
            height,
            depth,
            start,
        };
        let expected = start + n * this.record_bytes();
        if len != expected {
            return Err(bad(format!(
                "is {len} bytes; {n} frames of {w}x{h} make {expected} (truncated or corrupt)"
            )));
        }
        Ok(this)
    }

    fn pixels(&self) -> u64 {
        self.width as u64 * self.height as u64
    }

    fn record_bytes(&self) -> u64 {
        self.pixels() * if self.depth { 3 + 4 } else { 3 }
    }
}

impl FrameSource for DecodedFrames {
    fn len(&self) -> usize {
        self.stamps.len()
    }
    fn timestamp(&self, i: usize) -> f64 {
        self.stamps[i]
    }
    fn load(&self, i: usize) -> Result<Frame> {
        let err = |e: std::io::Error| Error::file(&self.path, format!("frame {i}: {e}"));
        let mut buf = vec![0u8; self.record_bytes() as usize];
        {
            let mut f = self.file.lock().unwrap_or_else(|e| e.into_inner());
            f.seek(SeekFrom::Start(self.start + i as u64 * self.record_bytes()))
                .map_err(err)?;
            f.read_exact(&mut buf).map_err(err)?;
        }
        let rgb_len = 3 * self.pixels() as usize;
        let depth = self.depth.then(|| DepthImage {
            width: self.width,
            height: self.height,
            data: buf[rgb_len..]
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                .collect(),
        });
        buf.truncate(rgb_len);
        let rgb = image::RgbImage::from_raw(self.width, self.height, buf)
            .ok_or_else(|| Error::file(&self.path, format!("frame {i}: short record")))?;
        Ok(Frame {
            index: i,
            t: self.stamps[i],
            rgb,
            depth,
        })
    }
}
