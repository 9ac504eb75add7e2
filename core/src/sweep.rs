//! Sweeps: running a graph once per point (a key set to one value), per repeat,
//! with one table across the sweep.
//!
//! A graph's `[sweep]` table ([`SweepSettings`]) gives its points in one of two
//! forms:
//!
//! * single key: `key` and `values`; point `p` is the graph with
//!   `key = values[p]`, labelled by the value and reporting into `<out>/<label>/`;
//! * series: `[[sweep.series]]` tables, each with a `name`, a `key`, `values`
//!   and optional constant overrides `set`; the sweep is the union of the
//!   series' points, each changing ONE key from the base graph (after its
//!   series' `set`), labelled `<series>/<value>` and reporting into
//!   `<out>/<series>/<value>/`. Series let one sweep explore several settings
//!   (a grid step, a hop, an encoder step, ...) around one base graph, which is
//!   what an accuracy-time frontier needs: a grid of every combination would
//!   multiply the run time, and each setting's effect is read against the base.
//!
//! Repeat `r` of a point uses `[run] seed = seed + r` (and reports into
//! `.../r<r>/`); a point whose last repeat's seed would pass `u64::MAX` is
//! an error naming `run.seed` and `sweep.repeats` (it wrapped to 0, 1, ...).
//! Every point is loaded (and so checked) before any runs; an error names the point's series (or key) and value. All points share one
//! [`Cache`]: a stage whose type, settings, seed, protocol and inputs did not change is not
//! run again, so sweeping a downstream key (a WSS weighting, a jitter width, a
//! grid step) does not re-simulate, re-encode or retrain; the cache keeps each
//! stage's timing from the run that computed it, so every point still reports
//! what each of its stages costs.
//!
//! The summary gives, per point, each metric's mean and population SD over the
//! repeats.

use crate::graph::{
    load_str, Diagnostic, Graph, LoadErrors, LoadOptions, Severity, SweepPoint, SweepSettings,
};
use crate::runtime::{run, Cache, RunError, RunOptions, RunResult};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// One run of a sweep.
#[derive(Debug)]
pub struct SweepRun {
    /// Index of the point (into [`SweepSettings::points`]).
    pub point: usize,
    /// The point's series (`None` in the single-key form).
    pub series: Option<String>,
    /// The key varied.
    pub key: String,
    /// The value.
    pub value: toml::Value,
    /// The point's label: the value's [`label`], prefixed by `<series>/` in the
    /// series form (also the report sub-directory).
    pub label: String,
    /// The point's graph as run: its `out_dir` is the point's report directory,
    /// and a series' `set` may have rewired it (reports that follow a stage's
    /// upstream path read it here).
    pub graph: Graph,
    /// Repeat number.
    pub repeat: usize,
    /// The seed the run used.
    pub seed: u64,
    /// What it produced.
    pub result: RunResult,
}

/// A failed sweep.
#[derive(Debug, thiserror::Error)]
pub enum SweepError {
    /// A point's graph did not load.
    #[error("{0}")]
    Load(LoadErrors),
    /// A point's run failed.
    #[error("sweep value {label}: {error}")]
    Run {
        /// The value's label.
        label: String,
        /// The failure.
        error: RunError,
    },
}

/// A short, file-name-safe label of a sweep value: a string as it is, a table
/// as `k=v,...`, an array as its items joined by `-` (`[60, 30]` -> `60-30`),
/// anything else as TOML writes it; characters other than letters, digits and
/// `-_.=,` become `_`.
pub fn label(value: &toml::Value) -> String {
    let raw = match value {
        toml::Value::String(s) => s.clone(),
        toml::Value::Array(a) => a.iter().map(label).collect::<Vec<_>>().join("-"),
        toml::Value::Table(t) => t
            .iter()
            .map(|(k, v)| format!("{k}={}", label(v)))
            .collect::<Vec<_>>()
            .join(","),
        other => other.to_string(),
    };
    raw.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "-_.=,".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// A point's label: the value's [`label`], prefixed by `<series>/` in the series
/// form.
pub fn point_label(point: &SweepPoint) -> String {
    match &point.series {
        Some(s) => format!("{s}/{}", label(&point.value)),
        None => label(&point.value),
    }
}

/// The seeds of a point's `repeats` repeats from `seed`: `seed..=seed +
/// repeats - 1`; `None` when the last one overflows u64.
pub fn repeat_seeds(seed: u64, repeats: usize) -> Option<std::ops::RangeInclusive<u64>> {
    let last = seed.checked_add(u64::try_from(repeats.saturating_sub(1)).ok()?)?;
    Some(seed..=last)
}

/// The error of a seed range that overflows u64 (see [`repeat_seeds`]).
pub fn seed_overflow_message(seed: u64, repeats: usize) -> String {
    let extra = repeats.saturating_sub(1) as u64;
    format!(
        "`run.seed` = {seed} with `sweep.repeats` = {repeats} needs seeds {seed} to {seed} + {extra}, \
         past the largest seed {}; lower `run.seed` to at most {} or `sweep.repeats`",
        u64::MAX,
        u64::MAX.saturating_sub(extra)
    )
}

/// The seed a point's repeats start from: the swept value when the point
/// is over `run.seed` (`None` when that value is no seed: loading the point
/// then names it), else `base_seed`.
pub fn point_seed(point: &SweepPoint, base_seed: u64) -> Option<u64> {
    match (point.key.as_str(), &point.value) {
        ("run.seed", toml::Value::Integer(v)) => u64::try_from(*v).ok(),
        ("run.seed", toml::Value::String(v)) => crate::graph::seed_from_digits(v),
        ("run.seed", _) => None,
        _ => Some(base_seed),
    }
}

/// Loads every (point, repeat) graph of a sweep, gathering every error. Point
/// indices are into [`SweepSettings::points`].
pub fn load_points(
    text: &str,
    file: &str,
    stem: &str,
    opts: &LoadOptions,
    base: &Graph,
    sweep: &SweepSettings,
) -> Result<Vec<(usize, usize, Graph)>, LoadErrors> {
    let mut graphs = Vec::new();
    let mut errors = Vec::new();
    for (p, point) in sweep.points().iter().enumerate() {
        let lbl = point_label(point);
        let value = &point.value;
        let at = match &point.series {
            Some(name) => format!("in sweep series `{name}`, with {} = {value}", point.key),
            None => format!("with sweep value {} = {value}", point.key),
        };
        // Repeat r shifts the seed by r; when the point is over the seed itself,
        // the swept value is the base (else the repeat's override would hide it).
        // A swept seed that is no seed (negative, not digits) is left as
        // written: loading the point then names it.
        let seed = point_seed(point, base.run.seed);
        if let Some(seed) = seed.filter(|&s| repeat_seeds(s, sweep.repeats).is_none()) {
            let message = seed_overflow_message(seed, sweep.repeats);
            let d = Diagnostic {
                severity: Severity::Error,
                file: file.to_string(),
                line: None,
                stage: None,
                key: Some("run.seed".into()),
                // The swept value is only news when the point is over the seed.
                message: if point.key == "run.seed" {
                    format!("{at}: {message}")
                } else {
                    format!("in [sweep]: {message}")
                },
            };
            if !errors.contains(&d) {
                errors.push(d);
            }
            continue;
        }
        for r in 0..sweep.repeats {
            let mut o = opts.clone();
            o.overrides.extend(point.set.iter().cloned());
            o.overrides.push((point.key.clone(), value.clone()));
            if let Some(seed) = seed {
                // Cannot overflow: checked above for the last repeat.
                let v = crate::graph::seed_value(seed.saturating_add(r as u64));
                o.overrides.push(("run.seed".into(), v));
            }
            o.out = Some(point_dir(&base.out_dir, &lbl, (sweep.repeats > 1).then_some(r)));
            match load_str(text, file, stem, &o) {
                Ok(g) => graphs.push((p, r, g)),
                Err(e) => {
                    for mut d in e.0.into_iter().filter(|d| d.severity == Severity::Error) {
                        d.message = format!("{at}: {}", d.message);
                        if !errors.contains(&d) {
                            errors.push(d);
                        }
                    }
                }
            }
        }
    }
    if errors.is_empty() {
        Ok(graphs)
    } else {
        Err(LoadErrors(errors))
    }
}

/// Runs a sweep of the graph in `path` (whose `[sweep]` is `base.sweep`).
pub fn run_file(
    path: &Path,
    opts: &LoadOptions,
    base: &Graph,
    run_opts: &RunOptions<'_>,
) -> Result<Vec<SweepRun>, SweepError> {
    let text = crate::input::read_text(path).map_err(|e| {
        SweepError::Load(LoadErrors(vec![Diagnostic {
            severity: Severity::Error,
            file: path.display().to_string(),
            line: None,
            stage: None,
            key: None,
            message: format!("cannot read the graph file: {e}"),
        }]))
    })?;
    let mut opts = opts.clone();
    if opts.base_dir.is_none() {
        opts.base_dir = Some(path.parent().map(Path::to_path_buf).unwrap_or_default());
    }
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("graph");
    run_text(&text, &path.display().to_string(), stem, &opts, base, run_opts)
}

/// Runs a sweep of the graph text.
pub fn run_text(
    text: &str,
    file: &str,
    stem: &str,
    opts: &LoadOptions,
    base: &Graph,
    run_opts: &RunOptions<'_>,
) -> Result<Vec<SweepRun>, SweepError> {
    let Some(sweep) = &base.sweep else {
        return Err(SweepError::Load(LoadErrors(vec![Diagnostic {
            severity: Severity::Error,
            file: file.to_string(),
            line: None,
            stage: None,
            key: None,
            message: "the graph has no [sweep] table".into(),
        }])));
    };
    let graphs = load_points(text, file, stem, opts, base, sweep).map_err(SweepError::Load)?;
    let points = sweep.points();
    let own_cache = Cache::default();
    let cache = run_opts.cache.unwrap_or(&own_cache);
    for (_, _, g) in &graphs {
        cache.expect(g);
    }
    let mut runs = Vec::with_capacity(graphs.len());
    for (p, r, g) in graphs {
        let point = &points[p];
        let lbl = point_label(point);
        let o = RunOptions {
            progress: run_opts.progress,
            cache: Some(cache),
            keep_outputs: run_opts.keep_outputs,
        };
        let result = run(&g, &o).map_err(|error| SweepError::Run {
            label: lbl.clone(),
            error,
        })?;
        runs.push(SweepRun {
            point: p,
            series: point.series.clone(),
            key: point.key.clone(),
            value: point.value.clone(),
            label: lbl,
            repeat: r,
            seed: g.run.seed,
            result,
            graph: g,
        });
    }
    Ok(runs)
}

/// One row of a sweep's summary: a point and each metric's statistics.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct SummaryRow {
    /// The point's label.
    pub label: String,
    /// The point's series (`None` in the single-key form).
    pub series: Option<String>,
    /// The value as a number, when it is one (for plots).
    pub x: Option<f64>,
    /// (metric, mean, population SD, runs) per metric.
    pub metrics: Vec<(String, f64, f64, usize)>,
}

/// Mean and population SD (`sqrt(mean (v − mean)²)`) of `vals`; `(0, 0)`
/// for none. The one definition of a sweep's "mean ± SD", in tables and plots.
pub fn mean_sd(vals: &[f64]) -> (f64, f64) {
    let n = vals.len().max(1) as f64;
    let mean = vals.iter().sum::<f64>() / n;
    let sd = (vals.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
    (mean, sd)
}

/// A TOML number as `f64` (integers converted); `None` for anything else.
pub fn as_number(v: &toml::Value) -> Option<f64> {
    match v {
        toml::Value::Integer(i) => Some(*i as f64),
        toml::Value::Float(f) => Some(*f),
        _ => None,
    }
}

/// Mean and SD of each metric per sweep point, over repeats. `wanted` filters
/// metric names (empty: all).
pub fn summarize(runs: &[SweepRun], wanted: &[String]) -> Vec<SummaryRow> {
    let mut rows: Vec<SummaryRow> = Vec::new();
    let points = runs.iter().map(|r| r.point).max().map_or(0, |m| m + 1);
    for p in 0..points {
        let of_point: Vec<&SweepRun> = runs.iter().filter(|r| r.point == p).collect();
        let Some(first) = of_point.first() else { continue };
        let mut names: Vec<String> = Vec::new();
        for r in &of_point {
            for (name, _) in r.result.reports.iter().flat_map(|(_, rep)| rep.metrics.iter()) {
                if (wanted.is_empty() || wanted.contains(name)) && !names.contains(name) {
                    names.push(name.clone());
                }
            }
        }
        let metrics = names
            .into_iter()
            .map(|name| {
                let vals: Vec<f64> = of_point
                    .iter()
                    .filter_map(|r| {
                        r.result
                            .reports
                            .iter()
                            .flat_map(|(_, rep)| rep.metrics.iter())
                            .find(|(n, _)| *n == name)
                            .map(|(_, v)| *v)
                    })
                    .collect();
                let (mean, sd) = mean_sd(&vals);
                (name, mean, sd, vals.len())
            })
            .collect();
        let x = as_number(&first.value);
        rows.push(SummaryRow {
            label: first.label.clone(),
            series: first.series.clone(),
            x,
            metrics,
        });
    }
    rows
}

/// The summary as a terminal table: one row per value, one column per metric
/// (`mean ± sd` when there are repeats). With more metrics than values
/// (a graph of many estimators swept over its seeds: one value, 80
/// metrics) the table is turned: one row per metric, one column per
/// value (the key heads the metric column), so it reads down the page
/// instead of as one line hundreds of characters wide.
pub fn render(key: &str, rows: &[SummaryRow]) -> String {
    let mut names: Vec<&str> = Vec::new();
    for r in rows {
        for (n, ..) in &r.metrics {
            if !names.contains(&n.as_str()) {
                names.push(n);
            }
        }
    }
    // cells[row][metric], formatted once for widths and for writing.
    let cells: Vec<Vec<String>> = rows
        .iter()
        .map(|r| {
            names
                .iter()
                .map(|n| match r.metrics.iter().find(|m| m.0 == *n) {
                    Some((_, mean, sd, k)) if *k > 1 => format!("{mean:.3} ± {sd:.3}"),
                    Some((_, mean, ..)) => format!("{mean:.3}"),
                    None => "-".into(),
                })
                .collect()
        })
        .collect();
    let mut s = String::new();
    if names.len() > rows.len() {
        // The key heads the metric column; each value heads its own,
        // as wide as its label or its widest cell.
        let width = names
            .iter()
            .map(|n| n.len())
            .chain([key.len()])
            .max()
            .unwrap_or(8);
        let cols: Vec<usize> = rows
            .iter()
            .zip(&cells)
            .map(|(r, c)| {
                c.iter()
                    .map(|x| x.chars().count())
                    .chain([r.label.chars().count()])
                    .max()
                    .unwrap_or(0)
            })
            .collect();
        let _ = write!(s, "{key:<width$}");
        for (r, w) in rows.iter().zip(&cols) {
            let _ = write!(s, "  {:>w$}", r.label);
        }
        s.push('\n');
        for (m, n) in names.iter().enumerate() {
            let _ = write!(s, "{n:<width$}");
            for (c, w) in cells.iter().zip(&cols) {
                let _ = write!(s, "  {:>w$}", c[m]);
            }
            s.push('\n');
        }
        return s;
    }
    let width = rows
        .iter()
        .map(|r| r.label.len())
        .chain([key.len()])
        .max()
        .unwrap_or(8);
    let _ = write!(s, "{key:<width$}");
    for n in &names {
        let _ = write!(s, "  {n:>20}");
    }
    s.push('\n');
    for (r, c) in rows.iter().zip(&cells) {
        let _ = write!(s, "{:<width$}", r.label);
        for x in c {
            let _ = write!(s, "  {x:>20}");
        }
        s.push('\n');
    }
    s
}

/// Where a point's reports go, as [`load_points`] sets it.
pub fn point_dir(base_out: &Path, label: &str, repeat: Option<usize>) -> PathBuf {
    match repeat {
        Some(r) => base_out.join(label).join(format!("r{r}")),
        None => base_out.join(label),
    }
}

#[cfg(test)]
mod tests {
    use super::{render, SummaryRow};

    fn row(label: &str, metrics: &[(&str, f64, f64, usize)]) -> SummaryRow {
        SummaryRow {
            label: label.into(),
            series: None,
            x: label.parse().ok(),
            metrics: metrics.iter().map(|&(n, m, s, k)| (n.into(), m, s, k)).collect(),
        }
    }

    /// Few metrics over many values: a row per value. Many metrics over one
    /// value (a graph's seeds): a row per metric, the value as the column.
    #[test]
    fn the_longer_side_of_a_sweep_table_runs_down_the_page() {
        let rows: Vec<SummaryRow> = (1..=3)
            .map(|v| row(&v.to_string(), &[("a.mae_deg", v as f64, 0.5, 5)]))
            .collect();
        let by_value = render("speed", &rows);
        let t = &by_value;
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(lines.len(), 4, "{t}");
        assert!(
            lines[0].starts_with("speed") && lines[0].contains("a.mae_deg"),
            "{t}"
        );
        assert!(
            lines[2].starts_with('2') && lines[2].contains("2.000 ± 0.500"),
            "{t}"
        );

        let many: Vec<(String, f64)> = (0..12).map(|i| (format!("est{i}.mae_deg"), i as f64)).collect();
        let metrics: Vec<(&str, f64, f64, usize)> =
            many.iter().map(|(n, v)| (n.as_str(), *v, 0.0, 1)).collect();
        let one = [row("1", &metrics)];
        let t = render("run.seed", &one);
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(lines.len(), 13, "{t}");
        assert!(
            lines[0].starts_with("run.seed") && lines[0].ends_with(" 1"),
            "{t}"
        );
        assert!(
            lines[8].starts_with("est7.mae_deg") && lines[8].ends_with("7.000"),
            "{t}"
        );
        // Every line of either form is short, and the turned table's
        // columns line up.
        assert!(
            by_value.lines().chain(t.lines()).all(|l| l.len() < 80),
            "{by_value}{t}"
        );
        assert!(
            t.lines().all(|l| l.chars().count() == lines[0].chars().count()),
            "{t}"
        );
    }
}
