//! Streaming forms of the built-in per-trial stages (see
//! [`palpate_core::stream`] for the block contract): each is registered by
//! its stage type name with [`palpate_core::register_stream!`], beside and
//! independent of the batch stage, whose code it does not touch.
//!
//! | type | streams when | otherwise use |
//! |---|---|---|
//! | `lowpass` | `mode = "causal"` | `mode = "causal"` (zero-phase runs backwards from the trial's end) |
//! | `normalize` | `mode = "causal"` | `mode = "causal"` with a calibrated `span` |
//! | `drive` | a fixed `gain` (or `kind = "direct"`) | `gain = G` from a calibration palpation |
//! | `izhikevich` | `input = "hold"` | `input = "hold"` (linear needs the next sample) |
//! | `lif` | `input = "hold"` | `input = "hold"` (linear needs the next sample) |
//! | `dead_taxels`, `subarea` | always | - |
//! | `jitter` | always (output `B·τ` behind, see [`events`]) | - |
//! | `bin` | always | - |
//! | `wss` | always (model-based) | - |
//! | `ann`, `edbn`, `svm`, `random_forest`, `knn`, `logistic` | `model_in` (a model saved offline) | `model_in = "<file>"` from an offline run with `save_model = true` |
//!
//! Every form gives, concatenated over a trial's blocks, its batch stage's
//! output on the whole trial, bit for bit (WSS: the same answer, scores to
//! 1e-9; the trained estimators with `model_in`: their batch estimate;
//! tested in `stages/tests/stream_blocks.rs` with blocks of 1, 7 and 1000
//! samples).

mod encode;
pub mod events;
mod signal;
mod spikes;
pub mod trained;
mod wss;

use palpate_core::{Payload, Signals, StageError, TaxelLayout};

/// The signals of a block, checked like the batch stage checks a trial
/// (positive rate, one row per taxel, equal lengths, finite samples).
pub(crate) fn block_signals<'a>(what: &str, block: &'a Payload) -> Result<&'a Signals, StageError> {
    let s = block.signals()?;
    crate::signal::check_signals(what, s)?;
    Ok(s)
}

/// Keeps the trial's layout from its first block in `slot`; a later block of
/// another layout is an error naming the stage.
pub(crate) fn same_layout(
    what: &str,
    slot: &mut Option<TaxelLayout>,
    layout: &TaxelLayout,
) -> Result<(), StageError> {
    match slot {
        Some(l) if l != layout => Err(StageError::new(format!(
            "{what}: a block's layout differs from the trial's first block"
        ))),
        Some(_) => Ok(()),
        None => {
            *slot = Some(layout.clone());
            Ok(())
        }
    }
}
