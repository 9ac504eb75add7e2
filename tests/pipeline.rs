//! End to end through the real stages: the ideal scene, FA-I encoding and WSS.

use palpate::core::{self, LoadOptions, RunOptions};
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Tests of this file run in parallel: each run gets its own output folder.
static RUNS: AtomicUsize = AtomicUsize::new(0);

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
        RUNS.fetch_add(1, Ordering::Relaxed)
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

/// The physics, the layout, the templates and every refinement respect the
/// array's mirror symmetry: an edge at `180 - θ` is the edge at `θ` seen
/// with the rows flipped, so on a scene without random draws its estimate
/// must be `180 - ` the estimate at `θ`, whatever the answer's bias. Checked
/// on a non-square 3 x 5 array, at angles between the classes, with every
/// deterministic effect of the lab scene (skin, edge stress, creep, the
/// piezoresistive divider, row and column crosstalk, the ADC; not the hum,
/// whose phase is drawn per trial, nor the other random effects), for the
/// grid class and the `search` and `timing` refinements. A sign slip in
/// the taxel rows, the templates' angle convention or the arrival-time
/// plane breaks it at once.
#[test]
fn mirrored_edges_get_mirrored_estimates() {
    let effects = r#"[
        { kind = "skin", sigma_mm = 0.5 },
        { kind = "stress", peak = 0.3, depth_mm = 0.3, width_mm = 0.2 },
        { kind = "creep", fraction = 0.1, tau_s = 0.5 },
        { kind = "piezo", v_open = 3.3, v_contact = 1.75, exponent = 1.0 },
        { kind = "crosstalk", row = 0.02, col = 0.02 },
        { kind = "adc", bits = 12, min = 0.0, max = 3.3 },
    ]"#
    .replace('\n', " ");
    let low = [12.5, 33.3, 47.0, 60.0, 71.9, 88.8];
    let list = |a: &[f64]| format!("{a:?}");
    let high: Vec<f64> = low.iter().map(|a| 180.0 - a).collect();
    for refine in ["none", "search", "timing"] {
        let refine = format!("\"{refine}\"");
        let run = |angles: &str| {
            run_quickstart(&[
                ("stages.scene.effects", &effects),
                ("stages.scene.array.rows", "3"),
                ("stages.scene.array.cols", "5"),
                ("stages.scene.angles", angles),
                ("stages.wss.angles", "{ from = 10, to = 170, step = 5 }"),
                ("stages.wss.refine", &refine),
            ])
        };
        let (lo, hi) = (run(&list(&low)), run(&list(&high)));
        assert_eq!(lo.len(), low.len());
        assert_eq!(hi.len(), high.len());
        for ((t, e), (tm, em)) in lo.iter().zip(&hi) {
            assert!((t + tm - 180.0).abs() < 1e-9, "trial order: {t} against {tm}");
            let (e, em) = (e.expect("an estimate"), em.expect("an estimate"));
            assert!(
                (e - (180.0 - em)).abs() < 1e-9,
                "refine {refine}: {t} deg estimated as {e}, its mirror {tm} deg as {em}"
            );
        }
    }
}

/// Small arrays (three rows or fewer) on the ideal scene: the grid class
/// drifts one step towards 90 degrees for some classes (eq. 5's end effect,
/// documented in the WSS module), never further and never the other way,
/// while `refine = "timing"`, the remedy the docs give, stays within half a
/// degree of every true angle. Pins both the finding and the advice.
#[test]
fn small_arrays_drift_one_class_towards_90_and_timing_does_not() {
    for (rows, cols) in [("3", "3"), ("2", "6")] {
        let geometry = [
            ("stages.wss.weighting", "constant"),
            ("stages.scene.array.rows", rows),
            ("stages.scene.array.cols", cols),
        ];
        let grid = run_quickstart(&geometry);
        assert_eq!(grid.len(), 17);
        let off: Vec<(f64, f64)> = grid
            .iter()
            .map(|&(t, e)| (t, e.expect("an estimate")))
            .filter(|(t, e)| e != t)
            .collect();
        assert!(
            !off.is_empty(),
            "{rows} x {cols}: every class exact, the documented drift is gone"
        );
        for &(t, e) in &off {
            assert!(
                e == t + 5.0,
                "{rows} x {cols}: class {t} answered {e}, not one step towards 90"
            );
        }
        let mut timed = geometry.to_vec();
        timed.push(("stages.wss.refine", "\"timing\""));
        let timed = run_quickstart(&timed);
        assert_eq!(timed.len(), 17);
        for (t, e) in timed {
            let e = e.expect("an estimate");
            assert!(
                (e - t).abs() <= 0.5,
                "{rows} x {cols}, timing: {t} deg estimated as {e}"
            );
        }
    }
}
