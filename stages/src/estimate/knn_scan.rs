//! The exact k-nearest-neighbour search of [`super::classic::Knn`]: every
//! training vector is compared with every query in `f32`, through the
//! identity `‖z − x‖² = ‖z‖² + ‖x‖² − 2 z·x` and a tiled product, and only
//! the few vectors that a rigorous rounding margin cannot exclude get their
//! exact distance, [`dense::sq_dist`] of the standardised `f64` vectors. So
//! the answer is exactly the full `f64` scan's: the `k` smallest
//! `(distance, index)` pairs, ties to the earlier training vector.
//!
//! # Why a brute-force scan
//!
//! It replaced a pruned index (principal axes, blocks with bounding boxes,
//! a k-d order) that computed ~12% of the coordinate terms: that index cost
//! ~2.2 ms to build (3060 x 80 training vectors), which a model pays at its
//! first prediction, and its branchy search ran at a small share of the
//! machine's multiply rate. The scan builds in a copy (the vectors in `f32`,
//! their norms) and its product is a dense multiply-add kernel: on the
//! `benches/peers` k-NN workload it both builds and searches faster (the
//! numbers are in docs/benches.md). With AVX2 the build's norms and its
//! transpose into the lane layout are vector kernels (`x86::norms_of`,
//! `x86::neg2_block`) doing the scalar loops' operations, so the same bits
//! (test `the_wide_build_is_the_scalar_build_bit_for_bit`).
//!
//! # The scan ([`Scan::search`])
//!
//! With `z` a query and `x_j` the training vectors (standardised, `f64`),
//! `z' = f32(z)`, `x'_j = f32(x_j)`, `n = dim`, `u = 2⁻²⁴` (`f32`'s unit
//! roundoff) and `v = 2⁻⁵³` (`f64`'s):
//!
//! * stored per training vector: `−2 x'_j` (exact) and `b_j = f32(‖x'_j‖²)`
//!   (the squares of `f32` values are exact in `f64`);
//! * computed per pair: `r̃_j = b_j + Σᵢ z'ᵢ (−2 x'_jᵢ)`, an `f32`
//!   multiply-add chain started at `b_j` (fused or not), which approximates
//!   `r_j = ‖x'_j‖² − 2 z'·x'_j`, so that `D'_j = ‖z'‖² + r_j` is the exact
//!   squared distance of the rounded vectors.
//!
//! Bounds, with `N_z = ‖z'‖²`, `N_X = max_j ‖x'_j‖²`, `e = u ‖z‖ + u max_j
//! ‖x_j‖` (plus an absolute slack for underflow, here and below):
//!
//! 1. `|r̃_j − r_j| ≤ ε = 1.02 (n + 4) u (N_z + 2 N_X)`: a chain of `n`
//!    rounded products and sums from a start `c` errs by at most
//!    `γ_{n+1} (|c| + Σ|pᵢ|)`, with `Σ|pᵢ| ≤ 2 ‖z'‖ ‖x'_j‖ ≤ N_z + N_X`,
//!    plus the rounding of `b_j` (`u ‖x'_j‖²`). The 2% margin also covers the
//!    `f64` rounding of the norms and of the few operations below.
//! 2. `|√D_j − √D'_j| ≤ e` for the exact distance `D_j = ‖z − x_j‖²`
//!    (triangle inequality: rounding to `f32` moves each vector by at most
//!    `u` times its norm).
//! 3. The computed exact distance `D̂_j` (any summation order, fused or not) satisfies
//!    `D_j (1 − γ) ≤ D̂_j ≤ D_j (1 + γ)`, `γ = 1.01 (n + 2) v`.
//!
//! A vector may be skipped only when `D̂_j > τ`, `τ` the `k`-th smallest `D̂`
//! (one with `D̂_j = τ` can still win on its index). With `r̃_(k)` the `k`-th
//! smallest `r̃`: those `k` vectors have `D'_j ≤ N_z + r̃_(k) + ε`, hence
//! `τ ≤ U = (1 + γ) (√(N_z + r̃_(k) + ε) + e)²` (2, 3); and a vector with
//! `D̂_j ≤ U` has `D'_j ≤ W = (√(U / (1 − γ)) + e)²`, so `r̃_j ≤ W − N_z + ε`.
//! Every vector below that threshold (rounded up to `f32`) is offered, in
//! index order, with its exact `D̂_j`, to the `k`-list: every candidate is
//! among them. On the peers workload (`k = 10`) ~10.6 vectors a query pass
//! it (a temporary counter over its 3154 queries).
//!
//! Inputs out of range are not scanned here: the scan is not built when a
//! training value is not finite or a squared norm exceeds [`LIMIT`] (so no
//! `f32` sum can overflow), and a query that is not finite or beyond it is
//! compared exactly with every vector, as the full scan does.
//!
//! # The kernel
//!
//! Training vectors in blocks of `LANES`, coordinate-major (one 16-lane
//! `f32` vector per coordinate of a block), so a query coordinate broadcast
//! against a block's coordinate advances 16 pairs at once. With AVX-512
//! (and FMA) a register tile holds `QT` queries against two blocks (12
//! accumulators), each coordinate costing 2 loads, 6 broadcasts and 12 fused
//! multiply-adds; without AVX-512 the same loop is written on 16-lane arrays
//! that the compiler vectorises (multiply, then add). Both feed the same
//! bounds (a fused multiply-add rounds once, within them), so the two may
//! pass different vectors through the threshold but give the same answer.

use super::dense;
use std::sync::OnceLock;

/// Training vectors per block (one AVX-512 register of `f32`).
pub(crate) const LANES: usize = 16;
/// Queries per register tile.
const QT: usize = 6;
/// Queries scored per pass over the training blocks (a multiple of [`QT`]):
/// their `f32` rows (48 x 80 x 4 bytes on the peers set) stay in L1 while
/// the blocks stream past.
const QB: usize = 8 * QT;
/// Largest squared norm of a training vector or query the scan takes: every
/// partial sum of the kernel stays below `3·10³⁰`, far from `f32`'s `3·10³⁸`.
pub const LIMIT: f64 = 1e30;
/// Most coordinates (keeps `γ_{n+1}` of `f32` below 1%).
const MAX_DIM: usize = 100_000;
/// Absolute slack for underflow in the bounds.
const ABS: f64 = 1e-30;
/// `f32`'s unit roundoff, `2⁻²⁴`.
const U32: f64 = 1.0 / 16_777_216.0;

/// A [`Scan`] built on first use, for a model field that is not saved: it
/// compares equal to any other (it is derived from the model's data).
#[derive(Clone, Default)]
pub struct ScanCell(OnceLock<Option<Scan>>);

impl ScanCell {
    /// The scan of `x` (built on the first call; later calls must pass the
    /// same rows), `None` when [`Scan::build`] declines them.
    pub fn get(&self, x: &[f64], dim: usize) -> Option<&Scan> {
        self.0.get_or_init(|| Scan::build(x, dim)).as_ref()
    }
}

impl PartialEq for ScanCell {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for ScanCell {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0.get() {
            None => f.write_str("ScanCell(not built)"),
            Some(None) => f.write_str("ScanCell(exact scan)"),
            Some(Some(s)) => write!(f, "ScanCell({} vectors)", s.n),
        }
    }
}

/// The training vectors in the scan's layout (module docs).
#[derive(Clone)]
pub struct Scan {
    dim: usize,
    n: usize,
    blocks: usize,
    /// `−2 x'_j`: block `b`, coordinate `i`, lane `l` at
    /// `(b·dim + i)·LANES + l` (vector `j = b·LANES + l`; empty lanes 0).
    neg2: Vec<f32>,
    /// `f32(‖x'_j‖²)` per vector, `+inf` in empty lanes (never kept).
    base: Vec<f32>,
    /// `N_X`.
    nx_max: f64,
    /// `u·max_j ‖x_j‖` plus the absolute slack.
    e_x: f64,
}

/// Buffers reused across the queries of a batch.
#[derive(Default)]
struct Scratch {
    zq: Vec<f32>,
    r: Vec<f32>,
    sel: Select,
}

/// [`Scan::candidates`]' buffers.
#[derive(Default)]
struct Select {
    mins: Vec<f32>,
    vals: Vec<f32>,
    cand: Vec<(f32, usize)>,
}

impl Scan {
    /// The scan of the rows of `x` (`dim` wide), or `None` when a value is
    /// not finite, a squared norm exceeds [`LIMIT`], `dim` is 0 or above
    /// 100 000, or `x` is not whole rows.
    pub fn build(x: &[f64], dim: usize) -> Option<Scan> {
        if dim == 0 || dim > MAX_DIM || !x.len().is_multiple_of(dim) {
            return None;
        }
        let n = x.len() / dim;
        let blocks = n.div_ceil(LANES);
        let mut neg2 = vec![0.0f32; blocks.checked_mul(dim)?.checked_mul(LANES)?];
        let mut base = vec![f32::INFINITY; blocks * LANES];
        let (mut nx_max, mut x_max) = (0.0f64, 0.0f64);
        let mut norms = Vec::with_capacity(n);
        // A plain loop: an iterator adapter's `fold` may be compiled outside
        // the wide function.
        let in_range = crate::wide::with_avx2(
            #[inline(always)]
            || {
                for row in x.chunks_exact(dim) {
                    let (s32, s64) = norms_of(row);
                    // Not finite (a NaN or an infinity makes the sums so) or too large.
                    if !(s32 <= LIMIT && s64 <= LIMIT) {
                        return false;
                    }
                    norms.push((s32, s64));
                }
                true
            },
        );
        if !in_range {
            return None;
        }
        for (j, &(s32, s64)) in norms.iter().enumerate() {
            base[j] = s32 as f32;
            nx_max = nx_max.max(s32);
            x_max = x_max.max(s64);
        }
        // Block by block, so the writes are sequential and a block's 16 rows
        // (read coordinate by coordinate) stay in L1.
        #[cfg(target_arch = "x86_64")]
        let wide = crate::wide::avx2();
        for (b, out) in neg2.chunks_exact_mut(dim * LANES).enumerate() {
            let rows = &x[b * LANES * dim..((b + 1) * LANES).min(n) * dim];
            #[cfg(target_arch = "x86_64")]
            if wide && rows.len() == LANES * dim {
                // SAFETY: the CPU has AVX2 (`wide::avx2`); a whole block of
                // rows and its output, sizes checked in the kernel.
                unsafe { x86::neg2_block(rows, dim, out) };
                continue;
            }
            neg2_block(rows, dim, 0, out);
        }
        Some(Scan {
            dim,
            n,
            blocks,
            neg2,
            base,
            nx_max,
            e_x: U32 * x_max.sqrt() * (1.0 + 1e-6) + ABS,
        })
    }

    /// The `k` nearest training rows of each standardised query row of `z`
    /// (rows of `x`, the `f64` vectors the scan was built from), passed to
    /// `each(query, neighbours)` in query order as `(D̂, index)` pairs,
    /// nearest first: exactly the `k` smallest pairs of the full scan.
    pub fn search(&self, x: &[f64], z: &[f64], k: usize, mut each: impl FnMut(usize, &[(f64, usize)])) {
        let dim = self.dim;
        let k = k.min(self.n);
        let nq = z.len() / dim;
        let stride = self.blocks * LANES;
        let mut s = Scratch::default();
        s.zq.resize(QB * dim, 0.0);
        s.r.resize(QB * stride, 0.0);
        let mut best: Vec<(f64, usize)> = Vec::with_capacity(k + 1);
        let mut info = [(0.0f64, 0.0f64, false); QB];
        for q0 in (0..nq).step_by(QB) {
            let qb = QB.min(nq - q0);
            for (q, zr) in z[q0 * dim..(q0 + qb) * dim].chunks_exact(dim).enumerate() {
                let row = &mut s.zq[q * dim..(q + 1) * dim];
                for (o, &v) in row.iter_mut().zip(zr) {
                    *o = v as f32;
                }
                let (nz, z2) = norms_of(zr);
                let ok = nz <= LIMIT && z2 <= LIMIT;
                if !ok {
                    row.iter_mut().for_each(|o| *o = 0.0);
                }
                info[q] = (nz, z2.sqrt(), ok);
            }
            // Rows past the batch's end keep what they held: finite values
            // whose results are not read.
            self.partials(&s.zq, &mut s.r, qb.div_ceil(QT) * QT);
            // The selection's loops compiled for the widest vectors too.
            let wide = crate::wide::avx512();
            crate::wide::with_avx2(
                #[inline(always)]
                || {
                    for (q, &(nz, zn, ok)) in info[..qb].iter().enumerate() {
                        let zr = &z[(q0 + q) * dim..(q0 + q + 1) * dim];
                        best.clear();
                        if k > 0 && ok {
                            let t = self.candidates(
                                &s.r[q * stride..(q + 1) * stride],
                                k,
                                nz,
                                zn,
                                &mut s.sel,
                                wide,
                            );
                            for &(v, j) in &s.sel.cand {
                                if v <= t {
                                    offer(&mut best, k, dense::sq_dist(zr, &x[j * dim..(j + 1) * dim]), j);
                                }
                            }
                        } else if k > 0 {
                            for (j, xr) in x.chunks_exact(dim).take(self.n).enumerate() {
                                offer(&mut best, k, dense::sq_dist(zr, xr), j);
                            }
                        }
                        each(q0 + q, &best);
                    }
                },
            );
        }
    }

    /// The vectors that may be among the `k` nearest of a query whose `r̃`
    /// row is `r` (`1 ≤ k ≤ n`), as `(r̃, j)` in index order in `s.cand`,
    /// and the threshold they are to be kept below (module docs):
    ///
    /// 1. `t₀`, the `k`-th smallest of the minima of `16·g` disjoint sets
    ///    (lane `l` of a run of chunks), bounds `r̃_(k)` from above: `k`
    ///    vectors are at or below it. (On the peers set, `k = 10`, `g = 2`:
    ///    ~30 of the 3060 vectors are at or below its threshold, and ~10.6
    ///    below the final one, counted over its 3154 queries.)
    /// 2. Every vector at or below the threshold of `t₀` goes to `s.cand`
    ///    (the threshold grows with `r̃_(k)`, so this holds every vector below
    ///    the final one): a vector comparison per chunk, rarely true.
    /// 3. `r̃_(k)` is the `k`-th smallest of them, and its threshold the answer.
    #[inline(always)]
    fn candidates(&self, r: &[f32], k: usize, nz: f64, zn: f64, s: &mut Select, wide: bool) -> f32 {
        let chunks = r.len() / LANES;
        let g = (2 * k).div_ceil(LANES).clamp(1, chunks.max(1));
        let per = chunks.div_ceil(g).max(1);
        s.mins.clear();
        for run in r.chunks(per * LANES) {
            let mut m = [f32::INFINITY; LANES];
            for c in run.chunks_exact(LANES) {
                for l in 0..LANES {
                    // Values are finite or +inf (empty lanes): a plain minimum.
                    if c[l] < m[l] {
                        m[l] = c[l];
                    }
                }
            }
            s.mins.extend_from_slice(&m);
        }
        let t0 = kth(&mut s.mins, k);
        let t1 = if t0.is_finite() {
            self.threshold(t0, nz, zn)
        } else {
            f32::INFINITY
        };
        s.cand.clear();
        for (b, c) in r.chunks_exact(LANES).enumerate() {
            // One vector comparison per chunk, then only the lanes that hit
            // (rare: ~30 vectors a query on the peers set, most chunks with one).
            let mut hits = at_or_below(c, t1, wide);
            while hits != 0 {
                let j = b * LANES + hits.trailing_zeros() as usize;
                hits &= hits - 1;
                if j < self.n {
                    s.cand.push((r[j], j));
                }
            }
        }
        s.vals.clear();
        s.vals.extend(s.cand.iter().map(|c| c.0));
        self.threshold(kth(&mut s.vals, k), nz, zn)
    }

    /// The `f32` threshold on `r̃` below which a vector may be a neighbour
    /// (module docs), from `r̃_(k)`, `N_z` and `‖z‖`.
    fn threshold(&self, rk: f32, nz: f64, zn: f64) -> f32 {
        let n = self.dim as f64;
        let gamma = 1.01 * (n + 2.0) * (f64::EPSILON / 2.0);
        let eps = 1.02 * (n + 4.0) * U32 * (nz + 2.0 * self.nx_max) + ABS;
        let e = U32 * zn * (1.0 + 1e-6) + ABS + self.e_x;
        let dk = (nz + f64::from(rk) + eps).max(0.0);
        let u = (1.0 + gamma) * (dk.sqrt() + e).powi(2);
        let w = ((u / (1.0 - gamma)).sqrt() + e).powi(2);
        // The relative slack covers this function's own roundings.
        let t = (w + eps - nz) + 1e-9 * (w + eps + nz) + ABS;
        let t32 = t as f32;
        if f64::from(t32) < t {
            t32.next_up()
        } else {
            t32
        }
    }

    /// `r̃` of the first `rows` query rows of `zq` (a multiple of [`QT`], at
    /// most [`QB`]) against every training vector, into rows of `r`
    /// ([`LANES`]` · blocks` wide). (A lone query, as a fit scores, costs
    /// one tile, not a batch's.)
    fn partials(&self, zq: &[f32], r: &mut [f32], rows: usize) {
        #[cfg(target_arch = "x86_64")]
        if crate::wide::avx512() && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has AVX-512 F and FMA (checked just above);
            // the kernel checks the slices' sizes against `rows`.
            unsafe { x86::partials(&self.neg2, &self.base, self.dim, self.blocks, zq, r, rows) };
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if crate::wide::avx2() {
            // SAFETY: the CPU has AVX2 and FMA (`wide::avx2` checks both);
            // the kernel checks the slices' sizes against `rows`.
            unsafe { x86::partials256(&self.neg2, &self.base, self.dim, self.blocks, zq, r, rows) };
            return;
        }
        crate::wide::with_avx2(
            #[inline(always)]
            || self.partials_lanes(zq, r, rows),
        );
    }

    /// [`Self::partials`] on 16-lane arrays (any CPU): a block against the
    /// queries two at a time, multiply then add.
    #[inline(always)]
    fn partials_lanes(&self, zq: &[f32], r: &mut [f32], rows: usize) {
        let (dim, stride) = (self.dim, self.blocks * LANES);
        for (b, xb) in self.neg2.chunks_exact(dim * LANES).enumerate() {
            let start: &[f32; LANES] = self.base[b * LANES..(b + 1) * LANES]
                .try_into()
                .unwrap_or(&[0.0; LANES]);
            for q in (0..rows).step_by(2) {
                let (mut a0, mut a1) = (*start, *start);
                let (z0, z1) = (&zq[q * dim..(q + 1) * dim], &zq[(q + 1) * dim..(q + 2) * dim]);
                for ((xi, &u0), &u1) in xb.chunks_exact(LANES).zip(z0).zip(z1) {
                    for l in 0..LANES {
                        a0[l] += u0 * xi[l];
                        a1[l] += u1 * xi[l];
                    }
                }
                r[q * stride + b * LANES..][..LANES].copy_from_slice(&a0);
                r[(q + 1) * stride + b * LANES..][..LANES].copy_from_slice(&a1);
            }
        }
    }
}

/// Bit `l` set when `c[l] ≤ t` ([`LANES`] values): one AVX-512 comparison
/// when `wide` ([`crate::wide::avx512`]), else a test of all lanes at once and the
/// lanes one by one only when one is.
#[inline(always)]
fn at_or_below(c: &[f32], t: f32, wide: bool) -> u32 {
    #[cfg(target_arch = "x86_64")]
    if wide {
        // SAFETY: `wide` is true only when the CPU has AVX-512 F.
        return unsafe { x86::at_or_below(c, t) };
    }
    let _ = wide;
    if c.iter().fold(0u32, |a, &v| a | u32::from(v <= t)) == 0 {
        return 0;
    }
    c.iter()
        .enumerate()
        .fold(0u32, |a, (l, &v)| a | (u32::from(v <= t) << l))
}

/// `(‖f32(v)‖², ‖v‖²)` in `f64`, each summed in eight lanes (any order is
/// within the bounds' margin; one running sum per row was a chain of
/// dependent additions, most of a build). Lane `l` sums the elements
/// `l, l + 8, ...` in order, then the lanes are added 0 to 7: the AVX2
/// kernel ([`x86::norms_of`]) does the same operations, so the same bits.
#[inline(always)]
fn norms_of(v: &[f64]) -> (f64, f64) {
    #[cfg(target_arch = "x86_64")]
    if crate::wide::avx2() {
        // SAFETY: the CPU has AVX2 (`wide::avx2` checks it).
        return unsafe { x86::norms_of(v) };
    }
    let (mut a, mut b) = ([0.0f64; 8], [0.0f64; 8]);
    let c = v.chunks_exact(8);
    let rest = c.remainder();
    for ch in c {
        for l in 0..8 {
            let w = f64::from(ch[l] as f32);
            a[l] += w * w;
            b[l] += ch[l] * ch[l];
        }
    }
    norms_tail(a, b, rest)
}

/// `−2·f32(x)` of a block's rows into the scan's layout (coordinate `i`,
/// lane `l` at `i·LANES + l`), coordinates `from..dim` of each row.
#[inline(always)]
fn neg2_block(rows: &[f64], dim: usize, from: usize, out: &mut [f32]) {
    for (l, row) in rows.chunks_exact(dim).enumerate() {
        for (i, &v) in row.iter().enumerate().skip(from) {
            out[i * LANES + l] = -2.0 * (v as f32);
        }
    }
}

/// [`norms_of`]'s end: the elements after the last whole eight into their
/// lanes, then each set of lanes summed.
#[inline(always)]
fn norms_tail(mut a: [f64; 8], mut b: [f64; 8], rest: &[f64]) -> (f64, f64) {
    for (l, &x) in rest.iter().enumerate() {
        let w = f64::from(x as f32);
        a[l] += w * w;
        b[l] += x * x;
    }
    (a.iter().sum(), b.iter().sum())
}

/// The `k`-th smallest of `v` (reordered), `+inf` when it has fewer than `k`.
/// (A sorted insertion into a list on the stack instead, for `k ≤ 32`, took
/// more samples than this selection on the peers set: the minima arrive in
/// no order, so most values shift the list.)
fn kth(v: &mut [f32], k: usize) -> f32 {
    if k == 0 || v.len() < k {
        return f32::INFINITY;
    }
    *v.select_nth_unstable_by(k - 1, f32::total_cmp).1
}

/// Offers vector `j` at exact distance `d2` to `best`, the `k` smallest
/// `(distance, index)` pairs so far in that order (vectors are offered in
/// index order, so an equal distance keeps the earlier vector first; a
/// distance that is not finite is never a neighbour).
#[inline]
pub(crate) fn offer(best: &mut Vec<(f64, usize)>, k: usize, d2: f64, j: usize) {
    if k == 0 || !d2.is_finite() || (best.len() == k && d2 >= best[k - 1].0) {
        return;
    }
    let pos = best.partition_point(|&(d, _)| d <= d2);
    best.insert(pos, (d2, j));
    best.truncate(k);
}

/// The AVX-512 + FMA kernel (module docs), and its AVX2 + FMA form.
#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{LANES, QB, QT};
    use std::arch::x86_64::*;

    /// [`super::at_or_below`] in one comparison.
    ///
    /// # Safety
    /// The CPU must have AVX-512 F; `c` holds at least [`LANES`] values.
    #[inline]
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn at_or_below(c: &[f32], t: f32) -> u32 {
        assert!(c.len() >= LANES);
        // SAFETY: 16 values from `c` (checked above); the CPU has AVX-512 F.
        unsafe {
            u32::from(_mm512_cmp_ps_mask::<_CMP_LE_OQ>(
                _mm512_loadu_ps(c.as_ptr()),
                _mm512_set1_ps(t),
            ))
        }
    }

    /// [`super::norms_of`] with its eight lanes in two registers of four
    /// (the compiler, left to itself, packed two lanes at a time with
    /// shuffles between: 0.47 of a 0.72 ms build of 3060 x 80 vectors).
    /// Multiply then add, as the scalar code (Rust never fuses them), and
    /// `_mm256_cvtpd_ps` rounds to nearest as `as f32` does.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn norms_of(v: &[f64]) -> (f64, f64) {
        let c = v.chunks_exact(8);
        let rest = c.remainder();
        let (mut a, mut b) = ([0.0f64; 8], [0.0f64; 8]);
        // SAFETY: each chunk holds 8 values; the stores write 4 of 8 each.
        unsafe {
            let (mut a0, mut a1) = (_mm256_setzero_pd(), _mm256_setzero_pd());
            let (mut b0, mut b1) = (_mm256_setzero_pd(), _mm256_setzero_pd());
            for ch in c {
                let x0 = _mm256_loadu_pd(ch.as_ptr());
                let x1 = _mm256_loadu_pd(ch.as_ptr().add(4));
                let w0 = _mm256_cvtps_pd(_mm256_cvtpd_ps(x0));
                let w1 = _mm256_cvtps_pd(_mm256_cvtpd_ps(x1));
                a0 = _mm256_add_pd(a0, _mm256_mul_pd(w0, w0));
                a1 = _mm256_add_pd(a1, _mm256_mul_pd(w1, w1));
                b0 = _mm256_add_pd(b0, _mm256_mul_pd(x0, x0));
                b1 = _mm256_add_pd(b1, _mm256_mul_pd(x1, x1));
            }
            _mm256_storeu_pd(a.as_mut_ptr(), a0);
            _mm256_storeu_pd(a.as_mut_ptr().add(4), a1);
            _mm256_storeu_pd(b.as_mut_ptr(), b0);
            _mm256_storeu_pd(b.as_mut_ptr().add(4), b1);
        }
        super::norms_tail(a, b, rest)
    }

    /// [`super::neg2_block`] of a whole block (16 rows) on AVX2: eight
    /// coordinates of the 16 rows at a time, rounded to `f32` and doubled
    /// (the same two roundings as the scalar code: `f32` first, then the
    /// exact `−2·` in `f32`), then two 8 x 8 transposes, so that each
    /// coordinate's 16 lanes are written as two whole vectors instead of 16
    /// scattered values (0.21 ms of a 0.44 ms build on 3060 x 80 vectors).
    /// The coordinates after the last whole eight go through the scalar code.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn neg2_block(rows: &[f64], dim: usize, out: &mut [f32]) {
        assert!(rows.len() == LANES * dim && out.len() >= LANES * dim);
        let whole = dim / 8 * 8;
        // SAFETY: row `r`'s coordinates `i..i + 8` lie in `rows` (i + 8 <=
        // dim, r < 16); the outputs `(i + c)·16 .. + 16` lie in `out`.
        unsafe {
            let m2 = _mm256_set1_ps(-2.0);
            let tile = |r0: usize, i: usize| -> [__m256; 8] {
                let mut v = [_mm256_setzero_ps(); 8];
                for (k, v) in v.iter_mut().enumerate() {
                    let p = rows.as_ptr().add((r0 + k) * dim + i);
                    let lo = _mm256_cvtpd_ps(_mm256_loadu_pd(p));
                    let hi = _mm256_cvtpd_ps(_mm256_loadu_pd(p.add(4)));
                    *v = _mm256_mul_ps(m2, _mm256_set_m128(hi, lo));
                }
                transpose8(v)
            };
            for i in (0..whole).step_by(8) {
                let (a, b) = (tile(0, i), tile(8, i));
                for c in 0..8 {
                    let o = out.as_mut_ptr().add((i + c) * LANES);
                    _mm256_storeu_ps(o, a[c]);
                    _mm256_storeu_ps(o.add(8), b[c]);
                }
            }
        }
        super::neg2_block(rows, dim, whole, out);
    }

    /// The transpose of an 8 x 8 tile of `f32` (rows in, columns out).
    #[inline]
    #[target_feature(enable = "avx2")]
    fn transpose8(r: [__m256; 8]) -> [__m256; 8] {
        let t0 = _mm256_unpacklo_ps(r[0], r[1]);
        let t1 = _mm256_unpackhi_ps(r[0], r[1]);
        let t2 = _mm256_unpacklo_ps(r[2], r[3]);
        let t3 = _mm256_unpackhi_ps(r[2], r[3]);
        let t4 = _mm256_unpacklo_ps(r[4], r[5]);
        let t5 = _mm256_unpackhi_ps(r[4], r[5]);
        let t6 = _mm256_unpacklo_ps(r[6], r[7]);
        let t7 = _mm256_unpackhi_ps(r[6], r[7]);
        let u0 = _mm256_shuffle_ps::<0x44>(t0, t2);
        let u1 = _mm256_shuffle_ps::<0xEE>(t0, t2);
        let u2 = _mm256_shuffle_ps::<0x44>(t1, t3);
        let u3 = _mm256_shuffle_ps::<0xEE>(t1, t3);
        let u4 = _mm256_shuffle_ps::<0x44>(t4, t6);
        let u5 = _mm256_shuffle_ps::<0xEE>(t4, t6);
        let u6 = _mm256_shuffle_ps::<0x44>(t5, t7);
        let u7 = _mm256_shuffle_ps::<0xEE>(t5, t7);
        [
            _mm256_permute2f128_ps::<0x20>(u0, u4),
            _mm256_permute2f128_ps::<0x20>(u1, u5),
            _mm256_permute2f128_ps::<0x20>(u2, u6),
            _mm256_permute2f128_ps::<0x20>(u3, u7),
            _mm256_permute2f128_ps::<0x31>(u0, u4),
            _mm256_permute2f128_ps::<0x31>(u1, u5),
            _mm256_permute2f128_ps::<0x31>(u2, u6),
            _mm256_permute2f128_ps::<0x31>(u3, u7),
        ]
    }

    /// The sizes the kernels read and write (their `# Safety` sections).
    fn check_sizes(
        neg2: &[f32],
        base: &[f32],
        dim: usize,
        blocks: usize,
        zq: &[f32],
        r: &[f32],
        rows: usize,
    ) {
        let stride = blocks * LANES;
        assert!(
            rows <= QB
                && rows.is_multiple_of(QT)
                && neg2.len() >= blocks * dim * LANES
                && base.len() >= stride
                && zq.len() >= rows * dim
                && r.len() >= rows * stride
        );
    }

    /// [`super::Scan::partials`]: blocks in pairs (an odd last block is
    /// paired with itself and stored once), queries in tiles of [`QT`].
    ///
    /// # Safety
    /// The CPU must have AVX-512 F and FMA. (The sizes are checked: `neg2`
    /// holds `blocks · dim · LANES` values, `base` `blocks · LANES`, `zq`
    /// `rows · dim` and `r` `rows · blocks · LANES`, `rows` a multiple of
    /// [`QT`] up to [`QB`].)
    #[target_feature(enable = "avx512f,fma")]
    pub(super) unsafe fn partials(
        neg2: &[f32],
        base: &[f32],
        dim: usize,
        blocks: usize,
        zq: &[f32],
        r: &mut [f32],
        rows: usize,
    ) {
        let stride = blocks * LANES;
        check_sizes(neg2, base, dim, blocks, zq, r, rows);
        let (xp, bp, zp, rp) = (neg2.as_ptr(), base.as_ptr(), zq.as_ptr(), r.as_mut_ptr());
        let mut b = 0;
        while b < blocks {
            let b1 = if b + 1 < blocks { b + 1 } else { b };
            // SAFETY (all pointer arithmetic below): b, b1 < blocks, i < dim,
            // q + t < rows, within the lengths asserted above.
            unsafe {
                let (x0, x1) = (xp.add(b * dim * LANES), xp.add(b1 * dim * LANES));
                let (s0, s1) = (
                    _mm512_loadu_ps(bp.add(b * LANES)),
                    _mm512_loadu_ps(bp.add(b1 * LANES)),
                );
                let mut q = 0;
                while q < rows {
                    let mut acc = [[s0, s1]; QT];
                    let z = zp.add(q * dim);
                    for i in 0..dim {
                        let v0 = _mm512_loadu_ps(x0.add(i * LANES));
                        let v1 = _mm512_loadu_ps(x1.add(i * LANES));
                        for (t, a) in acc.iter_mut().enumerate() {
                            let u = _mm512_set1_ps(*z.add(t * dim + i));
                            a[0] = _mm512_fmadd_ps(u, v0, a[0]);
                            a[1] = _mm512_fmadd_ps(u, v1, a[1]);
                        }
                    }
                    for (t, a) in acc.iter().enumerate() {
                        let o = rp.add((q + t) * stride);
                        _mm512_storeu_ps(o.add(b * LANES), a[0]);
                        if b1 != b {
                            _mm512_storeu_ps(o.add(b1 * LANES), a[1]);
                        }
                    }
                    q += QT;
                }
            }
            b += 2;
        }
    }

    /// [`partials`] with 256-bit vectors, for CPUs with AVX2 and FMA but
    /// not AVX-512: one block (two vectors) against [`QT`] queries, 12
    /// accumulators of the 16 registers, each term fused. Before it those
    /// CPUs ran [`super::Scan::partials_lanes`], a multiply and an add a
    /// term and two queries a pass: the peers k-NN prediction took 41 ms
    /// against scikit-learn's 81 on an AVX2-only host (docs/benches.md).
    /// The answer is the same: the bounds hold for fused and unfused chains.
    ///
    /// # Safety
    /// The CPU must have AVX2 and FMA. (The sizes are checked as in
    /// [`partials`].)
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn partials256(
        neg2: &[f32],
        base: &[f32],
        dim: usize,
        blocks: usize,
        zq: &[f32],
        r: &mut [f32],
        rows: usize,
    ) {
        const { assert!(LANES == 16) };
        let stride = blocks * LANES;
        check_sizes(neg2, base, dim, blocks, zq, r, rows);
        let (xp, bp, zp, rp) = (neg2.as_ptr(), base.as_ptr(), zq.as_ptr(), r.as_mut_ptr());
        for b in 0..blocks {
            // SAFETY (all pointer arithmetic below): b < blocks, i < dim,
            // q + t < rows, within the lengths asserted above.
            unsafe {
                let x = xp.add(b * dim * LANES);
                let start = [
                    _mm256_loadu_ps(bp.add(b * LANES)),
                    _mm256_loadu_ps(bp.add(b * LANES + 8)),
                ];
                let mut q = 0;
                while q < rows {
                    let mut acc = [start; QT];
                    let z = zp.add(q * dim);
                    for i in 0..dim {
                        let v0 = _mm256_loadu_ps(x.add(i * LANES));
                        let v1 = _mm256_loadu_ps(x.add(i * LANES + 8));
                        for (t, a) in acc.iter_mut().enumerate() {
                            let u = _mm256_set1_ps(*z.add(t * dim + i));
                            a[0] = _mm256_fmadd_ps(u, v0, a[0]);
                            a[1] = _mm256_fmadd_ps(u, v1, a[1]);
                        }
                    }
                    for (t, a) in acc.iter().enumerate() {
                        let o = rp.add((q + t) * stride + b * LANES);
                        _mm256_storeu_ps(o, a[0]);
                        _mm256_storeu_ps(o.add(8), a[1]);
                    }
                    q += QT;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The reference: every finite `(sq_dist, index)`, the `k` smallest.
    fn full_scan(x: &[f64], dim: usize, z: &[f64], k: usize) -> Vec<(f64, usize)> {
        let mut all: Vec<(f64, usize)> = x
            .chunks_exact(dim)
            .enumerate()
            .map(|(j, r)| (dense::sq_dist(r, z), j))
            .filter(|p| p.0.is_finite())
            .collect();
        all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        all.truncate(k);
        all
    }

    fn bits(v: &[(f64, usize)]) -> Vec<(u64, usize)> {
        v.iter().map(|&(d, j)| (d.to_bits(), j)).collect()
    }

    /// Every query's list from the scan, with the AVX-512 kernel (where the
    /// CPU has it) and with the 16-lane loop, which must agree.
    fn scanned(scan: &Scan, x: &[f64], q: &[f64], k: usize) -> Vec<Vec<(u64, usize)>> {
        let run = || {
            let mut out = Vec::new();
            scan.search(x, q, k, |i, best| {
                assert_eq!(i, out.len(), "queries in order");
                out.push(bits(best));
            });
            out
        };
        // The kernel the CPU picks, the AVX2 one and the portable lanes.
        let wide = run();
        let avx2 = crate::wide::without_avx512(run);
        let lanes = crate::wide::baseline_only(run);
        assert_eq!(wide, avx2, "the AVX-512 and AVX2 kernels");
        assert_eq!(wide, lanes, "the vector kernels and the portable lanes");
        assert_eq!(wide.len(), q.len() / scan.dim, "one list per query");
        wide
    }

    fn check(x: &[f64], dim: usize, q: &[f64], k: usize) {
        let scan = Scan::build(x, dim).expect("finite rows in range");
        for (i, got) in scanned(&scan, x, q, k).into_iter().enumerate() {
            let z = &q[i * dim..(i + 1) * dim];
            assert_eq!(got, bits(&full_scan(x, dim, z, k)), "query {i}, k {k}, dim {dim}");
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// Coarse values (ties, duplicate rows), 1-row sets, dim 1, `k` above
        /// the training set, tiny to huge magnitudes: the same list as the
        /// full scan (queries out of range are scanned exactly), or an
        /// honest refusal of a training set out of range.
        #[test]
        fn search_is_the_full_scan(
            n in 1usize..70,
            dim in 1usize..7,
            k in 1usize..90,
            scale_exp in prop::sample::select(vec![-300i32, -150, -40, -20, 0, 10, 14, 150]),
            seed in 0u64..1000,
        ) {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let scale = 10f64.powi(scale_exp);
            let mut x: Vec<f64> = (0..n * dim).map(|_| f64::from(rng.random_range(-3i8..4)) * scale).collect();
            if n > 2 {
                let (a, b) = x.split_at_mut(dim);
                b[..dim].copy_from_slice(a);
            }
            let q: Vec<f64> = (0..9 * dim).map(|_| f64::from(rng.random_range(-4i8..5)) * 0.5 * scale).collect();
            match Scan::build(&x, dim) {
                None => prop_assert!(scale_exp >= 150),
                Some(scan) => {
                    for (i, got) in scanned(&scan, &x, &q, k).into_iter().enumerate() {
                        let z = &q[i * dim..(i + 1) * dim];
                        prop_assert_eq!(got, bits(&full_scan(&x, dim, z, k)));
                    }
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        /// Wide rows, an odd number of blocks and a partial last one, more
        /// queries than a batch (and a last batch not a whole tile),
        /// constant columns, duplicate rows and many ties (values on a
        /// coarse grid), `k` from 1 to beyond the training set, queries that
        /// are training rows: the same list as the full scan.
        #[test]
        fn wide_rows_with_ties_and_constant_columns_are_the_full_scan(
            n in 1usize..700,
            dim in prop::sample::select(vec![2usize, 31, 33, 80]),
            k in prop::sample::select(vec![1usize, 2, 10, 17, 40, 800]),
            levels in 2i8..6,
            queries in prop::sample::select(vec![1usize, 7, 50, 101]),
            seed in 0u64..1000,
        ) {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let constant: Vec<bool> = (0..dim).map(|_| rng.random_range(0..4) == 0).collect();
            let mut x: Vec<f64> = Vec::with_capacity(n * dim);
            for r in 0..n {
                if r > 0 && rng.random_range(0..5) == 0 {
                    // A duplicate of an earlier row.
                    let src = rng.random_range(0..r);
                    let row: Vec<f64> = x[src * dim..(src + 1) * dim].to_vec();
                    x.extend(row);
                    continue;
                }
                for &c in &constant {
                    x.push(if c { 1.5 } else { f64::from(rng.random_range(0..levels)) * 0.75 });
                }
            }
            let mut q: Vec<f64> = (0..queries * dim)
                .map(|i| if constant[i % dim] { 1.5 } else { f64::from(rng.random_range(-1..levels + 1)) * 0.75 })
                .collect();
            q.extend_from_slice(&x[..dim.min(x.len())]);
            let scan = Scan::build(&x, dim).expect("finite rows in range");
            for (i, got) in scanned(&scan, &x, &q, k).into_iter().enumerate() {
                let z = &q[i * dim..(i + 1) * dim];
                prop_assert_eq!(got, bits(&full_scan(&x, dim, z, k)), "query {}", i);
            }
        }
    }

    /// Degenerate training sets: one vector, all vectors equal, fewer
    /// vectors than values, constant columns at subnormal and large
    /// magnitudes: a scan (no NaN, no panic) and the full scan's lists.
    #[test]
    fn degenerate_training_sets_are_the_full_scan() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let dim = 80;
        let row: Vec<f64> = (0..dim).map(|_| rng.random_range(-2.0..2.0)).collect();
        let q: Vec<f64> = (0..6 * dim).map(|_| rng.random_range(-2.0..2.0)).collect();
        let one = row.clone();
        let same: Vec<f64> = row.iter().copied().cycle().take(40 * dim).collect();
        let few: Vec<f64> = (0..5 * dim).map(|_| rng.random_range(-2.0..2.0)).collect();
        for x in [one, same, few] {
            for k in [1, 3, 50] {
                check(&x, dim, &q, k);
            }
        }
        for scale in [1e-310, 1e-200, 1e-40, 1e12] {
            let x: Vec<f64> = (0..60 * dim)
                .map(|i| if i % 3 == 0 { 1.0 } else { f64::from(rng.random_range(-3i8..4)) } * scale)
                .collect();
            let qs: Vec<f64> = q.iter().map(|v| v * scale).collect();
            check(&x, dim, &qs, 7);
        }
    }

    /// Clustered data, neighbours near and far, and queries that are
    /// training vectors (distance 0) or within rounding of one.
    #[test]
    fn finds_the_neighbours_of_the_full_scan_on_clustered_data() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (n, dim) = (700, 24);
        let centres: Vec<f64> = (0..8 * dim).map(|_| rng.random_range(-4.0..4.0)).collect();
        let mut x = Vec::new();
        for _ in 0..n {
            let c = rng.random_range(0..8);
            x.extend((0..dim).map(|i| centres[c * dim + i] + rng.random_range(-1.0..1.0)));
        }
        let q: Vec<f64> = (0..40 * dim).map(|_| rng.random_range(-5.0..5.0)).collect();
        for k in [1, 3, 10, 50, 700, 1000] {
            check(&x, dim, &q, k);
        }
        let q: Vec<f64> = x[..30 * dim]
            .iter()
            .map(|v| v + 1e-12)
            .chain(x[..5 * dim].iter().copied())
            .collect();
        check(&x, dim, &q, 5);
    }

    /// Distances that differ below `f32`'s resolution: training vectors
    /// on a sphere around the query, radii apart by ~1e-9 relative, in a
    /// random order, so the `f32` sums cannot rank them and only the
    /// margin keeps the true nearest among the candidates.
    #[test]
    fn near_ties_below_f32_resolution_are_the_full_scan() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let dim = 40;
        let z: Vec<f64> = (0..dim).map(|_| rng.random_range(-3.0..3.0)).collect();
        let mut x = Vec::new();
        for _ in 0..300 {
            let dir: Vec<f64> = (0..dim).map(|_| rng.random_range(-1.0..1.0)).collect();
            let norm = dir.iter().map(|v| v * v).sum::<f64>().sqrt();
            let radius = 2.0 * (1.0 + 1e-9 * rng.random_range(0.0..1.0));
            x.extend(z.iter().zip(&dir).map(|(c, d)| c + radius * d / norm));
        }
        for k in [1, 5, 30] {
            check(&x, dim, &z, k);
        }
    }

    /// The scan's layout and norms are the same bits with the AVX2 kernels
    /// (where the CPU has AVX2) and with the scalar loops, for widths with
    /// and without a ragged eight, whole and partial blocks, and values that
    /// round to `f32` in the awkward ways (`f32` and `f64` subnormals, a tie
    /// to even, -0, large values near the scan's [`LIMIT`]).
    #[test]
    fn the_wide_build_is_the_scalar_build_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let odd = [
            0.0,
            -0.0,
            1e-40,
            -3e-39,
            1e-310,
            1.0 + 2f64.powi(-24),
            -3e13,
            1.0 + 1e-12,
        ];
        for dim in [1, 7, 8, 9, 16, 80, 83] {
            for n in [1, 15, 16, 17, 40] {
                let mut x: Vec<f64> = (0..n * dim).map(|_| rng.random_range(-3.0..3.0)).collect();
                for (j, v) in x.iter_mut().enumerate().filter(|(j, _)| j % 5 == 0) {
                    *v = odd[j / 5 % odd.len()] * if j % 2 == 0 { 1.0 } else { 1e-3 };
                }
                let wide = Scan::build(&x, dim).expect("in range");
                let narrow = crate::wide::baseline_only(|| Scan::build(&x, dim)).expect("in range");
                let b32 = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(b32(&wide.neg2), b32(&narrow.neg2), "neg2, dim {dim}, n {n}");
                assert_eq!(b32(&wide.base), b32(&narrow.base), "base, dim {dim}, n {n}");
                assert_eq!(wide.nx_max.to_bits(), narrow.nx_max.to_bits(), "dim {dim}, n {n}");
                assert_eq!(wide.e_x.to_bits(), narrow.e_x.to_bits(), "dim {dim}, n {n}");
            }
        }
    }

    /// Values the scan cannot take: a training set with a NaN, an infinity
    /// or a norm beyond [`LIMIT`] is declined; queries with them are
    /// scanned exactly, between ordinary ones, and give the full scan's
    /// (possibly empty) lists.
    #[test]
    fn out_of_range_values_are_declined_or_scanned_exactly() {
        let dim = 5;
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let x: Vec<f64> = (0..40 * dim).map(|_| rng.random_range(-2.0..2.0)).collect();
        for bad in [f64::NAN, f64::INFINITY, 2e15] {
            let mut y = x.clone();
            y[7] = bad;
            assert!(Scan::build(&y, dim).is_none(), "training value {bad}");
        }
        assert!(Scan::build(&x, 0).is_none());
        assert!(Scan::build(&x[..7], dim).is_none(), "not whole rows");
        let mut q: Vec<f64> = (0..6 * dim).map(|_| rng.random_range(-2.0..2.0)).collect();
        q[dim] = f64::NAN;
        q[2 * dim + 1] = f64::NEG_INFINITY;
        q[3 * dim + 2] = 1e200;
        q[4 * dim + 3] = 2e15;
        check(&x, dim, &q, 4);
    }

    /// The threshold is at least `r̃_(k)` plus the rounding margin `2ε` of
    /// the `f32` sums (else a vector at the `k`-th distance could be left
    /// out), and grows with `r̃_(k)`.
    #[test]
    fn the_threshold_covers_the_margin_and_grows() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let dim = 80;
        let x: Vec<f64> = (0..100 * dim).map(|_| rng.random_range(-3.0..3.0)).collect();
        let scan = Scan::build(&x, dim).expect("in range");
        let nz = 80.0;
        let eps = 1.02 * (dim as f64 + 4.0) * U32 * (nz + 2.0 * scan.nx_max);
        let mut last = f32::NEG_INFINITY;
        for rk in [-80.0f32, -60.0, -10.0, 0.0, 5.0, 1e3] {
            let t = scan.threshold(rk, nz, nz.sqrt());
            assert!(f64::from(t) >= f64::from(rk) + 2.0 * eps, "rk {rk}: {t}");
            assert!(t >= last);
            last = t;
        }
    }
}
