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

/// Errors of `build` carry the key and its line. The stage under test, `x`,
/// reads the spikes of an encoder; its key under test is on line 14.
fn config_error(stage_toml: &str) -> (Option<String>, Option<usize>, String) {
    let text = format!(
        "[run]\nseed = 1\n\n[stages.scene]\ntype = \"encode_test_ramps\"\n\n[stages.enc]\ntype = \"izhikevich\"\ninputs = [\"scene\"]\n\n[stages.x]\n{stage_toml}\n"
    );
    palpate_stages::link();
    let errs = palpate_core::load_str(&text, "test.toml", "test", &LoadOptions::default()).unwrap_err();
    let all: Vec<_> = errs.errors().collect();
    assert_eq!(all.len(), 1, "{errs}");
    let d = all[0].clone();
    assert_eq!(d.stage.as_deref(), Some("x"), "{errs}");
    (d.key, d.line, d.message)
}

#[test]
fn bad_window_hop_and_share_are_config_errors_naming_the_key_and_line() {
    for (toml, key) in [
        ("type = \"bin\"\ninputs = [\"enc\"]\nwindow_ms = 0", "window_ms"),
        (
            "type = \"bin\"\ninputs = [\"enc\"]\nwindow_ms = -5.0",
            "window_ms",
        ),
        ("type = \"bin\"\ninputs = [\"enc\"]\nhop_ms = -10", "hop_ms"),
        ("type = \"bin\"\ninputs = [\"enc\"]\nhop_ms = 0.0", "hop_ms"),
        ("type = \"crop\"\ninputs = [\"enc\"]\nshare = 0.0", "share"),
        ("type = \"crop\"\ninputs = [\"enc\"]\nshare = 1.5", "share"),
        ("type = \"crop\"\ninputs = [\"enc\"]\nshare = -0.2", "share"),
        ("type = \"jitter\"\ninputs = [\"enc\"]\ntau_ms = -1.0", "tau_ms"),
        ("type = \"subarea\"\ninputs = [\"enc\"]\nsize = 0", "size"),
    ] {
        let (k, line, msg) = config_error(toml);
        assert_eq!((k.as_deref(), line), (Some(key), Some(14)), "{toml}: {msg}");
        assert!(msg.contains(key), "{msg}");
    }
    // And a valid share loads.
    let text = "[run]\nseed = 1\n[stages.scene]\ntype = \"encode_test_ramps\"\n[stages.enc]\ntype = \"izhikevich\"\ninputs = [\"scene\"]\n[stages.x]\ntype = \"crop\"\ninputs = [\"enc\"]\nshare = 0.6\n";
    load(text);
}

fn temp_out(name: &str) -> std::path::PathBuf {
    std::env::temp_dir().join(format!("palpate-encode-{name}-{}", std::process::id()))
}

const ROBUST: &str = r#"
[run]
seed = 7

[stages.scene]
type = "encode_test_ramps"
trials = 3
stagger_s = 0.1

[stages.norm]
type = "normalize"
inputs = ["scene"]

[stages.lp]
type = "lowpass"
inputs = ["norm"]
order = 2
cutoff_hz = 20

[stages.drive]
type = "drive"
inputs = ["lp"]

[stages.enc]
type = "izhikevich"
inputs = ["drive"]

[stages.jit]
type = "jitter"
inputs = ["enc"]
tau_ms = 10

[stages.crop]
type = "crop"
inputs = ["jit"]
share = 0.5

[stages.sub]
type = "subarea"
inputs = ["crop"]
size = 2
row = 1
col = 2

[stages.dead]
type = "dead_taxels"
inputs = ["sub"]
cells = [[0, 0]]

[stages.bin]
type = "bin"
inputs = ["dead"]

[stages.raster]
type = "raster_plot"
inputs = ["enc"]
n_trials = 2

[stages.strip]
type = "image_strip"
inputs = ["bin"]
trials = ["ramp-2"]
"#;

fn run_with_out(
    toml: &str,
    out: &std::path::Path,
) -> Result<palpate_core::RunResult, palpate_core::RunError> {
    palpate_stages::link();
    let opts = LoadOptions {
        out: Some(out.to_path_buf()),
        ..LoadOptions::default()
    };
    let g = palpate_core::load_str(toml, "test.toml", "test", &opts).unwrap_or_else(|e| panic!("{e}"));
    palpate_core::run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..Default::default()
        },
    )
}

/// The robustness chain of the paper's Figs. 7-9 runs end to end, is
/// deterministic for a seed, and the plot sinks write their SVGs.
#[test]
fn robustness_chain_runs_deterministically_and_plots() {
    let out = temp_out("robust");
    let r = run_with_out(ROBUST, &out).unwrap();
    let enc = r.outputs["enc"][0].payload.spikes().unwrap().clone();
    let jit = r.outputs["jit"][0].payload.spikes().unwrap().clone();
    assert_eq!(enc.events.len(), jit.events.len());
    assert_ne!(enc.events, jit.events);
    // Crossing known from the source: [2000, 2000 + 1000 + 1500] -> cut at 3250.
    let crop = r.outputs["crop"][0].payload.spikes().unwrap().clone();
    assert!(crop.events.iter().all(|e| e.t_ms <= 3250.0));
    assert!(crop.duration_ms > 3250.0 && crop.duration_ms < 3250.001);
    let sub = r.outputs["sub"][0].payload.spikes().unwrap().clone();
    assert_eq!(sub.layout.len(), 4);
    assert!(sub.events.iter().any(|e| e.taxel == 0));
    let dead = r.outputs["dead"][0].payload.spikes().unwrap().clone();
    assert!(dead.events.iter().all(|e| e.taxel != 0) && !dead.events.is_empty());
    let im = r.outputs["bin"][0].payload.images().unwrap().clone();
    assert_eq!((im.n_taxels(), im.n_frames), (4, 326));
    // Jitter differs per trial (seeded by trial id) but not per run.
    let jit1 = r.outputs["jit"][1].payload.spikes().unwrap().clone();
    let enc1 = r.outputs["enc"][1].payload.spikes().unwrap().clone();
    assert_eq!(enc.events, enc1.events, "identical trials encode identically");
    assert_ne!(jit.events, jit1.events);
    let again = run_with_out(ROBUST, &out).unwrap();
    for id in ["jit", "crop", "dead", "bin"] {
        for t in 0..3 {
            let (a, b) = (&r.outputs[id][t].payload, &again.outputs[id][t].payload);
            assert_eq!(format!("{a:?}"), format!("{b:?}"), "{id} trial {t}");
        }
    }
    let files: Vec<_> = r.reports.iter().flat_map(|(_, rep)| rep.files.clone()).collect();
    assert_eq!(files.len(), 3, "{files:?}");
    for f in &files {
        let text = std::fs::read_to_string(f).unwrap();
        assert!(
            text.starts_with("<svg") && text.contains("</svg>"),
            "{}",
            f.display()
        );
    }
    assert!(out.join("strip-ramp-2.svg").exists() && out.join("raster-ramp-0.svg").exists());
    if let Ok(keep) = std::env::var("PALPATE_KEEP_PLOTS") {
        for f in &files {
            let _ = std::fs::copy(f, std::path::Path::new(&keep).join(f.file_name().unwrap()));
        }
    }
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn subarea_placement_off_the_grid_is_a_run_error_naming_the_key() {
    let toml = "[run]\nseed = 1\n[stages.scene]\ntype = \"encode_test_ramps\"\ntrials = 1\n[stages.enc]\ntype = \"izhikevich\"\ninputs = [\"scene\"]\n[stages.sub]\ntype = \"subarea\"\ninputs = [\"enc\"]\nsize = 3\nrow = 2\n";
    let out = temp_out("sub");
    let e = run_with_out(toml, &out).expect_err("an error");
    assert!(
        e.to_string().contains("`row`") && e.to_string().contains("sub"),
        "{e}"
    );
    let unknown = ROBUST.replace("trials = [\"ramp-2\"]", "trials = [\"nope\"]");
    let e = run_with_out(&unknown, &out).expect_err("an error");
    assert!(
        e.to_string().contains("`trials`") && e.to_string().contains("nope"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// The live variant: causal normalization, causal filter, LIF encoder. Spikes
/// still come only from the crossing (plus the causal filter's lag).
#[test]
fn causal_chain_with_lif_fires_only_during_the_crossing() {
    let toml = r#"
[run]
seed = 1
[stages.scene]
type = "encode_test_ramps"
trials = 1
flat = [3]
[stages.norm]
type = "normalize"
inputs = ["scene"]
mode = "causal"
baseline_ms = 500
span = 1.0
[stages.lp]
type = "lowpass"
inputs = ["norm"]
mode = "causal"
cutoff_hz = 10
[stages.drive]
type = "drive"
inputs = ["lp"]
[stages.enc]
type = "lif"
inputs = ["drive"]
"#;
    let r = run(toml);
    let sp = r.outputs["enc"][0].payload.spikes().unwrap().clone();
    assert!(sp.events.iter().all(|e| e.taxel != 3));
    assert!(
        sp.events.iter().all(|e| (2000.0..3100.0).contains(&e.t_ms)),
        "{:?}",
        sp.events.first()
    );
    for taxel in [0u32, 15] {
        let n = sp.events.iter().filter(|e| e.taxel == taxel).count();
        assert!(n >= 60, "taxel {taxel}: {n}");
    }
}
