//! Feeds arbitrary bytes to the atlas loader (`--load-map`), both as a whole file and as the
//! payload of a well-formed header (so that decoding itself is exercised, past the checksum):
//! each must load or give a clear Err, never panic.
#![no_main]

use homing::atlas::{ATLAS_VERSION, Atlas, AtlasCamera};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let camera = AtlasCamera {
        fx: 517.3,
        fy: 516.5,
        cx: 318.6,
        cy: 255.3,
        width: 640,
        height: 480,
    };
    let path = std::env::temp_dir().join(format!("homing-fuzz-atlas-{}", std::process::id()));
    std::fs::write(&path, data).unwrap();
    let _ = Atlas::load(&path, &camera, false);
    let mut framed = b"homing-atlas\n".to_vec();
    framed.extend_from_slice(&ATLAS_VERSION.to_le_bytes());
    framed.extend_from_slice(&(data.len() as u64).to_le_bytes());
    framed.extend_from_slice(&crc32fast::hash(data).to_le_bytes());
    framed.extend_from_slice(data);
    std::fs::write(&path, &framed).unwrap();
    let _ = Atlas::load(&path, &camera, false);
    let _ = Atlas::load(&path, &camera, true);
});
