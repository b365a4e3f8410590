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
//! Consistency: with the edges' information calibrated (odometry σ growing with the distance
//! between the keyframes, closure
//! information from the validator with a floor), each edge's χ²/dof should be about 1. A
//! closure whose χ²/dof stays above `max_normalized_chi2` after the robust optimisation is
//! contradicted by the rest of the map — DCS switched it down instead of letting it bend the
//! map — and its pool is named as offending. Odometry edges above the threshold mean the
//! closures together distort the map without one standing out: inconsistent too, with every
//! pool of the map as a suspect. Each loop is also judged whole, against the odometry's drift
//! accumulated along it ([`loop_chi2`], decision 0032): the per-edge tests spread a turn's
//! drift over as many edges as keyframes cut it. This module reports; the state machine
//! decides.

use crate::atlas::{ClosureEdge, PoolId};
use crate::config::LoopClosingConfig;
use crate::geometry::Sim3;
use crate::map::{KfId, Map, PointId};
use crate::optim::pose_graph::{self, PgEdge, PgParams, PoseGraph, info7};
use nalgebra::{Isometry3, Matrix6, Vector2, Vector3};
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
    /// Largest loop χ²/dof ([`loop_chi2`]) among closure edges with a loop.
    pub max_loop_nchi2: f64,
    /// The residual of the closure edge with the largest χ²: translation (the map's units),
    /// rotation (degrees), |log scale|.
    pub worst_closure_residual: (f64, f64, f64),
    /// The same for the odometry edge of largest χ².
    pub worst_odometry_residual: (f64, f64, f64),
}

/// The odometry information of an edge whose keyframes are `length` apart (the map's units),
/// (ω, υ) order: tracking drift grows with the distance travelled, so σ = base + rate ·
/// length. What the camera turned is judged along whole loops ([`loop_chi2`]), not here: see
/// decision 0032 for the per-edge per-radian σ that was measured and not adopted.
pub fn odometry_information(cfg: &LoopClosingConfig, length: f64) -> Matrix6<f64> {
    let (sr, st) = odometry_sigmas(cfg, length);
    let (wr, wt) = (1.0 / (sr * sr), 1.0 / (st * st));
    Matrix6::from_diagonal(&nalgebra::Vector6::new(wr, wr, wr, wt, wt, wt))
}

/// The odometry σ over `length` (the map's units): rotation (radians), translation.
fn odometry_sigmas(cfg: &LoopClosingConfig, length: f64) -> (f64, f64) {
    (
        (cfg.odometry_sigma_deg + cfg.odometry_sigma_deg_per_m * length).to_radians(),
        cfg.odometry_sigma_m + cfg.odometry_sigma_per_m * length,
    )
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

/// The covariance a right closure's measurement has on a real sensor, in a scene `depth` away
/// (the map's units): `loop_closing.closure_sensor_sigma_depth` of the depth in translation,
/// `closure_sensor_sigma_deg` in rotation; (ω, υ, log-scale) order, the scale part left to
/// the closure's own information. Depth noise, misregistration and blur misplace a view by a
/// share of what it looks at, not by a fixed length: relative, the same σ holds for a desk
/// seen from 0.8 m and a hall from 4 m, and for a monocular map in its own units.
fn sensor_information(cfg: &LoopClosingConfig, depth: f64) -> pose_graph::Matrix7 {
    let sr = cfg.closure_sensor_sigma_deg.to_radians().powi(2);
    let st = (cfg.closure_sensor_sigma_depth * depth).powi(2);
    pose_graph::Matrix7::from_diagonal(&nalgebra::SVector::<f64, 7>::from_column_slice(&[
        sr, sr, sr, st, st, st, 0.0,
    ]))
}

/// A closure's information once the sensor's covariance is added to its own.
fn with_sensor_noise(
    info: &pose_graph::Matrix7,
    sensor: &pose_graph::Matrix7,
) -> pose_graph::Matrix7 {
    let Some(cov) = info
        .try_inverse()
        .filter(|c| c.iter().all(|v| v.is_finite()))
    else {
        return *info;
    };
    let cov = 0.5 * (cov + cov.transpose()) + sensor;
    cov.try_inverse().unwrap_or(*info)
}

/// The essential graph's odometry pairs `(older, newer)` of `map`.
pub fn essential_edges(map: &Map, min_covisibility: u32) -> BTreeSet<(KfId, KfId)> {
    let mut pairs = BTreeSet::new();
    for (id, kf) in &map.keyframes {
        // Spanning tree: the strongest covisible older keyframe (ties: the newest of them);
        // where culling has removed every point shared with older keyframes, the keyframe it
        // was tracked against. Without that link the keyframes made since hang on nothing,
        // and a closure there moves them anywhere at no cost: a look-alike loop 166° off
        // passed as consistent (small `aliasing`, 5 % noise frames, with Localized left
        // sooner).
        let parent = kf
            .covisibility
            .iter()
            .filter(|(o, _)| **o < *id && map.keyframes.contains_key(o))
            .max_by_key(|(o, w)| (**w, **o))
            .map(|(o, _)| *o)
            .or(kf
                .parent
                .filter(|p| *p < *id && map.keyframes.contains_key(p)));
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
    let depths = scene_depths(map, &ids);
    // Scale drift per edge (monocular): as loose as the rotation, in log units.
    let scale_info = 1.0 / cfg.odometry_sigma_deg.to_radians().powi(2);
    for (a, b) in essential_edges(map, cfg.essential_min_covisibility) {
        let (ia, ib) = (index[&a], index[&b]);
        let measurement = graph.nodes[ia]
            .pose
            .compose(&graph.nodes[ib].pose.inverse());
        let length = measurement.translation.norm();
        graph.edges.push(PgEdge {
            i: ia,
            j: ib,
            measurement,
            information: info7(&odometry_information(cfg, length), scale_info),
            robust: false,
        });
    }
    let n_odometry = graph.edges.len();
    // A closure's scale (monocular) is the median distance ratio seen from one frame, and a
    // pool takes candidates within `POOL_MAX_LOG_SCALE` of each other as one: it is known to
    // about half that (2 σ), not to the odometry's 0.5° equivalent (0.9 %). Held that tight, a
    // right merge into a young map whose scale was still settling failed the consistency check.
    let closure_scale_info =
        1.0 / (0.5 * crate::components::loop_validator::POOL_MAX_LOG_SCALE).powi(2);
    let mut pools = Vec::new();
    for c in closures {
        let (Some(&im), Some(&iq)) = (index.get(&c.matched), index.get(&c.query)) else {
            continue;
        };
        graph.edges.push(PgEdge {
            i: im,
            j: iq,
            measurement: c.measurement(
                map.keyframes[&c.matched].units,
                map.keyframes[&c.query].units,
            ),
            information: info7(
                &closure_information(cfg, &c.information),
                closure_scale_info,
            ),
            robust: true,
        });
        pools.push(c.pool);
    }
    let before: Vec<Sim3> = graph.nodes.iter().map(|n| n.pose).collect();
    let mut report = optimize_graph(cfg, &mut graph, n_odometry, &pools, &depths);
    report.keyframes = ids.len();
    apply(map, &ids, &before, &graph);
    report
}

/// Each keyframe's scene depth ([`Map::scene_depth`]); one without points takes the median of
/// the others' (1 in a map without any).
fn scene_depths(map: &Map, ids: &[KfId]) -> Vec<f64> {
    let own: Vec<Option<f64>> = ids
        .iter()
        .map(|k| map.scene_depth(&map.keyframes[k]))
        .collect();
    let mut known: Vec<f64> = own.iter().flatten().copied().collect();
    let fallback = if known.is_empty() {
        1.0
    } else {
        let mid = known.len() / 2;
        *known.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1
    };
    own.into_iter().map(|d| d.unwrap_or(fallback)).collect()
}

/// The loop test of every closure edge (indices `n_odometry..`, of the pools `pools`): the
/// closure's measurement against what the rest of the graph's measurements compose to between
/// its two keyframes, given the drift they allow, as χ² over the 6 dof of rotation and
/// translation
/// (`eᵀ (Σ_path + Σ_closure)⁻¹ e`); `None` where nothing but the closure's own pool joins
/// them (a merge: nothing else measured where one side stands in the other).
///
/// The path is the rest of the graph's tightest chain between the two keyframes (odometry
/// edges and older pools' closures). Its drift: the odometry σ ([`odometry_information`])
/// once for the path's length, plus a random walk in the angle turned,
/// `odometry_sigma_deg_per_sqrt_rad`² in rotation and (`odometry_sigma_depth_per_sqrt_rad` ·
/// scene depth)² in translation per radian (a misread rotation moves the map by its lever arm,
/// the scene's depth, in the map's own units), each rotation also moving the far end by its
/// lever arm; plus the covariance of the older closures it crosses.
/// The closure's covariance includes the sensor's ([`sensor_information`], at the two
/// keyframes' scene depth `depths`). A per-edge test cannot judge a loop: the drift of a turn
/// is spread over as many edges as keyframes cut it, and each edge's share shrinks with their
/// number; along the whole loop it does not.
pub fn loop_chi2(
    cfg: &LoopClosingConfig,
    graph: &PoseGraph,
    n_odometry: usize,
    pools: &[PoolId],
    depths: &[f64],
) -> Vec<Option<f64>> {
    let n = graph.nodes.len();
    let centre = |i: usize| graph.nodes[i].pose.inverse().translation;
    let closure_cov_of = |k: usize| -> Option<Matrix6<f64>> {
        let e = &graph.edges[k];
        let depth = edge_depth(e, depths);
        let cov = e
            .information
            .try_inverse()
            .filter(|c| c.iter().all(|v| v.is_finite()))?;
        let cov = 0.5 * (cov + cov.transpose()) + sensor_information(cfg, depth);
        Some(cov.fixed_view::<6, 6>(0, 0).into_owned())
    };
    let closure_covs: Vec<Option<Matrix6<f64>>> = (n_odometry..graph.edges.len())
        .map(closure_cov_of)
        .collect();
    let closure_cov = |k: usize| closure_covs[k - n_odometry];
    let walk_r = cfg.odometry_sigma_deg_per_sqrt_rad.to_radians().powi(2);
    let walk_t = cfg.odometry_sigma_depth_per_sqrt_rad.powi(2);
    // Per edge: (length, rotation variance, translation variance) of its drift — for an
    // odometry edge the random walk of its turn, for a closure its (isotropic) covariance.
    let drift: Vec<Option<(f64, f64, f64)>> = (0..graph.edges.len())
        .map(|k| {
            let e = &graph.edges[k];
            if k < n_odometry {
                let z = &e.measurement;
                let angle = nalgebra::UnitQuaternion::from_rotation_matrix(&z.rotation).angle();
                let depth = edge_depth(e, depths);
                let length = z.translation.norm();
                Some((length, walk_r * angle, walk_t * depth * depth * angle))
            } else {
                let c = closure_cov(k)?;
                let r = (0..3).map(|i| c[(i, i)]).fold(0.0f64, f64::max);
                let t = (3..6).map(|i| c[(i, i)]).fold(0.0f64, f64::max);
                Some((0.0, r, t))
            }
        })
        .collect();
    let mut adjacency: Vec<Vec<(usize, usize)>> = vec![Vec::new(); n];
    for (k, e) in graph.edges.iter().enumerate() {
        if drift[k].is_some() {
            adjacency[e.i].push((e.j, k));
            adjacency[e.j].push((e.i, k));
        }
    }
    (n_odometry..graph.edges.len())
        .map(|k| {
            let pool = pools.get(k - n_odometry).copied();
            let e = &graph.edges[k];
            // Only older pools may carry the path: a newer one is what is being judged
            // against the map as it stood, and a wrong one would condemn the right it crosses.
            let usable =
                |edge: usize| edge < n_odometry || pools.get(edge - n_odometry).copied() < pool;
            // Dijkstra from the matched keyframe by summed variance (rotation at a 1-unit arm,
            // length at the per-length rates).
            let cost = |(l, r, t): (f64, f64, f64)| {
                r + t
                    + (cfg.odometry_sigma_deg_per_m.to_radians() * l).powi(2)
                    + (cfg.odometry_sigma_per_m * l).powi(2)
            };
            let mut dist = vec![f64::INFINITY; n];
            let mut via: Vec<Option<(usize, usize)>> = vec![None; n];
            let mut heap = std::collections::BinaryHeap::new();
            dist[e.i] = 0.0;
            heap.push((std::cmp::Reverse(Ordered(0.0)), e.i));
            while let Some((std::cmp::Reverse(Ordered(d)), v)) = heap.pop() {
                if d > dist[v] {
                    continue;
                }
                if v == e.j {
                    break;
                }
                for &(w, edge) in &adjacency[v] {
                    if !usable(edge) {
                        continue;
                    }
                    let nd = d + cost(drift[edge].expect("listed"));
                    if nd < dist[w] {
                        dist[w] = nd;
                        via[w] = Some((v, edge));
                        heap.push((std::cmp::Reverse(Ordered(nd)), w));
                    }
                }
            }
            if !dist[e.j].is_finite() {
                return None;
            }
            let end = centre(e.j);
            let (mut length, mut rot, mut trans) = (0.0, 0.0, 0.0);
            // What the path measures of `S_i · S_j⁻¹`, composed from the far end back.
            let mut predicted = Sim3::identity();
            let mut v = e.j;
            while let Some((u, edge)) = via[v] {
                let (l, r, t) = drift[edge].expect("listed");
                length += l;
                rot += r;
                trans += t + r * (end - centre(u)).norm_squared();
                let z = &graph.edges[edge];
                let step = if z.i == u {
                    z.measurement
                } else {
                    z.measurement.inverse()
                };
                predicted = step.compose(&predicted);
                v = u;
            }
            let (sr, st) = odometry_sigmas(cfg, length);
            let mut cov = closure_cov(k)?;
            for i in 0..3 {
                cov[(i, i)] += rot + sr * sr;
                cov[(i + 3, i + 3)] += trans + st * st;
            }
            // The loop's error from the measurements alone (not the poses, which an earlier
            // optimisation or a merge may have moved off them).
            let err = pose_graph::log_sim3(&e.measurement.inverse().compose(&predicted));
            let err = nalgebra::Vector6::from_column_slice(&err.as_slice()[0..6]);
            let inv = cov.try_inverse()?;
            Some((err.transpose() * inv * err)[(0, 0)])
        })
        .collect()
}

/// The scene depth at an edge: the mean of its two keyframes' (`depths`, per node).
fn edge_depth(e: &PgEdge, depths: &[f64]) -> f64 {
    0.5 * (depths[e.i] + depths[e.j])
}

/// A total order on finite costs, for the loop test's priority queue.
struct Ordered(f64);
impl PartialEq for Ordered {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other).is_eq()
    }
}
impl Eq for Ordered {}
impl PartialOrd for Ordered {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Ordered {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.0.total_cmp(&other.0)
    }
}

/// Optimises a pose graph whose first `n_odometry` edges are odometry and the rest closures
/// (of the pools `pools`, one per closure edge), then checks its consistency; `depths` are
/// the nodes' scene depths in the graph's units (the sensor noise of a closure grows with
/// it).
pub fn optimize_graph(
    cfg: &LoopClosingConfig,
    graph: &mut PoseGraph,
    n_odometry: usize,
    pools: &[PoolId],
    depths: &[f64],
) -> GlobalReport {
    // Each loop judged before the optimisation spreads its error.
    let loops = loop_chi2(cfg, graph, n_odometry, pools, depths);
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
    // A closure is contradicted when what is left of it after the robust optimisation is
    // significant beyond what a right closure is off by on a real sensor (depth noise and
    // misregistration, rolling shutter, blur: a share of the scene's depth, decisions 0021
    // and 0032; under the validator's own estimate right closures score 4-40 χ²/dof), not
    // beyond the validator's estimate alone. The optimisation weighs each closure by the latter.
    // Each closure's χ²/dof with the sensor's noise, and whether it is contradicted.
    let mut offending: BTreeSet<PoolId> = BTreeSet::new();
    for (k, p) in (n_odometry..graph.edges.len()).zip(pools) {
        let e = &graph.edges[k];
        let depth = edge_depth(e, depths);
        let info = with_sensor_noise(&e.information, &sensor_information(cfg, depth));
        let judged = graph.edge_chi2_under(k, &info) / dof;
        if judged > limit {
            offending.insert(*p);
        }
        let (t, r, _) = graph.edge_residual(k);
        tracing::debug!(
            "closure edge of pool {p}: off by {t:.3} ({:.3} of the depth {depth:.2}) / {:.2} deg, judged chi2/dof {judged:.2}, loop chi2/dof {}",
            t / depth,
            r.to_degrees(),
            loops[k - n_odometry].map_or("-".into(), |c| format!("{:.2}", c / 6.0))
        );
    }
    // A loop whose error the drift along it cannot explain: its pool is named by itself.
    let max_loop = loops.iter().flatten().fold(0.0f64, |a, c| a.max(c / 6.0));
    offending.extend(
        loops
            .iter()
            .zip(pools)
            .filter(|(c, _)| c.is_some_and(|c| c / 6.0 > limit))
            .map(|(_, p)| *p),
    );
    let worst_closure_residual = rep.chi2[n_odometry..]
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map(|(k, _)| {
            let (t, r, s) = graph.edge_residual(n_odometry + k);
            (t, r.to_degrees(), s.abs())
        })
        .unwrap_or_default();
    let worst_odometry_residual = rep.chi2[..n_odometry]
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map(|(k, _)| {
            let (t, r, s) = graph.edge_residual(k);
            (t, r.to_degrees(), s.abs())
        })
        .unwrap_or_default();
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
        max_loop_nchi2: max_loop,
        worst_closure_residual,
        worst_odometry_residual,
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
        // `S = [sR | t]` maps the world to camera coordinates `s` times too long: the camera
        // is `[R | t/s]` and its frame's lengths change by `1/s` (ORB-SLAM's loop correction).
        let mut pose: Isometry3<f64> = new.to_isometry();
        pose.translation.vector /= new.scale;
        kf.units /= new.scale;
        for i in 3..6 {
            kf.twist[i] /= new.scale;
        }
        pose.rotation.renormalize();
        kf.pose_cw = pose;
    }
    move_points(map, &correction);
}

/// Each point moves with its reference keyframe's world correction (old world → new): the
/// keyframe that created it, else its first remaining observer.
pub fn move_points(map: &mut Map, correction: &BTreeMap<KfId, Sim3>) {
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
            p.min_distance *= c.scale;
            p.max_distance *= c.scale;
        }
    }
}

/// The expectation check of Localized: where the map predicts structure, the camera must see
/// it. The image is cut into cells; a cell is *expected* when a local-map point predicted
/// visible projects into it, and *confirmed* when an inlier keypoint lies in it. Counting cells
/// rather than points keeps the measure fair where the map holds two copies of the same
/// surface (before and after a loop closure fused them).
///
/// Cells also say whether the camera is still in mapped space: of the (coarser) cells where
/// the frame has keypoints, the share where the map predicts points is its *coverage*.
///
/// With depth the check is sharper: a predicted point whose image neighbourhood shows keypoints
/// at about its predicted depth is *confirmed by depth* (even when blur kept its descriptor from
/// matching); one whose neighbours all lie clearly *behind* it is *contradicted* — the camera
/// sees through where the map says a surface is. Nearer neighbours (occlusion) say nothing.
///
/// Without depth, a predicted cell without an inlier is *resembled* when a keypoint near one of
/// its predicted points still looks like that point (within `APPEARANCE_MAX_DISTANCE`): blur
/// or a changed viewpoint kept the tracker from matching it, but the texture the map predicts
/// is there. A wrong map predicts texture the camera does not see.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Expectation {
    pub expected_cells: usize,
    pub confirmed_cells: usize,
    /// Expected cells not confirmed, but resembled (without depth readings only; 0 with them).
    pub resembled_cells: usize,
    pub depth_confirmed: usize,
    pub depth_contradicted: usize,
    /// Cells holding keypoints of the frame, and those of them the map predicts.
    pub feature_cells: usize,
    pub covered_cells: usize,
}

impl Expectation {
    /// Share of the predicted cells that are re-observed.
    pub fn ratio(&self) -> f64 {
        self.confirmed_cells as f64 / self.expected_cells.max(1) as f64
    }

    /// Share of the predicted cells that are re-observed or resembled.
    pub fn found_share(&self) -> f64 {
        (self.confirmed_cells + self.resembled_cells) as f64 / self.expected_cells.max(1) as f64
    }

    /// Share of what the camera sees that the map predicts.
    pub fn coverage(&self) -> f64 {
        self.covered_cells as f64 / self.feature_cells.max(1) as f64
    }

    /// Points judged by depth.
    pub fn depth_judged(&self) -> usize {
        self.depth_confirmed + self.depth_contradicted
    }

    /// Share of the points judged by depth that the camera contradicts.
    pub fn contradiction(&self) -> f64 {
        self.depth_contradicted as f64 / self.depth_judged().max(1) as f64
    }
}

/// Depth check of a merge before it is made: the points of map `into`, seen from each
/// keyframe of map `from` placed by `alignment` (from's world → into's world), against that
/// keyframe's depth readings. Per keyframe of `from`: (points judged, points contradicted —
/// the keyframe saw clearly through them). Perceptual aliasing (a copy of a room) passes every
/// test local to the matched place; the rest of the two maps seldom agrees.
pub fn merge_depth_check(
    geo: &crate::components::preprocess::ImageGeometry,
    into: &Map,
    from: &Map,
    alignment: &Isometry3<f64>,
) -> Vec<(KfId, usize, usize)> {
    per_keyframe_placed(from, alignment, |kf, pose_cw| {
        seen_through(
            geo,
            kf,
            pose_cw,
            into.points.values().filter(|p| into.depth_measured(p)),
        )
    })
}

/// `judge` applied to each keyframe of `from` placed by `alignment` (from's world → the other
/// map's world): (keyframe, and the two counts it returns).
fn per_keyframe_placed(
    from: &Map,
    alignment: &Isometry3<f64>,
    judge: impl Fn(&crate::map::Keyframe, &Isometry3<f64>) -> (usize, usize),
) -> Vec<(KfId, usize, usize)> {
    let to_from = alignment.inverse();
    from.keyframes
        .values()
        .map(|kf| {
            let (a, b) = judge(kf, &(kf.pose_cw * to_from));
            (kf.id, a, b)
        })
        .collect()
}

/// The points of map `into` beyond the merged place: not observed by the keyframes of the
/// place (`place`: the keyframes matched and those covisible with them), and in view of no
/// keyframe of map `from` placed by `alignment` (from's world → into's, with its scale; in
/// front, inside the image, within the point's visibility cone). A copy of a place shares the
/// place itself and what both maps saw, not what lies beyond; the camera re-observing these
/// points after the merge is what tells the place from its copy (a provisional merge's
/// confirmation, [`crate::atlas::MergeEvidence`]).
pub fn unheld_points(
    geo: &crate::components::preprocess::ImageGeometry,
    into: &Map,
    from: &Map,
    alignment: &Sim3,
    place: &BTreeSet<KfId>,
) -> BTreeSet<PointId> {
    let mut held: BTreeSet<PointId> = into
        .points
        .values()
        .filter(|p| p.observations.keys().any(|k| place.contains(k)))
        .map(|p| p.id)
        .collect();
    for kf in from.keyframes.values() {
        // The keyframe's camera in into's world.
        let pose_cw = alignment.transform_pose_cw(&kf.pose_cw);
        for (p, ..) in in_view(geo, &pose_cw, into.points.values(), MIN_VIEW_COS) {
            held.insert(p.id);
        }
    }
    into.points
        .keys()
        .filter(|id| !held.contains(id))
        .copied()
        .collect()
}

/// The place a closure matched in a map: the keyframes matched and those sharing at least
/// `min_shared` points with one of them (ORB-SLAM's covisibility threshold is 15).
pub fn place_of(map: &Map, matched: impl Iterator<Item = KfId>, min_shared: u32) -> BTreeSet<KfId> {
    let mut place = BTreeSet::new();
    for k in matched {
        let Some(kf) = map.keyframes.get(&k) else {
            continue;
        };
        place.insert(k);
        place.extend(
            kf.covisibility
                .iter()
                .filter(|&(_, &w)| w >= min_shared)
                .map(|(&c, _)| c),
        );
    }
    place
}

/// Descriptor distance under which a keypoint re-finds a map point (ORB-SLAM's TH_HIGH
/// is 100; stricter, because a look-alike surface is what is being told apart).
const APPEARANCE_MAX_DISTANCE: u32 = 80;
/// Image radius (pixels) searched around a projected point for its descriptor.
const APPEARANCE_SEARCH_PX: f64 = 10.0;
/// Cosine of the widest angle between a point's mean viewing direction and a view from which
/// its appearance is judged (53°, narrower than the depth check's 60°): ORB descriptors do not
/// survive much more perspective change. Measured 2026-11-29: at 60° the case study's corridor,
/// driven back the other way, found 0–8 % of its points (a right merge refused); at 53° every
/// right merge of the case study finds ≥ 29 %, and `aliasing`'s look-alike corridor 2 %; at
/// 45° or less that corridor is no longer judged at all.
const APPEARANCE_VIEW_COS: f64 = 0.6;

/// Appearance check of a merge: per keyframe of `from` placed by `alignment`, the points of
/// `into` whose depth it confirms (a reading within tolerance near the projection: the
/// surface is there, in view and not occluded, within the point's scale range and visibility
/// cone), and how many of those it also finds by descriptor. Returns (keyframe, confirmed,
/// found). A look-alike of the same shape and other texture confirms by depth and is not
/// found: per keyframe with 50 or more confirmed points, right merges of the benchmark found
/// 14–96 %, `aliasing`'s look-alikes 2–4 % (2026-11-29).
pub fn merge_appearance_check(
    geo: &crate::components::preprocess::ImageGeometry,
    into: &Map,
    from: &Map,
    alignment: &Isometry3<f64>,
) -> Vec<(KfId, usize, usize)> {
    per_keyframe_placed(from, alignment, |kf, pose_cw| {
        found_by_appearance(geo, kf, pose_cw, into.points.values())
    })
}

/// Of `points`, seen by keyframe `kf` from pose `pose_cw`: those whose depth it confirms
/// (within their scale range and [`APPEARANCE_VIEW_COS`]), and those of them it also finds by
/// descriptor.
fn found_by_appearance<'a>(
    geo: &crate::components::preprocess::ImageGeometry,
    kf: &crate::map::Keyframe,
    pose_cw: &Isometry3<f64>,
    points: impl Iterator<Item = &'a crate::map::MapPoint>,
) -> (usize, usize) {
    let (mut confirmed, mut found) = (0, 0);
    for (p, pc, uv, dist) in in_view(geo, pose_cw, points, APPEARANCE_VIEW_COS) {
        if dist < p.min_distance || dist > p.max_distance {
            continue;
        }
        let depths = depths_near(&kf.grid, &kf.keypoints, &kf.depth, uv.x, uv.y);
        if !depth_confirms(&depths, pc.z) {
            continue;
        }
        confirmed += 1;
        if looks_like(&kf.grid, &kf.keypoints, &kf.descriptors, &p.descriptor, uv) {
            found += 1;
        }
    }
    (confirmed, found)
}

/// Whether a keypoint within [`APPEARANCE_SEARCH_PX`] of pixel `uv` looks like `descriptor`
/// (within [`APPEARANCE_MAX_DISTANCE`]).
fn looks_like(
    grid: &crate::components::preprocess::FeatureGrid,
    keypoints: &[crate::components::preprocess::Keypoint],
    descriptors: &[crate::components::preprocess::Descriptor],
    descriptor: &crate::components::preprocess::Descriptor,
    uv: Vector2<f64>,
) -> bool {
    grid.in_area(keypoints, uv.x, uv.y, APPEARANCE_SEARCH_PX, 0, u8::MAX)
        .iter()
        .any(|&i| {
            crate::components::preprocess::hamming(&descriptors[i], descriptor)
                <= APPEARANCE_MAX_DISTANCE
        })
}

/// Of `points`, those in front of a camera at `pose_cw`, projecting into the image, and seen
/// within `min_cos` of their mean viewing direction: (point, position in the camera, pixel,
/// distance from the camera).
fn in_view<'a>(
    geo: &crate::components::preprocess::ImageGeometry,
    pose_cw: &Isometry3<f64>,
    points: impl Iterator<Item = &'a crate::map::MapPoint>,
    min_cos: f64,
) -> Vec<(&'a crate::map::MapPoint, Vector3<f64>, Vector2<f64>, f64)> {
    let center = pose_cw.inverse().translation.vector;
    points
        .filter_map(|p| {
            let pc = Map::in_camera(pose_cw, &p.position);
            if pc.z <= 0.1 {
                return None;
            }
            let ray = p.position - center;
            let dist = ray.norm();
            if ray.dot(&p.normal) < min_cos * dist {
                return None;
            }
            let uv = geo.project_in_image(&pc)?;
            Some((p, pc, uv, dist))
        })
        .collect()
}

/// Depth check of a new keyframe against the rest of its own map: the map points it does not
/// observe, seen from it. Returns (points judged, points it saw clearly through). A map that
/// a wrong closure joined to a look-alike place passes every check at the place itself, but
/// once the camera maps beyond what the two places share, its keyframes look through the
/// other place's structure — the contradiction the expectation check of Localized finds,
/// here for Mapping.
pub fn keyframe_depth_check(
    geo: &crate::components::preprocess::ImageGeometry,
    map: &Map,
    kf: KfId,
    judge: impl Fn(&crate::map::MapPoint) -> bool,
) -> (usize, usize) {
    let Some(k) = map.keyframes.get(&kf) else {
        return (0, 0);
    };
    // The keyframe's own points and those its neighbourhood made agree with it by
    // construction: judge the structure mapped from elsewhere.
    let own: BTreeSet<PointId> = k.points.iter().flatten().copied().collect();
    let near: BTreeSet<KfId> = k.covisibility.keys().copied().chain([kf]).collect();
    seen_through(
        geo,
        k,
        &k.pose_cw,
        map.points.values().filter(|p| {
            !own.contains(&p.id) && !near.contains(&p.first_kf) && map.depth_measured(p) && judge(p)
        }),
    )
}

/// Cosine of the widest angle between a point's mean viewing direction and a view from which
/// it is expected to be seen (ORB-SLAM's visibility cone, as in the tracker's projection
/// search). Beyond it the point's surface is seen edge-on: a depth sensor reads nothing there
/// (small `aliasing`: a corridor wall seen from the room at its end) and the readings nearby
/// are of what lies behind, which is no contradiction.
const MIN_VIEW_COS: f64 = 0.5;

/// Points judged by keyframe `kf`'s depth readings from pose `pose_cw`, and those it saw
/// clearly through (every reading near the projection is farther than the point). Only points
/// within their visibility cone ([`MIN_VIEW_COS`]) are judged.
fn seen_through<'a>(
    geo: &crate::components::preprocess::ImageGeometry,
    kf: &crate::map::Keyframe,
    pose_cw: &Isometry3<f64>,
    points: impl Iterator<Item = &'a crate::map::MapPoint>,
) -> (usize, usize) {
    let (mut judged, mut contradicted) = (0, 0);
    for (_, pc, uv, _) in in_view(geo, pose_cw, points, MIN_VIEW_COS) {
        let depths = depths_near(&kf.grid, &kf.keypoints, &kf.depth, uv.x, uv.y);
        if depths.is_empty() {
            continue;
        }
        judged += 1;
        let tol = depth_tolerance(pc.z);
        if !depth_confirms(&depths, pc.z) && depths.iter().all(|d| *d > pc.z + tol) {
            contradicted += 1;
        }
    }
    (judged, contradicted)
}

/// Depth tolerance of the expectation check at depth `z` (m): sensor noise plus the spread
/// of keypoints around a projected point near depth edges.
fn depth_tolerance(z: f64) -> f64 {
    0.05 + 0.08 * z
}

/// Whether a rigid correction of `metres` and `radians` moves no point at any depth `z` beyond
/// `depth_tolerance` (it moves a point by at most metres + radians·z): a change the depth
/// checks cannot see.
pub fn within_depth_tolerance(metres: f64, radians: f64) -> bool {
    metres <= depth_tolerance(0.0) && radians <= depth_tolerance(1.0) - depth_tolerance(0.0)
}

/// Whether one of the depth readings near a point's projection is at its depth `z`
/// (within [`depth_tolerance`]): the surface is there and nothing hides it.
fn depth_confirms(depths: &[f64], z: f64) -> bool {
    let tol = depth_tolerance(z);
    depths.iter().any(|d| (d - z).abs() <= tol)
}

/// Image radius (pixels) searched around a projected point for keypoints with depth.
const DEPTH_SEARCH_PX: f64 = 6.0;

/// Depth readings (m) of the keypoints within [`DEPTH_SEARCH_PX`] of pixel (`u`, `v`).
fn depths_near(
    grid: &crate::components::preprocess::FeatureGrid,
    keypoints: &[crate::components::preprocess::Keypoint],
    depth: &[f32],
    u: f64,
    v: f64,
) -> Vec<f64> {
    grid.in_area(keypoints, u, v, DEPTH_SEARCH_PX, 0, u8::MAX)
        .iter()
        .map(|&i| depth[i] as f64)
        .filter(|d| *d > 0.0)
        .collect()
}

pub fn expectation(
    geo: &crate::components::preprocess::ImageGeometry,
    map: &Map,
    m: &crate::components::preprocess::Measurement,
    track: &crate::components::tracker::TrackResult,
    cell_px: f64,
    coverage_cell_px: f64,
) -> Expectation {
    let cell = |uv: (f64, f64), px: f64| ((uv.0 / px) as u32, (uv.1 / px) as u32);
    let mut predicted: Vec<(f64, f64)> = Vec::new();
    let mut resembling: BTreeSet<(u32, u32)> = BTreeSet::new();
    // Only the appearance check without depth asks for resemblance.
    let judge_texture = m.n_with_depth() == 0;
    let (mut depth_confirmed, mut depth_contradicted) = (0, 0);
    for p in track.visible.iter().filter_map(|id| map.points.get(id)) {
        let pc = Map::in_camera(&track.pose_cw, &p.position);
        let Some(uv) = geo.project_in_image(&pc) else {
            continue;
        };
        predicted.push((uv.x, uv.y));
        let c = cell((uv.x, uv.y), cell_px);
        if judge_texture
            && !resembling.contains(&c)
            && looks_like(&m.grid, &m.keypoints, &m.descriptors, &p.descriptor, uv)
        {
            resembling.insert(c);
        }
        let depths = depths_near(&m.grid, &m.keypoints, &m.depth, uv.x, uv.y);
        if depths.is_empty() {
            continue;
        }
        let tol = depth_tolerance(pc.z);
        if depth_confirms(&depths, pc.z) {
            depth_confirmed += 1;
        } else if depths.iter().all(|d| *d > pc.z + tol) {
            depth_contradicted += 1;
        }
    }
    let expected: BTreeSet<(u32, u32)> = predicted.iter().map(|&uv| cell(uv, cell_px)).collect();
    let confirmed = track
        .matches
        .iter()
        .zip(&m.keypoints)
        .filter(|(mt, _)| mt.is_some())
        .map(|(_, k)| cell((k.un.x, k.un.y), cell_px))
        .filter(|c| expected.contains(c))
        .collect::<BTreeSet<_>>();
    // Coverage is judged on coarser cells: the map's points are sparser than the keypoints.
    let known: BTreeSet<(u32, u32)> = predicted
        .iter()
        .map(|&uv| cell(uv, coverage_cell_px))
        .collect();
    let features: BTreeSet<(u32, u32)> = m
        .keypoints
        .iter()
        .map(|k| cell((k.un.x, k.un.y), coverage_cell_px))
        .collect();
    Expectation {
        expected_cells: expected.len(),
        confirmed_cells: confirmed.len(),
        resembled_cells: resembling.difference(&confirmed).count(),
        depth_confirmed,
        depth_contradicted,
        feature_cells: features.len(),
        covered_cells: features.intersection(&known).count(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::components::preprocess::{ImageGeometry, Measurement};
    use crate::optim::Intrinsics;
    use nalgebra::{Vector2, Vector3};

    /// A 20 × 15 grid of keypoints over a 640 × 480 image, every one with depth `depth` and
    /// descriptor `texture` (its texture, as far as ORB can tell).
    fn wall_view(frame: usize, depth: f32, texture: u8) -> Measurement {
        let uvs = (0..15).flat_map(|j| {
            (0..20).map(move |i| Vector2::new(16.0 + 32.0 * i as f64, 16.0 + 32.0 * j as f64))
        });
        Measurement::synthetic(frame, uvs, 0.0, depth, vec![[texture; 32]; 300])
    }

    /// A keyframe at the origin whose points lie at its depth readings.
    fn add_wall_keyframe(map: &mut Map, geo: &ImageGeometry, frame: usize, depth: f32) -> KfId {
        add_textured_wall_keyframe(map, geo, frame, depth, 0)
    }

    fn add_textured_wall_keyframe(
        map: &mut Map,
        geo: &ImageGeometry,
        frame: usize,
        depth: f32,
        texture: u8,
    ) -> KfId {
        let m = wall_view(frame, depth, texture);
        let kf = map.add_keyframe(&m, Isometry3::identity());
        for (i, kp) in m.keypoints.iter().enumerate() {
            let i_ = &geo.intr;
            let z = depth as f64;
            let p = Vector3::new(
                (kp.un.x - i_.cx) * z / i_.fx,
                (kp.un.y - i_.cy) * z / i_.fy,
                z,
            );
            map.add_point(kf, i, p, 1.2, 8);
        }
        kf
    }

    /// Three keyframes 1 m apart along x; the first two share points, the third shares none
    /// with them (culling removed them) and, when `tied`, was tracked against the second
    /// (`parent`).
    fn chain_with_detached_keyframe(tied: bool) -> (Map, [KfId; 3]) {
        let geo = ImageGeometry::new(Intrinsics::TUM_FREIBURG1, 640, 480, 1.2, 8);
        let mut map = Map::new(0);
        let a = add_wall_keyframe(&mut map, &geo, 0, 3.0);
        let m = wall_view(1, 3.0, 0);
        let b = map.add_keyframe(&m, Isometry3::translation(-1.0, 0.0, 0.0));
        let points: Vec<PointId> = map.keyframes[&a].points.iter().flatten().copied().collect();
        for (i, p) in points.into_iter().enumerate() {
            map.observe(b, i, p);
        }
        map.update_covisibility(b);
        let c = map.add_keyframe(
            &wall_view(2, 3.0, 0),
            Isometry3::translation(-2.0, 0.0, 0.0),
        );
        map.keyframes.get_mut(&c).expect("added").parent = tied.then_some(b);
        (map, [a, b, c])
    }

    #[test]
    fn a_keyframe_sharing_no_points_stays_tied_to_the_keyframe_it_was_tracked_against() {
        let (map, [a, b, c]) = chain_with_detached_keyframe(true);
        let edges = essential_edges(&map, 100);
        assert!(edges.contains(&(a, b)), "covisible pair: {edges:?}");
        assert!(edges.contains(&(b, c)), "tracking chain kept: {edges:?}");
        let (map, _) = chain_with_detached_keyframe(false);
        assert!(
            !essential_edges(&map, 100).iter().any(|e| e.1 == c),
            "no parent, no covisibility: nothing ties it"
        );
    }

    #[test]
    fn a_loop_that_would_turn_a_detached_keyframe_around_is_inconsistent() {
        // The loop says keyframe c is back at a's place, turned 166°: with c tied to b by the
        // tracking chain that bends the map and the optimiser flags it; untied, c just moves.
        let cfg = LoopClosingConfig::default();
        let z = Sim3::from_isometry(&Isometry3::new(
            Vector3::new(0.3, 0.0, 0.2),
            Vector3::y() * 166f64.to_radians(),
        ));
        let info = Matrix6::identity() * 1e4;
        let run = |tied| {
            let (mut map, [a, _, c]) = chain_with_detached_keyframe(tied);
            let edge = ClosureEdge::new(0, c, a, &z, (1.0, 1.0), info);
            optimize_map(&cfg, &mut map, &[edge], &[a], false)
        };
        let tied = run(true);
        assert!(!tied.consistent, "{tied:?}");
        let untied = run(false);
        assert!(untied.consistent, "{untied:?}");
    }

    #[test]
    fn a_keyframe_that_sees_through_older_structure_is_flagged() {
        let geo = ImageGeometry::new(Intrinsics::TUM_FREIBURG1, 640, 480, 1.2, 8);
        // The map says a wall stands 2 m ahead; a later keyframe from the same place reads
        // 3.5 m everywhere (a look-alike place with the far wall farther away).
        let mut map = Map::new(0);
        add_wall_keyframe(&mut map, &geo, 0, 2.0);
        let new = add_wall_keyframe(&mut map, &geo, 1, 3.5);
        let (judged, through) = keyframe_depth_check(&geo, &map, new, |_| true);
        assert!(judged >= 250, "judged {judged}");
        assert!(
            through as f64 > 0.9 * judged as f64,
            "{through} of {judged}"
        );

        // The same wall seen again: nothing is contradicted.
        let mut map = Map::new(0);
        add_wall_keyframe(&mut map, &geo, 0, 2.0);
        let again = add_wall_keyframe(&mut map, &geo, 1, 2.05);
        let (judged, through) = keyframe_depth_check(&geo, &map, again, |_| true);
        assert!(judged >= 250, "judged {judged}");
        assert_eq!(through, 0);

        // Structure seen farther than the map's: occlusion is no contradiction.
        let mut map = Map::new(0);
        add_wall_keyframe(&mut map, &geo, 0, 3.5);
        let nearer = add_wall_keyframe(&mut map, &geo, 1, 2.0);
        assert_eq!(keyframe_depth_check(&geo, &map, nearer, |_| true).1, 0);
    }

    #[test]
    fn points_seen_edge_on_are_not_judged() {
        let geo = ImageGeometry::new(Intrinsics::TUM_FREIBURG1, 640, 480, 1.2, 8);
        // The wall's points were observed from the side (mean viewing direction along x, a little
        // from behind, so that every ray from the origin is more than 60° off it): from the
        // origin their surface is edge-on, where a depth sensor reads nothing and the readings
        // near them (3.5 m) are of what lies behind.
        let mut map = Map::new(0);
        add_wall_keyframe(&mut map, &geo, 0, 2.0);
        let new = add_wall_keyframe(&mut map, &geo, 1, 3.5);
        let seen_from = |map: &mut Map, dir: Vector3<f64>| {
            for p in map.points.values_mut().filter(|p| p.first_kf != new) {
                p.normal = dir.normalize();
            }
        };
        seen_from(&mut map, Vector3::new(1.0, 0.0, -0.2));
        assert_eq!(keyframe_depth_check(&geo, &map, new, |_| true), (0, 0));
        // Observed from 45° off the new view: within the visibility cone, judged.
        seen_from(&mut map, Vector3::new(1.0, 0.0, 1.0));
        let (judged, through) = keyframe_depth_check(&geo, &map, new, |_| true);
        assert!(judged >= 100, "judged {judged}");
        assert_eq!(through, judged);
    }

    #[test]
    fn points_of_covisible_keyframes_are_not_judged() {
        let geo = ImageGeometry::new(Intrinsics::TUM_FREIBURG1, 640, 480, 1.2, 8);
        let mut map = Map::new(0);
        let old = add_wall_keyframe(&mut map, &geo, 0, 2.0);
        let new = add_wall_keyframe(&mut map, &geo, 1, 3.5);
        map.keyframes
            .get_mut(&new)
            .unwrap()
            .covisibility
            .insert(old, 100);
        assert_eq!(keyframe_depth_check(&geo, &map, new, |_| true), (0, 0));
    }

    #[test]
    fn a_merge_onto_the_same_shape_with_other_texture_is_told_apart_by_appearance() {
        let geo = ImageGeometry::new(Intrinsics::TUM_FREIBURG1, 640, 480, 1.2, 8);
        let mut into = Map::new(0);
        add_textured_wall_keyframe(&mut into, &geo, 0, 2.0, 0x00);
        let check = |depth: f32, texture: u8| {
            let mut from = Map::new(1);
            add_textured_wall_keyframe(&mut from, &geo, 1, depth, texture);
            merge_appearance_check(&geo, &into, &from, &Isometry3::identity())[0]
        };
        // The same wall, the same texture: every point confirmed by depth is found.
        let (_, confirmed, found) = check(2.0, 0x00);
        assert!(confirmed >= 250, "confirmed {confirmed}");
        assert_eq!(found, confirmed);
        // The same wall with another texture (a look-alike room's door onto another
        // corridor): confirmed by depth, found by nothing.
        let (_, confirmed, found) = check(2.0, 0xff);
        assert!(confirmed >= 250, "confirmed {confirmed}");
        assert_eq!(found, 0);
        // A wall farther away: the points are not where this keyframe sees a surface, so
        // appearance is not judged (the depth check's business).
        assert_eq!(check(3.5, 0x00).1, 0);
    }

    /// What a merged map never had in view stays unheld: a map of a wall seen from the front,
    /// merged with a map whose keyframe looks the other way, holds none of it; one looking at
    /// it holds all of it, also under a similarity (monocular scale). Tracking on enough
    /// unheld points for a few frames confirms the merge; a few chance matches do not.
    #[test]
    fn a_merge_is_confirmed_only_by_what_the_merged_map_never_saw() {
        use crate::atlas::MergeEvidence;
        let geo = ImageGeometry::new(Intrinsics::TUM_FREIBURG1, 640, 480, 1.2, 8);
        let mut into = Map::new(0);
        add_wall_keyframe(&mut into, &geo, 0, 2.0);
        let n = into.points.len();
        assert!(n >= 250);
        // Looking at the wall: everything held.
        let mut facing = Map::new(1);
        add_wall_keyframe(&mut facing, &geo, 1, 2.0);
        assert!(
            unheld_points(&geo, &into, &facing, &Sim3::identity(), &BTreeSet::new()).is_empty()
        );
        // The same view in a map of half the scale: placed by the similarity, the same.
        let half = Sim3 {
            scale: 2.0,
            ..Sim3::identity()
        };
        let mut small = Map::new(2);
        add_wall_keyframe(&mut small, &geo, 1, 1.0);
        assert!(unheld_points(&geo, &into, &small, &half, &BTreeSet::new()).is_empty());
        // Turned around: nothing of the wall was in its view.
        let behind = Sim3::from_isometry(&Isometry3::rotation(Vector3::y() * std::f64::consts::PI));
        let unheld = unheld_points(&geo, &into, &facing, &behind, &BTreeSet::new());
        assert_eq!(unheld.len(), n);
        // Unless it is the place matched: what its keyframes observed is the place itself.
        let place = place_of(&into, into.keyframes.keys().copied(), 15);
        assert!(unheld_points(&geo, &into, &facing, &behind, &place).is_empty());
        let mut ev = MergeEvidence {
            unheld,
            ..Default::default()
        };
        let ids: Vec<PointId> = into.points.keys().copied().collect();
        let few = &ids[..MergeEvidence::MIN_POINTS - 1];
        for f in 0..10 {
            assert!(!ev.observe(few.iter().copied(), f));
        }
        let enough = &ids[..MergeEvidence::MIN_POINTS];
        let confirmed: Vec<bool> = (10..10 + MergeEvidence::MIN_FRAMES)
            .map(|f| ev.observe(enough.iter().copied(), f))
            .collect();
        assert_eq!(confirmed.iter().filter(|&&c| c).count(), 1);
        assert!(*confirmed.last().unwrap());
        assert_eq!(ev.confirmed, Some(9 + MergeEvidence::MIN_FRAMES));
    }

    /// Without depth, a predicted cell the tracker did not match is resembled when the camera
    /// sees the point's texture there (blur, a changed viewpoint), not when it sees another
    /// texture (a look-alike's surroundings).
    #[test]
    fn unmatched_cells_are_resembled_only_by_the_texture_the_map_predicts() {
        let geo = ImageGeometry::new(Intrinsics::TUM_FREIBURG1, 640, 480, 1.2, 8);
        let mut map = Map::new(0);
        add_textured_wall_keyframe(&mut map, &geo, 0, 2.0, 0x00);
        let seen = |texture: u8, matched_every: usize| {
            let mut m = wall_view(1, 2.0, texture);
            m.depth.fill(0.0);
            let points: Vec<PointId> = map.points.keys().copied().collect();
            // The keypoints are the wall's, in the same order as its points.
            let matches = (0..m.keypoints.len())
                .map(|i| (i % matched_every == 0).then_some(points[i]))
                .collect();
            let track = crate::components::tracker::TrackResult {
                pose_cw: Isometry3::identity(),
                matches,
                n_inliers: 0,
                able_to_track: true,
                method: crate::components::tracker::TrackMethod::MotionModel,
                reference_kf: None,
                visible: points,
                twist: nalgebra::Vector6::zeros(),
                mean_chi2: 0.0,
            };
            expectation(&geo, &map, &m, &track, 640.0 / 16.0, 640.0 / 8.0)
        };
        // A quarter of the points matched; the rest show the predicted texture.
        let e = seen(0x00, 4);
        assert!(e.expected_cells >= 100, "{e:?}");
        assert!(e.confirmed_cells < e.expected_cells, "{e:?}");
        assert_eq!(
            e.confirmed_cells + e.resembled_cells,
            e.expected_cells,
            "{e:?}"
        );
        assert_eq!(e.found_share(), 1.0);
        // The same matches, another texture around them: nothing more is found.
        let e = seen(0xff, 4);
        assert!(e.confirmed_cells > 0, "{e:?}");
        assert_eq!(e.resembled_cells, 0, "{e:?}");
        assert_eq!(e.found_share(), e.ratio());
    }

    #[test]
    fn triangulated_points_are_not_judged_by_depth() {
        let geo = ImageGeometry::new(Intrinsics::TUM_FREIBURG1, 640, 480, 1.2, 8);
        let mut map = Map::new(0);
        let old = add_wall_keyframe(&mut map, &geo, 0, 2.0);
        let new = add_wall_keyframe(&mut map, &geo, 1, 3.5);
        // The old keyframe had no depth readings for its points (they were triangulated):
        // their place along the rays is too uncertain for the depth check.
        map.keyframes.get_mut(&old).unwrap().depth.fill(0.0);
        assert_eq!(keyframe_depth_check(&geo, &map, new, |_| true), (0, 0));
        // The same for a merge: the other map's keyframe reads 3.5 m where they stand.
        let mut triangulated = Map::new(0);
        let k = add_wall_keyframe(&mut triangulated, &geo, 0, 2.0);
        let mut from = Map::new(1);
        add_wall_keyframe(&mut from, &geo, 2, 3.5);
        let judged = |m: &Map| merge_depth_check(&geo, m, &from, &Isometry3::identity())[0];
        let (_, n, through) = judged(&triangulated);
        assert!(n >= 250 && through == n, "{through} of {n}");
        triangulated.keyframes.get_mut(&k).unwrap().depth.fill(0.0);
        assert_eq!(judged(&triangulated).1, 0);
    }
}
