//! Memory against input length: the batch pipeline (graphs/quickstart.toml's
//! chain from signals to a WSS estimate) and the streaming path
//! (graphs/live.toml's streaming plan, fed one sample frame at a time, as
//! the `daq` source does under `palpate run --live`) on 10, 100 and 1000 s of 16-taxel 1 kHz input
//! (the lab scene's 45-degree palpations back to back; see
//! `benches/common/memory.rs` for the input and what is counted).
//!
//! Target: batch memory linear in the input's length, streaming
//! memory constant. Peaks are counted by a `#[global_allocator]` that wraps
//! `System` and tracks live heap bytes, so they are exact and repeatable.
//!
//! Run: `cargo bench --bench memory` (release; ~1 min). Options:
//! `--seconds 10,100,1000` (lengths), `--trials 10` (distinct palpations
//! cycled), `--json PATH` (default `<target dir>/palpate-memory.json`).
//! Prints a Markdown table and writes the rows as JSON.

#[path = "common/memory.rs"]
mod memory;

use memory::{lab_trials, live_graph, measure, quickstart, stage_table, table, Counting, MIB};

#[global_allocator]
static ALLOC: Counting = Counting;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let value = |flag: &str| {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    let seconds: Vec<f64> = value("--seconds")
        .unwrap_or_else(|| "10,100,1000".into())
        .split(',')
        .map(|s| s.trim().parse().expect("--seconds: comma-separated numbers"))
        .collect();
    let n_trials: usize = value("--trials")
        .map(|s| s.parse().expect("--trials: a number"))
        .unwrap_or(10);
    let json = value("--json").map(std::path::PathBuf::from).unwrap_or_else(|| {
        // <target>/<profile>/deps/memory-<hash>: write beside the profile dirs.
        let exe = std::env::current_exe().expect("current exe");
        exe.ancestors()
            .nth(3)
            .map(|t| t.join("palpate-memory.json"))
            .unwrap_or_else(|| "palpate-memory.json".into())
    });

    let t0 = std::time::Instant::now();
    let trials = lab_trials(n_trials);
    let durations: Vec<f64> = trials
        .iter()
        .map(|t| t.payload.signals().unwrap().duration_ms() / 1000.0)
        .collect();
    eprintln!(
        "input: {} lab-scene trials at {} deg ({:.1}-{:.1} s each), cycled; simulated in {:.1} s",
        trials.len(),
        memory::ANGLE,
        durations.iter().cloned().fold(f64::INFINITY, f64::min),
        durations.iter().cloned().fold(0.0, f64::max),
        t0.elapsed().as_secs_f64()
    );
    let g = quickstart();
    let cfg = live_graph();
    let (tpl_bytes, state_bytes) = memory::stream_split(&cfg);
    eprintln!(
        "streaming, built: the plan and the first trial's state {:.3} MiB (once per graph), one more trial's state {:.3} MiB",
        tpl_bytes as f64 / MIB,
        state_bytes as f64 / MIB
    );
    let mut rows = Vec::new();
    for &s in &seconds {
        let r = measure(&g, &cfg, &trials, s);
        eprintln!(
            "{s} s: batch peak {:.2} MiB ({:.1} s), streaming peak {:.3} MiB ({:.1} s)",
            r.batch_peak_bytes as f64 / MIB,
            r.batch_wall_s,
            r.stream_peak_bytes as f64 / MIB,
            r.stream_wall_s
        );
        rows.push(r);
    }
    println!("{}", table(&rows));
    println!("Batch peak per stage (MiB, everything live while the stage ran):\n");
    println!("{}", stage_table(&rows));
    if let [a, .., b] = rows.as_slice() {
        println!(
            "batch: x{:.1} memory for x{:.0} input ({:.0} B per input second at {} s); \
             streaming: {:+.3} MiB from {} s to {} s",
            b.batch_peak_bytes as f64 / a.batch_peak_bytes as f64,
            b.seconds / a.seconds,
            b.batch_peak_bytes as f64 / b.seconds,
            b.seconds,
            (b.stream_peak_bytes as f64 - a.stream_peak_bytes as f64) / MIB,
            a.seconds,
            b.seconds
        );
    }
    let text = serde_json::to_string_pretty(&rows).expect("json");
    match std::fs::write(&json, text + "\n") {
        Ok(()) => println!("rows written to {}", json.display()),
        Err(e) => eprintln!("cannot write {}: {e}", json.display()),
    }
}
