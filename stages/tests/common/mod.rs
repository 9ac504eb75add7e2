//! Helpers shared by the stage integration tests.

use palpate_core::{run, LoadOptions, RunOptions};
use std::path::Path;

/// Writes `toml` to `<dir>/<name>`, loads it as a graph file (so relative
/// paths resolve against `dir`) and runs it keeping every stage's outputs;
/// load and run errors come back as their messages.
#[allow(dead_code)] // not every test binary that includes this module uses it
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

/// graphs/live.toml's causal front end as graph tables: `filter` (causal
/// 10 Hz low-pass), `norm` (causal, 1.55 V span) and `drive` (FA-I, the
/// paper graphs' fixed G = 30), reading the stage `input`. The live and
/// streaming tests put an encoder, bins and an estimator after it.
#[allow(dead_code)] // not every test binary that includes this module uses it
pub fn causal_front_end(input: &str) -> String {
    format!(
        r#"
[stages.filter]
type = "lowpass"
inputs = ["{input}"]
cutoff_hz = 10.0
mode = "causal"

[stages.norm]
type = "normalize"
inputs = ["filter"]
mode = "causal"
baseline_ms = 500.0
span = 1.55

[stages.drive]
type = "drive"
inputs = ["norm"]
kind = "fa_i"
gain = 30.0
"#
    )
}

/// Builds `cfg` (a map stage) and runs it on one trial holding `payload`:
/// its output, or its error's message.
#[allow(dead_code)] // not every test binary that includes this module uses it
pub fn process_one(
    cfg: &dyn palpate_core::StageConfig,
    payload: palpate_core::Payload,
) -> Result<palpate_core::Payload, String> {
    use palpate_core::{BuildContext, Item, Stage, TrialContext, TrialMeta};
    let ctx = BuildContext {
        stage_id: "s".into(),
        seed: 1,
        out_dir: ".".into(),
        base_dir: ".".into(),
    };
    let Ok(Stage::Map(map)) = cfg.build(&ctx) else {
        panic!("{cfg:?} builds a map")
    };
    let meta = TrialMeta {
        trial_id: "t".into(),
        ..TrialMeta::default()
    };
    let tctx = TrialContext {
        stage_id: "s",
        meta: &meta,
        seed: 1,
    };
    let item = Item {
        meta: std::sync::Arc::new(meta.clone()),
        payload,
    };
    map.process(&[&item], &tctx).map_err(|e| e.message)
}
