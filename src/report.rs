//! Presenting a run: the timing table and the run record (`run.json`).
//!
//! Timing: for every stage, the median and 95th percentile of its per-trial wall
//! time, its fits (trained estimators: one per fold), its total wall time, and for
//! estimators the estimates per second of the stage's wall time.

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
    /// Median fit time, ms.
    pub fit_median_ms: f64,
    /// Wall time of the whole stage, ms.
    pub total_ms: f64,
    /// Estimates per second of the stage's wall time (estimators only).
    pub estimates_per_s: Option<f64>,
}

/// Summarises a run's timings.
pub fn timing_rows(result: &RunResult) -> Vec<TimingRow> {
    result
        .timings
        .iter()
        .map(|t| {
            let (median, p95) = median_p95(&t.per_trial);
            let (fit_median, _) = median_p95(&t.fits);
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
                total_ms: total * 1e3,
                estimates_per_s: (t.role == "estimator" && total > 0.0)
                    .then(|| t.per_trial.len() as f64 / total),
            }
        })
        .collect()
}

/// Renders the timing table.
pub fn timing_table(rows: &[TimingRow]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{:<14} {:<14} {:>7} {:>12} {:>12} {:>6} {:>12} {:>10} {:>10}",
        "stage", "type", "trials", "median ms", "p95 ms", "fits", "fit med ms", "total s", "est/s"
    );
    for r in rows {
        let _ = writeln!(
            s,
            "{:<14} {:<14} {:>7} {:>12.3} {:>12.3} {:>6} {:>12.1} {:>10.2} {:>10}",
            r.stage,
            r.type_name,
            r.trials,
            r.median_ms,
            r.p95_ms,
            r.fits,
            r.fit_median_ms,
            r.total_ms / 1e3,
            r.estimates_per_s.map_or("-".to_string(), |v| format!("{v:.0}"))
        );
    }
    s
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
    /// Every stage's config, by id.
    pub stages: Vec<(String, serde_json::Value)>,
    /// Timing per stage.
    pub timing: Vec<TimingRow>,
    /// Every sink's metrics.
    pub metrics: Vec<(String, f64)>,
}

/// Builds the run record.
pub fn run_record<'a>(graph: &'a Graph, result: &RunResult) -> RunRecord<'a> {
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
        timing: timing_rows(result),
        metrics: result
            .reports
            .iter()
            .flat_map(|(_, r)| r.metrics.iter().cloned())
            .collect(),
    }
}

/// Prints a sweep's reports and summary, and writes `sweep.json`, `sweep.csv`
/// and one SVG curve per metric (when the swept values are numbers) into the
/// graph's output directory.
pub fn sweep_report(graph: &Graph, runs: &[palpate_core::sweep::SweepRun]) -> std::process::ExitCode {
    use palpate_core::output::write_atomic;
    let Some(sweep) = &graph.sweep else {
        return std::process::ExitCode::FAILURE;
    };
    for r in runs {
        println!(
            "== {} = {} (repeat {}, seed {})",
            sweep.key, r.label, r.repeat, r.seed
        );
        for (id, rep) in &r.result.reports {
            println!("-- {id}");
            print!("{}", rep.text);
        }
    }
    let rows = palpate_core::sweep::summarize(runs, &sweep.metrics);
    println!(
        "== sweep over {} ({} values x {} repeats)",
        sweep.key,
        sweep.values.len(),
        sweep.repeats
    );
    print!("{}", palpate_core::sweep::render(&sweep.key, &rows));
    let out = &graph.out_dir;
    let mut csv = String::from("value,metric,mean,sd,runs\n");
    for r in &rows {
        for (m, mean, sd, n) in &r.metrics {
            let _ = writeln!(csv, "{},{m},{mean},{sd},{n}", r.label);
        }
    }
    let mut failed = false;
    let mut write = |name: &str, bytes: &[u8]| {
        if let Err(e) = write_atomic(&out.join(name), bytes) {
            eprintln!("cannot write {}: {e}", out.join(name).display());
            failed = true;
        }
    };
    write("sweep.csv", csv.as_bytes());
    if let Ok(json) = serde_json::to_vec_pretty(&rows) {
        write("sweep.json", &json);
    }
    if rows.iter().all(|r| r.x.is_some()) {
        let mut names: Vec<&str> = Vec::new();
        for r in &rows {
            for (n, ..) in &r.metrics {
                if !names.contains(&n.as_str()) {
                    names.push(n);
                }
            }
        }
        for name in names {
            let points: Vec<(f64, f64)> = rows
                .iter()
                .filter_map(|r| Some((r.x?, r.metrics.iter().find(|m| m.0 == name)?.1)))
                .collect();
            let file = out.join(format!(
                "sweep_{}.svg",
                name.replace(|c: char| !c.is_ascii_alphanumeric(), "_")
            ));
            let series = [palpate_stages::plot::Series { name, points }];
            if let Err(e) = palpate_stages::plot::line_chart(
                &file,
                &format!("{name} across {}", sweep.key),
                &sweep.key,
                name,
                &series,
            ) {
                eprintln!("{e}");
                failed = true;
            }
        }
    }
    println!("reports in {}", out.display());
    if failed {
        std::process::ExitCode::FAILURE
    } else {
        std::process::ExitCode::SUCCESS
    }
}
