//! The run-output contract and perturbations, end to end through `homing run`.

use crate::common;
use common::{homing, tum_folder};
use serde_json::Value;
use std::fs;

#[test]
fn run_writes_the_contract_and_records_perturbations() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tum_folder(tmp.path(), "seq", 120);
    let out = tmp.path().join("out");
    let (ok, stdout, err) = homing(&[
        "run",
        "--sequence",
        dir.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--drop",
        "10:20",
        "--drop",
        "2.0:2.5",
        "--fault",
        "black@5,6",
        "--fault",
        "foreign@30",
        "--fault-rate",
        "noise:0.1",
        "--seed",
        "3",
        "--eval",
    ]);
    assert!(ok, "{err}");
    assert!(stdout.contains("frames delivered"), "{stdout}");
    for f in [
        "trajectory.txt",
        "keyframes.txt",
        "states.csv",
        "closures.csv",
        "summary.json",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let s: Value =
        serde_json::from_str(&fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(s["sequence_frames"], 120);
    // 10 frames by index, 2.0 s..2.5 s at 30 Hz = frames 60..75.
    assert_eq!(
        s["perturbations"]["dropped"],
        serde_json::json!([[10, 20], [60, 75]])
    );
    assert_eq!(s["frames"], 120 - 25);
    let faults = s["perturbations"]["faults"].as_array().unwrap();
    assert!(
        faults
            .iter()
            .any(|f| f["frame"] == 5 && f["kind"] == "black")
    );
    assert!(
        faults
            .iter()
            .any(|f| f["frame"] == 30 && f["kind"] == "foreign" && f["source"].is_number())
    );
    assert!(faults.iter().any(|f| f["kind"] == "noise"));
    for key in [
        "frames_with_pose",
        "keyframes",
        "maps",
        "closures_accepted",
        "closures_rejected",
        "final_state",
        "config",
        "timing",
        "wall_time_s",
    ] {
        assert!(!s[key].is_null(), "summary lacks {key}");
    }
    assert_eq!(s["final_state"], "Final");
    assert!(s["timing"]["load"]["median_ms"].as_f64().unwrap() > 0.0);
    // states.csv: a row per delivered frame plus the transition to Final.
    let states = fs::read_to_string(out.join("states.csv")).unwrap();
    let rows: Vec<&str> = states.lines().skip(1).collect();
    assert_eq!(rows.len(), 95 + 1);
    assert!(rows[0].starts_with("0,1000.000000,Init,(start),start"));
    assert!(
        !states
            .lines()
            .any(|l| l.starts_with("10,") || l.starts_with("60,")),
        "dropped frames appear"
    );
    assert!(rows.last().unwrap().contains(",Final,Init,end_of_data,"));
}

#[test]
fn same_input_same_output() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tum_folder(tmp.path(), "seq", 30);
    let mut outputs = Vec::new();
    for k in 0..2 {
        let out = tmp.path().join(format!("out{k}"));
        let (ok, _, err) = homing(&[
            "run",
            "--sequence",
            dir.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--fault-rate",
            "black:0.2",
            "--seed",
            "9",
        ]);
        assert!(ok, "{err}");
        outputs.push(
            [
                "trajectory.txt",
                "states.csv",
                "keyframes.txt",
                "closures.csv",
            ]
            .map(|f| fs::read(out.join(f)).unwrap()),
        );
    }
    assert_eq!(outputs[0], outputs[1]);
}

#[test]
fn mono_suppresses_depth_and_folder_name_picks_camera() {
    use homing::io::perturb::{PerturbationSpec, PerturbedSequence};
    use homing::io::tum::{FrameSource, TumSequence};
    let tmp = tempfile::tempdir().unwrap();
    let dir = tum_folder(tmp.path(), "seq", 4);
    let seq = TumSequence::open(&dir, common::W, common::H, 5000.0, 0.02, false).unwrap();
    let frames: Vec<_> = PerturbedSequence::new(
        &seq,
        &PerturbationSpec {
            mono: true,
            ..Default::default()
        },
    )
    .unwrap()
    .frames()
    .collect::<Result<_, _>>()
    .unwrap();
    assert_eq!(frames.len(), 4);
    assert!(frames.iter().all(|f| f.depth.is_none()));
    let with_depth = seq.load(0).unwrap();
    assert!((with_depth.depth.unwrap().get(3, 3) - 1.5).abs() < 1e-6);
    // A folder named like a TUM sequence gets the built-in camera, and says so.
    let cfg = homing::config::Config::default();
    let named = tmp.path().join("rgbd_dataset_freiburg2_desk");
    fs::create_dir(&named).unwrap();
    let (cam, src) = homing::config::resolve_camera(&cfg, None, &named).unwrap();
    assert_eq!(cam.depth_scale, 5208.0);
    assert!(src.to_string().contains("freiburg2"));
}

#[test]
fn frozen_and_black_faults_replace_images() {
    use homing::io::perturb::{PerturbationSpec, PerturbedSequence};
    use homing::io::tum::{FrameSource, TumSequence};
    let tmp = tempfile::tempdir().unwrap();
    let dir = tum_folder(tmp.path(), "seq", 6);
    let seq = TumSequence::open(&dir, common::W, common::H, 5000.0, 0.02, false).unwrap();
    let spec = PerturbationSpec {
        faults: vec!["frozen@3".parse().unwrap(), "black@4".parse().unwrap()],
        ..Default::default()
    };
    let frames: Vec<_> = PerturbedSequence::new(&seq, &spec)
        .unwrap()
        .frames()
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(frames[3].rgb, frames[2].rgb);
    assert_eq!(frames[3].t, seq.timestamp(3));
    assert!(frames[4].rgb.pixels().all(|p| p.0 == [0, 0, 0]));
    assert!(
        frames[4]
            .depth
            .as_ref()
            .unwrap()
            .data
            .iter()
            .all(|&d| d == 0.0)
    );
    assert_eq!(frames[5].rgb, seq.load(5).unwrap().rgb);
}

/// `homing bench memory` plays a sequence again with shifted stamps (one child run per play
/// count) and reports each run's peak memory from its summary.json.
#[test]
fn bench_memory_plays_the_sequence_again_and_reports_peak_memory() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tum_folder(tmp.path(), "seq", 20);
    let out = tmp.path().join("bench");
    let (ok, stdout, err) = homing(&[
        "bench",
        "memory",
        "--sequence",
        dir.to_str().unwrap(),
        "--repeats",
        "1,3",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    assert!(stdout.contains("| 3× | 60 |"), "{stdout}");
    let rows: Value =
        serde_json::from_str(&fs::read_to_string(out.join("memory.json")).unwrap()).unwrap();
    let rows = rows.as_array().unwrap();
    assert_eq!(rows.len(), 2);
    assert_eq!(rows[1]["frames"], 60);
    for r in rows {
        assert!(r["peak_rss_mb"].as_f64().unwrap() > 1.0, "{r}");
    }
    // The stamps of the second play follow the first's.
    let list = fs::read_to_string(out.join("sequence-x3/associations.txt")).unwrap();
    let stamps: Vec<f64> = list
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split_whitespace().next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(stamps.len(), 60);
    assert!(stamps.windows(2).all(|w| w[1] > w[0]));
}
