//! `jitter`: spike-time noise (paper section 3.4, Fig. 8).
//!
//! Every spike is displaced independently: `t' = t + δ` with `δ ~ N(0, τ²)`
//! (`kind = "gaussian"`: τ is the standard deviation) or `δ ~ U[-τ, τ]`
//! (`kind = "uniform"`: "randomly displaced by up to τ ms", the paper's wording).
//! τ = 0 leaves the train unchanged.
//!
//! Times stay inside the trial `[0, duration)` by reflection at its ends
//! (`-t` below 0, `2·duration - t` above; repeated for displacements longer
//! than the trial). Reflection rather than clamping keeps the displaced times
//! spread near the ends instead of piling them on the boundary, and unlike
//! dropping or redrawing it never loses a spike or biases the draw. The events
//! are sorted again afterwards (time, then taxel). No spike is lost or
//! duplicated: the output holds exactly the input's events per taxel.
//!
//! Randomness comes from the stage's per-trial generator (`ctx.rng()`), drawn in
//! event order, so the result is a pure function of (config, trial, seed).

use palpate_core::{
    check_range, register_stage, BuildContext, ConfigError, InputSpec, Item, Map, Payload, PayloadKind,
    SpikeTrain, Stage, StageConfig, StageError, TrialContext,
};
use rand::Rng;
use rand_distr::{Distribution, Normal};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Shape of the displacement.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum JitterKind {
    /// Normal with standard deviation `tau_ms`.
    #[default]
    Gaussian,
    /// Uniform on `[-tau_ms, tau_ms]`.
    Uniform,
}

/// Spike-time noise (paper Fig. 8): every spike moves by an independent random displacement.
///
/// Gaussian (SD `tau_ms`) or uniform on [-tau_ms, tau_ms]; times are reflected
/// into [0, duration) and re-sorted; no spike is lost or duplicated.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct JitterConfig {
    /// `gaussian` (tau_ms = SD) or `uniform` (on [-tau_ms, tau_ms]). Default `gaussian`.
    pub kind: JitterKind,
    /// Width of the displacement, ms (>= 0). Default 1.
    pub tau_ms: f64,
}

impl Default for JitterConfig {
    fn default() -> Self {
        JitterConfig {
            kind: JitterKind::Gaussian,
            tau_ms: 1.0,
        }
    }
}

#[typetag::serde(name = "jitter")]
impl StageConfig for JitterConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Spikes)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Spikes)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        check_range("tau_ms", self.tau_ms, 0.0, 1e9, "ms")?;
        Ok(Stage::Map(Box::new(Jitter {
            kind: self.kind,
            tau_ms: self.tau_ms,
        })))
    }
}
register_stage!("jitter", JitterConfig);

/// The runtime `jitter` stage.
#[derive(Clone, Debug)]
pub struct Jitter {
    /// Shape.
    pub kind: JitterKind,
    /// Width, ms.
    pub tau_ms: f64,
}

/// Folds `t` into `[0, d)` by reflection at 0 and `d`.
pub fn reflect(t: f64, d: f64) -> f64 {
    if d.is_nan() || d <= 0.0 {
        return 0.0;
    }
    // Period 2d: [0, d) maps to itself, [d, 2d) mirrors.
    let p = 2.0 * d;
    let mut x = t.rem_euclid(p);
    if x >= d {
        x = p - x;
    }
    // `p - x` can equal d exactly when x == d; keep the interval half-open.
    if x >= d {
        x = prev_down(d);
    }
    x.max(0.0)
}

/// The largest double below a positive `d`.
fn prev_down(d: f64) -> f64 {
    f64::from_bits(d.to_bits() - 1)
}

impl Jitter {
    /// Jitters one trial with `rng`.
    pub fn apply<R: Rng>(&self, train: &SpikeTrain, rng: &mut R) -> Result<SpikeTrain, StageError> {
        let mut out = train.clone();
        if self.tau_ms == 0.0 || out.events.is_empty() {
            return Ok(out);
        }
        let d = train.duration_ms;
        if !(d.is_finite() && d > 0.0) {
            return Err(StageError::new(format!(
                "jitter: trial has spikes but duration {d} ms; cannot keep times inside it"
            )));
        }
        match self.kind {
            JitterKind::Gaussian => {
                let normal = Normal::new(0.0, self.tau_ms)
                    .map_err(|e| StageError::new(format!("jitter: key `tau_ms`: {e}")))?;
                for e in &mut out.events {
                    e.t_ms = reflect(e.t_ms + normal.sample(rng), d);
                }
            }
            JitterKind::Uniform => {
                for e in &mut out.events {
                    e.t_ms = reflect(e.t_ms + rng.random_range(-self.tau_ms..=self.tau_ms), d);
                }
            }
        }
        out.sort();
        Ok(out)
    }
}

impl Map for Jitter {
    fn process(&self, inputs: &[&Item], ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let train = inputs[0].payload.spikes()?;
        Ok(self.apply(train, &mut ctx.rng())?.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use palpate_core::{SpikeEvent, TaxelLayout};
    use proptest::prelude::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn train(duration_ms: f64, events: Vec<(u32, f64)>) -> SpikeTrain {
        let mut t = SpikeTrain {
            layout: TaxelLayout::paper(),
            duration_ms,
            events: events
                .into_iter()
                .map(|(taxel, t_ms)| SpikeEvent { taxel, t_ms })
                .collect(),
        };
        t.sort();
        t
    }

    #[test]
    fn reflection_keeps_times_inside() {
        assert_eq!(reflect(-3.0, 100.0), 3.0);
        assert_eq!(reflect(103.0, 100.0), 97.0);
        assert_eq!(reflect(250.0, 100.0), 50.0);
        assert!(reflect(100.0, 100.0) < 100.0);
        assert_eq!(reflect(-1e9, 100.0), reflect(-1e9, 100.0));
        assert!((0.0..100.0).contains(&reflect(-123456.7, 100.0)));
    }

    #[test]
    fn spread_matches_tau() {
        let ev: Vec<(u32, f64)> = (0..4000).map(|i| ((i % 16) as u32, 5000.0)).collect();
        let t = train(10_000.0, ev);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for (kind, sd) in [
            (JitterKind::Gaussian, 10.0),
            (JitterKind::Uniform, 10.0 / 3f64.sqrt()),
        ] {
            let j = Jitter { kind, tau_ms: 10.0 }.apply(&t, &mut rng).unwrap();
            let n = j.events.len() as f64;
            let mean = j.events.iter().map(|e| e.t_ms).sum::<f64>() / n;
            let var = j.events.iter().map(|e| (e.t_ms - mean).powi(2)).sum::<f64>() / n;
            assert!((mean - 5000.0).abs() < 1.0, "{kind:?} mean {mean}");
            assert!((var.sqrt() - sd).abs() < 0.5, "{kind:?} sd {}", var.sqrt());
            if kind == JitterKind::Uniform {
                assert!(j.events.iter().all(|e| (e.t_ms - 5000.0).abs() <= 10.0));
            }
        }
    }

    #[test]
    fn zero_tau_is_identity_and_seed_is_deterministic() {
        let t = train(100.0, vec![(0, 1.0), (3, 50.0), (2, 99.0)]);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let j0 = Jitter {
            kind: JitterKind::Gaussian,
            tau_ms: 0.0,
        };
        assert_eq!(j0.apply(&t, &mut rng).unwrap(), t);
        let j = Jitter {
            kind: JitterKind::Gaussian,
            tau_ms: 5.0,
        };
        let a = j.apply(&t, &mut ChaCha8Rng::seed_from_u64(3)).unwrap();
        let b = j.apply(&t, &mut ChaCha8Rng::seed_from_u64(3)).unwrap();
        assert_eq!(a, b);
        assert_ne!(a, j.apply(&t, &mut ChaCha8Rng::seed_from_u64(4)).unwrap());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// Never loses or duplicates a spike: per-taxel counts are unchanged,
        /// times are sorted and inside [0, duration).
        #[test]
        fn never_loses_or_duplicates(
            ev in proptest::collection::vec((0u32..16, 0.0f64..1.0), 0..200),
            dur in 1.0f64..5000.0,
            tau in 0.0f64..20000.0,
            uniform in any::<bool>(),
            seed in any::<u64>(),
        ) {
            let t = train(dur, ev.into_iter().map(|(k, f)| (k, f * dur)).collect());
            let kind = if uniform { JitterKind::Uniform } else { JitterKind::Gaussian };
            let j = Jitter { kind, tau_ms: tau }.apply(&t, &mut ChaCha8Rng::seed_from_u64(seed)).unwrap();
            prop_assert_eq!(j.events.len(), t.events.len());
            let mut a: Vec<u32> = t.events.iter().map(|e| e.taxel).collect();
            let mut b: Vec<u32> = j.events.iter().map(|e| e.taxel).collect();
            a.sort_unstable();
            b.sort_unstable();
            prop_assert_eq!(a, b);
            prop_assert!(j.is_sorted());
            for e in &j.events {
                prop_assert!(e.t_ms >= 0.0 && e.t_ms < dur);
            }
        }
    }
}
