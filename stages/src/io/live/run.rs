//! [`run_live`]: a [`LivePipeline`] on a DAQ byte stream, via [`acquire`].

use super::pipeline::{LiveEstimate, LivePipeline};
use super::LiveConfig;
use crate::io::daq::{
    acquire, open_serial, AcquireOptions, DaqError, DaqErrorKind, DaqEvent, DaqStats, StopReason,
};
use palpate_core::{ConfigError, StageError};
use std::io::Read;
use std::ops::ControlFlow;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// What a live run tells its caller, in stream order.
#[derive(Clone, Debug, PartialEq)]
pub enum LiveUpdate {
    /// The running answer changed (class, "no edge", or became decided).
    Estimate(LiveEstimate),
    /// The final estimate, once the stream has ended (always the last update).
    Final(LiveEstimate),
    /// Frames missing before sequence `got`; `held`: filled by holding the
    /// previous frame (false: the gap exceeded `max_gap_ms` and ended the run).
    Lost {
        /// Sequence number due.
        expected: u32,
        /// Sequence number received.
        got: u32,
        /// Frames missing.
        count: u64,
        /// Whether they were filled.
        held: bool,
    },
    /// A frame failed its CRC and was dropped (its absence shows as `Lost`).
    CrcError {
        /// CRC errors so far.
        total: u64,
    },
    /// A frame from the past (device reset): the stream carries on.
    OutOfOrder {
        /// Out-of-order frames so far.
        total: u64,
    },
    /// No valid frame for this long.
    Stall {
        /// Silence, ms.
        silent_ms: f64,
    },
    /// A frame held non-finite samples, replaced by the taxels' previous values.
    NonFinite {
        /// Non-finite samples so far.
        total: u64,
    },
}

/// Why a live run ended.
#[derive(Clone, Debug, PartialEq)]
pub enum LiveEnd {
    /// The acquisition stopped normally (end of stream, `max_frames`, `max_duration`).
    Acquisition(StopReason),
    /// The estimate was decided and `stop_at_decision` is on.
    Decided,
    /// The caller's stop flag was set.
    Stopped,
    /// A gap of this many lost frames exceeded `max_gap_ms`.
    Gap(u64),
    /// The acquisition failed (device gone, stalled, recording); the estimate
    /// is that of every frame received before.
    Daq(DaqError),
}

/// The outcome of a live run.
#[derive(Clone, Debug, PartialEq)]
pub struct LiveReport {
    /// The estimate at the end of the stream.
    pub final_estimate: LiveEstimate,
    /// The first decided estimate (`wss.stop_margin`), if any.
    pub decision: Option<LiveEstimate>,
    /// Why the run ended.
    pub ended: LiveEnd,
    /// The DAQ's counts (frames, CRC errors, lost frames, gaps, garbage, stalls).
    pub stats: DaqStats,
    /// Samples consumed by the pipeline (frames received and held).
    pub samples: u64,
    /// Samples held in place of lost frames.
    pub held: u64,
    /// Non-finite samples replaced.
    pub non_finite: u64,
    /// Spike images pushed into WSS.
    pub images: usize,
    /// Spikes per taxel.
    pub spikes: Vec<u64>,
    /// Sample rate measured from the frames' timestamps, Hz (None with fewer than 2 frames).
    pub measured_rate_hz: Option<f64>,
    /// Bytes written to the raw recording.
    pub recorded_bytes: u64,
    /// Wall time.
    pub elapsed: Duration,
}

impl LiveReport {
    /// The answer of the run: the decision when the run stopped at it, else the final estimate.
    pub fn answer(&self) -> &LiveEstimate {
        match (&self.ended, &self.decision) {
            (LiveEnd::Decided, Some(d)) => d,
            _ => &self.final_estimate,
        }
    }

    /// A message when the run ended abnormally (device gone, stall, gap).
    pub fn error(&self) -> Option<String> {
        match &self.ended {
            LiveEnd::Daq(e) => Some(e.message.clone()),
            LiveEnd::Gap(n) => Some(format!(
                "{n} frames lost in one gap (more than `max_gap_ms`); the run stopped there"
            )),
            _ => None,
        }
    }
}

/// Why a live run could not produce an estimate at all.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LiveError {
    /// A bad config (the key is named).
    #[error("live config: {0}")]
    Config(#[from] ConfigError),
    /// The pipeline refused a frame.
    #[error("{0}")]
    Pipeline(#[from] StageError),
    /// The device could not be opened, or no frame ever came.
    #[error("{0}")]
    Daq(#[from] DaqError),
}

/// Runs the live path on a DAQ byte stream (a pipe, a file, a pseudo
/// terminal) until it ends: see [`run_live_until`].
pub fn run_live<R: Read + Send + 'static>(
    reader: R,
    cfg: &LiveConfig,
    acquire: &AcquireOptions,
    on_update: impl FnMut(&LiveUpdate),
) -> Result<LiveReport, LiveError> {
    run_live_until(reader, cfg, acquire, None, on_update)
}

/// Runs the live path on a DAQ byte stream: frames go through a
/// [`LivePipeline`] as they arrive; `on_update` hears every change of the
/// estimate and every anomaly, then the [`LiveUpdate::Final`] estimate. Stops
/// when the stream or a limit of `acquire` ends it, when `stop` is set
/// (checked at every event), at a decision with `stop_at_decision`, or at a
/// gap longer than `max_gap_ms`. An acquisition error after frames arrived
/// still gives a report (with [`LiveEnd::Daq`]) and the estimate so far.
/// `acquire.channels` must be unset or equal the layout's taxel count.
pub fn run_live_until<R: Read + Send + 'static>(
    reader: R,
    cfg: &LiveConfig,
    acquire_opts: &AcquireOptions,
    stop: Option<&AtomicBool>,
    mut on_update: impl FnMut(&LiveUpdate),
) -> Result<LiveReport, LiveError> {
    let start = Instant::now();
    let checked = cfg.check()?;
    let n = checked.layout.len();
    let mut opts = acquire_opts.clone();
    match opts.channels {
        Some(c) if c != n => {
            return Err(ConfigError::key(
                "layout",
                format!("the acquisition expects {c} channels, the layout has {n} taxels"),
            )
            .into())
        }
        _ => opts.channels = Some(n),
    }
    let (max_gap, stop_at_decision) = (checked.max_gap, checked.stop_at_decision);
    let tpl = Arc::new(checked.templates()?);
    let mut p = LivePipeline::from_checked(checked, tpl)?;
    let mut fail: Option<StageError> = None;
    let mut end: Option<LiveEnd> = None;
    let (mut crc, mut ooo) = (0u64, 0u64);
    // (timestamp µs, sample index) of the first frame since the device's
    // clock (re)started, and of the latest frame.
    let mut clock: Option<((u64, u64), (u64, u64))> = None;
    let mut rate: Option<f64> = None;
    let res = acquire(reader, &opts, |ev| {
        if stop.is_some_and(|s| s.load(Ordering::Relaxed)) {
            end = Some(LiveEnd::Stopped);
            return ControlFlow::Break(());
        }
        let changed = match ev {
            DaqEvent::Frame(f) => {
                let at = (f.timestamp_us, p.samples());
                clock = match clock {
                    Some((first, _)) if f.timestamp_us > first.0 => Some((first, at)),
                    _ => Some((at, at)),
                };
                let bad = p.non_finite();
                let r = p.push(&f.samples);
                if p.non_finite() > bad {
                    on_update(&LiveUpdate::NonFinite {
                        total: p.non_finite(),
                    });
                }
                r
            }
            DaqEvent::Lost { expected, got, count } => {
                let held = count <= max_gap;
                on_update(&LiveUpdate::Lost {
                    expected,
                    got,
                    count,
                    held,
                });
                if !held {
                    end = Some(LiveEnd::Gap(count));
                    return ControlFlow::Break(());
                }
                p.hold(count)
            }
            DaqEvent::CrcError => {
                crc += 1;
                on_update(&LiveUpdate::CrcError { total: crc });
                Ok(None)
            }
            DaqEvent::OutOfOrder => {
                ooo += 1;
                on_update(&LiveUpdate::OutOfOrder { total: ooo });
                // The device's clock restarted: measure the rate afresh.
                if let Some(r) = measured(clock) {
                    rate = Some(r);
                }
                clock = None;
                Ok(None)
            }
            DaqEvent::Stall { silent } => {
                on_update(&LiveUpdate::Stall {
                    silent_ms: silent.as_secs_f64() * 1000.0,
                });
                Ok(None)
            }
        };
        match changed {
            Ok(Some(e)) => on_update(&LiveUpdate::Estimate(e)),
            Ok(None) => {}
            Err(e) => {
                fail = Some(e);
                return ControlFlow::Break(());
            }
        }
        if stop_at_decision && p.decision().is_some() {
            end = Some(LiveEnd::Decided);
            return ControlFlow::Break(());
        }
        ControlFlow::Continue(())
    });
    if let Some(e) = fail {
        return Err(e.into());
    }
    let (stats, ended, recorded_bytes) = match res {
        Ok(r) => (
            r.stats,
            end.unwrap_or(LiveEnd::Acquisition(r.stopped)),
            r.recorded_bytes,
        ),
        Err(e) if e.stats.frames == 0 => return Err(e.into()),
        Err(e) => (e.stats.clone(), LiveEnd::Daq(e.clone()), e.recorded_bytes),
    };
    let final_estimate = p.finish()?;
    on_update(&LiveUpdate::Final(final_estimate.clone()));
    Ok(LiveReport {
        final_estimate,
        decision: p.decision().cloned(),
        ended,
        stats,
        samples: p.samples(),
        held: p.held(),
        non_finite: p.non_finite(),
        images: p.frames(),
        spikes: p.spike_counts().to_vec(),
        measured_rate_hz: measured(clock).or(rate),
        recorded_bytes,
        elapsed: start.elapsed(),
    })
}

/// True for a pseudo-terminal's device side (`/dev/pts/N`, BSD `/dev/ttyp*`):
/// an emulator, not a board, is on the other end.
pub fn is_pseudo_terminal(port: &str) -> bool {
    port.starts_with("/dev/pts/") || port.starts_with("/dev/ttyp")
}

/// Samples per second between two (timestamp, sample index) points.
fn measured(clock: Option<((u64, u64), (u64, u64))>) -> Option<f64> {
    let ((t0, k0), (t1, k1)) = clock?;
    (t1 > t0 && k1 > k0).then(|| (k1 - k0) as f64 / ((t1 - t0) as f64 * 1e-6))
}

/// [`run_live_until`] on a serial port (8N1, `baud`). A serial port does not
/// end: its closing is reported as [`LiveEnd::Daq`] (disconnected), with the
/// estimate of what came before. A pseudo-terminal (`/dev/pts/N`, what
/// `palpate daq emulate` plays into) does end: the emulator closes it after
/// its last frame, which the reader sees as a hang-up (a read error such as
/// "Broken pipe", or the end of the stream); after at least one frame that
/// is the normal end of playback, [`LiveEnd::Acquisition`]`(EndOfStream)`,
/// not an error.
pub fn run_live_serial(
    port: &str,
    baud: u32,
    cfg: &LiveConfig,
    acquire: &AcquireOptions,
    stop: Option<&AtomicBool>,
    on_update: impl FnMut(&LiveUpdate),
) -> Result<LiveReport, LiveError> {
    cfg.check()?;
    let dev = open_serial(port, baud)?;
    let mut r = run_live_until(dev, cfg, acquire, stop, on_update)?;
    let played = is_pseudo_terminal(port) && r.stats.frames > 0;
    match &r.ended {
        LiveEnd::Daq(e) if played && e.kind == DaqErrorKind::Disconnected => {
            r.ended = LiveEnd::Acquisition(StopReason::EndOfStream);
        }
        LiveEnd::Acquisition(StopReason::EndOfStream) if !played => {
            r.ended = LiveEnd::Daq(DaqError {
                kind: DaqErrorKind::Disconnected,
                message: format!(
                    "serial port {port} closed after {} received ({})",
                    crate::io::daq::protocol::count(r.stats.frames, "frame was", "frames were"),
                    r.stats
                ),
                stats: r.stats.clone(),
                recorded_bytes: r.recorded_bytes,
            });
        }
        _ => {}
    }
    Ok(r)
}
