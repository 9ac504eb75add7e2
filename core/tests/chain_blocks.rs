//! A per-trial chain runs its estimators for blocks of trials after the
//! stages before them (so an estimator's working set stays in cache): the
//! answers are those of running every stage over every trial in turn, and
//! when trials fail, the first failing trial in trial order is reported
//! with its first failing stage, as if trials ran one at a time.

mod common;
use common::{answers_of, load, Answer};
use palpate_core::{run, Cache, RunOptions};

/// 4 x 5 = 20 trials (ids c0-r0 .. c3-r4 in trial order): more than two
/// blocks of the chain's 8 trials, the last one partial.
const GRAPH: &str = r#"
[run]
seed = 5

[stages.src]
type = "t_source"
classes = 4
reps = 5
samples = 50

[stages.scale]
type = "t_scale"
inputs = ["src"]

[stages.est]
type = "t_fixed"
inputs = ["scale"]

[stages.sink]
type = "t_sink"
inputs = ["est"]
"#;

fn answers(cache: Option<&Cache>, graph: &str) -> Vec<Answer> {
    let g = load(graph).unwrap();
    let r = run(
        &g,
        &RunOptions {
            keep_outputs: true,
            cache,
            ..RunOptions::default()
        },
    )
    .unwrap();
    answers_of(&r.outputs["est"])
}

#[test]
fn blocked_chain_gives_the_answers_of_stage_at_a_time_in_trial_order() {
    let chain = answers(None, GRAPH);
    // Under a sweep cache every stage runs over every trial in turn.
    let cache = Cache::default();
    let staged = answers(Some(&cache), GRAPH);
    assert_eq!(chain.len(), 20);
    assert_eq!(chain, staged);
    let ids: Vec<&str> = chain.iter().map(|a| a.0.as_str()).collect();
    assert_eq!(ids[8], "c1-r3");
    assert_eq!(ids[19], "c3-r4");
    // Not all one answer: the test can tell trials apart.
    assert!(chain.iter().any(|a| a.2 != chain[0].2));
}

fn failure(scale_fails: &str, est_fails: &str) -> (String, Option<String>) {
    let graph = GRAPH
        .replace(
            "inputs = [\"src\"]\n",
            &format!("inputs = [\"src\"]\nfail_on = \"{scale_fails}\"\n"),
        )
        .replace(
            "inputs = [\"scale\"]\n",
            &format!("inputs = [\"scale\"]\nfail_on = \"{est_fails}\"\n"),
        );
    let g = load(&graph).unwrap();
    let on = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let e = pool.install(|| run(&g, &RunOptions::default())).unwrap_err();
        (e.stage, e.trial)
    };
    let one = on(1);
    assert_eq!(one, on(2), "1 and 2 threads report the same failure");
    one
}

#[test]
fn the_first_failing_trial_is_reported_whichever_part_of_the_chain_fails() {
    // Trials 9 (c1-r4) and 10 (c2-r0) share the block 8..16. The map fails
    // on the later trial, which in the block runs before the estimator's
    // failure on the earlier one: the earlier trial is still the one reported.
    assert_eq!(
        failure("c2-r0", "c1-r4"),
        ("est".to_string(), Some("c1-r4".to_string()))
    );
    assert_eq!(
        failure("c1-r4", "c2-r0"),
        ("scale".to_string(), Some("c1-r4".to_string()))
    );
    // Both fail on one trial: the stage first in graph order.
    assert_eq!(
        failure("c1-r4", "c1-r4"),
        ("scale".to_string(), Some("c1-r4".to_string()))
    );
    // Across blocks: trial 7 (last of block 0) before trial 8.
    assert_eq!(
        failure("c1-r3", "c1-r2"),
        ("est".to_string(), Some("c1-r2".to_string()))
    );
}
