//! Sweeps with several series: the union of their points, labels and report
//! directories, a series' constant overrides, errors naming the series, the
//! single-key form unchanged, and cached stages keeping their timing.

mod common;
use common::{load, SERIAL};
use palpate_core::sweep::{run_text, summarize, SweepRun};
use palpate_core::{Cache, LoadOptions, RunOptions};

const BASE: &str = r#"
[stages.src]
type = "t_source"
classes = 2
reps = 2
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
"#;

fn with_sweep(sweep: &str) -> String {
    format!("{BASE}\n{sweep}")
}

fn run_all(text: &str, cache: &Cache) -> Vec<SweepRun> {
    let g = load(text).unwrap_or_else(|e| panic!("{e}"));
    let opts = RunOptions {
        cache: Some(cache),
        ..Default::default()
    };
    let load_opts = LoadOptions {
        out: Some(g.out_dir.clone()),
        ..Default::default()
    };
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    run_text(text, "t.toml", "t", &load_opts, &g, &opts).unwrap_or_else(|e| panic!("{e}"))
}

/// The first number under `key` anywhere in a JSON value.
fn find(v: &serde_json::Value, key: &str) -> Option<f64> {
    match v {
        serde_json::Value::Object(o) => o
            .get(key)
            .and_then(|x| x.as_f64())
            .or_else(|| o.values().find_map(|x| find(x, key))),
        _ => None,
    }
}

fn load_error(text: &str) -> String {
    match load(text) {
        Err(e) => e.to_string(),
        Ok(g) => run_text(text, "t.toml", "t", &Default::default(), &g, &Default::default())
            .map(|_| String::new())
            .unwrap_or_else(|e| e.to_string()),
    }
}

#[test]
fn a_series_sweep_is_the_union_of_its_series() {
    let text = with_sweep(
        r#"
[sweep]
[[sweep.series]]
name = "scale_b"
key = "stages.b.factor"
values = [1.0, 3.0]

[[sweep.series]]
name = "len"
key = "stages.src.samples"
values = [10, 30, 40]
"#,
    );
    let g = load(&text).unwrap();
    let sweep = g.sweep.clone().unwrap();
    assert_eq!(sweep.points().len(), 5);
    let cache = Cache::default();
    let runs = run_all(&text, &cache);
    let labels: Vec<&str> = runs.iter().map(|r| r.label.as_str()).collect();
    assert_eq!(
        labels,
        ["scale_b/1.0", "scale_b/3.0", "len/10", "len/30", "len/40"]
    );
    let series: Vec<Option<&str>> = runs.iter().map(|r| r.series.as_deref()).collect();
    assert_eq!(series[0], Some("scale_b"));
    assert_eq!(series[4], Some("len"));
    assert_eq!(runs[3].key, "stages.src.samples");
    assert_eq!(runs[3].value, toml::Value::Integer(30));
    // Each point changes one key from the base: the other keeps its base value.
    let factor = |r: &SweepRun, id: &str| {
        let n = r.graph.nodes.iter().find(|n| n.id == id).unwrap();
        find(&serde_json::to_value(&n.config).unwrap(), "factor")
    };
    assert_eq!(factor(&runs[1], "b"), Some(3.0));
    assert_eq!(
        factor(&runs[3], "b"),
        Some(2.0),
        "len points keep b at its base factor"
    );
    // Report directories: <out>/<series>/<value>/.
    assert_eq!(runs[1].graph.out_dir, g.out_dir.join("scale_b").join("3.0"));
    assert_eq!(runs[4].graph.out_dir, g.out_dir.join("len").join("40"));
    let rows = summarize(&runs, &[]);
    assert_eq!(rows.len(), 5);
    assert_eq!(rows[2].series.as_deref(), Some("len"));
    assert_eq!(rows[2].x, Some(10.0));
    assert_eq!(sweep.describe(), "series scale_b, len");
    let lbl = |t: &str| palpate_core::sweep::label(&toml::from_str::<toml::Table>(t).unwrap()["v"]);
    assert_eq!(lbl("v = [60, 30]"), "60-30");
    assert_eq!(lbl("v = { from = 1.0, step = 0.5 }"), "from=1.0,step=0.5");
    assert_eq!(lbl("v = \"a b/c\""), "a_b_c");
}

#[test]
fn a_series_set_rewires_only_its_points() {
    let text = with_sweep(
        r#"
[sweep]
[[sweep.series]]
name = "skip_b"
key = "stages.a.factor"
values = [4.0]
set = { "stages.est.inputs" = ["a"] }

[[sweep.series]]
name = "plain"
key = "stages.a.factor"
values = [4.0]
"#,
    );
    let cache = Cache::default();
    let runs = run_all(&text, &cache);
    let est_inputs = |r: &SweepRun| {
        r.graph
            .nodes
            .iter()
            .find(|n| n.id == "est")
            .unwrap()
            .inputs
            .clone()
    };
    assert_eq!(est_inputs(&runs[0]), ["a"]);
    assert_eq!(est_inputs(&runs[1]), ["b"]);
}

#[test]
fn errors_name_the_series() {
    let bad_key = load_error(&with_sweep(
        r#"
[sweep]
[[sweep.series]]
name = "ok"
key = "stages.b.factor"
values = [1.0]

[[sweep.series]]
name = "wrong"
key = "stages.nope.factor"
values = [1.0]
"#,
    ));
    assert!(
        bad_key.contains("series `wrong`") && bad_key.contains("stages.nope.factor"),
        "{bad_key}"
    );
    assert!(!bad_key.contains("series `ok`"), "{bad_key}");

    let bad_value = load_error(&with_sweep(
        r#"
[sweep]
[[sweep.series]]
name = "len"
key = "stages.src.samples"
values = [10, 0]
"#,
    ));
    assert!(
        bad_value.contains("in sweep series `len`, with stages.src.samples = 0")
            && bad_value.contains("key `samples`"),
        "{bad_value}"
    );

    let both = load_error(&with_sweep(
        r#"
[sweep]
key = "stages.b.factor"
values = [1.0]
[[sweep.series]]
name = "x"
key = "stages.b.factor"
values = [1.0]
"#,
    ));
    assert!(both.contains("not both"), "{both}");

    let twice = load_error(&with_sweep(
        r#"
[sweep]
[[sweep.series]]
name = "x"
key = "stages.b.factor"
values = [1.0]
[[sweep.series]]
name = "x"
key = "stages.a.factor"
values = [1.0]
"#,
    ));
    assert!(twice.contains("two series share this name"), "{twice}");

    let bad_name = load_error(&with_sweep(
        r#"
[sweep]
[[sweep.series]]
name = "a/b"
key = "stages.b.factor"
values = [1.0]
"#,
    ));
    assert!(bad_name.contains("series `a/b`: `name`"), "{bad_name}");

    let bad_set = load_error(&with_sweep(
        r#"
[sweep]
[[sweep.series]]
name = "s"
key = "stages.b.factor"
values = [1.0]
set = { "stages.ghost.inputs" = ["a"] }
"#,
    ));
    assert!(
        bad_set.contains("series `s`: `set` key") && bad_set.contains("stages.ghost.inputs"),
        "{bad_set}"
    );

    // A value listed twice would be two points in one folder.
    let twice = load_error(&with_sweep(
        "[sweep]\nkey = \"stages.b.factor\"\nvalues = [1.0, 0.7, 1.0]\n",
    ));
    assert!(twice.contains("`values` lists 1.0 twice"), "{twice}");
    let twice = load_error(&with_sweep(
        "[sweep]\n[[sweep.series]]\nname = \"s\"\nkey = \"stages.b.factor\"\nvalues = [2.0, 2.0]\n",
    ));
    assert!(twice.contains("series `s`: `values` lists 2.0 twice"), "{twice}");
    // An integer and a float of one value: two folders, one setting run twice.
    let twice = load_error(&with_sweep(
        "[sweep]\nkey = \"stages.b.factor\"\nvalues = [2, 1.5, 2.0]\n",
    ));
    assert!(twice.contains("`values` lists 2 and 2.0, one number"), "{twice}");

    let no_values = load_error(&with_sweep("[sweep]\nkey = \"stages.b.factor\"\nrepeats = 2\n"));
    assert!(no_values.contains("`values` lists no value"), "{no_values}");

    let frontier = load_error(&with_sweep(
        "[sweep]\nkey = \"stages.b.factor\"\nvalues = [1.0]\nfrontier = [\"ghost\"]\n",
    ));
    assert!(frontier.contains("`frontier` names `ghost`"), "{frontier}");
}

#[test]
fn the_single_key_form_is_unchanged() {
    let text = with_sweep(
        r#"
[sweep]
key = "stages.b.factor"
values = [1.0, 5.0]
repeats = 2
"#,
    );
    let g = load(&text).unwrap();
    let cache = Cache::default();
    let runs = run_all(&text, &cache);
    let labels: Vec<&str> = runs.iter().map(|r| r.label.as_str()).collect();
    assert_eq!(labels, ["1.0", "1.0", "5.0", "5.0"]);
    assert!(runs
        .iter()
        .all(|r| r.series.is_none() && r.key == "stages.b.factor"));
    assert_eq!(runs[3].graph.out_dir, g.out_dir.join("5.0").join("r1"));
    let sweep = g.sweep.unwrap();
    assert_eq!(sweep.describe(), "stages.b.factor");
    assert_eq!(sweep.points().len(), 2);
    assert!(sweep
        .points()
        .iter()
        .all(|p| p.series.is_none() && p.set.is_empty()));
}

#[test]
fn a_cached_stage_reports_the_timing_of_the_run_that_computed_it() {
    let text = with_sweep(
        r#"
[sweep]
[[sweep.series]]
name = "b"
key = "stages.b.factor"
values = [1.0, 3.0]
"#,
    );
    let cache = Cache::default();
    let runs = run_all(&text, &cache);
    let timing = |r: &SweepRun, id: &str| r.result.timings.iter().find(|t| t.id == id).cloned().unwrap();
    for id in ["src", "a"] {
        let first = timing(&runs[0], id);
        let second = timing(&runs[1], id);
        assert!(!first.cached && second.cached, "{id}");
        assert_eq!(first.per_trial.len(), 4, "{id}");
        // The very durations measured at the first point, not zeros.
        assert_eq!(second.per_trial, first.per_trial, "{id}");
        assert_eq!(second.total, first.total, "{id}");
        assert_eq!(second.role, first.role);
    }
    let b = timing(&runs[1], "b");
    assert!(!b.cached && b.per_trial.len() == 4);
    // A trained estimator's fits are carried too (one per group).
    let text = with_sweep(
        r#"
[sweep]
[[sweep.series]]
name = "once"
key = "stages.b.factor"
values = [2.0]
[[sweep.series]]
name = "again"
key = "stages.b.factor"
values = [2.0]
"#,
    );
    let runs = run_all(&text, &Cache::default());
    let (e0, e1) = (timing(&runs[0], "est"), timing(&runs[1], "est"));
    assert!(e1.cached);
    assert_eq!(e1.fits, e0.fits);
    assert!(!e0.fits.is_empty());
}

/// A sweep of `repeats` alone is the base graph at consecutive seeds, and
/// `--set sweep.<key>` makes one for a graph without a sweep or changes a
/// graph's own (a paper graph's five seeds cut to one to try it).
#[test]
fn repeats_alone_run_the_base_graph_at_consecutive_seeds() {
    let text = format!("[run]\nseed = 7\n{BASE}\n[sweep]\nrepeats = 3\n");
    let runs = run_all(&text, &Cache::default());
    let seeds: Vec<u64> = runs.iter().map(|r| r.seed).collect();
    assert_eq!(seeds, [7, 8, 9]);
    assert!(runs.iter().all(|r| r.key == "run.seed" && r.point == 0));

    let set = |text: &str, sets: &[&str]| {
        let opts = LoadOptions {
            overrides: sets.iter().map(|s| LoadOptions::parse_set(s).unwrap()).collect(),
            ..Default::default()
        };
        palpate_core::load_str(text, "t.toml", "t", &opts)
    };
    // No [sweep] in the graph: the override makes one.
    let g = set(BASE, &["sweep.repeats=4", "run.seed=2"]).unwrap_or_else(|e| panic!("{e}"));
    let s = g.sweep.expect("a sweep");
    assert_eq!((s.repeats, s.key.as_str()), (4, "run.seed"));
    assert_eq!(s.values, [toml::Value::Integer(2)]);
    // A graph's own sweep: its repeats change, its points stay.
    let own = with_sweep("[sweep]\nkey = \"stages.b.factor\"\nvalues = [1.0, 0.5]\nrepeats = 5\n");
    let s = set(&own, &["sweep.repeats=1"]).unwrap().sweep.expect("a sweep");
    assert_eq!((s.repeats, s.points().len()), (1, 2));
    // A key the sweep does not have is an error naming it.
    let e = set(&own, &["sweep.repeets=1"]).unwrap_err().to_string();
    assert!(e.contains("repeets"), "{e}");
    // Other top-level paths still name the three forms.
    let e = set(BASE, &["swept.repeats=1"]).unwrap_err().to_string();
    assert!(e.contains("sweep.<key>"), "{e}");
}
