//! Local bundle adjustment on synthetic arc scenes.

use homing::optim::{
    BaCamera, BaObservation, BaParams, BaPoint, BaProblem, Intrinsics, Observation, Termination,
    octave_information, se3, solve, solve_with_outlier_rejection,
};
use nalgebra::{
    Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3, Vector6,
};
use rand::seq::index::sample;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

const INTR: Intrinsics = Intrinsics::TUM_FREIBURG1;

/// World-to-camera pose of a camera at `centre` looking at `target` (y down, z forward).
fn look_at(centre: Vector3<f64>, target: Vector3<f64>) -> Isometry3<f64> {
    let z = (target - centre).normalize();
    let x = Vector3::new(0.0, 1.0, 0.0).cross(&z).normalize();
    let y = z.cross(&x);
    let r_wc = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
    let pose_wc = Isometry3::from_parts(
        Translation3::from(centre),
        UnitQuaternion::from_rotation_matrix(&r_wc),
    );
    pose_wc.inverse()
}

struct Scene {
    problem: BaProblem,
    truth_poses: Vec<Isometry3<f64>>,
    truth_points: Vec<Vector3<f64>>,
}

/// `n_cams` cameras on a 4 m arc (±30°) looking at `n_points` points in a 4 m cube;
/// each point is observed by `obs_per_point` random cameras (all of them if `None`).
/// Every third observation is mono, the rest RGB-D; noise σ = 1.2^octave px, octave 0 or 1.
fn arc_scene(seed: u64, n_cams: usize, n_points: usize, obs_per_point: Option<usize>) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let truth_poses: Vec<Isometry3<f64>> = (0..n_cams)
        .map(|i| {
            let a = (-30.0 + 60.0 * i as f64 / (n_cams - 1) as f64).to_radians();
            let centre = Vector3::new(4.0 * a.sin(), 0.3 * a.cos(), -4.0 * a.cos());
            look_at(centre, Vector3::zeros())
        })
        .collect();
    let truth_points: Vec<Vector3<f64>> = (0..n_points)
        .map(|_| Vector3::from_fn(|_, _| rng.random_range(-2.0..2.0)))
        .collect();
    let mut observations = Vec::new();
    for (p, x) in truth_points.iter().enumerate() {
        let cams: Vec<usize> = match obs_per_point {
            Some(k) => sample(&mut rng, n_cams, k).into_vec(),
            None => (0..n_cams).collect(),
        };
        for c in cams {
            let p_c = (truth_poses[c] * Point3::from(*x)).coords;
            let uv = INTR
                .project(&p_c)
                .expect("points are in front of every camera");
            let octave: u32 = rng.random_range(0..2);
            let noise = Normal::new(0.0, 1.2f64.powi(octave as i32)).unwrap();
            let uv_n = uv + Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng));
            let obs = if (c + p) % 3 == 0 {
                Observation::Mono { uv: uv_n }
            } else {
                let ur = uv.x - INTR.bf / p_c.z + noise.sample(&mut rng);
                Observation::Rgbd {
                    uv: uv_n,
                    depth: INTR.bf / (uv_n.x - ur).max(0.5),
                }
            };
            observations.push(BaObservation {
                camera: c,
                point: p,
                obs,
                info: octave_information(octave),
                shutter: Isometry3::identity(),
            });
        }
    }
    let problem = BaProblem {
        keyframes: truth_poses
            .iter()
            .map(|&pose_cw| BaCamera {
                pose_cw,
                fixed: false,
            })
            .collect(),
        points: truth_points
            .iter()
            .map(|&position_w| BaPoint {
                position_w,
                fixed: false,
            })
            .collect(),
        observations,
        intrinsics: INTR,
        pose_edges: Vec::new(),
    };
    Scene {
        problem,
        truth_poses,
        truth_points,
    }
}

/// Fixes `fixed` cameras and perturbs the others by 5 cm / 2° and every point by 5 cm.
fn perturb(scene: &mut Scene, fixed: &[usize], seed: u64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let dir =
        |rng: &mut ChaCha8Rng| Vector3::from_fn(|_, _| rng.random_range(-1.0..1.0)).normalize();
    for (c, k) in scene.problem.keyframes.iter_mut().enumerate() {
        k.fixed = fixed.contains(&c);
        if !k.fixed {
            let w = dir(&mut rng) * 2f64.to_radians();
            let v = dir(&mut rng) * 0.05;
            k.pose_cw = se3::retract(&k.pose_cw, &Vector6::new(w.x, w.y, w.z, v.x, v.y, v.z));
        }
    }
    for p in scene.problem.points.iter_mut() {
        p.position_w += dir(&mut rng) * 0.05;
    }
}

/// Largest camera-centre (m) and rotation (deg) error of the free cameras.
fn max_pose_error(scene: &Scene) -> (f64, f64) {
    let mut worst = (0.0f64, 0.0f64);
    for (k, t) in scene.problem.keyframes.iter().zip(&scene.truth_poses) {
        let dc = (k.pose_cw.inverse().translation.vector - t.inverse().translation.vector).norm();
        let dr = k.pose_cw.rotation.angle_to(&t.rotation).to_degrees();
        worst = (worst.0.max(dc), worst.1.max(dr));
    }
    worst
}

#[test]
fn ba_recovers_perturbed_scene() {
    for seed in 0..2 {
        let params = BaParams {
            iterations: 20,
            ..BaParams::default()
        };
        // Reference optimum: the same problem solved from the true state.
        let mut reference = arc_scene(seed, 10, 300, None);
        perturb(&mut reference, &[0, 9], 50 + seed);
        reference
            .problem
            .keyframes
            .iter_mut()
            .zip(&reference.truth_poses)
            .for_each(|(k, t)| k.pose_cw = *t);
        reference
            .problem
            .points
            .iter_mut()
            .zip(&reference.truth_points)
            .for_each(|(p, t)| p.position_w = *t);
        let reference_cost = solve(&mut reference.problem, &params).unwrap().final_cost;

        let mut scene = arc_scene(seed, 10, 300, None);
        perturb(&mut scene, &[0, 9], 50 + seed);
        let report = solve(&mut scene.problem, &params).unwrap();
        // From 5 cm / 2° away it reaches the same minimum as from the truth.
        assert!(
            (report.final_cost - reference_cost).abs() < 1e-6 * reference_cost,
            "{report:?}"
        );
        let (dc, dr) = max_pose_error(&scene);
        assert!(report.final_chi2 < 0.01 * report.initial_chi2, "{report:?}");
        assert!(dc < 0.01 && dr < 0.2, "seed {seed}: {dc} m, {dr} deg");
        // Fixed cameras did not move.
        assert_eq!(scene.problem.keyframes[0].pose_cw, scene.truth_poses[0]);
        assert_eq!(scene.problem.keyframes[9].pose_cw, scene.truth_poses[9]);
        // Cost is monotone (rejected steps never increase it).
        let mut prev = report.initial_cost;
        for c in &report.cost_per_iteration {
            assert!(*c <= prev);
            prev = *c;
        }
        assert_eq!(report.cost_per_iteration.len(), report.iterations);
        let pt_err = scene
            .problem
            .points
            .iter()
            .zip(&scene.truth_points)
            .map(|(p, t)| (p.position_w - t).norm())
            .fold(0.0, f64::max);
        assert!(pt_err < 0.05, "worst point error {pt_err}");
        // With a correct model the 95 % threshold flags roughly 5 % of the observations.
        let rate = report.outliers.len() as f64 / scene.problem.observations.len() as f64;
        assert!(rate < 0.1, "outlier rate {rate}");
    }
}

#[test]
fn ba_flags_gross_outliers() {
    for two_stage in [false, true] {
        check_gross_outliers(two_stage);
    }
}

fn check_gross_outliers(two_stage: bool) {
    let mut scene = arc_scene(7, 10, 300, None);
    perturb(&mut scene, &[0, 1], 8);
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut injected = Vec::new();
    for (k, o) in scene.problem.observations.iter_mut().enumerate() {
        if rng.random_bool(0.05) {
            let shift = Vector2::new(rng.random_range(20.0..60.0), rng.random_range(-60.0..60.0));
            o.obs = match o.obs {
                Observation::Mono { uv } => Observation::Mono { uv: uv + shift },
                Observation::Rgbd { uv, depth } => Observation::Rgbd {
                    uv: uv + shift,
                    depth,
                },
            };
            injected.push(k);
        }
    }
    let params = BaParams {
        iterations: 20,
        ..BaParams::default()
    };
    let report = if two_stage {
        // ORB-SLAM's schedule: 5 robust iterations, drop outliers, 10 plain ones.
        let first = BaParams {
            iterations: 5,
            ..BaParams::default()
        };
        let second = BaParams {
            iterations: 10,
            huber: false,
            ..BaParams::default()
        };
        solve_with_outlier_rejection(&mut scene.problem, &first, &second).unwrap()
    } else {
        solve(&mut scene.problem, &params).unwrap()
    };
    for k in &injected {
        assert!(
            report.outliers.contains(k),
            "injected outlier {k} not reported"
        );
    }
    let false_pos = report.outliers.len() - injected.len();
    assert!((false_pos as f64) < 0.1 * scene.problem.observations.len() as f64);
    let (dc, dr) = max_pose_error(&scene);
    assert!(dc < 0.01 && dr < 0.2, "{dc} m, {dr} deg with outliers");
}

#[test]
fn ba_points_only_and_cameras_only() {
    // No free camera: only points move (the reduced system is empty).
    let mut scene = arc_scene(11, 6, 50, None);
    perturb(&mut scene, &[0, 1, 2, 3, 4, 5], 12);
    let report = solve(&mut scene.problem, &BaParams::default()).unwrap();
    assert!(report.final_chi2 < report.initial_chi2);
    assert_eq!(report.gauge_fixed_camera, None);
    // Points start 5 cm off; they end at the noise floor (a few mm for most).
    let errors: Vec<f64> = scene
        .problem
        .points
        .iter()
        .zip(&scene.truth_points)
        .map(|(p, t)| (p.position_w - t).norm())
        .collect();
    let mean = errors.iter().sum::<f64>() / errors.len() as f64;
    assert!(mean < 0.01, "mean point error {mean}");
    // No free point: motion-only BA over the free cameras.
    let mut scene = arc_scene(13, 6, 100, None);
    perturb(&mut scene, &[0], 14);
    for (p, t) in scene.problem.points.iter_mut().zip(&scene.truth_points) {
        p.position_w = *t;
        p.fixed = true;
    }
    let report = solve(&mut scene.problem, &BaParams::default()).unwrap();
    // Converged to the noise floor: χ² ≈ number of residual dimensions (~2.7 per obs).
    let dims: usize = scene.problem.observations.iter().map(|o| o.obs.dim()).sum();
    assert!(report.final_chi2 < 1.2 * dims as f64, "{report:?}");
    assert!(report.final_chi2 < 0.02 * report.initial_chi2, "{report:?}");
    let (dc, dr) = max_pose_error(&scene);
    assert!(dc < 0.01 && dr < 0.2);
}

#[test]
fn ba_degenerate_inputs() {
    // Empty problem.
    let mut empty = BaProblem {
        keyframes: vec![],
        points: vec![],
        observations: vec![],
        intrinsics: INTR,
        pose_edges: Vec::new(),
    };
    let r = solve(&mut empty, &BaParams::default()).unwrap();
    assert_eq!(r.iterations, 0);
    assert_eq!(r.termination, Termination::NothingToOptimize);
    // Everything fixed: nothing moves, but χ² and outliers are still reported.
    let mut scene = arc_scene(17, 3, 10, None);
    scene
        .problem
        .keyframes
        .iter_mut()
        .for_each(|k| k.fixed = true);
    scene.problem.points.iter_mut().for_each(|p| p.fixed = true);
    let before = scene.problem.clone();
    let r = solve(&mut scene.problem, &BaParams::default()).unwrap();
    assert_eq!(r.termination, Termination::NothingToOptimize);
    assert_eq!(scene.problem, before);
    assert!(r.initial_chi2 > 0.0 && r.initial_chi2 == r.final_chi2);
    // A point behind one camera is reported, not a panic.
    let mut scene = arc_scene(15, 4, 20, None);
    perturb(&mut scene, &[0], 16);
    scene.problem.points[3].position_w = Vector3::new(0.0, 0.0, -20.0);
    let r = solve(&mut scene.problem, &BaParams::default()).unwrap();
    assert!(r.final_cost.is_finite());
    assert!(!r.outliers.is_empty());
}

/// Timing: 10 keyframes × 2000 points × 10000 observations.
/// `cargo test --release --test it -- --ignored ba_timing --nocapture`
#[test]
#[ignore]
fn ba_timing() {
    let mut scene = arc_scene(21, 10, 2000, Some(5));
    perturb(&mut scene, &[0, 1], 22);
    assert_eq!(scene.problem.observations.len(), 10_000);
    let params = BaParams {
        iterations: 10,
        relative_tolerance: 0.0,
        ..BaParams::default()
    };
    let start = std::time::Instant::now();
    let report = solve(&mut scene.problem, &params).unwrap();
    let elapsed = start.elapsed().as_secs_f64() * 1e3;
    println!(
        "ba_timing: {} iterations in {elapsed:.1} ms = {:.2} ms/iteration (χ² {:.1} → {:.1}, {:?})",
        report.iterations,
        elapsed / report.iterations.max(1) as f64,
        report.initial_chi2,
        report.final_chi2,
        report.termination
    );
}
