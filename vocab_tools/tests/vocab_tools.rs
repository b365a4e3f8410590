//! Fast tests without external data: the descriptor file, tree statistics, the evaluation on a
//! synthetic out-and-back trajectory whose true matches are known, and the bench generator.

use homing::components::loop_detector::{HbstParams, LoopDetectorParams};
use homing::components::preprocess::{Descriptor, hamming};
use homing::io::tum::{StampedPose, write_trajectory};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use vocab_tools::bench::{self, BenchOptions, Source, WorldParams, flip_bits, place};
use vocab_tools::eval::{self, EvalFrame, EvalOptions, same_place};
use vocab_tools::{DescriptorFile, FrameDescriptors, tree};

fn small_file(seed: u64, frames: usize, per_frame: usize) -> DescriptorFile {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    DescriptorFile {
        frames: (0..frames)
            .map(|i| FrameDescriptors {
                t: 1305031102.175304 + i as f64 / 30.0,
                descriptors: (0..per_frame + i % 3).map(|_| rng.random()).collect(),
            })
            .collect(),
    }
}

#[test]
fn descriptor_file_round_trips_and_is_written_atomically() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("x.desc");
    let mut file = small_file(1, 7, 50);
    file.frames[3].descriptors.clear(); // a frame without descriptors is kept
    file.write(&path).unwrap();
    let back = DescriptorFile::read(&path).unwrap();
    assert_eq!(back, file);
    assert_eq!(back.n_descriptors(), file.n_descriptors());
    // Time stamps are bit-exact (f64 stored as is).
    assert_eq!(back.frames[6].t.to_bits(), file.frames[6].t.to_bits());
    // Only the target remains in the folder (the temporary file was renamed).
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names, vec![std::ffi::OsString::from("x.desc")]);
    // Overwriting replaces the content.
    let other = small_file(2, 2, 5);
    other.write(&path).unwrap();
    assert_eq!(DescriptorFile::read(&path).unwrap(), other);
}

#[test]
fn truncated_or_corrupt_descriptor_files_are_errors_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("broken.desc");
    let bytes = small_file(3, 3, 4).to_bytes();
    let check = |b: &[u8], what: &str| {
        std::fs::write(&path, b).unwrap();
        let e = DescriptorFile::read(&path).expect_err(what).to_string();
        assert!(
            e.contains("broken.desc"),
            "{what}: error does not name the file: {e}"
        );
        e
    };
    // Every proper prefix is truncated.
    for n in 0..bytes.len() {
        let e = check(&bytes[..n], &format!("prefix of {n} bytes"));
        assert!(
            e.contains("truncated") || e.contains("corrupt"),
            "prefix {n}: {e}"
        );
    }
    let mut b = bytes.clone();
    b[0] = b'X';
    assert!(check(&b, "magic").contains("magic"));
    let mut b = bytes.clone();
    b[8] = 9;
    assert!(check(&b, "version").contains("version 9"));
    let mut b = bytes.clone();
    b.push(0);
    assert!(check(&b, "trailing").contains("follow"));
    // A huge frame count must not allocate or panic.
    let mut b = bytes.clone();
    b[12..20].copy_from_slice(&u64::MAX.to_le_bytes());
    check(&b, "frame count");
    // A huge descriptor count in the first frame.
    let mut b = bytes.clone();
    b[28..32].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(check(&b, "descriptor count").contains("truncated"));
    // A NaN time stamp.
    let mut b = bytes;
    b[20..28].copy_from_slice(&f64::NAN.to_le_bytes());
    assert!(check(&b, "nan").contains("time stamp"));
    // A missing file.
    let e = DescriptorFile::read(&dir.path().join("missing.desc"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("missing.desc"), "{e}");
}

#[test]
fn build_statistics_are_consistent() {
    let file = small_file(4, 40, 100);
    let params = HbstParams {
        max_leaf_size: 30,
        ..Default::default()
    };
    let (t, r) = tree::build(&file, params);
    let n = file.n_descriptors();
    assert_eq!(r.stats.descriptors, n);
    assert_eq!(
        r.leaf_size_sum, n,
        "sum of leaf sizes = number of descriptors"
    );
    assert_eq!(t.len(), n);
    assert_eq!(r.stats.images, 40);
    assert_eq!(
        r.stats.leaf_size_histogram.iter().sum::<usize>(),
        r.stats.leaves
    );
    assert_eq!(r.stats.nodes, 2 * r.stats.leaves - 1, "a full binary tree");
    assert!(r.stats.leaves > n / 30, "the tree must have split");
    assert!(r.leaf_size_max <= 30 || r.stats.oversized_leaves > 0);
    assert!(r.leaf_size_min <= r.leaf_size_median && r.leaf_size_median <= r.leaf_size_max);
    assert!(r.min_leaf_depth as f64 <= r.stats.mean_leaf_depth);
    assert!(r.stats.mean_leaf_depth <= r.stats.max_depth as f64);
    assert!(r.min_leaf_depth >= 1);
    // Random descriptors split almost evenly.
    assert!(r.stats.mean_split_balance > 0.4 && r.stats.mean_split_balance <= 0.5);
    assert!(r.to_text().contains(&format!("sum {n}")));
}

/// An out-and-back walk along x: frames 0..30 go from 0 to 2.9 m, frames 30..60 come back.
/// Landmarks lie every 2 mm along the path; a frame observes each landmark within 0.3 m with
/// probability 0.8 (a noisy copy, 0–6 flipped bits) plus 20 % clutter. Returning frames see
/// the landmarks of the outgoing frames at the same place.
fn out_and_back(seed: u64) -> Vec<EvalFrame> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let landmarks: Vec<Descriptor> = (0..=1600).map(|_| rng.random()).collect(); // 0 .. 3.2 m
    let xs: Vec<f64> = (0..30)
        .map(|i| i as f64 * 0.1)
        .chain((0..30).map(|i| 2.9 - i as f64 * 0.1))
        .collect();
    xs.iter()
        .enumerate()
        .map(|(i, &x)| {
            let mut descriptors = Vec::new();
            for (l, d) in landmarks.iter().enumerate() {
                let lx = l as f64 * 0.002;
                if (lx - x).abs() <= 0.3 && rng.random_bool(0.8) {
                    let k = rng.random_range(0..=6);
                    descriptors.push(flip_bits(&mut rng, d, k));
                }
            }
            let clutter = descriptors.len() / 4;
            for _ in 0..clutter {
                descriptors.push(rng.random());
            }
            EvalFrame {
                t: i as f64 / 30.0,
                descriptors,
                pose: Isometry3::from_parts(
                    Translation3::new(x, 0.0, 1.0),
                    UnitQuaternion::from_euler_angles(0.0, 0.1 * x, 0.0),
                ),
            }
        })
        .collect()
}

fn synthetic_options() -> EvalOptions {
    EvalOptions {
        detector: LoopDetectorParams {
            hbst: HbstParams {
                max_leaf_size: 50,
                ..Default::default()
            },
            ..Default::default()
        },
        min_gap: 10,
        // 0.45 rather than 0.5: keeps frame 32 (exactly 0.5 m from its nearest eligible
        // frame) clear of rounding.
        max_distance_m: 0.45,
        ..Default::default()
    }
}

#[test]
fn eval_on_a_known_loop_gives_plausible_precision_and_recall() {
    let frames = out_and_back(5);
    let o = synthetic_options();
    let r = eval::evaluate(&frames, &o);
    assert_eq!(r.frames, 60);
    assert_eq!(r.queries, 50);
    // Positives: returning frames with an outgoing frame within 0.45 m at least 10 frames
    // earlier. Frame 30+j is at x = 2.9 − 0.1 j; eligible frames are ≤ 20 + j, the nearest at
    // x = 2.0 + 0.1 j, 0.9 − 0.2 j away. So j = 0..2 are negatives, j ≥ 3 positives; outgoing
    // frames only have frames ≥ 1 m behind them: negatives.
    let expected: Vec<bool> = (0..60).map(|i| i >= 33).collect();
    let got: Vec<bool> = r.records.iter().map(|q| q.positive).collect();
    assert_eq!(got, expected);
    assert_eq!(r.positives, 27);
    let bf = r.brute_force.as_ref().expect("brute force ran");
    for m in [&r.hbst, bf] {
        let p = &m.default_point;
        assert_eq!(p.min_matches, 40);
        assert!(
            p.precision.unwrap() >= 0.95,
            "{}: precision {:?}",
            m.name,
            p.precision
        );
        assert!(
            p.recall.unwrap() >= 0.6,
            "{}: recall {:?}",
            m.name,
            p.recall
        );
        // Recall falls (weakly) as the threshold rises.
        for w in m.sweep.windows(2) {
            assert!(w[1].recall.unwrap() <= w[0].recall.unwrap() + 1e-12);
            assert!(w[1].predictions <= w[0].predictions);
        }
    }
    // Brute force finds every true loop here.
    assert!(
        bf.default_point.recall.unwrap() >= 0.95,
        "{:?}",
        bf.default_point
    );
    // The HBST's descriptor matches are a subset of brute force's.
    for q in &r.records {
        let b = q.brute_force.as_ref().unwrap();
        assert!(
            q.hbst.raw_matches <= b.raw_matches,
            "frame {}: hbst {} > brute force {}",
            q.frame,
            q.hbst.raw_matches,
            b.raw_matches
        );
    }
    let rec = r.raw_match_recall.unwrap();
    assert!(rec <= 1.0 && rec > 0.3, "raw match recall {rec}");
    // Outgoing frames never get a candidate that reaches the default threshold: nothing they
    // could match is eligible.
    for q in &r.records[10..30] {
        if let Some((_, s, v)) = q.hbst.best {
            assert!(s < 0.05 || v < 40, "frame {}: {:?}", q.frame, q.hbst.best);
        }
    }
    // Deterministic apart from timing.
    let r2 = eval::evaluate(&frames, &o);
    let answers = |r: &eval::EvalReport| -> Vec<_> {
        r.records
            .iter()
            .map(|q| {
                (
                    q.hbst.best,
                    q.hbst.raw_matches,
                    q.brute_force.as_ref().unwrap().best,
                )
            })
            .collect()
    };
    assert_eq!(answers(&r), answers(&r2));
    assert!(r.to_text().contains("brute-force"));
}

#[test]
fn wrong_poses_lower_precision() {
    // The same descriptors with every pose moved 15 frames on: the matches are the same, but
    // most are now judged wrong, which shows the evaluation does look at the poses.
    let frames = out_and_back(6);
    let shifted: Vec<EvalFrame> = (0..frames.len())
        .map(|i| EvalFrame {
            pose: frames[(i + 15) % frames.len()].pose,
            ..frames[i].clone()
        })
        .collect();
    let o = synthetic_options();
    let good = eval::evaluate(&frames, &o)
        .brute_force
        .unwrap()
        .default_point;
    let bad = eval::evaluate(&shifted, &o)
        .brute_force
        .unwrap()
        .default_point;
    assert_eq!(good.predictions, bad.predictions);
    assert!(good.precision.unwrap() >= 0.95, "{good:?}");
    assert!(bad.precision.unwrap() < 0.5, "{bad:?}");
}

#[test]
fn same_place_uses_distance_and_angle() {
    let a = Isometry3::identity();
    let near = Isometry3::new(Vector3::new(0.4, 0.0, 0.0), Vector3::zeros());
    let far = Isometry3::new(Vector3::new(0.6, 0.0, 0.0), Vector3::zeros());
    let turned = Isometry3::new(Vector3::zeros(), Vector3::new(0.0, 40f64.to_radians(), 0.0));
    assert!(same_place(&a, &near, 0.5, 30.0));
    assert!(!same_place(&a, &far, 0.5, 30.0));
    assert!(!same_place(&a, &turned, 0.5, 30.0));
    assert!(same_place(&a, &turned, 0.5, 45.0));
}

#[test]
fn ground_truth_is_attached_by_nearest_stamp() {
    let dir = tempfile::tempdir().unwrap();
    let file = small_file(7, 5, 3);
    // Ground truth at 100 Hz covering all but the last frame.
    let t0 = file.frames[0].t - 0.05;
    let gt: Vec<StampedPose> = (0..16)
        .map(|k| StampedPose {
            t: t0 + k as f64 * 0.01,
            pose: Isometry3::new(Vector3::new(k as f64, 0.0, 0.0), Vector3::zeros()),
        })
        .collect();
    let gt_path = dir.path().join("groundtruth.txt");
    write_trajectory(&gt_path, &gt, "test").unwrap();
    let (frames, skipped) = eval::attach_ground_truth(&file, &gt_path, 0.02).unwrap();
    assert_eq!(skipped, 1);
    assert_eq!(frames.len(), 4);
    for f in &frames {
        let k = f.pose.translation.vector.x as usize;
        assert!(
            (gt[k].t - f.t).abs() <= 0.005 + 1e-9,
            "frame {} got gt {}",
            f.t,
            gt[k].t
        );
    }
    // A ground truth of another sequence is an error naming the file.
    let far: Vec<StampedPose> = gt
        .iter()
        .map(|p| StampedPose {
            t: p.t + 100.0,
            ..*p
        })
        .collect();
    write_trajectory(&gt_path, &far, "test").unwrap();
    let e = eval::attach_ground_truth(&file, &gt_path, 0.02)
        .unwrap_err()
        .to_string();
    assert!(e.contains("groundtruth.txt"), "{e}");
}

#[test]
fn bench_generator_is_deterministic_and_realistic() {
    let gen_kfs = |seed: u64| {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut s = Source::synthetic(WorldParams::new(200), &mut rng);
        (0..3).map(|k| s.keyframe(k, &mut rng)).collect::<Vec<_>>()
    };
    let a = gen_kfs(1);
    assert_eq!(a, gen_kfs(1));
    assert_ne!(a, gen_kfs(2));
    assert!(a.iter().all(|k| k.len() == 200));
    // Neighbouring keyframes share landmarks: many descriptors have a near copy.
    let near = a[1]
        .iter()
        .filter(|d| a[0].iter().any(|e| hamming(d, e) <= 16))
        .count();
    assert!(
        near > 50,
        "only {near} descriptors of keyframe 1 are near keyframe 0's"
    );
    // Revisits are old places.
    for k in 400..1000 {
        let p = place(k);
        assert!(p == k || p + 300 <= k, "keyframe {k} place {p}");
    }
    assert!((400..1000).filter(|&k| place(k) != k).count() >= 100);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let d: Descriptor = rng.random();
    for k in [0, 1, 5, 40] {
        assert_eq!(hamming(&d, &flip_bits(&mut rng, &d, k)), k as u32);
    }
}

#[test]
fn bench_times_every_size_and_finds_loops() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut s = Source::synthetic(WorldParams::new(100), &mut rng);
    let o = BenchOptions {
        sizes: vec![420, 50],
        probes: 10,
        seed: 1,
        detector: LoopDetectorParams::default(),
        temporal_window: 20,
    };
    let r = bench::run(&mut s, "test", &o, |_, _| {});
    assert_eq!(r.sizes.len(), 2);
    assert_eq!(r.sizes[0].keyframes, 50);
    assert_eq!(r.sizes[1].keyframes, 420);
    assert_eq!(r.sizes[0].tree.images, 60);
    assert_eq!(r.sizes[1].tree.images, 430);
    assert_eq!(r.sizes[1].tree.descriptors, 430 * 100);
    for z in &r.sizes {
        assert_eq!(z.index.count, 10);
        assert_eq!(z.descriptors_per_keyframe, 100.0);
        assert!(z.detector.median_ms >= z.index.median_ms);
    }
    // Before any revisit, the temporal window hides the only similar keyframes; keyframes
    // 424 and 429 revisit old places and match them.
    assert_eq!(r.sizes[0].matches_per_query, 0.0);
    assert!(
        r.sizes[1].matches_per_query > 5.0,
        "{}",
        r.sizes[1].matches_per_query
    );
}
