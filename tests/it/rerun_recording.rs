//! `homing run --rerun FILE.rrd`: with the `rerun` feature the recording is read back with the
//! rerun crate's own decoder and holds every entity the visualiser promises; without it, asking
//! for rerun is a clear error. CI runs this file once with `--features rerun`.

use crate::common;
use homing::io::perturb::PerturbationSpec;
use homing::outputs::viz::RerunTarget;
use homing::system::{RunOptions, run};
use homing_datasets::scenarios;
use homing_datasets::sensor::SensorOptions;
use homing_datasets::writer::GenOptions;
use std::path::Path;

/// 80 small desk frames with a kidnapping (frames 30–44 dropped), so there are two maps.
fn sequence(dir: &Path) {
    let sc = scenarios::build("desk", 1).unwrap();
    common::generate(
        &sc,
        &GenOptions {
            out: dir.to_path_buf(),
            small: true,
            seed: 1,
            sensor: SensorOptions::realistic(),
            max_frames: Some(80),
        },
    );
}

fn options(seq: &Path, out: &Path, rrd: &Path) -> RunOptions {
    RunOptions {
        sequence: seq.to_path_buf(),
        out: out.to_path_buf(),
        rerun: Some(RerunTarget::File(rrd.to_path_buf())),
        perturb: PerturbationSpec {
            drops: vec!["30:45".parse().unwrap()],
            ..Default::default()
        },
        ..Default::default()
    }
}

#[cfg(not(feature = "rerun"))]
#[test]
fn without_the_feature_rerun_is_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let seq = tmp.path().join("desk");
    sequence(&seq);
    let rrd = tmp.path().join("run.rrd");
    let e = run(&options(&seq, &tmp.path().join("out"), &rrd))
        .unwrap_err()
        .to_string();
    assert!(e.contains("--features rerun"), "{e}");
    assert!(!rrd.exists());
}

#[cfg(feature = "rerun")]
#[test]
fn recording_reads_back_with_every_entity() {
    use rerun::external::re_log_encoding::DecoderApp;
    use rerun::log::{Chunk, LogMsg};
    use std::collections::BTreeMap;

    let tmp = tempfile::tempdir().unwrap();
    let seq = tmp.path().join("desk");
    sequence(&seq);
    let out = tmp.path().join("out");
    let rrd = out.join("run.rrd");
    let summary = run(&options(&seq, &out, &rrd)).unwrap();
    assert!(summary.maps >= 1);
    // The file is complete under its name; no temporary is left.
    let names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(!names.iter().any(|n| n.ends_with(".partial")), "{names:?}");

    // Rows per entity, read back with rerun's decoder.
    let reader = std::io::BufReader::new(std::fs::File::open(&rrd).unwrap());
    let mut rows: BTreeMap<String, usize> = BTreeMap::new();
    let mut timelines = std::collections::BTreeSet::new();
    for msg in DecoderApp::decode_eager(reader).unwrap() {
        if let LogMsg::ArrowMsg(_, arrow) = msg.unwrap() {
            let chunk = Chunk::from_arrow_msg(&arrow).unwrap();
            *rows.entry(chunk.entity_path().to_string()).or_default() += chunk.num_rows();
            timelines.extend(chunk.timelines().keys().map(|t| t.to_string()));
        }
    }
    let n = |e: &str| rows.get(e).copied().unwrap_or(0);
    assert!(
        timelines.contains("frame") && timelines.contains("time"),
        "{timelines:?}"
    );
    // Every delivered frame has its image, keypoints and state number.
    assert_eq!(
        n("/world/camera/image/keypoints"),
        summary.frames,
        "{rows:?}"
    );
    assert_eq!(n("/state/index"), summary.frames, "{rows:?}");
    // Image: the static pinhole plus one image per frame.
    assert_eq!(n("/world/camera/image"), summary.frames + 1, "{rows:?}");
    // A pose for every frame tracked at the time.
    assert!(n("/world/camera") >= summary.frames_with_pose, "{rows:?}");
    // The first map, and a second one after the kidnapping.
    for e in [
        "/world/maps/0/points",
        "/world/maps/0/keyframes",
        "/world/maps/0/trajectory",
        "/world/maps/1/points",
        "/world/maps/1/trajectory",
        "/state",
    ] {
        assert!(n(e) > 0, "{e} missing: {rows:?}");
    }
    assert!(n("/world") > 0, "view coordinates missing: {rows:?}");
}
