//! Preprocess (paper Table I): image (+ depth) → Measurement.
//!
//! ORB keypoints and descriptors come from OpenCV. OpenCV's ORB keeps the strongest corners of
//! each pyramid level, which lets one highly textured corner take most of the budget; like
//! ORB-SLAM we therefore distribute per level over a grid of cells, round-robin by response,
//! and use the lower FAST threshold only in cells where the initial one finds nothing.
//! Keypoints are then undistorted with the camera model and get the depth under them.

use crate::config::{CameraConfig, OrbConfig};
use crate::error::{Error, Result};
use crate::io::tum::Frame;
use nalgebra::Vector2;
use opencv::core::{self as cv, KeyPoint, Mat, Point2f, Ptr, Vector};
use opencv::features2d::{ORB, ORB_ScoreType};
use opencv::prelude::*;

/// A 256-bit ORB descriptor.
pub type Descriptor = [u8; 32];

/// Hamming distance between two ORB descriptors.
#[inline]
pub fn hamming(a: &Descriptor, b: &Descriptor) -> u32 {
    let mut d = 0;
    for k in 0..4 {
        let x = u64::from_le_bytes(a[8 * k..8 * k + 8].try_into().expect("8 bytes"));
        let y = u64::from_le_bytes(b[8 * k..8 * k + 8].try_into().expect("8 bytes"));
        d += (x ^ y).count_ones();
    }
    d
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Keypoint {
    /// Position in the raw (distorted) image, level-0 pixels.
    pub raw: Vector2<f64>,
    /// Undistorted position, level-0 pixels (what geometry uses).
    pub un: Vector2<f64>,
    /// Pyramid level.
    pub octave: u8,
    /// Orientation in degrees (OpenCV convention).
    pub angle: f32,
    pub response: f32,
}

/// What the front end sees of a frame.
#[derive(Debug, Clone)]
pub struct Measurement {
    pub frame: usize,
    pub t: f64,
    pub keypoints: Vec<Keypoint>,
    pub descriptors: Vec<Descriptor>,
    /// Depth in metres under each keypoint; 0 = none (no reading, or monocular).
    pub depth: Vec<f32>,
    pub grid: FeatureGrid,
}

impl Measurement {
    pub fn len(&self) -> usize {
        self.keypoints.len()
    }
    pub fn is_empty(&self) -> bool {
        self.keypoints.is_empty()
    }
    /// Keypoints with a valid depth reading.
    pub fn n_with_depth(&self) -> usize {
        self.depth.iter().filter(|&&d| d > 0.0).count()
    }
}

/// Buckets keypoint indices by undistorted position, for fast projection search.
#[derive(Debug, Clone)]
pub struct FeatureGrid {
    cols: usize,
    rows: usize,
    cell: f64,
    cells: Vec<Vec<u32>>,
}

impl FeatureGrid {
    pub fn new(width: u32, height: u32, keypoints: &[Keypoint]) -> Self {
        let cell = 16.0;
        let cols = (width as f64 / cell).ceil() as usize;
        let rows = (height as f64 / cell).ceil() as usize;
        let mut cells = vec![Vec::new(); cols * rows];
        for (i, k) in keypoints.iter().enumerate() {
            let cx = (k.un.x / cell).floor();
            let cy = (k.un.y / cell).floor();
            if cx >= 0.0 && cy >= 0.0 && (cx as usize) < cols && (cy as usize) < rows {
                cells[cy as usize * cols + cx as usize].push(i as u32);
            }
        }
        Self {
            cols,
            rows,
            cell,
            cells,
        }
    }

    /// Indices of keypoints within `r` pixels of (x, y) whose octave is in [min, max].
    pub fn in_area(
        &self,
        kps: &[Keypoint],
        x: f64,
        y: f64,
        r: f64,
        min: u8,
        max: u8,
    ) -> Vec<usize> {
        let mut out = Vec::new();
        let c0 = ((x - r) / self.cell).floor().max(0.0) as usize;
        let r0 = ((y - r) / self.cell).floor().max(0.0) as usize;
        let c1 = (((x + r) / self.cell).floor() as isize).min(self.cols as isize - 1);
        let r1 = (((y + r) / self.cell).floor() as isize).min(self.rows as isize - 1);
        if c1 < 0 || r1 < 0 {
            return out;
        }
        for row in r0..=r1 as usize {
            for col in c0..=c1 as usize {
                for &i in &self.cells[row * self.cols + col] {
                    let k = &kps[i as usize];
                    if k.octave < min || k.octave > max {
                        continue;
                    }
                    if (k.un.x - x).abs() <= r && (k.un.y - y).abs() <= r {
                        out.push(i as usize);
                    }
                }
            }
        }
        out
    }
}

/// What projection searches need to know of the camera: intrinsics, image size and the ORB
/// pyramid. Shared by the tracker and the map merger.
#[derive(Debug, Clone)]
pub struct ImageGeometry {
    pub intr: crate::optim::Intrinsics,
    pub width: f64,
    pub height: f64,
    pub scale_factor: f64,
    pub n_levels: u32,
    /// Scale of each pyramid level relative to level 0.
    pub scales: Vec<f64>,
}

impl ImageGeometry {
    pub fn new(
        intr: crate::optim::Intrinsics,
        width: u32,
        height: u32,
        scale_factor: f64,
        n_levels: u32,
    ) -> Self {
        Self {
            intr,
            width: width as f64,
            height: height as f64,
            scale_factor,
            n_levels,
            scales: (0..n_levels).map(|l| scale_factor.powi(l as i32)).collect(),
        }
    }

    /// Pixel of a camera-frame point, if it is in front of the camera and inside the image.
    pub fn project_in_image(&self, p_c: &nalgebra::Vector3<f64>) -> Option<Vector2<f64>> {
        let uv = self.intr.project(p_c)?;
        (uv.x >= 0.0 && uv.y >= 0.0 && uv.x < self.width && uv.y < self.height).then_some(uv)
    }

    /// Pyramid level at which a point with scale-invariance limit `max_distance` is expected
    /// to be detected from `distance` (ORB-SLAM's PredictScale).
    pub fn predicted_level(&self, max_distance: f64, distance: f64) -> usize {
        ((max_distance / distance).ln() / self.scale_factor.ln())
            .ceil()
            .clamp(0.0, (self.n_levels - 1) as f64) as usize
    }
}

/// A detected key point before distribution.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    x: f32,
    y: f32,
    size: f32,
    angle: f32,
    response: f32,
    octave: i32,
    /// Found only with the low FAST threshold.
    weak: bool,
}

/// ORB extraction + undistortion + depth lookup.
pub struct Preprocessor {
    orb_ini: Ptr<ORB>,
    orb_min: Ptr<ORB>,
    cfg: OrbConfig,
    camera: CameraConfig,
    k: Mat,
    dist: Mat,
    /// Scale of each pyramid level relative to level 0.
    pub scales: Vec<f64>,
    /// Frames on which the low-threshold pass ran (reported in the run summary's log).
    pub weak_passes: usize,
}

fn cv_err(what: &str) -> impl Fn(opencv::Error) -> Error + '_ {
    move |e| Error::invalid(format!("OpenCV {what}: {e}"))
}

impl Preprocessor {
    pub fn new(camera: &CameraConfig, cfg: &OrbConfig) -> Result<Self> {
        let make = |fast: u32| {
            ORB::create(
                // Generous budget: the grid distribution below picks the final set.
                (cfg.n_features * 6) as i32,
                cfg.scale_factor as f32,
                cfg.n_levels as i32,
                19,
                0,
                2,
                ORB_ScoreType::HARRIS_SCORE,
                31,
                fast as i32,
            )
            .map_err(cv_err("ORB::create"))
        };
        let k = Mat::from_slice_2d(&[
            [camera.fx, 0.0, camera.cx],
            [0.0, camera.fy, camera.cy],
            [0.0, 0.0, 1.0],
        ])
        .map_err(cv_err("camera matrix"))?;
        let dist = Mat::from_slice(&[camera.k1, camera.k2, camera.p1, camera.p2, camera.k3])
            .map_err(cv_err("distortion"))?
            .try_clone()
            .map_err(cv_err("distortion"))?;
        let scales = (0..cfg.n_levels)
            .map(|l| cfg.scale_factor.powi(l as i32))
            .collect();
        Ok(Self {
            orb_ini: make(cfg.ini_fast_threshold)?,
            orb_min: make(cfg.min_fast_threshold)?,
            cfg: cfg.clone(),
            camera: camera.clone(),
            k,
            dist,
            scales,
            weak_passes: 0,
        })
    }

    /// Grayscale conversion (ITU-R 601 weights, as OpenCV's RGB2GRAY).
    fn gray(frame: &Frame) -> Result<Mat> {
        let gray = image::imageops::grayscale(&frame.rgb);
        let (w, h) = gray.dimensions();
        let m = Mat::new_rows_cols_with_data(h as i32, w as i32, gray.as_raw())
            .map_err(cv_err("gray image"))?;
        m.try_clone().map_err(cv_err("gray image"))
    }

    pub fn process(&mut self, frame: &Frame) -> Result<Measurement> {
        let img = Self::gray(frame)?;
        let strong = self.detect(&img, false)?;
        let mut chosen = self.distribute(&strong, &[]);
        // The low FAST threshold is for poorly textured images: run it (it costs as much as
        // the first pass) only when the first cannot fill the budget or leaves many cells empty.
        if chosen.len() < self.cfg.n_features as usize || self.empty_cell_share(&strong) > 0.25 {
            let weak = self.detect(&img, true)?;
            chosen = self.distribute(&strong, &weak);
            self.weak_passes += 1;
        }
        let mut kps = Vector::<KeyPoint>::with_capacity(chosen.len());
        for c in &chosen {
            kps.push(
                KeyPoint::new_coords(c.x, c.y, c.size, c.angle, c.response, c.octave, -1)
                    .map_err(cv_err("KeyPoint"))?,
            );
        }
        let mut desc = Mat::default();
        self.orb_ini
            .compute(&img, &mut kps, &mut desc)
            .map_err(cv_err("ORB compute"))?;
        let kps = kps.to_vec();
        let mut descriptors = Vec::with_capacity(kps.len());
        for r in 0..desc.rows() {
            let row = desc.at_row::<u8>(r).map_err(cv_err("descriptor row"))?;
            descriptors.push(<Descriptor>::try_from(row).map_err(|_| {
                Error::invalid("OpenCV ORB returned descriptors that are not 32 bytes")
            })?);
        }
        let un = self.undistort(&kps)?;
        let keypoints: Vec<Keypoint> = kps
            .iter()
            .zip(&un)
            .map(|(k, u)| Keypoint {
                raw: Vector2::new(k.pt().x as f64, k.pt().y as f64),
                un: *u,
                octave: k.octave().clamp(0, 255) as u8,
                angle: k.angle(),
                response: k.response(),
            })
            .collect();
        let depth = match &frame.depth {
            Some(d) => keypoints
                .iter()
                .map(|k| {
                    let (x, y) = (k.raw.x.round(), k.raw.y.round());
                    if x >= 0.0 && y >= 0.0 && x < d.width as f64 && y < d.height as f64 {
                        d.get(x as u32, y as u32)
                    } else {
                        0.0
                    }
                })
                .collect(),
            None => vec![0.0; keypoints.len()],
        };
        let grid = FeatureGrid::new(self.camera.width, self.camera.height, &keypoints);
        Ok(Measurement {
            frame: frame.index,
            t: frame.t,
            keypoints,
            descriptors,
            depth,
            grid,
        })
    }

    /// ORB detection, copied out of OpenCV once into plain structs (OpenCV key points are
    /// boxed FFI objects here; copying thousands of them costs more than detecting them).
    fn detect(&mut self, img: &Mat, weak: bool) -> Result<Vec<Candidate>> {
        let mut kps = Vector::<KeyPoint>::new();
        let orb = if weak {
            &mut self.orb_min
        } else {
            &mut self.orb_ini
        };
        orb.detect(img, &mut kps, &cv::no_array())
            .map_err(cv_err("ORB detect"))?;
        Ok(kps
            .iter()
            .map(|k| Candidate {
                x: k.pt().x,
                y: k.pt().y,
                size: k.size(),
                angle: k.angle(),
                response: k.response(),
                octave: k.octave(),
                weak,
            })
            .collect())
    }

    /// Per level: cells of ~32 px (at that level); round-robin over cells by response until the
    /// level's share of `n_features` (geometric in the scale, as ORB-SLAM) is reached. Weak
    /// (low FAST threshold) keypoints are only used in cells with no strong one.
    fn distribute(&self, strong: &[Candidate], weak: &[Candidate]) -> Vec<Candidate> {
        let n_levels = self.cfg.n_levels as usize;
        let f = 1.0 / self.cfg.scale_factor;
        let first = self.cfg.n_features as f64 * (1.0 - f) / (1.0 - f.powi(n_levels as i32));
        let mut out: Vec<Candidate> = Vec::with_capacity(self.cfg.n_features as usize);
        for level in 0..n_levels {
            let target = if level + 1 == n_levels {
                (self.cfg.n_features as usize).saturating_sub(out.len())
            } else {
                (first * f.powi(level as i32)).round() as usize
            };
            let cell = 32.0 * self.scales[level];
            let cols = (self.camera.width as f64 / cell).ceil().max(1.0) as usize;
            let rows = (self.camera.height as f64 / cell).ceil().max(1.0) as usize;
            let cell_of = |k: &Candidate| {
                let c = ((k.x as f64 / cell) as usize).min(cols - 1);
                let r = ((k.y as f64 / cell) as usize).min(rows - 1);
                r * cols + c
            };
            let mut cells: Vec<Vec<Candidate>> = vec![Vec::new(); cols * rows];
            for k in strong.iter().filter(|k| k.octave as usize == level) {
                cells[cell_of(k)].push(*k);
            }
            for k in weak.iter().filter(|k| k.octave as usize == level) {
                let c = cell_of(k);
                // Weak key points only where the initial threshold found nothing.
                if cells[c].first().is_none_or(|s| s.weak) {
                    cells[c].push(*k);
                }
            }
            for c in cells.iter_mut() {
                c.sort_by(|a, b| b.response.total_cmp(&a.response));
            }
            let mut taken = 0;
            let mut round = 0;
            while taken < target {
                let mut any = false;
                for c in &cells {
                    if let Some(k) = c.get(round) {
                        any = true;
                        if taken < target {
                            out.push(*k);
                            taken += 1;
                        }
                    }
                }
                if !any {
                    break;
                }
                round += 1;
            }
        }
        // Deterministic order: by level, then position.
        out.sort_by(|a, b| {
            (a.octave, a.y, a.x)
                .partial_cmp(&(b.octave, b.y, b.x))
                .unwrap_or(std::cmp::Ordering::Equal)
        });
        out
    }

    /// Share of 32-px level-0 cells without a keypoint.
    fn empty_cell_share(&self, kps: &[Candidate]) -> f64 {
        let cols = (self.camera.width as usize).div_ceil(32);
        let rows = (self.camera.height as usize).div_ceil(32);
        let mut hit = vec![false; cols * rows];
        for k in kps.iter().filter(|k| k.octave == 0) {
            let c = ((k.x / 32.0) as usize).min(cols - 1);
            let r = ((k.y / 32.0) as usize).min(rows - 1);
            hit[r * cols + c] = true;
        }
        hit.iter().filter(|&&h| !h).count() as f64 / hit.len() as f64
    }

    fn undistort(&self, kps: &[KeyPoint]) -> Result<Vec<Vector2<f64>>> {
        if !self.camera.has_distortion() || kps.is_empty() {
            return Ok(kps
                .iter()
                .map(|k| Vector2::new(k.pt().x as f64, k.pt().y as f64))
                .collect());
        }
        let src = Vector::<Point2f>::from_iter(kps.iter().map(|k| k.pt()));
        let mut dst = Vector::<Point2f>::new();
        opencv::calib3d::undistort_points(
            &src,
            &mut dst,
            &self.k,
            &self.dist,
            &cv::no_array(),
            &self.k,
        )
        .map_err(cv_err("undistortPoints"))?;
        Ok(dst
            .iter()
            .map(|p| Vector2::new(p.x as f64, p.y as f64))
            .collect())
    }
}
