//! The run-output contract: what `homing run --out OUTDIR` writes. Every later component fills
//! parts of it; its shape is fixed here so that evaluation and benchmarks can rely on it.
//!
//! | file | content |
//! |---|---|
//! | `trajectory.txt` | TUM: every frame that has a pose (camera-to-world) |
//! | `keyframes.txt` | TUM + map id: `timestamp tx ty tz qx qy qz qw map_id` |
//! | `states.csv` | one row per delivered frame: active state, transition (from, trigger) and the flags |
//! | `closures.csv` | every closure / relocalization candidate with its verdict |
//! | `summary.json` | counts, final state, perturbations, config, per-stage timing, wall time |
//!
//! All files are written atomically, so an interrupted run never leaves a half-written result.

pub mod mcap_log;
pub mod report;
pub mod viz;

use crate::config::{CameraConfig, CameraSource, Config};
use crate::error::{Error, Result};
use crate::io::atomic_write;
use crate::io::perturb::PerturbationPlan;
use crate::io::tum::{StampedPose, format_pose, write_trajectory};
use nalgebra::Isometry3;
use serde::Serialize;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The component status flags the state machine's guards read (paper Table I).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct Flags {
    pub initialized: bool,
    pub able_to_track: bool,
    pub able_to_localize: bool,
    pub consistent_map: bool,
}

/// One row of `states.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct StateRow {
    pub frame: usize,
    pub t: f64,
    /// Active state(s) after this frame, e.g. `Mapping` or `Core(M&R)`.
    pub state: String,
    /// Set on the frame where a transition happened (a frame that crosses several states has
    /// one row per transition).
    pub transition: Option<Transition>,
    pub flags: Flags,
    /// Map of the frame's pose (in the final atlas), if it has one.
    pub map: Option<u32>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Transition {
    pub from: String,
    pub trigger: String,
}

/// One row of `closures.csv`: a closure (loop, in Mapping) or relocalization (Relocalize
/// region) candidate and what became of it.
#[derive(Debug, Clone, PartialEq)]
pub struct ClosureRow {
    pub frame: usize,
    /// `loop`, `relocalization`, or `lost-place` (a relocalization candidate among the lost
    /// map's keyframes at the place tracking was lost, not the loop detector's; it joins the
    /// same pool).
    pub kind: String,
    pub t_query: f64,
    pub t_match: f64,
    pub map_query: u32,
    pub map_match: u32,
    pub matched_kf: u32,
    /// Pose of the query camera in the matched keyframe's camera frame (`T_match · T_query⁻¹`,
    /// world-to-camera poses), when the validator got as far as a pose.
    pub relative: Option<Isometry3<f64>>,
    pub inliers: u32,
    /// `accepted`, `accepted:provisional` (a merge no later frame confirmed:
    /// [`crate::atlas::MergeEvidence`]), `rolled-back`, `expired` (valid, but no pool formed),
    /// or `rejected:<reason>`.
    pub verdict: String,
    /// The pool that accepted it.
    pub pool: Option<u32>,
}

/// Per-stage timing, in milliseconds per frame.
#[derive(Debug, Clone, Default)]
pub struct Timing {
    samples: BTreeMap<String, Vec<f64>>,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TimingStats {
    pub median_ms: f64,
    pub p90_ms: f64,
    pub max_ms: f64,
    pub mean_ms: f64,
    pub count: usize,
}

impl Timing {
    pub fn record(&mut self, stage: &str, ms: f64) {
        self.samples.entry(stage.to_string()).or_default().push(ms);
    }

    /// Runs `f`, recording its duration under `stage`.
    pub fn time<T>(&mut self, stage: &str, f: impl FnOnce() -> T) -> T {
        let start = std::time::Instant::now();
        let out = f();
        self.record(stage, start.elapsed().as_secs_f64() * 1e3);
        out
    }

    /// Samples recorded so far under `stage`.
    pub fn count(&self, stage: &str) -> usize {
        self.samples.get(stage).map_or(0, Vec::len)
    }

    /// Samples recorded so far, per stage (see [`Self::since`]).
    pub fn counts(&self) -> BTreeMap<String, usize> {
        self.samples
            .iter()
            .map(|(k, v)| (k.clone(), v.len()))
            .collect()
    }

    /// Milliseconds per stage recorded after `counts` was taken (summed per stage).
    pub fn since(&self, counts: &BTreeMap<String, usize>) -> BTreeMap<String, f64> {
        self.samples
            .iter()
            .filter_map(|(k, v)| {
                let from = counts.get(k).copied().unwrap_or(0);
                (v.len() > from).then(|| (k.clone(), v[from..].iter().sum()))
            })
            .collect()
    }

    /// Every sample as CSV (`stage,ms`, one row per call in the order recorded), for the
    /// report's histograms: summary.json keeps only the statistics.
    pub fn samples_csv(&self) -> String {
        let mut out = String::from("stage,ms\n");
        for (stage, v) in &self.samples {
            for ms in v {
                out.push_str(&format!("{stage},{ms:.4}\n"));
            }
        }
        out
    }

    /// The latest sample of `stage`.
    pub fn last(&self, stage: &str) -> Option<f64> {
        self.samples.get(stage).and_then(|v| v.last().copied())
    }

    pub fn summary(&self) -> BTreeMap<String, TimingStats> {
        self.samples
            .iter()
            .filter(|(_, v)| !v.is_empty())
            .map(|(k, v)| {
                let mut s = v.clone();
                s.sort_by(|a, b| a.total_cmp(b));
                let pick = |q: f64| s[((s.len() - 1) as f64 * q).round() as usize];
                let stats = TimingStats {
                    median_ms: pick(0.5),
                    p90_ms: pick(0.9),
                    max_ms: s[s.len() - 1],
                    mean_ms: s.iter().sum::<f64>() / s.len() as f64,
                    count: s.len(),
                };
                (k.clone(), stats)
            })
            .collect()
    }
}

/// A frame that could not be read (missing, truncated or corrupt file, wrong size or depth
/// format), taken as a failed measurement.
#[derive(Debug, Clone, Serialize)]
pub struct UnreadableFrame {
    pub frame: usize,
    pub t: f64,
    /// The error, naming the file.
    pub error: String,
}

/// summary.json's account of a user stop.
#[derive(Debug, Clone, Serialize)]
pub struct UserStop {
    /// The last frame processed (sequence index) and its stamp.
    pub frame: usize,
    pub t: f64,
    /// Frames of the sequence (after the perturbation plan) left unread.
    pub frames_not_processed: usize,
    /// Final's refinement: "complete", or how it was cut short.
    pub refinement: String,
}

/// A tracked frame whose pose did not stand, and why (summary.json's `discarded_poses`).
#[derive(Debug, Clone, Serialize)]
pub struct DiscardedPose {
    pub frame: usize,
    pub t: f64,
    pub reason: String,
}

/// closures.csv's verdict of a merge's rows that no later frame confirmed.
pub const ACCEPTED_PROVISIONAL: &str = "accepted:provisional";

/// Whether a closures.csv verdict counts as accepted: confirmed, or a merge still provisional
/// (decision 0023).
pub fn is_accepted(verdict: &str) -> bool {
    verdict == "accepted" || verdict == ACCEPTED_PROVISIONAL
}

/// A merge of two maps in `summary.json`.
#[derive(Debug, Clone, Serialize)]
pub struct MergeRow {
    pub pool: u32,
    pub frame: usize,
    pub into: u32,
    pub from: u32,
    /// The frame that confirmed it; `None`: unconfirmed (provisional) at the end.
    pub confirmed_frame: Option<usize>,
    pub rolled_back: bool,
}

/// Monocular: the end of a rotation-only stretch, where the camera sets off again
/// (`summary.json`'s `lift_offs`, decision 0030).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LiftOff {
    /// The first frame not posed by its rotation alone.
    pub frame: usize,
    /// The stretch's first rotation-only frame and how many it had.
    pub turn_first_frame: usize,
    pub turn_frames: usize,
    /// Panoramic keyframes the stretch left in the map.
    pub panoramic_keyframes: usize,
    /// Key points of the lift-off frame matched (by descriptor) to a key point of those
    /// panoramic keyframes that look its way: the stored bearings it sees again.
    pub bearings_matched: usize,
    /// Key points of those panoramic keyframes that have a map point by now: the bearings
    /// triangulated, against another turn's view or the walk's.
    pub bearings_triangulated: usize,
    /// The frame was tracked in the map (`false`: lost there).
    pub continued: bool,
}

/// `summary.json`.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub homing_version: &'static str,
    pub sequence: PathBuf,
    /// The command line that produced the run.
    pub command: Vec<String>,
    /// Frames in the unperturbed sequence.
    pub sequence_frames: usize,
    /// Frames delivered to the system (after drops).
    pub frames: usize,
    pub frames_with_pose: usize,
    pub keyframes: usize,
    pub maps: usize,
    /// Closure and relocalization candidates the validator saw, and what became of them.
    pub closure_candidates: usize,
    pub closures_accepted: usize,
    pub closures_rejected: usize,
    pub closures_rolled_back: usize,
    /// Pools (atlas transactions) accepted, and how many were rolled back.
    pub pools: usize,
    pub pools_rolled_back: usize,
    /// Every merge of two maps, and whether later frames confirmed it (re-observed what only
    /// the map merged into had seen).
    pub merges: Vec<MergeRow>,
    /// Monocular: every end of a rotation-only stretch, and what the turn's stored bearings
    /// did for it (decision 0030).
    pub lift_offs: Vec<LiftOff>,
    /// The modal controller that ran (`ours`, `orbslam2`, `proslam`, `ldso`).
    pub controller: String,
    /// Frames whose pose was discarded because it was tracked on a map a rollback undid.
    pub poses_discarded: usize,
    /// Every pose discarded, and why.
    pub discarded_poses: Vec<DiscardedPose>,
    /// Keyframes that left the atlas during the run (only a map of one unconfirmed view is
    /// ever discarded; a revoked pool keeps every keyframe).
    pub keyframes_discarded: usize,
    /// Keyframes per map at the end.
    pub map_keyframes: BTreeMap<u32, usize>,
    /// Why the machine stopped early (corrupted map that no pool explains), if it did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub stop_reason: Option<String>,
    /// Where a user stop (SIGINT/SIGTERM) ended the run, if one did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub user_stop: Option<UserStop>,
    pub final_state: String,
    pub perturbations: PerturbationPlan,
    pub camera: CameraConfig,
    pub camera_source: String,
    pub config: Config,
    /// "deterministic" (mapping finishes before the next frame) or "threaded".
    pub mode: &'static str,
    pub timing: BTreeMap<String, TimingStats>,
    /// Wall-clock time of the run; with `--features`, plus the extraction time recorded for
    /// the frames taken from the file (what extracting them here took), so that fps still
    /// includes extraction.
    pub wall_time_s: f64,
    /// The process's peak resident memory (MB, Linux `VmHWM`) when the outputs were written;
    /// absent where the system does not report it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub peak_rss_mb: Option<f64>,
    /// Of `wall_time_s`: the recorded extraction time of frames taken from `--features`.
    pub extraction_reused_s: f64,
    /// Time span of the delivered frames' stamps: what "real time" means for this run.
    pub data_duration_s: f64,
    /// Evaluation against the sequence's ground truth, when asked for (`--eval`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub evaluation: Option<serde_json::Value>,
    /// The input error that ended the run early, if any (outputs up to it are still written).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Frames that could not be read and were taken as failed measurements (without
    /// `--strict-input`), and which.
    pub frames_unreadable: usize,
    pub unreadable_frames: Vec<UnreadableFrame>,
}

/// Writer for one run's output folder.
pub struct RunOutputs {
    pub dir: PathBuf,
}

impl RunOutputs {
    pub fn create(dir: &Path) -> Result<Self> {
        std::fs::create_dir_all(dir)
            .map_err(|e| Error::file(dir, format!("cannot create output folder: {e}")))?;
        Ok(Self {
            dir: dir.to_path_buf(),
        })
    }

    pub fn path(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }

    pub fn write_trajectory(&self, poses: &[StampedPose]) -> Result<()> {
        write_trajectory(
            &self.path("trajectory.txt"),
            poses,
            "homing trajectory (camera-to-world, TUM format)",
        )
    }

    pub fn write_keyframes(&self, keyframes: &[(StampedPose, u32)]) -> Result<()> {
        let mut s = String::from(
            "# homing keyframes (camera-to-world)\n# timestamp tx ty tz qx qy qz qw map_id\n",
        );
        for (p, map) in keyframes {
            s.push_str(&format_pose(p, Some(&map.to_string())));
            s.push('\n');
        }
        atomic_write(&self.path("keyframes.txt"), s.as_bytes())
    }

    pub fn write_states(&self, rows: &[StateRow]) -> Result<()> {
        let mut s = String::from(
            "frame,timestamp,state,from,trigger,initialized,able_to_track,able_to_localize,consistent_map,map\n",
        );
        for r in rows {
            let (from, trig) = r
                .transition
                .as_ref()
                .map_or(("", ""), |t| (t.from.as_str(), t.trigger.as_str()));
            let b = |v: bool| u8::from(v);
            let _ = writeln!(
                s,
                "{},{:.6},{},{},{},{},{},{},{},{}",
                r.frame,
                r.t,
                r.state,
                from,
                trig,
                b(r.flags.initialized),
                b(r.flags.able_to_track),
                b(r.flags.able_to_localize),
                b(r.flags.consistent_map),
                r.map.map_or(String::new(), |m| m.to_string())
            );
        }
        atomic_write(&self.path("states.csv"), s.as_bytes())
    }

    pub fn write_closures(&self, rows: &[ClosureRow]) -> Result<()> {
        let mut s = String::from(CLOSURES_HEADER);
        s.push('\n');
        for r in rows {
            let pose = match &r.relative {
                Some(rel) => {
                    let t = rel.translation.vector;
                    let q = rel.rotation.quaternion().coords;
                    format!(
                        "{:.6},{:.6},{:.6},{:.9},{:.9},{:.9},{:.9}",
                        t.x, t.y, t.z, q.x, q.y, q.z, q.w
                    )
                }
                None => ",,,,,,".into(),
            };
            let _ = writeln!(
                s,
                "{},{},{:.6},{:.6},{},{},{},{},{},{},{}",
                r.frame,
                r.kind,
                r.t_query,
                r.t_match,
                r.map_query,
                r.map_match,
                r.matched_kf,
                pose,
                r.inliers,
                r.verdict,
                r.pool.map_or(String::new(), |p| p.to_string())
            );
        }
        atomic_write(&self.path("closures.csv"), s.as_bytes())
    }

    /// `timing.csv`: every per-stage sample (measured, so it differs run to run, like the
    /// timing in summary.json).
    pub fn write_timing(&self, timing: &Timing) -> Result<()> {
        atomic_write(&self.path("timing.csv"), timing.samples_csv().as_bytes())
    }

    pub fn write_summary(&self, summary: &Summary) -> Result<()> {
        let mut json = serde_json::to_vec_pretty(summary)
            .map_err(|e| Error::invalid(format!("cannot serialise summary: {e}")))?;
        json.push(b'\n');
        atomic_write(&self.path("summary.json"), &json)
    }
}

/// Prints where the camera came from (the issue asks for the choice to be visible).
pub fn describe_camera(cam: &CameraConfig, src: &CameraSource) -> String {
    format!(
        "camera: {} {}x{} fx={} fy={} cx={} cy={} depth_scale={} — {src}",
        if cam.name.is_empty() {
            "(unnamed)"
        } else {
            &cam.name
        },
        cam.width,
        cam.height,
        cam.fx,
        cam.fy,
        cam.cx,
        cam.cy,
        cam.depth_scale
    )
}

const CLOSURES_HEADER: &str = "frame,kind,t_query,t_match,map_query,map_match,matched_kf,tx,ty,tz,qx,qy,qz,qw,inliers,verdict,pool";

/// Reads a run's `closures.csv` back (for `homing eval --run`).
pub fn read_closures(path: &Path) -> Result<Vec<ClosureRow>> {
    let text = crate::error::read_text(path)?;
    let mut rows = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let n = i + 1;
        if i == 0 {
            if line.trim() != CLOSURES_HEADER {
                return Err(Error::parse(
                    path,
                    n,
                    "not a homing closures.csv (unexpected header)",
                ));
            }
            continue;
        }
        if line.trim().is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != 17 {
            return Err(Error::parse(
                path,
                n,
                format!("expected 17 comma-separated fields, found {}", f.len()),
            ));
        }
        let num = |k: usize, what: &str| -> Result<f64> {
            f[k].trim()
                .parse::<f64>()
                .map_err(|_| Error::parse(path, n, format!("{what}: not a number: {:?}", f[k])))
        };
        let int = |k: usize, what: &str| -> Result<u64> {
            f[k].trim()
                .parse::<u64>()
                .map_err(|_| Error::parse(path, n, format!("{what}: not an integer: {:?}", f[k])))
        };
        let relative = if f[7..14].iter().all(|x| x.trim().is_empty()) {
            None
        } else {
            let v: Vec<f64> = (7..14)
                .map(|k| num(k, "pose"))
                .collect::<Result<Vec<f64>>>()?;
            let q = nalgebra::Quaternion::new(v[6], v[3], v[4], v[5]);
            if (q.norm() - 1.0).abs() > 1e-3 {
                return Err(Error::parse(path, n, "quaternion is not unit length"));
            }
            Some(Isometry3::from_parts(
                nalgebra::Translation3::new(v[0], v[1], v[2]),
                nalgebra::UnitQuaternion::from_quaternion(q),
            ))
        };
        rows.push(ClosureRow {
            frame: int(0, "frame")? as usize,
            kind: f[1].trim().to_string(),
            t_query: num(2, "t_query")?,
            t_match: num(3, "t_match")?,
            map_query: int(4, "map_query")? as u32,
            map_match: int(5, "map_match")? as u32,
            matched_kf: int(6, "matched_kf")? as u32,
            relative,
            inliers: int(14, "inliers")? as u32,
            verdict: f[15].trim().to_string(),
            pool: if f[16].trim().is_empty() {
                None
            } else {
                Some(int(16, "pool")? as u32)
            },
        });
    }
    Ok(rows)
}

/// One row of a run's `states.csv`, read back.
#[derive(Debug, Clone, PartialEq)]
pub struct StateCsvRow {
    pub frame: usize,
    pub t: f64,
    pub state: String,
    /// The state left, on a transition row.
    pub from: Option<String>,
    pub map: Option<u32>,
}

/// Reads a run's `states.csv` back.
pub fn read_states(path: &Path) -> Result<Vec<StateCsvRow>> {
    let text = crate::error::read_text(path)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let n = i + 1;
        if i == 0 {
            if !line.starts_with("frame,timestamp,state,from,trigger") {
                return Err(Error::parse(
                    path,
                    n,
                    "not a homing states.csv (unexpected header)",
                ));
            }
            continue;
        }
        if line.trim().is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != 10 {
            return Err(Error::parse(
                path,
                n,
                format!("expected 10 comma-separated fields, found {}", f.len()),
            ));
        }
        let frame = f[0]
            .parse::<usize>()
            .map_err(|_| Error::parse(path, n, "frame: not an integer"))?;
        let t = f[1]
            .parse::<f64>()
            .map_err(|_| Error::parse(path, n, "timestamp: not a number"))?;
        let map = if f[9].trim().is_empty() {
            None
        } else {
            Some(
                f[9].trim()
                    .parse::<u32>()
                    .map_err(|_| Error::parse(path, n, "map: not an integer"))?,
            )
        };
        out.push(StateCsvRow {
            frame,
            t,
            state: f[2].to_string(),
            from: (!f[3].is_empty()).then(|| f[3].to_string()),
            map,
        });
    }
    Ok(out)
}

/// The map of each frame with a pose, from a run's `states.csv`: `(timestamp, map)`.
pub fn read_state_maps(path: &Path) -> Result<Vec<(f64, u32)>> {
    let mut out: Vec<(f64, u32)> = Vec::new();
    for r in read_states(path)? {
        if let Some(m) = r.map
            && out.last().is_none_or(|&(t, _)| t != r.t)
        {
            out.push((r.t, m));
        }
    }
    Ok(out)
}
