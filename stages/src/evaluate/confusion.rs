//! The confusion sink: the normalized confusion matrix of each input estimator.
//!
//! Rows are true angles, columns estimated classes (an estimate's `class_deg`, the
//! grid class it chose; a refined `angle_deg` would scatter the columns) plus a
//! final "no edge" column. Entry `(i, j)` is the share of class-`i` trials
//! estimated as `j`, so each row sums to 1 (the paper's Fig. 6). Trials without
//! a true angle are left out and counted.
//!
//! Files per estimator `<est>`, written atomically into the run's output
//! directory: `<sink id>_<est>.csv` (counts and shares), `<sink id>_<est>.md`,
//! and `<sink id>_<est>.svg` (a heatmap).

use palpate_core::output::write_atomic;
use palpate_core::{
    register_stage, BuildContext, ConfigError, InputSpec, PayloadKind, Sink, SinkContext, SinkInput,
    SinkReport, Stage, StageConfig, StageError,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;

/// Normalized confusion matrix (true angle x estimated class, plus "no edge"),
/// as a terminal table, CSV, Markdown and an SVG heatmap; one per input.
#[derive(Clone, Debug, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ConfusionConfig {
    /// Print the matrix on the terminal (it is always written to files).
    /// Default false.
    pub print: bool,
}

#[typetag::serde(name = "confusion")]
impl StageConfig for ConfusionConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::many(PayloadKind::Estimates)
    }
    fn output(&self) -> Option<PayloadKind> {
        None
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Ok(Stage::Sink(Box::new(self.clone())))
    }
}
register_stage!("confusion", ConfusionConfig);

/// A confusion matrix.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Confusion {
    /// True angles (rows), degrees.
    pub truths: Vec<f64>,
    /// Estimated classes (columns), degrees; a last column counts "no edge".
    pub classes: Vec<f64>,
    /// `counts[row][col]`, with `classes.len() + 1` columns.
    pub counts: Vec<Vec<usize>>,
    /// Trials without a true angle.
    pub unlabelled: usize,
}

fn key(a: f64) -> i64 {
    (a * 1e6).round() as i64
}

impl Confusion {
    /// Builds the matrix from `(truth, estimated class)` pairs.
    pub fn new(pairs: &[(Option<f64>, Option<f64>)]) -> Self {
        let mut truths: Vec<f64> = pairs.iter().filter_map(|p| p.0).collect();
        let mut classes: Vec<f64> = pairs.iter().filter_map(|p| p.1).collect();
        for v in [&mut truths, &mut classes] {
            v.sort_by(f64::total_cmp);
            v.dedup_by(|a, b| key(*a) == key(*b));
        }
        let mut counts = vec![vec![0; classes.len() + 1]; truths.len()];
        let mut unlabelled = 0;
        for &(t, e) in pairs {
            let Some(t) = t else {
                unlabelled += 1;
                continue;
            };
            let row = truths.iter().position(|x| key(*x) == key(t)).unwrap_or(0);
            let col = e
                .and_then(|e| classes.iter().position(|x| key(*x) == key(e)))
                .unwrap_or(classes.len());
            counts[row][col] += 1;
        }
        Confusion {
            truths,
            classes,
            counts,
            unlabelled,
        }
    }

    /// Row-normalized shares (a row with no trial is all zeros, never NaN).
    pub fn normalized(&self) -> Vec<Vec<f64>> {
        self.counts
            .iter()
            .map(|row| {
                let n: usize = row.iter().sum();
                row.iter()
                    .map(|&c| if n == 0 { 0.0 } else { c as f64 / n as f64 })
                    .collect()
            })
            .collect()
    }

    fn col_labels(&self) -> Vec<String> {
        self.classes
            .iter()
            .map(|c| format!("{c}"))
            .chain(["none".to_string()])
            .collect()
    }

    /// As a terminal table of percentages.
    pub fn render(&self) -> String {
        let mut s = String::from("true\\\\est");
        for c in self.col_labels() {
            let _ = write!(s, " {c:>5}");
        }
        s.push('\n');
        for (t, row) in self.truths.iter().zip(self.normalized()) {
            let _ = write!(s, "{t:>9}");
            for v in row {
                if v == 0.0 {
                    let _ = write!(s, " {:>5}", ".");
                } else {
                    let _ = write!(s, " {:>5.0}", v * 100.0);
                }
            }
            s.push('\n');
        }
        s
    }

    /// As CSV: `true_deg,estimated,count,share`.
    pub fn to_csv(&self) -> String {
        let mut s = String::from("true_deg,estimated_deg,count,share\n");
        let labels = self.col_labels();
        for ((t, row), shares) in self.truths.iter().zip(&self.counts).zip(self.normalized()) {
            for ((c, n), sh) in labels.iter().zip(row).zip(shares) {
                let _ = writeln!(s, "{t},{c},{n},{sh}");
            }
        }
        s
    }

    /// As a Markdown table of shares.
    pub fn to_markdown(&self) -> String {
        let labels = self.col_labels();
        let mut s = String::from("| true \\\\ estimated |");
        for c in &labels {
            let _ = write!(s, " {c} |");
        }
        s.push_str("\n|---|");
        s.push_str(&"---|".repeat(labels.len()));
        s.push('\n');
        for (t, row) in self.truths.iter().zip(self.normalized()) {
            let _ = write!(s, "| {t}° |");
            for v in row {
                let _ = write!(
                    s,
                    " {} |",
                    if v == 0.0 {
                        String::new()
                    } else {
                        format!("{v:.2}")
                    }
                );
            }
            s.push('\n');
        }
        s
    }
}

impl Sink for ConfusionConfig {
    fn consume(&self, inputs: &[SinkInput<'_>], ctx: &SinkContext<'_>) -> Result<SinkReport, StageError> {
        let mut report = SinkReport::default();
        for input in inputs {
            let mut pairs = Vec::with_capacity(input.items.len());
            for item in input.items {
                let e = item.payload.estimate()?;
                pairs.push((item.meta.label.angle_deg, e.class_deg.or(e.angle_deg)));
            }
            let m = Confusion::new(&pairs);
            let diag: usize = m
                .truths
                .iter()
                .enumerate()
                .filter_map(|(r, t)| {
                    m.classes
                        .iter()
                        .position(|c| key(*c) == key(*t))
                        .map(|c| m.counts[r][c])
                })
                .sum();
            let labelled = pairs.len() - m.unlabelled;
            let accuracy = if labelled == 0 {
                0.0
            } else {
                diag as f64 / labelled as f64
            };
            let _ = writeln!(
                report.text,
                "estimator `{}`: {:.1}% of trials on the diagonal",
                input.stage_id,
                accuracy * 100.0
            );
            if self.print {
                report.text.push_str(&m.render());
            }
            report
                .metrics
                .push((format!("{}.accuracy", input.stage_id), accuracy));
            let base = ctx.out_dir.join(format!("{}_{}", ctx.stage_id, input.stage_id));
            let with_ext = |ext: &str| base.with_extension(ext);
            for (path, bytes) in [(with_ext("csv"), m.to_csv()), (with_ext("md"), m.to_markdown())] {
                write_atomic(&path, bytes.as_bytes())
                    .map_err(|e| StageError::new(format!("writing {}: {e}", path.display())))?;
                report.files.push(path);
            }
            let rows: Vec<String> = m.truths.iter().map(|t| format!("{t}")).collect();
            let svg = with_ext("svg");
            crate::plot::heatmap(
                &svg,
                &format!("Normalized confusion: {}", input.stage_id),
                &rows,
                &m.col_labels(),
                &m.normalized(),
            )
            .map_err(|e| StageError::new(e.to_string()))?;
            report.files.push(svg);
        }
        Ok(report)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_sum_to_one_and_no_edge_has_its_column() {
        let m = Confusion::new(&[
            (Some(10.0), Some(10.0)),
            (Some(10.0), Some(15.0)),
            (Some(15.0), None),
            (Some(15.0), Some(15.0)),
            (None, Some(10.0)),
        ]);
        assert_eq!(m.truths, vec![10.0, 15.0]);
        assert_eq!(m.classes, vec![10.0, 15.0]);
        assert_eq!(m.counts, vec![vec![1, 1, 0], vec![0, 1, 1]]);
        assert_eq!(m.unlabelled, 1);
        for row in m.normalized() {
            assert!((row.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        }
        assert!(m.render().contains("none"));
        assert_eq!(m.to_csv().lines().count(), 1 + 6);
        assert!(
            m.to_markdown().contains("| 10° | 0.50 | 0.50 |  |"),
            "{}",
            m.to_markdown()
        );
    }

    #[test]
    fn empty_input_gives_an_empty_matrix_without_nan() {
        let m = Confusion::new(&[]);
        assert!(m.normalized().is_empty());
        assert!(!m.render().contains("NaN"));
    }
}
