//! homing: visual SLAM (RGB-D and depth-suppressed monocular) whose modal behaviour is decided
//! by one explicit hierarchical state machine ("Better Lost in Transition Than Lost in Space:
//! SLAM State Machine"). See README.md and docs/architecture.md for the architecture.
//!
//! The layout follows the architecture: [`components`] are the paper's components (one module
//! each), [`atlas`] and [`map`] hold the maps, [`control`] is the state machine (one file per
//! state), [`optim`] the back-end solvers, [`io`] the inputs, [`outputs`] the run's files, logs
//! and reports, [`eval`] ATE/RPE, [`bench`](mod@bench) the benchmarks, [`slam`] the streaming API (one frame in, its pose out) and [`system`] the run driver on it.

pub mod config;
pub mod error;
pub mod io;

pub use error::{Error, Result};
pub mod atlas;
pub mod bench;
pub mod components;
pub mod control;
pub mod eval;
pub mod geometry;
pub mod interrupt;
pub mod map;
pub mod optim;
pub mod outputs;
pub mod slam;
pub mod system;
