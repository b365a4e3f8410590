//! ROS 2 bags in MCAP: a TUM folder converted to a bag runs to the same trajectory as the
//! folder; `--mcap-log` writes run.mcap that the mcap crate reads back; broken bags and wrong
//! topics are clear errors naming the file, never panics.

use crate::common;

use homing::io::mcap::{
    CAMERA_INFO_TOPIC, DEPTH_TOPIC, McapTopics, RGB_TOPIC, pose_from_json, tum_to_mcap,
};
use homing::outputs::mcap_log::{POSE_TOPIC, STATE_TOPIC, STATS_TOPIC, TRANSITION_TOPIC};
use homing::system::{RunOptions, run};
use homing_datasets::scenarios;
use homing_datasets::sensor::SensorOptions;
use homing_datasets::writer::GenOptions;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

fn topics(camera_info: bool) -> McapTopics {
    McapTopics {
        image: RGB_TOPIC.into(),
        depth: DEPTH_TOPIC.into(),
        camera_info: camera_info.then(|| CAMERA_INFO_TOPIC.into()),
    }
}

fn run_bag(bag: &Path, out: &Path, t: McapTopics) -> homing::Result<homing::outputs::Summary> {
    run(&RunOptions {
        mcap: Some((bag.to_path_buf(), t)),
        out: out.to_path_buf(),
        ..Default::default()
    })
}

/// Messages of run.mcap per topic, as JSON, in log-time order.
fn read_log(path: &Path) -> BTreeMap<String, Vec<(u64, serde_json::Value)>> {
    let bytes = std::fs::read(path).unwrap();
    let mut out: BTreeMap<String, Vec<(u64, serde_json::Value)>> = BTreeMap::new();
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        assert_eq!(m.channel.message_encoding, "json");
        let schema = m.channel.schema.as_ref().unwrap();
        assert_eq!(schema.encoding, "jsonschema");
        serde_json::from_slice::<serde_json::Value>(&schema.data).expect("schema is JSON");
        let v: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
        out.entry(m.channel.topic.clone())
            .or_default()
            .push((m.log_time, v));
    }
    out
}

#[test]
fn bag_run_matches_folder_run_and_run_mcap_reads_back() {
    let tmp = tempfile::tempdir().unwrap();
    let sc = scenarios::build("desk", 2).unwrap();
    let seq = tmp.path().join("desk");
    common::generate(
        &sc,
        &GenOptions {
            out: seq.clone(),
            small: true,
            seed: 2,
            sensor: SensorOptions::realistic(),
            max_frames: Some(60),
        },
    );
    let bag = tmp.path().join("desk.mcap");
    let stats = tum_to_mcap(&seq, &bag, false).unwrap();
    assert_eq!((stats.colour, stats.camera_info), (60, 60));
    assert!(stats.groundtruth > 0);

    let from_folder = tmp.path().join("folder");
    let s1 = run(&RunOptions {
        sequence: seq.clone(),
        out: from_folder.clone(),
        mcap_log: true,
        ..Default::default()
    })
    .unwrap();
    assert!(s1.frames_with_pose > 50, "{}", s1.frames_with_pose);
    for (name, with_info) in [("bag", true), ("bag-noinfo", false)] {
        let from_bag = tmp.path().join(name);
        let s2 = run(&RunOptions {
            mcap: Some((bag.clone(), topics(with_info))),
            out: from_bag.clone(),
            mcap_log: true,
            eval: true,
            ..Default::default()
        })
        .unwrap();
        assert_eq!(s2.frames, s1.frames);
        let a = std::fs::read(from_folder.join("trajectory.txt")).unwrap();
        let b = std::fs::read(from_bag.join("trajectory.txt")).unwrap();
        assert!(a == b, "{name}: trajectories differ");
        let a = std::fs::read(from_folder.join("run.mcap")).unwrap();
        let b = std::fs::read(from_bag.join("run.mcap")).unwrap();
        assert!(a == b, "{name}: run.mcap differs");
        // The bag's /groundtruth serves --eval.
        assert!(s2.evaluation.unwrap()["ate"]["stats"]["rmse"].is_number());
    }

    // run.mcap read back with the mcap crate.
    let log = read_log(&from_folder.join("run.mcap"));
    for t in [POSE_TOPIC, STATE_TOPIC, STATS_TOPIC, TRANSITION_TOPIC] {
        assert!(log.contains_key(t), "{t} missing: {:?}", log.keys());
    }
    let traj = homing::io::tum::read_trajectory(&from_folder.join("trajectory.txt")).unwrap();
    let poses = &log[POSE_TOPIC];
    assert_eq!(poses.len(), traj.len(), "one pose message per posed frame");
    for ((ns, v), p) in poses.iter().zip(&traj) {
        let q = pose_from_json(v).unwrap();
        assert_eq!(*ns, homing::io::mcap::seconds_to_ns(p.t));
        assert!((q.t - p.t).abs() < 1e-9);
        assert!((q.pose.translation.vector - p.pose.translation.vector).norm() < 1e-6);
        assert!(v["map"].is_u64() && v["frame"].is_u64());
    }
    assert_eq!(log[STATE_TOPIC].len(), s1.frames);
    assert_eq!(log[STATS_TOPIC].len(), s1.frames);
    let tracked = log[STATS_TOPIC]
        .iter()
        .filter(|(_, v)| v["tracked_inliers"].as_u64().is_some_and(|n| n > 20))
        .count();
    assert!(tracked > 50, "{tracked} frames with tracked inliers");
    let states = homing::outputs::read_states(&from_folder.join("states.csv")).unwrap();
    let expected: Vec<(usize, String, String)> = states
        .iter()
        .filter_map(|r| Some((r.frame, r.from.clone()?, r.state.clone())))
        .collect();
    let got: Vec<(usize, String, String)> = log[TRANSITION_TOPIC]
        .iter()
        .map(|(_, v)| {
            assert!(v["trigger"].is_string() && v["guards"]["able_to_track"].is_boolean());
            (
                v["frame"].as_u64().unwrap() as usize,
                v["from"].as_str().unwrap().to_string(),
                v["to"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    assert_eq!(got, expected);
    assert!(got.iter().any(|t| t.2 == "Final"));
}

fn tiny_bag(tmp: &Path) -> PathBuf {
    let dir = common::tum_folder(tmp, "tiny", 5);
    let bag = tmp.join("tiny.mcap");
    tum_to_mcap(&dir, &bag, false).unwrap();
    bag
}

fn err_of(r: homing::Result<homing::outputs::Summary>) -> String {
    r.expect_err("an error").to_string()
}

#[test]
fn broken_bags_are_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let bag = tiny_bag(tmp.path());
    let out = tmp.path().join("out");
    let bytes = std::fs::read(&bag).unwrap();
    let name = bag.display().to_string();

    // Truncated at several places.
    for cut in [0, 7, 100, bytes.len() / 2, bytes.len() - 9] {
        let p = tmp.path().join(format!("cut{cut}.mcap"));
        std::fs::write(&p, &bytes[..cut]).unwrap();
        let e = err_of(run_bag(&p, &out, topics(true)));
        assert!(e.contains(&p.display().to_string()), "{e}");
        assert!(
            e.contains("not an MCAP file") || e.contains("truncated"),
            "cut {cut}: {e}"
        );
    }
    // Bytes flipped inside the data section: a chunk or a record no longer decodes.
    let mut hits = 0;
    for pos in (8..bytes.len() - 8).step_by(bytes.len() / 97 + 1) {
        let mut b = bytes.clone();
        b[pos] ^= 0x5a;
        let p = tmp.path().join("flipped.mcap");
        std::fs::write(&p, &b).unwrap();
        // Either an error naming the file, or (a byte nothing checks, e.g. padding) a run.
        if let Err(e) = run_bag(&p, &out, topics(true)) {
            assert!(e.to_string().contains(&p.display().to_string()), "{e}");
            hits += 1;
        }
    }
    assert!(hits > 50, "{hits}");
    // Not an MCAP file at all.
    let p = tmp.path().join("text.mcap");
    std::fs::write(&p, "hello, world, this is not a bag").unwrap();
    let e = err_of(run_bag(&p, &out, topics(false)));
    assert!(e.contains("not an MCAP file"), "{e}");

    // Wrong topics: the error lists what the bag has.
    let mut t = topics(true);
    t.image = "/camera/color/image_raw".into();
    let e = err_of(run_bag(&bag, &out, t));
    assert!(e.contains(&name), "{e}");
    assert!(
        e.contains("--image-topic /camera/color/image_raw: no such topic"),
        "{e}"
    );
    for topic in [RGB_TOPIC, DEPTH_TOPIC, CAMERA_INFO_TOPIC, "/groundtruth"] {
        assert!(e.contains(topic), "{topic} not listed: {e}");
    }
    // A topic of the wrong type.
    let mut t = topics(true);
    t.depth = CAMERA_INFO_TOPIC.into();
    let e = err_of(run_bag(&bag, &out, t));
    assert!(
        e.contains("sensor_msgs/msg/CameraInfo") && e.contains("expected"),
        "{e}"
    );
    // And the intact tiny bag runs.
    run_bag(&bag, &out, topics(true)).unwrap();
}

#[test]
fn depth_encodings_give_metres() {
    use homing::io::cdr::{Image, Time};
    let img = |enc: &str, data: Vec<u8>| Image {
        header: homing::io::cdr::Header {
            stamp: Time::default(),
            frame_id: String::new(),
        },
        height: 1,
        width: 2,
        encoding: enc.into(),
        is_bigendian: 0,
        step: data.len() as u32,
        data,
    };
    let p = Path::new("x.mcap");
    let mm: Vec<u8> = [1500u16, 0].iter().flat_map(|v| v.to_le_bytes()).collect();
    let d = homing::io::mcap::image_to_depth(&img("16UC1", mm), p, "/d", 1000.0).unwrap();
    assert_eq!(d.data, vec![1.5, 0.0]);
    let m: Vec<u8> = [2.25f32, f32::NAN]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let d = homing::io::mcap::image_to_depth(&img("32FC1", m), p, "/d", 1000.0).unwrap();
    assert_eq!(d.data, vec![2.25, 0.0]);
    let e = homing::io::mcap::image_to_depth(&img("8UC1", vec![1, 2]), p, "/d", 1000.0)
        .unwrap_err()
        .to_string();
    assert!(e.contains("x.mcap") && e.contains("8UC1"), "{e}");
    let c = homing::io::mcap::image_to_rgb(&img("bgr8", vec![1, 2, 3, 4, 5, 6]), p, "/c").unwrap();
    assert_eq!(c.into_raw(), vec![3, 2, 1, 6, 5, 4]);
    let short = img("rgb8", vec![1, 2, 3]);
    assert!(homing::io::mcap::image_to_rgb(&short, p, "/c").is_err());
}
