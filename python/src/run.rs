//! Graphs (check, run) and building blocks (apply one stage, fit a baseline,
//! simulate a scene), each through the same registered stages the graphs use.

use crate::convert::{item_from_py, item_to_py, json_to_py};
use crate::{
    no_panic, with_attrs, ConfigError as PyConfigError, GraphError, PalpateError, RunError as PyRunError,
};
use palpate_core::{
    derive_seed, BuildContext, FitContext, Item, LoadErrors, LoadOptions, Progress, RunOptions, Severity,
    Stage, StageConfig, TrialContext,
};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict, PyList};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

/// A graph given as text, with where it came from (a dict with these keys).
#[derive(FromPyObject)]
#[pyo3(from_item_all)]
pub struct GraphText {
    text: String,
    file: String,
    stem: String,
    base_dir: Option<PathBuf>,
    /// Said after a TOML syntax error: a one-line string that named no file
    /// was read as TOML text (`Some("no file `...` exists")`).
    hint: Option<String>,
}

/// `e` with the text's `hint` after its TOML syntax error, if any.
fn with_hint(g: &GraphText, mut e: LoadErrors) -> LoadErrors {
    if let Some(h) = &g.hint {
        for d in &mut e.0 {
            if d.severity == Severity::Error && d.message.starts_with("not valid TOML") {
                d.message = format!("{} ({h})", d.message);
            }
        }
    }
    e
}

fn diag_dicts<'py>(py: Python<'py>, e: &LoadErrors) -> PyResult<Bound<'py, PyList>> {
    let list = PyList::empty(py);
    for d in &e.0 {
        let x = PyDict::new(py);
        x.set_item(
            "severity",
            match d.severity {
                Severity::Error => "error",
                Severity::Warning => "warning",
            },
        )?;
        x.set_item("file", &d.file)?;
        x.set_item("line", d.line)?;
        x.set_item("stage", &d.stage)?;
        x.set_item("key", &d.key)?;
        x.set_item("message", &d.message)?;
        x.set_item("text", d.to_string())?;
        list.append(x)?;
    }
    Ok(list)
}

fn graph_error(py: Python<'_>, e: &LoadErrors) -> PyErr {
    let first = e.errors().next();
    let err = with_attrs(
        py,
        GraphError::new_err(e.to_string()),
        &[
            ("file", first.map(|d| d.file.clone())),
            ("stage", first.and_then(|d| d.stage.clone())),
            ("key", first.and_then(|d| d.key.clone())),
        ],
    );
    let v = err.value(py);
    let _ = v.setattr("line", first.and_then(|d| d.line));
    if let Ok(l) = diag_dicts(py, e) {
        let _ = v.setattr("diagnostics", l);
    }
    err
}

fn overrides(set: Option<&Bound<'_, PyAny>>) -> PyResult<Vec<(String, toml::Value)>> {
    let mut out = Vec::new();
    let Some(set) = set.filter(|s| !s.is_none()) else {
        return Ok(out);
    };
    let d = set
        .downcast::<PyDict>()
        .map_err(|_| pyo3::exceptions::PyTypeError::new_err("`set` must be a dict of key -> value"))?;
    for (k, v) in d.iter() {
        let key: String = k.extract().map_err(|_| {
            pyo3::exceptions::PyTypeError::new_err(format!("`set` keys must be strings, got {k}"))
        })?;
        let value = match v.extract::<String>() {
            // A string is read as `--set` reads it: a TOML value if it parses.
            Ok(s) => palpate_core::graph::parse_value(&s),
            Err(_) => {
                // A seed past 2**64 - 1 was PyO3's bare OverflowError.
                if key == "run.seed"
                    && v.is_instance_of::<pyo3::types::PyInt>()
                    && v.extract::<i64>().is_err()
                    && v.extract::<u64>().is_err()
                {
                    return Err(pyo3::exceptions::PyValueError::new_err(format!(
                        "`set` value of `run.seed`: seed must be an integer in [0, 2**64), got {v}"
                    )));
                }
                crate::convert::py_to_toml(&v, &format!("`set` value of `{key}`"), 0)?
            }
        };
        out.push((key, value));
    }
    Ok(out)
}

fn load(
    py: Python<'_>,
    g: &GraphText,
    set: Option<&Bound<'_, PyAny>>,
    out: Option<PathBuf>,
) -> PyResult<(palpate_core::Graph, LoadOptions)> {
    let opts = LoadOptions {
        overrides: overrides(set)?,
        out,
        base_dir: g.base_dir.clone(),
    };
    let r = no_panic("loading the graph", || {
        Ok(palpate_core::load_str(&g.text, &g.file, &g.stem, &opts))
    })?;
    match r {
        Ok(graph) => {
            // The load's warnings (deprecated spellings, a bin window shorter
            // than its hop, ...) as Python warnings, which `warnings` filters,
            // records and turns into errors; `check` returns them as data.
            for w in &graph.warnings {
                let msg = std::ffi::CString::new(w.to_string().replace('\0', " "))
                    .unwrap_or_else(|_| c"graph warning".into());
                PyErr::warn(py, &py.get_type::<pyo3::exceptions::PyUserWarning>(), &msg, 2)?;
            }
            Ok((graph, opts))
        }
        Err(e) => Err(graph_error(py, &with_hint(g, e))),
    }
}

/// An output folder that is an existing file is refused before anything
/// runs, as the CLI refuses it (`prepare_out_dir`); otherwise every stage ran
/// and the first sink failed.
fn refuse_file_out(graph: &palpate_core::Graph) -> PyResult<()> {
    match std::fs::metadata(&graph.out_dir) {
        Ok(m) if !m.is_dir() => Err(PalpateError::new_err(format!(
            "output directory {}: exists and is not a directory; give `out` (or `[run] out`) a folder",
            graph.out_dir.display()
        ))),
        _ => Ok(()),
    }
}

/// Every diagnostic of a graph (errors and warnings), as dicts.
#[pyfunction]
#[pyo3(signature = (graph, set=None))]
pub fn check<'py>(
    py: Python<'py>,
    graph: GraphText,
    set: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyList>> {
    let r = check_impl(py, graph, set);
    crate::flushed(py, r)
}

fn check_impl<'py>(
    py: Python<'py>,
    graph: GraphText,
    set: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyList>> {
    let opts = LoadOptions {
        overrides: overrides(set)?,
        out: None,
        base_dir: graph.base_dir.clone(),
    };
    let r = no_panic("checking the graph", || {
        Ok(palpate_core::load_str(
            &graph.text,
            &graph.file,
            &graph.stem,
            &opts,
        ))
    })?;
    match r {
        Ok(g) => diag_dicts(py, &LoadErrors(g.warnings.clone())),
        Err(e) => diag_dicts(py, &with_hint(&graph, e)),
    }
}

/// Progress on stderr: indicatif bars when stderr is a terminal, otherwise one
/// line per stage as it finishes (so a notebook or a log still shows it);
/// nothing when not `shown`. Also the run's cancel flag ([`watched`]).
struct Bars {
    bar: Mutex<Option<(indicatif::ProgressBar, String, std::time::Instant)>>,
    tty: bool,
    shown: bool,
    cancel: std::sync::atomic::AtomicBool,
}

impl Bars {
    fn new(shown: bool) -> Bars {
        use std::io::IsTerminal;
        Bars {
            bar: Mutex::new(None),
            tty: std::io::stderr().is_terminal(),
            shown,
            cancel: std::sync::atomic::AtomicBool::new(false),
        }
    }
}

/// Runs `f` (a graph or sweep) on a thread of its own while this thread,
/// Python's main thread, looks for Ctrl-C every 20 ms (the interpreter
/// runs signal handlers only there): a signal sets `bars`' cancel flag, the
/// engine stops at its next trial or fold ([`Progress::cancelled`]), and
/// the signal's exception (`KeyboardInterrupt`) is raised once `f` has
/// returned. Without this a long run could not be interrupted from a
/// notebook.
fn watched<T: Send>(py: Python<'_>, bars: &Bars, f: impl FnOnce() -> PyResult<T> + Send) -> PyResult<T> {
    let mut signal: Option<PyErr> = None;
    let out = std::thread::scope(|s| {
        let h = s.spawn(f);
        while !h.is_finished() {
            if signal.is_none() {
                if let Err(e) = py.check_signals() {
                    bars.cancel.store(true, std::sync::atomic::Ordering::SeqCst);
                    signal = Some(e);
                }
            }
            py.allow_threads(|| std::thread::sleep(std::time::Duration::from_millis(20)));
        }
        h.join()
    });
    if let Some(e) = signal {
        return Err(e);
    }
    out.unwrap_or_else(|_| {
        Err(PalpateError::new_err(
            "the run's thread panicked (a bug in palpate, please report it)",
        ))
    })
}

impl Progress for Bars {
    fn cancelled(&self) -> bool {
        self.cancel.load(std::sync::atomic::Ordering::SeqCst)
    }
    fn start(&self, stage: &str, total: usize) {
        if !self.shown {
            return;
        }
        let bar = if self.tty {
            indicatif::ProgressBar::new(total as u64)
        } else {
            indicatif::ProgressBar::hidden()
        };
        if let Ok(style) =
            indicatif::ProgressStyle::with_template("{prefix:>14} [{bar:30}] {pos}/{len} {elapsed_precise}")
        {
            bar.set_style(style.progress_chars("=> "));
        }
        bar.set_prefix(stage.to_string());
        if let Ok(mut b) = self.bar.lock() {
            *b = Some((bar, stage.to_string(), std::time::Instant::now()));
        }
    }
    fn tick(&self) {
        if !self.shown {
            return;
        }
        if let Ok(b) = self.bar.lock() {
            if let Some((bar, _, _)) = b.as_ref() {
                bar.inc(1);
            }
        }
    }
    fn finish(&self, _stage: &str) {
        if let Ok(mut b) = self.bar.lock() {
            if let Some((bar, stage, t0)) = b.take() {
                bar.finish_and_clear();
                if !self.tty {
                    eprintln!("palpate: {stage} done ({:.2} s)", t0.elapsed().as_secs_f64());
                }
            }
        }
    }
}

fn run_error(py: Python<'_>, file: &str, e: &palpate_core::RunError) -> PyErr {
    with_attrs(
        py,
        PyRunError::new_err(format!("{file}: run failed: {e}")),
        &[
            ("file", Some(file.to_string())),
            ("stage", Some(e.stage.clone())),
            ("trial", e.trial.clone()),
            ("key", None),
        ],
    )
}

/// Runs a graph; returns reports, metrics, timing and every estimator's
/// per-trial estimates. Writes the same report files as `palpate run`.
#[pyfunction]
#[pyo3(signature = (graph, set=None, threads=None, out=None, progress=true, fresh=false))]
pub fn run<'py>(
    py: Python<'py>,
    graph: GraphText,
    set: Option<&Bound<'py, PyAny>>,
    threads: Option<usize>,
    out: Option<PathBuf>,
    progress: bool,
    fresh: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let r = run_impl(py, graph, set, threads, out, progress, fresh);
    crate::flushed(py, r)
}

fn run_impl<'py>(
    py: Python<'py>,
    graph: GraphText,
    set: Option<&Bound<'py, PyAny>>,
    threads: Option<usize>,
    out: Option<PathBuf>,
    progress: bool,
    fresh: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let text = graph.text.clone();
    let base_dir = graph.base_dir.clone();
    let (graph, opts) = load(py, &graph, set, out)?;
    refuse_file_out(&graph)?;
    let pool = palpate_core::thread_pool(threads.unwrap_or(0), "threads=")
        .map_err(pyo3::exceptions::PyValueError::new_err)?;
    let bars = Bars::new(progress);
    if graph.sweep.is_some() {
        let base = match base_dir {
            Some(b) => b,
            None => std::env::current_dir()
                .map_err(|e| PalpateError::new_err(format!("cannot read the working folder: {e}")))?,
        };
        return run_sweep(py, &graph, (&text, &base), &opts.overrides, &pool, &bars, fresh);
    }
    let t0 = std::time::Instant::now();
    // The graph runs on its own thread without the GIL (Python-defined
    // stages take it back for their own calls); Ctrl-C stops it.
    let result = watched(py, &bars, || {
        no_panic("running the graph", || {
            let opts = RunOptions {
                progress: Some(&bars as &dyn Progress),
                keep_outputs: true,
                cache: None,
            };
            Ok(pool.install(|| palpate_core::run(&graph, &opts)))
        })
    })?;
    let wall_s = t0.elapsed().as_secs_f64();
    let result = result.map_err(|e| run_error(py, &graph.file, &e))?;
    let files = palpate::report::write_run_files(&graph, &result)
        .map_err(|e| PalpateError::new_err(format!("{}: {e}", graph.file)))?;

    let d = PyDict::new(py);
    d.set_item("file", &graph.file)?;
    d.set_item("out_dir", graph.out_dir.display().to_string())?;
    d.set_item("wall_s", wall_s)?;
    let record = palpate::report::run_record(&graph, &result);
    let record_json = serde_json::to_value(&record).unwrap_or(serde_json::Value::Null);
    d.set_item("record", json_to_py(py, &record_json)?)?;
    d.set_item("reports", reports_dict(py, &result.reports)?)?;
    d.set_item(
        "run_files",
        files.iter().map(|f| f.display().to_string()).collect::<Vec<_>>(),
    )?;
    d.set_item(
        "timing_table",
        palpate::report::timing_table(&palpate::report::timing_rows(&result)),
    )?;
    // Every estimator's output, in trial order.
    let estimates = PyDict::new(py);
    for node in &graph.nodes {
        if !matches!(node.stage, Stage::Estimator(_)) {
            continue;
        }
        if let Some(items) = result.outputs.get(&node.id) {
            estimates.set_item(&node.id, items_to_list(py, items)?)?;
        }
    }
    d.set_item("estimates", estimates)?;
    Ok(d)
}

/// Each sink's report (`text`, `files`, `metrics`), by stage id.
fn reports_dict<'py>(
    py: Python<'py>,
    reports: &[(String, palpate_core::SinkReport)],
) -> PyResult<Bound<'py, PyDict>> {
    let out = PyDict::new(py);
    for (id, r) in reports {
        let x = PyDict::new(py);
        x.set_item("text", &r.text)?;
        x.set_item(
            "files",
            r.files
                .iter()
                .map(|f| f.display().to_string())
                .collect::<Vec<_>>(),
        )?;
        let m = PyDict::new(py);
        for (k, v) in &r.metrics {
            m.set_item(k, v)?;
        }
        x.set_item("metrics", m)?;
        out.set_item(id, x)?;
    }
    Ok(out)
}

/// Streams a graph live, as `palpate run GRAPH --live` does: every trial of
/// its source through the stages' streaming forms, `block` samples at a
/// time (a DAQ source: frame by frame as the board delivers them), with the
/// same report files plus `live_timing.md` / `.csv`. `on_update(dict)` is
/// called with every estimate as it changes (`trial_id`, `stage`, `t_ms`,
/// `last`, `estimate`). An exception it raises, or Ctrl-C (checked at each
/// update and every 50 ms between), stops the stream: the trial under way
/// is dropped, the sinks and the run record cover the trials finished, and
/// the exception is raised.
/// Returns the reports, the estimators' final estimates (as `run`'s
/// `estimates`), the run record with its `live` section (block latency,
/// per-stage times) and the CLI's per-stage table.
#[pyfunction]
#[pyo3(signature = (graph, set=None, out=None, block=1, on_update=None))]
pub fn run_live<'py>(
    py: Python<'py>,
    graph: GraphText,
    set: Option<&Bound<'py, PyAny>>,
    out: Option<PathBuf>,
    block: usize,
    on_update: Option<PyObject>,
) -> PyResult<Bound<'py, PyDict>> {
    let r = run_live_impl(py, graph, set, out, block, on_update);
    crate::flushed(py, r)
}

fn run_live_impl<'py>(
    py: Python<'py>,
    graph: GraphText,
    set: Option<&Bound<'py, PyAny>>,
    out: Option<PathBuf>,
    block: usize,
    on_update: Option<PyObject>,
) -> PyResult<Bound<'py, PyDict>> {
    if block == 0 {
        return Err(pyo3::exceptions::PyValueError::new_err(
            "block: samples per block must be at least 1",
        ));
    }
    let (graph, _) = load(py, &graph, set, out)?;
    refuse_file_out(&graph)?;
    let plan = palpate_core::stream::plan(&graph).map_err(|problems| {
        let lines: Vec<String> = problems.iter().map(|p| format!("  {p}")).collect();
        PalpateError::new_err(format!("{}: cannot run live:\n{}", graph.file, lines.join("\n")))
    })?;
    let t0 = std::time::Instant::now();
    // What stopped the stream (an exception from `on_update`, or Ctrl-C),
    // raised once the record is written. Shared by the two callbacks (a
    // mutex only because the closure must be `Send`; one thread uses it).
    let raised: std::sync::Mutex<Option<PyErr>> = std::sync::Mutex::new(None);
    let result = py.allow_threads(|| {
        no_panic("running the graph live", || {
            let updates = |u: &palpate_core::stream::LiveUpdate| {
                use std::ops::ControlFlow;
                // Ctrl-C (checked at each update) or an exception from
                // `on_update` stops the stream; it is raised at the end.
                let r = Python::with_gil(|py| -> PyResult<()> {
                    py.check_signals()?;
                    let Some(cb) = &on_update else { return Ok(()) };
                    let d = PyDict::new(py);
                    d.set_item("trial_id", &u.trial_id)?;
                    d.set_item("stage", &u.stage)?;
                    d.set_item("t_ms", u.t_ms)?;
                    d.set_item("last", u.last)?;
                    let e = palpate_core::Payload::Estimate(Arc::new(u.estimate.clone()));
                    d.set_item("estimate", crate::convert::payload_to_py(py, &e)?)?;
                    cb.call1(py, (d,))?;
                    Ok(())
                });
                match r {
                    Ok(()) => ControlFlow::Continue(()),
                    Err(e) => {
                        *raised.lock().unwrap_or_else(|p| p.into_inner()) = Some(e);
                        ControlFlow::Break(())
                    }
                }
            };
            // Between updates (a board with nothing in contact sends
            // frames but no estimate), Ctrl-C is checked every 50 ms of
            // the stream: taking the GIL at every 1 kHz frame would cost
            // the chain more than its stages.
            let mut last_check = std::time::Instant::now();
            let stop = || {
                if last_check.elapsed() < std::time::Duration::from_millis(50) {
                    return false;
                }
                last_check = std::time::Instant::now();
                match Python::with_gil(|py| py.check_signals()) {
                    Ok(()) => false,
                    Err(e) => {
                        *raised.lock().unwrap_or_else(|p| p.into_inner()) = Some(e);
                        true
                    }
                }
            };
            Ok(palpate_core::stream::replay_polled(
                &graph, &plan, block, updates, stop,
            ))
        })
    })?;
    let wall = t0.elapsed();
    let run = result.map_err(|e| run_error(py, &graph.file, &e))?;
    let live = palpate::report::LiveRecord::new(&graph, &run, wall);
    let table = live.stage_table();
    let summary = live.summary();
    let files = palpate::report::write_live_run_files(&graph, &run, &live)
        .map_err(|e| PalpateError::new_err(format!("{}: {e}", graph.file)))?;
    // A stopped run's record is written (the sinks reported the finished
    // trials) before what stopped it is raised.
    if let Some(e) = raised.into_inner().unwrap_or_else(|p| p.into_inner()) {
        return Err(e);
    }
    let record = serde_json::to_value(palpate::report::live_run_record(&graph, &run, &live))
        .unwrap_or(serde_json::Value::Null);
    let d = PyDict::new(py);
    d.set_item("file", &graph.file)?;
    d.set_item("out_dir", graph.out_dir.display().to_string())?;
    d.set_item("wall_s", wall.as_secs_f64())?;
    d.set_item("record", json_to_py(py, &record)?)?;
    d.set_item("reports", reports_dict(py, &run.reports)?)?;
    d.set_item(
        "run_files",
        files.iter().map(|f| f.display().to_string()).collect::<Vec<_>>(),
    )?;
    d.set_item("timing_table", format!("{summary}\n{table}"))?;
    let estimates = PyDict::new(py);
    for (id, items) in &run.estimates {
        estimates.set_item(id, items_to_list(py, items)?)?;
    }
    d.set_item("estimates", estimates)?;
    Ok(d)
}

/// A sweep through the CLI's own code path ([`palpate::cluster::run_points`]
/// and the sweep report): every point that is not yet complete runs (all with
/// `fresh`), each writes its folder and marker, and the sweep's report is
/// written from the markers. Returns the report's text, its summary rows and
/// every run's metrics.
fn run_sweep<'py>(
    py: Python<'py>,
    graph: &palpate_core::Graph,
    source: (&str, &std::path::Path),
    set: &[(String, toml::Value)],
    pool: &rayon::ThreadPool,
    bars: &Bars,
    fresh: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let path = PathBuf::from(&graph.file);
    let job = palpate::cluster::SweepJob {
        path: &path,
        source: Some(source),
        graph,
        set,
    };
    let t0 = std::time::Instant::now();
    let announce = |i: usize, n: usize, what: &str| {
        if bars.shown {
            eprintln!("{what}: {}/{n}", i + 1);
        }
    };
    let outcome = watched(py, bars, || {
        no_panic("running the sweep", || {
            let opts = RunOptions {
                progress: Some(bars as &dyn Progress),
                keep_outputs: false,
                cache: None,
            };
            Ok(pool.install(|| {
                palpate::cluster::run_points(
                    &job,
                    &palpate_core::shard::Selection::All,
                    fresh,
                    &opts,
                    &announce,
                )
            }))
        })
    })?;
    let (outcome, _, _) = outcome.map_err(PalpateError::new_err)?;
    let palpate::cluster::SweepOutcome::Complete(base, runs) = outcome else {
        // Selection::All runs every point, so nothing can be missing.
        return Err(PalpateError::new_err(format!(
            "{}: the sweep ended with points missing",
            graph.file
        )));
    };
    let (text, ok) = palpate::report::sweep_report(&base, &runs);
    if !ok {
        return Err(PalpateError::new_err(format!(
            "{}: the sweep ran but its report could not be written in full:\n{text}",
            graph.file
        )));
    }
    let d = PyDict::new(py);
    d.set_item("file", &graph.file)?;
    d.set_item("out_dir", graph.out_dir.display().to_string())?;
    d.set_item("wall_s", t0.elapsed().as_secs_f64())?;
    d.set_item("text", &text)?;
    let metrics = base.sweep.as_ref().map(|s| s.metrics.clone()).unwrap_or_default();
    let rows = palpate_core::sweep::summarize(&runs, &metrics);
    let rows_json = serde_json::to_value(&rows).unwrap_or(serde_json::Value::Null);
    d.set_item("rows", json_to_py(py, &rows_json)?)?;
    let list = PyList::empty(py);
    for r in &runs {
        let x = PyDict::new(py);
        x.set_item("point", r.point)?;
        x.set_item("repeat", r.repeat)?;
        x.set_item("label", &r.label)?;
        x.set_item("series", r.series.clone())?;
        x.set_item("key", &r.key)?;
        let v = serde_json::to_value(&r.value).unwrap_or(serde_json::Value::Null);
        x.set_item("value", json_to_py(py, &v)?)?;
        x.set_item("seed", r.seed)?;
        x.set_item("out_dir", r.graph.out_dir.display().to_string())?;
        let m = PyDict::new(py);
        for (_, rep) in &r.result.reports {
            for (k, v) in &rep.metrics {
                m.set_item(k, v)?;
            }
        }
        x.set_item("metrics", m)?;
        list.append(x)?;
    }
    d.set_item("runs", list)?;
    Ok(d)
}

fn items_to_list<'py>(py: Python<'py>, items: &[Item]) -> PyResult<Bound<'py, PyList>> {
    let l = PyList::empty(py);
    for it in items {
        l.append(item_to_py(py, it)?)?;
    }
    Ok(l)
}

/// Every registered stage type with its docs and keys.
#[pyfunction]
pub fn stage_types(py: Python<'_>) -> PyResult<Bound<'_, PyList>> {
    let l = PyList::empty(py);
    for reg in palpate_core::registry::registrations() {
        let doc = palpate_core::registry::stage_doc(reg);
        let d = PyDict::new(py);
        d.set_item("type", &doc.type_name)?;
        d.set_item("doc", &doc.doc)?;
        let keys = PyList::empty(py);
        for k in &doc.keys {
            let kd = PyDict::new(py);
            kd.set_item("name", &k.name)?;
            kd.set_item("type", &k.type_desc)?;
            kd.set_item("default", &k.default)?;
            kd.set_item("doc", &k.doc)?;
            keys.append(kd)?;
        }
        d.set_item("keys", keys)?;
        l.append(d)?;
    }
    Ok(l)
}

/// Deserializes and builds a registered stage from its type and keys, exactly
/// as the graph loader does; errors name the stage and key.
fn build_stage(
    py: Python<'_>,
    type_name: &str,
    config: &Bound<'_, PyAny>,
    seed: u64,
    stage_id: &str,
    base_dir: Option<PathBuf>,
) -> PyResult<(Box<dyn StageConfig>, Stage)> {
    let alias = palpate_core::registry::registered_aliases()
        .into_iter()
        .find(|(name, _)| name == type_name)
        .map(|(_, a)| a);
    if let (None, Some(alias)) = (palpate_core::registry::find(type_name), alias) {
        // A stage type registered at run time (a `@palpate.stage` class):
        // its keys go where the graph loader puts them, as it rewrites
        // `type = "<name>"` (the long form: `apply("python", stage=..., config=...)`).
        let inner = pyo3::types::PyDict::new(py);
        inner.set_item(alias.name_key, type_name)?;
        inner.set_item(alias.keys_into, config)?;
        return build_stage(py, alias.target, inner.as_any(), seed, stage_id, base_dir);
    }
    if palpate_core::registry::find(type_name).is_none() {
        let close = palpate_core::registry::close_matches(type_name);
        let hint = if close.is_empty() {
            String::new()
        } else {
            format!("; did you mean {}?", close.join(" or "))
        };
        return Err(with_attrs(
            py,
            PyConfigError::new_err(format!("unknown stage type `{type_name}`{hint}")),
            &[
                ("stage", Some(stage_id.to_string())),
                ("key", Some("type".into())),
            ],
        ));
    }
    let cfg = crate::convert::config_to_json(py, config)
        .map_err(|e| crate::convert::named(py, &format!("stage `{stage_id}` ({type_name})"), e))?;
    let tagged = serde_json::json!({ type_name: cfg });
    let config: Box<dyn StageConfig> = serde_path_to_error::deserialize(tagged).map_err(|e| {
        let path: Vec<String> = e.path().iter().skip(1).map(|s| s.to_string()).collect();
        let key = (!path.is_empty()).then(|| path.join("."));
        let msg = format!(
            "stage `{stage_id}` ({type_name}): {}{}",
            key.as_ref().map(|k| format!("key `{k}`: ")).unwrap_or_default(),
            e.inner()
        );
        with_attrs(
            py,
            PyConfigError::new_err(msg),
            &[("stage", Some(stage_id.to_string())), ("key", key)],
        )
    })?;
    let ctx = BuildContext {
        stage_id: stage_id.to_string(),
        seed,
        out_dir: std::env::temp_dir(),
        base_dir: base_dir.unwrap_or_else(|| std::env::current_dir().unwrap_or_default()),
    };
    let stage = config.build(&ctx).map_err(|e| {
        with_attrs(
            py,
            PyConfigError::new_err(format!("stage `{stage_id}` ({type_name}): {e}")),
            &[("stage", Some(stage_id.to_string())), ("key", e.key.clone())],
        )
    })?;
    Ok((config, stage))
}

fn stage_err(py: Python<'_>, stage_id: &str, trial: Option<&str>, msg: &str) -> PyErr {
    with_attrs(
        py,
        PyRunError::new_err(format!(
            "stage `{stage_id}`{}: {msg}",
            trial.map(|t| format!(", trial `{t}`")).unwrap_or_default()
        )),
        &[
            ("file", None),
            ("stage", Some(stage_id.to_string())),
            ("trial", trial.map(str::to_string)),
            ("key", None),
        ],
    )
}

/// Applies one registered map stage (an encoder, a filter, binning, ...) or a
/// model-based estimator (WSS) to a list of trials; each trial is a list of
/// raw payloads, one per input. Returns one raw payload per trial.
#[pyfunction]
#[pyo3(signature = (type_name, config, trials, seed=1, stage_id="stage", base_dir=None))]
pub fn apply<'py>(
    py: Python<'py>,
    type_name: &str,
    config: &Bound<'py, PyAny>,
    trials: &Bound<'py, PyList>,
    seed: u64,
    stage_id: &str,
    base_dir: Option<PathBuf>,
) -> PyResult<Bound<'py, PyList>> {
    let r = apply_impl(py, type_name, config, trials, seed, stage_id, base_dir);
    crate::flushed(py, r)
}

fn apply_impl<'py>(
    py: Python<'py>,
    type_name: &str,
    config: &Bound<'py, PyAny>,
    trials: &Bound<'py, PyList>,
    seed: u64,
    stage_id: &str,
    base_dir: Option<PathBuf>,
) -> PyResult<Bound<'py, PyList>> {
    let (config, stage) = build_stage(py, type_name, config, seed, stage_id, base_dir)?;
    let spec = config.inputs();
    let mut inputs: Vec<Vec<Item>> = Vec::with_capacity(trials.len());
    for (i, t) in trials.iter().enumerate() {
        let t = t.downcast::<PyList>().map_err(|_| {
            pyo3::exceptions::PyTypeError::new_err("each trial must be a list of payloads (one per input)")
        })?;
        // As the graph loader checks a stage's `inputs`: a stage handed more
        // inputs than it takes read the first and dropped the rest unseen.
        let n = t.len();
        if n < spec.min || spec.max.is_some_and(|max| n > max) {
            let takes = match spec.max {
                Some(max) if max == spec.min => format!("{max}"),
                Some(max) => format!("{} to {max}", spec.min),
                None => format!("at least {}", spec.min),
            };
            return Err(pyo3::exceptions::PyValueError::new_err(format!(
                "stage type `{type_name}` takes {takes} input(s) per trial, got {n}"
            )));
        }
        inputs.push(t.iter().map(|p| item_from_py(&p, i)).collect::<PyResult<_>>()?);
    }
    let outs: Vec<Result<Item, (Option<String>, String)>> = py.allow_threads(|| {
        no_panic(stage_id, || {
            Ok(match &stage {
                Stage::Map(m) => inputs
                    .iter()
                    .map(|items| {
                        let meta = items.first().map(|i| i.meta.clone()).unwrap_or_default();
                        let refs: Vec<&Item> = items.iter().collect();
                        let ctx = TrialContext {
                            stage_id,
                            meta: &meta,
                            seed: derive_seed(seed, &[stage_id, &meta.trial_id]),
                        };
                        m.process(&refs, &ctx)
                            .map(|payload| Item {
                                meta: meta.clone(),
                                payload,
                            })
                            .map_err(|e| (Some(meta.trial_id.clone()), e.message))
                    })
                    .collect(),
                Stage::Estimator(est) if !est.trained() => {
                    let fctx = FitContext {
                        stage_id,
                        fold: 0,
                        seed: derive_seed(seed, &[stage_id, "fold0"]),
                    };
                    match est.fit(&[], &fctx) {
                        Err(e) => vec![Err((None, format!("fitting: {}", e.message)))],
                        Ok(model) => predict_all(model.as_ref(), &inputs, stage_id, seed),
                    }
                }
                Stage::Estimator(_) => vec![Err((
                    None,
                    "a trained estimator: use palpate.fit(...) then .predict(...)".into(),
                ))],
                Stage::Source(_) | Stage::Sink(_) => vec![Err((
                    None,
                    format!("a {} cannot be applied to payloads", stage.role()),
                ))],
            })
        })
    })?;
    let l = PyList::empty(py);
    for o in outs {
        match o {
            Ok(item) => l.append(item_to_py(py, &item)?)?,
            Err((trial, msg)) => return Err(stage_err(py, stage_id, trial.as_deref(), &msg)),
        }
    }
    Ok(l)
}

fn predict_all(
    model: &dyn palpate_core::Model,
    inputs: &[Vec<Item>],
    stage_id: &str,
    seed: u64,
) -> Vec<Result<Item, (Option<String>, String)>> {
    inputs
        .iter()
        .map(|items| {
            let Some(item) = items.first() else {
                return Err((None, "an estimator takes one payload per trial".to_string()));
            };
            let ctx = TrialContext {
                stage_id,
                meta: &item.meta,
                seed: derive_seed(seed, &[stage_id, &item.meta.trial_id]),
            };
            model
                .predict(item, &ctx)
                .map(|e| Item {
                    meta: item.meta.clone(),
                    payload: e.into(),
                })
                .map_err(|e| (Some(item.meta.trial_id.clone()), e.message))
        })
        .collect()
}

/// A fitted estimator (a trained baseline, or WSS): `predict` estimates trials.
#[pyclass(module = "palpate._palpate")]
pub struct Model {
    model: Arc<dyn palpate_core::Model>,
    stage_id: String,
    seed: u64,
}

#[pymethods]
impl Model {
    /// Estimates each raw payload; returns raw estimates.
    fn predict<'py>(&self, py: Python<'py>, trials: &Bound<'py, PyList>) -> PyResult<Bound<'py, PyList>> {
        let r = self.predict_impl(py, trials);
        crate::flushed(py, r)
    }

    /// The model file's bytes (what `save_model = true` writes, `model_in`
    /// reads), or None for a model that is not saved as a file (WSS, a Python
    /// stage's).
    fn saved_bytes<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyBytes>>> {
        match self.model.saved_bytes() {
            None => Ok(None),
            Some(Ok(b)) => Ok(Some(PyBytes::new(py, &b))),
            Some(Err(e)) => Err(stage_err(py, &self.stage_id, None, &e.message)),
        }
    }

    /// The run seed the model predicts with (its per-trial seeds derive from it).
    #[getter]
    fn seed(&self) -> u64 {
        self.seed
    }

    /// The stage id its per-trial seeds derive from (a graph's stage id).
    #[getter]
    fn stage_id(&self) -> &str {
        &self.stage_id
    }
}

impl Model {
    fn predict_impl<'py>(
        &self,
        py: Python<'py>,
        trials: &Bound<'py, PyList>,
    ) -> PyResult<Bound<'py, PyList>> {
        let inputs: Vec<Vec<Item>> = trials
            .iter()
            .enumerate()
            .map(|(i, p)| item_from_py(&p, i).map(|it| vec![it]))
            .collect::<PyResult<_>>()?;
        let model = self.model.clone();
        let (stage_id, seed) = (self.stage_id.clone(), self.seed);
        let outs = py.allow_threads(|| {
            no_panic(&stage_id, || {
                Ok(predict_all(model.as_ref(), &inputs, &stage_id, seed))
            })
        })?;
        let l = PyList::empty(py);
        for o in outs {
            match o {
                Ok(item) => l.append(item_to_py(py, &item)?)?,
                Err((trial, msg)) => return Err(stage_err(py, &self.stage_id, trial.as_deref(), &msg)),
            }
        }
        Ok(l)
    }
}

/// Fits a registered estimator on raw payloads (each with `meta` carrying its
/// label). Returns a [`Model`].
#[pyfunction]
#[pyo3(signature = (type_name, config, train, seed=1, stage_id="stage"))]
pub fn fit<'py>(
    py: Python<'py>,
    type_name: &str,
    config: &Bound<'py, PyAny>,
    train: &Bound<'py, PyList>,
    seed: u64,
    stage_id: &str,
) -> PyResult<Model> {
    let r = fit_impl(py, type_name, config, train, seed, stage_id);
    crate::flushed(py, r)
}

fn fit_impl<'py>(
    py: Python<'py>,
    type_name: &str,
    config: &Bound<'py, PyAny>,
    train: &Bound<'py, PyList>,
    seed: u64,
    stage_id: &str,
) -> PyResult<Model> {
    let (_, stage) = build_stage(py, type_name, config, seed, stage_id, None)?;
    let Stage::Estimator(est) = stage else {
        return Err(with_attrs(
            py,
            PyConfigError::new_err(format!("stage type `{type_name}` is not an estimator")),
            &[
                ("stage", Some(stage_id.to_string())),
                ("key", Some("type".into())),
            ],
        ));
    };
    let items: Vec<Item> = train
        .iter()
        .enumerate()
        .map(|(i, p)| item_from_py(&p, i))
        .collect::<PyResult<_>>()?;
    let sid = stage_id.to_string();
    let model = py.allow_threads(|| {
        no_panic(&sid, || {
            let refs: Vec<&Item> = if est.trained() {
                items.iter().collect()
            } else {
                Vec::new()
            };
            let fctx = FitContext {
                stage_id: &sid,
                fold: 0,
                seed: derive_seed(seed, &[&sid, "fold0"]),
            };
            Ok(est.fit(&refs, &fctx))
        })
    })?;
    let model = model.map_err(|e| stage_err(py, stage_id, None, &format!("fitting: {}", e.message)))?;
    Ok(Model {
        model: Arc::from(model),
        stage_id: stage_id.to_string(),
        seed,
    })
}

/// Simulates a scene (the `scene` stage with these keys, stage id `stage_id`,
/// the given run seed): every trial's raw signals with its metadata.
#[pyfunction]
#[pyo3(signature = (config, seed=1, base_dir=None, stage_id="scene"))]
pub fn simulate<'py>(
    py: Python<'py>,
    config: &Bound<'py, PyAny>,
    seed: u64,
    base_dir: Option<PathBuf>,
    stage_id: &str,
) -> PyResult<Bound<'py, PyList>> {
    read_source(py, "scene", config, seed, base_dir, stage_id)
}

/// Every trial of the source stage `type_name` with these keys (stage id
/// `stage_id`, the given run seed), in the order a graph's run sees them:
/// `simulate` for a scene, `read_signals` for recordings (`signal_file`).
#[pyfunction]
#[pyo3(signature = (type_name, config, seed=1, base_dir=None, stage_id="source"))]
pub fn read_source<'py>(
    py: Python<'py>,
    type_name: &str,
    config: &Bound<'py, PyAny>,
    seed: u64,
    base_dir: Option<PathBuf>,
    stage_id: &str,
) -> PyResult<Bound<'py, PyList>> {
    let r = read_source_impl(py, type_name, config, seed, base_dir, stage_id);
    crate::flushed(py, r)
}

fn read_source_impl<'py>(
    py: Python<'py>,
    type_name: &str,
    config: &Bound<'py, PyAny>,
    seed: u64,
    base_dir: Option<PathBuf>,
    stage_id: &str,
) -> PyResult<Bound<'py, PyList>> {
    let (_, stage) = build_stage(py, type_name, config, seed, stage_id, base_dir)?;
    let Stage::Source(src) = stage else {
        return Err(PalpateError::new_err(format!(
            "stage type `{type_name}` is not a source (it takes inputs)"
        )));
    };
    let outs = py.allow_threads(|| {
        no_panic(stage_id, || {
            let metas = match src.trials() {
                Ok(m) => m,
                Err(e) => return Ok(Err((None, e.message))),
            };
            let mut items = Vec::with_capacity(metas.len());
            for (k, mut meta) in metas.into_iter().enumerate() {
                meta.index = k;
                let ctx = TrialContext {
                    stage_id,
                    meta: &meta,
                    seed: derive_seed(seed, &[stage_id, &meta.trial_id]),
                };
                match src.produce(&ctx) {
                    Ok(p) => items.push(Item {
                        meta: Arc::new(meta.clone()),
                        payload: p,
                    }),
                    Err(e) => return Ok(Err((Some(meta.trial_id.clone()), e.message))),
                }
            }
            Ok(Ok(items))
        })
    })?;
    let items = outs.map_err(|(t, m)| stage_err(py, stage_id, t.as_deref(), &m))?;
    items_to_list(py, &items)
}
