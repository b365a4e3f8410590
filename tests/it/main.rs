//! The `homing` crate's integration tests, one module per area, built as a single test
//! binary: every binary links the whole pipeline (and, in CI, the rerun SDK), so one binary
//! instead of seventeen saves most of the test build's link time, and the tests of all areas
//! share the test harness's threads instead of running one binary after another.
//!
//! Run one area with its module path, e.g. `cargo test --test it loop_closing::`.

mod common;

mod bad_inputs;
mod case_study;
mod decoded_frames;
mod eval_vs_evo;
mod loop_closing;
mod mcap_files;
mod optim_local_ba;
mod optim_pose_graph;
mod optim_pose_only;
mod preprocess;
mod report;
mod rerun_recording;
mod robustness;
mod run_outputs;
mod slam_api;
mod slam_mono;
mod slam_rgbd;
mod two_view;
mod user_stop;
