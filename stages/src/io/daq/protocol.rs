//! The DAQ frame format (specified for firmware authors in `docs/daq-protocol.md`),
//! its encoder, and a streaming decoder that resynchronises after garbage.
//!
//! ```text
//! offset  size  field
//! 0       2     sync word: bytes 0xAA 0x55
//! 2       1     version: 1
//! 3       1     sample format: 1 = u16 (ADC counts), 2 = f32
//! 4       2     channel count N (u16, 1..=1024)
//! 6       4     sequence number (u32, +1 per frame, wraps to 0)
//! 10      8     timestamp of the samples, µs since the device started (u64)
//! 18      N*w   samples, channel (= taxel) order; w = 2 (u16) or 4 (f32)
//! 18+N*w  4     CRC-32/ISO-HDLC (zlib's crc32) of bytes [0, 18+N*w)
//! ```
//!
//! All integers and floats are little-endian. A frame is `22 + N*w` bytes.
//!
//! ## Decoding
//!
//! The decoder scans for the sync word, checks the header (version, format,
//! channel count equal to the expected or first-seen count) and waits for the
//! whole frame; then it checks the CRC. A frame whose CRC fails is counted
//! (`crc_errors`) and dropped, and the scan resumes **one byte** after its sync
//! word, never past it: a corrupted length or a false sync inside a payload can
//! never swallow the real frame that follows. Bytes skipped while scanning are
//! counted as `garbage_bytes` (they include the bytes of dropped frames).
//!
//! Sequence numbers find lost frames: with `expected = last + 1 (mod 2^32)`, a
//! frame with `d = seq - expected (mod 2^32)` in `1..2^31` means `d` frames
//! were lost (this includes frames dropped for a bad CRC); `d >= 2^31` is a
//! frame from the past (a device reset or a replay), counted as `out_of_order`
//! and accepted, and the count restarts from it. Wrap-around from `2^32 - 1` to
//! 0 is an ordinary step.
//!
//! A frame whose header and CRC are valid but whose channel count differs from
//! the stream's (a board sending 8 channels to a 16-taxel config) is counted in
//! `wrong_channels` (with the count it carried) and skipped whole, so the
//! mismatch is named in every report instead of looking like garbage.
//!
//! ## One stream, one format, one clock ([`FrameCheck`])
//!
//! Every frame of a stream must carry the first frame's sample format
//! (`docs/daq-protocol.md`: "do not mix formats"), and its timestamps must
//! lie on a uniform grid: each within a quarter of the step (the rule the
//! CSV time column follows, [`GRID_TOLERANCE`]) of its point on the grid
//! learnt from the frames before it, whose step is their time span over
//! their sequence steps ([`TimeGrid`]). So a rate that changes, intervals
//! that alternate (13 and 7 ms, which a median reads as 77 Hz), or
//! timestamps that go back are errors naming the frame, its sequence
//! number and the expected and actual intervals, not a rate taken from
//! their median. The check holds a few numbers, whatever the stream's
//! length, so the live path makes it too. Across a sequence gap (lost
//! frames) or a device reset the grid restarts at the next frame, its step
//! kept: the sequence numbers, not the clock, count lost frames. A stream
//! whose timestamps all stay at their first value carries no clock (a
//! board that does not stamp): it passes, and gives no rate.
//!
//! ## Recordings ([`decode_recording`]) and their limits
//!
//! Every decoded sample must be finite (a NaN sent as f32, or a scale that
//! overflows, is an error naming the frame and channel). `fill_gaps` holds
//! values over lost frames, but at most as many as were received
//! ([`decode_recording`] fails otherwise): a reset may restart the sequence
//! anywhere, and a jump of 2^31 would otherwise ask for 2^31 filled frames
//! (17 GB per channel) from a 600-byte file. Memory is so bounded by a small
//! multiple of the file size.

use crate::io::common::{GridBreak, TimeGrid, GRID_TOLERANCE};
use std::fmt;

/// The two sync bytes that start every frame.
pub const SYNC: [u8; 2] = [0xAA, 0x55];
/// Protocol version this decoder reads.
pub const VERSION: u8 = 1;
/// Header length, bytes (sync to timestamp).
pub const HEADER_LEN: usize = 18;
/// CRC length, bytes.
pub const CRC_LEN: usize = 4;
/// Most channels a frame may carry.
pub const MAX_CHANNELS: usize = 1024;

const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// CRC-32/ISO-HDLC (the CRC of zlib, PNG and Ethernet) of `bytes`.
pub fn crc32(bytes: &[u8]) -> u32 {
    CRC32.checksum(bytes)
}

/// How samples are stored in a frame.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum SampleFormat {
    /// Unsigned 16-bit integers (ADC counts), code 1.
    U16,
    /// 32-bit floats, code 2.
    #[default]
    F32,
}

impl SampleFormat {
    /// The format's code in the header.
    pub fn code(self) -> u8 {
        match self {
            SampleFormat::U16 => 1,
            SampleFormat::F32 => 2,
        }
    }

    /// The format of a header code.
    pub fn from_code(c: u8) -> Option<Self> {
        match c {
            1 => Some(SampleFormat::U16),
            2 => Some(SampleFormat::F32),
            _ => None,
        }
    }

    /// Bytes per sample.
    pub fn width(self) -> usize {
        match self {
            SampleFormat::U16 => 2,
            SampleFormat::F32 => 4,
        }
    }
}

/// Length in bytes of a frame of `channels` samples.
pub fn frame_len(format: SampleFormat, channels: usize) -> usize {
    HEADER_LEN + channels * format.width() + CRC_LEN
}

/// Appends one frame to `out`. Values are raw: ADC counts for `U16` (rounded
/// and clamped to `0..=65535`; the number clamped is returned), any finite
/// number for `F32`.
pub fn encode_frame(
    out: &mut Vec<u8>,
    format: SampleFormat,
    seq: u32,
    timestamp_us: u64,
    raw: &[f64],
) -> usize {
    assert!(
        !raw.is_empty() && raw.len() <= MAX_CHANNELS,
        "a frame carries 1..={MAX_CHANNELS} channels"
    );
    let start = out.len();
    out.extend_from_slice(&SYNC);
    out.push(VERSION);
    out.push(format.code());
    out.extend_from_slice(&(raw.len() as u16).to_le_bytes());
    out.extend_from_slice(&seq.to_le_bytes());
    out.extend_from_slice(&timestamp_us.to_le_bytes());
    let mut clamped = 0;
    for &v in raw {
        match format {
            SampleFormat::U16 => {
                let r = v.round();
                if !(0.0..=65535.0).contains(&r) {
                    clamped += 1;
                }
                // `as` saturates (and maps NaN to 0), which is the clamp we want.
                out.extend_from_slice(&(r.clamp(0.0, 65535.0) as u16).to_le_bytes());
            }
            SampleFormat::F32 => out.extend_from_slice(&(v as f32).to_le_bytes()),
        }
    }
    let crc = crc32(&out[start..]);
    out.extend_from_slice(&crc.to_le_bytes());
    clamped
}

/// A decoded frame: one sample per channel, at one instant.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    /// Sequence number.
    pub seq: u32,
    /// Device time of the samples, µs.
    pub timestamp_us: u64,
    /// How the samples were sent (one format per stream: [`FrameCheck`]).
    pub format: SampleFormat,
    /// One value per channel (taxel order), `raw * scale + offset`.
    pub samples: Vec<f64>,
}

/// What the decoder found, beside frames.
#[derive(Clone, Debug, PartialEq)]
pub enum DecodeEvent {
    /// A valid frame.
    Frame(Frame),
    /// `count` frames are missing before frame `got` (expected `expected`).
    Lost {
        /// The sequence number that was due.
        expected: u32,
        /// The sequence number that came.
        got: u32,
        /// Frames missing.
        count: u64,
    },
    /// A frame with a valid header failed its CRC and was dropped.
    CrcError {
        /// The sequence number its (unverified) header claimed.
        claimed_seq: u32,
    },
    /// A frame from the past (device reset or replay).
    OutOfOrder {
        /// The sequence number that was due.
        expected: u32,
        /// The sequence number that came.
        got: u32,
    },
}

/// Counts of what a decoder (and an acquisition) saw.
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct DaqStats {
    /// Bytes received.
    pub bytes: u64,
    /// Valid frames decoded.
    pub frames: u64,
    /// Frames dropped for a bad CRC.
    pub crc_errors: u64,
    /// Frames missing from the sequence (including those dropped for a bad CRC).
    pub lost_frames: u64,
    /// Sequence gaps (events), each of one or more lost frames.
    pub gaps: u64,
    /// Frames from the past (device reset or replay).
    pub out_of_order: u64,
    /// Bytes skipped while looking for a frame.
    pub garbage_bytes: u64,
    /// Times the stream went silent for longer than the stall timeout.
    pub stalls: u64,
    /// Valid frames (header and CRC) skipped because their channel count is
    /// not the stream's; their bytes are also counted in `garbage_bytes`.
    pub wrong_channels: u64,
    /// The channel count the last such frame carried.
    pub wrong_channel_count: Option<u16>,
}

/// "1 frame", "2 frames": a count with its noun in the right number.
pub fn count(n: u64, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

impl fmt::Display for DaqStats {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} ({}); {} lost in {}, {}, {} out of order, {}, {}",
            count(self.frames, "frame", "frames"),
            count(self.bytes, "byte", "bytes"),
            self.lost_frames,
            count(self.gaps, "gap", "gaps"),
            count(self.crc_errors, "CRC error", "CRC errors"),
            self.out_of_order,
            count(self.garbage_bytes, "garbage byte", "garbage bytes"),
            count(self.stalls, "stall", "stalls"),
        )?;
        if let Some(n) = self.wrong_channel_count.filter(|_| self.wrong_channels > 0) {
            write!(
                f,
                "; channel mismatch: {} of {} skipped",
                count(self.wrong_channels, "valid frame", "valid frames"),
                count(u64::from(n), "channel", "channels")
            )?;
        }
        Ok(())
    }
}

/// A streaming frame decoder: feed it bytes as they arrive, in chunks of any
/// size; it hands back frames and anomalies in stream order.
#[derive(Clone, Debug)]
pub struct Decoder {
    buf: Vec<u8>,
    channels: Option<usize>,
    scale: f64,
    offset: f64,
    next_seq: Option<u32>,
    stats: DaqStats,
}

impl Decoder {
    /// A decoder for frames of `channels` channels (`None`: the first valid
    /// frame fixes the count); values are `raw * scale + offset`.
    pub fn new(channels: Option<usize>, scale: f64, offset: f64) -> Self {
        Decoder {
            buf: Vec::new(),
            channels,
            scale,
            offset,
            next_seq: None,
            stats: DaqStats::default(),
        }
    }

    /// What the decoder has seen so far.
    pub fn stats(&self) -> &DaqStats {
        &self.stats
    }

    /// Mutable counts (an acquisition adds stalls).
    pub fn stats_mut(&mut self) -> &mut DaqStats {
        &mut self.stats
    }

    /// The channel count, once known.
    pub fn channels(&self) -> Option<usize> {
        self.channels
    }

    /// Bytes held back waiting for the rest of a frame.
    pub fn pending(&self) -> usize {
        self.buf.len()
    }

    /// Feeds bytes; calls `on` for every frame and anomaly they complete.
    pub fn feed(&mut self, bytes: &[u8], mut on: impl FnMut(DecodeEvent)) {
        self.stats.bytes += bytes.len() as u64;
        self.buf.extend_from_slice(bytes);
        let mut pos = 0;
        loop {
            // Find the next sync word.
            let Some(rel) = self.buf[pos..].windows(2).position(|w| w == SYNC) else {
                // Keep a trailing first sync byte: its partner may be on its way.
                let keep = usize::from(self.buf.last() == Some(&SYNC[0]) && self.buf.len() > pos);
                let skip = self.buf.len() - pos - keep;
                self.stats.garbage_bytes += skip as u64;
                pos += skip;
                break;
            };
            self.stats.garbage_bytes += rel as u64;
            pos += rel;
            let h = &self.buf[pos..];
            if h.len() < HEADER_LEN {
                break;
            }
            let format = SampleFormat::from_code(h[3]);
            let n = usize::from(u16::from_le_bytes([h[4], h[5]]));
            let header_ok = h[2] == VERSION && format.is_some() && (1..=MAX_CHANNELS).contains(&n);
            let Some(format) = format.filter(|_| header_ok) else {
                self.stats.garbage_bytes += 1;
                pos += 1;
                continue;
            };
            let len = frame_len(format, n);
            if h.len() < len {
                break;
            }
            let body = &h[..len - CRC_LEN];
            let crc = u32::from_le_bytes([h[len - 4], h[len - 3], h[len - 2], h[len - 1]]);
            let seq = u32::from_le_bytes([h[6], h[7], h[8], h[9]]);
            let crc_ok = crc32(body) == crc;
            if self.channels.is_some_and(|c| c != n) {
                // Another channel count: a wrong board or config when the CRC
                // holds (skipped whole and counted), else noise (one byte on).
                let skip = if crc_ok {
                    self.stats.wrong_channels += 1;
                    self.stats.wrong_channel_count = u16::try_from(n).ok();
                    len
                } else {
                    1
                };
                self.stats.garbage_bytes += skip as u64;
                pos += skip;
                continue;
            }
            if !crc_ok {
                self.stats.crc_errors += 1;
                self.stats.garbage_bytes += 1;
                pos += 1;
                on(DecodeEvent::CrcError { claimed_seq: seq });
                continue;
            }
            let mut ts = [0u8; 8];
            ts.copy_from_slice(&h[10..18]);
            let timestamp_us = u64::from_le_bytes(ts);
            let samples = h[HEADER_LEN..len - CRC_LEN]
                .chunks_exact(format.width())
                .map(|c| {
                    let raw = match format {
                        SampleFormat::U16 => f64::from(u16::from_le_bytes([c[0], c[1]])),
                        SampleFormat::F32 => f64::from(f32::from_le_bytes([c[0], c[1], c[2], c[3]])),
                    };
                    raw * self.scale + self.offset
                })
                .collect();
            self.channels = Some(n);
            if let Some(expected) = self.next_seq {
                let d = seq.wrapping_sub(expected);
                if d != 0 && d < 1 << 31 {
                    self.stats.lost_frames += u64::from(d);
                    self.stats.gaps += 1;
                    on(DecodeEvent::Lost {
                        expected,
                        got: seq,
                        count: u64::from(d),
                    });
                } else if d != 0 {
                    self.stats.out_of_order += 1;
                    on(DecodeEvent::OutOfOrder { expected, got: seq });
                }
            }
            self.next_seq = Some(seq.wrapping_add(1));
            self.stats.frames += 1;
            pos += len;
            on(DecodeEvent::Frame(Frame {
                seq,
                timestamp_us,
                format,
                samples,
            }));
        }
        self.buf.drain(..pos);
    }
}

/// Checks a stream's frames as they come, in constant memory (module docs,
/// "One stream, one format, one clock"): one sample format, timestamps on a
/// uniform grid. Feed it every frame in stream order.
#[derive(Clone, Debug, Default)]
pub struct FrameCheck {
    /// The stream's format (its first frame's).
    format: Option<SampleFormat>,
    /// Whether every timestamp so far equals the first (a board without a
    /// clock; the grid is then not fed).
    clockless: bool,
    /// The last frame's sequence number and timestamp.
    last: Option<(u32, u64)>,
    grid: TimeGrid,
    /// Frames taken.
    frames: u64,
}

impl FrameCheck {
    /// Takes the next frame; an error names it (its 0-based index in the
    /// stream and its sequence number) and what is wrong.
    pub fn push(&mut self, f: &Frame) -> Result<(), String> {
        let k = self.frames;
        let at = || format!("frame {k} (sequence {})", f.seq);
        let name = |s: SampleFormat| match s {
            SampleFormat::U16 => "u16",
            SampleFormat::F32 => "f32",
        };
        match self.format {
            Some(s) if s != f.format => {
                return Err(format!(
                    "{}: {} samples, but the frames before it carry {}: a stream keeps one \
                     sample format (docs/daq-protocol.md: do not mix formats)",
                    at(),
                    name(f.format),
                    name(s)
                ))
            }
            _ => self.format = Some(f.format),
        }
        let t = f.timestamp_us;
        let Some((seq, before)) = self.last else {
            // Clockless until a second frame says otherwise.
            self.clockless = true;
            self.last = Some((f.seq, t));
            self.frames += 1;
            return Ok(());
        };
        if self.clockless {
            if t == before {
                self.last = Some((f.seq, t));
                self.frames += 1;
                return Ok(());
            }
            if k > 1 {
                return Err(format!(
                    "{}: timestamp {t} µs, but the {k} frames before it all carry {before} µs: \
                     the timestamps must advance with every frame",
                    at()
                ));
            }
            // The second frame moves: a clock after all, from the first frame on.
            self.clockless = false;
            let _ = self.grid.push(before as f64, 1);
        }
        // 1: the next frame; 2..2^31: after lost frames; else a reset or a
        // repeat (the sequence numbers judge those, not the clock).
        let steps = f.seq.wrapping_sub(seq);
        if steps != 1 {
            self.grid.restart();
        }
        if (1..1 << 31).contains(&steps) && t <= before {
            let what = if t < before { "decrease" } else { "do not advance" };
            return Err(format!(
                "{}: the timestamps {what}: {t} µs after {before} µs at frame {}; they must \
                 increase with the sequence numbers",
                at(),
                k - 1
            ));
        }
        match self.grid.push(t as f64, 1) {
            Ok(()) => {}
            // Ruled out above for a forward step; a restarted grid takes any time.
            Err(GridBreak::NotIncreasing { .. }) => {}
            Err(GridBreak::Off { step, interval }) => {
                return Err(format!(
                    "{}: timestamp {t} µs is off the uniform grid: {} µs after the frame before, \
                     where the frames before it are {} µs apart (more than {} of a sample off: \
                     a sample rate that changes, or timestamps that jitter)",
                    at(),
                    round3(interval),
                    round3(step),
                    GRID_TOLERANCE
                ))
            }
        }
        self.last = Some((f.seq, t));
        self.frames += 1;
        Ok(())
    }
}

/// `v` to 3 decimals, for messages (`1000` rather than `1000.0000000002`).
fn round3(v: f64) -> f64 {
    (v * 1e3).round() / 1e3
}

/// A whole recording decoded: per-channel data and what was found.
#[derive(Clone, Debug, PartialEq)]
pub struct DecodedRecording {
    /// `data[channel][sample]`, lost frames filled when asked.
    pub data: Vec<Vec<f64>>,
    /// Sample rate from the timestamps (median interval per sequence step), Hz;
    /// `None` with fewer than two frames, or timestamps that never advance
    /// (a board without a clock).
    pub sample_rate_hz: Option<f64>,
    /// Counts.
    pub stats: DaqStats,
    /// Bytes of an incomplete frame at the end (a recording cut mid-frame).
    pub trailing_bytes: usize,
}

/// The hint of [`cut_end_error`], which `palpate daq emulate` swaps for its flag.
pub const CUT_END_HINT: &str = "Set `allow_cut_end = true` to drop that frame";

/// The error for a recording `shown` that ends inside a frame: `trailing`
/// bytes of an incomplete frame starting at byte `at`. One wording for every
/// reader of recordings (the `signal_file` and `daq` sources).
pub fn cut_end_error(shown: impl std::fmt::Display, trailing: usize, at: u64) -> String {
    format!(
        "{shown}: the recording ends inside a frame ({trailing} bytes of an incomplete frame at byte {at}): \
         cut while being written? {CUT_END_HINT}"
    )
}

/// Decodes a raw recording. Lost frames (gaps) are an error unless
/// `fill_gaps`, which holds the previous frame's values over each lost frame
/// (at most as many lost frames as received ones, see the module docs);
/// frames from the past, frames of another channel count, samples that are
/// not finite, a change of sample format and timestamps off a uniform grid
/// ([`FrameCheck`]) are always an error. A cut last frame is reported in
/// `trailing_bytes` for the caller to judge.
pub fn decode_recording(
    bytes: &[u8],
    scale: f64,
    offset: f64,
    fill_gaps: bool,
) -> Result<DecodedRecording, String> {
    let mut dec = Decoder::new(None, scale, offset);
    let mut frames: Vec<Frame> = Vec::new();
    let mut gaps: Vec<(usize, u64)> = Vec::new();
    dec.feed(bytes, |ev| match ev {
        DecodeEvent::Frame(f) => frames.push(f),
        DecodeEvent::Lost { count, .. } => gaps.push((frames.len(), count)),
        _ => {}
    });
    let stats = dec.stats().clone();
    if frames.is_empty() {
        return Err(format!("no valid DAQ frame in {} bytes ({stats})", bytes.len()));
    }
    if stats.out_of_order > 0 {
        return Err(format!(
            "{} frames arrived out of order (device reset?); split the recording ({stats})",
            stats.out_of_order
        ));
    }
    if stats.wrong_channels > 0 {
        return Err(format!(
            "channel mismatch: the first frame carries {} channels but {} valid frames carry another count ({stats})",
            frames[0].samples.len(),
            stats.wrong_channels
        ));
    }
    if stats.lost_frames > 0 && !fill_gaps {
        return Err(format!(
            "{} frames lost in {} gaps ({} CRC errors); set `fill_gaps = true` to hold values over them ({stats})",
            stats.lost_frames, stats.gaps, stats.crc_errors
        ));
    }
    if stats.lost_frames > frames.len() as u64 {
        return Err(format!(
            "{} frames lost but only {} received: `fill_gaps` fills at most as many frames as were received \
             (a sequence jump this long is a device reset or a corrupt file; split the recording) ({stats})",
            stats.lost_frames,
            frames.len()
        ));
    }
    for (k, f) in frames.iter().enumerate() {
        if let Some(ch) = f.samples.iter().position(|v| !v.is_finite()) {
            return Err(format!(
                "frame {k} (sequence {}), channel {ch}: sample {:?} is not finite",
                f.seq, f.samples[ch]
            ));
        }
    }
    let mut check = FrameCheck::default();
    for f in &frames {
        check.push(f)?;
    }
    let n = frames[0].samples.len();
    let mut data = vec![Vec::with_capacity(frames.len() + stats.lost_frames as usize); n];
    let mut g = gaps.iter().peekable();
    for (k, f) in frames.iter().enumerate() {
        while let Some(&&(at, count)) = g.peek() {
            if at != k {
                break;
            }
            // Hold the previous frame (there is one: a gap needs a frame before it).
            for (ch, col) in data.iter_mut().enumerate() {
                let last = col.last().copied().unwrap_or(f.samples[ch]);
                col.extend(std::iter::repeat_n(last, count as usize));
            }
            g.next();
        }
        for (col, &v) in data.iter_mut().zip(&f.samples) {
            col.push(v);
        }
    }
    let mut dts: Vec<f64> = frames
        .windows(2)
        .filter_map(|w| {
            let steps = w[1].seq.wrapping_sub(w[0].seq);
            (w[1].timestamp_us > w[0].timestamp_us && steps > 0)
                .then(|| (w[1].timestamp_us - w[0].timestamp_us) as f64 / f64::from(steps))
        })
        .collect();
    dts.sort_by(f64::total_cmp);
    let sample_rate_hz = (!dts.is_empty()).then(|| 1e6 / dts[dts.len() / 2]);
    Ok(DecodedRecording {
        data,
        sample_rate_hz,
        stats,
        trailing_bytes: dec.pending(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc_is_zlibs_crc32() {
        // The standard check value of CRC-32/ISO-HDLC.
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn worked_example_of_the_docs() {
        // docs/daq-protocol.md: 2 channels, u16, seq 7, t = 1000 µs, samples 1000 and 2000.
        let mut b = Vec::new();
        encode_frame(&mut b, SampleFormat::U16, 7, 1000, &[1000.0, 2000.0]);
        let hex: Vec<String> = b.iter().map(|x| format!("{x:02X}")).collect();
        assert_eq!(
            hex.join(" "),
            "AA 55 01 01 02 00 07 00 00 00 E8 03 00 00 00 00 00 00 E8 03 D0 07 99 E9 6C 59"
        );
    }

    #[test]
    fn frames_round_trip_through_any_chunking() {
        let mut b = Vec::new();
        for k in 0..20u32 {
            encode_frame(
                &mut b,
                SampleFormat::F32,
                k,
                u64::from(k) * 1000,
                &[k as f64, -0.5, 3.25],
            );
        }
        for chunk in [1, 2, 7, 64, b.len()] {
            let mut d = Decoder::new(Some(3), 1.0, 0.0);
            let mut got = Vec::new();
            for c in b.chunks(chunk) {
                d.feed(c, |e| {
                    if let DecodeEvent::Frame(f) = e {
                        got.push(f)
                    }
                });
            }
            assert_eq!(got.len(), 20, "chunk {chunk}");
            assert_eq!(got[5].samples, vec![5.0, -0.5, 3.25]);
            assert_eq!(got[19].timestamp_us, 19_000);
            assert_eq!(d.stats().garbage_bytes, 0);
            assert_eq!(d.pending(), 0);
        }
    }

    #[test]
    fn sequence_wrap_is_not_a_gap_but_a_jump_is() {
        let mut b = Vec::new();
        for seq in [u32::MAX - 1, u32::MAX, 0, 1, 5] {
            encode_frame(&mut b, SampleFormat::U16, seq, 0, &[1.0]);
        }
        let mut d = Decoder::new(None, 1.0, 0.0);
        let mut lost = vec![];
        d.feed(&b, |e| {
            if let DecodeEvent::Lost { count, .. } = e {
                lost.push(count)
            }
        });
        assert_eq!(lost, vec![3]);
        assert_eq!(d.stats().frames, 5);
        assert_eq!(d.stats().lost_frames, 3);
        // A jump across the wrap: from MAX-1 to 2 loses MAX, 0, 1.
        let mut b = Vec::new();
        encode_frame(&mut b, SampleFormat::U16, u32::MAX - 1, 0, &[1.0]);
        encode_frame(&mut b, SampleFormat::U16, 2, 0, &[1.0]);
        let mut d = Decoder::new(None, 1.0, 0.0);
        d.feed(&b, |_| {});
        assert_eq!(d.stats().lost_frames, 3);
        assert_eq!(d.stats().out_of_order, 0);
    }

    #[test]
    fn u16_values_clamp_and_scale() {
        let mut b = Vec::new();
        let clamped = encode_frame(&mut b, SampleFormat::U16, 0, 0, &[-3.0, 70000.0, 4095.4]);
        assert_eq!(clamped, 2);
        let mut d = Decoder::new(Some(3), 3.3 / 4095.0, 0.0);
        let mut f = None;
        d.feed(&b, |e| {
            if let DecodeEvent::Frame(x) = e {
                f = Some(x)
            }
        });
        let f = f.unwrap();
        assert_eq!(f.samples[0], 0.0);
        assert!((f.samples[1] - 65535.0 * 3.3 / 4095.0).abs() < 1e-9);
        assert!((f.samples[2] - 3.3).abs() < 1e-9);
    }

    /// f32 frames of one channel, frame `k` with sequence `seqs[k]`,
    /// timestamp `ts[k]` µs and format `formats[k % len]`.
    fn stream(seqs: &[u32], ts: &[u64], formats: &[SampleFormat]) -> Vec<u8> {
        let mut b = Vec::new();
        for (k, (&s, &t)) in seqs.iter().zip(ts).enumerate() {
            encode_frame(&mut b, formats[k % formats.len()], s, t, &[1.0]);
        }
        b
    }

    /// Timestamps off a uniform grid and a change of sample format are
    /// errors naming the frame, its sequence number and the intervals (or
    /// formats), not a rate taken from the median interval.
    #[test]
    fn a_recording_off_a_uniform_grid_or_of_mixed_formats_is_refused() {
        let f32s = [SampleFormat::F32];
        // 100 Hz for 700 frames, then 200 Hz.
        let ts: Vec<u64> = (0..1400u64)
            .map(|k| {
                if k < 700 {
                    k * 10_000
                } else {
                    6_990_000 + (k - 699) * 5_000
                }
            })
            .collect();
        let seqs: Vec<u32> = (0..1400).collect();
        let e = decode_recording(&stream(&seqs, &ts, &f32s), 1.0, 0.0, false).unwrap_err();
        assert!(
            e.contains("frame 700 (sequence 700)")
                && e.contains("off the uniform grid")
                && e.contains("5000 µs after")
                && e.contains("10000 µs apart"),
            "{e}"
        );
        // Intervals alternating 13 and 7 ms (a median of 13 ms: read as 77 Hz).
        let ts: Vec<u64> = (0..40u64).map(|k| k / 2 * 20_000 + (k % 2) * 13_000).collect();
        let e = decode_recording(&stream(&seqs[..40], &ts, &f32s), 1.0, 0.0, false).unwrap_err();
        assert!(
            e.contains("frame 2 (sequence 2)") && e.contains("13000 µs apart"),
            "{e}"
        );
        // u16 and f32 frames in turn.
        let ts: Vec<u64> = (0..20u64).map(|k| k * 1000).collect();
        let mixed = stream(&seqs[..20], &ts, &[SampleFormat::U16, SampleFormat::F32]);
        let e = decode_recording(&mixed, 1.0, 0.0, false).unwrap_err();
        assert!(
            e.contains("frame 1 (sequence 1)") && e.contains("f32 samples") && e.contains("carry u16"),
            "{e}"
        );
        // Well-formed: the rate as before, lost frames (time goes on over
        // them) filled; a board that stamps nothing gives no rate.
        let seqs: Vec<u32> = (0..20).filter(|&s| s != 7).collect();
        let ts: Vec<u64> = seqs.iter().map(|&s| u64::from(s) * 1000).collect();
        let d = decode_recording(&stream(&seqs, &ts, &f32s), 1.0, 0.0, true).unwrap();
        assert_eq!((d.sample_rate_hz, d.data[0].len()), (Some(1000.0), 20));
        let d = decode_recording(&stream(&seqs, &[0; 19], &f32s), 1.0, 0.0, true).unwrap();
        assert_eq!(d.sample_rate_hz, None);
        // Stamped, then stuck: refused at the first frame that repeats a time.
        let mut ts: Vec<u64> = (0..10u64).map(|k| k * 1000).collect();
        ts[6] = 5000;
        let seqs: Vec<u32> = (0..10).collect();
        let e = decode_recording(&stream(&seqs, &ts, &f32s), 1.0, 0.0, false).unwrap_err();
        assert!(
            e.contains("frame 6 (sequence 6)") && e.contains("do not advance"),
            "{e}"
        );
    }

    /// The check holds a few numbers: it takes a frame at a time, and a
    /// device reset (the sequence going back) restarts its grid.
    #[test]
    fn the_frame_check_is_incremental_and_restarts_after_a_reset() {
        let mut c = FrameCheck::default();
        let frame = |seq: u32, t: u64| Frame {
            seq,
            timestamp_us: t,
            format: SampleFormat::F32,
            samples: vec![0.0],
        };
        for k in 0..100u32 {
            c.push(&frame(k, u64::from(k) * 1000)).unwrap();
        }
        // A reset: sequence and clock start again from 0, on the same step.
        c.push(&frame(0, 0)).unwrap();
        c.push(&frame(1, 1000)).unwrap();
        let e = c.push(&frame(2, 2600)).unwrap_err();
        assert!(
            e.contains("frame 102 (sequence 2)") && e.contains("1600 µs after"),
            "{e}"
        );
    }

    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        /// Any bytes, in any chunks: no panic, and every byte is accounted for
        /// (in a valid frame, skipped as garbage, or pending).
        #[test]
        fn decoder_accounts_for_every_byte(bytes in proptest::collection::vec(any::<u8>(), 0..600),
                                           chunk in 1usize..64, frames_in in 0usize..4) {
            let mut s = Vec::new();
            for k in 0..frames_in {
                encode_frame(&mut s, SampleFormat::U16, k as u32, 0, &[1.0, 2.0]);
            }
            s.extend(&bytes);
            let mut d = Decoder::new(None, 1.0, 0.0);
            let mut frame_bytes = 0u64;
            for c in s.chunks(chunk) {
                d.feed(c, |e| if let DecodeEvent::Frame(f) = e {
                    frame_bytes += frame_len(SampleFormat::U16, f.samples.len()) as u64;
                });
            }
            let st = d.stats();
            prop_assert_eq!(st.garbage_bytes + frame_bytes + d.pending() as u64, s.len() as u64);
            prop_assert!(st.frames >= frames_in as u64);
        }

        /// Frames round-trip exactly (f32 values, any sequence and time).
        #[test]
        fn frames_round_trip(vals in proptest::collection::vec(-1e6f32..1e6, 1..40), seq in any::<u32>(), ts in any::<u64>()) {
            let raw: Vec<f64> = vals.iter().map(|&v| f64::from(v)).collect();
            let mut b = Vec::new();
            encode_frame(&mut b, SampleFormat::F32, seq, ts, &raw);
            let mut d = Decoder::new(Some(raw.len()), 1.0, 0.0);
            let mut got = None;
            d.feed(&b, |e| if let DecodeEvent::Frame(f) = e { got = Some(f) });
            prop_assert_eq!(got, Some(Frame { seq, timestamp_us: ts, format: SampleFormat::F32, samples: raw }));
        }
    }
}
