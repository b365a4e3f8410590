//! Initializer (paper Table I): Measurements → first local map, reporting `initialized`.
//!
//! RGB-D: one frame with enough keypoints that have a valid depth starts a map whose world frame
//! is that camera's frame. (The monocular two-view SfM initializer comes with monocular mode.)

use crate::aligner::backproject;
use crate::map::{KfId, Map};
use crate::optim::Intrinsics;
use crate::preprocess::Measurement;
use nalgebra::Isometry3;

pub struct Initializer {
    pub min_points: usize,
    pub max_depth: f64,
    pub intr: Intrinsics,
    pub scale_factor: f64,
    pub n_levels: u32,
}

impl Initializer {
    /// Fills `map` (an empty map from [`crate::atlas::Atlas::blank_map`]) with the frame as its
    /// first keyframe, or `None` when the frame has fewer than `min_points` keypoints with depth
    /// (too dark, too close, no depth sensor).
    pub fn try_initialize(&self, m: &Measurement, mut map: Map) -> Option<(Map, KfId)> {
        let usable: Vec<usize> = (0..m.len())
            .filter(|&i| m.depth[i] > 0.0 && (m.depth[i] as f64) <= self.max_depth)
            .collect();
        if usable.len() < self.min_points {
            return None;
        }
        let kf = map.add_keyframe(m, Isometry3::identity());
        for i in usable {
            let p = backproject(&self.intr, &m.keypoints[i].un, m.depth[i] as f64);
            map.add_point(kf, i, p, self.scale_factor, self.n_levels);
        }
        Some((map, kf))
    }
}
