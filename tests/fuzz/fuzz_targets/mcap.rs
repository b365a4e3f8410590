//! Feeds arbitrary bytes to the ROS 2 bag reader (`homing run --mcap`): opening the file and
//! reading every frame must succeed or give a clear Err, never panic.
#![no_main]

use homing::io::mcap::{McapSequence, McapTopics};
use homing::io::tum::FrameSource;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let path = std::env::temp_dir().join(format!("homing-fuzz-mcap-{}.mcap", std::process::id()));
    std::fs::write(&path, data).unwrap();
    let topics = McapTopics {
        image: "/camera/rgb/image_color".into(),
        depth: "/camera/depth/image".into(),
        camera_info: Some("/camera/rgb/camera_info".into()),
    };
    for mono in [false, true] {
        if let Ok(seq) = McapSequence::open(&path, &topics, 0.02, mono) {
            for i in 0..seq.len().min(8) {
                let _ = seq.load(i);
            }
        }
    }
});
