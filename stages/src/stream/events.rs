//! Streaming forms of the spike stages that act event by event:
//! `dead_taxels`, `subarea` and `jitter`.
//!
//! * `dead_taxels` and `subarea` map each event on its own (drop it, or
//!   renumber its taxel) with a per-trial plan (the dead mask, drawn from the
//!   trial's seed; the window's taxel map). Their streaming form runs the
//!   batch stage itself on every block, with the trial's own context, so the
//!   plan and the arithmetic are the batch stage's (a block's output is
//!   time-sorted because its input is, and a tie never spans two blocks: every
//!   upstream stage releases events strictly before its `duration_ms`).
//! * `jitter` moves every event by `δ` drawn from the trial's generator in
//!   event order, as the batch stage draws: the events reach it in the same
//!   order whatever the blocks, so each gets the same `δ` for any block size.
//!   Two things need care. The reflected time `reflect(t + δ, d)` depends on
//!   the trial's duration `d` only when `x = t + δ` lies outside `[0, D)`,
//!   `D` being the time up to which the input is known (`d >= D`): inside, it
//!   is `x` itself, bit for bit; outside, it is computed at the flush, once
//!   `d` is known. And the output must stay time-sorted, so an event is
//!   released only once no later input can land before it: every later input
//!   event has `t >= D` and so lands at or after `D − B·τ`, with `B = 1` for
//!   `uniform` and `B = 14` for `gaussian` (the generator's normal deviates
//!   are bounded: its ziggurat tail draws `|z| < 3.66 + 37.5/3.66 < 14`).
//!   The output therefore runs `B·τ` behind the input (14 ms at `tau_ms = 1`).
//!   An event displaced below 0 (only in the first `B·τ` of a trial) is
//!   reflected at the flush, and holds the events after it until then.

use crate::spikes::jitter::{reflect, Jitter, JitterConfig, JitterKind};
use crate::spikes::{dead::DeadTaxelsConfig, subarea::SubareaConfig};
use palpate_core::stream::{StreamForm, StreamStage, StreamState};
use palpate_core::{
    register_stream, BuildContext, ConfigError, Item, Map, Payload, SpikeEvent, SpikeTrain, Stage,
    StageConfig, StageError, TaxelLayout, TrialContext, TrialMeta,
};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use std::sync::Arc;

/// Bound on `|δ| / τ` of a `gaussian` jitter draw (see the module docs).
pub const GAUSSIAN_BOUND: f64 = 14.0;

/// An event-by-event stage: its batch map, run on every block.
struct PerBlock {
    map: Arc<dyn Map>,
}

fn per_block(cfg: &dyn StageConfig, ctx: &BuildContext) -> Result<StreamForm, ConfigError> {
    match cfg.build(ctx)? {
        Stage::Map(m) => Ok(StreamForm::Streams(Box::new(PerBlock { map: Arc::from(m) }))),
        _ => Err(ConfigError::general("not a per-trial map (internal error)")),
    }
}

fn dead_stream(cfg: &DeadTaxelsConfig, ctx: &BuildContext) -> Result<StreamForm, ConfigError> {
    per_block(cfg, ctx)
}
register_stream!("dead_taxels", DeadTaxelsConfig, dead_stream);

fn subarea_stream(cfg: &SubareaConfig, ctx: &BuildContext) -> Result<StreamForm, ConfigError> {
    per_block(cfg, ctx)
}
register_stream!("subarea", SubareaConfig, subarea_stream);

impl StreamStage for PerBlock {
    fn open(&self, ctx: &TrialContext<'_>) -> Result<Box<dyn StreamState>, StageError> {
        Ok(Box::new(PerBlockState {
            map: self.map.clone(),
            stage_id: ctx.stage_id.to_string(),
            meta: Arc::new(ctx.meta.clone()),
            seed: ctx.seed,
        }))
    }
}

struct PerBlockState {
    map: Arc<dyn Map>,
    stage_id: String,
    meta: Arc<TrialMeta>,
    seed: u64,
}

impl StreamState for PerBlockState {
    fn push(&mut self, block: &Payload, out: &mut Vec<Payload>) -> Result<(), StageError> {
        block.spikes()?;
        let item = Item {
            meta: self.meta.clone(),
            payload: block.clone(),
        };
        let ctx = TrialContext {
            stage_id: &self.stage_id,
            meta: &self.meta,
            seed: self.seed,
        };
        out.push(self.map.process(&[&item], &ctx)?);
        Ok(())
    }

    fn flush(&mut self, _out: &mut Vec<Payload>) -> Result<(), StageError> {
        Ok(())
    }
}

fn jitter_stream(cfg: &JitterConfig, ctx: &BuildContext) -> Result<StreamForm, ConfigError> {
    // The batch stage's checks (`tau_ms`).
    cfg.build(ctx)?;
    let normal = Normal::new(0.0, cfg.tau_ms).map_err(|e| ConfigError::key("tau_ms", e.to_string()))?;
    Ok(StreamForm::Streams(Box::new(JitterStream {
        jitter: Jitter {
            kind: cfg.kind,
            tau_ms: cfg.tau_ms,
        },
        normal,
    })))
}
register_stream!("jitter", JitterConfig, jitter_stream);

struct JitterStream {
    jitter: Jitter,
    normal: Normal<f64>,
}

impl StreamStage for JitterStream {
    fn open(&self, ctx: &TrialContext<'_>) -> Result<Box<dyn StreamState>, StageError> {
        let reach = match self.jitter.kind {
            JitterKind::Gaussian => GAUSSIAN_BOUND * self.jitter.tau_ms,
            JitterKind::Uniform => self.jitter.tau_ms,
        };
        Ok(Box::new(JitterState {
            tau_ms: self.jitter.tau_ms,
            kind: self.jitter.kind,
            normal: self.normal,
            rng: ctx.rng(),
            reach,
            layout: None,
            known_ms: 0.0,
            released_ms: 0.0,
            ready: Vec::new(),
            held: Vec::new(),
            any: false,
        }))
    }
}

struct JitterState {
    tau_ms: f64,
    kind: JitterKind,
    normal: Normal<f64>,
    rng: ChaCha8Rng,
    /// Largest displacement a draw can make, ms.
    reach: f64,
    layout: Option<TaxelLayout>,
    /// `D`: every input event before it is known.
    known_ms: f64,
    /// The `duration_ms` of the last block out.
    released_ms: f64,
    /// Events with their final time, not yet released.
    ready: Vec<SpikeEvent>,
    /// Events whose displaced time `x` lies outside `[0, D)`: reflected once
    /// `D` covers them, or at the flush.
    held: Vec<SpikeEvent>,
    /// Whether the trial had any event (the batch stage then needs a duration).
    any: bool,
}

impl JitterState {
    /// Sorts and emits the ready events before `until`, as a block known up to it.
    fn release(&mut self, until: f64, out: &mut Vec<Payload>) {
        let Some(layout) = &self.layout else { return };
        let mut events: Vec<SpikeEvent> = Vec::new();
        self.ready.retain(|e| {
            let go = e.t_ms < until;
            if go {
                events.push(*e);
            }
            !go
        });
        let until = until.max(self.released_ms);
        if events.is_empty() && until <= self.released_ms {
            return;
        }
        self.released_ms = until;
        let mut train = SpikeTrain {
            layout: layout.clone(),
            duration_ms: until,
            events,
        };
        train.sort();
        out.push(train.into());
    }
}

impl StreamState for JitterState {
    fn push(&mut self, block: &Payload, out: &mut Vec<Payload>) -> Result<(), StageError> {
        let train = block.spikes()?;
        super::same_layout("jitter", &mut self.layout, &train.layout)?;
        if train.duration_ms.is_finite() && train.duration_ms > self.known_ms {
            self.known_ms = train.duration_ms;
        }
        let d = self.known_ms;
        if self.tau_ms == 0.0 {
            // The batch stage returns the train unchanged, without draws.
            out.push(block.clone());
            return Ok(());
        }
        for e in &train.events {
            self.any = true;
            // The batch stage's draw, in event order.
            let delta = match self.kind {
                JitterKind::Gaussian => self.normal.sample(&mut self.rng),
                JitterKind::Uniform => self.rng.random_range(-self.tau_ms..=self.tau_ms),
            };
            let x = e.t_ms + delta;
            let moved = SpikeEvent {
                taxel: e.taxel,
                t_ms: x,
            };
            if (0.0..d).contains(&x) {
                self.ready.push(SpikeEvent {
                    t_ms: reflect(x, d),
                    ..moved
                });
            } else {
                self.held.push(moved);
            }
        }
        // Held events past the end that `D` now covers are final too.
        let mut k = 0;
        while k < self.held.len() {
            let x = self.held[k].t_ms;
            if (0.0..d).contains(&x) {
                let e = self.held.swap_remove(k);
                self.ready.push(SpikeEvent {
                    t_ms: reflect(x, d),
                    ..e
                });
            } else {
                k += 1;
            }
        }
        // No later event lands before `D - reach`, nor before a held event
        // reflected at 0 (about `-x`, to within a few ulps of the duration).
        let mut until = d - self.reach - 1e-9 * d.abs() - 1e-9;
        for e in self.held.iter().filter(|e| e.t_ms < 0.0) {
            until = until.min(-e.t_ms - 1e-6 * (1.0 + e.t_ms.abs()));
        }
        self.release(until, out);
        Ok(())
    }

    fn flush(&mut self, out: &mut Vec<Payload>) -> Result<(), StageError> {
        if self.layout.is_none() || self.tau_ms == 0.0 {
            return Ok(());
        }
        let d = self.known_ms;
        if self.any && !(d.is_finite() && d > 0.0) {
            return Err(StageError::new(format!(
                "jitter: trial has spikes but duration {d} ms; cannot keep times inside it"
            )));
        }
        for e in std::mem::take(&mut self.held) {
            self.ready.push(SpikeEvent {
                t_ms: reflect(e.t_ms, d),
                ..e
            });
        }
        let Some(layout) = &self.layout else { return Ok(()) };
        let mut train = SpikeTrain {
            layout: layout.clone(),
            duration_ms: d,
            events: std::mem::take(&mut self.ready),
        };
        train.sort();
        out.push(train.into());
        Ok(())
    }
}
