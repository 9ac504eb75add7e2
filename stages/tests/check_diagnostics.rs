//! What `palpate check` reports: every wrong key of a stage, physical ranges
//! checked against the sample rate the source states, warnings that do not
//! stop a run, and the deprecated spellings of ranges.

use palpate_core::{load_str, Diagnostic, LoadOptions, Severity};

fn load(toml: &str) -> Result<palpate_core::Graph, Vec<Diagnostic>> {
    palpate_stages::link();
    let opts = LoadOptions {
        base_dir: Some(concat!(env!("CARGO_MANIFEST_DIR"), "/../graphs").into()),
        ..LoadOptions::default()
    };
    load_str(toml, "test.toml", "test", &opts).map_err(|e| e.0)
}

fn graph(scene: &str, lowpass: &str, bin: &str) -> String {
    format!(
        r#"
[stages.scene]
type = "scene"
trials_per_angle = 1
{scene}

[stages.filter]
type = "lowpass"
inputs = ["scene"]
{lowpass}

[stages.norm]
type = "normalize"
inputs = ["filter"]

[stages.drive]
type = "drive"
inputs = ["norm"]

[stages.enc]
type = "izhikevich"
inputs = ["drive"]

[stages.bins]
type = "bin"
inputs = ["enc"]
{bin}

[stages.out]
type = "write_images"
inputs = ["bins"]
"#
    )
}

fn errors(d: &[Diagnostic]) -> Vec<&Diagnostic> {
    d.iter().filter(|d| d.severity == Severity::Error).collect()
}

#[test]
fn two_bad_keys_of_one_stage_give_two_diagnostics_at_their_lines() {
    let text = graph("angles = [45]", "order = 0\ncutoff_hz = -1.0", "");
    let d = load(&text).unwrap_err();
    let e = errors(&d);
    assert_eq!(e.len(), 2, "{d:#?}");
    let keys: Vec<&str> = e.iter().filter_map(|d| d.key.as_deref()).collect();
    assert_eq!(keys, ["order", "cutoff_hz"]);
    for d in &e {
        assert_eq!(d.stage.as_deref(), Some("filter"));
        let key = d.key.as_deref().unwrap_or("");
        let line = text.lines().position(|l| l.starts_with(key)).map(|i| i + 1);
        assert_eq!(d.line, line, "{d}");
        assert!(
            d.to_string().starts_with(&format!(
                "test.toml:{}: error: stage `filter`: key `{key}`",
                line.unwrap_or(0)
            )),
            "{d}"
        );
    }
}

#[test]
fn every_wrong_scene_key_is_reported_not_only_the_first() {
    let text = graph(
        "angles = [45]\nmotion = { speed_mm_s = -2.0, hold_before_s = -1.0 }\nridge = { width_mm = 0.0 }",
        "cutoff_hz = 10.0",
        "",
    );
    let d = load(&text).unwrap_err();
    let keys: Vec<&str> = errors(&d).iter().filter_map(|d| d.key.as_deref()).collect();
    // In file order: `motion` is written before `ridge`.
    assert_eq!(
        keys,
        ["motion.speed_mm_s", "motion.hold_before_s", "ridge.width_mm"],
        "{d:#?}"
    );
}

#[test]
fn a_cutoff_at_or_above_nyquist_is_refused_at_check_time() {
    // The scene samples at 1000 Hz: Nyquist is 500 Hz.
    for cutoff in ["500.0", "600.0"] {
        let text = graph("angles = [45]", &format!("cutoff_hz = {cutoff}"), "");
        let d = load(&text).unwrap_err();
        let e = errors(&d);
        assert_eq!(e.len(), 1, "{d:#?}");
        assert_eq!(e[0].key.as_deref(), Some("cutoff_hz"));
        assert!(e[0].message.contains("Nyquist frequency 500 Hz"), "{}", e[0]);
    }
    // Beside another error of the stage's own build: both are reported.
    let d = load(&graph("angles = [45]", "order = 0\ncutoff_hz = 600.0", "")).unwrap_err();
    let keys: Vec<&str> = errors(&d).iter().filter_map(|d| d.key.as_deref()).collect();
    assert_eq!(keys, ["order", "cutoff_hz"], "{d:#?}");
    // Below it, or with another scene rate, the graph loads.
    assert!(load(&graph("angles = [45]", "cutoff_hz = 499.0", "")).is_ok());
    let text = graph(
        "angles = [45]\nmotion = { sample_rate_hz = 100.0 }",
        "cutoff_hz = 60.0",
        "",
    );
    let d = load(&text).unwrap_err();
    assert!(
        errors(&d)[0].message.contains("Nyquist frequency 50 Hz"),
        "{d:#?}"
    );
}

#[test]
fn a_bin_window_shorter_than_its_hop_is_a_warning() {
    let g = load(&graph(
        "angles = [45]",
        "cutoff_hz = 10.0",
        "window_ms = 5.0\nhop_ms = 10.0",
    ))
    .unwrap();
    let w: Vec<&Diagnostic> = g
        .warnings
        .iter()
        .filter(|w| w.key.as_deref() == Some("window_ms"))
        .collect();
    assert_eq!(w.len(), 1, "{:#?}", g.warnings);
    assert_eq!(w[0].severity, Severity::Warning);
    assert!(w[0].message.contains("shorter than hop_ms"), "{}", w[0]);
    let g = load(&graph("angles = [45]", "cutoff_hz = 10.0", "")).unwrap();
    assert!(g.warnings.iter().all(|w| w.key.as_deref() != Some("window_ms")));
}

#[test]
fn old_range_names_give_the_same_graph_with_a_deprecation_warning() {
    let new = load(&graph(
        "angles = { from = 10, to = 30, step = 10 }",
        "cutoff_hz = 10.0",
        "",
    ))
    .unwrap();
    let old = load(&graph(
        "angles = { start = 10, stop = 30, step = 10 }",
        "cutoff_hz = 10.0",
        "",
    ))
    .unwrap();
    let trials = |g: &palpate_core::Graph| -> Vec<String> {
        match &g.nodes[0].stage {
            palpate_core::Stage::Source(s) => s.trials().unwrap().into_iter().map(|m| m.trial_id).collect(),
            _ => panic!("the scene is a source"),
        }
    };
    assert_eq!(
        trials(&new),
        ["edge-10deg-r00", "edge-20deg-r00", "edge-30deg-r00"]
    );
    assert_eq!(trials(&new), trials(&old));
    let deprecations = |g: &palpate_core::Graph| -> Vec<String> {
        g.warnings
            .iter()
            .filter(|w| w.message.contains("deprecated"))
            .filter_map(|w| w.key.clone())
            .collect()
    };
    assert!(deprecations(&new).is_empty(), "{:#?}", new.warnings);
    assert_eq!(deprecations(&old), ["angles.start", "angles.stop"]);
    // Both spellings of one bound is an error.
    let d = load(&graph(
        "angles = { from = 10, start = 10, to = 30 }",
        "cutoff_hz = 10.0",
        "",
    ))
    .unwrap_err();
    assert_eq!(errors(&d)[0].key.as_deref(), Some("angles.start"), "{d:#?}");
}

/// A WSS key set to a value of its own that the other keys leave unused is
/// a warning naming the key and what it needs; the same key where it acts,
/// or left at its default, is not.
#[test]
fn wss_keys_that_the_other_keys_make_unused_are_warnings() {
    let with_wss = |keys: &str| {
        format!(
            "{}\n[stages.wss]\ntype = \"wss\"\ninputs = [\"bins\"]\n{keys}\n",
            graph("angles = [45]", "cutoff_hz = 10.0", "")
        )
    };
    let warned = |keys: &str| -> Vec<String> {
        let g = load(&with_wss(keys)).unwrap_or_else(|d| panic!("{d:#?}"));
        g.warnings
            .iter()
            .filter(|w| w.stage.as_deref() == Some("wss") && w.key.is_some())
            .map(|w| format!("{}: {}", w.key.as_deref().unwrap_or(""), w.message))
            .collect()
    };
    let w = warned("speed_steps = 9\nrefine_tol_deg = 0.1\ntiming_window_ms = 500.0");
    assert_eq!(w.len(), 3, "{w:#?}");
    assert!(
        w[0].starts_with("speed_steps:") && w[0].contains("speed_tolerance"),
        "{w:#?}"
    );
    assert!(
        w[1].starts_with("refine_tol_deg:") && w[1].contains("search"),
        "{w:#?}"
    );
    assert!(
        w[2].starts_with("timing_window_ms:") && w[2].contains("timing"),
        "{w:#?}"
    );
    assert!(warned("speed_steps = 9\nspeed_tolerance = 0.2").is_empty());
    assert!(warned("refine = \"search\"\nrefine_tol_deg = 0.1").is_empty());
    assert!(warned("refine = \"timing\"\ntiming_window_ms = 500.0").is_empty());
    assert!(warned("").is_empty());
}

#[test]
fn a_grid_beside_an_explicit_layout_is_a_warning_naming_array() {
    let layout = "layout = { positions_mm = [[0.0, 0.0], [3.0, 0.0]] }";
    let keys = |g: &palpate_core::Graph| -> Vec<String> {
        g.warnings
            .iter()
            .filter(|w| w.message.contains("`layout` is given"))
            .map(|w| w.key.clone().unwrap_or_default())
            .collect()
    };
    let both = format!("angles = [45]\narray = {{ rows = 8 }}\n{layout}");
    let g = load(&graph(&both, "cutoff_hz = 10.0", "")).unwrap();
    assert_eq!(keys(&g), ["array"], "{:#?}", g.warnings);
    assert!(g.warnings.iter().all(|w| w.severity == Severity::Warning));
    // Either alone: no warning.
    for one in [
        "angles = [45]\narray = { rows = 8 }".to_string(),
        format!("angles = [45]\n{layout}"),
    ] {
        let g = load(&graph(&one, "cutoff_hz = 10.0", "")).unwrap();
        assert!(keys(&g).is_empty(), "{one}: {:#?}", g.warnings);
    }
    // A condition's layout replaces the scene's grid (as an inline layout
    // replaces a scene file's `[array]`): nothing the user could leave out,
    // so no warning.
    let cond = format!("angles = [45]\narray = {{ rows = 8 }}\n[stages.scene.conditions.b]\n{layout}\n[stages.scene.conditions.a]");
    let g = load(&graph(&cond, "cutoff_hz = 10.0", "")).unwrap();
    assert!(keys(&g).is_empty(), "{:#?}", g.warnings);
    // A condition's grid under the scene's layout changes nothing: named under it.
    let cond = format!("angles = [45]\n{layout}\n[stages.scene.conditions.b]\narray = {{ rows = 8 }}\n[stages.scene.conditions.a]");
    let g = load(&graph(&cond, "cutoff_hz = 10.0", "")).unwrap();
    assert_eq!(keys(&g), ["conditions.b.array"], "{:#?}", g.warnings);
}

/// A stage called `run`, `timing` or `live_timing` (any case) is refused at
/// check, naming the stage: a sink's reports are named after its id, and the
/// run's own `run.json` and `timing.*` would overwrite them without a word.
#[test]
fn ids_the_run_writes_files_under_are_refused() {
    for id in ["run", "timing", "Timing", "live_timing"] {
        let text =
            graph("angles = [45]", "cutoff_hz = 10.0", "").replace("[stages.out]", &format!("[stages.{id}]"));
        let d = load(&text).unwrap_err();
        let e = errors(&d);
        assert!(
            e.iter()
                .any(|d| d.stage.as_deref() == Some(id) && d.message.contains("reserved")),
            "{id}: {d:#?}"
        );
    }
    // Ids that merely contain one are fine.
    let text = graph("angles = [45]", "cutoff_hz = 10.0", "").replace("[stages.out]", "[stages.timing_sink]");
    assert!(load(&text).is_ok());
}

/// Values of the wrong form say what was wrong in the user's terms: an
/// angle list with a string in it names the element (serde said only "data
/// did not match any variant of untagged enum Angles"), a whole number past
/// TOML's range says so (it said "invalid type: string ..., expected
/// usize"), and a `--set` array that does not parse is refused as such.
#[test]
fn wrong_forms_are_named_in_the_users_terms() {
    for (scene, key) in [
        ("angles = [30, \"60\", 90]", "angles"),
        (
            "angles = [30, 60]\n[stages.wss]\ntype = \"wss\"\ninputs = [\"bins\"]\nangles = [30, \"60\"]",
            "angles",
        ),
    ] {
        let d = load(&graph(scene, "cutoff_hz = 10.0", "")).unwrap_err();
        let e = errors(&d);
        assert!(
            e.iter().any(|d| d.key.as_deref() == Some(key)
                && d.message.contains("element [1] is \"60\", a string")
                && d.message.contains("{ from = 10, to = 90, step = 5 }")),
            "{scene}: {d:#?}"
        );
    }
    let d = load(&graph(
        "angles = { from = 10, to = \"90\" }",
        "cutoff_hz = 10.0",
        "",
    ))
    .unwrap_err();
    assert!(
        errors(&d)
            .iter()
            .any(|d| d.message.contains("`to` is \"90\", a string")),
        "{d:#?}"
    );

    palpate_stages::link();
    let opts = LoadOptions {
        base_dir: Some(concat!(env!("CARGO_MANIFEST_DIR"), "/../graphs").into()),
        overrides: vec![
            LoadOptions::parse_set("stages.scene.trials_per_angle=99999999999999999999").unwrap(),
        ],
        ..LoadOptions::default()
    };
    let d = load_str(
        &graph("angles = [45]", "cutoff_hz = 10.0", ""),
        "test.toml",
        "test",
        &opts,
    )
    .unwrap_err()
    .0;
    assert!(
        errors(&d)
            .iter()
            .any(|d| d.key.as_deref() == Some("trials_per_angle")
                && d.message.contains("99999999999999999999 is out of range")
                && d.message.contains("a whole number from 0")),
        "{d:#?}"
    );

    let e = LoadOptions::parse_set("sweep.values=[9223372036854775808]").unwrap_err();
    assert!(
        e.contains("is not a TOML value") && e.contains("sweep.values"),
        "{e}"
    );
    // A bare word is still a string, and a quoted one too.
    let (_, v) = LoadOptions::parse_set("stages.s.mode=trial").unwrap();
    assert_eq!(v.as_str(), Some("trial"));
    let (_, v) = LoadOptions::parse_set("run.seed=\"18446744073709551615\"").unwrap();
    assert_eq!(v.as_str(), Some("18446744073709551615"));
}
