//! Small geometry helpers shared by components and evaluation.

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// A similarity transform `p ↦ s·R·p + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim3 {
    pub rotation: Rotation3<f64>,
    pub translation: Vector3<f64>,
    pub scale: f64,
}

impl Sim3 {
    pub fn identity() -> Self {
        Self {
            rotation: Rotation3::identity(),
            translation: Vector3::zeros(),
            scale: 1.0,
        }
    }
    pub fn transform_point(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.scale * (self.rotation * p) + self.translation
    }

    /// `self ∘ other`: first `other`, then `self`.
    pub fn compose(&self, other: &Sim3) -> Sim3 {
        Sim3 {
            rotation: self.rotation * other.rotation,
            translation: self.scale * (self.rotation * other.translation) + self.translation,
            scale: self.scale * other.scale,
        }
    }

    pub fn inverse(&self) -> Sim3 {
        let r_inv = self.rotation.inverse();
        Sim3 {
            rotation: r_inv,
            translation: -(r_inv * self.translation) / self.scale,
            scale: 1.0 / self.scale,
        }
    }

    /// A rigid transform as a similarity of scale 1.
    pub fn from_isometry(t: &Isometry3<f64>) -> Sim3 {
        Sim3 {
            rotation: t.rotation.to_rotation_matrix(),
            translation: t.translation.vector,
            scale: 1.0,
        }
    }

    /// A camera's world-to-camera pose once its world is moved by this similarity: its centre
    /// is carried by the similarity and its orientation turned by the rotation,
    /// `T'_cw = [R_cw Rᵀ | −R'_cw c']` (the camera itself is not scaled).
    pub fn transform_pose_cw(&self, pose_cw: &Isometry3<f64>) -> Isometry3<f64> {
        let rot = UnitQuaternion::from_rotation_matrix(&self.rotation);
        let c = self.transform_point(&pose_cw.inverse().translation.vector);
        let r_cw = pose_cw.rotation * rot.inverse();
        Isometry3::from_parts(Translation3::from(-(r_cw * c)), r_cw)
    }

    /// The rigid part (the scale is dropped).
    pub fn to_isometry(&self) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::from(self.translation),
            UnitQuaternion::from_rotation_matrix(&self.rotation),
        )
    }
}

/// Least-squares alignment of point sets (Umeyama 1991): finds `T` minimising
/// `Σ ‖y_i − T(x_i)‖²`, with the scale fixed to 1 unless `with_scale`. This is the same
/// estimator as evo's `umeyama_alignment` (including the reflection fix), so ATE numbers agree.
/// Returns `None` for fewer than 3 points or degenerate (collinear / coincident) input.
pub fn umeyama(x: &[Vector3<f64>], y: &[Vector3<f64>], with_scale: bool) -> Option<Sim3> {
    let n = x.len();
    if n < 3 || y.len() != n {
        return None;
    }
    let nf = n as f64;
    let mx = x.iter().sum::<Vector3<f64>>() / nf;
    let my = y.iter().sum::<Vector3<f64>>() / nf;
    let mut sigma_x = 0.0;
    let mut cov = Matrix3::zeros();
    for (xi, yi) in x.iter().zip(y) {
        let dx = xi - mx;
        sigma_x += dx.norm_squared();
        cov += (yi - my) * dx.transpose();
    }
    sigma_x /= nf;
    cov /= nf;
    let svd = cov.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut s = Matrix3::identity();
    if u.determinant() * v_t.determinant() < 0.0 {
        s[(2, 2)] = -1.0;
    }
    // Rank check: with fewer than two non-zero singular values the rotation is undetermined.
    let mut sv = svd.singular_values;
    sv.as_mut_slice()
        .sort_by(|a, b| b.partial_cmp(a).unwrap_or(std::cmp::Ordering::Equal));
    // Written negated on purpose: a NaN singular value must fail the check too.
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    let degenerate = !(sv[1] > 1e-12 * sv[0].max(1e-300));
    if degenerate || sigma_x <= 0.0 {
        return None;
    }
    let r = u * s * v_t;
    let scale = if with_scale {
        (Matrix3::from_diagonal(&svd.singular_values) * s).trace() / sigma_x
    } else {
        1.0
    };
    let t = my - scale * (r * mx);
    Some(Sim3 {
        rotation: Rotation3::from_matrix_unchecked(r),
        translation: t,
        scale,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn umeyama_recovers_similarity() {
        let truth = Sim3 {
            rotation: Rotation3::from_euler_angles(0.3, -0.2, 1.1),
            translation: Vector3::new(1.0, -2.0, 0.5),
            scale: 2.5,
        };
        let x: Vec<_> = (0..20)
            .map(|i| {
                let f = i as f64;
                Vector3::new(f.sin(), (0.7 * f).cos(), 0.1 * f)
            })
            .collect();
        let y: Vec<_> = x.iter().map(|p| truth.transform_point(p)).collect();
        let est = umeyama(&x, &y, true).unwrap();
        assert!((est.scale - 2.5).abs() < 1e-9);
        assert!((est.translation - truth.translation).norm() < 1e-9);
        assert!((est.rotation.matrix() - truth.rotation.matrix()).norm() < 1e-9);
        assert!(umeyama(&x[..2], &y[..2], true).is_none());
        let line: Vec<_> = (0..5).map(|i| Vector3::new(i as f64, 0.0, 0.0)).collect();
        assert!(umeyama(&line, &line, false).is_none());
    }
}
