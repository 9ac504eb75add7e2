//! Streaming spiking encoders, `izhikevich` and `lif` (zero-order-hold input).
//!
//! Both run the same step plan through [`Neuron`]: each taxel's neuron keeps
//! its membrane (Izhikevich `(v, u)`; LIF `v` and its refractory steps left)
//! between blocks. Step `n`
//! (of `dt_ms`) holds sample `⌊n·dt·fs/1000 + 1e-9⌋`, as the batch encoder's
//! step plan does, so when sample `k` arrives every step whose held sample is
//! `k` runs ([`Izhikevich::step`]: one lane of the batch kernel, operation
//! for operation; same spike times, bit for bit). A spike of step `n` lies in
//! `[n·dt, (n+1)·dt]`, so a spike is emitted once every earlier one is known:
//! before the next step's start and before the samples' end. The flush runs
//! the steps up to `⌈duration/dt − 1e-9⌉` and, as the batch encoder, drops
//! spikes at or after the trial's end. `input = "linear"` would need one more
//! sample of look-ahead and is refused (`check --live` names it).
//!
//! The LIF step is the batch lane loop's arithmetic on one lane (see
//! [`LifNeuron::step`]): `v_inf = v_rest + R·I`, `v ← v_inf + (v − v_inf)·e^(−dt/τ)`,
//! held at `reset` while refractory steps remain; a crossing spikes at the
//! linear interpolation `(θ − v_start)/(v − v_start)` of the step.

use crate::encode::izhikevich::{Izhikevich, IzhikevichConfig, NeuronState};
use crate::encode::lif::{Lif, LifConfig};
use crate::encode::{fmax, sort_events, InputMode, MAX_CURRENT};
use palpate_core::stream::{StreamForm, StreamStage, StreamState};
use palpate_core::{
    check_range, register_stream, BuildContext, ConfigError, Payload, SpikeEvent, SpikeTrain, StageConfig,
    StageError, TaxelLayout, TrialContext,
};

/// A neuron model stepped one `dt` at a time, as its batch encoder steps it.
pub(crate) trait Neuron: Clone + Send + Sync + 'static {
    /// One neuron's state between steps.
    type State: Clone + Send;
    /// The stage type, for messages.
    const NAME: &'static str;
    /// Integration step, ms.
    fn dt_ms(&self) -> f64;
    /// The state at rest.
    fn initial(&self) -> Self::State;
    /// One step under current `i`; `Some(f)` for a spike at `f` of the step.
    fn step(&self, s: &mut Self::State, i: f64) -> Option<f64>;
}

impl Neuron for Izhikevich {
    type State = NeuronState;
    const NAME: &'static str = "izhikevich";
    fn dt_ms(&self) -> f64 {
        self.dt_ms
    }
    fn initial(&self) -> NeuronState {
        self.initial_state()
    }
    fn step(&self, s: &mut NeuronState, i: f64) -> Option<f64> {
        Izhikevich::step(self, s, i)
    }
}

/// The LIF encoder as a [`Neuron`] (its decay factor computed once, as the
/// batch kernel does per block).
#[derive(Clone, Debug)]
pub(crate) struct LifNeuron {
    lif: Lif,
    decay: f64,
}

/// A LIF membrane and its refractory steps left (an `f64`, as in the batch
/// kernel's lanes).
#[derive(Clone, Copy, Debug)]
pub(crate) struct LifState {
    v: f64,
    refr: f64,
}

impl Neuron for LifNeuron {
    type State = LifState;
    const NAME: &'static str = "lif";
    fn dt_ms(&self) -> f64 {
        self.lif.dt_ms
    }
    fn initial(&self) -> LifState {
        LifState {
            v: self.lif.v_rest,
            refr: 0.0,
        }
    }
    /// One lane of `Lif::run_block`, operation for operation.
    fn step(&self, s: &mut LifState, i: f64) -> Option<f64> {
        let l = &self.lif;
        let cur = i.clamp(-MAX_CURRENT, MAX_CURRENT);
        let start = s.v;
        let v_inf = l.v_rest + l.resistance * cur;
        let vn = v_inf + (s.v - v_inf) * self.decay;
        let vn = if s.refr > 0.5 { l.reset } else { vn };
        s.refr = fmax(s.refr - 1.0, 0.0);
        s.v = vn;
        if vn < l.threshold {
            return None;
        }
        let f = (l.threshold - start) / (vn - start);
        s.v = l.reset;
        s.refr = l.refractory_steps as f64;
        Some(if f.is_finite() { f.clamp(0.0, 1.0) } else { 1.0 })
    }
}

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
    Ok(StreamForm::Streams(Box::new(EncoderStream {
        neuron: Izhikevich {
            params,
            dt_ms: cfg.dt_ms,
            scheme: cfg.scheme,
            input: InputMode::Hold,
        },
    })))
}
register_stream!("izhikevich", IzhikevichConfig, izhikevich_stream);

fn lif_stream(cfg: &LifConfig, ctx: &BuildContext) -> Result<StreamForm, ConfigError> {
    if cfg.input != InputMode::Hold {
        return Ok(StreamForm::batch(
            "linear input interpolates towards the next sample, one sample of look-ahead",
            "input = \"hold\"",
        ));
    }
    // The batch stage's checks, every key named.
    cfg.build(ctx)?;
    let lif = Lif {
        tau_ms: cfg.tau_ms,
        threshold: cfg.threshold,
        reset: cfg.reset,
        v_rest: cfg.v_rest,
        refractory_steps: (cfg.refractory_ms / cfg.dt_ms).round() as u32,
        resistance: cfg.resistance,
        dt_ms: cfg.dt_ms,
        input: InputMode::Hold,
    };
    Ok(StreamForm::Streams(Box::new(EncoderStream {
        neuron: LifNeuron {
            decay: (-lif.dt_ms / lif.tau_ms).exp(),
            lif,
        },
    })))
}
register_stream!("lif", LifConfig, lif_stream);

struct EncoderStream<N: Neuron> {
    neuron: N,
}

impl<N: Neuron> StreamStage for EncoderStream<N> {
    fn open(&self, _ctx: &TrialContext<'_>) -> Result<Box<dyn StreamState>, StageError> {
        Ok(Box::new(EncoderState {
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

struct EncoderState<N: Neuron> {
    neuron: N,
    layout: Option<TaxelLayout>,
    fs: f64,
    states: Vec<N::State>,
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

impl<N: Neuron> EncoderState<N> {
    /// Runs step `n` of every neuron under `cur[taxel]`.
    fn step(&mut self, n: u64, cur: &[f64]) {
        let dt = self.neuron.dt_ms();
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

impl<N: Neuron> StreamState for EncoderState<N> {
    fn push(&mut self, block: &Payload, out: &mut Vec<Payload>) -> Result<(), StageError> {
        let s = super::block_signals(N::NAME, block)?;
        let n = s.n_samples();
        if n == 0 {
            return Ok(());
        }
        match &self.layout {
            Some(l) => {
                if *l != s.layout || self.fs.to_bits() != s.sample_rate_hz.to_bits() {
                    return Err(StageError::new(format!(
                        "{}: a block's rate or layout differs from the trial's first block",
                        N::NAME
                    )));
                }
            }
            None => {
                if s.layout.len() > u32::MAX as usize {
                    return Err(StageError::new(format!("{}: too many taxels", N::NAME)));
                }
                self.layout = Some(s.layout.clone());
                self.fs = s.sample_rate_hz;
                self.states = vec![self.neuron.initial(); s.data.len()];
            }
        }
        // The whole trial so far within the batch encoder's cap: a stream at
        // an absurd rate would otherwise run billions of steps per block.
        crate::encode::check_steps(
            N::NAME,
            self.samples + n as u64,
            self.fs,
            s.data.len(),
            self.neuron.dt_ms(),
        )?;
        let spp = self.neuron.dt_ms() * self.fs / 1000.0;
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
        let until = (self.next_step as f64 * self.neuron.dt_ms()).min(known);
        self.release(until, until, out);
        Ok(())
    }

    fn flush(&mut self, out: &mut Vec<Payload>) -> Result<(), StageError> {
        if self.layout.is_none() {
            return Ok(());
        }
        let duration = self.samples as f64 * 1000.0 / self.fs;
        let n_steps = (duration / self.neuron.dt_ms() - 1e-9).ceil().max(1.0) as u64;
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
