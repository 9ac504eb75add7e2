//! Training time of the paper's trained baselines, one fold on a paper-sized
//! synthetic set (17 classes x 10 trials at 2 mm/s, ~1000-4000 frames of 4x4
//! per trial; train on 9 repetitions = 153 trials) with each estimator's
//! defaults: ANN (S), ANN (ST), EDBN (rate inference), and the classical
//! SVM (exact SMO), random forest, k-NN and logistic regression. The held-out
//! accuracy of the fold is printed once, so a fast but broken fit shows.
//!
//! `CARGO_TARGET_DIR=... cargo bench --bench baselines`

use criterion::{criterion_group, criterion_main, Criterion};
use palpate_core::{FitContext, Item, StageError};
use palpate_stages::estimate::ann::{AnnConfig, AnnInput};
use palpate_stages::estimate::classic::{KnnConfig, LogisticConfig, RandomForestConfig, SvmConfig};
use palpate_stages::estimate::edbn::EdbnConfig;
use palpate_stages::estimate::features::{synthetic_items, FittedModel, SynthParams};
use std::time::Duration;

type Fit = Box<dyn Fn(&[&Item], &FitContext<'_>) -> Result<FittedModel, StageError>>;

fn ctx() -> FitContext<'static> {
    FitContext {
        stage_id: "bench",
        fold: 0,
        seed: 1,
    }
}

fn bench(c: &mut Criterion) {
    let angles: Vec<f64> = (0..17).map(|k| 10.0 + 5.0 * k as f64).collect();
    let items = synthetic_items(&angles, 10, &SynthParams::paper(), 11);
    let train: Vec<&Item> = items.iter().filter(|it| it.meta.group != 0).collect();
    let test: Vec<&Item> = items.iter().filter(|it| it.meta.group == 0).collect();
    let ann_st = AnnConfig::default();
    let ann_s = AnnConfig {
        input: AnnInput::Spatial,
        ..AnnConfig::default()
    };
    let edbn = EdbnConfig::default();
    let fits: Vec<(&str, Fit)> = vec![
        ("ann_s", Box::new(move |t, c| ann_s.fit_model(t, c))),
        ("ann_st", Box::new(move |t, c| ann_st.fit_model(t, c))),
        ("edbn", Box::new(move |t, c| edbn.fit_model(t, c))),
        ("svm", Box::new(|t, c| SvmConfig::default().fit_model(t, c))),
        (
            "random_forest",
            Box::new(|t, c| RandomForestConfig::default().fit_model(t, c)),
        ),
        ("knn", Box::new(|t, c| KnnConfig::default().fit_model(t, c))),
        (
            "logistic",
            Box::new(|t, c| LogisticConfig::default().fit_model(t, c)),
        ),
    ];
    let mut g = c.benchmark_group("baselines_fit_fold");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(10))
        .warm_up_time(Duration::from_secs(1));
    for (name, fit) in &fits {
        let m = fit(&train, &ctx()).expect("fit");
        let correct = test
            .iter()
            .filter(|it| {
                let e = m.predict_images(it.payload.images().unwrap(), 3, "t").unwrap();
                e.angle_deg == it.meta.label.angle_deg
            })
            .count();
        eprintln!(
            "{name}: {} training vectors, fold 0 correct {correct}/17",
            m.log.n_train
        );
        g.bench_function(*name, |b| b.iter(|| fit(&train, &ctx()).expect("fit")));
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
