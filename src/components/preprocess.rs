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

/// The nearest of `candidates` (index, descriptor) to `d`: its index and distance, when it is
/// within `max_distance` and nearer than `ratio` times the second nearest (Lowe's test; passed
/// when there is no second).
pub fn nearest_descriptor<'a>(
    d: &Descriptor,
    candidates: impl IntoIterator<Item = (usize, &'a Descriptor)>,
    max_distance: u32,
    ratio: f64,
) -> Option<(usize, u32)> {
    let (mut b1, mut b2, mut bi) = (u32::MAX, u32::MAX, usize::MAX);
    for (i, c) in candidates {
        let h = hamming(d, c);
        if h < b1 {
            (b2, b1, bi) = (b1, h, i);
        } else if h < b2 {
            b2 = h;
        }
    }
    (bi != usize::MAX && b1 <= max_distance && (b1 as f64) < ratio * b2 as f64).then_some((bi, b1))
}

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

/// Matches between two views by searching, for each key point `i` of `a`, the key points of `b`
/// within a radius of a pixel (`area(i)`: where and how far; `None` skips it) at a pyramid level
/// within one of `i`'s, by descriptor ([`nearest_descriptor`]). A key point of `b` keeps only
/// its nearest match, and matches whose change of orientation disagrees with the dominant ones
/// are dropped ([`dominant_rotation_bins`], as ORB-SLAM). Pairs `(i in a, j in b)`, by `j`.
pub fn match_in_areas(
    a: &Measurement,
    b: &Measurement,
    area: impl Fn(usize) -> Option<(Vector2<f64>, f64)>,
    max_distance: u32,
    ratio: f64,
) -> Vec<(usize, usize)> {
    // Key point of `b` → (distance, key point of `a`).
    let mut best: Vec<Option<(u32, usize)>> = vec![None; b.len()];
    for (i, ka) in a.keypoints.iter().enumerate() {
        let Some((p, r)) = area(i) else { continue };
        let near = b.grid.in_area(
            &b.keypoints,
            p.x,
            p.y,
            r,
            ka.octave.saturating_sub(1),
            ka.octave.saturating_add(1),
        );
        let Some((j, d)) = nearest_descriptor(
            &a.descriptors[i],
            near.into_iter().map(|j| (j, &b.descriptors[j])),
            max_distance,
            ratio,
        ) else {
            continue;
        };
        if best[j].is_none_or(|(d0, _)| d < d0) {
            best[j] = Some((d, i));
        }
    }
    rotation_consistent_pairs(&best, &a.keypoints, &b.keypoints)
}

/// The pairs `(i in a, j in b)` of `best` (per key point `j` of `b`: its match's distance and
/// key point `i` of `a`), by `j`, without those whose change of orientation disagrees with the
/// dominant ones ([`dominant_rotation_bins`], as ORB-SLAM).
pub fn rotation_consistent_pairs(
    best: &[Option<(u32, usize)>],
    a: &[Keypoint],
    b: &[Keypoint],
) -> Vec<(usize, usize)> {
    let mut pairs: Vec<(usize, usize)> = best
        .iter()
        .enumerate()
        .filter_map(|(j, x)| x.map(|(_, i)| (i, j)))
        .collect();
    let bin = |&(i, j): &(usize, usize)| rotation_bin(a[i].angle, b[j].angle);
    let keep = dominant_rotation_bins(pairs.iter().map(bin));
    pairs.retain(|x| keep.contains(&bin(x)));
    pairs
}

/// Bins of the rotation-consistency histogram (ORB-SLAM: 30 bins of 12°).
pub const ROTATION_BINS: usize = 30;

/// The histogram bin of the change of keypoint orientation `a1 - a2` (degrees).
pub fn rotation_bin(a1: f32, a2: f32) -> usize {
    let d = (a1 - a2).rem_euclid(360.0);
    ((d / 360.0 * ROTATION_BINS as f32) as usize).min(ROTATION_BINS - 1)
}

/// Rotation consistency (ORB-SLAM): between two views every true match turns by about the same
/// angle, so only matches in the three dominant bins (each with at least a tenth of the
/// largest bin's votes) are kept. Returns those bins; ties go to the lower bin.
pub fn dominant_rotation_bins(bins: impl IntoIterator<Item = usize>) -> Vec<usize> {
    let mut hist = [0usize; ROTATION_BINS];
    for b in bins {
        hist[b] += 1;
    }
    let mut order: Vec<usize> = (0..ROTATION_BINS).collect();
    order.sort_by(|a, b| hist[*b].cmp(&hist[*a]).then(a.cmp(b)));
    let max = hist[order[0]];
    order[..3]
        .iter()
        .copied()
        .filter(|&b| hist[b] > 0 && hist[b] as f64 >= 0.1 * max as f64)
        .collect()
}

#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
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
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Measurement {
    pub frame: usize,
    pub t: f64,
    pub keypoints: Vec<Keypoint>,
    pub descriptors: Vec<Descriptor>,
    /// Depth in metres under each keypoint; 0 = none (no reading, or monocular).
    pub depth: Vec<f32>,
    pub grid: FeatureGrid,
    /// The depth image sampled on a regular [`SURFACE_COLS`] × [`SURFACE_ROWS`] grid, row
    /// by row, in millimetres (0 = no reading): the surfaces a keyframe saw, for depth
    /// registration between keyframes that share no key point (`crate::components::depth_registration`).
    /// Empty without depth. The rays of the samples are [`Preprocessor::surface_rays`].
    pub surface: Vec<u16>,
}

/// Columns of the depth grid kept per frame ([`Measurement::surface`]): about 4 000
/// samples, enough for a plane in every 15 cm cell of a wall 2 m away at 640 × 480 or 320 × 240.
pub const SURFACE_COLS: usize = 80;
/// Rows of the depth grid kept per frame.
pub const SURFACE_ROWS: usize = 60;

/// The pixel (raw image, level 0) of grid sample (`col`, `row`) in a `width` × `height`
/// image: the centre of the grid cell.
pub fn surface_pixel(col: usize, row: usize, width: u32, height: u32) -> Vector2<f64> {
    Vector2::new(
        (col as f64 + 0.5) * width as f64 / SURFACE_COLS as f64 - 0.5,
        (row as f64 + 0.5) * height as f64 / SURFACE_ROWS as f64 - 0.5,
    )
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

    /// Test fixture: keypoints at the undistorted pixels `uvs` of a 640 × 480 image (level 0,
    /// angle `angle`), all at depth `depth` (0: monocular), with the given descriptors.
    #[cfg(test)]
    pub(crate) fn synthetic(
        frame: usize,
        uvs: impl IntoIterator<Item = nalgebra::Vector2<f64>>,
        angle: f32,
        depth: f32,
        descriptors: Vec<Descriptor>,
    ) -> Self {
        let keypoints: Vec<Keypoint> = uvs
            .into_iter()
            .map(|uv| Keypoint {
                raw: uv,
                un: uv,
                octave: 0,
                angle,
                response: 1.0,
            })
            .collect();
        Measurement {
            frame,
            t: frame as f64,
            grid: FeatureGrid::new(640, 480, &keypoints),
            depth: vec![depth; keypoints.len()],
            descriptors,
            keypoints,
            surface: Vec::new(),
        }
    }
}

/// Buckets keypoint indices by undistorted position, for fast projection search. Saved maps
/// keep only the image size; the buckets are rebuilt on load.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct FeatureGrid {
    cols: usize,
    rows: usize,
    cell: f64,
    #[serde(skip)]
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

    /// The image size the grid covers (in whole cells).
    pub fn size(&self) -> (u32, u32) {
        (
            (self.cols as f64 * self.cell) as u32,
            (self.rows as f64 * self.cell) as u32,
        )
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
    /// Rolling-shutter readout time, first to last row (seconds; 0 = global shutter).
    pub readout_s: f64,
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
            readout_s: 0.0,
        }
    }

    /// The same geometry for a rolling-shutter camera.
    pub fn with_readout(mut self, readout_s: f64) -> Self {
        self.readout_s = readout_s;
        self
    }

    /// Exposure time of image row `y` relative to the frame's stamp (the middle row).
    pub fn row_time(&self, y: f64) -> f64 {
        (y / self.height - 0.5) * self.readout_s
    }

    /// Camera motion between the frame's stamp and the exposure of row `y`, for a camera
    /// moving with world-to-camera twist `twist` (per second): the row sees the world from
    /// `shutter · T_cw`. Identity for a global shutter or a still camera.
    pub fn shutter(&self, twist: &nalgebra::Vector6<f64>, y: f64) -> nalgebra::Isometry3<f64> {
        if self.readout_s == 0.0 || *twist == nalgebra::Vector6::zeros() {
            nalgebra::Isometry3::identity()
        } else {
            crate::optim::se3::exp(&(twist * self.row_time(y)))
        }
    }

    /// [`ImageGeometry::project_in_image`] for a rolling-shutter camera: the point is
    /// projected with the pose of the row it lands on (one fixed-point step, plenty at
    /// the few-pixel skew of real cameras).
    pub fn project_moving(
        &self,
        pose_cw: &nalgebra::Isometry3<f64>,
        twist: &nalgebra::Vector6<f64>,
        p_w: &nalgebra::Vector3<f64>,
    ) -> Option<(Vector2<f64>, nalgebra::Vector3<f64>)> {
        let p = nalgebra::Point3::from(*p_w);
        let p_c = (pose_cw * p).coords;
        let uv = self.project_in_image(&p_c)?;
        let s = self.shutter(twist, uv.y);
        if s == nalgebra::Isometry3::identity() {
            return Some((uv, p_c));
        }
        let p_c = (s * pose_cw * p).coords;
        Some((self.project_in_image(&p_c)?, p_c))
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

/// A detected key point before distribution, in level-0 pixels.
#[derive(Debug, Clone, Copy)]
struct Candidate {
    x: f32,
    y: f32,
    /// Position at its own pyramid level (for the orientation).
    lx: f32,
    ly: f32,
    response: f32,
    octave: i32,
    /// Found only with the low FAST threshold.
    weak: bool,
}

/// ORB's patch radius (31-pixel patch): the orientation and descriptor need this margin.
const HALF_PATCH: i32 = 15;
/// Key points are detected at least this far from a level's border (ORB-SLAM's EDGE_THRESHOLD),
/// so that OpenCV's descriptor computation never drops one.
const EDGE: i32 = 19;
/// FAST needs 3 pixels around a corner; detection windows are grown by that much.
const FAST_RADIUS: i32 = 3;
/// Cell size of the low-threshold retry, in level pixels (ORB-SLAM's W = 30).
const FAST_CELL: i32 = 30;

/// ORB extraction + undistortion + depth lookup.
///
/// Detection follows ORB-SLAM rather than OpenCV's `ORB::detect`: one image pyramid, FAST with
/// the initial threshold per level, the low threshold only inside cells where the initial one
/// found nothing, orientation by intensity centroid. Only the descriptors come from OpenCV's
/// ORB (its rotated BRIEF pattern). OpenCV's detector builds its own pyramid, scores every
/// corner with Harris and would need a second full pass for the low threshold: about twice
/// the time for the same key points.
pub struct Preprocessor {
    orb: Ptr<ORB>,
    cfg: OrbConfig,
    camera: CameraConfig,
    k: Mat,
    dist: Mat,
    /// Scale of each pyramid level relative to level 0.
    pub scales: Vec<f64>,
    /// Frames on which the low-threshold FAST found key points (reported in the run log).
    pub weak_passes: usize,
    /// Precomputed row extents of the circular orientation patch (OpenCV's `umax`).
    umax: Vec<i32>,
    /// The depth-image pixel of every depth-grid sample, and its undistorted normalised
    /// image coordinates (x/z, y/z).
    surface_pixels: Vec<(u32, u32)>,
    surface_rays: Vec<Vector2<f64>>,
}

fn cv_err(what: &str) -> impl Fn(opencv::Error) -> Error + '_ {
    move |e| Error::invalid(format!("OpenCV {what}: {e}"))
}

impl Preprocessor {
    pub fn new(camera: &CameraConfig, cfg: &OrbConfig) -> Result<Self> {
        // Used for descriptors only (key points are provided), so the budget does not matter.
        let orb = ORB::create(
            cfg.n_features as i32,
            cfg.scale_factor as f32,
            cfg.n_levels as i32,
            EDGE,
            0,
            2,
            ORB_ScoreType::HARRIS_SCORE,
            2 * HALF_PATCH + 1,
            cfg.ini_fast_threshold as i32,
        )
        .map_err(cv_err("ORB::create"))?;
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
        let mut pre = Self {
            orb,
            cfg: cfg.clone(),
            camera: camera.clone(),
            k,
            dist,
            scales,
            weak_passes: 0,
            umax: patch_umax(HALF_PATCH),
            surface_pixels: Vec::new(),
            surface_rays: Vec::new(),
        };
        let pixels: Vec<Vector2<f64>> = (0..SURFACE_ROWS)
            .flat_map(|r| {
                (0..SURFACE_COLS).map(move |c| surface_pixel(c, r, camera.width, camera.height))
            })
            .collect();
        pre.surface_pixels = pixels
            .iter()
            .map(|p| (p.x.round() as u32, p.y.round() as u32))
            .collect();
        pre.surface_rays = pre
            .undistort(&pixels)?
            .iter()
            .map(|u| Vector2::new((u.x - camera.cx) / camera.fx, (u.y - camera.cy) / camera.fy))
            .collect();
        Ok(pre)
    }

    /// Undistorted normalised image coordinates (x/z, y/z) of the depth-grid samples of
    /// [`Measurement::surface`], in the same order: sample `i` at depth `d` is the point
    /// `d · (x, y, 1)` of the camera frame.
    pub fn surface_rays(&self) -> &[Vector2<f64>] {
        &self.surface_rays
    }

    /// Grayscale conversion: the `image` crate's luma, with ITU-R BT.709 weights (0.2126,
    /// 0.7152, 0.0722), not the BT.601 ones of OpenCV's RGB2GRAY and ORB-SLAM (0.299, 0.587,
    /// 0.114). Every result in the README was measured with these; changing them changes
    /// every key point's response.
    fn gray(frame: &Frame) -> Result<Mat> {
        let gray = image::imageops::grayscale(&frame.rgb);
        let (w, h) = gray.dimensions();
        let m = Mat::new_rows_cols_with_data(h as i32, w as i32, gray.as_raw())
            .map_err(cv_err("gray image"))?;
        m.try_clone().map_err(cv_err("gray image"))
    }

    /// The image pyramid as OpenCV's ORB builds it (each level resized from the previous one,
    /// sizes rounded), so that detection and OpenCV's descriptors see the same pixels.
    fn pyramid(&self, img: &Mat) -> Result<Vec<Mat>> {
        let mut levels: Vec<Mat> = vec![img.clone()];
        for l in 1..self.cfg.n_levels as usize {
            let s = self.scales[l];
            let size = cv::Size::new(
                (img.cols() as f64 / s).round() as i32,
                (img.rows() as f64 / s).round() as i32,
            );
            let mut out = Mat::default();
            opencv::imgproc::resize(
                &levels[l - 1],
                &mut out,
                size,
                0.0,
                0.0,
                opencv::imgproc::INTER_LINEAR_EXACT,
            )
            .map_err(cv_err("pyramid resize"))?;
            levels.push(out);
        }
        Ok(levels)
    }

    pub fn process(&mut self, frame: &Frame) -> Result<Measurement> {
        let img = Self::gray(frame)?;
        let pyramid = self.pyramid(&img)?;
        let mut strong = Vec::new();
        let mut weak = Vec::new();
        for (level, limg) in pyramid.iter().enumerate() {
            self.detect_level(limg, level, &mut strong, &mut weak)?;
        }
        if !weak.is_empty() {
            self.weak_passes += 1;
        }
        let chosen = self.distribute(&strong, &weak);
        let mut kps = Vector::<KeyPoint>::with_capacity(chosen.len());
        for c in &chosen {
            let level = c.octave as usize;
            let limg = &pyramid[level];
            let angle = ic_angle(limg, c.lx.round() as i32, c.ly.round() as i32, &self.umax)?;
            kps.push(
                KeyPoint::new_coords(
                    c.x,
                    c.y,
                    (2 * HALF_PATCH + 1) as f32 * self.scales[level] as f32,
                    angle,
                    c.response,
                    c.octave,
                    -1,
                )
                .map_err(cv_err("KeyPoint"))?,
            );
        }
        let mut desc = Mat::default();
        self.orb
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
        // OpenCV wants `level pixel · s` in the key points it describes (it divides by `s` and
        // rounds), but its resize aligns pixel centres: level pixel `x` is image pixel
        // `(x + 0.5)·s − 0.5`. `x·s` (ORB-SLAM's, the default) puts coarse-level points up to
        // 1.3 px up and left of the corner; `orb.pixel_centre_levels` corrects it.
        let centre = if self.cfg.pixel_centre_levels {
            0.5
        } else {
            0.0
        };
        let octave = |k: &KeyPoint| k.octave().clamp(0, 255) as u8;
        let raw: Vec<Vector2<f64>> = kps
            .iter()
            .map(|k| {
                let o = centre * (self.scales[octave(k) as usize] - 1.0);
                Vector2::new(k.pt().x as f64 + o, k.pt().y as f64 + o)
            })
            .collect();
        let un = self.undistort(&raw)?;
        let keypoints: Vec<Keypoint> = kps
            .iter()
            .zip(&un)
            .zip(&raw)
            .map(|((k, u), r)| Keypoint {
                raw: *r,
                un: *u,
                octave: octave(k),
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
        let surface = match &frame.depth {
            Some(d) => self
                .surface_pixels
                .iter()
                .map(|&(x, y)| {
                    let z = if x < d.width && y < d.height {
                        d.get(x, y)
                    } else {
                        0.0
                    };
                    if z.is_finite() && z > 0.0 {
                        (z * 1000.0).round().clamp(1.0, u16::MAX as f32) as u16
                    } else {
                        0
                    }
                })
                .collect(),
            None => Vec::new(),
        };
        let grid = FeatureGrid::new(self.camera.width, self.camera.height, &keypoints);
        Ok(Measurement {
            frame: frame.index,
            t: frame.t,
            keypoints,
            descriptors,
            depth,
            grid,
            surface,
        })
    }

    /// FAST at the initial threshold over the level's detection area; then, in every 30-px
    /// cell where it found nothing, FAST again at the low threshold (ORB-SLAM's scheme: the
    /// low threshold is for poorly textured places, not a second pass over the whole image).
    fn detect_level(
        &self,
        limg: &Mat,
        level: usize,
        strong: &mut Vec<Candidate>,
        weak: &mut Vec<Candidate>,
    ) -> Result<()> {
        let (w, h) = (limg.cols(), limg.rows());
        let (x0, y0) = (EDGE - FAST_RADIUS, EDGE - FAST_RADIUS);
        let (x1, y1) = (w - EDGE + FAST_RADIUS, h - EDGE + FAST_RADIUS);
        if x1 - x0 <= 2 * FAST_RADIUS || y1 - y0 <= 2 * FAST_RADIUS {
            return Ok(());
        }
        let scale = self.scales[level] as f32;
        let push = |out: &mut Vec<Candidate>, kps: &Vector<KeyPoint>, ox: i32, oy: i32, weak| {
            for k in kps.iter() {
                let (lx, ly) = (k.pt().x + ox as f32, k.pt().y + oy as f32);
                out.push(Candidate {
                    x: lx * scale,
                    y: ly * scale,
                    lx,
                    ly,
                    response: k.response(),
                    octave: level as i32,
                    weak,
                });
            }
        };
        let fast = |rect: cv::Rect, threshold: u32| -> Result<Vector<KeyPoint>> {
            let roi = limg.roi(rect).map_err(cv_err("FAST window"))?;
            let mut kps = Vector::<KeyPoint>::new();
            opencv::features2d::fast(&roi, &mut kps, threshold as i32, true)
                .map_err(cv_err("FAST"))?;
            Ok(kps)
        };
        let first = strong.len();
        let kps = fast(
            cv::Rect::new(x0, y0, x1 - x0, y1 - y0),
            self.cfg.ini_fast_threshold,
        )?;
        push(strong, &kps, x0, y0, false);
        // Occupancy of the retry cells by the initial threshold.
        let (iw, ih) = (x1 - x0 - 2 * FAST_RADIUS, y1 - y0 - 2 * FAST_RADIUS);
        let cols = (iw as f64 / FAST_CELL as f64).ceil().max(1.0) as i32;
        let rows = (ih as f64 / FAST_CELL as f64).ceil().max(1.0) as i32;
        let (cw, ch) = (iw as f64 / cols as f64, ih as f64 / rows as f64);
        let mut occupied = vec![false; (cols * rows) as usize];
        for c in &strong[first..] {
            let cx = (((c.lx - EDGE as f32) as f64 / cw) as i32).clamp(0, cols - 1);
            let cy = (((c.ly - EDGE as f32) as f64 / ch) as i32).clamp(0, rows - 1);
            occupied[(cy * cols + cx) as usize] = true;
        }
        for r in 0..rows {
            for c in 0..cols {
                if occupied[(r * cols + c) as usize] {
                    continue;
                }
                let cx0 = EDGE + (c as f64 * cw) as i32 - FAST_RADIUS;
                let cy0 = EDGE + (r as f64 * ch) as i32 - FAST_RADIUS;
                let cx1 = (EDGE + ((c + 1) as f64 * cw) as i32 + FAST_RADIUS).min(x1);
                let cy1 = (EDGE + ((r + 1) as f64 * ch) as i32 + FAST_RADIUS).min(y1);
                if cx1 - cx0 <= 2 * FAST_RADIUS || cy1 - cy0 <= 2 * FAST_RADIUS {
                    continue;
                }
                let kps = fast(
                    cv::Rect::new(cx0, cy0, cx1 - cx0, cy1 - cy0),
                    self.cfg.min_fast_threshold,
                )?;
                push(weak, &kps, cx0, cy0, true);
            }
        }
        Ok(())
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

    fn undistort(&self, pts: &[Vector2<f64>]) -> Result<Vec<Vector2<f64>>> {
        if !self.camera.has_distortion() || pts.is_empty() {
            return Ok(pts.to_vec());
        }
        let src =
            Vector::<Point2f>::from_iter(pts.iter().map(|p| Point2f::new(p.x as f32, p.y as f32)));
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

/// Row half-widths of the circular patch used for the orientation (OpenCV's `umax`, which makes
/// the circle symmetric so the angle does not depend on the raster direction).
fn patch_umax(half: i32) -> Vec<i32> {
    let mut umax = vec![0i32; half as usize + 2];
    let vmax = (half as f64 * std::f64::consts::FRAC_1_SQRT_2 + 1.0).floor() as i32;
    let vmin = (half as f64 * std::f64::consts::FRAC_1_SQRT_2).ceil() as i32;
    let hp2 = (half * half) as f64;
    for v in 0..=vmax {
        umax[v as usize] = (hp2 - (v * v) as f64).sqrt().round() as i32;
    }
    // Make sure the circle is symmetric.
    let mut v0 = 0;
    let mut v = half;
    while v >= vmin {
        while umax[v0 as usize] == umax[(v0 + 1) as usize] {
            v0 += 1;
        }
        umax[v as usize] = v0;
        v0 += 1;
        v -= 1;
    }
    umax
}

/// Orientation of a key point by the intensity centroid of its circular patch, in degrees
/// [0, 360) as OpenCV's ORB reports it (its descriptor rotates the pattern by this angle).
fn ic_angle(img: &Mat, x: i32, y: i32, umax: &[i32]) -> Result<f32> {
    let half = umax.len() as i32 - 2;
    let step = img
        .mat_step()
        .first()
        .copied()
        .unwrap_or(img.cols() as usize);
    let data = img.data_bytes().map_err(cv_err("pyramid level"))?;
    let at = |u: i32, v: i32| data[(y + v) as usize * step + (x + u) as usize] as i32;
    let (mut m01, mut m10) = (0i32, 0i32);
    for u in -half..=half {
        m10 += u * at(u, 0);
    }
    for v in 1..=half {
        let d = umax[v as usize];
        let mut v_sum = 0;
        for u in -d..=d {
            let (plus, minus) = (at(u, v), at(u, -v));
            v_sum += plus - minus;
            m10 += u * (plus + minus);
        }
        m01 += v * v_sum;
    }
    let a = (m01 as f32).atan2(m10 as f32).to_degrees();
    Ok(if a < 0.0 { a + 360.0 } else { a })
}
