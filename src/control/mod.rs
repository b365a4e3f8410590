//! The modal controller: the SLAM state machine of the paper (section V). Components compute and
//! report flags; only this module decides what runs on each measurement.
//!
//! Implemented so far: Init → [initialized] → Idle → [able_to_track] → Core (region Mapping)
//! → [!able_to_track] → Idle, and Interruptible → Final at the end of data. Relocalize,
//! Localized and CorruptedMap arrive with the multi-map atlas.

pub mod spec;

use crate::config::{CameraConfig, Config};
use crate::initializer::Initializer;
use crate::map::{KfId, Map};
use crate::map_merger::MapMerger;
use crate::optim::Intrinsics;
use crate::output::{Flags, Timing, Transition};
use crate::preprocess::{ImageGeometry, Measurement};
use crate::tracker::Tracker;
use nalgebra::Isometry3;

/// The states of the machine.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum State {
    Init,
    Idle,
    /// Orthogonal regions Mapping and Relocalize; shown as "Mapping" while the atlas has a
    /// single map (nothing to relocalize against).
    Core,
    Final,
}

/// What one step produced.
#[derive(Debug, Clone)]
pub struct StepOutput {
    pub state: String,
    pub transition: Option<Transition>,
    pub flags: Flags,
    /// World-to-camera pose when the frame was tracked, with the reference keyframe.
    pub pose: Option<(Isometry3<f64>, u32, KfId)>,
}

pub struct StateMachine {
    pub state: State,
    initializer: Initializer,
    tracker: Tracker,
    merger: MapMerger,
    /// The atlas: one map per tracking session.
    pub maps: Vec<Map>,
    flags: Flags,
}

impl StateMachine {
    pub fn new(config: &Config, camera: &CameraConfig, intr: Intrinsics) -> Self {
        let (sf, nl) = (config.orb.scale_factor, config.orb.n_levels);
        let geo = ImageGeometry::new(intr, camera.width, camera.height, sf, nl)
            .with_readout(camera.readout_s);
        Self {
            state: State::Init,
            initializer: Initializer {
                min_points: config.mapping.min_init_depth_points as usize,
                max_depth: config.mapping.max_point_depth_m,
                intr,
                scale_factor: sf,
                n_levels: nl,
            },
            tracker: Tracker::new(&config.tracker, geo.clone()),
            merger: MapMerger::new(&config.mapping, geo),
            maps: Vec::new(),
            flags: Flags::default(),
        }
    }

    /// Threaded mode: local BA runs on its own thread (see `MapMerger::set_threaded`).
    pub fn set_threaded(&mut self) {
        self.merger.set_threaded();
    }

    /// Local BA results from the mapping thread that are ready (threaded mode only).
    fn collect_mapping(&mut self, wait: bool, timing: &mut Timing) {
        for ms in self.merger.poll(&mut self.maps, wait) {
            timing.record("local_ba_thread", ms);
        }
    }

    pub fn state_name(&self) -> String {
        match self.state {
            State::Init => "Init".into(),
            State::Idle => "Idle".into(),
            State::Core if self.maps.len() > 1 => "Core(M&R)".into(),
            State::Core => "Mapping".into(),
            State::Final => "Final".into(),
        }
    }

    fn go(&mut self, to: State, trigger: &str) -> Option<Transition> {
        let from = self.state_name();
        self.state = to;
        tracing::debug!("{from} -> {} on {trigger}", self.state_name());
        Some(Transition {
            from,
            trigger: trigger.into(),
        })
    }

    /// Processes one measurement in the current state.
    pub fn step(&mut self, m: &Measurement, timing: &mut Timing) -> StepOutput {
        let mut transition = None;
        let mut pose = None;
        match self.state {
            State::Final => {}
            State::Init => {
                let id = self.maps.len() as u32;
                if let Some((map, kf)) =
                    timing.time("initialize", || self.initializer.try_initialize(m, id))
                {
                    let matches = map.keyframes[&kf].points.clone();
                    self.tracker.reset(Isometry3::identity(), m.t, &matches, kf);
                    self.merger.started(m.frame);
                    self.maps.push(map);
                    self.flags.initialized = true;
                    pose = Some((Isometry3::identity(), id, kf));
                    transition = self.go(State::Idle, "initialized");
                }
            }
            State::Idle | State::Core => {
                self.collect_mapping(false, timing);
                let map_id = self.maps.len() - 1;
                let map = &self.maps[map_id];
                let track = timing.time("track", || self.tracker.track(m, map));
                self.flags.able_to_track = track.able_to_track;
                tracing::debug!(
                    "frame {}: {:?}, {} inliers of {} key points, mean chi2 {:.3}",
                    m.frame,
                    track.method,
                    track.n_inliers,
                    m.len(),
                    track.mean_chi2
                );
                if track.able_to_track {
                    if self.state == State::Idle {
                        transition = self.go(State::Core, "able_to_track");
                    }
                    let map = &mut self.maps[map_id];
                    // Mapping region: the map merger grows the local map.
                    self.merger.note_tracked(map, &track);
                    if self.merger.need_keyframe(map, m, &track) {
                        let r = timing.time("map", || self.merger.insert_keyframe(map, m, &track));
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
                        self.tracker.reference_kf = Some(r.keyframe);
                    }
                    let kf = track
                        .reference_kf
                        .or(self.tracker.reference_kf)
                        .unwrap_or(0);
                    pose = Some((track.pose_cw, map_id as u32, kf));
                } else if self.state == State::Core {
                    transition = self.go(State::Idle, "!able_to_track");
                }
            }
        }
        StepOutput {
            state: self.state_name(),
            transition,
            flags: self.flags,
            pose,
        }
    }

    /// Interruptible → Final (end of data or user stop).
    pub fn finish(&mut self, trigger: &str, timing: &mut Timing) -> StepOutput {
        let transition = self.go(State::Final, trigger);
        self.collect_mapping(true, timing);
        // Final, entry: batch refinement of every map.
        for map in &mut self.maps {
            if let Some(r) = timing.time("final_ba", || self.merger.global_ba(map)) {
                tracing::info!(
                    "final BA of map {}: {} keyframes, cost {:.1} -> {:.1}, {} outlier observations",
                    map.id,
                    map.keyframes.len(),
                    r.initial_cost,
                    r.final_cost,
                    r.outliers.len()
                );
            }
        }
        StepOutput {
            state: self.state_name(),
            transition,
            flags: self.flags,
            pose: None,
        }
    }
}
