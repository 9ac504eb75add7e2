//! Scene simulation speed: the paper's whole dataset (17 angles x 10 trials,
//! 1 kHz, 16 taxels) with every effect of `graphs/scenes/lab.toml`, the same
//! with the ideal scene, and single trials. Single-threaded: this is CPU time.
//!
//! Times are **thread CPU time** (from `/proc/thread-self/schedstat`, ns
//! resolution; wall time where that file is missing), so that the numbers mean
//! the same on a loaded machine.
//!
//! `CARGO_TARGET_DIR=... cargo bench --bench scene`

use criterion::measurement::{Measurement, ValueFormatter};
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use palpate_core::{derive_seed, BuildContext};
use palpate_stages::scene::{SceneConfig, Simulator};
use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// CPU time of the calling thread, ns.
fn thread_cpu_ns() -> u64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next().and_then(|v| v.parse().ok()))
        .unwrap_or_else(|| {
            static START: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();
            START.get_or_init(std::time::Instant::now).elapsed().as_nanos() as u64
        })
}

/// Criterion measurement of thread CPU time.
struct ThreadCpu;

struct NsFormatter;

impl ValueFormatter for NsFormatter {
    fn scale_values(&self, ns: f64, values: &mut [f64]) -> &'static str {
        let (f, unit) = match ns {
            x if x < 1e3 => (1.0, "ns"),
            x if x < 1e6 => (1e-3, "µs"),
            x if x < 1e9 => (1e-6, "ms"),
            _ => (1e-9, "s"),
        };
        values.iter_mut().for_each(|v| *v *= f);
        unit
    }
    fn scale_throughputs(&self, ns: f64, t: &Throughput, values: &mut [f64]) -> &'static str {
        let n = match *t {
            Throughput::Elements(n)
            | Throughput::Bytes(n)
            | Throughput::BytesDecimal(n)
            | Throughput::Bits(n) => n as f64,
        };
        // Elements per CPU second, in millions.
        let _ = ns;
        values.iter_mut().for_each(|v| *v = n / (*v * 1e-9) / 1e6);
        "Melem/s"
    }
    fn scale_for_machines(&self, _values: &mut [f64]) -> &'static str {
        "ns"
    }
}

impl Measurement for ThreadCpu {
    type Intermediate = u64;
    type Value = u64;
    fn start(&self) -> u64 {
        thread_cpu_ns()
    }
    fn end(&self, i: u64) -> u64 {
        thread_cpu_ns().saturating_sub(i)
    }
    fn add(&self, a: &u64, b: &u64) -> u64 {
        a + b
    }
    fn zero(&self) -> u64 {
        0
    }
    fn to_f64(&self, v: &u64) -> f64 {
        *v as f64
    }
    fn formatter(&self) -> &dyn ValueFormatter {
        &NsFormatter
    }
}

fn simulator(scene: &str) -> Simulator {
    let graphs = Path::new(env!("CARGO_MANIFEST_DIR")).join("graphs");
    let cfg = SceneConfig {
        file: Some(PathBuf::from(format!("scenes/{scene}.toml"))),
        ..Default::default()
    };
    let ctx = BuildContext {
        stage_id: "scene".into(),
        seed: 1,
        out_dir: std::env::temp_dir(),
        base_dir: graphs,
    };
    let scene = cfg.resolve(&ctx).expect("scene file");
    Simulator::new(scene, derive_seed(1, &["scene", "array"])).expect("scene")
}

/// Every trial of the scene, one after the other, kept (as the `scene` source
/// stage keeps them for its readers).
fn dataset(sim: &Simulator) -> Vec<palpate_core::Signals> {
    let mut out = Vec::with_capacity(sim.scene.angles.len() * sim.scene.trials_per_angle);
    for &angle in &sim.scene.angles {
        for rep in 0..sim.scene.trials_per_angle {
            let seed = derive_seed(1, &["scene", &format!("{angle}-{rep}")]);
            out.push(sim.simulate(angle, seed).expect("trial"));
        }
    }
    out
}

/// The same trials simulated into one reused set of rows: the computation
/// alone, without the allocator and the kernel's first touch of fresh memory.
fn dataset_reused(sim: &Simulator, rows: &mut Vec<Vec<f64>>) -> f64 {
    let mut sum = 0.0;
    for &angle in &sim.scene.angles {
        for rep in 0..sim.scene.trials_per_angle {
            let seed = derive_seed(1, &["scene", &format!("{angle}-{rep}")]);
            sim.simulate_into(angle, seed, rows).expect("trial");
            sum += rows[5][rows[5].len() / 2];
        }
    }
    sum
}

fn lab_with(kinds: &[&str]) -> Simulator {
    let mut sim = simulator("lab");
    let mut scene = sim.scene.clone();
    scene.effects.retain(|e| kinds.contains(&e.kind()));
    sim = Simulator::new(scene, 1).expect("scene");
    sim
}

fn bench(c: &mut Criterion<ThreadCpu>) {
    let lab = simulator("lab");
    let ideal = simulator("ideal");
    let mut g = c.benchmark_group("scene");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(8))
        .warm_up_time(Duration::from_secs(1));
    // Simulating is producing the signals, first touch of their memory
    // included; handing the 576 MB back to the allocator afterwards is not, so
    // the drop falls outside the timed region.
    g.bench_function("scene_paper_dataset_lab", |b| {
        b.iter_with_large_drop(|| dataset(&lab))
    });
    g.bench_function("scene_paper_dataset_ideal", |b| {
        b.iter_with_large_drop(|| dataset(&ideal))
    });
    let mut rows = Vec::new();
    g.bench_function("scene_paper_dataset_lab_reused_rows", |b| {
        b.iter(|| black_box(dataset_reused(&lab, &mut rows)))
    });
    g.finish();

    let mut g = c.benchmark_group("scene_trial");
    g.sample_size(20)
        .measurement_time(Duration::from_secs(3))
        .warm_up_time(Duration::from_millis(500));
    for angle in [10.0, 45.0, 90.0] {
        g.bench_function(format!("lab_{angle}deg"), |b| {
            b.iter(|| black_box(lab.simulate(angle, 42).expect("trial")))
        });
        g.bench_function(format!("ideal_{angle}deg"), |b| {
            b.iter(|| black_box(ideal.simulate(angle, 42).expect("trial")))
        });
    }
    g.finish();

    // One effect at a time (plus piezo where the effect's units are volts), at 45°.
    let mut g = c.benchmark_group("scene_effect");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(2))
        .warm_up_time(Duration::from_millis(300));
    for kind in [
        "variation",
        "skin",
        "stress",
        "creep",
        "dead",
        "piezo",
        "mismatch",
        "crosstalk",
        "hum",
        "noise",
        "adc",
    ] {
        let sim = lab_with(&[kind]);
        g.bench_function(format!("{kind}_45deg"), |b| {
            b.iter(|| black_box(sim.simulate(45.0, 42).expect("trial")))
        });
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().with_measurement(ThreadCpu);
    targets = bench
}
criterion_main!(benches);
