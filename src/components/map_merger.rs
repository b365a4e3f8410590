//! Map merger (paper Table I): tracked frame → augmented local map. Keyframe decision
//! (ORB-SLAM's RGB-D criteria), map points from depth back-projection, point fusion with the
//! covisible keyframes, culling, and local bundle adjustment (optim::local_ba, faer).

use crate::atlas::Atlas;
use crate::components::aligner::backproject;
use crate::components::preprocess::{
    ImageGeometry, Measurement, hamming, rotation_consistent_pairs,
};
use crate::components::tracker::{TrackMethod, TrackResult};
use crate::components::two_view::{k_matrix, projection_matrix, triangulate};
use crate::config::MappingConfig;
use crate::map::{KfId, Map, PointId};
use crate::optim::{
    self, BaCamera, BaObservation, BaParams, BaPoint, BaProblem, Observation, octave_information,
};
use nalgebra::{Isometry3, Matrix3, Point3, Vector2, Vector3};
use std::collections::{BTreeMap, BTreeSet};

/// Monocular keyframe decision: a frame tracking fewer than this share of its reference
/// keyframe's points becomes a keyframe (ORB-SLAM's monocular `thRefRatio`).
const MONO_KEYFRAME_TRACKED_RATIO: f64 = 0.9;
/// Monocular keyframe decision: below this share of the reference keyframe's points the view
/// is leaving the map, and the frame becomes a keyframe whatever its baseline, unless the last
/// keyframe triangulated nothing (then `MONO_MIN_BASELINE`).
const MONO_KEYFRAME_LOST_RATIO: f64 = 0.5;
/// Monocular keyframe decision: least baseline to the reference keyframe, per unit of its
/// median scene depth, before tracking fewer points makes a keyframe: twice the smallest
/// triangulation parallax (`MAX_COS_PARALLAX`, 0.02 rad), so points up to twice the median
/// depth can be triangulated against the reference.
const MONO_KEYFRAME_BASELINE: f64 = 0.04;
/// Monocular: a baseline below this share of the median scene depth triangulates nothing
/// (ORB-SLAM's 1 %, `create_new_points`).
const MONO_MIN_BASELINE: f64 = 0.01;
/// Monocular triangulation: covisible keyframes paired with a new keyframe (ORB-SLAM: 20).
const TRIANGULATION_NEIGHBOURS: usize = 20;
/// RGB-D triangulation: covisible keyframes paired with a new keyframe (ORB-SLAM2: 10).
const TRIANGULATION_NEIGHBOURS_RGBD: usize = 10;
/// Largest Hamming distance of a triangulation match (ORB-SLAM's TH_LOW).
const TRIANGULATION_MAX_DISTANCE: u32 = 50;
/// Best/second-best ratio of a triangulation match. ORB-SLAM restricts the candidates to the
/// same vocabulary node instead; without a vocabulary, the ratio on the epipolar candidates
/// rejects the ambiguous ones.
const TRIANGULATION_RATIO: f64 = 0.8;
/// χ² 95 % quantile, 1 degree of freedom: distance to the epipolar line.
const CHI2_EPIPOLAR: f64 = 3.84;
/// Rays closer than this cosine do not triangulate well (ORB-SLAM: 0.9998, about 1.1°).
const MAX_COS_PARALLAX: f64 = 0.9998;
/// Panoramic keyframes (decision 0030): a keyframe is paired for triangulation with the
/// keyframes (a panoramic one: any keyframe; another: panoramic ones) whose optical axis is
/// within this angle of its own, as the views share part of the image; covisibility cannot
/// tell, since a panoramic keyframe starts without map points. TUM's camera sees 62° × 48°.
const PANORAMIC_MAX_VIEW_ANGLE_DEG: f64 = 40.0;
/// Most keyframes paired with a keyframe by view direction (nearest in angle first).
const PANORAMIC_NEIGHBOURS: usize = 10;

pub struct MapMerger {
    cfg: MappingConfig,
    geo: ImageGeometry,
    last_kf_frame: Option<usize>,
    /// Monocular: the last keyframe triangulated no point (see `need_keyframe`).
    last_kf_barren: bool,
    /// Points created recently, checked by culling: (point, keyframe that created it).
    recent: Vec<(PointId, KfId)>,
    /// Threaded mode: local BA runs on this worker (ORB-SLAM's local-mapping thread) while
    /// tracking goes on; `None` = deterministic mode, BA finishes before the next frame.
    worker: Option<BaWorker>,
    /// Solver times of jobs applied while waiting inside `insert_keyframe`, for `poll`.
    waited_ms: Vec<f64>,
    /// Monocular: points come from triangulation between keyframes instead of depth, and the
    /// keyframe and culling criteria are ORB-SLAM's monocular ones.
    mono: bool,
}

/// A bundle-adjustment problem cut out of a map, with what is needed to write it back.
pub struct BaJob {
    pub map: u32,
    pub keyframe: KfId,
    problem: BaProblem,
    cams: Vec<KfId>,
    pts: Vec<PointId>,
    obs_ref: Vec<(PointId, KfId)>,
    first: BaParams,
    second: BaParams,
}

/// A solved job.
pub struct BaDone {
    job: BaJob,
    report: Option<optim::BaReport>,
    /// Solver time.
    pub ms: f64,
}

impl BaJob {
    fn solve(mut self) -> BaDone {
        let t = std::time::Instant::now();
        let report = match optim::local_ba::solve_with_outlier_rejection(
            &mut self.problem,
            &self.first,
            &self.second,
        ) {
            Ok(r) => Some(r),
            Err(e) => {
                tracing::warn!("bundle adjustment failed ({e}); map left unchanged");
                None
            }
        };
        BaDone {
            job: self,
            report,
            ms: t.elapsed().as_secs_f64() * 1e3,
        }
    }
}

/// The local-mapping thread: solves jobs in order; the tracking thread applies the results.
struct BaWorker {
    jobs: std::sync::mpsc::Sender<BaJob>,
    done: std::sync::mpsc::Receiver<BaDone>,
    pending: usize,
    handle: Option<std::thread::JoinHandle<()>>,
}

impl BaWorker {
    fn spawn() -> Self {
        let (jobs, job_rx) = std::sync::mpsc::channel::<BaJob>();
        let (done_tx, done) = std::sync::mpsc::channel();
        let handle = std::thread::Builder::new()
            .name("local-ba".into())
            .spawn(move || {
                for job in job_rx {
                    if done_tx.send(job.solve()).is_err() {
                        break;
                    }
                }
            })
            .expect("spawning the local BA thread");
        Self {
            jobs,
            done,
            pending: 0,
            handle: Some(handle),
        }
    }
}

impl Drop for BaWorker {
    fn drop(&mut self) {
        // Closing the job channel ends the worker's loop.
        let (tx, _) = std::sync::mpsc::channel();
        drop(std::mem::replace(&mut self.jobs, tx));
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

/// What one keyframe insertion did (for logs and timing).
#[derive(Debug, Clone, Default)]
pub struct MergeReport {
    pub keyframe: KfId,
    pub new_points: usize,
    pub fused: usize,
    pub culled: usize,
    pub ba_initial_cost: f64,
    pub ba_final_cost: f64,
    pub ba_outliers: usize,
}

impl MapMerger {
    pub fn new(cfg: &MappingConfig, geo: ImageGeometry) -> Self {
        Self {
            cfg: cfg.clone(),
            geo,
            last_kf_frame: None,
            last_kf_barren: false,
            recent: Vec::new(),
            worker: None,
            waited_ms: Vec::new(),
            mono: false,
        }
    }

    /// Monocular mode (see `MapMerger::create_new_points`).
    pub fn monocular(mut self, mono: bool) -> Self {
        self.mono = mono;
        self
    }

    /// Threaded mode: local BA on its own thread from now on.
    pub fn set_threaded(&mut self) {
        if self.worker.is_none() {
            self.worker = Some(BaWorker::spawn());
        }
    }

    /// Applies the local BA results that are ready (threaded mode; nothing otherwise). With
    /// `wait`, blocks until every submitted job is back. Returns the solver times.
    pub fn poll(&mut self, atlas: &mut Atlas, wait: bool) -> Vec<f64> {
        let mut times = std::mem::take(&mut self.waited_ms);
        let Some(w) = self.worker.as_mut() else {
            return times;
        };
        while w.pending > 0 {
            let done = if wait {
                w.done.recv().ok()
            } else {
                w.done.try_recv().ok()
            };
            let Some(done) = done else { break };
            w.pending -= 1;
            times.push(done.ms);
            if let Some(map) = atlas.maps.get_mut(&done.job.map) {
                apply_ba(map, &self.geo, &done);
            }
        }
        times
    }

    /// Waits for every pending job and applies those of `map` (others belong to maps the
    /// atlas changed meanwhile and are dropped).
    fn wait_for(&mut self, map: &mut Map) -> Vec<f64> {
        let mut times = Vec::new();
        let Some(w) = self.worker.as_mut() else {
            return times;
        };
        while w.pending > 0 {
            let Ok(done) = w.done.recv() else { break };
            w.pending -= 1;
            times.push(done.ms);
            if done.job.map == map.id {
                apply_ba(map, &self.geo, &done);
            }
        }
        times
    }

    /// A loop in the current map was closed at frame `frame`: no keyframe right away (the
    /// tracker restarts from the matched keyframe), but the recent points stay under culling.
    pub fn closed(&mut self, frame: usize) {
        self.last_kf_frame = Some(frame);
    }

    /// A new map started at keyframe `kf` of frame `frame`.
    pub fn started(&mut self, frame: usize) {
        self.last_kf_frame = Some(frame);
        self.last_kf_barren = false;
        self.recent.clear();
    }

    /// Culling statistics of a tracked frame: its visible points were predicted in view, its
    /// inlier matches were found.
    pub fn note_tracked(&self, map: &mut Map, track: &TrackResult) {
        for pid in &track.visible {
            if let Some(p) = map.points.get_mut(pid) {
                p.visible += 1;
            }
        }
        for pid in track.matches.iter().flatten() {
            if let Some(p) = map.points.get_mut(pid) {
                p.found += 1;
            }
        }
    }

    /// ORB-SLAM's RGB-D keyframe decision: insert when the frame tracks clearly fewer points than
    /// its reference keyframe has well-observed points (observation weight as in culling), or when few close points are tracked while many could be created,
    /// or when too many frames passed. Always requires some tracked points (> 15).
    /// With `with_interval` false only the coverage criteria count (Localized uses that to
    /// tell when the camera leaves the mapped area).
    pub fn need_keyframe(
        &self,
        map: &Map,
        m: &Measurement,
        track: &TrackResult,
        with_interval: bool,
    ) -> bool {
        let Some(ref_kf) = track.reference_kf.and_then(|k| map.keyframes.get(&k)) else {
            return false;
        };
        let min_obs = if map.keyframes.len() <= 2 { 2 } else { 3 };
        let ref_matches = ref_kf
            .points
            .iter()
            .flatten()
            .filter(|p| {
                map.points
                    .get(p)
                    .is_some_and(|p| map.observation_weight(p) >= min_obs)
            })
            .count();
        let close = |i: usize| m.depth[i] > 0.0 && (m.depth[i] as f64) < self.cfg.max_point_depth_m;
        let tracked_close = (0..m.len())
            .filter(|&i| close(i) && track.matches[i].is_some())
            .count();
        let untracked_close = (0..m.len())
            .filter(|&i| close(i) && track.matches[i].is_none())
            .count();
        let need_close = tracked_close < 100 && untracked_close > 70;
        // Monocular: ORB-SLAM's 0.9. Without depth a keyframe is the only way to create
        // points, so keyframes must come often enough for the triangulation to keep up.
        let ratio = if self.mono {
            MONO_KEYFRAME_TRACKED_RATIO
        } else if map.keyframes.len() < 2 {
            0.4
        } else {
            self.cfg.keyframe_tracked_ratio
        };
        let since = if with_interval {
            self.last_kf_frame
                .map_or(usize::MAX, |f| m.frame.saturating_sub(f))
        } else {
            0
        };
        let mut weak = (track.n_inliers as f64) < ratio * ref_matches as f64 || need_close;
        let leaving = (track.n_inliers as f64) < MONO_KEYFRAME_LOST_RATIO * ref_matches as f64;
        if self.mono && weak && (!leaving || self.last_kf_barren) {
            let need = if leaving {
                MONO_MIN_BASELINE
            } else {
                MONO_KEYFRAME_BASELINE
            };
            // A monocular keyframe exists to triangulate points: not before its baseline to
            // the reference keyframe gives the points up to twice the scene's median depth
            // the parallax triangulation needs (ORB-SLAM gets the same spacing from its
            // local-mapping thread being busy; here mapping finishes before the next frame, and
            // a keyframe every frame made a map of 1 %-baseline pairs that drifted by 30 cm on
            // fr1_desk). When the view is leaving the map, a keyframe comes at once: the
            // older keyframes it is paired with may be far enough (on the small `desk`, such
            // keyframes triangulate 8–40 points each and carry tracking through a sparse
            // stretch). But once one of them triangulated nothing, the next needs the least
            // baseline triangulation uses: in a slow turn in place on `turn-in-place`, a
            // keyframe per frame for 24 frames with 0 new points, then a 1938-point fusion
            // and a loop pool accepted 1 m off (decision 0029).
            let center = track.pose_cw.inverse().translation.vector;
            if let Some(median) = map.scene_depth(ref_kf) {
                weak = (center - ref_kf.center()).norm() >= need * median;
            }
        }
        (since >= self.cfg.keyframe_max_interval as usize || weak) && track.n_inliers > 15
    }

    /// Monocular: a rotation-only frame whose view turned away from the tracker's anchor is
    /// kept as a panoramic keyframe ([`Self::insert_panoramic_keyframe`]).
    pub fn need_panoramic_keyframe(&self, track: &TrackResult) -> bool {
        self.mono && track.able_to_track && track.method == TrackMethod::RotationAnchor
    }

    /// Inserts a rotation-only frame as a panoramic keyframe (decision 0030): its key points
    /// are bearings from the turn's centre, without map points. They are triangulated at once
    /// against the keyframes seen from elsewhere that look the same way (another turn's
    /// panoramic keyframes, the walk's keyframes), in the map's scale since both poses are in
    /// the map; what has no partner yet waits for the keyframes of the walk after the turn
    /// ([`Self::create_new_points`] pairs those with panoramic keyframes by view direction).
    /// The keyframe decision's state (last keyframe's frame, barren) is the mapping's own and
    /// stays: a turn adds no baseline.
    pub fn insert_panoramic_keyframe(
        &mut self,
        map: &mut Map,
        m: &Measurement,
        track: &TrackResult,
    ) -> MergeReport {
        let (kf, mut report) = add_tracked_keyframe(map, m, track);
        map.keyframes.get_mut(&kf).expect("just added").panoramic = true;
        report.new_points = self.create_new_points(map, kf);
        map.update_covisibility(kf);
        if report.new_points > 0 {
            report.fused = self.fuse(map, kf);
            map.update_covisibility(kf);
            self.local_ba(map, kf, &mut report);
        }
        report
    }

    /// What a turn's panoramic keyframes `panoramic` hold for the frame `m` where the camera
    /// sets off (decision 0030): key points of `m` matched by descriptor (Lowe's ratio) to key
    /// points of those that look its way (at `pose`; all of them when unposed), key points of
    /// them all that have a map point by now, and how many are still in the map.
    pub fn stored_bearings_seen(
        &self,
        map: &Map,
        panoramic: &[KfId],
        m: &Measurement,
        pose: Option<&Isometry3<f64>>,
    ) -> (usize, usize, usize) {
        let kept: Vec<&crate::map::Keyframe> = panoramic
            .iter()
            .filter_map(|k| map.keyframes.get(k))
            .collect();
        let triangulated = kept.iter().map(|k| k.n_points()).sum();
        let cos_max = PANORAMIC_MAX_VIEW_ANGLE_DEG.to_radians().cos();
        let facing: Vec<&crate::map::Keyframe> = match pose {
            Some(p) => {
                let axis = optical_axis(p);
                kept.iter()
                    .copied()
                    .filter(|k| optical_axis(&k.pose_cw).dot(&axis) >= cos_max)
                    .collect()
            }
            None => kept.clone(),
        };
        // Per keyframe, Lowe's ratio: one place seen by two of them is no ambiguity.
        let seen = |d: &crate::components::preprocess::Descriptor, k: &crate::map::Keyframe| {
            let (mut b1, mut b2) = (u32::MAX, u32::MAX);
            for e in &k.descriptors {
                let h = hamming(d, e);
                if h < b1 {
                    (b2, b1) = (b1, h);
                } else if h < b2 {
                    b2 = h;
                }
            }
            b1 <= TRIANGULATION_MAX_DISTANCE
                && (b2 == u32::MAX || (b1 as f64) < TRIANGULATION_RATIO * b2 as f64)
        };
        let matched = m
            .descriptors
            .iter()
            .filter(|d| facing.iter().any(|k| seen(d, k)))
            .count();
        (matched, triangulated, kept.len())
    }

    /// Inserts the frame as a keyframe and runs local mapping on it.
    pub fn insert_keyframe(
        &mut self,
        map: &mut Map,
        m: &Measurement,
        track: &TrackResult,
    ) -> MergeReport {
        let (kf, mut report) = add_tracked_keyframe(map, m, track);
        for (i, p) in track.matches.iter().enumerate() {
            if let Some(p) = p {
                // A point claimed by two keypoints keeps the first.
                map.observe(kf, i, *p);
            }
        }
        // New points from depth for unmatched keypoints closer than the depth limit, each from
        // the pose of its own image row (rolling shutter).
        for i in 0..m.len() {
            let d = m.depth[i] as f64;
            if d <= 0.0 || d > self.cfg.max_point_depth_m || map.keyframes[&kf].points[i].is_some()
            {
                continue;
            }
            let kp = &m.keypoints[i];
            let pose_wc = (self.geo.shutter(&track.twist, kp.raw.y) * track.pose_cw).inverse();
            let pw = (pose_wc * Point3::from(backproject(&self.geo.intr, &kp.un, d))).coords;
            let id = map.add_point(kf, i, pw, self.geo.scale_factor, self.geo.n_levels);
            self.recent.push((id, kf));
            report.new_points += 1;
        }
        for pid in map.keyframes[&kf]
            .points
            .iter()
            .flatten()
            .copied()
            .collect::<Vec<_>>()
        {
            map.update_point(pid, self.geo.scale_factor, self.geo.n_levels);
        }
        map.update_covisibility(kf);
        report.culled = self.cull(map, kf);
        if self.mono || self.cfg.triangulate_points {
            report.new_points += self.create_new_points(map, kf);
            map.update_covisibility(kf);
        }
        report.fused = self.fuse(map, kf);
        map.update_covisibility(kf);
        self.local_ba(map, kf, &mut report);
        self.last_kf_frame = Some(m.frame);
        self.last_kf_barren = self.mono && report.new_points == 0;
        report
    }

    /// Removes recent points that the following keyframes do not confirm (ORB-SLAM's culling):
    /// found in fewer than a quarter of the frames that should have seen them, or, two
    /// keyframes after their birth, observed by fewer than two keyframes with depth (an
    /// observation with depth counts twice, one without once, as ORB-SLAM's stereo count).
    fn cull(&mut self, map: &mut Map, current: KfId) -> usize {
        let mut culled = 0;
        let mut keep = Vec::new();
        for &(pid, born) in &self.recent {
            let Some(p) = map.points.get(&pid) else {
                continue;
            };
            // Panoramic keyframes are no mapping progress: a point triangulated in a turn
            // waits for the walk after it to be confirmed (decision 0030).
            let panoramic = if born < current {
                map.keyframes
                    .range(born + 1..=current)
                    .filter(|(_, k)| k.panoramic)
                    .count() as KfId
            } else {
                0
            };
            let age = current.saturating_sub(born).saturating_sub(panoramic);
            let weight = map.observation_weight(p);
            let found_ratio = p.found as f64 / p.visible.max(1) as f64;
            // ORB-SLAM: at most 2 observations (monocular) or weight 3 (with depth) is too few.
            let min_weight = if self.mono { 2 } else { 3 };
            if found_ratio < 0.25 || (age >= 2 && weight <= min_weight) {
                map.remove_point(pid);
                culled += 1;
            } else if age < 3 {
                keep.push((pid, born));
            }
        }
        self.recent = keep;
        culled
    }

    /// New map points by triangulating the unmatched keypoints of the new keyframe `kf` with
    /// those of its best covisible keyframes (ORB-SLAM's `CreateNewMapPoints`). Without depth
    /// this is the only source of points; with depth (`mapping.triangulate_points`) it adds
    /// the points the sensor has no depth for. A pair of keypoints is matched by
    /// descriptor among the candidates near the epipolar line, and the point is kept only if
    /// the rays have parallax, it lies in front of both cameras, reprojects within the χ²
    /// gate in both, and its distances to the two cameras agree with the keypoints' pyramid
    /// levels. Returns the number of points created.
    fn create_new_points(&mut self, map: &mut Map, kf: KfId) -> usize {
        let (sf, nl) = (self.geo.scale_factor, self.geo.n_levels);
        let intr = self.geo.intr;
        let n_neighbours = if self.mono {
            TRIANGULATION_NEIGHBOURS
        } else {
            TRIANGULATION_NEIGHBOURS_RGBD
        };
        let mut neighbours = map.keyframes[&kf].best_covisible(n_neighbours);
        if self.mono {
            for n in view_neighbours(map, kf) {
                if !neighbours.contains(&n) {
                    neighbours.push(n);
                }
            }
        }
        let mut created = 0;
        for n in neighbours {
            let (k1, k2) = (&map.keyframes[&kf], &map.keyframes[&n]);
            let (pose1, pose2) = (k1.pose_cw, k2.pose_cw);
            let (o1, o2) = (k1.center(), k2.center());
            if self.mono {
                // A baseline that is tiny relative to the scene gives no depth (ORB-SLAM: 1 %).
                // A panoramic keyframe has no points of its own: the scene depth of the
                // keyframe its turn began from.
                let median = match scene_median_depth(map, k2) {
                    None if k2.panoramic => scene_median_depth(map, k1),
                    d => d,
                };
                let Some(median) = median else {
                    continue;
                };
                if (o1 - o2).norm() / median < MONO_MIN_BASELINE {
                    continue;
                }
            } else if (o1 - o2).norm() < intr.bf / intr.fx {
                // RGB-D: a baseline shorter than the virtual stereo baseline adds nothing the
                // depth does not give (ORB-SLAM2's rule).
                continue;
            }
            let pairs = match_for_triangulation(&self.geo, k1, k2);
            let r1 = *pose1.rotation.to_rotation_matrix().matrix();
            let r2 = *pose2.rotation.to_rotation_matrix().matrix();
            let p1 = projection_matrix(&intr, &r1, &pose1.translation.vector);
            let p2 = projection_matrix(&intr, &r2, &pose2.translation.vector);
            for (i1, i2) in pairs {
                let (k1, k2) = (&map.keyframes[&kf], &map.keyframes[&n]);
                if k1.points[i1].is_some() || k2.points[i2].is_some() {
                    continue; // claimed by an earlier neighbour
                }
                let (kp1, kp2) = (k1.keypoints[i1], k2.keypoints[i2]);
                // Parallax of the viewing rays.
                let ray = |pose: &Isometry3<f64>, uv: &Vector2<f64>| {
                    let x =
                        Vector3::new((uv.x - intr.cx) / intr.fx, (uv.y - intr.cy) / intr.fy, 1.0);
                    pose.rotation.inverse() * x
                };
                let (ray1, ray2) = (ray(&pose1, &kp1.un), ray(&pose2, &kp2.un));
                let cos = ray1.dot(&ray2) / (ray1.norm() * ray2.norm());
                if !(cos > 0.0 && cos < MAX_COS_PARALLAX) {
                    continue;
                }
                let Some(x) = triangulate(&p1, &p2, &kp1.un, &kp2.un) else {
                    continue;
                };
                let ok = |pose: &Isometry3<f64>, kp: &crate::components::preprocess::Keypoint| {
                    let pc = pose * Point3::from(x);
                    if pc.z <= 0.0 {
                        return false;
                    }
                    let Some(uv) = intr.project(&pc.coords) else {
                        return false;
                    };
                    (uv - kp.un).norm_squared() * octave_information(kp.octave as u32)
                        <= optim::CHI2_MONO
                };
                if !ok(&pose1, &kp1) || !ok(&pose2, &kp2) {
                    continue;
                }
                // Scale consistency: the distance ratio must match the octave ratio.
                let (d1, d2) = ((x - o1).norm(), (x - o2).norm());
                if d1 <= 0.0 || d2 <= 0.0 {
                    continue;
                }
                let ratio_dist = d2 / d1;
                let ratio_octave =
                    self.geo.scales[kp1.octave as usize] / self.geo.scales[kp2.octave as usize];
                let factor = 1.5 * sf;
                if ratio_dist * factor < ratio_octave || ratio_dist > ratio_octave * factor {
                    continue;
                }
                let pid = map.add_point(kf, i1, x, sf, nl);
                map.observe(n, i2, pid);
                map.update_point(pid, sf, nl);
                self.recent.push((pid, kf));
                created += 1;
            }
        }
        created
    }

    /// Projects the points of the best covisible keyframes into the new keyframe: a matching
    /// keypoint that has no point gets an observation; one that has another point merges the two
    /// (the one with fewer observations is replaced). Returns the number of fusions/additions.
    ///
    /// Monocular: also the other way (ORB-SLAM's `SearchInNeighbors`), the new keyframe's
    /// points into its neighbours and their best neighbours. A triangulated point starts with
    /// two observations and is culled two keyframes later unless a third keyframe observes it;
    /// an older keyframe that sees the same keypoint but had no point there is that third
    /// observation, and without it the map thins out wherever the camera keeps moving on (on
    /// fr1_desk the map fell to 45 tracked points by frame 53 and tracking was lost).
    fn fuse(&self, map: &mut Map, kf: KfId) -> usize {
        if !self.mono {
            let neighbours = map.keyframes[&kf].best_covisible(10);
            return self.fuse_into(map, kf, &neighbours);
        }
        let mut targets = map.keyframes[&kf].best_covisible(TRIANGULATION_NEIGHBOURS);
        let mut seen: BTreeSet<KfId> = targets.iter().copied().collect();
        seen.insert(kf);
        for n in targets.clone() {
            for n2 in map.keyframes[&n].best_covisible(5) {
                if seen.insert(n2) {
                    targets.push(n2);
                }
            }
        }
        let mut fused = 0;
        for &t in &targets {
            fused += self.fuse_into(map, t, &[kf]);
        }
        fused + self.fuse_into(map, kf, &targets)
    }

    /// Projects the points of keyframes `sources` into keyframe `kf` and fuses duplicates
    /// (see `fuse`). Loop closing uses it across the loop (ORB-SLAM's `SearchAndFuse`): the
    /// two sides then share points, so the covisibility graph, the tracker's local map and
    /// local BA see them as one place instead of two overlapping branches.
    pub fn fuse_into(&self, map: &mut Map, kf: KfId, sources: &[KfId]) -> usize {
        let mut cands: BTreeSet<PointId> = BTreeSet::new();
        for n in sources {
            if let Some(k) = map.keyframes.get(n) {
                cands.extend(k.points.iter().flatten().copied());
            }
        }
        let mut fused = 0;
        for pid in cands {
            let (pose, center) = {
                let k = &map.keyframes[&kf];
                (k.pose_cw, k.center())
            };
            let Some(p) = map.points.get(&pid) else {
                continue;
            };
            if p.observations.contains_key(&kf) {
                continue;
            }
            let pc = pose * Point3::from(p.position);
            let Some(uv) = self.geo.project_in_image(&pc.coords) else {
                continue;
            };
            let dist = (p.position - center).norm();
            if dist < 0.8 * p.min_distance || dist > 1.2 * p.max_distance {
                continue;
            }
            let level = self.geo.predicted_level(p.max_distance, dist);
            let r = 3.0 * self.geo.scales[level];
            let k = &map.keyframes[&kf];
            let mut best = (u32::MAX, usize::MAX);
            for i in k.grid.in_area(&k.keypoints, uv.x, uv.y, r, 0, 255) {
                let e = (k.keypoints[i].un - uv).norm_squared()
                    * octave_information(k.keypoints[i].octave as u32);
                // With depth, the point must also agree in depth (ORB-SLAM's stereo check).
                let d = k.depth[i] as f64;
                if d > 0.0 {
                    if e > optim::CHI2_RGBD || (d - pc.z).abs() > 0.05 * pc.z.max(0.5) {
                        continue;
                    }
                } else if self.mono {
                    // Without depth: ORB-SLAM's monocular fuse gates, the reprojection χ² and
                    // the keypoint's pyramid level near the one the distance predicts.
                    let octave = k.keypoints[i].octave as usize;
                    if e > optim::CHI2_MONO || octave + 1 < level || octave > level {
                        continue;
                    }
                }
                let h = hamming(&p.descriptor, &k.descriptors[i]);
                if h < best.0 {
                    best = (h, i);
                }
            }
            if best.0 > 50 {
                continue;
            }
            let i = best.1;
            match map.keyframes[&kf].points[i] {
                Some(other) if other != pid => {
                    let n_other = map.points.get(&other).map_or(0, |o| o.observations.len());
                    let n_this = map.points[&pid].observations.len();
                    if n_this >= n_other {
                        map.replace_point(other, pid);
                    } else {
                        map.replace_point(pid, other);
                    }
                    fused += 1;
                }
                Some(_) => {}
                None => {
                    if map.observe(kf, i, pid) {
                        fused += 1;
                    }
                }
            }
        }
        fused
    }

    /// Local BA over the new keyframe and its covisible window (ORB-SLAM's schedule: a robust
    /// pass, outliers set aside, a plain pass on the inliers).
    fn local_ba(&mut self, map: &mut Map, kf: KfId, report: &mut MergeReport) {
        let mut local: Vec<KfId> = vec![kf];
        local.extend(map.keyframes[&kf].best_covisible(self.cfg.local_ba_window as usize - 1));
        self.hold_fixed_mono(map, &mut local);
        let first = BaParams {
            iterations: 5,
            ..Default::default()
        };
        let second = BaParams {
            iterations: self.cfg.local_ba_iterations as usize,
            huber: false,
            ..Default::default()
        };
        let Some(job) = prepare_ba(map, &self.geo, &local, kf, &first, &second) else {
            return;
        };
        match self.worker.as_mut() {
            Some(w) => {
                // One job at a time: a still-running BA is finished and applied first, so that
                // the next one starts from its result (ORB-SLAM instead aborts it).
                if w.pending > 0 {
                    let times = self.wait_for(map);
                    self.waited_ms.extend(times);
                }
                let w = self.worker.as_mut().expect("threaded");
                if w.jobs.send(job).is_ok() {
                    w.pending += 1;
                }
            }
            None => {
                let done = job.solve();
                if let Some(r) = apply_ba(map, &self.geo, &done) {
                    report.ba_initial_cost = r.initial_cost;
                    report.ba_final_cost = r.final_cost;
                    report.ba_outliers = r.outliers.len();
                }
            }
        }
    }

    /// Monocular: the map's second keyframe and the panoramic keyframes are held fixed (removed
    /// from `free`). With only the first keyframe fixed, the BA's gauge keeps a free scale, and
    /// while the window still holds every keyframe the solver lets it drift (by tens of percent
    /// in one BA on fr1_xyz); frame poses, stored relative to their keyframe, would then no
    /// longer agree with the rescaled map. The pair's distance, set at initialisation, fixes
    /// the scale.
    fn hold_fixed_mono(&self, map: &Map, free: &mut Vec<KfId>) {
        if !self.mono {
            return;
        }
        if let Some(&second) = map.keyframes.keys().nth(1) {
            free.retain(|k| *k != second);
        }
        // A panoramic keyframe's position is the turn's centre, taken from the map-tracked
        // pose the turn began at; its bearings have no depth and do not observe it. Left free,
        // the few points triangulated from it later drag it away (small `turn-in-place` mono,
        // drops of 5 s in both turns: a panoramic keyframe moved 0.34 m, the walk after the
        // turns went 0.5 m off on points triangulated from it, and three wrong closures
        // stood). It takes part as a constant, like a keyframe outside the window.
        free.retain(|k| !map.keyframes[k].panoramic);
    }

    /// Full BA over every keyframe of the map (the first one fixed for the gauge), as after a
    /// consistent closure; Final's batch refinement adds frames ([`Self::global_ba_with_frames`]).
    pub fn global_ba(&self, map: &mut Map) -> Option<optim::BaReport> {
        self.global_ba_with_frames(map, &[], &[], None)
            .map(|(r, _)| r)
    }
}

/// Bundle adjustment of the keyframes `free` and every point they see, solved at once. Keyframes
/// outside `free` that see those points are fixed constants, and so is the map's first keyframe
/// (the gauge). Outlier observations are erased from the map; points left without any
/// disappear.
pub fn bundle_adjust(
    map: &mut Map,
    geo: &ImageGeometry,
    free: &[KfId],
    first: &BaParams,
    second: &BaParams,
) -> Option<optim::BaReport> {
    let kf = free.iter().copied().max()?;
    let done = prepare_ba(map, geo, free, kf, first, second)?.solve();
    apply_ba(map, geo, &done).cloned()
}

/// Cuts the BA problem of [`bundle_adjust`] out of the map.
pub fn prepare_ba(
    map: &Map,
    geo: &ImageGeometry,
    free: &[KfId],
    keyframe: KfId,
    first: &BaParams,
    second: &BaParams,
) -> Option<BaJob> {
    let mut local: Vec<KfId> = free.to_vec();
    local.sort_unstable();
    local.dedup();
    let anchor = map.keyframes.keys().next().copied();
    let local_set: BTreeSet<KfId> = local.iter().copied().collect();
    let mut points: BTreeSet<PointId> = BTreeSet::new();
    for k in &local {
        points.extend(map.keyframes[k].points.iter().flatten().copied());
    }
    let mut fixed: BTreeSet<KfId> = BTreeSet::new();
    for pid in &points {
        for o in map.points[pid].observations.keys() {
            if !local_set.contains(o) {
                fixed.insert(*o);
            }
        }
    }
    let cams: Vec<KfId> = local.iter().chain(fixed.iter()).copied().collect();
    let cam_index: BTreeMap<KfId, usize> = cams.iter().enumerate().map(|(i, &k)| (k, i)).collect();
    let pts: Vec<PointId> = points.into_iter().collect();
    let mut problem = BaProblem {
        keyframes: cams
            .iter()
            .map(|k| BaCamera {
                pose_cw: map.keyframes[k].pose_cw,
                fixed: fixed.contains(k) || Some(*k) == anchor,
            })
            .collect(),
        points: pts
            .iter()
            .map(|p| BaPoint {
                position_w: map.points[p].position,
                fixed: false,
            })
            .collect(),
        observations: Vec::new(),
        intrinsics: geo.intr,
        pose_edges: Vec::new(),
    };
    let mut obs_ref: Vec<(PointId, KfId)> = Vec::new();
    for (pi, pid) in pts.iter().enumerate() {
        for (k, &kp) in &map.points[pid].observations {
            let Some(&ci) = cam_index.get(k) else {
                continue;
            };
            let key = &map.keyframes[k];
            let d = key.depth[kp] as f64;
            let uv = key.keypoints[kp].un;
            problem.observations.push(BaObservation {
                camera: ci,
                point: pi,
                obs: if d > 0.0 {
                    Observation::Rgbd { uv, depth: d }
                } else {
                    Observation::Mono { uv }
                },
                info: octave_information(key.keypoints[kp].octave as u32),
                shutter: geo.shutter(&key.twist, key.keypoints[kp].raw.y),
            });
            obs_ref.push((*pid, *k));
        }
    }
    if problem.keyframes.iter().all(|c| c.fixed) {
        return None;
    }
    Some(BaJob {
        map: map.id,
        keyframe,
        problem,
        cams,
        pts,
        obs_ref,
        first: *first,
        second: *second,
    })
}

/// Writes a solved job back. In threaded mode the map moved on while it was solved: keyframes
/// and points that disappeared meanwhile are skipped, observations added meanwhile are kept.
pub fn apply_ba<'a>(
    map: &mut Map,
    geo: &ImageGeometry,
    done: &'a BaDone,
) -> Option<&'a optim::BaReport> {
    let r = done.report.as_ref()?;
    let BaJob {
        problem,
        cams,
        pts,
        obs_ref,
        ..
    } = &done.job;
    for (k, c) in cams.iter().zip(&problem.keyframes) {
        if !c.fixed
            && let Some(kf) = map.keyframes.get_mut(k)
        {
            kf.pose_cw = c.pose_cw;
        }
    }
    for (p, bp) in pts.iter().zip(&problem.points) {
        if let Some(p) = map.points.get_mut(p) {
            p.position = bp.position_w;
        }
    }
    // Drop outlier observations; points left with none disappear.
    for &o in &r.outliers {
        // Observations past the keyframes' are extra cameras' (see `global_ba_with_frames`).
        let Some(&(pid, k)) = obs_ref.get(o) else {
            continue;
        };
        let Some(p) = map.points.get_mut(&pid) else {
            continue;
        };
        if let Some(kp) = p.observations.remove(&k)
            && let Some(key) = map.keyframes.get_mut(&k)
        {
            key.points[kp] = None;
        }
        if p.observations.is_empty() {
            map.points.remove(&pid);
        }
    }
    for p in pts {
        if map.points.contains_key(p) {
            map.update_point(*p, geo.scale_factor, geo.n_levels);
        }
    }
    Some(r)
}

/// The tracked frame `m` as a new keyframe of `map`: its pose, velocity and tracking parent;
/// and the report of its local mapping, still empty.
fn add_tracked_keyframe(
    map: &mut Map,
    m: &Measurement,
    track: &TrackResult,
) -> (KfId, MergeReport) {
    let kf = map.add_keyframe(m, track.pose_cw);
    let k = map.keyframes.get_mut(&kf).expect("just added");
    k.twist = track.twist;
    k.parent = track.reference_kf;
    let report = MergeReport {
        keyframe: kf,
        ..Default::default()
    };
    (kf, report)
}

/// The optical axis (unit, world frame) of a camera at `pose_cw`.
fn optical_axis(pose_cw: &Isometry3<f64>) -> Vector3<f64> {
    pose_cw.rotation.inverse() * Vector3::z()
}

/// [`median_depth`], or for a panoramic keyframe without points that of the keyframe its
/// turn began from (up its parent chain).
fn scene_median_depth(map: &Map, k: &crate::map::Keyframe) -> Option<f64> {
    let mut k = k;
    for _ in 0..64 {
        if let Some(d) = map.scene_depth(k) {
            return Some(d);
        }
        if !k.panoramic {
            return None;
        }
        k = map.keyframes.get(&k.parent?)?;
    }
    None
}

/// Keyframes of `map` paired with `kf` for triangulation by view direction (decision 0030):
/// for a panoramic keyframe any other keyframe, for another only panoramic ones, whose optical
/// axis is within `PANORAMIC_MAX_VIEW_ANGLE_DEG` of `kf`'s and whose centre is no further from
/// `kf`'s than the scene depth of either: they look at the same place. A look-alike place
/// elsewhere faces the same way from further off: paired by direction alone, `aliasing`'s
/// room B (a copy of room A) was triangulated against room A's keyframes. The nearest in angle
/// first; none in a map without panoramic keyframes.
fn view_neighbours(map: &Map, kf: KfId) -> Vec<KfId> {
    let k = &map.keyframes[&kf];
    let a = optical_axis(&k.pose_cw);
    let cos_max = PANORAMIC_MAX_VIEW_ANGLE_DEG.to_radians().cos();
    let facing: Vec<(f64, &crate::map::Keyframe)> = map
        .keyframes
        .values()
        .filter(|o| o.id != kf && (k.panoramic || o.panoramic))
        .map(|o| (a.dot(&optical_axis(&o.pose_cw)), o))
        .filter(|(c, _)| *c >= cos_max)
        .collect();
    if facing.is_empty() {
        return Vec::new();
    }
    let Some(depth_k) = scene_median_depth(map, k) else {
        return Vec::new();
    };
    let mut v: Vec<(f64, KfId)> = facing
        .into_iter()
        .filter(|(_, o)| {
            let depth_o = scene_median_depth(map, o).unwrap_or(depth_k);
            (o.center() - k.center()).norm() <= depth_k.min(depth_o)
        })
        .map(|(c, o)| (c, o.id))
        .collect();
    v.sort_by(|x, y| y.0.total_cmp(&x.0).then(x.1.cmp(&y.1)));
    v.into_iter()
        .take(PANORAMIC_NEIGHBOURS)
        .map(|(_, id)| id)
        .collect()
}

/// ORB-SLAM's `SearchForTriangulation` without a vocabulary: each keypoint of `k1` that has no
/// point is compared with every keypoint of `k2` that has none; candidates must lie within
/// the χ² gate of the epipolar line (σ of `k2`'s keypoint octave) and not next to the epipole
/// (a point there has no depth), and the best must be clearly better than the second best.
/// A keypoint of `k2` keeps its best match; a rotation histogram drops matches whose
/// orientation change disagrees with the dominant ones. Sorted: deterministic.
fn match_for_triangulation(
    geo: &ImageGeometry,
    k1: &crate::map::Keyframe,
    k2: &crate::map::Keyframe,
) -> Vec<(usize, usize)> {
    let intr = &geo.intr;
    // F12 with x1ᵀ F12 x2 = 0, from the relative pose of camera 2 in camera 1.
    let t12 = k1.pose_cw * k2.pose_cw.inverse();
    let r12 = *t12.rotation.to_rotation_matrix().matrix();
    let t = t12.translation.vector;
    let tx = Matrix3::new(0.0, -t.z, t.y, t.z, 0.0, -t.x, -t.y, t.x, 0.0);
    let kinv = k_matrix(intr)
        .try_inverse()
        .unwrap_or_else(Matrix3::identity);
    let f12 = kinv.transpose() * tx * r12 * kinv;
    // Camera 1's centre in image 2.
    let epipole = intr.project(&(k2.pose_cw * Point3::from(k1.center())).coords);
    let free2: Vec<usize> = (0..k2.keypoints.len())
        .filter(|&i| k2.points[i].is_none())
        .collect();
    let mut best: Vec<Option<(u32, usize)>> = vec![None; k2.keypoints.len()];
    for i1 in 0..k1.keypoints.len() {
        if k1.points[i1].is_some() {
            continue;
        }
        let x1 = k1.keypoints[i1].un;
        let l = Vector3::new(x1.x, x1.y, 1.0).transpose() * f12;
        let (a, b, c) = (l[0], l[1], l[2]);
        let norm2 = a * a + b * b;
        if norm2 <= 0.0 {
            continue;
        }
        let d1 = &k1.descriptors[i1];
        let (mut b1, mut b2, mut bi) = (u32::MAX, u32::MAX, usize::MAX);
        for &i2 in &free2 {
            let h = hamming(d1, &k2.descriptors[i2]);
            if h > TRIANGULATION_MAX_DISTANCE || h >= b2 {
                continue;
            }
            let kp2 = &k2.keypoints[i2];
            let sigma2 = geo.scales[kp2.octave as usize].powi(2);
            if let Some(e) = epipole
                && (kp2.un - e).norm_squared() < 100.0 * geo.scales[kp2.octave as usize]
            {
                continue;
            }
            let num = a * kp2.un.x + b * kp2.un.y + c;
            if num * num / norm2 > CHI2_EPIPOLAR * sigma2 {
                continue;
            }
            if h < b1 {
                (b2, b1, bi) = (b1, h, i2);
            } else {
                b2 = h;
            }
        }
        if bi == usize::MAX || (b2 != u32::MAX && b1 as f64 > TRIANGULATION_RATIO * b2 as f64) {
            continue;
        }
        if best[bi].is_none_or(|(d, _)| b1 < d) {
            best[bi] = Some((b1, i1));
        }
    }
    let mut pairs = rotation_consistent_pairs(&best, &k1.keypoints, &k2.keypoints);
    pairs.sort_unstable();
    pairs
}

/// Refined frame poses (`T_cw`) by frame index.
pub type FramePoses = Vec<(usize, Isometry3<f64>)>;
/// A frame's inlier observations as BA terms, with the point each one sees.
pub type FrameTerms = Vec<(PointId, BaObservation)>;

/// A tracked frame's inlier observations, kept for the Final state's batch refinement: frames
/// tracked in Localized (no keyframes there, by design) and between keyframes still see the
/// map's points from other places, and the full BA uses them as extra cameras.
#[derive(Debug, Clone)]
pub struct FrameObservations {
    pub frame: usize,
    pub t: f64,
    /// The keyframe the frame's pose is kept relative to, and that pose (`T_cw · T_kw⁻¹`, its
    /// translation in the keyframe's creation units, see `Keyframe::relative_of`).
    pub kf: KfId,
    pub rel: Isometry3<f64>,
    /// Camera velocity (rolling shutter), its translation in the same units as `rel`'s.
    pub twist: nalgebra::Vector6<f64>,
    /// A keyframe was made from this frame (so it is no extra camera for the Final BA).
    pub keyframe: bool,
    pub obs: Vec<KeptObservation>,
}

/// One inlier observation of a kept frame, packed into 24 bytes (32 with an f64 key point):
/// Final keeps up to `final_frames_per_keyframe` frames of a few hundred of these per keyframe,
/// the largest part of the memory that grows with a run. f32 pixel coordinates are exact to
/// 1e-4 px at 640 px, far below a key point's noise.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeptObservation {
    pub point: PointId,
    /// Undistorted key point.
    pub uv: [f32; 2],
    /// Metres; 0 = none.
    pub depth: f32,
    /// Raw image row (rolling shutter).
    pub row: f32,
    pub octave: u8,
}

impl FrameObservations {
    pub fn new(m: &Measurement, track: &TrackResult) -> Self {
        let obs = track
            .matches
            .iter()
            .enumerate()
            .filter_map(|(i, p)| {
                let p = (*p)?;
                let kp = &m.keypoints[i];
                Some(KeptObservation {
                    point: p,
                    uv: [kp.un.x as f32, kp.un.y as f32],
                    depth: m.depth[i],
                    row: kp.raw.y as f32,
                    octave: kp.octave,
                })
            })
            .collect();
        Self {
            frame: m.frame,
            t: m.t,
            kf: 0,
            rel: Isometry3::identity(),
            twist: track.twist,
            keyframe: false,
            obs,
        }
    }

    /// Ties the observations to the frame's standing pose: `rel` on keyframe `k`. Like
    /// `rel`'s (see `Keyframe::relative_of`), the velocity's translation is kept in `k`'s
    /// units, so a Sim3 merge that later rescales the map rescales it too.
    pub fn anchor(&mut self, k: &crate::map::Keyframe, rel: Isometry3<f64>, keyframe: bool) {
        self.kf = k.id;
        self.rel = rel;
        self.keyframe = keyframe;
        for i in 3..6 {
            self.twist[i] /= k.units;
        }
    }

    /// The velocity in keyframe `k`'s current units (see [`Self::anchor`]).
    fn twist_on(&self, k: &crate::map::Keyframe) -> nalgebra::Vector6<f64> {
        let mut twist = self.twist;
        for i in 3..6 {
            twist[i] *= k.units;
        }
        twist
    }
}

impl MapMerger {
    /// Final's batch refinement with frames: a full BA over every keyframe and point of the
    /// map plus the given frames as free cameras, each first placed on the map as it is (see
    /// [`Self::place_frame`]) so that it starts consistent and brings only its inliers.
    /// Returns the BA report and the refined frame poses (`T_cw`). `cutoff` ends the solve
    /// early (after a user stop), keeping the estimate so far.
    pub fn global_ba_with_frames(
        &self,
        map: &mut Map,
        frames: &[&FrameObservations],
        depth_edges: &[crate::components::depth_registration::DepthEdge],
        cutoff: Option<optim::Cutoff>,
    ) -> Option<(optim::BaReport, FramePoses)> {
        let iterations = self.cfg.final_ba_iterations as usize;
        if iterations == 0 || map.keyframes.len() < 2 {
            return None;
        }
        let mut free: Vec<KfId> = map.keyframes.keys().copied().collect();
        self.hold_fixed_mono(map, &mut free);
        // With frames, every camera starts placed on the map, so the solve stops once a step
        // gains less than a millionth of the cost instead of running all its iterations.
        let tol = if frames.is_empty() {
            BaParams::default().relative_tolerance
        } else {
            1e-6
        };
        let first = BaParams {
            iterations,
            relative_tolerance: tol,
            cutoff,
            ..Default::default()
        };
        let second = BaParams {
            iterations,
            huber: false,
            relative_tolerance: tol,
            cutoff,
            ..Default::default()
        };
        let kf = free.iter().copied().max()?;
        let placed: Vec<(usize, Isometry3<f64>, FrameTerms)> = frames
            .iter()
            .filter_map(|f| {
                let (pose, obs) = self.place_frame(map, f)?;
                Some((f.frame, pose, obs))
            })
            .collect();
        let mut job = prepare_ba(map, &self.geo, &free, kf, &first, &second)?;
        let n_kf_cams = job.problem.keyframes.len();
        let cam_index: BTreeMap<KfId, usize> =
            job.cams.iter().enumerate().map(|(i, k)| (*k, i)).collect();
        for e in depth_edges {
            if let (Some(&a), Some(&b)) = (cam_index.get(&e.a), cam_index.get(&e.b)) {
                job.problem.pose_edges.push(optim::BaPoseEdge {
                    a,
                    b,
                    a_from_b: e.a_from_b,
                    info: e.information,
                });
            }
        }
        let pt_index: BTreeMap<PointId, usize> =
            job.pts.iter().enumerate().map(|(i, p)| (*p, i)).collect();
        let mut used = Vec::new();
        // Reserved once: grown by doubling, the frames' observations (the largest array of
        // Final's BA) would peak at up to three times their size while being copied.
        let extra: usize = placed.iter().map(|(_, _, obs)| obs.len()).sum();
        job.problem.observations.reserve_exact(extra);
        job.problem.keyframes.reserve_exact(placed.len());
        for (frame, pose_cw, obs) in placed {
            let camera = job.problem.keyframes.len();
            let before = job.problem.observations.len();
            for (pid, o) in obs {
                if let Some(&point) = pt_index.get(&pid) {
                    job.problem
                        .observations
                        .push(BaObservation { camera, point, ..o });
                }
            }
            if job.problem.observations.len() > before {
                job.problem.keyframes.push(BaCamera {
                    pose_cw,
                    fixed: false,
                });
                used.push(frame);
            }
        }
        let done = job.solve();
        let r = apply_ba(map, &self.geo, &done)?.clone();
        let poses = used
            .into_iter()
            .zip(&done.job.problem.keyframes[n_kf_cams..])
            .map(|(f, c)| (f, c.pose_cw))
            .collect();
        Some((r, poses))
    }

    /// Places frame `f` on the map as it now is: a motion-only BA of its stored observations
    /// of the points still in the map, from its pose relative to its keyframe. Returns the
    /// pose (`T_cw`) and the inlier observations (camera and point indices left 0), or `None`
    /// when too few inliers remain (the frame then keeps its pose relative to its keyframe).
    pub fn place_frame(
        &self,
        map: &Map,
        f: &FrameObservations,
    ) -> Option<(Isometry3<f64>, FrameTerms)> {
        // The frame was tracked and starts near its place: one robust round and one plain
        // one, each of a few iterations, are enough (the tracker's four rounds of ten start
        // from a prediction).
        let params = crate::optim::PoseParams {
            rounds: 2,
            iterations_per_round: 5,
            robust_rounds: 1,
            ..Default::default()
        };
        let k = map.keyframes.get(&f.kf)?;
        let twist = f.twist_on(k);
        let (ids, obs): (Vec<PointId>, Vec<crate::optim::PoseObservation>) = f
            .obs
            .iter()
            .filter_map(|o| {
                let pid = o.point;
                let uv = Vector2::new(o.uv[0] as f64, o.uv[1] as f64);
                let p = map.points.get(&pid)?;
                let d = o.depth as f64;
                Some((
                    pid,
                    crate::optim::PoseObservation {
                        point_w: p.position,
                        obs: if d > 0.0 {
                            Observation::Rgbd { uv, depth: d }
                        } else {
                            Observation::Mono { uv }
                        },
                        info: octave_information(o.octave as u32),
                        shutter: self.geo.shutter(&twist, o.row as f64),
                    },
                ))
            })
            .unzip();
        let r =
            crate::optim::refine_pose(&k.pose_from_relative(&f.rel), &obs, &self.geo.intr, &params);
        if r.n_inliers < params.min_inliers_to_continue {
            return None;
        }
        let inliers = ids
            .into_iter()
            .zip(obs)
            .zip(&r.inliers)
            .filter(|(_, inlier)| **inlier)
            .map(|((pid, o), _)| {
                (
                    pid,
                    BaObservation {
                        camera: 0,
                        point: 0,
                        obs: o.obs,
                        info: o.info,
                        shutter: o.shutter,
                    },
                )
            })
            .collect();
        Some((r.pose, inliers))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::components::tracker::TrackMethod;
    use crate::optim::Intrinsics;
    use nalgebra::Vector6;

    /// A monocular map whose reference keyframe (at the origin) sees 300 points of a wall 2 m
    /// away, each observed by three keyframes (the weight the keyframe decision counts); and a
    /// frame of that wall.
    fn mono_wall() -> (MapMerger, Map, KfId, Measurement) {
        let geo = ImageGeometry::new(Intrinsics::TUM_FREIBURG1, 640, 480, 1.2, 8);
        let uvs: Vec<Vector2<f64>> = (0..15)
            .flat_map(|j| {
                (0..20).map(move |i| Vector2::new(16.0 + 32.0 * i as f64, 16.0 + 32.0 * j as f64))
            })
            .collect();
        let view = |frame| Measurement::synthetic(frame, uvs.clone(), 0.0, 0.0, vec![[0; 32]; 300]);
        let mut map = Map::new(0);
        let others = [
            map.add_keyframe(&view(0), Isometry3::translation(0.1, 0.0, 0.0)),
            map.add_keyframe(&view(1), Isometry3::translation(-0.1, 0.0, 0.0)),
        ];
        let m = view(2);
        let reference = map.add_keyframe(&m, Isometry3::identity());
        let intr = geo.intr;
        for (i, kp) in m.keypoints.iter().enumerate() {
            let p = Vector3::new(
                (kp.un.x - intr.cx) * 2.0 / intr.fx,
                (kp.un.y - intr.cy) * 2.0 / intr.fy,
                2.0,
            );
            let pid = map.add_point(reference, i, p, 1.2, 8);
            for k in others {
                map.observe(k, i, pid);
            }
        }
        let mut merger = MapMerger::new(&MappingConfig::default(), geo).monocular(true);
        merger.last_kf_frame = Some(2);
        (merger, map, reference, view(3))
    }

    fn tracked(map: &Map, reference: KfId, inliers: usize, x: f64) -> TrackResult {
        let kf = &map.keyframes[&reference];
        let mut matches = kf.points.clone();
        for m in matches.iter_mut().skip(inliers) {
            *m = None;
        }
        TrackResult {
            pose_cw: Isometry3::translation(-x, 0.0, 0.0),
            matches,
            n_inliers: inliers,
            able_to_track: true,
            method: TrackMethod::MotionModel,
            reference_kf: Some(reference),
            visible: Vec::new(),
            twist: Vector6::zeros(),
            mean_chi2: 1.0,
        }
    }

    /// A panoramic keyframe sits at its turn's centre, which its bearings do not observe: the
    /// BA holds it where rotation-only tracking put it, while it still moves the others.
    #[test]
    fn the_bundle_adjustment_holds_a_panoramic_keyframe_where_its_turn_put_it() {
        let (merger, mut map, reference, m) = mono_wall();
        let off = Isometry3::translation(0.03, -0.02, 0.01);
        let panoramic = map.add_keyframe(&m, off);
        map.keyframes.get_mut(&panoramic).unwrap().panoramic = true;
        let points: Vec<_> = map.keyframes[&reference].points.clone();
        for (i, p) in points.iter().enumerate() {
            map.observe(panoramic, i, p.expect("every key point holds a point"));
        }
        let before = map.keyframes[&reference].pose_cw;
        merger.global_ba(&mut map).expect("a BA ran");
        assert_eq!(map.keyframes[&panoramic].pose_cw, off);
        let moved = (map.keyframes[&reference].pose_cw.translation.vector
            - before.translation.vector)
            .norm();
        assert!(moved > 1e-4, "the free keyframe moved {moved} m");
    }

    /// Monocular keyframes come when the frame tracks clearly fewer of the reference's points
    /// *and* has the baseline to triangulate new ones (4 % of the median depth: 8 cm at 2 m),
    /// or when it tracks fewer than half of them whatever the baseline, unless the last
    /// keyframe triangulated nothing: then the least baseline triangulation uses (1 %: 2 cm
    /// at 2 m) is needed (decision 0029).
    #[test]
    fn a_monocular_keyframe_needs_a_baseline_unless_the_view_is_leaving_the_map() {
        let (mut merger, map, reference, m) = mono_wall();
        // (last keyframe barren, points tracked of 300, metres from the reference, keyframe?)
        let cases = [
            // Below 90 % tracked: 1 cm away is too close, 10 cm is enough.
            (false, 200, 0.01, false),
            (false, 200, 0.10, true),
            // Below half: the view is leaving the map; a keyframe at once.
            (false, 120, 0.005, true),
            // Above 90 %: no keyframe wherever it is.
            (false, 285, 0.10, false),
            // After a keyframe that triangulated nothing, leaving the map needs 1 %: 3 cm is
            // enough, 5 mm is not.
            (true, 120, 0.005, false),
            (true, 120, 0.03, true),
        ];
        for (barren, inliers, x, expected) in cases {
            merger.last_kf_barren = barren;
            let track = tracked(&map, reference, inliers, x);
            assert_eq!(
                merger.need_keyframe(&map, &m, &track, true),
                expected,
                "last keyframe barren {barren}, {inliers} of 300 tracked, {x} m away"
            );
        }
    }
}
