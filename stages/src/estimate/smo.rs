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
//! * **Kernel in memory.** [`solve_gram`] is the same algorithm, step for
//!   step and bit for bit, for a kernel already held in memory (the `svm`
//!   stage's fits, [`PairBlocks`]; any [`GramRows`]): no row cache or
//!   gathers (a problem's kernel rows are copied once from its blocks), and the
//!   selections and the gradient update scan dense arrays with AVX2 (masks
//!   for `I_up`, `I_low` and the active set; ties broken by variable index as
//!   the sequential loops break them; the update of `G` and the next `i` in
//!   one pass). [`solve`] / [`solve_rows`] stay the reference (and the path
//!   for kernels that do not fit in memory); test
//!   `gram_solver_is_the_row_solver_bit_for_bit`. Measured on the peers SVM
//!   workload (136 machines of ~144 vectors, 21 k iterations in all; one
//!   core, shared 2-core machine, min of 20): the machines took 22.9 ms
//!   through `solve_rows` (≈1.1 µs an iteration, index-list loops with
//!   unpredictable branches) and ~7 ms through `solve_gram` (a quarter of
//!   that was the first copy of each row, from a whole Gram matrix that did
//!   not fit in L2; the machines' blocks, computed as each machine starts,
//!   now are in cache when it copies them).
//! * **Selections without per-lane branches** (2026-12-06). With
//!   AVX-512, the scans' running best `(value, variable)` pairs are
//!   reduced in registers (each half of the lanes offered to the other by
//!   the same rule, a total order, so the same pick), where they were
//!   stored and picked by a scalar loop with unpredictable branches
//!   (~40 % of the `j` scan and ~30 % of the gradient update in `perf
//!   annotate`); the lanes outside `I_up` / `I_low` are set to a pair that
//!   never wins before the comparison, which takes the mask off the
//!   latency chain from one block of positions to the next; and a
//!   problem's kept kernel rows reuse the thread's buffer of the last
//!   problem instead of fresh pages (a page fault and a zeroed page each
//!   time, 166 KB a machine). Every kernel value, gradient update and
//!   comparison is the IEEE operation it was, so the iterations and bits
//!   are unchanged (tests `gram_solver_is_the_row_solver_bit_for_bit`,
//!   `avx512_reductions_pick_as_the_scalar_rule`; the peers SVM's test
//!   scores `cmp`-identical). Peers SVM fit, CPU time of the one rayon
//!   worker per fit (`RAYON_NUM_THREADS=1 perf record -e cpu-clock
//!   target/release/examples/peers --out <dir> --seed 1 --only svm
//!   --profile N:0`, samples of N = 201 or 301 minus N = 1, per fit; old and new
//!   binaries alternated on a loaded 2-core AVX-512 host, six and seven
//!   runs): 11.2-12.4 ms before (median 11.4), 8.6-11.1 ms after (median
//!   9.6), −16 %; the fit's wall time in the bench's `baselines.json`
//!   (same command without `--profile`, eight alternated runs each on a
//!   quieter host) 10.85 ms before and 9.9 ms after (medians), −9 to
//!   −11 % (it also holds the fit's serial parts); the kernel blocks
//!   (`dense::sq_cols512`, at the FMA units' rate) are now the largest part.
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

/// libsvm's `TAU`: the curvature used where `Q_ii + Q_jj - 2 Q_ij` is not
/// positive (a semi-definite kernel, or rounding).
const TAU: f64 = 1e-12;

/// The analytic two-variable step of SMO on the pair `(i, j)` with the box
/// `[0, c]` (libsvm's `Solver::Solve`, Fan, Chen & Lin 2005): moves
/// `alpha[i]` and `alpha[j]` along the constraint line to the minimum of the
/// dual on it, then clips to the box. `qij` is `Q_ij`, `diag` and `grad` are
/// `(Q_ii, Q_jj)` and `(G_i, G_j)`. One function for every solver, so the row
/// and the Gram solvers take the same steps.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn pair_step(
    opposite: bool,
    qij: f64,
    [qii, qjj]: [f64; 2],
    [gi, gj]: [f64; 2],
    alpha: &mut [f64],
    i: usize,
    j: usize,
    c: f64,
) {
    let (ci, cj) = (c, c);
    if opposite {
        let quad = qii + qjj + 2.0 * qij;
        let quad = if quad > 0.0 { quad } else { TAU };
        let delta = (-gi - gj) / quad;
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
        let quad = qii + qjj - 2.0 * qij;
        let quad = if quad > 0.0 { quad } else { TAU };
        let delta = (gi - gj) / quad;
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
        let (old_i, old_j) = (alpha[i], alpha[j]);
        pair_step(
            y[i] != y[j],
            qi[j],
            [diag[i], diag[j]],
            [grad[i], grad[j]],
            &mut alpha,
            i,
            j,
            c,
        );
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

/// The kernel of a [`solve_gram`] problem, by positions `0..len()`.
pub trait GramRows {
    /// The number of positions.
    fn len(&self) -> usize;
    /// True when there are no positions.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// `K(p, p)`.
    fn diag(&self, p: usize) -> f64;
    /// Appends `K(p, q)` for every position `q`, in order, to `out`.
    fn extend_row(&self, p: usize, out: &mut Vec<f64>);
}

/// The kernel of a one-vs-one machine by class blocks: positions `0..na`
/// are class a's vectors, `na..na + nb` class b's; `a` (`na x na`) and `b`
/// (`nb x nb`) are the classes' own kernel matrices, whole and row-major,
/// `cross` (`na x nb`) the kernel between them. A row of class a is a row
/// of `a` then a row of `cross`; a row of class b a column of `cross` then
/// a row of `b`.
///
/// Why: with the whole Gram matrix computed before the machines (its upper
/// triangle alone 6 MB for the peers SVM's 1224 vectors), each machine
/// read its rows back from memory; a machine's `cross` block (~40 KB) is
/// computed when the machine starts and read while it is in cache, and the
/// classes' blocks are small and read by every machine of their class.
#[derive(Clone, Copy, Debug)]
pub struct PairBlocks<'a> {
    a: &'a [f64],
    b: &'a [f64],
    cross: &'a [f64],
    na: usize,
    nb: usize,
}

impl<'a> PairBlocks<'a> {
    /// Class a's kernel matrix `a` (`na x na`), class b's `b` (`nb x nb`)
    /// and the kernel between them `cross` (`na x nb`), all row-major.
    ///
    /// # Panics
    /// If a block's length is not its shape's.
    pub fn new(a: &'a [f64], b: &'a [f64], cross: &'a [f64], na: usize, nb: usize) -> Self {
        assert!(
            Some(a.len()) == na.checked_mul(na)
                && Some(b.len()) == nb.checked_mul(nb)
                && Some(cross.len()) == na.checked_mul(nb),
            "PairBlocks: blocks of the wrong size"
        );
        PairBlocks { a, b, cross, na, nb }
    }
}

impl GramRows for PairBlocks<'_> {
    fn len(&self) -> usize {
        self.na + self.nb
    }
    fn diag(&self, p: usize) -> f64 {
        if p < self.na {
            self.a[p * self.na + p]
        } else {
            let q = p - self.na;
            self.b[q * self.nb + q]
        }
    }
    fn extend_row(&self, p: usize, out: &mut Vec<f64>) {
        let (na, nb) = (self.na, self.nb);
        if p < na {
            out.extend_from_slice(&self.a[p * na..(p + 1) * na]);
            out.extend_from_slice(&self.cross[p * nb..(p + 1) * nb]);
        } else {
            let q = p - na;
            out.extend((0..na).map(|i| self.cross[i * nb + q]));
            out.extend_from_slice(&self.b[q * nb..(q + 1) * nb]);
        }
    }
}

/// Variables of a [`solve_gram`] problem are at most this many (ranks are
/// held exactly as `f64` lanes).
const MAX_GRAM_N: usize = 1 << 52;

/// [`solve_rows`] for a kernel held in memory, with the same iterations
/// and bits: variable `var[p]` is position `p` of `k`, `y` is indexed by
/// variable, and the answer equals `solve_rows(y, diag, fill, p)` with
/// `fill(v, out)` writing the kernel entries between the variables'
/// positions (test
/// `gram_solver_is_the_row_solver_bit_for_bit`).
///
/// Why a second solver: with every kernel value already in memory the
/// row cache and its gathers are pure overhead, and the three scans of an
/// iteration (select `i`, select `j`, update `G`) dominated the fit (1.1 µs
/// an iteration, branchy index-list loops). Here the scans run over dense
/// per-position arrays with the membership of `I_up`/`I_low` (and of the
/// active set) held as masks, four lanes at a time with AVX2, eight with
/// AVX-512 (a scalar loop otherwise, same bits): every value is the same
/// IEEE operation as in [`solve_rows`], and ties are broken as there (the
/// last variable in variable order wins) by comparing `(value, variable)`
/// pairs, so the positions may be in any order. Shrunk variables stay
/// masked out of the selections; their gradients are updated too (cheaper
/// than skipping them lane by lane) and, as in [`solve_rows`], rebuilt from
/// the multipliers before they count again. The update of `G` and the
/// next selection of `i` share one pass.
pub fn solve_gram<K: GramRows + ?Sized>(k: &K, y: &[f64], var: &[usize], p: &SmoParams) -> Solution {
    let n = k.len();
    assert!(n <= MAX_GRAM_N, "solve_gram: too many variables");
    assert_eq!(y.len(), n, "one label per position");
    assert_eq!(var.len(), n, "one variable per position");
    let mut pos_of = vec![usize::MAX; n];
    for (pos, &v) in var.iter().enumerate() {
        assert!(
            v < n && pos_of[v] == usize::MAX,
            "var must be a permutation of 0..n"
        );
        pos_of[v] = pos;
    }
    let mut st = GramState::new(k, y, var, p.c);
    let n_pad = st.y.len();
    let simd = crate::wide::avx2();
    let mut rows = KRows::new(k, n_pad, p.cache_bytes);
    let c = p.c;
    let mut shrunk = false;
    let mut unshrunk = false;
    let shrink_every = n.clamp(1, 1000);
    let mut counter = shrink_every;
    let mut iterations = 0usize;
    let mut converged = false;
    // (position of i or NONE, −y_i G_i) from the last gradient update's pass.
    let mut next_i: Option<(usize, f64)> = None;

    while iterations < p.max_iter {
        counter -= 1;
        if counter == 0 {
            counter = shrink_every;
            if p.shrinking && !unshrunk {
                st.shrink();
                shrunk |= st.n_active < n;
                next_i = None;
            }
        }
        let was_unshrunk = std::mem::replace(&mut unshrunk, false);
        let (i, gmax) = match next_i.take() {
            Some(sel) => sel,
            None => st.best_up(simd, pos_of.as_slice()),
        };
        let (mut j, mut gmax2) = (NONE, f64::NEG_INFINITY);
        if i != NONE {
            let ri = rows.fetch(i, 0);
            (j, gmax2) = st.best_low(simd, &pos_of, i, gmax, rows.get(ri), TAU);
        }
        if i == NONE || j == NONE || gmax + gmax2 < p.tol {
            if shrunk && !was_unshrunk {
                st.reconstruct_gradient(&mut rows, &pos_of);
                st.activate_all();
                shrunk = false;
                unshrunk = true;
                next_i = None;
                continue;
            }
            converged = true;
            break;
        }
        iterations += 1;
        let (ri, rj) = (rows.fetch(i, 0), rows.fetch(j, 1));
        let (ki, kj) = (rows.get(ri), rows.get(rj));
        let (y, alpha, grad, diag) = (&st.y, &mut st.alpha, &st.grad, &st.diag);
        // Q_ij, as the row cache holds it.
        let qij = ki[j] * (y[i] * y[j]);
        let (old_i, old_j) = (alpha[i], alpha[j]);
        pair_step(
            y[i] != y[j],
            qij,
            [diag[i], diag[j]],
            [grad[i], grad[j]],
            alpha,
            i,
            j,
            c,
        );
        let (di, dj) = (alpha[i] - old_i, alpha[j] - old_j);
        st.set_masks(i);
        st.set_masks(j);
        next_i = Some(st.update_and_best_up(simd, &pos_of, (i, di, ki), (j, dj, kj)));
    }
    if !converged && shrunk {
        // Hit the cap while shrunk: make the gradient whole for ρ.
        st.reconstruct_gradient(&mut rows, &pos_of);
    }
    // ρ and the answer in variable order (ρ sums over the free variables in that order).
    let y_var: Vec<f64> = pos_of.iter().map(|&q| st.y[q]).collect();
    let alpha: Vec<f64> = pos_of.iter().map(|&q| st.alpha[q]).collect();
    let grad: Vec<f64> = pos_of.iter().map(|&q| st.grad[q]).collect();
    let rho = rho(&y_var, &alpha, &grad, c);
    Solution {
        alpha,
        rho,
        iterations,
        converged,
        rows_computed: rows.copied,
    }
}

/// No variable (selection found none).
const NONE: usize = usize::MAX;

/// All bits set: a lane that takes part (the masks of [`GramState`]).
const ON: f64 = f64::from_bits(u64::MAX);

/// Per-position state of [`solve_gram`], padded to a multiple of 16 with
/// lanes that never take part (masks off, kernel 0).
struct GramState {
    n: usize,
    c: f64,
    y: Vec<f64>,
    /// `−y` (the sign of `−y_t G_t`).
    ny: Vec<f64>,
    /// Variable index, as `f64` (exact), for breaking ties as [`solve_rows`].
    rank: Vec<f64>,
    diag: Vec<f64>,
    alpha: Vec<f64>,
    grad: Vec<f64>,
    active: Vec<bool>,
    n_active: usize,
    /// [`ON`] where the variable is active and in `I_up` (`I_low`), else 0.
    up: Vec<f64>,
    low: Vec<f64>,
    /// The scans may use AVX-512 (asked once per problem, not per scan).
    x512: bool,
}

impl GramState {
    fn new<K: GramRows + ?Sized>(k: &K, y: &[f64], var: &[usize], c: f64) -> Self {
        let n = k.len();
        // A multiple of 16: the AVX-512 scans take 16 positions a step.
        let n_pad = n.div_ceil(16) * 16;
        let pad = |v: Vec<f64>, fill: f64| {
            let mut v = v;
            v.resize(n_pad, fill);
            v
        };
        let yp: Vec<f64> = var.iter().map(|&v| y[v]).collect();
        let mut st = GramState {
            n,
            c,
            ny: pad(yp.iter().map(|&v| -v).collect(), -1.0),
            y: pad(yp, 1.0),
            rank: pad(var.iter().map(|&v| v as f64).collect(), -1.0),
            diag: pad((0..n).map(|p| k.diag(p)).collect(), 1.0),
            alpha: vec![0.0; n_pad],
            grad: pad(vec![-1.0; n], 0.0),
            active: vec![true; n],
            n_active: n,
            up: vec![0.0; n_pad],
            low: vec![0.0; n_pad],
            x512: crate::wide::avx512(),
        };
        st.activate_all();
        st
    }

    /// Recomputes the masks of position `t` from its multiplier and activity.
    fn set_masks(&mut self, t: usize) {
        let (y, a, c, on) = (self.y[t], self.alpha[t], self.c, self.active[t]);
        let up = on && ((y > 0.0 && a < c) || (y < 0.0 && a > 0.0));
        let low = on && ((y > 0.0 && a > 0.0) || (y < 0.0 && a < c));
        self.up[t] = if up { ON } else { 0.0 };
        self.low[t] = if low { ON } else { 0.0 };
    }

    fn activate_all(&mut self) {
        self.active.iter_mut().for_each(|a| *a = true);
        self.n_active = self.n;
        (0..self.n).for_each(|t| self.set_masks(t));
    }

    /// [`shrink`] on positions: the same variables leave the active set.
    fn shrink(&mut self) {
        let (mut gmax1, mut gmax2) = (f64::NEG_INFINITY, f64::NEG_INFINITY);
        for t in 0..self.n {
            if self.up[t].to_bits() != 0 {
                gmax1 = gmax1.max(-self.y[t] * self.grad[t]);
            }
            if self.low[t].to_bits() != 0 {
                gmax2 = gmax2.max(self.y[t] * self.grad[t]);
            }
        }
        for t in 0..self.n {
            if !self.active[t] {
                continue;
            }
            let (y, g, a) = (self.y[t], self.grad[t], self.alpha[t]);
            let drop = if a >= self.c {
                if y > 0.0 {
                    -g > gmax1
                } else {
                    -g > gmax2
                }
            } else if a <= 0.0 {
                if y > 0.0 {
                    g > gmax2
                } else {
                    g > gmax1
                }
            } else {
                false
            };
            if drop {
                self.active[t] = false;
                self.n_active -= 1;
                self.set_masks(t);
            }
        }
    }

    /// [`reconstruct_gradient`]: `G_t = −1 + Σ_s Q_ts α_s`, summed over `s`
    /// in variable order as there, `Q_st = K_st · (y_s y_t)` as the row cache
    /// holds it.
    fn reconstruct_gradient<K: GramRows + ?Sized>(&mut self, rows: &mut KRows<'_, K>, pos_of: &[usize]) {
        self.grad[..self.n].iter_mut().for_each(|g| *g = -1.0);
        for &s in pos_of {
            let a = self.alpha[s];
            if a != 0.0 {
                let at = rows.fetch(s, 0);
                let row = rows.get(at);
                let ys = self.y[s];
                let (grad, y) = (&mut self.grad[..self.n], &self.y[..self.n]);
                crate::wide::with_avx2(
                    #[inline(always)]
                    || {
                        for ((g, &kv), &yt) in grad.iter_mut().zip(row.iter()).zip(y) {
                            *g += kv * (ys * yt) * a;
                        }
                    },
                );
            }
        }
    }

    /// WSS 2's `i`: the active `I_up` position with the largest `−y_t G_t`
    /// (the last in variable order among equals), and that value.
    fn best_up(&self, simd: bool, pos_of: &[usize]) -> (usize, f64) {
        #[cfg(target_arch = "x86_64")]
        if simd {
            // SAFETY: AVX2 is present (`simd` is `wide::avx2()`); the arrays
            // are equally long, a multiple of 8.
            let (r, v) = if self.x512 {
                // SAFETY: AVX-512 F/VL/DQ are present (`x512`); a multiple of 16.
                unsafe { x86::best_up512(&self.up, &self.ny, &self.grad, &self.rank) }
            } else {
                unsafe { x86::best_up(&self.up, &self.ny, &self.grad, &self.rank) }
            };
            return (rank_pos(r, pos_of), v);
        }
        let _ = simd;
        let (mut best, mut br) = (f64::NEG_INFINITY, -1.0);
        for t in 0..self.n {
            if self.up[t].to_bits() != 0 {
                let v = self.ny[t] * self.grad[t];
                if v > best || (v == best && self.rank[t] > br) {
                    (best, br) = (v, self.rank[t]);
                }
            }
        }
        (rank_pos(br, pos_of), best)
    }

    /// WSS 2's `j` for `i` (kernel row `ki`, `gmax = −y_i G_i`): among the
    /// active `I_low` positions with `b = gmax + y_t G_t > 0`, the smallest
    /// `−b² / a` (the last in variable order among equals); and
    /// `max_{I_low} y_t G_t`.
    fn best_low(
        &self,
        simd: bool,
        pos_of: &[usize],
        i: usize,
        gmax: f64,
        ki: &[f64],
        tau: f64,
    ) -> (usize, f64) {
        let di = self.diag[i];
        #[cfg(target_arch = "x86_64")]
        if simd {
            // SAFETY: as in `best_up`; `ki` is as long as the arrays.
            let l = x86::Low {
                low: &self.low,
                y: &self.y,
                grad: &self.grad,
                diag: &self.diag,
                rank: &self.rank,
                ki,
            };
            let (r, g2) = if self.x512 {
                // SAFETY: AVX-512 F/VL/DQ are present (`x512`); a multiple of 16.
                unsafe { x86::best_low512(l, gmax, di, tau) }
            } else {
                unsafe { x86::best_low(l, gmax, di, tau) }
            };
            return (rank_pos(r, pos_of), g2);
        }
        let _ = simd;
        let (mut best, mut br, mut gmax2) = (f64::INFINITY, -1.0, f64::NEG_INFINITY);
        for (t, &kt) in ki.iter().enumerate().take(self.n) {
            if self.low[t].to_bits() == 0 {
                continue;
            }
            let yg = self.y[t] * self.grad[t];
            if yg >= gmax2 {
                gmax2 = yg;
            }
            let b = gmax + yg;
            if b > 0.0 {
                // 2.0 · y_i · y_t · Q_it of solve_rows is exactly 2 K_it.
                let a = di + self.diag[t] - 2.0 * kt;
                let obj = -(b * b) / if a > 0.0 { a } else { tau };
                if obj < best || (obj == best && self.rank[t] > br) {
                    (best, br) = (obj, self.rank[t]);
                }
            }
        }
        (rank_pos(br, pos_of), gmax2)
    }

    /// `G_t += Q_it Δα_i + Q_jt Δα_j` at every position (`Q_st = K_st ·
    /// (y_s y_t)`, kernel rows `ki`, `kj`), then [`Self::best_up`] on the new
    /// gradient, in one pass.
    fn update_and_best_up(
        &mut self,
        simd: bool,
        pos_of: &[usize],
        (i, di, ki): (usize, f64, &[f64]),
        (j, dj, kj): (usize, f64, &[f64]),
    ) -> (usize, f64) {
        let (yi, yj) = (self.y[i], self.y[j]);
        #[cfg(target_arch = "x86_64")]
        if simd {
            // SAFETY: as in `best_up`; `ki` and `kj` are as long as the arrays.
            let u = x86::Up {
                up: &self.up,
                y: &self.y,
                ny: &self.ny,
                rank: &self.rank,
                ki,
                kj,
            };
            let (r, v) = if self.x512 {
                // SAFETY: AVX-512 F/VL/DQ are present (`x512`); a multiple of 16.
                unsafe { x86::update_best_up512(&mut self.grad, u, [yi, di, yj, dj]) }
            } else {
                unsafe { x86::update_best_up(&mut self.grad, u, [yi, di, yj, dj]) }
            };
            return (rank_pos(r, pos_of), v);
        }
        let _ = simd;
        for t in 0..self.n {
            let yt = self.y[t];
            self.grad[t] += ki[t] * (yi * yt) * di + kj[t] * (yj * yt) * dj;
        }
        self.best_up(false, pos_of)
    }
}

/// Kernel rows of a [`solve_gram`] problem over its positions (zero
/// padded), copied from the kernel's blocks the first time each is
/// needed and kept while they fit in `cache_bytes`: SMO comes back to the
/// same few rows again and again, and a problem's rows then sit in one
/// compact block that stays in cache, where reading them from the Gram
/// matrix went to as many scattered rows (measured: the row copies took a
/// quarter of the solver's time). Past the budget, two scratch rows are
/// refilled per iteration.
struct KRows<'a, K: GramRows + ?Sized> {
    k: &'a K,
    n: usize,
    n_pad: usize,
    /// Offset of each position's row in `kept` (`usize::MAX`: not there).
    slot: Vec<usize>,
    kept: Vec<f64>,
    keep: bool,
    scratch: [Vec<f64>; 2],
    /// Rows copied from the kernel.
    copied: usize,
}

impl<K: GramRows + ?Sized> Drop for KRows<'_, K> {
    /// Hands the buffer of kept rows to the thread's next problem (if at
    /// most [`SPARE_ROWS_BYTES`]).
    fn drop(&mut self) {
        if self.kept.capacity() * std::mem::size_of::<f64>() <= SPARE_ROWS_BYTES {
            let spare = std::mem::take(&mut self.kept);
            SPARE_ROWS.with(|s| s.set(spare));
        }
    }
}

/// The largest buffer of kept rows [`KRows`] leaves to its thread's next
/// problem (4 MiB: a problem of ~720 variables).
const SPARE_ROWS_BYTES: usize = 4 << 20;

thread_local! {
    /// A thread's buffer of kept rows from its last problem. Why: a
    /// problem's rows (166 KB for the peers SVM's 144-variable machines)
    /// were a fresh allocation each, above `malloc`'s threshold for a
    /// mapping of its own, so every machine's first touch of each page
    /// went through a page fault and the kernel's zeroing of the page
    /// (~4 % of the fit in `perf`); reused, they are also still in cache.
    static SPARE_ROWS: std::cell::Cell<Vec<f64>> = const { std::cell::Cell::new(Vec::new()) };
}

/// Where [`KRows::fetch`] put a row.
#[derive(Clone, Copy)]
enum RowAt {
    Kept(usize),
    Scratch(usize),
}

impl<'a, K: GramRows + ?Sized> KRows<'a, K> {
    fn new(k: &'a K, n_pad: usize, cache_bytes: usize) -> Self {
        let n = k.len();
        let keep = n.saturating_mul(n_pad).saturating_mul(std::mem::size_of::<f64>()) <= cache_bytes;
        let mut kept = Vec::new();
        if keep {
            kept = SPARE_ROWS.with(std::cell::Cell::take);
            kept.clear();
            kept.reserve(n * n_pad);
        }
        KRows {
            k,
            n,
            n_pad,
            slot: vec![usize::MAX; n],
            kept,
            keep,
            scratch: [vec![0.0; n_pad], vec![0.0; n_pad]],
            copied: 0,
        }
    }

    /// Makes the row of position `p` available (in scratch row `which` if
    /// rows are not kept).
    fn fetch(&mut self, p: usize, which: usize) -> RowAt {
        if self.keep && self.slot[p] != usize::MAX {
            return RowAt::Kept(self.slot[p]);
        }
        self.copied += 1;
        let (k, n, n_pad) = (self.k, self.n, self.n_pad);
        let fill = |out: &mut Vec<f64>| {
            k.extend_row(p, out);
            out.resize(out.len() + n_pad - n, 0.0);
        };
        if self.keep {
            let at = self.kept.len();
            fill(&mut self.kept);
            self.slot[p] = at;
            RowAt::Kept(at)
        } else {
            let out = &mut self.scratch[which];
            out.clear();
            fill(out);
            RowAt::Scratch(which)
        }
    }

    fn get(&self, at: RowAt) -> &[f64] {
        match at {
            RowAt::Kept(o) => &self.kept[o..o + self.n_pad],
            RowAt::Scratch(w) => &self.scratch[w],
        }
    }
}

/// Position of the variable with rank `r` (an `f64` from the lanes; −1: none).
fn rank_pos(r: f64, pos_of: &[usize]) -> usize {
    if r < 0.0 {
        NONE
    } else {
        pos_of[r as usize]
    }
}

/// AVX2 scans of [`solve_gram`]: positions go by 8, as two vectors of 4
/// with their own running best `(value, rank)` pairs (two chains, so the
/// loop is not bound by the latency of one); lane `l` of chain `h` sees
/// positions `8m + 4h + l`. The eight pairs are then reduced by the same
/// rule, so the pick is the scalar loop's. Only the IEEE operations of the
/// scalar code (no FMA), so the same bits.
///
/// Where the CPU has AVX-512 (F, VL, DQ), the `*512` forms take 16
/// positions a step (two chains of 8 lanes, lane masks as bits): the same
/// operations lane by lane and the same reduction rule, so the same pick.
/// Peers SVM fit, old and new binaries alternated (`RAYON_NUM_THREADS=1
/// target/release/examples/peers --out <dir> --seed 1 --only svm --repeats
/// 7`, four pairs, 2026-11-27): 19.3-20.8 ms against 18.2-19.3 ms, and
/// after a tidy-up of the reductions 20.2-22.0 against 19.6-20.3 ms; test
/// scores `cmp`-identical. The test `gram_solver_is_the_row_solver_bit_for_bit`
/// runs both forms (and the scalar loop) against the row solver.
#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    /// Inputs of [`best_low`].
    pub(super) struct Low<'a> {
        pub low: &'a [f64],
        pub y: &'a [f64],
        pub grad: &'a [f64],
        pub diag: &'a [f64],
        pub rank: &'a [f64],
        pub ki: &'a [f64],
    }

    /// Inputs of [`update_best_up`] besides the gradient.
    pub(super) struct Up<'a> {
        pub up: &'a [f64],
        pub y: &'a [f64],
        pub ny: &'a [f64],
        pub rank: &'a [f64],
        pub ki: &'a [f64],
        pub kj: &'a [f64],
    }

    /// Running best `(value, rank)` pairs of two chains.
    #[derive(Clone, Copy)]
    struct Best {
        v: [__m256d; 2],
        r: [__m256d; 2],
    }

    impl Best {
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn new(v: f64) -> Self {
            Best {
                v: [_mm256_set1_pd(v); 2],
                r: [_mm256_set1_pd(-1.0); 2],
            }
        }

        /// Chain `h` takes `(v, r)` where it beats its pair: `CMP` on the
        /// values (strictly), or equal values and a larger rank; only in
        /// `mask`. The lanes out of `mask` are first made `(∓∞, −1)`, which
        /// beat no pair, so the mask stays off the chain from one block of
        /// positions to the next (as in [`Best512::offer`]).
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn offer<const CMP: i32>(&mut self, h: usize, v: __m256d, r: __m256d, mask: __m256d) {
            let (best, br) = (self.v[h], self.r[h]);
            let none = _mm256_set1_pd(if CMP == _CMP_GT_OQ {
                f64::NEG_INFINITY
            } else {
                f64::INFINITY
            });
            let v = _mm256_blendv_pd(none, v, mask);
            let r = _mm256_blendv_pd(_mm256_set1_pd(-1.0), r, mask);
            let strict = _mm256_cmp_pd::<CMP>(v, best);
            let eq = _mm256_cmp_pd::<_CMP_EQ_OQ>(v, best);
            let later = _mm256_cmp_pd::<_CMP_GT_OQ>(r, br);
            let upd = _mm256_or_pd(strict, _mm256_and_pd(eq, later));
            self.v[h] = _mm256_blendv_pd(best, v, upd);
            self.r[h] = _mm256_blendv_pd(br, r, upd);
        }

        /// Chain 0 takes the pairs `(v, r)` that beat it, every lane.
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn merge(&mut self, max: bool, v: __m256d, r: __m256d) {
            let all = _mm256_castsi256_pd(_mm256_set1_epi64x(-1));
            if max {
                self.offer::<_CMP_GT_OQ>(0, v, r, all);
            } else {
                self.offer::<_CMP_LT_OQ>(0, v, r, all);
            }
        }

        /// The best of the eight pairs: the largest value (`max`) or the
        /// smallest, then the largest rank; `(rank, value)`, rank −1 = none.
        /// In registers and without a branch, as [`Best512::reduce`] (chain
        /// 1 offered to chain 0, then the 128-bit halves to each other,
        /// then neighbours): the rule is a total order on the pairs, so
        /// the winner is the pair `pick` returns. It replaced a store
        /// of the 16 doubles and `pick`'s loop, whose branches the
        /// predictor cannot learn: with the one-vs-one machines' few
        /// positions per scan, `best_low` and `update_best_up` were 38 %
        /// of the SVM's fit on the AVX2 path (`perf`, `PALPATE_NO_AVX512=1`).
        /// With it (and [`Self::offer`]'s pre-blend) that fit went from
        /// 11.1-11.5 to 10.3-10.8 ms (`RAYON_NUM_THREADS=1
        /// PALPATE_NO_AVX512=1 target/release/examples/peers --out <dir>
        /// --seed 1 --only svm --repeats 15`, old and new alternated three
        /// times, 2026-12-07, AMD EPYC).
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn reduce(&self, max: bool) -> (f64, f64) {
            let mut b = *self;
            b.merge(max, self.v[1], self.r[1]);
            let (v, r) = (b.v[0], b.r[0]);
            b.merge(
                max,
                _mm256_permute2f128_pd::<0x01>(v, v),
                _mm256_permute2f128_pd::<0x01>(r, r),
            );
            let (v, r) = (b.v[0], b.r[0]);
            b.merge(
                max,
                _mm256_permute_pd::<0b0101>(v),
                _mm256_permute_pd::<0b0101>(r),
            );
            (
                _mm_cvtsd_f64(_mm256_castpd256_pd128(b.r[0])),
                _mm_cvtsd_f64(_mm256_castpd256_pd128(b.v[0])),
            )
        }
    }

    /// The largest of the eight lanes of two running maxima of `y G`, in
    /// registers (see [`max16`]: the same value as `last_max` up to the
    /// sign of a zero).
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn max8(g: [__m256d; 2]) -> f64 {
        let m = _mm256_max_pd(g[0], g[1]);
        let m = _mm256_max_pd(m, _mm256_permute2f128_pd::<0x01>(m, m));
        let m = _mm256_max_pd(m, _mm256_permute_pd::<0b0101>(m));
        _mm_cvtsd_f64(_mm256_castpd256_pd128(m))
    }

    /// [`Best::reduce`] and [`max8`] on eight given lanes (lane `4h + l`
    /// is lane `l` of chain `h`), for the tests.
    #[cfg(test)]
    pub(super) fn reduce256_lanes(vs: &[f64; 8], rs: &[f64; 8], max: bool) -> ((f64, f64), f64) {
        assert!(crate::wide::avx2());
        // SAFETY: AVX2 is present (asserted); 8 doubles each.
        unsafe { reduce256_lanes_inner(vs, rs, max) }
    }

    #[cfg(test)]
    #[target_feature(enable = "avx2")]
    unsafe fn reduce256_lanes_inner(vs: &[f64; 8], rs: &[f64; 8], max: bool) -> ((f64, f64), f64) {
        // SAFETY: 8 doubles each, 4 per load.
        let ld = |a: &[f64; 8], h: usize| unsafe { _mm256_loadu_pd(a.as_ptr().add(4 * h)) };
        let b = Best {
            v: [ld(vs, 0), ld(vs, 1)],
            r: [ld(rs, 0), ld(rs, 1)],
        };
        // SAFETY: AVX2 is present (the caller's).
        unsafe { (b.reduce(max), max8([ld(vs, 0), ld(vs, 1)])) }
    }

    /// The best of the lanes' `(value, rank)` pairs: the largest value
    /// (`max`) or the smallest, then the largest rank, skipping rank −1
    /// (none); `(rank, value)`.
    #[cfg(test)]
    fn pick(vs: &[f64], rs: &[f64], max: bool) -> (f64, f64) {
        let (mut bv, mut br) = (vs[0], rs[0]);
        for (&v, &r) in vs.iter().zip(rs).skip(1) {
            if r < 0.0 {
                continue;
            }
            let better = if max { v > bv } else { v < bv };
            if br < 0.0 || better || (v == bv && r > br) {
                (bv, br) = (v, r);
            }
        }
        (br, bv)
    }

    /// The lanes' running maxima of `y G` reduced in lane order, as the
    /// scalar loop's `yg >= gmax2`.
    #[cfg(test)]
    fn last_max(gs: &[f64]) -> f64 {
        gs.iter()
            .fold(f64::NEG_INFINITY, |m, &v| if v >= m { v } else { m })
    }

    /// Four doubles of `a` from `t` (callers assert `t + 4 <= a.len()`).
    #[inline(always)]
    unsafe fn at(a: &[f64], t: usize) -> __m256d {
        debug_assert!(t + 4 <= a.len());
        // SAFETY: in bounds (above); the caller has AVX.
        unsafe { _mm256_loadu_pd(a.as_ptr().add(t)) }
    }

    /// `(rank, −y_i G_i)` of the best `I_up` lane (rank −1: none).
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn best_up(up: &[f64], ny: &[f64], grad: &[f64], rank: &[f64]) -> (f64, f64) {
        let n = up.len();
        assert!(n.is_multiple_of(8) && ny.len() == n && grad.len() == n && rank.len() == n);
        let mut best = Best::new(f64::NEG_INFINITY);
        for t0 in (0..n).step_by(8) {
            for h in 0..2 {
                let t = t0 + 4 * h;
                // SAFETY: t + 4 <= n, every array holds n doubles (asserted).
                let (m, v, r) = unsafe { (at(up, t), _mm256_mul_pd(at(ny, t), at(grad, t)), at(rank, t)) };
                best.offer::<_CMP_GT_OQ>(h, v, r, m);
            }
        }
        best.reduce(true)
    }

    /// The gradient update, then [`best_up`] on the result, in one pass.
    /// `s = [y_i, Δα_i, y_j, Δα_j]`.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn update_best_up(grad: &mut [f64], u: Up<'_>, s: [f64; 4]) -> (f64, f64) {
        let n = grad.len();
        assert!(n.is_multiple_of(8));
        for a in [u.up, u.y, u.ny, u.rank, u.ki, u.kj] {
            assert!(a.len() == n);
        }
        let (yi, di, yj, dj) = (
            _mm256_set1_pd(s[0]),
            _mm256_set1_pd(s[1]),
            _mm256_set1_pd(s[2]),
            _mm256_set1_pd(s[3]),
        );
        let mut best = Best::new(f64::NEG_INFINITY);
        let g = grad.as_mut_ptr();
        for t0 in (0..n).step_by(8) {
            for h in 0..2 {
                let t = t0 + 4 * h;
                // SAFETY: t + 4 <= n, every array holds n doubles (asserted).
                unsafe {
                    let yt = at(u.y, t);
                    // Q_it = K_it · (y_i y_t), then G += Q_it Δα_i + Q_jt Δα_j.
                    let qi = _mm256_mul_pd(at(u.ki, t), _mm256_mul_pd(yi, yt));
                    let qj = _mm256_mul_pd(at(u.kj, t), _mm256_mul_pd(yj, yt));
                    let step = _mm256_add_pd(_mm256_mul_pd(qi, di), _mm256_mul_pd(qj, dj));
                    let gv = _mm256_add_pd(_mm256_loadu_pd(g.add(t)), step);
                    _mm256_storeu_pd(g.add(t), gv);
                    let v = _mm256_mul_pd(at(u.ny, t), gv);
                    best.offer::<_CMP_GT_OQ>(h, v, at(u.rank, t), at(u.up, t));
                }
            }
        }
        best.reduce(true)
    }

    /// `(rank of j, max_{I_low} y_t G_t)` (rank −1: no `j`).
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn best_low(l: Low<'_>, gmax: f64, di: f64, tau: f64) -> (f64, f64) {
        let n = l.low.len();
        assert!(n.is_multiple_of(8));
        for a in [l.y, l.grad, l.diag, l.rank, l.ki] {
            assert!(a.len() == n);
        }
        let gm = _mm256_set1_pd(gmax);
        let dii = _mm256_set1_pd(di);
        let two = _mm256_set1_pd(2.0);
        let tau = _mm256_set1_pd(tau);
        let zero = _mm256_setzero_pd();
        let sign = _mm256_set1_pd(-0.0);
        let ninf = _mm256_set1_pd(f64::NEG_INFINITY);
        let mut best = Best::new(f64::INFINITY);
        let mut g2 = [ninf; 2];
        for t0 in (0..n).step_by(8) {
            for (h, g2h) in g2.iter_mut().enumerate() {
                let t = t0 + 4 * h;
                // SAFETY: t + 4 <= n, every array holds n doubles (asserted).
                let (m, yg) = unsafe { (at(l.low, t), _mm256_mul_pd(at(l.y, t), at(l.grad, t))) };
                // max_pd returns its second operand when the first is NaN: a
                // NaN y G is skipped, as `yg >= gmax2` skips it.
                *g2h = _mm256_max_pd(_mm256_blendv_pd(ninf, yg, m), *g2h);
                let b = _mm256_add_pd(gm, yg);
                let cand = _mm256_and_pd(m, _mm256_cmp_pd::<_CMP_GT_OQ>(b, zero));
                if _mm256_movemask_pd(cand) == 0 {
                    continue;
                }
                // SAFETY: as above.
                let (dt, kt, r) = unsafe { (at(l.diag, t), at(l.ki, t), at(l.rank, t)) };
                let a = _mm256_sub_pd(_mm256_add_pd(dii, dt), _mm256_mul_pd(two, kt));
                let a = _mm256_blendv_pd(tau, a, _mm256_cmp_pd::<_CMP_GT_OQ>(a, zero));
                let obj = _mm256_div_pd(_mm256_xor_pd(_mm256_mul_pd(b, b), sign), a);
                best.offer::<_CMP_LT_OQ>(h, obj, r, cand);
            }
        }
        let (rj, _) = best.reduce(false);
        (rj, max8(g2))
    }

    /// [`Best`] with 512-bit vectors: two chains of 8 lanes, lane `l` of
    /// chain `h` seeing positions `16m + 8h + l`; the same rule, so the
    /// same pick (ties go by rank, so the lane order does not matter).
    #[derive(Clone, Copy)]
    struct Best512 {
        v: [__m512d; 2],
        r: [__m512d; 2],
    }

    impl Best512 {
        #[inline]
        #[target_feature(enable = "avx2,avx512f,avx512vl,avx512dq")]
        fn new(v: f64) -> Self {
            Best512 {
                v: [_mm512_set1_pd(v); 2],
                r: [_mm512_set1_pd(-1.0); 2],
            }
        }

        /// As [`Best::offer`], with the lane mask as bits. The lanes out
        /// of `mask` are first made `(∓∞, −1)` (the start value and
        /// rank, which beat no pair), so the mask does not wait for the
        /// comparisons with the running best: it was folded into the
        /// last step of the chain from one position block to the next
        /// (a masked `vptestmq`), the scans' longest latency.
        #[inline]
        #[target_feature(enable = "avx2,avx512f,avx512vl,avx512dq")]
        fn offer<const CMP: i32>(&mut self, h: usize, v: __m512d, r: __m512d, mask: __mmask8) {
            let (best, br) = (self.v[h], self.r[h]);
            let none = _mm512_set1_pd(if CMP == _CMP_GT_OQ {
                f64::NEG_INFINITY
            } else {
                f64::INFINITY
            });
            let v = _mm512_mask_blend_pd(mask, none, v);
            let r = _mm512_mask_blend_pd(mask, _mm512_set1_pd(-1.0), r);
            let strict = _mm512_cmp_pd_mask::<CMP>(v, best);
            let eq = _mm512_cmp_pd_mask::<_CMP_EQ_OQ>(v, best);
            let later = _mm512_cmp_pd_mask::<_CMP_GT_OQ>(r, br);
            let upd = strict | (eq & later);
            self.v[h] = _mm512_mask_blend_pd(upd, best, v);
            self.r[h] = _mm512_mask_blend_pd(upd, br, r);
        }

        /// Chain 0 takes the pairs `(v, r)` that beat it, every lane.
        #[inline]
        #[target_feature(enable = "avx2,avx512f,avx512vl,avx512dq")]
        fn merge(&mut self, max: bool, v: __m512d, r: __m512d) {
            if max {
                self.offer::<_CMP_GT_OQ>(0, v, r, 0xff);
            } else {
                self.offer::<_CMP_LT_OQ>(0, v, r, 0xff);
            }
        }

        /// As [`Best::reduce`], over the sixteen pairs, in registers and
        /// without a branch: chain 1 is offered to chain 0, then each
        /// half of the lanes to the other (256-bit halves, 128-bit
        /// quarters, neighbours), by [`Self::offer`]'s rule. The rule is
        /// a total order on the pairs (the value, then the rank; no lane
        /// holds a NaN, and empty lanes, rank −1, lose to any other), so
        /// the winner is the one pair `pick` returns, whatever the
        /// order of the merges. It replaced a store of the 32 doubles and
        /// a scalar loop with unpredictable branches, which took ~40 % of
        /// `best_low512` and ~30 % of `update_best_up512` (`perf annotate`).
        #[inline]
        #[target_feature(enable = "avx2,avx512f,avx512vl,avx512dq")]
        fn reduce(&self, max: bool) -> (f64, f64) {
            let mut b = *self;
            b.merge(max, self.v[1], self.r[1]);
            let (v, r) = (b.v[0], b.r[0]);
            b.merge(
                max,
                _mm512_shuffle_f64x2::<0b01_00_11_10>(v, v),
                _mm512_shuffle_f64x2::<0b01_00_11_10>(r, r),
            );
            let (v, r) = (b.v[0], b.r[0]);
            b.merge(
                max,
                _mm512_shuffle_f64x2::<0b10_11_00_01>(v, v),
                _mm512_shuffle_f64x2::<0b10_11_00_01>(r, r),
            );
            let (v, r) = (b.v[0], b.r[0]);
            b.merge(
                max,
                _mm512_permute_pd::<0b0101_0101>(v),
                _mm512_permute_pd::<0b0101_0101>(r),
            );
            (
                _mm_cvtsd_f64(_mm512_castpd512_pd128(b.r[0])),
                _mm_cvtsd_f64(_mm512_castpd512_pd128(b.v[0])),
            )
        }
    }

    /// The largest of the sixteen lanes of two running maxima of `y G`
    /// (no lane holds a NaN: `max_pd` keeps its second operand then), in
    /// registers. The scalar fold (`last_max`) keeps the later of two
    /// equal values, so the two may differ only in the sign of a zero,
    /// and the one use of the result, `gmax + gmax2 < tol`, is the same
    /// for both signs.
    #[inline]
    #[target_feature(enable = "avx2,avx512f,avx512vl,avx512dq")]
    fn max16(g: [__m512d; 2]) -> f64 {
        let m = _mm512_max_pd(g[0], g[1]);
        let m = _mm512_max_pd(m, _mm512_shuffle_f64x2::<0b01_00_11_10>(m, m));
        let m = _mm512_max_pd(m, _mm512_shuffle_f64x2::<0b10_11_00_01>(m, m));
        let m = _mm512_max_pd(m, _mm512_permute_pd::<0b0101_0101>(m));
        _mm_cvtsd_f64(_mm512_castpd512_pd128(m))
    }

    /// [`Best512::reduce`] and [`max16`] on sixteen given lanes (lane
    /// `8h + l` is lane `l` of chain `h`), for the tests.
    #[cfg(test)]
    pub(super) fn reduce512_lanes(vs: &[f64; 16], rs: &[f64; 16], max: bool) -> ((f64, f64), f64) {
        assert!(crate::wide::avx512());
        // SAFETY: AVX-512 F/VL/DQ are present (asserted); 16 doubles each.
        unsafe { reduce512_lanes_inner(vs, rs, max) }
    }

    #[cfg(test)]
    #[target_feature(enable = "avx2,avx512f,avx512vl,avx512dq")]
    unsafe fn reduce512_lanes_inner(vs: &[f64; 16], rs: &[f64; 16], max: bool) -> ((f64, f64), f64) {
        // SAFETY: 16 doubles each, 8 per load.
        let ld = |a: &[f64; 16], h: usize| unsafe { _mm512_loadu_pd(a.as_ptr().add(8 * h)) };
        let b = Best512 {
            v: [ld(vs, 0), ld(vs, 1)],
            r: [ld(rs, 0), ld(rs, 1)],
        };
        (b.reduce(max), max16([ld(vs, 0), ld(vs, 1)]))
    }

    /// The scalar rule of the reductions, for the tests.
    #[cfg(test)]
    pub(super) fn pick_lanes(vs: &[f64], rs: &[f64], max: bool) -> ((f64, f64), f64) {
        (pick(vs, rs, max), last_max(vs))
    }

    /// Eight doubles of `a` from `t` (callers assert `t + 8 <= a.len()`).
    #[inline(always)]
    unsafe fn at8(a: &[f64], t: usize) -> __m512d {
        debug_assert!(t + 8 <= a.len());
        // SAFETY: in bounds (above); the caller has AVX-512.
        unsafe { _mm512_loadu_pd(a.as_ptr().add(t)) }
    }

    /// The lanes of a membership mask ([`super::ON`] or 0) that are on.
    #[inline]
    #[target_feature(enable = "avx2,avx512f,avx512vl,avx512dq")]
    fn on(m: __m512d) -> __mmask8 {
        let b = _mm512_castpd_si512(m);
        _mm512_test_epi64_mask(b, b)
    }

    /// [`best_up`] with 512-bit vectors, 16 positions a step.
    #[target_feature(enable = "avx2,avx512f,avx512vl,avx512dq")]
    pub(super) unsafe fn best_up512(up: &[f64], ny: &[f64], grad: &[f64], rank: &[f64]) -> (f64, f64) {
        let n = up.len();
        assert!(n.is_multiple_of(16) && ny.len() == n && grad.len() == n && rank.len() == n);
        let mut best = Best512::new(f64::NEG_INFINITY);
        for t0 in (0..n).step_by(16) {
            for h in 0..2 {
                let t = t0 + 8 * h;
                // SAFETY: t + 8 <= n, every array holds n doubles (asserted).
                let (m, v, r) = unsafe {
                    (
                        on(at8(up, t)),
                        _mm512_mul_pd(at8(ny, t), at8(grad, t)),
                        at8(rank, t),
                    )
                };
                best.offer::<_CMP_GT_OQ>(h, v, r, m);
            }
        }
        best.reduce(true)
    }

    /// [`update_best_up`] with 512-bit vectors, 16 positions a step.
    #[target_feature(enable = "avx2,avx512f,avx512vl,avx512dq")]
    pub(super) unsafe fn update_best_up512(grad: &mut [f64], u: Up<'_>, s: [f64; 4]) -> (f64, f64) {
        let n = grad.len();
        assert!(n.is_multiple_of(16));
        for a in [u.up, u.y, u.ny, u.rank, u.ki, u.kj] {
            assert!(a.len() == n);
        }
        let (yi, di, yj, dj) = (
            _mm512_set1_pd(s[0]),
            _mm512_set1_pd(s[1]),
            _mm512_set1_pd(s[2]),
            _mm512_set1_pd(s[3]),
        );
        let mut best = Best512::new(f64::NEG_INFINITY);
        let g = grad.as_mut_ptr();
        for t0 in (0..n).step_by(16) {
            for h in 0..2 {
                let t = t0 + 8 * h;
                // SAFETY: t + 8 <= n, every array holds n doubles (asserted).
                unsafe {
                    let yt = at8(u.y, t);
                    // The operations of `update_best_up`, lane by lane.
                    let qi = _mm512_mul_pd(at8(u.ki, t), _mm512_mul_pd(yi, yt));
                    let qj = _mm512_mul_pd(at8(u.kj, t), _mm512_mul_pd(yj, yt));
                    let step = _mm512_add_pd(_mm512_mul_pd(qi, di), _mm512_mul_pd(qj, dj));
                    let gv = _mm512_add_pd(_mm512_loadu_pd(g.add(t)), step);
                    _mm512_storeu_pd(g.add(t), gv);
                    let v = _mm512_mul_pd(at8(u.ny, t), gv);
                    best.offer::<_CMP_GT_OQ>(h, v, at8(u.rank, t), on(at8(u.up, t)));
                }
            }
        }
        best.reduce(true)
    }

    /// [`best_low`] with 512-bit vectors, 16 positions a step.
    #[target_feature(enable = "avx2,avx512f,avx512vl,avx512dq")]
    pub(super) unsafe fn best_low512(l: Low<'_>, gmax: f64, di: f64, tau: f64) -> (f64, f64) {
        let n = l.low.len();
        assert!(n.is_multiple_of(16));
        for a in [l.y, l.grad, l.diag, l.rank, l.ki] {
            assert!(a.len() == n);
        }
        let gm = _mm512_set1_pd(gmax);
        let dii = _mm512_set1_pd(di);
        let two = _mm512_set1_pd(2.0);
        let tau = _mm512_set1_pd(tau);
        let zero = _mm512_setzero_pd();
        let sign = _mm512_set1_pd(-0.0);
        let ninf = _mm512_set1_pd(f64::NEG_INFINITY);
        let mut best = Best512::new(f64::INFINITY);
        let mut g2 = [ninf; 2];
        for t0 in (0..n).step_by(16) {
            for (h, g2h) in g2.iter_mut().enumerate() {
                let t = t0 + 8 * h;
                // SAFETY: t + 8 <= n, every array holds n doubles (asserted).
                let (m, yg) = unsafe { (on(at8(l.low, t)), _mm512_mul_pd(at8(l.y, t), at8(l.grad, t))) };
                // max_pd returns its second operand when the first is NaN,
                // as in `best_low`.
                *g2h = _mm512_max_pd(_mm512_mask_blend_pd(m, ninf, yg), *g2h);
                let b = _mm512_add_pd(gm, yg);
                let cand = m & _mm512_cmp_pd_mask::<_CMP_GT_OQ>(b, zero);
                if cand == 0 {
                    continue;
                }
                // SAFETY: as above.
                let (dt, kt, r) = unsafe { (at8(l.diag, t), at8(l.ki, t), at8(l.rank, t)) };
                let a = _mm512_sub_pd(_mm512_add_pd(dii, dt), _mm512_mul_pd(two, kt));
                let a = _mm512_mask_blend_pd(_mm512_cmp_pd_mask::<_CMP_GT_OQ>(a, zero), tau, a);
                let obj = _mm512_div_pd(_mm512_xor_pd(_mm512_mul_pd(b, b), sign), a);
                best.offer::<_CMP_LT_OQ>(h, obj, r, cand);
            }
        }
        let (rj, _) = best.reduce(false);
        (rj, max16(g2))
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
    // In the AVX2 function so the fused `exp` is the FMA instruction.
    crate::wide::with_avx2(
        #[inline(always)]
        || super::vmath::exp(-gamma * sq_dist(a, b)),
    )
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

    /// `solve_gram` against `solve_rows` on the same kernel values: the
    /// problem is a few classes' blocks of a class-sorted Gram matrix, its
    /// variables in the original (unsorted) order, as the `svm` stage sets it up.
    fn gram_vs_rows(seed: u64, n: usize, dim: usize, coarse: bool, p: &SmoParams) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let k = 3;
        // Coarse values give exact kernel ties (the tie-breaking is tested).
        let x: Vec<Vec<f64>> = (0..n)
            .map(|_| {
                (0..dim)
                    .map(|_| {
                        if coarse {
                            f64::from(rng.random_range(0u8..3)) * 0.5
                        } else {
                            rng.random_range(-1.0..1.0)
                        }
                    })
                    .collect()
            })
            .collect();
        let class: Vec<usize> = (0..n).map(|_| rng.random_range(0..k)).collect();
        let mut sorted: Vec<usize> = (0..n).collect();
        sorted.sort_by_key(|&i| class[i]);
        let start = |c: usize| class.iter().filter(|&&d| d < c).count();
        let (a, b) = (0, 2);
        let idx: Vec<usize> = (0..n).filter(|&i| class[i] == a || class[i] == b).collect();
        let y: Vec<f64> = idx
            .iter()
            .map(|&i| if class[i] == b { 1.0 } else { -1.0 })
            .collect();
        let ranges = [start(a)..start(a + 1), start(b)..start(b + 1)];
        let var: Vec<usize> = ranges
            .iter()
            .flat_map(Clone::clone)
            .map(|s| idx.binary_search(&sorted[s]).expect("in the pair"))
            .collect();
        let block = |r: &std::ops::Range<usize>, c: &std::ops::Range<usize>| -> Vec<f64> {
            r.clone()
                .flat_map(|s| c.clone().map(move |t| (s, t)))
                .map(|(s, t)| rbf(&x[sorted[s]], &x[sorted[t]], 0.3))
                .collect()
        };
        let (ra, rb) = (&ranges[0], &ranges[1]);
        let (own_a, own_b, cross) = (block(ra, ra), block(rb, rb), block(ra, rb));
        let kern = PairBlocks::new(&own_a, &own_b, &cross, ra.len(), rb.len());
        let want = solve(&y, &|s, t| rbf(&x[idx[s]], &x[idx[t]], 0.3), p);
        let fast = solve_gram(&kern, &y, &var, p);
        let scalar = crate::wide::baseline_only(|| solve_gram(&kern, &y, &var, p));
        // The AVX2 scans where the CPU also has AVX-512 (`fast` took those).
        let avx2 = crate::wide::without_avx512(|| solve_gram(&kern, &y, &var, p));
        for got in [&fast, &scalar, &avx2] {
            let bits = |s: &Solution| s.alpha.iter().map(|a| a.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(got), bits(&want), "seed {seed}, n {n}");
            assert_eq!(got.rho.to_bits(), want.rho.to_bits(), "seed {seed}, n {n}");
            assert_eq!((got.iterations, got.converged), (want.iterations, want.converged));
        }
    }

    /// Every row and diagonal entry of [`PairBlocks`] is the symmetric
    /// matrix's: class a's rows from its own block and the cross block,
    /// class b's from a column of the cross block and its own block; with
    /// empty classes too.
    #[test]
    fn pair_blocks_read_the_symmetric_matrix() {
        let k = |s: usize, t: usize| (s.min(t) * 1000 + s.max(t)) as f64;
        for (na, nb) in [(1, 1), (3, 5), (17, 2), (0, 4), (4, 0)] {
            let n = na + nb;
            let block = |r: std::ops::Range<usize>, c: std::ops::Range<usize>| -> Vec<f64> {
                r.flat_map(|s| c.clone().map(move |t| k(s, t))).collect()
            };
            let (a, b, cross) = (block(0..na, 0..na), block(na..n, na..n), block(0..na, na..n));
            let g = PairBlocks::new(&a, &b, &cross, na, nb);
            assert_eq!(g.len(), n);
            for p in 0..n {
                let mut row = vec![-1.0];
                g.extend_row(p, &mut row);
                let want: Vec<f64> = std::iter::once(-1.0).chain((0..n).map(|q| k(p, q))).collect();
                assert_eq!(row, want, "({na}, {nb}), row {p}");
                assert_eq!(g.diag(p), k(p, p));
            }
        }
    }

    #[test]
    #[should_panic(expected = "blocks of the wrong size")]
    fn pair_blocks_of_the_wrong_size_are_refused() {
        let _ = PairBlocks::new(&[1.0], &[1.0], &[1.0, 2.0], 1, 1);
    }

    #[test]
    fn gram_solver_is_the_row_solver_bit_for_bit() {
        let base = SmoParams {
            c: 10.0,
            ..SmoParams::default()
        };
        for seed in 0..12u64 {
            // Sizes around the 8-position steps, with and without ties.
            let n = [90, 151, 37, 200][seed as usize % 4];
            gram_vs_rows(seed, n, 5, seed % 2 == 0, &base);
        }
        // No shrinking; rows not kept (cache below one problem); other C;
        // the iteration cap (hit while shrunk or not).
        gram_vs_rows(
            20,
            160,
            4,
            false,
            &SmoParams {
                shrinking: false,
                ..base
            },
        );
        gram_vs_rows(
            21,
            160,
            4,
            true,
            &SmoParams {
                cache_bytes: 0,
                ..base
            },
        );
        gram_vs_rows(22, 120, 3, false, &SmoParams { c: 0.5, ..base });
        gram_vs_rows(
            23,
            120,
            3,
            false,
            &SmoParams {
                c: 100.0,
                tol: 1e-6,
                ..base
            },
        );
        for cap in [5, 130, 400] {
            gram_vs_rows(
                24,
                300,
                3,
                false,
                &SmoParams {
                    max_iter: cap,
                    ..base
                },
            );
        }
        // Tiny problems: a class may be missing from the pair (one class only, or none).
        for seed in 30..40u64 {
            gram_vs_rows(seed, 1 + seed as usize % 5, 2, true, &base);
        }
    }

    /// The in-register reductions of the AVX-512 scans pick what the
    /// scalar rule picks, lane for lane: random values with ties (equal
    /// values, ±0), empty lanes (rank −1 with the start value), infinite
    /// values; the largest `y G` equal up to the sign of a zero.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx512_reductions_pick_as_the_scalar_rule() {
        if !crate::wide::avx512() {
            return;
        }
        reductions_pick_as_the_scalar_rule::<16>(x86::reduce512_lanes);
    }

    /// The same for the AVX2 scans' reductions (eight lanes).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_reductions_pick_as_the_scalar_rule() {
        if !crate::wide::avx2() {
            return;
        }
        reductions_pick_as_the_scalar_rule::<8>(x86::reduce256_lanes);
    }

    /// A reduction of `L` lanes of values and ranks: `((rank, value), max)`.
    #[cfg(target_arch = "x86_64")]
    type Reduce<const L: usize> = fn(&[f64; L], &[f64; L], bool) -> ((f64, f64), f64);

    /// `reduce` against `x86::pick_lanes` on `L` lanes (see above).
    #[cfg(target_arch = "x86_64")]
    fn reductions_pick_as_the_scalar_rule<const L: usize>(reduce: Reduce<L>) {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        for round in 0..20_000 {
            let max = round % 2 == 0;
            let start = if max { f64::NEG_INFINITY } else { f64::INFINITY };
            let mut ranks: Vec<f64> = (0..L as u32).map(f64::from).collect();
            for t in (1..L).rev() {
                ranks.swap(t, rng.random_range(0..=t));
            }
            let (mut vs, mut rs) = ([0.0f64; L], [0.0f64; L]);
            for ((v, r), &rank) in vs.iter_mut().zip(&mut rs).zip(&ranks) {
                (*v, *r) = match rng.random_range(0..8) {
                    0 => (start, -1.0),
                    1 => (0.0, rank),
                    2 => (-0.0, rank),
                    3 => (-start, rank),
                    4 => (start, rank),
                    _ => (f64::from(rng.random_range(-3i8..3)) * 0.25, rank),
                };
            }
            let ((r, v), g) = reduce(&vs, &rs, max);
            let ((wr, wv), wg) = x86::pick_lanes(&vs, &rs, max);
            assert_eq!(
                (r.to_bits(), v.to_bits()),
                (wr.to_bits(), wv.to_bits()),
                "{vs:?} {rs:?} {max}"
            );
            assert_eq!(g, wg, "{vs:?}");
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
