//! Core: its Mapping region (tracking, keyframes, local mapping, the expectation and depth checks) and its Relocalize region (place recognition, validation, the pools of candidates).

use super::spec::{Acceptance, Activity, LoopScope, State};
use super::{StateMachine, TurnStretch};
use crate::atlas::{MapId, PoolId};
use crate::components::global_optimizer::{self};
use crate::components::loop_detector::Neighbourhood;
use crate::components::loop_validator::{self, Accepted, Agreement, Query, Verdict, relative};
use crate::components::map_merger::FrameObservations;
use crate::components::preprocess::Measurement;
use crate::components::tracker::TrackResult;
use crate::map::KfId;
use crate::outputs::{ClosureRow, Timing};
use nalgebra::Isometry3;
use std::collections::{BTreeMap, BTreeSet};

use super::actions::*;

impl StateMachine {
    /// The tracker on the current map (Core's Mapping region and Localized). A break in the
    /// measurements longer than `controller.reacquire_gap_s` (frames dropped: the camera may
    /// have been carried anywhere, the paper's kidnapping) is a loss without asking the
    /// tracker: continuing from the last pose would be a guess that a look-alike place can
    /// confirm, whereas after the loss the place must be recognised and validated by a pool
    /// (Relocalize region) before the maps are joined. Idle applies the same gap to re-track.
    pub(super) fn track_current(
        &mut self,
        cur: MapId,
        m: &Measurement,
        timing: &mut Timing,
    ) -> Option<TrackResult> {
        let gap = self.last_tracked_t.map_or(0.0, |t| m.t - t);
        if gap > self.cfg.controller.reacquire_gap_s {
            tracing::info!(
                "frame {}: {gap:.2} s since the last tracked frame: tracking lost",
                m.frame
            );
        } else {
            let map = &self.atlas.maps[&cur];
            let track = timing.time("track", || self.tracker.track(m, map));
            self.note_turn(cur, m, &track);
            self.track_inliers = Some(track.n_inliers);
            self.track_matched = track.matches.iter().map(Option::is_some).collect();
            tracing::debug!(
                "frame {}: {:?}, {} inliers of {} key points, mean chi2 {:.3}",
                m.frame,
                track.method,
                track.n_inliers,
                m.len(),
                track.mean_chi2
            );
            if track.able_to_track {
                return Some(track);
            }
        }
        if gap > self.cfg.controller.reacquire_gap_s {
            self.end_turn(m, None);
        }
        self.flags.able_to_track = false;
        self.tracker.lose();
        self.discard_unconfirmed(cur, m);
        None
    }

    /// Monocular: a rotation-only frame starts or extends the turn under way; any other
    /// frame ends it (a lift-off, [`Self::end_turn`]).
    fn note_turn(&mut self, cur: MapId, m: &Measurement, track: &TrackResult) {
        if !track.method.is_rotation_only() {
            self.end_turn(m, Some(track));
            return;
        }
        if self.turn.as_ref().is_some_and(|t| t.map != cur) {
            self.end_turn(m, None);
        }
        let t = self.turn.get_or_insert_with(|| TurnStretch {
            map: cur,
            first_frame: m.frame,
            frames: 0,
            panoramic: Vec::new(),
        });
        t.frames += 1;
    }

    /// The turn under way ended at frame `m`: tracked on map points (`track` able) or lost.
    /// Counts what its stored bearings did for the frame (decision 0030), for the log and
    /// summary.json.
    fn end_turn(&mut self, m: &Measurement, track: Option<&TrackResult>) {
        let Some(turn) = self.turn.take() else {
            return;
        };
        let continued = track.is_some_and(|t| t.able_to_track);
        let (matched, triangulated, kept) = match self.atlas.maps.get(&turn.map) {
            Some(map) => {
                let pose = track.map(|t| t.pose_cw);
                self.merger
                    .stored_bearings_seen(map, &turn.panoramic, m, pose.as_ref())
            }
            None => (0, 0, 0),
        };
        let row = crate::outputs::LiftOff {
            frame: m.frame,
            turn_first_frame: turn.first_frame,
            turn_frames: turn.frames,
            panoramic_keyframes: kept,
            bearings_matched: matched,
            bearings_triangulated: triangulated,
            continued,
        };
        tracing::info!(
            "frame {}: lift-off after {} rotation-only frames from frame {}: {} panoramic keyframes, {} key points matched to stored bearings, {} bearings triangulated, {}",
            row.frame,
            row.turn_frames,
            row.turn_first_frame,
            row.panoramic_keyframes,
            row.bearings_matched,
            row.bearings_triangulated,
            if continued {
                "tracked in the map"
            } else {
                "lost"
            }
        );
        self.lift_offs.push(row);
    }

    /// A map lost on the very next frame after the one it was started from holds a single
    /// view that no other frame confirmed: a false measurement (an image from elsewhere) as
    /// likely as a real one. It is discarded before it can anchor a closure that would place
    /// the camera where that image was taken (ORB-SLAM3 likewise resets a map lost right
    /// after its start). Nothing else refers to it yet: no frame but the first was tracked in
    /// it and pools need several.
    pub(super) fn discard_unconfirmed(&mut self, cur: MapId, m: &Measurement) {
        let Some((id, t0)) = self.founded else { return };
        if id != cur || self.last_tracked_t != Some(t0) {
            return;
        }
        if self.waited_poses.as_ref().is_some_and(|(w, ..)| *w == id) {
            self.waited_poses = None;
        }
        if let Some(map) = self.atlas.discard_map(id) {
            for k in map.keyframes.keys() {
                self.detector.remove(*k as u64);
            }
            self.keyframes_discarded += map.keyframes.len();
            tracing::info!(
                "frame {}: map {id} discarded: lost on the frame after its first",
                m.frame
            );
        }
        self.founded = None;
        self.current = None;
        self.last_tracked_t = None;
        // Started from a false frame within a short gap: back to the map it interrupted, so
        // the next frame is re-tracked there instead of starting yet another map.
        if let Some(r) = self.resume.take()
            && self.atlas.maps.contains_key(&r.map)
        {
            tracing::info!(
                "frame {}: tracking resumes in map {} after the discarded one",
                m.frame,
                r.map
            );
            self.resume_tracking(r);
        }
    }

    /// Bookkeeping of a tracked frame; returns its pose.
    pub(super) fn tracked(&mut self, cur: MapId, track: &TrackResult, m: &Measurement) -> Pose {
        self.flags.able_to_track = true;
        self.last_tracked_t = Some(m.t);
        self.release_waited_poses(m);
        self.note_merge_evidence(track, m);
        let map = self.atlas.maps.get_mut(&cur).expect("current map exists");
        self.merger.note_tracked(map, track);
        self.pending_obs = Some(FrameObservations::new(m, track));
        let kf = track
            .reference_kf
            .or(self.tracker.reference_kf)
            .or_else(|| map.keyframes.keys().next_back().copied())
            .expect("a map has a keyframe");
        (map.keyframes[&kf].relative_of(&track.pose_cw), cur, kf)
    }

    /// Provisional merges: a tracked frame that re-observes enough of what only the map merged
    /// into had seen counts as evidence for each standing merge still unconfirmed
    /// ([`crate::atlas::MergeEvidence`]). Only recorded and reported for now.
    fn note_merge_evidence(&mut self, track: &TrackResult, m: &Measurement) {
        for rec in self.atlas.pools.iter_mut().filter(|p| !p.rolled_back) {
            let Some(ev) = rec.evidence.as_mut() else {
                continue;
            };
            if ev.observe(track.matches.iter().flatten().copied(), m.frame) {
                tracing::info!(
                    "frame {}: merge pool {} confirmed: {} frames re-observed what only the map merged into had seen",
                    m.frame,
                    rec.id,
                    ev.frames
                );
            }
        }
    }

    /// Core: region Mapping (tracker, map merger, loop closing on the current map) and region
    /// Relocalize (the other maps).
    pub(super) fn track_and_map(
        &mut self,
        m: &Measurement,
        scope: LoopScope,
        relocalize: bool,
        recognize_known: bool,
        timing: &mut Timing,
    ) -> Option<Pose> {
        let Some(cur) = self.current else {
            self.flags.able_to_track = false;
            return None;
        };
        let Some(track) = self.track_current(cur, m, timing) else {
            // The lost map was discarded and tracking resumed in the map it interrupted: this
            // frame is the first real one after the false frames, so it is tracked there now —
            // the next one may already be past the re-acquisition gap. (Once only: the resumed
            // map was not just founded, so it is never discarded.)
            if self.current.is_some_and(|r| r != cur) {
                return self.track_and_map(m, scope, relocalize, recognize_known, timing);
            }
            return None;
        };
        let mut pose = self.tracked(cur, &track, m);
        let new_kf = self.map_frame(cur, m, &track, scope, timing);
        if let Some(kf) = new_kf {
            // The frame is that keyframe: it follows the keyframe's refined pose exactly.
            pose = (Isometry3::identity(), cur, kf);
        }
        let mut expectation = None;
        if self.mono {
            let e = self.expectation(&self.atlas.maps[&cur], m, &track);
            self.note_mapping_reobserved(&e);
            expectation = Some(e);
        }
        let lc = self.cfg.loop_closing.enabled;
        if recognize_known && lc && new_kf.is_none() && !self.flags.able_to_localize {
            // Only where the map covers the view: Localized would be left at once otherwise.
            let e =
                expectation.unwrap_or_else(|| self.expectation(&self.atlas.maps[&cur], m, &track));
            if e.coverage() >= self.cfg.controller.min_recognize_coverage {
                timing.time("recognize", || self.recognize_known(m, &track));
            }
        }
        let others = self.atlas.maps.len() > 1;
        if relocalize && others && lc && !self.flags.able_to_localize {
            timing.time("relocalize", || self.relocalize(m, &track));
        }
        if self.spec.closures_in_place && self.flags.able_to_localize {
            // No Localized state to enter: the closure is applied here, and mapping goes on.
            self.localize(m, timing);
        }
        Some(pose)
    }

    /// Mapping region on a tracked frame: the map merger's keyframe decision and insertion,
    /// then the new keyframe's depth check and loop closing. Returns the new keyframe.
    pub(super) fn map_frame(
        &mut self,
        cur: MapId,
        m: &Measurement,
        track: &TrackResult,
        scope: LoopScope,
        timing: &mut Timing,
    ) -> Option<KfId> {
        let map = self.atlas.maps.get_mut(&cur).expect("current map exists");
        if self.merger.need_panoramic_keyframe(track) {
            let r = timing.time("map", || {
                self.merger.insert_panoramic_keyframe(map, m, track)
            });
            tracing::debug!(
                "panoramic keyframe {} at frame {}: {} bearings triangulated, {} fused",
                r.keyframe,
                m.frame,
                r.new_points,
                r.fused
            );
            self.keyframe_made = true;
            self.tracker.reference_kf = Some(r.keyframe);
            if let Some(t) = self.turn.as_mut() {
                t.panoramic.push(r.keyframe);
            }
            return Some(r.keyframe);
        }
        if !self.merger.need_keyframe(map, m, track, true) {
            return None;
        }
        let r = timing.time("map", || self.merger.insert_keyframe(map, m, track));
        tracing::debug!(
            "keyframe {} at frame {}: {} new points, {} fused, {} culled, BA {:.1} -> {:.1} ({} outliers)",
            r.keyframe,
            m.frame,
            r.new_points,
            r.fused,
            r.culled,
            r.ba_initial_cost,
            r.ba_final_cost,
            r.ba_outliers
        );
        let kf = r.keyframe;
        self.keyframe_made = true;
        self.tracker.reference_kf = Some(kf);
        self.check_keyframe_depth(cur, kf);
        if self.cfg.loop_closing.enabled {
            timing.time("loop_closing", || self.close_loops(m, kf, scope));
        } else {
            self.detector.insert(kf as u64, &m.descriptors);
        }
        Some(kf)
    }

    /// Entry of a tracking-and-mapping state on the frame that Idle re-tracked in the current
    /// map: that frame is mapped like any other. A short interruption (a false frame) in a
    /// turn leaves the camera looking at little of the map; without a keyframe from the
    /// re-tracked frame, the next one found too few points and a new map began (small
    /// `aliasing` with 1 % black frames: that new map then merged into the look-alike room).
    pub(super) fn map_retracked(&mut self, s: State, m: &Measurement, timing: &mut Timing) {
        let Some(track) = self.retracked.take() else {
            return;
        };
        let (Some(cur), Activity::TrackAndMap { loop_scope, .. }) =
            (self.current, self.spec.state(s).activity)
        else {
            return;
        };
        if let Some(kf) = self.map_frame(cur, m, &track, loop_scope, timing) {
            self.entry_pose = Some((Isometry3::identity(), cur, kf));
        }
    }

    /// Mapping region, each new keyframe (with depth, in a map that a closure pool changed):
    /// does it see through the rest of its map? A wrong closure to a look-alike place shows
    /// once the camera maps what the two places do not share; `keyframes_contradicting`
    /// keyframes in a row make the map inconsistent (→ CorruptedMap, which rolls back the
    /// newest pool of this map until the keyframe no longer contradicts).
    pub(super) fn check_keyframe_depth(&mut self, cur: MapId, kf: KfId) {
        let checks = self
            .spec
            .outgoing(State::Core)
            .any(|t| t.to == State::CorruptedMap);
        if self.mono || !checks || self.blameable_pools_of(cur).is_empty() {
            self.contradicting_keyframes = 0;
            return;
        }
        let c = &self.cfg.controller;
        let (judged, through) = self.depth_check_across_pools(cur, kf);
        let share = through as f64 / judged.max(1) as f64;
        tracing::debug!(
            "keyframe {kf}: depth check against map {cur}: {through} of {judged} points seen through ({share:.2})"
        );
        if judged >= c.min_expected_cells as usize && share > c.max_contradiction {
            self.contradicting_keyframes += 1;
        } else {
            self.contradicting_keyframes = 0;
        }
        if self.contradicting_keyframes >= c.keyframes_contradicting {
            tracing::info!(
                "keyframe {kf} sees through {through} of the {judged} points of map {cur} it can judge ({:.0} %): the map is inconsistent",
                100.0 * share
            );
            self.contradicting_kf = Some((cur, kf));
            self.flags.consistent_map = false;
            self.suspects.clear();
        }
    }

    /// Keyframe `kf`'s depth check against the structure of map `map` that a standing pool
    /// placed relative to it. A merge only moves the two merged maps against each other: a
    /// contradiction between parts of one of them (the far ends of a loop it never closed,
    /// apart by its drift) is not the merge's doing, and would condemn a right merge; so
    /// across a merge only points first seen on the other side of its seam are judged. A loop
    /// closure (or a merge whose side of `kf` cannot be told) bends its whole map: every point
    /// is judged, as without any pool.
    pub(super) fn depth_check_across_pools(&self, map: MapId, kf: KfId) -> (usize, usize) {
        let m = &self.atlas.maps[&map];
        // Per standing merge: every keyframe's side of its seam, and `kf`'s; `None`: judge the
        // whole map.
        let seams: Option<Vec<_>> = self
            .blameable_pools_of(map)
            .into_iter()
            .map(|p| {
                let (a, b) = self.atlas.pools[p as usize].merge_sides()?;
                let sides: BTreeMap<KfId, Option<bool>> = m
                    .keyframes
                    .keys()
                    .map(|&k| (k, merge_side(m, k, &a, &b)))
                    .collect();
                let side = sides.get(&kf).copied().flatten()?;
                Some((sides, side))
            })
            .collect();
        let seams = seams.filter(|s| !s.is_empty());
        global_optimizer::keyframe_depth_check(&self.geo, m, kf, |p| {
            seams.as_ref().is_none_or(|seams| {
                seams
                    .iter()
                    .any(|(sides, side)| sides.get(&p.first_kf).copied().flatten() != Some(*side))
            })
        })
    }

    /// Closure pools that touched map `map`, can still be undone and could explain what a
    /// keyframe's depth check sees, newest first. A loop that moved its camera by less than
    /// the check's depth tolerance (`global_optimizer::within_depth_tolerance`) moved no point
    /// far enough to be seen through: a contradiction then is the map's own drift (a loop it
    /// never closed), which no undo mends (small `aliasing` with bag of words: a right loop
    /// of 1 cm at the start, blamed for room B's drift 30 s later, cost 39 keyframes).
    pub(super) fn blameable_pools_of(&self, map: MapId) -> Vec<PoolId> {
        self.atlas
            .pools
            .iter()
            .rev()
            .filter(|p| p.undoable() && p.maps().contains(&map))
            .filter(|p| {
                self.atlas.loop_jump(p.id).is_none_or(|(metres, degrees)| {
                    !global_optimizer::within_depth_tolerance(metres, degrees.to_radians())
                })
            })
            .map(|p| p.id)
            .collect()
    }

    /// Mapping region, frame by frame: places of the current map mapped before the loop
    /// detector's temporal window, recognised and validated, go to the loop pool. A pool of
    /// them says the camera is in known space, whether or not drift needs correcting.
    pub(super) fn recognize_known(&mut self, m: &Measurement, track: &TrackResult) {
        let Some(cur) = self.current else { return };
        // Keyframes of the current map made long enough ago: what was mapped before, not the
        // local map the camera is building now.
        let newest = m.t - self.cfg.loop_closing.known_place_min_age_s;
        let old: BTreeSet<KfId> = self.atlas.maps[&cur]
            .keyframes
            .values()
            .filter(|k| k.t <= newest)
            .map(|k| k.id)
            .collect();
        if old.is_empty() {
            return;
        }
        let aliased = &self.aliased;
        let det = self.detect_frame(m, |k| !old.contains(&k) || aliased.contains(&k));
        for c in det.candidates.iter().take(CANDIDATES_PER_QUERY) {
            let q = self.frame_query(m, cur, track);
            let verdict = loop_validator::validate(
                &self.cfg.loop_closing,
                &self.geo,
                &q,
                &self.atlas.maps[&cur],
                c,
            );
            let window = self.cfg.loop_closing.pool_window_frames as usize;
            if self.offer(verdict, m, "loop", window) {
                break;
            }
        }
    }

    /// Tracked frame `m` of map `cur` as a validator's query: its pose and reference keyframe
    /// in its map, and without depth its tracked points (for the similarity).
    fn frame_query<'a>(
        &'a self,
        m: &'a Measurement,
        cur: MapId,
        track: &'a TrackResult,
    ) -> Query<'a> {
        Query {
            m,
            map: cur,
            pose: track.pose_cw,
            kf: None,
            reference_kf: track.reference_kf.or(self.tracker.reference_kf),
            own: self
                .mono
                .then(|| (&self.atlas.maps[&cur], track.matches.as_slice())),
        }
    }

    /// A frame's loop-detector query over the keyframes `exclude` does not reject, scored
    /// over the atlas' covisibility groups (a frame has no neighbours of its own: no floor).
    pub(super) fn detect_frame(
        &self,
        m: &Measurement,
        exclude: impl Fn(KfId) -> bool,
    ) -> crate::components::loop_detector::Detection {
        let covisible = covisible_in(&self.atlas, self.cfg.loop_closing.bow_group_size as usize);
        let nb = Neighbourhood {
            covisible: &covisible,
            floor: &[],
        };
        self.detector
            .detect_in(&m.descriptors, |img| exclude(img as KfId), &nb)
    }

    /// Mapping region: the new keyframe queries the loop detector (and is stored in it); the
    /// best candidates are validated and offered to the loop pool.
    pub(super) fn close_loops(&mut self, m: &Measurement, kf: KfId, scope: LoopScope) {
        let Some(cur) = self.current else { return };
        let map = &self.atlas.maps[&cur];
        let own: BTreeSet<KfId> = map.keyframes.keys().copied().collect();
        let covisible: BTreeSet<KfId> = map.keyframes[&kf].covisibility.keys().copied().collect();
        let recent = self
            .detector
            .recent_images(self.cfg.loop_closing.temporal_window as usize);
        let aliased = &self.aliased;
        let exclude = |img: u64| {
            let k = img as KfId;
            let near = recent.contains(&img) || covisible.contains(&k);
            aliased.contains(&k)
                || match scope {
                    LoopScope::CurrentMap => !own.contains(&k) || near,
                    LoopScope::AllMaps => own.contains(&k) && near,
                }
        };
        // The floor of the bag-of-words score: the query's covisible keyframes.
        let floor: Vec<u64> = covisible.iter().map(|&k| k as u64).collect();
        let det = {
            let group = covisible_in(&self.atlas, self.cfg.loop_closing.bow_group_size as usize);
            let nb = Neighbourhood {
                covisible: &group,
                floor: &floor,
            };
            self.detector
                .detect_and_insert_in(kf as u64, &m.descriptors, exclude, &nb)
        };
        let query_pose = self.atlas.maps[&cur].keyframes[&kf].pose_cw;
        for c in det.candidates.iter().take(CANDIDATES_PER_QUERY) {
            let Some(match_map) = self.atlas.map_of_keyframe(c.image as KfId) else {
                continue;
            };
            let own = &self.atlas.maps[&cur];
            let q = Query {
                m,
                map: cur,
                pose: query_pose,
                kf: Some(kf),
                reference_kf: Some(kf),
                own: self
                    .mono
                    .then(|| (own, own.keyframes[&kf].points.as_slice())),
            };
            let verdict = loop_validator::validate(
                &self.cfg.loop_closing,
                &self.geo,
                &q,
                &self.atlas.maps[&match_map],
                c,
            );
            let window = self.cfg.loop_closing.loop_pool_window_frames as usize;
            if self.offer(verdict, m, "loop", window) {
                break;
            }
        }
    }

    /// Relocalize region: the frame queries the other maps' keyframes.
    pub(super) fn relocalize(&mut self, m: &Measurement, track: &TrackResult) {
        let Some(cur) = self.current else { return };
        // A monocular map is not merged before it has grown past its two-view initial pair:
        // nothing in it yet can contradict a look-alike place (case study, mono: door C
        // merged into door B three frames after the new map's initialisation, and standing).
        if self.mono && self.atlas.maps[&cur].keyframes.len() < MONO_MIN_MERGE_KEYFRAMES {
            return;
        }
        let own: BTreeSet<KfId> = self.atlas.maps[&cur].keyframes.keys().copied().collect();
        let aliased = &self.aliased;
        let det = self.detect_frame(m, |k| own.contains(&k) || aliased.contains(&k));
        tracing::trace!(
            "frame {}: relocalization query: {:?}, near misses (keyframe, votes) {:?}",
            m.frame,
            det.report,
            det.near_misses
                .iter()
                .map(|c| (c.image, c.matches.len()))
                .collect::<Vec<_>>()
        );
        // Without a candidate, the best near miss in a loaded atlas: a second session sees the
        // places of the first from other viewpoints, which get only a few of the detector's
        // tight votes; the validator's wider descriptor search and geometry then decide.
        // Only there: within a session such weak evidence merged look-alike places sooner than
        // the merge depth check could tell them apart (small `aliasing`, one 1 s drop).
        let atlas = &self.atlas;
        let near_miss = det.near_misses.iter().take(1).filter(|c| {
            c.matches.len() >= NEAR_MISS_MIN_VOTES
                && atlas
                    .map_of_keyframe(c.image as KfId)
                    .is_some_and(|m| atlas.loaded.contains(&m))
        });
        let mut candidates: Vec<&loop_validator::Candidate> = if det.candidates.is_empty() {
            near_miss.collect()
        } else {
            det.candidates.iter().take(CANDIDATES_PER_QUERY).collect()
        };
        let lost = self.lost_place_candidates(m, cur);
        for c in &lost {
            if !candidates.iter().any(|d| d.image == c.image) {
                candidates.push(c);
            }
        }
        let proposed: BTreeSet<KfId> = candidates.iter().map(|c| c.image as KfId).collect();
        for c in candidates {
            let Some(match_map) = self.atlas.map_of_keyframe(c.image as KfId) else {
                continue;
            };
            let q = self.frame_query(m, cur, track);
            let mut verdict = loop_validator::validate(
                &self.cfg.loop_closing,
                &self.geo,
                &q,
                &self.atlas.maps[&match_map],
                c,
            );
            let from_lost_place = lost.iter().any(|l| std::ptr::eq(c, l));
            // Proposed without the detector's evidence, the lost place must show it in
            // geometry: a weak pose would make a weak pool, whose merge check then fails.
            if from_lost_place
                && let Verdict::Valid(v) = &verdict
                && v.n_inliers < LOST_PLACE_MIN_INLIERS
            {
                verdict = Verdict::Rejected {
                    matched: v.matched,
                    reason: loop_validator::Rejection::Refinement,
                    inliers: v.n_inliers,
                    pose_in_match: Some(v.pose_in_match),
                };
            }
            // The lost place seen from afar has few map points where the camera now is; the
            // new frame's depth can still place it (see `validate_from_query_depth`).
            if from_lost_place
                && self.cfg.loop_closing.lost_place_from_query_depth
                && !self.mono
                && matches!(verdict, Verdict::Rejected { .. })
            {
                verdict = loop_validator::validate_from_query_depth(
                    &self.cfg.loop_closing,
                    &self.geo,
                    &q,
                    &self.atlas.maps[&match_map],
                    c.image as KfId,
                    &track.matches,
                    LOST_PLACE_MIN_INLIERS,
                );
            }
            let window = self.cfg.loop_closing.pool_window_frames as usize;
            // Logged as its own kind; it joins the relocalization pool.
            let kind = if from_lost_place {
                "lost-place"
            } else {
                "relocalization"
            };
            if self.offer(verdict, m, kind, window) {
                return;
            }
        }
        self.recheck_open_hypothesis(m, cur, track, &proposed);
    }

    /// The relocalization pool's open hypothesis (its newest pending candidate), checked at
    /// frame `m` by projection (`loop_validator::validate_from_prior`) unless the detector or
    /// the lost place proposed its keyframe at this frame (`proposed`): a pool needs
    /// `pool_size` frames that validate the same alignment, and a hand-held camera's next
    /// frames, a few centimetres and degrees on, often get too few of the detector's tight
    /// votes to be proposed again (fr1_desk, two 1–3 s drops: a right candidate with 91–182
    /// inliers expired alone). Its verdict goes to the same pool, logged as `re-check`; the
    /// pool and the merge checks judge it like any other.
    /// Only a hypothesis at a place where the camera lost track before (`lost_places`) is
    /// re-checked: that is where a camera that lost track most often is again, and elsewhere a
    /// look-alike passes the re-check as well as the place would (small `aliasing`, three 1 s
    /// drops: room B's map, two frames proposed into room A 5 m from where its map was lost,
    /// was merged there by a re-check; with the restriction the maps stay apart). What the
    /// restriction costs on real data is in docs/decisions/0026.
    fn recheck_open_hypothesis(
        &mut self,
        m: &Measurement,
        cur: MapId,
        track: &TrackResult,
        proposed: &BTreeSet<KfId>,
    ) {
        let window = self.cfg.loop_closing.pool_window_frames as usize;
        let Some((kf, alignment)) = self.reloc_pool.open_hypothesis(cur, m.frame, window) else {
            return;
        };
        let Some(match_map) = self.atlas.map_of_keyframe(kf) else {
            return;
        };
        if match_map == cur
            || proposed.contains(&kf)
            || self.aliased.contains(&kf)
            || !self.lost_places.contains(&kf)
        {
            return;
        }
        let prior = alignment.transform_pose_cw(&track.pose_cw);
        let q = self.frame_query(m, cur, track);
        let verdict = loop_validator::validate_from_prior(
            &self.cfg.loop_closing,
            &self.geo,
            &q,
            &self.atlas.maps[&match_map],
            kf,
            &prior,
        );
        self.offer(verdict, m, "re-check", window);
    }

    /// For `LOST_PLACE_WINDOW_S` after a loss, in the map started after it, the lost place's
    /// keyframe with the most detector votes (the keyframe tracked last when none has any) is
    /// a candidate: after a short gap the camera is most likely still near it, but a view a
    /// few decimetres and degrees away gets too few of the detector's tight votes to be
    /// proposed. The validator, the pool and the merge depth check judge it like any other.
    /// With bag-of-words place recognition every keyframe gets a score, and on blurred
    /// hand-held frames the best-scored lost keyframe is often not the nearest: the keyframe
    /// tracked last is then a candidate too (first).
    pub(super) fn lost_place_candidates(
        &self,
        m: &Measurement,
        cur: MapId,
    ) -> Vec<loop_validator::Candidate> {
        let Some(lp) = self.lost_place.as_ref() else {
            return Vec::new();
        };
        if lp.new_map != cur || m.t - lp.lost_t > LOST_PLACE_WINDOW_S {
            return Vec::new();
        }
        self.lost_place_query(m, &lp.keyframes, |k| {
            self.atlas.map_of_keyframe(k).is_some_and(|mm| mm != cur)
        })
    }

    /// The lost place's keyframes `keyframes` (the one tracked last first) that `keep` keeps
    /// and no rollback marked as look-alikes, as candidates for frame `m`: the one with the
    /// most detector votes, or the one tracked last when none has any; with bag of words, the
    /// one tracked last and the best-scored (see `lost_place_candidates`).
    pub(super) fn lost_place_query(
        &self,
        m: &Measurement,
        keyframes: &[KfId],
        keep: impl Fn(KfId) -> bool,
    ) -> Vec<loop_validator::Candidate> {
        let kfs: BTreeSet<KfId> = keyframes
            .iter()
            .copied()
            .filter(|&k| !self.aliased.contains(&k) && keep(k))
            .collect();
        let Some(&first) = keyframes.iter().find(|k| kfs.contains(k)) else {
            return Vec::new();
        };
        let det = self
            .detector
            .detect(&m.descriptors, |img| !kfs.contains(&(img as KfId)));
        let last_tracked = loop_validator::Candidate {
            image: first as u64,
            score: 0.0,
            matches: Vec::new(),
        };
        let best = det.candidates.into_iter().chain(det.near_misses).next();
        if !self.detector.is_bow() {
            return vec![best.unwrap_or(last_tracked)];
        }
        let mut out = vec![last_tracked];
        out.extend(best.filter(|b| b.image != first as u64));
        out
    }

    /// A rejected verdict is logged as a `kind` row of closures.csv; a valid one is returned.
    pub(super) fn valid_or_log(
        &mut self,
        m: &Measurement,
        kind: &str,
        verdict: Verdict,
    ) -> Option<Box<loop_validator::Valid>> {
        match verdict {
            Verdict::Valid(v) => Some(v),
            Verdict::Rejected {
                matched,
                reason,
                inliers,
                pose_in_match,
            } => {
                self.log_closure(m, kind, matched, inliers, pose_in_match, reason.as_str());
                None
            }
        }
    }

    /// Logs a validator verdict and offers a valid candidate to its pool. Returns true when a
    /// pool was accepted (`able_to_localize`).
    pub(super) fn offer(
        &mut self,
        verdict: Verdict,
        m: &Measurement,
        kind: &str,
        window: usize,
    ) -> bool {
        let agreement = Agreement::from_config(&self.cfg.loop_closing);
        let pool_size = self.cfg.loop_closing.pool_size as usize;
        let Some(v) = self.valid_or_log(m, kind, verdict) else {
            return false;
        };
        let same = Agreement::refusal_from_config(&self.cfg.loop_closing);
        let refused = if kind == "loop" {
            self.loop_pool.is_refused(&v, &same)
        } else {
            self.reloc_pool.is_refused(&v, &same)
        };
        let drift = if self.mono {
            None
        } else {
            self.atlas
                .maps
                .get(&v.query_map)
                .and_then(|map| loop_validator::implausible_drift(&self.cfg.loop_closing, map, &v))
        };
        if let Some((moved, turned, path)) = drift {
            tracing::debug!(
                "frame {}: loop to keyframe {} would move the camera {moved:.2} m / \
                 {turned:.1}° after {path:.2} m of path: not drift",
                m.frame,
                v.matched
            );
        }
        let rejection = if drift.is_some() {
            Some(loop_validator::Rejection::ImplausibleDrift)
        } else if refused {
            Some(loop_validator::Rejection::RolledBackAlignment)
        } else {
            None
        };
        if let Some(r) = rejection {
            self.log_closure(
                m,
                kind,
                v.matched,
                v.n_inliers,
                Some(v.pose_in_match),
                r.as_str(),
            );
            return false;
        }
        self.log_closure(
            m,
            kind,
            v.matched,
            v.n_inliers,
            Some(v.pose_in_match),
            "pending",
        );
        let pool = if kind == "loop" {
            &mut self.loop_pool
        } else {
            &mut self.reloc_pool
        };
        let accepted = match self.spec.acceptance {
            Acceptance::Immediate => Some(Accepted {
                query_map: v.query_map,
                match_map: v.match_map,
                alignment: v.alignment(),
                members: vec![*v],
            }),
            Acceptance::Pool => pool.offer(*v, window, pool_size, &agreement),
        };
        let Some(acc) = accepted else { return false };
        if acc.query_map != acc.match_map && !self.mono {
            let Some(refusal) = self.merge_refusal(&acc, m) else {
                return false;
            };
            if let Some(why) = refusal {
                tracing::info!(
                    "frame {}: {kind} pool refused: merging map {} into map {} {why} (a look-alike place)",
                    m.frame,
                    acc.query_map,
                    acc.match_map
                );
                self.refuse(acc);
                return false;
            }
        }
        tracing::info!(
            "frame {}: {kind} pool accepted: map {} -> map {} from {} candidates (scale {:.3})",
            m.frame,
            acc.query_map,
            acc.match_map,
            acc.members.len(),
            acc.alignment.scale
        );
        self.accepted = Some(acc);
        self.flags.able_to_localize = true;
        true
    }

    /// The closures.csv rows of `acc`'s candidates, still pending, get their verdict.
    pub(super) fn settle_pending_rows(
        &mut self,
        acc: &Accepted,
        verdict: &str,
        pool: Option<PoolId>,
    ) {
        for row in self.closures.iter_mut().rev() {
            if row.verdict == "pending"
                && acc
                    .members
                    .iter()
                    .any(|v| v.frame == row.frame && v.matched == row.matched_kf)
            {
                row.verdict = verdict.into();
                if pool.is_some() {
                    row.pool = pool;
                }
            }
        }
    }

    /// The merge check of a pool joining two maps (with depth): the matched map's points seen
    /// from the query map's keyframes under the pool's alignment
    /// ([`global_optimizer::merge_depth_check`]). `None` when a map is gone, `Some(None)` when
    /// the merge may go ahead, `Some(Some(why))` when a keyframe sees clearly through them.
    pub(super) fn merge_refusal(&self, acc: &Accepted, m: &Measurement) -> Option<Option<String>> {
        let into = self.atlas.maps.get(&acc.match_map)?;
        let from = self.atlas.maps.get(&acc.query_map)?;
        let c = &self.cfg.controller;
        let alignment = acc.alignment.to_isometry();
        let through = global_optimizer::merge_depth_check(&self.geo, into, from, &alignment);
        tracing::debug!(
            "frame {}: merge depth check map {} -> {} (keyframe, judged, seen through): {through:?}",
            m.frame,
            acc.query_map,
            acc.match_map
        );
        let worst = keyframe_shares(&through, c.min_expected_cells as usize)
            .max_by(|a, b| a.0.total_cmp(&b.0).then(b.1.cmp(&a.1)));
        if let Some((share, kf)) = worst
            && share > c.max_contradiction
        {
            return Some(Some(format!(
                "would put {:.0} % of map {}'s points where keyframe {kf} saw through them",
                100.0 * share,
                acc.match_map
            )));
        }
        if c.min_merge_appearance > 0.0 {
            let seen = global_optimizer::merge_appearance_check(&self.geo, into, from, &alignment);
            tracing::debug!(
                "frame {}: merge appearance check map {} -> {} (keyframe, confirmed, found): {seen:?}",
                m.frame,
                acc.query_map,
                acc.match_map
            );
            let worst = keyframe_shares(&seen, c.min_merge_appearance_points as usize)
                .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            if let Some((share, kf)) = worst
                && share < c.min_merge_appearance
            {
                return Some(Some(format!(
                    "is contradicted by keyframe {kf}: it confirms map {}'s surfaces by depth \
                     but finds only {:.0} % of their points by appearance",
                    acc.match_map,
                    100.0 * share
                )));
            }
        }
        Some(None)
    }

    /// A refused pool: its alignment is refused from now on, its candidates are logged as
    /// rejected and the keyframes they matched are look-alikes.
    pub(super) fn refuse(&mut self, acc: Accepted) {
        self.reloc_pool
            .refuse(acc.query_map, acc.match_map, acc.alignment);
        self.loop_pool
            .refuse(acc.query_map, acc.match_map, acc.alignment);
        self.reloc_pool.clear();
        self.loop_pool.clear();
        self.settle_pending_rows(&acc, "rejected:map-contradiction", None);
        self.mark_lookalikes(acc.members.iter().map(|v| v.matched).collect());
    }

    pub(super) fn log_closure(
        &mut self,
        m: &Measurement,
        kind: &str,
        matched: KfId,
        inliers: usize,
        pose_in_match: Option<Isometry3<f64>>,
        verdict: &str,
    ) {
        let match_map = self.atlas.map_of_keyframe(matched).unwrap_or(u32::MAX);
        let t_match = self
            .atlas
            .maps
            .get(&match_map)
            .and_then(|mm| mm.keyframes.get(&matched))
            .map_or(f64::NAN, |k| k.t);
        // Pose of the query camera relative to the matched keyframe's camera.
        let rel = match (pose_in_match, self.atlas.maps.get(&match_map)) {
            (Some(p), Some(mm)) => Some(relative(&mm.keyframes[&matched].pose_cw, &p)),
            _ => None,
        };
        self.closures.push(ClosureRow {
            frame: m.frame,
            kind: kind.into(),
            t_query: m.t,
            t_match,
            map_query: self.current.unwrap_or(u32::MAX),
            map_match: match_map,
            matched_kf: matched,
            relative: rel,
            inliers: inliers as u32,
            verdict: verdict.into(),
            pool: None,
        });
    }
}
