//! `homing bench overlap`: how much place evidence two stretches of a sequence share, measured
//! with the ground truth instead of the pipeline.
//!
//! When no closure or relocalization joins two parts of a run, the question is whether the
//! components missed evidence or there was none. This probe answers it without place
//! recognition: every key point with depth of a reference frame is carried into a query frame
//! by the ground-truth poses; it counts as *visible* when it lands in the image and the query's
//! depth there agrees (not occluded, within the sensor's range), and as *matched* when a query
//! key point within the search radius has a descriptor within the Hamming distance the
//! components accept (50: the descriptor searches of closures and merges; the tracker's
//! `max_descriptor_distance` for projection searches). The same count with the query camera
//! turned by [`CONTROL_TURN_DEG`] gives the chance level of those descriptor distances.
//! Frames are processed exactly as a run's front end does (same camera, same ORB settings).

use crate::components::aligner::backproject;
use crate::components::loop_validator::SEARCH_MAX_DISTANCE;
use crate::components::preprocess::{ImageGeometry, Measurement, Preprocessor, hamming};
use crate::error::{Error, Result};
use crate::eval::run::gt_at;
use crate::io::tum::FrameSource;
use nalgebra::{Isometry3, Point3, UnitQuaternion, Vector3};
use std::fmt::Write as _;
use std::path::Path;

/// Turn of the query camera about its own vertical axis for the chance-level control: at
/// fx 262 (320 × 240) a point moves about 45 px, at fx 525 about 90 px, far outside any
/// search radius.
pub const CONTROL_TURN_DEG: f64 = 10.0;
/// Ground-truth stamps farther than this from a frame leave the frame out.
const MAX_GT_DT: f64 = 0.02;

/// The control's turn, in the query camera's frame.
fn control_turn() -> Isometry3<f64> {
    Isometry3::from_parts(
        nalgebra::Translation3::identity(),
        UnitQuaternion::from_axis_angle(&Vector3::y_axis(), CONTROL_TURN_DEG.to_radians()),
    )
}

/// What the probe compares: two stretches of one sequence, in seconds from its first frame.
#[derive(Debug, Clone)]
pub struct OverlapOptions {
    pub reference: (f64, f64),
    pub query: (f64, f64),
    /// Take every n-th frame of each stretch.
    pub every: usize,
    /// Search radius around the ground-truth projection, level-0 pixels.
    pub radius_px: f64,
}

/// The best reference frame for one query frame.
#[derive(Debug, Clone, PartialEq)]
pub struct OverlapRow {
    /// Query and best reference frame, seconds from the sequence's first frame.
    pub query_t: f64,
    pub reference_t: f64,
    /// Reference key points the query sees (in the image, depth agrees).
    pub visible: usize,
    /// Of those, found by a descriptor within 50, and within the tracker's distance.
    pub matched_search: usize,
    pub matched_tracker: usize,
    /// The same two counts with the query camera turned by [`CONTROL_TURN_DEG`].
    pub control_search: usize,
    pub control_tracker: usize,
}

/// A frame's features, its depth image and its ground-truth pose (camera to world).
struct Probe {
    t: f64,
    m: Measurement,
    depth: Option<crate::io::tum::DepthImage>,
    pose: Isometry3<f64>,
}

/// The image geometry the run uses for this camera and pyramid.
fn geometry(camera: &crate::config::CameraConfig, orb: &crate::config::OrbConfig) -> ImageGeometry {
    ImageGeometry::new(
        camera.intrinsics(),
        camera.width,
        camera.height,
        orb.scale_factor,
        orb.n_levels,
    )
}

/// Frame `i` with its features and ground-truth pose; `None` without ground truth near it.
fn probe_frame(
    seq: &crate::io::Sequence,
    pre: &mut Preprocessor,
    gt: &[crate::io::tum::StampedPose],
    i: usize,
    sequence: &Path,
) -> Result<Option<Probe>> {
    let Some(pose) = gt_at(gt, seq.timestamp(i), MAX_GT_DT) else {
        return Ok(None);
    };
    let frame = seq.load(i)?;
    if frame.depth.is_none() {
        return Err(Error::file(
            sequence,
            "is read without depth (a monocular config?); the overlap probe needs depth",
        ));
    }
    let m = pre.process(&frame)?;
    Ok(Some(Probe {
        t: frame.t,
        m,
        depth: frame.depth,
        pose,
    }))
}

/// The probe's result: per query frame, its best reference frame.
#[derive(Debug, Clone, PartialEq)]
pub struct OverlapReport {
    pub rows: Vec<OverlapRow>,
    /// The tracker's Hamming distance the second count used.
    pub tracker_distance: u32,
}

/// Runs the probe on `sequence` (the run's camera and ORB settings under `config`).
pub fn overlap(
    sequence: &Path,
    config: Option<&Path>,
    opts: &OverlapOptions,
) -> Result<OverlapReport> {
    let (seq, camera, orb) = crate::system::open_run_front_end(sequence, config, false)?;
    let tracker_distance = match config {
        Some(p) => crate::config::Config::load(p)?,
        None => crate::config::Config::default(),
    }
    .tracker
    .max_descriptor_distance;
    let gt = seq
        .groundtruth()?
        .ok_or_else(|| Error::file(sequence, "has no ground truth; the overlap probe needs it"))?;
    let mut pre = Preprocessor::new(&camera, &orb)?;
    let t0 = seq.timestamp(0);
    let mut load = |(a, b): (f64, f64)| -> Result<Vec<Probe>> {
        let mut out = Vec::new();
        let idx: Vec<usize> = (0..seq.len())
            .filter(|&i| (a..=b).contains(&(seq.timestamp(i) - t0)))
            .step_by(opts.every.max(1))
            .collect();
        for i in idx {
            if let Some(mut p) = probe_frame(&seq, &mut pre, &gt, i, sequence)? {
                p.t -= t0;
                out.push(p);
            }
        }
        if out.is_empty() {
            return Err(Error::file(
                sequence,
                format!("has no frame with ground truth between {a} and {b} s from its start"),
            ));
        }
        Ok(out)
    };
    let refs = load(opts.reference)?;
    let queries = load(opts.query)?;
    let turn = control_turn();
    let k = geometry(&camera, &orb);
    let rows = queries
        .iter()
        .map(|q| {
            let turned = q.pose * turn;
            refs.iter()
                .map(|r| {
                    let (visible, ms, mt) =
                        count(&k, r, q, &q.pose, opts.radius_px, tracker_distance);
                    let (_, cs, ct) = count(&k, r, q, &turned, opts.radius_px, tracker_distance);
                    OverlapRow {
                        query_t: q.t,
                        reference_t: r.t,
                        visible,
                        matched_search: ms,
                        matched_tracker: mt,
                        control_search: cs,
                        control_tracker: ct,
                    }
                })
                .max_by_key(|row| (row.matched_search, row.matched_tracker, row.visible))
                .expect("at least one reference frame")
        })
        .collect();
    Ok(OverlapReport {
        rows,
        tracker_distance,
    })
}

/// Reference key points of `r` visible from `q` placed at `q_pose`, and how many of them a
/// query descriptor within `radius` pixels matches at 50 and at `tracker_distance`.
fn count(
    k: &ImageGeometry,
    r: &Probe,
    q: &Probe,
    q_pose: &Isometry3<f64>,
    radius: f64,
    tracker_distance: u32,
) -> (usize, usize, usize) {
    let to_query = q_pose.inverse() * r.pose;
    let (mut visible, mut search, mut tracker) = (0, 0, 0);
    for (i, kp) in r.m.keypoints.iter().enumerate() {
        let d = r.m.depth[i] as f64;
        if d <= 0.0 {
            continue;
        }
        let p = to_query * Point3::from(backproject(&k.intr, &kp.un, d));
        let Some(uv) = k.project_in_image(&p.coords) else {
            continue;
        };
        let (u, v) = (uv.x, uv.y);
        // Sampled at the undistorted pixel: a few pixels off near the border of a distorted
        // camera, which only makes the count conservative there.
        if let Some(depth) = &q.depth {
            let z = depth.get(u as u32, v as u32) as f64;
            if z <= 0.0 || (z - p.z).abs() > 0.03 + 0.05 * p.z {
                continue;
            }
        }
        visible += 1;
        let best =
            q.m.grid
                .in_area(&q.m.keypoints, u, v, radius, 0, u8::MAX)
                .into_iter()
                .map(|j| hamming(&r.m.descriptors[i], &q.m.descriptors[j]))
                .min();
        if let Some(h) = best {
            search += usize::from(h <= SEARCH_MAX_DISTANCE);
            tracker += usize::from(h <= tracker_distance);
        }
    }
    (visible, search, tracker)
}

/// A place counts as in view again when a frame after the event finds at least this many
/// key points of the frames before it by descriptor (≤ 50, within [`SEEN_AGAIN_RADIUS_PX`] of
/// the ground-truth projection): the evidence a validation needs (`min_inliers`, 30).
pub const SEEN_AGAIN_MIN_MATCHED: usize = 30;
/// Search radius of the seen-again probe (level-0 pixels; `bench overlap`'s default).
pub const SEEN_AGAIN_RADIUS_PX: f64 = 8.0;
/// The place before an event: the frames of this many seconds before it.
pub const SEEN_AGAIN_BEFORE_S: f64 = 1.0;
/// Every this many frames are probed, before and after the event.
pub const SEEN_AGAIN_EVERY: usize = 3;

/// For each event (first frame of the event, first frame after it: sequence indices), the
/// first frame after it that sees the place before it again by the ground truth (see
/// [`SEEN_AGAIN_MIN_MATCHED`]), `None` when no frame to the end of the sequence does. The
/// sequence is opened once and each probed frame extracted once for all events.
pub fn seen_again(
    sequence: &Path,
    config: Option<&Path>,
    events: &[(usize, usize)],
) -> Result<Vec<Option<usize>>> {
    let (seq, camera, orb) = crate::system::open_run_front_end(sequence, config, false)?;
    let gt = seq
        .groundtruth()?
        .ok_or_else(|| Error::file(sequence, "has no ground truth; the overlap probe needs it"))?;
    let mut pre = Preprocessor::new(&camera, &orb)?;
    let k = geometry(&camera, &orb);
    let mut cache: std::collections::BTreeMap<usize, Option<Probe>> = Default::default();
    let mut load =
        |cache: &mut std::collections::BTreeMap<usize, Option<Probe>>, i: usize| -> Result<()> {
            if let std::collections::btree_map::Entry::Vacant(e) = cache.entry(i) {
                e.insert(probe_frame(&seq, &mut pre, &gt, i, sequence)?);
            }
            Ok(())
        };
    let mut out = Vec::with_capacity(events.len());
    for &(start, end) in events {
        let t_start = seq.timestamp(start.min(seq.len().saturating_sub(1)));
        let before: Vec<usize> = (0..start)
            .filter(|&i| t_start - seq.timestamp(i) <= SEEN_AGAIN_BEFORE_S)
            .step_by(SEEN_AGAIN_EVERY)
            .collect();
        for &i in &before {
            load(&mut cache, i)?;
        }
        let mut found = None;
        for q in (end..seq.len()).step_by(SEEN_AGAIN_EVERY) {
            load(&mut cache, q)?;
            let Some(qp) = &cache[&q] else { continue };
            let best = before
                .iter()
                .filter_map(|i| cache[i].as_ref())
                .map(|r| count(&k, r, qp, &qp.pose, SEEN_AGAIN_RADIUS_PX, 0).1)
                .max()
                .unwrap_or(0);
            if best >= SEEN_AGAIN_MIN_MATCHED {
                found = Some(q);
                break;
            }
        }
        out.push(found);
    }
    Ok(out)
}

impl OverlapReport {
    /// The rows as a Markdown table, with the command that produced them.
    pub fn markdown(&self, command: &str) -> String {
        let (rows, tracker_distance) = (&self.rows, self.tracker_distance);
        let mut s = String::new();
        let _ = writeln!(s, "`{command}`\n");
        let _ = writeln!(
            s,
            "| query t (s) | best reference t (s) | visible | matched ≤ {SEARCH_MAX_DISTANCE} | \
         matched ≤ {tracker_distance} | control ≤ {SEARCH_MAX_DISTANCE} | control ≤ {tracker_distance} |"
        );
        let _ = writeln!(s, "|---:|---:|---:|---:|---:|---:|---:|");
        for r in rows {
            let _ = writeln!(
                s,
                "| {:.2} | {:.2} | {} | {} | {} | {} | {} |",
                r.query_t,
                r.reference_t,
                r.visible,
                r.matched_search,
                r.matched_tracker,
                r.control_search,
                r.control_tracker
            );
        }
        let _ = writeln!(
            s,
            "\nvisible: reference key points with depth that land in the query image where its depth \
         agrees; matched: of those, found by a query descriptor within the Hamming distance; \
         control: the same with the query camera turned by {CONTROL_TURN_DEG}° (chance level)."
        );
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::tum::{DepthImage, StampedPose};
    use crate::optim::Intrinsics;
    use nalgebra::Vector2;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn k() -> ImageGeometry {
        ImageGeometry::new(Intrinsics::TUM_FREIBURG1, 640, 480, 1.2, 8)
    }

    /// A wall 2 m in front of the camera at `pose`: key points on a 40 px lattice, each with
    /// its own descriptor, and a depth image that reads the wall everywhere.
    fn wall_view(pose: Isometry3<f64>) -> Probe {
        let uvs: Vec<Vector2<f64>> = (1..15)
            .flat_map(|i| (1..11).map(move |j| Vector2::new(40.0 * i as f64, 40.0 * j as f64)))
            .collect();
        // Random descriptors: any two are about 128 bits apart.
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let descriptors = (0..uvs.len()).map(|_| rng.random()).collect();
        let mut depth = DepthImage::new(640, 480);
        depth.data.fill(2.0);
        Probe {
            t: 0.0,
            m: Measurement::synthetic(0, uvs, 0.0, 2.0, descriptors),
            depth: Some(depth),
            pose,
        }
    }

    #[test]
    fn the_same_view_is_found_and_the_turned_control_is_not() {
        let r = wall_view(Isometry3::identity());
        let (visible, search, tracker) = count(&k(), &r, &r, &r.pose, 8.0, 64);
        assert_eq!((visible, search, tracker), (140, 140, 140));
        let turned = r.pose * control_turn();
        let (visible, search, _) = count(&k(), &r, &r, &turned, 8.0, 64);
        // The wall still fills most of the turned view (its depth agrees), but every key point
        // lands about 90 px from its own, where only other descriptors are.
        assert!(visible > 90, "{visible} visible");
        assert_eq!(search, 0);
    }

    #[test]
    fn occluded_or_out_of_range_points_are_not_visible() {
        let r = wall_view(Isometry3::identity());
        let mut q = wall_view(Isometry3::identity());
        // Something 1 m in front of the query camera hides the wall.
        q.depth.as_mut().unwrap().data.fill(1.0);
        assert_eq!(count(&k(), &r, &q, &q.pose, 8.0, 64), (0, 0, 0));
        // No reading (beyond the sensor's range) is no evidence either.
        q.depth.as_mut().unwrap().data.fill(0.0);
        assert_eq!(count(&k(), &r, &q, &q.pose, 8.0, 64), (0, 0, 0));
    }

    #[test]
    fn ground_truth_is_taken_only_near_the_frame() {
        let gt: Vec<StampedPose> = [0.0, 0.1, 0.2]
            .iter()
            .map(|&t| StampedPose {
                t,
                pose: Isometry3::translation(t, 0.0, 0.0),
            })
            .collect();
        let p = gt_at(&gt, 0.105, MAX_GT_DT).unwrap();
        assert!((p.translation.vector.x - 0.1).abs() < 1e-12);
        assert!(gt_at(&gt, 0.15, MAX_GT_DT).is_none());
        assert!(gt_at(&gt, 0.3, MAX_GT_DT).is_none());
    }
}
