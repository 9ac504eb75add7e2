//! Integration tests of the `scene` source: geometry, the ideal response,
//! every effect's claim, scene files, determinism across thread counts, and
//! the NPY/CSV export.

#![allow(clippy::needless_range_loop)] // taxel-indexed loops read like the maths
use palpate_core::geometry::Edge;
use palpate_core::{load_str, run, Item, LoadOptions, RunOptions};
use palpate_stages::scene::field::TaxelShape;
use palpate_stages::scene::{SceneConfig, Simulator};
use std::path::{Path, PathBuf};
use std::sync::Arc;

fn graph(stage_keys: &str, seed: u64) -> String {
    format!("[run]\nseed = {seed}\n[stages.scene]\ntype = \"scene\"\n{stage_keys}\n")
}

fn items_in(text: &str, base: Option<&Path>) -> Arc<Vec<Item>> {
    palpate_stages::link();
    let opts = LoadOptions::default();
    let g = match base {
        Some(dir) => {
            let path = dir.join("g.toml");
            std::fs::write(&path, text).unwrap();
            palpate_core::load_file(&path, &opts).unwrap_or_else(|e| panic!("{e}"))
        }
        None => load_str(text, "test.toml", "test", &opts).unwrap_or_else(|e| panic!("{e}")),
    };
    let r = run(
        &g,
        &RunOptions {
            keep_outputs: true,
            ..Default::default()
        },
    )
    .unwrap();
    r.outputs["scene"].clone()
}

fn items(stage_keys: &str) -> Arc<Vec<Item>> {
    items_in(&graph(stage_keys, 7), None)
}

fn load_err(stage_keys: &str) -> String {
    palpate_stages::link();
    match load_str(
        &graph(stage_keys, 1),
        "test.toml",
        "test",
        &LoadOptions::default(),
    ) {
        Ok(_) => panic!("expected an error for {stage_keys}"),
        Err(e) => e.to_string(),
    }
}

fn data(item: &Item) -> &Vec<Vec<f64>> {
    &item.payload.signals().unwrap().data
}

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("palpate-scene-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// First and last sample at which some taxel departs from its start / end plateau by more than `tol`.
fn active_span(d: &[Vec<f64>], tol: f64) -> (usize, usize) {
    let n = d[0].len();
    let first = (0..n)
        .find(|&k| d.iter().any(|row| (row[k] - row[0]).abs() > tol))
        .unwrap();
    let last = (0..n)
        .rev()
        .find(|&k| d.iter().any(|row| (row[k] - row[n - 1]).abs() > tol))
        .unwrap();
    (first, last)
}

#[test]
fn crossing_takes_the_time_geometry_predicts() {
    let angles: [f64; 9] = [10.0, 20.0, 30.0, 45.0, 60.0, 75.0, 90.0, 120.0, 150.0];
    let list = angles.map(|a| a.to_string()).join(", ");
    let items = items(&format!("angles = [{list}]\ntrials_per_angle = 1"));
    for (item, &theta) in items.iter().zip(&angles) {
        let d = data(item);
        let (first, last) = active_span(d, 0.0);
        let t = theta.to_radians();
        // (footprint extent) / (v sin θ): 11 mm (sin θ + |cos θ|) / (2 mm/s sin θ).
        let want_s = 11.0 * (1.0 + (t.cos() / t.sin()).abs()) / 2.0;
        let got_s = (last + 1 - first) as f64 / 1000.0;
        assert!(
            (got_s - want_s).abs() <= 0.002,
            "θ={theta}: crossing {got_s} s, geometry says {want_s} s"
        );
        let [c0, c1] = item.meta.crossing_ms.unwrap();
        assert!(
            (c0 - first as f64).abs() <= 1.0 && (c1 - (last + 1) as f64).abs() <= 1.0,
            "θ={theta}: {c0}..{c1} vs {first}..{last}"
        );
        if theta == 90.0 {
            assert!((want_s - 5.5).abs() < 1e-12);
        }
        // Contact fraction: full contact before, none after, never outside [0, 1].
        assert!(d.iter().all(|r| r[0] == 1.0 && r[r.len() - 1] == 0.0));
        assert!(d.iter().flatten().all(|v| (0.0..=1.0).contains(v)));
    }
}

#[test]
fn the_skin_spreads_the_crossing_to_the_13_mm_active_area() {
    // A 1 mm skin (sigma 0.5 mm) widens each taxel's response by ~2 sigma = 1 mm
    // on each side: 13 mm at 2 mm/s is the paper's "about 6.5 s at 90 degrees". A
    // departure of 0.2 % of full scale marks where the response starts.
    let items = items("angles = [90]\ntrials_per_angle = 1\neffects = [{ kind = \"skin\", sigma_mm = 0.5 }]");
    let (first, last) = active_span(data(&items[0]), 0.002);
    let span = (last + 1 - first) as f64 / 1000.0;
    assert!((span - 6.5).abs() < 0.1, "skin-spread crossing {span} s");
    // The ideal response's span at the same threshold stays near 5.5 s.
    let ideal = items_in(&graph("angles = [90]\ntrials_per_angle = 1", 7), None);
    let (f0, l0) = active_span(data(&ideal[0]), 0.002);
    assert!(((l0 + 1 - f0) as f64 / 1000.0 - 5.5).abs() < 0.02);
}

#[test]
fn no_effects_gives_exactly_the_ideal_response() {
    let items = items("angles = [37.5]\ntrials_per_angle = 1");
    let d = data(&items[0]);
    let cfg = SceneConfig {
        angles: Some(palpate_stages::scene::config::Angles::List(vec![37.5])),
        ..Default::default()
    };
    let sim = Simulator::new(cfg.check().unwrap(), 0).unwrap();
    let plan = sim.plan(37.5).unwrap();
    let edge = Edge::new(37.5);
    let shape = TaxelShape::new(&edge, 2.0);
    let s0 = plan.hi + plan.margin;
    let slide = plan.travel / 2.0;
    for (i, row) in d.iter().enumerate() {
        let c = edge.offset(palpate_core::TaxelLayout::paper().position(i));
        for (k, &v) in row.iter().enumerate() {
            let x = 2.0 * (k as f64 / 1000.0 - 2.0).clamp(0.0, slide);
            let s = plan.s_mid - (x - plan.x_mid) * edge.normal[0];
            let want = shape.step_fraction(s - c);
            assert_eq!(v, want, "taxel {i} sample {k}");
            let _ = s0;
        }
    }
}

#[test]
fn same_seed_same_bits_on_one_or_two_threads() {
    let text = graph(
        "file = \"scenes/lab.toml\"\nangles = [30, 75]\ntrials_per_angle = 2",
        11,
    );
    let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("../graphs");
    let runs: Vec<Vec<Vec<u64>>> = [1, 2, 1]
        .iter()
        .map(|&n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
                .install(|| {
                    let g =
                        palpate_core::load_file(&write_graph(&base, "det", &text), &LoadOptions::default())
                            .unwrap();
                    let r = run(
                        &g,
                        &RunOptions {
                            keep_outputs: true,
                            ..Default::default()
                        },
                    )
                    .unwrap();
                    r.outputs["scene"]
                        .iter()
                        .map(|it| data(it).iter().flatten().map(|v| v.to_bits()).collect())
                        .collect()
                })
        })
        .collect();
    assert_eq!(runs[0], runs[1]);
    assert_eq!(runs[0], runs[2]);
    // A different seed gives different noise.
    let other = items_in(
        &text.replace("seed = 11", "seed = 12"),
        Some(&base_dir_copy(&base)),
    );
    let other_bits: Vec<Vec<u64>> = other
        .iter()
        .map(|it| data(it).iter().flatten().map(|v| v.to_bits()).collect())
        .collect();
    assert_ne!(runs[0], other_bits);
}

/// Writes a graph into a scratch directory that holds a copy of `graphs/scenes`.
fn write_graph(graphs: &Path, name: &str, text: &str) -> PathBuf {
    let dir = base_dir_copy_named(graphs, name);
    let p = dir.join("g.toml");
    std::fs::write(&p, text).unwrap();
    p
}

fn base_dir_copy(graphs: &Path) -> PathBuf {
    base_dir_copy_named(graphs, "other")
}

fn base_dir_copy_named(graphs: &Path, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("palpate-scene-graphs-{name}-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("scenes")).unwrap();
    for f in ["ideal.toml", "lab.toml"] {
        std::fs::copy(graphs.join("scenes").join(f), dir.join("scenes").join(f)).unwrap();
    }
    dir
}

#[test]
fn quantized_values_lie_on_the_adc_grid() {
    let items = items(
        "angles = [45]\ntrials_per_angle = 1\neffects = [{ kind = \"piezo\" }, { kind = \"noise\", sigma = 0.01 }, { kind = \"adc\", bits = 8, min = 0.0, max = 3.3 }]",
    );
    let step = 3.3 / 255.0;
    let d = data(&items[0]);
    let mut levels = std::collections::BTreeSet::new();
    for v in d.iter().flatten() {
        let code = v / step;
        assert!((code - code.round()).abs() < 1e-9, "{v} is off the grid");
        assert!((0.0..=3.3 + 1e-12).contains(v));
        levels.insert(code.round() as i64);
    }
    assert!(levels.len() > 50, "the crossing should sweep many levels");
    assert_eq!(items[0].payload.signals().unwrap().unit, "V");
}

#[test]
fn white_noise_has_the_stated_sigma() {
    let ideal = items("angles = [60]\ntrials_per_angle = 1");
    let noisy = items("angles = [60]\ntrials_per_angle = 1\neffects = [{ kind = \"noise\", sigma = 0.03 }]");
    let diffs: Vec<f64> = data(&ideal[0])
        .iter()
        .flatten()
        .zip(data(&noisy[0]).iter().flatten())
        .map(|(a, b)| b - a)
        .collect();
    let n = diffs.len() as f64;
    let mean = diffs.iter().sum::<f64>() / n;
    let sd = (diffs.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / n).sqrt();
    // ~1.9e5 samples: the SD's standard error is ~0.16 %.
    assert!((sd - 0.03).abs() < 0.03 * 0.01, "noise SD {sd}");
    assert!(mean.abs() < 0.03 * 0.01, "noise mean {mean}");
}

#[test]
fn gain_mismatch_is_fixed_per_array_not_per_trial() {
    let keys = "angles = [30, 80]\ntrials_per_angle = 3\neffects = [{ kind = \"mismatch\", gain_sd = 0.1, offset_sd = 0.0 }]";
    let items = items(keys);
    // At the start every taxel is in full contact (pressure 1): the reading is its gain.
    let gains: Vec<Vec<f64>> = items
        .iter()
        .map(|it| data(it).iter().map(|r| r[0]).collect())
        .collect();
    for g in &gains {
        assert_eq!(g, &gains[0], "gains differ between trials");
    }
    assert!(gains[0].iter().any(|&g| (g - 1.0).abs() > 1e-3));
    let distinct: std::collections::BTreeSet<u64> = gains[0].iter().map(|g| g.to_bits()).collect();
    assert_eq!(distinct.len(), 16, "every taxel has its own gain");
    // Another graph seed is another array.
    let other = items_in(&graph(keys, 8), None);
    assert_ne!(data(&other[0]).iter().map(|r| r[0]).collect::<Vec<_>>(), gains[0]);
}

#[test]
fn piezo_reads_1_75_v_in_contact_and_saturates_off_the_object() {
    let items = items("angles = [90]\ntrials_per_angle = 1\neffects = [{ kind = \"piezo\" }]");
    for row in data(&items[0]) {
        assert!((row[0] - 1.75).abs() < 1e-12);
        assert!((row[row.len() - 1] - 3.3).abs() < 1e-12);
        // Inverse response: the output only rises as contact is lost.
        assert!(row.windows(2).all(|w| w[1] >= w[0]));
    }
}

#[test]
fn each_effect_changes_only_what_it_claims() {
    let ideal = items("angles = [50]\ntrials_per_angle = 1");
    let ideal = data(&ideal[0]).clone();
    let n = ideal[0].len();

    // Hum: the difference is a 50 Hz sinusoid of the stated amplitude, common to all taxels.
    let hum = items("angles = [50]\ntrials_per_angle = 1\neffects = [{ kind = \"hum\", frequency_hz = 50, amplitude = 0.01 }]");
    let diff: Vec<f64> = (0..n).map(|k| data(&hum[0])[3][k] - ideal[3][k]).collect();
    let (mut a, mut b) = (0.0, 0.0);
    for (k, d) in diff.iter().enumerate() {
        let w = std::f64::consts::TAU * 50.0 * k as f64 / 1000.0;
        a += d * w.sin();
        b += d * w.cos();
    }
    let amp = 2.0 * (a * a + b * b).sqrt() / n as f64;
    assert!((amp - 0.01).abs() < 1e-4, "hum amplitude {amp}");
    assert!(diff.iter().all(|d| d.abs() <= 0.01 + 1e-12));
    for i in 0..16 {
        assert!((0..n).all(|k| ((data(&hum[0])[i][k] - ideal[i][k]) - diff[k]).abs() < 1e-12));
    }

    // Crosstalk: uniform contact (start and end) is unchanged; the crossing is blended.
    let xt = items(
        "angles = [50]\ntrials_per_angle = 1\neffects = [{ kind = \"crosstalk\", row = 0.05, col = 0.05 }]",
    );
    let x = data(&xt[0]);
    for i in 0..16 {
        assert!((x[i][0] - 1.0).abs() < 1e-12 && x[i][n - 1].abs() < 1e-12);
    }
    assert!((0..16).any(|i| (0..n).any(|k| (x[i][k] - ideal[i][k]).abs() > 0.01)));
    // The blend conserves the array's total (each taxel gives away what the others receive).
    for k in (0..n).step_by(97) {
        let s0: f64 = (0..16).map(|i| ideal[i][k]).sum();
        let s1: f64 = (0..16).map(|i| x[i][k]).sum();
        assert!((s0 - s1).abs() < 1e-9);
    }

    // Creep: plateaus settle to the ideal values; during the slide the output lags.
    let cr = items(
        "angles = [50]\ntrials_per_angle = 1\neffects = [{ kind = \"creep\", fraction = 0.3, tau_s = 0.2 }]",
    );
    let c = data(&cr[0]);
    for i in 0..16 {
        assert_eq!(c[i][0], 1.0);
        assert!(c[i][n - 1].abs() < 1e-6, "creep settles");
        let lag: f64 = (0..n).map(|k| c[i][k] - ideal[i][k]).sum();
        assert!(lag > 0.0, "a falling signal that creeps lies above the ideal");
        assert!((0..n).all(|k| c[i][k] >= ideal[i][k] - 1e-12));
    }

    // Dead taxels: listed ones read the constant; others are untouched.
    let dd = items(
        "angles = [50]\ntrials_per_angle = 1\neffects = [{ kind = \"dead\", taxels = [2, 9], value = 0.25 }]",
    );
    let d = data(&dd[0]);
    for i in 0..16 {
        if i == 2 || i == 9 {
            assert!(d[i].iter().all(|&v| v == 0.25));
        } else {
            assert_eq!(d[i], ideal[i]);
        }
    }

    // Stress concentration: plateaus unchanged, a pressure peak during the crossing.
    let st = items("angles = [50]\ntrials_per_angle = 1\neffects = [{ kind = \"stress\", peak = 0.5, depth_mm = 0.3, width_mm = 0.2 }]");
    let s = data(&st[0]);
    for i in 0..16 {
        assert!((s[i][0] - 1.0).abs() < 1e-9 && s[i][n - 1].abs() < 1e-9);
        assert!(s[i].iter().cloned().fold(f64::MIN, f64::max) > 1.02);
    }

    // Skin: the same plateaus, a smoother crossing.
    let sk = items("angles = [50]\ntrials_per_angle = 1\neffects = [{ kind = \"skin\", sigma_mm = 0.5 }]");
    let k = data(&sk[0]);
    for i in 0..16 {
        assert!((k[i][0] - 1.0).abs() < 1e-5 && k[i][n - 1].abs() < 1e-5);
        assert!(
            k[i].windows(2).all(|w| w[1] <= w[0] + 1e-12),
            "blurred contact still only falls"
        );
    }
}

#[test]
fn trial_variation_changes_trials_but_not_labels() {
    let items = items("angles = [45]\ntrials_per_angle = 4\neffects = [{ kind = \"variation\", force_rel_sd = 0.1, speed_rel_sd = 0.02 }]");
    let forces: Vec<f64> = items.iter().map(|it| data(it)[0][0]).collect();
    let lens: Vec<usize> = items.iter().map(|it| data(it)[0].len()).collect();
    for it in items.iter() {
        assert_eq!(it.meta.label.angle_deg, Some(45.0));
        let d = data(it);
        // Force scales the whole contact plateau equally for every taxel.
        assert!(d.iter().all(|r| r[0] == d[0][0]));
    }
    let distinct: std::collections::BTreeSet<u64> = forces.iter().map(|f| f.to_bits()).collect();
    assert_eq!(distinct.len(), 4, "force varies per trial: {forces:?}");
    assert!(forces.iter().all(|f| (f - 1.0).abs() <= 0.3 + 1e-12));
    assert!(
        lens.iter().any(|&l| l != lens[0]),
        "speed varies per trial: {lens:?}"
    );
    assert_eq!(
        items.iter().map(|it| it.meta.group).collect::<Vec<_>>(),
        vec![0, 1, 2, 3]
    );
    assert_eq!(items[3].meta.trial_id, "edge-45deg-r03");
}

#[test]
fn ridge_adds_the_bar_pressure_over_the_flat() {
    let items = items("stimulus = \"ridge\"\nangles = [60]\ntrials_per_angle = 1");
    let d = data(&items[0]);
    let n = d[0].len();
    for row in d {
        assert_eq!(row[0], 1.0);
        assert_eq!(row[n - 1], 1.0);
        let max = row.iter().cloned().fold(f64::MIN, f64::max);
        // 2 mm bar, 2 mm high over a 1 mm indentation: 3x the flat's pressure where
        // the bar covers the taxel (at 60° the 2 mm bar covers at most part of it).
        assert!(max > 1.5 && max <= 3.0 + 1e-12, "{max}");
        assert!(row.iter().all(|&v| (1.0..=3.0 + 1e-12).contains(&v)));
    }
    assert_eq!(items[0].meta.trial_id, "ridge-60deg-r00");
    let [c0, c1] = items[0].meta.crossing_ms.unwrap();
    let t = 60f64.to_radians();
    let want = (11.0 * (t.sin() + t.cos()) + 2.0) / (2.0 * t.sin()) * 1000.0;
    assert!((c1 - c0 - want).abs() < 1e-6);
}

#[test]
fn bad_angles_are_errors_naming_the_key() {
    for bad in [
        "[0]",
        "[180]",
        "[-5]",
        "[45, 45]",
        "[]",
        "{ from = 10, to = 5 }",
        "{ step = 0 }",
    ] {
        let e = load_err(&format!("angles = {bad}"));
        assert!(e.contains("angles"), "{bad}: {e}");
    }
    let e = load_err("angles = [0.0001]");
    assert!(e.contains("angles") && e.contains("limit"), "{e}");
    // Near-grazing angles that fit are fine and finite.
    let items = items("angles = [179, 1]\ntrials_per_angle = 1\nmotion = { speed_mm_s = 20 }");
    assert!(items
        .iter()
        .all(|it| data(it).iter().flatten().all(|v| v.is_finite())));
}

#[test]
fn effects_out_of_phase_order_or_with_bad_values_are_errors() {
    let e = load_err("effects = [{ kind = \"piezo\" }, { kind = \"skin\" }]");
    assert!(e.contains("effects[1]") && e.contains("piezo"), "{e}");
    let e = load_err("effects = [{ kind = \"noise\", sigma = -1 }]");
    assert!(e.contains("effects[0].sigma"), "{e}");
    // An unknown kind names the entry as other messages do (`effects[0]`,
    // not `effects.[0]`) and lists every kind.
    let e = load_err("effects = [{ kind = \"bogus\" }]");
    assert!(e.contains("key `effects[0].kind`") && e.contains("`adc`"), "{e}");
    // Not a string: the value and the choices are named all the same.
    let e = load_err("effects = [{ kind = 3 }]");
    assert!(
        e.contains("key `effects[0].kind`: 3 is not a choice") && e.contains("`adc`"),
        "{e}"
    );
    let e = load_err("effects = [{ kind = \"noise\", sigmaa = 1 }]");
    assert!(e.contains("sigmaa"), "{e}");
    let e = load_err("effects = [{ kind = \"dead\", taxels = [16] }]");
    assert!(e.contains("effects[0].taxels"), "{e}");
    let e = load_err("layout = { positions_mm = [[0, 0], [3, 0]] }\neffects = [{ kind = \"crosstalk\" }]");
    assert!(e.contains("grid"), "{e}");
    let e = load_err("effects = [{ kind = \"piezo\", v_contact = 4 }]");
    assert!(e.contains("v_contact"), "{e}");
    // A file source's layout table reads here too; a grid is `array`.
    let it = items("angles = [45]\ntrials_per_angle = 1\nlayout = { kind = \"positions\", positions_mm = [[0, 0], [3, 0], [0, 3]] }");
    assert_eq!(data(&it[0]).len(), 3);
    let e = load_err("layout = { kind = \"grid\", positions_mm = [[0, 0], [3, 0]] }");
    assert!(e.contains("layout.kind") && e.contains("`array`"), "{e}");
}

#[test]
fn scene_files_are_defaults_that_inline_keys_override() {
    let dir = temp_dir("file");
    std::fs::create_dir_all(dir.join("scenes")).unwrap();
    std::fs::write(
        dir.join("scenes/s.toml"),
        "angles = [20, 40]\ntrials_per_angle = 3\n[motion]\nhold_before_s = 1.0\nspeed_mm_s = 4.0\n",
    )
    .unwrap();
    // Inline `motion.speed_mm_s` overrides the file's, its hold stays.
    let items = items_in(
        &graph(
            "file = \"scenes/s.toml\"\ntrials_per_angle = 1\nmotion = { speed_mm_s = 2.0 }",
            1,
        ),
        Some(&dir),
    );
    assert_eq!(items.len(), 2);
    assert_eq!(items[1].meta.label.angle_deg, Some(40.0));
    // Each trial declares the speed it was palpated at (the inline one).
    assert!(items.iter().all(|it| it.meta.speed_mm_s == Some(2.0)));
    let [c0, _] = items[0].meta.crossing_ms.unwrap();
    let plan_margin_ms = 1.0 / (2.0 * 20f64.to_radians().sin()) * 1000.0;
    assert!((c0 - (1000.0 + plan_margin_ms)).abs() < 1e-6, "{c0}");

    // Unknown or mistyped keys in the file name the file and the key.
    std::fs::write(
        dir.join("scenes/bad.toml"),
        "angles = [20]\n[motion]\nsped_mm_s = 3\n",
    )
    .unwrap();
    let e = palpate_core::load_file(
        &write_at(&dir, &graph("file = \"scenes/bad.toml\"", 1)),
        &LoadOptions::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("bad.toml") && e.contains("sped_mm_s"), "{e}");
    std::fs::write(dir.join("scenes/bad2.toml"), "trials_per_angle = \"ten\"\n").unwrap();
    let e = palpate_core::load_file(
        &write_at(&dir, &graph("file = \"scenes/bad2.toml\"", 1)),
        &LoadOptions::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("bad2.toml") && e.contains("trials_per_angle"), "{e}");
    let e = palpate_core::load_file(
        &write_at(&dir, &graph("file = \"scenes/missing.toml\"", 1)),
        &LoadOptions::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("missing.toml"), "{e}");
}

fn write_at(dir: &Path, text: &str) -> PathBuf {
    let p = dir.join("g.toml");
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn shipped_scenes_load_and_lab_looks_like_fig_3a() {
    let base = Path::new(env!("CARGO_MANIFEST_DIR")).join("../graphs");
    let ideal = items_in(
        &graph(
            "file = \"scenes/ideal.toml\"\nangles = [45]\ntrials_per_angle = 1",
            3,
        ),
        Some(&base_dir_copy_named(&base, "ideal")),
    );
    assert_eq!(data(&ideal[0])[5][0], 1.0);
    let lab = items_in(
        &graph(
            "file = \"scenes/lab.toml\"\nangles = [45]\ntrials_per_angle = 1",
            3,
        ),
        Some(&base_dir_copy_named(&base, "lab")),
    );
    let sig = lab[0].payload.signals().unwrap();
    assert_eq!(sig.unit, "V");
    // An inner taxel: ~1.75 V in contact, rising to ~3.3 V off the object.
    let row = &sig.data[5];
    let n = row.len();
    let start: f64 = row[..1000].iter().sum::<f64>() / 1000.0;
    let end: f64 = row[n - 1000..].iter().sum::<f64>() / 1000.0;
    assert!((1.5..2.0).contains(&start), "contact {start} V");
    assert!((3.0..=3.3).contains(&end), "off the object {end} V");
}

#[test]
fn simulate_writes_what_signal_file_reads_back_with_labels() {
    let dir = temp_dir("export");
    let scene = dir.join("scene.toml");
    std::fs::write(
        &scene,
        // A 3 x 2 array: the label files carry the layout, so `signal_file`
        // reads the files back without a `layout` key.
        "angles = [90, 45]\ntrials_per_angle = 2\neffects = [{ kind = \"piezo\" }, { kind = \"noise\", sigma = 0.01 }]\n\
         array = { rows = 3, cols = 2, pitch_mm = 3.0, taxel_mm = 2.0 }\n",
    )
    .unwrap();
    let want = items_in(
        &graph(&format!("file = {:?}", scene.display().to_string()), 5),
        None,
    );
    for (csv, ext) in [(false, "npy"), (true, "csv")] {
        let out = dir.join(format!("out-{ext}"));
        let files = palpate_stages::scene::simulate_to_dir(&scene, &out, 5, csv).unwrap();
        // 4 trials, labels.toml, trials.json, the plot.
        assert_eq!(files.len(), 4 + 3, "{files:?}");
        assert!(files.iter().all(|f| f.exists()));
        let data_files = files
            .iter()
            .filter(|f| f.extension().is_some_and(|e| e == ext))
            .count();
        assert_eq!(data_files, 4, "one {ext} per trial, and no other format");
        let svg = files.last().unwrap();
        assert!(std::fs::read_to_string(svg).unwrap().contains("polyline"));
        // Read back by `signal_file` with either label file: the same samples,
        // bit for bit, and the same labels and groups as the scene's trials.
        for labels in ["labels.toml", "trials.json"] {
            let text = format!(
                "[run]\nseed = 5\n[stages.scene]\ntype = \"signal_file\"\npath = \"*.{ext}\"\nlabels = \"{labels}\"\n{}\n",
                if csv { "" } else { "sample_rate_hz = 1000.0" }
            );
            let got = items_in(&text, Some(&out));
            assert_eq!(got.len(), want.len());
            let mut got: Vec<&Item> = got.iter().collect();
            got.sort_by(|a, b| a.meta.trial_id.cmp(&b.meta.trial_id));
            let mut exp: Vec<&Item> = want.iter().collect();
            exp.sort_by(|a, b| a.meta.trial_id.cmp(&b.meta.trial_id));
            for (g, w) in got.iter().zip(&exp) {
                assert_eq!(g.meta.trial_id, w.meta.trial_id, "{ext} {labels}");
                assert_eq!(g.meta.label, w.meta.label, "{ext} {labels}");
                assert_eq!(g.meta.group, w.meta.group, "{ext} {labels}");
                assert_eq!(data(g), data(w), "{ext} {labels}: samples differ");
                let (gs, ws) = (g.payload.signals().unwrap(), w.payload.signals().unwrap());
                assert_eq!(
                    gs.layout, ws.layout,
                    "{ext} {labels}: the layout the labels declare"
                );
            }
        }
    }
    // The CSV's columns are the ones `signal_file` expects.
    let csv = std::fs::read_to_string(dir.join("out-csv/edge-90deg-r00.csv")).unwrap();
    let header = csv.lines().next().unwrap();
    assert!(header.starts_with("time_ms,taxel_0,taxel_1,") && header.ends_with(",taxel_5"));
    // The NPY is (samples, taxels).
    let bytes = std::fs::read(dir.join("out-npy/edge-45deg-r01.npy")).unwrap();
    let npy = npyz::NpyFile::new(&bytes[..]).unwrap();
    let w = want.iter().find(|i| i.meta.trial_id == "edge-45deg-r01").unwrap();
    assert_eq!(npy.shape(), &[data(w)[0].len() as u64, 6]);
    assert!(
        palpate_stages::scene::simulate_to_dir(&dir.join("nope.toml"), &dir.join("o"), 5, false)
            .unwrap_err()
            .message
            .contains("nope.toml")
    );
}

#[test]
fn each_condition_declares_its_own_speed() {
    let items = items(
        "angles = [30]\ntrials_per_angle = 1\nmotion = { speed_mm_s = 10.0, hold_before_s = 0.2, hold_after_s = 0.2 }\n\
         conditions = { slow = {}, fast = { motion = { speed_mm_s = 15.0 } } }",
    );
    let mut speeds: Vec<(String, Option<f64>)> = items
        .iter()
        .map(|it| (it.meta.conditions["condition"].clone(), it.meta.speed_mm_s))
        .collect();
    speeds.sort_by(|a, b| a.0.cmp(&b.0));
    assert_eq!(
        speeds,
        [("fast".to_string(), Some(15.0)), ("slow".to_string(), Some(10.0))]
    );
}
