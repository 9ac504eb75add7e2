//! Streaming `izhikevich` encoder (zero-order-hold input).
//!
//! Each taxel's neuron keeps its membrane `(v, u)` between blocks. Step `n`
//! (of `dt_ms`) holds sample `⌊n·dt·fs/1000 + 1e-9⌋`, as the batch encoder's
//! step plan does, so when sample `k` arrives every step whose held sample is
//! `k` runs ([`Izhikevich::step`]: one lane of the batch kernel, operation
//! for operation; same spike times, bit for bit). A spike of step `n` lies in
//! `[n·dt, (n+1)·dt]`, so a spike is emitted once every earlier one is known:
//! before the next step's start and before the samples' end. The flush runs
//! the steps up to `⌈duration/dt − 1e-9⌉` and, as the batch encoder, drops
//! spikes at or after the trial's end. `input = "linear"` would need one more
//! sample of look-ahead and is refused (`check --live` names it).

use crate::encode::izhikevich::{Izhikevich, IzhikevichConfig, NeuronState};
use crate::encode::{sort_events, InputMode};
use palpate_core::stream::{StreamForm, StreamStage, StreamState};
use palpate_core::{
    check_range, register_stream, BuildContext, ConfigError, Payload, SpikeEvent, SpikeTrain, StageError,
    TaxelLayout, TrialContext,
};

fn izhikevich_stream(cfg: &IzhikevichConfig, _ctx: &BuildContext) -> Result<StreamForm, ConfigError> {
    if cfg.input != InputMode::Hold {
        return Ok(StreamForm::batch(
            "linear input interpolates towards the next sample, one sample of look-ahead",
            "input = \"hold\"",
        ));
    }
    let params = cfg.params()?;
    check_range("dt_ms", cfg.dt_ms, 1e-4, 10.0, "ms")?;
    if params.a * cfg.dt_ms > 1.0 {
        return Err(ConfigError::key(
            "dt_ms",
            format!("a * dt_ms = {} must be at most 1", params.a * cfg.dt_ms),
        ));
    }
    Ok(StreamForm::Streams(Box::new(IzhikevichStream {
        neuron: Izhikevich {
            params,
            dt_ms: cfg.dt_ms,
            scheme: cfg.scheme,
            input: InputMode::Hold,
        },
    })))
}
register_stream!("izhikevich", IzhikevichConfig, izhikevich_stream);

struct IzhikevichStream {
    neuron: Izhikevich,
}

impl StreamStage for IzhikevichStream {
    fn open(&self, _ctx: &TrialContext<'_>) -> Result<Box<dyn StreamState>, StageError> {
        Ok(Box::new(IzhikevichState {
            neuron: self.neuron.clone(),
            layout: None,
            fs: 0.0,
            states: Vec::new(),
            samples: 0,
            next_step: 0,
            pending: Vec::new(),
            last_cur: Vec::new(),
        }))
    }
}

struct IzhikevichState {
    neuron: Izhikevich,
    layout: Option<TaxelLayout>,
    fs: f64,
    states: Vec<NeuronState>,
    /// Samples so far.
    samples: u64,
    /// The next step to run.
    next_step: u64,
    /// Spikes not yet known to be in order.
    pending: Vec<SpikeEvent>,
    /// The last sample's currents: the steps past the last sample's own (when
    /// `dt` is not a whole number of sample periods) hold it, as the batch
    /// plan's `min(last)` does.
    last_cur: Vec<f64>,
}

impl IzhikevichState {
    /// Runs step `n` of every neuron under `cur[taxel]`.
    fn step(&mut self, n: u64, cur: &[f64]) {
        let dt = self.neuron.dt_ms;
        for (t, s) in self.states.iter_mut().enumerate() {
            if let Some(f) = self.neuron.step(s, cur[t]) {
                self.pending.push(SpikeEvent {
                    taxel: t as u32,
                    t_ms: (n as f64 + f) * dt,
                });
            }
        }
    }

    /// Moves the spikes before `until` ms into a block, sorted (time, taxel).
    fn release(&mut self, until: f64, duration_ms: f64, out: &mut Vec<Payload>) {
        let mut ready: Vec<SpikeEvent> = Vec::new();
        self.pending.retain(|e| {
            if e.t_ms < until {
                ready.push(*e);
                false
            } else {
                true
            }
        });
        sort_events(&mut ready);
        if let Some(layout) = &self.layout {
            out.push(
                SpikeTrain {
                    layout: layout.clone(),
                    duration_ms,
                    events: ready,
                }
                .into(),
            );
        }
    }
}

impl StreamState for IzhikevichState {
    fn push(&mut self, block: &Payload, out: &mut Vec<Payload>) -> Result<(), StageError> {
        let s = super::block_signals("izhikevich", block)?;
        let n = s.n_samples();
        if n == 0 {
            return Ok(());
        }
        match &self.layout {
            Some(l) => {
                if *l != s.layout || self.fs.to_bits() != s.sample_rate_hz.to_bits() {
                    return Err(StageError::new(
                        "izhikevich: a block's rate or layout differs from the trial's first block",
                    ));
                }
            }
            None => {
                if s.layout.len() > u32::MAX as usize {
                    return Err(StageError::new("izhikevich: too many taxels"));
                }
                self.layout = Some(s.layout.clone());
                self.fs = s.sample_rate_hz;
                self.states = vec![self.neuron.initial_state(); s.data.len()];
            }
        }
        let spp = self.neuron.dt_ms * self.fs / 1000.0;
        let mut cur = vec![0.0; s.data.len()];
        for i in 0..n {
            let k = self.samples + i as u64;
            for (c, xs) in cur.iter_mut().zip(&s.data) {
                *c = xs[i];
            }
            // Steps whose held sample is k (the batch plan's index).
            while ((self.next_step as f64 * spp + 1e-9).floor()) <= k as f64 {
                let step = self.next_step;
                self.step(step, &cur);
                self.next_step += 1;
            }
        }
        self.samples += n as u64;
        self.last_cur = cur;
        let known = self.samples as f64 * 1000.0 / self.fs;
        let until = (self.next_step as f64 * self.neuron.dt_ms).min(known);
        self.release(until, until, out);
        Ok(())
    }

    fn flush(&mut self, out: &mut Vec<Payload>) -> Result<(), StageError> {
        if self.layout.is_none() {
            return Ok(());
        }
        let duration = self.samples as f64 * 1000.0 / self.fs;
        let n_steps = (duration / self.neuron.dt_ms - 1e-9).ceil().max(1.0) as u64;
        // The remaining steps hold the last sample (the batch plan's `min(last)`).
        if self.next_step < n_steps {
            let last = std::mem::take(&mut self.last_cur);
            for step in self.next_step..n_steps {
                self.step(step, &last);
            }
            self.next_step = n_steps;
        }
        self.pending.retain(|e| e.t_ms < duration);
        self.release(f64::INFINITY, duration, out);
        Ok(())
    }
}
