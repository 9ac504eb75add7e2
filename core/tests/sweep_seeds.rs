//! A sweep's repeat seeds `seed + r` never wrap: a range past `u64::MAX`
//! (`run.seed = "18446744073709551615"` with 3 repeats used to run at seeds
//! MAX, 0 and 1) is an error naming `run.seed` and `sweep.repeats`, for the
//! base seed and for a swept one; a range that ends at `u64::MAX` runs.

mod common;
use common::load;
use palpate_core::sweep::{load_points, repeat_seeds};
use palpate_core::LoadOptions;

const BASE: &str = r#"
[stages.src]
type = "t_source"
classes = 2
reps = 2
samples = 20

[stages.est]
type = "t_estimator"
inputs = ["src"]

[stages.sink]
type = "t_sink"
inputs = ["est"]
"#;

/// Every (point, repeat) seed of the graph `run` + `sweep` tables, or the
/// load error's text.
fn seeds(run: &str, sweep: &str) -> Result<Vec<u64>, String> {
    let text = format!("{run}\n{BASE}\n{sweep}");
    let base = load(&text).map_err(|e| e.to_string())?;
    let opts = LoadOptions {
        out: Some(base.out_dir.clone()),
        ..Default::default()
    };
    let s = base.sweep.clone().expect("a sweep");
    load_points(&text, "t.toml", "t", &opts, &base, &s)
        .map(|g| g.iter().map(|(_, _, g)| g.run.seed).collect())
        .map_err(|e| e.to_string())
}

#[test]
fn repeat_seeds_past_u64_max_are_refused_not_wrapped() {
    let max = u64::MAX;
    let e = seeds("[run]\nseed = \"18446744073709551615\"", "[sweep]\nrepeats = 3").unwrap_err();
    assert!(
        e.contains("`run.seed` = 18446744073709551615")
            && e.contains("`sweep.repeats` = 3")
            && e.contains("at most 18446744073709551613"),
        "{e}"
    );
    // Ending exactly at the largest seed is fine.
    assert_eq!(
        seeds("[run]\nseed = \"18446744073709551613\"", "[sweep]\nrepeats = 3").unwrap(),
        [max - 2, max - 1, max]
    );
    assert_eq!(
        seeds("[run]\nseed = \"18446744073709551615\"", "[sweep]\nrepeats = 1").unwrap(),
        [max]
    );
    // A swept seed: the point that overflows is named by its value.
    let e = seeds(
        "",
        "[sweep]\nkey = \"run.seed\"\nvalues = [1, \"18446744073709551614\"]\nrepeats = 3",
    )
    .unwrap_err();
    assert!(
        e.contains("run.seed = \"18446744073709551614\"") && e.contains("`sweep.repeats` = 3"),
        "{e}"
    );
    assert_eq!(
        seeds("", "[sweep]\nkey = \"run.seed\"\nvalues = [1, 7]\nrepeats = 2").unwrap(),
        [1, 2, 7, 8]
    );
    assert_eq!(repeat_seeds(max, 1), Some(max..=max));
    assert_eq!(repeat_seeds(max, 2), None);
    assert_eq!(repeat_seeds(5, 3), Some(5..=7));
}
