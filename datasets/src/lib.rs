//! Dataset tools for homing: a synthetic RGB-D sequence generator (TUM layout, ground truth,
//! scenario steps with the expected SLAM states) and contact sheets. `download_tum.sh` next to
//! this crate fetches the real TUM sequences.

pub mod cli;
pub mod motion;
pub mod render;
pub mod scenarios;
pub mod scene;
pub mod sensor;
pub mod sheet;
pub mod texture;
pub mod writer;
