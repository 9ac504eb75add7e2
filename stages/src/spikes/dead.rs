//! `dead_taxels`: remove the spikes of dead taxels.
//!
//! Dead taxels are given by index (`taxels`), by grid cell (`cells`, `[row,
//! col]`), and/or drawn at random per trial (`random_count` distinct taxels,
//! from the stage's per-trial generator, so reproducible from the seed). The
//! layout is unchanged: a dead taxel is still there, it just never fires, which
//! is what a broken trace does to the array.
//!
//! Trial metadata carries no per-taxel "dead" flag in palpate-core, so taxels
//! that a source knows to be dead must be listed here (or simulated in the
//! scene, whose dead taxels give flat signals and so no spikes anyway).
//!
//! A listed taxel or cell outside the input's layout is a run-time error naming
//! the key (the layout is known only then); `cells` on a positions layout is an
//! error naming the stage.

use palpate_core::{
    register_stage, BuildContext, ConfigError, InputSpec, Item, Map, Payload, PayloadKind, SpikeTrain, Stage,
    StageConfig, StageError, TrialContext,
};
use rand::seq::index::sample;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Removes the spikes of dead taxels: listed by index or [row, col], or drawn at random per trial.
#[derive(Clone, Debug, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct DeadTaxelsConfig {
    /// Dead taxels by index (row-major for grids). Default none.
    pub taxels: Vec<usize>,
    /// Dead taxels by grid cell, `[row, col]`. Default none.
    pub cells: Vec<[usize; 2]>,
    /// Further taxels drawn dead at random per trial (distinct, seeded). Default 0.
    pub random_count: usize,
}

#[typetag::serde(name = "dead_taxels")]
impl StageConfig for DeadTaxelsConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Spikes)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Spikes)
    }
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Ok(Stage::Map(Box::new(DeadTaxels {
            stage_id: ctx.stage_id.clone(),
            config: self.clone(),
        })))
    }
}
register_stage!("dead_taxels", DeadTaxelsConfig);

/// The runtime `dead_taxels` stage.
pub struct DeadTaxels {
    stage_id: String,
    config: DeadTaxelsConfig,
}

impl DeadTaxels {
    /// Which taxels of `train`'s layout are dead in this trial.
    pub fn dead_mask(&self, train: &SpikeTrain, ctx: &TrialContext<'_>) -> Result<Vec<bool>, StageError> {
        let n = train.layout.len();
        let mut dead = vec![false; n];
        for &t in &self.config.taxels {
            if t >= n {
                return Err(StageError::new(format!(
                    "dead_taxels: key `taxels` lists taxel {t}, but the layout has {n} taxels"
                )));
            }
            dead[t] = true;
        }
        if !self.config.cells.is_empty() {
            let Some((rows, cols)) = train.layout.grid() else {
                return Err(StageError::new(format!(
                    "dead_taxels `{}`: key `cells` needs a grid layout; list `taxels` by index instead",
                    self.stage_id
                )));
            };
            for &[r, c] in &self.config.cells {
                if r >= rows || c >= cols {
                    return Err(StageError::new(format!(
                        "dead_taxels: key `cells` lists [{r}, {c}], outside the {rows} x {cols} grid"
                    )));
                }
                dead[r * cols + c] = true;
            }
        }
        let k = self.config.random_count;
        if k > 0 {
            if k > n {
                return Err(StageError::new(format!(
                    "dead_taxels: key `random_count` = {k} exceeds the layout's {n} taxels"
                )));
            }
            for i in sample(&mut ctx.rng(), n, k) {
                dead[i] = true;
            }
        }
        Ok(dead)
    }
}

impl Map for DeadTaxels {
    fn process(&self, inputs: &[&Item], ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let train = inputs[0].payload.spikes()?;
        let dead = self.dead_mask(train, ctx)?;
        let events = train
            .events
            .iter()
            .copied()
            .filter(|e| !dead.get(e.taxel as usize).copied().unwrap_or(false))
            .collect();
        Ok(SpikeTrain {
            layout: train.layout.clone(),
            duration_ms: train.duration_ms,
            events,
        }
        .into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use palpate_core::{SpikeEvent, TaxelLayout, TrialMeta};
    use std::sync::Arc;

    fn item() -> Item {
        Item {
            meta: Arc::new(TrialMeta::default()),
            payload: SpikeTrain {
                layout: TaxelLayout::paper(),
                duration_ms: 100.0,
                events: (0..16)
                    .map(|i| SpikeEvent {
                        taxel: i,
                        t_ms: i as f64,
                    })
                    .collect(),
            }
            .into(),
        }
    }

    fn run(config: DeadTaxelsConfig, seed: u64) -> Result<Vec<u32>, StageError> {
        let it = item();
        let ctx = TrialContext {
            stage_id: "dead",
            meta: &it.meta,
            seed,
        };
        let st = DeadTaxels {
            stage_id: "dead".into(),
            config,
        };
        let out = st.process(&[&it], &ctx)?;
        Ok(out.spikes()?.events.iter().map(|e| e.taxel).collect())
    }

    #[test]
    fn removes_listed_cells_and_random_taxels() {
        let left = run(
            DeadTaxelsConfig {
                taxels: vec![0, 15],
                cells: vec![[1, 2]],
                random_count: 0,
            },
            1,
        )
        .unwrap();
        assert_eq!(left.len(), 13);
        assert!(!left.contains(&0) && !left.contains(&15) && !left.contains(&6));
        let r = DeadTaxelsConfig {
            random_count: 3,
            ..Default::default()
        };
        let a = run(r.clone(), 5).unwrap();
        assert_eq!(a.len(), 13);
        assert_eq!(a, run(r.clone(), 5).unwrap());
        assert_ne!(a, run(r, 6).unwrap());
    }

    #[test]
    fn out_of_range_is_named() {
        let e = run(
            DeadTaxelsConfig {
                taxels: vec![16],
                ..Default::default()
            },
            0,
        )
        .unwrap_err();
        assert!(e.message.contains("`taxels`"));
        let e = run(
            DeadTaxelsConfig {
                cells: vec![[0, 4]],
                ..Default::default()
            },
            0,
        )
        .unwrap_err();
        assert!(e.message.contains("`cells`"));
    }
}
