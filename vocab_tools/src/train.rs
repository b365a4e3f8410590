//! `vocab-tools train`: a bag-of-words vocabulary for homing's place recognition, from
//! generic photos (never from the sequences it is evaluated on).
//!
//! Each image is read (JPEG or PNG, any size), its ORB features extracted by homing's own
//! [`Preprocessor`] with the config's `[orb]` settings (a pinhole camera of the image's size, no
//! distortion), and the tree trained by [`Vocabulary::train`].

use homing::components::loop_detector::vocabulary::Vocabulary;
use homing::components::preprocess::{Descriptor, Preprocessor};
use homing::config::{CameraConfig, OrbConfig};
use homing::io::tum::Frame;
use homing::{Error, Result};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

#[derive(Debug, Clone)]
pub struct TrainSummary {
    pub images: usize,
    pub skipped: Vec<(PathBuf, String)>,
    pub descriptors: usize,
    pub words: usize,
    pub seconds_extract: f64,
    pub seconds_train: f64,
}

/// Image files (jpg, jpeg, png, any case) under `dirs`, recursively, sorted by path.
pub fn image_files(dirs: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    let mut stack: Vec<PathBuf> = dirs.to_vec();
    while let Some(d) = stack.pop() {
        if d.is_file() {
            out.push(d);
            continue;
        }
        let rd = std::fs::read_dir(&d).map_err(|e| Error::file(&d, format!("cannot list: {e}")))?;
        for e in rd {
            let p = e
                .map_err(|e| Error::file(&d, format!("cannot list: {e}")))?
                .path();
            if p.is_dir() {
                stack.push(p);
            } else if p
                .extension()
                .and_then(|x| x.to_str())
                .is_some_and(|x| matches!(x.to_ascii_lowercase().as_str(), "jpg" | "jpeg" | "png"))
            {
                out.push(p);
            }
        }
    }
    out.sort();
    Ok(out)
}

/// A pinhole camera of the image's size for the preprocessor (focal length = width).
fn camera(width: u32, height: u32) -> CameraConfig {
    CameraConfig {
        name: "training image".into(),
        fx: width as f64,
        fy: width as f64,
        cx: width as f64 / 2.0,
        cy: height as f64 / 2.0,
        k1: 0.0,
        k2: 0.0,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
        width,
        height,
        depth_scale: 5000.0,
        fps: 30.0,
        readout_s: 0.0,
        virtual_baseline_m: homing::config::default_virtual_baseline(),
    }
}

/// ORB descriptors of one image file, as homing extracts them.
pub fn image_descriptors(
    path: &Path,
    orb: &OrbConfig,
    pre: &mut BTreeMap<(u32, u32), Preprocessor>,
) -> Result<Vec<Descriptor>> {
    let img = image::open(path)
        .map_err(|e| Error::file(path, format!("cannot read image: {e}")))?
        .to_rgb8();
    let (w, h) = img.dimensions();
    if w < 64 || h < 64 {
        return Err(Error::file(path, format!("image too small ({w}x{h})")));
    }
    let p = match pre.entry((w, h)) {
        std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
        std::collections::btree_map::Entry::Vacant(e) => {
            e.insert(Preprocessor::new(&camera(w, h), orb)?)
        }
    };
    let frame = Frame {
        index: 0,
        t: 0.0,
        rgb: img,
        depth: None,
    };
    Ok(p.process(&frame)?.descriptors)
}

/// Extracts every image's descriptors and trains the vocabulary. Unreadable images are
/// skipped and listed. `progress` gets (done, total) after each image.
pub fn train(
    files: &[PathBuf],
    orb: &OrbConfig,
    k: u32,
    levels: u32,
    seed: u64,
    mut progress: impl FnMut(usize, usize),
) -> Result<(Vocabulary, TrainSummary)> {
    let t0 = std::time::Instant::now();
    let mut pre = BTreeMap::new();
    let mut images = Vec::new();
    let mut skipped = Vec::new();
    for (i, f) in files.iter().enumerate() {
        match image_descriptors(f, orb, &mut pre) {
            Ok(d) => images.push(d),
            Err(e) => skipped.push((f.clone(), e.to_string())),
        }
        progress(i + 1, files.len());
    }
    let seconds_extract = t0.elapsed().as_secs_f64();
    let t1 = std::time::Instant::now();
    let v = Vocabulary::train(&images, k, levels, seed)?;
    let summary = TrainSummary {
        images: images.len(),
        skipped,
        descriptors: images.iter().map(Vec::len).sum(),
        words: v.n_words(),
        seconds_extract,
        seconds_train: t1.elapsed().as_secs_f64(),
    };
    Ok((v, summary))
}
