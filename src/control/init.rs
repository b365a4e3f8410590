//! Init: the initializer on each measurement until a map starts, and starting maps.

use super::{EarlierPose, StateMachine};
use crate::atlas::MapId;
use crate::components::map_merger::FrameObservations;
use crate::components::preprocess::Measurement;
use crate::components::tracker::TrackResult;
use crate::map::KfId;
use crate::outputs::Timing;
use nalgebra::Isometry3;

use super::actions::*;

impl StateMachine {
    /// Init: the initializer on each measurement until it reports `initialized`.
    pub(super) fn initialize(&mut self, m: &Measurement, timing: &mut Timing) -> Option<Pose> {
        self.flags.able_to_track = false;
        // No map yet, nothing to return to: the first map starts as soon as a pair allows,
        // from the other two-view model when the selected one is ambiguous (decision 0027).
        self.initializer.try_other_model = true;
        // Nor anything to pose the frames before the pair in but this map (decision 0030).
        self.initializer.keep_before = true;
        let pose = self.start_new_map(m, timing)?;
        self.flags.initialized = true;
        // The first keyframe's frame is located (at the origin of the new map).
        self.flags.able_to_track = true;
        Some(pose)
    }

    /// A new map from the initializer: RGB-D, one frame with enough depth whose keyframe is
    /// the map's origin; monocular, a two-view reconstruction whose second keyframe is this
    /// frame (the first, an earlier frame, is the origin).
    pub(super) fn start_new_map(&mut self, m: &Measurement, timing: &mut Timing) -> Option<Pose> {
        let blank = self.atlas.blank_map();
        let (map, kf) = timing.time("initialize", || self.initializer.try_initialize(m, blank))?;
        for k in map.keyframes.values() {
            self.detector.insert(k.id as u64, &k.descriptors);
        }
        let pose = map.keyframes[&kf].pose_cw;
        let id = self.atlas.insert_map(map);
        self.pose_waited_frames(id);
        self.start_tracking_in(id, kf, pose, m);
        self.founded = Some((id, m.t));
        tracing::info!("frame {}: new map {id}", m.frame);
        Some((Isometry3::identity(), id, kf))
    }

    /// Points the tracker at map `id`, at `pose`, with the points of keyframe `kf` as the
    /// last frame's matches.
    pub(super) fn start_tracking_in(
        &mut self,
        id: MapId,
        kf: KfId,
        pose: Isometry3<f64>,
        m: &Measurement,
    ) {
        self.current = Some(id);
        self.atlas.activate(id);
        let matches = self.atlas.maps[&id].keyframes[&kf].points.clone();
        self.tracker.reset(pose, m.t, &matches, kf);
        self.merger.started(m.frame);
        self.last_tracked_t = Some(m.t);
        self.reloc_pool.clear();
        self.loop_pool.clear();
        self.idle_pool.clear();
    }

    /// Monocular: the frames the initializer waited on (its pair's first view, which is the
    /// new map's first keyframe, and the frames up to the second) are tracked in the new map,
    /// in order, from the first keyframe, by a tracker of their own. Their poses are held
    /// until the map is confirmed by the next tracked frame ([`Self::release_waited_poses`]).
    /// Before, each of them had no pose: fr1_xyz300 started its map at frame 8 with frames
    /// 0–7 unposed.
    fn pose_waited_frames(&mut self, id: MapId) {
        let Some((reference, waited)) = self.initializer.take_waited() else {
            return;
        };
        let map = &self.atlas.maps[&id];
        let Some(first) = map.keyframes.values().next() else {
            return;
        };
        let mut poses = vec![EarlierPose {
            frame: reference.frame,
            t: reference.t,
            relative: Isometry3::identity(),
            kf: first.id,
        }];
        // A tracker of their own, at the map's first view: one for the frames after it, one
        // for those before.
        let fresh_tracker = || {
            let mut t =
                crate::components::tracker::Tracker::new(&self.cfg.tracker, self.geo.clone())
                    .monocular(true);
            t.reset(first.pose_cw, reference.t, &first.points, first.id);
            t
        };
        let mut tracker = fresh_tracker();
        let mut observations = Vec::new();
        // A tracked frame's pose, and its observations for Final's refinement.
        fn keep(
            poses: &mut Vec<EarlierPose>,
            observations: &mut Vec<FrameObservations>,
            w: &Measurement,
            track: &TrackResult,
            k: &crate::map::Keyframe,
        ) {
            let relative = k.relative_of(&track.pose_cw);
            poses.push(EarlierPose {
                frame: w.frame,
                t: w.t,
                relative,
                kf: k.id,
            });
            let mut obs = FrameObservations::new(w, track);
            obs.anchor(k, relative, false);
            observations.push(obs);
        }
        for w in &waited {
            let track = tracker.track(w, map);
            if !track.able_to_track {
                continue;
            }
            let Some(k) = track.reference_kf.and_then(|k| map.keyframes.get(&k)) else {
                continue;
            };
            keep(&mut poses, &mut observations, w, &track, k);
        }
        tracing::debug!(
            "map {id}: {} of the {} frames the initializer waited on are posed in it",
            poses.len(),
            waited.len() + 1
        );
        // The frames before the reference, backwards from it, while they are tracked: the
        // camera was there just before, and the map's first view is the one it saw last (the
        // small `turn-in-place` stood still, then walked, for 36 frames before its map's
        // reference). The first frame that is not tracked, or a break in the frames, ends
        // it: going on would be a guess.
        let before = self.initializer.take_before();
        let mut tracker = fresh_tracker();
        let mut next_t = reference.t;
        let mut backwards = 0;
        for b in before.iter().rev() {
            if next_t - b.t > self.cfg.controller.reacquire_gap_s {
                break;
            }
            let track = tracker.track(b, map);
            let Some(k) = track
                .reference_kf
                .and_then(|k| map.keyframes.get(&k))
                .filter(|_| track.able_to_track)
            else {
                break;
            };
            keep(&mut poses, &mut observations, b, &track, k);
            next_t = b.t;
            backwards += 1;
        }
        if !before.is_empty() {
            tracing::debug!(
                "map {id}: {backwards} of the {} frames before the initializer's reference are posed in it, backwards",
                before.len()
            );
        }
        self.waited_poses = Some((id, poses, observations));
    }

    /// The waited frames' poses stand once their map is confirmed: a frame after its first
    /// was tracked (in it, or in the map it was merged into).
    pub(super) fn release_waited_poses(&mut self, m: &Measurement) {
        if self.waited_poses.is_some() && self.founded.is_none_or(|(_, t0)| m.t > t0) {
            let (_, poses, observations) = self.waited_poses.take().expect("checked above");
            self.earlier_poses.extend(poses);
            for obs in observations {
                self.frame_obs.insert(obs);
            }
        }
    }
}
