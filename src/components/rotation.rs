//! Rotation-only camera motion between two monocular views (part of the Tracker, paper Table I).
//!
//! # Why
//! Turning in place gives no parallax: without depth no new point can be triangulated, and the
//! mapped points leave the view as the camera turns. The tracker then has too few 3-D points,
//! but the key points of the last tracked frame still constrain the *rotation*: under a pure
//! rotation `R` a bearing `b` seen in one view is seen as `R b` in the other, whatever its depth
//! (points at infinity, the homography `K R K⁻¹`). So a frame that the map no longer holds can
//! still be posed: the rotation from key-point matches, the position kept (Pirchheim et al.,
//! "Handling pure camera rotation in keyframe-based SLAM", 2013; Gauglitz et al. 2012).
//!
//! # How
//! Matches are searched where the predicted rotation puts each key point of the anchor view
//! (grid search, descriptor distance and ratio, orientation consistency), the rotation comes from
//! a two-bearing RANSAC (Kabsch), and it is refined on all inliers. A match is an inlier when the
//! rotated bearing reprojects within the χ² (2 dof, 95 %) gate of its pyramid level. A camera
//! that translates shows it as matches the rotation cannot explain: the inlier fraction is
//! reported, and the tracker refuses a rotation that explains too few of them.

use crate::components::aligner::backproject;
use crate::components::preprocess::{ImageGeometry, Measurement, match_in_areas};
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// χ² 95 % quantile, 2 dof: the reprojection gate of an inlier, in units of its level's σ².
const CHI2_2DOF: f64 = 5.991;
/// Largest Hamming distance of a match (ORB-SLAM's TH_LOW) and Lowe's ratio.
const MAX_DISTANCE: u32 = 50;
const RATIO: f64 = 0.8;
/// RANSAC iterations; two bearings fix a rotation, so few are needed even at half outliers.
const ITERATIONS: usize = 64;

/// What [`estimate`] found.
#[derive(Debug, Clone)]
pub struct RotationEstimate {
    /// Rotation of camera coordinates from the anchor view to the current one:
    /// `b_current ≈ rotation · b_anchor`.
    pub rotation: UnitQuaternion<f64>,
    /// Matches found by the search.
    pub matches: usize,
    /// Matches the rotation explains.
    pub inliers: usize,
    /// Mean χ² (squared reprojection error over the level's σ²) of the inliers.
    pub mean_chi2: f64,
}

impl RotationEstimate {
    /// Fraction of the matches the rotation explains: close to 1 for a rotation (noise and
    /// wrong matches aside), lower when the camera also moved and near points show parallax.
    pub fn inlier_fraction(&self) -> f64 {
        self.inliers as f64 / self.matches.max(1) as f64
    }
}

/// Unit bearing of an undistorted pixel.
fn bearing(geo: &ImageGeometry, un: &Vector2<f64>) -> Vector3<f64> {
    backproject(&geo.intr, un, 1.0).normalize()
}

/// The pixel of a camera-frame direction, if it is in front of the camera and in the image.
fn project(geo: &ImageGeometry, d: &Vector3<f64>) -> Option<Vector2<f64>> {
    let p = geo.intr.project(d)?;
    (p.x >= 0.0 && p.y >= 0.0 && p.x < geo.width && p.y < geo.height).then_some(p)
}

/// The rotation that best maps bearings `a` onto `b` (least squares on unit vectors, Kabsch).
fn kabsch(pairs: impl Iterator<Item = (Vector3<f64>, Vector3<f64>)>) -> Option<Rotation3<f64>> {
    let mut m = Matrix3::zeros();
    for (a, b) in pairs {
        m += b * a.transpose();
    }
    let svd = m.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let d = (u * vt).determinant().signum();
    let r = u * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * vt;
    r.iter()
        .all(|x| x.is_finite())
        .then(|| Rotation3::from_matrix_unchecked(r))
}

/// The rotation from `anchor` to `m`, searching each anchor key point within `radius_px` (at
/// level 0, growing with the level) of where `predicted` puts it. `None` with fewer than
/// `min_inliers` inliers.
pub fn estimate(
    anchor: &Measurement,
    m: &Measurement,
    geo: &ImageGeometry,
    predicted: &UnitQuaternion<f64>,
    radius_px: f64,
    min_inliers: usize,
) -> Option<RotationEstimate> {
    let anchor_bearings: Vec<Vector3<f64>> = anchor
        .keypoints
        .iter()
        .map(|k| bearing(geo, &k.un))
        .collect();
    let pairs = match_in_areas(
        anchor,
        m,
        |a| {
            let p = project(geo, &(predicted * anchor_bearings[a]))?;
            Some((
                p,
                radius_px * geo.scales[anchor.keypoints[a].octave as usize],
            ))
        },
        MAX_DISTANCE,
        RATIO,
    );
    if pairs.len() < min_inliers.max(2) {
        return None;
    }
    let a: Vec<Vector3<f64>> = pairs.iter().map(|&(i, _)| anchor_bearings[i]).collect();
    let b: Vec<Vector2<f64>> = pairs.iter().map(|&(_, j)| m.keypoints[j].un).collect();
    let sigma2: Vec<f64> = pairs
        .iter()
        .map(|&(_, j)| geo.scales[m.keypoints[j].octave as usize].powi(2))
        .collect();
    let bb: Vec<Vector3<f64>> = b.iter().map(|u| bearing(geo, u)).collect();
    // χ² of each pair under a rotation (∞ behind the camera).
    let chi2 = |r: &Rotation3<f64>, i: usize| -> f64 {
        geo.intr
            .project(&(r * a[i]))
            .map_or(f64::INFINITY, |p| (p - b[i]).norm_squared() / sigma2[i])
    };
    let inliers_of = |r: &Rotation3<f64>| -> Vec<usize> {
        (0..a.len()).filter(|&i| chi2(r, i) <= CHI2_2DOF).collect()
    };
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut best_inl: Vec<usize> = Vec::new();
    for _ in 0..ITERATIONS {
        let i = rng.random_range(0..a.len());
        let j = rng.random_range(0..a.len());
        if i == j {
            continue;
        }
        let Some(r) = kabsch([(a[i], bb[i]), (a[j], bb[j])].into_iter()) else {
            continue;
        };
        let inl = inliers_of(&r);
        if inl.len() > best_inl.len() {
            best_inl = inl;
        }
    }
    let mut rotation = None;
    for _ in 0..3 {
        if best_inl.len() < min_inliers.max(2) {
            return None;
        }
        let r = kabsch(best_inl.iter().map(|&i| (a[i], bb[i])))?;
        let inl = inliers_of(&r);
        let same = inl == best_inl;
        best_inl = inl;
        rotation = Some(r);
        if same {
            break;
        }
    }
    let r = rotation?;
    if best_inl.len() < min_inliers {
        return None;
    }
    let mean_chi2 = best_inl.iter().map(|&i| chi2(&r, i)).sum::<f64>() / best_inl.len() as f64;
    Some(RotationEstimate {
        rotation: UnitQuaternion::from_rotation_matrix(&r),
        matches: pairs.len(),
        inliers: best_inl.len(),
        mean_chi2,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::Intrinsics;
    use nalgebra::{Isometry3, Point3, Translation3};

    /// 300 points 1–5 m in front of the anchor camera (the world frame), each with its own
    /// random descriptor, seen by the anchor and by a camera at `pose_cw`: the anchor's and the
    /// other view's measurements (points out of either image are left out of both).
    fn views(pose_cw: &Isometry3<f64>, geo: &ImageGeometry) -> (Measurement, Measurement) {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let k = geo.intr;
        let (mut a, mut b, mut d) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..300 {
            let z = rng.random_range(1.0..5.0);
            let u = rng.random_range(40.0..600.0);
            let v = rng.random_range(40.0..440.0);
            let p = Point3::new((u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z);
            let q = pose_cw * p;
            let Some(uv) = project(geo, &q.coords) else {
                continue;
            };
            let mut desc = [0u8; 32];
            rng.fill(&mut desc[..]);
            a.push(Vector2::new(u, v));
            b.push(uv);
            d.push(desc);
        }
        (
            Measurement::synthetic(0, a, 0.0, 0.0, d.clone()),
            Measurement::synthetic(1, b, 0.0, 0.0, d),
        )
    }

    fn geo() -> ImageGeometry {
        ImageGeometry::new(Intrinsics::TUM_FREIBURG1, 640, 480, 1.2, 8)
    }

    /// A pure rotation is recovered from the matches, whatever the points' depths, from a
    /// prediction 1° off; every match is explained.
    #[test]
    fn a_pure_rotation_is_recovered_from_the_key_points() {
        let geo = geo();
        let truth = UnitQuaternion::from_euler_angles(0.02, 0.15, -0.03);
        let (anchor, m) = views(
            &Isometry3::from_parts(Translation3::identity(), truth),
            &geo,
        );
        let predicted = UnitQuaternion::from_euler_angles(0.0, 0.15 + 1f64.to_radians(), 0.0);
        let est = estimate(&anchor, &m, &geo, &predicted, 30.0, 50).expect("a rotation");
        let err = est.rotation.angle_to(&truth).to_degrees();
        assert!(err < 0.01, "rotation {err} deg off");
        assert_eq!(est.inliers, est.matches);
        assert!(est.matches as f64 >= 0.9 * anchor.len() as f64, "{est:?}");
        assert!(est.mean_chi2 < 1e-6, "{est:?}");
    }

    /// A camera that also moved 20 cm sideways: the near points show parallax the rotation
    /// cannot explain. The estimate is refused, or explains clearly worse than noise.
    #[test]
    fn a_moving_camera_is_not_explained_by_a_rotation() {
        let geo = geo();
        let rot = UnitQuaternion::from_euler_angles(0.0, 0.1, 0.0);
        let pose = Isometry3::from_parts(Translation3::new(0.2, 0.0, 0.0), rot);
        let (anchor, m) = views(&pose, &geo);
        match estimate(&anchor, &m, &geo, &rot, 30.0, 50) {
            None => {}
            Some(est) => assert!(
                est.inlier_fraction() < 0.8 || est.mean_chi2 > 1.0,
                "a translation passed for a rotation: {est:?}"
            ),
        }
    }
}
