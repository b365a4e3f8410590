//! The paper's case study (Table II) end to end, under our state machine: both sessions of
//! the synthetic robot vacuum (rooms, a corridor whose doors B and C look alike, a dark
//! stretch, a kidnapping, a second session on the saved atlas), the run's state timeline
//! compared with the paper's column step by step, and the map it leaves behind.
//!
//! Rendered at 320×240 (every second frame, 15 Hz) so that the suite stays fast; the
//! full-size version is `homing bench case-study`.

use homing::bench::case_study::{self, Options};
use homing::config::ControllerKind;

mod common;

/// Steps of Table II that our machine does not reproduce yet, with the reason (issue #6 and
/// the README's case-study section): every other step must match.
const KNOWN_GAPS: &[(u32, &str)] = &[
    (
        2,
        "the own map's known places are not recognised from the offset viewpoints of the way back",
    ),
    (
        6,
        "at 320x240 the wrong relocalization at door C is made but the tracker loses it within \
         the step (Localized -> Idle)",
    ),
    (
        7,
        "so the camera never maps Room 2 into the wrong map, and neither Localized's expectation \
         check nor Mapping's keyframe depth check sees the closet contradicted (at 640x480 the \
         bench reaches CorruptedMap here)",
    ),
    (8, "(follows from 7: no recovery through Idle)"),
    (
        9,
        "the corridor driven the opposite way is not recognised, so Room 1 is not re-entered Localized",
    ),
    (
        12,
        "at 320x240 Room 2 is recognised through door D only late in the step (at 640x480 the \
         bench matches it)",
    ),
];

#[test]
fn ours_follows_table_ii_outside_the_known_gaps() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    common::synth_small("case-study", &data, Some(2));
    let out = tmp.path().join("out");
    let opts = Options {
        controllers: vec![ControllerKind::Ours],
        ..Default::default()
    };
    let (cs, md) = case_study::case_study(&data, &out, &opts).unwrap();
    println!("{md}");
    let ours = &cs.controllers[0];
    assert_eq!(ours.steps_total, 15, "{md}");
    for s in &ours.steps {
        if KNOWN_GAPS.iter().any(|(k, _)| *k == s.step) {
            continue;
        }
        assert!(
            s.matched,
            "step {} ({}): expected {:?}, observed {:?} (dominant {})\n{md}",
            s.step, s.name, s.expected, s.observed, s.dominant
        );
    }
    // The kidnapping started a new map (step 10): the atlas holds more than one.
    assert!(ours.maps >= 2, "{md}");
    // The dark stretch keeps the machine in Idle (the timeline rule only asks that Idle
    // occurs, since after a kidnapping it lasts one frame).
    let dark = ours.steps.iter().find(|s| s.step == 4).unwrap();
    assert_eq!(dark.dominant, "Idle", "{md}");
    // Multi-session (step 14): session 2 is Localized in the loaded atlas, not before the
    // camera looks from where a session-1 keyframe did. The 30-frame bound is
    // measured at 640x480 by `homing bench case-study` (0 frames there); at 320x240 and 15 Hz
    // the descriptors are coarser and it takes longer.
    let view = ours
        .session2_known_view_frame
        .expect("session 2 sees Room 2");
    let localized = ours
        .session2_localized_frame
        .unwrap_or_else(|| panic!("session 2 never Localized\n{md}"));
    assert!(
        localized >= view,
        "Localized at frame {localized}, before any known view (frame {view})\n{md}"
    );
}
