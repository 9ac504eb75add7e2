//! The live path: acquisition from any byte stream (a serial port, a pseudo
//! terminal, a pipe), raw recording to disk, and an emulator that plays signals
//! as DAQ frames at real-time rate.
//!
//! ## Acquisition ([`acquire`])
//!
//! A reader thread moves bytes from the stream into a channel as they arrive,
//! so the loop can notice silence even when the stream's `read` blocks. The
//! channel holds at most [`READ_AHEAD_BYTES`] (1 MiB): a stream faster than
//! the graph behind it makes the reader wait there instead of growing memory,
//! and the board's own buffer (or the terminal's) takes the rest. Each
//! chunk is first written to the raw recording (every byte, before decoding, so
//! a decoder bug can never lose data), then decoded; frames and anomalies go to
//! the caller's callback in stream order. The recording is flushed and synced to
//! disk every `flush_interval`, so a crash loses at most that much; it is
//! flushed and synced again on every way out, errors included.
//!
//! * **Stall**: no frame for `stall_timeout` counts one stall (reported once per
//!   silence); no frame for `give_up_after` ends the run with an error.
//! * **Disconnection**: a read error (a USB device unplugged gives `EIO`) ends
//!   the run with an error that says how many frames were received and where
//!   the recording is. End of stream (a file or pipe) ends it normally.
//!
//! ## Emulation ([`emulate`])
//!
//! Sample `k` of every taxel goes into frame `k` (sequence `first_seq + k`,
//! timestamp `(first_time_index + k) * 1e6 / rate` µs, rounded). Frame `k` is written once the wall clock
//! reaches `k / (rate * speed)` s after the start; frames already due are
//! written together, so a slow consumer or a high speed factor never skips
//! frames, it only batches them.

use super::protocol::{encode_frame, DaqStats, DecodeEvent, Decoder, Frame, SampleFormat};
use palpate_core::Signals;
use std::io::{Read, Write};
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

/// Writes a raw byte stream to disk as it arrives, flushing and syncing every
/// `interval`, on [`RawRecorder::flush`] and when dropped.
pub struct RawRecorder {
    file: std::io::BufWriter<std::fs::File>,
    path: PathBuf,
    interval: Duration,
    last_flush: Instant,
    bytes: u64,
}

impl RawRecorder {
    /// Creates (truncates) the recording file, and its folder.
    pub fn create(path: &Path, interval: Duration) -> std::io::Result<Self> {
        if let Some(d) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(d)?;
        }
        Ok(RawRecorder {
            file: std::io::BufWriter::new(std::fs::File::create(path)?),
            path: path.to_path_buf(),
            interval,
            last_flush: Instant::now(),
            bytes: 0,
        })
    }

    /// Appends bytes; flushes and syncs when the interval has passed.
    pub fn write(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.file.write_all(bytes)?;
        self.bytes += bytes.len() as u64;
        if self.last_flush.elapsed() >= self.interval {
            self.flush()?;
        }
        Ok(())
    }

    /// Flushes to the OS and syncs the data to disk.
    pub fn flush(&mut self) -> std::io::Result<()> {
        self.file.flush()?;
        self.file.get_ref().sync_data()?;
        self.last_flush = Instant::now();
        Ok(())
    }

    /// Bytes recorded.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Where the recording is.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for RawRecorder {
    fn drop(&mut self) {
        // Best effort on every way out; errors were reported by `flush` calls.
        let _ = self.flush();
    }
}

/// Settings of an acquisition.
#[derive(Clone, Debug)]
pub struct AcquireOptions {
    /// Expected channel count; `None`: the first valid frame fixes it.
    pub channels: Option<usize>,
    /// Decoded value = raw * `scale` + `offset` (e.g. volts per ADC count).
    pub scale: f64,
    /// See `scale`.
    pub offset: f64,
    /// Where to record the raw stream; `None`: no recording.
    pub record: Option<PathBuf>,
    /// How often the recording is flushed and synced.
    pub flush_interval: Duration,
    /// Silence (no valid frame) longer than this counts as a stall.
    pub stall_timeout: Duration,
    /// Silence longer than this ends the run with an error; `None`: wait forever.
    pub give_up_after: Option<Duration>,
    /// Stop after this many frames.
    pub max_frames: Option<u64>,
    /// Stop after this much wall time.
    pub max_duration: Option<Duration>,
}

impl Default for AcquireOptions {
    fn default() -> Self {
        AcquireOptions {
            channels: None,
            scale: 1.0,
            offset: 0.0,
            record: None,
            flush_interval: Duration::from_millis(200),
            stall_timeout: Duration::from_millis(500),
            give_up_after: Some(Duration::from_secs(5)),
            max_frames: None,
            max_duration: None,
        }
    }
}

/// What an acquisition hands its callback, in stream order.
#[derive(Clone, Debug, PartialEq)]
pub enum DaqEvent<'a> {
    /// A valid frame.
    Frame(&'a Frame),
    /// Frames missing before `got`.
    Lost {
        /// Sequence number due.
        expected: u32,
        /// Sequence number received.
        got: u32,
        /// Frames missing.
        count: u64,
    },
    /// A frame failed its CRC and was dropped.
    CrcError,
    /// A frame from the past (device reset).
    OutOfOrder,
    /// No frame for `silent`.
    Stall {
        /// How long the stream has been silent.
        silent: Duration,
    },
    /// No bytes came for one wait (`min(stall_timeout, flush_interval)`,
    /// at least 1 ms), `silent` since the last frame: the caller may act
    /// (stop) while the board is silent, which it otherwise could not
    /// until a frame or the stall.
    Waiting {
        /// How long the stream has been silent.
        silent: Duration,
    },
}

/// Why an acquisition stopped without error.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StopReason {
    /// The callback asked to stop.
    Callback,
    /// `max_frames` reached.
    MaxFrames,
    /// `max_duration` reached.
    MaxDuration,
    /// The stream ended (end of file or pipe).
    EndOfStream,
}

/// The outcome of an acquisition.
#[derive(Clone, Debug, PartialEq)]
pub struct AcquireReport {
    /// Counts.
    pub stats: DaqStats,
    /// Why it stopped.
    pub stopped: StopReason,
    /// Bytes written to the recording.
    pub recorded_bytes: u64,
    /// Wall time.
    pub elapsed: Duration,
}

/// What ended an acquisition in error.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DaqErrorKind {
    /// The port could not be opened.
    Open,
    /// Reading failed (the device disappeared).
    Disconnected,
    /// No frame for `give_up_after`.
    Stalled,
    /// The recording could not be written.
    Record,
}

/// An acquisition error; what was recorded up to it is kept and flushed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{message}")]
pub struct DaqError {
    /// What happened.
    pub kind: DaqErrorKind,
    /// A message with the frame count and the recording's path.
    pub message: String,
    /// Counts up to the error.
    pub stats: DaqStats,
    /// Bytes safely recorded.
    pub recorded_bytes: u64,
}

/// Bytes one `read` of the stream takes at most.
const READ_CHUNK_BYTES: usize = 4096;
/// Chunks the reader may queue ahead of the decoder.
const READ_QUEUE_CHUNKS: usize = 256;
/// The most raw bytes read from the stream but not yet decoded: the live
/// path's only buffer whose fill depends on how far the graph lags the
/// stream (256 chunks of at most 4 KiB; 1 MiB is ~19 s of a 16-taxel board's
/// 54-byte `U16` frames at 1 kHz).
pub const READ_AHEAD_BYTES: usize = READ_QUEUE_CHUNKS * READ_CHUNK_BYTES;

enum Chunk {
    Data(Vec<u8>),
    End,
    Error(std::io::Error),
}

fn spawn_reader<R: Read + Send + 'static>(mut reader: R, stop: Arc<AtomicBool>) -> mpsc::Receiver<Chunk> {
    let (tx, rx) = mpsc::sync_channel::<Chunk>(READ_QUEUE_CHUNKS);
    std::thread::spawn(move || {
        let mut buf = vec![0u8; READ_CHUNK_BYTES];
        while !stop.load(Ordering::Relaxed) {
            let msg = match reader.read(&mut buf) {
                Ok(0) => Chunk::End,
                Ok(n) => Chunk::Data(buf[..n].to_vec()),
                // Serial ports time out on silence: not an error, try again.
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::TimedOut
                            | std::io::ErrorKind::WouldBlock
                            | std::io::ErrorKind::Interrupted
                    ) =>
                {
                    continue
                }
                Err(e) => Chunk::Error(e),
            };
            let last = !matches!(msg, Chunk::Data(_));
            if tx.send(msg).is_err() || last {
                break;
            }
        }
    });
    rx
}

/// Acquires frames from `reader` until the callback breaks, a limit is reached,
/// the stream ends, or an error (see the module docs). The callback gets every
/// frame and anomaly; return `ControlFlow::Break(())` to stop.
pub fn acquire<R, F>(reader: R, opts: &AcquireOptions, mut on_event: F) -> Result<AcquireReport, DaqError>
where
    R: Read + Send + 'static,
    F: FnMut(DaqEvent<'_>) -> ControlFlow<()>,
{
    let start = Instant::now();
    let mut recorder = match &opts.record {
        Some(p) => Some(RawRecorder::create(p, opts.flush_interval).map_err(|e| DaqError {
            kind: DaqErrorKind::Record,
            message: format!("cannot create the recording {}: {e}", p.display()),
            stats: DaqStats::default(),
            recorded_bytes: 0,
        })?),
        None => None,
    };
    let stop = Arc::new(AtomicBool::new(false));
    let rx = spawn_reader(reader, stop.clone());
    let mut dec = Decoder::new(opts.channels, opts.scale, opts.offset);
    let mut last_frame = Instant::now();
    let mut stall_reported = false;
    let tick = opts
        .stall_timeout
        .min(opts.flush_interval)
        .max(Duration::from_millis(1));

    let where_recorded = |r: &Option<RawRecorder>| match r {
        Some(r) => format!(
            "; the recording ({} bytes) is kept at {}",
            r.bytes(),
            r.path().display()
        ),
        None => String::new(),
    };
    let result = (|| -> Result<StopReason, (DaqErrorKind, String)> {
        loop {
            if opts.max_duration.is_some_and(|d| start.elapsed() >= d) {
                return Ok(StopReason::MaxDuration);
            }
            match rx.recv_timeout(tick) {
                Ok(Chunk::Data(bytes)) => {
                    if let Some(r) = recorder.as_mut() {
                        r.write(&bytes).map_err(|e| {
                            (
                                DaqErrorKind::Record,
                                format!("cannot write the recording {}: {e}", r.path().display()),
                            )
                        })?;
                    }
                    let mut flow = ControlFlow::Continue(());
                    let mut limit = false;
                    let max = opts.max_frames;
                    let mut frames_now = dec.stats().frames;
                    dec.feed(&bytes, |ev| {
                        if flow.is_break() || limit {
                            return;
                        }
                        flow = match ev {
                            DecodeEvent::Frame(f) => {
                                frames_now += 1;
                                last_frame = Instant::now();
                                stall_reported = false;
                                let fl = on_event(DaqEvent::Frame(&f));
                                limit = max.is_some_and(|m| frames_now >= m);
                                fl
                            }
                            DecodeEvent::Lost { expected, got, count } => {
                                on_event(DaqEvent::Lost { expected, got, count })
                            }
                            DecodeEvent::CrcError { .. } => on_event(DaqEvent::CrcError),
                            DecodeEvent::OutOfOrder { .. } => on_event(DaqEvent::OutOfOrder),
                        };
                    });
                    if flow.is_break() {
                        return Ok(StopReason::Callback);
                    }
                    if limit {
                        return Ok(StopReason::MaxFrames);
                    }
                }
                Ok(Chunk::End) => return Ok(StopReason::EndOfStream),
                Ok(Chunk::Error(e)) => {
                    return Err((
                        DaqErrorKind::Disconnected,
                        format!("the device stopped answering ({e})"),
                    ))
                }
                Err(mpsc::RecvTimeoutError::Disconnected) => {
                    return Err((DaqErrorKind::Disconnected, "the reader thread ended".into()))
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {
                    if let Some(r) = recorder.as_mut() {
                        if r.last_flush.elapsed() >= opts.flush_interval {
                            r.flush().map_err(|e| {
                                (DaqErrorKind::Record, format!("cannot write the recording: {e}"))
                            })?;
                        }
                    }
                    let silent = last_frame.elapsed();
                    if on_event(DaqEvent::Waiting { silent }).is_break() {
                        return Ok(StopReason::Callback);
                    }
                }
            }
            let silent = last_frame.elapsed();
            if silent >= opts.stall_timeout && !stall_reported {
                stall_reported = true;
                dec.stats_mut().stalls += 1;
                if on_event(DaqEvent::Stall { silent }).is_break() {
                    return Ok(StopReason::Callback);
                }
            }
            if opts.give_up_after.is_some_and(|g| silent >= g) {
                return Err((
                    DaqErrorKind::Stalled,
                    format!("no frame for {:.1} s (stalled)", silent.as_secs_f64()),
                ));
            }
        }
    })();
    stop.store(true, Ordering::Relaxed);
    drop(rx);
    let flushed = recorder.as_mut().map_or(Ok(()), RawRecorder::flush);
    let stats = dec.stats().clone();
    let recorded_bytes = recorder.as_ref().map_or(0, RawRecorder::bytes);
    match (result, flushed) {
        (Ok(stopped), Ok(())) => Ok(AcquireReport {
            stats,
            stopped,
            recorded_bytes,
            elapsed: start.elapsed(),
        }),
        (Ok(_), Err(e)) => Err(DaqError {
            kind: DaqErrorKind::Record,
            message: format!("cannot flush the recording: {e}"),
            stats,
            recorded_bytes,
        }),
        (Err((kind, msg)), _) => Err(DaqError {
            kind,
            message: format!(
                "{msg} after {} received ({stats}){}",
                super::protocol::count(stats.frames, "frame was", "frames were"),
                where_recorded(&recorder)
            ),
            stats,
            recorded_bytes,
        }),
    }
}

/// Opens a serial port (8N1, no flow control) with a short read timeout, so
/// that silence is seen as a stall rather than a hang.
pub fn open_serial(path: &str, baud: u32) -> Result<Box<dyn serialport::SerialPort>, DaqError> {
    serialport::new(path, baud)
        .timeout(Duration::from_millis(50))
        .open()
        .map_err(|e| DaqError {
            kind: DaqErrorKind::Open,
            message: format!("cannot open serial port {path}: {e}"),
            stats: DaqStats::default(),
            recorded_bytes: 0,
        })
}

/// Acquires from a serial port (see [`acquire`]). A serial port does not
/// "end": end of stream there means the device went away, and is an error.
pub fn acquire_serial<F>(
    path: &str,
    baud: u32,
    opts: &AcquireOptions,
    on_event: F,
) -> Result<AcquireReport, DaqError>
where
    F: FnMut(DaqEvent<'_>) -> ControlFlow<()>,
{
    let port = open_serial(path, baud)?;
    let report = acquire(port, opts, on_event)?;
    if report.stopped == StopReason::EndOfStream {
        return Err(DaqError {
            kind: DaqErrorKind::Disconnected,
            message: format!(
                "serial port {path} closed after {} received ({}){}",
                super::protocol::count(report.stats.frames, "frame was", "frames were"),
                report.stats,
                opts.record
                    .as_ref()
                    .map(|p| format!("; the recording is kept at {}", p.display()))
                    .unwrap_or_default()
            ),
            stats: report.stats,
            recorded_bytes: report.recorded_bytes,
        });
    }
    Ok(report)
}

/// Settings of the emulator.
#[derive(Clone, Debug)]
pub struct EmulateOptions {
    /// Playback speed: 1 = real time, 10 = ten times faster; infinite = as fast
    /// as the consumer reads.
    pub speed: f64,
    /// Sample format of the frames.
    pub format: SampleFormat,
    /// Raw value = (value - `offset`) / `scale` (inverse of the decoder's).
    pub scale: f64,
    /// See `scale`.
    pub offset: f64,
    /// Sequence number of the first frame (tests use it to cross the wrap).
    pub first_seq: u32,
    /// Sample periods before the first frame's timestamp: frame `k` is
    /// stamped `(first_time_index + k) * 1e6 / rate` µs, so signals played
    /// one after another (an emulated scene's trials) go on in time as their
    /// sequence numbers do, on one uniform grid. Default 0.
    pub first_time_index: u64,
    /// Play the signals this many times back to back (sequence and time go on).
    pub repeat: usize,
}

impl Default for EmulateOptions {
    fn default() -> Self {
        EmulateOptions {
            speed: 1.0,
            format: SampleFormat::F32,
            scale: 1.0,
            offset: 0.0,
            first_seq: 0,
            first_time_index: 0,
            repeat: 1,
        }
    }
}

/// What the emulator did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EmulateReport {
    /// Frames written.
    pub frames: u64,
    /// Bytes written.
    pub bytes: u64,
    /// Samples clamped to the u16 range.
    pub clamped: u64,
    /// Wall time.
    pub elapsed: Duration,
}

/// Plays `signals` as DAQ frames into `out` at real-time rate times
/// `opts.speed` (see the module docs).
pub fn emulate<W: Write>(
    signals: &Signals,
    out: &mut W,
    opts: &EmulateOptions,
) -> Result<EmulateReport, String> {
    let n = signals.layout.len();
    if signals.data.len() != n || n == 0 || n > super::protocol::MAX_CHANNELS {
        return Err(format!(
            "signals have {} channels for a layout of {n} taxels (1..=1024 allowed)",
            signals.data.len()
        ));
    }
    let rate = signals.sample_rate_hz;
    if !(rate.is_finite() && rate > 0.0) {
        return Err(format!(
            "sample rate must be positive, got {}",
            palpate_core::fmt_num(rate)
        ));
    }
    if opts.speed.is_nan() || opts.speed <= 0.0 {
        return Err(format!(
            "speed must be positive, got {}",
            palpate_core::fmt_num(opts.speed)
        ));
    }
    if !(opts.scale.is_finite() && opts.scale != 0.0 && opts.offset.is_finite()) {
        return Err("scale must be finite and non-zero, offset finite".into());
    }
    let samples = signals.n_samples();
    for (x, col) in signals.data.iter().enumerate() {
        if col.len() != samples {
            return Err(format!(
                "taxel {x} has {} samples, taxel 0 has {samples}",
                col.len()
            ));
        }
        if let Some(s) = col.iter().position(|v| !v.is_finite()) {
            return Err(format!("sample {s} of taxel {x} is not finite ({})", col[s]));
        }
    }
    let start = Instant::now();
    let mut report = EmulateReport::default();
    let mut buf = Vec::new();
    let mut raw = vec![0.0; n];
    let total = samples as u64 * opts.repeat as u64;
    let mut k: u64 = 0;
    let write = |buf: &mut Vec<u8>, out: &mut W, report: &mut EmulateReport| -> Result<(), String> {
        out.write_all(buf).map_err(|e| {
            format!(
                "write failed after {}: {e}",
                super::protocol::count(report.frames, "frame", "frames")
            )
        })?;
        out.flush().map_err(|e| {
            format!(
                "flush failed after {}: {e}",
                super::protocol::count(report.frames, "frame", "frames")
            )
        })?;
        report.bytes += buf.len() as u64;
        buf.clear();
        Ok(())
    };
    while k < total {
        // Frames due by now (at least one), written together.
        let due = if opts.speed.is_finite() {
            let now = start.elapsed().as_secs_f64() * rate * opts.speed;
            (now.floor() as u64 + 1).clamp(k + 1, total)
        } else {
            total.min(k + 256)
        };
        while k < due {
            let s = (k % samples as u64) as usize;
            for (r, col) in raw.iter_mut().zip(&signals.data) {
                *r = (col[s] - opts.offset) / opts.scale;
            }
            let ts = ((opts.first_time_index + k) as f64 * 1e6 / rate).round() as u64;
            report.clamped += encode_frame(
                &mut buf,
                opts.format,
                opts.first_seq.wrapping_add(k as u32),
                ts,
                &raw,
            ) as u64;
            report.frames += 1;
            k += 1;
        }
        write(&mut buf, out, &mut report)?;
        if k < total && opts.speed.is_finite() {
            let next = Duration::from_secs_f64(k as f64 / (rate * opts.speed));
            if let Some(wait) = next.checked_sub(start.elapsed()) {
                std::thread::sleep(wait);
            }
        }
    }
    report.elapsed = start.elapsed();
    Ok(report)
}

/// A pseudo-terminal pair in raw mode: the emulator writes into `master`; a
/// reader opens `slave_path` (or uses `slave`) as if it were the DAQ's serial port.
pub struct Pty {
    /// The controlling side.
    pub master: serialport::TTYPort,
    /// The device side, already open.
    pub slave: serialport::TTYPort,
    /// The device side's path, e.g. `/dev/pts/3`.
    pub slave_path: String,
}

/// Opens a raw pseudo-terminal pair.
pub fn open_pty() -> Result<Pty, String> {
    let (master, slave) =
        serialport::TTYPort::pair().map_err(|e| format!("cannot open a pseudo-terminal: {e}"))?;
    let slave_path = serialport::SerialPort::name(&slave).ok_or("the pseudo-terminal has no name")?;
    Ok(Pty {
        master,
        slave,
        slave_path,
    })
}

/// How long [`emulate_pty`] waits for a reader to take any byte before it
/// gives up (the reader stopped, or never came).
pub const PTY_DRAIN_TIMEOUT: Duration = Duration::from_secs(10);

/// The master side of a pseudo-terminal, written without ever blocking for
/// good: the fd is non-blocking, and a write that makes no progress for
/// `limit` fails. A blocking write into a full terminal whose reader has
/// stopped (the slave is held open by the emulator, so no hang-up is seen)
/// used to wait forever: `daq run --emulate-scene --seconds 0.01` never exited.
struct DrainWriter<'a> {
    port: &'a mut serialport::TTYPort,
    limit: Duration,
}

impl Write for DrainWriter<'_> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let start = Instant::now();
        loop {
            // `TTYPort::write` polls for room (100 ms) before writing.
            match self.port.write(buf) {
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock
                            | std::io::ErrorKind::TimedOut
                            | std::io::ErrorKind::Interrupted
                    ) =>
                {
                    if start.elapsed() >= self.limit {
                        return Err(std::io::Error::new(
                            std::io::ErrorKind::TimedOut,
                            format!(
                                "no reader took a byte for {:.0} s (the reader stopped?)",
                                self.limit.as_secs_f64()
                            ),
                        ));
                    }
                }
                r => return r,
            }
        }
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.port.flush()
    }
}

/// Plays `signals` into a new pseudo-terminal: `on_ready` gets the device path
/// to give to `palpate daq run --port`, then playback starts. The slave side is
/// held open (never read) so that data written before a reader attaches waits
/// in the terminal's queue rather than failing; when no reader takes a byte
/// for [`PTY_DRAIN_TIMEOUT`] (it stopped first), playback ends with an error
/// instead of blocking for good.
pub fn emulate_pty(
    signals: &Signals,
    opts: &EmulateOptions,
    on_ready: impl FnOnce(&str),
) -> Result<EmulateReport, String> {
    emulate_pty_drain(signals, opts, PTY_DRAIN_TIMEOUT, on_ready)
}

/// [`emulate_pty`] with a given drain timeout (`drain`: how long a write may
/// make no progress before playback fails).
pub fn emulate_pty_drain(
    signals: &Signals,
    opts: &EmulateOptions,
    drain: Duration,
    on_ready: impl FnOnce(&str),
) -> Result<EmulateReport, String> {
    let mut pty = open_pty()?;
    {
        use std::os::fd::AsRawFd;
        let fd = pty.master.as_raw_fd();
        nix::fcntl::fcntl(fd, nix::fcntl::FcntlArg::F_SETFL(nix::fcntl::OFlag::O_NONBLOCK))
            .map_err(|e| format!("cannot make the pseudo-terminal non-blocking: {e}"))?;
    }
    on_ready(&pty.slave_path);
    let mut out = DrainWriter {
        port: &mut pty.master,
        limit: drain,
    };
    let report = emulate(signals, &mut out, opts)?;
    // Let a reader drain the queue before the terminal closes.
    std::thread::sleep(Duration::from_millis(200));
    drop(pty.slave);
    Ok(report)
}

/// Decodes a raw recording file into signals of `layout`; sample rate from the
/// frames' timestamps unless given. Errors name the file and the counts.
pub fn signals_from_recording(
    path: &Path,
    layout: palpate_core::TaxelLayout,
    unit: &str,
    sample_rate_hz: Option<f64>,
    scale: f64,
    offset: f64,
    fill_gaps: bool,
) -> Result<(Signals, DaqStats), String> {
    let bytes =
        palpate_core::input::read_data(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let rec = super::protocol::decode_recording(&bytes, scale, offset, fill_gaps)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    if rec.data.len() != layout.len() {
        return Err(format!(
            "{}: frames carry {} channels, the layout has {} taxels",
            path.display(),
            rec.data.len(),
            layout.len()
        ));
    }
    let rate = sample_rate_hz
        .or(rec.sample_rate_hz)
        .ok_or_else(|| format!("{}: one frame only; give the sample rate", path.display()))?;
    Ok((
        Signals {
            sample_rate_hz: rate,
            layout,
            unit: unit.into(),
            data: rec.data,
        },
        rec.stats,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `first_time_index` stamps the first frame that many sample periods
    /// on, so two signals played one after the other are one uniform stream
    /// (what an emulated scene's trials need to pass the frame check).
    #[test]
    fn signals_played_one_after_another_go_on_in_time() {
        let s = Signals {
            sample_rate_hz: 400.0,
            layout: palpate_core::TaxelLayout::Positions {
                positions_mm: vec![[0.0, 0.0]],
                taxel_mm: 2.0,
            },
            unit: "V".into(),
            data: vec![vec![1.0, 2.0, 3.0]],
        };
        let mut out = Vec::new();
        let fast = |first: u64| EmulateOptions {
            speed: f64::INFINITY,
            first_seq: first as u32,
            first_time_index: first,
            ..EmulateOptions::default()
        };
        emulate(&s, &mut out, &fast(0)).unwrap();
        emulate(&s, &mut out, &fast(3)).unwrap();
        let d = super::super::decode_recording(&out, 1.0, 0.0, false).unwrap();
        assert_eq!((d.data[0].len(), d.sample_rate_hz), (6, Some(400.0)));
        // Restarting the clock instead is refused (the timestamps go back).
        let mut out = Vec::new();
        emulate(&s, &mut out, &fast(0)).unwrap();
        emulate(
            &s,
            &mut out,
            &EmulateOptions {
                first_time_index: 0,
                ..fast(3)
            },
        )
        .unwrap();
        let e = super::super::decode_recording(&out, 1.0, 0.0, false).unwrap_err();
        assert!(
            e.contains("frame 3 (sequence 3)") && e.contains("decrease"),
            "{e}"
        );
    }
}
