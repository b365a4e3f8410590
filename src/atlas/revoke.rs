//! Revoking a transaction (the Corrupted Map state, paper section V: "the wrong loop closures
//! are removed and the graph is optimized again"): the pool's links go, nothing else does.
//!
//! A pool joined two places. A loop joined the place its query keyframes saw to the place they
//! matched, in one map; a merge joined the camera's map (`from`) to another (`into`); a
//! relocalization joined the lost camera to the map it was lost in. Each place is a *side*:
//! the camera's (near) and the one it was matched to (far). Revoking the pool
//! - cuts every link the pool made possible across the two sides: a key point of one side that
//!   sees a point of the other and did not before the pool (the pool's fused points, and what
//!   was tracked and mapped across since). A key point that saw a point of its own before the
//!   pool gets it back; the others share a copy of the point, on their side, where they saw it;
//! - splits the map at the seam when the pool had joined two maps: the far side keeps the map,
//!   the near side becomes a map of its own, where it stands;
//! - for a loop, moves every keyframe back to where it was before the loop's correction, and
//!   the keyframes made since with the keyframe that recognised the place;
//! - revokes with it the later pools whose own links cross the same seam: they measured the
//!   same join, and cannot stand across two maps.
//!
//! Every keyframe and every point stays (decision 0021). The caller re-optimises the maps and
//! re-anchors the frames tracked across the seam (see [`Revocation::reanchor`]).

use super::{Atlas, MapId, PoolId, PoolKind};
use crate::error::{Error, Result};
use crate::geometry::Sim3;
use crate::map::{Keyframe, KfId, Map, MapPoint, PointId};
use nalgebra::{Isometry3, Vector3};
use std::collections::{BTreeMap, BTreeSet};

/// Which side of a revoked pool a keyframe or point is on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Side {
    /// The camera's: the query side of the pool, and what the camera made after it.
    Near = 0,
    /// The place the pool matched the camera to.
    Far = 1,
    /// What the camera made after it lost track and was found again in the joined map by
    /// relocalizing against it: placed by the far side's structure, not by continuity with
    /// the near side, so it is tied to neither and becomes a map of its own.
    Detached = 2,
}

/// A keyframe's pose and units when the pool was revoked (before its geometry moved), for
/// re-anchoring the frames tracked relative to it.
#[derive(Debug, Clone, Copy)]
pub struct Anchor {
    pub kf: KfId,
    /// The frame the keyframe was made from.
    pub frame: usize,
    pub pose_cw: Isometry3<f64>,
    pub units: f64,
}

/// What revoking a pool did.
#[derive(Debug, Clone)]
pub struct Revocation {
    pub pool: PoolId,
    /// The frame the pool was accepted on.
    pub frame: usize,
    /// The map the near side is in now, and the far side's (the same for a loop).
    pub near_map: MapId,
    pub far_map: MapId,
    /// Far-side keyframes, as they were when revoked.
    pub far: BTreeMap<KfId, Anchor>,
    /// Near-side keyframes a frame tracked across the seam can be re-anchored to: the pool's
    /// query keyframe and the near keyframes made since, as they were when revoked.
    pub near_anchors: Vec<Anchor>,
    /// The frame from which the camera was detached (see [`Side::Detached`]), the map its
    /// keyframes since are in, and those keyframes as they were when revoked.
    pub detached_from: Option<usize>,
    pub detached_map: Option<MapId>,
    pub detached_anchors: Vec<Anchor>,
    /// Point → the copies of it made on the other sides, one per side whose key points saw
    /// it across the seam (see [`Revocation::copy_in`]).
    pub copies: BTreeMap<PointId, Vec<PointId>>,
    /// A loop's far-side points (the map is not split: they stay in the camera's map, but
    /// the camera did not see them where the loop said).
    pub far_points: BTreeSet<PointId>,
    /// Observations moved off the other side's points, and points given back to key points
    /// that saw them before the pool fused them away.
    pub links_cut: usize,
    pub points_restored: usize,
    /// Keyframes moved back by a loop's revocation.
    pub keyframes_moved: usize,
    /// Later pools revoked with this one: their links crossed the same seam.
    pub crossing: Vec<PoolId>,
    /// A loop's correction of the near side (current world → restored world), which the
    /// camera follows.
    pub near_correction: Option<Sim3>,
    /// From which frame on the camera was on which side (it starts on the near side; a later
    /// merge may bring it over from a map joined to the far side).
    pub camera: Vec<(usize, Side)>,
}

impl Revocation {
    /// A frame's pose kept relative to keyframe `kf` (`rel`, see `Keyframe::relative_of`), for
    /// frame index `frame`: when the frame was tracked after the pool against a far-side
    /// keyframe, it is re-expressed relative to the near keyframe made last before it (the
    /// camera was on the near side; the far side only looked like its place), as the two
    /// stood when the pool was revoked; with it, the ratio of the two keyframes' creation
    /// units (what converts the frame's other relative quantities). `None`: nothing to
    /// change, also when no near keyframe can hold it (a relocalization revoked before the
    /// camera mapped anything): the frame stays posed where it was tracked, on the far side,
    /// since the camera's side has nothing to place it by, and a revocation discards nothing
    /// that was tracked (issue #77).
    pub fn reanchor(
        &self,
        frame: usize,
        kf: KfId,
        rel: &Isometry3<f64>,
    ) -> Option<(KfId, Isometry3<f64>, f64)> {
        if frame < self.frame || self.camera_side(frame) != Side::Near {
            return None;
        }
        let far = self.far.get(&kf)?;
        let detached = self.detached_from.is_some_and(|d| frame >= d);
        let pick = |anchors: &'_ [Anchor]| {
            anchors
                .iter()
                .filter(|a| a.frame <= frame)
                .max_by_key(|a| (a.frame, a.kf))
                .or_else(|| anchors.first())
                .copied()
        };
        let near = if detached {
            pick(&self.detached_anchors).or_else(|| pick(&self.near_anchors))
        } else {
            pick(&self.near_anchors)
        };
        let near = near?;
        // Absolute pose as it stood, then relative to the near keyframe (creation units).
        let mut r = *rel;
        r.translation.vector *= far.units;
        let pose_cw = r * far.pose_cw;
        let mut out = pose_cw * near.pose_cw.inverse();
        out.translation.vector /= near.units;
        Some((near.kf, out, far.units / near.units))
    }
}

impl Revocation {
    /// The copy of point `p` that map `map` holds, if the revocation made one there.
    pub fn copy_in(&self, p: PointId, map: &Map) -> Option<PointId> {
        self.copies
            .get(&p)?
            .iter()
            .copied()
            .find(|c| map.points.contains_key(c))
    }

    /// The side the camera was on at frame `frame` (at or after the pool's).
    pub fn camera_side(&self, frame: usize) -> Side {
        self.camera
            .iter()
            .rev()
            .find(|(f, _)| *f <= frame)
            .map_or(Side::Near, |(_, s)| *s)
    }

    /// The map the camera is in after the revocation.
    pub fn camera_map(&self) -> MapId {
        match self.camera.last().map_or(Side::Near, |c| c.1) {
            Side::Near | Side::Detached => self.detached_map.unwrap_or(self.near_map),
            Side::Far => self.far_map,
        }
    }
}

/// Whether a keyframe moved by `c` moved with the anchor (moved by `a`) rather than stayed:
/// at the keyframe's centre, the two corrections differ by less than half of what the anchor's
/// correction moved the anchor.
fn moved_with(c: &Sim3, a: &Sim3, centre: &Vector3<f64>, jump: (f64, f64)) -> bool {
    let dt = (c.transform_point(centre) - a.transform_point(centre)).norm();
    let dr = (c.rotation * a.rotation.inverse()).angle();
    dt <= 0.5 * jump.0 + 1e-9 && dr <= 0.5 * jump.1 + 1e-9
}

/// `k`'s pose and units in another world (`r`: old world → new), as `Atlas::merge` moves them.
fn reframed(k: &Keyframe, r: &Sim3) -> (Isometry3<f64>, f64) {
    (r.transform_pose_cw(&k.pose_cw), k.units * r.scale)
}

/// The world correction (current world → restored world) that takes a keyframe at `now`
/// (units `u_now`) to `target` (units `u_target`): a point keeps its coordinates in the
/// keyframe's camera frame, in that frame's units.
fn correction_to(now: &Isometry3<f64>, u_now: f64, target: &Isometry3<f64>, u_target: f64) -> Sim3 {
    let scaling = Sim3 {
        scale: u_target / u_now,
        ..Sim3::identity()
    };
    Sim3::from_isometry(target)
        .inverse()
        .compose(&scaling)
        .compose(&Sim3::from_isometry(now))
}

/// Moves keyframe `k` by the world correction `c` (old world → new), as the pose graph's
/// corrections move keyframes (`global_optimizer::apply`).
fn move_keyframe(k: &mut Keyframe, c: &Sim3) {
    let new = Sim3::from_isometry(&k.pose_cw).compose(&c.inverse());
    let mut pose = new.to_isometry();
    pose.translation.vector /= new.scale;
    pose.rotation.renormalize();
    k.pose_cw = pose;
    k.units /= new.scale;
    for i in 3..6 {
        k.twist[i] /= new.scale;
    }
}

/// A point to create on a key point's side: where the key point's keyframe saw it (camera
/// coordinates and that frame's units at the time), its id and its template.
struct NewPoint {
    id: PointId,
    template: MapPoint,
    seen_from: KfId,
    in_camera: Vector3<f64>,
    units: f64,
    observations: Vec<(KfId, usize)>,
}

impl Atlas {
    /// Revokes pool `pool` (see the module's doc). `orb`: the ORB pyramid's scale factor and
    /// level count, to refresh the points whose observations changed.
    /// `reacquired`: the frames on which the camera, lost, was found again in its map by
    /// relocalizing against it (not by its motion model): from the first after the pool, what
    /// it made is [`Side::Detached`].
    pub fn revoke(
        &mut self,
        pool: PoolId,
        orb: (f64, u32),
        reacquired: &[usize],
    ) -> Result<Revocation> {
        let Some(rec) = self.pools.get(pool as usize).cloned() else {
            return Err(Error::invalid(format!("revoke: no pool {pool}")));
        };
        if !rec.undoable() {
            return Err(Error::invalid(format!(
                "revoke: pool {pool} cannot be revoked (already revoked, or from a loaded session)"
            )));
        }
        let before_kf: BTreeMap<KfId, MapId> = rec
            .before
            .iter()
            .flat_map(|m| m.keyframes.keys().map(move |k| (*k, m.id)))
            .collect();
        let anchor_kf = rec.edges.last().map(|e| e.query);
        // The map the pool's keyframes are in now: the anchor's, else most of them.
        let j = anchor_kf.and_then(|a| self.map_of_keyframe(a)).or_else(|| {
            let mut count: BTreeMap<MapId, usize> = BTreeMap::new();
            for k in before_kf.keys() {
                if let Some(m) = self.map_of_keyframe(*k) {
                    *count.entry(m).or_default() += 1;
                }
            }
            count.into_iter().max_by_key(|(m, n)| (*n, *m)).map(|x| x.0)
        });
        let Some(j) = j else {
            // Nothing of it is left to cut (its maps were split by another revocation).
            self.retire(pool);
            return Ok(Revocation {
                pool,
                frame: rec.frame,
                near_map: 0,
                far_map: 0,
                far: BTreeMap::new(),
                near_anchors: Vec::new(),
                detached_from: None,
                detached_map: None,
                detached_anchors: Vec::new(),
                copies: BTreeMap::new(),
                far_points: BTreeSet::new(),
                links_cut: 0,
                points_restored: 0,
                keyframes_moved: 0,
                crossing: Vec::new(),
                near_correction: None,
                camera: vec![(rec.frame, Side::Near)],
            });
        };
        self.refresh_high_water();
        let reframe: Sim3 = rec.reframed.as_ref().map_or(Sim3::identity(), Sim3::from);
        let skeleton_kf =
            |k: KfId| -> Option<&Keyframe> { rec.before.iter().find_map(|m| m.keyframes.get(&k)) };
        let map = &self.maps[&j];

        // --- Sides of the keyframes, and a loop's corrections back to before it.
        let mut side: BTreeMap<KfId, Side> = BTreeMap::new();
        // Every keyframe older than the pool goes back to where it was before the pool's
        // optimisation bent the map (a merged map's keyframes where the pool's alignment put
        // them); what the camera made since follows the keyframe that recognised the place.
        let mut corrections: BTreeMap<KfId, Sim3> = BTreeMap::new();
        let merged = match &rec.kind {
            PoolKind::Merge {
                from, alignment, ..
            } => Some((*from, Sim3::from(alignment))),
            _ => None,
        };
        for (id, k) in &map.keyframes {
            let Some((m, s)) = rec
                .before
                .iter()
                .find_map(|m| m.keyframes.get(id).map(|s| (m.id, s)))
            else {
                continue;
            };
            let world = match merged {
                Some((from, alignment)) if from == m => reframe.compose(&alignment),
                _ => reframe,
            };
            let (target, units) = reframed(s, &world);
            corrections.insert(*id, correction_to(&k.pose_cw, k.units, &target, units));
        }
        let a = anchor_kf.and_then(|a| corrections.get(&a).copied());
        let near_correction = a;
        let a = a.unwrap_or_else(Sim3::identity);
        let mut camera_sides = vec![(rec.frame, Side::Near)];
        let detached_from = reacquired.iter().copied().find(|f| *f > rec.frame);
        // A keyframe the camera made at frame `f` while on side `camera`.
        let made_by_camera = |f: usize, camera: Side| match (camera, detached_from) {
            (Side::Near, Some(d)) if f >= d => Side::Detached,
            _ => camera,
        };
        match &rec.kind {
            PoolKind::Loop { .. } => {
                let jump = anchor_kf
                    .and_then(|a| map.keyframes.get(&a))
                    .map_or((0.0, 0.0), |k| {
                        let c = k.center();
                        ((a.transform_point(&c) - c).norm(), a.rotation.angle())
                    });
                for (id, k) in &map.keyframes {
                    let s = match corrections.get(id) {
                        Some(c) if !moved_with(c, &a, &k.center(), jump) => Side::Far,
                        Some(_) => Side::Near,
                        // Made after the loop: with the camera.
                        None => {
                            let s = made_by_camera(k.frame, Side::Near);
                            if s == Side::Near {
                                corrections.insert(*id, a);
                            }
                            s
                        }
                    };
                    side.insert(*id, s);
                }
                for e in &rec.edges {
                    if side.contains_key(&e.matched) {
                        side.insert(e.matched, Side::Far);
                    }
                    if side.contains_key(&e.query) {
                        side.insert(e.query, Side::Near);
                    }
                }
            }
            PoolKind::Merge { into, .. } | PoolKind::Relocalization { map: into } => {
                for (k, m) in &before_kf {
                    if map.keyframes.contains_key(k) {
                        let far = m == into;
                        side.insert(*k, if far { Side::Far } else { Side::Near });
                    }
                }
                // What joined the map since: the keyframes the camera made sit on its side;
                // a map merged in later sits on the side its pool's links reached.
                let mut camera = Side::Near;
                for q in self.pools.iter().filter(|q| q.id > pool && q.undoable()) {
                    let PoolKind::Merge { into, from, .. } = q.kind else {
                        continue;
                    };
                    let sk = |id: MapId| q.before.iter().find(|m| m.id == id);
                    let (Some(si), Some(sf)) = (sk(into), sk(from)) else {
                        continue;
                    };
                    let sided = |m: &Map| m.keyframes.keys().any(|k| side.contains_key(k));
                    let (lineage, foreign, camera_came) = if sided(sf) {
                        (sf, si, false)
                    } else if sided(si) {
                        (si, sf, true)
                    } else {
                        continue;
                    };
                    for (k, kf) in &lineage.keyframes {
                        if map.keyframes.contains_key(k) {
                            side.entry(*k).or_insert(made_by_camera(kf.frame, camera));
                        }
                    }
                    let mut votes = [0usize; 3];
                    for e in &q.edges {
                        for k in [e.query, e.matched] {
                            if lineage.keyframes.contains_key(&k)
                                && let Some(s) = side.get(&k)
                            {
                                votes[*s as usize] += 1;
                            }
                        }
                    }
                    let fs = if votes[Side::Far as usize] > votes[Side::Near as usize] {
                        Side::Far
                    } else {
                        Side::Near
                    };
                    for k in foreign.keyframes.keys() {
                        if map.keyframes.contains_key(k) {
                            side.entry(*k).or_insert(fs);
                        }
                    }
                    if camera_came {
                        camera = fs;
                        camera_sides.push((q.frame, fs));
                    }
                }
                for (k, kf) in &map.keyframes {
                    side.entry(*k).or_insert(made_by_camera(kf.frame, camera));
                }
                // Made since: the near side's with the camera, the far side's stay.
                for (k, s) in &side {
                    if !corrections.contains_key(k) && *s == Side::Near {
                        corrections.insert(*k, a);
                    }
                }
            }
        }
        // A merge's (or relocalization's) two sides become two maps again; what the camera
        // made detached becomes a map of its own, whatever the pool.
        let split = !matches!(rec.kind, PoolKind::Loop { .. })
            && side.values().any(|s| *s == Side::Near)
            && side.values().any(|s| *s == Side::Far);
        let apart =
            |a: Side, b: Side| a != b && (split || a == Side::Detached || b == Side::Detached);

        // --- Sides of the points: their creator's, else most of their observers'.
        let kf_side = |k: &KfId| side.get(k).copied();
        let mut point_side: BTreeMap<PointId, Side> = BTreeMap::new();
        for (id, p) in &map.points {
            let s = kf_side(&p.first_kf).unwrap_or_else(|| {
                let mut votes = [0usize; 3];
                for k in p.observations.keys() {
                    if let Some(s) = kf_side(k) {
                        votes[s as usize] += 1;
                    }
                }
                [Side::Near, Side::Far, Side::Detached]
                    .into_iter()
                    .max_by_key(|s| (votes[*s as usize], std::cmp::Reverse(*s as usize)))
                    .expect("three sides")
            });
            point_side.insert(*id, s);
        }

        // --- The links to cut, and the points that take them, located where their key
        // point's keyframe saw them (camera coordinates, as the map stands now).
        let existing: BTreeSet<PointId> = self
            .maps
            .values()
            .flat_map(|m| m.points.keys().copied())
            .collect();
        let mut next_point = self.high_water.1;
        let mut new_points: BTreeMap<PointId, NewPoint> = BTreeMap::new();
        // One copy per side that saw the point across the seam: the sides become maps of
        // their own, and a copy shared by two would leave one side's key points referring to
        // a point of another map (fr1_desk, a right merge revoked after the camera was found
        // again: the near side's and the detached side's key points shared one copy, and the
        // detached map's next local BA found a keyframe point missing).
        let mut copies: BTreeMap<(PointId, Side), PointId> = BTreeMap::new();
        let mut cuts: Vec<(KfId, usize, PointId, PointId)> = Vec::new();
        let mut points_restored = 0;
        for (kid, k) in &map.keyframes {
            let ks = side[kid];
            for (kp, p) in k.points.iter().enumerate() {
                let Some(p) = *p else { continue };
                let Some(&ps) = point_side.get(&p) else {
                    continue;
                };
                if ps == ks {
                    continue;
                }
                let skel = skeleton_kf(*kid);
                let had = skel.and_then(|s| s.points.get(kp).copied().flatten());
                // A link older than the pool stands (a loop's two ends may share points
                // legitimately), unless the two go to different maps.
                if had == Some(p) && !apart(ks, ps) {
                    continue;
                }
                let in_camera = k.pose_cw * nalgebra::Point3::from(map.points[&p].position);
                let restorable = had.filter(|x| *x != p && !existing.contains(x));
                let target = match restorable {
                    Some(x) => {
                        if let std::collections::btree_map::Entry::Vacant(e) = new_points.entry(x) {
                            let s = skel.expect("had a skeleton");
                            let xp = rec
                                .before
                                .iter()
                                .find_map(|m| m.points.get(&x))
                                .expect("the skeleton's point");
                            let cam = s.pose_cw * nalgebra::Point3::from(xp.position);
                            e.insert(NewPoint {
                                id: x,
                                template: xp.clone(),
                                seen_from: *kid,
                                in_camera: cam.coords * (k.units / s.units),
                                units: k.units,
                                observations: Vec::new(),
                            });
                            points_restored += 1;
                        }
                        x
                    }
                    None => *copies.entry((p, ks)).or_insert_with(|| {
                        let id = next_point;
                        next_point += 1;
                        new_points.insert(
                            id,
                            NewPoint {
                                id,
                                template: map.points[&p].clone(),
                                seen_from: *kid,
                                in_camera: in_camera.coords,
                                units: k.units,
                                observations: Vec::new(),
                            },
                        );
                        id
                    }),
                };
                new_points
                    .get_mut(&target)
                    .expect("just made")
                    .observations
                    .push((*kid, kp));
                cuts.push((*kid, kp, p, target));
            }
        }
        for np in new_points.values() {
            point_side.insert(np.id, side[&np.seen_from]);
        }

        // --- Apply: the pool and the later ones across its seam stop standing.
        let mut crossing = Vec::new();
        {
            for q in self.pools.iter().filter(|q| q.id > pool && q.undoable()) {
                let across = q.edges.iter().any(|e| {
                    matches!((kf_side(&e.query), kf_side(&e.matched)), (Some(a), Some(b)) if apart(a, b))
                });
                if across {
                    crossing.push(q.id);
                }
            }
        }
        let anchor = |k: &Keyframe| Anchor {
            kf: k.id,
            frame: k.frame,
            pose_cw: k.pose_cw,
            units: k.units,
        };
        let side_of = &side;
        let on = |s: Side| map.keyframes.values().filter(move |k| side_of[&k.id] == s);
        let far_anchors: BTreeMap<KfId, Anchor> =
            on(Side::Far).map(|k| (k.id, anchor(k))).collect();
        let mut near_anchors: Vec<Anchor> = on(Side::Near)
            .filter(|k| Some(k.id) == anchor_kf || !before_kf.contains_key(&k.id))
            .map(anchor)
            .collect();
        let detached_anchors: Vec<Anchor> = on(Side::Detached).map(anchor).collect();
        if near_anchors.is_empty()
            && let Some(k) = on(Side::Near).max_by_key(|k| (k.frame, k.id))
        {
            near_anchors.push(anchor(k));
        }

        let map = self.maps.get_mut(&j).expect("checked");
        let links_cut = cuts.len();
        let mut touched: BTreeSet<PointId> = BTreeSet::new();
        for (kf, kp, old, _) in &cuts {
            if let Some(p) = map.points.get_mut(old) {
                p.observations.remove(kf);
                touched.insert(*old);
            }
            if let Some(k) = map.keyframes.get_mut(kf) {
                k.points[*kp] = None;
            }
        }
        // A loop's geometry: keyframes back where they were before its correction, points
        // with their reference keyframe (as the pose graph moves them).
        let mut keyframes_moved = 0;
        for (id, c) in &corrections {
            if let Some(k) = map.keyframes.get_mut(id) {
                move_keyframe(k, c);
                keyframes_moved += 1;
            }
        }
        if !corrections.is_empty() {
            crate::components::global_optimizer::move_points(map, &corrections);
        }
        for np in new_points.into_values() {
            let k = &map.keyframes[&np.seen_from];
            let cam = np.in_camera * (k.units / np.units);
            let position = k.pose_cw.inverse() * nalgebra::Point3::from(cam);
            let mut p = np.template;
            p.id = np.id;
            p.position = position.coords;
            p.observations = BTreeMap::new();
            p.first_kf = np.seen_from;
            p.visible = p.visible.max(1);
            p.found = p.found.max(1);
            map.insert_point(p);
            for (kf, kp) in np.observations {
                map.observe(kf, kp, np.id);
            }
            touched.insert(np.id);
        }
        for id in &touched {
            let empty = map
                .points
                .get(id)
                .is_some_and(|p| p.observations.is_empty());
            if empty {
                map.points.remove(id);
            } else if map.points.contains_key(id) {
                if map.points[id]
                    .observations
                    .contains_key(&map.points[id].first_kf)
                {
                } else if let Some(first) = map.points[id].observations.keys().next().copied() {
                    map.points.get_mut(id).expect("present").first_kf = first;
                }
                map.update_point(*id, orb.0, orb.1);
            }
        }

        // --- Split at the seam: the near side becomes a map of its own (a merge's or a
        // relocalization's), and so does what the camera made detached.
        let far_map = j;
        let mut near_map = j;
        let mut detached_map = None;
        let mut parts = Vec::new();
        if split {
            parts.push(Side::Near);
        }
        if side.values().any(|s| *s == Side::Detached) {
            parts.push(Side::Detached);
        }
        for part in parts {
            let id = match (part, &rec.kind) {
                (Side::Near, PoolKind::Merge { from, .. }) if !self.maps.contains_key(from) => {
                    *from
                }
                _ => {
                    let id = self.next_map;
                    self.next_map += 1;
                    id
                }
            };
            let map = self.maps.get_mut(&j).expect("checked");
            let mut moved = Map::new(id);
            let kfs: Vec<KfId> = map
                .keyframes
                .keys()
                .filter(|k| side[k] == part)
                .copied()
                .collect();
            for k in kfs {
                let kf = map.keyframes.remove(&k).expect("listed");
                moved.keyframes.insert(k, kf);
            }
            let points: Vec<PointId> = map
                .points
                .iter()
                .filter(|(id, p)| {
                    p.observations
                        .keys()
                        .next()
                        .is_some_and(|k| moved.keyframes.contains_key(k))
                        || (p.observations.is_empty() && point_side.get(id) == Some(&part))
                })
                .map(|(id, _)| *id)
                .collect();
            for p in points {
                let pt = map.points.remove(&p).expect("listed");
                moved.insert_point(pt);
            }
            self.maps.insert(id, moved);
            match part {
                Side::Near => near_map = id,
                _ => detached_map = Some(id),
            }
        }
        self.high_water.1 = self.high_water.1.max(next_point);
        for m in [Some(far_map), Some(near_map), detached_map]
            .into_iter()
            .flatten()
        {
            let hw = self.high_water;
            if let Some(map) = self.maps.get_mut(&m) {
                map.reserve_ids(hw);
                for k in map.keyframes.values_mut() {
                    k.covisibility.clear();
                }
                let ids: Vec<KfId> = map.keyframes.keys().copied().collect();
                for k in ids {
                    map.update_covisibility(k);
                }
            }
        }
        let far_points: BTreeSet<PointId> = if split || near_map != far_map {
            BTreeSet::new()
        } else {
            point_side
                .iter()
                .filter(|(_, s)| **s == Side::Far)
                .map(|(p, _)| *p)
                .collect()
        };
        self.retire(pool);
        for q in &crossing {
            self.retire(*q);
        }
        self.refresh_high_water();
        Ok(Revocation {
            pool,
            frame: rec.frame,
            near_map,
            far_map,
            far: far_anchors,
            near_anchors,
            detached_from: detached_map.and(detached_from),
            detached_map,
            detached_anchors,
            copies: copies
                .into_iter()
                .fold(BTreeMap::new(), |mut out, ((p, _), c)| {
                    out.entry(p).or_insert_with(Vec::new).push(c);
                    out
                }),
            far_points,
            links_cut,
            points_restored,
            keyframes_moved,
            crossing,
            near_correction,
            camera: camera_sides,
        })
    }

    /// Marks pool `pool` revoked and lets its skeletons go.
    fn retire(&mut self, pool: PoolId) {
        if let Some(p) = self.pools.get_mut(pool as usize) {
            p.rolled_back = true;
            p.before = Vec::new();
            p.reframed = None;
        }
    }
}
