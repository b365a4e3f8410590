//! Trajectory evaluation as the TUM RGB-D benchmark defines it, computed exactly as the `evo`
//! package does (association, Umeyama alignment, statistics), so numbers agree with
//! `evo_ape tum GT EST -a` / `-as` and `evo_rpe tum GT EST --delta N --delta_unit f` to 1e-6 m.
//!
//! - ATE: translational error after least-squares alignment (SE3 for RGB-D, Sim3 for mono).
//! - RPE: relative pose error `E = (Q_i⁻¹Q_j)⁻¹ (P_i⁻¹P_j)` over pairs a fixed delta apart,
//!   translational norm and rotation angle. In frames: evo's pairs (non-overlapping unless
//!   `all_pairs`). In seconds (evaluate_rpe.py's default, which evo lacks): every pose `i` paired
//!   with the pose nearest to `t_i + delta`, when that is within 10 % of delta.

pub mod plot;
pub mod report;
pub mod run;
pub mod timeline;

use crate::error::{Error, Result};
use crate::geometry::{Sim3, umeyama};
use crate::io::tum::{StampedPose, associate_nearest};
use nalgebra::{Isometry3, Translation3, Vector3};
use serde::Serialize;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Alignment {
    /// Rigid (rotation + translation): RGB-D.
    Se3,
    /// Similarity (with scale): monocular.
    Sim3,
    /// No alignment.
    None,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum RpeUnit {
    #[value(name = "s")]
    Seconds,
    #[value(name = "frames")]
    Frames,
}

/// Summary statistics of an error vector, as evo reports them (`std` is the population one).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Stats {
    pub rmse: f64,
    pub mean: f64,
    pub median: f64,
    pub std: f64,
    pub min: f64,
    pub max: f64,
    pub sse: f64,
}

impl Stats {
    pub fn of(e: &[f64]) -> Option<Self> {
        if e.is_empty() {
            return None;
        }
        let n = e.len() as f64;
        let sse: f64 = e.iter().map(|v| v * v).sum();
        let mean = e.iter().sum::<f64>() / n;
        let var = e.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
        let mut s = e.to_vec();
        s.sort_by(|a, b| a.total_cmp(b));
        let m = s.len() / 2;
        let median = if s.len().is_multiple_of(2) {
            0.5 * (s[m - 1] + s[m])
        } else {
            s[m]
        };
        Some(Self {
            rmse: (sse / n).sqrt(),
            mean,
            median,
            std: var.sqrt(),
            min: s[0],
            max: s[s.len() - 1],
            sse,
        })
    }
}

/// Estimate and reference poses at associated time stamps, the estimate already aligned.
#[derive(Debug, Clone)]
pub struct Associated {
    pub t: Vec<f64>,
    pub reference: Vec<Isometry3<f64>>,
    pub estimate: Vec<Isometry3<f64>>,
    pub alignment: Sim3,
}

/// Associates (evo's nearest-stamp rule) and aligns the estimate onto the reference.
pub fn associate_and_align(
    gt: &[StampedPose],
    est: &[StampedPose],
    align: Alignment,
    max_dt: f64,
) -> Result<Associated> {
    let tg: Vec<f64> = gt.iter().map(|p| p.t).collect();
    let te: Vec<f64> = est.iter().map(|p| p.t).collect();
    let pairs = associate_nearest(&tg, &te, max_dt);
    if pairs.is_empty() {
        return Err(Error::invalid(format!(
            "no estimate pose has a ground-truth pose within {max_dt} s (different sequences, or \
             time stamps in different units?)"
        )));
    }
    let reference: Vec<_> = pairs.iter().map(|&(i, _)| gt[i].pose).collect();
    let mut estimate: Vec<_> = pairs.iter().map(|&(_, j)| est[j].pose).collect();
    let t: Vec<f64> = pairs.iter().map(|&(_, j)| est[j].t).collect();
    let alignment = match align {
        Alignment::None => Sim3::identity(),
        Alignment::Se3 | Alignment::Sim3 => {
            let x: Vec<Vector3<f64>> = estimate.iter().map(|p| p.translation.vector).collect();
            let y: Vec<Vector3<f64>> = reference.iter().map(|p| p.translation.vector).collect();
            umeyama(&x, &y, align == Alignment::Sim3).ok_or_else(|| {
                Error::invalid(format!(
                    "cannot align: {} associated poses are fewer than 3 or degenerate \
                     (all at one point or on one line)",
                    x.len()
                ))
            })?
        }
    };
    for p in estimate.iter_mut() {
        let tr = alignment.transform_point(&p.translation.vector);
        let rot = nalgebra::UnitQuaternion::from_rotation_matrix(&alignment.rotation) * p.rotation;
        *p = Isometry3::from_parts(Translation3::from(tr), rot);
    }
    Ok(Associated {
        t,
        reference,
        estimate,
        alignment,
    })
}

#[derive(Debug, Clone, Serialize)]
pub struct AteResult {
    pub pairs: usize,
    pub alignment: Alignment,
    pub scale: f64,
    pub stats: Stats,
    /// Per associated pose: time stamp and translational error (metres).
    #[serde(skip)]
    pub errors: Vec<(f64, f64)>,
}

/// Absolute trajectory error (translation part), evo's APE with `-a` (SE3) or `-as` (Sim3).
pub fn ate(assoc: &Associated, align: Alignment) -> AteResult {
    let errors: Vec<(f64, f64)> = assoc
        .t
        .iter()
        .zip(assoc.reference.iter().zip(&assoc.estimate))
        .map(|(&t, (r, e))| (t, (e.translation.vector - r.translation.vector).norm()))
        .collect();
    let e: Vec<f64> = errors.iter().map(|x| x.1).collect();
    AteResult {
        pairs: e.len(),
        alignment: align,
        scale: assoc.alignment.scale,
        stats: Stats::of(&e).expect("association is non-empty"),
        errors,
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct RpeResult {
    pub delta: f64,
    pub unit: RpeUnit,
    pub pairs: usize,
    /// Translational error (metres).
    pub trans: Stats,
    /// Rotational error (degrees).
    pub rot_deg: Stats,
}

/// Relative pose error over pose pairs `delta` apart (see the module doc for the pairing).
pub fn rpe(assoc: &Associated, delta: f64, unit: RpeUnit, all_pairs: bool) -> Result<RpeResult> {
    if !(delta > 0.0 && delta.is_finite()) {
        return Err(Error::invalid(format!(
            "--rpe-delta must be positive, got {delta}"
        )));
    }
    let n = assoc.t.len();
    let pairs: Vec<(usize, usize)> = match unit {
        RpeUnit::Frames => {
            if delta.fract() != 0.0 {
                return Err(Error::invalid(format!(
                    "--rpe-delta {delta} frames must be a whole number"
                )));
            }
            if !(delta >= 1.0 && delta < n as f64) {
                return Err(Error::invalid(format!(
                    "--rpe-delta {delta} frames must be at least 1 and below the {n} associated poses"
                )));
            }
            let d = delta as usize;
            if all_pairs {
                (0..n).filter(|i| i + d < n).map(|i| (i, i + d)).collect()
            } else {
                let ids: Vec<usize> = (0..n).step_by(d).collect();
                ids.windows(2).map(|w| (w[0], w[1])).collect()
            }
        }
        RpeUnit::Seconds => (0..n)
            .filter_map(|i| {
                let target = assoc.t[i] + delta;
                let k = assoc.t.partition_point(|&t| t < target);
                let best = [k.checked_sub(1), (k < n).then_some(k)]
                    .into_iter()
                    .flatten()
                    .filter(|&j| j > i)
                    .min_by(|&a, &b| {
                        (assoc.t[a] - target)
                            .abs()
                            .total_cmp(&(assoc.t[b] - target).abs())
                    })?;
                ((assoc.t[best] - target).abs() <= 0.1 * delta).then_some((i, best))
            })
            .collect(),
    };
    if pairs.is_empty() {
        return Err(Error::invalid(format!(
            "RPE with delta {delta} {unit:?} finds no pose pair among {n} associated poses"
        )));
    }
    let (mut et, mut er) = (Vec::new(), Vec::new());
    for (i, j) in pairs {
        let q = assoc.reference[i].inverse() * assoc.reference[j];
        let p = assoc.estimate[i].inverse() * assoc.estimate[j];
        let e = q.inverse() * p;
        et.push(e.translation.vector.norm());
        er.push(e.rotation.angle().to_degrees());
    }
    Ok(RpeResult {
        delta,
        unit,
        pairs: et.len(),
        trans: Stats::of(&et).expect("non-empty"),
        rot_deg: Stats::of(&er).expect("non-empty"),
    })
}

/// Whether the increasing list `sorted` has a stamp within `max_dt` of `t`.
pub fn has_stamp_near(sorted: &[f64], t: f64, max_dt: f64) -> bool {
    let k = sorted.partition_point(|&x| x < t);
    [k.checked_sub(1), (k < sorted.len()).then_some(k)]
        .into_iter()
        .flatten()
        .any(|j| (sorted[j] - t).abs() <= max_dt)
}

/// Share of `eligible` frame stamps for which the estimate has a pose (nearest within `max_dt`).
pub fn coverage(eligible: &[f64], est: &[StampedPose], max_dt: f64) -> f64 {
    if eligible.is_empty() {
        return 0.0;
    }
    let te: Vec<f64> = est.iter().map(|p| p.t).collect();
    let covered = eligible
        .iter()
        .filter(|&&t| has_stamp_near(&te, t, max_dt))
        .count();
    covered as f64 / eligible.len() as f64
}

/// Frame stamps that have a ground-truth pose within `max_dt`: the frames an estimate could be
/// evaluated on (the denominator of coverage).
pub fn eligible_stamps(frame_stamps: &[f64], gt: &[StampedPose], max_dt: f64) -> Vec<f64> {
    let tg: Vec<f64> = gt.iter().map(|p| p.t).collect();
    frame_stamps
        .iter()
        .copied()
        .filter(|&t| has_stamp_near(&tg, t, max_dt))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stats_like_numpy() {
        let s = Stats::of(&[1.0, 2.0, 3.0, 4.0]).unwrap();
        assert_eq!(s.median, 2.5);
        assert!((s.std - 1.118033988749895).abs() < 1e-12);
        assert!((s.rmse - 7.5f64.sqrt()).abs() < 1e-12);
        assert!(Stats::of(&[]).is_none());
    }

    #[test]
    fn coverage_counts_stamps_with_a_pose() {
        let est: Vec<StampedPose> = [0.0, 0.1, 0.3]
            .iter()
            .map(|&t| StampedPose {
                t,
                pose: Isometry3::identity(),
            })
            .collect();
        assert_eq!(coverage(&[0.0, 0.1, 0.2, 0.305], &est, 0.02), 0.75);
    }
}
