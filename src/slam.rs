//! The streaming API: a camera loop hands homing one frame at a time and gets the frame's pose,
//! the state machine's state and what happened on that frame; `finish` leads to Final and
//! returns what a run writes. `homing run` ([`crate::system::run`]) drives the same [`Slam`]
//! over a sequence on disk, so the program and the library are one code path.
//!
//! ```no_run
//! use homing::config::{Config, resolve_camera};
//! use homing::slam::Slam;
//! # fn main() -> homing::Result<()> {
//! let config = Config::default();
//! // The camera as `homing run` picks it: DIR/camera.toml, or TUM's from the folder name.
//! let (camera, _) = resolve_camera(&config, None, std::path::Path::new("my_sequence"))?;
//! let mut slam = Slam::new(&config, &camera)?;
//! # let (t, rgb, depth): (f64, image::RgbImage, Option<homing::io::tum::DepthImage>) = todo!();
//! let r = slam.track(t, rgb, depth)?;
//! println!("{} {:?}", r.state, r.pose_wc);
//! let out = slam.finish()?;
//! println!("{} poses", out.trajectory.len());
//! # Ok(())
//! # }
//! ```

use crate::atlas::{Atlas, AtlasCamera, MapId, PoolId};
use crate::components::preprocess::{Measurement, Preprocessor};
use crate::config::{CameraConfig, Config};
use crate::control::{StateMachine, StepOutput, TransitionTaken};
use crate::error::{Error, Result};
use crate::io::tum::{DepthImage, Frame, StampedPose};
use crate::map::KfId;
use crate::outputs::{ClosureRow, DiscardedPose, Flags, MergeRow, StateRow, Timing, Transition};
use nalgebra::Isometry3;

/// What one frame gave.
#[derive(Debug, Clone)]
pub struct FrameResult {
    /// The frame's index (0, 1, … in the order frames were given).
    pub frame: usize,
    pub t: f64,
    /// Camera to world, in the world of `map` as the map stands after this frame; `None` when
    /// the frame was not tracked.
    pub pose_wc: Option<Isometry3<f64>>,
    /// The map the frame is in.
    pub map: Option<MapId>,
    /// The active state(s) after the frame, as states.csv names them (e.g. `Core(M&R)`).
    pub state: String,
    /// Transitions taken on this frame, in order.
    pub transitions: Vec<TransitionTaken>,
    /// The four flags after the frame.
    pub flags: Flags,
    /// Tracked inliers, when the tracker ran.
    pub inliers: Option<usize>,
    /// Closure pools (loops, relocalizations, merges) accepted on this frame.
    pub pools_accepted: Vec<PoolId>,
    /// Pools revoked on this frame (Corrupted Map).
    pub pools_revoked: Vec<PoolId>,
    /// Earlier frames posed on this frame: without depth, the frames the two-view
    /// initializer waited on, posed once their map started. Their poses are in
    /// [`Slam::trajectory`] from now on.
    pub earlier_frames: Vec<usize>,
}

/// Depth as a caller holds it, row-major at the camera's size.
#[derive(Debug, Clone, Copy)]
pub enum DepthBuffer<'a> {
    /// The sensor's 16-bit units, `camera.depth_scale` per metre; 0 = no reading.
    Units(&'a [u16]),
    /// Metres; 0, negative or not finite = no reading.
    Metres(&'a [f32]),
}

/// What a finished session leaves: the files `homing run` writes, as values.
#[derive(Debug, Clone)]
pub struct SlamOutput {
    /// Every posed frame, camera to world, through its keyframe in the final atlas.
    pub trajectory: Vec<StampedPose>,
    /// Each trajectory pose's frame index and map.
    pub trajectory_frames: Vec<usize>,
    pub trajectory_maps: Vec<MapId>,
    /// Every keyframe's pose (camera to world) and map.
    pub keyframes: Vec<(StampedPose, MapId)>,
    /// states.csv's rows.
    pub states: Vec<StateRow>,
    /// closures.csv's rows.
    pub closures: Vec<ClosureRow>,
    /// Every merge of two maps, confirmed or still provisional (summary.json's `merges`).
    pub merges: Vec<MergeRow>,
    /// Monocular: every end of a rotation-only stretch (summary.json's `lift_offs`).
    pub lift_offs: Vec<crate::outputs::LiftOff>,
    /// Poses that did not stand, and why.
    pub discarded: Vec<DiscardedPose>,
    /// The state the session ended in (`Final`).
    pub final_state: String,
}

/// A SLAM session: Init on construction, one [`Slam::track`] per frame, Final on
/// [`Slam::finish`].
pub struct Slam {
    camera: CameraConfig,
    mono: bool,
    pre: Preprocessor,
    machine: StateMachine,
    rec: Recorded,
    timing: Timing,
    next_index: usize,
    last_t: Option<f64>,
    finished: bool,
}

impl Slam {
    /// Init: the controller of `config` for `camera`; monocular when `config.sequence.mono`.
    pub fn new(config: &Config, camera: &CameraConfig) -> Result<Self> {
        let pre = Preprocessor::new(camera, &config.orb)?;
        let mut machine = StateMachine::new(config, camera, camera.intrinsics());
        machine.set_surface_rays(pre.surface_rays());
        Ok(Self {
            camera: camera.clone(),
            mono: config.sequence.mono,
            pre,
            machine,
            rec: Recorded::default(),
            timing: Timing::default(),
            next_index: 0,
            last_t: None,
            finished: false,
        })
    }

    /// Init with an atlas from an earlier session (`homing run --load-map`): the camera starts
    /// by relocalizing in it.
    pub fn with_atlas(mut self, atlas: Atlas) -> Self {
        self.machine.load_atlas(atlas);
        self
    }

    /// Local BA on its own thread while tracking goes on: faster, not bit-reproducible.
    pub fn set_threaded(&mut self) {
        self.machine.set_threaded();
    }

    /// Tracks one frame: `rgb` the colour image, `depth` in metres (none: monocular, and
    /// ignored when the session is monocular). Stamps must increase; the images must have the
    /// camera's size.
    pub fn track(
        &mut self,
        t: f64,
        rgb: image::RgbImage,
        depth: Option<DepthImage>,
    ) -> Result<FrameResult> {
        if self.finished {
            return Err(Error::Invalid("the session is finished".into()));
        }
        if !t.is_finite() || self.last_t.is_some_and(|l| t <= l) {
            return Err(Error::Invalid(format!(
                "frame stamp {t} does not follow the previous one ({})",
                self.last_t.map_or("none".into(), |l| l.to_string())
            )));
        }
        let (w, h) = (self.camera.width, self.camera.height);
        if rgb.dimensions() != (w, h) {
            return Err(Error::Invalid(format!(
                "colour image is {}x{}, the camera's is {w}x{h}",
                rgb.width(),
                rgb.height()
            )));
        }
        if let Some(d) = &depth
            && (d.width, d.height) != (w, h)
        {
            return Err(Error::Invalid(format!(
                "depth image is {}x{}, the camera's is {w}x{h}",
                d.width, d.height
            )));
        }
        let frame = Frame {
            index: self.next_index,
            t,
            rgb,
            depth: if self.mono { None } else { depth },
        };
        self.process_frame(&frame, None).map(|r| r.0)
    }

    /// [`Slam::track`] on borrowed buffers: `rgb` row-major RGB, 3 bytes a pixel, at the
    /// camera's size; `depth` likewise one value a pixel.
    pub fn track_buffers(
        &mut self,
        t: f64,
        rgb: &[u8],
        depth: Option<DepthBuffer<'_>>,
    ) -> Result<FrameResult> {
        let (w, h) = (self.camera.width, self.camera.height);
        let n = (w as usize) * (h as usize);
        if rgb.len() != 3 * n {
            return Err(Error::Invalid(format!(
                "colour buffer holds {} bytes, the camera's {w}x{h} RGB image {}",
                rgb.len(),
                3 * n
            )));
        }
        let depth_len = match depth {
            Some(DepthBuffer::Units(d)) => Some(d.len()),
            Some(DepthBuffer::Metres(d)) => Some(d.len()),
            None => None,
        };
        if let Some(len) = depth_len
            && len != n
        {
            return Err(Error::Invalid(format!(
                "depth buffer holds {len} values, the camera's {w}x{h} image {n}"
            )));
        }
        let rgb = image::RgbImage::from_raw(w, h, rgb.to_vec()).expect("length checked");
        let depth = match depth {
            Some(DepthBuffer::Units(d)) => Some(crate::io::tum::depth_from_units(
                w,
                h,
                d,
                self.camera.depth_scale,
            )),
            Some(DepthBuffer::Metres(d)) => Some(DepthImage {
                width: w,
                height: h,
                data: d
                    .iter()
                    .map(|&m| if m.is_finite() && m > 0.0 { m } else { 0.0 })
                    .collect(),
            }),
            None => None,
        };
        self.track(t, rgb, depth)
    }

    /// One delivered frame: its measurement (extracted here, or `reused` from a features
    /// file with the milliseconds its extraction took and whether extraction needed its weak
    /// pass), then the controller's step. Also returns the measurement and the step's output
    /// for the run driver's recordings.
    pub(crate) fn process_frame(
        &mut self,
        frame: &Frame,
        reused: Option<(Measurement, f64, bool)>,
    ) -> Result<(FrameResult, Measurement, StepOutput)> {
        if self.finished {
            return Err(Error::Invalid("the session is finished".into()));
        }
        let t_frame = std::time::Instant::now();
        let timing = &mut self.timing;
        let reused_ms = reused.as_ref().map_or(0.0, |r| r.1);
        let m = match reused {
            Some((mut m, ms, weak)) => {
                if self.mono {
                    m.depth.iter_mut().for_each(|d| *d = 0.0);
                    m.surface.clear();
                }
                self.pre.weak_passes += weak as usize;
                timing.record("preprocess", ms);
                self.rec.extraction_reused_ms += ms;
                m
            }
            None => timing.time("preprocess", || self.pre.process(frame))?,
        };
        // Counted once the frame could be processed: a frame that fails here leaves the
        // session as it was, so the caller may give the stamp again.
        self.rec.delivered += 1;
        self.next_index = frame.index + 1;
        self.last_t = Some(frame.t);
        let pre_ms = timing.last("preprocess").unwrap_or(0.0);
        let tracked = timing.count("track");
        let pools_before = self.machine.atlas.pools.len();
        let out = self.machine.step(&m, timing);
        timing.record("frame", t_frame.elapsed().as_secs_f64() * 1e3 + reused_ms);
        // The front end's budget: extraction + tracking of one frame (mapping excluded).
        if timing.count("track") > tracked {
            let track_ms = timing.last("track").unwrap_or(0.0);
            timing.record("extract_track", pre_ms + track_ms);
        }
        // A revoked pool loses no pose: the frames tracked across its seam follow the
        // camera's side of the cut, or stay where they were tracked when it has no keyframe.
        for r in &out.revocations {
            for (f, _, kf, rel) in self.rec.relative.iter_mut() {
                if let Some((k, new, _)) = r.reanchor(*f, *kf, rel) {
                    (*kf, *rel) = (k, new);
                }
            }
        }
        // Earlier frames posed now (monocular frames the initializer waited on): in frame
        // order among the rest.
        for e in &out.earlier {
            let at = self.rec.relative.partition_point(|(f, ..)| *f < e.frame);
            if self
                .rec
                .relative
                .get(at)
                .is_none_or(|(f, ..)| *f != e.frame)
            {
                self.rec
                    .relative
                    .insert(at, (e.frame, e.t, e.kf, e.relative));
            }
        }
        let mut pose_wc = None;
        let mut map = None;
        if let Some((rel, m, kf)) = out.pose {
            self.rec.relative.push((frame.index, frame.t, kf, rel));
            map = Some(m);
            pose_wc = self
                .machine
                .atlas
                .maps
                .get(&m)
                .and_then(|mp| mp.keyframes.get(&kf))
                .map(|k| k.pose_from_relative(&rel).inverse());
        }
        self.rec.record_states(frame, &out);
        let pools = &self.machine.atlas.pools;
        let result = FrameResult {
            frame: frame.index,
            t: frame.t,
            pose_wc,
            map,
            state: out.state.clone(),
            transitions: out.transitions.clone(),
            flags: out.flags,
            inliers: self.machine.track_inliers,
            pools_accepted: pools[pools_before.min(pools.len())..]
                .iter()
                .map(|p| p.id)
                .collect(),
            pools_revoked: out.revocations.iter().map(|r| r.pool).collect(),
            earlier_frames: out.earlier.iter().map(|e| e.frame).collect(),
        };
        Ok((result, m, out))
    }

    /// The current trajectory: every frame posed so far, camera to world, through its
    /// keyframe as the atlas stands now (the corrections applied so far).
    pub fn trajectory(&self) -> Vec<StampedPose> {
        let kfs = keyframe_index(&self.machine);
        self.rec
            .relative
            .iter()
            .filter_map(|(_, t, kf, rel)| {
                kfs.get(kf).map(|(_, k)| StampedPose {
                    t: *t,
                    pose: k.pose_from_relative(rel).inverse(),
                })
            })
            .collect()
    }

    /// The camera the session was made for.
    pub fn camera(&self) -> &CameraConfig {
        &self.camera
    }

    /// Whether the session is monocular (depth given to `track` is ignored).
    pub fn is_mono(&self) -> bool {
        self.mono
    }

    /// The maps as they stand: keyframe poses and map points.
    pub fn atlas(&self) -> &Atlas {
        &self.machine.atlas
    }

    /// The controller (for the run driver's summary and recordings).
    pub(crate) fn machine(&self) -> &StateMachine {
        &self.machine
    }

    /// Frames given so far.
    pub fn delivered(&self) -> usize {
        self.rec.delivered
    }

    /// The state machine's per-stage timing so far (timing.csv).
    pub fn timing(&self) -> &Timing {
        &self.timing
    }

    pub(crate) fn machine_and_timing(&mut self) -> (&StateMachine, &mut Timing) {
        (&self.machine, &mut self.timing)
    }

    pub(crate) fn timing_mut(&mut self) -> &mut Timing {
        &mut self.timing
    }

    pub(crate) fn recorded_mut(&mut self) -> &mut Recorded {
        &mut self.rec
    }

    pub(crate) fn preprocessor(&self) -> &Preprocessor {
        &self.pre
    }

    /// Saves the atlas for a later session (`Slam::with_atlas`, `homing run --load-map`).
    pub fn save_atlas(&self, path: &std::path::Path) -> Result<()> {
        self.machine
            .atlas
            .save(path, AtlasCamera::from(&self.camera), self.mono)
    }

    /// Interruptible's user stop: Final with its refinement cut to
    /// `mapping.final_refinement_max_s`, then the outputs.
    pub fn request_stop(&mut self) -> Result<SlamOutput> {
        if let Some(last) = self.rec.states.last() {
            self.rec.user_stop = Some((last.frame, last.t));
        }
        self.finish()
    }

    /// End of data: Final (its refinement), then every output. The session takes no more
    /// frames afterwards.
    pub fn finish(&mut self) -> Result<SlamOutput> {
        if self.finished {
            return Err(Error::Invalid("the session is finished".into()));
        }
        self.finished = true;
        let final_state = final_state(&mut self.machine, &mut self.rec, &mut self.timing);
        let posed = resolve_poses(&self.machine, &mut self.rec);
        Ok(SlamOutput {
            trajectory: posed.trajectory,
            trajectory_frames: posed.frames,
            trajectory_maps: posed.maps,
            keyframes: keyframe_rows(&self.machine),
            states: self.rec.states.clone(),
            closures: closure_rows(&self.machine),
            merges: merge_rows(&self.machine),
            lift_offs: self.machine.lift_offs.clone(),
            discarded: self.rec.discarded.clone(),
            final_state,
        })
    }
}

/// What the frame loop recorded, for Final and the outputs.
#[derive(Default)]
pub(crate) struct Recorded {
    pub states: Vec<StateRow>,
    /// Frame poses are kept relative to their reference keyframe, so that the final trajectory
    /// follows the keyframes' optimised poses (as ORB-SLAM does) and frames of merged maps end
    /// up in the merged frame. Keyframe ids are unique across the atlas.
    pub relative: Vec<(usize, f64, KfId, Isometry3<f64>)>,
    /// Poses that did not stand, and why.
    pub discarded: Vec<DiscardedPose>,
    /// The input error that ended the loop (`--strict-input`, or a frame that could not be
    /// processed).
    pub failure: Option<Error>,
    pub delivered: usize,
    /// The frame after which a user stop (SIGINT/SIGTERM) ended the loop.
    pub user_stop: Option<(usize, f64)>,
    pub extraction_reused_ms: f64,
}

impl Recorded {
    /// states.csv's rows for one frame: its state, or one row per transition it made.
    fn record_states(&mut self, frame: &Frame, out: &StepOutput) {
        if self.states.is_empty() && out.transitions.is_empty() {
            self.states.push(StateRow {
                frame: frame.index,
                t: frame.t,
                state: out.state.clone(),
                transition: Some(Transition {
                    from: "(start)".into(),
                    trigger: "start".into(),
                }),
                flags: out.flags,
                map: None,
            });
        } else if out.transitions.is_empty() {
            self.states.push(StateRow {
                frame: frame.index,
                t: frame.t,
                state: out.state.clone(),
                transition: None,
                flags: out.flags,
                map: None,
            });
        }
        for t in &out.transitions {
            self.states.push(StateRow {
                frame: frame.index,
                t: frame.t,
                state: t.to.clone(),
                transition: Some(t.transition.clone()),
                flags: t.flags,
                map: None,
            });
        }
    }
}

/// summary.json's merges: every merge of two maps, confirmed or still provisional.
pub(crate) fn merge_rows(machine: &StateMachine) -> Vec<MergeRow> {
    machine
        .atlas
        .pools
        .iter()
        .filter_map(|p| match p.kind {
            crate::atlas::PoolKind::Merge { into, from, .. } => Some(MergeRow {
                pool: p.id,
                frame: p.frame,
                into,
                from,
                confirmed_frame: p.evidence.as_ref().and_then(|e| e.confirmed),
                rolled_back: p.rolled_back,
            }),
            _ => None,
        })
        .collect()
}

/// Every keyframe of the atlas by id, with its map.
fn keyframe_index(
    machine: &StateMachine,
) -> std::collections::BTreeMap<KfId, (MapId, &crate::map::Keyframe)> {
    machine
        .atlas
        .maps
        .values()
        .flat_map(|m| m.keyframes.values().map(move |k| (k.id, (m.id, k))))
        .collect()
}

/// Final: end of data, a fatal input error or a user stop (Interruptible → Final). Returns the
/// state the controller ends in.
fn final_state(machine: &mut StateMachine, rec: &mut Recorded, timing: &mut Timing) -> String {
    let trigger = if rec.failure.is_some() {
        "input_error"
    } else if rec.user_stop.is_some() {
        crate::control::USER_STOP
    } else {
        "end_of_data"
    };
    let fin = machine.finish(trigger, timing);
    if let Some(last) = rec.states.last() {
        let (frame, t) = (last.frame, last.t);
        for tr in fin.transitions {
            rec.states.push(StateRow {
                frame,
                t,
                state: tr.to,
                transition: Some(tr.transition),
                flags: tr.flags,
                map: None,
            });
        }
    }
    fin.state
}

/// The frames' poses, resolved through their keyframes in the final atlas.
struct Posed {
    trajectory: Vec<StampedPose>,
    /// Each posed frame's index and map.
    frames: Vec<usize>,
    maps: Vec<MapId>,
}

/// Resolves every frame's pose through its keyframe in the final atlas (Final's refinement may
/// have re-estimated it), and names each states.csv row's map.
fn resolve_poses(machine: &StateMachine, rec: &mut Recorded) -> Posed {
    let kf_map = keyframe_index(machine);
    let mut frame_map: std::collections::BTreeMap<usize, u32> = std::collections::BTreeMap::new();
    let mut trajectory: Vec<StampedPose> = Vec::with_capacity(rec.relative.len());
    let mut maps: Vec<MapId> = Vec::with_capacity(rec.relative.len());
    let mut frames: Vec<usize> = Vec::with_capacity(rec.relative.len());
    for (frame, t, kf, rel) in &rec.relative {
        let Some((map, k)) = kf_map.get(kf) else {
            rec.discarded.push(DiscardedPose {
                frame: *frame,
                t: *t,
                reason: "its map was discarded: a map lost on the frame after its first holds one view no other frame confirmed (a false frame)".into(),
            });
            continue;
        };
        // Final's batch refinement may have re-estimated the frame.
        let rel = machine
            .refined_frames
            .get(frame)
            .filter(|(k, _)| k == kf)
            .map_or(rel, |(_, r)| r);
        let pose_wc = k.pose_from_relative(rel).inverse();
        frame_map.insert(*frame, *map);
        maps.push(*map);
        frames.push(*frame);
        trajectory.push(StampedPose {
            t: *t,
            pose: pose_wc,
        });
    }
    for row in rec.states.iter_mut() {
        row.map = frame_map.get(&row.frame).copied();
    }
    Posed {
        trajectory,
        frames,
        maps,
    }
}

/// closures.csv's rows: a candidate still pending when the run ends expired.
fn closure_rows(machine: &StateMachine) -> Vec<ClosureRow> {
    // Merges no later frame confirmed (see `atlas::MergeEvidence`) are reported as provisional.
    let provisional: Vec<PoolId> = merge_rows(machine)
        .iter()
        .filter(|m| !m.rolled_back && m.confirmed_frame.is_none())
        .map(|m| m.pool)
        .collect();
    machine
        .closures
        .iter()
        .cloned()
        .map(|mut c| {
            if c.verdict == "pending" {
                c.verdict = "expired".into();
            }
            if c.verdict == "accepted" && c.pool.is_some_and(|p| provisional.contains(&p)) {
                c.verdict = crate::outputs::ACCEPTED_PROVISIONAL.into();
            }
            c
        })
        .collect()
}

/// keyframes.txt's rows: every keyframe's pose and map.
fn keyframe_rows(machine: &StateMachine) -> Vec<(StampedPose, MapId)> {
    machine
        .atlas
        .maps
        .values()
        .flat_map(|m| {
            m.keyframes.values().map(move |k| {
                (
                    StampedPose {
                        t: k.t,
                        pose: k.pose_cw.inverse(),
                    },
                    m.id,
                )
            })
        })
        .collect()
}
