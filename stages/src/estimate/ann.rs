//! ANN baseline: one hidden layer, spatial or spatiotemporal input (SPEC.md section 5).
