//! The TUM RGB-D benchmark layout: `rgb.txt`, `depth.txt`, optional `associations.txt`,
//! `groundtruth.txt`, and the `rgb/` and `depth/` PNG folders.
//!
//! Reading is strict where a silent mistake would corrupt an evaluation (malformed or
//! non-increasing timestamps, NaN poses, 8-bit depth, wrong image sizes) and tolerant where
//! the benchmark's own tools are (comments, blank lines, extra whitespace). Every error names
//! the file and, for text files, the line.

use crate::error::{Error, Result, read_text};
use crate::io::atomic_write;
use image::{DynamicImage, RgbImage};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// A camera-to-world pose at a time stamp (TUM convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StampedPose {
    pub t: f64,
    pub pose: Isometry3<f64>,
}

/// One line of `rgb.txt` / `depth.txt`.
#[derive(Debug, Clone, PartialEq)]
pub struct ListEntry {
    pub t: f64,
    pub file: String,
    /// 1-based line in the list file, for error messages.
    pub line: usize,
}

/// Splits a TUM text file into (1-based line number, whitespace-separated fields), skipping
/// comments and blank lines.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, Vec<&str>)> {
    text.lines().enumerate().filter_map(|(i, l)| {
        let l = l.trim();
        (!l.is_empty() && !l.starts_with('#')).then(|| (i + 1, l.split_whitespace().collect()))
    })
}

fn parse_f64(path: &Path, line: usize, what: &str, s: &str) -> Result<f64> {
    let v: f64 = s
        .parse()
        .map_err(|_| Error::parse(path, line, format!("{what} '{s}' is not a number")))?;
    if !v.is_finite() {
        return Err(Error::parse(
            path,
            line,
            format!("{what} is {s}, not a finite number"),
        ));
    }
    Ok(v)
}

/// Checks that time stamps strictly increase; duplicated or unsorted ones are an error because
/// association and RPE silently go wrong on them.
fn check_increasing(path: &Path, prev: Option<(f64, usize)>, t: f64, line: usize) -> Result<()> {
    if let Some((tp, lp)) = prev
        && t <= tp
    {
        let what = if t == tp {
            "duplicated"
        } else {
            "not increasing"
        };
        return Err(Error::parse(
            path,
            line,
            format!("time stamp {t:.6} is {what} (line {lp} has {tp:.6})"),
        ));
    }
    Ok(())
}

/// Reads an image list (`rgb.txt`, `depth.txt`): `timestamp filename` per line.
pub fn read_list(path: &Path) -> Result<Vec<ListEntry>> {
    parse_list(&read_text(path)?, path)
}

/// Parses image-list text; `path` is only used in error messages.
pub fn parse_list(text: &str, path: &Path) -> Result<Vec<ListEntry>> {
    let mut out: Vec<ListEntry> = Vec::new();
    for (line, f) in data_lines(text) {
        if f.len() != 2 {
            return Err(Error::parse(
                path,
                line,
                format!("expected 2 columns 'timestamp filename', found {}", f.len()),
            ));
        }
        let t = parse_f64(path, line, "time stamp", f[0])?;
        check_increasing(path, out.last().map(|e| (e.t, e.line)), t, line)?;
        out.push(ListEntry {
            t,
            file: f[1].to_string(),
            line,
        });
    }
    Ok(out)
}

/// Reads a TUM trajectory: `timestamp tx ty tz qx qy qz qw` per line (camera-to-world).
/// Quaternions must have unit norm within 1e-3 (they are re-normalised); anything else is
/// reported, because a non-normalised quaternion usually means swapped columns.
pub fn read_trajectory(path: &Path) -> Result<Vec<StampedPose>> {
    parse_trajectory(&read_text(path)?, path)
}

/// Parses TUM trajectory text; `path` is only used in error messages.
pub fn parse_trajectory(text: &str, path: &Path) -> Result<Vec<StampedPose>> {
    let mut out: Vec<StampedPose> = Vec::new();
    let mut prev_line = 0;
    for (line, f) in data_lines(text) {
        if f.len() != 8 {
            return Err(Error::parse(
                path,
                line,
                format!(
                    "expected 8 columns 'timestamp tx ty tz qx qy qz qw', found {}",
                    f.len()
                ),
            ));
        }
        let names = ["time stamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"];
        let mut v = [0.0; 8];
        for k in 0..8 {
            v[k] = parse_f64(path, line, names[k], f[k])?;
        }
        check_increasing(path, out.last().map(|p| (p.t, prev_line)), v[0], line)?;
        let q = Quaternion::new(v[7], v[4], v[5], v[6]);
        let n = q.norm();
        if (n - 1.0).abs() > 1e-3 {
            return Err(Error::parse(
                path,
                line,
                format!("quaternion (qx qy qz qw) has norm {n:.6}, expected 1"),
            ));
        }
        out.push(StampedPose {
            t: v[0],
            pose: Isometry3::from_parts(
                Translation3::new(v[1], v[2], v[3]),
                UnitQuaternion::from_quaternion(q),
            ),
        });
        prev_line = line;
    }
    Ok(out)
}

/// Formats one pose as a TUM line (`%.6f` time stamp, full precision for the rest).
pub fn format_pose(p: &StampedPose, extra: Option<&str>) -> String {
    let t = p.pose.translation.vector;
    let q = p.pose.rotation.quaternion().coords; // (x, y, z, w)
    let mut s = format!(
        "{:.6} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}",
        p.t, t.x, t.y, t.z, q.x, q.y, q.z, q.w
    );
    if let Some(e) = extra {
        s.push(' ');
        s.push_str(e);
    }
    s
}

/// Writes a TUM trajectory atomically, with a comment header.
pub fn write_trajectory(path: &Path, poses: &[StampedPose], header: &str) -> Result<()> {
    let mut s = String::new();
    for h in header.lines() {
        let _ = writeln!(s, "# {h}");
    }
    let _ = writeln!(s, "# timestamp tx ty tz qx qy qz qw");
    for p in poses {
        s.push_str(&format_pose(p, None));
        s.push('\n');
    }
    atomic_write(path, s.as_bytes())
}

/// Writes an image list (`rgb.txt`, `depth.txt`) atomically.
pub fn write_list(path: &Path, entries: &[(f64, String)], header: &str) -> Result<()> {
    let mut s = String::new();
    for h in header.lines() {
        let _ = writeln!(s, "# {h}");
    }
    let _ = writeln!(s, "# timestamp filename");
    for (t, f) in entries {
        let _ = writeln!(s, "{t:.6} {f}");
    }
    atomic_write(path, s.as_bytes())
}

/// Associates two increasing time-stamp lists as `evo` does (`sync.matching_time_indices`):
/// each stamp of the *shorter* list takes its nearest stamp of the longer one if it is within
/// `max_dt` (ties go to the earlier stamp). Returns index pairs (into `a`, into `b`), sorted.
pub fn associate_nearest(a: &[f64], b: &[f64], max_dt: f64) -> Vec<(usize, usize)> {
    let swap = a.len() < b.len();
    let (short, long) = if swap { (a, b) } else { (b, a) };
    let mut out = Vec::new();
    if long.is_empty() {
        return out;
    }
    for (i, &t) in short.iter().enumerate() {
        if t < long[0] - max_dt || t > long[long.len() - 1] + max_dt {
            continue;
        }
        let mut j = long.partition_point(|&x| x <= t); // numpy searchsorted side="right"
        if j >= long.len() {
            j = long.len() - 1;
        }
        let ub = long[j] - t;
        let lb = if j > 0 {
            t - long[j - 1]
        } else {
            f64::INFINITY
        };
        let best = if ub <= max_dt && ub < lb {
            j
        } else if lb <= max_dt && lb <= ub {
            j - 1
        } else {
            continue;
        };
        out.push(if swap { (i, best) } else { (best, i) });
    }
    out.sort_unstable();
    out
}

/// Associates colour and depth stamps as the benchmark's `associate.py` does: all pairs closer
/// than `max_dt`, taken greedily by increasing difference, each stamp used at most once.
/// Returns (colour index, depth index) pairs sorted by colour index.
pub fn associate_unique(a: &[f64], b: &[f64], max_dt: f64) -> Vec<(usize, usize)> {
    let mut cand: Vec<(f64, usize, usize)> = Vec::new();
    let mut lo = 0;
    for (i, &t) in a.iter().enumerate() {
        while lo < b.len() && b[lo] <= t - max_dt {
            lo += 1;
        }
        let mut j = lo;
        while j < b.len() && b[j] < t + max_dt {
            let d = (t - b[j]).abs();
            if d < max_dt {
                cand.push((d, i, j));
            }
            j += 1;
        }
    }
    cand.sort_by(|x, y| x.partial_cmp(y).expect("finite differences"));
    let (mut used_a, mut used_b) = (vec![false; a.len()], vec![false; b.len()]);
    let mut out = Vec::new();
    for (_, i, j) in cand {
        if !used_a[i] && !used_b[j] {
            used_a[i] = true;
            used_b[j] = true;
            out.push((i, j));
        }
    }
    out.sort_unstable();
    out
}

/// A depth image in metres, row-major; 0 means no reading.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<f32>,
}

impl DepthImage {
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            data: vec![0.0; (width * height) as usize],
        }
    }
    pub fn get(&self, x: u32, y: u32) -> f32 {
        self.data[(y * self.width + x) as usize]
    }
}

/// One frame as it reaches the front end. `index` is the frame's index in the *unperturbed*
/// sequence, so that outputs can always be related to the original data.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub index: usize,
    pub t: f64,
    pub rgb: RgbImage,
    pub depth: Option<DepthImage>,
}

/// A frame of the sequence before its images are loaded.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRef {
    pub t: f64,
    pub rgb: PathBuf,
    pub depth: Option<PathBuf>,
}

/// Anything that delivers frames by index: a TUM folder, an MCAP bag, a perturbed view.
pub trait FrameSource {
    fn len(&self) -> usize;
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    fn timestamp(&self, i: usize) -> f64;
    fn load(&self, i: usize) -> Result<Frame>;
}

/// A TUM RGB-D folder, read lazily: the lists are parsed up front, images only on `load`.
#[derive(Debug, Clone)]
pub struct TumSequence {
    pub dir: PathBuf,
    pub frames: Vec<FrameRef>,
    pub width: u32,
    pub height: u32,
    pub depth_scale: f64,
    /// Colour frames that found no depth partner within the tolerance (dropped from `frames`).
    pub unassociated: usize,
}

impl TumSequence {
    /// Opens a TUM folder. `associations.txt` is used when present (`t_rgb rgb t_depth depth`);
    /// otherwise colour and depth are associated like `associate.py`. With `mono`, depth is not
    /// read at all and every colour frame is kept.
    pub fn open(
        dir: &Path,
        width: u32,
        height: u32,
        depth_scale: f64,
        max_dt: f64,
        mono: bool,
    ) -> Result<Self> {
        if !dir.is_dir() {
            return Err(Error::file(dir, "is not a folder"));
        }
        let assoc = dir.join("associations.txt");
        let mut unassociated = 0;
        let frames = if assoc.is_file() && !mono {
            read_associations(&assoc)?
                .into_iter()
                .map(|(t, rgb, _, depth)| FrameRef {
                    t,
                    rgb: dir.join(rgb),
                    depth: Some(dir.join(depth)),
                })
                .collect()
        } else {
            let rgb_list = dir.join("rgb.txt");
            if !rgb_list.is_file() {
                return Err(Error::file(
                    dir,
                    "is not a TUM RGB-D folder: it has no rgb.txt (nor associations.txt)",
                ));
            }
            let rgb = read_list(&rgb_list)?;
            if mono {
                rgb.iter()
                    .map(|e| FrameRef {
                        t: e.t,
                        rgb: dir.join(&e.file),
                        depth: None,
                    })
                    .collect()
            } else {
                let depth_list = dir.join("depth.txt");
                if !depth_list.is_file() {
                    return Err(Error::file(
                        dir,
                        "has rgb.txt but no depth.txt; use --mono to run without depth",
                    ));
                }
                let depth = read_list(&depth_list)?;
                let ta: Vec<f64> = rgb.iter().map(|e| e.t).collect();
                let tb: Vec<f64> = depth.iter().map(|e| e.t).collect();
                let pairs = associate_unique(&ta, &tb, max_dt);
                unassociated = rgb.len() - pairs.len();
                pairs
                    .into_iter()
                    .map(|(i, j)| FrameRef {
                        t: rgb[i].t,
                        rgb: dir.join(&rgb[i].file),
                        depth: Some(dir.join(&depth[j].file)),
                    })
                    .collect::<Vec<_>>()
            }
        };
        let frames: Vec<FrameRef> = frames;
        if frames.is_empty() {
            return Err(Error::file(
                dir,
                "holds no frames (empty lists, or no colour frame has a depth frame within the \
                 association tolerance)",
            ));
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            frames,
            width,
            height,
            depth_scale,
            unassociated,
        })
    }

    /// The ground truth of the folder, if it has `groundtruth.txt`.
    pub fn groundtruth(&self) -> Result<Option<Vec<StampedPose>>> {
        let p = self.dir.join("groundtruth.txt");
        if p.is_file() {
            read_trajectory(&p).map(Some)
        } else {
            Ok(None)
        }
    }
}

impl FrameSource for TumSequence {
    fn len(&self) -> usize {
        self.frames.len()
    }
    fn timestamp(&self, i: usize) -> f64 {
        self.frames[i].t
    }
    fn load(&self, i: usize) -> Result<Frame> {
        let f = &self.frames[i];
        let rgb = load_rgb(&f.rgb, self.width, self.height)?;
        let depth = match &f.depth {
            Some(p) => Some(load_depth(p, self.width, self.height, self.depth_scale)?),
            None => None,
        };
        Ok(Frame {
            index: i,
            t: f.t,
            rgb,
            depth,
        })
    }
}

/// Reads `associations.txt`: `t_rgb rgb_file t_depth depth_file`.
fn read_associations(path: &Path) -> Result<Vec<(f64, String, f64, String)>> {
    parse_associations(&read_text(path)?, path)
}

/// Parses `associations.txt` text; `path` is only used in error messages.
pub fn parse_associations(text: &str, path: &Path) -> Result<Vec<(f64, String, f64, String)>> {
    let mut out: Vec<(f64, String, f64, String)> = Vec::new();
    let mut prev = None;
    for (line, f) in data_lines(text) {
        if f.len() != 4 {
            return Err(Error::parse(
                path,
                line,
                format!(
                    "expected 4 columns 'timestamp rgb_file timestamp depth_file', found {}",
                    f.len()
                ),
            ));
        }
        let t = parse_f64(path, line, "colour time stamp", f[0])?;
        let td = parse_f64(path, line, "depth time stamp", f[2])?;
        check_increasing(path, prev, t, line)?;
        prev = Some((t, line));
        out.push((t, f[1].to_string(), td, f[3].to_string()));
    }
    Ok(out)
}

pub(crate) fn open_image(path: &Path) -> Result<DynamicImage> {
    let reader = image::ImageReader::open(path)
        .map_err(|e| Error::file(path, format!("cannot open image: {e}")))?
        .with_guessed_format()
        .map_err(|e| Error::file(path, format!("cannot read image: {e}")))?;
    reader.decode().map_err(|e| {
        Error::file(
            path,
            format!("cannot decode image (truncated or corrupt?): {e}"),
        )
    })
}

fn check_size(path: &Path, w: u32, h: u32, width: u32, height: u32) -> Result<()> {
    if (w, h) != (width, height) {
        return Err(Error::file(
            path,
            format!("image is {w}x{h}, the camera config says {width}x{height}"),
        ));
    }
    Ok(())
}

/// Loads an 8-bit colour image (grey images are expanded to RGB).
pub fn load_rgb(path: &Path, width: u32, height: u32) -> Result<RgbImage> {
    let img = open_image(path)?;
    check_size(path, img.width(), img.height(), width, height)?;
    to_rgb(path, img)
}

/// An 8-bit RGB image from a decoded one (grey expanded); other pixel types are errors.
pub(crate) fn to_rgb(path: &Path, img: DynamicImage) -> Result<RgbImage> {
    match img {
        DynamicImage::ImageRgb8(i) => Ok(i),
        DynamicImage::ImageRgba8(_)
        | DynamicImage::ImageLuma8(_)
        | DynamicImage::ImageLumaA8(_) => Ok(img.to_rgb8()),
        other => Err(Error::file(
            path,
            format!(
                "colour image has pixel type {:?}; expected 8-bit RGB or grey",
                other.color()
            ),
        )),
    }
}

/// Loads a 16-bit depth PNG and converts it to metres with `scale` units per metre.
/// An 8-bit depth image is an error: it cannot hold metric depth (wrong file or wrong export).
pub fn load_depth(path: &Path, width: u32, height: u32, scale: f64) -> Result<DepthImage> {
    let img = open_image(path)?;
    check_size(path, img.width(), img.height(), width, height)?;
    let raw = match img {
        DynamicImage::ImageLuma16(i) => i,
        other => {
            return Err(Error::file(
                path,
                format!(
                    "depth image has pixel type {:?}; TUM depth must be a 16-bit single-channel \
                     PNG ({} units per metre)",
                    other.color(),
                    scale
                ),
            ));
        }
    };
    Ok(depth_from_units(width, height, raw.as_raw(), scale))
}

/// Depth in metres from a sensor's 16-bit units (`scale` units per metre, 0 = no reading),
/// row-major `width` × `height` (the caller checks the length).
pub fn depth_from_units(width: u32, height: u32, raw: &[u16], scale: f64) -> DepthImage {
    let inv = 1.0 / scale;
    DepthImage {
        width,
        height,
        data: raw.iter().map(|&d| (d as f64 * inv) as f32).collect(),
    }
}

/// Encodes depth in metres as a 16-bit PNG with `scale` units per metre (0 = invalid;
/// values that do not fit are stored as 0, i.e. no reading).
pub fn save_depth(path: &Path, depth: &DepthImage, scale: f64) -> Result<()> {
    let raw: Vec<u16> = depth
        .data
        .iter()
        .map(|&m| {
            let v = (m as f64 * scale).round();
            if m > 0.0 && v >= 1.0 && v <= u16::MAX as f64 {
                v as u16
            } else {
                0
            }
        })
        .collect();
    let img =
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(depth.width, depth.height, raw)
            .ok_or_else(|| Error::file(path, "depth buffer size does not match its dimensions"))?;
    save_png(path, &DynamicImage::ImageLuma16(img))
}

/// Saves a PNG atomically.
pub fn save_png(path: &Path, img: &DynamicImage) -> Result<()> {
    let mut buf = std::io::Cursor::new(Vec::new());
    img.write_to(&mut buf, image::ImageFormat::Png)
        .map_err(|e| Error::file(path, format!("cannot encode PNG: {e}")))?;
    atomic_write(path, buf.get_ref())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_association_matches_evo_rules() {
        let a = [0.0, 0.1, 0.2, 0.3];
        let b = [0.005, 0.095, 0.15, 0.31, 0.5, 0.6];
        // a is shorter: each a takes its nearest b within 0.02 s.
        assert_eq!(
            associate_nearest(&a, &b, 0.02),
            vec![(0, 0), (1, 1), (3, 3)]
        );
        // Tie goes to the earlier stamp.
        assert_eq!(associate_nearest(&[1.0], &[0.99, 1.01], 0.02), vec![(0, 0)]);
        assert!(associate_nearest(&[1.0], &[], 0.02).is_empty());
    }

    #[test]
    fn unique_association_is_greedy_by_difference() {
        // Both colour stamps are near depth 0.0; the closer one wins it.
        let pairs = associate_unique(&[0.0, 0.01], &[0.009, 0.5], 0.02);
        assert_eq!(pairs, vec![(1, 0)]);
    }
}
