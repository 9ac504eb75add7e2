//! `adaptive_lif`: a leaky integrate-and-fire encoder with a spike-triggered
//! adaptive threshold, a simple model of a mechanoreceptor whose firing fades
//! under sustained drive.
//!
//! Per taxel, with input current `I(t)` (held constant over each step):
//!
//! ```text
//! tau_m dV/dt = -(V - v_rest) + gain * I          membrane
//! tau_a dA/dt = -A                                 threshold adaptation
//! spike when V >= theta0 + A:  V <- v_reset,  A <- A + delta_theta,
//!                              then no spike for refractory_ms
//! ```
//!
//! Both linear equations are integrated exactly over a step `dt` (an exponential
//! integrator): `V <- V_inf + (V - V_inf) exp(-dt/tau_m)` with
//! `V_inf = v_rest + gain*I`, and `A <- A exp(-dt/tau_a)`. Exact integration is
//! stable for any `dt`, and at most one spike is emitted per step by
//! construction. Units: `V`, `theta0`, `delta_theta` are dimensionless
//! (threshold units); `gain` is threshold units per unit of input current.

use palpate_core::{
    check_positive, register_stage, BuildContext, ConfigError, InputSpec, Item, Map, Payload, PayloadKind,
    SpikeEvent, SpikeTrain, Stage, StageConfig, StageError, TrialContext,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Leaky integrate-and-fire encoder with an adaptive threshold (plugin example).
///
/// Takes the input current (e.g. from a `drive` stage) and gives spike events.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct AdaptiveLifConfig {
    /// Membrane time constant, ms. Default 10.
    pub tau_m_ms: f64,
    /// Input gain, threshold units per unit current. Default 0.1.
    pub gain: f64,
    /// Resting potential, threshold units. Default 0.
    pub v_rest: f64,
    /// Reset potential after a spike, threshold units. Default 0.
    pub v_reset: f64,
    /// Baseline threshold, threshold units. Default 1.
    pub theta0: f64,
    /// Threshold increase per spike, threshold units. Default 0.5.
    pub delta_theta: f64,
    /// Time constant of the threshold's return to baseline, ms. Default 100.
    pub tau_a_ms: f64,
    /// Absolute refractory period, ms. Default 1.
    pub refractory_ms: f64,
    /// Integration step, ms. Default 0.5.
    pub dt_ms: f64,
}

impl Default for AdaptiveLifConfig {
    fn default() -> Self {
        AdaptiveLifConfig {
            tau_m_ms: 10.0,
            gain: 0.1,
            v_rest: 0.0,
            v_reset: 0.0,
            theta0: 1.0,
            delta_theta: 0.5,
            tau_a_ms: 100.0,
            refractory_ms: 1.0,
            dt_ms: 0.5,
        }
    }
}

#[typetag::serde(name = "adaptive_lif")]
impl StageConfig for AdaptiveLifConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Spikes)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        check_positive("tau_m_ms", self.tau_m_ms, "ms")?;
        check_positive("tau_a_ms", self.tau_a_ms, "ms")?;
        check_positive("dt_ms", self.dt_ms, "ms")?;
        for (key, v) in [
            ("gain", self.gain),
            ("v_rest", self.v_rest),
            ("v_reset", self.v_reset),
            ("delta_theta", self.delta_theta),
            ("refractory_ms", self.refractory_ms),
        ] {
            if !v.is_finite() {
                return Err(ConfigError::key(key, format!("must be a finite number, got {v}")));
            }
        }
        if self.delta_theta < 0.0 || self.refractory_ms < 0.0 {
            return Err(ConfigError::key(
                if self.delta_theta < 0.0 {
                    "delta_theta"
                } else {
                    "refractory_ms"
                },
                "must not be negative",
            ));
        }
        if !(self.theta0.is_finite() && self.theta0 > self.v_reset) {
            return Err(ConfigError::key(
                "theta0",
                "must be finite and above v_reset, or the neuron fires forever",
            ));
        }
        Ok(Stage::Map(Box::new(self.clone())))
    }
}
register_stage!("adaptive_lif", AdaptiveLifConfig);

impl AdaptiveLifConfig {
    /// Encodes one taxel's current, sampled every `sample_ms`, into spike times (ms).
    pub fn encode(&self, current: &[f64], sample_ms: f64) -> Vec<f64> {
        let duration = current.len() as f64 * sample_ms;
        let steps = (duration / self.dt_ms).floor() as usize;
        let decay_m = (-self.dt_ms / self.tau_m_ms).exp();
        let decay_a = (-self.dt_ms / self.tau_a_ms).exp();
        let (mut v, mut a, mut refractory_until) = (self.v_rest, 0.0_f64, f64::NEG_INFINITY);
        let mut spikes = Vec::new();
        for k in 0..steps {
            let t = k as f64 * self.dt_ms;
            let i = current[((t / sample_ms) as usize).min(current.len() - 1)];
            let v_inf = self.v_rest + self.gain * i;
            v = v_inf + (v - v_inf) * decay_m;
            a *= decay_a;
            let t_end = t + self.dt_ms;
            if v >= self.theta0 + a && t_end > refractory_until {
                spikes.push(t_end.min(duration - 1e-9).max(0.0));
                v = self.v_reset;
                a += self.delta_theta;
                refractory_until = t_end + self.refractory_ms;
            } else if t_end <= refractory_until {
                v = self.v_reset;
            }
        }
        spikes
    }
}

impl Map for AdaptiveLifConfig {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let s = inputs[0].payload.signals()?;
        let sample_ms = 1000.0 / s.sample_rate_hz;
        let mut events = Vec::new();
        for (taxel, ch) in s.data.iter().enumerate() {
            if let Some(k) = ch.iter().position(|x| !x.is_finite()) {
                return Err(StageError::new(format!(
                    "taxel {taxel}, sample {k}: the input current is {}",
                    ch[k]
                )));
            }
            if ch.is_empty() {
                continue;
            }
            events.extend(self.encode(ch, sample_ms).into_iter().map(|t_ms| SpikeEvent {
                taxel: taxel as u32,
                t_ms,
            }));
        }
        let mut train = SpikeTrain {
            layout: s.layout.clone(),
            duration_ms: s.duration_ms(),
            events,
        };
        train.sort();
        Ok(train.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn adaptation_slows_firing_under_constant_drive() {
        let c = AdaptiveLifConfig::default();
        let spikes = c.encode(&vec![30.0; 2000], 1.0);
        assert!(spikes.len() > 10, "{}", spikes.len());
        let first: Vec<f64> = spikes.windows(2).take(3).map(|w| w[1] - w[0]).collect();
        let last: Vec<f64> = spikes.windows(2).rev().take(3).map(|w| w[1] - w[0]).collect();
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        assert!(
            mean(&last) > 1.5 * mean(&first),
            "first ISIs {first:?}, last {last:?}"
        );
        // Without adaptation the rate stays constant.
        let flat = AdaptiveLifConfig {
            delta_theta: 0.0,
            ..c.clone()
        }
        .encode(&vec![30.0; 2000], 1.0);
        let isi: Vec<f64> = flat.windows(2).map(|w| w[1] - w[0]).collect();
        assert!(isi.iter().all(|d| (d - isi[0]).abs() < 1e-9), "{isi:?}");
    }

    #[test]
    fn below_threshold_never_fires() {
        let c = AdaptiveLifConfig::default();
        // V_inf = gain * I = 0.9 < theta0 = 1.
        assert!(c.encode(&vec![9.0; 5000], 1.0).is_empty());
        assert!(c.encode(&vec![0.0; 100], 1.0).is_empty());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn stable_for_any_current_and_step(i in 0.0f64..1e6, dt in 0.01f64..2.0) {
            let c = AdaptiveLifConfig { dt_ms: dt, ..AdaptiveLifConfig::default() };
            let spikes = c.encode(&vec![i; 200], 1.0);
            let steps = (200.0 / dt).floor() as usize;
            prop_assert!(spikes.len() <= steps);
            prop_assert!(spikes.iter().all(|t| t.is_finite() && *t >= 0.0 && *t < 200.0));
            prop_assert!(spikes.windows(2).all(|w| w[1] - w[0] >= dt.min(c.refractory_ms + dt) - 1e-9));
        }
    }
}
