//! Spike-level stages: binning, and the perturbations of the paper's robustness
//! studies (SPEC.md sections 3 and 8).
//!
//! | type | in -> out | what it does |
//! |---|---|---|
//! | `bin` | spikes -> images | counts per taxel in windows of `window_ms` every `hop_ms` |

pub mod bin;
