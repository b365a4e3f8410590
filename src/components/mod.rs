//! The paper's components (its Fig. 2), one module each. They compute and report flags and
//! statistics; only the state machine (`crate::control`) decides what runs.

pub mod aligner;
pub mod depth_registration;
pub mod global_optimizer;
pub mod initializer;
pub mod loop_detector;
pub mod loop_validator;
pub mod map_merger;
pub mod preprocess;
pub mod rotation;
pub mod tracker;
pub mod two_view;
