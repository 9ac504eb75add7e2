//! The whole pipeline per trial, stage by stage, and binning.
//!
//! * `pipeline_45deg_lab/*`: one trial of `graphs/quickstart.toml` (the lab
//!   scene at 45 degrees, trial r00 of seed 1: 16 taxels, ~21.7 s at 1 kHz)
//!   from the scene's signals to the estimate (lowpass -> normalize -> drive
//!   -> izhikevich -> bin -> wss), with the stages built from that file and
//!   called as the runtime calls them (same per-trial seeds); `chain` is the
//!   whole per-trial cost, the others one stage each on the graph's own input
//!   for it. The WSS model is fitted once, as in a run (its templates are
//!   built at its first trial: `pipeline_45deg_lab_once/wss_first_trial`
//!   measures that one-time cost).
//!   Before timing, every stage's output and the final estimate are checked
//!   to equal, value for value, what `palpate run` of the graph restricted
//!   to that trial produces.
//! * `bin_16x40s/bin_100_10`: the `bin` stage (100 ms windows, 10 ms hop) on a
//!   real 16-taxel x 40 s spike train: the first 40 s of what the quickstart
//!   chain makes of the lab scene's 10-degree trial. Throughput in spikes.
//!
//! The scene itself is benched in `benches/scene.rs`.
//!
//! Run: `cargo bench --bench pipeline`.
//!
//! Allocation: the binary's allocator setting
//! ([`palpate::cli::tune_allocator`]) is applied first, so that the stages
//! reuse freed heap as they do in `palpate run`.
//!
//! Timing: each iteration is timed by the thread's own on-CPU time
//! (`/proc/thread-self/schedstat`, Linux; wall time elsewhere), so the figure
//! is the cost on one core even when the machine is shared; the `_wall` group
//! times the chain by wall clock for comparison.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use palpate::core::{self, derive_seed, FitContext, Item, LoadOptions, Model, Payload, RunOptions, Stage};
use palpate::core::{SpikeTrain, TrialContext};
use std::hint::black_box;
use std::path::Path;
use std::time::{Duration, Instant};

/// This thread's on-CPU time so far, if the kernel reports it.
fn cpu_time() -> Option<Duration> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    let ns: u64 = s.split_whitespace().next()?.parse().ok()?;
    Some(Duration::from_nanos(ns))
}

/// Runs `f` `iters` times and returns the on-CPU (else wall) time it took.
fn timed<T>(iters: u64, mut f: impl FnMut() -> T) -> Duration {
    let (c0, w0) = (cpu_time(), Instant::now());
    for _ in 0..iters {
        black_box(f());
    }
    match (c0, cpu_time()) {
        (Some(a), Some(b)) => b - a,
        _ => w0.elapsed(),
    }
}

/// The quickstart's stages after the scene.
const CHAIN: [&str; 6] = ["filter", "norm", "drive", "enc", "bins", "wss"];

/// graphs/quickstart.toml restricted to one trial at `angle`, its stages
/// built, the WSS model fitted (once, as a run does).
struct Quickstart {
    g: core::Graph,
    wss: Box<dyn Model>,
}

impl Quickstart {
    fn load(angle: f64) -> Quickstart {
        palpate::link();
        let root = Path::new(env!("CARGO_MANIFEST_DIR"));
        let set = |s: &str| LoadOptions::parse_set(s).expect("override");
        let g = core::load_file(
            &root.join("graphs/quickstart.toml"),
            &LoadOptions {
                overrides: vec![
                    set(&format!("stages.scene.angles=[{angle}]")),
                    set("stages.scene.trials_per_angle=1"),
                ],
                out: Some(std::env::temp_dir().join(format!("palpate-bench-{}", std::process::id()))),
                base_dir: None,
            },
        )
        .expect("graphs/quickstart.toml");
        let wss = Self::fit(&g);
        Quickstart { g, wss }
    }

    fn fit(g: &core::Graph) -> Box<dyn Model> {
        let Stage::Estimator(e) = &g.nodes[g.index_of("wss").expect("wss")].stage else {
            panic!("wss is an estimator")
        };
        let fctx = FitContext {
            stage_id: "wss",
            fold: 0,
            seed: derive_seed(g.run.seed, &["wss", "fold0"]),
        };
        e.fit(&[], &fctx).expect("wss fit")
    }

    /// Every stage's output for the trial, by `palpate run` of the graph.
    fn run_graph(&self) -> std::collections::HashMap<String, std::sync::Arc<Vec<Item>>> {
        let r = core::run(
            &self.g,
            &RunOptions {
                keep_outputs: true,
                ..RunOptions::default()
            },
        )
        .expect("quickstart run");
        let _ = std::fs::remove_dir_all(&self.g.out_dir);
        r.outputs
    }

    /// Stage `id` on `item`, as the runtime calls it.
    fn stage(&self, id: &str, item: &Item) -> Payload {
        let ctx = TrialContext {
            stage_id: id,
            meta: &item.meta,
            seed: derive_seed(self.g.run.seed, &[id, &item.meta.trial_id]),
        };
        let r = match &self.g.nodes[self.g.index_of(id).expect("stage")].stage {
            Stage::Map(m) => m.process(&[item], &ctx),
            Stage::Estimator(_) => self.wss.predict(item, &ctx).map(Into::into),
            _ => panic!("{id}: not a map or estimator"),
        };
        r.unwrap_or_else(|e| panic!("{id}: {}", e.message))
    }

    /// The whole chain from the scene's signals.
    fn chain(&self, scene: &Item) -> Payload {
        let mut item = scene.clone();
        for id in CHAIN {
            item = Item {
                meta: item.meta.clone(),
                payload: self.stage(id, &item),
            };
        }
        item.payload
    }
}

fn same(a: &Payload, b: &Payload) -> bool {
    match (a, b) {
        (Payload::Signals(x), Payload::Signals(y)) => x == y,
        (Payload::Spikes(x), Payload::Spikes(y)) => x == y,
        (Payload::Images(x), Payload::Images(y)) => x == y,
        (Payload::Estimate(x), Payload::Estimate(y)) => x == y,
        _ => false,
    }
}

fn pipeline(c: &mut Criterion) {
    // The binary's allocator setting, so that a stage's fresh output reuses
    // freed heap as in `palpate run` instead of page-faulting new memory at
    // every iteration (before 2026-11-27 the bench ran without it).
    palpate::cli::tune_allocator();
    let q = Quickstart::load(45.0);
    let out = q.run_graph();
    let scene = &out["scene"][0];
    let sig = scene.payload.signals().expect("signals");
    // Same bits as the graph: every stage on the graph's input for it, and
    // the whole chain from the scene.
    let mut prev = scene;
    for id in CHAIN {
        let mine = q.stage(id, prev);
        assert!(
            same(&mine, &out[id][0].payload),
            "{id} differs from the graph's output"
        );
        prev = &out[id][0];
    }
    let est = q.chain(scene);
    assert!(same(&est, &out["wss"][0].payload));
    let e = est.estimate().expect("estimate");
    eprintln!(
        "pipeline: trial {} ({} samples x {} taxels, {:.1} s): estimate {:?} deg, equal to the graph's",
        scene.meta.trial_id,
        sig.n_samples(),
        sig.data.len(),
        sig.duration_ms() / 1000.0,
        e.angle_deg
    );

    let mut g = c.benchmark_group("pipeline_45deg_lab");
    g.warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(3))
        .sample_size(20);
    g.bench_function("chain", |b| {
        b.iter_custom(|n| timed(n, || q.chain(black_box(scene))))
    });
    let mut input = scene;
    for id in CHAIN {
        g.bench_function(id, |b| {
            b.iter_custom(|n| timed(n, || q.stage(id, black_box(input))))
        });
        input = &out[id][0];
    }
    g.finish();

    // One-time cost of a run: fitting the WSS model and its first trial
    // (templates and their spectra built then).
    let mut g = c.benchmark_group("pipeline_45deg_lab_once");
    g.warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(4))
        .sample_size(10);
    let images = &out["bins"][0];
    g.bench_function("wss_first_trial", |b| {
        b.iter_custom(|n| {
            timed(n, || {
                let m = Quickstart::fit(&q.g);
                let ctx = TrialContext {
                    stage_id: "wss",
                    meta: &images.meta,
                    seed: 0,
                };
                m.predict(black_box(images), &ctx).expect("predict")
            })
        })
    });
    g.finish();

    let mut g = c.benchmark_group("pipeline_45deg_lab_wall");
    g.warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(5))
        .sample_size(20);
    g.bench_function("chain", |b| b.iter(|| q.chain(black_box(scene))));
    g.finish();
}

fn binning(c: &mut Criterion) {
    let q = Quickstart::load(10.0);
    let out = q.run_graph();
    let full = out["enc"][0].payload.spikes().expect("spikes");
    let end = 40_000.0;
    assert!(
        full.duration_ms >= end,
        "the 10-degree trial lasts {} ms",
        full.duration_ms
    );
    let train = SpikeTrain {
        layout: full.layout.clone(),
        duration_ms: end,
        events: full.events.iter().copied().filter(|e| e.t_ms < end).collect(),
    };
    let item = Item {
        meta: out["enc"][0].meta.clone(),
        payload: train.into(),
    };
    let n_spikes = item.payload.spikes().expect("spikes").events.len();
    let im = q.stage("bins", &item);
    let im = im.images().expect("images");
    eprintln!(
        "binning: {n_spikes} spikes over 16 taxels x 40 s -> {} images of 100 ms every 10 ms",
        im.n_frames
    );
    let mut g = c.benchmark_group("bin_16x40s");
    g.throughput(Throughput::Elements(n_spikes as u64));
    g.warm_up_time(Duration::from_millis(500))
        .measurement_time(Duration::from_secs(2))
        .sample_size(20);
    g.bench_function("bin_100_10", |b| {
        b.iter_custom(|n| timed(n, || q.stage("bins", black_box(&item))))
    });
    g.finish();
}

criterion_group!(benches, pipeline, binning);
criterion_main!(benches);
