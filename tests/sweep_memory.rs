//! A sweep whose points share their front end (a WSS key swept, so every
//! point simulates, filters and encodes the same trials) holds about one
//! run's memory, not a signal stage's output for every trial: the shared
//! chain runs trial by trial under the sweep cache, and the cache keeps the
//! spike images the later points read. Its own test binary, so the counting
//! allocator (`benches/common/memory.rs`) sees nothing else.

#[path = "../benches/common/memory.rs"]
mod memory;

use memory::{root, with_peak, Counting, MIB};
use palpate_core as core;
use palpate_core::{LoadOptions, RunOptions};

#[global_allocator]
static ALLOC: Counting = Counting;

const SWEEP: &str = r#"
[sweep]
key = "stages.wss.weighting"
values = ["one_minus_sr", "constant"]
metrics = ["wss.mae_deg"]
"#;

#[test]
fn a_sweep_sharing_its_front_end_holds_about_one_runs_memory() {
    palpate::link();
    let dir = std::env::temp_dir().join(format!("palpate-sweep-memory-{}", std::process::id()));
    // The quickstart on 24 lab trials (debug numerics are slow).
    let path = root().join("graphs/quickstart.toml");
    let quickstart = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let angles = toml::Value::Array([45, 60, 75, 90].map(toml::Value::Integer).to_vec());
    let load_opts = LoadOptions {
        out: Some(dir.clone()),
        base_dir: Some(root().join("graphs")),
        overrides: vec![
            ("stages.scene.angles".into(), angles),
            ("stages.scene.trials_per_angle".into(), toml::Value::Integer(6)),
        ],
    };
    let single = core::load_str(&quickstart, "quickstart.toml", "quickstart", &load_opts)
        .unwrap_or_else(|e| panic!("{e}"));
    // One run alone, keeping every output (to size a trial's signals).
    let kept = core::run(
        &single,
        &RunOptions {
            keep_outputs: true,
            ..RunOptions::default()
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let bytes = |id: &str| -> Vec<usize> {
        kept.outputs[id]
            .iter()
            .map(|it| it.payload.approx_bytes())
            .collect()
    };
    let signals = bytes("filter");
    let images: usize = bytes("bins").iter().sum();
    let trials = signals.len();
    let signal_total: usize = signals.iter().sum();
    drop(kept);

    let (_, alone) =
        with_peak(|| core::run(&single, &RunOptions::default()).unwrap_or_else(|e| panic!("{e}")));
    let text = format!("{quickstart}{SWEEP}");
    let g =
        core::load_str(&text, "quickstart.toml", "quickstart", &load_opts).unwrap_or_else(|e| panic!("{e}"));
    let cache = core::Cache::default();
    let opts = RunOptions {
        cache: Some(&cache),
        ..RunOptions::default()
    };
    let (runs, swept) = with_peak(|| {
        core::sweep::run_text(&text, "quickstart.toml", "quickstart", &load_opts, &g, &opts)
            .unwrap_or_else(|e| panic!("{e}"))
    });
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(runs.len(), 2);
    // The second point computed no signal stage (served from the cache).
    for t in &runs[1].result.timings {
        if ["scene", "filter", "norm", "drive", "enc", "bins"].contains(&t.id.as_str()) {
            assert!(t.cached, "stage `{}` ran again at the second point", t.id);
        }
    }
    let mib = |b: usize| b as f64 / MIB;
    let one_mib = MIB as usize;
    eprintln!(
        "{trials} trials: one run alone peaked at {:.1} MiB, the two-point sweep at {:.1} MiB; \
         one stage's signals for every trial {:.1} MiB, the images {:.1} MiB",
        mib(alone),
        mib(swept),
        mib(signal_total),
        mib(images)
    );
    // The sweep may add what its cache keeps (the images) and a block of
    // computed trials in flight; stage-at-a-time held two signal stages
    // for every trial, which this bound excludes.
    let bound = alone + images + 8 * one_mib;
    assert!(
        2 * signal_total > bound,
        "the test is too small to tell: {} MiB of signals",
        mib(signal_total)
    );
    assert!(
        swept <= bound,
        "the sweep peaked at {:.1} MiB, one run at {:.1} MiB (+ {:.1} MiB of images)",
        mib(swept),
        mib(alone),
        mib(images)
    );
}
