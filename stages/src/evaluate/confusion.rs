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
//! and `<sink id>_<est>.svg`: the matrix drawn square over every class (true
//! or estimated) plus the "no edge" column, each cell coloured and labelled
//! with its share of the row in percent, with axis titles and a colour bar.

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

    /// Every class, true or estimated, in order: the rows and (with "no edge"
    /// last) the columns of the square matrix that is plotted.
    pub fn all_classes(&self) -> Vec<f64> {
        let mut all: Vec<f64> = self.truths.iter().chain(&self.classes).copied().collect();
        all.sort_by(f64::total_cmp);
        all.dedup_by(|a, b| key(*a) == key(*b));
        all
    }

    /// The square plot of the matrix: rows and columns are every class (true
    /// or estimated, so the diagonal is where it belongs even when an
    /// estimator answers a class no trial had), plus a last "no edge" column;
    /// a cell's colour and number are the share of its row, in percent. A
    /// class no trial had is a grey row.
    pub fn heatmap(&self, title: &str) -> ConfusionPlot {
        let all = self.all_classes();
        let shares = self.normalized();
        let n = all.len();
        let mut values = vec![vec![f64::NAN; n + 1]; n];
        let mut text = vec![vec![String::new(); n + 1]; n];
        for (r, t) in self.truths.iter().enumerate() {
            let Some(rr) = all.iter().position(|a| key(*a) == key(*t)) else {
                continue;
            };
            let cols = self
                .classes
                .iter()
                .map(|c| all.iter().position(|a| key(*a) == key(*c)).unwrap_or(n))
                .chain([n]);
            for (c, cc) in cols.enumerate() {
                let v = shares[r][c];
                values[rr][cc] = v;
                if self.counts[r][c] > 0 {
                    text[rr][cc] = format!("{:.0}", v * 100.0);
                }
            }
            for v in values[rr].iter_mut().filter(|v| v.is_nan()) {
                *v = 0.0;
            }
        }
        let labels: Vec<String> = all.iter().map(|a| format!("{a}")).collect();
        let mut cols = labels.clone();
        cols.push("no edge".into());
        ConfusionPlot {
            title: title.to_string(),
            rows: labels,
            cols,
            values,
            text,
        }
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

/// The data of a confusion matrix's plot (see [`Confusion::heatmap`]).
#[derive(Clone, Debug, PartialEq)]
pub struct ConfusionPlot {
    /// Caption.
    pub title: String,
    /// Row labels: every class, degrees.
    pub rows: Vec<String>,
    /// Column labels: every class, then "no edge".
    pub cols: Vec<String>,
    /// Share of the row in each cell (NaN: a class no trial had).
    pub values: Vec<Vec<f64>>,
    /// The share in percent, written in each non-empty cell.
    pub text: Vec<Vec<String>>,
}

impl ConfusionPlot {
    /// The heatmap to draw.
    pub fn as_plot(&self) -> crate::plot::Heatmap<'_> {
        crate::plot::Heatmap {
            title: &self.title,
            x_title: "estimated class (degrees)",
            y_title: "true angle (degrees)",
            row_labels: &self.rows,
            col_labels: &self.cols,
            values: &self.values,
            cell_text: &self.text,
            v_max: Some(1.0),
            scale_title: "% of row",
            scale_factor: 100.0,
        }
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
            let svg = with_ext("svg");
            crate::plot::heatmap(
                &svg,
                &m.heatmap(&format!("Confusion matrix: {}", input.stage_id))
                    .as_plot(),
            )
            .map_err(|e| StageError::new(format!("writing {}: {e}", svg.display())))?;
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

    #[test]
    fn the_plot_is_square_over_every_class_with_the_diagonal_in_place() {
        // Truths 10, 20; an estimator that also answers 15 (no trial's class).
        let m = Confusion::new(&[
            (Some(10.0), Some(10.0)),
            (Some(10.0), Some(15.0)),
            (Some(20.0), Some(20.0)),
            (Some(20.0), None),
        ]);
        let p = m.heatmap("t");
        assert_eq!(p.rows, ["10", "15", "20"]);
        assert_eq!(p.cols, ["10", "15", "20", "no edge"]);
        assert_eq!(p.values.len(), 3);
        assert!(p.values.iter().all(|r| r.len() == 4));
        assert_eq!(p.values[0], [0.5, 0.5, 0.0, 0.0]);
        assert!(
            p.values[1].iter().all(|v| v.is_nan()),
            "no trial of 15°: grey row"
        );
        assert_eq!(p.values[2], [0.0, 0.0, 0.5, 0.5]);
        assert_eq!(p.text[2], ["", "", "50", "50"]);
        let svg = crate::plot::heatmap_svg(&p.as_plot());
        assert_eq!(svg.matches(r#"class="label-y""#).count(), 3);
        assert_eq!(svg.matches(r#"class="label-x""#).count(), 4);
        assert!(svg.contains("true angle (degrees)") && svg.contains("no edge"));
        assert!(!svg.contains("NaN"));
    }
}
