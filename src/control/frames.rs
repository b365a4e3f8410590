//! The tracked frames Final's batch refinement uses (`StateMachine::final_refinement`), kept
//! within a budget per keyframe so that memory grows with the map, not with the run.
//!
//! Localized makes no keyframes in known space: an hour spent revisiting one room anchors
//! every frame to the same few keyframes, and keeping all their observations (about 40 KB a
//! frame) grew memory with the run's length. A keyframe keeps the observations of at most
//! `mapping.final_frames_per_keyframe` frames; past that, the frame whose neighbours in time are
//! closest is forgotten (its pose still follows its keyframe, as every frame's does), so the
//! frames kept stay spread over the whole time the keyframe was seen.

use crate::atlas::{Atlas, Revocation};
use crate::components::map_merger::FrameObservations;
use crate::map::KfId;
use std::collections::{BTreeMap, BTreeSet};

#[derive(Debug, Clone, Default)]
pub struct FrameStore {
    frames: BTreeMap<usize, FrameObservations>,
    /// The frames kept per keyframe they are anchored to.
    by_keyframe: BTreeMap<KfId, BTreeSet<usize>>,
    budget: usize,
    /// Frames forgotten for the budget (for the log).
    pub forgotten: usize,
}

impl FrameStore {
    /// A store keeping at most `budget` frames per keyframe (0: no limit).
    pub fn new(budget: usize) -> Self {
        Self {
            budget,
            ..Default::default()
        }
    }

    /// Keeps a frame whose pose stands. A frame that became a keyframe is no extra camera for
    /// Final (the keyframe is one) and is not kept.
    pub fn insert(&mut self, mut obs: FrameObservations) {
        if obs.keyframe {
            return;
        }
        // Collected from a filter, the observations' capacity can be up to twice their length.
        obs.obs.shrink_to_fit();
        let (frame, kf) = (obs.frame, obs.kf);
        if let Some(old) = self.frames.insert(frame, obs)
            && let Some(s) = self.by_keyframe.get_mut(&old.kf)
        {
            s.remove(&frame);
        }
        let kept = self.by_keyframe.entry(kf).or_default();
        kept.insert(frame);
        if self.budget >= 3 && kept.len() > self.budget {
            let order: Vec<usize> = kept.iter().copied().collect();
            let t = |f: &usize| self.frames[f].t;
            // The interior frame whose neighbours are closest in time: the most redundant.
            let drop = order
                .windows(3)
                .min_by(|a, b| (t(&a[2]) - t(&a[0])).total_cmp(&(t(&b[2]) - t(&b[0]))))
                .map(|w| w[1])
                .expect("budget >= 3");
            kept.remove(&drop);
            self.frames.remove(&drop);
            self.forgotten += 1;
        }
    }

    /// Pool `r.pool` was revoked: the frames tracked across its seam follow the camera's side
    /// ([`Revocation::reanchor`]), and the frames of the maps it cut keep only observations
    /// of points in their own map (a point of the other side becomes its copy there, when
    /// the revocation made one).
    pub fn reanchor(&mut self, r: &Revocation, atlas: &Atlas) {
        let cut: Vec<_> = [Some(r.near_map), Some(r.far_map), r.detached_map]
            .into_iter()
            .flatten()
            .collect();
        let frames: Vec<usize> = self.frames.keys().copied().collect();
        for f in frames {
            let obs = self.frames.get_mut(&f).expect("listed");
            match r.reanchor(f, obs.kf, &obs.rel) {
                None => {}
                Some((k, rel, ratio)) => {
                    if let Some(s) = self.by_keyframe.get_mut(&obs.kf) {
                        s.remove(&f);
                    }
                    self.by_keyframe.entry(k).or_default().insert(f);
                    obs.kf = k;
                    obs.rel = rel;
                    for i in 3..6 {
                        obs.twist[i] *= ratio;
                    }
                }
            }
            let Some(map) = cut
                .iter()
                .filter_map(|m| atlas.maps.get(m))
                .find(|m| m.keyframes.contains_key(&obs.kf))
            else {
                continue;
            };
            // A loop's far side stays in the map, but the camera's side did not see it.
            let near = !r.far.contains_key(&obs.kf);
            obs.obs.retain_mut(|o| {
                if map.points.contains_key(&o.point) && !(near && r.far_points.contains(&o.point)) {
                    return true;
                }
                match r.copy_in(o.point, map) {
                    Some(c) => {
                        o.point = c;
                        true
                    }
                    None => false,
                }
            });
        }
    }

    /// Every frame kept, by frame index.
    pub fn all(&self) -> &BTreeMap<usize, FrameObservations> {
        &self.frames
    }

    pub fn len(&self) -> usize {
        self.frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn obs(frame: usize, t: f64, kf: KfId) -> FrameObservations {
        FrameObservations {
            frame,
            t,
            kf,
            rel: nalgebra::Isometry3::identity(),
            twist: nalgebra::Vector6::zeros(),
            keyframe: false,
            obs: Vec::new(),
        }
    }

    #[test]
    fn a_keyframe_keeps_its_budget_of_frames_spread_over_time() {
        let mut s = FrameStore::new(4);
        // Keyframe 1 seen in two visits: frames 0..10 (t 0..0.9) and 100..110 (t 10..10.9).
        for f in (0..10).chain(100..110) {
            s.insert(obs(f, f as f64 / 10.0, 1));
        }
        s.insert(obs(50, 5.0, 2));
        let kept: Vec<usize> = s
            .all()
            .values()
            .filter(|o| o.kf == 1)
            .map(|o| o.frame)
            .collect();
        assert_eq!(kept.len(), 4);
        // The first and the newest stay, and both visits are represented.
        assert_eq!(kept.first(), Some(&0));
        assert_eq!(kept.last(), Some(&109));
        assert!(kept.iter().any(|&f| f < 10) && kept.iter().filter(|&&f| f >= 100).count() >= 2);
        assert_eq!(s.forgotten, 16);
        assert!(s.all().contains_key(&50));
    }

    #[test]
    fn without_a_budget_every_frame_is_kept_but_keyframes() {
        let mut s = FrameStore::new(0);
        for f in 0..50 {
            let mut o = obs(f, f as f64, 1);
            o.keyframe = f % 10 == 0;
            s.insert(o);
        }
        assert_eq!(s.len(), 45);
    }
}
