//! Loop validator (paper Table I): closure candidates → valid closures, reporting
//! `able_to_localize`.
//!
//! Two stages, because one wrong closure can ruin a map:
//! 1. **Geometry**, per candidate: the detector's descriptor matches between the query and a
//!    keyframe, plus a wider descriptor search among the keyframe's map points (ORB-SLAM's
//!    SearchByBoW), become 3-D correspondences (query keypoints with depth ↔ the keyframe's map
//!    points) for a 3-D–3-D RANSAC (Umeyama), or 2-D–3-D for OpenCV's PnP RANSAC when the query
//!    has too little depth; the pose found is then refined against the keyframe's whole local
//!    map (projection search + robust pose-only optimisation). Enough inliers, and a large
//!    enough share of the projected points found, make the candidate *valid*. Without depth
//!    (monocular) the query's own map points give the other side of a similarity: Sim3 RANSAC
//!    (ORB-SLAM's Sim3Solver) for the initial pose, and the scale of the query's map in the
//!    matched one from the refined inliers, so that closures and merges correct scale drift.
//! 2. **A pool** (the delayed decision of paper section III): a valid candidate implies an
//!    alignment of the query's map onto the matched map (for a loop inside one map: the
//!    correction of the drift). A closure is accepted only when `pool_size` valid candidates
//!    from different query frames, within a window of recent frames, agree on that alignment.
//!    Alignments of pools that were rolled back or refused are remembered, and candidates
//!    within the wider refusal tolerances of one are refused (the same hypothesis anchored on
//!    other keyframes of a bent map).
//!
//! The validator reports; the state machine decides what an accepted pool leads to.

use crate::components::aligner::{backproject, pnp_ransac, rigid_ransac};
use crate::components::preprocess::{
    ImageGeometry, Measurement, dominant_rotation_bins, hamming, nearest_descriptor, rotation_bin,
};
use crate::components::two_view::{Sim3RansacParams, sim3_ransac};
use crate::config::LoopClosingConfig;
use crate::geometry::Sim3;
use crate::map::{KfId, Map, PointId};
use crate::optim::{
    Observation, PoseObservation, PoseParams, octave_information, refine_pose, se3,
};
use nalgebra::{Isometry3, Matrix6, Point3, Vector2, Vector3};
use std::collections::{BTreeMap, BTreeSet, VecDeque};

pub use crate::components::loop_detector::Candidate;

/// Why a candidate was not valid.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rejection {
    TooFewMatches,
    Geometry,
    Refinement,
    /// Monocular: too few inliers carry a point of the query's map to measure the scale.
    Scale,
    RolledBackAlignment,
    /// A loop within one map that would move the camera farther than the odometry could
    /// have drifted along the path since the matched keyframe ([`implausible_drift`]).
    ImplausibleDrift,
}

impl Rejection {
    pub fn as_str(self) -> &'static str {
        match self {
            Self::TooFewMatches => "rejected:too-few-matches",
            Self::Geometry => "rejected:geometry",
            Self::Refinement => "rejected:refinement",
            Self::Scale => "rejected:scale",
            Self::RolledBackAlignment => "rejected:rolled-back-alignment",
            Self::ImplausibleDrift => "rejected:implausible-drift",
        }
    }
}

/// A geometrically valid candidate.
#[derive(Debug, Clone)]
pub struct Valid {
    pub frame: usize,
    pub t: f64,
    /// Map of the query (where its pose `query_pose` lives) and of the match.
    pub query_map: u32,
    pub match_map: u32,
    pub matched: KfId,
    /// The query's keyframe, when the query is a keyframe (loop closing in Mapping).
    pub query_kf: Option<KfId>,
    /// The keyframe of the query's map that `query_pose` was tracked against (the query
    /// keyframe itself, or a frame's reference keyframe); the closure edge hangs on it.
    pub reference_kf: Option<KfId>,
    /// The query frame's pose in its own map, and the one found in the matched map.
    pub query_pose: Isometry3<f64>,
    pub pose_in_match: Isometry3<f64>,
    /// Lengths in the matched map per length in the query's map (monocular; 1 with depth):
    /// query-camera coordinates times `scale` are `pose_in_match`'s camera coordinates.
    pub scale: f64,
    /// Query keypoint → matched-map point, inliers of the refinement; with `own_points`, the
    /// query's points in its own map instead.
    pub matches: Vec<Option<PointId>>,
    /// Validated from the query's depth ([`validate_from_query_depth`]): the matched map's
    /// points were too few, and tracking goes on from the query's own points once merged.
    pub own_points: bool,
    pub n_inliers: usize,
    /// Information of `pose_in_match` (Gauss–Newton, scaled by the residual variance).
    pub information: Matrix6<f64>,
}

impl Valid {
    /// Query `q` found at `pose_in_match` in map `match_map` through its keyframe `matched`:
    /// scale 1, no matches, no inliers and no information yet.
    fn of_query(q: &Query, match_map: u32, matched: KfId, pose_in_match: Isometry3<f64>) -> Self {
        Valid {
            frame: q.m.frame,
            t: q.m.t,
            query_map: q.map,
            match_map,
            matched,
            query_kf: q.kf,
            reference_kf: q.reference_kf.or(q.kf),
            query_pose: q.pose,
            pose_in_match,
            scale: 1.0,
            matches: Vec::new(),
            own_points: false,
            n_inliers: 0,
            information: Matrix6::zeros(),
        }
    }

    /// The alignment this candidate implies: query-map world → matched-map world.
    pub fn alignment(&self) -> Sim3 {
        let rigid = Sim3::from_isometry(&(self.pose_in_match.inverse() * self.query_pose));
        if self.scale == 1.0 {
            return rigid;
        }
        let q = Sim3::from_isometry(&self.query_pose);
        let scaled = Sim3 {
            scale: self.scale,
            ..Sim3::identity()
        };
        Sim3::from_isometry(&self.pose_in_match.inverse())
            .compose(&scaled)
            .compose(&q)
    }
}

/// Outcome of validating one candidate.
#[derive(Debug, Clone)]
pub enum Verdict {
    Valid(Box<Valid>),
    Rejected {
        matched: KfId,
        reason: Rejection,
        inliers: usize,
        /// Best pose found before the rejection, if any (for the closure log).
        pose_in_match: Option<Isometry3<f64>>,
    },
}

/// The rejection of keyframe `matched`, from a reason, the inliers found and the best pose.
fn rejection_of(matched: KfId) -> impl Fn(Rejection, usize, Option<Isometry3<f64>>) -> Verdict {
    move |reason, inliers, pose_in_match| Verdict::Rejected {
        matched,
        reason,
        inliers,
        pose_in_match,
    }
}

/// What the query side brings to validation.
pub struct Query<'a> {
    pub m: &'a Measurement,
    pub map: u32,
    /// Pose of the query frame in its own map (identity when it has none yet).
    pub pose: Isometry3<f64>,
    /// The query's keyframe, when it is one.
    pub kf: Option<KfId>,
    /// The keyframe `pose` refers to (see [`Valid::reference_kf`]).
    pub reference_kf: Option<KfId>,
    /// Without depth: the query's map and the point of each query keypoint there (a
    /// keyframe's points, or a tracked frame's inlier matches), for the similarity.
    pub own: Option<(&'a Map, &'a [Option<PointId>])>,
}

/// Geometric validation of one candidate against keyframe `c.matched` of `map`.
pub fn validate(
    cfg: &LoopClosingConfig,
    geo: &ImageGeometry,
    q: &Query,
    map: &Map,
    c: &Candidate,
) -> Verdict {
    let matched = c.image as KfId;
    let reject = rejection_of(matched);
    let Some(kf) = map.keyframes.get(&matched) else {
        return reject(Rejection::TooFewMatches, 0, None);
    };
    // Correspondences: query keypoint ↔ the keyframe keypoint's map point, from the
    // detector's votes and from a wider descriptor search among the keyframe's map points.
    let mut pairs: Vec<(usize, PointId)> = Vec::new();
    let mut seen = BTreeSet::new();
    let mut used = vec![false; q.m.len()];
    for &(qi, ri) in &c.matches {
        let (qi, ri) = (qi as usize, ri as usize);
        let Some(Some(p)) = kf.points.get(ri) else {
            continue;
        };
        if qi < q.m.len() && map.points.contains_key(p) && !used[qi] && seen.insert(*p) {
            used[qi] = true;
            pairs.push((qi, *p));
        }
    }
    // Without depth, a keyframe holds only the points triangulated with its neighbours: the
    // last ones before a loss, which had no successor, hold few, and their neighbours the rest
    // of what they saw (ORB-SLAM3 searches the candidate's covisible window for merges).
    let window: Vec<KfId> = if kf.depth.iter().all(|d| *d <= 0.0) {
        std::iter::once(matched)
            .chain(kf.best_covisible(MONO_SEARCH_WINDOW))
            .collect()
    } else {
        vec![matched]
    };
    for k in window.iter().filter_map(|k| map.keyframes.get(k)) {
        for (qi, p) in search_keyframe_points(q.m, k, map) {
            if !used[qi] && seen.insert(p) {
                used[qi] = true;
                pairs.push((qi, p));
            }
        }
    }
    if pairs.len() < cfg.min_validation_matches as usize {
        return reject(Rejection::TooFewMatches, pairs.len(), None);
    }
    let similarity = q
        .own
        .and_then(|(own, points)| sim3_pose(cfg, geo, q, own, points, map, kf, &pairs));
    let Some(initial) = similarity.or_else(|| ransac_pose(cfg, geo, q.m, map, &pairs)) else {
        return reject(Rejection::Geometry, 0, None);
    };
    let mut matches: Vec<Option<PointId>> = vec![None; q.m.len()];
    for &(qi, p) in &pairs {
        matches[qi] = Some(p);
    }
    let Some(local) = local_window(map, matched) else {
        return reject(Rejection::TooFewMatches, 0, None);
    };
    refine_and_judge(cfg, geo, q, map, matched, &local, &initial, matches)
}

/// Validation of a hypothesis the pool already holds: the query's pose in `map` predicted
/// from a pending candidate's alignment (`prior`), the points of keyframe `matched` and its
/// covisible ones projected with it and matched near their projections (ORB-SLAM3 checks a
/// merge candidate in the next keyframes the same way, by projection through its similarity),
/// then refined and judged as [`validate`] judges. A frame a few centimetres from a validated
/// one but blurred, or turned, often finds too few of the keyframe's points by descriptor
/// alone (fr1_desk, two drops: 91 inliers at one frame, 16–30 descriptor matches at the next
/// ones); a wrong hypothesis projects points where the image shows something else.
pub fn validate_from_prior(
    cfg: &LoopClosingConfig,
    geo: &ImageGeometry,
    q: &Query,
    map: &Map,
    matched: KfId,
    prior: &Isometry3<f64>,
) -> Verdict {
    let reject = rejection_of(matched);
    let Some(local) = local_window(map, matched) else {
        return reject(Rejection::TooFewMatches, 0, None);
    };
    let mut matches: Vec<Option<PointId>> = vec![None; q.m.len()];
    let found = search_local_map(
        geo,
        q.m,
        map,
        &local,
        prior,
        PRIOR_SEARCH_RADIUS_PX,
        &mut matches,
    );
    if found < cfg.min_validation_matches as usize {
        return reject(Rejection::TooFewMatches, found, None);
    }
    refine_and_judge(cfg, geo, q, map, matched, &local, prior, matches)
}

/// Largest angle between the optical axes of a seam pair ([`seam_pairs`]).
const SEAM_MAX_ANGLE_DEG: f64 = 30.0;
/// Largest distance between the centres of a seam pair, as a share of the near keyframe's
/// median scene depth: the two must see much of one scene for a projection search.
const SEAM_MAX_DISTANCE: f64 = 0.5;
/// Depth readings (or, without depth, map points) a keyframe needs for its scene depth.
const MIN_SEAM_POINTS: usize = 20;

/// The pairs across a merge's seam that [`validate_seam_pair`] tries: for each keyframe of the
/// camera's side `near` (not panoramic), the keyframe of the other side `far` with the nearest
/// centre among those looking the same way (optical axes within 30°, centres within half the
/// near keyframe's median scene depth) and sharing no point with it yet.
///
/// A merge joins two maps at the one place the camera recognised. Where else the two sides saw
/// the same scene (above all where the camera's map began, beside where the other one was
/// lost) nothing ties them, and the joined map keeps the drift of both there: fr1_desk RGB-D
/// with a 1 s drop, the new map's first seconds 2.4–4 cm from the old map's last ones.
pub fn seam_pairs(map: &Map, near: &BTreeSet<KfId>, far: &BTreeSet<KfId>) -> Vec<(KfId, KfId)> {
    let cos_max = SEAM_MAX_ANGLE_DEG.to_radians().cos();
    let axis = |k: &crate::map::Keyframe| k.pose_cw.rotation.inverse() * Vector3::z();
    let mut pairs = Vec::new();
    for n in near.iter().filter_map(|k| map.keyframes.get(k)) {
        // A panoramic keyframe's centre is its turn's, which its bearings do not observe.
        if n.panoramic {
            continue;
        }
        // The scene's depth: the sensor's, or without depth its points' (`Map::scene_depth`).
        let mut depths: Vec<f64> = n
            .depth
            .iter()
            .filter(|d| **d > 0.0)
            .map(|d| *d as f64)
            .collect();
        let depth = if depths.len() >= MIN_SEAM_POINTS {
            let mid = depths.len() / 2;
            *depths.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1
        } else if n
            .points
            .iter()
            .flatten()
            .filter(|p| map.points.contains_key(p))
            .count()
            >= MIN_SEAM_POINTS
            && let Some(d) = map.scene_depth(n)
        {
            d
        } else {
            continue;
        };
        let (c, a) = (n.center(), axis(n));
        let best = far
            .iter()
            .filter_map(|k| map.keyframes.get(k))
            .filter(|f| !n.covisibility.contains_key(&f.id) && axis(f).dot(&a) >= cos_max)
            .map(|f| ((f.center() - c).norm(), f.id))
            .filter(|(d, _)| *d <= SEAM_MAX_DISTANCE * depth)
            .min_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
        if let Some((_, f)) = best {
            pairs.push((n.id, f));
        }
    }
    pairs
}

/// Validation of a seam pair ([`seam_pairs`]) in the joined map: keyframe `query` is the
/// query, at the pose the merge gave it, and the points of keyframe `matched` and of its
/// covisible keyframes in `window` (the other side) are projected and matched near their
/// projections, then refined and judged as any candidate ([`validate_from_prior`]).
pub fn validate_seam_pair(
    cfg: &LoopClosingConfig,
    geo: &ImageGeometry,
    map: &Map,
    query: KfId,
    matched: KfId,
    window: &BTreeSet<KfId>,
) -> Verdict {
    let reject = rejection_of(matched);
    let (Some(k), Some(mk)) = (map.keyframes.get(&query), map.keyframes.get(&matched)) else {
        return reject(Rejection::TooFewMatches, 0, None);
    };
    let m = Measurement {
        frame: k.frame,
        t: k.t,
        keypoints: k.keypoints.clone(),
        descriptors: k.descriptors.clone(),
        depth: k.depth.clone(),
        grid: k.grid.clone(),
        surface: Vec::new(),
    };
    // Without depth the pair's scale is measured too, from the query's own points.
    let mono = k.depth.iter().all(|d| *d <= 0.0);
    let q = Query {
        m: &m,
        map: map.id,
        pose: k.pose_cw,
        kf: Some(query),
        reference_kf: Some(query),
        own: mono.then_some((map, &k.points[..])),
    };
    let local: Vec<KfId> = std::iter::once(matched)
        .chain(mk.best_covisible(10))
        .filter(|k| window.contains(k))
        .collect();
    let mut matches: Vec<Option<PointId>> = vec![None; m.len()];
    let found = search_local_map(
        geo,
        &m,
        map,
        &local,
        &k.pose_cw,
        PRIOR_SEARCH_RADIUS_PX,
        &mut matches,
    );
    if found < cfg.min_validation_matches as usize {
        return reject(Rejection::TooFewMatches, found, None);
    }
    refine_and_judge(cfg, geo, &q, map, matched, &local, &k.pose_cw, matches)
}

/// Keyframe `matched` of `map` and its 10 best covisible ones: the local map a validation is
/// refined against (`None` if the keyframe is gone).
fn local_window(map: &Map, matched: KfId) -> Option<Vec<KfId>> {
    let kf = map.keyframes.get(&matched)?;
    Some(
        std::iter::once(matched)
            .chain(kf.best_covisible(10))
            .collect(),
    )
}

/// Search radius (pixels at the finest level) of [`validate_from_prior`]'s first projection:
/// the tracker's own (`tracker.search_radius_px` = 15 by default).
const PRIOR_SEARCH_RADIUS_PX: f64 = 15.0;

/// The common end of a validation: the pose from `initial` and the correspondences `matches`
/// refined against the matched keyframe's local map `local` ([`local_window`]; two projection
/// searches, 8 then 4 pixels), and judged by its inliers; with the query's own points
/// (monocular), the scale.
#[allow(clippy::too_many_arguments)]
fn refine_and_judge(
    cfg: &LoopClosingConfig,
    geo: &ImageGeometry,
    q: &Query,
    map: &Map,
    matched: KfId,
    local: &[KfId],
    initial: &Isometry3<f64>,
    mut matches: Vec<Option<PointId>>,
) -> Verdict {
    let reject = rejection_of(matched);
    let (mut pose, mut inliers) = refine(geo, q.m, map, initial, &matches);
    for radius in [8.0, 4.0] {
        let mut m2: Vec<Option<PointId>> = vec![None; q.m.len()];
        for (i, ok) in inliers.iter().enumerate() {
            if *ok {
                m2[i] = matches[i];
            }
        }
        let found = search_local_map(geo, q.m, map, local, &pose, radius, &mut m2);
        let (p2, inl2) = refine(geo, q.m, map, &pose, &m2);
        tracing::trace!(
            "validate kf {matched}: {} projected matches, {} inliers",
            found,
            inl2.iter().filter(|b| **b).count()
        );
        pose = p2;
        inliers = inl2;
        matches = m2;
    }
    let n = inliers.iter().filter(|b| **b).count();
    let matched_total = matches.iter().flatten().count().max(1);
    if n < cfg.min_inliers as usize || (n as f64) < cfg.min_inlier_ratio * matched_total as f64 {
        return reject(Rejection::Refinement, n, Some(pose));
    }
    let inlier_matches: Vec<Option<PointId>> = matches
        .iter()
        .zip(&inliers)
        .map(|(m, ok)| if *ok { *m } else { None })
        .collect();
    let scale = match q.own {
        None => 1.0,
        Some((own, points)) => match map_scale(q, own, points, map, &pose, &inlier_matches) {
            Some(s) => s,
            None => return reject(Rejection::Scale, n, Some(pose)),
        },
    };
    let information = pose_information(geo, q.m, map, &pose, &inlier_matches);
    Verdict::Valid(Box::new(Valid {
        scale,
        matches: inlier_matches,
        n_inliers: n,
        information,
        ..Valid::of_query(q, map.id, matched, pose)
    }))
}

/// Validation with the roles reversed, for the lost place's keyframe after a kidnapping: the
/// query's key points with depth (3-D in its camera) matched by descriptor to all of the
/// keyframe's key points, with or without a map point, and the keyframe's camera placed among
/// them by PnP RANSAC. The lost place is often a view from afar (a corridor looking into the
/// room the camera was carried into): its far content had no depth, so it has no map points
/// for [`validate`] to match, while the new map's first frames, closer, have depth for it.
/// Where the query does see the matched map's points (at least `min_inliers` of them from
/// that pose), the view is not one from afar: the pose is refined on them and, as for any
/// candidate of the lost place, must then reach `min_map_inliers`.
/// `own_matches` (the query frame's points in its own map) go on as the valid candidate's
/// matches: after the merge they are points of the joined map, and tracking goes on from them.
pub fn validate_from_query_depth(
    cfg: &LoopClosingConfig,
    geo: &ImageGeometry,
    q: &Query,
    map: &Map,
    matched: KfId,
    own_matches: &[Option<PointId>],
    min_map_inliers: usize,
) -> Verdict {
    let reject = rejection_of(matched);
    let Some(kf) = map.keyframes.get(&matched) else {
        return reject(Rejection::TooFewMatches, 0, None);
    };
    // Query key point with depth → nearest keyframe key point (≤ TH_LOW, Lowe's ratio), one
    // query key point per keyframe key point, in the dominant changes of orientation.
    let mut best: BTreeMap<usize, (u32, usize)> = BTreeMap::new();
    for qi in (0..q.m.len()).filter(|&i| q.m.depth[i] > 0.0) {
        let Some((bj, b1)) = nearest_descriptor(
            &q.m.descriptors[qi],
            kf.descriptors.iter().enumerate(),
            SEARCH_MAX_DISTANCE,
            SEARCH_RATIO,
        ) else {
            continue;
        };
        if best.get(&bj).is_none_or(|&(h, _)| b1 < h) {
            best.insert(bj, (b1, qi));
        }
    }
    let mut pairs: Vec<(usize, usize)> = best.iter().map(|(&j, &(_, qi))| (qi, j)).collect();
    let bin =
        |&(qi, j): &(usize, usize)| rotation_bin(kf.keypoints[j].angle, q.m.keypoints[qi].angle);
    let keep = dominant_rotation_bins(pairs.iter().map(bin));
    pairs.retain(|x| keep.contains(&bin(x)));
    if pairs.len() < cfg.min_validation_matches as usize {
        return reject(Rejection::TooFewMatches, pairs.len(), None);
    }
    // The keyframe's camera among the query's points: T_kq (query camera → keyframe camera).
    let pts: Vec<Vector3<f64>> = pairs
        .iter()
        .map(|&(qi, _)| backproject(&geo.intr, &q.m.keypoints[qi].un, q.m.depth[qi] as f64))
        .collect();
    let uv: Vec<Vector2<f64>> = pairs.iter().map(|&(_, j)| kf.keypoints[j].un).collect();
    let Some(found) = pnp_ransac(&pts, &uv, &geo.intr, 4.0, cfg.min_inliers as usize)
        .ok()
        .flatten()
    else {
        return reject(Rejection::Geometry, 0, None);
    };
    // Robust refinement of T_kq on the keyframe's observations of the query's points.
    let obs: Vec<PoseObservation> = pairs
        .iter()
        .zip(&pts)
        .map(|(&(_, j), x)| PoseObservation {
            point_w: *x,
            obs: Observation::Mono {
                uv: kf.keypoints[j].un,
            },
            info: octave_information(kf.keypoints[j].octave as u32),
            shutter: Isometry3::identity(),
        })
        .collect();
    let r = refine_pose(&found.pose, &obs, &geo.intr, &PoseParams::default());
    if r.n_inliers < cfg.min_inliers as usize {
        return reject(Rejection::Refinement, r.n_inliers, None);
    }
    let t_kq = r.pose;
    let mut pose = t_kq.inverse() * kf.pose_cw;
    // The matched map's own points where the query sees them: with enough of them the pose
    // is the validator's usual one, as precise as any relocalization.
    let mut local: Vec<KfId> = vec![matched];
    local.extend(kf.best_covisible(10));
    let mut matches: Vec<Option<PointId>> = vec![None; q.m.len()];
    search_local_map(geo, q.m, map, &local, &pose, 8.0, &mut matches);
    let (refined, inl) = refine(geo, q.m, map, &pose, &matches);
    let on_points = inl.iter().filter(|b| **b).count();
    if on_points >= cfg.min_inliers as usize && on_points < min_map_inliers {
        return reject(Rejection::Refinement, on_points, Some(refined));
    }
    let information = if on_points >= cfg.min_inliers as usize {
        pose = refined;
        let inlier_matches: Vec<Option<PointId>> = matches
            .iter()
            .zip(&inl)
            .map(|(m, ok)| if *ok { *m } else { None })
            .collect();
        pose_information(geo, q.m, map, &pose, &inlier_matches)
    } else {
        // The keyframe's observations inform T_kq = T_kw · T_qw⁻¹; a left perturbation ε of
        // T_qw is one of −Ad(T_kq)·ε of T_kq.
        let inliers: Vec<PoseObservation> = obs
            .iter()
            .zip(&r.inliers)
            .filter(|(_, ok)| **ok)
            .map(|(o, _)| *o)
            .collect();
        let ad = se3::adjoint(&t_kq);
        ad.transpose() * information_of(geo, &t_kq, &inliers) * ad
    };
    let sigma = information
        .try_inverse()
        .map(|c| {
            let d = c.diagonal().map(|x| x.max(0.0).sqrt());
            (
                d.rows(0, 3).norm().to_degrees(),
                100.0 * d.rows(3, 3).norm(),
            )
        })
        .unwrap_or((f64::INFINITY, f64::INFINITY));
    tracing::debug!(
        "validate kf {matched} from the query's depth: {} pairs, {} PnP inliers, {} refined, {on_points} on the matched map's points, sigma {:.2} deg {:.2} cm",
        pairs.len(),
        found.n_inliers,
        r.n_inliers,
        sigma.0,
        sigma.1
    );
    Verdict::Valid(Box::new(Valid {
        matches: own_matches.to_vec(),
        own_points: true,
        n_inliers: r.n_inliers,
        information,
        ..Valid::of_query(q, map.id, matched, pose)
    }))
}

/// A loop within one map says where the camera is in that map; its map says where tracking put
/// it. The difference is the drift the loop corrects, and odometry can only have drifted so far
/// along the path from the matched keyframe: the pose graph's own model, σ = odometry_sigma +
/// odometry_sigma_per_m · path length (metres; degrees likewise). A correction beyond
/// `drift_gate_sigmas` σ is a look-alike place, not drift (a copy of a room several metres
/// away), and pooling it would only leave the consistency check to undo it, with the keyframes
/// made since. Returns (correction m, correction °, path m) when the loop is implausible.
/// Only for a map with metric scale (`v.scale` 1) and a loop within it.
pub fn implausible_drift(cfg: &LoopClosingConfig, map: &Map, v: &Valid) -> Option<(f64, f64, f64)> {
    let gate = cfg.drift_gate_sigmas;
    if gate <= 0.0 || v.query_map != v.match_map || v.scale != 1.0 {
        return None;
    }
    let matched_t = map.keyframes.get(&v.matched)?.t;
    let centre = |p: &Isometry3<f64>| p.inverse().translation.vector;
    // The path: keyframes from the matched one on, in time order, then the query camera.
    let mut kfs: Vec<(f64, Vector3<f64>)> = map
        .keyframes
        .values()
        .filter(|k| k.t >= matched_t && k.t <= v.t)
        .map(|k| (k.t, centre(&k.pose_cw)))
        .collect();
    kfs.sort_by(|a, b| a.0.total_cmp(&b.0));
    kfs.push((v.t, centre(&v.query_pose)));
    let path: f64 = kfs.windows(2).map(|w| (w[1].1 - w[0].1).norm()).sum();
    let moved = (centre(&v.query_pose) - centre(&v.pose_in_match)).norm();
    let turned = (v.query_pose.rotation * v.pose_in_match.rotation.inverse())
        .angle()
        .to_degrees();
    let max_m = gate * (cfg.odometry_sigma_m + cfg.odometry_sigma_per_m * path);
    let max_deg = gate * (cfg.odometry_sigma_deg + cfg.odometry_sigma_deg_per_m * path);
    (moved > max_m || turned > max_deg).then_some((moved, turned, path))
}

/// Largest Hamming distance of a descriptor-search match (ORB-SLAM's TH_LOW).
pub(crate) const SEARCH_MAX_DISTANCE: u32 = 50;
/// Lowe's ratio of the descriptor search (ORB-SLAM's SearchByBoW: 0.75).
const SEARCH_RATIO: f64 = 0.75;

/// ORB-SLAM's SearchByBoW without a vocabulary: every map point of keyframe `kf` is matched to
/// its nearest query descriptor (≤ [`SEARCH_MAX_DISTANCE`], Lowe's ratio), one point per query
/// keypoint, and only matches in the dominant changes of keypoint orientation are kept. The
/// loop detector's index only finds descriptors within its tight distance; from another
/// viewpoint (a second session, a re-entry from the other side) most true matches are
/// farther, and without them a right candidate fails for want of correspondences.
fn search_keyframe_points(
    m: &Measurement,
    kf: &crate::map::Keyframe,
    map: &Map,
) -> Vec<(usize, PointId)> {
    let best = map.search_by_descriptor(kf, m, SEARCH_MAX_DISTANCE, SEARCH_RATIO);
    let mut pairs: Vec<(usize, PointId, usize)> = best
        .iter()
        .enumerate()
        .filter_map(|(qi, b)| b.map(|(_, p, ri)| (qi, p, ri)))
        .collect();
    let bin = |&(qi, _, ri): &(usize, PointId, usize)| {
        rotation_bin(kf.keypoints[ri].angle, m.keypoints[qi].angle)
    };
    let keep = dominant_rotation_bins(pairs.iter().map(bin));
    pairs.retain(|x| keep.contains(&bin(x)));
    pairs.into_iter().map(|(qi, p, _)| (qi, p)).collect()
}

/// Covisible keyframes searched with a monocular candidate (ORB-SLAM3's merge detection: 5).
const MONO_SEARCH_WINDOW: usize = 5;
/// Fewest inliers of the monocular similarity RANSAC (ORB-SLAM2's loop closing: 20).
const SIM3_MIN_INLIERS: usize = 20;
/// Fewest refined inliers with a point of the query's map to measure the scale.
const SCALE_MIN_PAIRS: usize = 10;

/// Monocular initial pose (ORB-SLAM's Sim3Solver): the query's own points in its camera
/// frame ↔ the paired points in the matched keyframe's, observed there by `kf`; a similarity by
/// RANSAC with reprojection inliers in both images. Returns the query camera's pose in the
/// matched map (its camera frame rescaled to the matched map's lengths).
#[allow(clippy::too_many_arguments)]
fn sim3_pose(
    cfg: &LoopClosingConfig,
    geo: &ImageGeometry,
    q: &Query,
    own: &Map,
    own_points: &[Option<PointId>],
    map: &Map,
    kf: &crate::map::Keyframe,
    pairs: &[(usize, PointId)],
) -> Option<Isometry3<f64>> {
    let (mut p1, mut p2, mut uv1, mut uv2) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for &(qi, pm) in pairs {
        let Some(xq) = own_point(own, own_points, qi) else {
            continue;
        };
        let xm = &map.points[&pm];
        let in_kf = (kf.pose_cw * Point3::from(xm.position)).coords;
        // Where the keyframe saw the point, or (a point of its covisible window) where it
        // projects in it.
        let uv_kf = match xm.observations.get(&kf.id) {
            Some(&ri) => kf.keypoints[ri].un,
            None => match geo.project_in_image(&in_kf) {
                Some(uv) => uv,
                None => continue,
            },
        };
        p1.push((q.pose * Point3::from(xq.position)).coords);
        p2.push(in_kf);
        uv1.push(q.m.keypoints[qi].un);
        uv2.push(uv_kf);
    }
    let params = Sim3RansacParams {
        sigma: 1.5,
        min_inliers: SIM3_MIN_INLIERS.max(cfg.min_inliers as usize / 2),
        ..Default::default()
    };
    let (s21, _) = sim3_ransac(&p1, &p2, &uv1, &uv2, &geo.intr, &geo.intr, &params)?;
    // p_kf = s·R·p_query + t: with the query camera's lengths times s, `[R | t]` is the query
    // camera in the keyframe's frame.
    let t_kq = s21.to_isometry();
    Some(t_kq.inverse() * kf.pose_cw)
}

/// The query's own map point at keypoint `qi`, if it has one.
fn own_point<'m>(
    own: &'m Map,
    own_points: &[Option<PointId>],
    qi: usize,
) -> Option<&'m crate::map::MapPoint> {
    own.points.get(&own_points.get(qi).copied().flatten()?)
}

/// Monocular: lengths in the matched map per length in the query's map, the median ratio of
/// the distances of the refined inliers' points from the camera in the two maps.
fn map_scale(
    q: &Query,
    own: &Map,
    own_points: &[Option<PointId>],
    map: &Map,
    pose: &Isometry3<f64>,
    matches: &[Option<PointId>],
) -> Option<f64> {
    let mut ratios: Vec<f64> = matches
        .iter()
        .enumerate()
        .filter_map(|(qi, pm)| {
            let xm = map.points.get(&(*pm)?)?;
            let xq = own_point(own, own_points, qi)?;
            let dm = (pose * Point3::from(xm.position)).coords.norm();
            let dq = (q.pose * Point3::from(xq.position)).coords.norm();
            (dq > 0.0 && dm > 0.0).then(|| dm / dq)
        })
        .collect();
    if ratios.len() < SCALE_MIN_PAIRS {
        return None;
    }
    ratios.sort_by(f64::total_cmp);
    Some(ratios[ratios.len() / 2])
}

/// Initial pose of the query in the matched map: 3-D–3-D RANSAC when the query has depth
/// for enough of the pairs, PnP RANSAC otherwise.
fn ransac_pose(
    cfg: &LoopClosingConfig,
    geo: &ImageGeometry,
    m: &Measurement,
    map: &Map,
    pairs: &[(usize, PointId)],
) -> Option<Isometry3<f64>> {
    let with_depth: Vec<&(usize, PointId)> =
        pairs.iter().filter(|(qi, _)| m.depth[*qi] > 0.0).collect();
    if with_depth.len() >= cfg.min_validation_matches as usize {
        let src: Vec<Vector3<f64>> = with_depth
            .iter()
            .map(|(qi, _)| backproject(&geo.intr, &m.keypoints[*qi].un, m.depth[*qi] as f64))
            .collect();
        let dst: Vec<Vector3<f64>> = with_depth
            .iter()
            .map(|(_, p)| map.points[p].position)
            .collect();
        // Threshold grows with depth like the sensor's noise (σ ≈ 1.4 mm · z²) plus keypoint
        // error; 5 cm at 2 m is generous enough for real data and far below aliasing errors.
        let a = rigid_ransac(
            &src,
            &dst,
            0.05,
            (cfg.min_inliers as usize / 2).max(6),
            300,
            17,
        )?;
        // `a.pose` maps query-camera points into the matched map's world: T_wc.
        return Some(a.pose.inverse());
    }
    let pts: Vec<Vector3<f64>> = pairs.iter().map(|(_, p)| map.points[p].position).collect();
    let uv: Vec<Vector2<f64>> = pairs.iter().map(|(qi, _)| m.keypoints[*qi].un).collect();
    pnp_ransac(
        &pts,
        &uv,
        &geo.intr,
        4.0,
        (cfg.min_inliers as usize / 2).max(6),
    )
    .ok()
    .flatten()
    .map(|a| a.pose)
}

fn observations(
    m: &Measurement,
    map: &Map,
    matches: &[Option<PointId>],
) -> (Vec<usize>, Vec<PoseObservation>) {
    let idx: Vec<usize> = (0..m.len())
        .filter(|&i| matches[i].is_some_and(|p| map.points.contains_key(&p)))
        .collect();
    let obs = idx
        .iter()
        .map(|&i| {
            let kp = &m.keypoints[i];
            let d = m.depth[i] as f64;
            PoseObservation {
                point_w: map.points[&matches[i].expect("filtered")].position,
                obs: if d > 0.0 {
                    Observation::Rgbd {
                        uv: kp.un,
                        depth: d,
                    }
                } else {
                    Observation::Mono { uv: kp.un }
                },
                info: octave_information(kp.octave as u32),
                shutter: Isometry3::identity(),
            }
        })
        .collect();
    (idx, obs)
}

/// Robust pose-only refinement; returns the pose and an inlier flag per query keypoint.
fn refine(
    geo: &ImageGeometry,
    m: &Measurement,
    map: &Map,
    init: &Isometry3<f64>,
    matches: &[Option<PointId>],
) -> (Isometry3<f64>, Vec<bool>) {
    let (idx, obs) = observations(m, map, matches);
    let r = refine_pose(init, &obs, &geo.intr, &PoseParams::default());
    let mut inl = vec![false; m.len()];
    for (k, &i) in idx.iter().enumerate() {
        inl[i] = r.inliers[k];
    }
    (r.pose, inl)
}

/// Projects the points of keyframes `local` with `pose` and matches them to free query
/// keypoints near their projection (ORB distance ≤ 50 and Lowe's ratio). Returns how many
/// matches were added.
fn search_local_map(
    geo: &ImageGeometry,
    m: &Measurement,
    map: &Map,
    local: &[KfId],
    pose: &Isometry3<f64>,
    radius: f64,
    matches: &mut [Option<PointId>],
) -> usize {
    let mut cands: BTreeSet<PointId> = BTreeSet::new();
    for k in local {
        if let Some(kf) = map.keyframes.get(k) {
            cands.extend(kf.points.iter().flatten().copied());
        }
    }
    let used: BTreeSet<PointId> = matches.iter().flatten().copied().collect();
    let mut best: Vec<u32> = vec![u32::MAX; m.len()];
    let mut added = 0;
    for pid in cands {
        if used.contains(&pid) {
            continue;
        }
        let Some(p) = map.points.get(&pid) else {
            continue;
        };
        let pc = pose * Point3::from(p.position);
        let Some(uv) = geo.project_in_image(&pc.coords) else {
            continue;
        };
        let dist = pc.coords.norm();
        if dist < 0.8 * p.min_distance || dist > 1.2 * p.max_distance {
            continue;
        }
        let level = geo.predicted_level(p.max_distance, dist);
        let r = radius * geo.scales[level];
        let lo = level.saturating_sub(1) as u8;
        let hi = (level + 1).min(geo.n_levels as usize - 1) as u8;
        let (mut b1, mut b2, mut bi) = (u32::MAX, u32::MAX, usize::MAX);
        for i in m.grid.in_area(&m.keypoints, uv.x, uv.y, r, lo, hi) {
            if matches[i].is_some() && best[i] == u32::MAX {
                continue;
            }
            let h = hamming(&p.descriptor, &m.descriptors[i]);
            if h < b1 {
                (b2, b1, bi) = (b1, h, i);
            } else if h < b2 {
                b2 = h;
            }
        }
        if bi == usize::MAX || b1 > 50 || (b2 != u32::MAX && b1 as f64 > 0.8 * b2 as f64) {
            continue;
        }
        if b1 < best[bi] {
            if best[bi] == u32::MAX {
                added += 1;
            }
            best[bi] = b1;
            matches[bi] = Some(pid);
        }
    }
    added
}

/// Gauss–Newton information of the refined pose from its inlier observations, scaled by the
/// measured residual variance (a χ² per degree of freedom above 1 means the keypoint noise is
/// larger than the pyramid model says).
pub fn pose_information(
    geo: &ImageGeometry,
    m: &Measurement,
    map: &Map,
    pose: &Isometry3<f64>,
    matches: &[Option<PointId>],
) -> Matrix6<f64> {
    information_of(geo, pose, &observations(m, map, matches).1)
}

/// Gauss–Newton information of `pose` (left perturbation) from `observations`, scaled by the
/// measured residual variance (see [`pose_information`]).
fn information_of(
    geo: &ImageGeometry,
    pose: &Isometry3<f64>,
    observations: &[PoseObservation],
) -> Matrix6<f64> {
    let mut h = Matrix6::zeros();
    let (mut chi2, mut dof) = (0.0, 0usize);
    for o in observations {
        let Some(lin) = o.obs.linearize(&geo.intr, pose, &o.point_w) else {
            continue;
        };
        h += lin.jac_pose.transpose() * lin.jac_pose * o.info;
        chi2 += o.info * lin.residual.norm_squared();
        dof += o.obs.dim();
    }
    let variance = if dof > 6 {
        (chi2 / (dof - 6) as f64).max(1.0)
    } else {
        1.0
    };
    h / variance
}

/// A closure pool that reached consensus.
#[derive(Debug, Clone)]
pub struct Accepted {
    pub query_map: u32,
    pub match_map: u32,
    /// Query-map world → matched-map world (for a loop inside one map: the drift correction;
    /// a similarity in monocular mode).
    pub alignment: Sim3,
    /// The agreeing candidates, oldest first.
    pub members: Vec<Valid>,
}

/// The delayed decision over valid candidates.
#[derive(Debug, Clone, Default)]
pub struct Pool {
    recent: VecDeque<Valid>,
    /// Alignments of pools that were rolled back or refused, per (query map, match map).
    refused: Vec<(u32, u32, Sim3)>,
}

/// Largest scale difference (log) between the alignments of one pool's candidates (monocular).
pub const POOL_MAX_LOG_SCALE: f64 = 0.1;

/// Tolerances of "the same alignment".
pub struct Agreement {
    pub max_translation_m: f64,
    pub max_rotation_deg: f64,
}

impl Agreement {
    pub fn from_config(cfg: &LoopClosingConfig) -> Self {
        Self {
            max_translation_m: cfg.pool_max_translation_m,
            max_rotation_deg: cfg.pool_max_rotation_deg,
        }
    }

    /// The tolerances of "the same alignment as a refused one" (see [`Pool::is_refused`]).
    pub fn refusal_from_config(cfg: &LoopClosingConfig) -> Self {
        Self {
            max_translation_m: cfg.refused_max_translation_m,
            max_rotation_deg: cfg.refused_max_rotation_deg,
        }
    }

    /// Same rotation and translation within the tolerances, and (monocular) the same scale
    /// within [`POOL_MAX_LOG_SCALE`].
    pub fn agree(&self, a: &Sim3, b: &Sim3) -> bool {
        let d = a.inverse().compose(b);
        let angle = nalgebra::UnitQuaternion::from_rotation_matrix(&d.rotation).angle();
        d.translation.norm() <= self.max_translation_m
            && angle.to_degrees() <= self.max_rotation_deg
            && d.scale.ln().abs() <= POOL_MAX_LOG_SCALE
    }
}

impl Pool {
    /// Forgets pending candidates (e.g. when the query map changes).
    pub fn clear(&mut self) {
        self.recent.clear();
    }

    pub fn pending(&self) -> usize {
        self.recent.len()
    }

    /// The newest candidate of `query_map` still pending at frame `frame` (within `window`
    /// frames of it): the pool's open hypothesis, its matched keyframe and alignment, which
    /// the next frames can check by projection ([`validate_from_prior`]).
    pub fn open_hypothesis(
        &self,
        query_map: u32,
        frame: usize,
        window: usize,
    ) -> Option<(KfId, Sim3)> {
        self.recent
            .iter()
            .rev()
            .find(|o| {
                o.query_map == query_map && !o.own_points && frame.saturating_sub(o.frame) <= window
            })
            .map(|o| (o.matched, o.alignment()))
    }

    /// Whether `v` agrees, within `agreement` (the refusal tolerances, wider than a pool's),
    /// with an alignment that was rolled back or refused before.
    pub fn is_refused(&self, v: &Valid, agreement: &Agreement) -> bool {
        let a = v.alignment();
        self.refused
            .iter()
            .any(|(qm, mm, r)| *qm == v.query_map && *mm == v.match_map && agreement.agree(r, &a))
    }

    /// Remembers a rolled-back alignment so that the same wrong closure is not accepted again.
    pub fn refuse(&mut self, query_map: u32, match_map: u32, alignment: Sim3) {
        self.refused.push((query_map, match_map, alignment));
    }

    /// Adds a valid candidate of frame `frame`; candidates older than `window` frames leave
    /// the pool. Returns the accepted pool when `pool_size` candidates of different frames
    /// agree with the newest one.
    pub fn offer(
        &mut self,
        v: Valid,
        window: usize,
        pool_size: usize,
        agreement: &Agreement,
    ) -> Option<Accepted> {
        let frame = v.frame;
        self.recent
            .retain(|o| frame.saturating_sub(o.frame) <= window && o.query_map == v.query_map);
        let a = v.alignment();
        self.recent.push_back(v);
        let last = self.recent.back().expect("just pushed");
        // Evidence of one kind only: a reversed validation (`own_points`, a few times less
        // precise) does not complete a pool of the validator's usual ones, nor they its.
        let agreeing: Vec<&Valid> = self
            .recent
            .iter()
            .filter(|o| o.match_map == last.match_map && o.own_points == last.own_points)
            .filter(|o| agreement.agree(&o.alignment(), &a))
            .collect();
        let frames: BTreeSet<usize> = agreeing.iter().map(|o| o.frame).collect();
        if frames.len() < pool_size {
            return None;
        }
        // One member per frame (the one with most inliers), oldest first.
        let mut per_frame: BTreeMap<usize, Valid> = BTreeMap::new();
        for o in agreeing {
            let keep = per_frame
                .get(&o.frame)
                .is_none_or(|e| o.n_inliers > e.n_inliers);
            if keep {
                per_frame.insert(o.frame, o.clone());
            }
        }
        let members: Vec<Valid> = per_frame.into_values().collect();
        let last = members.last().expect("pool_size >= 1");
        let accepted = Accepted {
            query_map: last.query_map,
            match_map: last.match_map,
            alignment: last.alignment(),
            members,
        };
        self.recent.clear();
        Some(accepted)
    }
}

/// Relative pose between two poses as the pose graph measures it: pose of `b` in the frame
/// of `a`, both world-to-camera.
pub fn relative(a: &Isometry3<f64>, b: &Isometry3<f64>) -> Isometry3<f64> {
    a * b.inverse()
}

/// The information of a relative pose measurement `a·b⁻¹` when only `b` is uncertain with
/// information `info_b` (left perturbation): `a·(exp(δ)b)⁻¹ = a·b⁻¹·exp(−δ)` — the right
/// perturbation of the relative pose, so the information moves by the adjoint of `a·b⁻¹`.
pub fn relative_information(rel: &Isometry3<f64>, info_b: &Matrix6<f64>) -> Matrix6<f64> {
    let ad = se3::adjoint(rel);
    match ad.try_inverse() {
        Some(inv) => inv.transpose() * info_b * inv,
        None => *info_b,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn valid(frame: usize, alignment: Isometry3<f64>) -> Valid {
        // query_pose = identity → alignment = pose_in_match⁻¹.
        Valid {
            frame,
            t: frame as f64,
            query_map: 1,
            match_map: 0,
            matched: 3,
            query_kf: None,
            reference_kf: None,
            query_pose: Isometry3::identity(),
            pose_in_match: alignment.inverse(),
            scale: 1.0,
            matches: vec![],
            own_points: false,
            n_inliers: 50,
            information: Matrix6::identity(),
        }
    }

    fn agreement() -> Agreement {
        Agreement {
            max_translation_m: 0.1,
            max_rotation_deg: 3.0,
        }
    }

    #[test]
    fn pool_needs_agreeing_candidates_of_distinct_frames() {
        let mut pool = Pool::default();
        let a = Isometry3::new(Vector3::new(1.0, 2.0, 0.0), Vector3::new(0.0, 0.0, 0.5));
        let b = Isometry3::new(Vector3::new(-3.0, 0.0, 0.0), Vector3::new(0.0, 0.0, -1.0));
        assert!(pool.offer(valid(10, a), 30, 3, &agreement()).is_none());
        assert!(
            pool.offer(valid(10, a), 30, 3, &agreement()).is_none(),
            "same frame"
        );
        assert!(
            pool.offer(valid(11, b), 30, 3, &agreement()).is_none(),
            "disagrees"
        );
        let acc = pool.offer(valid(12, a), 30, 3, &agreement());
        assert!(acc.is_none(), "only two frames agree");
        let acc = pool
            .offer(valid(13, a), 30, 3, &agreement())
            .expect("three agree");
        assert_eq!(acc.members.len(), 3);
        assert!(agreement().agree(&acc.alignment, &Sim3::from_isometry(&a)));
        assert_eq!(pool.pending(), 0);
    }

    /// Small `aliasing` 2×5 s with `lost_place_from_query_depth`: a reversed validation (56
    /// inliers, loose) and two of the validator's usual ones agreed, the pool completed a frame
    /// earlier on the mixed evidence, and room B's map was later merged into room A's (3 wrong).
    /// A pool is of one kind of evidence.
    #[test]
    fn a_pool_does_not_mix_reversed_and_usual_validations() {
        let mut pool = Pool::default();
        let a = Isometry3::new(Vector3::new(1.0, 2.0, 0.0), Vector3::new(0.0, 0.0, 0.5));
        let reversed = |f| Valid {
            own_points: true,
            ..valid(f, a)
        };
        assert!(pool.offer(reversed(10), 30, 3, &agreement()).is_none());
        assert!(pool.offer(valid(11, a), 30, 3, &agreement()).is_none());
        assert!(
            pool.offer(valid(12, a), 30, 3, &agreement()).is_none(),
            "two usual and one reversed"
        );
        let acc = pool
            .offer(valid(13, a), 30, 3, &agreement())
            .expect("three usual ones");
        assert!(acc.members.iter().all(|m| !m.own_points));
        assert!(pool.offer(reversed(20), 30, 3, &agreement()).is_none());
        assert!(pool.offer(reversed(21), 30, 3, &agreement()).is_none());
        let acc = pool
            .offer(reversed(22), 30, 3, &agreement())
            .expect("three reversed ones");
        assert!(acc.members.iter().all(|m| m.own_points));
    }

    #[test]
    fn old_candidates_leave_the_window_and_refused_alignments_stay_refused() {
        let mut pool = Pool::default();
        let a = Isometry3::new(Vector3::new(1.0, 0.0, 0.0), Vector3::zeros());
        assert!(pool.offer(valid(0, a), 5, 2, &agreement()).is_none());
        assert!(
            pool.offer(valid(20, a), 5, 2, &agreement()).is_none(),
            "frame 0 expired"
        );
        pool.refuse(1, 0, Sim3::from_isometry(&a));
        let near = Isometry3::new(Vector3::new(1.05, 0.0, 0.0), Vector3::zeros());
        assert!(pool.is_refused(&valid(21, near), &agreement()));
        let far = Isometry3::new(Vector3::new(3.0, 0.0, 0.0), Vector3::zeros());
        assert!(!pool.is_refused(&valid(22, far), &agreement()));
    }

    /// The same wrong hypothesis anchored on another keyframe of a bent map (small `aliasing`
    /// 3×2 s: 13 cm and 3.1° from the refused one) is refused, though it would not join the
    /// refused pool; a different hypothesis (a correct merge 0.75 m away) is not.
    #[test]
    fn refusal_covers_the_same_hypothesis_on_other_keyframes() {
        let cfg = crate::config::LoopClosingConfig::default();
        let (pool_tol, refusal) = (
            Agreement::from_config(&cfg),
            Agreement::refusal_from_config(&cfg),
        );
        let mut pool = Pool::default();
        pool.refuse(1, 0, Sim3::from_isometry(&Isometry3::identity()));
        let rot = |deg: f64| Vector3::new(0.0, deg.to_radians(), 0.0);
        let same = Isometry3::new(Vector3::new(0.13, 0.0, 0.0), rot(3.1));
        assert!(pool.is_refused(&valid(30, same), &refusal));
        assert!(!pool.is_refused(&valid(30, same), &pool_tol));
        let other = Isometry3::new(Vector3::new(0.75, 0.0, 0.0), rot(3.6));
        assert!(!pool.is_refused(&valid(31, other), &refusal));
    }

    #[test]
    fn monocular_alignment_carries_the_scale_and_pools_agree_on_it() {
        // The query camera sees a point at distance 1 in its map; the matched map measures 2.
        let query_pose = Isometry3::new(Vector3::new(0.3, -0.1, 0.2), Vector3::new(0.1, 0.2, 0.0));
        let pose_in_match =
            Isometry3::new(Vector3::new(1.0, 0.5, 0.0), Vector3::new(0.0, 0.3, 0.1));
        let mut v = valid(5, Isometry3::identity());
        v.query_pose = query_pose;
        v.pose_in_match = pose_in_match;
        v.scale = 2.0;
        let a = v.alignment();
        assert!((a.scale - 2.0).abs() < 1e-12);
        // A query-map point maps to where the matched map's camera sees it, twice as far.
        let x = Vector3::new(0.2, 0.1, 1.5);
        let in_query_cam = (query_pose * Point3::from(x)).coords;
        let in_match_cam = (pose_in_match * Point3::from(a.transform_point(&x))).coords;
        assert!((in_match_cam - 2.0 * in_query_cam).norm() < 1e-9);
        let mut w = v.clone();
        w.scale = 2.1;
        assert!(agreement().agree(&a, &w.alignment()), "5 % apart");
        w.scale = 2.5;
        assert!(!agreement().agree(&a, &w.alignment()), "25 % apart");
    }

    #[test]
    fn relative_information_is_invariant_for_identity() {
        let info = Matrix6::from_diagonal(&nalgebra::Vector6::new(1.0, 2.0, 3.0, 4.0, 5.0, 6.0));
        let r = relative_information(&Isometry3::identity(), &info);
        assert!((r - info).norm() < 1e-12);
    }

    /// A view of `n` keypoints with the given descriptors (all with depth 2 m).
    fn view(frame: usize, descriptors: Vec<[u8; 32]>) -> Measurement {
        let uvs: Vec<_> = (0..descriptors.len())
            .map(|i| nalgebra::Vector2::new(20.0 + 6.0 * i as f64, 240.0))
            .collect();
        Measurement::synthetic(frame, uvs, 30.0, 2.0, descriptors)
    }

    #[test]
    fn descriptor_search_finds_matches_beyond_the_detector_threshold() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let n = 80;
        let stored: Vec<[u8; 32]> = (0..n).map(|_| rng.random()).collect();
        // The same places from another viewpoint: 35 of 256 bits changed (the detector's
        // index keeps only matches within 25), in reverse order.
        let mut seen: Vec<[u8; 32]> = stored
            .iter()
            .map(|d| {
                let mut d = *d;
                for b in rand::seq::index::sample(&mut rng, 256, 35) {
                    d[b / 8] ^= 1 << (b % 8);
                }
                d
            })
            .collect();
        seen.reverse();
        let mut map = Map::new(0);
        let kf = map.add_keyframe(&view(0, stored), Isometry3::identity());
        let ids: Vec<PointId> = (0..n)
            .map(|i| map.add_point(kf, i, Vector3::new(i as f64 * 0.01, 0.0, 2.0), 1.2, 8))
            .collect();
        let q = view(1, seen);
        let pairs = search_keyframe_points(&q, &map.keyframes[&kf], &map);
        assert_eq!(pairs.len(), n, "{pairs:?}");
        for (qi, p) in pairs {
            assert_eq!(p, ids[n - 1 - qi], "query keypoint {qi}");
        }
        // Unrelated descriptors (about 128 bits away) give nothing.
        let other: Vec<[u8; 32]> = (0..n).map(|_| rng.random()).collect();
        assert!(search_keyframe_points(&view(2, other), &map.keyframes[&kf], &map).is_empty());
    }

    /// A monocular view of world points `xs` from `pose_cw` (depth suppressed), one random
    /// descriptor per point; points outside the image keep a keypoint at the centre (they are
    /// not used).
    fn mono_view(
        frame: usize,
        geo: &ImageGeometry,
        pose_cw: &Isometry3<f64>,
        xs: &[Vector3<f64>],
        descriptors: &[[u8; 32]],
    ) -> Measurement {
        let uvs: Vec<_> = xs
            .iter()
            .map(|x| {
                let pc = pose_cw * Point3::from(*x);
                geo.project_in_image(&pc.coords)
                    .unwrap_or(nalgebra::Vector2::new(320.0, 240.0))
            })
            .collect();
        Measurement::synthetic(frame, uvs, 30.0, 0.0, descriptors.to_vec())
    }

    /// A monocular query: `n` points seen by a camera 20 cm and a few degrees from the matched
    /// map's origin, in the query's own map at half the matched map's scale and in another
    /// world frame (`a`: query world → matched world, scale 2).
    struct MonoQuery {
        geo: ImageGeometry,
        xs: Vec<Vector3<f64>>,
        descriptors: Vec<[u8; 32]>,
        a: Sim3,
        cam_in_match: Isometry3<f64>,
        m: Measurement,
        own: Map,
        own_points: Vec<Option<PointId>>,
        pose: Isometry3<f64>,
        own_kf: KfId,
    }

    fn mono_query(n: usize) -> MonoQuery {
        use crate::optim::Intrinsics;
        use rand::{Rng, SeedableRng};
        let geo = ImageGeometry::new(Intrinsics::TUM_FREIBURG1, 640, 480, 1.2, 8);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let xs: Vec<Vector3<f64>> = (0..n)
            .map(|_| {
                Vector3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-0.8..0.8),
                    rng.random_range(2.0..4.0),
                )
            })
            .collect();
        let descriptors: Vec<[u8; 32]> = (0..n).map(|_| rng.random()).collect();
        let a = Sim3 {
            rotation: nalgebra::Rotation3::new(Vector3::new(0.1, -0.4, 0.2)),
            translation: Vector3::new(1.0, -2.0, 0.5),
            scale: 2.0,
        };
        let cam_in_match =
            Isometry3::new(Vector3::new(0.2, 0.05, -0.1), Vector3::new(0.02, 0.08, 0.0));
        let m = mono_view(9, &geo, &cam_in_match, &xs, &descriptors);
        // Its pose in its own map: `S(1/2) ∘ T ∘ a` is rigid.
        let half = Sim3 {
            scale: 0.5,
            ..Sim3::identity()
        };
        let pose = half
            .compose(&Sim3::from_isometry(&cam_in_match))
            .compose(&a)
            .to_isometry();
        let mut own = Map::new(1);
        let own_kf = own.add_keyframe(&m, pose);
        let own_points: Vec<Option<PointId>> = (0..n)
            .map(|i| Some(own.add_point(own_kf, i, a.inverse().transform_point(&xs[i]), 1.2, 8)))
            .collect();
        MonoQuery {
            geo,
            xs,
            descriptors,
            a,
            cam_in_match,
            m,
            own,
            own_points,
            pose,
            own_kf,
        }
    }

    impl MonoQuery {
        fn query(&self) -> Query<'_> {
            Query {
                m: &self.m,
                map: 1,
                pose: self.pose,
                kf: None,
                reference_kf: Some(self.own_kf),
                own: Some((&self.own, &self.own_points)),
            }
        }
    }

    #[test]
    fn monocular_validation_measures_the_scale_between_two_maps() {
        let n = 150;
        let mq = mono_query(n);
        let (geo, xs, a, cam_in_match) = (&mq.geo, &mq.xs, &mq.a, mq.cam_in_match);
        let in_query = |x: &Vector3<f64>| a.inverse().transform_point(x);
        // The matched map: a keyframe at its origin observing every point.
        let mut matched = Map::new(0);
        let kf_pose = Isometry3::identity();
        let kf = matched.add_keyframe(&mono_view(0, geo, &kf_pose, xs, &mq.descriptors), kf_pose);
        let pm: Vec<PointId> = (0..n)
            .map(|i| matched.add_point(kf, i, xs[i], 1.2, 8))
            .collect();
        let (own, own_points, geo) = (&mq.own, &mq.own_points, geo);
        let c = Candidate {
            image: kf as u64,
            score: 1.0,
            matches: (0..n as u32).map(|i| (i, i)).collect(),
        };
        let q = mq.query();
        let cfg = LoopClosingConfig::default();
        // The Sim3 RANSAC alone already places the query camera in the matched map.
        let pairs: Vec<(usize, PointId)> = (0..n).map(|i| (i, pm[i])).collect();
        let initial = sim3_pose(
            &cfg,
            geo,
            &q,
            own,
            own_points,
            &matched,
            &matched.keyframes[&kf],
            &pairs,
        )
        .expect("Sim3 RANSAC");
        let d = initial.inverse() * cam_in_match;
        assert!(
            d.translation.vector.norm() < 1e-6 && d.rotation.angle() < 1e-6,
            "{d}"
        );
        let Verdict::Valid(v) = validate(&cfg, geo, &q, &matched, &c) else {
            panic!("the similarity is not found");
        };
        assert!((v.scale - 2.0).abs() < 1e-3, "scale {}", v.scale);
        let found = v.alignment();
        for x in xs.iter().take(10) {
            let y = found.transform_point(&in_query(x));
            assert!((y - x).norm() < 1e-3, "{y} vs {x}");
        }
        assert!(v.matches.iter().flatten().all(|p| pm.contains(p)));
        // Without the query's map points there is no scale: a rigid alignment.
        let rigid = Query { own: None, ..q };
        let Verdict::Valid(v) = validate(&cfg, geo, &rigid, &matched, &c) else {
            panic!("PnP finds the pose");
        };
        assert_eq!(v.scale, 1.0);
    }

    /// Without depth, the last keyframe before a loss holds few points (none of its successors
    /// triangulated with it): a candidate there is validated on the points of its covisible
    /// window, which saw the same place.
    #[test]
    fn a_monocular_candidate_is_searched_with_its_covisible_window() {
        let n = 150;
        let mq = mono_query(n);
        let cfg = LoopClosingConfig::default();
        let few = cfg.min_validation_matches as usize - 1;
        let validated = |linked: bool| {
            let mut matched = Map::new(0);
            let pose = Isometry3::identity();
            let view = mono_view(0, &mq.geo, &pose, &mq.xs, &mq.descriptors);
            let neighbour = matched.add_keyframe(&view, pose);
            let last = matched.add_keyframe(&view, pose);
            for i in 0..n {
                let p = matched.add_point(neighbour, i, mq.xs[i], 1.2, 8);
                if i < few {
                    matched.observe(last, i, p);
                }
            }
            if linked {
                matched.update_covisibility(last);
            }
            // The detector proposes the last keyframe, with no correspondences of its own.
            let c = Candidate {
                image: last as u64,
                score: 1.0,
                matches: Vec::new(),
            };
            validate(&cfg, &mq.geo, &mq.query(), &matched, &c)
        };
        let Verdict::Valid(v) = validated(true) else {
            panic!("the window's points place the query");
        };
        assert!((v.scale - 2.0).abs() < 1e-3, "scale {}", v.scale);
        assert!(v.n_inliers > few, "{} inliers", v.n_inliers);
        // The keyframe's own points alone are too few.
        assert!(
            matches!(validated(false), Verdict::Rejected { .. }),
            "without the window"
        );
    }

    /// A pending hypothesis is checked again by projection: from the alignment of the pool's
    /// pending candidate, the next frame's points are found where the prior puts them, and the
    /// pose and scale come out refined. A prior a few decimetres and degrees wrong (another
    /// place) projects the points where the image shows other things: rejected.
    #[test]
    fn a_pending_hypothesis_is_checked_by_projection_and_a_wrong_one_finds_nothing() {
        let n = 150;
        let mq = mono_query(n);
        let mut matched = Map::new(0);
        let kf_pose = Isometry3::identity();
        let kf = matched.add_keyframe(
            &mono_view(0, &mq.geo, &kf_pose, &mq.xs, &mq.descriptors),
            kf_pose,
        );
        for i in 0..n {
            matched.add_point(kf, i, mq.xs[i], 1.2, 8);
        }
        let cfg = LoopClosingConfig::default();
        let q = mq.query();
        // The prior of a pending candidate whose alignment was off by a few millimetres.
        let nudge = Sim3::from_isometry(&Isometry3::new(
            Vector3::new(0.004, -0.003, 0.002),
            Vector3::new(0.002, 0.0, -0.001),
        ));
        let prior = nudge.compose(&mq.a).transform_pose_cw(&mq.pose);
        let Verdict::Valid(v) = validate_from_prior(&cfg, &mq.geo, &q, &matched, kf, &prior) else {
            panic!("the prior's projections find the points");
        };
        let d = v.pose_in_match.inverse() * mq.cam_in_match;
        assert!(
            d.translation.vector.norm() < 1e-3 && d.rotation.angle() < 1e-3,
            "{d}"
        );
        assert!((v.scale - 2.0).abs() < 1e-2, "scale {}", v.scale);
        assert!(v.n_inliers > n / 2, "{} inliers", v.n_inliers);
        // A prior 40 cm and 12° away.
        let off = Sim3::from_isometry(&Isometry3::new(
            Vector3::new(0.4, 0.0, 0.1),
            Vector3::new(0.0, 0.2, 0.0),
        ));
        let wrong = off.compose(&mq.a).transform_pose_cw(&mq.pose);
        assert!(
            matches!(
                validate_from_prior(&cfg, &mq.geo, &q, &matched, kf, &wrong),
                Verdict::Rejected { .. }
            ),
            "a wrong prior"
        );
    }

    /// The pool's open hypothesis is its newest pending candidate of the query map, within
    /// the window; none once the pool was accepted (cleared) or the candidates left the window.
    #[test]
    fn the_open_hypothesis_is_the_newest_pending_candidate_of_the_query_map() {
        let mut pool = Pool::default();
        assert!(pool.open_hypothesis(1, 10, 30).is_none());
        let a = Isometry3::translation(1.0, 0.0, 0.0);
        let b = Isometry3::translation(0.0, 2.0, 0.0);
        pool.offer(valid(10, a), 30, 3, &agreement());
        let mut newer = valid(12, b);
        newer.matched = 7;
        pool.offer(newer, 30, 3, &agreement());
        let (kf, alignment) = pool.open_hypothesis(1, 13, 30).expect("pending");
        assert_eq!(kf, 7);
        assert!(agreement().agree(&alignment, &Sim3::from_isometry(&b)));
        assert!(
            pool.open_hypothesis(2, 13, 30).is_none(),
            "another query map"
        );
        assert!(
            pool.open_hypothesis(1, 43, 30).is_none(),
            "out of the window"
        );
    }

    /// A wall of 300 points seen by a keyframe of the other side (`far`, at the origin) and by
    /// one of the camera's side (`near`, 10 cm to the right), whose merge left it 2 cm and 0.5°
    /// off, with its own copies of the points where that pose put them; and a far keyframe
    /// looking away. Returns the map, near, the far keyframe facing the wall, the one looking
    /// away, and near's true pose.
    fn seam(depth: f32) -> (Map, KfId, KfId, KfId, Isometry3<f64>) {
        use crate::components::preprocess::Descriptor;
        let intr = crate::optim::Intrinsics::TUM_FREIBURG1;
        let uvs: Vec<Vector2<f64>> = (0..15)
            .flat_map(|j| {
                (0..20).map(move |i| Vector2::new(16.0 + 32.0 * i as f64, 16.0 + 32.0 * j as f64))
            })
            .collect();
        let wall: Vec<Vector3<f64>> = uvs
            .iter()
            .map(|uv| {
                Vector3::new(
                    (uv.x - intr.cx) * 2.0 / intr.fx,
                    (uv.y - intr.cy) * 2.0 / intr.fy,
                    2.0,
                )
            })
            .collect();
        // One distinct descriptor per wall point (a linear congruential sequence).
        let mut x: u64 = 12345;
        let descriptors: Vec<Descriptor> = (0..wall.len())
            .map(|_| {
                let mut d = [0u8; 32];
                for b in d.iter_mut() {
                    x = x
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    *b = (x >> 56) as u8;
                }
                d
            })
            .collect();
        let mut map = Map::new(0);
        let far = map.add_keyframe(
            &Measurement::synthetic(0, uvs.clone(), 0.0, depth, descriptors.clone()),
            Isometry3::identity(),
        );
        for (i, p) in wall.iter().enumerate() {
            map.add_point(far, i, *p, 1.2, 8);
        }
        let away = map.add_keyframe(
            &Measurement::synthetic(1, uvs.clone(), 0.0, depth, descriptors.clone()),
            Isometry3::rotation(Vector3::y() * 90f64.to_radians()),
        );
        let truth = Isometry3::translation(-0.1, 0.0, 0.0);
        let (mut near_uvs, mut near_desc, mut near_wall) = (Vec::new(), Vec::new(), Vec::new());
        for (p, d) in wall.iter().zip(&descriptors) {
            let c = truth * Point3::from(*p);
            let uv = Vector2::new(intr.fx * c.x / c.z + intr.cx, intr.fy * c.y / c.z + intr.cy);
            if uv.x >= 0.0 && uv.x < 640.0 {
                near_uvs.push(uv);
                near_desc.push(*d);
                near_wall.push(c.coords);
            }
        }
        let estimate = Isometry3::new(
            Vector3::new(0.02, 0.0, 0.0),
            Vector3::y() * 0.5f64.to_radians(),
        ) * truth;
        let near = map.add_keyframe(
            &Measurement::synthetic(2, near_uvs, 0.0, depth, near_desc),
            estimate,
        );
        for (i, c) in near_wall.iter().enumerate() {
            map.add_point(near, i, estimate.inverse() * c, 1.2, 8);
        }
        (map, near, far, away, truth)
    }

    /// Across a merge's seam, the keyframe of the camera's side is paired with the other
    /// side's keyframe that saw its scene (not one looking away, not one beyond half the
    /// scene's depth), and the pair's validation finds where it really is: the error the merge
    /// left (2 cm, 0.5°) is what the pose graph then corrects. With and without depth.
    #[test]
    fn a_seam_pair_is_found_where_both_sides_saw_one_wall_and_validated_to_the_truth() {
        let geo = ImageGeometry::new(crate::optim::Intrinsics::TUM_FREIBURG1, 640, 480, 1.2, 8);
        let cfg = LoopClosingConfig::default();
        for depth in [2.0, 0.0] {
            let (map, near, far, away, truth) = seam(depth);
            let (n, f) = (BTreeSet::from([near]), BTreeSet::from([far, away]));
            assert_eq!(seam_pairs(&map, &n, &f), vec![(near, far)], "depth {depth}");
            let Verdict::Valid(v) = validate_seam_pair(&cfg, &geo, &map, near, far, &f) else {
                panic!("depth {depth}: the seam pair is not valid");
            };
            let err = v.pose_in_match * truth.inverse();
            assert!(
                err.translation.vector.norm() < 0.002 && err.rotation.angle() < 0.1f64.to_radians(),
                "depth {depth}: off by {err:?}"
            );
            assert!(v.n_inliers >= 250, "depth {depth}: {} inliers", v.n_inliers);
            assert!(
                (v.scale - 1.0).abs() < 0.02,
                "depth {depth}: scale {}",
                v.scale
            );
            // Beyond half the scene's depth (2 m) there is no pair.
            let mut moved = map.clone();
            moved.keyframes.get_mut(&far).unwrap().pose_cw = Isometry3::translation(-1.2, 0.0, 0.0);
            assert!(seam_pairs(&moved, &n, &f).is_empty(), "depth {depth}");
        }
    }
}
