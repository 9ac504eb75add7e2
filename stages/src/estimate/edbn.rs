//! Event-based deep belief network after O'Connor et al. 2013 ("Real-time
//! classification and sensor fusion with a spiking deep belief network",
//! Front. Neurosci. 7:178), the paper's EDBN baseline (section 3.2).
//!
//! # Training (generative, layer by layer)
//!
//! A stack of restricted Boltzmann machines over the spatiotemporal feature
//! vectors `v ∈ [0, 1]^D` (see [`super::features`]; default 5 stacked images).
//! Each RBM has energy `E(v, h) = -vᵀWh - aᵀv - bᵀh` with Bernoulli units, so
//! `p(h_j = 1 | v) = σ(b_j + W_j·v)` and `p(v_i = 1 | h) = σ(a_i + Wᵀ_i·h)`.
//! The top RBM (the "associative" layer, last entry of `layers`) also has a
//! softmax group of label units `y` on its visible side, trained jointly with
//! the layer below's activities (a label-augmented RBM, as in Hinton et al. 2006
//! and O'Connor et al.), `p(y | h) = softmax(c + Uᵀh)`.
//!
//! Every RBM is trained with persistent contrastive divergence (PCD, Tieleman
//! 2008): the positive statistics use the data with `p(h | v)`; the negative
//! statistics come from `batch_size` persistent Gibbs chains advanced one step
//! per minibatch (sample `h`, sample `v` (and `y`), recompute `p(h | v)`). The
//! update is `ΔW = lr (⟨v hᵀ⟩_data - ⟨v hᵀ⟩_chains) - lr·l2·W`, with momentum 0.5
//! for the first epochs and 0.9 after, and a learning rate decaying linearly to
//! a tenth over the epochs (PCD needs a decaying rate for its chains to track the
//! model). The top RBM's update also adds `discriminative ·` the gradient of
//! `log p(y | h)` (hybrid generative/discriminative training, Larochelle &
//! Bengio 2008): with a few thousand training vectors, purely generative PCD
//! left the label units near the class prior in our tests (`discriminative =
//! 0` restores it). Weights start at `N(0, 1/n_vis)` so hidden units
//! differentiate within the first epochs. The layer above is trained on the mean-field activities `p(h | v)` of
//! the layer below.
//!
//! Training runs in `f32` (`super::rbm32`: every weight, gradient,
//! activity and uniform of the minibatch loop; the network is stored in
//! `f64` before and after, so inference and saved models are unchanged).
//! Until 2026-12-06 it ran in `f64` with the bits of straightforward
//! loops, at 0.26-0.36 s a `benches/peers` fit (by host), about twice as fast as
//! scikit-learn's RBM stack rather than the 3x the project asks of every
//! baseline; in `f32` the same fit takes ~0.14 s (rbm32's module docs have
//! the why and the numbers). It moved every EDBN figure in its digits:
//! RESULTS.md says what.
//!
//! The training log records each layer-epoch's mean squared
//! reconstruction error `‖v - p(v | p(h | v))‖² / D` after the epoch, on a
//! fixed evenly spaced subset of at most 256 training vectors.
//!
//! # Inference (`inference` key)
//!
//! * `rate` (mean-field): `h_1 = σ(W_1 v + b_1)`, ... up to the layer under
//!   the top; then the top RBM's label posterior, exactly (free energies):
//!   `p(y | h) ∝ exp(c_y + Σ_j softplus(b_j + W_j·h + U_jy))`. The frame's class
//!   scores are `p(y | h)`. The softplus sum is evaluated as the product
//!   `Π_j (1 + e^{base_j}·e^{U_jy})` kept as mantissa and binary exponent
//!   (no logarithm; `n_hid + labels` exponentials per frame, from
//!   [`super::vmath::exp`], vectorised), falling back to the softplus sum for
//!   a frame whose net inputs exceed `±300`: see `Rbm::posterior_from_base`.
//!   A batch evaluates it 16 frames at a time with the frames across the
//!   vector lanes (`Rbm::posterior_rows`, the same bits; the test
//!   `grouped_posterior_is_the_bits_of_frame_by_frame`): with it the peers
//!   EDBN prediction (3154 frames) fell from 3.3-3.7 to 2.4-2.7 ms (thread
//!   CPU, old and new binaries alternated, `RAYON_NUM_THREADS=1
//!   target/release/examples/peers --out /tmp/wk --seed 1 --only edbn`).
//!   The layers up to the top's net inputs `b_j + W_j·h` run in `f32`, as
//!   training does (`super::rbm32::Forward`: each frame's values times
//!   `Wᵀ` with the units across the lanes, the features' zeros skipped,
//!   `σ` from an `f32` exponential), and the posterior in `f64` from those
//!   net inputs; a frame alone and in a batch take the same path, so the
//!   same bits (test `batch_scores_are_the_bits_of_frame_by_frame`). Since
//!   2026-12-06 (before, `f64` products with a fixed four-way split of each
//!   dot product): the peers prediction 1.44 ms on 2026-11-29 and 0.77 ms on
//!   2026-12-06, both on an AMD EPYC (best wall sample, `benches/peers/run.sh
//!   --seed 1 -- --skip-encoder`; docs/benches.md).
//! * `spiking` (event-driven, as O'Connor et al. run their DBN): each input value
//!   drives a Poisson spike train at `v_i · input_rate_hz` for `duration_ms`, in
//!   steps of `dt_ms`; every layer is integrate-and-fire units (reset by
//!   subtraction, threshold 1, membrane floor -1) receiving, per step, the weights
//!   of the units that spiked below plus bias current. The drive is scaled so that
//!   a unit's spike probability per step is `p_in · hardσ(z)` with `p_in =
//!   input_rate_hz · dt`, `hardσ(z) = clip(0.5 + z/4, 0, 1)` (the piecewise-linear
//!   sigmoid) and `z` its RBM net input: the firing rates carry the mean-field
//!   activities, which is the rate-based correspondence O'Connor et al. obtain by
//!   training with Siegert units (we train with sigmoids and map through hardσ,
//!   a simplification we state here). Label units integrate `c + Uᵀ s_top` and the
//!   frame's class scores are their spike counts divided by the total (all zero if
//!   none fired). Spikes come from the trial's seeded RNG, so spiking inference is
//!   reproducible.
//!
//! In both modes a trial's answer is the winner-take-all vote of the paper.
//!
//! Saved models: `save_model = true` writes each fold's fitted network; a
//! stage given one with `model_in` predicts with it instead of fitting, and
//! streams under `palpate run --live` (see [`super::saved`]).

use super::features::{
    want, FeatureKeys, FittedModel, FrameClassifier, TrainSet, TrainingLog, Vote, MODEL_FORMAT,
};
use super::rbm32;
use super::vmath::{self, softmax};
use palpate_core::{check_positive, check_range, ConfigChecks, ConfigError, FitContext, Item, StageError};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// How the fitted network is run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Inference {
    /// Mean-field rates.
    Rate,
    /// Event-driven integrate-and-fire units driven by Poisson input spikes.
    Spiking,
}

/// Event-based deep belief network (O'Connor et al. 2013): stacked RBMs trained with PCD, label-augmented top layer.
///
/// Rate (mean-field) or event-driven spiking inference per frame, winner-take-all
/// over the trial. Input: spike images; output: orientation estimates.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct EdbnConfig {
    /// Images stacked per vector (EDBN uses spatiotemporal input). Default 5.
    pub frames: usize,
    /// Frames between stacked images; 0 = one window (`round(window_ms / hop_ms)`). Default 0.
    pub step: usize,
    /// Frames between the frames a trial contributes; 0 = one window. Default 0.
    pub stride: usize,
    /// Smallest spike total of a used vector. Default 1.
    pub min_spikes: f64,
    /// Most vectors a training trial contributes (evenly spaced). Default 30.
    pub max_train_frames: usize,
    /// Hidden layer sizes, bottom to top; the last is the associative layer trained with the labels. Default [60, 30].
    pub layers: Vec<usize>,
    /// PCD epochs per layer. Default 15.
    pub epochs: usize,
    /// Vectors per minibatch, and persistent chains. Default 20.
    pub batch_size: usize,
    /// Initial learning rate (decays linearly to a tenth). Default 0.05.
    pub learning_rate: f64,
    /// L2 weight decay. Default 1e-4.
    pub l2: f64,
    /// Weight of the discriminative gradient `∇ log p(y | x)` added to the top RBM's PCD update (hybrid training; 0 = purely generative). Default 10.
    pub discriminative: f64,
    /// `rate` (mean-field) or `spiking` (event-driven LIF). Default `rate`.
    pub inference: Inference,
    /// Spiking: input rate of a unit at value 1, Hz. Default 200.
    pub input_rate_hz: f64,
    /// Spiking: simulated time per frame, ms. Default 100.
    pub duration_ms: f64,
    /// Spiking: time step, ms. Default 1.
    pub dt_ms: f64,
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

impl Default for EdbnConfig {
    fn default() -> Self {
        EdbnConfig {
            frames: 5,
            step: 0,
            stride: 0,
            min_spikes: 1.0,
            max_train_frames: 30,
            layers: vec![60, 30],
            epochs: 15,
            batch_size: 20,
            learning_rate: 0.05,
            l2: 1e-4,
            discriminative: 10.0,
            inference: Inference::Rate,
            input_rate_hz: 200.0,
            duration_ms: 100.0,
            dt_ms: 1.0,
            vote: Vote::Winner,
            save_model: false,
            model_in: None,
        }
    }
}

/// One RBM: `w` is hidden x visible, row-major. The top RBM's visible side
/// ends with `labels` softmax units.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Rbm {
    /// Visible units (including labels).
    pub n_vis: usize,
    /// Hidden units.
    pub n_hid: usize,
    /// Label units at the end of the visible side (0 below the top).
    pub labels: usize,
    /// Weights, hidden x visible.
    pub w: Vec<f64>,
    /// Visible biases.
    pub a: Vec<f64>,
    /// Hidden biases.
    pub b: Vec<f64>,
}

/// Scratch of the label posterior, with `exp(U)` of the weights it was
/// last [prepared](Disc::prepare) for.
struct Disc {
    /// `e^{o_jy}` of the hidden net inputs `o_jy = base_j + U_jy` (x with
    /// label y), hidden-major (`j·labels + y`), clamped to `e^{±700}` on the
    /// exact path: `σ(o) = t / (1 + t)`.
    t: Vec<f64>,
    /// Label posterior.
    p: Vec<f64>,
    /// `base_j = b_j + W_j·x`.
    base: Vec<f64>,
    /// `e^{base_j}`.
    eb: Vec<f64>,
    /// `e^{U_jy}`, hidden-major.
    eu: Vec<f64>,
    /// Per label: the running product's mantissa in `[1, 2)` ...
    m: Vec<f64>,
    /// ... and its binary exponent.
    e: Vec<i64>,
    /// Every `|U_jy| ≤ EXP_SAFE`, so `e^{base}·e^{U}` is finite for the fast path.
    u_ok: bool,
    /// `max |U_jy|`.
    u_max: f64,
}

/// Whether at least half of `data` is zero: then training's products with
/// these rows visit only their nonzero values ([`rbm32::train_pcd`]). True
/// of the bottom layer's spike counts (four in five zero on the lab set),
/// not of the mean-field activities above it.
fn mostly_zeros(data: &[f64]) -> bool {
    2 * data.iter().filter(|&&x| x == 0.0).count() >= data.len()
}

/// Largest `|z|` whose `e^z` is taken in the product form of the posterior:
/// `e^{±300}` and their product stay finite and normal.
const EXP_SAFE: f64 = 300.0;

/// Frames per group of [`Rbm::posterior_rows`] (lanes of its vector loops).
const POST_LANES: usize = 16;

/// Rows per block of [`Dbn::scores_batch`]: a block's net inputs (30 units:
/// 123 KB) stay in L2 for the posterior, and a multiple of [`POST_LANES`]
/// so only the batch's last frames take the posterior's row-by-row path.
const BLOCK_ROWS: usize = 512;

/// One block of [`Rbm::posterior_rows`]' products, the frames across the
/// lanes: `m_y ← m_y·(1 + e^{base_j}·e^{U_jy})` for each hidden unit `j` of
/// the block in order (`eb[j]` the frames' `e^{base_j}`, `eu` the block's
/// `e^{U}`, hidden-major), then each mantissa's binary exponent moved into
/// `e`. With AVX2 written with intrinsics: left to the compiler, the loop
/// over the labels was vectorised instead, with gathers and scatters 16
/// frames apart (a third of a prediction).
fn product_block(
    m: &mut [[f64; POST_LANES]],
    e: &mut [[i64; POST_LANES]],
    eb: &[[f64; POST_LANES]],
    eu: &[f64],
) {
    let k = m.len();
    assert!(e.len() == k && eu.len() == eb.len() * k);
    #[cfg(target_arch = "x86_64")]
    if crate::wide::avx512() {
        // SAFETY: the CPU supports AVX-512 F (checked at run time); shapes asserted.
        unsafe { product_block_avx512(m, e, eb, eu) };
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if crate::wide::avx2() {
        // SAFETY: the CPU supports AVX2 (checked at run time); shapes asserted.
        unsafe { product_block_avx(m, e, eb, eu) };
        return;
    }
    const MANT: u64 = (1 << 52) - 1;
    const ONE: u64 = 1023 << 52;
    for (ebj, uj) in eb.iter().zip(eu.chunks_exact(k.max(1))) {
        for (my, &u) in m.iter_mut().zip(uj) {
            for (m, &x) in my.iter_mut().zip(ebj) {
                *m *= 1.0 + x * u;
            }
        }
    }
    for (my, ey) in m.iter_mut().zip(e.iter_mut()) {
        for (m, e) in my.iter_mut().zip(ey.iter_mut()) {
            let b = m.to_bits();
            *e += (b >> 52) as i64 - 1023;
            *m = f64::from_bits((b & MANT) | ONE);
        }
    }
}

/// [`product_block`] with 256-bit vectors: the same operations lane by lane.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn product_block_avx(
    m: &mut [[f64; POST_LANES]],
    e: &mut [[i64; POST_LANES]],
    eb: &[[f64; POST_LANES]],
    eu: &[f64],
) {
    use std::arch::x86_64::*;
    const V: usize = POST_LANES / 4;
    let k = m.len();
    let one = _mm256_set1_pd(1.0);
    for (ebj, uj) in eb.iter().zip(eu.chunks_exact(k.max(1))) {
        // SAFETY: ebj holds 4·V doubles.
        let x: [__m256d; V] = std::array::from_fn(|q| unsafe { _mm256_loadu_pd(ebj.as_ptr().add(4 * q)) });
        for (my, &u) in m.iter_mut().zip(uj) {
            let uv = _mm256_set1_pd(u);
            for (q, &xq) in x.iter().enumerate() {
                // SAFETY: my holds 4·V doubles.
                unsafe {
                    let p = my.as_mut_ptr().add(4 * q);
                    let t = _mm256_add_pd(one, _mm256_mul_pd(xq, uv));
                    _mm256_storeu_pd(p, _mm256_mul_pd(_mm256_loadu_pd(p), t));
                }
            }
        }
    }
    let mant = _mm256_set1_epi64x((1 << 52) - 1);
    let onev = _mm256_set1_epi64x(1023 << 52);
    let bias = _mm256_set1_epi64x(1023);
    for (my, ey) in m.iter_mut().zip(e.iter_mut()) {
        for q in 0..V {
            // SAFETY: my and ey hold 4·V values each.
            unsafe {
                let pm = my.as_mut_ptr().add(4 * q);
                let pe = ey.as_mut_ptr().add(4 * q).cast::<__m256i>();
                let b = _mm256_castpd_si256(_mm256_loadu_pd(pm));
                let ex = _mm256_sub_epi64(_mm256_srli_epi64::<52>(b), bias);
                _mm256_storeu_si256(pe, _mm256_add_epi64(_mm256_loadu_si256(pe), ex));
                let nm = _mm256_or_si256(_mm256_and_si256(b, mant), onev);
                _mm256_storeu_pd(pm, _mm256_castsi256_pd(nm));
            }
        }
    }
}

/// [`product_block`] with 512-bit vectors: the same operations lane by
/// lane, half the instructions of the 256-bit form.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn product_block_avx512(
    m: &mut [[f64; POST_LANES]],
    e: &mut [[i64; POST_LANES]],
    eb: &[[f64; POST_LANES]],
    eu: &[f64],
) {
    use std::arch::x86_64::*;
    const V: usize = POST_LANES / 8;
    let k = m.len();
    let one = _mm512_set1_pd(1.0);
    for (ebj, uj) in eb.iter().zip(eu.chunks_exact(k.max(1))) {
        // SAFETY: ebj holds 8·V doubles.
        let x: [__m512d; V] = std::array::from_fn(|q| unsafe { _mm512_loadu_pd(ebj.as_ptr().add(8 * q)) });
        for (my, &u) in m.iter_mut().zip(uj) {
            let uv = _mm512_set1_pd(u);
            for (q, &xq) in x.iter().enumerate() {
                // SAFETY: my holds 8·V doubles.
                unsafe {
                    let p = my.as_mut_ptr().add(8 * q);
                    let t = _mm512_add_pd(one, _mm512_mul_pd(xq, uv));
                    _mm512_storeu_pd(p, _mm512_mul_pd(_mm512_loadu_pd(p), t));
                }
            }
        }
    }
    let mant = _mm512_set1_epi64((1 << 52) - 1);
    let onev = _mm512_set1_epi64(1023 << 52);
    let bias = _mm512_set1_epi64(1023);
    for (my, ey) in m.iter_mut().zip(e.iter_mut()) {
        for q in 0..V {
            // SAFETY: my and ey hold 8·V values each.
            unsafe {
                let pm = my.as_mut_ptr().add(8 * q);
                let pe = ey.as_mut_ptr().add(8 * q).cast::<__m512i>();
                let b = _mm512_castpd_si512(_mm512_loadu_pd(pm));
                let ex = _mm512_sub_epi64(_mm512_srli_epi64::<52>(b), bias);
                _mm512_storeu_si512(pe, _mm512_add_epi64(_mm512_loadu_si512(pe), ex));
                let nm = _mm512_or_si512(_mm512_and_si512(b, mant), onev);
                _mm512_storeu_pd(pm, _mm512_castsi512_pd(nm));
            }
        }
    }
}

impl Disc {
    fn new(k: usize, nh: usize) -> Self {
        Disc {
            t: vec![0.0; k * nh],
            p: vec![0.0; k],
            base: vec![0.0; nh],
            eb: vec![0.0; nh],
            eu: vec![0.0; k * nh],
            m: vec![0.0; k],
            e: vec![0; k],
            u_ok: false,
            u_max: 0.0,
        }
    }

    /// Takes `e^{U}` of `rbm`'s label weights (after every weight update).
    fn prepare(&mut self, rbm: &Rbm) {
        let (nb, k) = (rbm.n_vis - rbm.labels, rbm.labels);
        self.u_max = 0.0;
        self.u_ok = true;
        for (row, eu) in rbm
            .w
            .chunks_exact(rbm.n_vis.max(1))
            .zip(self.eu.chunks_exact_mut(k.max(1)))
        {
            for (e, &u) in eu.iter_mut().zip(&row[nb..]) {
                // NaN fails `<=` and clears `u_ok`.
                self.u_ok &= u.abs() <= EXP_SAFE;
                self.u_max = self.u_max.max(u.abs());
                *e = u.clamp(-EXP_SAFE, EXP_SAFE);
            }
        }
        vmath::exp_in_place(&mut self.eu);
    }
}

/// `ln(1 + e^z)` for every `z`, never overflowing.
fn softplus(z: f64) -> f64 {
    z.max(0.0) + vmath::exp(-z.abs()).ln_1p()
}

/// `v ← σ(v)` over a slice, vectorised.
fn sigmoid_in_place(v: &mut [f64]) {
    crate::wide::with_avx2(
        #[inline(always)]
        || v.iter_mut().for_each(|z| *z = vmath::sigmoid(*z)),
    );
}

impl Rbm {
    pub(super) fn new(
        n_vis: usize,
        n_hid: usize,
        labels: usize,
        mean_vis: &[f64],
        rng: &mut ChaCha8Rng,
    ) -> Self {
        let sd = 1.0 / (n_vis as f64).sqrt();
        let w = (0..n_vis * n_hid)
            .map(|_| {
                // N(0, 1/n_vis) by Box–Muller, from the fold's RNG: large enough
                // that hidden units differ from the first epoch.
                let u1: f64 = rng.random::<f64>().max(1e-300);
                let u2: f64 = rng.random();
                sd * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
            })
            .collect();
        let a = mean_vis
            .iter()
            .map(|&p| {
                let p = p.clamp(1e-3, 1.0 - 1e-3);
                (p / (1.0 - p)).ln()
            })
            .collect();
        Rbm {
            n_vis,
            n_hid,
            labels,
            w,
            a,
            b: vec![0.0; n_hid],
        }
    }

    /// Hidden net inputs `b + W v`.
    fn hid_input(&self, v: &[f64], out: &mut [f64]) {
        for (j, o) in out.iter_mut().enumerate() {
            *o = self.b[j] + super::ann::dot(&self.w[j * self.n_vis..(j + 1) * self.n_vis], v);
        }
    }

    /// `p(h | v)`.
    fn hid_prob(&self, v: &[f64], out: &mut [f64]) {
        self.hid_input(v, out);
        sigmoid_in_place(out);
    }

    /// Label posterior `p(y | x)` of a label-augmented RBM, exactly (free
    /// energies): `p(y|x) ∝ exp(c_y + Σ_j softplus(b_j + W_j·x + U_jy))`. Fills
    /// `d.t` with `e^{o_jy}` and `d.p` with p. `d` must be
    /// [prepared](Disc::prepare) for these weights.
    fn label_posterior(&self, x: &[f64], d: &mut Disc) {
        let nb = self.n_vis - self.labels;
        for j in 0..self.n_hid {
            let row = &self.w[j * self.n_vis..(j + 1) * self.n_vis];
            d.base[j] = self.b[j] + super::ann::dot(&row[..nb], &x[..nb]);
        }
        self.posterior_from_base(d);
    }

    /// [`Self::label_posterior`] from `d.base`, without a logarithm. With
    /// `t_jy = e^{base_j}·e^{U_jy}`, the free energy's exponential is a
    /// product, `exp(Σ_j softplus(o_jy)) = Π_j (1 + t_jy)`, held per label as
    /// a mantissa `m_y ∈ [1, 2)` and a binary exponent `E_y` (the exponent
    /// bits are moved into `E_y` every `g` factors, `g` small enough that the
    /// mantissa cannot overflow in between: scaling by a power of two is
    /// exact, so `g` does not change the bits). Then `p(y) ∝ m_y ·
    /// exp(z_y − max z)` with `z_y = c_y + E_y·ln 2`: `n_hid` exponentials,
    /// `n_hid · labels` products and `labels` exponentials per frame, each
    /// loop over the labels (or hidden units) vectorised; the same value as
    /// summing the softplus terms to a few ulps. A frame with a unit at
    /// `|base_j| > 300` (or a model with `|U| > 300`) takes the exact
    /// softplus sum instead, stable for any finite input.
    fn posterior_from_base(&self, d: &mut Disc) {
        let nb = self.n_vis - self.labels;
        let (nh, k) = (self.n_hid, self.labels);
        let mut top = f64::NEG_INFINITY;
        let mut fast = d.u_ok;
        for &b in &d.base {
            fast &= b.abs() <= EXP_SAFE;
            top = top.max(b);
        }
        if !fast {
            // In the AVX2 function so the fused `exp` is the FMA instruction.
            crate::wide::with_avx2(
                #[inline(always)]
                || {
                    for y in 0..k {
                        let mut f = 0.0;
                        for j in 0..nh {
                            let o = d.base[j] + self.w[j * self.n_vis + nb + y];
                            f += softplus(o);
                            d.t[j * k + y] = o.clamp(-700.0, 700.0);
                        }
                        d.p[y] = self.a[nb + y] + f;
                    }
                },
            );
            vmath::exp_in_place(&mut d.t[..nh * k]);
            softmax(&mut d.p);
            return;
        }
        // Each factor is below 2^(bits + 1); after `g` of them the mantissa
        // (below 2) stays below 2^1000.
        let bits = (top + d.u_max).max(0.0) * std::f64::consts::LOG2_E + 1.0;
        let g = ((999.0 / bits) as usize).clamp(1, nh.max(1));
        const MANT: u64 = (1 << 52) - 1;
        const ONE: u64 = 1023 << 52;
        let Disc {
            t,
            p,
            base,
            eb,
            eu,
            m,
            e,
            ..
        } = d;
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                eb.iter_mut()
                    .zip(base.iter())
                    .for_each(|(e, &b)| *e = vmath::exp(b));
                for ((tj, uj), &ebj) in t.chunks_exact_mut(k).zip(eu.chunks_exact(k)).zip(eb.iter()) {
                    tj.iter_mut().zip(uj).for_each(|(t, u)| *t = ebj * u);
                }
                m.iter_mut().for_each(|m| *m = 1.0);
                e.iter_mut().for_each(|e| *e = 0);
                for block in t[..nh * k].chunks(g * k) {
                    for tj in block.chunks_exact(k) {
                        m.iter_mut().zip(tj).for_each(|(m, t)| *m *= 1.0 + t);
                    }
                    for (m, e) in m.iter_mut().zip(e.iter_mut()) {
                        let b = m.to_bits();
                        *e += (b >> 52) as i64 - 1023;
                        *m = f64::from_bits((b & MANT) | ONE);
                    }
                }
                let mut zmax = f64::NEG_INFINITY;
                for ((p, &e), c) in p.iter_mut().zip(e.iter()).zip(&self.a[nb..]) {
                    *p = c + e as f64 * std::f64::consts::LN_2;
                    zmax = zmax.max(*p);
                }
                p.iter_mut().for_each(|p| *p = vmath::exp(*p - zmax));
                let mut sum = 0.0;
                for (p, m) in p.iter_mut().zip(m.iter()) {
                    *p *= m;
                    sum += *p;
                }
                p.iter_mut().for_each(|p| *p /= sum);
            },
        );
    }

    /// [`Self::posterior_from_base`] of each row of `base` (`n_hid` wide, at
    /// least one) in turn into the first `labels` entries of the rows of `out`
    /// (`stride` wide): the row-by-row path of [`Self::posterior_rows`].
    fn posterior_each_row(&self, base: &[f64], d: &mut Disc, out: &mut [f64], stride: usize) {
        let k = self.labels;
        for (bi, o) in base
            .chunks_exact(self.n_hid.max(1))
            .zip(out.chunks_exact_mut(stride.max(1)))
        {
            d.base.copy_from_slice(bi);
            self.posterior_from_base(d);
            o[..k].copy_from_slice(&d.p);
        }
    }

    /// [`Self::posterior_from_base`] of every row of `base` (`n_hid` wide)
    /// into the rows of `out` (`stride` wide, the first `labels` entries),
    /// with its bits, [`POST_LANES`] frames at a time with the frames across
    /// the vector lanes: row by row, the loops over 17 labels left most lanes
    /// of the last vector idle and the per-frame setup cost as much as the
    /// products (perf on `benches/peers`, EDBN predict). Per frame and label
    /// the operations are those of `posterior_from_base` in the same order
    /// (the product over the hidden units in order, then the labels' sum in
    /// order); the mantissas are renormalised every `g` factors with the
    /// smallest `g` of the frames in the group, which does not change the
    /// bits (scaling by powers of two is exact, and no product overflows).
    /// A group with a frame off the fast path, and the last frames, go row
    /// by row. `d` must be [prepared](Disc::prepare) for these weights.
    // Indexed loops over the group's fixed width: each compiles to whole-vector operations.
    #[allow(clippy::needless_range_loop)]
    fn posterior_rows(&self, base: &[f64], d: &mut Disc, out: &mut [f64], stride: usize) {
        const L: usize = POST_LANES;
        let nb = self.n_vis - self.labels;
        let (nh, k) = (self.n_hid, self.labels);
        let n = (base.len() / nh.max(1)).min(out.len() / stride.max(1));
        assert!(
            stride >= k,
            "posterior_rows: rows of {stride} cannot hold {k} labels"
        );
        if nh == 0 || k == 0 {
            self.posterior_each_row(&base[..n * nh], d, out, stride);
            return;
        }
        // Group scratch, label- or hidden-major with the frames innermost,
        // as arrays of the group's width: with slices, the compiler turned
        // the product loop inside out and gathered and scattered a label's
        // values 16 frames apart (a third of a prediction).
        let mut ebt = vec![[0.0; L]; nh];
        let mut m = vec![[0.0; L]; k];
        let mut e = vec![[0i64; L]; k];
        let mut p = vec![[0.0; L]; k];
        let c = &self.a[nb..nb + k];
        // A copy: the frames off the fast path borrow `d` mutably.
        let eu = d.eu[..nh * k].to_vec();
        let mut i0 = 0;
        while i0 < n {
            let group = &base[i0 * nh..(i0 + L.min(n - i0)) * nh];
            let whole = n - i0 >= L;
            if whole {
                for (j, ej) in ebt.iter_mut().enumerate() {
                    for (i, v) in ej.iter_mut().enumerate() {
                        *v = group[i * nh + j];
                    }
                }
            }
            // The fast path's test and `g`, per frame as
            // `posterior_from_base` takes them, the frames across the lanes
            // (the maximum is exact whatever the order; a NaN fails the
            // test).
            let (fast, g) = crate::wide::with_avx2(
                #[inline(always)]
                || {
                    if !(whole && d.u_ok) {
                        return (false, nh);
                    }
                    let mut top = [f64::NEG_INFINITY; L];
                    let mut ok = [true; L];
                    for ej in &ebt {
                        for i in 0..L {
                            ok[i] &= ej[i].abs() <= EXP_SAFE;
                            top[i] = top[i].max(ej[i]);
                        }
                    }
                    let mut g = nh;
                    for &t in &top {
                        let bits = (t + d.u_max).max(0.0) * std::f64::consts::LOG2_E + 1.0;
                        g = g.min(((999.0 / bits) as usize).clamp(1, nh));
                    }
                    (ok.iter().all(|&o| o), g)
                },
            );
            if !fast {
                let rows = group.len() / nh;
                self.posterior_each_row(group, d, &mut out[i0 * stride..], stride);
                i0 += rows;
                continue;
            }
            let out = &mut out[i0 * stride..(i0 + L) * stride];
            crate::wide::with_avx2(
                #[inline(always)]
                || {
                    for ej in ebt.iter_mut() {
                        for v in ej.iter_mut() {
                            *v = vmath::exp(*v);
                        }
                    }
                },
            );
            m.iter_mut().for_each(|m| *m = [1.0; L]);
            e.iter_mut().for_each(|e| *e = [0; L]);
            for (eb_block, eu_block) in ebt.chunks(g).zip(eu.chunks(g * k)) {
                product_block(&mut m, &mut e, eb_block, eu_block);
            }
            crate::wide::with_avx2(
                #[inline(always)]
                || {
                    let mut zmax = [f64::NEG_INFINITY; L];
                    for ((py, ey), &cy) in p.iter_mut().zip(&e).zip(c) {
                        for i in 0..L {
                            py[i] = cy + ey[i] as f64 * std::f64::consts::LN_2;
                            zmax[i] = zmax[i].max(py[i]);
                        }
                    }
                    let mut sum = [0.0; L];
                    for (py, my) in p.iter_mut().zip(&m) {
                        for i in 0..L {
                            py[i] = vmath::exp(py[i] - zmax[i]) * my[i];
                            sum[i] += py[i];
                        }
                    }
                    for (y, py) in p.iter().enumerate() {
                        for i in 0..L {
                            out[i * stride + y] = py[i] / sum[i];
                        }
                    }
                },
            );
            i0 += L;
        }
    }
}

/// A fitted deep belief network.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Dbn {
    /// RBMs bottom to top; the last has the label units.
    pub rbms: Vec<Rbm>,
    /// Number of classes.
    pub classes: usize,
    /// Inference mode.
    pub inference: Inference,
    /// Spiking: input rate at value 1, Hz.
    pub input_rate_hz: f64,
    /// Spiking: simulated time per frame, ms.
    pub duration_ms: f64,
    /// Spiking: step, ms.
    pub dt_ms: f64,
    /// The rate network in `f32` layouts, built at first use from `rbms`
    /// (a model is not changed after it is fitted or loaded).
    #[serde(skip)]
    pub(crate) net32: Net32,
}

/// `Dbn::net32`: the layers below the top and the top's data columns as
/// `rbm32::Forward` layers, or `None` when the layers do not chain.
#[derive(Clone, Debug, Default)]
pub struct Net32(std::sync::OnceLock<Option<Vec<rbm32::Forward>>>);

impl PartialEq for Net32 {
    /// A cache: models are equal by their weights alone.
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl Dbn {
    /// The rate network's [`rbm32::Forward`] layers (built once), if its
    /// layers chain from `dim` inputs to the top's label units.
    fn forward_layers(&self, dim: usize) -> Option<&[rbm32::Forward]> {
        let layers = self.net32.0.get_or_init(|| {
            let (top, below) = self.rbms.split_last()?;
            let mut fed = below
                .first()
                .map_or(top.n_vis.checked_sub(top.labels)?, |r| r.n_vis);
            let mut out = Vec::with_capacity(self.rbms.len());
            for r in below {
                if r.n_vis != fed || r.labels != 0 || r.w.len() != r.n_vis * r.n_hid || r.b.len() != r.n_hid {
                    return None;
                }
                out.push(rbm32::Forward::new(r, r.n_vis, true, out.is_empty()));
                fed = r.n_hid;
            }
            if top.labels != self.classes
                || top.n_vis.checked_sub(top.labels) != Some(fed)
                || top.w.len() != top.n_vis * top.n_hid
                || top.b.len() != top.n_hid
            {
                return None;
            }
            let first = out.is_empty();
            out.push(rbm32::Forward::new(top, fed, false, first));
            Some(out)
        });
        layers
            .as_deref()
            .filter(|l| l.first().is_some_and(|f| f.inputs() == dim))
    }

    /// Class scores of one normalised vector.
    pub fn frame_scores(&self, x: &[f64], rng: &mut ChaCha8Rng, out: &mut [f64]) {
        match self.inference {
            Inference::Rate => self.rate_scores(x, out),
            Inference::Spiking => self.spiking_scores(x, rng, out),
        }
    }

    /// [`Self::frame_scores`] of every row of `x` (row-major, `dim` wide) into
    /// the rows of `out` (`classes` wide), in row order: the same bits as row
    /// by row. Rate inference runs the `f32` layers two rows at a time and the
    /// posterior over blocks of `BLOCK_ROWS` rows, 16 frames across the
    /// lanes (`Rbm::posterior_rows`, the bits of
    /// `Rbm::posterior_from_base`).
    pub fn scores_batch(&self, x: &[f64], dim: usize, rng: &mut ChaCha8Rng, out: &mut [f64]) {
        let k = self.classes.max(1);
        let layers = match (self.inference, self.rbms.last()) {
            (Inference::Rate, Some(top)) => self.forward_layers(dim).map(|l| (l, top)),
            _ => None,
        };
        let Some((layers, top)) = layers else {
            // Spiking inference, or a model whose layers do not chain: the
            // row-by-row path decides.
            for (row, o) in x.chunks_exact(dim.max(1)).zip(out.chunks_exact_mut(k)) {
                self.frame_scores(row, rng, o);
            }
            return;
        };
        let n = (x.len() / dim.max(1)).min(out.len() / k);
        let mut d = Disc::new(self.classes, top.n_hid);
        d.prepare(top);
        // The top layer's net inputs for a block of rows at a time (the
        // layers in `f32`, two rows at a time: their weights stay in L1), then the
        // block's posteriors, 16 frames across the lanes.
        let block = n.min(BLOCK_ROWS);
        let mut base = vec![0.0; block * top.n_hid];
        for (b0, o) in (0..n)
            .step_by(BLOCK_ROWS)
            .zip(out[..n * k].chunks_mut(BLOCK_ROWS * k))
        {
            let rows = (n - b0).min(BLOCK_ROWS);
            let base = &mut base[..rows * top.n_hid];
            rbm32::forward_rows(layers, &x[b0 * dim..(b0 + rows) * dim], base, top.n_hid);
            top.posterior_rows(base, &mut d, o, k);
        }
    }

    /// Mean-field label posterior: the layers in `f32`
    /// (`rbm32::Forward`), the posterior in `f64`
    /// (`Rbm::posterior_from_base`); a model whose layers do not chain
    /// takes the plain `f64` loops.
    pub fn rate_scores(&self, x: &[f64], out: &mut [f64]) {
        let Some(top) = self.rbms.last() else {
            out.iter_mut().for_each(|o| *o = 0.0);
            return;
        };
        let k = self.classes;
        let mut d = Disc::new(k, top.n_hid);
        d.prepare(top);
        match self.forward_layers(x.len()) {
            Some(layers) => {
                rbm32::forward_rows(layers, x, &mut d.base, top.n_hid);
                top.posterior_from_base(&mut d);
            }
            None => {
                let mut v = x.to_vec();
                for r in &self.rbms[..self.rbms.len() - 1] {
                    let mut h = vec![0.0; r.n_hid];
                    r.hid_prob(&v, &mut h);
                    v = h;
                }
                v.extend(std::iter::repeat_n(0.0, k));
                top.label_posterior(&v, &mut d);
            }
        }
        out[..k].copy_from_slice(&d.p);
    }

    /// Event-driven inference: spike counts of the label units.
    pub fn spiking_scores(&self, x: &[f64], rng: &mut ChaCha8Rng, out: &mut [f64]) {
        let k = self.classes;
        let p_in = (self.input_rate_hz * self.dt_ms / 1000.0).clamp(0.0, 1.0);
        let steps = (self.duration_ms / self.dt_ms).round().max(1.0) as usize;
        let n_layers = self.rbms.len();
        let mut vm: Vec<Vec<f64>> = self.rbms.iter().map(|r| vec![0.0; r.n_hid]).collect();
        let mut vlab = vec![0.0; k];
        let mut counts = vec![0.0; k];
        let mut spikes_in: Vec<usize> = Vec::with_capacity(x.len());
        let mut spikes_out: Vec<usize> = Vec::new();
        for _ in 0..steps {
            spikes_in.clear();
            for (i, &xi) in x.iter().enumerate() {
                if rng.random::<f64>() < xi * p_in {
                    spikes_in.push(i);
                }
            }
            for (l, r) in self.rbms.iter().enumerate() {
                // Drive per step: (W s + b p_in)/4 + p_in/2 → rate p_in·hardσ(z).
                spikes_out.clear();
                let vmem = &mut vm[l];
                for (j, vm_j) in vmem.iter_mut().enumerate().take(r.n_hid) {
                    let row = &r.w[j * r.n_vis..(j + 1) * r.n_vis];
                    let mut drive = r.b[j] * p_in;
                    for &i in &spikes_in {
                        drive += row[i];
                    }
                    let v = (*vm_j + drive * 0.25 + 0.5 * p_in).max(-1.0);
                    if v >= 1.0 {
                        *vm_j = v - 1.0;
                        spikes_out.push(j);
                    } else {
                        *vm_j = v;
                    }
                }
                if l + 1 == n_layers {
                    // Label units integrate c + Uᵀ s_top.
                    let nb = r.n_vis - k;
                    for (c, vl) in vlab.iter_mut().enumerate() {
                        let mut drive = r.a[nb + c] * p_in;
                        for &j in &spikes_out {
                            drive += r.w[j * r.n_vis + nb + c];
                        }
                        let v = (*vl + drive).max(-1.0);
                        if v >= 1.0 {
                            *vl = v - 1.0;
                            counts[c] += 1.0;
                        } else {
                            *vl = v;
                        }
                    }
                }
                std::mem::swap(&mut spikes_in, &mut spikes_out);
            }
        }
        let total: f64 = counts.iter().sum();
        for c in 0..k {
            out[c] = if total > 0.0 { counts[c] / total } else { 0.0 };
        }
    }
}

impl EdbnConfig {
    /// The feature keys this config states.
    pub fn keys(&self) -> FeatureKeys {
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
        if self.layers.is_empty() || self.layers.iter().any(|&n| n == 0 || n > 100_000) {
            c.push(ConfigError::key(
                "layers",
                format!(
                    "must list one or more layer sizes in 1..=100000, got {:?}",
                    self.layers
                ),
            ));
        }
        if self.epochs == 0 {
            c.push(ConfigError::key("epochs", "must be at least 1"));
        }
        if self.batch_size == 0 {
            c.push(ConfigError::key("batch_size", "must be at least 1"));
        }
        c.take(check_positive("learning_rate", self.learning_rate, ""));
        c.take(check_range("l2", self.l2, 0.0, 1e3, ""));
        c.take(check_range("discriminative", self.discriminative, 0.0, 1e3, ""));
        let rate = c.take(check_positive("input_rate_hz", self.input_rate_hz, "Hz"));
        c.take(check_positive("duration_ms", self.duration_ms, "ms"));
        let dt = c.take(check_positive("dt_ms", self.dt_ms, "ms"));
        if rate.is_some() && dt.is_some() && self.input_rate_hz * self.dt_ms / 1000.0 > 1.0 {
            c.push(ConfigError::key(
                "dt_ms",
                format!(
                    "input_rate_hz x dt_ms must be at most one spike per step, got {}",
                    self.input_rate_hz * self.dt_ms / 1000.0
                ),
            ));
        }
        c.finish()
    }

    /// Fits the DBN on a fold's training trials.
    pub fn fit_model(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<FittedModel, StageError> {
        self.check()?;
        let set = TrainSet::build(train, &self.keys())?;
        self.fit_set(set, &mut ctx.rng())
    }

    /// Fits the DBN on a fold's training vectors (the part of
    /// [`EdbnConfig::fit_model`] after feature extraction; `rng` is the fold's
    /// generator). The config must have passed [`EdbnConfig::check`].
    /// `benches/peers` times training through this.
    pub fn fit_set(&self, set: TrainSet, rng: &mut ChaCha8Rng) -> Result<FittedModel, StageError> {
        let k = set.classes.len();
        let mut data = set.x.clone();
        let mut dim = set.dim;
        let mut rbms = Vec::new();
        let mut log = TrainingLog {
            n_train: set.len(),
            ..TrainingLog::default()
        };
        for (l, &nh) in self.layers.iter().enumerate() {
            let top = l + 1 == self.layers.len();
            let n = set.len();
            if top {
                // Append the one-hot labels to the visible side.
                let mut aug = Vec::with_capacity(n * (dim + k));
                for i in 0..n {
                    aug.extend_from_slice(&data[i * dim..(i + 1) * dim]);
                    aug.extend((0..k).map(|c| f64::from(u8::from(c == set.y[i]))));
                }
                data = aug;
            }
            let nv = if top { dim + k } else { dim };
            let mut mean = vec![0.0; nv];
            for row in data.chunks_exact(nv) {
                mean.iter_mut().zip(row).for_each(|(m, x)| *m += x / n as f64);
            }
            let mut rbm = Rbm::new(nv, nh, if top { k } else { 0 }, &mean, rng);
            // Decided once per layer, from its training vectors.
            let sparse = mostly_zeros(&data);
            log.loss
                .extend(super::rbm32::train_pcd(&mut rbm, &data, sparse, self, rng));
            if !top {
                // The layer above learns from what inference will feed it.
                let mut next = vec![0.0; n * nh];
                rbm32::forward_rows(
                    &[rbm32::Forward::new(&rbm, nv, true, l == 0)],
                    &data,
                    &mut next,
                    nh,
                );
                data = next;
                dim = nh;
            }
            rbms.push(rbm);
        }
        if rbms
            .iter()
            .any(|r| r.w.iter().chain(&r.a).chain(&r.b).any(|v| !v.is_finite()))
        {
            return Err(StageError::new(
                "EDBN training diverged (non-finite weights); lower `learning_rate`",
            ));
        }
        Ok(FittedModel {
            format: MODEL_FORMAT,
            stage_type: "edbn".into(),
            classes: set.classes,
            features: set.spec,
            vote: self.vote,
            classifier: Box::new(Dbn {
                rbms,
                classes: k,
                inference: self.inference,
                input_rate_hz: self.input_rate_hz,
                duration_ms: self.duration_ms,
                dt_ms: self.dt_ms,
                net32: Net32::default(),
            }),
            log,
        })
    }
}

super::features::trained_baseline_stage!("edbn", EdbnConfig);

#[typetag::serde(name = "edbn")]
impl FrameClassifier for Dbn {
    fn frame_scores(&self, x: &[f64], rng: &mut ChaCha8Rng, out: &mut [f64]) {
        Dbn::frame_scores(self, x, rng, out)
    }

    fn scores_batch(&self, x: &[f64], dim: usize, _classes: usize, rng: &mut ChaCha8Rng, out: &mut [f64]) {
        Dbn::scores_batch(self, x, dim, rng, out)
    }

    fn kind(&self) -> &'static str {
        "edbn"
    }

    fn check_shape(&self, dim: usize, classes: usize) -> Result<(), String> {
        let d = self;
        want("the network's label units", d.classes, classes)?;
        if d.rbms.is_empty() {
            return Err("the network has no layer".into());
        }
        let mut fed = dim;
        for (l, r) in d.rbms.iter().enumerate() {
            let what = |x: &str| format!("layer {l}'s {x}");
            let vis = if l + 1 == d.rbms.len() { fed + classes } else { fed };
            want(&what("visible units"), r.n_vis, vis)?;
            want(
                &what("label units"),
                r.labels,
                if l + 1 == d.rbms.len() { classes } else { 0 },
            )?;
            let w = r
                .n_hid
                .checked_mul(r.n_vis)
                .ok_or_else(|| what("size overflows"))?;
            want(&what("weight count"), r.w.len(), w)?;
            want(&what("visible bias count"), r.a.len(), r.n_vis)?;
            want(&what("hidden bias count"), r.b.len(), r.n_hid)?;
            fed = r.n_hid;
        }
        for (what, x) in [
            ("input_rate_hz", d.input_rate_hz),
            ("duration_ms", d.duration_ms),
            ("dt_ms", d.dt_ms),
        ] {
            if !(x.is_finite() && x > 0.0) {
                return Err(format!("its spiking `{what}` is {x}, not a finite value > 0"));
            }
        }
        Ok(())
    }

    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use rand::SeedableRng;

    #[test]
    fn sigmoid_and_softplus_are_finite_everywhere() {
        for z in [-1e308, -800.0, -1.0, 0.0, 1.0, 800.0, 1e308] {
            let mut s = [z; 5];
            sigmoid_in_place(&mut s);
            assert!(s.iter().all(|s| (0.0..=1.0).contains(s)), "{z} -> {s:?}");
            let sp = softplus(z);
            assert!(sp.is_finite() && sp >= 0.0, "softplus({z}) = {sp}");
            if z.abs() > 50.0 {
                assert_eq!(sp, z.max(0.0));
            }
        }
        assert!((softplus(0.0) - std::f64::consts::LN_2).abs() < 1e-15);
    }

    /// A top RBM with `nb` data units, `nh` hidden and `k` labels, weights
    /// scaled by `scale`.
    fn top_rbm(nb: usize, nh: usize, k: usize, scale: f64, seed: u64) -> Rbm {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mean = vec![0.3; nb + k];
        let mut r = Rbm::new(nb + k, nh, k, &mean, &mut rng);
        r.w.iter_mut().for_each(|w| *w *= scale);
        r.b.iter_mut()
            .for_each(|b| *b = rng.random_range(-1.0..1.0) * scale);
        r
    }

    /// The posterior by its definition: softplus sums, then a softmax.
    fn posterior_by_definition(r: &Rbm, base: &[f64]) -> Vec<f64> {
        let nb = r.n_vis - r.labels;
        let mut f: Vec<f64> = (0..r.labels)
            .map(|y| {
                let s: f64 = (0..r.n_hid)
                    .map(|j| softplus(base[j] + r.w[j * r.n_vis + nb + y]))
                    .sum();
                r.a[nb + y] + s
            })
            .collect();
        softmax(&mut f);
        f
    }

    #[test]
    fn product_posterior_matches_the_softplus_sum() {
        // Small, moderate and large weights (the large ones push the
        // products through many renormalisations).
        for (scale, seed) in [(0.1, 1), (1.0, 2), (8.0, 3), (40.0, 4)] {
            let r = top_rbm(23, 30, 17, scale, seed);
            let mut d = Disc::new(17, 30);
            d.prepare(&r);
            let mut rng = ChaCha8Rng::seed_from_u64(seed + 10);
            for _ in 0..20 {
                let x: Vec<f64> = (0..23).map(|_| rng.random_range(0.0..1.0)).collect();
                r.label_posterior(&x, &mut d);
                let want = posterior_by_definition(&r, &d.base);
                for (p, q) in d.p.iter().zip(&want) {
                    assert!(
                        (p - q).abs() <= 1e-12 * q.max(1e-300) + 1e-300,
                        "{p} vs {q} (scale {scale})"
                    );
                }
                assert!((d.p.iter().sum::<f64>() - 1.0).abs() < 1e-12);
                // The e^o the discriminative gradient reads.
                for j in 0..30 {
                    for y in 0..17 {
                        let o = d.base[j] + r.w[j * r.n_vis + 23 + y];
                        let t = d.t[j * 17 + y];
                        assert!((t - o.exp()).abs() <= 1e-12 * o.exp(), "t {t} vs e^{o}");
                    }
                }
            }
        }
    }

    #[test]
    fn posterior_is_finite_for_huge_and_tiny_inputs() {
        let r = top_rbm(5, 7, 4, 1.0, 9);
        let mut d = Disc::new(4, 7);
        d.prepare(&r);
        for v in [
            1e300, -1e300, 1e4, -1e4, 400.0, -400.0, 299.0, -299.0, 1e-300, 0.0,
        ] {
            // One unit or every unit extreme.
            for all in [false, true] {
                d.base
                    .iter_mut()
                    .enumerate()
                    .for_each(|(j, b)| *b = if all || j == 2 { v } else { 0.1 * j as f64 });
                let base = d.base.clone();
                r.posterior_from_base(&mut d);
                assert!(d.p.iter().all(|p| p.is_finite() && *p >= 0.0), "{v}: {:?}", d.p);
                assert!((d.p.iter().sum::<f64>() - 1.0).abs() < 1e-12, "{v}: {:?}", d.p);
                let want = posterior_by_definition(&r, &base);
                for (p, q) in d.p.iter().zip(&want) {
                    assert!((p - q).abs() <= 1e-9, "{v}: {p} vs {q}");
                }
            }
        }
        // Label weights beyond e^±300 take the exact path.
        let mut big = r.clone();
        big.w.iter_mut().for_each(|w| *w *= 1e3);
        d.prepare(&big);
        assert!(!d.u_ok);
        d.base.iter_mut().for_each(|b| *b = 0.5);
        big.posterior_from_base(&mut d);
        assert!(d.p.iter().all(|p| p.is_finite()) && (d.p.iter().sum::<f64>() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn batch_scores_are_the_bits_of_frame_by_frame() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (dim, k) = (20, 6);
        let below = Rbm::new(dim, 12, 0, &vec![0.2; dim], &mut rng);
        let top = top_rbm(12, 9, k, 3.0, 6);
        let dbn = Dbn {
            rbms: vec![below, top],
            classes: k,
            inference: Inference::Rate,
            input_rate_hz: 200.0,
            duration_ms: 100.0,
            dt_ms: 1.0,
            net32: Net32::default(),
        };
        // Within one block, and across blocks with a ragged last one (the
        // narrow kernels from 64 rows, the posterior's groups of 16).
        for n in [37, 2 * BLOCK_ROWS + 37] {
            let x: Vec<f64> = (0..n * dim)
                .map(|i| {
                    if i % 3 == 0 {
                        0.0
                    } else {
                        rng.random_range(0.0..1.0)
                    }
                })
                .collect();
            let mut batch = vec![0.0; n * k];
            dbn.scores_batch(&x, dim, &mut rng, &mut batch);
            for (row, b) in x.chunks_exact(dim).zip(batch.chunks_exact(k)) {
                let mut one = vec![0.0; k];
                dbn.frame_scores(row, &mut rng, &mut one);
                assert_eq!(
                    b.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    one.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
                );
                assert!((one.iter().sum::<f64>() - 1.0).abs() < 1e-12);
            }
        }
    }

    /// The grouped posterior gives `posterior_from_base`'s bits frame by
    /// frame: groups on the fast path (weights small to huge, so the
    /// renormalisation interval differs from frame to frame), groups with
    /// a frame past `±EXP_SAFE` (row by row), a ragged end, saturated and
    /// tiny net inputs, AVX2 and SSE2.
    #[test]
    fn grouped_posterior_is_the_bits_of_frame_by_frame() {
        for (scale, seed, nh, k) in [
            (0.1, 1, 30, 17),
            (3.0, 2, 30, 17),
            (40.0, 3, 9, 6),
            (1.0, 4, 60, 5),
            (120.0, 5, 30, 17),
        ] {
            let r = top_rbm(11, nh, k, scale, seed);
            let mut rng = ChaCha8Rng::seed_from_u64(seed + 100);
            let n = 3 * POST_LANES + 5;
            let mut base: Vec<f64> = (0..n * nh)
                .map(|_| rng.random_range(-1.0..1.0) * scale * 4.0)
                .collect();
            // Saturated, tiny and off-the-fast-path values in some frames.
            base[3] = 299.9;
            base[nh + 1] = -299.9;
            base[2 * nh] = 1e-300;
            base[POST_LANES * nh + 2] = 450.0;
            base[(2 * POST_LANES + 1) * nh] = -1e6;
            for path in 0..3 {
                let run = || {
                    let mut d = Disc::new(k, nh);
                    d.prepare(&r);
                    let mut out = vec![f64::NAN; n * (k + 2)];
                    r.posterior_rows(&base, &mut d, &mut out, k + 2);
                    out
                };
                // AVX-512 where the CPU has it, AVX2, the baseline.
                let out = match path {
                    0 => run(),
                    1 => crate::wide::without_avx512(run),
                    _ => crate::wide::baseline_only(run),
                };
                let mut d = Disc::new(k, nh);
                d.prepare(&r);
                for (i, bi) in base.chunks_exact(nh).enumerate() {
                    d.base.copy_from_slice(bi);
                    r.posterior_from_base(&mut d);
                    let got = &out[i * (k + 2)..i * (k + 2) + k];
                    assert_eq!(
                        got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                        d.p.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                        "frame {i}, scale {scale}"
                    );
                    assert!(out[i * (k + 2) + k].is_nan());
                }
            }
        }
    }

    #[test]
    fn bad_keys_are_named() {
        let c = EdbnConfig {
            layers: vec![],
            ..EdbnConfig::default()
        };
        assert_eq!(c.check().unwrap_err().key.as_deref(), Some("layers"));
        let c = EdbnConfig {
            dt_ms: 10.0,
            ..EdbnConfig::default()
        };
        assert_eq!(c.check().unwrap_err().key.as_deref(), Some("dt_ms"));
    }
}
