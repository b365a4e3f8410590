//! Benchmarks that print numbers (never assert on them): `homing bench tracking` runs a
//! sequence in both modes and reports per-stage milliseconds per frame, throughput against
//! real time and the trajectory error; `homing bench case-study` reproduces the paper's
//! Table II (see [`case_study`]); `homing bench robustness` runs the perturbation grid of the
//! paper's experiments under every controller (see [`robustness`]); `homing bench overlap`
//! measures with the ground truth how much place evidence two stretches share (see [`overlap`]).

pub mod case_study;
pub mod memory;
pub mod overlap;
pub mod robustness;
pub mod robustness_plot;

use crate::error::Result;
use crate::output::Summary;
use crate::system::{RunOptions, run};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Jobs to run at a time: `jobs`, or one per core when it is 0.
pub(crate) fn resolve_jobs(jobs: usize) -> usize {
    if jobs == 0 {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    } else {
        jobs
    }
}

/// `f` applied to every item, `jobs` at a time; results come back in item order whatever
/// order they finish in.
pub(crate) fn parallel_map<T: Sync, R: Send>(
    items: &[T],
    jobs: usize,
    f: impl Fn(&T) -> R + Sync,
) -> Vec<R> {
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicUsize, Ordering};
    let next = AtomicUsize::new(0);
    let slots: Mutex<Vec<Option<R>>> = Mutex::new((0..items.len()).map(|_| None).collect());
    std::thread::scope(|s| {
        for _ in 0..jobs.clamp(1, items.len().max(1)) {
            s.spawn(|| {
                loop {
                    let i = next.fetch_add(1, Ordering::SeqCst);
                    let Some(item) = items.get(i) else { break };
                    let r = f(item);
                    slots.lock().unwrap_or_else(|e| e.into_inner())[i] = Some(r);
                }
            });
        }
    });
    slots
        .into_inner()
        .unwrap_or_else(|e| e.into_inner())
        .into_iter()
        .flatten()
        .collect()
}

/// The stages reported, in pipeline order, with what they cover.
const STAGES: &[(&str, &str)] = &[
    ("load", "PNG decoding (loader thread)"),
    ("preprocess", "ORB extraction, undistortion, depth"),
    ("track", "tracker"),
    ("extract_track", "preprocess + track per frame"),
    ("map", "keyframe insertion (+ local BA when deterministic)"),
    ("local_ba_thread", "local BA on the mapping thread"),
    ("final_ba", "full BA in Final"),
    ("frame", "whole step on the tracking thread"),
];

/// Runs `sequence` deterministic and threaded, writes OUT/{deterministic,threaded}/ and
/// returns a Markdown report.
pub fn tracking(sequence: &Path, config: Option<&Path>, out: &Path) -> Result<String> {
    let mut runs: Vec<(&str, Summary)> = Vec::new();
    for (mode, threaded) in [("deterministic", false), ("threaded", true)] {
        let opts = RunOptions {
            sequence: sequence.to_path_buf(),
            out: out.join(mode),
            config: config.map(PathBuf::from),
            eval: true,
            command: std::env::args().collect(),
            threaded,
            ..Default::default()
        };
        tracing::info!("bench: {mode} run of {}", sequence.display());
        runs.push((mode, run(&opts)?));
    }
    let mut md = String::new();
    let _ = writeln!(md, "# homing bench tracking: {}\n", sequence.display());
    let _ = writeln!(
        md,
        "Per-stage time per call, median / p90 (ms); cores: {}.\n",
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    let _ = writeln!(
        md,
        "| stage | what | {} |",
        runs.iter().map(|(m, _)| *m).collect::<Vec<_>>().join(" | ")
    );
    let _ = writeln!(md, "|---|---|{}", "---|".repeat(runs.len()));
    for (stage, what) in STAGES {
        let cells: Vec<String> = runs
            .iter()
            .map(|(_, s)| {
                s.timing.get(*stage).map_or("–".into(), |t| {
                    format!("{:.1} / {:.1} (n={})", t.median_ms, t.p90_ms, t.count)
                })
            })
            .collect();
        let _ = writeln!(md, "| {stage} | {what} | {} |", cells.join(" | "));
    }
    let _ = writeln!(md);
    let _ = writeln!(
        md,
        "| mode | frames | wall s | data s | fps | × real time | keyframes | ATE RMSE cm |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|");
    for (mode, s) in &runs {
        let fps = s.frames as f64 / s.wall_time_s.max(1e-9);
        let rt = s.data_duration_s / s.wall_time_s.max(1e-9);
        let ate = s
            .evaluation
            .as_ref()
            .and_then(|e| e.pointer("/ate/stats/rmse"))
            .and_then(|v| v.as_f64())
            .map_or("–".into(), |v| format!("{:.3}", v * 100.0));
        let _ = writeln!(
            md,
            "| {mode} | {} | {:.2} | {:.2} | {:.1} | {:.2} | {} | {ate} |",
            s.frames, s.wall_time_s, s.data_duration_s, fps, rt, s.keyframes
        );
    }
    crate::io::atomic_write(&out.join("bench_tracking.md"), md.as_bytes())?;
    Ok(md)
}
