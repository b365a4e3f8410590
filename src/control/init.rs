//! Init: the initializer on each measurement until a map starts, and starting maps.

use super::StateMachine;
use crate::atlas::MapId;
use crate::components::preprocess::Measurement;
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
}
