//! Loop closing end to end on the synthetic sequences: a real loop is closed and corrects the
//! drift; perceptual aliasing never leaves a wrong closure standing.

use homing::atlas::{Atlas, AtlasCamera};
use homing::system::{RunOptions, run};

use crate::common;

fn ate(s: &homing::outputs::Summary) -> f64 {
    s.evaluation.as_ref().unwrap()["ate"]["stats"]["rmse"]
        .as_f64()
        .unwrap()
}

#[test]
fn loop_is_closed_and_corrects_the_drift() {
    let tmp = tempfile::tempdir().unwrap();
    let seq = common::small("loop");
    let atlas = tmp.path().join("atlas.bin");
    let with = run(&RunOptions {
        sequence: seq.clone(),
        out: tmp.path().join("lc"),
        eval: true,
        save_map: Some(atlas.clone()),
        ..Default::default()
    })
    .unwrap();
    let without = run(&RunOptions {
        sequence: seq.clone(),
        out: tmp.path().join("nolc"),
        eval: true,
        no_loop_closing: true,
        ..Default::default()
    })
    .unwrap();
    let ev = with.evaluation.as_ref().unwrap();
    let closures = &ev["closures"];
    assert!(with.pools >= 1, "no closure pool accepted: {closures}");
    assert_eq!(with.pools_rolled_back, 0, "{closures}");
    assert!(closures["accepted"].as_u64().unwrap() >= 3, "{closures}");
    assert_eq!(
        closures["accepted_wrong"].as_u64().unwrap(),
        0,
        "{closures}"
    );
    assert_eq!(with.maps, 1);
    assert_eq!(ev["coverage"].as_f64().unwrap(), 1.0);
    let (a, b) = (ate(&with), ate(&without));
    assert!(a <= b / 3.0, "ATE {a} m with loop closing, {b} m without");
    // The loop's states: Mapping until the loop pool, Localized on it.
    let states = std::fs::read_to_string(tmp.path().join("lc/states.csv")).unwrap();
    assert!(
        states
            .lines()
            .any(|l| l.contains(",Localized,Mapping,able_to_localize,")),
        "no Mapping -> Localized transition"
    );
    // The saved atlas loads back, with consistent links.
    let camera = AtlasCamera::from(&with.camera);
    let loaded = Atlas::load(&atlas, &camera, false).unwrap();
    assert_eq!(loaded.maps.len(), 1);
    assert_eq!(loaded.n_keyframes(), with.keyframes);
}

#[test]
fn aliasing_leaves_no_wrong_closure_standing() {
    let s = common::run_small("aliasing", Default::default()).summary;
    let c = &s.evaluation.as_ref().unwrap()["closures"];
    // Room B looks exactly like room A: the detector does propose it...
    assert!(c["candidates_wrong"].as_u64().unwrap() >= 1, "{c}");
    // ... and every such candidate is rejected, never pooled, or rolled back.
    assert_eq!(c["accepted_wrong"].as_u64().unwrap(), 0, "{c}");
    // A rollback costs no frame its pose: the pool's own frame was tracked before the pool
    // was applied, and the recovery's frame is re-tracked by Idle (2 rollbacks here; before,
    // frames 470, 471, 548 and 549 had none).
    assert!(s.pools_rolled_back >= 1);
    assert_eq!(s.frames_with_pose, s.frames, "frames lost to the recovery");
    assert_eq!(s.maps, 1);
}

/// Bounded map (#6): on `revisit` (five laps of the same circle) the camera is back in mapped
/// space after the first lap, so Localized holds and keyframes stop growing with the
/// trajectory: at the end at most 1.2 × the keyframes the map had when the first lap closed.
#[test]
fn revisiting_keeps_the_map_bounded() {
    let tmp = tempfile::tempdir().unwrap();
    let seq = common::small("revisit");
    let out = tmp.path().join("out");
    let s = run(&RunOptions {
        sequence: seq,
        out: out.clone(),
        eval: true,
        ..Default::default()
    })
    .unwrap();
    let states = std::fs::read_to_string(out.join("states.csv")).unwrap();
    // Per-frame rows: frame,timestamp,state,... (transition rows name a `from` state).
    let rows: Vec<Vec<&str>> = states
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect())
        .collect();
    let first_localized = rows
        .iter()
        .find(|r| r[2] == "Localized")
        .expect("never Localized on revisit");
    let t_closed: f64 = first_localized[1].parse().unwrap();
    let kf_times: Vec<f64> = std::fs::read_to_string(out.join("keyframes.txt"))
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split_whitespace().next().unwrap().parse().unwrap())
        .collect();
    let after_first_lap = kf_times.iter().filter(|&&t| t <= t_closed).count();
    assert!(after_first_lap >= 5, "{after_first_lap} keyframes in lap 1");
    assert_eq!(kf_times.len(), s.keyframes);
    assert!(
        s.keyframes as f64 <= 1.2 * after_first_lap as f64,
        "{} keyframes at the end, {after_first_lap} when lap 1 closed",
        s.keyframes
    );
    // Most of laps 2-5 is spent Localized, and the map stays one consistent map.
    let frames: Vec<&Vec<&str>> = rows
        .iter()
        .filter(|r| r.len() > 3 && r[3].is_empty())
        .collect();
    let later: Vec<_> = frames
        .iter()
        .filter(|r| r[1].parse::<f64>().unwrap() > t_closed)
        .collect();
    let localized = later.iter().filter(|r| r[2] == "Localized").count();
    assert!(
        localized as f64 >= 0.8 * later.len() as f64,
        "Localized on {localized} of {} frames after lap 1",
        later.len()
    );
    assert_eq!(s.maps, 1);
    let ev = s.evaluation.as_ref().unwrap();
    assert_eq!(ev["closures"]["accepted_wrong"].as_u64().unwrap(), 0);
    assert!(ate(&s) < 0.06, "ATE {} m", ate(&s));
}

/// A kidnapping just before the first lap of `revisit` closes (3 s dropped from 8.7 s): the
/// new map merges into the first mid-lap, which leaves the first lap's loop open. Localized
/// must not hold on that map's drifted copy of the lap's start: mapping resumes there, the loop
/// detector closes the lap, and the depth check does not blame the (right) merge for the
/// contradiction between the loop's two ends. Before, the lap stayed open: ATE 11 cm.
#[test]
fn a_kidnapping_before_the_loop_closes_leaves_no_open_loop() {
    revisit_ends_in_one_right_map(&["8.733s:11.733s"], 0.05);
}

/// Two 2 s drops in small `revisit` (12.6 and 26.3 s): after the second, the new map's
/// candidate into the place where the camera was lost is pending, and the next frames are
/// checked against it by projection (decision 0026); one of them completes the merge pool, and
/// the maps end as one, right.
#[test]
fn a_pending_merge_at_the_lost_place_is_re_checked_by_projection() {
    let rows = revisit_ends_in_one_right_map(&["12.645s:14.645s", "26.289s:28.289s"], 0.03);
    assert!(
        rows.iter().any(|r| r.kind == "re-check"
            && r.pool.is_some()
            && homing::outputs::is_accepted(&r.verdict)),
        "no re-checked frame in a merge pool: {rows:?}"
    );
}

/// Small `revisit` with frames dropped at `drops`: one map, no pool rolled back, no wrong
/// closure, ATE under `max_ate_m`. Every merge is reported, confirmed or provisional, in
/// summary.json and in its closures.csv rows alike. Returns closures.csv's rows.
fn revisit_ends_in_one_right_map(
    drops: &[&str],
    max_ate_m: f64,
) -> Vec<homing::outputs::ClosureRow> {
    let perturb = homing::io::perturb::PerturbationSpec {
        drops: drops.iter().map(|d| d.parse().unwrap()).collect(),
        ..Default::default()
    };
    let run = common::run_small("revisit", perturb);
    let s = &run.summary;
    assert!(!s.merges.is_empty(), "a drop leaves a map to merge");
    let rows = homing::outputs::read_closures(&run.out.join("closures.csv")).unwrap();
    for m in &s.merges {
        let verdicts: Vec<&str> = rows
            .iter()
            .filter(|r| r.pool == Some(m.pool))
            .map(|r| r.verdict.as_str())
            .collect();
        let expected = match (m.rolled_back, m.confirmed_frame) {
            (true, _) => "rolled-back",
            (false, Some(f)) => {
                assert!(f > m.frame, "confirmed at {f}, merged at {}", m.frame);
                "accepted"
            }
            (false, None) => homing::outputs::ACCEPTED_PROVISIONAL,
        };
        assert!(
            !verdicts.is_empty() && verdicts.iter().all(|v| *v == expected),
            "pool {}: {verdicts:?}, expected {expected}",
            m.pool
        );
    }
    assert_eq!(s.maps, 1);
    assert_eq!(s.pools_rolled_back, 0, "a right merge was rolled back");
    let ev = s.evaluation.as_ref().unwrap();
    assert_eq!(ev["closures"]["accepted_wrong"].as_u64().unwrap(), 0);
    assert!(ate(s) < max_ate_m, "ATE {} m", ate(s));
    rows
}

/// The benchmark's three 5 s drops in small `revisit`. After the first merge, Localized is left
/// as the camera turns off the map (under 70 % of the view covered); a frame whose view the map
/// covers between half and 70 % then recognises the first lap's start and closes the loop
/// (frame 127). When looking for known places was held to the same 70 %, that loop was never
/// found, the next keyframe saw through a third of the drifted map, and two right merges were
/// undone (4 maps, 46 % in the largest, 8.1 cm).
#[test]
fn a_loop_is_recognised_where_the_map_covers_half_the_view() {
    revisit_ends_in_one_right_map(&["7.733s:12.733s", "17.967s:22.967s", "28.2s:33.2s"], 0.03);
}

/// Two 1 s drops in small `desk` (2.8 s and 6.2 s): each time the camera comes back about
/// where it was lost, but the first frames of the new map get too few of the loop detector's
/// tight votes for the lost map's keyframes to be proposed (the view moved on during the
/// drop). The lost place's keyframes are candidates while the new map is young, so the new
/// map is merged back into the one it lost. Measured: 1 map holding 78.8 % of the frames
/// (121 of 151 were delivered), 0.46 cm; without them 2 maps, 56.3 % in the largest.
#[test]
fn a_map_started_after_a_short_drop_is_merged_back_into_the_lost_map() {
    let perturb = homing::io::perturb::PerturbationSpec {
        drops: vec![
            "2.833s:3.833s".parse().unwrap(),
            "6.166s:7.166s".parse().unwrap(),
        ],
        ..Default::default()
    };
    let s = common::run_small("desk", perturb).summary;
    let ev = s.evaluation.as_ref().unwrap();
    assert_eq!(s.maps, 1, "{}", ev["closures"]);
    assert_eq!(ev["closures"]["accepted_wrong"].as_u64().unwrap(), 0);
    let largest = ev["largest_map_coverage"].as_f64().unwrap();
    assert!(largest >= 0.75, "largest map coverage {largest}");
    assert!(ate(&s) < 0.01, "ATE {} m", ate(&s));
}

/// Aliasing after a kidnapping: a 1 s drop as the camera enters room B leaves it in a new map
/// with no odometry to room A, so the pose graph can never catch a wrong merge. Room B looks
/// like room A, and the relocalization into A is proposed and pooled; the merge depth check
/// refuses it (map A's points, seen from the new map's keyframes, lie where those keyframes
/// saw through them).
#[test]
fn aliasing_after_a_kidnapping_is_not_merged() {
    aliasing_merge_refused(&["18.799s:19.799s"]);
}

/// With `loop_closing.lost_place_from_query_depth` (off by default), small `aliasing` after
/// the same 1 s drop: the lost place is the corridor looking into room B, whose far content had
/// no depth there and so no map points, while the new map's first frames, closer, have depth
/// for it; the new map is joined to the lost one at once. Near the end the look-alike loop
/// into room A (11 m and 166° away) is undone, and the merge it crossed stands: it was not
/// what made that loop possible. Without the key the two maps stay apart (largest 48.6 %).
#[test]
fn a_lost_place_seen_from_afar_is_joined_from_the_new_frames_depth() {
    let run = common::run_small_with_config(
        "aliasing",
        homing::io::perturb::PerturbationSpec {
            drops: vec!["18.799s:19.799s".parse().unwrap()],
            ..Default::default()
        },
        Some("[loop_closing]\nlost_place_from_query_depth = true\n"),
    );
    let e = run.summary.evaluation.as_ref().unwrap();
    assert_eq!(e["closures"]["accepted_wrong"].as_u64().unwrap(), 0, "{e}");
    let coverage = e["largest_map_coverage"].as_f64().unwrap();
    assert!(coverage > 0.85, "the maps were not joined: {e}");
    let closures = std::fs::read_to_string(run.out.join("closures.csv")).unwrap();
    assert!(
        closures
            .lines()
            .any(|l| l.contains(",lost-place,") && accepted(l)),
        "not joined through the lost place: {closures}"
    );
}

/// Three 3 s drops in `aliasing` (centred at 9.7, 19.3 and 29 s): the map started after the
/// second one, in room B, relocalizes into the first map, which holds room A and what it saw
/// of the corridor through A's door. The rooms' shapes and textures are the same, so the
/// depth check passes; but the keyframes of room B that look towards its door see the
/// corridor's other end, where the first map's corridor points lie at depths they confirm
/// with other texture: the appearance check refuses the merge (before it: 3 wrong closures,
/// 4.9 m).
#[test]
fn aliasing_after_three_kidnappings_is_told_apart_by_appearance() {
    aliasing_merge_refused(&["8.15s:11.15s", "17.799s:20.799s", "27.449s:30.449s"]);
}

/// `mapping.triangulate_points` (off by default): with points triangulated where the sensor
/// has no depth, the local BA of `aliasing`'s fast turns no longer bends consecutive
/// keyframes (unperturbed ATE 24.9 → 3.7 cm, measured 2026-11-29).
#[test]
fn rgbd_points_triangulated_beyond_the_depth_range_hold_fast_turns() {
    let run = common::run_small_with_config(
        "aliasing",
        homing::io::perturb::PerturbationSpec::default(),
        Some("[mapping]\ntriangulate_points = true\n"),
    );
    let e = run.summary.evaluation.as_ref().unwrap();
    assert_eq!(e["closures"]["accepted_wrong"].as_u64().unwrap(), 0, "{e}");
    let ate = e["ate"]["stats"]["rmse"].as_f64().unwrap();
    assert!(ate < 0.10, "ATE {ate} m: {e}");
}

/// Small `aliasing` with frames dropped at `drops`: asserts that no wrong closure stands and
/// that a look-alike merge was proposed and refused by the merge depth check; returns
/// closures.csv.
fn aliasing_merge_refused(drops: &[&str]) -> String {
    let run = common::run_small(
        "aliasing",
        homing::io::perturb::PerturbationSpec {
            drops: drops.iter().map(|d| d.parse().unwrap()).collect(),
            ..Default::default()
        },
    );
    let c = &run.summary.evaluation.as_ref().unwrap()["closures"];
    assert_eq!(c["accepted_wrong"].as_u64().unwrap(), 0, "{c}");
    let closures = std::fs::read_to_string(run.out.join("closures.csv")).unwrap();
    assert!(
        closures.contains("rejected:map-contradiction"),
        "the look-alike merge was not proposed and refused: {closures}"
    );
    closures
}

/// Whether a closures.csv line was accepted: confirmed or, for a merge nothing confirmed
/// later, provisional (decision 0023).
fn accepted(line: &str) -> bool {
    line.contains(",accepted,")
        || line.contains(&format!(",{},", homing::outputs::ACCEPTED_PROVISIONAL))
}

/// Three 1 s drops in `aliasing` (9.2, 18.8, 28.4 s): the map started after the third one, in
/// room B, turns on the spot where the map before it was lost, and is joined to it through the
/// lost place (the keyframes taken there, whichever way they look). Room B's end looks exactly
/// like room A's start, and that look-alike merge is proposed at the end; the joined map's
/// keyframes see through room A's points under its alignment and refuse it. Before the lost
/// place was searched by position: the third map alone was merged into room A (3 wrong
/// closures, 5.3 m).
#[test]
fn aliasing_after_three_drops_is_not_merged() {
    let closures = aliasing_merge_refused(&["9.15s:10.15s", "18.799s:19.799s", "28.449s:29.449s"]);
    assert!(
        closures
            .lines()
            .any(|l| l.contains(",lost-place,") && accepted(l)),
        "no merge through the lost place: {closures}"
    );
}

/// Small `scenario` with false frames of `kind` at rate `p` (seed 1).
fn with_false_frames(
    scenario: &str,
    kind: homing::io::perturb::FaultKind,
    p: f64,
) -> homing::outputs::Summary {
    with_false_frames_and_config(scenario, kind, p, None)
}

/// [`with_false_frames`] with `config` (TOML text) as the run's `--config`.
fn with_false_frames_and_config(
    scenario: &str,
    kind: homing::io::perturb::FaultKind,
    p: f64,
    config: Option<&str>,
) -> homing::outputs::Summary {
    use homing::io::perturb::{FaultRate, PerturbationSpec};
    let spec = PerturbationSpec {
        fault_rates: vec![FaultRate { kind, p }],
        seed: 1,
        ..Default::default()
    };
    common::run_small_with_config(scenario, spec, config).summary
}

/// Asserts no wrong closure was accepted and the largest map holds at least `min_largest` of
/// the frames.
fn assert_no_wrong_closure(s: &homing::outputs::Summary, min_largest: f64) {
    let ev = s.evaluation.as_ref().unwrap();
    let wrong = ev["closures"]["accepted_wrong"].as_u64().unwrap();
    assert_eq!(wrong, 0, "wrong closures");
    let largest = ev["largest_map_coverage"].as_f64().unwrap();
    assert!(largest >= min_largest, "largest map coverage {largest}");
}

/// Isolated false frames (5 % noise images) cost only themselves: the tracker keeps its
/// motion model across the missing frame, so the next real frame is tracked in the same map
/// instead of starting a new one (which, in this look-alike world, has nothing to merge
/// back with but room A). Two false frames in a row (frames 462 and 463, in room B): Idle
/// cannot re-track the second and starts a map from it, which the next real frame loses at
/// once and discards; tracking then resumes in the map they interrupted. Measured: 1 map,
/// 94 % of the frames, none wrong (0.62 and 6 wrong closures when a third map began there,
/// was refused by the interrupted map's depth check and merged into room A; 0.32 when each
/// false frame reset the motion model).
#[test]
fn aliasing_with_isolated_false_frames_keeps_one_large_map() {
    let s = with_false_frames("aliasing", homing::io::perturb::FaultKind::Noise, 0.05);
    assert_no_wrong_closure(&s, 0.9);
}

/// A false frame in a turn (1 % black frames, seed 1: frame 537, camera turning in room B)
/// leaves the re-tracked frame seeing little of the map. Entering Core, that frame is mapped
/// (a keyframe), so the next frame is tracked in the same map. Before, the next frame found
/// too few points, a new map began, and three frames later it merged into the look-alike
/// room A (3 wrong closures, ATE 3.0 m).
#[test]
fn a_false_frame_in_a_turn_keeps_tracking_in_the_same_map() {
    let s = with_false_frames("aliasing", homing::io::perturb::FaultKind::Black, 0.01);
    assert_no_wrong_closure(&s, 0.95);
    assert_eq!(s.maps, 1);
}

/// With 5 % black frames (seed 1), a false frame in the turn at the end of room B comes
/// right after one the motion model tracked from few points: across the two intervals the last
/// frame's points mostly leave the view. The prediction with the local map's points keeps the
/// camera in its map (measured: 1 map, 94 % of the frames, no wrong closure; with the last
/// frame's points only, a new map began and merged into room A: 6 wrong closures).
#[test]
fn a_false_frame_after_a_weakly_tracked_one_keeps_the_map() {
    let s = with_false_frames("aliasing", homing::io::perturb::FaultKind::Black, 0.05);
    assert_no_wrong_closure(&s, 0.9);
}

/// Two false frames in a row on the slow (7.5 Hz) `revisit` (5 % noise images, seed 1:
/// frames 23 and 24): Idle starts a map from the second, which the next real frame (25)
/// loses at once; the map is discarded and tracking resumes in the interrupted map — and that
/// real frame is tracked there at once, since the frame after it is already past the
/// re-acquisition gap (0.53 s since the last tracked frame). Before, a new map began at frame
/// 26, its merge left the pose graph open across the false frames, and the depth check later
/// blamed right closures on the drift between the two ends: 4 maps, 32 % of the frames in the
/// largest (measured after: 1 map, 94 %, ATE 3.1 cm).
#[test]
fn two_false_frames_on_a_slow_sequence_keep_one_map() {
    let s = with_false_frames("revisit", homing::io::perturb::FaultKind::Noise, 0.05);
    assert_no_wrong_closure(&s, 0.9);
    assert_eq!(s.maps, 1);
    assert_eq!(s.pools_rolled_back, 0, "a right closure was rolled back");
}

/// When a closure makes the map inconsistent and the optimiser blames an older pool, the new
/// pool is tried first: the map was consistent until it came. On `revisit` with 5 % black
/// frames (seed 1) and `controller.known_view_angle_deg = 15`, a loop closed right after a
/// keyframe re-acquired past a black frame (pool 14, frame 291) had pool 3 blamed (χ²/dof 7.6).
/// Undoing pool 3 undid the eleven right pools after it and discarded their keyframes: 39 % of
/// the frames posed, ATE 4.1 cm. Undoing pool 14 alone left the map consistent (χ²/dof 1.5):
/// measured 94 % posed, ATE 2.1 cm, one pool rolled back.
#[test]
fn an_inconsistent_closure_is_undone_before_the_older_pools_it_contradicts() {
    let s = with_false_frames_and_config(
        "revisit",
        homing::io::perturb::FaultKind::Black,
        0.05,
        Some("[controller]\nknown_view_angle_deg = 15.0\n"),
    );
    assert_no_wrong_closure(&s, 0.9);
    assert!(
        s.pools_rolled_back <= 1,
        "{} pools rolled back: right pools were undone with the blamed one",
        s.pools_rolled_back
    );
}

/// `mapping.final_depth_edges` with `final_depth_edges_local_planes`: Final's BA also holds
/// the geometric edges that register the depth of keyframes which see the same corridor
/// walls from its two legs (no key point is shared: one leg looks out, the other back),
/// including pairs registered on local planes alone. Measured on this sequence: ATE 3.46 →
/// 1.91 cm (2.85 with the wide planes only, the default). The edges go through the whole
/// pipeline (the depth grid kept per keyframe, the search, the registration, the BA's pose
/// edges); what is posed does not change.
#[test]
fn depth_edges_join_the_corridor_legs_of_the_loop() {
    let (with, without) =
        loop_with_and_without_depth_edges(&[], "final_depth_edges_local_planes = true");
    let (a, b) = (ate(&with), ate(&without));
    assert!(a <= 0.7 * b, "ATE {a} m with depth edges, {b} m without");
}

/// The benchmark's one 2 s drop in small `loop` (23.5–25.5 s, in the turn at the corridor's
/// end): the second leg's map is merged back only in the room, and the two legs are 30–40 cm
/// and 4° apart at the corridor's far end. Local planes alone register from there into wrong
/// minima (the edges were 20–70 cm off the truth) and the inlier gate let none through; the
/// walls, floor and ceiling paired join them. With the defaults: 12.0 cm without the edges,
/// 2.77 cm with them.
#[test]
fn depth_edges_join_the_legs_after_a_two_second_drop() {
    let (with, without) = loop_with_and_without_depth_edges(&["23.466s:25.466s"], "");
    let (a, b) = (ate(&with), ate(&without));
    assert!(a <= 0.4 * b, "ATE {a} m with depth edges, {b} m without");
}

/// Small `loop` with frames dropped at `drops`, run with the depth edges (the defaults plus
/// the `[mapping]` lines `with`) and without them; the edges must not change what is posed.
fn loop_with_and_without_depth_edges(
    drops: &[&str],
    with: &str,
) -> (homing::outputs::Summary, homing::outputs::Summary) {
    let tmp = tempfile::tempdir().unwrap();
    let seq = common::small("loop");
    let run_with = |name: &str, mapping: &str| {
        let config = tmp.path().join(format!("{name}.toml"));
        std::fs::write(&config, format!("[mapping]\n{mapping}\n")).unwrap();
        run(&RunOptions {
            sequence: seq.clone(),
            out: tmp.path().join(name),
            config: Some(config),
            perturb: homing::io::perturb::PerturbationSpec {
                drops: drops.iter().map(|d| d.parse().unwrap()).collect(),
                ..Default::default()
            },
            eval: true,
            ..Default::default()
        })
        .unwrap()
    };
    let with = run_with("with", with);
    let without = run_with("without", "final_depth_edges = false");
    assert_eq!(
        (with.maps, with.frames_with_pose),
        (without.maps, without.frames_with_pose)
    );
    (with, without)
}

/// The shipped real-data preset's text.
fn real_handheld_preset() -> String {
    let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/real-handheld.toml");
    std::fs::read_to_string(p).unwrap()
}

/// The real-data preset (`configs/real-handheld.toml`: bag-of-words place recognition, the
/// validator from 15 correspondences, the drift gate) end to end on small `loop`: the vocabulary
/// proposes the corridor's start when the camera comes back (hundreds of candidates, where the
/// HBST proposes a handful), and what is accepted is right. Measured: 3 accepted, 0 wrong,
/// 1 map, 2.8 cm.
#[test]
fn the_real_handheld_preset_closes_the_loop_by_bag_of_words() {
    let preset = real_handheld_preset();
    let r = common::run_small_with_config("loop", Default::default(), Some(&preset));
    let c = &r.summary.evaluation.as_ref().unwrap()["closures"];
    assert!(c["candidates"].as_u64().unwrap() >= 100, "{c}");
    assert!(c["accepted"].as_u64().unwrap() >= 1, "{c}");
    assert_eq!(c["accepted_wrong"].as_u64().unwrap(), 0, "{c}");
    assert_eq!(r.summary.maps, 1);
}

/// The drift gate of the real-data preset on small `aliasing`: room B's look-alike loops to
/// room A would move the camera metres after a few metres of path, beyond 3 σ of the
/// odometry's drift model; they are refused before they are pooled (measured: 49), and no
/// wrong closure stands. The right loop pooled at 5 s (the camera turned back to its start
/// view) corrected the map by less than the depth checks can see, so room B's own drift is not
/// blamed on it 30 s later: one map, every frame posed (before: that loop was undone with the
/// 39 keyframes made since, 2 maps, 99 of 580 frames posed).
#[test]
fn the_drift_gate_refuses_look_alike_loops_the_odometry_could_not_have_drifted() {
    let preset = real_handheld_preset();
    let r = common::run_small_with_config("aliasing", Default::default(), Some(&preset));
    let closures = std::fs::read_to_string(r.out.join("closures.csv")).unwrap();
    let gated = closures
        .lines()
        .filter(|l| l.contains("rejected:implausible-drift"))
        .count();
    assert!(gated >= 10, "{gated} loops refused by the drift gate");
    let c = &r.summary.evaluation.as_ref().unwrap()["closures"];
    assert_eq!(c["accepted_wrong"].as_u64().unwrap(), 0, "{c}");
    assert_eq!(r.summary.maps, 1, "{c}");
    assert_eq!(r.summary.frames_with_pose, r.summary.frames);
}
