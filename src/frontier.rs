//! The accuracy-time frontier of a sweep: what each estimator's accuracy costs
//! in compute time and in palpation time, and which settings are worth it.
//!
//! A sweep whose `[sweep]` table lists `frontier = ["wss", "ann", ...]`
//! (estimator stage ids, each read by an `mae` sink) gets, after its runs, one
//! row per (sweep point, estimator):
//!
//! * **MAE** and its SD over trials: the `mae` sink's `<id>.mae_deg` and
//!   `<id>.sd_deg` ("no edge" answers are left out of the MAE and counted in
//!   `no_edge`, as the sink does).
//! * **compute time per trial**, ms: the sum, over the stages on the
//!   estimator's upstream path (every stage it reads, directly or not, and the
//!   estimator itself), of each stage's median per-trial wall time. For a
//!   trained estimator the per-trial time is its prediction; its training is
//!   the separate **training time per fold** (median over folds, s). A stage
//!   served from the sweep cache reports the times of the run that computed it
//!   (the runtime's [`Cache`](palpate_core::Cache) keeps them), so a point costs
//!   what it would cost run alone. The path's *sources* (the scene simulation
//!   here, a file reader or the sensor itself elsewhere) are left out of the
//!   sum and reported as `source_ms`: producing the data is not part of
//!   estimating from it, and a simulated scene's cost would otherwise swamp
//!   the differences between estimators' pipelines. The median (not the mean)
//!   per stage, because a shared two-core machine gives a few slow outliers;
//!   a sum of medians is not the median of sums, but the stages run one after
//!   another on each trial, so it estimates a typical trial's cost.
//! * **decision time**, ms: the `mae` sink's `<id>.decision_ms`, the median
//!   palpation from the edge's first contact the answers needed (defined in
//!   the `mae` sink's and the estimators' docs).
//!
//! With repeats, a point's values are means over its repeats.
//!
//! Every series of a sweep usually includes the base value, and a setting of
//! one estimator leaves the others as they were, so many rows repeat the same
//! configuration (the same stages with the same settings on the estimator's
//! path, and the same seed). Such a row is listed with `same_as` naming the
//! first point with that configuration and is left out of the frontiers and
//! plots, so each configuration counts once; the base graph's configuration
//! is flagged `is_base` and drawn with its own marker.
//!
//! # Pareto frontier
//!
//! Against each time (compute, decision) separately, a row is on the frontier
//! when no other row is at least as good in both MAE and time and strictly
//! better in one ([`pareto`]). Exact ties (the same MAE and time) do not
//! dominate each other, so duplicates are all on the frontier. Rows without an
//! MAE (every trial "no edge") or without a time are never on it and dominate
//! nothing. The overall frontier is taken over every estimator at once: it
//! answers "for this much time, what is the best accuracy any setting gives".
//! Each estimator's own frontier (over its rows only) is marked too
//! (`on_own_frontier_*`) and drawn dashed in its colour: it shows what that
//! estimator's settings trade, even where another estimator dominates it.
//!
//! # Files
//!
//! Into the sweep's output directory: `frontier.md` (every row, then the
//! frontier points by time), `frontier.csv`, `frontier.json`,
//! `frontier_compute.svg` (MAE against compute time per trial, log x axis)
//! and `frontier_decision.svg` (MAE against decision time), coloured by
//! estimator with a marker per series, the overall frontier ringed and
//! joined by a black step line, each estimator's own frontier dashed.

use palpate_core::runtime::median_p95;
use palpate_core::sweep::{label, SweepRun};
use palpate_core::{Graph, RunResult};
use serde::Serialize;
use std::collections::{HashMap, HashSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// One (sweep point, estimator) of the frontier table.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FrontierRow {
    /// The point's series (the swept key in the single-key form).
    pub series: String,
    /// The value's label.
    pub value: String,
    /// The point's label (`<series>/<value>` in the series form).
    pub point: String,
    /// The estimator's stage id.
    pub estimator: String,
    /// MAE, degrees; `None` when no trial was answered.
    pub mae_deg: Option<f64>,
    /// SD of the absolute errors, degrees.
    pub sd_deg: Option<f64>,
    /// "No edge" answers.
    pub no_edge: f64,
    /// Compute time per trial, ms: the estimator's upstream path without its sources.
    pub compute_ms: f64,
    /// Of it, the estimator's own median per-trial time (prediction), ms.
    pub estimator_ms: f64,
    /// Median per-trial time of the path's sources (data production), ms.
    pub source_ms: f64,
    /// Median decision time, ms of palpation from first contact.
    pub decision_ms: Option<f64>,
    /// Median training time per fold, s (trained estimators).
    pub train_s_per_fold: Option<f64>,
    /// Stages of the path (sources left out) served from the sweep cache.
    pub cached_stages: usize,
    /// Runs (repeats) averaged.
    pub runs: usize,
    /// The base graph's configuration for this estimator.
    pub is_base: bool,
    /// The first point with the same configuration, when this row repeats it
    /// (then it is on no frontier and not plotted).
    pub same_as: Option<String>,
    /// On the overall MAE-against-compute-time frontier.
    pub on_frontier_compute: bool,
    /// On the overall MAE-against-decision-time frontier.
    pub on_frontier_decision: bool,
    /// On this estimator's own MAE-against-compute-time frontier.
    pub on_own_frontier_compute: bool,
    /// On this estimator's own MAE-against-decision-time frontier.
    pub on_own_frontier_decision: bool,
}

/// Which of `points` (`(time, error)`, lower is better in both) are Pareto
/// optimal: no other point has both coordinates lower or equal and one
/// strictly lower. Points with a non-finite coordinate are never optimal and
/// dominate nothing; equal points do not dominate each other.
pub fn pareto(points: &[(f64, f64)]) -> Vec<bool> {
    let finite = |p: &(f64, f64)| p.0.is_finite() && p.1.is_finite();
    points
        .iter()
        .map(|p| {
            finite(p)
                && !points
                    .iter()
                    .any(|q| finite(q) && q.0 <= p.0 && q.1 <= p.1 && (q.0 < p.0 || q.1 < p.1))
        })
        .collect()
}

/// The stages on `id`'s upstream path in `graph`: every stage it reads,
/// directly or not, and itself.
pub fn upstream(graph: &Graph, id: &str) -> Vec<String> {
    let inputs: HashMap<&str, &[String]> = graph
        .nodes
        .iter()
        .map(|n| (n.id.as_str(), n.inputs.as_slice()))
        .collect();
    let mut seen: HashSet<&str> = HashSet::new();
    let mut stack = vec![id];
    while let Some(s) = stack.pop() {
        if seen.insert(s) {
            stack.extend(
                inputs
                    .get(s)
                    .into_iter()
                    .flat_map(|v| v.iter().map(String::as_str)),
            );
        }
    }
    graph
        .nodes
        .iter()
        .filter(|n| seen.contains(n.id.as_str()))
        .map(|n| n.id.clone())
        .collect()
}

/// A configuration's identity: the seed and, for every stage on the path, its
/// id, type, inputs and settings.
pub fn config_key(graph: &Graph, path: &[String]) -> String {
    let mut key = format!("seed={}", graph.run.seed);
    for n in graph.nodes.iter().filter(|n| path.contains(&n.id)) {
        let settings = serde_json::to_string(&n.config).unwrap_or_default();
        let _ = write!(key, "|{}:{}<{}>{settings}", n.id, n.type_name, n.inputs.join(","));
    }
    key
}

/// Per-run times of one estimator.
struct Times {
    compute: f64,
    own: f64,
    source: f64,
    train: Option<f64>,
    cached: usize,
}

fn times(result: &RunResult, path: &[String], estimator: &str) -> Times {
    let ms = |t: &palpate_core::StageTiming| median_p95(&t.per_trial).0.as_secs_f64() * 1e3;
    let mut out = Times {
        compute: 0.0,
        own: 0.0,
        source: 0.0,
        train: None,
        cached: 0,
    };
    for t in result.timings.iter().filter(|t| path.contains(&t.id)) {
        if t.role == "source" {
            out.source += ms(t);
            continue;
        }
        out.compute += ms(t);
        out.cached += usize::from(t.cached);
        if t.id == estimator {
            out.own = ms(t);
            if t.fits.len() > 1 {
                out.train = Some(median_p95(&t.fits).0.as_secs_f64());
            }
        }
    }
    out
}

fn metric(result: &RunResult, name: &str) -> Option<f64> {
    result
        .reports
        .iter()
        .flat_map(|(_, r)| r.metrics.iter())
        .find(|(n, _)| n == name)
        .map(|(_, v)| *v)
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// Builds the frontier rows of a sweep's runs for `estimators`, in point then
/// estimator order, with repeated configurations and the frontiers marked.
/// `base` is the sweep's base graph (for `is_base`).
pub fn rows(
    runs: &[SweepRun],
    estimators: &[String],
    base: Option<&Graph>,
) -> Result<Vec<FrontierRow>, String> {
    let mut out = Vec::new();
    let mut seen: HashMap<String, String> = HashMap::new();
    let points = runs.iter().map(|r| r.point).max().map_or(0, |m| m + 1);
    for p in 0..points {
        let of_point: Vec<&SweepRun> = runs.iter().filter(|r| r.point == p).collect();
        let Some(first) = of_point.first() else { continue };
        for est in estimators {
            let (mut mae, mut sd, mut no_edge, mut dec) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
            let (mut comp, mut own, mut src, mut train, mut cached) =
                (Vec::new(), Vec::new(), Vec::new(), Vec::new(), 0);
            for r in &of_point {
                let res = &r.result;
                let Some(ne) = metric(res, &format!("{est}.no_edge")) else {
                    return Err(format!(
                        "sweep point {}: no metric `{est}.no_edge`: estimator `{est}` feeds no mae sink",
                        r.label
                    ));
                };
                no_edge.push(ne);
                mae.extend(metric(res, &format!("{est}.mae_deg")));
                sd.extend(metric(res, &format!("{est}.sd_deg")));
                dec.extend(metric(res, &format!("{est}.decision_ms")));
                let path = upstream(&r.graph, est);
                let t = times(res, &path, est);
                comp.push(t.compute);
                own.push(t.own);
                src.push(t.source);
                train.extend(t.train);
                cached = cached.max(t.cached);
            }
            let key = config_key(&first.graph, &upstream(&first.graph, est));
            let is_base = base.is_some_and(|g| config_key(g, &upstream(g, est)) == key);
            let same_as = match seen.get(&key) {
                Some(p) => Some(p.clone()),
                None => {
                    seen.insert(key, first.label.clone());
                    None
                }
            };
            // A metric missing from some repeats (all "no edge" there) is not averaged in.
            let all = |v: &Vec<f64>| if v.len() == of_point.len() { mean(v) } else { None };
            out.push(FrontierRow {
                series: first.series.clone().unwrap_or_else(|| first.key.clone()),
                value: label(&first.value),
                point: first.label.clone(),
                estimator: est.clone(),
                mae_deg: all(&mae),
                sd_deg: all(&sd),
                no_edge: mean(&no_edge).unwrap_or(0.0),
                compute_ms: mean(&comp).unwrap_or(0.0),
                estimator_ms: mean(&own).unwrap_or(0.0),
                source_ms: mean(&src).unwrap_or(0.0),
                decision_ms: all(&dec),
                train_s_per_fold: mean(&train),
                cached_stages: cached,
                runs: of_point.len(),
                is_base,
                same_as,
                on_frontier_compute: false,
                on_frontier_decision: false,
                on_own_frontier_compute: false,
                on_own_frontier_decision: false,
            });
        }
    }
    mark(&mut out);
    Ok(out)
}

/// Marks the overall and per-estimator frontiers, against both times, over the
/// rows that do not repeat an earlier configuration.
pub fn mark(rows: &mut [FrontierRow]) {
    let nan = f64::NAN;
    let point = |r: &FrontierRow, decision: bool| {
        if r.same_as.is_some() {
            return (nan, nan);
        }
        let t = if decision {
            r.decision_ms.unwrap_or(nan)
        } else {
            r.compute_ms
        };
        (t, r.mae_deg.unwrap_or(nan))
    };
    for decision in [false, true] {
        let pts: Vec<(f64, f64)> = rows.iter().map(|r| point(r, decision)).collect();
        let all = pareto(&pts);
        let mut own = vec![false; rows.len()];
        let mut names: Vec<String> = Vec::new();
        for r in rows.iter() {
            if !names.contains(&r.estimator) {
                names.push(r.estimator.clone());
            }
        }
        for name in &names {
            let idx: Vec<usize> = (0..rows.len()).filter(|&i| &rows[i].estimator == name).collect();
            let sub: Vec<(f64, f64)> = idx.iter().map(|&i| pts[i]).collect();
            for (&i, on) in idx.iter().zip(pareto(&sub)) {
                own[i] = on;
            }
        }
        for ((r, a), o) in rows.iter_mut().zip(all).zip(own) {
            if decision {
                r.on_frontier_decision = a;
                r.on_own_frontier_decision = o;
            } else {
                r.on_frontier_compute = a;
                r.on_own_frontier_compute = o;
            }
        }
    }
}

fn opt(v: Option<f64>, prec: usize) -> String {
    v.map_or_else(|| "-".to_string(), |x| format!("{x:.prec$}"))
}

/// A frontier cell: `overall` (on the overall frontier, hence on its own),
/// `own` (on its estimator's only), or empty.
fn mark_cell(all: bool, own: bool) -> &'static str {
    match (all, own) {
        (true, _) => "overall",
        (false, true) => "own",
        _ => "",
    }
}

/// Rows on a frontier (`on`), by estimator order when `per_estimator`, then by time.
fn frontier_by(
    rows: &[FrontierRow],
    on: impl Fn(&FrontierRow) -> bool,
    time: impl Fn(&FrontierRow) -> f64,
    per_estimator: bool,
) -> Vec<&FrontierRow> {
    let mut order: Vec<&str> = Vec::new();
    for r in rows {
        if !order.contains(&r.estimator.as_str()) {
            order.push(&r.estimator);
        }
    }
    let rank = |r: &FrontierRow| {
        if per_estimator {
            order.iter().position(|e| *e == r.estimator).unwrap_or(0)
        } else {
            0
        }
    };
    let mut v: Vec<&FrontierRow> = rows.iter().filter(|r| on(r)).collect();
    v.sort_by(|a, b| rank(a).cmp(&rank(b)).then(time(a).total_cmp(&time(b))));
    v
}

/// The time axis a frontier is drawn against.
#[derive(Clone, Copy)]
enum Axis {
    Compute,
    Decision,
}

impl Axis {
    fn time(self, r: &FrontierRow) -> Option<f64> {
        match self {
            Axis::Compute => Some(r.compute_ms),
            Axis::Decision => r.decision_ms,
        }
    }
    fn on(self, r: &FrontierRow) -> bool {
        match self {
            Axis::Compute => r.on_frontier_compute,
            Axis::Decision => r.on_frontier_decision,
        }
    }
    fn on_own(self, r: &FrontierRow) -> bool {
        match self {
            Axis::Compute => r.on_own_frontier_compute,
            Axis::Decision => r.on_own_frontier_decision,
        }
    }
    fn what(self) -> &'static str {
        match self {
            Axis::Compute => "compute time per trial",
            Axis::Decision => "decision time",
        }
    }
    fn column(self) -> &'static str {
        match self {
            Axis::Compute => "compute ms/trial",
            Axis::Decision => "decision ms",
        }
    }
}

/// The rows as Markdown: the full table, then each frontier's points by time
/// (overall, then per estimator).
pub fn to_markdown(rows: &[FrontierRow]) -> String {
    let mut s = String::from(
        "| series | value | estimator | MAE (°) | SD (°) | no edge | compute ms/trial | of which estimator | \
         decision ms | training s/fold | frontier (compute) | frontier (decision) | note |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let note = match (&r.same_as, r.is_base) {
            (Some(p), true) => format!("base, as {p}"),
            (Some(p), false) => format!("as {p}"),
            (None, true) => "base".to_string(),
            (None, false) => String::new(),
        };
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {:.2} | {:.2} | {} | {} | {} | {} | {note} |",
            r.series,
            r.value,
            r.estimator,
            opt(r.mae_deg, 2),
            opt(r.sd_deg, 2),
            r.no_edge,
            r.compute_ms,
            r.estimator_ms,
            opt(r.decision_ms, 0),
            opt(r.train_s_per_fold, 2),
            mark_cell(r.on_frontier_compute, r.on_own_frontier_compute),
            mark_cell(r.on_frontier_decision, r.on_own_frontier_decision)
        );
    }
    s.push_str(
        "\nA point is on a frontier when no other point has both lower-or-equal MAE and lower-or-equal \
         time, one strictly; `overall` = over every estimator, `own` = over its estimator's points only. \
         Rows that repeat an earlier configuration (`as ...`) count once.\n",
    );
    for axis in [Axis::Compute, Axis::Decision] {
        let time = |r: &FrontierRow| axis.time(r).unwrap_or(f64::NAN);
        for (title, per, on) in [
            (
                "Overall frontier",
                false,
                Box::new(move |r: &FrontierRow| axis.on(r)) as Box<dyn Fn(&FrontierRow) -> bool>,
            ),
            (
                "Each estimator's own frontier",
                true,
                Box::new(move |r: &FrontierRow| axis.on_own(r)),
            ),
        ] {
            let _ = write!(
                s,
                "\n{title} against {}, by time:\n\n| {} | MAE (°) | estimator | series | value |\n|---|---|---|---|---|\n",
                axis.what(),
                axis.column()
            );
            for r in frontier_by(rows, on, time, per) {
                let _ = writeln!(
                    s,
                    "| {:.2} | {} | {} | {} | {}{} |",
                    time(r),
                    opt(r.mae_deg, 2),
                    r.estimator,
                    r.series,
                    r.value,
                    if r.is_base { " (base)" } else { "" }
                );
            }
        }
    }
    s
}

fn csv_cell(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// The rows as CSV (empty cells for missing values).
pub fn to_csv(rows: &[FrontierRow]) -> String {
    let mut s = String::from(
        "series,value,estimator,mae_deg,sd_deg,no_edge,compute_ms,estimator_ms,source_ms,decision_ms,\
         train_s_per_fold,cached_stages,runs,is_base,same_as,on_frontier_compute,on_frontier_decision,\
         on_own_frontier_compute,on_own_frontier_decision\n",
    );
    let f = |v: Option<f64>| v.map_or(String::new(), |x| x.to_string());
    for r in rows {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            csv_cell(&r.series),
            csv_cell(&r.value),
            csv_cell(&r.estimator),
            f(r.mae_deg),
            f(r.sd_deg),
            r.no_edge,
            r.compute_ms,
            r.estimator_ms,
            r.source_ms,
            f(r.decision_ms),
            f(r.train_s_per_fold),
            r.cached_stages,
            r.runs,
            r.is_base,
            csv_cell(r.same_as.as_deref().unwrap_or("")),
            r.on_frontier_compute,
            r.on_frontier_decision,
            r.on_own_frontier_compute,
            r.on_own_frontier_decision
        );
    }
    s
}

/// The table for the terminal (rows repeating an earlier configuration left out).
pub fn render(rows: &[FrontierRow]) -> String {
    let w = rows.iter().map(|r| r.point.len()).chain([5]).max().unwrap_or(5);
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{:<w$}  {:<10} {:>8} {:>7} {:>11} {:>9} {:>11} {:>8}  frontier (compute / decision)",
        "point", "estimator", "MAE °", "no edge", "compute ms", "of which", "decision ms", "train s"
    );
    for r in rows.iter().filter(|r| r.same_as.is_none()) {
        let _ = writeln!(
            s,
            "{:<w$}  {:<10} {:>8} {:>7} {:>11.2} {:>9.2} {:>11} {:>8}  {} / {}{}",
            r.point,
            r.estimator,
            opt(r.mae_deg, 2),
            r.no_edge,
            r.compute_ms,
            r.estimator_ms,
            opt(r.decision_ms, 0),
            opt(r.train_s_per_fold, 2),
            mark_cell(r.on_frontier_compute, r.on_own_frontier_compute),
            mark_cell(r.on_frontier_decision, r.on_own_frontier_decision),
            if r.is_base { "  (base)" } else { "" }
        );
    }
    s
}

/// Writes `frontier.{md,csv,json}` and the two plots into `dir`. `series`
/// orders the marker groups (the base configuration gets one more, "base"),
/// `estimators` the colours.
pub fn write(
    dir: &Path,
    rows: &[FrontierRow],
    series: &[String],
    estimators: &[String],
) -> Result<Vec<PathBuf>, String> {
    use palpate_core::output::write_atomic;
    use palpate_stages::plot::{frontier_chart, FrontierChart, ScatterPoint};
    let mut files = Vec::new();
    let json = serde_json::to_vec_pretty(rows).map_err(|e| format!("encoding frontier.json: {e}"))?;
    for (name, bytes) in [
        ("frontier.md", to_markdown(rows).into_bytes()),
        ("frontier.csv", to_csv(rows).into_bytes()),
        ("frontier.json", json),
    ] {
        let path = dir.join(name);
        write_atomic(&path, &bytes).map_err(|e| format!("writing {}: {e}", path.display()))?;
        files.push(path);
    }
    let colors: Vec<&str> = estimators.iter().map(String::as_str).collect();
    let markers: Vec<&str> = series.iter().map(String::as_str).collect();
    let base_marker = markers.len();
    let base = rows.iter().any(|r| r.is_base).then_some("base");
    let index = |v: &[String], s: &str| v.iter().position(|x| x == s).unwrap_or(0);
    let charts = [
        (
            Axis::Compute,
            "frontier_compute.svg",
            "MAE against compute time per trial",
            "compute time per trial, ms (log scale; median per stage, summed; data source left out)",
            true,
        ),
        (
            Axis::Decision,
            "frontier_decision.svg",
            "MAE against decision time",
            "decision time, ms of palpation from first contact (median over trials)",
            false,
        ),
    ];
    for (axis, name, title, x_label, log_x) in charts {
        let unique: Vec<&FrontierRow> = rows.iter().filter(|r| r.same_as.is_none()).collect();
        let at = |r: &FrontierRow| Some((axis.time(r)?, r.mae_deg?));
        let points: Vec<ScatterPoint> = unique
            .iter()
            .filter_map(|r| {
                let (x, y) = at(r)?;
                Some(ScatterPoint {
                    x,
                    y,
                    color: index(estimators, &r.estimator),
                    marker: if r.is_base {
                        base_marker
                    } else {
                        index(series, &r.series)
                    },
                })
            })
            .collect();
        let front: Vec<(f64, f64)> = unique
            .iter()
            .filter(|r| axis.on(r))
            .filter_map(|r| at(r))
            .collect();
        let own: Vec<Vec<(f64, f64)>> = estimators
            .iter()
            .map(|e| {
                unique
                    .iter()
                    .filter(|r| &r.estimator == e && axis.on_own(r))
                    .filter_map(|r| at(r))
                    .collect()
            })
            .collect();
        let path = dir.join(name);
        frontier_chart(
            &path,
            &FrontierChart {
                title,
                x_label,
                y_label: "MAE, degrees",
                log_x,
                colors: &colors,
                markers: &markers,
                points: &points,
                frontier: &front,
                own_frontiers: &own,
                base,
            },
        )
        .map_err(|e| e.to_string())?;
        files.push(path);
    }
    Ok(files)
}

/// The frontier report of a sweep whose `[sweep] frontier` is set: builds the
/// rows, writes the files into the graph's output directory and returns the
/// terminal table (empty when the sweep asks for no frontier).
pub fn report(graph: &Graph, runs: &[SweepRun]) -> Result<String, String> {
    let Some(sweep) = &graph.sweep else {
        return Ok(String::new());
    };
    if sweep.frontier.is_empty() {
        return Ok(String::new());
    }
    let rows = rows(runs, &sweep.frontier, Some(graph))?;
    let series: Vec<String> = if sweep.series.is_empty() {
        vec![sweep.key.clone()]
    } else {
        sweep.series.iter().map(|s| s.name.clone()).collect()
    };
    write(&graph.out_dir, &rows, &series, &sweep.frontier)?;
    Ok(render(&rows))
}
