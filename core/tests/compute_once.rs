//! An output read by several stages is computed once.

mod common;
use common::{load, SCALE_CALLS};
use std::sync::atomic::Ordering;

#[test]
fn a_shared_output_is_computed_once() {
    let text = r#"
[stages.src]
type = "t_source"
classes = 2
reps = 3
samples = 20

[stages.scale]
type = "t_scale"
inputs = ["src"]

[stages.est]
type = "t_estimator"
inputs = ["scale"]

[stages.est2]
type = "t_estimator"
inputs = ["scale"]

[stages.sink]
type = "t_sink"
inputs = ["est", "est2"]
"#;
    let g = load(text).unwrap();
    SCALE_CALLS.store(0, Ordering::SeqCst);
    let r = palpate_core::run(&g, &Default::default()).unwrap();
    assert_eq!(
        SCALE_CALLS.load(Ordering::SeqCst),
        6,
        "one call per trial, not per reader"
    );
    assert_eq!(r.reports[0].1.metrics.len(), 2);
}
