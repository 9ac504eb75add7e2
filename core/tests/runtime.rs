//! Running graphs: leave-one-trial-out never trains on a test trial, results do
//! not depend on the number of threads, and failures name the stage and trial.

mod common;
use common::{answers_of, load, outputs, Answer, SERIAL, TRAINED_ON};
use std::collections::HashSet;

const GRAPH: &str = r#"
[run]
seed = 11

[stages.src]
type = "t_source"
classes = 4
reps = 5
samples = 200

[stages.est]
type = "t_estimator"
inputs = ["src"]

[stages.sink]
type = "t_sink"
inputs = ["est"]
"#;

#[test]
fn leave_one_trial_out_never_sees_a_test_trial_and_tests_each_once() {
    let g = load(GRAPH).unwrap();
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    TRAINED_ON.lock().unwrap().clear();
    let est = outputs(&g);
    assert_eq!(est.len(), 20);
    let trained = TRAINED_ON.lock().unwrap().clone();
    assert_eq!(trained.len(), 5, "one fit per repetition");
    for (fold, ids) in &trained {
        assert_eq!(ids.len(), 16);
        // Fold f holds out repetition f of every class.
        for id in ids {
            assert!(!id.ends_with(&format!("-r{fold}")), "fold {fold} trained on {id}");
        }
    }
    let all: HashSet<&str> = est.iter().map(|i| i.meta.trial_id.as_str()).collect();
    assert_eq!(all.len(), 20);
    // Provenance records every stage, source first.
    let p: Vec<&str> = est[0].meta.provenance.iter().map(|p| p.stage.as_str()).collect();
    assert_eq!(p, ["src", "est"]);
    assert_eq!(est[0].meta.provenance[0].settings["t_source"]["samples"], 200);
}

fn run_on(threads: usize) -> Vec<Answer> {
    let g = load(GRAPH).unwrap();
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let est = pool.install(|| outputs(&g));
    answers_of(&est)
}

#[test]
fn one_and_two_threads_give_identical_bits() {
    let a = run_on(1);
    let b = run_on(2);
    assert_eq!(a, b);
    // And the seed matters: another seed gives other scores.
    let g = load(&GRAPH.replace("seed = 11", "seed = 12")).unwrap();
    let c: Vec<Vec<u64>> = outputs(&g)
        .iter()
        .map(|i| {
            i.payload
                .estimate()
                .unwrap()
                .scores
                .iter()
                .map(|s| s.score.to_bits())
                .collect()
        })
        .collect();
    assert_ne!(a.iter().map(|x| x.2.clone()).collect::<Vec<_>>(), c);
}

#[test]
fn a_trained_estimator_with_one_repetition_is_a_clear_error() {
    let g = load(&GRAPH.replace("reps = 5", "reps = 1")).unwrap();
    let e = palpate_core::run(&g, &Default::default()).unwrap_err();
    assert_eq!(e.stage, "est");
    assert!(e.message.contains("two repetitions"), "{e}");
}

#[test]
fn timings_cover_every_trial_and_fold() {
    let g = load(GRAPH).unwrap();
    let r = palpate_core::run(&g, &Default::default()).unwrap();
    let t: Vec<(&str, usize, usize)> = r
        .timings
        .iter()
        .map(|t| (t.id.as_str(), t.per_trial.len(), t.fits.len()))
        .collect();
    assert_eq!(t, [("src", 20, 0), ("est", 20, 5), ("sink", 0, 0)]);
    assert_eq!(r.reports[0].1.metrics, vec![("est.n".to_string(), 20.0)]);
}
