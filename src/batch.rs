//! `palpate batch JOBS.toml`: several graphs run by one process, a few at a
//! time, sharing one cache of stage outputs and fitted models.
//!
//! Graphs of one study often begin alike: every graph of graphs/paper/ on
//! the lab scene simulates the same 170 trials per seed and encodes them
//! with the same front end before its own stages (a jitter, a crop, an
//! estimator) differ. Run one by one, each graph computes that front end
//! again; in a batch, the first graph to need an output computes it and
//! the others read it from the shared [`palpate_core::Cache`]. A stage's
//! cache key is a hash of its id, type, settings, the graph's seed,
//! protocol and folder (relative paths in settings resolve against it),
//! and its inputs' keys, so an output is shared only where the stage and
//! everything upstream of it are the same; results are the same bits as
//! running each graph alone (tested).
//!
//! Only graphs with a `[sweep]` go through the cache: a graph without one
//! runs as `palpate run` runs it, depth first, trial by trial through its
//! stage chains, so its memory stays that of a few trials whatever the
//! number of trials, and it keeps no stage output to share. A job can opt
//! in with `set = ["sweep.repeats=1"]` (a one-point sweep; the same
//! results). The batch's closing line counts such jobs.
//!
//! Every job's runs are announced to the cache before any starts
//! ([`palpate_core::Cache::expect`]), so it keeps an output exactly while a
//! run still to come needs it, within its memory budget
//! ([`palpate_core::runtime::DEFAULT_CACHE_BYTES`]). Two jobs that run at the same time and
//! need the same output may both compute it (the cache does not wait for
//! an output in progress); ordering the jobs so that graphs sharing a front
//! end do not start together avoids it.
//!
//! The jobs file (at most [`MAX_JOBS_FILE_BYTES`], [`MAX_JOBS`] jobs):
//!
//! ```toml
//! [[job]]
//! graph = "graphs/paper/table2.toml"      # relative to the working directory
//! out = "out/paper/table2"                # default: as `palpate run`
//! set = ["stages.scene.file=../scenes/paper_sensor.toml"]   # --set, each
//! name = "table2"                         # default: the graph path
//! log = "out/paper/table2.log"            # default: <out>.log
//! ```
//!
//! Jobs start in file order, `--jobs` at a time (default: the core count),
//! each on its own pool of `--threads / --jobs` threads (at least one; see
//! [`threads_per_job`] for why not one pool for all);
//! each writes what `palpate run` would print into its log, and the batch
//! prints one line per job with its wall time (taken while other jobs run
//! beside it) and, with `--times FILE`, writes them as JSON
//! (`{"name": seconds, ...}`). Every graph is loaded and checked before
//! any runs: an error names the jobs file, the job and the key. Each job's
//! output directory must be a directory or creatable (it is created then),
//! and no two jobs may share an output directory or a log (they would
//! overwrite each other's reports): the error names both jobs. If a job
//! fails, no further job starts; the jobs running finish, and the batch
//! exits with failure after naming each failed job and its log.

use crate::cluster::{outcome_text, prepare_points, ran_line, run_prepared, PreparedSweep, SweepJob};
use crate::core::shard::Selection;
use crate::core::{self, Graph, LoadOptions, RunOptions};
use serde::Deserialize;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

/// Largest jobs file read: 1 MiB (a few thousand jobs).
pub const MAX_JOBS_FILE_BYTES: u64 = 1 << 20;
/// Most jobs in one batch.
pub const MAX_JOBS: usize = 10_000;

/// The jobs file.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JobsFile {
    /// The jobs, in the order they start.
    #[serde(default)]
    job: Vec<JobSpec>,
}

/// One job of the jobs file.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JobSpec {
    /// The graph file, relative to the working directory.
    graph: PathBuf,
    /// Output directory. Default: the graph's `[run] out`, else
    /// `out/<graph name>` (as `palpate run`).
    out: Option<PathBuf>,
    /// Key overrides, `PATH=VALUE` each, as `palpate run --set`. Default none.
    #[serde(default)]
    set: Vec<String>,
    /// The job's name in messages and in the times file. Default: the graph
    /// path.
    name: Option<String>,
    /// File the job's reports go to (what `palpate run` prints). Default:
    /// `<out>.log`.
    log: Option<PathBuf>,
}

/// A job loaded and checked.
struct Job {
    name: String,
    path: PathBuf,
    set: Vec<(String, toml::Value)>,
    graph: Graph,
    log: PathBuf,
    /// A sweep's runs (`None`: a single run).
    sweep: Mutex<Option<PreparedSweep>>,
    /// The output directory, held so that one this batch created and left
    /// empty (a later job refused at load) is removed again.
    _out: crate::cli::OutDir,
}

/// Reads and checks the jobs file: every job's graph loaded (warnings
/// printed), every sweep's points loaded and its manifest written.
fn load_jobs(path: &Path, fresh: bool) -> Result<Vec<Job>, String> {
    let file = std::fs::File::open(path)
        .map_err(|e| format!("{}: cannot read the jobs file: {e}", path.display()))?;
    let mut text = String::new();
    file.take(MAX_JOBS_FILE_BYTES + 1)
        .read_to_string(&mut text)
        .map_err(|e| format!("{}: cannot read the jobs file: {e}", path.display()))?;
    if text.len() as u64 > MAX_JOBS_FILE_BYTES {
        return Err(format!(
            "{}: the jobs file is larger than {MAX_JOBS_FILE_BYTES} bytes",
            path.display()
        ));
    }
    let spec: JobsFile = toml::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
    if spec.job.is_empty() {
        return Err(format!("{}: no [[job]] tables", path.display()));
    }
    if spec.job.len() > MAX_JOBS {
        return Err(format!(
            "{}: {} jobs, more than the {MAX_JOBS} a batch takes",
            path.display(),
            spec.job.len()
        ));
    }
    let mut jobs = Vec::with_capacity(spec.job.len());
    // Each earlier job's label, output directory and log ([`resolved`]),
    // to refuse a second job writing to the same place.
    let mut places: Vec<(String, PathBuf, PathBuf)> = Vec::with_capacity(spec.job.len());
    for (i, j) in spec.job.into_iter().enumerate() {
        let name = j.name.unwrap_or_else(|| j.graph.display().to_string());
        let label = format!("job {} ({name})", i + 1);
        let at = format!("{}: {label}", path.display());
        let set = j
            .set
            .iter()
            .map(|s| LoadOptions::parse_set(s))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| format!("{at}: set: {e}"))?;
        let opts = LoadOptions {
            overrides: set.clone(),
            out: j.out.clone(),
            base_dir: None,
        };
        let graph = core::load_file(&j.graph, &opts).map_err(|e| format!("{at}: {e}"))?;
        for w in &graph.warnings {
            eprintln!("{at}: {w}");
        }
        let log = j.log.unwrap_or_else(|| {
            let mut s = graph.out_dir.clone().into_os_string();
            s.push(".log");
            PathBuf::from(s)
        });
        let out = crate::cli::prepare_out_dir(&graph.out_dir).map_err(|e| format!("{at}: {e}"))?;
        let (out_at, log_at) = (resolved(&graph.out_dir), resolved(&log));
        for (other, out, other_log) in &places {
            let both = format!("{}: {other} and {label} both write", path.display());
            if *out == out_at {
                return Err(format!(
                    "{both} to the output directory {}: each job needs its own `out`",
                    graph.out_dir.display()
                ));
            }
            if *other_log == log_at {
                return Err(format!(
                    "{both} the log {}: each job needs its own `log`",
                    log.display()
                ));
            }
        }
        places.push((label, out_at, log_at));
        let sweep = if graph.sweep.is_some() {
            let job = SweepJob {
                path: &j.graph,
                source: None,
                graph: &graph,
                set: &set,
            };
            Some(prepare_points(&job, &Selection::All, fresh).map_err(|e| format!("{at}: {e}"))?)
        } else {
            None
        };
        jobs.push(Job {
            name,
            path: j.graph,
            set,
            graph,
            log,
            sweep: Mutex::new(sweep),
            _out: out,
        });
    }
    Ok(jobs)
}

/// `p` made comparable with other jobs' paths: through its symbolic links
/// when it exists (an output directory does by then), else absolute, with
/// its parent resolved when that exists (a log not yet written).
fn resolved(p: &Path) -> PathBuf {
    if let Ok(c) = std::fs::canonicalize(p) {
        return c;
    }
    let abs = std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
    match (abs.parent(), abs.file_name()) {
        (Some(dir), Some(name)) => std::fs::canonicalize(dir).map_or(abs.clone(), |d| d.join(name)),
        _ => abs,
    }
}

/// Runs one job: its text (what `palpate run` prints) or an error message.
fn run_job(job: &Job, cache: &core::Cache) -> Result<String, String> {
    let t0 = Instant::now();
    let prepared = job
        .sweep
        .lock()
        .map_err(|_| format!("{}: its sweep's lock was poisoned", job.name))?
        .take();
    let opts = RunOptions::default();
    match prepared {
        Some(prepared) => {
            let sweep = SweepJob {
                path: &job.path,
                source: None,
                graph: &job.graph,
                set: &job.set,
            };
            let lines = Mutex::new(String::new());
            let on_point = |i: usize, n: usize, what: &str| {
                if let Ok(mut l) = lines.lock() {
                    l.push_str(&format!("{what}: {}/{n}\n", i + 1));
                }
            };
            let (outcome, ran, skipped) = run_prepared(&sweep, prepared, &opts, cache, &on_point)?;
            let mut text = lines.into_inner().unwrap_or_default();
            text.push_str(&ran_line(ran, skipped, t0.elapsed()));
            text.push('\n');
            let (report, ok) = outcome_text(&sweep, outcome, t0.elapsed());
            text.push_str(&report);
            if ok {
                Ok(text)
            } else {
                Err(format!(
                    "{}: a check of the sweep's report failed\n{text}",
                    job.graph.file
                ))
            }
        }
        None => {
            // A graph without a sweep runs as `palpate run` runs it, stage
            // chains trial by trial, keeping no outputs to share.
            let result =
                core::run(&job.graph, &opts).map_err(|e| format!("{}: run failed: {e}", job.graph.file))?;
            crate::cli::single_run_text(&job.graph, &result, t0.elapsed())
        }
    }
}

/// One job's end: its index in the jobs file, wall time and whether it
/// succeeded.
struct Done {
    index: usize,
    secs: f64,
    ok: bool,
}

/// Threads of each job's pool: `threads` (0: the core count) shared out
/// among the `workers` jobs that run at once, at least one each.
///
/// Why a pool per job: with one pool shared by all jobs, a thread waiting
/// inside one job's parallel stage (for the last trials of a scene, say)
/// takes whatever work is queued, and a job the batch has just started is
/// queued work: the thread ran that whole graph before returning to the
/// stage. Measured on `scripts/reproduce.sh`'s 25 jobs (2 at a time, 2
/// cores): one scene stage of 340 trials (median 3 ms a trial) recorded
/// 149 s of wall time, the graph it belonged to stalled meanwhile, and the
/// batch took 434 s wall and 842 s CPU; with a pool of one thread per job,
/// 399 s and 782 s, every result file identical (docs/benches.md, "The
/// paper's reproduction"). A job's recorded time is then its own stages'
/// time, on its share of the cores.
pub fn threads_per_job(threads: usize, workers: usize, cores: usize) -> usize {
    let threads = if threads == 0 { cores } else { threads };
    (threads / workers.max(1)).max(1)
}

/// `palpate batch`: see the module docs. `workers` jobs at a time (0: the
/// core count), each on a pool of its share of `threads` (0: the core
/// count; see [`threads_per_job`]).
pub fn run_batch(path: &Path, workers: usize, threads: usize, fresh: bool, times: Option<&Path>) -> ExitCode {
    let t0 = Instant::now();
    let jobs = match load_jobs(path, fresh) {
        Ok(j) => j,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
    };
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let workers = if workers == 0 { cores } else { workers }.clamp(1, jobs.len());
    // One pool per worker, not one pool for all: see `threads_per_job`.
    let per = threads_per_job(threads, workers, cores);
    let mut pools = Vec::with_capacity(workers);
    if workers.saturating_mul(per) > palpate_core::MAX_THREADS {
        eprintln!(
            "--jobs {workers} x {per} threads each is over the cap of {} worker threads",
            palpate_core::MAX_THREADS
        );
        return ExitCode::FAILURE;
    }
    for _ in 0..workers {
        match palpate_core::thread_pool(per, "--threads") {
            Ok(p) => pools.push(p),
            Err(e) => {
                eprintln!("{e}");
                return ExitCode::FAILURE;
            }
        }
    }
    let cache = core::Cache::default();
    for job in &jobs {
        if let Ok(s) = job.sweep.lock() {
            for g in s.iter().flat_map(|p| p.todo_graphs()) {
                cache.expect(g);
            }
        }
    }
    let next = AtomicUsize::new(0);
    let stop = AtomicBool::new(false);
    let done = Mutex::new(Vec::with_capacity(jobs.len()));
    std::thread::scope(|s| {
        for pool in &pools {
            let (next, stop, done, jobs, cache) = (&next, &stop, &done, &jobs, &cache);
            s.spawn(move || loop {
                if stop.load(Ordering::SeqCst) {
                    break;
                }
                let i = next.fetch_add(1, Ordering::SeqCst);
                let Some(job) = jobs.get(i) else {
                    break;
                };
                eprintln!(
                    "[{}/{}] {} -> {}",
                    i + 1,
                    jobs.len(),
                    job.name,
                    job.graph.out_dir.display()
                );
                let t = Instant::now();
                let outcome = pool.install(|| run_job(job, cache));
                let secs = t.elapsed().as_secs_f64();
                let (text, ok) = match outcome {
                    Ok(text) => (text, true),
                    Err(e) => (e, false),
                };
                let written = write_log(&job.log, &text);
                let ok = ok && written.is_ok();
                if ok {
                    println!("== {} -> {}: {secs:.2} s", job.name, job.graph.out_dir.display());
                } else {
                    stop.store(true, Ordering::SeqCst);
                    eprintln!("FAILED: {} (log: {})", job.name, job.log.display());
                    if let Err(e) = written {
                        eprintln!("  {e}");
                    }
                    for line in text.lines().rev().take(20).collect::<Vec<_>>().into_iter().rev() {
                        eprintln!("  {line}");
                    }
                }
                if let Ok(mut d) = done.lock() {
                    d.push(Done { index: i, secs, ok });
                }
            });
        }
    });
    let mut done = done.into_inner().unwrap_or_default();
    done.sort_by_key(|d| d.index);
    let failed = done.iter().filter(|d| !d.ok).count();
    let not_run = jobs.len() - done.len();
    // Jobs without a sweep bypass the cache (see `run_job`): say so, or a
    // batch of such graphs reads "0 reused, 0 computed" without a reason.
    let unshared = done
        .iter()
        .filter(|d| jobs[d.index].graph.sweep.is_none())
        .count();
    let unshared = match unshared {
        0 => String::new(),
        n => format!(
            " ({n} job{} without a [sweep] ran trial by trial, sharing nothing: add `sweep.repeats = 1` to share)",
            if n == 1 { "" } else { "s" }
        ),
    };
    eprintln!(
        "batch: {} job{} in {:.1} s, {failed} failed, {not_run} not started; cache: {} stage outputs reused, {} computed{unshared}",
        done.len(),
        if done.len() == 1 { "" } else { "s" },
        t0.elapsed().as_secs_f64(),
        cache.hits(),
        cache.misses()
    );
    if let Some(times) = times {
        let map: serde_json::Map<String, serde_json::Value> = done
            .iter()
            .filter(|d| d.ok)
            .map(|d| {
                (
                    jobs[d.index].name.clone(),
                    serde_json::json!((d.secs * 100.0).round() / 100.0),
                )
            })
            .collect();
        if let Err(e) = std::fs::write(times, serde_json::Value::Object(map).to_string()) {
            eprintln!("{}: cannot write the times: {e}", times.display());
            return ExitCode::FAILURE;
        }
    }
    if failed > 0 || not_run > 0 {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    }
}

/// Writes a job's text to its log, creating the folder.
fn write_log(path: &Path, text: &str) -> Result<(), String> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| format!("{}: cannot create: {e}", dir.display()))?;
    }
    std::fs::write(path, text).map_err(|e| format!("{}: cannot write the log: {e}", path.display()))
}
