//! Orientation estimators: WSS and trained baselines.
//!
//! # Decision time
//!
//! Every estimator sets [`Estimate::decision_time_ms`](palpate_core::Estimate)
//! the same way: the palpation its answer depends on, in ms from the trial's
//! start, i.e. the end of the data of the last frame the answer used. Frame `k`
//! covers `[k·hop, k·hop + window)`, so an answer that used frames `0..=k`
//! needed `k·hop + window` ms of palpation, but never more than the trial
//! holds: the binner emits frames while `k·hop < duration`, so the images of a
//! trial of `n` frames are known to cover `(n - 1)·hop` ms (the trial ends
//! within the following hop), and the decision time is
//! `min(k·hop + window, (n - 1)·hop)` ([`decision_time_ms`]). Taking the lower
//! bound keeps the decision time of a cropped trial (`crop`, `truncate = true`)
//! at or before the cut.
//!
//! * WSS, batch: the answer `argmax_θ max_k WSS_θ(k)` depends on every frame
//!   (the maximum runs over every alignment, and the 1 - SR weights over every
//!   frame's count), so it needs the whole trial.
//! * WSS with `stop_margin`: the frame at which it stopped.
//! * Trained baselines (ANN, EDBN, ...): the last frame that voted; later
//!   frames are inactive (too few spikes) and cannot change the answer.
//! * Trained baselines with a saved model (`model_in`): the same, batch or
//!   streamed.
//! * "No edge" for want of data (no frame, or no active frame): `None`.

pub mod ann;
pub mod ann32;
pub mod classic;
pub mod dense;
pub mod edbn;
pub mod features;
pub mod forest;
pub mod knn_scan;
pub mod lbfgs;
mod rbm32;
pub mod saved;
pub mod smo;
pub mod vmath;
pub mod wss;

use palpate_core::SpikeImages;

/// The palpation, ms from the trial's start, that the images are known to
/// cover: `(n_frames - 1)·hop` (the trial ends within the following hop).
pub fn images_end_ms(images: &SpikeImages) -> f64 {
    images.n_frames.saturating_sub(1) as f64 * images.hop_ms
}

/// Decision time of an answer that used frames `0..=k` of `images`:
/// `min(k·hop + window, (n - 1)·hop)`, ms from the trial's start (see the
/// module docs).
pub fn decision_time_ms(images: &SpikeImages, k: usize) -> f64 {
    (k as f64 * images.hop_ms + images.window_ms).min(images_end_ms(images))
}

/// Caps an estimate's decision time at what its images cover (estimators
/// compute `k·hop + window` frame by frame, without knowing the trial's end;
/// streams keep the uncapped value, since they cannot know it either).
pub(crate) fn cap_decision_time(
    mut e: palpate_core::Estimate,
    images: &SpikeImages,
) -> palpate_core::Estimate {
    let end = images_end_ms(images);
    e.decision_time_ms = e.decision_time_ms.map(|t| t.min(end));
    e
}
