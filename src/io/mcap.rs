//! ROS 2 bags in MCAP as a sequence: `sensor_msgs/msg/Image` colour (`rgb8`, `bgr8`, `mono8`)
//! and depth (`16UC1` millimetres, `32FC1` metres) on two topics, an optional
//! `sensor_msgs/msg/CameraInfo`, and an optional ground truth (`/groundtruth`, JSON poses as
//! `homing convert tum-to-mcap` writes them). Messages must be `cdr` with `ros2msg` schemas.
//!
//! The bag is read lazily: opening it reads the summary (chunk and message indexes) and scans
//! the image topics once for their header stamps; a frame's images are decoded from their chunks
//! when the frame is loaded. Colour and depth are associated by their header stamps as
//! [`crate::io::tum`] associates `rgb.txt` and `depth.txt`. A bag without a summary (a recording
//! that was not closed, or a truncated file) is an error; `mcap recover` rebuilds it.
//!
//! [`tum_to_mcap`] writes such a bag from a TUM folder, so the reader is tested without ROS.

use crate::config::{CameraConfig, Config, resolve_camera};
use crate::error::{Error, Result};
use crate::io::cdr::{self, CameraInfo, Header, Image, Time};
use crate::io::tum::{
    DepthImage, Frame, FrameSource, StampedPose, associate_unique, open_image, read_list,
    read_trajectory,
};
use ::mcap::records::MessageHeader;
use ::mcap::sans_io::indexed_reader::{
    IndexedReadEvent, IndexedReader, IndexedReaderOptions, ReadOrder,
};
use ::mcap::sans_io::summary_reader::{SummaryReadEvent, SummaryReader, SummaryReaderOptions};
use image::{DynamicImage, RgbImage};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

/// Schema names of the ROS 2 messages read and written.
pub const IMAGE_SCHEMA: &str = "sensor_msgs/msg/Image";
pub const CAMERA_INFO_SCHEMA: &str = "sensor_msgs/msg/CameraInfo";
/// Topics `homing convert tum-to-mcap` writes.
pub const RGB_TOPIC: &str = "/camera/rgb/image_color";
pub const DEPTH_TOPIC: &str = "/camera/depth/image";
pub const CAMERA_INFO_TOPIC: &str = "/camera/rgb/camera_info";
pub const GROUNDTRUTH_TOPIC: &str = "/groundtruth";
/// Channel metadata key: units per metre of a `16UC1` depth topic (default: 1000, ROS's
/// millimetres). `tum-to-mcap` keeps the TUM values (5000 per metre) and records that here.
pub const DEPTH_SCALE_KEY: &str = "homing.depth_scale";
/// MCAP metadata record holding the source's full camera config (`camera.toml` text).
pub const CAMERA_METADATA: &str = "homing.camera";

/// JSON schema of a pose message (Foxglove's `foxglove.PoseInFrame`, plus homing's fields).
pub const POSE_JSON_SCHEMA: &str = r#"{"title":"foxglove.PoseInFrame","description":"A camera-to-world pose (TUM convention)","type":"object","properties":{"timestamp":{"type":"object","properties":{"sec":{"type":"integer","minimum":0},"nsec":{"type":"integer","minimum":0}}},"frame_id":{"type":"string"},"pose":{"type":"object","properties":{"position":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"}}},"orientation":{"type":"object","properties":{"x":{"type":"number"},"y":{"type":"number"},"z":{"type":"number"},"w":{"type":"number"}}}}},"frame":{"type":"integer","description":"frame index in the unperturbed sequence"},"map":{"type":"integer","description":"map id in the final atlas"}}}"#;

/// Seconds (as `f64`) to integer nanoseconds, through the shortest decimal that round-trips the
/// value, so that a TUM stamp like 1305031102.175304 becomes exactly 1305031102175304000.
pub fn seconds_to_ns(t: f64) -> u64 {
    if !t.is_finite() || t <= 0.0 {
        return 0;
    }
    let s = format!("{t}");
    if s.contains(['e', 'E']) {
        return (t * 1e9).round() as u64;
    }
    let (int, frac) = s.split_once('.').unwrap_or((&s, ""));
    let int: u64 = int.parse().unwrap_or(0);
    let digits: Vec<u64> = frac.bytes().map(|b| (b - b'0') as u64).collect();
    let mut ns = 0u64;
    for k in 0..9 {
        ns = ns * 10 + digits.get(k).copied().unwrap_or(0);
    }
    if digits.get(9).is_some_and(|&d| d >= 5) {
        ns += 1;
    }
    int.saturating_mul(1_000_000_000).saturating_add(ns)
}

/// Nanoseconds to seconds: the `f64` nearest to the decimal `sec.nanosec` (the inverse of
/// [`seconds_to_ns`] for stamps with at most 9 decimals).
pub fn ns_to_seconds(ns: u64) -> f64 {
    format!("{}.{:09}", ns / 1_000_000_000, ns % 1_000_000_000)
        .parse()
        .unwrap_or(ns as f64 * 1e-9)
}

/// The topics of a bag to run on.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct McapTopics {
    pub image: String,
    pub depth: String,
    pub camera_info: Option<String>,
}

/// Where one message is: its topic, log time and rank among that topic's messages with the
/// same log time.
#[derive(Debug, Clone, PartialEq)]
struct MsgRef {
    topic: String,
    log_time: u64,
    nth: usize,
}

/// One associated frame of a bag.
#[derive(Debug, Clone, PartialEq)]
pub struct McapFrame {
    pub t: f64,
    rgb: MsgRef,
    depth: Option<MsgRef>,
}

/// A ROS 2 bag (MCAP) read as a sequence. See the module documentation.
#[derive(Debug)]
pub struct McapSequence {
    pub path: PathBuf,
    summary: ::mcap::Summary,
    pub topics: McapTopics,
    pub frames: Vec<McapFrame>,
    /// The first `CameraInfo` of `--camera-info-topic`.
    pub camera_info: Option<CameraInfo>,
    /// The camera config `tum-to-mcap` stored in the bag's metadata.
    pub bag_camera: Option<CameraConfig>,
    /// Units per metre of a `16UC1` depth topic.
    pub depth_scale: f64,
    /// Colour frames without a depth frame within the tolerance (dropped from `frames`).
    pub unassociated: usize,
    /// Image size the camera expects (checked on load); 0 until [`Self::set_size`].
    pub width: u32,
    pub height: u32,
    groundtruth: Option<Vec<StampedPose>>,
}

fn bag_err(path: &Path, what: &str, e: impl std::fmt::Display) -> Error {
    Error::file(
        path,
        format!("{what}: {e} (truncated or corrupt MCAP file?)"),
    )
}

fn read_summary(path: &Path, file: &mut File) -> Result<::mcap::Summary> {
    let size = file
        .metadata()
        .map_err(|e| Error::file(path, format!("cannot read: {e}")))?
        .len();
    let mut magic = [0u8; 8];
    if size < 8 || file.read_exact(&mut magic).is_err() || magic != ::mcap::MAGIC {
        return Err(Error::file(
            path,
            "not an MCAP file (it does not start with the MCAP magic bytes)",
        ));
    }
    let mut reader = SummaryReader::new_with_options(
        SummaryReaderOptions::default()
            .with_file_size(size)
            .with_record_length_limit(size as usize),
    );
    while let Some(event) = reader.next_event() {
        match event.map_err(|e| bag_err(path, "cannot read the summary", e))? {
            SummaryReadEvent::ReadRequest(n) => {
                let k = file
                    .read(reader.insert(n))
                    .map_err(|e| Error::file(path, format!("cannot read: {e}")))?;
                reader.notify_read(k);
            }
            SummaryReadEvent::SeekRequest(to) => {
                let pos = file
                    .seek(to)
                    .map_err(|e| Error::file(path, format!("cannot seek: {e}")))?;
                reader.notify_seeked(pos);
            }
        }
    }
    reader.finish().ok_or_else(|| {
        Error::file(
            path,
            "the MCAP file has no summary section (truncated, or the recording was not closed); \
             rebuild it with `mcap recover`",
        )
    })
}

/// Checks a chunk's records against the CRC its header stores (the indexed reader does not).
/// `data` is the chunk's compressed records, read from `offset`.
fn check_chunk_crc(
    path: &Path,
    file: &mut File,
    summary: &::mcap::Summary,
    offset: u64,
    data: &[u8],
) -> Result<()> {
    let Some(ci) = summary
        .chunk_indexes
        .iter()
        .find(|c| c.compressed_data_offset().ok() == Some(offset))
    else {
        return Ok(());
    };
    // Chunk record: opcode u8, record length u64, start time u64, end time u64,
    // uncompressed size u64, uncompressed CRC u32, ...
    let mut crc = [0u8; 4];
    file.seek(SeekFrom::Start(ci.chunk_start_offset + 33))
        .and_then(|_| file.read_exact(&mut crc))
        .map_err(|e| bag_err(path, "cannot read a chunk", e))?;
    let expected = u32::from_le_bytes(crc);
    if expected == 0 {
        return Ok(()); // 0: the writer did not compute it
    }
    let records;
    let plain = match ci.compression.as_str() {
        "" => data,
        "zstd" => {
            let cap = usize::try_from(ci.uncompressed_size).unwrap_or(usize::MAX);
            records = zstd::bulk::decompress(data, cap.min(data.len().saturating_mul(1024)))
                .map_err(|e| bag_err(path, "bad chunk", e))?;
            &records[..]
        }
        _ => return Ok(()), // the reader reports compressions it cannot read
    };
    let actual = crc32fast::hash(plain);
    if actual != expected {
        return Err(bag_err(
            path,
            &format!(
                "chunk at byte {}: CRC {actual:08x}, the chunk says {expected:08x}",
                ci.chunk_start_offset
            ),
            "corrupt data",
        ));
    }
    Ok(())
}

/// Reads the messages of `options`' topics and time range, calling `f(header, topic, data)`.
/// With `verify`, each chunk read is checked against its CRC first (done once, when the bag is
/// opened and scanned, not again per frame).
fn for_each_message(
    path: &Path,
    summary: &::mcap::Summary,
    options: IndexedReaderOptions,
    verify: bool,
    mut f: impl FnMut(&MessageHeader, &str, &[u8]) -> Result<bool>,
) -> Result<()> {
    let mut file = File::open(path).map_err(|e| Error::file(path, format!("cannot open: {e}")))?;
    // Lengths beyond the file are corruption: refuse them instead of allocating.
    let size = file.metadata().map(|m| m.len()).unwrap_or(u64::MAX);
    let limit = usize::try_from(size.saturating_mul(64)).unwrap_or(usize::MAX);
    let options = options.with_record_length_limit(limit);
    let mut reader = IndexedReader::new_with_options(summary, options)
        .map_err(|e| bag_err(path, "bad chunk index", e))?;
    let mut buf = Vec::new();
    while let Some(event) = reader.next_event() {
        match event.map_err(|e| bag_err(path, "cannot read messages", e))? {
            IndexedReadEvent::ReadChunkRequest { offset, length } => {
                buf.resize(length, 0);
                file.seek(SeekFrom::Start(offset))
                    .and_then(|_| file.read_exact(&mut buf))
                    .map_err(|e| bag_err(path, "cannot read a chunk", e))?;
                if verify {
                    check_chunk_crc(path, &mut file, summary, offset, &buf)?;
                }
                reader
                    .insert_chunk_record_data(offset, &buf)
                    .map_err(|e| bag_err(path, "bad chunk", e))?;
            }
            IndexedReadEvent::Message { header, data } => {
                let topic = summary
                    .channels
                    .get(&header.channel_id)
                    .map(|c| c.topic.as_str())
                    .unwrap_or("");
                if !f(&header, topic, data)? {
                    break;
                }
            }
        }
    }
    Ok(())
}

/// The bag's topics as `topic (schema)`, sorted, for error messages.
fn topic_list(summary: &::mcap::Summary) -> String {
    let mut v: Vec<String> = summary
        .channels
        .values()
        .map(|c| {
            format!(
                "{} ({})",
                c.topic,
                c.schema.as_ref().map_or("no schema", |s| s.name.as_str())
            )
        })
        .collect();
    v.sort();
    v.dedup();
    if v.is_empty() {
        "none".into()
    } else {
        v.join(", ")
    }
}

impl McapSequence {
    /// Opens a bag. With `mono`, the depth topic is not read and every colour frame is kept.
    pub fn open(path: &Path, topics: &McapTopics, max_dt: f64, mono: bool) -> Result<Self> {
        let mut file =
            File::open(path).map_err(|e| Error::file(path, format!("cannot open: {e}")))?;
        let summary = read_summary(path, &mut file)?;
        // Check the topics and their types.
        let mut wanted: Vec<(&str, &str, &str)> =
            vec![("--image-topic", topics.image.as_str(), IMAGE_SCHEMA)];
        if !mono {
            wanted.push(("--depth-topic", topics.depth.as_str(), IMAGE_SCHEMA));
        }
        if let Some(ci) = &topics.camera_info {
            wanted.push(("--camera-info-topic", ci.as_str(), CAMERA_INFO_SCHEMA));
        }
        let mut depth_scale = 1000.0;
        for (flag, topic, schema) in &wanted {
            let Some(ch) = summary.channels.values().find(|c| c.topic == *topic) else {
                return Err(Error::file(
                    path,
                    format!(
                        "{flag} {topic}: no such topic; the bag has: {}",
                        topic_list(&summary)
                    ),
                ));
            };
            let (name, enc) = ch
                .schema
                .as_ref()
                .map_or(("", ""), |s| (s.name.as_str(), s.encoding.as_str()));
            if name != *schema || enc != "ros2msg" || ch.message_encoding != "cdr" {
                return Err(Error::file(
                    path,
                    format!(
                        "{flag} {topic}: has schema '{name}' ({enc}), messages '{}'; expected \
                         {schema} (ros2msg) in cdr",
                        ch.message_encoding
                    ),
                ));
            }
            if *flag == "--depth-topic"
                && let Some(s) = ch.metadata.get(DEPTH_SCALE_KEY)
            {
                depth_scale = s.parse().ok().filter(|v: &f64| *v > 0.0).ok_or_else(|| {
                        Error::file(
                            path,
                            format!("{topic}: channel metadata {DEPTH_SCALE_KEY}='{s}' is not a positive number"),
                        )
                    })?;
            }
        }
        if summary.chunk_indexes.is_empty() {
            return Err(Error::file(
                path,
                "the MCAP file has no chunk index (written without chunks?); homing reads \
                 chunked, indexed bags as ros2 bag record writes them",
            ));
        }
        // One pass over the image topics for the header stamps.
        let mut colour: Vec<(f64, MsgRef)> = Vec::new();
        let mut depth: Vec<(f64, MsgRef)> = Vec::new();
        let mut camera_info = None;
        let mut seen: BTreeMap<(u16, u64), usize> = BTreeMap::new();
        let names: Vec<String> = wanted.iter().map(|w| w.1.to_string()).collect();
        let options = IndexedReaderOptions::new()
            .with_order(ReadOrder::LogTime)
            .include_topics(names);
        for_each_message(path, &summary, options, true, |h, topic, data| {
            let nth = seen.entry((h.channel_id, h.log_time)).or_default();
            let r = MsgRef {
                topic: topic.to_string(),
                log_time: h.log_time,
                nth: *nth,
            };
            *nth += 1;
            let bad = |e: cdr::CdrError| {
                Error::file(
                    path,
                    format!("{topic}: message at log time {} ns: {e}", h.log_time),
                )
            };
            if Some(topic) == topics.camera_info.as_deref() {
                if camera_info.is_none() {
                    camera_info = Some(cdr::decode_camera_info(data).map_err(bad)?);
                }
                return Ok(true);
            }
            let img = cdr::decode_image(data, false).map_err(bad)?;
            let t = ns_to_seconds(img.header.stamp.as_ns());
            if topic == topics.image {
                colour.push((t, r));
            } else if !mono {
                depth.push((t, r));
            }
            Ok(true)
        })?;
        let sort = |v: &mut Vec<(f64, MsgRef)>, topic: &str| -> Result<()> {
            v.sort_by(|a, b| a.0.total_cmp(&b.0));
            if let Some(w) = v.windows(2).find(|w| w[0].0 == w[1].0) {
                return Err(Error::file(
                    path,
                    format!("{topic}: two images have the header stamp {:.9}", w[0].0),
                ));
            }
            Ok(())
        };
        sort(&mut colour, &topics.image)?;
        sort(&mut depth, &topics.depth)?;
        if let Some(ci) = &topics.camera_info
            && camera_info.is_none()
        {
            return Err(Error::file(
                path,
                format!("--camera-info-topic {ci}: the topic has no message"),
            ));
        }
        let mut unassociated = 0;
        let frames: Vec<McapFrame> = if mono {
            colour
                .into_iter()
                .map(|(t, rgb)| McapFrame {
                    t,
                    rgb,
                    depth: None,
                })
                .collect()
        } else {
            let ta: Vec<f64> = colour.iter().map(|c| c.0).collect();
            let tb: Vec<f64> = depth.iter().map(|c| c.0).collect();
            let pairs = associate_unique(&ta, &tb, max_dt);
            unassociated = colour.len() - pairs.len();
            pairs
                .into_iter()
                .map(|(i, j)| McapFrame {
                    t: colour[i].0,
                    rgb: colour[i].1.clone(),
                    depth: Some(depth[j].1.clone()),
                })
                .collect()
        };
        if frames.is_empty() {
            return Err(Error::file(
                path,
                format!(
                    "holds no frames: {} has {} images, {} has {} (none within {max_dt} s of a \
                     colour image)",
                    topics.image,
                    ta_len(&frames, unassociated),
                    topics.depth,
                    depth.len()
                ),
            ));
        }
        let bag_camera = read_camera_metadata(path, &mut file, &summary)?;
        let groundtruth = read_groundtruth(path, &summary)?;
        Ok(Self {
            path: path.to_path_buf(),
            summary,
            topics: topics.clone(),
            frames,
            camera_info,
            bag_camera,
            depth_scale,
            unassociated,
            width: 0,
            height: 0,
            groundtruth,
        })
    }

    /// Sets the image size the camera expects (every image is checked against it on load).
    pub fn set_size(&mut self, width: u32, height: u32) {
        self.width = width;
        self.height = height;
    }

    /// The ground truth on `/groundtruth`, if the bag has it.
    pub fn groundtruth(&self) -> Option<Vec<StampedPose>> {
        self.groundtruth.clone()
    }

    /// Picks the camera: intrinsics, distortion and size from the CameraInfo topic when there
    /// is one; the rest (and everything, without CameraInfo) from `--config`'s `[camera]`, else
    /// from the camera config stored in the bag by `tum-to-mcap`. Returns the camera and a
    /// description of where it came from.
    pub fn resolve_camera(
        &self,
        config: &Config,
        config_path: Option<&Path>,
    ) -> Result<(CameraConfig, String)> {
        let base = match (&config.camera, &self.bag_camera) {
            (Some(c), _) => Some((
                c.clone(),
                format!(
                    "the config file {}",
                    config_path.map_or("(given)".into(), |p| p.display().to_string())
                ),
            )),
            (None, Some(c)) => Some((c.clone(), format!("the bag's {CAMERA_METADATA} metadata"))),
            (None, None) => None,
        };
        let Some(ci) = &self.camera_info else {
            return base.ok_or_else(|| {
                Error::file(
                    &self.path,
                    "cannot tell the camera: no --camera-info-topic, no [camera] in --config and \
                     no homing.camera metadata in the bag; pass --camera-info-topic or --config",
                )
            });
        };
        let topic = self.topics.camera_info.as_deref().unwrap_or("");
        let bad = |msg: String| Error::file(&self.path, format!("{topic}: {msg}"));
        let k = ci.k;
        if k[0] <= 0.0 || k[4] <= 0.0 || ci.width == 0 || ci.height == 0 {
            return Err(bad(format!(
                "CameraInfo is not calibrated (K = {k:?}, {}x{})",
                ci.width, ci.height
            )));
        }
        let d = |i: usize| ci.d.get(i).copied().unwrap_or(0.0);
        match ci.distortion_model.as_str() {
            "plumb_bob" | "rational_polynomial" | "" => {}
            m => {
                return Err(bad(format!(
                    "distortion model '{m}' is not supported (plumb_bob or rational_polynomial \
                     with k4..k6 = 0)"
                )));
            }
        }
        if ci.d.iter().skip(5).any(|&v| v != 0.0) {
            return Err(bad(format!(
                "distortion {:?} has rational coefficients k4..k6; only k1, k2, p1, p2, k3 are \
                 supported",
                ci.d
            )));
        }
        let fps = self.estimated_fps();
        let (mut cam, rest) = match base {
            Some((c, src)) => (c, format!("; the other camera settings from {src}")),
            None => (
                CameraConfig {
                    name: format!("{} CameraInfo", topic),
                    fx: 0.0,
                    fy: 0.0,
                    cx: 0.0,
                    cy: 0.0,
                    k1: 0.0,
                    k2: 0.0,
                    p1: 0.0,
                    p2: 0.0,
                    k3: 0.0,
                    width: 0,
                    height: 0,
                    depth_scale: self.depth_scale,
                    fps,
                    readout_s: 0.0,
                    virtual_baseline_m: crate::config::default_virtual_baseline(),
                },
                format!("; fps {fps:.2} from the image stamps, global shutter"),
            ),
        };
        cam.fx = k[0];
        cam.fy = k[4];
        cam.cx = k[2];
        cam.cy = k[5];
        (cam.k1, cam.k2, cam.p1, cam.p2, cam.k3) = (d(0), d(1), d(2), d(3), d(4));
        cam.width = ci.width;
        cam.height = ci.height;
        Ok((
            cam,
            format!("intrinsics and distortion from the bag's {topic} (CameraInfo){rest}"),
        ))
    }

    /// Frames per second from the median colour stamp interval.
    fn estimated_fps(&self) -> f64 {
        let mut dt: Vec<f64> = self.frames.windows(2).map(|w| w[1].t - w[0].t).collect();
        if dt.is_empty() {
            return 30.0;
        }
        dt.sort_by(f64::total_cmp);
        let m = dt[dt.len() / 2];
        if m > 0.0 { 1.0 / m } else { 30.0 }
    }

    fn fetch(&self, r: &MsgRef) -> Result<Image> {
        let options = IndexedReaderOptions::new()
            .include_topics([r.topic.clone()])
            .starting_at(r.log_time)
            .ending_before(r.log_time.saturating_add(1));
        let mut k = 0;
        let mut found = None;
        for_each_message(&self.path, &self.summary, options, false, |_, _, data| {
            if k == r.nth {
                found = Some(cdr::decode_image(data, true).map_err(|e| {
                    Error::file(
                        &self.path,
                        format!("{}: message at log time {} ns: {e}", r.topic, r.log_time),
                    )
                })?);
                return Ok(false);
            }
            k += 1;
            Ok(true)
        })?;
        found.ok_or_else(|| {
            Error::file(
                &self.path,
                format!(
                    "{}: the message at log time {} ns is gone (file changed?)",
                    r.topic, r.log_time
                ),
            )
        })
    }

    fn check_size(&self, img: &Image, topic: &str) -> Result<()> {
        if self.width > 0 && (img.width, img.height) != (self.width, self.height) {
            return Err(Error::file(
                &self.path,
                format!(
                    "{topic}: image at {:.6} is {}x{}, the camera says {}x{}",
                    ns_to_seconds(img.header.stamp.as_ns()),
                    img.width,
                    img.height,
                    self.width,
                    self.height
                ),
            ));
        }
        Ok(())
    }
}

/// The number of colour images (for a message): frames kept plus those without depth.
fn ta_len(frames: &[McapFrame], unassociated: usize) -> usize {
    frames.len() + unassociated
}

/// The pixel rows of an image, checked against its size and step.
fn rows<'a>(
    img: &'a Image,
    path: &Path,
    topic: &str,
    bpp: usize,
) -> Result<impl Iterator<Item = &'a [u8]>> {
    let (w, h, step) = (img.width as usize, img.height as usize, img.step as usize);
    if step < w * bpp || img.data.len() < step * h.saturating_sub(1) + w * bpp {
        return Err(Error::file(
            path,
            format!(
                "{topic}: {} image {w}x{h} with step {step} has {} data bytes (too few)",
                img.encoding,
                img.data.len()
            ),
        ));
    }
    Ok((0..h).map(move |y| &img.data[y * step..y * step + w * bpp]))
}

/// A colour `Image` (rgb8, bgr8, mono8) as RGB.
pub fn image_to_rgb(img: &Image, path: &Path, topic: &str) -> Result<RgbImage> {
    let bpp = match img.encoding.as_str() {
        "rgb8" | "bgr8" => 3,
        "mono8" | "8UC1" => 1,
        e => {
            return Err(Error::file(
                path,
                format!("{topic}: colour encoding '{e}' is not supported (rgb8, bgr8, mono8)"),
            ));
        }
    };
    let mut out = Vec::with_capacity(img.width as usize * img.height as usize * 3);
    for row in rows(img, path, topic, bpp)? {
        match img.encoding.as_str() {
            "rgb8" => out.extend_from_slice(row),
            "bgr8" => row
                .chunks_exact(3)
                .for_each(|p| out.extend_from_slice(&[p[2], p[1], p[0]])),
            _ => row.iter().for_each(|&g| out.extend_from_slice(&[g, g, g])),
        }
    }
    RgbImage::from_raw(img.width, img.height, out)
        .ok_or_else(|| Error::file(path, format!("{topic}: image size does not match its data")))
}

/// A depth `Image` in metres: `16UC1` / `mono16` with `scale` units per metre (ROS: 1000),
/// `32FC1` in metres (NaN, infinite and non-positive values: no reading, 0).
pub fn image_to_depth(img: &Image, path: &Path, topic: &str, scale: f64) -> Result<DepthImage> {
    let be = img.is_bigendian != 0;
    let mut data = Vec::with_capacity(img.width as usize * img.height as usize);
    match img.encoding.as_str() {
        "16UC1" | "mono16" => {
            // As io::tum::load_depth converts PNG values.
            let inv = 1.0 / scale;
            for row in rows(img, path, topic, 2)? {
                for p in row.chunks_exact(2) {
                    let v = if be {
                        u16::from_be_bytes([p[0], p[1]])
                    } else {
                        u16::from_le_bytes([p[0], p[1]])
                    };
                    data.push((v as f64 * inv) as f32);
                }
            }
        }
        "32FC1" => {
            for row in rows(img, path, topic, 4)? {
                for p in row.chunks_exact(4) {
                    let b = [p[0], p[1], p[2], p[3]];
                    let v = if be {
                        f32::from_be_bytes(b)
                    } else {
                        f32::from_le_bytes(b)
                    };
                    data.push(if v.is_finite() && v > 0.0 { v } else { 0.0 });
                }
            }
        }
        e => {
            return Err(Error::file(
                path,
                format!(
                    "{topic}: depth encoding '{e}' is not supported (16UC1 in millimetres, 32FC1 in metres)"
                ),
            ));
        }
    }
    Ok(DepthImage {
        width: img.width,
        height: img.height,
        data,
    })
}

impl FrameSource for McapSequence {
    fn len(&self) -> usize {
        self.frames.len()
    }
    fn timestamp(&self, i: usize) -> f64 {
        self.frames[i].t
    }
    fn load(&self, i: usize) -> Result<Frame> {
        let f = &self.frames[i];
        let img = self.fetch(&f.rgb)?;
        self.check_size(&img, &f.rgb.topic)?;
        let rgb = image_to_rgb(&img, &self.path, &f.rgb.topic)?;
        let depth = match &f.depth {
            Some(r) => {
                let img = self.fetch(r)?;
                self.check_size(&img, &r.topic)?;
                Some(image_to_depth(
                    &img,
                    &self.path,
                    &r.topic,
                    self.depth_scale,
                )?)
            }
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

/// The camera config `tum-to-mcap` stores in a metadata record, if the bag has one.
fn read_camera_metadata(
    path: &Path,
    file: &mut File,
    summary: &::mcap::Summary,
) -> Result<Option<CameraConfig>> {
    let Some(idx) = summary
        .metadata_indexes
        .iter()
        .find(|m| m.name == CAMERA_METADATA)
    else {
        return Ok(None);
    };
    if idx.length < 9 || idx.length > 1 << 20 {
        return Err(bag_err(path, "metadata index", "bad record length"));
    }
    let mut buf = vec![0u8; idx.length as usize];
    file.seek(SeekFrom::Start(idx.offset))
        .and_then(|_| file.read_exact(&mut buf))
        .map_err(|e| bag_err(path, "cannot read the camera metadata", e))?;
    let rec = ::mcap::parse_record(buf[0], &buf[9..])
        .map_err(|e| bag_err(path, "bad camera metadata record", e))?;
    let ::mcap::records::Record::Metadata(m) = rec else {
        return Err(bag_err(path, "metadata index", "points to another record"));
    };
    let Some(text) = m.metadata.get("camera.toml") else {
        return Ok(None);
    };
    let name = PathBuf::from(format!("{}#{CAMERA_METADATA}", path.display()));
    Ok(Config::parse(text, &name)?.camera)
}

/// Poses on `/groundtruth` (JSON, [`POSE_JSON_SCHEMA`]), if the bag has that topic.
fn read_groundtruth(path: &Path, summary: &::mcap::Summary) -> Result<Option<Vec<StampedPose>>> {
    if !summary
        .channels
        .values()
        .any(|c| c.topic == GROUNDTRUTH_TOPIC && c.message_encoding == "json")
    {
        return Ok(None);
    }
    let mut out = Vec::new();
    let options = IndexedReaderOptions::new()
        .with_order(ReadOrder::LogTime)
        .include_topics([GROUNDTRUTH_TOPIC]);
    for_each_message(path, summary, options, true, |h, _, data| {
        let bad = |m: &str| {
            Error::file(
                path,
                format!("{GROUNDTRUTH_TOPIC}: message at {} ns: {m}", h.log_time),
            )
        };
        let v: serde_json::Value = serde_json::from_slice(data).map_err(|_| bad("not JSON"))?;
        out.push(pose_from_json(&v).ok_or_else(|| bad("not a pose"))?);
        Ok(true)
    })?;
    out.sort_by(|a, b| a.t.total_cmp(&b.t));
    Ok(Some(out))
}

/// A pose message as JSON ([`POSE_JSON_SCHEMA`]); `extra` fields are added at the top level.
pub fn pose_json(t: f64, pose: &Isometry3<f64>, extra: serde_json::Value) -> serde_json::Value {
    let ns = seconds_to_ns(t);
    let p = pose.translation.vector;
    let q = pose.rotation.quaternion().coords;
    let mut v = serde_json::json!({
        "timestamp": {"sec": ns / 1_000_000_000, "nsec": ns % 1_000_000_000},
        "frame_id": "world",
        "pose": {
            "position": {"x": p.x, "y": p.y, "z": p.z},
            "orientation": {"x": q.x, "y": q.y, "z": q.z, "w": q.w},
        },
    });
    if let (Some(o), serde_json::Value::Object(e)) = (v.as_object_mut(), extra) {
        o.extend(e);
    }
    v
}

/// Reads a pose message back.
pub fn pose_from_json(v: &serde_json::Value) -> Option<StampedPose> {
    let ts = &v["timestamp"];
    let ns = ts["sec"].as_u64()? * 1_000_000_000 + ts["nsec"].as_u64()?;
    let p = &v["pose"]["position"];
    let o = &v["pose"]["orientation"];
    let f = |x: &serde_json::Value| x.as_f64();
    let q = Quaternion::new(f(&o["w"])?, f(&o["x"])?, f(&o["y"])?, f(&o["z"])?);
    Some(StampedPose {
        t: ns_to_seconds(ns),
        pose: Isometry3::from_parts(
            Translation3::new(f(&p["x"])?, f(&p["y"])?, f(&p["z"])?),
            UnitQuaternion::from_quaternion(q),
        ),
    })
}

/// MCAP writer options shared by homing's writers: zstd chunks, compressed on this thread
/// (multi-threaded zstd output would depend on the machine's core count), so that the same
/// input gives a byte-identical file.
pub fn write_options(profile: &str) -> ::mcap::WriteOptions {
    ::mcap::WriteOptions::new()
        .profile(profile)
        .compression(Some(::mcap::Compression::Zstd))
        .compression_threads(0)
}

/// What [`tum_to_mcap`] wrote.
#[derive(Debug, Clone, Default)]
pub struct ConvertStats {
    pub colour: usize,
    pub depth: usize,
    pub camera_info: usize,
    pub groundtruth: usize,
    pub camera: Option<String>,
    pub bytes: u64,
}

/// Converts a TUM RGB-D folder to a ROS 2 bag in MCAP: `rgb8` images on [`RGB_TOPIC`], `16UC1`
/// depth on [`DEPTH_TOPIC`], `CameraInfo` on [`CAMERA_INFO_TOPIC`] with each colour image when
/// the camera is known (`camera.toml` or the folder name), the ground truth on
/// [`GROUNDTRUTH_TOPIC`] (JSON). Depth keeps the TUM values (lossless; the units per metre are
/// in the channel metadata) unless `depth_mm`, which writes ROS's millimetres (rounded).
pub fn tum_to_mcap(dir: &Path, out: &Path, depth_mm: bool) -> Result<ConvertStats> {
    if !dir.is_dir() {
        return Err(Error::file(dir, "is not a folder"));
    }
    let rgb_list = dir.join("rgb.txt");
    if !rgb_list.is_file() {
        return Err(Error::file(
            dir,
            "is not a TUM RGB-D folder: it has no rgb.txt",
        ));
    }
    let rgb = read_list(&rgb_list)?;
    let depth_list = dir.join("depth.txt");
    let depth = if depth_list.is_file() {
        read_list(&depth_list)?
    } else {
        Vec::new()
    };
    let camera = match resolve_camera(&Config::default(), None, dir) {
        Ok((c, _)) => Some(c),
        Err(e) if dir.join("camera.toml").is_file() => return Err(e),
        Err(e) => {
            tracing::warn!("no CameraInfo written: {e}");
            None
        }
    };
    let scale = camera.as_ref().map_or(5000.0, |c| c.depth_scale);
    let gt_path = dir.join("groundtruth.txt");
    let gt = if gt_path.is_file() {
        read_trajectory(&gt_path)?
    } else {
        Vec::new()
    };
    // Everything in log-time order (colour, its CameraInfo, depth, ground truth at a tie).
    let mut events: Vec<(u64, u8, usize)> = Vec::new();
    events.extend(
        rgb.iter()
            .enumerate()
            .map(|(i, e)| (seconds_to_ns(e.t), 0, i)),
    );
    events.extend(
        depth
            .iter()
            .enumerate()
            .map(|(i, e)| (seconds_to_ns(e.t), 2, i)),
    );
    events.extend(
        gt.iter()
            .enumerate()
            .map(|(i, p)| (seconds_to_ns(p.t), 3, i)),
    );
    events.sort_unstable();
    let mut stats = ConvertStats {
        camera: camera.as_ref().map(|c| c.name.clone()),
        ..Default::default()
    };
    let mcap_err = |e: ::mcap::McapError| Error::file(out, format!("cannot write MCAP: {e}"));
    crate::io::atomic_write_with(out, |w| {
        let mut mw =
            ::mcap::Writer::with_options(&mut *w, write_options("ros2")).map_err(mcap_err)?;
        let image_schema = mw
            .add_schema(IMAGE_SCHEMA, "ros2msg", cdr::IMAGE_MSG.as_bytes())
            .map_err(mcap_err)?;
        let none = BTreeMap::new();
        let rgb_ch = mw
            .add_channel(image_schema, RGB_TOPIC, "cdr", &none)
            .map_err(mcap_err)?;
        let depth_meta = if depth_mm {
            BTreeMap::new()
        } else {
            BTreeMap::from([(DEPTH_SCALE_KEY.to_string(), format!("{scale}"))])
        };
        let depth_ch = mw
            .add_channel(image_schema, DEPTH_TOPIC, "cdr", &depth_meta)
            .map_err(mcap_err)?;
        let info_ch = match &camera {
            Some(_) => {
                let s = mw
                    .add_schema(
                        CAMERA_INFO_SCHEMA,
                        "ros2msg",
                        cdr::CAMERA_INFO_MSG.as_bytes(),
                    )
                    .map_err(mcap_err)?;
                Some(
                    mw.add_channel(s, CAMERA_INFO_TOPIC, "cdr", &none)
                        .map_err(mcap_err)?,
                )
            }
            None => None,
        };
        let gt_ch = if gt.is_empty() {
            None
        } else {
            let s = mw
                .add_schema(
                    "foxglove.PoseInFrame",
                    "jsonschema",
                    POSE_JSON_SCHEMA.as_bytes(),
                )
                .map_err(mcap_err)?;
            Some(
                mw.add_channel(s, GROUNDTRUTH_TOPIC, "json", &none)
                    .map_err(mcap_err)?,
            )
        };
        if let Some(cam) = &camera {
            #[derive(serde::Serialize)]
            struct CameraOnly<'a> {
                camera: &'a CameraConfig,
            }
            let text = toml::to_string(&CameraOnly { camera: cam })
                .map_err(|e| Error::invalid(format!("cannot serialise the camera: {e}")))?;
            mw.write_metadata(&::mcap::records::Metadata {
                name: CAMERA_METADATA.into(),
                metadata: BTreeMap::from([("camera.toml".to_string(), text)]),
            })
            .map_err(mcap_err)?;
        }
        let mut seq = [0u32; 4];
        let frame_id = "camera_rgb_optical_frame";
        for &(ns, kind, i) in &events {
            let header = Header {
                stamp: Time::from_ns(ns),
                frame_id: frame_id.into(),
            };
            let mut put = |ch: u16, slot: usize, data: &[u8]| {
                seq[slot] += 1;
                mw.write_to_known_channel(
                    &MessageHeader {
                        channel_id: ch,
                        sequence: seq[slot],
                        log_time: ns,
                        publish_time: ns,
                    },
                    data,
                )
                .map_err(mcap_err)
            };
            match kind {
                0 => {
                    let p = dir.join(&rgb[i].file);
                    let img = png_rgb(&p)?;
                    let (w, h) = img.dimensions();
                    let msg = Image {
                        header: header.clone(),
                        height: h,
                        width: w,
                        encoding: "rgb8".into(),
                        is_bigendian: 0,
                        step: w * 3,
                        data: img.into_raw(),
                    };
                    put(rgb_ch, 0, &cdr::encode_image(&msg))?;
                    stats.colour += 1;
                    if let (Some(ch), Some(cam)) = (info_ch, &camera) {
                        put(ch, 1, &cdr::encode_camera_info(&camera_info(cam, header)))?;
                        stats.camera_info += 1;
                    }
                }
                2 => {
                    let p = dir.join(&depth[i].file);
                    let (w, h, raw) = png_depth(&p)?;
                    let data: Vec<u8> = raw
                        .iter()
                        .map(|&v| {
                            if depth_mm {
                                (v as f64 * 1000.0 / scale).round().min(65535.0) as u16
                            } else {
                                v
                            }
                        })
                        .flat_map(u16::to_le_bytes)
                        .collect();
                    let msg = Image {
                        header,
                        height: h,
                        width: w,
                        encoding: "16UC1".into(),
                        is_bigendian: 0,
                        step: w * 2,
                        data,
                    };
                    put(depth_ch, 2, &cdr::encode_image(&msg))?;
                    stats.depth += 1;
                }
                _ => {
                    let Some(ch) = gt_ch else { continue };
                    let v = pose_json(gt[i].t, &gt[i].pose, serde_json::json!({}));
                    put(ch, 3, v.to_string().as_bytes())?;
                    stats.groundtruth += 1;
                }
            }
        }
        mw.finish().map_err(mcap_err)?;
        drop(mw);
        w.flush()
            .map_err(|e| Error::file(out, format!("cannot write: {e}")))
    })?;
    stats.bytes = std::fs::metadata(out).map(|m| m.len()).unwrap_or(0);
    Ok(stats)
}

/// A `CameraInfo` for a camera config (plumb bob distortion).
fn camera_info(cam: &CameraConfig, header: Header) -> CameraInfo {
    CameraInfo {
        header,
        height: cam.height,
        width: cam.width,
        distortion_model: "plumb_bob".into(),
        d: vec![cam.k1, cam.k2, cam.p1, cam.p2, cam.k3],
        k: [cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0],
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [
            cam.fx, 0.0, cam.cx, 0.0, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
        ],
        ..Default::default()
    }
}

/// A colour PNG as `io::tum::load_rgb` reads it (grey expanded to RGB).
fn png_rgb(path: &Path) -> Result<RgbImage> {
    crate::io::tum::to_rgb(path, open_image(path)?)
}

/// A 16-bit depth PNG's raw values.
fn png_depth(path: &Path) -> Result<(u32, u32, Vec<u16>)> {
    match open_image(path)? {
        DynamicImage::ImageLuma16(i) => Ok((i.width(), i.height(), i.into_raw())),
        other => Err(Error::file(
            path,
            format!(
                "depth image has pixel type {:?}; TUM depth must be a 16-bit single-channel PNG",
                other.color()
            ),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stamps_round_trip_through_nanoseconds() {
        for t in [1305031102.175304, 1305031102.2114, 0.5, 1000.0, 1000.033333] {
            let ns = seconds_to_ns(t);
            assert_eq!(ns_to_seconds(ns), t, "{t}");
        }
        assert_eq!(seconds_to_ns(1305031102.175304), 1_305_031_102_175_304_000);
        assert_eq!(seconds_to_ns(1.0000000005), 1_000_000_001);
    }
}
