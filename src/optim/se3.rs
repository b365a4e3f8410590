//! Lie-group helpers for SO(3) and SE(3).
//!
//! Convention used throughout `optim`: a tangent vector δ ∈ se(3) is stored as a
//! `Vector6` **(ω, υ)** — rotation first, translation second — the order used by g2o and
//! therefore by ORB-SLAM's `VertexSE3Expmap`. Poses are updated by **left** perturbation,
//! `T ← exp(δ) · T`, so for a world-to-camera pose the perturbation acts in the camera frame
//! and `∂(exp(δ)·X)/∂δ |₀ = [ -[X]ₓ | I ]`.

use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3, Vector6};

/// Below this rotation angle (radians) the closed-form coefficients of `exp`/`log` lose
/// precision to cancellation, so their Taylor expansions (to θ⁴, truncation < 1e-17 here)
/// are used instead.
const SMALL_ANGLE: f64 = 1e-2;

/// The skew-symmetric (cross-product) matrix `[v]ₓ`, such that `[v]ₓ · w = v × w`.
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Coefficients `(a, b, c) = (sin θ/θ, (1 − cos θ)/θ², (θ − sin θ)/θ³)` with series
/// expansions near zero; they appear in both the rotation and the SE(3) `V` matrix.
fn coefficients(theta: f64) -> (f64, f64, f64) {
    let t2 = theta * theta;
    if theta < SMALL_ANGLE {
        (
            1.0 - t2 / 6.0 + t2 * t2 / 120.0,
            0.5 - t2 / 24.0 + t2 * t2 / 720.0,
            1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0,
        )
    } else {
        let s = theta.sin();
        // 1 − cos θ = 2 sin²(θ/2) avoids the cancellation of the direct form.
        let half_sin = (0.5 * theta).sin();
        (
            s / theta,
            2.0 * half_sin * half_sin / t2,
            (theta - s) / (t2 * theta),
        )
    }
}

/// SO(3) exponential map (Rodrigues), accurate for tiny angles.
pub fn so3_exp(omega: &Vector3<f64>) -> UnitQuaternion<f64> {
    let theta = omega.norm();
    let half = 0.5 * theta;
    // sin(θ/2)/θ, with its series near zero.
    let k = if theta < SMALL_ANGLE {
        let t2 = theta * theta;
        0.5 - t2 / 48.0 + t2 * t2 / 3840.0
    } else {
        half.sin() / theta
    };
    UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(
        half.cos(),
        k * omega.x,
        k * omega.y,
        k * omega.z,
    ))
}

/// SO(3) logarithm, returning the rotation vector with angle in `[0, π]`.
///
/// Works from the quaternion with `atan2`, which stays well conditioned both near the
/// identity (where `acos` of the trace would lose half the digits) and near π.
pub fn so3_log(q: &UnitQuaternion<f64>) -> Vector3<f64> {
    // q and −q are the same rotation; pick w ≥ 0 so the angle lies in [0, π].
    let (w, v) = if q.w < 0.0 {
        (-q.w, -q.imag())
    } else {
        (q.w, q.imag())
    };
    let s = v.norm();
    if s < 1e-8 {
        // θ = 2 atan(s/w) ≈ 2 s/w (1 − s²/(3w²)); w ≈ 1 here.
        let k = 2.0 / w * (1.0 - s * s / (3.0 * w * w));
        v * k
    } else {
        let theta = 2.0 * s.atan2(w);
        v * (theta / s)
    }
}

/// SE(3) exponential of δ = (ω, υ).
pub fn exp(delta: &Vector6<f64>) -> Isometry3<f64> {
    let omega = Vector3::new(delta[0], delta[1], delta[2]);
    let upsilon = Vector3::new(delta[3], delta[4], delta[5]);
    let theta = omega.norm();
    let (_, b, c) = coefficients(theta);
    let w = skew(&omega);
    let v = Matrix3::identity() + w * b + w * w * c;
    Isometry3::from_parts(Translation3::from(v * upsilon), so3_exp(&omega))
}

/// SE(3) logarithm, returning δ = (ω, υ) with `exp(log(T)) = T`.
pub fn log(t: &Isometry3<f64>) -> Vector6<f64> {
    let omega = so3_log(&t.rotation);
    let theta = omega.norm();
    let w = skew(&omega);
    // V⁻¹ = I − ½W + d·W² with d = (1 − (θ/2)·cot(θ/2))/θ².
    let t2 = theta * theta;
    let d = if theta < SMALL_ANGLE {
        1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    } else {
        let half = 0.5 * theta;
        (1.0 - half * half.cos() / half.sin()) / t2
    };
    let v_inv = Matrix3::identity() - w * 0.5 + w * w * d;
    let upsilon = v_inv * t.translation.vector;
    Vector6::new(omega.x, omega.y, omega.z, upsilon.x, upsilon.y, upsilon.z)
}

/// Applies the left update `exp(δ) · T`.
///
/// The rotation is renormalised: repeated updates (and a tracker's motion model composing them
/// frame after frame) otherwise let rounding drift grow until poses are no longer rigid.
pub fn retract(t: &Isometry3<f64>, delta: &Vector6<f64>) -> Isometry3<f64> {
    let mut out = exp(delta) * t;
    out.rotation.renormalize();
    out
}

/// Adjoint of `T` for the (ω, υ) ordering: `T · exp(δ) = exp(Ad_T δ) · T`, and so
/// `S · exp(δ) · T = exp(Ad_S δ) · S · T`, which lets a residual evaluated through an extra
/// left factor `S` reuse the ordinary left-perturbation Jacobian (times `Ad_S`).
pub fn adjoint(t: &Isometry3<f64>) -> nalgebra::Matrix6<f64> {
    let r = t.rotation.to_rotation_matrix().into_inner();
    let mut ad = nalgebra::Matrix6::zeros();
    ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    ad.fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&(skew(&t.translation.vector) * r));
    ad
}

/// Constant-velocity twist (per second) that carries world-to-camera pose `from` to `to` in
/// `dt` seconds: `to = exp(dt · ξ) · from`. Zero when `dt` is not positive.
pub fn twist_between(from: &Isometry3<f64>, to: &Isometry3<f64>, dt: f64) -> Vector6<f64> {
    if dt > 0.0 && dt.is_finite() {
        log(&(to * from.inverse())) / dt
    } else {
        Vector6::zeros()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_delta(rng: &mut ChaCha8Rng, angle_scale: f64) -> Vector6<f64> {
        Vector6::from_fn(|i, _| {
            let s = if i < 3 { angle_scale } else { 2.0 };
            rng.random_range(-s..s)
        })
    }

    #[test]
    fn adjoint_moves_a_perturbation_across_a_pose() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for _ in 0..50 {
            let t = exp(&random_delta(&mut rng, 1.0));
            let d = random_delta(&mut rng, 0.3) * 0.1;
            let lhs = t * exp(&d);
            let rhs = exp(&(adjoint(&t) * d)) * t;
            assert_iso_close(&lhs, &rhs, 1e-9);
        }
    }

    #[test]
    fn twist_between_recovers_the_motion() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let a = exp(&random_delta(&mut rng, 1.0));
        let xi = random_delta(&mut rng, 0.5);
        let b = exp(&(xi * 0.04)) * a;
        assert!((twist_between(&a, &b, 0.04) - xi).norm() < 1e-9);
        assert_eq!(twist_between(&a, &b, 0.0), Vector6::zeros());
    }

    fn assert_iso_close(a: &Isometry3<f64>, b: &Isometry3<f64>, tol: f64) {
        let da = a.rotation.angle_to(&b.rotation);
        let dt = (a.translation.vector - b.translation.vector).norm();
        assert!(da < tol && dt < tol, "rot {da} trans {dt}");
    }

    #[test]
    fn skew_is_cross_product() {
        let a = Vector3::new(0.3, -1.2, 2.0);
        let b = Vector3::new(-0.7, 0.1, 0.5);
        assert!((skew(&a) * b - a.cross(&b)).norm() < 1e-15);
    }

    #[test]
    fn identity_round_trip() {
        let id = Isometry3::identity();
        assert!(log(&id).norm() < 1e-15);
        assert_iso_close(&exp(&Vector6::zeros()), &id, 1e-15);
    }

    #[test]
    fn exp_matches_nalgebra_rotation() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for _ in 0..100 {
            let d = random_delta(&mut rng, 2.0);
            let omega = Vector3::new(d[0], d[1], d[2]);
            let q = so3_exp(&omega);
            let r = nalgebra::Rotation3::new(omega);
            assert!((q.to_rotation_matrix().matrix() - r.matrix()).norm() < 1e-12);
        }
    }

    #[test]
    fn random_round_trips() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        for scale in [1e-9, 1e-5, 1e-3, 0.5, 3.0] {
            for _ in 0..200 {
                let d = random_delta(&mut rng, scale);
                // Angles beyond π wrap, so compare log∘exp only inside the principal range.
                let t = exp(&d);
                let back = log(&t);
                if d.fixed_rows::<3>(0).norm() < std::f64::consts::PI - 1e-3 {
                    assert!((back - d).norm() < 1e-9 * (1.0 + d.norm()), "{d} vs {back}");
                }
                // exp∘log is the identity on the group for every T.
                assert_iso_close(&exp(&back), &t, 1e-12);
            }
        }
    }

    #[test]
    fn near_pi_rotation() {
        let axis = Vector3::new(1.0, 2.0, -0.5).normalize();
        for eps in [0.0, 1e-10, 1e-6, 1e-3] {
            let omega = axis * (std::f64::consts::PI - eps);
            let t = Isometry3::from_parts(Translation3::new(0.1, 0.2, 0.3), so3_exp(&omega));
            assert_iso_close(&exp(&log(&t)), &t, 1e-10);
        }
    }

    #[test]
    fn left_perturbation_derivative() {
        // d/dδ (exp(δ)·X) at 0 is [-[X]ₓ | I]; check by central differences.
        let x = Vector3::new(0.4, -1.0, 2.5);
        let t = exp(&Vector6::new(0.1, 0.2, -0.3, 1.0, 0.0, 0.5));
        let xc = t * nalgebra::Point3::from(x);
        let h = 1e-6;
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = h;
            let plus = retract(&t, &d) * nalgebra::Point3::from(x);
            d[k] = -h;
            let minus = retract(&t, &d) * nalgebra::Point3::from(x);
            let num = (plus - minus) / (2.0 * h);
            let ana = if k < 3 {
                -skew(&xc.coords).column(k).into_owned()
            } else {
                Vector3::from_fn(|i, _| if i == k - 3 { 1.0 } else { 0.0 })
            };
            assert!((num - ana).norm() < 1e-8);
        }
    }
}
