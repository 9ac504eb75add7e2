//! Orientation estimators: WSS (SPEC.md section 4) and trained baselines (section 5).

pub mod ann;
pub mod classic;
pub mod edbn;
pub mod features;
pub mod wss;
