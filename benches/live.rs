//! Live path cost per DAQ frame: a 60-degree trial of the lab scene (16
//! taxels at 1 kHz, ~14 s, i.e. ~14 000 frames) pushed frame by frame through
//! `LivePipeline` with graphs/live.toml's settings (causal low-pass,
//! normalization, drive, Izhikevich at dt = 0.5 ms, 100/10 ms images,
//! streaming WSS over 17 classes). Throughput is in frames per second
//! (criterion's "elements"); the time per frame is its inverse. A 1 kHz
//! board needs < 1 ms per frame.
//!
//! Run: `cargo bench --bench live`.
//!
//! Timing: on-CPU time of the benchmark thread (`/proc/thread-self/schedstat`,
//! Linux; wall time elsewhere), so a shared machine does not inflate it.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use palpate_stages::io::live::{simulate_trial, LiveConfig, LivePipeline};
use std::hint::black_box;
use std::path::Path;
use std::time::{Duration, Instant};

fn cpu_time() -> Option<Duration> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    let ns: u64 = s.split_whitespace().next()?.parse().ok()?;
    Some(Duration::from_nanos(ns))
}

fn live(c: &mut Criterion) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let cfg = LiveConfig::from_file(&root.join("graphs/live.toml")).expect("graphs/live.toml");
    let sig = simulate_trial(&root.join("graphs/scenes/lab.toml"), 60.0, 3).expect("lab scene");
    let n = sig.n_samples();
    let frames: Vec<Vec<f64>> = (0..n)
        .map(|k| sig.data.iter().map(|xs| xs[k]).collect())
        .collect();
    let tpl = cfg.templates().expect("templates");
    let mut g = c.benchmark_group("live");
    g.sample_size(10);
    g.throughput(Throughput::Elements(n as u64));
    g.bench_function("push_60deg_lab_trial", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                let mut p = LivePipeline::with_templates(&cfg, tpl.clone()).expect("pipeline");
                let (c0, w0) = (cpu_time(), Instant::now());
                for f in &frames {
                    black_box(p.push(f).expect("push"));
                }
                black_box(p.finish().expect("finish"));
                total += match (c0, cpu_time()) {
                    (Some(a), Some(b)) => b - a,
                    _ => w0.elapsed(),
                };
            }
            total
        })
    });
    g.finish();
}

criterion_group!(benches, live);
criterion_main!(benches);
