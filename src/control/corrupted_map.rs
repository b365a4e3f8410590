//! Corrupted Map: the map is distrusted; the transactions that look-alikes made possible are undone.

use super::StateMachine;
use crate::atlas::{MapId, PoolId, PoolKind};
use crate::geometry::Sim3;
use crate::map::KfId;
use std::collections::{BTreeMap, BTreeSet};

use super::actions::*;

impl StateMachine {
    /// After pool `pool` was rolled back: its matched keyframes and their best covisible
    /// neighbours are look-alikes of the place the camera was really in (see `aliased`).
    pub(super) fn mark_aliased(&mut self, pool: PoolId) {
        let matched: BTreeSet<KfId> = self.atlas.pools[pool as usize]
            .edges
            .iter()
            .map(|e| e.matched)
            .collect();
        tracing::info!("pool {pool} was wrong");
        self.mark_lookalikes(matched);
    }

    /// Keyframes `matched` anchored a wrong closure: they and their best covisible neighbours
    /// are look-alikes of the place the camera was really in, and anchor no more closures.
    pub(super) fn mark_lookalikes(&mut self, matched: BTreeSet<KfId>) {
        let mut marked = matched.clone();
        for kf in &matched {
            if let Some(k) = self
                .atlas
                .map_of_keyframe(*kf)
                .and_then(|id| self.atlas.maps[&id].keyframes.get(kf))
            {
                marked.extend(k.best_covisible(5));
            }
        }
        tracing::info!("keyframes {marked:?} are look-alikes; they anchor no more closures");
        self.aliased.extend(marked);
    }

    /// Corrupted map: undo the pools that explain the inconsistency, newest first, until the
    /// map is consistent again.
    pub(super) fn recover(&mut self) {
        self.flags.able_to_track = false;
        self.merger.poll(&mut self.atlas, true);
        let aliased_before = self.aliased.clone();
        let standing_before: BTreeSet<PoolId> = self
            .atlas
            .pools
            .iter()
            .filter(|p| !p.rolled_back)
            .map(|p| p.id)
            .collect();
        let crossed = self.atlas.loops_across_merges();
        let recovered = if let Some((map, kf)) = self.contradicting_kf.take() {
            self.contradicting_keyframes = 0;
            self.recover_from_keyframe(map, kf)
        } else {
            self.recover_from_pools()
        };
        self.cond.recovered = Some(recovered);
        if recovered {
            // A wrong merge proves two separate places look alike, and other pools anchored
            // there are suspect too. A wrong loop inside one map proves less: in a small scene
            // every keyframe shares points with every other, and the cascade would undo every
            // correct closure of the map (fr1_xyz with noise frames lost 70 % of its map).
            let wrong_merge = standing_before.iter().any(|&p| {
                let rec = &self.atlas.pools[p as usize];
                rec.rolled_back && matches!(rec.kind, PoolKind::Merge { .. })
            });
            if wrong_merge {
                let found: BTreeSet<KfId> =
                    self.aliased.difference(&aliased_before).copied().collect();
                self.undo_pools_anchored_at(&found);
            }
            // A wrong loop between the two sides of a standing merge re-measured what the
            // merge joined, and it could only be closed there because the merge put the
            // look-alike place next to the camera: the merge goes too (the case study with
            // depth weighed by the sensor's noise: door C's wrong merge outlived the loop it
            // led to, whose undo took the contradicting keyframe with it).
            // (`crossed` holds only loops standing before the recovery: one rolled back now
            // was undone by it.)
            // Only a loop the merge made possible implicates it: one that moved the camera by
            // little (the merge had put the look-alike place next to it). A loop that jumped
            // across the scene was proposed by appearance alone, merge or not (small
            // `aliasing` after a 1 s drop: room B, joined to the corridor through the lost
            // place, recognised as room A: a loop of 11 m and 166°; undoing the correct
            // merge with it let room B be merged into room A right after).
            // Without depth the loop was condemned by appearance alone, which says that the
            // map is wrong somewhere, not which pool: the newest goes, and the merge only when
            // the map fails again with it newest (fr1_desk --mono, 1 s dark: a right loop
            // condemned by appearance took the right merge and two right loops with it).
            let crossed = if self.mono { BTreeMap::new() } else { crossed };
            for (&l, merges) in &crossed {
                if !self.atlas.pools[l as usize].rolled_back {
                    continue;
                }
                if let Some((metres, degrees)) = self.atlas.loop_jump(l)
                    && (metres > LOCAL_LOOP_M || degrees > LOCAL_LOOP_DEG)
                {
                    tracing::info!(
                        "pool {l}, a wrong loop across merges {merges:?}, moved its camera {metres:.2} m and {degrees:.1}°: not made possible by a merge, which stands"
                    );
                    continue;
                }
                for &m in merges {
                    if self.atlas.pools[m as usize].undoable() {
                        tracing::info!(
                            "pool {l}, a wrong loop, closed across merge pool {m}'s seam: the merge is undone too"
                        );
                        self.undo_pool(m);
                    }
                }
            }
            self.flags.consistent_map = true;
            self.suspects.clear();
            // The maps the recovery cut are optimised again without the revoked links (those
            // the optimiser's own recovery re-checked already are not).
            let mut maps: BTreeSet<MapId> = BTreeSet::new();
            for r in &self.revocations {
                maps.extend([r.near_map, r.far_map]);
            }
            for m in maps {
                if self.atlas.maps.contains_key(&m) && !self.reoptimized.contains(&m) {
                    self.pose_graph(m);
                }
            }
            self.reoptimized.clear();
            // Nothing was discarded: the camera is where it was, in its side's map, and Idle
            // re-tracks this frame there when the gap allows (else it starts a new map).
            self.tracker.lose();
        } else {
            let msg = "the map is inconsistent and no closure pool explains it: stopping; \
                       the atlas is marked corrupted";
            tracing::error!("{msg}");
            self.stop_reason = Some(msg.into());
        }
    }

    /// After a recovery found the look-alike keyframes `lookalikes`: the merges still standing
    /// whose closures matched the same place (one of those keyframes, or a keyframe sharing
    /// points with one) are undone too. The recovery proved that place ambiguous: a second
    /// closure to it is no better evidence than the one that was wrong, and it may have
    /// nothing left in view that would contradict it.
    pub(super) fn undo_pools_anchored_at(&mut self, lookalikes: &BTreeSet<KfId>) {
        if lookalikes.is_empty() {
            return;
        }
        // With depth, the place is also what the look-alike keyframes saw: a keyframe whose
        // points fall among theirs looks at the same place (from wherever it stood).
        let voxel = |p: &nalgebra::Vector3<f64>| {
            let v = p / LOOKALIKE_VOXEL_M;
            (v.x.floor() as i64, v.y.floor() as i64, v.z.floor() as i64)
        };
        let mut place: BTreeMap<MapId, BTreeSet<(i64, i64, i64)>> = BTreeMap::new();
        if !self.mono {
            for l in lookalikes {
                let Some(m) = self.atlas.map_of_keyframe(*l) else {
                    continue;
                };
                let map = &self.atlas.maps[&m];
                let cells = place.entry(m).or_default();
                for id in map.keyframes[l].points.iter().flatten() {
                    if let Some(p) = map.points.get(id) {
                        cells.insert(voxel(&p.position));
                    }
                }
            }
        }
        let sees_place = |map: &crate::map::Map, kf: KfId| {
            let Some(k) = map.keyframes.get(&kf) else {
                return false;
            };
            let shared = place.get(&map.id).map_or(0, |cells| {
                k.points
                    .iter()
                    .flatten()
                    .filter_map(|id| map.points.get(id))
                    .filter(|p| cells.contains(&voxel(&p.position)))
                    .count()
            });
            let own = k.points.iter().flatten().count().max(1);
            lookalikes.contains(&kf)
                || k.covisibility
                    .iter()
                    .any(|(o, w)| *w >= PLACE_COVISIBILITY && lookalikes.contains(o))
                || shared as f64 / own as f64 >= LOOKALIKE_SHARED
        };
        // Only what claims another map is at that place: a merge (or a relocalization of a
        // lost camera). A loop is its map's own revisit of its own place, which the look-alike
        // says nothing about; it stands on its own evidence (a right loop went with a right
        // merge condemned on a real sensor, #64).
        let standing: Vec<PoolId> = self
            .atlas
            .pools
            .iter()
            .rev()
            .filter(|p| p.undoable() && !matches!(p.kind, PoolKind::Loop { .. }))
            .map(|p| p.id)
            .collect();
        for p in standing {
            let Some(rec) = self.atlas.pools.get(p as usize) else {
                continue;
            };
            if !rec.undoable() {
                continue;
            }
            let anchored = rec.edges.iter().any(|e| {
                self.atlas
                    .map_of_keyframe(e.matched)
                    .is_some_and(|m| sees_place(&self.atlas.maps[&m], e.matched))
            });
            if anchored {
                tracing::info!(
                    "pool {p} matched the look-alike place the recovery found: undone too"
                );
                self.undo_pool(p);
            }
        }
    }

    /// Mapping's depth check condemned keyframe `kf` of map `map`: the pools that changed
    /// that map are revoked, newest first, until the keyframe leaves the map with one (it was
    /// made on the near side of a wrong merge, which is cut) or no longer sees through it.
    pub(super) fn recover_from_keyframe(&mut self, map: MapId, kf: KfId) -> bool {
        let c = &self.cfg.controller;
        let (min_judged, max_share) = (c.min_expected_cells as usize, c.max_contradiction);
        for p in self.blameable_pools_of(map) {
            if !self.undo_pool(p) {
                continue;
            }
            // Split off with the camera's side: the seam it saw through is cut.
            let Some(m) = self.atlas.map_of_keyframe(kf).filter(|m| *m == map) else {
                return true;
            };
            let (judged, through) = self.depth_check_across_pools(m, kf);
            if judged < min_judged || through as f64 / judged as f64 <= max_share {
                return true;
            }
        }
        false
    }

    /// Localized's expectation check or the global optimizer condemned the map: the flagged
    /// pools (or the newest undoable one) are undone, newest first, until the optimizer finds
    /// the maps consistent again.
    pub(super) fn recover_from_pools(&mut self) -> bool {
        let mut order: Vec<PoolId> = if self.suspects.is_empty() {
            self.atlas.last_undoable_pool().into_iter().collect()
        } else {
            self.suspects.clone()
        };
        order.sort_unstable_by(|a, b| b.cmp(a));
        order.dedup();
        let from_optimizer = !self.suspects.is_empty();
        for p in order {
            let Some(rec) = self.atlas.pools.get(p as usize).cloned() else {
                continue;
            };
            if !self.undo_pool(p) {
                continue;
            }
            let recovered = if from_optimizer {
                let _ = rec;
                let maps: BTreeSet<MapId> = self
                    .revocations
                    .last()
                    .map(|r| [r.near_map, r.far_map].into_iter().collect())
                    .unwrap_or_default();
                let maps: Vec<MapId> = maps
                    .into_iter()
                    .filter(|m| self.atlas.maps.contains_key(m))
                    .collect();
                self.reoptimized.extend(maps.iter().copied());
                maps.into_iter()
                    .all(|m| self.global_optimization(m, None, None).consistent)
            } else {
                true
            };
            if recovered {
                return true;
            }
        }
        false
    }

    /// Revokes pool `p` (see `Atlas::revoke`): its links go, and with it the later pools whose
    /// links cross the same seam; every keyframe, point and pose stays. Their alignments are
    /// refused from now on, their anchors are look-alikes, their rows in closures.csv rolled
    /// back. The camera goes on where it is, in the map of its side of the cut, and the frames
    /// tracked across the seam follow it (`Revocation::reanchor`). False when the pool cannot
    /// be revoked.
    pub(super) fn undo_pool(&mut self, p: PoolId) -> bool {
        if !self
            .atlas
            .pools
            .get(p as usize)
            .is_some_and(|r| r.undoable())
        {
            return false;
        }
        let camera_map = self.current;
        let orb = (self.cfg.orb.scale_factor, self.cfg.orb.n_levels);
        let r = match self.atlas.revoke(p, orb, &self.reacquired) {
            Ok(r) => r,
            Err(e) => {
                tracing::warn!("revocation of pool {p} failed: {e}");
                return false;
            }
        };
        for u in std::iter::once(p).chain(r.crossing.iter().copied()) {
            match &self.atlas.pools[u as usize].kind {
                // The near side stands where the wrong alignment put it: that alignment is
                // the identity between the two maps now.
                PoolKind::Merge { .. } | PoolKind::Relocalization { .. } => {
                    self.reloc_pool
                        .refuse(r.near_map, r.far_map, Sim3::identity());
                    self.loop_pool
                        .refuse(r.near_map, r.far_map, Sim3::identity());
                }
                PoolKind::Loop { correction, .. } => {
                    let s: Sim3 = correction.into();
                    self.loop_pool.refuse(r.far_map, r.far_map, s);
                }
            }
            self.mark_aliased(u);
            for row in self.closures.iter_mut() {
                if row.pool == Some(u) {
                    row.verdict = "rolled-back".into();
                }
            }
        }
        tracing::info!(
            "pool {p} revoked{}: map {} (near side) and map {} (far side){}, {} links cut, {} points given back, {} keyframes moved back, nothing discarded",
            if r.crossing.is_empty() {
                String::new()
            } else {
                format!(" with pools {:?}, whose links crossed its seam", r.crossing)
            },
            r.near_map,
            r.far_map,
            r.detached_map.map_or(String::new(), |d| format!(
                ", map {d} (made after the camera was found again at frame {})",
                r.detached_from.unwrap_or_default()
            )),
            r.links_cut,
            r.points_restored,
            r.keyframes_moved
        );
        // The camera goes on in its side's map, where it is.
        if camera_map.is_some_and(|c| c == r.far_map || c == r.near_map) {
            // Before the camera was detached, frames followed the near side; a detached
            // camera goes on in its own map.
            let cam = r.camera_map();
            if self.current != Some(cam) {
                self.merger.started(r.frame);
            }
            self.current = Some(cam);
            self.atlas.activate(cam);
            let map = &self.atlas.maps[&cam];
            // On the camera's side: a loop's far side is in the same map, but the camera is
            // not where the loop put it.
            let on_side = |k: &KfId| {
                map.keyframes.contains_key(k) && (cam != r.near_map || !r.far.contains_key(k))
            };
            let reference = self
                .tracker
                .reference_kf
                .filter(on_side)
                .or_else(|| r.near_anchors.iter().rev().map(|a| a.kf).find(on_side))
                .or_else(|| {
                    map.keyframes
                        .values()
                        .filter(|k| on_side(&k.id))
                        .max_by_key(|k| (k.frame, k.id))
                        .map(|k| k.id)
                });
            if let Some(reference) = reference {
                let correction = r.near_correction.filter(|_| cam == r.near_map);
                self.tracker.reframe(
                    correction.as_ref(),
                    |pt| {
                        let pt = if map.points.contains_key(&pt) && !r.far_points.contains(&pt) {
                            pt
                        } else {
                            r.copy_in(pt, map)?
                        };
                        (map.points.contains_key(&pt) && !r.far_points.contains(&pt)).then_some(pt)
                    },
                    reference,
                );
            }
        }
        self.frame_obs.reanchor(&r, &self.atlas);
        self.revocations.push(r);
        true
    }
}
