//! homing: visual SLAM (RGB-D and depth-suppressed monocular) whose modal behaviour is decided
//! by one explicit hierarchical state machine ("Better Lost in Transition Than Lost in Space:
//! SLAM State Machine"). See README.md for the architecture.

pub mod config;
pub mod error;
pub mod io;

pub use error::{Error, Result};
pub mod aligner;
pub mod atlas;
pub mod bench;
pub mod control;
pub mod depth_registration;
pub mod eval;
pub mod geometry;
pub mod global_optimizer;
pub mod initializer;
pub mod interrupt;
pub mod loop_detector;
pub mod loop_validator;
pub mod map;
pub mod map_merger;
pub mod mcap_log;
pub mod optim;
pub mod output;
pub mod preprocess;
pub mod report;
pub mod system;
pub mod tracker;
pub mod two_view;
pub mod viz;
