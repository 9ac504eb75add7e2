//! palpate: tactile-sensing experiments as TOML graphs of typed, pluggable stages.
//!
//! This crate is the facade and the `palpate` command line. The machinery lives in
//! [`core`] (payloads, stage traits, graph loading, runtime); the built-in stages
//! in [`stages`]. [`report`] formats a run's results for the terminal and the run
//! record; [`frontier`] builds a sweep's accuracy-time frontier; [`cluster`] runs
//! sweeps as shards, merges them and writes Slurm job arrays.

pub mod batch;
pub mod cli;
pub mod cluster;
pub mod frontier;
pub mod guide;
pub mod report;
pub mod sweep_plot;

pub use palpate_core as core;
pub use palpate_stages as stages;

/// Makes sure the built-in stages are linked and registered (a crate nothing
/// references may be dropped by the linker with its registrations). Returns the
/// number of registered stage types.
pub fn link() -> usize {
    palpate_stages::link()
}
