//! `lif`: leaky integrate-and-fire neuron, one per taxel (SPEC.md 2.5).
//!
//! ```text
//! tau dv/dt = -(v - v_rest) + R I
//! if v >= threshold: spike, v <- reset, and v is held at reset for refractory_ms
//! ```
//!
//! Integration is exact for a current held over the step (exponential Euler):
//! `v <- v_inf + (v - v_inf) e^(-dt/tau)` with `v_inf = v_rest + R I`. It is
//! stable for every `dt` and `tau` (the factor lies in (0, 1)), so there is
//! nothing to guard but the current's magnitude (clamped to ±1e12, see
//! [`super`]). A neuron spikes at most once per step; the refractory period is
//! rounded to whole steps (`round(refractory_ms / dt)`, counted from the step
//! after the spike).
//!
//! Units are the model's own: a membrane in units of threshold (`v_rest = 0`,
//! `threshold = 1`, `reset = 0` by default), so the rheobase is
//! `threshold / resistance`. Defaults (`tau_ms = 10`, `resistance = 0.2`,
//! `refractory_ms = 2`) put the rheobase at a current of 5, near the FA-I
//! Izhikevich neuron's (~3.8), and make the default drive's peak current of 20
//! fire at about 30 Hz... see the tests for the measured f-I curve, so the two
//! encoders can be swapped in a pipeline without retuning the drive.

use super::{check_input, lane_inputs, sort_events, InputMode, StepInput, LANES};
use palpate_core::{
    check_positive, check_range, register_stage, BuildContext, ConfigError, InputSpec, Item, Map, Payload,
    PayloadKind, SpikeEvent, SpikeTrain, Stage, StageConfig, StageError, TrialContext,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Leaky integrate-and-fire neuron per taxel: input current to spikes (exact exponential integration).
///
/// `tau dv/dt = -(v - v_rest) + R I`; at `v >= threshold` a spike, `v <- reset`,
/// held for `refractory_ms`.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct LifConfig {
    /// Membrane time constant, ms. Default 10.
    pub tau_ms: f64,
    /// Spike threshold, membrane units. Default 1.
    pub threshold: f64,
    /// Potential after a spike, membrane units. Default 0.
    pub reset: f64,
    /// Resting potential, membrane units. Default 0.
    pub v_rest: f64,
    /// Refractory period after a spike, ms (rounded to whole steps). Default 2.
    pub refractory_ms: f64,
    /// Input resistance (gain from current to membrane), membrane units per current unit. Default 0.2.
    pub resistance: f64,
    /// Integration step, ms. Default 0.5.
    pub dt_ms: f64,
    /// Input sampling between signal samples: `hold` or `linear`. Default `hold`.
    pub input: InputMode,
}

impl Default for LifConfig {
    fn default() -> Self {
        LifConfig {
            tau_ms: 10.0,
            threshold: 1.0,
            reset: 0.0,
            v_rest: 0.0,
            refractory_ms: 2.0,
            resistance: 0.2,
            dt_ms: 0.5,
            input: InputMode::Hold,
        }
    }
}

#[typetag::serde(name = "lif")]
impl StageConfig for LifConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Spikes)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        check_positive("tau_ms", self.tau_ms, "ms")?;
        check_range("dt_ms", self.dt_ms, 1e-4, 10.0, "ms")?;
        check_range("refractory_ms", self.refractory_ms, 0.0, 1e6, "ms")?;
        check_range(
            "resistance",
            self.resistance,
            0.0,
            1e12,
            "membrane units per current unit",
        )?;
        check_range("threshold", self.threshold, -1e6, 1e6, "")?;
        check_range("v_rest", self.v_rest, -1e6, 1e6, "")?;
        check_range("reset", self.reset, -1e6, 1e6, "")?;
        if self.reset >= self.threshold {
            return Err(ConfigError::key(
                "reset",
                format!(
                    "must lie below threshold = {}, got {}",
                    self.threshold, self.reset
                ),
            ));
        }
        Ok(Stage::Map(Box::new(Lif {
            tau_ms: self.tau_ms,
            threshold: self.threshold,
            reset: self.reset,
            v_rest: self.v_rest,
            refractory_steps: (self.refractory_ms / self.dt_ms).round() as u32,
            resistance: self.resistance,
            dt_ms: self.dt_ms,
            input: self.input,
        })))
    }
}
register_stage!("lif", LifConfig);

/// The runtime `lif` encoder.
#[derive(Clone, Debug)]
pub struct Lif {
    /// Membrane time constant, ms.
    pub tau_ms: f64,
    /// Threshold.
    pub threshold: f64,
    /// Reset.
    pub reset: f64,
    /// Rest.
    pub v_rest: f64,
    /// Refractory period, whole steps.
    pub refractory_steps: u32,
    /// Input resistance.
    pub resistance: f64,
    /// Step, ms.
    pub dt_ms: f64,
    /// Input sampling.
    pub input: InputMode,
}

impl Default for Lif {
    fn default() -> Self {
        let c = LifConfig::default();
        Lif {
            tau_ms: c.tau_ms,
            threshold: c.threshold,
            reset: c.reset,
            v_rest: c.v_rest,
            refractory_steps: (c.refractory_ms / c.dt_ms).round() as u32,
            resistance: c.resistance,
            dt_ms: c.dt_ms,
            input: c.input,
        }
    }
}

impl Lif {
    /// Encodes currents `currents[taxel][sample]` at `fs` Hz into time-sorted
    /// spike events. `currents` must be finite (callers check).
    pub fn encode(&self, currents: &[Vec<f64>], fs: f64) -> Vec<SpikeEvent> {
        let n_samples = currents.first().map_or(0, Vec::len);
        let plan = StepInput::new(n_samples, fs, self.dt_ms, self.input);
        let decay = (-self.dt_ms / self.tau_ms).exp();
        let (th, reset, rest, r) = (self.threshold, self.reset, self.v_rest, self.resistance);
        let mut events = Vec::new();
        let zeros = vec![0.0; n_samples];
        for (block, chunk) in currents.chunks(LANES).enumerate() {
            let mut lanes: [&[f64]; LANES] = [&zeros; LANES];
            for (l, xs) in chunk.iter().enumerate() {
                lanes[l] = xs;
            }
            let mut v = [rest; LANES];
            let mut refr = [0u32; LANES];
            for n in 0..plan.n_steps {
                let cur = lane_inputs(&plan, &lanes, n);
                let mut any = false;
                let start = v;
                for l in 0..LANES {
                    let v_inf = rest + r * cur[l];
                    let vn = v_inf + (v[l] - v_inf) * decay;
                    // Refractory: held at reset.
                    let vn = if refr[l] > 0 { reset } else { vn };
                    refr[l] = refr[l].saturating_sub(1);
                    any |= vn >= th;
                    v[l] = vn;
                }
                if any {
                    for l in 0..LANES {
                        if v[l] < th {
                            continue;
                        }
                        let f = (th - start[l]) / (v[l] - start[l]);
                        let frac = if f.is_finite() { f.clamp(0.0, 1.0) } else { 1.0 };
                        v[l] = reset;
                        refr[l] = self.refractory_steps;
                        let t = (n as f64 + frac) * self.dt_ms;
                        if l < chunk.len() && t < plan.duration_ms {
                            events.push(SpikeEvent {
                                taxel: (block * LANES + l) as u32,
                                t_ms: t,
                            });
                        }
                    }
                }
            }
        }
        sort_events(&mut events);
        events
    }
}

impl Map for Lif {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let s = inputs[0].payload.signals()?;
        check_input("lif", s)?;
        let events = self.encode(&s.data, s.sample_rate_hz);
        Ok(SpikeTrain {
            layout: s.layout.clone(),
            duration_ms: s.duration_ms(),
            events,
        }
        .into())
    }
}
