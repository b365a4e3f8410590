//! Localized: the accepted pool as an atlas transaction (merge, closure edges, global optimisation and its consistency check), then tracking in known space without new keyframes.

use super::StateMachine;
use crate::atlas::{ClosureEdge, MapId, PoolKind};
use crate::components::global_optimizer::{self, GlobalReport};
use crate::components::loop_validator::{self, Accepted, relative_information};
use crate::components::preprocess::Measurement;
use crate::geometry::Sim3;
use crate::map::KfId;
use crate::outputs::Timing;
use std::collections::BTreeSet;

use super::actions::*;

/// A merge's pool and its two sides before it: the camera's map's keyframes and the other's.
type Seam = (crate::atlas::PoolId, BTreeSet<KfId>, BTreeSet<KfId>);

/// Keyframes `seeds` of `map` and their 10 best covisible ones: the neighbourhood a closure
/// fuses across (`fuse_closure`), and so the place a merge ties by itself.
fn around(map: &crate::map::Map, seeds: impl IntoIterator<Item = KfId>) -> BTreeSet<KfId> {
    let mut set = BTreeSet::new();
    for k in seeds {
        if let Some(kf) = map.keyframes.get(&k) {
            set.insert(k);
            set.extend(kf.best_covisible(10));
        }
    }
    set
}

/// Keyframe `q`'s key points take the points they were matched to (`matches`, one per key
/// point): an own point is replaced by the match, a key point without one observes it.
/// Returns how many were fused.
fn fuse_matches(
    map: &mut crate::map::Map,
    q: KfId,
    matches: &[Option<crate::map::PointId>],
) -> usize {
    let mut fused = 0;
    for (i, target) in matches.iter().enumerate() {
        let Some(target) = target else { continue };
        if !map.points.contains_key(target) {
            continue;
        }
        let own = map
            .keyframes
            .get(&q)
            .and_then(|k| k.points.get(i).copied().flatten());
        match own {
            Some(p) if p != *target => {
                map.replace_point(p, *target);
                fused += 1;
            }
            None if map.observe(q, i, *target) => fused += 1,
            _ => {}
        }
    }
    if map.keyframes.contains_key(&q) {
        map.update_covisibility(q);
    }
    fused
}

impl StateMachine {
    /// Localized's entry: the accepted pool becomes an atlas transaction — maps merged if it
    /// links two, closure edges added, global optimisation with its consistency check — and the
    /// tracker continues from the best-matching local map.
    pub(super) fn localize(&mut self, m: &Measurement, timing: &mut Timing) {
        self.flags.able_to_localize = false;
        if self.relocalized_in_idle.is_none() && self.accepted.is_none() {
            return;
        }
        for ms in self.merger.poll(&mut self.atlas, true) {
            timing.record("local_ba_thread", ms);
        }
        if let Some(acc) = self.relocalized_in_idle.take() {
            self.relocalized(acc, m);
            return;
        }
        let Some(acc) = self.accepted.take() else {
            return;
        };
        let (into, from) = (acc.match_map, acc.query_map);
        // Closure edges, computed in the query map's frame before any merge.
        let mut edges = Vec::new();
        for v in &acc.members {
            let Some(q_map) = self.atlas.maps.get(&from) else {
                continue;
            };
            let Some(m_kf) = self
                .atlas
                .maps
                .get(&into)
                .and_then(|mm| mm.keyframes.get(&v.matched))
            else {
                continue;
            };
            // The query's keyframe: itself (loop) or the frame's reference keyframe.
            let r = v.reference_kf.or(self.tracker.reference_kf);
            let Some(r_kf) = r.and_then(|r| q_map.keyframes.get(&r)) else {
                continue;
            };
            // Reference keyframe → matched keyframe: the query camera's offset from its
            // reference keyframe, rescaled to the matched map's lengths (monocular), then the
            // query camera in the matched map. After a merge the reference keyframe's frame is
            // in the matched map's lengths already; within one map the scale is measured.
            let mut t_qr = v.query_pose * r_kf.pose_cw.inverse();
            t_qr.translation.vector *= v.scale;
            let rel = m_kf.pose_cw * v.pose_in_match.inverse() * t_qr;
            let (scale, units_after_merge) = if into == from {
                (v.scale, 1.0)
            } else {
                (1.0, v.scale)
            };
            let z = Sim3 {
                scale,
                ..Sim3::from_isometry(&rel)
            };
            edges.push(ClosureEdge::new(
                0,
                r_kf.id,
                v.matched,
                &z,
                (m_kf.units, r_kf.units * units_after_merge),
                relative_information(&rel, &v.information),
            ));
        }
        let kind = if into == from {
            PoolKind::Loop {
                map: into,
                correction: (&acc.alignment).into(),
            }
        } else {
            PoolKind::Merge {
                into,
                from,
                alignment: (&acc.alignment).into(),
            }
        };
        let pool = self.atlas.begin_pool(kind, m.frame, m.t);
        for e in edges.iter_mut() {
            e.pool = pool;
        }
        self.atlas.add_edges(pool, edges);
        let mut seam = None;
        if into != from {
            // What only the map merged into saw: the merge is provisional until the camera
            // re-observes some of it.
            let unheld = match (self.atlas.maps.get(&into), self.atlas.maps.get(&from)) {
                (Some(i), Some(f)) => {
                    let place = global_optimizer::place_of(
                        i,
                        acc.members.iter().map(|v| v.matched),
                        PLACE_COVISIBILITY,
                    );
                    global_optimizer::unheld_points(&self.geo, i, f, &acc.alignment, &place)
                }
                _ => BTreeSet::new(),
            };
            tracing::debug!(
                "frame {}: merge pool {pool}: {} of map {into}'s points lie beyond the merged place",
                m.frame,
                unheld.len()
            );
            if let Some(rec) = self.atlas.pools.get_mut(pool as usize) {
                rec.evidence = Some(crate::atlas::MergeEvidence {
                    unheld,
                    ..Default::default()
                });
            }
            let sides = |id: MapId| -> BTreeSet<KfId> {
                self.atlas
                    .maps
                    .get(&id)
                    .map(|mm| mm.keyframes.keys().copied().collect())
                    .unwrap_or_default()
            };
            // The place the merge itself ties (the query side's keyframes and their covisible
            // ones, which `fuse_closure` fuses across): the seam is what lies beyond it.
            let place = self
                .atlas
                .maps
                .get(&from)
                .map(|q| {
                    around(
                        q,
                        acc.members
                            .iter()
                            .filter_map(|v| v.query_kf.or(v.reference_kf)),
                    )
                })
                .unwrap_or_default();
            let near: BTreeSet<KfId> = sides(from).difference(&place).copied().collect();
            let far = sides(into);
            if let Err(e) = self.atlas.merge(into, from, &acc.alignment) {
                tracing::warn!("merge failed: {e}");
                return;
            }
            tracing::info!("frame {}: map {from} merged into map {into}", m.frame);
            seam = Some((pool, near, far));
        }
        self.settle_pending_rows(&acc, "accepted", Some(pool));
        let last = acc.members.last().expect("a pool has members");
        let anchor_before = self.atlas.maps[&into]
            .keyframes
            .get(&last.matched)
            .map(|k| k.pose_cw);
        // A frame that recognised an older part of its own map keeps its pose relative to its
        // reference keyframe (the optimisation moved both together), but tracks on from the
        // matched keyframe (ORB-SLAM after a relocalization): the local map is then the old
        // keyframes the camera is back among, so new keyframes, if any, observe the old points
        // instead of duplicating them.
        // A frame validated from its own depth (`Valid::own_points`) tracks on from its own
        // points and reference keyframe, now part of the joined map.
        let own_ref = last
            .reference_kf
            .filter(|_| (into == from && last.query_kf.is_none()) || last.own_points);
        let own_ref_before = own_ref
            .and_then(|r| self.atlas.maps[&into].keyframes.get(&r))
            .map(|k| k.pose_cw);
        let report = timing.time("global_opt", || {
            self.global_optimization(into, Some(&acc), seam.as_ref())
        });
        self.flags.consistent_map = report.consistent;
        self.suspects = report.offending_pools;
        // The map was consistent until this pool came: it is a suspect too, whichever older
        // pool the optimiser blames, and the recovery tries it first (newest first). An older
        // pool has already agreed with every pool accepted since; undoing it undoes those too
        // and discards their keyframes (`revisit` with the view angle at 15° and 5 % black
        // frames: a closure after a re-acquired keyframe had pool 3 of 14 blamed, and undoing
        // pools 3-14 left 39 % of the frames posed; undoing pool 14 alone was consistent: 94 %).
        if !report.consistent && !self.suspects.contains(&pool) {
            self.suspects.push(pool);
        }
        // The tracker continues at the newest member's pose (a loop's query keyframe as
        // optimised; a relocalized frame relative to its matched keyframe, which the
        // optimisation may have moved).
        let map = &self.atlas.maps[&into];
        // The query's pose in the map it is now part of (a merge moved its map).
        let query_now = if into == from {
            last.query_pose
        } else {
            last.query_pose * acc.alignment.to_isometry().inverse()
        };
        let own = match (own_ref, own_ref_before) {
            (Some(r), Some(before)) => map.keyframes.get(&r).map(|after| {
                (
                    query_now * before.inverse() * after.pose_cw,
                    if last.own_points { r } else { last.matched },
                )
            }),
            _ => None,
        };
        // A frame whose own map was just merged into the matched one (its points are part of
        // the joined map now, its velocity rescaled by the merge), and without depth a frame
        // that closed a loop in its own map, tracks on with its motion model (see
        // `Tracker::closed_in_place`). A reset leaves the next frame to the matched keyframe's
        // descriptors alone, and a keyframe validated by projection (a re-check) is one the
        // frame matched too few descriptors of: fr1_desk RGB-D, two drops, was lost the frame
        // after such a merge. An RGB-D loop keeps the reset: its re-tracking from the matched
        // keyframe uses depth and was not lost after a loop (fr1_desk with the preset: 15
        // closures).
        let in_place = last.frame == m.frame
            && ((self.mono && into == from && own.is_some())
                || (into != from && self.current == Some(from)));
        let (pose, ref_kf) = match (own, last.query_kf.and_then(|k| map.keyframes.get(&k))) {
            (Some(o), _) => o,
            (None, Some(k)) => (k.pose_cw, k.id),
            (None, None) => match (anchor_before, map.keyframes.get(&last.matched)) {
                (Some(before), Some(after)) => (
                    last.pose_in_match * before.inverse() * after.pose_cw,
                    last.matched,
                ),
                _ => (last.pose_in_match, last.matched),
            },
        };
        let scale = if into == from {
            1.0
        } else {
            acc.alignment.scale
        };
        self.current = Some(into);
        self.atlas.activate(into);
        let matches = last.matches.clone();
        if in_place {
            self.tracker.closed_in_place(pose, &matches, ref_kf, scale);
        } else {
            self.tracker.reset(pose, m.t, &matches, ref_kf);
        }
        if into == from {
            // The same map goes on: its recent points still await culling.
            self.merger.closed(m.frame);
        } else {
            self.merger.started(m.frame);
        }
        self.start_localized();
    }

    /// What every Localized entry starts from: no pending candidates, no failed expectations,
    /// no inlier peak yet, in known space.
    fn start_localized(&mut self) {
        self.reloc_pool.clear();
        self.loop_pool.clear();
        self.expectation_failures = 0;
        self.localized_peak_inliers = 0;
        self.unknown_view_frames = 0;
        self.cond.left_known_area = false;
    }

    /// Localized's entry for a pool of frames relocalized in the map they were lost in (see
    /// `relocalize_in_lost_map`): nothing to merge or optimise, and the tracker is there
    /// already; the pool is recorded so that a rollback can undo it and what is mapped on it.
    /// Undone, the camera is lost again (Idle starts afresh).
    fn relocalized(&mut self, acc: Accepted, m: &Measurement) {
        let map = acc.match_map;
        let pool = self
            .atlas
            .begin_pool(PoolKind::Relocalization { map }, m.frame, m.t);
        self.settle_pending_rows(&acc, "accepted", Some(pool));
        self.merger.closed(m.frame);
        self.start_localized();
    }

    /// The merge's other overlaps ([`loop_validator::seam_pairs`]): each keyframe of the
    /// camera's side (`near`) that sees a scene a keyframe of the other side (`far`) saw is
    /// validated against it in the joined map, as the pose graph has just placed them. The
    /// valid pairs are closure edges of the merge's pool (revoked with it); the pose graph is
    /// tried again with them on a copy of the map, and only if it stays consistent are they
    /// kept, the copy adopted and their matches fused, so that the full BA that follows holds
    /// the two sides together there too, as continuous tracking would have. ORB-SLAM3 welds
    /// only the merge place and leaves the rest to later loops. A seam the map cannot take
    /// (without depth, a young map's bends) is left out: the merge stands as it was.
    fn weld_seam(&mut self, into: MapId, (pool, near, far): &Seam) {
        let pool = *pool;
        let Some(map) = self.atlas.maps.get(&into) else {
            return;
        };
        let pairs = loop_validator::seam_pairs(map, near, far);
        let valid: Vec<_> = pairs
            .iter()
            .filter_map(|&(q, f)| {
                match loop_validator::validate_seam_pair(
                    &self.cfg.loop_closing,
                    &self.geo,
                    map,
                    q,
                    f,
                    far,
                ) {
                    loop_validator::Verdict::Valid(v) => Some(v),
                    _ => None,
                }
            })
            .collect();
        let mut edges = Vec::new();
        for v in &valid {
            let (Some(q), Some(f)) = (
                v.query_kf.and_then(|k| map.keyframes.get(&k)),
                map.keyframes.get(&v.matched),
            ) else {
                continue;
            };
            let rel = f.pose_cw * v.pose_in_match.inverse();
            let z = Sim3 {
                scale: v.scale,
                ..Sim3::from_isometry(&rel)
            };
            edges.push(ClosureEdge::new(
                pool,
                q.id,
                f.id,
                &z,
                (f.units, q.units),
                relative_information(&rel, &v.information),
            ));
        }
        if edges.is_empty() {
            return;
        }
        let mut closures = self.atlas.closure_edges(into);
        closures.extend(edges.iter().cloned());
        let mut trial = map.clone();
        let report = global_optimizer::optimize_map(
            &self.cfg.loop_closing,
            &mut trial,
            &closures,
            &[],
            self.mono,
        );
        tracing::info!(
            "merge pool {pool}: {} of {} seam pairs valid; with them the pose graph is {} (max chi2/dof closure {:.2} odometry {:.2})",
            edges.len(),
            pairs.len(),
            if report.consistent {
                "consistent"
            } else {
                "inconsistent: left out"
            },
            report.max_closure_nchi2,
            report.max_odometry_nchi2,
        );
        if !report.consistent {
            return;
        }
        self.atlas.maps.insert(into, trial);
        self.atlas.add_edges(pool, edges);
        let map = self.atlas.maps.get_mut(&into).expect("just inserted");
        // The other side's points the pairs matched: fusion keeps them, under their ids.
        let seen_by_both: BTreeSet<_> = valid
            .iter()
            .flat_map(|v| v.matches.iter().flatten().copied())
            .filter(|p| map.points.contains_key(p))
            .collect();
        let fused: usize = valid
            .iter()
            .filter_map(|v| Some(fuse_matches(map, v.query_kf?, &v.matches)))
            .sum();
        tracing::debug!("merge pool {pool}: {fused} points fused across the seam");
        // The camera's map saw these points too: re-observing them cannot tell the place
        // from a copy of it, so they are no evidence for the merge (decision 0023).
        if let Some(ev) = self
            .atlas
            .pools
            .get_mut(pool as usize)
            .and_then(|r| r.evidence.as_mut())
        {
            ev.unheld.retain(|p| !seen_by_both.contains(p));
        }
    }

    /// Replaces a query keyframe's points by the matched map's points it was matched to, then
    /// fuses the two neighbourhoods of the closure.
    pub(super) fn fuse_closure(&mut self, map_id: MapId, acc: &Accepted) {
        let Some(map) = self.atlas.maps.get_mut(&map_id) else {
            return;
        };
        let fused: usize = acc
            .members
            .iter()
            .filter_map(|v| Some(fuse_matches(map, v.query_kf?, &v.matches)))
            .sum();
        // Then the neighbourhoods: the points around the matched keyframes are projected into
        // the keyframes around the camera (its query or reference keyframe and their covisible
        // neighbours) and duplicates fused, as ORB-SLAM's loop correction does.
        let matched = around(map, acc.members.iter().map(|v| v.matched));
        let current: BTreeSet<KfId> = around(
            map,
            acc.members
                .iter()
                .filter_map(|v| v.query_kf.or(v.reference_kf)),
        )
        .difference(&matched)
        .copied()
        .collect();
        let sources: Vec<KfId> = matched.iter().copied().collect();
        let mut fused_around = 0;
        for &kf in &current {
            fused_around += self.merger.fuse_into(map, kf, &sources);
        }
        for kf in current.iter().chain(matched.iter()) {
            if map.keyframes.contains_key(kf) {
                map.update_covisibility(*kf);
            }
        }
        tracing::debug!(
            "loop fusion: {fused} points of the query keyframes, {fused_around} between {} keyframes around the camera and {} around the match",
            current.len(),
            matched.len()
        );
    }

    /// Without depth, a mapped frame's re-observed share (see `appearance_floor`); frames
    /// with too few predicted cells to judge are left out, as the check leaves them out.
    pub(super) fn note_mapping_reobserved(&mut self, e: &global_optimizer::Expectation) {
        if e.expected_cells < self.cfg.controller.min_expected_cells as usize {
            return;
        }
        if self.mapping_reobserved.len() == REOBSERVED_WINDOW {
            self.mapping_reobserved.pop_front();
        }
        self.mapping_reobserved
            .push_back((e.ratio(), e.found_share()));
    }

    /// Without depth, whether the frame fails the appearance check: it re-observes less of
    /// the predicted structure than [`appearance_floor`], and where it does not re-observe it,
    /// it does not see its texture either ([`resemblance_floor`]). On real hand-held images a
    /// right map re-observes as little as a look-alike does (fr1_desk after a kidnapping:
    /// 0.20-0.36 of its cells, the case study's door C 0.25-0.31); what tells them apart is
    /// what the rest shows: 0.47-0.62 of fr1_desk's cells are found against 0.32-0.41 of door
    /// C's (mapping's medians 0.56 and 0.65).
    fn fails_appearance(&self, e: &global_optimizer::Expectation) -> bool {
        let (reobserved, found) = self.appearance_floors();
        e.expected_cells >= self.cfg.controller.min_expected_cells as usize
            && e.ratio() < reobserved
            && found.is_none_or(|f| e.found_share() < f)
    }

    /// The appearance check's floors on the re-observed and the found shares.
    fn appearance_floors(&self) -> (f64, Option<f64>) {
        let c = &self.cfg.controller;
        let reobserved = self.mapping_reobserved.iter().map(|s| s.0);
        let found = self.mapping_reobserved.iter().map(|s| s.1);
        (
            appearance_floor(c.min_expectation_ratio, c.expectation_relative, reobserved),
            resemblance_floor(c.expectation_relative, found),
        )
    }

    /// Localized: track in known space without new keyframes; check the map's expectation.
    pub(super) fn track_localized(&mut self, m: &Measurement, timing: &mut Timing) -> Option<Pose> {
        let cur = self.current?;
        let track = self.track_current(cur, m, timing)?;
        let map = &self.atlas.maps[&cur];
        // Expectation: where the map predicts structure, the camera must see it.
        let e = self.expectation(map, m, &track);
        let known_view = known_viewpoint(map, &track, &self.cfg.controller);
        let pose = self.tracked(cur, &track, m);
        let ratio = e.ratio();
        tracing::debug!(
            "frame {}: {} inliers ({:?}), expectation {} of {} cells ({:.2}), {} more resembled, depth {} confirmed {} contradicted ({:.2}), coverage {} of {} ({:.2})",
            m.frame,
            track.n_inliers,
            track.method,
            e.confirmed_cells,
            e.expected_cells,
            ratio,
            e.resembled_cells,
            e.depth_confirmed,
            e.depth_contradicted,
            e.contradiction(),
            e.covered_cells,
            e.feature_cells,
            e.coverage()
        );
        let c = &self.cfg.controller;
        // With depth: the camera contradicts where the map says surfaces are. Without (mono,
        // or too few readings): the predicted structure is not re-observed.
        let by_depth = e.depth_judged() >= c.min_expected_cells as usize;
        let failed = if by_depth {
            e.contradiction() > c.max_contradiction
        } else {
            self.fails_appearance(&e)
        };
        if failed {
            self.expectation_failures += 1;
        } else {
            self.expectation_failures = 0;
        }
        self.flags.consistent_map = self.expectation_failures < c.corrupted_after_frames;
        if !self.flags.consistent_map {
            self.suspects.clear();
            let (reobserved, found) = self.appearance_floors();
            tracing::info!(
                "frame {}: the map contradicts the camera for {} frames ({} of {} predicted points behind what the depth sensor sees; {} of {} predicted image cells re-observed, floor {reobserved:.2}; {} more resembled, found floor {})",
                m.frame,
                self.expectation_failures,
                e.depth_contradicted,
                e.depth_judged(),
                e.confirmed_cells,
                e.expected_cells,
                e.resembled_cells,
                found.map_or("none".to_string(), |f| format!("{f:.2}"))
            );
        }
        // Left the known area: most of what the camera sees is not in the map and no keyframe
        // looks from here, for a few frames running; or the map no longer holds the tracker.
        if e.coverage() < c.min_known_coverage && !known_view {
            self.unknown_view_frames += 1;
        } else {
            self.unknown_view_frames = 0;
        }
        // Weak tracking off the keyframes' viewpoints: mapping must resume before tracking
        // fails. Where a keyframe looks from, a new keyframe would duplicate it, so with depth
        // Localized holds as long as the tracker does (the depth check guards the map).
        // Without depth the check is appearance only, which cannot tell a blurred frame from a
        // wrong map: weak tracking leaves before that check could condemn a correct map. So does
        // losing half the inliers Localized had, after a loop as after a merge: as the camera
        // leaves the place it was recognised in, the inliers of a correct closure decay just as
        // a wrong one's do (fr1_xyz after each kidnapping; the look-alike door C of the case
        // study), and waiting for the appearance check condemned the correct merges. Mapping
        // resumes, and its keyframes reach the closures again.
        self.localized_peak_inliers = self.localized_peak_inliers.max(track.n_inliers);
        let floor = localized_inlier_floor(
            self.mono,
            c.min_localized_inliers as usize,
            self.localized_peak_inliers,
        );
        let weak = track.n_inliers < floor && !(known_view && by_depth);
        self.cond.left_known_area =
            self.flags.consistent_map && (weak || self.unknown_view_frames >= c.left_after_frames);
        Some(pose)
    }

    /// The global optimizer on map `map`: its pose graph ([`Self::pose_graph`]); when
    /// consistent, a merge's seam is welded ([`Self::weld_seam`]), the closure just accepted
    /// (if any) is fused (see `fuse_closure`) and a full BA follows. Fusing
    /// between the two is what keeps the loop closed in the BA: without shared points the BA
    /// has nothing holding the two sides together and relaxes them apart again.
    pub(super) fn global_optimization(
        &mut self,
        map: MapId,
        closure: Option<&Accepted>,
        seam: Option<&Seam>,
    ) -> GlobalReport {
        let report = self.pose_graph(map);
        if report.consistent
            && let Some(seam) = seam
        {
            self.weld_seam(map, seam);
        }
        if report.consistent
            && let Some(acc) = closure
        {
            self.fuse_closure(map, acc);
        }
        if report.consistent
            && self.cfg.loop_closing.full_ba_after_closure
            && let Some(m) = self.atlas.maps.get_mut(&map)
            && let Some(r) = self.merger.global_ba(m)
        {
            tracing::debug!(
                "full BA after closure: cost {:.1} -> {:.1}",
                r.initial_cost,
                r.final_cost
            );
        }
        report
    }

    /// The pose graph of map `map` optimised with its standing closure edges and checked;
    /// alone, a revocation's re-optimisation (the map was consistent before the revoked pool,
    /// and its points keep their local BA).
    pub(super) fn pose_graph(&mut self, map: MapId) -> GlobalReport {
        let closures = self.atlas.closure_edges(map);
        let Some(m) = self.atlas.maps.get_mut(&map) else {
            return GlobalReport {
                consistent: true,
                ..Default::default()
            };
        };
        let report =
            global_optimizer::optimize_map(&self.cfg.loop_closing, m, &closures, &[], self.mono);
        tracing::info!(
            "global optimisation of map {map}: {} keyframes, {} odometry + {} closure edges, cost {:.1} -> {:.1} in {} iterations, max chi2/dof closure {:.2} odometry {:.2} loop {:.2} (worst closure off by {:.3} / {:.2} deg / scale {:.3}, odometry {:.3} / {:.2} deg / scale {:.3}): {}",
            report.keyframes,
            report.odometry_edges,
            report.closure_edges,
            report.initial_cost,
            report.final_cost,
            report.iterations,
            report.max_closure_nchi2,
            report.max_odometry_nchi2,
            report.max_loop_nchi2,
            report.worst_closure_residual.0,
            report.worst_closure_residual.1,
            report.worst_closure_residual.2,
            report.worst_odometry_residual.0,
            report.worst_odometry_residual.1,
            report.worst_odometry_residual.2,
            if report.consistent {
                "consistent".to_string()
            } else {
                format!("INCONSISTENT, offending pools {:?}", report.offending_pools)
            }
        );
        report
    }
}
