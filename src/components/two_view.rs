//! Two-view geometry for monocular mode: model selection and reconstruction from two frames,
//! linear triangulation, and a Sim3 RANSAC for monocular loop validation.
//!
//! # Why
//! Without depth, the *Initializer* of the paper's state-machine taxonomy (Table I:
//! Measurements → first local map) cannot back-project one frame; it needs a two-view
//! structure-from-motion step. We follow ORB-SLAM2's `Initializer` (Mur-Artal et al., 2015,
//! Sec. IV): a homography `H` and a fundamental matrix `F` are estimated in parallel RANSACs
//! that share the same 8-point minimal sets, each scored with ORB-SLAM's truncated
//! symmetric-transfer score (`S_M = Σ ρ_M(d²_cr) + ρ_M(d²_rc)`), and the model is chosen by
//! `R_H = S_H / (S_H + S_F)`: a planar or low-parallax scene is better explained by `H`
//! (`R_H > 0.40`), a general 3-D scene by `F`. The chosen model is decomposed (Faugeras' eight
//! solutions for `H`, the four `(R, t)` of `E = Kᵀ F K` for `F`), every candidate is checked by
//! triangulating the inliers, and the reconstruction is accepted only when one candidate clearly
//! wins with enough points and enough parallax — otherwise a [`RejectReason`] says why.
//! The code is our own; the algorithm, thresholds and acceptance rules are ORB-SLAM2's, with the
//! deviations listed below.
//!
//! **Selection margin.** `σ` should be the std of the *match residual* per axis, not of one
//! keypoint: a planar scene is fitted by `F` as well as by `H` (any `[e']ₓH` is a valid `F`), and
//! then the expected scores give `R_H ≈ 0.41` when both images carry σ-level noise (the 0.40
//! threshold is a coin flip), `≈ 0.45` for a 1σ match residual, `≈ 0.48` for σ/2 per image
//! (`tests/it/two_view.rs::planar_rh_depends_on_noise_relative_to_sigma`).
//!
//! Monocular loop closing needs a similarity (scale drifts), estimated by [`sim3_ransac`]
//! as ORB-SLAM's `Sim3Solver` does: minimal 3-point sets, inliers by reprojection in both images.
//!
//! # Conventions
//! - Image points are *undistorted pixel* coordinates; `K = [fx 0 cx; 0 fy cy; 0 0 1]`
//!   ([`Intrinsics::bf`] is ignored).
//! - `H` (`h21`) maps image 1 to image 2: `x2 ~ H x1`; `F` (`f21`) satisfies `x2ᵀ F x1 = 0`.
//! - The relative pose is that of camera 2 with respect to camera 1 as a *point transform*:
//!   `X_c2 = R · X_c1 + t` (ORB-SLAM's `R21`, `t21`; camera 1 is the world frame, camera 2's
//!   centre is `−Rᵀ t` in it). Monocular scale is unobservable, so `‖t‖ = 1` and the
//!   triangulated points (in camera-1 coordinates) are in units of the baseline.
//! - Projection matrices are `P1 = K [I | 0]`, `P2 = K [R | t]`.
//! - Everything is `f64`, pure and deterministic: the RANSAC sets come from
//!   `ChaCha8Rng::seed_from_u64(seed)`.
//!
//! # Deviations from ORB-SLAM2
//! - Normalisation is Hartley's isotropic one (centroid at 0, mean distance √2) rather than
//!   ORB-SLAM's per-axis mean absolute deviation.
//! - With [`TwoViewParams::refine`] (default on) the *selected* model is re-estimated on its
//!   inliers (normalised DLT / 8-point on all of them, repeated while the score does not drop)
//!   before it is decomposed. ORB-SLAM decomposes the minimal-sample model and leaves accuracy
//!   to the following bundle adjustment; the refit makes `R, t` usable directly. The selection
//!   itself (`S_H`, `S_F`, `R_H`) uses the minimal-sample models, as in ORB-SLAM: refitting `F`
//!   on a planar scene makes it fit as well as `H` does, and with σ-level noise in both images
//!   ORB's score then gives `R_H ≈ 0.41` for *any* scene both models fit, i.e. no margin.
//! - When the rejection has several causes, one reason is reported, checked in the order
//!   documented on [`RejectReason`]. A homography with three equal singular values (a pure
//!   rotation: no parallax at all) is reported as [`RejectReason::LowParallax`].

use crate::geometry::{Sim3, umeyama};
use crate::optim::Intrinsics;
use nalgebra::{DMatrix, Matrix3, Matrix3x4, Matrix4, Rotation3, SVector, Vector2, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// χ² 95 % quantile, 1 degree of freedom: the point-to-epipolar-line threshold of `F`.
pub const CHI2_1DOF: f64 = 3.841;
/// χ² 95 % quantile, 2 degrees of freedom: the transfer threshold of `H`, and the score offset
/// of both models (so that `H` and `F` scores are comparable).
pub const CHI2_2DOF: f64 = 5.991;
/// χ² 99 % quantile, 2 degrees of freedom: ORB-SLAM's Sim3Solver reprojection threshold.
pub const CHI2_2DOF_99: f64 = 9.21;
/// Below this cosine (≈ 0.36°) a point's parallax is large enough to triangulate it; points
/// with less parallax skip the cheirality test and are never reported as triangulated
/// (ORB-SLAM's `CheckRT`).
const COS_PARALLAX_TRIANGULATE: f64 = 0.99998;

/// The other model's reconstruction (see [`TwoViewParams::try_other_model`]) needs this many
/// times the usual parallax: the selected model's ambiguity says the views barely tell the
/// motions apart, and at the usual 1° a fundamental-matrix start made maps that drifted
/// (small `desk` mono: 7.7 cm after a merge, where a start at 4° gave under 3 cm).
const OTHER_MODEL_PARALLAX_FACTOR: f64 = 2.0;

/// A motion hypothesis `(R, t)`: `X_c2 = R · X_c1 + t`.
pub type Motion = (Matrix3<f64>, Vector3<f64>);

/// Which two-view model explains the matches.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelKind {
    Homography,
    Fundamental,
}

/// Why a two-view reconstruction was refused. When several apply, the first in this order is
/// reported: `TooFewMatches`, `TooFewInliers` (model inliers < `min_triangulated`),
/// `DegenerateHomography`, `TooFewTriangulated` (best candidate < `min_triangulated` good
/// points), `LowParallax`, `TooFewTriangulated` (best candidate < `min_good_fraction` of the
/// inliers), `Ambiguous`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RejectReason {
    /// Fewer than 8 matches, or the two slices differ in length.
    TooFewMatches,
    /// The selected model has fewer inliers than `min_triangulated`.
    TooFewInliers,
    /// The homography has two (but not three) equal singular values: Faugeras' decomposition is
    /// undefined (e.g. translation along the plane normal).
    DegenerateHomography,
    /// The best motion hypothesis triangulates too few points.
    TooFewTriangulated,
    /// The best motion hypothesis has less parallax than `min_parallax_deg`.
    LowParallax,
    /// A second motion hypothesis explains almost as many points as the best one.
    Ambiguous,
}

/// Parameters of [`initialize_two_view`]; the defaults are ORB-SLAM2's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TwoViewParams {
    /// Pixel noise σ; all χ² tests are on `d² / σ²`.
    pub sigma: f64,
    /// RANSAC iterations (shared 8-point sets for `H` and `F`).
    pub iterations: usize,
    pub seed: u64,
    /// `H` is chosen when `R_H` exceeds this (ORB-SLAM2: 0.40; the paper says 0.45).
    pub rh_threshold: f64,
    /// Minimum number of good triangulated points of the accepted hypothesis.
    pub min_triangulated: usize,
    /// Minimum parallax (degrees) of the accepted hypothesis, measured as in ORB-SLAM's
    /// `CheckRT` (see [`ParallaxStats::orb_deg`]).
    pub min_parallax_deg: f64,
    /// The accepted hypothesis must triangulate at least this fraction of the model inliers.
    pub min_good_fraction: f64,
    /// `H`: the second-best of the 8 solutions must have fewer than this × best good points.
    pub ambiguity_ratio_h: f64,
    /// `F`: the second-best of the 4 solutions must have at most this × best good points.
    pub ambiguity_ratio_f: f64,
    /// Reprojection gate of triangulated points, in units of σ²: `d² ≤ reproj_chi2 · σ²`.
    pub reproj_chi2: f64,
    /// Re-estimate the best minimal model on its inliers (see the module docs).
    pub refine: bool,
    /// When the selected model's hypotheses are ambiguous, reconstruct from the other model.
    pub try_other_model: bool,
}

impl Default for TwoViewParams {
    fn default() -> Self {
        Self {
            sigma: 1.0,
            iterations: 200,
            seed: 0,
            rh_threshold: 0.40,
            min_triangulated: 50,
            min_parallax_deg: 1.0,
            min_good_fraction: 0.9,
            ambiguity_ratio_h: 0.75,
            ambiguity_ratio_f: 0.7,
            reproj_chi2: 4.0,
            refine: true,
            try_other_model: true,
        }
    }
}

/// Parallax of the triangulated points of a hypothesis, in degrees.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ParallaxStats {
    /// ORB-SLAM's statistic, the one compared with `min_parallax_deg`: over all good points
    /// (including those too distant to triangulate), the 51st largest parallax, or the smallest
    /// when there are at most 51.
    pub orb_deg: f64,
    /// Median over the triangulated points (0 when there are none).
    pub median_deg: f64,
    pub min_deg: f64,
    pub max_deg: f64,
}

/// An accepted two-view reconstruction.
#[derive(Debug, Clone, PartialEq)]
pub struct TwoViewReconstruction {
    pub model: ModelKind,
    /// The estimated model matrix (refitted with `refine`): `h21` (`x2 ~ H x1`) or `f21`
    /// (`x2ᵀ F x1 = 0`), pixels.
    pub matrix: Matrix3<f64>,
    /// `R_H = S_H / (S_H + S_F)`, from the RANSAC (minimal-sample) scores.
    pub r_h: f64,
    pub score_h: f64,
    pub score_f: f64,
    /// `X_c2 = rotation · X_c1 + translation`.
    pub rotation: Rotation3<f64>,
    /// Unit norm.
    pub translation: Vector3<f64>,
    /// Per match: the triangulated point in camera-1 coordinates (units of the baseline), `None`
    /// when the match is an outlier, failed the cheirality/reprojection checks or has too little
    /// parallax to be triangulated.
    pub points: Vec<Option<Vector3<f64>>>,
    /// Per match: inlier of the selected model.
    pub inliers: Vec<bool>,
    /// Good points of the best and the second-best motion hypothesis.
    pub n_good: usize,
    pub n_good_second: usize,
    pub parallax: ParallaxStats,
}

/// A refused two-view reconstruction with what was measured on the way.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TwoViewRejection {
    pub reason: RejectReason,
    pub model: Option<ModelKind>,
    pub r_h: f64,
    pub n_inliers: usize,
    pub n_good: usize,
    pub n_good_second: usize,
    pub parallax_deg: f64,
}

/// `K` as a matrix.
pub fn k_matrix(k: &Intrinsics) -> Matrix3<f64> {
    Matrix3::new(k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0)
}

/// `K [R | t]`.
pub fn projection_matrix(k: &Intrinsics, r: &Matrix3<f64>, t: &Vector3<f64>) -> Matrix3x4<f64> {
    let mut rt = Matrix3x4::zeros();
    rt.fixed_view_mut::<3, 3>(0, 0).copy_from(r);
    rt.set_column(3, t);
    k_matrix(k) * rt
}

// ---------------------------------------------------------------------------------------------
// Triangulation helpers
// ---------------------------------------------------------------------------------------------

/// Linear (DLT) triangulation of one match from two projection matrices: the homogeneous point
/// minimising the algebraic error, by SVD of the 4×4 system (rows scaled to unit norm for
/// conditioning). `None` for a point at infinity or non-finite input.
pub fn triangulate(
    p1: &Matrix3x4<f64>,
    p2: &Matrix3x4<f64>,
    x1: &Vector2<f64>,
    x2: &Vector2<f64>,
) -> Option<Vector3<f64>> {
    let mut a = Matrix4::zeros();
    let rows = [
        x1.x * p1.row(2) - p1.row(0),
        x1.y * p1.row(2) - p1.row(1),
        x2.x * p2.row(2) - p2.row(0),
        x2.y * p2.row(2) - p2.row(1),
    ];
    for (i, r) in rows.iter().enumerate() {
        let n = r.norm();
        if !n.is_finite() || n <= 0.0 {
            return None;
        }
        a.set_row(i, &(r / n));
    }
    let svd = a.svd(false, true);
    let v_t = svd.v_t?;
    let imin = argmin(svd.singular_values.as_slice());
    let h = v_t.row(imin);
    let w = h[3];
    if w.abs() < 1e-300 {
        return None;
    }
    let p = Vector3::new(h[0] / w, h[1] / w, h[2] / w);
    p.iter().all(|v| v.is_finite()).then_some(p)
}

/// Parallax angle (degrees) at `p` between the rays from the camera centres `c1` and `c2`.
pub fn parallax_deg(p: &Vector3<f64>, c1: &Vector3<f64>, c2: &Vector3<f64>) -> f64 {
    cos_parallax(p, c1, c2).clamp(-1.0, 1.0).acos().to_degrees()
}

fn cos_parallax(p: &Vector3<f64>, c1: &Vector3<f64>, c2: &Vector3<f64>) -> f64 {
    let (n1, n2) = (p - c1, p - c2);
    n1.dot(&n2) / (n1.norm() * n2.norm())
}

/// Squared reprojection error (pixels²) of a point through a 3×4 projection matrix; `None` when
/// the point projects to infinity.
pub fn reprojection_error_sq(
    p: &Matrix3x4<f64>,
    x: &Vector3<f64>,
    uv: &Vector2<f64>,
) -> Option<f64> {
    let h = p * x.push(1.0);
    if h.z.abs() < 1e-300 {
        return None;
    }
    Some((Vector2::new(h.x / h.z, h.y / h.z) - uv).norm_squared())
}

fn argmin(v: &[f64]) -> usize {
    let mut best = 0;
    for (i, x) in v.iter().enumerate() {
        if *x < v[best] {
            best = i;
        }
    }
    best
}

// ---------------------------------------------------------------------------------------------
// Model estimation
// ---------------------------------------------------------------------------------------------

/// Hartley normalisation: points moved to their centroid and scaled isotropically to a mean
/// distance of √2. Returns the normalised points and `T` (`x_n = T x`).
pub fn hartley_normalize(x: &[Vector2<f64>]) -> (Vec<Vector2<f64>>, Matrix3<f64>) {
    let n = x.len().max(1) as f64;
    let mean = x.iter().sum::<Vector2<f64>>() / n;
    let mean_dist = x.iter().map(|p| (p - mean).norm()).sum::<f64>() / n;
    let s = if mean_dist > 0.0 {
        std::f64::consts::SQRT_2 / mean_dist
    } else {
        1.0
    };
    let t = Matrix3::new(s, 0.0, -s * mean.x, 0.0, s, -s * mean.y, 0.0, 0.0, 1.0);
    (x.iter().map(|p| (p - mean) * s).collect(), t)
}

/// The right singular vector of the smallest singular value of the `rows × 9` system.
fn null_vector(rows: &[[f64; 9]]) -> Option<SVector<f64, 9>> {
    // At least 9 rows so that the SVD returns the full 9×9 V (zero rows do not change it).
    let m = rows.len().max(9);
    let mut a = DMatrix::<f64>::zeros(m, 9);
    for (i, r) in rows.iter().enumerate() {
        for (j, v) in r.iter().enumerate() {
            a[(i, j)] = *v;
        }
    }
    let svd = a.svd(false, true);
    let v_t = svd.v_t?;
    let imin = argmin(svd.singular_values.as_slice());
    let v = SVector::<f64, 9>::from_iterator(v_t.row(imin).iter().copied());
    v.iter().all(|x| x.is_finite()).then_some(v)
}

fn mat_from_9(v: &SVector<f64, 9>) -> Matrix3<f64> {
    Matrix3::new(v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8])
}

/// DLT homography `x2 ~ H x1` from ≥ 4 (already normalised) matches.
fn dlt_homography(x1: &[Vector2<f64>], x2: &[Vector2<f64>]) -> Option<Matrix3<f64>> {
    let mut rows = Vec::with_capacity(2 * x1.len());
    for (a, b) in x1.iter().zip(x2) {
        let (u1, v1, u2, v2) = (a.x, a.y, b.x, b.y);
        rows.push([0.0, 0.0, 0.0, -u1, -v1, -1.0, v2 * u1, v2 * v1, v2]);
        rows.push([u1, v1, 1.0, 0.0, 0.0, 0.0, -u2 * u1, -u2 * v1, -u2]);
    }
    null_vector(&rows).map(|v| mat_from_9(&v))
}

/// 8-point fundamental matrix `x2ᵀ F x1 = 0` from ≥ 8 (already normalised) matches, with the
/// rank-2 constraint enforced by zeroing the smallest singular value.
fn eight_point_fundamental(x1: &[Vector2<f64>], x2: &[Vector2<f64>]) -> Option<Matrix3<f64>> {
    let rows: Vec<[f64; 9]> = x1
        .iter()
        .zip(x2)
        .map(|(a, b)| {
            let (u1, v1, u2, v2) = (a.x, a.y, b.x, b.y);
            [u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, 1.0]
        })
        .collect();
    let f = mat_from_9(&null_vector(&rows)?);
    let mut svd = f.svd(true, true);
    svd.singular_values[2] = 0.0; // sorted descending
    svd.recompose().ok()
}

/// Normalised DLT homography `x2 ~ H x1` (pixels) from ≥ 4 matches.
pub fn homography_dlt(x1: &[Vector2<f64>], x2: &[Vector2<f64>]) -> Option<Matrix3<f64>> {
    if x1.len() < 4 || x1.len() != x2.len() {
        return None;
    }
    let (n1, t1) = hartley_normalize(x1);
    let (n2, t2) = hartley_normalize(x2);
    let hn = dlt_homography(&n1, &n2)?;
    Some(t2.try_inverse()? * hn * t1)
}

/// Normalised 8-point fundamental matrix `x2ᵀ F x1 = 0` (pixels, rank 2) from ≥ 8 matches.
pub fn fundamental_8point(x1: &[Vector2<f64>], x2: &[Vector2<f64>]) -> Option<Matrix3<f64>> {
    if x1.len() < 8 || x1.len() != x2.len() {
        return None;
    }
    let (n1, t1) = hartley_normalize(x1);
    let (n2, t2) = hartley_normalize(x2);
    let fn_ = eight_point_fundamental(&n1, &n2)?;
    Some(t2.transpose() * fn_ * t1)
}

/// ORB-SLAM's `CheckHomography`: symmetric transfer error, both directions gated at χ²(2) =
/// 5.991 and each passing direction adding `5.991 − d²/σ²` to the score. A match is an inlier
/// when both directions pass. Returns `(score, inliers)`.
pub fn homography_score(
    h21: &Matrix3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    sigma: f64,
) -> (f64, Vec<bool>) {
    let Some(h12) = h21.try_inverse() else {
        return (0.0, vec![false; x1.len()]);
    };
    let inv_s2 = 1.0 / (sigma * sigma);
    let transfer = |h: &Matrix3<f64>, a: &Vector2<f64>, b: &Vector2<f64>| -> f64 {
        let p = h * a.push(1.0);
        if p.z.abs() < 1e-300 {
            return f64::INFINITY;
        }
        (Vector2::new(p.x / p.z, p.y / p.z) - b).norm_squared() * inv_s2
    };
    let mut score = 0.0;
    let inliers = x1
        .iter()
        .zip(x2)
        .map(|(a, b)| {
            let mut inlier = true;
            for chi2 in [transfer(&h12, b, a), transfer(h21, a, b)] {
                if chi2 <= CHI2_2DOF {
                    score += CHI2_2DOF - chi2;
                } else {
                    inlier = false;
                }
            }
            inlier
        })
        .collect();
    (score, inliers)
}

/// ORB-SLAM's `CheckFundamental`: squared distances to the epipolar lines in both images,
/// gated at χ²(1) = 3.841, each passing one adding `5.991 − d²/σ²` (the χ²(2) offset makes the
/// score comparable with [`homography_score`]). Returns `(score, inliers)`.
pub fn fundamental_score(
    f21: &Matrix3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    sigma: f64,
) -> (f64, Vec<bool>) {
    let inv_s2 = 1.0 / (sigma * sigma);
    let line_dist = |l: &Vector3<f64>, p: &Vector2<f64>| -> f64 {
        let num = l.x * p.x + l.y * p.y + l.z;
        let den = l.x * l.x + l.y * l.y;
        if den <= 0.0 {
            f64::INFINITY
        } else {
            num * num / den * inv_s2
        }
    };
    let mut score = 0.0;
    let inliers = x1
        .iter()
        .zip(x2)
        .map(|(a, b)| {
            let l2 = f21 * a.push(1.0); // epipolar line of x1 in image 2
            let l1 = f21.transpose() * b.push(1.0); // epipolar line of x2 in image 1
            let mut inlier = true;
            for chi2 in [line_dist(&l2, b), line_dist(&l1, a)] {
                if chi2 <= CHI2_1DOF {
                    score += CHI2_2DOF - chi2;
                } else {
                    inlier = false;
                }
            }
            inlier
        })
        .collect();
    (score, inliers)
}

/// A model fitted by [`ransac_model`]: matrix (pixels), score, inliers.
#[derive(Debug, Clone, PartialEq)]
pub struct ScoredModel {
    pub matrix: Matrix3<f64>,
    pub score: f64,
    pub inliers: Vec<bool>,
}

/// The RANSAC minimal sets: `iterations` sets of 8 distinct match indices, drawn once and
/// shared by `H` and `F` (as ORB-SLAM does).
pub fn minimal_sets(n: usize, iterations: usize, seed: u64) -> Vec<[usize; 8]> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..iterations)
        .map(|_| {
            let idx = rand::seq::index::sample(&mut rng, n, 8);
            let mut s = [0; 8];
            for (d, i) in s.iter_mut().zip(idx.iter()) {
                *d = i;
            }
            s
        })
        .collect()
}

/// RANSAC for one model kind over the given minimal sets with ORB-SLAM's scoring: the
/// minimal-sample model of highest score (the first one on ties).
pub fn ransac_model(
    kind: ModelKind,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    sets: &[[usize; 8]],
    sigma: f64,
) -> Option<ScoredModel> {
    if x1.len() < 8 || x1.len() != x2.len() {
        return None;
    }
    // Normalised once for all sets, as ORB-SLAM does.
    let (n1, t1) = hartley_normalize(x1);
    let (n2, t2) = hartley_normalize(x2);
    let t2_inv = t2.try_inverse()?;
    let mut best: Option<ScoredModel> = None;
    for set in sets {
        let a: Vec<_> = set.iter().map(|&i| n1[i]).collect();
        let b: Vec<_> = set.iter().map(|&i| n2[i]).collect();
        let m = match kind {
            ModelKind::Homography => dlt_homography(&a, &b).map(|h| t2_inv * h * t1),
            ModelKind::Fundamental => {
                eight_point_fundamental(&a, &b).map(|f| t2.transpose() * f * t1)
            }
        };
        let Some(m) = m else { continue };
        let (score, inliers) = score_model(kind, &m, x1, x2, sigma);
        if best.as_ref().is_none_or(|b| score > b.score) {
            best = Some(ScoredModel {
                matrix: m,
                score,
                inliers,
            });
        }
    }
    best
}

/// The score and inliers of a model ([`homography_score`] or [`fundamental_score`]).
pub fn score_model(
    kind: ModelKind,
    m: &Matrix3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    sigma: f64,
) -> (f64, Vec<bool>) {
    match kind {
        ModelKind::Homography => homography_score(m, x1, x2, sigma),
        ModelKind::Fundamental => fundamental_score(m, x1, x2, sigma),
    }
}

/// Re-estimates a model on its inliers ([`homography_dlt`] / [`fundamental_8point`], each with
/// its own normalisation) and re-scores it, repeated (at most 5 times) while the score does not
/// drop and the inlier set changes. Returns the input when no refit scores at least as well.
pub fn refine_model(
    kind: ModelKind,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    model: ScoredModel,
    sigma: f64,
) -> ScoredModel {
    let mut best = model;
    for _ in 0..5 {
        let (a, b): (Vec<_>, Vec<_>) = (0..x1.len())
            .filter(|&i| best.inliers[i])
            .map(|i| (x1[i], x2[i]))
            .unzip();
        let m = match kind {
            ModelKind::Homography => homography_dlt(&a, &b),
            ModelKind::Fundamental => fundamental_8point(&a, &b),
        };
        let Some(m) = m else { break };
        let (score, inliers) = score_model(kind, &m, x1, x2, sigma);
        if score < best.score {
            break;
        }
        let converged = inliers == best.inliers;
        best = ScoredModel {
            matrix: m,
            score,
            inliers,
        };
        if converged {
            break;
        }
    }
    best
}

// ---------------------------------------------------------------------------------------------
// Motion hypotheses
// ---------------------------------------------------------------------------------------------

/// Faugeras' decomposition of a homography (pixels, `x2 ~ H x1`) into its eight `(R, t)`
/// hypotheses (`X_c2 = R X_c1 + t`, `‖t‖ = 1`), as in ORB-SLAM's `ReconstructH`.
/// `Err(DegenerateHomography)` when two singular values of `K⁻¹ H K` coincide, `Err(LowParallax)`
/// when all three do (a pure rotation).
pub fn decompose_homography(
    h21: &Matrix3<f64>,
    k: &Intrinsics,
) -> Result<Vec<Motion>, RejectReason> {
    let km = k_matrix(k);
    let k_inv = km.try_inverse().ok_or(RejectReason::DegenerateHomography)?;
    let a = k_inv * h21 * km;
    let svd = a.svd(true, true);
    let (u, v_t) = match (svd.u, svd.v_t) {
        (Some(u), Some(v)) => (u, v),
        _ => return Err(RejectReason::DegenerateHomography),
    };
    let (d1, d2, d3) = (
        svd.singular_values[0],
        svd.singular_values[1],
        svd.singular_values[2],
    );
    if d3.is_nan() || d3 <= 0.0 || d1 / d3 < 1.00001 {
        return Err(RejectReason::LowParallax);
    }
    if d1 / d2 < 1.00001 || d2 / d3 < 1.00001 {
        return Err(RejectReason::DegenerateHomography);
    }
    let s = u.determinant() * v_t.determinant();
    let (d1s, d2s, d3s) = (d1 * d1, d2 * d2, d3 * d3);
    let aux1 = ((d1s - d2s) / (d1s - d3s)).sqrt();
    let aux3 = ((d2s - d3s) / (d1s - d3s)).sqrt();
    let x1 = [aux1, aux1, -aux1, -aux1];
    let x3 = [aux3, -aux3, aux3, -aux3];
    let mut out = Vec::with_capacity(8);
    // d' = d2 > 0
    let aux_st = ((d1s - d2s) * (d2s - d3s)).sqrt() / ((d1 + d3) * d2);
    let ct = (d2s + d1 * d3) / ((d1 + d3) * d2);
    let st = [aux_st, -aux_st, -aux_st, aux_st];
    for i in 0..4 {
        let rp = Matrix3::new(ct, 0.0, -st[i], 0.0, 1.0, 0.0, st[i], 0.0, ct);
        let r = s * u * rp * v_t;
        let t = u * (Vector3::new(x1[i], 0.0, -x3[i]) * (d1 - d3));
        out.push((r, t.normalize()));
    }
    // d' = -d2 < 0
    let aux_sp = ((d1s - d2s) * (d2s - d3s)).sqrt() / ((d1 - d3) * d2);
    let cp = (d1 * d3 - d2s) / ((d1 - d3) * d2);
    let sp = [aux_sp, -aux_sp, -aux_sp, aux_sp];
    for i in 0..4 {
        let rp = Matrix3::new(cp, 0.0, sp[i], 0.0, -1.0, 0.0, sp[i], 0.0, -cp);
        let r = s * u * rp * v_t;
        let t = u * (Vector3::new(x1[i], 0.0, x3[i]) * (d1 + d3));
        out.push((r, t.normalize()));
    }
    Ok(out)
}

/// The four `(R, t)` hypotheses of an essential matrix (`‖t‖ = 1`, `det R = +1`):
/// `(R1, t), (R2, t), (R1, −t), (R2, −t)`.
pub fn decompose_essential(e: &Matrix3<f64>) -> Option<[Motion; 4]> {
    let svd = e.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let t = u.column(2).normalize();
    let w = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let fix = |r: Matrix3<f64>| if r.determinant() < 0.0 { -r } else { r };
    let r1 = fix(u * w * v_t);
    let r2 = fix(u * w.transpose() * v_t);
    Some([(r1, t), (r2, t), (r1, -t), (r2, -t)])
}

/// The result of checking one motion hypothesis (ORB-SLAM's `CheckRT`).
#[derive(Debug, Clone, PartialEq)]
pub struct HypothesisCheck {
    /// Matches passing cheirality (unless nearly parallel rays) and the reprojection gate.
    pub n_good: usize,
    /// Per match: the triangulated point (camera 1) when good *and* its parallax is above
    /// ≈ 0.36°.
    pub points: Vec<Option<Vector3<f64>>>,
    pub parallax: ParallaxStats,
}

/// Triangulates the `inliers` under `(R, t)` and counts the good points: finite, in front of
/// both cameras (checked only when the parallax exceeds ≈ 0.36°, as ORB-SLAM does), and
/// reprojecting within `th2` pixels² in both images.
pub fn check_rt(
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    inliers: &[bool],
    k: &Intrinsics,
    th2: f64,
) -> HypothesisCheck {
    let p1 = projection_matrix(k, &Matrix3::identity(), &Vector3::zeros());
    let p2 = projection_matrix(k, r, t);
    let o1 = Vector3::zeros();
    let o2 = -(r.transpose() * t);
    let mut points = vec![None; x1.len()];
    let mut cos_all = Vec::new();
    let mut tri_deg = Vec::new();
    for i in 0..x1.len() {
        if !inliers[i] {
            continue;
        }
        let Some(p) = triangulate(&p1, &p2, &x1[i], &x2[i]) else {
            continue;
        };
        let cp = cos_parallax(&p, &o1, &o2);
        let wide = cp < COS_PARALLAX_TRIANGULATE;
        if p.z <= 0.0 && wide {
            continue;
        }
        let pc2 = r * p + t;
        if pc2.z <= 0.0 && wide {
            continue;
        }
        let e1 = reprojection_error_sq(&p1, &p, &x1[i]).unwrap_or(f64::INFINITY);
        let e2 = reprojection_error_sq(&p2, &p, &x2[i]).unwrap_or(f64::INFINITY);
        if e1 > th2 || e2 > th2 {
            continue;
        }
        cos_all.push(cp);
        if wide {
            points[i] = Some(p);
            tri_deg.push(cp.clamp(-1.0, 1.0).acos().to_degrees());
        }
    }
    let mut parallax = ParallaxStats::default();
    if !cos_all.is_empty() {
        cos_all.sort_by(f64::total_cmp); // ascending cosine = descending parallax
        let idx = 50.min(cos_all.len() - 1);
        parallax.orb_deg = cos_all[idx].clamp(-1.0, 1.0).acos().to_degrees();
    }
    if !tri_deg.is_empty() {
        tri_deg.sort_by(f64::total_cmp);
        parallax.median_deg = tri_deg[tri_deg.len() / 2];
        parallax.min_deg = tri_deg[0];
        parallax.max_deg = tri_deg[tri_deg.len() - 1];
    }
    HypothesisCheck {
        n_good: cos_all.len(),
        points,
        parallax,
    }
}

// ---------------------------------------------------------------------------------------------
// The initializer
// ---------------------------------------------------------------------------------------------

/// ORB-SLAM2's two-view initialisation: `H` and `F` RANSACs on shared minimal sets, selection by
/// `R_H`, decomposition of the chosen model, and acceptance of a clear winner among its motion
/// hypotheses. `x1[i] ↔ x2[i]` are matched undistorted pixels in frames 1 and 2.
pub fn initialize_two_view(
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    k: &Intrinsics,
    params: &TwoViewParams,
) -> Result<TwoViewReconstruction, TwoViewRejection> {
    let mut rej = TwoViewRejection {
        reason: RejectReason::TooFewMatches,
        model: None,
        r_h: f64::NAN,
        n_inliers: 0,
        n_good: 0,
        n_good_second: 0,
        parallax_deg: 0.0,
    };
    if x1.len() < 8 || x1.len() != x2.len() {
        return Err(rej);
    }
    let sets = minimal_sets(x1.len(), params.iterations, params.seed);
    let h = ransac_model(ModelKind::Homography, x1, x2, &sets, params.sigma);
    let f = ransac_model(ModelKind::Fundamental, x1, x2, &sets, params.sigma);
    // Selection on the minimal-sample scores, exactly as ORB-SLAM (a refit would let F fit a
    // planar scene as well as H does, pushing R_H down towards its noise-only value ≈ 0.41).
    let (sh, sf) = (
        h.as_ref().map_or(0.0, |m| m.score),
        f.as_ref().map_or(0.0, |m| m.score),
    );
    let r_h = if sh + sf > 0.0 { sh / (sh + sf) } else { 0.0 };
    rej.r_h = r_h;
    let kind = if r_h > params.rh_threshold {
        ModelKind::Homography
    } else {
        ModelKind::Fundamental
    };
    let (chosen, other) = match kind {
        ModelKind::Homography => ((kind, h), (ModelKind::Fundamental, f)),
        ModelKind::Fundamental => ((kind, f), (ModelKind::Homography, h)),
    };
    let scores = (sh, sf);
    let first = reconstruct(chosen.0, chosen.1, x1, x2, k, params, scores, rej);
    // The selected model's motion hypotheses may tie where the other model's do not: at a
    // few degrees of parallax a 3-D scene is still fitted by `H` within σ (R_H just above the
    // threshold), and the eight solutions of `H` then explain the points about equally well.
    // `F` decomposes into four, of which only one puts the points in front of both cameras.
    match first {
        Err(r) if params.try_other_model && r.reason == RejectReason::Ambiguous => {
            let strict = TwoViewParams {
                min_parallax_deg: params.min_parallax_deg * OTHER_MODEL_PARALLAX_FACTOR,
                ..*params
            };
            reconstruct(other.0, other.1, x1, x2, k, &strict, scores, rej).map_err(|_| r)
        }
        x => x,
    }
}

/// The reconstruction from one fitted model: decomposition into motion hypotheses, the
/// triangulation check of each, and the acceptance of a clear winner. `scores` are the
/// selection's `(S_H, S_F)`; `rej` carries what was measured before (`R_H`).
#[allow(clippy::too_many_arguments)]
fn reconstruct(
    kind: ModelKind,
    chosen: Option<ScoredModel>,
    x1: &[Vector2<f64>],
    x2: &[Vector2<f64>],
    k: &Intrinsics,
    params: &TwoViewParams,
    (score_h, score_f): (f64, f64),
    mut rej: TwoViewRejection,
) -> Result<TwoViewReconstruction, TwoViewRejection> {
    rej.model = Some(kind);
    let Some(mut model) = chosen else {
        rej.reason = RejectReason::TooFewInliers;
        return Err(rej);
    };
    if params.refine {
        model = refine_model(kind, x1, x2, model, params.sigma);
    }
    let n_inliers = model.inliers.iter().filter(|b| **b).count();
    rej.n_inliers = n_inliers;
    if n_inliers < params.min_triangulated.max(8) {
        rej.reason = RejectReason::TooFewInliers;
        return Err(rej);
    }
    let (hypotheses, ratio) = match kind {
        ModelKind::Homography => match decompose_homography(&model.matrix, k) {
            Ok(hs) => (hs, params.ambiguity_ratio_h),
            Err(reason) => {
                rej.reason = reason;
                return Err(rej);
            }
        },
        ModelKind::Fundamental => {
            let km = k_matrix(k);
            let e = km.transpose() * model.matrix * km;
            match decompose_essential(&e) {
                Some(hs) => (hs.to_vec(), params.ambiguity_ratio_f),
                None => {
                    rej.reason = RejectReason::TooFewInliers;
                    return Err(rej);
                }
            }
        }
    };
    let th2 = params.reproj_chi2 * params.sigma * params.sigma;
    let checks: Vec<HypothesisCheck> = hypotheses
        .iter()
        .map(|(r, t)| check_rt(r, t, x1, x2, &model.inliers, k, th2))
        .collect();
    // Best by good count; ties keep the first (deterministic).
    let mut best = 0;
    for (i, c) in checks.iter().enumerate() {
        if c.n_good > checks[best].n_good {
            best = i;
        }
    }
    let second = checks
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != best)
        .map(|(_, c)| c.n_good)
        .max()
        .unwrap_or(0);
    let bc = &checks[best];
    rej.n_good = bc.n_good;
    rej.n_good_second = second;
    rej.parallax_deg = bc.parallax.orb_deg;
    let min_good =
        ((params.min_good_fraction * n_inliers as f64) as usize).max(params.min_triangulated);
    let reason = if bc.n_good < params.min_triangulated {
        Some(RejectReason::TooFewTriangulated)
    } else if bc.parallax.orb_deg < params.min_parallax_deg {
        Some(RejectReason::LowParallax)
    } else if bc.n_good < min_good {
        Some(RejectReason::TooFewTriangulated)
    } else if second as f64 >= ratio * bc.n_good as f64 {
        Some(RejectReason::Ambiguous)
    } else {
        None
    };
    if let Some(reason) = reason {
        rej.reason = reason;
        return Err(rej);
    }
    let (r, t) = hypotheses[best];
    Ok(TwoViewReconstruction {
        model: kind,
        matrix: model.matrix,
        r_h: rej.r_h,
        score_h,
        score_f,
        rotation: Rotation3::from_matrix(&r),
        translation: t,
        points: bc.points.clone(),
        inliers: model.inliers,
        n_good: bc.n_good,
        n_good_second: second,
        parallax: bc.parallax,
    })
}

// ---------------------------------------------------------------------------------------------
// Sim3 RANSAC
// ---------------------------------------------------------------------------------------------

/// Parameters of [`sim3_ransac`]; defaults as ORB-SLAM2's loop closing uses its Sim3Solver.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim3RansacParams {
    pub iterations: usize,
    pub seed: u64,
    /// Keypoint noise σ (pixels); a match is an inlier when its squared reprojection error is
    /// at most `chi2 · σ²` in *both* images.
    pub sigma: f64,
    pub chi2: f64,
    /// Fewer inliers than this → `None`.
    pub min_inliers: usize,
}

impl Default for Sim3RansacParams {
    fn default() -> Self {
        Self {
            iterations: 300,
            seed: 0,
            sigma: 1.0,
            chi2: CHI2_2DOF_99,
            min_inliers: 20,
        }
    }
}

/// Inliers of a similarity `s21` (`p2 ≈ s21 · p1`): `s21·p1` projected with `k2` must land near
/// `uv2`, and `s21⁻¹·p2` projected with `k1` near `uv1` (ORB-SLAM's `Sim3Solver::CheckInliers`).
#[allow(clippy::too_many_arguments)]
pub fn sim3_inliers(
    s21: &Sim3,
    p1: &[Vector3<f64>],
    p2: &[Vector3<f64>],
    uv1: &[Vector2<f64>],
    uv2: &[Vector2<f64>],
    k1: &Intrinsics,
    k2: &Intrinsics,
    th2: f64,
) -> Vec<bool> {
    let s12 = s21.inverse();
    (0..p1.len())
        .map(|i| {
            let in2 = k2
                .project(&s21.transform_point(&p1[i]))
                .is_some_and(|uv| (uv - uv2[i]).norm_squared() <= th2);
            let in1 = k1
                .project(&s12.transform_point(&p2[i]))
                .is_some_and(|uv| (uv - uv1[i]).norm_squared() <= th2);
            in1 && in2
        })
        .collect()
}

/// Similarity RANSAC between two sets of 3-D points seen from two keyframes (monocular loop
/// validation, ORB-SLAM's `Sim3Solver`): `p1[i]` (camera-1 coordinates, observed at `uv1[i]` by
/// camera `k1`) ↔ `p2[i]` (camera 2, `uv2[i]`, `k2`). Each iteration fits
/// [`umeyama`] with scale to 3 random distinct correspondences and counts the inliers by
/// reprojection in both images; the best hypothesis is refitted on all its inliers (repeated
/// while the inlier set grows). Returns `s21` with `p2 ≈ s21 · p1` and the inlier mask, or `None`
/// with fewer than `min_inliers` inliers.
pub fn sim3_ransac(
    p1: &[Vector3<f64>],
    p2: &[Vector3<f64>],
    uv1: &[Vector2<f64>],
    uv2: &[Vector2<f64>],
    k1: &Intrinsics,
    k2: &Intrinsics,
    params: &Sim3RansacParams,
) -> Option<(Sim3, Vec<bool>)> {
    let n = p1.len();
    if n < 3 || p2.len() != n || uv1.len() != n || uv2.len() != n {
        return None;
    }
    let th2 = params.chi2 * params.sigma * params.sigma;
    let mut rng = ChaCha8Rng::seed_from_u64(params.seed);
    let count = |m: &[bool]| m.iter().filter(|b| **b).count();
    let mut best: Option<(Sim3, Vec<bool>, usize)> = None;
    for _ in 0..params.iterations {
        let idx = rand::seq::index::sample(&mut rng, n, 3);
        let a: Vec<_> = idx.iter().map(|i| p1[i]).collect();
        let b: Vec<_> = idx.iter().map(|i| p2[i]).collect();
        let Some(s) = umeyama(&a, &b, true) else {
            continue;
        };
        let inl = sim3_inliers(&s, p1, p2, uv1, uv2, k1, k2, th2);
        let c = count(&inl);
        if best.as_ref().is_none_or(|b| c > b.2) {
            best = Some((s, inl, c));
        }
    }
    let (mut s, mut inl, mut c) = best?;
    // Refit on all inliers; the first refit is always taken, later ones while the inlier count
    // does not drop.
    for round in 0..5 {
        if c < 3 {
            break;
        }
        let a: Vec<_> = (0..n).filter(|&i| inl[i]).map(|i| p1[i]).collect();
        let b: Vec<_> = (0..n).filter(|&i| inl[i]).map(|i| p2[i]).collect();
        let Some(s_new) = umeyama(&a, &b, true) else {
            break;
        };
        let inl_new = sim3_inliers(&s_new, p1, p2, uv1, uv2, k1, k2, th2);
        let c_new = count(&inl_new);
        if round > 0 && c_new < c {
            break;
        }
        let same = inl_new == inl;
        (s, inl, c) = (s_new, inl_new, c_new);
        if same {
            break;
        }
    }
    (c >= params.min_inliers.max(3)).then_some((s, inl))
}
