//! Bag-of-words place recognition (DBoW2's scheme, as ORB-SLAM uses it): a vocabulary tree of
//! binary words trained by hierarchical k-majority on images that are not evaluated on, TF-IDF
//! weighted L1-normalised word vectors, L1 scores, and an inverted file per word.
//!
//! Why, next to the HBST: a revisit from another viewpoint changes ORB descriptors by 30–60
//! bits, far beyond the HBST's match distance (25), so the tree finds almost none of a real
//! revisit's matches (fr1_desk: 14 % of brute force's at that distance). A word is a region of
//! descriptor space learned from generic images, so two views of one place share words even
//! where their descriptors are far apart (docs/decisions/0001-bag-of-words-place-recognition.md).

use crate::components::preprocess::{Descriptor, hamming};
use crate::{Error, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};

/// The vocabulary shipped with homing: k = 10, 5 levels, trained by `vocab-tools train` on
/// 1,500 generic photos (ImageNet samples and BSDS500; see vocab/README.md).
static BUILT_IN: &[u8] = include_bytes!("../../../vocab/orb_k10_l5.voc");

const MAGIC: &[u8; 8] = b"HOMVOC01";

/// The vocabulary at `path` (`None`: the built-in one), parsed once per process and shared:
/// every detector of a benchmark's runs uses the same tree.
pub fn shared(path: Option<&Path>) -> Result<Arc<Vocabulary>> {
    static CACHE: OnceLock<Mutex<BTreeMap<Option<PathBuf>, Arc<Vocabulary>>>> = OnceLock::new();
    let key = path.map(Path::to_path_buf);
    let cache = CACHE.get_or_init(Default::default);
    if let Some(v) = cache.lock().expect("vocabulary cache").get(&key) {
        return Ok(v.clone());
    }
    let v = Arc::new(match path {
        None => Vocabulary::built_in(),
        Some(p) => Vocabulary::load(p)?,
    });
    cache
        .lock()
        .expect("vocabulary cache")
        .insert(key, v.clone());
    Ok(v)
}
const NO_PARENT: u32 = u32::MAX;

/// A vocabulary tree: node 0 is the root; every other node has a parent earlier in the list
/// and a cluster centre; leaves are the words, each with its inverse document frequency.
#[derive(Debug, Clone, PartialEq)]
pub struct Vocabulary {
    k: u32,
    levels: u32,
    parent: Vec<u32>,
    centre: Vec<Descriptor>,
    /// Children of each node (derived from `parent`).
    children: Vec<Vec<u32>>,
    /// Word id of each node (`u32::MAX`: an inner node).
    word: Vec<u32>,
    /// IDF weight of each word.
    idf: Vec<f32>,
}

/// A TF-IDF word vector, L1-normalised: (word, weight) by word.
pub type BowVector = Vec<(u32, f32)>;

/// Σ min(a_w, b_w) over shared words: DBoW2's L1 score (0: nothing shared, 1: identical).
pub fn score(a: &BowVector, b: &BowVector) -> f64 {
    let (mut i, mut j, mut s) = (0, 0, 0.0f64);
    while i < a.len() && j < b.len() {
        match a[i].0.cmp(&b[j].0) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                s += a[i].1.min(b[j].1) as f64;
                i += 1;
                j += 1;
            }
        }
    }
    s
}

impl Vocabulary {
    /// The vocabulary built into the binary.
    pub fn built_in() -> Self {
        Self::from_bytes(BUILT_IN, Path::new("<built-in vocabulary>"))
            .expect("the built-in vocabulary is valid (checked by a unit test)")
    }

    /// Reads a vocabulary file written by [`Vocabulary::save`].
    pub fn load(path: &Path) -> Result<Self> {
        let bytes =
            std::fs::read(path).map_err(|e| Error::file(path, format!("cannot read: {e}")))?;
        Self::from_bytes(&bytes, path)
    }

    pub fn k(&self) -> u32 {
        self.k
    }
    pub fn levels(&self) -> u32 {
        self.levels
    }
    pub fn n_words(&self) -> usize {
        self.idf.len()
    }

    /// Trains the tree by hierarchical k-majority (k-means++ seeding, bitwise-majority centres)
    /// on `images`' descriptors, then sets each word's IDF = ln(images / images containing it).
    /// Deterministic for a given seed.
    pub fn train(images: &[Vec<Descriptor>], k: u32, levels: u32, seed: u64) -> Result<Self> {
        if k < 2 || levels == 0 {
            return Err(Error::invalid(
                "a vocabulary needs k ≥ 2 and at least one level",
            ));
        }
        let all: Vec<Descriptor> = images.iter().flatten().copied().collect();
        if all.is_empty() {
            return Err(Error::invalid("no descriptors to train a vocabulary on"));
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut v = Vocabulary::root(k, levels);
        // Depth-first, so that a node's subtree is contiguous; (node, depth, members).
        let mut stack: Vec<(u32, u32, Vec<u32>)> = vec![(0, 0, (0..all.len() as u32).collect())];
        while let Some((node, depth, members)) = stack.pop() {
            let clusters = k_majority(&all, &members, k as usize, &mut rng);
            let mut pushed = Vec::new();
            for (centre, cluster) in clusters {
                let id = v.parent.len() as u32;
                v.parent.push(node);
                v.centre.push(centre);
                v.children.push(Vec::new());
                v.word.push(u32::MAX);
                v.children[node as usize].push(id);
                if depth + 1 < levels && cluster.len() > 1 {
                    pushed.push((id, depth + 1, cluster));
                }
            }
            stack.extend(pushed.into_iter().rev());
        }
        let mut n_words = 0;
        for i in 0..v.parent.len() {
            if i > 0 && v.children[i].is_empty() {
                v.word[i] = n_words;
                n_words += 1;
            }
        }
        // IDF from the training images.
        let mut containing = vec![0u32; n_words as usize];
        for img in images {
            let mut words: Vec<u32> = img.iter().map(|d| v.word_of(d)).collect();
            words.sort_unstable();
            words.dedup();
            for w in words {
                containing[w as usize] += 1;
            }
        }
        let n = images.iter().filter(|i| !i.is_empty()).count().max(1) as f64;
        v.idf = containing
            .iter()
            .map(|&c| (n / c.max(1) as f64).ln() as f32)
            .collect();
        Ok(v)
    }

    /// A tree of only its root, to grow.
    fn root(k: u32, levels: u32) -> Self {
        Vocabulary {
            k,
            levels,
            parent: vec![NO_PARENT],
            centre: vec![[0; 32]],
            children: vec![Vec::new()],
            word: vec![u32::MAX],
            idf: Vec::new(),
        }
    }

    /// The word of one descriptor: the nearest child at every level, root to leaf.
    pub fn word_of(&self, d: &Descriptor) -> u32 {
        let mut node = 0usize;
        while !self.children[node].is_empty() {
            let mut best = (u32::MAX, 0u32);
            for &c in &self.children[node] {
                let h = hamming(d, &self.centre[c as usize]);
                if h < best.0 {
                    best = (h, c);
                }
            }
            node = best.1 as usize;
        }
        self.word[node]
    }

    /// The TF-IDF word vector of an image's descriptors, L1-normalised.
    pub fn transform(&self, descriptors: &[Descriptor]) -> BowVector {
        let mut acc: BTreeMap<u32, f32> = BTreeMap::new();
        for d in descriptors {
            let w = self.word_of(d);
            let idf = self.idf[w as usize];
            if idf > 0.0 {
                *acc.entry(w).or_default() += idf;
            }
        }
        let total: f32 = acc.values().sum();
        if total <= 0.0 {
            return Vec::new();
        }
        acc.into_iter().map(|(w, x)| (w, x / total)).collect()
    }

    /// The file format: magic, k, levels, node count, then per node (root excluded) its parent,
    /// centre and IDF (negative for inner nodes), and a CRC-32 of everything before it.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut b = Vec::with_capacity(16 + self.parent.len() * 40);
        b.extend_from_slice(MAGIC);
        for x in [self.k, self.levels, self.parent.len() as u32] {
            b.extend_from_slice(&x.to_le_bytes());
        }
        for i in 1..self.parent.len() {
            b.extend_from_slice(&self.parent[i].to_le_bytes());
            b.extend_from_slice(&self.centre[i]);
            let w = self.word[i];
            let idf = if w == u32::MAX {
                -1.0
            } else {
                self.idf[w as usize]
            };
            b.extend_from_slice(&idf.to_le_bytes());
        }
        let crc = crc32fast::hash(&b);
        b.extend_from_slice(&crc.to_le_bytes());
        b
    }

    /// Writes the vocabulary atomically (temporary file, then rename).
    pub fn save(&self, path: &Path) -> Result<()> {
        crate::io::atomic_write(path, &self.to_bytes())
    }

    /// Parses [`Vocabulary::to_bytes`]; `path` names the source in errors.
    pub fn from_bytes(b: &[u8], path: &Path) -> Result<Self> {
        let bad = |msg: String| Error::file(path, format!("not a valid vocabulary: {msg}"));
        if b.len() < MAGIC.len() + 16 || &b[..MAGIC.len()] != MAGIC {
            return Err(bad(
                "wrong header (expected a homing vocabulary file)".into()
            ));
        }
        let (payload, crc) = b.split_at(b.len() - 4);
        if crc32fast::hash(payload) != u32::from_le_bytes(crc.try_into().expect("4 bytes")) {
            return Err(bad("checksum mismatch (truncated or corrupt)".into()));
        }
        let u32_at = |o: usize| u32::from_le_bytes(payload[o..o + 4].try_into().expect("4"));
        let (k, levels, n) = (u32_at(8), u32_at(12), u32_at(16) as usize);
        const NODE: usize = 4 + 32 + 4;
        if n == 0 || payload.len() != 20 + (n - 1) * NODE {
            return Err(bad(format!("{n} nodes do not fit {} bytes", payload.len())));
        }
        let mut v = Vocabulary::root(k, levels);
        for i in 1..n {
            let o = 20 + (i - 1) * NODE;
            let p = u32_at(o);
            if p as usize >= i {
                return Err(bad(format!("node {i} has parent {p}, not an earlier node")));
            }
            let centre: Descriptor = payload[o + 4..o + 36].try_into().expect("32 bytes");
            let idf = f32::from_le_bytes(payload[o + 36..o + 40].try_into().expect("4"));
            v.parent.push(p);
            v.centre.push(centre);
            v.children.push(Vec::new());
            v.children[p as usize].push(i as u32);
            v.word.push(u32::MAX);
            v.idf.push(idf); // provisional, per node; words are picked out below
        }
        let node_idf = std::mem::take(&mut v.idf);
        for i in 1..n {
            let leaf = v.children[i].is_empty();
            let idf = node_idf[i - 1];
            if leaf != (idf >= 0.0) || !idf.is_finite() {
                return Err(bad(format!("node {i}: leaf and weight disagree")));
            }
            if leaf {
                v.word[i] = v.idf.len() as u32;
                v.idf.push(idf);
            }
        }
        if v.idf.is_empty() {
            return Err(bad("no words".into()));
        }
        Ok(v)
    }
}

/// One k-majority clustering of `members`: k-means++ seeds, then assignment to the nearest
/// centre and bitwise-majority centres until nothing moves (at most 10 rounds). Fewer members
/// than `k`: each is its own cluster. Returns (centre, members) of the non-empty clusters.
fn k_majority(
    all: &[Descriptor],
    members: &[u32],
    k: usize,
    rng: &mut ChaCha8Rng,
) -> Vec<(Descriptor, Vec<u32>)> {
    if members.len() <= k {
        return members
            .iter()
            .map(|&m| (all[m as usize], vec![m]))
            .collect();
    }
    // k-means++ seeding.
    let mut centres: Vec<Descriptor> =
        vec![all[members[rng.random_range(0..members.len())] as usize]];
    let mut d2: Vec<f64> = members
        .iter()
        .map(|&m| (hamming(&all[m as usize], &centres[0]) as f64).powi(2))
        .collect();
    while centres.len() < k {
        let total: f64 = d2.iter().sum();
        if total <= 0.0 {
            break; // every member equals a centre
        }
        let mut r = rng.random::<f64>() * total;
        let mut pick = members.len() - 1;
        for (i, &x) in d2.iter().enumerate() {
            if r < x {
                pick = i;
                break;
            }
            r -= x;
        }
        let c = all[members[pick] as usize];
        centres.push(c);
        for (i, &m) in members.iter().enumerate() {
            d2[i] = d2[i].min((hamming(&all[m as usize], &c) as f64).powi(2));
        }
    }
    let mut assign = vec![usize::MAX; members.len()];
    for _round in 0..10 {
        let mut moved = false;
        for (i, &m) in members.iter().enumerate() {
            let d = &all[m as usize];
            let (mut best, mut bc) = (u32::MAX, 0);
            for (c, centre) in centres.iter().enumerate() {
                let h = hamming(d, centre);
                if h < best {
                    (best, bc) = (h, c);
                }
            }
            if assign[i] != bc {
                assign[i] = bc;
                moved = true;
            }
        }
        if !moved {
            break;
        }
        // Bitwise majority of each cluster.
        let mut counts = vec![[0u32; 256]; centres.len()];
        let mut sizes = vec![0u32; centres.len()];
        for (i, &m) in members.iter().enumerate() {
            let c = assign[i];
            sizes[c] += 1;
            let d = &all[m as usize];
            for (byte, &x) in d.iter().enumerate() {
                if x == 0 {
                    continue;
                }
                for bit in 0..8 {
                    counts[c][byte * 8 + bit] += ((x >> bit) & 1) as u32;
                }
            }
        }
        for (c, centre) in centres.iter_mut().enumerate() {
            if sizes[c] == 0 {
                continue; // keeps its seed; empty clusters are dropped below
            }
            let mut out = [0u8; 32];
            for (bit, &n) in counts[c].iter().enumerate() {
                if 2 * n > sizes[c] {
                    out[bit / 8] |= 1 << (bit % 8);
                }
            }
            *centre = out;
        }
    }
    let mut clusters: Vec<Vec<u32>> = vec![Vec::new(); centres.len()];
    for (i, &m) in members.iter().enumerate() {
        clusters[assign[i]].push(m);
    }
    centres
        .into_iter()
        .zip(clusters)
        .filter(|(_, c)| !c.is_empty())
        .collect()
}

/// The keyframe database (DBoW2's inverted file): each stored image's word vector, and per
/// word the images that contain it, so a query only touches images that share a word.
#[derive(Debug, Clone, Default)]
pub struct BowDatabase {
    vectors: BTreeMap<u64, BowVector>,
    inverted: BTreeMap<u32, BTreeMap<u64, f32>>,
}

impl BowDatabase {
    pub fn insert(&mut self, image: u64, v: BowVector) {
        self.remove(image);
        for &(w, x) in &v {
            self.inverted.entry(w).or_default().insert(image, x);
        }
        self.vectors.insert(image, v);
    }

    pub fn remove(&mut self, image: u64) {
        if let Some(v) = self.vectors.remove(&image) {
            for (w, _) in v {
                if let Some(l) = self.inverted.get_mut(&w) {
                    l.remove(&image);
                    if l.is_empty() {
                        self.inverted.remove(&w);
                    }
                }
            }
        }
    }

    pub fn get(&self, image: u64) -> Option<&BowVector> {
        self.vectors.get(&image)
    }

    pub fn len(&self) -> usize {
        self.vectors.len()
    }
    pub fn is_empty(&self) -> bool {
        self.vectors.is_empty()
    }

    /// Every stored image that `accept`s and shares a word with `v`: (image, L1 score,
    /// shared words), by image.
    pub fn query(&self, v: &BowVector, accept: impl Fn(u64) -> bool) -> Vec<(u64, f64, u32)> {
        let mut acc: BTreeMap<u64, (f64, u32)> = BTreeMap::new();
        for &(w, x) in v {
            if let Some(l) = self.inverted.get(&w) {
                for (&img, &y) in l {
                    if accept(img) {
                        let e = acc.entry(img).or_default();
                        e.0 += x.min(y) as f64;
                        e.1 += 1;
                    }
                }
            }
        }
        acc.into_iter().map(|(i, (s, n))| (i, s, n)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn noisy(rng: &mut ChaCha8Rng, d: &Descriptor, flips: usize) -> Descriptor {
        let mut o = *d;
        for _ in 0..flips {
            let b = rng.random_range(0..256);
            o[b / 8] ^= 1 << (b % 8);
        }
        o
    }

    /// Images of distinct "places", each a set of random landmarks seen with bit noise.
    fn places(n_places: usize, per: usize, seed: u64) -> Vec<Vec<Descriptor>> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n_places)
            .map(|_| (0..per).map(|_| rng.random::<[u8; 32]>()).collect())
            .collect()
    }

    #[test]
    fn a_revisit_scores_above_other_places() {
        let world = places(20, 200, 1);
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        // Trained on other views of the same world: random descriptors have no structure a
        // vocabulary of other data could capture.
        let training: Vec<Vec<Descriptor>> = world
            .iter()
            .map(|p| p.iter().map(|d| noisy(&mut rng, d, 10)).collect())
            .collect();
        let v = Vocabulary::train(&training, 8, 3, 7).unwrap();
        assert!(v.n_words() > 64, "{} words", v.n_words());
        let mut db = BowDatabase::default();
        for (i, p) in world.iter().enumerate() {
            db.insert(i as u64, v.transform(p));
        }
        // Place 5 seen again: 60 % of its landmarks, each with 20 bits changed.
        let seen: Vec<Descriptor> = world[5][..120]
            .iter()
            .map(|d| noisy(&mut rng, d, 20))
            .collect();
        let q = v.transform(&seen);
        let mut r = db.query(&q, |_| true);
        r.sort_by(|a, b| b.1.total_cmp(&a.1));
        assert_eq!(r[0].0, 5);
        assert!(r[0].1 > 2.0 * r[1].1, "{r:?}");
        assert!((score(&q, db.get(5).unwrap()) - r[0].1).abs() < 1e-6);
        // Excluded images are not scored.
        assert!(db.query(&q, |i| i != 5).iter().all(|x| x.0 != 5));
    }

    #[test]
    fn vectors_are_l1_normalised_and_identical_images_score_one() {
        let v = Vocabulary::train(&places(10, 100, 4), 5, 2, 1).unwrap();
        let img = &places(1, 150, 9)[0];
        let a = v.transform(img);
        let sum: f32 = a.iter().map(|x| x.1).sum();
        assert!((sum - 1.0).abs() < 1e-4);
        assert!((score(&a, &a) - 1.0).abs() < 1e-4);
        assert!(a.windows(2).all(|w| w[0].0 < w[1].0));
    }

    #[test]
    fn save_and_load_round_trip_and_corruption_is_an_error_naming_the_file() {
        let v = Vocabulary::train(&places(10, 100, 5), 4, 3, 2).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("v.voc");
        v.save(&p).unwrap();
        assert_eq!(Vocabulary::load(&p).unwrap(), v);
        let mut b = std::fs::read(&p).unwrap();
        let mid = b.len() / 2;
        b[mid] ^= 1;
        std::fs::write(&p, &b).unwrap();
        let e = Vocabulary::load(&p).unwrap_err().to_string();
        assert!(e.contains("v.voc") && e.contains("checksum"), "{e}");
        std::fs::write(&p, &b[..10]).unwrap();
        assert!(Vocabulary::load(&p).is_err());
        assert!(Vocabulary::load(&dir.path().join("missing.voc")).is_err());
    }

    #[test]
    fn training_is_deterministic() {
        let imgs = places(8, 120, 6);
        let a = Vocabulary::train(&imgs, 6, 3, 11).unwrap();
        let b = Vocabulary::train(&imgs, 6, 3, 11).unwrap();
        assert_eq!(a.to_bytes(), b.to_bytes());
    }

    #[test]
    fn the_built_in_vocabulary_loads() {
        let v = Vocabulary::built_in();
        assert_eq!((v.k(), v.levels()), (10, 5));
        assert!(v.n_words() > 10_000, "{} words", v.n_words());
    }
}
