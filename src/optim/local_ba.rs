//! Local bundle adjustment: Levenberg–Marquardt over keyframe poses and map points with a
//! Schur complement on the points and a sparse Cholesky of the reduced camera system.
//!
//! Why this shape: in local BA there are a few tens of cameras and thousands of points, and
//! each point's 3×3 block of the normal equations is independent of every other point's.
//! Eliminating the points (Schur complement) leaves a `6·n_cams` square system whose 6×6
//! blocks are non-zero only where two cameras see a common point. That system is assembled
//! as a sparse matrix and factorised with faer's supernodal Cholesky; its *symbolic*
//! factorisation depends only on the co-visibility pattern, so it is computed once per
//! [`solve`] call and only the numeric factorisation is repeated each iteration. Points are
//! then recovered by back-substitution, one 3×3 solve each.
//!
//! Damping is Nielsen's: `H + λI`, λ scaled by the gain ratio on success and by a growing
//! factor on a rejected step. Fixed cameras and fixed points are constants, not variables.
//!
//! Cost: 10 keyframes × 2000 points × 10 000 observations take ≈ 2.8 ms per LM iteration in
//! release on the 2-core dev machine (`ba_timing` in `tests/it/optim_local_ba.rs`).
//!
//! faer's sparse Cholesky runs with faer's global parallelism setting (rayon by default);
//! the reduced systems of local BA are small enough that this rarely matters.

use std::collections::HashMap;

use faer::Side;
use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat};
use nalgebra::{Isometry3, Matrix3, Matrix6, Matrix6x3, Vector3, Vector6};
use thiserror::Error;

use super::reprojection::{Intrinsics, Observation, huber};
use super::se3;

/// A keyframe pose in the problem (world-to-camera).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaCamera {
    pub pose_cw: Isometry3<f64>,
    /// Fixed cameras (e.g. the covisible keyframes at the boundary of the local window) are
    /// constants that anchor the gauge.
    pub fixed: bool,
}

/// A map point in the problem.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaPoint {
    pub position_w: Vector3<f64>,
    pub fixed: bool,
}

/// Observation of `point` in `camera` (indices into the problem's vectors).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaObservation {
    pub camera: usize,
    pub point: usize,
    pub obs: Observation,
    /// Isotropic information 1/σ² (see [`super::reprojection::octave_information`]).
    pub info: f64,
    /// Camera motion from the keyframe's reference time to the exposure of this keypoint's
    /// row (rolling shutter): the point is seen at `shutter · T_cw`. Identity for a global
    /// shutter.
    pub shutter: Isometry3<f64>,
}

/// A measured relative pose between cameras `a` and `b` (indices into the problem's
/// cameras): `a_from_b` ≈ `T_a · T_b⁻¹` (maps `b`'s camera frame into `a`'s), with
/// information `info` over a left perturbation (ω, υ) of it. What a depth registration of
/// surfaces two keyframes share without a common key point measures (see
/// `crate::components::depth_registration`); directions the surfaces leave free carry no
/// information.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaPoseEdge {
    pub a: usize,
    pub b: usize,
    pub a_from_b: Isometry3<f64>,
    pub info: Matrix6<f64>,
}

impl BaPoseEdge {
    /// χ² threshold of the Huber kernel on an edge (6 dof, 95 %).
    const CHI2_THRESHOLD: f64 = 12.592;

    /// The error `log(T_a · T_b⁻¹ · Z⁻¹)`: zero when the poses agree with the measurement.
    fn residual(&self, pose_a: &Isometry3<f64>, pose_b: &Isometry3<f64>) -> Vector6<f64> {
        se3::log(&(pose_a * pose_b.inverse() * self.a_from_b.inverse()))
    }

    fn chi2(&self, state: &State) -> f64 {
        let r = self.residual(&state.poses[self.a], &state.poses[self.b]);
        r.dot(&(self.info * r))
    }

    /// Residual and its Jacobians with respect to left perturbations of `T_a` and `T_b`
    /// (central differences: two 6×6 blocks per edge, negligible beside the observations).
    fn linearize(&self, state: &State) -> (Vector6<f64>, Matrix6<f64>, Matrix6<f64>) {
        let (pa, pb) = (&state.poses[self.a], &state.poses[self.b]);
        let r = self.residual(pa, pb);
        let h = 1e-6;
        let mut ja = Matrix6::zeros();
        let mut jb = Matrix6::zeros();
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = h;
            let ra = self.residual(&se3::retract(pa, &d), pb)
                - self.residual(&se3::retract(pa, &-d), pb);
            let rb = self.residual(pa, &se3::retract(pb, &d))
                - self.residual(pa, &se3::retract(pb, &-d));
            ja.set_column(k, &(ra / (2.0 * h)));
            jb.set_column(k, &(rb / (2.0 * h)));
        }
        (r, ja, jb)
    }
}

/// A bundle-adjustment problem; [`solve`] updates poses and points in place.
#[derive(Debug, Clone, PartialEq)]
pub struct BaProblem {
    pub keyframes: Vec<BaCamera>,
    pub points: Vec<BaPoint>,
    pub observations: Vec<BaObservation>,
    pub intrinsics: Intrinsics,
    /// Relative-pose edges between cameras, besides the observations (usually none).
    pub pose_edges: Vec<BaPoseEdge>,
}

/// Solver settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaParams {
    /// Maximum LM iterations (linearisations). ORB-SLAM's local BA runs 5 + 10.
    pub iterations: usize,
    /// Use the Huber kernel (δ² = the observation's χ² threshold) — ORB-SLAM does.
    pub huber: bool,
    /// Initial λ = `tau · max diag(H)` (g2o uses 1e-5).
    pub tau: f64,
    /// Damping increases tried within one iteration before giving up.
    pub max_rejections: usize,
    /// Stop when an accepted step lowers the cost by less than this fraction.
    pub relative_tolerance: f64,
    /// Stop before the next iteration once this says so (Final's refinement after a user
    /// stop); the estimate so far stands.
    pub cutoff: Option<Cutoff>,
}

/// When a solve must end early: a deadline, or a check for a stop signal (a plain function,
/// so that the solver knows nothing of where it comes from).
#[derive(Debug, Clone, Copy)]
pub struct Cutoff {
    pub deadline: Option<std::time::Instant>,
    pub signal: Option<fn() -> bool>,
}

impl Cutoff {
    pub fn reached(&self) -> bool {
        self.deadline
            .is_some_and(|d| std::time::Instant::now() >= d)
            || self.signal.is_some_and(|f| f())
    }
}

impl PartialEq for Cutoff {
    /// Function pointers do not compare reliably; two cutoffs are alike when they have the
    /// same deadline and both or neither check a signal.
    fn eq(&self, other: &Self) -> bool {
        self.deadline == other.deadline && self.signal.is_some() == other.signal.is_some()
    }
}

impl Default for BaParams {
    fn default() -> Self {
        Self {
            iterations: 10,
            huber: true,
            tau: 1e-5,
            max_rejections: 10,
            relative_tolerance: 1e-10,
            cutoff: None,
        }
    }
}

/// Why the solver stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Termination {
    /// Ran the requested number of iterations.
    MaxIterations,
    /// The cost decrease fell below `relative_tolerance` or the gradient vanished.
    Converged,
    /// No damping produced a cost decrease (local minimum or numerical trouble).
    NoProgress,
    /// There was nothing to optimise (no free variable with a valid observation).
    NothingToOptimize,
    /// `BaParams::cutoff` was reached.
    CutOff,
}

/// Outcome of [`solve`].
#[derive(Debug, Clone, PartialEq)]
pub struct BaReport {
    /// Sum of plain χ² (`info·|r|²`) over the observations valid at the start.
    pub initial_chi2: f64,
    /// Same sum over the observations valid at the end.
    pub final_chi2: f64,
    /// Optimised objective (robust if `huber`) at the start and the end.
    pub initial_cost: f64,
    pub final_cost: f64,
    /// Objective after each iteration (length = `iterations`).
    pub cost_per_iteration: Vec<f64>,
    pub iterations: usize,
    /// Indices of observations whose χ² exceeds their threshold after the solve, or whose
    /// point ended up behind the camera — candidates for removal by the map merger.
    pub outliers: Vec<usize>,
    /// The camera held fixed to remove the gauge freedom when none was marked fixed.
    pub gauge_fixed_camera: Option<usize>,
    pub termination: Termination,
}

/// Inputs [`solve`] refuses rather than panicking on.
#[derive(Debug, Error, PartialEq)]
pub enum BaError {
    #[error("observation {observation} refers to camera {camera}, but there are {n} cameras")]
    CameraOutOfRange {
        observation: usize,
        camera: usize,
        n: usize,
    },
    #[error("observation {observation} refers to point {point}, but there are {n} points")]
    PointOutOfRange {
        observation: usize,
        point: usize,
        n: usize,
    },
    #[error("observation {0} has a non-positive or non-finite information weight")]
    BadInformation(usize),
    #[error("pose edge {edge} joins cameras {a} and {b}, but there are {n} cameras (or a = b)")]
    EdgeOutOfRange {
        edge: usize,
        a: usize,
        b: usize,
        n: usize,
    },
    #[error("pose edge {0} has a non-finite or non-symmetric information matrix")]
    BadEdgeInformation(usize),
    #[error("camera {0} has a non-finite pose")]
    NonFinitePose(usize),
    #[error("point {0} has a non-finite position")]
    NonFinitePoint(usize),
    #[error("sparse symbolic factorisation failed: {0}")]
    Symbolic(String),
}

/// Index structure of the problem, built once per [`solve`].
struct Structure {
    /// Free-variable index of each camera / point (`None` = fixed).
    cam_var: Vec<Option<usize>>,
    point_var: Vec<Option<usize>>,
    n_cam: usize,
    n_point: usize,
    /// Observations of each free point, CSR style: `point_obs[point_obs_start[p]..[p+1]]`.
    point_obs_start: Vec<usize>,
    point_obs: Vec<usize>,
    /// Per free point, the block of each Schur update, in the order [`for_each_pair`] visits
    /// the point's pairs of observations: the pairs themselves are implied by that order, so
    /// only 4 bytes a pair are kept (in Final's BA with frames, where every camera sees the
    /// same points, the pairs are the solver's largest array).
    pair_start: Vec<usize>,
    pairs: Vec<u32>,
    /// Block `(row cam, col cam)` of the upper triangle of the reduced system.
    blocks: Vec<(usize, usize)>,
    /// Index of the diagonal block of each free camera.
    diag_block: Vec<usize>,
    /// Per pose edge, its off-diagonal block when both cameras are free.
    edge_block: Vec<Option<usize>>,
    /// For each block and each of its 6 columns, the offset in the CSC values of its first
    /// row (rows are contiguous within a block column).
    block_offsets: Vec<[usize; 6]>,
    symbolic: Option<(SymbolicSparseColMat<usize>, SymbolicLlt<usize>)>,
    n_values: usize,
}

impl Structure {
    #[allow(clippy::needless_range_loop)] // c indexes both a block's columns and its offsets
    fn build(problem: &BaProblem, fixed_cam: &[bool]) -> Result<Self, BaError> {
        let mut cam_var = vec![None; problem.keyframes.len()];
        let mut n_cam = 0;
        for (c, v) in cam_var.iter_mut().enumerate() {
            if !fixed_cam[c] {
                *v = Some(n_cam);
                n_cam += 1;
            }
        }
        let mut point_var = vec![None; problem.points.len()];
        let mut n_point = 0;
        for (p, v) in point_var.iter_mut().enumerate() {
            if !problem.points[p].fixed {
                *v = Some(n_point);
                n_point += 1;
            }
        }
        // Observations grouped by free point (counting sort).
        let mut counts = vec![0usize; n_point + 1];
        for o in &problem.observations {
            if let Some(p) = point_var[o.point] {
                counts[p + 1] += 1;
            }
        }
        for p in 0..n_point {
            counts[p + 1] += counts[p];
        }
        let point_obs_start = counts.clone();
        let mut point_obs = vec![0; counts[n_point]];
        let mut fill = counts;
        for (k, o) in problem.observations.iter().enumerate() {
            if let Some(p) = point_var[o.point] {
                point_obs[fill[p]] = k;
                fill[p] += 1;
            }
        }

        // Block pattern of the reduced camera system (upper triangle, ci ≤ cj).
        let mut block_index: HashMap<(usize, usize), usize> = HashMap::new();
        let mut blocks = Vec::new();
        let mut diag_block = Vec::with_capacity(n_cam);
        for c in 0..n_cam {
            diag_block.push(blocks.len());
            block_index.insert((c, c), blocks.len());
            blocks.push((c, c));
        }
        let mut pair_start = Vec::with_capacity(n_point + 1);
        // Sized exactly: with many cameras sharing points (Final's BA with frames) the pairs
        // are the solver's largest array, and growing it by doubling would peak at up to
        // three times its size.
        let n_pairs: usize = (0..n_point)
            .map(|p| {
                let m = point_obs[point_obs_start[p]..point_obs_start[p + 1]]
                    .iter()
                    .filter(|&&o| cam_var[problem.observations[o].camera].is_some())
                    .count();
                m * (m + 1) / 2
            })
            .sum();
        let mut pairs = Vec::with_capacity(n_pairs);
        for p in 0..n_point {
            pair_start.push(pairs.len());
            let obs = &point_obs[point_obs_start[p]..point_obs_start[p + 1]];
            for_each_pair(problem, &cam_var, obs, |_, _, ci, cj| {
                let next = blocks.len();
                let b = *block_index.entry((ci, cj)).or_insert(next);
                if b == next {
                    blocks.push((ci, cj));
                }
                pairs.push(b as u32);
            });
        }
        pair_start.push(pairs.len());
        let edge_block = problem
            .pose_edges
            .iter()
            .map(|e| {
                let (ca, cb) = (cam_var[e.a]?, cam_var[e.b]?);
                let key = (ca.min(cb), ca.max(cb));
                let next = blocks.len();
                let b = *block_index.entry(key).or_insert(next);
                if b == next {
                    blocks.push(key);
                }
                Some(b)
            })
            .collect();

        // CSC layout of the upper triangle: block column cj holds its row blocks in
        // increasing ci; within a block column every scalar column has the same rows,
        // except that the diagonal block is cut at the diagonal.
        let mut by_col: Vec<Vec<usize>> = vec![Vec::new(); n_cam];
        for (b, &(_, cj)) in blocks.iter().enumerate() {
            by_col[cj].push(b);
        }
        let n = 6 * n_cam;
        let mut col_ptr = Vec::with_capacity(n + 1);
        // 21 values in a diagonal block's upper triangle, 36 in any other block.
        let mut row_idx = Vec::with_capacity(21 * n_cam + 36 * (blocks.len() - n_cam));
        let mut block_offsets = vec![[0usize; 6]; blocks.len()];
        col_ptr.push(0);
        for (cj, col_blocks) in by_col.iter_mut().enumerate() {
            col_blocks.sort_by_key(|&b| blocks[b].0);
            for c in 0..6 {
                for &b in col_blocks.iter() {
                    let ci = blocks[b].0;
                    block_offsets[b][c] = row_idx.len();
                    let rows = if ci == cj { c + 1 } else { 6 };
                    row_idx.extend((0..rows).map(|r| 6 * ci + r));
                }
                col_ptr.push(row_idx.len());
            }
        }
        let n_values = row_idx.len();
        let symbolic = if n_cam > 0 {
            let sym = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
            let llt = SymbolicLlt::try_new(sym.as_ref(), Side::Upper)
                .map_err(|e| BaError::Symbolic(format!("{e:?}")))?;
            Some((sym, llt))
        } else {
            None
        };
        Ok(Self {
            cam_var,
            point_var,
            n_cam,
            n_point,
            point_obs_start,
            point_obs,
            pair_start,
            pairs,
            blocks,
            diag_block,
            edge_block,
            block_offsets,
            symbolic,
            n_values,
        })
    }

    /// Applies `f(value, row, column)` to each stored value of block `b` of the reduced
    /// system (row and column within the 6×6 block; a diagonal block stores its upper
    /// triangle only).
    fn block_values(
        &self,
        b: usize,
        mut f: impl FnMut(&mut f64, usize, usize),
        values: &mut [f64],
    ) {
        let (ci, cj) = self.blocks[b];
        for c in 0..6 {
            let rows = if ci == cj { c + 1 } else { 6 };
            let off = self.block_offsets[b][c];
            for (r, v) in values[off..off + rows].iter_mut().enumerate() {
                f(v, r, c);
            }
        }
    }
}

/// Calls `f(i, j, ci, cj)` for each pair of a point's observations `obs` (`i`, `j` index
/// `obs`) whose cameras are free with variables `ci ≤ cj`, always in the same order: the
/// order [`Structure::pairs`] is stored in.
fn for_each_pair(
    problem: &BaProblem,
    cam_var: &[Option<usize>],
    obs: &[usize],
    mut f: impl FnMut(usize, usize, usize, usize),
) {
    for (i, &oi) in obs.iter().enumerate() {
        let Some(ci) = cam_var[problem.observations[oi].camera] else {
            continue;
        };
        for (j, &oj) in obs.iter().enumerate() {
            let Some(cj) = cam_var[problem.observations[oj].camera] else {
                continue;
            };
            if ci <= cj {
                f(i, j, ci, cj);
            }
        }
    }
}

/// The (undamped) normal equations `H δ = −b` in block form.
struct NormalEquations {
    h_cc: Vec<Matrix6<f64>>,
    b_c: Vec<Vector6<f64>>,
    h_pp: Vec<Matrix3<f64>>,
    b_p: Vec<Vector3<f64>>,
    /// Camera–point block per observation (zero unless both are free).
    h_cp: Vec<Matrix6x3<f64>>,
    /// Per pose edge, its block `(min camera, max camera)` of the reduced system (zero
    /// unless [`Structure::edge_block`] has one).
    h_edge: Vec<Matrix6<f64>>,
}

/// Current estimate of every camera and point (fixed ones included, unchanged).
#[derive(Clone)]
struct State {
    poses: Vec<Isometry3<f64>>,
    points: Vec<Vector3<f64>>,
}

/// χ² of observation `o` in `state`, `None` when it cannot be evaluated.
fn obs_chi2(problem: &BaProblem, state: &State, o: &BaObservation) -> Option<f64> {
    let r = o.obs.residual_through(
        &problem.intrinsics,
        &o.shutter,
        &state.poses[o.camera],
        &state.points[o.point],
    )?;
    Some(o.info * r.norm_squared())
}

fn robust_cost(chi2: f64, o: &BaObservation, use_huber: bool) -> f64 {
    if use_huber {
        huber(chi2, o.obs.chi2_threshold()).0
    } else {
        chi2
    }
}

/// Robust cost of an edge's χ².
fn edge_cost(chi2: f64, use_huber: bool) -> f64 {
    if use_huber {
        huber(chi2, BaPoseEdge::CHI2_THRESHOLD).0
    } else {
        chi2
    }
}

/// Objective of the pose edges and their plain χ² sum.
fn evaluate_edges(problem: &BaProblem, state: &State, use_huber: bool) -> (f64, f64) {
    problem.pose_edges.iter().fold((0.0, 0.0), |(c, x), e| {
        let chi2 = e.chi2(state);
        (c + edge_cost(chi2, use_huber), x + chi2)
    })
}

/// Objective over the observations in `mask` and the pose edges; `None` if an observation
/// became invalid.
fn evaluate(problem: &BaProblem, state: &State, mask: &[bool], use_huber: bool) -> Option<f64> {
    let mut total = evaluate_edges(problem, state, use_huber).0;
    for (o, _) in problem.observations.iter().zip(mask).filter(|(_, m)| **m) {
        total += robust_cost(obs_chi2(problem, state, o)?, o, use_huber);
    }
    Some(total)
}

/// Validity mask, objective and plain χ² sum at `state`.
fn evaluate_all(problem: &BaProblem, state: &State, use_huber: bool) -> (Vec<bool>, f64, f64) {
    let (mut cost, mut chi2_sum) = evaluate_edges(problem, state, use_huber);
    let mask = problem
        .observations
        .iter()
        .map(|o| match obs_chi2(problem, state, o) {
            Some(c) => {
                cost += robust_cost(c, o, use_huber);
                chi2_sum += c;
                true
            }
            None => false,
        })
        .collect();
    (mask, cost, chi2_sum)
}

fn linearize(
    problem: &BaProblem,
    st: &Structure,
    state: &State,
    use_huber: bool,
) -> (NormalEquations, f64) {
    let mut ne = NormalEquations {
        h_cc: vec![Matrix6::zeros(); st.n_cam],
        b_c: vec![Vector6::zeros(); st.n_cam],
        h_pp: vec![Matrix3::zeros(); st.n_point],
        b_p: vec![Vector3::zeros(); st.n_point],
        h_cp: vec![Matrix6x3::zeros(); problem.observations.len()],
        h_edge: vec![Matrix6::zeros(); problem.pose_edges.len()],
    };
    for (k, o) in problem.observations.iter().enumerate() {
        let cv = st.cam_var[o.camera];
        let pv = st.point_var[o.point];
        if cv.is_none() && pv.is_none() {
            continue;
        }
        let Some(lin) = o.obs.linearize_through(
            &problem.intrinsics,
            &o.shutter,
            &state.poses[o.camera],
            &state.points[o.point],
        ) else {
            continue;
        };
        let chi2 = o.info * lin.residual.norm_squared();
        // IRLS weight: information times the kernel's derivative (g2o's robustified Ω).
        let w = if use_huber {
            o.info * huber(chi2, o.obs.chi2_threshold()).1
        } else {
            o.info
        };
        let wr = lin.residual * w;
        let wjp = lin.jac_point * w;
        if let Some(c) = cv {
            let jct = lin.jac_pose.transpose();
            ne.h_cc[c] += jct * (lin.jac_pose * w);
            ne.b_c[c] += jct * wr;
            if pv.is_some() {
                ne.h_cp[k] = jct * wjp;
            }
        }
        if let Some(p) = pv {
            let jpt = lin.jac_point.transpose();
            ne.h_pp[p] += jpt * wjp;
            ne.b_p[p] += jpt * wr;
        }
    }
    for (k, e) in problem.pose_edges.iter().enumerate() {
        let (ca, cb) = (st.cam_var[e.a], st.cam_var[e.b]);
        if ca.is_none() && cb.is_none() {
            continue;
        }
        let (r, ja, jb) = e.linearize(state);
        let w = if use_huber {
            huber(r.dot(&(e.info * r)), BaPoseEdge::CHI2_THRESHOLD).1
        } else {
            1.0
        };
        let info = e.info * w;
        if let Some(a) = ca {
            ne.h_cc[a] += ja.transpose() * info * ja;
            ne.b_c[a] += ja.transpose() * info * r;
        }
        if let Some(b) = cb {
            ne.h_cc[b] += jb.transpose() * info * jb;
            ne.b_c[b] += jb.transpose() * info * r;
        }
        if let (Some(a), Some(b)) = (ca, cb) {
            if a < b {
                ne.h_edge[k] = ja.transpose() * info * jb;
            } else {
                ne.h_edge[k] = jb.transpose() * info * ja;
            }
        }
    }
    let max_diag = ne
        .h_cc
        .iter()
        .map(|h| h.diagonal().max())
        .chain(ne.h_pp.iter().map(|h| h.diagonal().max()))
        .fold(0.0f64, f64::max);
    (ne, max_diag)
}

/// An LM step: one increment per free camera and per free point.
type Step = (Vec<Vector6<f64>>, Vec<Vector3<f64>>);

/// Solves `(H + λI) δ = −b` by the Schur complement on the points and faer's sparse
/// Cholesky on the reduced camera system. `None` if a damped block is not positive
/// definite (the caller then raises λ).
// Index loops: several parallel per-point arrays are read at the same index.
#[allow(clippy::needless_range_loop)]
fn schur_step(
    problem: &BaProblem,
    st: &Structure,
    ne: &NormalEquations,
    lambda: f64,
) -> Option<Step> {
    let damp3 = Matrix3::identity() * lambda;
    let mut h_pp_inv = Vec::with_capacity(st.n_point);
    for h in &ne.h_pp {
        h_pp_inv.push((h + damp3).cholesky()?.inverse());
    }
    let mut dx_c = vec![Vector6::zeros(); st.n_cam];
    if let Some((sym, llt_sym)) = &st.symbolic {
        // The reduced system is summed straight into its CSC values (no 6×6 copy of each
        // block first: with every camera seeing the same points that copy is as large as the
        // values themselves).
        let mut values = vec![0.0; st.n_values];
        let mut rhs: Vec<f64> = Vec::with_capacity(6 * st.n_cam);
        for c in 0..st.n_cam {
            let m = ne.h_cc[c] + Matrix6::identity() * lambda;
            st.block_values(st.diag_block[c], |v, r, k| *v += m[(r, k)], &mut values);
        }
        for (k, b) in st.edge_block.iter().enumerate() {
            if let Some(b) = b {
                let m = &ne.h_edge[k];
                st.block_values(*b, |v, r, c| *v += m[(r, c)], &mut values);
            }
        }
        let mut rhs_c: Vec<Vector6<f64>> = ne.b_c.iter().map(|b| -b).collect();
        let mut y: Vec<Matrix6x3<f64>> = Vec::new();
        for p in 0..st.n_point {
            let obs = &st.point_obs[st.point_obs_start[p]..st.point_obs_start[p + 1]];
            y.clear();
            for &k in obs {
                // Y_i = H_cp · H_pp⁻¹ (zero when the camera is fixed).
                let yk = ne.h_cp[k] * h_pp_inv[p];
                if let Some(c) = st.cam_var[problem.observations[k].camera] {
                    rhs_c[c] += yk * ne.b_p[p];
                }
                y.push(yk);
            }
            let mut blocks = st.pairs[st.pair_start[p]..st.pair_start[p + 1]].iter();
            for_each_pair(problem, &st.cam_var, obs, |i, j, _, _| {
                let b = *blocks.next().expect("one block per pair, as built") as usize;
                let m = y[i] * ne.h_cp[obs[j]].transpose();
                st.block_values(b, |v, r, c| *v -= m[(r, c)], &mut values);
            });
        }
        let mat = SparseColMatRef::new(sym.as_ref(), &values);
        let llt = Llt::try_new_with_symbolic(llt_sym.clone(), mat, Side::Upper).ok()?;
        for r in &rhs_c {
            rhs.extend(r.iter());
        }
        let n = rhs.len();
        let mut x = faer::MatMut::from_column_major_slice_mut(&mut rhs, n, 1);
        llt.solve_in_place(x.as_mut());
        for (c, d) in dx_c.iter_mut().enumerate() {
            *d = Vector6::from_column_slice(&rhs[6 * c..6 * c + 6]);
        }
    }
    // Back-substitution: δp = H_pp⁻¹ (−b_p − Σ H_cpᵀ δc).
    let mut dx_p = Vec::with_capacity(st.n_point);
    for p in 0..st.n_point {
        let mut r = -ne.b_p[p];
        for &k in &st.point_obs[st.point_obs_start[p]..st.point_obs_start[p + 1]] {
            if let Some(c) = st.cam_var[problem.observations[k].camera] {
                r -= ne.h_cp[k].transpose() * dx_c[c];
            }
        }
        dx_p.push(h_pp_inv[p] * r);
    }
    let finite = dx_c.iter().all(|d| d.iter().all(|x| x.is_finite()))
        && dx_p.iter().all(|d| d.iter().all(|x| x.is_finite()));
    finite.then_some((dx_c, dx_p))
}

fn apply_step(
    st: &Structure,
    state: &State,
    dx_c: &[Vector6<f64>],
    dx_p: &[Vector3<f64>],
) -> State {
    let mut next = state.clone();
    for (c, v) in st.cam_var.iter().enumerate() {
        if let Some(v) = v {
            next.poses[c] = se3::retract(&state.poses[c], &dx_c[*v]);
        }
    }
    for (p, v) in st.point_var.iter().enumerate() {
        if let Some(v) = v {
            next.points[p] += dx_p[*v];
        }
    }
    next
}

fn validate(problem: &BaProblem) -> Result<(), BaError> {
    for (c, k) in problem.keyframes.iter().enumerate() {
        let ok = k.pose_cw.translation.vector.iter().all(|x| x.is_finite())
            && k.pose_cw.rotation.coords.iter().all(|x| x.is_finite());
        if !ok {
            return Err(BaError::NonFinitePose(c));
        }
    }
    for (p, pt) in problem.points.iter().enumerate() {
        if !pt.position_w.iter().all(|x| x.is_finite()) {
            return Err(BaError::NonFinitePoint(p));
        }
    }
    for (k, o) in problem.observations.iter().enumerate() {
        if o.camera >= problem.keyframes.len() {
            return Err(BaError::CameraOutOfRange {
                observation: k,
                camera: o.camera,
                n: problem.keyframes.len(),
            });
        }
        if o.point >= problem.points.len() {
            return Err(BaError::PointOutOfRange {
                observation: k,
                point: o.point,
                n: problem.points.len(),
            });
        }
        if !(o.info > 0.0 && o.info.is_finite()) {
            return Err(BaError::BadInformation(k));
        }
    }
    let n = problem.keyframes.len();
    for (k, e) in problem.pose_edges.iter().enumerate() {
        if e.a >= n || e.b >= n || e.a == e.b {
            return Err(BaError::EdgeOutOfRange {
                edge: k,
                a: e.a,
                b: e.b,
                n,
            });
        }
        let symmetric = (e.info - e.info.transpose()).norm() <= 1e-9 * e.info.norm().max(1.0);
        if !(e.info.iter().all(|x| x.is_finite()) && symmetric) {
            return Err(BaError::BadEdgeInformation(k));
        }
    }
    Ok(())
}

/// Cameras held fixed: the user's flags, plus the first camera if none is fixed (the
/// reprojection error is invariant to a global rigid motion, so without an anchor the
/// normal equations are singular up to damping and the solution drifts).
fn fixed_cameras(problem: &BaProblem) -> (Vec<bool>, Option<usize>) {
    let mut fixed: Vec<bool> = problem.keyframes.iter().map(|k| k.fixed).collect();
    let mut gauge = None;
    if !fixed.iter().any(|f| *f) && !fixed.is_empty() {
        fixed[0] = true;
        gauge = Some(0);
    }
    (fixed, gauge)
}

/// Observations whose χ² exceeds their threshold, or that cannot be evaluated.
fn outliers_at(problem: &BaProblem, state: &State) -> Vec<usize> {
    problem
        .observations
        .iter()
        .enumerate()
        .filter(|(_, o)| match obs_chi2(problem, state, o) {
            Some(c) => c > o.obs.chi2_threshold(),
            None => true,
        })
        .map(|(k, _)| k)
        .collect()
}

/// Runs Levenberg–Marquardt bundle adjustment, updating the problem's free poses and points.
pub fn solve(problem: &mut BaProblem, params: &BaParams) -> Result<BaReport, BaError> {
    validate(problem)?;
    let (fixed_cam, gauge_fixed_camera) = fixed_cameras(problem);
    let st = Structure::build(problem, &fixed_cam)?;
    let mut state = State {
        poses: problem.keyframes.iter().map(|k| k.pose_cw).collect(),
        points: problem.points.iter().map(|p| p.position_w).collect(),
    };
    let use_huber = params.huber;
    let (mut mask, initial_cost, initial_chi2) = evaluate_all(problem, &state, use_huber);
    let mut cost = initial_cost;
    let mut cost_per_iteration = Vec::with_capacity(params.iterations);
    let mut lambda: Option<f64> = None;
    let mut nu = 2.0;
    let mut termination = Termination::MaxIterations;
    let has_variables = st.n_cam + st.n_point > 0 && mask.iter().any(|m| *m);
    if !has_variables {
        termination = Termination::NothingToOptimize;
    }
    let mut iterations = 0;
    while has_variables && iterations < params.iterations {
        if params.cutoff.is_some_and(|c| c.reached()) {
            termination = Termination::CutOff;
            break;
        }
        iterations += 1;
        let (ne, max_diag) = linearize(problem, &st, &state, use_huber);
        let grad_inf = ne
            .b_c
            .iter()
            .flat_map(|b| b.iter())
            .chain(ne.b_p.iter().flat_map(|b| b.iter()))
            .fold(0.0f64, |m, x| m.max(x.abs()));
        if grad_inf < 1e-12 {
            cost_per_iteration.push(cost);
            termination = Termination::Converged;
            break;
        }
        let mut lam = *lambda.get_or_insert_with(|| params.tau * max_diag.max(1e-12));
        let mut accepted = false;
        for _ in 0..params.max_rejections.max(1) {
            let trial = schur_step(problem, &st, &ne, lam).and_then(|(dc, dp)| {
                let next = apply_step(&st, &state, &dc, &dp);
                let c = evaluate(problem, &next, &mask, use_huber)?;
                // Predicted decrease of the quadratic model: δᵀ(λδ − b).
                let predicted: f64 = dc
                    .iter()
                    .zip(&ne.b_c)
                    .map(|(d, b)| d.dot(&(d * lam - b)))
                    .chain(dp.iter().zip(&ne.b_p).map(|(d, b)| d.dot(&(d * lam - b))))
                    .sum();
                Some((next, c, predicted))
            });
            match trial {
                Some((next, c, predicted)) if c < cost => {
                    let rho = (cost - c) / predicted.max(f64::MIN_POSITIVE);
                    lam *= (1.0 - (2.0 * rho - 1.0).powi(3)).max(1.0 / 3.0);
                    nu = 2.0;
                    let decrease = (cost - c) / cost.max(f64::MIN_POSITIVE);
                    state = next;
                    // Re-evaluate on the new state: observations may have become valid.
                    let (m, new_cost, _) = evaluate_all(problem, &state, use_huber);
                    mask = m;
                    cost = new_cost;
                    accepted = true;
                    if decrease < params.relative_tolerance {
                        termination = Termination::Converged;
                    }
                    break;
                }
                _ => {
                    lam *= nu;
                    nu *= 2.0;
                }
            }
        }
        lambda = Some(lam);
        cost_per_iteration.push(cost);
        if !accepted {
            termination = Termination::NoProgress;
            break;
        }
        if termination == Termination::Converged {
            break;
        }
    }

    for (k, pose) in problem.keyframes.iter_mut().zip(&state.poses) {
        k.pose_cw = *pose;
    }
    for (p, pos) in problem.points.iter_mut().zip(&state.points) {
        p.position_w = *pos;
    }
    let (_, final_cost, final_chi2) = evaluate_all(problem, &state, use_huber);
    let outliers = outliers_at(problem, &state);
    Ok(BaReport {
        initial_chi2,
        final_chi2,
        initial_cost,
        final_cost,
        cost_per_iteration,
        iterations,
        outliers,
        gauge_fixed_camera,
        termination,
    })
}

/// ORB-SLAM's local-BA schedule: a robust solve (`first`, ORB-SLAM: 5 iterations with
/// Huber), then the observations it flags as outliers are set aside and a second solve
/// (`second`, ORB-SLAM: 10 iterations without the kernel) refines on the inliers only.
///
/// The returned report spans both stages: initial values from the first, final values and
/// per-iteration costs concatenated, and `outliers` re-evaluated over **all** observations
/// at the final estimate, so the caller can erase those map-point observations.
pub fn solve_with_outlier_rejection(
    problem: &mut BaProblem,
    first: &BaParams,
    second: &BaParams,
) -> Result<BaReport, BaError> {
    let r1 = solve(problem, first)?;
    if r1.outliers.is_empty() {
        let r2 = solve(problem, second)?;
        return Ok(merge_reports(r1, r2, outliers_all(problem)));
    }
    // Solve without the outliers, then copy the estimate back. The observations are the
    // largest array of a BA (Final's most of all): they are moved into the inlier problem,
    // the outliers set aside, and restored in their order afterwards, not copied.
    let mut observations = std::mem::take(&mut problem.observations);
    let total = observations.len();
    let mut set_aside = Vec::with_capacity(r1.outliers.len());
    let mut outlier_iter = r1.outliers.iter().peekable();
    let mut kept = 0;
    for k in 0..total {
        if outlier_iter.peek() == Some(&&k) {
            outlier_iter.next();
            set_aside.push(observations[k]);
        } else {
            observations[kept] = observations[k];
            kept += 1;
        }
    }
    observations.truncate(kept);
    let mut inlier_problem = BaProblem {
        keyframes: problem.keyframes.clone(),
        points: problem.points.clone(),
        observations,
        intrinsics: problem.intrinsics,
        pose_edges: problem.pose_edges.clone(),
    };
    // Keep the gauge of the first stage even if its anchor lost all its observations.
    if let Some(c) = r1.gauge_fixed_camera {
        inlier_problem.keyframes[c].fixed = true;
    }
    let r2 = solve(&mut inlier_problem, second);
    problem.observations = restore_outliers(
        std::mem::take(&mut inlier_problem.observations),
        &set_aside,
        &r1.outliers,
    );
    let r2 = r2?;
    for (dst, src) in problem.keyframes.iter_mut().zip(&inlier_problem.keyframes) {
        dst.pose_cw = src.pose_cw;
    }
    for (dst, src) in problem.points.iter_mut().zip(&inlier_problem.points) {
        dst.position_w = src.position_w;
    }
    Ok(merge_reports(r1, r2, outliers_all(problem)))
}

/// The inliers with the outliers set aside put back at their indices (`outliers`, sorted):
/// filled from the back, in the inliers' own buffer.
fn restore_outliers(
    mut observations: Vec<BaObservation>,
    set_aside: &[BaObservation],
    outliers: &[usize],
) -> Vec<BaObservation> {
    let kept = observations.len();
    let Some(&filler) = observations.first().or(set_aside.first()) else {
        return observations;
    };
    observations.resize(kept + set_aside.len(), filler);
    let (mut inlier, mut outlier) = (kept, set_aside.len());
    for k in (0..observations.len()).rev() {
        if outlier > 0 && outliers[outlier - 1] == k {
            outlier -= 1;
            observations[k] = set_aside[outlier];
        } else {
            inlier -= 1;
            observations[k] = observations[inlier];
        }
    }
    observations
}

/// Outliers over every observation of `problem` at its current estimate.
fn outliers_all(problem: &BaProblem) -> Vec<usize> {
    let state = State {
        poses: problem.keyframes.iter().map(|k| k.pose_cw).collect(),
        points: problem.points.iter().map(|p| p.position_w).collect(),
    };
    outliers_at(problem, &state)
}

fn merge_reports(r1: BaReport, r2: BaReport, outliers: Vec<usize>) -> BaReport {
    let mut cost_per_iteration = r1.cost_per_iteration;
    cost_per_iteration.extend(r2.cost_per_iteration);
    BaReport {
        initial_chi2: r1.initial_chi2,
        final_chi2: r2.final_chi2,
        initial_cost: r1.initial_cost,
        final_cost: r2.final_cost,
        cost_per_iteration,
        iterations: r1.iterations + r2.iterations,
        outliers,
        gauge_fixed_camera: r1.gauge_fixed_camera,
        termination: r2.termination,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector, Point3, Vector2};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    const INTR: Intrinsics = Intrinsics::TUM_FREIBURG1;

    #[test]
    fn outliers_set_aside_are_restored_at_their_indices() {
        let o = |point| BaObservation {
            camera: 0,
            point,
            obs: Observation::Mono {
                uv: Vector2::zeros(),
            },
            info: 1.0,
            shutter: Isometry3::identity(),
        };
        for outliers in [
            vec![],
            vec![0],
            vec![5],
            vec![0, 2, 3, 5],
            vec![0, 1, 2, 3, 4, 5],
        ] {
            let inliers: Vec<_> = (0..6).filter(|k| !outliers.contains(k)).map(o).collect();
            let aside: Vec<_> = outliers.iter().map(|&k| o(k)).collect();
            let back = restore_outliers(inliers, &aside, &outliers);
            let order: Vec<usize> = back.iter().map(|b| b.point).collect();
            assert_eq!(order, (0..6).collect::<Vec<_>>(), "outliers {outliers:?}");
        }
    }

    /// Small perturbed scene: 5 cameras (camera 0 fixed), 30 points (two fixed), every
    /// camera sees every point, observations alternate mono / RGB-D.
    #[test]
    fn a_cutoff_ends_the_solve_and_keeps_the_estimate_so_far() {
        let run = |cutoff| {
            let mut problem = small_problem(3);
            let start: Vec<_> = problem.keyframes.iter().map(|k| k.pose_cw).collect();
            let params = BaParams {
                cutoff,
                ..Default::default()
            };
            let r = solve(&mut problem, &params).unwrap();
            let moved =
                problem.keyframes.iter().zip(&start).any(|(k, s)| {
                    (k.pose_cw.translation.vector - s.translation.vector).norm() > 0.0
                });
            (r, moved)
        };
        let (free, moved) = run(None);
        assert!(free.iterations > 0 && moved);
        assert!(free.final_cost < free.initial_cost);
        let past = std::time::Instant::now();
        for cutoff in [
            Cutoff {
                deadline: Some(past),
                signal: None,
            },
            Cutoff {
                deadline: None,
                signal: Some(|| true),
            },
        ] {
            let (r, moved) = run(Some(cutoff));
            assert_eq!(r.termination, Termination::CutOff);
            assert_eq!(r.iterations, 0);
            assert!(!moved);
            assert_eq!(r.final_cost, r.initial_cost);
        }
        let later = Cutoff {
            deadline: Some(past + std::time::Duration::from_secs(3600)),
            signal: Some(|| false),
        };
        assert_eq!(run(Some(later)).0, free);
    }

    fn small_problem(seed: u64) -> BaProblem {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let keyframes: Vec<BaCamera> = (0..5)
            .map(|i| {
                let pose_wc = Isometry3::new(
                    Vector3::new(0.2 * i as f64, 0.05 * i as f64, 0.0),
                    Vector3::new(0.0, 0.03 * i as f64, 0.0),
                );
                BaCamera {
                    pose_cw: pose_wc.inverse(),
                    fixed: i == 0,
                }
            })
            .collect();
        let points: Vec<BaPoint> = (0..30)
            .map(|i| BaPoint {
                position_w: Vector3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(3.0..5.0),
                ),
                fixed: i < 2,
            })
            .collect();
        let mut observations = Vec::new();
        for (c, k) in keyframes.iter().enumerate() {
            for (p, pt) in points.iter().enumerate() {
                let pc = (k.pose_cw * Point3::from(pt.position_w)).coords;
                let uv = INTR.project(&pc).unwrap()
                    + Vector2::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
                let obs = if (c + p) % 2 == 0 {
                    Observation::Mono { uv }
                } else {
                    Observation::Rgbd { uv, depth: pc.z }
                };
                observations.push(BaObservation {
                    camera: c,
                    point: p,
                    obs,
                    info: 1.0 / (1.0 + (p % 3) as f64),
                    shutter: Isometry3::identity(),
                });
            }
        }
        let mut problem = BaProblem {
            keyframes,
            points,
            observations,
            intrinsics: INTR,
            pose_edges: Vec::new(),
        };
        for k in problem.keyframes.iter_mut().filter(|k| !k.fixed) {
            let d = Vector6::from_fn(|_, _| rng.random_range(-0.03..0.03));
            k.pose_cw = se3::retract(&k.pose_cw, &d);
        }
        for p in problem.points.iter_mut().filter(|p| !p.fixed) {
            p.position_w += Vector3::from_fn(|_, _| rng.random_range(-0.05..0.05));
        }
        problem
    }

    /// Full normal equations `(H + λI) δ = −b` assembled densely and solved by Cholesky.
    fn dense_step(
        problem: &BaProblem,
        st: &Structure,
        ne: &NormalEquations,
        lambda: f64,
    ) -> DVector<f64> {
        let n = 6 * st.n_cam + 3 * st.n_point;
        let mut h = DMatrix::<f64>::identity(n, n) * lambda;
        let mut b = DVector::<f64>::zeros(n);
        for c in 0..st.n_cam {
            h.view_mut((6 * c, 6 * c), (6, 6)).add_assign(&ne.h_cc[c]);
            b.rows_mut(6 * c, 6).copy_from(&ne.b_c[c]);
        }
        let po = 6 * st.n_cam;
        for p in 0..st.n_point {
            h.view_mut((po + 3 * p, po + 3 * p), (3, 3))
                .add_assign(&ne.h_pp[p]);
            b.rows_mut(po + 3 * p, 3).copy_from(&ne.b_p[p]);
        }
        for (k, o) in problem.observations.iter().enumerate() {
            if let (Some(c), Some(p)) = (st.cam_var[o.camera], st.point_var[o.point]) {
                h.view_mut((6 * c, po + 3 * p), (6, 3))
                    .add_assign(&ne.h_cp[k]);
                h.view_mut((po + 3 * p, 6 * c), (3, 6))
                    .add_assign(&ne.h_cp[k].transpose());
            }
        }
        for (k, e) in problem.pose_edges.iter().enumerate() {
            if let (Some(a), Some(b)) = (st.cam_var[e.a], st.cam_var[e.b]) {
                let (lo, hi) = (a.min(b), a.max(b));
                h.view_mut((6 * lo, 6 * hi), (6, 6))
                    .add_assign(&ne.h_edge[k]);
                h.view_mut((6 * hi, 6 * lo), (6, 6))
                    .add_assign(&ne.h_edge[k].transpose());
            }
        }
        h.cholesky()
            .expect("damped H is positive definite")
            .solve(&(-b))
    }

    use std::ops::AddAssign;

    /// Pose edges between cameras 1–3 and 4–2 (measured from the unperturbed poses, so
    /// slightly inconsistent with the perturbed start) and one to the fixed camera 0.
    fn with_edges(mut problem: BaProblem, truth: &[Isometry3<f64>]) -> BaProblem {
        for (a, b) in [(1, 3), (4, 2), (0, 4)] {
            let info = Matrix6::from_fn(|i, j| if i == j { 1e4 } else { 10.0 });
            problem.pose_edges.push(BaPoseEdge {
                a,
                b,
                a_from_b: truth[a] * truth[b].inverse(),
                info,
            });
        }
        problem
    }

    #[test]
    fn schur_step_equals_dense_solve() {
        for seed in 0..6 {
            let mut problem = small_problem(seed);
            if seed >= 3 {
                let truth: Vec<_> = problem.keyframes.iter().map(|k| k.pose_cw).collect();
                problem = with_edges(problem, &truth);
            }
            let (fixed, _) = fixed_cameras(&problem);
            let st = Structure::build(&problem, &fixed).unwrap();
            let state = State {
                poses: problem.keyframes.iter().map(|k| k.pose_cw).collect(),
                points: problem.points.iter().map(|p| p.position_w).collect(),
            };
            let (ne, max_diag) = linearize(&problem, &st, &state, true);
            for lambda in [1e-6 * max_diag, 1e-2 * max_diag, 1e-9] {
                let (dc, dp) = schur_step(&problem, &st, &ne, lambda).unwrap();
                let dense = dense_step(&problem, &st, &ne, lambda);
                let mut schur = DVector::<f64>::zeros(dense.len());
                for (c, d) in dc.iter().enumerate() {
                    schur.rows_mut(6 * c, 6).copy_from(d);
                }
                for (p, d) in dp.iter().enumerate() {
                    schur.rows_mut(6 * st.n_cam + 3 * p, 3).copy_from(d);
                }
                let err = (&schur - &dense).norm() / dense.norm();
                assert!(
                    err < 1e-8,
                    "seed {seed} λ {lambda}: relative difference {err}"
                );
            }
        }
    }

    /// Two cameras that share no point: only the pose edge says where the second is. The
    /// solve must put it there (its points move along) and the edge's χ² must vanish.
    #[test]
    fn pose_edge_places_a_camera_without_shared_points() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let truth = [
            Isometry3::identity(),
            Isometry3::new(Vector3::new(0.3, 0.0, 0.1), Vector3::new(0.0, 0.4, 0.0)).inverse(),
        ];
        let mut points = Vec::new();
        let mut observations = Vec::new();
        for (c, t) in truth.iter().enumerate() {
            let pose_wc = t.inverse();
            for _ in 0..40 {
                let pc = Vector3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-0.8..0.8),
                    rng.random_range(2.0..4.0),
                );
                observations.push(BaObservation {
                    camera: c,
                    point: points.len(),
                    obs: Observation::Rgbd {
                        uv: INTR.project(&pc).unwrap(),
                        depth: pc.z,
                    },
                    info: 1.0,
                    shutter: Isometry3::identity(),
                });
                points.push(BaPoint {
                    position_w: (pose_wc * Point3::from(pc)).coords,
                    fixed: false,
                });
            }
        }
        // The second camera and its points start 20 cm and 3° off together: their
        // reprojection errors are zero there, so without the edge nothing moves them.
        let offset = Isometry3::new(Vector3::new(0.2, -0.05, 0.1), Vector3::new(0.0, 0.05, 0.0));
        let mut problem = BaProblem {
            keyframes: vec![
                BaCamera {
                    pose_cw: truth[0],
                    fixed: true,
                },
                BaCamera {
                    pose_cw: truth[1] * offset.inverse(),
                    fixed: false,
                },
            ],
            points: points
                .iter()
                .enumerate()
                .map(|(i, p)| BaPoint {
                    position_w: if i >= 40 {
                        (offset * Point3::from(p.position_w)).coords
                    } else {
                        p.position_w
                    },
                    fixed: false,
                })
                .collect(),
            observations,
            intrinsics: INTR,
            pose_edges: Vec::new(),
        };
        let mut without = problem.clone();
        solve(&mut without, &BaParams::default()).unwrap();
        let off = |p: &BaProblem| {
            (p.keyframes[1].pose_cw.inverse().translation.vector
                - truth[1].inverse().translation.vector)
                .norm()
        };
        assert!(off(&without) > 0.19, "no edge: {} m off", off(&without));
        problem.pose_edges.push(BaPoseEdge {
            a: 0,
            b: 1,
            a_from_b: truth[0] * truth[1].inverse(),
            info: Matrix6::identity() * 1e4,
        });
        let report = solve(
            &mut problem,
            &BaParams {
                iterations: 30,
                ..Default::default()
            },
        )
        .unwrap();
        assert!(
            off(&problem) < 1e-4,
            "with the edge: {} m off",
            off(&problem)
        );
        let err = se3::log(&(problem.keyframes[1].pose_cw * truth[1].inverse())).norm();
        assert!(err < 1e-4, "pose error {err}");
        assert!(report.final_cost < 1e-4 * report.initial_cost);
        // The points moved with their camera, back to where they are.
        for (solved, start) in problem.points.iter().zip(&points).skip(40) {
            assert!((solved.position_w - start.position_w).norm() < 1e-3);
        }
    }

    #[test]
    fn gauge_is_fixed_when_no_camera_is() {
        let mut problem = small_problem(5);
        problem.keyframes[0].fixed = false;
        let before = problem.keyframes[0].pose_cw;
        let report = solve(&mut problem, &BaParams::default()).unwrap();
        assert_eq!(report.gauge_fixed_camera, Some(0));
        assert_eq!(problem.keyframes[0].pose_cw, before);
        assert!(report.final_cost < report.initial_cost);
    }

    #[test]
    fn bad_indices_are_errors() {
        let mut problem = small_problem(6);
        problem.observations[3].point = 1000;
        assert!(matches!(
            solve(&mut problem, &BaParams::default()),
            Err(BaError::PointOutOfRange { observation: 3, .. })
        ));
    }
}
