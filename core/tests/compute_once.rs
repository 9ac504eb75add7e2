//! An output read by several stages is computed once.

mod common;
use common::{load, ORDER, SCALE_CALLS, SERIAL};
use std::sync::atomic::Ordering;

/// Runs the sweep of graph `text` under `cache`.
fn sweep_runs(text: &str, cache: &palpate_core::Cache) -> Vec<palpate_core::sweep::SweepRun> {
    let g = load(text).unwrap();
    let load_opts = palpate_core::LoadOptions {
        out: Some(g.out_dir.clone()),
        ..Default::default()
    };
    let opts = palpate_core::RunOptions {
        cache: Some(cache),
        ..Default::default()
    };
    palpate_core::sweep::run_text(text, "t.toml", "t", &load_opts, &g, &opts).unwrap()
}

#[test]
fn a_shared_output_is_computed_once() {
    let text = r#"
[stages.src]
type = "t_source"
classes = 2
reps = 3
samples = 20

[stages.scale]
type = "t_scale"
inputs = ["src"]

[stages.est]
type = "t_estimator"
inputs = ["scale"]

[stages.est2]
type = "t_estimator"
inputs = ["scale"]

[stages.sink]
type = "t_sink"
inputs = ["est", "est2"]
"#;
    let g = load(text).unwrap();
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    SCALE_CALLS.store(0, Ordering::SeqCst);
    let r = palpate_core::run(&g, &Default::default()).unwrap();
    assert_eq!(
        SCALE_CALLS.load(Ordering::SeqCst),
        6,
        "one call per trial, not per reader"
    );
    assert_eq!(r.reports[0].1.metrics.len(), 2);
}

#[test]
fn a_sweep_over_a_downstream_key_does_not_rerun_upstream_stages() {
    let text = r#"
[stages.src]
type = "t_source"
classes = 2
reps = 3
samples = 20

[stages.a]
type = "t_scale"
inputs = ["src"]

[stages.b]
type = "t_scale"
inputs = ["a"]

[stages.est]
type = "t_estimator"
inputs = ["b"]

[stages.sink]
type = "t_sink"
inputs = ["est"]

[sweep]
key = "stages.b.factor"
values = [1.0, 2.0, 3.0]
"#;
    let g = load(text).unwrap();
    let sweep = g.sweep.clone().unwrap();
    assert_eq!(sweep.values.len(), 3);
    let cache = palpate_core::Cache::default();
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    SCALE_CALLS.store(0, Ordering::SeqCst);
    let runs = sweep_runs(text, &cache);
    assert_eq!(runs.len(), 3);
    // `a` runs for the first point only (6 trials); `b` for every point (3 x 6).
    assert_eq!(SCALE_CALLS.load(Ordering::SeqCst), 6 + 18);
    // `a` hits the cache at points 2 and 3; `src`, read only by `a`, is
    // neither recomputed nor fetched there.
    assert_eq!(cache.hits(), 2);
    let cached: Vec<bool> = runs[1].result.timings.iter().map(|t| t.cached).collect();
    assert_eq!(cached, [true, true, false, false, false]);
    let rows = palpate_core::sweep::summarize(&runs, &[]);
    assert_eq!(rows.len(), 3);
    assert_eq!(rows[0].x, Some(1.0));
    assert_eq!(rows[0].metrics[0].0, "est.n");
    let table = palpate_core::sweep::render(&sweep.key, &rows);
    assert!(
        table.contains("stages.b.factor") && table.lines().count() == 4,
        "{table}"
    );
}

#[test]
fn a_bad_sweep_value_is_a_load_error_naming_the_value() {
    let text = r#"
[stages.src]
type = "t_source"
samples = 20

[stages.est]
type = "t_estimator"
inputs = ["src"]

[stages.sink]
type = "t_sink"
inputs = ["est"]

[sweep]
key = "stages.src.samples"
values = [10, 0]
"#;
    let g = load(text).unwrap();
    let e = palpate_core::sweep::run_text(text, "t.toml", "t", &Default::default(), &g, &Default::default())
        .unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("with sweep value stages.src.samples = 0") && msg.contains("key `samples`"),
        "{msg}"
    );
}

#[test]
fn a_sweep_over_the_seed_uses_each_value() {
    let text = r#"
[run]
seed = 1

[stages.src]
type = "t_source"
samples = 20

[stages.est]
type = "t_estimator"
inputs = ["src"]

[stages.sink]
type = "t_sink"
inputs = ["est"]

[sweep]
key = "run.seed"
values = [5, 9]
repeats = 2
"#;
    let g = load(text).unwrap();
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let runs =
        palpate_core::sweep::run_text(text, "t.toml", "t", &Default::default(), &g, &Default::default())
            .unwrap();
    let seeds: Vec<u64> = runs.iter().map(|r| r.seed).collect();
    assert_eq!(seeds, [5, 6, 9, 10]);
}

#[test]
fn a_cached_downstream_output_spares_upstream_stages_that_no_longer_fit() {
    // A budget that holds two of the chain's four signal outputs: plain
    // least-recently-used eviction, with every stage run in order, re-ran the
    // whole chain at every point (the source was gone, and recomputing it
    // evicted the rest); the plan runs only what reads a missing output.
    let text = r#"
[stages.src]
type = "t_source"
classes = 2
reps = 3
samples = 400

[stages.a]
type = "t_scale"
inputs = ["src"]

[stages.b]
type = "t_scale"
inputs = ["a"]

[stages.c]
type = "t_scale"
inputs = ["b"]

[stages.est]
type = "t_estimator"
inputs = ["c"]

[stages.sink]
type = "t_sink"
inputs = ["est"]

[sweep]
key = "stages.c.factor"
values = [1.0, 2.0, 3.0]
"#;
    let g = load(text).unwrap();
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let one = palpate_core::run(
        &g,
        &palpate_core::RunOptions {
            keep_outputs: true,
            ..Default::default()
        },
    )
    .unwrap();
    let size: usize = one.outputs["src"]
        .iter()
        .map(|it| it.payload.approx_bytes())
        .sum();
    let run_with = |budget: usize| {
        let cache = palpate_core::Cache::with_budget(budget);
        SCALE_CALLS.store(0, Ordering::SeqCst);
        let runs = sweep_runs(text, &cache);
        (runs, SCALE_CALLS.load(Ordering::SeqCst), cache.held_bytes())
    };
    let (full, calls_full, _) = run_with(palpate_core::runtime::DEFAULT_CACHE_BYTES);
    let budget = 2 * size + size / 2;
    let (tight, calls_tight, held) = run_with(budget);
    assert!(held <= budget);
    // a and b once (6 trials each), c at every point (3 x 6).
    assert_eq!(calls_full, 12 + 18);
    assert_eq!(calls_tight, 12 + 18, "the chain re-ran though `b` was cached");
    for (x, y) in full.iter().zip(&tight) {
        assert_eq!(x.result.reports[0].1.metrics, y.result.reports[0].1.metrics);
        let stages: Vec<&str> = y.result.timings.iter().map(|t| t.id.as_str()).collect();
        assert_eq!(
            stages,
            ["src", "a", "b", "c", "est", "sink"],
            "every stage reports a timing"
        );
    }
}

#[test]
fn a_sweep_reuses_a_model_fitted_on_unchanged_training_items() {
    // `a`'s note changes its settings, not its output: the estimator's input
    // key changes at every point, its training items do not.
    let text = r#"
[stages.src]
type = "t_source"
classes = 2
reps = 3
samples = 20

[stages.a]
type = "t_scale"
inputs = ["src"]

[stages.est]
type = "t_estimator"
inputs = ["a"]

[stages.sink]
type = "t_sink"
inputs = ["est"]

[sweep]
key = "stages.a.note"
values = ["x", "y", "z"]
"#;
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let fits = |text: &str| {
        common::TRAINED_ON
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clear();
        let runs = sweep_runs(text, &palpate_core::Cache::default());
        let n = common::TRAINED_ON.lock().unwrap_or_else(|e| e.into_inner()).len();
        (runs, n)
    };
    let (runs, n) = fits(text);
    // 3 folds (one per repetition), fitted at the first point only.
    assert_eq!(n, 3);
    let m0 = &runs[0].result.reports[0].1.metrics;
    assert!(runs.iter().all(|r| &r.result.reports[0].1.metrics == m0));
    assert!(runs[2]
        .result
        .timings
        .iter()
        .any(|t| t.id == "est" && t.fits.len() == 3));
    // Changing the items (a factor) fits again at every point.
    let scaled = text.replace(
        r#"key = "stages.a.note"
values = ["x", "y", "z"]"#,
        "key = \"stages.a.factor\"\nvalues = [1.0, 2.0, 3.0]",
    );
    let (_, n) = fits(&scaled);
    assert_eq!(n, 9);
    // A fit with effects (a saved model file per point) runs at every point,
    // and its stage is not served from the cache either.
    let effects = text.replace("type = \"t_estimator\"", "type = \"t_estimator\"\neffects = true");
    let (_, n) = fits(&effects);
    assert_eq!(n, 9);
    // Three points that set the same value (three series: one series may
    // not list a value twice).
    let unchanged = effects.replace(
        "key = \"stages.a.note\"\nvalues = [\"x\", \"y\", \"z\"]",
        &["p", "q", "r"]
            .map(|s| format!("[[sweep.series]]\nname = \"{s}\"\nkey = \"stages.a.note\"\nvalues = [\"x\"]\n"))
            .concat(),
    );
    assert_ne!(unchanged, effects);
    let (_, n) = fits(&unchanged);
    assert_eq!(
        n, 9,
        "an estimator with effects is fitted at every point, even an identical one"
    );
}

/// The order in which one thread ran the two `t_scale` stages of `text`'s
/// sweep under a cache: `(note, trial)` per call.
fn scale_order(text: &str) -> Vec<(String, String)> {
    let cache = palpate_core::Cache::default();
    ORDER.lock().unwrap_or_else(|e| e.into_inner()).clear();
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    pool.install(|| sweep_runs(text, &cache));
    std::mem::take(&mut *ORDER.lock().unwrap_or_else(|e| e.into_inner()))
}

#[test]
fn a_chain_no_other_run_shares_runs_depth_first_under_a_sweep_cache() {
    let graph = |sweep: &str| {
        format!(
            r#"
[stages.src]
type = "t_source"
classes = 2
reps = 2
samples = 20

[stages.a]
type = "t_scale"
inputs = ["src"]
note = "order-a"

[stages.b]
type = "t_scale"
inputs = ["a"]
note = "order-b"

[stages.est]
type = "t_estimator"
inputs = ["b"]

[stages.sink]
type = "t_sink"
inputs = ["est"]

[sweep]
{sweep}
"#
        )
    };
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    // Seeds: every run simulates its own trials and nothing is shared, so
    // each trial goes through `a` and `b` before the next starts (peak
    // memory: one trial's chain, not a stage's output for every trial).
    let order = scale_order(&graph("key = \"run.seed\"\nvalues = [1, 2]"));
    assert_eq!(order.len(), 2 * 2 * 4, "{order:?}");
    for run in order.chunks(8) {
        for pair in run.chunks(2) {
            assert_eq!(pair[0].0, "order-a", "{order:?}");
            assert_eq!(pair[1].0, "order-b", "{order:?}");
            assert_eq!(pair[0].1, pair[1].1, "the same trial: {order:?}");
        }
    }
    // A downstream key: `a`'s trials are kept for the later points, and the
    // first point still runs trial by trial (each trial through `a` and `b`
    // before the next: a shared chain holds one trial's signals, not a
    // stage's output for every trial); the later ones serve `a` from the
    // cache and run `b` alone.
    let order = scale_order(&graph("key = \"stages.b.factor\"\nvalues = [1.0, 3.0]"));
    let trials = ["c0-r0", "c0-r1", "c1-r0", "c1-r1"];
    let mut expected: Vec<(String, String)> = Vec::new();
    for t in trials {
        expected.push(("order-a".into(), t.into()));
        expected.push(("order-b".into(), t.into()));
    }
    for t in trials {
        expected.push(("order-b".into(), t.into()));
    }
    assert_eq!(order, expected);
}
