//! The ANN's prediction in `f32`: the trained `f64` network
//! ([`super::ann::Mlp`]) rounded to `f32` once, and every frame's
//! `softmax(W2 tanh(W1 x + b1) + b2)` computed in `f32`.
//!
//! # What is computed
//!
//! With `W1`, `b1` the first layer (the input standardisation folded in
//! when [`super::ann::Mlp`] folds it; otherwise the rows arrive
//! standardised in `f64`) and `W2`, `b2` the output layer, each rounded to
//! `f32`, a row `x` (rounded to `f32`: spike counts are exact) gives
//!
//! ```text
//! h_j = tanh32( (b1_j + Σ_{i: x_i ≠ 0} x_i W1_ji) + 0 )   (terms in input order, each fused)
//! o_c = b2_c + Σ_j h_j W2_cj                               (terms in unit order, each fused)
//! p   = softmax(o)                                         (e^{o − max o} over their sum in class order)
//! ```
//!
//! and `p` is returned as `f64`. The order of every sum depends only on the
//! row, so a row gives the same bits alone (live, one frame a hop) and in
//! any batch, and on every path (AVX-512, AVX2, the baseline; test
//! `every_path_and_batch_gives_the_bits_of_one_row`). Rows pass four at a
//! time with AVX-512, two otherwise, for independent chains of additions (one row's chain of `f32`
//! fused adds per output vector waits on each add's latency); the first
//! layer's lists of non-zero inputs are padded to the longest of the pass
//! with a term `0 · 0`, which leaves a sum as it is except a `−0` (made
//! `+0`), and the `+ 0` after the sum makes every `−0` a `+0`, padded or
//! not: the bits of a row alone.
//!
//! `tanh32(z) = sign(z)·(1 − e)/(1 + e)` with `e = e^{−2|z|}`
//! (the EDBN training's `exp_neg`, within 2 ulp of `e^x`, floored at `e^{−87}`):
//! within about `2.5e-7` of `tanh` absolutely (the subtraction `1 − e`
//! loses relative precision for `|z|` near 0, where the error is a few
//! ulp of 1; test `tanh32_is_close_to_tanh`), odd, and exactly `±1` for
//! `|z| > 9`.
//!
//! # Why `f32`
//!
//! Prediction was 3154 x 80 inputs in `f64` on 4 lanes (AVX2) for the ANN
//! (ST) of `benches/peers`: two products and 95 k `tanh` plus 54 k `exp`.
//! In `f32` a vector holds twice the values and the functions cost about
//! half; the network is trained in `f64` (its gradients and early stopping
//! are as before) and only its outputs' last digits move, far below the
//! gaps between a frame's class probabilities that decide the vote. On
//! `benches/peers`' fold 0 (`PEERS_DUMP_SCORES=1`, the builds before and
//! after, 2026-12-07) the probabilities moved by at most 1.6e-6 (ANN (ST);
//! 1.1e-6 ANN (S)), no frame's winning class changed, and the closest two
//! leading classes of any frame were 1.4e-4 apart; no number in RESULTS.md
//! moved. Prediction of that fold's 3154 x 80 vectors (`RAYON_NUM_THREADS=1
//! target/release/examples/peers --out <dir> --seed 1 --only ann_st`): with
//! AVX2 alone (`PALPATE_NO_AVX512=1`) 0.58-0.61 ms in `f64`, 0.39-0.40 ms
//! in `f32`; with AVX-512 0.31 ms in `f64` (its `narrow512` kernel),
//! 0.31-0.33 ms in `f32`.

use super::rbm32::{exp_neg, fma_row, padded, padded_f32, push_nonzeros, LANES};

/// `tanh(z)` in `f32` (module docs).
#[inline(always)]
pub(super) fn tanh32(z: f32) -> f32 {
    let e = exp_neg(-2.0 * z.abs());
    ((1.0 - e) / (1.0 + e)).copysign(z)
}

/// A one-hidden-layer network's prediction in `f32` (module docs).
#[derive(Clone, Debug)]
pub(super) struct Infer32 {
    dim: usize,
    hidden: usize,
    classes: usize,
    /// `hidden` padded to [`LANES`].
    hp: usize,
    /// `classes` padded to [`LANES`].
    kp: usize,
    /// `W1ᵀ`: `dim + 1` rows of `hp` (unit `j` of input `i` at `i·hp + j`);
    /// row `dim` is zero (the padding term's) and so is every padding lane.
    w1t: Vec<f32>,
    /// `b1`, `hp` (padding 0).
    b1: Vec<f32>,
    /// `W2ᵀ`: `hidden` rows of `kp`.
    w2t: Vec<f32>,
    /// `b2`, `kp` (padding 0).
    b2: Vec<f32>,
}

impl Infer32 {
    /// The network `softmax(w2 tanh(w1 x + b1) + b2)`, `w1` row-major
    /// `hidden x dim`, `w2` row-major `classes x hidden` (shorter slices:
    /// the missing values 0).
    pub(super) fn new(
        dim: usize,
        hidden: usize,
        classes: usize,
        w1: &[f64],
        b1: &[f64],
        w2: &[f64],
        b2: &[f64],
    ) -> Self {
        let (hp, kp) = (padded(hidden), padded(classes));
        let mut w1t = vec![0.0f32; (dim + 1) * hp];
        for (j, row) in w1.chunks(dim.max(1)).take(hidden).enumerate() {
            for (i, &w) in row.iter().take(dim).enumerate() {
                w1t[i * hp + j] = w as f32;
            }
        }
        let mut w2t = vec![0.0f32; hidden * kp];
        for (c, row) in w2.chunks(hidden.max(1)).take(classes).enumerate() {
            for (j, &w) in row.iter().take(hidden).enumerate() {
                w2t[j * kp + c] = w as f32;
            }
        }
        Infer32 {
            dim,
            hidden,
            classes,
            hp,
            kp,
            w1t,
            b1: padded_f32(b1, hp),
            w2t,
            b2: padded_f32(b2, kp),
        }
    }

    /// The class probabilities of the first `n` rows of `x` (`dim` wide)
    /// into the rows of `out` (`classes` wide); `n` at most what both hold.
    pub(super) fn scores(&self, x: &[f64], n: usize, out: &mut [f64]) {
        if n == 0 || self.classes == 0 {
            return;
        }
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                // Four rows' accumulators fill 8 of AVX-512's 32 registers
                // (eight rows took 1.5 ms against 0.31-0.33 ms for the ANN
                // (ST)'s 3154 x 80 in `benches/peers`); with AVX2 four rows
                // would fill all 16, and two ran as fast (0.39-0.40 ms).
                if crate::wide::avx512() {
                    self.scores_by::<4>(x, n, out)
                } else {
                    self.scores_by::<2>(x, n, out)
                }
            },
        );
    }

    /// [`Self::scores`], `R` rows a pass (the same bits for every `R`).
    #[inline(always)]
    fn scores_by<const R: usize>(&self, x: &[f64], n: usize, out: &mut [f64]) {
        let (dim, k, hp, kp) = (self.dim, self.classes, self.hp, self.kp);
        let stride = dim + 1;
        let mut xa = vec![0.0f32; R * stride];
        let mut lists: [Vec<u32>; R] = std::array::from_fn(|_| Vec::with_capacity(stride));
        let mut a = vec![0.0f32; R * hp];
        let mut o = vec![0.0f32; R * kp];
        for g in (0..n).step_by(R) {
            let rows = (n - g).min(R);
            // Rows past `n` in the last pass are all zero (their outputs
            // dropped): a list of padding terms alone.
            for (r, list) in lists.iter_mut().enumerate() {
                let xr = &mut xa[r * stride..r * stride + dim];
                if r < rows {
                    let src = &x[(g + r) * dim..(g + r + 1) * dim];
                    xr.iter_mut().zip(src).for_each(|(a, &v)| *a = v as f32);
                } else {
                    xr.iter_mut().for_each(|a| *a = 0.0);
                }
                list.clear();
                push_nonzeros(xr, list);
            }
            let longest = lists.iter().map(Vec::len).max().unwrap_or(0);
            for list in lists.iter_mut() {
                list.resize(longest, dim as u32);
            }
            let mut c0 = 0;
            while c0 < hp {
                if hp - c0 >= 2 * LANES {
                    self.first_block::<R, 2>(&xa, stride, &lists, c0, &mut a);
                    c0 += 2 * LANES;
                } else {
                    self.first_block::<R, 1>(&xa, stride, &lists, c0, &mut a);
                    c0 += LANES;
                }
            }
            lanewise(&mut a, tanh32);
            let mut c0 = 0;
            while c0 < kp {
                if kp - c0 >= 2 * LANES {
                    self.output_block::<R, 2>(&a, c0, &mut o);
                    c0 += 2 * LANES;
                } else {
                    self.output_block::<R, 1>(&a, c0, &mut o);
                    c0 += LANES;
                }
            }
            for r in 0..rows {
                let p = &mut o[r * kp..(r + 1) * kp];
                softmax(p, k);
                let p = &p[..k];
                let dst = &mut out[(g + r) * k..(g + r + 1) * k];
                dst.iter_mut().zip(p.iter()).for_each(|(d, &v)| *d = f64::from(v));
            }
        }
    }

    /// Lanes `c0 .. c0 + V·LANES` of `a ← (b1 + W1 x) + 0` for the `R`
    /// rows of `xa` (`stride` apart), each over its list of inputs (all of
    /// one length); rows `hp` apart in `a`.
    #[inline(always)]
    fn first_block<const R: usize, const V: usize>(
        &self,
        xa: &[f32],
        stride: usize,
        lists: &[Vec<u32>; R],
        c0: usize,
        a: &mut [f32],
    ) {
        let hp = self.hp;
        let mut acc = [[[0.0f32; LANES]; V]; R];
        for row in acc.iter_mut() {
            for (q, v) in row.iter_mut().enumerate() {
                v.copy_from_slice(&self.b1[c0 + q * LANES..c0 + (q + 1) * LANES]);
            }
        }
        let len = lists.iter().map(Vec::len).min().unwrap_or(0);
        // Term `s` of every row's list in turn: `R` independent chains.
        #[allow(clippy::needless_range_loop)]
        for s in 0..len {
            for (r, row) in acc.iter_mut().enumerate() {
                let i = lists[r][s] as usize;
                let at = i * hp + c0;
                fma_row(row, xa[r * stride + i], &self.w1t[at..at + V * LANES]);
            }
        }
        for (r, row) in acc.iter().enumerate() {
            for (q, v) in row.iter().enumerate() {
                let at = r * hp + c0 + q * LANES;
                a[at..at + LANES]
                    .iter_mut()
                    .zip(v)
                    .for_each(|(d, &s)| *d = s + 0.0);
            }
        }
    }

    /// Lanes `c0 .. c0 + V·LANES` of `o ← b2 + W2 a` for the `R` rows of
    /// `a` (`hp` apart); rows `kp` apart in `o`.
    #[inline(always)]
    fn output_block<const R: usize, const V: usize>(&self, a: &[f32], c0: usize, o: &mut [f32]) {
        let (hp, kp) = (self.hp, self.kp);
        let mut acc = [[[0.0f32; LANES]; V]; R];
        for row in acc.iter_mut() {
            for (q, v) in row.iter_mut().enumerate() {
                v.copy_from_slice(&self.b2[c0 + q * LANES..c0 + (q + 1) * LANES]);
            }
        }
        for j in 0..self.hidden {
            let at = j * kp + c0;
            let w = &self.w2t[at..at + V * LANES];
            for (r, row) in acc.iter_mut().enumerate() {
                fma_row(row, a[r * hp + j], w);
            }
        }
        for (r, row) in acc.iter().enumerate() {
            for (q, v) in row.iter().enumerate() {
                let at = r * kp + c0 + q * LANES;
                o[at..at + LANES].copy_from_slice(v);
            }
        }
    }
}

/// `f` of every value of `v` (a multiple of [`LANES`] long), a whole
/// vector at a time (a plain loop over the slice was left scalar).
#[inline(always)]
fn lanewise(v: &mut [f32], f: impl Fn(f32) -> f32) {
    for chunk in v.chunks_exact_mut(LANES) {
        let chunk: &mut [f32; LANES] = match chunk.try_into() {
            Ok(c) => c,
            Err(_) => unreachable!("chunks_exact_mut gives LANES values"),
        };
        for x in chunk.iter_mut() {
            *x = f(*x);
        }
    }
}

/// `p[..k] ← softmax(p[..k])`, `p` padded to a multiple of [`LANES`]: the
/// largest of `p[..k]` in order, `e^{p − max}` of whole vectors (padding
/// lanes too, then ignored), their sum over `p[..k]` in order, each over
/// it.
#[inline(always)]
fn softmax(p: &mut [f32], k: usize) {
    // `>` rather than `f32::max`: the same largest value (a NaN never
    // replaces the running one, which starts at −∞), without `max`'s
    // blend for NaN operands.
    let top = p[..k]
        .iter()
        .fold(f32::NEG_INFINITY, |m, &x| if x > m { x } else { m });
    lanewise(p, |x| exp_neg(x - top));
    let sum: f32 = p[..k].iter().fold(0.0, |s, &x| s + x);
    p[..k].iter_mut().for_each(|x| *x /= sum);
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::Rng;
    use rand_chacha::rand_core::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn tanh32_is_close_to_tanh() {
        let mut zs = vec![
            0.0f32, 1e-30, 1e-8, 1e-4, 0.01, 0.3, 0.5, 0.625, 1.0, 2.0, 4.5, 8.9, 9.1, 20.0, 50.0, 1e30,
        ];
        zs.extend((0..20_000).map(|i| (i as f32 - 10_000.0) * 1.1e-3));
        for z in zs {
            for z in [z, -z] {
                let got = tanh32(z);
                let want = f64::from(z).tanh();
                assert!((f64::from(got) - want).abs() <= 2.5e-7, "{z}: {got} vs {want}");
                assert_eq!(tanh32(-z).to_bits(), (-got).to_bits(), "odd at {z}");
                if z.abs() > 9.0 {
                    assert_eq!(got.abs(), 1.0, "{z}");
                }
            }
        }
        assert_eq!(tanh32(0.0).to_bits(), 0.0f32.to_bits());
        assert_eq!(tanh32(-0.0).to_bits(), (-0.0f32).to_bits());
        assert_eq!(tanh32(f32::INFINITY), 1.0);
        assert_eq!(tanh32(f32::NEG_INFINITY), -1.0);
        assert!(tanh32(f32::NAN).is_nan());
    }

    /// A network of random weights of size `scale` and rows of mostly zero
    /// counts (with some negative and fractional values, as standardised
    /// rows have).
    fn case(
        dim: usize,
        hidden: usize,
        classes: usize,
        n: usize,
        scale: f64,
        seed: u64,
    ) -> (Infer32, Vec<f64>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut draw =
            |len: usize| -> Vec<f64> { (0..len).map(|_| rng.random_range(-scale..scale)).collect() };
        let (w1, b1, w2, b2) = (
            draw(hidden * dim),
            draw(hidden),
            draw(classes * hidden),
            draw(classes),
        );
        let net = Infer32::new(dim, hidden, classes, &w1, &b1, &w2, &b2);
        let mut rng = ChaCha8Rng::seed_from_u64(seed + 1);
        let x = (0..n * dim)
            .map(|_| match rng.random_range(0..10) {
                0..=5 => 0.0,
                6 => -rng.random_range(0.0..2.0),
                7 => rng.random_range(0.0..2.0),
                _ => rng.random_range(1..6) as f64,
            })
            .collect();
        (net, x)
    }

    fn bits(v: &[f64]) -> Vec<u64> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// A batch gives every row the bits of that row scored alone, on every
    /// path this CPU has (AVX-512 passes four rows at a time, AVX2 two, the
    /// baseline two, and the last pass of a batch is partial).
    #[test]
    fn every_path_and_batch_gives_the_bits_of_one_row() {
        let shapes = [
            (80, 30, 17),
            (16, 30, 17),
            (7, 5, 4),
            (3, 40, 33),
            (1, 1, 1),
            (0, 3, 2),
        ];
        for (s, &(d, h, k)) in shapes.iter().enumerate() {
            for n in [1, 2, 3, 5, 8, 67] {
                let (net, x) = case(d, h, k, n, 1.0, 10 * s as u64 + n as u64);
                let mut batch = vec![0.0; n * k];
                net.scores(&x, n, &mut batch);
                for i in 0..n {
                    let mut one = vec![0.0; k];
                    net.scores(&x[i * d..(i + 1) * d], 1, &mut one);
                    assert_eq!(
                        bits(&one),
                        bits(&batch[i * k..(i + 1) * k]),
                        "{d}x{h}x{k}, n {n}, row {i}"
                    );
                }
                let score = || {
                    let mut o = vec![0.0; n * k];
                    net.scores(&x, n, &mut o);
                    o
                };
                let without = crate::wide::without_avx512(score);
                assert_eq!(
                    bits(&without),
                    bits(&batch),
                    "without AVX-512: {d}x{h}x{k}, n {n}"
                );
                let baseline = crate::wide::baseline_only(score);
                assert_eq!(bits(&baseline), bits(&batch), "baseline: {d}x{h}x{k}, n {n}");
            }
        }
    }

    proptest! {
        /// Probabilities for any finite rows and weights of sizes far past
        /// a trained network's: finite, in [0, 1], summing to 1.
        #[test]
        fn scores_are_probabilities(
            d in 1usize..20, h in 1usize..40, k in 1usize..20, n in 1usize..9,
            scale in prop_oneof![Just(0.1), Just(1.0), Just(1e3)],
            seed in 0u64..1000,
        ) {
            let (net, x) = case(d, h, k, n, scale, seed);
            let x: Vec<f64> = x.iter().map(|v| v * 1e4).collect();
            let mut p = vec![0.0; n * k];
            net.scores(&x, n, &mut p);
            for row in p.chunks_exact(k) {
                prop_assert!(row.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v)), "{:?}", row);
                let sum: f64 = row.iter().sum();
                prop_assert!((sum - 1.0).abs() <= 1e-5, "sum {}", sum);
            }
        }
    }
}
