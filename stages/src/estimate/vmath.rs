//! The exponential the trained baselines use ([`exp`]), written so that a
//! loop over a slice vectorises and gives the same bits as the scalar call,
//! and the activations built on it ([`tanh`], [`sigmoid`], [`softmax`]).
//!
//! Why not `f64::exp`: it is a call into the C library per value (glibc's
//! `exp`, ~15-20 ns through its wrapper on this machine's shared cores),
//! which no loop can vectorise; the baselines evaluate hundreds of
//! thousands of them per prediction (an RBF kernel value per support
//! vector, a `tanh` per hidden unit, a softmax per class), and they were
//! the largest single cost of several predictions. glibc also picks an FMA
//! or a non-FMA variant at run time, so its bits depended on the CPU; this
//! one does not.
//!
//! The method (Cody and Waite's reduction, as in fdlibm):
//!
//! ```text
//! k = round(x / ln 2)                  (fma(x, log2 e, 1.5·2^52) − 1.5·2^52)
//! r = fma(−k, ln2_lo, fma(−k, ln2_hi, x))   |r| ≤ ln2/2 + ε, ln2_hi·k exact
//! e^r ≈ 1 + r + r²·(1/2! + r/3! + … + r^11/13!)   (Taylor to degree 13,
//!                                       Estrin's scheme;
//!                                       truncation < 5e-18 on |r| ≤ 0.35)
//! e^x = e^r · 2^k1 · 2^k2,             k1 = round(k/2), k2 = k − k1
//! ```
//!
//! Splitting the scale into two powers of two keeps both normal for every
//! `k` in range, so results that overflow give `+inf` and results in the
//! subnormal range round once more, gradually, to the subnormal or zero.
//! Inputs are clamped to `[−745.2, 709.8]` first (beyond them the result is
//! `0` or `+inf` anyway), and NaN passes through. The error is within about
//! 1 ulp of the correctly rounded value (tested against `f64::exp` over the
//! whole range).
//!
//! Bits: only IEEE additions, multiplications, fused multiply-adds
//! (`mul_add`: each a single correctly rounded operation), comparisons and
//! integer shifts of the bit pattern, so every path -- scalar, SSE2, AVX2,
//! AVX-512 -- rounds identically: a frame scored alone and a batch give the
//! same bits on every x86-64 machine. Fused since 2026-11-27 (the
//! polynomial's pairs and the reduction; about a quarter fewer operations:
//! `tanh` 1.71 -> 1.25 ns a value in `cargo run --release --example
//! machine`). Where a function is not compiled with FMA, `mul_add` is a call
//! into the C library's exact `fma`, 15 an exponential: so every call
//! in a loop runs inside [`crate::wide::with_avx2`] (whose AVX2 function
//! enables FMA), the scalar [`softmax`] included.
//!
//! Two shortcuts with the same bits (2026-11-28, each proptested against
//! the form it replaced): [`tanh`] clamps its exponential's argument at
//! `−40` and scales it by one power of two (its argument is never
//! positive), and the softmax takes each row's maximum in eight lanes
//! ([`row_max`]) instead of a fold over `f64::max`. `cargo run --release
//! --example machine` (its last line; four runs of each build alternated,
//! 2026-11-28): `tanh` with its bias 1.30-1.36 -> 1.11-1.14 ns a value, the
//! row softmax of 17 1.81-1.90 -> 1.51-1.60.

/// `1.5·2^52`: adding it rounds a double below `2^51` in magnitude to an
/// integer (round half to even), which subtracting it recovers exactly.
const SHIFT: f64 = 6_755_399_441_055_744.0;
/// `ln 2`'s leading 32 bits (fdlibm's `ln2_hi`): `k·LN2_HI` is exact for `|k| < 2^21`.
const LN2_HI: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000);
/// `ln 2 − LN2_HI` (fdlibm's `ln2_lo`).
const LN2_LO: f64 = f64::from_bits(0x3dea_39ef_3579_3c76);
/// Below this `e^x` rounds to 0 (the smallest subnormal is `e^−744.44`).
const X_MIN: f64 = -745.2;
/// Above this `e^x` overflows (`ln f64::MAX ≈ 709.78`).
const X_MAX: f64 = 709.8;

/// `2^n` for an integer-valued `n` in `[−1022, 1023]`, from its bit pattern:
/// `n + 1023 + 1.5·2^52` holds `n + 1023` in its low 11 bits, which the
/// shift moves into the exponent field (the rest shifts out).
#[inline(always)]
fn pow2(n: f64) -> f64 {
    f64::from_bits((n + (SHIFT + 1023.0)).to_bits() << 52)
}

/// `e^x`, within about 1 ulp, with the same bits in every vector width (see
/// the module docs). `exp(NaN)` is NaN, `exp(−inf) = 0`, `exp(+inf) = +inf`.
#[inline(always)]
pub fn exp(x: f64) -> f64 {
    // NaN passes through the clamp (and is returned at the end).
    let xc = x.clamp(X_MIN, X_MAX);
    let (p, k) = exp_parts(xc);
    let k1 = (k * 0.5 + SHIFT) - SHIFT;
    let y = p * pow2(k1) * pow2(k - k1);
    if x.is_nan() {
        x
    } else {
        y
    }
}

/// `e^x` for `x` in `[−40, 0]`, with [`exp`]'s bits there: `k` is then in
/// `[−58, 0]`, where one power of two scales `p` exactly, as [`exp`]'s two
/// do (both products are exact in the normal range). No clamp, no NaN
/// test: the caller's. For [`tanh`], whose exponential is always there.
#[inline(always)]
fn exp_small_nonpositive(x: f64) -> f64 {
    let (p, k) = exp_parts(x);
    p * pow2(k)
}

/// [`exp`]'s reduction and polynomial: `(e^r, k)` with `x = k·ln 2 + r`.
#[inline(always)]
fn exp_parts(xc: f64) -> (f64, f64) {
    let k = xc.mul_add(std::f64::consts::LOG2_E, SHIFT) - SHIFT;
    let r = (-k).mul_add(LN2_LO, (-k).mul_add(LN2_HI, xc));
    // q = Σ_{i=2..13} r^(i-2)/i! by Estrin's scheme: a dependency chain of
    // 6 operations after `r` instead of Horner's 12, so a lone scalar call
    // is not latency-bound; the vector paths evaluate the same expression,
    // so the bits are the same.
    let r2 = r * r;
    let r4 = r2 * r2;
    let r8 = r4 * r4;
    let a0 = r.mul_add(1.0 / 6.0, 1.0 / 2.0);
    let a1 = r.mul_add(1.0 / 120.0, 1.0 / 24.0);
    let a2 = r.mul_add(1.0 / 5_040.0, 1.0 / 720.0);
    let a3 = r.mul_add(1.0 / 362_880.0, 1.0 / 40_320.0);
    let a4 = r.mul_add(1.0 / 39_916_800.0, 1.0 / 3_628_800.0);
    let a5 = r.mul_add(1.0 / 6_227_020_800.0, 1.0 / 479_001_600.0);
    let q = r8.mul_add(
        r2.mul_add(a5, a4),
        r4.mul_add(r2.mul_add(a3, a2), r2.mul_add(a1, a0)),
    );
    (1.0 + r2.mul_add(q, r), k)
}

/// `tanh x = sign(x)·(1 − e)/(1 + e)` with `e = exp(−2|x|)`: one
/// exponential. Within a few ulps of the C library's `tanh` in absolute
/// terms (relative accuracy degrades only where `|x|` is tiny and the value
/// is too).
///
/// The exponential's argument is clamped at `−40` first: `e^−40 < 2^−54`,
/// and for any `e` below that `1 − e` and `1 + e` both round to 1, so the
/// result is `±1` whether `e` is `e^−40` or smaller: the bits of the
/// unclamped formula, with the cheaper `exp_small_nonpositive` (about a
/// fifth fewer operations than [`exp`]: no upper clamp, one scaling).
#[inline(always)]
pub fn tanh(x: f64) -> f64 {
    let e = exp_small_nonpositive((-2.0 * x.abs()).max(TANH_FLOOR));
    let t = ((1.0 - e) / (1.0 + e)).copysign(x);
    if x.is_nan() {
        x
    } else {
        t
    }
}

/// Where [`tanh`] clamps its exponential's argument (see there).
const TANH_FLOOR: f64 = -40.0;

/// The logistic function `1/(1 + e^−z)`, never overflowing: for `z < 0` it
/// is computed as `e^z/(1 + e^z)`. Finite for every finite `z`; in `[0, 1]`.
#[inline(always)]
pub fn sigmoid(z: f64) -> f64 {
    let e = exp(-z.abs());
    if z >= 0.0 {
        1.0 / (1.0 + e)
    } else {
        e / (1.0 + e)
    }
}

/// The largest non-NaN value of `row` (`−inf` when there is none): the
/// value of `row.iter().fold(f64::NEG_INFINITY, f64::max)`, in eight
/// independent lanes.
///
/// Why: the fold is one dependent chain of a compare and a blend per value
/// (`f64::max`'s NaN rule): in a throwaway timing of a softmax's passes
/// (3154 rows of 17, one core, not kept) the maximum and shift took 0.58
/// ns a value of 1.89, 0.21 in lanes (the module docs' figures are the
/// committed `machine` example's). A maximum does not
/// depend on the order it is taken in, and a select `v > m` skips NaN as
/// `f64::max` does (the lanes start at `−inf`, so they never hold NaN), so
/// the lanes give the same value. Only the sign of a zero maximum may
/// differ, which no caller can see: they subtract it from every value, and
/// `v − 0` and `v + 0` differ only for `v = ±0`, whose `exp` is 1 either way.
#[inline(always)]
pub fn row_max(row: &[f64]) -> f64 {
    #[inline(always)]
    fn larger(a: f64, b: f64) -> f64 {
        if b > a {
            b
        } else {
            a
        }
    }
    let mut l = [f64::NEG_INFINITY; 8];
    let mut chunks = row.chunks_exact(8);
    for c in &mut chunks {
        for j in 0..8 {
            l[j] = larger(l[j], c[j]);
        }
    }
    for j in 0..4 {
        l[j] = larger(l[j], l[j + 4]);
    }
    let m = larger(larger(l[0], l[2]), larger(l[1], l[3]));
    chunks.remainder().iter().fold(m, |m, &v| larger(m, v))
}

/// In-place softmax, shifted by the maximum so it never overflows. Runs in
/// [`crate::wide::with_avx2`], so the fused `exp` is the FMA instruction.
#[inline]
pub fn softmax(z: &mut [f64]) {
    crate::wide::with_avx2(
        #[inline(always)]
        || {
            let m = row_max(z);
            let mut sum = 0.0;
            for v in z.iter_mut() {
                *v = exp(*v - m);
                sum += *v;
            }
            z.iter_mut().for_each(|v| *v /= sum);
        },
    )
}

/// [`softmax`] of every `k`-wide row of `z`, with the same bits, the
/// exponentials of all rows in one vectorised pass.
///
/// All three passes run inside [`crate::wide::with_avx2`]: the divisions by
/// each row's sum were the largest cost of a batch when compiled for the
/// SSE2 baseline (two lanes per `divpd`; perf on the logistic predictions of
/// `benches/peers`), and a division rounds the same at any width.
pub fn softmax_rows(z: &mut [f64], k: usize) {
    let k = k.max(1);
    let whole = z.len() / k * k;
    let z = &mut z[..whole];
    crate::wide::with_avx2(
        #[inline(always)]
        || {
            for row in z.chunks_exact_mut(k) {
                let m = row_max(row);
                row.iter_mut().for_each(|v| *v -= m);
            }
            z.iter_mut().for_each(|x| *x = exp(*x));
            for row in z.chunks_exact_mut(k) {
                let mut sum = 0.0;
                row.iter().for_each(|v| sum += v);
                row.iter_mut().for_each(|v| *v /= sum);
            }
        },
    );
}

/// `v ← exp(v)` for every entry, vectorised ([`crate::wide::with_avx2`]).
pub fn exp_in_place(v: &mut [f64]) {
    crate::wide::with_avx2(
        #[inline(always)]
        || v.iter_mut().for_each(|x| *x = exp(*x)),
    );
}

/// `v ← exp(−γ·v)` for every entry (RBF kernel values from squared
/// distances), vectorised.
pub fn rbf_in_place(v: &mut [f64], gamma: f64) {
    crate::wide::with_avx2(
        #[inline(always)]
        || v.iter_mut().for_each(|x| *x = exp(-gamma * *x)),
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Distance in units in the last place (both finite, same sign).
    fn ulps(a: f64, b: f64) -> u64 {
        (a.to_bits() as i64 - b.to_bits() as i64).unsigned_abs()
    }

    #[test]
    fn matches_the_library_exp_within_an_ulp_over_the_range() {
        let mut worst = 0;
        let n = 200_000;
        for i in 0..=n {
            let x = -708.0 + 1417.0 * i as f64 / n as f64;
            let (a, b) = (exp(x), x.exp());
            if b.is_finite() && b > f64::MIN_POSITIVE {
                worst = worst.max(ulps(a, b));
            }
        }
        // Near 0, where the reduction does nothing, finely.
        for i in -10_000..=10_000 {
            let x = i as f64 * 1e-4;
            worst = worst.max(ulps(exp(x), x.exp()));
        }
        assert!(worst <= 1, "worst error {worst} ulp");
    }

    #[test]
    fn edges_overflow_underflow_and_specials() {
        assert_eq!(exp(0.0), 1.0);
        assert_eq!(exp(-0.0), 1.0);
        assert_eq!(exp(f64::INFINITY), f64::INFINITY);
        assert_eq!(exp(f64::NEG_INFINITY), 0.0);
        assert!(exp(f64::NAN).is_nan());
        assert_eq!(exp(709.79), f64::INFINITY);
        assert_eq!(exp(1e300), f64::INFINITY);
        assert_eq!(exp(-1e300), 0.0);
        assert_eq!(exp(-746.0), 0.0);
        // The largest finite result and the subnormal range are reached.
        let big = exp(709.78);
        assert!(big.is_finite() && big > 1.7e308, "{big}");
        let tiny = exp(-740.0);
        assert!(tiny > 0.0 && tiny < f64::MIN_POSITIVE);
        let rel = (tiny - (-740.0f64).exp()).abs() / (-740.0f64).exp();
        assert!(rel < 1e-10, "subnormal result off by {rel}");
        // exp(1) is e within an ulp.
        assert!(ulps(exp(1.0), std::f64::consts::E) <= 1);
    }

    #[test]
    fn activations_are_finite_and_bounded_everywhere() {
        for z in [
            -1e308,
            -800.0,
            -40.0,
            -1e-300,
            0.0,
            1e-300,
            40.0,
            800.0,
            1e308,
            f64::MAX,
        ] {
            let s = sigmoid(z);
            assert!((0.0..=1.0).contains(&s), "sigmoid({z}) = {s}");
            let t = tanh(z);
            assert!((-1.0..=1.0).contains(&t), "tanh({z}) = {t}");
            assert!((t - z.tanh()).abs() < 1e-15, "tanh({z})");
        }
        let mut z = [1e308, -1e308, 0.0, 700.0];
        softmax(&mut z);
        assert!(z.iter().all(|p| p.is_finite()));
        assert!((z.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        // Rows at once: the bits of row by row (a ragged tail is left alone).
        let rows: Vec<f64> = (0..3 * 17 + 2)
            .map(|i| ((i * 37 % 101) as f64 - 50.0) * 0.7)
            .collect();
        let mut batch = rows.clone();
        softmax_rows(&mut batch, 17);
        for (b, r) in batch.chunks_exact(17).zip(rows.chunks_exact(17)) {
            let mut one = r.to_vec();
            softmax(&mut one);
            assert_eq!(
                b.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                one.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
            );
        }
        assert_eq!(batch[51..], rows[51..]);
    }

    /// The bits of `v`, every NaN as one.
    fn canon(v: f64) -> u64 {
        if v.is_nan() {
            f64::NAN.to_bits()
        } else {
            v.to_bits()
        }
    }

    proptest! {
        /// The batch form (every row's exponentials in one pass) gives
        /// [`softmax`]'s bits row by row for any values (NaN, infinities,
        /// signed zeros, ties), any width and any row count (a ragged tail
        /// left alone), on every path. A
        /// NaN is compared as NaN: Rust leaves the sign and payload of a
        /// NaN produced by arithmetic unspecified (the compiler may swap
        /// the operands of an addition), so no two compilations promise them.
        #[test]
        fn softmax_rows_gives_the_bits_of_each_row(
            k in 1usize..24,
            xs in prop::collection::vec(
                prop_oneof![
                    -800.0f64..800.0,
                    Just(0.0),
                    Just(-0.0),
                    Just(3.0),
                    Just(f64::NAN),
                    Just(f64::INFINITY),
                    Just(f64::NEG_INFINITY),
                    any::<f64>(),
                ],
                0..400,
            ),
        ) {
            let expect: Vec<u64> = xs
                .chunks(k)
                .flat_map(|r| {
                    let mut one = r.to_vec();
                    if one.len() == k {
                        softmax(&mut one);
                    }
                    one.into_iter().map(canon)
                })
                .collect();
            let run = || {
                let mut v = xs.clone();
                softmax_rows(&mut v, k);
                v.into_iter().map(canon).collect::<Vec<_>>()
            };
            prop_assert_eq!(&run(), &expect);
            prop_assert_eq!(&crate::wide::without_avx512(run), &expect);
            prop_assert_eq!(&crate::wide::baseline_only(run), &expect);
        }

        /// [`tanh`] (its exponential clamped and scaled once) gives the
        /// bits of the formula over the full [`exp`] for any input, on
        /// every path, NaN compared as NaN.
        #[test]
        fn tanh_is_the_formula_over_the_full_exp(
            xs in prop::collection::vec(
                prop_oneof![
                    -25.0f64..25.0,
                    -1e-3f64..1e-3,
                    18.0f64..22.0,
                    Just(0.0),
                    Just(-0.0),
                    Just(f64::NAN),
                    Just(f64::INFINITY),
                    Just(f64::NEG_INFINITY),
                    Just(f64::MIN_POSITIVE / 4.0),
                    any::<f64>(),
                ],
                0..40,
            ),
        ) {
            let formula = |x: f64| {
                crate::wide::with_avx2(|| {
                    let e = exp(-2.0 * x.abs());
                    ((1.0 - e) / (1.0 + e)).copysign(x)
                })
            };
            let run = || {
                let mut v = xs.clone();
                crate::wide::with_avx2(|| v.iter_mut().for_each(|x| *x = tanh(*x)));
                v
            };
            for got in [run(), crate::wide::without_avx512(run), crate::wide::baseline_only(run)] {
                for (x, t) in xs.iter().zip(got) {
                    prop_assert_eq!(canon(t), canon(formula(*x)), "tanh({})", x);
                }
            }
        }

        /// [`row_max`] is the fold over `f64::max` it replaced (compared by
        /// value: the sign of a zero maximum may differ), and the softmax
        /// built on it gives the bits of one shifted by the fold's maximum,
        /// for any values (NaN, infinities, signed zeros) and length.
        #[test]
        fn row_max_is_the_fold_of_f64_max(
            xs in prop::collection::vec(
                prop_oneof![
                    -800.0f64..800.0,
                    Just(0.0),
                    Just(-0.0),
                    Just(f64::NAN),
                    Just(f64::INFINITY),
                    Just(f64::NEG_INFINITY),
                    any::<f64>(),
                ],
                0..40,
            ),
        ) {
            let fold = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let m = row_max(&xs);
            prop_assert!(m == fold, "row_max {} vs fold {}", m, fold);
            // The softmax before `row_max`, spelled out.
            let mut expect = xs.clone();
            crate::wide::with_avx2(|| {
                let mut sum = 0.0;
                for v in expect.iter_mut() {
                    *v = exp(*v - fold);
                    sum += *v;
                }
                expect.iter_mut().for_each(|v| *v /= sum);
            });
            let mut got = xs.clone();
            softmax(&mut got);
            prop_assert_eq!(
                got.into_iter().map(canon).collect::<Vec<_>>(),
                expect.into_iter().map(canon).collect::<Vec<_>>()
            );
        }

        /// The vectorised slice call gives the scalar call's bits for any
        /// input, NaN and infinities included, at every position (the
        /// scalar tail after the vector body as well).
        #[test]
        fn slice_and_scalar_give_the_same_bits(
            xs in prop::collection::vec(
                prop_oneof![
                    -800.0f64..800.0,
                    -1.0f64..1.0,
                    Just(f64::NAN),
                    Just(f64::INFINITY),
                    Just(f64::NEG_INFINITY),
                    any::<f64>(),
                ],
                0..67,
            ),
            gamma in 0.0f64..3.0,
        ) {
            let mut v = xs.clone();
            exp_in_place(&mut v);
            let mut w = xs.clone();
            rbf_in_place(&mut w, gamma);
            let base = crate::wide::baseline_only(|| {
                let mut b = xs.clone();
                exp_in_place(&mut b);
                b
            });
            for (i, &x) in xs.iter().enumerate() {
                let e = exp(x);
                prop_assert_eq!(v[i].to_bits(), e.to_bits(), "exp({}) at {}", x, i);
                prop_assert_eq!(base[i].to_bits(), e.to_bits());
                prop_assert_eq!(w[i].to_bits(), exp(-gamma * x).to_bits());
                if x.is_finite() && e.is_finite() && e > f64::MIN_POSITIVE {
                    prop_assert!(ulps(e, x.exp()) <= 1, "exp({}) = {} vs {}", x, e, x.exp());
                }
            }
        }
    }
}
