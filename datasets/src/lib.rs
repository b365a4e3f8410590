//! Dataset tools for homing: the synthetic sequence generator and the TUM download tool.
