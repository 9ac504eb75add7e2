//! Encoder and binning speed: 16 taxels x 40 s of a 1 kHz drive (the paper's
//! array over a slow, 10-degree edge crossing), integrated at dt = 0.5 ms, i.e.
//! 16 x 80 000 = 1.28 million neuron-steps per run. Throughput is reported in
//! neuron-steps per second (criterion's "elements"). Target: >= 1e8 on one core.
//!
//! Run: `cargo bench --bench encode`.
//!
//! Timing: each iteration is timed by the thread's own on-CPU time
//! (`/proc/thread-self/schedstat`, Linux; wall time elsewhere), so that the
//! figure is the speed on one core even when the machine is shared and the
//! benchmark thread waits for a CPU. Groups `*_wall` time the same work by wall
//! clock for comparison.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use palpate_core::{SpikeTrain, TaxelLayout};
use palpate_stages::encode::izhikevich::{IzhParams, Izhikevich, Preset, Scheme};
use palpate_stages::encode::lif::Lif;
use palpate_stages::encode::InputMode;
use palpate_stages::spikes::bin::Binner;
use std::hint::black_box;
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

const FS: f64 = 1000.0;
const SECONDS: f64 = 40.0;
const DT_MS: f64 = 0.5;

/// FA-I-like currents: each taxel sees a 20-unit bump lasting ~6 s at its own
/// time, 0 elsewhere (the shape a 10-degree crossing gives).
fn currents() -> Vec<Vec<f64>> {
    let n = (SECONDS * FS) as usize;
    (0..16)
        .map(|i| {
            let centre = 10.0 + i as f64 * 1.2;
            (0..n)
                .map(|k| {
                    let t = k as f64 / FS;
                    20.0 * (-((t - centre) / 2.0).powi(2)).exp()
                })
                .collect()
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let cur = currents();
    let steps = 16 * (SECONDS * 1000.0 / DT_MS) as u64;
    let mut g = c.benchmark_group("encode_16x40s_dt0.5");
    g.throughput(Throughput::Elements(steps));
    g.warm_up_time(Duration::from_millis(500));
    g.measurement_time(Duration::from_secs(3));
    g.sample_size(20);
    for (name, scheme, input) in [
        ("izhikevich_scheme_hold", Scheme::Izhikevich, InputMode::Hold),
        ("izhikevich_euler_hold", Scheme::Euler, InputMode::Hold),
        ("izhikevich_scheme_linear", Scheme::Izhikevich, InputMode::Linear),
    ] {
        let enc = Izhikevich {
            params: IzhParams::preset(Preset::FaI),
            dt_ms: DT_MS,
            scheme,
            input,
        };
        g.bench_function(name, |b| {
            b.iter_custom(|n| timed(n, || enc.encode(black_box(&cur), FS)))
        });
    }
    let lif = Lif::default();
    g.bench_function("lif_hold", |b| {
        b.iter_custom(|n| timed(n, || lif.encode(black_box(&cur), FS)))
    });
    g.finish();

    // The same Izhikevich run timed by wall clock, for comparison (inflated
    // when the machine is shared).
    let mut g = c.benchmark_group("encode_16x40s_dt0.5_wall");
    g.throughput(Throughput::Elements(steps));
    g.warm_up_time(Duration::from_millis(500));
    g.measurement_time(Duration::from_secs(3));
    g.sample_size(20);
    let enc = Izhikevich {
        params: IzhParams::preset(Preset::FaI),
        dt_ms: DT_MS,
        scheme: Scheme::Izhikevich,
        input: InputMode::Hold,
    };
    g.bench_function("izhikevich_scheme_hold", |b| {
        b.iter(|| black_box(enc.encode(black_box(&cur), FS)))
    });
    g.finish();

    // Binning the Izhikevich output (window 100 ms, hop 10 ms): throughput in spikes.
    let enc = Izhikevich {
        params: IzhParams::preset(Preset::FaI),
        dt_ms: DT_MS,
        scheme: Scheme::Izhikevich,
        input: InputMode::Hold,
    };
    let train = SpikeTrain {
        layout: TaxelLayout::paper(),
        duration_ms: SECONDS * 1000.0,
        events: enc.encode(&cur, FS),
    };
    let binner = Binner::new(100.0, 10.0);
    let mut g = c.benchmark_group("bin_16x40s");
    g.throughput(Throughput::Elements(train.events.len() as u64));
    g.warm_up_time(Duration::from_millis(500));
    g.measurement_time(Duration::from_secs(2));
    g.sample_size(20);
    g.bench_function("bin_100_10", |b| {
        b.iter_custom(|n| timed(n, || binner.bin(black_box(&train))))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
