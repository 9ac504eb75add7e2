//! IO benches: DAQ frame decoding (must keep far ahead of 1 kHz x 16 taxels),
//! and the content keys a sweep hashes its trained estimators' inputs into
//! (`Item::content_key`) to reuse their fits.
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

/// The keys of one run's training items in a fit-sharing sweep: the lab
/// set's 170 trials of spike images, a median trial's 2158 frames x 16 taxels
/// each (5.9 M counts).
fn content_keys(c: &mut Criterion) {
    use palpate_core::{Item, Payload, SpikeImages, TaxelLayout, TrialMeta};
    use std::sync::Arc;
    let items: Vec<Item> = (0..170)
        .map(|t| Item {
            meta: Arc::new(TrialMeta {
                trial_id: format!("edge-r{t:03}"),
                index: t,
                ..TrialMeta::default()
            }),
            payload: Payload::from(SpikeImages {
                layout: TaxelLayout::paper(),
                window_ms: 100.0,
                hop_ms: 10.0,
                n_frames: 2158,
                counts: (0..2158 * 16)
                    .map(|k| f64::from(((k * 7 + t) % 11) as u32 % 3))
                    .collect(),
            }),
        })
        .collect();
    let mut g = c.benchmark_group("cache");
    g.throughput(Throughput::Bytes((170 * 2158 * 16 * 8) as u64));
    g.bench_function("content_keys_170_lab_trials", |b| {
        b.iter(|| items.iter().map(Item::content_key).fold(0u64, |a, k| a ^ k))
    });
    g.finish();
}

criterion_group!(benches, decode, content_keys);
criterion_main!(benches);
