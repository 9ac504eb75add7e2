//! Trained baselines through the runtime and under arbitrary input: the same
//! bits on 1 and 2 rayon threads (fold fitting, the SVM's parallel pairs and
//! prediction all run in parallel), and property tests of hard inputs (all-zero
//! frames, huge counts) that must never give NaN scores or a panic.

use palpate_core::{Item, LoadOptions, RunOptions, SpikeImages, TaxelLayout};
use palpate_stages::estimate::ann::{AnnConfig, AnnInput};
use palpate_stages::estimate::classic::KnnConfig;
use palpate_stages::estimate::edbn::{EdbnConfig, Inference};
use palpate_stages::estimate::features::{synthetic_items, FittedModel, SynthParams};
use proptest::prelude::*;
use std::path::Path;
use std::sync::OnceLock;

/// A small scene (3 angles x 3 trials, fast slide) through the FA-I pipeline
/// into every trained baseline, with small training settings.
const GRAPH: &str = r#"
[run]
seed = 5

[stages.scene]
type = "scene"
file = "scenes/ideal.toml"
angles = [30, 60, 90]
trials_per_angle = 3
effects = [{ kind = "variation", speed_rel_sd = 0.05, start_sd_mm = 0.3 }, { kind = "noise", sigma = 0.002 }]
[stages.scene.motion]
speed_mm_s = 10.0
hold_before_s = 0.3
hold_after_s = 0.3

[stages.norm]
type = "normalize"
inputs = ["scene"]

[stages.lowpass]
type = "lowpass"
inputs = ["norm"]

[stages.drive]
type = "drive"
inputs = ["lowpass"]

[stages.enc]
type = "izhikevich"
inputs = ["drive"]
preset = "fa_i"

[stages.bins]
type = "bin"
inputs = ["enc"]
window_ms = 100.0
hop_ms = 10.0

[stages.ann]
type = "ann"
inputs = ["bins"]
max_epochs = 5
max_train_frames = 10

[stages.edbn]
type = "edbn"
inputs = ["bins"]
layers = [16, 8]
epochs = 3
max_train_frames = 10

[stages.edbn_spiking]
type = "edbn"
inputs = ["bins"]
layers = [16, 8]
epochs = 2
max_train_frames = 10
inference = "spiking"
duration_ms = 20.0

[stages.svm]
type = "svm"
inputs = ["bins"]
frames = 2

[stages.knn]
type = "knn"
inputs = ["bins"]
k = 3
max_train_frames = 10
"#;

const ESTIMATORS: [&str; 5] = ["ann", "edbn", "edbn_spiking", "svm", "knn"];

fn estimates_on(threads: usize) -> Vec<String> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(|| {
            let opts = LoadOptions {
                base_dir: Some(Path::new(env!("CARGO_MANIFEST_DIR")).join("../graphs")),
                ..LoadOptions::default()
            };
            let g = palpate_core::load_str(GRAPH, "det.toml", "det", &opts).unwrap();
            let r = palpate_core::run(
                &g,
                &RunOptions {
                    keep_outputs: true,
                    ..Default::default()
                },
            )
            .unwrap();
            ESTIMATORS
                .iter()
                .flat_map(|id| {
                    r.outputs[*id].iter().map(move |it| {
                        let e = it.payload.estimate().unwrap();
                        assert!(e.scores.iter().all(|s| s.score.is_finite()), "{id}: {e:?}");
                        // Debug prints the shortest round-trip form of every f64:
                        // equal strings are equal bits.
                        format!("{id} {} {e:?}", it.meta.trial_id)
                    })
                })
                .collect()
        })
}

#[test]
fn trained_estimates_are_the_same_bits_on_one_or_two_threads() {
    let one = estimates_on(1);
    let two = estimates_on(2);
    assert_eq!(one.len(), ESTIMATORS.len() * 9);
    assert_eq!(one, two);
    // Not vacuous: the trained models do answer.
    assert!(one.iter().any(|s| s.contains("angle_deg: Some")), "{one:?}");
}

/// Models fitted once (small synthetic set) for the property tests.
fn models() -> &'static Vec<FittedModel> {
    static M: OnceLock<Vec<FittedModel>> = OnceLock::new();
    M.get_or_init(|| {
        let items = synthetic_items(&[20.0, 50.0, 80.0], 3, &SynthParams::small(), 3);
        let train: Vec<&Item> = items.iter().collect();
        let ctx = palpate_core::FitContext {
            stage_id: "prop",
            fold: 0,
            seed: 9,
        };
        let ann = AnnConfig {
            max_epochs: 3,
            max_train_frames: 10,
            ..AnnConfig::default()
        };
        let ann_s = AnnConfig {
            input: AnnInput::Spatial,
            ..ann.clone()
        };
        let edbn = EdbnConfig {
            layers: vec![12, 6],
            epochs: 2,
            max_train_frames: 10,
            ..EdbnConfig::default()
        };
        let edbn_spiking = EdbnConfig {
            inference: Inference::Spiking,
            duration_ms: 10.0,
            ..edbn.clone()
        };
        let knn = KnnConfig {
            k: 3,
            max_train_frames: 10,
            ..KnnConfig::default()
        };
        vec![
            ann.fit_model(&train, &ctx).unwrap(),
            ann_s.fit_model(&train, &ctx).unwrap(),
            edbn.fit_model(&train, &ctx).unwrap(),
            edbn_spiking.fit_model(&train, &ctx).unwrap(),
            knn.fit_model(&train, &ctx).unwrap(),
        ]
    })
}

/// A count: mostly zero, else small, else huge (up to f64::MAX).
fn count() -> impl Strategy<Value = f64> {
    prop_oneof![
        4 => Just(0.0),
        3 => 0.0f64..20.0,
        1 => prop_oneof![Just(1e300), Just(f64::MAX), 1e6f64..1e12],
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    #[test]
    fn arbitrary_counts_never_give_nan_or_panic(
        frames in prop::collection::vec(
            prop_oneof![
                1 => Just(vec![0.0; 16]),
                3 => prop::collection::vec(count(), 16),
            ],
            1..40,
        ),
        seed in any::<u64>(),
    ) {
        let images = SpikeImages {
            layout: TaxelLayout::paper(),
            window_ms: 100.0,
            hop_ms: 10.0,
            n_frames: frames.len(),
            counts: frames.concat(),
        };
        for m in models() {
            let e = m.predict_images(&images, seed, "prop").unwrap();
            prop_assert!(e.scores.iter().all(|s| s.score.is_finite() && s.score >= 0.0), "{}: {:?}", m.stage_type, e);
            if let Some(a) = e.angle_deg {
                prop_assert!(m.classes.contains(&a));
            }
            // A trial whose frames are all zero is "no edge".
            if images.counts.iter().all(|c| *c == 0.0) {
                prop_assert_eq!(e.angle_deg, None);
            }
        }
    }
}
