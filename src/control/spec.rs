//! The state machines as data: states (with their parent and regions), entry/do/exit
//! activities, and transitions with their trigger and guard. The runtime in
//! [`super::StateMachine`] follows these tables and nothing else, so the diagram that
//! `homing states --dot` prints is the machine that runs.
//!
//! `ours` is the SLAM state machine of the paper (section V, Fig. 8); the peers are the modal
//! behaviour the paper extracted from ORB-SLAM2, ProSLAM and LDSO (section IV), driving the
//! same components.

use crate::config::ControllerKind;
use std::fmt::Write as _;

/// A state of one of the machines. `Core` has the orthogonal regions Mapping and Relocalize
/// (shown as "Mapping" while there is no other map to relocalize in).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum State {
    Init,
    Idle,
    Core,
    Localized,
    CorruptedMap,
    Final,
    /// Peers: tracking and mapping (ORB-SLAM2, ProSLAM, LDSO all have it).
    Mapping,
    /// Peers: lost (ORB-SLAM2: relocalize in the one map; ProSLAM: wait to start a new map).
    Relocalization,
}

/// What a state does on each measurement (its *do* activity). The activities call the
/// components; which ones run is the state's business, not the components'.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activity {
    /// Run the initializer until it reports `initialized`.
    Initialize,
    /// Try to (re)start tracking: first in the current map when the loss was short, else a
    /// new map from one good frame (RGB-D) or the two-view initializer (monocular).
    Restart { new_map: bool, same_map: bool },
    /// Core: tracker + map merger (region Mapping), loop closing on the current map, and
    /// relocalization against the other maps (region Relocalize) when `relocalize`.
    TrackAndMap {
        loop_scope: LoopScope,
        relocalize: bool,
        /// Also recognise, frame by frame, places of the current map mapped earlier (outside
        /// the loop detector's temporal window): a validated pool of them means the camera is
        /// in known space (`able_to_localize`), even without a loop to close.
        recognize_known: bool,
    },
    /// Localized: tracking in known space, no new keyframes, expectation check.
    TrackLocalized,
    /// Corrupted map: undo the closure pool that explains the inconsistency. It does not use
    /// the measurement, so the state the recovery leads to runs on the same one.
    Recover,
    /// ORB-SLAM2 when lost: relocalize in the (single) map; the frame gets no pose otherwise.
    RelocalizeOnly,
    /// Nothing (Final; a stopped system).
    None,
}

/// Where the loop closer looks for candidates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LoopScope {
    /// Keyframes of the current map (outside the temporal window).
    CurrentMap,
    /// Every keyframe of every map; a closure to another map merges them (ProSLAM).
    AllMaps,
}

/// How a closure pool is accepted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Acceptance {
    /// Only after `pool_size` agreeing candidates (the paper's delayed decision).
    Pool,
    /// The first geometrically valid candidate (ORB-SLAM2's relocalization, ProSLAM).
    Immediate,
}

/// Guards: boolean conditions over the components' flags (paper Table I) and events.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Guard {
    Initialized,
    AbleToTrack,
    NotAbleToTrack,
    AbleToLocalize,
    NotConsistentMap,
    /// Localized: the map does not cover the view any more (a keyframe would be needed).
    LeftKnownArea,
    /// Corrupted map: a pool was found and undone.
    Recovered,
    NotRecovered,
}

impl Guard {
    pub fn label(self) -> &'static str {
        match self {
            Self::Initialized => "initialized",
            Self::AbleToTrack => "able_to_track",
            Self::NotAbleToTrack => "!able_to_track",
            Self::AbleToLocalize => "able_to_localize",
            Self::NotConsistentMap => "!consistent_map",
            Self::LeftKnownArea => "left_known_area",
            Self::Recovered => "recovered",
            Self::NotRecovered => "!recovered",
        }
    }
}

/// A transition `from --trigger [guard] / effect--> to`. Guard-only transitions are
/// evaluated after the state's activity on every measurement (in table order); the
/// Interruptible top state's events (end of data, user stop) lead every state to Final.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Transition {
    pub from: State,
    pub to: State,
    pub guard: Guard,
}

/// One state's description.
#[derive(Debug, Clone)]
pub struct StateSpec {
    pub state: State,
    /// Name in states.csv and the diagram.
    pub name: &'static str,
    pub entry: &'static str,
    pub activity: Activity,
    pub does: &'static str,
    pub exit: &'static str,
}

/// A whole machine.
#[derive(Debug, Clone)]
pub struct MachineSpec {
    pub kind: ControllerKind,
    pub title: &'static str,
    pub states: Vec<StateSpec>,
    pub transitions: Vec<Transition>,
    pub acceptance: Acceptance,
    /// Whether a new map is started when tracking is re-acquired (an atlas of several maps).
    pub multi_map: bool,
    /// An accepted closure pool is applied where it is found, without a change of state (the
    /// peers have no Localized state; ORB-SLAM2's loop closer corrects the map in Mapping).
    pub closures_in_place: bool,
}

impl MachineSpec {
    pub fn for_kind(kind: ControllerKind) -> Self {
        match kind {
            ControllerKind::Ours => ours(),
            ControllerKind::Orbslam2 => orbslam2(),
            ControllerKind::Proslam => proslam(),
            ControllerKind::Ldso => ldso(),
        }
    }

    pub fn state(&self, s: State) -> &StateSpec {
        self.states
            .iter()
            .find(|x| x.state == s)
            .expect("every state of a machine has a spec")
    }

    pub fn outgoing(&self, s: State) -> impl Iterator<Item = &Transition> {
        self.transitions.iter().filter(move |t| t.from == s)
    }

    /// Graphviz DOT of the machine (UML-ish: rounded states with entry/do/exit, the
    /// Interruptible super-state, Core's two regions).
    pub fn to_dot(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "digraph \"{}\" {{", self.title);
        let _ = writeln!(
            s,
            "  graph [fontname=\"Helvetica\", label=\"{} ({})\", labelloc=t, compound=true];",
            self.title,
            self.kind.as_str()
        );
        let _ = writeln!(
            s,
            "  node [shape=box, style=rounded, fontname=\"Helvetica\", fontsize=10];"
        );
        let _ = writeln!(s, "  edge [fontname=\"Helvetica\", fontsize=9];");
        let _ = writeln!(
            s,
            "  start [shape=circle, style=filled, fillcolor=black, label=\"\", width=0.2];"
        );
        let _ = writeln!(s, "  subgraph cluster_interruptible {{");
        let _ = writeln!(
            s,
            "    label=\"Interruptible\\n(user stop / end of data → Final)\"; style=rounded;"
        );
        for st in &self.states {
            if st.state == State::Final {
                continue;
            }
            let label = format!(
                "{}\\n—\\nentry / {}\\ndo / {}\\nexit / {}",
                st.name, st.entry, st.does, st.exit
            );
            if st.state == State::Core {
                let _ = writeln!(s, "    subgraph cluster_core {{");
                let _ = writeln!(s, "      label=\"Core\"; style=rounded;");
                let _ = writeln!(
                    s,
                    "      Core [label=\"{label}\"];\n      Core_regions [shape=record, label=\"{{Mapping | tracker, map merger, loop closing on the current map}} | {{Relocalize | loop detector + validator on the other maps}}\"];"
                );
                let _ = writeln!(s, "      Core -> Core_regions [style=invis];");
                let _ = writeln!(s, "    }}");
            } else {
                let _ = writeln!(s, "    {:?} [label=\"{label}\"];", st.state);
            }
        }
        let _ = writeln!(s, "  }}");
        let fin = self.state(State::Final);
        let _ = writeln!(
            s,
            "  Final [shape=box, style=rounded, peripheries=2, label=\"Final\\nentry / {}\"];",
            fin.entry
        );
        let _ = writeln!(s, "  start -> Init;");
        for t in &self.transitions {
            let _ = writeln!(
                s,
                "  {:?} -> {:?} [label=\"[{}]\"];",
                t.from,
                t.to,
                t.guard.label()
            );
        }
        let _ = writeln!(
            s,
            "  Init -> Final [label=\"end_of_data / user_stop\", ltail=cluster_interruptible, style=dashed];"
        );
        let _ = writeln!(s, "}}");
        s
    }
}

fn st(
    state: State,
    name: &'static str,
    entry: &'static str,
    activity: Activity,
    does: &'static str,
    exit: &'static str,
) -> StateSpec {
    StateSpec {
        state,
        name,
        entry,
        activity,
        does,
        exit,
    }
}

fn tr(from: State, to: State, guard: Guard) -> Transition {
    Transition { from, to, guard }
}

/// The paper's SLAM state machine (section V).
fn ours() -> MachineSpec {
    use Guard::*;
    use State::*;
    MachineSpec {
        kind: ControllerKind::Ours,
        title: "SLAM state machine",
        states: vec![
            st(
                Init,
                "Init",
                "load config; load a saved atlas if given",
                Activity::Initialize,
                "initializer",
                "-",
            ),
            st(
                Idle,
                "Idle",
                "tracker reset",
                Activity::Restart {
                    new_map: true,
                    same_map: true,
                },
                "re-track a short gap in the current map (without depth: relocalize in it), else start a new map",
                "-",
            ),
            st(
                Core,
                "Core",
                "map the frame Idle re-tracked",
                Activity::TrackAndMap {
                    loop_scope: LoopScope::CurrentMap,
                    relocalize: true,
                    recognize_known: true,
                },
                "Mapping ∥ Relocalize",
                "-",
            ),
            st(
                Localized,
                "Localized",
                "add closure pool, merge maps, global optimisation + consistency check, load tracker with best-matching local map",
                Activity::TrackLocalized,
                "track in known maps, no new keyframes, expectation check",
                "-",
            ),
            st(
                CorruptedMap,
                "CorruptedMap",
                "-",
                Activity::Recover,
                "find the bad closure pool (newest first), roll it back, re-optimise",
                "-",
            ),
            st(
                Final,
                "Final",
                "batch refinement (full BA), save atlas, write outputs",
                Activity::None,
                "-",
                "-",
            ),
        ],
        transitions: vec![
            tr(Init, Idle, Initialized),
            tr(Idle, Core, AbleToTrack),
            tr(Core, Idle, NotAbleToTrack),
            tr(Core, Localized, AbleToLocalize),
            tr(Core, CorruptedMap, NotConsistentMap),
            tr(Localized, CorruptedMap, NotConsistentMap),
            tr(Localized, Idle, NotAbleToTrack),
            tr(Localized, Core, LeftKnownArea),
            tr(CorruptedMap, Idle, Recovered),
            tr(CorruptedMap, Final, NotRecovered),
        ],
        acceptance: Acceptance::Pool,
        multi_map: true,
        closures_in_place: false,
    }
}

/// ORB-SLAM2 (paper Fig. 3): one map; when lost, only relocalization in it, frames dropped.
fn orbslam2() -> MachineSpec {
    use Guard::*;
    use State::*;
    MachineSpec {
        kind: ControllerKind::Orbslam2,
        title: "ORB-SLAM2 modal controller",
        states: vec![
            st(Init, "Init", "-", Activity::Initialize, "initializer", "-"),
            st(
                Mapping,
                "Mapping",
                "-",
                Activity::TrackAndMap {
                    loop_scope: LoopScope::CurrentMap,
                    relocalize: false,
                    recognize_known: false,
                },
                "tracking, local mapping, loop closing",
                "-",
            ),
            st(
                Relocalization,
                "Relocalization",
                "-",
                Activity::RelocalizeOnly,
                "relocalize in the map; frames dropped",
                "-",
            ),
            st(
                Final,
                "Final",
                "full BA, write outputs",
                Activity::None,
                "-",
                "-",
            ),
        ],
        transitions: vec![
            tr(Init, Mapping, Initialized),
            tr(Mapping, Relocalization, NotAbleToTrack),
            tr(Relocalization, Mapping, AbleToTrack),
        ],
        acceptance: Acceptance::Immediate,
        multi_map: false,
        closures_in_place: true,
    }
}

/// ProSLAM (paper Fig. 5): when lost, a new disconnected map; loop closures may rejoin maps;
/// no relocalize region, no consistency state.
fn proslam() -> MachineSpec {
    use Guard::*;
    use State::*;
    MachineSpec {
        kind: ControllerKind::Proslam,
        title: "ProSLAM modal controller",
        states: vec![
            st(Init, "Init", "-", Activity::Initialize, "initializer", "-"),
            st(
                Mapping,
                "Mapping",
                "-",
                Activity::TrackAndMap {
                    loop_scope: LoopScope::AllMaps,
                    relocalize: false,
                    recognize_known: false,
                },
                "tracking, mapping, loop closing over all maps",
                "-",
            ),
            st(
                Relocalization,
                "Relocalization",
                "-",
                Activity::Restart {
                    new_map: true,
                    same_map: false,
                },
                "start a new map from the next good frame",
                "-",
            ),
            st(Final, "Final", "write outputs", Activity::None, "-", "-"),
        ],
        transitions: vec![
            tr(Init, Mapping, Initialized),
            tr(Mapping, Relocalization, NotAbleToTrack),
            tr(Relocalization, Mapping, AbleToTrack),
        ],
        acceptance: Acceptance::Immediate,
        multi_map: true,
        closures_in_place: true,
    }
}

/// LDSO (paper Fig. 4): when the odometry fails, stop.
fn ldso() -> MachineSpec {
    use Guard::*;
    use State::*;
    MachineSpec {
        kind: ControllerKind::Ldso,
        title: "LDSO modal controller",
        states: vec![
            st(Init, "Init", "-", Activity::Initialize, "initializer", "-"),
            st(
                Mapping,
                "Mapping",
                "-",
                Activity::TrackAndMap {
                    loop_scope: LoopScope::CurrentMap,
                    relocalize: false,
                    recognize_known: false,
                },
                "odometry, mapping, loop closing",
                "-",
            ),
            st(
                Final,
                "Final",
                "global optimisation, write outputs",
                Activity::None,
                "-",
                "-",
            ),
        ],
        transitions: vec![
            tr(Init, Mapping, Initialized),
            tr(Mapping, Final, NotAbleToTrack),
        ],
        acceptance: Acceptance::Immediate,
        multi_map: false,
        closures_in_place: true,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_transition_joins_states_of_its_machine() {
        for kind in [
            ControllerKind::Ours,
            ControllerKind::Orbslam2,
            ControllerKind::Proslam,
            ControllerKind::Ldso,
        ] {
            let m = MachineSpec::for_kind(kind);
            for t in &m.transitions {
                assert!(m.states.iter().any(|s| s.state == t.from), "{kind:?} {t:?}");
                assert!(m.states.iter().any(|s| s.state == t.to), "{kind:?} {t:?}");
            }
            // Every state but Final is left by some transition or by the Interruptible events.
            let dot = m.to_dot();
            assert!(dot.starts_with("digraph") && dot.trim_end().ends_with('}'));
            for s in &m.states {
                assert!(
                    dot.contains(s.name),
                    "{kind:?}: {} missing from the diagram",
                    s.name
                );
            }
        }
    }

    #[test]
    fn ours_has_the_papers_states_and_guards() {
        let m = ours();
        let names: Vec<&str> = m.states.iter().map(|s| s.name).collect();
        assert_eq!(
            names,
            ["Init", "Idle", "Core", "Localized", "CorruptedMap", "Final"]
        );
        let has = |f, t, g| m.transitions.contains(&tr(f, t, g));
        assert!(has(State::Core, State::Localized, Guard::AbleToLocalize));
        assert!(has(
            State::Localized,
            State::CorruptedMap,
            Guard::NotConsistentMap
        ));
        assert!(has(State::CorruptedMap, State::Idle, Guard::Recovered));
        assert!(has(State::CorruptedMap, State::Final, Guard::NotRecovered));
    }
}
