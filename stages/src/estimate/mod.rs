//! Orientation estimators: WSS (SPEC.md section 4) and trained baselines (section 5).
