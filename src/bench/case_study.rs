//! `homing bench case-study`: the paper's Table II, reproduced. Both sessions of the synthetic
//! robot-vacuum case study run under every controller on the same components; each run's
//! state timeline is compared step by step with the paper's column for that controller.
//!
//! Session 2 (step 14) starts from the atlas session 1 saved — for `ours`, the only
//! controller that loads a map (the peers start from scratch, as the paper's "Init" says).
//! The paper's "N/A" (the system has stopped or has no such state) is a stopped machine here:
//! `Final`.

use crate::config::ControllerKind;
use crate::error::{Error, Result};
use crate::eval::timeline::{self, StepResult};
use crate::outputs::Summary;
use crate::system::{RunOptions, run};
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

pub const CONTROLLERS: [ControllerKind; 4] = [
    ControllerKind::Ours,
    ControllerKind::Orbslam2,
    ControllerKind::Proslam,
    ControllerKind::Ldso,
];

/// The paper's Table II columns for the peers, steps 0–14 (ours comes from scenario.json).
fn paper_column(kind: ControllerKind) -> Option<[&'static [&'static str]; 15]> {
    const I: &[&str] = &["Init"];
    const M: &[&str] = &["Mapping"];
    const R: &[&str] = &["Relocalization"];
    const F: &[&str] = &["Final"];
    match kind {
        ControllerKind::Ours => None,
        ControllerKind::Orbslam2 => Some([I, M, M, M, R, R, R, R, R, M, R, R, R, F, I]),
        ControllerKind::Ldso => Some([I, M, M, M, F, F, F, F, F, F, F, F, F, F, I]),
        ControllerKind::Proslam => Some([I, M, M, M, R, M, M, M, M, M, R, M, M, F, I]),
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ControllerResult {
    pub controller: String,
    pub steps_total: usize,
    pub steps_matched: usize,
    pub steps: Vec<StepResult>,
    pub maps: usize,
    pub keyframes: usize,
    pub coverage: Option<f64>,
    pub ate_largest_map_m: Option<f64>,
    pub closures_accepted: u64,
    pub closures_accepted_wrong: u64,
    pub closures_rolled_back: u64,
    pub final_state: String,
    /// Session 2 (step 14): the first frame whose camera is within
    /// [`KNOWN_VIEW_DISTANCE_M`] and [`KNOWN_VIEW_ANGLE_DEG`] of a session-1 keyframe (ground
    /// truth of both: the mapped part of Room 2 comes into view) and the first frame in
    /// Localized; the issue asks for at most 30 frames between them.
    pub session2_known_view_frame: Option<usize>,
    pub session2_localized_frame: Option<usize>,
}

/// Session 2's camera "sees the mapped part of Room 2" when it is this close to where a
/// session-1 keyframe looked from (the viewpoints the atlas can recognise).
pub const KNOWN_VIEW_DISTANCE_M: f64 = 1.5;
pub const KNOWN_VIEW_ANGLE_DEG: f64 = 30.0;

#[derive(Debug, Clone, Serialize)]
pub struct CaseStudy {
    pub data: PathBuf,
    /// Frames of tolerance around each step's boundaries.
    pub window_frames: usize,
    pub controllers: Vec<ControllerResult>,
}

/// Generates the case study with the `homing-datasets` binary next to this one (the homing
/// library cannot depend on the generator crate, which depends on it).
pub fn generate(dir: &Path, small: bool) -> Result<()> {
    let exe = std::env::current_exe().map_err(|e| Error::invalid(e.to_string()))?;
    let gen_name = format!("homing-datasets{}", std::env::consts::EXE_SUFFIX);
    let generator = exe.with_file_name(&gen_name);
    if !generator.is_file() {
        return Err(Error::invalid(format!(
            "{} not found: build it (cargo build --release -p homing-datasets) or pass --data DIR \
             with a generated case study",
            generator.display()
        )));
    }
    let mut cmd = std::process::Command::new(&generator);
    cmd.args(["synth", "--scenario", "case-study", "--out"])
        .arg(dir);
    if small {
        cmd.arg("--small");
    }
    tracing::info!("bench: generating the case study into {}", dir.display());
    let status = cmd
        .status()
        .map_err(|e| Error::invalid(format!("cannot run {}: {e}", generator.display())))?;
    if !status.success() {
        return Err(Error::invalid(format!(
            "{} failed: {status}",
            generator.display()
        )));
    }
    Ok(())
}

fn num(s: &Summary, ptr: &str) -> Option<f64> {
    s.evaluation.as_ref()?.pointer(ptr)?.as_f64()
}

/// How [`case_study`] runs.
#[derive(Debug, Clone)]
pub struct Options {
    pub threaded: bool,
    /// In table order.
    pub controllers: Vec<ControllerKind>,
    /// Config file for every run (`None`: the defaults).
    pub config: Option<PathBuf>,
    /// Controllers run at a time (0: one per core). Each controller's two sessions are
    /// independent of the others', so the outputs do not depend on it.
    pub jobs: usize,
    /// Reuse the controllers a stopped (or earlier) case study with the same data, config and
    /// mode finished in OUT (see [`DONE_MARK`]); only the others run.
    pub resume: bool,
    /// Run nothing: only the controllers finished in OUT (by another process, such as a
    /// benchmark plan's job) make the table; the others are reported as not finished.
    pub collect_only: bool,
}

impl Default for Options {
    fn default() -> Self {
        Self {
            threaded: false,
            controllers: CONTROLLERS.to_vec(),
            config: None,
            jobs: 0,
            resume: false,
            collect_only: false,
        }
    }
}

/// What every controller's runs share: the two sessions and their steps.
struct Sessions<'a> {
    s1: &'a Path,
    s2: &'a Path,
    steps1: &'a [timeline::ScenarioStep],
    steps2: &'a [timeline::ScenarioStep],
    window: usize,
}

/// Both sessions under controller `kind`, compared with its Table II column; `None` when a
/// user stop ended a session early (its outputs are written, but it is no Table II run).
fn run_controller(
    kind: ControllerKind,
    session: &Sessions<'_>,
    out: &Path,
    o: &Options,
) -> Result<Option<ControllerResult>> {
    let (s1, s2, window) = (session.s1, session.s2, session.window);
    let name = kind.as_str();
    let dir = out.join(name);
    let atlas = dir.join("atlas.bin");
    let ours = kind == ControllerKind::Ours;
    let session_run = |sequence: &Path, sub: &str| RunOptions {
        sequence: sequence.to_path_buf(),
        out: dir.join(sub),
        eval: true,
        command: std::env::args().collect(),
        threaded: o.threaded,
        config: o.config.clone(),
        controller: Some(kind),
        ..Default::default()
    };
    tracing::info!("bench case-study: {name}, session 1");
    let sum1 = run(&RunOptions {
        save_map: ours.then(|| atlas.clone()),
        ..session_run(s1, "session1")
    })?;
    if sum1.user_stop.is_some() {
        return Ok(None);
    }
    tracing::info!("bench case-study: {name}, session 2");
    let sum2 = run(&RunOptions {
        load_map: ours.then(|| atlas.clone()),
        ..session_run(s2, "session2")
    })?;
    if sum2.user_stop.is_some() {
        return Ok(None);
    }
    let mut st1 = session.steps1.to_vec();
    let mut st2 = session.steps2.to_vec();
    if let Some(col) = paper_column(kind) {
        for s in st1.iter_mut().chain(st2.iter_mut()) {
            if let Some(e) = col.get(s.step as usize) {
                s.expected_states = e.iter().map(|x| x.to_string()).collect();
            }
        }
    }
    let rows1 = crate::outputs::read_states(&dir.join("session1/states.csv"))?;
    let rows2 = crate::outputs::read_states(&dir.join("session2/states.csv"))?;
    let known_view = if ours {
        first_known_view(s1, s2, &dir.join("session1/keyframes.txt"))?
    } else {
        None
    };
    let localized = rows2
        .iter()
        .find(|r| r.state == "Localized")
        .map(|r| r.frame);
    let mut steps = timeline::compare(&st1, &rows1, window);
    steps.extend(timeline::compare(&st2, &rows2, window));
    let c = |p: &str| {
        sum1.evaluation
            .as_ref()
            .and_then(|e| e.pointer(p))
            .and_then(|v| v.as_u64())
            .unwrap_or(0)
    };
    Ok(Some(ControllerResult {
        controller: name.into(),
        steps_total: steps.len(),
        steps_matched: steps.iter().filter(|s| s.matched).count(),
        maps: sum1.maps,
        keyframes: sum1.keyframes,
        coverage: num(&sum1, "/coverage"),
        ate_largest_map_m: num(&sum1, "/largest_map/ate_rmse_m"),
        closures_accepted: c("/closures/accepted"),
        closures_accepted_wrong: c("/closures/accepted_wrong"),
        closures_rolled_back: c("/closures/rolled_back"),
        final_state: sum1.final_state.clone(),
        steps,
        session2_known_view_frame: known_view,
        session2_localized_frame: localized,
    }))
}

/// Written into OUT/CONTROLLER/ once both of its sessions finished: what the runs depended on
/// (`identity`) and the controller's result, which `--resume` reuses.
pub const DONE_MARK: &str = "bench-done.json";

#[derive(Serialize, Deserialize)]
struct Done {
    identity: String,
    result: ControllerResult,
}

/// What a controller's runs depend on besides the binary's code: the data, the config's
/// text, the mode and the controller.
fn identity(kind: ControllerKind, data: &Path, o: &Options) -> String {
    let config = super::config_text(o.config.as_deref());
    format!(
        "homing {}\ndata {}\nthreaded {}\ncontroller {}\nconfig\n{config}",
        env!("CARGO_PKG_VERSION"),
        data.display(),
        o.threaded,
        kind.as_str()
    )
}

/// A controller's result: reused from an earlier finished run with `--resume`, `None` when a
/// user stop came before or during its runs, else run now (and marked done).
fn finished_or_run(
    kind: ControllerKind,
    session: &Sessions<'_>,
    data: &Path,
    out: &Path,
    o: &Options,
) -> Result<Option<ControllerResult>> {
    if (o.resume || o.collect_only)
        && let Some(result) = finished(kind, data, out, o)
    {
        tracing::info!("{} is finished", out.join(kind.as_str()).display());
        return Ok(Some(result));
    }
    if o.collect_only || crate::interrupt::stop_requested() {
        return Ok(None);
    }
    let Some(result) = run_controller(kind, session, out, o)? else {
        return Ok(None);
    };
    let done = Done {
        identity: identity(kind, data, o),
        result,
    };
    let json = serde_json::to_vec_pretty(&done).map_err(|e| Error::invalid(e.to_string()))?;
    crate::io::atomic_write(&out.join(kind.as_str()).join(DONE_MARK), &json)?;
    Ok(Some(done.result))
}

/// Controller `kind`'s result when a case study with the same data, config and mode
/// finished it in OUT (its [`DONE_MARK`]), whichever process ran it.
pub fn finished(
    kind: ControllerKind,
    data: &Path,
    out: &Path,
    o: &Options,
) -> Option<ControllerResult> {
    let text = std::fs::read_to_string(out.join(kind.as_str()).join(DONE_MARK)).ok()?;
    let done = serde_json::from_str::<Done>(&text).ok()?;
    (done.identity == identity(kind, data, o)).then_some(done.result)
}

/// Runs the controllers on both sessions under `data` (session1/, session2/) and writes
/// OUT/case_study.md and OUT/case_study.json.
pub fn case_study(data: &Path, out: &Path, o: &Options) -> Result<(CaseStudy, String)> {
    let s1 = data.join("session1");
    let s2 = data.join("session2");
    let steps1 = timeline::read_steps(&s1.join("scenario.json"))?;
    let steps2 = timeline::read_steps(&s2.join("scenario.json"))?;
    let fps = scenario_fps(&s1.join("scenario.json"))?;
    let window = (fps * 1.0).round() as usize;
    let session = Sessions {
        s1: &s1,
        s2: &s2,
        steps1: &steps1,
        steps2: &steps2,
        window,
    };
    // The controllers' runs are independent: `jobs` at a time (the benchmark's case study was
    // a quarter of its wall time, on one core), results in table order. After a user stop a
    // controller whose runs did not both finish has no result.
    let results = super::parallel_map(&o.controllers, super::resolve_jobs(o.jobs), |&kind| {
        finished_or_run(kind, &session, data, out, o)
    })
    .into_iter()
    .collect::<Result<Vec<_>>>()?;
    let unfinished = results.iter().filter(|r| r.is_none()).count();
    let cs = CaseStudy {
        data: data.to_path_buf(),
        window_frames: window,
        controllers: results.into_iter().flatten().collect(),
    };
    let mut md = markdown(&cs, &steps1, &steps2);
    if unfinished > 0 && o.collect_only {
        let _ = writeln!(
            md,
            "\n**Not finished:** {unfinished} of {} controllers (their jobs did not finish): run them, then collect again.",
            o.controllers.len()
        );
    } else if unfinished > 0 {
        let _ = writeln!(
            md,
            "\n**Stopped by the user:** {unfinished} of {} controllers not finished; the same command with `--resume` runs only those.",
            o.controllers.len()
        );
    }
    std::fs::create_dir_all(out).map_err(|e| Error::file(out, format!("cannot create: {e}")))?;
    crate::io::atomic_write(&out.join("case_study.md"), md.as_bytes())?;
    let json = serde_json::to_vec_pretty(&cs).map_err(|e| Error::invalid(e.to_string()))?;
    crate::io::atomic_write(&out.join("case_study.json"), &json)?;
    Ok((cs, md))
}

/// The first session-2 frame (index in rgb.txt) whose ground-truth camera is near the
/// ground-truth pose of a session-1 keyframe (see [`KNOWN_VIEW_DISTANCE_M`]).
fn first_known_view(s1: &Path, s2: &Path, keyframes: &Path) -> Result<Option<usize>> {
    use crate::io::tum::{associate_nearest, read_list, read_trajectory};
    let gt1 = read_trajectory(&s1.join("groundtruth.txt"))?;
    let gt2 = read_trajectory(&s2.join("groundtruth.txt"))?;
    let frames2 = read_list(&s2.join("rgb.txt"))?;
    let kfs = crate::outputs::report::read_keyframes(keyframes)?;
    let t1: Vec<f64> = gt1.iter().map(|p| p.t).collect();
    let t_kf: Vec<f64> = kfs.iter().map(|(p, _)| p.t).collect();
    let views: Vec<_> = associate_nearest(&t_kf, &t1, 0.02)
        .into_iter()
        .map(|(_, j)| gt1[j].pose)
        .collect();
    let t2: Vec<f64> = gt2.iter().map(|p| p.t).collect();
    let tf: Vec<f64> = frames2.iter().map(|e| e.t).collect();
    for (i, j) in associate_nearest(&tf, &t2, 0.02) {
        let cam = &gt2[j].pose;
        let near = views.iter().any(|v| {
            let d = (v.translation.vector - cam.translation.vector).norm();
            let a = (v.rotation * nalgebra::Vector3::z())
                .angle(&(cam.rotation * nalgebra::Vector3::z()));
            d <= KNOWN_VIEW_DISTANCE_M && a.to_degrees() <= KNOWN_VIEW_ANGLE_DEG
        });
        if near {
            return Ok(Some(i));
        }
    }
    Ok(None)
}

fn scenario_fps(path: &Path) -> Result<f64> {
    let text = crate::error::read_text(path)?;
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| Error::parse(path, e.line(), e.to_string()))?;
    v.get("fps")
        .and_then(|f| f.as_f64())
        .ok_or_else(|| Error::file(path, "no fps"))
}

fn markdown(
    cs: &CaseStudy,
    steps1: &[timeline::ScenarioStep],
    steps2: &[timeline::ScenarioStep],
) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "# Case study (paper Table II): {}\n", cs.data.display());
    let _ = writeln!(
        md,
        "Each cell: the states observed during the step (±{} frames); ✓ when the expected \
         states (ours: Table II's last column; peers: their columns, N/A = Final) occur in \
         order and the step's dominant state is one of them.\n",
        cs.window_frames
    );
    let head: Vec<String> = cs
        .controllers
        .iter()
        .map(|c| format!("{} ({}/{})", c.controller, c.steps_matched, c.steps_total))
        .collect();
    let _ = writeln!(
        md,
        "| step | event | expected (ours) | {} |",
        head.join(" | ")
    );
    let _ = writeln!(md, "|---|---|---|{}", "---|".repeat(cs.controllers.len()));
    let all: Vec<&timeline::ScenarioStep> = steps1.iter().chain(steps2).collect();
    for (i, s) in all.iter().enumerate() {
        let cells: Vec<String> = cs
            .controllers
            .iter()
            .map(|c| {
                let r = &c.steps[i];
                format!(
                    "{} {}",
                    if r.matched { "✓" } else { "✗" },
                    r.observed.join(" → ")
                )
            })
            .collect();
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} |",
            s.step,
            s.event,
            s.expected_states.join(", "),
            cells.join(" | ")
        );
    }
    let _ = writeln!(md);
    let _ = writeln!(
        md,
        "| controller | steps matched | maps | keyframes | coverage | ATE largest map (cm) | closures accepted (wrong) | rolled back | final state |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|");
    for c in &cs.controllers {
        let _ = writeln!(
            md,
            "| {} | {}/{} | {} | {} | {} | {} | {} ({}) | {} | {} |",
            c.controller,
            c.steps_matched,
            c.steps_total,
            c.maps,
            c.keyframes,
            c.coverage
                .map_or("–".into(), |v| format!("{:.1} %", 100.0 * v)),
            c.ate_largest_map_m
                .map_or("–".into(), |v| format!("{:.2}", 100.0 * v)),
            c.closures_accepted,
            c.closures_accepted_wrong,
            c.closures_rolled_back,
            c.final_state
        );
    }
    for c in &cs.controllers {
        if let Some(v) = c.session2_known_view_frame {
            let _ = writeln!(
                md,
                "\n{}, session 2: the camera first looks from within {KNOWN_VIEW_DISTANCE_M} m and \
                 {KNOWN_VIEW_ANGLE_DEG}° of a session-1 keyframe at frame {v}; {}.",
                c.controller,
                match c.session2_localized_frame {
                    Some(l) => format!(
                        "Localized at frame {l} ({} frames later)",
                        l as i64 - v as i64
                    ),
                    None => "never Localized".into(),
                }
            );
        }
    }
    md
}
