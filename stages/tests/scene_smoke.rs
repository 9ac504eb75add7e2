use palpate_core::{load_str, run, LoadOptions, RunOptions};

#[test]
fn smoke() {
    palpate_stages::link();
    let g = load_str(
        "[run]\nseed = 1\n[stages.scene]\ntype = \"scene\"\nangles = [90, 45]\ntrials_per_angle = 2\n",
        "t.toml",
        "t",
        &LoadOptions::default(),
    )
    .unwrap();
    let r = run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..Default::default()
        },
    )
    .unwrap();
    let items = &r.outputs["scene"];
    for it in items.iter() {
        let s = it.payload.signals().unwrap();
        println!(
            "{} {:?} n={} unit={}",
            it.meta.trial_id,
            it.meta.crossing_ms,
            s.n_samples(),
            s.unit
        );
    }
}
