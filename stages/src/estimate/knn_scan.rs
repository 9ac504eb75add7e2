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
//! # The sparse path
//!
//! The k-NN features are standardised spike counts, mostly 0: a count of 0
//! in coordinate `i` becomes the same value in every vector (`−mean·/sd`),
//! so a query differs in few coordinates from a background `c` (on the
//! peers test set 16 of 80 on average, 18 at the median, at most 47).
//! With `c'ᵢ = f32(minⱼ x_jᵢ)` (the smallest training value, the image of
//! a count of 0; any `c'` gives exact answers, a good one gives speed),
//! `S = {i : z'ᵢ ≠ c'ᵢ}` (`m = |S|`) and `d'ᵢ = z'ᵢ − c'ᵢ` rounded in `f32`:
//!
//! * stored per training vector (`background`, built by the first batch
//!   of at least 96 queries, so a fit's lone query does not pay it):
//!   `s_j = f32(‖x'_j‖² − 2 c'·x'_j)`, summed in `f64` (the products of two
//!   `f32` are exact there), so `|s_j − (‖x'_j‖² − 2c'·x'_j)| ≤ 1.001 u P_j`
//!   with `P_j = ‖x'_j‖² + 2 ‖c'‖ ‖x'_j‖ ≤ P = N_X + 2 ‖c'‖ √N_X`;
//! * computed per pair: `r̃_j = s_j + Σ_{i∈S} d'ᵢ (−2 x'_jᵢ)`, an `f32`
//!   chain of `m` terms (fused or not) approximating the same
//!   `r_j = ‖x'_j‖² − 2 z'·x'_j` as the dense chain (for `i ∉ S`,
//!   `z'ᵢ = c'ᵢ` exactly).
//!
//! Its error: the chain's `γ_{m+1} (|s_j| + 2 ‖d'‖ ‖x'_j‖)`, the rounding of
//! `s_j` above, and that of the `d'ᵢ` (`u |z'ᵢ − c'ᵢ|` each, so
//! `2u ‖z' − c'‖ ‖x'_j‖` in all), so with `Q = 2 ‖d'‖ √N_X`,
//! `|r̃_j − r_j| ≤ u (P + Q) (1.001 + 1.01 (m + 1)(1 + 2u)) ≤ ε_s =
//! 1.02 (m + 4) u (P + Q)` (the spare terms cover the `f64` rounding of
//! `P`, `Q`). Bounds 2 and 3 and the threshold are the dense path's with
//! `ε_s` for `ε`, so the same vectors can win, each with its exact `D̂_j`:
//! the answer is the dense path's, bit for bit (tests
//! `sparse_queries_are_the_full_scan`, every path against the full scan on
//! spike-count-like data at scales 1e-150 to 1e12, all-background queries,
//! duplicates; `scanned` runs every test's queries through the per-query
//! choice, all-dense and all-sparse, with each kernel set). Every partial
//! sum stays below `P + Q (1 + 2u) < 10³¹` (the scan declines a background
//! with `‖c'‖² >` [`LIMIT`]; `‖d'‖ ≤ ‖z'‖ + ‖c'‖`).
//!
//! A query takes the sparse path when `m ≤ 0.7 dim`; otherwise (and for
//! vectors that are not sparse at all) the dense kernel, its queries packed
//! into tiles. The sparse kernel (`x86::sparse_partials` with AVX-512,
//! `Scan::sparse_lanes` elsewhere) takes 8 blocks at a time (8 independent
//! accumulators), and all of a batch's sparse queries against them, so
//! those blocks' coordinates are read from L1: a term costs a load and a
//! fused multiply-add per 16 vectors, against the dense tile's `dim` terms.
//! On the peers k-NN workload the prediction's thread CPU went from a
//! median 11.98 ms to 8.8 ms (-27 %; the fit unchanged), alternating the old
//! and new binaries four times (`RAYON_NUM_THREADS=1
//! target/release/examples/peers --out DIR --seed 1 --only knn --repeats
//! 15`, `predict_time.cpu_s.median` in `DIR/baselines/baselines.json`; the
//! runs in docs/benches.md).
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
/// A query takes the sparse path when at most `SPARSE_MAX / 80` of its
/// coordinates differ from the background: a sparse term costs a load and a
/// multiply-add per 16 vectors, a dense one a multiply-add shared with the
/// tile's queries (measured on the peers set, module docs).
const SPARSE_MAX: usize = 56;
/// Fewest queries of a batch call that builds the sparse path's data
/// (`background`, ~0.05 ms on the peers set) when no call has.
const SPARSE_MIN_QUERIES: usize = 2 * QB;
/// Blocks per group of the sparse kernel (independent accumulators).
const SG: usize = 8;
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
    /// `‖x'_j‖²` and `‖x_j‖²` per vector (`f64`).
    norms: Vec<(f64, f64)>,
    /// The sparse path's data, built by the first batch of at least
    /// [`SPARSE_MIN_QUERIES`] queries (`None`: `‖c'‖²` beyond [`LIMIT`]).
    sparse: OnceLock<Option<Sparse>>,
}

/// The sparse path's data (module docs).
#[derive(Clone)]
struct Sparse {
    /// The background `c'` (`f32` of each coordinate's smallest training value).
    bg: Vec<f32>,
    /// `s_j = f32(‖x'_j‖² − 2 c'·x'_j)` per vector (summed in `f64`), `+inf`
    /// in empty lanes.
    sbase: Vec<f32>,
    /// `P = N_X + 2 ‖c'‖ √N_X` (bound of `|s_j|`), and `√N_X`.
    p_bound: f64,
    sqrt_nx: f64,
}

/// How a query's `r̃` row is computed (module docs).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Path {
    /// Chosen per query: sparse when it differs from the background in at
    /// most [`SPARSE_MAX`] of its coordinates (per 80).
    Auto,
    /// Every query in range through the dense kernel (tests).
    #[cfg_attr(not(test), allow(dead_code))]
    Dense,
    /// Every query in range through the sparse kernel when the scan has a
    /// background (tests).
    #[cfg_attr(not(test), allow(dead_code))]
    Sparse,
}

/// How one query of a batch is scored.
#[derive(Clone, Copy)]
enum Mode {
    /// Not finite or out of range: every vector exactly.
    Exact,
    /// `r̃` from the dense kernel in row `row` of the batch, to be cut with
    /// rounding bound `eps`.
    Dense { row: usize, eps: f64 },
    /// `r̃` from the sparse kernel, the batch's `idx`-th sparse query.
    Sparse { idx: usize, eps: f64 },
}

/// Buffers reused across the queries of a batch.
#[derive(Default)]
struct Scratch {
    zq: Vec<f32>,
    r: Vec<f32>,
    sel: Select,
    /// One query's `f32` row.
    row: Vec<f32>,
    /// The sparse queries' terms `(i, d'_i)`, and per sparse query its
    /// terms' range and `r̃` row.
    terms: Vec<(u32, f32)>,
    spans: Vec<(usize, usize)>,
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
            norms,
            sparse: OnceLock::new(),
        })
    }

    /// The `k` nearest training rows of each standardised query row of `z`
    /// (rows of `x`, the `f64` vectors the scan was built from), passed to
    /// `each(query, neighbours)` in query order as `(D̂, index)` pairs,
    /// nearest first: exactly the `k` smallest pairs of the full scan.
    pub fn search(&self, x: &[f64], z: &[f64], k: usize, each: impl FnMut(usize, &[(f64, usize)])) {
        self.search_on(x, z, k, Path::Auto, each);
    }

    /// [`Self::search`] with the kernels chosen by `path`.
    fn search_on(
        &self,
        x: &[f64],
        z: &[f64],
        k: usize,
        path: Path,
        mut each: impl FnMut(usize, &[(f64, usize)]),
    ) {
        let dim = self.dim;
        let k = k.min(self.n);
        let nq = z.len() / dim;
        let stride = self.blocks * LANES;
        // The sparse data pays for itself over many queries, not for the
        // one a fit scores.
        let sp = match path {
            Path::Dense => None,
            Path::Auto if nq < SPARSE_MIN_QUERIES && self.sparse.get().is_none() => None,
            _ => self
                .sparse
                .get_or_init(|| background(x, dim, &self.neg2, &self.norms, self.nx_max))
                .as_ref(),
        };
        let sparse_max = match path {
            Path::Auto => dim * SPARSE_MAX / 80,
            _ => dim,
        };
        let dim_f = dim as f64;
        let eps_dense = |nz: f64| 1.02 * (dim_f + 4.0) * U32 * (nz + 2.0 * self.nx_max) + ABS;
        let mut s = Scratch::default();
        s.zq.resize(QB * dim, 0.0);
        s.r.resize((QB + QT) * stride, 0.0);
        s.row.resize(dim, 0.0);
        let mut best: Vec<(f64, usize)> = Vec::with_capacity(k + 1);
        let mut info = [(0.0f64, 0.0f64, Mode::Exact); QB];
        for q0 in (0..nq).step_by(QB) {
            let qb = QB.min(nq - q0);
            let batch = &z[q0 * dim..(q0 + qb) * dim];
            // Dense queries first (their rows packed at the top of `zq` and
            // `r`), then the sparse ones' `r̃` rows after the dense tiles.
            let mut nd = 0;
            s.terms.clear();
            s.spans.clear();
            for (q, zr) in batch.chunks_exact(dim).enumerate() {
                let (nz, z2) = norms_of(zr);
                let ok = nz <= LIMIT && z2 <= LIMIT;
                info[q] = (nz, z2.sqrt(), Mode::Exact);
                if ok {
                    for (o, &v) in s.row.iter_mut().zip(zr) {
                        *o = v as f32;
                    }
                    let t0 = s.terms.len();
                    if let Some(sp) = sp {
                        for (i, (&v, &c)) in s.row.iter().zip(&sp.bg).enumerate() {
                            if v != c {
                                s.terms.push((i as u32, v - c));
                            }
                        }
                    }
                    let m = s.terms.len() - t0;
                    if let Some(sp) = sp.filter(|_| m <= sparse_max) {
                        let d2: f64 = s.terms[t0..]
                            .iter()
                            .map(|&(_, d)| f64::from(d) * f64::from(d))
                            .sum();
                        let eps =
                            1.02 * (m as f64 + 4.0) * U32 * (sp.p_bound + 2.0 * d2.sqrt() * sp.sqrt_nx) + ABS;
                        info[q].2 = Mode::Sparse {
                            idx: s.spans.len(),
                            eps,
                        };
                        s.spans.push((t0, s.terms.len()));
                    } else {
                        s.terms.truncate(t0);
                        s.zq[nd * dim..(nd + 1) * dim].copy_from_slice(&s.row);
                        info[q].2 = Mode::Dense {
                            row: nd,
                            eps: eps_dense(nz),
                        };
                        nd += 1;
                    }
                }
            }
            let top = nd.div_ceil(QT) * QT;
            // Rows past the dense queries keep what they held: finite
            // values whose results are not read.
            if nd > 0 {
                self.partials(&s.zq, &mut s.r, top);
            }
            if let Some(sp) = sp.filter(|_| !s.spans.is_empty()) {
                self.sparse_partials(sp, &s.terms, &s.spans, &mut s.r[top * stride..]);
            }
            // The selection's loops compiled for the widest vectors too.
            let wide = crate::wide::avx512();
            crate::wide::with_avx2(
                #[inline(always)]
                || {
                    for (q, &(nz, zn, mode)) in info[..qb].iter().enumerate() {
                        let zr = &batch[q * dim..(q + 1) * dim];
                        best.clear();
                        let scan = match mode {
                            Mode::Dense { row, eps } => Some((row, eps)),
                            Mode::Sparse { idx, eps } => Some((top + idx, eps)),
                            Mode::Exact => None,
                        };
                        match scan {
                            _ if k == 0 => {}
                            Some((row, eps)) => {
                                let t = self.candidates(
                                    &s.r[row * stride..(row + 1) * stride],
                                    k,
                                    nz,
                                    zn,
                                    eps,
                                    &mut s.sel,
                                    wide,
                                );
                                for &(v, j) in &s.sel.cand {
                                    if v <= t {
                                        offer(
                                            &mut best,
                                            k,
                                            dense::sq_dist(zr, &x[j * dim..(j + 1) * dim]),
                                            j,
                                        );
                                    }
                                }
                            }
                            None => {
                                for (j, xr) in x.chunks_exact(dim).take(self.n).enumerate() {
                                    offer(&mut best, k, dense::sq_dist(zr, xr), j);
                                }
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
    #[allow(clippy::too_many_arguments)]
    fn candidates(&self, r: &[f32], k: usize, nz: f64, zn: f64, eps: f64, s: &mut Select, wide: bool) -> f32 {
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
            self.threshold(t0, nz, zn, eps)
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
        self.threshold(kth(&mut s.vals, k), nz, zn, eps)
    }

    /// The `f32` threshold on `r̃` below which a vector may be a neighbour
    /// (module docs), from `r̃_(k)`, `N_z`, `‖z‖` and the bound `ε` on the
    /// rounding of the query's `r̃` (the dense or the sparse one).
    fn threshold(&self, rk: f32, nz: f64, zn: f64, eps: f64) -> f32 {
        let n = self.dim as f64;
        let gamma = 1.01 * (n + 2.0) * (f64::EPSILON / 2.0);
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

    /// `r̃` of the sparse queries (module docs): query `p` has the terms
    /// `terms[spans[p].0..spans[p].1]`, `(i, d'_i)`, and its row is row `p`
    /// of `r` ([`LANES`]` · blocks` wide): `s_j` plus each term times
    /// `−2 x'_jᵢ`, in the terms' order.
    fn sparse_partials(&self, sp: &Sparse, terms: &[(u32, f32)], spans: &[(usize, usize)], r: &mut [f32]) {
        let stride = self.blocks * LANES;
        // The kernels index with these unchecked.
        assert!(
            terms.iter().all(|&(i, _)| (i as usize) < self.dim)
                && spans.iter().all(|&(a, b)| a <= b && b <= terms.len())
                && r.len() >= spans.len() * stride
                && sp.sbase.len() >= stride
                && self.neg2.len() >= stride * self.dim
        );
        #[cfg(target_arch = "x86_64")]
        if crate::wide::avx512() && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has AVX-512 F and FMA (checked just above);
            // the indices and sizes are checked above.
            unsafe { x86::sparse_partials(&self.neg2, &sp.sbase, self.dim, self.blocks, terms, spans, r) };
            return;
        }
        crate::wide::with_avx2(
            #[inline(always)]
            || self.sparse_lanes(&sp.sbase, terms, spans, r),
        );
    }

    /// [`Self::sparse_partials`] on 16-lane arrays (any CPU): multiply
    /// then add, [`SG`] blocks at a time.
    #[inline(always)]
    fn sparse_lanes(&self, sbase: &[f32], terms: &[(u32, f32)], spans: &[(usize, usize)], r: &mut [f32]) {
        let (dim, stride) = (self.dim, self.blocks * LANES);
        let mut b0 = 0;
        while b0 < self.blocks {
            let g = SG.min(self.blocks - b0);
            for (p, &(a, e)) in spans.iter().enumerate() {
                let mut acc = [[0.0f32; LANES]; SG];
                for (t, acc) in acc.iter_mut().enumerate().take(g) {
                    acc.copy_from_slice(&sbase[(b0 + t) * LANES..(b0 + t + 1) * LANES]);
                }
                for &(i, d) in &terms[a..e] {
                    for (t, acc) in acc.iter_mut().enumerate().take(g) {
                        let xi = &self.neg2[((b0 + t) * dim + i as usize) * LANES..][..LANES];
                        for l in 0..LANES {
                            acc[l] += d * xi[l];
                        }
                    }
                }
                for (t, acc) in acc.iter().enumerate().take(g) {
                    r[p * stride + (b0 + t) * LANES..][..LANES].copy_from_slice(acc);
                }
            }
            b0 += g;
        }
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

/// The sparse path's background `c'` (each coordinate's smallest training
/// value, in `f32`), the `s_j` of the module docs (`‖x'_j‖²` from `norms`,
/// plus `Σᵢ c'ᵢ (−2 x'_jᵢ)` summed in `f64` along the coordinates, 16 lanes
/// at a time from the `neg2` layout: the products of two `f32` are exact in
/// `f64`), rounded to `f32`, and `‖c'‖`. Empty vectors (and 0) when
/// `‖c'‖²` exceeds [`LIMIT`]. Plain loops (the same operations compiled
/// with or without AVX2, so the same bits).
fn background(x: &[f64], dim: usize, neg2: &[f32], norms: &[(f64, f64)], nx_max: f64) -> Option<Sparse> {
    let n = norms.len();
    let mut mins = vec![f64::INFINITY; dim];
    crate::wide::with_avx2(
        #[inline(always)]
        || {
            for row in x.chunks_exact(dim).take(n) {
                for (m, &v) in mins.iter_mut().zip(row) {
                    // Finite values (the build checked them).
                    if v < *m {
                        *m = v;
                    }
                }
            }
        },
    );
    let bg: Vec<f32> = mins
        .iter()
        .map(|&m| if m.is_finite() { m as f32 } else { 0.0 })
        .collect();
    let c2: f64 = bg.iter().map(|&c| f64::from(c) * f64::from(c)).sum();
    // Finite: the squares of finite `f32` values.
    if c2 > LIMIT {
        return None;
    }
    let mut sbase = vec![f32::INFINITY; n.div_ceil(LANES) * LANES];
    crate::wide::with_avx2(
        #[inline(always)]
        || {
            for (b, (xb, out)) in neg2
                .chunks_exact(dim * LANES)
                .zip(sbase.chunks_exact_mut(LANES))
                .enumerate()
            {
                let mut acc = [0.0f64; LANES];
                for (xi, &c) in xb.chunks_exact(LANES).zip(&bg) {
                    let c = f64::from(c);
                    for l in 0..LANES {
                        acc[l] += c * f64::from(xi[l]);
                    }
                }
                for (l, (o, a)) in out.iter_mut().zip(acc).enumerate() {
                    if let Some(&(s32, _)) = norms.get(b * LANES + l) {
                        *o = (s32 + a) as f32;
                    }
                }
            }
        },
    );
    let sqrt_nx = nx_max.sqrt();
    Some(Sparse {
        bg,
        sbase,
        p_bound: nx_max + 2.0 * c2.sqrt() * sqrt_nx,
        sqrt_nx,
    })
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
    use super::{LANES, QB, QT, SG};
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
                crate::wide::transpose8_ps(v)
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

    /// [`super::Scan::sparse_partials`] with AVX-512: [`SG`] blocks a group
    /// (as many independent accumulators), each query's terms against them
    /// (a load, a broadcast shared by the group, a fused multiply-add), all
    /// the batch's sparse queries against one group before the next, so the
    /// group's coordinates (`SG · dim · 64` bytes) are read from L1.
    ///
    /// # Safety
    /// The CPU must have AVX-512 F and FMA; every term's index is below
    /// `dim`, every span within `terms`, `r` holds `spans.len()` rows of
    /// `blocks · LANES`, `neg2` and `base` the scan's sizes.
    #[target_feature(enable = "avx512f,fma")]
    pub(super) unsafe fn sparse_partials(
        neg2: &[f32],
        base: &[f32],
        dim: usize,
        blocks: usize,
        terms: &[(u32, f32)],
        spans: &[(usize, usize)],
        r: &mut [f32],
    ) {
        let stride = blocks * LANES;
        let (xp, bp, rp) = (neg2.as_ptr(), base.as_ptr(), r.as_mut_ptr());
        let mut b0 = 0;
        // SAFETY (all pointer arithmetic below): blocks below `blocks`,
        // coordinates below `dim`, rows below `spans.len()` (the caller's
        // contract).
        unsafe {
            while b0 + SG <= blocks {
                let x = xp.add(b0 * dim * LANES);
                for (p, &(a, e)) in spans.iter().enumerate() {
                    let mut acc = [_mm512_setzero_ps(); SG];
                    for (t, acc) in acc.iter_mut().enumerate() {
                        *acc = _mm512_loadu_ps(bp.add((b0 + t) * LANES));
                    }
                    for &(i, d) in terms.get_unchecked(a..e) {
                        let u = _mm512_set1_ps(d);
                        let xi = x.add(i as usize * LANES);
                        for (t, acc) in acc.iter_mut().enumerate() {
                            *acc = _mm512_fmadd_ps(u, _mm512_loadu_ps(xi.add(t * dim * LANES)), *acc);
                        }
                    }
                    for (t, acc) in acc.iter().enumerate() {
                        _mm512_storeu_ps(rp.add(p * stride + (b0 + t) * LANES), *acc);
                    }
                }
                b0 += SG;
            }
            for b in b0..blocks {
                let x = xp.add(b * dim * LANES);
                for (p, &(a, e)) in spans.iter().enumerate() {
                    let mut acc = _mm512_loadu_ps(bp.add(b * LANES));
                    for &(i, d) in terms.get_unchecked(a..e) {
                        acc = _mm512_fmadd_ps(
                            _mm512_set1_ps(d),
                            _mm512_loadu_ps(x.add(i as usize * LANES)),
                            acc,
                        );
                    }
                    _mm512_storeu_ps(rp.add(p * stride + b * LANES), acc);
                }
            }
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

    /// Every query's list from the scan, with the AVX-512 kernels (where the
    /// CPU has them), the AVX2 ones and the 16-lane loops, each with the
    /// path chosen per query, every query dense and every query sparse:
    /// all must agree.
    fn scanned(scan: &Scan, x: &[f64], q: &[f64], k: usize) -> Vec<Vec<(u64, usize)>> {
        let run = |path: Path| {
            move || {
                let mut out = Vec::new();
                scan.search_on(x, q, k, path, |i, best| {
                    assert_eq!(i, out.len(), "queries in order");
                    out.push(bits(best));
                });
                out
            }
        };
        let wide = run(Path::Auto)();
        for path in [Path::Auto, Path::Dense, Path::Sparse] {
            // The kernel the CPU picks, the AVX2 one and the portable lanes.
            assert_eq!(wide, run(path)(), "{path:?}: the kernels the CPU picks");
            assert_eq!(wide, crate::wide::without_avx512(run(path)), "{path:?}: AVX2");
            assert_eq!(
                wide,
                crate::wide::baseline_only(run(path)),
                "{path:?}: portable lanes"
            );
        }
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

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        /// Spike-count-like data (most counts 0), standardised per column
        /// with random means and scales from tiny to huge, duplicate rows,
        /// all-zero queries (every coordinate the background), queries
        /// that are training rows, one count off one, and batches large
        /// enough for the sparse path to be built on its own: every path
        /// (per query, all dense, all sparse) gives the full scan's list.
        #[test]
        fn sparse_queries_are_the_full_scan(
            n in 1usize..400,
            dim in prop::sample::select(vec![1usize, 5, 16, 80, 83]),
            k in prop::sample::select(vec![1usize, 3, 10, 50, 500]),
            zero_pct in prop::sample::select(vec![50u32, 80, 95, 100]),
            scale_exp in prop::sample::select(vec![-150i32, -12, 0, 6, 12]),
            queries in prop::sample::select(vec![3usize, 60, 130]),
            seed in 0u64..1000,
        ) {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let scale = 10f64.powi(scale_exp);
            let mean: Vec<f64> = (0..dim).map(|_| rng.random_range(0.0..3.0)).collect();
            let inv_sd: Vec<f64> = (0..dim).map(|_| rng.random_range(0.2..5.0) * scale).collect();
            let count = |rng: &mut ChaCha8Rng| -> f64 {
                if rng.random_range(0..100) < zero_pct { 0.0 } else { f64::from(rng.random_range(1..6)) }
            };
            let mut raw: Vec<f64> = Vec::with_capacity(n * dim);
            for r in 0..n {
                if r > 0 && rng.random_range(0..6) == 0 {
                    let src = rng.random_range(0..r);
                    let row: Vec<f64> = raw[src * dim..(src + 1) * dim].to_vec();
                    raw.extend(row);
                } else {
                    for _ in 0..dim {
                        raw.push(count(&mut rng));
                    }
                }
            }
            let mut qraw: Vec<f64> = (0..queries * dim).map(|_| count(&mut rng)).collect();
            qraw.extend(std::iter::repeat_n(0.0, dim));
            qraw.extend_from_slice(&raw[..dim]);
            let mut near = raw[(n - 1) * dim..].to_vec();
            near[0] += 1.0;
            qraw.extend(near);
            let std = |v: &[f64]| -> Vec<f64> {
                v.iter().enumerate().map(|(i, &c)| (c - mean[i % dim]) * inv_sd[i % dim]).collect()
            };
            let (x, q) = (std(&raw), std(&qraw));
            let scan = Scan::build(&x, dim).expect("finite rows in range");
            for (i, got) in scanned(&scan, &x, &q, k).into_iter().enumerate() {
                let z = &q[i * dim..(i + 1) * dim];
                prop_assert_eq!(got, bits(&full_scan(&x, dim, z, k)), "query {}", i);
            }
        }
    }

    /// The per-query choice takes the sparse path for sparse queries in a
    /// large batch (its data built then, not by a lone query), and declines
    /// a background whose squared norm exceeds [`LIMIT`].
    #[test]
    fn the_sparse_path_is_built_for_large_batches_only() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let dim = 80;
        let raw = |rng: &mut ChaCha8Rng, rows: usize| -> Vec<f64> {
            (0..rows * dim)
                .map(|_| {
                    if rng.random_range(0..5) == 0 {
                        f64::from(rng.random_range(1..4)) - 0.4
                    } else {
                        -0.4
                    }
                })
                .collect()
        };
        let x = raw(&mut rng, 300);
        let q = raw(&mut rng, SPARSE_MIN_QUERIES);
        let scan = Scan::build(&x, dim).expect("in range");
        scan.search(&x, &q[..dim], 10, |_, _| {});
        assert!(scan.sparse.get().is_none(), "a lone query builds no sparse data");
        let mut got = Vec::new();
        scan.search(&x, &q, 10, |_, best| got.push(bits(best)));
        for (i, got) in got.into_iter().enumerate() {
            assert_eq!(
                got,
                bits(&full_scan(&x, dim, &q[i * dim..(i + 1) * dim], 10)),
                "query {i}"
            );
        }
        let sp = scan
            .sparse
            .get()
            .and_then(|s| s.as_ref())
            .expect("built by the batch");
        assert!(sp.bg.iter().all(|&c| c == -0.4f32));
        // Each row's squared norm within the limit, the columns' minima
        // (the background) beyond it: no sparse data, the dense path.
        let x = [-9e14, 0.0, 0.0, -9e14, 1.0, 2.0];
        let scan = Scan::build(&x, 2).expect("norms within the limit");
        assert!(background(&x, 2, &scan.neg2, &scan.norms, scan.nx_max).is_none());
        check(&x, 2, &[0.0, 0.0, -9e14, 1.0, 3.0, -2.0], 2);
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
            let t = scan.threshold(rk, nz, nz.sqrt(), eps + ABS);
            assert!(f64::from(t) >= f64::from(rk) + 2.0 * eps, "rk {rk}: {t}");
            assert!(t >= last);
            last = t;
        }
    }
}
