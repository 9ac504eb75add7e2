//! Unit tests that need the crate's internals: the effect construction log.

use super::effects::LOG;
use super::*;
use palpate_core::{Signals, Source, Stage, TrialContext};
use proptest::prelude::*;

fn ctx() -> BuildContext {
    BuildContext {
        stage_id: "scene".into(),
        seed: 3,
        out_dir: std::env::temp_dir(),
        base_dir: std::path::PathBuf::from("."),
    }
}

/// The config error building a scene from `keys` gives (panics if it builds).
fn build_error(keys: &str) -> ConfigError {
    let cfg: SceneConfig = toml::from_str(keys).unwrap();
    match cfg.build(&ctx()) {
        Ok(_) => panic!("built: {keys}"),
        Err(e) => e,
    }
}

fn build(toml_keys: &str) -> Box<dyn Source> {
    let cfg: SceneConfig = toml::from_str(toml_keys).unwrap();
    match cfg.build(&ctx()).unwrap() {
        Stage::Source(s) => s,
        other => panic!("scene built a {}", other.role()),
    }
}

fn produce(src: &dyn Source, i: usize) -> Signals {
    let metas = src.trials().unwrap();
    let ctx = TrialContext {
        stage_id: "scene",
        meta: &metas[i],
        seed: 99,
    };
    let p = src.produce(&ctx).unwrap();
    (**p.signals().unwrap()).clone()
}

fn take_log() -> Vec<String> {
    LOG.with(|l| std::mem::take(&mut *l.borrow_mut()))
}

#[test]
fn unlisted_effects_are_never_constructed_nor_computed() {
    take_log();
    let src = build("angles = [45]\ntrials_per_angle = 1\neffects = [{ kind = \"noise\", sigma = 0.1 }]");
    produce(src.as_ref(), 0);
    assert_eq!(take_log(), vec!["build:noise", "run:noise"]);

    let src = build("angles = [45]\ntrials_per_angle = 1");
    produce(src.as_ref(), 0);
    assert!(take_log().is_empty(), "the ideal scene touches no effect");

    // The lab scene constructs and runs every kind it lists, once each.
    let lab =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../graphs/scenes/lab.toml")).unwrap();
    let src = build(&format!("{lab}\n").replace("trials_per_angle = 10", "trials_per_angle = 1"));
    let built = take_log();
    let kinds = [
        "variation",
        "skin",
        "stress",
        "creep",
        "dead",
        "piezo",
        "mismatch",
        "crosstalk",
        "hum",
        "noise",
        "adc",
    ];
    assert_eq!(
        built,
        kinds.iter().map(|k| format!("build:{k}")).collect::<Vec<_>>()
    );
    produce(src.as_ref(), 0);
    let ran = take_log();
    // Field effects shape the profile at build; the rest run in every trial.
    for k in [
        "variation",
        "creep",
        "dead",
        "piezo",
        "mismatch",
        "crosstalk",
        "hum",
        "noise",
        "adc",
    ] {
        assert_eq!(
            ran.iter().filter(|e| **e == format!("run:{k}")).count(),
            1,
            "{k}: {ran:?}"
        );
    }
}

#[test]
fn trials_are_listed_angle_by_angle_with_groups_and_ids() {
    let src = build("angles = { from = 10, to = 20, step = 2.5 }\ntrials_per_angle = 2");
    let t = src.trials().unwrap();
    let ids: Vec<&str> = t.iter().map(|m| m.trial_id.as_str()).collect();
    assert_eq!(
        ids[..4],
        [
            "edge-10deg-r00",
            "edge-10deg-r01",
            "edge-12.5deg-r00",
            "edge-12.5deg-r01"
        ]
    );
    assert_eq!(t.len(), 10);
    assert_eq!(
        t.iter().map(|m| m.group).collect::<Vec<_>>(),
        [0, 1, 0, 1, 0, 1, 0, 1, 0, 1]
    );
    assert!(t
        .iter()
        .all(|m| m.crossing_ms.is_some() && m.label.angle_deg.is_some()));
}

#[test]
fn default_angles_are_the_papers_17_classes() {
    let src = build("");
    let t = src.trials().unwrap();
    assert_eq!(t.len(), 170);
    let angles: std::collections::BTreeSet<i64> =
        t.iter().map(|m| m.label.angle_deg.unwrap() as i64).collect();
    assert_eq!(
        angles.into_iter().collect::<Vec<_>>(),
        (10..=90).step_by(5).collect::<Vec<_>>()
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]
    /// Any angle and any effect strengths give finite signals of the stated
    /// shape, never a panic.
    #[test]
    fn any_scene_gives_finite_signals(
        theta in 5.0f64..175.0,
        sigma in 0.0f64..2.0,
        peak in 0.0f64..2.0,
        noise in 0.0f64..0.1,
        ridge in any::<bool>(),
    ) {
        let keys = format!(
            "stimulus = \"{}\"\nangles = [{theta}]\ntrials_per_angle = 1\nmotion = {{ sample_rate_hz = 50, speed_mm_s = 10 }}\neffects = [{{ kind = \"variation\" }}, {{ kind = \"skin\", sigma_mm = {sigma} }}, {{ kind = \"stress\", peak = {peak} }}, {{ kind = \"creep\" }}, {{ kind = \"piezo\" }}, {{ kind = \"noise\", sigma = {noise} }}, {{ kind = \"adc\" }}]",
            if ridge { "ridge" } else { "edge" }
        );
        let src = build(&keys);
        let s = produce(src.as_ref(), 0);
        prop_assert_eq!(s.data.len(), 16);
        prop_assert!(s.n_samples() > 0);
        prop_assert!(s.data.iter().all(|r| r.len() == s.n_samples()));
        prop_assert!(s.data.iter().flatten().all(|v| v.is_finite() && (0.0..=3.3 + 1e-9).contains(v)));
    }
}

#[test]
fn placement_variation_too_large_for_a_grazing_angle_is_a_config_error() {
    let cfg: SceneConfig =
        toml::from_str("angles = [2]\neffects = [{ kind = \"variation\", angle_sd_deg = 1.0 }]").unwrap();
    let ctx = BuildContext {
        stage_id: "scene".into(),
        seed: 3,
        out_dir: std::env::temp_dir(),
        base_dir: std::path::PathBuf::from("."),
    };
    let e = cfg.build(&ctx).err().expect("an error");
    assert_eq!(e.key.as_deref(), Some("effects"));
    assert!(e.message.contains("too large for the angle 2"), "{e}");
    // It names both ways out, and each works: the largest SD for the angle
    // (sin 2° / 6 rad = 0.333°), or the smallest angle for the SD.
    assert!(
        e.message.contains("at or under 0.333 degrees") && e.message.contains("from 6.0"),
        "{e}"
    );
    let ok = |text: &str| toml::from_str::<SceneConfig>(text).unwrap().build(&ctx).is_ok();
    assert!(ok(
        "angles = [2]\neffects = [{ kind = \"variation\", angle_sd_deg = 0.333 }]"
    ));
    let bound = |after: &str| -> f64 {
        e.message
            .split(after)
            .nth(1)
            .unwrap()
            .split(' ')
            .next()
            .unwrap()
            .parse()
            .unwrap()
    };
    let (min_angle, max_angle) = (bound("angles from "), bound(" to "));
    assert!((min_angle + max_angle - 180.0).abs() < 1e-9, "{e}");
    for a in [min_angle, max_angle] {
        assert!(ok(&format!(
            "angles = [{a}]\neffects = [{{ kind = \"variation\", angle_sd_deg = 1.0 }}]"
        )));
    }
    // Near 180 degrees the way out is the range's upper end, not a lower
    // bound the angle already meets.
    let cfg: SceneConfig =
        toml::from_str("angles = [179]\neffects = [{ kind = \"variation\", angle_sd_deg = 1.0 }]").unwrap();
    let e = cfg.build(&ctx).err().expect("an error");
    assert!(e.message.contains(&format!("to {max_angle:.2} degrees")), "{e}");
    // An SD no angle can take names no range.
    let cfg: SceneConfig =
        toml::from_str("angles = [90]\neffects = [{ kind = \"variation\", angle_sd_deg = 10.0 }]").unwrap();
    let e = cfg.build(&ctx).err().expect("an error");
    assert!(!e.message.contains("angles from"), "{e}");
}

#[test]
fn the_avx2_and_baseline_paths_give_the_same_bits() {
    // Every lab effect, at a steep and a shallow angle.
    let src = build(
        r#"angles = [15, 70]
trials_per_angle = 1
effects = [
  { kind = "variation", speed_rel_sd = 0.01, start_sd_mm = 0.2, force_rel_sd = 0.05, angle_sd_deg = 0.5 },
  { kind = "skin", sigma_mm = 0.5 },
  { kind = "stress", peak = 0.3, depth_mm = 0.3, width_mm = 0.2 },
  { kind = "creep", fraction = 0.1, tau_s = 0.5 },
  { kind = "dead", probability = 0.1, value = 0.0 },
  { kind = "piezo", v_open = 3.3, v_contact = 1.75, exponent = 1.0 },
  { kind = "mismatch", gain_sd = 0.05, offset_sd = 0.02 },
  { kind = "crosstalk", row = 0.02, col = 0.02 },
  { kind = "hum", frequency_hz = 50.0, amplitude = 0.003 },
  { kind = "noise", sigma = 0.005 },
  { kind = "adc", bits = 12, min = 0.0, max = 3.3 },
]"#,
    );
    for i in 0..2 {
        let fast = produce(src.as_ref(), i);
        let slow = crate::wide::baseline_only(|| produce(src.as_ref(), i));
        let bits = |s: &Signals| s.data.iter().flatten().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&fast), bits(&slow), "trial {i}");
    }
}

#[test]
fn sensor_effects_are_built_only_when_listed_and_keep_scenes_finite() {
    take_log();
    let src = build(
        "angles = [30, 90]\ntrials_per_angle = 1\neffects = [\
         { kind = \"sleeve\" }, { kind = \"tilt\" }, { kind = \"hysteresis\" },\
         { kind = \"dynamics\" }, { kind = \"ghosting\" }, { kind = \"piezo\" }]",
    );
    let built = take_log();
    assert_eq!(
        built,
        ["sleeve", "tilt", "hysteresis", "dynamics", "ghosting", "piezo"]
            .iter()
            .map(|k| format!("build:{k}"))
            .collect::<Vec<_>>()
    );
    for i in 0..2 {
        let s = produce(src.as_ref(), i);
        assert!(s
            .data
            .iter()
            .flatten()
            .all(|v| v.is_finite() && (0.0..=3.3).contains(v)));
        let ran = take_log();
        for k in ["sleeve", "tilt", "hysteresis", "dynamics", "ghosting", "piezo"] {
            assert!(ran.contains(&format!("run:{k}")), "{k} did not run: {ran:?}");
        }
    }
    // Same seed, same bits; the sleeve's shear delays the crossing.
    let a = produce(src.as_ref(), 1);
    assert_eq!(a, produce(src.as_ref(), 1));
}

#[test]
fn pressure_effects_after_piezo_are_config_errors() {
    for kind in ["hysteresis", "ghosting"] {
        let cfg: SceneConfig = toml::from_str(&format!(
            "angles = [45]\neffects = [{{ kind = \"piezo\" }}, {{ kind = \"{kind}\" }}]"
        ))
        .unwrap();
        let ctx = BuildContext {
            stage_id: "scene".into(),
            seed: 3,
            out_dir: std::env::temp_dir(),
            base_dir: std::path::PathBuf::from("."),
        };
        let err = cfg.build(&ctx).err().expect("an error");
        assert_eq!(err.key.as_deref(), Some("effects[1]"), "{kind}: {err}");
        assert!(err.message.contains("before `piezo`"), "{err}");
    }
}

#[test]
fn the_sleeve_delays_the_pattern_by_its_shear() {
    // A sleeve with no spread and no moment: only the lag. At 90 degrees the
    // last taxel column (x = 4.5) leaves the object when the actual displacement
    // reaches its plan; with shear the array must travel u further.
    let plain = build("angles = [90]\ntrials_per_angle = 1\neffects = [{ kind = \"skin\", sigma_mm = 0.5 }]");
    let sleeve = build(
        "angles = [90]\ntrials_per_angle = 1\neffects = [{ kind = \"sleeve\", thickness_mm = 1.0, pressure_coupling = 0.0, threshold_sd = 0.0 }]",
    );
    let (a, b) = (produce(plain.as_ref(), 0), produce(sleeve.as_ref(), 0));
    // Half-contact time of taxel 3 (row 0, col 3), in samples, from the end of
    // the hold; the two scenes plan different margins, so compare to the plan.
    let half = |s: &Signals| s.data[3].iter().position(|&v| v < 0.5).unwrap();
    let (ka, kb) = (half(&a), half(&b));
    assert!(kb > ka, "shear must delay the crossing: {ka} vs {kb}");
}

#[test]
fn conditions_simulate_each_scene_variant_with_labels_and_prefixed_ids() {
    let src = build(
        "angles = [45]\ntrials_per_angle = 2\n\
         effects = [{ kind = \"mismatch\", gain_sd = 0.2, offset_sd = 0.0 }]\n\
         [conditions.base]\n\
         [conditions.fast]\nmotion = { speed_mm_s = 4.0 }\n\
         [conditions.hard]\nmotion = { force_rel = 1.3 }\n\
         [conditions.other]\narray_copy = 1\n",
    );
    let metas = src.trials().unwrap();
    let ids: Vec<&str> = metas.iter().map(|m| m.trial_id.as_str()).collect();
    assert_eq!(
        ids,
        [
            "base-edge-45deg-r00",
            "base-edge-45deg-r01",
            "fast-edge-45deg-r00",
            "fast-edge-45deg-r01",
            "hard-edge-45deg-r00",
            "hard-edge-45deg-r01",
            "other-edge-45deg-r00",
            "other-edge-45deg-r01"
        ]
    );
    for m in &metas {
        assert_eq!(m.conditions["condition"], m.trial_id.split('-').next().unwrap());
    }
    // Same trial seed in each: only the condition's keys differ.
    let base = produce(src.as_ref(), 0);
    let fast = produce(src.as_ref(), 2);
    let hard = produce(src.as_ref(), 4);
    let other = produce(src.as_ref(), 6);
    // Twice the speed: the slide takes about half as long (holds unchanged).
    assert!(
        fast.n_samples() < base.n_samples() * 3 / 4,
        "{} vs {}",
        fast.n_samples(),
        base.n_samples()
    );
    // 30 % more force: 30 % more pressure in full contact (the ideal response
    // scaled, before the mismatch gain of the same array).
    let full = |s: &Signals| s.data.iter().map(|t| t[0]).fold(0.0, f64::max);
    assert!(
        (full(&hard) / full(&base) - 1.3).abs() < 1e-9,
        "{}",
        full(&hard) / full(&base)
    );
    // A second array: another gain draw, so the same pressure reads differently.
    assert_eq!(other.n_samples(), base.n_samples());
    assert_ne!(other.data, base.data);
}

#[test]
fn bad_conditions_are_named_errors() {
    let err = build_error;
    let e = err("[conditions.\"a/b\"]\n");
    assert!(e.message.contains("letters, digits"), "{e}");
    let e = err("[conditions.fast]\nmotion = { speed_mm_s = -1.0 }\n");
    assert_eq!(e.key.as_deref(), Some("conditions.fast.motion.speed_mm_s"), "{e}");
    let e = err("[conditions.x]\nconditions = { y = {} }\n");
    assert_eq!(e.key.as_deref(), Some("conditions.x.conditions"), "{e}");
    let e = err("conditions = {}\n");
    assert_eq!(e.key.as_deref(), Some("conditions"), "{e}");
}

#[test]
fn adjust_changes_one_key_of_an_inherited_effect() {
    // A condition that thickens the skin: the same list, one key changed.
    let src = build(
        "angles = [45]\ntrials_per_angle = 1\n\
         effects = [{ kind = \"skin\", sigma_mm = 0.5 }, { kind = \"mismatch\", gain_sd = 0.1, offset_sd = 0.0 }]\n\
         [conditions.thin]\n\
         [conditions.thick]\nadjust = { skin = { sigma_mm = 1.5 } }\n\
         [conditions.same]\nadjust = { skin = { sigma_mm = 0.5 } }\n",
    );
    // Conditions in name order: same, thick, thin.
    let same = produce(src.as_ref(), 0);
    let thick = produce(src.as_ref(), 1);
    let thin = produce(src.as_ref(), 2);
    // Adjusting a key to its own value changes nothing (the mismatch, listed
    // after the skin, is kept, with the same draw).
    assert!(
        same.data == thin.data,
        "adjusting sigma_mm to its own value changed the signals"
    );
    // A thicker skin spreads the pressure: the transition of a taxel takes
    // longer (10-90 % of its fall), and the mismatch is still applied.
    let rise = |s: &Signals| {
        let t = &s.data[5];
        let (hi, lo) = (t[0], *t.last().unwrap());
        let at = |f: f64| t.iter().position(|&v| v < lo + f * (hi - lo)).unwrap();
        at(0.1) - at(0.9)
    };
    assert!(
        rise(&thick) > rise(&thin) + 100,
        "{} vs {}",
        rise(&thick),
        rise(&thin)
    );
}

#[test]
fn bad_adjust_names_the_kind() {
    let err = build_error;
    let skin = "effects = [{ kind = \"skin\", sigma_mm = 0.5 }]\n";
    let e = err(&format!("{skin}adjust = {{ creep = {{ fraction = 0.2 }} }}\n"));
    assert_eq!(e.key.as_deref(), Some("adjust.creep"), "{e}");
    assert!(e.message.contains("no `creep` effect"), "{e}");
    let e = err(&format!("{skin}adjust = {{ skin = {{ thickness = 1.0 }} }}\n"));
    assert_eq!(e.key.as_deref(), Some("adjust.skin"), "{e}");
    let e = err(
        "effects = [{ kind = \"skin\", sigma_mm = 0.5 }, { kind = \"skin\", sigma_mm = 0.2 }]\nadjust = { skin = { sigma_mm = 1.0 } }\n",
    );
    assert!(e.message.contains("2 `skin` effects"), "{e}");
    let e = err(&format!(
        "{skin}[conditions.a]\nadjust = {{ skin = {{ kind = \"creep\" }} }}\n"
    ));
    assert_eq!(e.key.as_deref(), Some("conditions.a.adjust.skin"), "{e}");
}

#[test]
fn non_finite_keys_over_a_scene_file_are_refused_not_dropped() {
    // The keys over a scene file were merged through JSON, where NaN and
    // infinity become `null`, read back as "not set": the file's value ran.
    let dir = std::env::temp_dir().join(format!("palpate-scene-nan-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("base.toml");
    std::fs::write(
        &file,
        "angles = [30, 60]\ntrials_per_angle = 1\neffects = [{ kind = \"skin\", sigma_mm = 0.5 }]\n\
         [motion]\nspeed_mm_s = 2.0\n",
    )
    .unwrap();
    let f = file.display().to_string().replace('\\', "/");
    let with = |over: &str| format!("file = \"{f}\"\n{over}\n");
    for (over, key) in [
        ("[motion]\nspeed_mm_s = nan", "motion.speed_mm_s"),
        ("[motion]\nspeed_mm_s = -inf", "motion.speed_mm_s"),
        ("[motion]\nhold_before_s = inf", "motion.hold_before_s"),
        ("angles = [nan]", "angles"),
        ("angles = [30, nan]", "angles"),
        ("adjust = { skin = { sigma_mm = nan } }", "effects[0].sigma_mm"),
    ] {
        let e = build_error(&with(over));
        assert_eq!(e.key.as_deref(), Some(key), "{over}: {e}");
        assert!(
            e.message.contains("NaN") || e.message.contains("inf"),
            "{over}: {e}"
        );
    }
    // Finite keys over the file still win over it.
    let cfg: SceneConfig = toml::from_str(&with("[motion]\nspeed_mm_s = 3.0")).unwrap();
    let scene = cfg.resolve(&ctx()).unwrap();
    assert_eq!(scene.motion.speed_mm_s, 3.0);
    assert_eq!(scene.angles, vec![30.0, 60.0]);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn an_inline_layout_over_a_scene_files_grid_is_no_warning() {
    let dir = std::env::temp_dir().join(format!("palpate-scene-grid-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("base.toml");
    std::fs::write(
        &file,
        "angles = [45]\ntrials_per_angle = 1\n[array]\nrows = 8\ncols = 8\n",
    )
    .unwrap();
    let f = file.display().to_string().replace('\\', "/");
    let warnings = |inline: &str| {
        let cfg: SceneConfig = toml::from_str(&format!("file = \"{f}\"\n{inline}\n")).unwrap();
        let (scenes, w) = cfg.resolve_conditions(&ctx()).unwrap();
        (scenes[0].2.layout.len(), w.len())
    };
    // The file's 8 x 8 grid, replaced by the inline layout: no warning.
    assert_eq!(
        warnings("layout = { positions_mm = [[0.0, 0.0], [3.0, 0.0]] }"),
        (2, 0)
    );
    assert_eq!(warnings(""), (64, 0));
    std::fs::remove_dir_all(&dir).ok();
}

/// Recordings an earlier run left in the folder are named (a few, and the
/// count); the files this run wrote and other files are not.
#[test]
fn stale_recordings_in_the_output_folder_are_named() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path();
    let mut written = Vec::new();
    for name in ["a.npy", "b.npy", "labels.toml"] {
        std::fs::write(out.join(name), b"x").unwrap();
        written.push(out.join(name));
    }
    assert_eq!(super::stale_recordings(out, &written), None);
    for name in ["old1.npy", "old2.CSV", "old3.npy", "old4.npy", "notes.txt"] {
        std::fs::write(out.join(name), b"x").unwrap();
    }
    let w = super::stale_recordings(out, &written).unwrap();
    assert!(
        w.contains("holds 4 recordings")
            && w.contains("old1.npy, old2.CSV, old3.npy, ...")
            && !w.contains("notes"),
        "{w}"
    );
}
