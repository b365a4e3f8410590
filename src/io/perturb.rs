//! Perturbations of a sequence (filled in below).
