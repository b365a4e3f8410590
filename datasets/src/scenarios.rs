//! The scenario catalogue: scenes, camera scripts and the expected SLAM state per step.
//!
//! World frame of every scenario: x east, y north, z up (metres), floor at z = 0.

use crate::motion::{HandScript, Jitter, Path, RobotScript};
use crate::scene::{Door, RoomLook, Scene, Side};
use crate::texture::mix;

/// One step of a scenario: a stretch of frames with an event and the states a correct
/// controller should show during it.
#[derive(Debug, Clone)]
pub struct StepDef {
    pub step: usize,
    pub name: String,
    pub event: String,
    pub expected: Vec<String>,
    /// Script time at which the step begins; it lasts until the next step begins.
    pub t_start: f64,
}

/// One recording (one output folder).
#[derive(Debug, Clone)]
pub struct Session {
    /// Sub-folder name (`None`: written directly into the output folder).
    pub dir: Option<String>,
    pub name: String,
    /// Continuous pieces of motion; a gap between two legs is a kidnapping (no frames).
    pub legs: Vec<Path>,
    pub steps: Vec<StepDef>,
    /// Script-time intervals with the lights off.
    pub dark: Vec<(f64, f64)>,
    /// Time stamp of script time 0 (seconds, like TUM's Unix stamps).
    pub stamp0: f64,
}

#[derive(Debug, Clone)]
pub struct Scenario {
    pub name: String,
    pub description: String,
    pub motion: String,
    pub scene: Scene,
    pub sessions: Vec<Session>,
    /// With `--small`, keep every n-th frame (fps is divided accordingly).
    pub small_stride: usize,
}

/// CLI names of all scenarios.
pub const NAMES: [&str; 8] = [
    "desk",
    "loop",
    "aliasing",
    "aliasing-return",
    "revisit",
    "case-study",
    "turn-in-place",
    "turn-in-place-reference",
];

/// Builds a scenario by CLI name.
pub fn build(name: &str, seed: u64) -> Option<Scenario> {
    match name {
        "desk" => Some(desk(seed)),
        "loop" => Some(loop_scenario(seed)),
        "aliasing" => Some(aliasing(seed, false)),
        "aliasing-return" => Some(aliasing(seed, true)),
        "revisit" => Some(revisit(seed)),
        "case-study" => Some(case_study(seed)),
        "turn-in-place" => Some(turn_in_place(seed, true)),
        "turn-in-place-reference" => Some(turn_in_place(seed, false)),
        _ => None,
    }
}

fn s(x: &str) -> String {
    x.to_string()
}

fn steps(
    marks: &[(String, f64)],
    defs: &[(&str, &str, &[&str])],
    first_step: usize,
) -> Vec<StepDef> {
    marks
        .iter()
        .zip(defs)
        .enumerate()
        .map(|(k, ((_, t), (name, event, exp)))| StepDef {
            step: first_step + k,
            name: s(name),
            event: s(event),
            expected: exp.iter().map(|e| s(e)).collect(),
            t_start: *t,
        })
        .collect()
}

const STAMP0: f64 = 1_700_000_000.0;
const HEIGHT: f64 = 2.6;

/// A furnished room used by `desk`, `revisit` and (as two copies) `aliasing`.
fn furnished_room(sc: &mut Scene, seed: u64, min: [f64; 2], max: [f64; 2], doors: &[Door]) {
    sc.add_room(
        min,
        max,
        HEIGHT,
        doors,
        RoomLook::from_seed(mix(seed ^ 0x100)),
    );
    let (x0, y0, x1, y1) = (min[0], min[1], max[0], max[1]);
    // Desk against the north wall, a shelf on the west wall, a cabinet in the south-east.
    sc.add_box(
        [x0 + 1.2, y1 - 0.75, 0.0],
        [x0 + 3.0, y1, 0.75],
        mix(seed ^ 0x201),
    );
    sc.add_box(
        [x0 + 1.6, y1 - 0.35, 0.75],
        [x0 + 2.4, y1 - 0.05, 1.1],
        mix(seed ^ 0x202),
    );
    sc.add_box(
        [x0, y0 + 1.0, 0.0],
        [x0 + 0.4, y0 + 2.4, 1.9],
        mix(seed ^ 0x203),
    );
    sc.add_box([x1 - 0.5, y0, 0.0], [x1, y0 + 1.2, 1.0], mix(seed ^ 0x204));
    sc.add_poster(
        "room/north",
        Side::North,
        y1,
        [x0 + 3.3, 1.0],
        [0.7, 0.9],
        mix(seed ^ 0x301),
    );
    sc.add_poster(
        "room/west",
        Side::West,
        x0,
        [y0 + 2.7, 0.9],
        [0.8, 1.0],
        mix(seed ^ 0x302),
    );
    sc.add_poster(
        "room/south",
        Side::South,
        y0,
        [x0 + 1.5, 1.0],
        [1.0, 0.7],
        mix(seed ^ 0x303),
    );
    // The east poster moves aside when a door takes its place (it would float in the doorway).
    let mut east = y0 + 1.6;
    for d in doors.iter().filter(|d| d.side == Side::East) {
        if (east - d.center).abs() < 0.3 + d.width / 2.0 + 0.1 {
            let beyond = d.center + d.width / 2.0 + 0.5;
            east = if beyond + 0.4 < y1 {
                beyond
            } else {
                d.center - d.width / 2.0 - 0.5
            };
        }
    }
    sc.add_poster(
        "room/east",
        Side::East,
        x1,
        [east, 1.1],
        [0.6, 0.8],
        mix(seed ^ 0x304),
    );
}

/// `desk`: one textured room, slow hand-held motion, ~300 frames.
pub fn desk(seed: u64) -> Scenario {
    let mut sc = Scene::default();
    furnished_room(&mut sc, seed, [0.0, 0.0], [5.0, 4.0], &[]);
    let mut h = HandScript::default();
    h.key(0.0, [2.5, 1.7, 1.45], [2.4, 4.0, 0.9])
        .key(2.5, [2.1, 1.9, 1.5], [1.4, 4.0, 1.0])
        .key(5.0, [1.9, 1.9, 1.5], [0.0, 2.4, 1.1])
        .key(7.5, [2.3, 1.6, 1.4], [0.4, 3.4, 1.0])
        .key(10.0, [2.8, 1.8, 1.35], [3.6, 4.0, 0.9]);
    h.mark("start", 0.0).mark("move", 1.0);
    let defs: &[(&str, &str, &[&str])] = &[
        ("start", "camera turned on, nearly still", &["Init", "Idle"]),
        (
            "explore",
            "slow hand-held motion over the desk and walls",
            &["Mapping"],
        ),
    ];
    let session = Session {
        dir: None,
        name: s("desk"),
        legs: vec![h.path(Jitter::new(mix(seed ^ 0x900), 0.004, 0.004, false))],
        steps: steps(&h.marks, defs, 0),
        dark: vec![],
        stamp0: STAMP0,
    };
    Scenario {
        name: s("desk"),
        description: s(
            "One furnished, textured room; slow hand-held motion 0.8-2.5 m from the surfaces.",
        ),
        motion: s("hand-held"),
        scene: sc,
        sessions: vec![session],
        small_stride: 2,
    }
}

/// A straight corridor along x between `x0` and `x1`, centred on y = `yc`, 2 m wide.
fn corridor(sc: &mut Scene, seed: u64, x0: f64, x1: f64, yc: f64, doors: &[Door]) {
    sc.add_room(
        [x0, yc - 1.0],
        [x1, yc + 1.0],
        HEIGHT,
        doors,
        RoomLook::from_seed(seed),
    );
}

/// `loop`: room, corridor, back into the room to the start pose.
pub fn loop_scenario(seed: u64) -> Scenario {
    let mut sc = Scene::default();
    let door = |side, center| Door {
        side,
        center,
        width: 1.0,
        height: 2.1,
    };
    furnished_room(
        &mut sc,
        seed,
        [0.0, 0.0],
        [5.0, 4.0],
        &[door(Side::East, 2.0)],
    );
    corridor(
        &mut sc,
        mix(seed ^ 0x400),
        5.1,
        14.0,
        2.0,
        &[door(Side::West, 2.0)],
    );
    sc.add_door_frame(0, 5.0, 5.1, 2.0, 1.0, 2.1, mix(seed ^ 0x401));
    // Two cabinets in the corridor: through the doorway the corridor's end wall is beyond
    // the depth sensor's range and its side walls are hidden, so without something near an
    // RGB-D camera would see no depth at all there (this scenario is about the loop, not
    // about a sensor outage; the case study has those).
    sc.add_box([7.5, 1.0, 0.0], [8.3, 1.5, 1.6], mix(seed ^ 0x402));
    sc.add_box([9.5, 2.5, 0.0], [10.3, 3.0, 1.6], mix(seed ^ 0x403));
    for (k, x) in [6.5, 9.0, 11.5].iter().enumerate() {
        sc.add_poster(
            &format!("corridor/n{k}"),
            Side::North,
            3.0,
            [*x, 0.9],
            [0.8, 0.9],
            mix(seed ^ (0x410 + k as u64)),
        );
        sc.add_poster(
            &format!("corridor/s{k}"),
            Side::South,
            1.0,
            [*x + 1.0, 0.9],
            [0.7, 0.8],
            mix(seed ^ (0x420 + k as u64)),
        );
    }
    let mut r = RobotScript::new(2.0, 1.8, 150.0, 0.0, 1.35, -8.0);
    r.speed = 0.9;
    r.turn_rate = 75f64.to_radians();
    r.mark("start").wait(1.0).mark("explore");
    r.turn_to(90.0).turn_to(-20.0).go(3.5, 2.0).mark("corridor");
    r.go(12.0, 2.0).turn_to(180.0).mark("back");
    r.go(5.6, 2.0).mark("return");
    // Back at the start it looks around the room: a loop is closed once several keyframes
    // agree on it (the validator's pool), as in ORB-SLAM.
    r.go(2.0, 1.8).turn_to(150.0).look_around(60.0).wait(1.0);
    let defs: &[(&str, &str, &[&str])] = &[
        ("start", "camera turned on", &["Init", "Idle"]),
        ("explore room", "explores the room", &["Mapping"]),
        ("corridor", "walks down the corridor", &["Mapping"]),
        (
            "back",
            "turns round, walks back up the corridor (seen from the other side)",
            &["Mapping", "Localized"],
        ),
        (
            "loop closure",
            "re-enters the room, returns to the start pose and looks around",
            &["Localized"],
        ),
    ];
    let session = Session {
        dir: None,
        name: s("loop"),
        legs: vec![r.path(Jitter::new(mix(seed ^ 0x901), 0.005, 0.005, false))],
        steps: steps(&r.marks, defs, 0),
        dark: vec![],
        stamp0: STAMP0,
    };
    Scenario {
        name: s("loop"),
        description: s("Room -> corridor -> back to the start pose (loop closure)."),
        motion: s("hand-held (walking, 1.35 m)"),
        scene: sc,
        sessions: vec![session],
        small_stride: 2,
    }
}

/// `aliasing`: two identical rooms joined by a corridor (the second is the first rotated by
/// 180 degrees about the corridor's centre, so entering it looks exactly like entering the first).
///
/// With `back` true, `aliasing-return`: after room B the camera walks back out through room
/// B's door and along the corridor towards room A. The corridor is not symmetric (its posters
/// and wall textures differ under the rotation), so a map that merged room B into room A sees
/// the difference there, and a right join with room A's map comes through room A's door. The
/// seed changes textures, furniture and hand-held jitter; room B stays an exact copy of room A.
pub fn aliasing(seed: u64, back: bool) -> Scenario {
    let door = |side, center| Door {
        side,
        center,
        width: 1.0,
        height: 2.1,
    };
    let mut room = Scene::default();
    furnished_room(
        &mut room,
        seed,
        [0.0, 0.0],
        [5.0, 4.0],
        &[door(Side::East, 2.0)],
    );
    room.add_door_frame(0, 5.0, 5.1, 2.0, 1.0, 2.1, mix(seed ^ 0x401));
    let mut sc = room.clone();
    sc.append_rotated180(&room, 7.55, 2.0);
    corridor(
        &mut sc,
        mix(seed ^ 0x400),
        5.1,
        10.0,
        2.0,
        &[door(Side::West, 2.0), door(Side::East, 2.0)],
    );
    sc.add_poster(
        "corridor/n",
        Side::North,
        3.0,
        [6.3, 0.9],
        [1.0, 0.9],
        mix(seed ^ 0x410),
    );
    sc.add_poster(
        "corridor/s",
        Side::South,
        1.0,
        [7.0, 0.9],
        [0.8, 0.8],
        mix(seed ^ 0x411),
    );
    let mut r = RobotScript::new(1.6, 2.0, 30.0, 0.0, 1.35, -8.0);
    r.speed = 0.9;
    r.turn_rate = 75f64.to_radians();
    r.mark("start").wait(1.0).mark("explore A");
    r.turn_to(120.0)
        .turn_to(-60.0)
        .go(3.4, 2.0)
        .mark("corridor");
    r.go(7.55, 2.0).mark("enter B");
    // The same motion as in room A, rotated by 180 degrees.
    r.go(11.7, 2.0)
        .turn_to(-60.0)
        .turn_to(120.0)
        .go(13.5, 2.0)
        .turn_to(210.0)
        .wait(1.0);
    if back {
        // At a brisk walk (1.2 m/s peak): the full-size sequence stays within 1,500 frames.
        r.mark("back");
        r.speed = 1.2;
        r.go(10.6, 2.0).go(6.2, 2.0).wait(0.5);
    }
    let defs: &[(&str, &str, &[&str])] = &[
        ("start", "camera turned on in room A", &["Init", "Idle"]),
        ("explore room A", "looks around room A", &["Mapping"]),
        ("corridor", "walks through the corridor", &["Mapping"]),
        (
            "room B",
            "enters room B, identical to room A: a closure here is wrong",
            &["Mapping"],
        ),
        (
            "back to the corridor",
            "walks back out of room B and along the corridor towards room A: a merge of room B into room A is contradicted here",
            &["Mapping", "Localized"],
        ),
    ];
    let defs = &defs[..if back { 5 } else { 4 }];
    let name = if back { "aliasing-return" } else { "aliasing" };
    let session = Session {
        dir: None,
        name: s(name),
        legs: vec![r.path(Jitter::new(mix(seed ^ 0x902), 0.005, 0.005, false))],
        steps: steps(&r.marks, defs, 0),
        dark: vec![],
        stamp0: STAMP0,
    };
    Scenario {
        name: s(name),
        description: s(if back {
            "Two identical rooms joined by a corridor (perceptual aliasing); the camera walks back out of the second room along the corridor."
        } else {
            "Two identical rooms joined by a corridor (perceptual aliasing)."
        }),
        motion: s("hand-held (walking, 1.35 m)"),
        scene: sc,
        sessions: vec![session],
        small_stride: 2,
    }
}

/// `turn-in-place`: a walk through one furnished room with two full turns on the spot, at 60
/// and 100 °/s, and 2 s standing still. Without depth a turn in place gives no parallax: no
/// point can be triangulated while it lasts (monocular tracking must hold on by rotation).
///
/// With `turns` false, `turn-in-place-reference`: the same walk without the two full turns
/// (same room, waypoints, stand and jitter seed), the reference an ATE with the turns is
/// compared with.
pub fn turn_in_place(seed: u64, turns: bool) -> Scenario {
    let mut sc = Scene::default();
    // The room of `desk`: from anywhere on the path every wall is within the depth sensor's
    // 4 m, so RGB-D runs see the turns with depth while monocular runs have only the images.
    furnished_room(&mut sc, seed, [0.0, 0.0], [5.0, 4.0], &[]);
    let mut r = RobotScript::new(1.5, 1.8, 60.0, 0.0, 1.35, -8.0);
    r.speed = 0.6;
    r.turn_rate = 45f64.to_radians();
    r.mark("start").wait(1.0).mark("walk");
    r.go(2.5, 2.0).turn_to(60.0);
    if turns {
        r.mark("turn at 60");
        r.turn_rate = 60f64.to_radians();
        r.turn_by(360.0);
        r.turn_rate = 45f64.to_radians();
    }
    r.mark("walk on");
    r.go(3.3, 2.4).turn_to(-30.0);
    if turns {
        r.mark("turn at 100");
        r.turn_rate = 100f64.to_radians();
        r.turn_by(-360.0);
        r.turn_rate = 45f64.to_radians();
    }
    r.mark("walk on again");
    r.go(2.6, 1.5).turn_to(150.0).mark("stand still");
    r.wait(2.0).mark("walk to the end");
    r.go(1.7, 2.1).wait(0.5);
    let defs: &[(&str, &str, &[&str])] = &[
        ("start", "camera turned on", &["Init", "Idle"]),
        ("walk", "walks into the room", &["Mapping"]),
        (
            "turn at 60",
            "turns a full circle on the spot, up to 60 °/s",
            &["Mapping", "Localized"],
        ),
        ("walk on", "walks on", &["Mapping", "Localized"]),
        (
            "turn at 100",
            "turns a full circle the other way, up to 100 °/s",
            &["Mapping", "Localized"],
        ),
        ("walk on again", "walks on", &["Mapping", "Localized"]),
        (
            "stand still",
            "stands still for 2 s",
            &["Mapping", "Localized"],
        ),
        (
            "walk to the end",
            "walks on and stops",
            &["Mapping", "Localized"],
        ),
    ];
    let defs: Vec<_> = defs
        .iter()
        .filter(|d| turns || !d.0.starts_with("turn at"))
        .copied()
        .collect();
    let name = if turns {
        "turn-in-place"
    } else {
        "turn-in-place-reference"
    };
    let session = Session {
        dir: None,
        name: s(name),
        legs: vec![r.path(Jitter::new(mix(seed ^ 0x905), 0.005, 0.005, false))],
        steps: steps(&r.marks, &defs, 0),
        dark: vec![],
        stamp0: STAMP0,
    };
    Scenario {
        name: s(name),
        description: s(if turns {
            "One furnished room; a walk with two full turns on the spot (60 and 100 °/s) and 2 s standing still."
        } else {
            "The walk of turn-in-place without its two full turns: the reference for its ATE."
        }),
        motion: s("hand-held (walking, 1.35 m)"),
        scene: sc,
        sessions: vec![session],
        small_stride: 2,
    }
}

/// `revisit`: the same room traversed five times on a circle, looking outwards.
pub fn revisit(seed: u64) -> Scenario {
    let mut sc = Scene::default();
    furnished_room(&mut sc, seed, [0.0, 0.0], [6.0, 5.0], &[]);
    let (cx, cy, rad) = (3.0, 2.5, 0.7);
    let lap = 8.0;
    let mut h = HandScript::default();
    let keys_per_lap = 8;
    let laps = 5;
    h.key(0.0, [cx + rad, cy, 1.4], [6.0, cy + 1.2, 1.0]);
    for k in 0..=(keys_per_lap * laps) {
        let a = std::f64::consts::TAU * k as f64 / keys_per_lap as f64;
        let p = [
            cx + rad * a.cos(),
            cy + rad * a.sin(),
            1.4 + 0.05 * (3.0 * a).sin(),
        ];
        let look = a + 0.6;
        let tgt = [cx + 3.0 * look.cos(), cy + 3.0 * look.sin(), 1.0];
        h.key(1.0 + lap * k as f64 / keys_per_lap as f64, p, tgt);
    }
    h.mark("start", 0.0);
    for l in 0..laps {
        h.mark("lap", 1.0 + lap * l as f64);
    }
    let defs: &[(&str, &str, &[&str])] = &[
        ("start", "camera turned on", &["Init", "Idle"]),
        ("lap 1", "first traversal of the room", &["Mapping"]),
        (
            "lap 2",
            "second traversal: everything is known",
            &["Localized"],
        ),
        ("lap 3", "third traversal", &["Localized"]),
        ("lap 4", "fourth traversal", &["Localized"]),
        (
            "lap 5",
            "fifth traversal (map size must not grow)",
            &["Localized"],
        ),
    ];
    let session = Session {
        dir: None,
        name: s("revisit"),
        legs: vec![h.path(Jitter::new(mix(seed ^ 0x903), 0.004, 0.004, false))],
        steps: steps(&h.marks, defs, 0),
        dark: vec![],
        stamp0: STAMP0,
    };
    Scenario {
        name: s("revisit"),
        description: s("One room traversed five times on the same circle."),
        motion: s("hand-held"),
        scene: sc,
        sessions: vec![session],
        small_stride: 4,
    }
}

/// Corridor piece of the case study: floor, ceiling, both walls and optionally a door in the
/// north wall at local x = 2; textures anchored at the piece's west end, so two pieces built
/// with the same `look` are identical.
fn corridor_piece(
    sc: &mut Scene,
    x0: f64,
    x1: f64,
    look: u64,
    north_door: Option<f64>,
    south_door: Option<f64>,
) {
    use crate::texture::Texture;
    let l = RoomLook::from_seed(look);
    let (ys, yn) = (4.1, 6.1);
    let fl = sc.add_texture(Texture::floor(l.floor));
    let ce = sc.add_texture(Texture::ceiling(l.ceiling));
    sc.add_quad(2, 0.0, 1.0, [x0, ys], [x1, yn], fl, [x0, ys]);
    sc.add_quad(2, HEIGHT, -1.0, [x0, ys], [x1, yn], ce, [x0, ys]);
    let ts = sc.add_texture(Texture::wall(l.walls[0]));
    let tn = sc.add_texture(Texture::wall(l.walls[1]));
    let nd: Vec<_> = north_door.iter().map(|c| (*c, 1.0, 2.1)).collect();
    let sd: Vec<_> = south_door.iter().map(|c| (*c, 1.0, 2.1)).collect();
    sc.add_wall(1, yn, -1.0, [x0, x1], HEIGHT, &nd, tn, [x0, 0.0]);
    sc.add_wall(1, ys, 1.0, [x0, x1], HEIGHT, &sd, ts, [x0, 0.0]);
}

/// The paper's case study (section VI-A, Fig. 9, Table II): a robot vacuum in Room 1, a
/// corridor with doors A, B, C (B and C with identical surroundings), a dark stretch, Room 2
/// behind C, Room 3 next to Room 2 reached only by kidnapping; session 2 in a corner of Room 2.
///
/// Layout (x east, y north, metres): Room 1 `[0,5]x[0,4]` with door A at x = 2.5 in its north
/// wall; corridor [-0.5,17.5]x[4.1,6.1]; identical corridor pieces [4.5,8.5] (door B at 6.5)
/// and [10.5,14.5] (door C at 12.5); a closet behind B, [4.5,8.5]x[6.2,8.7], whose far wall,
/// floor and ceiling look like Room 2's [10.5,14.5]x[6.2,10.2] (Room 2 differs in its side
/// walls and furniture, and its far wall is 1.5 m further: the robot maps the closet from
/// door B, and the depth sensor sees through the closet's predicted far wall once it enters
/// Room 2 believing it is behind B); Room 3 [14.6,18.6]x[6.2,10.2] with door D to Room 2 at
/// y = 8.5. The corridor lights are off while the robot crosses x = 8.3..9.5.
pub fn case_study(seed: u64) -> Scenario {
    let m = |k: u64| mix(seed ^ k);
    let door = |side, center| Door {
        side,
        center,
        width: 1.0,
        height: 2.1,
    };
    let mut sc = Scene::default();
    // Room 1.
    sc.add_room(
        [0.0, 0.0],
        [5.0, 4.0],
        HEIGHT,
        &[door(Side::North, 2.5)],
        RoomLook::from_seed(m(0x1000)),
    );
    sc.add_box([0.0, 0.0, 0.0], [1.2, 0.6, 0.8], m(0x1001));
    sc.add_box([3.6, 0.0, 0.0], [5.0, 0.5, 1.8], m(0x1002));
    sc.add_box([4.5, 1.5, 0.0], [5.0, 3.0, 0.9], m(0x1003));
    sc.add_poster(
        "room1/west",
        Side::West,
        0.0,
        [1.4, 0.5],
        [0.8, 0.9],
        m(0x1004),
    );
    sc.add_poster(
        "room1/north",
        Side::North,
        4.0,
        [3.5, 0.5],
        [0.9, 0.8],
        m(0x1005),
    );
    sc.add_poster(
        "room1/south",
        Side::South,
        0.0,
        [1.6, 0.6],
        [1.0, 0.7],
        m(0x1006),
    );
    sc.add_door_frame(1, 4.0, 4.1, 2.5, 1.0, 2.1, m(0x1007));
    // Corridor: unique pieces and the two identical pieces around doors B and C.
    let alias = m(0x2000);
    corridor_piece(&mut sc, -0.5, 4.5, m(0x2001), None, Some(2.5));
    corridor_piece(&mut sc, 4.5, 8.5, alias, Some(6.5), None);
    corridor_piece(&mut sc, 8.5, 10.5, m(0x2002), None, None);
    corridor_piece(&mut sc, 10.5, 14.5, alias, Some(12.5), None);
    corridor_piece(&mut sc, 14.5, 17.5, m(0x2003), None, None);
    {
        use crate::texture::Texture;
        let w = sc.add_texture(Texture::wall(m(0x2004)));
        sc.add_quad(0, -0.5, 1.0, [4.1, 0.0], [6.1, HEIGHT], w, [4.1, 0.0]);
        let e = sc.add_texture(Texture::wall(m(0x2005)));
        sc.add_quad(0, 17.5, -1.0, [4.1, 0.0], [6.1, HEIGHT], e, [4.1, 0.0]);
    }
    for (name, x0) in [("B", 4.5), ("C", 10.5)] {
        // Identical posters and door frames around B and C.
        sc.add_poster(
            &format!("corridor/{name}/left"),
            Side::North,
            6.1,
            [x0 + 0.3, 0.45],
            [0.9, 0.8],
            m(0x2010),
        );
        sc.add_poster(
            &format!("corridor/{name}/right"),
            Side::North,
            6.1,
            [x0 + 2.8, 0.5],
            [0.7, 0.9],
            m(0x2011),
        );
        sc.add_poster(
            &format!("corridor/{name}/opposite"),
            Side::South,
            4.1,
            [x0 + 1.2, 0.5],
            [1.2, 0.8],
            m(0x2012),
        );
        sc.add_door_frame(1, 6.1, 6.2, x0 + 2.0, 1.0, 2.1, m(0x2013));
    }
    sc.add_poster(
        "corridor/west",
        Side::South,
        4.1,
        [0.5, 0.5],
        [1.0, 0.8],
        m(0x2020),
    );
    sc.add_poster(
        "corridor/dark",
        Side::North,
        6.1,
        [9.0, 0.5],
        [0.9, 0.9],
        m(0x2021),
    );
    sc.add_poster(
        "corridor/east",
        Side::North,
        6.1,
        [15.2, 0.5],
        [0.9, 0.8],
        m(0x2022),
    );
    // Closet behind B and Room 2 behind C: shared floor, ceiling, far and door walls.
    let shared = RoomLook::from_seed(m(0x3000));
    let closet = RoomLook {
        walls: [shared.walls[0], shared.walls[1], m(0x3001), m(0x3002)],
        ..shared
    };
    let room2 = RoomLook {
        walls: [shared.walls[0], shared.walls[1], m(0x3003), m(0x3004)],
        ..shared
    };
    sc.add_room(
        [4.5, 6.2],
        [8.5, 8.7],
        HEIGHT,
        &[door(Side::South, 6.5)],
        closet,
    );
    sc.add_poster(
        "closet/north",
        Side::North,
        8.7,
        [6.1, 0.6],
        [0.8, 0.8],
        m(0x3005),
    );
    sc.add_poster(
        "room2/north",
        Side::North,
        10.2,
        [12.1, 0.6],
        [0.8, 0.8],
        m(0x3005),
    );
    sc.add_room(
        [10.5, 6.2],
        [14.5, 10.2],
        HEIGHT,
        &[door(Side::South, 12.5), door(Side::East, 8.5)],
        room2,
    );
    sc.add_box([10.5, 8.8, 0.0], [11.3, 10.2, 1.2], m(0x3006));
    sc.add_box([13.8, 6.2, 0.0], [14.5, 7.4, 0.7], m(0x3007));
    sc.add_poster(
        "room2/west",
        Side::West,
        10.5,
        [6.6, 0.5],
        [0.9, 0.9],
        m(0x3008),
    );
    sc.add_poster(
        "room2/east",
        Side::East,
        14.5,
        [9.2, 0.5],
        [0.8, 0.8],
        m(0x3009),
    );
    sc.add_door_frame(0, 14.5, 14.6, 8.5, 1.0, 2.1, m(0x300a));
    // Room 3.
    sc.add_room(
        [14.6, 6.2],
        [18.6, 10.2],
        HEIGHT,
        &[door(Side::West, 8.5)],
        RoomLook::from_seed(m(0x4000)),
    );
    sc.add_box([17.6, 9.0, 0.0], [18.6, 10.2, 1.5], m(0x4001));
    sc.add_box([15.5, 6.2, 0.0], [17.0, 6.8, 0.8], m(0x4002));
    sc.add_poster(
        "room3/east",
        Side::East,
        18.6,
        [6.8, 0.5],
        [1.0, 0.8],
        m(0x4003),
    );
    sc.add_poster(
        "room3/north",
        Side::North,
        10.2,
        [15.2, 0.6],
        [0.9, 0.8],
        m(0x4004),
    );

    // Robot vacuum: camera 0.35 m above the floor, looking 15 degrees up.
    let (hgt, pitch) = (0.35, 15.0);
    let mut r = RobotScript::new(1.2, 1.0, 30.0, 0.0, hgt, pitch);
    r.speed = 1.0;
    r.turn_rate = 100f64.to_radians();
    r.mark("0").wait(1.0);
    // Room 1, explored as a loop: east, north up the middle towards door A, a look back south
    // (the view of anyone entering from the door), east, south, west, ending facing east.
    r.mark("1")
        .go(2.5, 1.0)
        .go(2.5, 2.8)
        .turn_to(-90.0)
        .go(4.0, 2.8)
        .go(4.0, 1.4)
        .go(1.5, 1.4)
        .turn_to(0.0);
    // Step 2 drives back through what step 1 mapped (its first two legs, seen the same way)
    // towards door A: known space, the paper's "realizes that it moves in a known area".
    r.mark("2").go(2.5, 1.4).go(2.5, 3.0);
    r.mark("3")
        .go(2.5, 5.1)
        .go(5.5, 5.1)
        .turn_to(90.0)
        .wait(0.7)
        // Straight through door B: the closet is mapped (its far wall is within range).
        .go(6.5, 5.1)
        .turn_to(90.0)
        .wait(1.0)
        .go(8.3, 5.1);
    // Lights off: the robot drives on and turns to face the south wall of the corridor's
    // unique stretch between the look-alike pieces.
    r.mark("4").go(9.5, 5.1).turn_to(-90.0);
    // Lights on (5): it tracks again, facing a wall no map has (nothing to recognise, and
    // nothing a look-alike could contradict: its counterpart 6 m west, next to door A, was
    // never in view); then it keeps moving (6) towards door C, whose surroundings look like
    // door B's.
    r.mark("5").wait(1.5);
    r.mark("6")
        .go(11.5, 5.1)
        .turn_to(90.0)
        .wait(0.7)
        .go(12.5, 5.1)
        .turn_to(90.0);
    // Through door C into Room 2 (7); the depth sees past the closet's far wall.
    r.mark("7").go(12.5, 6.4);
    // Explores Room 2 (8), then drives back west along the corridor to door A.
    r.mark("8")
        .go(12.5, 7.2)
        .turn_to(0.0)
        .go(13.6, 8.8)
        .go(11.8, 8.8)
        .go(12.5, 7.3)
        .go(12.5, 5.1)
        .turn_to(180.0);
    // The corridor is known by now: the robot drives it faster.
    r.speed = 1.3;
    r.go(2.5, 5.1);
    r.speed = 1.0;
    r.turn_to(-90.0);
    // Re-enters Room 1 (9) through door A, looking where step 1 looked back from, and drives
    // step 1's third leg again.
    r.mark("9").go(2.5, 2.8).go(4.0, 2.8);
    let t_kidnap = r.now();
    let leg1 = r.path(Jitter::new(m(0x9000), 0.0, 0.0015, true));
    let marks1 = r.marks.clone();
    // Kidnapping: carried for 6 s, put down in Room 3 (no frames meanwhile).
    let mut k = RobotScript::new(17.0, 7.4, 100.0, t_kidnap + 6.0, hgt, pitch);
    k.speed = 1.0;
    k.turn_rate = 100f64.to_radians();
    k.mark("10").wait(1.2);
    k.mark("11").go(16.0, 9.3).go(16.0, 8.5);
    // Step 12 begins on Room 2's threshold (door D, x = 14.5): the step is re-entering it.
    k.turn_to(180.0).go(14.5, 8.5);
    k.mark("12").go(13.0, 8.5).turn_to(120.0);
    k.mark("13").wait(1.0);
    let leg2 = k.path(Jitter::new(m(0x9001), 0.0, 0.0015, true));
    let mut marks = marks1;
    marks.extend(k.marks.iter().cloned());
    let defs: &[(&str, &str, &[&str])] = &[
        ("turned on", "robot turned on in Room 1", &["Init", "Idle"]),
        ("explore Room 1", "explores Room 1", &["Mapping"]),
        (
            "back in Room 1",
            "drives back through the known part of Room 1 towards the corridor",
            &["Localized"],
        ),
        (
            "explore corridor",
            "explores the corridor, looks at door B",
            &["Mapping"],
        ),
        (
            "dark",
            "enters the dark area (lights off: no usable images, depth still valid)",
            &["Idle"],
        ),
        ("leaves dark", "leaves the dark area", &["Core(M&R)"]),
        (
            "door C",
            "keeps moving, relocalizes wrongly (door C looks like door B)",
            &["Localized"],
        ),
        (
            "enters Room 2",
            "enters Room 2: observations contradict the map (closet behind B differs)",
            &["CorruptedMap"],
        ),
        (
            "explore Room 2",
            "explores Room 2, drives back west along the corridor",
            &["Idle", "Core(M&R)"],
        ),
        (
            "re-enters Room 1",
            "re-enters Room 1 through door A",
            &["Localized"],
        ),
        (
            "kidnapped",
            "kidnapped to Room 3 (6 s without frames, pose jumps)",
            &["Idle"],
        ),
        ("explore Room 3", "explores Room 3", &["Core(M&R)"]),
        (
            "re-enters Room 2",
            "re-enters Room 2 through door D",
            &["Localized"],
        ),
        ("turned off", "robot stops and is turned off", &["Final"]),
    ];
    let dark = vec![(marks[4].1, marks[5].1)];
    let s1 = Session {
        dir: Some(s("session1")),
        name: s("session1"),
        legs: vec![leg1, leg2],
        steps: steps(&marks, defs, 0),
        dark,
        stamp0: STAMP0,
    };
    // Session 2: placed in the north-east corner of Room 2, same world frame.
    let mut q = RobotScript::new(14.0, 9.7, -135.0, 0.0, hgt, pitch);
    q.speed = 1.0;
    q.turn_rate = 100f64.to_radians();
    q.mark("14")
        .wait(1.5)
        .turn_to(-180.0)
        .turn_to(-90.0)
        .go(12.5, 8.0)
        .turn_to(180.0)
        .wait(1.0);
    let defs2: &[(&str, &str, &[&str])] = &[(
        "turned on again",
        "turned on again in a corner of Room 2 (saved atlas loaded)",
        &["Init", "Core(M&R)", "Localized"],
    )];
    let s2 = Session {
        dir: Some(s("session2")),
        name: s("session2"),
        legs: vec![q.path(Jitter::new(m(0x9002), 0.0, 0.0015, true))],
        steps: steps(&q.marks, defs2, 14),
        dark: vec![],
        stamp0: STAMP0 + 86_400.0,
    };
    Scenario {
        name: s("case-study"),
        description: s("The paper's robot-vacuum case study (Fig. 9, Table II)."),
        motion: s("robot (planar, camera 0.35 m above the floor, pitched 15 degrees up)"),
        scene: sc,
        sessions: vec![s1, s2],
        small_stride: 6,
    }
}
