//! Initializer (paper Table I): Measurements → first local map, reporting `initialized`.
//!
//! RGB-D: one frame with enough keypoints that have a valid depth starts a map whose world frame
//! is that camera's frame.
//!
//! Monocular: one frame cannot be back-projected, so the initializer is a two-view
//! structure-from-motion step (ORB-SLAM2's `Initializer`): it keeps a reference measurement,
//! matches every new measurement to it, and when the two views have enough matches and enough
//! parallax, [`crate::components::two_view::initialize_two_view`] recovers the relative motion and the
//! points. The map then starts with two keyframes (the reference at the origin, the current
//! frame at the recovered pose), refined by a two-view bundle adjustment, with the scale fixed
//! by a median scene depth of 1 (monocular scale is unobservable; this is ORB-SLAM's choice).
//! The initializer only computes; whether it runs is the controller's decision.

use crate::components::aligner::backproject;
use crate::components::map_merger::bundle_adjust;
use crate::components::preprocess::{ImageGeometry, Measurement, match_in_areas};
use crate::components::two_view::{TwoViewParams, initialize_two_view};
use crate::map::{KfId, Map};
use crate::optim::{BaParams, Intrinsics};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector2};

/// Monocular matching: search radius around the reference keypoint's pixel (ORB-SLAM's
/// initializer uses 100 px), best/second-best ratio (0.9) and the largest accepted Hamming
/// distance (ORB-SLAM's TH_LOW).
const MONO_SEARCH_RADIUS_PX: f64 = 100.0;
const MONO_MATCH_RATIO: f64 = 0.9;
const MONO_MAX_DISTANCE: u32 = 50;
/// Fewer matches than this: the reference is replaced by the current frame (ORB-SLAM: 100).
const MONO_MIN_MATCHES: usize = 100;
/// The reference needs this many keypoints to be worth keeping (ORB-SLAM: > 100).
const MONO_MIN_KEYPOINTS: usize = 100;
/// A reference older than this is replaced: the initializer may not have run for a while
/// (tracking resumed in the meantime), and an old view would pair frames far apart in time.
const MONO_MAX_REFERENCE_AGE_S: f64 = 2.0;
/// The first local map of a new map: RGB-D, one frame with at least `min_points` key points
/// with valid depth (up to `max_depth`); monocular, a two-view reconstruction (H or F).
pub struct Initializer {
    pub min_points: usize,
    pub max_depth: f64,
    pub intr: Intrinsics,
    pub scale_factor: f64,
    pub n_levels: u32,
    /// Monocular: the two-view initializer instead of the one-frame RGB-D one.
    pub mono: bool,
    /// Camera and pyramid, for the two-view bundle adjustment.
    pub geo: ImageGeometry,
    /// Monocular: the first view of the pair being tried.
    reference: Option<Measurement>,
    /// Monocular: the frames after the reference that did not make a pair with it, kept so
    /// that they can be posed in the map once a later pair starts it (#67: initialisation
    /// that waits without losing frames). At most `MONO_MAX_REFERENCE_AGE_S` of frames.
    waited: Vec<Measurement>,
    /// Monocular: the frames before the reference (earlier references and the frames that
    /// waited on them), at most `MONO_MAX_REFERENCE_AGE_S` older than the reference, kept so
    /// that a map that starts can pose them too, tracked backwards from its first keyframe.
    before: Vec<Measurement>,
    /// Monocular: the reference and the waited frames of the pair that just started a map,
    /// for [`Initializer::take_waited`], and the frames before the reference.
    started_from: Option<(Measurement, Vec<Measurement>)>,
    started_before: Vec<Measurement>,
    /// Monocular: when the selected two-view model is ambiguous, try the other
    /// ([`TwoViewParams::try_other_model`]); the controller turns it off where a new map
    /// should wait.
    pub try_other_model: bool,
    /// Monocular: keep the frames before the reference (`before`); the controller turns it
    /// off after a loss, where they made the maps worse (decision 0030).
    pub keep_before: bool,
}

/// What [`Initializer::match_to_reference`] found: reference keypoint → current keypoint.
type Matches = Vec<(usize, usize)>;

impl Initializer {
    pub fn new(min_points: usize, max_depth: f64, geo: ImageGeometry, mono: bool) -> Initializer {
        Initializer {
            min_points,
            max_depth,
            intr: geo.intr,
            scale_factor: geo.scale_factor,
            n_levels: geo.n_levels,
            mono,
            geo,
            reference: None,
            waited: Vec::new(),
            before: Vec::new(),
            started_from: None,
            started_before: Vec::new(),
            try_other_model: true,
            keep_before: true,
        }
    }

    /// Fills `map` (an empty map from [`crate::atlas::Atlas::blank_map`]) with its first
    /// keyframes and points, and returns it with the keyframe of `m`; `None` while the
    /// measurements do not allow it yet.
    ///
    /// RGB-D: `None` when the frame has fewer than `min_points` keypoints with depth (too
    /// dark, too close, no depth sensor). Monocular: see `Initializer::try_two_view`.
    pub fn try_initialize(&mut self, m: &Measurement, map: Map) -> Option<(Map, KfId)> {
        if self.mono {
            return self.try_two_view(m, map);
        }
        let mut map = map;
        let usable: Vec<usize> = (0..m.len())
            .filter(|&i| m.depth[i] > 0.0 && (m.depth[i] as f64) <= self.max_depth)
            .collect();
        if usable.len() < self.min_points {
            tracing::debug!(
                "frame {}: {} key points with depth up to {} m, {} needed to start a map",
                m.frame,
                usable.len(),
                self.max_depth,
                self.min_points
            );
            return None;
        }
        let kf = map.add_keyframe(m, Isometry3::identity());
        for i in usable {
            let p = backproject(&self.intr, &m.keypoints[i].un, m.depth[i] as f64);
            map.add_point(kf, i, p, self.scale_factor, self.n_levels);
        }
        Some((map, kf))
    }

    /// Forgets the monocular reference (a map was started, or the controller starts over).
    pub fn reset(&mut self) {
        self.reference = None;
        self.waited.clear();
        self.before.clear();
    }

    /// `m` becomes the reference: the old one and the frames that waited on it join the
    /// frames before it, of which those more than `MONO_MAX_REFERENCE_AGE_S` older than `m`
    /// are dropped (as is all of it when time went backwards).
    fn new_reference(&mut self, m: &Measurement) {
        if let Some(r) = self.reference.take()
            && self.keep_before
        {
            self.before.push(r);
            self.before.append(&mut self.waited);
        }
        self.waited.clear();
        if !self.keep_before {
            self.before.clear();
        }
        if self.before.last().is_some_and(|b| b.t >= m.t) {
            self.before.clear();
        }
        self.before
            .retain(|b| m.t - b.t <= MONO_MAX_REFERENCE_AGE_S);
        self.reference = Some(m.clone());
    }

    /// Monocular, after a map was started: the frames before its first view, in order (see
    /// `before`).
    pub fn take_before(&mut self) -> Vec<Measurement> {
        std::mem::take(&mut self.started_before)
    }

    /// Monocular, after a map was started: its first view (the reference, the map's first
    /// keyframe) and the frames between it and the second, in order. They had no pose when
    /// they came; the map can now give them one.
    pub fn take_waited(&mut self) -> Option<(Measurement, Vec<Measurement>)> {
        self.started_from.take()
    }

    /// Monocular: pairs `m` with the reference view. The first call (and any call where the
    /// pair has too few matches or the reference is stale) makes `m` the reference and returns
    /// `None`; a pair whose two-view geometry is refused (too little parallax, ambiguous)
    /// keeps the reference so that the baseline can grow.
    fn try_two_view(&mut self, m: &Measurement, map: Map) -> Option<(Map, KfId)> {
        let stale = self.reference.as_ref().is_none_or(|r| {
            m.t - r.t > MONO_MAX_REFERENCE_AGE_S || m.t <= r.t || r.len() < MONO_MIN_KEYPOINTS
        });
        if stale {
            self.new_reference(m);
            return None;
        }
        let r = self.reference.as_ref().expect("checked above");
        let matches = match_to_reference(r, m);
        if matches.len() < MONO_MIN_MATCHES {
            tracing::debug!(
                "frame {}: {} matches with reference frame {}: new reference",
                m.frame,
                matches.len(),
                r.frame
            );
            self.new_reference(m);
            return None;
        }
        let x1: Vec<Vector2<f64>> = matches.iter().map(|&(a, _)| r.keypoints[a].un).collect();
        let x2: Vec<Vector2<f64>> = matches.iter().map(|&(_, b)| m.keypoints[b].un).collect();
        let params = TwoViewParams {
            try_other_model: self.try_other_model,
            ..Default::default()
        };
        let rec = match initialize_two_view(&x1, &x2, &self.intr, &params) {
            Ok(rec) => rec,
            Err(rej) => {
                tracing::debug!(
                    "frame {}: two-view with reference frame {} refused ({:?}; {} matches, R_H {:.2}, {} inliers, {} good, parallax {:.2} deg)",
                    m.frame,
                    r.frame,
                    rej.reason,
                    matches.len(),
                    rej.r_h,
                    rej.n_inliers,
                    rej.n_good,
                    rej.parallax_deg
                );
                self.waited.push(m.clone());
                return None;
            }
        };
        let built = self.build_map(r, m, &matches, &rec, map);
        if built.is_some() {
            tracing::info!(
                "frame {}: monocular initialisation with reference frame {} ({:?}, R_H {:.2}, {} matches, {} points, parallax {:.2} deg)",
                m.frame,
                r.frame,
                rec.model,
                rec.r_h,
                matches.len(),
                rec.n_good,
                rec.parallax.orb_deg
            );
            let reference = self.reference.take().expect("paired above");
            self.started_from = Some((reference, std::mem::take(&mut self.waited)));
            self.started_before = std::mem::take(&mut self.before);
        } else {
            self.waited.push(m.clone());
        }
        built
    }

    /// The two-keyframe map of an accepted reconstruction: points from the triangulated
    /// inliers, two-view BA (first keyframe fixed), then the scale set so that the median
    /// depth of the points in the first keyframe is 1. `None` when too few points survive
    /// the BA or the median depth is not positive (ORB-SLAM's checks).
    fn build_map(
        &self,
        r: &Measurement,
        m: &Measurement,
        matches: &Matches,
        rec: &crate::components::two_view::TwoViewReconstruction,
        mut map: Map,
    ) -> Option<(Map, KfId)> {
        let pose2 = Isometry3::from_parts(
            Translation3::from(rec.translation),
            UnitQuaternion::from_rotation_matrix(&rec.rotation),
        );
        let k1 = map.add_keyframe(r, Isometry3::identity());
        let k2 = map.add_keyframe(m, pose2);
        let (sf, nl) = (self.scale_factor, self.n_levels);
        let mut pids = Vec::new();
        for (&(a, b), p) in matches.iter().zip(&rec.points) {
            let Some(p) = p else { continue };
            let pid = map.add_point(k1, a, *p, sf, nl);
            map.observe(k2, b, pid);
            pids.push(pid);
        }
        for pid in &pids {
            map.update_point(*pid, sf, nl);
        }
        map.update_covisibility(k1);
        map.update_covisibility(k2);
        let first = BaParams {
            iterations: 20,
            ..Default::default()
        };
        let second = BaParams {
            iterations: 20,
            huber: false,
            ..Default::default()
        };
        bundle_adjust(&mut map, &self.geo, &[k1, k2], &first, &second);
        // Points the BA left with one view are unconstrained in depth.
        let lone: Vec<_> = map
            .points
            .values()
            .filter(|p| p.observations.len() < 2)
            .map(|p| p.id)
            .collect();
        for pid in lone {
            map.remove_point(pid);
        }
        let n_tracked = map.keyframes[&k2].n_points();
        let mut depths: Vec<f64> = map.points.values().map(|p| p.position.z).collect();
        if n_tracked < MONO_MIN_MATCHES || depths.is_empty() {
            tracing::debug!(
                "frame {}: two-view map refused: {n_tracked} points after BA",
                m.frame
            );
            return None;
        }
        depths.sort_by(f64::total_cmp);
        let median = depths[(depths.len() - 1) / 2];
        if median <= 0.0 || !median.is_finite() {
            tracing::debug!(
                "frame {}: two-view map refused: median depth {median}",
                m.frame
            );
            return None;
        }
        let s = 1.0 / median;
        let kf2 = map.keyframes.get_mut(&k2).expect("added above");
        kf2.pose_cw.translation.vector *= s;
        let ids: Vec<_> = map.points.keys().copied().collect();
        for pid in ids {
            if let Some(p) = map.points.get_mut(&pid) {
                p.position *= s;
            }
            map.update_point(pid, sf, nl);
        }
        map.update_covisibility(k1);
        map.update_covisibility(k2);
        Some((map, k2))
    }
}

/// ORB-SLAM's `SearchForInitialization`: each reference keypoint is matched to the keypoints
/// of `m` near the same pixel (the camera moved little between the views) at a similar pyramid
/// level, with a distance limit and Lowe's ratio; a current keypoint keeps only its best
/// reference match; matches whose orientation change disagrees with the dominant ones
/// (rotation histogram) are dropped. Sorted by reference keypoint: deterministic.
fn match_to_reference(r: &Measurement, m: &Measurement) -> Matches {
    let mut matches = match_in_areas(
        r,
        m,
        |a| Some((r.keypoints[a].un, MONO_SEARCH_RADIUS_PX)),
        MONO_MAX_DISTANCE,
        MONO_MATCH_RATIO,
    );
    matches.sort_unstable();
    matches
}
