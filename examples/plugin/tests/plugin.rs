//! The plugin's stages register like built-ins, its graph checks and runs, and
//! its binary lists its stages.

use palpate_core::{load_file, run, LoadOptions, RunOptions};
use std::path::Path;

#[test]
fn plugin_types_are_registered_with_typetag_and_schema() {
    palpate_plugin_example::link();
    let names: Vec<&str> = palpate_core::registry::registrations()
        .iter()
        .map(|r| r.type_name)
        .collect();
    assert_eq!(names, palpate_core::registry::typetag_names());
    for t in ["adaptive_lif", "hex_fingertip", "scene", "wss"] {
        assert!(names.contains(&t), "{t} missing from {names:?}");
    }
}

#[test]
fn the_plugin_graph_checks_and_runs_on_a_hexagonal_layout() {
    palpate_plugin_example::link();
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("graphs/hex_adaptive.toml");
    let out = std::env::temp_dir().join(format!("palpate-plugin-test-{}", std::process::id()));
    let opts = LoadOptions {
        out: Some(out.clone()),
        overrides: vec![("stages.skin.trials_per_angle".into(), toml::Value::Integer(1))],
        ..Default::default()
    };
    let g = load_file(&path, &opts).unwrap_or_else(|e| panic!("{e}"));
    let r = run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..Default::default()
        },
    )
    .unwrap();
    let signals = r.outputs["skin"][0].payload.signals().unwrap().clone();
    assert!(signals.layout.grid().is_none(), "the fingertip is not a grid");
    assert!(signals.layout.len() >= 12);
    let spikes = r.outputs["enc"]
        .iter()
        .map(|i| i.payload.spikes().unwrap().events.len())
        .sum::<usize>();
    assert!(spikes > 0, "the adaptive LIF fired nothing");
    let est = &r.outputs["wss"];
    assert_eq!(est.len(), 5);
    let answered = est
        .iter()
        .filter(|i| i.payload.estimate().unwrap().angle_deg.is_some())
        .count();
    assert_eq!(answered, 5);
    let _ = std::fs::remove_dir_all(out);
}

#[test]
fn the_plugin_binary_lists_its_stages() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_palpate-plugin"))
        .arg("stages")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success());
    assert!(
        text.contains("adaptive_lif") && text.contains("hex_fingertip") && text.contains("izhikevich"),
        "{text}"
    );
}
