//! The `daq` source stage: trials from a DAQ byte stream, cut where the array
//! touches the object (or in fixed windows).
//!
//! The bytes come from a serial port (`port`, `baud`), a recorded raw stream
//! (`recording`) or an emulated scene (`scene`: the scene's trials played as
//! DAQ frames, with `gap_ms` off the object between them), and go through the
//! same path in every case: [`acquire`] (reader thread, stall detection, raw
//! recording with `record`), the [`Decoder`](super::Decoder) (CRC, sequence
//! gaps), gap filling, then a [`Segmenter`] that cuts the stream into trials.
//! When several are given, `port` wins over `recording`, and `recording` over
//! `scene`, so `--set stages.daq.port=...` turns an emulated graph into one
//! on a board.
//!
//! ## Segmentation
//!
//! * `segment = "contact"` (default): a trial is a stretch of contact. Let
//!   `m_k` be the lowest taxel value of frame `k` (a pressed piezoresistive
//!   taxel reads low; a dead one reads open-circuit high, so the minimum is
//!   not fooled by it). Contact begins at the first frame of a run of
//!   `N_in = max(1, round(enter_ms·fs/1000))` frames with `m_k <= contact_v`,
//!   and ends before the first frame of a run of
//!   `N_out = max(1, round(exit_ms·fs/1000))` frames with `m_k >= release_v`.
//!   `release_v > contact_v` is the hysteresis: noise around one threshold
//!   cannot start and stop trials. A sensor whose output rises with pressure
//!   (`contact_polarity = "rises"`) uses the highest taxel with the
//!   inequalities turned: `m_k >= contact_v` begins, `m_k <= release_v`
//!   ends, `release_v < contact_v`. The frames of a run that does not complete
//!   belong to the state it interrupted (a short dip back to the open level
//!   stays inside its trial). A trial still open when the stream ends ends
//!   there (and is scored); when a `recording` ends so, in contact, a
//!   warning names the file and the trial cut short. Latency: the first
//!   `N_in` frames of a trial are handed on together once contact is
//!   confirmed; frames during a possible release are held until it is
//!   confirmed or denied (at most `N_out` frames).
//! * `segment = "fixed"`: consecutive trials of `W = round(window_ms·fs/1000)`
//!   frames from the first frame on (the last may be shorter).
//!
//! ## The stream
//!
//! Time is the frame count over `sample_rate_hz`. A sequence gap of lost
//! frames (CRC errors included) is filled by holding the previous frame, up
//! to `max_gap_ms`; a longer gap ends the run with an error. A frame with a
//! non-finite sample is an error naming it, and so is a frame whose sample
//! format differs from the stream's or whose timestamp lies off the uniform
//! grid of the frames before it ([`FrameCheck`](super::FrameCheck), checked
//! as the frames arrive, in constant memory). Anomalies (CRC errors, gaps,
//! out-of-order frames, stalls) are reported on stderr as they happen.
//!
//! A `recording` is decoded once before it streams (constant memory): one
//! that ends inside a frame (copied or stopped while being written) is
//! refused with an error naming the file and the byte, as `signal_file`
//! refuses it, unless `allow_cut_end = true`, which drops that frame; one
//! holding valid frames of another channel count is refused too.
//!
//! The frames' timestamps must keep the pace of `sample_rate_hz` (within
//! half a sample and 0.1 %, `RateCheck`): a board stamping 500 Hz read
//! at the default 1 kHz is an error naming both rates, not trials stretched
//! twofold. A board without a clock (every timestamp equal) is not timed.
//!
//! A stream that ends without a trial is an error, offline and live alike,
//! naming why (no valid frame, with a recording's counts; or no contact,
//! with the levels seen, on stderr): the end of a recording or of an
//! emulated scene, a pseudo-terminal's hang-up, or `seconds` elapsed. Only a
//! live session the user stops (Ctrl-C) before any contact is not a failure:
//! a board streams until stopped, and nothing touched it yet.
//!
//! An emulated scene's random draws (the array's and each trial's) are
//! keyed by the stage id `scene_stage_id` (default this stage's id), as a
//! `scene` stage of that id keys its own: `scene_stage_id = "scene"` plays
//! the trials `palpate simulate` and `palpate daq emulate` give for the same
//! run seed and angles.
//!
//! Offline (`palpate run`), the stream is acquired to its end (a recording's
//! end, the scene's last trial, `seconds`, or a pseudo-terminal's hang-up) and
//! its trials are an ordinary source's. Live (`palpate run --live`), each
//! trial's frames stream through the graph as they arrive
//! ([`palpate_core::stream::LiveSource`]). Contact trials of an emulated
//! scene carry the scene's labels (the `k`-th contact is the scene's `k`-th
//! trial); others are named `<stage>-0000`, `<stage>-0001`, ... without a label.

use super::live::{acquire, open_serial, AcquireOptions, DaqErrorKind, DaqEvent, EmulateOptions, StopReason};
use crate::io::common::LayoutConfig;
use crate::scene::SceneConfig;
use palpate_core::stream::{LiveSource, SourceEvent};
use palpate_core::{
    check_positive, check_range, derive_seed, fmt_num, register_stage, BuildContext, ConfigChecks,
    ConfigError, InputSpec, Inspection, OutputFacts, Payload, PayloadKind, RunError, Signals, Source, Stage,
    StageConfig, StageError, TaxelLayout, TrialContext, TrialMeta,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::io::{Read, Write};
use std::ops::ControlFlow;
use std::path::PathBuf;
use std::sync::{mpsc, Arc, OnceLock};
use std::time::Duration;

/// Holds a stream's timestamps to the source's `sample_rate_hz`: time is
/// the frame count over that rate, so frames stamped at another rate (a
/// board at 500 Hz read as 1 kHz) would silently stretch every trial. Over
/// each run of consecutive sequence numbers from frame `(q0, t0)`, frame
/// `(q, t)` with `n = q − q0` must satisfy `|t − t0 − n·T| <= T/2 + 0.001·n·T`
/// (`T = 1e6 / fs` µs): the half sample [`FrameCheck`](super::FrameCheck)'s
/// quarter-sample grid allows at both ends, plus a 0.1 % clock tolerance
/// (the one `signal_file` holds a recording's rate to). Lost frames keep
/// the run (their time passed too: `n` counts sequence steps); a reset
/// (the sequence or the clock going back) starts a new one; a board without
/// a clock (every timestamp equal) is not checked.
struct RateCheck {
    period_us: f64,
    run: Option<(u32, u64)>,
}

impl RateCheck {
    fn new(fs: f64) -> Self {
        RateCheck {
            period_us: 1e6 / fs,
            run: None,
        }
    }

    fn push(&mut self, k: u64, seq: u32, t: u64) -> Result<(), String> {
        let Some((q0, t0)) = self.run else {
            self.run = Some((seq, t));
            return Ok(());
        };
        let n = seq.wrapping_sub(q0);
        if !(1..1 << 31).contains(&n) || t < t0 {
            self.run = Some((seq, t));
            return Ok(());
        }
        if t == t0 {
            return Ok(());
        }
        let p = self.period_us;
        let n = f64::from(n);
        let span = (t - t0) as f64;
        if (span - n * p).abs() > 0.5 * p + 0.001 * n * p {
            let per = span / n;
            return Err(format!(
                "frame {k} (sequence {seq}): the timestamps advance {} µs a frame ({} Hz), but \
                 `sample_rate_hz` is {} Hz ({} µs): set `sample_rate_hz` to the board's rate",
                (per * 1e3).round() / 1e3,
                fmt_num((1e9 / per).round() / 1e3),
                fmt_num(1e6 / p),
                (p * 1e3).round() / 1e3
            ));
        }
        Ok(())
    }
}

/// How the stream is cut into trials.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum SegmentMode {
    /// A trial per stretch of contact (`contact_v`, `release_v`, `enter_ms`, `exit_ms`).
    #[default]
    Contact,
    /// Consecutive trials of `window_ms`.
    Fixed,
}

/// Which way a sensor's output moves with pressure (`contact_polarity`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Polarity {
    /// The output falls with pressure (a piezoresistive divider, as the paper's).
    #[default]
    Falls,
    /// The output rises with pressure.
    Rises,
}

impl Polarity {
    /// Checks `contact_v` and `release_v` (finite, release past contact
    /// the polarity's way) into `c`; returns them when both are good.
    pub fn check_thresholds(
        self,
        c: &mut ConfigChecks,
        contact: f64,
        release: f64,
        unit: &str,
    ) -> Option<(f64, f64)> {
        let contact = c.take(check_range("contact_v", contact, -1e12, 1e12, unit));
        let release = c.take(check_range("release_v", release, -1e12, 1e12, unit));
        let (a, b) = (contact?, release?);
        let (ok, side, name) = match self {
            Polarity::Falls => (b > a, "above", "falls"),
            Polarity::Rises => (b < a, "below", "rises"),
        };
        if !ok {
            c.push(ConfigError::key(
                "release_v",
                format!("must lie {side} contact_v = {a} (the hysteresis; contact_polarity = \"{name}\"), got {b}"),
            ));
            return None;
        }
        Some((a, b))
    }
}

/// DAQ source: trials from a serial port, a raw recording or an emulated scene, cut at contact.
///
/// One of `port`, `recording`, `scene` (that order wins when several are
/// set). Offline, the whole stream is acquired and cut into trials; with
/// `palpate run --live` each trial streams through the graph frame by frame.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct DaqConfig {
    /// Serial device of the board, e.g. `/dev/ttyACM0` (or an emulator's
    /// pseudo-terminal). Default none.
    pub port: Option<String>,
    /// Baud rate of `port`, bit/s (USB CDC devices ignore it). Default 921600.
    pub baud: u32,
    /// A recorded raw DAQ stream (what `record` writes), relative to the
    /// graph's folder. Default none.
    pub recording: Option<PathBuf>,
    /// With `recording`: accept a recording that ends inside a frame (a
    /// recording stopped or copied while being written); that incomplete
    /// frame is dropped. Without it such a recording is refused before any
    /// of it streams, as `signal_file` refuses it. Default false.
    pub allow_cut_end: bool,
    /// A scene file to emulate, relative to the graph's folder: its trials
    /// are simulated and played as DAQ frames (f32), `gap_ms` apart. Default none.
    pub scene: Option<PathBuf>,
    /// With `scene`: the angles to simulate, degrees. Default the scene's.
    pub angles: Option<Vec<f64>>,
    /// With `scene`: trials per angle. Default the scene's.
    pub trials_per_angle: Option<usize>,
    /// With `scene`: playback speed, times real time; 0 plays as fast as the
    /// graph reads. Default 0.
    pub speed: f64,
    /// With `scene`: time off the object between emulated trials, ms. Default 1000.
    pub gap_ms: f64,
    /// With `scene`: what every taxel reads off the object, DAQ units (V).
    /// Default 3.3 (the paper's board saturates at its supply).
    pub open_v: f64,
    /// With `scene`: the stage id the emulated scene draws its random
    /// numbers as (array and per-trial noise). A `scene` stage of this id
    /// with the same file, angles and run seed simulates the same trials to
    /// the bit; `palpate simulate` and `palpate daq emulate` draw as
    /// `scene`, and `palpate daq run --emulate-scene` sets that. Default
    /// none: this stage's own id.
    pub scene_stage_id: Option<String>,
    /// Taxel layout; channel `i` is taxel `i`. Default: with `scene` (and no
    /// `port` or `recording`), the emulated scene's array (a layout of
    /// another taxel count is then an error); else the paper's 4x4 grid
    /// (3 mm pitch, 2 mm taxels).
    /// (`kind = "grid"` or `"positions"` may be left out: `positions_mm` or
    /// `rows`/`cols` tell it.)
    #[serde(default, deserialize_with = "crate::io::common::layout_with_inferred_kind")]
    pub layout: Option<LayoutConfig>,
    /// Frame rate of the board, Hz. Default: with `scene` alone, the
    /// scene's rate (another value is then an error: the emulator plays the
    /// scene's samples as frames); else 1000.
    pub sample_rate_hz: Option<f64>,
    /// Decoded value = raw · `scale` + `offset` (e.g. V per ADC count). Default 1.
    pub scale: f64,
    /// See `scale`, DAQ units. Default 0.
    pub offset: f64,
    /// Unit of the decoded values. Default "V".
    pub unit: String,
    /// Trial segmentation: `contact` or `fixed`. Default `contact`.
    pub segment: SegmentMode,
    /// Contact begins when the lowest taxel reads at most this (the highest at
    /// least this, with `contact_polarity = "rises"`), DAQ units (V). Default 3.0.
    pub contact_v: f64,
    /// Contact ends when the lowest taxel reads at least this, DAQ units (V);
    /// above `contact_v` (hysteresis; below it, and the highest taxel at
    /// most this, with `contact_polarity = "rises"`). Default 3.2.
    pub release_v: f64,
    /// How the output moves with pressure: `falls` (a piezoresistive
    /// divider, as the paper's board) or `rises`; see `contact_v`. Default falls.
    pub contact_polarity: Polarity,
    /// Contact must hold this long to begin a trial, ms. Default 20.
    pub enter_ms: f64,
    /// Release must hold this long to end a trial, ms. Default 200.
    pub exit_ms: f64,
    /// With `segment = "fixed"`: trial length, ms. Required there.
    pub window_ms: Option<f64>,
    /// Record the raw byte stream to this file as it arrives, relative to the
    /// output folder. Default none.
    pub record: Option<PathBuf>,
    /// Stop acquiring after this much wall time, s. Default none (the stream's end).
    pub seconds: Option<f64>,
    /// Longest run of lost frames filled by holding the previous frame, ms; a
    /// longer gap ends the run. Default 1000.
    pub max_gap_ms: f64,
    /// Silence longer than this counts as a stall (reported), ms. Default 500.
    pub stall_ms: f64,
    /// Silence longer than this ends the run with an error, ms. Default 5000.
    pub give_up_ms: f64,
}

impl Default for DaqConfig {
    fn default() -> Self {
        DaqConfig {
            port: None,
            baud: 921_600,
            recording: None,
            allow_cut_end: false,
            scene: None,
            angles: None,
            trials_per_angle: None,
            speed: 0.0,
            gap_ms: 1000.0,
            open_v: 3.3,
            scene_stage_id: None,
            layout: None,
            sample_rate_hz: None,
            scale: 1.0,
            offset: 0.0,
            unit: "V".into(),
            segment: SegmentMode::Contact,
            contact_v: 3.0,
            release_v: 3.2,
            contact_polarity: Polarity::Falls,
            enter_ms: 20.0,
            exit_ms: 200.0,
            window_ms: None,
            record: None,
            seconds: None,
            max_gap_ms: 1000.0,
            stall_ms: 500.0,
            give_up_ms: 5000.0,
        }
    }
}

/// Where the bytes come from.
#[derive(Clone)]
enum Input {
    Port(String),
    Recording(PathBuf),
    Scene(Arc<dyn Source>),
}

/// The checked segmentation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SegmentPlan {
    /// See the module docs; run lengths in frames.
    Contact {
        /// `contact_v`.
        contact: f64,
        /// `release_v`.
        release: f64,
        /// Whether the output rises with pressure (the highest taxel then
        /// decides, the inequalities turned).
        rises: bool,
        /// `N_in`.
        enter: usize,
        /// `N_out`.
        exit: usize,
    },
    /// Trials of this many frames.
    Fixed(usize),
}

/// What the [`Segmenter`] hands on, in stream order.
#[derive(Debug, PartialEq)]
pub enum SegEvent<'a> {
    /// A trial begins.
    Start,
    /// The trial's next frame (one value per taxel).
    Frame(&'a [f64]),
    /// The trial ends.
    End,
}

/// Cuts a stream of frames into trials (see the module docs). Holds at most
/// `max(N_in, N_out)` frames, whatever the stream's length.
#[derive(Clone, Debug)]
pub struct Segmenter {
    plan: SegmentPlan,
    in_trial: bool,
    /// Frames of a run that has not yet decided (contact) or the frames of
    /// the open trial so far (fixed: only counted).
    held: Vec<Vec<f64>>,
    count: usize,
    /// Contact: the range of the frames' lowest taxel so far, and the
    /// longest run of frames at or under `contact` outside a trial (what
    /// [`Self::levels`] reports when no trial began).
    lows: (f64, f64),
    longest_under: usize,
}

/// What a [`Segmenter`] saw of the frames' deciding taxel (contact plans):
/// the lowest taxel of each frame, the highest for a rising output.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Levels {
    /// Lowest and highest of the frames' deciding taxel.
    pub low_range: (f64, f64),
    /// Longest run of frames in contact range (at or under `contact_v`; at
    /// or over it for a rising output) outside a trial.
    pub longest_under: usize,
}

impl Segmenter {
    /// A segmenter following `plan`.
    pub fn new(plan: SegmentPlan) -> Self {
        Segmenter {
            plan,
            in_trial: false,
            held: Vec::new(),
            count: 0,
            lows: (f64::INFINITY, f64::NEG_INFINITY),
            longest_under: 0,
        }
    }

    /// The levels seen so far, for a contact plan that has seen a frame.
    pub fn levels(&self) -> Option<Levels> {
        (self.lows.0 <= self.lows.1).then_some(Levels {
            low_range: self.lows,
            longest_under: self.longest_under,
        })
    }

    /// Whether a trial is open.
    pub fn in_trial(&self) -> bool {
        self.in_trial
    }

    /// Frames held back, waiting for a run to decide.
    pub fn held(&self) -> usize {
        self.held.len()
    }

    /// Takes the next frame; `on` gets what it completes.
    pub fn push<E>(
        &mut self,
        frame: &[f64],
        on: &mut impl FnMut(SegEvent<'_>) -> Result<(), E>,
    ) -> Result<(), E> {
        match self.plan {
            SegmentPlan::Fixed(w) => {
                if !self.in_trial {
                    on(SegEvent::Start)?;
                    self.in_trial = true;
                    self.count = 0;
                }
                on(SegEvent::Frame(frame))?;
                self.count += 1;
                if self.count >= w {
                    self.in_trial = false;
                    on(SegEvent::End)?;
                }
            }
            SegmentPlan::Contact {
                contact,
                release,
                enter,
                exit,
                rises,
            } => {
                let m = if rises {
                    frame.iter().copied().fold(f64::NEG_INFINITY, f64::max)
                } else {
                    frame.iter().copied().fold(f64::INFINITY, f64::min)
                };
                self.lows = (self.lows.0.min(m), self.lows.1.max(m));
                let (pressed, released) = if rises {
                    (m >= contact, m <= release)
                } else {
                    (m <= contact, m >= release)
                };
                if !self.in_trial {
                    if pressed {
                        self.held.push(frame.to_vec());
                        self.longest_under = self.longest_under.max(self.held.len());
                        if self.held.len() >= enter {
                            self.in_trial = true;
                            on(SegEvent::Start)?;
                            for f in std::mem::take(&mut self.held) {
                                on(SegEvent::Frame(&f))?;
                            }
                        }
                    } else {
                        self.held.clear();
                    }
                } else if released {
                    self.held.push(frame.to_vec());
                    if self.held.len() >= exit {
                        self.held.clear();
                        self.in_trial = false;
                        on(SegEvent::End)?;
                    }
                } else {
                    for f in std::mem::take(&mut self.held) {
                        on(SegEvent::Frame(&f))?;
                    }
                    on(SegEvent::Frame(frame))?;
                }
            }
        }
        Ok(())
    }

    /// The stream ended: closes an open trial (with its held frames).
    pub fn finish<E>(&mut self, on: &mut impl FnMut(SegEvent<'_>) -> Result<(), E>) -> Result<(), E> {
        let held = std::mem::take(&mut self.held);
        if self.in_trial {
            for f in held {
                on(SegEvent::Frame(&f))?;
            }
            self.in_trial = false;
            on(SegEvent::End)?;
        }
        Ok(())
    }
}

/// A checked [`DaqConfig`].
#[derive(Clone)]
struct Checked {
    input: Input,
    baud: u32,
    layout: TaxelLayout,
    fs: f64,
    scale: f64,
    offset: f64,
    unit: String,
    plan: SegmentPlan,
    gap_frames: usize,
    open_v: f64,
    speed: f64,
    /// The stage id an emulated scene's draws are keyed by.
    scene_stage: String,
    allow_cut_end: bool,
    record: Option<PathBuf>,
    seconds: Option<f64>,
    max_gap: u64,
    stall: Duration,
    give_up: Duration,
}

impl DaqConfig {
    /// The scene this config emulates: only with `scene` and neither `port`
    /// nor `recording` (which win over it).
    fn emulated_scene(&self) -> Option<SceneConfig> {
        match (&self.port, &self.recording, &self.scene) {
            (None, None, Some(file)) => Some(SceneConfig {
                file: Some(file.clone()),
                angles: self.angles.clone().map(crate::scene::config::Angles::List),
                trials_per_angle: self.trials_per_angle,
                ..SceneConfig::default()
            }),
            _ => None,
        }
    }

    /// Checks every key, naming each bad one (all at once).
    fn check(&self, ctx: &BuildContext) -> Result<Checked, ConfigError> {
        let mut c = ConfigChecks::new();
        let scale = c.take(check_range(
            "scale",
            self.scale,
            -1e12,
            1e12,
            "DAQ units per count",
        ));
        if self.scale == 0.0 {
            c.push(ConfigError::key("scale", "must not be 0"));
        }
        let offset = c.take(check_range("offset", self.offset, -1e12, 1e12, "DAQ units"));
        let speed = c.take(check_range("speed", self.speed, 0.0, 1e6, "x real time"));
        let gap_ms = c.take(check_range("gap_ms", self.gap_ms, 0.0, 3.6e6, "ms"));
        let open_v = c.take(check_range("open_v", self.open_v, -1e12, 1e12, "DAQ units"));
        let thresholds =
            self.contact_polarity
                .check_thresholds(&mut c, self.contact_v, self.release_v, "DAQ units");
        let enter_ms = c.take(check_range("enter_ms", self.enter_ms, 0.0, 3.6e6, "ms"));
        let exit_ms = c.take(check_range("exit_ms", self.exit_ms, 0.0, 3.6e6, "ms"));
        let window_ms = match (self.segment, self.window_ms) {
            (SegmentMode::Fixed, None) => {
                c.push(ConfigError::key(
                    "window_ms",
                    "required with segment = \"fixed\": the length of each trial, ms",
                ));
                None
            }
            (_, Some(w)) => c.take(check_positive("window_ms", w, "ms")),
            (SegmentMode::Contact, None) => Some(0.0),
        };
        let max_gap_ms = c.take(check_range("max_gap_ms", self.max_gap_ms, 0.0, 3.6e6, "ms"));
        let stall_ms = c.take(check_positive("stall_ms", self.stall_ms, "ms"));
        let give_up_ms = c.take(check_positive("give_up_ms", self.give_up_ms, "ms"));
        if let Some(s) = self.seconds {
            c.take(check_positive("seconds", s, "s"));
        }
        if self.angles.is_some() && self.scene.is_none() {
            c.push(ConfigError::key(
                "angles",
                "only with `scene` (the angles to emulate)",
            ));
        }
        if self.scene_stage_id.is_some() && self.scene.is_none() {
            c.push(ConfigError::key(
                "scene_stage_id",
                "only with `scene` (the id the emulated scene draws as)",
            ));
        }
        if self
            .scene_stage_id
            .as_deref()
            .is_some_and(|id| id.trim().is_empty())
        {
            c.push(ConfigError::key(
                "scene_stage_id",
                "must not be empty (leave it out to draw as this stage)",
            ));
        }
        if self.allow_cut_end && self.recording.is_none() {
            c.push(ConfigError::key(
                "allow_cut_end",
                "only with `recording` (a live port's stream has no end to cut)",
            ));
        }
        // The emulated scene is built as a `scene` stage of this id would be.
        let scene_ctx = BuildContext {
            stage_id: self
                .scene_stage_id
                .clone()
                .unwrap_or_else(|| ctx.stage_id.clone()),
            ..ctx.clone()
        };
        let mut emulated: Option<(TaxelLayout, f64)> = None;
        let input = match (&self.port, &self.recording, self.emulated_scene()) {
            (Some(p), _, _) => Some(Input::Port(p.clone())),
            (None, Some(r), _) => Some(Input::Recording(ctx.base_dir.join(r))),
            (None, None, Some(scene)) => {
                // The board an emulated scene stands for has the scene's
                // array and rate unless the keys say otherwise.
                if let Ok(sc) = scene.resolve(&scene_ctx) {
                    emulated = Some((sc.layout.clone(), sc.motion.sample_rate_hz));
                }
                match c.take(scene.build(&scene_ctx).map_err(|e| e.within("scene"))) {
                    Some(Stage::Source(src)) => Some(Input::Scene(Arc::from(src))),
                    _ => None,
                }
            }
            (None, None, None) => {
                c.push(ConfigError::general(
                    "give one of `port` (a serial device), `recording` (a raw DAQ file) or `scene` (a scene file to emulate)",
                ));
                None
            }
        };
        let layout = match (&self.layout, &emulated) {
            (Some(l), _) => c.take(l.to_layout("layout")),
            (None, Some((l, _))) => Some(l.clone()),
            (None, None) => c.take(LayoutConfig::default().to_layout("layout")),
        };
        let fs = self
            .sample_rate_hz
            .or(emulated.as_ref().map(|e| e.1))
            .unwrap_or(1000.0);
        let fs = c.take(check_range("sample_rate_hz", fs, 1.0, 1e6, "Hz"));
        // An emulated board plays the scene's samples as its frames, so its
        // rate and taxel count must be the scene's: said here, not when the
        // first trial plays.
        if let Some((scene_layout, scene_fs)) = &emulated {
            if let Some(r) = self.sample_rate_hz.filter(|r| r != scene_fs) {
                c.push(ConfigError::key(
                    "sample_rate_hz",
                    format!(
                        "{} Hz, but the emulated scene samples at {} Hz: leave the key out or set the scene's `motion.sample_rate_hz`",
                        fmt_num(r),
                        fmt_num(*scene_fs)
                    ),
                ));
            }
            if let Some(l) = layout.as_ref().filter(|l| l.len() != scene_layout.len()) {
                c.push(ConfigError::key(
                    "layout",
                    format!(
                        "{} taxels, but the emulated scene's array has {}: leave the key out to use the scene's",
                        l.len(),
                        scene_layout.len()
                    ),
                ));
            }
        }
        c.finish()?;
        let (
            Some(input),
            Some(layout),
            Some(fs),
            Some(scale),
            Some(offset),
            Some(speed),
            Some(gap_ms),
            Some(open_v),
            Some((contact, release)),
            Some(enter_ms),
            Some(exit_ms),
            Some(window_ms),
            Some(max_gap_ms),
            Some(stall_ms),
            Some(give_up_ms),
        ) = (
            input, layout, fs, scale, offset, speed, gap_ms, open_v, thresholds, enter_ms, exit_ms,
            window_ms, max_gap_ms, stall_ms, give_up_ms,
        )
        else {
            return Err(ConfigError::general("invalid daq config"));
        };
        let frames = |ms: f64| ((ms * fs / 1000.0).round() as usize).max(1);
        let plan = match self.segment {
            SegmentMode::Contact => SegmentPlan::Contact {
                contact,
                release,
                enter: frames(enter_ms),
                exit: frames(exit_ms),
                rises: self.contact_polarity == Polarity::Rises,
            },
            SegmentMode::Fixed => SegmentPlan::Fixed(frames(window_ms)),
        };
        Ok(Checked {
            input,
            baud: self.baud,
            layout,
            fs,
            scale,
            offset,
            unit: self.unit.clone(),
            plan,
            gap_frames: (gap_ms * fs / 1000.0).round() as usize,
            open_v,
            speed,
            scene_stage: scene_ctx.stage_id,
            allow_cut_end: self.allow_cut_end,
            record: self.record.as_ref().map(|r| ctx.out_dir.join(r)),
            seconds: self.seconds,
            max_gap: (max_gap_ms * fs / 1000.0).floor() as u64,
            stall: Duration::from_secs_f64(stall_ms / 1000.0),
            give_up: Duration::from_secs_f64(give_up_ms / 1000.0),
        })
    }
}

#[typetag::serde(name = "daq")]
impl StageConfig for DaqConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::none()
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Signals)
    }
    fn build(&self, ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Ok(Stage::Source(Box::new(DaqSource::new(self, ctx)?)))
    }
    /// The board's frame rate and array as the checked config settles them
    /// (an emulated scene's unless `sample_rate_hz` or `layout` say
    /// otherwise), so that a low-pass checks its cutoff against the rate
    /// and a `union` warns when its sources' arrays differ before anything
    /// runs; and an emulated scene's own warnings (deprecated keys), under
    /// `scene`. Nothing is known of a config `build` rejects (it reports
    /// why).
    fn inspect(&self, ctx: &BuildContext, _inputs: &[OutputFacts]) -> Inspection {
        let Ok(c) = self.check(ctx) else {
            return Inspection::default();
        };
        let warnings = self
            .emulated_scene()
            .map(|s| s.inspect(ctx, &[]).warnings)
            .unwrap_or_default()
            .into_iter()
            .map(|w| w.within("scene"))
            .collect();
        Inspection {
            facts: OutputFacts {
                sample_rate_hz: Some(c.fs),
                layout: Some(c.layout),
            },
            errors: Vec::new(),
            warnings,
        }
    }
}
register_stage!("daq", DaqConfig);

/// Every trial of a stream acquired offline, or why not.
type Acquired = Result<Vec<(TrialMeta, Arc<Signals>)>, String>;

/// The runtime `daq` source (offline and live).
pub struct DaqSource {
    c: Checked,
    stage_id: String,
    seed: u64,
    /// Offline: every trial, acquired once.
    trials: OnceLock<Acquired>,
}

impl DaqSource {
    /// Checks the config and builds the source (nothing is opened yet).
    pub fn new(cfg: &DaqConfig, ctx: &BuildContext) -> Result<Self, ConfigError> {
        Ok(DaqSource {
            c: cfg.check(ctx)?,
            stage_id: ctx.stage_id.clone(),
            seed: ctx.seed,
            trials: OnceLock::new(),
        })
    }

    fn error(&self, message: impl Into<String>) -> RunError {
        RunError {
            stage: self.stage_id.clone(),
            trial: None,
            message: message.into(),
        }
    }

    /// The scene's trials, for labels (none for a board or a recording).
    fn scene_metas(&self) -> Result<Vec<TrialMeta>, RunError> {
        match &self.c.input {
            Input::Scene(src) => src.trials().map_err(|e| self.error(e.message)),
            _ => Ok(Vec::new()),
        }
    }

    /// A one-frame block of signals.
    fn block(&self, frame: &[f64]) -> Payload {
        Signals {
            sample_rate_hz: self.c.fs,
            layout: self.c.layout.clone(),
            unit: self.c.unit.clone(),
            data: frame.iter().map(|&v| vec![v]).collect(),
        }
        .into()
    }

    /// Acquires the stream to its end, cut into trials: `on` gets every
    /// trial's start (with its metadata), frames and end, in order.
    pub fn run(&self, on: &mut dyn FnMut(SourceEvent) -> Result<(), RunError>) -> Result<(), RunError> {
        let player_metas = self.scene_metas()?;
        // Only contact segments are the scene's trials (fixed windows are not).
        let metas = match self.c.plan {
            SegmentPlan::Contact { .. } => player_metas.clone(),
            SegmentPlan::Fixed(_) => Vec::new(),
        };
        let n = self.c.layout.len();
        let opts = AcquireOptions {
            channels: Some(n),
            scale: self.c.scale,
            offset: self.c.offset,
            record: self.c.record.clone(),
            stall_timeout: self.c.stall,
            give_up_after: Some(self.c.give_up),
            max_duration: self.c.seconds.map(Duration::from_secs_f64),
            ..AcquireOptions::default()
        };
        // A recording is checked whole before any of it streams: one that
        // ends inside a frame is refused (unless `allow_cut_end`), not
        // found out after its trials were scored.
        let scanned = match &self.c.input {
            Input::Recording(path) => Some(self.check_recording(path)?),
            _ => None,
        };
        let mut seg = Segmenter::new(self.c.plan);
        // Trials begun so far (a cell: read after the stream, while the
        // closure that counts them still lives).
        let trial = std::cell::Cell::new(0usize);
        let trial_id = |k: usize| {
            metas
                .get(k)
                .map_or_else(|| format!("{}-{k:04}", self.stage_id), |m| m.trial_id.clone())
        };
        let mut last: Option<Vec<f64>> = None;
        let mut fail: Option<RunError> = None;
        let mut frames = 0u64;
        let mut check = super::protocol::FrameCheck::default();
        let mut clock = RateCheck::new(self.c.fs);
        let mut crc_errors = 0u64;
        // `None`: a tick (see `SourceEvent::Tick`); one closure holds `on`.
        let mut on_event = |ev: Option<SegEvent<'_>>| -> Result<(), RunError> {
            let Some(ev) = ev else {
                return on(SourceEvent::Tick);
            };
            match ev {
                SegEvent::Start => {
                    let k = trial.get();
                    let meta = metas.get(k).cloned().unwrap_or_else(|| TrialMeta {
                        trial_id: trial_id(k),
                        group: k,
                        ..TrialMeta::default()
                    });
                    trial.set(k + 1);
                    on(SourceEvent::Start(meta))
                }
                SegEvent::Frame(f) => on(SourceEvent::Block(self.block(f))),
                SegEvent::End => on(SourceEvent::End),
            }
        };
        let mut handle = |ev: DaqEvent<'_>| -> Result<(), RunError> {
            match ev {
                DaqEvent::Frame(f) => {
                    if let Some(ch) = f.samples.iter().position(|v| !v.is_finite()) {
                        return Err(self.error(format!(
                            "frame {} (sequence {}), channel {ch}: sample {} is not finite",
                            frames, f.seq, f.samples[ch]
                        )));
                    }
                    check.push(f).map_err(|m| self.error(m))?;
                    clock
                        .push(frames, f.seq, f.timestamp_us)
                        .map_err(|m| self.error(m))?;
                    frames += 1;
                    seg.push(&f.samples, &mut |e| on_event(Some(e)))?;
                    // A frame outside a trial streams nothing: a tick, so
                    // that a live run can stop on a board with nothing in
                    // contact (see `SourceEvent::Tick`).
                    if !seg.in_trial() {
                        on_event(None)?;
                    }
                    match last.as_mut() {
                        Some(l) => l.copy_from_slice(&f.samples),
                        None => last = Some(f.samples.clone()),
                    }
                }
                DaqEvent::Lost { expected, got, count } => {
                    if count > self.c.max_gap {
                        return Err(self.error(format!(
                            "{count} frames lost in one gap (sequence {expected} due, {got} received), \
                             more than `max_gap_ms`"
                        )));
                    }
                    eprintln!(
                        "daq `{}`: {count} frames lost (sequence {expected} due, {got} received); held the previous frame",
                        self.stage_id
                    );
                    if let Some(l) = last.clone() {
                        for _ in 0..count {
                            seg.push(&l, &mut |e| on_event(Some(e)))?;
                        }
                    }
                }
                DaqEvent::CrcError => {
                    // The first few, then at 2^k: a noisy link's log stays
                    // short (every error printed made 22,646 lines of one
                    // bad recording) and still says how bad it is.
                    crc_errors += 1;
                    if crc_errors <= 5 || crc_errors.is_power_of_two() {
                        eprintln!(
                            "daq `{}`: a frame failed its CRC and was dropped ({crc_errors} so far)",
                            self.stage_id
                        )
                    }
                }
                DaqEvent::OutOfOrder => {
                    eprintln!("daq `{}`: a frame from the past (device reset?)", self.stage_id)
                }
                DaqEvent::Stall { silent } => eprintln!(
                    "daq `{}`: no frame for {:.1} s",
                    self.stage_id,
                    silent.as_secs_f64()
                ),
                DaqEvent::Waiting { .. } => on_event(None)?,
            }
            Ok(())
        };
        let mut callback = |ev: DaqEvent<'_>| match handle(ev) {
            Ok(()) => ControlFlow::Continue(()),
            Err(e) => {
                fail = Some(e);
                ControlFlow::Break(())
            }
        };
        let result = match &self.c.input {
            Input::Recording(path) => {
                let file = std::fs::File::open(path)
                    .map_err(|e| self.error(format!("cannot read {}: {e}", path.display())))?;
                acquire(file, &opts, &mut callback).map(|_| ())
            }
            Input::Port(port) => {
                let dev = open_serial(port, self.c.baud).map_err(|e| self.error(e.message))?;
                let played = |frames: u64| {
                    eprintln!(
                        "{port}: end of playback after {}",
                        super::protocol::count(frames, "frame", "frames")
                    )
                };
                match acquire(dev, &opts, &mut callback) {
                    // A pseudo-terminal's emulator hangs up after its last frame: the end.
                    Err(e)
                        if e.kind == DaqErrorKind::Disconnected
                            && is_pseudo_terminal(port)
                            && e.stats.frames > 0 =>
                    {
                        played(e.stats.frames);
                        Ok(())
                    }
                    Ok(r) if r.stopped == StopReason::EndOfStream && is_pseudo_terminal(port) => {
                        played(r.stats.frames);
                        Ok(())
                    }
                    Ok(r) if r.stopped == StopReason::EndOfStream && !is_pseudo_terminal(port) => {
                        Err(super::DaqError {
                            kind: DaqErrorKind::Disconnected,
                            message: format!(
                                "serial port {port} closed after {} frames ({})",
                                r.stats.frames, r.stats
                            ),
                            stats: r.stats,
                            recorded_bytes: r.recorded_bytes,
                        })
                    }
                    r => r.map(|_| ()),
                }
            }
            Input::Scene(src) => {
                let (tx, rx) = mpsc::sync_channel::<Vec<u8>>(64);
                let player = self.spawn_emulator(src.clone(), player_metas, tx);
                let r = acquire(
                    ChanReader {
                        rx,
                        buf: Vec::new(),
                        pos: 0,
                    },
                    &opts,
                    &mut callback,
                );
                // The player ends once the reader is gone; its error explains a short stream.
                if let (Ok(Err(e)), Ok(rep)) = (player.join(), &r) {
                    if fail.is_none() && rep.stopped == StopReason::EndOfStream {
                        return Err(self.error(format!("emulator: {e}")));
                    }
                }
                r.map(|_| ())
            }
        };
        // Why no trial began, when none did: at the stream's end, or when
        // the user stopped a session that never saw contact (a board
        // streams until stopped), but not over a failure.
        let diagnose = |trial: usize, seg: &Segmenter| {
            if let (0, Some(levels), SegmentPlan::Contact { contact, enter, .. }) =
                (trial, seg.levels(), self.c.plan)
            {
                eprintln!("{}", self.no_contact(frames, levels, contact, enter));
            }
        };
        if let Some(e) = fail {
            if e.message == palpate_core::stream::STOPPED {
                diagnose(trial.get(), &seg);
            }
            return Err(e);
        }
        result.map_err(|e| self.error(e.message))?;
        // A recording that ends in contact cut its last trial short (a
        // board's stream, stopped by `seconds` or its emulator, is not
        // warned of: it was stopped, not cut).
        if let (Input::Recording(path), true) = (&self.c.input, seg.in_trial()) {
            eprintln!(
                "daq `{}`: warning: the recording {} ends in contact, inside trial `{}`: that trial \
                 is cut short (it is still scored, on the frames recorded)",
                self.stage_id,
                path.display(),
                trial_id(trial.get().saturating_sub(1))
            );
        }
        seg.finish(&mut |e| on_event(Some(e)))?;
        diagnose(trial.get(), &seg);
        // The stream ended on its own (or after `seconds`) without a trial:
        // a failure, live as offline; only a stop by the user is not (see
        // the module docs).
        if trial.get() == 0 {
            return Err(self.error(self.no_trial(frames, scanned.as_ref())));
        }
        Ok(())
    }

    /// Decodes the recording at `path` once (in constant memory) for what
    /// streaming it cannot tell in time: its counts, and whether it ends
    /// inside a frame, which is an error naming the file and byte unless
    /// `allow_cut_end` (then the frame is dropped, said on stderr). A
    /// recording without a valid frame is left to [`Self::no_trial`].
    fn check_recording(&self, path: &std::path::Path) -> Result<(super::DaqStats, usize), RunError> {
        let shown = path.display();
        let mut file =
            std::fs::File::open(path).map_err(|e| self.error(format!("cannot read {shown}: {e}")))?;
        let mut dec = super::Decoder::new(Some(self.c.layout.len()), self.c.scale, self.c.offset);
        let mut buf = vec![0u8; 1 << 16];
        loop {
            match file.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => dec.feed(&buf[..n], |_| {}),
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(self.error(format!("cannot read {shown}: {e}"))),
            }
        }
        let (stats, cut) = (dec.stats().clone(), dec.pending());
        // Frames of another channel count are skipped by the decoder (on a
        // live link, noise that happens to parse); a recording holding
        // whole valid ones is another board's or a mixed file, refused as
        // `signal_file` refuses it rather than half scored.
        if stats.wrong_channels > 0 {
            return Err(self.error(format!(
                "{shown}: channel mismatch: the layout has {} taxels but {} valid frames carry another \
                 count ({stats})",
                self.c.layout.len(),
                stats.wrong_channels
            )));
        }
        if stats.frames > 0 && cut > 0 {
            let at = stats.bytes - cut as u64;
            if !self.c.allow_cut_end {
                return Err(self.error(super::cut_end_error(&shown, cut, at)));
            }
            eprintln!(
                "daq `{}`: {shown} ends inside a frame ({cut} bytes at byte {at}): dropped it (`allow_cut_end`)",
                self.stage_id
            );
        }
        Ok((stats, cut))
    }

    /// Why a stream that ended on its own held no trial: no valid frame in
    /// it (a recording's counts, and the bytes of an incomplete frame at its
    /// end, say what was there instead), or no contact (the levels were said
    /// on stderr).
    fn no_trial(&self, frames: u64, scanned: Option<&(super::DaqStats, usize)>) -> String {
        let what = match &self.c.input {
            Input::Recording(path) => format!("the recording {}", path.display()),
            _ => "the stream".to_string(),
        };
        match (frames, scanned) {
            (0, Some((stats, cut))) => format!(
                "{what} held no trial: no valid DAQ frame of the layout's {} channels in it ({stats}{})",
                self.c.layout.len(),
                if *cut > 0 {
                    format!("; {cut} bytes of an incomplete frame at its end")
                } else {
                    String::new()
                }
            ),
            (0, None) => format!("{what} held no trial: no valid DAQ frame came"),
            _ => format!("{what} held no trial (no contact: is `contact_v` right for the board?)"),
        }
    }

    /// Why a stream of `frames` frames began no trial: the `levels` of
    /// each frame's lowest taxel against `contact_v`, and what to set. The
    /// usual causes: thresholds left at the default 3.0 V for a board with
    /// another range, or values in other units (a recording in mV reads
    /// ~1700 where the default thresholds expect volts).
    fn no_contact(&self, frames: u64, levels: Levels, contact: f64, enter: usize) -> String {
        let Levels {
            low_range: lows,
            longest_under,
        } = levels;
        let unit = &self.c.unit;
        let num = palpate_core::fmt_num;
        // Four significant digits: the samples are f32 from the board.
        let sig = |v: f64| {
            if v == 0.0 || !v.is_finite() {
                return num(v);
            }
            let p = 10f64.powi(3 - v.abs().log10().floor() as i32);
            num((v * p).round() / p)
        };
        let rises = matches!(self.c.plan, SegmentPlan::Contact { rises: true, .. });
        let (which, past, reads) = if rises {
            ("highest", "over", "a pressed taxel reads high")
        } else {
            (
                "lowest",
                "under",
                "a pressed taxel reads low; `contact_polarity = \"rises\"` for one that reads high",
            )
        };
        let never = if rises { lows.1 < contact } else { lows.0 > contact };
        let relation = if never {
            format!("never at or {past} `contact_v` = {}", num(contact))
        } else {
            format!(
                "at or {past} `contact_v` = {} for at most {} in a row",
                num(contact),
                super::protocol::count(longest_under as u64, "frame", "frames")
            )
        };
        format!(
            "daq `{}`: no contact in {}: the {which} taxel of a frame read {} to {} {unit}, {relation}; \
             a trial begins after {} at or {past} it (`enter_ms`). Set `contact_v` and `release_v` \
             for this board ({reads}), or `scale` if its values come in other \
             units (e.g. 0.001 for mV)",
            self.stage_id,
            super::protocol::count(frames, "frame", "frames"),
            sig(lows.0),
            sig(lows.1),
            super::protocol::count(enter as u64, "frame", "frames"),
        )
    }

    /// Plays the scene's trials as frames into `tx`, `gap_ms` at `open_v` after each.
    fn spawn_emulator(
        &self,
        src: Arc<dyn Source>,
        metas: Vec<TrialMeta>,
        tx: mpsc::SyncSender<Vec<u8>>,
    ) -> std::thread::JoinHandle<Result<(), String>> {
        // Keyed as the scene stage `scene_stage_id` would key its trials.
        let (stage, seed, c) = (self.c.scene_stage.clone(), self.seed, self.c.clone());
        std::thread::spawn(move || {
            let mut out = ChanWriter(tx);
            // Frames played so far: the next trial's sequence and time go on from them.
            let mut played = 0u64;
            for meta in &metas {
                let ctx = TrialContext {
                    stage_id: &stage,
                    meta,
                    seed: derive_seed(seed, &[&stage, &meta.trial_id]),
                };
                let mut s = match src.produce(&ctx).map_err(|e| e.message)? {
                    Payload::Signals(s) => Arc::unwrap_or_clone(s),
                    _ => return Err("the scene gave no signals".into()),
                };
                if s.sample_rate_hz != c.fs {
                    return Err(format!(
                        "the scene samples at {} Hz, key `sample_rate_hz` = {} Hz",
                        s.sample_rate_hz, c.fs
                    ));
                }
                if s.layout.len() != c.layout.len() {
                    return Err(format!(
                        "the scene's array has {} taxels, key `layout` {}",
                        s.layout.len(),
                        c.layout.len()
                    ));
                }
                for col in s.data.iter_mut() {
                    col.extend(std::iter::repeat_n(c.open_v, c.gap_frames));
                }
                let opts = EmulateOptions {
                    speed: if c.speed > 0.0 { c.speed } else { f64::INFINITY },
                    scale: c.scale,
                    offset: c.offset,
                    first_seq: played as u32,
                    first_time_index: played,
                    ..EmulateOptions::default()
                };
                let r = super::emulate(&s, &mut out, &opts)?;
                played += r.frames;
            }
            Ok(())
        })
    }
}

/// True for a pseudo-terminal's device side (`/dev/pts/N`, BSD `/dev/ttyp*`):
/// an emulator, not a board, is on the other end, and its hang-up ends the stream.
pub fn is_pseudo_terminal(port: &str) -> bool {
    port.starts_with("/dev/pts/") || port.starts_with("/dev/ttyp")
}

/// The emulator's end of an in-process byte pipe.
struct ChanWriter(mpsc::SyncSender<Vec<u8>>);

impl Write for ChanWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0
            .send(buf.to_vec())
            .map_err(|_| std::io::Error::new(std::io::ErrorKind::BrokenPipe, "the reader stopped"))?;
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// The acquisition's end of the pipe: end of stream once the emulator is done.
struct ChanReader {
    rx: mpsc::Receiver<Vec<u8>>,
    buf: Vec<u8>,
    pos: usize,
}

impl Read for ChanReader {
    fn read(&mut self, out: &mut [u8]) -> std::io::Result<usize> {
        if self.pos == self.buf.len() {
            match self.rx.recv() {
                Ok(b) => {
                    self.buf = b;
                    self.pos = 0;
                }
                Err(_) => return Ok(0),
            }
        }
        let n = out.len().min(self.buf.len() - self.pos);
        out[..n].copy_from_slice(&self.buf[self.pos..self.pos + n]);
        self.pos += n;
        Ok(n)
    }
}

impl Source for DaqSource {
    fn trials(&self) -> Result<Vec<TrialMeta>, StageError> {
        let all = self.trials.get_or_init(|| {
            let mut out: Vec<(TrialMeta, Vec<Vec<f64>>)> = Vec::new();
            let n = self.c.layout.len();
            self.run(&mut |ev| {
                match ev {
                    SourceEvent::Start(m) => out.push((m, vec![Vec::new(); n])),
                    SourceEvent::Block(b) => {
                        if let (Some((_, data)), Ok(s)) = (out.last_mut(), b.signals()) {
                            for (d, x) in data.iter_mut().zip(&s.data) {
                                d.extend_from_slice(x);
                            }
                        }
                    }
                    SourceEvent::End | SourceEvent::Tick => {}
                }
                Ok(())
            })
            .map_err(|e| e.message)?;
            Ok(out
                .into_iter()
                .map(|(m, data)| {
                    let s = Signals {
                        sample_rate_hz: self.c.fs,
                        layout: self.c.layout.clone(),
                        unit: self.c.unit.clone(),
                        data,
                    };
                    (m, Arc::new(s))
                })
                .collect())
        });
        // `run` fails a stream that held no trial, with the message a live
        // run gives; the caller names the stage.
        match all {
            Ok(t) => Ok(t.iter().map(|(m, _)| m.clone()).collect()),
            Err(e) => Err(StageError::new(e.clone())),
        }
    }

    fn live(&self) -> Option<&dyn LiveSource> {
        Some(self)
    }

    fn produce(&self, ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let Some(Ok(all)) = self.trials.get() else {
            return Err(StageError::new(
                "daq: trials() was not called first (internal error)",
            ));
        };
        all.iter()
            .find(|(m, _)| m.trial_id == ctx.meta.trial_id)
            .map(|(_, s)| Payload::Signals(s.clone()))
            .ok_or_else(|| StageError::new(format!("daq: no trial `{}`", ctx.meta.trial_id)))
    }
}

impl LiveSource for DaqSource {
    fn stream(&self, on: &mut dyn FnMut(SourceEvent) -> Result<(), RunError>) -> Result<(), RunError> {
        self.run(on)
    }
}

/// Simulates one trial of a scene file at `angle_deg`: exactly the trial
/// `r00` at that angle of a graph with `[run] seed = <seed>` and a stage
/// `[stages.scene] type = "scene", file = <scene_file>` (the same seeds), for
/// `palpate daq emulate` to play through a pseudo-terminal.
pub fn simulate_trial(
    scene_file: &std::path::Path,
    angle_deg: f64,
    seed: u64,
) -> Result<Signals, StageError> {
    use crate::scene::{config::Angles, trial_id, Simulator};
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

#[cfg(test)]
mod tests {
    use super::*;

    fn cut(plan: SegmentPlan, lows: &[f64]) -> Vec<String> {
        // Taxel 0 is dead (open circuit, high); taxel 1 carries the contact.
        cut_beside(plan, 3.3, lows).0
    }

    /// The events of `plan` over frames `[open, v]`, and the levels it saw.
    fn cut_beside(plan: SegmentPlan, open: f64, values: &[f64]) -> (Vec<String>, Option<Levels>) {
        let mut seg = Segmenter::new(plan);
        let mut out = Vec::new();
        let mut on = |e: SegEvent<'_>| -> Result<(), ()> {
            out.push(match e {
                SegEvent::Start => "S".to_string(),
                SegEvent::Frame(f) => format!("{}", f[1]),
                SegEvent::End => "E".to_string(),
            });
            Ok(())
        };
        for &v in values {
            seg.push(&[open, v], &mut on).unwrap();
            assert!(seg.held() <= 3);
        }
        seg.finish(&mut on).unwrap();
        let levels = seg.levels();
        (out, levels)
    }

    #[test]
    fn an_emulated_board_has_the_scenes_array_and_rate_unless_the_keys_say_otherwise() {
        let d = tempfile::tempdir().unwrap();
        std::fs::write(
            d.path().join("s.toml"),
            "angles = [45]\ntrials_per_angle = 1\narray = { rows = 3, cols = 2, pitch_mm = 3.0, taxel_mm = 2.0 }\n\
             motion = { sample_rate_hz = 500.0 }\n",
        )
        .unwrap();
        let ctx = BuildContext {
            stage_id: "daq".into(),
            seed: 1,
            out_dir: d.path().to_path_buf(),
            base_dir: d.path().to_path_buf(),
        };
        let scene = DaqConfig {
            scene: Some("s.toml".into()),
            ..DaqConfig::default()
        };
        let c = scene.check(&ctx).unwrap();
        assert_eq!((c.layout.len(), c.fs), (6, 500.0));
        // Keys that disagree with the scene are errors at check time, each
        // naming its key, not when the first trial plays.
        let keyed = DaqConfig {
            layout: Some(LayoutConfig::default()),
            sample_rate_hz: Some(1000.0),
            ..scene.clone()
        };
        let Err(e) = keyed.check(&ctx) else {
            panic!("keys that disagree with the scene passed the check");
        };
        let keys: Vec<_> = e.problems().into_iter().filter_map(|(k, _)| k).collect();
        assert_eq!(keys, ["sample_rate_hz", "layout"], "{e}");
        assert!(
            e.to_string().contains("16 taxels") && e.to_string().contains("500 Hz"),
            "{e}"
        );
        // Keys that agree win: another geometry of the scene's six taxels.
        let keyed = DaqConfig {
            layout: Some(LayoutConfig::Grid {
                rows: 2,
                cols: 3,
                pitch_mm: 2.5,
                taxel_mm: 2.0,
            }),
            sample_rate_hz: Some(500.0),
            ..scene
        };
        let c = keyed.check(&ctx).unwrap();
        assert_eq!((c.layout.len(), c.fs), (6, 500.0));
        assert!(matches!(c.layout, TaxelLayout::Grid { rows: 2, cols: 3, .. }));
        // A real board: the paper's array at 1 kHz.
        let port = DaqConfig {
            port: Some("/dev/null".into()),
            ..DaqConfig::default()
        };
        let c = port.check(&ctx).unwrap();
        assert_eq!((c.layout.len(), c.fs), (16, 1000.0));
    }

    #[test]
    fn contact_needs_its_run_and_release_its_own_with_hysteresis() {
        let plan = SegmentPlan::Contact {
            contact: 3.0,
            release: 3.2,
            enter: 2,
            exit: 3,
            rises: false,
        };
        // A single low frame is noise; two begin a trial (both inside it).
        // 3.1 lies between the thresholds: still contact. Two high frames
        // then a low one: a dip, kept in the trial; three high frames end it.
        let got = cut(
            plan,
            &[3.3, 2.0, 3.3, 2.0, 1.5, 3.1, 3.25, 3.3, 1.7, 3.3, 3.3, 3.3, 3.3],
        );
        assert_eq!(got, ["S", "2", "1.5", "3.1", "3.25", "3.3", "1.7", "E"]);
        // A trial open at the stream's end ends there, with its held frames.
        let got = cut(plan, &[2.0, 2.0, 3.3]);
        assert_eq!(got, ["S", "2", "2", "3.3", "E"]);
    }

    /// A rising output: the falling test's stream mirrored (`6.5 - v`) and
    /// its thresholds with it cut the same trials at the same frames, the
    /// highest taxel deciding.
    #[test]
    fn a_rising_output_is_cut_as_the_mirror_of_a_falling_one() {
        let falling = [3.3, 2.0, 3.3, 2.0, 1.5, 3.1, 3.25, 3.3, 1.7, 3.3, 3.3, 3.3, 3.3];
        let plan = |rises: bool, contact: f64, release: f64| SegmentPlan::Contact {
            contact,
            release,
            enter: 2,
            exit: 3,
            rises,
        };
        let mirror = |v: f64| 6.5 - v;
        let rising: Vec<f64> = falling.iter().map(|&v| mirror(v)).collect();
        // The other taxel sits at the open level (low for a rising output):
        // the maximum, not the minimum, must decide.
        let (got, levels) = cut_beside(plan(true, mirror(3.0), mirror(3.2)), mirror(3.3), &rising);
        // The falling cut, each frame's value mirrored as the input was.
        let want: Vec<String> = cut(plan(false, 3.0, 3.2), &falling)
            .into_iter()
            .map(|e| e.parse::<f64>().map_or(e, |v| format!("{}", mirror(v))))
            .collect();
        assert!(want.len() > 4 && want.contains(&"E".to_string()), "{want:?}");
        assert_eq!(got, want);
        assert_eq!(levels.map(|l| l.low_range), Some((mirror(3.3), mirror(1.5))));
    }

    #[test]
    fn a_contact_segmenter_reports_the_levels_it_saw() {
        let plan = SegmentPlan::Contact {
            contact: 3.0,
            release: 3.2,
            enter: 3,
            exit: 3,
            rises: false,
        };
        let mut seg = Segmenter::new(plan);
        assert_eq!(seg.levels(), None);
        let mut on = |_: SegEvent<'_>| -> Result<(), ()> { Ok(()) };
        // Under the threshold twice in a row at most: no trial (enter = 3).
        for v in [3.3, 2.9, 3.3, 2.5, 2.8, 3.1, 3.25] {
            seg.push(&[3.3, v], &mut on).unwrap();
        }
        assert!(!seg.in_trial());
        assert_eq!(
            seg.levels(),
            Some(Levels {
                low_range: (2.5, 3.3),
                longest_under: 2
            })
        );
    }

    #[test]
    fn fixed_windows_cut_every_w_frames() {
        let got = cut(SegmentPlan::Fixed(2), &[1.0, 2.0, 3.0, 4.0, 5.0]);
        assert_eq!(got, ["S", "1", "2", "E", "S", "3", "4", "E", "S", "5", "E"]);
    }

    /// The live path checks frames as they arrive: a recording whose rate
    /// changes, or whose frames change sample format, ends the stream with
    /// an error naming the frame; the well-formed one streams its trials.
    #[test]
    fn a_stream_off_its_grid_or_of_mixed_formats_is_refused_as_it_arrives() {
        use super::super::{encode_frame, SampleFormat};
        let d = tempfile::tempdir().unwrap();
        let ctx = BuildContext {
            stage_id: "daq".into(),
            seed: 0,
            out_dir: d.path().to_path_buf(),
            base_dir: d.path().to_path_buf(),
        };
        let trials = |name: &str, ts: &dyn Fn(u64) -> u64, format: &dyn Fn(u64) -> SampleFormat| {
            let mut b = Vec::new();
            for k in 0..1400u64 {
                encode_frame(&mut b, format(k), k as u32, ts(k), &[1.0]);
            }
            std::fs::write(d.path().join(name), b).unwrap();
            let cfg = DaqConfig {
                recording: Some(name.into()),
                layout: Some(LayoutConfig::Positions {
                    positions_mm: vec![[0.0, 0.0]],
                    taxel_mm: 2.0,
                }),
                sample_rate_hz: Some(100.0),
                segment: SegmentMode::Fixed,
                window_ms: Some(1000.0),
                ..DaqConfig::default()
            };
            DaqSource::new(&cfg, &ctx)
                .unwrap()
                .trials()
                .map_err(|e| e.message)
        };
        let f32s = |_| SampleFormat::F32;
        assert_eq!(trials("ok.daq", &|k| k * 10_000, &f32s).unwrap().len(), 14);
        // Stamped at 200 Hz, read at the key's 100: refused by the third
        // frame (past the half sample of slack), naming both rates (every
        // trial was stretched 2x before).
        let e = trials("fast.daq", &|k| k * 5_000, &f32s).unwrap_err();
        assert!(
            e.contains("frame 2 (sequence 2)") && e.contains("(200 Hz)") && e.contains("is 100 Hz"),
            "{e}"
        );
        // A board clock 0.05 % fast, or one with a quarter sample of jitter,
        // is the key's rate.
        assert_eq!(trials("drift.daq", &|k| k * 9_995, &f32s).unwrap().len(), 14);
        let jitter = |k: u64| k * 10_000 + if k >= 10 && k.is_multiple_of(2) { 2_000 } else { 0 };
        assert_eq!(trials("jitter.daq", &jitter, &f32s).unwrap().len(), 14);
        // A board without a clock (every stamp the same) is not timed.
        assert_eq!(trials("clockless.daq", &|_| 7, &f32s).unwrap().len(), 14);
        // 100 Hz for 700 frames, then 200 Hz.
        let e = trials(
            "rate.daq",
            &|k| {
                if k < 700 {
                    k * 10_000
                } else {
                    6_990_000 + (k - 699) * 5_000
                }
            },
            &f32s,
        )
        .unwrap_err();
        // The caller names the stage (`stage `daq`: ...`), live and offline alike.
        assert!(
            e.contains("frame 700 (sequence 700)") && e.contains("off the uniform grid"),
            "{e}"
        );
        let e = trials("mixed.daq", &|k| k * 10_000, &|k| {
            if k % 2 == 0 {
                SampleFormat::U16
            } else {
                SampleFormat::F32
            }
        })
        .unwrap_err();
        assert!(e.contains("frame 1 (sequence 1)") && e.contains("u16"), "{e}");
    }

    /// A one-taxel source reading `name` in `d` (100 Hz, contact below 3.0).
    fn one_taxel(d: &std::path::Path, name: &str, allow_cut_end: bool) -> DaqSource {
        let ctx = BuildContext {
            stage_id: "daq".into(),
            seed: 0,
            out_dir: d.to_path_buf(),
            base_dir: d.to_path_buf(),
        };
        let cfg = DaqConfig {
            recording: Some(name.into()),
            allow_cut_end,
            layout: Some(LayoutConfig::Positions {
                positions_mm: vec![[0.0, 0.0]],
                taxel_mm: 2.0,
            }),
            sample_rate_hz: Some(100.0),
            enter_ms: 10.0,
            exit_ms: 10.0,
            ..DaqConfig::default()
        };
        DaqSource::new(&cfg, &ctx).unwrap()
    }

    /// Frames of one taxel at 100 Hz: `open` frames at 3.3 V, then
    /// `contact` at 1.0 V.
    fn one_taxel_frames(open: u64, contact: u64) -> Vec<u8> {
        let mut b = Vec::new();
        for k in 0..open + contact {
            let v = if k < open { 3.3 } else { 1.0 };
            super::super::encode_frame(
                &mut b,
                super::super::SampleFormat::F32,
                k as u32,
                k * 10_000,
                &[v],
            );
        }
        b
    }

    /// A recording that ends inside a frame is refused before any frame
    /// streams, naming the file and byte, unless `allow_cut_end`; a trial
    /// still in contact at its end is streamed (and scored) whole.
    #[test]
    fn a_recording_cut_inside_a_frame_is_refused_unless_allowed() {
        let d = tempfile::tempdir().unwrap();
        let whole = one_taxel_frames(20, 30);
        let frame = whole.len() / 50;
        std::fs::write(d.path().join("cut.daq"), &whole[..whole.len() - 3]).unwrap();
        let mut events = 0;
        let e = one_taxel(d.path(), "cut.daq", false)
            .run(&mut |_| {
                events += 1;
                Ok(())
            })
            .unwrap_err();
        assert_eq!(events, 0, "frames streamed before the refusal");
        let at = 49 * frame;
        assert!(
            e.stage == "daq"
                && e.message.contains("cut.daq: the recording ends inside a frame")
                && e.message.contains(&format!(
                    "({} bytes of an incomplete frame at byte {at})",
                    frame - 3
                ))
                && e.message.contains("`allow_cut_end = true`"),
            "{e}"
        );
        // Allowed: the 49 whole frames; the trial (in contact at the end)
        // closed there with its 29 frames.
        assert_eq!(one_taxel(d.path(), "cut.daq", true).trials().unwrap().len(), 1);
        let mut blocks = 0;
        one_taxel(d.path(), "cut.daq", true)
            .run(&mut |ev| {
                blocks += usize::from(matches!(ev, SourceEvent::Block(_)));
                Ok(())
            })
            .unwrap();
        assert_eq!(blocks, 29);
        // A whole recording needs no key.
        std::fs::write(d.path().join("whole.daq"), &whole).unwrap();
        assert_eq!(one_taxel(d.path(), "whole.daq", false).trials().unwrap().len(), 1);
    }

    /// A recording whose frames change their channel count half way is
    /// refused before it streams, with the counts (the decoder skipped the
    /// others' frames, and the half trial was scored).
    #[test]
    fn a_recording_of_mixed_channel_counts_is_refused() {
        let d = tempfile::tempdir().unwrap();
        let mut b = one_taxel_frames(20, 30);
        for k in 50..100u64 {
            super::super::encode_frame(
                &mut b,
                super::super::SampleFormat::F32,
                k as u32,
                k * 10_000,
                &[1.0, 1.0],
            );
        }
        std::fs::write(d.path().join("mixed.daq"), &b).unwrap();
        let e = one_taxel(d.path(), "mixed.daq", false).trials().unwrap_err();
        assert!(
            e.message.contains("mixed.daq: channel mismatch")
                && e.message.contains("the layout has 1 taxels but 50 valid frames"),
            "{e}"
        );
    }

    /// A stream that ends on its own without a trial fails, live (`run`)
    /// as offline (`trials`), with one message: why, naming the recording.
    #[test]
    fn a_recording_without_a_trial_fails_live_and_offline_alike() {
        let d = tempfile::tempdir().unwrap();
        std::fs::write(d.path().join("empty.daq"), b"").unwrap();
        std::fs::write(d.path().join("open.daq"), one_taxel_frames(40, 0)).unwrap();
        for (name, why) in [
            (
                "empty.daq",
                "held no trial: no valid DAQ frame of the layout's 1 channels in it (0 frames (0 bytes)",
            ),
            (
                "open.daq",
                "held no trial (no contact: is `contact_v` right for the board?)",
            ),
        ] {
            let live = one_taxel(d.path(), name, false).run(&mut |_| Ok(())).unwrap_err();
            let offline = one_taxel(d.path(), name, false).trials().unwrap_err();
            assert_eq!(live.message, offline.message);
            assert!(
                live.message.starts_with("the recording ") && live.message.contains(&format!("{name} {why}")),
                "{live}"
            );
        }
    }

    /// `scene_stage_id` keys an emulated scene's draws as a `scene` stage
    /// of that id: `"scene"` plays what [`simulate_trial`] (`palpate daq
    /// emulate`, `palpate simulate`) gives; the stage's own id, another draw.
    #[test]
    fn an_emulated_scene_draws_as_its_scene_stage_id() {
        let lab = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../graphs/scenes/lab.toml");
        let ctx = BuildContext {
            stage_id: "daq".into(),
            seed: 0,
            out_dir: std::env::temp_dir(),
            base_dir: std::env::temp_dir(),
        };
        let first = |scene_stage_id: Option<&str>| {
            let cfg = DaqConfig {
                scene: Some(lab.clone()),
                angles: Some(vec![30.0]),
                trials_per_angle: Some(1),
                scene_stage_id: scene_stage_id.map(str::to_string),
                ..DaqConfig::default()
            };
            let mut first: Option<Vec<f64>> = None;
            DaqSource::new(&cfg, &ctx)
                .unwrap()
                .run(&mut |ev| {
                    if let (None, SourceEvent::Block(b)) = (&first, ev) {
                        first = Some(b.signals().unwrap().data.iter().map(|c| c[0]).collect());
                    }
                    Ok(())
                })
                .unwrap();
            first.unwrap()
        };
        let want: Vec<f64> = simulate_trial(&lab, 30.0, 0)
            .unwrap()
            .data
            .iter()
            .map(|c| f64::from(c[0] as f32))
            .collect();
        assert_eq!(first(Some("scene")), want);
        assert_ne!(first(None), want);
    }

    #[test]
    fn bad_keys_are_named() {
        let ctx = BuildContext {
            stage_id: "daq".into(),
            seed: 0,
            out_dir: std::env::temp_dir(),
            base_dir: std::env::temp_dir(),
        };
        let e = DaqConfig::default().build(&ctx).err().unwrap().to_string();
        assert!(e.contains("`port`") && e.contains("`scene`"), "{e}");
        let cfg = DaqConfig {
            port: Some("/dev/null".into()),
            release_v: 2.0,
            segment: SegmentMode::Fixed,
            sample_rate_hz: Some(-1.0),
            ..DaqConfig::default()
        };
        let e = cfg.build(&ctx).err().unwrap().to_string();
        for key in ["release_v", "window_ms", "sample_rate_hz"] {
            assert!(e.contains(key), "{key}: {e}");
        }
        // Keys of one input, given for another.
        let cfg = DaqConfig {
            port: Some("/dev/null".into()),
            allow_cut_end: true,
            scene_stage_id: Some("scene".into()),
            ..DaqConfig::default()
        };
        let e = cfg.build(&ctx).err().unwrap().to_string();
        for key in ["allow_cut_end", "scene_stage_id"] {
            assert!(e.contains(key), "{key}: {e}");
        }
    }
}
