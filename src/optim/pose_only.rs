//! Pose-only refinement for the tracker: ORB-SLAM's `Optimizer::PoseOptimization`.
//!
//! The map points are held fixed and only the world-to-camera pose moves. The schedule is
//! ORB-SLAM's: several rounds of a few Levenberg–Marquardt iterations; after each round
//! every observation (including those already rejected) is re-classified by its χ² against
//! the 95 % threshold, outliers sit out the next round, and the Huber kernel is dropped for
//! the final round(s) once the inlier set can be trusted. Re-checking rejected observations
//! lets a correspondence that only looked wrong from the initial guess come back.

use nalgebra::{Isometry3, Matrix6, Vector3, Vector6};

use super::reprojection::{Intrinsics, Observation, huber};
use super::se3;

/// One 2-D/3-D correspondence: a fixed world point and its observation in the frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseObservation {
    pub point_w: Vector3<f64>,
    pub obs: Observation,
    /// Isotropic information (1/σ², see [`super::reprojection::octave_information`]).
    pub info: f64,
    /// Camera motion from the frame's reference time to the exposure of this keypoint's row
    /// (rolling shutter): the point is seen at `shutter · T_cw`. Identity for a global shutter.
    pub shutter: Isometry3<f64>,
}

/// Parameters of [`refine_pose`]; the defaults are ORB-SLAM's.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseParams {
    /// Outlier-classification rounds (ORB-SLAM: 4).
    pub rounds: usize,
    /// LM iterations per round (ORB-SLAM: 10).
    pub iterations_per_round: usize,
    /// The Huber kernel is used in rounds `0..robust_rounds` and dropped afterwards
    /// (ORB-SLAM: 3, i.e. removed after the third classification).
    pub robust_rounds: usize,
    /// Stop classifying rounds early when fewer inliers than this remain (ORB-SLAM: 10).
    pub min_inliers_to_continue: usize,
    /// Below this many usable observations the pose is under-determined and is returned
    /// unchanged (only classified). Three mono points fix six degrees of freedom.
    pub min_observations: usize,
}

impl Default for PoseParams {
    fn default() -> Self {
        Self {
            rounds: 4,
            iterations_per_round: 10,
            robust_rounds: 3,
            min_inliers_to_continue: 10,
            min_observations: 3,
        }
    }
}

/// Result of [`refine_pose`].
#[derive(Debug, Clone, PartialEq)]
pub struct PoseRefinement {
    /// Refined world-to-camera pose (the initial pose if nothing could be optimised).
    pub pose: Isometry3<f64>,
    /// Per observation: χ² below its threshold at the final pose (and point in front).
    pub inliers: Vec<bool>,
    pub n_inliers: usize,
    /// Sum of (non-robust) χ² over the final inliers.
    pub final_chi2: f64,
    /// False when there were too few observations to optimise at all.
    pub optimized: bool,
}

/// χ² of one observation at `pose`, `None` if it cannot be evaluated (point behind the
/// camera or non-finite, information not positive and finite).
fn chi2_of(o: &PoseObservation, intr: &Intrinsics, pose: &Isometry3<f64>) -> Option<f64> {
    if !(o.info > 0.0 && o.info.is_finite()) {
        return None;
    }
    let r = o.obs.residual_through(intr, &o.shutter, pose, &o.point_w)?;
    Some(o.info * r.norm_squared())
}

/// Robust cost over the active observations; `None` if an active one became invalid, which
/// makes an LM step that pushes an inlier behind the camera a rejected step.
fn cost(
    obs: &[PoseObservation],
    active: &[bool],
    intr: &Intrinsics,
    pose: &Isometry3<f64>,
    robust: bool,
) -> Option<f64> {
    let mut total = 0.0;
    for (o, _) in obs.iter().zip(active).filter(|(_, a)| **a) {
        let chi2 = chi2_of(o, intr, pose)?;
        total += if robust {
            huber(chi2, o.obs.chi2_threshold()).0
        } else {
            chi2
        };
    }
    Some(total)
}

/// Classifies every observation at `pose`; returns the mask and the inliers' χ² sum.
fn classify(obs: &[PoseObservation], intr: &Intrinsics, pose: &Isometry3<f64>) -> (Vec<bool>, f64) {
    let mut chi2_sum = 0.0;
    let mask = obs
        .iter()
        .map(|o| match chi2_of(o, intr, pose) {
            Some(c) if c <= o.obs.chi2_threshold() => {
                chi2_sum += c;
                true
            }
            _ => false,
        })
        .collect();
    (mask, chi2_sum)
}

/// Runs up to `iterations` LM iterations on the active observations (Nielsen's damping
/// update with step rejection). Returns the final pose.
fn levenberg_marquardt(
    obs: &[PoseObservation],
    active: &[bool],
    intr: &Intrinsics,
    mut pose: Isometry3<f64>,
    robust: bool,
    iterations: usize,
) -> Isometry3<f64> {
    let Some(mut current) = cost(obs, active, intr, &pose, robust) else {
        return pose;
    };
    let mut lambda: Option<f64> = None;
    let mut nu = 2.0;
    for _ in 0..iterations {
        let mut h = Matrix6::zeros();
        let mut b = Vector6::zeros();
        for (o, _) in obs.iter().zip(active).filter(|(_, a)| **a) {
            let Some(lin) = o.obs.linearize_through(intr, &o.shutter, &pose, &o.point_w) else {
                continue;
            };
            let chi2 = o.info * lin.residual.norm_squared();
            let w = if robust {
                o.info * huber(chi2, o.obs.chi2_threshold()).1
            } else {
                o.info
            };
            let jt = lin.jac_pose.transpose();
            h += jt * lin.jac_pose * w;
            b += jt * lin.residual * w;
        }
        // g2o's initial damping: τ · max diag(H), τ = 1e-5.
        let lam = *lambda.get_or_insert_with(|| 1e-5 * h.diagonal().max().max(1e-12));
        let mut accepted = false;
        let mut lam_try = lam;
        // A few damping increases per iteration, as g2o does, before giving up.
        for _ in 0..10 {
            let damped = h + Matrix6::identity() * lam_try;
            let Some(chol) = damped.cholesky() else {
                lam_try *= nu;
                nu *= 2.0;
                continue;
            };
            let delta = -chol.solve(&b);
            if !delta.iter().all(|x| x.is_finite()) {
                break;
            }
            let candidate = se3::retract(&pose, &delta);
            let predicted = delta.dot(&(delta * lam_try - b));
            match cost(obs, active, intr, &candidate, robust) {
                Some(c) if c < current => {
                    let rho = (current - c) / predicted.max(f64::MIN_POSITIVE);
                    lam_try *= (1.0 - (2.0 * rho - 1.0).powi(3)).max(1.0 / 3.0);
                    nu = 2.0;
                    pose = candidate;
                    current = c;
                    accepted = true;
                    break;
                }
                _ => {
                    lam_try *= nu;
                    nu *= 2.0;
                }
            }
        }
        lambda = Some(lam_try);
        if !accepted {
            break; // no damping made progress: at a (local) minimum
        }
    }
    pose
}

/// Refines a world-to-camera pose against fixed map points (ORB-SLAM's pose optimisation).
///
/// Never panics on bad input: with fewer than `params.min_observations` usable
/// observations, or when every observation is an outlier, it returns the best pose it has
/// and reports the (few) inliers, so the tracker can declare tracking lost.
pub fn refine_pose(
    pose_init: &Isometry3<f64>,
    observations: &[PoseObservation],
    intr: &Intrinsics,
    params: &PoseParams,
) -> PoseRefinement {
    let usable: Vec<bool> = observations
        .iter()
        .map(|o| {
            o.info > 0.0
                && o.info.is_finite()
                && o.point_w.iter().all(|x| x.is_finite())
                && chi2_of(o, intr, pose_init).is_some()
        })
        .collect();
    let n_usable = usable.iter().filter(|u| **u).count();
    if n_usable < params.min_observations.max(1) {
        let (inliers, final_chi2) = classify(observations, intr, pose_init);
        return PoseRefinement {
            pose: *pose_init,
            n_inliers: inliers.iter().filter(|i| **i).count(),
            inliers,
            final_chi2,
            optimized: false,
        };
    }

    let mut pose = *pose_init;
    let mut active = usable.clone();
    for round in 0..params.rounds {
        let robust = round < params.robust_rounds;
        pose = levenberg_marquardt(
            observations,
            &active,
            intr,
            pose,
            robust,
            params.iterations_per_round,
        );
        let (mask, _) = classify(observations, intr, &pose);
        active = mask.iter().zip(&usable).map(|(m, u)| *m && *u).collect();
        let n_active = active.iter().filter(|a| **a).count();
        if n_active < params.min_inliers_to_continue.max(params.min_observations) {
            break;
        }
    }
    let (inliers, final_chi2) = classify(observations, intr, &pose);
    PoseRefinement {
        pose,
        n_inliers: inliers.iter().filter(|i| **i).count(),
        inliers,
        final_chi2,
        optimized: true,
    }
}
