//! Pose-only refinement (ORB-SLAM's PoseOptimization) on synthetic correspondences.

use homing::optim::{
    Intrinsics, Observation, PoseObservation, PoseParams, octave_information, refine_pose, se3,
};
use nalgebra::{Isometry3, Point3, Vector2, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

const INTR: Intrinsics = Intrinsics::TUM_FREIBURG1;

fn pose_error(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    // Compare camera centres (metres) and orientations (degrees).
    let ca = a.inverse().translation.vector;
    let cb = b.inverse().translation.vector;
    (
        (ca - cb).norm(),
        a.rotation.angle_to(&b.rotation).to_degrees(),
    )
}

/// Perturbs a pose by exactly `trans` metres and `rot_deg` degrees in random directions.
fn perturb(
    rng: &mut ChaCha8Rng,
    pose: &Isometry3<f64>,
    trans: f64,
    rot_deg: f64,
) -> Isometry3<f64> {
    let dir =
        |rng: &mut ChaCha8Rng| Vector3::from_fn(|_, _| rng.random_range(-1.0..1.0)).normalize();
    let w = dir(rng) * rot_deg.to_radians();
    let v = dir(rng) * trans;
    se3::retract(pose, &Vector6::new(w.x, w.y, w.z, v.x, v.y, v.z))
}

struct Scene {
    truth: Isometry3<f64>,
    observations: Vec<PoseObservation>,
    is_outlier: Vec<bool>,
}

/// `n` points in front of the camera; a fraction `outlier_rate` of the observations are
/// replaced by random pixels at least 30 px from the true projection.
fn scene(seed: u64, n: usize, outlier_rate: f64, rgbd: bool) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let truth = Isometry3::new(Vector3::new(0.3, -0.1, 0.5), Vector3::new(0.05, -0.2, 0.1));
    let mut observations = Vec::new();
    let mut is_outlier = Vec::new();
    for _ in 0..n {
        let p_c = Vector3::new(
            rng.random_range(-2.0..2.0),
            rng.random_range(-1.5..1.5),
            rng.random_range(1.0..6.0),
        );
        let point_w = (truth.inverse() * Point3::from(p_c)).coords;
        let octave: u32 = rng.random_range(0..4);
        let sigma = 1.2f64.powi(octave as i32);
        let noise = Normal::new(0.0, sigma).unwrap();
        let true_uv = INTR.project(&p_c).unwrap();
        let outlier = rng.random_bool(outlier_rate);
        let uv = if outlier {
            loop {
                let uv = Vector2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0));
                if (uv - true_uv).norm() > 30.0 {
                    break uv;
                }
            }
        } else {
            true_uv + Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng))
        };
        let obs = if rgbd {
            // Noise on the virtual right coordinate, as ORB-SLAM models it.
            let ur = true_uv.x - INTR.bf / p_c.z + noise.sample(&mut rng);
            let disparity = (uv.x - ur).max(0.5);
            Observation::Rgbd {
                uv,
                depth: INTR.bf / disparity,
            }
        } else {
            Observation::Mono { uv }
        };
        observations.push(PoseObservation {
            point_w,
            obs,
            info: octave_information(octave),
            shutter: Isometry3::identity(),
        });
        is_outlier.push(outlier);
    }
    Scene {
        truth,
        observations,
        is_outlier,
    }
}

fn check_recovery(rgbd: bool) {
    for seed in 0..5 {
        let s = scene(seed, 200, 0.3, rgbd);
        let mut rng = ChaCha8Rng::seed_from_u64(100 + seed);
        let init = perturb(&mut rng, &s.truth, 0.05, 2.0);
        let r = refine_pose(&init, &s.observations, &INTR, &PoseParams::default());
        let (dt, dr) = pose_error(&r.pose, &s.truth);
        assert!(r.optimized);
        assert!(dt < 0.01 && dr < 0.2, "seed {seed}: {dt} m, {dr} deg");
        // Every gross outlier is flagged; most good observations are kept.
        for (k, out) in s.is_outlier.iter().enumerate() {
            if *out {
                assert!(!r.inliers[k], "seed {seed}: outlier {k} kept");
            }
        }
        let n_good = s.is_outlier.iter().filter(|o| !**o).count();
        assert!(
            r.n_inliers as f64 > 0.85 * n_good as f64,
            "{} of {n_good}",
            r.n_inliers
        );
        assert_eq!(r.n_inliers, r.inliers.iter().filter(|i| **i).count());
        assert!(r.final_chi2.is_finite() && r.final_chi2 > 0.0);
    }
}

#[test]
fn recovers_pose_mono_with_outliers() {
    check_recovery(false);
}

#[test]
fn recovers_pose_rgbd_with_outliers() {
    check_recovery(true);
}

#[test]
fn too_few_observations_do_not_panic() {
    let s = scene(1, 6, 0.0, false);
    let init = s.truth;
    for n in 0..4 {
        let r = refine_pose(&init, &s.observations[..n], &INTR, &PoseParams::default());
        assert_eq!(r.inliers.len(), n);
        assert!(r.n_inliers <= n);
        assert!(r.pose.translation.vector.iter().all(|x| x.is_finite()));
        assert_eq!(r.optimized, n >= 3);
    }
}

#[test]
fn all_outliers_report_few_inliers() {
    let s = scene(2, 80, 1.0, false);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let init = perturb(&mut rng, &s.truth, 0.05, 2.0);
    let r = refine_pose(&init, &s.observations, &INTR, &PoseParams::default());
    assert!(
        r.n_inliers < 10,
        "{} inliers among pure outliers",
        r.n_inliers
    );
    assert!(r.pose.translation.vector.iter().all(|x| x.is_finite()));
    assert!(r.pose.rotation.coords.iter().all(|x| x.is_finite()));
}

#[test]
fn degenerate_points_do_not_panic() {
    let mut s = scene(4, 40, 0.0, true);
    // A point behind the camera, one at the camera centre and one non-finite.
    s.observations[0].point_w = (s.truth.inverse() * Point3::new(0.0, 0.0, -2.0)).coords;
    s.observations[1].point_w = s.truth.inverse().translation.vector;
    s.observations[2].point_w = Vector3::new(f64::NAN, 0.0, 1.0);
    // Invalid information weights are ignored, never counted as inliers.
    s.observations[3].info = -1.0;
    s.observations[4].info = f64::NAN;
    let r = refine_pose(&s.truth, &s.observations, &INTR, &PoseParams::default());
    assert!(r.inliers[..5].iter().all(|i| !i), "{:?}", &r.inliers[..5]);
    assert!(r.n_inliers >= 30);
    let (dt, dr) = pose_error(&r.pose, &s.truth);
    assert!(dt < 0.01 && dr < 0.2);
}

/// A fast-moving rolling-shutter camera: every row is exposed at its own pose. Refinement that
/// knows the motion (`shutter` per observation) recovers the frame's pose; one that assumes a
/// global shutter is pulled centimetres away along the translation/rotation ambiguity.
#[test]
fn rolling_shutter_model_removes_the_skew_bias() {
    use homing::components::preprocess::ImageGeometry;
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let geo = ImageGeometry::new(INTR, 640, 480, 1.2, 8).with_readout(0.025);
    let truth = Isometry3::new(Vector3::new(0.1, 0.2, 0.3), Vector3::new(0.1, -0.05, 0.02));
    // 0.45 m/s sideways and 30°/s: fr1_xyz's fast moments.
    let twist = Vector6::new(0.0, 0.5, 0.0, 0.45, 0.0, 0.0);
    let noise = Normal::new(0.0, 0.5).unwrap();
    let mut with_rs = Vec::new();
    let mut without = Vec::new();
    for _ in 0..300 {
        // A desk-like scene: depth grows towards the top of the image.
        let (x, y) = (rng.random_range(-0.6..0.6), rng.random_range(-0.45..0.45));
        let p_c = Vector3::new(x, y, 1.2 - 0.8 * y);
        let point_w = (truth.inverse() * Point3::from(p_c)).coords;
        // The row a point lands on depends on the pose of that row: iterate to the fixed point.
        let mut uv = INTR.project(&p_c).unwrap();
        for _ in 0..5 {
            let s = geo.shutter(&twist, uv.y);
            uv = INTR
                .project(&(s * truth * Point3::from(point_w)).coords)
                .unwrap();
        }
        let s = geo.shutter(&twist, uv.y);
        let depth = (s * truth * Point3::from(point_w)).z;
        let uv_n = uv + Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng));
        let obs = Observation::Rgbd { uv: uv_n, depth };
        with_rs.push(PoseObservation {
            point_w,
            obs,
            info: 1.0,
            shutter: s,
        });
        without.push(PoseObservation {
            point_w,
            obs,
            info: 1.0,
            shutter: Isometry3::identity(),
        });
    }
    let init = perturb(&mut rng, &truth, 0.02, 1.0);
    let params = PoseParams::default();
    let a = refine_pose(&init, &with_rs, &INTR, &params);
    let b = refine_pose(&init, &without, &INTR, &params);
    let (ta, ra) = pose_error(&a.pose, &truth);
    let (tb, _) = pose_error(&b.pose, &truth);
    assert!(
        ta < 0.002 && ra < 0.1,
        "with the shutter model: {ta} m, {ra} deg"
    );
    assert!(
        tb > 5.0 * ta && tb > 0.005,
        "global-shutter model: {tb} m (rolling: {ta} m)"
    );
    assert!(a.n_inliers > 280, "{} inliers", a.n_inliers);
}
