//! `homing report`: one self-contained HTML page from a run's output folder.
//!
//! Reads the run-output contract (`trajectory.txt`, `keyframes.txt`, `states.csv`,
//! `closures.csv`, `summary.json`) and, when there is ground truth (`--gt`, else the recorded
//! sequence's `groundtruth.txt`), evaluates exactly as `homing eval` does (the same
//! association, SE3 or — for monocular runs — Sim3 alignment, ATE, RPE over 1 s). The page
//! holds:
//!
//! - the trajectory's top view against the ground truth (equal aspect, keyframes marked);
//! - the translational error over time, with the controller's state timeline as a coloured band
//!   under it on the same time axis (one colour per state, legend);
//! - the per-stage timing: median / p90 / max table and chart from summary.json, and
//!   histograms of the per-call samples from timing.csv;
//! - map and closure statistics, and the closure candidates.
//!
//! Plots are PNGs rendered in memory with plotters (the bundled DejaVu font) and embedded as
//! base64 `data:` URIs: the file references nothing outside itself. It is written atomically.

use crate::error::{Error, Result};
use crate::eval::plot::{equal_aspect, padded_range, principal_axes, register_font};
use crate::eval::run::{ClosureCheck, MapAte};
use crate::eval::{self, Alignment, Associated, AteResult, RpeResult, RpeUnit};
use crate::io::atomic_write;
use crate::io::tum::{StampedPose, read_trajectory};
use crate::outputs::{
    ClosureRow, StateCsvRow, Summary, read_closures, read_state_maps, read_states,
};
use base64::Engine as _;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use plotters::coord::Shift;
use plotters::prelude::*;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Association window (seconds), as the evaluation uses.
const MAX_DT: f64 = 0.02;

/// Everything the report is made from.
pub struct RunData {
    pub dir: PathBuf,
    pub summary: serde_json::Value,
    pub trajectory: Vec<StampedPose>,
    /// Keyframe poses (camera-to-world) with their map.
    pub keyframes: Vec<(StampedPose, u32)>,
    pub states: Vec<StateCsvRow>,
    pub closures: Vec<ClosureRow>,
    /// Map of each pose, by stamp (from states.csv).
    pub pose_maps: Vec<(f64, u32)>,
    /// Ground truth and where it came from.
    pub gt: Option<(PathBuf, Vec<StampedPose>)>,
    /// Per-stage samples from timing.csv (empty for runs written before it existed).
    pub timing_samples: BTreeMap<String, Vec<f64>>,
}

/// Reads timing.csv (`stage,ms` per call); a missing file is no samples.
pub fn read_timing_samples(path: &Path) -> Result<BTreeMap<String, Vec<f64>>> {
    let mut out: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    if !path.exists() {
        return Ok(out);
    }
    let text = crate::error::read_text(path)?;
    for (i, line) in text.lines().enumerate() {
        if i == 0 {
            if line.trim() != "stage,ms" {
                return Err(Error::parse(path, 1, "expected the header `stage,ms`"));
            }
            continue;
        }
        if line.trim().is_empty() {
            continue;
        }
        let (stage, ms) = line
            .rsplit_once(',')
            .ok_or_else(|| Error::parse(path, i + 1, "expected `stage,ms`"))?;
        let ms: f64 = ms
            .trim()
            .parse()
            .ok()
            .filter(|v: &f64| v.is_finite() && *v >= 0.0)
            .ok_or_else(|| Error::parse(path, i + 1, format!("`{ms}` is not a duration in ms")))?;
        out.entry(stage.trim().to_string()).or_default().push(ms);
    }
    Ok(out)
}

/// Reads a run's output folder; `gt` overrides the sequence's `groundtruth.txt`.
pub fn load_run(dir: &Path, gt: Option<&Path>) -> Result<RunData> {
    if !dir.is_dir() {
        return Err(Error::file(
            dir,
            "not a folder (expected a `homing run` output folder)",
        ));
    }
    let summary_path = dir.join("summary.json");
    let text = crate::error::read_text(&summary_path)?;
    let summary: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| Error::parse(&summary_path, e.line(), format!("not valid JSON: {e}")))?;
    if !summary.is_object() {
        return Err(Error::parse(&summary_path, 1, "expected a JSON object"));
    }
    for key in ["frames", "keyframes", "maps"] {
        if !summary.get(key).is_some_and(|v| v.is_u64()) {
            return Err(Error::file(
                &summary_path,
                format!("not a homing summary.json: `{key}` is missing or not a count"),
            ));
        }
    }
    if let Some(t) = summary.get("timing") {
        timing_rows(t).map_err(|m| Error::file(&summary_path, format!("timing: {m}")))?;
    }
    let trajectory = read_trajectory(&dir.join("trajectory.txt"))?;
    let keyframes = read_keyframes(&dir.join("keyframes.txt"))?;
    let states = read_states(&dir.join("states.csv"))?;
    let pose_maps = read_state_maps(&dir.join("states.csv"))?;
    let closures = read_closures(&dir.join("closures.csv"))?;
    let timing_samples = read_timing_samples(&dir.join("timing.csv"))?;
    let gt_path = match gt {
        Some(p) => Some(p.to_path_buf()),
        None => summary
            .get("sequence")
            .and_then(|s| s.as_str())
            .map(|s| Path::new(s).join("groundtruth.txt"))
            .filter(|p| p.is_file()),
    };
    let gt = match gt_path {
        Some(p) => {
            let poses = read_trajectory(&p)?;
            if poses.is_empty() {
                return Err(Error::file(&p, "holds no poses"));
            }
            Some((p, poses))
        }
        None => None,
    };
    Ok(RunData {
        dir: dir.to_path_buf(),
        summary,
        trajectory,
        keyframes,
        states,
        closures,
        pose_maps,
        gt,
        timing_samples,
    })
}

/// Reads `keyframes.txt`: `timestamp tx ty tz qx qy qz qw map_id` per line (maps one after
/// the other, so stamps need not increase).
pub fn read_keyframes(path: &Path) -> Result<Vec<(StampedPose, u32)>> {
    let text = crate::error::read_text(path)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let n = i + 1;
        let l = line.trim();
        if l.is_empty() || l.starts_with('#') {
            continue;
        }
        let f: Vec<&str> = l.split_whitespace().collect();
        if f.len() != 9 {
            return Err(Error::parse(
                path,
                n,
                format!(
                    "expected 9 columns 'timestamp tx ty tz qx qy qz qw map_id', found {}",
                    f.len()
                ),
            ));
        }
        let names = ["time stamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"];
        let mut v = [0.0; 8];
        for k in 0..8 {
            v[k] = f[k]
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| {
                    Error::parse(path, n, format!("{}: not a number: {:?}", names[k], f[k]))
                })?;
        }
        let map = f[8]
            .parse::<u32>()
            .map_err(|_| Error::parse(path, n, format!("map_id: not an integer: {:?}", f[8])))?;
        let q = Quaternion::new(v[7], v[4], v[5], v[6]);
        if (q.norm() - 1.0).abs() > 1e-3 {
            return Err(Error::parse(
                path,
                n,
                "quaternion (qx qy qz qw) is not unit length",
            ));
        }
        out.push((
            StampedPose {
                t: v[0],
                pose: Isometry3::from_parts(
                    Translation3::new(v[1], v[2], v[3]),
                    UnitQuaternion::from_quaternion(q),
                ),
            },
            map,
        ));
    }
    Ok(out)
}

/// One row of the timing table.
#[derive(Debug, Clone, PartialEq)]
struct TimingRow {
    stage: String,
    median: f64,
    p90: f64,
    max: f64,
    mean: Option<f64>,
    count: Option<u64>,
}

/// The stages in pipeline order; others follow alphabetically.
const STAGE_ORDER: [&str; 12] = [
    "frame",
    "load",
    "preprocess",
    "extract_track",
    "track",
    "initialize",
    "map",
    "loop_closing",
    "recognize",
    "global_opt",
    "recover",
    "final_ba",
];

fn timing_rows(t: &serde_json::Value) -> std::result::Result<Vec<TimingRow>, String> {
    let obj = t.as_object().ok_or("expected an object of stages")?;
    let mut rows = Vec::new();
    for (stage, v) in obj {
        let num = |k: &str| {
            v.get(k)
                .and_then(|x| x.as_f64())
                .ok_or_else(|| format!("stage `{stage}`: `{k}` is missing or not a number"))
        };
        rows.push(TimingRow {
            stage: stage.clone(),
            median: num("median_ms")?,
            p90: num("p90_ms")?,
            max: num("max_ms")?,
            mean: v.get("mean_ms").and_then(|x| x.as_f64()),
            count: v.get("count").and_then(|x| x.as_u64()),
        });
    }
    let rank = |s: &str| {
        STAGE_ORDER
            .iter()
            .position(|&k| k == s)
            .unwrap_or(STAGE_ORDER.len())
    };
    rows.sort_by(|a, b| {
        rank(&a.stage)
            .cmp(&rank(&b.stage))
            .then(a.stage.cmp(&b.stage))
    });
    Ok(rows)
}

/// The evaluation of the run against ground truth, as `homing eval` computes it.
struct Evaluation {
    align: Alignment,
    assoc: Associated,
    ate: AteResult,
    rpe: std::result::Result<RpeResult, String>,
    closures: ClosureCheck,
    per_map: Vec<MapAte>,
    largest: Option<u32>,
}

fn is_mono(summary: &serde_json::Value) -> bool {
    let p = |ptr: &str| summary.pointer(ptr).and_then(|v| v.as_bool());
    p("/perturbations/spec/mono")
        .or(p("/config/sequence/mono"))
        .unwrap_or(false)
}

fn evaluate(run: &RunData) -> Option<std::result::Result<Evaluation, String>> {
    let (_, gt) = run.gt.as_ref()?;
    let align = if is_mono(&run.summary) {
        Alignment::Sim3
    } else {
        Alignment::Se3
    };
    if run.trajectory.len() < 3 {
        return Some(Err(format!(
            "{} poses: too few to align and evaluate",
            run.trajectory.len()
        )));
    }
    let assoc = match eval::associate_and_align(gt, &run.trajectory, align, MAX_DT) {
        Ok(a) => a,
        Err(e) => return Some(Err(e.to_string())),
    };
    let ate = eval::ate(&assoc, align);
    let rpe = eval::rpe(&assoc, 1.0, RpeUnit::Seconds, false).map_err(|e| e.to_string());
    let (per_map, largest) =
        eval::run::per_map_ate(gt, &run.trajectory, &run.pose_maps, align, MAX_DT);
    let mono =
        (align == Alignment::Sim3).then(|| eval::run::MonoScales::from_maps(&per_map, largest));
    let closures = eval::run::check_closures(&run.closures, gt, MAX_DT, mono.as_ref());
    Some(Ok(Evaluation {
        align,
        assoc,
        ate,
        rpe,
        closures,
        per_map,
        largest,
    }))
}

/// Coverage as the run defines it (summary.json: frames the sequence delivers, i.e. colour
/// frames with a depth partner, that have a pose). Recomputed from the sequence's rgb.txt only
/// for a run evaluated without it; that count includes colour frames without depth.
fn coverage(run: &RunData) -> Option<f64> {
    if let Some(c) = run
        .summary
        .pointer("/evaluation/coverage")
        .and_then(|v| v.as_f64())
    {
        return Some(c);
    }
    let (_, gt) = run.gt.as_ref()?;
    let rgb = run
        .summary
        .get("sequence")
        .and_then(|s| s.as_str())
        .map(|s| Path::new(s).join("rgb.txt"))?;
    let list = crate::io::tum::read_list(&rgb).ok()?;
    let stamps: Vec<f64> = list.iter().map(|e| e.t).collect();
    let eligible = eval::eligible_stamps(&stamps, gt, MAX_DT);
    (!eligible.is_empty()).then(|| eval::coverage(&eligible, &run.trajectory, MAX_DT))
}

// ---------------------------------------------------------------------------------------------
// Plots

/// A rendered plot: PNG bytes and size.
pub struct Png {
    pub bytes: Vec<u8>,
    pub width: u32,
    pub height: u32,
}

fn draw_err<E: std::fmt::Display>(e: E) -> Error {
    Error::invalid(format!("cannot draw the report's plots: {e}"))
}

fn render(
    w: u32,
    h: u32,
    draw: impl FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> Result<()>,
) -> Result<Png> {
    register_font();
    let mut buf = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(draw_err)?;
        draw(&root)?;
        root.present().map_err(draw_err)?;
    }
    let img = image::RgbImage::from_raw(w, h, buf).expect("buffer has w*h*3 bytes");
    let mut png = std::io::Cursor::new(Vec::new());
    image::DynamicImage::ImageRgb8(img)
        .write_to(&mut png, image::ImageFormat::Png)
        .map_err(|e| Error::invalid(format!("cannot encode PNG: {e}")))?;
    Ok(Png {
        bytes: png.into_inner(),
        width: w,
        height: h,
    })
}

/// Colours for maps (estimate points) and unknown states.
const PALETTE: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
    RGBColor(127, 127, 127),
];

/// One fixed colour per state name (the same in every report).
fn state_color(state: &str, unknown_index: usize) -> RGBColor {
    match state {
        "Init" => RGBColor(160, 160, 160),
        "Idle" => RGBColor(255, 191, 0),
        "Mapping" => RGBColor(44, 160, 44),
        "Core(M&R)" => RGBColor(23, 190, 207),
        "Localized" => RGBColor(31, 119, 180),
        "Relocalization" | "Relocalize" => RGBColor(148, 103, 189),
        "CorruptedMap" => RGBColor(214, 39, 40),
        "Final" => RGBColor(40, 40, 40),
        _ => PALETTE[(unknown_index + 4) % PALETTE.len()],
    }
}

/// Tick labels with as many decimals as the axis range needs, and no "-0.0".
fn tick_format(r: &std::ops::Range<f64>) -> impl Fn(&f64) -> String + use<> {
    let step = (r.end - r.start).abs() / 10.0;
    let d = if step > 0.0 {
        (-step.log10()).ceil().clamp(0.0, 6.0) as usize
    } else {
        2
    };
    move |v: &f64| {
        let s = format!("{v:.d$}");
        if s.chars().all(|c| matches!(c, '-' | '0' | '.')) {
            s.trim_start_matches('-').to_string()
        } else {
            s
        }
    }
}

fn stamp_key(t: f64) -> i64 {
    (t * 1e6).round() as i64
}

/// Top view: ground truth, the aligned estimate (coloured by map), keyframes. Equal aspect.
fn plot_top_view(run: &RunData, ev: Option<&Evaluation>) -> Result<Png> {
    const W: u32 = 1000;
    let gt: Vec<Vector3<f64>> = run
        .gt
        .as_ref()
        .map(|(_, g)| g.iter().map(|p| p.pose.translation.vector).collect())
        .unwrap_or_default();
    // The estimate: aligned (with its stamps) when there is an evaluation, else as written.
    let (est, est_t, transform): (Vec<Vector3<f64>>, Vec<f64>, Option<&crate::geometry::Sim3>) =
        match ev {
            Some(e) => (
                e.assoc
                    .estimate
                    .iter()
                    .map(|p| p.translation.vector)
                    .collect(),
                e.assoc.t.clone(),
                Some(&e.assoc.alignment),
            ),
            None => (
                run.trajectory
                    .iter()
                    .map(|p| p.pose.translation.vector)
                    .collect(),
                run.trajectory.iter().map(|p| p.t).collect(),
                None,
            ),
        };
    let kfs: Vec<Vector3<f64>> = run
        .keyframes
        .iter()
        .map(|(p, _)| {
            let v = p.pose.translation.vector;
            transform.map_or(v, |a| a.transform_point(&v))
        })
        .collect();
    let (mean, a1, a2) = principal_axes(if gt.len() >= 3 { &gt } else { &est });
    let proj = |p: &Vector3<f64>| ((p - mean).dot(&a1), (p - mean).dot(&a2));
    let gt2: Vec<(f64, f64)> = gt.iter().map(proj).collect();
    let est2: Vec<(f64, f64)> = est.iter().map(proj).collect();
    let kf2: Vec<(f64, f64)> = kfs.iter().map(proj).collect();
    let map_of: BTreeMap<i64, u32> = run
        .pose_maps
        .iter()
        .map(|&(t, m)| (stamp_key(t), m))
        .collect();
    let mut by_map: BTreeMap<u32, Vec<(f64, f64)>> = BTreeMap::new();
    for (p, t) in est2.iter().zip(&est_t) {
        let m = map_of.get(&stamp_key(*t)).copied().unwrap_or(0);
        by_map.entry(m).or_default().push(*p);
    }
    let align_name = ev.map_or("not aligned".to_string(), |e| {
        format!("{:?}-aligned", e.align).to_lowercase()
    });
    // The image's height follows the trajectory's shape (a corridor gives a flat image), within
    // limits; the equal aspect is then made exact on the plotting area.
    let h = {
        let all = gt2.iter().chain(&est2).chain(&kf2);
        let (xr, yr) = (
            padded_range(all.clone().map(|p| p.0)),
            padded_range(all.map(|p| p.1)),
        );
        let plot_w = (W - 15 - 25 - 70) as f64;
        let plot_h = plot_w * (yr.end - yr.start) / (xr.end - xr.start);
        plot_h.clamp(260.0, 700.0) as u32 + 15 + 15 + 50
    };
    render(W, h, |root| {
        let area = root.margin(15, 15, 15, 25);
        let build = |xr: std::ops::Range<f64>, yr: std::ops::Range<f64>| {
            ChartBuilder::on(&area)
                .x_label_area_size(50)
                .y_label_area_size(70)
                .build_cartesian_2d(xr, yr)
                .map_err(draw_err)
        };
        // The plotting area's size in pixels, to make a metre equally long on both axes.
        let (pw, ph) = build(0.0..1.0, 0.0..1.0)?.plotting_area().dim_in_pixel();
        let all = gt2.iter().chain(&est2).chain(&kf2);
        let (xr, yr) = equal_aspect(
            padded_range(all.clone().map(|p| p.0)),
            padded_range(all.map(|p| p.1)),
            pw as f64 / ph as f64,
        );
        let (fx, fy) = (tick_format(&xr), tick_format(&yr));
        let mut c = build(xr, yr)?;
        c.configure_mesh()
            .x_label_formatter(&fx)
            .y_label_formatter(&fy)
            .x_desc("principal axis 1 of the ground truth [m]")
            .y_desc("principal axis 2 [m]")
            .label_style(("sans-serif", 16))
            .axis_desc_style(("sans-serif", 18))
            .draw()
            .map_err(draw_err)?;
        if !gt2.is_empty() {
            c.draw_series(LineSeries::new(gt2.clone(), BLACK.stroke_width(2)))
                .map_err(draw_err)?
                .label("ground truth")
                .legend(|(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], BLACK.stroke_width(2))
                });
        }
        let several = by_map.len() > 1;
        for (i, (m, pts)) in by_map.iter().enumerate() {
            let col = PALETTE[i % PALETTE.len()];
            let label = if several {
                format!("estimate, map {m} ({align_name})")
            } else {
                format!("estimate ({align_name})")
            };
            c.draw_series(pts.iter().map(|&p| Circle::new(p, 2, col.filled())))
                .map_err(draw_err)?
                .label(label)
                .legend(move |(x, y)| Circle::new((x + 10, y), 4, col.filled()));
        }
        if !kf2.is_empty() {
            let kc = RGBColor(214, 39, 40);
            c.draw_series(kf2.iter().map(|&p| {
                EmptyElement::at(p) + Rectangle::new([(-4, -4), (4, 4)], kc.stroke_width(2))
            }))
            .map_err(draw_err)?
            .label("keyframes")
            .legend(move |(x, y)| {
                Rectangle::new([(x + 6, y - 4), (x + 14, y + 4)], kc.stroke_width(2))
            });
        }
        c.configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .label_font(("sans-serif", 16))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()
            .map_err(draw_err)?;
        Ok(())
    })
}

/// A stretch of the state timeline.
#[derive(Debug, Clone, PartialEq)]
pub struct StateSpan {
    pub state: String,
    pub t0: f64,
    pub t1: f64,
}

/// The state timeline: consecutive stretches of one state, in stamps. A frame that passes
/// through several states (a transition row each) gives zero-length stretches for the states
/// it only passed through; a stretch ends one frame interval after its last frame, and where no
/// frames came for more than five frame intervals (dropped frames) the timeline has a hole.
pub fn state_spans(rows: &[StateCsvRow]) -> Vec<StateSpan> {
    // Frame interval: the median gap between distinct stamps.
    let mut stamps: Vec<f64> = rows.iter().map(|r| r.t).collect();
    stamps.dedup();
    let mut gaps: Vec<f64> = stamps
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|g| *g > 0.0)
        .collect();
    gaps.sort_by(|a, b| a.total_cmp(b));
    let dt = gaps.get(gaps.len() / 2).copied().unwrap_or(0.0);
    let mut spans: Vec<StateSpan> = Vec::new();
    let mut last_t = f64::NEG_INFINITY;
    for r in rows {
        let hole = dt > 0.0 && r.t - last_t > 5.0 * dt;
        match spans.last_mut() {
            Some(s) if s.state == r.state && !hole => s.t1 = r.t,
            _ => {
                if let Some(s) = spans.last_mut() {
                    s.t1 = if hole { last_t + dt } else { r.t };
                }
                spans.push(StateSpan {
                    state: r.state.clone(),
                    t0: r.t,
                    t1: r.t,
                });
            }
        }
        last_t = r.t;
    }
    if let Some(s) = spans.last_mut() {
        s.t1 += dt;
    }
    spans
}

/// The colour of each state of a legend (unknown names get palette colours in order).
fn state_colors(legend: &[(String, usize)]) -> BTreeMap<String, RGBColor> {
    let mut unknown = 0;
    let mut out = BTreeMap::new();
    for (s, _) in legend {
        let c = state_color(s, unknown);
        if c == state_color(s, unknown + 1) {
            // A fixed colour (a known state).
        } else {
            unknown += 1;
        }
        out.insert(s.clone(), c);
    }
    out
}

/// Distinct states in order of first appearance, with the number of frames each was active on
/// (a frame counts for every state it passed through).
fn state_legend(rows: &[StateCsvRow]) -> Vec<(String, usize)> {
    let mut out: Vec<(String, usize)> = Vec::new();
    let mut seen: std::collections::BTreeSet<(usize, String)> = Default::default();
    for r in rows {
        let first = seen.insert((r.frame, r.state.clone()));
        match out.iter_mut().find(|(s, _)| *s == r.state) {
            Some((_, n)) => *n += usize::from(first),
            None => out.push((r.state.clone(), 1)),
        }
    }
    out
}

/// The translational error over time (when evaluated) with the state band under it, both on
/// one time axis: seconds since the first frame.
fn plot_error_and_states(run: &RunData, ev: Option<&Evaluation>) -> Result<Png> {
    const W: u32 = 1200;
    let err_h: u32 = if ev.is_some() { 380 } else { 0 };
    let band_h: u32 = if ev.is_some() { 110 } else { 120 };
    const LEGEND_H: u32 = 60;
    let h = err_h + band_h + LEGEND_H;
    let spans = state_spans(&run.states);
    let legend = state_legend(&run.states);
    let colors = state_colors(&legend);
    let t0 = run
        .states
        .first()
        .map(|r| r.t)
        .or(ev.and_then(|e| e.assoc.t.first().copied()))
        .unwrap_or(0.0);
    let errs: Vec<(f64, f64)> = ev
        .map(|e| e.ate.errors.iter().map(|&(t, x)| (t - t0, x)).collect())
        .unwrap_or_default();
    let times = spans
        .iter()
        .flat_map(|s| [s.t0 - t0, s.t1 - t0])
        .chain(errs.iter().map(|p| p.0));
    let tr = {
        let r = padded_range(times);
        r.start.min(0.0)..r.end
    };
    // Same horizontal layout for both charts, so that a time is at the same x in both.
    const LEFT: u32 = 15;
    const RIGHT: u32 = 30;
    const Y_LABELS: u32 = 80;
    render(W, h, |root| {
        let (top, rest) = root.split_vertically(err_h);
        let (band, leg) = rest.split_vertically(band_h);
        if let Some(e) = ev {
            let area = top.margin(15, 5, LEFT, RIGHT);
            let emax = errs.iter().map(|p| p.1).fold(0.0, f64::max).max(1e-6) * 1.1;
            let mut c = ChartBuilder::on(&area)
                .x_label_area_size(0)
                .y_label_area_size(Y_LABELS)
                .build_cartesian_2d(tr.clone(), 0.0..emax)
                .map_err(draw_err)?;
            let fy = tick_format(&(0.0..emax));
            c.configure_mesh()
                .y_label_formatter(&fy)
                .y_desc("translational error [m]")
                .label_style(("sans-serif", 16))
                .axis_desc_style(("sans-serif", 18))
                .draw()
                .map_err(draw_err)?;
            // Broken where poses are missing (lost, dropped frames): gaps longer than 5 frame
            // intervals are not bridged.
            let mut gaps: Vec<f64> = errs.windows(2).map(|w| w[1].0 - w[0].0).collect();
            gaps.sort_by(|a, b| a.total_cmp(b));
            let dt = gaps.get(gaps.len() / 2).copied().unwrap_or(f64::INFINITY);
            let mut pieces: Vec<Vec<(f64, f64)>> = Vec::new();
            for &p in &errs {
                match pieces.last_mut() {
                    Some(v) if p.0 - v.last().expect("non-empty").0 <= 5.0 * dt => v.push(p),
                    _ => pieces.push(vec![p]),
                }
            }
            let red = RGBColor(214, 39, 40);
            for (i, piece) in pieces.into_iter().enumerate() {
                let s = c
                    .draw_series(LineSeries::new(piece, red.stroke_width(2)))
                    .map_err(draw_err)?;
                if i == 0 {
                    s.label(format!(
                        "ATE per pose ({}-aligned)",
                        format!("{:?}", e.align).to_lowercase()
                    ))
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], red.stroke_width(2))
                    });
                }
            }
            c.draw_series(std::iter::once(PathElement::new(
                vec![(tr.start, e.ate.stats.rmse), (tr.end, e.ate.stats.rmse)],
                BLACK.stroke_width(1),
            )))
            .map_err(draw_err)?
            .label(format!("RMSE {:.4} m", e.ate.stats.rmse))
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
            c.configure_series_labels()
                .position(SeriesLabelPosition::UpperLeft)
                .label_font(("sans-serif", 16))
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .draw()
                .map_err(draw_err)?;
        }
        let area = band.margin(if ev.is_some() { 5 } else { 15 }, 5, LEFT, RIGHT);
        let mut c = ChartBuilder::on(&area)
            .x_label_area_size(55)
            .y_label_area_size(Y_LABELS)
            .build_cartesian_2d(tr.clone(), 0.0..1.0)
            .map_err(draw_err)?;
        c.configure_mesh()
            .disable_y_mesh()
            .set_all_tick_mark_size(5)
            .y_labels(0)
            .x_desc("time since the first frame [s]")
            .y_desc("state")
            .label_style(("sans-serif", 16))
            .axis_desc_style(("sans-serif", 18))
            .draw()
            .map_err(draw_err)?;
        // One-frame states (Init, CorruptedMap, Final) would be invisible: every stretch is at
        // least 3 px wide, and later stretches are pushed right by the few pixels this takes.
        let (pw, _) = c.plotting_area().dim_in_pixel();
        let min_w = 3.0 * (tr.end - tr.start) / pw.max(1) as f64;
        let mut cursor = f64::NEG_INFINITY;
        let mut rects = Vec::new();
        for s in &spans {
            let a = (s.t0 - t0).max(cursor);
            let b = (s.t1 - t0).max(a + min_w);
            cursor = b;
            let col = colors.get(&s.state).copied().unwrap_or(BLACK);
            rects.push(Rectangle::new([(a, 0.0), (b, 1.0)], col.filled()));
        }
        c.draw_series(rects).map_err(draw_err)?;
        // Legend: a swatch and the state's name with its frame count.
        let leg = leg.margin(8, 0, LEFT + Y_LABELS, RIGHT);
        let font = TextStyle::from(("sans-serif", 17).into_font());
        let mut x = 0i32;
        let mut y = 4i32;
        let (lw, _) = leg.dim_in_pixel();
        for (s, n) in &legend {
            let text = format!("{s} ({n} frame{})", if *n == 1 { "" } else { "s" });
            let (tw, _) = leg.estimate_text_size(&text, &font).map_err(draw_err)?;
            let need = 26 + tw as i32 + 24;
            if x > 0 && x + need > lw as i32 {
                x = 0;
                y += 26;
            }
            let col = colors.get(s).copied().unwrap_or(BLACK);
            leg.draw(&Rectangle::new([(x, y), (x + 20, y + 16)], col.filled()))
                .map_err(draw_err)?;
            leg.draw(&Rectangle::new(
                [(x, y), (x + 20, y + 16)],
                BLACK.stroke_width(1),
            ))
            .map_err(draw_err)?;
            leg.draw(&Text::new(text, (x + 26, y), font.clone()))
                .map_err(draw_err)?;
            x += need;
        }
        Ok(())
    })
}

/// Per-stage timing: median bar, p90 bar behind it, max tick; log scale.
fn plot_timing(rows: &[TimingRow]) -> Result<Png> {
    const W: u32 = 1000;
    let h = 140 + 34 * rows.len().max(1) as u32;
    let lo = rows
        .iter()
        .map(|r| r.median)
        .filter(|v| *v > 0.0)
        .fold(f64::INFINITY, f64::min);
    let hi = rows.iter().map(|r| r.max).fold(0.0, f64::max);
    let lo = if lo.is_finite() { lo / 2.0 } else { 0.01 }.max(1e-3);
    let hi = (hi * 2.0).max(lo * 10.0);
    let n = rows.len() as u32;
    let names: Vec<String> = rows.iter().map(|r| r.stage.clone()).collect();
    let p90c = RGBColor(158, 202, 225);
    let medc = RGBColor(31, 119, 180);
    render(W, h, |root| {
        let (top, rest) = root.split_vertically(40);
        // Legend strip above the chart (inside it, it would hide the longest bars).
        let top = top.margin(12, 0, 160, 0);
        let font = TextStyle::from(("sans-serif", 17).into_font());
        let mut x = 0i32;
        for (name, col, w) in [("median", medc, 20), ("p90", p90c, 20), ("max", BLACK, 4)] {
            top.draw(&Rectangle::new([(x, 2), (x + w, 16)], col.filled()))
                .map_err(draw_err)?;
            top.draw(&Text::new(name, (x + w + 6, 0), font.clone()))
                .map_err(draw_err)?;
            x += w + 90;
        }
        let area = rest.margin(0, 10, 15, 30);
        // Integer coordinates are inclusive: 0..n-1 makes n rows.
        let mut c = ChartBuilder::on(&area)
            .x_label_area_size(50)
            .y_label_area_size(130)
            .build_cartesian_2d(
                (lo..hi).log_scale(),
                (0..n.saturating_sub(1)).into_segmented(),
            )
            .map_err(draw_err)?;
        let label = |v: &SegmentValue<u32>| match v {
            SegmentValue::CenterOf(i) => n
                .checked_sub(1 + *i)
                .and_then(|k| names.get(k as usize))
                .cloned()
                .unwrap_or_default(),
            _ => String::new(),
        };
        c.configure_mesh()
            .disable_y_mesh()
            .y_label_formatter(&label)
            .y_labels(rows.len().max(1))
            .x_desc("ms per call (log scale)")
            .label_style(("sans-serif", 16))
            .axis_desc_style(("sans-serif", 18))
            .draw()
            .map_err(draw_err)?;
        // Row 0 at the top.
        let y = |i: usize| n - 1 - i as u32;
        // The p90 bar first, the median bar over it.
        let bar = |v: fn(&TimingRow) -> f64, colour: RGBColor| {
            rows.iter().enumerate().map(move |(i, r)| {
                let mut b = Rectangle::new(
                    [
                        (lo, SegmentValue::Exact(y(i))),
                        (v(r).max(lo), SegmentValue::Exact(y(i) + 1)),
                    ],
                    colour.filled(),
                );
                b.set_margin(4, 4, 0, 0);
                b
            })
        };
        c.draw_series(bar(|r| r.p90, p90c)).map_err(draw_err)?;
        c.draw_series(bar(|r| r.median, medc)).map_err(draw_err)?;
        c.draw_series(rows.iter().enumerate().map(|(i, r)| {
            EmptyElement::at((r.max.max(lo), SegmentValue::CenterOf(y(i))))
                + Rectangle::new([(-2, -11), (2, 11)], BLACK.filled())
        }))
        .map_err(draw_err)?;
        Ok(())
    })
}

/// Stages shown as histograms: those that run once per frame or per keyframe.
const HISTOGRAM_STAGES: [&str; 6] = [
    "frame",
    "load",
    "preprocess",
    "track",
    "extract_track",
    "map",
];

/// Per-stage histograms of the per-call milliseconds (timing.csv), two per row, 30 bins from 0
/// to the 99th percentile (calls above it are counted in the last bin), median marked.
fn plot_timing_histograms(samples: &BTreeMap<String, Vec<f64>>) -> Result<Option<Png>> {
    let stages: Vec<(&str, &Vec<f64>)> = HISTOGRAM_STAGES
        .iter()
        .filter_map(|k| samples.get(*k).map(|v| (*k, v)))
        .filter(|(_, v)| v.len() >= 5)
        .collect();
    if stages.is_empty() {
        return Ok(None);
    }
    const W: u32 = 1000;
    const ROW: u32 = 230;
    let rows = stages.len().div_ceil(2) as u32;
    let png = render(W, ROW * rows, |root| {
        let cells = root.split_evenly((rows as usize, 2));
        for ((stage, v), cell) in stages.iter().zip(cells.iter()) {
            let mut sorted = (*v).clone();
            sorted.sort_by(f64::total_cmp);
            let pick = |q: f64| sorted[((sorted.len() - 1) as f64 * q).round() as usize];
            let median = pick(0.5);
            let hi = (pick(0.99) * 1.05).max(1e-3);
            const BINS: usize = 30;
            let width = hi / BINS as f64;
            let mut counts = [0u32; BINS];
            for x in &sorted {
                counts[((x / width) as usize).min(BINS - 1)] += 1;
            }
            let top = counts.iter().copied().max().unwrap_or(1).max(1) as f64 * 1.1;
            let mut c = ChartBuilder::on(&cell.margin(8, 8, 8, 16))
                .caption(
                    format!("{stage}: {} calls, median {median:.2} ms", v.len()),
                    ("sans-serif", 17),
                )
                .x_label_area_size(36)
                .y_label_area_size(48)
                .build_cartesian_2d(0.0..hi, 0.0..top)
                .map_err(draw_err)?;
            c.configure_mesh()
                .disable_x_mesh()
                .x_desc("ms per call")
                .y_desc("calls")
                .y_label_formatter(&|v: &f64| format!("{v:.0}"))
                .label_style(("sans-serif", 13))
                .axis_desc_style(("sans-serif", 14))
                .draw()
                .map_err(draw_err)?;
            let blue = RGBColor(31, 119, 180);
            c.draw_series(
                counts
                    .iter()
                    .enumerate()
                    .filter(|(_, n)| **n > 0)
                    .map(|(i, n)| {
                        let x0 = i as f64 * width;
                        let mut r =
                            Rectangle::new([(x0, 0.0), (x0 + width, *n as f64)], blue.filled());
                        r.set_margin(0, 0, 1, 1);
                        r
                    }),
            )
            .map_err(draw_err)?;
            c.draw_series(std::iter::once(PathElement::new(
                vec![(median, 0.0), (median, top)],
                BLACK.stroke_width(2),
            )))
            .map_err(draw_err)?;
        }
        Ok(())
    })?;
    Ok(Some(png))
}

// ---------------------------------------------------------------------------------------------
// HTML

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

fn img(png: &Png, alt: &str) -> String {
    format!(
        "<img width=\"{}\" height=\"{}\" alt=\"{}\" src=\"data:image/png;base64,{}\">",
        png.width,
        png.height,
        esc(alt),
        base64::engine::general_purpose::STANDARD.encode(&png.bytes)
    )
}

fn count(summary: &serde_json::Value, key: &str) -> String {
    match summary.get(key) {
        Some(serde_json::Value::Number(n)) => n.to_string(),
        Some(serde_json::Value::String(s)) => esc(s),
        _ => "n/a".into(),
    }
}

fn row(html: &mut String, k: &str, v: &str) {
    let _ = writeln!(html, "<tr><th>{}</th><td>{v}</td></tr>", esc(k));
}

const CSS: &str = "body{font-family:sans-serif;max-width:1240px;margin:1em auto;padding:0 1em;color:#222}\
h1{font-size:1.5em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}\
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:.2em .6em;text-align:left}\
td.n{text-align:right;font-variant-numeric:tabular-nums}th{background:#f4f4f4}\
img{max-width:100%;height:auto;display:block;margin:.5em 0}.note{color:#a40}code{background:#f4f4f4;padding:0 .2em}";

/// Renders the report page.
pub fn render_html(run: &RunData) -> Result<String> {
    let s = &run.summary;
    let ev_result = evaluate(run);
    let ev = ev_result.as_ref().and_then(|r| r.as_ref().ok());
    let ev_note = ev_result.as_ref().and_then(|r| r.as_ref().err());
    let coverage = coverage(run);
    let timing = s
        .get("timing")
        .map(timing_rows)
        .transpose()
        .map_err(|m| Error::file(&run.dir.join("summary.json"), format!("timing: {m}")))?
        .unwrap_or_default();

    let mut h = String::new();
    let title = format!("homing report: {}", run.dir.display());
    let _ = writeln!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>{}</title>\n<style>{CSS}</style>\n</head>\n<body>\n<h1>{}</h1>",
        esc(&title),
        esc(&title)
    );

    // Run
    let _ = writeln!(h, "<section id=\"run\">\n<h2>Run</h2>\n<table>");
    let str_of = |k: &str| s.get(k).and_then(|v| v.as_str()).map(esc);
    row(
        &mut h,
        "sequence",
        &str_of("sequence").unwrap_or_else(|| "n/a".into()),
    );
    if let Some(cmd) = s.get("command").and_then(|v| v.as_array()) {
        let c: Vec<&str> = cmd.iter().filter_map(|v| v.as_str()).collect();
        row(
            &mut h,
            "command",
            &format!("<code>{}</code>", esc(&c.join(" "))),
        );
    }
    row(&mut h, "controller", &count(s, "controller"));
    row(&mut h, "mode", &count(s, "mode"));
    row(
        &mut h,
        "input",
        if is_mono(s) {
            "monocular (depth suppressed)"
        } else {
            "RGB-D"
        },
    );
    row(&mut h, "homing version", &count(s, "homing_version"));
    row(&mut h, "final state", &count(s, "final_state"));
    if let Some(r) = str_of("stop_reason") {
        row(&mut h, "stop reason", &r);
    }
    if let Some(e) = str_of("error") {
        row(
            &mut h,
            "input error",
            &format!("<span class=\"note\">{e}</span>"),
        );
    }
    let frames = s.get("frames").and_then(|v| v.as_f64()).unwrap_or(0.0);
    let wall = s.get("wall_time_s").and_then(|v| v.as_f64());
    let data = s.get("data_duration_s").and_then(|v| v.as_f64());
    if let Some(w) = wall {
        row(
            &mut h,
            "wall time",
            &format!(
                "{w:.2} s ({:.1} frames/s){}",
                if w > 0.0 { frames / w } else { 0.0 },
                data.map_or(String::new(), |d| format!("; the data span {d:.2} s"))
            ),
        );
    }
    match &run.gt {
        Some((p, g)) => row(
            &mut h,
            "ground truth",
            &format!("{} ({} poses)", esc(&p.display().to_string()), g.len()),
        ),
        None => row(
            &mut h,
            "ground truth",
            "<span class=\"note\">none (no --gt, and the sequence's groundtruth.txt was not found)</span>",
        ),
    }
    let _ = writeln!(h, "</table>\n</section>");

    // Trajectory
    let _ = writeln!(
        h,
        "<section id=\"trajectory\">\n<h2>Trajectory (top view)</h2>"
    );
    let _ = writeln!(
        h,
        "<p>The plane of largest spread of the ground truth (its first two principal axes), equal \
         scale on both axes. The estimate is aligned as the evaluation aligns it{}.</p>",
        ev.map_or(String::new(), |e| format!(
            " ({:?}, {} associated poses{})",
            e.align,
            e.ate.pairs,
            if e.align == Alignment::Sim3 {
                format!(", scale {:.4}", e.ate.scale)
            } else {
                String::new()
            }
        ))
    );
    if let Some(n) = ev_note {
        let _ = writeln!(h, "<p class=\"note\">Not evaluated: {}</p>", esc(n));
    }
    let top = plot_top_view(run, ev)?;
    let _ = writeln!(h, "{}\n</section>", img(&top, "trajectory top view"));

    // Error over time and states
    let _ = writeln!(
        h,
        "<section id=\"error\">\n<h2>{}</h2>",
        if ev.is_some() {
            "Error over time and controller states"
        } else {
            "Controller states"
        }
    );
    let band = plot_error_and_states(run, ev)?;
    let _ = writeln!(
        h,
        "<p>The band under the plot is the state after each frame (states.csv), on the same time \
         axis; one-frame states are widened to be visible, and white is a stretch without \
         frames (dropped).</p>\n{}",
        img(&band, "translational error over time and state timeline")
    );
    let legend = state_legend(&run.states);
    let colors = state_colors(&legend);
    let _ = writeln!(
        h,
        "<table>\n<tr><th>state</th><th>frames</th><th>stretches</th></tr>"
    );
    for (state, frames) in &legend {
        let c = colors.get(state).copied().unwrap_or(BLACK);
        let entered = state_spans(&run.states)
            .iter()
            .filter(|x| x.state == *state)
            .count();
        let _ = writeln!(
            h,
            "<tr><td><span style=\"display:inline-block;width:1em;height:1em;vertical-align:middle;margin-right:.4em;background:#{:02x}{:02x}{:02x}\"></span>{}</td><td class=\"n\">{frames}</td><td class=\"n\">{entered}</td></tr>",
            c.0,
            c.1,
            c.2,
            esc(state)
        );
    }
    let _ = writeln!(h, "</table>\n</section>");

    // Timing
    let _ = writeln!(h, "<section id=\"timing\">\n<h2>Per-stage timing</h2>");
    if timing.is_empty() {
        let _ = writeln!(h, "<p class=\"note\">summary.json holds no timing.</p>");
    } else {
        let _ = writeln!(
            h,
            "<p>Milliseconds per call of each stage (<code>frame</code>: a whole frame; \
             <code>extract_track</code>: extraction + tracking, the front end's budget).</p>\n<table>\n<tr><th>stage</th><th>median ms</th><th>p90 ms</th><th>max ms</th><th>mean ms</th><th>calls</th></tr>"
        );
        for r in &timing {
            let _ = writeln!(
                h,
                "<tr><td>{}</td><td class=\"n\">{:.2}</td><td class=\"n\">{:.2}</td><td class=\"n\">{:.2}</td><td class=\"n\">{}</td><td class=\"n\">{}</td></tr>",
                esc(&r.stage),
                r.median,
                r.p90,
                r.max,
                r.mean.map_or("n/a".into(), |m| format!("{m:.2}")),
                r.count.map_or("n/a".into(), |c| c.to_string())
            );
        }
        let _ = writeln!(h, "</table>");
        let chart = plot_timing(&timing)?;
        let _ = writeln!(h, "{}", img(&chart, "per-stage timing"));
        match plot_timing_histograms(&run.timing_samples)? {
            Some(hist) => {
                let _ = writeln!(
                    h,
                    "<p>Histograms of the per-call times (timing.csv; 30 bins up to the 99th \
                     percentile, slower calls in the last bin; the line is the median).</p>\n{}",
                    img(&hist, "per-stage timing histograms")
                );
            }
            None => {
                let _ = writeln!(
                    h,
                    "<p class=\"note\">No timing.csv (a run older than it): no histograms.</p>"
                );
            }
        }
    }
    let _ = writeln!(h, "</section>");

    // Map statistics and accuracy
    let _ = writeln!(
        h,
        "<section id=\"map\">\n<h2>Map and accuracy</h2>\n<table>"
    );
    row(
        &mut h,
        "frames",
        &format!(
            "{} delivered of {} in the sequence; {} with a pose",
            count(s, "frames"),
            count(s, "sequence_frames"),
            count(s, "frames_with_pose")
        ),
    );
    row(&mut h, "keyframes", &count(s, "keyframes"));
    let mk = s
        .get("map_keyframes")
        .and_then(|v| v.as_object())
        .map(|o| {
            o.iter()
                .map(|(k, v)| format!("map {}: {v} keyframes", esc(k)))
                .collect::<Vec<_>>()
                .join(", ")
        })
        .filter(|t| !t.is_empty());
    row(
        &mut h,
        "maps",
        &format!(
            "{}{}",
            count(s, "maps"),
            mk.map_or(String::new(), |t| format!(" ({t})"))
        ),
    );
    row(
        &mut h,
        "closure candidates",
        &format!(
            "{}: {} accepted, {} rejected, {} rolled back",
            count(s, "closure_candidates"),
            count(s, "closures_accepted"),
            count(s, "closures_rejected"),
            count(s, "closures_rolled_back")
        ),
    );
    row(
        &mut h,
        "closure pools",
        &format!(
            "{} ({} rolled back)",
            count(s, "pools"),
            count(s, "pools_rolled_back")
        ),
    );
    row(
        &mut h,
        "poses discarded by roll-backs",
        &count(s, "poses_discarded"),
    );
    row(
        &mut h,
        "coverage",
        &coverage.map_or("n/a".into(), |c| format!("{:.2} %", 100.0 * c)),
    );
    if let Some(e) = ev {
        let st = &e.ate.stats;
        row(
            &mut h,
            &format!("ATE ({:?})", e.align),
            &format!(
                "RMSE <b>{:.4} m</b>, mean {:.4}, median {:.4}, std {:.4}, max {:.4} m ({} poses)",
                st.rmse, st.mean, st.median, st.std, st.max, e.ate.pairs
            ),
        );
        match &e.rpe {
            Ok(r) => row(
                &mut h,
                "RPE (1 s)",
                &format!(
                    "translation RMSE {:.4} m, rotation RMSE {:.3}° ({} pairs)",
                    r.trans.rmse, r.rot_deg.rmse, r.pairs
                ),
            ),
            Err(m) => row(&mut h, "RPE (1 s)", &format!("n/a: {}", esc(m))),
        }
        for m in &e.per_map {
            row(
                &mut h,
                &format!(
                    "ATE of map {}{}",
                    m.map,
                    if Some(m.map) == e.largest {
                        " (largest)"
                    } else {
                        ""
                    }
                ),
                &format!(
                    "{} poses, RMSE {}",
                    m.poses,
                    m.ate_rmse_m.map_or("n/a".into(), |r| format!("{r:.4} m"))
                ),
            );
        }
        let c = &e.closures;
        row(
            &mut h,
            "closures against ground truth",
            &format!(
                "{} candidates ({} wrong); accepted {} ({} wrong), rolled back {} ({} wrong), \
                 rejected {} ({} wrong), expired {} ({} wrong)",
                c.candidates,
                c.candidates_wrong,
                c.accepted,
                c.accepted_wrong,
                c.rolled_back,
                c.rolled_back_wrong,
                c.rejected,
                c.rejected_wrong,
                c.expired,
                c.expired_wrong
            ),
        );
    } else {
        row(
            &mut h,
            "ATE / RPE",
            &format!(
                "<span class=\"note\">n/a: {}</span>",
                esc(ev_note.map_or("no ground truth", |n| n.as_str()))
            ),
        );
    }
    let _ = writeln!(h, "</table>\n</section>");

    // Closure candidates
    let _ = writeln!(h, "<section id=\"closures\">\n<h2>Closure candidates</h2>");
    if run.closures.is_empty() {
        let _ = writeln!(h, "<p>None.</p>");
    } else {
        let _ = writeln!(
            h,
            "<table>\n<tr><th>frame</th><th>kind</th><th>maps (query → match)</th><th>keyframe</th><th>inliers</th><th>verdict</th><th>pool</th>{}</tr>",
            if ev.is_some() {
                "<th>wrong (ground truth)</th>"
            } else {
                ""
            }
        );
        let mono_scales = ev
            .filter(|e| e.align == Alignment::Sim3)
            .map(|e| eval::run::MonoScales::from_maps(&e.per_map, e.largest));
        for c in &run.closures {
            let wrong = match (&run.gt, ev) {
                (Some((_, gt)), Some(_)) => format!(
                    "<td>{}</td>",
                    match eval::run::closure_is_wrong(c, gt, MAX_DT, mono_scales.as_ref()) {
                        Some(true) => "<b>yes</b>",
                        Some(false) => "no",
                        None => "n/a",
                    }
                ),
                _ => String::new(),
            };
            let _ = writeln!(
                h,
                "<tr><td class=\"n\">{}</td><td>{}</td><td>{} → {}</td><td class=\"n\">{}</td><td class=\"n\">{}</td><td>{}</td><td>{}</td>{wrong}</tr>",
                c.frame,
                esc(&c.kind),
                c.map_query,
                c.map_match,
                c.matched_kf,
                c.inliers,
                esc(&c.verdict),
                c.pool.map_or(String::new(), |p| p.to_string())
            );
        }
        let _ = writeln!(h, "</table>");
    }
    let _ = writeln!(h, "</section>\n</body>\n</html>");
    Ok(h)
}

/// Writes the report of the run in `dir` to `out` (default `dir/report.html`), atomically;
/// returns where it went.
pub fn write_report(dir: &Path, gt: Option<&Path>, out: Option<&Path>) -> Result<PathBuf> {
    let run = load_run(dir, gt)?;
    let html = render_html(&run)?;
    let out = out.map_or_else(|| dir.join("report.html"), Path::to_path_buf);
    atomic_write(&out, html.as_bytes())?;
    Ok(out)
}

/// The compact results table `homing run --eval` prints at the end.
pub fn results_table(s: &Summary) -> String {
    let mut t = String::new();
    let ev = s.evaluation.as_ref();
    let get = |p: &str| ev.and_then(|e| e.pointer(p)).and_then(|v| v.as_f64());
    let mut line = |k: &str, v: String| {
        let _ = writeln!(t, "  {k:<18} {v}");
    };
    let align = ev
        .and_then(|e| e.pointer("/ate/alignment"))
        .and_then(|v| v.as_str())
        .unwrap_or("")
        .to_uppercase();
    // The largest map leads: several disconnected maps aligned as one give an ATE that
    // describes none of them (a mono run's 1 cm largest map read as 13.5 cm over all maps).
    let largest_ate = get("/largest_map/ate_rmse_m");
    if let Some(r) = largest_ate {
        line(
            "largest map",
            format!(
                "ATE RMSE {} {:.4} m, {:.2} % of the frames, {:.2} % of the delivered \
                 ones within {:.0} cm ({} maps in all)",
                if align.is_empty() { "" } else { &align },
                r,
                100.0 * get("/largest_map_coverage").unwrap_or(0.0),
                100.0 * get("/largest_map_accurate_coverage").unwrap_or(0.0),
                100.0 * crate::eval::run::ACCURATE_M,
                s.maps
            ),
        );
    }
    line(
        format!(
            "ATE RMSE {}{}",
            if align.is_empty() { "" } else { &align },
            if largest_ate.is_some() && s.maps > 1 {
                " all maps"
            } else {
                ""
            }
        )
        .trim_end(),
        match get("/ate/stats/rmse") {
            Some(r) => format!(
                "{:.4} m ({} poses)",
                r,
                get("/ate/pairs").map_or("?".into(), |p| format!("{p:.0}"))
            ),
            None => "n/a".into(),
        },
    );
    line(
        "RPE 1 s trans/rot",
        match (get("/rpe/trans/rmse"), get("/rpe/rot_deg/rmse")) {
            (Some(tr), Some(rot)) => format!("{tr:.4} m / {rot:.3} deg"),
            _ => "n/a".into(),
        },
    );
    line(
        "coverage",
        get("/coverage").map_or("n/a".into(), |c| format!("{:.2} %", 100.0 * c)),
    );
    line("maps", s.maps.to_string());
    line("keyframes", s.keyframes.to_string());
    line(
        "closures",
        format!(
            "{} accepted, {} rejected, {} rolled back (of {} candidates)",
            s.closures_accepted, s.closures_rejected, s.closures_rolled_back, s.closure_candidates
        ),
    );
    line("final state", s.final_state.clone());
    line(
        "fps",
        if s.wall_time_s > 0.0 {
            format!(
                "{:.1} ({} frames in {:.2} s; the data span {:.2} s)",
                s.frames as f64 / s.wall_time_s,
                s.frames,
                s.wall_time_s,
                s.data_duration_s
            )
        } else {
            "n/a".into()
        },
    );
    if let Some(n) = ev.and_then(|e| e.get("note")).and_then(|v| v.as_str()) {
        line("note", n.to_string());
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(frame: usize, t: f64, state: &str) -> StateCsvRow {
        StateCsvRow {
            frame,
            t,
            state: state.into(),
            from: None,
            map: None,
        }
    }

    #[test]
    fn spans_follow_states_and_leave_holes_for_dropped_frames() {
        let mut rows: Vec<StateCsvRow> = (0..10).map(|f| row(f, f as f64, "Mapping")).collect();
        // Frame 10 passes through Localized and CorruptedMap and ends in Idle.
        rows.push(row(10, 10.0, "Localized"));
        rows.push(row(10, 10.0, "CorruptedMap"));
        rows.push(row(10, 10.0, "Idle"));
        // Frames 11..19 dropped.
        rows.extend((20..23).map(|f| row(f, f as f64, "Idle")));
        let s = state_spans(&rows);
        let got: Vec<(&str, f64, f64)> = s.iter().map(|x| (x.state.as_str(), x.t0, x.t1)).collect();
        assert_eq!(
            got,
            [
                ("Mapping", 0.0, 10.0),
                ("Localized", 10.0, 10.0),
                ("CorruptedMap", 10.0, 10.0),
                ("Idle", 10.0, 11.0),
                ("Idle", 20.0, 23.0),
            ]
        );
        let legend = state_legend(&rows);
        assert_eq!(legend[0], ("Mapping".to_string(), 10));
        assert_eq!(legend[3], ("Idle".to_string(), 4));
    }

    #[test]
    fn tick_labels_have_no_negative_zero() {
        let f = tick_format(&(-0.3..0.3));
        assert_eq!(f(&-0.0), "0.00");
        assert_eq!(f(&-0.05), "-0.05");
        assert_eq!(tick_format(&(0.0..40.0))(&5.0), "5");
    }
}
