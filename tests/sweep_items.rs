//! A sweep's cache reuses trials one at a time: a sweep that shifts one
//! condition of a two-condition scene simulates and encodes the other
//! condition's trials once, and every result is the bits of running each
//! point alone.

use palpate_core as core;
use palpate_core::{LoadOptions, Progress, RunOptions};
use std::sync::Mutex;

const GRAPH: &str = r#"
[run]
seed = 7
protocol = { train_test = { key = "condition", train = ["train"] } }

[stages.scene]
type = "scene"
file = "graphs/scenes/lab.toml"
angles = [30, 60]
trials_per_angle = 2

[stages.scene.conditions.train]
[stages.scene.conditions.test]

[stages.filter]
type = "lowpass"
inputs = ["scene"]
cutoff_hz = 10.0

[stages.norm]
type = "normalize"
inputs = ["filter"]

[stages.drive]
type = "drive"
inputs = ["norm"]
gain = 30.0

[stages.enc]
type = "izhikevich"
inputs = ["drive"]

[stages.bins]
type = "bin"
inputs = ["enc"]

[stages.knn]
type = "knn"
inputs = ["bins"]

# Model-based: scored on the `test` trials only, as the trained `knn` is,
# whether the chain runs alone or under the sweep's cache.
[stages.wss]
type = "wss"
inputs = ["bins"]
angles = { from = 30, to = 60, step = 30 }

[stages.mae]
type = "mae"
inputs = ["knn", "wss"]

[sweep]
# The normal force: a shift the trials' metadata (crossing times) does not
# show, so only the scene's fingerprint tells the points' `test` trials apart.
key = "stages.scene.conditions.test.motion.force_rel"
values = [1.0, 1.3]
"#;

/// Records how many trials each stage starts, run by run.
#[derive(Default)]
struct Starts(Mutex<Vec<(String, usize)>>);

impl Progress for Starts {
    fn start(&self, stage: &str, total: usize) {
        if let Ok(mut v) = self.0.lock() {
            v.push((stage.to_string(), total));
        }
    }
    fn tick(&self) {}
    fn finish(&self, _stage: &str) {}
}

fn sweep(out: &std::path::Path, keep_outputs: bool, progress: &Starts) -> Vec<core::sweep::SweepRun> {
    palpate::link();
    let opts = LoadOptions {
        out: Some(out.to_path_buf()),
        ..Default::default()
    };
    let g = core::load_str(GRAPH, "items.toml", "items", &opts).unwrap_or_else(|e| panic!("{e}"));
    let cache = core::Cache::default();
    let run_opts = RunOptions {
        cache: Some(&cache),
        keep_outputs,
        progress: Some(progress),
    };
    core::sweep::run_text(GRAPH, "items.toml", "items", &opts, &g, &run_opts)
        .unwrap_or_else(|e| panic!("{e}"))
}

fn out_dir(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("palpate-sweep-items-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

#[test]
fn shifting_one_condition_recomputes_only_its_trials() {
    let starts = Starts::default();
    let out = out_dir("counts");
    let runs = sweep(&out, false, &starts);
    assert_eq!(runs.len(), 2);
    let starts = starts.0.into_inner().unwrap();
    // The signal chain runs trial by trial and counts the trials any of its
    // stages computes. Point 1: both conditions (2 angles x 2 trials each);
    // point 2: the shifted `test` condition alone (a `train` trial computed
    // by any stage would need its scene trial, and count).
    let counts: Vec<(&str, usize)> = starts
        .iter()
        .filter(|(s, _)| s.starts_with("scene"))
        .map(|(s, n)| (s.as_str(), *n))
        .collect();
    assert_eq!(counts, [("scene .. bins", 8), ("scene .. bins", 4)]);
    // The second point's scene is computed, not served: it reports a run's
    // own times (not `cached`), one per trial.
    let scene = runs[1].result.timings.iter().find(|t| t.id == "scene").unwrap();
    assert!(!scene.cached && scene.per_trial.len() == 8);
    // The reports are those of each point run alone, without a cache.
    for r in &runs {
        let alone = core::run(&r.graph, &RunOptions::default()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(alone.reports, r.result.reports, "{}", r.label);
    }
    let mae = |k: usize| runs[k].result.reports[0].1.metrics.clone();
    assert_ne!(mae(0), mae(1), "the shift changes the test trials' estimates");
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn trials_served_from_the_cache_are_the_bits_of_running_each_point_alone() {
    let out = out_dir("bits");
    let runs = sweep(&out, true, &Starts::default());
    for r in &runs {
        let alone = core::run(
            &r.graph,
            &RunOptions {
                keep_outputs: true,
                ..Default::default()
            },
        )
        .unwrap_or_else(|e| panic!("{e}"));
        for id in ["scene", "filter", "enc", "bins", "knn", "wss"] {
            let (a, b) = (&alone.outputs[id], &r.result.outputs[id]);
            assert_eq!(a.len(), b.len(), "{id} at {}", r.label);
            for (x, y) in a.iter().zip(b.iter()) {
                assert_eq!(
                    x.content_key(),
                    y.content_key(),
                    "{id} {} at {}",
                    x.meta.trial_id,
                    r.label
                );
                // Metadata and provenance are this point's, not those of the
                // point that computed the payload.
                assert_eq!(x.meta, y.meta, "{id} {} at {}", x.meta.trial_id, r.label);
            }
        }
        assert_eq!(alone.reports, r.result.reports, "{}", r.label);
        // Under train/test, WSS estimates the 4 `test` trials and no
        // `train` one, in either path (alone, the depth-first chain once
        // estimated all 8 and scored WSS on the training trials too).
        let ids = |o: &core::RunResult| -> Vec<String> {
            o.outputs["wss"].iter().map(|i| i.meta.trial_id.clone()).collect()
        };
        assert_eq!(ids(&alone), ids(&r.result), "{}", r.label);
        assert_eq!(ids(&alone).len(), 4, "{}", r.label);
        assert!(ids(&alone).iter().all(|t| t.starts_with("test-")), "{}", r.label);
        // Their timings hold the 4 estimates, not 8 entries padded with
        // zeros (which made the median and the estimates per second wrong).
        for o in [&alone, &r.result] {
            for id in ["wss", "knn"] {
                let t = o.timings.iter().find(|t| t.id == id).unwrap();
                assert_eq!(t.per_trial.len(), 4, "{id} at {}", r.label);
            }
        }
    }
    // The shifted condition differs between the points; the other does not.
    let scene = |k: usize, t: &str| {
        runs[k].result.outputs["scene"]
            .iter()
            .find(|i| i.meta.trial_id == t)
            .map(|i| i.content_key())
            .unwrap()
    };
    assert_eq!(scene(0, "train-edge-30deg-r00"), scene(1, "train-edge-30deg-r00"));
    assert_ne!(scene(0, "test-edge-30deg-r00"), scene(1, "test-edge-30deg-r00"));
    let _ = std::fs::remove_dir_all(&out);
}

/// A progress receiver that asks the run to stop after `after` ticks.
struct StopAfter {
    ticks: std::sync::atomic::AtomicUsize,
    after: usize,
}

impl Progress for StopAfter {
    fn start(&self, _stage: &str, _total: usize) {}
    fn tick(&self) {
        self.ticks.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
    }
    fn finish(&self, _stage: &str) {}
    fn cancelled(&self) -> bool {
        self.ticks.load(std::sync::atomic::Ordering::SeqCst) >= self.after
    }
}

/// A cancelled run (Python's Ctrl-C) stops with an `interrupted` error, in
/// the depth-first chain and in a sweep's cached runs, before
/// doing all its work; a receiver that never cancels changes nothing.
#[test]
fn a_cancelled_run_stops_with_an_interrupted_error() {
    palpate::link();
    let out = out_dir("cancel");
    let opts = LoadOptions {
        out: Some(out.clone()),
        ..Default::default()
    };
    let g = core::load_str(GRAPH, "items.toml", "items", &opts).unwrap_or_else(|e| panic!("{e}"));
    // The graph without its sweep: one run, depth-first.
    let plain = GRAPH.split("[sweep]").next().unwrap_or(GRAPH);
    let point = core::load_str(plain, "items.toml", "items", &opts).unwrap_or_else(|e| panic!("{e}"));
    for after in [0, 3] {
        let stop = StopAfter {
            ticks: Default::default(),
            after,
        };
        let e = core::run(
            &point,
            &RunOptions {
                progress: Some(&stop),
                ..Default::default()
            },
        )
        .expect_err("the run stops");
        assert_eq!(e.message, core::INTERRUPTED, "{e}");
        // 8 trials through 6 per-trial stages, 2 estimators and a sink: far
        // fewer ticks before the stop took.
        assert!(stop.ticks.into_inner() < 8, "after {after}");
        let cache = core::Cache::default();
        let stop = StopAfter {
            ticks: Default::default(),
            after,
        };
        let run_opts = RunOptions {
            cache: Some(&cache),
            keep_outputs: false,
            progress: Some(&stop),
        };
        let e = core::sweep::run_text(GRAPH, "items.toml", "items", &opts, &g, &run_opts)
            .expect_err("the sweep stops");
        assert!(e.to_string().contains(core::INTERRUPTED), "{e}");
    }
    let never = StopAfter {
        ticks: Default::default(),
        after: usize::MAX,
    };
    let a = core::run(
        &point,
        &RunOptions {
            progress: Some(&never),
            ..Default::default()
        },
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let b = core::run(&point, &RunOptions::default()).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(a.reports, b.reports);
    let _ = std::fs::remove_dir_all(&out);
}
