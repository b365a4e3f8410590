//! Evaluation of a whole run beyond the trajectory: were the closures right, and how good is
//! each map.
//!
//! A closure or relocalization candidate is *wrong* when the transform it claims (pose of the
//! query camera in the matched keyframe's camera) disagrees with the ground truth's by more than
//! 0.3 m or 10° (the project's convention). A candidate the validator rejected before it had a
//! pose is judged by place instead: wrong when the two cameras were more than 0.3 m apart or
//! looked more than 30° apart (it proposed another place). A monocular map has no metric
//! scale: its claimed translations are converted to metres with the scale of that map's own
//! Sim3 alignment to the ground truth ([`MonoScales`]).

use super::{Alignment, associate_and_align, ate};
use crate::io::tum::StampedPose;
use crate::outputs::ClosureRow;
use nalgebra::Isometry3;
use serde::Serialize;
use std::collections::BTreeMap;

pub const WRONG_TRANSLATION_M: f64 = 0.3;
pub const WRONG_ROTATION_DEG: f64 = 10.0;
pub const OTHER_PLACE_ROTATION_DEG: f64 = 30.0;

/// Counts over a run's `closures.csv`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ClosureCheck {
    /// Candidates with ground truth at both ends.
    pub candidates: usize,
    pub candidates_wrong: usize,
    /// Accepted into a pool that stands at the end.
    pub accepted: usize,
    pub accepted_wrong: usize,
    /// Accepted, then rolled back by the Corrupted Map state.
    pub rolled_back: usize,
    pub rolled_back_wrong: usize,
    /// Pools rolled back, and those of them with a wrong member (the safety net's catches;
    /// the others are its cost: right work it condemned).
    pub pools_rolled_back: usize,
    pub pools_rolled_back_wrong: usize,
    /// Rejected by the validator (or refused as a rolled-back alignment).
    pub rejected: usize,
    pub rejected_wrong: usize,
    /// Valid but no pool formed in time.
    pub expired: usize,
    pub expired_wrong: usize,
    /// Frames of the wrong candidates that stand accepted (what must be zero).
    pub accepted_wrong_frames: Vec<usize>,
}

/// Ground-truth camera-to-world pose nearest `t` (within `max_dt`).
pub(crate) fn gt_at(gt: &[StampedPose], t: f64, max_dt: f64) -> Option<Isometry3<f64>> {
    let i = gt.partition_point(|p| p.t < t);
    [i.checked_sub(1), Some(i)]
        .into_iter()
        .flatten()
        .filter_map(|k| gt.get(k))
        .filter(|p| (p.t - t).abs() <= max_dt)
        .min_by(|a, b| (a.t - t).abs().total_cmp(&(b.t - t).abs()))
        .map(|p| p.pose)
}

/// Whether one candidate is wrong; `None` without ground truth at both ends.
pub fn closure_is_wrong(
    row: &ClosureRow,
    gt: &[StampedPose],
    max_dt: f64,
    mono: Option<&MonoScales>,
) -> Option<bool> {
    let q = gt_at(gt, row.t_query, max_dt)?;
    let m = gt_at(gt, row.t_match, max_dt)?;
    // World-to-camera relative of the truth: T_m,w · T_q,w⁻¹ = G_m⁻¹ · G_q.
    let truth = m.inverse() * q;
    Some(match &row.relative {
        Some(claimed) => {
            let mut claimed = *claimed;
            if let Some(s) = mono {
                // No scale known for the map: judge the rotation and direction only.
                let metres = s.of(row.map_match).unwrap_or(0.0);
                claimed.translation.vector *= metres;
                if metres == 0.0 {
                    claimed.translation.vector = truth.translation.vector;
                }
            }
            let d = claimed.inverse() * truth;
            d.translation.vector.norm() > WRONG_TRANSLATION_M
                || d.rotation.angle().to_degrees() > WRONG_ROTATION_DEG
        }
        None => {
            truth.translation.vector.norm() > WRONG_TRANSLATION_M
                || truth.rotation.angle().to_degrees() > OTHER_PLACE_ROTATION_DEG
        }
    })
}

/// Metres per map unit of monocular maps, for judging their closures: each map's own Sim3
/// alignment scale; for a map gone by the end (merged, rolled back) the largest map's.
#[derive(Debug, Clone, Default)]
pub struct MonoScales {
    per_map: BTreeMap<u32, f64>,
    fallback: Option<f64>,
}

impl MonoScales {
    pub fn from_maps(maps: &[MapAte], largest: Option<u32>) -> Self {
        let per_map: BTreeMap<u32, f64> = maps
            .iter()
            .filter_map(|m| m.scale.map(|s| (m.map, s)))
            .collect();
        let fallback = largest.and_then(|l| per_map.get(&l).copied());
        Self { per_map, fallback }
    }

    pub fn of(&self, map: u32) -> Option<f64> {
        self.per_map.get(&map).copied().or(self.fallback)
    }
}

/// `mono`: the run is monocular (see [`MonoScales`]).
pub fn check_closures(
    rows: &[ClosureRow],
    gt: &[StampedPose],
    max_dt: f64,
    mono: Option<&MonoScales>,
) -> ClosureCheck {
    let mut c = ClosureCheck::default();
    let mut pools: BTreeMap<u32, bool> = BTreeMap::new();
    for r in rows {
        if r.verdict == "rolled-back"
            && let Some(p) = r.pool
        {
            let wrong = closure_is_wrong(r, gt, max_dt, mono).unwrap_or(false);
            *pools.entry(p).or_default() |= wrong;
        }
        let Some(wrong) = closure_is_wrong(r, gt, max_dt, mono) else {
            continue;
        };
        let w = usize::from(wrong);
        c.candidates += 1;
        c.candidates_wrong += w;
        match r.verdict.as_str() {
            v if crate::outputs::is_accepted(v) => {
                c.accepted += 1;
                c.accepted_wrong += w;
                if wrong {
                    c.accepted_wrong_frames.push(r.frame);
                }
            }
            "rolled-back" => {
                c.rolled_back += 1;
                c.rolled_back_wrong += w;
            }
            "expired" | "pending" => {
                c.expired += 1;
                c.expired_wrong += w;
            }
            _ => {
                c.rejected += 1;
                c.rejected_wrong += w;
            }
        }
    }
    c.pools_rolled_back = pools.len();
    c.pools_rolled_back_wrong = pools.values().filter(|w| **w).count();
    c
}

/// A posed frame counts as recovered only this close to the truth after its map's alignment:
/// coverage won by a wrong merge does not count.
pub const ACCURATE_M: f64 = 0.10;

/// ATE of one map's frames.
#[derive(Debug, Clone, Serialize)]
pub struct MapAte {
    pub map: u32,
    pub poses: usize,
    pub ate_rmse_m: Option<f64>,
    /// Scale of the map's alignment to the ground truth (metres per map unit; 1 for SE3).
    pub scale: Option<f64>,
    /// Stamps of the map's poses within [`ACCURATE_M`] of the truth after its own alignment.
    #[serde(skip)]
    pub accurate: Vec<f64>,
}

/// ATE per map (each map aligned on its own: the maps are disconnected frames) and the id of
/// the largest map (most poses). `maps` gives each estimated pose's map, by stamp.
pub fn per_map_ate(
    gt: &[StampedPose],
    est: &[StampedPose],
    maps: &[(f64, u32)],
    align: Alignment,
    max_dt: f64,
) -> (Vec<MapAte>, Option<u32>) {
    let mut sorted = maps.to_vec();
    sorted.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut by_map: BTreeMap<u32, Vec<StampedPose>> = BTreeMap::new();
    for p in est {
        // Stamps are written with 6 decimals in both files: match at that precision.
        let i = sorted.partition_point(|(t, _)| *t < p.t - 5e-7);
        if let Some((t, m)) = sorted.get(i)
            && (t - p.t).abs() < 5e-7
        {
            by_map.entry(*m).or_default().push(*p);
        }
    }
    let mut out = Vec::new();
    for (m, poses) in &by_map {
        let aligned = (poses.len() >= 3)
            .then(|| associate_and_align(gt, poses, align, max_dt).ok())
            .flatten();
        let a = aligned.as_ref().map(|a| ate(a, align));
        out.push(MapAte {
            map: *m,
            poses: poses.len(),
            ate_rmse_m: a.as_ref().map(|a| a.stats.rmse),
            scale: aligned.as_ref().map(|a| a.alignment.scale),
            accurate: a
                .map(|a| {
                    a.errors
                        .iter()
                        .filter(|e| e.1 <= ACCURATE_M)
                        .map(|e| e.0)
                        .collect()
                })
                .unwrap_or_default(),
        });
    }
    let largest = out
        .iter()
        .max_by(|a, b| a.poses.cmp(&b.poses).then(b.map.cmp(&a.map)))
        .map(|m| m.map);
    (out, largest)
}
