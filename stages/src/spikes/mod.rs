//! Spike-level stages: binning, the perturbations of the paper's robustness
//! studies, and spike plots.
//!
//! | type | in -> out | what it does |
//! |---|---|---|
//! | `bin` | spikes -> images | counts per taxel in windows of `window_ms` every `hop_ms` |
//! | `jitter` | spikes -> spikes | spike-time noise, Gaussian or uniform (Fig. 8) |
//! | `crop` | spikes -> spikes | keeps the first share of the edge's crossing (Fig. 7) |
//! | `subarea` | spikes -> spikes | an `n x n` window of the grid as a smaller array (Fig. 9) |
//! | `dead_taxels` | spikes -> spikes | removes the spikes of dead taxels |
//! | `raster_plot` | spikes -> sink | SVG spike raster per trial |
//! | `image_strip` | images -> sink | SVG strip of a trial's spike images (Fig. 3(c)) |

pub mod bin;
pub mod crop;
pub mod dead;
pub mod jitter;
pub mod plot;
pub mod subarea;
