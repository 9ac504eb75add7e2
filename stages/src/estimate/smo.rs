//! Exact binary C-SVM training by sequential minimal optimisation (SMO), the
//! algorithm of libsvm (Chang & Lin 2011; Fan, Chen & Lin 2005), used by the
//! `svm` stage for each of its one-vs-one machines.
//!
//! # The problem
//!
//! Given vectors `x_1 .. x_n` with labels `y_t ∈ {-1, +1}`, a kernel `K` and a
//! penalty `C`, the dual of the soft-margin SVM is
//!
//! ```text
//! min_α  ½ αᵀ Q α − Σ_t α_t,   Q_st = y_s y_t K(x_s, x_t),
//! s.t.   0 ≤ α_t ≤ C,   Σ_t y_t α_t = 0.
//! ```
//!
//! The decision function is `f(x) = Σ_t α_t y_t K(x_t, x) − ρ`.
//!
//! # The algorithm
//!
//! SMO keeps the gradient `G = Q α − e` and changes two multipliers per
//! iteration, the pair that most violates the KKT conditions to second order
//! (libsvm's "WSS 2"): `i = argmax_{t ∈ I_up} −y_t G_t`, then among `t ∈ I_low`
//! with `−y_t G_t < −y_i G_i` the `j` minimising `−b²/a` with
//! `b = −y_i G_i + y_t G_t` and `a = K_ii + K_tt − 2 K_it` (`τ = 1e-12` when
//! `a ≤ 0`). The two-variable sub-problem is solved exactly and clipped to the
//! box, and `G` is updated with the two Q rows. It stops when the maximal
//! violation `m(α) − M(α) = max_{I_up} −y G − min_{I_low} −y G` is below `tol`
//! (libsvm's `eps`, default 1e-3), which bounds the distance to the optimum;
//! `ρ` is the mean of `y_t G_t` over the free multipliers (midpoint of the
//! feasible interval when none is free), as libsvm's `calculate_rho`.
//!
//! * **Kernel cache.** Q rows are computed when first needed and kept in a
//!   least-recently-used cache bounded in bytes (`cache_bytes`), stored by row
//!   index (a hit is an index, no hashing). The kernel comes by entries
//!   ([`solve`], `K(s, t)`) or by whole rows ([`solve_rows`], e.g. gathered
//!   from a precomputed Gram matrix, one call per row); SMO touches the
//!   rows of the few vectors that end up as support vectors again and again, so
//!   most kernel values are computed once. When the whole matrix fits (the
//!   `svm` stage's problems do: a pair of classes has ~10² vectors) nothing is
//!   ever evicted.
//! * **Shrinking.** Every `min(n, 1000)` iterations, multipliers at a bound
//!   whose gradient says they will stay there (libsvm's `be_shrunk`) leave the
//!   active set, so selection and gradient updates scan fewer entries. When the
//!   active set has converged, the full gradient is rebuilt from the
//!   multipliers (`G_t = −1 + Σ_s Q_ts α_s`), every variable is reactivated,
//!   and the solver goes on until the *whole* problem meets `tol`, so shrinking
//!   changes the path, not the answer (to within `tol`).
//! * **Iteration cap.** `max_iter` (libsvm has one too) bounds the work on a
//!   degenerate problem; each iteration strictly lowers the objective, so the
//!   cap is only a guard. [`Solution::converged`] says whether it was hit.
//!
//! Why not smartcore's `SVC`: it is an approximate online solver (LaSVM, a
//! fixed number of passes) that recomputes and allocates every kernel value it
//! touches: ~10 s per Table 2 fold, against well under 1 s here (the `svm`
//! stage's `fit median ms` in the timing table of graphs/paper/table2.toml).
//! The stage's accuracy "cliff" (5 training vectors per trial: 34.9° MAE with
//! LaSVM, 8: 0.26°) was **not** the solver: this exact solver, and
//! scikit-learn's `SVC` on the same vectors, gave the same cliff. Its cause
//! was which vectors a capped trial contributed (see the training caps in
//! `features`).

/// Settings of [`solve`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SmoParams {
    /// Upper bound of every multiplier (the soft-margin penalty).
    pub c: f64,
    /// Stopping tolerance on the maximal KKT violation.
    pub tol: f64,
    /// Most iterations (two-variable updates).
    pub max_iter: usize,
    /// Byte budget of the Q-row cache (at least two rows are always kept).
    pub cache_bytes: usize,
    /// Shrink the active set (libsvm's heuristic).
    pub shrinking: bool,
}

impl Default for SmoParams {
    fn default() -> Self {
        SmoParams {
            c: 1.0,
            tol: 1e-3,
            max_iter: 10_000_000,
            cache_bytes: 64 << 20,
            shrinking: true,
        }
    }
}

/// The optimum found by [`solve`].
#[derive(Clone, Debug, PartialEq)]
pub struct Solution {
    /// Multipliers `α_t`, in `[0, C]`.
    pub alpha: Vec<f64>,
    /// Offset ρ of `f(x) = Σ α_t y_t K(x_t, x) − ρ`.
    pub rho: f64,
    /// Iterations run.
    pub iterations: usize,
    /// Whether the KKT violation fell below `tol` (false: `max_iter` was hit).
    pub converged: bool,
    /// Kernel rows computed (cache misses), for tests and benches.
    pub rows_computed: usize,
}

/// Least-recently-used cache of Q rows (full length `n`), stored by row
/// index (no hashing: a lookup is an index, a miss with a full cache scans
/// the `n` stamps for the oldest row and reuses its buffer).
struct RowCache<'a> {
    n: usize,
    y: &'a [f64],
    fill: &'a (dyn Fn(usize, &mut [f64]) + Sync),
    rows: Vec<Option<Vec<f64>>>,
    stamp: Vec<u64>,
    len: usize,
    capacity: usize,
    clock: u64,
    computed: usize,
}

impl<'a> RowCache<'a> {
    fn new(n: usize, y: &'a [f64], fill: &'a (dyn Fn(usize, &mut [f64]) + Sync), cache_bytes: usize) -> Self {
        let per_row = n.max(1).saturating_mul(std::mem::size_of::<f64>());
        RowCache {
            n,
            y,
            fill,
            rows: vec![None; n],
            stamp: vec![0; n],
            len: 0,
            capacity: (cache_bytes / per_row).max(2),
            clock: 0,
            computed: 0,
        }
    }

    /// Q row `i` (`Q_it = y_i y_t K(x_i, x_t)`).
    fn row(&mut self, i: usize) -> &[f64] {
        self.clock += 1;
        self.stamp[i] = self.clock;
        if self.rows[i].is_none() {
            let mut buf = None;
            if self.len >= self.capacity {
                // Evict the least recently used row (O(n), and only on a miss
                // with a full cache); its buffer is reused.
                let old = (0..self.n)
                    .filter(|&t| t != i && self.rows[t].is_some())
                    .min_by_key(|&t| self.stamp[t]);
                if let Some(old) = old {
                    buf = self.rows[old].take();
                    self.len -= 1;
                }
            }
            let mut row = buf.unwrap_or_else(|| vec![0.0; self.n]);
            (self.fill)(i, &mut row);
            let yi = self.y[i];
            row.iter_mut().zip(self.y).for_each(|(q, &yt)| *q *= yi * yt);
            self.computed += 1;
            self.len += 1;
            self.rows[i] = Some(row);
        }
        match &self.rows[i] {
            Some(r) => r,
            None => unreachable!("row {i} was just computed"),
        }
    }
}

/// Solves the C-SVM dual for labels `y` (each ±1) with kernel values
/// `kernel(s, t) = K(x_s, x_t)`, which must be symmetric with `K(t, t) > 0`
/// for the usual convergence guarantee (an RBF kernel gives `K(t, t) = 1`).
/// `n = y.len()`; an empty problem, or one with a single class, returns all
/// multipliers 0 and `ρ` from the gradient (`f` then has the sign of the one
/// class).
pub fn solve(y: &[f64], kernel: &(dyn Fn(usize, usize) -> f64 + Sync), p: &SmoParams) -> Solution {
    let diag: Vec<f64> = (0..y.len()).map(|t| kernel(t, t)).collect();
    let fill = |i: usize, out: &mut [f64]| out.iter_mut().enumerate().for_each(|(t, k)| *k = kernel(i, t));
    solve_rows(y, &diag, &fill, p)
}

/// [`solve`] with the kernel given by rows: `fill(i, out)` writes
/// `K(x_i, x_t)` into `out[t]` for every `t < n` (one call per cache miss
/// instead of one per entry, e.g. a gather from a precomputed Gram matrix),
/// and `diag[t] = K(x_t, x_t)`. The same iterations and bits as [`solve`]
/// with the same kernel values.
pub fn solve_rows(
    y: &[f64],
    diag: &[f64],
    fill: &(dyn Fn(usize, &mut [f64]) + Sync),
    p: &SmoParams,
) -> Solution {
    const TAU: f64 = 1e-12;
    let n = y.len();
    assert_eq!(diag.len(), n, "one diagonal kernel value per variable");
    let c = p.c;
    let mut alpha = vec![0.0f64; n];
    let mut grad = vec![-1.0f64; n];
    let mut cache = RowCache::new(n, y, fill, p.cache_bytes);
    let mut active: Vec<usize> = (0..n).collect();
    let mut shrunk = false;
    let mut unshrunk = false;
    let shrink_every = n.clamp(1, 1000);
    let mut counter = shrink_every;
    let mut iterations = 0usize;
    let mut converged = false;
    let up = |t: usize, a: &[f64]| (y[t] > 0.0 && a[t] < c) || (y[t] < 0.0 && a[t] > 0.0);
    let low = |t: usize, a: &[f64]| (y[t] > 0.0 && a[t] > 0.0) || (y[t] < 0.0 && a[t] < c);
    let mut qi = vec![0.0f64; n];

    while iterations < p.max_iter {
        counter -= 1;
        if counter == 0 {
            counter = shrink_every;
            // Never right after un-shrinking: the whole problem must be
            // checked first, or a converged problem would shrink and
            // un-shrink forever.
            if p.shrinking && !unshrunk {
                shrink(&mut active, y, &alpha, &grad, c, &up, &low);
                shrunk |= active.len() < n;
            }
        }
        let was_unshrunk = std::mem::replace(&mut unshrunk, false);
        // Working-set selection (WSS 2) over the active set.
        let mut gmax = f64::NEG_INFINITY;
        let mut i = usize::MAX;
        for &t in &active {
            if up(t, &alpha) {
                let v = -y[t] * grad[t];
                if v >= gmax {
                    gmax = v;
                    i = t;
                }
            }
        }
        let mut gmax2 = f64::NEG_INFINITY;
        let mut j = usize::MAX;
        let mut best = f64::INFINITY;
        if i != usize::MAX {
            qi.copy_from_slice(cache.row(i));
            for &t in &active {
                if !low(t, &alpha) {
                    continue;
                }
                let yg = y[t] * grad[t];
                if yg >= gmax2 {
                    gmax2 = yg;
                }
                let b = gmax + yg;
                if b > 0.0 {
                    // y_i y_t Q_it = K_it.
                    let a = diag[i] + diag[t] - 2.0 * y[i] * y[t] * qi[t];
                    let obj = -(b * b) / if a > 0.0 { a } else { TAU };
                    if obj <= best {
                        best = obj;
                        j = t;
                    }
                }
            }
        }
        if i == usize::MAX || j == usize::MAX || gmax + gmax2 < p.tol {
            // Converged on the active set: check the whole problem.
            if shrunk && !was_unshrunk {
                reconstruct_gradient(&mut grad, &alpha, &mut cache);
                active = (0..n).collect();
                shrunk = false;
                unshrunk = true;
                continue;
            }
            converged = true;
            break;
        }
        iterations += 1;
        let qj = cache.row(j);
        let (ci, cj) = (c, c);
        let (old_i, old_j) = (alpha[i], alpha[j]);
        if y[i] != y[j] {
            let quad = diag[i] + diag[j] + 2.0 * qi[j];
            let quad = if quad > 0.0 { quad } else { TAU };
            let delta = (-grad[i] - grad[j]) / quad;
            let diff = alpha[i] - alpha[j];
            alpha[i] += delta;
            alpha[j] += delta;
            if diff > 0.0 {
                if alpha[j] < 0.0 {
                    alpha[j] = 0.0;
                    alpha[i] = diff;
                }
            } else if alpha[i] < 0.0 {
                alpha[i] = 0.0;
                alpha[j] = -diff;
            }
            if diff > ci - cj {
                if alpha[i] > ci {
                    alpha[i] = ci;
                    alpha[j] = ci - diff;
                }
            } else if alpha[j] > cj {
                alpha[j] = cj;
                alpha[i] = cj + diff;
            }
        } else {
            let quad = diag[i] + diag[j] - 2.0 * qi[j];
            let quad = if quad > 0.0 { quad } else { TAU };
            let delta = (grad[i] - grad[j]) / quad;
            let sum = alpha[i] + alpha[j];
            alpha[i] -= delta;
            alpha[j] += delta;
            if sum > ci {
                if alpha[i] > ci {
                    alpha[i] = ci;
                    alpha[j] = sum - ci;
                }
            } else if alpha[j] < 0.0 {
                alpha[j] = 0.0;
                alpha[i] = sum;
            }
            if sum > cj {
                if alpha[j] > cj {
                    alpha[j] = cj;
                    alpha[i] = sum - cj;
                }
            } else if alpha[i] < 0.0 {
                alpha[i] = 0.0;
                alpha[j] = sum;
            }
        }
        let (di, dj) = (alpha[i] - old_i, alpha[j] - old_j);
        for &t in &active {
            grad[t] += qi[t] * di + qj[t] * dj;
        }
    }
    if !converged && shrunk {
        // Hit the cap while shrunk: make the gradient whole for ρ.
        reconstruct_gradient(&mut grad, &alpha, &mut cache);
    }
    let rho = rho(y, &alpha, &grad, c);
    Solution {
        alpha,
        rho,
        iterations,
        converged,
        rows_computed: cache.computed,
    }
}

/// libsvm's `be_shrunk`: drops bounded variables that cannot be selected again
/// while the current violation bounds hold.
fn shrink(
    active: &mut Vec<usize>,
    y: &[f64],
    alpha: &[f64],
    grad: &[f64],
    c: f64,
    up: &impl Fn(usize, &[f64]) -> bool,
    low: &impl Fn(usize, &[f64]) -> bool,
) {
    let mut gmax1 = f64::NEG_INFINITY; // max over I_up of −y G
    let mut gmax2 = f64::NEG_INFINITY; // max over I_low of y G
    for &t in active.iter() {
        if up(t, alpha) {
            gmax1 = gmax1.max(-y[t] * grad[t]);
        }
        if low(t, alpha) {
            gmax2 = gmax2.max(y[t] * grad[t]);
        }
    }
    active.retain(|&t| {
        let at_upper = alpha[t] >= c;
        let at_lower = alpha[t] <= 0.0;
        let drop = if at_upper {
            if y[t] > 0.0 {
                -grad[t] > gmax1
            } else {
                -grad[t] > gmax2
            }
        } else if at_lower {
            if y[t] > 0.0 {
                grad[t] > gmax2
            } else {
                grad[t] > gmax1
            }
        } else {
            false
        };
        !drop
    });
}

/// `G_t = −1 + Σ_s Q_ts α_s` for every `t`, from the rows of the nonzero multipliers.
fn reconstruct_gradient(grad: &mut [f64], alpha: &[f64], cache: &mut RowCache<'_>) {
    grad.iter_mut().for_each(|g| *g = -1.0);
    for (s, &a) in alpha.iter().enumerate() {
        if a != 0.0 {
            // Q is symmetric: column s = row s.
            let row = cache.row(s);
            grad.iter_mut().zip(row).for_each(|(g, q)| *g += q * a);
        }
    }
}

/// libsvm's `calculate_rho`.
fn rho(y: &[f64], alpha: &[f64], grad: &[f64], c: f64) -> f64 {
    let (mut ub, mut lb) = (f64::INFINITY, f64::NEG_INFINITY);
    let (mut n_free, mut sum_free) = (0usize, 0.0f64);
    for t in 0..y.len() {
        let yg = y[t] * grad[t];
        if alpha[t] >= c {
            if y[t] < 0.0 {
                ub = ub.min(yg);
            } else {
                lb = lb.max(yg);
            }
        } else if alpha[t] <= 0.0 {
            if y[t] > 0.0 {
                ub = ub.min(yg);
            } else {
                lb = lb.max(yg);
            }
        } else {
            n_free += 1;
            sum_free += yg;
        }
    }
    if n_free > 0 {
        sum_free / n_free as f64
    } else if ub.is_finite() && lb.is_finite() {
        (ub + lb) / 2.0
    } else if ub.is_finite() {
        ub
    } else if lb.is_finite() {
        lb
    } else {
        0.0
    }
}

/// `exp(-γ ‖a − b‖²)`, the RBF kernel: the distance with four partial sums
/// ([`sq_dist`]), the exponential by [`super::vmath::exp`], so an entry has
/// the bits of the vectorised Gram and prediction paths
/// ([`super::vmath::rbf_in_place`] of [`super::dense::sq_dists`]).
#[inline]
pub fn rbf(a: &[f64], b: &[f64], gamma: f64) -> f64 {
    super::vmath::exp(-gamma * sq_dist(a, b))
}

pub use super::dense::sq_dist;

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn problem(n: usize, dim: usize, sep: f64, seed: u64) -> (Vec<Vec<f64>>, Vec<f64>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut x = Vec::new();
        let mut y = Vec::new();
        for t in 0..n {
            let label = if t % 2 == 0 { 1.0 } else { -1.0 };
            x.push(
                (0..dim)
                    .map(|d| rng.random_range(-1.0..1.0) + if d == 0 { label * sep } else { 0.0 })
                    .collect(),
            );
            y.push(label);
        }
        (x, y)
    }

    fn objective(x: &[Vec<f64>], y: &[f64], a: &[f64], gamma: f64) -> f64 {
        let mut q = 0.0;
        for s in 0..y.len() {
            for t in 0..y.len() {
                q += a[s] * a[t] * y[s] * y[t] * rbf(&x[s], &x[t], gamma);
            }
        }
        0.5 * q - a.iter().sum::<f64>()
    }

    /// Maximal KKT violation m(α) − M(α) of a solution, from scratch.
    fn violation(x: &[Vec<f64>], y: &[f64], a: &[f64], c: f64, gamma: f64) -> f64 {
        let n = y.len();
        let g: Vec<f64> = (0..n)
            .map(|t| {
                -1.0 + (0..n)
                    .map(|s| y[t] * y[s] * rbf(&x[t], &x[s], gamma) * a[s])
                    .sum::<f64>()
            })
            .collect();
        let mut m = f64::NEG_INFINITY;
        let mut mm = f64::INFINITY;
        for t in 0..n {
            let v = -y[t] * g[t];
            if (y[t] > 0.0 && a[t] < c) || (y[t] < 0.0 && a[t] > 0.0) {
                m = m.max(v);
            }
            if (y[t] > 0.0 && a[t] > 0.0) || (y[t] < 0.0 && a[t] < c) {
                mm = mm.min(v);
            }
        }
        m - mm
    }

    #[test]
    fn solution_is_feasible_and_meets_the_kkt_tolerance() {
        for (sep, c) in [(0.2, 1.0), (1.0, 10.0), (0.0, 0.5)] {
            let (x, y) = problem(60, 4, sep, 3);
            let k = |s: usize, t: usize| rbf(&x[s], &x[t], 0.5);
            let p = SmoParams {
                c,
                ..SmoParams::default()
            };
            let sol = solve(&y, &k, &p);
            assert!(sol.converged);
            assert!(sol.alpha.iter().all(|&a| (0.0..=c).contains(&a)));
            let eq: f64 = sol.alpha.iter().zip(&y).map(|(a, y)| a * y).sum();
            assert!(eq.abs() < 1e-9, "Σ y α = {eq}");
            let v = violation(&x, &y, &sol.alpha, c, 0.5);
            assert!(v < 1.5e-3, "KKT violation {v}");
            assert!(sol.rho.is_finite());
        }
    }

    #[test]
    fn optimum_beats_perturbed_feasible_points() {
        let (x, y) = problem(40, 3, 0.5, 9);
        let k = |s: usize, t: usize| rbf(&x[s], &x[t], 1.0);
        let p = SmoParams {
            c: 2.0,
            tol: 1e-8,
            ..SmoParams::default()
        };
        let sol = solve(&y, &k, &p);
        let f0 = objective(&x, &y, &sol.alpha, 1.0);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for _ in 0..200 {
            // Move along a feasible direction: +d on one positive, +d on one negative.
            let s = 2 * rng.random_range(0..20);
            let t = 2 * rng.random_range(0..20) + 1;
            let d = rng.random_range(-0.05..0.05);
            let mut a = sol.alpha.clone();
            a[s] += d;
            a[t] += d;
            if a[s] < 0.0 || a[t] < 0.0 || a[s] > 2.0 || a[t] > 2.0 {
                continue;
            }
            assert!(objective(&x, &y, &a, 1.0) >= f0 - 1e-9);
        }
    }

    #[test]
    fn separable_data_is_classified_and_shrinking_does_not_change_the_answer() {
        let (x, y) = problem(300, 5, 2.0, 5);
        let k = |s: usize, t: usize| rbf(&x[s], &x[t], 0.2);
        let base = SmoParams {
            c: 10.0,
            tol: 1e-6,
            ..SmoParams::default()
        };
        let a = solve(&y, &k, &base);
        let b = solve(
            &y,
            &k,
            &SmoParams {
                shrinking: false,
                ..base
            },
        );
        // A tiny cache (2 rows) forces evictions and recomputation.
        let tiny = solve(
            &y,
            &k,
            &SmoParams {
                cache_bytes: 0,
                ..base
            },
        );
        let fa = objective(&x, &y, &a.alpha, 0.2);
        let fb = objective(&x, &y, &b.alpha, 0.2);
        let ft = objective(&x, &y, &tiny.alpha, 0.2);
        assert!((fa - fb).abs() < 1e-4 * fa.abs().max(1.0), "{fa} vs {fb}");
        assert!((fa - ft).abs() < 1e-4 * fa.abs().max(1.0), "{fa} vs {ft}");
        assert!(tiny.rows_computed > a.rows_computed);
        for t in 0..y.len() {
            let f: f64 = (0..y.len()).map(|s| a.alpha[s] * y[s] * k(s, t)).sum::<f64>() - a.rho;
            assert!(f * y[t] > 0.0, "training vector {t} misclassified");
        }
    }

    #[test]
    fn row_kernel_and_cache_size_do_not_change_a_bit() {
        // Rows are recomputed with the same bits after an eviction, so the
        // iterations, and the answer, are the same whatever the cache size,
        // and `solve_rows` is `solve` with the kernel given by rows.
        for (seed, n, c) in [(1u64, 90usize, 10.0), (2, 151, 1.0), (3, 40, 100.0)] {
            let (x, y) = problem(n, 4, 0.3, seed);
            let k = |s: usize, t: usize| rbf(&x[s], &x[t], 0.4);
            let p = SmoParams {
                c,
                ..SmoParams::default()
            };
            let a = solve(&y, &k, &p);
            let diag: Vec<f64> = (0..n).map(|t| k(t, t)).collect();
            let fill = |i: usize, out: &mut [f64]| {
                for (t, o) in out.iter_mut().enumerate() {
                    *o = rbf(&x[i], &x[t], 0.4);
                }
            };
            let b = solve_rows(&y, &diag, &fill, &p);
            let tiny = solve_rows(
                &y,
                &diag,
                &fill,
                &SmoParams {
                    cache_bytes: 3 * n * 8,
                    ..p
                },
            );
            assert!(a.converged);
            assert_eq!(a, b);
            assert!(tiny.rows_computed > a.rows_computed);
            assert_eq!((&a.alpha, a.rho.to_bits()), (&tiny.alpha, tiny.rho.to_bits()));
            assert_eq!(a.iterations, tiny.iterations);
        }
    }

    #[test]
    fn degenerate_problems_do_not_panic() {
        let k1 = |_: usize, _: usize| 1.0;
        // Empty, one class only, identical vectors with both labels.
        let e = solve(&[], &k1, &SmoParams::default());
        assert!(e.alpha.is_empty() && e.rho.is_finite());
        let one = solve(&[1.0, 1.0, 1.0], &k1, &SmoParams::default());
        assert!(one.alpha.iter().all(|&a| a == 0.0) && one.rho.is_finite());
        let same = solve(&[1.0, -1.0, 1.0, -1.0], &k1, &SmoParams::default());
        assert!(same.converged && same.rho.is_finite());
        assert!(same.alpha.iter().all(|a| a.is_finite()));
        // The iteration cap stops a run and says so.
        let (x, y) = problem(50, 3, 0.0, 2);
        let k = |s: usize, t: usize| rbf(&x[s], &x[t], 1.0);
        let capped = solve(
            &y,
            &k,
            &SmoParams {
                max_iter: 3,
                ..SmoParams::default()
            },
        );
        assert_eq!(capped.iterations, 3);
        assert!(!capped.converged && capped.rho.is_finite());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]
        #[test]
        fn random_problems_stay_feasible_and_finite(
            seed in 0u64..1000,
            n in 2usize..40,
            c in 0.01f64..100.0,
            gamma in 1e-3f64..10.0,
        ) {
            let (x, y) = problem(n, 3, 0.3, seed);
            let k = |s: usize, t: usize| rbf(&x[s], &x[t], gamma);
            let sol = solve(&y, &k, &SmoParams { c, ..SmoParams::default() });
            prop_assert!(sol.converged);
            prop_assert!(sol.rho.is_finite());
            prop_assert!(sol.alpha.iter().all(|&a| a.is_finite() && (0.0..=c).contains(&a)));
            let eq: f64 = sol.alpha.iter().zip(&y).map(|(a, y)| a * y).sum();
            prop_assert!(eq.abs() < 1e-8 * c.max(1.0) * n as f64);
        }
    }
}
