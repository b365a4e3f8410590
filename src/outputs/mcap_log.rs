//! `run.mcap` (`homing run --mcap-log`): the run as an MCAP log that Foxglove shows. Every
//! channel is JSON with a JSON-schema schema; every message's log time is its frame's time
//! stamp in nanoseconds.
//!
//! | topic | schema | per |
//! |---|---|---|
//! | `/homing/pose` | `foxglove.PoseInFrame` + `frame`, `map` | frame with a pose (camera-to-world, as in `trajectory.txt`) |
//! | `/homing/state` | `homing.State` | delivered frame: the state after it, the flags, the map |
//! | `/homing/stats` | `homing.FrameStats` | delivered frame: tracked inliers, keyframes, maps (and per-stage ms with `--mcap-timing`) |
//! | `/homing/transition` | `homing.Transition` | transition (as the `from` rows of `states.csv`): frame, time stamp, from, to, trigger, guard values |
//!
//! The file is deterministic (the same input gives the same bytes: no wall-clock, ordered
//! containers, single-threaded compression) except with `--mcap-timing`, whose per-stage
//! milliseconds are measured. It is written atomically.

use crate::error::{Error, Result};
use crate::io::atomic_write;
use crate::io::mcap::{POSE_JSON_SCHEMA, pose_json, seconds_to_ns, write_options};
use crate::outputs::{Flags, StateRow};
use nalgebra::Isometry3;
use serde_json::json;
use std::collections::BTreeMap;
use std::path::Path;

pub const POSE_TOPIC: &str = "/homing/pose";
pub const STATE_TOPIC: &str = "/homing/state";
pub const STATS_TOPIC: &str = "/homing/stats";
pub const TRANSITION_TOPIC: &str = "/homing/transition";

/// Per-frame statistics gathered during the run.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameStats {
    pub frame: usize,
    pub t: f64,
    /// Inliers of the tracker's final pose refinement, when the tracker ran on this frame.
    pub tracked_inliers: Option<usize>,
    /// Keyframes and maps in the atlas after the frame.
    pub keyframes: usize,
    pub maps: usize,
    /// Milliseconds per stage spent on this frame (only with `--mcap-timing`).
    pub timing_ms: Option<BTreeMap<String, f64>>,
}

/// A frame's final pose (camera-to-world) and its map.
#[derive(Debug, Clone, PartialEq)]
pub struct PosedFrame {
    pub frame: usize,
    pub t: f64,
    pub map: u32,
    pub pose: Isometry3<f64>,
}

const FLAGS_SCHEMA: &str = r#"{"type":"object","properties":{"initialized":{"type":"boolean"},"able_to_track":{"type":"boolean"},"able_to_localize":{"type":"boolean"},"consistent_map":{"type":"boolean"}}}"#;

fn state_schema() -> String {
    format!(
        r#"{{"title":"homing.State","description":"The controller's state after a frame","type":"object","properties":{{"frame":{{"type":"integer"}},"timestamp":{{"type":"number","description":"seconds"}},"state":{{"type":"string"}},"map":{{"type":["integer","null"]}},"flags":{FLAGS_SCHEMA}}}}}"#
    )
}

fn stats_schema() -> String {
    r#"{"title":"homing.FrameStats","description":"Per-frame statistics","type":"object","properties":{"frame":{"type":"integer"},"timestamp":{"type":"number"},"tracked_inliers":{"type":["integer","null"]},"keyframes":{"type":"integer"},"maps":{"type":"integer"},"timing_ms":{"type":"object","additionalProperties":{"type":"number"}}}}"#.into()
}

fn transition_schema() -> String {
    format!(
        r#"{{"title":"homing.Transition","description":"A state transition of the controller","type":"object","properties":{{"frame":{{"type":"integer"}},"timestamp":{{"type":"number"}},"from":{{"type":"string"}},"to":{{"type":"string"}},"trigger":{{"type":"string"}},"guards":{FLAGS_SCHEMA}}}}}"#
    )
}

fn flags_json(f: &Flags) -> serde_json::Value {
    json!({
        "initialized": f.initialized,
        "able_to_track": f.able_to_track,
        "able_to_localize": f.able_to_localize,
        "consistent_map": f.consistent_map,
    })
}

/// The log as bytes (see the module documentation).
pub fn encode(states: &[StateRow], stats: &[FrameStats], poses: &[PosedFrame]) -> Result<Vec<u8>> {
    // (log time, channel slot, order within the slot, payload)
    let mut msgs: Vec<(u64, usize, usize, Vec<u8>)> = Vec::new();
    for (k, p) in poses.iter().enumerate() {
        let v = pose_json(p.t, &p.pose, json!({"frame": p.frame, "map": p.map}));
        msgs.push((seconds_to_ns(p.t), 0, k, v.to_string().into_bytes()));
    }
    // The state after each frame: the frame's last row.
    for (k, r) in states.iter().enumerate() {
        if states.get(k + 1).is_some_and(|n| n.frame == r.frame) {
            continue;
        }
        let v = json!({
            "frame": r.frame,
            "timestamp": r.t,
            "state": r.state,
            "map": r.map,
            "flags": flags_json(&r.flags),
        });
        msgs.push((seconds_to_ns(r.t), 1, k, v.to_string().into_bytes()));
    }
    for (k, s) in stats.iter().enumerate() {
        let mut v = json!({
            "frame": s.frame,
            "timestamp": s.t,
            "tracked_inliers": s.tracked_inliers,
            "keyframes": s.keyframes,
            "maps": s.maps,
        });
        if let Some(t) = &s.timing_ms {
            v["timing_ms"] = json!(t);
        }
        msgs.push((seconds_to_ns(s.t), 2, k, v.to_string().into_bytes()));
    }
    for (k, r) in states.iter().enumerate() {
        let Some(tr) = &r.transition else { continue };
        let v = json!({
            "frame": r.frame,
            "timestamp": r.t,
            "from": tr.from,
            "to": r.state,
            "trigger": tr.trigger,
            "guards": flags_json(&r.flags),
        });
        msgs.push((seconds_to_ns(r.t), 3, k, v.to_string().into_bytes()));
    }
    msgs.sort_by_key(|a| (a.0, a.1, a.2));

    let err = |e: ::mcap::McapError| Error::invalid(format!("cannot encode run.mcap: {e}"));
    let mut buf = std::io::Cursor::new(Vec::new());
    {
        let mut w = ::mcap::Writer::with_options(&mut buf, write_options("")).map_err(err)?;
        let none = BTreeMap::new();
        let mut channels = Vec::new();
        for (topic, name, schema) in [
            (
                POSE_TOPIC,
                "foxglove.PoseInFrame",
                POSE_JSON_SCHEMA.to_string(),
            ),
            (STATE_TOPIC, "homing.State", state_schema()),
            (STATS_TOPIC, "homing.FrameStats", stats_schema()),
            (TRANSITION_TOPIC, "homing.Transition", transition_schema()),
        ] {
            let s = w
                .add_schema(name, "jsonschema", schema.as_bytes())
                .map_err(err)?;
            channels.push(w.add_channel(s, topic, "json", &none).map_err(err)?);
        }
        let mut seq = [0u32; 4];
        for (ns, slot, _, data) in &msgs {
            seq[*slot] += 1;
            w.write_to_known_channel(
                &::mcap::records::MessageHeader {
                    channel_id: channels[*slot],
                    sequence: seq[*slot],
                    log_time: *ns,
                    publish_time: *ns,
                },
                data,
            )
            .map_err(err)?;
        }
        w.finish().map_err(err)?;
    }
    Ok(buf.into_inner())
}

/// Writes `run.mcap` atomically.
pub fn write(
    path: &Path,
    states: &[StateRow],
    stats: &[FrameStats],
    poses: &[PosedFrame],
) -> Result<()> {
    atomic_write(path, &encode(states, stats, poses)?)
}
