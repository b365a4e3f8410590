//! `vocab-tools eval`: place recognition of the loop detector against ground truth, with the
//! HBST and with brute-force matching under the identical voting rules.
//!
//! Every frame of the descriptor file is a keyframe, in sequence order: it first queries the
//! images stored so far, excluding the last `min_gap` frames (they are trivially similar), then
//! is stored. Both indices run through [`LoopDetector::with_index`], so the only difference is
//! which descriptor matches the index finds. A query's answer is its best-scoring candidate.
//!
//! Ground truth: two frames show the same place when their cameras are within `max_distance_m`
//! and their orientations within `max_angle_deg`. A query is a *positive* when at least one
//! eligible stored frame (≥ `min_gap` frames earlier) is the same place. At a score threshold,
//! a query *predicts* when its best candidate reaches the threshold; the prediction is a true
//! positive when that candidate is the same place. Precision = TP / predictions, recall =
//! TP / positives.

use crate::descfile::DescriptorFile;
use homing::components::loop_detector::vocabulary::{
    BowDatabase, BowVector, Vocabulary, score as bow_score,
};
use homing::components::loop_detector::{
    BruteForce, DescriptorIndex, Detection, Hbst, LoopDetector, LoopDetectorParams,
};
use homing::components::preprocess::Descriptor;
use homing::io::tum::{associate_nearest, read_trajectory};
use homing::outputs::Timing;
use homing::{Error, Result};
use nalgebra::Isometry3;
use serde::Serialize;
use std::fmt::Write as _;
use std::path::Path;
use std::time::Instant;

/// Thresholds of the bag-of-words sweep: score relative to the query's score against the
/// frame before it.
pub const BOW_THRESHOLDS: [f64; 14] = [
    0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.6, 0.7, 0.8,
];
/// The bag-of-words operating point (relative score).
pub const BOW_MIN_SCORE: f64 = 0.3;

/// Score thresholds of the default sweep.
pub const DEFAULT_THRESHOLDS: [f64; 14] = [
    0.0, 0.01, 0.02, 0.03, 0.04, 0.05, 0.075, 0.1, 0.125, 0.15, 0.2, 0.25, 0.3, 0.4,
];

#[derive(Debug, Clone)]
pub struct EvalOptions {
    /// The detector as configured; its `min_score` and `min_matches` are the default operating
    /// point, the sweep varies the score threshold alone.
    pub detector: LoopDetectorParams,
    /// A candidate must be at least this many frames older than the query.
    pub min_gap: usize,
    pub max_distance_m: f64,
    pub max_angle_deg: f64,
    pub thresholds: Vec<f64>,
    /// Query time is reported in this many bins of the number of stored images.
    pub time_bins: usize,
    /// Also run brute force (the reference); without it only the HBST is evaluated.
    pub brute_force: bool,
    /// Also evaluate the bag-of-words database with this vocabulary.
    pub vocabulary: Option<std::sync::Arc<Vocabulary>>,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            detector: LoopDetectorParams::default(),
            min_gap: 30,
            max_distance_m: 0.5,
            max_angle_deg: 30.0,
            thresholds: DEFAULT_THRESHOLDS.to_vec(),
            time_bins: 6,
            brute_force: true,
            vocabulary: None,
        }
    }
}

/// One frame for the evaluation: its descriptors and ground-truth camera-to-world pose.
#[derive(Debug, Clone)]
pub struct EvalFrame {
    pub t: f64,
    pub descriptors: Vec<Descriptor>,
    pub pose: Isometry3<f64>,
}

/// One method's answer to one query.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Answer {
    /// Best candidate: (frame index, score, votes).
    pub best: Option<(usize, f64, usize)>,
    /// Whether the best candidate shows the same place.
    pub correct: Option<bool>,
    /// How far the best candidate's camera is from the query's (metres, degrees).
    pub error: Option<(f64, f64)>,
    /// Descriptor matches the index returned (before voting).
    pub raw_matches: usize,
    pub ms: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct QueryRecord {
    pub frame: usize,
    /// Images stored when the query ran (all earlier frames).
    pub stored: usize,
    /// A same-place frame exists among the eligible ones.
    pub positive: bool,
    pub hbst: Answer,
    pub brute_force: Option<Answer>,
    /// The bag-of-words database: best candidate by score normalised by the query's score
    /// against the frame before it (DBoW2's normalised similarity).
    pub bow: Option<Answer>,
    /// The same, with each stored frame's score accumulated over its temporal neighbours
    /// (ORB-SLAM's covisibility groups; here ±`BOW_GROUP` frames stand in for covisibility).
    pub bow_group: Option<Answer>,
}

/// Half-width (frames) of the temporal neighbourhood that stands in for covisibility.
pub const BOW_GROUP: usize = 5;

/// Precision and recall of one method at one threshold.
#[derive(Debug, Clone, Serialize)]
pub struct PrPoint {
    pub min_score: f64,
    pub min_matches: usize,
    pub predictions: usize,
    pub true_positives: usize,
    pub precision: Option<f64>,
    pub recall: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct MethodReport {
    pub name: String,
    /// At the configured `min_score` and `min_matches`.
    pub default_point: PrPoint,
    /// Score threshold sweep (`min_matches` not applied).
    pub sweep: Vec<PrPoint>,
    /// Median query (+ insert + voting) time per bin of stored images.
    pub time_by_stored: Vec<TimeBin>,
}

#[derive(Debug, Clone, Serialize)]
pub struct TimeBin {
    pub stored_from: usize,
    pub stored_to: usize,
    pub queries: usize,
    pub median_ms: f64,
    pub p90_ms: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    pub frames: usize,
    /// Frames that query at least one eligible image (frame index ≥ min_gap).
    pub queries: usize,
    pub positives: usize,
    pub min_gap: usize,
    pub max_distance_m: f64,
    pub max_angle_deg: f64,
    /// Share of all eligible (query, stored) frame pairs that are the same place.
    pub same_place_pair_share: f64,
    pub hbst: MethodReport,
    pub brute_force: Option<MethodReport>,
    pub bow: Option<MethodReport>,
    pub bow_group: Option<MethodReport>,
    /// Σ HBST descriptor matches / Σ brute-force descriptor matches (HBST's are a subset).
    pub raw_match_recall: Option<f64>,
    /// Median over queries (with brute-force matches) of the same ratio per query.
    pub raw_match_recall_median: Option<f64>,
    /// Queries whose best candidate is the same image with both indices, among those where
    /// brute force has a candidate.
    pub top1_agreement: Option<f64>,
    pub records: Vec<QueryRecord>,
}

/// Distance (m) and angle (degrees) between two camera-to-world poses.
pub fn pose_gap(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let rel = a.inverse() * b;
    (
        rel.translation.vector.norm(),
        rel.rotation.angle().to_degrees(),
    )
}

/// Whether two camera-to-world poses show the same place.
pub fn same_place(a: &Isometry3<f64>, b: &Isometry3<f64>, max_m: f64, max_deg: f64) -> bool {
    let rel = a.inverse() * b;
    rel.translation.vector.norm() <= max_m && rel.rotation.angle().to_degrees() <= max_deg
}

fn answer(d: &Detection, ms: f64, frames: &[EvalFrame], q: usize, o: &EvalOptions) -> Answer {
    let best = d
        .candidates
        .first()
        .map(|c| (c.image as usize, c.score, c.matches.len()));
    judged(best, d.report.raw_matches, ms, frames, q, o)
}

/// Query `q`'s answer `best` (frame, score, votes) judged against the ground truth.
fn judged(
    best: Option<(usize, f64, usize)>,
    raw_matches: usize,
    ms: f64,
    frames: &[EvalFrame],
    q: usize,
    o: &EvalOptions,
) -> Answer {
    let (a, b) = (&frames[q].pose, |j: usize| &frames[j].pose);
    Answer {
        best,
        correct: best.map(|(j, _, _)| same_place(a, b(j), o.max_distance_m, o.max_angle_deg)),
        error: best.map(|(j, _, _)| pose_gap(a, b(j))),
        raw_matches,
        ms,
    }
}

fn run_query<I: DescriptorIndex>(
    det: &mut LoopDetector<I>,
    frames: &[EvalFrame],
    i: usize,
    o: &EvalOptions,
) -> Answer {
    let gap = o.min_gap as u64;
    let t0 = Instant::now();
    let d = det.detect_and_insert(i as u64, &frames[i].descriptors, |j| j + gap > i as u64);
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    answer(&d, ms, frames, i, o)
}

/// One bag-of-words query: every stored frame at least `min_gap` older is scored; scores are
/// divided by the query's score against the frame just before it (how similar "the same
/// place" looks right now), and the best answers, per frame and per temporal group.
fn run_bow_query(
    db: &mut BowDatabase,
    vecs: &[BowVector],
    frames: &[EvalFrame],
    i: usize,
    o: &EvalOptions,
) -> (Answer, Answer) {
    let t0 = Instant::now();
    let gap = o.min_gap as u64;
    let scores = db.query(&vecs[i], |j| j + gap <= i as u64);
    let norm = if i > 0 {
        bow_score(&vecs[i], &vecs[i - 1])
    } else {
        0.0
    };
    let rel = |s: f64| if norm > 0.0 { s / norm } else { 0.0 };
    let best = scores
        .iter()
        .max_by(|a, b| a.1.total_cmp(&b.1).then(b.0.cmp(&a.0)))
        .map(|&(j, sc, n)| (j as usize, rel(sc), n as usize));
    // Group: accumulate over stored neighbours within ±BOW_GROUP frames.
    let by: std::collections::BTreeMap<u64, f64> =
        scores.iter().map(|&(j, sc, _)| (j, sc)).collect();
    let mut group_best: Option<(usize, f64, usize)> = None;
    let mut best_acc = 0.0;
    for &(j, _, _) in &scores {
        let lo = j.saturating_sub(BOW_GROUP as u64);
        let acc: f64 = by.range(lo..=j + BOW_GROUP as u64).map(|(_, s)| s).sum();
        if acc > best_acc {
            best_acc = acc;
            // The group's best member answers.
            let (&bj, &bs) = by
                .range(lo..=j + BOW_GROUP as u64)
                .max_by(|a, b| a.1.total_cmp(b.1).then(b.0.cmp(a.0)))
                .expect("non-empty");
            group_best = Some((bj as usize, rel(bs), 0));
        }
    }
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    db.insert(i as u64, vecs[i].clone());
    let mk = |best: Option<(usize, f64, usize)>| judged(best, scores.len(), ms, frames, i, o);
    (mk(best), mk(group_best))
}

/// Precision/recall of answers `a` (queries' best candidates) at one threshold.
fn pr_point(
    records: &[QueryRecord],
    a: impl Fn(&QueryRecord) -> Option<&Answer>,
    min_score: f64,
    min_matches: usize,
    positives: usize,
) -> PrPoint {
    let (mut predictions, mut tp) = (0, 0);
    for r in records {
        let Some(ans) = a(r) else { continue };
        if let Some((_, score, votes)) = ans.best
            && score >= min_score
            && votes >= min_matches
        {
            predictions += 1;
            tp += usize::from(ans.correct == Some(true));
        }
    }
    PrPoint {
        min_score,
        min_matches,
        predictions,
        true_positives: tp,
        precision: (predictions > 0).then(|| tp as f64 / predictions as f64),
        recall: (positives > 0).then(|| tp as f64 / positives as f64),
    }
}

fn time_bins(
    records: &[QueryRecord],
    a: impl Fn(&QueryRecord) -> Option<&Answer>,
    bins: usize,
) -> Vec<TimeBin> {
    let n = records.len();
    let bins = bins.clamp(1, n.max(1));
    let mut out = Vec::new();
    for b in 0..bins {
        let (lo, hi) = (b * n / bins, (b + 1) * n / bins);
        let chunk = &records[lo..hi];
        if chunk.is_empty() {
            continue;
        }
        let mut t = Timing::default();
        for r in chunk {
            if let Some(ans) = a(r) {
                t.record("q", ans.ms);
            }
        }
        if let Some(s) = t.summary().get("q") {
            out.push(TimeBin {
                stored_from: chunk[0].stored,
                stored_to: chunk[chunk.len() - 1].stored,
                queries: s.count,
                median_ms: s.median_ms,
                p90_ms: s.p90_ms,
            });
        }
    }
    out
}

fn method_report(
    name: &str,
    records: &[QueryRecord],
    a: impl Fn(&QueryRecord) -> Option<&Answer> + Copy,
    positives: usize,
    o: &EvalOptions,
) -> MethodReport {
    let queries: Vec<QueryRecord> = records
        .iter()
        .filter(|r| r.frame >= o.min_gap)
        .cloned()
        .collect();
    MethodReport {
        name: name.into(),
        default_point: pr_point(
            &queries,
            a,
            o.detector.min_score,
            o.detector.min_matches as usize,
            positives,
        ),
        sweep: o
            .thresholds
            .iter()
            .map(|&s| pr_point(&queries, a, s, 0, positives))
            .collect(),
        time_by_stored: time_bins(records, a, o.time_bins),
    }
}

/// Runs the evaluation on frames with known poses.
pub fn evaluate(frames: &[EvalFrame], o: &EvalOptions) -> EvalReport {
    // Every candidate is kept; thresholds are applied afterwards.
    let mut p = o.detector;
    p.min_score = 0.0;
    p.min_matches = 0;
    let mut hbst = LoopDetector::with_index(Hbst::new(p.hbst), p);
    let mut bf = LoopDetector::with_index(BruteForce::new(p.hbst.max_distance), p);
    let mut records = Vec::with_capacity(frames.len());
    let vecs: Vec<BowVector> = match &o.vocabulary {
        Some(v) => frames.iter().map(|f| v.transform(&f.descriptors)).collect(),
        None => Vec::new(),
    };
    let mut db = BowDatabase::default();
    let (mut pairs, mut same_pairs) = (0usize, 0usize);
    for i in 0..frames.len() {
        let mut positive = false;
        for j in 0..(i + 1).saturating_sub(o.min_gap) {
            pairs += 1;
            if same_place(
                &frames[i].pose,
                &frames[j].pose,
                o.max_distance_m,
                o.max_angle_deg,
            ) {
                same_pairs += 1;
                positive = true;
            }
        }
        let h = run_query(&mut hbst, frames, i, o);
        let b = o.brute_force.then(|| run_query(&mut bf, frames, i, o));
        let (bow, bow_group) = match o.vocabulary {
            Some(_) => {
                let (a, g) = run_bow_query(&mut db, &vecs, frames, i, o);
                (Some(a), Some(g))
            }
            None => (None, None),
        };
        records.push(QueryRecord {
            frame: i,
            stored: i,
            positive,
            hbst: h,
            brute_force: b,
            bow,
            bow_group,
        });
    }
    let positives = records.iter().filter(|r| r.positive).count();
    let queries = records.iter().filter(|r| r.frame >= o.min_gap).count();
    let hbst_report = method_report("hbst", &records, |r| Some(&r.hbst), positives, o);
    let bf_report = o.brute_force.then(|| {
        method_report(
            "brute-force",
            &records,
            |r| r.brute_force.as_ref(),
            positives,
            o,
        )
    });
    let bow_o = EvalOptions {
        thresholds: BOW_THRESHOLDS.to_vec(),
        detector: LoopDetectorParams {
            min_score: BOW_MIN_SCORE,
            min_matches: 0,
            ..o.detector
        },
        ..o.clone()
    };
    let bow_report = o
        .vocabulary
        .is_some()
        .then(|| method_report("bow", &records, |r| r.bow.as_ref(), positives, &bow_o));
    let bow_group_report = o.vocabulary.is_some().then(|| {
        method_report(
            "bow-group",
            &records,
            |r| r.bow_group.as_ref(),
            positives,
            &bow_o,
        )
    });
    let (mut raw_h, mut raw_b) = (0usize, 0usize);
    let mut per_query = Vec::new();
    let (mut agree, mut bf_answers) = (0usize, 0usize);
    for r in &records {
        let Some(b) = &r.brute_force else { continue };
        raw_h += r.hbst.raw_matches;
        raw_b += b.raw_matches;
        if b.raw_matches > 0 {
            per_query.push(r.hbst.raw_matches as f64 / b.raw_matches as f64);
        }
        if let Some((jb, _, _)) = b.best {
            bf_answers += 1;
            agree += usize::from(r.hbst.best.map(|x| x.0) == Some(jb));
        }
    }
    per_query.sort_by(f64::total_cmp);
    EvalReport {
        frames: frames.len(),
        queries,
        positives,
        min_gap: o.min_gap,
        max_distance_m: o.max_distance_m,
        max_angle_deg: o.max_angle_deg,
        same_place_pair_share: same_pairs as f64 / pairs.max(1) as f64,
        hbst: hbst_report,
        brute_force: bf_report,
        bow: bow_report,
        bow_group: bow_group_report,
        raw_match_recall: (raw_b > 0).then(|| raw_h as f64 / raw_b as f64),
        raw_match_recall_median: (!per_query.is_empty()).then(|| per_query[per_query.len() / 2]),
        top1_agreement: (bf_answers > 0).then(|| agree as f64 / bf_answers as f64),
        records,
    }
}

/// Pairs the frames of a descriptor file with ground-truth poses (nearest stamp within
/// `max_dt`, evo's rule); frames without one are left out. Returns the frames and how many
/// were left out.
pub fn attach_ground_truth(
    file: &DescriptorFile,
    gt_path: &Path,
    max_dt: f64,
) -> Result<(Vec<EvalFrame>, usize)> {
    let gt = read_trajectory(gt_path)?;
    let tf: Vec<f64> = file.frames.iter().map(|f| f.t).collect();
    let tg: Vec<f64> = gt.iter().map(|p| p.t).collect();
    let pairs = associate_nearest(&tf, &tg, max_dt);
    if pairs.is_empty() {
        return Err(Error::file(
            gt_path,
            format!(
                "no frame of the descriptor file has a ground-truth pose within {max_dt} s \
                 (another sequence?)"
            ),
        ));
    }
    let frames: Vec<EvalFrame> = pairs
        .iter()
        .map(|&(i, j)| EvalFrame {
            t: file.frames[i].t,
            descriptors: file.frames[i].descriptors.clone(),
            pose: gt[j].pose,
        })
        .collect();
    let skipped = file.frames.len() - frames.len();
    Ok((frames, skipped))
}

fn fmt_opt(v: Option<f64>) -> String {
    v.map_or("-".into(), |x| format!("{x:.3}"))
}

/// The sweep as text: a threshold per row, precision / recall (predictions) per method.
fn sweep_table(o: &mut String, threshold: &str, methods: &[&MethodReport]) {
    let _ = write!(o, "  {threshold:>9}");
    for m in methods {
        let _ = write!(o, " | {:^24}", m.name);
    }
    o.push('\n');
    let Some(first) = methods.first() else { return };
    for (k, th) in first.sweep.iter().map(|p| p.min_score).enumerate() {
        let _ = write!(o, "  {th:>9.3}");
        for m in methods {
            let p = &m.sweep[k];
            let _ = write!(
                o,
                " | {:>5} / {:>5}  ({:>4} pred)",
                fmt_opt(p.precision),
                fmt_opt(p.recall),
                p.predictions
            );
        }
        o.push('\n');
    }
}

impl EvalReport {
    pub fn to_text(&self) -> String {
        let mut o = String::new();
        let _ = writeln!(
            o,
            "frames {}, queries {} (frames ≥ min gap {}), positives {} (a same-place frame \
             within {} m and {}° exists ≥ {} frames earlier)",
            self.frames,
            self.queries,
            self.min_gap,
            self.positives,
            self.max_distance_m,
            self.max_angle_deg,
            self.min_gap
        );
        let _ = writeln!(
            o,
            "same-place share of eligible (query, stored) pairs: {:.3}",
            self.same_place_pair_share
        );
        let methods: Vec<&MethodReport> = std::iter::once(&self.hbst)
            .chain(&self.brute_force)
            .collect();
        let bows: Vec<&MethodReport> = self.bow.iter().chain(&self.bow_group).collect();
        let _ = writeln!(o, "\ndefault operating point (min_score, min_matches):");
        for m in &methods {
            let p = &m.default_point;
            let _ = writeln!(
                o,
                "  {:<12} score ≥ {}, votes ≥ {}: predictions {}, TP {}, precision {}, recall {}",
                m.name,
                p.min_score,
                p.min_matches,
                p.predictions,
                p.true_positives,
                fmt_opt(p.precision),
                fmt_opt(p.recall)
            );
        }
        let _ = writeln!(
            o,
            "\nscore sweep (best candidate with score ≥ threshold), precision / recall:"
        );
        sweep_table(&mut o, "min_score", &methods);
        if !bows.is_empty() {
            let _ = writeln!(
                o,
                "\nbag of words: best candidate's score / the query's score against the frame \
                 before it (bow-group: best of the best ±{BOW_GROUP}-frame group)"
            );
            for m in &bows {
                let p = &m.default_point;
                let _ = writeln!(
                    o,
                    "  {:<12} relative score ≥ {}: predictions {}, TP {}, precision {}, recall {}",
                    m.name,
                    p.min_score,
                    p.predictions,
                    p.true_positives,
                    fmt_opt(p.precision),
                    fmt_opt(p.recall)
                );
            }
            sweep_table(&mut o, "rel_score", &bows);
            if let Some(t) = bows[0].time_by_stored.last() {
                let _ = writeln!(
                    o,
                    "  bow query time at {}-{} stored: median {:.3} ms, p90 {:.3} ms",
                    t.stored_from, t.stored_to, t.median_ms, t.p90_ms
                );
            }
        }
        if self.brute_force.is_some() {
            let _ = writeln!(
                o,
                "\nHBST vs brute force: descriptor-match recall {} (median per query {}), \
                 same best image in {} of the queries",
                fmt_opt(self.raw_match_recall),
                fmt_opt(self.raw_match_recall_median),
                fmt_opt(self.top1_agreement)
            );
        }
        let _ = writeln!(
            o,
            "\nquery + insert + voting time (ms, median / p90) by images stored:"
        );
        for (k, b) in self.hbst.time_by_stored.iter().enumerate() {
            let _ = write!(
                o,
                "  {:>5}-{:<5} hbst {:>7.3} / {:>7.3}",
                b.stored_from, b.stored_to, b.median_ms, b.p90_ms
            );
            if let Some(bb) = self
                .brute_force
                .as_ref()
                .and_then(|m| m.time_by_stored.get(k))
            {
                let _ = write!(
                    o,
                    "   brute force {:>8.2} / {:>8.2}",
                    bb.median_ms, bb.p90_ms
                );
            }
            o.push('\n');
        }
        o
    }
}
