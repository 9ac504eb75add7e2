//! End to end through the real stages: the ideal scene, FA-I encoding and WSS.

use palpate::core::{self, LoadOptions, RunOptions};
use std::path::Path;

fn run_quickstart(overrides: &[(&str, &str)]) -> Vec<(f64, Option<f64>)> {
    palpate::link();
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("graphs/quickstart.toml");
    let mut set = vec![
        LoadOptions::parse_set("stages.scene.file=scenes/ideal.toml").unwrap(),
        LoadOptions::parse_set("stages.scene.trials_per_angle=1").unwrap(),
    ];
    for (k, v) in overrides {
        set.push(LoadOptions::parse_set(&format!("{k}={v}")).unwrap());
    }
    let out = std::env::temp_dir().join(format!(
        "palpate-pipeline-{}-{}",
        std::process::id(),
        overrides.len()
    ));
    let g = core::load_file(
        &path,
        &LoadOptions {
            overrides: set,
            out: Some(out.clone()),
            base_dir: None,
        },
    )
    .unwrap();
    let r = core::run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..Default::default()
        },
    )
    .unwrap();
    let _ = std::fs::remove_dir_all(out);
    r.outputs["wss"]
        .iter()
        .map(|i| {
            (
                i.meta.label.angle_deg.unwrap(),
                i.payload.estimate().unwrap().angle_deg,
            )
        })
        .collect()
}

/// Every one of the paper's 17 classes of the ideal scene is estimated exactly
/// through the real pipeline (scene -> filter -> normalize -> FA-I drive ->
/// Izhikevich -> bins -> WSS) with constant and with 1 + SR weights.
///
/// With the paper's 1 - SR weights the ideal scene is NOT exact (a few classes
/// go 5 degrees high): on that scene a taxel fires only while the edge is over
/// its own area, so a template's span holds spike-free frames (correlation 0),
/// and 1 - SR gives exactly those frames its largest weight, diluting longer
/// templates (smaller angles) more. No template width or shape fixes it; the
/// lab scene's skin spread fills those frames (see the WSS module docs, and
/// why WSS's default weighting is constant). This test pins that finding too,
/// so a change to it is noticed.
#[test]
fn ideal_scene_is_estimated_exactly_with_constant_and_one_plus_sr_weights() {
    for w in ["constant", "one_plus_sr"] {
        let est = run_quickstart(&[("stages.wss.weighting", w)]);
        assert_eq!(est.len(), 17);
        for (truth, e) in est {
            assert_eq!(e, Some(truth), "weighting {w}: class {truth} estimated as {e:?}");
        }
    }
    let est = run_quickstart(&[("stages.wss.weighting", "one_minus_sr")]);
    let wrong: Vec<f64> = est
        .iter()
        .filter(|(t, e)| *e != Some(*t))
        .map(|(t, _)| *t)
        .collect();
    assert!(
        !wrong.is_empty() && wrong.len() <= 6,
        "1 - SR on the ideal scene: wrong classes {wrong:?}"
    );
    for (t, e) in &est {
        assert!((e.unwrap() - t).abs() <= 5.0 + 1e-9, "{t}: {e:?}");
    }
}
