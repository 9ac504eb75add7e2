//! palpate-stages: every built-in stage, one module per family.
//!
//! | family | stages |
//! |---|---|
//! | [`scene`] | simulated scenes: edges and ridges crossing a taxel array, with pluggable effects |
//! | [`signal`] | normalization, filters, derivatives, drives |
//! | [`encode`] | spiking encoders: Izhikevich, LIF |
//! | [`spikes`] | spike-level stages: jitter, cropping, sub-areas, binning |
//! | [`estimate`] | orientation estimators: WSS and trained baselines |
//! | [`evaluate`] | sinks: metrics, confusion, reports |
//! | [`io`] | file sources and sinks, DAQ |
//!
//! Each stage's config registers itself (typetag + [`palpate_core::register_stage!`]);
//! nothing here is listed by hand. [`link`] exists so that a binary can reference
//! this crate explicitly: a crate nothing references may be dropped by the linker
//! together with its registrations.

pub mod encode;
pub mod estimate;
pub mod evaluate;
pub mod io;
pub mod plot;
pub mod scene;
pub mod signal;
pub mod spikes;
pub mod stream;
pub mod wide;

/// Call once from a binary or test that relies on the built-in stages being
/// registered; it keeps the linker from dropping this crate. Returns the number
/// of registered stage types.
pub fn link() -> usize {
    palpate_core::registry::registrations().len()
}
