//! Non-linear least squares for the back end: pose-only refinement (tracker), local bundle
//! adjustment (map merger) and, later, pose-graph optimisation (global optimizer).
