//! Helpers shared by the stage integration tests.

use palpate_core::{run, LoadOptions, RunOptions};
use std::path::Path;

/// Writes `toml` to `<dir>/<name>`, loads it as a graph file (so relative
/// paths resolve against `dir`) and runs it keeping every stage's outputs;
/// load and run errors come back as their messages.
pub fn run_graph_file(dir: &Path, name: &str, toml: &str) -> Result<palpate_core::RunResult, String> {
    palpate_stages::link();
    let path = dir.join(name);
    std::fs::write(&path, toml).unwrap();
    let g = palpate_core::load_file(&path, &LoadOptions::default()).map_err(|e| e.to_string())?;
    run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..Default::default()
        },
    )
    .map_err(|e| e.to_string())
}
