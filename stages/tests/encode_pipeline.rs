//! Graph-level tests of the signal, encoder and spike stages: a test source
//! makes ideal edge-crossing ramps; the stages are loaded from TOML, checked and
//! run through palpate-core, as the lead's pipelines will.

use palpate_core::{
    register_stage, BuildContext, ConfigError, InputSpec, Label, LoadOptions, Payload, PayloadKind,
    RunOptions, Signals, Source, Stage, StageConfig, StageError, TaxelLayout, TrialContext, TrialMeta,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Test source: a 4 x 4 array at 1 kHz; every taxel holds at 1 for `hold_s`,
/// ramps to 0 over `ramp_s` (taxel i starting `i * stagger_s` later), holds at 0.
/// `flat` lists taxels that stay at 1.75 throughout.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
struct RampsConfig {
    /// Trials.
    trials: usize,
    /// Hold before the ramp, s.
    hold_s: f64,
    /// Ramp length, s.
    ramp_s: f64,
    /// Delay between taxels, s.
    stagger_s: f64,
    /// Trial length, s.
    total_s: f64,
    /// Taxels that never change.
    flat: Vec<usize>,
}

impl Default for RampsConfig {
    fn default() -> Self {
        RampsConfig {
            trials: 2,
            hold_s: 2.0,
            ramp_s: 1.0,
            stagger_s: 0.0,
            total_s: 5.0,
            flat: vec![],
        }
    }
}

#[typetag::serde(name = "encode_test_ramps")]
impl StageConfig for RampsConfig {
    fn inputs(&self) -> InputSpec {
        InputSpec::none()
    }
    fn output(&self) -> Option<PayloadKind> {
        Some(PayloadKind::Signals)
    }
    fn build(&self, _ctx: &BuildContext) -> Result<Stage, ConfigError> {
        Ok(Stage::Source(Box::new(self.clone())))
    }
}
register_stage!("encode_test_ramps", RampsConfig);

impl Source for RampsConfig {
    fn trials(&self) -> Result<Vec<TrialMeta>, StageError> {
        Ok((0..self.trials)
            .map(|t| TrialMeta {
                trial_id: format!("ramp-{t}"),
                label: Label {
                    angle_deg: Some(90.0),
                    ..Label::default()
                },
                group: t,
                crossing_ms: Some([
                    self.hold_s * 1000.0,
                    (self.hold_s + self.ramp_s + 15.0 * self.stagger_s) * 1000.0,
                ]),
                ..TrialMeta::default()
            })
            .collect())
    }
    fn produce(&self, _ctx: &TrialContext<'_>) -> Result<Payload, StageError> {
        let fs = 1000.0;
        let n = (self.total_s * fs).round() as usize;
        let data = (0..16)
            .map(|i| {
                if self.flat.contains(&i) {
                    return vec![1.75; n];
                }
                let start = self.hold_s + i as f64 * self.stagger_s;
                (0..n)
                    .map(|k| (1.0 - (k as f64 / fs - start) / self.ramp_s).clamp(0.0, 1.0))
                    .collect()
            })
            .collect();
        Ok(Signals {
            sample_rate_hz: fs,
            layout: TaxelLayout::paper(),
            unit: "V".into(),
            data,
        }
        .into())
    }
}

fn load(toml: &str) -> palpate_core::Graph {
    palpate_stages::link();
    match palpate_core::load_str(toml, "test.toml", "test", &LoadOptions::default()) {
        Ok(g) => g,
        Err(e) => panic!("{e}"),
    }
}

fn run(toml: &str) -> palpate_core::RunResult {
    let g = load(toml);
    palpate_core::run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..Default::default()
        },
    )
    .unwrap()
}

const PIPELINE: &str = r#"
[run]
seed = 1

[stages.scene]
type = "encode_test_ramps"
flat = [5]

[stages.norm]
type = "normalize"
inputs = ["scene"]

[stages.drive]
type = "drive"
inputs = ["norm"]

[stages.enc]
type = "izhikevich"
inputs = ["drive"]

[stages.bin]
type = "bin"
inputs = ["enc"]
"#;

/// The lead's pipeline on an ideal crossing: every moving taxel fires clearly,
/// only while the edge crosses it; the flat taxel fires nothing.
#[test]
fn fa_i_fires_only_while_the_edge_crosses() {
    let r = run(PIPELINE);
    let spikes = r.outputs["enc"][0].payload.spikes().unwrap().clone();
    assert_eq!(spikes.duration_ms, 5000.0);
    assert!(spikes.is_sorted());
    for taxel in 0..16u32 {
        let ts: Vec<f64> = spikes
            .events
            .iter()
            .filter(|e| e.taxel == taxel)
            .map(|e| e.t_ms)
            .collect();
        if taxel == 5 {
            assert!(ts.is_empty(), "flat taxel fired {ts:?}");
            continue;
        }
        // Default drive: a 20-unit plateau for 1 s -> tonic firing ~120 Hz.
        assert!(
            ts.len() >= 80 && ts.len() <= 160,
            "taxel {taxel}: {} spikes",
            ts.len()
        );
        assert!(
            ts.iter().all(|&t| (2000.0..3010.0).contains(&t)),
            "taxel {taxel}: {ts:?}"
        );
        assert!(ts[0] < 2030.0 && *ts.last().unwrap() > 2950.0);
    }
    let im = r.outputs["bin"][0].payload.images().unwrap().clone();
    assert_eq!(im.n_frames, 500);
    // A frame inside the crossing holds ~12 spikes per moving taxel; a frame on
    // the hold holds none.
    let mid = im.frame(250);
    assert!(mid[0] >= 8.0 && mid[0] <= 16.0, "{mid:?}");
    assert_eq!(mid[5], 0.0);
    assert!(im.frame(100).iter().all(|&c| c == 0.0));
    assert!(im.frame(400).iter().all(|&c| c == 0.0));
    // Same seed, same bits.
    let again = run(PIPELINE);
    assert_eq!(
        *again.outputs["enc"][1].payload.spikes().unwrap(),
        *r.outputs["enc"][1].payload.spikes().unwrap()
    );
}

/// Errors of `build` carry the key and its line.
fn config_error(stage_toml: &str) -> (Option<String>, Option<usize>, String) {
    let text = format!(
        "[run]\nseed = 1\n\n[stages.scene]\ntype = \"encode_test_ramps\"\n\n[stages.x]\n{stage_toml}\n"
    );
    palpate_stages::link();
    let errs = palpate_core::load_str(&text, "test.toml", "test", &LoadOptions::default()).unwrap_err();
    let d = errs.errors().next().expect("an error").clone();
    assert_eq!(d.stage.as_deref(), Some("x"), "{errs}");
    (d.key, d.line, d.message)
}

#[test]
fn bad_bin_and_share_values_are_config_errors_naming_the_key_and_line() {
    // Lines: 7 = [stages.x], 8 = type, 9 = inputs, 10 = the key under test.
    let (key, line, _) = config_error("type = \"bin\"\ninputs = [\"scene\"]\nwindow_ms = 0");
    assert_eq!((key.as_deref(), line), (Some("window_ms"), Some(10)));
    let (key, line, _) = config_error("type = \"bin\"\ninputs = [\"scene\"]\nhop_ms = -10");
    assert_eq!((key.as_deref(), line), (Some("hop_ms"), Some(10)));
}
