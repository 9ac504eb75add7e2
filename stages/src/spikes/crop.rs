//! `crop`: keep only the first share of the palpation (paper section 3.3, Fig. 7).
//!
//! The crossing interval `[t0, t1]` is the trial's `meta.crossing_ms` when the
//! source knows it (simulated scenes do), else the first and last spike of the
//! trial. The stage keeps every spike at or before the cut
//! `t_cut = t0 + share · (t1 - t0)`: the hold before the crossing and the first
//! `share` of the crossing itself, i.e. the data a real-time system would have
//! when `share` of the edge had passed.
//!
//! With `truncate = true` (default) the trial ends at the cut
//! (`duration_ms = min(duration, t_cut⁺)`, just past the cut so the last kept
//! spike lies inside), so the binned images stop there too, as if the palpation
//! had been stopped; with `false` the trial keeps its length and the later
//! frames are empty.
//!
//! `share` must lie in (0, 1]; anything else is a config error naming `share`.
//! A trial without spikes and without a known crossing is passed through
//! unchanged (there is nothing to crop).

use palpate_core::{
    register_stage, BuildContext, ConfigError, InputSpec, Item, Map, Payload, PayloadKind, SpikeTrain, Stage,
    StageConfig, StageError, TrialContext, TrialMeta,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Keeps the first `share` of the edge's crossing (paper Fig. 7): spikes up to t0 + share*(t1 - t0).
///
/// `[t0, t1]` is the trial's known crossing (`crossing_ms`), else its first and
/// last spike. `share` in (0, 1].
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct CropConfig {
    /// Share of the crossing kept, in (0, 1]. Default 1.
    pub share: f64,
    /// End the trial at the cut (true) or keep its length with empty tail (false). Default true.
    pub truncate: bool,
}

impl Default for CropConfig {
    fn default() -> Self {
        CropConfig {
            share: 1.0,
            truncate: true,
        }
    }
}

#[typetag::serde(name = "crop")]
impl StageConfig for CropConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Spikes)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Spikes)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        if !(self.share.is_finite() && self.share > 0.0 && self.share <= 1.0) {
            return Err(ConfigError::key(
                "share",
                format!(
                    "must lie in (0, 1] (a share of the crossing), got {}",
                    palpate_core::fmt_num(self.share)
                ),
            ));
        }
        Ok(Stage::Map(Box::new(Crop {
            share: self.share,
            truncate: self.truncate,
        })))
    }
}
register_stage!("crop", CropConfig);

/// The runtime `crop` stage.
#[derive(Clone, Debug)]
pub struct Crop {
    /// Share kept, in (0, 1].
    pub share: f64,
    /// End the trial at the cut.
    pub truncate: bool,
}

impl Crop {
    /// The cut time for a trial, if there is anything to cut by.
    pub fn cut_ms(&self, train: &SpikeTrain, meta: &TrialMeta) -> Option<f64> {
        let [t0, t1] = match meta.crossing_ms {
            Some([a, b]) if a.is_finite() && b.is_finite() && b >= a => [a, b],
            _ => [train.events.first()?.t_ms, train.events.last()?.t_ms],
        };
        Some(t0 + self.share * (t1 - t0))
    }

    /// Crops one trial.
    pub fn apply(&self, train: &SpikeTrain, meta: &TrialMeta) -> SpikeTrain {
        let Some(cut) = self.cut_ms(train, meta) else {
            return train.clone();
        };
        let events: Vec<_> = train.events.iter().copied().filter(|e| e.t_ms <= cut).collect();
        let duration_ms = if self.truncate {
            // Just past the cut, so an event at the cut stays inside [0, duration).
            let end = if cut >= 0.0 { next_up(cut) } else { 0.0 };
            train.duration_ms.min(end)
        } else {
            train.duration_ms
        };
        SpikeTrain {
            layout: train.layout.clone(),
            duration_ms,
            events,
        }
    }
}

/// The smallest double above a non-negative finite `x`.
fn next_up(x: f64) -> f64 {
    if x == 0.0 {
        f64::from_bits(1)
    } else {
        f64::from_bits(x.to_bits() + 1)
    }
}

impl Map for Crop {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let item = inputs[0];
        Ok(self.apply(item.payload.spikes()?, &item.meta).into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use palpate_core::{SpikeEvent, TaxelLayout};

    fn train(events: &[f64]) -> SpikeTrain {
        SpikeTrain {
            layout: TaxelLayout::paper(),
            duration_ms: 5000.0,
            events: events.iter().map(|&t_ms| SpikeEvent { taxel: 0, t_ms }).collect(),
        }
    }

    #[test]
    fn uses_known_crossing_then_falls_back_to_spikes() {
        let t = train(&[100.0, 2000.0, 2500.0, 2999.0, 3500.0]);
        let meta = TrialMeta {
            crossing_ms: Some([2000.0, 3000.0]),
            ..TrialMeta::default()
        };
        let c = Crop {
            share: 0.6,
            truncate: true,
        };
        let out = c.apply(&t, &meta);
        let ts: Vec<f64> = out.events.iter().map(|e| e.t_ms).collect();
        assert_eq!(ts, vec![100.0, 2000.0, 2500.0]);
        assert!(out.duration_ms > 2600.0 && out.duration_ms < 2600.001);
        // No known crossing: first..last spike = 100..3500, cut at 2140.
        let out = c.apply(&t, &TrialMeta::default());
        assert_eq!(out.events.len(), 2);
        // share = 1 keeps the last spike, inside the trial.
        let full = Crop {
            share: 1.0,
            truncate: true,
        }
        .apply(&t, &TrialMeta::default());
        assert_eq!(full.events.len(), 5);
        assert!(full.events.iter().all(|e| e.t_ms < full.duration_ms));
        // Not truncated: the length stays.
        let keep = Crop {
            share: 0.5,
            truncate: false,
        }
        .apply(&t, &meta);
        assert_eq!(keep.duration_ms, 5000.0);
    }

    #[test]
    fn empty_trial_passes_through() {
        let t = train(&[]);
        let out = Crop {
            share: 0.3,
            truncate: true,
        }
        .apply(&t, &TrialMeta::default());
        assert_eq!(out, t);
    }

    #[test]
    fn share_out_of_range_names_the_key() {
        let ctx = BuildContext {
            stage_id: "c".into(),
            seed: 0,
            out_dir: ".".into(),
            base_dir: ".".into(),
        };
        for s in [0.0, -0.1, 1.01, f64::NAN] {
            let e = CropConfig {
                share: s,
                truncate: true,
            }
            .build(&ctx)
            .err()
            .unwrap();
            assert_eq!(e.key.as_deref(), Some("share"));
        }
    }
}
