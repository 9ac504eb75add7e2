//! Shared plumbing of the trained baselines (`ann`, `edbn`, `svm`, `random_forest`,
//! `knn`, `logistic`): the feature vectors they all see, the paper's
//! winner-take-all vote over a trial, the serializable fitted model with its
//! save/load and frame-by-frame streaming, and a synthetic data generator for
//! their tests and benches.
//!
//! # Features (one vector per selected frame)
//!
//! A trial's spike images are frames `I_0 .. I_{K-1}` of per-taxel counts. The
//! vector anchored at frame `k` stacks `N = frames` images spaced `step` frames
//! apart, oldest first: `x_k = [I_{k-(N-1)step}, ..., I_{k-step}, I_k]`, with
//! frames before the trial's start taken as empty (zeros). `N = 1` is the
//! paper's spatial input ("ANN (S)"), `N > 1` its spatiotemporal input.
//!
//! * `step = 0` (auto) spaces the stacked images by `round(window_ms / hop_ms)`
//!   frames, so that they tile time without overlap (100 ms windows at a 10 ms
//!   hop overlap by 90 %: ten consecutive frames share most of their spikes and
//!   stacking them would add little temporal information).
//! * Anchors are taken every `stride` frames (`0` = auto = `round(window/hop)`),
//!   at absolute frame indices `k ≡ 0 (mod stride)`, so that a stream and a
//!   batch pick the same frames. Overlapping frames are near-duplicates; a stride
//!   of one window keeps the information and cuts training and voting cost ~10x.
//! * Only *active* vectors are used, in training and in the vote: those whose raw
//!   spike total is at least `min_spikes` (and above zero). A frame without spikes
//!   says nothing about the edge; counting such frames would only teach the
//!   classifiers how long the silent holds last (which, with trial duration
//!   growing like `1/tan θ`, would leak the answer through timing rather than
//!   through the tactile pattern) and would add a constant bias to every vote.
//! * Normalisation: each active vector is divided by its largest count, so it lies
//!   in `[0, 1]` with a maximum of 1. The spatiotemporal *pattern* is kept, the
//!   overall rate (which varies with force, skin and encoder gain) is not. The
//!   `[0, 1]` range is what the RBMs' Bernoulli visible units need; the MLP and
//!   the classical classifiers (SVM, forest, k-NN, logistic) further standardise each feature ([`Standardizer`]).
//! * Training caps: a trial contributes at most `max_train_frames` active vectors,
//!   evenly spaced over its active ones (deterministic, no RNG), so that every
//!   trial weighs about the same whatever its duration (a 10° trial is ~6x longer
//!   than a 90° one) and training time is bounded. Consecutive anchors are one
//!   window apart, so a cap of 20-50 still spans a trial's whole crossing; the
//!   defaults per estimator (ANN 50, EDBN 30, k-NN/logistic 20, forest 15, SVM 8)
//!   are set so that the whole Table 2 graph (`graphs/paper/table2.toml`, 17 x 10
//!   trials, 10 folds) trains and evaluates in well under a minute on two cores.
//!   A capped trial's `take` vectors are the centres of `take` equal segments of
//!   its `n` active ones, `j = ⌊(2i + 1) n / (2 take)⌋`, *not* spaced from the
//!   first to the last: the first and last active vectors are the onset and
//!   offset of contact, one or two spikes each, and with both ends included
//!   they made 2 of every `take` training vectors. That was the SVM's accuracy
//!   "cliff" (`max_train_frames = 5`: 37.7° MAE on Table 2's front end, 8:
//!   1.7°; scikit-learn's `SVC` on the same 5 vectors gives the same 37.6°):
//!   near-empty vectors look alike in every class, the slowest class (10°,
//!   fewest spikes per window) owns that region of feature space, and at 40 %
//!   of the training set they made every test trial's sparse frames vote 10°,
//!   which outvoted the few informative frames of a fast (short) trial. With
//!   the segment centres, 5 gives 2.35° and 8 gives 0.15° (`palpate run` of
//!   table2.toml's front end with `svm` stages at `max_train_frames` 5 and 8;
//!   the ignored regression test `svm_cliff_at_five_vectors_per_trial_is_gone`
//!   runs it). Uncapped trials (`n ≤ max_train_frames`) use every active
//!   vector, as before; with `n ≤ 2·take` the last centre can still be the
//!   last vector. On Table 2 (`graphs/paper/table2.toml`, seed 1) the
//!   change moved SVM 1.71° → 0.15°, EDBN 2.09° → 1.91°, logistic 30.29° →
//!   28.38° and the forest 0.00° → 0.09° (together with their new solvers);
//!   ANN (S), ANN (ST) and k-NN stayed at 0.00°.
//!
//! # Vote (paper section 3.2)
//!
//! Each classifier gives per-frame class scores `p_k(c)` (softmax outputs, label
//! unit activity, vote shares). `vote = "winner"` is the paper's winner-take-all:
//! for each frame only the winning class `c*_k = argmax_c p_k(c)` collects its
//! activation, `S(c) = Σ_k [c = c*_k] p_k(c)`; `vote = "sum"` sums every class's
//! output, `S(c) = Σ_k p_k(c)`. The trial's answer is `argmax_c S(c)` (ties go to
//! the first class, i.e. the smallest angle); the reported scores are `S(c)`
//! divided by the number of frames used. A trial with no active frame is
//! answered "no edge" (`angle_deg = None`, every score 0), never NaN.
//!
//! # Save, load and stream
//!
//! [`FittedModel`] holds everything a prediction needs (classes, feature spec,
//! weights, standardisation) and is plain serde data: [`save_model`] /
//! [`load_model`] write and read it as JSON (f64 values round-trip exactly, so
//! a loaded model predicts the same bits). [`FittedModel::stream`] returns a
//! [`Streamer`] that takes one frame at a time and keeps the running vote; the
//! batch [`Model::predict`] takes the frames a stream would use, scores them in
//! one batch (`Classifier::scores_batch`, the same bits row by row) and votes
//! in the same order, so the two agree (except in `decision_time_ms`, which the batch caps at the
//! trial's end: a stream cannot know where the trial ends; see `estimate`).
//! A stage given a saved model (`model_in`, see [`super::saved`]) loads it
//! with [`load_model`], checks it ([`FittedModel::check`]) and predicts or
//! streams with it instead of fitting.

use palpate_core::output::write_atomic;
use palpate_core::{
    ClassScore, Estimate, FitContext, Item, Model, SpikeImages, StageError, TaxelLayout, TrialContext,
};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Poisson};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::path::Path;

/// How per-frame outputs are combined over a trial.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema, Default)]
#[serde(rename_all = "snake_case")]
pub enum Vote {
    /// The paper's winner-take-all: each frame's winning class collects its output.
    #[default]
    Winner,
    /// Every class collects its output of every frame.
    Sum,
}

/// The feature settings a fitted model was trained with (resolved: no "auto").
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FeatureSpec {
    /// Images stacked per vector (1 = spatial).
    pub frames: usize,
    /// Frames between stacked images.
    pub step: usize,
    /// Frames between anchors.
    pub stride: usize,
    /// Smallest raw spike total of a used vector.
    pub min_spikes: f64,
    /// Taxels per image.
    pub n_taxels: usize,
    /// Frame window of the training images, ms.
    pub window_ms: f64,
    /// Frame hop of the training images, ms.
    pub hop_ms: f64,
    /// The array the training images came from. A saved model applied to
    /// images of another taxel arrangement is refused (see
    /// [`super::saved`]); absent from models saved before it was recorded,
    /// which are then checked on the taxel count alone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layout: Option<palpate_core::TaxelLayout>,
}

/// The feature keys as a config states them (0 = auto for `step` and `stride`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FeatureKeys {
    /// Images per vector.
    pub frames: usize,
    /// Spacing of stacked images, frames; 0 = auto.
    pub step: usize,
    /// Spacing of anchors, frames; 0 = auto.
    pub stride: usize,
    /// Smallest spike total of a used vector.
    pub min_spikes: f64,
    /// Most vectors per training trial.
    pub max_train_frames: usize,
}

impl FeatureKeys {
    /// Checks the keys, naming the wrong one.
    pub fn check(&self) -> Result<(), palpate_core::ConfigError> {
        use palpate_core::{ConfigChecks, ConfigError};
        let mut c = ConfigChecks::new();
        if self.frames == 0 || self.frames > 1000 {
            c.push(ConfigError::key(
                "frames",
                format!("must be 1..=1000, got {}", self.frames),
            ));
        }
        if !(self.min_spikes.is_finite() && self.min_spikes >= 0.0) {
            c.push(ConfigError::key(
                "min_spikes",
                format!(
                    "must be a finite count >= 0, got {}",
                    palpate_core::fmt_num(self.min_spikes)
                ),
            ));
        }
        if self.max_train_frames == 0 {
            c.push(ConfigError::key("max_train_frames", "must be at least 1"));
        }
        c.finish()
    }

    /// Resolves the auto values against the training images.
    pub fn resolve(&self, images: &SpikeImages) -> FeatureSpec {
        let auto = (images.window_ms / images.hop_ms).round();
        let auto = if auto.is_finite() && auto >= 1.0 {
            auto as usize
        } else {
            1
        };
        FeatureSpec {
            frames: self.frames,
            step: if self.step == 0 { auto } else { self.step },
            stride: if self.stride == 0 { auto } else { self.stride },
            min_spikes: self.min_spikes,
            n_taxels: images.n_taxels(),
            window_ms: images.window_ms,
            hop_ms: images.hop_ms,
            layout: Some(images.layout.clone()),
        }
    }
}

impl FeatureSpec {
    /// Length of a feature vector.
    pub fn dim(&self) -> usize {
        self.frames * self.n_taxels
    }

    /// Frames a vector spans (the stream's memory).
    pub fn span(&self) -> usize {
        (self.frames - 1) * self.step + 1
    }

    /// Checks that `images` fit a model trained with this spec.
    pub fn check_images(&self, images: &SpikeImages, what: &str) -> Result<(), StageError> {
        if images.n_taxels() != self.n_taxels {
            return Err(StageError::new(format!(
                "{what}: images have {} taxels, the model was trained on {}",
                images.n_taxels(),
                self.n_taxels
            )));
        }
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1.0);
        if !close(images.window_ms, self.window_ms) || !close(images.hop_ms, self.hop_ms) {
            return Err(StageError::new(format!(
                "{what}: images have window {} ms / hop {} ms, the model was trained on {} ms / {} ms",
                images.window_ms, images.hop_ms, self.window_ms, self.hop_ms
            )));
        }
        if images.n_frames.checked_mul(self.n_taxels) != Some(images.counts.len()) {
            return Err(StageError::new(format!(
                "{what}: {} counts for {} frames of {} taxels",
                images.counts.len(),
                images.n_frames,
                self.n_taxels
            )));
        }
        Ok(())
    }

    /// Every active, normalised vector of a trial, with its anchor frame:
    /// the vectors [`FrameStream`] returns when the trial's frames are pushed
    /// in order (the same bits, tested), and its error for the first bad
    /// frame.
    pub fn trial_vectors(
        &self,
        images: &SpikeImages,
        what: &str,
    ) -> Result<Vec<(usize, Vec<f64>)>, StageError> {
        let mut out = Vec::new();
        self.for_each_vector(images, what, |k, v| out.push((k, v.to_vec())))?;
        Ok(out)
    }

    /// Calls `f(anchor, vector)` for every active, normalised vector of a
    /// trial, in order, as [`Self::trial_vectors`] lists them, without
    /// allocating one per frame: a fit builds its training set from every
    /// training trial, for every fold, and one allocation and copy per frame
    /// were most of that.
    pub fn for_each_vector(
        &self,
        images: &SpikeImages,
        what: &str,
        mut f: impl FnMut(usize, &[f64]),
    ) -> Result<(), StageError> {
        let mut v = vec![0.0; self.dim()];
        for k in self.active_anchors(images, what)? {
            self.vector_at(images, k, &mut v);
            f(k, &v);
        }
        Ok(())
    }

    /// The anchors of a trial's active vectors, in order: what
    /// [`Self::for_each_vector`] would visit, without building them.
    ///
    /// A vector is active when its spike total, summed over the stack in
    /// order as [`FrameStream::push`] sums it, is positive and at least
    /// `min_spikes`. That sum is a chain of `dim` dependent additions per
    /// anchor (most of a fit's feature building); instead, the total is
    /// first taken from per-frame sums, `s`. The counts are `>= 0`, so
    /// `s > 0` exactly when the in-order total is, and any two summation
    /// orders of `N` such terms agree within a relative `2 (N − 1) u`
    /// (`u = 2^-53`; Higham, *Accuracy and Stability of Numerical
    /// Algorithms*, §4.2): with a margin of `8 (N + 2) u`, `s (1 − margin) >=
    /// min_spikes` proves the in-order total is too, and `s (1 + margin) <
    /// min_spikes` proves it is not. Only an anchor between the two (a total
    /// within about `1e-13` of the threshold; on integer counts, one equal to
    /// it), or with `s` non-finite or below `1e-300` (where relative bounds
    /// fail), is summed in order. So the answer is the in-order one, always.
    pub fn active_anchors(&self, images: &SpikeImages, what: &str) -> Result<Vec<usize>, StageError> {
        self.check_images(images, what)?;
        let (sums, valid) = frame_sums(&images.counts, self.n_taxels);
        if !valid {
            self.check_counts(images, what)?;
        }
        let margin = 4.0 * (self.dim() as f64 + 2.0) * f64::EPSILON;
        let mut v = vec![0.0; self.dim()];
        Ok(self
            .anchors(images)
            .filter(|&k| {
                let mut s = 0.0;
                for j in 0..self.frames {
                    if let Some(m) = k.checked_sub((self.frames - 1 - j) * self.step) {
                        s += sums[m];
                    }
                }
                if s == 0.0 {
                    // Every count of the stack is 0: the total is 0.
                    return false;
                }
                if s.is_finite() && s >= 1e-300 {
                    if s * (1.0 - margin) >= self.min_spikes {
                        return true;
                    }
                    if s * (1.0 + margin) < self.min_spikes {
                        return false;
                    }
                }
                self.stack_at(images, k, &mut v).is_some()
            })
            .collect())
    }

    /// The frames a stream would anchor vectors at.
    fn anchors(&self, images: &SpikeImages) -> impl Iterator<Item = usize> + use<'_> {
        let stride = self.stride;
        (0..images.n_frames).filter(move |k| k.is_multiple_of(stride))
    }

    /// [`FrameStream::push`]'s check of the counts, frame by frame: the
    /// first count that is not finite and `>= 0` is the error. (Called only
    /// when [`frame_sums`] found one, to name it.)
    fn check_counts(&self, images: &SpikeImages, what: &str) -> Result<(), StageError> {
        (0..images.n_frames)
            .try_for_each(|k| check_frame(k, images.frame(k)))
            .map_err(|e| StageError::new(format!("{what}: {}", e.message)))
    }

    /// The raw stack anchored at frame `k` into `v` (`dim` values; images
    /// before frame 0 are zero), and its largest count if the vector is
    /// active: the values, sums and test of [`FrameStream::push`].
    fn stack_at(&self, images: &SpikeImages, k: usize, v: &mut [f64]) -> Option<f64> {
        let n = self.n_taxels;
        for j in 0..self.frames {
            // Image j of the stack is `(frames-1-j)*step` frames before the anchor.
            let back = (self.frames - 1 - j) * self.step;
            let dst = &mut v[j * n..(j + 1) * n];
            match k.checked_sub(back) {
                Some(m) => dst.copy_from_slice(images.frame(m)),
                None => dst.fill(0.0),
            }
        }
        let total: f64 = v.iter().sum();
        let max = v.iter().copied().fold(0.0, f64::max);
        if !(total > 0.0 && total >= self.min_spikes) || max <= 0.0 {
            return None;
        }
        Some(max)
    }

    /// The normalised vector anchored at frame `k` into `v`; false (and `v`
    /// unspecified) if it is not active.
    fn vector_at(&self, images: &SpikeImages, k: usize, v: &mut [f64]) -> bool {
        let Some(max) = self.stack_at(images, k, v) else {
            return false;
        };
        let inv = 1.0 / max;
        v.iter_mut().for_each(|x| *x *= inv);
        true
    }
}

/// Each frame's sum of counts (`n` a frame), and whether every count is
/// finite and `>= 0` (NaN fails both tests), in one pass over the counts.
///
/// Why one pass, and why in lanes: a fit builds its training set from every
/// training trial again for every fold and every estimator (~24 000 counts a
/// lab trial); checking the counts frame by frame, then summing each frame
/// in order (a chain of dependent additions), was ~90 % of a k-NN fit in a
/// graph. Each frame is summed in four lanes: any summation order is within
/// the margin [`FeatureSpec::active_anchors`] allows for, and the check is
/// an OR without a branch.
fn frame_sums(counts: &[f64], n: usize) -> (Vec<f64>, bool) {
    let mut sums = Vec::with_capacity(counts.len() / n.max(1));
    // A plain loop: an iterator adapter's `fold` may be compiled outside
    // the wide function (it was: SSE2 code, ~2 ns a count).
    let valid = crate::wide::with_avx2(
        #[inline(always)]
        || {
            let mut bad = false;
            for f in counts.chunks_exact(n.max(1)) {
                let mut a = [0.0f64; 4];
                let c = f.chunks_exact(4);
                let rest = c.remainder();
                for q in c {
                    for l in 0..4 {
                        bad |= !is_count(q[l]);
                        a[l] += q[l];
                    }
                }
                for (l, &x) in rest.iter().enumerate() {
                    bad |= !is_count(x);
                    a[l] += x;
                }
                sums.push((a[0] + a[1]) + (a[2] + a[3]));
            }
            !bad
        },
    );
    (sums, valid)
}

/// A finite count `>= 0` (NaN fails both tests). Both tests always run
/// (`&`, not `&&`), so a loop over counts has no branch and vectorises.
#[inline(always)]
#[allow(clippy::manual_range_contains)]
fn is_count(x: f64) -> bool {
    (x >= 0.0) & (x <= f64::MAX)
}

/// Frame `k`'s counts: the first that is not finite and `>= 0` is an error
/// naming the frame and taxel.
fn check_frame(k: usize, frame: &[f64]) -> Result<(), StageError> {
    match frame.iter().position(|c| !(c.is_finite() && *c >= 0.0)) {
        Some(t) => Err(StageError::new(format!(
            "frame {k}, taxel {t}: spike count {} is not a finite count >= 0",
            frame[t]
        ))),
        None => Ok(()),
    }
}

/// Builds feature vectors from frames pushed one at a time.
#[derive(Clone, Debug)]
pub struct FrameStream {
    spec: FeatureSpec,
    /// The last `span` frames, newest at the back.
    ring: VecDeque<Vec<f64>>,
    /// Index of the next frame.
    next: usize,
}

impl FrameStream {
    /// A stream at frame 0.
    pub fn new(spec: FeatureSpec) -> Self {
        FrameStream {
            ring: VecDeque::with_capacity(spec.span()),
            spec,
            next: 0,
        }
    }

    /// Index of the next frame to be pushed.
    pub fn frames_seen(&self) -> usize {
        self.next
    }

    /// Pushes frame `frames_seen()`; returns its normalised vector if it is an
    /// anchor and active. Errors on a wrong taxel count or a non-finite or
    /// negative count (naming the frame and taxel).
    pub fn push(&mut self, frame: &[f64]) -> Result<Option<Vec<f64>>, StageError> {
        let k = self.next;
        if frame.len() != self.spec.n_taxels {
            return Err(StageError::new(format!(
                "frame {k} has {} taxels, the model expects {}",
                frame.len(),
                self.spec.n_taxels
            )));
        }
        check_frame(k, frame)?;
        if self.ring.len() == self.spec.span() {
            let mut old = self.ring.pop_front().unwrap_or_default();
            old.clear();
            old.extend_from_slice(frame);
            self.ring.push_back(old);
        } else {
            self.ring.push_back(frame.to_vec());
        }
        self.next += 1;
        if !k.is_multiple_of(self.spec.stride) {
            return Ok(None);
        }
        let n = self.spec.n_taxels;
        let mut v = vec![0.0; self.spec.dim()];
        let len = self.ring.len();
        for j in 0..self.spec.frames {
            // Image j of the stack is `(frames-1-j)*step` frames before the anchor.
            let back = (self.spec.frames - 1 - j) * self.spec.step;
            if back < len {
                v[j * n..(j + 1) * n].copy_from_slice(&self.ring[len - 1 - back]);
            }
        }
        let total: f64 = v.iter().sum();
        let max = v.iter().copied().fold(0.0, f64::max);
        if !(total > 0.0 && total >= self.spec.min_spikes) || max <= 0.0 {
            return Ok(None);
        }
        let inv = 1.0 / max;
        v.iter_mut().for_each(|x| *x *= inv);
        Ok(Some(v))
    }
}

/// The classes of a training set: distinct true angles, sorted. Trials without
/// an angle are skipped. Fewer than two classes is an error.
pub fn classes_of(train: &[&Item]) -> Result<Vec<f64>, StageError> {
    let mut angles: Vec<f64> = train.iter().filter_map(|it| it.meta.label.angle_deg).collect();
    if let Some(a) = angles.iter().find(|a| !a.is_finite()) {
        return Err(StageError::new(format!("a training trial's true angle is {a}")));
    }
    angles.sort_by(f64::total_cmp);
    angles.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    if angles.len() < 2 {
        return Err(StageError::new(format!(
            "a trained estimator needs training trials of at least two classes (distinct `label.angle_deg`), got {} ({})",
            angles.len(),
            angles.iter().map(|a| format!("{a}°")).collect::<Vec<_>>().join(", ")
        )));
    }
    Ok(angles)
}

/// Index of `angle` in `classes`.
pub fn class_index(classes: &[f64], angle: f64) -> Option<usize> {
    classes.iter().position(|c| (c - angle).abs() < 1e-9)
}

/// The training vectors of a fold, row-major.
#[derive(Clone, Debug, Default)]
pub struct TrainSet {
    /// Vector length.
    pub dim: usize,
    /// `x[i*dim..(i+1)*dim]` is vector `i`.
    pub x: Vec<f64>,
    /// Class index of each vector.
    pub y: Vec<usize>,
    /// Training-trial number (position in the fold's labelled trials) of each vector.
    pub trial: Vec<usize>,
    /// Class index of each labelled training trial.
    pub trial_class: Vec<usize>,
    /// The classes (sorted angles).
    pub classes: Vec<f64>,
    /// The resolved feature spec.
    pub spec: FeatureSpec,
}

impl TrainSet {
    /// Number of vectors.
    pub fn len(&self) -> usize {
        self.y.len()
    }

    /// True when there is no vector.
    pub fn is_empty(&self) -> bool {
        self.y.is_empty()
    }

    /// Vector `i`.
    pub fn row(&self, i: usize) -> &[f64] {
        &self.x[i * self.dim..(i + 1) * self.dim]
    }

    /// Builds the training set of a fold. Errors: fewer than two classes, images of
    /// differing shape, or a class without any active vector.
    pub fn build(train: &[&Item], keys: &FeatureKeys) -> Result<TrainSet, StageError> {
        let classes = classes_of(train)?;
        let labelled: Vec<&Item> = train
            .iter()
            .copied()
            .filter(|it| it.meta.label.angle_deg.is_some())
            .collect();
        let first = labelled[0].payload.images()?;
        let spec = keys.resolve(first);
        if spec.n_taxels == 0 {
            return Err(StageError::new("training images have no taxel"));
        }
        let mut set = TrainSet {
            dim: spec.dim(),
            classes,
            spec,
            ..TrainSet::default()
        };
        for (t, item) in labelled.iter().enumerate() {
            let images = item.payload.images()?;
            let angle = item.meta.label.angle_deg.unwrap_or_default();
            let c = class_index(&set.classes, angle).unwrap_or_default();
            set.trial_class.push(c);
            let what = format!("training trial `{}`", item.meta.trial_id);
            // Only the vectors taken are built and normalised.
            let anchors = set.spec.active_anchors(images, &what)?;
            let n = anchors.len();
            let take = n.min(keys.max_train_frames);
            let mut v = vec![0.0; set.dim];
            for i in 0..take {
                // The centre of segment i of `take` equal segments (see the
                // module docs: the onset and offset ends are left out).
                let j = (2 * i + 1) * n / (2 * take);
                set.spec.vector_at(images, anchors[j], &mut v);
                set.x.extend_from_slice(&v);
                set.y.push(c);
                set.trial.push(t);
            }
        }
        let mut seen = vec![false; set.classes.len()];
        set.y.iter().for_each(|&c| seen[c] = true);
        if let Some(c) = seen.iter().position(|s| !s) {
            // Name the threshold: a `min_spikes` set too high, not the
            // trials, is the usual cause of a class with no frame.
            return Err(StageError::new(format!(
                "class {}° has no frame of at least `min_spikes` = {} spikes (and above zero) in its \
                 training trials; nothing to learn it from",
                set.classes[c],
                palpate_core::fmt_num(set.spec.min_spikes)
            )));
        }
        Ok(set)
    }

    /// Splits the training *trials* into (fit, validation) for early stopping:
    /// per class, `round(fraction * trials)` randomly chosen trials (none if the
    /// class has a single trial) go to validation. Splitting by trial, not by
    /// frame, keeps near-duplicate overlapping frames of one trial from landing
    /// on both sides. Returns vector indices.
    pub fn split_by_trial(&self, fraction: f64, rng: &mut ChaCha8Rng) -> (Vec<usize>, Vec<usize>) {
        let n_trials = self.trial_class.len();
        let mut is_val = vec![false; n_trials];
        if fraction > 0.0 {
            for c in 0..self.classes.len() {
                let mut trials: Vec<usize> = (0..n_trials).filter(|&t| self.trial_class[t] == c).collect();
                if trials.len() < 2 {
                    continue;
                }
                let k = ((fraction * trials.len() as f64).round() as usize).clamp(1, trials.len() - 1);
                rand::seq::SliceRandom::shuffle(trials.as_mut_slice(), rng);
                trials[..k].iter().for_each(|&t| is_val[t] = true);
            }
        }
        (0..self.len()).partition(|&i| !is_val[self.trial[i]])
    }
}

/// Per-feature standardisation `(x - mean) / sd` fitted on training vectors; a
/// feature with no spread (a dead taxel) gets `sd = 1`, so it maps to 0, not NaN.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Standardizer {
    /// Per-feature mean.
    pub mean: Vec<f64>,
    /// Per-feature `1 / sd`.
    pub inv_sd: Vec<f64>,
}

impl Standardizer {
    /// Fits on the rows `idx` of `set`.
    pub fn fit(set: &TrainSet, idx: &[usize]) -> Self {
        let d = set.dim;
        let n = idx.len().max(1) as f64;
        let mut mean = vec![0.0; d];
        let mut var = vec![0.0; d];
        // Column sums over the rows, four columns to an instruction inside
        // the AVX2 function instead of the baseline's two (the same
        // additions in the same order per column, so the same bits; timed
        // only with the k-NN build's kernels, docs/benches.md).
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                for &i in idx {
                    mean.iter_mut().zip(set.row(i)).for_each(|(m, x)| *m += x);
                }
                mean.iter_mut().for_each(|m| *m /= n);
                for &i in idx {
                    var.iter_mut()
                        .zip(set.row(i))
                        .zip(&mean)
                        .for_each(|((v, x), m)| *v += (x - m) * (x - m));
                }
            },
        );
        let inv_sd = var
            .iter()
            .map(|v| {
                let sd = (v / n).sqrt();
                if sd > 1e-9 {
                    1.0 / sd
                } else {
                    1.0
                }
            })
            .collect();
        Standardizer { mean, inv_sd }
    }

    /// Standardises `x` in place.
    pub fn apply(&self, x: &mut [f64]) {
        x.iter_mut()
            .zip(&self.mean)
            .zip(&self.inv_sd)
            .for_each(|((x, m), s)| *x = (*x - m) * s);
    }

    /// A standardised copy of the rows of `x` (row-major, as wide as the
    /// standardiser; a ragged tail is dropped).
    ///
    /// One pass, written straight into the new vector: a copy standardised
    /// in place read and wrote the batch twice (perf: the copy and the pass
    /// ~12 % of an ANN (ST) prediction of the peers test set). Written by
    /// zipped row slices into the vector's capacity, in vector code: with
    /// `extend` row by row that prediction took 0.665 ms, now 0.649 ms
    /// (docs/benches.md); the same operations per value.
    pub fn apply_rows(&self, x: &[f64]) -> Vec<f64> {
        let d = self.mean.len().max(1);
        // Columns past the shorter of the two vectors stay as they are, as
        // in [`Self::apply`].
        let s = self.mean.len().min(self.inv_sd.len());
        let (mean, inv_sd) = (&self.mean[..s], &self.inv_sd[..s]);
        let n = x.len() / d * d;
        // Not `vec![0.0; n]`: zeroed memory is fresh pages from the kernel
        // at every call, each faulted in.
        let mut z: Vec<f64> = Vec::with_capacity(n);
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                let out = &mut z.spare_capacity_mut()[..n];
                for (o, r) in out.chunks_exact_mut(d).zip(x.chunks_exact(d)) {
                    let (head, tail) = o.split_at_mut(s);
                    head.iter_mut()
                        .zip(&r[..s])
                        .zip(mean)
                        .zip(inv_sd)
                        .for_each(|(((o, x), m), s)| {
                            o.write((x - m) * s);
                        });
                    tail.iter_mut().zip(&r[s..]).for_each(|(o, x)| {
                        o.write(*x);
                    });
                }
            },
        );
        // SAFETY: the loop above wrote all `n` values (`n / d` rows of `d`).
        unsafe { z.set_len(n) };
        z
    }
}

/// The fitted per-frame classifier of a trained estimator: what a saved
/// model's `classifier` holds, tagged by `kind` (the stage type that fits it).
///
/// Open to plugins: a crate that adds a trained estimator implements this
/// trait for its fitted model with `#[typetag::serde(name = "<stage type>")]`
/// and returns it in a [`FittedModel`]; its models then vote, save, load
/// (`model_in`), check their shape and stream like the built-in ones, and
/// nothing here names them (the built-in kinds live in `ann`, `edbn` and
/// `classic`).
#[typetag::serde(tag = "kind")]
pub trait FrameClassifier: std::fmt::Debug + Send + Sync + std::any::Any {
    /// Per-frame class scores of a normalised feature vector (non-negative,
    /// larger is more likely). `rng` feeds stochastic inference (EDBN spiking).
    fn frame_scores(&self, x: &[f64], rng: &mut ChaCha8Rng, out: &mut [f64]);

    /// [`Self::frame_scores`] of every row of `x` (row-major, `dim` wide) into
    /// the rows of `out` (`classes` wide, so `out.len() / classes` rows), in
    /// row order (so stochastic inference draws from `rng` as row by row):
    /// the same bits as calling it row by row. The default does exactly
    /// that; a model with a faster batch path overrides it.
    fn scores_batch(&self, x: &[f64], dim: usize, classes: usize, rng: &mut ChaCha8Rng, out: &mut [f64]) {
        if dim == 0 || classes == 0 {
            return;
        }
        for (row, o) in x.chunks_exact(dim).zip(out.chunks_exact_mut(classes)) {
            self.frame_scores(row, rng, o);
        }
    }

    /// The stage type that fits this kind of classifier (`ann`, `edbn`,
    /// `svm`, `random_forest`, `knn`, `logistic`, or a plugin's): the `kind`
    /// tag of a saved model.
    fn kind(&self) -> &'static str;

    /// Checks that the classifier takes vectors of `dim` values and scores
    /// `classes` classes, and that every weight array and index agrees with
    /// its stated shape, so that a hand-edited or corrupted model file is an
    /// error here rather than a panic (an index out of range) when it predicts.
    fn check_shape(&self, dim: usize, classes: usize) -> Result<(), String>;

    /// The concrete model, for callers (and tests) that need it.
    fn as_any(&self) -> &dyn std::any::Any;
}

/// A fitted per-frame classifier of any kind.
pub type Classifier = Box<dyn FrameClassifier>;

/// `Ok` when `got == want`, else "`what` is `got`, expected `want`"
/// (the shape checks of [`FrameClassifier::check_shape`]).
pub(crate) fn want(what: &str, got: usize, want: usize) -> Result<(), String> {
    if got == want {
        Ok(())
    } else {
        Err(format!("{what} is {got}, expected {want}"))
    }
}

/// A standardiser fits `dim`-value features.
pub(crate) fn check_scaler(s: &Standardizer, dim: usize) -> Result<(), String> {
    want("the standardiser's mean length", s.mean.len(), dim)?;
    want("the standardiser's 1/sd length", s.inv_sd.len(), dim)
}

/// What training recorded, for reports and tests.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TrainingLog {
    /// Training loss per epoch (or per layer-epoch), in order.
    pub loss: Vec<f64>,
    /// Validation loss per epoch, where there is one.
    pub val_loss: Vec<f64>,
    /// Epoch whose weights were kept (early stopping).
    pub best_epoch: Option<usize>,
    /// Training vectors used.
    pub n_train: usize,
    /// Validation vectors used.
    pub n_val: usize,
}

/// A fitted baseline: everything a prediction needs, as plain serde data.
#[derive(Debug, Serialize, Deserialize)]
pub struct FittedModel {
    /// Format version of this file.
    pub format: u32,
    /// The stage type that trained it (`ann`, `edbn`, `svm`, ...).
    pub stage_type: String,
    /// Class angles, degrees, sorted.
    pub classes: Vec<f64>,
    /// Feature settings.
    pub features: FeatureSpec,
    /// How frames are combined.
    pub vote: Vote,
    /// The per-frame classifier.
    pub classifier: Classifier,
    /// Training record.
    pub log: TrainingLog,
}

/// Most frames a loaded model's stacked vector may span (see [`FittedModel::check`]).
pub const MAX_SPAN_FRAMES: usize = 1_000_000;

/// Largest model file [`load_model`] reads: 1 GiB. A hostile or mistaken
/// path (a recording, a device) must not be read whole into memory; the
/// largest built-in model, k-NN keeping its training vectors, is tens of MB
/// on the paper's data.
pub const MAX_MODEL_BYTES: u64 = 1 << 30;

/// Current [`FittedModel::format`].
pub const MODEL_FORMAT: u32 = 3;

impl FittedModel {
    /// A streaming estimator over this model; `seed` drives stochastic inference.
    pub fn stream(&self, seed: u64) -> Streamer<&FittedModel> {
        Streamer::new(self, seed)
    }

    /// [`Self::stream`] owning a share of the model, for a stream that
    /// outlives the borrow (a live stage's per-trial state).
    pub fn stream_shared(
        model: std::sync::Arc<FittedModel>,
        seed: u64,
    ) -> Streamer<std::sync::Arc<FittedModel>> {
        Streamer::new(model, seed)
    }

    /// Checks a loaded model before use: it was fitted by a stage of type
    /// `stage_type` (its `stage_type` and its classifier's kind), its classes
    /// are finite and increasing, its feature spec is usable, and its
    /// classifier's shape agrees with both. What is wrong, as a sentence.
    pub fn check(&self, stage_type: &str) -> Result<(), String> {
        let kind = self.classifier.kind();
        if self.stage_type != stage_type || kind != stage_type {
            return Err(format!(
                "a model fitted by a `{}` stage ({kind} classifier), not by a `{stage_type}` stage: give this stage type `{kind}` or load a `{stage_type}` model",
                self.stage_type
            ));
        }
        if self.classes.is_empty() {
            return Err("a model without classes".into());
        }
        if !self.classes.iter().all(|c| c.is_finite()) || !self.classes.windows(2).all(|w| w[0] < w[1]) {
            return Err(format!(
                "its classes {:?} are not finite, increasing angles",
                self.classes
            ));
        }
        let f = &self.features;
        if f.frames == 0 || f.frames > 1000 || f.step == 0 || f.stride == 0 || f.n_taxels == 0 {
            return Err(format!(
                "its feature spec (frames {}, step {}, stride {}, taxels {}) needs each at least 1 (frames at most 1000)",
                f.frames, f.step, f.stride, f.n_taxels
            ));
        }
        // A stream keeps the last `span` frames: bound it (10^6 frames is
        // 10^4 s at a 10 ms hop), and the vector length.
        let span = (f.frames - 1).checked_mul(f.step).and_then(|x| x.checked_add(1));
        if f.frames.checked_mul(f.n_taxels).is_none() || span.is_none_or(|s| s > MAX_SPAN_FRAMES) {
            return Err(format!(
                "its feature spec (frames {}, step {}) spans more than {MAX_SPAN_FRAMES} frames",
                f.frames, f.step
            ));
        }
        let usable = f.min_spikes.is_finite()
            && f.min_spikes >= 0.0
            && f.window_ms.is_finite()
            && f.window_ms > 0.0
            && f.hop_ms.is_finite()
            && f.hop_ms > 0.0;
        if !usable {
            return Err(format!(
                "its feature spec (min_spikes {}, window {} ms, hop {} ms) needs finite values, window and hop > 0",
                f.min_spikes, f.window_ms, f.hop_ms
            ));
        }
        self.classifier
            .check_shape(f.dim(), self.classes.len())
            .map_err(|e| {
                format!(
                    "its classifier does not fit its {} classes and {}-value features: {e}",
                    self.classes.len(),
                    f.dim()
                )
            })
    }

    /// Estimates a whole trial of images (by streaming every frame).
    pub fn predict_images(
        &self,
        images: &SpikeImages,
        seed: u64,
        what: &str,
    ) -> Result<Estimate, StageError> {
        // The frames a stream would use, in its order, scored in one batch and
        // then voted in that order: the same answer as streaming (tested).
        let mut anchors = Vec::new();
        let mut x = Vec::new();
        self.features.for_each_vector(images, what, |k, v| {
            anchors.push(k);
            x.extend_from_slice(v);
        })?;
        let classes = self.classes.len();
        let mut scores = vec![0.0; anchors.len() * classes];
        let mut rng: ChaCha8Rng = rand_chacha::rand_core::SeedableRng::seed_from_u64(seed);
        self.classifier
            .scores_batch(&x, self.features.dim(), classes, &mut rng, &mut scores);
        let mut acc = Accumulator::new(classes);
        acc.add_rows(&anchors, &scores, self.vote);
        Ok(acc.estimate(&self.classes, &self.features))
    }
}

impl Model for FittedModel {
    fn predict(&self, item: &Item, ctx: &TrialContext<'_>) -> Result<Estimate, StageError> {
        let images = item.payload.images()?;
        let e = self.predict_images(images, ctx.seed, &format!("trial `{}`", item.meta.trial_id))?;
        // A stream (and so `predict_images`) cannot know where the trial ends;
        // a whole trial's answer can: cap its decision time there (see the
        // decision-time rule in `estimate`).
        Ok(super::cap_decision_time(e, images))
    }
    fn saved_bytes(&self) -> Option<Result<Vec<u8>, StageError>> {
        Some(model_bytes(self))
    }
}

/// A fitted model as the JSON of its model file.
pub fn model_bytes(model: &FittedModel) -> Result<Vec<u8>, StageError> {
    serde_json::to_vec(model).map_err(|e| StageError::new(format!("serializing the model: {e}")))
}

/// Writes a fitted model as JSON (atomically).
pub fn save_model(model: &FittedModel, path: &Path) -> Result<(), StageError> {
    let json = model_bytes(model)?;
    write_atomic(path, &json).map_err(|e| StageError::new(format!("writing {}: {e}", path.display())))
}

/// Reads a fitted model written by [`save_model`].
pub fn load_model(path: &Path) -> Result<FittedModel, StageError> {
    // Capped while reading: a length check first missed devices and pipes,
    // which report none.
    let bytes = palpate_core::input::read_capped(path, MAX_MODEL_BYTES).map_err(|e| {
        StageError::new(format!(
            "reading {}: {e} (a model file may have at most {MAX_MODEL_BYTES} bytes)",
            path.display()
        ))
    })?;
    let m: FittedModel = serde_json::from_slice(&bytes)
        .map_err(|e| StageError::new(format!("{}: not a palpate baseline model: {e}", path.display())))?;
    if m.format != MODEL_FORMAT {
        return Err(StageError::new(format!(
            "{}: model format {} is not the supported {MODEL_FORMAT}",
            path.display(),
            m.format
        )));
    }
    Ok(m)
}

/// Saves a fold's model beside the run's reports when the config asks for it:
/// `<out_dir>/<stage>.fold<f>.model.json`.
pub fn maybe_save(
    model: &FittedModel,
    save: bool,
    out_dir: &Path,
    ctx: &FitContext<'_>,
) -> Result<(), StageError> {
    if !save {
        return Ok(());
    }
    std::fs::create_dir_all(out_dir)
        .map_err(|e| StageError::new(format!("creating {}: {e}", out_dir.display())))?;
    save_model(
        model,
        &out_dir.join(format!("{}.fold{}.model.json", ctx.stage_id, ctx.fold)),
    )
}

/// The stage glue every trained baseline's config shares, for a config type
/// with `check()`, `fit_model(train, ctx)`, `model_in` and `save_model`:
/// spike images in, estimates out; built as a [`TrainedEstimator`], or from
/// a saved model when `model_in` names one ([`super::saved::stage`]); and
/// registered under its stage type name.
macro_rules! trained_baseline_stage {
    ($name:literal, $config:ty) => {
        #[typetag::serde(name = $name)]
        impl palpate_core::StageConfig for $config {
            fn inputs(&self) -> palpate_core::InputSpec {
                palpate_core::InputSpec::one(palpate_core::PayloadKind::Images)
            }
            fn output(&self) -> Option<palpate_core::PayloadKind> {
                Some(palpate_core::PayloadKind::Estimates)
            }
            fn build(
                &self,
                ctx: &palpate_core::BuildContext,
            ) -> Result<palpate_core::Stage, palpate_core::ConfigError> {
                self.check()?;
                if let Some(stage) =
                    $crate::estimate::saved::stage($name, self.model_in.as_deref(), self.save_model, ctx)?
                {
                    return Ok(stage);
                }
                Ok($crate::estimate::features::TrainedEstimator::stage(
                    self, ctx,
                ))
            }
        }
        palpate_core::register_stage!($name, $config);
        impl $crate::estimate::features::FitBaseline for $config {
            fn fit_fold(
                &self,
                train: &[&palpate_core::Item],
                ctx: &palpate_core::FitContext<'_>,
            ) -> Result<$crate::estimate::features::FittedModel, palpate_core::StageError> {
                self.fit_model(train, ctx)
            }
            fn saves_models(&self) -> bool {
                self.save_model
            }
        }
    };
}
pub(crate) use trained_baseline_stage;

/// A baseline's config: fits one fold's [`FittedModel`] and says whether to save it.
pub trait FitBaseline: Clone + Send + Sync + 'static {
    /// Fits on one fold's training trials.
    fn fit_fold(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<FittedModel, StageError>;
    /// True when each fold's model is saved beside the run's reports.
    fn saves_models(&self) -> bool;
}

/// The runtime estimator every trained baseline shares: fits per fold (saving
/// the model when asked) and hands the fitted model to the runtime.
pub struct TrainedEstimator<C> {
    config: C,
    out_dir: std::path::PathBuf,
}

impl<C: FitBaseline> TrainedEstimator<C> {
    /// The runtime stage of `config`, whose models (if saved) go to the run's output directory.
    pub fn stage(config: &C, ctx: &palpate_core::BuildContext) -> palpate_core::Stage {
        palpate_core::Stage::Estimator(Box::new(TrainedEstimator {
            config: config.clone(),
            out_dir: ctx.out_dir.clone(),
        }))
    }
}

impl<C: FitBaseline> palpate_core::Estimator for TrainedEstimator<C> {
    fn trained(&self) -> bool {
        true
    }
    fn fit(&self, train: &[&Item], ctx: &FitContext<'_>) -> Result<Box<dyn Model>, StageError> {
        let m = self.config.fit_fold(train, ctx)?;
        maybe_save(&m, self.config.saves_models(), &self.out_dir, ctx)?;
        Ok(Box::new(m))
    }
    fn reusable(&self) -> bool {
        // A saved model is a file per point: fit again at every point.
        !self.config.saves_models()
    }
}

/// The running vote of a trial.
#[derive(Clone, Debug)]
pub struct Accumulator {
    totals: Vec<f64>,
    /// Per class: the largest per-frame score, and its frame in `peak_frame`
    /// (two arrays, so the per-frame update is a vectorised select).
    peak: Vec<f64>,
    peak_frame: Vec<usize>,
    used: usize,
    last_frame: Option<usize>,
}

impl Accumulator {
    /// An empty vote over `n` classes.
    pub fn new(n: usize) -> Self {
        Accumulator {
            totals: vec![0.0; n],
            peak: vec![f64::NEG_INFINITY; n],
            peak_frame: vec![0; n],
            used: 0,
            last_frame: None,
        }
    }

    /// [`Self::add`] of each frame `frames[i]` with the `i`-th row of
    /// `scores` (rows as wide as the vote's classes), in order: the same
    /// state as those calls one by one.
    ///
    /// With AVX-512 and at most 32 classes, `Self::add_rows512`: a row's
    /// test, maximum, first index of the maximum and peaks in a few vector
    /// operations, where the frame-by-frame form took ~13 ns a frame of 17
    /// classes (a tenth of an ANN (S) prediction of the peers test set).
    pub fn add_rows(&mut self, frames: &[usize], scores: &[f64], vote: Vote) {
        let n = self.totals.len().max(1);
        #[cfg(target_arch = "x86_64")]
        if n <= 32 && crate::wide::avx512() {
            // SAFETY: the CPU supports AVX-512 F/VL/DQ (checked above).
            unsafe { self.add_rows512(frames, scores, vote) };
            return;
        }
        crate::wide::with_avx2(
            #[inline(always)]
            || {
                for (&k, row) in frames.iter().zip(scores.chunks_exact(n)) {
                    self.add(k, row, vote);
                }
            },
        );
    }

    /// [`Self::add_rows`] for at most 32 classes, in up to four 512-bit
    /// vectors a row: the same state as [`Self::add`] row by row. A row
    /// with an infinite or NaN score is skipped (`vfpclasspd`); the maximum
    /// of a finite row does not depend on the order it is taken in, and
    /// the winner is the first class equal to it (`-0.0 == 0.0`, as
    /// [`argmax`]); a peak moves where the score is greater (ordered `>`).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,avx512f,avx512vl,avx512dq")]
    unsafe fn add_rows512(&mut self, frames: &[usize], scores: &[f64], vote: Vote) {
        use std::arch::x86_64::*;
        let n = self.totals.len();
        assert!(
            (1..=32).contains(&n) && self.peak.len() == n && self.peak_frame.len() == n,
            "a vote over {n} classes"
        );
        let chunks = n.div_ceil(8);
        let masks: [__mmask8; 4] =
            std::array::from_fn(|c| ((1u16 << n.saturating_sub(8 * c).min(8)) - 1) as __mmask8);
        let (tp, pp, fp) = (
            self.totals.as_mut_ptr(),
            self.peak.as_mut_ptr(),
            self.peak_frame.as_mut_ptr().cast::<i64>(),
        );
        const _: () = assert!(std::mem::size_of::<usize>() == 8);
        // The peaks, their frames and (for a sum) the totals stay in
        // registers over the rows: stored and reloaded per row, each masked
        // store stalled the next row's load (no forwarding from it).
        // SAFETY (these loads and the stores after the loop): lanes 8c.. < n
        // of each vector; `usize`s are 8-byte, read and written as the same bits.
        let mut peak: [__m512d; 4] =
            std::array::from_fn(|c| unsafe { _mm512_maskz_loadu_pd(masks[c], pp.add(8 * c)) });
        let mut frame: [__m512i; 4] =
            std::array::from_fn(|c| unsafe { _mm512_maskz_loadu_epi64(masks[c], fp.add(8 * c)) });
        let mut total: [__m512d; 4] =
            std::array::from_fn(|c| unsafe { _mm512_maskz_loadu_pd(masks[c], tp.add(8 * c)) });
        for (&k, row) in frames.iter().zip(scores.chunks_exact(n)) {
            let rp = row.as_ptr();
            let mut v = [_mm512_setzero_pd(); 4];
            let mut bad = 0u8;
            let mut top = _mm512_set1_pd(f64::NEG_INFINITY);
            for c in 0..chunks {
                // SAFETY: the unmasked lanes are entries 8c.. < n of the row.
                v[c] = unsafe { _mm512_mask_loadu_pd(top, masks[c], rp.add(8 * c)) };
                // QNaN, +inf, -inf, SNaN.
                bad |= _mm512_mask_fpclass_pd_mask::<0x99>(masks[c], v[c]);
                top = _mm512_max_pd(top, v[c]);
            }
            if bad != 0 {
                continue;
            }
            let kv = _mm512_set1_epi64(k as i64);
            for c in 0..chunks {
                let up = _mm512_mask_cmp_pd_mask::<_CMP_GT_OQ>(masks[c], v[c], peak[c]);
                peak[c] = _mm512_mask_mov_pd(peak[c], up, v[c]);
                frame[c] = _mm512_mask_mov_epi64(frame[c], up, kv);
            }
            match vote {
                Vote::Winner => {
                    let top = _mm512_set1_pd(_mm512_reduce_max_pd(top));
                    let mut hits = 0u32;
                    for c in 0..chunks {
                        let eq = _mm512_mask_cmp_pd_mask::<_CMP_EQ_OQ>(masks[c], v[c], top);
                        hits |= u32::from(eq) << (8 * c);
                    }
                    let w = hits.trailing_zeros() as usize;
                    self.totals[w] += row[w];
                }
                Vote::Sum => {
                    for c in 0..chunks {
                        total[c] = _mm512_add_pd(total[c], v[c]);
                    }
                }
            }
            self.used += 1;
            self.last_frame = Some(k);
        }
        for c in 0..chunks {
            // SAFETY: as for the loads above.
            unsafe {
                _mm512_mask_storeu_pd(pp.add(8 * c), masks[c], peak[c]);
                _mm512_mask_storeu_epi64(fp.add(8 * c), masks[c], frame[c]);
                // A winner vote added to `totals` itself.
                if vote == Vote::Sum {
                    _mm512_mask_storeu_pd(tp.add(8 * c), masks[c], total[c]);
                }
            }
        }
    }

    /// Adds frame `k`'s scores. Non-finite scores (never produced by the
    /// classifiers here) would poison the sums, so such a frame is skipped.
    /// Inlined, so [`Self::add_rows`]'s loop runs it with AVX2.
    #[inline(always)]
    pub fn add(&mut self, k: usize, scores: &[f64], vote: Vote) {
        // Without an early exit, so the test vectorises.
        if !scores.iter().fold(true, |ok, s| ok & s.is_finite()) {
            return;
        }
        let w = argmax(scores);
        match vote {
            Vote::Winner => self.totals[w] += scores[w],
            Vote::Sum => self.totals.iter_mut().zip(scores).for_each(|(t, s)| *t += s),
        }
        // Selects rather than branches: a class's peak moves at random frames.
        for ((p, f), &s) in self.peak.iter_mut().zip(&mut self.peak_frame).zip(scores) {
            let up = s > *p;
            *f = if up { k } else { *f };
            *p = if up { s } else { *p };
        }
        self.used += 1;
        self.last_frame = Some(k);
    }

    /// Frames used so far.
    pub fn used(&self) -> usize {
        self.used
    }

    /// The estimate so far.
    pub fn estimate(&self, classes: &[f64], spec: &FeatureSpec) -> Estimate {
        let n = self.used.max(1) as f64;
        let scores: Vec<ClassScore> = classes
            .iter()
            .zip(&self.totals)
            .map(|(&a, &t)| ClassScore {
                angle_deg: a,
                score: t / n,
            })
            .collect();
        if self.used == 0 || self.totals.iter().all(|t| *t <= 0.0) {
            return Estimate {
                scores,
                ..Estimate::default()
            };
        }
        let w = argmax(&self.totals);
        Estimate {
            angle_deg: Some(classes[w]),
            class_deg: Some(classes[w]),
            scores,
            best_frame: Some(self.peak_frame[w]),
            decision_time_ms: self.last_frame.map(|k| k as f64 * spec.hop_ms + spec.window_ms),
            uncertain: false,
        }
    }
}

/// Index of the largest value (first on ties; a NaN is never largest, and
/// a NaN first entry wins, as a scan that replaces on `>` gives).
///
/// Branch-free, in two passes, instead of that scan: its "new best" branch
/// is taken at random places in a row of class scores and mispredicts, and
/// with the vote it was a quarter of a logistic prediction (perf on
/// `benches/peers`). The largest value does not depend on the order it is
/// found in (four running maxima, each ignoring NaN as `>` does), and the
/// scan's answer is the first index equal to it (`-0.0 == 0.0`, as `>`
/// treats them).
pub fn argmax(v: &[f64]) -> usize {
    let Some(&first) = v.first() else { return 0 };
    if first.is_nan() {
        return 0;
    }
    argmax_from(v, first)
}

/// [`argmax`] of a `v` whose first entry `first` is not NaN, with SSE2
/// (part of x86-64): `maxpd(x, m)` is exactly the select `x > m ? x : m`
/// (NaN `x` keeps `m`), and the first entry equal to the largest is found
/// two at a time from a compare mask. The loops below compiled to scalar
/// compares and conditional moves (a sixth of an ANN prediction with the
/// vote, perf on `benches/peers`).
#[cfg(target_arch = "x86_64")]
#[inline]
fn argmax_from(v: &[f64], first: f64) -> usize {
    use std::arch::x86_64::*;
    let n = v.len();
    let p = v.as_ptr();
    // SAFETY: SSE2 is part of x86-64; every load reads below `n`.
    unsafe {
        let mut m0 = _mm_set1_pd(first);
        let mut m1 = m0;
        let mut i = 0;
        while i + 4 <= n {
            m0 = _mm_max_pd(_mm_loadu_pd(p.add(i)), m0);
            m1 = _mm_max_pd(_mm_loadu_pd(p.add(i + 2)), m1);
            i += 4;
        }
        let m = _mm_max_pd(m1, m0);
        let mut top = _mm_cvtsd_f64(_mm_max_sd(_mm_unpackhi_pd(m, m), m));
        for &x in &v[i..] {
            top = if x > top { x } else { top };
        }
        let t = _mm_set1_pd(top);
        let mut i = 0;
        while i + 2 <= n {
            let hit = _mm_movemask_pd(_mm_cmpeq_pd(_mm_loadu_pd(p.add(i)), t));
            if hit != 0 {
                return i + hit.trailing_zeros() as usize;
            }
            i += 2;
        }
        if i < n && v[i] == top {
            return i;
        }
    }
    n - 1
}

#[cfg(not(target_arch = "x86_64"))]
fn argmax_from(v: &[f64], first: f64) -> usize {
    let mut m = [first; 4];
    let chunks = v.chunks_exact(4);
    for &x in chunks.remainder() {
        m[0] = if x > m[0] { x } else { m[0] };
    }
    for c in chunks {
        for l in 0..4 {
            m[l] = if c[l] > m[l] { c[l] } else { m[l] };
        }
    }
    let a = if m[1] > m[0] { m[1] } else { m[0] };
    let b = if m[3] > m[2] { m[3] } else { m[2] };
    let top = if b > a { b } else { a };
    v.iter()
        .enumerate()
        .fold(
            usize::MAX,
            |best, (i, &x)| if x == top && i < best { i } else { best },
        )
        .min(v.len() - 1)
}

/// Frame-by-frame estimation with a fitted model (borrowed, `&FittedModel`,
/// or shared, `Arc<FittedModel>`).
pub struct Streamer<M> {
    model: M,
    frames: FrameStream,
    acc: Accumulator,
    rng: ChaCha8Rng,
    scratch: Vec<f64>,
}

impl<M: std::ops::Deref<Target = FittedModel>> Streamer<M> {
    /// A stream at frame 0; `seed` drives stochastic inference.
    pub fn new(model: M, seed: u64) -> Self {
        let n = model.classes.len();
        Streamer {
            frames: FrameStream::new(model.features.clone()),
            acc: Accumulator::new(n),
            rng: rand_chacha::rand_core::SeedableRng::seed_from_u64(seed),
            scratch: vec![0.0; n],
            model,
        }
    }

    /// Frames pushed so far.
    pub fn frames_seen(&self) -> usize {
        self.frames.frames_seen()
    }

    /// Pushes the next frame (one count per taxel). Returns this frame's class
    /// scores when it was used in the vote (an active anchor frame).
    pub fn push(&mut self, frame: &[f64]) -> Result<Option<&[f64]>, StageError> {
        let k = self.frames.frames_seen();
        let Some(x) = self.frames.push(frame)? else {
            return Ok(None);
        };
        self.model
            .classifier
            .frame_scores(&x, &mut self.rng, &mut self.scratch);
        self.acc.add(k, &self.scratch, self.model.vote);
        Ok(Some(&self.scratch))
    }

    /// Frames used in the vote so far.
    pub fn frames_used(&self) -> usize {
        self.acc.used()
    }

    /// The estimate from every frame pushed so far.
    pub fn estimate(&self) -> Estimate {
        self.acc.estimate(&self.model.classes, &self.model.features)
    }
}

/// Settings of [`synthetic_images`].
#[derive(Clone, Debug)]
pub struct SynthParams {
    /// Sliding speed, mm/s.
    pub speed_mm_s: f64,
    /// Still time before and after the crossing, ms.
    pub hold_ms: f64,
    /// Peak firing rate of a taxel on the edge, Hz.
    pub peak_hz: f64,
    /// Background firing rate, Hz.
    pub background_hz: f64,
    /// Spatial spread of the edge response (Gaussian SD across the edge), mm.
    pub spread_mm: f64,
    /// Frame window, ms.
    pub window_ms: f64,
    /// Frame hop, ms.
    pub hop_ms: f64,
}

impl SynthParams {
    /// The paper's protocol: 2 mm/s, 2 s holds, 100 ms / 10 ms frames: 1000 to
    /// 4000 frames per trial over 10..90°.
    pub fn paper() -> Self {
        SynthParams {
            speed_mm_s: 2.0,
            hold_ms: 2000.0,
            peak_hz: 60.0,
            background_hz: 0.5,
            spread_mm: 1.2,
            window_ms: 100.0,
            hop_ms: 10.0,
        }
    }

    /// A fast variant for debug tests: 20 mm/s, short holds (a few hundred frames).
    pub fn small() -> Self {
        SynthParams {
            speed_mm_s: 20.0,
            hold_ms: 200.0,
            peak_hz: 150.0,
            ..SynthParams::paper()
        }
    }
}

/// Synthetic spike images of an edge at `angle_deg` sweeping the paper's 4x4
/// array, for tests and benches of the trained baselines (not a physical model:
/// the scene and encoder stages do that). It follows the geometry convention of
/// `palpate_core::geometry`: the edge's offset along its normal falls at
/// `v·sinθ`; taxel `i` fires at `peak · g_i · exp(-(n·p_i - s(t))² / 2σ²)` plus a
/// background, with per-trial gains `g_i ∈ [0.6, 1.4]`, ±10 % speed and a random
/// start delay; spikes are Poisson per hop bin, summed over each window.
pub fn synthetic_images(angle_deg: f64, p: &SynthParams, rng: &mut ChaCha8Rng) -> SpikeImages {
    let layout = TaxelLayout::paper();
    let edge = palpate_core::geometry::Edge::new(angle_deg);
    let (lo, hi) = edge.footprint(&layout);
    let speed = p.speed_mm_s * rng.random_range(0.9..1.1);
    let ds = edge.normal_speed(speed).abs().max(1e-6); // mm/s along the normal
    let margin = 2.0 * p.spread_mm;
    let crossing_ms = (hi - lo + 2.0 * margin) / ds * 1000.0;
    let delay_ms = rng.random_range(0.0..0.25) * p.hold_ms;
    let total_ms = 2.0 * p.hold_ms + crossing_ms;
    let n_bins = (total_ms / p.hop_ms).ceil() as usize;
    let per_window = ((p.window_ms / p.hop_ms).round() as usize).max(1);
    let n_taxels = layout.len();
    let gains: Vec<f64> = (0..n_taxels).map(|_| rng.random_range(0.6..1.4)).collect();
    let offsets: Vec<f64> = layout.positions().iter().map(|&q| edge.offset(q)).collect();
    let mut bins = vec![0.0; n_bins * n_taxels];
    for b in 0..n_bins {
        let t_ms = (b as f64 + 0.5) * p.hop_ms;
        let moving_ms = (t_ms - p.hold_ms - delay_ms).clamp(0.0, crossing_ms);
        let s = hi + margin - ds * moving_ms / 1000.0;
        for i in 0..n_taxels {
            let d = offsets[i] - s;
            let rate =
                p.peak_hz * gains[i] * (-d * d / (2.0 * p.spread_mm * p.spread_mm)).exp() + p.background_hz;
            let lambda = rate * p.hop_ms / 1000.0;
            bins[b * n_taxels + i] = match Poisson::new(lambda) {
                Ok(d) => d.sample(rng),
                Err(_) => 0.0,
            };
        }
    }
    let n_frames = n_bins.saturating_sub(per_window - 1);
    let mut counts = vec![0.0; n_frames * n_taxels];
    for k in 0..n_frames {
        for w in 0..per_window {
            for i in 0..n_taxels {
                counts[k * n_taxels + i] += bins[(k + w) * n_taxels + i];
            }
        }
    }
    SpikeImages {
        layout,
        window_ms: p.window_ms,
        hop_ms: p.hop_ms,
        n_frames,
        counts,
    }
}

/// A labelled synthetic data set: `reps` trials of each angle, as items whose
/// `group` is the repetition number (the LOOCV key). Trial `r` of angle `a` is
/// seeded from `(seed, a, r)`, so sets of any size agree on shared trials.
pub fn synthetic_items(angles: &[f64], reps: usize, p: &SynthParams, seed: u64) -> Vec<Item> {
    use palpate_core::{Label, Payload, Stimulus, TrialMeta};
    use std::sync::Arc;
    let mut items = Vec::new();
    for r in 0..reps {
        for &a in angles {
            let id = format!("edge-{a}deg-r{r:02}");
            let mut rng: ChaCha8Rng = rand_chacha::rand_core::SeedableRng::seed_from_u64(
                palpate_core::derive_seed(seed, &["synth", &id]),
            );
            let images = synthetic_images(a, p, &mut rng);
            items.push(Item {
                meta: Arc::new(TrialMeta {
                    trial_id: id,
                    index: items.len(),
                    label: Label {
                        stimulus: Stimulus::Edge,
                        angle_deg: Some(a),
                    },
                    group: r,
                    ..TrialMeta::default()
                }),
                payload: Payload::from(images),
            });
        }
    }
    items
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The copy-then-standardise definition [`Standardizer::apply_rows`] must match.
    fn apply_rows_by_copy(s: &Standardizer, x: &[f64]) -> Vec<f64> {
        let d = s.mean.len().max(1);
        let mut z = x[..x.len() / d * d].to_vec();
        z.chunks_exact_mut(d).for_each(|r| s.apply(r));
        z
    }

    proptest! {
        /// One pass gives the bits of a copy standardised row by row, also
        /// with a ragged tail, mean and scale of different lengths (the
        /// columns past the shorter kept as they are) and an empty scaler.
        #[test]
        fn apply_rows_gives_the_bits_of_each_row_standardised(
            mean in prop::collection::vec(-1e3f64..1e3, 0..6),
            inv_sd in prop::collection::vec(1e-3f64..1e3, 0..6),
            x in prop::collection::vec(prop_oneof![-1e6f64..1e6, Just(f64::NAN), Just(-0.0)], 0..40),
        ) {
            let s = Standardizer { mean, inv_sd };
            let got = s.apply_rows(&x);
            let want = apply_rows_by_copy(&s, &x);
            prop_assert_eq!(got.len(), want.len());
            for (g, w) in got.iter().zip(&want) {
                prop_assert!(g.to_bits() == w.to_bits() || (g.is_nan() && w.is_nan()), "{} vs {}", g, w);
            }
        }
    }

    /// The definition [`argmax`] must match: a scan replacing on `>`.
    fn argmax_scan(v: &[f64]) -> usize {
        let mut best = 0;
        for (i, x) in v.iter().enumerate() {
            if *x > v[best] {
                best = i;
            }
        }
        best
    }

    /// Scores drawn from a few values (so ties are common), with NaN, ±0 and ±inf.
    fn score() -> impl Strategy<Value = f64> {
        prop_oneof![
            4 => prop::sample::select(vec![0.1, 0.25, 0.5, 1.0]),
            4 => -1e3f64..1e3,
            1 => prop::sample::select(vec![f64::NAN, 0.0, -0.0, f64::INFINITY, f64::NEG_INFINITY]),
        ]
    }

    proptest! {
        /// [`Accumulator::add_rows`] leaves the state that [`Accumulator::add`]
        /// frame by frame leaves (totals, peaks and their frames, frames
        /// used, last frame), bit for bit, for 1 to 40 classes (the
        /// AVX-512 form up to 32, the other above), both votes, ties, ±0,
        /// and rows with NaN or infinite scores; with AVX-512 off too.
        #[test]
        fn add_rows_is_add_frame_by_frame(
            n in 1usize..41,
            rows in prop::collection::vec(prop::collection::vec(score(), 40), 0..12),
            sum in any::<bool>(),
            first in 0usize..1000,
        ) {
            let vote = if sum { Vote::Sum } else { Vote::Winner };
            let scores: Vec<f64> = rows.iter().flat_map(|r| r[..n].iter().copied()).collect();
            let frames: Vec<usize> = (0..rows.len()).map(|i| first + 3 * i).collect();
            let mut want = Accumulator::new(n);
            for (&k, r) in frames.iter().zip(scores.chunks_exact(n)) {
                want.add(k, r, vote);
            }
            let bits = |a: &Accumulator| {
                (
                    a.totals.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                    a.peak.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                    a.peak_frame.clone(),
                    a.used,
                    a.last_frame,
                )
            };
            for no512 in [false, true] {
                let mut got = Accumulator::new(n);
                if no512 {
                    crate::wide::without_avx512(|| got.add_rows(&frames, &scores, vote));
                } else {
                    got.add_rows(&frames, &scores, vote);
                }
                prop_assert_eq!(bits(&got), bits(&want), "no512 {}", no512);
            }
        }
    }

    /// Counts of a 4x4 image sequence: mostly 0 (so vectors near the
    /// activity threshold are common), small integers, now and then a bad
    /// value (NaN, -1, inf) that both paths must reject at the same frame.
    fn counts(bad: bool) -> impl Strategy<Value = Vec<f64>> {
        let value = if bad {
            prop_oneof![
                20 => Just(0.0),
                10 => (0u8..4).prop_map(f64::from),
                1 => prop::sample::select(vec![f64::NAN, -1.0, f64::INFINITY]),
            ]
            .boxed()
        } else {
            // Integer counts (sums exact in any order, totals often equal to
            // the threshold) and fractional ones (sums that round).
            prop_oneof![
                6 => Just(0.0),
                2 => (0u8..4).prop_map(f64::from),
                1 => (0u32..1000).prop_map(|x| f64::from(x) / 7.0),
                1 => prop::sample::select(vec![0.1, 0.2, 0.7, 1e-310, 1e300]),
            ]
            .boxed()
        };
        (0usize..40).prop_flat_map(move |frames| prop::collection::vec(value.clone(), frames * 16))
    }

    /// A count that is not finite and `>= 0`, anywhere in a trial (the last
    /// of several frames; with 9 taxels, in the values past whole vector
    /// chunks), is the batch path's error, naming the frame and taxel as the
    /// stream's does; a trial of valid counts (zeros, subnormals, huge, -0)
    /// passes.
    #[test]
    fn bad_counts_are_the_streams_error_in_the_batch_path() {
        let grid = |rows, cols| TaxelLayout::Grid {
            rows,
            cols,
            pitch_mm: 3.0,
            taxel_mm: 2.0,
        };
        for (layout, n) in [(TaxelLayout::paper(), 16), (grid(3, 3), 9)] {
            let spec = FeatureSpec {
                frames: 2,
                step: 1,
                stride: 1,
                min_spikes: 1.0,
                n_taxels: n,
                window_ms: 100.0,
                hop_ms: 10.0,
                layout: None,
            };
            let images = |counts: Vec<f64>| SpikeImages {
                layout: layout.clone(),
                window_ms: 100.0,
                hop_ms: 10.0,
                n_frames: counts.len() / n,
                counts,
            };
            let mut ok = vec![1.0; 5 * n];
            ok[3] = 0.0;
            ok[n + 2] = 1e-310;
            ok[4 * n] = 1e300;
            ok[2 * n + 1] = -0.0;
            assert!(spec.active_anchors(&images(ok.clone()), "t").is_ok());
            for (at, bad) in [
                (5 * n - 1, f64::NAN),
                (5 * n - 2, -1.0),
                (n, f64::INFINITY),
                (0, f64::NEG_INFINITY),
                (3 * n + 4, -0.5),
            ] {
                let mut c = ok.clone();
                c[at] = bad;
                let want = format!(
                    "t: frame {}, taxel {}: spike count {bad} is not a finite count >= 0",
                    at / n,
                    at % n
                );
                let got = spec
                    .active_anchors(&images(c.clone()), "t")
                    .err()
                    .map(|e| e.message);
                assert_eq!(got.as_deref(), Some(want.as_str()), "count {bad} at {at}");
                let mut stream = FrameStream::new(spec.clone());
                let streamed = (0..5).find_map(|k| stream.push(&c[k * n..(k + 1) * n]).err());
                assert!(
                    streamed.is_some_and(|e| want.ends_with(&e.message)),
                    "the stream's error"
                );
            }
        }
    }

    /// A total whose in-order sum and per-frame sums round apart, with the
    /// threshold between them: `1 + 1e-16 + 1e-16` is 1 summed in order but
    /// `1 + 2e-16 = 1 + 2^-52` summed per frame. The in-order answer
    /// (inactive) must win; a fast path trusting the per-frame sum says
    /// active.
    #[test]
    fn a_total_on_the_threshold_is_decided_in_order() {
        let spec = FeatureSpec {
            frames: 2,
            step: 1,
            stride: 1,
            min_spikes: 1.0 + f64::EPSILON,
            n_taxels: 16,
            window_ms: 100.0,
            hop_ms: 10.0,
            layout: None,
        };
        let mut counts = vec![0.0; 2 * 16];
        counts[0] = 1.0;
        counts[16] = 1e-16;
        counts[17] = 1e-16;
        let images = SpikeImages {
            layout: TaxelLayout::paper(),
            window_ms: 100.0,
            hop_ms: 10.0,
            n_frames: 2,
            counts,
        };
        let mut stream = FrameStream::new(spec.clone());
        assert_eq!(stream.push(images.frame(0)).ok(), Some(None));
        assert_eq!(stream.push(images.frame(1)).ok(), Some(None));
        assert_eq!(spec.active_anchors(&images, "t").ok(), Some(vec![]));
        // Just below: both agree it is active.
        let spec = FeatureSpec {
            min_spikes: 1.0,
            ..spec
        };
        assert_eq!(spec.active_anchors(&images, "t").ok(), Some(vec![0, 1]));
    }

    proptest! {
        /// The batch paths (`trial_vectors`, `active_anchors`) give the
        /// vectors, anchors and first error that streaming the frames one by
        /// one gives, bit for bit, for any stack, step, stride and threshold.
        #[test]
        fn batch_vectors_are_the_streams_bits(
            counts in prop_oneof![counts(false), counts(true)],
            frames in 1usize..4,
            step in 1usize..4,
            stride in 1usize..4,
            min_spikes in prop::sample::select(vec![0.0, 1.0, 2.5, 6.0, 0.3, 1.0 / 3.0, 1e-310, 0.1 + 0.2]),
        ) {
            let spec = FeatureSpec {
                frames,
                step,
                stride,
                min_spikes,
                n_taxels: 16,
                window_ms: 100.0,
                hop_ms: 10.0,
                layout: None,
            };
            let images = SpikeImages {
                layout: TaxelLayout::paper(),
                window_ms: 100.0,
                hop_ms: 10.0,
                n_frames: counts.len() / 16,
                counts,
            };
            let mut stream = FrameStream::new(spec.clone());
            let mut streamed = Ok(Vec::new());
            for k in 0..images.n_frames {
                match stream.push(images.frame(k)) {
                    Ok(Some(v)) => {
                        if let Ok(s) = &mut streamed {
                            s.push((k, v.iter().map(|x| x.to_bits()).collect::<Vec<_>>()));
                        }
                    }
                    Ok(None) => {}
                    Err(e) => {
                        streamed = Err(format!("t: {}", e.message));
                        break;
                    }
                }
            }
            let batch = spec
                .trial_vectors(&images, "t")
                .map(|vs| vs.into_iter().map(|(k, v)| (k, v.iter().map(|x| x.to_bits()).collect())).collect())
                .map_err(|e| e.message);
            prop_assert_eq!(&batch, &streamed);
            let anchors = spec.active_anchors(&images, "t").map_err(|e| e.message);
            prop_assert_eq!(anchors, streamed.map(|s| s.into_iter().map(|(k, _)| k).collect::<Vec<_>>()));
        }

        #[test]
        fn argmax_is_the_first_largest_as_a_scan_finds_it(v in prop::collection::vec(score(), 0..40)) {
            prop_assert_eq!(argmax(&v), argmax_scan(&v));
        }
    }

    /// A classifier no built-in stage names, as a plugin would add one:
    /// nearest centre, score `1 / (1 + squared distance)`.
    #[derive(Debug, Serialize, Deserialize)]
    struct NearestCentre {
        centres: Vec<Vec<f64>>,
    }

    #[typetag::serde(name = "test_nearest_centre")]
    impl FrameClassifier for NearestCentre {
        fn frame_scores(&self, x: &[f64], _rng: &mut ChaCha8Rng, out: &mut [f64]) {
            for (o, c) in out.iter_mut().zip(&self.centres) {
                let d: f64 = x.iter().zip(c).map(|(a, b)| (a - b) * (a - b)).sum();
                *o = 1.0 / (1.0 + d);
            }
        }
        fn kind(&self) -> &'static str {
            "test_nearest_centre"
        }
        fn check_shape(&self, dim: usize, classes: usize) -> Result<(), String> {
            want("centres", self.centres.len(), classes)?;
            self.centres
                .iter()
                .try_for_each(|c| want("a centre's length", c.len(), dim))
        }
        fn as_any(&self) -> &dyn std::any::Any {
            self
        }
    }

    #[test]
    fn a_plugin_classifier_saves_loads_checks_and_votes_like_a_built_in_one() {
        let model = FittedModel {
            format: MODEL_FORMAT,
            stage_type: "test_nearest_centre".into(),
            classes: vec![30.0, 60.0],
            features: FeatureSpec {
                frames: 1,
                step: 1,
                stride: 1,
                min_spikes: 0.0,
                n_taxels: 2,
                window_ms: 100.0,
                hop_ms: 10.0,
                layout: None,
            },
            vote: Vote::Winner,
            classifier: Box::new(NearestCentre {
                centres: vec![vec![1.0, 0.0], vec![0.0, 1.0]],
            }),
            log: TrainingLog::default(),
        };
        model.check("test_nearest_centre").unwrap();
        let wrong = model.check("ann").unwrap_err();
        assert!(wrong.contains("test_nearest_centre classifier"), "{wrong}");
        let path = std::env::temp_dir().join(format!("palpate-plugin-model-{}.json", std::process::id()));
        save_model(&model, &path).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(
            text.contains("\"kind\": \"test_nearest_centre\"")
                || text.contains("\"kind\":\"test_nearest_centre\"")
        );
        let loaded = load_model(&path).unwrap();
        let _ = std::fs::remove_file(&path);
        loaded.check("test_nearest_centre").unwrap();
        // Frames lit on the second taxel vote for the second class, through the
        // default batch path as through the stream.
        let mut s = loaded.stream(1);
        for _ in 0..3 {
            s.push(&[0.0, 4.0]).unwrap();
        }
        assert_eq!(s.estimate().angle_deg, Some(60.0));
        let mut rng: ChaCha8Rng = rand_chacha::rand_core::SeedableRng::seed_from_u64(1);
        let mut out = vec![0.0; 4];
        loaded
            .classifier
            .scores_batch(&[1.0, 0.0, 0.0, 1.0], 2, 2, &mut rng, &mut out);
        assert!(out[0] > out[1] && out[3] > out[2], "{out:?}");
        // A centre of the wrong length is a shape error, not a panic.
        let bad = FittedModel {
            classifier: Box::new(NearestCentre {
                centres: vec![vec![1.0], vec![0.0, 1.0]],
            }),
            ..loaded
        };
        assert!(bad
            .check("test_nearest_centre")
            .unwrap_err()
            .contains("a centre's length"));
    }

    #[test]
    fn capped_trials_contribute_segment_centres_not_their_ends() {
        let items = synthetic_items(&[20.0, 70.0], 2, &SynthParams::small(), 4);
        let refs: Vec<&Item> = items.iter().collect();
        let keys = FeatureKeys {
            frames: 1,
            step: 0,
            stride: 0,
            min_spikes: 1.0,
            max_train_frames: 5,
        };
        let set = TrainSet::build(&refs, &keys).expect("set");
        let mut long = 0;
        for (t, item) in refs.iter().enumerate() {
            let all = set
                .spec
                .trial_vectors(item.payload.images().expect("images"), "t")
                .expect("vectors");
            let n = all.len();
            assert!(n > 5, "the test needs capped trials ({n} vectors)");
            let rows: Vec<&[f64]> = (0..set.len())
                .filter(|&i| set.trial[i] == t)
                .map(|i| set.row(i))
                .collect();
            assert_eq!(rows.len(), 5);
            for (i, row) in rows.iter().enumerate() {
                let j = (2 * i + 1) * n / 10;
                assert_eq!(
                    *row,
                    &all[j].1[..],
                    "vector {i} of trial {t} is active vector {j} of {n}"
                );
            }
            // With more than two vectors per segment, neither the onset nor the offset vector.
            if n > 10 {
                long += 1;
                assert!((1..n - 1).contains(&(n / 10)) && (1..n - 1).contains(&(9 * n / 10)));
            }
        }
        assert!(long > 0, "no trial with more than 10 active vectors");
        // An uncapped trial keeps every active vector.
        let keys = FeatureKeys {
            max_train_frames: 100_000,
            ..keys
        };
        let all = TrainSet::build(&refs, &keys).expect("set");
        let n0 = set
            .spec
            .trial_vectors(refs[0].payload.images().expect("images"), "t")
            .expect("vectors")
            .len();
        assert_eq!(all.trial.iter().filter(|&&t| t == 0).count(), n0);
    }
}
