//! End to end: RGB-D SLAM on the synthetic `desk` scenario (small, realistic sensor noise).
//! The accuracy target of the full-size sequence (ATE ≤ 0.5 cm) is measured by the benchmark
//! commands in the README; this test guards against regressions at test-suite cost.

use crate::common;

use homing::system::{RunOptions, run};
use homing_datasets::scenarios;
use homing_datasets::sensor::SensorOptions;
use homing_datasets::writer::GenOptions;

#[test]
fn desk_small_tracks_every_frame() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("run");
    let summary = run(&RunOptions {
        sequence: common::small("desk"),
        out: out.clone(),
        eval: true,
        ..Default::default()
    })
    .unwrap();
    assert_eq!(summary.frames, summary.sequence_frames);
    assert_eq!(summary.frames_with_pose, summary.frames, "a frame was lost");
    assert!(summary.keyframes >= 3, "{} keyframes", summary.keyframes);
    let ev = summary.evaluation.unwrap();
    let ate = ev["ate"]["stats"]["rmse"].as_f64().unwrap();
    assert!(ate < 0.03, "ATE {ate} m");
    assert_eq!(ev["coverage"].as_f64().unwrap(), 1.0);
    // The state timeline: Init, Idle, then Mapping — and Localized where the camera comes
    // back to what it mapped more than a few seconds before — never lost, never corrupted,
    // then Final.
    let states = std::fs::read_to_string(out.join("states.csv")).unwrap();
    let rows: Vec<&str> = states.lines().skip(1).collect();
    assert!(rows[0].contains(",Idle,Init,initialized,"), "{}", rows[0]);
    assert!(
        rows[1].contains(",Mapping,Idle,able_to_track,"),
        "{}",
        rows[1]
    );
    for r in &rows[2..rows.len() - 1] {
        assert!(
            r.contains(",Mapping,,,")
                || r.contains(",Localized,,,")
                || r.contains(",Localized,Mapping,able_to_localize,")
                || r.contains(",Mapping,Localized,left_known_area,"),
            "{r}"
        );
    }
    let last = rows.last().unwrap();
    assert!(
        last.contains(",Final,Mapping,end_of_data,")
            || last.contains(",Final,Localized,end_of_data,"),
        "{last}"
    );
}

#[test]
fn two_runs_are_byte_identical() {
    let tmp = tempfile::tempdir().unwrap();
    let sc = scenarios::build("desk", 3).unwrap();
    let opts = GenOptions {
        out: tmp.path().join("desk"),
        small: true,
        seed: 3,
        sensor: SensorOptions::realistic(),
        max_frames: Some(60),
    };
    common::generate(&sc, &opts);
    let mut outputs = Vec::new();
    for k in 0..2 {
        let out = tmp.path().join(format!("run{k}"));
        let s = run(&RunOptions {
            sequence: tmp.path().join("desk"),
            out: out.clone(),
            ..Default::default()
        })
        .unwrap();
        assert!(
            s.frames_with_pose > 50 && s.keyframes >= 2,
            "{} poses, {} keyframes",
            s.frames_with_pose,
            s.keyframes
        );
        outputs.push(
            [
                "trajectory.txt",
                "keyframes.txt",
                "states.csv",
                "closures.csv",
            ]
            .map(|f| std::fs::read(out.join(f)).unwrap()),
        );
    }
    assert!(
        outputs[0] == outputs[1],
        "two runs on the same input differ"
    );
    // Threaded mode (local BA on its own thread) runs the same code: same frames tracked,
    // close to the deterministic trajectory, but not required to be bit-identical.
    let s = run(&RunOptions {
        sequence: tmp.path().join("desk"),
        out: tmp.path().join("threaded"),
        eval: true,
        threaded: true,
        ..Default::default()
    })
    .unwrap();
    assert_eq!(s.mode, "threaded");
    assert_eq!(s.frames_with_pose, s.frames, "threaded mode lost a frame");
    assert!(
        s.timing.contains_key("local_ba_thread"),
        "BA never ran on the thread"
    );
    let ate = s.evaluation.unwrap()["ate"]["stats"]["rmse"]
        .as_f64()
        .unwrap();
    assert!(ate < 0.03, "threaded ATE {ate} m");
}

/// A map started from a false frame (an image from elsewhere in the sequence) and lost on the
/// next, real, frame is discarded: no other frame confirmed it, and left in the atlas it would
/// anchor closures that put the camera where that image was taken. With 8 % foreign frames
/// (seed 5) on the small desk, frame 62 shows frame 137's view after frame 61 failed to track;
/// the map started from it is gone, its keyframe and its frame's pose with it.
#[test]
fn a_map_started_from_a_false_frame_is_discarded() {
    use homing::io::perturb::{FaultKind, FaultRate, PerturbationSpec};
    let run = common::run_small(
        "desk",
        PerturbationSpec {
            fault_rates: vec![FaultRate {
                kind: FaultKind::Foreign,
                p: 0.08,
            }],
            seed: 5,
            ..Default::default()
        },
    );
    let (seq, out, s) = (&run.seq, &run.out, &run.summary);
    let faults = serde_json::to_value(&s.perturbations).unwrap()["faults"].clone();
    let source_of = |frame: u64| {
        faults
            .as_array()
            .unwrap()
            .iter()
            .find(|f| f["frame"] == frame)
            .map(|f| f["source"].as_u64().unwrap())
    };
    assert_eq!(source_of(61), Some(15), "the fault draw changed: {faults}");
    assert_eq!(source_of(62), Some(137), "the fault draw changed: {faults}");
    let stamp62 = stamps(seq)[62].clone();
    for f in ["keyframes.txt", "trajectory.txt"] {
        let text = std::fs::read_to_string(out.join(f)).unwrap();
        assert!(
            !text.lines().any(|l| l.starts_with(&stamp62)),
            "{f} keeps frame 62 ({stamp62}), whose map only that false frame ever saw"
        );
    }
    assert_eq!(s.maps, 1, "{} maps", s.maps);
    // The closures are judged by where their images were taken: a keyframe made from a
    // tracked foreign frame shows its source frame's view, and a closure to it is right when
    // it places the camera there (judged by the delivered stamp, this run had 2 "wrong").
    let closures = &s.evaluation.as_ref().unwrap()["closures"];
    assert!(closures["accepted"].as_u64().unwrap() >= 3, "{closures}");
    assert_eq!(closures["accepted_wrong"], 0, "{closures}");
}

/// An isolated foreign frame (small desk, frame 60 replaced by frame 119's images) that the
/// map can explain is still refused: its tracked pose lands far off the constant-velocity
/// prediction. It gets no pose, and the next frame is tracked on in the same map.
#[test]
fn an_isolated_foreign_frame_is_refused_and_tracking_goes_on() {
    use homing::io::perturb::PerturbationSpec;
    let run = common::run_small(
        "desk",
        PerturbationSpec {
            faults: vec!["foreign@60".parse().unwrap()],
            ..Default::default()
        },
    );
    let (seq, out, s) = (&run.seq, &run.out, &run.summary);
    let faults = serde_json::to_value(&s.perturbations).unwrap()["faults"].clone();
    assert_eq!(faults[0]["source"], 119, "the fault draw changed: {faults}");
    let stamps = stamps(seq);
    let trajectory = std::fs::read_to_string(out.join("trajectory.txt")).unwrap();
    let posed = |i: usize| trajectory.lines().any(|l| l.starts_with(&stamps[i]));
    assert!(!posed(60), "the foreign frame 60 has a pose");
    assert!(
        posed(59) && posed(61),
        "a real frame next to it lost its pose"
    );
    assert_eq!(s.maps, 1);
    assert_eq!(s.frames_with_pose, s.frames - 1);
}

/// The same foreign frame right after a recording gap (frame 59 dropped, as real recordings
/// skip frames): the prediction spans two intervals, and the frame is still judged against it
/// and refused. Before, only a frame directly after a tracked one was judged; on fr1_desk such
/// a frame was tracked 32° off, made a keyframe, and cost the next three real frames.
#[test]
fn a_foreign_frame_after_a_skipped_frame_is_refused() {
    use homing::io::perturb::PerturbationSpec;
    let run = common::run_small(
        "desk",
        PerturbationSpec {
            drops: vec!["59:60".parse().unwrap()],
            faults: vec!["foreign@60".parse().unwrap()],
            ..Default::default()
        },
    );
    let (seq, out, s) = (&run.seq, &run.out, &run.summary);
    let p = serde_json::to_value(&s.perturbations).unwrap();
    assert_eq!(p["faults"][0]["source"], 119, "the fault draw changed: {p}");
    assert_eq!(p["dropped_frames"], 1, "{p}");
    let stamps = stamps(seq);
    let trajectory = std::fs::read_to_string(out.join("trajectory.txt")).unwrap();
    let posed = |i: usize| trajectory.lines().any(|l| l.starts_with(&stamps[i]));
    assert!(!posed(59), "the dropped frame 59 has a pose");
    assert!(!posed(60), "the foreign frame 60 has a pose");
    assert!(
        posed(58) && posed(61),
        "a real frame next to it lost its pose"
    );
    assert_eq!(s.maps, 1);
    assert_eq!(s.frames_with_pose, s.frames - 1);
}

/// Final's batch refinement holds tracked frames as cameras, not only keyframes. Full-size
/// `desk` with a 1 s kidnapping at 4.5 s: the local BA of the keyframe made at frame 128,
/// just before the drop, slides it by 2 cm; the camera relocalizes next to it and stays
/// Localized (no keyframes in known space), so with keyframes alone the final BA has nothing
/// to pull it back and the frames after the drop inherit its error (measured: ATE 0.85 cm,
/// 0.32 cm without the drop). The frames tracked there see its points from elsewhere
/// (measured with them: 0.24 cm).
#[test]
fn final_refinement_with_frames_repairs_a_frozen_keyframe() {
    use homing::io::perturb::PerturbationSpec;
    let tmp = tempfile::tempdir().unwrap();
    let seq = tmp.path().join("desk");
    common::synth_full("desk", &seq);
    let run_with = |interval: f64| {
        let config = tmp.path().join(format!("final-{interval}.toml"));
        std::fs::write(
            &config,
            format!("[mapping]\nfinal_ba_frame_interval_s = {interval}\n"),
        )
        .unwrap();
        let s = run(&RunOptions {
            sequence: seq.clone(),
            out: tmp.path().join(format!("run-{interval}")),
            config: Some(config),
            perturb: PerturbationSpec {
                drops: vec!["4.5s:5.5s".parse().unwrap()],
                ..Default::default()
            },
            eval: true,
            ..Default::default()
        })
        .unwrap();
        let ev = s.evaluation.unwrap();
        (
            ev["ate"]["stats"]["rmse"].as_f64().unwrap(),
            s.frames_with_pose,
            s.maps,
        )
    };
    let (keyframes_only, posed_k, maps_k) = run_with(0.0);
    let (with_frames, posed_f, maps_f) = run_with(0.2);
    assert_eq!(
        (posed_f, maps_f),
        (posed_k, maps_k),
        "the refinement changed what is posed"
    );
    assert!(
        with_frames < 0.004 && with_frames < 0.5 * keyframes_only,
        "ATE {with_frames} m with frames, {keyframes_only} m with keyframes only"
    );
}

/// The image stamps of a TUM folder, as written (for finding a frame in the run's outputs).
fn stamps(seq: &std::path::Path) -> Vec<String> {
    std::fs::read_to_string(seq.join("rgb.txt"))
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split_whitespace().next().unwrap().to_string())
        .collect()
}
