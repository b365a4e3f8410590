//! Decoded frames (`homing run --decoded-frames`): a run reading them computes what it
//! computes from the images, and a file that does not belong to the sequence, or is cut
//! short, is a clear error naming it.

mod common;

use homing::io::decoded;
use homing::io::tum::{FrameSource, TumSequence};
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
    let mut args = vec![
        "run",
        "--sequence",
        seq.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    if let Some(d) = decoded {
        args.extend(["--decoded-frames", d.to_str().unwrap()]);
    }
    let (ok, _, stderr) = common::homing(&args);
    (ok, stderr)
}

#[test]
fn a_run_on_decoded_frames_equals_the_run_on_the_images() {
    use homing_datasets::{scenarios, sensor::SensorOptions, writer};
    let tmp = tempfile::tempdir().unwrap();
    let seq = tmp.path().join("desk");
    writer::generate(
        &scenarios::build("desk", 1).unwrap(),
        &writer::GenOptions {
            out: seq.clone(),
            small: true,
            seed: 1,
            sensor: SensorOptions::realistic(),
            max_frames: Some(40),
        },
    )
    .unwrap();
    let file = tmp.path().join("desk.frames");
    write_decoded(&seq, &file, (320, 240));
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    let (ok, stderr) = run(&seq, &a, None);
    assert!(ok, "{stderr}");
    let (ok, stderr) = run(&seq, &b, Some(&file));
    assert!(ok, "{stderr}");
    for f in ["trajectory.txt", "states.csv", "keyframes.txt"] {
        let (x, y) = (
            std::fs::read(a.join(f)).unwrap(),
            std::fs::read(b.join(f)).unwrap(),
        );
        assert!(x == y, "{f} differs");
    }
    let poses = std::fs::read_to_string(b.join("trajectory.txt")).unwrap();
    let n = poses.lines().filter(|l| !l.starts_with('#')).count();
    assert!(n >= 30, "only {n} poses: the comparison would prove little");
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
