//! The machine constants the per-trial chain's limits are stated in
//! (docs/benches.md, "The per-trial chain against its limits"): the latency
//! of one dependent double-precision multiply or add (the floor of a
//! recursion such as a biquad or a neuron's membrane, which waits on its own
//! last result), the rate at which one core copies a buffer of a lab
//! trial's size (the floor of a stage that reads and writes every sample),
//! and the rate at which one core reads a 10 MB working set again and again
//! (the floor of WSS, which reads its cached template spectra, 17 classes x
//! 16 taxels x 2 305 complex bins, once per trial: too large for the 2 MB L2,
//! so they come from L3 or memory every trial).
//!
//! `cargo run --release --example machine`. Each figure is the best of 5
//! runs, so a shared machine's interruptions inflate it less.

use std::hint::black_box;
use std::time::Instant;

fn best(mut f: impl FnMut() -> f64) -> f64 {
    (0..5).map(|_| f()).fold(f64::INFINITY, f64::min)
}

fn main() {
    // x = x·a + b: each multiply waits on the last add, each add on its
    // multiply: 2 dependent operations per iteration.
    let n = 50_000_000u64;
    let ns_per_op = best(|| {
        let (a, b) = (black_box(0.999_999_999), black_box(1e-9));
        let mut x = black_box(1.0f64);
        let t = Instant::now();
        for _ in 0..n {
            x = x * a + b;
        }
        black_box(x);
        t.elapsed().as_secs_f64() * 1e9 / (2 * n) as f64
    });
    // A 21.6 s, 16-taxel lab trial at 1 kHz: 345 280 doubles, 2.76 MB.
    let len = 21_580 * 16;
    let src: Vec<f64> = (0..len).map(|i| i as f64).collect();
    let mut dst = vec![0.0f64; len];
    let copy_ms = best(|| {
        let t = Instant::now();
        for _ in 0..20 {
            dst.copy_from_slice(black_box(&src));
            black_box(&mut dst);
        }
        t.elapsed().as_secs_f64() * 1e3 / 20.0
    });
    let gb_s = (len * 8) as f64 / (copy_ms * 1e-3) / 1e9;
    // 17 x 16 x 2 305 complex doubles = 10.0 MB, summed by 8 independent
    // lanes (the read, not the adds, is the limit).
    let spectra = 17 * 16 * 2_305 * 2;
    let tpl: Vec<f64> = (0..spectra).map(|i| (i % 7) as f64).collect();
    let read_ms = best(|| {
        let t = Instant::now();
        for _ in 0..20 {
            let mut acc = [0.0f64; 8];
            for c in black_box(&tpl).chunks_exact(8) {
                for l in 0..8 {
                    acc[l] += c[l];
                }
            }
            black_box(acc);
        }
        t.elapsed().as_secs_f64() * 1e3 / 20.0
    });
    let read_gb_s = (spectra * 8) as f64 / (read_ms * 1e-3) / 1e9;
    println!("dependent f64 multiply or add: {ns_per_op:.2} ns");
    println!("copy of one lab trial's signals (2.76 MB): {copy_ms:.3} ms ({gb_s:.1} GB/s read + write)");
    println!(
        "read of the WSS template spectra (17 classes, {:.1} MB), again and again: {read_ms:.3} ms ({read_gb_s:.1} GB/s)",
        (spectra * 8) as f64 / 1e6
    );
}
