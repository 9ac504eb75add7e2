//! WSS benches: one paper-like trial's estimate (17 classes, 10 ms hop, 4x4
//! array, 2 s holds, crossing at 2 mm/s) by the fast batch path, the streaming
//! cost per frame, the direct reference on a short trial for scale, and the
//! templates of one angle (what each probe of a refining search builds), and
//! one trial's estimate refined by `refine = "search"` at the known speed and
//! with the joint speed search (`speed_tolerance = 0.25`: five grid speeds,
//! then golden-section probes of speed and angle), the cost that
//! graphs/paper/speed_error.toml's points pay per trial.
//!
//! Trials are ideal spike images built from the geometry (each taxel's count
//! proportional to the time the edge spends over its area in the frame).

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use palpate_core::geometry::Edge;
use palpate_core::{SpikeImages, TaxelLayout};
use palpate_stages::estimate::wss::{
    wss_batch, wss_batch_speeds, wss_reference, Refine, Templates, WssParams, WssStream,
};
use std::hint::black_box;
use std::sync::Arc;

fn ideal(layout: &TaxelLayout, theta: f64, speed: f64, hold_ms: f64) -> SpikeImages {
    let (hop, window) = (10.0, 100.0);
    let edge = Edge::new(theta);
    let (lo, hi) = edge.footprint(layout);
    let vn = edge.normal_speed(speed) / 1000.0;
    let duration = 2.0 * hold_ms + (hi - lo) / vn;
    let n_frames = ((duration - window) / hop).floor() as usize + 1;
    let h = layout.taxel_mm() / 2.0 * (edge.normal[0].abs() + edge.normal[1].abs());
    let n = layout.len();
    let mut counts = vec![0.0; n_frames * n];
    for t in 0..n {
        let o = edge.offset(layout.position(t));
        let (t_in, t_out) = (hold_ms + (hi - (o + h)) / vn, hold_ms + (hi - (o - h)) / vn);
        for k in 0..n_frames {
            let (a, b) = (k as f64 * hop, k as f64 * hop + window);
            counts[k * n + t] = (0.2 * (b.min(t_out) - a.max(t_in)).max(0.0)).round();
        }
    }
    SpikeImages {
        layout: layout.clone(),
        window_ms: window,
        hop_ms: hop,
        n_frames,
        counts,
    }
}

fn bench(c: &mut Criterion) {
    let params = WssParams::default();
    let layout = TaxelLayout::paper();
    let tpl = Arc::new(Templates::new(&layout, 10.0, &params).unwrap());
    for theta in [45.0, 90.0, 10.0] {
        let im = ideal(&layout, theta, 2.0, 2000.0);
        // Warm the template spectra caches (a run computes them once).
        let _ = wss_batch(&im, &tpl, &params).unwrap();
        c.bench_function(
            &format!("wss_batch_17cls_{theta}deg_{}frames", im.n_frames),
            |b| b.iter(|| wss_batch(black_box(&im), &tpl, &params).unwrap()),
        );
        let mut g = c.benchmark_group("wss_stream");
        g.throughput(Throughput::Elements(im.n_frames as u64));
        g.sample_size(10);
        g.bench_function(format!("per_frame_17cls_{theta}deg_{}frames", im.n_frames), |b| {
            b.iter(|| {
                let mut s = WssStream::new(tpl.clone(), params.clone(), im.window_ms).unwrap();
                for k in 0..im.n_frames {
                    black_box(s.push(im.frame(k)).unwrap());
                }
            })
        });
        g.finish();
    }
    let mut g = c.benchmark_group("wss_templates_one_angle");
    for theta in [12.3, 52.1] {
        let frames = Templates::for_angles(&layout, 10.0, &params, &[theta])
            .unwrap()
            .classes()[0]
            .len;
        g.throughput(Throughput::Elements((frames * layout.len()) as u64));
        g.bench_function(format!("{theta}deg_{frames}frames"), |b| {
            b.iter(|| Templates::for_angles(&layout, 10.0, &params, black_box(&[theta])).unwrap())
        });
    }
    g.finish();
    // Refined searches: templates per speed built once, as the stage does
    // (each probe still builds its own one-angle templates and spectra).
    let mut g = c.benchmark_group("wss_search");
    g.sample_size(20);
    for (name, tolerance) in [("known_speed", 0.0), ("joint_speed", 0.25)] {
        let p = WssParams {
            refine: Refine::Search,
            speed_tolerance: tolerance,
            ..params.clone()
        };
        let sets: Vec<(f64, Templates)> = p
            .speed_factors()
            .into_iter()
            .map(|f| (f, Templates::new(&layout, 10.0, &p.at_speed(f)).unwrap()))
            .collect();
        let sets: Vec<(f64, &Templates)> = sets.iter().map(|(f, t)| (*f, t)).collect();
        for theta in [47.3, 21.8] {
            let im = ideal(&layout, theta, 2.0, 2000.0);
            let _ = wss_batch_speeds(&im, &sets, &p).unwrap();
            g.bench_function(format!("{name}_{theta}deg_{}frames", im.n_frames), |b| {
                b.iter(|| wss_batch_speeds(black_box(&im), &sets, &p).unwrap())
            });
        }
    }
    g.finish();
    let mut g = c.benchmark_group("wss_reference");
    g.sample_size(10);
    let im = ideal(&layout, 60.0, 2.0, 500.0);
    g.bench_function(format!("direct_17cls_60deg_{}frames", im.n_frames), |b| {
        b.iter(|| wss_reference(black_box(&im), &tpl, &params).unwrap())
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
