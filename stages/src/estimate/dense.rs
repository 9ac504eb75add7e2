//! Small dense kernels shared by the trained baselines: row-against-row
//! products `C = A Bᵀ` (`C[i][j] = a_i · b_j`) and squared distances
//! (`C[i][j] = ‖a_i − b_j‖²`) of row-major `f64` matrices.
//!
//! Why by hand rather than `matrixmultiply`/`gemm`: those crates pick a
//! kernel (and with it a summation order) at run time, so the bits of every
//! dot product would depend on the CPU, and a single-row call (a stream's
//! frame) could differ from the batch call over the same row. Here every
//! entry is computed exactly as the scalar [`dot`] / [`sq_dist`] compute it:
//! four partial sums over chunks of four, each term fused into its partial
//! sum (`s_l ← fma(x, y, s_l)`, or `fma(d, d, s_l)` with `d = x − y`: one
//! rounding per term), reduced as `(s0 + s1) + (s2 + s3)`, then the
//! remainder fused in order. So a frame scored alone, a batch, the AVX-512,
//! AVX2 and baseline paths all give the same bits on every x86-64 CPU.
//!
//! Fused, since 2026-11-27 (before, a separate multiply and add, two
//! roundings per term): a fused multiply-add is a single correctly rounded
//! operation wherever it runs (the FMA instruction, which the vector paths
//! require with AVX2, or `f64::mul_add`, which on a CPU without one is the
//! C library's exact software `fma`), so fusing keeps the bit rule above
//! while doing a product's two operations in one: the layer products ran at
//! about 60 % of the unfused limit, and the prediction of the ANN (ST) and
//! the EDBN were ~45 % products. Every baseline that uses these kernels
//! (ANN, EDBN, SVM, k-NN's exact distances, logistic regression) changed in
//! its last bits then; RESULTS.md says what that moved. The speed comes
//! from register tiling: a tile of 2 rows
//! of `A` against 4 rows of `B` keeps 8 four-lane accumulators in registers
//! and loads each chunk once per tile instead of once per entry, written
//! with AVX intrinsics where the CPU has AVX2 and FMA ([`crate::wide::avx2`];
//! lane `l` is partial sum `l`), and blocks of `B`
//! stay in cache while every row of `A` passes. The shapes here are small
//! (dims 16-80, tens to thousands of rows), where a GEMM's packing would not
//! pay anyway. Measured on the k-NN workload (3154 x 3060 x 80, one core,
//! shared machine): the plain scalar loop ~5 GFLOP/s, these tiles 15-25;
//! each tile's four sums per row are reduced in registers (`hadd` and a
//! lane swap, the same additions), 17-20 GFLOP/s at the EDBN's layer shapes
//! on a loaded 2-core host.
//! A layer's weights (few rows, short) take a second kernel with the same
//! bits, the outputs across the lanes instead of `k` ([`gemm_nt`]); where
//! the CPU has AVX-512 (F, VL, DQ), a third, that kernel with 512-bit
//! vectors and two rows at a time (`narrow512`). The register tiles have
//! an AVX-512 form too (`tile512`: 4 rows of `A` against 4 of `B`, each
//! 512-bit accumulator two pairs' four partial sums side by side), half the
//! vector operations of the AVX2 tiles for the same sums: the SVM's kernel
//! rows and the logistic and RBM gradients' long products (SVM predict
//! -10 %, EDBN and logistic fits -4-5 % in `benches/peers`). Each is tested
//! against the scalar [`dot`] / [`sq_dist`] bit for bit, the AVX2 ones also
//! on an AVX-512 CPU ([`crate::wide::without_avx512`]).
//!
//! [`gemm_nn`] is the same product with the second operand as columns
//! (`b` row-major, `k x n`) and the first read through strides
//! ([`View`]: a matrix or its transpose without a copy), for the RBMs'
//! training minibatches: 20 rows, too few for `narrow512`'s packing, and
//! whose products are `v Wᵀ`, `h W` and `hᵀ v`. Outputs across the lanes
//! as in `narrow512`, the same bits as [`gemm_nt`] over the materialised
//! operands (test `gemm_nn_is_gemm_nt_bit_for_bit`).
//!
//! CPUs with AVX2 and FMA but not AVX-512 have their own forms of the
//! `gemm_nn` kernel (`nn256`: three rows against four columns, 12 of the
//! 16 registers), with the same bits (a zero-skipping product, removed on
//! 2026-12-07 when its last users, the `f64` RBM training and the ANN's
//! prediction, moved to `f32`, had one too). Until 2026-12-02 they materialised both
//! operands for [`gemm_nt`]'s tiles and ran the EDBN's mostly zero rows
//! dense, so its fit took 806-831 ms on an AVX2-only AMD EPYC against 264
//! ms on an AVX-512 one; with them 537-575 ms (`RAYON_NUM_THREADS=1
//! target/release/examples/peers --out /tmp/wk --seed 1 --only edbn`, the
//! same host and hour). `cargo run --release --example machine` prints the
//! training products' rates with each kernel (its "EDBN training
//! products" line).

/// Rows of `A` per tile.
const MR: usize = 2;
/// Rows of `B` per tile.
const NR: usize = 4;

/// Dot product over fixed-width chunks (vectorises) with a fixed summation
/// order, each term fused into its partial sum (module docs), so the same
/// bits on every run and every path.
#[inline]
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    single_any::<false>(a, b)
}

/// `‖a − b‖²` with four partial sums in a fixed order, each squared
/// difference fused into its sum (same bits everywhere).
#[inline]
pub fn sq_dist(a: &[f64], b: &[f64]) -> f64 {
    single_any::<true>(a, b)
}

/// [`single_fused`] inside [`crate::wide::with_avx2`], whose function
/// enables FMA, so `mul_add` is the instruction; on the baseline path it is
/// the C library's `fma` (exact, the same bits, a call per term: slow, and
/// only where no vector path runs).
#[inline]
fn single_any<const SQ: bool>(a: &[f64], b: &[f64]) -> f64 {
    crate::wide::with_avx2(
        #[inline(always)]
        || single_fused::<SQ>(a, b),
    )
}

/// The reference order: `s_l ← fma(x_t, y_t, s_l)` for `t ≡ l (mod 4)`
/// over the whole chunks, `(s0 + s1) + (s2 + s3)`, then the remaining
/// terms fused in order ([`madd`]).
#[inline(always)]
fn single_fused<const SQ: bool>(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let ca = a.chunks_exact(4);
    let cb = b.chunks_exact(4);
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for l in 0..4 {
            acc[l] = madd::<SQ>(x[l], y[l], acc[l]);
        }
    }
    let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for (&x, &y) in ra.iter().zip(rb) {
        s = madd::<SQ>(x, y, s);
    }
    s
}

/// One entry's term fused into the sum `s`: `fma(x, y, s)`, or
/// `fma(d, d, s)` with `d = x − y` for a squared distance.
#[inline(always)]
fn madd<const SQ: bool>(x: f64, y: f64, s: f64) -> f64 {
    if SQ {
        let d = x - y;
        d.mul_add(d, s)
    } else {
        x.mul_add(y, s)
    }
}

/// The full tile: rows `a[0..MR]` against rows `b[0..NR]`, each `k` long;
/// entry `(r, c)` goes to `out[r][c]`, with the bits of [`dot`] / [`sq_dist`].
#[inline(always)]
fn tile<const SQ: bool, const AVX: bool>(a: [&[f64]; MR], b: [&[f64]; NR], k: usize) -> [[f64; NR]; MR] {
    #[cfg(target_arch = "x86_64")]
    if AVX {
        // SAFETY: AVX is only requested from `pairwise_avx`, which runs after
        // the run-time check; every load reads 4 doubles below `k / 4 * 4`
        // of rows at least `k` long.
        return unsafe { tile_avx::<SQ>(a, b, k) };
    }
    let mut out = [[0.0f64; NR]; MR];
    for r in 0..MR {
        for c in 0..NR {
            out[r][c] = single::<SQ>(&a[r][..k], &b[c][..k]);
        }
    }
    out
}

/// [`tile`] with 256-bit vectors: lane `l` of each accumulator is partial
/// sum `l` of the scalar kernels, each term fused as theirs is, so the bits
/// are theirs.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2,fma")]
unsafe fn tile_avx<const SQ: bool>(a: [&[f64]; MR], b: [&[f64]; NR], k: usize) -> [[f64; NR]; MR] {
    use std::arch::x86_64::*;
    let full = k / 4 * 4;
    for r in a.iter().chain(&b) {
        assert!(r.len() >= k);
    }
    let mut acc = [[_mm256_setzero_pd(); NR]; MR];
    let (pa, pb) = (a.map(<[f64]>::as_ptr), b.map(<[f64]>::as_ptr));
    let mut p = 0;
    while p < full {
        // SAFETY: p + 4 <= full <= k <= every row's length (asserted above).
        let av: [__m256d; MR] = std::array::from_fn(|r| unsafe { _mm256_loadu_pd(pa[r].add(p)) });
        for c in 0..NR {
            // SAFETY: as above.
            let bv = unsafe { _mm256_loadu_pd(pb[c].add(p)) };
            for r in 0..MR {
                acc[r][c] = if SQ {
                    let d = _mm256_sub_pd(av[r], bv);
                    _mm256_fmadd_pd(d, d, acc[r][c])
                } else {
                    _mm256_fmadd_pd(av[r], bv, acc[r][c])
                };
            }
        }
        p += 4;
    }
    let mut out = [[0.0f64; NR]; MR];
    const { assert!(NR == 4) };
    // Padding the ragged edges into whole tiles was tried and was slower
    // (the extra branches in the tile loop cost more than the scalar edge
    // columns saved).
    for r in 0..MR {
        out[r] = reduce_row::<SQ>(acc[r], a[r], b, full, k);
    }
    out
}

/// One tile row's four entries from their four-lane accumulators (lane `l`
/// partial sum `l`): `(q0 + q1) + (q2 + q3)` of each, then the terms past
/// the last whole chunk (`full..k`) fused in order: [`dot`]'s / [`sq_dist`]'s
/// operations.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2,fma")]
fn reduce_row<const SQ: bool>(
    acc: [std::arch::x86_64::__m256d; NR],
    a: &[f64],
    b: [&[f64]; NR],
    full: usize,
    k: usize,
) -> [f64; NR] {
    use std::arch::x86_64::*;
    // `(q0 + q1) + (q2 + q3)` of the four entries at once: `hadd` gives
    // `[c0: q0+q1, c1: q0+q1, c0: q2+q3, c1: q2+q3]` (and likewise for
    // columns 2 and 3), the lane swaps line the halves up. The same
    // additions as the scalar reduction, without storing and reloading
    // each accumulator (6-9% off the products at the peers shapes in a
    // same-process comparison while it was written; too small for the
    // shared machine's peers runs to show).
    let x = _mm256_hadd_pd(acc[0], acc[1]);
    let y = _mm256_hadd_pd(acc[2], acc[3]);
    let s = _mm256_add_pd(
        _mm256_permute2f128_pd::<0x20>(x, y),
        _mm256_permute2f128_pd::<0x31>(x, y),
    );
    let mut out = [0.0f64; NR];
    // SAFETY: out holds NR = 4 doubles.
    unsafe { _mm256_storeu_pd(out.as_mut_ptr(), s) };
    for (c, o) in out.iter_mut().enumerate() {
        for t in full..k {
            *o = madd::<SQ>(a[t], b[c][t], *o);
        }
    }
    out
}

/// [`tile`] with 512-bit vectors, four rows of `a` against four of `b`:
/// each accumulator holds two pairs' four partial sums (lanes 0-3 row `r`
/// against `b[2h]`, lanes 4-7 against `b[2h + 1]`; `a`'s chunk is
/// broadcast to both halves), so every lane is still partial sum `l` of one
/// pair, added in the same order, and the halves are reduced as
/// [`tile_avx`] reduces its accumulators: the bits of [`dot`] /
/// [`sq_dist`]. Half the vector operations of two AVX2 tiles.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2,fma,avx512f,avx512vl,avx512dq")]
unsafe fn tile512<const SQ: bool>(a: [&[f64]; R512], b: [&[f64]; NR], k: usize) -> [[f64; NR]; R512] {
    use std::arch::x86_64::*;
    const { assert!(NR == 4) };
    let full = k / 4 * 4;
    for r in a.iter().chain(&b) {
        assert!(r.len() >= k);
    }
    let mut acc = [[_mm512_setzero_pd(); 2]; R512];
    let (pa, pb) = (a.map(<[f64]>::as_ptr), b.map(<[f64]>::as_ptr));
    let mut p = 0;
    while p < full {
        // SAFETY (loads): p + 4 <= full <= k <= every row's length.
        let bv: [__m512d; 2] = std::array::from_fn(|h| unsafe {
            _mm512_insertf64x4::<1>(
                _mm512_castpd256_pd512(_mm256_loadu_pd(pb[2 * h].add(p))),
                _mm256_loadu_pd(pb[2 * h + 1].add(p)),
            )
        });
        for r in 0..R512 {
            let av = _mm512_broadcast_f64x4(unsafe { _mm256_loadu_pd(pa[r].add(p)) });
            for h in 0..2 {
                acc[r][h] = if SQ {
                    let d = _mm512_sub_pd(av, bv[h]);
                    _mm512_fmadd_pd(d, d, acc[r][h])
                } else {
                    _mm512_fmadd_pd(av, bv[h], acc[r][h])
                };
            }
        }
        p += 4;
    }
    let mut out = [[0.0f64; NR]; R512];
    for r in 0..R512 {
        let c = [
            _mm512_castpd512_pd256(acc[r][0]),
            _mm512_extractf64x4_pd::<1>(acc[r][0]),
            _mm512_castpd512_pd256(acc[r][1]),
            _mm512_extractf64x4_pd::<1>(acc[r][1]),
        ];
        out[r] = reduce_row::<SQ>(c, a[r], b, full, k);
    }
    out
}

/// Rows of `A` per [`tile512`].
const R512: usize = 4;

/// Every entry of `out` (rows `ldc` apart) from tiles of `R` rows of `a`
/// against [`NR`] rows of `b` (`tile`), the ragged edges entry by entry.
#[inline(always)]
fn pairwise_tiled<const SQ: bool, const R: usize>(
    a: &[f64],
    b: &[f64],
    k: usize,
    out: &mut [f64],
    ldc: usize,
    tile: impl Fn([&[f64]; R], [&[f64]; NR], usize) -> [[f64; NR]; R],
) {
    fn row(x: &[f64], i: usize, k: usize) -> &[f64] {
        &x[i * k..(i + 1) * k]
    }
    let k1 = k.max(1);
    let m = a.len() / k1;
    let n = b.len() / k1;
    assert!(ldc >= n && (m == 0 || out.len() >= (m - 1) * ldc + n));
    // Blocks of `jb` rows of `b` (~32 KB) stay in cache while every row of
    // `a` passes over them (without blocking, a large `b` streamed from
    // memory once per pair of rows of `a`, at half the speed).
    let jb = (4096 / k1).clamp(NR, 256) / NR * NR;
    let mut j0 = 0;
    while j0 < n {
        let j1 = (j0 + jb).min(n);
        let mut i = 0;
        while i + R <= m {
            let ar: [&[f64]; R] = std::array::from_fn(|r| row(a, i + r, k));
            let mut j = j0;
            while j + NR <= j1 {
                let br: [&[f64]; NR] = std::array::from_fn(|c| row(b, j + c, k));
                let t = tile(ar, br, k);
                for (r, tr) in t.iter().enumerate() {
                    out[(i + r) * ldc + j..(i + r) * ldc + j + NR].copy_from_slice(tr);
                }
                j += NR;
            }
            for j in j..j1 {
                for (r, a_r) in ar.iter().enumerate() {
                    out[(i + r) * ldc + j] = single::<SQ>(a_r, row(b, j, k));
                }
            }
            i += R;
        }
        for i in i..m {
            for j in j0..j1 {
                out[i * ldc + j] = single::<SQ>(row(a, i, k), row(b, j, k));
            }
        }
        j0 = j1;
    }
}

#[inline(always)]
fn pairwise<const SQ: bool, const AVX: bool>(a: &[f64], b: &[f64], k: usize, out: &mut [f64], ldc: usize) {
    pairwise_tiled::<SQ, MR>(a, b, k, out, ldc, tile::<SQ, AVX>);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn pairwise_avx<const SQ: bool>(a: &[f64], b: &[f64], k: usize, out: &mut [f64], ldc: usize) {
    pairwise::<SQ, true>(a, b, k, out, ldc);
}

/// [`pairwise`] with [`tile512`] over the rows of `a` in fours, the last
/// rows with the AVX2 tiles.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,avx512f,avx512vl,avx512dq")]
unsafe fn pairwise512<const SQ: bool>(a: &[f64], b: &[f64], k: usize, out: &mut [f64], ldc: usize) {
    let m = a.len() / k.max(1);
    let m4 = m / R512 * R512;
    // SAFETY (tiles): this function runs only where the CPU has AVX-512 F,
    // VL and DQ (checked by the caller).
    pairwise_tiled::<SQ, R512>(&a[..m4 * k], b, k, out, ldc, |ar, br, k| unsafe {
        tile512::<SQ>(ar, br, k)
    });
    if m4 < m {
        let out = &mut out[m4 * ldc..];
        pairwise_tiled::<SQ, MR>(&a[m4 * k..m * k], b, k, out, ldc, |ar, br, k| unsafe {
            tile_avx::<SQ>(ar, br, k)
        });
    }
}

/// [`pairwise`] with the widest tiles the CPU has: [`tile512`] with
/// AVX-512 ([`crate::wide::avx512`]) and rows of at least 4 values, the
/// AVX2 tiles with AVX2 ([`crate::wide::avx2`]).
/// `ldc`: the row stride of `out` (at least the number of rows of `b`).
fn pairwise_any<const SQ: bool>(a: &[f64], b: &[f64], k: usize, out: &mut [f64], ldc: usize) {
    #[cfg(target_arch = "x86_64")]
    if k >= 4 && crate::wide::avx512() {
        // SAFETY: the CPU supports AVX-512 F/VL/DQ (checked at run time).
        return unsafe { pairwise512::<SQ>(a, b, k, out, ldc) };
    }
    #[cfg(target_arch = "x86_64")]
    if crate::wide::avx2() {
        // SAFETY: the CPU supports AVX2 (checked at run time).
        return unsafe { pairwise_avx::<SQ>(a, b, k, out, ldc) };
    }
    pairwise::<SQ, false>(a, b, k, out, ldc);
}

#[inline(always)]
fn single<const SQ: bool>(x: &[f64], y: &[f64]) -> f64 {
    if SQ {
        sq_dist(x, y)
    } else {
        dot(x, y)
    }
}

/// `out[i·n + j] = dot(a_i, b_j)` for the `m = a.len()/k` rows of `a` and the
/// `n = b.len()/k` rows of `b` (both row-major, `k` wide): the same bits as
/// [`dot`] entry by entry.
///
///
/// Three kernels, the same bits: when `b` has few rows (a layer's weights:
/// at most [`NARROW`]), the outputs go across the vector lanes: with
/// AVX-512, rows of at most [`NARROW_K512`] values and at least
/// `ROWS512` (64) rows of `a`, `narrow512`; with AVX2 and rows of at
/// most [`NARROW_K`] values, `narrow_avx`; otherwise the register tiles
/// across `k`.
pub fn gemm_nt(a: &[f64], b: &[f64], k: usize, out: &mut [f64]) {
    let n = b.len() / k.max(1);
    // Rows of `a` that have room in `out` (the narrow kernels' batch).
    #[cfg(target_arch = "x86_64")]
    let m = (a.len() / k.max(1)).min(out.len() / n.max(1));
    #[cfg(target_arch = "x86_64")]
    if packs512(n, k) && m >= ROWS512 {
        let panels = panels512(b, k, panel_columns(n));
        // SAFETY: the CPU supports AVX-512 F/VL/DQ (checked above); the
        // shapes are the ones `narrow512` asserts.
        unsafe { narrow512(&a[..m * k], b, &panels, k, n, &mut out[..m * n]) };
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if (1..=NARROW).contains(&n) && (1..=NARROW_K).contains(&k) && crate::wide::avx2() {
        let np = n.div_ceil(4) * 4;
        let bt = transposed(b, k, np);
        // SAFETY: the CPU supports AVX2 (checked above); the shapes are
        // the ones `narrow_avx` asserts.
        unsafe { narrow_avx(&a[..m * k], &bt, k, n, np, &mut out[..m * n]) };
        return;
    }
    pairwise_any::<false>(a, b, k, out, n);
}

/// Whether [`gemm_nt`] packs a right operand of `n` rows of `k` for
/// [`narrow512`] (given enough rows of `a`, [`ROWS512`]).
#[cfg(target_arch = "x86_64")]
fn packs512(n: usize, k: usize) -> bool {
    (1..=NARROW).contains(&n) && (1..=NARROW_K512).contains(&k) && crate::wide::avx512()
}

/// Writes the first `o.len()` lanes (at most 4) of `s` to `o`: a row's
/// last, partial group of outputs goes through a masked store (the 256-bit
/// kernels' form of `_mm512_mask_storeu_pd`), a whole group through a plain
/// one.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn store256(o: &mut [f64], s: std::arch::x86_64::__m256d) {
    use std::arch::x86_64::*;
    let lanes = o.len().min(4);
    if lanes == 4 {
        // SAFETY: `o` holds at least four doubles.
        unsafe { _mm256_storeu_pd(o.as_mut_ptr(), s) };
    } else {
        // Lane `q` on when `q < lanes` (the sign bit of each 64-bit lane).
        let mask = _mm256_cmpgt_epi64(_mm256_set1_epi64x(lanes as i64), _mm256_setr_epi64x(0, 1, 2, 3));
        // SAFETY: the lanes written are `o`'s; a masked-off lane is neither
        // written nor touched (no fault past the end).
        unsafe { _mm256_maskstore_pd(o.as_mut_ptr(), mask, s) };
    }
}

/// `b`'s `k`-wide rows as columns: `bt[t·np + j] = b_j[t]`, zero past the
/// last row (`np` at least the number of rows).
fn transposed(b: &[f64], k: usize, np: usize) -> Aligned {
    let mut bt = Aligned::zeros(k * np);
    for (j, row) in b.chunks_exact(k.max(1)).enumerate() {
        for (t, &v) in row.iter().enumerate() {
            bt[t * np + j] = v;
        }
    }
    bt
}

/// Widest rows for `narrow512`: the EDBN's input layer (80 values) and
/// the ANN (ST)'s. Its packed `b` (`panels512`, `k x 64` at most, 40 KB
/// at 80) is read one 16-column panel at a time (10 KB at 80), in L1.
pub const NARROW_K512: usize = 128;

/// Rows of `a` per pass of [`narrow512`] over the panels: 64 rows of 80
/// values (40 KB) stay in L2 while each panel passes. Also the fewest rows
/// for which [`gemm_nt`] takes [`narrow512`]: below it packing `b` costs
/// too much against the products (the RBMs' training batches of 20 rows
/// made the EDBN's fit 3-5% slower through it: 0.616-0.623 s against
/// 0.591-0.603 s, `benches/peers` alternated, 2026-11-26).
const ROWS512: usize = 64;

/// Width of the column panel starting at `j0` of `n` columns: 16 (two
/// 512-bit vectors), or 8 for a last panel of at most 8 columns.
fn panel_width(j0: usize, n: usize) -> usize {
    if n - j0 > 8 {
        16
    } else {
        8
    }
}

/// `b`'s `n` rows (each `k` wide) as column panels for [`narrow512`]: the
/// panel of columns `j0..j0 + w` ([`panel_width`]) is a contiguous `k x w`
/// block at offset `j0 · k`, entry `(t, jj) = b_{j0 + jj}[t]` (0 past `n`).
/// Contiguous panels, not a `k x n` transpose: with 64 columns the rows of
/// a 16-column slice of the transpose lie 512 bytes apart and map to a
/// sixteenth of L1's sets, which evicted them (15 against 18 G products/s
/// at 3154 x 60 x 80 in a throwaway timing, one core, best of 30, not kept).
fn panels512(b: &[f64], k: usize, n: usize) -> Aligned {
    let mut p = Aligned::zeros(n.div_ceil(8) * 8 * k);
    let mut j0 = 0;
    while j0 < n {
        let w = panel_width(j0, n);
        for jj in 0..w.min(n - j0) {
            for (t, &v) in b[(j0 + jj) * k..(j0 + jj + 1) * k].iter().enumerate() {
                p[j0 * k + t * w + jj] = v;
            }
        }
        j0 += w;
    }
    p
}

/// [`narrow_avx`] with 512-bit vectors (8 outputs each) and two rows of
/// `a` at a time, so each load of `b` serves two rows: 16 accumulators of
/// the 32 registers AVX-512 gives. Lane `j` of accumulator `l` is partial
/// sum `l` of [`dot`] for output `j`, so the bits are [`dot`]'s, as in
/// [`narrow_avx`]. Outputs are stored with a lane mask, never past a row's
/// `n`-th. `panels`: [`panels512`], of the first [`panel_columns`] columns;
/// one or two columns past a multiple of 8 are each row's dot product with
/// `b`'s row instead ([`dots_of_rows`]; `2848 x 17 x 30`, the ANN (S)'s
/// output layer: 16.1-18.3 -> 20.6-20.7 G products a second, `cargo run
/// --release --example machine`, four runs of each build alternated,
/// 2026-11-28). Loop order: blocks of [`ROWS512`] rows; within one, each
/// panel (`k · 128` bytes, in L1) passes over all its rows, then the
/// columns past the panels.
///
/// Why: the AVX2 kernels spend their time on loads (one weight vector per
/// product in [`narrow_avx`], which holds one row in its 16 registers) and
/// on the tiles' horizontal sums and edge columns. `cargo run --release
/// --example machine` (its last line; 2026-11-26 08:20, one core, best of
/// 5) gave, in billions of products a second, this kernel / the AVX2 ones:
/// 16.8 / 13.9 at the ANN (S)'s input layer (2848 rows x 30 x 16), 14.4 /
/// 12.2 at its output layer (x 17 x 30), 17.7 / 14.6 at the ANN (ST)'s
/// input layer (3154 x 30 x 80), 17.7 / 15.6 and 17.5 / 13.8 at the EDBN's
/// layers (x 60 x 80, x 30 x 60). The limit without FMA was two multiplies
/// and two adds of four lanes a cycle, 8 products a cycle: ~29 G a second
/// at the ~3.6 GHz the same program's dependent-operation latency implies
/// (0.82 ns for 3 cycles), so this ran at ~60% of it. Three rows at a
/// time (24 accumulators) was no faster. Fused (module docs), the same
/// program on 2026-11-27 18:10 (the AMD EPYC again, one core, best of 5): 24.0,
/// 18.0, 24.9, 21.6 and 22.0 G a second at those five shapes (the AVX2
/// kernels 13.0, 11.8, 15.6, 17.3, 14.3), up to ~7 products a cycle at
/// the ~3.6 GHz above. Whether the core's FMA units or a step's loads (a
/// broadcast of `a` per row, one or two panel vectors) bound it now was not
/// measured.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,avx512f,avx512vl,avx512dq")]
unsafe fn narrow512(a: &[f64], b: &[f64], panels: &[f64], k: usize, n: usize, out: &mut [f64]) {
    let m = a.len() / k;
    let n_panels = panel_columns(n);
    assert!(n > 0 && panels.len() >= n_panels.div_ceil(8) * 8 * k && out.len() >= m * n && b.len() >= n * k);
    // `ar`: the rows as a slice, for the columns past the panels.
    let (ar, a) = (a, View::rows_of(a, m, k));
    for r0 in (0..m).step_by(ROWS512) {
        let r1 = (r0 + ROWS512).min(m);
        let mut j0 = 0;
        while j0 < n_panels {
            let w = panel_width(j0, n_panels);
            let panel = &panels[j0 * k..(j0 + w) * k];
            let cols = Cols {
                b: panel,
                ld: w,
                at: 0,
                padded: true,
            };
            let mut i = r0;
            // SAFETY (every call): rows i..i + R < m of `a`, a panel of
            // k x 8·H values, outputs masked to row i's n.
            while i + 2 <= r1 {
                unsafe {
                    if w == 16 {
                        nn_block512::<2, 2, true, false>(a, i, cols, n, j0, out);
                    } else {
                        nn_block512::<2, 1, true, false>(a, i, cols, n, j0, out);
                    }
                }
                i += 2;
            }
            if i < r1 {
                unsafe {
                    if w == 16 {
                        nn_block512::<1, 2, true, false>(a, i, cols, n, j0, out);
                    } else {
                        nn_block512::<1, 1, true, false>(a, i, cols, n, j0, out);
                    }
                }
            }
            j0 += w;
        }
        // The columns past the panels: each row's [`dot`] with them, the
        // reference order itself (inlined here, so with AVX-512 and FMA).
        for j in n_panels..n {
            dots_of_rows(
                &ar[r0 * k..r1 * k],
                &b[j * k..(j + 1) * k],
                &mut out[r0 * n + j..],
                n,
            );
        }
    }
}

/// `out[i·ld] = dot(a_i, col)` for every `k`-wide row `a_i` of `a` (`k` =
/// `col.len()`), with [`single_fused`]'s bits: lane `l` of a row's 256-bit
/// accumulator is its partial sum `l`, four rows at a time, so that 16
/// chains run side by side (one dot product of 30 terms alone waits on
/// the FMA's latency: the compiler's own vectorisation of this loop was no
/// faster than the mostly empty panel it replaces).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn dots_of_rows(a: &[f64], col: &[f64], out: &mut [f64], ld: usize) {
    use std::arch::x86_64::*;
    let k = col.len();
    let whole = k / 4 * 4;
    let mut rows = a.chunks_exact(4 * k);
    let mut i = 0;
    for block in &mut rows {
        let mut acc = [_mm256_setzero_pd(); 4];
        for c in (0..whole).step_by(4) {
            // SAFETY: c + 4 <= whole <= k, and row r's chunk lies in `block`.
            unsafe {
                let y = _mm256_loadu_pd(col.as_ptr().add(c));
                for (r, acc) in acc.iter_mut().enumerate() {
                    let x = _mm256_loadu_pd(block.as_ptr().add(r * k + c));
                    *acc = _mm256_fmadd_pd(x, y, *acc);
                }
            }
        }
        for (r, acc) in acc.iter().enumerate() {
            let mut l = [0.0f64; 4];
            // SAFETY: `l` holds four doubles.
            unsafe { _mm256_storeu_pd(l.as_mut_ptr(), *acc) };
            let mut s = (l[0] + l[1]) + (l[2] + l[3]);
            for t in whole..k {
                s = block[r * k + t].mul_add(col[t], s);
            }
            out[(i + r) * ld] = s;
        }
        i += 4;
    }
    for row in rows.remainder().chunks_exact(k) {
        out[i * ld] = single_fused::<false>(row, col);
        i += 1;
    }
}

/// Columns of a product of `n` columns that [`narrow512`] computes from
/// panels: all but a last [`FEW_COLUMNS`] or fewer past a multiple of 8
/// (when there are more than 8), which it computes as plain dot products.
///
/// Why: 17 classes made a 16-wide and an 8-wide panel, the second
/// seven-eighths zero lanes: a third of the layer's vector products wasted
/// (the ANN's, the logistic regression's and the EDBN's output layers).
fn panel_columns(n: usize) -> usize {
    let tail = n % 8;
    if n > 8 && tail <= FEW_COLUMNS {
        n - tail
    } else {
        n
    }
}

/// Most columns past a multiple of 8 that [`narrow512`] computes as dot
/// products instead of a mostly empty panel. A panel's row costs `k`
/// 512-bit products whatever its width; a dot product of `k` terms about
/// `k/4` 256-bit ones and a reduction, so up to two columns win.
const FEW_COLUMNS: usize = 2;

/// Most rows of `b` for `narrow_avx`: its transposed copy (`k x n`) is
/// then at most `k · 64` doubles, in L1 for the widths used here.
pub const NARROW: usize = 64;
/// Widest rows for `narrow_avx`. In a throwaway timing of both kernels
/// (thread CPU time, one core, not kept) it was ahead at the ANN's shapes
/// (2848 rows x 30 x 16, x 17 x 30) and behind at 3154 x 30 x 80: with
/// long rows the tiles' horizontal sums are amortised and their fewer loads
/// win. `benches/peers` times the layers in place (ANN and logistic predict).
pub const NARROW_K: usize = 32;

/// [`gemm_nt`] for a `b` of few rows, with the outputs across the lanes:
/// `bt` is `b` transposed (`bt[t·np + j] = b_j[t]`, `np` = `n` rounded up
/// to 4, zero-padded), and each row `a` updates 8 outputs at a time (4 at
/// the edge), lane `j` keeping the four partial sums of [`dot`]
/// (`acc_l[j] += a[4c + l] · b_j[4c + l]`), reduced as
/// `(acc_0 + acc_1) + (acc_2 + acc_3)`, then the remainder in order. Each
/// lane does exactly [`dot`]'s operations, so the bits are its own; there
/// are no horizontal sums, which in the tiles cost more than the products
/// when `k` is 16-80 and `b` has tens of rows (a layer's weights).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn narrow_avx(a: &[f64], bt: &[f64], k: usize, n: usize, np: usize, out: &mut [f64]) {
    let m = a.len() / k;
    assert!(np.is_multiple_of(4) && np >= n && bt.len() >= k * np && out.len() >= m * n);
    // Each block's 4 or 8 outputs are stored whole, as a fixed-size copy
    // (inlined): a copy of a run-time length is a call into libc's memcpy,
    // which cost a tenth of an ANN prediction (perf). A row's last block
    // may run past its `n` outputs into the next row's first ones, which
    // that row then overwrites; only the very end of `out` takes the
    // trimmed copy.
    let out = &mut out[..m * n];
    for (i, ar) in a.chunks_exact(k).enumerate() {
        let mut j0 = 0;
        while j0 + 8 <= np {
            // SAFETY: j0 + 8 <= np (and AVX2, from our caller).
            let s = unsafe { narrow_block::<2>(ar, bt, np, j0) };
            store(out, i * n + j0, &s);
            j0 += 8;
        }
        if j0 < np {
            // SAFETY: j0 + 4 == np.
            let s = unsafe { narrow_block::<1>(ar, bt, np, j0) };
            store(out, i * n + j0, &[s[0], s[1], s[2], s[3]]);
        }
    }
}

/// `out[at..at + W] = s`, trimmed at the end of `out`; a fixed-size copy
/// (see [`narrow_avx`]).
#[inline(always)]
fn store<const W: usize>(out: &mut [f64], at: usize, s: &[f64; W]) {
    if let Some(dst) = out.get_mut(at..at + W) {
        dst.copy_from_slice(s);
    } else {
        let w = W.min(out.len().saturating_sub(at));
        out[at..at + w].copy_from_slice(&s[..w]);
    }
}

/// `H` vectors (4 outputs each) of [`narrow_avx`]'s row `a` from column
/// `j0` of `bt`; a compile-time `H` keeps the `4·H` accumulators in
/// registers. Requires `j0 + 4·H <= np` and `bt.len() >= a.len() · np`.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2,fma")]
unsafe fn narrow_block<const H: usize>(a: &[f64], bt: &[f64], np: usize, j0: usize) -> [f64; 8] {
    use std::arch::x86_64::*;
    let k = a.len();
    assert!(j0 + 4 * H <= np && bt.len() >= k * np && H <= 2);
    let full = k / 4 * 4;
    let (pa, pb) = (a.as_ptr(), bt.as_ptr());
    let mut acc = [[_mm256_setzero_pd(); H]; 4];
    let mut c = 0;
    while c < full {
        for (l, acc_l) in acc.iter_mut().enumerate() {
            // SAFETY: c + l < k; row c + l of bt holds np >= j0 + 4·H values.
            unsafe {
                let x = _mm256_broadcast_sd(&*pa.add(c + l));
                let w = pb.add((c + l) * np + j0);
                for (h, v) in acc_l.iter_mut().enumerate() {
                    *v = _mm256_fmadd_pd(x, _mm256_loadu_pd(w.add(4 * h)), *v);
                }
            }
        }
        c += 4;
    }
    let mut s = [_mm256_setzero_pd(); H];
    for (h, v) in s.iter_mut().enumerate() {
        *v = _mm256_add_pd(
            _mm256_add_pd(acc[0][h], acc[1][h]),
            _mm256_add_pd(acc[2][h], acc[3][h]),
        );
    }
    for t in full..k {
        // SAFETY: t < k; as above.
        unsafe {
            let x = _mm256_broadcast_sd(&*pa.add(t));
            let w = pb.add(t * np + j0);
            for (h, v) in s.iter_mut().enumerate() {
                *v = _mm256_fmadd_pd(x, _mm256_loadu_pd(w.add(4 * h)), *v);
            }
        }
    }
    let mut out = [0.0f64; 8];
    for (h, v) in s.iter().enumerate() {
        // SAFETY: out holds 8 doubles and 4·h + 4 <= 8.
        unsafe { _mm256_storeu_pd(out.as_mut_ptr().add(4 * h), *v) };
    }
    out
}

/// `out[i·n + j] = sq_dist(a_i, b_j)`, as [`gemm_nt`]: the same bits as
/// [`sq_dist`] entry by entry.
pub fn sq_dists(a: &[f64], b: &[f64], k: usize, out: &mut [f64]) {
    let n = b.len() / k.max(1);
    pairwise_any::<true>(a, b, k, out, n);
}

/// [`sq_dists`] into rows of `out` `ldc` apart (`ldc` at least the number
/// of rows of `b`): entry `(i, j)` at `out[i·ldc + j]`, the rest of each row
/// untouched. For writing a block of a larger matrix in place.
pub fn sq_dists_strided(a: &[f64], b: &[f64], k: usize, out: &mut [f64], ldc: usize) {
    pairwise_any::<true>(a, b, k, out, ldc);
}

/// A matrix read through strides: entry `(i, t)` is `data[i·rs + t·cs]`.
/// A row-major matrix and its transpose are both views of one buffer,
/// without a copy ([`View::rows_of`], [`View::transpose_of`]).
#[derive(Clone, Copy, Debug)]
pub struct View<'a> {
    /// The values.
    pub data: &'a [f64],
    /// Rows.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// Distance between rows.
    pub rs: usize,
    /// Distance between columns.
    pub cs: usize,
}

impl<'a> View<'a> {
    /// `data` as `rows` rows of `cols` values.
    pub fn rows_of(data: &'a [f64], rows: usize, cols: usize) -> Self {
        View {
            data,
            rows,
            cols,
            rs: cols,
            cs: 1,
        }
    }

    /// The transpose of `data` taken as `rows` rows of `cols` values: a
    /// `cols x rows` view.
    pub fn transpose_of(data: &'a [f64], rows: usize, cols: usize) -> Self {
        View {
            data,
            rows: cols,
            cols: rows,
            rs: 1,
            cs: cols,
        }
    }

    /// Entry `(i, t)`.
    #[inline(always)]
    fn at(&self, i: usize, t: usize) -> f64 {
        self.data[i * self.rs + t * self.cs]
    }

    /// True when every entry lies inside `data`.
    fn in_bounds(&self) -> bool {
        self.rows == 0
            || self.cols == 0
            || (self.rows - 1)
                .checked_mul(self.rs)
                .zip((self.cols - 1).checked_mul(self.cs))
                .and_then(|(x, y)| x.checked_add(y))
                .is_some_and(|last| last < self.data.len())
    }
}

/// `out[i·n + j] = Σ_t a(i, t) · b[t·n + j]`: the product of a view `a`
/// (`m x k`) and a row-major `b` (`k x n`), each entry with the bits of
/// [`dot`] of row `i` of `a` and column `j` of `b` (so of [`gemm_nt`] over
/// the materialised row and column). For the RBM's training products,
/// whose operands are a matrix or its transpose and whose batches are too
/// small (20 rows) for [`gemm_nt`]'s packed kernels: `h Wᵀ`'s partner `W`,
/// `Σ_rows h vᵀ` as `hᵀ v` (a transposed view, no copy) and `v Wᵀ` with
/// one transpose of `W` a minibatch, all with the outputs across the
/// lanes. With AVX-512 ([`crate::wide::avx512`]) the kernel is
/// `nn512`, with AVX2 and FMA alone `nn256`; otherwise the operands are
/// materialised for [`gemm_nt`].
///
/// # Panics
/// If `a` reaches past its data, `b` holds fewer than `k·n` values or
/// `out` fewer than `m·n`.
pub fn gemm_nn(a: View<'_>, b: &[f64], n: usize, out: &mut [f64]) {
    let (m, k) = (a.rows, a.cols);
    assert!(a.in_bounds(), "gemm_nn: the view reaches past its data");
    assert!(b.len() >= k * n && out.len() >= m * n, "gemm_nn: short b or out");
    if m == 0 || n == 0 {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if crate::wide::avx512() {
        // SAFETY: the CPU supports AVX-512 F/VL/DQ (checked at run time);
        // the shapes are asserted above.
        unsafe { nn512(a, b, n, out) };
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if crate::wide::avx2() {
        // SAFETY: the CPU supports AVX2 and FMA (checked at run time);
        // the shapes are asserted above.
        unsafe { nn256(a, b, n, out) };
        return;
    }
    let mut rows = Vec::with_capacity(m * k);
    for i in 0..m {
        rows.extend((0..k).map(|t| a.at(i, t)));
    }
    let mut bt = vec![0.0; k * n];
    transpose(&b[..k * n], k, n, &mut bt);
    if k == 0 {
        out[..m * n].iter_mut().for_each(|o| *o = 0.0);
    } else {
        gemm_nt(&rows, &bt, k, &mut out[..m * n]);
    }
}

/// [`gemm_nn`] with 512-bit vectors: three rows of `a` against 16 columns
/// of `b` (8 at the edge, the last vector masked), lane `j` of accumulator
/// `l` partial sum `l` of [`dot`] for output `j`, as in [`narrow512`], but
/// `b` read in place (rows `n` apart) and `a` through its strides.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,avx512f,avx512vl,avx512dq")]
unsafe fn nn512(a: View<'_>, b: &[f64], n: usize, out: &mut [f64]) {
    let m = a.rows;
    let mut i = 0;
    while i < m {
        let rows = (m - i).min(3);
        let mut j0 = 0;
        while j0 < n {
            let wide = n - j0 > 8;
            // SAFETY (every call): rows i..i + R < m; columns j0.. < n, the
            // lanes past n masked; shapes asserted by `gemm_nn`.
            unsafe {
                let c = Cols {
                    b,
                    ld: n,
                    at: j0,
                    padded: false,
                };
                match (rows, wide, a.cs == 1) {
                    (3, true, true) => nn_block512::<3, 2, true, false>(a, i, c, n, j0, out),
                    (3, false, true) => nn_block512::<3, 1, true, false>(a, i, c, n, j0, out),
                    (3, true, false) => nn_block512::<3, 2, false, false>(a, i, c, n, j0, out),
                    (3, false, false) => nn_block512::<3, 1, false, false>(a, i, c, n, j0, out),
                    (2, true, _) => nn_block512::<2, 2, false, false>(a, i, c, n, j0, out),
                    (2, false, _) => nn_block512::<2, 1, false, false>(a, i, c, n, j0, out),
                    (_, true, _) => nn_block512::<1, 2, false, false>(a, i, c, n, j0, out),
                    (_, false, _) => nn_block512::<1, 1, false, false>(a, i, c, n, j0, out),
                }
            }
            j0 += if wide { 16 } else { 8 };
        }
        i += rows;
    }
}

/// [`gemm_nn`] with 256-bit vectors, for CPUs with AVX2 and FMA but not
/// AVX-512: three rows of `a` against four columns of `b` a block, lane
/// `j` of accumulator `l` partial sum `l` of [`dot`] for output `j` (12
/// accumulators of the 16 registers), reduced as `dot` reduces, so the
/// bits are `dot`'s, as in [`nn512`]. Before it, such CPUs materialised
/// both operands for [`gemm_nt`]'s tiles (a transpose of `b` a call and
/// four horizontal sums a tile): the EDBN's fit took three times as long
/// on an AVX2-only host as on an AVX-512 one (docs/benches.md).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn nn256(a: View<'_>, b: &[f64], n: usize, out: &mut [f64]) {
    // One stride of `a` as 1 lets the compiler fold it into the loads'
    // displacements: with both strides at run time, the 12 offsets of a
    // block's broadcasts did not fit the registers and were reloaded from
    // the stack every chunk.
    match (a.rs == 1, a.cs == 1) {
        (true, _) => nn256_strides::<RS_ONE>(a, b, n, out),
        (false, true) => nn256_strides::<CS_ONE>(a, b, n, out),
        _ => nn256_strides::<STRIDED>(a, b, n, out),
    }
}

/// Stride cases of [`nn_block256`]: `a`'s rows adjacent (a transposed view),
/// its columns adjacent (a row-major matrix), or neither.
const RS_ONE: u8 = 0;
const CS_ONE: u8 = 1;
const STRIDED: u8 = 2;

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn nn256_strides<const S: u8>(a: View<'_>, b: &[f64], n: usize, out: &mut [f64]) {
    let m = a.rows;
    let mut i = 0;
    while i < m {
        let rows = (m - i).min(3);
        let mut j0 = 0;
        while j0 < n {
            // SAFETY (every call): rows i..i + R < m; columns j0.. < n, the
            // lanes past n masked; shapes asserted by `gemm_nn`.
            unsafe {
                match (rows, n - j0 >= 4) {
                    (3, true) => nn_block256::<3, true, S>(a, i, b, n, j0, out),
                    (3, false) => nn_block256::<3, false, S>(a, i, b, n, j0, out),
                    (2, true) => nn_block256::<2, true, S>(a, i, b, n, j0, out),
                    (2, false) => nn_block256::<2, false, S>(a, i, b, n, j0, out),
                    (_, true) => nn_block256::<1, true, S>(a, i, b, n, j0, out),
                    (_, false) => nn_block256::<1, false, S>(a, i, b, n, j0, out),
                }
            }
            j0 += 4;
        }
        i += rows;
    }
}

/// Rows `i..i + R` of `a` against columns `j0..j0 + 4` of the row-major
/// `b` (`n` a row), into the same columns of `out`: [`nn_block512`] with
/// four lanes. An edge block (`FULL` false: fewer than four columns left)
/// loads with a lane mask and stores only its columns. `S`: which of
/// `a`'s strides is 1 ([`RS_ONE`], [`CS_ONE`]; [`STRIDED`] neither).
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2,fma")]
unsafe fn nn_block256<const R: usize, const FULL: bool, const S: u8>(
    a: View<'_>,
    i: usize,
    b: &[f64],
    n: usize,
    j0: usize,
    out: &mut [f64],
) {
    use std::arch::x86_64::*;
    let k = a.cols;
    let full = k / 4 * 4;
    let lanes = n.saturating_sub(j0).min(4);
    let (rs, cs) = match S {
        RS_ONE => (1, a.cs),
        CS_ONE => (a.rs, 1),
        _ => (a.rs, a.cs),
    };
    assert!(
        i + R <= a.rows
            && (lanes == 4) == FULL
            && lanes > 0
            && (rs, cs) == (a.rs, a.cs)
            && (k == 0 || (k - 1) * n + j0 + lanes <= b.len())
            && (i + R - 1) * n + j0 + lanes <= out.len()
    );
    // Lane `q` on when `q < lanes` (the sign bit of each 64-bit lane).
    let mask = _mm256_cmpgt_epi64(_mm256_set1_epi64x(lanes as i64), _mm256_setr_epi64x(0, 1, 2, 3));
    // SAFETY (loads): t < k, and the unmasked lanes of row t lie within
    // `b` (asserted); entry (i + r, t) of `a` is in bounds
    // (`View::in_bounds`, asserted by `gemm_nn`), at `pa + r·rs + t·cs`.
    let load = |p: *const f64| unsafe {
        if FULL {
            _mm256_loadu_pd(p)
        } else {
            _mm256_maskload_pd(p, mask)
        }
    };
    let bcast = |p: *const f64, r: usize, t: usize| unsafe { _mm256_set1_pd(*p.add(r * rs + t * cs)) };
    let pa = a.data.as_ptr().wrapping_add(i * a.rs);
    let pb = b.as_ptr().wrapping_add(j0);
    let mut acc = [[_mm256_setzero_pd(); 4]; R];
    // Pointers to chunk `c`'s first entries, stepped a chunk at a time.
    let (mut qa, mut qb) = (pa, pb);
    let mut c = 0;
    while c < full {
        for l in 0..4 {
            let bv = load(qb.wrapping_add(l * n));
            for (r, acc_r) in acc.iter_mut().enumerate() {
                acc_r[l] = _mm256_fmadd_pd(bcast(qa, r, l), bv, acc_r[l]);
            }
        }
        qa = qa.wrapping_add(4 * cs);
        qb = qb.wrapping_add(4 * n);
        c += 4;
    }
    for (r, [a0, a1, a2, a3]) in acc.into_iter().enumerate() {
        let mut s = _mm256_add_pd(_mm256_add_pd(a0, a1), _mm256_add_pd(a2, a3));
        for t in full..k {
            s = _mm256_fmadd_pd(bcast(pa, r, t), load(pb.wrapping_add(t * n)), s);
        }
        store256(&mut out[(i + r) * n + j0..(i + r) * n + j0 + lanes], s);
    }
}

/// The columns a block of [`nn_block512`] reads: `b`'s rows `ld` apart,
/// starting at column `at` (a panel of [`panels512`], or `b` itself).
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
struct Cols<'a> {
    b: &'a [f64],
    ld: usize,
    at: usize,
    /// Every row holds `8·H` readable values from `at` (a panel).
    padded: bool,
}

/// Rows `i..i + R` of `a` against `8·H` columns of `b` (`cols`), into
/// columns `j0..j0 + 8·H` of `out` (`n` a row; lanes at or past `n`
/// masked off on load and store): lane `j` of accumulator `l` is partial
/// sum `l` of [`dot`] for output `j`, reduced as `dot` reduces, so the
/// bits are `dot`'s. The block of [`narrow512`] (a packed panel, read
/// whole, and rows of `a` adjacent: `UNIT`) and of [`nn512`] (`b` in
/// place, `a` through its strides). The masked loads and the stride
/// multiply cost the packed layer kernel ~4 % (ANN (ST) predict 0.84-0.85
/// against 0.80-0.86 ms, `benches/peers` alternated), hence `UNIT`. With
/// `SQ` each term is a squared difference instead ([`term512`]), so the
/// bits are [`sq_dist`]'s: the block of [`sq_dists_cols`].
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2,fma,avx512f,avx512vl,avx512dq")]
unsafe fn nn_block512<const R: usize, const H: usize, const UNIT: bool, const SQ: bool>(
    a: View<'_>,
    i: usize,
    cols: Cols<'_>,
    n: usize,
    j0: usize,
    out: &mut [f64],
) {
    use std::arch::x86_64::*;
    const { assert!(H == 1 || H == 2) };
    assert!(!UNIT || a.cs == 1);
    let k = a.cols;
    let full = k / 4 * 4;
    let masks: [__mmask8; H] = std::array::from_fn(|h| {
        let lanes = n.saturating_sub(j0 + 8 * h).min(8);
        ((1u16 << lanes) - 1) as __mmask8
    });
    let lanes = n.saturating_sub(j0).min(8 * H);
    let read = if cols.padded { 8 * H } else { lanes };
    assert!(
        i + R <= a.rows
            && (k == 0 || (k - 1) * cols.ld + cols.at + read <= cols.b.len())
            && (i + R - 1) * n + j0 + lanes <= out.len()
    );
    let (pa, pb) = (a.data.as_ptr(), cols.b.as_ptr().wrapping_add(cols.at));
    let rows: [usize; R] = std::array::from_fn(|r| (i + r) * a.rs);
    // SAFETY (loads): t < k, and the unmasked lanes of row t lie within
    // `cols` (asserted); entry (i + r, t) of `a` is in bounds
    // (`View::in_bounds`, asserted by the callers).
    // `UNIT` blocks read a zero-padded panel whole; the others mask.
    let load = |t: usize, h: usize| unsafe {
        let p = pb.add(t * cols.ld + 8 * h);
        if UNIT && cols.padded {
            _mm512_loadu_pd(p)
        } else {
            _mm512_maskz_loadu_pd(masks[h], p)
        }
    };
    // `UNIT`: `a`'s columns adjacent (`cs == 1`), the index without a multiply.
    let cs = if UNIT { 1 } else { a.cs };
    let bcast = |r: usize, t: usize| unsafe { _mm512_set1_pd(*pa.add(rows[r] + t * cs)) };
    let mut acc = [[[_mm512_setzero_pd(); H]; 4]; R];
    let mut c = 0;
    while c < full {
        for l in 0..4 {
            let bv: [__m512d; H] = std::array::from_fn(|h| load(c + l, h));
            for (r, acc_r) in acc.iter_mut().enumerate() {
                let x = bcast(r, c + l);
                for (v, &bh) in acc_r[l].iter_mut().zip(&bv) {
                    *v = term512::<SQ>(x, bh, *v);
                }
            }
        }
        c += 4;
    }
    for (r, acc_r) in acc.iter().enumerate() {
        for h in 0..H {
            let [a0, a1, a2, a3] = acc_r.map(|l| l[h]);
            let mut s = _mm512_add_pd(_mm512_add_pd(a0, a1), _mm512_add_pd(a2, a3));
            for t in full..k {
                s = term512::<SQ>(bcast(r, t), load(t, h), s);
            }
            // SAFETY: the unmasked lanes are outputs j0 + 8h.. < n of row
            // i + r, inside `out` (asserted above).
            unsafe { _mm512_mask_storeu_pd(out.as_mut_ptr().add((i + r) * n + j0 + 8 * h), masks[h], s) };
        }
    }
}

/// One term of [`nn_block512`], lane by lane [`madd`]: `fma(x, b, s)`, or
/// `fma(d, d, s)` with `d = x − b` for a squared distance.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2,fma,avx512f,avx512vl,avx512dq")]
fn term512<const SQ: bool>(
    x: std::arch::x86_64::__m512d,
    b: std::arch::x86_64::__m512d,
    s: std::arch::x86_64::__m512d,
) -> std::arch::x86_64::__m512d {
    use std::arch::x86_64::*;
    if SQ {
        let d = _mm512_sub_pd(x, b);
        _mm512_fmadd_pd(d, d, s)
    } else {
        _mm512_fmadd_pd(x, b, s)
    }
}

/// [`sq_dists`] against vectors held as columns: `out[i·w + j] =
/// sq_dist(a_i, v_{c0 + j})` for the rows `a_i` of `a` (`k` wide) and the
/// vectors `cols = c0..c1` of `bt` (`k x n` row-major, `bt[t·n + c]` =
/// value `t` of vector `c`), `w = c1 − c0` outputs a row, each with
/// [`sq_dist`]'s bits.
/// For the SVM's kernel blocks ([`super::classic::rbf_block`]): by rows of
/// vectors ([`sq_dists_strided`]) each tile ends in horizontal sums; here
/// the outputs lie across the lanes (`nn_block512`, a subtraction and an
/// FMA a term) and there are none. Without AVX-512 the vectors are copied
/// back into rows for [`sq_dists`].
///
/// # Panics
/// If `cols` is not within `0..n`, `bt` holds fewer than `k·n` values or
/// `out` fewer than `m·w`.
pub fn sq_dists_cols(
    a: &[f64],
    bt: &[f64],
    k: usize,
    n: usize,
    cols: std::ops::Range<usize>,
    out: &mut [f64],
) {
    let m = a.len() / k.max(1);
    let (c0, c1) = (cols.start, cols.end);
    assert!(
        c0 <= c1 && c1 <= n && bt.len() >= k * n,
        "sq_dists_cols: short bt or columns past n"
    );
    let w = c1 - c0;
    assert!(out.len() >= m * w, "sq_dists_cols: short out");
    if m == 0 || w == 0 {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if k > 0 && crate::wide::avx512() {
        // SAFETY: the CPU supports AVX-512 F/VL/DQ (checked above); shapes
        // asserted above.
        unsafe { sq_cols512(View::rows_of(&a[..m * k], m, k), bt, n, c0, w, out) };
        return;
    }
    let mut rows = vec![0.0; w * k];
    for (t, col) in bt.chunks_exact(n).take(k).enumerate() {
        for (j, &v) in col[c0..c1].iter().enumerate() {
            rows[j * k + t] = v;
        }
    }
    pairwise_any::<true>(&a[..m * k], &rows, k, out, w);
}

/// [`sq_dists_cols`] with AVX-512: three rows against 16 vectors a block
/// (8 at the edge, masked), as [`nn512`] with squared differences, panel
/// by panel.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,avx512f,avx512vl,avx512dq")]
unsafe fn sq_cols512(a: View<'_>, bt: &[f64], n: usize, c0: usize, w: usize, out: &mut [f64]) {
    let m = a.rows;
    // Each panel of 16 vectors (k rows of `bt` apart, 10 KB at k = 80)
    // passes over all the rows, so it is read from memory once.
    let mut j0 = 0;
    while j0 < w {
        let wide = w - j0 > 8;
        let c = Cols {
            b: bt,
            ld: n,
            at: c0 + j0,
            // A whole panel is loaded without masks.
            padded: w - j0 >= if wide { 16 } else { 8 },
        };
        let mut i = 0;
        while i < m {
            let rows = (m - i).min(3);
            // SAFETY (every call): rows i..i + R < m; vectors c0 + j0.. < n,
            // the lanes past n masked; `a` is row-major (`cs == 1`).
            unsafe {
                match (rows, wide) {
                    (3, true) => nn_block512::<3, 2, true, true>(a, i, c, w, j0, out),
                    (3, false) => nn_block512::<3, 1, true, true>(a, i, c, w, j0, out),
                    (2, true) => nn_block512::<2, 2, true, true>(a, i, c, w, j0, out),
                    (2, false) => nn_block512::<2, 1, true, true>(a, i, c, w, j0, out),
                    (_, true) => nn_block512::<1, 2, true, true>(a, i, c, w, j0, out),
                    (_, false) => nn_block512::<1, 1, true, true>(a, i, c, w, j0, out),
                }
            }
            i += rows;
        }
        j0 += if wide { 16 } else { 8 };
    }
}

/// Writes the transpose of `src` (`rows x cols`, row-major) into `dst` (`cols x rows`).
///
/// Four source rows at a time, so each destination row gets four
/// adjacent values per visit (one store of four values instead of four
/// stores a row apart); the EDBN's fit transposes its weights once a
/// minibatch, and the entry-by-entry loop was a twentieth of the fit.
///
/// # Panics
/// If `src` or `dst` holds fewer than `rows · cols` values.
pub fn transpose(src: &[f64], rows: usize, cols: usize, dst: &mut [f64]) {
    transpose_into(src, rows, cols, dst, rows);
}

/// [`transpose`] into rows `ld` apart (`ld >= rows`): `dst[j·ld + i] =
/// src[i·cols + j]`, the rest of each row untouched.
fn transpose_into(src: &[f64], rows: usize, cols: usize, dst: &mut [f64], ld: usize) {
    let len = rows * cols;
    assert!(
        ld >= rows && src.len() >= len && dst.len() >= (cols.max(1) - 1) * ld + rows,
        "transpose: short buffers"
    );
    let src = &src[..len];
    let mut i0 = 0;
    while i0 + 4 <= rows {
        let r: [&[f64]; 4] = std::array::from_fn(|q| &src[(i0 + q) * cols..(i0 + q + 1) * cols]);
        for j in 0..cols {
            let d = &mut dst[j * ld + i0..j * ld + i0 + 4];
            d.copy_from_slice(&[r[0][j], r[1][j], r[2][j], r[3][j]]);
        }
        i0 += 4;
    }
    for i in i0..rows {
        for (j, &v) in src[i * cols..(i + 1) * cols].iter().enumerate() {
            dst[j * ld + i] = v;
        }
    }
}

/// Adds `bias[j]` to every row of `out` (`bias.len()` wide) and applies `f` to each entry.
/// Vectorised ([`crate::wide::with_avx2`]) when `f` is (e.g. the
/// activations of [`super::vmath`]).
pub fn add_bias_map(out: &mut [f64], bias: &[f64], f: impl Fn(f64) -> f64) {
    // The closure inlined into the wide function, or the loop stays SSE2.
    // `f` runs over the whole matrix in one pass, not row by row: rows are
    // short (a layer's 17-30 units), and per row the vector loop left a
    // scalar tail of up to 7 entries, each a scalar `f` (an exponential)
    // several times the cost of a lane. Same bits: `f` of the same sums.
    crate::wide::with_avx2(
        #[inline(always)]
        || {
            let w = bias.len();
            let whole = out.len().checked_div(w).map_or(0, |rows| rows * w);
            let out = &mut out[..whole];
            for row in out.chunks_exact_mut(w.max(1)) {
                row.iter_mut().zip(bias).for_each(|(o, b)| *o += b);
            }
            out.iter_mut().for_each(|o| *o = f(*o));
        },
    )
}

/// 64 bytes on a 64-byte boundary: one cache line of [`Aligned`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(64))]
struct Line([f64; 8]);

/// A zero-initialised `f64` buffer that starts on a cache line: the packed
/// operands the AVX-512 kernels read in 64-byte vectors ([`panels512`],
/// [`transposed`]).
///
/// Why: the allocator returns 16-byte-aligned blocks (large ones 16 past a
/// page), so from a `Vec<f64>` every 64-byte load spans two cache lines and
/// the load port pays twice for one of its halves. On the EDBN's sparse
/// first layer (3154 x 80 features, a fifth non-zero, 60 outputs; a
/// throwaway timing loop, best of 30 passes, three runs each alternated,
/// 2026-11-29): 445-533 us a pass from a `Vec`, 362-386 us aligned; the
/// peers predictions, EDBN 1.46-1.54 -> 1.42-1.49 ms and ANN (ST)
/// 0.62-0.65 -> 0.60-0.61 ms (docs/benches.md). The bits are the same:
/// the kernels use unaligned loads either way.
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct Aligned {
    lines: Vec<Line>,
    len: usize,
}

impl Aligned {
    /// `len` zeros.
    pub(crate) fn zeros(len: usize) -> Self {
        Self {
            lines: vec![Line::default(); len.div_ceil(8)],
            len,
        }
    }
}

impl std::ops::Deref for Aligned {
    type Target = [f64];
    fn deref(&self) -> &[f64] {
        // SAFETY: `Line` is `repr(C)` over `[f64; 8]`, 64 bytes without
        // padding, so the lines are `8 · lines.len() >= len` contiguous,
        // initialised f64.
        unsafe { std::slice::from_raw_parts(self.lines.as_ptr().cast(), self.len) }
    }
}

impl std::ops::DerefMut for Aligned {
    fn deref_mut(&mut self) -> &mut [f64] {
        // SAFETY: as in `deref`, through the unique borrow.
        unsafe { std::slice::from_raw_parts_mut(self.lines.as_mut_ptr().cast(), self.len) }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Every entry of [`sq_dists_cols`] is [`sq_dist`] of its two vectors,
    /// bit for bit: row counts around the three-row blocks, widths around
    /// the 16- and 8-vector panels (full and masked), `k` with and without
    /// a remainder of four, ranges of vectors from every start and to every
    /// end; on the AVX-512
    /// kernel and the fallback. Fails if the kernel's order of summation
    /// changes or it rounds the square before adding it (values with many
    /// significant bits, so roundings differ).
    #[test]
    fn sq_dists_cols_is_sq_dist_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for &(m, k, n) in &[
            (1, 1, 1),
            (2, 3, 9),
            (3, 4, 16),
            (4, 7, 17),
            (7, 80, 41),
            (5, 13, 33),
        ] {
            let a: Vec<f64> = (0..m * k).map(|_| rng.random_range(-3.0..3.0)).collect();
            let v: Vec<f64> = (0..n * k).map(|_| rng.random_range(-3.0..3.0)).collect();
            let mut bt = vec![0.0; k * n];
            transpose(&v, n, k, &mut bt);
            for (c0, c1) in (0..=n).flat_map(|c0| [(c0, n), (c0, (c0 + 9).min(n)), (0, c0)]) {
                let w = c1 - c0;
                for no512 in [false, true] {
                    let mut got = vec![f64::NAN; m * w + 2];
                    let mut run = || sq_dists_cols(&a, &bt, k, n, c0..c1, &mut got);
                    if no512 {
                        crate::wide::without_avx512(run);
                    } else {
                        run();
                    }
                    for i in 0..m {
                        for j in 0..w {
                            let want = sq_dist(&a[i * k..(i + 1) * k], &v[(c0 + j) * k..(c0 + j + 1) * k]);
                            assert_eq!(
                                got[i * w + j].to_bits(),
                                want.to_bits(),
                                "m {m} k {k} n {n} {c0}..{c1} ({i}, {j}) no512 {no512}"
                            );
                        }
                    }
                    assert!(got[m * w..].iter().all(|g| g.is_nan()), "wrote past its rows");
                }
            }
        }
    }

    /// [`gemm_nn`] gives [`gemm_nt`]'s bits over the materialised operands,
    /// for row-major and transposed views, edge widths (masked lanes),
    /// odd row counts and `k` with and without a remainder, on the
    /// AVX-512 kernel and the fallback.
    #[test]
    fn gemm_nn_is_gemm_nt_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let mut cases = 0;
        for &(m, k, n) in &[
            (1, 1, 1),
            (2, 3, 5),
            (3, 4, 8),
            (5, 7, 9),
            (20, 80, 60),
            (20, 60, 80),
            (60, 20, 80),
            (30, 20, 77),
            (20, 77, 30),
            (7, 0, 3),
            (4, 13, 17),
            (3, 16, 16),
        ] {
            let am: Vec<f64> = (0..m * k).map(|_| rng.random_range(-2.0..2.0)).collect();
            let at: Vec<f64> = (0..m * k).map(|_| rng.random_range(-2.0..2.0)).collect();
            let b: Vec<f64> = (0..k * n).map(|_| rng.random_range(-2.0..2.0)).collect();
            let mut bt = vec![0.0; k * n];
            transpose(&b, k, n, &mut bt);
            // `at` holds a k x m matrix whose transpose is the operand.
            let mut at_rows = vec![0.0; m * k];
            transpose(&at, k, m, &mut at_rows);
            for (view, rows) in [
                (View::rows_of(&am, m, k), &am),
                (View::transpose_of(&at, k, m), &at_rows),
            ] {
                let mut want = vec![0.0; m * n];
                if k > 0 {
                    gemm_nt(rows, &bt, k, &mut want);
                }
                // The kernel picked, the AVX2 one (`nn256`), and no vector
                // kernel (the operands materialised).
                for path in ["picked", "avx2", "baseline"] {
                    let mut got = vec![f64::NAN; m * n + 3];
                    match path {
                        "picked" => gemm_nn(view, &b, n, &mut got),
                        "avx2" => crate::wide::without_avx512(|| gemm_nn(view, &b, n, &mut got)),
                        _ => crate::wide::baseline_only(|| gemm_nn(view, &b, n, &mut got)),
                    }
                    let same = want.iter().zip(&got).all(|(x, y)| x.to_bits() == y.to_bits());
                    assert!(same, "m {m} k {k} n {n} path {path}");
                    assert!(got[m * n..].iter().all(|x| x.is_nan()), "wrote past m·n");
                    cases += 1;
                }
            }
        }
        assert_eq!(cases, 72);
    }

    /// Each term is fused into its partial sum on every path: values where
    /// a separate multiply and add would round differently (the module
    /// docs' order), in lane 0 of the chunks and in the remainder, through
    /// the narrow kernels (few rows of `b`), the tiles (many), the AVX2 and
    /// the baseline paths. Fails when any kernel multiplies and adds apart.
    #[test]
    fn every_path_fuses_each_term() {
        let e = |p: i32| 2f64.powi(p);
        // dot: -1 + (1 + 2^-30)(1 - 2^-30) = -2^-60 exactly when fused; the
        // product rounds to 1 on its own, which gives 0.
        // sq_dist: 2^-54 + 2^-54 + (1 + 2^-30)^2 rounds to 1 + 2^-29 + 2^-52
        // when fused; the square rounded on its own leaves a tie that rounds
        // to 1 + 2^-29.
        let (dot_want, sq_want) = (-e(-60), 1.0 + e(-29) + e(-52));
        for k in [3usize, 12, 14] {
            let lane = |v: [f64; 3]| -> Vec<f64> {
                let mut r = vec![0.0; k];
                let step = if k == 3 { 1 } else { 4 };
                for (i, x) in v.into_iter().enumerate() {
                    r[i * step] = x;
                }
                r
            };
            let (da, db) = (lane([0.0, -1.0, 1.0 + e(-30)]), lane([0.0, 1.0, 1.0 - e(-30)]));
            let (sa, sb) = (lane([e(-27), e(-27), 1.0 + e(-30)]), vec![0.0; k]);
            assert_eq!(dot(&da, &db), dot_want, "dot, k = {k}");
            assert_eq!(sq_dist(&sa, &sb), sq_want, "sq_dist, k = {k}");
            let rows = |r: &[f64], m: usize| r.repeat(m);
            let check = |what: &str| {
                for (m, n) in [(70, 3), (70, 70), (5, 9), (70, 17), (67, 26)] {
                    let mut g = vec![f64::NAN; m * n];
                    gemm_nt(&rows(&da, m), &rows(&db, n), k, &mut g);
                    assert!(
                        g.iter().all(|&v| v == dot_want),
                        "{what} gemm_nt {m}x{n}x{k}: {g:?}"
                    );
                    let mut d = vec![f64::NAN; m * n];
                    sq_dists(&rows(&sa, m), &rows(&sb, n), k, &mut d);
                    assert!(d.iter().all(|&v| v == sq_want), "{what} sq_dists {m}x{n}x{k}");
                }
            };
            check("widest");
            crate::wide::without_avx512(|| check("AVX2"));
            crate::wide::baseline_only(|| {
                check("baseline");
                assert_eq!(dot(&da, &db), dot_want);
                assert_eq!(sq_dist(&sa, &sb), sq_want);
            });
        }
    }

    #[test]
    fn tiles_match_the_scalar_kernels_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        // Shapes that exercise full tiles, ragged edges and a k remainder.
        for (m, n, k) in [
            (5, 9, 7),
            (2, 4, 8),
            (1, 1, 3),
            (7, 13, 80),
            (4, 3, 16),
            (3, 0, 5),
            (9, 30, 16),
            (5, 17, 30),
            (3, 64, 32),
            (3, 64, 80),
            (2, 65, 80),
            (4, 1, 1),
            (6, 33, 2),
            (3155, 30, 60),
            (7, 30, 80),
            (5, 61, 80),
            (1, 7, 81),
            (3, 2, 4),
            (130, 60, 80),
            (65, 17, 30),
            // Columns past the AVX-512 panels as dot products: one and
            // two, rows in fours and not, a `k` remainder.
            (67, 26, 13),
            (66, 10, 4),
            (71, 25, 1),
            (64, 64, 128),
            (70, 9, 7),
            (129, 8, 16),
            (96, 1, 129),
            // Rows in fours and not (the AVX-512 tiles, then AVX2 ones).
            (9, 70, 5),
            (13, 40, 80),
            (6, 9, 4),
            (17, 66, 3155),
        ] {
            let a: Vec<f64> = (0..m * k).map(|_| rng.random_range(-3.0..3.0)).collect();
            let b: Vec<f64> = (0..n * k).map(|_| rng.random_range(-3.0..3.0)).collect();
            let mut g = vec![f64::NAN; m * n];
            let mut d = vec![f64::NAN; m * n];
            gemm_nt(&a, &b, k, &mut g);
            sq_dists(&a, &b, k, &mut d);
            let base = crate::wide::baseline_only(|| {
                let mut g2 = vec![0.0; m * n];
                gemm_nt(&a, &b, k, &mut g2);
                g2
            });
            // The AVX2 kernels where the CPU also has AVX-512.
            let (avx2, avx2_d) = crate::wide::without_avx512(|| {
                let mut g2 = vec![0.0; m * n];
                gemm_nt(&a, &b, k, &mut g2);
                let mut d2 = vec![0.0; m * n];
                sq_dists(&a, &b, k, &mut d2);
                (g2, d2)
            });
            let bits = |v: &[f64]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&avx2), bits(&g), "{m}x{n}x{k}");
            assert_eq!(bits(&avx2_d), bits(&d), "{m}x{n}x{k}");
            for i in 0..m {
                for j in 0..n {
                    let (x, y) = (&a[i * k..(i + 1) * k], &b[j * k..(j + 1) * k]);
                    assert_eq!(
                        g[i * n + j].to_bits(),
                        dot(x, y).to_bits(),
                        "dot {m}x{n}x{k} ({i},{j})"
                    );
                    assert_eq!(d[i * n + j].to_bits(), sq_dist(x, y).to_bits(), "dist ({i},{j})");
                    assert_eq!(base[i * n + j].to_bits(), g[i * n + j].to_bits());
                }
            }
        }
    }

    #[test]
    fn aligned_buffers_start_on_a_line_and_hold_their_values() {
        for len in [0, 1, 7, 8, 9, 80 * 64, 12_345] {
            let mut a = Aligned::zeros(len);
            assert_eq!(a.len(), len);
            assert!(a.iter().all(|&v| v == 0.0));
            if len > 0 {
                assert_eq!(a.as_ptr() as usize % 64, 0, "{len} values");
            }
            a.iter_mut().enumerate().for_each(|(i, v)| *v = i as f64);
            let b = a.clone();
            assert_eq!(b, a);
            if len > 0 {
                assert_eq!(b.as_ptr() as usize % 64, 0, "clone of {len}");
                assert_eq!(b[len - 1], (len - 1) as f64);
            }
        }
    }
}
