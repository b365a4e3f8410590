//! `vocab-tools build`: an HBST of all descriptors of a file, and its shape.

use crate::descfile::DescriptorFile;
use homing::components::loop_detector::{DescriptorIndex, Hbst, HbstParams, TreeStats};
use serde::Serialize;
use std::fmt::Write as _;
use std::time::Instant;

#[derive(Debug, Clone, Serialize)]
pub struct BuildReport {
    pub max_leaf_size: usize,
    pub max_distance: u32,
    pub max_split_imbalance: f64,
    /// The tree's own statistics.
    pub stats: TreeStats,
    /// Smallest depth of a non-empty leaf.
    pub min_leaf_depth: u32,
    /// Sizes of the non-empty leaves: min, median, p90, max.
    pub leaf_size_min: usize,
    pub leaf_size_median: usize,
    pub leaf_size_p90: usize,
    pub leaf_size_max: usize,
    /// Sum of all leaf sizes (= descriptors stored).
    pub leaf_size_sum: usize,
    /// Wall time of inserting every frame, in sequence order.
    pub build_ms: f64,
    pub insert_ms_per_frame: f64,
}

/// Inserts every frame (image key = frame index) and measures the tree.
pub fn build(file: &DescriptorFile, params: HbstParams) -> (Hbst, BuildReport) {
    let mut tree = Hbst::new(params);
    let t0 = Instant::now();
    for (i, f) in file.frames.iter().enumerate() {
        tree.insert(i as u64, &f.descriptors);
    }
    let build_ms = t0.elapsed().as_secs_f64() * 1e3;
    let report = report(&tree, build_ms, file.frames.len());
    (tree, report)
}

/// The shape of `tree` (`build_ms` over `frames` inserts, for the timing fields).
pub fn report(tree: &Hbst, build_ms: f64, frames: usize) -> BuildReport {
    let stats = tree.stats();
    let mut sizes: Vec<usize> = tree.leaf_report().iter().map(|r| r.0).collect();
    let leaf_size_sum = sizes.iter().sum();
    sizes.retain(|&n| n > 0);
    sizes.sort_unstable();
    let pick = |q: f64| {
        if sizes.is_empty() {
            0
        } else {
            sizes[((sizes.len() - 1) as f64 * q).round() as usize]
        }
    };
    // Leaf depths are only visible through descents: the depth of every stored descriptor's
    // leaf covers exactly the non-empty leaves.
    let min_leaf_depth = tree
        .stored()
        .iter()
        .map(|(_, _, d)| tree.leaf_of(d).1)
        .min()
        .unwrap_or(0);
    let p = tree.params();
    BuildReport {
        max_leaf_size: p.max_leaf_size,
        max_distance: p.max_distance,
        max_split_imbalance: p.max_split_imbalance,
        min_leaf_depth,
        leaf_size_min: pick(0.0),
        leaf_size_median: pick(0.5),
        leaf_size_p90: pick(0.9),
        leaf_size_max: pick(1.0),
        leaf_size_sum,
        build_ms,
        insert_ms_per_frame: build_ms / frames.max(1) as f64,
        stats,
    }
}

impl BuildReport {
    pub fn to_text(&self) -> String {
        let s = &self.stats;
        let mut o = String::new();
        let _ = writeln!(
            o,
            "HBST: max_leaf_size {}, max_distance {}, max_split_imbalance {}",
            self.max_leaf_size, self.max_distance, self.max_split_imbalance
        );
        let _ = writeln!(
            o,
            "images {}, descriptors {}, nodes {}, leaves {} ({} empty, {} above max_leaf_size)",
            s.images, s.descriptors, s.nodes, s.leaves, s.empty_leaves, s.oversized_leaves
        );
        let _ = writeln!(
            o,
            "depth of non-empty leaves: min {}, mean {:.2}, max {}; mean depth per descriptor {:.2}",
            self.min_leaf_depth, s.mean_leaf_depth, s.max_depth, s.mean_descriptor_depth
        );
        let _ = writeln!(
            o,
            "leaf size (non-empty): min {}, median {}, p90 {}, max {}; sum {}",
            self.leaf_size_min,
            self.leaf_size_median,
            self.leaf_size_p90,
            self.leaf_size_max,
            self.leaf_size_sum
        );
        let m = self.max_leaf_size.max(1);
        let _ = write!(o, "leaf size histogram:");
        for (k, n) in s.leaf_size_histogram.iter().enumerate() {
            let label = if k == 10 {
                format!(">{m}")
            } else {
                format!("{}-{}", k * m / 10 + usize::from(k > 0), (k + 1) * m / 10)
            };
            let _ = write!(o, " {label}: {n}");
        }
        o.push('\n');
        let _ = writeln!(
            o,
            "split balance (smaller side / node, mean over splits; 0.5 = even): {:.3}",
            s.mean_split_balance
        );
        let _ = writeln!(
            o,
            "memory ≈ {:.1} MB; build {:.1} ms ({:.3} ms per frame insert)",
            s.memory_bytes as f64 / 1e6,
            self.build_ms,
            self.insert_ms_per_frame
        );
        o
    }
}
