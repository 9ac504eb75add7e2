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
