//! Loop detector (paper Table I): keyframe descriptors → closure candidates.
//!
//! Each keyframe's ORB descriptors are matched against a descriptor index (the HBST of
//! [`hbst`]) and inserted into it in the same pass. Every query descriptor then votes for the
//! stored images it matches; an image's score is the share of the query's descriptors that
//! voted for it. Votes that carry no place information are dropped first:
//! - *ambiguous* matches: within one image the best and second-best reference are nearly
//!   equally close (ratio test), or one reference descriptor is claimed by several queries;
//! - optionally *self-similar* descriptors (repetitive texture, generic corners): those with
//!   many near-duplicates inside their own image, or that match many different images.
//!
//! The detector only proposes; which keyframes may be candidates (temporal window, map
//! membership) is the caller's rule, passed as a predicate, and geometric validation is the
//! loop validator's job. Nothing here decides modal behaviour.

pub mod hbst;

pub use hbst::{
    BruteForce, DescriptorIndex, DescriptorMatch, Hbst, HbstParams, ImageMatches, QueryResult,
    TreeStats,
};

use crate::config::LoopClosingConfig;
use crate::preprocess::Descriptor;
use std::collections::{BTreeMap, BTreeSet};

/// Self-similarity filter: query descriptors that do not vote.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SelfSimilarityParams {
    /// A descriptor with more near-duplicates (within the match distance) in its own image
    /// does not vote (repetitive texture).
    pub max_own_neighbours: u32,
    /// A descriptor that matches more distinct candidate images does not vote (it is generic).
    pub max_images: u32,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoopDetectorParams {
    pub hbst: HbstParams,
    /// Fewest unambiguous matched query descriptors for a candidate.
    pub min_matches: u32,
    /// Lowest score (matched query descriptors / query descriptors) for a candidate.
    pub min_score: f64,
    /// A match is kept only when its distance is < ratio × the distance of the second-best
    /// match of the same query in the same image (when there is one within the threshold).
    pub ambiguity_ratio: f64,
    pub self_similarity: Option<SelfSimilarityParams>,
}

impl Default for LoopDetectorParams {
    fn default() -> Self {
        Self::from_config(&LoopClosingConfig::default())
    }
}

impl LoopDetectorParams {
    pub fn from_config(c: &LoopClosingConfig) -> Self {
        Self {
            hbst: HbstParams::from_config(c),
            min_matches: c.min_matches,
            min_score: c.min_score,
            ambiguity_ratio: c.ambiguity_ratio,
            self_similarity: c.self_similarity_filter.then_some(SelfSimilarityParams {
                max_own_neighbours: c.self_similarity_max_own_neighbours,
                max_images: c.self_similarity_max_images,
            }),
        }
    }
}

/// A closure candidate: a stored image that enough query descriptors voted for.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    pub image: u64,
    /// Voting query descriptors / query descriptors.
    pub score: f64,
    /// (query descriptor index, reference descriptor index in `image`), by query index.
    pub matches: Vec<(u32, u32)>,
}

/// What happened to the votes of one query (for logs and `vocab-tools eval`).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct DetectionReport {
    pub query_descriptors: usize,
    /// Descriptor matches the index returned (all images the predicate accepted).
    pub raw_matches: usize,
    pub images_matched: usize,
    /// Query descriptors silenced by the self-similarity filter.
    pub self_similar: usize,
    /// (query, image) votes dropped by the ratio test.
    pub ambiguous: usize,
    /// (query, image) votes dropped because their reference was claimed by another query.
    pub shared_reference: usize,
    pub candidates: usize,
}

#[derive(Debug, Clone, Default, PartialEq)]
pub struct Detection {
    /// Best first (score, then image key).
    pub candidates: Vec<Candidate>,
    /// The best few images that got votes but too few for a candidate, most votes first: a
    /// place seen before from another viewpoint gets only these (see `NEAR_MISSES`).
    pub near_misses: Vec<Candidate>,
    pub report: DetectionReport,
}

/// The loop detector: a descriptor index plus the voting rules. `I` is the HBST in the system;
/// [`BruteForce`] gives the exact reference with the same scoring.
#[derive(Debug, Clone)]
pub struct LoopDetector<I: DescriptorIndex = Hbst> {
    index: I,
    params: LoopDetectorParams,
    /// Insertion order of the stored images (sequence number → image, and back).
    by_seq: BTreeMap<u64, u64>,
    seq_of: BTreeMap<u64, u64>,
    next_seq: u64,
}

impl LoopDetector<Hbst> {
    pub fn new(params: LoopDetectorParams) -> Self {
        Self::with_index(Hbst::new(params.hbst), params)
    }

    pub fn from_config(c: &LoopClosingConfig) -> Self {
        Self::new(LoopDetectorParams::from_config(c))
    }
}

impl<I: DescriptorIndex> LoopDetector<I> {
    pub fn with_index(index: I, params: LoopDetectorParams) -> Self {
        Self {
            index,
            params,
            by_seq: BTreeMap::new(),
            seq_of: BTreeMap::new(),
            next_seq: 0,
        }
    }

    pub fn params(&self) -> &LoopDetectorParams {
        &self.params
    }

    pub fn index(&self) -> &I {
        &self.index
    }

    /// Queries a new keyframe against the stored images that `exclude` does not reject, then
    /// stores it under `image` (one descent per descriptor).
    pub fn detect_and_insert(
        &mut self,
        image: u64,
        descriptors: &[Descriptor],
        exclude: impl Fn(u64) -> bool,
    ) -> Detection {
        let own = self.params.self_similarity.is_some();
        let r = self
            .index
            .query_and_insert_detailed(image, descriptors, |i| !exclude(i), own);
        self.note_inserted(image);
        let d = score(descriptors.len(), &r, &self.params);
        tracing::debug!(
            image,
            candidates = d.candidates.len(),
            best = d.candidates.first().map(|c| c.score),
            "loop detector: {:?}",
            d.report
        );
        d
    }

    /// Queries without storing (e.g. relocalization of a frame against other maps).
    pub fn detect(&self, descriptors: &[Descriptor], exclude: impl Fn(u64) -> bool) -> Detection {
        let own = self.params.self_similarity.is_some();
        let r = self.index.query_detailed(descriptors, |i| !exclude(i), own);
        score(descriptors.len(), &r, &self.params)
    }

    /// Stores an image without querying.
    pub fn insert(&mut self, image: u64, descriptors: &[Descriptor]) {
        self.index.insert(image, descriptors);
        self.note_inserted(image);
    }

    /// Forgets an image (its keyframe was culled or its map discarded).
    pub fn remove(&mut self, image: u64) {
        self.index.remove_image(image);
        if let Some(s) = self.seq_of.remove(&image) {
            self.by_seq.remove(&s);
        }
    }

    /// The `window` most recently inserted images still stored: the temporal-window helper.
    /// The caller decides which of them to exclude (usually those of the current map).
    pub fn recent_images(&self, window: usize) -> BTreeSet<u64> {
        self.by_seq.values().rev().take(window).copied().collect()
    }

    fn note_inserted(&mut self, image: u64) {
        if let Some(s) = self.seq_of.insert(image, self.next_seq) {
            self.by_seq.remove(&s);
        }
        self.by_seq.insert(self.next_seq, image);
        self.next_seq += 1;
    }
}

/// Near misses kept per query.
pub const NEAR_MISSES: usize = 3;

/// The voting rules, shared by every index: self-similarity filter, ratio test, one query per
/// reference, then score = votes / query size and the minimum score and match count.
pub fn score(n_query: usize, r: &QueryResult, p: &LoopDetectorParams) -> Detection {
    let mut report = DetectionReport {
        query_descriptors: n_query,
        raw_matches: r.matches.values().map(Vec::len).sum(),
        images_matched: r.matches.len(),
        ..Default::default()
    };
    let mut votes_ok = vec![true; n_query];
    if let Some(ss) = &p.self_similarity {
        let mut images_per_query = vec![0u32; n_query];
        for ms in r.matches.values() {
            // Matches are ordered by query: count each query once per image.
            for g in ms.chunk_by(|a, b| a.query == b.query) {
                images_per_query[g[0].query as usize] += 1;
            }
        }
        for (q, ok) in votes_ok.iter_mut().enumerate() {
            let own = r.own_neighbours.get(q).copied().unwrap_or(0);
            if own > ss.max_own_neighbours || images_per_query[q] > ss.max_images {
                *ok = false;
                report.self_similar += 1;
            }
        }
    }
    let mut candidates = Vec::new();
    let mut near_misses = Vec::new();
    let mut best: Vec<(u32, u32)> = Vec::new(); // (query, reference) after the ratio test
    for (&image, ms) in &r.matches {
        best.clear();
        for g in ms.chunk_by(|a, b| a.query == b.query) {
            if !votes_ok[g[0].query as usize] {
                continue;
            }
            // Best (lowest distance, then lowest reference) and second-best distance.
            let b = g
                .iter()
                .min_by_key(|m| (m.distance, m.reference))
                .expect("non-empty group");
            let second = g
                .iter()
                .filter(|m| m.reference != b.reference)
                .map(|m| m.distance)
                .min();
            if let Some(d2) = second
                && (b.distance as f64) >= p.ambiguity_ratio * d2 as f64
            {
                report.ambiguous += 1;
                continue;
            }
            best.push((b.query, b.reference));
        }
        // A reference claimed by several queries is dropped for all of them.
        let mut claims: BTreeMap<u32, u32> = BTreeMap::new();
        for &(_, rf) in &best {
            *claims.entry(rf).or_default() += 1;
        }
        let before = best.len();
        best.retain(|&(_, rf)| claims[&rf] == 1);
        report.shared_reference += before - best.len();
        let votes = best.len();
        let s = votes as f64 / n_query.max(1) as f64;
        let c = Candidate {
            image,
            score: s,
            matches: best.clone(),
        };
        if votes as u32 >= p.min_matches && votes > 0 && s >= p.min_score {
            candidates.push(c);
        } else if votes > 0 {
            near_misses.push(c);
        }
    }
    let order =
        |a: &Candidate, b: &Candidate| b.score.total_cmp(&a.score).then(a.image.cmp(&b.image));
    candidates.sort_by(order);
    near_misses.sort_by(order);
    near_misses.truncate(NEAR_MISSES);
    report.candidates = candidates.len();
    Detection {
        candidates,
        near_misses,
        report,
    }
}

#[cfg(test)]
mod tests;
