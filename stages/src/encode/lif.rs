//! `lif`: leaky integrate-and-fire neuron, one per taxel.
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
//! `threshold / resistance`. Defaults (`tau_ms = 25`, `resistance = 0.25`,
//! `refractory_ms = 2`) are matched to the FA-I Izhikevich neuron so the two
//! encoders can be swapped without retuning the drive: rheobase 4 (Izhikevich
//! FA-I: ~3.78), and at the default drive's peak current of 20 the analytic
//! period `refractory + tau ln(v_inf / (v_inf - threshold))` = 2 + 25 ln 1.25
//! = 7.6 ms, about 130 Hz (Izhikevich FA-I at 20: ~120 Hz); at 10, ~70 Hz
//! (Izhikevich: ~50 Hz). Tested below.

use super::{block_input, check_input_shape, fmax, sort_events, tiled, InputMode, StepInput, LANES};
use palpate_core::{
    check_positive, check_range, register_stage, BuildContext, ConfigChecks, ConfigError, InputSpec, Item,
    Map, Payload, PayloadKind, SpikeEvent, SpikeTrain, Stage, StageConfig, StageError, TrialContext,
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
    /// Membrane time constant, ms. Default 25.
    pub tau_ms: f64,
    /// Spike threshold, membrane units. Default 1.
    pub threshold: f64,
    /// Potential after a spike, membrane units. Default 0.
    pub reset: f64,
    /// Resting potential, membrane units. Default 0.
    pub v_rest: f64,
    /// Refractory period after a spike, ms (rounded to whole steps). Default 2.
    pub refractory_ms: f64,
    /// Input resistance (gain from current to membrane), membrane units per current unit. Default 0.25.
    pub resistance: f64,
    /// Integration step, ms. Default 0.5.
    pub dt_ms: f64,
    /// Input sampling between signal samples: `hold` or `linear`. Default `hold`.
    pub input: InputMode,
}

impl Default for LifConfig {
    fn default() -> Self {
        LifConfig {
            tau_ms: 25.0,
            threshold: 1.0,
            reset: 0.0,
            v_rest: 0.0,
            refractory_ms: 2.0,
            resistance: 0.25,
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
        let mut c = ConfigChecks::new();
        c.take(check_positive("tau_ms", self.tau_ms, "ms"));
        c.take(check_range("dt_ms", self.dt_ms, 1e-4, 10.0, "ms"));
        c.take(check_range("refractory_ms", self.refractory_ms, 0.0, 1e6, "ms"));
        c.take(check_range(
            "resistance",
            self.resistance,
            0.0,
            1e12,
            "membrane units per current unit",
        ));
        let threshold = c.take(check_range("threshold", self.threshold, -1e6, 1e6, ""));
        c.take(check_range("v_rest", self.v_rest, -1e6, 1e6, ""));
        let reset = c.take(check_range("reset", self.reset, -1e6, 1e6, ""));
        if threshold.is_some() && reset.is_some() && self.reset >= self.threshold {
            c.push(ConfigError::key(
                "reset",
                format!(
                    "must lie below threshold = {}, got {}",
                    palpate_core::fmt_num(self.threshold),
                    palpate_core::fmt_num(self.reset)
                ),
            ));
        }
        c.finish()?;
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
        self.encode_finite(currents, fs).0
    }

    /// [`Lif::encode`], also telling whether every current was finite
    /// (noted while the input is transposed).
    fn encode_finite(&self, currents: &[Vec<f64>], fs: f64) -> (Vec<SpikeEvent>, bool) {
        let mut finite = true;
        let n_samples = currents.first().map_or(0, Vec::len);
        let plan = StepInput::new(n_samples, fs, self.dt_ms, self.input);
        let mut events = Vec::new();
        // One reused buffer per thread (see `with_scratch`); the lanes in
        // 256-bit vectors where the CPU has them (no FMA: the same bits).
        crate::wide::with_scratch(|data| {
            for (block, chunk) in currents.chunks(LANES).enumerate() {
                let first = (block * LANES) as u32;
                let ev = &mut events;
                let mut state = ([self.v_rest; LANES], [0.0f64; LANES]);
                finite &= tiled(chunk, n_samples, &plan, data, |data, steps, off| {
                    let at = (steps, off, chunk.len(), first);
                    state = crate::wide::with_avx2(
                        #[inline(always)]
                        || match self.input {
                            InputMode::Hold => self.run_block::<false>(&plan, data, state, at, ev),
                            InputMode::Linear => self.run_block::<true>(&plan, data, state, at, ev),
                        },
                    );
                });
            }
        });
        sort_events(&mut events);
        (events, finite)
    }

    /// Integrates one block of lanes over the steps `steps` from the state
    /// `(v, refractory steps left)`, `data[0]` holding sample `off` (one
    /// tile of [`super::tiled`]); inlined into the wide function.
    #[inline(always)]
    fn run_block<const LINEAR: bool>(
        &self,
        plan: &StepInput,
        data: &[[f64; LANES]],
        (mut v, mut refr): ([f64; LANES], [f64; LANES]),
        (steps, off, live, first_taxel): (std::ops::Range<usize>, usize, usize, u32),
        events: &mut Vec<SpikeEvent>,
    ) -> ([f64; LANES], [f64; LANES]) {
        let decay = (-self.dt_ms / self.tau_ms).exp();
        let (th, reset, rest, r) = (self.threshold, self.reset, self.v_rest, self.resistance);
        // Refractory steps left are f64 so the lane loop stays one SIMD type.
        let refr_steps = self.refractory_steps as f64;
        let s0 = steps.start;
        for (n, &i) in plan.idx[steps].iter().enumerate() {
            let n = s0 + n;
            let cur = block_input::<LINEAR>(data, plan, n, i as usize - off);
            let start = v;
            let mut any = false;
            for l in 0..LANES {
                let v_inf = rest + r * cur[l];
                let vn = v_inf + (v[l] - v_inf) * decay;
                // Refractory: held at reset.
                let vn = if refr[l] > 0.5 { reset } else { vn };
                refr[l] = fmax(refr[l] - 1.0, 0.0);
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
                    refr[l] = refr_steps;
                    let t = (n as f64 + frac) * self.dt_ms;
                    if l < live && t < plan.duration_ms {
                        events.push(SpikeEvent {
                            taxel: first_taxel + l as u32,
                            t_ms: t,
                        });
                    }
                }
            }
        }
        (v, refr)
    }
}

impl Map for Lif {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let s = inputs[0].payload.signals()?;
        check_input_shape("lif", s, self.dt_ms)?;
        let (events, finite) = self.encode_finite(&s.data, s.sample_rate_hz);
        if !finite {
            return Err(crate::signal::non_finite_error("lif", s));
        }
        Ok(SpikeTrain {
            layout: s.layout.clone(),
            duration_ms: s.duration_ms(),
            events,
        }
        .into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn rate(l: &Lif, i: f64) -> f64 {
        // Spikes per second over the second half of 2 s of constant current.
        let ev = l.encode(&[vec![i; 2000]], 1000.0);
        ev.iter().filter(|e| e.t_ms >= 1000.0).count() as f64
    }

    #[test]
    fn rheobase_is_threshold_over_resistance() {
        let l = Lif::default();
        assert_eq!(rate(&l, 3.99), 0.0);
        assert!(rate(&l, 4.1) > 0.0);
        assert!(l.encode(&[vec![0.0; 1000]], 1000.0).is_empty());
    }

    #[test]
    fn rate_matches_the_analytic_period() {
        let l = Lif::default();
        for i in [5.0f64, 10.0, 20.0, 40.0] {
            let v_inf = 0.25 * i;
            let period = 2.0 + 25.0 * (v_inf / (v_inf - 1.0)).ln();
            let expect = 1000.0 / period;
            let got = rate(&l, i);
            // Refractory rounding and reset timing cost at most a step per spike.
            assert!(
                (got - expect).abs() <= 0.1 * expect + 2.0,
                "I={i}: {got} vs {expect}"
            );
        }
        assert!(rate(&l, 20.0) > 110.0 && rate(&l, 20.0) < 150.0);
    }

    #[test]
    fn refractory_caps_the_rate_and_huge_currents_fire_once_per_step() {
        let l = Lif::default();
        // 2 ms refractory at dt 0.5: at most one spike per 5 steps.
        assert!(rate(&l, 1e9) <= 400.0 + 1.0);
        let no_refr = Lif {
            refractory_steps: 0,
            ..Lif::default()
        };
        let ev = no_refr.encode(&[vec![1e6; 100], vec![-1e300; 100]], 1000.0);
        assert_eq!(ev.len(), 200); // every step of taxel 0, never taxel 1
        assert!(ev.iter().all(|e| e.taxel == 0));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        #[test]
        fn never_nan_and_at_most_one_spike_per_step(
            segs in proptest::collection::vec((-1.0f64..6.0, 1usize..40), 1..8),
            dt in 0.01f64..2.0,
            tau in 0.1f64..100.0,
            refr in 0.0f64..5.0,
        ) {
            let mut xs = Vec::new();
            for (lg, len) in segs {
                let i = if lg < 0.0 { 0.0 } else { 10f64.powf(lg) };
                xs.extend(std::iter::repeat_n(i, len));
            }
            let l = Lif { dt_ms: dt, tau_ms: tau, refractory_steps: (refr / dt).round() as u32, ..Lif::default() };
            let dur = xs.len() as f64;
            let ev = l.encode(&[xs], 1000.0);
            prop_assert!(ev.len() <= (dur / dt - 1e-9).ceil() as usize);
            for e in &ev {
                prop_assert!(e.t_ms.is_finite() && e.t_ms >= 0.0 && e.t_ms < dur);
            }
            for w in ev.windows(3) {
                prop_assert!(w[2].t_ms - w[0].t_ms > dt * (1.0 - 1e-9));
            }
        }
    }
}
