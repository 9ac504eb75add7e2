//! The `union` source: several named sources as one, for training on one data
//! set and testing on another.

mod common;

use palpate_core::{Item, Payload};

const SCENE: &str = r#"{ type = "scene", angles = [30, 60], trials_per_angle = 2, motion = { speed_mm_s = 10.0, hold_before_s = 0.3, hold_after_s = 0.3 } }"#;

/// The test pipeline after a `data` stage whose keys are `sources` (a union
/// unless they say otherwise).
fn graph(protocol: &str, sources: &str) -> String {
    let sources = if sources.starts_with("type") {
        sources.to_string()
    } else {
        format!("type = \"union\"\n{sources}")
    };
    format!(
        r#"[run]
seed = 4
{protocol}

[stages.data]
{sources}

[stages.norm]
type = "normalize"
inputs = ["data"]

[stages.drive]
type = "drive"
inputs = ["norm"]
kind = "fa_i"

[stages.enc]
type = "izhikevich"
inputs = ["drive"]

[stages.bins]
type = "bin"
inputs = ["enc"]
window_ms = 100.0
hop_ms = 50.0

[stages.knn]
type = "knn"
inputs = ["bins"]

[stages.mae]
type = "mae"
inputs = ["knn"]
"#
    )
}

fn ids(items: &[Item]) -> Vec<String> {
    items.iter().map(|i| i.meta.trial_id.clone()).collect()
}

#[test]
fn a_union_lists_every_source_prefixed_and_labelled_and_trains_on_one_tests_on_the_other() {
    let dir = tempfile::tempdir().unwrap();
    let sources = format!("sources.sim = {SCENE}\nsources.other = {SCENE}\n");
    let r = common::run_graph_file(
        dir.path(),
        "g.toml",
        &graph(
            r#"protocol = { train_test = { key = "source", train = ["sim"] } }"#,
            &sources,
        ),
    )
    .unwrap();
    let data = &r.outputs["data"];
    // Name order: `other` before `sim`, each source's own order inside.
    assert_eq!(
        ids(data),
        [
            "other-edge-30deg-r00",
            "other-edge-30deg-r01",
            "other-edge-60deg-r00",
            "other-edge-60deg-r01",
            "sim-edge-30deg-r00",
            "sim-edge-30deg-r01",
            "sim-edge-60deg-r00",
            "sim-edge-60deg-r01",
        ]
    );
    for it in data.iter() {
        assert_eq!(
            it.meta.conditions["source"],
            it.meta.trial_id.split('-').next().unwrap()
        );
    }
    // The ideal scene draws nothing at random, so the two sources' trials
    // of one class are equal and equal to the scene run on its own.
    let sig = |it: &Item| match &it.payload {
        Payload::Signals(s) => s.data.clone(),
        _ => panic!("not signals"),
    };
    assert!(sig(&data[0]) == sig(&data[4]));
    let alone = common::run_graph_file(
        dir.path(),
        "alone.toml",
        &graph(
            "",
            "type = \"scene\"\nangles = [30, 60]\ntrials_per_angle = 2\n\
             motion = { speed_mm_s = 10.0, hold_before_s = 0.3, hold_after_s = 0.3 }\n",
        ),
    )
    .unwrap();
    assert!(sig(&alone.outputs["data"][0]) == sig(&data[0]));
    // Trained on `sim`, scored on `other` only.
    let est = &r.outputs["knn"];
    assert_eq!(ids(est), ids(&data[..4]));
}

#[test]
fn leave_one_source_out_tests_each_source_once() {
    let dir = tempfile::tempdir().unwrap();
    let sources = format!("sources.a = {SCENE}\nsources.b = {SCENE}\nsources.c = {SCENE}\n");
    let r = common::run_graph_file(
        dir.path(),
        "g.toml",
        &graph(
            r#"protocol = { leave_one_condition_out = { key = "source" } }"#,
            &sources,
        ),
    )
    .unwrap();
    let mut scored = ids(&r.outputs["knn"]);
    scored.sort();
    let mut all = ids(&r.outputs["data"]);
    all.sort();
    assert_eq!(scored, all, "every trial is scored exactly once");
}

#[test]
fn bad_unions_are_errors_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let err = |sources: &str| {
        common::run_graph_file(dir.path(), "bad.toml", &graph("", sources)).expect_err(sources)
    };
    let e = err("sources = {}\n");
    assert!(e.contains("sources") && e.contains("no source"), "{e}");
    let e = err(&format!("sources.\"a b\" = {SCENE}\n"));
    assert!(e.contains("letters, digits"), "{e}");
    let e = err(&format!(
        "sources.a = {SCENE}\nsources.b = {{ type = \"spike_file\", path = \"nowhere\" }}\n"
    ));
    assert!(e.contains("sources.b.type") && e.contains("one kind"), "{e}");
    let e = err("sources.a = { type = \"lowpass\", cutoff_hz = 10.0 }\n");
    assert!(e.contains("sources.a.type") && e.contains("not a source"), "{e}");
    let e = err("sources.a = { type = \"scene\", motion = { speed_mm_s = -1.0 } }\n");
    assert!(e.contains("sources.a.motion.speed_mm_s"), "{e}");
    let e = err(
        "sources.a = { type = \"scene\", motion = { sample_rate_hz = 1000.0 } }\n\
         sources.b = { type = \"scene\", motion = { sample_rate_hz = 500.0 } }\n",
    );
    assert!(e.contains("sources.b") && e.contains("500"), "{e}");
}

/// Writes `text` as `g.toml` in `dir` and loads it (the error as text).
fn load_text(dir: &std::path::Path, text: &str) -> Result<palpate_core::Graph, String> {
    let path = dir.join("g.toml");
    std::fs::write(&path, text).unwrap();
    palpate_core::load_file(&path, &palpate_core::LoadOptions::default()).map_err(|e| e.to_string())
}

#[test]
fn a_union_of_sources_on_different_arrays_is_a_warning_naming_both() {
    palpate_stages::link();
    let dir = tempfile::tempdir().unwrap();
    // Loading builds the sources, and a file source wants its file to exist
    // (it is read only when the run lists the trials).
    std::fs::write(dir.path().join("rec.csv"), "time_s,taxel_0\n").unwrap();
    let load = |sources: &str| load_text(dir.path(), &graph("", sources));
    let on_arrays = |w: &palpate_core::Diagnostic| w.message.contains("array is");
    let small = r#"{ type = "scene", angles = [30], array = { rows = 3, cols = 5 } }"#;
    let sources = format!("sources.a = {SCENE}\nsources.b = {small}\n");
    let g = load(&sources).unwrap();
    let w: Vec<_> = g.warnings.iter().filter(|w| on_arrays(w)).collect();
    assert_eq!(w.len(), 1, "{:#?}", g.warnings);
    assert_eq!(w[0].key.as_deref(), Some("sources.b"), "{}", w[0]);
    // At the nested key's own line, not the first `sources.` line.
    let b_line = graph("", &sources)
        .lines()
        .position(|l| l.starts_with("sources.b"))
        .unwrap()
        + 1;
    assert_eq!(w[0].line, Some(b_line), "{}", w[0]);
    assert!(
        w[0].message.contains("3 x 5") && w[0].message.contains("4 x 4") && w[0].message.contains("`a`"),
        "{}",
        w[0]
    );
    // Each source on another array than the first is named.
    let wide = r#"{ type = "scene", angles = [30], array = { rows = 2, cols = 6 } }"#;
    let g = load(&format!("{sources}sources.c = {wide}\n")).unwrap();
    let keys: Vec<_> = g
        .warnings
        .iter()
        .filter(|w| on_arrays(w))
        .map(|w| w.key.clone())
        .collect();
    assert_eq!(
        keys,
        [Some("sources.b".to_string()), Some("sources.c".to_string())]
    );
    // The same array twice, or a source that does not state its array: no warning.
    let g = load(&format!("sources.a = {SCENE}\nsources.b = {SCENE}\n")).unwrap();
    assert!(!g.warnings.iter().any(on_arrays), "{:#?}", g.warnings);
    let g = load(&format!(
        "sources.a = {SCENE}\nsources.b = {{ type = \"signal_file\", path = \"rec.csv\" }}\n"
    ))
    .unwrap();
    assert!(!g.warnings.iter().any(on_arrays), "{:#?}", g.warnings);
    // A file source's `layout` key states its array.
    let g = load(&format!(
        "sources.a = {SCENE}\nsources.b = {{ type = \"signal_file\", path = \"rec.csv\", layout = {{ rows = 2, cols = 8, pitch_mm = 3.0, taxel_mm = 2.0 }} }}\n"
    ))
    .unwrap();
    assert!(
        g.warnings
            .iter()
            .any(|w| on_arrays(w) && w.message.contains("2 x 8")),
        "{:#?}",
        g.warnings
    );
}

/// A single scene whose conditions use different arrays is warned about as
/// a union of sources on different arrays is: at each condition whose array
/// differs from the first condition's (conditions in name order).
#[test]
fn a_scene_with_conditions_on_different_arrays_is_a_warning_naming_both() {
    palpate_stages::link();
    let dir = tempfile::tempdir().unwrap();
    let load = |conditions: &str| {
        let body = format!(
            "type = \"scene\"\nangles = [30]\ntrials_per_angle = 1\nconditions = {{ {conditions} }}\n"
        );
        load_text(dir.path(), &graph("", &body))
    };
    let arrays = |g: &palpate_core::Graph| -> Vec<(Option<String>, String)> {
        g.warnings
            .iter()
            .filter(|w| w.message.contains("array is"))
            .map(|w| (w.key.clone(), w.message.clone()))
            .collect()
    };
    let g = load("a = {}, b = { array = { rows = 3, cols = 5 } }, c = {}").unwrap();
    let w = arrays(&g);
    assert_eq!(w.len(), 1, "{:#?}", g.warnings);
    assert_eq!(w[0].0.as_deref(), Some("conditions.b"), "{:?}", w[0]);
    assert!(
        w[0].1.contains("3 x 5") && w[0].1.contains("4 x 4") && w[0].1.contains("condition `a`"),
        "{}",
        w[0].1
    );
    let g =
        load("a = {}, b = { array = { rows = 3, cols = 5 } }, c = { array = { pitch_mm = 4.0 } }").unwrap();
    let keys: Vec<_> = arrays(&g).into_iter().map(|(k, _)| k).collect();
    assert_eq!(
        keys,
        [Some("conditions.b".to_string()), Some("conditions.c".to_string())]
    );
    // Conditions that change something else: no warning.
    let g = load("a = {}, b = { motion = { speed_mm_s = 4.0 } }").unwrap();
    assert!(arrays(&g).is_empty(), "{:#?}", g.warnings);
}

#[test]
fn a_daq_source_states_its_rate_and_array_before_the_run() {
    palpate_stages::link();
    let dir = tempfile::tempdir().unwrap();
    let write = |text: &str| load_text(dir.path(), text);
    let on_arrays = |w: &palpate_core::Diagnostic| w.message.contains("array is");
    // A board on a 3 x 5 array beside a 4 x 4 scene: the union warns (the
    // recording is opened only when the run lists the trials).
    let board = r#"{ type = "daq", recording = "rec.daq", layout = { rows = 3, cols = 5, pitch_mm = 3.0, taxel_mm = 2.0 } }"#;
    let g = write(&graph("", &format!("sources.a = {SCENE}\nsources.b = {board}\n"))).unwrap();
    let w: Vec<_> = g.warnings.iter().filter(|w| on_arrays(w)).collect();
    assert_eq!(w.len(), 1, "{:#?}", g.warnings);
    assert_eq!(w[0].key.as_deref(), Some("sources.b"), "{}", w[0]);
    assert!(
        w[0].message.contains("3 x 5") && w[0].message.contains("4 x 4"),
        "{}",
        w[0]
    );
    // Without `layout` a board is the default 4 x 4 grid: no warning.
    let g = write(&graph(
        "",
        &format!("sources.a = {SCENE}\nsources.b = {{ type = \"daq\", recording = \"rec.daq\" }}\n"),
    ))
    .unwrap();
    assert!(!g.warnings.iter().any(on_arrays), "{:#?}", g.warnings);
    // The board's frame rate reaches the low-pass's check: a 10 Hz cutoff
    // on a 15 Hz board is an error at load time, naming the key.
    let lowpass = |rate: f64| {
        format!(
            "[stages.daq]\ntype = \"daq\"\nrecording = \"rec.daq\"\nsample_rate_hz = {rate}\n\n\
             [stages.filter]\ntype = \"lowpass\"\ninputs = [\"daq\"]\ncutoff_hz = 10.0\n\n\
             [stages.out]\ntype = \"write_signals\"\ninputs = [\"filter\"]\n"
        )
    };
    let e = write(&lowpass(15.0)).unwrap_err();
    assert!(
        e.contains("cutoff_hz") && e.contains("Nyquist") && e.contains("15 Hz"),
        "{e}"
    );
    write(&lowpass(1000.0)).unwrap();
}
