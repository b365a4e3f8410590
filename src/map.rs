//! The local map: keyframes, map points, covisibility. Ordered containers everywhere (BTreeMap)
//! so that iteration order, and with it every output, is deterministic.

use crate::components::preprocess::{
    Descriptor, FeatureGrid, Keypoint, Measurement, hamming, nearest_descriptor,
};
use nalgebra::{Isometry3, Point3, Vector3, Vector6};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};

pub type KfId = u32;
pub type PointId = u32;

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MapPoint {
    pub id: PointId,
    pub position: Vector3<f64>,
    /// The observation descriptor with the least median distance to the others (ORB-SLAM).
    pub descriptor: Descriptor,
    /// Keyframe → keypoint index.
    pub observations: BTreeMap<KfId, usize>,
    /// Mean viewing direction (unit), for the viewing-angle check in projection search.
    pub normal: Vector3<f64>,
    /// Scale-invariance distance range.
    pub min_distance: f64,
    pub max_distance: f64,
    /// Times predicted visible by the tracker / times actually matched (culling statistics).
    pub visible: u32,
    pub found: u32,
    pub first_kf: KfId,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Keyframe {
    pub id: KfId,
    pub frame: usize,
    pub t: f64,
    /// World-to-camera.
    pub pose_cw: Isometry3<f64>,
    /// Camera velocity when the keyframe was taken (world-to-camera twist per second), for
    /// the rolling-shutter model: row `y` was exposed at `ImageGeometry::shutter(twist, y)·T_cw`.
    pub twist: Vector6<f64>,
    pub keypoints: Vec<Keypoint>,
    pub descriptors: Vec<Descriptor>,
    pub depth: Vec<f32>,
    pub grid: FeatureGrid,
    /// Map point of each keypoint.
    pub points: Vec<Option<PointId>>,
    /// Covisible keyframe → number of shared map points.
    pub covisibility: BTreeMap<KfId, u32>,
    /// The keyframe this one's frame was tracked against when it was made: its link in the
    /// tracking chain, which the essential graph keeps after culling has removed every point
    /// the two shared (see `global_optimizer::essential_edges`). `None` for a map's first.
    #[serde(default)]
    pub parent: Option<KfId>,
    /// How much lengths in this keyframe's camera frame have been rescaled since it was made
    /// (monocular: Sim3 merges and pose graphs change a map's scale locally; 1 with depth).
    /// Frame poses and closure measurements kept relative to the keyframe are stored in its
    /// creation units and rescaled by this on use.
    pub units: f64,
    /// The depth grid of the keyframe's frame ([`crate::components::preprocess::Measurement::surface`],
    /// millimetres in its creation units; empty when monocular): what depth registration
    /// aligns when no key point is shared.
    pub surface: Vec<u16>,
    /// Monocular: a *panoramic* keyframe, made while the camera only turned (rotation-only
    /// tracking, decision 0030). Its key points are bearings from its centre, which is the
    /// position the turn began at; none had a map point when it was made. It is kept for
    /// what a turn cannot give: a baseline later. Paired with a keyframe seen from elsewhere
    /// in the map (another turn's, or the walk's after it), its bearings are triangulated in
    /// the map's own scale (Pirchheim et al., ISMAR 2013).
    #[serde(default)]
    pub panoramic: bool,
}

impl Keyframe {
    pub fn from_measurement(id: KfId, m: &Measurement, pose_cw: Isometry3<f64>) -> Self {
        Self {
            id,
            frame: m.frame,
            t: m.t,
            pose_cw,
            twist: Vector6::zeros(),
            keypoints: m.keypoints.clone(),
            descriptors: m.descriptors.clone(),
            depth: m.depth.clone(),
            grid: m.grid.clone(),
            points: vec![None; m.keypoints.len()],
            covisibility: BTreeMap::new(),
            parent: None,
            units: 1.0,
            surface: m.surface.clone(),
            panoramic: false,
        }
    }

    pub fn center(&self) -> Vector3<f64> {
        self.pose_cw.inverse().translation.vector
    }

    /// What a frame tracked at `pose_cw` keeps relative to this keyframe: `T_cw · T_kw⁻¹`,
    /// its translation in the keyframe's creation units (see `units`).
    pub fn relative_of(&self, pose_cw: &Isometry3<f64>) -> Isometry3<f64> {
        let mut rel = pose_cw * self.pose_cw.inverse();
        rel.translation.vector /= self.units;
        rel
    }

    /// The camera pose (`T_cw`) of a frame kept relative to this keyframe ([`Self::relative_of`]).
    pub fn pose_from_relative(&self, rel: &Isometry3<f64>) -> Isometry3<f64> {
        let mut rel = *rel;
        rel.translation.vector *= self.units;
        rel * self.pose_cw
    }

    pub fn n_points(&self) -> usize {
        self.points.iter().filter(|p| p.is_some()).count()
    }

    /// Covisible keyframes, strongest first.
    pub fn best_covisible(&self, n: usize) -> Vec<KfId> {
        let mut v: Vec<(KfId, u32)> = self.covisibility.iter().map(|(&k, &w)| (k, w)).collect();
        v.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        v.into_iter().take(n).map(|(k, _)| k).collect()
    }
}

/// One map: a connected set of keyframes and points in one coordinate frame.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Map {
    pub id: u32,
    pub keyframes: BTreeMap<KfId, Keyframe>,
    pub points: BTreeMap<PointId, MapPoint>,
    next_kf: KfId,
    next_point: PointId,
}

impl Map {
    pub fn new(id: u32) -> Self {
        Self {
            id,
            ..Default::default()
        }
    }

    /// The ids the next keyframe and point would get.
    pub fn next_ids(&self) -> (KfId, PointId) {
        (self.next_kf, self.next_point)
    }

    /// Moves the id counters past `floor` (ids stay unique across the atlas's maps).
    pub fn reserve_ids(&mut self, floor: (KfId, PointId)) {
        self.next_kf = self.next_kf.max(floor.0);
        self.next_point = self.next_point.max(floor.1);
    }

    /// Takes over every keyframe and point of `other` (already in this map's frame; ids are
    /// unique across the atlas).
    pub fn absorb(&mut self, other: Map) {
        debug_assert!(
            other
                .keyframes
                .keys()
                .all(|k| !self.keyframes.contains_key(k))
                && other.points.keys().all(|p| !self.points.contains_key(p)),
            "absorbed map {} shares ids with map {}",
            other.id,
            self.id
        );
        let (k, p) = other.next_ids();
        self.reserve_ids((k, p));
        self.keyframes.extend(other.keyframes);
        self.points.extend(other.points);
    }

    /// What a transaction keeps of the map to revoke it later: every keyframe's pose, units,
    /// parent and which point each key point saw, and every point; not the key points,
    /// descriptors, depth or grids (most of a map's memory), which a revocation never restores.
    pub fn skeleton(&self) -> Map {
        let keyframes = self
            .keyframes
            .iter()
            .map(|(&id, k)| {
                let kf = Keyframe {
                    id,
                    frame: k.frame,
                    t: k.t,
                    pose_cw: k.pose_cw,
                    twist: k.twist,
                    keypoints: Vec::new(),
                    descriptors: Vec::new(),
                    depth: Vec::new(),
                    grid: FeatureGrid::new(0, 0, &[]),
                    points: k.points.clone(),
                    covisibility: BTreeMap::new(),
                    parent: k.parent,
                    units: k.units,
                    surface: Vec::new(),
                    panoramic: k.panoramic,
                };
                (id, kf)
            })
            .collect();
        Map {
            id: self.id,
            keyframes,
            points: self.points.clone(),
            next_kf: self.next_kf,
            next_point: self.next_point,
        }
    }

    /// Inserts a point made elsewhere (a revocation's copy) under its own id, which must be
    /// unused in the atlas; the id counter moves past it.
    pub fn insert_point(&mut self, p: MapPoint) {
        self.next_point = self.next_point.max(p.id + 1);
        self.points.insert(p.id, p);
    }

    /// Recomputes what a saved map does not store.
    pub fn rebuild_after_load(&mut self) {
        for kf in self.keyframes.values_mut() {
            let (w, h) = kf.grid.size();
            kf.grid = FeatureGrid::new(w, h, &kf.keypoints);
        }
    }

    pub fn add_keyframe(&mut self, m: &Measurement, pose_cw: Isometry3<f64>) -> KfId {
        let id = self.next_kf;
        self.next_kf += 1;
        self.keyframes
            .insert(id, Keyframe::from_measurement(id, m, pose_cw));
        id
    }

    /// Creates a map point observed by keypoint `kp` of keyframe `kf`.
    pub fn add_point(
        &mut self,
        kf: KfId,
        kp: usize,
        position: Vector3<f64>,
        scale_factor: f64,
        n_levels: u32,
    ) -> PointId {
        let id = self.next_point;
        self.next_point += 1;
        let k = &self.keyframes[&kf];
        let descriptor = k.descriptors[kp];
        let mut p = MapPoint {
            id,
            position,
            descriptor,
            observations: BTreeMap::new(),
            normal: Vector3::z(),
            min_distance: 0.0,
            max_distance: f64::INFINITY,
            visible: 1,
            found: 1,
            first_kf: kf,
        };
        p.observations.insert(kf, kp);
        self.points.insert(id, p);
        self.keyframes.get_mut(&kf).expect("keyframe exists").points[kp] = Some(id);
        self.update_point(id, scale_factor, n_levels);
        id
    }

    /// Median depth of keyframe `k`'s points in its camera, in the map's units (ORB-SLAM's
    /// scene median depth: what a change of its pose moves the scene by); `None` without
    /// points in front of it.
    pub fn scene_depth(&self, k: &Keyframe) -> Option<f64> {
        let mut z: Vec<f64> = k
            .points
            .iter()
            .flatten()
            .filter_map(|p| self.points.get(p))
            .map(|p| (k.pose_cw * nalgebra::Point3::from(p.position)).z)
            .collect();
        if z.is_empty() {
            return None;
        }
        z.sort_by(f64::total_cmp);
        Some(z[(z.len() - 1) / 2]).filter(|m| *m > 0.0)
    }

    /// Whether some keyframe measured the point's depth: a point triangulated from rays a few
    /// degrees apart (`mapping.triangulate_points`) is uncertain along its ray by more than a
    /// depth check's tolerance, so depth checks judge only points measured by depth.
    pub fn depth_measured(&self, p: &MapPoint) -> bool {
        p.observations
            .iter()
            .any(|(k, &i)| self.keyframes.get(k).is_some_and(|k| k.depth[i] > 0.0))
    }

    /// Adds an observation of an existing point.
    /// ORB-SLAM's observation count: an observation with depth counts twice (it constrains the
    /// point like a stereo pair), one without once.
    pub fn observation_weight(&self, p: &MapPoint) -> usize {
        p.observations
            .iter()
            .map(|(k, &i)| {
                if self.keyframes.get(k).is_some_and(|k| k.depth[i] > 0.0) {
                    2
                } else {
                    1
                }
            })
            .sum()
    }

    /// Records that keypoint `kp` of keyframe `kf` sees `point`. A point is seen at most once
    /// per keyframe: when `kf` already sees it through another keypoint, nothing changes and
    /// false is returned.
    pub fn observe(&mut self, kf: KfId, kp: usize, point: PointId) -> bool {
        let Some(p) = self.points.get_mut(&point) else {
            return false;
        };
        if p.observations.get(&kf).is_some_and(|&k| k != kp) {
            return false;
        }
        let Some(k) = self.keyframes.get_mut(&kf) else {
            return false;
        };
        if let Some(old) = k.points[kp].filter(|&o| o != point)
            && let Some(o) = self.points.get_mut(&old)
        {
            o.observations.remove(&kf);
        }
        k.points[kp] = Some(point);
        if let Some(p) = self.points.get_mut(&point) {
            p.observations.insert(kf, kp);
        }
        true
    }

    /// Checks that keyframes and points reference each other consistently (for tests and
    /// after loading a saved atlas).
    pub fn check_links(&self) -> std::result::Result<(), String> {
        for (kid, k) in &self.keyframes {
            for (i, p) in k.points.iter().enumerate() {
                let Some(p) = p else { continue };
                match self.points.get(p) {
                    None => return Err(format!("keyframe {kid} keypoint {i}: point {p} missing")),
                    Some(mp) if mp.observations.get(kid) != Some(&i) => {
                        return Err(format!(
                            "keyframe {kid} keypoint {i} sees point {p}, which does not list it"
                        ));
                    }
                    _ => {}
                }
            }
        }
        for (pid, p) in &self.points {
            for (kid, &i) in &p.observations {
                let ok = self
                    .keyframes
                    .get(kid)
                    .and_then(|k| k.points.get(i))
                    .is_some_and(|x| *x == Some(*pid));
                if !ok {
                    return Err(format!(
                        "point {pid} lists keyframe {kid} keypoint {i}, which does not see it"
                    ));
                }
            }
        }
        Ok(())
    }

    /// Removes a point and its observations.
    pub fn remove_point(&mut self, id: PointId) {
        if let Some(p) = self.points.remove(&id) {
            for (kf, kp) in p.observations {
                if let Some(k) = self.keyframes.get_mut(&kf)
                    && k.points[kp] == Some(id)
                {
                    k.points[kp] = None;
                }
            }
        }
    }

    /// Replaces `old` by `new` everywhere (point fusion).
    pub fn replace_point(&mut self, old: PointId, new: PointId) {
        if old == new {
            return;
        }
        let Some(p) = self.points.remove(&old) else {
            return;
        };
        for (kf, kp) in p.observations {
            let already = self
                .points
                .get(&new)
                .is_some_and(|n| n.observations.contains_key(&kf));
            if let Some(k) = self.keyframes.get_mut(&kf) {
                k.points[kp] = if already { None } else { Some(new) };
            }
            if !already && let Some(n) = self.points.get_mut(&new) {
                n.observations.insert(kf, kp);
            }
        }
        if let Some(n) = self.points.get_mut(&new) {
            n.visible += p.visible;
            n.found += p.found;
        }
    }

    /// Recomputes a point's normal, distance range and representative descriptor.
    pub fn update_point(&mut self, id: PointId, scale_factor: f64, n_levels: u32) {
        let Some(p) = self.points.get(&id) else {
            return;
        };
        let mut normal = Vector3::zeros();
        let mut descs = Vec::new();
        for (kf, &kp) in &p.observations {
            let k = &self.keyframes[kf];
            normal += (p.position - k.center()).normalize();
            descs.push(k.descriptors[kp]);
        }
        let (ref_kf, ref_kp) = (p.first_kf, p.observations.get(&p.first_kf).copied());
        let (dist, level) = match (self.keyframes.get(&ref_kf), ref_kp) {
            (Some(k), Some(kp)) => (
                (p.position - k.center()).norm(),
                k.keypoints[kp].octave as i32,
            ),
            _ => {
                let (kf, &kp) = p
                    .observations
                    .iter()
                    .next()
                    .expect("point has an observation");
                let k = &self.keyframes[kf];
                (
                    (p.position - k.center()).norm(),
                    k.keypoints[kp].octave as i32,
                )
            }
        };
        let level_scale = scale_factor.powi(level);
        let max_distance = dist * level_scale;
        let min_distance = max_distance / scale_factor.powi(n_levels as i32 - 1);
        // Representative descriptor: least median distance to the others.
        let best = (0..descs.len())
            .min_by_key(|&i| {
                let mut d: Vec<u32> = descs.iter().map(|o| hamming(&descs[i], o)).collect();
                d.sort_unstable();
                d[(d.len() - 1) / 2]
            })
            .map(|i| descs[i]);
        let p = self.points.get_mut(&id).expect("checked above");
        if normal.norm() > 0.0 {
            p.normal = normal.normalize();
        }
        p.max_distance = max_distance;
        p.min_distance = min_distance;
        if let Some(d) = best {
            p.descriptor = d;
        }
    }

    /// Recomputes the covisibility edges of `kf` (and the reverse edges) from shared points.
    pub fn update_covisibility(&mut self, kf: KfId) {
        let mut counts: BTreeMap<KfId, u32> = BTreeMap::new();
        for pid in self.keyframes[&kf].points.iter().flatten() {
            if let Some(p) = self.points.get(pid) {
                for &other in p.observations.keys() {
                    if other != kf {
                        *counts.entry(other).or_default() += 1;
                    }
                }
            }
        }
        counts.retain(|_, &mut w| w >= 15);
        for (&other, &w) in &counts {
            if let Some(o) = self.keyframes.get_mut(&other) {
                o.covisibility.insert(kf, w);
            }
        }
        self.keyframes
            .get_mut(&kf)
            .expect("keyframe exists")
            .covisibility = counts;
    }

    /// Brute-force descriptor search (ORB-SLAM's SearchByBoW without a vocabulary): each live
    /// map point of keyframe `kf` goes to its nearest descriptor of `m` if that is within
    /// `max_distance` and below `ratio` × the second nearest; a keypoint keeps the closest
    /// point. Per keypoint of `m`: (distance, point, keypoint index in `kf`).
    pub fn search_by_descriptor(
        &self,
        kf: &Keyframe,
        m: &Measurement,
        max_distance: u32,
        ratio: f64,
    ) -> Vec<Option<(u32, PointId, usize)>> {
        let mut best: Vec<Option<(u32, PointId, usize)>> = vec![None; m.len()];
        for (kp, pid) in kf.points.iter().enumerate() {
            let Some(pid) = pid else { continue };
            if !self.points.contains_key(pid) {
                continue;
            }
            let Some((bi, b1)) = nearest_descriptor(
                &kf.descriptors[kp],
                m.descriptors.iter().enumerate(),
                max_distance,
                ratio,
            ) else {
                continue;
            };
            if best[bi].is_none_or(|(h, _, _)| b1 < h) {
                best[bi] = Some((b1, *pid, kp));
            }
        }
        best
    }

    /// Keyframes observing any of `points`, plus their best covisible neighbours.
    pub fn local_keyframes(&self, points: impl Iterator<Item = PointId>, max: usize) -> Vec<KfId> {
        let mut votes: BTreeMap<KfId, u32> = BTreeMap::new();
        for pid in points {
            if let Some(p) = self.points.get(&pid) {
                for &kf in p.observations.keys() {
                    *votes.entry(kf).or_default() += 1;
                }
            }
        }
        let mut v: Vec<(KfId, u32)> = votes.into_iter().collect();
        v.sort_by(|a, b| b.1.cmp(&a.1).then(b.0.cmp(&a.0)));
        let mut set: BTreeSet<KfId> = v.iter().take(max).map(|x| x.0).collect();
        let firsts: Vec<KfId> = set.iter().copied().collect();
        for kf in firsts {
            if set.len() >= max {
                break;
            }
            for n in self.keyframes[&kf].best_covisible(5) {
                set.insert(n);
            }
        }
        let mut out: Vec<KfId> = set.into_iter().collect();
        out.truncate(max.max(1) * 2);
        out
    }

    /// Map point in camera coordinates of `pose_cw`.
    pub fn in_camera(pose_cw: &Isometry3<f64>, p: &Vector3<f64>) -> Vector3<f64> {
        (pose_cw * Point3::from(*p)).coords
    }
}
