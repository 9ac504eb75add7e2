//! The `palpate` command line: run, check and draw experiment graphs, and list
//! the registered stage types.
//!
//! It lives in the library so that a plugin crate can ship its own binary with
//! its stages linked: `fn main() -> ExitCode { my_plugin::link(); palpate::cli::main() }`.

use crate::core::shard::Selection;
use crate::core::{self, registry, Graph, LoadOptions, Progress, RunOptions};
use clap::{Parser, Subcommand, ValueEnum};
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Mutex;

#[derive(Parser)]
#[command(
    name = "palpate",
    version,
    about = "Tactile-sensing experiments as TOML graphs of typed, pluggable stages"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a graph and print its reports and timing.
    Run {
        /// The graph file.
        graph: PathBuf,
        /// Override a key: `stages.<id>.<key>=<value>`, `run.<key>=<value>` or `sweep.<key>=<value>`
        /// (TOML value; a table is merged into the key's table, except `run.protocol`, which it
        /// replaces). `sweep.repeats=5` runs a graph without a sweep at 5 seeds.
        #[arg(long = "set", value_name = "PATH=VALUE", value_parser = LoadOptions::parse_set)]
        set: Vec<(String, toml::Value)>,
        /// Output directory (default: `[run] out`, else out/<graph name>); created
        /// if missing, and refused before anything runs if it is a file.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Worker threads (default: all cores; at most 4096). Results do not depend on it.
        #[arg(long)]
        threads: Option<usize>,
        /// Sweeps: run only these points (numbers from `palpate sweep list`),
        /// e.g. `3,7-9`.
        #[arg(long, conflicts_with_all = ["shard", "live"], value_parser = Selection::parse_points)]
        points: Option<Selection>,
        /// Sweeps: run only shard K of N (1-based; contiguous blocks of points),
        /// e.g. `2/4`.
        #[arg(long, conflicts_with = "live", value_parser = Selection::parse_shard)]
        shard: Option<Selection>,
        /// Sweeps: run every selected point again, even those with a completion
        /// marker from an earlier run.
        #[arg(long, conflicts_with = "live")]
        fresh: bool,
        /// After the reports, print what each reported number means (accuracy,
        /// MAE, SD, no edge, decision time, ...).
        #[arg(long)]
        explain: bool,
        /// Stream every trial through the stages' streaming forms, block by
        /// block as a board delivers them, printing estimates as they change
        /// (every stage must stream: see `check --live`); then the time per
        /// block and each stage's share (also in live_timing.md / .csv).
        #[arg(long)]
        live: bool,
        /// With --live: samples per block, at least 1 (1 = frame by frame).
        #[arg(long, default_value_t = 1, requires = "live", value_parser = parse_block)]
        block: usize,
    },
    /// Run several graphs (a jobs file) in one process, a few at a time,
    /// sharing one cache: stages alike in several graphs (a scene and front
    /// end every graph of a study starts with) run once. Only graphs with a
    /// `[sweep]` share (one without runs trial by trial, as `palpate run`
    /// does, keeping nothing; `--set sweep.repeats=1` in its job makes it
    /// share). Each job's reports go to its log; see `palpate::batch` for
    /// the jobs file.
    Batch {
        /// The jobs file: `[[job]]` tables with `graph` and optional `out`,
        /// `set`, `name`, `log` (no two jobs may share an `out` or a `log`).
        jobs: PathBuf,
        /// Jobs at a time (default: the core count).
        #[arg(long = "jobs", value_name = "N", default_value_t = 0)]
        workers: usize,
        /// Worker threads of the whole batch (default: all cores), shared out
        /// among the jobs that run at once: each job gets its own pool of
        /// threads/jobs, at least one. Results do not depend on it.
        #[arg(long, default_value_t = 0)]
        threads: usize,
        /// Run every sweep point again, even those with a completion marker.
        #[arg(long)]
        fresh: bool,
        /// Write each job's wall time (seconds, JSON) to this file.
        #[arg(long)]
        times: Option<PathBuf>,
    },
    /// Sweep points: list them (number, label, keys).
    Sweep {
        #[command(subcommand)]
        command: SweepCommand,
    },
    /// Write a sweep's report from its point folders (after `run --shard` or
    /// `--points` runs, or a Slurm array); lists the points still missing.
    Merge {
        /// The sweep's output folder (holding sweep-manifest.json).
        out: PathBuf,
    },
    /// Write Slurm batch scripts for a sweep: a job array over its points and a
    /// merge job that runs once every task succeeded; prints how to submit them.
    Slurm {
        /// The graph file (with a [sweep] table).
        graph: PathBuf,
        /// Override a key, as for `run`.
        #[arg(long = "set", value_name = "PATH=VALUE", value_parser = LoadOptions::parse_set)]
        set: Vec<(String, toml::Value)>,
        /// Output folder of the sweep (default: `[run] out`, else out/<graph name>);
        /// must be on a file system every node sees.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Tasks in the array (each runs one shard); at most the number of points.
        #[arg(long, default_value_t = 8)]
        array_size: usize,
        /// Slurm partition (default: the cluster's default).
        #[arg(long)]
        partition: Option<String>,
        /// Time limit per task, in a form `sbatch --time` takes: M, M:S, H:M:S, D-H, D-H:M, D-H:M:S or UNLIMITED.
        #[arg(long, default_value = "01:00:00")]
        time: String,
        /// CPUs per task (and worker threads per shard; at most 4096).
        #[arg(long, default_value_t = 2)]
        cpus: usize,
    },
    /// Check a graph: print every error and warning; exit non-zero on an error.
    Check {
        /// The graph file.
        graph: PathBuf,
        /// Override a key, as for `run`.
        #[arg(long = "set", value_name = "PATH=VALUE", value_parser = LoadOptions::parse_set)]
        set: Vec<(String, toml::Value)>,
        /// Also check that every stage can stream (for `run --live`): name each
        /// stage that cannot, and its causal alternative.
        #[arg(long)]
        live: bool,
    },
    /// Print a graph as Graphviz dot or a Mermaid flowchart.
    Graph {
        /// The graph file.
        graph: PathBuf,
        /// Output format.
        #[arg(long, value_enum, default_value_t = Format::Dot)]
        format: Format,
    },
    /// Simulate a scene file's trials as files `signal_file` reads back: one NPY
    /// `(samples, taxels)` per trial (CSV with --csv), a `labels.toml` label file,
    /// the trials' metadata (`trials.json`), and an SVG plot of one taxel over a
    /// trial (like the paper's Fig. 3a).
    Simulate {
        /// A scene file, e.g. graphs/scenes/lab.toml.
        scene: PathBuf,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Seed (the same seed gives the same bits as a graph whose `scene` stage
        /// has id `scene` and `file` = this file).
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Write CSV (`time_ms, taxel_0 ..`) instead of NPY: about twice the disk.
        #[arg(long)]
        csv: bool,
    },
    /// A DAQ board over serial: emulate one, or estimate live from one.
    Daq {
        #[command(subcommand)]
        command: DaqCommand,
    },
    /// Print the JSON schema of graph files (generated from every registered
    /// stage), for editors that validate and complete TOML.
    Schema,
    /// List every registered stage type, or show one type's keys.
    Stages {
        /// A stage type: show its keys with defaults, units and docs.
        r#type: Option<String>,
    },
}

#[derive(Subcommand)]
enum SweepCommand {
    /// Print every point of a graph's sweep: number, label, keys, and how many
    /// of its repeats are already complete in the output folder.
    List {
        /// The graph file.
        graph: PathBuf,
        /// Override a key, as for `run`.
        #[arg(long = "set", value_name = "PATH=VALUE", value_parser = LoadOptions::parse_set)]
        set: Vec<(String, toml::Value)>,
        /// Output folder to look for completion markers in (default as for `run`).
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

#[derive(Subcommand)]
enum DaqCommand {
    /// Play a simulated trial or a recording into a pseudo-terminal at real-time
    /// rate (times --speed), as a DAQ board would, so the live path runs without
    /// hardware. Prints the device path to open with `palpate daq run`.
    Emulate {
        /// A scene file (e.g. graphs/scenes/lab.toml) to simulate one trial of.
        #[arg(long, conflicts_with = "recording")]
        scene: Option<PathBuf>,
        /// Edge angle of the simulated trial, degrees.
        #[arg(long, default_value_t = 45.0)]
        angle: f64,
        /// Seed of the simulated trial: the array's and the trial's random
        /// draws, as a `scene` stage of id `scene` makes them with this run
        /// seed. The same --scene, --angle and --seed play the same trial as
        /// `palpate simulate --seed` (its trial at that angle, r00) and
        /// `palpate daq run --emulate-scene`.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// A recording (CSV, NPY, NPZ, MAT or raw DAQ; the first trial is played). Its array is the one a
        /// `labels.toml` or `trials.json` beside it declares (as `palpate simulate` writes), else 4 x 4.
        #[arg(long)]
        recording: Option<PathBuf>,
        /// With a raw DAQ --recording that ends inside a frame (cut while
        /// being written): play it without that incomplete frame instead of
        /// refusing it.
        #[arg(long, requires = "recording")]
        allow_cut_end: bool,
        /// Sample rate of the recording, Hz, when the file does not carry it
        /// (with `--recording` only: a scene's rate is its
        /// `motion.sample_rate_hz`, and a flag that changes nothing is refused).
        #[arg(long)]
        sample_rate_hz: Option<f64>,
        /// Playback speed: 1 = real time.
        #[arg(long, default_value_t = 1.0)]
        speed: f64,
        /// Seconds to wait after printing the device path before playing, so a
        /// reader (`palpate daq run PATH`) can open it first.
        #[arg(long, default_value_t = 5.0, value_parser = parse_seconds)]
        delay: f64,
    },
    /// Estimate edges live from a DAQ on a serial port (or an emulated one):
    /// `palpate run GRAPH --live` on a live graph whose `daq` source is pointed
    /// at the port (GRAPH: --config, default the shipped graphs/live.toml).
    Run {
        /// The serial device, e.g. /dev/ttyACM0 (omit with --emulate-scene).
        #[arg(required_unless_present = "emulate_scene")]
        port: Option<String>,
        /// Instead of a device, emulate one in this process: a trial of this
        /// scene file (at --angle, --seed) played at --speed.
        #[arg(long)]
        emulate_scene: Option<PathBuf>,
        /// Edge angle of the emulated trial, degrees.
        #[arg(long, default_value_t = 45.0)]
        angle: f64,
        /// Seed of the emulated trial (the graph's `[run] seed`): the array's
        /// and the trial's random draws, keyed as a `scene` stage of id
        /// `scene` keys them (the `daq` stage's `scene_stage_id`). The same
        /// scene, --angle and --seed play the same trial as `palpate daq
        /// emulate --seed` and `palpate simulate --seed` (its trial at that
        /// angle, r00).
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Playback speed of the emulated trial: 1 = real time, 0 = as fast as
        /// the graph reads.
        #[arg(long, default_value_t = 1.0)]
        speed: f64,
        /// The live graph (its one `daq` source gets the port). Default: the
        /// shipped graphs/live.toml, built into palpate, so the command works
        /// from any folder.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Baud rate (USB CDC devices ignore it).
        #[arg(long, default_value_t = 921_600)]
        baud: u32,
        /// Record the raw byte stream to this file as it arrives.
        #[arg(long)]
        record: Option<PathBuf>,
        /// Stop after this many seconds.
        #[arg(long, value_parser = parse_seconds)]
        seconds: Option<f64>,
    },
}

/// Most seconds a duration flag takes (about 31 years): `Duration` panics on
/// NaN, infinite or overflowing seconds, so those are refused when parsing.
const MAX_FLAG_SECONDS: f64 = 1e9;

/// Parses a duration flag in seconds: finite, `0..=MAX_FLAG_SECONDS`.
fn parse_seconds(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("`{s}` is not a number of seconds"))?;
    if !(0.0..=MAX_FLAG_SECONDS).contains(&v) {
        return Err(format!(
            "`{s}` must be a number of seconds from 0 to {MAX_FLAG_SECONDS:e}"
        ));
    }
    Ok(v)
}

/// Parses `--block`: a whole number of samples, at least 1 (a block of no
/// samples delivers nothing; it used to be taken silently as 1).
fn parse_block(s: &str) -> Result<usize, String> {
    match s.trim().parse::<usize>() {
        Ok(0) => Err("a block holds at least 1 sample (1 = frame by frame)".into()),
        Ok(n) => Ok(n),
        Err(_) => Err(format!("`{s}` is not a whole number of samples")),
    }
}

/// Checks, before anything is computed, that a run's output directory can
/// take its reports: an existing directory, or one it creates now. Why
/// first: the sinks write last, so a file in the way (`--out` naming a
/// file, or `/dev/null`) failed only after every stage had run.
///
/// Hold the returned [`OutDir`] until the run has written its reports.
pub(crate) fn prepare_out_dir(dir: &std::path::Path) -> Result<OutDir, String> {
    let created = match std::fs::metadata(dir) {
        Ok(m) if m.is_dir() => false,
        Ok(_) => {
            return Err(format!(
                "output directory {}: exists and is not a directory; give --out (or `[run] out`) a folder",
                dir.display()
            ))
        }
        Err(_) => {
            std::fs::create_dir_all(dir)
                .map_err(|e| format!("output directory {}: cannot create it: {e}", dir.display()))?;
            true
        }
    };
    Ok(OutDir {
        path: dir.to_path_buf(),
        created,
    })
}

/// A run's output directory, ready ([`prepare_out_dir`]). If this run
/// created it, dropping this removes it again when it is still empty: a run
/// refused after the check (a sweep series with a bad value, a batch whose
/// third job does not load) leaves no empty folder behind. A folder that
/// was there before is never removed, and `remove_dir` refuses one holding
/// anything, so no report is ever deleted.
#[must_use = "the folder is removed again when this is dropped empty"]
pub(crate) struct OutDir {
    path: PathBuf,
    created: bool,
}

impl Drop for OutDir {
    fn drop(&mut self) {
        if self.created {
            // Best effort: a folder that cannot be removed is only untidy.
            let _ = std::fs::remove_dir(&self.path);
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum Format {
    Dot,
    Mermaid,
}

/// Keeps freed memory in the process for reuse instead of returning it to
/// the kernel (glibc only; elsewhere a no-op).
///
/// Why: every stage of a trial's chain allocates its output (2.8 MB for a
/// 21 s, 16-taxel lab trial) and frees its input. glibc serves blocks that
/// large with `mmap` and unmaps them when freed (or trims the heap above
/// 128 kB), so the next trial's buffers are page-faulted and zeroed by the
/// kernel again: ~0.3 to 0.5 ms of a 4 ms trial
/// (`palpate run graphs/quickstart.toml --threads 1` with and without
/// `MALLOC_TRIM_THRESHOLD_` and `MALLOC_MMAP_THRESHOLD_` set). Blocks up to
/// 32 MiB (glibc's largest threshold) now come from the heap, and up to
/// 1 GiB of free heap is kept. The peak is unchanged, and since the same
/// sizes recur trial after trial the kept memory is reused, not grown.
/// Public so that benches that time stages (`benches/pipeline.rs`) measure
/// them under the allocator the binary runs them with.
pub fn tune_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets allocator parameters; it is called before
    // any other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
    }
}

/// Parses the command line and runs it.
pub fn main() -> ExitCode {
    // Printing into a closed pipe (`palpate stages | head`) ends quietly, as
    // command-line tools do, instead of panicking.
    let default_hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let msg = info
            .payload()
            .downcast_ref::<String>()
            .map(String::as_str)
            .unwrap_or("");
        if msg.contains("Broken pipe") {
            std::process::exit(0);
        }
        default_hook(info);
    }));
    crate::link();
    tune_allocator();
    let cli = Cli::parse();
    match cli.command {
        Command::Run {
            graph,
            set,
            out,
            live: true,
            block,
            ..
        } => cmd_run_live(graph, set, out, block),
        Command::Run {
            graph,
            set,
            out,
            threads,
            points,
            shard,
            fresh,
            explain,
            ..
        } => {
            let code = cmd_run(
                graph,
                set,
                out,
                threads,
                points.or(shard).unwrap_or_default(),
                fresh,
            );
            if explain {
                print!("\n{}", crate::guide::EXPLAIN);
            }
            code
        }
        Command::Sweep {
            command: SweepCommand::List { graph, set, out },
        } => match load(&graph, set, out) {
            Some(g) => crate::cluster::list(&graph, &g),
            None => ExitCode::FAILURE,
        },
        Command::Batch {
            jobs,
            workers,
            threads,
            fresh,
            times,
        } => crate::batch::run_batch(&jobs, workers, threads, fresh, times.as_deref()),
        Command::Merge { out } => crate::cluster::merge(&out),
        Command::Slurm {
            graph,
            set,
            out,
            array_size,
            partition,
            time,
            cpus,
        } => cmd_slurm(
            graph,
            set,
            out,
            crate::cluster::SlurmOptions {
                array_size,
                partition,
                time,
                cpus,
            },
        ),

        Command::Check {
            graph,
            set,
            live: true,
        } => match load(&graph, set, None) {
            Some(g) => match core::stream::plan(&g) {
                Ok(p) => {
                    println!(
                        "{}: ok, live: every stage streams ({} streaming stages after source `{}`)",
                        graph.display(),
                        p.stages.len(),
                        g.nodes[p.source].id
                    );
                    ExitCode::SUCCESS
                }
                Err(problems) => {
                    for p in &problems {
                        eprintln!("{}: {p}", graph.display());
                    }
                    ExitCode::FAILURE
                }
            },
            None => ExitCode::FAILURE,
        },
        Command::Check { graph, set, .. } => match load(&graph, set.clone(), None) {
            Some(g) if g.sweep.is_some() && load_sweep_points(&graph, set, &g).is_none() => ExitCode::FAILURE,
            Some(g) => {
                println!(
                    "{}: ok ({} stages, {} warning{})",
                    graph.display(),
                    g.nodes.len(),
                    g.warnings.len(),
                    if g.warnings.len() == 1 { "" } else { "s" }
                );
                ExitCode::SUCCESS
            }
            None => ExitCode::FAILURE,
        },
        Command::Graph { graph, format } => match load(&graph, Vec::new(), None) {
            Some(g) => {
                print!(
                    "{}",
                    match format {
                        Format::Dot => g.to_dot(),
                        Format::Mermaid => g.to_mermaid(),
                    }
                );
                ExitCode::SUCCESS
            }
            None => ExitCode::FAILURE,
        },
        Command::Stages { r#type } => cmd_stages(r#type),
        Command::Simulate {
            scene,
            out,
            seed,
            csv,
        } => match crate::stages::scene::simulate_to_dir(&scene, &out, seed, csv) {
            Ok(files) => {
                let n = files.len();
                println!(
                        "wrote {n} file{} to {d}\nread them back with a `signal_file` stage: path = \"{d}/*.{}\", labels = \"{d}/labels.toml\" (it declares the layout and the sample rate)",
                        if n == 1 { "" } else { "s" },
                        if csv { "csv" } else { "npy" },
                        d = out.display()
                    );
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("{}: {e}", scene.display());
                ExitCode::FAILURE
            }
        },
        Command::Daq { command } => cmd_daq(command),
        Command::Schema => match serde_json::to_string_pretty(&registry::graph_schema()) {
            Ok(s) => {
                println!("{s}");
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("cannot encode the schema: {e}");
                ExitCode::FAILURE
            }
        },
    }
}

/// Loads every point of a graph's sweep (checking them), printing errors.
fn load_sweep_points(path: &std::path::Path, set: Vec<(String, toml::Value)>, base: &Graph) -> Option<usize> {
    let text = palpate_core::input::read_text(path).ok()?;
    let opts = LoadOptions {
        overrides: set,
        out: Some(base.out_dir.clone()),
        base_dir: Some(
            path.parent()
                .map(std::path::Path::to_path_buf)
                .unwrap_or_default(),
        ),
    };
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("graph");
    let sweep = base.sweep.as_ref()?;
    match core::sweep::load_points(&text, &base.file, stem, &opts, base, sweep) {
        Ok(points) => Some(points.len()),
        Err(e) => {
            eprintln!("{e}");
            None
        }
    }
}

/// Loads a graph, printing warnings and errors to stderr.
fn load(path: &std::path::Path, set: Vec<(String, toml::Value)>, out: Option<PathBuf>) -> Option<Graph> {
    let opts = LoadOptions {
        overrides: set,
        out,
        base_dir: None,
    };
    match core::load_file(path, &opts) {
        Ok(g) => {
            for w in &g.warnings {
                eprintln!("{w}");
            }
            Some(g)
        }
        Err(e) => {
            eprintln!("{e}");
            None
        }
    }
}

fn cmd_slurm(
    path: PathBuf,
    set: Vec<(String, toml::Value)>,
    out: Option<PathBuf>,
    o: crate::cluster::SlurmOptions,
) -> ExitCode {
    let Some(graph) = load(&path, set.clone(), out) else {
        return ExitCode::FAILURE;
    };
    if graph.sweep.is_none() {
        eprintln!(
            "{}: the graph has no [sweep] table: nothing to spread over a cluster",
            graph.file
        );
        return ExitCode::FAILURE;
    }
    if load_sweep_points(&path, set.clone(), &graph).is_none() {
        return ExitCode::FAILURE;
    }
    let job = crate::cluster::SweepJob {
        path: &path,
        source: None,
        graph: &graph,
        set: &set,
    };
    match crate::cluster::slurm_scripts(&job, &o) {
        Ok(files) => {
            for f in &files {
                println!("wrote {}", f.display());
            }
            if let Some(submit) = files.last() {
                println!("submit with:\n  sh {}", submit.display());
                println!(
                    "(or by hand: sbatch array.sbatch, then sbatch --dependency=afterok:<array job id> merge.sbatch)"
                );
            }
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("{}: {e}", graph.file);
            ExitCode::FAILURE
        }
    }
}

fn cmd_run(
    path: PathBuf,
    set: Vec<(String, toml::Value)>,
    out: Option<PathBuf>,
    threads: Option<usize>,
    selection: Selection,
    fresh: bool,
) -> ExitCode {
    let Some(graph) = load(&path, set.clone(), out) else {
        return ExitCode::FAILURE;
    };
    // Held to the end: the folder goes again if nothing was written into it.
    let _out = match prepare_out_dir(&graph.out_dir) {
        Ok(out) => out,
        Err(e) => {
            eprintln!("{}: {e}", graph.file);
            return ExitCode::FAILURE;
        }
    };
    let pool = match palpate_core::thread_pool(threads.unwrap_or(0), "--threads") {
        Ok(p) => p,
        Err(e) => {
            eprintln!("{e}");
            return ExitCode::FAILURE;
        }
    };
    let interactive = std::io::stdout().is_terminal() && std::io::stderr().is_terminal();
    let stages = graph.nodes.len();
    let bars = interactive.then(|| Bars::new(stages));
    // Off a terminal (a log, a batch job) bars would be noise: one plain line
    // per stage instead.
    let lines = (!interactive).then(|| Lines::new(stages));
    let opts = RunOptions {
        progress: match (&bars, &lines) {
            (Some(b), _) => Some(b as &dyn Progress),
            (None, Some(l)) => Some(l as &dyn Progress),
            (None, None) => None,
        },
        keep_outputs: false,
        cache: None,
    };
    if graph.sweep.is_some() {
        let job = crate::cluster::SweepJob {
            path: &path,
            source: None,
            graph: &graph,
            set: &set,
        };
        let code = pool.install(|| crate::cluster::run_sweep(&job, &selection, fresh, &opts));
        drop(bars);
        return code;
    }
    if selection != Selection::All || fresh {
        eprintln!(
            "{}: --points, --shard and --fresh apply to sweeps; this graph has no [sweep] table",
            graph.file
        );
        return ExitCode::FAILURE;
    }
    let t0 = std::time::Instant::now();
    let result = pool.install(|| core::run(&graph, &opts));
    drop(bars);
    let result = match result {
        Ok(r) => r,
        Err(e) => {
            eprintln!("{}: run failed: {e}", graph.file);
            return ExitCode::FAILURE;
        }
    };
    match single_run_text(&graph, &result, t0.elapsed()) {
        Ok(text) => {
            print!("{text}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("{e}");
            ExitCode::FAILURE
        }
    }
}

/// A run's reports and timing table as `palpate run` prints them, after
/// writing its report files (the error names the file that failed).
pub(crate) fn single_run_text(
    graph: &Graph,
    result: &core::RunResult,
    elapsed: std::time::Duration,
) -> Result<String, String> {
    let mut text = String::new();
    for (id, report) in &result.reports {
        text.push_str(&format!("== {id}\n"));
        // A report is text lines; one that forgot its last line end must not
        // run into the next report's header.
        text.push_str(&report.text);
        if !report.text.is_empty() && !report.text.ends_with('\n') {
            text.push('\n');
        }
    }
    let rows = crate::report::timing_rows(result);
    text.push_str(&format!(
        "== timing (wall time; {:.2} s in all)\n",
        elapsed.as_secs_f64()
    ));
    text.push_str(&crate::report::timing_table(&rows));
    crate::report::write_run_files(graph, result)?;
    text.push_str(&format!(
        "reports in {} (timing in timing.md, timing.csv)\n",
        graph.out_dir.display()
    ));
    Ok(text)
}

/// `run --live`: every trial of the graph's source streamed through the
/// stages' streaming forms (see `palpate_core::stream::replay`).
fn cmd_run_live(
    path: PathBuf,
    set: Vec<(String, toml::Value)>,
    out: Option<PathBuf>,
    block: usize,
) -> ExitCode {
    let Some(graph) = load(&path, set, out) else {
        return ExitCode::FAILURE;
    };
    run_live_graph(&graph, block)
}

/// Streams a loaded graph live (`run --live`, `daq run`), printing every
/// estimate as it changes and the sinks' reports at the end.
fn run_live_graph(graph: &Graph, block: usize) -> ExitCode {
    let path = std::path::Path::new(&graph.file);
    let plan = match core::stream::plan(graph) {
        Ok(p) => p,
        Err(problems) => {
            for p in &problems {
                eprintln!("{}: {p}", path.display());
            }
            eprintln!("{}: cannot run live", path.display());
            return ExitCode::FAILURE;
        }
    };
    // Held to the end: the folder goes again if nothing was written into it.
    let _out = match prepare_out_dir(&graph.out_dir) {
        Ok(out) => out,
        Err(e) => {
            eprintln!("{}: {e}", graph.file);
            return ExitCode::FAILURE;
        }
    };
    // Ctrl-C ends the session after the block under way (or, with nothing
    // in contact, the frame or wait under way), with the reports of the
    // trials finished (a board streams until stopped); a second one quits
    // at once. (A handler can be set once per process: one live run here.)
    static INTERRUPTS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let _ = ctrlc::set_handler(|| {
        if INTERRUPTS.fetch_add(1, std::sync::atomic::Ordering::SeqCst) > 0 {
            std::process::exit(130);
        }
        eprintln!("stopping; the trial under way is dropped (Ctrl-C again to quit now)");
    });
    eprintln!(
        "{}: streaming live; Ctrl-C stops (the trial under way is dropped, the reports are written)",
        graph.file
    );
    let t0 = std::time::Instant::now();
    let interrupted = || INTERRUPTS.load(std::sync::atomic::Ordering::SeqCst) > 0;
    let on_update = |u: &core::stream::LiveUpdate| {
        if interrupted() {
            return std::ops::ControlFlow::Break(());
        }
        let what = if u.last { "final" } else { "now" };
        match u.estimate.angle_deg {
            Some(a) => println!(
                "{:<22} {:>8.2} s  {}: {what} {a:.1} deg",
                u.trial_id,
                u.t_ms / 1e3,
                u.stage
            ),
            None => println!(
                "{:<22} {:>8.2} s  {}: {what} no edge",
                u.trial_id,
                u.t_ms / 1e3,
                u.stage
            ),
        }
        std::ops::ControlFlow::Continue(())
    };
    let result = core::stream::replay_polled(graph, &plan, block, on_update, interrupted);
    match result {
        Ok(run) => {
            for (id, report) in &run.reports {
                println!("== {id}");
                crate::report::print_lines(&report.text);
            }
            let live = crate::report::LiveRecord::new(graph, &run, t0.elapsed());
            println!("{}", live.summary());
            if live.blocks > 0 {
                print!("{}", live.stage_table());
            }
            match crate::report::write_live_run_files(graph, &run, &live) {
                Ok(files) => {
                    let names: Vec<String> = files.iter().map(|p| p.display().to_string()).collect();
                    println!("run record and per-stage timing in {}", names.join(", "));
                    if run.stopped {
                        println!("stopped by Ctrl-C after {} finished trials", run.trials);
                        // The shell's code for an interrupted command.
                        return ExitCode::from(130);
                    }
                    ExitCode::SUCCESS
                }
                Err(e) => {
                    eprintln!("{e}");
                    ExitCode::FAILURE
                }
            }
        }
        Err(e) => {
            eprintln!("{}: live run failed: {e}", graph.file);
            ExitCode::FAILURE
        }
    }
}

fn cmd_stages(type_name: Option<String>) -> ExitCode {
    match type_name {
        None => {
            for reg in registry::registrations() {
                let doc = registry::stage_doc(reg);
                println!("{:<18} {}", doc.type_name, doc.summary());
            }
            ExitCode::SUCCESS
        }
        Some(t) => {
            let Some(reg) = registry::find(&t) else {
                let close = registry::close_matches(&t);
                eprintln!(
                    "unknown stage type `{t}`{}",
                    if close.is_empty() {
                        String::new()
                    } else {
                        format!("; did you mean {}?", close.join(" or "))
                    }
                );
                return ExitCode::FAILURE;
            };
            let doc = registry::stage_doc(reg);
            println!("{}\n", doc.type_name);
            println!("{}\n", doc.doc);
            if let Some(page) = crate::guide::stage_page(&doc.type_name) {
                println!("The maths, file formats and examples: the user guide, {page}\n");
            }
            if doc.keys.is_empty() {
                println!("(no keys)");
            }
            for k in &doc.keys {
                println!(
                    "  {} ({}){}",
                    k.name,
                    k.type_desc,
                    k.default
                        .as_ref()
                        .map_or(" [required]".to_string(), |d| format!(" = {d}"))
                );
                for line in k.doc.lines() {
                    println!("      {line}");
                }
            }
            ExitCode::SUCCESS
        }
    }
}

/// The layout a label file beside `rec` declares (`labels.toml`, else
/// `trials.json`), as a `layout` key; `None` when neither exists or declares one.
fn sibling_layout(rec: &std::path::Path) -> Result<Option<crate::stages::io::LayoutConfig>, String> {
    use crate::stages::io::LayoutConfig;
    let dir = rec.parent().unwrap_or_else(|| std::path::Path::new("."));
    for name in ["labels.toml", "trials.json"] {
        let p = dir.join(name);
        if !p.is_file() {
            continue;
        }
        if let Some(l) = crate::stages::io::common::read_sidecar_layout(&p)? {
            eprintln!("layout from {}", p.display());
            return Ok(Some(LayoutConfig::from(&l)));
        }
    }
    Ok(None)
}

fn cmd_daq(command: DaqCommand) -> ExitCode {
    use crate::stages::io::{daq, signal_file};
    match command {
        DaqCommand::Emulate {
            scene,
            angle,
            seed,
            recording,
            allow_cut_end,
            sample_rate_hz,
            speed,
            delay,
        } => {
            if recording.is_none() && sample_rate_hz.is_some() {
                eprintln!(
                    "--sample-rate-hz is the rate of a --recording; a scene's rate is its \
                     motion.sample_rate_hz (edit the scene file)"
                );
                return ExitCode::from(2);
            }
            let signals = match (scene, recording) {
                (Some(scene), None) => match daq::simulate_trial(&scene, angle, seed) {
                    Ok(s) => s,
                    Err(e) => {
                        eprintln!("{}: {e}", scene.display());
                        return ExitCode::FAILURE;
                    }
                },
                (None, Some(rec)) => {
                    // The array: the one a label file beside the recording
                    // declares (`palpate simulate` and the `write_*` sinks
                    // write one), else the reader's default 4 x 4.
                    let layout = match sibling_layout(&rec) {
                        Ok(l) => l,
                        Err(e) => {
                            eprintln!("{e}");
                            return ExitCode::FAILURE;
                        }
                    };
                    let cfg = signal_file::SignalFileConfig {
                        path: Some(rec.display().to_string()),
                        sample_rate_hz,
                        layout,
                        allow_cut_end,
                        ..Default::default()
                    };
                    match signal_file::read_signal_files(&cfg, std::path::Path::new(".")) {
                        Ok(trials) if !trials.is_empty() => (*trials[0].1).clone(),
                        Ok(_) => {
                            eprintln!("{}: no trial in the recording", rec.display());
                            return ExitCode::FAILURE;
                        }
                        Err(e) => {
                            // The reader's hint names its graph key; here
                            // the flag sets it.
                            let e = e.to_string().replace(
                                crate::stages::io::daq::CUT_END_HINT,
                                "Pass --allow-cut-end to drop that frame",
                            );
                            let shown = rec.display().to_string();
                            if e.contains(&shown) {
                                eprintln!("{e}");
                            } else {
                                eprintln!("{shown}: {e}");
                            }
                            return ExitCode::FAILURE;
                        }
                    }
                }
                _ => {
                    eprintln!("give --scene FILE (with --angle, --seed) or --recording FILE");
                    return ExitCode::FAILURE;
                }
            };
            let opts = daq::EmulateOptions {
                speed,
                ..Default::default()
            };
            let result = daq::emulate_pty(&signals, &opts, |path| {
                println!(
                    "emulating a DAQ on {path} ({} taxels, {:.1} s at {speed}x), starting in {delay} s",
                    signals.data.len(),
                    signals.duration_ms() / 1e3
                );
                std::thread::sleep(std::time::Duration::from_secs_f64(delay.max(0.0)));
            });
            match result {
                Ok(report) => {
                    println!("{}", describe_playback(&report));
                    ExitCode::SUCCESS
                }
                Err(e) => {
                    eprintln!("emulator: {e}");
                    ExitCode::FAILURE
                }
            }
        }
        DaqCommand::Run {
            port,
            emulate_scene,
            angle,
            seed,
            speed,
            config,
            baud,
            record,
            seconds,
        } => {
            let (text, file) = match &config {
                Some(path) => match palpate_core::input::read_text(path) {
                    Ok(t) => (t, path.display().to_string()),
                    Err(e) => {
                        eprintln!("cannot read {}: {e}", path.display());
                        return ExitCode::FAILURE;
                    }
                },
                None => (
                    DEFAULT_LIVE_CONFIG.to_string(),
                    "graphs/live.toml (built in)".to_string(),
                ),
            };
            let id = match daq_stage_id(&text) {
                Ok(id) => id,
                Err(e) => {
                    eprintln!("{file}: {e}");
                    return ExitCode::FAILURE;
                }
            };
            let key = |k: &str| format!("stages.{id}.{k}");
            let abs = |p: &std::path::Path| {
                std::path::absolute(p)
                    .unwrap_or_else(|_| p.to_path_buf())
                    .display()
                    .to_string()
            };
            let mut set: Vec<(String, toml::Value)> = Vec::new();
            match (port, emulate_scene) {
                (_, Some(scene)) => {
                    set.push((key("scene"), abs(&scene).into()));
                    set.push((key("angles"), toml::Value::Array(vec![angle.into()])));
                    set.push((key("trials_per_angle"), 1.into()));
                    set.push((key("speed"), speed.into()));
                    // Drawn as `daq emulate` and `simulate` draw (a scene
                    // stage `scene`), not as the graph's daq stage id.
                    set.push((key("scene_stage_id"), "scene".into()));
                    set.push(("run.seed".into(), core::graph::seed_value(seed)));
                }
                (Some(p), None) => {
                    set.push((key("port"), p.into()));
                    set.push((key("baud"), i64::from(baud).into()));
                }
                (None, None) => {
                    eprintln!("give a serial device or --emulate-scene FILE");
                    return ExitCode::FAILURE;
                }
            }
            if let Some(r) = record {
                set.push((key("record"), abs(&r).into()));
            }
            if let Some(sec) = seconds {
                set.push((key("seconds"), sec.into()));
            }
            let opts = LoadOptions {
                overrides: set,
                out: None,
                base_dir: config
                    .as_ref()
                    .map(|p| p.parent().map(std::path::Path::to_path_buf).unwrap_or_default()),
            };
            let stem = config
                .as_ref()
                .and_then(|p| p.file_stem())
                .and_then(|s| s.to_str())
                .unwrap_or("live")
                .to_string();
            match core::load_str(&text, &file, &stem, &opts) {
                Ok(g) => {
                    for w in &g.warnings {
                        eprintln!("{w}");
                    }
                    run_live_graph(&g, 1)
                }
                Err(e) => {
                    eprintln!("{e}");
                    ExitCode::FAILURE
                }
            }
        }
    }
}

/// The id of a graph's one `daq` source (what `palpate daq run` points at the port).
fn daq_stage_id(text: &str) -> Result<String, String> {
    let doc: toml::Table = toml::from_str(text).map_err(|e| e.message().trim().to_string())?;
    let ids: Vec<&String> = doc
        .get("stages")
        .and_then(|s| s.as_table())
        .map(|stages| {
            stages
                .iter()
                .filter(|(_, v)| v.get("type").and_then(|t| t.as_str()) == Some("daq"))
                .map(|(id, _)| id)
                .collect()
        })
        .unwrap_or_default();
    match ids.as_slice() {
        [id] => Ok((*id).clone()),
        [] => Err("no stage of type \"daq\": `palpate daq run` needs a live graph with a DAQ source".into()),
        _ => Err(format!(
            "{} stages of type \"daq\"; a live graph has one source",
            ids.len()
        )),
    }
}

/// graphs/live.toml, built in: the default `--config` of `palpate daq run`,
/// so that it does not depend on the folder palpate runs in (its emulated
/// scene is replaced by the port or `--emulate-scene`).
const DEFAULT_LIVE_CONFIG: &str = include_str!("../graphs/live.toml");

/// "1 frame", "2 frames".
fn plural(n: u64, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

/// One line on a finished playback, for people (not a struct dump).
fn describe_playback(r: &crate::stages::io::daq::EmulateReport) -> String {
    let mut s = format!(
        "played {} ({}) in {:.1} s",
        plural(r.frames, "frame", "frames"),
        plural(r.bytes, "byte", "bytes"),
        r.elapsed.as_secs_f64()
    );
    if r.clamped > 0 {
        s.push_str(&format!(
            "; {} clamped to the u16 range",
            plural(r.clamped, "sample", "samples")
        ));
    }
    s
}

/// Progress bars, drawn to stderr: an overall bar counting finished stages
/// (across every point of a sweep), and one bar for the running stage.
struct Bars {
    multi: MultiProgress,
    overall: ProgressBar,
    current: Mutex<Option<ProgressBar>>,
}

impl Bars {
    fn new(stages: usize) -> Self {
        let multi = MultiProgress::new();
        let overall = multi.add(ProgressBar::new(stages as u64));
        if let Ok(style) =
            ProgressStyle::with_template("{prefix:>14} [{bar:30}] {pos}/{len} stages {elapsed_precise}")
        {
            overall.set_style(style.progress_chars("=> "));
        }
        overall.set_prefix("all");
        Bars {
            multi,
            overall,
            current: Mutex::new(None),
        }
    }
}

/// Progress as plain lines on stderr, for logs: one line when a stage starts
/// and one when it ends, with its place among the run's stages and its time.
struct Lines {
    stages: usize,
    done: std::sync::atomic::AtomicUsize,
    started: Mutex<Option<std::time::Instant>>,
}

impl Lines {
    fn new(stages: usize) -> Self {
        Lines {
            stages,
            done: std::sync::atomic::AtomicUsize::new(0),
            started: Mutex::new(None),
        }
    }
}

impl Progress for Lines {
    fn start(&self, stage: &str, total: usize) {
        let k = self.done.load(std::sync::atomic::Ordering::Relaxed) + 1;
        eprintln!("[{k}/{}] {stage}: {total} to do", self.stages.max(k));
        if let Ok(mut t) = self.started.lock() {
            *t = Some(std::time::Instant::now());
        }
    }
    fn tick(&self) {}
    fn finish(&self, stage: &str) {
        let k = self.done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        let secs = self
            .started
            .lock()
            .ok()
            .and_then(|t| t.map(|t| t.elapsed().as_secs_f64()))
            .unwrap_or(0.0);
        eprintln!("[{k}/{}] {stage}: done in {secs:.1} s", self.stages.max(k));
    }
}

impl Progress for Bars {
    fn start(&self, stage: &str, total: usize) {
        let bar = self.multi.add(ProgressBar::new(total as u64));
        if let Ok(style) =
            ProgressStyle::with_template("{prefix:>14} [{bar:30}] {pos}/{len} {elapsed_precise} eta {eta}")
        {
            bar.set_style(style.progress_chars("=> "));
        }
        bar.set_prefix(stage.to_string());
        if let Ok(mut c) = self.current.lock() {
            *c = Some(bar);
        }
    }
    fn tick(&self) {
        if let Ok(c) = self.current.lock() {
            if let Some(b) = c.as_ref() {
                b.inc(1);
            }
        }
    }
    fn finish(&self, _stage: &str) {
        if let Ok(mut c) = self.current.lock() {
            if let Some(b) = c.take() {
                b.finish_and_clear();
            }
        }
        // A sweep runs the stages once per point: the overall bar grows.
        if self.overall.position() >= self.overall.length().unwrap_or(0) {
            self.overall.inc_length(1);
        }
        self.overall.inc(1);
    }
}
