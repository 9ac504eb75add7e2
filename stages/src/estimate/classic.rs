//! Classical baselines on the same features as the ANN, all written here
//! (SMO, CART, pruned exact neighbours, L-BFGS): stage types `svm`,
//! `random_forest`, `knn` and `logistic`.
//!
//! Design: one stage type per model (rather than one `classic` type with a
//! `model` key), so that each type's keys are exactly the ones that model has
//! and `palpate stages svm` documents them; the feature keys (`frames`, `step`,
//! `stride`, `min_spikes`, `max_train_frames`, `vote`, `save_model`, `model_in`)
//! are the same in all four and mean what they mean for `ann` (see
//! [`super::features`] and, for `model_in`, [`super::saved`]). Every
//! model classifies single feature vectors (default: 5 stacked images, the
//! ANN (ST) input), standardised per feature on the training vectors; a trial's
//! answer is the paper's winner-take-all vote over its active frames.
//!
//! * `svm`: RBF-kernel SVMs, `K(x, z) = exp(-γ‖x - z‖²)`, **one-vs-one** as
//!   libsvm/scikit-learn's `SVC`: one machine per pair of classes (K(K-1)/2 of
//!   them), each on that pair's vectors only, so each problem is small and
//!   balanced. Each machine is trained *exactly* (to libsvm's KKT tolerance) by
//!   our own SMO solver, [`super::smo`] (libsvm's algorithm: second-order
//!   working-set selection, a kernel cache, shrinking). The fold's kernel
//!   is computed once when it fits in `cache_mb` (every vector serves in
//!   K - 1 machines), by class blocks ([`rbf_block`]; the vectors sorted
//!   by class): each class's own block once, in parallel, and the block
//!   between a machine's two classes when that machine starts, so it is in
//!   cache while the machine reads it (the distances with the vectors
//!   across the lanes, [`super::dense::sq_dists_cols`], or the tiled kernel
//!   [`super::dense::sq_dists_strided`] without AVX-512; the exponentials
//!   vectorised, [`super::vmath::rbf_in_place`], ~1 ulp from glibc's `exp`,
//!   which cost a call per entry). A machine's kernel rows come from its
//!   three blocks ([`super::smo::PairBlocks`]; the distances are symmetric
//!   bit for bit, so a column of the cross block is a row of the other),
//!   which [`super::smo::solve_gram`] reads (copying each row it needs
//!   once, within the same `cache_mb` budget) and solves with vectorised
//!   scans, taking the steps of the per-machine solver
//!   ([`super::smo::solve`]) bit for bit (test
//!   `svm_gram_solver_fits_the_model_of_the_per_machine_path_bit_for_bit`).
//!   Memory: the classes' own blocks and one cross block a thread
//!   (`8 (Σ_c n_c² + max n_a n_b)` bytes, ~0.8 MB for the peers SVM's 1224
//!   vectors in 17 classes, where the whole Gram matrix was 12 MB) only when
//!   they fit in `cache_mb` (default 256 MiB), plus per thread the
//!   rows of the machine it trains (`8 n_ab²` bytes, also only within
//!   `cache_mb`); above that each machine computes its rows into its own
//!   row cache of `cache_mb` (the previous path). Measured on the peers SVM
//!   workload (1224 x 80, 17 classes, C = 10; one core, shared 2-core
//!   machine, min of repeats; `RAYON_NUM_THREADS=1
//!   target/release/examples/peers --out /tmp/ws --seed 1 --only svm`):
//!   fit 32-34 ms with per-machine row caches (Gram 9.3 ms, machines
//!   22.9 ms), ~17 ms with the whole Gram matrix in memory, 14-16 ms by
//!   class blocks (2026-11-28; docs/benches.md); scikit-learn's `SVC` on
//!   the same arrays: 41-48 ms (`benches/peers`, by the hour). A vector's
//!   class scores are its votes plus sklearn's tie-breaker, `votes_c + conf_c / (3 (max|conf| + 1))` with
//!   `conf_c` the summed decision values in favour of `c`, so confidences only
//!   order classes with equal votes; scores are divided by `K - 1`. The
//!   machines' support vectors are pooled in [`OvoSvm`] so each one's kernel
//!   value is computed once per frame (libsvm's scheme), for blocks of frames
//!   by the tiled kernel and the vectorised exponential (the bits of
//!   [`super::smo::rbf`], in fit and predict alike). `γ = 0` (auto) is
//!   `1 / dim` (sklearn's "scale" for standardised features).
//!   Why not smartcore's `SVC` (used before): it is LaSVM, an *approximate*
//!   online solver run for a fixed number of passes, which recomputes and
//!   allocates every kernel value it touches (~10 s per Table 2 fold; now
//!   well under 1 s). The accuracy "cliff" in `max_train_frames` (5 vectors
//!   per trial gave 34.9° MAE, 8 gave 0.26°) was not the solver's (the
//!   exact solver and scikit-learn's `SVC` gave the same): it was how a
//!   capped trial's training vectors were picked, now fixed (see the
//!   training caps in [`super::features`]).
//! * `random_forest`: CART trees grown here ([`super::forest`]: Gini,
//!   bootstrap, `m = sqrt(dim)` features per split by default, as
//!   scikit-learn's `RandomForestClassifier`), 15 trees on at most 15 vectors
//!   per training trial; each tree grows from its own seeded generator (in
//!   parallel), and each vector votes for the class most trees predict
//!   (score 1). smartcore's forest, used before, fitted ~3x slower than
//!   scikit-learn and predicted through a matrix per row.
//! * `knn`: k nearest neighbours (Euclidean, on the standardised vectors),
//!   class scores = the neighbours' shares (optionally `1/d`-weighted), as
//!   scikit-learn's `KNeighborsClassifier::predict_proba`. The search is exact
//!   ([`super::knn_scan`]): every query against every training vector in
//!   `f32` through `‖z‖² + ‖x‖² − 2 z·x` (a fused multiply-add kernel with
//!   AVX-512), a rigorous rounding margin, and the exact [`sq_dist`] for the
//!   few vectors the margin cannot exclude (~`k` + 1), so the neighbours are
//!   those of a scan that keeps the `k` smallest `(distance, index)` pairs
//!   (ties go to the earlier training vector), bit for bit. It replaced a
//!   pruned index (principal axes, boxes, a k-d order) that computed ~12% of
//!   the coordinate terms but cost ~2.2 ms to build at the first prediction
//!   and searched at a small share of the multiply rate: on the peers k-NN
//!   workload (3154 x 3060 x 80, k = 10) the scan builds and searches faster
//!   (docs/benches.md). For training sets far larger than the paper's
//!   (~3000 vectors) a pruned index would compute fewer terms. The full `f64`
//!   scan (GEMM identity through the tiled kernel, then an exact re-rank of
//!   the candidates) stays for training sets the scan declines (a value not
//!   finite, a squared norm beyond 1e30). smartcore's search (cover tree or
//!   linear) went through boxed iterators per distance and took ~20 s per fold.
//! * `logistic`: multinomial logistic regression, `alpha/2 ‖W‖²` (intercepts
//!   not penalised) added to the summed log loss, i.e. scikit-learn's
//!   `LogisticRegression(C = 1/alpha)`, fitted by L-BFGS ([`super::lbfgs`])
//!   with scikit-learn's stopping rule (`tol` on the largest gradient
//!   component of the mean objective); the class scores are the softmax
//!   probabilities. smartcore's solver (used before) took ~30x scikit-learn's
//!   time; on Table 2 the new fit moves the MAE from 30.29° to 30.50° (the
//!   intercepts are no longer penalised). Default input: one image
//!   (`frames = 1`): a linear score cannot express "these taxels fire *after*
//!   those" wherever the edge sits in a stacked window, and on the lab scene
//!   the stacked 5-image input gave a worse MAE (~24° against ~16°) at ~10x the
//!   L-BFGS cost. It is the weakest baseline by design, kept as the linear reference.
//!
//! Seeds: the forest takes its seed from the fold's RNG (tree `t` from
//! [`forest::tree_rng`]`(seed, t)`); the SVM (SMO draws
//! nothing at random), k-NN and logistic regression are deterministic. The SVM pairs train in parallel and
//! are gathered (and their support vectors pooled) in pair order, so 1 or N
//! threads give the same bits.

use super::dense::sq_dist;
use super::features::{
    check_scaler, want, Classifier, FeatureKeys, FittedModel, FrameClassifier, Standardizer, TrainSet,
    TrainingLog, Vote, MODEL_FORMAT,
};
use super::{dense, forest, knn_scan, lbfgs, smo, vmath};
use palpate_core::{check_positive, check_range, ConfigChecks, ConfigError, FitContext, Item, StageError};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Standardised training rows of a fold, row-major.
struct Design {
    flat: Vec<f64>,
}

/// Standardises the training vectors in place and moves them out of `set`
/// (`set.x` is left empty; the fits read only the design): the same bits
/// as [`Standardizer::apply_rows`], without a second copy of the training
/// set. That copy was a fresh allocation (2 MB for the k-NN's 3060 x 80)
/// whose page faults cost up to 0.75 ms of a 2.5 ms k-NN fit.
fn design(set: &mut TrainSet, scaler: &Standardizer) -> Design {
    let d = set.dim.max(1);
    let mut flat = std::mem::take(&mut set.x);
    flat.truncate(flat.len() / d * d);
    flat.chunks_exact_mut(d).for_each(|r| scaler.apply(r));
    Design { flat }
}

/// Shared fit after the features are built: standardisation on every
/// training vector, one seed drawn from `rng` (the fold's generator), the
/// model-specific part, packaging.
fn fit_classic_set(
    mut set: TrainSet,
    vote: Vote,
    stage_type: &str,
    rng: &mut ChaCha8Rng,
    fit: impl FnOnce(&TrainSet, Design, Standardizer, u64) -> Result<Classifier, StageError>,
) -> Result<FittedModel, StageError> {
    let all: Vec<usize> = (0..set.len()).collect();
    let scaler = Standardizer::fit(&set, &all);
    let d = design(&mut set, &scaler);
    let seed = rng.random::<u64>();
    let classifier = fit(&set, d, scaler, seed)?;
    Ok(FittedModel {
        format: MODEL_FORMAT,
        stage_type: stage_type.into(),
        log: TrainingLog {
            n_train: set.len(),
            ..TrainingLog::default()
        },
        classes: set.classes,
        features: set.spec,
        vote,
        classifier,
    })
}

// ---------------------------------------------------------------- SVM

/// Multi-class RBF SVM (one-vs-one, each machine trained exactly by SMO) on spike-image features.
///
/// Per-frame votes are combined by the paper's winner-take-all over the trial.
/// Input: spike images; output: orientation estimates.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SvmConfig {
    /// Images stacked per vector (1 = spatial). Default 5.
    pub frames: usize,
    /// Frames between stacked images; 0 = one window. Default 0.
    pub step: usize,
    /// Frames between the frames a trial contributes; 0 = one window. Default 0.
    pub stride: usize,
    /// Smallest spike total of a used vector. Default 1.
    pub min_spikes: f64,
    /// Most vectors a training trial contributes (segment centres, see
    /// `features`). Default 8. Measured on graphs/paper/table2.toml's front
    /// end (lab scene, seed 1): 5 gave a 37.7° MAE cliff (8: 1.7°) while the
    /// picked vectors included each trial's near-empty onset and offset
    /// frames; with segment centres, 2.35° at 5 and 0.15° at 8 (regression
    /// test `svm_cliff_at_five_vectors_per_trial_is_gone`).
    pub max_train_frames: usize,
    /// Soft-margin penalty C. Default 10.
    pub c: f64,
    /// RBF width γ of `exp(-γ‖x-z‖²)` on standardised features; 0 = auto (1 / dim). Default 0.
    pub gamma: f64,
    /// Most SMO iterations per pairwise machine (a guard: the solver stops
    /// earlier, at `tol`; hitting it is an error naming this key). Default 10000000.
    pub max_iter: usize,
    /// Stopping tolerance: largest KKT violation left, as libsvm's `eps`. Default 1e-3.
    pub tol: f64,
    /// Shrink the active set during SMO (libsvm's heuristic; the answer is the
    /// same to within `tol`). Default true.
    pub shrinking: bool,
    /// Kernel cache budget, MiB: the fold's kernel is computed once, by class
    /// blocks (8 (Σ n_c² + max n_a n_b) bytes for classes of n_c training
    /// vectors), when the blocks fit (and each machine
    /// copies the rows it needs from them, when they fit too), otherwise
    /// each machine keeps its own LRU row cache of this size. Default 256.
    pub cache_mb: usize,
    /// `winner` (paper) or `sum`. Default `winner`.
    pub vote: Vote,
    /// Write each fold's fitted model to `<out>/<stage id>.fold<f>.model.json`. Default false.
    pub save_model: bool,
    /// A model saved by an offline run of this stage type (`save_model =
    /// true`), JSON, relative to the graph file. With it the stage does not
    /// fit: it predicts every trial with the loaded model (no folds or
    /// training trials) and streams under `palpate run --live`; the feature
    /// and training keys are then unused (the model keeps its own). Default
    /// none: fit per fold.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model_in: Option<String>,
}

impl Default for SvmConfig {
    fn default() -> Self {
        SvmConfig {
            frames: 5,
            step: 0,
            stride: 0,
            min_spikes: 1.0,
            max_train_frames: 8,
            c: 10.0,
            gamma: 0.0,
            max_iter: 10_000_000,
            tol: 1e-3,
            shrinking: true,
            cache_mb: 256,
            vote: Vote::Winner,
            save_model: false,
            model_in: None,
        }
    }
}

/// One binary machine of [`OvoSvm`]: positive decision = class `b`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BinarySvm {
    /// Class index on the negative side.
    pub a: usize,
    /// Class index on the positive side.
    pub b: usize,
    /// Its support vectors, as rows of [`OvoSvm::sv`].
    pub sv_index: Vec<u32>,
    /// Their coefficients.
    pub coef: Vec<f64>,
    /// Bias.
    pub bias: f64,
}

/// A fitted one-vs-one RBF SVM. The machines' support vectors are pooled:
/// a training vector is a support vector of up to `K - 1` machines, and its
/// kernel value is computed once per frame (as libsvm does), which cuts the
/// cost of a prediction ~`K/2`-fold.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OvoSvm {
    /// Input size.
    pub dim: usize,
    /// Number of classes.
    pub classes: usize,
    /// RBF γ.
    pub gamma: f64,
    /// Input standardisation.
    pub scaler: Standardizer,
    /// Distinct support vectors of all machines, row-major.
    pub sv: Vec<f64>,
    /// One machine per class pair, in pair order.
    pub machines: Vec<BinarySvm>,
}

impl OvoSvm {
    /// Kernel values `exp(-γ‖x - s‖²)` of standardised `x` against every pooled support vector.
    pub fn kernel_row(&self, x: &[f64], out: &mut Vec<f64>) {
        out.resize(self.sv.len() / self.dim.max(1), 0.0);
        self.kernel_into(x, out);
    }

    #[inline]
    fn kernel_into(&self, x: &[f64], out: &mut [f64]) {
        let gamma = self.gamma;
        // Four partial sums per distance in a fixed order, each term fused
        // (`dense` module docs): the same bits with or without AVX2.
        crate::wide::with_avx2(|| {
            for (k, s) in out.iter_mut().zip(self.sv.chunks_exact(self.dim.max(1))) {
                *k = sq_dist(s, x);
            }
        });
        vmath::rbf_in_place(out, gamma);
    }

    /// Decision value of machine `m` given the kernel row of `x`.
    pub fn decision(&self, m: &BinarySvm, kernel: &[f64]) -> f64 {
        let mut f = m.bias;
        for (&i, c) in m.sv_index.iter().zip(&m.coef) {
            f += c * kernel.get(i as usize).copied().unwrap_or(0.0);
        }
        f
    }

    /// Vote shares (with the confidence tie-breaker) of a normalised vector.
    pub fn frame_scores(&self, x: &[f64], out: &mut [f64]) {
        self.scores_batch(x, out);
    }

    /// [`Self::frame_scores`] of every row of `x` (row-major, `dim` wide) into
    /// the rows of `out` (`classes` wide), with the working buffers allocated
    /// once: the same bits as row by row.
    pub fn scores_batch(&self, x: &[f64], out: &mut [f64]) {
        // Rows per block of kernel rows: the block's distances come from one
        // tiled call ([`dense::sq_dists`], the bits of `sq_dist`).
        const QB: usize = 32;
        let dim = self.dim.max(1);
        let k = self.classes;
        let n_sv = self.sv.len() / dim;
        let z = self.scaler.apply_rows(x);
        let n = (z.len() / dim).min(out.len() / k.max(1));
        let mut kernels = vec![0.0; QB * n_sv];
        let mut votes = vec![0.0; k];
        let mut conf = vec![0.0; k];
        let norm = 1.0 / (k.max(2) - 1) as f64;
        let gamma = self.gamma;
        for q0 in (0..n).step_by(QB) {
            let qb = QB.min(n - q0);
            let kb = &mut kernels[..qb * n_sv];
            dense::sq_dists(&z[q0 * dim..(q0 + qb) * dim], &self.sv, dim, kb);
            vmath::rbf_in_place(kb, gamma);
            for q in 0..qb {
                let kernel = &kb[q * n_sv..(q + 1) * n_sv];
                let o = &mut out[(q0 + q) * k..(q0 + q + 1) * k];
                self.vote_row(kernel, &mut votes, &mut conf, norm, o);
            }
        }
    }

    /// Votes and tie-broken shares of one frame from its kernel row.
    #[inline]
    fn vote_row(&self, kernel: &[f64], votes: &mut [f64], conf: &mut [f64], norm: f64, o: &mut [f64]) {
        votes.iter_mut().for_each(|v| *v = 0.0);
        conf.iter_mut().for_each(|v| *v = 0.0);
        for m in &self.machines {
            let f = self.decision(m, kernel);
            if f > 0.0 {
                votes[m.b] += 1.0;
            } else {
                votes[m.a] += 1.0;
            }
            conf[m.b] += f;
            conf[m.a] -= f;
        }
        let cmax = conf.iter().fold(0.0f64, |a, c| a.max(c.abs()));
        for c in 0..self.classes {
            let s = votes[c] + conf[c] / (3.0 * (cmax + 1.0));
            o[c] = (s * norm).max(0.0);
        }
    }
}

/// Bytes of the SVM's kernel blocks for classes of `sizes` vectors: each
/// class's own block and one cross block per machine in progress (the
/// widest counted once), `8 (Σ_c n_c² + max_{a<b} n_a n_b)`; `None` if that
/// overflows.
pub fn kernel_block_bytes(sizes: &[usize]) -> Option<usize> {
    let own = sizes
        .iter()
        .try_fold(0usize, |acc, &c| acc.checked_add(c.checked_mul(c)?))?;
    let widest = sizes
        .iter()
        .enumerate()
        .flat_map(|(a, &na)| sizes[a + 1..].iter().map(move |&nb| na.saturating_mul(nb)))
        .max()
        .unwrap_or(0);
    own.checked_add(widest)?.checked_mul(std::mem::size_of::<f64>())
}

/// The RBF kernel block `K_ij = exp(-γ‖x_i − x_j‖²)` between the vectors
/// `rows` and the vectors `cols` of `x` (row-major, `dim` wide), row-major
/// `rows.len() x cols.len()`, each entry with the bits of [`smo::rbf`]
/// (the distances are symmetric bit for bit, so a block and the block of
/// the swapped ranges are each other's transpose). `xt`, `x` transposed
/// (`dim x n`), takes the distances with the vectors across the lanes
/// ([`dense::sq_dists_cols`]); without it, the tiled kernel.
pub fn rbf_block(
    x: &[f64],
    xt: Option<&[f64]>,
    dim: usize,
    rows: std::ops::Range<usize>,
    cols: std::ops::Range<usize>,
    gamma: f64,
) -> Vec<f64> {
    let dim = dim.max(1);
    let n = x.len() / dim;
    let w = cols.len();
    let mut out = vec![0.0; rows.len() * w];
    if out.is_empty() {
        return out;
    }
    let a = &x[rows.start * dim..rows.end * dim];
    match xt {
        Some(xt) => dense::sq_dists_cols(a, xt, dim, n, cols, &mut out),
        None => dense::sq_dists_strided(a, &x[cols.start * dim..cols.end * dim], dim, &mut out, w),
    }
    vmath::rbf_in_place(&mut out, gamma);
    out
}

impl SvmConfig {
    /// The feature keys, as the shared plumbing takes them.
    pub fn feature_keys(&self) -> FeatureKeys {
        self.keys()
    }

    fn keys(&self) -> FeatureKeys {
        FeatureKeys {
            frames: self.frames,
            step: self.step,
            stride: self.stride,
            min_spikes: self.min_spikes,
            max_train_frames: self.max_train_frames,
        }
    }

    /// Checks every key, naming the wrong one.
    pub fn check(&self) -> Result<(), ConfigError> {
        let mut c = ConfigChecks::new();
        c.take(self.keys().check());
        c.take(check_positive("c", self.c, ""));
        c.take(check_range("gamma", self.gamma, 0.0, 1e6, ""));
        c.take(check_positive("tol", self.tol, ""));
        if self.max_iter == 0 {
            c.push(ConfigError::key("max_iter", "must be at least 1"));
        }
        if self.cache_mb == 0 || self.cache_mb > 1 << 20 {
            c.push(ConfigError::key("cache_mb", "must be in 1..=1048576 (MiB)"));
        }
        c.finish()
    }

    /// Fits the one-vs-one SVM on a fold's training trials.
    pub fn fit_model(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<FittedModel, StageError> {
        self.check()?;
        let set = TrainSet::build(train, &self.keys())?;
        self.fit_set(set, &mut ctx.rng())
    }

    /// Fits on prepared training vectors (what [`Self::fit_model`] does after
    /// building them from the trials), drawing from `rng` as from the fold's generator.
    pub fn fit_set(&self, set: TrainSet, rng: &mut ChaCha8Rng) -> Result<FittedModel, StageError> {
        self.check()?;
        fit_classic_set(set, self.vote, "svm", rng, |set, d, scaler, _seed| {
            let rows: Vec<Vec<f64>> = d.flat.chunks_exact(set.dim.max(1)).map(<[f64]>::to_vec).collect();
            self.fit_design(set.classes.len(), set.dim, &rows, &set.y, scaler)
        })
    }

    /// Fits the one-vs-one machines on standardised rows `rows` with class
    /// indices `y` (`0..k`). Deterministic: SMO draws nothing at random.
    pub fn fit_design(
        &self,
        k: usize,
        dim: usize,
        rows: &[Vec<f64>],
        y: &[usize],
        scaler: Standardizer,
    ) -> Result<Classifier, StageError> {
        let gamma = if self.gamma > 0.0 {
            self.gamma
        } else {
            1.0 / dim.max(1) as f64
        };
        let n = rows.len();
        // The fold's kernel by class blocks when they fit in the cache budget
        // (module docs): every vector takes part in K - 1 pairs, so each
        // kernel value is computed once per fold instead of once per pair.
        // The vectors are sorted by class (stably), so a class is a range
        // of them; each entry's bits do not depend on the thread count.
        let budget = self.cache_mb.saturating_mul(1 << 20);
        let mut by_class: Vec<usize> = (0..n).collect();
        by_class.sort_by_key(|&i| y[i]);
        let mut class_start = vec![0usize; k + 1];
        for &c in y {
            if c < k {
                class_start[c + 1] += 1;
            }
        }
        for c in 0..k {
            class_start[c + 1] += class_start[c];
        }
        // The classes' own kernel blocks, and per machine the block between
        // its two classes (computed when the machine starts, in cache while
        // it reads it): `Σ_c n_c²` values, plus `n_a n_b` per machine in
        // progress (one per thread).
        let sizes: Vec<usize> = class_start.windows(2).map(|w| w[1] - w[0]).collect();
        let block_bytes = kernel_block_bytes(&sizes);
        // (The vectors sorted by class, their transpose, the classes' blocks.)
        type Blocks = (Vec<f64>, Option<Vec<f64>>, Vec<Vec<f64>>);
        let gram: Option<Blocks> = block_bytes
            .filter(|&bytes| bytes <= budget && class_start[k] == n)
            .map(|_| {
                let sorted: Vec<f64> = by_class.iter().flat_map(|&i| rows[i].iter().copied()).collect();
                let xt = crate::wide::avx512().then(|| {
                    let mut xt = vec![0.0; n * dim];
                    dense::transpose(&sorted, n, dim, &mut xt);
                    xt
                });
                let own = (0..k)
                    .into_par_iter()
                    .map(|c| {
                        let r = class_start[c]..class_start[c + 1];
                        rbf_block(&sorted, xt.as_deref(), dim, r.clone(), r, gamma)
                    })
                    .collect();
                (sorted, xt, own)
            });
        let pairs: Vec<(usize, usize)> = (0..k).flat_map(|a| (a + 1..k).map(move |b| (a, b))).collect();
        let params = smo::SmoParams {
            c: self.c,
            tol: self.tol,
            max_iter: self.max_iter,
            cache_bytes: budget,
            shrinking: self.shrinking,
        };
        // Each pair's machine: (class a, class b, training rows used, coefficients, bias).
        type Raw = (usize, usize, Vec<usize>, Vec<f64>, f64, bool);
        let machines: Vec<Raw> = pairs
            .par_iter()
            .map(|&(a, b)| {
                // The machine's variables: its two classes' rows in row order.
                let idx: Vec<usize> = (0..n).filter(|&i| y[i] == a || y[i] == b).collect();
                // Class b is the positive side (libsvm puts the first class there;
                // only the sign convention differs).
                let lab: Vec<f64> = idx.iter().map(|&i| if y[i] == b { 1.0 } else { -1.0 }).collect();
                let sol = match &gram {
                    Some((sorted, xt, own)) => {
                        // Positions: class a's vectors in sorted order, then
                        // class b's; `var` numbers them as `idx` does.
                        let ranges = [
                            class_start[a]..class_start[a + 1],
                            class_start[b]..class_start[b + 1],
                        ];
                        let var: Vec<usize> = ranges
                            .iter()
                            .flat_map(Clone::clone)
                            .map(|s| idx.binary_search(&by_class[s]).unwrap_or(usize::MAX))
                            .collect();
                        let [ra, rb] = ranges;
                        let cross = rbf_block(sorted, xt.as_deref(), dim, ra.clone(), rb.clone(), gamma);
                        let kern = smo::PairBlocks::new(&own[a], &own[b], &cross, ra.len(), rb.len());
                        smo::solve_gram(&kern, &lab, &var, &params)
                    }
                    None => smo::solve(
                        &lab,
                        &|s, t| smo::rbf(&rows[idx[s]], &rows[idx[t]], gamma),
                        &params,
                    ),
                };
                let mut sv = Vec::new();
                let mut coef = Vec::new();
                for (s, &al) in sol.alpha.iter().enumerate() {
                    if al > 0.0 {
                        sv.push(idx[s]);
                        coef.push(al * lab[s]);
                    }
                }
                (a, b, sv, coef, -sol.rho, sol.converged)
            })
            .collect();
        // Pool the support vectors: a training row is stored once whatever the
        // number of machines using it, in order of first use (pair order, so
        // the same on any thread count).
        let mut pool: Vec<f64> = Vec::new();
        let mut slot: Vec<Option<u32>> = vec![None; n];
        let mut out = Vec::with_capacity(machines.len());
        for (a, b, sv, coef, bias, converged) in machines {
            if !converged {
                return Err(StageError::new(format!(
                    "svm: the machine for classes {a} and {b} did not reach tol = {} within max_iter = {} \
                     iterations (raise `max_iter` or `tol`)",
                    self.tol, self.max_iter
                )));
            }
            let sv_index = sv
                .iter()
                .map(|&r| {
                    *slot[r].get_or_insert_with(|| {
                        let next = (pool.len() / dim.max(1)) as u32;
                        pool.extend_from_slice(&rows[r]);
                        next
                    })
                })
                .collect();
            out.push(BinarySvm {
                a,
                b,
                sv_index,
                coef,
                bias,
            });
        }
        Ok(Box::new(OvoSvm {
            dim,
            classes: k,
            gamma,
            scaler,
            sv: pool,
            machines: out,
        }))
    }
}

super::features::trained_baseline_stage!("svm", SvmConfig);

// ---------------------------------------------------------------- random forest

/// Random forest (CART trees, Gini, bootstrap) on spike-image features, winner-take-all over the trial.
///
/// Each active frame votes for its predicted class. Input: spike images; output:
/// orientation estimates.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct RandomForestConfig {
    /// Images stacked per vector (1 = spatial). Default 5.
    pub frames: usize,
    /// Frames between stacked images; 0 = one window. Default 0.
    pub step: usize,
    /// Frames between the frames a trial contributes; 0 = one window. Default 0.
    pub stride: usize,
    /// Smallest spike total of a used vector. Default 1.
    pub min_spikes: f64,
    /// Most vectors a training trial contributes (evenly spaced). Default 15.
    pub max_train_frames: usize,
    /// Trees. Default 15.
    pub n_trees: u16,
    /// Largest tree depth; 0 = unlimited. Default 0.
    pub max_depth: u16,
    /// Fewest vectors in a leaf. Default 1.
    pub min_samples_leaf: usize,
    /// Features tried per split; 0 = auto (sqrt of the vector length). Default 0.
    pub m: usize,
    /// `winner` (paper) or `sum`. Default `winner`.
    pub vote: Vote,
    /// Write each fold's fitted model to `<out>/<stage id>.fold<f>.model.json`. Default false.
    pub save_model: bool,
    /// A model saved by an offline run of this stage type (`save_model =
    /// true`), JSON, relative to the graph file. With it the stage does not
    /// fit: it predicts every trial with the loaded model (no folds or
    /// training trials) and streams under `palpate run --live`; the feature
    /// and training keys are then unused (the model keeps its own). Default
    /// none: fit per fold.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model_in: Option<String>,
}

impl Default for RandomForestConfig {
    fn default() -> Self {
        RandomForestConfig {
            frames: 5,
            step: 0,
            stride: 0,
            min_spikes: 1.0,
            max_train_frames: 15,
            n_trees: 15,
            max_depth: 0,
            min_samples_leaf: 1,
            m: 0,
            vote: Vote::Winner,
            save_model: false,
            model_in: None,
        }
    }
}

/// A fitted random forest (trees grown by [`forest`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Forest {
    /// Number of classes.
    pub classes: usize,
    /// Input size.
    pub dim: usize,
    /// Input standardisation.
    pub scaler: Standardizer,
    /// The trees.
    pub trees: Vec<forest::Tree>,
    /// The trees laid out for prediction (built on first use, not saved).
    #[serde(skip)]
    flat: forest::FlatCache,
}

impl Forest {
    /// One vote (score 1) for the forest's class: the class most trees
    /// predict (ties: the lower class index).
    pub fn frame_scores(&self, x: &[f64], out: &mut [f64]) {
        self.scores_batch(x, out);
    }

    /// [`Self::frame_scores`] of every row of `x` into the rows of `out`.
    ///
    /// Rows go a block at a time: the block is standardised into a small
    /// buffer (no copy of the whole batch), then walked down all the trees
    /// together ([`forest::Flat::vote`]), tallying the votes per row; the
    /// same votes, hence the same scores, as one row through every tree.
    pub fn scores_batch(&self, x: &[f64], out: &mut [f64]) {
        /// Rows standardised and voted together.
        const ROWS: usize = 64;
        let k = self.classes.max(1);
        let dim = self.dim.max(1);
        let flat = self.flat.get(&self.trees, dim);
        let rows = (x.len() / dim).min(out.len() / k);
        let mut z = vec![0.0; ROWS * dim];
        let mut votes = vec![0u32; ROWS * k];
        for start in (0..rows).step_by(ROWS) {
            let b = ROWS.min(rows - start);
            let z = &mut z[..b * dim];
            z.copy_from_slice(&x[start * dim..(start + b) * dim]);
            z.chunks_exact_mut(dim).for_each(|r| self.scaler.apply(r));
            let votes = &mut votes[..b * k];
            votes.iter_mut().for_each(|v| *v = 0);
            flat.vote(z, k, votes);
            for (v, o) in votes
                .chunks_exact(k)
                .zip(out[start * k..(start + b) * k].chunks_exact_mut(k))
            {
                let mut best = 0;
                for (c, &n) in v.iter().enumerate() {
                    if n > v[best] {
                        best = c;
                    }
                }
                o.iter_mut().for_each(|o| *o = 0.0);
                if !self.trees.is_empty() {
                    o[best] = 1.0;
                }
            }
        }
    }
}

impl RandomForestConfig {
    /// The feature keys, as the shared plumbing takes them.
    pub fn feature_keys(&self) -> FeatureKeys {
        self.keys()
    }

    fn keys(&self) -> FeatureKeys {
        FeatureKeys {
            frames: self.frames,
            step: self.step,
            stride: self.stride,
            min_spikes: self.min_spikes,
            max_train_frames: self.max_train_frames,
        }
    }

    /// Checks every key, naming the wrong one.
    pub fn check(&self) -> Result<(), ConfigError> {
        let mut c = ConfigChecks::new();
        c.take(self.keys().check());
        if self.n_trees == 0 {
            c.push(ConfigError::key("n_trees", "must be at least 1"));
        }
        if self.min_samples_leaf == 0 {
            c.push(ConfigError::key("min_samples_leaf", "must be at least 1"));
        }
        c.finish()
    }

    /// Fits the forest on a fold's training trials.
    pub fn fit_model(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<FittedModel, StageError> {
        self.check()?;
        let set = TrainSet::build(train, &self.keys())?;
        self.fit_set(set, &mut ctx.rng())
    }

    /// Fits on prepared training vectors (what [`Self::fit_model`] does after
    /// building them from the trials), drawing from `rng` as from the fold's generator.
    pub fn fit_set(&self, set: TrainSet, rng: &mut ChaCha8Rng) -> Result<FittedModel, StageError> {
        self.check()?;
        fit_classic_set(set, self.vote, "random_forest", rng, |set, d, scaler, seed| {
            let g = forest::Growth {
                m: if self.m > 0 {
                    self.m.min(set.dim)
                } else {
                    ((set.dim as f64).sqrt() as usize).max(1)
                },
                max_depth: usize::from(self.max_depth),
                min_samples_leaf: self.min_samples_leaf,
            };
            let k = set.classes.len();
            // The rows as per-feature ranks, once for all trees.
            let rows = forest::Prepared::new(&d.flat, &set.y, set.dim, k);
            // Each tree from its own generator: the same forest on any thread count.
            let trees = (0..usize::from(self.n_trees))
                .into_par_iter()
                .map(|t| forest::grow_prepared(&rows, &g, &mut forest::tree_rng(seed, t)))
                .collect();
            Ok(Box::new(Forest {
                classes: k,
                dim: set.dim,
                scaler,
                trees,
                flat: Default::default(),
            }))
        })
    }
}

super::features::trained_baseline_stage!("random_forest", RandomForestConfig);

// ---------------------------------------------------------------- k-NN

/// How the k nearest neighbours are weighted.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum KnnWeight {
    /// Every neighbour counts the same.
    Uniform,
    /// Neighbours count by inverse distance.
    Distance,
}

/// k nearest neighbours (exact, Euclidean) on spike-image features, winner-take-all over the trial.
///
/// Class scores per frame are the neighbours' shares. Input: spike images; output:
/// orientation estimates.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct KnnConfig {
    /// Images stacked per vector (1 = spatial). Default 5.
    pub frames: usize,
    /// Frames between stacked images; 0 = one window. Default 0.
    pub step: usize,
    /// Frames between the frames a trial contributes; 0 = one window. Default 0.
    pub stride: usize,
    /// Smallest spike total of a used vector. Default 1.
    pub min_spikes: f64,
    /// Most vectors a training trial contributes (evenly spaced). Default 20.
    pub max_train_frames: usize,
    /// Neighbours. Default 10. Capped at the training vectors a fold has (a
    /// larger `k` votes over all of them).
    pub k: usize,
    /// `uniform` or `distance`. Default `uniform`.
    pub weight: KnnWeight,
    /// `winner` (paper) or `sum`. Default `winner`.
    pub vote: Vote,
    /// Write each fold's fitted model to `<out>/<stage id>.fold<f>.model.json`. Default false.
    pub save_model: bool,
    /// A model saved by an offline run of this stage type (`save_model =
    /// true`), JSON, relative to the graph file. With it the stage does not
    /// fit: it predicts every trial with the loaded model (no folds or
    /// training trials) and streams under `palpate run --live`; the feature
    /// and training keys are then unused (the model keeps its own). Default
    /// none: fit per fold.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model_in: Option<String>,
}

impl Default for KnnConfig {
    fn default() -> Self {
        KnnConfig {
            frames: 5,
            step: 0,
            stride: 0,
            min_spikes: 1.0,
            max_train_frames: 20,
            k: 10,
            weight: KnnWeight::Uniform,
            vote: Vote::Winner,
            save_model: false,
            model_in: None,
        }
    }
}

/// A fitted k-NN classifier: the standardised training vectors and their classes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Knn {
    /// Number of classes.
    pub classes: usize,
    /// Input size.
    pub dim: usize,
    /// Neighbours.
    pub k: usize,
    /// Neighbour weighting.
    pub weight: KnnWeight,
    /// Input standardisation.
    pub scaler: Standardizer,
    /// Standardised training vectors, row-major.
    pub x: Vec<f64>,
    /// Their class indices.
    pub y: Vec<usize>,
    /// The `f32` scan of `x` ([`knn_scan`]), built on the first
    /// prediction and not saved, so a saved model loads as
    /// before; `x` and `dim` must not change once it is built.
    #[serde(skip)]
    scan: knn_scan::ScanCell,
}

impl Knn {
    /// A model over standardised training rows `x` with classes `y`.
    pub fn new(
        classes: usize,
        dim: usize,
        k: usize,
        weight: KnnWeight,
        scaler: Standardizer,
        x: Vec<f64>,
        y: Vec<usize>,
    ) -> Knn {
        Knn {
            classes,
            dim,
            k,
            weight,
            scaler,
            x,
            y,
            scan: Default::default(),
        }
    }

    /// The scan (built on the first call), `None` when the rows are not
    /// searched through one (empty, zero-width, not finite or too large).
    fn scan(&self) -> Option<&knn_scan::Scan> {
        if self.dim == 0 || self.x.len() != self.y.len() * self.dim {
            return None;
        }
        self.scan.get(&self.x, self.dim)
    }

    /// The `k` nearest training vectors of standardised `z` as (squared
    /// distance, index), nearest first; ties go to the lower index, so the
    /// answer does not depend on evaluation order.
    pub fn neighbours(&self, z: &[f64]) -> Vec<(f64, usize)> {
        let mut best = Vec::with_capacity(self.k.min(self.y.len()) + 1);
        self.neighbours_into(z, &mut best);
        best
    }

    /// [`Self::neighbours`] into a reused buffer.
    #[inline]
    fn neighbours_into(&self, z: &[f64], best: &mut Vec<(f64, usize)>) {
        let k = self.k.min(self.y.len());
        best.clear();
        for (i, row) in self.x.chunks_exact(self.dim.max(1)).enumerate() {
            knn_scan::offer(best, k, sq_dist(row, z), i);
        }
    }

    /// Neighbour shares per class (weighted by `1 / distance` in `distance`
    /// mode; neighbours at distance 0, if any, share all the weight).
    pub fn frame_scores(&self, x: &[f64], out: &mut [f64]) {
        self.scores_batch(x, out);
    }

    /// [`Self::frame_scores`] of every row of `x` into the rows of `out`,
    /// with the neighbours of [`Self::neighbours`] found through the `f32`
    /// scan ([`knn_scan`]) when there is one, else by `Self::scores_full`.
    pub fn scores_batch(&self, x: &[f64], out: &mut [f64]) {
        let dim = self.dim.max(1);
        let kc = self.classes.max(1);
        let z = self.scaler.apply_rows(x);
        let n = (z.len() / dim).min(out.len() / kc);
        match self.scan() {
            Some(scan) => scan.search(&self.x, &z[..n * dim], self.k, |q, best| {
                self.shares(best, &mut out[q * kc..(q + 1) * kc]);
            }),
            None => self.scores_full(&z[..n * dim], out),
        }
    }

    /// The full scan of the standardised rows `z`:
    ///
    /// 1. for a block of `QB` queries, every dot product with the training
    ///    vectors in one tiled product ([`dense::gemm_nt`]), giving the
    ///    distances `d̃² = ‖a‖² + ‖b‖² − 2 a·b` (two flops per term
    ///    instead of three);
    /// 2. `τ`, the `k`-th smallest `d̃²` of the query;
    /// 3. the exact [`sq_dist`] of the candidates with `d̃² ≤ τ + 2δ` only,
    ///    offered in training order as the full scan offers them.
    ///
    /// `δ = (8·dim + 32)·ε·(‖a‖² + max ‖b‖²)` bounds the rounding of `d̃²`
    /// against the computed exact distance (each dot product of `dim` terms
    /// errs by at most `dim·ε·‖a‖‖b‖`), so every vector whose exact distance
    /// is within the `k` smallest is a candidate: the neighbours, their
    /// order and their ties are exactly those of the full exact scan.
    fn scores_full(&self, z: &[f64], out: &mut [f64]) {
        const QB: usize = 16;
        let dim = self.dim.max(1);
        let k = self.k.min(self.y.len());
        let kc = self.classes.max(1);
        let n = z.len() / dim;
        let n_train = self.x.len() / dim;

        let norms: Vec<f64> = self.x.chunks_exact(dim).map(|r| dense::dot(r, r)).collect();
        let norm_max = norms.iter().copied().fold(0.0, f64::max);
        let mut g = vec![0.0; QB * n_train];
        let mut kth: Vec<f64> = Vec::with_capacity(k + 1);
        let mut best: Vec<(f64, usize)> = Vec::with_capacity(k + 1);
        for q0 in (0..n).step_by(QB) {
            let qb = QB.min(n - q0);
            let zq = &z[q0 * dim..(q0 + qb) * dim];
            dense::gemm_nt(zq, &self.x, dim, &mut g[..qb * n_train]);
            for (q, (a, row)) in zq
                .chunks_exact(dim)
                .zip(g.chunks_exact_mut(n_train.max(1)))
                .enumerate()
            {
                let an = dense::dot(a, a);
                // Approximate distances, and the k-th smallest of them.
                kth.clear();
                for (v, &bn) in row.iter_mut().zip(&norms) {
                    *v = an + bn - 2.0 * *v;
                    if kth.len() < k || *v < kth[k - 1] {
                        let pos = kth.partition_point(|&d| d <= *v);
                        kth.insert(pos, *v);
                        kth.truncate(k);
                    }
                }
                best.clear();
                if let Some(&tau) = kth.last() {
                    let delta = (8.0 * dim as f64 + 32.0) * f64::EPSILON * (an + norm_max);
                    let cut = tau + 2.0 * delta;
                    for (j, &v) in row.iter().enumerate() {
                        if v <= cut {
                            knn_scan::offer(&mut best, k, sq_dist(a, &self.x[j * dim..(j + 1) * dim]), j);
                        }
                    }
                }
                self.shares(&best, &mut out[(q0 + q) * kc..(q0 + q + 1) * kc]);
            }
        }
    }

    fn shares(&self, nb: &[(f64, usize)], out: &mut [f64]) {
        out.iter_mut().for_each(|o| *o = 0.0);
        let exact = nb.iter().any(|&(d, _)| d == 0.0);
        let mut total = 0.0;
        for &(d2, i) in nb {
            let w = match self.weight {
                KnnWeight::Uniform => 1.0,
                KnnWeight::Distance if exact => f64::from(u8::from(d2 == 0.0)),
                KnnWeight::Distance => 1.0 / d2.sqrt(),
            };
            if let Some(o) = out.get_mut(self.y[i]) {
                *o += w;
                total += w;
            }
        }
        if total > 0.0 && total.is_finite() {
            out.iter_mut().for_each(|o| *o /= total);
        } else {
            out.iter_mut().for_each(|o| *o = 0.0);
        }
    }
}

impl KnnConfig {
    /// The feature keys, as the shared plumbing takes them.
    pub fn feature_keys(&self) -> FeatureKeys {
        self.keys()
    }

    fn keys(&self) -> FeatureKeys {
        FeatureKeys {
            frames: self.frames,
            step: self.step,
            stride: self.stride,
            min_spikes: self.min_spikes,
            max_train_frames: self.max_train_frames,
        }
    }

    /// Checks every key, naming the wrong one.
    pub fn check(&self) -> Result<(), ConfigError> {
        let mut c = ConfigChecks::new();
        c.take(self.keys().check());
        if self.k == 0 {
            c.push(ConfigError::key("k", "must be at least 1"));
        }
        c.finish()
    }

    /// Fits k-NN on a fold's training trials (`k` is capped at the vectors available).
    pub fn fit_model(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<FittedModel, StageError> {
        self.check()?;
        let set = TrainSet::build(train, &self.keys())?;
        self.fit_set(set, &mut ctx.rng())
    }

    /// Fits on prepared training vectors (what [`Self::fit_model`] does after
    /// building them from the trials), drawing from `rng` as from the fold's generator.
    pub fn fit_set(&self, set: TrainSet, rng: &mut ChaCha8Rng) -> Result<FittedModel, StageError> {
        self.check()?;
        fit_classic_set(set, self.vote, "knn", rng, |set, d, scaler, _| {
            let knn = Knn::new(
                set.classes.len(),
                set.dim,
                self.k.min(set.len()),
                self.weight,
                scaler,
                d.flat,
                set.y.clone(),
            );
            // The `f32` scan is built at the first prediction (as for a
            // loaded model), so fitting stays a copy of the training set.
            Ok(Box::new(knn))
        })
    }
}

super::features::trained_baseline_stage!("knn", KnnConfig);

// ---------------------------------------------------------------- logistic

/// Multinomial logistic regression (L-BFGS) on spike-image features, winner-take-all over the trial.
///
/// Class scores per frame are softmax probabilities. Input: spike images; output:
/// orientation estimates.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct LogisticConfig {
    /// Images stacked per vector (1 = spatial). Default 1 (see the module docs).
    pub frames: usize,
    /// Frames between stacked images; 0 = one window. Default 0.
    pub step: usize,
    /// Frames between the frames a trial contributes; 0 = one window. Default 0.
    pub stride: usize,
    /// Smallest spike total of a used vector. Default 1.
    pub min_spikes: f64,
    /// Most vectors a training trial contributes (evenly spaced). Default 20.
    pub max_train_frames: usize,
    /// L2 penalty on the coefficients (not the intercepts), added as
    /// `alpha/2 · ‖W‖²` to the summed log loss (scikit-learn's `C = 1/alpha`). Default 1.
    pub alpha: f64,
    /// L-BFGS stopping tolerance: largest gradient component of the mean
    /// objective (scikit-learn's `tol`). Default 1e-4.
    pub tol: f64,
    /// Most L-BFGS iterations (scikit-learn's `max_iter`). Default 1000.
    pub max_iter: usize,
    /// `winner` (paper) or `sum`. Default `winner`.
    pub vote: Vote,
    /// Write each fold's fitted model to `<out>/<stage id>.fold<f>.model.json`. Default false.
    pub save_model: bool,
    /// A model saved by an offline run of this stage type (`save_model =
    /// true`), JSON, relative to the graph file. With it the stage does not
    /// fit: it predicts every trial with the loaded model (no folds or
    /// training trials) and streams under `palpate run --live`; the feature
    /// and training keys are then unused (the model keeps its own). Default
    /// none: fit per fold.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model_in: Option<String>,
}

impl Default for LogisticConfig {
    fn default() -> Self {
        LogisticConfig {
            frames: 1,
            step: 0,
            stride: 0,
            min_spikes: 1.0,
            max_train_frames: 20,
            alpha: 1.0,
            tol: 1e-4,
            max_iter: 1000,
            vote: Vote::Winner,
            save_model: false,
            model_in: None,
        }
    }
}

/// A fitted multinomial logistic regression: `p = softmax(W x + b)`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Softmax {
    /// Input size.
    pub dim: usize,
    /// Number of classes.
    pub classes: usize,
    /// `W`, classes x dim, row-major.
    pub w: Vec<f64>,
    /// `b`, one per class.
    pub b: Vec<f64>,
    /// Input standardisation.
    pub scaler: Standardizer,
}

impl Softmax {
    /// Class probabilities.
    pub fn frame_scores(&self, x: &[f64], out: &mut [f64]) {
        self.scores_batch(x, out);
    }

    /// [`Self::frame_scores`] of every row of `x` into the rows of `out`: the
    /// rows standardised, then all logits in one tiled product
    /// ([`dense::gemm_nt`], the bits of a row-by-row dot product).
    pub fn scores_batch(&self, x: &[f64], out: &mut [f64]) {
        let z = self.scaler.apply_rows(x);
        let k = self.classes.max(1);
        let n = (z.len() / self.dim.max(1)).min(out.len() / k);
        let out = &mut out[..n * k];
        dense::gemm_nt(&z[..n * self.dim], &self.w, self.dim, out);
        for o in out.chunks_exact_mut(k) {
            o.iter_mut().zip(&self.b).for_each(|(o, b)| *o += b);
        }
        vmath::softmax_rows(out, k);
    }
}

/// Fits multinomial logistic regression on standardised rows `x` (row-major,
/// `dim` wide) with classes `y` in `0..k`: minimises the mean objective
/// `(1/n) [Σ_i −log softmax(W x_i + b)_{y_i} + alpha/2 ‖W‖²]` (scikit-learn's,
/// with `C = 1/alpha`; the intercepts are not penalised) by [`lbfgs`] from
/// zero, stopping at `max |∇| ≤ tol` as scikit-learn's `lbfgs` solver.
/// Returns `(W, b)`, `W` `k x dim` row-major.
///
/// Each evaluation is two products: the logits class by class, `Z = W Xᵀ`
/// ([`dense::gemm_nn`] on `Xᵀ`, formed once), and the gradient `Rᵀ X`
/// ([`dense::gemm_nn`] on `X`) of the residuals `R = P − Y`; without
/// AVX-512, [`dense::gemm_nt`] on the operands as they are for the
/// gradient (`Rᵀ` against the rows of `Xᵀ`; AVX2's `gemm_nn` kernel is
/// slower at its shape), and for the logits too (`W` against the rows of
/// `X`) on a CPU without AVX2, where `gemm_nn` would copy them into that
/// form.
/// Both hold a class's values for every row contiguously, so the softmax
/// between them runs with the rows across the vector lanes, each row's
/// operations those of the row-by-row definition in the same order (its
/// running maximum and sum over the classes in class order, the loss and
/// the bias gradients summed in row order): the same bits, which the test
/// `logistic_fit_has_the_bits_of_the_row_by_row_evaluation` checks. Row by
/// row (before 2026-11-28) the per-row loops over 17 classes were scalar
/// and took ~40 % of a fit (perf on the peers logistic fit).
fn fit_softmax(
    x: &[f64],
    y: &[usize],
    dim: usize,
    k: usize,
    alpha: f64,
    tol: f64,
    max_iter: usize,
) -> (Vec<f64>, Vec<f64>) {
    let n = y.len();
    let inv_n = 1.0 / n.max(1) as f64;
    let mut xt = vec![0.0; dim * n];
    dense::transpose(&x[..n * dim], n, dim, &mut xt);
    // Class-major: `zt[c·n + i]` is row `i`'s logit (then exponential) of
    // class `c`, `rt` its residual.
    let mut zt = vec![0.0; k * n];
    let mut rt = vec![0.0; k * n];
    // Per row: the largest logit, the true class's logit, the sum of the
    // exponentials.
    let (mut mx, mut zy, mut sum) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    let nw = k * dim;
    // Where `gemm_nn` has no vector kernel it would copy its operands into
    // `gemm_nt`'s form, so `gemm_nt` takes them as they are: `dot(w_c,
    // x_i)` and `dot(r_c, xᵀ_j)`, the same bits (a fused term is symmetric
    // in its factors). With AVX2 alone, `gemm_nn` for the logits (17 x 16
    // against 16 x 3060: 75 against 160 us for `gemm_nt`'s tiles) but not
    // for the gradient (17 x 3060 against 3060 x 16, whose 16 columns it
    // reads once per three classes: 100-115 against 70 us); best of 1000
    // calls, throwaway timing on an AVX2-only host, 2026-12-02.
    let z_nn = crate::wide::avx2();
    let g_nn = crate::wide::avx512();
    let fg = |theta: &[f64], g: &mut [f64]| -> f64 {
        let (w, b) = theta.split_at(nw);
        if n == 0 {
            // No rows (the slices below are chunked by `n`): the penalty alone.
            let (gw, gb) = g.split_at_mut(nw);
            gw.iter_mut().zip(w).for_each(|(g, w)| *g = alpha * inv_n * w);
            gb.iter_mut().for_each(|g| *g = 0.0);
            return 0.5 * alpha * w.iter().map(|w| w * w).sum::<f64>() * inv_n;
        }
        if dim == 0 {
            zt.iter_mut().for_each(|z| *z = 0.0);
        } else if z_nn {
            dense::gemm_nn(dense::View::rows_of(w, k, dim), &xt, n, &mut zt);
        } else {
            dense::gemm_nt(w, &x[..n * dim], dim, &mut zt);
        }
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                mx.iter_mut().for_each(|m| *m = f64::NEG_INFINITY);
                for (zc, &bc) in zt.chunks_exact_mut(n).zip(b) {
                    // `f64::max` of the row-by-row code: a NaN logit never
                    // wins, and the sign of a zero maximum cannot reach the
                    // results (`z − m` and `m + ln Σ` are then the same).
                    for (z, m) in zc.iter_mut().zip(mx.iter_mut()) {
                        *z += bc;
                        *m = if *z > *m { *z } else { *m };
                    }
                }
                for (i, (zy, &yi)) in zy.iter_mut().zip(y).enumerate() {
                    *zy = zt[yi * n + i];
                }
                for zc in zt.chunks_exact_mut(n) {
                    zc.iter_mut().zip(&mx).for_each(|(z, m)| *z -= m);
                }
            },
        );
        vmath::exp_in_place(&mut zt);
        let (gw, gb) = g.split_at_mut(nw);
        let mut loss = 0.0;
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                sum.iter_mut().for_each(|s| *s = 0.0);
                for zc in zt.chunks_exact(n) {
                    sum.iter_mut().zip(zc).for_each(|(s, e)| *s += e);
                }
                for ((&m, &s), &zy) in mx.iter().zip(&sum).zip(&zy) {
                    loss += m + s.ln() - zy;
                }
                // From here `sum` holds `1 / Σ`.
                sum.iter_mut().for_each(|s| *s = 1.0 / *s);
                for (c, (rc, zc)) in rt.chunks_exact_mut(n).zip(zt.chunks_exact(n)).enumerate() {
                    for (((r, &e), &inv), &yi) in rc.iter_mut().zip(zc).zip(&sum).zip(y) {
                        *r = (e * inv - f64::from(u8::from(c == yi))) * inv_n;
                    }
                }
                // The bias gradients `Σ_i rt[c][i]` in row order from -0.0
                // (as `Iterator::sum`), the classes' chains interleaved.
                gb.iter_mut().for_each(|g| *g = -0.0);
                for i0 in (0..n).step_by(8) {
                    let i1 = (i0 + 8).min(n);
                    for (gb, rc) in gb.iter_mut().zip(rt.chunks_exact(n)) {
                        rc[i0..i1].iter().for_each(|r| *gb += r);
                    }
                }
            },
        );
        if dim > 0 && g_nn {
            dense::gemm_nn(dense::View::rows_of(&rt, k, n), x, dim, gw);
        } else if dim > 0 {
            dense::gemm_nt(&rt, &xt, n, gw);
        }
        let mut sq = 0.0;
        for (gw, w) in gw.iter_mut().zip(w) {
            *gw += alpha * inv_n * w;
            sq += w * w;
        }
        (loss + 0.5 * alpha * sq) * inv_n
    };
    let params = lbfgs::Params {
        memory: 10,
        gtol: tol,
        // scipy's L-BFGS-B as scikit-learn sets it (64 machine epsilons).
        ftol: 64.0 * f64::EPSILON,
        max_iter,
        max_line_search: 50,
    };
    let out = lbfgs::minimize(vec![0.0; nw + k], fg, &params);
    let mut theta = out.x;
    let b = theta.split_off(nw);
    (theta, b)
}

impl LogisticConfig {
    /// The feature keys, as the shared plumbing takes them.
    pub fn feature_keys(&self) -> FeatureKeys {
        self.keys()
    }

    fn keys(&self) -> FeatureKeys {
        FeatureKeys {
            frames: self.frames,
            step: self.step,
            stride: self.stride,
            min_spikes: self.min_spikes,
            max_train_frames: self.max_train_frames,
        }
    }

    /// Checks every key, naming the wrong one.
    pub fn check(&self) -> Result<(), ConfigError> {
        let mut c = ConfigChecks::new();
        c.take(self.keys().check());
        c.take(check_range("alpha", self.alpha, 0.0, 1e9, ""));
        c.take(check_positive("tol", self.tol, ""));
        if self.max_iter == 0 {
            c.push(ConfigError::key("max_iter", "must be at least 1"));
        }
        c.finish()
    }

    /// Fits logistic regression on a fold's training trials.
    pub fn fit_model(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<FittedModel, StageError> {
        self.check()?;
        let set = TrainSet::build(train, &self.keys())?;
        self.fit_set(set, &mut ctx.rng())
    }

    /// Fits on prepared training vectors (what [`Self::fit_model`] does after
    /// building them from the trials), drawing from `rng` as from the fold's generator.
    pub fn fit_set(&self, set: TrainSet, rng: &mut ChaCha8Rng) -> Result<FittedModel, StageError> {
        self.check()?;
        fit_classic_set(set, self.vote, "logistic", rng, |set, d, scaler, _| {
            let k = set.classes.len();
            let (w, b) = fit_softmax(&d.flat, &set.y, set.dim, k, self.alpha, self.tol, self.max_iter);
            if w.iter().chain(&b).any(|v| !v.is_finite()) {
                return Err(StageError::new(
                    "logistic regression diverged (non-finite coefficients); raise `alpha`",
                ));
            }
            Ok(Box::new(Softmax {
                dim: set.dim,
                classes: k,
                w,
                b,
                scaler,
            }))
        })
    }
}

super::features::trained_baseline_stage!("logistic", LogisticConfig);

#[typetag::serde(name = "svm")]
impl FrameClassifier for OvoSvm {
    fn frame_scores(&self, x: &[f64], _rng: &mut ChaCha8Rng, out: &mut [f64]) {
        OvoSvm::frame_scores(self, x, out)
    }

    fn scores_batch(&self, x: &[f64], _dim: usize, _classes: usize, _rng: &mut ChaCha8Rng, out: &mut [f64]) {
        OvoSvm::scores_batch(self, x, out)
    }

    fn kind(&self) -> &'static str {
        "svm"
    }

    fn check_shape(&self, dim: usize, classes: usize) -> Result<(), String> {
        let m = self;
        want("the SVM's input size", m.dim, dim)?;
        want("the SVM's classes", m.classes, classes)?;
        check_scaler(&m.scaler, dim)?;
        if dim == 0 || !m.sv.len().is_multiple_of(dim) {
            return Err(format!(
                "{} support-vector values are not rows of {dim}",
                m.sv.len()
            ));
        }
        let n_sv = m.sv.len() / dim;
        for (i, b) in m.machines.iter().enumerate() {
            if b.a >= classes || b.b >= classes {
                return Err(format!("machine {i} names class {} / {} of {classes}", b.a, b.b));
            }
            want(
                &format!("machine {i}'s coefficient count"),
                b.coef.len(),
                b.sv_index.len(),
            )?;
            if let Some(j) = b.sv_index.iter().find(|&&j| j as usize >= n_sv) {
                return Err(format!("machine {i} names support vector {j} of {n_sv}"));
            }
        }
        Ok(())
    }

    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
}

#[typetag::serde(name = "random_forest")]
impl FrameClassifier for Forest {
    fn frame_scores(&self, x: &[f64], _rng: &mut ChaCha8Rng, out: &mut [f64]) {
        Forest::frame_scores(self, x, out)
    }

    fn scores_batch(&self, x: &[f64], _dim: usize, _classes: usize, _rng: &mut ChaCha8Rng, out: &mut [f64]) {
        Forest::scores_batch(self, x, out)
    }

    fn kind(&self) -> &'static str {
        "random_forest"
    }

    fn check_shape(&self, dim: usize, classes: usize) -> Result<(), String> {
        let f = self;
        want("the forest's input size", f.dim, dim)?;
        want("the forest's classes", f.classes, classes)?;
        check_scaler(&f.scaler, dim)?;
        for (t, tree) in f.trees.iter().enumerate() {
            if tree.nodes.is_empty() {
                return Err(format!("tree {t} has no node"));
            }
            for (i, n) in tree.nodes.iter().enumerate() {
                let ok = if n.feature == u32::MAX {
                    (n.left_or_class as usize) < classes
                } else {
                    // Children come after their parent (depth-first),
                    // so a walk from the root always ends.
                    let left = n.left_or_class as usize;
                    (n.feature as usize) < dim && left > i && left + 1 < tree.nodes.len()
                };
                if !ok {
                    return Err(format!(
                        "tree {t}, node {i} points outside the tree, the features or the classes"
                    ));
                }
            }
        }
        Ok(())
    }

    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
}

#[typetag::serde(name = "knn")]
impl FrameClassifier for Knn {
    fn frame_scores(&self, x: &[f64], _rng: &mut ChaCha8Rng, out: &mut [f64]) {
        Knn::frame_scores(self, x, out)
    }

    fn scores_batch(&self, x: &[f64], _dim: usize, _classes: usize, _rng: &mut ChaCha8Rng, out: &mut [f64]) {
        Knn::scores_batch(self, x, out)
    }

    fn kind(&self) -> &'static str {
        "knn"
    }

    fn check_shape(&self, dim: usize, classes: usize) -> Result<(), String> {
        let m = self;
        want("k-NN's input size", m.dim, dim)?;
        want("k-NN's classes", m.classes, classes)?;
        check_scaler(&m.scaler, dim)?;
        if m.k == 0 {
            return Err("k-NN's k is 0".into());
        }
        let n = m.y.len().checked_mul(dim).ok_or("k-NN's size overflows")?;
        want("k-NN's training values", m.x.len(), n)?;
        if let Some(c) = m.y.iter().find(|&&c| c >= classes) {
            return Err(format!("k-NN has a training vector of class {c} of {classes}"));
        }
        Ok(())
    }

    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
}

#[typetag::serde(name = "logistic")]
impl FrameClassifier for Softmax {
    fn frame_scores(&self, x: &[f64], _rng: &mut ChaCha8Rng, out: &mut [f64]) {
        Softmax::frame_scores(self, x, out)
    }

    fn scores_batch(&self, x: &[f64], _dim: usize, _classes: usize, _rng: &mut ChaCha8Rng, out: &mut [f64]) {
        Softmax::scores_batch(self, x, out)
    }

    fn kind(&self) -> &'static str {
        "logistic"
    }

    fn check_shape(&self, dim: usize, classes: usize) -> Result<(), String> {
        let m = self;
        want("the regression's input size", m.dim, dim)?;
        want("the regression's classes", m.classes, classes)?;
        check_scaler(&m.scaler, dim)?;
        let n = classes
            .checked_mul(dim)
            .ok_or("the regression's size overflows")?;
        want("the regression's weight count", m.w.len(), n)?;
        want("the regression's bias count", m.b.len(), classes)
    }

    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn random_rows(n: usize, dim: usize, seed: u64) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        // Coarse values, so exact ties and duplicate rows occur.
        (0..n * dim)
            .map(|_| f64::from(rng.random_range(0u8..4)) * 0.5)
            .collect()
    }

    #[test]
    fn knn_batch_finds_exactly_the_neighbours_of_the_full_scan() {
        let (n, dim, k) = (300, 13, 7);
        let x = random_rows(n, dim, 1);
        let y: Vec<usize> = (0..n).map(|i| i % 5).collect();
        for weight in [KnnWeight::Uniform, KnnWeight::Distance] {
            let knn = Knn::new(
                5,
                dim,
                k,
                weight,
                Standardizer {
                    mean: vec![0.3; dim],
                    inv_sd: vec![1.7; dim],
                },
                x.clone(),
                y.clone(),
            );
            let q = random_rows(37, dim, 2);
            let mut batch = vec![0.0; 37 * 5];
            knn.scores_batch(&q, &mut batch);
            for (row, b) in q.chunks_exact(dim).zip(batch.chunks_exact(5)) {
                let mut z = row.to_vec();
                knn.scaler.apply(&mut z);
                let mut want = vec![0.0; 5];
                knn.shares(&knn.neighbours(&z), &mut want);
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(b), bits(&want));
            }
        }
    }

    #[test]
    fn logistic_fit_reaches_the_optimum_of_the_penalised_loss() {
        let (n, dim, k) = (120, 4, 3);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let x: Vec<f64> = (0..n * dim).map(|_| rng.random_range(-1.0..1.0)).collect();
        let y: Vec<usize> = (0..n)
            .map(|i| {
                let r = &x[i * dim..(i + 1) * dim];
                usize::from(r[0] + 0.3 * r[1] > 0.2) + usize::from(r[2] > 0.5)
            })
            .collect();
        let alpha = 0.5;
        let (w, b) = fit_softmax(&x, &y, dim, k, alpha, 1e-9, 1000);
        // The gradient of Σ loss + alpha/2 |W|² is zero at the optimum.
        let mut gw = vec![0.0; k * dim];
        let mut gb = vec![0.0; k];
        for i in 0..n {
            let r = &x[i * dim..(i + 1) * dim];
            let mut p: Vec<f64> = (0..k)
                .map(|c| dense::dot(&w[c * dim..(c + 1) * dim], r) + b[c])
                .collect();
            vmath::softmax(&mut p);
            for c in 0..k {
                let e = p[c] - f64::from(u8::from(c == y[i]));
                gb[c] += e;
                for j in 0..dim {
                    gw[c * dim + j] += e * r[j];
                }
            }
        }
        for (g, w) in gw.iter_mut().zip(&w) {
            *g += alpha * w;
        }
        let worst = gw.iter().chain(&gb).fold(0.0f64, |m, g| m.max(g.abs()));
        assert!(worst < 1e-6 * n as f64, "largest gradient component {worst}");
        assert!(w.iter().any(|v| v.abs() > 0.1), "learned something");
    }

    #[test]
    fn forest_has_the_same_bits_on_one_and_two_threads() {
        let (n, dim) = (200, 9);
        let x = random_rows(n, dim, 4);
        let y: Vec<usize> = (0..n)
            .map(|i| usize::from(x[i * dim] + x[i * dim + 3] > 1.5))
            .collect();
        let set = TrainSet {
            dim,
            x,
            y,
            classes: vec![10.0, 20.0],
            ..TrainSet::default()
        };
        let cfg = RandomForestConfig {
            n_trees: 6,
            ..RandomForestConfig::default()
        };
        let fit = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool");
            let m = pool.install(|| cfg.fit_set(set.clone(), &mut ChaCha8Rng::seed_from_u64(9)));
            let m = m.expect("fit");
            m.classifier
                .as_any()
                .downcast_ref::<Forest>()
                .expect("a forest")
                .clone()
        };
        let (one, two) = (fit(1), fit(2));
        assert_eq!(one, two);
        assert_eq!(one.trees.len(), 6);
        let acc = (0..n)
            .filter(|&i| {
                let mut o = [0.0; 2];
                one.frame_scores(set.row(i), &mut o);
                o[set.y[i]] == 1.0
            })
            .count();
        assert!(acc > n * 9 / 10, "training accuracy {acc}/{n}");
    }

    /// Every entry of an RBF block is [`smo::rbf`] of its two vectors, bit
    /// for bit, with the vectors across the lanes (`xt`) and with the tiled
    /// kernel: blocks of one range against itself (a class's own block),
    /// against another and against an empty one, sizes around the 16- and
    /// 8-vector panels, a dimension that leaves a tail.
    #[test]
    fn rbf_blocks_equal_the_kernel_bit_for_bit() {
        for (n, dim) in [(1, 3), (31, 5), (40, 4), (77, 9)] {
            let x = random_rows(n, dim, n as u64);
            let mut xt = vec![0.0; n * dim];
            dense::transpose(&x, n, dim, &mut xt);
            let gamma = 0.37;
            let cuts = [0, n / 3, n / 2, n];
            for (r, c) in [
                (0..n, 0..n),
                (cuts[1]..cuts[2], cuts[2]..n),
                (0..cuts[1], cuts[1]..cuts[1]),
            ] {
                for t in [Some(xt.as_slice()), None] {
                    let g = rbf_block(&x, t, dim, r.clone(), c.clone(), gamma);
                    assert_eq!(g.len(), r.len() * c.len());
                    for (i, s) in r.clone().enumerate() {
                        for (j, u) in c.clone().enumerate() {
                            let want =
                                smo::rbf(&x[s * dim..(s + 1) * dim], &x[u * dim..(u + 1) * dim], gamma);
                            let got = g[i * c.len() + j];
                            assert_eq!(
                                got.to_bits(),
                                want.to_bits(),
                                "n {n}, ({s}, {u}), xt {}",
                                t.is_some()
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn svm_gram_and_row_cache_paths_and_thread_counts_give_the_same_model() {
        // 3 classes, 720 vectors: the kernel blocks (over 1.3 MB) are over a
        // 1 MiB budget, so `cache_mb = 1` trains from per-machine row caches.
        let (n, dim) = (720, 6);
        let x = random_rows(n, dim, 8);
        let y: Vec<usize> = (0..n)
            .map(|i| usize::from(x[i * dim] > 0.2) + usize::from(x[i * dim + 1] + 0.5 * x[i * dim + 2] > 0.3))
            .collect();
        let rows: Vec<Vec<f64>> = x.chunks_exact(dim).map(<[f64]>::to_vec).collect();
        // The identity scaling: the fitted rows are the inputs as given.
        let scaler = Standardizer {
            mean: vec![0.0; dim],
            inv_sd: vec![1.0; dim],
        };
        assert!(block_bytes(&y, 3) > 1 << 20, "the blocks must not fit in 1 MiB");
        let fit = |cfg: &SvmConfig, threads: usize| fit_svm_on(cfg, 3, dim, &rows, &y, &scaler, threads);
        let gram = fit(&SvmConfig::default(), 1);
        let small = SvmConfig {
            cache_mb: 1,
            ..SvmConfig::default()
        };
        assert_eq!(gram, fit(&small, 1));
        assert_eq!(gram, fit(&SvmConfig::default(), 2));
        assert_eq!(gram.machines.len(), 3);
        // The batch and one-frame kernels agree with the reference kernel.
        let mut k = Vec::new();
        gram.kernel_row(&rows[5], &mut k);
        for (s, v) in gram.sv.chunks_exact(dim).zip(&k) {
            assert_eq!(v.to_bits(), smo::rbf(s, &rows[5], gram.gamma).to_bits());
        }
        let mut batch = vec![0.0; n * 3];
        gram.scores_batch(&x, &mut batch);
        let mut right = 0;
        for i in 0..n {
            let mut o = [0.0; 3];
            gram.frame_scores(&x[i * dim..(i + 1) * dim], &mut o);
            assert_eq!(o, batch[i * 3..(i + 1) * 3]);
            right += usize::from((0..3).all(|c| o[c] <= o[y[i]]));
        }
        assert!(right > n * 9 / 10, "training accuracy {right}/{n}");
    }

    /// [`kernel_block_bytes`] for labels `y` of `k` classes.
    fn block_bytes(y: &[usize], k: usize) -> usize {
        let mut sizes = vec![0usize; k];
        y.iter().for_each(|&c| sizes[c] += 1);
        kernel_block_bytes(&sizes).unwrap_or(usize::MAX)
    }

    #[test]
    fn kernel_block_bytes_counts_own_and_widest_cross_blocks() {
        // 8 (3² + 1² + 2² + max(3·1, 3·2, 1·2)) = 8 (14 + 6).
        assert_eq!(kernel_block_bytes(&[3, 1, 2]), Some(160));
        assert_eq!(kernel_block_bytes(&[5]), Some(200));
        assert_eq!(kernel_block_bytes(&[]), Some(0));
        assert_eq!(kernel_block_bytes(&[usize::MAX, 1]), None);
    }

    /// Every number of a fitted SVM, as bits (`PartialEq` on `f64` takes
    /// `-0.0 == 0.0`).
    fn svm_bits(m: &OvoSvm) -> Vec<u64> {
        let mut b: Vec<u64> = m.sv.iter().map(|v| v.to_bits()).collect();
        for mc in &m.machines {
            b.extend([mc.a as u64, mc.b as u64, mc.bias.to_bits()]);
            b.extend(mc.sv_index.iter().map(|&i| u64::from(i)));
            b.extend(mc.coef.iter().map(|c| c.to_bits()));
        }
        b
    }

    #[test]
    fn svm_gram_solver_fits_the_model_of_the_per_machine_path_bit_for_bit() {
        // 5 classes in no particular order, 800 vectors of 7 values (a
        // dimension with a tail), coarse values (kernel ties): the block path
        // (class-sorted kernel blocks, `smo::solve_gram`, AVX2 or not, 1 or 2
        // threads) gives the bits of the per-machine path (`cache_mb = 1`:
        // the kernel blocks, over 1 MiB, do not fit, each machine runs
        // `smo::solve` with its own row cache and the scalar kernel).
        let (n, dim) = (800, 7);
        let x = random_rows(n, dim, 11);
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let y: Vec<usize> = (0..n)
            .map(|i| {
                (usize::from(x[i * dim] > 0.7) * 2
                    + usize::from(x[i * dim + 1] > 0.7)
                    + rng.random_range(0..2))
                    % 5
            })
            .collect();
        let rows: Vec<Vec<f64>> = x.chunks_exact(dim).map(<[f64]>::to_vec).collect();
        let scaler = Standardizer {
            mean: vec![0.0; dim],
            inv_sd: vec![1.0; dim],
        };
        assert!(block_bytes(&y, 5) > 1 << 20, "the blocks must not fit in 1 MiB");
        let fit = |cfg: &SvmConfig, threads: usize| fit_svm_on(cfg, 5, dim, &rows, &y, &scaler, threads);
        let per_machine = svm_bits(&fit(
            &SvmConfig {
                cache_mb: 1,
                ..SvmConfig::default()
            },
            1,
        ));
        let gram = fit(&SvmConfig::default(), 1);
        assert_eq!(gram.machines.len(), 10);
        assert!(gram.machines.iter().all(|m| !m.coef.is_empty()));
        assert_eq!(svm_bits(&gram), per_machine);
        assert_eq!(svm_bits(&fit(&SvmConfig::default(), 2)), per_machine);
        let scalar = crate::wide::baseline_only(|| fit(&SvmConfig::default(), 1));
        assert_eq!(svm_bits(&scalar), per_machine);
    }

    /// Mean |error| of each SVM stage over Table 2's front end (lab scene,
    /// 17 angles x 10 trials, 10-fold leave-one-trial-out), seed 1.
    fn lab_svm_mae(stages: &[(&str, usize)]) -> Vec<f64> {
        crate::link();
        let root = concat!(env!("CARGO_MANIFEST_DIR"), "/..");
        let mut g = format!(
            "[run]\nseed = 1\n\
             [stages.scene]\ntype = \"scene\"\nfile = \"{root}/graphs/scenes/lab.toml\"\n\
             [stages.filter]\ntype = \"lowpass\"\ninputs = [\"scene\"]\ncutoff_hz = 10.0\norder = 2\n\
             [stages.norm]\ntype = \"normalize\"\ninputs = [\"filter\"]\nmin_span = 0.1\n\
             [stages.drive]\ntype = \"drive\"\ninputs = [\"norm\"]\nkind = \"fa_i\"\n\
             [stages.enc]\ntype = \"izhikevich\"\ninputs = [\"drive\"]\npreset = \"fa_i\"\n\
             [stages.bins]\ntype = \"bin\"\ninputs = [\"enc\"]\nwindow_ms = 100.0\nhop_ms = 10.0\n"
        );
        for (id, cap) in stages {
            g += &format!("[stages.{id}]\ntype = \"svm\"\ninputs = [\"bins\"]\nmax_train_frames = {cap}\n");
        }
        let graph = palpate_core::load_str(&g, "cliff.toml", "cliff", &palpate_core::LoadOptions::default())
            .expect("graph loads");
        let r = palpate_core::run(
            &graph,
            &palpate_core::RunOptions {
                keep_outputs: true,
                ..Default::default()
            },
        )
        .expect("graph runs");
        stages
            .iter()
            .map(|(id, _)| {
                let items = &r.outputs[*id];
                let err: f64 = items
                    .iter()
                    .map(|it| {
                        let e = it.payload.estimate().expect("estimates");
                        match (e.angle_deg, it.meta.label.angle_deg) {
                            (Some(a), Some(t)) => (a - t).abs(),
                            _ => 90.0,
                        }
                    })
                    .sum();
                err / items.len() as f64
            })
            .collect()
    }

    /// Regression test of the SVM "cliff" (see `features`' training caps):
    /// 5 training vectors per trial gave 37.7° MAE where 8 gave 1.7°. Slow
    /// (the lab scene's 170 trials): `cargo test --release -p palpate-stages
    /// -- --ignored svm_cliff`.
    #[test]
    #[ignore = "slow: simulates the lab scene; run with --release -- --ignored"]
    fn svm_cliff_at_five_vectors_per_trial_is_gone() {
        let mae = lab_svm_mae(&[("s5", 5), ("s8", 8)]);
        assert!(mae[0] < 5.0, "5 vectors per trial: MAE {}°", mae[0]);
        assert!(mae[1] < 5.0, "8 vectors per trial: MAE {}°", mae[1]);
    }

    /// Three Gaussian blobs in 5 dimensions, overlapping a little: rows,
    /// labels.
    fn blobs(n: usize, seed: u64) -> (Vec<f64>, Vec<usize>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let dim = 5;
        let centres = [
            [1.0, 0.0, 0.5, -0.5, 0.0],
            [-1.0, 0.5, 0.0, 0.5, 0.0],
            [0.0, -1.0, -0.5, 0.0, 0.5],
        ];
        let mut x = Vec::with_capacity(n * dim);
        let mut y = Vec::with_capacity(n);
        for i in 0..n {
            let c = i % 3;
            for centre in &centres[c] {
                // A sum of uniforms: close enough to a normal for blobs.
                let noise: f64 = (0..4).map(|_| rng.random_range(-0.5..0.5)).sum::<f64>() * 0.6;
                x.push(centre + noise);
            }
            y.push(c);
        }
        (x, y)
    }

    fn smart_matrix(x: &[f64], dim: usize) -> smartcore::linalg::basic::matrix::DenseMatrix<f64> {
        smartcore::linalg::basic::matrix::DenseMatrix::new(x.len() / dim, dim, x.to_vec(), false)
            .expect("a well-formed matrix")
    }

    /// `cfg`'s SVM fitted on `rows` (classes `y` in `0..classes`) on a pool of
    /// `threads` threads.
    fn fit_svm_on(
        cfg: &SvmConfig,
        classes: usize,
        dim: usize,
        rows: &[Vec<f64>],
        y: &[usize],
        scaler: &Standardizer,
        threads: usize,
    ) -> OvoSvm {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool");
        let m = pool.install(|| cfg.fit_design(classes, dim, rows, y, scaler.clone()));
        m.expect("fit")
            .as_any()
            .downcast_ref::<OvoSvm>()
            .expect("an SVM")
            .clone()
    }

    /// The definition [`fit_softmax`]'s interleaved evaluation must match
    /// bit for bit: one row at a time, the bias gradients summed afterwards
    /// (the code before rows were interleaved).
    fn fit_softmax_by_rows(x: &[f64], y: &[usize], dim: usize, k: usize, alpha: f64) -> (Vec<f64>, Vec<f64>) {
        let n = y.len();
        let inv_n = 1.0 / n as f64;
        let mut xt = vec![0.0; dim * n];
        for i in 0..n {
            for j in 0..dim {
                xt[j * n + i] = x[i * dim + j];
            }
        }
        let (mut z, mut rt, nw) = (vec![0.0; n * k], vec![0.0; k * n], k * dim);
        let mut mz = vec![(0.0, 0.0); n];
        let fg = |theta: &[f64], g: &mut [f64]| -> f64 {
            let (w, b) = theta.split_at(nw);
            dense::gemm_nt(x, w, dim, &mut z);
            for ((zi, (m, zy)), &yi) in z.chunks_exact_mut(k).zip(mz.iter_mut()).zip(y) {
                zi.iter_mut().zip(b).for_each(|(z, b)| *z += b);
                *m = zi.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                *zy = zi[yi];
                zi.iter_mut().for_each(|v| *v -= *m);
            }
            vmath::exp_in_place(&mut z);
            let mut loss = 0.0;
            for (i, (zi, &(m, zy))) in z.chunks_exact(k).zip(mz.iter()).enumerate() {
                let mut sum = 0.0;
                zi.iter().for_each(|v| sum += v);
                loss += m + sum.ln() - zy;
                let inv_sum = 1.0 / sum;
                for (c, &e) in zi.iter().enumerate() {
                    rt[c * n + i] = (e * inv_sum - f64::from(u8::from(c == y[i]))) * inv_n;
                }
            }
            let (gw, gb) = g.split_at_mut(nw);
            dense::gemm_nt(&rt, &xt, n, gw);
            let mut sq = 0.0;
            for (gw, w) in gw.iter_mut().zip(w) {
                *gw += alpha * inv_n * w;
                sq += w * w;
            }
            for (c, gb) in gb.iter_mut().enumerate() {
                *gb = rt[c * n..(c + 1) * n].iter().sum();
            }
            (loss + 0.5 * alpha * sq) * inv_n
        };
        let params = lbfgs::Params {
            memory: 10,
            gtol: 1e-6,
            ftol: 64.0 * f64::EPSILON,
            max_iter: 200,
            max_line_search: 50,
        };
        let mut theta = lbfgs::minimize(vec![0.0; nw + k], fg, &params).x;
        let b = theta.split_off(nw);
        (theta, b)
    }

    #[test]
    fn logistic_fit_has_the_bits_of_the_row_by_row_evaluation() {
        // Row counts that do and do not fill the last block of rows; one class
        // absent from the labels; a constant column.
        for (n, dim, k, seed) in [
            (203, 6, 5usize, 1u64),
            (64, 16, 17, 2),
            (3, 2, 4, 3),
            (1, 3, 2, 4),
        ] {
            let mut x = random_rows(n, dim, seed);
            x.iter_mut().step_by(dim).for_each(|v| *v = 0.5);
            let y: Vec<usize> = (0..n)
                .map(|i| (i * 7 + seed as usize) % k.saturating_sub(1).max(1))
                .collect();
            for alpha in [1.0, 1e-3] {
                let (w0, b0) = fit_softmax_by_rows(&x, &y, dim, k, alpha);
                let fit = || fit_softmax(&x, &y, dim, k, alpha, 1e-6, 200);
                // Every path: AVX-512 where the CPU has it, AVX2, baseline.
                for (path, (w, b)) in [
                    ("default", fit()),
                    ("avx2", crate::wide::without_avx512(fit)),
                    ("baseline", crate::wide::baseline_only(fit)),
                ] {
                    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    assert_eq!(
                        bits(&w),
                        bits(&w0),
                        "W, {path}, n {n} dim {dim} k {k} alpha {alpha}"
                    );
                    assert_eq!(
                        bits(&b),
                        bits(&b0),
                        "b, {path}, n {n} dim {dim} k {k} alpha {alpha}"
                    );
                }
            }
        }
    }

    /// No rows: the penalty alone, minimised at zero, without a panic on
    /// the evaluation's slices chunked by the row count.
    #[test]
    fn logistic_fit_of_no_rows_is_zero() {
        let (w, b) = fit_softmax(&[], &[], 3, 4, 1.0, 1e-6, 50);
        assert_eq!((w.len(), b.len()), (12, 4));
        assert!(w.iter().chain(&b).all(|v| *v == 0.0));
    }

    /// smartcore's L-BFGS logistic regression (which this one replaced)
    /// minimises the same penalised loss: on the same rows the two must give
    /// the same answers, up to points on a decision boundary.
    #[test]
    fn logistic_agrees_with_smartcore() {
        use smartcore::linear::logistic_regression::{LogisticRegression, LogisticRegressionParameters};
        let (dim, k) = (5, 3);
        let (x, y) = blobs(300, 11);
        let (tx, _) = blobs(300, 12);
        let (w, b) = fit_softmax(&x, &y, dim, k, 1.0, 1e-8, 1000);
        let ours: Vec<usize> = tx
            .chunks_exact(dim)
            .map(|r| {
                let z: Vec<f64> = (0..k)
                    .map(|c| dense::dot(&w[c * dim..(c + 1) * dim], r) + b[c])
                    .collect();
                (0..k).max_by(|&a, &c| z[a].total_cmp(&z[c])).unwrap_or(0)
            })
            .collect();
        let yi: Vec<i32> = y.iter().map(|&c| c as i32).collect();
        let lr = LogisticRegression::fit(
            &smart_matrix(&x, dim),
            &yi,
            LogisticRegressionParameters::default().with_alpha(1.0),
        )
        .expect("smartcore fits");
        let theirs = lr.predict(&smart_matrix(&tx, dim)).expect("smartcore predicts");
        let same = ours
            .iter()
            .zip(&theirs)
            .filter(|(a, b)| **a as i32 == **b)
            .count();
        assert!(
            same * 100 >= 97 * ours.len(),
            "{same} of {} answers agree",
            ours.len()
        );
    }

    /// The CART forest against smartcore's random forest: on held-out rows
    /// both must be about as accurate (their trees differ by their draws).
    #[test]
    fn forest_is_as_accurate_as_smartcores() {
        use smartcore::ensemble::random_forest_classifier::{
            RandomForestClassifier, RandomForestClassifierParameters,
        };
        let dim = 5;
        let (x, y) = blobs(300, 21);
        let (tx, ty) = blobs(300, 22);
        let g = forest::Growth {
            m: 2,
            max_depth: 0,
            min_samples_leaf: 1,
        };
        let trees: Vec<forest::Tree> = (0..30)
            .map(|t| {
                // A bootstrap per tree, as the forest stage draws it.
                let mut rng = forest::tree_rng(5, t);
                let rows: Vec<usize> = (0..y.len()).map(|_| rng.random_range(0..y.len())).collect();
                let bx: Vec<f64> = rows
                    .iter()
                    .flat_map(|&i| x[i * dim..(i + 1) * dim].to_vec())
                    .collect();
                let by: Vec<usize> = rows.iter().map(|&i| y[i]).collect();
                forest::grow(&bx, &by, dim, 3, &g, &mut rng)
            })
            .collect();
        let ours = tx
            .chunks_exact(dim)
            .zip(&ty)
            .filter(|(r, &c)| {
                let mut votes = [0usize; 3];
                trees.iter().for_each(|t| votes[t.predict(r)] += 1);
                (0..3).max_by_key(|&v| votes[v]) == Some(c)
            })
            .count() as f64
            / ty.len() as f64;
        let yi: Vec<i32> = y.iter().map(|&c| c as i32).collect();
        let rf = RandomForestClassifier::fit(
            &smart_matrix(&x, dim),
            &yi,
            RandomForestClassifierParameters::default()
                .with_n_trees(30)
                .with_m(2)
                .with_seed(5),
        )
        .expect("smartcore fits");
        let pred = rf.predict(&smart_matrix(&tx, dim)).expect("smartcore predicts");
        let theirs = pred.iter().zip(&ty).filter(|(p, &c)| **p == c as i32).count() as f64 / ty.len() as f64;
        assert!(
            ours > 0.8 && theirs > 0.8,
            "accuracy ours {ours}, smartcore {theirs}"
        );
        assert!(
            (ours - theirs).abs() <= 0.05,
            "accuracy ours {ours}, smartcore {theirs}"
        );
    }
}
