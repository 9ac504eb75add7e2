//! Real inputs and outputs: file sources and sinks, and the DAQ.
//!
//! | stage | role | kinds | module |
//! |---|---|---|---|
//! | `daq` | source | -> signals | [`daq::source`]: a board, a raw recording or an emulated scene, cut at contact |
//! | `signal_file` | source | -> signals | [`signal_file`]: CSV, NPY, NPZ, MATLAB .mat, raw DAQ streams |
//! | `spike_file` | source | -> spikes | [`spike_file`]: `(x, y, t[, p])` events from CSV or NPY |
//! | `image_file` | source | -> images | [`image_file`]: the folder `write_images` wrote, read back |
//! | `union` | source | -> any one kind | [`union`]: several named sources as one, each trial labelled `source = <name>` (train on one, test on another) |
//! | `write_signals` | sink | signals | [`sinks`]: NPY or CSV, one file per trial |
//! | `write_spikes` | sink | spikes | [`sinks`]: NPY or CSV, one file per trial |
//! | `write_images` | sink | images | [`sinks`]: NPY or CSV, one file per trial |
//! | `write_estimates` | sink | estimates | [`sinks`]: NPY or CSV, one file per run |
//!
//! [`daq`] holds the live path: the `daq` source stage (a board, a raw
//! recording or an emulated scene, cut into trials at contact), the frame
//! protocol (`docs/daq-protocol.md`), acquisition from a serial port or any
//! byte stream with raw recording, and an emulator that plays signals through
//! a pseudo-terminal.
//!
//! Principle: lose nothing. Bad input (NaN or infinite samples, truncated
//! files, wrong shapes, unknown columns, mismatched sample rates, corrupted
//! frames, a device that disappears) is an error naming the file and position,
//! never a silent drop or fill; the only filling there is (`fill_gaps` for DAQ
//! recordings) is asked for explicitly.

pub mod arrays;
pub mod common;
pub mod daq;
pub mod image_file;
pub mod mat5;
pub mod signal_file;
pub mod sinks;
pub mod spike_file;
pub mod union;

pub use common::LayoutConfig;
pub use image_file::ImageFileConfig;
pub use signal_file::SignalFileConfig;
pub use sinks::{WriteEstimatesConfig, WriteImagesConfig, WriteSignalsConfig, WriteSpikesConfig};
pub use spike_file::SpikeFileConfig;
