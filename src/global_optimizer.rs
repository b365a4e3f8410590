//! Global optimizer (paper Table I): the map's pose graph with its valid closures, optimised,
//! and the consistency check that reports `consistent_map`.
//!
//! The graph is ORB-SLAM's *essential graph* over the keyframes of one map: each keyframe is
//! tied to its strongest covisible older keyframe (the spanning tree) and to every keyframe it
//! shares at least `essential_min_covisibility` points with, each edge measuring the current
//! relative pose (what tracking and local BA established); plus the closure edges of the
//! atlas's standing pools, with the information the validator measured. After optimisation
//! every keyframe takes its new pose and every map point moves rigidly with its reference
//! keyframe.
//!
//! Consistency: with the edges' information calibrated (odometry σ from the config, closure
//! information from the validator with a floor), each edge's χ²/dof should be about 1. A
//! closure whose χ²/dof stays above `max_normalized_chi2` after the robust optimisation is
//! contradicted by the rest of the map — DCS switched it down instead of letting it bend the
//! map — and its pool is named as offending. Odometry edges above the threshold mean the
//! closures together distort the map without one standing out: inconsistent too, with every
//! pool of the map as a suspect. This module reports; the state machine decides.

use crate::atlas::{ClosureEdge, PoolId};
use crate::config::LoopClosingConfig;
use crate::geometry::Sim3;
use crate::map::{KfId, Map};
use crate::optim::pose_graph::{self, PgEdge, PgParams, PoseGraph, info7};
use nalgebra::{Isometry3, Matrix6};
use std::collections::{BTreeMap, BTreeSet};

/// What one global optimisation found.
#[derive(Debug, Clone, Default)]
pub struct GlobalReport {
    pub consistent: bool,
    /// Pools whose closure edges the map contradicts, newest first.
    pub offending_pools: Vec<PoolId>,
    pub keyframes: usize,
    pub odometry_edges: usize,
    pub closure_edges: usize,
    pub initial_cost: f64,
    pub final_cost: f64,
    pub iterations: usize,
    /// Largest χ²/dof among closure edges and among odometry edges.
    pub max_closure_nchi2: f64,
    pub max_odometry_nchi2: f64,
}

/// The odometry information of the config's per-edge σ, (ω, υ) order.
pub fn odometry_information(cfg: &LoopClosingConfig) -> Matrix6<f64> {
    let wr = 1.0 / cfg.odometry_sigma_deg.to_radians().powi(2);
    let wt = 1.0 / cfg.odometry_sigma_m.powi(2);
    Matrix6::from_diagonal(&nalgebra::Vector6::new(wr, wr, wr, wt, wt, wt))
}

/// A closure's information with the config's floor added to its covariance (the validator's
/// information is a Cramér–Rao bound from the inliers; the keypoint noise model is not exact).
pub fn closure_information(cfg: &LoopClosingConfig, info: &Matrix6<f64>) -> Matrix6<f64> {
    let sr = cfg.closure_min_sigma_deg.to_radians().powi(2);
    let st = cfg.closure_min_sigma_m.powi(2);
    let floor = Matrix6::from_diagonal(&nalgebra::Vector6::new(sr, sr, sr, st, st, st));
    let cov = info
        .try_inverse()
        .filter(|c| c.iter().all(|v| v.is_finite()))
        .unwrap_or_else(Matrix6::zeros);
    let cov = 0.5 * (cov + cov.transpose()) + floor;
    cov.try_inverse()
        .unwrap_or_else(|| floor.try_inverse().expect("diagonal"))
}

/// The essential graph's odometry pairs `(older, newer)` of `map`.
pub fn essential_edges(map: &Map, min_covisibility: u32) -> BTreeSet<(KfId, KfId)> {
    let mut pairs = BTreeSet::new();
    for (id, kf) in &map.keyframes {
        // Spanning tree: the strongest covisible older keyframe (ties: the newest of them).
        let parent = kf
            .covisibility
            .iter()
            .filter(|(o, _)| **o < *id && map.keyframes.contains_key(o))
            .max_by_key(|(o, w)| (**w, **o))
            .map(|(o, _)| *o);
        if let Some(p) = parent {
            pairs.insert((p, *id));
        }
        for (o, w) in &kf.covisibility {
            if *w >= min_covisibility && map.keyframes.contains_key(o) && o != id {
                pairs.insert(((*o).min(*id), (*o).max(*id)));
            }
        }
    }
    pairs
}

/// Optimises `map` with `closures` (closure edges between its keyframes) and checks it.
/// `fixed` keyframes (at least the map's first) stay where they are.
pub fn optimize_map(
    cfg: &LoopClosingConfig,
    map: &mut Map,
    closures: &[ClosureEdge],
    fixed: &[KfId],
    with_scale: bool,
) -> GlobalReport {
    let ids: Vec<KfId> = map.keyframes.keys().copied().collect();
    let index: BTreeMap<KfId, usize> = ids.iter().enumerate().map(|(i, k)| (*k, i)).collect();
    let first = ids.first().copied();
    let mut graph = PoseGraph {
        nodes: ids
            .iter()
            .map(|k| {
                let fix = fixed.contains(k) || Some(*k) == first;
                pose_graph::node(&map.keyframes[k].pose_cw, fix)
            })
            .collect(),
        edges: Vec::new(),
        with_scale,
    };
    // Scale drift per edge (monocular): as loose as the rotation, in log units.
    let scale_info = 1.0 / cfg.odometry_sigma_deg.to_radians().powi(2);
    let odo_info = info7(&odometry_information(cfg), scale_info);
    for (a, b) in essential_edges(map, cfg.essential_min_covisibility) {
        let (ia, ib) = (index[&a], index[&b]);
        graph.edges.push(PgEdge {
            i: ia,
            j: ib,
            measurement: graph.nodes[ia]
                .pose
                .compose(&graph.nodes[ib].pose.inverse()),
            information: odo_info,
            robust: false,
        });
    }
    let n_odometry = graph.edges.len();
    let mut pools = Vec::new();
    for c in closures {
        let (Some(&im), Some(&iq)) = (index.get(&c.matched), index.get(&c.query)) else {
            continue;
        };
        graph.edges.push(PgEdge {
            i: im,
            j: iq,
            measurement: Sim3::from_isometry(&c.relative),
            information: info7(&closure_information(cfg, &c.information), scale_info),
            robust: true,
        });
        pools.push(c.pool);
    }
    let before: Vec<Sim3> = graph.nodes.iter().map(|n| n.pose).collect();
    let mut report = optimize_graph(cfg, &mut graph, n_odometry, &pools);
    report.keyframes = ids.len();
    apply(map, &ids, &before, &graph);
    report
}

/// Optimises a pose graph whose first `n_odometry` edges are odometry and the rest closures
/// (of the pools `pools`, one per closure edge), then checks its consistency.
pub fn optimize_graph(
    cfg: &LoopClosingConfig,
    graph: &mut PoseGraph,
    n_odometry: usize,
    pools: &[PoolId],
) -> GlobalReport {
    let params = PgParams {
        iterations: cfg.pgo_iterations as usize,
        dcs_phi: cfg.dcs_phi,
        ..Default::default()
    };
    // Least squares first: a fresh closure's error is the drift it corrects, and a robust
    // kernel evaluated at the uncorrected poses would switch a right closure off. Then DCS
    // from the least-squares solution, where only closures the rest contradicts stand out.
    for e in graph.edges.iter_mut() {
        e.robust = false;
    }
    let first_pass = graph.optimize(&params);
    for e in graph.edges[n_odometry..].iter_mut() {
        e.robust = true;
    }
    let rep = graph.optimize(&params);

    let dof = graph.dof() as f64;
    let max_closure = rep.chi2[n_odometry..]
        .iter()
        .fold(0.0f64, |a, c| a.max(c / dof));
    let max_odometry = rep.chi2[..n_odometry]
        .iter()
        .fold(0.0f64, |a, c| a.max(c / dof));
    let limit = cfg.max_normalized_chi2;
    let mut offending: BTreeSet<PoolId> = rep.chi2[n_odometry..]
        .iter()
        .zip(pools)
        .filter(|(c, _)| *c / dof > limit)
        .map(|(_, p)| *p)
        .collect();
    let consistent = offending.is_empty() && max_odometry <= limit;
    if offending.is_empty() && !consistent {
        offending = pools.iter().copied().collect();
    }
    GlobalReport {
        consistent,
        offending_pools: offending.into_iter().rev().collect(),
        keyframes: graph.nodes.len(),
        odometry_edges: n_odometry,
        closure_edges: graph.edges.len() - n_odometry,
        initial_cost: first_pass.initial_cost,
        final_cost: rep.final_cost,
        iterations: first_pass.iterations + rep.iterations,
        max_closure_nchi2: max_closure,
        max_odometry_nchi2: max_odometry,
    }
}

/// Keyframes take their optimised poses; each point moves with its reference keyframe (the
/// keyframe that created it, else its first remaining observer).
fn apply(map: &mut Map, ids: &[KfId], before: &[Sim3], graph: &PoseGraph) {
    // Per keyframe: world correction `S_new⁻¹ · S_old` (old world → new world).
    let mut correction: BTreeMap<KfId, Sim3> = BTreeMap::new();
    for (k, id) in ids.iter().enumerate() {
        let new = graph.nodes[k].pose;
        correction.insert(*id, new.inverse().compose(&before[k]));
        let kf = map.keyframes.get_mut(id).expect("listed");
        let mut pose: Isometry3<f64> = new.to_isometry();
        pose.rotation.renormalize();
        kf.pose_cw = pose;
    }
    for p in map.points.values_mut() {
        let r = if correction.contains_key(&p.first_kf) {
            Some(p.first_kf)
        } else {
            p.observations
                .keys()
                .find(|k| correction.contains_key(k))
                .copied()
        };
        if let Some(c) = r.and_then(|r| correction.get(&r)) {
            p.position = c.transform_point(&p.position);
            p.normal = c.rotation * p.normal;
        }
    }
}

/// The expectation check of Localized: where the map predicts structure, the camera must see
/// it. The image is cut into cells; a cell is *expected* when a local-map point predicted
/// visible projects into it, and *confirmed* when an inlier keypoint lies in it. Counting cells
/// rather than points keeps the measure fair where the map holds two copies of the same
/// surface (before and after a loop closure fused them).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Expectation {
    pub expected_cells: usize,
    pub confirmed_cells: usize,
}

impl Expectation {
    pub fn ratio(&self) -> f64 {
        self.confirmed_cells as f64 / self.expected_cells.max(1) as f64
    }
}

pub fn expectation(
    geo: &crate::preprocess::ImageGeometry,
    map: &Map,
    m: &crate::preprocess::Measurement,
    track: &crate::tracker::TrackResult,
    cell_px: f64,
) -> Expectation {
    let cell = |u: f64, v: f64| ((u / cell_px) as u32, (v / cell_px) as u32);
    let expected: BTreeSet<(u32, u32)> = track
        .visible
        .iter()
        .filter_map(|id| map.points.get(id))
        .filter_map(|p| geo.project_in_image(&Map::in_camera(&track.pose_cw, &p.position)))
        .map(|uv| cell(uv.x, uv.y))
        .collect();
    let confirmed = track
        .matches
        .iter()
        .zip(&m.keypoints)
        .filter(|(mt, _)| mt.is_some())
        .map(|(_, k)| cell(k.un.x, k.un.y))
        .filter(|c| expected.contains(c))
        .collect::<BTreeSet<_>>()
        .len();
    Expectation {
        expected_cells: expected.len(),
        confirmed_cells: confirmed,
    }
}
