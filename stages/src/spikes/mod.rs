//! Spike-level stages: jitter, cropping, sub-areas, binning (SPEC.md sections 3 and 8).
