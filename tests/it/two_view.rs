//! Two-view geometry (src/components/two_view.rs) on synthetic scenes: ORB-SLAM's H/F model selection,
//! motion recovery, low-parallax refusal, triangulation accuracy, Sim3 RANSAC, determinism.
//!
//! "1 px noise" in the two-view scenes is Gaussian noise of 1 px std per axis on the image-2
//! keypoint of each match (image 1 exact), so the match residual has a 1 px std, matching the
//! default σ = 1; see `planar_rh_depends_on_noise_relative_to_sigma` for noise in both images.
//! Outliers (20 %) are matches whose image-2 keypoint is a uniformly random pixel.

use homing::components::two_view::{
    ModelKind, RejectReason, Sim3RansacParams, TwoViewParams, decompose_essential,
    decompose_homography, initialize_two_view, k_matrix, parallax_deg, projection_matrix,
    reprojection_error_sq, sim3_ransac, triangulate,
};
use homing::geometry::Sim3;
use homing::optim::Intrinsics;
use nalgebra::{Matrix3, Rotation3, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

const K: Intrinsics = Intrinsics::TUM_FREIBURG1;
const W: f64 = 640.0;
const H: f64 = 480.0;

/// The plane of the planar scenes, `n·X = d` in camera 1: tilted by 45° (a floor or table seen
/// obliquely, 2.7–7 m away). With a plane facing the camera (tilt ≲ 25°) the second of
/// Faugeras' solutions keeps ~75–80 % of the points in front of both cameras and ORB-SLAM's
/// ambiguity test (second < 0.75 × best) refuses to initialise, as it should.
const PLANE_N: Vector3<f64> = Vector3::new(0.0, -1.0, 1.0);
const PLANE_D: f64 = 4.0;

#[derive(Clone, Copy)]
enum SceneKind {
    /// Points on the plane `PLANE_N·X = PLANE_D` (camera 1).
    Planar,
    /// Points at depths uniform in [2, 8] m.
    General,
}

struct Scene {
    x1: Vec<Vector2<f64>>,
    x2: Vec<Vector2<f64>>,
    /// Ground-truth points in camera 1 (metres); meaningless for outliers.
    points: Vec<Vector3<f64>>,
    outlier: Vec<bool>,
    r: Rotation3<f64>,
    /// `X_c2 = r X_c1 + t` (metres).
    t: Vector3<f64>,
}

fn in_image(p: &Vector2<f64>) -> bool {
    p.x >= 0.0 && p.x < W && p.y >= 0.0 && p.y < H
}

/// `n` matches seen by camera 1 (identity) and camera 2 (rotation `r`, centre `c2` in camera 1),
/// Gaussian pixel noise of std `noise.0` in image 1 and `noise.1` in image 2, a fraction `outliers` of matches replaced by a
/// random pixel in image 2.
fn scene(
    kind: SceneKind,
    r: Rotation3<f64>,
    c2: Vector3<f64>,
    n: usize,
    outliers: f64,
    noise: (f64, f64),
    seed: u64,
) -> Scene {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let gauss = Normal::new(0.0, 1.0).unwrap();
    let t = -(r * c2);
    let k_inv = k_matrix(&K).try_inverse().unwrap();
    let (mut x1, mut x2, mut points, mut outlier) = (vec![], vec![], vec![], vec![]);
    while x1.len() < n {
        let u = Vector2::new(
            rng.random_range(10.0..W - 10.0),
            rng.random_range(10.0..H - 10.0),
        );
        let ray = k_inv * u.push(1.0);
        let p = match kind {
            SceneKind::Planar => ray * (PLANE_D / PLANE_N.dot(&ray)),
            SceneKind::General => ray * rng.random_range(2.0..8.0),
        };
        let Some(v) = K.project(&(r * p + t)) else {
            continue;
        };
        if !in_image(&v) {
            continue;
        }
        let is_out = rng.random::<f64>() < outliers;
        let mut noisy = |q: Vector2<f64>, sd: f64| {
            q + Vector2::new(gauss.sample(&mut rng), gauss.sample(&mut rng)) * sd
        };
        let a = noisy(u, noise.0);
        let b = noisy(v, noise.1);
        let b = if is_out {
            Vector2::new(rng.random_range(0.0..W), rng.random_range(0.0..H))
        } else {
            b
        };
        x1.push(a);
        x2.push(b);
        points.push(p);
        outlier.push(is_out);
    }
    Scene {
        x1,
        x2,
        points,
        outlier,
        r,
        t,
    }
}

fn moderate_motion() -> (Rotation3<f64>, Vector3<f64>) {
    // ~5° rotation, 0.5 m mostly sideways baseline.
    (
        Rotation3::from_euler_angles(0.03, -0.08, 0.02),
        Vector3::new(0.5, 0.1, 0.05),
    )
}

fn rot_err_deg(a: &Rotation3<f64>, b: &Rotation3<f64>) -> f64 {
    (a * b.inverse()).angle().to_degrees()
}

fn dir_err_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.normalize()
        .dot(&b.normalize())
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Checks the accepted reconstruction against the truth and prints its numbers.
fn check_reconstruction(name: &str, s: &Scene, expect: ModelKind, rh_above: bool) {
    let params = TwoViewParams::default();
    let rec = initialize_two_view(&s.x1, &s.x2, &K, &params)
        .unwrap_or_else(|e| panic!("{name}: refused: {e:?}"));
    let (er, et) = (
        rot_err_deg(&rec.rotation, &s.r),
        dir_err_deg(&rec.translation, &s.t),
    );
    let n_out = s.outlier.iter().filter(|o| **o).count();
    let out_as_in = (0..s.x1.len())
        .filter(|&i| s.outlier[i] && rec.inliers[i])
        .count();
    let n_tri = rec.points.iter().flatten().count();
    // Points are in units of the baseline: scale by the true baseline to compare.
    let baseline = s.t.norm();
    let rel: Vec<f64> = (0..s.x1.len())
        .filter(|&i| !s.outlier[i])
        .filter_map(|i| {
            rec.points[i].map(|p| (p * baseline - s.points[i]).norm() / s.points[i].norm())
        })
        .collect();
    println!(
        "{name}: model {:?}, R_H {:.3} (S_H {:.1}, S_F {:.1}), rot err {er:.4}°, t dir err {et:.4}°, \
         inliers {} ({} of {n_out} outliers), good {} / second {}, triangulated {n_tri}, \
         parallax orb {:.2}° median {:.2}°, median point rel err {:.4}",
        rec.model,
        rec.r_h,
        rec.score_h,
        rec.score_f,
        rec.inliers.iter().filter(|b| **b).count(),
        out_as_in,
        rec.n_good,
        rec.n_good_second,
        rec.parallax.orb_deg,
        rec.parallax.median_deg,
        median(rel.clone()),
    );
    assert_eq!(rec.model, expect, "{name}: wrong model, R_H = {}", rec.r_h);
    if rh_above {
        assert!(rec.r_h > params.rh_threshold, "{name}: R_H {}", rec.r_h);
    } else {
        assert!(rec.r_h < params.rh_threshold, "{name}: R_H {}", rec.r_h);
    }
    assert!(er < 0.5, "{name}: rotation error {er}°");
    assert!(et < 2.0, "{name}: translation direction error {et}°");
    assert!((rec.translation.norm() - 1.0).abs() < 1e-9);
    assert!(rec.parallax.orb_deg >= params.min_parallax_deg);
    // Nearly all outliers are rejected (a random pixel can land within ~2 px of an epipolar
    // line by chance), and most true matches are triangulated.
    assert!(
        out_as_in * 10 <= n_out,
        "{name}: {out_as_in} of {n_out} outliers kept"
    );
    assert!(
        n_tri >= (s.x1.len() - n_out) * 7 / 10,
        "{name}: only {n_tri} triangulated"
    );
    assert!(median(rel) < 0.05, "{name}: triangulated points off");
}

/// Plane tilted 45°, 300 matches, 20 % outliers, ~5° rotation and 0.5 m baseline: H is
/// selected (R_H > 0.40), R within 0.5°, t direction within 2°.
#[test]
fn planar_scene_selects_homography_and_recovers_motion() {
    let (r, c2) = moderate_motion();
    let s = scene(SceneKind::Planar, r, c2, 300, 0.2, (0.0, 1.0), 1);
    check_reconstruction("planar", &s, ModelKind::Homography, true);
}

/// Same motion, points at 2–8 m: F is selected (R_H < 0.40), same accuracy bounds.
#[test]
fn general_scene_selects_fundamental_and_recovers_motion() {
    let (r, c2) = moderate_motion();
    let s = scene(SceneKind::General, r, c2, 300, 0.2, (0.0, 1.0), 2);
    check_reconstruction("general", &s, ModelKind::Fundamental, false);
}

#[test]
fn model_selection_holds_over_seeds() {
    // R_H stays on the right side of 0.40 for several scenes and RANSAC seeds.
    let (r, c2) = moderate_motion();
    for seed in 10..16 {
        for (kind, want_h) in [(SceneKind::Planar, true), (SceneKind::General, false)] {
            let s = scene(kind, r, c2, 250, 0.2, (0.0, 1.0), seed);
            let params = TwoViewParams {
                seed,
                ..Default::default()
            };
            let r_h = match initialize_two_view(&s.x1, &s.x2, &K, &params) {
                Ok(rec) => rec.r_h,
                Err(e) => e.r_h,
            };
            println!("seed {seed} planar {want_h}: R_H {r_h:.3}");
            assert_eq!(r_h > 0.40, want_h, "seed {seed}: R_H {r_h}");
        }
    }
}

/// The selection margin depends on the noise relative to σ. "1 px noise" above is 1 px on the
/// image-2 keypoint of a match (image 1 exact), i.e. a match residual of 1 px per axis. With
/// σ-level noise in *both* images, ORB-SLAM's score gives a planar scene (which H and F both
/// fit) R_H ≈ 0.41 in expectation — right at the 0.40 threshold: the selection is a coin flip.
/// Setting σ to the residual's std (√2 × per-image noise) restores the margin. This pins the
/// behaviour down so that a change of the scoring shows up here.
#[test]
fn planar_rh_depends_on_noise_relative_to_sigma() {
    let (r, c2) = moderate_motion();
    let mean_rh = |noise: (f64, f64), sigma: f64| {
        let v: Vec<f64> = (20..28)
            .map(|seed| {
                let s = scene(SceneKind::Planar, r, c2, 300, 0.2, noise, seed);
                let params = TwoViewParams {
                    seed,
                    sigma,
                    ..Default::default()
                };
                match initialize_two_view(&s.x1, &s.x2, &K, &params) {
                    Ok(rec) => rec.r_h,
                    Err(e) => e.r_h,
                }
            })
            .collect();
        v.iter().sum::<f64>() / v.len() as f64
    };
    let both_1px = mean_rh((1.0, 1.0), 1.0);
    let both_1px_sigma_sqrt2 = mean_rh((1.0, 1.0), std::f64::consts::SQRT_2);
    let match_1px = mean_rh((0.0, 1.0), 1.0);
    let both_half_px = mean_rh((0.5, 0.5), 1.0);
    println!(
        "planar mean R_H: 1 px in both images {both_1px:.3} (σ = √2: {both_1px_sigma_sqrt2:.3}), \
         1 px in image 2 {match_1px:.3}, 0.5 px in both {both_half_px:.3}"
    );
    assert!((0.38..0.43).contains(&both_1px), "{both_1px}");
    assert!(both_1px_sigma_sqrt2 > 0.42, "{both_1px_sigma_sqrt2}");
    assert!(match_1px > 0.42, "{match_1px}");
    assert!(both_half_px > 0.45, "{both_half_px}");
}

#[test]
fn low_parallax_is_refused() {
    // 1 cm of translation at 2–8 m: parallax ≈ 0.1–0.3°.
    let r = Rotation3::from_euler_angles(0.01, -0.02, 0.005);
    for kind in [SceneKind::General, SceneKind::Planar] {
        let s = scene(
            kind,
            r,
            Vector3::new(0.01, 0.0, 0.0),
            300,
            0.2,
            (0.0, 1.0),
            3,
        );
        let e = initialize_two_view(&s.x1, &s.x2, &K, &TwoViewParams::default())
            .expect_err("accepted a 1 cm baseline");
        println!("low parallax: {e:?}");
        assert_eq!(e.reason, RejectReason::LowParallax, "{e:?}");
    }
    // Pure rotation.
    let s = scene(
        SceneKind::General,
        r,
        Vector3::zeros(),
        300,
        0.2,
        (0.0, 1.0),
        4,
    );
    let e = initialize_two_view(&s.x1, &s.x2, &K, &TwoViewParams::default())
        .expect_err("accepted a pure rotation");
    println!("pure rotation: {e:?}");
    assert_eq!(e.reason, RejectReason::LowParallax, "{e:?}");
}

#[test]
fn too_few_matches_and_all_outliers_are_refused() {
    let (r, c2) = moderate_motion();
    let s = scene(SceneKind::General, r, c2, 7, 0.0, (0.0, 0.0), 5);
    let e = initialize_two_view(&s.x1, &s.x2, &K, &TwoViewParams::default()).unwrap_err();
    assert_eq!(e.reason, RejectReason::TooFewMatches);
    let s = scene(SceneKind::General, r, c2, 300, 1.0, (0.0, 1.0), 6);
    let e = initialize_two_view(&s.x1, &s.x2, &K, &TwoViewParams::default()).unwrap_err();
    println!("all outliers: {e:?}");
    assert_eq!(e.reason, RejectReason::TooFewInliers, "{e:?}");
}

#[test]
fn decompositions_contain_the_true_motion() {
    let (r, c2) = moderate_motion();
    let t = -(r * c2);
    let km = k_matrix(&K);
    let k_inv = km.try_inverse().unwrap();
    // Plane n·X = d in camera 1: X_c2 = (R + t nᵀ/d) X_c1.
    let n = Vector3::new(0.2, -0.12, 1.0);
    let d = 4.0;
    let h = km * (r.matrix() + t * n.transpose() / d) * k_inv;
    let hs = decompose_homography(&(h * -3.7), &K).unwrap();
    assert_eq!(hs.len(), 8);
    let best = hs
        .iter()
        .map(|(rr, tt)| rot_err_deg(&Rotation3::from_matrix(rr), &r).max(dir_err_deg(tt, &t)))
        .fold(f64::INFINITY, f64::min);
    assert!(best < 1e-4, "Faugeras: best hypothesis off by {best}°");
    for (rr, tt) in &hs {
        assert!((rr.determinant() - 1.0).abs() < 1e-9);
        assert!((rr * rr.transpose() - Matrix3::identity()).norm() < 1e-9);
        assert!((tt.norm() - 1.0).abs() < 1e-12);
    }
    let tx = t.cross_matrix();
    let e = tx * r.matrix() * 0.3;
    let es = decompose_essential(&e).unwrap();
    let best = es
        .iter()
        .map(|(rr, tt)| rot_err_deg(&Rotation3::from_matrix(rr), &r).max(dir_err_deg(tt, &t)))
        .fold(f64::INFINITY, f64::min);
    assert!(best < 1e-4, "essential: best hypothesis off by {best}°");
}

#[test]
fn triangulation_is_exact_without_noise_and_within_1pct_with_half_pixel() {
    let (r, c2) = (
        Rotation3::from_euler_angles(0.02, -0.1, 0.01),
        Vector3::new(0.8, 0.05, 0.1),
    );
    let t = -(r * c2);
    let p1 = projection_matrix(&K, &Matrix3::identity(), &Vector3::zeros());
    let p2 = projection_matrix(&K, r.matrix(), &t);
    let s = scene(SceneKind::General, r, c2, 500, 0.0, (0.0, 0.0), 7);
    let mut worst: f64 = 0.0;
    for i in 0..s.x1.len() {
        let x = triangulate(&p1, &p2, &s.x1[i], &s.x2[i]).unwrap();
        worst = worst.max((x - s.points[i]).norm() / s.points[i].norm());
        assert!(reprojection_error_sq(&p1, &x, &s.x1[i]).unwrap() < 1e-12);
        assert!(reprojection_error_sq(&p2, &x, &s.x2[i]).unwrap() < 1e-12);
    }
    println!("noise-free triangulation: worst relative error {worst:.3e}");
    assert!(worst < 1e-9, "worst relative error {worst}");

    let s = scene(SceneKind::General, r, c2, 500, 0.0, (0.5, 0.5), 8);
    let rel: Vec<f64> = (0..s.x1.len())
        .map(|i| {
            let x = triangulate(&p1, &p2, &s.x1[i], &s.x2[i]).unwrap();
            (x - s.points[i]).norm() / s.points[i].norm()
        })
        .collect();
    let pars: Vec<f64> = s
        .points
        .iter()
        .map(|p| parallax_deg(p, &Vector3::zeros(), &c2))
        .collect();
    let med = median(rel);
    println!(
        "0.5 px triangulation: median relative error {med:.4}, median parallax {:.2}°",
        median(pars)
    );
    assert!(med < 0.01, "median relative error {med}");
}

#[test]
fn parallax_helper() {
    let p = Vector3::new(0.0, 0.0, 1.0);
    let a = parallax_deg(
        &p,
        &Vector3::new(-1.0, 0.0, 0.0),
        &Vector3::new(1.0, 0.0, 0.0),
    );
    assert!((a - 90.0).abs() < 1e-9);
    assert!(parallax_deg(&p, &Vector3::zeros(), &Vector3::new(0.0, 0.0, -1.0)).abs() < 1e-6);
}

struct Sim3Case {
    truth: Sim3,
    p1: Vec<Vector3<f64>>,
    p2: Vec<Vector3<f64>>,
    uv1: Vec<Vector2<f64>>,
    uv2: Vec<Vector2<f64>>,
    outlier: Vec<bool>,
}

/// 200 correspondences `p2 = S·p1` (scale 2.3, 30° rotation) with 3 mm point noise in camera 1 (6.9 mm in camera 2),
/// 0.5 px keypoint noise, and 30 % outliers (a wrong point in camera 2, observed where it is).
fn sim3_case(seed: u64) -> Sim3Case {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let truth = Sim3 {
        rotation: Rotation3::from_scaled_axis(
            Vector3::new(0.2, 1.0, -0.1).normalize() * 30f64.to_radians(),
        ),
        translation: Vector3::new(0.5, -0.2, 1.0),
        scale: 2.3,
    };
    let px = Normal::new(0.0, 0.5).unwrap();
    let mm = Normal::new(0.0, 0.003).unwrap();
    let mut c = Sim3Case {
        truth,
        p1: vec![],
        p2: vec![],
        uv1: vec![],
        uv2: vec![],
        outlier: vec![],
    };
    while c.p1.len() < 200 {
        let p = Vector3::new(
            rng.random_range(-2.0..2.0),
            rng.random_range(-1.5..1.5),
            rng.random_range(2.0..6.0),
        );
        let q = truth.transform_point(&p);
        let (Some(a), Some(b)) = (K.project(&p), K.project(&q)) else {
            continue;
        };
        let is_out = rng.random::<f64>() < 0.3;
        let noise3 =
            |rng: &mut ChaCha8Rng| Vector3::new(mm.sample(rng), mm.sample(rng), mm.sample(rng));
        let noise2 = |rng: &mut ChaCha8Rng| Vector2::new(px.sample(rng), px.sample(rng));
        let (q, b) = if is_out {
            // A mismatch: another point of camera 2's view.
            let q = Vector3::new(
                rng.random_range(-4.0..6.0),
                rng.random_range(-3.0..3.0),
                rng.random_range(4.0..14.0),
            );
            let Some(b) = K.project(&q) else { continue };
            (q, b)
        } else {
            (q, b)
        };
        c.p1.push(p + noise3(&mut rng));
        c.p2.push(q + noise3(&mut rng) * truth.scale);
        c.uv1.push(a + noise2(&mut rng));
        c.uv2.push(b + noise2(&mut rng));
        c.outlier.push(is_out);
    }
    c
}

#[test]
fn sim3_ransac_recovers_similarity_and_flags_outliers() {
    let c = sim3_case(11);
    let params = Sim3RansacParams {
        seed: 5,
        ..Default::default()
    };
    let t0 = std::time::Instant::now();
    let (s, inl) = sim3_ransac(&c.p1, &c.p2, &c.uv1, &c.uv2, &K, &K, &params).unwrap();
    let dt = t0.elapsed();
    let rot = rot_err_deg(&s.rotation, &c.truth.rotation);
    let scale = (s.scale / c.truth.scale - 1.0).abs();
    let n_out = c.outlier.iter().filter(|o| **o).count();
    let out_kept = (0..200).filter(|&i| c.outlier[i] && inl[i]).count();
    let in_lost = (0..200).filter(|&i| !c.outlier[i] && !inl[i]).count();
    println!(
        "sim3: rotation err {rot:.4}°, scale err {:.4} %, translation err {:.4}, outliers kept \
         {out_kept} / {n_out}, true matches lost {in_lost} / {}, {:.2} ms",
        scale * 100.0,
        (s.translation - c.truth.translation).norm(),
        200 - n_out,
        dt.as_secs_f64() * 1e3
    );
    assert!(rot < 0.1, "rotation error {rot}°");
    assert!(scale < 0.005, "scale error {scale}");
    assert_eq!(out_kept, 0, "outliers kept");
    assert!(in_lost * 20 <= 200 - n_out, "{in_lost} true matches lost");
    // Below min_inliers → None.
    let strict = Sim3RansacParams {
        min_inliers: 200,
        ..params
    };
    assert!(sim3_ransac(&c.p1, &c.p2, &c.uv1, &c.uv2, &K, &K, &strict).is_none());
}

#[test]
fn same_input_and_seed_give_identical_output() {
    let (r, c2) = moderate_motion();
    for kind in [SceneKind::Planar, SceneKind::General] {
        let s = scene(kind, r, c2, 300, 0.2, (0.0, 1.0), 9);
        let params = TwoViewParams {
            seed: 42,
            ..Default::default()
        };
        let a = initialize_two_view(&s.x1, &s.x2, &K, &params).unwrap();
        let b = initialize_two_view(&s.x1, &s.x2, &K, &params).unwrap();
        assert_eq!(a, b);
        // Bitwise, not only PartialEq on floats.
        assert_eq!(
            a.matrix
                .as_slice()
                .iter()
                .map(|v| v.to_bits())
                .collect::<Vec<_>>(),
            b.matrix
                .as_slice()
                .iter()
                .map(|v| v.to_bits())
                .collect::<Vec<_>>()
        );
        // Another seed draws other minimal sets: the model differs (the test can tell).
        let other = TwoViewParams {
            seed: 43,
            refine: false,
            ..params
        };
        let same_seed_no_refine = TwoViewParams {
            refine: false,
            ..params
        };
        let c = initialize_two_view(&s.x1, &s.x2, &K, &other);
        let d = initialize_two_view(&s.x1, &s.x2, &K, &same_seed_no_refine);
        let (c, d) = (c.map(|r| r.matrix), d.map(|r| r.matrix));
        assert!(c.is_err() || d.is_err() || c.unwrap() != d.unwrap());
    }
    let c = sim3_case(12);
    let params = Sim3RansacParams {
        seed: 9,
        ..Default::default()
    };
    let a = sim3_ransac(&c.p1, &c.p2, &c.uv1, &c.uv2, &K, &K, &params).unwrap();
    let b = sim3_ransac(&c.p1, &c.p2, &c.uv1, &c.uv2, &K, &K, &params).unwrap();
    assert_eq!(a, b);
}

/// Prints the time per call (a number to read, not to assert: tests never assert on time);
/// asserts only that 500 matches of a good pair initialise.
#[test]
fn timing_500_matches() {
    let (r, c2) = moderate_motion();
    for (name, kind) in [
        ("planar", SceneKind::Planar),
        ("general", SceneKind::General),
    ] {
        let s = scene(kind, r, c2, 500, 0.2, (0.0, 1.0), 13);
        let params = TwoViewParams::default();
        let t0 = std::time::Instant::now();
        let runs = 5;
        let mut ok = 0;
        for _ in 0..runs {
            ok += initialize_two_view(&s.x1, &s.x2, &K, &params).is_ok() as usize;
        }
        let ms = t0.elapsed().as_secs_f64() * 1e3 / runs as f64;
        println!("initialize_two_view, 500 matches, 200 iterations ({name}): {ms:.1} ms per call");
        assert_eq!(ok, runs);
    }
}
