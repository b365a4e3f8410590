//! The run driver: sequence in, perturbations applied, one `step` per delivered frame, run
//! outputs written. What runs inside a step is decided by the controller; the components
//! (initializer, tracker, map merger, loop closing) are wired in by their own modules.
//!

use crate::atlas::{Atlas, AtlasCamera};
use crate::config::{CameraSource, Config, ControllerKind, resolve_camera};
use crate::control::StateMachine;
use crate::error::{Error, Result};
use crate::eval::{self, Alignment, RpeUnit};
use crate::io::Sequence;
use crate::io::mcap::{McapSequence, McapTopics};
use crate::io::perturb::{PerturbationPlan, PerturbationSpec, PerturbedSequence};
use crate::io::tum::{FrameSource, StampedPose, TumSequence};
use crate::outputs::{ClosureRow, RunOutputs, Summary, Timing, describe_camera};
use crate::slam::{Recorded, Slam};
use std::path::PathBuf;
use std::time::Instant;

/// What `homing run` is asked to do.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    pub sequence: PathBuf,
    pub out: PathBuf,
    pub config: Option<PathBuf>,
    pub perturb: PerturbationSpec,
    /// Evaluate against the sequence's ground truth at the end (into summary.json).
    pub eval: bool,
    /// The command line, recorded in summary.json.
    pub command: Vec<String>,
    /// Threaded mode: local BA on its own thread while tracking goes on (faster, not
    /// bit-reproducible). Default: deterministic, mapping finishes before the next frame.
    pub threaded: bool,
    /// Override the config's modal controller.
    pub controller: Option<ControllerKind>,
    /// Override the config: no loop closing.
    pub no_loop_closing: bool,
    /// Init loads this saved atlas (a previous session) before the first frame.
    pub load_map: Option<PathBuf>,
    /// Final saves the atlas here.
    pub save_map: Option<PathBuf>,
    /// Read this ROS 2 bag (MCAP) instead of the TUM folder `sequence`, with these topics.
    pub mcap: Option<(PathBuf, McapTopics)>,
    /// Also write OUTDIR/run.mcap (poses, states, statistics, transitions).
    pub mcap_log: bool,
    /// Put per-stage milliseconds into run.mcap (measured: the file then differs run to run).
    pub mcap_timing: bool,
    /// Also log the run to rerun (a file or a live viewer); needs the `rerun` feature.
    pub rerun: Option<crate::outputs::viz::RerunTarget>,
    /// Read the frames from this file of decoded frames (`io::decoded`, written by
    /// `homing bench robustness` once per sequence) instead of decoding the sequence's images.
    /// The sequence still gives the frame list, the camera and the ground truth.
    pub decoded_frames: Option<PathBuf>,
    /// Take the measurements of unperturbed frames from this file of extracted features
    /// (`io::features`, written by `homing bench robustness` once per sequence) instead of
    /// extracting them again. The outputs are the same; the extraction time recorded in the
    /// file is counted as the run's.
    pub features: Option<PathBuf>,
    /// Called after every processed frame (a progress bar). It only looks: the run's outputs
    /// are the same with or without it.
    pub progress: Option<ProgressHook>,
    /// `--strict-input`: a frame that cannot be read ends the run (the outputs so far are
    /// written) instead of becoming a failed measurement.
    pub strict_input: bool,
}

/// Where a run stands after a frame, for a progress display.
#[derive(Debug, Clone, Copy)]
pub struct Progress<'a> {
    /// Frames processed so far.
    pub delivered: usize,
    /// Frames the (perturbed) sequence delivers in all.
    pub total: usize,
    /// The controller's state after the frame, as states.csv names it.
    pub state: &'a str,
    pub maps: usize,
    pub keyframes: usize,
}

/// A progress callback (see [`RunOptions::progress`]).
#[derive(Clone)]
pub struct ProgressHook(pub std::sync::Arc<dyn Fn(&Progress<'_>) + Send + Sync>);

impl std::fmt::Debug for ProgressHook {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ProgressHook")
    }
}

/// Runs a whole sequence and writes the run outputs. On a bad frame the outputs gathered so far
/// are still written (with the error recorded) before the error is returned.
///
/// The steps: the config, the input (sequence, prepared frames and features, perturbations),
/// Init (the controller, with a saved atlas), the frame loop, Final, the frames' poses
/// resolved through the final keyframes, the saved atlas, evaluation, the output files.
pub fn run(opts: &RunOptions) -> Result<Summary> {
    let wall = Instant::now();
    let (config, spec) = run_config(opts)?;
    let (seq, camera, source) = open_sequence(opts, &config, spec.mono)?;
    if seq.unassociated() > 0 {
        tracing::warn!(
            "{} colour frames have no depth frame within {} s and are skipped",
            seq.unassociated(),
            config.sequence.max_association_dt
        );
    }
    let decoded = match &opts.decoded_frames {
        Some(p) => Some(crate::io::decoded::DecodedFrames::open(
            p,
            &seq,
            camera.width,
            camera.height,
            !spec.mono,
        )?),
        None => None,
    };
    let frames: &(dyn FrameSource + Sync) = match &decoded {
        Some(d) => d,
        None => &seq,
    };
    let perturbed = PerturbedSequence::new(frames, &spec)?;
    let mut features = match &opts.features {
        Some(p) => Some(crate::io::features::Features::open(
            p,
            &seq,
            &camera,
            &config.orb,
        )?),
        None => None,
    };
    let out = RunOutputs::create(&opts.out)?;
    let intr = camera.intrinsics();
    let mut viz = match &opts.rerun {
        Some(target) => Some(crate::outputs::viz::Visualizer::open(
            target,
            &intr,
            (camera.width, camera.height),
        )?),
        None => None,
    };
    let mut slam = init(opts, &config, &camera, spec.mono)?;
    let input = Input {
        opts,
        frames,
        perturbed: &perturbed,
        camera: &camera,
        mono: spec.mono,
    };
    let mut extra = frame_loop(&input, features.as_mut(), viz.as_mut(), &mut slam);
    tracing::info!(
        "low-threshold FAST found key points on {} of {} frames",
        slam.preprocessor().weak_passes,
        slam.delivered()
    );
    let result = slam.finish()?;
    let posed = Posed {
        pose_maps: result
            .trajectory
            .iter()
            .zip(&result.trajectory_maps)
            .map(|(p, m)| (p.t, *m))
            .collect(),
        posed: if opts.mcap_log {
            result
                .trajectory
                .iter()
                .zip(&result.trajectory_frames)
                .zip(&result.trajectory_maps)
                .map(|((p, f), m)| crate::outputs::mcap_log::PosedFrame {
                    frame: *f,
                    t: p.t,
                    map: *m,
                    pose: p.pose,
                })
                .collect()
        } else {
            Vec::new()
        },
        trajectory: result.trajectory,
    };
    if let Some(path) = &opts.save_map {
        // Final: the atlas is stored for a later session.
        slam.save_atlas(path)?;
        tracing::info!("atlas saved to {}", path.display());
    }
    let closures = result.closures;
    let keyframes = result.keyframes;
    let evaluation = if opts.eval {
        evaluate(
            &seq,
            &posed.trajectory,
            &spec,
            &perturbed.plan,
            &closures,
            &posed.pose_maps,
            &extra.unreadable.iter().map(|u| u.frame).collect(),
        )?
    } else {
        None
    };
    let n = perturbed.len();
    extra.rec = std::mem::take(slam.recorded_mut());
    let mut fin = Finished {
        rec: extra,
        state: result.final_state,
        posed,
        closures,
        keyframes,
        evaluation,
        timing: std::mem::take(slam.timing_mut()),
    };
    let setup = Setup {
        config,
        camera,
        source,
    };
    let summary = summarize(
        opts,
        (&seq, n),
        setup,
        &perturbed.plan,
        slam.machine(),
        &mut fin,
        wall,
    );
    write_outputs(&out, opts, &fin, &summary, viz)?;
    match fin.rec.rec.failure {
        Some(e) => Err(e),
        None => Ok(summary),
    }
}

/// The config a run uses: the file (or the defaults) with the command line's overrides.
fn run_config(opts: &RunOptions) -> Result<(Config, PerturbationSpec)> {
    let mut config = match &opts.config {
        Some(p) => Config::load(p)?,
        None => Config::default(),
    };
    let mut spec = opts.perturb.clone();
    spec.mono |= config.sequence.mono;
    config.sequence.mono = spec.mono;
    if let Some(k) = opts.controller {
        config.controller.kind = k;
    }
    if opts.no_loop_closing {
        config.loop_closing.enabled = false;
    }
    Ok((config, spec))
}

/// Init: the controller, and (its entry) a saved atlas from an earlier session.
fn init(
    opts: &RunOptions,
    config: &Config,
    camera: &crate::config::CameraConfig,
    mono: bool,
) -> Result<Slam> {
    let mut slam = Slam::new(config, camera)?;
    if opts.threaded {
        slam.set_threaded();
    }
    if let Some(path) = &opts.load_map {
        let atlas = Atlas::load(path, &AtlasCamera::from(camera), mono)?;
        tracing::info!(
            "loaded atlas {}: {} maps, {} keyframes",
            path.display(),
            atlas.maps.len(),
            atlas.n_keyframes()
        );
        slam = slam.with_atlas(atlas);
    }
    Ok(slam)
}

/// What the frame loop reads.
struct Input<'a> {
    opts: &'a RunOptions,
    frames: &'a (dyn FrameSource + Sync),
    perturbed: &'a PerturbedSequence<'a>,
    camera: &'a crate::config::CameraConfig,
    mono: bool,
}

/// What the run driver records beside the session: for summary.json and run.mcap.
#[derive(Default)]
struct RunRecord {
    rec: Recorded,
    frame_stats: Vec<crate::outputs::mcap_log::FrameStats>,
    unreadable: Vec<crate::outputs::UnreadableFrame>,
}

/// The frames' poses for the outputs and the evaluation.
struct Posed {
    trajectory: Vec<StampedPose>,
    /// Each posed frame's stamp and map.
    pose_maps: Vec<(f64, u32)>,
    /// For run.mcap (`--mcap-log`).
    posed: Vec<crate::outputs::mcap_log::PosedFrame>,
}

/// The frame loop: one [`Slam`] frame per delivered frame, until the data ends, the
/// controller stops, an input error ends the run or the user stops it.
fn frame_loop(
    input: &Input<'_>,
    mut features: Option<&mut crate::io::features::Features>,
    mut viz: Option<&mut crate::outputs::viz::Visualizer>,
    slam: &mut Slam,
) -> RunRecord {
    let mut extra = RunRecord::default();
    let n = input.perturbed.len();
    // Images are decoded on a loader thread a few frames ahead (in both modes: it changes
    // when a frame is read, never what is computed from it).
    std::thread::scope(|scope| {
        let (tx, rx) = std::sync::mpsc::sync_channel(4);
        let perturbed = input.perturbed;
        let strict = input.opts.strict_input;
        scope.spawn(move || {
            let mut frames = perturbed.frames();
            loop {
                let t0 = Instant::now();
                let Some(frame) = frames.next() else { break };
                let ms = t0.elapsed().as_secs_f64() * 1e3;
                let stop = frame.is_err() && strict;
                if tx.send((frame, ms)).is_err() || stop {
                    break;
                }
            }
        });
        for (frame, load_ms) in rx {
            slam.timing_mut().record("load", load_ms);
            let frame = match frame {
                Ok(f) => f,
                // A frame on disk that cannot be read is a failed measurement, which the state
                // machine meets like a black frame: the run goes on.
                Err(e) if !input.opts.strict_input => {
                    let index = perturbed.plan.delivered[slam.delivered()];
                    let t = input.frames.timestamp(index);
                    tracing::warn!(
                        "frame {index}: {e}: taken as a failed measurement (--strict-input stops instead)"
                    );
                    extra.unreadable.push(crate::outputs::UnreadableFrame {
                        frame: index,
                        t,
                        error: e.to_string(),
                    });
                    failed_measurement(index, t, input.camera, input.mono)
                }
                Err(e) => {
                    slam.recorded_mut().failure = Some(e);
                    break;
                }
            };
            // An unperturbed frame's features from the file: the same measurement, and the
            // extraction time it took when the file was written.
            let reused = features
                .as_deref_mut()
                .filter(|_| {
                    perturbed.plan.fault(frame.index).is_none()
                        && perturbed.plan.depth_shift_px.is_none()
                })
                .and_then(|f| f.take(frame.index))
                .map(|e| (e.m, e.ms, e.weak));
            let counts = input.opts.mcap_timing.then(|| slam.timing().counts());
            let (result, m, out) = match slam.process_frame(&frame, reused) {
                Ok(r) => r,
                Err(e) => {
                    slam.recorded_mut().failure = Some(e);
                    break;
                }
            };
            let machine = slam.machine();
            if input.opts.mcap_log {
                extra
                    .frame_stats
                    .push(crate::outputs::mcap_log::FrameStats {
                        frame: frame.index,
                        t: frame.t,
                        tracked_inliers: result.inliers,
                        keyframes: machine.atlas.n_keyframes(),
                        maps: machine.atlas.maps.len(),
                        timing_ms: counts.map(|c| slam.timing().since(&c)),
                    });
            }
            if let Some(v) = viz.as_mut() {
                let (machine, timing) = slam.machine_and_timing();
                if let Err(e) = timing.time("visualize", || v.log_frame(&frame, &m, machine, &out))
                {
                    slam.recorded_mut().failure = Some(e);
                    break;
                }
            }
            let machine = slam.machine();
            if let Some(hook) = &input.opts.progress {
                (hook.0)(&Progress {
                    delivered: slam.delivered(),
                    total: n,
                    state: &out.state,
                    maps: machine.atlas.maps.len(),
                    keyframes: machine.atlas.n_keyframes(),
                });
            }
            if machine.state == crate::control::State::Final {
                // The controller stopped (LDSO on loss, or a map no pool explains): the rest of
                // the sequence is not processed.
                break;
            }
            // Interruptible: a user stop (SIGINT/SIGTERM) ends the run after this frame.
            if crate::interrupt::stop_requested() {
                let delivered = slam.delivered();
                slam.recorded_mut().user_stop = Some((frame.index, frame.t));
                tracing::warn!(
                    "user stop after frame {} ({} of {n} delivered): to Final",
                    frame.index,
                    delivered
                );
                break;
            }
            let delivered = slam.delivered();
            if delivered.is_multiple_of(100) {
                tracing::info!(
                    "frame {}/{n} state {} keyframes {}",
                    delivered,
                    out.state,
                    slam.machine().atlas.n_keyframes()
                );
            }
        }
    });
    extra
}

/// What the run was set up with, for summary.json.
struct Setup {
    config: Config,
    camera: crate::config::CameraConfig,
    source: CameraSource,
}

/// Everything a run ends with, for summary.json and the output files.
struct Finished {
    rec: RunRecord,
    state: String,
    posed: Posed,
    closures: Vec<ClosureRow>,
    keyframes: Vec<(StampedPose, u32)>,
    evaluation: Option<serde_json::Value>,
    timing: Timing,
}

/// summary.json: what ran, on what, how it ended, and (with --eval) how good it is.
fn summarize(
    opts: &RunOptions,
    (seq, n): (&Sequence, usize),
    setup: Setup,
    plan: &PerturbationPlan,
    machine: &StateMachine,
    fin: &mut Finished,
    wall: Instant,
) -> Summary {
    Summary {
        homing_version: env!("CARGO_PKG_VERSION"),
        sequence: opts
            .mcap
            .as_ref()
            .map_or_else(|| opts.sequence.clone(), |m| m.0.clone()),
        command: opts.command.clone(),
        sequence_frames: seq.len(),
        frames: fin.rec.rec.delivered,
        frames_with_pose: fin.posed.trajectory.len(),
        keyframes: fin.keyframes.len(),
        maps: machine.atlas.maps.len(),
        closure_candidates: fin.closures.len(),
        closures_rolled_back: fin
            .closures
            .iter()
            .filter(|c| c.verdict == "rolled-back")
            .count(),
        pools: machine.atlas.pools.len(),
        pools_rolled_back: machine.atlas.pools.iter().filter(|p| p.rolled_back).count(),
        merges: crate::slam::merge_rows(machine),
        lift_offs: machine.lift_offs.clone(),
        controller: setup.config.controller.kind.as_str().into(),
        poses_discarded: fin.rec.rec.discarded.len(),
        discarded_poses: std::mem::take(&mut fin.rec.rec.discarded),
        keyframes_discarded: machine.keyframes_discarded,
        map_keyframes: machine
            .atlas
            .maps
            .values()
            .map(|m| (m.id, m.keyframes.len()))
            .collect(),
        stop_reason: machine.stop_reason.clone(),
        user_stop: fin
            .rec
            .rec
            .user_stop
            .map(|(frame, t)| crate::outputs::UserStop {
                frame,
                t,
                frames_not_processed: n - fin.rec.rec.delivered,
                refinement: machine
                    .refinement_cut
                    .clone()
                    .unwrap_or_else(|| "complete".into()),
            }),
        closures_accepted: fin
            .closures
            .iter()
            .filter(|c| crate::outputs::is_accepted(&c.verdict))
            .count(),
        closures_rejected: fin
            .closures
            .iter()
            .filter(|c| c.verdict.starts_with("rejected"))
            .count(),
        final_state: std::mem::take(&mut fin.state),
        perturbations: plan.clone(),
        camera: setup.camera,
        camera_source: setup.source.to_string(),
        config: setup.config,
        timing: fin.timing.summary(),
        mode: if opts.threaded {
            "threaded"
        } else {
            "deterministic"
        },
        wall_time_s: wall.elapsed().as_secs_f64() + fin.rec.rec.extraction_reused_ms / 1e3,
        peak_rss_mb: peak_rss_mb(),
        extraction_reused_s: fin.rec.rec.extraction_reused_ms / 1e3,
        data_duration_s: match (fin.rec.rec.states.first(), fin.rec.rec.states.last()) {
            (Some(a), Some(b)) => b.t - a.t,
            _ => 0.0,
        },
        evaluation: fin.evaluation.take(),
        error: fin.rec.rec.failure.as_ref().map(|e| e.to_string()),
        frames_unreadable: fin.rec.unreadable.len(),
        unreadable_frames: std::mem::take(&mut fin.rec.unreadable),
    }
}

/// The output files (each written atomically), and run.mcap / the rerun recording when asked.
fn write_outputs(
    out: &RunOutputs,
    opts: &RunOptions,
    fin: &Finished,
    summary: &Summary,
    viz: Option<crate::outputs::viz::Visualizer>,
) -> Result<()> {
    out.write_trajectory(&fin.posed.trajectory)?;
    out.write_keyframes(&fin.keyframes)?;
    out.write_states(&fin.rec.rec.states)?;
    out.write_closures(&fin.closures)?;
    out.write_timing(&fin.timing)?;
    out.write_summary(summary)?;
    if let Some(v) = viz {
        v.finish()?;
    }
    if opts.mcap_log {
        crate::outputs::mcap_log::write(
            &out.path("run.mcap"),
            &fin.rec.rec.states,
            &fin.rec.frame_stats,
            &fin.posed.posed,
        )?;
    }
    Ok(())
}

/// This process's peak resident set size in MB (`VmHWM` of /proc/self/status, Linux).
pub fn peak_rss_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// What a sensor that failed to deliver frame `index` gives: black images (no depth either),
/// like a `black` fault.
fn failed_measurement(
    index: usize,
    t: f64,
    camera: &crate::config::CameraConfig,
    mono: bool,
) -> crate::io::tum::Frame {
    let (w, h) = (camera.width, camera.height);
    crate::io::tum::Frame {
        index,
        t,
        rgb: image::RgbImage::new(w, h),
        depth: (!mono).then(|| crate::io::tum::DepthImage {
            width: w,
            height: h,
            data: vec![0.0; (w * h) as usize],
        }),
    }
}

/// The sequence a run with `config_path` and `mono` reads (its frame list and images), for
/// tools that prepare its frames (`io::decoded`).
pub fn open_run_sequence(
    sequence: &std::path::Path,
    config_path: Option<&std::path::Path>,
    mono: bool,
) -> Result<Sequence> {
    Ok(open_run_front_end(sequence, config_path, mono)?.0)
}

/// The camera and ORB settings a run with `config_path` and `mono` extracts features with,
/// and its sequence, for tools that prepare its features (`io::features`).
pub fn open_run_front_end(
    sequence: &std::path::Path,
    config_path: Option<&std::path::Path>,
    mono: bool,
) -> Result<(
    Sequence,
    crate::config::CameraConfig,
    crate::config::OrbConfig,
)> {
    let config = match config_path {
        Some(p) => Config::load(p)?,
        None => Config::default(),
    };
    let opts = RunOptions {
        sequence: sequence.to_path_buf(),
        config: config_path.map(std::path::Path::to_path_buf),
        ..Default::default()
    };
    let mono = mono || config.sequence.mono;
    let (seq, camera, _) = open_sequence(&opts, &config, mono)?;
    Ok((seq, camera, config.orb))
}

/// Opens the TUM folder or the bag and picks the camera.
fn open_sequence(
    opts: &RunOptions,
    config: &Config,
    mono: bool,
) -> Result<(Sequence, crate::config::CameraConfig, CameraSource)> {
    let max_dt = config.sequence.max_association_dt;
    let Some((bag, topics)) = &opts.mcap else {
        let (camera, source) = resolve_camera(config, opts.config.as_deref(), &opts.sequence)?;
        tracing::info!("{}", describe_camera(&camera, &source));
        let seq = TumSequence::open(
            &opts.sequence,
            camera.width,
            camera.height,
            camera.depth_scale,
            max_dt,
            mono,
        )?;
        return Ok((Sequence::Tum(seq), camera, source));
    };
    let mut seq = McapSequence::open(bag, topics, max_dt, mono)?;
    let (camera, source) = seq.resolve_camera(config, opts.config.as_deref())?;
    let source = CameraSource::Bag(source);
    tracing::info!("{}", describe_camera(&camera, &source));
    seq.set_size(camera.width, camera.height);
    Ok((Sequence::Mcap(Box::new(seq)), camera, source))
}

/// A stamp as the output files write it (microseconds), for matching stamps exactly.
fn stamp_key(t: f64) -> u64 {
    (t * 1e6).round() as u64
}

/// ATE/RPE against the sequence's ground truth, or a note why there is none.
fn evaluate(
    seq: &Sequence,
    est: &[StampedPose],
    spec: &PerturbationSpec,
    plan: &PerturbationPlan,
    closures: &[ClosureRow],
    pose_maps: &[(f64, u32)],
    unreadable: &std::collections::BTreeSet<usize>,
) -> Result<Option<serde_json::Value>> {
    let Some(gt) = seq.groundtruth()? else {
        return Ok(Some(
            serde_json::json!({"note": "the sequence has no ground truth (groundtruth.txt or /groundtruth)"}),
        ));
    };
    let align = if spec.mono {
        Alignment::Sim3
    } else {
        Alignment::Se3
    };
    let stamps: Vec<f64> = seq.stamps();
    let eligible = eval::eligible_stamps(&stamps, &gt, 0.02);
    let coverage = eval::coverage(&eligible, est, 0.02);
    if est.len() < 3 {
        return Ok(Some(serde_json::json!({
            "coverage": coverage,
            "note": format!("{} poses: too few to align and evaluate", est.len()),
        })));
    }
    let assoc = match eval::associate_and_align(&gt, est, align, 0.02) {
        Ok(a) => a,
        // A trajectory that cannot be aligned (a straight line, a point) is a fact about the
        // run, not an error of it.
        Err(e) => {
            return Ok(Some(serde_json::json!({
                "coverage": coverage,
                "note": format!("no ATE: {e}"),
            })));
        }
    };
    let ate = eval::ate(&assoc, align);
    let rpe = eval::rpe(&assoc, 1.0, RpeUnit::Seconds, false).ok();
    let (maps, largest) = eval::run::per_map_ate(&gt, est, pose_maps, align, 0.02);
    let mono = (align == Alignment::Sim3).then(|| eval::run::MonoScales::from_maps(&maps, largest));
    // A closure relates images: one whose keyframe or query is a foreign frame is judged by
    // where that image was taken (its source frame's ground truth), not by the stamp it was
    // delivered under.
    let source_stamp: std::collections::BTreeMap<u64, f64> = plan
        .faults
        .iter()
        .filter_map(|f| Some((stamp_key(stamps[f.frame]), stamps[f.source?])))
        .collect();
    let restamp = |t: f64| source_stamp.get(&stamp_key(t)).copied().unwrap_or(t);
    let closures: Vec<ClosureRow> = closures
        .iter()
        .map(|r| ClosureRow {
            t_query: restamp(r.t_query),
            t_match: restamp(r.t_match),
            ..r.clone()
        })
        .collect();
    let closures = eval::run::check_closures(&closures, &gt, 0.02, mono.as_ref());
    let largest_map = largest.and_then(|l| maps.iter().find(|m| m.map == l));
    // Coverage of the largest map alone: frames posed in disconnected maps do not count, so a
    // controller that starts a new map on every loss (PRoSLAM) is not credited for poses it
    // cannot relate to the rest (the robustness benchmark's coverage). `est` and `pose_maps`
    // are built together, pose by pose.
    let largest_est: Vec<StampedPose> = est
        .iter()
        .zip(pose_maps)
        .filter(|(_, (_, m))| Some(*m) == largest)
        .map(|(p, _)| *p)
        .collect();
    let largest_map_coverage = eval::coverage(&eligible, &largest_est, 0.02);
    // Recovery as the robustness benchmark judges it: of the frames delivered (false frames
    // and unreadable ones excluded: nothing should pose them), those the final largest map
    // holds within ACCURATE_M of the truth after aligning that map alone.
    let faults: std::collections::BTreeSet<usize> = plan
        .faults
        .iter()
        .map(|f| f.frame)
        .chain(unreadable.iter().copied())
        .collect();
    let delivered: Vec<f64> = plan
        .delivered
        .iter()
        .filter(|i| !faults.contains(i))
        .filter_map(|&i| stamps.get(i).copied())
        .collect();
    let delivered = eval::eligible_stamps(&delivered, &gt, 0.02);
    let accurate: Vec<StampedPose> = largest_map
        .map(|m| {
            m.accurate
                .iter()
                .map(|&t| StampedPose {
                    t,
                    pose: nalgebra::Isometry3::identity(),
                })
                .collect()
        })
        .unwrap_or_default();
    let largest_map_accurate_coverage = eval::coverage(&delivered, &accurate, 0.02);
    serde_json::to_value(serde_json::json!({
        "ate": ate,
        "rpe": rpe,
        "coverage": coverage,
        "largest_map_coverage": largest_map_coverage,
        "largest_map_accurate_coverage": largest_map_accurate_coverage,
        "delivered_frames_judged": delivered.len(),
        "closures": closures,
        "maps": maps,
        "largest_map": largest_map,
    }))
    .map(Some)
    .map_err(|e| Error::invalid(e.to_string()))
}
