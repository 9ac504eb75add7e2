//! `subarea`: the spikes of an `n x n` window of the grid, as a smaller array
//! (paper section 3.5, Fig. 9).
//!
//! The window's top-left taxel sits at (`row`, `col`) of the input grid. The
//! output layout is an `n x n` grid with the input's pitch and taxel size,
//! centred on the origin like every grid (so estimators see a smaller array,
//! not a masked big one), and taxel `(r, c)` of the input becomes
//! `(r - row) · n + (c - col)`. Spikes outside the window are dropped.
//!
//! Fig. 9 averages over every placement of the window (4 for 3 x 3, 9 for
//! 2 x 2 on a 4 x 4 array). One stage gives one placement, because a stage maps
//! one trial to one trial; sweeping `row` and `col` over `0..=rows - n` and
//! `0..=cols - n` covers every placement.
//!
//! Errors: a window that does not fit the grid is a config error naming the
//! key when the config alone shows it (`size` = 0) and a run-time error naming
//! `row`, `col` or `size` when it does not fit the input's grid; an input with
//! an explicit-positions layout is an error naming the stage (there is no grid
//! to cut a window from).

use palpate_core::{
    register_stage, BuildContext, ConfigError, InputSpec, Item, Map, Payload, PayloadKind, SpikeEvent,
    SpikeTrain, Stage, StageConfig, StageError, TaxelLayout, TrialContext,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Spikes of an n x n window of the grid at (row, col), renumbered as a smaller grid (paper Fig. 9).
///
/// Sweep `row` and `col` to cover every placement of the window.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SubareaConfig {
    /// Side of the window, taxels (n of n x n). Default 3.
    pub size: usize,
    /// Row of the window's top-left taxel (0 = top row). Default 0.
    pub row: usize,
    /// Column of the window's top-left taxel (0 = left column). Default 0.
    pub col: usize,
}

impl Default for SubareaConfig {
    fn default() -> Self {
        SubareaConfig {
            size: 3,
            row: 0,
            col: 0,
        }
    }
}

#[typetag::serde(name = "subarea")]
impl StageConfig for SubareaConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Spikes)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Spikes)
    }
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError> {
        if self.size == 0 {
            return Err(ConfigError::key(
                "size",
                "a window needs at least one taxel (size >= 1)",
            ));
        }
        Ok(Stage::Map(Box::new(Subarea {
            stage_id: ctx.stage_id.clone(),
            size: self.size,
            row: self.row,
            col: self.col,
        })))
    }
}
register_stage!("subarea", SubareaConfig);

/// The runtime `subarea` stage.
#[derive(Clone, Debug)]
pub struct Subarea {
    /// The stage's id, for messages.
    pub stage_id: String,
    /// Window side.
    pub size: usize,
    /// Top row.
    pub row: usize,
    /// Left column.
    pub col: usize,
}

impl Subarea {
    /// The window's layout and the map from input taxel to output taxel.
    pub fn plan(&self, layout: &TaxelLayout) -> Result<(TaxelLayout, Vec<Option<u32>>), StageError> {
        let TaxelLayout::Grid {
            rows,
            cols,
            pitch_mm,
            taxel_mm,
        } = *layout
        else {
            return Err(StageError::new(format!(
                "subarea `{}`: the input's layout is a list of positions, not a grid; \
                 a window of rows and columns needs a grid",
                self.stage_id
            )));
        };
        let n = self.size;
        if n > rows || n > cols {
            return Err(StageError::new(format!(
                "subarea: key `size` = {n} does not fit the {rows} x {cols} grid"
            )));
        }
        if self.row + n > rows {
            return Err(StageError::new(format!(
                "subarea: key `row` = {} puts a {n}-row window past the {rows}-row grid (row <= {})",
                self.row,
                rows - n
            )));
        }
        if self.col + n > cols {
            return Err(StageError::new(format!(
                "subarea: key `col` = {} puts a {n}-column window past the {cols}-column grid (col <= {})",
                self.col,
                cols - n
            )));
        }
        let map = (0..rows * cols)
            .map(|i| {
                let (r, c) = (i / cols, i % cols);
                let inside = (self.row..self.row + n).contains(&r) && (self.col..self.col + n).contains(&c);
                inside.then(|| ((r - self.row) * n + (c - self.col)) as u32)
            })
            .collect();
        Ok((
            TaxelLayout::Grid {
                rows: n,
                cols: n,
                pitch_mm,
                taxel_mm,
            },
            map,
        ))
    }

    /// Cuts one trial.
    pub fn apply(&self, train: &SpikeTrain) -> Result<SpikeTrain, StageError> {
        let (layout, map) = self.plan(&train.layout)?;
        let mut events = Vec::with_capacity(train.events.len());
        for e in &train.events {
            let Some(slot) = map.get(e.taxel as usize) else {
                return Err(StageError::new(format!(
                    "subarea: spike of taxel {} but the layout has {} taxels",
                    e.taxel,
                    map.len()
                )));
            };
            if let Some(t) = slot {
                events.push(SpikeEvent {
                    taxel: *t,
                    t_ms: e.t_ms,
                });
            }
        }
        // Renumbering keeps row-major order within the window, so ties by time
        // stay ordered by taxel; sort anyway to keep the invariant obvious.
        let mut out = SpikeTrain {
            layout,
            duration_ms: train.duration_ms,
            events,
        };
        out.sort();
        Ok(out)
    }
}

impl Map for Subarea {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        Ok(self.apply(inputs[0].payload.spikes()?)?.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sub(size: usize, row: usize, col: usize) -> Subarea {
        Subarea {
            stage_id: "sa".into(),
            size,
            row,
            col,
        }
    }

    fn all_taxels() -> SpikeTrain {
        SpikeTrain {
            layout: TaxelLayout::paper(),
            duration_ms: 100.0,
            events: (0..16)
                .map(|i| SpikeEvent {
                    taxel: i,
                    t_ms: i as f64,
                })
                .collect(),
        }
    }

    #[test]
    fn window_renumbers_and_keeps_pitch() {
        let out = sub(2, 1, 2).apply(&all_taxels()).unwrap();
        // Input taxels (1,2)=6, (1,3)=7, (2,2)=10, (2,3)=11 -> 0, 1, 2, 3.
        let got: Vec<(u32, f64)> = out.events.iter().map(|e| (e.taxel, e.t_ms)).collect();
        assert_eq!(got, vec![(0, 6.0), (1, 7.0), (2, 10.0), (3, 11.0)]);
        assert_eq!(
            out.layout,
            TaxelLayout::Grid {
                rows: 2,
                cols: 2,
                pitch_mm: 3.0,
                taxel_mm: 2.0
            }
        );
        assert_eq!(out.duration_ms, 100.0);
    }

    #[test]
    fn every_placement_covers_each_taxel_the_expected_number_of_times() {
        // 3 x 3 on 4 x 4: 4 placements; corner taxels appear once, the 4 centre ones 4 times.
        let mut hits = [0; 16];
        for row in 0..=1 {
            for col in 0..=1 {
                let s = sub(3, row, col);
                let (_, map) = s.plan(&TaxelLayout::paper()).unwrap();
                for (i, m) in map.iter().enumerate() {
                    hits[i] += m.is_some() as usize;
                }
                assert_eq!(s.apply(&all_taxels()).unwrap().events.len(), 9);
            }
        }
        assert_eq!((hits[0], hits[5], hits[6], hits[3]), (1, 4, 4, 1));
    }

    #[test]
    fn bad_placement_and_positions_layout_are_named() {
        let e = sub(3, 2, 0).apply(&all_taxels()).unwrap_err().message;
        assert!(e.contains("`row`"), "{e}");
        let e = sub(3, 0, 2).apply(&all_taxels()).unwrap_err().message;
        assert!(e.contains("`col`"), "{e}");
        let e = sub(5, 0, 0).apply(&all_taxels()).unwrap_err().message;
        assert!(e.contains("`size`"), "{e}");
        let mut t = all_taxels();
        t.layout = TaxelLayout::Positions {
            positions_mm: vec![[0.0, 0.0]; 16],
            taxel_mm: 1.0,
        };
        let e = sub(2, 0, 0).apply(&t).unwrap_err().message;
        assert!(e.contains("subarea `sa`") && e.contains("grid"), "{e}");
    }
}
