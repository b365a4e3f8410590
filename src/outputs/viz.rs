//! Visualiser: the run as a rerun recording (`homing run --rerun FILE.rrd`, or
//! `--rerun-connect ADDR` for a live viewer). It only looks at what the components and the
//! controller produced; the run's outputs are the same with or without it.
//!
//! The rerun SDK is ~400 crates, so it is behind the `rerun` cargo feature
//! (`cargo build --features rerun`); without it the options are refused with that hint.
//!
//! Entities (world = the first camera of each map, x right, y down, z forward):
//!
//! | entity | what | when |
//! |---|---|---|
//! | `world/camera` | camera-to-world pose in its map | frames with a pose |
//! | `world/camera/image` | pinhole and the colour image (JPEG) | every frame |
//! | `world/camera/image/keypoints` | keypoints: green = matched to a map point by the tracker, red = not | every frame |
//! | `world/maps/<id>/points` | map points, a colour per map | when the atlas changes |
//! | `world/maps/<id>/keyframes` | keyframe centres | when the atlas changes |
//! | `world/maps/<id>/trajectory` | frame positions so far in that map | every frame with a pose |
//! | `world/maps/<id>/closures` | standing closure edges between keyframe centres | when the atlas changes |
//! | `state` | transitions as text (`from -> to (trigger)`) | on transitions |
//! | `state/index` | the controller state as a number (scalar timeline) | every frame |
//!
//! Timelines: `frame` (index in the unperturbed sequence) and `time` (seconds since the first
//! frame).

use crate::components::preprocess::Measurement;
use crate::control::{State, StateMachine, StepOutput};
use crate::error::{Error, Result};
use crate::io::tum::Frame;
use crate::optim::Intrinsics;
use std::path::PathBuf;

/// Where the recording goes.
#[derive(Debug, Clone, PartialEq)]
pub enum RerunTarget {
    /// An `.rrd` file, written next to its final name and renamed when complete.
    File(PathBuf),
    /// A running viewer (`rerun` started with its gRPC server), e.g.
    /// `rerun+http://127.0.0.1:9876/proxy`; a bare `HOST:PORT` is completed to that form.
    Connect(String),
}

/// The number of a state on the `state/index` timeline: its position in the paper's order.
pub fn state_index(s: State) -> i64 {
    match s {
        State::Init => 0,
        State::Idle => 1,
        State::Core => 2,
        State::Mapping => 2,
        State::Relocalization => 3,
        State::Localized => 4,
        State::CorruptedMap => 5,
        State::Final => 6,
    }
}

/// A colour per map id (tab10), so merged maps change colour to the survivor's.
pub fn map_colour(id: u32) -> [u8; 3] {
    const TAB10: [[u8; 3]; 10] = [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
        [188, 189, 34],
        [23, 190, 207],
    ];
    TAB10[id as usize % TAB10.len()]
}

#[cfg(not(feature = "rerun"))]
mod imp {
    use super::*;

    /// Stand-in when built without the `rerun` feature: asking for it is an error.
    pub struct Visualizer;

    impl Visualizer {
        pub fn open(_: &RerunTarget, _: &Intrinsics, _: (u32, u32)) -> Result<Self> {
            Err(Error::Invalid(
                "this homing was built without rerun support; rebuild with \
                 `cargo build --release --features rerun` to use --rerun/--rerun-connect"
                    .into(),
            ))
        }
        pub fn log_frame(
            &mut self,
            _: &Frame,
            _: &Measurement,
            _: &StateMachine,
            _: &StepOutput,
        ) -> Result<()> {
            Ok(())
        }
        pub fn finish(self) -> Result<()> {
            Ok(())
        }
    }
}

#[cfg(feature = "rerun")]
mod imp {
    use super::*;
    use nalgebra::Isometry3;
    use std::collections::{BTreeMap, BTreeSet};

    pub struct Visualizer {
        rec: rerun::RecordingStream,
        /// `(temporary, final)` paths of an `.rrd` being written.
        file: Option<(PathBuf, PathBuf)>,
        t0: Option<f64>,
        /// Frame positions per map, in that map's frame.
        trajectories: BTreeMap<u32, Vec<[f32; 3]>>,
        /// What the atlas looked like when its maps were last logged.
        atlas_key: (usize, usize, usize),
        logged_maps: BTreeSet<u32>,
        current_map: Option<u32>,
    }

    fn rr_err(what: &str, e: impl std::fmt::Display) -> Error {
        Error::Invalid(format!("rerun: {what}: {e}"))
    }

    fn p3(v: &nalgebra::Vector3<f64>) -> [f32; 3] {
        [v.x as f32, v.y as f32, v.z as f32]
    }

    fn transform(pose_wc: &Isometry3<f64>) -> rerun::Transform3D {
        let q = pose_wc.rotation.quaternion();
        rerun::Transform3D::from_translation_rotation(
            p3(&pose_wc.translation.vector),
            rerun::Quaternion::from_xyzw([q.i as f32, q.j as f32, q.k as f32, q.w as f32]),
        )
    }

    impl Visualizer {
        pub fn open(target: &RerunTarget, k: &Intrinsics, size: (u32, u32)) -> Result<Self> {
            let builder = rerun::RecordingStreamBuilder::new("homing").default_enabled(true);
            let (rec, file) = match target {
                RerunTarget::File(path) => {
                    let name = path
                        .file_name()
                        .ok_or_else(|| Error::file(path, "--rerun needs a file name"))?;
                    let mut tmp_name = std::ffi::OsString::from(".");
                    tmp_name.push(name);
                    tmp_name.push(".partial");
                    let tmp = path.with_file_name(tmp_name);
                    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
                        std::fs::create_dir_all(dir)
                            .map_err(|e| Error::file(dir, format!("cannot create: {e}")))?;
                    }
                    let rec = builder
                        .save(&tmp)
                        .map_err(|e| Error::file(path, format!("cannot write: {e}")))?;
                    (rec, Some((tmp, path.clone())))
                }
                RerunTarget::Connect(addr) => {
                    let url = if addr.contains("://") {
                        addr.clone()
                    } else {
                        format!("rerun+http://{addr}/proxy")
                    };
                    // The SDK connects lazily and would wait for ever at the end for a viewer
                    // that is not there: check that something listens first.
                    let authority = url
                        .split("://")
                        .nth(1)
                        .and_then(|r| r.split('/').next())
                        .unwrap_or("");
                    let reachable = std::net::ToSocketAddrs::to_socket_addrs(authority)
                        .ok()
                        .into_iter()
                        .flatten()
                        .any(|a| {
                            std::net::TcpStream::connect_timeout(
                                &a,
                                std::time::Duration::from_secs(2),
                            )
                            .is_ok()
                        });
                    if !reachable {
                        return Err(Error::Invalid(format!(
                            "--rerun-connect: no rerun viewer listens at {url} (start `rerun` \
                             first, or write a file with --rerun FILE.rrd)"
                        )));
                    }
                    let rec = builder
                        .connect_grpc_opts(url.clone())
                        .map_err(|e| rr_err(&format!("cannot connect to {url}"), e))?;
                    (rec, None)
                }
            };
            let log = |path: &str, what: &dyn rerun::AsComponents| {
                rec.log_static(path, what)
                    .map_err(|e| rr_err(&format!("cannot log {path}"), e))
            };
            log("world", &rerun::ViewCoordinates::RDF())?;
            log(
                "world/camera/image",
                &rerun::Pinhole::from_focal_length_and_resolution(
                    [k.fx as f32, k.fy as f32],
                    [size.0 as f32, size.1 as f32],
                )
                .with_principal_point([k.cx as f32, k.cy as f32])
                .with_image_plane_distance(0.1),
            )?;
            Ok(Self {
                rec,
                file,
                t0: None,
                trajectories: BTreeMap::new(),
                atlas_key: (usize::MAX, 0, 0),
                logged_maps: BTreeSet::new(),
                current_map: None,
            })
        }

        fn log(&self, path: &str, what: &dyn rerun::AsComponents) -> Result<()> {
            self.rec
                .log(path, what)
                .map_err(|e| rr_err(&format!("cannot log {path}"), e))
        }

        /// Logs one processed frame: image, keypoints, pose, trajectory, state; the maps when
        /// the atlas changed.
        pub fn log_frame(
            &mut self,
            frame: &Frame,
            m: &Measurement,
            machine: &StateMachine,
            out: &StepOutput,
        ) -> Result<()> {
            let t0 = *self.t0.get_or_insert(frame.t);
            self.rec.set_time_sequence("frame", frame.index as i64);
            self.rec.set_duration_secs("time", frame.t - t0);

            let mut jpeg = Vec::new();
            image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 80)
                .encode_image(&frame.rgb)
                .map_err(|e| rr_err("cannot encode the image", e))?;
            self.log(
                "world/camera/image",
                &rerun::EncodedImage::from_file_contents(jpeg),
            )?;
            let matched = &machine.track_matched;
            let (pos, col): (Vec<[f32; 2]>, Vec<[u8; 3]>) = m
                .keypoints
                .iter()
                .enumerate()
                .map(|(i, kp)| {
                    let c = if matched.get(i).copied().unwrap_or(false) {
                        [40, 200, 40]
                    } else {
                        [230, 50, 50]
                    };
                    ([kp.raw.x as f32, kp.raw.y as f32], c)
                })
                .unzip();
            self.log(
                "world/camera/image/keypoints",
                &rerun::Points2D::new(pos)
                    .with_colors(
                        col.into_iter()
                            .map(|c| rerun::Color::from_rgb(c[0], c[1], c[2])),
                    )
                    .with_radii([2.0f32]),
            )?;

            if let Some((rel, map, kf)) = &out.pose {
                let pose_cw = machine
                    .atlas
                    .maps
                    .get(map)
                    .and_then(|mp| mp.keyframes.get(kf))
                    .map(|k| k.pose_from_relative(rel));
                if let Some(pose_cw) = pose_cw {
                    let pose_wc = pose_cw.inverse();
                    self.log("world/camera", &transform(&pose_wc))?;
                    let traj = self.trajectories.entry(*map).or_default();
                    traj.push(p3(&pose_wc.translation.vector));
                    let strip = traj.clone();
                    let c = map_colour(*map);
                    self.log(
                        &format!("world/maps/{map}/trajectory"),
                        &rerun::LineStrips3D::new([strip])
                            .with_colors([rerun::Color::from_rgb(c[0], c[1], c[2])])
                            .with_radii([rerun::Radius::new_ui_points(1.0)]),
                    )?;
                    self.current_map = Some(*map);
                }
            }

            for tr in &out.transitions {
                let text = format!(
                    "{} -> {} ({})",
                    tr.transition.from, tr.to, tr.transition.trigger
                );
                self.log(
                    "state",
                    &rerun::TextLog::new(text).with_level(rerun::TextLogLevel::INFO),
                )?;
            }
            self.log(
                "state/index",
                &rerun::Scalars::single(state_index(machine.state) as f64),
            )?;

            let key = (
                machine.atlas.n_keyframes(),
                machine.atlas.maps.len(),
                machine.atlas.pools.len(),
            );
            if key != self.atlas_key || !out.revocations.is_empty() {
                self.atlas_key = key;
                self.log_maps(machine)?;
            }
            Ok(())
        }

        fn log_maps(&mut self, machine: &StateMachine) -> Result<()> {
            let atlas = &machine.atlas;
            let now: BTreeSet<u32> = atlas.maps.keys().copied().collect();
            for gone in self.logged_maps.difference(&now) {
                self.rec
                    .log(format!("world/maps/{gone}"), &rerun::Clear::recursive())
                    .map_err(|e| rr_err("cannot clear a map", e))?;
                self.trajectories.remove(gone);
            }
            for (id, map) in &atlas.maps {
                let c = map_colour(*id);
                let colour = rerun::Color::from_rgb(c[0], c[1], c[2]);
                let points: Vec<[f32; 3]> = map.points.values().map(|p| p3(&p.position)).collect();
                self.log(
                    &format!("world/maps/{id}/points"),
                    &rerun::Points3D::new(points)
                        .with_colors([colour])
                        .with_radii([rerun::Radius::new_ui_points(1.5)]),
                )?;
                let centre =
                    |kf: &crate::map::Keyframe| p3(&kf.pose_cw.inverse().translation.vector);
                let centres: Vec<[f32; 3]> = map.keyframes.values().map(centre).collect();
                self.log(
                    &format!("world/maps/{id}/keyframes"),
                    &rerun::Points3D::new(centres)
                        .with_colors([colour])
                        .with_radii([rerun::Radius::new_ui_points(5.0)]),
                )?;
                let edges: Vec<Vec<[f32; 3]>> = atlas
                    .pools
                    .iter()
                    .filter(|p| !p.rolled_back)
                    .flat_map(|p| &p.edges)
                    .filter_map(|e| {
                        let a = map.keyframes.get(&e.query)?;
                        let b = map.keyframes.get(&e.matched)?;
                        Some(vec![centre(a), centre(b)])
                    })
                    .collect();
                self.log(
                    &format!("world/maps/{id}/closures"),
                    &rerun::LineStrips3D::new(edges)
                        .with_colors([rerun::Color::from_rgb(255, 200, 0)])
                        .with_radii([rerun::Radius::new_ui_points(2.0)]),
                )?;
            }
            self.logged_maps = now;
            Ok(())
        }

        /// Flushes the recording; an `.rrd` gets its final name only now.
        pub fn finish(self) -> Result<()> {
            // A file flushes in well under this; a viewer that went away must not hang the run.
            let flushed = self
                .rec
                .flush_with_timeout(std::time::Duration::from_secs(30));
            match (&self.file, flushed) {
                (_, Ok(())) => {}
                (Some(_), Err(e)) => return Err(rr_err("cannot flush the recording", e)),
                (None, Err(e)) => {
                    tracing::warn!("rerun: the viewer did not take the whole recording: {e}")
                }
            }
            drop(self.rec);
            if let Some((tmp, path)) = &self.file {
                std::fs::rename(tmp, path)
                    .map_err(|e| Error::file(path, format!("cannot write: {e}")))?;
            }
            Ok(())
        }
    }
}

pub use imp::Visualizer;
