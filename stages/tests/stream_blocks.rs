//! Every streamable stage, fed a trial in blocks of 1, 7 and 1000 samples,
//! gives its batch output (`palpate_core::stream`'s contract): bit for bit
//! for the signal stages, the encoder and the binner; the same answer with
//! scores within 1e-9 for WSS (its streaming form keeps running sums that
//! round differently from the batch FFT). The spike stages (`lif`, `jitter`,
//! `dead_taxels`, `subarea`) are fed the lab trials' spike trains and
//! currents in blocks of 1, 7 and 1000 ms. Also: `stream::plan` names every
//! stage of the offline quickstart that cannot stream, and hostile blocks
//! give errors, not panics.

mod common;

use palpate_core::stream::{self, concat, signal_blocks, StreamForm};
use palpate_core::{
    BuildContext, Item, LoadOptions, Payload, RunOptions, Signals, SpikeEvent, SpikeTrain, Stage,
    StageConfig, TaxelLayout, TrialContext, TrialMeta,
};
use palpate_stages::encode::izhikevich::IzhikevichConfig;
use palpate_stages::encode::lif::LifConfig;
use palpate_stages::signal::drive::{DriveConfig, DriveKind};
use palpate_stages::signal::lowpass::{FilterMode, LowpassConfig};
use palpate_stages::signal::normalize::{NormalizeConfig, NormalizeMode};
use palpate_stages::spikes::bin::BinConfig;
use palpate_stages::spikes::dead::DeadTaxelsConfig;
use palpate_stages::spikes::jitter::{JitterConfig, JitterKind};
use palpate_stages::spikes::subarea::SubareaConfig;
use proptest::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Arc;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The quickstart's chain in its causal form (graphs/live.toml's settings),
/// on two lab-scene trials palpated at 3 mm/s, which WSS (no speed of its
/// own) must take from each trial, streamed or not.
fn live_graph() -> String {
    let front = common::causal_front_end("scene");
    format!(
        r#"
[run]
seed = 1

[stages.scene]
type = "scene"
file = "{}"
trials_per_angle = 1
angles = [30.0, 75.0]
motion = {{ speed_mm_s = 3.0 }}

{front}
[stages.enc]
type = "izhikevich"
inputs = ["drive"]

[stages.bins]
type = "bin"
inputs = ["enc"]

[stages.wss]
type = "wss"
inputs = ["bins"]
weighting = "one_minus_sr"

[stages.mae]
type = "mae"
inputs = ["wss"]
"#,
        root().join("graphs/scenes/lab.toml").display()
    )
}

fn load(text: &str) -> palpate_core::Graph {
    palpate_stages::link();
    let opts = LoadOptions {
        out: Some(std::env::temp_dir().join("palpate-stream-blocks")),
        ..LoadOptions::default()
    };
    palpate_core::load_str(text, "stream_blocks.toml", "stream_blocks", &opts).unwrap()
}

/// Runs a graph in batch, keeping every stage's outputs.
fn run_kept(g: &palpate_core::Graph) -> palpate_core::RunResult {
    palpate_core::run(
        g,
        &RunOptions {
            keep_outputs: true,
            ..RunOptions::default()
        },
    )
    .unwrap()
}

fn bits(v: &[f64]) -> Vec<u64> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// Asserts that a streamed payload equals the batch one (see the module docs).
fn assert_same(what: &str, streamed: &Payload, batch: &Payload) {
    match (streamed, batch) {
        (Payload::Signals(a), Payload::Signals(b)) => {
            assert_eq!(a.data.len(), b.data.len(), "{what}: taxels");
            for (t, (x, y)) in a.data.iter().zip(&b.data).enumerate() {
                assert_eq!(bits(x), bits(y), "{what}: taxel {t}");
            }
            assert_eq!(a.unit, b.unit, "{what}: unit");
        }
        (Payload::Spikes(a), Payload::Spikes(b)) => {
            assert_eq!(a.events.len(), b.events.len(), "{what}: spike count");
            for (x, y) in a.events.iter().zip(&b.events) {
                assert_eq!((x.taxel, x.t_ms.to_bits()), (y.taxel, y.t_ms.to_bits()), "{what}");
            }
            assert_eq!(
                a.duration_ms.to_bits(),
                b.duration_ms.to_bits(),
                "{what}: duration"
            );
        }
        (Payload::Images(a), Payload::Images(b)) => {
            assert_eq!(a.n_frames, b.n_frames, "{what}: frames");
            assert_eq!(bits(&a.counts), bits(&b.counts), "{what}: counts");
        }
        (Payload::Estimate(a), Payload::Estimate(b)) => {
            assert_eq!(a.angle_deg, b.angle_deg, "{what}: angle");
            assert_eq!(a.class_deg, b.class_deg, "{what}: class");
            assert_eq!(a.scores.len(), b.scores.len());
            for (x, y) in a.scores.iter().zip(&b.scores) {
                assert_eq!(x.angle_deg, y.angle_deg);
                assert!(
                    (x.score - y.score).abs() <= 1e-9,
                    "{what}: score {} vs {}",
                    x.score,
                    y.score
                );
            }
            match (a.decision_time_ms, b.decision_time_ms) {
                (Some(x), Some(y)) => assert!((x - y).abs() <= 1e-6, "{what}: decision {x} vs {y}"),
                (x, y) => assert_eq!(x, y, "{what}: decision time"),
            }
        }
        _ => panic!("{what}: kinds differ"),
    }
}

#[test]
fn every_stage_of_the_live_chain_streams_to_its_batch_output_in_blocks_of_1_7_and_1000() {
    let g = load(&live_graph());
    let batch = run_kept(&g);
    let plan = stream::plan(&g).unwrap_or_else(|p| panic!("{p:?}"));
    assert_eq!(plan.stages.len(), 6, "filter, norm, drive, enc, bins, wss stream");
    let scene = &batch.outputs["scene"];
    assert_eq!(scene.len(), 2);
    for (t, item) in scene.iter().enumerate() {
        let s = item.payload.signals().unwrap();
        for block in [1usize, 7, 1000] {
            let kept = plan
                .run_trial(&g, &item.meta, signal_blocks(s, block), true, |_, _| {})
                .unwrap();
            assert_eq!(kept.len(), 7, "source and six stages kept");
            for (node, blocks) in &kept {
                let id = &g.nodes[*node].id;
                let want = &batch.outputs[id][t].payload;
                let got = concat(blocks).unwrap();
                assert_same(&format!("{id}, trial {t}, blocks of {block}"), &got, want);
            }
        }
    }
    // The scenes' answers are right, offline and streamed alike.
    let wss = &batch.outputs["wss"];
    for it in wss.iter() {
        let e = it.payload.estimate().unwrap();
        assert_eq!(e.class_deg, it.meta.label.angle_deg, "{}", it.meta.trial_id);
    }
}

#[test]
fn the_offline_quickstart_names_each_stage_that_cannot_stream_and_its_alternative() {
    let text = std::fs::read_to_string(root().join("graphs/quickstart.toml"))
        .unwrap()
        .replace(
            "scenes/lab.toml",
            &root().join("graphs/scenes/lab.toml").display().to_string(),
        );
    let g = load(&text);
    let problems = match stream::plan(&g) {
        Ok(_) => panic!("the zero-phase quickstart cannot stream"),
        Err(p) => p,
    };
    let ids: Vec<&str> = problems.iter().map(|p| p.stage.as_str()).collect();
    assert_eq!(ids, ["filter", "norm", "drive"]);
    assert!(problems[0].instead.contains("causal"), "{}", problems[0]);
    assert!(problems[1].instead.contains("span"), "{}", problems[1]);
    assert!(problems[2].instead.contains("gain"), "{}", problems[2]);
}

fn ctx() -> BuildContext {
    BuildContext {
        stage_id: "s".into(),
        seed: 7,
        out_dir: std::env::temp_dir(),
        base_dir: std::env::temp_dir(),
    }
}

/// Batch output of `cfg` on `input`, and its streamed output in `block`s.
fn both(cfg: &dyn StageConfig, type_name: &str, input: &Signals, block: usize) -> (Payload, Payload) {
    both_blocks(
        cfg,
        type_name,
        &input.clone().into(),
        &signal_blocks(input, block),
    )
}

/// A spike train cut as an upstream stage streams it: block `k` holds the
/// events in `[k·block, (k+1)·block)` ms and is known up to its end.
fn spike_blocks(t: &SpikeTrain, block_ms: f64) -> Vec<Payload> {
    let n = (t.duration_ms / block_ms).ceil().max(1.0) as usize;
    (0..n)
        .map(|k| {
            let (a, b) = (
                k as f64 * block_ms,
                ((k + 1) as f64 * block_ms).min(t.duration_ms),
            );
            SpikeTrain {
                layout: t.layout.clone(),
                duration_ms: b,
                events: t
                    .events
                    .iter()
                    .copied()
                    .filter(|e| e.t_ms >= a && e.t_ms < b)
                    .collect(),
            }
            .into()
        })
        .collect()
}

/// Batch output of `cfg` on `input`, and its output streamed from `blocks`.
fn both_blocks(
    cfg: &dyn StageConfig,
    type_name: &str,
    input: &Payload,
    blocks: &[Payload],
) -> (Payload, Payload) {
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
        meta: Arc::new(meta.clone()),
        payload: input.clone(),
    };
    let Ok(Stage::Map(map)) = cfg.build(&ctx()) else {
        panic!("{type_name} is a map")
    };
    let batch = map.process(&[&item], &tctx).unwrap();
    let settings = serde_json::to_value(cfg).unwrap();
    let Ok(StreamForm::Streams(s)) = stream::form(type_name, &settings, &ctx()) else {
        panic!("{type_name} streams")
    };
    let out = stream::run_blocks(s.as_ref(), blocks, &tctx).unwrap();
    // Every block but empty ones is time-sorted and known up to its duration.
    let mut known = 0.0f64;
    for b in &out {
        if let Ok(t) = b.spikes() {
            assert!(
                t.events.windows(2).all(|w| w[0].t_ms <= w[1].t_ms),
                "{type_name}: unsorted block"
            );
            assert!(
                t.events.iter().all(|e| e.t_ms >= known),
                "{type_name}: an event before the last block's end"
            );
            known = known.max(t.duration_ms);
        }
    }
    (concat(&out).unwrap(), batch)
}

#[test]
fn spike_stages_and_lif_stream_to_their_batch_output_in_blocks_of_1_7_and_1000() {
    let g = load(&live_graph());
    let batch = run_kept(&g);
    let mut jitters = Vec::new();
    for (kind, tau_ms) in [
        (JitterKind::Gaussian, 1.0),
        (JitterKind::Gaussian, 5.0),
        (JitterKind::Uniform, 3.0),
    ] {
        jitters.push(JitterConfig { kind, tau_ms });
    }
    for (t, item) in batch.outputs["enc"].iter().enumerate() {
        let mut train = item.payload.spikes().unwrap().as_ref().clone();
        // Spikes at the very start and end, so that jitter reflects some at 0
        // and some at the trial's end.
        let d = train.duration_ms;
        for (taxel, t_ms) in [(0, 0.0), (3, 0.2), (5, 1.5), (2, d - 0.1), (7, d - 2.0)] {
            train.events.push(SpikeEvent { taxel, t_ms });
        }
        train.sort();
        let input: Payload = train.clone().into();
        for block in [1.0, 7.0, 1000.0] {
            let blocks = spike_blocks(&train, block);
            let what = |s: &str| format!("{s}, trial {t}, blocks of {block} ms");
            for j in &jitters {
                let (a, b) = both_blocks(j, "jitter", &input, &blocks);
                assert_same(&what(&format!("jitter {:?} {}", j.kind, j.tau_ms)), &a, &b);
            }
            let dead = DeadTaxelsConfig {
                taxels: vec![1],
                cells: vec![[2, 2]],
                random_count: 3,
            };
            let (a, b) = both_blocks(&dead, "dead_taxels", &input, &blocks);
            assert_same(&what("dead_taxels"), &a, &b);
            for (row, col) in [(0, 0), (1, 1)] {
                let sub = SubareaConfig { size: 3, row, col };
                let (a, b) = both_blocks(&sub, "subarea", &input, &blocks);
                assert_same(&what("subarea"), &a, &b);
            }
        }
        // LIF on the drive's currents, in blocks of samples.
        let cur = batch.outputs["drive"][t]
            .payload
            .signals()
            .unwrap()
            .as_ref()
            .clone();
        for block in [1usize, 7, 1000] {
            let (a, b) = both(&LifConfig::default(), "lif", &cur, block);
            assert_same(&format!("lif, trial {t}, blocks of {block}"), &a, &b);
            assert!(!a.spikes().unwrap().events.is_empty());
        }
    }
}

fn signals(data: Vec<Vec<f64>>) -> Signals {
    let n = data.len();
    Signals {
        sample_rate_hz: 1000.0,
        layout: TaxelLayout::Positions {
            positions_mm: (0..n).map(|i| [i as f64, 0.0]).collect(),
            taxel_mm: 1.0,
        },
        unit: "V".into(),
        data,
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Random signals (wild values included), random block sizes: every
    /// signal stage and the encoder and binner equal their batch output.
    #[test]
    fn random_signals_stream_to_the_batch_output(
        rows in proptest::collection::vec(proptest::collection::vec(-1e6f64..1e6, 2..300), 1..4),
        block in 1usize..64,
        fc in 1.0f64..400.0,
        gain in 0.0f64..1e3,
    ) {
        let len = rows.iter().map(Vec::len).min().unwrap_or(0);
        let s = signals(rows.into_iter().map(|mut r| { r.truncate(len); r }).collect());
        let lp = LowpassConfig { order: 3, cutoff_hz: fc, mode: FilterMode::Causal };
        let (a, b) = both(&lp, "lowpass", &s, block);
        assert_same("lowpass", &a, &b);
        let nb = NormalizeConfig { mode: NormalizeMode::Causal, baseline_ms: 1.0, span: Some(3.0), min_span: 0.1, dead_fraction: 0.25 };
        let (a, b) = both(&nb, "normalize", &s, block);
        assert_same("normalize", &a, &b);
        for kind in [DriveKind::FaI, DriveKind::SaI] {
            let d = DriveConfig { kind, gain: Some(gain), target_peak_current: None, peak_of: Default::default() };
            let (a, b) = both(&d, "drive", &s, block);
            assert_same("drive", &a, &b);
        }
        let cur = signals(s.data.iter().map(|r| r.iter().map(|x| (x * 1e-4).abs()).collect()).collect());
        let enc = IzhikevichConfig::default();
        let (a, b) = both(&enc, "izhikevich", &cur, block);
        assert_same("izhikevich", &a, &b);
        let lif = LifConfig { tau_ms: 5.0, refractory_ms: 1.3, dt_ms: 0.3, ..LifConfig::default() };
        let (a, b) = both(&lif, "lif", &cur, block);
        assert_same("lif", &a, &b);
    }
}

#[test]
fn hostile_blocks_are_errors_not_panics() {
    let settings = serde_json::to_value(&BinConfig::default() as &dyn StageConfig).unwrap();
    let Ok(StreamForm::Streams(bin)) = stream::form("bin", &settings, &ctx()) else {
        panic!("bin streams")
    };
    let meta = TrialMeta::default();
    let tctx = TrialContext {
        stage_id: "bins",
        meta: &meta,
        seed: 0,
    };
    let layout = TaxelLayout::paper();
    let huge = palpate_core::SpikeTrain {
        layout: layout.clone(),
        duration_ms: 1e300,
        events: vec![],
    };
    assert!(stream::run_blocks(bin.as_ref(), &[huge.into()], &tctx).is_err());
    let bad_taxel = palpate_core::SpikeTrain {
        layout,
        duration_ms: 10.0,
        events: vec![palpate_core::SpikeEvent { taxel: 99, t_ms: 1.0 }],
    };
    assert!(stream::run_blocks(bin.as_ref(), &[bad_taxel.into()], &tctx).is_err());
    // The streaming form of a causal order-2 low-pass at `cutoff_hz`.
    let lowpass = |cutoff_hz: f64| {
        let lp = LowpassConfig {
            order: 2,
            cutoff_hz,
            mode: FilterMode::Causal,
        };
        let settings = serde_json::to_value(&lp as &dyn StageConfig).unwrap();
        let Ok(StreamForm::Streams(f)) = stream::form("lowpass", &settings, &ctx()) else {
            panic!("causal lowpass streams")
        };
        f
    };
    // A non-finite sample is refused by the signal stages, as in batch.
    let s = signals(vec![vec![1.0, f64::NAN, 2.0]]);
    assert!(stream::run_blocks(lowpass(10.0).as_ref(), &signal_blocks(&s, 1), &tctx).is_err());
    // A cutoff above Nyquist is named.
    let e = stream::run_blocks(
        lowpass(900.0).as_ref(),
        &signal_blocks(&signals(vec![vec![0.0; 10]]), 3),
        &tctx,
    )
    .unwrap_err();
    assert!(e.message.contains("cutoff_hz"), "{e}");
    // A cutoff too small a share of the rate for f64 (10 Hz at 1e50 Hz)
    // is refused as in batch, not streamed as NaN.
    let f = lowpass(10.0);
    let mut fast = signals(vec![vec![0.0, 1.0, 0.5, 0.2]]);
    fast.sample_rate_hz = 1e50;
    let e = stream::run_blocks(f.as_ref(), &signal_blocks(&fast, 2), &tctx).unwrap_err();
    assert!(
        e.message.contains("cutoff_hz") && e.message.contains("resample"),
        "{e}"
    );
    // A stream at a rate that makes each sample hours long stops at the
    // batch encoder's cap on neuron steps, not after billions of steps.
    let mut slow = signals(vec![vec![20.0; 40]; 16]);
    slow.sample_rate_hz = 1e-3;
    for (name, cfg) in [
        (
            "izhikevich",
            serde_json::to_value(&IzhikevichConfig::default() as &dyn StageConfig).unwrap(),
        ),
        (
            "lif",
            serde_json::to_value(&LifConfig::default() as &dyn StageConfig).unwrap(),
        ),
    ] {
        let Ok(StreamForm::Streams(enc)) = stream::form(name, &cfg, &ctx()) else {
            panic!("{name} streams")
        };
        let e = stream::run_blocks(enc.as_ref(), &signal_blocks(&slow, 1), &tctx).unwrap_err();
        assert!(
            e.message.contains("over the cap of 268435456 neuron steps"),
            "{name}: {e}"
        );
    }
}

/// The live chain's images, then a saved ANN (spatiotemporal) and a saved
/// EDBN (spiking inference, so the streamed and batch random draws must
/// agree too) loading `model_in`, each with its `mae` sink.
fn saved_models_graph(ann: &Path, edbn: &Path) -> String {
    let text = live_graph();
    let (chain, _) = text.split_once("[stages.wss]").unwrap();
    format!(
        r#"{chain}
[stages.ann]
type = "ann"
inputs = ["bins"]
model_in = {ann:?}

[stages.edbn]
type = "edbn"
inputs = ["bins"]
model_in = {edbn:?}

[stages.mae_ann]
type = "mae"
inputs = ["ann"]

[stages.mae_edbn]
type = "mae"
inputs = ["edbn"]
"#,
        ann = ann.display().to_string(),
        edbn = edbn.display().to_string(),
    )
}

/// Trained estimators with a saved model (`model_in`) stream to their batch
/// estimate, the same bits, in blocks of 1, 7 and 1000 samples; the models
/// are fitted on the live chain's two lab trials and saved as an offline run
/// saves them.
#[test]
fn saved_ann_and_edbn_stream_to_their_batch_estimates_in_blocks_of_1_7_and_1000() {
    use palpate_core::FitContext;
    use palpate_stages::estimate::ann::AnnConfig;
    use palpate_stages::estimate::edbn::{EdbnConfig, Inference};
    use palpate_stages::estimate::features::{save_model, FitBaseline};
    let g = load(&live_graph());
    let batch = run_kept(&g);
    let images: Vec<&Item> = batch.outputs["bins"].iter().collect();
    let dir = std::env::temp_dir().join(format!("palpate-stream-saved-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let fctx = FitContext {
        stage_id: "ann",
        fold: 0,
        seed: 5,
    };
    let ann = AnnConfig {
        hidden: 12,
        max_epochs: 30,
        val_fraction: 0.0,
        ..AnnConfig::default()
    };
    let edbn = EdbnConfig {
        layers: vec![30],
        epochs: 6,
        inference: Inference::Spiking,
        ..EdbnConfig::default()
    };
    let (ann_file, edbn_file) = (dir.join("ann.model.json"), dir.join("edbn.model.json"));
    save_model(&ann.fit_fold(&images, &fctx).unwrap(), &ann_file).unwrap();
    save_model(&edbn.fit_fold(&images, &fctx).unwrap(), &edbn_file).unwrap();

    let g = load(&saved_models_graph(&ann_file, &edbn_file));
    let batch = run_kept(&g);
    let plan = stream::plan(&g).unwrap_or_else(|p| panic!("{p:?}"));
    assert_eq!(
        plan.stages.len(),
        7,
        "filter, norm, drive, enc, bins, ann, edbn stream"
    );
    for id in ["ann", "edbn"] {
        assert_eq!(batch.outputs[id].len(), 2, "{id} estimates every trial, no fold");
    }
    // The ANN learnt its two training trials.
    for it in batch.outputs["ann"].iter() {
        let e = it.payload.estimate().unwrap();
        assert_eq!(e.angle_deg, it.meta.label.angle_deg, "{}", it.meta.trial_id);
    }
    for (t, item) in batch.outputs["scene"].iter().enumerate() {
        let s = item.payload.signals().unwrap();
        for block in [1usize, 7, 1000] {
            let kept = plan
                .run_trial(&g, &item.meta, signal_blocks(s, block), true, |_, _| {})
                .unwrap();
            for id in ["ann", "edbn"] {
                let node = g.index_of(id).unwrap();
                let blocks = &kept.iter().find(|(n, _)| *n == node).unwrap().1;
                let got = concat(blocks).unwrap();
                let want = &batch.outputs[id][t].payload;
                assert_eq!(
                    got.estimate().unwrap(),
                    want.estimate().unwrap(),
                    "{id}, trial {t}, blocks of {block}"
                );
                assert!(want.estimate().unwrap().angle_deg.is_some(), "{id}: an edge");
                // Running estimates came before the final one.
                assert!(blocks.len() >= 2, "{id}, trial {t}: {} blocks", blocks.len());
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Without `model_in` a trained estimator cannot stream, and the plan says
/// so, naming `model_in` as the alternative.
#[test]
fn a_trained_estimator_without_model_in_names_model_in_as_its_alternative() {
    let text = live_graph().replace(
        "type = \"wss\"\ninputs = [\"bins\"]\nweighting = \"one_minus_sr\"",
        "type = \"ann\"\ninputs = [\"bins\"]",
    );
    let g = load(&text);
    let problems = match stream::plan(&g) {
        Ok(_) => panic!("a fitting ANN cannot stream"),
        Err(p) => p,
    };
    assert_eq!(problems.len(), 1, "{problems:?}");
    assert_eq!(problems[0].stage, "wss");
    assert_eq!(problems[0].type_name, "ann");
    assert!(problems[0].instead.contains("model_in"), "{}", problems[0]);
    assert!(problems[0].to_string().contains("save_model"), "{}", problems[0]);
}

/// A live run scores every trial as it streams and runs one graph: a
/// protocol that scores a held-out subset (chosen from the whole trial list)
/// or a `[sweep]` table is refused by the plan, as the graph as a whole, and
/// so by `check --live` too (before, `run --live` scored every trial, the
/// batch run only the held-out ones, and a sweep ran its base graph alone).
#[test]
fn a_hold_out_protocol_or_a_sweep_cannot_run_live() {
    let base = live_graph();
    assert!(stream::plan(&load(&base)).is_ok());
    for (extra, what) in [
        ("protocol = { hold_out = { test_share = 0.3 } }", "hold_out"),
        (
            "protocol = { train_test = { key = \"group\", train = [0] } }",
            "TrainTest",
        ),
    ] {
        let text = base.replacen("[run]\n", &format!("[run]\n{extra}\n"), 1);
        assert_ne!(text, base, "the live graph has a [run] table");
        let problems = match stream::plan(&load(&text)) {
            Ok(_) => panic!("{what}: a held-out protocol cannot stream"),
            Err(p) => p,
        };
        assert_eq!(problems.len(), 1, "{problems:?}");
        let msg = problems[0].to_string();
        assert!(msg.starts_with("the graph cannot run live"), "{msg}");
        assert!(
            msg.contains("protocol") && msg.contains("without --live"),
            "{msg}"
        );
    }
    let text = format!("{base}\n[sweep]\nkey = \"stages.bins.hop_ms\"\nvalues = [10.0, 20.0]\n");
    let problems = match stream::plan(&load(&text)) {
        Ok(_) => panic!("a sweep cannot stream"),
        Err(p) => p,
    };
    assert!(problems[0].to_string().contains("[sweep]"), "{}", problems[0]);
}
