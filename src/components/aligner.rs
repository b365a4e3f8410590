//! Aligner (paper Table I): (map points, keypoints) → pose + inliers. Stateless functions over
//! plain data, used by the tracker's fallbacks, the relocalizer and the loop validator.
//!
//! - [`pnp_ransac`]: 3-D points ↔ undistorted pixels, OpenCV's `solvePnPRansac` (EPnP minimal
//!   sets, refined on the inliers) — the best-kept implementation at hand.
//! - [`rigid_ransac`]: 3-D ↔ 3-D (RGB-D on both sides), RANSAC over 3-point Umeyama fits, refit
//!   on the inliers; deterministic (seeded).

use crate::error::{Error, Result};
use crate::geometry::umeyama;
use nalgebra::{Isometry3, Point3, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3};
use opencv::core::{Mat, Point2d, Point3d, Vector};
use opencv::prelude::*;
use rand::{Rng, SeedableRng};

pub use crate::optim::Intrinsics;

/// Back-projects an undistorted pixel with a depth (metres) into camera coordinates.
pub fn backproject(k: &Intrinsics, uv: &Vector2<f64>, depth: f64) -> Vector3<f64> {
    Vector3::new(
        (uv.x - k.cx) / k.fx * depth,
        (uv.y - k.cy) / k.fy * depth,
        depth,
    )
}

/// Result of an alignment: world-to-camera pose (PnP) or source-to-target transform (3D-3D).
#[derive(Debug, Clone)]
pub struct Alignment {
    pub pose: Isometry3<f64>,
    pub inliers: Vec<bool>,
    pub n_inliers: usize,
    /// RMS error over the inliers (pixels for PnP, metres for 3D-3D).
    pub rms: f64,
}

/// PnP RANSAC: finds T_cw with `project(T_cw · X_i) ≈ uv_i`. `None` when fewer than 6
/// correspondences or RANSAC finds no model with at least `min_inliers`.
pub fn pnp_ransac(
    points_w: &[Vector3<f64>],
    uv: &[Vector2<f64>],
    k: &Intrinsics,
    threshold_px: f64,
    min_inliers: usize,
) -> Result<Option<Alignment>> {
    if points_w.len() != uv.len() {
        return Err(Error::invalid(
            "pnp_ransac: point and pixel lists differ in length",
        ));
    }
    if points_w.len() < 6 {
        return Ok(None);
    }
    let cv = |e: opencv::Error| Error::invalid(format!("OpenCV solvePnPRansac: {e}"));
    let obj = Vector::<Point3d>::from_iter(points_w.iter().map(|p| Point3d::new(p.x, p.y, p.z)));
    let img = Vector::<Point2d>::from_iter(uv.iter().map(|p| Point2d::new(p.x, p.y)));
    let kmat =
        Mat::from_slice_2d(&[[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]]).map_err(cv)?;
    let mut rvec = Mat::default();
    let mut tvec = Mat::default();
    let mut inl = Vector::<i32>::new();
    // OpenCV seeds its RANSAC RNG itself (fixed state per call), so this is deterministic.
    let ok = opencv::calib3d::solve_pnp_ransac(
        &obj,
        &img,
        &kmat,
        &opencv::core::no_array(),
        &mut rvec,
        &mut tvec,
        false,
        200,
        threshold_px as f32,
        0.99,
        &mut inl,
        opencv::calib3d::SOLVEPNP_EPNP,
    )
    .map_err(cv)?;
    if !ok || (inl.len()) < min_inliers {
        return Ok(None);
    }
    let r = |m: &Mat, i: i32| -> Result<f64> { m.at::<f64>(i).copied().map_err(cv) };
    let rv = Vector3::new(r(&rvec, 0)?, r(&rvec, 1)?, r(&rvec, 2)?);
    let tv = Vector3::new(r(&tvec, 0)?, r(&tvec, 1)?, r(&tvec, 2)?);
    let pose = Isometry3::from_parts(
        Translation3::from(tv),
        UnitQuaternion::from_rotation_matrix(&Rotation3::new(rv)),
    );
    let mut inliers = vec![false; points_w.len()];
    let mut sse = 0.0;
    let mut n = 0;
    for (i, (p, u)) in points_w.iter().zip(uv).enumerate() {
        let Some(proj) = k.project(&(pose * Point3::from(*p)).coords) else {
            continue;
        };
        let e = (proj - u).norm();
        if e <= threshold_px {
            inliers[i] = true;
            sse += e * e;
            n += 1;
        }
    }
    if n < min_inliers {
        return Ok(None);
    }
    Ok(Some(Alignment {
        pose,
        inliers,
        n_inliers: n,
        rms: (sse / n as f64).sqrt(),
    }))
}

/// 3D-3D RANSAC: finds T with `T · src_i ≈ dst_i` (rigid), using minimal 3-point Umeyama fits,
/// then refits on the inliers. `threshold` in metres; `seed` makes it deterministic.
pub fn rigid_ransac(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    threshold: f64,
    min_inliers: usize,
    iterations: usize,
    seed: u64,
) -> Option<Alignment> {
    let n = src.len();
    if n < 3 || dst.len() != n {
        return None;
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let count = |t: &crate::geometry::Sim3| {
        src.iter()
            .zip(dst)
            .filter(|(s, d)| (t.transform_point(s) - *d).norm() <= threshold)
            .count()
    };
    let mut best: Option<(usize, crate::geometry::Sim3)> = None;
    for _ in 0..iterations {
        let i = rng.random_range(0..n);
        let j = rng.random_range(0..n);
        let l = rng.random_range(0..n);
        if i == j || j == l || i == l {
            continue;
        }
        let Some(t) = umeyama(&[src[i], src[j], src[l]], &[dst[i], dst[j], dst[l]], false) else {
            continue;
        };
        let c = count(&t);
        if best.as_ref().is_none_or(|(b, _)| c > *b) {
            best = Some((c, t));
        }
    }
    let (_, mut t) = best?;
    // Refit on the inliers twice (the inlier set can grow after the first refit).
    for _ in 0..2 {
        let (s, d): (Vec<_>, Vec<_>) = src
            .iter()
            .zip(dst)
            .filter(|(s, d)| (t.transform_point(s) - *d).norm() <= threshold)
            .map(|(s, d)| (*s, *d))
            .unzip();
        t = umeyama(&s, &d, false)?;
    }
    let errs: Vec<f64> = src
        .iter()
        .zip(dst)
        .map(|(s, d)| (t.transform_point(s) - d).norm())
        .collect();
    let inliers: Vec<bool> = errs.iter().map(|&e| e <= threshold).collect();
    let n_in = inliers.iter().filter(|&&b| b).count();
    if n_in < min_inliers {
        return None;
    }
    let sse: f64 = errs
        .iter()
        .filter(|&&e| e <= threshold)
        .map(|e| e * e)
        .sum();
    Some(Alignment {
        pose: Isometry3::from_parts(
            Translation3::from(t.translation),
            UnitQuaternion::from_rotation_matrix(&t.rotation),
        ),
        inliers,
        n_inliers: n_in,
        rms: (sse / n_in as f64).sqrt(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(n: usize, seed: u64) -> Vec<Vector3<f64>> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                Vector3::new(
                    rng.random_range(-2.0..2.0),
                    rng.random_range(-1.5..1.5),
                    rng.random_range(2.0..6.0),
                )
            })
            .collect()
    }

    #[test]
    fn pnp_recovers_pose_with_outliers() {
        let k = Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
            bf: 40.0,
        };
        let truth = Isometry3::new(Vector3::new(0.1, -0.2, 0.3), Vector3::new(0.05, -0.1, 0.02));
        let pts = scene(200, 1);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        let uv: Vec<Vector2<f64>> = pts
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let pc = truth * Point3::from(*p);
                if i % 4 == 0 {
                    Vector2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0))
                } else {
                    k.project(&pc.coords).unwrap()
                        + Vector2::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5))
                }
            })
            .collect();
        let a = pnp_ransac(&pts, &uv, &k, 2.0, 50).unwrap().unwrap();
        assert!((a.pose.translation.vector - truth.translation.vector).norm() < 0.01);
        assert!(a.pose.rotation.angle_to(&truth.rotation) < 0.005);
        assert!(a.n_inliers >= 140 && a.inliers.iter().step_by(4).filter(|&&b| b).count() < 5);
        assert!(
            pnp_ransac(&pts[..4], &uv[..4], &k, 2.0, 3)
                .unwrap()
                .is_none()
        );
    }

    #[test]
    fn rigid_ransac_recovers_transform() {
        let truth = Isometry3::new(Vector3::new(0.5, 0.1, -0.3), Vector3::new(0.2, 0.4, -0.1));
        let src = scene(100, 3);
        let mut dst: Vec<Vector3<f64>> = src
            .iter()
            .map(|p| (truth * Point3::from(*p)).coords)
            .collect();
        for d in dst.iter_mut().step_by(3) {
            *d += Vector3::new(1.0, -1.0, 0.5);
        }
        let a = rigid_ransac(&src, &dst, 0.02, 30, 200, 7).unwrap();
        assert!((a.pose.translation.vector - truth.translation.vector).norm() < 1e-9);
        assert_eq!(a.n_inliers, 100 - 34);
    }
}
