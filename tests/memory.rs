//! Memory against input length: the batch pipeline grows linearly
//! with the input, the streaming path not at all. Its own test binary, so the
//! counting allocator (`benches/common/memory.rs`) sees nothing else.
//!
//! Allocation sizes are deterministic, so these are exact assertions; the
//! release bench (`cargo bench --bench memory`) measures 10, 100 and 1000 s,
//! this debug test 10, 100 and 400 s (three palpations cycled) to stay fast.

#[path = "../benches/common/memory.rs"]
mod memory;

use memory::{lab_trials, live_graph, measure, quickstart, stage_table, table, Counting, MIB};

#[global_allocator]
static ALLOC: Counting = Counting;

#[test]
fn batch_memory_is_linear_and_streaming_memory_constant() {
    let trials = lab_trials(3);
    let g = quickstart();
    let cfg = live_graph();
    let rows: Vec<memory::Row> = [10.0, 100.0, 400.0]
        .into_iter()
        .map(|s| measure(&g, &cfg, &trials, s))
        .collect();
    eprintln!("{}\n{}", table(&rows), stage_table(&rows));
    let [a, b, c] = rows.as_slice() else {
        unreachable!()
    };

    // Streaming: the WSS stream reserves its state with the first images and
    // holds it to the end; 40 times more input adds only its few kept
    // alignments (48 B each).
    assert!(a.stream_images == 1000 && c.stream_images == 40_000);
    assert_eq!(a.stream_built_bytes, c.stream_built_bytes);
    for r in &rows {
        assert!(
            // Kept alignments (48 B each, in a doubling Vec): up to ~1900 with the
            // default 33-class grid before the edge arrives.
            r.stream_peak_bytes <= r.stream_end_bytes + 256 * 1024,
            "{} s: peak {} B, at the end {} B",
            r.seconds,
            r.stream_peak_bytes,
            r.stream_end_bytes
        );
    }
    assert!(
        c.stream_peak_bytes <= a.stream_peak_bytes + 64 * 1024,
        "streaming: {} B at 10 s, {} B at 400 s",
        a.stream_peak_bytes,
        c.stream_peak_bytes
    );
    // ... and holds far less than the input it has seen (25 MiB by 400 s).
    assert!((c.stream_peak_bytes as f64) < 0.5 * c.input_bytes as f64);

    // Batch: holds at least its input, and grows linearly: the growth per
    // input second from 100 to 400 s is that from 10 to 100 s within a factor
    // of 2 (a superlinear stage would break it), and 4x the input costs 2x
    // to 8x the memory.
    for r in &rows {
        assert!(r.batch_peak_bytes > r.input_bytes);
    }
    let slope = |x: &memory::Row, y: &memory::Row| {
        (y.batch_peak_bytes as f64 - x.batch_peak_bytes as f64) / (y.seconds - x.seconds)
    };
    let (s1, s2) = (slope(a, b), slope(b, c));
    assert!(
        s1 > 0.0 && (0.5..=2.0).contains(&(s2 / s1)),
        "batch grows {:.0} B/s from 10 to 100 s, {:.0} B/s from 100 to 400 s",
        s1,
        s2
    );
    let ratio = c.batch_peak_bytes as f64 / b.batch_peak_bytes as f64;
    assert!((2.0..=8.0).contains(&ratio), "x{ratio:.2} for x4 input");
    eprintln!(
        "batch {:.0} B per input second; streaming {:.3} MiB at every length",
        s2,
        c.stream_peak_bytes as f64 / MIB
    );
    // Both paths still answer on the long inputs.
    assert!(b.batch_angle_deg.is_some() && c.stream_angle_deg.is_some());
}
