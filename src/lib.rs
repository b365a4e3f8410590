//! homing: visual SLAM (RGB-D and depth-suppressed monocular) whose modal behaviour is decided
//! by one explicit hierarchical state machine ("Better Lost in Transition Than Lost in Space:
//! SLAM State Machine"). See README.md for the architecture.

pub mod config;
pub mod error;
pub mod io;

pub use error::{Error, Result};
pub mod eval;
pub mod geometry;
pub mod output;
pub mod system;
pub mod optim;
pub mod preprocess;
pub mod aligner;
pub mod map;
pub mod tracker;
pub mod control;
pub mod initializer;
pub mod map_merger;
