//! Live path cost per DAQ frame, graphs/live.toml at 16 taxels: a 60-degree
//! trial of the lab scene (1 kHz, ~18 s, i.e. ~18 000 frames) streamed one
//! frame at a time through the graph's streaming plan (causal low-pass,
//! normalization, drive, Izhikevich at dt = 0.5 ms, 100/10 ms images,
//! streaming WSS over its default 33 classes).
//!
//! * `graph_per_frame`: each frame made into a one-sample block (as the `daq`
//!   source makes it) and pushed through every stage; the trial's open and
//!   flush included. This is the latency a frame adds after it is decoded.
//! * `ann_graph_per_frame`: the same for graphs/live_ann.toml, the same chain
//!   with its saved ANN (`model_in`) streaming instead of WSS.
//! * `daq_recording_per_frame`: the whole path of `palpate run --live` on
//!   the same trial recorded as raw DAQ frames: reader thread, decoder (CRC,
//!   sequence), contact segmentation, the graph. Reported per frame.
//!
//! Throughput is in frames per second (criterion's "elements"); the time per
//! frame is its inverse. A 1 kHz board needs < 1 ms per frame; the target is
//! <= 20 µs.
//!
//! Run: `cargo bench --bench live`.
//!
//! Timing of `graph_per_frame`: on-CPU time of the benchmark thread
//! (`/proc/thread-self/schedstat`, Linux; wall time elsewhere), so a shared
//! machine does not inflate it. `daq_recording_per_frame` is wall time (two
//! threads).

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use palpate::core::{self, stream, LoadOptions, Signals, TrialMeta};
use palpate::stages::io::daq::{encode_frame, simulate_trial, SampleFormat};
use std::hint::black_box;
use std::path::Path;
use std::time::{Duration, Instant};

fn cpu_time() -> Option<Duration> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    let ns: u64 = s.split_whitespace().next()?.parse().ok()?;
    Some(Duration::from_nanos(ns))
}

fn load(root: &Path, overrides: Vec<(String, toml::Value)>) -> core::Graph {
    load_graph(root, "graphs/live.toml", overrides)
}

fn load_graph(root: &Path, file: &str, overrides: Vec<(String, toml::Value)>) -> core::Graph {
    palpate::stages::link();
    let opts = LoadOptions {
        overrides,
        out: Some(std::env::temp_dir().join("palpate-bench-live")),
        base_dir: None,
    };
    core::load_file(&root.join(file), &opts).expect(file)
}

/// Pushes `sig` frame by frame through `plan`, trial open and flush included:
/// on-CPU time of the thread.
fn per_frame(
    grp: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>,
    name: &str,
    g: &core::Graph,
    plan: &stream::LivePlan,
    sig: &Signals,
    meta: &TrialMeta,
) {
    let n = sig.n_samples();
    grp.bench_function(name, |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                let (c0, w0) = (cpu_time(), Instant::now());
                let mut t = plan.start_trial(g, meta, false).expect("open");
                for k in 0..n {
                    let block = Signals {
                        sample_rate_hz: sig.sample_rate_hz,
                        layout: sig.layout.clone(),
                        unit: sig.unit.clone(),
                        data: sig.data.iter().map(|xs| vec![xs[k]]).collect(),
                    };
                    t.push(block.into(), &mut |_, out| {
                        black_box(out);
                    })
                    .expect("push");
                }
                black_box(t.finish(&mut |_, _| {}).expect("finish"));
                total += match (c0, cpu_time()) {
                    (Some(a), Some(b)) => b - a,
                    _ => w0.elapsed(),
                };
            }
            total
        })
    });
}

fn live(c: &mut Criterion) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let sig = simulate_trial(&root.join("graphs/scenes/lab.toml"), 60.0, 3).expect("lab scene");
    let n = sig.n_samples();
    let g = load(root, Vec::new());
    let plan = stream::plan(&g).expect("graphs/live.toml streams");
    let meta = TrialMeta {
        trial_id: "bench".into(),
        ..TrialMeta::default()
    };
    let mut grp = c.benchmark_group("live");
    grp.sample_size(10);
    grp.throughput(Throughput::Elements(n as u64));
    per_frame(&mut grp, "graph_per_frame", &g, &plan, &sig, &meta);
    let ann = load_graph(root, "graphs/live_ann.toml", Vec::new());
    let ann_plan = stream::plan(&ann).expect("graphs/live_ann.toml streams");
    per_frame(&mut grp, "ann_graph_per_frame", &ann, &ann_plan, &sig, &meta);
    // The same trial as a raw recording, through the daq source.
    let dir = std::env::temp_dir().join("palpate-bench-live");
    std::fs::create_dir_all(&dir).expect("temp dir");
    let path = dir.join("lab-60deg.daq");
    let mut bytes = Vec::new();
    let mut frame = vec![0.0; sig.data.len()];
    for k in 0..n {
        for (f, xs) in frame.iter_mut().zip(&sig.data) {
            *f = xs[k];
        }
        encode_frame(&mut bytes, SampleFormat::F32, k as u32, k as u64 * 1000, &frame);
    }
    std::fs::write(&path, &bytes).expect("write the recording");
    let g = load(
        root,
        vec![("stages.daq.recording".into(), path.display().to_string().into())],
    );
    let plan = stream::plan(&g).expect("graphs/live.toml streams");
    grp.bench_function("daq_recording_per_frame", |b| {
        b.iter(|| {
            let mut last = None;
            stream::replay(&g, &plan, 1, |u| last = Some(u.estimate.angle_deg)).expect("replay");
            assert_eq!(last, Some(Some(60.0)));
        })
    });
    grp.finish();
}

criterion_group!(benches, live);
criterion_main!(benches);
