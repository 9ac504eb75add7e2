//! IO benches: DAQ frame decoding (must keep far ahead of 1 kHz x 16 taxels) and
//! CSV signal reading.
//!
//! Run: `cargo bench --bench io`.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use palpate_stages::io::daq::{encode_frame, DecodeEvent, Decoder, SampleFormat};

fn decode(c: &mut Criterion) {
    // 10 s of the paper's board: 10 000 frames of 16 u16 samples.
    let mut stream = Vec::new();
    for k in 0..10_000u32 {
        let raw: Vec<f64> = (0..16).map(|x| f64::from((k * 7 + x * 13) % 4096)).collect();
        encode_frame(&mut stream, SampleFormat::U16, k, u64::from(k) * 1000, &raw);
    }
    let mut g = c.benchmark_group("daq");
    g.throughput(Throughput::Bytes(stream.len() as u64));
    g.bench_function("decode_10s_16taxels_1khz", |b| {
        b.iter(|| {
            let mut d = Decoder::new(Some(16), 3.3 / 4095.0, 0.0);
            let mut n = 0usize;
            for chunk in stream.chunks(512) {
                d.feed(chunk, |e| n += usize::from(matches!(e, DecodeEvent::Frame(_))));
            }
            assert_eq!(n, 10_000);
            n
        })
    });
    g.finish();
}

criterion_group!(benches, decode);
criterion_main!(benches);
