//! The modal controller: the SLAM state machine of the paper (section V) and the peers'
//! controllers (section IV), on the same components. Components compute and report flags;
//! only this module decides what runs on each measurement.
//!
//! The machine itself is data ([`spec::MachineSpec`]): states with their entry/do activities
//! and guarded transitions. [`StateMachine::step`] runs the active state's *do* activity on a
//! measurement (which updates the flags), then follows the first outgoing transition whose
//! guard holds, runs the target's *entry* activity, and repeats while guards hold (a frame can
//! cross several states, e.g. Core → Localized → CorruptedMap when the entry's global
//! optimisation finds the map inconsistent). Every transition is reported.

pub mod actions;
mod core;
mod corrupted_map;
mod final_state;
pub mod frames;
mod idle;
mod init;
mod localized;
pub mod spec;

use crate::atlas::{Atlas, MapId};
use crate::components::initializer::Initializer;
use crate::components::loop_detector::LoopDetector;
use crate::components::loop_validator::{Accepted, Pool};
use crate::components::map_merger::MapMerger;
use crate::components::preprocess::{ImageGeometry, Measurement};
use crate::components::tracker::Tracker;
use crate::config::{CameraConfig, Config};
use crate::map::KfId;
use crate::optim::Intrinsics;
use crate::outputs::{ClosureRow, Flags, Timing, Transition};
use nalgebra::Isometry3;
pub use spec::{Activity, Guard, MachineSpec, State};

use std::collections::{BTreeMap, BTreeSet};

/// Monocular: frames posed by their rotation alone, one after another (decision 0030).
#[derive(Debug, Clone)]
struct TurnStretch {
    map: MapId,
    first_frame: usize,
    frames: usize,
    /// The panoramic keyframes it made.
    panoramic: Vec<KfId>,
}

/// What one step produced.
#[derive(Debug, Clone)]
pub struct StepOutput {
    /// Active state(s) after the step, e.g. `Mapping` or `Core(M&R)`.
    pub state: String,
    /// Transitions taken during the step, in order.
    pub transitions: Vec<TransitionTaken>,
    pub flags: Flags,
    /// When the frame was tracked: its pose relative to its reference keyframe
    /// (`T_cw · T_kw⁻¹`), the map and the keyframe.
    pub pose: Option<(Isometry3<f64>, MapId, KfId)>,
    /// Pools revoked on this step: the frames tracked across their seams are re-anchored with
    /// them (`Revocation::reanchor`).
    pub revocations: Vec<crate::atlas::Revocation>,
    /// Earlier frames posed on this step: monocular frames that came while the initializer
    /// waited for a pair, posed in the map that pair started.
    pub earlier: Vec<EarlierPose>,
}

/// The pose of an earlier frame, relative to its keyframe as [`StepOutput::pose`].
#[derive(Debug, Clone)]
pub struct EarlierPose {
    pub frame: usize,
    pub t: f64,
    pub relative: Isometry3<f64>,
    pub kf: KfId,
}

/// A transition as states.csv records it.
#[derive(Debug, Clone)]
pub struct TransitionTaken {
    pub to: String,
    pub transition: Transition,
    pub flags: Flags,
}

/// Where the tracker was: its map, its state and the last tracked stamp (to return there).
#[derive(Clone)]
struct TrackingAt {
    map: MapId,
    tracker: Tracker,
    last_tracked_t: Option<f64>,
}

/// Where the camera was when tracking was lost, for the map started after it (see
/// `StateMachine::lost_place`).
#[derive(Debug, Clone)]
struct LostPlace {
    /// The map started after the loss.
    new_map: MapId,
    /// The lost map's keyframe the tracker referred to last, then its keyframes taken
    /// nearest to it (see `StateMachine::lost_keyframes`).
    keyframes: Vec<KfId>,
    /// Stamp of the last frame tracked before the loss.
    lost_t: f64,
}

/// Internal conditions besides the paper's four flags.
#[derive(Debug, Clone, Copy, Default)]
struct Conditions {
    left_known_area: bool,
    recovered: Option<bool>,
}

/// The Interruptible state's user-stop event (SIGINT/SIGTERM, [`crate::interrupt`]).
pub const USER_STOP: &str = "user_stop";

pub struct StateMachine {
    pub spec: MachineSpec,
    pub state: State,
    flags: Flags,
    cond: Conditions,
    cfg: Config,
    geo: ImageGeometry,
    initializer: Initializer,
    tracker: Tracker,
    merger: MapMerger,
    detector: LoopDetector,
    /// Relocalization pool (frames of the Relocalize region) and loop pool (keyframes of the
    /// Mapping region).
    reloc_pool: Pool,
    loop_pool: Pool,
    /// Every map of the run.
    pub atlas: Atlas,
    /// The map the tracker works in.
    current: Option<MapId>,
    /// Stamp of the last tracked frame (a short gap is re-tracked in the same map).
    last_tracked_t: Option<f64>,
    /// The map started last and the stamp of the frame it was started from: until another
    /// frame is tracked in it, one unconfirmed view (see `discard_unconfirmed`).
    founded: Option<(MapId, f64)>,
    /// The pool accepted by the validator, waiting for Localized's entry.
    accepted: Option<Accepted>,
    /// A pool of Idle frames relocalized in the map they were lost in, waiting for
    /// Localized's entry (see `relocalize_in_lost_map`).
    relocalized_in_idle: Option<Accepted>,
    /// Monocular Idle: frames relocalized in the lost map, waiting to make a pool.
    idle_pool: Vec<crate::components::loop_validator::Valid>,
    /// Consecutive frames in Localized whose expectation failed, and whose view the map did
    /// not cover.
    expectation_failures: u32,
    /// Without depth: the shares of predicted cells re-observed and found (re-observed or
    /// resembled) on the last mapped frames (at most `REOBSERVED_WINDOW`), the appearance
    /// check's references (see `appearance_floor`, `resemblance_floor`).
    mapping_reobserved: std::collections::VecDeque<(f64, f64)>,
    /// Most inliers of a frame since Localized was entered (see `track_localized`).
    localized_peak_inliers: usize,
    unknown_view_frames: u32,
    /// Why the map was found inconsistent: pools the global optimizer flagged (empty: the
    /// expectation check failed).
    suspects: Vec<u32>,
    /// Mapping's depth check (see `global_optimizer::keyframe_depth_check`): consecutive new
    /// keyframes that saw through the rest of their map, and the last of them.
    contradicting_keyframes: u32,
    contradicting_kf: Option<(MapId, KfId)>,
    /// Keyframes that anchored a closure pool the map later contradicted (and their best
    /// covisible neighbours): proven look-alikes of another place, they no longer anchor
    /// relocalizations or loop closures, so the same wrong closure is not made again from a
    /// new map (whose frame the refused alignments of the pools do not cover).
    aliased: std::collections::BTreeSet<KfId>,
    /// Every closure or relocalization candidate, for closures.csv.
    pub closures: Vec<ClosureRow>,
    /// Frames on which Idle found the lost camera again in its map other than by the motion
    /// model (see `Atlas::revoke`).
    reacquired: Vec<usize>,
    /// Pools revoked on this step, for its output.
    revocations: Vec<crate::atlas::Revocation>,
    /// Maps a recovery has optimised again already.
    reoptimized: std::collections::BTreeSet<MapId>,
    /// Tracking before the newest map was started within a short gap (see
    /// `discard_unconfirmed`).
    resume: Option<TrackingAt>,
    /// After a loss, the lost map's keyframes at the lost place: the Relocalize region of the
    /// map started next validates them as candidates while the camera may still be near them,
    /// whatever the loop detector's votes (a short gap rarely moves the camera far).
    lost_place: Option<LostPlace>,
    /// The keyframes of every lost place so far: where the camera lost track is where it
    /// most often comes back to, and a pending hypothesis there is re-checked by projection
    /// (see `recheck_open_hypothesis`).
    lost_places: BTreeSet<KfId>,
    /// Monocular: poses of the frames the initializer waited on, found when their map
    /// started; held until the map is confirmed (a map discarded as a false start takes
    /// them with it), then handed out with the step ([`StepOutput::earlier`]).
    /// With their observations, for Final's refinement (as every tracked frame's).
    waited_poses: Option<(
        MapId,
        Vec<EarlierPose>,
        Vec<crate::components::map_merger::FrameObservations>,
    )>,
    earlier_poses: Vec<EarlierPose>,
    /// A frame Idle re-tracked in the current map, for the entered state's Mapping region
    /// (see `map_retracked`); and the frame's pose when that made it a keyframe.
    retracked: Option<crate::components::tracker::TrackResult>,
    entry_pose: Option<actions::Pose>,
    /// The observations of the frame tracked last in this step, kept if its pose stands.
    pending_obs: Option<crate::components::map_merger::FrameObservations>,
    /// A keyframe was made from this step's frame (it is a camera of the Final BA already).
    keyframe_made: bool,
    /// The observations of every frame whose pose stands, for Final's batch refinement.
    frame_obs: frames::FrameStore,
    /// Frame poses Final's batch refinement re-estimated: keyframe and pose relative to it.
    pub refined_frames: BTreeMap<usize, (KfId, Isometry3<f64>)>,
    /// Keyframes that left the atlas: only those of a map discarded as one unconfirmed view
    /// (`discard_unconfirmed`); a revoked pool keeps every keyframe.
    pub keyframes_discarded: usize,
    /// Monocular: the rotation-only stretch under way (decision 0030), and every one ended.
    turn: Option<TurnStretch>,
    pub lift_offs: Vec<crate::outputs::LiftOff>,
    /// Set when the machine stopped because the map is unusable.
    pub stop_reason: Option<String>,
    /// After a user stop: when Final's refinement must end (`mapping.final_refinement_max_s`).
    refinement_deadline: Option<std::time::Instant>,
    /// How Final's refinement ended when it was cut short (a user stop's time limit or second
    /// signal), for summary.json.
    pub refinement_cut: Option<String>,
    mono: bool,
    /// Inliers of the tracker's pose on the latest step's frame, if the tracker ran on it.
    pub track_inliers: Option<usize>,
    /// Which of the latest frame's keypoints the tracker matched to a map point (empty when it
    /// did not run); for the visualiser.
    pub track_matched: Vec<bool>,
    /// Rays of the depth-grid samples ([`crate::components::preprocess::Preprocessor::surface_rays`]);
    /// empty: no depth registration.
    surface_rays: Vec<nalgebra::Vector2<f64>>,
}

impl StateMachine {
    pub fn new(config: &Config, camera: &CameraConfig, intr: Intrinsics) -> Self {
        let (sf, nl) = (config.orb.scale_factor, config.orb.n_levels);
        let geo = ImageGeometry::new(intr, camera.width, camera.height, sf, nl)
            .with_readout(camera.readout_s);
        let spec = MachineSpec::for_kind(config.controller.kind);
        Self {
            state: State::Init,
            flags: Flags {
                consistent_map: true,
                ..Flags::default()
            },
            cond: Conditions::default(),
            cfg: config.clone(),
            initializer: Initializer::new(
                config.mapping.min_init_depth_points as usize,
                config.mapping.max_point_depth_m,
                geo.clone(),
                config.sequence.mono,
            ),
            tracker: Tracker::new(&config.tracker, geo.clone()).monocular(config.sequence.mono),
            merger: MapMerger::new(&config.mapping, geo.clone()).monocular(config.sequence.mono),
            detector: LoopDetector::from_config(&config.loop_closing),
            reloc_pool: Pool::default(),
            loop_pool: Pool::default(),
            atlas: Atlas::new(),
            current: None,
            last_tracked_t: None,
            founded: None,
            accepted: None,
            expectation_failures: 0,
            mapping_reobserved: Default::default(),
            localized_peak_inliers: 0,
            relocalized_in_idle: None,
            idle_pool: Vec::new(),
            unknown_view_frames: 0,
            suspects: Vec::new(),
            contradicting_keyframes: 0,
            contradicting_kf: None,
            aliased: Default::default(),
            closures: Vec::new(),
            reacquired: Vec::new(),
            revocations: Vec::new(),
            reoptimized: Default::default(),
            stop_reason: None,
            keyframes_discarded: 0,
            turn: None,
            lift_offs: Vec::new(),
            retracked: None,
            resume: None,
            lost_place: None,
            lost_places: BTreeSet::new(),
            waited_poses: None,
            earlier_poses: Vec::new(),
            entry_pose: None,
            pending_obs: None,
            keyframe_made: false,
            frame_obs: frames::FrameStore::new(config.mapping.final_frames_per_keyframe as usize),
            refined_frames: BTreeMap::new(),
            refinement_deadline: None,
            refinement_cut: None,
            mono: config.sequence.mono,
            track_inliers: None,
            track_matched: Vec::new(),
            surface_rays: Vec::new(),
            geo,
            spec,
        }
    }

    /// The rays of the frames' depth-grid samples, from the preprocessor: with them Final's
    /// batch refinement can register keyframes by their depth (`crate::components::depth_registration`).
    pub fn set_surface_rays(&mut self, rays: &[nalgebra::Vector2<f64>]) {
        self.surface_rays = rays.to_vec();
    }

    /// Starts from a saved atlas (multi-session, Init's entry): its maps become the "other
    /// maps" the Relocalize region looks in.
    pub fn load_atlas(&mut self, atlas: Atlas) {
        for map in atlas.maps.values() {
            for kf in map.keyframes.values() {
                self.detector.insert(kf.id as u64, &kf.descriptors);
            }
        }
        self.atlas = atlas;
    }

    /// Threaded mode: local BA runs on its own thread (see `MapMerger::set_threaded`).
    pub fn set_threaded(&mut self) {
        self.merger.set_threaded();
    }

    /// The state name as states.csv shows it.
    pub fn state_name(&self) -> String {
        match self.state {
            State::Core if self.atlas.maps.len() > 1 => "Core(M&R)".into(),
            State::Core => "Mapping".into(),
            s => self.spec.state(s).name.into(),
        }
    }

    pub fn flags(&self) -> Flags {
        self.flags
    }

    fn guard(&self, g: Guard) -> bool {
        match g {
            Guard::Initialized => self.flags.initialized,
            Guard::AbleToTrack => self.flags.able_to_track,
            Guard::NotAbleToTrack => !self.flags.able_to_track,
            Guard::AbleToLocalize => self.flags.able_to_localize,
            Guard::NotConsistentMap => !self.flags.consistent_map,
            Guard::LeftKnownArea => self.cond.left_known_area,
            Guard::Recovered => self.cond.recovered == Some(true),
            Guard::NotRecovered => self.cond.recovered == Some(false),
        }
    }

    /// Processes one measurement in the current state.
    pub fn step(&mut self, m: &Measurement, timing: &mut Timing) -> StepOutput {
        self.revocations.clear();
        self.pending_obs = None;
        self.keyframe_made = false;
        self.retracked = None;
        self.track_inliers = None;
        self.track_matched.clear();
        let activity = self.spec.state(self.state).activity;
        let mut pose = self.run_activity(activity, m, timing);
        let mut transitions = Vec::new();
        self.follow_transitions(m, timing, &mut transitions);
        // CorruptedMap's recovery does not look at the measurement: the state it leads to gets
        // it (Idle re-tracks it where the camera was before the undone pool), so a recovery
        // costs no frame its pose.
        if activity == Activity::Recover && self.state != State::CorruptedMap {
            let next = self.spec.state(self.state).activity;
            pose = self.run_activity(next, m, timing);
            self.follow_transitions(m, timing, &mut transitions);
        }
        // The frame's pose stands only if its keyframe is still in the atlas (a rollback may
        // have discarded it); a merge may have moved it to another map.
        let pose = self
            .entry_pose
            .take()
            .or(pose)
            .and_then(|(rel, _, kf)| self.atlas.map_of_keyframe(kf).map(|map| (rel, map, kf)));
        if let (Some((rel, map, kf)), Some(mut obs)) = (pose, self.pending_obs.take())
            && let Some(k) = self.atlas.maps[&map].keyframes.get(&kf)
        {
            obs.anchor(k, rel, self.keyframe_made);
            self.frame_obs.insert(obs);
        }
        StepOutput {
            state: self.state_name(),
            transitions,
            flags: self.flags,
            pose,
            revocations: std::mem::take(&mut self.revocations),
            earlier: std::mem::take(&mut self.earlier_poses),
        }
    }

    /// Follows guarded transitions until none holds (bounded: the tables have no cycle of
    /// guards that can all hold at once, but a bug must not hang a run).
    fn follow_transitions(
        &mut self,
        m: &Measurement,
        timing: &mut Timing,
        transitions: &mut Vec<TransitionTaken>,
    ) {
        for _ in 0..6 {
            let Some(t) = self
                .spec
                .outgoing(self.state)
                .find(|t| self.guard(t.guard))
                .copied()
            else {
                break;
            };
            let from = self.state_name();
            tracing::debug!(
                "frame {}: {from} -> {:?} [{}]",
                m.frame,
                t.to,
                t.guard.label()
            );
            self.exit(self.state);
            self.state = t.to;
            self.enter(t.to, m, timing);
            transitions.push(TransitionTaken {
                to: self.state_name(),
                transition: Transition {
                    from,
                    trigger: t.guard.label().into(),
                },
                flags: self.flags,
            });
        }
    }

    fn exit(&mut self, s: State) {
        if s == State::Localized {
            self.expectation_failures = 0;
            self.unknown_view_frames = 0;
        }
    }

    /// Interruptible → Final (end of data, user stop, or an input error).
    /// After a [`USER_STOP`] the refinement is bounded in time (and skipped on a second
    /// signal, see [`crate::interrupt`]).
    pub fn finish(&mut self, trigger: &str, timing: &mut Timing) -> StepOutput {
        let from = self.state_name();
        let was_final = self.state == State::Final;
        self.state = State::Final;
        self.merger.poll(&mut self.atlas, true);
        if trigger == USER_STOP {
            self.refinement_deadline = Some(
                std::time::Instant::now()
                    + std::time::Duration::from_secs_f64(self.cfg.mapping.final_refinement_max_s),
            );
        }
        if !was_final {
            self.final_refinement(timing);
        }
        let transitions = if was_final {
            Vec::new()
        } else {
            vec![TransitionTaken {
                to: self.state_name(),
                transition: Transition {
                    from,
                    trigger: trigger.into(),
                },
                flags: self.flags,
            }]
        };
        StepOutput {
            state: self.state_name(),
            transitions,
            flags: self.flags,
            pose: None,
            revocations: Vec::new(),
            earlier: Vec::new(),
        }
    }
}
