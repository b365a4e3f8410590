//! Input and output: TUM RGB-D folders and trajectories, ROS 2 bags in MCAP, perturbations of
//! a sequence, and atomic writes of run outputs.

pub mod cdr;
pub mod decoded;
pub mod features;
pub mod mcap;
pub mod perturb;
pub mod tum;

use crate::error::{Error, Result};
use std::io::Write;
use std::path::Path;

/// Writes `bytes` to `path` atomically: a temporary file in the same folder, flushed and synced,
/// then renamed over the target. A crash mid-write never leaves a half-written result, and an
/// earlier complete file stays until the new one is whole.
pub fn atomic_write(path: &Path, bytes: &[u8]) -> Result<()> {
    atomic_write_with(path, |w| {
        w.write_all(bytes)
            .map_err(|e| Error::file(path, format!("cannot write: {e}")))
    })
}

/// Writes `f`'s output to `path` atomically (a temporary file in the same folder, synced, then
/// renamed), streaming; [`atomic_write`] for bytes in memory.
pub fn atomic_write_with(
    path: &Path,
    f: impl FnOnce(&mut std::io::BufWriter<std::fs::File>) -> Result<()>,
) -> Result<()> {
    write_via_temporary(path, true, f)
}

/// Writes `f`'s output to a temporary file next to `path` and renames it to `path`, so that a
/// reader never sees a half-written file; `sync` flushes it to disk before the rename (results;
/// a scratch file that is rebuilt when lost, as `decoded`'s, skips that cost).
pub(crate) fn write_via_temporary(
    path: &Path,
    sync: bool,
    f: impl FnOnce(&mut std::io::BufWriter<std::fs::File>) -> Result<()>,
) -> Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let name = path
        .file_name()
        .ok_or_else(|| Error::file(path, "not a file path"))?;
    let tmp = dir.join(format!(
        ".{}.tmp.{}",
        name.to_string_lossy(),
        std::process::id()
    ));
    let result = (|| -> Result<()> {
        let file = std::fs::File::create(&tmp)
            .map_err(|e| Error::file(path, format!("cannot write: {e}")))?;
        let mut w = std::io::BufWriter::new(file);
        f(&mut w)?;
        let file = w
            .into_inner()
            .map_err(|e| Error::file(path, format!("cannot write: {e}")))?;
        if sync {
            file.sync_all()
                .map_err(|e| Error::file(path, format!("cannot write: {e}")))?;
        }
        std::fs::rename(&tmp, path).map_err(|e| Error::file(path, format!("cannot write: {e}")))
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// A sequence to run on: a TUM folder or a ROS 2 bag. Both deliver frames through
/// [`tum::FrameSource`], so perturbations apply to either.
#[derive(Debug)]
pub enum Sequence {
    Tum(tum::TumSequence),
    Mcap(Box<mcap::McapSequence>),
}

impl Sequence {
    fn source(&self) -> &(dyn tum::FrameSource + Sync) {
        match self {
            Self::Tum(s) => s,
            Self::Mcap(s) => s.as_ref(),
        }
    }

    /// Colour frames without a depth partner (skipped).
    pub fn unassociated(&self) -> usize {
        match self {
            Self::Tum(s) => s.unassociated,
            Self::Mcap(s) => s.unassociated,
        }
    }

    /// Every frame's time stamp.
    pub fn stamps(&self) -> Vec<f64> {
        let s = self.source();
        (0..s.len()).map(|i| s.timestamp(i)).collect()
    }

    /// The ground truth: a TUM folder's groundtruth.txt, a bag's `/groundtruth` topic.
    pub fn groundtruth(&self) -> Result<Option<Vec<tum::StampedPose>>> {
        match self {
            Self::Tum(s) => s.groundtruth(),
            Self::Mcap(s) => Ok(s.groundtruth()),
        }
    }
}

impl tum::FrameSource for Sequence {
    fn len(&self) -> usize {
        self.source().len()
    }
    fn timestamp(&self, i: usize) -> f64 {
        self.source().timestamp(i)
    }
    fn load(&self, i: usize) -> Result<tum::Frame> {
        self.source().load(i)
    }
}
