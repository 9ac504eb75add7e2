//! The live path: DAQ frames -> causal FA-I encoding -> streaming WSS, with the
//! running orientation estimate reported as it changes (`palpate daq run`).
//!
//! One DAQ frame (one sample of every taxel, `k` = its index, `h = 1/fs`)
//! goes through these steps, each causal and O(taxels) per frame:
//!
//! 1. **Low-pass** (`lowpass`, optional): the Butterworth design of
//!    [`crate::signal::lowpass`] in its causal mode, a single forward pass of
//!    cascaded second-order sections (`K = tan(π fc/fs)`, transposed DF-II,
//!    each section starting in the steady state of its first input). Its
//!    group delay is the price of causality: about `√2 / (2π fc)` at low
//!    frequencies for order 2 (22 ms at 10 Hz).
//! 2. **Normalization** (`normalize`): `r` = mean of the first
//!    `N_b = round(baseline_ms·fs/1000)` filtered samples; `V_k = 0` for
//!    `k < N_b`, then `V_k = clamp(|y_k − r| / span, 0, 1)` (0 when
//!    `|y_k − r| <= min_span`). `span` is a calibration value (see
//!    [`calibrate`]): live data cannot know its own range.
//! 3. **FA-I drive** (`drive`, paper eq. 4): `I_k = G·|V_{k+1} − V_{k−1}|/(2h)`
//!    (central difference; `I_0 = G|V_1 − V_0|/h`, the last sample's current
//!    `G|V_{K−1} − V_{K−2}|/h` at the end of the stream). It needs the next
//!    sample, so the encoder runs **one sample (1 ms) behind** the DAQ. `G` is
//!    **fixed**: the offline default sets it per trial from the trial's own
//!    peak slope, which a live stream cannot know in advance. Choose it from a
//!    calibration palpation: `G = target / max |dV/dt|` with the target peak
//!    current of the offline pipeline (20: ~120 Hz tonic firing of the FA-I
//!    neuron) at the fastest crossing you expect (90°); shallower edges then
//!    give proportionally smaller currents (about 7× smaller at 10°), so keep
//!    `G·max|dV/dt|` at the slowest angle above the neuron's rheobase (~3.8).
//!    [`calibrate`] computes both `span` and `G` from a recording.
//! 4. **Izhikevich FA-I neurons** (`encoder`, paper eqs. 1-3): each taxel's
//!    neuron keeps `(v, u)` between frames and advances by the steps of
//!    `dt_ms` whose start falls in sample `k`'s period, holding `I_k`
//!    ([`Izhikevich::step`](crate::encode::izhikevich::Izhikevich::step),
//!    the batch encoder's arithmetic). Spike times are interpolated within
//!    the step. `input = "linear"` would need one more sample of look-ahead
//!    and is refused.
//! 5. **Binning** (`bin`): image `j` counts the spikes in
//!    `[j·hop, j·hop + window)` ms and is pushed once every spike before its
//!    end is known (at stream time `j·hop + window`, plus the sample of
//!    latency); at the end, the images that run past the stream's end are
//!    pushed with what they cover, as the `bin` stage counts them.
//! 6. **Streaming WSS** ([`WssStream`](crate::estimate::wss::WssStream),
//!    `wss`): after image `j` the running estimate is exactly the batch WSS of
//!    the images so far; an update is emitted when the answer changes (class,
//!    "no edge", or becoming `decided`: above the threshold with
//!    `margin >= wss.stop_margin`). The final estimate applies `refine`.
//!
//! ## What equals what offline
//!
//! A [`LivePipeline`] fed a trial's samples one frame at a time gives the
//! same spike events (bit for bit), the same images and the same estimate (to
//! WssStream's ~1e-9 rounding of scores) as the batch graph
//! `lowpass{mode="causal"} -> normalize{mode="causal"} -> drive{kind="fa_i", gain=G}
//! -> izhikevich{input="hold"} -> bin -> wss` on the same samples (tested in
//! `stages/tests/io_live.rs`). It differs from the paper's offline pipeline
//! (`graphs/quickstart.toml`) in three ways, all forced by causality: the
//! filter is a forward pass (lag, -3 dB at `fc` once) instead of zero-phase;
//! normalization uses a baseline and a calibrated span instead of the
//! trial's min and max; the gain is fixed instead of set from the trial's
//! peak.
//!
//! ## The stream
//!
//! Time is the sample index over `sample_rate_hz`, not the frames'
//! timestamps (those are reported as a measured rate). **Lost frames** (a
//! sequence gap) are filled by holding the previous frame (zero-order hold,
//! as offline `fill_gaps = true` does), so the time base stays aligned with
//! the device's clock and a recording with `fill_gaps` replays identically;
//! the change across the gap then reaches the drive at once. A gap longer
//! than `max_gap_ms` ends the run (a time base that far off cannot match the
//! templates). CRC errors, out-of-order frames (device reset: the stream
//! carries on) and stalls are passed to the caller as [`LiveUpdate`]s and
//! counted in the report. A non-finite sample is replaced by the taxel's
//! previous value and counted.
//!
//! ## Cost and memory
//!
//! Per frame: the filter, normalization and drive of every taxel, and
//! `dt`-steps of every neuron (`fs·dt/1000` steps per sample): O(taxels).
//! Every `hop` one image goes into WSS (WssStream: a few µs per image, plus
//! a re-scoring of its few kept alignments on the rare images that raise the
//! largest count). Measured
//! (`cargo bench --bench live`, on-CPU time, one core of a shared AMD EPYC):
//! 0.93 µs per frame over a 60-degree lab trial, everything included (1.07
//! million frames/s; a 1 kHz board needs 1000).
//!
//! Memory is constant: whatever the stream's length, nothing grows. The
//! pipeline holds the spikes of the current sample and at most
//! `window/hop + 2` open images. The WSS stream keeps, instead of every
//! image's statistics, the frames its longest template still reads (37 s at
//! 10 degrees and 2 mm/s), a frequency-domain delay line as long
//! ([`wss_delay_line_bytes`]: 1.9 MB) and, per class, the few alignments that
//! may still be the best for any largest count still to come (see
//! [`WssStream`](crate::estimate::wss::WssStream)), all reserved when the
//! stream is built ([`wss_stream_bytes`]: 2.7 MB for graphs/live.toml). With
//! the templates and their spectra (8.0 MiB, once per config) a live run holds
//! 10.7 MiB after 10, 100 or 1000 s of stream alike (`cargo bench --bench
//! memory`, which also shows the batch path's linear growth).

mod pipeline;
mod run;

pub use pipeline::{LiveEstimate, LivePipeline};
pub use run::{run_live, run_live_serial, run_live_until, LiveEnd, LiveError, LiveReport, LiveUpdate};

use super::common::LayoutConfig;
use crate::encode::izhikevich::{Izhikevich, IzhikevichConfig};
use crate::encode::InputMode;
use crate::estimate::wss::{Templates, WssConfig, WssParams};
use crate::signal::lowpass::{butterworth_sos, Biquad};
use crate::spikes::bin::BinConfig;
use palpate_core::{
    check_positive, check_range, derive_seed, register_stage, BuildContext, ConfigChecks, ConfigError,
    InputSpec, Item, Map, Payload, PayloadKind, Signals, Stage, StageConfig, StageError, TaxelLayout,
    TrialContext,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

/// Bytes a WSS stream for `templates` reserves when it is built and keeps
/// to its end, whatever the stream's length (the templates themselves
/// aside): its delay line ([`wss_delay_line_bytes`]) and the frames its
/// longest template reads, with up to half as many again before old frames
/// are dropped (`8·taxels + 17` bytes each: the centred frame, its count,
/// its prefix sum, an activity flag).
pub fn wss_stream_bytes(templates: &Templates) -> usize {
    let longest = templates
        .classes()
        .iter()
        .map(|c| c.len)
        .max()
        .unwrap_or(1)
        .max(128);
    let frames = longest + (longest / 2).max(64) + 2;
    wss_delay_line_bytes(templates) + frames * (8 * templates.n_taxels() + 17)
}

/// Bytes of the WSS stream's frequency-domain delay line once full (after
/// the longest template's length in images): one spectrum pair of
/// `2·taxels·65` complex bins per 64-image block of the longest template
/// (WssStream's partition size). Bounded: it does not grow with the stream.
pub fn wss_delay_line_bytes(templates: &Templates) -> usize {
    const BLOCK: usize = 64;
    let parts = templates
        .classes()
        .iter()
        .map(|c| c.len.div_ceil(BLOCK))
        .max()
        .unwrap_or(1);
    parts * 2 * (2 * templates.n_taxels() * (BLOCK + 1)) * 8
}

/// Causal low-pass of the live path.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct LiveLowpass {
    /// Butterworth order (poles), 0 to 16; 0 turns the filter off. Default 2.
    pub order: usize,
    /// -3 dB cutoff, Hz, below half the sample rate. Default 10.
    pub cutoff_hz: f64,
}

impl Default for LiveLowpass {
    fn default() -> Self {
        LiveLowpass {
            order: 2,
            cutoff_hz: 10.0,
        }
    }
}

/// Causal normalization of the live path.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct LiveNormalize {
    /// Length of the rest-level window at the stream's start, ms (the array
    /// must rest on the object meanwhile). Default 500.
    pub baseline_ms: f64,
    /// Full-scale change of the (filtered) signal from rest, in DAQ units
    /// (e.g. V after the DAQ's scale): `V = |y - rest| / span`. Required; from
    /// a calibration recording ([`calibrate`]); e.g. 1.55 for the paper's board
    /// (1.75 V in contact, 3.3 V off).
    pub span: Option<f64>,
    /// Noise floor, DAQ units: deviations from rest up to it count as 0. Default 0.
    pub min_span: f64,
}

impl Default for LiveNormalize {
    fn default() -> Self {
        LiveNormalize {
            baseline_ms: 500.0,
            span: None,
            min_span: 0.0,
        }
    }
}

/// FA-I drive of the live path.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct LiveDrive {
    /// Fixed gain G of `I = G |dV/dt|`, current units per (normalized unit per
    /// second). Required: a live stream cannot set it from its own peak. From
    /// a calibration palpation, `G = 20 / max|dV/dt|` at the fastest
    /// crossing ([`calibrate`]); 20 to 40 suits the paper's protocol (2 mm/s,
    /// 2 mm taxels: `max|dV/dt|` is about 1/s at 90 degrees).
    pub gain: Option<f64>,
}

/// Live path: DAQ samples, frame by frame, through causal FA-I encoding to a running WSS estimate.
///
/// As a graph stage (`type = "live"`, signals -> estimates) it replays each
/// trial through exactly the live computation, frame by frame, and answers
/// what `palpate daq run` would have answered (the decision if
/// `stop_at_decision`, else the final estimate). The same table is what
/// `palpate daq run --config` reads. Steps: causal Butterworth low-pass,
/// causal normalization from a baseline and a calibrated span, FA-I drive
/// `G|dV/dt|` with a fixed gain, Izhikevich neurons with persistent state,
/// streaming binning, streaming WSS.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct LiveConfig {
    /// Taxel layout; channel `i` of the DAQ is taxel `i`. Default the paper's
    /// 4x4 grid (3 mm pitch, 2 mm taxels).
    pub layout: LayoutConfig,
    /// Sample rate of the DAQ, Hz. Default 1000.
    pub sample_rate_hz: f64,
    /// Causal Butterworth low-pass: `order` (default 2; 0 = off), `cutoff_hz` (default 10).
    pub lowpass: LiveLowpass,
    /// Causal normalization: `baseline_ms` (default 500), `span` (required), `min_span` (default 0).
    pub normalize: LiveNormalize,
    /// FA-I drive `I = G|dV/dt|`: `gain` (required, fixed).
    pub drive: LiveDrive,
    /// The Izhikevich encoder's keys (`preset`, default `fa_i`; `dt_ms`,
    /// default 0.5; `scheme`; `a`..`d`; `v_peak`); `input` must be `hold`.
    pub encoder: IzhikevichConfig,
    /// Spike images: `window_ms` (default 100), `hop_ms` (default 10).
    pub bin: BinConfig,
    /// WSS keys (`angles`, `sigma_mm`, `weighting`, `threshold`,
    /// `stop_margin`, ...; defaults the `wss` stage's). `stop_margin` marks the
    /// running estimate `decided` once the best class leads by it.
    pub wss: WssConfig,
    /// Longest run of lost frames filled by holding the previous frame, ms;
    /// a longer gap ends the run. Default 1000.
    pub max_gap_ms: f64,
    /// Stop the run at the first decided estimate (needs `wss.stop_margin`). Default false.
    pub stop_at_decision: bool,
}

impl Default for LiveConfig {
    fn default() -> Self {
        LiveConfig {
            layout: LayoutConfig::default(),
            sample_rate_hz: 1000.0,
            lowpass: LiveLowpass::default(),
            normalize: LiveNormalize::default(),
            drive: LiveDrive::default(),
            encoder: IzhikevichConfig::default(),
            bin: BinConfig::default(),
            wss: WssConfig::default(),
            max_gap_ms: 1000.0,
            stop_at_decision: false,
        }
    }
}

/// A checked [`LiveConfig`].
#[derive(Clone, Debug)]
pub(crate) struct Checked {
    pub layout: TaxelLayout,
    pub fs: f64,
    pub sos: Vec<Biquad>,
    pub nb: usize,
    pub span: f64,
    pub min_span: f64,
    pub gain: f64,
    pub neuron: Izhikevich,
    pub window_ms: f64,
    pub hop_ms: f64,
    pub wss: WssParams,
    pub stop_margin: Option<f64>,
    pub max_gap: u64,
    pub stop_at_decision: bool,
}

impl Checked {
    pub fn templates(&self) -> Result<Templates, ConfigError> {
        Templates::new(&self.layout, self.hop_ms, &self.wss)
    }
}

fn prefix(section: &str) -> impl Fn(ConfigError) -> ConfigError + '_ {
    move |e| e.within(section)
}

impl LiveConfig {
    /// Reads a live config from a TOML file: either a graph whose one stage of
    /// `type = "live"` holds the keys (like `graphs/live.toml`), or a file of
    /// the keys alone.
    pub fn from_file(path: &Path) -> Result<LiveConfig, ConfigError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| ConfigError::general(format!("cannot read {}: {e}", path.display())))?;
        Self::from_toml_str(&text).map_err(|e| e.context(&path.display().to_string()))
    }

    /// The config of an ordinary live graph: the keys of its one stage of
    /// each type `lowpass` (causal; absent = off), `normalize` (causal),
    /// `drive` (fixed `gain`), `izhikevich`, `bin` and `wss`; layout and rate
    /// are the board's defaults (the paper's 4x4 array at 1 kHz).
    fn from_stage_tables(stages: &toml::Table) -> Result<LiveConfig, ConfigError> {
        let of_type = |ty: &str| -> Result<Option<toml::Table>, ConfigError> {
            let found: Vec<&toml::Value> = stages
                .values()
                .filter(|v| v.get("type").and_then(|t| t.as_str()) == Some(ty))
                .collect();
            match found.as_slice() {
                [] => Ok(None),
                [v] => {
                    let mut t = v.as_table().cloned().unwrap_or_default();
                    t.remove("type");
                    t.remove("inputs");
                    Ok(Some(t))
                }
                _ => Err(ConfigError::general(format!(
                    "a live graph has one `{ty}` stage, found {}",
                    found.len()
                ))),
            }
        };
        fn parse<T: serde::de::DeserializeOwned>(ty: &str, t: toml::Table) -> Result<T, ConfigError> {
            toml::Value::Table(t)
                .try_into()
                .map_err(|e: toml::de::Error| ConfigError::key(ty, e.message().trim().to_string()))
        }
        let causal = |ty: &str, t: &mut toml::Table| -> Result<(), ConfigError> {
            match t.remove("mode") {
                Some(m) if m.as_str() == Some("causal") => Ok(()),
                _ => Err(ConfigError::key(
                    format!("{ty}.mode"),
                    "a live graph needs mode = \"causal\"",
                )),
            }
        };
        let mut cfg = LiveConfig::default();
        match of_type("lowpass")? {
            Some(mut t) => {
                causal("lowpass", &mut t)?;
                cfg.lowpass = parse("lowpass", t)?;
            }
            None => cfg.lowpass.order = 0,
        }
        let mut t = of_type("normalize")?.ok_or_else(|| {
            ConfigError::general("a live graph needs a `normalize` stage (mode = \"causal\")")
        })?;
        causal("normalize", &mut t)?;
        cfg.normalize = parse("normalize", t)?;
        let mut t =
            of_type("drive")?.ok_or_else(|| ConfigError::general("a live graph needs a `drive` stage"))?;
        if t.remove("kind").is_some_and(|k| k.as_str() != Some("fa_i")) {
            return Err(ConfigError::key(
                "drive.kind",
                "the DAQ path drives FA-I neurons: kind = \"fa_i\"",
            ));
        }
        cfg.drive = parse("drive", t)?;
        cfg.encoder = parse(
            "izhikevich",
            of_type("izhikevich")?
                .ok_or_else(|| ConfigError::general("a live graph needs an `izhikevich` stage"))?,
        )?;
        cfg.bin = parse("bin", of_type("bin")?.unwrap_or_default())?;
        cfg.wss = parse(
            "wss",
            of_type("wss")?.ok_or_else(|| ConfigError::general("a live graph needs a `wss` stage"))?,
        )?;
        Ok(cfg)
    }

    /// Parses the text of [`LiveConfig::from_file`].
    pub fn from_toml_str(text: &str) -> Result<LiveConfig, ConfigError> {
        let doc: toml::Table =
            toml::from_str(text).map_err(|e| ConfigError::general(e.message().trim().to_string()))?;
        let table = match doc.get("stages").and_then(|s| s.as_table()) {
            Some(stages) => {
                let live: Vec<(&String, &toml::Value)> = stages
                    .iter()
                    .filter(|(_, v)| v.get("type").and_then(|t| t.as_str()) == Some("live"))
                    .collect();
                if live.is_empty() {
                    // An ordinary live graph (graphs/live.toml): the keys of
                    // its causal stages, found by type.
                    let cfg = Self::from_stage_tables(stages)?;
                    cfg.check()?;
                    return Ok(cfg);
                }
                let [(_, v)] = live.as_slice() else {
                    return Err(ConfigError::general(format!(
                        "a graph used as a live config needs exactly one stage of type \"live\", found {}",
                        live.len()
                    )));
                };
                let mut t = v.as_table().cloned().unwrap_or_default();
                t.remove("type");
                t.remove("inputs");
                t
            }
            None => doc,
        };
        let cfg: LiveConfig = toml::Value::Table(table)
            .try_into()
            .map_err(|e: toml::de::Error| ConfigError::general(e.message().trim().to_string()))?;
        cfg.check()?;
        Ok(cfg)
    }

    /// The checked layout.
    pub fn taxel_layout(&self) -> Result<TaxelLayout, ConfigError> {
        self.layout.to_layout("layout")
    }

    /// Builds the WSS templates for this config (shareable between pipelines).
    pub fn templates(&self) -> Result<Arc<Templates>, ConfigError> {
        Ok(Arc::new(self.check()?.templates()?))
    }

    /// Checks every key and reports every problem at once (not only the
    /// first), each naming its key.
    pub(crate) fn check(&self) -> Result<Checked, ConfigError> {
        let mut c = ConfigChecks::new();
        let layout = c.take(self.taxel_layout());
        let fs = c.take(check_range("sample_rate_hz", self.sample_rate_hz, 1.0, 1e6, "Hz"));
        let lp = &self.lowpass;
        c.take(check_range("lowpass.order", lp.order as f64, 0.0, 16.0, ""));
        let sos = if lp.order == 0 || lp.order > 16 {
            Some(Vec::new())
        } else {
            let cutoff = c.take(check_positive("lowpass.cutoff_hz", lp.cutoff_hz, "Hz"));
            match (cutoff, fs) {
                (Some(cut), Some(fs)) if cut >= fs / 2.0 => {
                    c.push(ConfigError::key(
                        "lowpass.cutoff_hz",
                        format!("{cut} Hz must lie below the Nyquist frequency {} Hz", fs / 2.0),
                    ));
                    None
                }
                (Some(cut), Some(fs)) => {
                    Some(butterworth_sos(lp.order, (std::f64::consts::PI * cut / fs).tan()))
                }
                _ => None,
            }
        };
        let nm = &self.normalize;
        let baseline_ms = c.take(check_positive("normalize.baseline_ms", nm.baseline_ms, "ms"));
        let span = match nm.span {
            Some(s) => c.take(check_positive("normalize.span", s, "DAQ units")),
            None => {
                c.push(ConfigError::key(
                    "normalize.span",
                    "required: the full-scale change of the signal from rest, in DAQ units, from a \
                     calibration recording (live data cannot know its own range)",
                ));
                None
            }
        };
        let min_span = c.take(check_range(
            "normalize.min_span",
            nm.min_span,
            0.0,
            f64::MAX,
            "DAQ units",
        ));
        let gain = match self.drive.gain {
            Some(g) if g.is_finite() && g >= 0.0 => Some(g),
            Some(g) => {
                c.push(ConfigError::key(
                    "drive.gain",
                    format!("must be finite and >= 0, got {}", palpate_core::fmt_num(g)),
                ));
                None
            }
            None => {
                c.push(ConfigError::key(
                    "drive.gain",
                    "required: a fixed gain G of I = G|dV/dt| (live data cannot set it from its own \
                     peak); e.g. 20 / max|dV/dt| of a calibration palpation at 90 degrees",
                ));
                None
            }
        };
        let enc = &self.encoder;
        let params = c.take(enc.params().map_err(prefix("encoder")));
        let dt_ms = c.take(check_range("encoder.dt_ms", enc.dt_ms, 1e-4, 10.0, "ms"));
        if let (Some(p), Some(dt)) = (&params, dt_ms) {
            if p.a * dt > 1.0 {
                c.push(ConfigError::key(
                    "encoder.dt_ms",
                    format!("a * dt_ms = {} must be at most 1", p.a * dt),
                ));
            }
        }
        if enc.input != InputMode::Hold {
            c.push(ConfigError::key(
                "encoder.input",
                "the live path holds each sample (`hold`); `linear` would look one more sample ahead",
            ));
        }
        let window_ms = c.take(check_positive("bin.window_ms", self.bin.window_ms, "ms"));
        let hop_ms = c.take(check_positive("bin.hop_ms", self.bin.hop_ms, "ms"));
        let wss = c.take(self.wss.params().map_err(prefix("wss")));
        if self.stop_at_decision && self.wss.stop_margin.is_none() {
            c.push(ConfigError::key(
                "stop_at_decision",
                "needs `wss.stop_margin` (the lead that makes an estimate decided)",
            ));
        }
        let max_gap_ms = c.take(check_range("max_gap_ms", self.max_gap_ms, 0.0, 3.6e6, "ms"));
        c.finish()?;
        // Every `None` above pushed its problem, so after `finish` all are
        // `Some`; the fallback only guards that reasoning.
        let (
            Some(layout),
            Some(fs),
            Some(sos),
            Some(baseline_ms),
            Some(span),
            Some(min_span),
            Some(gain),
            Some(params),
            Some(window_ms),
            Some(hop_ms),
            Some(wss),
            Some(max_gap_ms),
        ) = (
            layout,
            fs,
            sos,
            baseline_ms,
            span,
            min_span,
            gain,
            params,
            window_ms,
            hop_ms,
            wss,
            max_gap_ms,
        )
        else {
            return Err(ConfigError::general("invalid live config"));
        };
        Ok(Checked {
            layout,
            fs,
            sos,
            nb: ((baseline_ms * fs / 1000.0).round() as usize).max(1),
            span,
            min_span,
            gain,
            neuron: Izhikevich {
                params,
                dt_ms: enc.dt_ms,
                scheme: enc.scheme,
                input: InputMode::Hold,
            },
            window_ms,
            hop_ms,
            wss,
            stop_margin: self.wss.stop_margin,
            max_gap: (max_gap_ms * fs / 1000.0).floor() as u64,
            stop_at_decision: self.stop_at_decision,
        })
    }
}

/// What [`calibrate`] found in a calibration recording.
#[derive(Clone, Debug, PartialEq)]
pub struct Calibration {
    /// Largest deviation of any taxel's filtered signal from its rest level, DAQ units: `normalize.span`.
    pub span: f64,
    /// Largest `|dV/dt|` of the normalized signals (with that span), per second.
    pub peak_slope: f64,
    /// `target_peak_current / peak_slope`: `drive.gain` (0 if nothing changed).
    pub gain: f64,
}

/// Finds `normalize.span` and `drive.gain` from a calibration recording (a
/// palpation at the fastest crossing expected, e.g. 90 degrees), with the
/// config's low-pass and baseline: `span` = largest `|y − rest|` over the
/// taxels after the baseline, `gain = target_peak_current / max|dV/dt|` of the
/// signals normalized with that span (central differences, as the drive).
pub fn calibrate(
    signals: &Signals,
    cfg: &LiveConfig,
    target_peak_current: f64,
) -> Result<Calibration, StageError> {
    crate::signal::check_signals("calibrate", signals)?;
    check_positive("target_peak_current", target_peak_current, "current units")
        .map_err(|e| StageError::new(e.to_string()))?;
    let mut c = cfg.clone();
    c.normalize.span = Some(1.0);
    c.drive.gain = Some(1.0);
    c.sample_rate_hz = signals.sample_rate_hz;
    let ck = c
        .check()
        .map_err(|e| StageError::new(format!("calibrate: {e}")))?;
    let n = signals.n_samples();
    if ck.nb >= n {
        return Err(StageError::new(format!(
            "calibrate: the recording ({n} samples) is no longer than the baseline ({} samples)",
            ck.nb
        )));
    }
    let filtered: Vec<Vec<f64>> = signals
        .data
        .iter()
        .map(|xs| {
            let mut y = xs.clone();
            crate::signal::lowpass::sosfilt(&ck.sos, &mut y);
            y
        })
        .collect();
    let mut span: f64 = 0.0;
    let rests: Vec<f64> = filtered
        .iter()
        .map(|y| y[..ck.nb].iter().sum::<f64>() / ck.nb as f64)
        .collect();
    for (y, r) in filtered.iter().zip(&rests) {
        for &v in &y[ck.nb..] {
            span = span.max((v - r).abs());
        }
    }
    let mut peak: f64 = 0.0;
    if span > 0.0 {
        for y in &filtered {
            let v = crate::signal::normalize::normalize_causal(y, ck.nb, span, ck.min_span);
            let d = crate::signal::derivative::differentiate(&v, signals.sample_rate_hz, Default::default());
            peak = d.iter().fold(peak, |m, x| m.max(x.abs()));
        }
    }
    Ok(Calibration {
        span,
        peak_slope: peak,
        gain: if peak > 0.0 {
            target_peak_current / peak
        } else {
            0.0
        },
    })
}

/// Simulates one trial of a scene file at `angle_deg`: exactly the trial
/// `r00` at that angle of a graph with `[run] seed = <seed>` and a stage
/// `[stages.scene] type = "scene", file = <scene_file>` (the same seeds), for
/// `palpate daq emulate` to play through a pseudo-terminal.
pub fn simulate_trial(scene_file: &Path, angle_deg: f64, seed: u64) -> Result<Signals, StageError> {
    use crate::scene::{config::Angles, trial_id, SceneConfig, Simulator};
    let config = SceneConfig {
        file: Some(scene_file.to_path_buf()),
        angles: Some(Angles::List(vec![angle_deg])),
        trials_per_angle: Some(1),
        ..SceneConfig::default()
    };
    let ctx = BuildContext {
        stage_id: "scene".into(),
        seed,
        out_dir: PathBuf::from("."),
        base_dir: PathBuf::from("."),
    };
    let scene = config
        .resolve(&ctx)
        .map_err(|e| StageError::new(format!("scene file {}: {e}", scene_file.display())))?;
    let stimulus = scene.stimulus;
    let sim = Simulator::new(scene, derive_seed(seed, &["scene", "array"]))
        .map_err(|e| StageError::new(format!("scene file {}: {e}", scene_file.display())))?;
    let id = trial_id(stimulus, angle_deg, 0);
    sim.simulate(angle_deg, derive_seed(seed, &["scene", &id]))
}

#[typetag::serde(name = "live")]
impl StageConfig for LiveConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::one(PayloadKind::Signals)
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Estimates)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        let checked = self.check()?;
        Ok(Stage::Map(Box::new(LiveStage {
            checked,
            templates: OnceLock::new(),
        })))
    }
}
register_stage!("live", LiveConfig);

/// The runtime `live` stage: replays each trial frame by frame.
struct LiveStage {
    checked: Checked,
    templates: OnceLock<Arc<Templates>>,
}

impl Map for LiveStage {
    fn process(&self, inputs: &[&Item], _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let s = inputs[0].payload.signals()?;
        crate::signal::check_signals("live", s)?;
        let c = &self.checked;
        if s.layout != c.layout {
            return Err(StageError::new(format!(
                "live: the signals' layout ({} taxels) differs from key `layout` ({} taxels)",
                s.layout.len(),
                c.layout.len()
            )));
        }
        if s.sample_rate_hz != c.fs {
            return Err(StageError::new(format!(
                "live: the signals are sampled at {} Hz, key `sample_rate_hz` = {} Hz",
                s.sample_rate_hz, c.fs
            )));
        }
        let tpl = match self.templates.get() {
            Some(t) => t.clone(),
            None => {
                let t = Arc::new(c.templates().map_err(|e| StageError::new(format!("live: {e}")))?);
                self.templates.get_or_init(|| t).clone()
            }
        };
        let mut p =
            LivePipeline::from_checked(c.clone(), tpl).map_err(|e| StageError::new(format!("live: {e}")))?;
        let mut frame = vec![0.0; s.data.len()];
        for k in 0..s.n_samples() {
            for (f, xs) in frame.iter_mut().zip(&s.data) {
                *f = xs[k];
            }
            p.push(&frame)?;
            if c.stop_at_decision {
                if let Some(d) = p.decision() {
                    return Ok(d.estimate.clone().into());
                }
            }
        }
        Ok(p.finish()?.estimate.into())
    }
}
