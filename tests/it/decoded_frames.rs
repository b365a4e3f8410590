//! Decoded frames (`homing run --decoded-frames`) and extracted features (`--features`): a
//! run reading them computes what it computes from the images, and a file that does not
//! belong to the sequence (or to the run's settings), or is cut short, is a clear error
//! naming it.

use crate::common;

use homing::io::tum::{FrameSource, TumSequence};
use homing::io::{decoded, features};
use std::path::{Path, PathBuf};

/// A sequence's frames written as decoded frames to `path` (the sequence `w`×`h`).
fn write_decoded(seq: &Path, path: &Path, (w, h): (u32, u32)) {
    let s = TumSequence::open(seq, w, h, 5000.0, 0.02, false).unwrap();
    decoded::write(path, &s, 2).unwrap();
    let d = decoded::DecodedFrames::open(path, &s, w, h, true).unwrap();
    assert_eq!(d.len(), s.len());
    for i in [0, s.len() - 1] {
        assert_eq!(d.load(i).unwrap(), s.load(i).unwrap(), "frame {i}");
    }
}

fn run(seq: &Path, out: &Path, decoded: Option<&Path>) -> (bool, String) {
    run_with(
        seq,
        out,
        decoded
            .map(|d| ["--decoded-frames", d.to_str().unwrap()])
            .as_slice(),
    )
}

fn run_with(seq: &Path, out: &Path, extra: &[[&str; 2]]) -> (bool, String) {
    let mut args = vec![
        "run",
        "--sequence",
        seq.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend(extra.iter().flatten());
    let (ok, _, stderr) = common::homing(&args);
    (ok, stderr)
}

/// A sequence's features, extracted as a run with default settings does, written to `path`.
fn write_features(seq: &Path, path: &Path) {
    let (s, camera, orb) = homing::system::open_run_front_end(seq, None, false).unwrap();
    features::write(path, &s, &camera, &orb, 2).unwrap();
}

#[test]
fn a_run_on_decoded_frames_equals_the_run_on_the_images() {
    let tmp = tempfile::tempdir().unwrap();
    let seq = common::generated_desk(tmp.path(), 40);
    let file = tmp.path().join("desk.frames");
    write_decoded(&seq, &file, (320, 240));
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    let (ok, stderr) = run(&seq, &a, None);
    assert!(ok, "{stderr}");
    let (ok, stderr) = run(&seq, &b, Some(&file));
    assert!(ok, "{stderr}");
    common::same_outputs(&a, &b, 30);
}

/// With false frames (extracted by the run itself) and without depth (the file's depth
/// cleared) too: the features file changes nothing but the work done.
#[test]
fn a_run_on_extracted_features_equals_the_run_on_the_images() {
    let tmp = tempfile::tempdir().unwrap();
    let seq = common::generated_desk(tmp.path(), 40);
    let file = tmp.path().join("desk.features");
    write_features(&seq, &file);
    let with = ["--features", file.to_str().unwrap()];
    for (name, extra) in [
        ("plain", vec![]),
        (
            "faults",
            vec![
                ["--fault", "noise@5,6"],
                ["--fault", "black@20"],
                ["--fault", "foreign@35"],
            ],
        ),
        ("mono", vec![["--mono", "--eval"]]),
    ] {
        let (a, b) = (tmp.path().join(format!("{name}-a")), tmp.path().join(name));
        let (ok, stderr) = run_with(&seq, &a, &extra);
        assert!(ok, "{name}: {stderr}");
        let mut extra = extra.clone();
        extra.push(with);
        let (ok, stderr) = run_with(&seq, &b, &extra);
        assert!(ok, "{name}: {stderr}");
        // Monocular initialisation takes a few frames more.
        common::same_outputs(&a, &b, 20);
        // The file's extraction time is counted as the run's.
        let s: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(b.join("summary.json")).unwrap())
                .unwrap();
        let reused = s["extraction_reused_s"].as_f64().unwrap();
        assert!(reused > 0.0, "{name}: no frame taken from the file");
        assert!(s["wall_time_s"].as_f64().unwrap() > reused, "{name}");
    }
}

#[test]
fn features_of_another_sequence_other_settings_or_cut_short_are_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let seq = common::tum_folder(tmp.path(), "seq", 12);
    let shorter = common::tum_folder(tmp.path(), "shorter", 8);
    let file = tmp.path().join("shorter.features");
    write_features(&shorter, &file);
    let out = tmp.path().join("out");
    fn with(f: &Path) -> [[&str; 2]; 1] {
        [["--features", f.to_str().unwrap()]]
    }
    // Another sequence: its frame count differs.
    let (ok, stderr) = run_with(&seq, &out, &with(&file));
    common::assert_clear_error(ok, &stderr, "shorter.features");
    assert!(stderr.contains("8 frames"), "{stderr}");
    // Other ORB settings than the run's.
    let cfg = tmp.path().join("orb.toml");
    std::fs::write(&cfg, "[orb]\nn_features = 500\n").unwrap();
    let mut extra = with(&file).to_vec();
    extra.push(["--config", cfg.to_str().unwrap()]);
    let (ok, stderr) = run_with(&shorter, &out, &extra);
    common::assert_clear_error(ok, &stderr, "shorter.features");
    assert!(stderr.contains("ORB settings"), "{stderr}");
    // Cut short.
    let bytes = std::fs::read(&file).unwrap();
    let cut = tmp.path().join("cut.features");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let (ok, stderr) = run_with(&shorter, &out, &with(&cut));
    common::assert_clear_error(ok, &stderr, "cut.features");
    assert!(stderr.contains("truncated or corrupt"), "{stderr}");
    // Not a features file at all, and a missing one.
    let txt = shorter.join("rgb.txt");
    let (ok, stderr) = run_with(&shorter, &out, &with(&txt));
    common::assert_clear_error(ok, &stderr, "rgb.txt");
    let none = tmp.path().join("none.features");
    let (ok, stderr) = run_with(&shorter, &out, &with(&none));
    common::assert_clear_error(ok, &stderr, "none.features");
}

#[test]
fn decoded_frames_of_another_sequence_or_cut_short_are_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let seq = common::tum_folder(tmp.path(), "seq", 12);
    let shorter = common::tum_folder(tmp.path(), "shorter", 8);
    let file: PathBuf = tmp.path().join("shorter.frames");
    write_decoded(&shorter, &file, (common::W, common::H));
    let out = tmp.path().join("out");
    // Another sequence: its frame count differs.
    let (ok, stderr) = run(&seq, &out, Some(&file));
    common::assert_clear_error(ok, &stderr, "shorter.frames");
    assert!(stderr.contains("8 frames"), "{stderr}");
    // Cut short: the records do not add up.
    let bytes = std::fs::read(&file).unwrap();
    let cut = tmp.path().join("cut.frames");
    std::fs::write(&cut, &bytes[..bytes.len() - 100]).unwrap();
    let (ok, stderr) = run(&shorter, &out, Some(&cut));
    common::assert_clear_error(ok, &stderr, "cut.frames");
    assert!(stderr.contains("truncated"), "{stderr}");
    // Not a decoded-frames file at all, and a missing one.
    let png = shorter.join("rgb.txt");
    let (ok, stderr) = run(&shorter, &out, Some(&png));
    common::assert_clear_error(ok, &stderr, "rgb.txt");
    let (ok, stderr) = run(&shorter, &out, Some(&tmp.path().join("none.frames")));
    common::assert_clear_error(ok, &stderr, "none.frames");
}
