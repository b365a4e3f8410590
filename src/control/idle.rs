//! Idle: tracking lost; a new map is started (or, for ORB-SLAM2's controller, only relocalization runs).

use super::StateMachine;
use crate::components::loop_validator::{self, Accepted, Agreement, Query, Valid, Verdict};
use crate::components::preprocess::Measurement;
use crate::components::tracker::{TrackMethod, TrackResult};
use crate::geometry::Sim3;
use crate::map::KfId;
use crate::outputs::Timing;
use nalgebra::Isometry3;
use std::collections::BTreeSet;

use super::actions::*;

impl StateMachine {
    /// Idle (and ProSLAM's lost state): re-track a short interruption in the current map; else
    /// start a new map from this frame.
    pub(super) fn restart(
        &mut self,
        m: &Measurement,
        new_map: bool,
        same_map: bool,
        timing: &mut Timing,
    ) -> Option<Pose> {
        self.flags.able_to_track = false;
        let gap = self.cfg.controller.reacquire_gap_s;
        let recent = self.last_tracked_t.is_some_and(|t| m.t - t <= gap);
        if let (true, true, Some(cur)) = (same_map, recent, self.current) {
            let map = &self.atlas.maps[&cur];
            let track = timing.time("track", || self.tracker.track(m, map));
            self.track_inliers = Some(track.n_inliers);
            self.track_matched = track.matches.iter().map(Option::is_some).collect();
            if track.able_to_track {
                let pose = self.tracked(cur, &track, m);
                // Found by the motion model, it continues the trajectory across the
                // interruption (a false frame re-tracked by descriptors alone is not mapped).
                // Found otherwise, the map placed it where it looks like it is: a revocation
                // of a pool before does not carry it with the camera's side (`Side::Detached`).
                if track.method == TrackMethod::MotionModel {
                    self.retracked = Some(track);
                } else {
                    self.reacquired.push(m.frame);
                }
                return Some(pose);
            }
            self.tracker.lose();
        }
        if new_map
            && same_map
            && self.mono
            && self.cfg.controller.relocalize_lost_map
            && let Some(pose) = self.relocalize_in_lost_map(m, timing)
        {
            return Some(pose);
        }
        if new_map {
            // Within the re-acquisition gap, this frame may be a second false one: if the map
            // it starts is lost at once (discarded), tracking resumes where it was.
            let resume = (same_map && recent).then(|| self.tracking_at()).flatten();
            let lost = self.lost_keyframes();
            // After a loss a new monocular map starts only on a pair the selected two-view
            // model accepts: the other model's starts come earlier, before the lost place is
            // back in view, and a new map then costs a Sim3 merge where a relocalization in the
            // lost map would do (decisions 0019, 0027).
            self.initializer.try_other_model = false;
            // Nor are the frames before the pair tracked backwards into the new map: on
            // fr1_desk mono after one 2–3 s drop they came out 6–11 cm off and the ATE of the
            // map rose by 36–81 % (decision 0030).
            self.initializer.keep_before = false;
            let pose = self.start_new_map(m, timing)?;
            self.resume = resume;
            if let Some((keyframes, _)) = &lost {
                self.lost_places.extend(keyframes.iter().copied());
            }
            self.lost_place = lost.map(|(keyframes, lost_t)| super::LostPlace {
                new_map: pose.1,
                keyframes,
                lost_t,
            });
            self.flags.able_to_track = true;
            return Some(pose);
        }
        None
    }

    /// Monocular Idle, before a new map: the frame is relocalized in the map tracking was lost
    /// in, as ORB-SLAM relocalizes in its map, for `LOST_PLACE_WINDOW_S` after the loss. A new
    /// monocular map costs the frames its two-view initialisation waits for, and joining it
    /// back costs a Sim3 merge, whose undo takes every later pool across its seam with it:
    /// on fr1_desk --mono, 7-22 frames in Idle after each 1 s drop, and with two drops 2-5
    /// maps at the end. Candidates are the detector's in the lost map and the lost place's
    /// keyframes; `pool_size` frames relocalized within `pool_window_frames` at poses a
    /// camera can move between (see `idle_poses_agree`) make a pool, and Localized takes it
    /// as a transaction: the pool is recorded, its checks run, and a rollback undoes it and
    /// what was mapped on it. Returns the frame's pose when it was relocalized.
    pub(super) fn relocalize_in_lost_map(
        &mut self,
        m: &Measurement,
        timing: &mut Timing,
    ) -> Option<Pose> {
        let cur = self.current?;
        let (keyframes, lost_t) = self.lost_keyframes()?;
        if m.t - lost_t > LOST_PLACE_WINDOW_S {
            self.idle_pool.clear();
            return None;
        }
        let in_map: BTreeSet<KfId> = self.atlas.maps[&cur].keyframes.keys().copied().collect();
        let candidates = timing.time("relocalize", || {
            let aliased = &self.aliased;
            let det = self.detect_frame(m, |k| !in_map.contains(&k) || aliased.contains(&k));
            let mut c: Vec<loop_validator::Candidate> = det
                .candidates
                .into_iter()
                .take(CANDIDATES_PER_QUERY)
                .collect();
            for l in self.lost_place_query(m, &keyframes, |_| true) {
                if !c.iter().any(|d| d.image == l.image) {
                    c.push(l);
                }
            }
            c
        });
        let mut best: Option<Box<loop_validator::Valid>> = None;
        for c in &candidates {
            let verdict = timing.time("relocalize", || self.validate_in_map(m, cur, c));
            let Some(v) = self.valid_or_log(m, "relocalization", verdict) else {
                continue;
            };
            let pose = Some(v.pose_in_match);
            self.log_closure(m, "relocalization", v.matched, v.n_inliers, pose, "pending");
            if best.as_ref().is_none_or(|b| v.n_inliers > b.n_inliers) {
                best = Some(v);
            }
        }
        let v = *best?;
        let window = self.cfg.loop_closing.pool_window_frames as usize;
        self.idle_pool
            .retain(|o| m.frame.saturating_sub(o.frame) <= window && o.match_map == cur);
        self.idle_pool.push(v.clone());
        let agreement = Agreement::from_config(&self.cfg.loop_closing);
        let members: Vec<loop_validator::Valid> = self
            .idle_pool
            .iter()
            .filter(|o| idle_poses_agree(&agreement, o, &v))
            .cloned()
            .collect();
        if members.len() < self.cfg.loop_closing.pool_size as usize {
            return None;
        }
        tracing::info!(
            "frame {}: relocalized in map {cur}, where tracking was lost, by {} frames (keyframe {}, {} inliers)",
            m.frame,
            members.len(),
            v.matched,
            v.n_inliers
        );
        self.idle_pool.clear();
        self.initializer.reset();
        self.tracker
            .reset(v.pose_in_match, m.t, &v.matches, v.matched);
        let track = TrackResult {
            pose_cw: v.pose_in_match,
            matches: v.matches.clone(),
            n_inliers: v.n_inliers,
            able_to_track: true,
            method: TrackMethod::Pnp,
            reference_kf: Some(v.matched),
            visible: Vec::new(),
            twist: Default::default(),
            mean_chi2: 0.0,
        };
        let pose = self.tracked(cur, &track, m);
        self.relocalized_in_idle = Some(Accepted {
            query_map: cur,
            match_map: cur,
            alignment: Sim3::identity(),
            members,
        });
        self.flags.able_to_localize = true;
        Some(pose)
    }

    /// The keyframe the tracker referred to last in the current (lost) map, then the map's
    /// other keyframes taken within `LOST_PLACE_RADIUS_M` of it, nearest first (in a turn in
    /// place the camera may look anywhere from there after the gap, not only where the
    /// reference keyframe's covisible ones look); and the stamp of the last tracked frame.
    pub(super) fn lost_keyframes(&self) -> Option<(Vec<KfId>, f64)> {
        let map = self.atlas.maps.get(&self.current?)?;
        let kf = map.keyframes.get(&self.tracker.reference_kf?)?;
        let c = kf.center();
        let mut near: Vec<(f64, KfId)> = map
            .keyframes
            .values()
            .filter(|k| k.id != kf.id)
            .map(|k| ((k.center() - c).norm(), k.id))
            .filter(|&(d, _)| d <= LOST_PLACE_RADIUS_M)
            .collect();
        near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let mut kfs = vec![kf.id];
        kfs.extend(near.iter().take(LOST_PLACE_KEYFRAMES - 1).map(|&(_, k)| k));
        Some((kfs, self.last_tracked_t?))
    }

    /// ORB-SLAM2 when lost: relocalize in the map (first valid candidate); frames get no pose
    /// until then.
    pub(super) fn relocalize_only(&mut self, m: &Measurement, timing: &mut Timing) -> Option<Pose> {
        self.flags.able_to_track = false;
        let cur = self.current?;
        let det = timing.time("relocalize", || {
            self.detector.detect(&m.descriptors, |_| false)
        });
        for c in det.candidates.iter().take(CANDIDATES_PER_QUERY) {
            if self.atlas.map_of_keyframe(c.image as KfId) != Some(cur) {
                continue;
            }
            let verdict = self.validate_in_map(m, cur, c);
            let Some(v) = self.valid_or_log(m, "relocalization", verdict) else {
                continue;
            };
            self.log_closure(
                m,
                "relocalization",
                v.matched,
                v.n_inliers,
                Some(v.pose_in_match),
                "accepted",
            );
            self.tracker
                .reset(v.pose_in_match, m.t, &v.matches, v.matched);
            self.flags.able_to_track = true;
            self.last_tracked_t = Some(m.t);
            // ORB-SLAM2 drops the relocalized frame itself; tracking resumes next frame.
            return None;
        }
        None
    }

    /// The validator's verdict on candidate `c` for frame `m` in map `cur`, the map the
    /// camera was lost in: a pose there, no scale to measure.
    fn validate_in_map(
        &self,
        m: &Measurement,
        cur: crate::atlas::MapId,
        c: &loop_validator::Candidate,
    ) -> Verdict {
        let q = Query {
            m,
            map: cur,
            pose: Isometry3::identity(),
            kf: None,
            reference_kf: None,
            own: None,
        };
        loop_validator::validate(
            &self.cfg.loop_closing,
            &self.geo,
            &q,
            &self.atlas.maps[&cur],
            c,
        )
    }
}

/// Two frames relocalized in Idle agree when their poses differ by no more than the pool's
/// tolerances plus what a hand-held camera moves between them (`IDLE_POOL_SPEED_M_S`,
/// `IDLE_POOL_TURN_DEG_S`): a false match lands anywhere, a real place where the camera can
/// have gone.
pub(super) fn idle_poses_agree(a: &Agreement, o: &Valid, v: &Valid) -> bool {
    let dt = (v.t - o.t).abs();
    let d = o.pose_in_match * v.pose_in_match.inverse();
    d.translation.vector.norm() <= a.max_translation_m + IDLE_POOL_SPEED_M_S * dt
        && d.rotation.angle().to_degrees() <= a.max_rotation_deg + IDLE_POOL_TURN_DEG_S * dt
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix6, UnitQuaternion, Vector3};

    fn valid(t: f64, pose_in_match: Isometry3<f64>) -> Valid {
        Valid {
            frame: (t * 30.0).round() as usize,
            t,
            query_map: 0,
            match_map: 0,
            matched: 1,
            query_kf: None,
            reference_kf: None,
            query_pose: Isometry3::identity(),
            pose_in_match,
            scale: 1.0,
            matches: Vec::new(),
            own_points: false,
            n_inliers: 50,
            information: Matrix6::identity(),
        }
    }

    /// Two frames relocalized in Idle agree when a camera can have moved between their poses
    /// in the time between them, and not when either the distance or the turn is too large.
    #[test]
    fn idle_relocalizations_agree_only_within_what_a_camera_moves() {
        let a = Agreement {
            max_translation_m: 0.1,
            max_rotation_deg: 3.0,
        };
        let o = valid(0.0, Isometry3::identity());
        let moved = |dt: f64, metres: f64, degrees: f64| {
            let r = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), degrees.to_radians());
            valid(
                dt,
                Isometry3::from_parts(Vector3::new(metres, 0.0, 0.0).into(), r),
            )
        };
        // 2 frames apart (1/15 s): 0.1 m + 1 m/s · dt = 0.167 m, 3° + 90°/s · dt = 9°.
        assert!(idle_poses_agree(&a, &o, &moved(1.0 / 15.0, 0.15, 8.0)));
        assert!(!idle_poses_agree(&a, &o, &moved(1.0 / 15.0, 0.2, 0.0)));
        assert!(!idle_poses_agree(&a, &o, &moved(1.0 / 15.0, 0.0, 10.0)));
        // Half a second apart, the same offsets are within reach; the order does not matter.
        assert!(idle_poses_agree(&a, &o, &moved(0.5, 0.2, 10.0)));
        assert!(idle_poses_agree(&a, &moved(0.5, 0.2, 10.0), &o));
    }
}
