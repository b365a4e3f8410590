//! Benchmarks that print numbers (never assert on them): `homing bench tracking` runs a
//! sequence in both modes and reports per-stage milliseconds per frame, throughput against
//! real time and the trajectory error; `homing bench case-study` reproduces the paper's
//! Table II (see [`case_study`]); `homing bench robustness` runs the perturbation grid of the
//! paper's experiments under every controller (see [`robustness`]); `homing bench overlap`
//! measures with the ground truth how much place evidence two stretches share (see [`overlap`]).

pub mod case_study;
pub mod memory;
pub mod overlap;
pub mod plan;
pub mod robustness;
pub mod robustness_plot;

use crate::error::Result;
use crate::system::{RunOptions, run};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Written into OUT/MODE/ once `homing bench tracking`'s run in that mode finished: what it
/// depended on ([`tracking_identity`]), which `--resume` compares.
const TRACKING_DONE_MARK: &str = "bench-done.txt";

/// What a tracking run depends on besides its mode: the binary's version, the sequence,
/// whether depth is suppressed and the config's text.
fn tracking_identity(sequence: &Path, config: Option<&Path>, mono: bool) -> String {
    let config = config_text(config);
    format!(
        "homing {}\nsequence {}\nmono {mono}\nconfig\n{config}",
        env!("CARGO_PKG_VERSION"),
        sequence.display()
    )
}

/// A config file's text, for the identity of a benchmark's finished runs that `--resume`
/// compares (a run with another config is not reused).
pub(crate) fn config_text(config: Option<&Path>) -> String {
    config.map_or("(defaults)".to_string(), |c| {
        std::fs::read_to_string(c).unwrap_or_else(|e| format!("{}: {e}", c.display()))
    })
}

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

/// Runs `sequence` deterministic and threaded (with depth suppressed when `mono`), writes
/// OUT/{deterministic,threaded}/ and returns a Markdown report.
pub fn tracking(
    sequence: &Path,
    config: Option<&Path>,
    mono: bool,
    out: &Path,
    resume: bool,
) -> Result<String> {
    // Each mode's summary.json, as written (a resumed mode's is read back).
    let mut runs: Vec<(&str, serde_json::Value)> = Vec::new();
    let mut stopped = Vec::new();
    for (mode, threaded) in [("deterministic", false), ("threaded", true)] {
        let dir = out.join(mode);
        let mark = dir.join(TRACKING_DONE_MARK);
        let id = tracking_identity(sequence, config, mono);
        if resume
            && std::fs::read_to_string(&mark).is_ok_and(|m| m == id)
            && let Ok(text) = std::fs::read_to_string(dir.join("summary.json"))
            && let Ok(summary) = serde_json::from_str(&text)
        {
            tracing::info!("resumed: the {mode} run is finished");
            runs.push((mode, summary));
            continue;
        }
        if crate::interrupt::stop_requested() {
            stopped.push(mode);
            continue;
        }
        let opts = RunOptions {
            sequence: sequence.to_path_buf(),
            out: dir.clone(),
            config: config.map(PathBuf::from),
            perturb: crate::io::perturb::PerturbationSpec {
                mono,
                ..Default::default()
            },
            eval: true,
            command: std::env::args().collect(),
            threaded,
            ..Default::default()
        };
        tracing::info!("bench: {mode} run of {}", sequence.display());
        let summary = run(&opts)?;
        if summary.user_stop.is_some() {
            stopped.push(mode);
            continue;
        }
        crate::io::atomic_write(&mark, id.as_bytes())?;
        let value = serde_json::to_value(&summary)
            .map_err(|e| crate::error::Error::invalid(e.to_string()))?;
        runs.push((mode, value));
    }
    let mut md = String::new();
    let _ = writeln!(
        md,
        "# homing bench tracking: {}{}\n",
        sequence.display(),
        if mono { " (monocular)" } else { "" }
    );
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
                let t = |k: &str| s.pointer(&format!("/timing/{stage}/{k}"))?.as_f64();
                match (t("median_ms"), t("p90_ms"), t("count")) {
                    (Some(m), Some(p), Some(n)) => format!("{m:.1} / {p:.1} (n={n})"),
                    _ => "–".into(),
                }
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
        let f = |p: &str| s.pointer(p).and_then(|v| v.as_f64()).unwrap_or(0.0);
        let (frames, wall, data) = (f("/frames"), f("/wall_time_s"), f("/data_duration_s"));
        let fps = frames / wall.max(1e-9);
        let rt = data / wall.max(1e-9);
        let ate = s
            .pointer("/evaluation/ate/stats/rmse")
            .and_then(|v| v.as_f64())
            .map_or("–".into(), |v| format!("{:.3}", v * 100.0));
        let _ = writeln!(
            md,
            "| {mode} | {frames} | {wall:.2} | {data:.2} | {fps:.1} | {rt:.2} | {} | {ate} |",
            f("/keyframes")
        );
    }
    if !stopped.is_empty() {
        let _ = writeln!(
            md,
            "\n**Stopped by the user:** the {} run{} not finished; the same command with `--resume` runs only {}.",
            stopped.join(" and "),
            if stopped.len() > 1 { "s are" } else { " is" },
            if stopped.len() > 1 {
                "those"
            } else {
                "that one"
            }
        );
    }
    crate::io::atomic_write(&out.join("bench_tracking.md"), md.as_bytes())?;
    Ok(md)
}
