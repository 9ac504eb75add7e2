//! Streaming `wss`: the running estimate after every spike image.
//!
//! [`WssStream`] keeps, per class, the alignments that may still be the best,
//! so that after image `j` its estimate is the batch WSS of images `0..=j`
//! (scores to ~1e-9). An estimate block is emitted whenever the answer
//! changes (class, "no edge", or becoming decided with `stop_margin`); the
//! flush emits the trial's final estimate, refined, its decision time capped
//! at what the images cover, as the batch model does. With `stop_margin` the
//! final estimate is the first decided one, as in batch. Templates are built
//! on the first block (they depend on the layout, the hop and the speed: the
//! config's, else the trial's declared one, as in batch) and shared by every
//! trial with the same ones.

use crate::estimate::wss::{Templates, WssConfig, WssParams, WssStream};
use palpate_core::stream::{StreamForm, StreamStage, StreamState};
use palpate_core::{
    register_stream, BuildContext, ConfigError, Estimate, Payload, SpikeImages, StageError, TaxelLayout,
    TrialContext,
};
use std::sync::{Arc, Mutex};

fn wss_stream(cfg: &WssConfig, _ctx: &BuildContext) -> Result<StreamForm, ConfigError> {
    Ok(StreamForm::Streams(Box::new(WssStage {
        params: cfg.params()?,
        templates: Arc::new(Mutex::new(None)),
    })))
}
register_stream!("wss", WssConfig, wss_stream);

/// Templates for a (layout, hop, speed).
type Cached = (TaxelLayout, u64, u64, Arc<Templates>);

struct WssStage {
    params: WssParams,
    /// The last templates built, shared by every trial's state.
    templates: Arc<Mutex<Option<Cached>>>,
}

/// The templates for `images`' layout and hop, built once and shared.
fn templates(
    cache: &Mutex<Option<Cached>>,
    images: &SpikeImages,
    params: &WssParams,
) -> Result<Arc<Templates>, StageError> {
    let speed = params.speed().to_bits();
    if let Some((l, h, v, t)) = cache.lock().unwrap_or_else(|e| e.into_inner()).as_ref() {
        if *l == images.layout && *h == images.hop_ms.to_bits() && *v == speed {
            return Ok(t.clone());
        }
    }
    // Built outside the lock: two trials may both build them on first use,
    // which costs time but never changes a result.
    let t = Arc::new(
        Templates::new(&images.layout, images.hop_ms, params)
            .map_err(|e| StageError::new(format!("wss: images' {e}")))?,
    );
    *cache.lock().unwrap_or_else(|e| e.into_inner()) =
        Some((images.layout.clone(), images.hop_ms.to_bits(), speed, t.clone()));
    Ok(t)
}

impl StreamStage for WssStage {
    fn open(&self, ctx: &TrialContext<'_>) -> Result<Box<dyn StreamState>, StageError> {
        Ok(Box::new(WssState {
            params: self.params.for_trial(ctx.meta.speed_mm_s, ctx.stage_id),
            cache: self.templates.clone(),
            stream: None,
            first: None,
            frames: 0,
            last: None,
            decided: None,
        }))
    }
}

struct WssState {
    params: WssParams,
    cache: Arc<Mutex<Option<Cached>>>,
    stream: Option<WssStream>,
    /// The first block's frame (layout, window, hop), no counts.
    first: Option<SpikeImages>,
    /// Images received.
    frames: usize,
    /// The last emitted answer: (angle, class, decided) bits.
    last: Option<(Option<u64>, Option<u64>, bool)>,
    /// The first decided estimate (with `stop_margin`).
    decided: Option<Estimate>,
}

impl StreamState for WssState {
    fn push(&mut self, block: &Payload, out: &mut Vec<Payload>) -> Result<(), StageError> {
        let images = block.images()?;
        let n = images.n_taxels();
        if images.counts.len() != images.n_frames.saturating_mul(n) {
            return Err(StageError::new(format!(
                "wss: an images block of {} frames x {n} taxels holds {} counts",
                images.n_frames,
                images.counts.len()
            )));
        }
        if self.stream.is_none() {
            let tpl = templates(&self.cache, images, &self.params)?;
            self.stream = Some(WssStream::new(tpl, self.params.clone(), images.window_ms)?);
            self.first = Some(SpikeImages {
                layout: images.layout.clone(),
                window_ms: images.window_ms,
                hop_ms: images.hop_ms,
                n_frames: 0,
                counts: Vec::new(),
            });
        } else if let Some(f) = &self.first {
            if f.layout != images.layout || f.hop_ms.to_bits() != images.hop_ms.to_bits() {
                return Err(StageError::new(
                    "wss: a block's layout or hop differs from the trial's first block",
                ));
            }
        }
        let Some(stream) = self.stream.as_mut() else {
            return Ok(());
        };
        let mut changed = None;
        for k in 0..images.n_frames {
            self.frames += 1;
            if self.decided.is_some() {
                continue;
            }
            let e = stream.push(&images.counts[k * n..(k + 1) * n])?;
            let decided = self
                .params
                .stop_margin
                .is_some_and(|m| e.angle_deg.is_some() && stream.margin() >= m);
            let key = (
                e.angle_deg.map(f64::to_bits),
                e.class_deg.map(f64::to_bits),
                decided,
            );
            if decided {
                self.decided = Some(e.clone());
            }
            if self.last != Some(key) {
                self.last = Some(key);
                changed = Some(e);
            }
        }
        if let Some(e) = changed {
            out.push(e.into());
        }
        Ok(())
    }

    fn flush(&mut self, out: &mut Vec<Payload>) -> Result<(), StageError> {
        let (Some(stream), Some(first)) = (&self.stream, &self.first) else {
            return Err(StageError::new("wss: a trial without images"));
        };
        let e = match &self.decided {
            Some(e) => e.clone(),
            None => stream.estimate(),
        };
        let covered = SpikeImages {
            n_frames: self.frames,
            ..first.clone()
        };
        out.push(crate::estimate::cap_decision_time(e, &covered).into());
        Ok(())
    }
}
