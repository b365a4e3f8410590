//! Reprojection residuals, their analytic Jacobians and the robust kernel.
//!
//! Two observation kinds, as in ORB-SLAM:
//! - [`Observation::Mono`]: a keypoint `uv`; residual `uv − π(T_cw·X)` (2-D).
//! - [`Observation::Rgbd`]: a keypoint with measured depth. Following ORB-SLAM's RGB-D mode,
//!   depth is turned into a *virtual right-image* coordinate `u_r = u − bf/depth`, so the
//!   residual is `(u, v, u_r) − (π_u(X_c), π_v(X_c), π_u(X_c) − bf/z_c)` (3-D). Expressing depth
//!   as a disparity makes its noise roughly pixel-like (depth error grows with z²) and lets
//!   the same isotropic information `1/σ²` weight all three rows.
//!
//! Jacobians are with respect to the left pose perturbation δ = (ω, υ) of the
//! world-to-camera pose (see [`super::se3`]) and to the world point.

use nalgebra::{Isometry3, Matrix3, Matrix3x6, Point3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// χ² quantile (95 %) for 2 degrees of freedom: ORB-SLAM's mono outlier threshold, also
/// used as the Huber δ² for mono residuals.
pub const CHI2_MONO: f64 = 5.991;
/// χ² quantile (95 %) for 3 degrees of freedom: the RGB-D/stereo threshold and Huber δ².
pub const CHI2_RGBD: f64 = 7.815;
/// ORB pyramid scale factor; an octave-`o` keypoint has σ = 1.2^o pixels.
pub const ORB_SCALE_FACTOR: f64 = 1.2;
/// Points closer than this to the camera plane (in camera z, metres) cannot be projected;
/// their observations are treated as invalid instead of producing huge or NaN residuals.
pub const MIN_DEPTH: f64 = 1e-6;

/// Pinhole intrinsics for undistorted keypoints, plus the RGB-D virtual baseline.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// `fx · baseline` (pixels·metres) used to convert depth into a virtual right
    /// coordinate; ORB-SLAM's TUM configurations use 40 (≈ fx · 0.08 m). Only
    /// [`Observation::Rgbd`] uses it.
    pub bf: f64,
}

impl Intrinsics {
    /// The TUM freiburg1 Kinect with ORB-SLAM's virtual baseline (bf = 40): a realistic
    /// camera for tests and examples.
    pub const TUM_FREIBURG1: Intrinsics = Intrinsics {
        fx: 517.3,
        fy: 516.5,
        cx: 318.6,
        cy: 255.3,
        bf: 40.0,
    };

    /// Pixel projection of a camera-frame point, `None` if it is not in front of the camera.
    pub fn project(&self, p_c: &Vector3<f64>) -> Option<Vector2<f64>> {
        if p_c.z.is_nan() || p_c.z <= MIN_DEPTH {
            return None;
        }
        let iz = 1.0 / p_c.z;
        Some(Vector2::new(
            self.fx * p_c.x * iz + self.cx,
            self.fy * p_c.y * iz + self.cy,
        ))
    }
}

/// One measurement of a 3-D point in an image.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Observation {
    /// Undistorted keypoint position in pixels.
    Mono { uv: Vector2<f64> },
    /// Keypoint plus its measured depth (metres, > 0).
    Rgbd { uv: Vector2<f64>, depth: f64 },
}

/// Residual and Jacobians of one observation at one linearisation point.
///
/// Rows beyond [`Observation::dim`] are zero for mono observations, which lets mono and
/// RGB-D residuals share fixed-size 3-row storage without changing any normal-equation sum.
#[derive(Debug, Clone, Copy)]
pub struct Linearization {
    /// `measurement − prediction`.
    pub residual: Vector3<f64>,
    /// ∂residual/∂δ for the left pose perturbation δ = (ω, υ).
    pub jac_pose: Matrix3x6<f64>,
    /// ∂residual/∂X_w.
    pub jac_point: Matrix3<f64>,
}

impl Observation {
    /// Residual dimension: 2 for mono, 3 for RGB-D.
    pub fn dim(&self) -> usize {
        match self {
            Observation::Mono { .. } => 2,
            Observation::Rgbd { .. } => 3,
        }
    }

    /// The 95 % χ² threshold for this residual's dimension ([`CHI2_MONO`] / [`CHI2_RGBD`]).
    pub fn chi2_threshold(&self) -> f64 {
        match self {
            Observation::Mono { .. } => CHI2_MONO,
            Observation::Rgbd { .. } => CHI2_RGBD,
        }
    }

    /// The measurement vector (`(u, v, 0)` for mono, `(u, v, u_r)` for RGB-D).
    fn measurement(&self, intr: &Intrinsics) -> Vector3<f64> {
        match *self {
            Observation::Mono { uv } => Vector3::new(uv.x, uv.y, 0.0),
            Observation::Rgbd { uv, depth } => Vector3::new(uv.x, uv.y, uv.x - intr.bf / depth),
        }
    }

    /// Residual `measurement − prediction` for a camera-frame point, `None` if the point
    /// is not in front of the camera (or the measured depth is not positive and finite).
    pub fn residual_camera(&self, intr: &Intrinsics, p_c: &Vector3<f64>) -> Option<Vector3<f64>> {
        let uv = intr.project(p_c)?;
        let pred = match *self {
            Observation::Mono { .. } => Vector3::new(uv.x, uv.y, 0.0),
            Observation::Rgbd { depth, .. } => {
                if !(depth > 0.0 && depth.is_finite()) {
                    return None;
                }
                Vector3::new(uv.x, uv.y, uv.x - intr.bf / p_c.z)
            }
        };
        let r = self.measurement(intr) - pred;
        r.iter().all(|x| x.is_finite()).then_some(r)
    }

    /// Residual for a world point seen from world-to-camera pose `pose_cw`.
    pub fn residual(
        &self,
        intr: &Intrinsics,
        pose_cw: &Isometry3<f64>,
        point_w: &Vector3<f64>,
    ) -> Option<Vector3<f64>> {
        let p_c = (pose_cw * Point3::from(*point_w)).coords;
        self.residual_camera(intr, &p_c)
    }

    /// Residual and analytic Jacobians, `None` where [`Observation::residual`] is `None`.
    pub fn linearize(
        &self,
        intr: &Intrinsics,
        pose_cw: &Isometry3<f64>,
        point_w: &Vector3<f64>,
    ) -> Option<Linearization> {
        let p_c = (pose_cw * Point3::from(*point_w)).coords;
        let residual = self.residual_camera(intr, &p_c)?;
        let (x, y, z) = (p_c.x, p_c.y, p_c.z);
        let iz = 1.0 / z;
        let iz2 = iz * iz;
        // ∂prediction/∂X_c; the residual Jacobian is its negative.
        let mut d_pred = Matrix3::new(
            intr.fx * iz,
            0.0,
            -intr.fx * x * iz2,
            0.0,
            intr.fy * iz,
            -intr.fy * y * iz2,
            0.0,
            0.0,
            0.0,
        );
        if let Observation::Rgbd { .. } = self {
            // u_r = u − bf/z  ⇒  ∂u_r/∂X_c = ∂u/∂X_c + (0, 0, bf/z²).
            d_pred[(2, 0)] = d_pred[(0, 0)];
            d_pred[(2, 2)] = d_pred[(0, 2)] + intr.bf * iz2;
        }
        let jac_point_c = -d_pred;
        // ∂X_c/∂δ = [-[X_c]ₓ | I] (left perturbation), ∂X_c/∂X_w = R_cw.
        let mut dxc_dpose = Matrix3x6::zeros();
        dxc_dpose
            .fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(-super::se3::skew(&p_c)));
        dxc_dpose
            .fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&Matrix3::identity());
        let rot = pose_cw.rotation.to_rotation_matrix();
        Some(Linearization {
            residual,
            jac_pose: jac_point_c * dxc_dpose,
            jac_point: jac_point_c * rot.matrix(),
        })
    }
}

impl Observation {
    /// Residual of a point seen through an extra camera motion `shutter` applied after the
    /// pose (`X_c = shutter · T_cw · X`): a rolling-shutter row exposed slightly before or
    /// after the frame's reference time. The identity gives [`Observation::residual`].
    pub fn residual_through(
        &self,
        intr: &Intrinsics,
        shutter: &Isometry3<f64>,
        pose_cw: &Isometry3<f64>,
        point_w: &Vector3<f64>,
    ) -> Option<Vector3<f64>> {
        self.residual(intr, &(shutter * pose_cw), point_w)
    }

    /// [`Observation::linearize`] through `shutter`, still with respect to the left
    /// perturbation of `pose_cw`: `S·exp(δ)·T = exp(Ad_S δ)·S·T`, so `J_δ = J_{δ'} · Ad_S`.
    pub fn linearize_through(
        &self,
        intr: &Intrinsics,
        shutter: &Isometry3<f64>,
        pose_cw: &Isometry3<f64>,
        point_w: &Vector3<f64>,
    ) -> Option<Linearization> {
        let mut lin = self.linearize(intr, &(shutter * pose_cw), point_w)?;
        if *shutter != Isometry3::identity() {
            lin.jac_pose *= super::se3::adjoint(shutter);
        }
        Some(lin)
    }
}

/// Information weight ORB-SLAM gives a keypoint detected at pyramid `octave`:
/// `1/σ²` with σ = 1.2^octave pixels.
pub fn octave_information(octave: u32) -> f64 {
    ORB_SCALE_FACTOR.powi(-2 * octave as i32)
}

/// Huber kernel on the *weighted squared error* `chi2 = info · |r|²` (g2o's convention,
/// which ORB-SLAM uses with δ² = [`CHI2_MONO`] or [`CHI2_RGBD`]).
///
/// Returns `(ρ(chi2), ρ'(chi2))`: the robust cost and the IRLS weight that multiplies the
/// observation's information in the normal equations. Quadratic below δ², linear in
/// `√chi2` above it, so a gross outlier pulls with bounded force.
pub fn huber(chi2: f64, delta2: f64) -> (f64, f64) {
    if chi2 <= delta2 {
        (chi2, 1.0)
    } else {
        let e = chi2.sqrt();
        let delta = delta2.sqrt();
        (2.0 * delta * e - delta2, delta / e)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::se3;
    use nalgebra::{Vector3, Vector6};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    const INTR: Intrinsics = Intrinsics::TUM_FREIBURG1;

    fn random_setup(rng: &mut ChaCha8Rng) -> (Isometry3<f64>, Vector3<f64>) {
        let d = Vector6::from_fn(|_, _| rng.random_range(-1.0..1.0));
        let pose = se3::exp(&d);
        // A point in front of the camera, mapped back into the world.
        let p_c = Vector3::new(
            rng.random_range(-1.5..1.5),
            rng.random_range(-1.0..1.0),
            rng.random_range(0.5..6.0),
        );
        let p_w = pose.inverse() * Point3::from(p_c);
        (pose, p_w.coords)
    }

    fn rel_err(a: f64, b: f64) -> f64 {
        (a - b).abs() / a.abs().max(b.abs()).max(1.0)
    }

    fn check_jacobians(obs: &Observation, pose: &Isometry3<f64>, p_w: &Vector3<f64>) {
        let lin = obs.linearize(&INTR, pose, p_w).expect("point in front");
        let h = 1e-6;
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = h;
            let rp = obs.residual(&INTR, &se3::retract(pose, &d), p_w).unwrap();
            d[k] = -h;
            let rm = obs.residual(&INTR, &se3::retract(pose, &d), p_w).unwrap();
            let num = (rp - rm) / (2.0 * h);
            for i in 0..3 {
                let e = rel_err(num[i], lin.jac_pose[(i, k)]);
                assert!(
                    e < 1e-6,
                    "pose J[{i},{k}] {} vs {} ({e})",
                    lin.jac_pose[(i, k)],
                    num[i]
                );
            }
        }
        for k in 0..3 {
            let mut d = Vector3::zeros();
            d[k] = h;
            let rp = obs.residual(&INTR, pose, &(p_w + d)).unwrap();
            let rm = obs.residual(&INTR, pose, &(p_w - d)).unwrap();
            let num = (rp - rm) / (2.0 * h);
            for i in 0..3 {
                let e = rel_err(num[i], lin.jac_point[(i, k)]);
                assert!(
                    e < 1e-6,
                    "point J[{i},{k}] {} vs {} ({e})",
                    lin.jac_point[(i, k)],
                    num[i]
                );
            }
        }
    }

    #[test]
    fn jacobians_match_central_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for _ in 0..200 {
            let (pose, p_w) = random_setup(&mut rng);
            let uv = Vector2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0));
            check_jacobians(&Observation::Mono { uv }, &pose, &p_w);
            let depth = rng.random_range(0.5..6.0);
            check_jacobians(&Observation::Rgbd { uv, depth }, &pose, &p_w);
        }
    }

    #[test]
    fn jacobians_through_a_shutter_motion_match_central_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        for _ in 0..100 {
            let (pose, p_w) = random_setup(&mut rng);
            let shutter = se3::exp(&Vector6::from_fn(|_, _| rng.random_range(-0.05..0.05)));
            let uv = Vector2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0));
            let obs = Observation::Rgbd {
                uv,
                depth: rng.random_range(0.5..6.0),
            };
            let Some(lin) = obs.linearize_through(&INTR, &shutter, &pose, &p_w) else {
                continue;
            };
            let h = 1e-6;
            for k in 0..6 {
                let mut d = Vector6::zeros();
                d[k] = h;
                let rp = obs.residual_through(&INTR, &shutter, &se3::retract(&pose, &d), &p_w);
                d[k] = -h;
                let rm = obs.residual_through(&INTR, &shutter, &se3::retract(&pose, &d), &p_w);
                let num = (rp.unwrap() - rm.unwrap()) / (2.0 * h);
                for i in 0..3 {
                    let e = rel_err(num[i], lin.jac_pose[(i, k)]);
                    assert!(
                        e < 1e-6,
                        "J[{i},{k}] {} vs {}",
                        lin.jac_pose[(i, k)],
                        num[i]
                    );
                }
            }
        }
    }

    #[test]
    fn residual_is_zero_at_truth() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let (pose, p_w) = random_setup(&mut rng);
        let p_c = (pose * Point3::from(p_w)).coords;
        let uv = INTR.project(&p_c).unwrap();
        let mono = Observation::Mono { uv };
        let rgbd = Observation::Rgbd { uv, depth: p_c.z };
        assert!(mono.residual(&INTR, &pose, &p_w).unwrap().norm() < 1e-9);
        assert!(rgbd.residual(&INTR, &pose, &p_w).unwrap().norm() < 1e-9);
        assert_eq!(mono.dim(), 2);
        assert_eq!(rgbd.dim(), 3);
    }

    #[test]
    fn points_behind_camera_are_invalid() {
        let pose = Isometry3::identity();
        let uv = Vector2::new(300.0, 200.0);
        let mono = Observation::Mono { uv };
        assert!(
            mono.residual(&INTR, &pose, &Vector3::new(0.0, 0.0, -1.0))
                .is_none()
        );
        assert!(
            mono.linearize(&INTR, &pose, &Vector3::new(0.0, 0.0, 0.0))
                .is_none()
        );
        let bad_depth = Observation::Rgbd { uv, depth: 0.0 };
        assert!(
            bad_depth
                .residual(&INTR, &pose, &Vector3::new(0.0, 0.0, 1.0))
                .is_none()
        );
    }

    #[test]
    fn huber_is_continuous_and_bounded() {
        let d2 = CHI2_MONO;
        let (below, w_below) = huber(d2 - 1e-9, d2);
        let (above, w_above) = huber(d2 + 1e-9, d2);
        assert!((below - above).abs() < 1e-6 && (w_below - w_above).abs() < 1e-6);
        assert_eq!(huber(1.0, d2), (1.0, 1.0));
        let (rho, w) = huber(100.0 * d2, d2);
        assert!(rho < 100.0 * d2 && (w - 0.1).abs() < 1e-12);
    }

    #[test]
    fn octave_weights() {
        assert_eq!(octave_information(0), 1.0);
        assert!((octave_information(2) - 1.0 / 1.44f64.powi(2)).abs() < 1e-12);
    }
}
