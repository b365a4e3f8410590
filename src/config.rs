//! Typed configuration (TOML, one format everywhere).
//!
//! Every section rejects unknown keys (a typo must not silently fall back to a default) and
//! every numeric value is range-checked after parsing; both kinds of error name the file, the
//! line and the dotted key. All sections have defaults, so a config file only needs what it
//! changes. The camera is special: it usually comes from the sequence (see [`resolve_camera`]).

use crate::error::{Error, Result, read_text};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Pinhole camera with radial-tangential (OpenCV "plumb bob") distortion.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    /// Free-form name printed when the camera is chosen (e.g. "TUM freiburg1").
    #[serde(default)]
    pub name: String,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    #[serde(default)]
    pub k1: f64,
    #[serde(default)]
    pub k2: f64,
    #[serde(default)]
    pub p1: f64,
    #[serde(default)]
    pub p2: f64,
    #[serde(default)]
    pub k3: f64,
    pub width: u32,
    pub height: u32,
    /// Depth image units per metre (TUM: 5000; freiburg2 uses 5208 as in ORB-SLAM).
    #[serde(default = "default_depth_scale")]
    pub depth_scale: f64,
    #[serde(default = "default_fps")]
    pub fps: f64,
    /// Rolling-shutter readout: seconds from the exposure of the first image row to the last
    /// (0 = global shutter). The frame's time stamp is taken to be the middle row's time, and
    /// the tracker and bundle adjustment place every keypoint at its own row's pose (a
    /// constant-velocity model of the camera). A Kinect's colour camera is rolling shutter;
    /// ignoring it turns the skew of fast frames into centimetres of pose error.
    #[serde(default)]
    pub readout_s: f64,
    /// How much a depth reading weighs in pose refinement and bundle adjustment: it enters as
    /// the disparity of a virtual stereo pair with this baseline (ORB-SLAM's `Camera.bf` =
    /// fx · baseline), with the keypoint's pixel σ; a larger baseline trusts depth more.
    /// TUM's Kinects and the synthetic sensor: 0.08 m (ORB-SLAM's bf = 40); set it per sensor.
    #[serde(default = "default_virtual_baseline")]
    pub virtual_baseline_m: f64,
}

fn default_depth_scale() -> f64 {
    5000.0
}
/// ORB-SLAM's TUM setting (bf = 40 ≈ fx · 0.08 m).
pub fn default_virtual_baseline() -> f64 {
    0.08
}
fn default_fps() -> f64 {
    30.0
}

impl CameraConfig {
    /// Pinhole intrinsics of the undistorted image, with the virtual stereo baseline that
    /// weighs depth (`bf = fx · virtual_baseline_m`).
    pub fn intrinsics(&self) -> crate::optim::Intrinsics {
        crate::optim::Intrinsics {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            bf: self.fx * self.virtual_baseline_m,
        }
    }

    pub fn has_distortion(&self) -> bool {
        [self.k1, self.k2, self.p1, self.p2, self.k3]
            .iter()
            .any(|&k| k != 0.0)
    }
}

/// ORB extraction (ORB-SLAM defaults).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OrbConfig {
    pub n_features: u32,
    pub n_levels: u32,
    pub scale_factor: f64,
    /// FAST threshold tried first in each grid cell ...
    pub ini_fast_threshold: u32,
    /// ... and the lower one used where the first finds nothing.
    pub min_fast_threshold: u32,
    /// Report a key point of pyramid level `l` (scale `s`) at image pixel `(x + 0.5)·s − 0.5`,
    /// where OpenCV's pixel-centre-aligned resize puts it, instead of ORB-SLAM's `x·s` (up to
    /// 1.3 px up and left). Off by default: it makes tracking more accurate, and with less
    /// drift the merge depth check no longer refuses the look-alike merge of small `aliasing`
    /// after a kidnapping (docs/decisions/0012-depth-weight-and-keypoint-coordinates.md).
    pub pixel_centre_levels: bool,
}

impl Default for OrbConfig {
    fn default() -> Self {
        Self {
            n_features: 1000,
            n_levels: 8,
            scale_factor: 1.2,
            ini_fast_threshold: 20,
            min_fast_threshold: 7,
            pixel_centre_levels: false,
        }
    }
}

/// Frame-to-map tracking.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackerConfig {
    /// Inliers after pose refinement below which `able_to_track` is false.
    pub min_inliers: u32,
    /// Projection search radius in pixels at level 0 (motion-model search).
    pub search_radius_px: f64,
    /// Search radius at level 0 when refining against the local map (the pose is good by then).
    pub local_map_radius_px: f64,
    /// Maximum Hamming distance of an accepted descriptor match.
    pub max_descriptor_distance: u32,
    /// Lowe ratio between best and second-best match.
    pub match_ratio: f64,
    /// Huber threshold on the reprojection error, in pixels.
    pub huber_px: f64,
    /// A frame tracked right after a tracked frame is refused (a false measurement) when its
    /// pose is more than this far from the constant-velocity prediction (metres, at 30 Hz;
    /// proportionally more at lower frame rates) ...
    pub max_jump_m: f64,
    /// ... or turned more than this from it (degrees, at 30 Hz). Measured on clean
    /// sequences: fr1_xyz 0.05 m / 2.9 deg, synthetic `desk` 0.03 m / 0.8 deg, small `loop`
    /// (15 Hz) 0.15 m / 5.0 deg, small `revisit` (7.5 Hz) 0.26 m / 6.8 deg; images from 2 s
    /// away or more (foreign frames) land at 0.05 m / 5.7 deg and beyond at 30 Hz.
    pub max_jump_deg: f64,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        Self {
            min_inliers: 30,
            search_radius_px: 15.0,
            local_map_radius_px: 3.0,
            max_descriptor_distance: 64,
            match_ratio: 0.9,
            huber_px: 2.45,
            max_jump_m: 0.2,
            max_jump_deg: 7.0,
        }
    }
}

/// Initialisation, keyframes and local mapping.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MappingConfig {
    /// RGB-D initializer: keypoints with valid depth needed to start a map.
    pub min_init_depth_points: u32,
    /// Depth readings beyond this are not used to create map points (metres).
    pub max_point_depth_m: f64,
    /// A keyframe is inserted when the tracked share of the reference keyframe's points drops
    /// below this ratio (ORB-SLAM's 0.75 for RGB-D).
    pub keyframe_tracked_ratio: f64,
    /// ... or when this many frames passed since the last keyframe.
    pub keyframe_max_interval: u32,
    /// Local bundle adjustment iterations.
    pub local_ba_iterations: u32,
    /// Number of covisible keyframes optimised by local BA.
    pub local_ba_window: u32,
    /// Iterations of each of the two passes of the full BA the Final state runs over every
    /// map (0 = none).
    pub final_ba_iterations: u32,
    /// The Final full BA also holds tracked frames as cameras, one per this many seconds of
    /// each map's frames (0 = keyframes only); every other tracked frame is then re-placed on
    /// the refined map by a motion-only BA. Localized makes no keyframes in known space, so
    /// without the frames the map keeps the precision of its first visit.
    pub final_ba_frame_interval_s: f64,
    /// Final's BA also holds geometric edges between keyframes that view the same surfaces
    /// without sharing a key point (the two sides of a merge's seam), from registering their
    /// depth (`crate::components::depth_registration::seam_edges`): pairs whose wide planes (walls, floor,
    /// ceiling) pair up. No effect without depth.
    pub final_depth_edges: bool,
    /// ... and also pairs without three wide planes, registered on local planes alone. Off:
    /// on real depth of a desk scene it made wrong edges (see the module's doc).
    pub final_depth_edges_local_planes: bool,
    /// After a user stop (SIGINT/SIGTERM), Final's refinement gets at most this many seconds:
    /// maps not refined by then keep their tracked poses (0 = no refinement). The end of the
    /// data is never limited.
    pub final_refinement_max_s: f64,
    /// Final's refinement keeps the observations of at most this many tracked frames per
    /// keyframe (0 = all): past it, the frame closest in time to its neighbours is forgotten
    /// (`control::frames`). Memory then grows with the map, not with the run's length.
    pub final_frames_per_keyframe: u32,
    /// Of those, at most this many per keyframe are cameras of the Final BA (0 = no limit); the
    /// others are re-placed on the refined map. The BA's memory grows with the square of its
    /// cameras where they share points (a long revisit of one place).
    pub final_ba_cameras_per_keyframe: u32,
    /// RGB-D: also triangulate the new keyframe's unmatched key points with those of its
    /// covisible keyframes, as ORB-SLAM2's `CreateNewMapPoints` does for RGB-D, so the map
    /// holds points where the sensor has no depth (far walls, a room seen through its door).
    /// Pairs closer than the virtual baseline are skipped (ORB-SLAM2's rule).
    pub triangulate_points: bool,
}

impl Default for MappingConfig {
    fn default() -> Self {
        Self {
            min_init_depth_points: 500,
            max_point_depth_m: 4.0,
            keyframe_tracked_ratio: 0.75,
            keyframe_max_interval: 30,
            local_ba_iterations: 10,
            local_ba_window: 10,
            final_ba_iterations: 10,
            final_ba_frame_interval_s: 0.2,
            final_depth_edges: true,
            final_depth_edges_local_planes: false,
            final_refinement_max_s: 30.0,
            final_frames_per_keyframe: 100,
            final_ba_cameras_per_keyframe: 10,
            triangulate_points: false,
        }
    }
}

/// Loop detection (HBST), validation (pooled RANSAC) and global optimisation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LoopClosingConfig {
    pub enabled: bool,
    /// Which index proposes closure candidates: `hbst` (the paper's descriptor tree, the
    /// default; its votes need descriptors within `hbst_max_distance`, which real revisits
    /// from another viewpoint rarely give) or `bow` (a bag-of-words vocabulary, ORB-SLAM's
    /// scheme; with `configs/real-handheld.toml`, see
    /// docs/decisions/0001-bag-of-words-place-recognition.md for why it is not the default).
    pub place_recognition: PlaceRecognition,
    /// Vocabulary file for `bow` (from `vocab-tools train`); none: the built-in one.
    pub vocabulary: Option<std::path::PathBuf>,
    /// `bow`: keyframes covisible with a scored keyframe that add their scores to its group
    /// (ORB-SLAM's accumulated score: a place is a group of views, not one image).
    pub bow_group_size: u32,
    /// `bow`: groups whose accumulated score is below this share of the best are no
    /// candidates.
    pub bow_group_ratio: f64,
    pub hbst_max_leaf_size: u32,
    pub hbst_max_distance: u32,
    /// Largest accepted |0.5 - set fraction| of the split bit of a node.
    pub hbst_max_split_imbalance: f64,
    /// `hbst`: a query also scans the leaves whose path differs from its own in up to this
    /// many split bits (0: the paper's single descent; see `HbstParams::search_flips`). 1: real
    /// revisits a few decimetres and degrees away are proposed (fr1_desk: 46 % of brute
    /// force's descriptor matches, against 14 % for one descent), at 12 ms a query against 2 with
    /// 550 keyframes stored; docs/decisions/0025-hbst-neighbouring-leaves-by-default.md.
    pub hbst_search_flips: u32,
    /// Keyframes this recent are not closure candidates.
    pub temporal_window: u32,
    /// `hbst`: fewest detector votes for a candidate.
    pub min_matches: u32,
    /// Fewest descriptor correspondences (query key point ↔ candidate keyframe's map point,
    /// Hamming ≤ 50) before the validator's RANSAC. Real revisits from a few decimetres and
    /// 10–30° away give 15–40 (ORB-SLAM's relocalization needs 15); the RANSAC, the projection
    /// search of the keyframe's local map and `min_inliers` then decide.
    pub min_validation_matches: u32,
    /// A loop within one map is refused when its correction exceeds this many σ of the
    /// odometry's drift along the path since the matched keyframe (the pose graph's
    /// `odometry_sigma*` model; `loop_validator::implausible_drift`). 0: off.
    pub drift_gate_sigmas: f64,
    /// Lowest loop-detector score (voting query descriptors / query descriptors).
    pub min_score: f64,
    /// Ratio test of the loop detector: a match is kept only when its distance is below this
    /// times the second-best distance in the same keyframe.
    pub ambiguity_ratio: f64,
    /// Self-similar query descriptors (repetitive texture, generic corners) do not vote.
    pub self_similarity_filter: bool,
    /// ... those with more near-duplicates than this in their own keyframe ...
    pub self_similarity_max_own_neighbours: u32,
    /// ... or that match more distinct keyframes than this.
    pub self_similarity_max_images: u32,
    pub min_inliers: u32,
    pub min_inlier_ratio: f64,
    /// Candidates (of different frames) that must agree before a closure pool is accepted.
    pub pool_size: u32,
    /// Frames a valid relocalization candidate waits in the pool for others to agree with it.
    pub pool_window_frames: u32,
    /// The same for loop candidates, which come one per keyframe.
    pub loop_pool_window_frames: u32,
    /// Two candidates agree when their implied alignments differ by at most this much.
    pub pool_max_translation_m: f64,
    pub pool_max_rotation_deg: f64,
    /// A candidate is refused when its alignment differs from a rolled-back or refused pool's
    /// (same two maps) by at most this much: the same hypothesis anchored on other keyframes,
    /// whose relative poses carry the maps' local bending (up to ~6° in fast turns).
    pub refused_max_translation_m: f64,
    pub refused_max_rotation_deg: f64,
    /// Normalised chi-square per edge above which the map is inconsistent.
    pub max_normalized_chi2: f64,
    /// Pose-graph optimisation: Levenberg–Marquardt iterations (per phase).
    pub pgo_iterations: u32,
    /// Dynamic covariance scaling Φ (χ² units) of closure edges: a closure with χ² ≤ Φ keeps
    /// its full weight (12.59 = χ²₀.₉₅ with 6 dof).
    pub dcs_phi: f64,
    /// Odometry (essential-graph) edge uncertainty: the drift the tracker may accumulate
    /// between two connected keyframes.
    pub odometry_sigma_m: f64,
    pub odometry_sigma_deg: f64,
    /// ... plus this much per metre between the two keyframes.
    pub odometry_sigma_per_m: f64,
    pub odometry_sigma_deg_per_m: f64,
    /// Along a loop (`global_optimizer::loop_chi2`), also a random walk in the angle turned:
    /// this much rotation σ per √radian, and this share of the scene's depth in translation σ
    /// per √radian (a misread rotation moves the map by its lever arm).
    pub odometry_sigma_deg_per_sqrt_rad: f64,
    pub odometry_sigma_depth_per_sqrt_rad: f64,
    /// Floor on a closure edge's uncertainty, added to the validator's estimate.
    pub closure_min_sigma_m: f64,
    pub closure_min_sigma_deg: f64,
    /// What a right closure is off by on a real sensor, added to its uncertainty when the
    /// consistency check judges it (not when the pose graph weighs it).
    /// (translation: this share of the scene's depth, so it holds in a monocular map's units)
    pub closure_sensor_sigma_depth: f64,
    pub closure_sensor_sigma_deg: f64,
    /// Keyframes sharing at least this many points are joined in the essential graph.
    pub essential_min_covisibility: u32,
    /// Full bundle adjustment after a consistent global optimisation.
    pub full_ba_after_closure: bool,
    /// Ours, in Mapping: keyframes of the current map at least this old (seconds) are "known
    /// places" that frames are recognised in (younger ones are the local map being built).
    pub known_place_min_age_s: f64,
    /// After a kidnapping, a lost place seen from afar (no map points where the camera now
    /// is) may also be validated from the new frame's depth
    /// (`loop_validator::validate_from_query_depth`). Off: such joins are a few times less
    /// precise than the validator's (0.5–1.9° and 3–13 cm, one σ); on small `loop` 2×1 s the
    /// join made at the corridor's end left 14.4 cm where two maps had 2.9 cm, and on small
    /// `aliasing` 2×5 s an earlier join let room B's map be merged into room A.
    pub lost_place_from_query_depth: bool,
}

impl Default for LoopClosingConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            place_recognition: PlaceRecognition::Hbst,
            vocabulary: None,
            bow_group_size: 10,
            bow_group_ratio: 0.75,
            hbst_max_leaf_size: 100,
            hbst_max_distance: 25,
            hbst_max_split_imbalance: 0.45,
            hbst_search_flips: 1,
            temporal_window: 20,
            min_matches: 40,
            min_validation_matches: 40,
            drift_gate_sigmas: 0.0,
            min_score: 0.05,
            ambiguity_ratio: 0.9,
            self_similarity_filter: false,
            self_similarity_max_own_neighbours: 2,
            self_similarity_max_images: 20,
            min_inliers: 30,
            min_inlier_ratio: 0.3,
            pool_size: 3,
            pool_window_frames: 30,
            loop_pool_window_frames: 300,
            pool_max_translation_m: 0.1,
            pool_max_rotation_deg: 3.0,
            refused_max_translation_m: 0.3,
            refused_max_rotation_deg: 6.0,
            max_normalized_chi2: 3.0,
            pgo_iterations: 20,
            dcs_phi: 12.59,
            odometry_sigma_m: 0.01,
            odometry_sigma_deg: 0.5,
            odometry_sigma_per_m: 0.05,
            odometry_sigma_deg_per_m: 2.0,
            odometry_sigma_deg_per_sqrt_rad: 1.0,
            odometry_sigma_depth_per_sqrt_rad: 0.02,
            closure_min_sigma_m: 0.005,
            closure_min_sigma_deg: 0.25,
            closure_sensor_sigma_depth: 0.04,
            closure_sensor_sigma_deg: 1.5,
            essential_min_covisibility: 100,
            full_ba_after_closure: true,
            known_place_min_age_s: 5.0,
            lost_place_from_query_depth: false,
        }
    }
}

/// The loop detector's index (see `LoopClosingConfig::place_recognition`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum PlaceRecognition {
    Bow,
    #[default]
    Hbst,
}

/// The modal controller (paper section IV/V).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ControllerKind {
    /// The SLAM state machine of the paper.
    #[default]
    Ours,
    /// On loss only relocalize in the single map.
    Orbslam2,
    /// On loss start a new disconnected map.
    Proslam,
    /// On loss stop.
    Ldso,
}

impl ControllerKind {
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Ours => "ours",
            Self::Orbslam2 => "orbslam2",
            Self::Proslam => "proslam",
            Self::Ldso => "ldso",
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ControllerConfig {
    pub kind: ControllerKind,
    /// Share of the image cells where the map predicts points that must be re-observed in
    /// Localized.
    pub min_expectation_ratio: f64,
    /// Without depth, that share is also judged against what this run re-observes while
    /// mapping (where the map is right by construction): a frame fails below this fraction of
    /// the median share of the last mapped frames, when that is lower than
    /// `min_expectation_ratio`. Blur and hand-held viewpoints on real images keep right maps
    /// at 0.2-0.35 (fr1_desk mono), where a synthetic look-alike sits; see
    /// docs/decisions/0018-appearance-check-relative-to-mapping.md.
    pub expectation_relative: f64,
    /// With depth: share of the predicted points judged by depth that the camera sees clearly
    /// behind their predicted place, above which a frame fails the expectation check.
    pub max_contradiction: f64,
    /// Consecutive failing frames before Localized declares the map corrupted.
    pub corrupted_after_frames: u32,
    /// Consecutive new keyframes that see through more than `max_contradiction` of the rest of
    /// their map before Mapping declares the map corrupted (a closure pool changed it).
    pub keyframes_contradicting: u32,
    /// The expectation check needs at least this many image cells (20 px) where the map
    /// predicts points to judge.
    pub min_expected_cells: u32,
    /// Mapping looks for a known place on frames that are not keyframes only where the map
    /// predicts points in at least this share of the cells holding key points (Localized would
    /// be left at once otherwise). Lower than `min_known_coverage`: a loop recognised where the
    /// map covers half the view corrects the drift before the next keyframe is judged against
    /// the map (small `revisit`, three 5 s drops: with 0.7 here too, the loop at frame 127 was
    /// not found and the next keyframe saw through a third of the map).
    pub min_recognize_coverage: f64,
    /// Localized is left for Core when, for `left_after_frames` frames running, less than this
    /// share of the image cells holding keypoints are cells where the map predicts points ...
    pub min_known_coverage: f64,
    /// ... and no keyframe of the map has a similar viewpoint: a centre within this distance
    /// and an optical axis within `known_view_angle_deg`. The viewpoint test keeps the number
    /// of keyframes bounded by the area explored: where a keyframe already looks, a thinly
    /// mapped view is a sparse map, not an unknown place. 20° (a third of the field of view)
    /// and a 0.7 coverage floor: frames tracked while the map's points drift out of view
    /// slip by millimetres on few inliers, so mapping resumes before that (`desk` after a
    /// drop, see docs/decisions/0008-when-localized-hands-back-to-mapping.md).
    pub known_view_distance_m: f64,
    pub known_view_angle_deg: f64,
    /// ... or, at once and off the keyframes' viewpoints, when the tracker keeps fewer inliers
    /// than this (the map no longer holds it well: mapping must resume before tracking fails).
    pub min_localized_inliers: u32,
    pub left_after_frames: u32,
    /// Tracking continues in the current map only across breaks in the measurements of at
    /// most this many seconds since the last tracked frame: Idle re-tracks a shorter loss in
    /// the current map, and a longer break (frames dropped: kidnapping) is a loss even where
    /// the tracker might still find a pose; a new map is started and the Relocalize region
    /// must validate the place before the maps are joined.
    pub reacquire_gap_s: f64,
    /// Merge check by appearance (with depth): a merge is refused when a keyframe of the
    /// query map, placed by the pool's alignment, confirms by its depth readings at least
    /// `min_merge_appearance_points` of the matched map's points (their surface is there, in
    /// view, not occluded) but finds fewer than this share of them by descriptor. A copy of
    /// the place with the same shape and other texture (the corridor beyond a look-alike
    /// room's door) passes the depth check and fails this one. 0 = off. 30 points: on the
    /// real grids no right merge's keyframe with 30–49 confirmed points found less than 18 %,
    /// and a look-alike's found 2 of 38 (decision 0025).
    pub min_merge_appearance: f64,
    pub min_merge_appearance_points: u32,
    /// Without depth, Idle first relocalizes a lost camera in the map it was lost in, and
    /// starts a new map only when that fails (see `relocalize_in_lost_map` in
    /// `control/idle.rs`); false: every loss starts a new map, merged back in Sim3.
    pub relocalize_lost_map: bool,
}

impl Default for ControllerConfig {
    fn default() -> Self {
        Self {
            kind: ControllerKind::Ours,
            min_expectation_ratio: 0.3,
            expectation_relative: 0.65,
            max_contradiction: 0.3,
            corrupted_after_frames: 5,
            keyframes_contradicting: 1,
            min_expected_cells: 30,
            min_recognize_coverage: 0.5,
            min_known_coverage: 0.7,
            known_view_distance_m: 0.5,
            known_view_angle_deg: 20.0,
            min_localized_inliers: 100,
            left_after_frames: 3,
            reacquire_gap_s: 0.5,
            min_merge_appearance: 0.1,
            min_merge_appearance_points: 30,
            relocalize_lost_map: true,
        }
    }
}

/// How a TUM folder is read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SequenceConfig {
    /// Colour/depth association tolerance in seconds (associate.py's max_difference).
    pub max_association_dt: f64,
    /// Ignore depth entirely (monocular mode).
    pub mono: bool,
}

impl Default for SequenceConfig {
    fn default() -> Self {
        Self {
            max_association_dt: 0.02,
            mono: false,
        }
    }
}

/// A whole config file. Sections are optional; the camera may come from the sequence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Config {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<CameraConfig>,
    #[serde(default)]
    pub sequence: SequenceConfig,
    #[serde(default)]
    pub orb: OrbConfig,
    #[serde(default)]
    pub tracker: TrackerConfig,
    #[serde(default)]
    pub mapping: MappingConfig,
    #[serde(default)]
    pub loop_closing: LoopClosingConfig,
    #[serde(default)]
    pub controller: ControllerConfig,
}

/// Camera configs shipped with the binary (also in `configs/`), keyed by the TUM sensor name.
pub const BUILTIN_CAMERAS: [(&str, &str); 3] = [
    ("freiburg1", include_str!("../configs/tum_freiburg1.toml")),
    ("freiburg2", include_str!("../configs/tum_freiburg2.toml")),
    ("freiburg3", include_str!("../configs/tum_freiburg3.toml")),
];

impl Config {
    /// Parses and validates a config file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = read_text(path)?;
        Self::parse(&text, path)
    }

    /// Parses and validates config text; `path` is only used in error messages.
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let cfg: Config = toml::from_str(text).map_err(|e| {
            let line = e
                .span()
                .map(|s| 1 + text[..s.start.min(text.len())].matches('\n').count())
                .unwrap_or(0);
            Error::parse(path, line, e.message().to_string())
        })?;
        cfg.validate().map_err(|(key, msg)| {
            Error::parse(path, find_key_line(text, &key), format!("{key}: {msg}"))
        })?;
        Ok(cfg)
    }

    /// Range checks; returns the dotted key and what is wrong with it.
    pub fn validate(&self) -> std::result::Result<(), (String, String)> {
        let mut c = Checker::default();
        if let Some(cam) = &self.camera {
            c.pos("camera.fx", cam.fx);
            c.pos("camera.fy", cam.fy);
            c.range("camera.cx", cam.cx, 0.0, cam.width as f64);
            c.range("camera.cy", cam.cy, 0.0, cam.height as f64);
            for (k, v) in [
                ("camera.k1", cam.k1),
                ("camera.k2", cam.k2),
                ("camera.p1", cam.p1),
                ("camera.p2", cam.p2),
                ("camera.k3", cam.k3),
            ] {
                c.range(k, v, -100.0, 100.0);
            }
            c.range("camera.width", cam.width as f64, 1.0, 16384.0);
            c.range("camera.height", cam.height as f64, 1.0, 16384.0);
            c.pos("camera.depth_scale", cam.depth_scale);
            c.range("camera.fps", cam.fps, 0.1, 1000.0);
            c.range("camera.readout_s", cam.readout_s, 0.0, 1.0 / cam.fps);
            c.range(
                "camera.virtual_baseline_m",
                cam.virtual_baseline_m,
                0.001,
                10.0,
            );
        }
        let s = &self.sequence;
        c.range(
            "sequence.max_association_dt",
            s.max_association_dt,
            0.0,
            1.0,
        );
        let o = &self.orb;
        c.range("orb.n_features", o.n_features as f64, 10.0, 100000.0);
        c.range("orb.n_levels", o.n_levels as f64, 1.0, 16.0);
        c.range("orb.scale_factor", o.scale_factor, 1.01, 2.0);
        c.range(
            "orb.ini_fast_threshold",
            o.ini_fast_threshold as f64,
            1.0,
            255.0,
        );
        c.range(
            "orb.min_fast_threshold",
            o.min_fast_threshold as f64,
            1.0,
            o.ini_fast_threshold as f64,
        );
        let t = &self.tracker;
        c.range("tracker.min_inliers", t.min_inliers as f64, 3.0, 10000.0);
        c.range("tracker.search_radius_px", t.search_radius_px, 1.0, 1000.0);
        c.range(
            "tracker.local_map_radius_px",
            t.local_map_radius_px,
            0.5,
            1000.0,
        );
        c.range(
            "tracker.max_descriptor_distance",
            t.max_descriptor_distance as f64,
            0.0,
            256.0,
        );
        c.range("tracker.match_ratio", t.match_ratio, 0.1, 1.0);
        c.range("tracker.huber_px", t.huber_px, 0.1, 100.0);
        c.range("tracker.max_jump_m", t.max_jump_m, 0.001, 1000.0);
        c.range("tracker.max_jump_deg", t.max_jump_deg, 0.01, 360.0);
        let m = &self.mapping;
        c.range(
            "mapping.min_init_depth_points",
            m.min_init_depth_points as f64,
            3.0,
            100000.0,
        );
        c.range("mapping.max_point_depth_m", m.max_point_depth_m, 0.1, 100.0);
        c.range(
            "mapping.keyframe_tracked_ratio",
            m.keyframe_tracked_ratio,
            0.0,
            1.0,
        );
        c.range(
            "mapping.keyframe_max_interval",
            m.keyframe_max_interval as f64,
            1.0,
            100000.0,
        );
        c.range(
            "mapping.local_ba_iterations",
            m.local_ba_iterations as f64,
            0.0,
            1000.0,
        );
        c.range(
            "mapping.local_ba_window",
            m.local_ba_window as f64,
            1.0,
            1000.0,
        );
        c.range(
            "mapping.final_ba_iterations",
            m.final_ba_iterations as f64,
            0.0,
            1000.0,
        );
        c.range(
            "mapping.final_ba_frame_interval_s",
            m.final_ba_frame_interval_s,
            0.0,
            3600.0,
        );
        c.range(
            "mapping.final_frames_per_keyframe",
            m.final_frames_per_keyframe as f64,
            0.0,
            1e6,
        );
        c.range(
            "mapping.final_ba_cameras_per_keyframe",
            m.final_ba_cameras_per_keyframe as f64,
            0.0,
            1e6,
        );
        c.range(
            "mapping.final_refinement_max_s",
            m.final_refinement_max_s,
            0.0,
            86400.0,
        );
        let l = &self.loop_closing;
        c.range(
            "loop_closing.hbst_max_leaf_size",
            l.hbst_max_leaf_size as f64,
            1.0,
            100000.0,
        );
        c.range(
            "loop_closing.hbst_max_distance",
            l.hbst_max_distance as f64,
            0.0,
            256.0,
        );
        c.range(
            "loop_closing.hbst_max_split_imbalance",
            l.hbst_max_split_imbalance,
            0.0,
            0.5,
        );
        c.range(
            "loop_closing.hbst_search_flips",
            l.hbst_search_flips as f64,
            0.0,
            3.0,
        );
        c.range(
            "loop_closing.temporal_window",
            l.temporal_window as f64,
            0.0,
            100000.0,
        );
        c.range(
            "loop_closing.min_matches",
            l.min_matches as f64,
            3.0,
            100000.0,
        );
        c.range(
            "loop_closing.min_validation_matches",
            l.min_validation_matches as f64,
            4.0,
            100000.0,
        );
        c.range("loop_closing.min_score", l.min_score, 0.0, 1.0);
        c.range(
            "loop_closing.bow_group_size",
            l.bow_group_size as f64,
            0.0,
            1000.0,
        );
        c.range("loop_closing.bow_group_ratio", l.bow_group_ratio, 0.0, 1.0);
        c.range(
            "loop_closing.drift_gate_sigmas",
            l.drift_gate_sigmas,
            0.0,
            100.0,
        );
        if c.first.is_none()
            && let Some(v) = &l.vocabulary
            && let Err(e) = crate::components::loop_detector::vocabulary::shared(Some(v))
        {
            c.first = Some(("loop_closing.vocabulary".into(), e.to_string()));
        }
        c.range("loop_closing.ambiguity_ratio", l.ambiguity_ratio, 0.1, 1.0);
        c.range(
            "loop_closing.self_similarity_max_own_neighbours",
            l.self_similarity_max_own_neighbours as f64,
            0.0,
            100000.0,
        );
        c.range(
            "loop_closing.self_similarity_max_images",
            l.self_similarity_max_images as f64,
            1.0,
            100000.0,
        );
        c.range(
            "loop_closing.min_inliers",
            l.min_inliers as f64,
            3.0,
            100000.0,
        );
        c.range(
            "loop_closing.min_inlier_ratio",
            l.min_inlier_ratio,
            0.0,
            1.0,
        );
        c.range("loop_closing.pool_size", l.pool_size as f64, 1.0, 1000.0);
        c.range(
            "loop_closing.pool_window_frames",
            l.pool_window_frames as f64,
            1.0,
            100000.0,
        );
        c.range(
            "loop_closing.loop_pool_window_frames",
            l.loop_pool_window_frames as f64,
            1.0,
            100000.0,
        );
        c.range(
            "loop_closing.pool_max_translation_m",
            l.pool_max_translation_m,
            0.0,
            100.0,
        );
        c.range(
            "loop_closing.pool_max_rotation_deg",
            l.pool_max_rotation_deg,
            0.0,
            180.0,
        );
        c.range(
            "loop_closing.refused_max_translation_m",
            l.refused_max_translation_m,
            0.0,
            100.0,
        );
        c.range(
            "loop_closing.refused_max_rotation_deg",
            l.refused_max_rotation_deg,
            0.0,
            180.0,
        );
        c.pos("loop_closing.max_normalized_chi2", l.max_normalized_chi2);
        c.range(
            "loop_closing.pgo_iterations",
            l.pgo_iterations as f64,
            1.0,
            1000.0,
        );
        c.pos("loop_closing.dcs_phi", l.dcs_phi);
        c.pos("loop_closing.odometry_sigma_m", l.odometry_sigma_m);
        c.pos("loop_closing.odometry_sigma_deg", l.odometry_sigma_deg);
        c.range(
            "loop_closing.odometry_sigma_per_m",
            l.odometry_sigma_per_m,
            0.0,
            10.0,
        );
        c.range(
            "loop_closing.odometry_sigma_deg_per_m",
            l.odometry_sigma_deg_per_m,
            0.0,
            180.0,
        );
        c.range(
            "loop_closing.odometry_sigma_deg_per_sqrt_rad",
            l.odometry_sigma_deg_per_sqrt_rad,
            0.0,
            180.0,
        );
        c.range(
            "loop_closing.odometry_sigma_depth_per_sqrt_rad",
            l.odometry_sigma_depth_per_sqrt_rad,
            0.0,
            10.0,
        );
        c.pos("loop_closing.closure_min_sigma_m", l.closure_min_sigma_m);
        c.pos(
            "loop_closing.closure_min_sigma_deg",
            l.closure_min_sigma_deg,
        );
        c.range(
            "loop_closing.closure_sensor_sigma_depth",
            l.closure_sensor_sigma_depth,
            0.0,
            10.0,
        );
        c.range(
            "loop_closing.closure_sensor_sigma_deg",
            l.closure_sensor_sigma_deg,
            0.0,
            180.0,
        );
        c.range(
            "loop_closing.essential_min_covisibility",
            l.essential_min_covisibility as f64,
            1.0,
            100000.0,
        );
        let k = &self.controller;
        c.range(
            "controller.min_expectation_ratio",
            k.min_expectation_ratio,
            0.0,
            1.0,
        );
        c.range(
            "controller.expectation_relative",
            k.expectation_relative,
            0.0,
            1.0,
        );
        c.range(
            "controller.corrupted_after_frames",
            k.corrupted_after_frames as f64,
            1.0,
            100000.0,
        );
        c.range(
            "controller.keyframes_contradicting",
            k.keyframes_contradicting as f64,
            1.0,
            100000.0,
        );
        c.range(
            "controller.min_expected_cells",
            k.min_expected_cells as f64,
            1.0,
            100000.0,
        );
        c.range("controller.reacquire_gap_s", k.reacquire_gap_s, 0.0, 3600.0);
        c.range(
            "controller.min_known_coverage",
            k.min_known_coverage,
            0.0,
            1.0,
        );
        c.range(
            "controller.min_recognize_coverage",
            k.min_recognize_coverage,
            0.0,
            1.0,
        );
        c.range(
            "controller.known_view_distance_m",
            k.known_view_distance_m,
            0.0,
            1000.0,
        );
        c.range(
            "controller.known_view_angle_deg",
            k.known_view_angle_deg,
            0.0,
            180.0,
        );
        c.range(
            "controller.max_contradiction",
            k.max_contradiction,
            0.0,
            1.0,
        );
        c.range(
            "controller.min_merge_appearance",
            k.min_merge_appearance,
            0.0,
            1.0,
        );
        c.range(
            "controller.min_merge_appearance_points",
            k.min_merge_appearance_points as f64,
            1.0,
            1e9,
        );
        c.range(
            "controller.min_localized_inliers",
            k.min_localized_inliers as f64,
            0.0,
            100000.0,
        );
        c.range(
            "controller.left_after_frames",
            k.left_after_frames as f64,
            1.0,
            100000.0,
        );
        c.first.map_or(Ok(()), Err)
    }
}

/// Collects the first failing range check.
#[derive(Default)]
struct Checker {
    first: Option<(String, String)>,
}

impl Checker {
    fn range(&mut self, key: &str, v: f64, lo: f64, hi: f64) {
        if self.first.is_none() && !(v.is_finite() && v >= lo && v <= hi) {
            self.first = Some((key.into(), format!("{v} is out of range [{lo}, {hi}]")));
        }
    }
    fn pos(&mut self, key: &str, v: f64) {
        if self.first.is_none() && !(v.is_finite() && v > 0.0) {
            self.first = Some((key.into(), format!("{v} must be a positive number")));
        }
    }
}

/// Line (1-based) of `key = ...` inside its `[section]`, or 0 when the value came from a default.
fn find_key_line(text: &str, dotted: &str) -> usize {
    let (section, key) = dotted.split_once('.').unwrap_or(("", dotted));
    let mut current = String::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if let Some(rest) = line.strip_prefix('[') {
            current = rest.trim_end_matches(']').trim().to_string();
        } else if current == section
            && line
                .split_once('=')
                .is_some_and(|(k, _)| k.trim().trim_matches('"') == key)
        {
            return i + 1;
        }
    }
    0
}

/// Where the camera of a run came from, printed at start-up.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub enum CameraSource {
    ConfigFile(PathBuf),
    SequenceFile(PathBuf),
    FolderName(&'static str),
    /// A ROS 2 bag's CameraInfo or stored camera; the text says which.
    Bag(String),
}

impl std::fmt::Display for CameraSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::ConfigFile(p) => write!(f, "from the config file {}", p.display()),
            Self::SequenceFile(p) => write!(f, "from the sequence's own {}", p.display()),
            Self::FolderName(n) => write!(
                f,
                "built-in TUM {n} camera (the folder name says {n}; pass --config to override)"
            ),
            Self::Bag(s) => f.write_str(s),
        }
    }
}

/// Parses one of the built-in camera configs by TUM sensor name.
pub fn builtin_camera(name: &str) -> Option<CameraConfig> {
    let (_, text) = BUILTIN_CAMERAS.iter().find(|(n, _)| *n == name)?;
    let cfg = Config::parse(text, Path::new(&format!("configs/tum_{name}.toml")))
        .expect("built-in camera configs are valid (checked by tests)");
    cfg.camera
}

/// Picks the camera: the config's `[camera]` if it has one, else a `camera.toml` inside the
/// sequence folder, else `freiburg1/2/3` in the folder name.
pub fn resolve_camera(
    config: &Config,
    config_path: Option<&Path>,
    sequence_dir: &Path,
) -> Result<(CameraConfig, CameraSource)> {
    if let Some(cam) = &config.camera {
        let src = config_path.map(Path::to_path_buf).unwrap_or_default();
        return Ok((cam.clone(), CameraSource::ConfigFile(src)));
    }
    let own = sequence_dir.join("camera.toml");
    if own.is_file() {
        let cfg = Config::load(&own)?;
        let cam = cfg
            .camera
            .ok_or_else(|| Error::file(&own, "has no [camera] section"))?;
        return Ok((cam, CameraSource::SequenceFile(own)));
    }
    let folder = sequence_dir
        .canonicalize()
        .unwrap_or_else(|_| sequence_dir.to_path_buf());
    let folder_name = folder
        .file_name()
        .map(|n| n.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    for (name, _) in BUILTIN_CAMERAS {
        if folder_name.contains(name) {
            let cam = builtin_camera(name).expect("built-in camera");
            return Ok((cam, CameraSource::FolderName(name)));
        }
    }
    Err(Error::file(
        sequence_dir,
        "cannot tell the camera: no [camera] in --config, no camera.toml in the sequence and no \
         freiburg1/2/3 in the folder name; pass --config configs/tum_freiburg1.toml or similar",
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_cameras_parse() {
        for (name, _) in BUILTIN_CAMERAS {
            let cam = builtin_camera(name).unwrap();
            assert_eq!((cam.width, cam.height), (640, 480));
        }
        assert_eq!(builtin_camera("freiburg2").unwrap().depth_scale, 5208.0);
        assert!(!builtin_camera("freiburg3").unwrap().has_distortion());
        // TUM's Kinects keep ORB-SLAM's depth weight (bf = 40 at fx ≈ 517).
        for (name, _) in BUILTIN_CAMERAS {
            assert_eq!(builtin_camera(name).unwrap().virtual_baseline_m, 0.08);
        }
    }

    #[test]
    fn virtual_baseline_is_read_and_must_be_positive() {
        let cam = "[camera]\nfx = 500\nfy = 500\ncx = 320\ncy = 240\nwidth = 640\nheight = 480\n";
        let ok = Config::parse(
            &format!("{cam}virtual_baseline_m = 0.16\n"),
            Path::new("c.toml"),
        );
        assert_eq!(ok.unwrap().camera.unwrap().virtual_baseline_m, 0.16);
        let err = Config::parse(
            &format!("{cam}virtual_baseline_m = 0\n"),
            Path::new("c.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(err.starts_with("c.toml:8:"), "{err}");
        assert!(err.contains("camera.virtual_baseline_m"), "{err}");
    }

    #[test]
    fn unknown_key_names_key_and_line() {
        let err = Config::parse(
            "[orb]\nn_features = 500\nn_levles = 8\n",
            Path::new("x.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(err.starts_with("x.toml:3:"), "{err}");
        assert!(err.contains("n_levles"), "{err}");
    }

    #[test]
    fn out_of_range_names_key_and_line() {
        let err = Config::parse("[tracker]\n\nmatch_ratio = 1.5\n", Path::new("y.toml"))
            .unwrap_err()
            .to_string();
        assert!(err.starts_with("y.toml:3:"), "{err}");
        assert!(err.contains("tracker.match_ratio"), "{err}");
    }

    #[test]
    fn unknown_section_is_an_error() {
        let err = Config::parse("[trackr]\nmin_inliers = 3\n", Path::new("z.toml")).unwrap_err();
        assert!(err.to_string().contains("trackr"), "{err}");
    }

    #[test]
    fn shipped_default_toml_is_the_default() {
        let text = include_str!("../configs/default.toml");
        assert_eq!(
            Config::parse(text, Path::new("configs/default.toml")).unwrap(),
            Config::default()
        );
    }

    #[test]
    fn defaults_round_trip() {
        let cfg = Config::default();
        let text = toml::to_string(&cfg).unwrap();
        assert_eq!(Config::parse(&text, Path::new("d.toml")).unwrap(), cfg);
    }
}
