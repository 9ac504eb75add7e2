//! Trained baselines on a paper-sized synthetic set (17 classes x 10 trials,
//! 2 mm/s, ~1000-4000 frames of 4x4 per trial): one fold's fit (train on 9
//! repetitions, predict the 17 held-out trials) per estimator.
//!
//! `CARGO_TARGET_DIR=... cargo bench --bench baselines`

use criterion::{criterion_group, criterion_main, Criterion};
use palpate_core::StageError;
use palpate_core::{FitContext, Item};
use palpate_stages::estimate::ann::{AnnConfig, AnnInput};
use palpate_stages::estimate::classic::{KnnConfig, LogisticConfig, RandomForestConfig, SvmConfig};
use palpate_stages::estimate::edbn::EdbnConfig;
use palpate_stages::estimate::features::{synthetic_items, FittedModel, SynthParams};
use std::time::Duration;

fn fold(items: &[Item], fit: &dyn Fn(&[&Item], &FitContext<'_>) -> Result<FittedModel, StageError>) -> usize {
    let train: Vec<&Item> = items.iter().filter(|it| it.meta.group != 0).collect();
    let ctx = FitContext {
        stage_id: "bench",
        fold: 0,
        seed: 1,
    };
    let m = fit(&train, &ctx).expect("fit");
    items
        .iter()
        .filter(|it| it.meta.group == 0)
        .filter(|it| {
            let e = m.predict_images(it.payload.images().unwrap(), 3, "t").unwrap();
            e.angle_deg == it.meta.label.angle_deg
        })
        .count()
}

fn bench(c: &mut Criterion) {
    let angles: Vec<f64> = (0..17).map(|k| 10.0 + 5.0 * k as f64).collect();
    let items = synthetic_items(&angles, 10, &SynthParams::paper(), 11);
    let mut g = c.benchmark_group("baselines_fold");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(8))
        .warm_up_time(Duration::from_secs(1));
    let ann_st = AnnConfig::default();
    let ann_s = AnnConfig {
        input: AnnInput::Spatial,
        ..AnnConfig::default()
    };
    let edbn = EdbnConfig::default();
    let svm = SvmConfig::default();
    let rf = RandomForestConfig::default();
    let knn = KnnConfig::default();
    let logistic = LogisticConfig::default();
    let fits: Vec<(
        &str,
        Box<dyn Fn(&[&Item], &FitContext<'_>) -> Result<FittedModel, StageError>>,
    )> = vec![
        ("ann_st", Box::new(move |t, c| ann_st.fit_model(t, c))),
        ("ann_s", Box::new(move |t, c| ann_s.fit_model(t, c))),
        ("edbn", Box::new(move |t, c| edbn.fit_model(t, c))),
        ("svm", Box::new(move |t, c| svm.fit_model(t, c))),
        ("random_forest", Box::new(move |t, c| rf.fit_model(t, c))),
        ("knn", Box::new(move |t, c| knn.fit_model(t, c))),
        ("logistic", Box::new(move |t, c| logistic.fit_model(t, c))),
    ];
    for (name, f) in &fits {
        eprintln!("{name}: fold 0 correct {}/17", fold(&items, f.as_ref()));
        g.bench_function(*name, |b| b.iter(|| fold(&items, f.as_ref())));
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
