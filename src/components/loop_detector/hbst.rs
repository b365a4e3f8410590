//! Hamming Binary Search Tree (HBST; Schlegel & Grisetti, "HBST: A Hamming Distance Embedding
//! Binary Search Tree for Feature-Based Visual Place Recognition", RA-L 2018), the descriptor
//! index ProSLAM uses for loop detection.
//!
//! Every inner node tests one bit of the 256-bit descriptor; a descriptor follows its bits down
//! to exactly one leaf and is compared there, by Hamming distance, with the descriptors stored in
//! that leaf only. A leaf that grows beyond `max_leaf_size` splits on the bit whose set-fraction
//! over its descriptors is closest to 0.5, so that both halves stay balanced; if even the best
//! bit is more imbalanced than `max_split_imbalance` the leaf stays a (large) leaf. The search is
//! approximate: a near neighbour that differs from the query in one of the bits on the path is
//! in another leaf and is missed. What it buys is a query cost of one descent plus one leaf scan,
//! independent of the number of stored images.
//!
//! Layout (measured, see vocab_tools/README.md): nodes live in one arena addressed by `u32`;
//! each leaf stores its descriptors contiguously as `[u64; 4]` (one XOR + popcount per word) and,
//! in a parallel vector, the (image slot, descriptor index) they came from. Everything is
//! ordered and single-threaded, so the same inserts give the same tree and the same matches.

use crate::components::preprocess::Descriptor;
use std::collections::BTreeMap;

/// HBST parameters (see [`crate::config::LoopClosingConfig`] for the configured values).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HbstParams {
    /// A leaf with more descriptors than this splits (if a balanced enough bit exists).
    pub max_leaf_size: usize,
    /// Largest Hamming distance reported as a match (inclusive).
    pub max_distance: u32,
    /// A split is rejected when |0.5 − set fraction| of the best bit exceeds this.
    pub max_split_imbalance: f64,
    /// A query also scans every leaf whose path differs from its own in at most this many
    /// split bits (0: one descent, the paper's tree). A revisit's descriptor differs from the
    /// stored one in ~10 % of its bits, so it leaves the query's path at one of the ~12 splits
    /// more often than not; each allowed flip brings back the neighbours that left at one split
    /// (see [`Hbst::probe_leaves`]).
    pub search_flips: u32,
}

impl Default for HbstParams {
    fn default() -> Self {
        Self {
            max_leaf_size: 100,
            max_distance: 25,
            max_split_imbalance: 0.45,
            search_flips: 0,
        }
    }
}

impl HbstParams {
    pub fn from_config(c: &crate::config::LoopClosingConfig) -> Self {
        Self {
            max_leaf_size: c.hbst_max_leaf_size as usize,
            max_distance: c.hbst_max_distance,
            max_split_imbalance: c.hbst_max_split_imbalance,
            search_flips: c.hbst_search_flips,
        }
    }
}

/// One descriptor match: query descriptor `query` is within the distance threshold of
/// descriptor `reference` of image `image`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct DescriptorMatch {
    pub query: u32,
    pub image: u64,
    pub reference: u32,
    pub distance: u32,
}

/// Matches per image, images in key order, each image's matches ordered by (query, reference).
pub type ImageMatches = BTreeMap<u64, Vec<DescriptorMatch>>;

/// What a query returns when the caller also wants the query's self-similarity.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct QueryResult {
    pub matches: ImageMatches,
    /// Per query descriptor: how many *other* descriptors of the same query lie within the
    /// distance threshold (repetitive texture). Empty unless asked for. The tree computes it
    /// among the query descriptors that reach the same leaf, so it is approximate like the
    /// matches themselves.
    pub own_neighbours: Vec<u32>,
}

/// A descriptor index the loop detector can vote with: the HBST, or brute force as the
/// reference it is evaluated against (`vocab-tools eval`).
pub trait DescriptorIndex {
    /// Matches of `descriptors` against the stored images that `accept` lets through.
    fn query_detailed(
        &self,
        descriptors: &[Descriptor],
        accept: impl Fn(u64) -> bool,
        own_neighbours: bool,
    ) -> QueryResult;
    /// `query_detailed`, then `insert`, possibly in one pass; must give the same result.
    fn query_and_insert_detailed(
        &mut self,
        image: u64,
        descriptors: &[Descriptor],
        accept: impl Fn(u64) -> bool,
        own_neighbours: bool,
    ) -> QueryResult;
    /// Stores the descriptors of one image under `image`; descriptor i gets reference index i
    /// (counted on from the image's earlier descriptors if the key is already stored).
    fn insert(&mut self, image: u64, descriptors: &[Descriptor]);
    /// Forgets an image (e.g. when its map is discarded).
    fn remove_image(&mut self, image: u64);
    /// Number of stored images.
    fn n_images(&self) -> usize;
}

type Words = [u64; 4];

#[inline]
fn words(d: &Descriptor) -> Words {
    let w = |k: usize| u64::from_le_bytes(d[8 * k..8 * k + 8].try_into().expect("8 bytes"));
    [w(0), w(1), w(2), w(3)]
}

/// Bit `b` (0..256) of a descriptor: bit `b % 8` of byte `b / 8`.
#[inline]
fn bit(w: &Words, b: u8) -> usize {
    ((w[(b >> 6) as usize] >> (b & 63)) & 1) as usize
}

#[inline(always)]
fn dist(a: &Words, b: &Words) -> u32 {
    (a[0] ^ b[0]).count_ones()
        + (a[1] ^ b[1]).count_ones()
        + (a[2] ^ b[2]).count_ones()
        + (a[3] ^ b[3]).count_ones()
}

/// Indices and distances of the descriptors of `leaf` within `max` of `q`, appended to `out`.
#[inline(always)]
fn scan_generic(leaf: &[Words], q: &Words, max: u32, out: &mut Vec<(u32, u32)>) {
    for (j, s) in leaf.iter().enumerate() {
        let d = dist(s, q);
        if d <= max {
            out.push((j as u32, d));
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "popcnt")]
fn scan_popcnt(leaf: &[Words], q: &Words, max: u32, out: &mut Vec<(u32, u32)>) {
    scan_generic(leaf, q, max, out)
}

/// The leaf scan is the hot loop. The baseline x86-64 target has no POPCNT instruction (the
/// portable count is ~4x slower), so use it when the CPU has it.
#[inline]
fn scan(leaf: &[Words], q: &Words, max: u32, out: &mut Vec<(u32, u32)>) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("popcnt") {
            // SAFETY: the CPU supports POPCNT (checked just above).
            unsafe { scan_popcnt(leaf, q, max, out) };
            return;
        }
    }
    scan_generic(leaf, q, max, out)
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Node {
    /// Descriptors with bit `bit` clear go to `children[0]`, set to `children[1]`.
    Split {
        bit: u8,
        children: [u32; 2],
    },
    Leaf(u32),
}

#[derive(Debug, Clone, Default)]
struct Leaf {
    /// The node that points at this leaf.
    node: u32,
    depth: u32,
    descs: Vec<Words>,
    /// (image slot, descriptor index within the image), parallel to `descs`.
    refs: Vec<(u32, u32)>,
}

/// Shape of the tree, for `vocab-tools build` and logging.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct TreeStats {
    pub images: usize,
    pub descriptors: usize,
    pub nodes: usize,
    pub leaves: usize,
    pub empty_leaves: usize,
    /// Leaves above `max_leaf_size` (no bit splits them within the imbalance limit).
    pub oversized_leaves: usize,
    pub max_depth: u32,
    /// Mean depth of the non-empty leaves.
    pub mean_leaf_depth: f64,
    /// Mean depth at which a stored descriptor sits (= descents' length weighted by content).
    pub mean_descriptor_depth: f64,
    /// Mean over split nodes of the share of their descriptors on the smaller side (0.5 =
    /// perfectly balanced).
    pub mean_split_balance: f64,
    /// Leaf sizes in buckets of a tenth of `max_leaf_size`: bucket k counts leaves with
    /// k·m/10 < size ≤ (k+1)·m/10; the first bucket also holds empty leaves, and the last
    /// (index 10) those above `max_leaf_size`.
    pub leaf_size_histogram: Vec<usize>,
    /// Heap bytes held by nodes, leaves and descriptors (capacity, approximate).
    pub memory_bytes: usize,
}

/// The tree. See the module documentation.
#[derive(Debug, Clone)]
pub struct Hbst {
    params: HbstParams,
    nodes: Vec<Node>,
    leaves: Vec<Leaf>,
    /// Image key of each slot; `None` once removed (slots are never reused, which keeps slot
    /// order = insertion order).
    slots: Vec<Option<u64>>,
    /// Descriptors stored per slot (the next reference index of that image).
    slot_len: Vec<u32>,
    slot_of: BTreeMap<u64, u32>,
    n_descriptors: usize,
}

impl Default for Hbst {
    fn default() -> Self {
        Self::new(HbstParams::default())
    }
}

impl Hbst {
    pub fn new(params: HbstParams) -> Self {
        Self {
            params,
            nodes: vec![Node::Leaf(0)],
            leaves: vec![Leaf::default()],
            slots: Vec::new(),
            slot_len: Vec::new(),
            slot_of: BTreeMap::new(),
            n_descriptors: 0,
        }
    }

    pub fn params(&self) -> &HbstParams {
        &self.params
    }

    /// Number of stored descriptors.
    pub fn len(&self) -> usize {
        self.n_descriptors
    }

    pub fn is_empty(&self) -> bool {
        self.n_descriptors == 0
    }

    /// Stored image keys, in key order.
    pub fn images(&self) -> impl Iterator<Item = u64> + '_ {
        self.slot_of.keys().copied()
    }

    pub fn contains_image(&self, image: u64) -> bool {
        self.slot_of.contains_key(&image)
    }

    #[inline]
    fn descend(&self, w: &Words) -> u32 {
        let mut i = 0u32;
        loop {
            match self.nodes[i as usize] {
                Node::Split { bit: b, children } => i = children[bit(w, b)],
                Node::Leaf(l) => return l,
            }
        }
    }

    /// The leaves a query scans: its own leaf (`own_leaf`, its descent) first, then every leaf
    /// reached by taking the other branch at up to `search_flips` of the splits on the way
    /// (each leaf once: a stored descriptor sits in exactly one leaf, so no match is found
    /// twice). With `f` flips and depth `d` that is Σ_{k≤f} C(d, k) leaves: 1, ~13, ~80 at the
    /// real trees' depth of 12.
    fn probe_leaves(&self, w: &Words, own_leaf: u32, out: &mut Vec<u32>) {
        out.clear();
        out.push(own_leaf);
        if self.params.search_flips == 0 {
            return;
        }
        // (node, flips left), depth first in a fixed order: deterministic.
        let mut stack: Vec<(u32, u32)> = vec![(0, self.params.search_flips)];
        while let Some((mut i, left)) = stack.pop() {
            loop {
                match self.nodes[i as usize] {
                    Node::Split { bit: b, children } => {
                        let own = bit(w, b);
                        if left > 0 {
                            stack.push((children[1 - own], left - 1));
                        }
                        i = children[own];
                    }
                    Node::Leaf(l) => {
                        if left < self.params.search_flips {
                            out.push(l);
                        }
                        break;
                    }
                }
            }
        }
    }

    /// The leaf a descriptor falls into, with its depth (for tests and diagnostics).
    pub fn leaf_of(&self, d: &Descriptor) -> (u32, u32) {
        let l = self.descend(&words(d));
        (l, self.leaves[l as usize].depth)
    }

    /// Matches per image (images filtered by `accept`).
    pub fn query(&self, descriptors: &[Descriptor], accept: impl Fn(u64) -> bool) -> ImageMatches {
        self.query_detailed(descriptors, accept, false).matches
    }

    /// [`Self::query`] then [`Self::insert`] with one descent per descriptor; the result equals
    /// that of `query` (the image does not match itself).
    pub fn query_and_insert(
        &mut self,
        image: u64,
        descriptors: &[Descriptor],
        accept: impl Fn(u64) -> bool,
    ) -> ImageMatches {
        self.query_and_insert_detailed(image, descriptors, accept, false)
            .matches
    }

    fn run_query(
        &self,
        qs: &[Words],
        leaves: &[u32],
        accept: impl Fn(u64) -> bool,
        own: bool,
    ) -> QueryResult {
        const UNKNOWN: u8 = 2;
        // `accept` once per image slot, lazily (it may be a set lookup in the caller).
        let mut accepted = vec![UNKNOWN; self.slots.len()];
        let mut found: Vec<(u32, u32, u32, u32)> = Vec::new(); // (slot, query, ref, distance)
        let mut hits = Vec::with_capacity(2 * self.params.max_leaf_size);
        let mut probe = Vec::new();
        for (qi, (q, &own_leaf)) in qs.iter().zip(leaves).enumerate() {
            self.probe_leaves(q, own_leaf, &mut probe);
            for &l in &probe {
                let leaf = &self.leaves[l as usize];
                hits.clear();
                scan(&leaf.descs, q, self.params.max_distance, &mut hits);
                for &(j, d) in &hits {
                    let (slot, r) = leaf.refs[j as usize];
                    let a = &mut accepted[slot as usize];
                    if *a == UNKNOWN {
                        let key = self.slots[slot as usize].expect("stored slots are live");
                        *a = accept(key) as u8;
                    }
                    if *a == 1 {
                        found.push((slot, qi as u32, r, d));
                    }
                }
            }
        }
        found.sort_unstable();
        let mut matches = ImageMatches::new();
        for chunk in found.chunk_by(|a, b| a.0 == b.0) {
            let image = self.slots[chunk[0].0 as usize].expect("live slot");
            matches.insert(
                image,
                chunk
                    .iter()
                    .map(|&(_, query, reference, distance)| DescriptorMatch {
                        query,
                        image,
                        reference,
                        distance,
                    })
                    .collect(),
            );
        }
        let own_neighbours = if own {
            self.own_neighbours(qs, leaves)
        } else {
            Vec::new()
        };
        QueryResult {
            matches,
            own_neighbours,
        }
    }

    /// For each query descriptor, the other query descriptors in its leaf within the threshold.
    fn own_neighbours(&self, qs: &[Words], leaves: &[u32]) -> Vec<u32> {
        let mut order: Vec<u32> = (0..qs.len() as u32).collect();
        order.sort_unstable_by_key(|&i| (leaves[i as usize], i));
        let mut count = vec![0u32; qs.len()];
        for group in order.chunk_by(|&a, &b| leaves[a as usize] == leaves[b as usize]) {
            for (k, &a) in group.iter().enumerate() {
                for &b in &group[k + 1..] {
                    if dist(&qs[a as usize], &qs[b as usize]) <= self.params.max_distance {
                        count[a as usize] += 1;
                        count[b as usize] += 1;
                    }
                }
            }
        }
        count
    }

    /// Adds one image's descriptors to the leaves they descended to, then splits the leaves
    /// that grew too large (in leaf order, so the result is deterministic).
    fn append(&mut self, image: u64, qs: &[Words], leaves: &[u32]) {
        let slot = match self.slot_of.get(&image) {
            Some(&s) => s,
            None => {
                let s = self.slots.len() as u32;
                self.slots.push(Some(image));
                self.slot_len.push(0);
                self.slot_of.insert(image, s);
                s
            }
        };
        let base = self.slot_len[slot as usize];
        for (i, (q, &l)) in qs.iter().zip(leaves).enumerate() {
            let leaf = &mut self.leaves[l as usize];
            leaf.descs.push(*q);
            leaf.refs.push((slot, base + i as u32));
        }
        self.slot_len[slot as usize] = base + qs.len() as u32;
        self.n_descriptors += qs.len();
        let mut touched: Vec<u32> = leaves.to_vec();
        touched.sort_unstable();
        touched.dedup();
        for l in touched {
            if self.leaves[l as usize].descs.len() > self.params.max_leaf_size {
                self.split(l);
            }
        }
    }

    /// Splits leaf `l` and, recursively, its children while they are too large.
    fn split(&mut self, l: u32) {
        let mut stack = vec![l];
        while let Some(l) = stack.pop() {
            let leaf = &self.leaves[l as usize];
            let n = leaf.descs.len();
            if n <= self.params.max_leaf_size {
                continue;
            }
            let Some(b) = best_split_bit(&leaf.descs, self.params.max_split_imbalance) else {
                continue;
            };
            let leaf = std::mem::take(&mut self.leaves[l as usize]);
            let (node, depth) = (leaf.node, leaf.depth);
            let mut halves = [Leaf::default(), Leaf::default()];
            for (d, r) in leaf.descs.into_iter().zip(leaf.refs) {
                let h = &mut halves[bit(&d, b)];
                h.descs.push(d);
                h.refs.push(r);
            }
            let [mut zero, mut one] = halves;
            let (n0, n1) = (self.nodes.len() as u32, self.nodes.len() as u32 + 1);
            let l1 = self.leaves.len() as u32;
            zero.node = n0;
            zero.depth = depth + 1;
            one.node = n1;
            one.depth = depth + 1;
            self.nodes[node as usize] = Node::Split {
                bit: b,
                children: [n0, n1],
            };
            self.nodes.push(Node::Leaf(l));
            self.nodes.push(Node::Leaf(l1));
            self.leaves[l as usize] = zero;
            self.leaves.push(one);
            stack.push(l1);
            stack.push(l);
        }
    }

    /// Statistics of the current tree.
    pub fn stats(&self) -> TreeStats {
        let m = self.params.max_leaf_size.max(1);
        let mut s = TreeStats {
            images: self.slot_of.len(),
            descriptors: self.n_descriptors,
            nodes: self.nodes.len(),
            leaves: self.leaves.len(),
            leaf_size_histogram: vec![0; 11],
            ..Default::default()
        };
        let (mut depth_sum, mut nonempty, mut weighted) = (0u64, 0usize, 0u64);
        for leaf in &self.leaves {
            let n = leaf.descs.len();
            s.max_depth = s.max_depth.max(leaf.depth);
            if n == 0 {
                s.empty_leaves += 1;
            } else {
                nonempty += 1;
                depth_sum += leaf.depth as u64;
                weighted += leaf.depth as u64 * n as u64;
            }
            if n > m {
                s.oversized_leaves += 1;
            }
            let bucket = if n > m {
                10
            } else {
                (n * 10).div_ceil(m).saturating_sub(1)
            };
            s.leaf_size_histogram[bucket] += 1;
            s.memory_bytes += leaf.descs.capacity() * 32 + leaf.refs.capacity() * 8;
        }
        s.memory_bytes += self.nodes.capacity() * std::mem::size_of::<Node>()
            + self.leaves.capacity() * std::mem::size_of::<Leaf>();
        s.mean_leaf_depth = depth_sum as f64 / nonempty.max(1) as f64;
        s.mean_descriptor_depth = weighted as f64 / self.n_descriptors.max(1) as f64;
        // Subtree sizes bottom-up: children always have larger node indices than their parent.
        let mut size = vec![0usize; self.nodes.len()];
        let (mut balance, mut splits) = (0.0, 0usize);
        for i in (0..self.nodes.len()).rev() {
            size[i] = match self.nodes[i] {
                Node::Leaf(l) => self.leaves[l as usize].descs.len(),
                Node::Split { children, .. } => {
                    let (a, b) = (size[children[0] as usize], size[children[1] as usize]);
                    if a + b > 0 {
                        balance += a.min(b) as f64 / (a + b) as f64;
                        splits += 1;
                    }
                    a + b
                }
            };
        }
        s.mean_split_balance = if splits > 0 {
            balance / splits as f64
        } else {
            0.5
        };
        s
    }

    /// Every stored descriptor with its image and reference index, leaf by leaf (tests).
    pub fn stored(&self) -> Vec<(u64, u32, Descriptor)> {
        let mut out = Vec::with_capacity(self.n_descriptors);
        for leaf in &self.leaves {
            for (d, &(slot, r)) in leaf.descs.iter().zip(&leaf.refs) {
                let mut bytes = [0u8; 32];
                for k in 0..4 {
                    bytes[8 * k..8 * k + 8].copy_from_slice(&d[k].to_le_bytes());
                }
                out.push((self.slots[slot as usize].expect("live"), r, bytes));
            }
        }
        out
    }

    /// Leaf sizes and whether a split would be accepted, for the invariant tests.
    pub fn leaf_report(&self) -> Vec<(usize, bool)> {
        self.leaves
            .iter()
            .map(|l| {
                (
                    l.descs.len(),
                    best_split_bit(&l.descs, self.params.max_split_imbalance).is_some(),
                )
            })
            .collect()
    }
}

impl DescriptorIndex for Hbst {
    fn query_detailed(
        &self,
        descriptors: &[Descriptor],
        accept: impl Fn(u64) -> bool,
        own_neighbours: bool,
    ) -> QueryResult {
        let qs: Vec<Words> = descriptors.iter().map(words).collect();
        let leaves: Vec<u32> = qs.iter().map(|q| self.descend(q)).collect();
        self.run_query(&qs, &leaves, accept, own_neighbours)
    }

    fn query_and_insert_detailed(
        &mut self,
        image: u64,
        descriptors: &[Descriptor],
        accept: impl Fn(u64) -> bool,
        own_neighbours: bool,
    ) -> QueryResult {
        let qs: Vec<Words> = descriptors.iter().map(words).collect();
        let leaves: Vec<u32> = qs.iter().map(|q| self.descend(q)).collect();
        let r = self.run_query(&qs, &leaves, accept, own_neighbours);
        self.append(image, &qs, &leaves);
        r
    }

    fn insert(&mut self, image: u64, descriptors: &[Descriptor]) {
        let qs: Vec<Words> = descriptors.iter().map(words).collect();
        let leaves: Vec<u32> = qs.iter().map(|q| self.descend(q)).collect();
        self.append(image, &qs, &leaves);
    }

    /// O(stored descriptors): every leaf is filtered. The tree keeps its shape (leaves may
    /// become small or empty), which does not affect correctness.
    fn remove_image(&mut self, image: u64) {
        let Some(slot) = self.slot_of.remove(&image) else {
            return;
        };
        self.slots[slot as usize] = None;
        let mut removed = 0;
        for leaf in &mut self.leaves {
            if !leaf.refs.iter().any(|r| r.0 == slot) {
                continue;
            }
            let mut k = 0;
            for j in 0..leaf.refs.len() {
                if leaf.refs[j].0 != slot {
                    leaf.refs[k] = leaf.refs[j];
                    leaf.descs[k] = leaf.descs[j];
                    k += 1;
                }
            }
            removed += leaf.refs.len() - k;
            leaf.refs.truncate(k);
            leaf.descs.truncate(k);
        }
        self.n_descriptors -= removed;
    }

    fn n_images(&self) -> usize {
        self.slot_of.len()
    }
}

/// The bit whose set fraction over `descs` is closest to 0.5 (lowest index on ties), or `None`
/// when that bit's imbalance exceeds `max_imbalance` or it would leave one side empty.
fn best_split_bit(descs: &[Words], max_imbalance: f64) -> Option<u8> {
    let n = descs.len();
    if n < 2 {
        return None;
    }
    let mut counts = [0u32; 256];
    for d in descs {
        for (w, word) in d.iter().enumerate() {
            let c = &mut counts[64 * w..64 * w + 64];
            for (b, cb) in c.iter_mut().enumerate() {
                *cb += ((word >> b) & 1) as u32;
            }
        }
    }
    // |n/2 − count| in integers (doubled to stay exact): 2·|0.5 − c/n|·n = |n − 2c|.
    let (b, c) = counts
        .iter()
        .enumerate()
        .min_by_key(|&(b, &c)| ((n as i64 - 2 * c as i64).unsigned_abs(), b))
        .expect("256 bits");
    let c = *c as usize;
    let imbalance = (0.5 - c as f64 / n as f64).abs();
    (c > 0 && c < n && imbalance <= max_imbalance).then_some(b as u8)
}

/// Exhaustive matching with the same interface: the reference the HBST is measured against.
#[derive(Debug, Clone, Default)]
pub struct BruteForce {
    max_distance: u32,
    images: BTreeMap<u64, Vec<Words>>,
}

impl BruteForce {
    pub fn new(max_distance: u32) -> Self {
        Self {
            max_distance,
            images: BTreeMap::new(),
        }
    }

    pub fn len(&self) -> usize {
        self.images.values().map(Vec::len).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.images.is_empty()
    }
}

impl DescriptorIndex for BruteForce {
    fn query_detailed(
        &self,
        descriptors: &[Descriptor],
        accept: impl Fn(u64) -> bool,
        own_neighbours: bool,
    ) -> QueryResult {
        let qs: Vec<Words> = descriptors.iter().map(words).collect();
        let mut matches = ImageMatches::new();
        let mut hits = Vec::new();
        for (&image, stored) in &self.images {
            if !accept(image) {
                continue;
            }
            let mut v = Vec::new();
            for (qi, q) in qs.iter().enumerate() {
                hits.clear();
                scan(stored, q, self.max_distance, &mut hits);
                v.extend(hits.iter().map(|&(r, d)| DescriptorMatch {
                    query: qi as u32,
                    image,
                    reference: r,
                    distance: d,
                }));
            }
            if !v.is_empty() {
                matches.insert(image, v);
            }
        }
        let own_neighbours = if own_neighbours {
            let mut count = vec![0u32; qs.len()];
            for a in 0..qs.len() {
                for b in a + 1..qs.len() {
                    if dist(&qs[a], &qs[b]) <= self.max_distance {
                        count[a] += 1;
                        count[b] += 1;
                    }
                }
            }
            count
        } else {
            Vec::new()
        };
        QueryResult {
            matches,
            own_neighbours,
        }
    }

    fn query_and_insert_detailed(
        &mut self,
        image: u64,
        descriptors: &[Descriptor],
        accept: impl Fn(u64) -> bool,
        own_neighbours: bool,
    ) -> QueryResult {
        let r = self.query_detailed(descriptors, accept, own_neighbours);
        self.insert(image, descriptors);
        r
    }

    fn insert(&mut self, image: u64, descriptors: &[Descriptor]) {
        self.images
            .entry(image)
            .or_default()
            .extend(descriptors.iter().map(words));
    }

    fn remove_image(&mut self, image: u64) {
        self.images.remove(&image);
    }

    fn n_images(&self) -> usize {
        self.images.len()
    }
}
