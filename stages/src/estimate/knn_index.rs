//! An exact k-nearest-neighbour search for [`super::classic::Knn`] that
//! computes few distances: a principal-axes rotation, a partition of the
//! training vectors into blocks of [`LANES`] neighbours with a bounding ball
//! each, and a cheap `f32` lower bound that discards most of the remaining
//! vectors after a few of their coordinates. Every vector that survives is
//! compared with its exact distance, [`dense::sq_dist`] of the standardised
//! vectors, the same bits as the full scan, so the answer is exactly the full
//! scan's: the `k` smallest `(distance, index)` pairs.
//!
//! # The index ([`KnnIndex::build`])
//!
//! * `m` = the training mean, `R` = the eigenvectors of the training scatter
//!   matrix `Σ (x − m)(x − m)ᵀ` (cyclic Jacobi), one per row, by decreasing
//!   eigenvalue: the first coordinates of `R (x − m)` carry most of the
//!   spread (on the 80-value spike windows, 13 axes hold 80% of it).
//! * `ŵ_j = R (x_j − m)` in `f64`, kept as `w_j = f32(ŵ_j)`.
//! * The vectors are ordered as the leaves of a k-d tree on `ŵ` (split at a
//!   multiple of [`LANES`] near the median of the widest coordinate) and
//!   stored in blocks of [`LANES`] (a leaf; the last block repeats its first
//!   vector in its empty lanes), coordinate-major within a block so one
//!   vector operation advances all its lanes by one coordinate. Each block
//!   has a centre `μ_b` and a radius `r_b ≥ max_j ‖w_j − μ_b‖`.
//!
//! # The search ([`KnnIndex::search`]) and why it is exact
//!
//! Let `D = ‖z − x‖²` (real numbers) and `D̂` its computed value
//! ([`dense::sq_dist`]). The answer is the `k` smallest `(D̂, index)` pairs,
//! so a vector may be skipped only when `D̂ > τ`, with `τ` the `k`-th smallest
//! `D̂` found so far (`+∞` until `k` are found); a vector with `D̂ = τ` may
//! still win on its index and is never skipped. A *candidate* is a vector
//! with `D̂ ≤ τ`. Bounds, with `u` the unit roundoff of `f64` and `n = dim`:
//!
//! 1. `D̂ ≥ D (1 − γ)` with `γ = 1.01 (n + 2) u` (a sum of `n` rounded
//!    squares of rounded differences, any order), so a candidate has
//!    `D ≤ τ (1 + 2γ)`.
//! 2. `R` is a fixed matrix, not exactly orthonormal; `s ≥ ‖R‖₂` is
//!    bounded at build time by the largest absolute row sum of `R Rᵀ`
//!    (plus its rounding), so `‖R v‖ ≤ s ‖v‖`. The mean cancels:
//!    `R (z − m) − R (x − m) = R (z − x)`, so `‖y − w*‖ ≤ s √D` where
//!    `y`, `w*` are the exact rotations.
//! 3. The stored and query rotations are off the exact ones by at most
//!    `e = √n γ' max|R_ij| ‖v‖₁ + 2⁻²⁴ ‖ŵ‖` (the `f64` product, `γ' =
//!    1.01 (n + 2) u`, then the rounding to `f32`), plus an absolute slack
//!    for underflow; `E_q`, and `E_X` = the largest over the training set.
//!    By the triangle inequality a candidate has
//!    `‖y_f32 − w_j‖ ≤ B(τ) = s √(τ (1 + 2γ)) + E_q + E_X`.
//! 4. **Blocks**: `‖y_f32 − w_j‖ ≥ ‖y_f32 − μ_b‖ − r_b` for every vector
//!    of block `b` (triangle inequality; the computed centre distance is
//!    shrunk by a relative `10⁻⁹` to a lower bound). Blocks are visited by
//!    increasing lower bound, and the search stops at the first block whose
//!    bound exceeds `B(τ)`: no later block holds a candidate.
//! 5. **Coordinates**: within a block, the partial sums `p` of
//!    `(y_i − w_ji)²` over the first coordinates, in `f32`, only grow, and
//!    every partial sum of squares is at most the full one; with the `f32`
//!    rounding (`γ₃₂ = 1.01 (2n + 4) 2⁻²⁴`) a candidate has
//!    `p ≤ T(τ) = (1 + γ₃₂) B(τ)² (1 + 10⁻⁶) + 10⁻³⁰`. A block is left as
//!    soon as every lane's partial sum exceeds `T` (checked every [`CHUNK`]
//!    coordinates); the lanes still at or below `T` after the last
//!    coordinate get their exact distance.
//!
//! Inputs that would overflow the `f32` bound (a rotated coordinate beyond
//! `10¹⁵`) or that are not finite are not searched here: the index is not
//! built, or the caller scans that query in full. Tiny magnitudes only make
//! the bound looser (the absolute slack), never unsafe.
//!
//! Cost, measured on the k-NN workload of `benches/peers` (3060 training
//! vectors of 80 values, 3154 queries, `k = 10`): see the numbers in the
//! `knn` paragraph of [`super::classic`].

use super::dense;
use std::sync::OnceLock;

/// A [`KnnIndex`] built on first use, for a model field that is not saved:
/// it compares equal to any other (it is derived from the model's data).
#[derive(Clone, Default)]
pub struct IndexCell(OnceLock<Option<KnnIndex>>);

impl IndexCell {
    /// The index of `x` (built on the first call; later calls must pass the
    /// same rows), `None` when [`KnnIndex::build`] declines them.
    pub fn get(&self, x: &[f64], dim: usize) -> Option<&KnnIndex> {
        self.0.get_or_init(|| KnnIndex::build(x, dim)).as_ref()
    }
}

impl PartialEq for IndexCell {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for IndexCell {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0.get() {
            None => f.write_str("IndexCell(not built)"),
            Some(None) => f.write_str("IndexCell(full scan)"),
            Some(Some(ix)) => write!(f, "IndexCell({} blocks)", ix.blocks),
        }
    }
}

/// Vectors per block (one AVX-512 register of `f32`, two AVX2 ones).
pub(crate) const LANES: usize = 16;
/// Coordinates between two checks of a block's partial sums.
const CHUNK: usize = 8;
/// Largest rotated coordinate the `f32` bound takes: differences of two
/// are below 2·10¹⁵, squares below 4·10³⁰, so no `f32` sum of fewer than
/// ~10⁷ of them overflows.
const LIMIT: f64 = 1e15;
/// Absolute slack for underflow in the `f32` and `f64` bounds.
const ABS: f64 = 1e-30;
/// Jacobi sweeps at most (the axes need not be exact: the bound takes `R` as it is).
const SWEEPS: usize = 8;

/// The search structure of one training set (see the module docs).
#[derive(Clone, Debug)]
pub struct KnnIndex {
    dim: usize,
    /// Training mean `m`.
    mean: Vec<f64>,
    /// `R`, `dim x dim`, row-major, one axis per row.
    rot: Vec<f64>,
    /// `max |R_ij|`.
    rmax: f64,
    /// `s ≥ ‖R‖₂`.
    scale: f64,
    /// `E_X`: the largest error of a stored rotated vector.
    err_x: f64,
    /// Blocks.
    blocks: usize,
    /// Block centres, coordinate-major: `centres[i * blocks + b]`.
    centres: Vec<f64>,
    /// Block radii.
    radii: Vec<f64>,
    /// Rotated vectors, `f32`: `pts[(b * dim + i) * LANES + l]`.
    pts: Vec<f32>,
    /// Training index of each lane, `usize::MAX` for the padding lanes.
    ids: Vec<usize>,
}

/// Work done by the searches (for measuring the pruning).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SearchStats {
    /// Queries searched through the index.
    pub queries: usize,
    /// Blocks whose lanes were scanned.
    pub blocks: usize,
    /// Lane-coordinates accumulated by the `f32` bound.
    pub lane_coords: usize,
    /// Exact distances computed.
    pub exact: usize,
}

/// Reused buffers of [`KnnIndex::search`].
#[derive(Default)]
pub struct Scratch {
    y32: Vec<f32>,
    keys: Vec<(f64, usize)>,
    c2: Vec<f64>,
    /// Work counters, summed over the searches.
    pub stats: SearchStats,
}

fn gamma(terms: usize, unit: f64) -> f64 {
    1.01 * (terms as f64 + 2.0) * unit
}

impl KnnIndex {
    /// The index of `x` (`n` rows of `dim`, row-major), or `None` when the
    /// rows are empty, not finite or too large for the `f32` bound (then the
    /// caller scans in full).
    pub fn build(x: &[f64], dim: usize) -> Option<KnnIndex> {
        if dim == 0 || x.is_empty() || x.len() % dim != 0 || !x.iter().all(|v| v.is_finite()) {
            return None;
        }
        let n = x.len() / dim;
        if gamma(2 * dim + 2, f64::from(f32::EPSILON)) > 0.01 {
            return None;
        }
        let mut mean = vec![0.0; dim];
        for row in x.chunks_exact(dim) {
            mean.iter_mut().zip(row).for_each(|(m, v)| *m += v);
        }
        mean.iter_mut().for_each(|m| *m /= n as f64);
        let v: Vec<f64> = x
            .chunks_exact(dim)
            .flat_map(|row| row.iter().zip(&mean).map(|(a, m)| a - m))
            .collect();
        if !v.iter().all(|a| a.is_finite()) {
            return None;
        }
        // Scatter matrix and its eigenvectors, by decreasing eigenvalue.
        let mut vt = vec![0.0; n * dim];
        dense::transpose(&v, n, dim, &mut vt);
        let mut scatter = vec![0.0; dim * dim];
        dense::gemm_nt(&vt, &vt, n, &mut scatter);
        if !scatter.iter().all(|a| a.is_finite()) {
            return None;
        }
        let vecs = jacobi_eigen(&mut scatter, dim);
        let mut axes: Vec<usize> = (0..dim).collect();
        axes.sort_by(|&a, &b| {
            scatter[b * dim + b]
                .total_cmp(&scatter[a * dim + a])
                .then(a.cmp(&b))
        });
        let mut rot = vec![0.0; dim * dim];
        for (r, &a) in axes.iter().enumerate() {
            for i in 0..dim {
                rot[r * dim + i] = vecs[i * dim + a];
            }
        }
        let rmax = rot.iter().fold(0.0f64, |m, a| m.max(a.abs()));
        // ‖R‖₂² = λmax(R Rᵀ) ≤ the largest absolute row sum of R Rᵀ; each
        // computed entry errs by at most γ · dim · rmax².
        let mut gram = vec![0.0; dim * dim];
        dense::gemm_nt(&rot, &rot, dim, &mut gram);
        let entry_err = gamma(dim, f64::EPSILON / 2.0) * dim as f64 * rmax * rmax;
        let row_sum = gram
            .chunks_exact(dim)
            .map(|r| r.iter().map(|g| g.abs() + entry_err).sum::<f64>())
            .fold(0.0f64, f64::max);
        let scale = (row_sum * (1.0 + 1e-9)).sqrt() * (1.0 + 1e-9);
        // Rotated training vectors and their error radius.
        let mut w = vec![0.0; n * dim];
        dense::gemm_nt(&v, &rot, dim, &mut w);
        if !w.iter().all(|a| a.is_finite() && a.abs() <= LIMIT) {
            return None;
        }
        let err_x = v
            .chunks_exact(dim)
            .zip(w.chunks_exact(dim))
            .map(|(vr, wr)| rotation_error(vr, wr, rmax))
            .fold(0.0f64, f64::max);
        // Blocks: the leaves of a k-d tree.
        let mut order: Vec<usize> = (0..n).collect();
        kd_order(&w, dim, &mut order);
        let blocks = n.div_ceil(LANES);
        let mut pts = vec![0.0f32; blocks * dim * LANES];
        let mut ids = vec![usize::MAX; blocks * LANES];
        let mut centres = vec![0.0; dim * blocks];
        let mut radii = vec![0.0; blocks];
        for (b, leaf) in order.chunks(LANES).enumerate() {
            for l in 0..LANES {
                let (j, real) = match leaf.get(l) {
                    Some(&j) => (j, true),
                    None => (leaf[0], false),
                };
                if real {
                    ids[b * LANES + l] = j;
                }
                for i in 0..dim {
                    pts[(b * dim + i) * LANES + l] = w[j * dim + i] as f32;
                }
            }
            let lane = |l: usize, i: usize| f64::from(pts[(b * dim + i) * LANES + l]);
            for i in 0..dim {
                let s: f64 = (0..leaf.len()).map(|l| lane(l, i)).sum();
                centres[i * blocks + b] = s / leaf.len() as f64;
            }
            // The computed squared radius errs by a relative γ at most.
            let r2 = (0..leaf.len())
                .map(|l| {
                    (0..dim)
                        .map(|i| {
                            let d = lane(l, i) - centres[i * blocks + b];
                            d * d
                        })
                        .sum::<f64>()
                })
                .fold(0.0f64, f64::max);
            radii[b] = (r2 * (1.0 + 1e-9)).sqrt() * (1.0 + 1e-9) + ABS;
        }
        Some(KnnIndex {
            dim,
            mean,
            rot,
            rmax,
            scale,
            err_x,
            blocks,
            centres,
            radii,
            pts,
            ids,
        })
    }

    /// The rotations `ŷ = R (z − m)` of the standardised queries `z` (rows
    /// of `dim`) into `y`, and `z − m` into `v`.
    pub fn rotate(&self, z: &[f64], v: &mut Vec<f64>, y: &mut Vec<f64>) {
        v.clear();
        for row in z.chunks_exact(self.dim) {
            v.extend(row.iter().zip(&self.mean).map(|(a, m)| a - m));
        }
        y.clear();
        y.resize(v.len(), 0.0);
        dense::gemm_nt(v, &self.rot, self.dim, y);
    }

    /// `B(τ)` squared, as the `f32` threshold `T(τ)` of the module docs,
    /// and `B(τ)` itself; both `+∞` when `τ` is.
    fn thresholds(&self, tau: f64, err: f64) -> (f64, f32) {
        if !tau.is_finite() {
            return (f64::INFINITY, f32::INFINITY);
        }
        let g = gamma(self.dim, f64::EPSILON / 2.0);
        // The relative 1e-9 covers the rounding of this line and of the
        // blocks' keys (each a few ulps).
        let b = (self.scale * (tau * (1.0 + 2.0 * g)).sqrt() + err) * (1.0 + 1e-9);
        let g32 = gamma(2 * self.dim + 2, f64::from(f32::EPSILON) / 2.0);
        let t = (1.0 + g32) * b * b * (1.0 + 1e-6) + ABS;
        (b, t as f32)
    }

    /// Offers to `best` (sorted, at most `k`) every training vector whose
    /// exact distance to `z` may be among the `k` smallest, as described in
    /// the module docs; `x` are the training rows the index was built on,
    /// `v = z − m` and `yhat = R v` as [`Self::rotate`] made them. Returns
    /// `false`, with `best` untouched, when the query is out of the bound's
    /// range (the caller then scans in full).
    #[allow(clippy::too_many_arguments)]
    pub fn search(
        &self,
        x: &[f64],
        z: &[f64],
        v: &[f64],
        yhat: &[f64],
        k: usize,
        best: &mut Vec<(f64, usize)>,
        scratch: &mut Scratch,
    ) -> bool {
        // Compiled with AVX-512 / AVX2 where the CPU has them: the block
        // sums are 16-lane loops. Only the bound's bits depend on it; the
        // exact distances are the same at any width (no FMA). The closure
        // is inlined into the wide function, or the loops stay SSE2.
        crate::wide::with_avx2(
            #[inline(always)]
            || self.search_body(x, z, v, yhat, k, best, scratch),
        )
    }

    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn search_body(
        &self,
        x: &[f64],
        z: &[f64],
        v: &[f64],
        yhat: &[f64],
        k: usize,
        best: &mut Vec<(f64, usize)>,
        scratch: &mut Scratch,
    ) -> bool {
        let dim = self.dim;
        if !yhat.iter().all(|a| a.is_finite() && a.abs() <= LIMIT) || !v.iter().all(|a| a.is_finite()) {
            return false;
        }
        best.clear();
        if k == 0 {
            return true;
        }
        scratch.stats.queries += 1;
        let err = rotation_error(v, yhat, self.rmax) + self.err_x;
        scratch.y32.clear();
        scratch.y32.extend(yhat.iter().map(|&a| a as f32));
        let y32 = &scratch.y32;
        // Lower bounds of the blocks.
        let nb = self.blocks;
        let c2 = &mut scratch.c2;
        c2.clear();
        c2.resize(nb, 0.0);
        for (i, &q) in y32.iter().enumerate() {
            let q = f64::from(q);
            for (acc, &c) in c2.iter_mut().zip(&self.centres[i * nb..(i + 1) * nb]) {
                let d = q - c;
                *acc += d * d;
            }
        }
        let keys = &mut scratch.keys;
        keys.clear();
        keys.extend(
            c2.iter()
                .zip(&self.radii)
                .enumerate()
                .map(|(b, (&c, &r))| ((c * (1.0 - 1e-9)).sqrt() * (1.0 - 1e-9) - r, b)),
        );
        keys.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let (mut bound, mut t) = self.thresholds(f64::INFINITY, err);
        let mut visited = 0;
        let mut lanes = 0;
        let mut exact = 0;
        for &(key, b) in keys.iter() {
            if key > bound {
                break;
            }
            visited += 1;
            let block = &self.pts[b * dim * LANES..(b + 1) * dim * LANES];
            let (acc, used) = block_partial_sums(y32, block, t);
            lanes += used * LANES;
            if used < dim {
                continue;
            }
            for (l, &a) in acc.iter().enumerate() {
                let j = self.ids[b * LANES + l];
                if a <= t && j != usize::MAX {
                    exact += 1;
                    let d2 = dense::sq_dist(&x[j * dim..(j + 1) * dim], z);
                    if offer(best, k, d2, j) && best.len() == k {
                        (bound, t) = self.thresholds(best[k - 1].0, err);
                    }
                }
            }
        }
        scratch.stats.blocks += visited;
        scratch.stats.lane_coords += lanes;
        scratch.stats.exact += exact;
        true
    }
}

/// The partial sums of `(q_i − p_il)²` over the coordinates `i` of one block
/// (`p` coordinate-major, [`LANES`] wide), stopping after a chunk once every
/// lane exceeds `t`. Returns the sums and the coordinates summed (`q.len()`
/// when some lane is still at or below `t`).
#[inline(always)]
fn block_partial_sums(q: &[f32], p: &[f32], t: f32) -> ([f32; LANES], usize) {
    let mut acc = [0.0f32; LANES];
    let dim = q.len();
    let mut i0 = 0;
    while i0 < dim {
        let i1 = (i0 + CHUNK).min(dim);
        // Two interleaved sums per lane, so consecutive adds do not wait on
        // each other; every partial sum still only grows.
        let (mut a0, mut a1) = ([0.0f32; LANES], [0.0f32; LANES]);
        let mut i = i0;
        while i + 2 <= i1 {
            let (q0, q1) = (q[i], q[i + 1]);
            let r0: &[f32; LANES] = p[i * LANES..(i + 1) * LANES].try_into().expect("LANES wide");
            let r1: &[f32; LANES] = p[(i + 1) * LANES..(i + 2) * LANES]
                .try_into()
                .expect("LANES wide");
            for l in 0..LANES {
                let d0 = q0 - r0[l];
                let d1 = q1 - r1[l];
                a0[l] += d0 * d0;
                a1[l] += d1 * d1;
            }
            i += 2;
        }
        if i < i1 {
            let r0 = &p[i * LANES..(i + 1) * LANES];
            for l in 0..LANES {
                let d0 = q[i] - r0[l];
                a0[l] += d0 * d0;
            }
        }
        let mut alive = 0u32;
        for l in 0..LANES {
            acc[l] += a0[l] + a1[l];
            alive |= u32::from(acc[l] <= t);
        }
        if alive == 0 {
            return (acc, i1);
        }
        i0 = i1;
    }
    (acc, dim)
}

/// `‖ŵ − w‖` bound for a rotated vector `ŵ = R v` computed in `f64` and
/// then rounded to `f32` (module docs, bound 3).
fn rotation_error(v: &[f64], w: &[f64], rmax: f64) -> f64 {
    let n = v.len();
    let l1: f64 = v.iter().map(|a| a.abs()).sum();
    let l2: f64 = w.iter().map(|a| a * a).sum::<f64>().sqrt();
    let prod = (n as f64).sqrt() * gamma(n + 2, f64::EPSILON / 2.0) * rmax * l1;
    let round = f64::from(f32::EPSILON) / 2.0 * l2;
    (prod + round) * 1.01 + ABS
}

/// Offers vector `j` at computed distance `d2` to `best`, the `k` smallest
/// `(distance, index)` pairs so far in that order; returns whether it was
/// kept. Any offering order gives the list [`super::classic`]'s index-order
/// scan gives.
#[inline]
pub fn offer(best: &mut Vec<(f64, usize)>, k: usize, d2: f64, j: usize) -> bool {
    if k == 0 || !d2.is_finite() {
        return false;
    }
    let before = |e: &(f64, usize)| e.0 < d2 || (e.0 == d2 && e.1 < j);
    if best.len() == k && before(&best[k - 1]) {
        return false;
    }
    let pos = best.partition_point(before);
    best.insert(pos, (d2, j));
    best.truncate(k);
    true
}

/// Orders `idx` as the leaves of a k-d tree on the rows of `w` (`dim`
/// wide): split at a multiple of [`LANES`] near the median of the
/// coordinate of largest range, so all leaves but the last are full.
fn kd_order(w: &[f64], dim: usize, idx: &mut [usize]) {
    if idx.len() <= LANES {
        return;
    }
    let mut widest = (0, f64::NEG_INFINITY);
    for i in 0..dim {
        let (lo, hi) = idx
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &j| {
                let a = w[j * dim + i];
                (lo.min(a), hi.max(a))
            });
        if hi - lo > widest.1 {
            widest = (i, hi - lo);
        }
    }
    let c = widest.0;
    idx.sort_unstable_by(|&a, &b| w[a * dim + c].total_cmp(&w[b * dim + c]).then(a.cmp(&b)));
    let leaves = idx.len().div_ceil(LANES);
    let left = (leaves.div_ceil(2) * LANES).min(idx.len());
    let (l, r) = idx.split_at_mut(left);
    kd_order(w, dim, l);
    kd_order(w, dim, r);
}

/// Eigenvectors of the symmetric `a` (`d x d`, row-major) by cyclic Jacobi
/// rotations; on return the diagonal of `a` holds the eigenvalues and column
/// `j` of the result (row-major) the eigenvector of `a[j][j]`. Stops after
/// [`SWEEPS`] sweeps or when the off-diagonal part is negligible.
fn jacobi_eigen(a: &mut [f64], d: usize) -> Vec<f64> {
    let mut v = vec![0.0; d * d];
    for i in 0..d {
        v[i * d + i] = 1.0;
    }
    for _ in 0..SWEEPS {
        let mut off = 0.0;
        let mut diag = 0.0;
        for p in 0..d {
            diag += a[p * d + p] * a[p * d + p];
            for q in p + 1..d {
                off += a[p * d + q] * a[p * d + q];
            }
        }
        if off <= 1e-24 * diag || off == 0.0 {
            break;
        }
        for p in 0..d {
            for q in p + 1..d {
                let apq = a[p * d + q];
                if apq == 0.0 {
                    continue;
                }
                let theta = (a[q * d + q] - a[p * d + p]) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                if !(c.is_finite() && s.is_finite()) || s == 0.0 {
                    continue;
                }
                for r in 0..d {
                    let (x, y) = (a[r * d + p], a[r * d + q]);
                    a[r * d + p] = c * x - s * y;
                    a[r * d + q] = s * x + c * y;
                }
                for r in 0..d {
                    let (x, y) = (a[p * d + r], a[q * d + r]);
                    a[p * d + r] = c * x - s * y;
                    a[q * d + r] = s * x + c * y;
                }
                for r in 0..d {
                    let (x, y) = (v[r * d + p], v[r * d + q]);
                    v[r * d + p] = c * x - s * y;
                    v[r * d + q] = s * x + c * y;
                }
            }
        }
    }
    v
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

    /// The indexed search of every query (`None` where it declines).
    fn indexed(ix: &KnnIndex, x: &[f64], dim: usize, q: &[f64], k: usize) -> Vec<Option<Vec<(f64, usize)>>> {
        let (mut v, mut y) = (Vec::new(), Vec::new());
        ix.rotate(q, &mut v, &mut y);
        let mut scratch = Scratch::default();
        (0..q.len() / dim)
            .map(|i| {
                let r = i * dim..(i + 1) * dim;
                let mut best = vec![(1.0, 7)];
                ix.search(x, &q[r.clone()], &v[r.clone()], &y[r], k, &mut best, &mut scratch)
                    .then_some(best)
            })
            .collect()
    }

    fn bits(v: &[(f64, usize)]) -> Vec<(u64, usize)> {
        v.iter().map(|&(d, j)| (d.to_bits(), j)).collect()
    }

    fn check(x: &[f64], dim: usize, q: &[f64], k: usize) {
        let ix = KnnIndex::build(x, dim).expect("finite rows in range");
        for (i, got) in indexed(&ix, x, dim, q, k).into_iter().enumerate() {
            let z = &q[i * dim..(i + 1) * dim];
            let got = got.expect("query in range");
            assert_eq!(
                bits(&got),
                bits(&full_scan(x, dim, z, k)),
                "query {i}, k {k}, dim {dim}"
            );
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// Coarse values (ties, duplicate rows), 1-row sets, dim 1, `k` above
        /// the training set, tiny to huge magnitudes: the same list as the
        /// full scan, or an honest refusal out of range.
        #[test]
        fn search_is_the_full_scan(
            n in 1usize..70,
            dim in 1usize..7,
            k in 1usize..90,
            scale_exp in prop::sample::select(vec![-300i32, -150, -20, 0, 10, 14, 150]),
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
            match KnnIndex::build(&x, dim) {
                None => prop_assert!(scale_exp >= 14),
                Some(ix) => {
                    for (i, got) in indexed(&ix, &x, dim, &q, k).into_iter().enumerate() {
                        let z = &q[i * dim..(i + 1) * dim];
                        match got {
                            Some(got) => prop_assert_eq!(bits(&got), bits(&full_scan(&x, dim, z, k))),
                            None => prop_assert!(scale_exp >= 14),
                        }
                    }
                }
            }
        }
    }

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
        // Queries that are training vectors (distance 0) and near copies.
        let q: Vec<f64> = x[..30 * dim]
            .iter()
            .map(|v| v + 1e-12)
            .chain(x[..5 * dim].iter().copied())
            .collect();
        check(&x, dim, &q, 5);
    }
}

#[cfg(test)]
mod measure {
    use super::*;

    /// Pruning statistics on exported standardised arrays (raw little-endian
    /// f64, 80 wide): `KNN_BIN=/tmp/knn_tr1.bin,/tmp/knn_te1.bin`.
    #[test]
    #[ignore = "measurement on exported data"]
    fn pruning_statistics() {
        let Ok(paths) = std::env::var("KNN_BIN") else {
            return;
        };
        let read = |p: &str| -> Vec<f64> {
            std::fs::read(p)
                .expect("readable")
                .chunks_exact(8)
                .map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes")))
                .collect()
        };
        let mut it = paths.split(',');
        let (x, q) = (read(it.next().expect("train")), read(it.next().expect("test")));
        let dim = 80;
        let t0 = std::time::Instant::now();
        let ix = KnnIndex::build(&x, dim).expect("index");
        let build = t0.elapsed();
        let (mut v, mut y) = (Vec::new(), Vec::new());
        ix.rotate(&q, &mut v, &mut y);
        let mut scratch = Scratch::default();
        let mut best = Vec::new();
        let t0 = std::time::Instant::now();
        for i in 0..q.len() / dim {
            let r = i * dim..(i + 1) * dim;
            assert!(ix.search(
                &x,
                &q[r.clone()],
                &v[r.clone()],
                &y[r],
                10,
                &mut best,
                &mut scratch
            ));
        }
        let s = scratch.stats;
        let n = (x.len() / dim) as f64;
        eprintln!(
            "build {build:?}, search {:?}; per query: blocks {:.1} of {}, lanes visited {:.3} of n, f32 coordinate work {:.3} of n*dim, exact {:.1} ({:.4} of n)",
            t0.elapsed(),
            s.blocks as f64 / s.queries as f64,
            ix.blocks,
            s.blocks as f64 * LANES as f64 / s.queries as f64 / n,
            s.lane_coords as f64 / s.queries as f64 / (n * dim as f64),
            s.exact as f64 / s.queries as f64,
            s.exact as f64 / s.queries as f64 / n
        );
    }
}
