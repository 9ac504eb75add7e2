//! Evaluation sinks: metrics over every trial's estimate, shown as tables and
//! written as report files.

pub mod confusion;
pub mod mae;
pub mod signal_levels;
pub mod spike_timing;
