//! Trained estimators with `model_in`: a graph that fits and saves models
//! (`save_model = true`) and a second graph that loads one give the same
//! estimates, bit for bit, on the trials the saved fold tested (ANN and
//! EDBN); and every bad `model_in` (missing file, bad JSON, another stage
//! type's model, a model inconsistent with itself, images of another taxel
//! count, frame window or hop, `save_model` beside it) is an error naming the
//! stage, the key and the file.

mod common;

use palpate_core::stream::{self, StreamForm};
use palpate_core::{
    BuildContext, FitContext, Item, LoadOptions, RunOptions, SpikeImages, Stage, StageConfig, TaxelLayout,
    TrialContext, TrialMeta,
};
use palpate_stages::estimate::ann::AnnConfig;
use palpate_stages::estimate::classic::{KnnConfig, LogisticConfig, RandomForestConfig, SvmConfig};
use palpate_stages::estimate::edbn::EdbnConfig;
use palpate_stages::estimate::features::{save_model, synthetic_items, FitBaseline, SynthParams};
use std::path::{Path, PathBuf};
use std::sync::Arc;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("palpate-saved-models-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// graphs/live.toml's causal chain on two lab trials of 30 and 75 degrees,
/// then `estimators` (stage tables reading `bins`).
fn graph_text(estimators: &str) -> String {
    let front = common::causal_front_end("scene");
    format!(
        r#"
[run]
seed = 2

[stages.scene]
type = "scene"
file = "{}"
trials_per_angle = 2
angles = [30.0, 75.0]

{front}
[stages.enc]
type = "izhikevich"
inputs = ["drive"]
input = "hold"

[stages.bins]
type = "bin"
inputs = ["enc"]
{estimators}
"#,
        root().join("graphs/scenes/lab.toml").display()
    )
}

const ANN_KEYS: &str = "hidden = 12\nmax_epochs = 30\nval_fraction = 0.0";
const EDBN_KEYS: &str = "layers = [20]\nepochs = 4";

fn estimators(extra_ann: &str, extra_edbn: &str) -> String {
    format!(
        "[stages.ann]\ntype = \"ann\"\ninputs = [\"bins\"]\n{ANN_KEYS}\n{extra_ann}\n\
         [stages.edbn]\ntype = \"edbn\"\ninputs = [\"bins\"]\n{EDBN_KEYS}\n{extra_edbn}\n\
         [stages.mae]\ntype = \"mae\"\ninputs = [\"ann\", \"edbn\"]\n"
    )
}

fn run(text: &str, out: &Path) -> palpate_core::RunResult {
    palpate_stages::link();
    let opts = LoadOptions {
        out: Some(out.to_path_buf()),
        ..LoadOptions::default()
    };
    let g = palpate_core::load_str(text, "saved.toml", "saved", &opts).unwrap_or_else(|e| panic!("{e}"));
    palpate_core::run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..RunOptions::default()
        },
    )
    .unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn a_saved_ann_and_edbn_predict_the_fitting_runs_estimates_bit_for_bit() {
    let out = tmp("fit");
    let fitted = run(
        &graph_text(&estimators("save_model = true", "save_model = true")),
        &out,
    );
    let (ann, edbn) = (
        out.join("ann.fold0.model.json"),
        out.join("edbn.fold0.model.json"),
    );
    assert!(ann.is_file() && edbn.is_file() && out.join("ann.fold1.model.json").is_file());
    let loaded = run(
        &graph_text(&estimators(
            &format!("model_in = {:?}", ann.display().to_string()),
            &format!("model_in = {:?}", edbn.display().to_string()),
        )),
        &tmp("load"),
    );
    for id in ["ann", "edbn"] {
        let (a, b) = (&fitted.outputs[id], &loaded.outputs[id]);
        assert_eq!(a.len(), 4);
        assert_eq!(b.len(), 4, "{id}: every trial estimated, no fold");
        let mut same = 0;
        for (x, y) in a.iter().zip(b.iter()) {
            assert_eq!(x.meta.trial_id, y.meta.trial_id);
            // Fold 0 held out the first repetition of each class.
            if x.meta.group == 0 {
                let (ex, ey) = (x.payload.estimate().unwrap(), y.payload.estimate().unwrap());
                assert_eq!(ex, ey, "{id}, {}", x.meta.trial_id);
                let bits = |e: &palpate_core::Estimate| -> Vec<u64> {
                    e.scores.iter().map(|s| s.score.to_bits()).collect()
                };
                assert_eq!(bits(ex), bits(ey), "{id}, {}", x.meta.trial_id);
                assert!(ex.angle_deg.is_some(), "{id}, {}: an edge", x.meta.trial_id);
                same += 1;
            }
        }
        assert_eq!(same, 2, "{id}: the fold's two test trials compared");
    }
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(tmp("load"));
}

// ---------------------------------------------------------------- bad input

/// Small models of every type, fitted on synthetic images (16 taxels, 100 ms
/// windows every 10 ms) and saved in `dir`: `(type, file)`.
fn saved_models(dir: &Path) -> Vec<(&'static str, PathBuf)> {
    let items = synthetic_items(&[30.0, 75.0], 2, &SynthParams::small(), 3);
    let refs: Vec<&Item> = items.iter().collect();
    let fctx = FitContext {
        stage_id: "m",
        fold: 0,
        seed: 1,
    };
    let ann = AnnConfig {
        hidden: 4,
        max_epochs: 3,
        ..AnnConfig::default()
    };
    let edbn = EdbnConfig {
        layers: vec![6],
        epochs: 1,
        ..EdbnConfig::default()
    };
    let forest = RandomForestConfig {
        n_trees: 3,
        ..RandomForestConfig::default()
    };
    let fits = [
        ("ann", ann.fit_fold(&refs, &fctx)),
        ("edbn", edbn.fit_fold(&refs, &fctx)),
        ("svm", SvmConfig::default().fit_fold(&refs, &fctx)),
        ("random_forest", forest.fit_fold(&refs, &fctx)),
        ("knn", KnnConfig::default().fit_fold(&refs, &fctx)),
        ("logistic", LogisticConfig::default().fit_fold(&refs, &fctx)),
    ];
    fits.into_iter()
        .map(|(t, m)| {
            let f = dir.join(format!("{t}.model.json"));
            save_model(&m.unwrap(), &f).unwrap();
            (t, f)
        })
        .collect()
}

/// Loads a graph whose stage `est` (of `type_name`, with `keys`) reads an
/// `image_file` source; the text of the load errors about `est` (the
/// source's folder need not exist: its own error is left out).
fn load_error(dir: &Path, type_name: &str, keys: &str) -> String {
    palpate_stages::link();
    let text = format!(
        "[stages.images]\ntype = \"image_file\"\ndir = \"no-images-needed\"\n\
         [stages.est]\ntype = \"{type_name}\"\ninputs = [\"images\"]\n{keys}\n\
         [stages.mae]\ntype = \"mae\"\ninputs = [\"est\"]\n"
    );
    let opts = LoadOptions {
        base_dir: Some(dir.to_path_buf()),
        out: Some(dir.join("out")),
        ..LoadOptions::default()
    };
    match palpate_core::load_str(&text, "bad.toml", "bad", &opts) {
        Ok(_) => panic!("`{keys}` loaded"),
        Err(e) => {
            e.0.iter()
                .filter(|d| d.stage.as_deref() == Some("est"))
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join("\n")
        }
    }
}

fn ctx(dir: &Path) -> BuildContext {
    BuildContext {
        stage_id: "est".into(),
        seed: 1,
        out_dir: dir.join("out"),
        base_dir: dir.to_path_buf(),
    }
}

#[test]
fn every_trained_type_loads_its_own_model_and_refuses_bad_ones_naming_stage_key_and_file() {
    let dir = tmp("bad");
    let models = saved_models(&dir);
    // Relative to the graph's directory, every type builds with its own model.
    for (t, f) in &models {
        let name = f.file_name().unwrap().to_string_lossy().to_string();
        let cfg: Box<dyn StageConfig> =
            serde_json::from_value(serde_json::json!({ *t: { "model_in": name } })).unwrap();
        let Ok(Stage::Estimator(est)) = cfg.build(&ctx(&dir)) else {
            panic!("{t} builds with model_in")
        };
        assert!(!est.trained(), "{t}: a loaded model does not fit");
        let settings = serde_json::to_value(cfg.as_ref()).unwrap();
        assert!(
            matches!(stream::form(t, &settings, &ctx(&dir)), Ok(StreamForm::Streams(_))),
            "{t} streams with model_in"
        );
    }
    let check = |e: &str, want: &[&str]| {
        for w in want {
            assert!(e.contains(w), "`{w}` not in: {e}");
        }
    };
    // Missing file.
    let e = load_error(&dir, "ann", "model_in = \"nope.model.json\"");
    check(&e, &["est", "model_in", "nope.model.json", "save_model"]);
    // Bad JSON.
    std::fs::write(dir.join("bad.json"), "{\"format\": 3, \"classes\": [").unwrap();
    let e = load_error(&dir, "ann", "model_in = \"bad.json\"");
    check(
        &e,
        &["est", "model_in", "bad.json", "not a palpate baseline model"],
    );
    // Another stage type's model, each way round.
    for (t, f) in &models {
        let other = if *t == "ann" { "edbn" } else { "ann" };
        let name = f.file_name().unwrap().to_string_lossy().to_string();
        let e = load_error(&dir, other, &format!("model_in = {name:?}"));
        check(
            &e,
            &[
                "est",
                "model_in",
                &name,
                &format!("`{t}` stage"),
                &format!("`{other}`"),
            ],
        );
    }
    // A model inconsistent with itself: a class missing, a taxel count that
    // is not its classifier's, an unsorted class list, a kind tag edited.
    let text = std::fs::read_to_string(&models[0].1).unwrap();
    let json: serde_json::Value = serde_json::from_str(&text).unwrap();
    let edit = |name: &str, f: &dyn Fn(&mut serde_json::Value)| {
        let mut j = json.clone();
        f(&mut j);
        std::fs::write(dir.join(name), serde_json::to_string(&j).unwrap()).unwrap();
        load_error(&dir, "ann", &format!("model_in = {name:?}"))
    };
    let e = edit("one_class.json", &|j| j["classes"] = serde_json::json!([30.0]));
    check(&e, &["est", "model_in", "one_class.json", "classes"]);
    let e = edit("taxels.json", &|j| {
        j["features"]["n_taxels"] = serde_json::json!(9)
    });
    check(&e, &["est", "model_in", "taxels.json", "input size"]);
    let e = edit("unsorted.json", &|j| {
        j["classes"] = serde_json::json!([75.0, 30.0])
    });
    check(&e, &["est", "model_in", "unsorted.json", "increasing"]);
    let e = edit("params.json", &|j| {
        j["classifier"]["params"].as_array_mut().unwrap().pop();
    });
    check(&e, &["est", "model_in", "params.json", "parameter count"]);
    let e = edit("step.json", &|j| {
        j["features"]["step"] = serde_json::json!(1u64 << 60)
    });
    check(&e, &["est", "model_in", "step.json", "spans more than"]);
    let e = edit("kind.json", &|j| j["stage_type"] = serde_json::json!("edbn"));
    check(&e, &["est", "model_in", "kind.json", "`edbn` stage"]);
    // save_model beside model_in.
    let e = load_error(&dir, "ann", "model_in = \"ann.model.json\"\nsave_model = true");
    check(&e, &["est", "save_model", "model_in"]);
    // An empty path.
    let e = load_error(&dir, "knn", "model_in = \"\"");
    check(&e, &["est", "model_in", "empty"]);
    // A file too large to be a model (sparse: no disk used) is refused
    // before it is read.
    std::fs::File::create(dir.join("huge.json"))
        .unwrap()
        .set_len((1 << 30) + 1)
        .unwrap();
    let e = load_error(&dir, "ann", "model_in = \"huge.json\"");
    check(&e, &["est", "model_in", "huge.json", "a model file may have"]);

    // Images the model was not trained on: 9 taxels, another hop. Batch and
    // streamed, each error names the key and the file.
    let meta = TrialMeta {
        trial_id: "t".into(),
        ..TrialMeta::default()
    };
    let tctx = TrialContext {
        stage_id: "est",
        meta: &meta,
        seed: 1,
    };
    let good = synthetic_items(&[30.0], 1, &SynthParams::small(), 9)[0]
        .payload
        .images()
        .unwrap()
        .as_ref()
        .clone();
    let nine = SpikeImages {
        layout: TaxelLayout::Grid {
            rows: 3,
            cols: 3,
            pitch_mm: 4.0,
            taxel_mm: 2.0,
        },
        counts: vec![1.0; good.n_frames * 9],
        ..good.clone()
    };
    let hop = SpikeImages {
        hop_ms: 20.0,
        ..good.clone()
    };
    // 16 taxels as the model's 4 x 4 grid, but in a 2 x 8 strip: the count
    // agrees, the taxels are not the ones the model learnt.
    let strip = SpikeImages {
        layout: TaxelLayout::Grid {
            rows: 2,
            cols: 8,
            pitch_mm: 3.0,
            taxel_mm: 2.0,
        },
        ..good.clone()
    };
    // The model's grid at another pitch, its taxels given as positions: the
    // same arrangement, accepted.
    let wide = SpikeImages {
        layout: TaxelLayout::Positions {
            positions_mm: good
                .layout
                .positions()
                .iter()
                .map(|p| [2.0 * p[0] + 1.0, 2.0 * p[1]])
                .collect(),
            taxel_mm: 2.0,
        },
        ..good.clone()
    };
    for (t, f) in &models {
        let name = f.file_name().unwrap().to_string_lossy().to_string();
        let cfg: Box<dyn StageConfig> =
            serde_json::from_value(serde_json::json!({ *t: { "model_in": name } })).unwrap();
        let Ok(Stage::Estimator(est)) = cfg.build(&ctx(&dir)) else {
            panic!("{t} builds")
        };
        let model = est
            .fit(
                &[],
                &FitContext {
                    stage_id: "est",
                    fold: 0,
                    seed: 1,
                },
            )
            .unwrap();
        let settings = serde_json::to_value(cfg.as_ref()).unwrap();
        let Ok(StreamForm::Streams(s)) = stream::form(t, &settings, &ctx(&dir)) else {
            panic!("{t} streams")
        };
        for (images, want) in [(&nine, "9 taxels"), (&hop, "hop"), (&strip, "a 2 x 8 grid")] {
            let item = Item {
                meta: Arc::new(meta.clone()),
                payload: images.clone().into(),
            };
            let e = model.predict(&item, &tctx).unwrap_err().to_string();
            check(&e, &["model_in", &name, want]);
            let e = stream::run_blocks(s.as_ref(), &[images.clone().into()], &tctx)
                .unwrap_err()
                .to_string();
            check(&e, &["model_in", &name, want]);
        }
        // The good images predict, batch and streamed alike.
        let item = Item {
            meta: Arc::new(meta.clone()),
            payload: good.clone().into(),
        };
        let b = model.predict(&item, &tctx).unwrap();
        let out = stream::run_blocks(s.as_ref(), &[good.clone().into()], &tctx).unwrap();
        assert_eq!(out.last().unwrap().estimate().unwrap().as_ref(), &b, "{t}");
        let item = Item {
            meta: Arc::new(meta.clone()),
            payload: wide.clone().into(),
        };
        model.predict(&item, &tctx).unwrap();
    }
    let _ = std::fs::remove_dir_all(&dir);
}
