//! [`LivePipeline`]: one DAQ frame in, O(taxels) work, the running WSS
//! estimate out (the maths is in the [module docs](super)).

use super::{Checked, LiveConfig};
use crate::encode::izhikevich::{Izhikevich, NeuronState};
use crate::estimate::wss::{Templates, WssStream};
use crate::signal::lowpass::Biquad;
use palpate_core::{ConfigError, Estimate, SpikeEvent, StageError};
use std::collections::VecDeque;
use std::sync::Arc;

/// The running answer of a live run, as reported to the caller.
#[derive(Clone, Debug, PartialEq)]
pub struct LiveEstimate {
    /// Stream time when it was reached: samples so far (held ones included) / rate, ms.
    pub t_ms: f64,
    /// Spike images pushed into WSS so far.
    pub frames: usize,
    /// The answer, degrees; `None` = "no edge" (yet).
    pub angle_deg: Option<f64>,
    /// The best class of the grid; `None` = "no edge".
    pub class_deg: Option<f64>,
    /// The best class's score (a weighted mean correlation, `max_k WSS_θ(k)`); 0 before any image.
    pub score: f64,
    /// The best class's score minus the second best's.
    pub margin: f64,
    /// Palpation the answer needed, ms from the stream's start (end of its best frame).
    pub decision_time_ms: Option<f64>,
    /// True once the answer passes the threshold and `margin >= wss.stop_margin`.
    pub decided: bool,
    /// The full estimate (every class's score).
    pub estimate: Estimate,
}

/// Frame counts of the spike images, built as spikes arrive: frame `j`
/// covers `[j·hop, j·hop + window)` ms (the `bin` stage's definition) and is
/// complete once every spike before its end is known.
struct StreamBinner {
    window: f64,
    hop: f64,
    n: usize,
    /// Index of `open[0]`.
    next: usize,
    open: VecDeque<Vec<f64>>,
    spare: Vec<Vec<f64>>,
}

impl StreamBinner {
    fn add(&mut self, taxel: usize, t: f64) {
        // Same candidate range and exact test as `spikes::bin::Binner::bin`.
        let lo = ((t - self.window) / self.hop).floor().max(0.0) as usize;
        let hi = ((t / self.hop).floor() + 1.0).max(0.0) as usize;
        for k in lo.max(self.next)..hi {
            let start = k as f64 * self.hop;
            if start <= t && t < start + self.window {
                while self.open.len() <= k - self.next {
                    let f = self.spare.pop().unwrap_or_else(|| vec![0.0; self.n]);
                    self.open.push_back(f);
                }
                self.open[k - self.next][taxel] += 1.0;
            }
        }
    }

    /// End of the next frame, ms.
    fn next_end(&self) -> f64 {
        self.next as f64 * self.hop + self.window
    }

    /// Takes the next frame into `out` (zeros when no spike touched it).
    fn pop(&mut self, out: &mut [f64]) {
        match self.open.pop_front() {
            Some(mut f) => {
                out.copy_from_slice(&f);
                f.iter_mut().for_each(|v| *v = 0.0);
                self.spare.push(f);
            }
            None => out.iter_mut().for_each(|v| *v = 0.0),
        }
        self.next += 1;
    }
}

/// The live path for one stream: push DAQ frames, read the running estimate.
/// See the [module docs](super) for the maths and what it equals offline.
pub struct LivePipeline {
    fs: f64,
    n: usize,
    sos: Vec<Biquad>,
    /// Per taxel, per section: transposed DF-II state `(z1, z2)`.
    z: Vec<[f64; 2]>,
    nb: usize,
    base: Vec<f64>,
    span: f64,
    min_span: f64,
    gain: f64,
    /// Normalized values of the last two samples, per taxel: `[V_{k-1}, V_k]`.
    hist: Vec<[f64; 2]>,
    neuron: Izhikevich,
    states: Vec<NeuronState>,
    spp: f64,
    next_step: u64,
    samples: u64,
    last_raw: Vec<f64>,
    raw: Vec<f64>,
    cur: Vec<f64>,
    pending: Vec<SpikeEvent>,
    binner: StreamBinner,
    frame: Vec<f64>,
    wss: WssStream,
    stop_margin: Option<f64>,
    spikes: Vec<u64>,
    kept: Option<Vec<SpikeEvent>>,
    held: u64,
    non_finite: u64,
    last: Option<(Option<u64>, Option<u64>, bool)>,
    latest: Option<LiveEstimate>,
    decision: Option<LiveEstimate>,
    finished: bool,
}

impl LivePipeline {
    /// A pipeline for `cfg`, building the WSS templates (a few ms).
    pub fn new(cfg: &LiveConfig) -> Result<Self, ConfigError> {
        let c = cfg.check()?;
        let tpl = Arc::new(c.templates()?);
        Self::from_checked(c, tpl)
    }

    /// A pipeline for `cfg` reusing templates built by [`LiveConfig::templates`]
    /// (they must be for the same layout, hop and WSS keys).
    pub fn with_templates(cfg: &LiveConfig, templates: Arc<Templates>) -> Result<Self, ConfigError> {
        Self::from_checked(cfg.check()?, templates)
    }

    pub(super) fn from_checked(c: Checked, tpl: Arc<Templates>) -> Result<Self, ConfigError> {
        let n = c.layout.len();
        if tpl.n_taxels() != n || tpl.hop_ms() != c.hop_ms {
            return Err(ConfigError::general(format!(
                "templates are for {} taxels and a {} ms hop, the config has {n} taxels and {} ms",
                tpl.n_taxels(),
                tpl.hop_ms(),
                c.hop_ms
            )));
        }
        let wss =
            WssStream::new(tpl, c.wss.clone(), c.window_ms).map_err(|e| ConfigError::general(e.message))?;
        let state = c.neuron.initial_state();
        Ok(LivePipeline {
            fs: c.fs,
            n,
            z: vec![[0.0; 2]; n * c.sos.len()],
            sos: c.sos,
            nb: c.nb,
            base: vec![0.0; n],
            span: c.span,
            min_span: c.min_span,
            gain: c.gain,
            hist: vec![[0.0; 2]; n],
            spp: c.neuron.dt_ms * c.fs / 1000.0,
            neuron: c.neuron,
            states: vec![state; n],
            next_step: 0,
            samples: 0,
            last_raw: vec![0.0; n],
            raw: vec![0.0; n],
            cur: vec![0.0; n],
            pending: Vec::new(),
            binner: StreamBinner {
                window: c.window_ms,
                hop: c.hop_ms,
                n,
                next: 0,
                open: VecDeque::new(),
                spare: Vec::new(),
            },
            frame: vec![0.0; n],
            wss,
            stop_margin: c.stop_margin,
            spikes: vec![0; n],
            kept: None,
            held: 0,
            non_finite: 0,
            last: None,
            latest: None,
            decision: None,
            finished: false,
        })
    }

    /// Also keep every spike event (for tests and diagnostics; it grows with
    /// the stream, so it is off by default).
    pub fn keep_spikes(&mut self, on: bool) {
        self.kept = on.then(Vec::new);
    }

    /// Kept spike events, time-sorted then by taxel like the batch encoder's
    /// (empty unless [`LivePipeline::keep_spikes`] was turned on).
    pub fn spike_events(&self) -> Vec<SpikeEvent> {
        let mut ev = self.kept.clone().unwrap_or_default();
        crate::encode::sort_events(&mut ev);
        ev
    }

    /// Samples consumed (received and held).
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// Samples held in place of lost frames.
    pub fn held(&self) -> u64 {
        self.held
    }

    /// Non-finite samples replaced by the taxel's previous value.
    pub fn non_finite(&self) -> u64 {
        self.non_finite
    }

    /// Spike images pushed into WSS.
    pub fn frames(&self) -> usize {
        self.wss.frames()
    }

    /// Spikes per taxel so far (those binned).
    pub fn spike_counts(&self) -> &[u64] {
        &self.spikes
    }

    /// Stream time, ms.
    pub fn t_ms(&self) -> f64 {
        self.samples as f64 * 1000.0 / self.fs
    }

    /// The latest running estimate (after the last image), if any image yet.
    pub fn latest(&self) -> Option<&LiveEstimate> {
        self.latest.as_ref()
    }

    /// The first estimate that was `decided` (see `wss.stop_margin`), if any.
    pub fn decision(&self) -> Option<&LiveEstimate> {
        self.decision.as_ref()
    }

    /// Alignments the WSS stream keeps as possible bests, over every class
    /// ([`WssStream::candidates`]): a handful per class on real streams.
    pub fn wss_candidates(&self) -> usize {
        self.wss.candidates()
    }

    /// What the pipeline holds besides the WSS stream: (spikes waiting for
    /// their sample's end, images still open). Both stay bounded however long
    /// the stream (by taxels and by `window / hop + 2`).
    pub fn buffered(&self) -> (usize, usize) {
        (
            self.pending.len(),
            self.binner.open.len() + self.binner.spare.len(),
        )
    }

    /// Pushes one frame: one raw sample per taxel (after the DAQ's scale and
    /// offset). Returns the running estimate when it changed (class, "no
    /// edge", or decided); several changes within one push collapse to the
    /// last. A non-finite sample is replaced by that taxel's previous value
    /// (0 before any) and counted.
    pub fn push(&mut self, samples: &[f64]) -> Result<Option<LiveEstimate>, StageError> {
        if self.finished {
            return Err(StageError::new("live: push after finish"));
        }
        if samples.len() != self.n {
            return Err(StageError::new(format!(
                "live: frame {} has {} samples, the layout has {} taxels",
                self.samples,
                samples.len(),
                self.n
            )));
        }
        for (t, &x) in samples.iter().enumerate() {
            if x.is_finite() {
                self.raw[t] = x;
            } else {
                self.non_finite += 1;
                self.raw[t] = self.last_raw[t];
            }
        }
        let raw = std::mem::take(&mut self.raw);
        let r = self.sample(&raw);
        self.last_raw.copy_from_slice(&raw);
        self.raw = raw;
        r
    }

    /// Holds the previous frame for `count` lost frames (zero-order hold; see
    /// the module docs). Before any frame there is nothing to hold: no-op.
    pub fn hold(&mut self, count: u64) -> Result<Option<LiveEstimate>, StageError> {
        if self.samples == 0 || self.finished {
            return Ok(None);
        }
        let raw = self.last_raw.clone();
        let mut changed = None;
        for _ in 0..count {
            if let Some(e) = self.sample(&raw)? {
                changed = Some(e);
            }
            self.held += 1;
        }
        Ok(changed)
    }

    /// Ends the stream: the last sample's current (one-sided difference), the
    /// neuron steps up to the stream's end, the images that run past it (as
    /// the `bin` stage counts them), and the final estimate (with `refine`).
    pub fn finish(&mut self) -> Result<LiveEstimate, StageError> {
        if !self.finished {
            self.finished = true;
            let k = self.samples;
            if k > 0 {
                // Current of the last sample: one-sided difference (0 for a single sample).
                for t in 0..self.n {
                    let [p, v] = self.hist[t];
                    self.cur[t] = if k >= 2 {
                        self.current((v - p) * self.fs)
                    } else {
                        0.0
                    };
                }
                let dur = k as f64 * 1000.0 / self.fs;
                let n_steps = (dur / self.neuron.dt_ms - 1e-9).ceil().max(1.0) as u64;
                self.advance(n_steps);
                let pending = std::mem::take(&mut self.pending);
                for e in pending.into_iter().filter(|e| e.t_ms < dur) {
                    self.bin(e);
                }
            }
            let dur = k as f64 * 1000.0 / self.fs;
            let n_frames = if dur > 0.0 {
                ((dur / self.binner.hop).ceil() as usize).max(1)
            } else {
                1
            };
            while self.binner.next < n_frames {
                self.emit_frame()?;
            }
        }
        let e = self.wss.estimate();
        Ok(self.live_estimate(e))
    }

    /// One sample of every taxel (finite), through every causal step.
    fn sample(&mut self, raw: &[f64]) -> Result<Option<LiveEstimate>, StageError> {
        let k = self.samples as usize;
        let ns = self.sos.len();
        for (t, &x) in raw.iter().enumerate() {
            // Low-pass: transposed DF-II sections, each starting in the steady
            // state of its first input (as `signal::lowpass::sosfilt`).
            let mut v = x;
            for (s, sec) in self.sos.iter().enumerate() {
                let [b0, b1, b2] = sec.b;
                let [a1, a2] = sec.a;
                let z = &mut self.z[t * ns + s];
                if k == 0 {
                    z[1] = (b2 - a2) * v;
                    z[0] = (b1 - a1) * v + z[1];
                }
                let y = b0 * v + z[0];
                z[0] = b1 * v - a1 * y + z[1];
                z[1] = b2 * v - a2 * y;
                v = y;
            }
            // Causal normalization (as `normalize_causal`): 0 while the rest
            // level is being measured.
            let norm = if k < self.nb {
                self.base[t] += v;
                if k + 1 == self.nb {
                    self.base[t] /= self.nb as f64;
                }
                0.0
            } else {
                let dev = (v - self.base[t]).abs();
                if dev > self.min_span {
                    (dev / self.span).clamp(0.0, 1.0)
                } else {
                    0.0
                }
            };
            // FA-I drive of the previous sample, now that its successor is known.
            let [p, q] = self.hist[t];
            if k >= 1 {
                let d = if k == 1 {
                    (norm - q) * self.fs
                } else {
                    (norm - p) * (0.5 * self.fs)
                };
                self.cur[t] = self.current(d);
            }
            self.hist[t] = [q, norm];
        }
        self.samples += 1;
        if k >= 1 {
            // Neuron steps whose held input is sample k - 1.
            let j = (k - 1) as f64;
            let mut end = self.next_step;
            while ((end as f64 * self.spp + 1e-9).floor()) <= j {
                end += 1;
            }
            self.advance(end);
            // Spikes before the samples' end are final; later ones wait.
            let known = self.samples as f64 * 1000.0 / self.fs;
            let mut i = 0;
            while i < self.pending.len() {
                if self.pending[i].t_ms < known {
                    let e = self.pending.swap_remove(i);
                    self.bin(e);
                } else {
                    i += 1;
                }
            }
            // Every spike before `safe` is binned: later ones come from later steps.
            let safe = (self.next_step as f64 * self.neuron.dt_ms).min(known);
            let mut changed = None;
            while self.binner.next_end() <= safe {
                if let Some(e) = self.emit_frame()? {
                    changed = Some(e);
                }
            }
            return Ok(changed);
        }
        Ok(None)
    }

    /// `G·|d|`, guarded against overflow like the `drive` stage.
    #[inline]
    fn current(&self, d: f64) -> f64 {
        let x = d.abs() * self.gain;
        if x.is_finite() {
            x
        } else {
            f64::MAX.copysign(x)
        }
    }

    /// Runs every neuron from `next_step` up to (not including) `end` with the current inputs.
    fn advance(&mut self, end: u64) {
        let dt = self.neuron.dt_ms;
        for n in self.next_step..end {
            for t in 0..self.n {
                if let Some(f) = self.neuron.step(&mut self.states[t], self.cur[t]) {
                    self.pending.push(SpikeEvent {
                        taxel: t as u32,
                        t_ms: (n as f64 + f) * dt,
                    });
                }
            }
        }
        self.next_step = self.next_step.max(end);
    }

    fn bin(&mut self, e: SpikeEvent) {
        self.spikes[e.taxel as usize] += 1;
        self.binner.add(e.taxel as usize, e.t_ms);
        if let Some(k) = self.kept.as_mut() {
            k.push(e);
        }
    }

    /// Pushes the next image into WSS; returns the estimate if it changed.
    fn emit_frame(&mut self) -> Result<Option<LiveEstimate>, StageError> {
        self.binner.pop(&mut self.frame);
        let e = self.wss.push(&self.frame)?;
        let key = (
            e.angle_deg.map(f64::to_bits),
            e.class_deg.map(f64::to_bits),
            self.is_decided(&e),
        );
        let le = self.live_estimate(e);
        if le.decided && self.decision.is_none() {
            self.decision = Some(le.clone());
        }
        self.latest = Some(le.clone());
        if self.last == Some(key) {
            return Ok(None);
        }
        self.last = Some(key);
        Ok(Some(le))
    }

    fn is_decided(&self, e: &Estimate) -> bool {
        self.stop_margin
            .is_some_and(|m| e.angle_deg.is_some() && self.wss.margin() >= m)
    }

    fn live_estimate(&self, e: Estimate) -> LiveEstimate {
        let score = e.scores.iter().map(|s| s.score).fold(f64::NEG_INFINITY, f64::max);
        LiveEstimate {
            t_ms: self.t_ms(),
            frames: self.wss.frames(),
            angle_deg: e.angle_deg,
            class_deg: e.class_deg,
            score: if score.is_finite() { score } else { 0.0 },
            margin: self.wss.margin(),
            decision_time_ms: e.decision_time_ms,
            decided: self.is_decided(&e),
            estimate: e,
        }
    }
}
