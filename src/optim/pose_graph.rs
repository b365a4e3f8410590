//! Pose-graph optimisation (the global optimizer's solver): keyframe poses as nodes, relative
//! pose measurements as edges, Levenberg–Marquardt on the manifold with faer's sparse
//! Cholesky, robust closure edges, and the per-edge residuals the consistency check reads.
//!
//! - Nodes are world-to-camera similarities `S_iw` (scale fixed at 1 for RGB-D: SE(3), 6 dof;
//!   free for monocular: Sim(3), 7 dof, the scale drift is then a variable).
//! - An edge `(i, j)` measures `Z_ij = S_i · S_j⁻¹` (the pose of camera `j` in camera `i`'s
//!   frame). Its error is `e = Log(Z_ij⁻¹ · S_i · S_j⁻¹)` with `Log(R, t, s) = (se3::log(R, t),
//!   ln s)`, zero when the graph agrees with the measurement; the information is given for
//!   that error, (ω, υ[, σ]) order as everywhere in [`super`].
//! - Updates are left perturbations `S ← Exp(δ) · S`. Jacobians are central differences of
//!   the error: an edge costs a few dozen 4×4 products, negligible against the factorisation.
//! - Closure edges may be *robust*: Dynamic Covariance Scaling (Agarwal et al., ICRA 2013)
//!   scales their information by `w = min(1, 2Φ/(Φ + χ²))²`, re-evaluated at every iteration,
//!   so a closure the rest of the graph contradicts is switched down instead of bending the
//!   map. The report keeps each edge's *unscaled* χ², which is what exposes such a closure.
//! - The gauge: nodes marked fixed are constants; every connected component without a fixed
//!   node gets its first node fixed, so the system is never singular by construction.

use super::se3;
use crate::geometry::Sim3;
use faer::Side;
use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::{SparseColMat, Triplet};
use nalgebra::{DMatrix, DVector, Isometry3, SMatrix, SVector, Vector6};
use std::collections::BTreeMap;

/// The normal matrix as dof×dof blocks of its upper triangle, keyed by (row, column) variable.
type BlockHessian = BTreeMap<(usize, usize), DMatrix<f64>>;

pub type Vector7 = SVector<f64, 7>;
pub type Matrix7 = SMatrix<f64, 7, 7>;

/// A node: a keyframe's world-to-camera pose.
#[derive(Debug, Clone, Copy)]
pub struct PgNode {
    pub pose: Sim3,
    pub fixed: bool,
}

/// A relative pose measurement between nodes `i` and `j`.
#[derive(Debug, Clone)]
pub struct PgEdge {
    pub i: usize,
    pub j: usize,
    /// `Z_ij = S_i · S_j⁻¹`.
    pub measurement: Sim3,
    /// Information of the error, (ω, υ, σ) order; in SE(3) mode only the top-left 6×6 is read.
    pub information: Matrix7,
    /// Dynamic covariance scaling applies (closure edges).
    pub robust: bool,
}

#[derive(Debug, Clone, Default)]
pub struct PoseGraph {
    pub nodes: Vec<PgNode>,
    pub edges: Vec<PgEdge>,
    /// Sim(3) nodes (monocular); SE(3) when false.
    pub with_scale: bool,
}

#[derive(Debug, Clone, Copy)]
pub struct PgParams {
    pub iterations: usize,
    /// DCS Φ (in χ² units): a robust edge with χ² ≤ Φ keeps its full weight.
    pub dcs_phi: f64,
    /// Stop when the relative cost decrease of an accepted step is below this.
    pub relative_tolerance: f64,
}

impl Default for PgParams {
    fn default() -> Self {
        Self {
            iterations: 30,
            dcs_phi: 1.0,
            relative_tolerance: 1e-9,
        }
    }
}

/// What the optimisation did, and every edge's residual at the end.
#[derive(Debug, Clone, Default)]
pub struct PgReport {
    /// Σ (weighted) χ² before and after.
    pub initial_cost: f64,
    pub final_cost: f64,
    pub iterations: usize,
    /// Per edge, at the solution: unscaled χ² = eᵀ Ω e.
    pub chi2: Vec<f64>,
    /// Per edge: the DCS weight applied at the solution (1 for non-robust edges).
    pub weight: Vec<f64>,
    /// Nodes the gauge fixed besides those marked fixed.
    pub gauge_fixed: Vec<usize>,
}

impl PoseGraph {
    /// Degrees of freedom of a node (and of an edge's error).
    pub fn dof(&self) -> usize {
        if self.with_scale { 7 } else { 6 }
    }

    /// The error of edge `e` for node poses `si`, `sj`.
    fn error(&self, e: &PgEdge, si: &Sim3, sj: &Sim3) -> Vector7 {
        let d = e.measurement.inverse().compose(si).compose(&sj.inverse());
        log_sim3(&d)
    }

    fn weighted_info(&self, e: &PgEdge, chi2: f64, phi: f64) -> (Matrix7, f64) {
        let w = if e.robust { dcs_weight(chi2, phi) } else { 1.0 };
        (e.information * w, w)
    }

    /// Edge `k`'s χ² at the current poses under the information `info` instead of its own
    /// (what a verdict judges it with).
    pub fn edge_chi2_under(&self, k: usize, info: &Matrix7) -> f64 {
        let e = &self.edges[k];
        let r = self.error(e, &self.nodes[e.i].pose, &self.nodes[e.j].pose);
        chi2_of(&r, info, self.dof())
    }

    /// How far edge `k`'s measurement is from the current poses: the translation (in the
    /// measurement's units) and rotation (radians) of the error, and its log-scale.
    pub fn edge_residual(&self, k: usize) -> (f64, f64, f64) {
        let e = &self.edges[k];
        let r = self.error(e, &self.nodes[e.i].pose, &self.nodes[e.j].pose);
        let d = e
            .measurement
            .inverse()
            .compose(&self.nodes[e.i].pose)
            .compose(&self.nodes[e.j].pose.inverse());
        (d.translation.norm(), d.rotation.angle(), r[6])
    }

    /// Unscaled χ² of every edge at the current poses.
    pub fn edge_chi2(&self) -> Vec<f64> {
        let dof = self.dof();
        self.edges
            .iter()
            .map(|e| {
                let r = self.error(e, &self.nodes[e.i].pose, &self.nodes[e.j].pose);
                chi2_of(&r, &e.information, dof)
            })
            .collect()
    }

    fn cost(&self, phi: f64) -> f64 {
        self.edge_chi2()
            .iter()
            .zip(&self.edges)
            .map(|(c, e)| {
                if e.robust {
                    dcs_weight(*c, phi) * c
                } else {
                    *c
                }
            })
            .sum()
    }

    /// Fixes the first node of every connected component that has no fixed node.
    fn fix_gauge(&mut self) -> Vec<usize> {
        let n = self.nodes.len();
        let mut parent: Vec<usize> = (0..n).collect();
        fn find(p: &mut [usize], mut x: usize) -> usize {
            while p[x] != x {
                p[x] = p[p[x]];
                x = p[x];
            }
            x
        }
        for e in &self.edges {
            let (a, b) = (find(&mut parent, e.i), find(&mut parent, e.j));
            if a != b {
                parent[a.max(b)] = a.min(b);
            }
        }
        let mut has_fixed = vec![false; n];
        for i in 0..n {
            if self.nodes[i].fixed {
                let r = find(&mut parent, i);
                has_fixed[r] = true;
            }
        }
        let mut fixed = Vec::new();
        for i in 0..n {
            let r = find(&mut parent, i);
            if !has_fixed[r] {
                has_fixed[r] = true;
                self.nodes[i].fixed = true;
                fixed.push(i);
            }
        }
        fixed
    }

    /// Levenberg–Marquardt. The graph's node poses are updated in place.
    pub fn optimize(&mut self, params: &PgParams) -> PgReport {
        let gauge_fixed = self.fix_gauge();
        let dof = self.dof();
        let mut var_of = vec![None; self.nodes.len()];
        let mut n_var = 0;
        for (i, nd) in self.nodes.iter().enumerate() {
            if !nd.fixed {
                var_of[i] = Some(n_var);
                n_var += 1;
            }
        }
        let phi = params.dcs_phi;
        let mut cost = self.cost(phi);
        let initial_cost = cost;
        let mut lambda = 1e-4;
        let mut iterations = 0;
        if n_var > 0 {
            for _ in 0..params.iterations {
                iterations += 1;
                let (h_blocks, b) = self.normal_equations(&var_of, n_var, phi);
                let mut improved = false;
                for _ in 0..10 {
                    let Some(delta) = solve_damped(&h_blocks, &b, n_var, dof, lambda) else {
                        lambda *= 10.0;
                        continue;
                    };
                    let saved: Vec<Sim3> = self.nodes.iter().map(|n| n.pose).collect();
                    for (i, v) in var_of.iter().enumerate() {
                        if let Some(v) = v {
                            let mut d = Vector7::zeros();
                            for k in 0..dof {
                                d[k] = delta[dof * v + k];
                            }
                            self.nodes[i].pose = exp_sim3(&d).compose(&self.nodes[i].pose);
                            renormalize(&mut self.nodes[i].pose);
                        }
                    }
                    let new_cost = self.cost(phi);
                    if new_cost.is_finite() && new_cost <= cost {
                        let rel = (cost - new_cost) / cost.max(1e-300);
                        cost = new_cost;
                        lambda = (lambda / 10.0).max(1e-12);
                        improved = rel > params.relative_tolerance;
                        break;
                    }
                    for (n, p) in self.nodes.iter_mut().zip(saved) {
                        n.pose = p;
                    }
                    lambda *= 10.0;
                }
                if !improved {
                    break;
                }
            }
        }
        for i in &gauge_fixed {
            self.nodes[*i].fixed = false;
        }
        let chi2 = self.edge_chi2();
        let weight = chi2
            .iter()
            .zip(&self.edges)
            .map(|(c, e)| if e.robust { dcs_weight(*c, phi) } else { 1.0 })
            .collect();
        PgReport {
            initial_cost,
            final_cost: cost,
            iterations,
            chi2,
            weight,
            gauge_fixed,
        }
    }

    /// H (as dof×dof blocks of the upper triangle, keyed by variable pair) and b.
    fn normal_equations(
        &self,
        var_of: &[Option<usize>],
        n_var: usize,
        phi: f64,
    ) -> (BlockHessian, DVector<f64>) {
        let dof = self.dof();
        let mut h: BlockHessian = BTreeMap::new();
        let mut b = DVector::zeros(dof * n_var);
        for e in &self.edges {
            let (vi, vj) = (var_of[e.i], var_of[e.j]);
            if vi.is_none() && vj.is_none() {
                continue;
            }
            let (si, sj) = (self.nodes[e.i].pose, self.nodes[e.j].pose);
            let r = self.error(e, &si, &sj);
            let chi2 = chi2_of(&r, &e.information, dof);
            let (info, _) = self.weighted_info(e, chi2, phi);
            let info = info.view((0, 0), (dof, dof)).into_owned();
            let r = r.rows(0, dof).into_owned();
            let ji = vi.map(|_| self.numeric_jacobian(e, &si, &sj, true));
            let jj = vj.map(|_| self.numeric_jacobian(e, &si, &sj, false));
            let parts = [(vi, ji), (vj, jj)];
            for (va, ja) in &parts {
                let (Some(va), Some(ja)) = (va, ja) else {
                    continue;
                };
                let jt_info = ja.transpose() * &info;
                let g = &jt_info * &r;
                for k in 0..dof {
                    b[dof * va + k] += g[k];
                }
                for (vb, jb) in &parts {
                    let (Some(vb), Some(jb)) = (vb, jb) else {
                        continue;
                    };
                    if va > vb {
                        continue;
                    }
                    let blk = &jt_info * jb;
                    h.entry((*va, *vb))
                        .and_modify(|m| *m += &blk)
                        .or_insert(blk);
                }
            }
        }
        (h, b)
    }

    /// ∂e/∂δ for the left perturbation of node i (`first`) or j, by central differences.
    fn numeric_jacobian(&self, e: &PgEdge, si: &Sim3, sj: &Sim3, first: bool) -> DMatrix<f64> {
        let dof = self.dof();
        let h = 1e-6;
        let mut jac = DMatrix::zeros(dof, dof);
        for k in 0..dof {
            let mut d = Vector7::zeros();
            d[k] = h;
            let plus = exp_sim3(&d);
            d[k] = -h;
            let minus = exp_sim3(&d);
            let (rp, rm) = if first {
                (
                    self.error(e, &plus.compose(si), sj),
                    self.error(e, &minus.compose(si), sj),
                )
            } else {
                (
                    self.error(e, si, &plus.compose(sj)),
                    self.error(e, si, &minus.compose(sj)),
                )
            };
            let col = (rp - rm) / (2.0 * h);
            for r in 0..dof {
                jac[(r, k)] = col[r];
            }
        }
        jac
    }
}

/// Solves `(H + λ·diag(H)) δ = −b` with faer's sparse Cholesky. `None` when not positive
/// definite.
fn solve_damped(
    h: &BlockHessian,
    b: &DVector<f64>,
    n_var: usize,
    dof: usize,
    lambda: f64,
) -> Option<DVector<f64>> {
    let n = n_var * dof;
    let mut triplets = Vec::new();
    for (&(vi, vj), blk) in h {
        for c in 0..dof {
            for r in 0..dof {
                let (row, col) = (dof * vi + r, dof * vj + c);
                if row > col {
                    continue;
                }
                let mut v = blk[(r, c)];
                if row == col {
                    v += lambda * v.abs().max(1e-9);
                }
                triplets.push(Triplet::new(row, col, v));
            }
        }
    }
    let mat = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &triplets).ok()?;
    let sym = SymbolicLlt::try_new(mat.symbolic(), Side::Upper).ok()?;
    let llt = Llt::try_new_with_symbolic(sym, mat.as_ref(), Side::Upper).ok()?;
    let mut rhs: Vec<f64> = b.iter().map(|x| -x).collect();
    let mut x = faer::MatMut::from_column_major_slice_mut(&mut rhs, n, 1);
    llt.solve_in_place(x.as_mut());
    let out = DVector::from_vec(rhs);
    out.iter().all(|v| v.is_finite()).then_some(out)
}

fn chi2_of(r: &Vector7, info: &Matrix7, dof: usize) -> f64 {
    let r = r.rows(0, dof);
    let info = info.view((0, 0), (dof, dof));
    (r.transpose() * info * r)[(0, 0)]
}

/// Dynamic covariance scaling: the information factor of a robust edge with χ² `chi2`.
pub fn dcs_weight(chi2: f64, phi: f64) -> f64 {
    let s = (2.0 * phi / (phi + chi2.max(0.0))).min(1.0);
    s * s
}

/// `Log(R, t, s) = (se3::log(R, t), ln s)`.
pub fn log_sim3(s: &Sim3) -> Vector7 {
    let v = se3::log(&s.to_isometry());
    let mut out = Vector7::zeros();
    out.fixed_rows_mut::<6>(0).copy_from(&v);
    out[6] = s.scale.ln();
    out
}

/// Inverse of [`log_sim3`].
pub fn exp_sim3(d: &Vector7) -> Sim3 {
    let v = Vector6::from_column_slice(&d.as_slice()[0..6]);
    let mut s = Sim3::from_isometry(&se3::exp(&v));
    s.scale = d[6].exp();
    s
}

fn renormalize(s: &mut Sim3) {
    let q = nalgebra::UnitQuaternion::from_rotation_matrix(&s.rotation);
    s.rotation = q.to_rotation_matrix();
}

/// The information of an SE(3) measurement as a 7×7 one (the scale part gets `scale_info`).
pub fn info7(info6: &nalgebra::Matrix6<f64>, scale_info: f64) -> Matrix7 {
    let mut m = Matrix7::zeros();
    m.fixed_view_mut::<6, 6>(0, 0).copy_from(info6);
    m[(6, 6)] = scale_info;
    m
}

/// The world-to-camera isometry as a node pose.
pub fn node(pose_cw: &Isometry3<f64>, fixed: bool) -> PgNode {
    PgNode {
        pose: Sim3::from_isometry(pose_cw),
        fixed,
    }
}
