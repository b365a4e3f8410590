//! `vocab-tools extract`: the ORB descriptors of a TUM sequence, exactly as `homing run`
//! computes them (same config loading, camera choice, colour/depth association and
//! [`Preprocessor`]).

use crate::descfile::{DescriptorFile, FrameDescriptors};
use homing::components::preprocess::Preprocessor;
use homing::config::{Config, resolve_camera};
use homing::io::tum::{FrameSource, TumSequence};
use homing::outputs::{Timing, describe_camera};
use homing::{Error, Result};
use std::path::Path;

#[derive(Debug, Clone)]
pub struct ExtractSummary {
    pub camera: String,
    /// Frames of the sequence (after colour/depth association).
    pub sequence_frames: usize,
    pub frames: usize,
    pub descriptors: usize,
    pub min_per_frame: usize,
    pub max_per_frame: usize,
    pub median_ms_per_frame: f64,
}

/// Extracts every `every`-th frame of the sequence (starting with the first).
/// `progress` is called after each extracted frame with (done, total).
pub fn extract(
    sequence: &Path,
    config_path: Option<&Path>,
    every: usize,
    mut progress: impl FnMut(usize, usize),
) -> Result<(DescriptorFile, ExtractSummary)> {
    if every == 0 {
        return Err(Error::invalid("--every must be at least 1"));
    }
    let config = match config_path {
        Some(p) => Config::load(p)?,
        None => Config::default(),
    };
    let (camera, source) = resolve_camera(&config, config_path, sequence)?;
    let seq = TumSequence::open(
        sequence,
        camera.width,
        camera.height,
        camera.depth_scale,
        config.sequence.max_association_dt,
        config.sequence.mono,
    )?;
    let mut pre = Preprocessor::new(&camera, &config.orb)?;
    let picked: Vec<usize> = (0..seq.len()).step_by(every).collect();
    let mut timing = Timing::default();
    let mut frames = Vec::with_capacity(picked.len());
    for (k, &i) in picked.iter().enumerate() {
        let frame = seq.load(i)?;
        let m = timing.time("extract", || pre.process(&frame))?;
        frames.push(FrameDescriptors {
            t: frame.t,
            descriptors: m.descriptors,
        });
        progress(k + 1, picked.len());
    }
    let file = DescriptorFile { frames };
    let sizes = file.frames.iter().map(|f| f.descriptors.len());
    let summary = ExtractSummary {
        camera: describe_camera(&camera, &source),
        sequence_frames: seq.len(),
        frames: file.frames.len(),
        descriptors: file.n_descriptors(),
        min_per_frame: sizes.clone().min().unwrap_or(0),
        max_per_frame: sizes.max().unwrap_or(0),
        median_ms_per_frame: timing.summary().get("extract").map_or(0.0, |s| s.median_ms),
    };
    Ok((file, summary))
}
