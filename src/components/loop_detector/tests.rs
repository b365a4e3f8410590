use super::*;
use crate::components::preprocess::hamming;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn random_descs(rng: &mut ChaCha8Rng, n: usize) -> Vec<Descriptor> {
    (0..n).map(|_| rng.random()).collect()
}

/// `d` with exactly `k` distinct bits flipped.
fn perturb(rng: &mut ChaCha8Rng, d: &Descriptor, k: usize) -> Descriptor {
    let mut out = *d;
    let mut bits: Vec<usize> = (0..256).collect();
    for i in 0..k {
        let j = rng.random_range(i..256);
        bits.swap(i, j);
        out[bits[i] / 8] ^= 1 << (bits[i] % 8);
    }
    out
}

/// Images whose descriptors share some structure (a common pool with noise plus fresh random
/// ones), so that splits are not all perfectly balanced as with uniform random bits.
fn structured_images(seed: u64, n_images: usize, per_image: usize) -> Vec<Vec<Descriptor>> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let pool = random_descs(&mut rng, 300);
    (0..n_images)
        .map(|_| {
            (0..per_image)
                .map(|k| {
                    if k % 3 == 0 {
                        rng.random()
                    } else {
                        let p = pool[rng.random_range(0..pool.len())];
                        let flips = rng.random_range(0..12);
                        perturb(&mut rng, &p, flips)
                    }
                })
                .collect()
        })
        .collect()
}

fn small_params() -> HbstParams {
    HbstParams {
        max_leaf_size: 20,
        max_distance: 25,
        max_split_imbalance: 0.45,
        search_flips: 0,
    }
}

#[test]
fn every_inserted_descriptor_is_reachable_and_found_exactly() {
    let images = structured_images(1, 40, 60);
    let mut t = Hbst::new(small_params());
    for (i, d) in images.iter().enumerate() {
        t.insert(i as u64, d);
    }
    assert_eq!(t.len(), 40 * 60);
    assert_eq!(t.stored().len(), 40 * 60);
    assert!(t.stats().leaves > 20, "the tree must have split");
    for (i, descs) in images.iter().enumerate() {
        let m = t.query(descs, |_| true);
        let own = &m[&(i as u64)];
        for (q, _) in descs.iter().enumerate() {
            assert!(
                own.iter()
                    .any(|x| x.query == q as u32 && x.reference == q as u32 && x.distance == 0),
                "image {i} descriptor {q} not found as an exact duplicate of itself"
            );
        }
    }
    // Reachability directly: every stored descriptor descends to the leaf that holds it.
    let mut by_leaf: BTreeMap<u32, usize> = BTreeMap::new();
    for (_, _, d) in t.stored() {
        *by_leaf.entry(t.leaf_of(&d).0).or_default() += 1;
    }
    let sizes: Vec<usize> = t.leaf_report().iter().map(|r| r.0).collect();
    for (l, n) in by_leaf {
        assert!(sizes[l as usize] >= n);
    }
}

#[test]
fn leaves_respect_max_size_unless_unsplittable() {
    let images = structured_images(2, 30, 80);
    let mut t = Hbst::new(small_params());
    for (i, d) in images.iter().enumerate() {
        t.insert(i as u64, d);
    }
    // Plus an unsplittable pile: 50 identical descriptors.
    let same = [[0xA5u8; 32]; 50];
    t.insert(1000, &same);
    let report = t.leaf_report();
    let mut oversized = 0;
    for &(n, splittable) in &report {
        assert!(
            n <= 20 || !splittable,
            "leaf of {n} > 20 descriptors could have been split"
        );
        oversized += (n > 20) as usize;
    }
    assert!(oversized >= 1, "the identical descriptors cannot be split");
    let s = t.stats();
    assert_eq!(s.oversized_leaves, oversized);
    assert_eq!(s.leaf_size_histogram.iter().sum::<usize>(), s.leaves);
    assert_eq!(s.descriptors, 30 * 80 + 50);
    assert_eq!(s.images, 31);
    assert!(s.mean_split_balance > 0.3 && s.mean_split_balance <= 0.5);
    assert!(s.max_depth as f64 >= s.mean_leaf_depth);
}

#[test]
fn split_imbalance_limit_is_applied() {
    // 95 descriptors with bit 0 clear and 6 with it set, every other bit equal: the only
    // usable bit has imbalance |0.5 − 6/101| = 0.44, accepted at 0.45, rejected at 0.4.
    let mut descs = vec![[0u8; 32]; 95];
    descs.extend(std::iter::repeat_n(
        {
            let mut d = [0u8; 32];
            d[0] = 1;
            d
        },
        6,
    ));
    for (limit, splits) in [(0.45, true), (0.4, false)] {
        let mut t = Hbst::new(HbstParams {
            max_leaf_size: 100,
            max_distance: 25,
            max_split_imbalance: limit,
            search_flips: 0,
        });
        t.insert(0, &descs);
        assert_eq!(t.stats().leaves > 1, splits, "limit {limit}");
    }
}

#[test]
fn building_is_deterministic() {
    let images = structured_images(3, 25, 70);
    let build = || {
        let mut t = Hbst::new(small_params());
        for (i, d) in images.iter().enumerate() {
            t.insert(i as u64 * 7, d);
        }
        t
    };
    let (a, b) = (build(), build());
    assert_eq!(a.stats(), b.stats());
    assert_eq!(a.stored(), b.stored());
    let q = &images[5];
    assert_eq!(a.query(q, |_| true), b.query(q, |_| true));
}

/// HBST is approximate: a stored descriptor at Hamming distance k from the query is found
/// only when none of the k flipped bits lies on the query's path. Measured here on 40 000
/// random descriptors (tree depth ≈ 9 with leaves of ≤ 100): the recall falls with k roughly
/// like (1 − k/256)^depth.
#[test]
fn perturbed_descriptors_are_found_with_reasonable_recall() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let images: Vec<Vec<Descriptor>> = (0..200).map(|_| random_descs(&mut rng, 200)).collect();
    let mut t = Hbst::default();
    for (i, d) in images.iter().enumerate() {
        t.insert(i as u64, d);
    }
    let mut recall = Vec::new();
    for k in [0usize, 4, 8, 16, 25] {
        let mut found = 0;
        let n = 2000;
        for s in 0..n {
            let (img, idx) = (s % 200, (s * 7) % 200);
            let q = perturb(&mut rng, &images[img][idx], k);
            assert_eq!(hamming(&q, &images[img][idx]), k as u32);
            let m = t.query(&[q], |_| true);
            found += m.get(&(img as u64)).is_some_and(|v| {
                v.iter()
                    .any(|x| x.reference == idx as u32 && x.distance == k as u32)
            }) as usize;
        }
        recall.push((k, found as f64 / n as f64));
    }
    eprintln!("HBST recall by flipped bits: {recall:?}");
    let r = |k: usize| recall.iter().find(|x| x.0 == k).unwrap().1;
    assert_eq!(r(0), 1.0);
    assert!(r(4) >= 0.8, "{recall:?}");
    assert!(r(8) >= 0.65, "{recall:?}");
    assert!(r(16) >= 0.4, "{recall:?}");
    assert!(r(25) >= 0.25, "{recall:?}");
    assert!(r(4) >= r(8) && r(8) >= r(16) && r(16) >= r(25));
}

#[test]
fn hbst_matches_are_a_subset_of_brute_force_and_equal_without_splits() {
    let images = structured_images(5, 20, 50);
    let mut t = Hbst::new(small_params());
    let mut flat = Hbst::new(HbstParams {
        max_leaf_size: 1_000_000,
        ..small_params()
    });
    let mut bf = BruteForce::new(25);
    for (i, d) in images.iter().enumerate() {
        t.insert(i as u64, d);
        flat.insert(i as u64, d);
        bf.insert(i as u64, d);
    }
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let q: Vec<Descriptor> = images[3].iter().map(|d| perturb(&mut rng, d, 6)).collect();
    let accept = |i: u64| i != 4;
    let exact = bf.query_detailed(&q, accept, true);
    assert_eq!(flat.query_detailed(&q, accept, true), exact);
    let approx = t.query(&q, accept);
    assert!(!approx.contains_key(&4));
    let (mut n_approx, mut n_exact) = (0, 0);
    for (img, ms) in &approx {
        for m in ms {
            assert!(exact.matches[img].contains(m), "{m:?} not a true match");
        }
        n_approx += ms.len();
    }
    for ms in exact.matches.values() {
        n_exact += ms.len();
    }
    assert!(n_approx > n_exact / 3, "{n_approx} of {n_exact}");
}

#[test]
fn search_flips_find_more_true_matches_and_nothing_else() {
    // Queries whose descriptors differ by up to 12 bits leave their stored neighbours' path
    // at some split: each allowed flip must bring matches back, all of them true, none twice.
    let images = structured_images(5, 20, 50);
    let mut bf = BruteForce::new(25);
    let mut trees: Vec<Hbst> = (0..3)
        .map(|f| {
            Hbst::new(HbstParams {
                search_flips: f,
                ..small_params()
            })
        })
        .collect();
    for (i, d) in images.iter().enumerate() {
        bf.insert(i as u64, d);
        for t in &mut trees {
            t.insert(i as u64, d);
        }
    }
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let q: Vec<Descriptor> = images[2].iter().map(|d| perturb(&mut rng, d, 12)).collect();
    let exact = bf.query_detailed(&q, |_| true, false).matches;
    let mut counts = Vec::new();
    for t in &trees {
        let r = t.query(&q, |_| true);
        let mut n = 0;
        for (img, ms) in &r {
            let mut seen = std::collections::BTreeSet::new();
            for m in ms {
                assert!(exact[img].contains(m), "{m:?} not a true match");
                assert!(seen.insert((m.query, m.reference)), "{m:?} twice");
            }
            n += ms.len();
        }
        counts.push(n);
    }
    let n_exact: usize = exact.values().map(Vec::len).sum();
    assert!(
        counts[0] < counts[1] && counts[1] < counts[2] && counts[2] <= n_exact,
        "{counts:?} of {n_exact}"
    );
    // Inserting is unchanged by the search: the trees have the same shape.
    assert_eq!(trees[0].stats(), trees[2].stats());
}

#[test]
fn query_and_insert_equals_query_then_insert() {
    let images = structured_images(7, 30, 60);
    let mut a = Hbst::new(small_params());
    let mut b = Hbst::new(small_params());
    for (i, d) in images.iter().enumerate() {
        let key = 100 + i as u64;
        let accept = |k: u64| !k.is_multiple_of(3);
        let ra = a.query_and_insert_detailed(key, d, accept, true);
        let rb = b.query_detailed(d, accept, true);
        b.insert(key, d);
        assert_eq!(ra, rb, "image {i}");
        assert!(
            !ra.matches.contains_key(&key),
            "an image must not match itself"
        );
    }
    assert_eq!(a.stats(), b.stats());
    assert_eq!(a.stored(), b.stored());
}

#[test]
fn remove_image_forgets_only_that_image() {
    let images = structured_images(8, 15, 60);
    let mut t = Hbst::new(small_params());
    for (i, d) in images.iter().enumerate() {
        t.insert(i as u64, d);
    }
    t.remove_image(6);
    t.remove_image(999); // unknown: no-op
    assert_eq!(t.len(), 14 * 60);
    assert!(!t.contains_image(6));
    assert_eq!(t.stats().images, 14);
    assert!(!t.query(&images[6], |_| true).contains_key(&6));
    for (i, d) in images.iter().enumerate().filter(|(i, _)| *i != 6) {
        let m = t.query(d, |_| true);
        assert_eq!(
            m[&(i as u64)].iter().filter(|x| x.distance == 0).count(),
            60
        );
    }
    // The key can be used again.
    t.insert(6, &images[0]);
    let m = t.query(&images[0], |k| k == 6);
    assert_eq!(m[&6].iter().filter(|x| x.distance == 0).count(), 60);
}

#[test]
fn inserting_a_key_again_continues_its_reference_indices() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let (x, y) = (random_descs(&mut rng, 10), random_descs(&mut rng, 5));
    let mut t = Hbst::new(small_params());
    t.insert(1, &x);
    t.insert(1, &y);
    let m = t.query(&y, |_| true);
    for (q, _) in y.iter().enumerate() {
        assert!(
            m[&1]
                .iter()
                .any(|x| x.query == q as u32 && x.reference == 10 + q as u32 && x.distance == 0)
        );
    }
}

fn dm(query: u32, reference: u32, distance: u32) -> DescriptorMatch {
    DescriptorMatch {
        query,
        image: 5,
        reference,
        distance,
    }
}

fn params(min_matches: u32, min_score: f64) -> LoopDetectorParams {
    LoopDetectorParams {
        hbst: HbstParams::default(),
        min_matches,
        min_score,
        ambiguity_ratio: 0.9,
        self_similarity: None,
    }
}

#[test]
fn ambiguity_filter_drops_ratio_failures_and_shared_references() {
    let mut r = QueryResult::default();
    r.matches.insert(
        5,
        vec![
            dm(0, 1, 10), // q0: 10 vs 11 → ambiguous
            dm(0, 2, 11),
            dm(1, 3, 5), // q1: 5 vs 20 → kept
            dm(1, 4, 20),
            dm(2, 7, 3), // q2 and q3 both claim reference 7 → both dropped
            dm(3, 7, 4),
            dm(4, 8, 0), // q4: alone → kept
            dm(5, 9, 0), // q5: exact tie at 0 → ambiguous
            dm(5, 10, 0),
        ],
    );
    let d = score(10, &r, &params(1, 0.0));
    assert_eq!(d.candidates.len(), 1);
    let c = &d.candidates[0];
    assert_eq!(c.image, 5);
    assert_eq!(c.matches, vec![(1, 3), (4, 8)]);
    assert!((c.score - 0.2).abs() < 1e-12);
    assert_eq!(d.report.ambiguous, 2);
    assert_eq!(d.report.shared_reference, 2);
    assert_eq!(d.report.raw_matches, 9);
    // Thresholds: 2 votes pass min_matches 2 but not 3; score 0.2 passes 0.2 but not 0.25.
    assert_eq!(score(10, &r, &params(2, 0.2)).candidates.len(), 1);
    assert!(score(10, &r, &params(3, 0.0)).candidates.is_empty());
    assert!(score(10, &r, &params(1, 0.25)).candidates.is_empty());
}

#[test]
fn self_similarity_filter_silences_repetitive_and_generic_descriptors() {
    let mut r = QueryResult::default();
    for img in 0..4u64 {
        let mut v = vec![DescriptorMatch {
            query: 0,
            image: img,
            reference: 0,
            distance: 1,
        }];
        if img == 0 {
            v.push(DescriptorMatch {
                query: 1,
                image: 0,
                reference: 1,
                distance: 1,
            });
            v.push(DescriptorMatch {
                query: 2,
                image: 0,
                reference: 2,
                distance: 1,
            });
        }
        r.matches.insert(img, v);
    }
    // q0 matches 4 images; q1 has 5 near-duplicates in its own image; q2 is clean.
    r.own_neighbours = vec![0, 5, 1];
    let mut p = params(1, 0.0);
    let off = score(3, &r, &p);
    assert_eq!(off.candidates[0].image, 0);
    assert_eq!(off.candidates[0].matches.len(), 3);
    p.self_similarity = Some(SelfSimilarityParams {
        max_own_neighbours: 2,
        max_images: 3,
    });
    let on = score(3, &r, &p);
    assert_eq!(on.report.self_similar, 2);
    assert_eq!(on.candidates.len(), 1, "images 1-3 had only q0's vote");
    assert_eq!(on.candidates[0].matches, vec![(2, 2)]);
}

#[test]
fn detector_finds_the_revisited_keyframe_and_respects_exclusion() {
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    let mut det = LoopDetector::new(LoopDetectorParams {
        min_matches: 30,
        min_score: 0.1,
        ..LoopDetectorParams::default()
    });
    let places: Vec<Vec<Descriptor>> = (0..30).map(|_| random_descs(&mut rng, 300)).collect();
    for (i, p) in places.iter().enumerate() {
        let d = det.detect_and_insert(i as u64, p, |_| false);
        assert!(d.candidates.is_empty(), "new place {i} matched {d:?}");
    }
    assert_eq!(det.recent_images(3), BTreeSet::from([27, 28, 29]));
    // Revisit place 12 with 5-bit noise on every descriptor (plus 100 new descriptors).
    let mut revisit: Vec<Descriptor> = places[12].iter().map(|d| perturb(&mut rng, d, 5)).collect();
    revisit.extend(random_descs(&mut rng, 100));
    let d = det.detect(&revisit, |_| false);
    assert_eq!(d.candidates.len(), 1, "{:?}", d.report);
    let c = &d.candidates[0];
    assert_eq!(c.image, 12);
    assert!(c.score > 0.4, "score {}", c.score);
    assert!(
        c.matches.iter().all(|&(q, r)| q == r),
        "wrong correspondences"
    );
    // Excluded → no candidate; then stored and queried again it finds both visits.
    assert!(det.detect(&revisit, |i| i == 12).candidates.is_empty());
    det.detect_and_insert(100, &revisit, |_| false);
    let again = det.detect(&revisit, |_| false);
    assert_eq!(again.candidates[0].image, 100);
    assert_eq!(again.candidates[1].image, 12);
    det.remove(100);
    assert_eq!(det.recent_images(1), BTreeSet::from([29]));
    assert_eq!(det.detect(&revisit, |_| false).candidates.len(), 1);
}

#[test]
fn params_come_from_the_config() {
    let c = LoopClosingConfig {
        self_similarity_filter: true,
        min_score: 0.2,
        ..Default::default()
    };
    let p = LoopDetectorParams::from_config(&c);
    assert_eq!(p.min_score, 0.2);
    assert_eq!(p.hbst.max_leaf_size, c.hbst_max_leaf_size as usize);
    assert_eq!(
        p.self_similarity.unwrap().max_images,
        c.self_similarity_max_images
    );
    assert!(
        LoopDetectorParams::from_config(&LoopClosingConfig::default())
            .self_similarity
            .is_none()
    );
}

/// Places: each a set of landmarks; a view of a place sees most of them with bit noise.
fn bow_world(seed: u64) -> (ChaCha8Rng, Vec<Vec<Descriptor>>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let places = (0..12).map(|_| random_descs(&mut rng, 300)).collect();
    (rng, places)
}

fn view(rng: &mut ChaCha8Rng, place: &[Descriptor], flips: usize) -> Vec<Descriptor> {
    let mut out = Vec::new();
    for d in place {
        if rng.random::<f64>() < 0.7 {
            out.push(perturb(rng, d, flips));
        }
    }
    out
}

fn bow_detector(seed: u64) -> LoopDetector {
    let (mut rng, places) = bow_world(seed + 100);
    let training: Vec<Vec<Descriptor>> = places.iter().map(|p| view(&mut rng, p, 10)).collect();
    let v = vocabulary::Vocabulary::train(&training, 8, 3, 1).unwrap();
    let mut d = LoopDetector::new(LoopDetectorParams::default());
    d.use_vocabulary(Arc::new(v), 10, 0.75);
    d
}

#[test]
fn bow_finds_a_revisit_far_beyond_the_hbst_distance_and_respects_exclusion() {
    // Views of places 0..6 stored as keyframes 0..6; place 3 revisited with 35 bits changed
    // per descriptor (a real change of viewpoint), where the HBST's 25 finds nothing.
    let (mut rng, places) = bow_world(7);
    let mut det = bow_detector(7);
    assert!(det.is_bow());
    for (i, p) in places.iter().take(6).enumerate() {
        let v = view(&mut rng, p, 8);
        det.insert(i as u64, &v);
    }
    let q = view(&mut rng, &places[3], 35);
    let d = det.detect(&q, |_| false);
    assert_eq!(
        d.candidates.first().map(|c| c.image),
        Some(3),
        "{:?}",
        d.report
    );
    assert!(d.candidates.iter().all(|c| c.matches.is_empty()));
    let d = det.detect(&q, |i| i == 3);
    assert!(d.candidates.iter().all(|c| c.image != 3));
    // A removed keyframe is no candidate any more.
    det.remove(3);
    assert!(
        det.detect(&q, |_| false)
            .candidates
            .iter()
            .all(|c| c.image != 3)
    );
}

#[test]
fn bow_groups_accumulate_over_covisible_keyframes_and_the_floor_refuses_weak_ones() {
    let (mut rng, places) = bow_world(9);
    let mut det = bow_detector(9);
    // Keyframes 0..3: three views of place 1 (one group); keyframe 10: one view of place 2.
    for i in 0..3 {
        let v = view(&mut rng, &places[1], 12);
        det.insert(i, &v);
    }
    let v = view(&mut rng, &places[2], 12);
    det.insert(10, &v);
    // The query sees place 2 best, place 1 somewhat: a mix.
    let mut q = view(&mut rng, &places[2], 30);
    q.truncate(110);
    q.extend(view(&mut rng, &places[1], 30).into_iter().take(90));
    let single = det.detect(&q, |_| false);
    let group = |k: u64| -> Vec<u64> {
        if k < 3 {
            (0..3).filter(|&j| j != k).collect()
        } else {
            Vec::new()
        }
    };
    let nb = Neighbourhood {
        covisible: &group,
        floor: &[],
    };
    let grouped = det.detect_in(&q, |_| false, &nb);
    assert_eq!(single.candidates[0].image, 10, "{:?}", single.candidates);
    // Three views of place 1 together outweigh the single view of place 2.
    assert!(grouped.candidates[0].image < 3, "{:?}", grouped.candidates);
    // A floor above every stored score leaves no candidate.
    let floor_img = 20;
    det.insert(floor_img, &q);
    let nb = Neighbourhood {
        covisible: &group,
        floor: &[floor_img],
    };
    assert!(
        det.detect_in(&q, |i| i == floor_img, &nb)
            .candidates
            .is_empty()
    );
}
