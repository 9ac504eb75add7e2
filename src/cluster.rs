//! Sweeps beyond one machine: running a subset of a sweep's points, resuming,
//! merging point folders into the sweep's report, and Slurm job arrays.
//!
//! The model ([`palpate_core::shard`]): every (point, repeat) of a sweep writes
//! its reports into its own folder and, last, a completion marker; a rerun skips
//! complete points; the sweep's report (table, CSV/JSON, curves, accuracy-time
//! frontier) is always built from the markers, by the same code whether one
//! process ran every point or N shards ran a part each, so `palpate merge`
//! equals a single run (timing aside). See docs/cluster.md.

use crate::core::shard::{record_dir, Manifest, PointRecord, Selection};
use crate::core::sweep::{load_points, point_label, SweepRun};
use crate::core::{self, Graph, RunOptions};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// A sweep as run from the command line (or from Python).
pub struct SweepJob<'a> {
    /// The graph file (for a graph given as text: its name in messages).
    pub path: &'a Path,
    /// The graph's text and the folder its relative paths resolve against,
    /// when it did not come from `path` (Python's `palpate.run` on a string).
    pub source: Option<(&'a str, &'a Path)>,
    /// Its base graph (loaded with the overrides and output folder).
    pub graph: &'a Graph,
    /// `--set` overrides.
    pub set: &'a [(String, toml::Value)],
}

fn absolute(p: &Path) -> PathBuf {
    std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf())
}

impl SweepJob<'_> {
    fn manifest(&self) -> Result<Manifest, String> {
        let (text, base_dir) = match self.source {
            Some((text, base)) => (text.to_string(), absolute(base)),
            None => (
                palpate_core::input::read_text(self.path)
                    .map_err(|e| format!("{}: cannot read the graph file: {e}", self.path.display()))?,
                absolute(self.path.parent().unwrap_or(Path::new(""))),
            ),
        };
        let sweep = self
            .graph
            .sweep
            .as_ref()
            .ok_or_else(|| format!("{}: the graph has no [sweep] table", self.graph.file))?;
        Ok(Manifest {
            format: 1,
            file: self.graph.file.clone(),
            text,
            base_dir,
            overrides: self.set.iter().map(|(k, v)| (k.clone(), v.to_string())).collect(),
            points: sweep.points().len(),
            repeats: sweep.repeats,
        })
    }
}

/// A sweep's (point, repeat, graph) list, as `load_points` gives it.
type PointGraphs = Vec<(usize, usize, Graph)>;

/// Every (point, repeat) graph of the sweep the manifest describes, checked.
fn load_all(manifest: &Manifest, out: &Path) -> Result<(Graph, PointGraphs), String> {
    let (base, opts) = manifest.load(out).map_err(|e| e.to_string())?;
    let sweep = base
        .sweep
        .clone()
        .ok_or_else(|| format!("{}: the graph has no [sweep] table", manifest.file))?;
    // A job name as Slurm shows it, from the graph's file name: letters,
    // digits and `-_.` (`my graph;x.toml` would split the `#SBATCH` line).
    let stem: String = core::shard::stem(&manifest.file)
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "-_.".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect();
    let graphs = load_points(&manifest.text, &manifest.file, &stem, &opts, &base, &sweep)
        .map_err(|e| e.to_string())?;
    Ok((base, graphs))
}

/// What [`run_points`] leaves: every run of the sweep, rebuilt from the
/// completion markers, or how many are still missing.
pub enum SweepOutcome {
    /// Every (point, repeat) is complete: the base graph and the runs.
    Complete(Box<Graph>, Vec<SweepRun>),
    /// Some (point, repeat) runs are missing (other shards' work).
    Partial {
        /// Runs complete.
        complete: usize,
        /// Runs in the sweep.
        total: usize,
    },
}

/// A sweep checked and ready to run: every (point, repeat) graph loaded, its
/// manifest written, and the runs still to do chosen ([`prepare_points`]).
pub struct PreparedSweep {
    base: Graph,
    graphs: PointGraphs,
    /// Indices into `graphs` of the runs to do.
    todo: Vec<usize>,
    /// Selected runs skipped as already complete.
    skipped: usize,
}

impl PreparedSweep {
    /// The graphs of the runs still to do, in order (what a shared cache is
    /// told to expect, see [`core::Cache::expect`]).
    pub fn todo_graphs(&self) -> impl Iterator<Item = &Graph> {
        self.todo.iter().map(|&i| &self.graphs[i].2)
    }
}

/// Loads and checks every point of a sweep, writes its manifest, and picks
/// the selected runs that are not yet complete (all of them with `fresh`).
/// Errors are messages naming the graph file (and the point).
pub fn prepare_points(
    job: &SweepJob<'_>,
    selection: &Selection,
    fresh: bool,
) -> Result<PreparedSweep, String> {
    let manifest = job.manifest()?;
    let out = job.graph.out_dir.clone();
    let (base, graphs) = load_all(&manifest, &out)?;
    let total = manifest.points;
    let missing = selection.out_of_range(total);
    if !missing.is_empty() {
        return Err(format!(
            "{}: --points names {} but the sweep has points 0..{} (see `palpate sweep list {}`)",
            job.graph.file,
            missing
                .iter()
                .map(usize::to_string)
                .collect::<Vec<_>>()
                .join(", "),
            total.saturating_sub(1),
            job.path.display()
        ));
    }
    manifest.write(&out)?;
    let chosen: Vec<usize> = (0..graphs.len())
        .filter(|&i| selection.contains(graphs[i].0, total))
        .collect();
    let todo: Vec<usize> = chosen
        .iter()
        .copied()
        .filter(|&i| {
            let (p, r, g) = &graphs[i];
            fresh || PointRecord::read_matching(&g.out_dir, g, *p, *r).is_none()
        })
        .collect();
    Ok(PreparedSweep {
        skipped: chosen.len() - todo.len(),
        base,
        graphs,
        todo,
    })
}

/// Runs the selected points of a sweep that are not yet complete (all of them
/// with `fresh`), each writing its reports and completion marker; then gathers
/// the whole sweep from the markers. `on_point(i, n, label)` is called before
/// each point runs. Errors are messages naming the graph file and the point.
pub fn run_points(
    job: &SweepJob<'_>,
    selection: &Selection,
    fresh: bool,
    opts: &RunOptions<'_>,
    on_point: &dyn Fn(usize, usize, &str),
) -> Result<(SweepOutcome, usize, usize), String> {
    let prepared = prepare_points(job, selection, fresh)?;
    // The cache is told which runs will happen, so it keeps just what they
    // share.
    let cache = core::Cache::default();
    for g in prepared.todo_graphs() {
        cache.expect(g);
    }
    run_prepared(job, prepared, opts, &cache, on_point)
}

/// Runs a [`PreparedSweep`]'s runs under `cache`, which the caller has told
/// to expect them ([`core::Cache::expect`]; `palpate batch` shares one cache
/// among several sweeps and announces all of their runs first), then
/// gathers the sweep as [`run_points`] does.
pub fn run_prepared(
    job: &SweepJob<'_>,
    prepared: PreparedSweep,
    opts: &RunOptions<'_>,
    cache: &core::Cache,
    on_point: &dyn Fn(usize, usize, &str),
) -> Result<(SweepOutcome, usize, usize), String> {
    let PreparedSweep {
        base,
        graphs,
        todo,
        skipped,
    } = prepared;
    let points = base.sweep.as_ref().map(|s| s.points()).unwrap_or_default();
    let mut ran = 0usize;
    for (i, &t) in todo.iter().enumerate() {
        let (p, r, g) = &graphs[t];
        let label = points.get(*p).map(point_label).unwrap_or_default();
        on_point(i, todo.len(), &format!("point {p} ({label}), repeat {r}"));
        let o = RunOptions {
            progress: opts.progress,
            cache: Some(cache),
            keep_outputs: false,
        };
        let result = core::run(g, &o)
            .map_err(|e| format!("{}: sweep point {p} ({label}), repeat {r}: {e}", job.graph.file))?;
        crate::report::write_run_files(g, &result)?;
        PointRecord::new(g, *p, *r, &label, &result).write(&g.out_dir)?;
        ran += 1;
    }
    let count = graphs.len();
    let outcome = match gather(&base, graphs) {
        Ok(runs) => SweepOutcome::Complete(Box::new(base), runs),
        Err(missing) => SweepOutcome::Partial {
            complete: count - missing.len(),
            total: count,
        },
    };
    Ok((outcome, ran, skipped))
}

/// `palpate run GRAPH` on a sweep: [`run_points`], then, when every point of
/// the sweep is complete, the sweep's report.
pub fn run_sweep(job: &SweepJob<'_>, selection: &Selection, fresh: bool, opts: &RunOptions<'_>) -> ExitCode {
    let t0 = std::time::Instant::now();
    let announce = |i: usize, n: usize, what: &str| eprintln!("{what}: {}/{n}", i + 1);
    let (outcome, ran, skipped) = match run_points(job, selection, fresh, opts, &announce) {
        Ok(x) => x,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
    };
    eprintln!("{}", ran_line(ran, skipped, t0.elapsed()));
    let (text, ok) = outcome_text(job, outcome, t0.elapsed());
    print!("{text}");
    if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    }
}

/// How many point runs ran and were skipped, and the time.
pub(crate) fn ran_line(ran: usize, skipped: usize, elapsed: std::time::Duration) -> String {
    format!(
        "ran {ran} point run{}, skipped {skipped} already complete ({:.1} s)",
        if ran == 1 { "" } else { "s" },
        elapsed.as_secs_f64()
    )
}

/// What `palpate run` prints at the end of a sweep (the sweep's report, or
/// how to merge a partial one), and whether the report's checks passed.
pub(crate) fn outcome_text(
    job: &SweepJob<'_>,
    outcome: SweepOutcome,
    elapsed: std::time::Duration,
) -> (String, bool) {
    match outcome {
        SweepOutcome::Complete(base, runs) => {
            let (mut text, ok) = crate::report::sweep_report(&base, &runs);
            text.push_str(&format!("sweep wall time: {:.1} s\n", elapsed.as_secs_f64()));
            (text, ok)
        }
        SweepOutcome::Partial { complete, total } => (
            format!(
                "{complete} of {total} point runs complete; when every shard has finished, write the sweep's report with\n  palpate merge {}\n",
                job.graph.out_dir.display()
            ),
            true,
        ),
    }
}

/// The sweep's runs rebuilt from their markers, or the (point, repeat, folder)
/// of each one missing.
fn gather(
    base: &Graph,
    graphs: Vec<(usize, usize, Graph)>,
) -> Result<Vec<SweepRun>, Vec<(usize, usize, PathBuf)>> {
    let points = base.sweep.as_ref().map(|s| s.points()).unwrap_or_default();
    let mut runs = Vec::with_capacity(graphs.len());
    let mut missing = Vec::new();
    for (p, r, g) in graphs {
        let Some(point) = points.get(p) else {
            missing.push((p, r, g.out_dir.clone()));
            continue;
        };
        match PointRecord::read_matching(&g.out_dir, &g, p, r) {
            Some(rec) => runs.push(SweepRun {
                point: p,
                series: point.series.clone(),
                key: point.key.clone(),
                value: point.value.clone(),
                label: point_label(point),
                seed: g.run.seed,
                graph: g,
                repeat: r,
                result: rec.to_result(),
            }),
            None => missing.push((p, r, g.out_dir.clone())),
        }
    }
    if missing.is_empty() {
        Ok(runs)
    } else {
        Err(missing)
    }
}

/// `palpate merge OUT`: the sweep's report from the point folders under `out`.
pub fn merge(out: &Path) -> ExitCode {
    let manifest = match Manifest::read(out) {
        Ok(m) => m,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
    };
    let (base, graphs) = match load_all(&manifest, out) {
        Ok(g) => g,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
    };
    let count = graphs.len();
    match gather(&base, graphs) {
        Ok(runs) => {
            let (text, ok) = crate::report::sweep_report(&base, &runs);
            print!("{text}");
            if ok {
                ExitCode::SUCCESS
            } else {
                ExitCode::FAILURE
            }
        }
        Err(missing) => {
            eprintln!(
                "{}: {} of {} point runs are not complete (no valid {} in their folder); nothing merged:",
                out.display(),
                missing.len(),
                count,
                core::shard::MARKER
            );
            for (p, r, dir) in &missing {
                eprintln!("  point {p}, repeat {r}: {}", dir.display());
            }
            let list: Vec<String> = {
                let mut ps: Vec<usize> = missing.iter().map(|m| m.0).collect();
                ps.dedup();
                ps.iter().map(usize::to_string).collect()
            };
            eprintln!(
                "run them with: palpate run {} --out {} --points {}",
                manifest.file,
                out.display(),
                list.join(",")
            );
            ExitCode::FAILURE
        }
    }
}

/// `palpate sweep list GRAPH`: every point with its number, label and keys.
pub fn list(path: &Path, graph: &Graph) -> ExitCode {
    let Some(sweep) = &graph.sweep else {
        eprintln!("{}: the graph has no [sweep] table", path.display());
        return ExitCode::FAILURE;
    };
    let points = sweep.points();
    // The seeds the runs use: refused, as the run refuses them, if a
    // point's repeats would pass u64::MAX (they used to print clamped).
    for p in &points {
        if let Some(seed) = core::sweep::point_seed(p, graph.run.seed) {
            if core::sweep::repeat_seeds(seed, sweep.repeats).is_none() {
                eprintln!(
                    "{}: point {}: {}",
                    path.display(),
                    point_label(p),
                    core::sweep::seed_overflow_message(seed, sweep.repeats)
                );
                return ExitCode::FAILURE;
            }
        }
    }
    // One range when every point starts at the same seed (a sweep of
    // `repeats` alone is one point over `run.seed`, the graph's own).
    let starts: Vec<Option<u64>> = points
        .iter()
        .map(|p| core::sweep::point_seed(p, graph.run.seed))
        .collect();
    let last = sweep.repeats.saturating_sub(1);
    let seeds = match starts.first() {
        Some(&Some(first)) if starts.iter().all(|&s| s == Some(first)) => {
            match core::sweep::repeat_seeds(first, sweep.repeats) {
                Some(r) => format!("seeds {}..={}", r.start(), r.end()),
                None => format!("seeds {first} + 0..={last}"),
            }
        }
        _ => format!("seeds: each point's run.seed + 0..={last}"),
    };
    println!(
        "{}: {} point{} x {} repeat{} ({seeds}), output {}",
        path.display(),
        points.len(),
        if points.len() == 1 { "" } else { "s" },
        sweep.repeats,
        if sweep.repeats == 1 { "" } else { "s" },
        graph.out_dir.display()
    );
    println!("{:>5}  {:<28}  keys", "point", "label");
    for (i, p) in points.iter().enumerate() {
        let mut keys: Vec<String> = p.set.iter().map(|(k, v)| format!("{k} = {v}")).collect();
        keys.push(format!("{} = {}", p.key, p.value));
        let done = (0..sweep.repeats)
            .filter(|&r| {
                record_dir(&graph.out_dir, p, sweep.repeats, r)
                    .join(core::shard::MARKER)
                    .is_file()
            })
            .count();
        println!(
            "{i:>5}  {:<28}  {}{}",
            point_label(p),
            keys.join(", "),
            if done > 0 {
                format!("  [{done}/{} repeats have a marker]", sweep.repeats)
            } else {
                String::new()
            }
        );
    }
    ExitCode::SUCCESS
}

/// Settings of `palpate slurm`.
pub struct SlurmOptions {
    /// Tasks in the job array (each runs one shard); capped at the number of points.
    pub array_size: usize,
    /// `--partition`, if any.
    pub partition: Option<String>,
    /// `--time` per task (Slurm's format, e.g. `01:00:00`).
    pub time: String,
    /// CPUs per task (also the worker threads of each shard).
    pub cpus: usize,
}

/// Whether `t` is one of the forms of time limit `sbatch --time` accepts:
/// `M`, `M:S`, `H:M:S`, `D-H`, `D-H:M`, `D-H:M:S` (digits), or `UNLIMITED` /
/// `INFINITE`. Checked here so that a typo fails when the scripts are
/// written, not when the array is submitted.
fn slurm_time_ok(t: &str) -> bool {
    if t.eq_ignore_ascii_case("unlimited") || t.eq_ignore_ascii_case("infinite") {
        return true;
    }
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    let (days, rest) = match t.split_once('-') {
        Some((d, r)) => (Some(d), r),
        None => (None, t),
    };
    let parts: Vec<&str> = rest.split(':').collect();
    days.is_none_or(digits) && (1..=3).contains(&parts.len()) && parts.iter().all(|p| digits(p))
}

/// Quotes a string for a POSIX shell.
fn sh(s: &str) -> String {
    format!("'{}'", s.replace('\'', r"'\''"))
}

/// Writes `OUT/slurm/{array,merge}.sbatch` and `submit.sh` for the sweep, and
/// returns their paths.
pub fn slurm_scripts(job: &SweepJob<'_>, o: &SlurmOptions) -> Result<Vec<PathBuf>, String> {
    let manifest = job.manifest()?;
    if o.array_size == 0 || o.cpus == 0 {
        return Err("--array-size and --cpus must be at least 1".into());
    }
    // Each task runs `palpate run --threads <cpus>`, which refuses more.
    if o.cpus > core::MAX_THREADS {
        return Err(format!(
            "--cpus {} is over the cap of {} worker threads a task's run may start",
            o.cpus,
            core::MAX_THREADS
        ));
    }
    if !slurm_time_ok(&o.time) {
        return Err(format!(
            "--time `{}`: give one of Slurm's forms: minutes, minutes:seconds, hours:minutes:seconds, \
             days-hours, days-hours:minutes, days-hours:minutes:seconds (e.g. 01:00:00), or UNLIMITED",
            o.time
        ));
    }
    if let Some(p) = &o.partition {
        if p.is_empty() || !p.chars().all(|c| c.is_ascii_alphanumeric() || "-_.,".contains(c)) {
            return Err(format!("--partition `{p}`: letters, digits and -_., only"));
        }
    }
    let n = o.array_size.min(manifest.points.max(1));
    let out = absolute(&job.graph.out_dir);
    // `#SBATCH` lines are not shell lines: Slurm splits their values at
    // white space and reads `%` as a file-name pattern, so a folder holding
    // either would send the logs elsewhere; refused before anything is
    // written. (The `exec` lines are quoted and carry any path.)
    if let Some(c) = out
        .to_string_lossy()
        .chars()
        .find(|c| c.is_whitespace() || "%\"'\\".contains(*c))
    {
        return Err(format!(
            "the output folder {} holds {c:?}, which a `#SBATCH --output` line cannot carry (Slurm splits \
             its values at spaces and reads % as a pattern): give --out a folder without it",
            out.display()
        ));
    }
    let dir = out.join("slurm");
    std::fs::create_dir_all(dir.join("logs")).map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
    let exe = std::env::current_exe().map_err(|e| format!("cannot find palpate's own path: {e}"))?;
    let graph = absolute(job.path);
    let cwd = std::env::current_dir().map_err(|e| format!("cannot read the working directory: {e}"))?;
    let sets: String = job
        .set
        .iter()
        .map(|(k, v)| format!(" --set {}", sh(&format!("{k}={v}"))))
        .collect();
    let stem = core::shard::stem(&manifest.file);
    let partition = o
        .partition
        .as_ref()
        .map(|p| format!("#SBATCH --partition={p}\n"))
        .unwrap_or_default();
    let array = format!(
        "#!/bin/bash\n\
         # A Slurm job array over the sweep points of {graph}: task K of {n} runs\n\
         # shard K/{n} (`palpate run --shard K/{n}`); a point already complete in\n\
         # {out} is skipped, so resubmitting resumes. Written by `palpate slurm`.\n\
         #SBATCH --job-name=palpate-{stem}\n\
         #SBATCH --array=1-{n}\n\
         #SBATCH --cpus-per-task={cpus}\n\
         #SBATCH --time={time}\n\
         {partition}\
         #SBATCH --output={logs}/shard-%a.out\n\
         set -euo pipefail\n\
         cd {cwd}\n\
         exec {exe} run {graph_q} --out {out_q} --shard \"${{SLURM_ARRAY_TASK_ID}}/{n}\" --threads \"${{SLURM_CPUS_PER_TASK:-{cpus}}}\"{sets}\n",
        graph = graph.display(),
        out = out.display(),
        cpus = o.cpus,
        time = o.time,
        logs = dir.join("logs").display(),
        cwd = sh(&cwd.display().to_string()),
        exe = sh(&exe.display().to_string()),
        graph_q = sh(&graph.display().to_string()),
        out_q = sh(&out.display().to_string()),
    );
    let merge = format!(
        "#!/bin/bash\n\
         # Merges the point folders of {out} into the sweep's report once every\n\
         # array task has succeeded (submitted with --dependency=afterok).\n\
         #SBATCH --job-name=palpate-{stem}-merge\n\
         #SBATCH --cpus-per-task=1\n\
         #SBATCH --time={time}\n\
         {partition}\
         #SBATCH --output={logs}/merge.out\n\
         set -euo pipefail\n\
         cd {cwd}\n\
         exec {exe} merge {out_q}\n",
        out = out.display(),
        time = o.time,
        logs = dir.join("logs").display(),
        cwd = sh(&cwd.display().to_string()),
        exe = sh(&exe.display().to_string()),
        out_q = sh(&out.display().to_string()),
    );
    let submit = format!(
        "#!/bin/sh\n\
         # Submits the array, then the merge job that waits for every task to succeed.\n\
         set -eu\n\
         cd {d}\n\
         array=$(sbatch --parsable array.sbatch)\n\
         array=${{array%%;*}}\n\
         merge=$(sbatch --parsable --dependency=afterok:\"$array\" merge.sbatch)\n\
         merge=${{merge%%;*}}\n\
         echo \"submitted array job $array ({n} tasks) and merge job $merge\"\n\
         echo \"$array $merge\" > jobs.txt\n",
        d = sh(&dir.display().to_string()),
    );
    let mut files = Vec::new();
    for (name, text) in [
        ("array.sbatch", array),
        ("merge.sbatch", merge),
        ("submit.sh", submit),
    ] {
        let path = dir.join(name);
        core::output::write_atomic(&path, text.as_bytes())
            .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let _ = std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755));
        }
        files.push(path);
    }
    manifest.write(&job.graph.out_dir)?;
    Ok(files)
}
