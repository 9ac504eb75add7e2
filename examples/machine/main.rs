//! The machine constants the per-trial chain's limits are stated in
//! (docs/benches.md, "The per-trial chain against its limits"): the latency
//! of one dependent double-precision multiply or add (the floor of a
//! recursion such as a biquad or a neuron's membrane, which waits on its own
//! last result), the rate at which one core copies a buffer of a lab
//! trial's size (the floor of a stage that reads and writes every sample),
//! and the rate at which one core reads a 10 MB working set again and again
//! (the floor of WSS, which reads its cached template spectra, 17 classes x
//! 16 taxels x 2 305 complex bins, once per trial: too large for the 2 MB L2,
//! so they come from L3 or memory every trial). Last, WSS's frequency-domain
//! products themselves (17 classes x 16 taxels x 2 305 bins, `acc += x·h`)
//! per trial in three settings: nothing between trials; 11 MB written
//! between trials (what a lab trial's signal stages write between two
//! estimates in a depth-first run); and those writes with four trials per
//! pass over each class's spectra. And the trained baselines' layer
//! products (`estimate::dense::gemm_nt`, the bits of a fixed-order dot
//! product, each term fused) at their prediction shapes, in billions of products a
//! second, with the kernel the CPU picks and with AVX-512 switched off (the
//! AVX2 kernels). And the activations applied to those products' outputs
//! (`tanh` with the bias, the row softmax), in ns per value.
//!
//! The dependent multiply or add is also timed in 512-bit and 256-bit
//! registers (the lane kernels' operations): a core's vector operations
//! may wait longer on their last result than its scalar ones.
//!
//! `cargo run --release --example machine`. Each figure is the best of 5
//! runs, so a shared machine's interruptions inflate it less.

use palpate_stages::estimate::{dense, vmath};
use std::hint::black_box;
use std::time::Instant;

/// `acc += x ⊙ h` over complex bins stored as separate parts.
#[inline(always)]
fn cmac_body(acc: &mut [Vec<f64>; 2], x: [&[f64]; 2], h: [&[f64]; 2]) {
    let [ar, ai] = acc;
    for f in 0..ar.len() {
        ar[f] += x[0][f] * h[0][f] - x[1][f] * h[1][f];
        ai[f] += x[0][f] * h[1][f] + x[1][f] * h[0][f];
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn cmac_avx2(acc: &mut [Vec<f64>; 2], x: [&[f64]; 2], h: [&[f64]; 2]) {
    cmac_body(acc, x, h)
}

fn cmac(acc: &mut [Vec<f64>; 2], x: [&[f64]; 2], h: [&[f64]; 2]) {
    #[cfg(target_arch = "x86_64")]
    if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
        // SAFETY: the CPU supports AVX2 and FMA (checked above).
        return unsafe { cmac_avx2(acc, x, h) };
    }
    cmac_body(acc, x, h)
}

/// WSS's products for `trials` trials per pass over each class's spectra,
/// ms per trial, after writing `junk` once per trial (best of 5).
fn products_ms(h: &[Vec<f64>], x: &[Vec<f64>], trials: usize, per_pass: usize, junk: &mut [u8]) -> f64 {
    let (classes, taxels, bins) = (17, 16, h[0].len());
    let mut acc: Vec<[Vec<f64>; 2]> = (0..per_pass)
        .map(|_| [vec![0.0; bins], vec![0.0; bins]])
        .collect();
    let mut round = 0u8;
    best(|| {
        let mut total = 0.0;
        for group in 0..trials / per_pass {
            for _ in 0..per_pass {
                round = round.wrapping_add(1);
                junk.iter_mut().for_each(|b| *b = b.wrapping_add(round));
            }
            let t = Instant::now();
            for c in 0..classes {
                acc.iter_mut()
                    .flatten()
                    .for_each(|a| a.iter_mut().for_each(|v| *v = 0.0));
                for t in 0..taxels {
                    let hc = (c * taxels + t) * 2;
                    for (g, a) in acc.iter_mut().enumerate() {
                        let xt = (((group * per_pass + g) % 4) * taxels + t) * 2;
                        cmac(a, [&x[xt], &x[xt + 1]], [&h[hc], &h[hc + 1]]);
                    }
                }
                black_box(&acc);
            }
            total += t.elapsed().as_secs_f64();
        }
        total * 1e3 / trials as f64
    })
}

/// `x = x·a + b` on `L` independent lanes, `n` times: the latency of a
/// dependent multiply or add when the lanes are one vector register (the
/// loop over lanes vectorizes; the chain runs through every element).
#[inline(always)]
fn lane_chain<const L: usize>(n: u64) -> f64 {
    let (a, b) = (black_box(0.999_999_999), black_box(1e-9));
    let mut x = black_box([1.0f64; L]);
    let t = Instant::now();
    for _ in 0..n {
        for v in x.iter_mut() {
            *v = *v * a + b;
        }
    }
    black_box(x);
    t.elapsed().as_secs_f64() * 1e9 / (2 * n) as f64
}

/// [`lane_chain`] with 8 lanes in one 512-bit register, if the CPU has
/// AVX-512 (the encoders' and the filter's lane kernels run there).
fn chain512(n: u64) -> Option<f64> {
    #[cfg(target_arch = "x86_64")]
    if is_x86_feature_detected!("avx512f") {
        #[target_feature(enable = "avx512f")]
        fn run(n: u64) -> f64 {
            lane_chain::<8>(n)
        }
        // SAFETY: the CPU supports AVX-512F (checked above).
        return Some(unsafe { run(n) });
    }
    let _ = n;
    None
}

/// [`lane_chain`] with 4 lanes in one 256-bit register, if the CPU has AVX2.
fn chain256(n: u64) -> Option<f64> {
    #[cfg(target_arch = "x86_64")]
    if is_x86_feature_detected!("avx2") {
        #[target_feature(enable = "avx2")]
        fn run(n: u64) -> f64 {
            lane_chain::<4>(n)
        }
        // SAFETY: the CPU supports AVX2 (checked above).
        return Some(unsafe { run(n) });
    }
    let _ = n;
    None
}

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
    // The same chain in vector registers: a core's scalar and vector
    // operations need not have the same latency.
    let ns512 = chain512(n).map(|first| best(|| chain512(n).unwrap_or(first)).min(first));
    let ns256 = chain256(n).map(|first| best(|| chain256(n).unwrap_or(first)).min(first));
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
    // Template spectra (17 classes x 16 taxels, re and im) and four trials'
    // input spectra, as WSS holds them.
    let bins = 2_305;
    let h: Vec<Vec<f64>> = (0..17 * 16 * 2)
        .map(|i| (0..bins).map(|f| ((i * 7 + f) % 13) as f64 * 0.1).collect())
        .collect();
    let x: Vec<Vec<f64>> = (0..4 * 16 * 2)
        .map(|i| (0..bins).map(|f| ((i * 3 + f) % 11) as f64 * 0.1).collect())
        .collect();
    let quiet = products_ms(&h, &x, 8, 1, &mut []);
    let mut junk = vec![0u8; 11 << 20];
    let evicted = products_ms(&h, &x, 8, 1, &mut junk);
    let grouped = products_ms(&h, &x, 8, 4, &mut junk);
    // Rows x outputs x inputs: ANN (S) input and output layers, ANN (ST)
    // input layer, EDBN's two layers (3154 test frames each).
    let layers = [
        (2848, 30, 16),
        (2848, 17, 30),
        (3154, 30, 80),
        (3154, 60, 80),
        (3154, 30, 60),
    ];
    let mut products = Vec::new();
    for (m, n, k) in layers {
        let a: Vec<f64> = (0..m * k)
            .map(|i| ((i * 7919) % 1000) as f64 / 500.0 - 1.0)
            .collect();
        let b: Vec<f64> = (0..n * k)
            .map(|i| ((i * 104_729) % 1000) as f64 / 500.0 - 1.0)
            .collect();
        let mut out = vec![0.0; m * n];
        let mut rate = |f: &dyn Fn(&mut [f64])| {
            let ms = best(|| {
                let t = Instant::now();
                for _ in 0..10 {
                    f(black_box(&mut out));
                }
                t.elapsed().as_secs_f64() * 1e3 / 10.0
            });
            (m * n * k) as f64 / (ms * 1e-3) / 1e9
        };
        let picked = rate(&|o| dense::gemm_nt(&a, &b, k, o));
        let avx2 = rate(&|o| palpate_stages::wide::without_avx512(|| dense::gemm_nt(&a, &b, k, o)));
        products.push(format!("{m}x{n}x{k} {picked:.1} / {avx2:.1}"));
    }
    // The EDBN's training products, a minibatch of 20 rows against its
    // bottom RBM (80 visible, 60 hidden): `v Wᵀ` (rows of `v`, `W`
    // transposed once), `Σ h vᵀ` as `hᵀ v` (a transposed view) and `h W`,
    // through `dense::gemm_nn`, with the kernel picked, the AVX2 one, and
    // the operands materialised for `gemm_nt`'s tiles (what AVX2-only CPUs
    // ran before `gemm_nn` had an AVX2 kernel).
    let (bs, nv, nh) = (20, 80, 60);
    let fill = |len: usize, p: usize| -> Vec<f64> {
        (0..len).map(|i| ((i * p) % 1000) as f64 / 500.0 - 1.0).collect()
    };
    let (v, h, w) = (
        fill(bs * nv, 7919),
        fill(bs * nh, 104_729),
        fill(nh * nv, 15_485_863),
    );
    let mut wt = vec![0.0; nv * nh];
    dense::transpose(&w, nh, nv, &mut wt);
    let cases: [(&str, dense::View<'_>, &[f64], usize); 3] = [
        ("v Wt 20x60x80", dense::View::rows_of(&v, bs, nv), &wt, nh),
        ("ht v 60x80x20", dense::View::transpose_of(&h, bs, nh), &v, nv),
        ("h W 20x80x60", dense::View::rows_of(&h, bs, nh), &w, nv),
    ];
    let mut train = Vec::new();
    for (name, a, b, n) in cases {
        let (m, k) = (a.rows, a.cols);
        let mut out = vec![0.0; m * n];
        let mut rate = |f: &dyn Fn(&mut [f64])| {
            let ms = best(|| {
                let t = Instant::now();
                for _ in 0..2000 {
                    f(black_box(&mut out));
                }
                t.elapsed().as_secs_f64() * 1e3 / 2000.0
            });
            (m * n * k) as f64 / (ms * 1e-3) / 1e9
        };
        let picked = rate(&|o| dense::gemm_nn(a, b, n, o));
        let avx2 = rate(&|o| palpate_stages::wide::without_avx512(|| dense::gemm_nn(a, b, n, o)));
        let materialised = rate(&|o| {
            let mut rows = Vec::with_capacity(m * k);
            for i in 0..m {
                rows.extend((0..k).map(|t| a.data[i * a.rs + t * a.cs]));
            }
            let mut bt = vec![0.0; k * n];
            dense::transpose(&b[..k * n], k, n, &mut bt);
            palpate_stages::wide::without_avx512(|| dense::gemm_nt(&rows, &bt, k, o));
        });
        train.push(format!("{name} {picked:.1} / {avx2:.1} / {materialised:.1}"));
    }
    // The activations a prediction applies to every layer output: `tanh`
    // (the ANN's hidden layer, through `dense::add_bias_map` as the ANN
    // runs it) and the row softmax (its output), over ANN (ST)'s shapes:
    // ns per value, the floor those terms put under a prediction.
    let act_ns = |rows: usize, width: usize, f: &dyn Fn(&mut [f64])| {
        let base: Vec<f64> = (0..rows * width)
            .map(|i| ((i * 7919) % 1000) as f64 / 250.0 - 2.0)
            .collect();
        let mut v = base.clone();
        best(|| {
            let mut ns = 0.0;
            for _ in 0..10 {
                v.copy_from_slice(&base);
                let t = Instant::now();
                f(black_box(&mut v));
                ns += t.elapsed().as_secs_f64() * 1e9;
            }
            ns / 10.0 / (rows * width) as f64
        })
    };
    let bias = vec![0.01; 30];
    let tanh_ns = act_ns(3154, 30, &|v| dense::add_bias_map(v, &bias, vmath::tanh));
    let softmax_ns = act_ns(3154, 17, &|v| vmath::softmax_rows(v, 17));
    println!("dependent f64 multiply or add: {ns_per_op:.2} ns");
    let show = |o: Option<f64>| o.map_or("no such registers".to_string(), |v| format!("{v:.2} ns"));
    println!(
        "the same in vector registers, every lane dependent: 512-bit (8 lanes) {}, 256-bit (4 lanes) {}",
        show(ns512),
        show(ns256)
    );
    println!("copy of one lab trial's signals (2.76 MB): {copy_ms:.3} ms ({gb_s:.1} GB/s read + write)");
    println!(
        "read of the WSS template spectra (17 classes, {:.1} MB), again and again: {read_ms:.3} ms ({read_gb_s:.1} GB/s)",
        (spectra * 8) as f64 / 1e6
    );
    println!(
        "WSS products per trial (17 classes): {quiet:.3} ms with nothing between trials, \
         {evicted:.3} ms with 11 MB written between trials, {grouped:.3} ms with those writes and 4 trials per pass"
    );
    println!(
        "baseline layer products, G products/s, kernel picked / AVX2 only (rows x outputs x inputs): {}",
        products.join(", ")
    );
    println!(
        "EDBN training products (gemm_nn), G products/s, kernel picked / AVX2 only / operands materialised for gemm_nt: {}",
        train.join(", ")
    );
    println!(
        "baseline activations, ns per value: tanh with bias {tanh_ns:.2} (3154 x 30), row softmax {softmax_ns:.2} (3154 x 17)"
    );
}
