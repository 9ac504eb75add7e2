//! `bin`: spike events to count images (paper section 2.5).
//!
//! Frame `k` covers `[k·hop, k·hop + window)` ms and holds, per taxel, the
//! number of spikes in it. With the paper's `window = 100`, `hop = 10`,
//! consecutive frames overlap by 90 ms and every spike counts in 10 frames.
//!
//! End rule: frames are emitted while `k·hop < duration`, i.e.
//! `n_frames = ceil(duration / hop)`; the last `window/hop - 1` frames run past
//! the trial's end and count only the part they cover (the trial is silent
//! after its end, so they are true counts of a shorter window). This keeps
//! every spike in the same number of frames as any other except within one
//! window of either end, and keeps the frame index a pure function of time
//! (frame `k` starts at `k·hop` whatever the trial's length). A trial of zero
//! duration gives one all-zero frame, so downstream stages always see an image.
//!
//! A window shorter than the hop leaves gaps between frames whose spikes no
//! frame counts. That runs (it subsamples the spike train), but is rarely
//! meant, so `palpate check` and `run` print a warning naming `window_ms`;
//! it is not an error.
//!
//! Cost: `O(events · window/hop + frames · taxels)`.
//!
//! ## Limits (docs/resource-policy.md)
//!
//! Both terms are capped so that no input can make `bin` allocate without
//! bound or spin: `window / hop` (frames per spike) at most
//! [`MAX_FRAMES_PER_SPIKE`], checked when the graph is built, and the image,
//! `frames x taxels`, at most [`MAX_IMAGE_CELLS`] counts, checked per trial
//! before anything is allocated. An outlier spike time (1e12 µs) or a
//! duration of 1e15 ms is then an error naming the trial's length, never a
//! capacity overflow.

use palpate_core::{
    check_positive, fmt_num, register_stage, BuildContext, ConfigChecks, ConfigError, InputSpec, Inspection,
    Item, Map, OutputFacts, Payload, PayloadKind, SpikeImages, SpikeTrain, Stage, StageConfig, StageError,
    TrialContext,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Most frames one spike may fall in (`window_ms / hop_ms`); the paper uses 10.
pub const MAX_FRAMES_PER_SPIKE: f64 = 10_000.0;

/// Most counts (`frames x taxels`) one trial's image may hold: 2^26, 512 MiB
/// of `f64` (the paper's 10 s trial at a 10 ms hop on 16 taxels holds 16,000).
pub const MAX_IMAGE_CELLS: usize = 1 << 26;

/// Bins spikes into per-taxel count images: frame k covers [k*hop, k*hop + window) ms.
///
/// Frames are emitted while `k*hop < duration`; the last frames, which run past
/// the trial's end, count what they cover.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct BinConfig {
    /// Length of each frame's window, ms. Default 100.
    pub window_ms: f64,
    /// Time between frame starts, ms. Default 10.
    pub hop_ms: f64,
}

impl Default for BinConfig {
    fn default() -> Self {
        BinConfig {
            window_ms: 100.0,
            hop_ms: 10.0,
        }
    }
}

#[typetag::serde(name = "bin")]
impl StageConfig for BinConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Spikes)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Images)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        let mut c = ConfigChecks::new();
        c.take(check_positive("window_ms", self.window_ms, "ms"));
        c.take(check_positive("hop_ms", self.hop_ms, "ms"));
        c.finish()?;
        if self.window_ms / self.hop_ms > MAX_FRAMES_PER_SPIKE {
            return Err(ConfigError::key(
                "hop_ms",
                format!(
                    "window_ms / hop_ms = {:?} frames per spike is over the cap of {MAX_FRAMES_PER_SPIKE:?} \
                     (a longer hop, or a shorter window)",
                    self.window_ms / self.hop_ms
                ),
            ));
        }
        Ok(Stage::Map(Box::new(Binner {
            window_ms: self.window_ms,
            hop_ms: self.hop_ms,
        })))
    }
    /// A window shorter than the hop is a warning: the spikes between
    /// frames are counted by none.
    fn inspect(&self, _ctx: &BuildContext, _inputs: &[OutputFacts]) -> Inspection {
        let mut out = Inspection::default();
        // A window that is not positive is an error of `build` already.
        if self.window_ms > 0.0 && self.window_ms < self.hop_ms {
            out.warnings.push(ConfigError::key(
                "window_ms",
                format!(
                    "{} ms is shorter than hop_ms = {} ms: the spikes in the {} ms between frames are counted by no frame",
                    fmt_num(self.window_ms),
                    fmt_num(self.hop_ms),
                    fmt_num(self.hop_ms - self.window_ms)
                ),
            ));
        }
        out
    }
}
register_stage!("bin", BinConfig);

/// The runtime `bin` stage.
#[derive(Clone, Debug)]
pub struct Binner {
    /// Window, ms.
    pub window_ms: f64,
    /// Hop, ms.
    pub hop_ms: f64,
}

impl Binner {
    /// A binner; both lengths must be positive and finite.
    pub fn new(window_ms: f64, hop_ms: f64) -> Self {
        Binner { window_ms, hop_ms }
    }

    /// Number of frames for a trial of `duration_ms` (saturating: `usize::MAX`
    /// for an absurd duration, which [`Binner::bin`] then refuses).
    pub fn n_frames(&self, duration_ms: f64) -> usize {
        if duration_ms.is_finite() && duration_ms > 0.0 {
            // `as` saturates on overflow (and a NaN ratio cannot occur: hop > 0).
            ((duration_ms / self.hop_ms).ceil() as usize).max(1)
        } else {
            1
        }
    }

    /// Bins one trial; an image over [`MAX_IMAGE_CELLS`] counts, or a window
    /// over [`MAX_FRAMES_PER_SPIKE`] hops, is an error.
    pub fn bin(&self, train: &SpikeTrain) -> Result<SpikeImages, StageError> {
        if !(self.hop_ms > 0.0
            && self.window_ms > 0.0
            && self.window_ms / self.hop_ms <= MAX_FRAMES_PER_SPIKE)
        {
            return Err(StageError::new(format!(
                "bin: window {:?} ms / hop {:?} ms must be positive with at most {MAX_FRAMES_PER_SPIKE:?} frames per spike",
                self.window_ms, self.hop_ms
            )));
        }
        let n_taxels = train.layout.len();
        let n_frames = self.n_frames(train.duration_ms);
        let cells = n_frames
            .checked_mul(n_taxels)
            .filter(|&c| c <= MAX_IMAGE_CELLS)
            .ok_or_else(|| {
                StageError::new(format!(
                    "bin: a trial of {:?} ms at a hop of {:?} ms needs {n_frames} frames of {n_taxels} taxels, \
                     over the cap of {MAX_IMAGE_CELLS} counts (an outlier spike time, or a wrong time unit?)",
                    train.duration_ms, self.hop_ms
                ))
            })?;
        let mut counts = vec![0.0; cells];
        for e in &train.events {
            let taxel = e.taxel as usize;
            if taxel >= n_taxels {
                return Err(StageError::new(format!(
                    "bin: spike of taxel {taxel} at {:?} ms, but the layout has {n_taxels} taxels",
                    e.t_ms
                )));
            }
            if !e.t_ms.is_finite() {
                return Err(StageError::new(format!(
                    "bin: spike of taxel {taxel} has time {}",
                    e.t_ms
                )));
            }
            // Candidate frames k with k*hop <= t < k*hop + window, then the exact
            // test with the same arithmetic as the definition (no off-by-one at
            // window edges from rounding).
            let lo = ((e.t_ms - self.window_ms) / self.hop_ms).floor().max(0.0) as usize;
            let hi = ((e.t_ms / self.hop_ms).floor() + 1.0).max(0.0) as usize;
            for k in lo..hi.min(n_frames) {
                let start = k as f64 * self.hop_ms;
                if start <= e.t_ms && e.t_ms < start + self.window_ms {
                    counts[k * n_taxels + taxel] += 1.0;
                }
            }
        }
        Ok(SpikeImages {
            layout: train.layout.clone(),
            window_ms: self.window_ms,
            hop_ms: self.hop_ms,
            n_frames,
            counts,
        })
    }
}

impl Map for Binner {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        Ok(self.bin(inputs[0].payload.spikes()?)?.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use palpate_core::{SpikeEvent, TaxelLayout};
    use proptest::prelude::*;

    fn train(duration_ms: f64, events: Vec<(u32, f64)>) -> SpikeTrain {
        SpikeTrain {
            layout: TaxelLayout::paper(),
            duration_ms,
            events: events
                .into_iter()
                .map(|(taxel, t_ms)| SpikeEvent { taxel, t_ms })
                .collect(),
        }
    }

    #[test]
    fn frames_and_windows_follow_the_definition() {
        let b = Binner::new(100.0, 10.0);
        let im = b
            .bin(&train(
                1000.0,
                vec![(0, 0.0), (5, 99.999), (5, 100.0), (15, 999.0)],
            ))
            .unwrap();
        assert_eq!(im.n_frames, 100);
        // t = 0 is only in frame 0; t = 100 in frames 1..=10; t = 99.999 in frames 0..=9.
        assert_eq!(im.frame(0)[0], 1.0);
        assert_eq!(im.frame(1)[0], 0.0);
        let f5: Vec<f64> = (0..100).map(|k| im.frame(k)[5]).collect();
        assert_eq!(f5[0], 1.0);
        assert_eq!(f5[9], 2.0);
        assert_eq!(f5[10], 1.0); // only the spike at 100
        assert_eq!(f5[1..10].iter().sum::<f64>(), 18.0);
        assert_eq!(f5[11], 0.0);
        // The spike at 999 ms is in the last 10 frames (90..=99), each partial.
        let f15: Vec<f64> = (0..100).map(|k| im.frame(k)[15]).collect();
        assert_eq!(f15[90..].iter().sum::<f64>(), 10.0);
        assert_eq!(f15[89], 0.0);
    }

    #[test]
    fn empty_train_bins_to_all_zero_images() {
        let b = Binner::new(100.0, 10.0);
        let im = b.bin(&train(5000.0, vec![])).unwrap();
        assert_eq!(im.n_frames, 500);
        assert_eq!(im.counts.len(), 500 * 16);
        assert!(im.counts.iter().all(|&c| c == 0.0));
        let z = b.bin(&train(0.0, vec![])).unwrap();
        assert_eq!((z.n_frames, z.counts.len()), (1, 16));
    }

    #[test]
    fn bad_taxel_is_an_error() {
        let b = Binner::new(100.0, 10.0);
        assert!(b
            .bin(&train(100.0, vec![(16, 1.0)]))
            .unwrap_err()
            .message
            .contains("taxel 16"));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        /// Against a brute-force count, for any window and hop (including
        /// windows shorter than the hop, which leave gaps).
        #[test]
        fn matches_brute_force(
            window in 0.5f64..50.0,
            hop in 0.5f64..30.0,
            ts in proptest::collection::vec((0u32..16, 0.0f64..300.0), 0..60),
        ) {
            let b = Binner::new(window, hop);
            let mut tr = train(300.0, ts);
            tr.sort();
            let im = b.bin(&tr).unwrap();
            prop_assert_eq!(im.n_frames, (300.0 / hop).ceil() as usize);
            for k in 0..im.n_frames {
                for taxel in 0..16u32 {
                    let s = k as f64 * hop;
                    let n = tr.events.iter().filter(|e| e.taxel == taxel && s <= e.t_ms && e.t_ms < s + window).count();
                    prop_assert_eq!(im.frame(k)[taxel as usize], n as f64);
                }
            }
        }
    }
}
