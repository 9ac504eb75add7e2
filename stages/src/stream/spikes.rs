//! Streaming `bin`: spike images as spikes arrive.
//!
//! Frame `j` counts the spikes in `[j·hop, j·hop + window)` ms (the batch
//! stage's definition, with its exact membership test) and is emitted once
//! every spike before its end is known (a spikes block's `duration_ms`). The
//! flush emits the frames that run past the trial's end, up to the batch
//! stage's `max(⌈duration/hop⌉, 1)`, with what they cover. At most
//! `window/hop + 2` frames are open at once, whatever the trial's length.

use crate::spikes::bin::{BinConfig, Binner};
use palpate_core::stream::{StreamForm, StreamStage, StreamState};
use palpate_core::{
    check_positive, register_stream, BuildContext, ConfigError, Payload, SpikeImages, StageError,
    TaxelLayout, TrialContext,
};
use std::collections::VecDeque;

/// Most frames one trial may have (2^26: 7.8 days at a 10 ms hop), so a
/// hostile `duration_ms` is an error, not an allocation of its size.
pub const MAX_FRAMES: usize = 1 << 26;

fn too_many(duration_ms: f64) -> StageError {
    StageError::new(format!(
        "bin: a spikes block says {duration_ms} ms, more than {MAX_FRAMES} frames"
    ))
}

fn bin_stream(cfg: &BinConfig, _ctx: &BuildContext) -> Result<StreamForm, ConfigError> {
    check_positive("window_ms", cfg.window_ms, "ms")?;
    check_positive("hop_ms", cfg.hop_ms, "ms")?;
    Ok(StreamForm::Streams(Box::new(BinStream {
        binner: Binner::new(cfg.window_ms, cfg.hop_ms),
    })))
}
register_stream!("bin", BinConfig, bin_stream);

struct BinStream {
    binner: Binner,
}

impl StreamStage for BinStream {
    fn open(&self, _ctx: &TrialContext<'_>) -> Result<Box<dyn StreamState>, StageError> {
        Ok(Box::new(BinState {
            binner: self.binner.clone(),
            layout: None,
            next: 0,
            open: VecDeque::new(),
            duration_ms: 0.0,
        }))
    }
}

struct BinState {
    binner: Binner,
    layout: Option<TaxelLayout>,
    /// Index of the first open frame (every earlier one is emitted).
    next: usize,
    /// Counts of frames `next..`, one row per taxel each.
    open: VecDeque<Vec<f64>>,
    /// Time up to which every spike is known.
    duration_ms: f64,
}

impl BinState {
    /// Emits frames `next..end` as one block (nothing when empty).
    fn emit(&mut self, end: usize, out: &mut Vec<Payload>) {
        let Some(layout) = &self.layout else { return };
        let n = layout.len();
        if end <= self.next {
            return;
        }
        let k = end - self.next;
        let mut counts = Vec::with_capacity(k * n);
        for _ in 0..k {
            match self.open.pop_front() {
                Some(f) => counts.extend_from_slice(&f),
                None => counts.extend(std::iter::repeat_n(0.0, n)),
            }
        }
        self.next = end;
        out.push(
            SpikeImages {
                layout: layout.clone(),
                window_ms: self.binner.window_ms,
                hop_ms: self.binner.hop_ms,
                n_frames: k,
                counts,
            }
            .into(),
        );
    }
}

impl StreamState for BinState {
    fn push(&mut self, block: &Payload, out: &mut Vec<Payload>) -> Result<(), StageError> {
        let train = block.spikes()?;
        super::same_layout("bin", &mut self.layout, &train.layout)?;
        let n_taxels = train.layout.len();
        let (window, hop) = (self.binner.window_ms, self.binner.hop_ms);
        for e in &train.events {
            let taxel = e.taxel as usize;
            if taxel >= n_taxels {
                return Err(StageError::new(format!(
                    "bin: spike of taxel {taxel} at {} ms, but the layout has {n_taxels} taxels",
                    e.t_ms
                )));
            }
            if !e.t_ms.is_finite() {
                return Err(StageError::new(format!(
                    "bin: spike of taxel {taxel} has time {}",
                    e.t_ms
                )));
            }
            let lo = ((e.t_ms - window) / hop).floor().max(0.0) as usize;
            let hi = ((e.t_ms / hop).floor() + 1.0).max(0.0) as usize;
            // Spikes before an emitted frame's end cannot arrive (the
            // upstream block's `duration_ms` promised them all).
            for k in lo.max(self.next)..hi {
                let start = k as f64 * hop;
                if start <= e.t_ms && e.t_ms < start + window {
                    // Open frames grow only to the spike's frame: at most window/hop + 1.
                    let idx = k - self.next;
                    while self.open.len() <= idx {
                        self.open.push_back(vec![0.0; n_taxels]);
                    }
                    self.open[idx][taxel] += 1.0;
                }
            }
        }
        if train.duration_ms.is_finite() && train.duration_ms > self.duration_ms {
            self.duration_ms = train.duration_ms;
        }
        // Frames whose end is known: j·hop + window <= duration (found from
        // the closed form, then corrected for rounding: no per-frame loop on
        // a hostile duration).
        let d = self.duration_ms;
        let mut end = if d >= window {
            (((d - window) / hop).floor() + 1.0).min(MAX_FRAMES as f64) as usize
        } else {
            0
        };
        while end > 0 && (end - 1) as f64 * hop + window > d {
            end -= 1;
        }
        while end < MAX_FRAMES && end as f64 * hop + window <= d {
            end += 1;
        }
        if end >= MAX_FRAMES {
            return Err(too_many(d));
        }
        self.emit(end.max(self.next), out);
        Ok(())
    }

    fn flush(&mut self, out: &mut Vec<Payload>) -> Result<(), StageError> {
        if self.layout.is_none() {
            return Ok(());
        }
        let n_frames = self.binner.n_frames(self.duration_ms);
        if n_frames >= MAX_FRAMES {
            return Err(too_many(self.duration_ms));
        }
        self.emit(n_frames, out);
        Ok(())
    }
}
