//! Renders a scenario and writes it in the TUM RGB-D layout: `rgb/`, `depth/`, `rgb.txt`,
//! `depth.txt`, `groundtruth.txt`, plus `camera.toml` (read by `homing run`) and
//! `scenario.json` (steps and expected states). Frames are rendered in parallel; every random
//! draw is keyed by (seed, session, frame), so output bytes do not depend on scheduling.

use std::path::{Path, PathBuf};
use std::time::Instant;

use homing::config::CameraConfig;
use homing::io::tum::{StampedPose, save_depth, save_png, write_list, write_trajectory};
use homing::{Error, Result};
use image::DynamicImage;
use nalgebra::Isometry3;
use rayon::prelude::*;
use serde::Serialize;

use crate::render::{Intrinsics, RenderOut, render};
use crate::scenarios::{Scenario, Session};
use crate::sensor::{SensorOptions, colour_image, depth_image, stamp_offsets};
use crate::texture::mix;

/// Full-size frame rate of every scenario.
pub const FPS: f64 = 30.0;
/// Depth PNG units per metre (TUM).
pub const DEPTH_SCALE: f64 = 5000.0;
/// Exposure time simulated by `--motion-blur` (an indoor Kinect exposes ~10-30 ms).
pub const BLUR_EXPOSURE: f64 = 0.02;
/// Exposure gain while the lights are off.
pub const DARK_GAIN: f32 = 0.02;

#[derive(Debug, Clone)]
pub struct GenOptions {
    pub out: PathBuf,
    pub small: bool,
    pub seed: u64,
    pub sensor: SensorOptions,
    /// Render only the first n frames of each session (for quick looks and tests).
    pub max_frames: Option<usize>,
}

impl GenOptions {
    pub fn size(&self) -> (u32, u32) {
        if self.small { (320, 240) } else { (640, 480) }
    }
}

/// What was written.
#[derive(Debug, Clone)]
pub struct Stats {
    pub frames: usize,
    pub seconds: f64,
    pub dirs: Vec<PathBuf>,
}

impl Stats {
    pub fn fps(&self) -> f64 {
        self.frames as f64 / self.seconds.max(1e-9)
    }
}

/// One frame to render.
#[derive(Debug, Clone, Copy)]
pub struct FramePlan {
    pub index: usize,
    pub leg: usize,
    /// Script time of the exposure (stamp minus `stamp0`).
    pub t: f64,
    pub t_rgb: f64,
    pub t_depth: f64,
    pub pose: Isometry3<f64>,
}

/// Frame times of a session: 30 Hz along each leg (every `stride`-th frame), no frames in the
/// gaps between legs.
pub fn plan_frames(
    sess: &Session,
    stride: usize,
    sensor: &SensorOptions,
    seed: u64,
) -> Vec<FramePlan> {
    let mut out = Vec::new();
    let dt = 1.0 / FPS;
    for (li, leg) in sess.legs.iter().enumerate() {
        let n = ((leg.end() - leg.start()) / dt + 1e-6).floor() as usize + 1;
        for k in (0..n).step_by(stride.max(1)) {
            let index = out.len();
            let (jit, doff) = stamp_offsets(sensor, seed, index as u64);
            let t = (leg.start() + k as f64 * dt + jit).clamp(leg.start(), leg.end());
            let t_rgb = round6(sess.stamp0 + t);
            let t_depth = round6(t_rgb + doff);
            out.push(FramePlan {
                index,
                leg: li,
                t,
                t_rgb,
                t_depth,
                pose: leg.pose(t),
            });
        }
    }
    out
}

/// Stamps are written with 6 decimals; round once so lists, file names and ground truth agree.
fn round6(t: f64) -> f64 {
    (t * 1e6).round() / 1e6
}

/// Exposure gain at script time t: 1 with lights on, `DARK_GAIN` when off, 0.3 s ramps.
pub fn gain_at(sess: &Session, t: f64, sensor: &SensorOptions) -> f32 {
    if !sensor.darkness {
        return 1.0;
    }
    let mut g = 1.0f64;
    for &(a, b) in &sess.dark {
        let ramp = 0.3;
        let inside = ((t - a) / ramp)
            .clamp(0.0, 1.0)
            .min(((b - t) / ramp).clamp(0.0, 1.0));
        let s = inside * inside * (3.0 - 2.0 * inside);
        g = g.min(1.0 - (1.0 - DARK_GAIN as f64) * s);
    }
    g as f32
}

#[derive(Serialize)]
struct StepJson<'a> {
    step: usize,
    name: &'a str,
    event: &'a str,
    first_frame: usize,
    last_frame: usize,
    t_start: f64,
    t_end: f64,
    expected_states: &'a [String],
}

#[derive(Serialize)]
struct ScenarioJson<'a> {
    scenario: &'a str,
    description: &'a str,
    session: &'a str,
    seed: u64,
    width: u32,
    height: u32,
    fps: f64,
    frames: usize,
    small: bool,
    motion: &'a str,
    world_frame: &'a str,
    camera_frame: &'a str,
    depth_scale: f64,
    sensor: &'a SensorOptions,
    dark_intervals: Vec<(f64, f64)>,
    kidnappings: Vec<(f64, f64)>,
    steps: Vec<StepJson<'a>>,
    landmarks: Vec<(&'a str, [f64; 3])>,
}

#[derive(Serialize)]
struct CameraFile<'a> {
    camera: &'a CameraConfig,
}

pub const WORLD_FRAME: &str = "x east, y north, z up (metres); floor at z = 0";
pub const CAMERA_FRAME: &str =
    "TUM/OpenCV camera axes: x right, y down, z forward; poses are camera-to-world";

/// Camera configuration written next to the images.
pub fn camera_config(k: &Intrinsics, fps: f64, scenario: &str) -> CameraConfig {
    CameraConfig {
        name: format!("homing-datasets synthetic ({scenario})"),
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        k1: 0.0,
        k2: 0.0,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
        width: k.width,
        height: k.height,
        depth_scale: DEPTH_SCALE,
        fps,
        // The renderer exposes every pixel at once (global shutter).
        readout_s: 0.0,
        // Depth weighs as for TUM's Kinects (0.16 m measured better on these scenarios; see
        // docs/decisions/0012-depth-weight-and-keypoint-coordinates.md).
        virtual_baseline_m: homing::config::default_virtual_baseline(),
    }
}

fn io_err(path: &Path, e: impl std::fmt::Display) -> Error {
    Error::file(path, e)
}

fn average(a: &mut RenderOut, others: &[RenderOut]) {
    let n = (others.len() + 1) as f32;
    for (i, v) in a.rgb.iter_mut().enumerate() {
        let s: f32 = others.iter().map(|o| o.rgb[i]).sum();
        *v = (*v + s) / n;
    }
}

/// Renders and writes every session of `sc`.
pub fn generate(sc: &Scenario, opts: &GenOptions) -> Result<Stats> {
    let start = Instant::now();
    let (w, h) = opts.size();
    let k = Intrinsics::kinect(w, h);
    let stride = if opts.small { sc.small_stride } else { 1 };
    let fps = FPS / stride as f64;
    let mut total = 0;
    let mut dirs = Vec::new();
    for (si, sess) in sc.sessions.iter().enumerate() {
        let dir = match &sess.dir {
            Some(d) => opts.out.join(d),
            None => opts.out.clone(),
        };
        for sub in ["rgb", "depth"] {
            std::fs::create_dir_all(dir.join(sub)).map_err(|e| io_err(&dir.join(sub), e))?;
        }
        let seed = mix(opts.seed ^ mix(si as u64 + 1));
        let mut frames = plan_frames(sess, stride, &opts.sensor, seed);
        if let Some(n) = opts.max_frames {
            frames.truncate(n);
        }
        frames.par_iter().try_for_each(|f| -> Result<()> {
            let mut r = render(&sc.scene, &k, &f.pose);
            if opts.sensor.motion_blur {
                let leg = &sess.legs[f.leg];
                let extra: Vec<RenderOut> = [
                    -0.5 * BLUR_EXPOSURE,
                    -0.25 * BLUR_EXPOSURE,
                    0.25 * BLUR_EXPOSURE,
                    0.5 * BLUR_EXPOSURE,
                ]
                .iter()
                .map(|d| render(&sc.scene, &k, &leg.pose(f.t + d)))
                .collect();
                average(&mut r, &extra);
            }
            let gain = gain_at(sess, f.t, &opts.sensor);
            let rgb = colour_image(&r, gain, &opts.sensor, seed, f.index as u64);
            let depth = depth_image(&r, &opts.sensor, seed, f.index as u64);
            save_png(
                &dir.join(format!("rgb/{:.6}.png", f.t_rgb)),
                &DynamicImage::ImageRgb8(rgb),
            )?;
            save_depth(
                &dir.join(format!("depth/{:.6}.png", f.t_depth)),
                &depth,
                DEPTH_SCALE,
            )
        })?;
        let header = format!(
            "homing-datasets {} {} seed {}",
            sc.name, sess.name, opts.seed
        );
        let rgb_list: Vec<(f64, String)> = frames
            .iter()
            .map(|f| (f.t_rgb, format!("rgb/{:.6}.png", f.t_rgb)))
            .collect();
        let depth_list: Vec<(f64, String)> = frames
            .iter()
            .map(|f| (f.t_depth, format!("depth/{:.6}.png", f.t_depth)))
            .collect();
        write_list(
            &dir.join("rgb.txt"),
            &rgb_list,
            &format!("color images\n{header}"),
        )?;
        write_list(
            &dir.join("depth.txt"),
            &depth_list,
            &format!("depth maps\n{header}"),
        )?;
        let gt: Vec<StampedPose> = frames
            .iter()
            .map(|f| StampedPose {
                t: f.t_rgb,
                pose: f.pose,
            })
            .collect();
        write_trajectory(
            &dir.join("groundtruth.txt"),
            &gt,
            &format!("ground truth trajectory\n{header}"),
        )?;
        let cam = camera_config(&k, fps, &sc.name);
        let toml = toml::to_string(&CameraFile { camera: &cam })
            .map_err(|e| Error::Invalid(format!("cannot serialise camera.toml: {e}")))?;
        write_atomic(&dir.join("camera.toml"), toml.as_bytes())?;
        let json = scenario_json(sc, sess, &frames, opts, &k, fps)?;
        write_atomic(&dir.join("scenario.json"), json.as_bytes())?;
        total += frames.len();
        dirs.push(dir);
    }
    Ok(Stats {
        frames: total,
        seconds: start.elapsed().as_secs_f64(),
        dirs,
    })
}

/// Frame range (index into `sess.steps`, first frame, last frame) of every step that has
/// frames: a step runs from its start time to the next step's start; the first step also takes
/// any frame before its start.
pub fn step_ranges(sess: &Session, frames: &[FramePlan]) -> Vec<(usize, usize, usize)> {
    let mut out = Vec::new();
    for (i, st) in sess.steps.iter().enumerate() {
        let t_next = sess.steps.get(i + 1).map_or(f64::INFINITY, |n| n.t_start);
        let first = if i == 0 {
            Some(0)
        } else {
            frames.iter().position(|f| f.t >= st.t_start - 1e-9)
        };
        let last = frames.iter().rposition(|f| f.t < t_next - 1e-9);
        if let (Some(a), Some(b)) = (first, last)
            && a <= b
        {
            out.push((i, a, b));
        }
    }
    out
}

fn scenario_json(
    sc: &Scenario,
    sess: &Session,
    frames: &[FramePlan],
    opts: &GenOptions,
    k: &Intrinsics,
    fps: f64,
) -> Result<String> {
    let steps = step_ranges(sess, frames)
        .into_iter()
        .map(|(i, a, b)| {
            let st = &sess.steps[i];
            StepJson {
                step: st.step,
                name: &st.name,
                event: &st.event,
                first_frame: a,
                last_frame: b,
                t_start: frames[a].t_rgb,
                t_end: frames[b].t_rgb,
                expected_states: &st.expected,
            }
        })
        .collect();
    let kidnappings = sess
        .legs
        .windows(2)
        .map(|l| {
            (
                round6(sess.stamp0 + l[0].end()),
                round6(sess.stamp0 + l[1].start()),
            )
        })
        .collect();
    let dark_intervals = if opts.sensor.darkness {
        sess.dark
            .iter()
            .map(|(a, b)| (round6(sess.stamp0 + a), round6(sess.stamp0 + b)))
            .collect()
    } else {
        vec![]
    };
    let j = ScenarioJson {
        scenario: &sc.name,
        description: &sc.description,
        session: &sess.name,
        seed: opts.seed,
        width: k.width,
        height: k.height,
        fps,
        frames: frames.len(),
        small: opts.small,
        motion: &sc.motion,
        world_frame: WORLD_FRAME,
        camera_frame: CAMERA_FRAME,
        depth_scale: DEPTH_SCALE,
        sensor: &opts.sensor,
        dark_intervals,
        kidnappings,
        steps,
        landmarks: sc
            .scene
            .landmarks
            .iter()
            .map(|l| (l.name.as_str(), l.p))
            .collect(),
    };
    serde_json::to_string_pretty(&j)
        .map_err(|e| Error::Invalid(format!("cannot serialise scenario.json: {e}")))
}

/// Writes via a temporary file and a rename, like homing's own writers.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes).map_err(|e| io_err(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| io_err(path, e))
}
