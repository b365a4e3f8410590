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
//! With `place_recognition = "bow"` a bag-of-words database ([`vocabulary`]) replaces the
//! index and its votes: images are scored by shared visual words, accumulated over
//! covisibility groups ([`Neighbourhood`]), and candidates carry no descriptor matches (the
//! validator finds its own). Real revisits from another viewpoint change descriptors beyond
//! the HBST's match distance; words tolerate that.
//!
//! The detector only proposes; which keyframes may be candidates (temporal window, map
//! membership) is the caller's rule, passed as a predicate, and geometric validation is the
//! loop validator's job. Nothing here decides modal behaviour.

pub mod hbst;
pub mod vocabulary;

pub use hbst::{
    BruteForce, DescriptorIndex, DescriptorMatch, Hbst, HbstParams, ImageMatches, QueryResult,
    TreeStats,
};

use crate::components::preprocess::Descriptor;
use crate::config::{LoopClosingConfig, PlaceRecognition};
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;
use vocabulary::{BowDatabase, BowVector, Vocabulary};

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

/// The bag-of-words index (when `place_recognition = "bow"`): it replaces the descriptor index
/// and its votes.
#[derive(Debug, Clone)]
struct Bow {
    vocabulary: Arc<Vocabulary>,
    db: BowDatabase,
    group_size: usize,
    group_ratio: f64,
}

/// What bag-of-words scoring needs from the map (ORB-SLAM's DetectLoopCandidates): the
/// covisibility groups that accumulate scores, and the query's own neighbours, whose lowest
/// score is the least a candidate must reach.
#[derive(Clone, Copy)]
pub struct Neighbourhood<'a> {
    /// The best covisible keyframes of a stored image.
    pub covisible: &'a dyn Fn(u64) -> Vec<u64>,
    /// Stored images that see what the query sees (a keyframe's covisible keyframes); empty:
    /// no floor (a frame relocalizing has no such neighbours).
    pub floor: &'a [u64],
}

impl Neighbourhood<'static> {
    /// No covisibility known: every image is its own group, no floor.
    pub fn none() -> Self {
        Neighbourhood {
            covisible: &|_| Vec::new(),
            floor: &[],
        }
    }
}

/// The loop detector: a descriptor index plus the voting rules, or a bag-of-words database.
/// `I` is the HBST in the system; [`BruteForce`] gives the exact reference with the same
/// scoring.
#[derive(Debug, Clone)]
pub struct LoopDetector<I: DescriptorIndex = Hbst> {
    index: I,
    params: LoopDetectorParams,
    bow: Option<Bow>,
    /// Insertion order of the stored images (sequence number → image, and back).
    by_seq: BTreeMap<u64, u64>,
    seq_of: BTreeMap<u64, u64>,
    next_seq: u64,
}

impl LoopDetector<Hbst> {
    pub fn new(params: LoopDetectorParams) -> Self {
        Self::with_index(Hbst::new(params.hbst), params)
    }

    /// The configured index. A vocabulary that cannot be read was already refused by
    /// `Config::validate`; should it vanish since, the HBST stands in (logged as an error).
    pub fn from_config(c: &LoopClosingConfig) -> Self {
        let mut d = Self::new(LoopDetectorParams::from_config(c));
        if c.place_recognition == PlaceRecognition::Bow {
            match vocabulary::shared(c.vocabulary.as_deref()) {
                Ok(v) => d.use_vocabulary(v, c.bow_group_size as usize, c.bow_group_ratio),
                Err(e) => tracing::error!("place recognition falls back to the HBST: {e}"),
            }
        }
        d
    }
}

impl<I: DescriptorIndex> LoopDetector<I> {
    pub fn with_index(index: I, params: LoopDetectorParams) -> Self {
        Self {
            index,
            params,
            bow: None,
            by_seq: BTreeMap::new(),
            seq_of: BTreeMap::new(),
            next_seq: 0,
        }
    }

    pub fn params(&self) -> &LoopDetectorParams {
        &self.params
    }

    /// Proposes candidates by bag of words from now on (call before storing images).
    pub fn use_vocabulary(&mut self, v: Arc<Vocabulary>, group_size: usize, group_ratio: f64) {
        self.bow = Some(Bow {
            vocabulary: v,
            db: BowDatabase::default(),
            group_size,
            group_ratio,
        });
    }

    /// Whether candidates come from the bag-of-words database (they then carry no
    /// descriptor matches: the validator searches for its own).
    pub fn is_bow(&self) -> bool {
        self.bow.is_some()
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
        self.detect_and_insert_in(image, descriptors, exclude, &Neighbourhood::none())
    }

    /// [`Self::detect_and_insert`] with the map's covisibility for bag-of-words scoring.
    pub fn detect_and_insert_in(
        &mut self,
        image: u64,
        descriptors: &[Descriptor],
        exclude: impl Fn(u64) -> bool,
        nb: &Neighbourhood,
    ) -> Detection {
        if let Some(bow) = &mut self.bow {
            let v = bow.vocabulary.transform(descriptors);
            let d = bow_detect(bow, descriptors.len(), &v, exclude, nb);
            bow.db.insert(image, v);
            self.note_inserted(image);
            return d;
        }
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
        self.detect_in(descriptors, exclude, &Neighbourhood::none())
    }

    /// [`Self::detect`] with the map's covisibility for bag-of-words scoring.
    pub fn detect_in(
        &self,
        descriptors: &[Descriptor],
        exclude: impl Fn(u64) -> bool,
        nb: &Neighbourhood,
    ) -> Detection {
        if let Some(bow) = &self.bow {
            let v = bow.vocabulary.transform(descriptors);
            return bow_detect(bow, descriptors.len(), &v, exclude, nb);
        }
        let own = self.params.self_similarity.is_some();
        let r = self.index.query_detailed(descriptors, |i| !exclude(i), own);
        score(descriptors.len(), &r, &self.params)
    }

    /// Stores an image without querying.
    pub fn insert(&mut self, image: u64, descriptors: &[Descriptor]) {
        match &mut self.bow {
            Some(bow) => bow.db.insert(image, bow.vocabulary.transform(descriptors)),
            None => self.index.insert(image, descriptors),
        }
        self.note_inserted(image);
    }

    /// Forgets an image (its keyframe was culled or its map discarded).
    pub fn remove(&mut self, image: u64) {
        match &mut self.bow {
            Some(bow) => bow.db.remove(image),
            None => self.index.remove_image(image),
        }
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

/// Bag-of-words candidates (ORB-SLAM's DetectLoopCandidates / DetectRelocalizationCandidates):
/// stored images that share at least 80 % of the most words any image shares with the query,
/// and score at least the query's lowest score against its own neighbours (`nb.floor`); each
/// is scored with its group (itself and its best covisible images that also pass), and the
/// groups within `group_ratio` of the best give their best image as a candidate, best group
/// first. The rest of the groups are near misses.
fn bow_detect(
    bow: &Bow,
    n_query: usize,
    v: &BowVector,
    exclude: impl Fn(u64) -> bool,
    nb: &Neighbourhood,
) -> Detection {
    let scored = bow.db.query(v, |i| !exclude(i));
    let mut report = DetectionReport {
        query_descriptors: n_query,
        raw_matches: scored.iter().map(|x| x.2 as usize).sum(),
        images_matched: scored.len(),
        ..Default::default()
    };
    let max_common = scored.iter().map(|x| x.2).max().unwrap_or(0);
    let floor = nb
        .floor
        .iter()
        .filter_map(|f| bow.db.get(*f))
        .map(|w| vocabulary::score(v, w))
        .min_by(f64::total_cmp)
        .unwrap_or(0.0);
    let kept: BTreeMap<u64, f64> = scored
        .iter()
        .filter(|x| x.2 as f64 >= 0.8 * max_common as f64 && x.1 >= floor && x.1 > 0.0)
        .map(|x| (x.0, x.1))
        .collect();
    // (accumulated score, best image, its score) per group, one per best image.
    let mut groups: BTreeMap<u64, (f64, f64)> = BTreeMap::new();
    for (&img, &s) in &kept {
        let (mut acc, mut best) = (s, (s, img));
        for n in (nb.covisible)(img).into_iter().take(bow.group_size) {
            if let Some(&sn) = kept.get(&n) {
                acc += sn;
                if sn > best.0 || (sn == best.0 && n < best.1) {
                    best = (sn, n);
                }
            }
        }
        let e = groups.entry(best.1).or_insert((acc, best.0));
        e.0 = e.0.max(acc);
    }
    let best_acc = groups.values().map(|g| g.0).fold(0.0, f64::max);
    let mut ranked: Vec<(f64, u64, f64)> =
        groups.into_iter().map(|(i, (a, s))| (a, i, s)).collect();
    ranked.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    let mut candidates = Vec::new();
    let mut near_misses = Vec::new();
    for (acc, image, s) in ranked {
        let c = Candidate {
            image,
            score: s,
            matches: Vec::new(),
        };
        if acc >= bow.group_ratio * best_acc {
            candidates.push(c);
        } else if near_misses.len() < NEAR_MISSES {
            near_misses.push(c);
        }
    }
    report.candidates = candidates.len();
    Detection {
        candidates,
        near_misses,
        report,
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
