//! Classical baselines from smartcore on the same features (SPEC.md section 5).
