//! Idle: tracking lost; a new map is started (or, for ORB-SLAM2's controller, only relocalization runs).

use super::StateMachine;
use crate::components::loop_validator::{self, Query, Verdict};
use crate::components::preprocess::Measurement;
use crate::components::tracker::TrackMethod;
use crate::map::KfId;
use crate::outputs::Timing;
use nalgebra::Isometry3;

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
                if track.method == TrackMethod::MotionModel {
                    self.retracked = Some(track);
                }
                return Some(pose);
            }
            self.tracker.lose();
        }
        if new_map {
            // Within the re-acquisition gap, this frame may be a second false one: if the map
            // it starts is lost at once (discarded), tracking resumes where it was.
            let resume = (same_map && recent).then(|| self.tracking_at()).flatten();
            let lost = self.lost_keyframes();
            let pose = self.start_new_map(m, timing)?;
            self.resume = resume;
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
            let q = Query {
                m,
                map: cur,
                pose: Isometry3::identity(),
                kf: None,
                reference_kf: None,
                // Relocalization in the same map: a pose, no scale to measure.
                own: None,
            };
            let verdict = loop_validator::validate(
                &self.cfg.loop_closing,
                &self.geo,
                &q,
                &self.atlas.maps[&cur],
                c,
            );
            match verdict {
                Verdict::Valid(v) => {
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
                Verdict::Rejected {
                    matched,
                    reason,
                    inliers,
                    pose_in_match,
                } => self.log_closure(
                    m,
                    "relocalization",
                    matched,
                    inliers,
                    pose_in_match,
                    reason.as_str(),
                ),
            }
        }
        None
    }
}
