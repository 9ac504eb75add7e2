//! Presenting a run: the timing table, the run record (`run.json`) and a
//! sweep's summary.
//!
//! Timing: for every stage, the median and 95th percentile of its per-trial wall
//! time, the median and 95th percentile of its fits (trained estimators: one
//! fit per fold, i.e. the training time per fold; a model-based estimator fits
//! once, on nothing), its total wall time, and for estimators the estimates per
//! second of the stage's wall time. A stage served from a sweep's cache shows the
//! times of the run that computed it, marked `*`. Every run (and every point of
//! a sweep) writes the table into its output directory as `timing.md` and
//! `timing.csv`, beside `run.json`, which holds it too.

use palpate_core::runtime::median_p95;
use palpate_core::{Graph, RunResult};
use serde::Serialize;
use std::fmt::Write as _;
use std::time::Duration;

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// One stage's timing summary.
#[derive(Clone, Debug, Serialize)]
pub struct TimingRow {
    /// Stage id.
    pub stage: String,
    /// Stage type.
    pub type_name: String,
    /// Role.
    pub role: String,
    /// Trials processed.
    pub trials: usize,
    /// Median per-trial wall time, ms.
    pub median_ms: f64,
    /// 95th-percentile per-trial wall time, ms.
    pub p95_ms: f64,
    /// Number of fits (folds).
    pub fits: usize,
    /// Median fit time (training time per fold), ms.
    pub fit_median_ms: f64,
    /// 95th-percentile fit time, ms.
    pub fit_p95_ms: f64,
    /// Wall time of the whole stage, ms.
    pub total_ms: f64,
    /// Estimates per second of the stage's wall time (estimators only).
    pub estimates_per_s: Option<f64>,
    /// Served from a sweep's cache: the times are those of the run that computed it.
    pub cached: bool,
}

/// Summarises a run's timings.
pub fn timing_rows(result: &RunResult) -> Vec<TimingRow> {
    result
        .timings
        .iter()
        .map(|t| {
            let (median, p95) = median_p95(&t.per_trial);
            let (fit_median, fit_p95) = median_p95(&t.fits);
            let total = t.total.as_secs_f64();
            TimingRow {
                stage: t.id.clone(),
                type_name: t.type_name.clone(),
                role: t.role.to_string(),
                trials: t.per_trial.len(),
                median_ms: ms(median),
                p95_ms: ms(p95),
                fits: t.fits.len(),
                fit_median_ms: ms(fit_median),
                fit_p95_ms: ms(fit_p95),
                total_ms: total * 1e3,
                estimates_per_s: (t.role == "estimator" && total > 0.0)
                    .then(|| t.per_trial.len() as f64 / total),
                cached: t.cached,
            }
        })
        .collect()
}

fn stage_name(r: &TimingRow) -> String {
    if r.cached {
        format!("{}*", r.stage)
    } else {
        r.stage.clone()
    }
}

const CACHED_NOTE: &str = "* served from the sweep cache: times of the run that computed it";

/// One row's cells, as both the terminal and the Markdown table show them:
/// stage, type, trials, median and p95 ms per trial, fits, fit median and
/// p95 ms, total s, estimates/s.
fn cells(r: &TimingRow) -> [String; 10] {
    [
        stage_name(r),
        r.type_name.clone(),
        r.trials.to_string(),
        format!("{:.3}", r.median_ms),
        format!("{:.3}", r.p95_ms),
        r.fits.to_string(),
        format!("{:.1}", r.fit_median_ms),
        format!("{:.1}", r.fit_p95_ms),
        format!("{:.2}", r.total_ms / 1e3),
        r.estimates_per_s.map_or("-".to_string(), |v| format!("{v:.0}")),
    ]
}

/// Renders the timing table.
pub fn timing_table(rows: &[TimingRow]) -> String {
    const HEAD: [&str; 10] = [
        "stage",
        "type",
        "trials",
        "median ms",
        "p95 ms",
        "fits",
        "fit med ms",
        "fit p95 ms",
        "total s",
        "est/s",
    ];
    // Column widths; the first two are left-aligned names, the rest numbers.
    const WIDTH: [usize; 10] = [14, 14, 7, 12, 12, 6, 12, 12, 10, 10];
    let line = |c: &[String]| {
        let mut l = String::new();
        for (k, (cell, w)) in c.iter().zip(WIDTH).enumerate() {
            let sep = if k == 0 { "" } else { " " };
            let _ = if k < 2 {
                write!(l, "{sep}{cell:<w$}")
            } else {
                write!(l, "{sep}{cell:>w$}")
            };
        }
        l
    };
    let mut s = line(&HEAD.map(String::from));
    s.push('\n');
    for r in rows {
        s += &line(&cells(r));
        s.push('\n');
    }
    if rows.iter().any(|r| r.cached) {
        let _ = writeln!(s, "{CACHED_NOTE}");
    }
    s
}

/// The timing table as Markdown.
pub fn timing_markdown(rows: &[TimingRow]) -> String {
    let mut s = String::from(
        "Wall time per stage: per trial (median, p95), per fit (training per fold for trained \
         estimators; median, p95), the whole stage, and estimates per second of it.\n\n\
         | stage | type | role | trials | median ms/trial | p95 ms/trial | fits | fit median ms | \
         fit p95 ms | total s | estimates/s |\n|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let mut c = cells(r).to_vec();
        c.insert(2, r.role.clone());
        let _ = writeln!(s, "| {} |", c.join(" | "));
    }
    if rows.iter().any(|r| r.cached) {
        let _ = write!(s, "\n{CACHED_NOTE}\n");
    }
    s
}

/// The timing table as CSV.
pub fn timing_csv(rows: &[TimingRow]) -> String {
    let mut s = String::from(
        "stage,type,role,trials,median_ms,p95_ms,fits,fit_median_ms,fit_p95_ms,total_ms,estimates_per_s,cached\n",
    );
    for r in rows {
        let _ = writeln!(
            s,
            "{},{},{},{},{},{},{},{},{},{},{},{}",
            r.stage,
            r.type_name,
            r.role,
            r.trials,
            r.median_ms,
            r.p95_ms,
            r.fits,
            r.fit_median_ms,
            r.fit_p95_ms,
            r.total_ms,
            r.estimates_per_s.map_or(String::new(), |v| v.to_string()),
            r.cached
        );
    }
    s
}

/// Writes a run's `run.json`, `timing.md` and `timing.csv` into its output
/// directory; returns the files written.
pub fn write_run_files(graph: &Graph, result: &RunResult) -> Result<Vec<std::path::PathBuf>, String> {
    use palpate_core::output::write_atomic;
    let record = run_record(graph, result);
    let rows = &record.timing;
    let json =
        serde_json::to_vec_pretty(&record).map_err(|e| format!("cannot encode the run record: {e}"))?;
    let mut files = Vec::new();
    for (name, bytes) in [
        ("run.json", json),
        ("timing.md", timing_markdown(rows).into_bytes()),
        ("timing.csv", timing_csv(rows).into_bytes()),
    ] {
        let path = graph.out_dir.join(name);
        write_atomic(&path, &bytes).map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        files.push(path);
    }
    Ok(files)
}

/// The run record written to `<out>/run.json`.
#[derive(Serialize)]
pub struct RunRecord<'a> {
    /// The graph file.
    pub graph: &'a str,
    /// palpate's version.
    pub version: &'static str,
    /// Run settings.
    pub run: &'a palpate_core::RunSettings,
    /// Every stage's config, an object keyed by stage id (`{"wss": {"wss": {...}}}`:
    /// each value is the config tagged with its type, as typetag writes it).
    pub stages: serde_json::Map<String, serde_json::Value>,
    /// Timing per stage, in execution order.
    pub timing: Vec<TimingRow>,
    /// Every sink's metrics, an object keyed by metric name (`{"wss.mae_deg": 0.12}`);
    /// a non-finite value is written as `null`, as JSON has no NaN.
    pub metrics: serde_json::Map<String, serde_json::Value>,
    /// A live run's speed (`run --live`, `daq run`), absent for a batch run
    /// (whose `timing` is per stage; a live run's `timing` is empty).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub live: Option<&'a LiveRecord>,
}

/// How fast a live run went: its blocks' wall times through the chain.
#[derive(Serialize)]
pub struct LiveRecord {
    /// Trials streamed.
    pub trials: usize,
    /// Stream time fed, s (samples over their rate, summed over trials).
    pub stream_s: f64,
    /// Wall time of the whole replay, s (source, chain, printing, sinks).
    pub wall_s: f64,
    /// Blocks pushed through the chain.
    pub blocks: u64,
    /// Per block through the chain (the printing left out), µs: mean,
    /// median, 95th and 99th percentile (each at most 12.5 % above the exact
    /// value, from a histogram) and maximum.
    pub block_us: LatencyUs,
    /// Per stage of the chain, in order: its share of the blocks' time.
    pub stages: Vec<LiveStageRow>,
    /// The stream was stopped before its end (Ctrl-C in `palpate run
    /// --live`; in Python's `run_live`, also an exception in `on_update`);
    /// `trials` are those finished before.
    pub stopped: bool,
}

/// One stage's time in a live run (see [`LiveRecord::stages`]): per block
/// pushed through the chain (and per trial's final flush), the wall time the
/// stage spent on it.
#[derive(Serialize)]
pub struct LiveStageRow {
    /// Stage id.
    pub stage: String,
    /// Stage type.
    pub type_name: String,
    /// Blocks timed (the chain's blocks plus one flush per trial).
    pub blocks: u64,
    /// Per block, µs: mean, median, 95th and 99th percentile, maximum.
    pub block_us: LatencyUs,
    /// The stage's whole time, s.
    pub total_s: f64,
    /// Its share of the summed stage times, percent.
    pub share_pct: f64,
}

impl LatencyUs {
    fn of(l: &palpate_core::stream::BlockLatency) -> LatencyUs {
        let us = |ns: u64| ns as f64 / 1e3;
        LatencyUs {
            mean: l.mean_ns() / 1e3,
            median: us(l.quantile_ns(0.5)),
            p95: us(l.quantile_ns(0.95)),
            p99: us(l.quantile_ns(0.99)),
            max: us(l.max_ns()),
        }
    }
}

/// Block latencies in µs (see [`LiveRecord::block_us`]).
#[derive(Serialize)]
pub struct LatencyUs {
    /// Mean.
    pub mean: f64,
    /// Median.
    pub median: f64,
    /// 95th percentile.
    pub p95: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Maximum.
    pub max: f64,
}

impl LiveRecord {
    /// The record of a live run of `graph` that took `wall` in all.
    pub fn new(graph: &Graph, run: &palpate_core::stream::LiveRun, wall: std::time::Duration) -> LiveRecord {
        let l = &run.latency;
        let sum: u128 = run.stages.iter().map(|(_, l)| l.total_ns()).sum();
        let stages = run
            .stages
            .iter()
            .map(|(id, l)| LiveStageRow {
                stage: id.clone(),
                type_name: graph
                    .nodes
                    .iter()
                    .find(|n| &n.id == id)
                    .map_or_else(String::new, |n| n.type_name.clone()),
                blocks: l.blocks(),
                block_us: LatencyUs::of(l),
                total_s: l.total_ns() as f64 / 1e9,
                share_pct: if sum > 0 {
                    100.0 * l.total_ns() as f64 / sum as f64
                } else {
                    0.0
                },
            })
            .collect();
        LiveRecord {
            trials: run.trials,
            stream_s: run.stream_s,
            wall_s: wall.as_secs_f64(),
            blocks: l.blocks(),
            block_us: LatencyUs::of(l),
            stages,
            stopped: run.stopped,
        }
    }

    /// The per-stage table for the terminal: stage, type, blocks, mean,
    /// median, p95 and max µs per block, total s and share of the chain.
    pub fn stage_table(&self) -> String {
        let mut s = format!(
            "{:<14} {:<14} {:>10} {:>10} {:>10} {:>10} {:>10} {:>9} {:>7}\n",
            "stage", "type", "blocks", "mean us", "median us", "p95 us", "max us", "total s", "share"
        );
        for r in &self.stages {
            let b = &r.block_us;
            let _ = writeln!(
                s,
                "{:<14} {:<14} {:>10} {:>10.2} {:>10.2} {:>10.2} {:>10.1} {:>9.3} {:>6.1}%",
                r.stage, r.type_name, r.blocks, b.mean, b.median, b.p95, b.max, r.total_s, r.share_pct
            );
        }
        s
    }

    /// The per-stage table as Markdown (`live_timing.md`).
    pub fn stage_markdown(&self) -> String {
        let mut s = format!(
            "Live run: {} trials, {:.1} s of stream in {:.2} s of wall time; {} blocks through the \
             chain (per block mean {:.2} us, median {:.2} us, p95 {:.2} us, max {:.1} us).\n\n\
             Wall time each stage spent per block (its pushes; one flush per trial counted as a \
             block), and its share of the summed stage times.\n\n\
             | stage | type | blocks | mean us | median us | p95 us | p99 us | max us | total s | share % |\n\
             |---|---|---|---|---|---|---|---|---|---|\n",
            self.trials,
            self.stream_s,
            self.wall_s,
            self.blocks,
            self.block_us.mean,
            self.block_us.median,
            self.block_us.p95,
            self.block_us.max
        );
        for c in self.stage_cells(true) {
            let _ = writeln!(s, "| {} |", c.join(" | "));
        }
        s
    }

    /// Each stage's cells: stage, type, blocks, mean, median, p95, p99 and
    /// max µs, total s, share % (`round`: as the Markdown table shows them;
    /// else every digit, for the CSV).
    fn stage_cells(&self, round: bool) -> Vec<[String; 10]> {
        let f = |v: f64, d: usize| if round { format!("{v:.d$}") } else { v.to_string() };
        self.stages
            .iter()
            .map(|r| {
                let b = &r.block_us;
                [
                    r.stage.clone(),
                    r.type_name.clone(),
                    r.blocks.to_string(),
                    f(b.mean, 3),
                    f(b.median, 3),
                    f(b.p95, 3),
                    f(b.p99, 3),
                    f(b.max, 1),
                    f(r.total_s, 3),
                    f(r.share_pct, 1),
                ]
            })
            .collect()
    }

    /// The per-stage table as CSV (`live_timing.csv`).
    pub fn stage_csv(&self) -> String {
        let mut s =
            String::from("stage,type,blocks,mean_us,median_us,p95_us,p99_us,max_us,total_s,share_pct\n");
        for c in self.stage_cells(false) {
            let _ = writeln!(s, "{}", c.join(","));
        }
        s
    }

    /// One line for the terminal.
    pub fn summary(&self) -> String {
        let b = &self.block_us;
        if self.blocks == 0 {
            // Stopped before any trial began (nothing in contact): no
            // latency to give, rather than a row of zeros.
            return format!(
                "live replay: {:.2} s wall, no trial began: no block went through the chain",
                self.wall_s
            );
        }
        format!(
            "live replay: {:.2} s wall for {:.1} s of stream ({} trials, {:.0}x real time); \
             {} blocks through the chain, per block mean {:.1} us, median {:.1} us, p95 {:.1} us, \
             p99 {:.1} us, max {:.1} us",
            self.wall_s,
            self.stream_s,
            self.trials,
            self.stream_s / self.wall_s.max(1e-9),
            self.blocks,
            b.mean,
            b.median,
            b.p95,
            b.p99,
            b.max
        )
    }
}

/// Builds the run record.
pub fn run_record<'a>(graph: &'a Graph, result: &RunResult) -> RunRecord<'a> {
    record(graph, &result.reports, timing_rows(result), None)
}

/// The record of a run with these sink reports, timing rows and live speed.
fn record<'a>(
    graph: &'a Graph,
    reports: &[(String, palpate_core::SinkReport)],
    timing: Vec<TimingRow>,
    live: Option<&'a LiveRecord>,
) -> RunRecord<'a> {
    RunRecord {
        graph: &graph.file,
        version: env!("CARGO_PKG_VERSION"),
        run: &graph.run,
        stages: graph
            .nodes
            .iter()
            .map(|n| {
                (
                    n.id.clone(),
                    serde_json::to_value(&n.config).unwrap_or(serde_json::Value::Null),
                )
            })
            .collect(),
        timing,
        metrics: reports
            .iter()
            .flat_map(|(_, r)| r.metrics.iter())
            .map(|(k, v)| (k.clone(), serde_json::Value::from(*v)))
            .collect(),
        live,
    }
}

/// The run record of a live run (`run.json`): its `live` section, and an
/// empty batch timing table.
pub fn live_run_record<'a>(
    graph: &'a Graph,
    run: &palpate_core::stream::LiveRun,
    live: &'a LiveRecord,
) -> RunRecord<'a> {
    record(graph, &run.reports, Vec::new(), Some(live))
}

/// Writes a live run's `run.json` (its `live` record; the batch timing
/// table stays empty), `live_timing.md` and `live_timing.csv` (the per-stage
/// time per block) into the graph's output directory; returns the files
/// written. (Not `timing.md`: that is a batch run's per-trial table, which
/// a live run beside it must not overwrite.)
pub fn write_live_run_files(
    graph: &Graph,
    run: &palpate_core::stream::LiveRun,
    live: &LiveRecord,
) -> Result<Vec<std::path::PathBuf>, String> {
    let (md, csv) = (live.stage_markdown(), live.stage_csv());
    let rec = live_run_record(graph, run, live);
    let json = serde_json::to_vec_pretty(&rec).map_err(|e| format!("cannot encode the run record: {e}"))?;
    std::fs::create_dir_all(&graph.out_dir)
        .map_err(|e| format!("cannot create {}: {e}", graph.out_dir.display()))?;
    let mut files = Vec::new();
    for (name, bytes) in [
        ("run.json", json),
        ("live_timing.md", md.into_bytes()),
        ("live_timing.csv", csv.into_bytes()),
    ] {
        let path = graph.out_dir.join(name);
        palpate_core::output::write_atomic(&path, &bytes)
            .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        files.push(path);
    }
    Ok(files)
}

/// Prints a sweep's reports and summary, and writes into the graph's output
/// directory `sweep.json`, `sweep.csv`, SVG curves, the declared figures
/// (`[[sweep.plot]]`, [`crate::sweep_plot`]) and (with `[sweep] frontier`)
/// the accuracy-time frontier ([`crate::frontier`]). Each point's
/// directory gets its `run.json`, `timing.md` and `timing.csv`.
///
/// Curves: in the single-key form with numeric values, one `sweep_<metric>.svg`
/// per metric; in the series form (whose series vary different keys, so share
/// no x axis), one `sweep_<series>_<metric>.svg` per series with numeric values
/// and per metric listed in `metrics` (none when `metrics` is empty: a series
/// sweep reports many metrics, and the frontier plots are its summary). A
/// curve needs two values of its key: a sweep of one value charts nothing.
pub fn sweep_report(graph: &Graph, runs: &[palpate_core::sweep::SweepRun]) -> (String, bool) {
    use palpate_core::output::write_atomic;
    let mut text = String::new();
    let Some(sweep) = &graph.sweep else {
        return (format!("{}: the graph has no [sweep] table\n", graph.file), false);
    };
    let mut failed = false;
    for r in runs {
        let value = palpate_core::sweep::label(&r.value);
        match &r.series {
            Some(s) => {
                let _ = writeln!(
                    text,
                    "== {s}: {} = {value} (repeat {}, seed {})",
                    r.key, r.repeat, r.seed
                );
            }
            None => {
                let _ = writeln!(
                    text,
                    "== {} = {value} (repeat {}, seed {})",
                    r.key, r.repeat, r.seed
                );
            }
        }
        for (id, rep) in &r.result.reports {
            let _ = writeln!(text, "-- {id}");
            push_lines(&mut text, &rep.text);
        }
        if let Err(e) = write_run_files(&r.graph, &r.result) {
            eprintln!("{e}");
            failed = true;
        }
    }
    let rows = palpate_core::sweep::summarize(runs, &sweep.metrics);
    let points = sweep.points().len();
    let _ = writeln!(
        text,
        "== sweep over {} ({} x {}; per-point timing in <point>/timing.md)",
        sweep.describe(),
        crate::stages::io::daq::protocol::count(points as u64, "point", "points"),
        crate::stages::io::daq::protocol::count(sweep.repeats as u64, "repeat", "repeats")
    );
    let head = if sweep.series.is_empty() {
        sweep.key.as_str()
    } else {
        "point"
    };
    text.push_str(&palpate_core::sweep::render(head, &rows));
    let out = &graph.out_dir;
    let mut csv = String::from("value,metric,mean,sd,runs\n");
    for r in &rows {
        for (m, mean, sd, n) in &r.metrics {
            let _ = writeln!(csv, "{},{m},{mean},{sd},{n}", r.label);
        }
    }
    let write = |name: &str, bytes: &[u8]| {
        if let Err(e) = write_atomic(&out.join(name), bytes) {
            eprintln!("cannot write {}: {e}", out.join(name).display());
            false
        } else {
            true
        }
    };
    failed |= !write("sweep.csv", csv.as_bytes());
    if let Ok(json) = serde_json::to_vec_pretty(&rows) {
        failed |= !write("sweep.json", &json);
    }
    let safe = |s: &str| s.replace(|c: char| !c.is_ascii_alphanumeric(), "_");
    // (file, title, x label, rows) per curve group.
    let mut groups: Vec<(String, String, Vec<&palpate_core::sweep::SummaryRow>, bool)> = Vec::new();
    if sweep.series.is_empty() {
        groups.push((String::new(), sweep.key.clone(), rows.iter().collect(), true));
    } else if !sweep.metrics.is_empty() {
        for s in &sweep.series {
            let of: Vec<_> = rows
                .iter()
                .filter(|r| r.series.as_ref() == Some(&s.name))
                .collect();
            groups.push((format!("{}_", safe(&s.name)), s.key.clone(), of, false));
        }
    }
    for (prefix, key, of, all_metrics) in groups {
        if of.is_empty() || !of.iter().all(|r| r.x.is_some()) {
            continue;
        }
        // A line over one x value is a dot: a sweep of one point (repeats
        // over seeds, as graphs/paper/table2.toml) wrote 72 such charts;
        // the table above says it all.
        let first = of[0].x;
        if of.iter().all(|r| r.x == first) {
            continue;
        }
        let mut names: Vec<&str> = Vec::new();
        for r in &of {
            for (n, ..) in &r.metrics {
                if !names.contains(&n.as_str()) && (all_metrics || sweep.metrics.contains(n)) {
                    names.push(n);
                }
            }
        }
        for name in names {
            let points: Vec<(f64, f64)> = of
                .iter()
                .filter_map(|r| Some((r.x?, r.metrics.iter().find(|m| m.0 == name)?.1)))
                .collect();
            let file = out.join(format!("sweep_{prefix}{}.svg", safe(name)));
            let series = [palpate_stages::plot::Series { name, points }];
            if let Err(e) =
                palpate_stages::plot::line_chart(&file, &format!("{name} across {key}"), &key, name, &series)
            {
                eprintln!("{e}");
                failed = true;
            }
        }
    }
    // The declared figures ([[sweep.plot]]): a run without the metric is
    // left out and said here, never a failure of the sweep.
    for plot in &sweep.plots {
        let (written, data) = crate::sweep_plot::write(plot, sweep, runs, out);
        for note in &data.notes {
            eprintln!("{note}");
        }
        match written {
            Ok(path) => {
                let _ = writeln!(
                    text,
                    "plot {}: {} series, {} points",
                    path.display(),
                    data.series.len(),
                    data.series.iter().map(|s| s.points.len()).sum::<usize>(),
                );
            }
            Err(e) => {
                eprintln!("cannot write {}: {e}", out.join(&plot.file).display());
                failed = true;
            }
        }
    }
    if !sweep.frontier.is_empty() {
        match crate::frontier::report(graph, runs) {
            Ok(frontier) => {
                let _ = writeln!(
                    text,
                    "== accuracy-time frontier (compute ms: median per trial summed over the estimator's upstream stages, sources left out; decision ms: median palpation from first contact)"
                );
                push_lines(&mut text, &frontier);
            }
            Err(e) => {
                eprintln!("frontier: {e}");
                failed = true;
            }
        }
    }
    let _ = writeln!(text, "reports in {}", out.display());
    (text, !failed)
}

/// Appends text lines to `out`, ending with a newline even when the text
/// forgot its last one (so the next line never runs into it).
pub fn push_lines(out: &mut String, text: &str) {
    out.push_str(text);
    if !text.is_empty() && !text.ends_with('\n') {
        out.push('\n');
    }
}

/// Prints `text`, ending it with a newline if it lacks one.
pub fn print_lines(text: &str) {
    print!("{text}");
    if !text.is_empty() && !text.ends_with('\n') {
        println!();
    }
}
