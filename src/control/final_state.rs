//! Final: the batch refinement at the end of the run (a full BA per map with tracked frames as extra cameras, the rest re-placed), bounded in time after a user stop.

use super::StateMachine;
use crate::atlas::MapId;
use crate::components::map_merger::FrameObservations;
use crate::map::KfId;
use crate::outputs::Timing;
use std::collections::BTreeMap;

impl StateMachine {
    /// Final's entry: batch refinement of every map: a full BA over its keyframes and points,
    /// with tracked frames as extra cameras (one per `final_ba_frame_interval_s`), then every
    /// other tracked frame re-placed on the refined map (see `MapMerger::place_frame`).
    pub(super) fn final_refinement(&mut self, timing: &mut Timing) {
        for ms in self.merger.poll(&mut self.atlas, true) {
            timing.record("local_ba_thread", ms);
        }
        let interval = self.cfg.mapping.final_ba_frame_interval_s;
        tracing::info!(
            "Final refines with {} tracked frames ({} forgotten for the budget of {} per keyframe)",
            self.frame_obs.len(),
            self.frame_obs.forgotten,
            self.cfg.mapping.final_frames_per_keyframe
        );
        // After a user stop, the time limit and a second signal also end a map's BA and its
        // frames' re-placing part-way (the estimate so far stands), not only the next map's.
        let cutoff = self
            .refinement_deadline
            .map(|deadline| crate::optim::Cutoff {
                deadline: Some(deadline),
                signal: Some(crate::interrupt::skip_refinement),
            });
        let ids: Vec<MapId> = self.atlas.maps.keys().copied().collect();
        for id in ids {
            if self.refinement_cut_short(id, cutoff) {
                break;
            }
            let map = self.atlas.maps.get_mut(&id).expect("listed");
            let (cameras, rest) = select_frames(
                map,
                self.frame_obs.all(),
                interval,
                self.cfg.mapping.final_ba_cameras_per_keyframe as usize,
            );
            let edges = if self.cfg.mapping.final_depth_edges && !self.mono {
                timing.time("final_depth_edges", || {
                    crate::components::depth_registration::seam_edges(
                        map,
                        &self.surface_rays,
                        &crate::components::depth_registration::EdgeSearch {
                            local_planes: self.cfg.mapping.final_depth_edges_local_planes,
                            ..Default::default()
                        },
                    )
                })
            } else {
                Vec::new()
            };
            for e in &edges {
                tracing::info!(
                    "depth edge in map {id}: keyframe {} <- {}, {} points on {} planes, rms {:.1} mm, moves them {:.1} cm and {:.2}°",
                    e.a,
                    e.b,
                    e.registration.inliers,
                    e.registration.planes,
                    1e3 * e.registration.rms_m,
                    1e2 * e.correction_m,
                    e.correction_deg
                );
            }
            let Some((r, poses)) = timing.time("final_ba", || {
                self.merger
                    .global_ba_with_frames(map, &cameras, &edges, cutoff)
            }) else {
                continue;
            };
            if r.termination == crate::optim::Termination::CutOff {
                let why = refinement_cut_reason();
                tracing::warn!(
                    "Final's refinement {why}: map {id}'s BA stopped after {} iterations",
                    r.iterations
                );
                self.refinement_cut.get_or_insert_with(|| {
                    format!(
                        "{why}: map {id}'s BA stopped after {} iterations",
                        r.iterations
                    )
                });
            }
            tracing::info!(
                "final BA of map {id}: {} keyframes and {} frames, cost {:.1} -> {:.1} in {} iterations, {} outlier observations",
                map.keyframes.len(),
                poses.len(),
                r.initial_cost,
                r.final_cost,
                r.iterations,
                r.outliers.len()
            );
            // Past the cutoff, the frames not yet re-placed keep their tracked poses.
            let placed: crate::components::map_merger::FramePoses =
                timing.time("final_frames", || {
                    rest.iter()
                        .take_while(|_| !cutoff.is_some_and(|c| c.reached()))
                        .filter_map(|f| Some((f.frame, self.merger.place_frame(map, f)?.0)))
                        .collect()
                });
            for (f, pose_cw) in poses.into_iter().chain(placed) {
                let kf = self.frame_obs.all()[&f].kf;
                if let Some(k) = map.keyframes.get(&kf) {
                    self.refined_frames.insert(f, (kf, k.relative_of(&pose_cw)));
                }
            }
        }
    }

    /// Whether Final's refinement stops before map `next` (`cutoff`, set after a user stop, is
    /// reached: its time limit is over, or a second signal came); records why.
    pub(super) fn refinement_cut_short(
        &mut self,
        next: MapId,
        cutoff: Option<crate::optim::Cutoff>,
    ) -> bool {
        if !cutoff.is_some_and(|c| c.reached()) {
            return false;
        }
        let why = refinement_cut_reason();
        let unrefined = self.atlas.maps.range(next..).count();
        tracing::warn!("Final's refinement {why}: {unrefined} maps keep their tracked poses");
        let cut = format!("{why}: {unrefined} maps not refined");
        self.refinement_cut = Some(match self.refinement_cut.take() {
            Some(before) => format!("{before}; {cut}"),
            None => cut,
        });
        true
    }
}

/// Why Final's refinement stopped early: a second stop signal, else its time limit.
pub(super) fn refinement_cut_reason() -> &'static str {
    if crate::interrupt::skip_refinement() {
        "skipped by a second stop signal"
    } else {
        "cut short by mapping.final_refinement_max_s"
    }
}

/// The tracked frames of `map` for the Final BA: the cameras (the first frame, then the first
/// one at least `interval` seconds after the last chosen; frames that became keyframes are
/// cameras already and left out), and the rest, to be re-placed on the refined map. None
/// when `interval` is 0 (keyframes only). At most `per_keyframe` cameras are anchored to one
/// keyframe (0: no limit): the BA's reduced camera system grows with the square of its cameras
/// where they share points, and revisiting one place for long would otherwise make it the
/// run's memory peak.
pub(super) fn select_frames<'a>(
    map: &crate::map::Map,
    frames: &'a BTreeMap<usize, FrameObservations>,
    interval: f64,
    per_keyframe: usize,
) -> (Vec<&'a FrameObservations>, Vec<&'a FrameObservations>) {
    let mut cameras = Vec::new();
    let mut rest = Vec::new();
    if interval <= 0.0 {
        return (cameras, rest);
    }
    let mut last: Option<f64> = None;
    let mut anchored: BTreeMap<KfId, usize> = BTreeMap::new();
    for f in frames
        .values()
        .filter(|f| map.keyframes.contains_key(&f.kf) && !f.keyframe)
    {
        let n = anchored.entry(f.kf).or_default();
        if last.is_none_or(|l| f.t - l >= interval) && (per_keyframe == 0 || *n < per_keyframe) {
            last = Some(f.t);
            *n += 1;
            cameras.push(f);
        } else {
            rest.push(f);
        }
    }
    (cameras, rest)
}
