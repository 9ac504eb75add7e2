//! The DAQ: a binary frame protocol for boards that stream taxel samples over
//! USB serial (the paper's board: 16 taxels at 1 kHz), its decoder, live
//! acquisition with raw recording, and an emulator that plays any signals
//! through a pseudo-terminal so the live path runs without hardware.
//!
//! * [`protocol`]: the frame format, [`encode_frame`], the streaming
//!   [`Decoder`] (resynchronisation, CRC errors, lost frames) and
//!   [`decode_recording`] for recorded streams;
//! * [`live`]: [`acquire`] (any `Read`), [`acquire_serial`], [`RawRecorder`],
//!   [`emulate`], [`emulate_pty`], [`open_pty`], [`signals_from_recording`];
//! * [`source`]: the `daq` source stage ([`DaqConfig`]): a port, a recording
//!   or an emulated scene, cut into trials at contact ([`Segmenter`]), offline
//!   or streamed live through a graph.
//!
//! The format is specified for firmware authors in `docs/daq-protocol.md`.
//! Recorded streams are read back offline by the `signal_file` source
//! (`format = "daq"`, or a `.daq`/`.bin` extension).

pub mod live;
pub mod protocol;
pub mod source;

pub use live::{
    acquire, acquire_serial, emulate, emulate_pty, emulate_pty_drain, open_pty, open_serial,
    signals_from_recording, AcquireOptions, AcquireReport, DaqError, DaqErrorKind, DaqEvent, EmulateOptions,
    EmulateReport, Pty, RawRecorder, StopReason, READ_AHEAD_BYTES,
};
pub use protocol::{
    crc32, cut_end_error, decode_recording, encode_frame, frame_len, DaqStats, DecodeEvent, DecodedRecording,
    Decoder, Frame, FrameCheck, SampleFormat, CUT_END_HINT,
};
pub use source::{
    is_pseudo_terminal, simulate_trial, DaqConfig, DaqSource, SegEvent, SegmentMode, SegmentPlan, Segmenter,
};
