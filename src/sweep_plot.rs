//! A sweep's declared figures (`[[sweep.plot]]`, [`SweepPlot`]): from the
//! runs of a sweep to the series of a line plot or a grouped bar chart, drawn
//! by [`palpate_stages::plot`] in the house style.
//!
//! Every run (point `p`, repeat `r`) gives rows `(series, x, y)`:
//!
//! * `y` is the run's value of the plot's `metric`; with `x = "class"` (or
//!   `by = "class"`), one row per class the sinks report the metric for
//!   ([`palpate_core::SinkReport::class_metrics`]: the `mae` sink's per-class
//!   MAE), keyed by the class's true angle;
//! * `x` and the series come from the point ([`SweepPoint::field`]): a key of
//!   its table value, the value itself, or its series' name.
//!
//! Rows sharing (series, x) are averaged: `ȳ = mean of every row's y` (over
//! the repeats, and over the points that share them: the placements of one
//! array size average into one bar). With more than one repeat, the error bar
//! is the population SD over repeats of each repeat's mean, `sqrt(mean_r
//! (ȳ_r − mean_r ȳ_r)²)`: the spread the seeds cause, not the spread between
//! the points averaged. A run without the metric is left out and said on
//! stderr; nothing here panics on what a run did or did not report.

use palpate_core::graph::{value_text, PlotKind, SweepPlot, SweepPoint, SweepSettings};
use palpate_core::sweep::{as_number, mean_sd as mean_and_sd, SweepRun};
use palpate_stages::plot::{BarPlot, Figure, PlotSeries, Point};
use std::path::{Path, PathBuf};

/// What a declared plot draws, gathered from the runs.
#[derive(Clone, Debug, PartialEq)]
pub struct PlotData {
    /// The measured series, in order of first appearance; on a bar chart a
    /// point's `x` is its category's index.
    pub series: Vec<PlotSeries>,
    /// The reference series, as `series`.
    pub reference: Vec<PlotSeries>,
    /// Bar charts: the category labels, in order of first appearance (then
    /// the references' categories that no run has).
    pub categories: Vec<String>,
    /// Runs (or rows) left out, each said once.
    pub notes: Vec<String>,
}

/// One run's contribution: its series' name, x (number, label), repeat and y.
struct Row {
    series: String,
    x: Option<f64>,
    label: String,
    repeat: usize,
    y: f64,
}

/// The rows of one run.
fn rows_of(plot: &SweepPlot, point: &SweepPoint, run: &SweepRun, notes: &mut Vec<String>) -> Vec<Row> {
    let x_field = plot.x_field();
    let by = plot.by.as_deref();
    let per_class = x_field == "class" || by == Some("class");
    // (class, y) pairs: every class's value, or the one overall value.
    let values: Vec<(Option<f64>, f64)> = if per_class {
        run.result
            .reports
            .iter()
            .flat_map(|(_, r)| r.class_metrics.iter())
            .filter(|c| c.name == plot.metric)
            .map(|c| (Some(c.class), c.value))
            .collect()
    } else {
        run.result
            .reports
            .iter()
            .flat_map(|(_, r)| r.metrics.iter())
            .find(|(n, _)| *n == plot.metric)
            .map(|(_, v)| vec![(None, *v)])
            .unwrap_or_default()
    };
    let at = format!("point `{}` (repeat {})", run.label, run.repeat);
    if values.is_empty() {
        let what = if per_class {
            "no per-class values of"
        } else {
            "no metric"
        };
        notes.push(format!(
            "{}: {at} has {what} `{}`; left out",
            plot.file, plot.metric
        ));
        return Vec::new();
    }
    let field = |name: &str, class: Option<f64>| {
        if name == "class" {
            class.map(toml::Value::Float)
        } else {
            point.field(name)
        }
    };
    let mut rows = Vec::new();
    for (class, y) in values {
        let Some(xv) = field(x_field, class) else {
            notes.push(format!("{}: {at} gives no `{x_field}`; left out", plot.file));
            continue;
        };
        let by_value = by.and_then(|b| field(b, class));
        let x = as_number(&xv);
        if plot.kind == PlotKind::Line && x.is_none() {
            notes.push(format!(
                "{}: {at}: `{x_field}` = {xv} is not a number; left out of the line plot",
                plot.file
            ));
            continue;
        }
        rows.push(Row {
            series: plot.series_name(by_value.as_ref()),
            x,
            label: value_text(&xv),
            repeat: run.repeat,
            y,
        });
    }
    rows
}

/// Mean of `ys`, and (over more than one repeat) the SD over repeats of each
/// repeat's mean.
fn mean_sd(ys: &[(usize, f64)]) -> (f64, Option<f64>) {
    let all: Vec<f64> = ys.iter().map(|p| p.1).collect();
    let (mean, _) = mean_and_sd(&all);
    let mut repeats: Vec<usize> = ys.iter().map(|p| p.0).collect();
    repeats.sort_unstable();
    repeats.dedup();
    if repeats.len() < 2 {
        return (mean, None);
    }
    let per: Vec<f64> = repeats
        .iter()
        .map(|r| {
            let of: Vec<f64> = ys.iter().filter(|p| p.0 == *r).map(|p| p.1).collect();
            mean_and_sd(&of).0
        })
        .collect();
    (mean, Some(mean_and_sd(&per).1))
}

/// Gathers what `plot` draws from the runs of `sweep`.
pub fn plot_data(plot: &SweepPlot, sweep: &SweepSettings, runs: &[SweepRun]) -> PlotData {
    let points = sweep.points();
    let mut notes = Vec::new();
    let mut rows = Vec::new();
    for run in runs {
        let Some(point) = points.get(run.point) else {
            notes.push(format!(
                "{}: run of unknown point {}; left out",
                plot.file, run.point
            ));
            continue;
        };
        rows.extend(rows_of(plot, point, run, &mut notes));
    }
    // Order of first appearance, for series and categories alike.
    let mut names: Vec<String> = Vec::new();
    let mut categories: Vec<String> = Vec::new();
    for r in &rows {
        if !names.contains(&r.series) {
            names.push(r.series.clone());
        }
        if !categories.contains(&r.label) {
            categories.push(r.label.clone());
        }
    }
    let bars = plot.kind == PlotKind::Bars;
    let mut series = Vec::new();
    for name in names {
        let of: Vec<&Row> = rows.iter().filter(|r| r.series == name).collect();
        let mut keys: Vec<&str> = Vec::new();
        for r in &of {
            if !keys.contains(&r.label.as_str()) {
                keys.push(&r.label);
            }
        }
        let points = keys
            .iter()
            .map(|key| {
                let at: Vec<&&Row> = of.iter().filter(|r| r.label == *key).collect();
                let ys: Vec<(usize, f64)> = at.iter().map(|r| (r.repeat, r.y)).collect();
                let (y, sd) = mean_sd(&ys);
                let x = if bars {
                    categories.iter().position(|c| c == key).unwrap_or(0) as f64
                } else {
                    at[0].x.unwrap_or(f64::NAN)
                };
                Point { x, y, sd }
            })
            .collect();
        series.push(PlotSeries { name, points });
    }
    let mut reference = Vec::new();
    for r in &plot.reference {
        let mut points = Vec::new();
        for &[x, y] in &r.points {
            let x = if bars {
                let label = value_text(&toml::Value::Float(x));
                let i = match categories.iter().position(|c| *c == label) {
                    Some(i) => i,
                    None => {
                        categories.push(label);
                        categories.len() - 1
                    }
                };
                i as f64
            } else {
                x
            };
            points.push(Point { x, y, sd: None });
        }
        reference.push(PlotSeries {
            name: r.name.clone(),
            points,
        });
    }
    PlotData {
        series,
        reference,
        categories,
        notes,
    }
}

/// The plot's title, axis titles: as declared, else from the metric and the
/// x field (`"value"` reads as what the sweep varies).
fn titles(plot: &SweepPlot, sweep: &SweepSettings) -> (String, String, String) {
    let x_name = match plot.x_field() {
        "value" => sweep.describe(),
        "class" => "class (true angle, degrees)".to_string(),
        other => other.to_string(),
    };
    let title = plot
        .title
        .clone()
        .unwrap_or_else(|| format!("{} across {x_name}", plot.metric));
    let x = plot.x_label.clone().unwrap_or(x_name);
    let y = plot.y_label.clone().unwrap_or_else(|| plot.metric.clone());
    (title, x, y)
}

/// Draws `plot` from the runs into `out_dir`; returns the file written and
/// the notes on what was left out.
pub fn write(
    plot: &SweepPlot,
    sweep: &SweepSettings,
    runs: &[SweepRun],
    out_dir: &Path,
) -> (std::io::Result<PathBuf>, PlotData) {
    let data = plot_data(plot, sweep, runs);
    let (title, x_title, y_title) = titles(plot, sweep);
    let path = out_dir.join(&plot.file);
    let figure = Figure {
        title: &title,
        x_title: &x_title,
        y_title: &y_title,
        series: &data.series,
        reference: &data.reference,
    };
    let written = match plot.kind {
        PlotKind::Line => palpate_stages::plot::line_plot(&path, &figure),
        PlotKind::Bars => palpate_stages::plot::bar_plot(
            &path,
            &BarPlot {
                figure,
                categories: &data.categories,
                value_labels: plot.value_labels,
            },
        ),
    };
    (written.map(|()| path), data)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_average_over_points_and_spread_over_repeats() {
        // Two placements per repeat: the mean is over all four rows, the SD
        // over the two repeats' means (1.5 and 3.5), not over the rows.
        let (m, sd) = mean_sd(&[(0, 1.0), (0, 2.0), (1, 3.0), (1, 4.0)]);
        assert_eq!(m, 2.5);
        assert_eq!(sd, Some(1.0));
        // One repeat: no error bar, however many points.
        assert_eq!(mean_sd(&[(0, 1.0), (0, 3.0)]), (2.0, None));
        // A float category matches an integer reference, as plots label them.
        assert_eq!(value_text(&toml::Value::Float(4.0)), "4");
        assert_eq!(value_text(&toml::Value::Integer(4)), "4");
        assert_eq!(value_text(&toml::Value::Float(0.6)), "0.6");
    }
}
