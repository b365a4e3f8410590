//! The Interruptible state's user stop: SIGINT / SIGTERM end a run in Final with every output
//! written (`homing::interrupt`).

use crate::common;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};

/// Runs `homing run ARGS` and sends `signals` (kill names, in order) once its log reports frame
/// 100; returns (exit code, log).
fn run_and_signal(args: &[&str], signals: &[&str]) -> (Option<i32>, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_homing"))
        .arg("run")
        .args(args)
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut log = String::new();
    let mut sent = false;
    for line in BufReader::new(child.stderr.take().unwrap()).lines() {
        let line = line.unwrap();
        if !sent && line.contains("frame 100/") {
            for s in signals {
                let ok = Command::new("kill")
                    .args([&format!("-{s}"), &child.id().to_string()])
                    .status()
                    .unwrap()
                    .success();
                assert!(ok, "kill -{s} failed");
            }
            sent = true;
        }
        log.push_str(&line);
        log.push('\n');
    }
    let code = child.wait().unwrap().code();
    assert!(sent, "the run never reached frame 100: {log}");
    (code, log)
}

fn summary(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap()
}

/// Asserts the outputs of a run stopped by the user: states.csv ends in Final by `user_stop`,
/// summary.json says where, the trajectory holds every posed frame. Returns summary.json.
fn assert_stopped(out: &Path, code: Option<i32>, log: &str) -> serde_json::Value {
    assert_eq!(code, Some(homing::interrupt::EXIT_STATUS), "{log}");
    let states = std::fs::read_to_string(out.join("states.csv")).unwrap();
    let last = states.lines().last().unwrap();
    assert!(
        last.contains(",Final,") && last.contains(",user_stop,"),
        "states.csv ends with {last}"
    );
    let s = summary(out);
    let stop = &s["user_stop"];
    let frame = stop["frame"].as_u64().unwrap();
    assert!(frame >= 99, "{stop}");
    assert!(stop["frames_not_processed"].as_u64().unwrap() > 0, "{stop}");
    let posed = s["frames_with_pose"].as_u64().unwrap();
    assert!(posed >= 50, "{posed} frames posed");
    let trajectory = std::fs::read_to_string(out.join("trajectory.txt")).unwrap();
    let rows = trajectory
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .count();
    assert_eq!(rows as u64, posed);
    for f in ["keyframes.txt", "closures.csv", "timing.csv"] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    s
}

/// Ctrl-C part-way through small `revisit`: the current frame finishes, Final refines, and
/// every output is written, the atlas too. That atlas loads back in a second session, which
/// SIGTERM and then SIGINT stop: the second signal skips the refinement, and what was posed is
/// still written.
#[test]
fn a_run_stopped_by_signals_writes_every_output_and_its_atlas_loads_back() {
    let seq = common::small("revisit");
    let tmp = tempfile::tempdir().unwrap();
    let (out, atlas) = (tmp.path().join("first"), tmp.path().join("first.atlas"));
    let args = |o: &Path| {
        vec![
            "--sequence".to_string(),
            seq.display().to_string(),
            "--out".into(),
            o.display().to_string(),
        ]
    };
    let mut first = args(&out);
    first.extend(["--save-map".into(), atlas.display().to_string()]);
    let first: Vec<&str> = first.iter().map(String::as_str).collect();
    let (code, log) = run_and_signal(&first, &["INT"]);
    let s = assert_stopped(&out, code, &log);
    assert_eq!(s["user_stop"]["refinement"], "complete", "{s}");
    assert!(atlas.exists(), "no atlas saved: {log}");

    let second_out = tmp.path().join("second");
    let mut second = args(&second_out);
    second.extend(["--load-map".into(), atlas.display().to_string()]);
    let second: Vec<&str> = second.iter().map(String::as_str).collect();
    let (code, log) = run_and_signal(&second, &["TERM", "INT"]);
    assert!(log.contains("loaded atlas"), "{log}");
    let s = assert_stopped(&second_out, code, &log);
    let refinement = s["user_stop"]["refinement"].as_str().unwrap();
    assert!(
        refinement.starts_with("skipped by a second stop signal"),
        "{refinement}"
    );
}
