//! `homing eval` as a value: an estimate file against ground truth (ATE, RPE, coverage and,
//! for a run folder, its closures judged and each map's ATE). The program prints it; the Python
//! package's `homing.evaluate` returns it.

use super::{Alignment, AteResult, RpeResult, RpeUnit, run};
use crate::error::{Error, Result};
use crate::io::tum::{StampedPose, read_trajectory};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// What to evaluate, as `homing eval`'s options say it.
#[derive(Debug, Clone)]
pub struct EvalRequest {
    /// Ground truth, TUM format (default with `run`: the run's sequence's groundtruth.txt).
    pub gt: Option<PathBuf>,
    /// Estimate, TUM format (default with `run`: RUN/trajectory.txt).
    pub est: Option<PathBuf>,
    /// A `homing run` output folder: also judge its closures and give each map's ATE.
    pub run: Option<PathBuf>,
    pub align: Alignment,
    pub rpe_delta: f64,
    pub rpe_unit: RpeUnit,
    pub all_pairs: bool,
    /// Maximum time difference for associating estimate and ground truth (seconds).
    pub max_dt: f64,
    /// The sequence the estimate came from, for coverage (else the summary.json next to the
    /// estimate names it).
    pub sequence: Option<PathBuf>,
}

impl Default for EvalRequest {
    fn default() -> Self {
        Self {
            gt: None,
            est: None,
            run: None,
            align: Alignment::Se3,
            rpe_delta: 1.0,
            rpe_unit: RpeUnit::Seconds,
            all_pairs: false,
            max_dt: 0.02,
            sequence: None,
        }
    }
}

/// The evaluation (`homing eval --json` prints it).
#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    pub ate: AteResult,
    pub rpe: Option<RpeResult>,
    /// Why there is no RPE (too few poses a delta apart, …).
    pub rpe_error: Option<String>,
    /// Share of the sequence's frames with ground truth that have a pose; `None` when the
    /// sequence is unknown.
    pub coverage: Option<f64>,
    pub estimate_poses: usize,
    pub groundtruth_poses: usize,
    /// With a run folder: its closures judged against the ground truth.
    pub closures: Option<run::ClosureCheck>,
    /// With a run folder: each map's ATE, and the largest map.
    pub maps: Option<Vec<run::MapAte>>,
    pub largest_map: Option<u32>,
    /// The files evaluated, and what a plot needs.
    #[serde(skip)]
    pub gt_path: PathBuf,
    #[serde(skip)]
    pub est_path: PathBuf,
    #[serde(skip)]
    pub gt_poses: Vec<StampedPose>,
    #[serde(skip)]
    pub associated: super::Associated,
}

/// Evaluates as `homing eval` does.
pub fn evaluate(req: &EvalRequest) -> Result<EvalReport> {
    let mut req = req.clone();
    if let Some(run) = &req.run {
        if !run.is_dir() {
            return Err(Error::file(run, "is not a run folder"));
        }
        if req.est.is_none() {
            req.est = Some(run.join("trajectory.txt"));
        }
        if req.gt.is_none() {
            req.gt = run_sequence(run)?.map(|d| d.join("groundtruth.txt"));
        }
    }
    let (Some(gt_path), Some(est_path)) = (req.gt.clone(), req.est.clone()) else {
        return Err(Error::invalid(
            "give the ground truth and the estimate, or a run folder whose summary.json names \
             the sequence",
        ));
    };
    let gt = read_trajectory(&gt_path)?;
    let est = read_trajectory(&est_path)?;
    if gt.is_empty() {
        return Err(Error::file(&gt_path, "holds no poses"));
    }
    if est.is_empty() {
        return Err(Error::file(&est_path, "holds no poses"));
    }
    let (closures, maps, largest_map) = match &req.run {
        Some(dir) => {
            let closures = crate::outputs::read_closures(&dir.join("closures.csv"))?;
            let state_maps = crate::outputs::read_state_maps(&dir.join("states.csv"))?;
            let (per_map, largest) =
                run::per_map_ate(&gt, &est, &state_maps, req.align, req.max_dt);
            let mono = (req.align == Alignment::Sim3)
                .then(|| run::MonoScales::from_maps(&per_map, largest));
            let check = run::check_closures(&closures, &gt, req.max_dt, mono.as_ref());
            (Some(check), Some(per_map), largest)
        }
        None => (None, None, None),
    };
    let associated = super::associate_and_align(&gt, &est, req.align, req.max_dt)?;
    let ate = super::ate(&associated, req.align);
    let rpe = super::rpe(&associated, req.rpe_delta, req.rpe_unit, req.all_pairs);
    let coverage = coverage_for(&req, &gt, &est)?;
    Ok(EvalReport {
        ate,
        rpe_error: rpe.as_ref().err().map(|e| e.to_string()),
        rpe: rpe.ok(),
        coverage,
        estimate_poses: est.len(),
        groundtruth_poses: gt.len(),
        closures,
        maps,
        largest_map,
        gt_path,
        est_path,
        gt_poses: gt,
        associated,
    })
}

/// The sequence folder a run's summary.json names.
pub fn run_sequence(run: &Path) -> Result<Option<PathBuf>> {
    let summary = run.join("summary.json");
    if !summary.is_file() {
        return Ok(None);
    }
    let text = crate::error::read_text(&summary)?;
    let v: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| Error::parse(&summary, e.line(), format!("not valid JSON: {e}")))?;
    Ok(v.get("sequence")
        .and_then(|s| s.as_str())
        .map(PathBuf::from))
}

/// Coverage needs the frames the estimate could have had: from the request's sequence, or from
/// the summary.json that `homing run` writes next to its trajectory.
fn coverage_for(req: &EvalRequest, gt: &[StampedPose], est: &[StampedPose]) -> Result<Option<f64>> {
    let seq_dir = match (&req.sequence, &req.est) {
        (Some(d), _) => Some(d.clone()),
        (None, Some(est)) => run_sequence(est.parent().unwrap_or(Path::new(".")))?,
        (None, None) => None,
    };
    let Some(dir) = seq_dir else { return Ok(None) };
    let rgb = dir.join("rgb.txt");
    if !rgb.is_file() {
        return Ok(None);
    }
    let stamps: Vec<f64> = crate::io::tum::read_list(&rgb)?
        .iter()
        .map(|e| e.t)
        .collect();
    let eligible = super::eligible_stamps(&stamps, gt, req.max_dt);
    Ok(Some(super::coverage(&eligible, est, req.max_dt)))
}
