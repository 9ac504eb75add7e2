//! The DAQ path end to end: an in-memory stream with injected corruption, and
//! the live path through a pseudo-terminal (emulator -> pty -> acquisition ->
//! raw recording -> `signal_file`), a device that disappears, and a stall.

use palpate_core::{Payload, Signals, TaxelLayout};
use palpate_stages::io::daq::{
    acquire, acquire_serial, decode_recording, emulate, encode_frame, frame_len, open_pty, AcquireOptions,
    DaqErrorKind, DaqEvent, EmulateOptions, Frame, RawRecorder, SampleFormat, StopReason,
};
use std::io::Cursor;
use std::ops::ControlFlow;
use std::time::Duration;

fn value(x: usize, k: usize) -> f64 {
    1.75 + 0.05 * x as f64 + 0.5 * ((k as f64) * 0.05).sin()
}

fn recording(taxels: usize, samples: usize) -> Signals {
    Signals {
        sample_rate_hz: 1000.0,
        layout: TaxelLayout::Grid {
            rows: taxels / 4,
            cols: 4,
            pitch_mm: 3.0,
            taxel_mm: 2.0,
        },
        unit: "V".into(),
        data: (0..taxels)
            .map(|x| (0..samples).map(|k| value(x, k)).collect())
            .collect(),
    }
}

#[test]
fn corrupted_stream_counts_crc_errors_lost_frames_and_garbage() {
    const N: u32 = 200;
    let first = u32::MAX - 50; // the sequence wraps inside the stream
    let fl = frame_len(SampleFormat::U16, 16);
    let mut stream = Vec::new();
    let mut sent = Vec::new();
    for k in 0..N {
        let mut f = Vec::new();
        let raw: Vec<f64> = (0..16).map(|x| (k as usize * 16 + x) as f64).collect();
        encode_frame(
            &mut f,
            SampleFormat::U16,
            first.wrapping_add(k),
            u64::from(k) * 1000,
            &raw,
        );
        assert_eq!(f.len(), fl);
        match k {
            10 | 11 => continue,         // dropped by the link
            50 => f[HEADER + 3] ^= 0x10, // payload bit flip: CRC error
            80 => f[0] ^= 0xFF,          // sync destroyed: the frame is unreadable
            120 => f[fl - 1] ^= 0x01,    // CRC byte flipped
            _ => sent.push(k),
        }
        stream.extend(&f);
        if k == 100 {
            // Line noise, including a false sync word with a bad header.
            stream.extend([0x00, 0xAA, 0x55, 0x01, 0x02, 0x03, 0x00, 0xAA, 0x13, 0x55, 0xAA]);
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("raw.daq");
    let opts = AcquireOptions {
        channels: Some(16),
        record: Some(rec.clone()),
        ..Default::default()
    };
    let mut frames: Vec<Frame> = Vec::new();
    let mut events = (0u64, 0u64, Vec::new());
    let report = acquire(Cursor::new(stream.clone()), &opts, |ev| {
        match ev {
            DaqEvent::Frame(f) => frames.push(f.clone()),
            DaqEvent::CrcError => events.0 += 1,
            DaqEvent::OutOfOrder => events.1 += 1,
            DaqEvent::Lost { count, .. } => events.2.push(count),
            DaqEvent::Stall { .. } | DaqEvent::Waiting { .. } => {}
        }
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!(report.stopped, StopReason::EndOfStream);
    let s = &report.stats;
    assert_eq!(s.frames, sent.len() as u64);
    assert_eq!(s.crc_errors, 2, "frames 50 and 120");
    assert_eq!(s.lost_frames, 5, "10, 11 dropped; 50, 80, 120 unreadable");
    assert_eq!(s.gaps, 4);
    assert_eq!(events.2, vec![2, 1, 1, 1]);
    assert_eq!(events.0, 2);
    assert_eq!(s.out_of_order, 0, "the wrap is not a reordering");
    assert_eq!(s.bytes, stream.len() as u64);
    // Every received frame is intact and in order.
    let got: Vec<u32> = frames.iter().map(|f| f.seq.wrapping_sub(first)).collect();
    assert_eq!(got, sent);
    for f in &frames {
        let k = f.seq.wrapping_sub(first) as usize;
        assert_eq!(f.samples[3], (k * 16 + 3) as f64);
        assert_eq!(f.timestamp_us, k as u64 * 1000);
    }
    // The recording holds every byte that arrived.
    assert_eq!(std::fs::read(&rec).unwrap(), stream);
    assert_eq!(report.recorded_bytes, stream.len() as u64);
    // Offline: an error naming the counts, or filled gaps when asked.
    let e = decode_recording(&stream, 1.0, 0.0, false).unwrap_err();
    assert!(e.contains("5 frames lost") && e.contains("2 CRC errors"), "{e}");
    let d = decode_recording(&stream, 1.0, 0.0, true).unwrap();
    assert_eq!(d.data[0].len(), N as usize, "every frame slot, lost ones held");
    assert_eq!(
        d.data[3][10],
        (9 * 16 + 3) as f64,
        "lost frames 10, 11 hold frame 9"
    );
    assert_eq!(d.data[3][11], (9 * 16 + 3) as f64);
    assert_eq!(d.data[3][12], (12 * 16 + 3) as f64);
    assert_eq!(d.data[3][80], (79 * 16 + 3) as f64);
    assert_eq!(d.sample_rate_hz, Some(1000.0));
}

const HEADER: usize = 18;

#[test]
fn garbage_before_and_between_frames_is_skipped_byte_by_byte() {
    // Every prefix of garbage, and frames split at every offset, decode the same.
    let mut frames = Vec::new();
    for k in 0..3u32 {
        encode_frame(&mut frames, SampleFormat::F32, k, u64::from(k), &[0.25, -1.0]);
    }
    for junk in [
        vec![],
        vec![0xAA],
        vec![0x55, 0xAA, 0xAA],
        vec![1, 2, 3, 0xAA, 0x55, 9],
    ] {
        let mut s = junk.clone();
        s.extend(&frames);
        let mut d = palpate_stages::io::daq::Decoder::new(None, 1.0, 0.0);
        let mut n = 0;
        for b in s.chunks(5) {
            d.feed(b, |e| {
                n += usize::from(matches!(e, palpate_stages::io::daq::DecodeEvent::Frame(_)))
            });
        }
        assert_eq!(n, 3, "junk {junk:?}");
        assert_eq!(d.stats().garbage_bytes, junk.len() as u64, "junk {junk:?}");
    }
}

#[test]
fn recorder_flushes_every_interval() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("r.bin");
    let mut r = RawRecorder::create(&p, Duration::ZERO).unwrap();
    r.write(b"abc").unwrap();
    // Readable by another handle before the recorder is dropped or finished.
    assert_eq!(std::fs::read(&p).unwrap(), b"abc");
    let mut r2 = RawRecorder::create(&dir.path().join("s.bin"), Duration::from_secs(3600)).unwrap();
    r2.write(b"xyz").unwrap();
    r2.flush().unwrap();
    assert_eq!(std::fs::read(dir.path().join("s.bin")).unwrap(), b"xyz");
    drop(r);
}

#[test]
fn live_path_through_a_pty_matches_the_recording() {
    let sig = recording(16, 600);
    let pty = open_pty().unwrap();
    let mut master = pty.master;
    let play = sig.clone();
    let player = std::thread::spawn(move || {
        let r = emulate(
            &play,
            &mut master,
            &EmulateOptions {
                speed: 20.0,
                first_seq: u32::MAX - 300,
                ..Default::default()
            },
        );
        // Keep the terminal open until the reader is done.
        std::thread::sleep(Duration::from_millis(500));
        r
    });
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("live.daq");
    let opts = AcquireOptions {
        channels: Some(16),
        record: Some(rec.clone()),
        max_frames: Some(600),
        give_up_after: Some(Duration::from_secs(10)),
        ..Default::default()
    };
    let mut frames = Vec::new();
    let report = acquire(pty.slave, &opts, |ev| {
        if let DaqEvent::Frame(f) = ev {
            frames.push(f.clone());
        }
        ControlFlow::Continue(())
    })
    .unwrap();
    let played = player.join().unwrap().unwrap();
    assert_eq!(played.frames, 600);
    // Real-time pacing: 600 ms of signal at 20x takes about 30 ms, never less.
    assert!(
        played.elapsed >= Duration::from_millis(29),
        "{:?}",
        played.elapsed
    );
    assert_eq!(report.stopped, StopReason::MaxFrames);
    assert_eq!(report.stats.frames, 600);
    assert_eq!(
        report.stats.lost_frames + report.stats.crc_errors + report.stats.garbage_bytes,
        0
    );
    for (k, f) in frames.iter().enumerate() {
        assert_eq!(f.timestamp_us, k as u64 * 1000);
        for x in 0..16 {
            assert_eq!(
                f.samples[x],
                f64::from(sig.data[x][k] as f32),
                "frame {k} taxel {x}"
            );
        }
    }
    // The raw recording, read back by the `signal_file` source, is the same signal.
    palpate_stages::link();
    let toml = format!(
        "[stages.src]\ntype = \"signal_file\"\npath = \"{}\"\n",
        rec.display()
    );
    let g = palpate_core::load_str(&toml, "g.toml", "g", &Default::default()).unwrap();
    let r = palpate_core::run(
        &g,
        &palpate_core::RunOptions {
            keep_outputs: true,
            ..Default::default()
        },
    )
    .unwrap();
    let Payload::Signals(s) = &r.outputs["src"][0].payload else {
        panic!()
    };
    assert_eq!(s.sample_rate_hz, 1000.0);
    assert_eq!(s.n_samples(), 600);
    assert_eq!(s.data[5][123], f64::from(sig.data[5][123] as f32));
}

#[test]
fn a_device_that_disappears_keeps_what_was_recorded() {
    let half = recording(16, 300);
    let pty = open_pty().unwrap();
    let path = pty.slave_path.clone();
    let mut master = pty.master;
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("cut.daq");
    let opts = AcquireOptions {
        channels: Some(16),
        record: Some(rec.clone()),
        give_up_after: Some(Duration::from_secs(10)),
        ..Default::default()
    };
    let reader = std::thread::spawn(move || {
        let mut n = 0u64;
        let r = acquire_serial(&path, 115_200, &opts, |ev| {
            n += u64::from(matches!(ev, DaqEvent::Frame(_)));
            ControlFlow::Continue(())
        });
        (r, n)
    });
    std::thread::sleep(Duration::from_millis(200)); // let the reader open the port
    emulate(
        &half,
        &mut master,
        &EmulateOptions {
            speed: 50.0,
            ..Default::default()
        },
    )
    .unwrap();
    std::thread::sleep(Duration::from_millis(300)); // let it drain
    drop(master); // unplugged
    drop(pty.slave);
    let (r, n) = reader.join().unwrap();
    let e = r.unwrap_err();
    assert_eq!(e.kind, DaqErrorKind::Disconnected, "{}", e.message);
    assert_eq!(n, 300);
    assert_eq!(e.stats.frames, 300);
    assert!(e.message.contains("after 300 frames"), "{}", e.message);
    assert!(e.message.contains("cut.daq"), "{}", e.message);
    // Everything received is on disk.
    let d = decode_recording(&std::fs::read(&rec).unwrap(), 1.0, 0.0, false).unwrap();
    assert_eq!(d.data[0].len(), 300);
    assert_eq!(e.recorded_bytes, 300 * frame_len(SampleFormat::F32, 16) as u64);
}

/// A pseudo-terminal whose device side has sent 50 frames of 4 channels at
/// once and then stays silent (keep the returned master open meanwhile).
fn fifty_frames_then_silence() -> (impl Sized, impl std::io::Read + Send + 'static) {
    let sig = recording(4, 50);
    let pty = open_pty().unwrap();
    let mut master = pty.master;
    emulate(
        &sig,
        &mut master,
        &EmulateOptions {
            speed: f64::INFINITY,
            ..Default::default()
        },
    )
    .unwrap();
    (master, pty.slave)
}

#[test]
fn a_silent_device_stalls_then_gives_up() {
    let (master, slave) = fifty_frames_then_silence();
    let opts = AcquireOptions {
        channels: Some(4),
        stall_timeout: Duration::from_millis(100),
        give_up_after: Some(Duration::from_millis(400)),
        ..Default::default()
    };
    let mut stalls = 0;
    let e = acquire(slave, &opts, |ev| {
        stalls += u64::from(matches!(ev, DaqEvent::Stall { .. }));
        ControlFlow::Continue(())
    })
    .unwrap_err();
    drop(master);
    assert_eq!(e.kind, DaqErrorKind::Stalled);
    assert_eq!(e.stats.frames, 50);
    assert_eq!(e.stats.stalls, 1, "one stall per silence");
    assert_eq!(stalls, 1);
    assert!(e.message.contains("after 50 frames"), "{}", e.message);
}

/// A caller can stop while the board is silent: between frames the
/// acquisition reports each wait (`DaqEvent::Waiting`), so a stop asked for
/// then (Ctrl-C on a live session) is seen without waiting for a frame,
/// the stall or the give-up.
#[test]
fn a_silent_device_can_be_stopped_while_waiting() {
    let (master, slave) = fifty_frames_then_silence();
    let opts = AcquireOptions {
        channels: Some(4),
        stall_timeout: Duration::from_millis(100),
        flush_interval: Duration::from_millis(10),
        give_up_after: Some(Duration::from_secs(30)),
        ..Default::default()
    };
    let (mut frames, mut waits) = (0u64, 0u64);
    let report = acquire(slave, &opts, |ev| match ev {
        DaqEvent::Frame(_) => {
            frames += 1;
            ControlFlow::Continue(())
        }
        // Once every frame is in, the first wait stops it.
        DaqEvent::Waiting { silent } if frames == 50 => {
            waits += 1;
            assert!(silent < Duration::from_secs(30), "{silent:?}");
            ControlFlow::Break(())
        }
        _ => ControlFlow::Continue(()),
    })
    .unwrap_or_else(|e| panic!("{}", e.message));
    drop(master);
    assert_eq!(report.stopped, StopReason::Callback);
    assert_eq!((report.stats.frames, frames, waits), (50, 50, 1));
    assert_eq!(report.stats.stalls, 0, "stopped before the stall");
}

#[test]
fn emulator_rejects_bad_signals() {
    let mut sig = recording(4, 10);
    sig.data[2][7] = f64::NAN;
    let e = emulate(&sig, &mut Vec::new(), &EmulateOptions::default()).unwrap_err();
    assert!(e.contains("sample 7 of taxel 2"), "{e}");
    let sig = recording(4, 10);
    let e = emulate(
        &sig,
        &mut Vec::new(),
        &EmulateOptions {
            speed: 0.0,
            ..Default::default()
        },
    )
    .unwrap_err();
    assert!(e.contains("speed"), "{e}");
    // u16 frames with a volts-per-count scale round-trip to the ADC resolution.
    let mut out = Vec::new();
    let scale = 3.3 / 4095.0;
    let rep = emulate(
        &sig,
        &mut out,
        &EmulateOptions {
            speed: f64::INFINITY,
            format: SampleFormat::U16,
            scale,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(rep.clamped, 0);
    let d = decode_recording(&out, scale, 0.0, false).unwrap();
    for x in 0..4 {
        for k in 0..10 {
            assert!((d.data[x][k] - sig.data[x][k]).abs() <= scale / 2.0 + 1e-12);
        }
    }
}
