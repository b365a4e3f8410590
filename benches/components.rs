//! Criterion benches of the hot components (issue #9), so that regressions show:
//! ORB extraction of one 640×480 frame, a tracking step, a local-BA iteration, an HBST query
//! and a pose-graph solve. All inputs are generated here (a few synthetic desk frames rendered
//! by `homing-datasets`, seeded synthetic geometry): no data set is needed.
//!
//! `cargo bench --bench components -- --quick` for a fast pass.

use criterion::{BatchSize, Criterion, criterion_group, criterion_main};
use homing::components::initializer::Initializer;
use homing::components::loop_detector::hbst::{Hbst, HbstParams};
use homing::components::preprocess::{ImageGeometry, Measurement, Preprocessor};
use homing::components::tracker::Tracker;
use homing::config::{Config, resolve_camera};
use homing::geometry::Sim3;
use homing::io::tum::{FrameSource, TumSequence};
use homing::map::Map;
use homing::optim::pose_graph::{PgEdge, PgParams, PoseGraph, info7, node};
use homing::optim::{
    BaCamera, BaObservation, BaParams, BaPoint, BaProblem, Intrinsics, Observation,
    octave_information, solve,
};
use homing_datasets::{scenarios, sensor::SensorOptions, writer};
use nalgebra::{
    Isometry3, Matrix3, Matrix6, Point3, Rotation3, Translation3, UnitQuaternion, Vector3,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::hint::black_box;

/// Frames rendered for the image benches (full 640×480 resolution).
const FRAMES: usize = 24;

struct Images {
    _dir: tempfile::TempDir,
    seq: TumSequence,
    pre: Preprocessor,
    config: Config,
    intr: Intrinsics,
    width: u32,
    height: u32,
}

/// Renders the first frames of the synthetic desk at 640×480 and opens them.
fn images() -> Images {
    let dir = tempfile::tempdir().expect("temporary folder");
    let sc = scenarios::build("desk", 1).expect("desk scenario");
    writer::generate(
        &sc,
        &writer::GenOptions {
            out: dir.path().to_path_buf(),
            small: false,
            seed: 1,
            sensor: SensorOptions::realistic(),
            max_frames: Some(FRAMES),
        },
    )
    .expect("render the desk");
    let config = Config::default();
    let (camera, _) = resolve_camera(&config, None, dir.path()).expect("camera.toml");
    assert_eq!((camera.width, camera.height), (640, 480));
    let seq = TumSequence::open(
        dir.path(),
        camera.width,
        camera.height,
        camera.depth_scale,
        config.sequence.max_association_dt,
        false,
    )
    .expect("open the rendered sequence");
    let pre = Preprocessor::new(&camera, &config.orb).expect("preprocessor");
    let intr = Intrinsics {
        fx: camera.fx,
        fy: camera.fy,
        cx: camera.cx,
        cy: camera.cy,
        bf: camera.fx * camera.virtual_baseline_m,
    };
    Images {
        _dir: dir,
        seq,
        pre,
        config,
        intr,
        width: camera.width,
        height: camera.height,
    }
}

fn measurements(im: &mut Images) -> Vec<Measurement> {
    (0..im.seq.frames.len())
        .map(|i| {
            let f = im.seq.load(i).expect("load frame");
            im.pre.process(&f).expect("preprocess")
        })
        .collect()
}

fn bench_image_components(c: &mut Criterion) {
    let mut im = images();
    let frame = im.seq.load(0).expect("load frame");
    c.bench_function("orb_extraction_640x480", |b| {
        b.iter(|| im.pre.process(black_box(&frame)).expect("preprocess"))
    });

    let ms = measurements(&mut im);
    // Tracking step: a map initialised on frame 0 (RGB-D), the tracker reset there, frame 1
    // tracked against it (the tracker is cloned per iteration so every step is the same).
    let cfg = &im.config;
    let geo = ImageGeometry::new(
        im.intr,
        im.width,
        im.height,
        cfg.orb.scale_factor,
        cfg.orb.n_levels,
    );
    let mut init = Initializer::new(
        cfg.mapping.min_init_depth_points as usize,
        cfg.mapping.max_point_depth_m,
        geo.clone(),
        false,
    );
    let (map, kf) = init
        .try_initialize(&ms[0], Map::new(0))
        .expect("the first desk frame initialises a map");
    let mut tracker = Tracker::new(&cfg.tracker, geo);
    tracker.reset(
        Isometry3::identity(),
        ms[0].t,
        &map.keyframes[&kf].points,
        kf,
    );
    assert!(
        tracker.clone().track(&ms[1], &map).able_to_track,
        "frame 1 tracks against frame 0's map"
    );
    c.bench_function("tracking_step", |b| {
        b.iter_batched(
            || tracker.clone(),
            |mut t| t.track(black_box(&ms[1]), &map),
            BatchSize::SmallInput,
        )
    });

    // HBST: every frame but the last inserted, the last one queried.
    let mut tree = Hbst::new(HbstParams::from_config(&cfg.loop_closing));
    for (i, m) in ms[..ms.len() - 1].iter().enumerate() {
        tree.query_and_insert(i as u64, &m.descriptors, |_| false);
    }
    let query = &ms[ms.len() - 1].descriptors;
    c.bench_function("hbst_query", |b| {
        b.iter(|| tree.query(black_box(query), |_| true))
    });
}

/// World-to-camera pose of a camera at `centre` looking at `target`.
fn look_at(centre: Vector3<f64>, target: Vector3<f64>) -> Isometry3<f64> {
    let z = (target - centre).normalize();
    let x = Vector3::new(0.0, 1.0, 0.0).cross(&z).normalize();
    let y = z.cross(&x);
    let r_wc = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    Isometry3::from_parts(
        Translation3::from(centre),
        UnitQuaternion::from_rotation_matrix(&r_wc),
    )
    .inverse()
}

/// A local-BA window of ORB-SLAM's size: 10 keyframes on an arc, 1500 points seen by all of
/// them (RGB-D observations), poses and points disturbed by a few centimetres.
fn ba_problem() -> BaProblem {
    const INTR: Intrinsics = Intrinsics::TUM_FREIBURG1;
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let poses: Vec<Isometry3<f64>> = (0..10)
        .map(|i| {
            let a = (-20.0 + 4.0 * i as f64).to_radians();
            look_at(
                Vector3::new(4.0 * a.sin(), 0.0, -4.0 * a.cos()),
                Vector3::zeros(),
            )
        })
        .collect();
    let points: Vec<Vector3<f64>> = (0..1500)
        .map(|_| Vector3::from_fn(|_, _| rng.random_range(-1.5..1.5)))
        .collect();
    let mut observations = Vec::new();
    for (p, x) in points.iter().enumerate() {
        for (c, pose) in poses.iter().enumerate() {
            let p_c = (pose * Point3::from(*x)).coords;
            let Some(uv) = INTR.project(&p_c) else {
                continue;
            };
            observations.push(BaObservation {
                camera: c,
                point: p,
                obs: Observation::Rgbd { uv, depth: p_c.z },
                info: octave_information(0),
                shutter: Isometry3::identity(),
            });
        }
    }
    let jitter = |rng: &mut ChaCha8Rng, s: f64| Vector3::from_fn(|_, _| rng.random_range(-s..s));
    BaProblem {
        keyframes: poses
            .iter()
            .enumerate()
            .map(|(c, pose)| BaCamera {
                pose_cw: Isometry3::from_parts(
                    Translation3::from(pose.translation.vector + jitter(&mut rng, 0.03)),
                    pose.rotation,
                ),
                fixed: c < 2,
            })
            .collect(),
        points: points
            .iter()
            .map(|x| BaPoint {
                position_w: x + jitter(&mut rng, 0.03),
                fixed: false,
            })
            .collect(),
        observations,
        intrinsics: INTR,
        pose_edges: Vec::new(),
    }
}

/// A 200-node loop with drifted odometry and three closures.
fn pose_graph() -> PoseGraph {
    const N: usize = 200;
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let truth: Vec<Isometry3<f64>> = (0..N)
        .map(|i| {
            let a = i as f64 / N as f64 * std::f64::consts::TAU;
            let c = Vector3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.0);
            let yaw = UnitQuaternion::from_euler_angles(0.0, 0.0, a + std::f64::consts::FRAC_PI_2);
            Isometry3::from_parts(Translation3::from(c), yaw).inverse()
        })
        .collect();
    let info = info7(&(Matrix6::identity() * 1e4), 1.0);
    let mut g = PoseGraph::default();
    let mut est = truth[0];
    g.nodes.push(node(&est, true));
    for i in 1..N {
        let n = Vector3::from_fn(|_, _| rng.random_range(-0.01..0.01));
        let r = UnitQuaternion::from_scaled_axis(n * 0.5);
        let z = truth[i - 1] * truth[i].inverse() * Isometry3::from_parts(Translation3::from(n), r);
        est = z.inverse() * est;
        g.nodes.push(node(&est, false));
        g.edges.push(PgEdge {
            i: i - 1,
            j: i,
            measurement: Sim3::from_isometry(&z),
            information: info,
            robust: false,
        });
    }
    for (i, j) in [(N - 1, 0), (N - 2, 1), (N / 2, 0)] {
        g.edges.push(PgEdge {
            i,
            j,
            measurement: Sim3::from_isometry(&(truth[i] * truth[j].inverse())),
            information: info,
            robust: true,
        });
    }
    g
}

fn bench_optimisers(c: &mut Criterion) {
    let ba = ba_problem();
    let one = BaParams {
        iterations: 1,
        ..Default::default()
    };
    c.bench_function("local_ba_iteration_10kf_1500pts", |b| {
        b.iter_batched(
            || ba.clone(),
            |mut p| solve(&mut p, &one),
            BatchSize::LargeInput,
        )
    });
    let g = pose_graph();
    c.bench_function("pose_graph_solve_200_nodes", |b| {
        b.iter_batched(
            || g.clone(),
            |mut g| g.optimize(&PgParams::default()),
            BatchSize::SmallInput,
        )
    });
}

criterion_group!(
    name = components;
    config = Criterion::default()
        .sample_size(10)
        .warm_up_time(std::time::Duration::from_millis(500))
        .measurement_time(std::time::Duration::from_secs(2));
    targets = bench_image_components, bench_optimisers
);
criterion_main!(components);
