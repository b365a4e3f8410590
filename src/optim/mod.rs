//! Non-linear least squares for the back end: pose-only refinement (tracker), local bundle
//! adjustment (map merger) and pose-graph optimisation (global optimizer).
//!
//! Conventions shared by every submodule:
//! - poses are `Isometry3<f64>` **world-to-camera** (`T_cw`); camera axes x right, y down,
//!   z forward; pinhole intrinsics on undistorted keypoints;
//! - pose updates are left perturbations `T ← exp(δ)·T` with δ = (ω, υ), rotation first
//!   (g2o/ORB-SLAM order), see [`se3`];
//! - each observation carries an isotropic information `1/σ²` (σ = 1.2^octave) and the
//!   Huber kernel acts on the weighted squared error with ORB-SLAM's 95 % χ² thresholds,
//!   see [`reprojection`].

pub mod local_ba;
pub mod pose_graph;
pub mod pose_only;
pub mod reprojection;
pub mod se3;

pub use local_ba::{
    BaCamera, BaError, BaObservation, BaParams, BaPoint, BaPoseEdge, BaProblem, BaReport, Cutoff,
    Termination, solve, solve_with_outlier_rejection,
};
pub use pose_only::{PoseObservation, PoseParams, PoseRefinement, refine_pose};
pub use reprojection::{CHI2_MONO, CHI2_RGBD, Intrinsics, Observation, huber, octave_information};
