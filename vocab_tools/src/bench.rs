//! `vocab-tools bench`: HBST query + insert time per keyframe as the tree grows.
//!
//! Keyframes are fed one after another through `query_and_insert` (as the loop detector does),
//! the query accepting every stored keyframe except the most recent `temporal_window`; the
//! result is then scored with the loop detector's voting rules ([`score`]). At each size N the
//! keyframes N .. N + probes are timed (the tree holds N … N + probes − 1 keyframes then).
//!
//! Descriptors are not uniformly random (that would give a perfectly balanced tree and almost
//! no matches). Either real descriptors from a file are cycled through (every pass after the
//! first flips 1–4 random bits of each descriptor, so repeats are near and not exact
//! duplicates), or a synthetic world is used: landmarks with biased bits (each bit set with its
//! own probability in [0.2, 0.8], as ORB bits are not fair coins), a camera that moves on so
//! that keyframe k sees a window of landmarks overlapping its neighbours', each observation a
//! noisy copy (0–8 flipped bits) of its landmark, plus a share of unmatched descriptors; every
//! fifth keyframe from the 400th on revisits an older place (a loop).
//! Everything is drawn from one seeded ChaCha8 generator.

use crate::descfile::DescriptorFile;
use homing::components::loop_detector::{
    DescriptorIndex, Hbst, LoopDetectorParams, TreeStats, score,
};
use homing::components::preprocess::Descriptor;
use homing::outputs::{Timing, TimingStats};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::fmt::Write as _;
use std::time::Instant;

/// The synthetic world's shape.
#[derive(Debug, Clone, Copy)]
pub struct WorldParams {
    pub per_keyframe: usize,
    /// New landmarks per keyframe (the camera's progress).
    pub stride: usize,
    /// Landmarks visible from one keyframe (observed: a random subset of them).
    pub window: usize,
    /// Share of a keyframe's descriptors that are unmatched clutter.
    pub clutter: f64,
    /// Observations flip up to this many bits of their landmark.
    pub max_flips: usize,
}

impl WorldParams {
    pub fn new(per_keyframe: usize) -> Self {
        Self {
            per_keyframe,
            stride: per_keyframe / 10,
            window: per_keyframe,
            clutter: 0.2,
            max_flips: 8,
        }
    }
}

/// The place keyframe k sees: the camera moves on, except that every fifth keyframe from the
/// 400th on revisits an older place (at least 300 keyframes back, spread pseudo-randomly):
/// loops.
pub fn place(k: usize) -> usize {
    if k >= 400 && k % 5 == 4 {
        let span = k - 300;
        (k.wrapping_mul(2_654_435_761) >> 7) % span
    } else {
        k
    }
}

/// Where keyframe descriptors come from.
pub enum Source {
    Synthetic {
        params: WorldParams,
        /// Probability of each bit being set.
        bit_p: Vec<f64>,
        landmarks: Vec<Descriptor>,
    },
    Real {
        frames: Vec<Vec<Descriptor>>,
    },
}

/// `d` with `k` distinct random bits flipped.
pub fn flip_bits(rng: &mut ChaCha8Rng, d: &Descriptor, k: usize) -> Descriptor {
    let mut out = *d;
    let mut flipped = [false; 256];
    let mut done = 0;
    while done < k.min(256) {
        let b = rng.random_range(0..256usize);
        if !flipped[b] {
            flipped[b] = true;
            out[b / 8] ^= 1 << (b % 8);
            done += 1;
        }
    }
    out
}

fn biased_descriptor(rng: &mut ChaCha8Rng, bit_p: &[f64]) -> Descriptor {
    let mut d = [0u8; 32];
    for (b, &p) in bit_p.iter().enumerate() {
        if rng.random_bool(p) {
            d[b / 8] |= 1 << (b % 8);
        }
    }
    d
}

impl Source {
    pub fn synthetic(params: WorldParams, rng: &mut ChaCha8Rng) -> Self {
        let bit_p = (0..256).map(|_| rng.random_range(0.2..0.8)).collect();
        Source::Synthetic {
            params,
            bit_p,
            landmarks: Vec::new(),
        }
    }

    /// Real descriptors (frames without descriptors are skipped).
    pub fn real(file: &DescriptorFile) -> Option<Self> {
        let frames: Vec<Vec<Descriptor>> = file
            .frames
            .iter()
            .filter(|f| !f.descriptors.is_empty())
            .map(|f| f.descriptors.clone())
            .collect();
        (!frames.is_empty()).then_some(Source::Real { frames })
    }

    /// The descriptors of keyframe `k` (keyframes must be asked for in order 0, 1, 2, …).
    pub fn keyframe(&mut self, k: usize, rng: &mut ChaCha8Rng) -> Vec<Descriptor> {
        match self {
            Source::Real { frames } => {
                let f = &frames[k % frames.len()];
                if k < frames.len() {
                    f.clone()
                } else {
                    f.iter()
                        .map(|d| {
                            let n = rng.random_range(1..=4);
                            flip_bits(rng, d, n)
                        })
                        .collect()
                }
            }
            Source::Synthetic {
                params: p,
                bit_p,
                landmarks,
            } => {
                let start = place(k) * p.stride;
                while landmarks.len() < start + p.window {
                    landmarks.push(biased_descriptor(rng, bit_p));
                }
                let n_obs = ((1.0 - p.clutter) * p.per_keyframe as f64).round() as usize;
                let n_obs = n_obs.min(p.window);
                // A random subset of the window (partial Fisher–Yates), each a noisy copy.
                let mut ids: Vec<usize> = (start..start + p.window).collect();
                let mut out = Vec::with_capacity(p.per_keyframe);
                for i in 0..n_obs {
                    let j = rng.random_range(i..ids.len());
                    ids.swap(i, j);
                    let flips = rng.random_range(0..=p.max_flips);
                    out.push(flip_bits(rng, &landmarks[ids[i]], flips));
                }
                while out.len() < p.per_keyframe {
                    out.push(biased_descriptor(rng, bit_p));
                }
                out
            }
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct SizeReport {
    /// Keyframes stored when timing started.
    pub keyframes: usize,
    pub probes: usize,
    pub descriptors_per_keyframe: f64,
    /// `Hbst::query_and_insert_detailed` alone.
    pub index: TimingStats,
    /// Index plus the loop detector's voting (`score`): the per-keyframe cost in the system.
    pub detector: TimingStats,
    pub matches_per_query: f64,
    pub tree: TreeStats,
}

#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    pub source: String,
    pub seed: u64,
    pub max_leaf_size: usize,
    pub max_distance: u32,
    pub temporal_window: usize,
    pub sizes: Vec<SizeReport>,
}

#[derive(Debug, Clone)]
pub struct BenchOptions {
    pub sizes: Vec<usize>,
    pub probes: usize,
    pub seed: u64,
    pub detector: LoopDetectorParams,
    pub temporal_window: usize,
}

/// Grows one tree through all sizes (ascending) and times the probe keyframes at each.
pub fn run(
    source: &mut Source,
    source_name: &str,
    o: &BenchOptions,
    mut progress: impl FnMut(usize, usize),
) -> BenchReport {
    let mut sizes = o.sizes.clone();
    sizes.sort_unstable();
    sizes.dedup();
    let mut rng = ChaCha8Rng::seed_from_u64(o.seed);
    let mut tree = Hbst::new(o.detector.hbst);
    let own = o.detector.self_similarity.is_some();
    let mut k = 0usize;
    let total = sizes.last().copied().unwrap_or(0) + o.probes;
    let mut reports = Vec::new();
    for &n in &sizes {
        let mut timing = Timing::default();
        let (mut descs, mut matches) = (0usize, 0usize);
        while k < n + o.probes {
            let d = source.keyframe(k, &mut rng);
            let probe = k >= n;
            let w = o.temporal_window as u64;
            let kk = k as u64;
            let t0 = Instant::now();
            let r = tree.query_and_insert_detailed(kk, &d, |i| i + w < kk, own);
            let t1 = Instant::now();
            let det = score(d.len(), &r, &o.detector);
            let t2 = Instant::now();
            std::hint::black_box(&det);
            if probe {
                timing.record("index", (t1 - t0).as_secs_f64() * 1e3);
                timing.record("detector", (t2 - t0).as_secs_f64() * 1e3);
                descs += d.len();
                matches += det.report.raw_matches;
            }
            k += 1;
            if k.is_multiple_of(100) {
                progress(k, total);
            }
        }
        let s = timing.summary();
        let probes = o.probes.max(1);
        reports.push(SizeReport {
            keyframes: n,
            probes: o.probes,
            descriptors_per_keyframe: descs as f64 / probes as f64,
            index: s.get("index").copied().unwrap_or(ZERO),
            detector: s.get("detector").copied().unwrap_or(ZERO),
            matches_per_query: matches as f64 / probes as f64,
            tree: tree.stats(),
        });
    }
    BenchReport {
        source: source_name.into(),
        seed: o.seed,
        max_leaf_size: o.detector.hbst.max_leaf_size,
        max_distance: o.detector.hbst.max_distance,
        temporal_window: o.temporal_window,
        sizes: reports,
    }
}

const ZERO: TimingStats = TimingStats {
    median_ms: 0.0,
    p90_ms: 0.0,
    max_ms: 0.0,
    mean_ms: 0.0,
    count: 0,
};

impl BenchReport {
    pub fn to_text(&self) -> String {
        let mut o = String::new();
        let _ = writeln!(
            o,
            "source: {}; seed {}; max_leaf_size {}, max_distance {}, temporal window {}",
            self.source, self.seed, self.max_leaf_size, self.max_distance, self.temporal_window
        );
        let _ = writeln!(
            o,
            "{:>9} {:>6} {:>7} | {:>17} | {:>17} | {:>9} {:>8} {:>9} {:>9}",
            "keyframes",
            "probes",
            "desc/kf",
            "index ms med/p90",
            "+voting med/p90",
            "matches",
            "leaves",
            "oversized",
            "mean dep"
        );
        for s in &self.sizes {
            let _ = writeln!(
                o,
                "{:>9} {:>6} {:>7.0} | {:>7.3} / {:>7.3} | {:>7.3} / {:>7.3} | {:>9.0} {:>8} {:>9} {:>9.2}",
                s.keyframes,
                s.probes,
                s.descriptors_per_keyframe,
                s.index.median_ms,
                s.index.p90_ms,
                s.detector.median_ms,
                s.detector.p90_ms,
                s.matches_per_query,
                s.tree.leaves,
                s.tree.oversized_leaves,
                s.tree.mean_descriptor_depth
            );
        }
        o
    }
}
