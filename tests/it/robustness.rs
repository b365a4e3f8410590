//! `homing bench robustness --quick` on a tiny generated sequence: the CSV has its columns and
//! one row per (perturbation, controller), every row records its command, and re-running a
//! row's command reproduces its trajectory byte for byte (the bench's runs read decoded
//! frames, the re-run decodes the PNGs).

use crate::common;

use homing_datasets::{scenarios, sensor::SensorOptions, writer};
use std::path::Path;

/// Splits one CSV line, honouring double quotes.
fn csv_split(line: &str) -> Vec<String> {
    let mut out = vec![String::new()];
    let mut quoted = false;
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        match (c, quoted) {
            ('"', true) if chars.peek() == Some(&'"') => {
                chars.next();
                out.last_mut().unwrap().push('"');
            }
            ('"', _) => quoted = !quoted,
            (',', false) => out.push(String::new()),
            _ => out.last_mut().unwrap().push(c),
        }
    }
    out
}

fn generate_desk(dir: &Path, frames: usize) {
    let sc = scenarios::build("desk", 1).unwrap();
    common::generate(
        &sc,
        &writer::GenOptions {
            out: dir.to_path_buf(),
            small: true,
            seed: 1,
            sensor: SensorOptions::realistic(),
            max_frames: Some(frames),
        },
    );
}

/// `homing bench robustness` on `seq`'s quick grid (none and one kidnapping) under ours and
/// ProSLAM's controller: four runs, `jobs` at a time, into `out`.
fn quick_grid_args(seq: &Path, jobs: usize, out: &Path) -> Vec<String> {
    [
        "bench",
        "robustness",
        "--sequence",
        &seq.display().to_string(),
        "--quick",
        "--controller",
        "ours",
        "--controller",
        "proslam",
        "--jobs",
        &jobs.to_string(),
        "--out",
        &out.display().to_string(),
    ]
    .map(String::from)
    .to_vec()
}

#[test]
fn quick_grid_rows_commands_and_reproduction() {
    let tmp = tempfile::tempdir().unwrap();
    let seq = tmp.path().join("desk");
    // 72 frames at 15 Hz: 4.7 s, long enough for a 1 s kidnapping with 1 s tracked around it.
    generate_desk(&seq, 72);
    let out = tmp.path().join("bench");
    let args = quick_grid_args(&seq, 2, &out);
    let (ok, stdout, stderr) = common::homing(&args);
    assert!(ok, "bench failed: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    // A progress line per run, then the Markdown table.
    assert_eq!(stdout.lines().filter(|l| l.starts_with('[')).count(), 4);
    assert!(
        stdout.contains("| perturbation | ours | proslam |"),
        "{stdout}"
    );
    assert!(stdout.contains("kidnap-1x1s: ours"), "{stdout}");

    let csv = std::fs::read_to_string(out.join("robustness.csv")).unwrap();
    let mut lines = csv.lines();
    let header = csv_split(lines.next().unwrap());
    for col in [
        "sequence",
        "perturbation",
        "controller",
        "ate_m",
        "coverage",
        "maps",
        "closures_accepted",
        "closures_wrong",
        "recovery_frames",
        "final_state",
        "wall_s",
        "fps",
        "command",
    ] {
        assert!(
            header.iter().any(|h| h == col),
            "no column {col}: {header:?}"
        );
    }
    let col = |name: &str| header.iter().position(|h| h == name).unwrap();
    let rows: Vec<Vec<String>> = lines.map(csv_split).collect();
    assert!(rows.iter().all(|r| r.len() == header.len()), "{csv}");
    let mut keys: Vec<(String, String)> = rows
        .iter()
        .map(|r| (r[col("perturbation")].clone(), r[col("controller")].clone()))
        .collect();
    keys.sort();
    let expected: Vec<(String, String)> = [
        ("kidnap-1x1s", "ours"),
        ("kidnap-1x1s", "proslam"),
        ("none", "ours"),
        ("none", "proslam"),
    ]
    .iter()
    .map(|(a, b)| (a.to_string(), b.to_string()))
    .collect();
    assert_eq!(keys, expected);
    for r in &rows {
        assert_eq!(r[col("sequence")], "desk");
        let cmd = &r[col("command")];
        assert!(cmd.contains(" run --sequence "), "{cmd}");
        assert!(
            cmd.contains(&format!("--controller {}", r[col("controller")])),
            "{cmd}"
        );
        let cov: f64 = r[col("coverage")].parse().unwrap();
        assert!((0.0..=1.0).contains(&cov), "{cov}");
    }

    // Re-run the kidnapped `ours` row by its recorded command: same trajectory, byte for byte.
    let row = rows
        .iter()
        .find(|r| r[col("perturbation")] == "kidnap-1x1s" && r[col("controller")] == "ours")
        .unwrap();
    let cmd = &row[col("command")];
    assert!(
        !cmd.contains('\''),
        "a temporary path needed quoting: {cmd}"
    );
    assert!(cmd.contains("--drop "), "{cmd}");
    let argv: Vec<&str> = cmd.split_whitespace().collect();
    let run_dir = out.join("runs/desk/kidnap-1x1s/ours");
    let before = std::fs::read(run_dir.join("trajectory.txt")).unwrap();
    assert!(!before.is_empty());
    let status = std::process::Command::new(argv[0])
        .args(&argv[1..])
        .output()
        .unwrap();
    assert!(
        status.status.success(),
        "{}",
        String::from_utf8_lossy(&status.stderr)
    );
    let after = std::fs::read(run_dir.join("trajectory.txt")).unwrap();
    assert!(before == after, "the re-run's trajectory differs");

    // The bench's runs read the frames it decoded once per sequence (`--decoded-frames`),
    // while the CSV records the command without it: the re-run above decoded the PNGs itself
    // and gave the same trajectory. The bench's runs did use the file, and it is gone after.
    assert!(!stderr.contains("decode their images"), "{stderr}");
    for p in ["none", "kidnap-1x1s"] {
        let summary =
            std::fs::read_to_string(out.join(format!("runs/desk/{p}/proslam/summary.json")))
                .unwrap();
        assert!(summary.contains("\"--decoded-frames\""), "{p}: {summary}");
    }
    assert!(!out.join("decoded-frames").exists());
    assert!(!csv.contains("decoded-frames"), "{csv}");
}

#[test]
fn missing_sequence_is_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("nope");
    let (ok, _, stderr) = common::homing(&[
        "bench",
        "robustness",
        "--sequence",
        missing.to_str().unwrap(),
        "--quick",
        "--out",
        tmp.path().join("o").to_str().unwrap(),
    ]);
    common::assert_clear_error(ok, &stderr, "nope");
}

/// `homing bench overlap` on small `aliasing`: where `aliasing` 3×3 s loses the first map (drops
/// 8.15–11.15 s), the ground truth shows no place evidence across the gap (docs/robustness.md);
/// on the same path 0.5–2 s apart it shows plenty, and the turned control shows none.
#[test]
fn overlap_probe_tells_an_absent_join_from_a_present_one() {
    use homing::bench::overlap::{OverlapOptions, overlap};
    let seq = common::small("aliasing");
    let probe = |reference, query| {
        let opts = OverlapOptions {
            reference,
            query,
            every: 5,
            radius_px: 8.0,
        };
        overlap(&seq, None, &opts).unwrap().rows
    };
    let same_path = probe((14.0, 15.0), (15.5, 17.0));
    assert!(!same_path.is_empty());
    for r in &same_path {
        assert!(r.matched_search >= 50, "{r:?}");
        assert!(r.control_tracker <= 3, "{r:?}");
    }
    let across_gap = probe((0.0, 8.15), (11.15, 14.0));
    let best = across_gap.iter().map(|r| r.matched_search).max().unwrap();
    assert!(best <= 5, "{across_gap:?}");
}

/// Ctrl-C (SIGINT to the benchmark) after its first run: no new run starts, the finished row
/// and the unfinished ones are written, and the exit status says it was stopped. The same
/// command with `--resume` reuses the finished run (its row unchanged) and runs only the rest.
#[test]
fn a_stopped_benchmark_keeps_its_finished_rows_and_resumes() {
    use std::io::{BufRead, BufReader};
    let tmp = tempfile::tempdir().unwrap();
    let seq = tmp.path().join("desk");
    generate_desk(&seq, 72);
    let out = tmp.path().join("bench");
    let args = |resume: bool| {
        let mut a = quick_grid_args(&seq, 1, &out);
        if resume {
            a.push("--resume".into());
        }
        a
    };
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_homing"))
        .args(args(false))
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut sent = false;
    for line in BufReader::new(child.stdout.take().unwrap()).lines() {
        if !sent && line.unwrap().starts_with("[1/4]") {
            let pid = child.id().to_string();
            assert!(
                std::process::Command::new("kill")
                    .args(["-INT", &pid])
                    .status()
                    .unwrap()
                    .success()
            );
            sent = true;
        }
    }
    assert_eq!(child.wait().unwrap().code(), Some(130));
    assert!(sent);
    let rows = |csv: &str| csv.lines().skip(1).map(String::from).collect::<Vec<_>>();
    let first = rows(&std::fs::read_to_string(out.join("robustness.csv")).unwrap());
    assert_eq!(first.len(), 4);
    let stopped = first
        .iter()
        .filter(|r| r.contains("stopped by the user before it started"))
        .count();
    assert!((1..=3).contains(&stopped), "{first:#?}");
    let md = std::fs::read_to_string(out.join("robustness.md")).unwrap();
    assert!(md.contains("Stopped by the user"), "{md}");

    let (ok, stdout, stderr) = common::homing(&args(true));
    assert!(ok, "{stderr}");
    assert!(!stdout.contains("stopped by the user"), "{stdout}");
    let second = rows(&std::fs::read_to_string(out.join("robustness.csv")).unwrap());
    assert_eq!(second.len(), 4);
    for (a, b) in first.iter().zip(&second) {
        if !a.contains("stopped by the user") {
            assert_eq!(a, b, "a finished row changed on --resume");
        }
    }
}

/// `homing bench tracking --resume` reuses a mode's run that a finished (or stopped) benchmark
/// with the same sequence and config ran, and runs only the others; another config, or
/// `--mono`, runs both again.
#[test]
fn a_tracking_benchmark_resumes_only_the_runs_not_finished() {
    let tmp = tempfile::tempdir().unwrap();
    let seq = tmp.path().join("desk");
    generate_desk(&seq, 40);
    let out = tmp.path().join("bench");
    let config = tmp.path().join("config.toml");
    std::fs::write(&config, "[tracker]\n").unwrap();
    let args = |resume: bool| {
        let mut a = vec![
            "bench",
            "tracking",
            "--sequence",
            seq.to_str().unwrap(),
            "--config",
            config.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        if resume {
            a.push("--resume");
        }
        a
    };
    let (ok, _, stderr) = common::homing(&args(false));
    assert!(ok, "{stderr}");
    let summary = |mode: &str| std::fs::read(out.join(mode).join("summary.json")).ok();
    let deterministic = summary("deterministic").unwrap();
    // The threaded run as a stop leaves it: outputs written, not marked finished.
    std::fs::remove_file(out.join("threaded/bench-done.txt")).unwrap();
    std::fs::remove_file(out.join("threaded/summary.json")).unwrap();
    let (ok, stdout, stderr) = common::homing(&args(true));
    assert!(ok, "{stderr}");
    assert!(stdout.contains("| threaded |"), "{stdout}");
    assert_eq!(
        summary("deterministic").unwrap(),
        deterministic,
        "a finished run was run again"
    );
    assert!(
        summary("threaded").is_some(),
        "the unfinished run did not run"
    );
    // Another config: nothing is reused (each run's mark names the config it ran with).
    std::fs::write(&config, "[tracker]\n# changed\n").unwrap();
    let (ok, _, stderr) = common::homing(&args(true));
    assert!(ok, "{stderr}");
    for mode in ["deterministic", "threaded"] {
        let mark = std::fs::read_to_string(out.join(mode).join("bench-done.txt")).unwrap();
        assert!(
            mark.contains("# changed"),
            "{mode} was not run again: {mark}"
        );
    }
    // Monocular (`--mono`): nothing RGB-D is reused, and the report says which it is.
    let mut mono = args(true);
    mono.push("--mono");
    let (ok, stdout, stderr) = common::homing(&mono);
    assert!(ok, "{stderr}");
    assert!(stdout.contains("(monocular)"), "{stdout}");
    for mode in ["deterministic", "threaded"] {
        let mark = std::fs::read_to_string(out.join(mode).join("bench-done.txt")).unwrap();
        assert!(
            mark.contains("mono true"),
            "{mode} was not run again: {mark}"
        );
        let run: serde_json::Value = serde_json::from_slice(&summary(mode).unwrap()).unwrap();
        assert_eq!(
            run.pointer("/perturbations/spec/mono"),
            Some(&serde_json::Value::Bool(true)),
            "{mode} ran with depth"
        );
    }
}

/// The benchmark as a plan (issue #52): `--plan-only` writes one command a line, two separate
/// shell processes each run half of the lines (as two job-array tasks would), and `--collect`
/// gives the robustness.csv of the single-process benchmark, row for row (the run times
/// aside, and the output folder in the recorded commands). Before the second half has run,
/// `--collect` fails and names the lines not finished, in a list `sbatch --array` takes.
#[test]
fn a_plan_run_by_two_processes_collects_the_single_process_rows() {
    let tmp = tempfile::tempdir().unwrap();
    let seq = tmp.path().join("desk");
    generate_desk(&seq, 72);
    let grid = |out: &Path| quick_grid_args(&seq, 2, out);

    let single = tmp.path().join("single");
    let (ok, _, stderr) = common::homing(&grid(&single));
    assert!(ok, "{stderr}");

    let plan = tmp.path().join("plan");
    let mut args = grid(&plan);
    args.push("--plan-only".into());
    let (ok, stdout, stderr) = common::homing(&args);
    assert!(ok, "{stderr}");
    assert!(stdout.contains("4 jobs"), "{stdout}");
    assert!(
        !plan.join("robustness.csv").exists(),
        "--plan-only ran something"
    );
    let jobs = std::fs::read_to_string(plan.join("jobs.txt")).unwrap();
    let lines: Vec<&str> = jobs.lines().collect();
    assert_eq!(lines.len(), 4, "{jobs}");
    assert!(
        lines.iter().all(|l| l.contains(" run --sequence ")),
        "{jobs}"
    );
    let half = |part: &[&str]| {
        let script = part.join("\n");
        let status = std::process::Command::new("bash")
            .args(["-c", &script])
            .env("RUST_LOG", "warn")
            .stdout(std::process::Stdio::null())
            .status()
            .unwrap();
        assert!(status.success(), "{script}");
    };
    half(&lines[..2]);
    let collect = ["bench", "robustness", "--collect", plan.to_str().unwrap()];
    let (ok, _, stderr) = common::homing(&collect);
    assert!(!ok, "collected with half of the lines not run");
    assert!(stderr.contains("--array=3-4"), "{stderr}");
    let unfinished = std::fs::read_to_string(plan.join("unfinished.txt")).unwrap();
    assert_eq!(
        unfinished.lines().map(|l| &l[..2]).collect::<Vec<_>>(),
        ["3\t", "4\t"],
        "{unfinished}"
    );
    half(&lines[2..]);
    let (ok, _, stderr) = common::homing(&collect);
    assert!(ok, "{stderr}");
    assert_eq!(
        std::fs::read_to_string(plan.join("unfinished.txt")).unwrap(),
        ""
    );
    assert!(
        !plan.join("decoded-frames").exists(),
        "prepared inputs kept after every line finished"
    );

    // Row for row, but for the run times and the output folder in the commands.
    let rows = |out: &Path| {
        let csv = std::fs::read_to_string(out.join("robustness.csv")).unwrap();
        let mut lines = csv.lines();
        let header = csv_split(lines.next().unwrap());
        let timing: Vec<usize> = ["wall_s", "fps"]
            .iter()
            .map(|c| header.iter().position(|h| h == c).unwrap())
            .collect();
        lines
            .map(|l| {
                let mut r = csv_split(&l.replace(out.to_str().unwrap(), "OUT"));
                for &i in &timing {
                    r[i].clear();
                }
                r
            })
            .collect::<Vec<_>>()
    };
    let (a, b) = (rows(&single), rows(&plan));
    assert_eq!(a.len(), 4);
    assert_eq!(a, b);
}
