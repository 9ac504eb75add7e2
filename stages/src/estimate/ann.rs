//! ANN baseline (paper section 3.2): a one-hidden-layer
//! perceptron over spike images, trained per fold, with the paper's
//! winner-take-all vote over the trial.
//!
//! # Model
//!
//! For a feature vector `x` (one image, "ANN (S)", or `frames` stacked images,
//! "ANN (ST)"; see [`super::features`] for selection and normalisation, then
//! per-feature standardisation fitted on the training vectors):
//!
//! ```text
//! a = tanh(W1 x + b1)          (hidden = 30 units by default, as in the paper)
//! p = softmax(W2 a + b2)       (one output per class)
//! ```
//!
//! trained to minimise the mean cross-entropy `-log p_y` plus `l2/2 · ‖W‖²` on
//! the weights (not the biases), with minibatches (Adam by default, or SGD with
//! momentum). tanh rather than a ReLU: with 30 units a dead unit costs a lot,
//! and tanh is smooth, so the gradient check is exact.
//!
//! Early stopping: a validation split of whole training *trials* (per class,
//! `val_fraction` of them; see [`super::features::TrainSet::split_by_trial`])
//! is held out; training stops when the validation loss has not improved for
//! `patience` epochs, and the weights of the best epoch are kept.
//!
//! Default input: `spatiotemporal` with `frames = 5` images spaced one window
//! apart (0.5 s of contact). Spatial images are ambiguous on a 4x4 array (the
//! paper's ANN (S) has ~3x the error of ANN (ST)); 0.5 s spans the crossing of
//! more than one taxel row or column for angles above ~20° (a row-to-row delay
//! of `pitch / (v tan θ)`) while keeping the input at 80 values.
//!
//! Initialisation: Glorot-uniform weights, zero biases, from the fold's seeded
//! RNG, which also shuffles the minibatches and draws the validation split, so a
//! fit is bit-identical for the same seed. Loops run in a fixed order on one
//! thread (folds run in parallel in the runtime).
//!
//! Prediction runs in `f32` ([`super::ann32`]: the trained network rounded
//! once; a frame's probabilities within 2e-5 of the `f64` pass's in the
//! tests, 1.6e-6 measured on `benches/peers`' fold 0; the same bits alone
//! or in a batch, on every CPU path), training in `f64`.
//!
//! A minibatch's forward pass is two tiled products over its rows
//! ([`dense::gemm_nt`]), and each weight gradient
//! `Σ_rows δ xᵀ` is summed row after row per entry with a strip of entries
//! in registers: the bits of a row-by-row pass (the test
//! `batched_passes_are_the_bits_of_row_by_row`), at half its time.
//!
//! Saved models: `save_model = true` writes each fold's fitted network; a
//! stage given one with `model_in` predicts with it instead of fitting, and
//! streams under `palpate run --live` (see [`super::saved`]).

use super::ann32::Infer32;
use super::features::{
    check_scaler, want, FeatureKeys, FittedModel, FrameClassifier, Standardizer, TrainSet, TrainingLog, Vote,
    MODEL_FORMAT,
};
use super::{dense, vmath};
use palpate_core::{check_positive, check_range, ConfigChecks, ConfigError, FitContext, Item, StageError};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Input of the ANN.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum AnnInput {
    /// One spike image per vector ("ANN (S)").
    Spatial,
    /// `frames` stacked images per vector ("ANN (ST)").
    Spatiotemporal,
}

/// Minibatch optimiser.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Optimizer {
    /// Adam (Kingma & Ba 2015), β1 = 0.9, β2 = 0.999, ε = 1e-8.
    Adam,
    /// SGD with (heavy-ball) momentum.
    Sgd,
}

/// One-hidden-layer ANN on spike images, trained per fold (paper's ANN (S) / ANN (ST)).
///
/// Per-frame softmax outputs are combined over the trial by the paper's
/// winner-take-all vote. Input: spike images; output: orientation estimates.
/// See the module docs of `palpate_stages::estimate::ann` for the maths.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct AnnConfig {
    /// `spatial` (one image per vector) or `spatiotemporal` (`frames` images). Default `spatiotemporal`.
    pub input: AnnInput,
    /// Images stacked per spatiotemporal vector (ignored for `spatial`). Default 5.
    pub frames: usize,
    /// Frames between stacked images; 0 = one window (`round(window_ms / hop_ms)`). Default 0.
    pub step: usize,
    /// Frames between the frames a trial contributes; 0 = one window. Default 0.
    pub stride: usize,
    /// Smallest spike total of a used vector (frames below are skipped). Default 1.
    pub min_spikes: f64,
    /// Most vectors a training trial contributes (evenly spaced). Default 50.
    pub max_train_frames: usize,
    /// Hidden units. Default 30 (the paper's).
    pub hidden: usize,
    /// `adam` or `sgd` (with momentum). Default `adam`.
    pub optimizer: Optimizer,
    /// Learning rate. Default 0.005.
    pub learning_rate: f64,
    /// Momentum of `sgd` (unused by `adam`). Default 0.9.
    pub momentum: f64,
    /// L2 weight decay on the weights. Default 1e-4.
    pub l2: f64,
    /// Vectors per minibatch. Default 32.
    pub batch_size: usize,
    /// Most training epochs. Default 60.
    pub max_epochs: usize,
    /// Epochs without validation improvement before stopping. Default 6.
    pub patience: usize,
    /// Share of each class's training trials held out for early stopping (0 = none: train `max_epochs`). Default 0.15.
    pub val_fraction: f64,
    /// `winner` (paper: each frame's winning class collects its output) or `sum`. Default `winner`.
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

impl Default for AnnConfig {
    fn default() -> Self {
        AnnConfig {
            input: AnnInput::Spatiotemporal,
            frames: 5,
            step: 0,
            stride: 0,
            min_spikes: 1.0,
            max_train_frames: 50,
            hidden: 30,
            optimizer: Optimizer::Adam,
            learning_rate: 0.005,
            momentum: 0.9,
            l2: 1e-4,
            batch_size: 32,
            max_epochs: 60,
            patience: 6,
            val_fraction: 0.15,
            vote: Vote::Winner,
            save_model: false,
            model_in: None,
        }
    }
}

impl AnnConfig {
    /// The feature keys this config states (`frames` is 1 for `spatial` input).
    pub fn feature_keys(&self) -> FeatureKeys {
        FeatureKeys {
            frames: match self.input {
                AnnInput::Spatial => 1,
                AnnInput::Spatiotemporal => self.frames,
            },
            step: self.step,
            stride: self.stride,
            min_spikes: self.min_spikes,
            max_train_frames: self.max_train_frames,
        }
    }

    /// Checks every key, naming the wrong one.
    pub fn check(&self) -> Result<(), ConfigError> {
        let mut c = ConfigChecks::new();
        c.take(self.feature_keys().check());
        if self.hidden == 0 || self.hidden > 100_000 {
            c.push(ConfigError::key(
                "hidden",
                format!("must be 1..=100000, got {}", self.hidden),
            ));
        }
        c.take(check_positive("learning_rate", self.learning_rate, ""));
        c.take(check_range("momentum", self.momentum, 0.0, 0.999, ""));
        c.take(check_range("l2", self.l2, 0.0, 1e3, ""));
        if self.batch_size == 0 {
            c.push(ConfigError::key("batch_size", "must be at least 1"));
        }
        if self.max_epochs == 0 {
            c.push(ConfigError::key("max_epochs", "must be at least 1"));
        }
        c.take(check_range("val_fraction", self.val_fraction, 0.0, 0.5, ""));
        c.finish()
    }

    /// Fits the ANN on a fold's training trials.
    pub fn fit_model(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<FittedModel, StageError> {
        self.check()?;
        let set = TrainSet::build(train, &self.feature_keys())?;
        Ok(self.fit_set(set, &mut ctx.rng()))
    }

    /// Fits the ANN on a fold's training vectors (the part of
    /// [`AnnConfig::fit_model`] after feature extraction; `rng` is the fold's
    /// generator, first drawn on for the validation split). The config must have
    /// passed [`AnnConfig::check`]. `benches/peers` times training through this.
    pub fn fit_set(&self, set: TrainSet, rng: &mut ChaCha8Rng) -> FittedModel {
        let (fit_idx, val_idx) = set.split_by_trial(self.val_fraction, rng);
        let scaler = Standardizer::fit(&set, &fit_idx);
        let standardized = |idx: &[usize]| -> (Vec<f64>, Vec<usize>) {
            let mut x = Vec::with_capacity(idx.len() * set.dim);
            for &i in idx {
                let start = x.len();
                x.extend_from_slice(set.row(i));
                scaler.apply(&mut x[start..]);
            }
            (x, idx.iter().map(|&i| set.y[i]).collect())
        };
        let (xf, yf) = standardized(&fit_idx);
        let (xv, yv) = standardized(&val_idx);
        let mut mlp = Mlp::new(set.dim, self.hidden, set.classes.len(), scaler, rng);
        let log = mlp.train(&xf, &yf, &xv, &yv, self, rng);
        FittedModel {
            format: MODEL_FORMAT,
            stage_type: "ann".into(),
            classes: set.classes,
            features: set.spec,
            vote: self.vote,
            classifier: Box::new(mlp),
            log,
        }
    }
}

super::features::trained_baseline_stage!("ann", AnnConfig);

/// A fitted one-hidden-layer perceptron. Parameters are one flat vector,
/// `[W1 (hidden x dim, row-major) | b1 | W2 (classes x hidden) | b2]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Mlp {
    /// Input size.
    pub dim: usize,
    /// Hidden units.
    pub hidden: usize,
    /// Output classes.
    pub classes: usize,
    /// Flat parameters. Set before the first prediction: the first layer
    /// with the standardisation folded in is made then and kept
    /// (`Mlp::folded`); a network changed after it is a new `Mlp`.
    pub params: Vec<f64>,
    /// Input standardisation (set before the first prediction, as `params`).
    pub scaler: Standardizer,
    /// The network in `f32` that predicts, made at the first prediction.
    #[serde(skip)]
    fold: FoldCache,
}

/// [`Mlp::predictor`]'s network (with [`Mlp::folded`]'s first layer), kept
/// from the first prediction: the folded layer alone, made at every call,
/// was ~2 µs, more than a one-frame prediction itself (1.4-1.9 µs against
/// 3.3-4.1 µs with it, 80 inputs; the live ANN graph predicts once a hop).
#[derive(Clone, Debug, Default)]
struct FoldCache(std::sync::OnceLock<(Infer32, bool)>);

/// A cache: two networks are equal whether or not either made it.
impl PartialEq for FoldCache {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

/// Working buffers of the tests' row-by-row reference passes.
#[cfg(test)]
struct Scratch {
    a: Vec<f64>,
    p: Vec<f64>,
    da: Vec<f64>,
}

/// `g[j][d] += dz[i][j] · x[i][d]` for every row `i` in order (`g` is
/// `h x dim`, `dz` is `n x h`, `x` is `n x dim`, all row-major): each entry
/// sums its rows' products one after another, unfused, as the row-by-row
/// update `g[j] += dz[i][j] · x[i]` did, so the bits are the same. Row by
/// row, every row reloaded and stored the whole `h x dim` gradient; here
/// a strip of up to 16 entries of `g` stays in registers while the rows
/// pass (a fifth of a fit before).
fn add_outer_rows(g: &mut [f64], dz: &[f64], x: &[f64], h: usize, dim: usize) {
    let n = x.len() / dim.max(1);
    crate::wide::with_avx2(
        #[inline(always)]
        || {
            for (j, grow) in g.chunks_exact_mut(dim.max(1)).enumerate().take(h) {
                // Strips of 16, then 8, 4, 2 and 1 for the rest of the row.
                let mut d0 = 0;
                d0 = outer_strips::<16>(grow, dz, x, (h, j), (dim, d0), n);
                d0 = outer_strips::<8>(grow, dz, x, (h, j), (dim, d0), n);
                d0 = outer_strips::<4>(grow, dz, x, (h, j), (dim, d0), n);
                d0 = outer_strips::<2>(grow, dz, x, (h, j), (dim, d0), n);
                outer_strips::<1>(grow, dz, x, (h, j), (dim, d0), n);
            }
        },
    )
}

/// [`add_outer_rows`] for entries `d0..` of row `j` of `g`, `S` at a time
/// while `S` fit; returns the first entry left.
#[inline(always)]
fn outer_strips<const S: usize>(
    grow: &mut [f64],
    dz: &[f64],
    x: &[f64],
    (h, j): (usize, usize),
    (dim, mut d0): (usize, usize),
    n: usize,
) -> usize {
    while d0 + S <= dim {
        let mut acc: [f64; S] = std::array::from_fn(|l| grow[d0 + l]);
        for i in 0..n {
            let z = dz[i * h + j];
            let xs = &x[i * dim + d0..i * dim + d0 + S];
            for l in 0..S {
                acc[l] += z * xs[l];
            }
        }
        grow[d0..d0 + S].copy_from_slice(&acc);
        d0 += S;
    }
    d0
}

impl Mlp {
    /// A network with Glorot-uniform weights and zero biases.
    pub fn new(
        dim: usize,
        hidden: usize,
        classes: usize,
        scaler: Standardizer,
        rng: &mut ChaCha8Rng,
    ) -> Self {
        let mut m = Mlp {
            dim,
            hidden,
            classes,
            params: vec![0.0; hidden * dim + hidden + classes * hidden + classes],
            scaler,
            fold: FoldCache::default(),
        };
        let (w1, _, w2, _) = m.offsets();
        let r1 = (6.0 / (dim + hidden) as f64).sqrt();
        let r2 = (6.0 / (hidden + classes) as f64).sqrt();
        for i in 0..hidden * dim {
            m.params[w1 + i] = rng.random_range(-r1..r1);
        }
        for i in 0..classes * hidden {
            m.params[w2 + i] = rng.random_range(-r2..r2);
        }
        m
    }

    /// Offsets of W1, b1, W2, b2 in `params`.
    fn offsets(&self) -> (usize, usize, usize, usize) {
        let w1 = 0;
        let b1 = self.hidden * self.dim;
        let w2 = b1 + self.hidden;
        let b2 = w2 + self.classes * self.hidden;
        (w1, b1, w2, b2)
    }

    #[cfg(test)]
    fn scratch(&self) -> Scratch {
        Scratch {
            a: vec![0.0; self.hidden],
            p: vec![0.0; self.classes],
            da: vec![0.0; self.hidden],
        }
    }

    /// Forward pass of a standardised vector: hidden activations into `s.a`,
    /// class probabilities into `s.p`. The reference that the batched
    /// passes (`scores_batch`, `loss_grad`) reproduce bit for bit.
    #[cfg(test)]
    fn forward(&self, x: &[f64], s: &mut Scratch) {
        let (w1, b1, _, _) = self.offsets();
        let p = &self.params;
        self.forward_with(x, &p[w1..b1], &p[b1..b1 + self.hidden], s);
    }

    /// [`Self::forward`] of a raw vector with the first layer as `scores_batch`
    /// folds it ([`Self::folded`]), or of its standardised copy when it does not.
    #[cfg(test)]
    fn forward_raw(&self, x: &[f64], s: &mut Scratch) {
        match self.folded() {
            Some((w, b)) => self.forward_with(x, &w, &b, s),
            None => {
                let z = self.scaler.apply_rows(x);
                self.forward(&z, s)
            }
        }
    }

    /// The forward pass with the first layer's weights `w` and biases `b`.
    #[cfg(test)]
    fn forward_with(&self, x: &[f64], w: &[f64], b: &[f64], s: &mut Scratch) {
        let (_, _, w2, b2) = self.offsets();
        let p = &self.params;
        for j in 0..self.hidden {
            let row = &w[j * self.dim..(j + 1) * self.dim];
            s.a[j] = dot(row, x) + b[j];
        }
        // A loop of its own: the units' exponentials are independent, so
        // they overlap instead of waiting for each other's dot products.
        s.a.iter_mut().for_each(|a| *a = tanh(*a));
        for c in 0..self.classes {
            let row = &p[w2 + c * self.hidden..w2 + (c + 1) * self.hidden];
            s.p[c] = dot(row, &s.a) + p[b2 + c];
        }
        softmax(&mut s.p);
    }

    /// Class probabilities of a normalised (not yet standardised) vector.
    pub fn frame_scores(&self, x: &[f64], out: &mut [f64]) {
        self.scores_batch(x, out);
    }

    /// The first layer with the standardisation folded in: `W1' = W1·diag(s)`
    /// and `b1' = b1 − W1'·μ` (`μ` the scaler's means, `s` its `1/sd`), so
    /// that `W1' x + b1' = W1 (s ⊙ (x − μ)) + b1` up to rounding, and a
    /// prediction reads the raw vectors instead of a standardised copy of
    /// them (a pass over the batch written and read again: ~65 µs of the
    /// ANN (ST)'s ~710 µs prediction of 3154 x 80 vectors).
    ///
    /// `None` (the standardised copy is made) when a mean lies more than
    /// [`FOLD_LIMIT`] standard deviations from 0: `b1'` then cancels terms of
    /// that size against `W1' x`, and the rounding of `W1' x` would be that
    /// many times a standardised input's. Spike-image features sit a few
    /// SDs from 0 (a Poisson count's mean is `√λ` of its SDs away); a
    /// feature nearly constant at a non-zero value is what the limit
    /// catches.
    ///
    /// Made once, for [`Self::predictor`] (`params` and `scaler` are set
    /// before a network predicts).
    fn folded(&self) -> Option<(Vec<f64>, Vec<f64>)> {
        let (w1, b1, w2, _) = self.offsets();
        let p = &self.params;
        let dim = self.dim;
        let s = self.scaler.mean.len().min(self.scaler.inv_sd.len()).min(dim);
        let (mean, inv_sd) = (&self.scaler.mean[..s], &self.scaler.inv_sd[..s]);
        // Not `any(> FOLD_LIMIT)`: a NaN product must not fold either.
        if !mean.iter().zip(inv_sd).all(|(m, k)| (m * k).abs() <= FOLD_LIMIT) {
            return None;
        }
        let mut w = p[w1..b1].to_vec();
        let mut b = p[b1..w2].to_vec();
        for (row, bj) in w.chunks_exact_mut(dim.max(1)).zip(&mut b) {
            let mut shift = 0.0;
            for ((wd, k), m) in row[..s].iter_mut().zip(inv_sd).zip(mean) {
                *wd *= k;
                shift += *wd * m;
            }
            *bj -= shift;
        }
        Some((w, b))
    }

    /// [`Self::frame_scores`] of every row of `x` (row-major, `dim` wide) into
    /// the rows of `out` (`classes` wide), in `f32` ([`super::ann32`]): the
    /// first layer with the standardisation folded into its weights
    /// (`Self::folded`) reads the raw rows and skips their zeros; unfolded,
    /// the rows are standardised (in `f64`) first. A frame scored alone
    /// (live) and in a batch give the same bits.
    pub fn scores_batch(&self, x: &[f64], out: &mut [f64]) {
        let k = self.classes.max(1);
        let n = (x.len() / self.dim.max(1)).min(out.len() / k);
        let (net, folded) = self.predictor();
        if *folded {
            net.scores(x, n, out);
        } else {
            let z = self.scaler.apply_rows(&x[..n * self.dim]);
            net.scores(&z, n, out);
        }
    }

    /// The network in `f32` that predicts, and whether its first layer
    /// has the standardisation folded in; made at the first prediction and
    /// kept, as [`Self::folded`].
    fn predictor(&self) -> &(Infer32, bool) {
        self.fold.0.get_or_init(|| {
            let (w1, b1, w2, b2) = self.offsets();
            let p = &self.params;
            let (d, h, k) = (self.dim, self.hidden, self.classes);
            match self.folded() {
                Some((w, b)) => (Infer32::new(d, h, k, &w, &b, &p[w2..b2], &p[b2..]), true),
                None => (
                    Infer32::new(d, h, k, &p[w1..b1], &p[b1..w2], &p[w2..b2], &p[b2..]),
                    false,
                ),
            }
        })
    }

    /// Mean cross-entropy of standardised rows `x` (row-major) with labels `y`,
    /// plus the L2 term; adds the gradient of that loss to `grad` when given.
    pub fn loss_grad(&self, x: &[f64], y: &[usize], l2: f64, grad: Option<&mut [f64]>) -> f64 {
        let (w1, b1, w2, b2) = self.offsets();
        let n = y.len();
        if n == 0 {
            return 0.0;
        }
        let inv_n = 1.0 / n as f64;
        let mut loss = 0.0;
        // The forward pass of every row at once, as `scores_batch` does it
        // (tiled products over the batch, the bits of `forward` row by row);
        // row by row, its short dot products were three fifths of a fit.
        let (h, k) = (self.hidden, self.classes);
        let p = &self.params;
        let mut act = vec![0.0; n * h];
        dense::gemm_nt(&x[..n * self.dim], &p[w1..b1], self.dim, &mut act);
        dense::add_bias_map(&mut act, &p[b1..w2], tanh);
        let mut prob = vec![0.0; n * k];
        dense::gemm_nt(&act, &p[w2..b2], h, &mut prob);
        dense::add_bias_map(&mut prob, &p[b2..], |v| v);
        vmath::softmax_rows(&mut prob, k);
        let Some(g) = grad else {
            for (i, &yi) in y.iter().enumerate() {
                loss -= prob[i * k + yi].max(1e-300).ln();
            }
            return self.with_l2(loss * inv_n, l2, None);
        };
        // Each row's output and first-layer pre-activation gradients; the
        // weight gradients are summed over the rows after the loop (row
        // after row per entry, the bits of the row-by-row updates).
        let mut dz1 = vec![0.0; n * h];
        let mut da = vec![0.0; h];
        for (i, &yi) in y.iter().enumerate() {
            let a = &act[i * h..(i + 1) * h];
            let dz2 = &mut prob[i * k..(i + 1) * k];
            loss -= dz2[yi].max(1e-300).ln();
            // dL/dz2 = p - onehot(y), scaled by 1/n for the mean.
            dz2[yi] -= 1.0;
            dz2.iter_mut().for_each(|d| *d *= inv_n);
            da.iter_mut().for_each(|d| *d = 0.0);
            for (c, &dz) in dz2.iter().enumerate() {
                g[b2 + c] += dz;
                let wrow = &p[w2 + c * h..w2 + (c + 1) * h];
                da.iter_mut().zip(wrow).for_each(|(d, w)| *d += dz * w);
            }
            for j in 0..h {
                let dz = da[j] * (1.0 - a[j] * a[j]);
                g[b1 + j] += dz;
                dz1[i * h + j] = dz;
            }
        }
        add_outer_rows(&mut g[w2..b2], &prob, &act, k, h);
        add_outer_rows(&mut g[w1..b1], &dz1, &x[..n * self.dim], h, self.dim);
        self.with_l2(loss * inv_n, l2, Some(g))
    }

    /// `loss + l2/2 · ‖W‖²` (both layers' weights, not the biases), adding
    /// `l2 · W` to the gradient when given.
    fn with_l2(&self, mut loss: f64, l2: f64, mut grad: Option<&mut [f64]>) -> f64 {
        let (w1, b1, w2, b2) = self.offsets();
        if l2 > 0.0 {
            let mut sq = 0.0;
            for range in [w1..b1, w2..b2] {
                for k in range {
                    let w = self.params[k];
                    sq += w * w;
                    if let Some(g) = grad.as_deref_mut() {
                        g[k] += l2 * w;
                    }
                }
            }
            loss += 0.5 * l2 * sq;
        }
        loss
    }

    /// Minibatch training with early stopping; returns the log.
    fn train(
        &mut self,
        xf: &[f64],
        yf: &[usize],
        xv: &[f64],
        yv: &[usize],
        cfg: &AnnConfig,
        rng: &mut ChaCha8Rng,
    ) -> TrainingLog {
        let n_params = self.params.len();
        let mut grad = vec![0.0; n_params];
        let mut m1 = vec![0.0; n_params];
        let mut m2 = vec![0.0; n_params];
        let mut order: Vec<usize> = (0..yf.len()).collect();
        let mut bx = Vec::with_capacity(cfg.batch_size * self.dim);
        let mut by = Vec::with_capacity(cfg.batch_size);
        let mut log = TrainingLog {
            n_train: yf.len(),
            n_val: yv.len(),
            ..TrainingLog::default()
        };
        let mut best = (f64::INFINITY, self.params.clone(), 0usize);
        let mut t = 0i32;
        let mut since_best = 0;
        for epoch in 0..cfg.max_epochs {
            rand::seq::SliceRandom::shuffle(order.as_mut_slice(), rng);
            let mut epoch_loss = 0.0;
            for batch in order.chunks(cfg.batch_size) {
                bx.clear();
                by.clear();
                for &i in batch {
                    bx.extend_from_slice(&xf[i * self.dim..(i + 1) * self.dim]);
                    by.push(yf[i]);
                }
                grad.iter_mut().for_each(|g| *g = 0.0);
                let l = self.loss_grad(&bx, &by, cfg.l2, Some(&mut grad));
                epoch_loss += l * batch.len() as f64;
                t += 1;
                match cfg.optimizer {
                    Optimizer::Adam => {
                        let (b1, b2, eps) = (0.9f64, 0.999f64, 1e-8);
                        let c1 = 1.0 / (1.0 - b1.powi(t));
                        let c2 = 1.0 / (1.0 - b2.powi(t));
                        let lr = cfg.learning_rate;
                        // Vectorised (zipped slices, AVX2 or AVX-512 where
                        // the CPU has them); each entry's operations are
                        // unchanged, so are its bits (square root and
                        // division are exact in every width).
                        crate::wide::with_avx2(
                            #[inline(always)]
                            || {
                                for (((p, m1), m2), &g) in
                                    self.params.iter_mut().zip(&mut m1).zip(&mut m2).zip(&grad)
                                {
                                    *m1 = b1 * *m1 + (1.0 - b1) * g;
                                    *m2 = b2 * *m2 + (1.0 - b2) * g * g;
                                    *p -= lr * (*m1 * c1) / ((*m2 * c2).sqrt() + eps);
                                }
                            },
                        );
                    }
                    Optimizer::Sgd => {
                        for k in 0..n_params {
                            m1[k] = cfg.momentum * m1[k] - cfg.learning_rate * grad[k];
                            self.params[k] += m1[k];
                        }
                    }
                }
            }
            let train_loss = epoch_loss / yf.len().max(1) as f64;
            log.loss.push(train_loss);
            // Early stopping watches validation loss, or training loss without a split.
            let watched = if yv.is_empty() {
                train_loss
            } else {
                let v = self.loss_grad(xv, yv, 0.0, None);
                log.val_loss.push(v);
                v
            };
            if !watched.is_finite() {
                break;
            }
            if !best.0.is_finite() || watched < best.0 - 1e-9 * best.0.abs().max(1.0) {
                best = (watched, self.params.clone(), epoch);
                since_best = 0;
            } else {
                since_best += 1;
                if !yv.is_empty() && since_best >= cfg.patience.max(1) {
                    break;
                }
            }
        }
        if best.0.is_finite() {
            self.params = best.1;
            log.best_epoch = Some(best.2);
        }
        log
    }
}

pub(crate) use super::dense::dot;

/// Largest magnitude of a saved network's weights and biases: prediction
/// runs in `f32`, whose range ends at 3.4e38; training keeps weights
/// orders of magnitude below this (its L2 term and early stopping), so a
/// larger one is a file that was damaged or made by hand.
const MAX_PARAM: f64 = 1e20;

/// Largest `|mean / sd|` of an input for which [`Mlp::folded`] folds the
/// standardisation into the first layer: the rounding of the folded
/// product grows with it: at the limit, 10³ times a standardised input's,
/// i.e. up to 10³ times `f32`'s 6e-8 relative rounding in the prediction
/// (a bound, not a measurement).
const FOLD_LIMIT: f64 = 1e3;

/// The activations of training, shared with the other baselines and
/// vectorisable ([`super::vmath`]): `tanh` with one exponential, and the
/// softmax (of a batch's rows, `vmath::softmax_rows`; one row's in the
/// tests' reference pass). Prediction uses their `f32` forms
/// ([`super::ann32`]; its `tanh` within 2.5e-7 of this one, tested).
#[cfg(test)]
pub(crate) use super::vmath::softmax;
pub(crate) use super::vmath::tanh;

#[typetag::serde(name = "ann")]
impl FrameClassifier for Mlp {
    fn frame_scores(&self, x: &[f64], _rng: &mut ChaCha8Rng, out: &mut [f64]) {
        Mlp::frame_scores(self, x, out)
    }

    fn scores_batch(&self, x: &[f64], _dim: usize, _classes: usize, _rng: &mut ChaCha8Rng, out: &mut [f64]) {
        Mlp::scores_batch(self, x, out)
    }

    fn kind(&self) -> &'static str {
        "ann"
    }

    fn check_shape(&self, dim: usize, classes: usize) -> Result<(), String> {
        let m = self;
        want("the network's input size", m.dim, dim)?;
        want("the network's outputs", m.classes, classes)?;
        if m.hidden == 0 {
            return Err("the network has no hidden unit".into());
        }
        let n = m
            .hidden
            .checked_mul(dim + 1 + classes)
            .and_then(|x| x.checked_add(classes))
            .ok_or("the network's size overflows")?;
        want("the network's parameter count", m.params.len(), n)?;
        // Prediction runs in `f32` (`super::ann32`): a weight past
        // `MAX_PARAM` could overflow it where the `f64` network does not.
        if let Some(p) = m.params.iter().find(|p| !p.is_finite() || p.abs() > MAX_PARAM) {
            return Err(format!(
                "the network has a weight or bias of {p}: every one must be a finite number of magnitude at most {MAX_PARAM:e}"
            ));
        }
        check_scaler(&m.scaler, dim)
    }

    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand_chacha::rand_core::SeedableRng;

    /// A `d`-input, `h`-unit, `k`-class network with an identity scaler and
    /// non-zero biases in both layers (so their gradients are exercised too).
    fn random_net(d: usize, h: usize, k: usize, rng: &mut ChaCha8Rng) -> Mlp {
        let scaler = Standardizer {
            mean: vec![0.0; d],
            inv_sd: vec![1.0; d],
        };
        let mut m = Mlp::new(d, h, k, scaler, rng);
        let (_, b1, w2, b2) = m.offsets();
        for j in (b1..w2).chain(b2..b2 + k) {
            m.params[j] = rng.random_range(-0.5..0.5);
        }
        m
    }

    /// The standardisation folded into the first layer gives the scores of
    /// the standardised copy to rounding (a scaler of spike-count scale),
    /// and a mean past `FOLD_LIMIT` SDs is not folded (the copy is made):
    /// both within `SCORE_TOL` of the `f64` pass of the copy.
    #[test]
    fn folding_the_scaler_keeps_the_scores() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let (d, h, k, n) = (80, 30, 17, 70);
        for far in [false, true] {
            let mut m = random_net(d, h, k, &mut rng);
            m.scaler = Standardizer {
                mean: (0..d).map(|_| rng.random_range(0.0..5.0)).collect(),
                inv_sd: (0..d).map(|_| rng.random_range(0.2..3.0)).collect(),
            };
            if far {
                // A feature nearly constant at 5: mean 5, SD 1e-4.
                m.scaler.mean[7] = 5.0;
                m.scaler.inv_sd[7] = 1e4;
            }
            assert_eq!(m.folded().is_none(), far);
            let x: Vec<f64> = (0..n * d)
                .map(|_| {
                    if rng.random_bool(0.3) {
                        rng.random_range(0.0..8.0f64).floor()
                    } else {
                        0.0
                    }
                })
                .collect();
            let mut got = vec![0.0; n * k];
            m.scores_batch(&x, &mut got);
            // The reference: the standardised copy through the unfolded layer.
            let z = m.scaler.apply_rows(&x);
            let mut s = m.scratch();
            for i in 0..n {
                m.forward(&z[i * d..(i + 1) * d], &mut s);
                for (c, (&g, &w)) in got[i * k..(i + 1) * k].iter().zip(&s.p).enumerate() {
                    assert!(
                        (g - w).abs() <= SCORE_TOL,
                        "far {far}, row {i} class {c}: {g} vs {w}"
                    );
                }
            }
        }
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let (d, h, k, n) = (7, 5, 4, 9);
        let mut m = random_net(d, h, k, &mut rng);
        let x: Vec<f64> = (0..n * d).map(|_| rng.random_range(-2.0..2.0)).collect();
        let y: Vec<usize> = (0..n).map(|i| i % k).collect();
        let l2 = 0.01;
        let mut g = vec![0.0; m.params.len()];
        m.loss_grad(&x, &y, l2, Some(&mut g));
        let eps = 1e-6;
        for (p, &gp) in g.iter().enumerate() {
            let orig = m.params[p];
            m.params[p] = orig + eps;
            let lp = m.loss_grad(&x, &y, l2, None);
            m.params[p] = orig - eps;
            let lm = m.loss_grad(&x, &y, l2, None);
            m.params[p] = orig;
            let num = (lp - lm) / (2.0 * eps);
            let err = (num - gp).abs() / (num.abs() + gp.abs()).max(1e-8);
            assert!(err < 1e-5, "param {p}: analytic {gp} vs numeric {num}");
        }
    }

    /// `loss_grad`'s batched forward pass and gradient are the bits of the
    /// row-by-row passes, and `scores_batch` (in `f32`) is within
    /// `SCORE_TOL` of them with each row's bits alone or batched, at batch
    /// sizes on both sides of the product kernels' thresholds and at the
    /// paper's input widths.
    #[test]
    fn batched_passes_are_the_bits_of_row_by_row() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for (d, h, k) in [(16, 30, 17), (80, 30, 17), (7, 5, 4)] {
            let m = random_net(d, h, k, &mut rng);
            for n in [1, 3, 31, 32, 64, 65, 200] {
                let x: Vec<f64> = (0..n * d).map(|_| rng.random_range(-3.0..3.0)).collect();
                assert_batch_is_row_by_row(&m, &x, &format!("d {d}, n {n}"));
                let mut s = m.scratch();
                // Loss and gradient: the row-by-row pass, as it was
                // written before the batched one.
                let y: Vec<usize> = (0..n).map(|i| i % k).collect();
                let (w1, b1, w2, b2) = m.offsets();
                let inv_n = 1.0 / n as f64;
                let mut want = 0.0;
                let mut r = vec![0.0; m.params.len()];
                for (i, &yi) in y.iter().enumerate() {
                    let xi = &x[i * d..(i + 1) * d];
                    m.forward(xi, &mut s);
                    want -= s.p[yi].max(1e-300).ln();
                    s.p[yi] -= 1.0;
                    s.p.iter_mut().for_each(|v| *v *= inv_n);
                    s.da.iter_mut().for_each(|v| *v = 0.0);
                    for c in 0..k {
                        let dz = s.p[c];
                        r[b2 + c] += dz;
                        for j in 0..h {
                            r[w2 + c * h + j] += dz * s.a[j];
                            s.da[j] += dz * m.params[w2 + c * h + j];
                        }
                    }
                    for j in 0..h {
                        let dz = s.da[j] * (1.0 - s.a[j] * s.a[j]);
                        r[b1 + j] += dz;
                        for (gd, xd) in r[w1 + j * d..w1 + (j + 1) * d].iter_mut().zip(xi) {
                            *gd += dz * xd;
                        }
                    }
                }
                want *= inv_n;
                let loss = m.loss_grad(&x, &y, 0.0, None);
                assert_eq!(loss.to_bits(), want.to_bits(), "loss, d {d}, n {n}");
                let mut g = vec![0.0; m.params.len()];
                let loss = m.loss_grad(&x, &y, 0.0, Some(&mut g));
                assert_eq!(loss.to_bits(), want.to_bits(), "loss with gradient, d {d}, n {n}");
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&g), bits(&r), "gradient, d {d}, n {n}");
            }
        }
    }

    /// Mostly zero rows (spike counts) through the folded, zero-skipping
    /// first layer: within `SCORE_TOL` of the `f64` pass, each row's bits
    /// alone or batched, on every path this CPU has.
    #[test]
    fn sparse_batches_are_the_bits_of_row_by_row() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        for (d, h, k) in [(16, 30, 17), (80, 30, 17)] {
            let mut m = random_net(d, h, k, &mut rng);
            // Counts: a scaler with a mean and spread per feature, which folds.
            m.scaler.mean = (0..d).map(|i| 0.1 * (i % 5) as f64).collect();
            m.scaler.inv_sd = (0..d).map(|i| 1.0 + 0.25 * (i % 3) as f64).collect();
            m.fold = Default::default();
            assert!(m.folded().is_some());
            let n = 200;
            let x: Vec<f64> = (0..n * d)
                .map(|_| {
                    if rng.random_range(0..5) == 0 {
                        rng.random_range(1..4) as f64
                    } else {
                        0.0
                    }
                })
                .collect();
            assert_batch_is_row_by_row(&m, &x, &format!("native, d {d}"));
            crate::wide::without_avx512(|| {
                assert_batch_is_row_by_row(&m, &x, &format!("without AVX-512, d {d}"))
            });
            crate::wide::baseline_only(|| assert_batch_is_row_by_row(&m, &x, &format!("baseline, d {d}")));
        }
    }

    /// `scores_batch` of the rows of `x` (in `f32`) is within `SCORE_TOL`
    /// of `forward_raw` (the `f64` pass) row by row, and each row scored
    /// alone has its bits in the batch.
    fn assert_batch_is_row_by_row(m: &Mlp, x: &[f64], what: &str) {
        let (d, k) = (m.dim, m.classes);
        let n = x.len() / d;
        let mut batch = vec![0.0; n * k];
        m.scores_batch(x, &mut batch);
        let mut s = m.scratch();
        let mut one = vec![0.0; k];
        for i in 0..n {
            let row = &x[i * d..(i + 1) * d];
            m.forward_raw(row, &mut s);
            let got = &batch[i * k..(i + 1) * k];
            for (c, (&g, &w)) in got.iter().zip(&s.p).enumerate() {
                assert!(
                    (g - w).abs() <= SCORE_TOL,
                    "{what}, row {i}, class {c}: {g} vs {w}"
                );
            }
            m.frame_scores(row, &mut one);
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&one), bits(got), "{what}, row {i} alone");
        }
    }

    /// How far the `f32` prediction's probabilities may be from the `f64`
    /// pass's: a few `f32` roundings of each layer, amplified by the
    /// weights' sizes in these tests (up to 1 and 80 inputs).
    const SCORE_TOL: f64 = 2e-5;

    /// A saved network with a weight `f32` prediction cannot hold (or a
    /// NaN) is refused with the value named, not predicted with.
    #[test]
    fn weights_past_f32_range_are_refused() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let m = random_net(4, 3, 2, &mut rng);
        assert!(FrameClassifier::check_shape(&m, 4, 2).is_ok());
        for bad in [1e21, -1e39, f64::INFINITY, f64::NAN] {
            let mut m = m.clone();
            m.params[5] = bad;
            let err = FrameClassifier::check_shape(&m, 4, 2).unwrap_err();
            assert!(
                err.contains("weight or bias") && err.contains(&format!("{bad}")),
                "{err}"
            );
        }
    }

    #[test]
    fn tanh_matches_the_library_function() {
        for i in -4000..=4000 {
            let x = f64::from(i) * 0.005;
            assert!((tanh(x) - x.tanh()).abs() <= 4.0 * f64::EPSILON, "{x}");
        }
        assert_eq!(tanh(1e6), 1.0);
        assert_eq!(tanh(-1e6), -1.0);
        assert_eq!(tanh(0.0), 0.0);
    }

    #[test]
    fn softmax_is_stable_for_huge_logits() {
        let mut z = vec![1e300, -1e300, 0.0];
        softmax(&mut z);
        assert!(z.iter().all(|v| v.is_finite()));
        assert_eq!(z[0], 1.0);
        let d = dot(&[1.0, 2.0, 3.0, 4.0, 5.0], &[1.0; 5]);
        assert_eq!(d, 15.0);
    }

    #[test]
    fn bad_keys_are_named() {
        let c = AnnConfig {
            hidden: 0,
            ..AnnConfig::default()
        };
        assert_eq!(c.check().unwrap_err().key.as_deref(), Some("hidden"));
        let c = AnnConfig {
            val_fraction: 0.9,
            ..AnnConfig::default()
        };
        assert_eq!(c.check().unwrap_err().key.as_deref(), Some("val_fraction"));
        let c = AnnConfig {
            frames: 0,
            ..AnnConfig::default()
        };
        assert_eq!(c.check().unwrap_err().key.as_deref(), Some("frames"));
    }
}
