//! vocab-tools: descriptor extraction, HBST construction, place-recognition evaluation and
//! timing of the loop detector's descriptor index (the `homing::components::loop_detector` HBST).
//! The binary `vocab-tools` is a thin command line over these modules; see README.md.

pub mod bench;
pub mod descfile;
pub mod eval;
pub mod extract;
pub mod train;
pub mod tree;

pub use descfile::{DescriptorFile, FrameDescriptors};
