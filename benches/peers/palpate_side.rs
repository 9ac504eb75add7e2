//! palpate's side of the peer comparison (`benches/peers/`): exports
//! identical inputs for Brian2 and scikit-learn, and runs and times palpate's own
//! kernels on exactly those inputs. `benches/peers/run.py` reads the export, runs
//! the peers and compares (see `benches/peers/README.md`).
//!
//! ```text
//! cargo run --release --example peers -- --out <dir> [--seed N] [--repeats N]
//! ```
//!
//! 1. Encoder. The drive currents come from the real pipeline of
//!    `graphs/quickstart.toml` (lab scene -> low-pass -> normalize -> FA-I drive)
//!    for the scene's two trials at 10° (its slowest crossing, ~42 s each at 1 kHz),
//!    concatenated taxel by taxel and cut to exactly 40 s (40 000 samples), so the
//!    workload is the issue's "16 taxels x 40 s" at the stage's default step
//!    dt = 0.5 ms (80 000 steps per neuron). Written as `encoder/currents.npy`
//!    (`[taxel][sample]`) with every parameter in `encoder/encoder.json`. Then the
//!    `izhikevich` stage's kernel ([`Izhikevich::encode`], not the graph runtime)
//!    encodes that input with the stage's defaults in both schemes (`izhikevich`
//!    half-steps, the default, and `euler`), `--repeats` times each; the JSON gets
//!    every run's wall and thread-CPU time and the per-taxel spike counts, and
//!    `encoder/spikes_<scheme>.npy` the spikes as `(taxel, t_ms)` rows. As a check
//!    that this is the kernel the graph runs, trial 1's spikes from the kernel
//!    must equal the graph's `enc` output for that trial.
//! 2. Baselines. The quickstart front end on the whole lab data set (17 angles x
//!    10 trials, seed `--seed`), binned into 100 ms / 10 ms images; fold 0 of
//!    leave-one-trial-out (train on repetitions 1-9, test on repetition 0 of every
//!    class, as the runtime's fold 0). For `ann_s` (ANN (S)), `ann_st` (ANN (ST)),
//!    `edbn`, `svm`, `random_forest`, `knn` and `logistic` with the stage defaults (stage ids and fold seed as in
//!    `graphs/paper/table2.toml`), the training vectors exactly as the stages
//!    build them ([`TrainSet::build`]) and every active test vector
//!    ([`FeatureSpec::trial_vectors`]) are written as NPY; palpate trains on them
//!    (each config's `fit_set`) and predicts every test vector in one batch
//!    call (`Classifier::scores_batch`) plus the trials' winner-take-all vote, timed; the JSON gets times,
//!    frame accuracy and the test trials' MAE. The ANN's early-stopping split
//!    (whole trials, drawn from the fold's generator) is exported too, so the peer
//!    can stop on the same validation trials.
//!
//! Timing: each figure is a sample of wall time and of the process's on-CPU
//! time (every thread's `/proc/self/task/*/schedstat`: fits run on the
//! rayon pool's one worker), per call, averaged over a
//! batch of calls of at least 50 ms; `--repeats` samples, their minimum ("best")
//! and median. The machine is shared, so the best sample is the one least
//! disturbed by other processes; run.py compares best with best.

use palpate_core::{derive_seed, FitContext, Item, LoadOptions, RunOptions, SpikeEvent};
use palpate_stages::encode::izhikevich::{Izhikevich, IzhikevichConfig, Scheme};
use palpate_stages::estimate::ann::{AnnConfig, AnnInput};
use palpate_stages::estimate::classic::{KnnConfig, LogisticConfig, RandomForestConfig, SvmConfig};
use palpate_stages::estimate::edbn::EdbnConfig;
use palpate_stages::estimate::features::{argmax, Accumulator, FittedModel, TrainSet};
use palpate_stages::io::arrays::npy_bytes;
use serde_json::{json, Value};
use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

type Res<T> = Result<T, String>;

/// Encoder workload length, s.
const SECONDS: f64 = 40.0;
/// The angle whose trials feed the encoder (the slowest crossing).
const ENCODER_ANGLE: f64 = 10.0;

struct Args {
    out: PathBuf,
    seed: u64,
    repeats: usize,
    /// `--only a,b`: run just these workloads (`encoder` or a baseline id);
    /// empty = all. For profiling one estimator; run.py needs a full export.
    only: Vec<String>,
    /// `--profile N[:M]`: after building each wanted baseline's sets, fit
    /// it N times and predict the test set M times (default N), untimed,
    /// and skip the rest (no export, no timing): a profiler then sees only
    /// the estimator (`--profile 1:500`: mostly its prediction).
    profile: Option<(usize, usize)>,
}

impl Args {
    fn wants(&self, id: &str) -> bool {
        self.only.is_empty() || self.only.iter().any(|o| o == id)
    }
}

fn parse_args() -> Res<Args> {
    let mut out = None;
    let mut seed = 1;
    let mut repeats = 15;
    let mut only = Vec::new();
    let mut profile = None;
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        let mut val = |name: &str| it.next().ok_or(format!("{name} needs a value"));
        match a.as_str() {
            "--out" => out = Some(PathBuf::from(val("--out")?)),
            "--seed" => seed = val("--seed")?.parse().map_err(|e| format!("--seed: {e}"))?,
            "--repeats" => repeats = val("--repeats")?.parse().map_err(|e| format!("--repeats: {e}"))?,
            "--only" => only = val("--only")?.split(',').map(str::to_string).collect(),
            "--profile" => {
                let v = val("--profile")?;
                let (f, p) = v.split_once(':').unwrap_or((&v, &v));
                let num = |s: &str| s.parse::<usize>().map_err(|e| format!("--profile {v}: {e}"));
                profile = Some((num(f)?.max(1), num(p)?));
            }
            "-h" | "--help" => {
                println!("cargo run --release --example peers -- --out <dir> [--seed N] [--repeats N] [--only encoder,ann_s,...] [--profile N[:M]]");
                std::process::exit(0);
            }
            other => return Err(format!("unknown argument `{other}` (try --help)")),
        }
    }
    Ok(Args {
        out: out.ok_or("--out <dir> is required")?,
        seed,
        repeats: repeats.max(1),
        only,
        profile,
    })
}

/// The process's on-CPU time so far, summed over its live threads (Linux:
/// the first field of each `/proc/self/task/<tid>/schedstat`, in ns), else
/// `None`. Every thread, not this one: the forest's trees and the SVM's
/// machines are fitted on the rayon pool's worker (one, under run.sh's
/// `RAYON_NUM_THREADS=1`) while this thread waits, so this thread's clock
/// saw ~1-2 ms of a ~10 ms fit. The pool's threads live as long as the
/// process, so no time is lost to an exited thread between two readings.
fn cpu_time() -> Option<Duration> {
    let mut ns = 0u64;
    for task in std::fs::read_dir("/proc/self/task").ok()? {
        let mut path = task.ok()?.path();
        path.push("schedstat");
        // A thread may exit between the listing and the read: skip it.
        let Ok(s) = std::fs::read_to_string(&path) else {
            continue;
        };
        ns = ns.saturating_add(s.split_whitespace().next()?.parse().ok()?);
    }
    Some(Duration::from_nanos(ns))
}

/// Times `f`: `repeats` samples, each the average of a batch of calls long
/// enough (>= 50 ms, found from one untimed warm-up call) that the threads'
/// CPU clocks, which this kernel advances in ticks of a few ms, resolve it.
/// Returns the last result and the per-call times as JSON (`wall_s`, `cpu_s`:
/// every sample, median and minimum; `cpu_s` is null where the kernel does not
/// report threads' times).
fn timed<T>(repeats: usize, mut f: impl FnMut() -> T) -> (T, Value) {
    timed_owned(repeats, || (), |()| f(), usize::MAX)
}

/// [`timed`] for a call that consumes its input: `make` builds each call's
/// input before the clock starts (a batch's inputs at once, at most
/// `max_batch` calls a batch), so the timing is of `f` alone.
fn timed_owned<I, T>(
    repeats: usize,
    mut make: impl FnMut() -> I,
    mut f: impl FnMut(I) -> T,
    max_batch: usize,
) -> (T, Value) {
    let input = make();
    let w0 = Instant::now();
    let mut last = black_box(f(input));
    let once = w0.elapsed().as_secs_f64().max(1e-6);
    let batch = ((0.05 / once).ceil() as usize).clamp(1, max_batch.clamp(1, 10_000));
    let mut wall = Vec::new();
    let mut cpu = Vec::new();
    for _ in 0..repeats {
        let inputs: Vec<I> = (0..batch).map(|_| make()).collect();
        let c0 = cpu_time();
        let w0 = Instant::now();
        for input in inputs {
            last = black_box(f(input));
        }
        wall.push(w0.elapsed().as_secs_f64() / batch as f64);
        if let (Some(a), Some(b)) = (c0, cpu_time()) {
            cpu.push((b - a).as_secs_f64() / batch as f64);
        }
    }
    let stats = |xs: &[f64]| -> Value {
        if xs.is_empty() {
            return Value::Null;
        }
        let mut s = xs.to_vec();
        s.sort_by(f64::total_cmp);
        json!({ "median": s[s.len() / 2], "min": s[0], "all": xs })
    };
    let t = json!({ "repeats": repeats, "calls_per_repeat": batch, "wall_s": stats(&wall), "cpu_s": stats(&cpu) });
    (last, t)
}

fn write(path: &Path, bytes: &[u8]) -> Res<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| format!("creating {}: {e}", dir.display()))?;
    }
    std::fs::write(path, bytes).map_err(|e| format!("writing {}: {e}", path.display()))
}

fn write_npy(path: &Path, shape: &[usize], data: &[f64]) -> Res<()> {
    let bytes = npy_bytes(shape, data).map_err(|e| format!("encoding {}: {e}", path.display()))?;
    write(path, &bytes)
}

fn write_json(path: &Path, v: &Value) -> Res<()> {
    let text = serde_json::to_string_pretty(v).map_err(|e| e.to_string())?;
    write(path, text.as_bytes())
}

/// Runs `graphs/quickstart.toml` with `overrides`, keeping every stage's output.
fn run_quickstart(
    seed: u64,
    overrides: Vec<(&str, toml::Value)>,
    out: &Path,
) -> Res<palpate_core::RunResult> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("graphs/quickstart.toml");
    let mut opts = LoadOptions {
        out: Some(out.to_path_buf()),
        ..LoadOptions::default()
    };
    opts.overrides
        .push(("run.seed".into(), toml::Value::Integer(seed as i64)));
    opts.overrides
        .extend(overrides.into_iter().map(|(k, v)| (k.to_string(), v)));
    let g = palpate_core::load_file(&path, &opts).map_err(|e| e.to_string())?;
    palpate_core::run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..RunOptions::default()
        },
    )
    .map_err(|e| format!("running {}: stage {}: {}", path.display(), e.stage, e.message))
}

fn scheme_name(s: Scheme) -> &'static str {
    match s {
        Scheme::Izhikevich => "izhikevich",
        Scheme::Euler => "euler",
    }
}

fn encoder(args: &Args) -> Res<Value> {
    let dir = args.out.join("encoder");
    let angle = toml::Value::Array(vec![toml::Value::Float(ENCODER_ANGLE)]);
    let r = run_quickstart(
        args.seed,
        vec![
            ("stages.scene.angles", angle),
            ("stages.scene.trials_per_angle", toml::Value::Integer(2)),
        ],
        &dir.join("graph-out"),
    )?;
    let drive = &r.outputs["drive"];
    let first = drive[0].payload.signals().map_err(|e| e.message)?;
    let fs = first.sample_rate_hz;
    let n_taxels = first.data.len();
    let n = (SECONDS * fs).round() as usize;
    // Concatenate the trials' drives taxel by taxel, then cut to exactly 40 s.
    let mut currents = vec![Vec::with_capacity(n); n_taxels];
    let mut used = Vec::new();
    for item in drive.iter() {
        let s = item.payload.signals().map_err(|e| e.message)?;
        if s.sample_rate_hz != fs || s.data.len() != n_taxels {
            return Err("the trials' drives differ in rate or taxels".into());
        }
        let have = currents[0].len();
        if have >= n {
            break;
        }
        let take = (n - have).min(s.n_samples());
        for (c, x) in currents.iter_mut().zip(&s.data) {
            c.extend_from_slice(&x[..take]);
        }
        used.push(json!({ "trial_id": item.meta.trial_id, "samples": take, "trial_samples": s.n_samples() }));
    }
    if currents[0].len() != n {
        return Err(format!(
            "the drives give {} samples, fewer than {SECONDS} s",
            currents[0].len()
        ));
    }
    let flat: Vec<f64> = currents.iter().flatten().copied().collect();
    write_npy(&dir.join("currents.npy"), &[n_taxels, n], &flat)?;

    // The stage's defaults, as the quickstart configures it (preset fa_i).
    let cfg = IzhikevichConfig::default();
    let params = cfg.params().map_err(|e| e.to_string())?;
    let (v0, u0) = params.rest();

    // Check: the kernel on trial 1's own drive gives the graph's `enc` spikes.
    let kernel = Izhikevich {
        params,
        dt_ms: cfg.dt_ms,
        scheme: cfg.scheme,
        input: cfg.input,
    };
    let graph_spikes = r.outputs["enc"][0].payload.spikes().map_err(|e| e.message)?;
    if kernel.encode(&first.data, fs) != graph_spikes.events {
        return Err("the kernel's spikes differ from the graph's `enc` output on trial 1".into());
    }

    let mut runs = serde_json::Map::new();
    for scheme in [Scheme::Izhikevich, Scheme::Euler] {
        let enc = Izhikevich {
            scheme,
            ..kernel.clone()
        };
        let (events, times): (Vec<SpikeEvent>, Value) =
            timed(args.repeats, || enc.encode(black_box(&currents), fs));
        let mut counts = vec![0u64; n_taxels];
        events.iter().for_each(|e| counts[e.taxel as usize] += 1);
        let rows: Vec<f64> = events.iter().flat_map(|e| [e.taxel as f64, e.t_ms]).collect();
        let name = scheme_name(scheme);
        write_npy(&dir.join(format!("spikes_{name}.npy")), &[events.len(), 2], &rows)?;
        let wall = |k: &str| times["wall_s"][k].as_f64().unwrap_or(f64::NAN) * 1e3;
        println!(
            "encoder {name:>10}: {} spikes, {:.2} ms best, {:.2} ms median wall over {} samples",
            events.len(),
            wall("min"),
            wall("median"),
            args.repeats
        );
        runs.insert(
            name.into(),
            json!({ "spikes": events.len(), "counts": counts, "time": times }),
        );
    }
    let meta = json!({
        "workload": format!("{n_taxels} taxels x {SECONDS} s"),
        "source": {
            "graph": "graphs/quickstart.toml",
            "stages": "scene (lab) -> lowpass -> normalize -> drive fa_i",
            "angle_deg": ENCODER_ANGLE,
            "seed": args.seed,
            "trials": used,
        },
        "sample_rate_hz": fs,
        "n_samples": n,
        "n_taxels": n_taxels,
        "duration_ms": n as f64 * 1000.0 / fs,
        "currents_file": "currents.npy",
        "currents_layout": "[taxel][sample], f64",
        "params": { "a": params.a, "b": params.b, "c": params.c, "d": params.d, "v_peak": params.v_peak },
        "dt_ms": cfg.dt_ms,
        "input": "hold",
        "v0": v0,
        "u0": u0,
        "default_scheme": scheme_name(cfg.scheme),
        "neuron_steps": n_taxels as f64 * (n as f64 * 1000.0 / fs / cfg.dt_ms).ceil(),
        "palpate": runs,
    });
    write_json(&dir.join("encoder.json"), &meta)?;
    Ok(meta)
}

/// A baseline to export: stage id, its config, and how to fit it.
enum Baseline {
    Ann(AnnConfig),
    Edbn(EdbnConfig),
    Svm(SvmConfig),
    Forest(RandomForestConfig),
    Knn(KnnConfig),
    Logistic(LogisticConfig),
}

impl Baseline {
    fn kind(&self) -> &'static str {
        match self {
            Baseline::Ann(_) => "ann",
            Baseline::Edbn(_) => "edbn",
            Baseline::Svm(_) => "svm",
            Baseline::Forest(_) => "random_forest",
            Baseline::Knn(_) => "knn",
            Baseline::Logistic(_) => "logistic",
        }
    }
    fn keys(&self) -> palpate_stages::estimate::features::FeatureKeys {
        match self {
            Baseline::Ann(c) => c.feature_keys(),
            Baseline::Edbn(c) => c.keys(),
            Baseline::Svm(c) => c.feature_keys(),
            Baseline::Forest(c) => c.feature_keys(),
            Baseline::Knn(c) => c.feature_keys(),
            Baseline::Logistic(c) => c.feature_keys(),
        }
    }
    fn config_json(&self) -> Value {
        match self {
            Baseline::Ann(c) => serde_json::to_value(c).unwrap_or(Value::Null),
            Baseline::Edbn(c) => serde_json::to_value(c).unwrap_or(Value::Null),
            Baseline::Svm(c) => serde_json::to_value(c).unwrap_or(Value::Null),
            Baseline::Forest(c) => serde_json::to_value(c).unwrap_or(Value::Null),
            Baseline::Knn(c) => serde_json::to_value(c).unwrap_or(Value::Null),
            Baseline::Logistic(c) => serde_json::to_value(c).unwrap_or(Value::Null),
        }
    }
    /// Fits on `set` with the fold's generator, as the stage's `fit_model` does
    /// after building the set.
    fn fit(&self, set: TrainSet, ctx: &FitContext<'_>) -> Res<FittedModel> {
        let rng = &mut ctx.rng();
        match self {
            Baseline::Ann(c) => {
                c.check().map_err(|e| e.to_string())?;
                Ok(c.fit_set(set, rng))
            }
            Baseline::Edbn(c) => {
                c.check().map_err(|e| e.to_string())?;
                c.fit_set(set, rng).map_err(|e| e.message)
            }
            Baseline::Svm(c) => c.fit_set(set, rng).map_err(|e| e.message),
            Baseline::Forest(c) => c.fit_set(set, rng).map_err(|e| e.message),
            Baseline::Knn(c) => c.fit_set(set, rng).map_err(|e| e.message),
            Baseline::Logistic(c) => c.fit_set(set, rng).map_err(|e| e.message),
        }
    }
}

/// Test vectors of one fold: rows, class per row, test-trial number per row.
struct TestSet {
    dim: usize,
    x: Vec<f64>,
    y: Vec<usize>,
    trial: Vec<usize>,
    /// Each row's frame (its window's index in the trial), as the stage votes it.
    frame: Vec<usize>,
    trial_angle: Vec<f64>,
}

/// Per-frame class scores of every test row (one batch call, as the stage
/// scores a trial), and each trial's winner-take-all answer (degrees; `None`
/// = no edge).
fn predict(model: &FittedModel, t: &TestSet) -> (Vec<f64>, Vec<Option<f64>>) {
    let k = model.classes.len();
    // Only spiking EDBN inference draws on it; the defaults (rate) do not.
    let mut rng = FitContext {
        stage_id: "peers",
        fold: 0,
        seed: 0,
    }
    .rng();
    let mut scores = vec![0.0; t.y.len() * k];
    model
        .classifier
        .scores_batch(&t.x, t.dim, k, &mut rng, &mut scores);
    let mut accs: Vec<Accumulator> = (0..t.trial_angle.len()).map(|_| Accumulator::new(k)).collect();
    // Each trial's frames are one run of the test set: voted a run at a time.
    let mut start = 0;
    while start < t.trial.len() {
        let tr = t.trial[start];
        let end = start + t.trial[start..].iter().take_while(|&&x| x == tr).count();
        accs[tr].add_rows(&t.frame[start..end], &scores[start * k..end * k], model.vote);
        start = end;
    }
    let answers = accs
        .iter()
        .map(|a| a.estimate(&model.classes, &model.features).angle_deg)
        .collect();
    (scores, answers)
}

fn baselines(args: &Args) -> Res<Value> {
    let dir = args.out.join("baselines");
    let r = run_quickstart(args.seed, vec![], &dir.join("graph-out"))?;
    let items = &r.outputs["bins"];
    let train: Vec<&Item> = items.iter().filter(|it| it.meta.group != 0).collect();
    let test: Vec<&Item> = items.iter().filter(|it| it.meta.group == 0).collect();
    println!(
        "baselines: {} trials binned; fold 0 trains on {}, tests on {}",
        items.len(),
        train.len(),
        test.len()
    );
    let models = [
        (
            "ann_s",
            Baseline::Ann(AnnConfig {
                input: AnnInput::Spatial,
                ..AnnConfig::default()
            }),
        ),
        ("ann_st", Baseline::Ann(AnnConfig::default())),
        ("edbn", Baseline::Edbn(EdbnConfig::default())),
        ("svm", Baseline::Svm(SvmConfig::default())),
        ("random_forest", Baseline::Forest(RandomForestConfig::default())),
        ("knn", Baseline::Knn(KnnConfig::default())),
        ("logistic", Baseline::Logistic(LogisticConfig::default())),
    ];
    let mut out = serde_json::Map::new();
    for (id, b) in models.iter().filter(|(id, _)| args.wants(id)) {
        let set = TrainSet::build(&train, &b.keys()).map_err(|e| e.message)?;
        // The runtime's fold 0 of a stage with this id (as in table2.toml).
        let fold_seed = derive_seed(args.seed, &[id, "fold0"]);
        let fctx = FitContext {
            stage_id: id,
            fold: 0,
            seed: fold_seed,
        };
        // The ANN's early-stopping split: the first draw of the fold's generator.
        let is_val: Vec<f64> = match b {
            Baseline::Ann(c) => {
                let (_, val) = set.split_by_trial(c.val_fraction, &mut fctx.rng());
                let mut m = vec![0.0; set.len()];
                val.iter().for_each(|&i| m[i] = 1.0);
                m
            }
            _ => vec![0.0; set.len()],
        };
        let mut t = TestSet {
            dim: set.dim,
            x: Vec::new(),
            y: Vec::new(),
            trial: Vec::new(),
            frame: Vec::new(),
            trial_angle: Vec::new(),
        };
        for (k, it) in test.iter().enumerate() {
            let images = it.payload.images().map_err(|e| e.message)?;
            let angle = it.meta.label.angle_deg.ok_or("a test trial has no angle")?;
            let c = set
                .classes
                .iter()
                .position(|a| (a - angle).abs() < 1e-9)
                .ok_or("a test class is missing from training")?;
            for (f, v) in set
                .spec
                .trial_vectors(images, &it.meta.trial_id)
                .map_err(|e| e.message)?
            {
                t.x.extend_from_slice(&v);
                t.y.push(c);
                t.trial.push(k);
                t.frame.push(f);
            }
            t.trial_angle.push(angle);
        }
        if let Some((fits, predictions)) = args.profile {
            let mut model = None;
            for _ in 0..fits {
                model = Some(black_box(b.fit(set.clone(), &fctx)?));
            }
            if let Some(m) = &model {
                for _ in 0..predictions {
                    black_box(predict(m, &t));
                }
            }
            println!("{id:>7}: {fits} fits and {predictions} predictions done (--profile)");
            continue;
        }
        let d = dir.join(id);
        let as_f = |v: &[usize]| v.iter().map(|&x| x as f64).collect::<Vec<f64>>();
        write_npy(&d.join("X_train.npy"), &[set.len(), set.dim], &set.x)?;
        write_npy(&d.join("y_train.npy"), &[set.len()], &as_f(&set.y))?;
        write_npy(&d.join("trial_train.npy"), &[set.len()], &as_f(&set.trial))?;
        write_npy(&d.join("val_train.npy"), &[set.len()], &is_val)?;
        write_npy(&d.join("X_test.npy"), &[t.y.len(), t.dim], &t.x)?;
        write_npy(&d.join("y_test.npy"), &[t.y.len()], &as_f(&t.y))?;
        write_npy(&d.join("trial_test.npy"), &[t.y.len()], &as_f(&t.trial))?;
        write_npy(
            &d.join("test_trial_angle.npy"),
            &[t.trial_angle.len()],
            &t.trial_angle,
        )?;

        // Training: a fit is deterministic, so every repeat gives the same model.
        let fit_repeats = args.repeats.clamp(1, 7);
        let mut err = None;
        // Fitting includes scoring one test row: what a model builds lazily
        // at its first prediction (the k-NN search index, the forest's flat
        // node layout) is part of its training cost, and the predict timing
        // below (after a warm-up call) would otherwise never see it.
        // The training set is copied before the clock starts (a fit takes
        // it by value; scikit-learn's fit reads its arrays in place), at
        // most 64 copies at a time (the ANN's 7650 x 80 is 4.9 MB).
        let (model, fit_time) = timed_owned(
            fit_repeats,
            || set.clone(),
            |set| {
                let m = b.fit(set, &fctx).map_err(|e| err = Some(e)).ok()?;
                let k = m.classes.len();
                let mut one = vec![0.0; k];
                let mut rng = FitContext {
                    stage_id: "peers",
                    fold: 0,
                    seed: 0,
                }
                .rng();
                m.classifier
                    .scores_batch(&t.x[..t.dim.min(t.x.len())], t.dim, k, &mut rng, &mut one);
                Some(m)
            },
            64,
        );
        let model = model.ok_or_else(|| err.unwrap_or_default())?;
        let ((scores, answers), predict_time) = timed(args.repeats, || predict(&model, &t));
        if std::env::var_os("PEERS_DUMP_SCORES").is_some() {
            write_npy(&d.join("scores_test.npy"), &[scores.len()], &scores)?;
        }
        // Each frame's class, for the frame accuracy: outside the timing, as
        // run.py computes scikit-learn's.
        let pred: Vec<usize> = scores
            .chunks_exact(model.classes.len().max(1))
            .map(argmax)
            .collect();
        // Check: the arrays path answers as the stage does on the test trials.
        for (k, it) in test.iter().enumerate() {
            let e = model
                .predict_images(it.payload.images().map_err(|e| e.message)?, 0, "check")
                .map_err(|e| e.message)?;
            if e.angle_deg != answers[k] {
                return Err(format!("{id}: trial {k}: arrays and stage paths disagree"));
            }
        }
        let frame_acc = pred.iter().zip(&t.y).filter(|(p, y)| p == y).count() as f64 / t.y.len() as f64;
        let errs: Vec<f64> = answers
            .iter()
            .zip(&t.trial_angle)
            .map(|(a, truth)| a.map_or(f64::NAN, |a| (a - truth).abs()))
            .collect();
        let mae = errs.iter().sum::<f64>() / errs.len() as f64;
        println!(
            "{id:>7}: {} train x {} dims, {} test vectors; fit {:.3} s, predict {:.2} ms; frame acc {:.3}, MAE {:.2} deg",
            set.len(),
            set.dim,
            t.y.len(),
            fit_time["wall_s"]["min"].as_f64().unwrap_or(f64::NAN),
            predict_time["wall_s"]["min"].as_f64().unwrap_or(f64::NAN) * 1e3,
            frame_acc,
            mae
        );
        out.insert(
            id.to_string(),
            json!({
                "kind": b.kind(),
                "config": b.config_json(),
                "fold": 0,
                "fold_seed": fold_seed,
                "classes_deg": set.classes,
                "n_train": set.len(),
                "n_val": is_val.iter().filter(|&&v| v > 0.0).count(),
                "n_test": t.y.len(),
                "n_test_trials": t.trial_angle.len(),
                "dim": set.dim,
                "vote": "winner",
                "palpate": {
                    "fit_time": fit_time,
                    "predict_time": predict_time,
                    // ANN: epochs; EDBN: layer-epochs.
                    "epochs_run": model.log.loss.len(),
                    "best_epoch": model.log.best_epoch,
                    "frame_accuracy": frame_acc,
                    "trial_answers_deg": answers,
                    "trial_abs_err_deg": errs,
                    "mae_deg": mae,
                },
            }),
        );
    }
    let meta = json!({
        "source": {
            "graph": "graphs/quickstart.toml (front end and bins; 17 angles x 10 trials)",
            "seed": args.seed,
            "fold": "0: test on repetition 0 of every class, train on 1-9",
        },
        "models": out,
    });
    write_json(&dir.join("baselines.json"), &meta)?;
    Ok(meta)
}

fn main() {
    let args = match parse_args() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("peers: {e}");
            std::process::exit(2);
        }
    };
    let res = if args.wants("encoder") {
        encoder(&args).map(drop)
    } else {
        Ok(())
    }
    .and_then(|_| baselines(&args));
    if let Err(e) = res {
        eprintln!("peers: {e}");
        std::process::exit(1);
    }
    println!("wrote {}", args.out.display());
}
