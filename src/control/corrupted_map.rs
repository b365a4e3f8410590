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
            // When the newest pool was undone and its query map is back as it was, the camera
            // resumes from where it was then (Idle re-tracks a short gap in that map); else
            // its place was only known in the corrupted map, and Idle starts afresh.
            let newest = self
                .atlas
                .pools
                .iter()
                .rev()
                .find(|p| !p.rolled_back)
                .map(|p| p.id);
            match self.before_pool.take() {
                Some(b)
                    if self.atlas.pools[b.pool as usize].rolled_back
                        && newest.is_none_or(|n| n < b.pool)
                        && self.atlas.maps.contains_key(&b.at.map) =>
                {
                    self.resume_tracking(b.at)
                }
                _ => {
                    self.tracker.lose();
                    self.current = None;
                    self.last_tracked_t = None;
                }
            }
        } else {
            let msg = "the map is inconsistent and no closure pool explains it: stopping; \
                       the atlas is marked corrupted";
            tracing::error!("{msg}");
            self.stop_reason = Some(msg.into());
        }
    }

    /// After a recovery found the look-alike keyframes `lookalikes`: the pools still standing
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
                    .any(|(o, w)| *w >= LOOKALIKE_COVISIBILITY && lookalikes.contains(o))
                || shared as f64 / own as f64 >= LOOKALIKE_SHARED
        };
        let standing: Vec<PoolId> = self
            .atlas
            .pools
            .iter()
            .rev()
            .filter(|p| p.undoable())
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
    /// that map are undone, newest first, until the keyframe is gone with one (it was made
    /// on the wrong map) or no longer sees through its map.
    pub(super) fn recover_from_keyframe(&mut self, map: MapId, kf: KfId) -> bool {
        let c = &self.cfg.controller;
        let (min_judged, max_share) = (c.min_expected_cells as usize, c.max_contradiction);
        for p in self.blameable_pools_of(map) {
            if !self.undo_pool(p) {
                continue;
            }
            let Some(m) = self.atlas.map_of_keyframe(kf) else {
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
                let maps: Vec<MapId> = rec
                    .maps()
                    .into_iter()
                    .filter(|m| self.atlas.maps.contains_key(m))
                    .collect();
                maps.into_iter()
                    .all(|m| self.global_optimization(m, None).consistent)
            } else {
                true
            };
            if recovered {
                return true;
            }
        }
        false
    }

    /// Rolls pool `p` back (and the later pools built on it): their alignments are refused
    /// from now on, their anchors marked look-alikes, their rows in closures.csv rolled back.
    /// False when the pool cannot be undone.
    pub(super) fn undo_pool(&mut self, p: PoolId) -> bool {
        if !self
            .atlas
            .pools
            .get(p as usize)
            .is_some_and(|r| r.undoable())
        {
            return false;
        }
        let before = self.atlas.keyframe_ids();
        let undone = match self.atlas.rollback(p) {
            Ok(u) => u,
            Err(e) => {
                tracing::warn!("rollback of pool {p} failed: {e}");
                return false;
            }
        };
        for u in &undone {
            let r = &self.atlas.pools[u.pool as usize];
            match &r.kind {
                PoolKind::Merge {
                    into,
                    from,
                    alignment,
                } => {
                    let s: Sim3 = alignment.into();
                    self.reloc_pool.refuse(*from, *into, s);
                    self.loop_pool.refuse(*from, *into, s);
                }
                PoolKind::Loop { map, correction } => {
                    let s: Sim3 = correction.into();
                    self.loop_pool.refuse(*map, *map, s);
                }
                // No alignment to refuse: its matched keyframes become look-alikes below.
                PoolKind::Relocalization { .. } => {}
            }
            self.mark_aliased(u.pool);
            // Frames tracked after the pool was applied are placed by it; the pool's own frame
            // was tracked before (relative to a keyframe the rollback restores) and stands.
            if let Some(&(_, f)) = self.pool_frames.iter().find(|(q, _)| *q == u.pool) {
                let after = f + 1;
                self.invalidated_from = Some(self.invalidated_from.map_or(after, |x| x.min(after)));
                // Their observations go too: Final may follow in this very step.
                self.frame_obs.forget_from(after);
            }
            for row in self.closures.iter_mut() {
                if row.pool == Some(u.pool) {
                    row.verdict = "rolled-back".into();
                }
            }
            tracing::info!(
                "pool {} rolled back: maps {:?} restored, {} keyframes discarded",
                u.pool,
                u.maps,
                u.discarded_keyframes
            );
        }
        let after = self.atlas.keyframe_ids();
        for gone in before.difference(&after) {
            self.detector.remove(*gone as u64);
        }
        true
    }
}
