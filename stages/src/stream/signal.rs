//! Streaming `lowpass` (causal), `normalize` (causal) and `drive` (fixed gain).
//!
//! * `lowpass`: the causal mode's cascade of transposed DF-II sections, run
//!   sample by sample with each taxel's section memories kept between blocks;
//!   every section starts in the steady state of the trial's first sample, as
//!   [`sosfilt`](crate::signal::lowpass::sosfilt) does. Same operations per
//!   sample as the batch pass: same bits.
//! * `normalize`: `r` = the running sum of the first `N_b = round(baseline_ms·fs/1000)`
//!   samples (at least 1) over `N_b`; 0 during the baseline, then
//!   `clamp(|x − r| / span, 0, 1)` (0 when `|x − r| <= min_span`).
//! * `drive`, `fa_i`: `I_k = G·|x_{k+1} − x_{k−1}|·fs/2`, `I_0 = G·|x_1 − x_0|·fs`,
//!   `I_{n−1} = G·|x_{n−1} − x_{n−2}|·fs` at the flush: **one sample of
//!   latency** (the central difference needs the next sample). `sa_i`:
//!   `G·x`; `direct`: `x`.

use super::block_signals;
use crate::signal::drive::{DriveConfig, DriveKind};
use crate::signal::lowpass::{Biquad, FilterMode, Lowpass, LowpassConfig};
use crate::signal::normalize::{NormalizeConfig, NormalizeMode};
use palpate_core::stream::{StreamForm, StreamStage, StreamState};
use palpate_core::{register_stream, BuildContext, ConfigError, Payload, Signals, StageError, TrialContext};

/// The frame (rate, layout, unit) of the first block, for later output blocks.
fn frame_of(s: &Signals, unit: &str) -> Signals {
    Signals {
        sample_rate_hz: s.sample_rate_hz,
        layout: s.layout.clone(),
        unit: unit.to_string(),
        data: Vec::new(),
    }
}

/// Checks that a later block has the first block's rate and taxels.
fn same_frame(what: &str, first: &Signals, s: &Signals) -> Result<(), StageError> {
    if first.sample_rate_hz.to_bits() != s.sample_rate_hz.to_bits() || first.layout != s.layout {
        return Err(StageError::new(format!(
            "{what}: a block's rate or layout differs from the trial's first block"
        )));
    }
    Ok(())
}

// ---------------------------------------------------------------- lowpass

fn lowpass_stream(cfg: &LowpassConfig, _ctx: &BuildContext) -> Result<StreamForm, ConfigError> {
    if cfg.mode != FilterMode::Causal {
        return Ok(StreamForm::batch(
            "zero-phase filtering runs a second pass backwards from the trial's end",
            "mode = \"causal\" (one forward pass; lags ~√2/(2π·cutoff) at order 2)",
        ));
    }
    palpate_core::check_range("order", cfg.order as f64, 1.0, 16.0, "")?;
    palpate_core::check_positive("cutoff_hz", cfg.cutoff_hz, "Hz")?;
    Ok(StreamForm::Streams(Box::new(LowpassStream {
        order: cfg.order,
        cutoff_hz: cfg.cutoff_hz,
    })))
}
register_stream!("lowpass", LowpassConfig, lowpass_stream);

struct LowpassStream {
    order: usize,
    cutoff_hz: f64,
}

impl StreamStage for LowpassStream {
    fn open(&self, _ctx: &TrialContext<'_>) -> Result<Box<dyn StreamState>, StageError> {
        Ok(Box::new(LowpassState {
            order: self.order,
            cutoff_hz: self.cutoff_hz,
            first: None,
            sos: Vec::new(),
            z: Vec::new(),
        }))
    }
}

struct LowpassState {
    order: usize,
    cutoff_hz: f64,
    first: Option<Signals>,
    sos: Vec<Biquad>,
    /// Per taxel, per section: `(z1, z2)`.
    z: Vec<[f64; 2]>,
}

impl StreamState for LowpassState {
    fn push(&mut self, block: &Payload, out: &mut Vec<Payload>) -> Result<(), StageError> {
        let s = block_signals("lowpass", block)?;
        if s.n_samples() == 0 {
            return Ok(());
        }
        let ns = match &self.first {
            Some(f) => {
                same_frame("lowpass", f, s)?;
                self.sos.len()
            }
            None => {
                // The batch stage's causal design: the same sections, and
                // the same refusals (the Nyquist frequency, a cutoff too
                // small a share of the rate for f64 to hold).
                self.sos =
                    Lowpass::new(self.order, self.cutoff_hz, FilterMode::Causal).design(s.sample_rate_hz)?;
                let ns = self.sos.len();
                // Steady state of the first sample in every section (as `sosfilt`).
                self.z = Vec::with_capacity(s.data.len() * ns);
                for xs in &s.data {
                    let x0 = xs[0];
                    for sec in &self.sos {
                        let z2 = (sec.b[2] - sec.a[1]) * x0;
                        self.z.push([(sec.b[1] - sec.a[0]) * x0 + z2, z2]);
                    }
                }
                self.first = Some(frame_of(s, &s.unit));
                ns
            }
        };
        let mut data = Vec::with_capacity(s.data.len());
        for (t, xs) in s.data.iter().enumerate() {
            let mut ys = xs.clone();
            for (k, sec) in self.sos.iter().enumerate() {
                let [b0, b1, b2] = sec.b;
                let [a1, a2] = sec.a;
                let [mut z1, mut z2] = self.z[t * ns + k];
                for y in ys.iter_mut() {
                    let xi = *y;
                    let o = b0 * xi + z1;
                    z1 = b1 * xi - a1 * o + z2;
                    z2 = b2 * xi - a2 * o;
                    *y = o;
                }
                self.z[t * ns + k] = [z1, z2];
            }
            // As the batch stage: overflow anywhere in the block leaves its
            // last sample non-finite (see `ends_finite`).
            if !crate::signal::lowpass::ends_finite(&ys) {
                return Err(crate::signal::lowpass::overflow_error(t, xs));
            }
            data.push(ys);
        }
        out.push(s.with_data(s.unit.clone(), data).into());
        Ok(())
    }

    fn flush(&mut self, _out: &mut Vec<Payload>) -> Result<(), StageError> {
        Ok(())
    }
}

// ---------------------------------------------------------------- normalize

fn normalize_stream(cfg: &NormalizeConfig, _ctx: &BuildContext) -> Result<StreamForm, ConfigError> {
    if cfg.mode != NormalizeMode::Causal {
        return Ok(StreamForm::batch(
            "whole-trial normalization needs the trial's minimum and maximum",
            "mode = \"causal\" with `span` (the full-scale change from rest, from a calibration palpation)",
        ));
    }
    palpate_core::check_range("min_span", cfg.min_span, 0.0, f64::MAX, "input units")?;
    palpate_core::check_positive("baseline_ms", cfg.baseline_ms, "ms")?;
    let span = match cfg.span {
        Some(s) => palpate_core::check_positive("span", s, "input units")?,
        None => return Err(ConfigError::key(
            "span",
            "causal mode needs the expected full-scale change of the signal (input units, from calibration)",
        )),
    };
    Ok(StreamForm::Streams(Box::new(NormalizeStream {
        baseline_ms: cfg.baseline_ms,
        span,
        min_span: cfg.min_span,
    })))
}
register_stream!("normalize", NormalizeConfig, normalize_stream);

struct NormalizeStream {
    baseline_ms: f64,
    span: f64,
    min_span: f64,
}

impl StreamStage for NormalizeStream {
    fn open(&self, _ctx: &TrialContext<'_>) -> Result<Box<dyn StreamState>, StageError> {
        Ok(Box::new(NormalizeState {
            baseline_ms: self.baseline_ms,
            span: self.span,
            min_span: self.min_span,
            first: None,
            nb: 0,
            nb_raw: 0,
            k: 0,
            sum: Vec::new(),
        }))
    }
}

struct NormalizeState {
    baseline_ms: f64,
    span: f64,
    min_span: f64,
    first: Option<Signals>,
    /// Baseline samples (at least 1), and as configured (for the batch's error).
    nb: usize,
    nb_raw: usize,
    /// Samples so far.
    k: usize,
    /// Per taxel: the sum of the baseline so far, then the rest level.
    sum: Vec<f64>,
}

impl StreamState for NormalizeState {
    fn push(&mut self, block: &Payload, out: &mut Vec<Payload>) -> Result<(), StageError> {
        let s = block_signals("normalize", block)?;
        let n = s.n_samples();
        if n == 0 {
            return Ok(());
        }
        match &self.first {
            Some(f) => same_frame("normalize", f, s)?,
            None => {
                let nb = (self.baseline_ms * s.sample_rate_hz / 1000.0).round();
                self.nb_raw = if nb.is_finite() && nb < usize::MAX as f64 {
                    nb as usize
                } else {
                    usize::MAX
                };
                self.nb = self.nb_raw.max(1);
                // -0.0 is the identity of f64 addition, as in `Iterator::sum`.
                self.sum = vec![-0.0; s.data.len()];
                self.first = Some(frame_of(s, "normalized"));
            }
        }
        let mut data = Vec::with_capacity(s.data.len());
        for (t, xs) in s.data.iter().enumerate() {
            let mut ys = vec![0.0; n];
            for (i, (&x, y)) in xs.iter().zip(ys.iter_mut()).enumerate() {
                let k = self.k + i;
                if k < self.nb {
                    self.sum[t] += x;
                    if k + 1 == self.nb {
                        self.sum[t] /= self.nb as f64;
                    }
                } else {
                    let dev = (x - self.sum[t]).abs();
                    if dev > self.min_span {
                        *y = (dev / self.span).clamp(0.0, 1.0);
                    }
                }
            }
            data.push(ys);
        }
        self.k += n;
        out.push(s.with_data("normalized", data).into());
        Ok(())
    }

    fn flush(&mut self, _out: &mut Vec<Payload>) -> Result<(), StageError> {
        if let Some(f) = &self.first {
            if self.nb_raw >= self.k && self.k > 0 {
                return Err(StageError::new(format!(
                    "normalize: key `baseline_ms` = {} ms covers the whole trial ({:.1} ms)",
                    self.baseline_ms,
                    self.k as f64 * 1000.0 / f.sample_rate_hz
                )));
            }
        }
        Ok(())
    }
}

// ---------------------------------------------------------------- drive

fn drive_stream(cfg: &DriveConfig, _ctx: &BuildContext) -> Result<StreamForm, ConfigError> {
    let gain =
        match (cfg.kind, cfg.gain, cfg.target_peak_current) {
            (DriveKind::Direct, None, None) => 1.0,
            (DriveKind::Direct, _, _) => {
                return Err(ConfigError::key(
                    "gain",
                    "kind `direct` passes the signal unchanged; remove `gain` and `target_peak_current`",
                ))
            }
            (_, Some(g), None) if g.is_finite() && g >= 0.0 => g,
            (_, Some(g), None) => {
                return Err(ConfigError::key(
                    "gain",
                    format!("must be a finite number >= 0, got {}", palpate_core::fmt_num(g)),
                ))
            }
            (_, Some(_), Some(_)) => {
                return Err(ConfigError::key(
                    "gain",
                    "set either `gain` (fixed) or `target_peak_current` (per trial), not both",
                ))
            }
            (_, None, _) => return Ok(StreamForm::batch(
                "`target_peak_current` sets the gain from the trial's largest slope, known only at its end",
                "a fixed `gain` (e.g. target / max |dV/dt| of a calibration palpation)",
            )),
        };
    Ok(StreamForm::Streams(Box::new(DriveStream {
        kind: cfg.kind,
        gain,
    })))
}
register_stream!("drive", DriveConfig, drive_stream);

struct DriveStream {
    kind: DriveKind,
    gain: f64,
}

impl StreamStage for DriveStream {
    fn open(&self, _ctx: &TrialContext<'_>) -> Result<Box<dyn StreamState>, StageError> {
        Ok(Box::new(DriveState {
            kind: self.kind,
            gain: self.gain,
            first: None,
            k: 0,
            hist: Vec::new(),
        }))
    }
}

struct DriveState {
    kind: DriveKind,
    gain: f64,
    first: Option<Signals>,
    /// Samples so far.
    k: usize,
    /// Per taxel: `[x_{k-2}, x_{k-1}]` (the last two samples seen).
    hist: Vec<[f64; 2]>,
}

impl DriveState {
    /// `G·|d|`, guarded against overflow as the batch stage is.
    #[inline]
    fn current(&self, d: f64) -> f64 {
        crate::signal::drive::scaled(d.abs(), self.gain)
    }
}

impl StreamState for DriveState {
    fn push(&mut self, block: &Payload, out: &mut Vec<Payload>) -> Result<(), StageError> {
        let s = block_signals("drive", block)?;
        let n = s.n_samples();
        if n == 0 {
            return Ok(());
        }
        match &self.first {
            Some(f) => same_frame("drive", f, s)?,
            None => {
                let unit = if self.kind == DriveKind::Direct {
                    s.unit.as_str()
                } else {
                    "current"
                };
                self.first = Some(frame_of(s, unit));
                self.hist = vec![[0.0; 2]; s.data.len()];
            }
        }
        let fs = s.sample_rate_hz;
        let data: Vec<Vec<f64>> = match self.kind {
            DriveKind::Direct => s.data.clone(),
            DriveKind::SaI => s
                .data
                .iter()
                .map(|xs| xs.iter().map(|&x| self.current_sa(x)).collect())
                .collect(),
            DriveKind::FaI => {
                let half = 0.5 * fs;
                let mut data = Vec::with_capacity(s.data.len());
                for (t, xs) in s.data.iter().enumerate() {
                    let mut ys = Vec::with_capacity(n);
                    let [mut p, mut q] = self.hist[t];
                    for (i, &x) in xs.iter().enumerate() {
                        match self.k + i {
                            0 => {}
                            1 => ys.push(self.current((x - q) * fs)),
                            _ => ys.push(self.current((x - p) * half)),
                        }
                        p = q;
                        q = x;
                    }
                    self.hist[t] = [p, q];
                    data.push(ys);
                }
                data
            }
        };
        self.k += n;
        if let Some(f) = &self.first {
            if data.first().is_some_and(|d| !d.is_empty()) {
                out.push(f.with_data(f.unit.clone(), data).into());
            }
        }
        Ok(())
    }

    fn flush(&mut self, out: &mut Vec<Payload>) -> Result<(), StageError> {
        if self.kind != DriveKind::FaI {
            return Ok(());
        }
        let Some(f) = &self.first else { return Ok(()) };
        let fs = f.sample_rate_hz;
        // The last sample's one-sided difference (0 for a one-sample trial).
        let data = self
            .hist
            .iter()
            .map(|&[p, q]| {
                vec![if self.k >= 2 {
                    self.current((q - p) * fs)
                } else {
                    0.0
                }]
            })
            .collect();
        out.push(f.with_data(f.unit.clone(), data).into());
        Ok(())
    }
}

impl DriveState {
    /// `G·x` (`sa_i`), guarded like the batch stage (no absolute value).
    #[inline]
    fn current_sa(&self, x: f64) -> f64 {
        crate::signal::drive::scaled(x, self.gain)
    }
}
