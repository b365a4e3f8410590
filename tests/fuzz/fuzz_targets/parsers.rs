//! Feeds arbitrary text to every text parser: each must return Ok or a clear Err, never panic.
#![no_main]

use homing::config::Config;
use homing::io::perturb::{DropSpec, FaultRate, FaultSpec};
use homing::io::tum::{parse_associations, parse_list, parse_trajectory};
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let p = Path::new("fuzz.txt");
    let _ = parse_list(text, p);
    if let Ok(traj) = parse_trajectory(text, p) {
        // Whatever parses must be finite and increasing.
        assert!(traj.windows(2).all(|w| w[0].t < w[1].t));
        assert!(traj.iter().all(|s| s.pose.translation.vector.iter().all(|v| v.is_finite())));
    }
    let _ = parse_associations(text, p);
    let _ = Config::parse(text, Path::new("fuzz.toml"));
    let _ = text.parse::<DropSpec>();
    let _ = text.parse::<FaultSpec>();
    let _ = text.parse::<FaultRate>();
});
