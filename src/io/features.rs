//! Extracted features: every frame's [`Measurement`] (ORB key points, descriptors, depth under
//! them) computed once, so that the many runs of a benchmark on one sequence do not extract
//! them again.
//!
//! ORB extraction is 45 % of `homing bench robustness`'s run time (935 of 2068 s summed over
//! its 372 runs), and every run of a sequence extracts the same features from the same
//! images: only the perturbed frames (black, noise, foreign, frozen) differ. The bench writes
//! one file per sequence from its decoded frames and hands it to its runs (`homing run
//! --features FILE`); a run takes the measurement of every unperturbed frame from it (depth
//! cleared when the run is monocular) and extracts the others itself, and so computes exactly
//! what it computes without the file (`tests/it/decoded_frames.rs` compares the outputs). The
//! time each frame's extraction took when the file was written is kept with it, and a run
//! counts it as its own, so ms/frame and the benchmark's fps still include extraction.
//!
//! Layout: the magic, then a postcard payload (`FeaturesFile`): the version, the camera and
//! ORB settings the features were extracted with, the frames' time stamps and one record per
//! frame.

use super::tum::FrameSource;
use crate::components::preprocess::{FeatureGrid, Measurement, Preprocessor};
use crate::config::{CameraConfig, OrbConfig};
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::Path;
use std::time::Instant;

const MAGIC: &[u8; 16] = b"homing-features\0";
/// 2: measurements keep the depth grid (`Measurement::surface`).
const VERSION: u32 = 2;

/// One frame's extraction.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Extracted {
    pub m: Measurement,
    /// How long the extraction took when the file was written (ms).
    pub ms: f64,
    /// FAST's low threshold found key points (counted in the run log's weak passes).
    pub weak: bool,
}

#[derive(Serialize, Deserialize)]
struct FeaturesFile {
    version: u32,
    camera: CameraConfig,
    orb: OrbConfig,
    stamps: Vec<f64>,
    frames: Vec<Extracted>,
}

/// Extracts every frame of `source` as a run with `camera` and `orb` would (on `jobs`
/// threads, one extractor each) and writes them to `path` through a temporary file.
pub fn write(
    path: &Path,
    source: &(dyn FrameSource + Sync),
    camera: &CameraConfig,
    orb: &OrbConfig,
    jobs: usize,
) -> Result<()> {
    let n = source.len();
    if n == 0 {
        return Err(Error::invalid("no frames to extract"));
    }
    let jobs = jobs.clamp(1, n);
    // Frame i on thread i % jobs; each extraction only depends on its own image.
    let parts: Vec<Result<Vec<(usize, Extracted)>>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..jobs)
            .map(|j| {
                s.spawn(move || {
                    let mut pre = Preprocessor::new(camera, orb)?;
                    let mut out = Vec::new();
                    for i in (j..n).step_by(jobs) {
                        let frame = source.load(i)?;
                        let weak_before = pre.weak_passes;
                        let t = Instant::now();
                        let m = pre.process(&frame)?;
                        let ms = t.elapsed().as_secs_f64() * 1e3;
                        let weak = pre.weak_passes > weak_before;
                        out.push((i, Extracted { m, ms, weak }));
                    }
                    Ok(out)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(Error::invalid("feature extraction panicked")))
            })
            .collect()
    });
    let mut frames: Vec<Option<Extracted>> = vec![None; n];
    for part in parts {
        for (i, e) in part? {
            frames[i] = Some(e);
        }
    }
    let file = FeaturesFile {
        version: VERSION,
        camera: camera.clone(),
        orb: orb.clone(),
        stamps: (0..n).map(|i| source.timestamp(i)).collect(),
        frames: frames
            .into_iter()
            .map(|f| f.expect("every frame"))
            .collect(),
    };
    let payload = postcard::to_stdvec(&file)
        .map_err(|e| Error::file(path, format!("cannot encode features: {e}")))?;
    // A scratch file, rebuilt by every benchmark: not synced to disk.
    super::write_via_temporary(path, false, |w| {
        w.write_all(MAGIC)
            .and_then(|_| w.write_all(&payload))
            .map_err(|e| Error::file(path, format!("cannot write: {e}")))
    })
}

/// A file written by [`write()`], checked against the run that reads it.
#[derive(Debug)]
pub struct Features {
    /// Taken out as the run delivers them (each unperturbed frame once).
    frames: Vec<Option<Extracted>>,
    /// The image size, for the key-point grids.
    size: (u32, u32),
}

impl Features {
    /// Reads `path` as the features of `source` extracted with `camera` and `orb`: the frame
    /// count, every time stamp and the settings must match. A stale or foreign file is an
    /// error naming it, never features of other images.
    pub fn open(
        path: &Path,
        source: &dyn FrameSource,
        camera: &CameraConfig,
        orb: &OrbConfig,
    ) -> Result<Self> {
        let bad = |msg: String| Error::file(path, msg);
        let bytes = std::fs::read(path).map_err(|e| bad(format!("cannot read: {e}")))?;
        if bytes.len() < MAGIC.len() || &bytes[..MAGIC.len()] != MAGIC {
            return Err(bad("is not a features file (wrong magic)".into()));
        }
        let file: FeaturesFile = postcard::from_bytes(&bytes[MAGIC.len()..])
            .map_err(|e| bad(format!("is truncated or corrupt: {e}")))?;
        if file.version != VERSION {
            return Err(bad(format!(
                "features version {}; this build reads {VERSION}",
                file.version
            )));
        }
        if file.camera != *camera || file.orb != *orb {
            return Err(bad(
                "was extracted with other camera or ORB settings than this run's".into(),
            ));
        }
        if file.stamps.len() != source.len() || file.frames.len() != source.len() {
            return Err(bad(format!(
                "holds {} frames; the sequence has {}",
                file.frames.len(),
                source.len()
            )));
        }
        for (i, &t) in file.stamps.iter().enumerate() {
            if t.to_bits() != source.timestamp(i).to_bits() {
                return Err(bad(format!(
                    "frame {i} is stamped {t:.6}; the sequence's is {:.6} (a file of another \
                     sequence, or of an older version of it)",
                    source.timestamp(i)
                )));
            }
        }
        for (i, e) in file.frames.iter().enumerate() {
            if e.m.frame != i
                || e.m.descriptors.len() != e.m.keypoints.len()
                || e.m.depth.len() != e.m.keypoints.len()
            {
                return Err(bad(format!("frame {i}: inconsistent record (corrupt)")));
            }
        }
        Ok(Self {
            frames: file.frames.into_iter().map(Some).collect(),
            size: (camera.width, camera.height),
        })
    }

    /// Frame `i`'s extraction, taken out of the file (`None` once taken). The grid's buckets
    /// are not stored: they are rebuilt from the key points here, for frames a run uses.
    pub fn take(&mut self, i: usize) -> Option<Extracted> {
        let mut e = self.frames.get_mut(i)?.take()?;
        e.m.grid = FeatureGrid::new(self.size.0, self.size.1, &e.m.keypoints);
        Some(e)
    }
}
